//! `radiosity bench-vertices`: the light the baked glTF shows at its vertices, against the path
//! tracer evaluated at the same points ([`crate::direct::reference::path_traced_points`]),
//! with the per-vertex averaging of patches that the outputs carried before (issue 46)
//! measured on the same vertices in the same run.

use std::time::Instant;

use serde::Serialize;

use super::{DARK, timed_bake};
use crate::control::TraceError;
use crate::direct::points::{Lighting, PointRadiance};
use crate::output::NodeMesh;
use crate::output::tonemap::luminance;
use crate::scene::Scene;

/// The scenes `bench-vertices` measures by default.
pub const VERTEX_SCENES: [&str; 4] = [
    "level.gltf",
    "cornell_moving.gltf",
    "lamp_room.gltf",
    "panel_room.gltf",
];

/// What `bench-vertices` measures and how.
#[derive(Clone, Copy, Debug)]
pub struct VertexBench {
    /// Lines of every bake (solved on pieces, as `bake` makes them).
    pub lines: u64,
    /// Seed of the lines.
    pub seed: u64,
    /// Frames measured, spread over the timeline from frame 0.
    pub frames: usize,
    /// Paths of the reference per vertex, in each of its two independent halves.
    pub paths: usize,
    /// Whether the patches are cut and merged where the light needs them (`auto`), or kept as
    /// the scene was loaded.
    pub auto: bool,
    /// Lightmaps measured too, at this many texels per scene unit, if any: at most
    /// `texel_limit` of their texels (evenly spread), with `texel_paths` paths of the
    /// reference each in each half.
    pub texels_per_unit: Option<f64>,
    pub texel_limit: usize,
    pub texel_paths: usize,
}

/// One scene's bake measured at its vertices.
#[derive(Clone, Debug, Serialize)]
pub struct VertexPoint {
    /// Scene file.
    pub scene: String,
    /// Lines traced.
    pub lines: usize,
    /// Patches the bake answered for.
    pub patches: usize,
    /// Vertices of the baked glTF at the measured frames (summed).
    pub vertices: usize,
    /// Frames baked.
    pub frames: usize,
    /// The frames measured.
    pub measured_frames: Vec<usize>,
    /// Wall time of the bake: tracing, patches, pieces, every frame solved.
    pub bake_seconds: f64,
    /// Wall time of the light at every vertex of every frame the bake writes (frames that share
    /// their solution evaluated once), as the bake's outputs evaluate it.
    pub vertex_seconds: f64,
    /// The light evaluated at the vertices ([`crate::output::light_vertices`]).
    pub evaluated: VertexMeasured,
    /// The mean of the patches around each vertex, weighed by their faces' areas: what the
    /// outputs carried before.
    pub averaged: VertexMeasured,
    /// The lightmap's texels, if measured.
    pub texels: Option<TexelPoint>,
}

/// One scene's lightmap measured at its texels' points.
#[derive(Clone, Debug, Serialize)]
pub struct TexelPoint {
    /// Texels per scene unit.
    pub texels_per_unit: f64,
    /// Texels the atlas covers, and those measured (evenly spread over them).
    pub covered: usize,
    pub measured: usize,
    /// Wall time of the lightmaps of every lighting state the bake writes (the vertices' light
    /// given, as the bake's outputs have it).
    pub texel_seconds: f64,
    /// The texels' radiance ([`crate::output::lightmap::Lightmap::texels`]); each texel weighs
    /// the same (one texel's area).
    pub evaluated: VertexMeasured,
    /// Each texel's patch's solved radiance: a lightmap filled from the patches.
    pub patches: VertexMeasured,
}

/// Values at vertices against the reference at the same points, over the measured frames.
/// Each vertex weighs a third of the area of its faces; a value is lit when the reference is
/// above [`DARK`] times the frame's mean over non-emitting vertices, in a channel its material
/// reflects.
#[derive(Clone, Debug, Default, Serialize)]
pub struct VertexMeasured {
    /// Area-weighted RMS of the relative error `(l − r) / r` over lit values, the reference's
    /// noise taken out in quadrature (from its two halves' difference).
    pub rms: Option<f64>,
    /// The same over the vertices on creases (a position with another vertex of the same side
    /// whose normal turns by more than 30°: where a floor meets a wall).
    pub crease_rms: Option<f64>,
    /// Share of the crease values above the reference (corners too bright).
    pub crease_too_bright: Option<f64>,
    /// Median of `|l − r| / r` over lit values (the reference's noise left in).
    pub median: Option<f64>,
    /// 90th percentile of the same.
    pub p90: Option<f64>,
    /// Area-weighted mean of the bake over the reference's, minus 1, on lit values.
    pub bias: Option<f64>,
    /// Share (by weight) of lit values within 2σ of the reference, σ the value's error bar and
    /// the reference's in quadrature (a value with no error bar is outside).
    pub coverage: Option<f64>,
    /// The reference's own relative noise on lit values (area-weighted RMS).
    pub reference_noise: Option<f64>,
    /// The brightest value (luminance) where the reference is dark (no light arrives), over
    /// the frame's mean: points under a resting object or inside a closed one.
    pub dark_max: Option<f64>,
    /// Lit values measured.
    pub lit_values: usize,
    /// Dark values (by the reference).
    pub dark_values: usize,
}

