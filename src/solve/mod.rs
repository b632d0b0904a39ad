//! The radiosity solve of one frame from its tallies (METHOD.md §4, §6).
//!
//! Per colour channel, with `F_ij = S_ij / N_i`:
//! `L_i = Le_i + ρ_i Σ_j F_ij L_j + ρ_i F_i,sky L_sky`. Multiplied by `N_i / ρ_i` the system
//! `diag(N/ρ) L − S L = diag(N/ρ) Le + S_sky L_sky` is symmetric (`S_ij = S_ji`) and strictly
//! diagonally dominant for ρ < 1, hence positive definite: it is solved by conjugate gradients
//! with a diagonal preconditioner, which converge in about `√((1+ρ)/(1−ρ))/2` iterations per
//! factor e even at ρ = 0.999. Patches with ρ = 0, or that no line crossed, are `L = Le`.
//!
//! The standard error of each patch: the lines come as 16 independent replicas (each an
//! unbiased stratified estimate on its own); every frame is also solved with each replica's
//! tallies alone, warm-started from the pooled solution, and the spread of those solutions
//! over √16 is the error of the pooled one. It carries every bounce and the correlations
//! between patches; it is never taken below the spread of the patch's own first bounce between
//! the replicas, which low sample counts can hide from the solutions' spread.
//!
//! A bake solved on pieces of its patches ([`crate::bake::Bake::split`]) answers for each
//! patch with the mean of its pieces ([`Groups`]); each replica's answer is grouped the same
//! way, so the error bar is the spread of the patches' means, not of the noisier pieces'.
//!
//! Conjugate gradients stop when the answer can no longer move by a visible share of its own
//! noise: with `M = D⁻¹S` the transport among the unknowns (row sums `q_i = ρ_i Σ_j S_ij / N_i`
//! ≤ ρ_i) and `z = D⁻¹r` the preconditioned residual, the error `e` of the iterate solves
//! `(I − M) e = z`, so `|e_i| ≤ |z_i| + q_i ‖z‖∞ / (1 − max q)` (a rigorous bound, which grows
//! as 1/(1 − ρ) for reflectance near 1). The solve stops once that bound is below
//! [`SolveParams::noise`] times every patch's standard error (its first bounce's spread between
//! the replicas, a lower bound on the σ reported, measured at the iterate and lowered by what
//! the remaining error can change it), or below [`SolveParams::precision`] times its radiance
//! (patches without noise, a furnace); solved on pieces, each piece is held to its group's
//! standard error, the error bar of every answer that reads it; reaching the relative residual
//! [`SolveParams::tolerance`] also stops it, so it never costs more than that. At the default
//! 5% the answer moves by less than 0.05σ, by the bound, and in practice by 0.002σ to 0.01σ
//! against a solve to 1e-10 (`tests/solve.rs`).
//!
//! The replicas stop at a relative residual of `REPLICA_TOLERANCE` alone: they start from
//! the pooled answer, so a replica stopped early is too close to it and narrows the spread,
//! and the rigorous bound, loose by a few iterations, would cost twice the iterations. At 1e-5
//! the error bars are within 2.4% of those of replicas solved to 1e-6 on every patch of the
//! spheres sample (median 0.01%), against 20% at 1e-4. Their vectors are `f32` (`Real`).
//!
//! The three channels share `S`: they are solved together, one pass over the rows updating
//! three vectors, the rows split between threads when the system is large (a static scene is
//! one frame). A solve can start from a nearby solution (the previous frame,
//! [`solve_lit_from`]); the replicas start from the pooled one.
//!
//! A solve that stops at its iteration cap is no answer: [`FrameSolution::converged`] says so and
//! [`FrameSolution::ensure_converged`] turns it into an error, which fails the bake or the job.
//! The replica solves only measure the spread: when the pooled solve did not converge they are
//! skipped, and a replica that stops at the cap (at its looser tolerance) is left out of the
//! spread, so the error bar is the others' spread over the square root of their number: wider
//! in expectation, never narrowed by a replica that did not move, and the pooled answer stands.

pub mod analytic;
pub mod information;
pub mod tally;

use rayon::prelude::*;
use serde::Serialize;

use crate::scene::Material;
use tally::{ABSORBED, FrameTally, HIDDEN, MAX_PATCHES, SKY};

/// How to solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveParams {
    /// Radiance of everything outside the scene, RGB, in emission units.
    pub sky: [f64; 3],
    /// Stop at the latest when the residual has fallen to this fraction of the right-hand side
    /// (`|r| / |b|`), whatever the noise.
    pub tolerance: f64,
    /// Stop as soon as a bound on every patch's remaining error is below this fraction of its
    /// standard error (module docs): the answer then moves by less than that share of its own
    /// noise however long the solve goes on.
    pub noise: f64,
    /// Or below this fraction of its radiance: the stop for patches whose estimate has no noise
    /// (every segment from them ends on equal radiance, as in a furnace).
    pub precision: f64,
    /// Give up after this many iterations per channel: the frame is then not converged, and
    /// the bake and the service fail it rather than answer with it.
    pub max_iterations: usize,
}

impl Default for SolveParams {
    fn default() -> Self {
        Self {
            sky: [0.0; 3],
            tolerance: 1e-10,
            noise: 0.05,
            precision: 1e-8,
            max_iterations: 20_000,
        }
    }
}

/// The radiosity of one frame.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FrameSolution {
    /// Outgoing radiance per patch, RGB, in the units of the scene's emission.
    pub radiance: Vec<[f64; 3]>,
    /// Standard error per patch and channel; `None` for a patch no line crossed (its radiance
    /// is then only its emission). A split bake's ([`crate::bake::Bake::split`]) also takes in
    /// the error of the pieces' shape ([`crate::bake::SHAPE_ERROR`]).
    pub stderr: Vec<Option<[f64; 3]>>,
    /// A split bake's pieces' radiance ([`crate::bake::Bake::split`]; empty otherwise), which
    /// the outputs' points read where a gather ray lands. Not written out: a solution read
    /// back from disk has none, and its points read the patches.
    #[serde(skip)]
    pub pieces: Vec<[f32; 3]>,
    /// With [`FrameSolution::pieces`], each patch's error bar from the lines alone (without
    /// the pieces' shape term, which a reading of the pieces does not have).
    #[serde(skip)]
    pub pieces_stderr: Vec<[f32; 3]>,
    /// With [`FrameSolution::pieces`], per patch its pieces' mean and the mean of its pieces
    /// one level coarser at the frame where both were last solved (this one, or the first of
    /// its run's): the shape term of its error bar ([`crate::bake::SHAPE_ERROR`]), which the
    /// run's later frames carry.
    #[serde(skip)]
    pub shape: Vec<[[f32; 3]; 2]>,
    /// Per patch and channel, how its error from the lines (the replicas' spread) stood to the
    /// first bounce's spread and to its radiance at the frame the replicas were last solved
    /// (this one, or the first of its run's): `[e / first, 0]`, or `[0, e / radiance]` where
    /// the first bounce had no spread; `None` where the replicas gave no error. A run's later
    /// frames carry it ([`Spread::Carried`]).
    #[serde(skip)]
    pub spread: Vec<[Option<[f32; 2]>; 3]>,
    /// Per patch, the first bounce's spread at this answer (the lower bound of its error
    /// bar): the next frame of its run takes it as its noise test's first guess. Dropped
    /// with [`FrameSolution::shape`].
    #[serde(skip)]
    pub first: Vec<[f64; 3]>,
    /// Crossings of each patch by the lines, where a surface touches it included (0:
    /// unsampled), in global lines (a gap's denser lines count a fraction each).
    pub samples: Vec<u64>,
    /// Conjugate-gradient iterations, most over the channels.
    pub iterations: usize,
    /// Relative residual reached, worst over the channels.
    pub residual: f64,
    /// Whether every channel stopped by its criterion (noise, precision or tolerance) rather
    /// than at the iteration cap or a breakdown.
    pub converged: bool,
}

