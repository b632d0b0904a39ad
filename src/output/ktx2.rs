//! KTX 2.0 containers (Khronos, `KTX-Specification` 2.0): the lightmaps' texture for the web and
//! Bevy (issue 49), one level of `VK_FORMAT_R16G16B16A16_SFLOAT` texels, supercompressed with
//! Zstandard (scheme 2), rows from the top (the format's default orientation, `rd`).

/// `VK_FORMAT_R16G16B16A16_SFLOAT`.
const R16G16B16A16_SFLOAT: u32 = 97;

/// Supercompression scheme 2: Zstandard.
const ZSTANDARD: u32 = 2;

/// The Zstandard level: a lightmap compresses to about a third at 6, and a level of 19 took
/// many times as long for a few percent.
const LEVEL: i32 = 6;

/// The file's first 12 bytes.
const IDENTIFIER: [u8; 12] = [
    0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A,
];

/// A KTX2 file of `width × height` linear RGBA half-float texels (`rgba`, row 0 the top),
/// Zstandard-supercompressed, with a `KTXwriter` and a `KTXorientation` entry.
///
/// # Errors
/// The compressor's, as text; a size that does not match `rgba`.
pub fn rgba16f(width: u32, height: u32, rgba: &[[f32; 4]]) -> Result<Vec<u8>, String> {
    if rgba.len() != width as usize * height as usize || width == 0 || height == 0 {
        return Err(format!(
            "a {width} × {height} KTX2 texture of {} texels",
            rgba.len()
        ));
    }
    let mut raw = Vec::with_capacity(rgba.len() * 8);
    for texel in rgba {
        for c in texel {
            raw.extend_from_slice(&exr::prelude::f16::from_f32(*c).to_le_bytes());
        }
    }
    let level =
        zstd::bulk::compress(&raw, LEVEL).map_err(|e| format!("compressing the texture: {e}"))?;
    let dfd = descriptor();
    let kvd = key_values(&[
        ("KTXorientation", "rd"),
        (
            "KTXwriter",
            concat!("radiosity ", env!("CARGO_PKG_VERSION")),
        ),
    ]);
    // Header (80 bytes), one level's index (24), then the descriptor, the key/values and the
    // level, each after the one before (no alignment with supercompression but the
    // descriptor's and key/values' 4 bytes).
    let dfd_offset = 12 + 68 + 24;
    let kvd_offset = dfd_offset + dfd.len();
    let level_offset = kvd_offset + kvd.len();
    let mut out = Vec::with_capacity(level_offset + level.len());
    out.extend_from_slice(&IDENTIFIER);
    for value in [R16G16B16A16_SFLOAT, 2, width, height, 0, 0, 1, 1, ZSTANDARD] {
        out.extend_from_slice(&value.to_le_bytes());
    }
    for value in [dfd_offset, dfd.len(), kvd_offset, kvd.len()] {
        out.extend_from_slice(&(value as u32).to_le_bytes());
    }
    out.extend_from_slice(&0u64.to_le_bytes()); // no supercompression global data
    out.extend_from_slice(&0u64.to_le_bytes());
    for value in [level_offset, level.len(), raw.len()] {
        out.extend_from_slice(&(value as u64).to_le_bytes());
    }
    debug_assert_eq!(out.len(), dfd_offset);
    out.extend_from_slice(&dfd);
    out.extend_from_slice(&kvd);
    out.extend_from_slice(&level);
    Ok(out)
}