/// Bakes each of `scenes` as `bench` says and measures it at its vertices, each point given
/// to `measured` as soon as it is.
///
/// # Errors
/// When a scene cannot be traced or cut, or its lightmap cannot be unwrapped.
pub fn vertex_points(
    scenes: &[(String, Scene)],
    bench: VertexBench,
    mut measured: impl FnMut(&VertexPoint),
) -> Result<Vec<VertexPoint>, String> {
    let mut out = Vec::new();
    for (name, scene) in scenes {
        let run = timed_bake(scene, bench.lines, bench.seed, (bench.auto, true))
            .map_err(|e: TraceError| e.to_string())?;
        let bake = &run.bake;
        let power = bake.light_power();
        let sky = crate::solve::SolveParams::default().sky;
        let lighting = Lighting {
            materials: &bake.scene.materials,
            power: &power,
            sky,
        };
        let count = bake.scene.frames.count;
        let measured_frames = super::measured_frames(count, bench.frames);
        // Every frame's vertices, as the bake's outputs evaluate them.
        let started = Instant::now();
        let representatives = bake.representatives();
        let mut lit: Vec<Option<Vec<NodeMesh>>> = vec![None; count];
        for f in 0..count {
            if representatives[f] == f {
                lit[f] = Some(crate::output::lit_geometry(
                    bake,
                    f,
                    &run.solved[f],
                    lighting,
                ));
            }
        }
        let vertex_seconds = started.elapsed().as_secs_f64();
        let (mut evaluated, mut averaged) = (Tally::default(), Tally::default());
        let mut vertices = 0;
        for &f in &measured_frames {
            let Some(meshes) = &lit[representatives[f]] else {
                continue;
            };
            let points = crate::output::geometry::vertex_points(bake, meshes);
            vertices += points.len();
            let halves = [1, 2].map(|k| {
                crate::direct::reference::path_traced_points(
                    (&bake.scene, bake.tracer(), f),
                    &points,
                    bench.paths,
                    sky,
                    bench.seed ^ (0x5EED * k),
                )
            });
            let at = Vertices::of(bake, f, meshes, &run.solved[f].radiance);
            let values: Vec<PointRadiance> = (meshes.iter())
                .flat_map(|m| {
                    (m.radiance.iter().zip(&m.stderr)).map(|(&radiance, &stderr)| PointRadiance {
                        radiance,
                        stderr,
                        ..PointRadiance::default()
                    })
                })
                .collect();
            evaluated.add(&at, &values, &halves);
            let old: Vec<PointRadiance> = (at.averaged.iter())
                .map(|&radiance| PointRadiance {
                    radiance,
                    ..PointRadiance::default()
                })
                .collect();
            averaged.add(&at, &old, &halves);
        }
        let point = VertexPoint {
            scene: name.clone(),
            lines: bake.list().lines(),
            patches: bake.scene.patches.len(),
            vertices,
            frames: count,
            measured_frames,
            bake_seconds: run.seconds,
            vertex_seconds,
            evaluated: evaluated.finish(),
            averaged: averaged.finish(),
            texels: match bench.texels_per_unit {
                Some(density) => Some(texel_point(&run, &lit, (bench, density), lighting)?),
                None => None,
            },
        };
        measured(&point);
        out.push(point);
    }
    Ok(out)
}