impl FrameSolution {
    /// Bytes kept per patch: radiance, standard error and samples.
    pub const BYTES_PER_PATCH: usize =
        size_of::<[f64; 3]>() + size_of::<Option<[f64; 3]>>() + size_of::<u64>();

    /// The memory it holds.
    #[must_use]
    pub fn bytes(&self) -> usize {
        size_of::<Self>()
            + self.radiance.len() * size_of::<[f64; 3]>()
            + self.stderr.len() * size_of::<Option<[f64; 3]>>()
            + self.samples.len() * size_of::<u64>()
            + (self.pieces.len() + self.pieces_stderr.len()) * size_of::<[f32; 3]>()
    }

    /// `Ok` if every channel converged; otherwise why frame `frame`, solved with
    /// `params`, is no answer.
    pub fn ensure_converged(&self, frame: usize, params: &SolveParams) -> Result<(), NotConverged> {
        if self.converged {
            return Ok(());
        }
        Err(NotConverged {
            frame,
            residual: self.residual,
            iterations: self.iterations,
            tolerance: params.tolerance,
        })
    }

    /// Appends the frame's arrays, little-endian: P×3 f32 radiance, P×3 f32 standard error
    /// (−1 where the patch was not sampled), P u32 sample counts. The layout of the service's
    /// binary frames and of `radiance.bin`.
    pub fn write_f32(&self, out: &mut Vec<u8>) {
        for l in &self.radiance {
            l.iter()
                .for_each(|&c| out.extend_from_slice(&(c as f32).to_le_bytes()));
        }
        for e in &self.stderr {
            e.unwrap_or([-1.0; 3])
                .iter()
                .for_each(|&c| out.extend_from_slice(&(c as f32).to_le_bytes()));
        }
        for &n in &self.samples {
            out.extend_from_slice(&(n.min(u64::from(u32::MAX)) as u32).to_le_bytes());
        }
    }
}

/// Why a frame's radiance is no answer: its solve stopped before reaching the tolerance.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error(
    "frame {frame} did not converge: relative residual {residual:.3e} after {iterations} \
     iterations (tolerance {tolerance:e}); a closed scene whose reflectance is near 1 has no \
     steady state (see max_reflectance)"
)]
pub struct NotConverged {
    /// The frame.
    pub frame: usize,
    /// Relative residual reached, worst over the channels (infinite if the light overflowed).
    pub residual: f64,
    /// Iterations done, most over the channels.
    pub iterations: usize,
    /// The tolerance it did not reach.
    pub tolerance: f64,
}

/// Solves one frame: `materials[patch_material[i]]` gives each patch's reflectance and
/// emission.
#[must_use]
pub fn solve(
    tally: &FrameTally,
    patch_material: &[u32],
    materials: &[Material],
    params: &SolveParams,
) -> FrameSolution {
    solve_lit(tally, patch_material, materials, params, None)
}

/// The light that reaches each patch straight from its sources, computed apart from the lines:
/// punctual lights ([`crate::direct`]) and sampled emitting surfaces ([`crate::direct::area`]).
#[derive(Clone, Copy, Debug)]
pub struct Direct<'a> {
    /// Irradiance of each patch, RGB (it leaves patch i as the radiance ρ_i·E_i/π).
    pub irradiance: &'a [[f64; 3]],
    /// The variance of that irradiance from its sampling.
    pub variance: &'a [[f64; 3]],
    /// Per patch: whether its emission reaches the others through `irradiance` (a sampled
    /// emitter) rather than through the lines, which then carry only the light it reflects.
    pub sampled: &'a [bool],
    /// Per patch, the share of its area that no surface touches at the frame (a floor patch
    /// partly under a box), if any is less than whole: `irradiance` is that of the visible
    /// part, and pieces answered together ([`Groups`]) weigh by their visible area.
    pub visible: Option<&'a [f64]>,
}

/// [`solve`] with `direct` light: each patch's ρ_i·E_i/π is added to its emission as the light
/// the interreflection starts from, and the lines carry `L_j − Le_j` from the sampled emitters
/// (`L = Le + ρE/π + ρ Σ_j F_ij (L_j − [j sampled] Le_j)`: their emission is never counted
/// twice). The irradiance's variance is added to each patch's error bar (as `ρ²·var/π²`).
#[must_use]
pub fn solve_lit(
    tally: &FrameTally,
    patch_material: &[u32],
    materials: &[Material],
    params: &SolveParams,
    direct: Option<Direct<'_>>,
) -> FrameSolution {
    solve_lit_from(tally, patch_material, materials, params, direct, None)
}

/// [`solve_lit`] starting from `start`, the radiance of a nearby solution (the frame before, in
/// an animation) instead of the emission: the same answer to within the stopping criterion, in
/// fewer iterations.
#[must_use]
pub fn solve_lit_from(
    tally: &FrameTally,
    patch_material: &[u32],
    materials: &[Material],
    params: &SolveParams,
    direct: Option<Direct<'_>>,
    start: Option<&[[f64; 3]]>,
) -> FrameSolution {
    solve_grouped(
        tally,
        patch_material,
        materials,
        params,
        direct,
        start,
        (None, Spread::Replicas, None),
    )
}

/// The patches a solve answers for, each the group of some of the patches it solves (the
/// pieces of [`crate::bake::Bake::split`]): the answer for a group is the mean of its pieces
/// over its area, and its error bar the spread of that mean between the replicas.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct Groups {
    /// The group of each piece.
    of: Vec<u32>,
    /// Each piece's area (weighs what the lines do not sample: its emission and direct light).
    area: Vec<f64>,
    /// Each group's pieces: `members[offsets[g]..offsets[g + 1]]`.
    offsets: Vec<usize>,
    members: Vec<u32>,
}

impl Groups {
    /// Groups of `count` patches, piece `k` in group `of[k]` with area `area[k]`.
    #[must_use]
    pub fn new(of: Vec<u32>, area: Vec<f64>, count: usize) -> Self {
        let mut offsets = vec![0usize; count + 1];
        for &g in &of {
            offsets[g as usize + 1] += 1;
        }
        for g in 0..count {
            offsets[g + 1] += offsets[g];
        }
        let mut next = offsets.clone();
        let mut members = vec![0u32; of.len()];
        for (k, &g) in of.iter().enumerate() {
            members[next[g as usize]] = k as u32;
            next[g as usize] += 1;
        }
        Self {
            of,
            area,
            offsets,
            members,
        }
    }

