//! Materials: the diffuse reflectance and the emission the radiosity solve needs.
//!
//! reflectance = baseColorFactor × mean(baseColorTexture, linear) × (1 − metallic), with
//! metallic = metallicFactor × mean(blue channel of metallicRoughnessTexture);
//! emission = emissiveFactor × KHR_materials_emissive_strength × mean(emissiveTexture, linear).
//! Textures are averaged: a patch carries one value. Colour textures are sRGB and are decoded to
//! linear before averaging.

use std::collections::HashMap;
use std::io::Cursor;

use gltf::Document;

use super::LoadError;
use super::container::decode_data_uri;
use crate::scene::Material;

/// Images larger than this (in pixels per side) are not decoded: the loader must not be a
/// decompression bomb's victim.
const MAX_IMAGE_SIDE: u32 = 8192;
/// Memory the image decoder may allocate for one image.
const MAX_IMAGE_BYTES: u64 = 512 << 20;

/// Converts every material of the document; `warnings` receives what could not be honoured.
pub fn convert(
    document: &Document,
    buffers: &[Vec<u8>],
    warnings: &mut Vec<String>,
) -> Result<Vec<Material>, LoadError> {
    let mut averages = TextureAverages::default();
    document
        .materials()
        .map(|m| convert_one(&m, document, buffers, &mut averages, warnings))
        .collect()
}

fn convert_one(
    m: &gltf::Material<'_>,
    document: &Document,
    buffers: &[Vec<u8>],
    averages: &mut TextureAverages,
    warnings: &mut Vec<String>,
) -> Result<Material, LoadError> {
    let index = m.index().unwrap_or(0);
    let pbr = m.pbr_metallic_roughness();
    let base = pbr.base_color_factor();
    let mut reflectance = [0, 1, 2].map(|c| f64::from(base[c]));
    if let Some(info) = pbr.base_color_texture()
        && let Some(mean) = averages.get(document, buffers, &info, true, warnings)?
    {
        (0..3).for_each(|c| reflectance[c] *= mean[c]);
    }
    let mut metallic = f64::from(pbr.metallic_factor());
    if let Some(info) = pbr.metallic_roughness_texture()
        && let Some(mean) = averages.get(document, buffers, &info, false, warnings)?
    {
        metallic *= mean[2];
    }
    let coloured = reflectance.iter().any(|&r| r > 0.0);
    reflectance = reflectance.map(|r| r * (1.0 - metallic.clamp(0.0, 1.0)));
    if coloured && metallic >= 1.0 {
        // glTF's metallicFactor is 1 when a file leaves it out (COLLADA2GLTF and older
        // exporters do): the surface then bakes black, and a user should hear why.
        let name = m.name().map_or_else(String::new, |n| format!(" ({n})"));
        warnings.push(format!(
            "material {index}{name} is fully metallic (metallicFactor 1, glTF's default when a \
             file leaves it out): its diffuse reflectance is 0 and it reflects no light in the \
             bake; set metallicFactor to 0 if it is a diffuse surface"
        ));
    }
    let strength = f64::from(m.emissive_strength().unwrap_or(1.0));
    let factor = m.emissive_factor();
    let mut emission = [0, 1, 2].map(|c| f64::from(factor[c]) * strength);
    if let Some(info) = m.emissive_texture()
        && let Some(mean) = averages.get(document, buffers, &info, true, warnings)?
    {
        (0..3).for_each(|c| emission[c] *= mean[c]);
    }
    let name = m.name().map(str::to_owned);
    let what = format!("material {index}");
    if reflectance.iter().chain(&emission).any(|v| !v.is_finite()) {
        return Err(LoadError::malformed(
            what,
            "reflectance or emission is not finite",
        ));
    }
    if reflectance.iter().any(|r| !(0.0..=1.0).contains(r)) {
        warnings.push(format!(
            "{what}: reflectance {reflectance:?} outside [0, 1], clamped"
        ));
        reflectance = reflectance.map(|r| r.clamp(0.0, 1.0));
    }
    if emission.iter().any(|&e| e < 0.0) {
        warnings.push(format!(
            "{what}: negative emission {emission:?}, clamped to 0"
        ));
        emission = emission.map(|e| e.max(0.0));
    }
    Ok(Material {
        name,
        reflectance,
        emission,
        double_sided: m.double_sided(),
    })
}

