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
//! The plug-in estimate of `I_d` from the tallies is biased upwards, by about the number of
//! pairs the segments reach over twice the segments. Its bias is measured and removed from the
//! line groups (the independent replicas): the same estimate from each half of the lines is
//! biased twice as much when the bias falls as `1/N`, so `2 I_d(N) − I_d(N/2)` removes it (the
//! first step of Strong et al.'s extrapolation, Phys. Rev. Lett. 80, 1998). The quarters check
//! the `1/N` law: where pairs of patches that see each other get one segment or none (a 5,120
//! patch sphere at 200k lines, whose plug-in reads 4.8 nats where `I_c` is 0.0025) the bias
//! grows with `ln N` instead, nothing removes it, and `I_d` is reported unresolved.

use rayon::prelude::*;
use serde::Serialize;

use super::tally::{FrameTally, GROUPS, MAX_PATCHES};
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
    /// Its standard error (from the spread of the line groups' estimates; infinite with one
    /// group or none).
    pub continuous_stderr: f64,
    /// `I_d`, the discrete mutual information of the patches (nats), its plug-in bias removed;
    /// `None` when the lines do not resolve it (pairs of patches get too few segments: more
    /// lines or fewer patches resolve it).
    pub discrete: Option<f64>,
    /// The plug-in estimate of `I_d` from all the segments.
    pub discrete_plugin: f64,
    /// The bias removed from the plug-in estimate (the halves' estimate less the whole's).
    pub discrete_bias: f64,
    /// `I_c − I_d`: what the patches lose of the scene's visibility (when `I_d` is resolved).
    pub gap: Option<f64>,
    /// Each patch's share of the gap: its segments' share of `I_c` minus its row's share of
    /// `I_d` (they sum to `gap`; when `I_d` is resolved).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub patch_gap: Option<Vec<f64>>,
    /// Patch-to-patch segments measured (each direction counted).
    pub segments: u64,
    /// Pairs of patches (ordered) that the segments join.
    pub pairs: u64,
}

/// A patch's share of the information gap.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct GapShare {
    /// The patch.
    pub patch: usize,
    /// Its share of `I_c − I_d` (nats).
    pub share: f64,
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
        // Sums in fixed point (whole numbers of 2^-32 nats), so that they do not depend on
        // the order the threads add them in: the summary of a bake is the same on any run.
        let fixed = |x: f64| (x * UNIT).round() as i128;
        let groups = list.line_groups(GROUPS);
        // Each segment counts its line's weight, as in the tallies.
        let weights = list.line_weights();
        let (sums, by_group) = (0..list.lines())
            .into_par_iter()
            .filter(|&l| weights[l] > 0)
            .fold(
                || (vec![0i128; patches], [(0i128, 0u64); G], Vec::new()),
                |(mut sums, mut by_group, mut scratch), l| {
                    let group = &mut by_group[groups[l] as usize];
                    let weight = weights[l];
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
                        let term = i128::from(weight) * fixed(term);
                        sums[i as usize] += term;
                        sums[j as usize] += term;
                        group.0 += 2 * term;
                        group.1 += 2 * u64::from(weight);
                    }
                    (sums, by_group, scratch)
                },
            )
            .map(|(sums, by_group, _)| (sums, by_group))
            .reduce(
                || (vec![0; patches], [(0, 0); G]),
                |(mut a, mut ga), (b, gb)| {
                    a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                    ga.iter_mut().zip(&gb).for_each(|(x, y)| {
                        x.0 += y.0;
                        x.1 += y.1;
                    });
                    (a, ga)
                },
            );
        let count: u64 = by_group.iter().map(|g| g.1).sum();
        let n = count.max(1) as f64;
        let sums: Vec<f64> = sums.iter().map(|&s| s as f64 / UNIT).collect();
        let continuous: f64 = sums.iter().sum::<f64>() / n;
        // The standard error from the spread of the line groups' estimates (independent
        // replicas): the segments of one bundle are not independent (they share a direction).
        let replicas: Vec<f64> = by_group
            .iter()
            .filter(|g| g.1 > 0)
            .map(|g| g.0 as f64 / UNIT / g.1 as f64)
            .collect();
        let r = replicas.len() as f64;
        let continuous_stderr = if r > 1.0 {
            let mean = replicas.iter().sum::<f64>() / r;
            (replicas.iter().map(|m| (m - mean).powi(2)).sum::<f64>() / (r * (r - 1.0))).sqrt()
        } else {
            f64::INFINITY
        };
        // The discrete information from the tallies' patch-to-patch counts: from all the
        // lines, and the mean over their halves and over their quarters (line groups taken
        // by the remainder of their number).
        let (whole, pairs) = plugin_shares(tally, |_| true);
        let split = |parts: u8| {
            let mut mean = vec![0.0; patches];
            for part in 0..parts {
                let (shares, _) = plugin_shares(tally, |g| g % parts == part);
                mean.iter_mut()
                    .zip(&shares)
                    .for_each(|(m, s)| *m += s / f64::from(parts));
            }
            mean
        };
        let (halves, quarters) = (split(2), split(4));
        let total = |v: &[f64]| v.iter().sum::<f64>();
        let discrete_plugin = total(&whole);
        let discrete_bias = total(&halves) - discrete_plugin;
        // Under the 1/N law the quarters are biased twice as much again as the halves.
        let further = total(&quarters) - total(&halves);
        let resolved = discrete_bias.abs() <= RESOLVED_BIAS
            || (further / discrete_bias - 2.0).abs() <= LAW_TOLERANCE;
        let corrected: Vec<f64> = whole
            .iter()
            .zip(&halves)
            .map(|(w, h)| 2.0 * w - h)
            .collect();
        let discrete = resolved.then(|| total(&corrected));
        Self {
            frame,
            continuous,
            continuous_stderr,
            discrete,
            discrete_plugin,
            discrete_bias,
            gap: discrete.map(|d| continuous - d),
            patch_gap: resolved.then(|| {
                sums.iter()
                    .zip(&corrected)
                    .map(|(c, d)| c / n - d)
                    .collect()
            }),
            segments: count,
            pairs,
        }
    }

    /// The report of this measure, with every patch's share of the gap if `every_patch`.
    #[must_use]
    pub fn report(mut self, every_patch: bool) -> Report {
        let largest_gaps = self.largest_gaps(LARGEST_GAPS);
        if !every_patch {
            self.patch_gap = None;
        }
        Report {
            measured: self,
            largest_gaps,
        }
    }

    /// The `k` patches with the largest shares of the gap, largest first; none when `I_d` is
    /// unresolved.
    #[must_use]
    pub fn largest_gaps(&self, k: usize) -> Vec<GapShare> {
        let Some(shares) = &self.patch_gap else {
            return Vec::new();
        };
        let mut order: Vec<GapShare> = shares
            .iter()
            .enumerate()
            .map(|(patch, &share)| GapShare { patch, share })
            .collect();
        order.sort_by(|a, b| b.share.total_cmp(&a.share).then(a.patch.cmp(&b.patch)));
        order.truncate(k);
        order
    }
}