    /// Groups.
    #[must_use]
    pub fn len(&self) -> usize {
        self.offsets.len() - 1
    }

    /// Whether there are no groups.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The group of each piece.
    #[must_use]
    pub fn of(&self) -> &[u32] {
        &self.of
    }

    /// Group `g`'s pieces.
    fn members(&self, g: usize) -> &[u32] {
        &self.members[self.offsets[g]..self.offsets[g + 1]]
    }

    /// Each group's mean of its pieces' `values` weighed by their areas (what one sampling
    /// over the whole group estimates, when each piece's value is a mean over the piece), and
    /// that mean's variance from the pieces' `variances` (sampled independently).
    #[must_use]
    pub fn area_mean(
        &self,
        values: &[[f64; 3]],
        variances: &[[f64; 3]],
    ) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        (0..self.len())
            .map(|g| {
                let members = self.members(g);
                let total: f64 = members.iter().map(|&k| self.area[k as usize]).sum();
                let (mut mean, mut variance) = ([0.0; 3], [0.0; 3]);
                for &k in members {
                    let k = k as usize;
                    let w = if total > 0.0 {
                        self.area[k] / total
                    } else {
                        0.0
                    };
                    for c in 0..3 {
                        mean[c] += w * values[k][c];
                        variance[c] += w * w * variances[k][c];
                    }
                }
                (mean, variance)
            })
            .unzip()
    }

    /// Bytes it holds.
    #[must_use]
    pub fn bytes(&self) -> usize {
        self.of.len() * (2 * size_of::<u32>() + size_of::<f64>())
            + self.offsets.len() * size_of::<usize>()
    }

    /// Each group's radiance from its pieces' `values`: what the lines do not carry (`source`:
    /// emission and direct light) averaged over the pieces' visible area (`visible`: the share
    /// of each piece no surface touches, all of it if `None`), and what they gather
    /// (`values − source`) over their `crossings` (of their visible parts), as one patch of
    /// them all would gather it. A piece no line crossed then weighs nothing in the gathered
    /// light, rather than counting as dark, and a piece a box covers nothing at all.
    fn mean<T: Copy + Into<f64>>(
        &self,
        values: &[[T; 3]],
        (source, visible): (&[[f64; 3]], Option<&[f64]>),
        crossings: &[u64],
    ) -> Vec<[f64; 3]> {
        (0..self.len())
            .map(|g| {
                let (mut area, mut lines) = (0.0, 0.0);
                let (mut sourced, mut gathered) = ([0.0; 3], [0.0; 3]);
                for &k in self.members(g) {
                    let k = k as usize;
                    let share = visible.map_or(1.0, |v| v[k]);
                    let (a, n) = (self.area[k] * share, crossings[k] as f64);
                    area += a;
                    lines += n;
                    for c in 0..3 {
                        sourced[c] += a * source[k][c];
                        gathered[c] += n * (values[k][c].into() - source[k][c]);
                    }
                }
                std::array::from_fn(|c| {
                    let s = if area > 0.0 { sourced[c] / area } else { 0.0 };
                    s + if lines > 0.0 {
                        gathered[c] / lines
                    } else {
                        0.0
                    }
                })
            })
            .collect()
    }

    /// Each group's variance of the direct light's sampling (`variance` per piece, of its
    /// reflected radiance), as [`Groups::mean`] weighs it (by visible area).
    fn direct_variance(&self, variance: &[[f64; 3]], visible: Option<&[f64]>) -> Vec<[f64; 3]> {
        let area = |k: u32| self.area[k as usize] * visible.map_or(1.0, |v| v[k as usize]);
        (0..self.len())
            .map(|g| {
                let members = self.members(g);
                let total: f64 = members.iter().map(|&k| area(k)).sum();
                std::array::from_fn(|c| {
                    members
                        .iter()
                        .map(|&k| {
                            let w = if total > 0.0 { area(k) / total } else { 0.0 };
                            w * w * variance[k as usize][c]
                        })
                        .sum()
                })
            })
            .collect()
    }
}