/// The data format descriptor of linear RGBA half floats: its total size, then one basic block
/// (Khronos Data Format 1.3, §5) of four 16-bit signed float samples.
fn descriptor() -> Vec<u8> {
    let samples = 4u16;
    let block = 24 + 16 * samples;
    let mut out = Vec::with_capacity(4 + usize::from(block));
    out.extend_from_slice(&(4 + u32::from(block)).to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes()); // vendor Khronos, basic descriptor type
    out.extend_from_slice(&2u16.to_le_bytes()); // version 1.3
    out.extend_from_slice(&block.to_le_bytes());
    // RGBSDA model, BT.709 primaries, linear transfer, straight alpha; texel block 1 × 1
    // (stored as 0); bytes per plane 0 (supercompressed).
    out.extend_from_slice(&[1, 1, 1, 0]);
    out.extend_from_slice(&[0; 4]);
    out.extend_from_slice(&[0; 8]);
    for (k, channel) in [0u8, 1, 2, 15].into_iter().enumerate() {
        out.extend_from_slice(&(16 * k as u16).to_le_bytes()); // bit offset
        out.push(15); // bit length − 1
        out.push(channel | 0x80 | 0x40); // float, signed
        out.extend_from_slice(&[0; 4]); // sample position
        out.extend_from_slice(&(-1.0f32).to_bits().to_le_bytes()); // lower
        out.extend_from_slice(&1.0f32.to_bits().to_le_bytes()); // upper
    }
    out
}

/// Key/value entries, each its length, the key, a NUL, the value (NUL-terminated text) and
/// padding to 4 bytes; keys in byte order as the format asks.
fn key_values(entries: &[(&str, &str)]) -> Vec<u8> {
    let mut sorted = entries.to_vec();
    sorted.sort_unstable();
    let mut out = Vec::new();
    for (key, value) in sorted {
        let length = key.len() + 1 + value.len() + 1;
        out.extend_from_slice(&(length as u32).to_le_bytes());
        out.extend_from_slice(key.as_bytes());
        out.push(0);
        out.extend_from_slice(value.as_bytes());
        out.push(0);
        out.resize(out.len().next_multiple_of(4), 0);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The file reads back through the `ktx2` crate (an independent reader): its header, its
    /// descriptor's model, transfer and samples, the orientation entry, and the texels.
    #[test]
    fn a_texture_reads_back_through_an_independent_reader() {
        let (width, height) = (5, 3);
        let rgba: Vec<[f32; 4]> = (0..width * height)
            .map(|k| [k as f32 * 0.5, 1.0 / (k + 1) as f32, 1000.0, 1.0])
            .collect();
        let bytes = rgba16f(width, height, &rgba).unwrap();
        let reader = ktx2::Reader::new(&bytes[..]).unwrap();
        let header = reader.header();
        assert_eq!(header.format, Some(ktx2::Format::R16G16B16A16_SFLOAT));
        assert_eq!((header.pixel_width, header.pixel_height), (width, height));
        assert_eq!(
            header.supercompression_scheme,
            Some(ktx2::SupercompressionScheme::Zstandard)
        );
        // The descriptor as the reader builds it for the format (but the bytes per plane,
        // which a supercompressed file leaves at 0).
        let basic = reader.basic_dfd().unwrap();
        let (expected, _) =
            ktx2::dfd::Basic::from_format(ktx2::Format::R16G16B16A16_SFLOAT).unwrap();
        assert_eq!(basic.color_model, expected.color_model);
        assert_eq!(basic.color_primaries, expected.color_primaries);
        assert_eq!(
            basic.transfer_function,
            Some(ktx2::TransferFunction::Linear)
        );
        assert_eq!(
            basic.texel_block_dimensions,
            expected.texel_block_dimensions
        );
        assert_eq!(basic.sample_information, expected.sample_information);
        assert_eq!(basic.bytes_planes, [0; 8]);
        let orientation = (reader.key_value_data())
            .find(|(key, _)| *key == "KTXorientation")
            .map(|(_, value)| value.to_vec());
        assert_eq!(orientation.as_deref(), Some(&b"rd\0"[..]));
        let level = reader.levels().next().unwrap();
        let raw =
            zstd::bulk::decompress(level.data, level.uncompressed_byte_length as usize).unwrap();
        for (k, texel) in rgba.iter().enumerate() {
            for (c, value) in texel.iter().enumerate() {
                let at = 8 * k + 2 * c;
                let half = exr::prelude::f16::from_le_bytes([raw[at], raw[at + 1]]).to_f32();
                assert!((half - value).abs() <= value.abs() * 1e-3, "{k} {c}");
            }
        }
    }
}
