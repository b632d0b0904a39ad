//! Files that say when they are damaged: a 24-byte header (`RADSTOR1`, the payload's length as
//! u64, its CRC-32 as u32, 4 zero bytes) before the payload, checked when read. The service's
//! data directory and the bake's partial files ([`crate::batch::shard`]) are written so; files
//! whose encoding does not describe itself also carry the [`build`] that wrote them.

use std::io::Read;
use std::path::Path;

/// First bytes of a checked file.
pub const CHECKED: &[u8; 8] = b"RADSTOR1";
/// Bytes of a checked file's header.
pub const HEADER: usize = 24;

/// A file that cannot be used: `name` is damaged as `what` says (an error of kind
/// `InvalidData`).
pub fn damaged(name: &str, what: impl std::fmt::Display) -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::InvalidData,
        format!("{name} is damaged: {what}"),
    )
}

/// `payload` with the header of a checked file before it.
pub fn checked(payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER + payload.len());
    out.resize(HEADER, 0);
    out.extend_from_slice(payload);
    sealed(out)
}

/// `out`, a checked file's header's bytes (any) then its payload, with the header written.
pub fn sealed(mut out: Vec<u8>) -> Vec<u8> {
    let payload = &out[HEADER..];
    let (length, crc) = (payload.len() as u64, crc32fast::hash(payload));
    out[..8].copy_from_slice(CHECKED);
    out[8..16].copy_from_slice(&length.to_le_bytes());
    out[16..20].copy_from_slice(&crc.to_le_bytes());
    out[20..24].fill(0);
    out
}

/// The running build's identity: the CRC-32 and length of its executable (`None` if it cannot
/// be read: no traced state is then kept on disk). Read once.
pub fn build() -> Option<[u8; 12]> {
    static BUILD: std::sync::OnceLock<Option<[u8; 12]>> = std::sync::OnceLock::new();
    *BUILD.get_or_init(|| {
        // The running executable, even if a newer one was installed over it since.
        let path = Path::new("/proc/self/exe");
        let path = if path.exists() {
            path.to_path_buf()
        } else {
            std::env::current_exe().ok()?
        };
        let mut file = std::fs::File::open(path).ok()?;
        let (mut hasher, mut length) = (crc32fast::Hasher::new(), 0u64);
        let mut buffer = vec![0; 1 << 20];
        loop {
            match file.read(&mut buffer) {
                Ok(0) => break,
                Ok(n) => {
                    hasher.update(&buffer[..n]);
                    length += n as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(_) => return None,
            }
        }
        let mut id = [0; 12];
        id[..4].copy_from_slice(&hasher.finalize().to_le_bytes());
        id[4..].copy_from_slice(&length.to_le_bytes());
        Some(id)
    })
}

/// The payload of checked file `name` (its bytes as they are if it has no header: a file of the
/// service's data directory written before they were checked).
///
/// # Errors
/// The length or the checksum does not match.
pub fn payload<'a>(name: &str, bytes: &'a [u8]) -> std::io::Result<&'a [u8]> {
    let Some(header) = bytes.strip_prefix(CHECKED) else {
        return Ok(bytes);
    };
    let (Some(length), Some(crc), Some([0, 0, 0, 0])) =
        (header.get(..8), header.get(8..12), header.get(12..16))
    else {
        return Err(damaged(name, "its header is cut short or damaged"));
    };
    let length = u64::from_le_bytes(length.try_into().unwrap_or_default());
    let crc = u32::from_le_bytes(crc.try_into().unwrap_or_default());
    let payload = &bytes[HEADER.min(bytes.len())..];
    if payload.len() as u64 != length {
        return Err(damaged(
            name,
            format!("it holds {} bytes of {length}", payload.len()),
        ));
    }
    if crc32fast::hash(payload) != crc {
        return Err(damaged(name, "its checksum does not match its contents"));
    }
    Ok(payload)
}

/// Bytes of a stamp: the kind of file (8 bytes) and the [`build`] that wrote it.
pub const STAMP: usize = 8 + 12;

/// The start of a checked file of kind `kind` whose encoding does not describe itself: the
/// header's room, then `kind` and this build. The caller writes the rest after it, then
/// [`sealed`]. `None` if this build cannot tell itself from others.
#[must_use]
pub fn stamped(kind: &[u8; 8]) -> Option<Vec<u8>> {
    let mut out = vec![0; HEADER];
    out.extend_from_slice(kind);
    out.extend_from_slice(&build()?);
    Some(out)
}

/// What the payload of a [`stamped`] file holds.
pub enum Stamp<'a> {
    /// This build wrote it: what follows the stamp.
    Ours(&'a [u8]),
    /// Another build wrote it, which this one cannot read.
    OtherBuild,
}

/// The payload after the stamp of checked file `name` of kind `kind` ([`stamped`]), `what` naming
/// the kind in errors ("a traced state").
///
/// # Errors
/// It is not such a file, or it is damaged.
pub fn unstamped<'a>(
    name: &str,
    bytes: &'a [u8],
    (kind, what): (&[u8; 8], &str),
) -> std::io::Result<Stamp<'a>> {
    let not = || damaged(name, format!("it is not {what}"));
    if !bytes.starts_with(CHECKED) {
        return Err(not());
    }
    let payload = payload(name, bytes)?;
    if payload.get(..8) != Some(&kind[..]) {
        return Err(not());
    }
    let Some(rest) = payload.get(STAMP..) else {
        return Err(damaged(name, "it is cut short"));
    };
    Ok(match build() {
        Some(b) if payload[8..STAMP] == b => Stamp::Ours(rest),
        _ => Stamp::OtherBuild,
    })
}

/// Writes `bytes` to `path` so that a crash or a full disk leaves either the file before or
/// the new one: a temporary file, flushed to the disk, renamed over it, the directory flushed
/// (the temporary file removed if anything fails). Two writers of one path at once share its
/// temporary file: callers keep them apart.
///
/// # Errors
/// What writing, flushing or renaming met.
pub fn write_whole(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let tmp = path.with_extension("tmp");
    let written = std::fs::File::create(&tmp)
        .and_then(|mut file| {
            file.write_all(bytes)?;
            file.sync_all()
        })
        .and_then(|()| std::fs::rename(&tmp, path));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written?;
    // The rename itself reaches the disk with the directory.
    if let Some(dir) = path.parent() {
        std::fs::File::open(dir)?.sync_all()?;
    }
    Ok(())
}
