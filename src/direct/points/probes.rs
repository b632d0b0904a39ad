//! Light probes (issue 49): the light arriving at points in the scene's empty space, for what
//! moves through it, as the order-2 spherical harmonics of the incident radiance
//! (Ramamoorthi and Hanrahan 2001), the form Godot's `LightmapGI` probes and Unity's
//! `SphericalHarmonicsL2` take.
//!
//! A probe's coefficients are `L_lm = ∫ L(ω) Y_lm(ω) dω` over the whole sphere, `L(ω)` the
//! radiance arriving from direction `ω`, estimated from the frame's solution as a texel's light
//! is ([`super`]), each part by the sampling that suits it:
//! - **punctual lights** exactly: a light arriving from `ω` with irradiance `E⊥` on a plane
//!   facing it adds `E⊥ Y_lm(ω)`, behind one shadow ray;
//! - **the sampled emitters** by stratified directions uniform in the solid angle each one
//!   subtends, behind shadow rays (exact where nothing is in the way);
//! - **the rest gathered** along stratified directions uniform over the sphere, each reading
//!   what the solution says the surface it meets sends back (less the sampled emitters'
//!   emission, which the term above has; followed on where it lands near, as a texel's gather
//!   ray is).
//!
//! Each coefficient carries a standard error: the strata's (pairs of neighbouring strata), and
//! the error of the patches the gather read, wholly correlated between them. So does the
//! irradiance the coefficients give a surface facing along each axis ([`AXES`]), measured on
//! the same samples (the coefficients' errors are correlated: they come from the same rays).

use glam::DVec3;
use rayon::prelude::*;

use super::super::area::{AreaLights, point_grid};
use super::super::reference::{Met, Sight};
use super::super::{Occluders, Posed, strata};
use super::{
    Gather, GatherCache, Gatherer, Lighting, Linear, PathTest, Read, Solved, with_gatherer,
};
use crate::scene::Scene;
use crate::trace::coincident::mix;
use crate::trace::{Hit, SceneTracer};

/// Gather rays per probe (a 16 × 16 grid of strata of the sphere).
pub const PROBE_GATHER_RAYS: usize = 256;

/// Rays per probe that tell whether it is inside geometry ([`inside`]).
const INSIDE_RAYS: usize = 64;

/// The share of those rays meeting the back of a one-sided face above which a probe is taken
/// for inside geometry: light cannot get there.
const INSIDE_SHARE: f64 = 0.25;

/// The real spherical harmonics of bands 0 to 2 at unit direction `w`, orthonormal over the
/// sphere, in the order `Y₀₀; Y₁₋₁, Y₁₀, Y₁₁; Y₂₋₂, Y₂₋₁, Y₂₀, Y₂₁, Y₂₂`, that is
/// `1; y, z, x; xy, yz, 3z² − 1, xz, x² − y²` times their constants (the axes the glTF file's).
#[must_use]
pub fn sh_basis(w: DVec3) -> [f64; 9] {
    let (x, y, z) = (w.x, w.y, w.z);
    [
        0.282_094_791_773_878_14,
        0.488_602_511_902_919_9 * y,
        0.488_602_511_902_919_9 * z,
        0.488_602_511_902_919_9 * x,
        1.092_548_430_592_079_2 * x * y,
        1.092_548_430_592_079_2 * y * z,
        0.315_391_565_252_520_05 * (3.0 * z * z - 1.0),
        1.092_548_430_592_079_2 * x * z,
        0.546_274_215_296_039_6 * (x * x - y * y),
    ]
}

/// The clamped cosine's coefficient per band: the irradiance's coefficients are the
/// radiance's times these (`π`, `2π/3`, `π/4`).
pub const COSINE_LOBE: [f64; 3] = [
    std::f64::consts::PI,
    2.0 * std::f64::consts::FRAC_PI_3,
    std::f64::consts::FRAC_PI_4,
];

/// The band of coefficient `k` of [`sh_basis`].
fn band(k: usize) -> usize {
    match k {
        0 => 0,
        1..=3 => 1,
        _ => 2,
    }
}

/// The normals a probe's irradiance error is measured at ([`Probe::axes_stderr`]).
pub const AXES: [DVec3; 6] = [
    DVec3::X,
    DVec3::NEG_X,
    DVec3::Y,
    DVec3::NEG_Y,
    DVec3::Z,
    DVec3::NEG_Z,
];