/// [`solve_lit_from`] answering for `groups` of the tally's patches, if given: the pieces are
/// solved, each group answered by the mean of its pieces ([`Groups`]), its error bar from the
/// replicas' means (or as `spread` says). The solve then stops when no piece can move by more
/// than `noise` of its group's standard error (its first bounce's spread, measured over the
/// group's pieces): the group's answer, a mean of its pieces, then moves by no more than that,
/// and so does any answer read from a piece (the outputs' gather, whose error bar is its
/// group's).
#[must_use]
pub fn solve_grouped(
    tally: &FrameTally,
    patch_material: &[u32],
    materials: &[Material],
    params: &SolveParams,
    direct: Option<Direct<'_>>,
    start: Option<&[[f64; 3]]>,
    (groups, spread, guess): (Option<&Groups>, Spread<'_>, Option<&[[f64; 3]]>),
) -> FrameSolution {
    let setup = (tally, patch_material, materials, params);
    solve_with(setup, direct, (start, guess), groups, spread)
}

/// How a solve measures each answer's error from the lines.
#[derive(Clone, Copy, Debug)]
pub enum Spread<'a> {
    /// The first bounce's spread alone (a lower bound).
    FirstBounce,
    /// The spread of the 16 replicas' solutions (module docs).
    Replicas,
    /// The first bounce's spread at this frame times what the replicas made of it at a nearby
    /// frame ([`FrameSolution::spread`] of a run's first frame): the later bounces widen the
    /// first one's spread by what the scene's transport does, which a moving object changes
    /// little from frame to frame, while the first bounce's spread is this frame's own. At a
    /// sixteenth of the replicas' cost.
    Carried(&'a [[Option<[f32; 2]>; 3]]),
}

/// [`solve_lit_from`] without the replicas: the answer, with the first bounce's spread alone
/// as its error bar (a lower bound), at a sixteenth of the cost.
#[must_use]
pub fn solve_answer(
    tally: &FrameTally,
    patch_material: &[u32],
    materials: &[Material],
    params: &SolveParams,
    direct: Option<Direct<'_>>,
    start: Option<&[[f64; 3]]>,
) -> FrameSolution {
    let setup = (tally, patch_material, materials, params);
    solve_with(setup, direct, (start, None), None, Spread::FirstBounce)
}

/// An RGB value per patch.
type PerPatch = [[f64; 3]];

/// [`solve_grouped`], with the replicas' error bars or not.
fn solve_with(
    (tally, patch_material, materials, params): (&FrameTally, &[u32], &[Material], &SolveParams),
    direct: Option<Direct<'_>>,
    (start, guess): (Option<&[[f64; 3]]>, Option<&PerPatch>),
    groups: Option<&Groups>,
    spread: Spread<'_>,
) -> FrameSolution {
    let patches = patch_material.len();
    let rho: Vec<[f64; 3]> = patch_material
        .iter()
        .map(|&m| materials[m as usize].reflectance)
        .collect();
    let emission: Vec<[f64; 3]> = patch_material
        .iter()
        .enumerate()
        .map(|(i, &m)| {
            let material = &materials[m as usize];
            std::array::from_fn(|c| {
                let reflected = direct.map_or(0.0, |d| {
                    material.reflectance[c] * d.irradiance[i][c] * std::f64::consts::FRAC_1_PI
                });
                material.emission[c] + reflected
            })
        })
        .collect();
    // The emission the lines do not carry: the sampled emitters'.
    let seen: Vec<[f64; 3]> = patch_material
        .iter()
        .enumerate()
        .map(|(i, &m)| match direct {
            Some(d) if d.sampled[i] => materials[m as usize].emission,
            _ => [0.0; 3],
        })
        .collect();
    let system = System::new(tally, &rho);
    let stop = Stop {
        tolerance: params.tolerance,
        max_iterations: params.max_iterations,
        noise: params.noise,
        precision: params.precision,
        groups,
        guess: guess.filter(|g| g.len() == groups.map_or(patches, Groups::len)),
    };
    let light = system.solve::<f64>(&emission, &seen, params.sky, start, &stop);
    let converged = light.converged.iter().all(|&c| c);
    // The spread of each patch's own first bounce, which low sample counts can hide from the
    // replicas' spread.
    let first = system.first_bounce(&light.values, &seen, params.sky, groups);
    let answered = groups.map_or(patches, Groups::len);
    // Replicas of a solve that is no answer would measure nothing: skip them.
    let error = if converged && matches!(spread, Spread::Replicas) {
        let replicas = Replicas {
            rho: &rho,
            emission: &emission,
            seen: &seen,
            pooled: &light.values,
            groups,
            visible: direct.and_then(|d| d.visible),
        };
        replica_errors(tally, &replicas, params)
    } else {
        vec![[None; 3]; answered]
    };
    // The direct light's own sampling error (of the radiance it reflects), independent of the
    // lines'.
    let sampled: Vec<[f64; 3]> = (0..patches)
        .map(|i| {
            std::array::from_fn(|c| {
                direct.map_or(0.0, |d| {
                    d.variance[i][c] * (rho[i][c] * std::f64::consts::FRAC_1_PI).powi(2)
                })
            })
        })
        .collect();
    // A patch's samples: the crossings of its visible part and of its hidden one. It has an
    // answer if the lines crossed its visible part, or if a surface covers it whole (a box's
    // bottom on the floor: known black); a part left to see that no line crossed is
    // unsampled, though crossings of its hidden part were counted.
    let visible = direct.and_then(|d| d.visible);
    // In global lines (a dense region's crossings count a fraction each), at least one for a
    // patch any line crossed.
    let samples = |k: usize| (tally.crossings[k] + tally.hidden[k]).div_ceil(tally.unit.max(1));
    let answer = |members: &mut dyn Iterator<Item = usize>| {
        let (mut seen, mut hidden, mut open) = (0, 0, 0.0);
        for k in members {
            seen += tally.crossings[k];
            hidden += tally.hidden[k];
            open += visible.map_or(0.0, |v| v[k]);
        }
        seen > 0 || (hidden > 0 && open == 0.0)
    };
    let mut pieces: Vec<[f32; 3]> = match groups {
        Some(_) => (light.values.iter()).map(|l| l.map(|x| x as f32)).collect(),
        None => Vec::new(),
    };
    let (mut radiance, sampled, crossings, unknown, answered_by) = match groups {
        None => {
            let unknown: Vec<[bool; 3]> = (0..patches)
                .map(|i| std::array::from_fn(|c| system.unknown(i, c)))
                .collect();
            let answered_by: Vec<bool> = (0..patches)
                .map(|i| answer(&mut std::iter::once(i)))
                .collect();
            let crossings = (0..patches).map(samples).collect();
            (light.values, sampled, crossings, unknown, answered_by)
        }
        Some(g) => {
            let radiance = g.mean(&light.values, (&emission, visible), &tally.crossings);
            let members = |h: usize| g.members(h).iter().map(|&k| k as usize);
            let crossings: Vec<u64> = (0..g.len())
                .map(|h| members(h).map(samples).sum())
                .collect();
            let answered_by: Vec<bool> = (0..g.len()).map(|h| answer(&mut members(h))).collect();
            let unknown = (0..g.len())
                .map(|h| {
                    std::array::from_fn(|c| {
                        g.members(h).iter().any(|&k| system.unknown(k as usize, c))
                    })
                })
                .collect();
            let sampled = g.direct_variance(&sampled, visible);
            (radiance, sampled, crossings, unknown, answered_by)
        }
    };
    // What the replicas made of the first bounce's spread, measured or carried.
    let (error, spread) = match spread {
        Spread::Carried(carried) if converged && carried.len() == answered => {
            let error = (0..answered)
                .map(|i| {
                    std::array::from_fn(|c| {
                        carried[i][c].map(|[by_first, by_radiance]| {
                            first[i][c] * f64::from(by_first)
                                + radiance[i][c].abs() * f64::from(by_radiance)
                        })
                    })
                })
                .collect();
            (error, carried.to_vec())
        }
        _ => {
            let spread = (0..answered)
                .map(|i| {
                    std::array::from_fn(|c| {
                        error[i][c].map(|e| {
                            if first[i][c] > 0.0 {
                                [(e / first[i][c]) as f32, 0.0]
                            } else if radiance[i][c] != 0.0 {
                                [0.0, (e / radiance[i][c].abs()) as f32]
                            } else {
                                [0.0; 2]
                            }
                        })
                    })
                })
                .collect();
            (error, spread)
        }
    };
    // Radiance is never negative: an answer within the solve's tolerance of 0 (a patch no
    // light reaches, a mean of pieces that are) can round below it, by 1e-13.
    radiance.iter_mut().for_each(|v| *v = v.map(|c| c.max(0.0)));
    pieces.iter_mut().for_each(|v| *v = v.map(|c| c.max(0.0)));
    let stderr = (0..answered)
        .map(|i| {
            answered_by[i].then(|| {
                std::array::from_fn(|c| {
                    if !unknown[i][c] {
                        return 0.0;
                    }
                    // The spread of the replicas' solutions, and never less than the first
                    // bounce's.
                    let lines = error[i][c].map_or(first[i][c], |e: f64| e.max(first[i][c]));
                    (lines * lines + sampled[i][c]).sqrt()
                })
            })
        })
        .collect();
    FrameSolution {
        radiance,
        stderr,
        pieces,
        pieces_stderr: Vec::new(),
        shape: Vec::new(),
        spread,
        first,
        samples: crossings,
        iterations: light.iterations,
        residual: light.residual.iter().copied().fold(0.0, f64::max),
        converged,
    }
}

/// The fewest replicas (line groups) whose crossings of a patch tell its error: with fewer,
/// the replicas give none, and the first bounce's error is the light gathered itself.
const MIN_GROUPS: usize = 4;

/// The replicas stop at this relative residual (module docs): they measure a spread, not an
/// answer.
const REPLICA_TOLERANCE: f64 = 1e-5;

/// Standard errors from the independent replicas of the lines (METHOD.md §6): each replica's
/// tallies alone give a full solution (warm-started from the `pooled` one, stopped at the
/// relative residual [`REPLICA_TOLERANCE`]), and the spread of those solutions, divided by √K,
/// is the error of their pooled mean. It carries every bounce and every correlation between
/// patches. `None` for a patch fewer than [`MIN_GROUPS`] replicas crossed. A replica channel that stops at
/// the iteration cap is left out (its values, still near the pooled ones it started from,
/// would narrow the spread): the others' spread over √(their number) is wider in expectation.
fn replica_errors(
    tally: &FrameTally,
    replicas: &Replicas<'_>,
    params: &SolveParams,
) -> Vec<[Option<f64>; 3]> {
    let Replicas {
        rho,
        emission,
        seen,
        pooled,
        groups,
        visible,
    } = *replicas;
    let patches = rho.len();
    let stop = Stop {
        tolerance: REPLICA_TOLERANCE,
        max_iterations: params.max_iterations,
        noise: 0.0,
        precision: 0.0,
        groups: None,
        guess: None,
    };
    // The replicas are solved in parallel (a frame alone, as a static scene is, then uses every
    // core), and summed in their order: the result does not depend on the thread count. With
    // groups, each replica's answer is its groups' means (weighed by the pooled crossings).
    // Per replica: which values it solved for, its values and which channels converged.
    type Replica = (Vec<[bool; 3]>, Vec<[f64; 3]>, [bool; 3]);
    let solved: Vec<Replica> = tally
        .replicas()
        .par_iter()
        .map(|replica| {
            let system = System::new(replica, rho);
            let solved = system.solve::<f32>(emission, seen, params.sky, Some(pooled), &stop);
            let unknown: Vec<[bool; 3]> = (0..patches)
                .map(|i| std::array::from_fn(|c| system.unknown(i, c)))
                .collect();
            match groups {
                None => (unknown, solved.values, solved.converged),
                Some(g) => {
                    let values = g.mean(&solved.values, (emission, visible), &tally.crossings);
                    let unknown = (0..g.len())
                        .map(|h| {
                            std::array::from_fn(|c| {
                                g.members(h).iter().any(|&k| unknown[k as usize][c])
                            })
                        })
                        .collect();
                    (unknown, values, solved.converged)
                }
            }
        })
        .collect();
    let answered = groups.map_or(patches, Groups::len);
    let mut sum = vec![[0.0; 3]; answered];
    let mut sum_sq = vec![[0.0; 3]; answered];
    let mut count = vec![[0usize; 3]; answered];
    for (unknown, values, converged) in &solved {
        for i in 0..answered {
            for c in 0..3 {
                if unknown[i][c] && converged[c] {
                    let v = values[i][c];
                    sum[i][c] += v;
                    sum_sq[i][c] += v * v;
                    count[i][c] += 1;
                }
            }
        }
    }
    (0..answered)
        .map(|i| {
            std::array::from_fn(|c| {
                let k = count[i][c] as f64;
                (count[i][c] >= MIN_GROUPS).then(|| {
                    let mean = sum[i][c] / k;
                    let variance = ((sum_sq[i][c] - k * mean * mean) / (k - 1.0)).max(0.0);
                    (variance / k).sqrt()
                })
            })
        })
        .collect()
}

/// What [`replica_errors`] solves again: the pooled solve's system (reflectances, emission and
/// the emission the lines do not carry), its answer to start from, and the groups answered.
#[derive(Clone, Copy)]
struct Replicas<'a> {
    rho: &'a [[f64; 3]],
    emission: &'a [[f64; 3]],
    seen: &'a [[f64; 3]],
    pooled: &'a [[f64; 3]],
    groups: Option<&'a Groups>,
    visible: Option<&'a [f64]>,
}

