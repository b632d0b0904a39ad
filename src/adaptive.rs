//! Adaptive patches (`patch_size=auto`): patches cut where the light needs them, decided from
//! the lines already traced.
//!
//! A patch holds one radiance; where the light arriving on it differs across it, the light it
//! sends on is misplaced (a ceiling triangle lit in a 1 cm gap behind a lamp re-emits that
//! light into the room). Every segment of a line gathers, at the crossing it leaves a patch
//! from, the radiance of the patch (or sky) at its other end: split each patch in the two
//! halves its longest-edge bisection would make, and the segments leaving each half estimate
//! the radiance that half gathers, with their own standard error. A patch whose halves gather
//! differently beyond their noise ([`Adaptive::significance`] standard errors) is cut, those
//! that misplace the most reflected power (ρ · area · difference) first, up to the patch
//! budget. Each round solves a few frames, scores, cuts, and moves the crossings to the new
//! patches ([`Bake::cut`]): no line is traced again.
//!
//! One set of patches serves the whole timeline (patch ids are stable across frames): the
//! scores are taken at up to [`FRAMES`] frames spread over it, and a patch is cut if any of
//! them needs it.

use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::bake::Bake;
use crate::scene::refine::{Corners, barycentric, longest_edge};
use crate::solve::SolveParams;
use crate::solve::tally::{ABSORBED, SKY, walk_from};
use crate::timeline::{Control, TraceError};

/// Frames scored per round at most, spread over the distinct frames of the timeline.
pub const FRAMES: usize = 3;

/// How adaptive patches are chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Adaptive {
    /// Most patches the cuts may reach (a cut's neighbours may take it a little beyond).
    pub budget: usize,
    /// Rounds of solving, scoring and cutting at most; each can cut every patch once.
    pub rounds: usize,
    /// A patch is cut when the radiance its halves gather differs by more than this many
    /// standard errors of the difference.
    pub significance: f64,
    /// ... and each half has at least this many crossings (below it, a half's estimate is
    /// too noisy to say anything and the halves would be noisier still).
    pub min_crossings: f64,
}

impl Adaptive {
    /// The standard choice for a bake of `lines` lines: a budget of one patch per
    /// [`LINES_PER_PATCH`] lines (at least the scene's own patches), six rounds, cuts beyond
    /// 3σ with 32 crossings per half.
    #[must_use]
    pub fn for_lines(lines: u64, patches: usize) -> Self {
        Self {
            budget: ((lines / LINES_PER_PATCH) as usize).max(patches),
            rounds: 6,
            significance: 3.0,
            min_crossings: 32.0,
        }
    }
}

/// Lines per patch of the standard budget ([`Adaptive::for_lines`]).
pub const LINES_PER_PATCH: u64 = 100;

/// What one round did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Round {
    /// Patches before the round.
    pub patches: usize,
    /// Patches whose halves differed beyond their noise.
    pub significant: usize,
    /// Patches added by the round's cuts.
    pub added: usize,
    /// Seconds the round took (solve, scores, cuts, direct light).
    pub seconds: f64,
}

/// Cuts `bake`'s patches where the light needs them ([`Adaptive`]); `solve` gives the sky and
/// the stopping rule of the scoring solves. Returns what each round did.
///
/// # Errors
/// [`TraceError::Cancelled`] when `control` is cancelled (the bake is then left with the cuts
/// of the rounds already done).
pub fn adapt(
    bake: &mut Bake,
    auto: &Adaptive,
    solve: &SolveParams,
    control: &Control,
) -> Result<Vec<Round>, TraceError> {
    let mut rounds = Vec::new();
    for _ in 0..auto.rounds {
        control.check()?;
        let started = Instant::now();
        let patches = bake.scene.patches.len();
        if patches >= auto.budget {
            break;
        }
        let marked = mark(bake, auto, solve);
        let significant = marked.iter().filter(|&&m| m).count();
        let added = if significant == 0 {
            0
        } else {
            bake.cut(&marked, control)?
        };
        rounds.push(Round {
            patches,
            significant,
            added,
            seconds: started.elapsed().as_secs_f64(),
        });
        if added == 0 {
            break;
        }
    }
    Ok(rounds)
}

/// Up to [`FRAMES`] distinct frames spread over the timeline.
fn scored_frames(bake: &Bake) -> Vec<usize> {
    let representatives = bake.representatives();
    let distinct: Vec<usize> = (0..representatives.len())
        .filter(|&f| representatives[f] == f)
        .collect();
    let n = distinct.len().min(FRAMES);
    let mut frames: Vec<usize> = (0..n)
        .map(|k| distinct[k * (distinct.len() - 1) / (n - 1).max(1)])
        .collect();
    frames.dedup();
    frames
}

