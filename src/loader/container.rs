//! The file container: GLB chunks or JSON, and the buffers' bytes.
//!
//! The loader never reads the filesystem or the network on behalf of a scene: buffers and images
//! come from the GLB binary chunk, from a buffer view, or from a `data:` URI; any other URI is
//! refused.

use base64::Engine as _;
use gltf::Document;

use super::LoadError;

/// A parsed file: the validated document and the bytes of each of its buffers.
pub struct Container {
    /// The glTF document, validated by the `gltf` crate (indices between objects are in range).
    pub document: Document,
    /// Bytes of each buffer, exactly `byteLength` long.
    pub buffers: Vec<Vec<u8>>,
    /// What was read past: animation channels without a target node.
    pub warnings: Vec<String>,
}

const GLB_MAGIC: &[u8; 4] = b"glTF";
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;

/// What a file that is neither GLB nor JSON looks like, if it is not: `None` when it starts
/// (after a byte-order mark and white space) with `{`, as a `.gltf` does.
fn not_gltf(bytes: &[u8]) -> Option<String> {
    let text = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let start = text.iter().position(|b| !b.is_ascii_whitespace());
    let Some(start) = start else {
        return Some("it is empty".into());
    };
    let text = &text[start..];
    if text.starts_with(b"{") {
        return None;
    }
    let known: [(&[u8], &str); 9] = [
        (b"\x89PNG", "a PNG image"),
        (b"\xFF\xD8\xFF", "a JPEG image"),
        (b"PK\x03\x04", "a zip archive"),
        (b"\x1F\x8B", "a gzip file"),
        (b"Kaydara FBX Binary", "a binary FBX file"),
        (b"BLENDER", "a Blender .blend file"),
        (b"ply", "a PLY file"),
        (b"solid", "an ASCII STL file"),
        (b"<?xml", "an XML file (COLLADA .dae?)"),
    ];
    if let Some((_, what)) = known.iter().find(|(magic, _)| text.starts_with(magic)) {
        return Some(format!("it looks like {what}"));
    }
    let obj = text.split(|&b| b == b'\n').take(64).any(|line| {
        ["v ", "vn ", "vt ", "f ", "o ", "mtllib "]
            .iter()
            .any(|k| line.starts_with(k.as_bytes()))
    });
    if obj {
        return Some("it looks like a Wavefront OBJ file".into());
    }
    let head: String = text
        .iter()
        .take(16)
        .flat_map(|&b| std::ascii::escape_default(b))
        .map(char::from)
        .collect();
    Some(format!("it starts with \"{head}\""))
}

/// Parses a `.glb` or `.gltf` file from memory.
pub fn parse(bytes: &[u8]) -> Result<Container, LoadError> {
    let (json, blob) = if bytes.starts_with(GLB_MAGIC) {
        split_glb(bytes)?
    } else {
        (bytes, None)
    };
    if blob.is_none()
        && let Some(what) = not_gltf(json)
    {
        return Err(LoadError::Container(format!(
            "not a glTF file (a .gltf is JSON, a .glb starts with \"glTF\"): {what}"
        )));
    }
    let (json, warnings) = without_untargeted_channels(json)?;
    let mut root = gltf::json::Root::from_slice(&json)
        .map_err(|e| LoadError::Container(format!("invalid JSON: {e}")))?;
    // What KHR_mesh_quantization allows (positions, normals and morph deltas as 8- and 16-bit
    // integers, normalised or not, elements padded to 4 bytes) the accessors are read as
    // anyway (`accessor::read`: every component type, any stride); the `gltf` crate refuses
    // the extension as required only because it does not know it.
    root.extensions_required
        .retain(|e| e != "KHR_mesh_quantization");
    let compressed = super::meshopt::Plan::read(&mut root)?;
    precheck(&root)?;
    let document = Document::from_json(root).map_err(describe_gltf_error)?;
    let mut buffers = Vec::with_capacity(document.buffers().len());
    for buffer in document.buffers() {
        let what = || format!("buffer {}", buffer.index());
        // A fallback buffer holds only views decoded below.
        // (allocated by `decode`, once the compressed bytes it holds are known to be present).
        if compressed.is_fallback(buffer.index()) {
            buffers.push(Vec::new());
            continue;
        }
        let mut data = match buffer.source() {
            gltf::buffer::Source::Bin => blob.map(<[u8]>::to_vec).ok_or_else(|| {
                LoadError::malformed(
                    what(),
                    "refers to the GLB binary chunk, but the file has none",
                )
            })?,
            gltf::buffer::Source::Uri(uri) => decode_data_uri(uri, &what)?,
        };
        let length = buffer.length();
        if data.len() < length {
            return Err(LoadError::malformed(
                what(),
                format!(
                    "byteLength is {length} but only {} bytes are present",
                    data.len()
                ),
            ));
        }
        data.truncate(length);
        buffers.push(data);
    }
    let lengths: Vec<usize> = document.buffers().map(|b| b.length()).collect();
    compressed.decode(&mut buffers, &lengths)?;
    Ok(Container {
        document,
        buffers,
        warnings,
    })
}

