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
//! A solve that stops at its iteration cap is no answer: [`FrameSolution::converged`] says so and
//! [`FrameSolution::ensure_converged`] turns it into an error, which fails the bake or the job.
//! The replica solves only measure the spread: when the pooled solve did not converge they are
//! skipped, and a replica that stops at the cap (at its looser tolerance) is left out of the
//! spread, so the error bar is the others' spread over the square root of their number: wider
//! in expectation, never narrowed by a replica that did not move, and the pooled answer stands.

pub mod analytic;
pub mod tally;

use rayon::prelude::*;
use serde::Serialize;

use crate::scene::Material;
use tally::{ABSORBED, FrameTally, SKY};

/// How to solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveParams {
    /// Radiance of everything outside the scene, RGB, in emission units.
    pub sky: [f64; 3],
    /// Stop when the residual has fallen to this fraction of the right-hand side (`|r| / |b|`).
    pub tolerance: f64,
    /// Give up after this many iterations per channel: the frame is then not converged, and
    /// the bake and the service fail it rather than answer with it.
    pub max_iterations: usize,
}

impl Default for SolveParams {
    fn default() -> Self {
        Self {
            sky: [0.0; 3],
            tolerance: 1e-10,
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
    /// is then only its emission).
    pub stderr: Vec<Option<[f64; 3]>>,
    /// Crossings of each patch by the lines (0: unsampled).
    pub samples: Vec<u64>,
    /// Conjugate-gradient iterations, most over the channels.
    pub iterations: usize,
    /// Relative residual reached, worst over the channels.
    pub residual: f64,
    /// Whether every channel reached the tolerance.
    pub converged: bool,
}

impl FrameSolution {
    /// `Ok` if every channel reached the tolerance; otherwise why frame `frame`, solved with
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
    let patches = patch_material.len();
    let mut radiance = vec![[0.0; 3]; patches];
    let mut stderr: Vec<Option<[f64; 3]>> = (0..patches)
        .map(|i| (tally.crossings[i] > 0).then_some([0.0; 3]))
        .collect();
    let (mut iterations, mut residual, mut converged) = (0, 0.0f64, true);
    // Each replica's tallies, taken apart once for the three channels.
    let replicas: Vec<FrameTally> = (0..tally::GROUPS as u8)
        .into_par_iter()
        .map(|g| tally.replica(g))
        .collect();
    for c in 0..3 {
        let rho: Vec<f64> = patch_material
            .iter()
            .map(|&m| materials[m as usize].reflectance[c])
            .collect();
        let emission: Vec<f64> = patch_material
            .iter()
            .enumerate()
            .map(|(i, &m)| {
                let material = &materials[m as usize];
                let reflected = direct.map_or(0.0, |d| {
                    material.reflectance[c] * d.irradiance[i][c] * std::f64::consts::FRAC_1_PI
                });
                material.emission[c] + reflected
            })
            .collect();
        // The emission the lines do not carry: the sampled emitters'.
        let seen: Vec<f64> = patch_material
            .iter()
            .enumerate()
            .map(|(i, &m)| match direct {
                Some(d) if d.sampled[i] => materials[m as usize].emission[c],
                _ => 0.0,
            })
            .collect();
        let system = System::new(tally, &rho);
        let light = system.solve(&emission, &seen, params.sky[c], params);
        iterations = iterations.max(light.iterations);
        residual = residual.max(light.residual);
        converged &= light.converged;
        // Replicas of a solve that is no answer would measure nothing: skip them.
        let error = if light.converged {
            replica_errors(
                &replicas,
                &rho,
                &emission,
                &seen,
                params.sky[c],
                &light.values,
                params,
            )
        } else {
            vec![None; patches]
        };
        for i in 0..patches {
            radiance[i][c] = light.values[i];
            if let Some(e) = &mut stderr[i] {
                e[c] = if system.unknown[i] {
                    // The spread of the replicas' solutions, and never less than the spread of
                    // the patch's own first bounce (which low sample counts can hide from
                    // the former).
                    let first =
                        rho[i] * system.sample_deviation(i, &light.values, &seen, params.sky[c]);
                    let lines = error[i].map_or(first, |e| e.max(first));
                    // The direct light's own sampling error, independent of the lines'.
                    let sampled = direct.map_or(0.0, |d| {
                        d.variance[i][c] * (rho[i] * std::f64::consts::FRAC_1_PI).powi(2)
                    });
                    (lines * lines + sampled).sqrt()
                } else {
                    0.0
                };
            }
        }
    }
    FrameSolution {
        radiance,
        stderr,
        samples: tally.crossings.clone(),
        iterations,
        residual,
        converged,
    }
}

/// Standard errors from the independent replicas of the lines (METHOD.md §6): each replica's
/// tallies alone give a full solution (warm-started from the pooled one), and the spread of
/// those solutions, divided by √K, is the error of their pooled mean. It carries every bounce
/// and every correlation between patches. `None` for a patch fewer than 4 replicas crossed. A
/// replica that stops at the iteration cap is left out (its values, still near the pooled ones
/// it started from, would narrow the spread): the others' spread over √(their number) is wider
/// in expectation.
fn replica_errors(
    replicas: &[FrameTally],
    rho: &[f64],
    emission: &[f64],
    seen: &[f64],
    sky: f64,
    pooled: &[f64],
    params: &SolveParams,
) -> Vec<Option<f64>> {
    let patches = rho.len();
    let mut sum = vec![0.0; patches];
    let mut sum_sq = vec![0.0; patches];
    let mut count = vec![0usize; patches];
    let loose = SolveParams {
        tolerance: 1e-6,
        ..*params
    };
    // The replicas are solved in parallel (a frame alone, as a static scene is, then uses every
    // core), and summed in their order: the result does not depend on the thread count.
    let solved: Vec<Option<(Vec<bool>, Vec<f64>)>> = replicas
        .par_iter()
        .map(|replica| {
            let system = System::new(replica, rho);
            let solved = system.solve_from(emission, seen, sky, Some(pooled), &loose);
            solved.converged.then_some((system.unknown, solved.values))
        })
        .collect();
    for (unknown, values) in solved.iter().flatten() {
        for i in 0..patches {
            if unknown[i] {
                let v = values[i];
                sum[i] += v;
                sum_sq[i] += v * v;
                count[i] += 1;
            }
        }
    }
    (0..patches)
        .map(|i| {
            let k = count[i] as f64;
            (count[i] >= 4).then(|| {
                let mean = sum[i] / k;
                let variance = ((sum_sq[i] - k * mean * mean) / (k - 1.0)).max(0.0);
                (variance / k).sqrt()
            })
        })
        .collect()
}

/// The system of one channel.
struct System<'a> {
    tally: &'a FrameTally,
    rho: &'a [f64],
    /// Patches solved for: crossed by some line and reflecting.
    unknown: Vec<bool>,
    /// Diagonal `N_i / ρ_i` of the unknowns.
    diagonal: Vec<f64>,
}

/// A channel's solution.
struct Solved {
    values: Vec<f64>,
    iterations: usize,
    residual: f64,
    converged: bool,
}

impl<'a> System<'a> {
    fn new(tally: &'a FrameTally, rho: &'a [f64]) -> Self {
        let unknown: Vec<bool> = (0..rho.len())
            .map(|i| tally.crossings[i] > 0 && rho[i] > 0.0)
            .collect();
        let diagonal = (0..rho.len())
            .map(|i| {
                if unknown[i] {
                    tally.crossings[i] as f64 / rho[i]
                } else {
                    0.0
                }
            })
            .collect();
        Self {
            tally,
            rho,
            unknown,
            diagonal,
        }
    }