/// When conjugate gradients stop (see the module docs).
struct Stop<'g> {
    /// Relative residual that stops a channel whatever the noise.
    tolerance: f64,
    /// Iterations after which a channel gives up, not converged.
    max_iterations: usize,
    /// [`SolveParams::noise`].
    noise: f64,
    /// [`SolveParams::precision`].
    precision: f64,
    /// The groups answered for, if the unknowns are pieces: each piece is then held to its
    /// group's standard error, the error bar of every answer that reads it.
    groups: Option<&'g Groups>,
    /// The first bounce's spread per answered patch at a nearby frame's answer (the one the
    /// solve starts from, [`FrameSolution::first`]): the noise test's guess of this frame's
    /// until it measures its own, where a cold start measures it at the start.
    guess: Option<&'g [[f64; 3]]>,
}

/// The precision of a solve's working vectors: `f64` for the answer; `f32` for the replicas,
/// which stop at a relative residual of [`REPLICA_TOLERANCE`], far above `f32`'s 6e-8, and
/// move half the bytes (their iterations are bound by memory traffic, not arithmetic). Sums,
/// dot products and the steps' coefficients are `f64` either way.
trait Real: Copy + Send + Sync + 'static {
    fn of(v: f64) -> Self;
    fn get(self) -> f64;
}

impl Real for f64 {
    fn of(v: f64) -> Self {
        v
    }
    fn get(self) -> f64 {
        self
    }
}

impl Real for f32 {
    fn of(v: f64) -> Self {
        v as f32
    }
    fn get(self) -> f64 {
        f64::from(self)
    }
}

/// Rows per unit of parallel work: systems smaller than this are applied on one thread.
const ROWS: usize = 2048;

/// `out[i] = f(i)` for every row, split between threads when there are many.
fn for_rows<T: Send>(out: &mut [T], f: impl Fn(usize) -> T + Sync) {
    if out.len() <= ROWS {
        out.iter_mut().enumerate().for_each(|(i, o)| *o = f(i));
    } else {
        out.par_chunks_mut(ROWS).enumerate().for_each(|(k, chunk)| {
            for (o, v) in chunk.iter_mut().enumerate() {
                *v = f(k * ROWS + o);
            }
        });
    }
}

/// Per channel, `Σ_i a_i·b_i`.
fn dots(a: &[[f64; 3]], b: &[[f64; 3]]) -> [f64; 3] {
    a.iter().zip(b).fold([0.0; 3], |mut s, (x, y)| {
        (0..3).for_each(|c| s[c] += x[c] * y[c]);
        s
    })
}

/// The three channels' systems of one tally: `S` is shared, the diagonal is per channel.
struct System<'a> {
    tally: &'a FrameTally,
    rho: &'a [[f64; 3]],
    /// Diagonal `N_i / ρ_i` where patch i is solved for in a channel (crossed by some line and
    /// reflecting in it), 0 elsewhere.
    diagonal: Vec<[f64; 3]>,
    /// Row sums `q_i = ρ_i Σ_j S_ij / N_i` of the transport among the unknowns: how far a
    /// residual spreads into error (module docs).
    coupling: Vec<[f64; 3]>,
    /// The largest row sum per channel.
    max_coupling: [f64; 3],
}

/// A solve's outcome, per channel.
struct Solved {
    /// Radiance per patch (the emission where a patch is not solved for).
    values: Vec<[f64; 3]>,
    /// Iterations, most over the channels.
    iterations: usize,
    residual: [f64; 3],
    converged: [bool; 3],
}