/// `run`'s lightmap at `density` texels per unit measured at `bench`'s frames, every lighting
/// state's texels timed, from the lit vertices `lit` (per frame, its representatives').
fn texel_point(
    run: &super::Timed,
    lit: &[Option<Vec<NodeMesh>>],
    (bench, density): (VertexBench, f64),
    lighting: Lighting<'_>,
) -> Result<TexelPoint, String> {
    use crate::output::lightmap::Lightmap;
    let bake = &run.bake;
    let lightmap = Lightmap::new(bake, density)?;
    let count = bake.scene.frames.count;
    let representatives = bake.representatives();
    let started = Instant::now();
    let maps: Vec<Option<crate::output::lightmap::Texels>> = (0..count)
        .map(|f| {
            (representatives[f] == f).then(|| {
                let states = (&run.solved[f], lighting);
                lightmap.texels(bake, f, lit[f].as_deref(), states)
            })
        })
        .collect();
    let texel_seconds = started.elapsed().as_secs_f64();
    // An even spread of the covered texels.
    let texels: Vec<(usize, u32)> = lightmap.texel_patches().collect();
    let step = texels.len().div_ceil(bench.texel_limit.max(1)).max(1);
    let chosen: Vec<usize> = (0..texels.len()).step_by(step).collect();
    let mut points = crate::direct::points::Points::default();
    for &i in &chosen {
        points.push(lightmap.points().point(i).iter().cloned());
    }
    let shown = bake.shown();
    let (mut evaluated, mut patches) = (Tally::default(), Tally::default());
    for &f in &super::measured_frames(count, bench.frames) {
        let Some(map) = &maps[representatives[f]] else {
            continue;
        };
        let halves = [1, 2].map(|k| {
            crate::direct::reference::path_traced_points(
                (&bake.scene, bake.tracer(), f),
                &points,
                bench.texel_paths,
                lighting.sky,
                bench.seed ^ (0x7E1 * k),
            )
        });
        let radiance = &run.solved[f].radiance;
        let mut at = Vertices::default();
        let (mut values, mut flat) = (Vec::new(), Vec::new());
        for &i in &chosen {
            let (texel, patch) = texels[i];
            let p = &shown.patches[patch as usize];
            let m = &shown.materials[p.material as usize];
            at.weight.push(1.0);
            at.crease.push(false);
            at.material.push((m.reflectance, m.emission));
            at.averaged.push(radiance[patch as usize]);
            values.push(PointRadiance {
                radiance: map.radiance[texel].map(f64::from),
                stderr: map.stderr[texel].map(f64::from),
                ..PointRadiance::default()
            });
            flat.push(PointRadiance {
                radiance: radiance[patch as usize],
                ..PointRadiance::default()
            });
        }
        evaluated.add(&at, &values, &halves);
        patches.add(&at, &flat, &halves);
    }
    Ok(TexelPoint {
        texels_per_unit: density,
        covered: texels.len(),
        measured: chosen.len(),
        texel_seconds,
        evaluated: evaluated.finish(),
        patches: patches.finish(),
    })
}

/// What the measure needs of each vertex of one frame, in the order of the meshes' vertices.
#[derive(Default)]
struct Vertices {
    /// A third of its faces' area.
    weight: Vec<f64>,
    /// Whether it lies on a crease.
    crease: Vec<bool>,
    /// The reflectance and emission of its material.
    material: Vec<([f64; 3], [f64; 3])>,
    /// The area-weighted mean of its faces' patches (the outputs before issue 46).
    averaged: Vec<[f64; 3]>,
}

impl Vertices {
    fn of(
        bake: &crate::bake::Bake,
        frame: usize,
        meshes: &[NodeMesh],
        radiance: &[[f64; 3]],
    ) -> Self {
        let shown = bake.shown();
        let triangles = shown.triangles_at(frame);
        let crease = CREASE_COS;
        let mut out = Self {
            weight: Vec::new(),
            crease: Vec::new(),
            material: Vec::new(),
            averaged: Vec::new(),
        };
        for mesh in meshes {
            let mut at: std::collections::HashMap<[u64; 3], Vec<usize>> = Default::default();
            for (v, p) in mesh.positions.iter().enumerate() {
                at.entry(p.to_array().map(f64::to_bits))
                    .or_default()
                    .push(v);
            }
            for v in 0..mesh.positions.len() {
                let corners = mesh.corners_of(v);
                let (mut area, mut sum) = (0.0, [0.0; 3]);
                let mut material = ([0.0; 3], [0.0; 3]);
                for c in corners {
                    let (t, faces) = &triangles[c.triangle as usize];
                    let [a, b, d] = t.map(|x| x.as_dvec3());
                    let face_area = 0.5 * (b - a).cross(d - a).length();
                    let patch = if c.back {
                        faces.back
                    } else {
                        Some(faces.front)
                    };
                    let Some(patch) = patch else { continue };
                    let m = &shown.materials[shown.patches[patch as usize].material as usize];
                    material = (m.reflectance, m.emission);
                    area += face_area;
                    (0..3).for_each(|k| sum[k] += face_area * radiance[patch as usize][k]);
                }
                let n = mesh.normals[v].as_dvec3();
                let on_crease = at[&mesh.positions[v].to_array().map(f64::to_bits)]
                    .iter()
                    .any(|&u| {
                        let cos = mesh.normals[u].as_dvec3().dot(n);
                        u != v && cos < crease && cos > -crease
                    });
                out.weight.push(area / 3.0);
                out.crease.push(on_crease);
                out.material.push(material);
                out.averaged.push(if area > 0.0 {
                    sum.map(|s| s / area)
                } else {
                    [0.0; 3]
                });
            }
        }
        out
    }
}

