//! Light probes for what moves (issue 49): a regular grid of order-2 spherical-harmonic probes
//! over the box where the scene is at any frame, the probes inside geometry dropped, each
//! probe's incident radiance evaluated per lighting state from the solved radiosity
//! ([`crate::direct::points::probes_at`]). A moving object is lit by interpolating the probes
//! around it, as engines do with baked probes.
//!
//! The grid: `⌈extent / spacing⌉` cells along each axis (at least one), a probe at each cell's
//! centre, so that no probe lies on the box's faces (a room's walls). The default spacing is one
//! scene unit (a metre in glTF), widened to give at least [`LEAST_CELLS`] cells along the
//! longest side and at most [`DEFAULT_MOST`] probes.

use std::collections::HashMap;

use glam::DVec3;
use serde_json::json;

use crate::bake::Bake;
use crate::direct::points::{AXES, Gather, Lighting, PROBE_GATHER_RAYS, Probe, inside, reach};
use crate::solve::FrameSolution;

/// Cells at least along the longest side of a default grid.
pub const LEAST_CELLS: f64 = 4.0;

/// Probes at most in a default grid (the spacing is widened until it holds).
pub const DEFAULT_MOST: usize = 4096;

/// Probes at most in any grid (before the ones inside geometry are dropped).
pub const MAX_PROBES: usize = 1 << 18;

/// A grid of light probes over a bake's scene, fixed for its timeline.
#[derive(Clone, Debug)]
pub struct ProbeGrid {
    /// The spacing asked for, or the default's, in scene units.
    pub spacing: f64,
    /// The first probe's position (the lowest corner's cell centre), in scene units.
    pub origin: DVec3,
    /// The step between neighbouring probes along each axis, in scene units (at most
    /// `spacing`: the cells divide the box's sides evenly).
    pub step: DVec3,
    /// Probes along each axis.
    pub counts: [usize; 3],
    /// Each probe kept: its grid index (`i + nx (j + ny k)`) and its position (normalised
    /// space).
    pub kept: Vec<(usize, DVec3)>,
}

impl ProbeGrid {
    /// The grid over `bake`'s scene at `spacing` scene units (the default if `None`; module
    /// docs), without the probes inside geometry.
    ///
    /// # Errors
    /// A message if `spacing` is not a positive number or gives more than [`MAX_PROBES`].
    pub fn new(bake: &Bake, spacing: Option<f64>) -> Result<Self, String> {
        let scene = &bake.scene;
        let norm = &scene.normalisation;
        let (lo, hi) = reach(scene);
        if !(lo.is_finite() && hi.is_finite()) {
            return Err("light probes: the scene has no geometry to place them in".to_string());
        }
        let (lo, hi) = (norm.to_scene(lo), norm.to_scene(hi));
        let extent = (hi - lo).max(DVec3::ZERO);
        let cells = |s: f64| extent.to_array().map(|e| ((e / s).ceil() as usize).max(1));
        let count = |c: [usize; 3]| c.iter().try_fold(1usize, |n, &k| n.checked_mul(k));
        let spacing = match spacing {
            Some(s) if !(s.is_finite() && s > 0.0) => {
                return Err(format!("probe spacing {s}: must be a positive number"));
            }
            Some(s) => s,
            None => {
                let longest = extent.max_element();
                let mut s = if longest > 0.0 {
                    1.0f64.min(longest / LEAST_CELLS)
                } else {
                    1.0
                };
                while count(cells(s)).is_none_or(|n| n > DEFAULT_MOST) {
                    s *= 1.25;
                }
                s
            }
        };
        let counts = cells(spacing);
        match count(counts) {
            Some(n) if n <= MAX_PROBES => {}
            _ => {
                return Err(format!(
                    "probe spacing {spacing} gives {} × {} × {} probes, more than {MAX_PROBES}: \
                     give a larger spacing",
                    counts[0], counts[1], counts[2]
                ));
            }
        }
        let step = DVec3::from_array(std::array::from_fn(|a| extent[a] / counts[a] as f64));
        let origin = lo + step * 0.5;
        let to_normalised = norm.to_normalised();
        let all: Vec<(usize, DVec3)> = (0..counts[2])
            .flat_map(|k| (0..counts[1]).flat_map(move |j| (0..counts[0]).map(move |i| (i, j, k))))
            .map(|(i, j, k)| {
                let at = origin + step * DVec3::new(i as f64, j as f64, k as f64);
                (
                    i + counts[0] * (j + counts[1] * k),
                    to_normalised.transform_point3(at),
                )
            })
            .collect();
        let positions: Vec<DVec3> = all.iter().map(|p| p.1).collect();
        let dropped = inside((scene, bake.tracer()), &positions, bake.seed());
        let kept = (all.into_iter().zip(dropped))
            .filter_map(|(p, inside)| (!inside).then_some(p))
            .collect();
        Ok(Self {
            spacing,
            origin,
            step,
            counts,
            kept,
        })
    }