/// What one sample along unit `w` adds per unit of radiance: the 9 coefficients'
/// [`sh_basis`], then the irradiance the coefficients give at each of [`AXES`] (the
/// order-2 kernel `Σ Â_l Y_lm(w) Y_lm(n)`).
pub(in crate::direct) fn kernel(w: DVec3) -> [f64; 15] {
    let y = sh_basis(w);
    let mut out = [0.0; 15];
    out[..9].copy_from_slice(&y);
    for (a, n) in AXES.iter().enumerate() {
        let yn = sh_basis(*n);
        out[9 + a] = (0..9).map(|k| COSINE_LOBE[band(k)] * y[k] * yn[k]).sum();
    }
    out
}

/// One light probe: its incident radiance's coefficients ([`sh_basis`] order, RGB, in the
/// scene's emission units) and their standard errors.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Probe {
    /// `L_lm`, per coefficient, RGB.
    pub sh: [[f64; 3]; 9],
    /// Each one's standard error.
    pub stderr: [[f64; 3]; 9],
    /// The standard error of [`Probe::irradiance`] at each of [`AXES`] (the coefficients'
    /// errors are correlated, coming from the same rays: measured whole, not added up).
    pub axes_stderr: [[f64; 3]; 6],
    /// Whether the probe is inside geometry at this frame (more than [`INSIDE_SHARE`] of its
    /// gather rays meet the back of a one-sided face: a moving object passing through it),
    /// where its light is no light a moving object could get.
    pub inside: bool,
}

impl Probe {
    /// The irradiance the probe gives a surface of unit normal `n` at its point, from its
    /// coefficients: `E(n) = Σ Â_l L_lm Y_lm(n)` (a diffuse surface of albedo `ρ` there sends
    /// back `ρ E / π`).
    #[must_use]
    pub fn irradiance(&self, n: DVec3) -> [f64; 3] {
        let y = sh_basis(n);
        std::array::from_fn(|c| {
            (0..9)
                .map(|k| COSINE_LOBE[band(k)] * y[k] * self.sh[k][c])
                .sum()
        })
    }

    /// The standard error of [`Probe::irradiance`] at unit `n`: the variances at the axes
    /// `n` leans towards, weighted by the squares of its components (exact at the axes).
    #[must_use]
    pub fn irradiance_stderr(&self, n: DVec3) -> [f64; 3] {
        std::array::from_fn(|c| {
            (0..3)
                .map(|a| {
                    let axis = 2 * a + usize::from(n[a] < 0.0);
                    n[a] * n[a] * self.axes_stderr[axis][c].powi(2)
                })
                .sum::<f64>()
                .sqrt()
        })
    }
}

