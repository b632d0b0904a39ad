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