/// What is reported of a frame's information (`/stats`, `summary.json`): the measure, every
/// patch's share only when asked for, and the patches with the largest shares.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Report {
    /// The measure.
    #[serde(flatten)]
    pub measured: Information,
    /// The [`LARGEST_GAPS`] patches with the largest shares of the gap, largest first (none
    /// when `I_d` is unresolved).
    pub largest_gaps: Vec<GapShare>,
}

/// Patches a [`Report`] lists with the largest shares of the gap.
pub const LARGEST_GAPS: usize = 10;

/// Line groups ([`GROUPS`]).
const G: usize = GROUPS as usize;

/// Fixed-point units per nat of [`Information::measure`]'s sums.
const UNIT: f64 = 4_294_967_296.0;

/// A plug-in bias this small (nats) is resolved whatever its law.
const RESOLVED_BIAS: f64 = 1e-3;

/// How far the quarters' extra bias over the halves' may stray from the `1/N` law's 2 (as a
/// ratio to the halves' bias) for the bias to be removed: in the sparse regime it is 1.
const LAW_TOLERANCE: f64 = 0.5;

/// Each patch's share of the plug-in estimate of `I_d`, `Σ_j (S_ij / N) ln(N S_ij / (N_i N_j))`,
/// from the segments of the line groups `keep` takes; and the pairs of patches they join.
fn plugin_shares(tally: &FrameTally, keep: impl Fn(u8) -> bool + Sync) -> (Vec<f64>, u64) {
    let patches = tally.patches();
    let rows: Vec<Vec<(u32, u64)>> = (0..patches)
        .into_par_iter()
        .map(|i| {
            let mut row: Vec<(u32, u64)> = (tally.group_row(i).iter())
                .filter(|&&(j, g, _)| (j as usize) < MAX_PATCHES && keep(g))
                .map(|&(j, _, s)| (j, u64::from(s)))
                .collect();
            row.sort_unstable_by_key(|e| e.0);
            row.dedup_by(|next, kept| {
                let same = next.0 == kept.0;
                if same {
                    kept.1 += next.1;
                }
                same
            });
            row
        })
        .collect();
    let leaving: Vec<f64> = rows
        .iter()
        .map(|r| r.iter().map(|e| e.1 as f64).sum())
        .collect();
    let total = leaving.iter().sum::<f64>().max(1.0);
    let shares = rows
        .par_iter()
        .enumerate()
        .map(|(i, row)| {
            row.iter()
                .map(|&(j, s)| {
                    let s = s as f64;
                    s / total * (total * s / (leaving[i] * leaving[j as usize])).ln()
                })
                .sum()
        })
        .collect();
    (shares, rows.iter().map(|r| r.len() as u64).sum())
}