    fn row(&self, i: usize) -> impl Iterator<Item = (u32, f64)> + '_ {
        let range = self.tally.offsets[i]..self.tally.offsets[i + 1];
        self.tally.columns[range.clone()]
            .iter()
            .copied()
            .zip(self.tally.counts[range].iter().map(|&c| c as f64))
    }

    /// `y = A x` on the unknowns.
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        for (i, yi) in y.iter_mut().enumerate() {
            if !self.unknown[i] {
                *yi = 0.0;
                continue;
            }
            let mut sum = self.diagonal[i] * x[i];
            for (j, s) in self.row(i) {
                if j < ABSORBED && self.unknown[j as usize] {
                    sum -= s * x[j as usize];
                }
            }
            *yi = sum;
        }
    }

    /// Solves `L = Le + ρ F (L − seen) + ρ F_sky L_sky` for emission `le` (the known patches
    /// keep `L = Le`); `seen` is the emission the lines do not carry (sampled emitters').
    fn solve(&self, le: &[f64], seen: &[f64], sky: f64, params: &SolveParams) -> Solved {
        self.solve_from(le, seen, sky, None, params)
    }

    /// [`System::solve`] starting from `start` (a nearby solution) instead of the emission.
    fn solve_from(
        &self,
        le: &[f64],
        seen: &[f64],
        sky: f64,
        start: Option<&[f64]>,
        params: &SolveParams,
    ) -> Solved {
        let n = le.len();
        // The system is linear: solve it scaled to O(1) whatever the emission's magnitude
        // (1e-30 or 1e30), and scale back.
        let scale = le.iter().fold(sky.abs(), |m, v| m.max(v.abs()));
        let mut values: Vec<f64> = le.to_vec();
        if scale == 0.0 || !scale.is_finite() {
            return Solved {
                values,
                iterations: 0,
                residual: if scale == 0.0 { 0.0 } else { f64::INFINITY },
                converged: scale == 0.0,
            };
        }
        let le_s: Vec<f64> = le.iter().map(|v| v / scale).collect();
        let sky_s = sky / scale;
        let mut b = vec![0.0; n];
        for i in 0..n {
            if !self.unknown[i] {
                continue;
            }
            let mut bi = self.diagonal[i] * le_s[i];
            for (j, s) in self.row(i) {
                bi += s * match j {
                    SKY => sky_s,
                    ABSORBED => 0.0,
                    j if !self.unknown[j as usize] => (le[j as usize] - seen[j as usize]) / scale,
                    j => -seen[j as usize] / scale,
                };
            }
            b[i] = bi;
        }
        let x0: Vec<f64> = match start {
            Some(x) => x.iter().map(|v| v / scale).collect(),
            None => le_s.clone(),
        };
        let (x, iterations, residual, converged) = self.conjugate_gradients(&b, &x0, params);
        for i in 0..n {
            if self.unknown[i] {
                values[i] = x[i] * scale;
            }
        }
        Solved {
            values,
            iterations,
            residual,
            converged,
        }
    }

    /// Diagonally preconditioned conjugate gradients from `x0`.
    fn conjugate_gradients(
        &self,
        b: &[f64],
        x0: &[f64],
        params: &SolveParams,
    ) -> (Vec<f64>, usize, f64, bool) {
        let n = b.len();
        let dot = |a: &[f64], c: &[f64]| a.iter().zip(c).map(|(x, y)| x * y).sum::<f64>();
        let mut x: Vec<f64> = (0..n)
            .map(|i| if self.unknown[i] { x0[i] } else { 0.0 })
            .collect();
        let mut r = vec![0.0; n];
        self.apply(&x, &mut r);
        r.iter_mut().zip(b).for_each(|(ri, bi)| *ri = bi - *ri);
        let precondition = |r: &[f64], z: &mut [f64]| {
            for i in 0..n {
                z[i] = if self.unknown[i] {
                    r[i] / self.diagonal[i]
                } else {
                    0.0
                };
            }
        };
        let b_norm = dot(b, b).sqrt();
        if b_norm == 0.0 {
            return (vec![0.0; n], 0, 0.0, true);
        }
        let mut z = vec![0.0; n];
        precondition(&r, &mut z);
        let mut p = z.clone();
        let mut rz = dot(&r, &z);
        let mut q = vec![0.0; n];
        let mut residual = dot(&r, &r).sqrt() / b_norm;
        for iteration in 0..params.max_iterations {
            if residual <= params.tolerance {
                return (x, iteration, residual, true);
            }
            self.apply(&p, &mut q);
            let pq = dot(&p, &q);
            if pq <= 0.0 || !pq.is_finite() {
                return (x, iteration, residual, false);
            }
            let alpha = rz / pq;
            for i in 0..n {
                x[i] += alpha * p[i];
                r[i] -= alpha * q[i];
            }
            residual = dot(&r, &r).sqrt() / b_norm;
            precondition(&r, &mut z);
            let rz_next = dot(&r, &z);
            let beta = rz_next / rz;
            rz = rz_next;
            for i in 0..n {
                p[i] = z[i] + beta * p[i];
            }
        }
        let converged = residual <= params.tolerance;
        (x, params.max_iterations, residual, converged)
    }

    /// Standard error of the mean radiance the lines carry from the far ends of the segments
    /// leaving unknown patch `i` (`l − seen`; sky at `sky`, absorbed at 0), from the spread between the line groups: the
    /// ratio estimator `Σ_g Y_g / Σ_g X_g` (Y_g the radiance summed over group g's segments, X_g
    /// their number) has variance `K/(K−1) Σ_g (Y_g − m X_g)² / N²`.
    fn sample_deviation(&self, i: usize, l: &[f64], seen: &[f64], sky: f64) -> f64 {
        let groups = tally::GROUPS as usize;
        let (mut y, mut x) = (vec![0.0; groups], vec![0.0; groups]);
        let range = self.tally.group_offsets[i]..self.tally.group_offsets[i + 1];
        for &(j, g, count) in &self.tally.group_entries[range] {
            let v = match j {
                SKY => sky,
                ABSORBED => 0.0,
                j => l[j as usize] - seen[j as usize],
            };
            y[g as usize] += f64::from(count) * v;
            x[g as usize] += f64::from(count);
        }
        let n: f64 = x.iter().sum();
        let mean = y.iter().sum::<f64>() / n;
        let k = groups as f64;
        let spread: f64 = y
            .iter()
            .zip(&x)
            .map(|(yg, xg)| (yg - mean * xg).powi(2))
            .sum();
        debug_assert!(self.rho[i] > 0.0 && n > 0.0);
        (k / (k - 1.0) * spread).sqrt() / n
    }
}