/// The JSON without the animation channels that have no `target.node` (the specification
/// allows them, for extensions to target something else; they animate no node here), and a
/// warning naming them. The JSON as it is when there are none.
fn without_untargeted_channels(
    json: &[u8],
) -> Result<(std::borrow::Cow<'_, [u8]>, Vec<String>), LoadError> {
    let needle = b"\"channels\"";
    if !json.windows(needle.len()).any(|w| w == needle) {
        return Ok((json.into(), Vec::new()));
    }
    let mut value: serde_json::Value = serde_json::from_slice(json)
        .map_err(|e| LoadError::Container(format!("invalid JSON: {e}")))?;
    let mut dropped = Vec::new();
    if let Some(animations) = value
        .get_mut("animations")
        .and_then(serde_json::Value::as_array_mut)
    {
        for (a, animation) in animations.iter_mut().enumerate() {
            let Some(channels) = animation
                .get_mut("channels")
                .and_then(serde_json::Value::as_array_mut)
            else {
                continue;
            };
            let mut c = 0;
            channels.retain(|channel| {
                let keep = channel
                    .get("target")
                    .is_none_or(|t| t.get("node").is_some());
                if !keep {
                    dropped.push(format!("animations[{a}].channels[{c}]"));
                }
                c += 1;
                keep
            });
        }
    }
    if dropped.is_empty() {
        return Ok((json.into(), Vec::new()));
    }
    let warning = format!(
        "{} ignored: {} no target node",
        dropped.join(", "),
        if dropped.len() == 1 {
            "it has"
        } else {
            "they have"
        }
    );
    let json = serde_json::to_vec(&value)
        .map_err(|e| LoadError::Container(format!("invalid JSON: {e}")))?;
    Ok((json.into(), vec![warning]))
}

/// Checks what the `gltf` crate's validation (gltf-json 1.4.1) gets wrong: it indexes the
/// accessor of each POSITION attribute before checking that it exists, and it never validates
/// animation channel targets, whose getters then unwrap. Both would panic on a hostile file.
fn precheck(root: &gltf::json::Root) -> Result<(), LoadError> {
    use gltf::json::validation::Checked;
    let position = Checked::Valid(gltf::json::mesh::Semantic::Positions);
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            if let Some(index) = primitive.attributes.get(&position)
                && index.value() >= root.accessors.len()
            {
                return Err(LoadError::Validation(format!(
                    "meshes[{m}].primitives[{p}].attributes[\"POSITION\"]: index {} out of \
                         range ({} accessors)",
                    index.value(),
                    root.accessors.len()
                )));
            }
        }
    }
    for (a, animation) in root.animations.iter().enumerate() {
        for (c, channel) in animation.channels.iter().enumerate() {
            let path = format!("animations[{a}].channels[{c}].target");
            if channel.target.node.value() >= root.nodes.len() {
                return Err(LoadError::Validation(format!(
                    "{path}.node: index {} out of range ({} nodes)",
                    channel.target.node.value(),
                    root.nodes.len()
                )));
            }
            if !matches!(channel.target.path, Checked::Valid(_)) {
                return Err(LoadError::Validation(format!(
                    "{path}.path: not one of translation, rotation, scale, weights"
                )));
            }
        }
    }
    Ok(())
}