/// The direction at `(u, v)` in the unit square, mapped so that uniform `(u, v)` are uniform
/// over the sphere (equal areas: a grid of strata of the square stratifies the sphere).
pub(in crate::direct) fn sphere_direction(u: f64, v: f64) -> DVec3 {
    let z = 1.0 - 2.0 * u;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * std::f64::consts::PI * v;
    DVec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// One sample of a probe's light: its kernel's 15 values ([`kernel`]) times its weight, and
/// the radiance it reads, RGB.
type Sample = ([f64; 15], [f64; 3]);

/// The weighted sum `Σ wᵢ vᵢ` of `samples` `(wᵢ, vᵢ)`, one per stratum (`None`: a stratum whose
/// sample falls outside the domain, adding nothing), and its variance by collapsed strata: each
/// pair of neighbouring strata as one stratum of two samples, `Σ (a − b)²` over the pairs of
/// what is summed (conservative: the pair's difference of means adds to it).
///
/// With `whole` the integrals of the weights over the domain (the gather's part of the sphere,
/// where they are known), the sum is taken with the mean value `v̄` as a control variate,
/// `v̄ ∫ w + Σ wᵢ (vᵢ − v̄)`: a constant radiance is integrated exactly, and what is summed, so
/// what the strata's variance is of, is `wᵢ (vᵢ − v̄)`, small where the light is even (the
/// basis's own variation between strata, which pairs of `wᵢ vᵢ` would count as noise many
/// times over for the quickly varying coefficients, is not noise). Without `whole` (an
/// emitter's solid angle, over which the basis's integrals are what its samples measure), the
/// plain sum `Σ wᵢ vᵢ`.
fn weighted_sum(
    samples: &[Option<Sample>],
    whole: Option<&[f64; 15]>,
) -> ([[f64; 3]; 15], [[f64; 3]; 15]) {
    let inside = samples.iter().flatten();
    let n = inside.clone().count().max(1) as f64;
    let average: [f64; 3] = match whole {
        Some(_) => std::array::from_fn(|c| inside.clone().map(|s| s.1[c]).sum::<f64>() / n),
        None => [0.0; 3],
    };
    let (mut mean, mut variance) = ([[0.0; 3]; 15], [[0.0; 3]; 15]);
    for k in 0..15 {
        let base = whole.map_or(0.0, |whole| whole[k]);
        for c in 0..3 {
            let term = |s: &Option<Sample>| s.map_or(0.0, |(w, v)| w[k] * (v[c] - average[c]));
            mean[k][c] = average[c] * base + samples.iter().map(term).sum::<f64>();
            variance[k][c] = (samples.chunks_exact(2))
                .map(|pair| (term(&pair[0]) - term(&pair[1])).powi(2))
                .sum();
        }
    }
    (mean, variance)
}

/// The integrals over the sphere of [`kernel`]'s values: `√(4π)` for `Y₀₀`, 0 for the other
/// coefficients, and `π` for the irradiance at each axis (a radiance of 1 from everywhere).
fn sphere_integrals() -> [f64; 15] {
    let mut out = [0.0; 15];
    out[0] = (4.0 * std::f64::consts::PI).sqrt();
    out[9..].fill(std::f64::consts::PI);
    out
}

/// The seed of the probe at `x` (normalised space): its place, whatever the frame, so that a
/// probe's light does not flicker between frames whose light is the same.
fn probe_seed(seed: u64, x: DVec3) -> u64 {
    mix(seed ^ mix(x.x.to_bits() ^ mix(x.y.to_bits() ^ mix(x.z.to_bits()))))
}

/// The light probes at `positions` (normalised space, on no surface) at `frame`: the scene and
/// its tracer, the bake's sampled emitters, the frame's solved patches and the lighting they
/// were solved with; `gather.rays` gather rays per probe (module docs).
#[must_use]
pub fn probes_at(
    state: (&Scene, &SceneTracer, &AreaLights),
    frame: usize,
    positions: &[DVec3],
    read: (Solved<'_>, Lighting<'_>),
    sampling: (Gather, &GatherCache),
) -> Vec<Probe> {
    let seed = sampling.0.seed;
    with_gatherer(state, frame, read, sampling, |gatherer| {
        (positions.par_iter())
            .map_init(Vec::new, |hits, &x| {
                gatherer.probe(x, probe_seed(seed, x), hits)
            })
            .collect()
    })
}

/// The box (normalised space) holding the scene's static triangles and every moving object at
/// every frame: where light probes go.
#[must_use]
pub fn reach(scene: &Scene) -> (DVec3, DVec3) {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for p in &scene.statics.positions {
        lo = lo.min(p.as_dvec3());
        hi = hi.max(p.as_dvec3());
    }
    for object in &scene.objects {
        let (a, b) = super::Swept::reach(object, 0..scene.frames.count);
        (lo, hi) = (lo.min(a), hi.max(b));
    }
    (lo, hi)
}

/// Whether each of `positions` (normalised space) is inside geometry: more than
/// [`INSIDE_SHARE`] of [`INSIDE_RAYS`] stratified rays from it meet the back of a one-sided
/// face first, with the static geometry at frame 0 (a probe the moving objects pass through is
/// kept: it reads their light when they are elsewhere).
#[must_use]
pub fn inside(
    (scene, tracer): (&Scene, &SceneTracer),
    positions: &[DVec3],
    seed: u64,
) -> Vec<bool> {
    let posed = Posed::at(scene, tracer, 0);
    let view = posed.frame(scene, tracer, Occluders::Static);
    let sight = Sight::new(scene, &view, 0, &[]);
    let g = INSIDE_RAYS.isqrt();
    (positions.par_iter())
        .map_init(Vec::new, |hits, &x| {
            let backs = strata(g, probe_seed(seed, x))
                .filter(|&(u, v)| {
                    matches!(
                        sight.free_hit(x, sphere_direction(u, v), hits),
                        Met::Nothing
                    )
                })
                .count();
            backs as f64 > INSIDE_SHARE * (g * g) as f64
        })
        .collect()
}

/// A probe's sums as its samples come in: the coefficients, the variances of the coefficients
/// and of the axes' irradiance ([`kernel`]'s 15 values), and the error of the solution the
/// samples read (wholly correlated between them: added linearly).
#[derive(Default)]
struct Tally {
    sh: [[f64; 3]; 9],
    variance: [[f64; 3]; 15],
    read: [[f64; 3]; 15],
}

impl Tally {
    /// Adds `samples` ([`weighted_sum`]: `whole` the integrals of their weights over their
    /// domain, if known).
    fn add(&mut self, samples: &[Option<Sample>], whole: Option<&[f64; 15]>) {
        let (mean, variance) = weighted_sum(samples, whole);
        for c in 0..3 {
            (0..9).for_each(|k| self.sh[k][c] += mean[k][c]);
            (0..15).for_each(|k| self.variance[k][c] += variance[k][c]);
        }
    }

    /// Adds the error `error` (per unit of weight) of what a sample of weights `y` read.
    fn read(&mut self, y: &[f64; 15], error: [f64; 3]) {
        for (m, y) in y.iter().enumerate() {
            (0..3).for_each(|c| self.read[m][c] += y.abs() * error[c]);
        }
    }

    /// The probe, with whether it is inside geometry at this frame.
    fn probe(&self, inside: bool) -> Probe {
        let error = |k: usize| -> [f64; 3] {
            std::array::from_fn(|c| (self.variance[k][c] + self.read[k][c].powi(2)).sqrt())
        };
        Probe {
            sh: self.sh,
            stderr: std::array::from_fn(error),
            axes_stderr: std::array::from_fn(|a| error(9 + a)),
            inside,
        }
    }
}

/// What a ray from a probe reads ([`Gatherer::arriving`]).
struct Arriving {
    /// The whole radiance arriving along it, RGB.
    radiance: [f64; 3],
    /// The error bar of the solution it read, per unit of the sample's weight.
    error: [f64; 3],
    /// Whether it met the back of a one-sided face first.
    back: bool,
}

impl Gatherer<'_> {
    /// The probe at `x` (module docs), its sampling seeded by `seed`.
    fn probe(&self, x: DVec3, seed: u64, hits: &mut Vec<Hit>) -> Probe {
        let mut tally = Tally::default();
        for (w, e) in self.sight.punctual_toward(x, hits) {
            let y = sh_basis(w);
            for (k, coefficient) in tally.sh.iter_mut().enumerate() {
                (0..3).for_each(|c| coefficient[c] += e[c] * y[k]);
            }
        }
        let mut path = Vec::new();
        // The sphere in parts: the solid angle of each sampled emitter in front of the probe
        // (a direction in several, the first's), sampled uniformly within it; the rest by the
        // gather. Each part's integrals of the kernel, from its samples, tell the gather what
        // it leaves out.
        let fronts: Vec<usize> = (0..self.emitters.len())
            .filter(|&k| self.emitters[k].0.faces(x))
            .collect();
        let earlier = |w: DVec3, before: usize| {
            (fronts.iter().take_while(|&&e| e < before)).any(|&e| self.emitters[e].0.covers(x, w))
        };
        let mut parts = [0.0; 15];
        for &k in &fronts {
            let emitter = &self.emitters[k].0;
            let g = point_grid(x, emitter, self.gather.density);
            let samples = emitter.seen_from(x, (mix(seed ^ k as u64), g));
            let n = samples.len().max(1) as f64;
            let mut values = Vec::with_capacity(samples.len());
            for (j, sample) in samples.iter().enumerate() {
                let Some((w, _, angle)) = sample.filter(|s| !earlier(s.0, k)) else {
                    values.push(None);
                    continue;
                };
                let y = kernel(w).map(|b| b * angle / n);
                let on = (
                    mix(seed ^ ((k as u64) << 32 | j as u64)),
                    &mut *hits,
                    &mut path,
                );
                let arriving = self.arriving(x, w, on);
                (0..15).for_each(|m| parts[m] += y[m]);
                tally.read(&y, arriving.error);
                values.push(Some((y, arriving.radiance)));
            }
            tally.add(&values, None);
        }
        // The rest, gathered over the whole sphere but the emitters' parts: each ray's
        // radiance times 4π Y_lm along it estimates L_lm.
        let g = (self.gather.rays as f64).sqrt().ceil().max(4.0) as usize;
        let n = (g * g) as f64;
        let sphere = 4.0 * std::f64::consts::PI;
        let mut values = Vec::with_capacity(g * g);
        let mut backs = 0;
        for (i, (u, v)) in strata(g, mix(seed ^ 0x7072_6f62)).enumerate() {
            let w = sphere_direction(u, v);
            if earlier(w, usize::MAX) {
                values.push(None);
                continue;
            }
            let y = kernel(w).map(|b| sphere * b / n);
            let arriving = self.arriving(x, w, (mix(seed ^ i as u64), &mut *hits, &mut path));
            backs += usize::from(arriving.back);
            tally.read(&y, arriving.error);
            values.push(Some((y, arriving.radiance)));
        }
        let whole: [f64; 15] = std::array::from_fn(|m| sphere_integrals()[m] - parts[m]);
        tally.add(&values, Some(&whole));
        tally.probe(backs as f64 > INSIDE_SHARE * n)
    }

    /// What the ray from the probe at `x` along `w` reads: the whole radiance of what it meets
    /// first (the gather's reading leaves the sampled emitters' emission out; a probe's rays
    /// are split by direction instead, so each reads the whole of it), followed on where it
    /// lands near as a texel's gather ray is (`seed` its bounces' sampling).
    fn arriving(
        &self,
        x: DVec3,
        w: DVec3,
        (seed, hits, path): (u64, &mut Vec<Hit>, &mut Vec<PathTest>),
    ) -> Arriving {
        let (linear, patch) = match self.sight.free_hit(x, w, hits) {
            Met::Sky => (Linear::read(Read::Sky), None),
            Met::Nothing => (Linear::read(Read::Nothing), None),
            Met::Patch(face, p, t) => {
                path.clear();
                let linear = self.reflected(p, (face, x + w * t), (t, 0), (seed, hits, path));
                (linear, Some(p))
            }
        };
        let error = match linear.read {
            Read::Patch(q) => self.read_error(q).unwrap_or_default(),
            _ => [0.0; 3],
        };
        let seen = patch.map_or([0.0; 3], |p| self.seen[p]);
        let value = self.value(&linear);
        Arriving {
            radiance: std::array::from_fn(|c| value[c] + seen[c]),
            error: std::array::from_fn(|c| linear.weight[c] * error[c]),
            back: matches!(linear.read, Read::Nothing) && patch.is_none(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The basis is orthonormal over the sphere, integrated on a fine grid of
    /// [`sphere_direction`]'s strata (which a direction mapping that is not uniform fails).
    #[test]
    fn the_basis_is_orthonormal_over_the_sphere() {
        let g = 256;
        let mut gram = [[0.0; 9]; 9];
        for i in 0..g {
            for j in 0..g {
                let w = sphere_direction((i as f64 + 0.5) / g as f64, (j as f64 + 0.5) / g as f64);
                let y = sh_basis(w);
                for (row, a) in gram.iter_mut().zip(y) {
                    for (entry, b) in row.iter_mut().zip(y) {
                        *entry += 4.0 * std::f64::consts::PI * a * b / (g * g) as f64;
                    }
                }
            }
        }
        for (a, row) in gram.iter().enumerate() {
            for (b, entry) in row.iter().enumerate() {
                let expected = if a == b { 1.0 } else { 0.0 };
                assert!((entry - expected).abs() < 1e-3, "{a} {b}: {entry}");
            }
        }
    }

    /// A light from one direction `d` of irradiance `E⊥`: its order-2 irradiance is
    /// `E⊥ Σ_l Â_l (2l + 1) P_l(n·d) / 4π`: `17/16 E⊥` facing it, `1/16 E⊥` facing away and
    /// `3/32 E⊥` sideways (the cosine's truncation, exactly).
    #[test]
    fn a_light_from_one_direction_gives_the_truncated_cosine() {
        let d = DVec3::new(1.0, 2.0, -2.0) / 3.0;
        let y = sh_basis(d);
        let probe = Probe {
            sh: std::array::from_fn(|k| [2.0 * y[k]; 3]),
            ..Probe::default()
        };
        let side = d.any_orthonormal_vector();
        for (n, expected) in [(d, 17.0 / 16.0), (-d, 1.0 / 16.0), (side, 3.0 / 32.0)] {
            let e = probe.irradiance(n)[0];
            assert!(
                (e - 2.0 * expected).abs() < 1e-12,
                "{n}: {e} against {}",
                2.0 * expected
            );
        }
    }

    /// The kernel's irradiance values are the irradiance of a probe made of one direction.
    #[test]
    fn the_kernel_holds_the_axes_irradiance() {
        let w = DVec3::new(-0.3, 0.5, 0.8).normalize();
        let k = kernel(w);
        let probe = Probe {
            sh: std::array::from_fn(|i| [k[i]; 3]),
            ..Probe::default()
        };
        for (a, n) in AXES.iter().enumerate() {
            assert!((probe.irradiance(*n)[0] - k[9 + a]).abs() < 1e-12);
        }
    }
}