/// The cosine of the angle past which two vertices at one place are on a crease.
const CREASE_COS: f64 = 0.866_025_403_784_438_6;

/// One lit value: its weight, relative error, the reference's relative half difference, and
/// whether its vertex is on a crease.
type LitValue = (f64, f64, f64, bool);

/// Sums towards a [`VertexMeasured`].
#[derive(Default)]
struct Tally {
    lit: Vec<LitValue>,
    within: f64,
    baked: f64,
    traced: f64,
    dark_max: Option<f64>,
    dark_values: usize,
}

impl Tally {
    /// Adds one frame: `values` at `at`'s vertices against the two halves of the reference.
    fn add(&mut self, at: &Vertices, values: &[PointRadiance], halves: &[Vec<PointRadiance>; 2]) {
        let reference: Vec<[f64; 3]> = (halves[0].iter().zip(&halves[1]))
            .map(|(a, b)| std::array::from_fn(|c| 0.5 * (a.radiance[c] + b.radiance[c])))
            .collect();
        // The frame's mean over non-emitting vertices, by the reference.
        let (mut sum, mut weight) = (0.0, 0.0);
        for (i, r) in reference.iter().enumerate() {
            if at.material[i].1 == [0.0; 3] {
                sum += at.weight[i] * luminance(*r);
                weight += at.weight[i];
            }
        }
        let mean = if weight > 0.0 { sum / weight } else { 0.0 };
        for (i, r) in reference.iter().enumerate() {
            let (rho, le) = at.material[i];
            if le != [0.0; 3] || at.weight[i] <= 0.0 {
                continue;
            }
            let l = values[i].radiance;
            if luminance(*r) <= DARK * mean {
                self.dark_values += 1;
                if mean > 0.0 {
                    let share = luminance(l) / mean;

                    self.dark_max = Some(self.dark_max.map_or(share, |m: f64| m.max(share)));
                }
                continue;
            }
            for c in 0..3 {
                if rho[c] <= 0.0 || r[c] <= 0.0 {
                    continue;
                }
                let w = at.weight[i];
                let half = 0.5 * (halves[0][i].radiance[c] - halves[1][i].radiance[c]);
                let own = 0.5 * halves[0][i].stderr[c].hypot(halves[1][i].stderr[c]);
                let e = (l[c] - r[c]) / r[c];
                self.lit.push((w, e, half / r[c], at.crease[i]));
                let sigma = values[i].stderr[c].hypot(own);
                if (l[c] - r[c]).abs() <= 2.0 * sigma {
                    self.within += w;
                }
                self.baked += w * l[c];
                self.traced += w * r[c];
            }
        }
    }

    fn finish(mut self) -> VertexMeasured {
        let rms = |keep: &dyn Fn(&LitValue) -> bool| {
            let (mut sum, mut noise, mut weight) = (0.0, 0.0, 0.0);
            for v in self.lit.iter().filter(|v| keep(v)) {
                sum += v.0 * v.1 * v.1;
                noise += v.0 * v.2 * v.2;
                weight += v.0;
            }
            (weight > 0.0).then(|| ((sum - noise).max(0.0) / weight).sqrt())
        };
        let weight: f64 = self.lit.iter().map(|v| v.0).sum();
        let measured = weight > 0.0;
        let creases: Vec<_> = self.lit.iter().filter(|v| v.3).collect();
        let too_bright = (!creases.is_empty())
            .then(|| creases.iter().filter(|v| v.1 > 0.0).count() as f64 / creases.len() as f64);
        let noise = measured
            .then(|| (self.lit.iter().map(|v| v.0 * v.2 * v.2).sum::<f64>() / weight).sqrt());
        let out = VertexMeasured {
            rms: rms(&|_| true),
            crease_rms: rms(&|v| v.3),
            crease_too_bright: too_bright,
            median: None,
            p90: None,
            bias: measured.then(|| self.baked / self.traced - 1.0),
            coverage: measured.then(|| self.within / weight),
            reference_noise: noise,
            dark_max: self.dark_max,
            lit_values: self.lit.len(),
            dark_values: self.dark_values,
        };
        self.lit.sort_by(|a, b| a.1.abs().total_cmp(&b.1.abs()));
        let quantile = |q: f64| {
            let k = ((self.lit.len() as f64 - 1.0) * q).round() as usize;
            self.lit.get(k).map(|v| v.1.abs())
        };
        VertexMeasured {
            median: quantile(0.5),
            p90: quantile(0.9),
            ..out
        }
    }
}