impl<'a> System<'a> {
    fn new(tally: &'a FrameTally, rho: &'a [[f64; 3]]) -> Self {
        let n = rho.len();
        let mut diagonal = vec![[0.0; 3]; n];
        for_rows(&mut diagonal, |i| {
            let crossings = tally.crossings[i] as f64;
            rho[i].map(|r| {
                if crossings > 0.0 && r > 0.0 {
                    crossings / r
                } else {
                    0.0
                }
            })
        });
        let mut coupling = vec![[0.0; 3]; n];
        let diagonal_ref = &diagonal;
        for_rows(&mut coupling, |i| {
            let mut sum = [0.0; 3];
            if diagonal_ref[i] != [0.0; 3] {
                for (j, s) in Self::row_of(tally, i) {
                    if (j as usize) < MAX_PATCHES {
                        let d = diagonal_ref[j as usize];
                        (0..3).for_each(|c| {
                            if d[c] > 0.0 {
                                sum[c] += s;
                            }
                        });
                    }
                }
            }
            std::array::from_fn(|c| {
                if diagonal_ref[i][c] > 0.0 {
                    rho[i][c] * sum[c] / tally.crossings[i] as f64
                } else {
                    0.0
                }
            })
        });
        let max_coupling = coupling
            .iter()
            .fold([0.0f64; 3], |m, q| std::array::from_fn(|c| m[c].max(q[c])));
        Self {
            tally,
            rho,
            diagonal,
            coupling,
            max_coupling,
        }
    }

    /// Whether patch i is solved for in channel c.
    fn unknown(&self, i: usize, c: usize) -> bool {
        self.diagonal[i][c] > 0.0
    }

