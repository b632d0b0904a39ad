//! From radiance (HDR, the scene's emission units) to display colours in [0, 1].
//!
//! One exposure per timeline, so an animation does not flicker as the light changes; Reinhard's
//! global operator on luminance (Reinhard et al. 2002, eq. 3–4), which keeps hue and compresses
//! emitters smoothly instead of clipping the whole room.

use std::hash::{Hash, Hasher};

use crate::scene::Scene;
use crate::solve::FrameSolution;

/// The scene's log-average luminance of lit surfaces is mapped to this value (Reinhard's
/// "key": 0.18 is middle grey).
pub const KEY: f64 = 0.18;

/// Patches whose luminance is at most this share of the brightest are unlit for the exposure
/// ([`ToneMap::for_timeline`]).
pub const UNLIT: f64 = 1e-4;

/// Rec. 709 luminance's weights of the linear RGB channels.
pub const LUMINANCE: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Rec. 709 luminance of a linear RGB colour.
#[must_use]
pub fn luminance(c: [f64; 3]) -> f64 {
    LUMINANCE[0] * c[0] + LUMINANCE[1] * c[1] + LUMINANCE[2] * c[2]
}

/// A tone map: `display = x / (1 + Y(x))` per channel with `x = exposure · radiance`, clamped
/// to [0, 1]. The exposure is recorded in the outputs so the mapping can be undone.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToneMap {
    /// Radiance is multiplied by this before the curve.
    pub exposure: f64,
}

impl ToneMap {
    /// The exposure that maps the log-average luminance of the lit, non-emitting patches (area
    /// weighted, over every frame) to [`KEY`]. A scene with no such light gets exposure 1.
    ///
    /// Unlit patches do not count: below [`UNLIT`] of the brightest, a patch shows black
    /// whatever the exposure, and it is most often a side no light reaches at all (the outward
    /// side of a double-sided wall, as Blender exports every material; the floor under a box).
    /// Counted at a floor, as they were, the outer sides of a Blender room took its exposure
    /// from 0.52 to 8.07: the lit inside washed out.
    #[must_use]
    pub fn for_timeline(scene: &Scene, frames: &[std::sync::Arc<FrameSolution>]) -> Self {
        // Frames with equal radiance count once, weighted by how many frames show it, in order
        // of first appearance: the sum is the same whether shared frames share an `Arc` (a
        // batch bake) or hold equal copies (the service solves frames in parallel chunks).
        let mut distinct: Vec<(&FrameSolution, f64)> = Vec::new();
        let mut seen: std::collections::HashMap<u64, Vec<usize>> = Default::default();
        for frame in frames {
            let mut h = std::collections::hash_map::DefaultHasher::new();
            frame
                .radiance
                .iter()
                .for_each(|l| l.map(f64::to_bits).hash(&mut h));
            let candidates = seen.entry(h.finish()).or_default();
            match candidates
                .iter()
                .find(|&&k| distinct[k].0.radiance == frame.radiance)
            {
                Some(&k) => distinct[k].1 += 1.0,
                None => {
                    candidates.push(distinct.len());
                    distinct.push((frame, 1.0));
                }
            }
        }
        let brightest = distinct
            .iter()
            .flat_map(|(f, _)| f.radiance.iter())
            .map(|&l| luminance(l))
            .fold(0.0, f64::max);
        let (mut sum, mut weight) = (0.0, 0.0);
        for (frame, times) in distinct {
            for (patch, &l) in scene.patches.iter().zip(&frame.radiance) {
                if scene.materials[patch.material as usize].is_emitter() {
                    continue;
                }
                let y = luminance(l);
                if y > UNLIT * brightest && y > 0.0 {
                    sum += times * patch.area * y.ln();
                    weight += times * patch.area;
                }
            }
        }
        let exposure = if weight > 0.0 {
            KEY / (sum / weight).exp()
        } else if brightest > 0.0 {
            // Only emitters: show the brightest as mid-grey rather than white.
            KEY / brightest
        } else {
            1.0
        };
        Self {
            exposure: if exposure.is_finite() && exposure > 0.0 {
                exposure
            } else {
                1.0
            },
        }
    }

    /// The display colour of a radiance, linear, each channel in [0, 1].
    #[must_use]
    pub fn apply(&self, radiance: [f64; 3]) -> [f32; 3] {
        let x = radiance.map(|c| c.max(0.0) * self.exposure);
        let scale = 1.0 / (1.0 + luminance(x));
        // An overflowing channel (∞ · 0) is as bright as can be shown.
        x.map(|c| {
            let v = c * scale;
            if v.is_nan() {
                1.0
            } else {
                v.clamp(0.0, 1.0) as f32
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reinhard_maps_the_key_and_saturates() {
        let map = ToneMap { exposure: 2.0 };
        // Grey 0.5 × 2 = 1 → 1 / (1 + 1).
        assert_eq!(map.apply([0.5; 3]), [0.5; 3]);
        assert_eq!(map.apply([0.0; 3]), [0.0; 3]);
        // Very bright tends to white, never beyond.
        let white = map.apply([1e12; 3]);
        assert!(white.iter().all(|&c| c > 0.999 && c <= 1.0));
        // Hue is kept below saturation: equal ratios in, equal ratios out.
        let c = map.apply([0.1, 0.05, 0.0]);
        assert!((c[0] / c[1] - 2.0).abs() < 1e-5);
        assert_eq!(map.apply([-1.0, f64::MIN_POSITIVE, 0.0])[0], 0.0);
        // Overflow shows white, never NaN (which would cast to black).
        let huge = ToneMap { exposure: 1e300 }.apply([1e300, 0.0, 0.0]);
        assert_eq!(huge, [1.0, 0.0, 0.0]);
    }

    #[test]
    fn unlit_patches_leave_the_exposure_as_the_lit_ones_set_it() {
        let sample = crate::samples::all().swap_remove(0);
        let options = crate::loader::LoadOptions::default();
        let scene = crate::loader::load(sample.gltf.as_bytes(), &options).unwrap();
        let frame = |radiance: Vec<[f64; 3]>| {
            let n = radiance.len();
            std::sync::Arc::new(FrameSolution {
                pieces: Vec::new(),
                pieces_stderr: Vec::new(),
                shape: Vec::new(),
                spread: Vec::new(),
                first: Vec::new(),
                radiance,
                stderr: vec![None; n],
                samples: vec![0; n],
                iterations: 0,
                residual: 0.0,
                converged: true,
            })
        };
        let emits = |p: usize| scene.materials[scene.patches[p].material as usize].is_emitter();
        // Every non-emitting patch lit at 0.5 (luminance): the key over 0.5.
        let lit: Vec<[f64; 3]> = (0..scene.patches.len())
            .map(|p| if emits(p) { [10.0; 3] } else { [0.5; 3] })
            .collect();
        let alone = ToneMap::for_timeline(&scene, &[frame(lit.clone())]);
        assert!((alone.exposure - KEY / 0.5).abs() < 1e-9, "{alone:?}");
        // Half of them black (the outer sides of a double-sided room): the same exposure.
        let half: Vec<[f64; 3]> = (lit.iter().enumerate())
            .map(|(p, &l)| if !emits(p) && p % 2 == 0 { [0.0; 3] } else { l })
            .collect();
        assert_eq!(ToneMap::for_timeline(&scene, &[frame(half)]), alone);
    }
}