    /// The probes' light at `frame`, from `solution` solved with `lighting`.
    #[must_use]
    pub fn probes(
        &self,
        bake: &Bake,
        frame: usize,
        (solution, lighting): (&FrameSolution, Lighting<'_>),
    ) -> Vec<Probe> {
        let positions: Vec<DVec3> = self.kept.iter().map(|p| p.1).collect();
        let gather = Gather {
            rays: PROBE_GATHER_RAYS,
            ..Gather::standard(bake.seed())
        };
        let solved = (solution, lighting);
        let mut probes =
            crate::output::geometry::light_probes(bake, frame, &positions, solved, gather);
        self.fill_inside(&mut probes);
        probes
    }

    /// Gives each probe inside geometry at this state ([`Probe::inside`]: a moving object
    /// passing through it) the mean light of its neighbours in the grid that are not (the 26
    /// around it), so that an object lit from the probes around it does not go dark where
    /// another passes; its errors the largest of theirs and their spread, in quadrature. One
    /// with no such neighbour keeps its own.
    fn fill_inside(&self, probes: &mut [Probe]) {
        let [nx, ny, nz] = self.counts;
        let slot: HashMap<usize, usize> = (self.kept.iter().enumerate())
            .map(|(s, p)| (p.0, s))
            .collect();
        let original = probes.to_vec();
        for (s, probe) in probes.iter_mut().enumerate() {
            if !probe.inside {
                continue;
            }
            let index = self.kept[s].0;
            let (i, j, k) = (index % nx, index / nx % ny, index / (nx * ny));
            let mut around = Vec::new();
            for (di, dj, dk) in (0..27).map(|d| (d % 3, d / 3 % 3, d / 9)) {
                let (a, b, c) = (i + di, j + dj, k + dk);
                if (di, dj, dk) == (1, 1, 1) || a == 0 || b == 0 || c == 0 {
                    continue;
                }
                let (a, b, c) = (a - 1, b - 1, c - 1);
                if a >= nx || b >= ny || c >= nz {
                    continue;
                }
                let near = slot.get(&(a + nx * (b + ny * c))).map(|&t| &original[t]);
                around.extend(near.filter(|p| !p.inside));
            }
            if around.is_empty() {
                continue;
            }
            let n = around.len() as f64;
            // The mean of `value` over the neighbours, and the error: the largest of
            // `error`'s and their spread, in quadrature.
            let pool = |value: &dyn Fn(&Probe) -> f64, error: &dyn Fn(&Probe) -> f64| {
                let mean = around.iter().copied().map(value).sum::<f64>() / n;
                let spread = around
                    .iter()
                    .map(|p| (value(p) - mean).powi(2))
                    .sum::<f64>()
                    / n;
                let largest = around.iter().copied().map(error).fold(0.0, f64::max);
                (mean, (largest * largest + spread).sqrt())
            };
            for m in 0..9 {
                for c in 0..3 {
                    (probe.sh[m][c], probe.stderr[m][c]) =
                        pool(&|p| p.sh[m][c], &|p| p.stderr[m][c]);
                }
            }
            for (a, n) in AXES.iter().enumerate() {
                for c in 0..3 {
                    probe.axes_stderr[a][c] =
                        pool(&|p| p.irradiance(*n)[c], &|p| p.axes_stderr[a][c]).1;
                }
            }
        }
    }

    /// The grid's document (`probes.json` beside the states' files): where the probes are and
    /// how to read their coefficients. `frames` maps each frame to its state's file.
    #[must_use]
    pub fn document(&self, bake: &Bake, frames: serde_json::Value) -> serde_json::Value {
        let norm = &bake.scene.normalisation;
        let positions: Vec<[f32; 3]> = (self.kept.iter())
            .map(|p| norm.to_scene(p.1).as_vec3().to_array())
            .collect();
        let total: usize = self.counts.iter().product();
        json!({
            "convention": {
                "basis": "real spherical harmonics, bands 0 to 2, orthonormal over the sphere",
                "order": ["1", "y", "z", "x", "xy", "yz", "3z²-1", "xz", "x²-y²"],
                "constants": [0.282_094_8, 0.488_602_5, 0.488_602_5, 0.488_602_5,
                    1.092_548_4, 1.092_548_4, 0.315_391_6, 1.092_548_4, 0.546_274_2],
                "coefficients": "L_lm = ∫ L(ω) Y_lm(ω) dω of the radiance L arriving from direction ω (scene's emission units), not convolved",
                "irradiance": "E(n) = Σ A_l L_lm Y_lm(n), A = [π, 2π/3, π/4] per band (Ramamoorthi and Hanrahan 2001); a diffuse surface of albedo ρ shows ρ E / π",
                "axes": "the glTF file's (right-handed, +Y up); an importer that mirrors one axis into left-handed axes negates the coefficients odd in it (z: indices 2, 5, 7; x: 3, 4, 7)",
                "inside": "per state, the probes inside geometry then (a moving object passing through them): their light is the mean of their neighbours' that are not",
                "layout": "sh and stderr (each coefficient's standard error): per probe (in this file's order) 9 coefficients in order, each RGB, 27 numbers a probe; irradiance_stderr: the standard error of E(n) at n = +x, -x, +y, -y, +z, -z, each RGB, 18 numbers a probe (at other normals, weight the variances by the squares of n's components)",
            },
            "spacing": self.spacing,
            "origin": self.origin.to_array(),
            "step": self.step.to_array(),
            "counts": self.counts,
            "dropped_inside_geometry": total - self.kept.len(),
            "indices": self.kept.iter().map(|p| p.0).collect::<Vec<_>>(),
            "positions": positions,
            "frames": frames,
        })
    }

    /// A lighting state's document: every probe's coefficients and their standard errors
    /// ([`ProbeGrid::document`]'s layout).
    #[must_use]
    pub fn state_document(probes: &[Probe]) -> serde_json::Value {
        let flat = |of: &dyn Fn(&Probe) -> [[f64; 3]; 9]| -> Vec<f32> {
            (probes.iter())
                .flat_map(|p| of(p).into_iter().flatten().map(|v| v as f32))
                .collect()
        };
        let axes: Vec<f32> = (probes.iter())
            .flat_map(|p| p.axes_stderr.into_iter().flatten().map(|v| v as f32))
            .collect();
        let inside: Vec<usize> = (probes.iter().enumerate())
            .filter_map(|(s, p)| p.inside.then_some(s))
            .collect();
        json!({
            "sh": flat(&|p| p.sh),
            "stderr": flat(&|p| p.stderr),
            "irradiance_stderr": axes,
            "inside": inside,
        })
    }
}