    fn row_of(tally: &FrameTally, i: usize) -> impl Iterator<Item = (u32, f64)> + '_ {
        let (columns, counts) = tally.row(i);
        (columns.iter().copied()).zip(counts.iter().map(|&c| f64::from(c)))
    }

    /// [`System::apply`], returning `x·y` per channel (summed per chunk of rows, the chunks in
    /// their order).
    fn apply_dot<T: Real>(&self, x: &[[T; 3]], y: &mut [[T; 3]]) -> [f64; 3] {
        let sums: Vec<[f64; 3]> = y
            .par_chunks_mut(ROWS)
            .enumerate()
            .map(|(k, chunk)| {
                let mut sum = [0.0; 3];
                for (o, v) in chunk.iter_mut().enumerate() {
                    let i = k * ROWS + o;
                    let row = self.row(x, i);
                    (0..3).for_each(|c| sum[c] += row[c] * x[i][c].get());
                    *v = row.map(T::of);
                }
                sum
            })
            .collect();
        sums.iter().fold([0.0; 3], |mut s, v| {
            (0..3).for_each(|c| s[c] += v[c]);
            s
        })
    }

    /// Per channel among `check`, `‖z‖∞ / (1 − max q)` from `largest = ‖z‖∞`: the second term
    /// of the bound on the remaining error (module docs). Infinite for the others, and for a
    /// channel whose transport does not contract (`max q ≥ 1`, reflectance 1 in a closed scene),
    /// which has no such bound.
    fn bound(&self, largest: [f64; 3], check: [bool; 3]) -> [f64; 3] {
        std::array::from_fn(|c| {
            if check[c] && self.max_coupling[c] < 1.0 {
                largest[c] / (1.0 - self.max_coupling[c])
            } else {
                f64::INFINITY
            }
        })
    }

    /// Row i of `A x` (see [`System::apply`]).
    fn row<T: Real>(&self, x: &[[T; 3]], i: usize) -> [f64; 3] {
        let d = self.diagonal[i];
        if d == [0.0; 3] {
            return [0.0; 3];
        }
        let xi = x[i];
        let mut sum = [d[0] * xi[0].get(), d[1] * xi[1].get(), d[2] * xi[2].get()];
        for (j, s) in Self::row_of(self.tally, i) {
            if (j as usize) < MAX_PATCHES {
                let xj = x[j as usize];
                sum[0] -= s * xj[0].get();
                sum[1] -= s * xj[1].get();
                sum[2] -= s * xj[2].get();
            }
        }
        std::array::from_fn(|c| if d[c] > 0.0 { sum[c] } else { 0.0 })
    }

    /// `y = A x` on the unknowns, the three channels in one pass over the rows; `x` is 0 where
    /// a patch is not solved for.
    fn apply<T: Real>(&self, x: &[[T; 3]], y: &mut [[f64; 3]]) {
        for_rows(y, |i| self.row(x, i));
    }

    /// Solves `L = Le + ρ F (L − seen) + ρ F_sky L_sky` for emission `le` (the known patches
    /// keep `L = Le`); `seen` is the emission the lines do not carry (sampled emitters'). Starts
    /// from `start` (a nearby solution) if given, else from the emission.
    fn solve<T: Real>(
        &self,
        le: &[[f64; 3]],
        seen: &[[f64; 3]],
        sky: [f64; 3],
        start: Option<&[[f64; 3]]>,
        stop: &Stop,
    ) -> Solved {
        let n = le.len();
        // The system is linear: each channel is solved scaled to O(1) whatever the emission's
        // magnitude (1e-30 or 1e30), and scaled back.
        let scale: [f64; 3] =
            std::array::from_fn(|c| le.iter().fold(sky[c].abs(), |m, v| m.max(v[c].abs())));
        let solvable = scale.map(|s| s > 0.0 && s.is_finite());
        let scaled = |v: &[f64; 3]| -> [f64; 3] {
            std::array::from_fn(|c| if solvable[c] { v[c] / scale[c] } else { 0.0 })
        };
        let le_s: Vec<[f64; 3]> = le.iter().map(scaled).collect();
        let seen_s: Vec<[f64; 3]> = seen.iter().map(scaled).collect();
        let sky_s = scaled(&sky);
        let mut b = vec![[0.0; 3]; n];
        for_rows(&mut b, |i| {
            let d = self.diagonal[i];
            let mut bi = [0.0; 3];
            if d == [0.0; 3] {
                return bi;
            }
            for c in 0..3 {
                bi[c] = d[c] * le_s[i][c];
            }
            for (j, s) in Self::row_of(self.tally, i) {
                for c in 0..3 {
                    bi[c] += s * match j {
                        SKY => sky_s[c],
                        ABSORBED | HIDDEN => 0.0,
                        j if !self.unknown(j as usize, c) => {
                            le_s[j as usize][c] - seen_s[j as usize][c]
                        }
                        j => -seen_s[j as usize][c],
                    };
                }
            }
            std::array::from_fn(|c| if d[c] > 0.0 { bi[c] } else { 0.0 })
        });
        let x0: Vec<[T; 3]> = (0..n)
            .map(|i| {
                std::array::from_fn(|c| {
                    T::of(match start {
                        _ if !self.unknown(i, c) || !solvable[c] => 0.0,
                        Some(s) => s[i][c] / scale[c],
                        None => le_s[i][c],
                    })
                })
            })
            .collect();
        let problem = Scaled {
            b: &b,
            le: &le_s,
            seen: &seen_s,
            sky: sky_s,
        };
        // A nearby frame's first-bounce spread, in this solve's scale: the noise test's guess.
        let guess = (stop.guess).map(|g| {
            (g.iter())
                .map(|s| std::array::from_fn(|c| if solvable[c] { s[c] / scale[c] } else { 0.0 }))
                .collect()
        });
        let (x, iterations, mut residual, mut converged) =
            self.conjugate_gradients(&problem, (x0, guess), solvable, stop);
        let mut values = le.to_vec();
        for (i, v) in values.iter_mut().enumerate() {
            for c in 0..3 {
                if solvable[c] && self.unknown(i, c) {
                    v[c] = x[i][c].get() * scale[c];
                }
            }
        }
        for c in 0..3 {
            if !solvable[c] {
                // Nothing to solve (no light at all), or light beyond f64 (no answer).
                converged[c] = scale[c] == 0.0;
                residual[c] = if converged[c] { 0.0 } else { f64::INFINITY };
            }
        }
        Solved {
            values,
            iterations,
            residual,
            converged,
        }
    }

    /// Diagonally preconditioned conjugate gradients from `x`, the channels in step; a channel
    /// stops as [`Stop`] says and its values stay as they are while the others go on.
    fn conjugate_gradients<T: Real>(
        &self,
        problem: &Scaled<'_>,
        (mut x, guess): (Vec<[T; 3]>, Option<Vec<[f64; 3]>>),
        solvable: [bool; 3],
        stop: &Stop,
    ) -> (Vec<[T; 3]>, usize, [f64; 3], [bool; 3]) {
        let n = x.len();
        let b = problem.b;
        let mut ax = vec![[0.0; 3]; n];
        self.apply(&x, &mut ax);
        let r: Vec<[f64; 3]> = ax
            .iter()
            .zip(b)
            .map(|(ai, bi)| std::array::from_fn(|c| bi[c] - ai[c]))
            .collect();
        let z: Vec<[f64; 3]> = r
            .iter()
            .zip(&self.diagonal)
            .map(|(r, d)| std::array::from_fn(|c| if d[c] > 0.0 { r[c] / d[c] } else { 0.0 }))
            .collect();
        let b_norm = dots(b, b).map(f64::sqrt);
        let mut residual = [0.0; 3];
        let mut converged = [false; 3];
        // Channels still iterating.
        let mut running = solvable;
        for c in 0..3 {
            if running[c] && b_norm[c] == 0.0 {
                // Nothing reaches the unknowns: they are dark.
                x.iter_mut().for_each(|v| v[c] = T::of(0.0));
                running[c] = false;
                converged[c] = true;
            }
        }
        let mut rz = dots(&r, &z);
        let mut rr = dots(&r, &r);
        let narrow = |v: Vec<[f64; 3]>| -> Vec<[T; 3]> { v.iter().map(|e| e.map(T::of)).collect() };
        let (mut r, mut z) = (narrow(r), narrow(z));
        let mut p = z.clone();
        let mut q = vec![[T::of(0.0); 3]; n];
        let mut noise = Noise::new(guess);
        let mut iteration = 0;
        // Per channel, the largest |z_i|.
        let mut largest = z.iter().fold([0.0f64; 3], |m, v| {
            std::array::from_fn(|c| m[c].max(v[c].get().abs()))
        });
        loop {
            let mut check = [false; 3];
            for c in 0..3 {
                if running[c] {
                    residual[c] = rr[c].sqrt() / b_norm[c];
                    if residual[c] <= stop.tolerance {
                        running[c] = false;
                        converged[c] = true;
                    } else {
                        check[c] = true;
                    }
                }
            }
            let bound = self.bound(largest, check);
            let quiet = noise.quiet(self, problem, &x, &z, bound, stop);
            for c in 0..3 {
                if quiet[c] {
                    running[c] = false;
                    converged[c] = true;
                }
            }
            if running == [false; 3] || iteration == stop.max_iterations {
                break;
            }
            let pq = self.apply_dot(&p, &mut q);
            let mut alpha = [0.0; 3];
            for c in 0..3 {
                if running[c] {
                    if pq[c] <= 0.0 || !pq[c].is_finite() {
                        // A breakdown: no answer.
                        running[c] = false;
                    } else {
                        alpha[c] = rz[c] / pq[c];
                    }
                }
            }
            // One pass: the step, the preconditioned residual and the next dot products, in
            // chunks on every core, the chunks' sums added in their order (the same answer
            // whatever the thread count).
            let diagonal = &self.diagonal;
            let sums: Vec<[[f64; 3]; 3]> = x
                .par_chunks_mut(ROWS)
                .zip(r.par_chunks_mut(ROWS))
                .zip(z.par_chunks_mut(ROWS))
                .zip(p.par_chunks(ROWS).zip(q.par_chunks(ROWS)))
                .enumerate()
                .map(|(k, (((x, r), z), (p, q)))| {
                    let mut sum = [[0.0; 3]; 3];
                    for o in 0..x.len() {
                        let d = diagonal[k * ROWS + o];
                        for c in 0..3 {
                            x[o][c] = T::of(x[o][c].get() + alpha[c] * p[o][c].get());
                            let ro = r[o][c].get() - alpha[c] * q[o][c].get();
                            let zo = if d[c] > 0.0 { ro / d[c] } else { 0.0 };
                            r[o][c] = T::of(ro);
                            z[o][c] = T::of(zo);
                            sum[0][c] += ro * zo;
                            sum[1][c] += ro * ro;
                            sum[2][c] = sum[2][c].max(zo.abs());
                        }
                    }
                    sum
                })
                .collect();
            let mut rz_next = [0.0; 3];
            let mut rr_next = [0.0; 3];
            largest = [0.0; 3];
            for sum in &sums {
                for c in 0..3 {
                    rz_next[c] += sum[0][c];
                    rr_next[c] += sum[1][c];
                    largest[c] = largest[c].max(sum[2][c]);
                }
            }
            rr = rr_next;
            let beta: [f64; 3] =
                std::array::from_fn(|c| if running[c] { rz_next[c] / rz[c] } else { 0.0 });
            rz = rz_next;
            p.par_chunks_mut(ROWS)
                .zip(z.par_chunks(ROWS))
                .for_each(|(p, z)| {
                    for (p, z) in p.iter_mut().zip(z) {
                        for c in 0..3 {
                            p[c] = T::of(z[c].get() + beta[c] * p[c].get());
                        }
                    }
                });
            iteration += 1;
        }
        (x, iteration, residual, converged)
    }

    /// `ρ_i` times the standard error of the mean radiance the lines carry from the far ends of
    /// the segments leaving patch i (`l − seen`; sky at `sky`, absorbed at 0), per channel,
    /// from the spread between the line groups: the ratio estimator `Σ_g Y_g / Σ_g X_g` (Y_g
    /// the radiance summed over group g's segments, X_g their number) has variance
    /// `K/(K−1) Σ_g (Y_g − m X_g)² / N²`. 0 where a patch is not solved for. Needs the per-group
    /// entries (the pooled tallies, not a replica's).
    fn first_bounce(
        &self,
        l: &[[f64; 3]],
        seen: &[[f64; 3]],
        sky: [f64; 3],
        groups: Option<&Groups>,
    ) -> Vec<[f64; 3]> {
        const K: usize = tally::GROUPS as usize;
        let answered = groups.map_or(l.len(), Groups::len);
        let mut out = vec![[0.0; 3]; answered];
        // What a segment to each patch carries, once: the per-group entries name it a few
        // times in a row (a column's groups), and every row names it.
        let carried: Vec<[f64; 3]> = (l.iter().zip(seen))
            .map(|(l, s)| std::array::from_fn(|c| l[c] - s[c]))
            .collect();
        for_rows(&mut out, |h| {
            let single = [h as u32];
            let members = groups.map_or(&single[..], |g| g.members(h));
            let (mut y, mut x) = ([[0.0; 3]; K], [0.0; K]);
            let mut solved = [false; 3];
            let mut rho = [0.0; 3];
            for &i in members {
                let i = i as usize;
                let d = self.diagonal[i];
                if d == [0.0; 3] {
                    continue;
                }
                (0..3).for_each(|c| solved[c] |= d[c] > 0.0);
                rho = self.rho[i];
                for &(j, g, count) in self.tally.group_row(i) {
                    let v = match j {
                        SKY => sky,
                        ABSORBED => [0.0; 3],
                        // Not a crossing of what can be seen of the patch (its `N_i`).
                        HIDDEN => continue,
                        j => carried[j as usize],
                    };
                    let w = f64::from(count);
                    (0..3).for_each(|c| y[g as usize][c] += w * v[c]);
                    x[g as usize] += w;
                }
            }
            let n: f64 = x.iter().sum();
            if n == 0.0 {
                return [0.0; 3];
            }
            let k = K as f64;
            // Crossings in fewer groups than the replicas need (a patch almost wholly under a
            // box, with one or two crossings left to see) tell no spread: the light they
            // gather is known to about itself.
            let few = x.iter().filter(|&&xg| xg > 0.0).count() < MIN_GROUPS;
            std::array::from_fn(|c| {
                if !solved[c] {
                    return 0.0;
                }
                let mean = y.iter().map(|yg| yg[c]).sum::<f64>() / n;
                if few {
                    return rho[c] * mean.abs();
                }
                let spread: f64 = y
                    .iter()
                    .zip(&x)
                    .map(|(yg, xg)| (yg[c] - mean * xg).powi(2))
                    .sum();
                rho[c] * (k / (k - 1.0) * spread).sqrt() / n
            })
        });
        out
    }
}

