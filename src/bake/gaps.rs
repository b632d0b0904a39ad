//! Where a piece holds light that one radiance per piece misplaces: the pieces [`super::Bake::split`]
//! cuts further (issue 13: light trapped in a 1 cm gap escaping into the room).
//!
//! A piece is solved as one radiance sent evenly from all of it. Where part of it faces
//! something closer than the piece is wide (a panel 1 cm below a ceiling, a box resting on a
//! floor) and the rest faces the room, the two parts gather different light, and the light the
//! near part reflects goes back to what is near, physically; solved as one piece, the mean of
//! both is sent everywhere, so the near part's light leaks into the room (or the room's into
//! the gap). Every segment of a line leaving a piece tells both what it faces and how far:
//! split at the piece's width into `near` and `far`, with shares `s` and `1 − s` and mean
//! gathered luminances `L_n` and `L_f`, the flux the piece sends to the far side in the wrong
//! amount is about
//!
//!   `A · ρ · s (1 − s) · |L_n − L_f|`
//!
//! (the near part, area ≈ `s·A`, sends `ρ·L̄` where it physically sends its own `ρ·L_n` to what
//! is near; the share `1 − s` of it that the model sends far is misplaced). The difference is
//! taken less three times its standard error ([`SIGNIFICANCE`]), so that noise alone seldom
//! scores. A piece's score falls
//! with its area as it is cut, while the share across a gap's rim stays: the cuts follow the
//! rim down until its pieces hold too little flux to matter.

use glam::DVec3;
use rayon::prelude::*;

use super::PIECE_CROSSINGS;
use crate::output::tonemap::luminance;
use crate::scene::Scene;
use crate::scene::refine::Corners;
use crate::solve::tally::{FixedLight, walk_from};
use crate::timeline::IntersectionList;
use crate::trace::SceneTracer;

/// Standard errors a piece's near and far light must differ by before any of it counts: noise
/// alone passes 3σ in about one piece in 370 (a side whose segments all meet one neighbour
/// shows no spread, hence at least [`PIECE_CROSSINGS`] segments on each side).
pub const SIGNIFICANCE: f64 = 3.0;

/// Per piece, the segments leaving it split by length at its width: count, fixed-point sum and
/// sum of squares of the gathered luminance, near then far.
#[derive(Clone, Copy, Default)]
struct Sides {
    count: [u64; 2],
    sum: [u64; 2],
    square: [u128; 2],
}

/// Each piece's misplaced flux (module docs) and the segments leaving it, at frame 0, with
/// `gathered(j)` the luminance of piece `j` (the patches' solution will do: the score needs
/// what each piece faces, not its own detail) and `sky` the sky's luminance.
pub(super) fn misplaced(
    scene: &Scene,
    tracer: &SceneTracer,
    list: &IntersectionList,
    gathered: &(dyn Fn(u32) -> f64 + Sync),
    sky: f64,
) -> Vec<(f64, u64)> {
    let corners = Corners::new(scene);
    // Each triangle's width: its longest edge at frame 0 (normalised space).
    let width: Vec<f32> = (0..tracer.triangles() as u32)
        .map(|g| {
            let c = corners
                .posed(g, Some(0))
                .unwrap_or_else(|| corners.own(g).map(|p| p.as_dvec3()));
            let edge = |a: DVec3, b: DVec3| a.distance(b);
            edge(c[0], c[1]).max(edge(c[1], c[2])).max(edge(c[2], c[0])) as f32
        })
        .collect();
    // Sums in fixed point: the cuts are the same on any machine.
    let pieces = scene.patches.len();
    let light = FixedLight::new(gathered, pieces, sky);
    let (unit, value) = (light.unit, |to| light.value(to));
    let surfaces = tracer.surfaces();
    let sides = list
        .bundles(scene)
        .fold(
            || (vec![Sides::default(); pieces], Vec::new()),
            |(mut acc, mut hits), (first, bundle)| {
                let surfaces = surfaces.along(bundle.direction);
                for i in 0..bundle.origins.len() {
                    list.frame_hits(first + i, 0, &mut hits);
                    walk_from(&hits, &surfaces, |from, to, at, length| {
                        let side = usize::from(length >= width[at.surface() as usize]);
                        let g = value(to);
                        let s = &mut acc[from as usize];
                        s.count[side] += 1;
                        s.sum[side] += g;
                        s.square[side] += u128::from(g) * u128::from(g);
                    });
                }
                (acc, hits)
            },
        )
        .map(|(acc, _)| acc)
        .reduce(
            || vec![Sides::default(); pieces],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(&b) {
                    for k in 0..2 {
                        x.count[k] += y.count[k];
                        x.sum[k] += y.sum[k];
                        x.square[k] += y.square[k];
                    }
                }
                a
            },
        );
    (scene.patches.iter())
        .zip(&sides)
        .map(|(p, s)| {
            let segments = s.count[0] + s.count[1];
            let rho = luminance(scene.materials[p.material as usize].reflectance);
            // Both sides known from a piece's worth of segments, or no score.
            if s.count.iter().any(|&n| (n as f64) < PIECE_CROSSINGS) || rho <= 0.0 {
                return (0.0, segments);
            }
            let (mean, variance): (Vec<f64>, Vec<f64>) = (0..2)
                .map(|k| {
                    let n = s.count[k] as f64;
                    let mean = s.sum[k] as f64 * unit / n;
                    let square = s.square[k] as f64 * unit * unit / n;
                    // The variance of the mean: the unbiased sample variance over n.
                    (mean, (square - mean * mean).max(0.0) * n / (n - 1.0) / n)
                })
                .unzip();
            let difference =
                (mean[0] - mean[1]).abs() - SIGNIFICANCE * (variance[0] + variance[1]).sqrt();
            let near = s.count[0] as f64 / segments as f64;
            let score = p.area * rho * near * (1.0 - near) * difference.max(0.0);
            (score, segments)
        })
        .collect()
}