/// The traced triangles to cut this round (by global index), within the budget.
fn mark(bake: &Bake, auto: &Adaptive, solve: &SolveParams) -> Vec<bool> {
    let scene = &bake.scene;
    let faces = bake.tracer().faces();
    let mut triangle_of = vec![0u32; scene.patches.len()];
    for (g, f) in faces.iter().enumerate() {
        triangle_of[f.front as usize] = g as u32;
        if let Some(b) = f.back {
            triangle_of[b as usize] = g as u32;
        }
    }
    // The reflected power each patch would misplace, if significant, most over the frames.
    let mut priority = vec![0.0f64; scene.patches.len()];
    for frame in scored_frames(bake) {
        let solution = bake.solve_frame(frame, &scene.materials, solve);
        let halves = halves(bake, frame, &solution.radiance, solve.sky);
        for (i, h) in halves.iter().enumerate() {
            let Some(difference) = significant_difference(h, auto) else {
                continue;
            };
            let patch = &scene.patches[i];
            let rho = luminance(scene.materials[patch.material as usize].reflectance);
            priority[i] = priority[i].max(rho * patch.area * difference);
        }
    }
    let mut order: Vec<usize> = (0..priority.len()).filter(|&i| priority[i] > 0.0).collect();
    order.sort_by(|&a, &b| priority[b].total_cmp(&priority[a]));
    let mut marked = vec![false; faces.len()];
    let mut patches = scene.patches.len();
    for i in order {
        let t = triangle_of[i] as usize;
        if marked[t] {
            continue;
        }
        let adds = 1 + usize::from(faces[t].back.is_some());
        if patches + adds > auto.budget {
            break;
        }
        marked[t] = true;
        patches += adds;
    }
    marked
}

/// |μ₀ − μ₁| of a patch's halves if it exceeds their noise ([`Adaptive::significance`]) and
/// both halves have enough crossings.
fn significant_difference(h: &[f64; 6], auto: &Adaptive) -> Option<f64> {
    let [n0, s0, q0, n1, s1, q1] = *h;
    if n0 < auto.min_crossings || n1 < auto.min_crossings {
        return None;
    }
    let (m0, m1) = (s0 / n0, s1 / n1);
    // Variance of each half's mean (crossings taken as independent: the lines' stratification
    // only makes it smaller, so the test errs towards not cutting).
    let variance = (q0 / n0 - m0 * m0).max(0.0) / n0 + (q1 / n1 - m1 * m1).max(0.0) / n1;
    let difference = (m0 - m1).abs();
    (difference > auto.significance * variance.sqrt()).then_some(difference)
}

/// Rec. 709 luminance.
fn luminance(c: [f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

/// Per patch, for each of its two halves (the longest-edge bisection of its triangle): the
/// crossings whose segment leaves the patch from that half, and the sum and sum of squares of
/// the luminance at the segments' other ends, at `frame` with `radiance`:
/// `[n₀, Σ₀, Σ²₀, n₁, Σ₁, Σ²₁]`.
fn halves(bake: &Bake, frame: usize, radiance: &[[f64; 3]], sky: [f64; 3]) -> Vec<[f64; 6]> {
    let scene = &bake.scene;
    let list = bake.list();
    let surfaces = bake.tracer().surfaces();
    let corners = Corners::new(scene);
    let edges: Vec<u8> = (0..bake.tracer().triangles() as u32)
        .into_par_iter()
        .map(|g| longest_edge(corners.own(g)) as u8)
        .collect();
    let sky = luminance(sky);
    let value = |to: u32| match to {
        SKY => sky,
        ABSORBED => 0.0,
        j => luminance(radiance[j as usize]),
    };
    let patches = scene.patches.len();
    list.bundles(scene)
        .fold(
            || (vec![[0.0; 6]; patches], Vec::new()),
            |(mut acc, mut hits), (first, bundle)| {
                let surfaces = surfaces.along(bundle.direction);
                let direction = bundle.direction.as_dvec3();
                for (i, origin) in bundle.origins.iter().enumerate() {
                    list.frame_hits(first + i, frame, &mut hits);
                    walk_from(&hits, &surfaces, |from, to, at| {
                        let Some(c) = corners.posed(at.surface(), Some(frame)) else {
                            return;
                        };
                        let p = origin.as_dvec3() + direction * f64::from(at.t);
                        let Some(l) = barycentric(c, p) else { return };
                        let k = usize::from(edges[at.surface() as usize]);
                        let half = if l[k] >= l[(k + 1) % 3] { 0 } else { 3 };
                        let g = value(to);
                        let a = &mut acc[from as usize];
                        a[half] += 1.0;
                        a[half + 1] += g;
                        a[half + 2] += g * g;
                    });
                }
                (acc, hits)
            },
        )
        .map(|(acc, _)| acc)
        .reduce(
            || vec![[0.0; 6]; patches],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(&b) {
                    for k in 0..6 {
                        x[k] += y[k];
                    }
                }
                a
            },
        )
}