/// A system's right-hand side and what its stopping test reads, in the solve's scaled units.
struct Scaled<'b> {
    b: &'b [[f64; 3]],
    /// The emission (the radiance of the patches not solved for).
    le: &'b [[f64; 3]],
    seen: &'b [[f64; 3]],
    sky: [f64; 3],
}

/// The noise test of one solve (module docs).
struct Noise {
    /// Per patch and channel, a lower bound on the standard error; empty until measured.
    floor: Vec<[f64; 3]>,
    /// The first-bounce spread as last measured.
    spread: Vec<[f64; 3]>,
    /// The error bound when `floor` was measured: it is measured again once the bound has
    /// fallen 16-fold and the test still fails (the bound it was lowered by has shrunk).
    measured_at: [f64; 3],
}

impl Noise {
    /// With `guess`, the first bounce's spread as a nearby frame measured it: the test waits
    /// until it would let a channel stop before it measures this frame's (a cold start
    /// measures it at once, to have a guess).
    fn new(guess: Option<Vec<[f64; 3]>>) -> Self {
        Self {
            floor: Vec::new(),
            measured_at: [if guess.is_some() {
                f64::NAN
            } else {
                f64::INFINITY
            }; 3],
            spread: guess.unwrap_or_default(),
        }
    }

    /// Per channel with a finite `bound` (`‖z‖∞ / (1 − max q)`, see [`System::bound`]):
    /// whether the bound on every unknown patch's remaining error, `|z_i| + q_i·bound`, is below
    /// `stop.noise` times its standard error or `stop.precision` times its radiance.
    fn quiet<T: Real>(
        &mut self,
        system: &System<'_>,
        problem: &Scaled<'_>,
        x: &[[T; 3]],
        z: &[[T; 3]],
        bound: [f64; 3],
        stop: &Stop,
    ) -> [bool; 3] {
        let check = bound.map(f64::is_finite);
        // With a guess, the bound it stands for is the first one.
        for (at, bound) in self.measured_at.iter_mut().zip(bound) {
            if at.is_nan() {
                *at = bound;
            }
        }
        if check == [false; 3] || (stop.noise == 0.0 && stop.precision == 0.0) {
            // Nothing to test, or stopped by the residual alone.
            return [false; 3];
        }
        let quiet = Self::test(system, &self.floor, x, z, bound, check, stop);
        // Measuring costs a pass over the per-group entries: only when the spread as last
        // measured, not lowered, would let a channel stop (it hardly changes once the iterate
        // is near), or once the bound has fallen a thousandfold since.
        let hopeful = Self::test(system, &self.spread, x, z, bound, check, stop);
        let stale = (0..3).any(|c| {
            check[c] && !quiet[c] && (hopeful[c] || bound[c] <= self.measured_at[c] / 1e3)
        });
        if !stale {
            return quiet;
        }
        let values: Vec<[f64; 3]> = (0..x.len())
            .map(|i| {
                std::array::from_fn(|c| {
                    if system.unknown(i, c) {
                        x[i][c].get()
                    } else {
                        problem.le[i][c]
                    }
                })
            })
            .collect();
        let sigma = system.first_bounce(&values, problem.seen, problem.sky, stop.groups);
        // The first bounce's spread is a seminorm of the radiance (plus a constant): an error of
        // at most E on every patch moves it by at most ρ·2E·√(K/(K−1)) (each group's term by
        // 2E·X_g). What is left is a lower bound on the spread at the answer.
        let k = f64::from(tally::GROUPS);
        let slack = 2.0 * (k / (k - 1.0)).sqrt();
        // A group's pieces are of its patch's material: one reflectance.
        let rho = |k: usize| match stop.groups {
            Some(g) => (g.members(k).first()).map_or([0.0; 3], |&i| system.rho[i as usize]),
            None => system.rho[k],
        };
        self.floor = (sigma.iter().enumerate())
            .map(|(k, s)| {
                let rho = rho(k);
                std::array::from_fn(|c| {
                    if check[c] {
                        (s[c] - slack * rho[c] * bound[c]).max(0.0)
                    } else {
                        0.0
                    }
                })
            })
            .collect();
        self.measured_at = bound;
        self.spread = sigma;
        Self::test(system, &self.floor, x, z, bound, check, stop)
    }

    /// The test of [`Noise::quiet`] against `floor`.
    fn test<T: Real>(
        system: &System<'_>,
        floor: &[[f64; 3]],
        x: &[[T; 3]],
        z: &[[T; 3]],
        bound: [f64; 3],
        mut quiet: [bool; 3],
        stop: &Stop,
    ) -> [bool; 3] {
        for (i, (xi, zi)) in x.iter().zip(z).enumerate() {
            // A piece's group's floor: the error bar of every answer that reads the piece.
            let k = stop.groups.map_or(i, |g| g.of()[i] as usize);
            for c in 0..3 {
                if quiet[c] && system.unknown(i, c) {
                    let error = zi[c].get().abs() + system.coupling[i][c] * bound[c];
                    let floor = floor.get(k).map_or(0.0, |f| f[c]);
                    if error > (stop.noise * floor).max(stop.precision * xi[c].get().abs()) {
                        quiet[c] = false;
                    }
                }
            }
        }
        quiet
    }
}