/// Lowers every reflectance above `max` to it ([`Material::reflects_above`]): at reflectance 1 a
/// closed scene has no steady state (METHOD.md §4). `default` is the index of the glTF default
/// material, if the scene uses it. Returns a warning naming the materials changed, if any.
pub fn cap_reflectance(
    materials: &mut [Material],
    max: f64,
    default: Option<usize>,
) -> Option<String> {
    let mut changed = Vec::new();
    for (index, material) in materials.iter_mut().enumerate() {
        if !material.reflects_above(max) {
            continue;
        }
        let what = match (&material.name, Some(index) == default) {
            (_, true) => "the glTF default material (primitives without one)".to_string(),
            (Some(name), false) => format!("material {index} ({name:?})"),
            (None, false) => format!("material {index}"),
        };
        changed.push(format!("{what}: {:?}", material.reflectance));
        material.reflectance = material.reflectance.map(|r| r.min(max));
    }
    (!changed.is_empty()).then(|| {
        format!(
            "reflectance lowered to max_reflectance {max} (a closed scene that reflects \
             everything has no steady state) for {}",
            changed.join(", ")
        )
    })
}

/// Largest radiance the outputs can hold: `radiance.bin`, the baked glTF and the service's
/// binary frames store `f32` (at most 3.4e38), with a margin for the sky and the lamps.
pub const MAX_RADIANCE: f64 = 1e37;

/// Refuses emission so strong that the radiance it builds up could overflow the `f32` outputs:
/// in a closed scene a patch can reach `Le / (1 − ρ)` for the largest emission and reflectance.
/// (Up to 1e30 with reflectance at the 0.999 cap passes; `KHR_materials_emissive_strength`
/// allows more.) A scene that reflects everything is left to the solve, which fails it.
///
/// # Errors
/// [`LoadError::Limit`] naming the strongest material.
pub fn check_emission(materials: &[Material]) -> Result<(), LoadError> {
    let rho = materials
        .iter()
        .flat_map(|m| m.reflectance)
        .fold(0.0, f64::max);
    let Some((index, material)) = materials.iter().enumerate().max_by(|a, b| {
        let peak = |m: &Material| m.emission.iter().copied().fold(0.0, f64::max);
        peak(a.1).total_cmp(&peak(b.1))
    }) else {
        return Ok(());
    };
    let peak = material.emission.iter().copied().fold(0.0, f64::max);
    if rho < 1.0 && peak / (1.0 - rho) > MAX_RADIANCE {
        let name = material
            .name
            .as_ref()
            .map_or(String::new(), |n| format!(" ({n:?})"));
        return Err(LoadError::Limit(format!(
            "material {index}{name} emits {peak:e}: with reflectance up to {rho} the radiance \
             could reach {:e}, beyond the {MAX_RADIANCE:e} that the f32 outputs hold",
            peak / (1.0 - rho)
        )));
    }
    Ok(())
}

/// Mean linear RGB of each (image, colour space) pair, decoded once however many materials use
/// it.
#[derive(Default)]
struct TextureAverages {
    cache: HashMap<(usize, bool), Option<[f64; 3]>>,
}

impl TextureAverages {
    /// The mean of the image behind `info`, or `None` (with a warning) if it cannot be decoded.
    /// External URIs are refused as an error, like buffers'.
    fn get(
        &mut self,
        document: &Document,
        buffers: &[Vec<u8>],
        info: &gltf::texture::Info<'_>,
        srgb: bool,
        warnings: &mut Vec<String>,
    ) -> Result<Option<[f64; 3]>, LoadError> {
        let image = info.texture().source().index();
        if let Some(&mean) = self.cache.get(&(image, srgb)) {
            return Ok(mean);
        }
        let bytes = image_bytes(document, buffers, image)?;
        let mean = match mean_rgb(&bytes, srgb) {
            Ok(mean) => Some(mean),
            Err(reason) => {
                warnings.push(format!(
                    "image {image} could not be decoded ({reason}); its factor is used alone"
                ));
                None
            }
        };
        self.cache.insert((image, srgb), mean);
        Ok(mean)
    }
}