/// Splits a GLB file into its JSON chunk and optional binary chunk (glTF 2.0 §4.4), checking
/// every length against the data actually present.
///
/// Not the gltf crate's `Glb::from_slice` (which writes the baked files, `output::glb`): it
/// subtracts 12 from the header's declared length unchecked (a header declaring fewer than 12
/// bytes overflows: a panic where overflow is checked), reads chunks past the declared end, and
/// its messages name no chunk ("could not completely read the object").
fn split_glb(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), LoadError> {
    let bad = |reason: &str| LoadError::Container(format!("GLB: {reason}"));
    let word = |at: usize| -> Option<u32> {
        let b = bytes.get(at..at.checked_add(4)?)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    let version = word(4).ok_or_else(|| bad("truncated header"))?;
    if version != 2 {
        return Err(bad(&format!("version {version}, expected 2")));
    }
    let declared = word(8).ok_or_else(|| bad("truncated header"))? as usize;
    if declared > bytes.len() {
        return Err(bad(&format!(
            "header declares {declared} bytes but the file has {}",
            bytes.len()
        )));
    }
    let bytes = &bytes[..declared];
    let mut at = 12;
    let mut chunk = |expected: u32, name: &str| -> Result<Option<&[u8]>, LoadError> {
        if at >= bytes.len() {
            return Ok(None);
        }
        let length = word(at).ok_or_else(|| bad(&format!("truncated {name} chunk header")))?;
        let kind = word(at + 4).ok_or_else(|| bad(&format!("truncated {name} chunk header")))?;
        if kind != expected {
            return Err(bad(&format!(
                "expected the {name} chunk, found type {kind:#010x}"
            )));
        }
        let start = at + 8;
        let end = start
            .checked_add(length as usize)
            .filter(|&end| end <= bytes.len())
            .ok_or_else(|| bad(&format!("{name} chunk runs past the end of the file")))?;
        at = end;
        Ok(Some(&bytes[start..end]))
    };
    let json = chunk(CHUNK_JSON, "JSON")?.ok_or_else(|| bad("no JSON chunk"))?;
    let bin = chunk(CHUNK_BIN, "BIN")?;
    Ok((json, bin))
}

/// Decodes a `data:` URI; refuses any other URI.
pub fn decode_data_uri(uri: &str, what: &dyn Fn() -> String) -> Result<Vec<u8>, LoadError> {
    let Some(rest) = uri.strip_prefix("data:") else {
        return Err(LoadError::ExternalUri {
            object: what(),
            uri: uri.chars().take(120).collect(),
        });
    };
    let Some((media, payload)) = rest.split_once(',') else {
        return Err(LoadError::malformed(what(), "data: URI without a ','"));
    };
    if !media.ends_with(";base64") {
        return Err(LoadError::malformed(
            what(),
            "data: URI is not base64-encoded (';base64' is required)",
        ));
    }
    base64::engine::general_purpose::STANDARD
        .decode(payload.trim())
        .map_err(|e| LoadError::malformed(what(), format!("data: URI is not valid base64 ({e})")))
}

/// Turns the `gltf` crate's error into ours, naming the offending objects.
fn describe_gltf_error(error: gltf::Error) -> LoadError {
    match error {
        gltf::Error::Validation(errors) => {
            let mut lines: Vec<String> = errors
                .iter()
                .take(8)
                .map(|(path, e)| format!("{path}: {e}"))
                .collect();
            if errors.len() > 8 {
                lines.push(format!("and {} more", errors.len() - 8));
            }
            LoadError::Validation(lines.join("; "))
        }
        gltf::Error::Deserialize(e) => LoadError::Container(format!("invalid JSON: {e}")),
        other => LoadError::Container(other.to_string()),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_file_that_is_not_gltf_is_named_for_what_it_looks_like() {
        for (bytes, says) in [
            (
                &b"# Blender 4.2\nmtllib room.mtl\no Cube\nv 1 1 1\n"[..],
                "Wavefront OBJ",
            ),
            (b"\x89PNG\r\n\x1a\n", "PNG image"),
            (b"   \n", "empty"),
            (b"hello", "starts with \"hello\""),
        ] {
            let error = super::parse(bytes).err().expect("refused").to_string();
            assert!(
                error.contains("not a glTF file") && error.contains(says),
                "{error}"
            );
        }
        // JSON that is not glTF keeps the parser's own message.
        let error = super::parse(b"{\"a\": 1}")
            .err()
            .expect("refused")
            .to_string();
        assert!(!error.contains("not a glTF file"), "{error}");
    }

    use super::*;

    fn glb(json: &[u8], bin: Option<&[u8]>) -> Vec<u8> {
        let mut out = Vec::new();
        let pad = |v: &mut Vec<u8>, fill: u8| {
            while !v.len().is_multiple_of(4) {
                v.push(fill);
            }
        };
        let mut j = json.to_vec();
        pad(&mut j, b' ');
        out.extend_from_slice(GLB_MAGIC);
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes());
        out.extend_from_slice(&(j.len() as u32).to_le_bytes());
        out.extend_from_slice(&CHUNK_JSON.to_le_bytes());
        out.extend_from_slice(&j);
        if let Some(bin) = bin {
            let mut b = bin.to_vec();
            pad(&mut b, 0);
            out.extend_from_slice(&(b.len() as u32).to_le_bytes());
            out.extend_from_slice(&CHUNK_BIN.to_le_bytes());
            out.extend_from_slice(&b);
        }
        let len = out.len() as u32;
        out[8..12].copy_from_slice(&len.to_le_bytes());
        out
    }

    const MINIMAL: &str = r#"{"asset":{"version":"2.0"},"buffers":[{"byteLength":4}]}"#;

    #[test]
    fn glb_with_binary_chunk() {
        let file = glb(MINIMAL.as_bytes(), Some(&[1, 2, 3, 4]));
        let c = parse(&file).unwrap();
        assert_eq!(c.buffers, vec![vec![1, 2, 3, 4]]);
    }

    #[test]
    fn glb_lengths_are_checked() {
        let mut file = glb(MINIMAL.as_bytes(), Some(&[1, 2, 3, 4]));
        // A header shorter than itself, a chunk longer than the file, a truncated file.
        file[8..12].copy_from_slice(&3u32.to_le_bytes());
        assert!(parse(&file).is_err());
        let mut file = glb(MINIMAL.as_bytes(), Some(&[1, 2, 3, 4]));
        file[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(parse(&file).is_err());
        let file = glb(MINIMAL.as_bytes(), Some(&[1, 2, 3, 4]));
        assert!(parse(&file[..file.len() - 2]).is_err());
    }

    #[test]
    fn missing_binary_chunk_is_an_error() {
        let file = glb(MINIMAL.as_bytes(), None);
        let e = parse(&file).err().unwrap().to_string();
        assert!(e.contains("buffer 0"), "{e}");
    }

    #[test]
    fn external_uris_are_refused() {
        for uri in [
            "/etc/passwd",
            "file:///etc/passwd",
            "http://example.com/a.bin",
            "a.bin",
        ] {
            let json = format!(
                r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":4,"uri":"{uri}"}}]}}"#
            );
            match parse(json.as_bytes()) {
                Err(LoadError::ExternalUri { object, uri: u }) => {
                    assert_eq!(object, "buffer 0");
                    assert_eq!(u, uri);
                }
                Err(other) => panic!("{uri}: wrong error {other}"),
                Ok(_) => panic!("{uri}: accepted"),
            }
        }
    }

    #[test]
    fn data_uris_are_decoded_and_checked() {
        let ok = r#"{"asset":{"version":"2.0"},"buffers":[{"byteLength":3,"uri":"data:application/octet-stream;base64,AQIDBA=="}]}"#;
        assert_eq!(parse(ok.as_bytes()).unwrap().buffers, vec![vec![1, 2, 3]]);
        let short = r#"{"asset":{"version":"2.0"},"buffers":[{"byteLength":9,"uri":"data:application/octet-stream;base64,AQIDBA=="}]}"#;
        assert!(parse(short.as_bytes()).is_err());
        let not_b64 =
            r#"{"asset":{"version":"2.0"},"buffers":[{"byteLength":1,"uri":"data:,abc"}]}"#;
        assert!(parse(not_b64.as_bytes()).is_err());
    }
}
