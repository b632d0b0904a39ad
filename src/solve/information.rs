//! The scene's visibility information, measured by the lines already traced (Feixas, Sbert et
//! al.; the seed in `../shared/reference/`).
//!
//! Every segment between consecutive crossings `x`, `y` of a global line samples the
//! continuous mutual information of visibility,
//! `I_c ≈ (1/N) Σ_k ln(A_T cos θ_x cos θ_y / (π r²))`, and the patches' form factors give the
//! discrete one, `I_d = Σ_i Σ_j (A_i / A_T) F_ij ln(A_T F_ij / A_j)`, estimated from the
//! tallies as `Σ_ij (S_ij / N) ln(N S_ij / (N_i N_j))` (`N_i` the patch-to-patch segments
//! leaving i, `N` their total). `I_d ≤ I_c`: the gap is the visibility information the patches
//! lose, and each patch's share of it says where the discretisation is too coarse. Both are in
//! nats and use the segments between two patches only (not the sky, not absorbed ones).
//!
//! Not yet served: the `I_d` estimate is the plug-in one, biased upwards by about the number
//! of pairs the segments reach over twice the segments. It is right when every pair that sees
//! each other gets many segments (a room of 384 patches at 400k lines), and useless when they
//! get one or none: inside a sphere of 5,120 patches at 200k lines it reads 4.8 nats where
//! `I_c` is 0.0025. A bias-corrected estimator is needed before the gap can steer the cuts.

use rayon::prelude::*;
use serde::Serialize;

use super::tally::{FrameTally, MAX_PATCHES};
use crate::scene::Scene;
use crate::scene::refine::Corners;
use crate::timeline::IntersectionList;
use crate::trace::Surfaces;
use crate::trace::coincident::{COINCIDENT, is_contact, resolve};

/// The visibility information of one frame.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Information {
    /// The frame measured.
    pub frame: usize,
    /// `I_c`, the continuous mutual information (nats).
    pub continuous: f64,
    /// Its standard error (the segments' spread over √N).
    pub continuous_stderr: f64,
    /// `I_d`, the discrete mutual information of the patches (nats).
    pub discrete: f64,
    /// `I_c − I_d`: what the patches lose of the scene's visibility.
    pub gap: f64,
    /// Each patch's share of the gap: its segments' share of `I_c` minus its row's share of
    /// `I_d` (they sum to `gap`).
    pub patch_gap: Vec<f64>,
    /// Patch-to-patch segments measured (each direction counted).
    pub segments: u64,
}

impl Information {
    /// Measures the information of `list` at `frame`, `tally` being that frame's tallies.
    #[must_use]
    pub fn measure(
        scene: &Scene,
        list: &IntersectionList,
        surfaces: &Surfaces<'_>,
        tally: &FrameTally,
        frame: usize,
    ) -> Self {
        let patches = scene.patches.len();
        let corners = Corners::new(scene);
        // A_T in normalised units: every face that can be a segment's end.
        let total_area: f64 = scene
            .triangles_at(frame)
            .iter()
            .map(|(c, faces)| {
                let [a, b, c] = c.map(glam::Vec3::as_dvec3);
                0.5 * (b - a).cross(c - a).length() * (1.0 + f64::from(faces.back.is_some()))
            })
            .sum();
        let normal = |surface: u32| -> glam::DVec3 {
            match corners.posed(surface, Some(frame)) {
                Some([a, b, c]) => (b - a).cross(c - a).normalize_or_zero(),
                // A deforming object's frame-0 normal.
                None => surfaces.normals[surface as usize].as_dvec3(),
            }
        };
        let faces = surfaces.faces;
        let (sums, square, count) = (0..list.lines())
            .into_par_iter()
            .fold(
                || (vec![0.0f64; patches], 0.0f64, 0u64, Vec::new()),
                |(mut sums, mut square, mut count, mut scratch), l| {
                    list.frame_hits(l, frame, &mut scratch);
                    let d = list.direction(l).as_dvec3();
                    let surfaces = surfaces.along(list.direction(l));
                    let reordered = resolve(&scratch, &surfaces);
                    let hits = reordered.as_deref().unwrap_or(&scratch);
                    for w in hits.windows(2) {
                        let (a, b) = (w[0], w[1]);
                        let r = f64::from(b.t - a.t);
                        if is_contact(&a, &b) || r <= f64::from(COINCIDENT) {
                            continue;
                        }
                        let fa = faces[a.surface() as usize];
                        let fb = faces[b.surface() as usize];
                        let exit = if a.front() { fa.back } else { Some(fa.front) };
                        let entry = if b.front() { Some(fb.front) } else { fb.back };
                        let (Some(i), Some(j)) = (exit, entry) else {
                            continue;
                        };
                        let cos = |s: u32| normal(s).dot(d).abs().max(1e-12);
                        let term = (total_area * cos(a.surface()) * cos(b.surface())
                            / (std::f64::consts::PI * r * r))
                            .ln();
                        sums[i as usize] += term;
                        sums[j as usize] += term;
                        square += 2.0 * term * term;
                        count += 2;
                    }
                    (sums, square, count, scratch)
                },
            )
            .map(|(sums, square, count, _)| (sums, square, count))
            .reduce(
                || (vec![0.0; patches], 0.0, 0),
                |(mut a, sa, ca), (b, sb, cb)| {
                    a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                    (a, sa + sb, ca + cb)
                },
            );
        let n = count.max(1) as f64;
        let continuous: f64 = sums.iter().sum::<f64>() / n;
        let continuous_stderr = ((square / n - continuous * continuous).max(0.0) / n).sqrt();
        // The discrete information from the tallies' patch-to-patch counts.
        let row = |i: usize| tally.offsets[i]..tally.offsets[i + 1];
        let leaving: Vec<f64> = (0..patches)
            .map(|i| {
                row(i)
                    .filter(|&e| (tally.columns[e] as usize) < MAX_PATCHES)
                    .map(|e| f64::from(tally.counts[e]))
                    .sum()
            })
            .collect();
        let total: f64 = leaving.iter().sum::<f64>().max(1.0);
        let discrete_share: Vec<f64> = (0..patches)
            .map(|i| {
                row(i)
                    .filter(|&e| (tally.columns[e] as usize) < MAX_PATCHES)
                    .map(|e| {
                        let s = f64::from(tally.counts[e]);
                        let j = tally.columns[e] as usize;
                        s / total * (total * s / (leaving[i] * leaving[j])).ln()
                    })
                    .sum()
            })
            .collect();
        let discrete: f64 = discrete_share.iter().sum();
        Self {
            frame,
            continuous,
            continuous_stderr,
            discrete,
            gap: continuous - discrete,
            patch_gap: sums
                .iter()
                .zip(&discrete_share)
                .map(|(c, d)| c / n - d)
                .collect(),
            segments: count,
        }
    }
}