/// The encoded bytes of image `index`: from a buffer view or a `data:` URI.
fn image_bytes(
    document: &Document,
    buffers: &[Vec<u8>],
    index: usize,
) -> Result<Vec<u8>, LoadError> {
    let what = || format!("image {index}");
    let json = &document.as_json().images[index];
    if let Some(view) = json.buffer_view {
        let view = &document.as_json().buffer_views[view.value()];
        let buffer = &buffers[view.buffer.value()];
        let offset = view.byte_offset.map_or(0, |o| o.0 as usize);
        let length = view.byte_length.0 as usize;
        return offset
            .checked_add(length)
            .and_then(|end| buffer.get(offset..end))
            .map(<[u8]>::to_vec)
            .ok_or_else(|| LoadError::malformed(what(), "its bufferView lies outside its buffer"));
    }
    match &json.uri {
        Some(uri) => decode_data_uri(uri, &what),
        None => Err(LoadError::malformed(
            what(),
            "has neither a bufferView nor a uri",
        )),
    }
}

/// Mean RGB of an encoded PNG or JPEG, linear (from sRGB if `srgb`), in [0, 1].
fn mean_rgb(bytes: &[u8], srgb: bool) -> Result<[f64; 3], String> {
    let mut reader = image::ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| e.to_string())?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE);
    limits.max_image_height = Some(MAX_IMAGE_SIDE);
    limits.max_alloc = Some(MAX_IMAGE_BYTES);
    reader.limits(limits);
    let decoded = reader.decode().map_err(|e| e.to_string())?.into_rgb32f();
    let pixels = u64::from(decoded.width()) * u64::from(decoded.height());
    if pixels == 0 {
        return Err("empty image".into());
    }
    let mut sum = [0.0f64; 3];
    for p in decoded.pixels() {
        for (total, &v) in sum.iter_mut().zip(&p.0) {
            let v = f64::from(v);
            *total += if srgb { srgb_to_linear(v) } else { v };
        }
    }
    Ok(sum.map(|s| s / pixels as f64))
}

/// The sRGB transfer function, inverted (IEC 61966-2-1).
#[must_use]
fn srgb_to_linear(v: f64) -> f64 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png(pixels: &[[u8; 3]], width: u32) -> Vec<u8> {
        let img = image::RgbImage::from_raw(
            width,
            pixels.len() as u32 / width,
            pixels.iter().flatten().copied().collect(),
        )
        .unwrap();
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    }

    #[test]
    fn srgb_decoding_matches_the_standard() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-15);
        assert!((srgb_to_linear(0.5) - 0.214_041_140_5).abs() < 1e-9);
    }

    #[test]
    fn texture_means_are_linear() {
        // Half black, half white: the linear mean is 0.5 whether or not sRGB-decoded, while a
        // mid-grey sRGB texel (188) is about 0.5 only after decoding.
        let bytes = png(&[[0, 0, 0], [255, 255, 255]], 2);
        let m = mean_rgb(&bytes, true).unwrap();
        assert!(m.iter().all(|&c| (c - 0.5).abs() < 1e-6), "{m:?}");
        let grey = png(&[[188, 188, 188]], 1);
        let m = mean_rgb(&grey, true).unwrap();
        assert!((m[0] - 0.5029).abs() < 1e-3, "{m:?}");
        let m = mean_rgb(&grey, false).unwrap();
        assert!((m[0] - 188.0 / 255.0).abs() < 1e-6, "{m:?}");
    }

    #[test]
    fn garbage_images_are_reported_not_fatal() {
        assert!(mean_rgb(b"not an image", true).is_err());
        let mut bytes = png(&[[1, 2, 3]; 16], 4);
        bytes.truncate(bytes.len() / 2);
        assert!(mean_rgb(&bytes, true).is_err());
    }
}
