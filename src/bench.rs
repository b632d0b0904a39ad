//! Benchmarks run by the `bench` command: what the engine costs on a given scene, measured in
//! one run so that ratios are meaningful on a shared machine.

pub mod native;
pub mod vertices;

use std::array::from_fn;
use std::borrow::Borrow;
use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::control::{Control, TraceError};
use crate::direct::reference::Estimate;
use crate::scene::{Material, Scene};
use crate::timeline::{IntersectionList, LineParams};
use crate::trace::{BuildEffort, Hit, ParallelLines, SceneTracer, Scratch};

/// Tracing figures: the multiframe list against tracing every frame independently.
#[derive(Clone, Debug, Serialize)]
pub struct TraceReport {
    /// Traced triangles of the scene.
    pub triangles: usize,
    /// Of which on moving objects.
    pub moving_triangles: usize,
    /// Frames of the timeline.
    pub frames: usize,
    /// Lines traced.
    pub lines: usize,
    /// Threads used.
    pub threads: usize,
    /// Building the BVHs (static and rigid objects), seconds.
    pub bvh_seconds: f64,
    /// The effort their build was given.
    pub bvh_effort: BuildEffort,
    /// Building the multiframe list, seconds.
    pub list_seconds: f64,
    /// Crossings stored in the list (static once, moving once per frame).
    pub list_hits: usize,
    /// Crossings traced per second while building the list.
    pub list_hits_per_second: f64,
    /// Crossings available to the solver, summed over frames (static ones counted every
    /// frame), per second of list building.
    pub frame_hits_per_second: f64,
    /// Bytes of the list.
    pub list_bytes: usize,
    /// Bytes per stored crossing, offsets included.
    pub bytes_per_hit: f64,
    /// Building one list per frame, each traced from scratch (static geometry again every
    /// frame), seconds.
    pub independent_seconds: f64,
    /// Crossings found by the independent tracing, summed over frames.
    pub independent_hits: usize,
    /// Bytes the independent per-frame lists would take (8 per crossing, 4 per line per frame).
    pub independent_bytes: usize,
    /// Crossings traced per second by the independent tracing.
    pub independent_hits_per_second: f64,
    /// independent_seconds / list_seconds.
    pub time_ratio: f64,
    /// independent_bytes / list_bytes.
    pub memory_ratio: f64,
    /// Frame 0 traced alone by this tracer and by native Embree, when asked for.
    pub native: Option<native::NativeComparison>,
}

/// Measures tracing on `scene` with about `lines` lines.
///
/// With `native`, a directory to build the native Embree comparison program in, it also traces
/// frame 0 alone with this tracer and with native Embree ([`native::compare`]).
pub fn trace(
    scene: &Scene,
    lines: u64,
    seed: u64,
    native: Option<&std::path::Path>,
    effort: BuildEffort,
) -> Result<TraceReport, TraceError> {
    let start = Instant::now();
    let tracer = SceneTracer::with_effort(scene, effort);
    let bvh_seconds = start.elapsed().as_secs_f64();

    let params = LineParams { lines, seed };
    let build_list = || IntersectionList::build(scene, &tracer, &params, &Control::default());
    let start = Instant::now();
    let list = build_list()?;
    let list_seconds = start.elapsed().as_secs_f64();
    let memory = list.memory();
    let bundles: Vec<ParallelLines> = list
        .bundles(scene)
        .map(|(_, b)| ParallelLines::new(b.direction, b.origins))
        .collect();
    // Every moving crossing belongs to one frame; every static one to all of them.
    let frame_hits = memory.static_hits * scene.frames.count + memory.moving_hits;

    // The alternative to the multiframe list: one list per frame (CSR: an offset per line and
    // the sorted crossings), each traced from scratch.
    let start = Instant::now();
    let mut independent_hits = 0;
    for frame in 0..scene.frames.count {
        let deformed = tracer.deformed_at(scene, frame);
        let chunks: Vec<(Vec<u32>, Vec<Hit>)> = bundles
            .par_iter()
            .map_init(
                || (Scratch::default(), Vec::new()),
                |(scratch, found), lines| {
                    let starts =
                        tracer.trace_frame_parallel(lines, frame, &deformed, scratch, found);
                    (
                        starts[1..].to_vec(),
                        found.iter().map(|&(_, hit)| hit).collect(),
                    )
                },
            )
            .collect();
        let mut offsets = Vec::with_capacity(list.lines() + 1);
        let mut hits = Vec::new();
        offsets.push(0u32);
        for (chunk_offsets, chunk_hits) in chunks {
            let base = hits.len() as u32;
            offsets.extend(chunk_offsets.iter().map(|o| base + o));
            hits.extend_from_slice(&chunk_hits);
        }
        independent_hits += hits.len();
    }
    let independent_seconds = start.elapsed().as_secs_f64();
    let independent_bytes =
        independent_hits * size_of::<Hit>() + scene.frames.count * (list.lines() + 1) * 4;
    let moving_triangles = scene.objects.iter().map(|o| o.mesh.triangles.len()).sum();
    Ok(TraceReport {
        triangles: tracer.triangles(),
        moving_triangles,
        frames: scene.frames.count,
        lines: list.lines(),
        threads: rayon::current_num_threads(),
        bvh_seconds,
        bvh_effort: effort,
        list_seconds,
        list_hits: memory.hits(),
        list_hits_per_second: memory.hits() as f64 / list_seconds,
        frame_hits_per_second: frame_hits as f64 / list_seconds,
        list_bytes: memory.bytes,
        bytes_per_hit: memory.bytes_per_hit(),
        independent_seconds,
        independent_hits,
        independent_bytes,
        independent_hits_per_second: independent_hits as f64 / independent_seconds,
        time_ratio: independent_seconds / list_seconds,
        memory_ratio: independent_bytes as f64 / memory.bytes as f64,
        native: native.map(|dir| {
            let list = || {
                let start = Instant::now();
                let hits = build_list().ok()?.memory().hits();
                Some((hits, start.elapsed().as_secs_f64()))
            };
            let threads = rayon::current_num_threads();
            native::compare(scene, &tracer, &bundles, dir, threads, effort, &list)
        }),
    })
}

impl std::fmt::Display for TraceReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let m = |x: f64| x / 1e6;
        writeln!(
            f,
            "scene            {} triangles ({} moving), {} frames",
            self.triangles, self.moving_triangles, self.frames
        )?;
        writeln!(
            f,
            "lines            {} on {} threads",
            self.lines, self.threads
        )?;
        writeln!(
            f,
            "BVH build        {:.3} s ({} effort)",
            self.bvh_seconds,
            self.bvh_effort.name()
        )?;
        writeln!(
            f,
            "multiframe list  {:.3} s, {} crossings, {:.1} M crossings/s traced, {:.1} M frame-crossings/s delivered",
            self.list_seconds,
            self.list_hits,
            m(self.list_hits_per_second),
            m(self.frame_hits_per_second)
        )?;
        writeln!(
            f,
            "list memory      {:.1} MiB, {:.2} bytes per crossing",
            self.list_bytes as f64 / 1048576.0,
            self.bytes_per_hit
        )?;
        writeln!(
            f,
            "every frame alone {:.3} s, {} crossings, {:.1} M crossings/s, {:.1} MiB",
            self.independent_seconds,
            self.independent_hits,
            m(self.independent_hits_per_second),
            self.independent_bytes as f64 / 1048576.0
        )?;
        writeln!(
            f,
            "multiframe gain  {:.1}x time, {:.1}x memory",
            self.time_ratio, self.memory_ratio
        )?;
        match &self.native {
            Some(native) => write!(f, "{native}"),
            None => Ok(()),
        }
    }
}

/// One point of the speed/accuracy trade: a scene baked with a line budget, its patches made
/// as a bake makes them, solved on pieces, against physics.
#[derive(Clone, Debug, Serialize)]
pub struct AccuracyPoint {
    /// Scene file.
    pub scene: String,
    /// How the patches were made.
    pub patch_size: crate::params::PatchSize,
    /// What the error is measured against.
    pub reference: String,
    /// Frames baked.
    pub frames: usize,
    /// The frames measured (all of them against a closed form; a few against the path tracer).
    pub measured_frames: Vec<usize>,
    /// Lines traced.
    pub lines: usize,
    /// Patches the bake answered for.
    pub patches: usize,
    /// Wall time: tracing, making the patches, cutting the pieces and solving every frame.
    pub seconds: f64,
    /// The bake against the reference.
    #[serde(flatten)]
    pub error: Measured,
}

/// Which (patch, channel) values a per-patch error is taken over.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PatchClass {
    /// Lit, non-emitting surfaces: what people look at on a wall.
    Lit,
    /// Emitting surfaces, measured apart: they are bright, and an error relative to their
    /// emission says little about the light they throw.
    Emitter,
}

/// Below this fraction of a frame's mean radiance over non-emitting surfaces ([`dark_floor`]),
/// a value is dark: the tone map puts the log-average of those surfaces at 0.18, so a dark
/// value shows at most a step or two above black in 8-bit sRGB (whose first step is 3e-4
/// linear), and its relative error is nowhere people look. Counted, such values would swamp
/// the measure: faces in contact that should receive nothing receive a trace in some bakes and
/// none in others (the sliding block's bottom in the moving Cornell box: 4e-7 to 1e-6 with 40M
/// lines, 0 with 3M; the open door's hinge-side edge, pressed against the wall at 90°, in the
/// level: 2e-5 with 40M lines, 1e-3 with 10M; lit walls are about 0.1 to 0.2), relative errors
/// of 100% to 4000%.
pub const DARK: f64 = 1e-3;

/// Per channel, the radiance at or below which a value of `radiance` (one frame) is dark:
/// [`DARK`] times the area-weighted mean over non-emitting patches that reflect in the channel.
#[must_use]
pub fn dark_floor(scene: &Scene, radiance: &[[f64; 3]]) -> [f64; 3] {
    [0, 1, 2].map(|c| {
        let (mut sum, mut area) = (0.0, 0.0);
        for (p, l) in scene.patches.iter().zip(radiance) {
            let m = &scene.materials[p.material as usize];
            if !m.is_emitter() && m.reflectance[c] > 0.0 {
                sum += p.area * l[c];
                area += p.area;
            }
        }
        if area > 0.0 { DARK * sum / area } else { 0.0 }
    })
}

impl PatchClass {
    /// The class of channel `channel` of a patch of `material` whose radiance is `radiance`
    /// (the reference's, or the bake's own for its error estimate), `dark` being that frame's
    /// [`dark_floor`]; `None` when the value has no relative error to measure: a channel that
    /// reflects nothing is exactly its emission, and a dark surface has no scale to be
    /// relative to.
    #[must_use]
    pub fn of(material: &Material, channel: usize, radiance: f64, dark: [f64; 3]) -> Option<Self> {
        if material.reflectance[channel] <= 0.0 || radiance <= dark[channel].max(0.0) {
            None
        } else if material.is_emitter() {
            Some(Self::Emitter)
        } else {
            Some(Self::Lit)
        }
    }
}

/// Area-weighted root mean square `sqrt(Σ A x² / Σ A)`: every square metre of surface counts
/// the same, however finely it is cut into patches.
#[derive(Clone, Copy, Debug, Default)]
struct AreaRms {
    sum: f64,
    area: f64,
    values: usize,
}

impl AreaRms {
    fn add(&mut self, area: f64, x: f64) {
        self.sum += area * x * x;
        self.area += area;
        self.values += 1;
    }

    /// `None` when nothing (of positive area) was added.
    fn value(&self) -> Option<f64> {
        (self.area > 0.0).then(|| (self.sum / self.area).sqrt())
    }
}

/// A bake's error against a reference, over the frames the reference has.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Measured {
    /// Area-weighted RMS of the per-patch relative error `(l − r) / r` over lit, non-emitting
    /// values ([`PatchClass::Lit`] by the reference: (patch, channel, frame) with `r` above the
    /// frame's [`dark_floor`], a material that emits nothing and reflects in that channel), the
    /// reference's own noise taken out in quadrature (from its two halves' difference). The
    /// error a viewer sees on a wall. `None` when the scene has no such value (the furnace,
    /// where everything emits).
    pub lit_error: Option<f64>,
    /// The relative L² error of the patch-constant answer against the true radiance at
    /// uniformly random points on the lit values: the patches' means against the true means
    /// plus each patch's own variation ([`crate::direct::reference::Estimate::spread`]), what a
    /// baked lightmap shows. `None` against a closed form, which gives only the means.
    pub point_error: Option<f64>,
    /// The smallest [`Measured::point_error`] the reference resolves: the square root of twice
    /// the standard error of the squared error at points, which the reference's estimate of the
    /// patches' own variation dominates (its paths' noise at a point is far larger than the
    /// variation within a small patch; measured from its two halves). An error at points below
    /// it reads anywhere from 0 to about it.
    pub point_resolution: Option<f64>,
    /// [`Measured::point_error`] without the patches' own variation: the patches' means
    /// against the true means, as a relative L² error.
    pub patch_l2_error: Option<f64>,
    /// The area-weighted mean of the bake over the reference's, minus 1, on the lit values.
    pub bias: Option<f64>,
    /// The reference's own per-patch noise on the lit values (area-weighted RMS, relative).
    pub reference_noise: Option<f64>,
    /// The bake's error bars on the lit values a line sampled: area-weighted RMS of σ / r.
    pub estimated_noise: Option<f64>,
    /// The same as [`Measured::lit_error`] over emitting patches (channels that reflect), the
    /// reference's noise left in; `None` when there are none.
    pub emitter_error: Option<f64>,
    /// `sqrt(Σ A (l − r)² / Σ A r²)` over every value that reflects, emitters included: the
    /// measure of the figures before issue 12, which bright emitters dominate. Kept only to
    /// compare with those figures.
    pub total_error: f64,
    /// Share (by area) of the lit, non-emitting values within 2σ of the reference, σ the bake's
    /// error bar and the reference's own standard error in quadrature (a patch the bake did
    /// not sample has no σ and counts as outside): about 0.95 when the error bars are honest.
    /// `None` without such values.
    pub coverage: Option<f64>,
    /// Median of |l − r| / σ over the lit, non-emitting values: about 0.67 for honest Gaussian
    /// error bars, less when they are conservative. `None` without such values.
    pub median_z: Option<f64>,
    /// The mean of the square of the reference's half difference over its own variance on the
    /// lit values: about 1 when the reference's own error estimate is honest (which
    /// [`Measured::coverage`] relies on). `None` against a closed form.
    pub reference_calibration: Option<f64>,
    /// Lit, non-emitting (patch, channel, frame) values measured.
    pub lit_values: usize,
    /// Emitting (patch, channel, frame) values measured.
    pub emitter_values: usize,
    /// Non-emitting values that reflect but are dark in the reference (0, or at most its
    /// [`dark_floor`]): left out of every measure above but `total_error`.
    pub dark_values: usize,
    /// (share of the lit squared error, patch), most first, at most [`WORST`]; the frame's
    /// own when one frame is measured.
    #[serde(skip)]
    pub worst: Vec<(f64, usize)>,
}

/// Per frame, per patch, per channel.
type PerFrame<T> = Vec<Vec<[T; 3]>>;

/// A scene's reference radiance at some of its frames, with its own standard error (0 for
/// closed forms), and for a path-traced one the half difference of its two independent halves
/// (a draw of its noise) and the variance of the true radiance over each patch.
#[derive(Clone)]
struct Reference {
    name: String,
    /// The frames the values are for.
    frames: Vec<usize>,
    values: PerFrame<f64>,
    sigma: PerFrame<f64>,
    half_difference: Option<PerFrame<f64>>,
    /// The spread and half the difference of its two halves' estimates.
    spread: Option<PerFrame<(f64, f64)>>,
    /// Per frame and patch, the share of its area no surface touches (what can be seen of it,
    /// which it is measured over and weighs by); all of it if `None`.
    visible: Option<Vec<Vec<f64>>>,
}

/// The relative standard error under which a patch's path-traced reference is believed
/// ([`reference_halves`]). Where light reaches a patch only by rare paths (deep in a 2 cm gap,
/// from a lit rim half a metre away), a few hundred paths mostly miss it: the estimate and
/// its standard error come out far too low together (the level's ceiling above a fixture read
/// 0.0049 with 122 paths a half where 200,000 read 0.164 ± 0.003), and the bake was charged
/// with the reference's error. A standard error above this share of the estimate says few
/// paths found the light.
pub const REFERENCE_PRECISION: f64 = 0.25;

/// How many times the paths of a patch whose reference is not believed are doubled at most
/// ([`reference_halves`]): up to 64 times the first count.
pub const REFERENCE_DOUBLINGS: u32 = 6;

/// Two independent path-traced estimates of every patch of `scene` at `frame`, from
/// `per_patch` paths each, and as many again, doubling, where their pooled relative standard
/// error is above [`REFERENCE_PRECISION`] or nothing was found on a patch that reflects (up to
/// [`REFERENCE_DOUBLINGS`] times); each half pooled over its rounds by paths.
#[must_use]
pub fn reference_halves(
    (scene, tracer): (&Scene, &SceneTracer),
    frame: usize,
    per_patch: usize,
    sky: [f64; 3],
    seed: u64,
) -> (Vec<Estimate>, Vec<Estimate>) {
    use crate::output::tonemap::luminance;
    let traced = |paths: &(dyn Fn(usize) -> usize + Sync), seed| {
        crate::direct::reference::path_traced_each(scene, tracer, frame, paths, sky, seed)
    };
    let mut halves = [
        traced(&|_| per_patch, seed + 6),
        traced(&|_| per_patch, seed + 1006),
    ];
    let mut paths = vec![per_patch; scene.patches.len()];
    for round in 0..REFERENCE_DOUBLINGS {
        let unsure: Vec<bool> = (0..scene.patches.len())
            .map(|i| {
                let (a, b) = (&halves[0][i], &halves[1][i]);
                let mean = 0.5 * (luminance(a.radiance) + luminance(b.radiance));
                let stderr = 0.5 * luminance(a.stderr).hypot(luminance(b.stderr));
                let reflects =
                    luminance(scene.materials[scene.patches[i].material as usize].reflectance)
                        > 0.0;
                let visible = a.visible.min(b.visible) > 0.0;
                reflects && visible && (stderr > REFERENCE_PRECISION * mean || mean <= 0.0)
            })
            .collect();
        if !unsure.contains(&true) {
            break;
        }
        let more = |i: usize| if unsure[i] { paths[i] } else { 0 };
        let round = u64::from(round + 1) * 7919;
        for (half, offset) in halves.iter_mut().zip([6, 1006]) {
            let drawn = traced(&more, seed + offset + round);
            for (i, e) in drawn.iter().enumerate() {
                if unsure[i] {
                    half[i] = pooled(&half[i], paths[i], e, paths[i]);
                }
            }
        }
        for (i, &u) in unsure.iter().enumerate() {
            paths[i] *= 1 + usize::from(u);
        }
    }
    let [first, second] = halves;
    (first, second)
}

/// Two estimates of one patch from `n` and `m` paths, as one from all of them.
fn pooled(a: &Estimate, n: usize, b: &Estimate, m: usize) -> Estimate {
    let (n, m) = (n as f64, m as f64);
    let total = n + m;
    let mean = |x: f64, y: f64| (n * x + m * y) / total;
    Estimate {
        radiance: from_fn(|c| mean(a.radiance[c], b.radiance[c])),
        stderr: from_fn(|c| (n * a.stderr[c]).hypot(m * b.stderr[c]) / total),
        spread: from_fn(|c| mean(a.spread[c], b.spread[c])),
        visible: mean(a.visible, b.visible),
    }
}

/// The path-traced reference ([`crate::direct::reference::path_traced`]) of `bake`'s patches
/// at `frames`: per frame, two independent estimates of half of `paths` each (at least 32 per
/// patch each), their mean the reference, half their difference a draw of its noise.
fn path_traced(
    bake: &crate::bake::Bake,
    frames: &[usize],
    paths: usize,
    sky: [f64; 3],
    seed: u64,
) -> Reference {
    let scene = &bake.scene;
    let per_patch = (paths / 2 / scene.patches.len().max(1)).max(32);
    let (mut values, mut sigma, mut half_difference, mut spread) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut visible = Vec::new();
    for &frame in frames {
        let (first, second) = reference_halves((scene, bake.tracer()), frame, per_patch, sky, seed);
        let pairs = || first.iter().zip(&second);
        values.push(
            pairs()
                .map(|(a, b)| from_fn(|c| 0.5 * (a.radiance[c] + b.radiance[c])))
                .collect(),
        );
        sigma.push(
            pairs()
                .map(|(a, b)| from_fn(|c| 0.5 * a.stderr[c].hypot(b.stderr[c])))
                .collect(),
        );
        half_difference.push(
            pairs()
                .map(|(a, b)| from_fn(|c| 0.5 * (a.radiance[c] - b.radiance[c])))
                .collect(),
        );
        visible.push(
            pairs()
                .map(|(a, b)| 0.5 * (a.visible + b.visible))
                .collect(),
        );
        spread.push(
            pairs()
                .map(|(a, b)| {
                    from_fn(|c| {
                        (
                            0.5 * (a.spread[c] + b.spread[c]),
                            0.5 * (a.spread[c] - b.spread[c]),
                        )
                    })
                })
                .collect(),
        );
    }
    Reference {
        name: format!("path tracer, {per_patch} paths per patch twice"),
        frames: frames.to_vec(),
        values,
        sigma,
        half_difference: Some(half_difference),
        spread: Some(spread),
        visible: Some(visible),
    }
}

/// A bake timed from tracing to the last frame solved.
struct Timed {
    bake: crate::bake::Bake,
    solved: Vec<crate::solve::FrameSolution>,
    seconds: f64,
}

/// Bakes `scene` with `lines` lines from `seed` as the bake command does: traced, its patches
/// cut and merged if `auto`, split into pieces if `split`, every frame solved.
fn timed_bake(
    scene: &Scene,
    lines: u64,
    seed: u64,
    (auto, split): (bool, bool),
) -> Result<Timed, TraceError> {
    let start = Instant::now();
    let params = LineParams { lines, seed };
    let mut bake = crate::bake::Bake::trace(scene.clone(), &params)?;
    let solve = crate::solve::SolveParams::default();
    if auto {
        let standard = crate::adaptive::Adaptive::for_lines(lines, bake.scene.patches.len());
        crate::adaptive::adapt(&mut bake, &standard, &solve, &Control::default())?;
    }
    if split {
        bake.split(&solve, &Control::default())?;
    }
    let solved = bake.solve_all(&bake.scene.materials, &solve);
    let seconds = start.elapsed().as_secs_f64();
    let solved = solved.iter().map(|s| (**s).clone()).collect();
    Ok(Timed {
        bake,
        solved,
        seconds,
    })
}

/// Closed-form references where the sample scenes have one, per patch of `scene` (its
/// patches however made): the furnace (L = Le / (1 − ρ)) and the parallel squares' receiver
/// (ρ · F, the emitter being black: the area mean over the patch's triangles).
fn closed_form(name: &str, scene: &Scene) -> Option<Reference> {
    let frames = scene.frames.count;
    let emission = |p: &crate::scene::Patch| scene.materials[p.material as usize].emission;
    let per_patch: Vec<[f64; 3]> = match name {
        "furnace.gltf" => scene
            .patches
            .iter()
            .map(|p| {
                let m = &scene.materials[p.material as usize];
                [0, 1, 2].map(|c| m.emission[c] / (1.0 - m.reflectance[c]))
            })
            .collect(),
        "parallel_squares.gltf" => {
            // Σ area · ρF over each patch's front faces (the receiver faces the emitter), then
            // over the patch's area.
            let mut sums = vec![(0.0, 0.0); scene.patches.len()];
            let (n, mesh) = (scene.normalisation, &scene.statics);
            for (t, faces) in mesh.triangles.iter().zip(&mesh.faces) {
                let corners = t.map(|v| n.to_scene(mesh.positions[v as usize].as_dvec3()));
                let area =
                    crate::scene::subdivide::triangle_area(corners[0], corners[1], corners[2]);
                let f = crate::solve::analytic::triangle_to_parallel_rectangle(
                    corners,
                    (-0.5, 0.5),
                    (-0.5, 0.5),
                    0.0,
                );
                let (sum, a) = &mut sums[faces.front as usize];
                *sum += area * f;
                *a += area;
            }
            (scene.patches.iter().zip(sums))
                .map(|(p, (sum, a))| {
                    let m = &scene.materials[p.material as usize];
                    if m.is_emitter() || a <= 0.0 {
                        return emission(p);
                    }
                    m.reflectance.map(|r| r * sum / a)
                })
                .collect()
        }
        _ => return None,
    };
    Some(Reference {
        name: "closed form".into(),
        frames: (0..frames).collect(),
        sigma: vec![vec![[0.0; 3]; per_patch.len()]; frames],
        values: vec![per_patch; frames],
        half_difference: None,
        spread: None,
        visible: None,
    })
}

/// The error of `solved` (every frame of the bake) against `reference` at its frames
/// ([`Measured`]).
fn compare(
    scene: &Scene,
    solved: &[crate::solve::FrameSolution],
    reference: &Reference,
) -> Measured {
    let (mut lit, mut emitters) = (AreaRms::default(), AreaRms::default());
    let (mut num, mut den, mut dark_values) = (0.0, 0.0, 0usize);
    let (mut within, mut noise, mut estimated, mut sampled) = (0.0, 0.0, 0.0, 0.0);
    let (mut squared_error, mut spread, mut squared, mut noise_squared) = (0.0, 0.0, 0.0, 0.0);
    let (mut baked, mut traced, mut calibration, mut spread_noise) = (0.0, 0.0, 0.0, 0.0);
    let mut contributions: Vec<(f64, usize)> = Vec::new();
    let mut z = Vec::new();
    for (k, &f) in reference.frames.iter().enumerate() {
        let s = &solved[f];
        let values = &reference.values[k];
        let dark = dark_floor(scene, values);
        for (i, p) in scene.patches.iter().enumerate() {
            let m = &scene.materials[p.material as usize];
            // What can be seen of the patch weighs (a floor patch under a box, the rest).
            let area = p.area * reference.visible.as_ref().map_or(1.0, |v| v[k][i]);
            // The halves' difference in this patch's spread, over its channels (which share
            // their paths).
            let mut spread_apart = 0.0;
            for c in 0..3 {
                if m.reflectance[c] <= 0.0 {
                    continue;
                }
                let (l, r) = (s.radiance[i][c], values[i][c]);
                num += area * (l - r).powi(2);
                den += area * r * r;
                match PatchClass::of(m, c, r, dark) {
                    Some(PatchClass::Emitter) => emitters.add(area, (l - r) / r),
                    Some(PatchClass::Lit) => {
                        let e = (l - r) / r;
                        lit.add(area, e);
                        if reference.frames.len() == 1 {
                            match contributions.last_mut() {
                                Some((sum, j)) if *j == i => *sum += area * e * e,
                                _ => contributions.push((area * e * e, i)),
                            }
                        }
                        let own = reference.sigma[k][i][c];
                        let h = (reference.half_difference.as_ref()).map_or(0.0, |h| h[k][i][c]);
                        if own > 0.0 {
                            calibration += area * (h / own).powi(2);
                        }
                        noise += area * (h / r).powi(2);
                        squared_error += area * ((l - r).powi(2) - h * h);
                        if let Some(s) = reference.spread.as_ref() {
                            spread += area * s[k][i][c].0;
                            spread_apart += area * s[k][i][c].1;
                        }
                        squared += area * r * r;
                        noise_squared += area * h * h;
                        baked += area * l;
                        traced += area * r;
                        // A patch no line crossed has no error bar: never covered.
                        if let Some(e) = s.stderr[i] {
                            let sigma = e[c].hypot(own);
                            if (l - r).abs() <= 2.0 * sigma + 1e-9 * r {
                                within += area;
                            }
                            if sigma > 0.0 {
                                z.push((l - r).abs() / sigma);
                            }
                            estimated += area * (e[c] / r).powi(2);
                            sampled += area;
                        }
                    }
                    None => dark_values += usize::from(!m.is_emitter()),
                }
            }
            spread_noise += spread_apart * spread_apart;
        }
    }
    z.sort_by(f64::total_cmp);
    contributions.sort_by(|a, b| b.0.total_cmp(&a.0));
    contributions.truncate(WORST);
    let area = lit.area;
    let measured = lit.values > 0 && area > 0.0;
    let path_traced = reference.half_difference.is_some();
    Measured {
        lit_error: measured.then(|| ((lit.sum - noise).max(0.0) / area).sqrt()),
        point_error: (measured && reference.spread.is_some()).then(|| {
            // The true radiance's mean square over points is the means' (less the reference's
            // noise, which r² also holds) plus the spread within the patches.
            ((squared_error + spread).max(0.0) / (squared - noise_squared + spread)).sqrt()
        }),
        patch_l2_error: measured
            .then(|| (squared_error.max(0.0) / (squared - noise_squared)).sqrt()),
        point_resolution: (measured && reference.spread.is_some()).then(|| {
            (2.0 * spread_noise.sqrt() / (squared - noise_squared + spread).max(f64::MIN_POSITIVE))
                .sqrt()
        }),
        bias: measured.then(|| baked / traced - 1.0),
        reference_noise: (measured && path_traced).then(|| (noise / area).sqrt()),
        estimated_noise: (sampled > 0.0).then(|| (estimated / sampled).sqrt()),
        emitter_error: emitters.value(),
        total_error: (num / den.max(f64::MIN_POSITIVE)).sqrt(),
        coverage: measured.then(|| within / area),
        median_z: z.get(z.len() / 2).copied(),
        reference_calibration: (measured && path_traced).then(|| calibration / area),
        lit_values: lit.values,
        emitter_values: emitters.values,
        dark_values,
        worst: (contributions.iter())
            .map(|&(e, i)| (e / lit.sum, i))
            .collect(),
    }
}

/// The bake's own estimate of its error, the measure of [`Measured::lit_error`] with the
/// reported standard error in place of the error: the area-weighted RMS of σ / L over lit,
/// non-emitting values (by the bake's own radiance L and [`dark_floor`]) that lines sampled,
/// over every frame. `None` when there are none.
#[must_use]
pub fn estimated_error(
    scene: &Scene,
    solved: &[impl Borrow<crate::solve::FrameSolution>],
) -> Option<f64> {
    let mut lit = AreaRms::default();
    for s in solved.iter().map(Borrow::borrow) {
        let dark = dark_floor(scene, &s.radiance);
        for (i, p) in scene.patches.iter().enumerate() {
            let Some(e) = s.stderr[i] else { continue };
            let m = &scene.materials[p.material as usize];
            for (c, (sigma, l)) in e.iter().zip(s.radiance[i]).enumerate() {
                if PatchClass::of(m, c, l, dark) == Some(PatchClass::Lit) {
                    lit.add(p.area, sigma / l);
                }
            }
        }
    }
    lit.value()
}

/// How `bench-accuracy` measures each bake against physics where no closed form exists.
#[derive(Clone, Copy, Debug)]
pub struct PathReference {
    /// Paths of the reference per measured frame, over all the bake's patches (at least 64
    /// per patch).
    pub paths: usize,
    /// Frames measured, spread evenly over the timeline from frame 0.
    pub frames: usize,
}

/// The `count` frames of a timeline of `frames` measured against the path tracer: evenly
/// spread from frame 0 (frame k·frames/count), so an animation that returns to its start is
/// measured on its way out.
fn measured_frames(frames: usize, count: usize) -> Vec<usize> {
    let count = count.clamp(1, frames.max(1));
    (0..count).map(|k| k * frames / count).collect()
}

/// Sweeps the line budget on each scene (its patches made as `patch_size` says, split into
/// pieces and solved as a bake does) and measures error against time: against the closed form
/// where the scene has one (every frame), else against the path tracer
/// ([`PathReference`]) at a few frames. Unless the patches are `auto`'s, every budget bakes
/// the same patches: the path tracer then runs once per scene and every budget is measured
/// against it (its noise, taken out of each, is shared), so that a reference fine enough for
/// the largest budget costs its time once.
///
/// # Errors
/// When a scene cannot be traced or cut.
pub fn accuracy(
    scenes: &[(String, Scene)],
    budgets: &[u64],
    patch_size: crate::params::PatchSize,
    reference: PathReference,
    mut progress: impl FnMut(&AccuracyPoint),
) -> Result<Vec<AccuracyPoint>, TraceError> {
    let mut points = Vec::new();
    let auto = patch_size == crate::params::PatchSize::Auto;
    for (name, scene) in scenes {
        let mut traced: Option<Reference> = None;
        for &lines in budgets {
            let run = timed_bake(scene, lines, 1, (auto, true))?;
            let baked = &run.bake.scene;
            let against = match (closed_form(name, baked), &traced) {
                (Some(exact), _) => exact,
                (None, Some(shared)) if !auto => shared.clone(),
                (None, _) => {
                    let frames = measured_frames(baked.frames.count, reference.frames);
                    let sky = crate::solve::SolveParams::default().sky;
                    let paths = path_traced(&run.bake, &frames, reference.paths, sky, 0x5EED);
                    traced.insert(paths).clone()
                }
            };
            let point = AccuracyPoint {
                scene: name.clone(),
                patch_size,
                reference: against.name.clone(),
                frames: baked.frames.count,
                measured_frames: against.frames.clone(),
                lines: run.bake.list().lines(),
                patches: baked.patches.len(),
                seconds: run.seconds,
                error: compare(baked, &run.solved, &against),
            };
            progress(&point);
            points.push(point);
        }
    }
    Ok(points)
}

/// The multiframe gain at equal error: one bake of the whole timeline against one bake per
/// frame with the same lines (each frame's scene loaded alone, everything static).
#[derive(Clone, Debug, Serialize)]
pub struct MultiframeGain {
    /// Frames of the timeline.
    pub frames: usize,
    /// Lines per bake.
    pub lines: usize,
    /// The multiframe bake, seconds.
    pub multiframe_seconds: f64,
    /// The per-frame bakes together, seconds.
    pub independent_seconds: f64,
    /// independent / multiframe.
    pub ratio: f64,
}

/// Measures [`MultiframeGain`]: `load_frame(t)` loads the scene with its one frame at time t.
pub fn multiframe_gain(
    scene: &Scene,
    lines: u64,
    load_frame: impl Fn(f64) -> Option<Scene>,
) -> Result<Option<MultiframeGain>, TraceError> {
    let whole = timed_bake(scene, lines, 1, (false, false))?;
    let start = Instant::now();
    for f in 0..scene.frames.count {
        let Some(single) = load_frame(scene.frames.time(f)) else {
            return Ok(None);
        };
        timed_bake(&single, lines, 1, (false, false))?;
    }
    let independent_seconds = start.elapsed().as_secs_f64();
    Ok(Some(MultiframeGain {
        frames: scene.frames.count,
        lines: whole.bake.list().lines(),
        multiframe_seconds: whole.seconds,
        independent_seconds,
        ratio: independent_seconds / whole.seconds,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::FrameSolution;

    /// A loaded sample scene.
    fn sample(file_name: &str) -> Scene {
        let sample = crate::samples::all()
            .into_iter()
            .find(|s| s.file_name == file_name)
            .unwrap();
        crate::loader::load(sample.gltf.as_bytes(), &Default::default()).unwrap()
    }

    fn solution(radiance: Vec<[f64; 3]>, stderr: Vec<Option<[f64; 3]>>) -> FrameSolution {
        FrameSolution {
            pieces: Vec::new(),
            pieces_stderr: Vec::new(),
            shape: Vec::new(),
            spread: Vec::new(),
            first: Vec::new(),
            samples: stderr.iter().map(|e| u64::from(e.is_some())).collect(),
            radiance,
            stderr,
            iterations: 1,
            residual: 0.0,
            converged: true,
        }
    }

    fn close(a: Option<f64>, b: f64) -> bool {
        a.is_some_and(|a| (a - b).abs() <= 1e-12 * b.abs().max(1.0))
    }

    /// Issue 12: the error of the figures was `sqrt(Σ A (l−r)² / Σ A r²)` over every patch, which
    /// the bright ceiling light dominated. Here the light is off by 400% and the lit patches by
    /// exactly 3% each: the lit error is 3%, and unlit or dark patches (no relative error worth
    /// measuring) are left out.
    #[test]
    fn the_lit_error_is_the_per_patch_relative_error_whatever_the_emitters_do() {
        let scene = sample("cornell_box.gltf");
        let (mut values, mut solved, mut stderr) = (Vec::new(), Vec::new(), Vec::new());
        for (i, p) in scene.patches.iter().enumerate() {
            let emits = scene.materials[p.material as usize].is_emitter();
            let (r, l): ([f64; 3], [f64; 3]) = if emits {
                ([10.0; 3], [50.0; 3])
            } else if i % 7 == 3 {
                // Unlit in the reference, wrongly lit in the bake.
                ([0.0; 3], [1.0; 3])
            } else if i % 7 == 5 {
                // Dark (a millionth of the mean): a leak of 1000 times as much is still black.
                ([1e-6; 3], [1e-3; 3])
            } else {
                let r = [1.0 + (i % 5) as f64, 0.5, 2.0];
                let delta = if i % 2 == 0 { 0.03 } else { -0.03 };
                (r, r.map(|x| x * (1.0 + delta)))
            };
            values.push(r);
            solved.push(l);
            stderr.push(Some(r.map(|x| 0.02 * x)));
        }
        let reference = Reference {
            name: "hand-made".into(),
            frames: vec![0],
            sigma: vec![vec![[0.0; 3]; values.len()]],
            values: vec![values],
            half_difference: None,
            spread: None,
            visible: None,
        };
        let m = compare(&scene, &[solution(solved, stderr)], &reference);
        assert!(close(m.lit_error, 0.03), "{m:?}");
        assert!(close(m.emitter_error, 4.0), "{m:?}");
        // Every lit error is 1.5σ.
        assert!(close(m.coverage, 1.0) && close(m.median_z, 1.5), "{m:?}");
        assert!(m.lit_values > 0 && m.emitter_values > 0 && m.dark_values > 0);
        // The former measure: the light alone puts it far above the walls' 3%.
        assert!(m.total_error > 10.0 * 0.03, "{m:?}");
    }

    /// A path-traced reference's own noise is taken out of the per-patch error (from its
    /// halves' difference), its patches' variation added at points, and its own standard
    /// error widens the error bars the coverage counts.
    #[test]
    fn a_path_traced_reference_s_noise_is_taken_out_and_its_variation_counted_at_points() {
        let scene = sample("cornell_box.gltf");
        let n = scene.patches.len();
        let r: Vec<[f64; 3]> = (0..n).map(|i| [1.0 + (i % 4) as f64, 0.5, 2.0]).collect();
        let scaled = |k: f64| -> Vec<[f64; 3]> { r.iter().map(|r| r.map(|x| k * x)).collect() };
        let reference = |sigma: f64, variation: f64, noise: f64| Reference {
            name: "hand-made".into(),
            frames: vec![0],
            values: vec![r.clone()],
            sigma: vec![scaled(sigma)],
            half_difference: Some(vec![scaled(noise)]),
            spread: Some(vec![
                (r.iter())
                    .map(|r| r.map(|x| ((variation * x).powi(2), 0.0)))
                    .collect(),
            ]),
            visible: None,
        };
        // 5% off everywhere against a reference whose own noise is 3%: 4% is the bake's.
        let solved = [solution(scaled(1.05), vec![Some([0.01; 3]); n])];
        let m = compare(&scene, &solved, &reference(0.0, 0.0, 0.03));
        assert!(close(m.lit_error, 0.04), "{m:?}");
        assert!(
            close(m.reference_noise, 0.03) && close(m.bias, 0.05),
            "{m:?}"
        );
        // Exact means, and a variation of 10% within every patch: the error at points is
        // 0.1 over the RMS of the true radiance at points, √(1 + 0.01); none on the means.
        let exact = [solution(r.clone(), vec![Some([0.01; 3]); n])];
        let m = compare(&scene, &exact, &reference(0.0, 0.1, 0.0));
        let point = 0.1 / 1.01f64.sqrt();
        assert!(close(m.point_error, point), "{m:?} against {point}");
        assert!(close(m.patch_l2_error, 0.0), "{m:?}");
        // 5% off with error bars of 2% of the radiance: outside two of them, inside once the
        // reference's own 3% are added in quadrature (2 × 3.6% > 5%).
        let bars = |k: f64| -> Vec<Option<[f64; 3]>> { scaled(k).into_iter().map(Some).collect() };
        let off = [solution(scaled(1.05), bars(0.02))];
        let covered = |sigma| compare(&scene, &off, &reference(sigma, 0.0, 0.0)).coverage;
        assert!(close(covered(0.0), 0.0) && close(covered(0.03), 1.0));
    }

    /// The parallel squares' closed form follows the patches however they are made: the area
    /// mean over the receiver's patches is ρ times the square-to-square form factor.
    #[test]
    fn the_parallel_squares_closed_form_holds_for_any_patches() {
        let sample = crate::samples::all()
            .into_iter()
            .find(|s| s.file_name == "parallel_squares.gltf")
            .unwrap();
        let options = crate::loader::LoadOptions {
            patch_size: Some(0.3),
            ..Default::default()
        };
        let scene = crate::loader::load(sample.gltf.as_bytes(), &options).unwrap();
        let reference = closed_form("parallel_squares.gltf", &scene).unwrap();
        let (mut sum, mut area) = (0.0, 0.0);
        for (p, l) in scene.patches.iter().zip(&reference.values[0]) {
            if !scene.materials[p.material as usize].is_emitter() {
                sum += p.area * l[0];
                area += p.area;
            }
        }
        assert!(scene.patches.len() > 8);
        assert!((sum / area - 0.5 * 0.19982).abs() < 1e-4, "{}", sum / area);
    }

    #[test]
    fn measured_frames_spread_from_frame_zero() {
        assert_eq!(measured_frames(25, 3), [0, 8, 16]);
        assert_eq!(measured_frames(2, 3), [0, 1]);
        assert_eq!(measured_frames(1, 3), [0]);
        assert_eq!(measured_frames(61, 1), [0]);
    }

    #[test]
    fn the_estimated_error_is_the_rms_of_sigma_over_radiance_on_lit_sampled_patches() {
        let scene = sample("cornell_box.gltf");
        let (mut radiance, mut stderr) = (Vec::new(), Vec::new());
        for (i, p) in scene.patches.iter().enumerate() {
            let emits = scene.materials[p.material as usize].is_emitter();
            let l = [1.0 + (i % 3) as f64, 2.0, 0.25];
            let (l, e) = match i % 5 {
                _ if emits => (l, Some(l)),
                // Unlit or dark: no relative error, whatever its σ.
                1 if i % 2 == 0 => ([0.0; 3], Some([0.1; 3])),
                1 => ([1e-7; 3], Some([1e-6; 3])),
                // Unsampled: no estimate.
                2 => (l, None),
                // RMS of 4% and 2% is √10 %.
                3 => (l, Some(l.map(|x| 0.04 * x))),
                _ => (l, Some(l.map(|x| 0.02 * x))),
            };
            radiance.push(l);
            stderr.push(e);
        }
        let solved = [solution(radiance, stderr)];
        let area = |k: usize| -> f64 {
            let lit = |i: &usize| {
                i % 5 == k && !scene.materials[scene.patches[*i].material as usize].is_emitter()
            };
            (0..scene.patches.len())
                .filter(lit)
                .map(|i| scene.patches[i].area)
                .sum()
        };
        let (a4, a2) = (area(3), area(0) + area(4));
        let expected = ((a4 * 0.04f64.powi(2) + a2 * 0.02f64.powi(2)) / (a4 + a2)).sqrt();
        assert!(close(estimated_error(&scene, &solved), expected));
        // Frames weigh alike: twice the same frame is the same error.
        let twice = [solved[0].clone(), solved[0].clone()];
        assert!(close(estimated_error(&scene, &twice), expected));
    }

    #[test]
    fn a_scene_where_everything_emits_has_no_lit_error() {
        let scene = sample("furnace.gltf");
        let n = scene.patches.len();
        let solved = [solution(vec![[1000.0; 3]; n], vec![Some([1.0; 3]); n])];
        assert_eq!(estimated_error(&scene, &solved), None);
        let reference = Reference {
            name: "closed form".into(),
            frames: vec![0],
            values: vec![vec![[1000.0; 3]; n]],
            sigma: vec![vec![[0.0; 3]; n]],
            half_difference: None,
            spread: None,
            visible: None,
        };
        let m = compare(&scene, &solved, &reference);
        assert_eq!((m.lit_error, m.coverage, m.median_z), (None, None, None));
        assert!(close(m.emitter_error, 0.0) && m.emitter_values == 3 * n);
    }
}

/// One bake of `bench-patches`: a way of making patches, against the path-traced reference.
#[derive(Clone, Debug, Serialize)]
pub struct PatchPoint {
    /// Scene file name.
    pub scene: String,
    /// How the patches were made.
    pub patch_size: crate::params::PatchSize,
    /// Whether they were solved on pieces ([`crate::bake::Bake::split`]) or whole.
    pub split: bool,
    /// Patches the bake solved.
    pub patches: usize,
    /// With auto: the patch budget.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub budget: Option<usize>,
    /// Seconds of the bake: tracing, cutting (`auto`) and the solve of frame 0.
    pub seconds: f64,
    /// The bake's per-patch error: area-weighted RMS of (bake − reference) / reference over
    /// lit, non-emitting patches and channels, the reference's own noise taken out in
    /// quadrature (the two are independent).
    pub patch_error: f64,
    /// The bake's error at the resolution of points rather than patches: over the same
    /// patch-channels, the area-weighted RMS of (bake − the true radiance at a uniformly random
    /// point of the patch) over the RMS of the true radiance (a relative L² error of the
    /// field), the reference's noise taken out. [`PatchPoint::patch_l2_error`] with each
    /// patch's own variation added ([`crate::direct::reference::Estimate::spread`]): what one
    /// value per patch cannot show, however exact. A patch-constant answer's error as a
    /// lightmap: it charges coarse patches for the detail they miss, which the per-patch
    /// errors do not, and its scale does not depend on the patches (a patch's relative error
    /// would be relative to a mean that does).
    pub point_error: f64,
    /// The smallest [`PatchPoint::point_error`] the reference resolves
    /// ([`Measured::point_resolution`]).
    pub point_resolution: f64,
    /// [`PatchPoint::point_error`] without the patches' own variation: the patches' means
    /// against the true means, as a relative L² error.
    pub patch_l2_error: f64,
    /// The reference's own per-patch noise on the same patches (half the difference of its two
    /// independent halves, RMS), for scale.
    pub reference_noise: f64,
    /// The area-weighted mean of the bake over the reference's, minus 1, on the same patches.
    pub bias: f64,
    /// The bake's own error bars on the same patches (those a line crossed): area-weighted RMS
    /// of σ / reference, σ the error bar the bake reports.
    pub estimated_noise: f64,
    /// Share of those patch-channels (by area) whose error is within twice the error bar (the
    /// bake's σ and the reference's own standard error in quadrature): about 0.95 when the
    /// error bars are honest ([`Measured::coverage`]).
    pub coverage: f64,
    /// [`Measured::reference_calibration`]: about 1 when the reference's own standard error,
    /// which the coverage takes, is honest.
    pub reference_calibration: f64,
    /// The patches that hold most of the squared error, most first (at most [`WORST`]).
    pub worst: Vec<WorstPatch>,
}

/// Patches listed in [`PatchPoint::worst`].
pub const WORST: usize = 8;

/// A patch of [`PatchPoint::worst`], in luminance.
#[derive(Clone, Debug, Serialize)]
pub struct WorstPatch {
    /// Patch id.
    pub patch: usize,
    /// Its material's name.
    pub material: String,
    /// Its area.
    pub area: f64,
    /// Its share of the bake's squared error (area-weighted).
    pub share: f64,
    /// The bake's luminance, its error bar (σ) and the reference's.
    pub baked: f64,
    pub sigma: f64,
    pub reference: f64,
}

/// Bakes frame 0 of `scene` with `lines` lines from `seed`, patches made as `patch_size` says (the scene
/// must have been loaded with its length, if any; `auto` cut as `auto` says, or the standard
/// choice), solved on pieces if `split` (as the bake command and the service solve,
/// [`crate::bake::Bake::split`]) or whole, and compares every patch with the path-traced reference of `reference_paths`
/// paths over all its patches (at least 64 per patch)
/// ([`crate::direct::reference`]). The lit patches are those [`PatchClass::of`] calls lit on
/// the reference's radiance (not black on screen), whatever the reference's noise.
///
/// # Errors
/// When the scene cannot be traced or cut.
pub fn patch_point(
    name: &str,
    scene: Scene,
    patch_size: crate::params::PatchSize,
    (lines, seed): (u64, u64),
    reference_paths: usize,
    auto: Option<crate::adaptive::Adaptive>,
    split: bool,
) -> Result<PatchPoint, String> {
    use crate::adaptive::{Adaptive, adapt};
    let started = Instant::now();
    let params = LineParams { lines, seed };
    let mut bake = crate::bake::Bake::trace(scene, &params).map_err(|e| e.to_string())?;
    let solve = crate::solve::SolveParams::default();
    let mut budget = None;
    if patch_size == crate::params::PatchSize::Auto {
        let auto = auto.unwrap_or_else(|| Adaptive::for_lines(lines, bake.scene.patches.len()));
        adapt(&mut bake, &auto, &solve, &Control::default()).map_err(|e| e.to_string())?;
        budget = Some(auto.budget);
    }
    if split {
        bake.split(&solve, &Control::default())
            .map_err(|e| e.to_string())?;
    }
    let scene = &bake.scene;
    let solved = bake.solve_frame(0, &scene.materials, &solve);
    let seconds = started.elapsed().as_secs_f64();
    let reference = path_traced(&bake, &[0], reference_paths, [0.0; 3], seed);
    let measured = compare(scene, std::slice::from_ref(&solved), &reference);
    let luminance = crate::output::tonemap::luminance;
    let worst = (measured.worst.iter())
        .map(|&(share, i)| {
            let p = &scene.patches[i];
            WorstPatch {
                patch: i,
                material: (scene.materials[p.material as usize].name.clone()).unwrap_or_default(),
                area: p.area,
                share,
                baked: luminance(solved.radiance[i]),
                sigma: solved.stderr[i].map_or(f64::INFINITY, luminance),
                reference: luminance(reference.values[0][i]),
            }
        })
        .collect();
    let unmeasured = || format!("{name}: no lit, non-emitting patch to measure");
    Ok(PatchPoint {
        scene: name.to_string(),
        patch_size,
        split,
        patches: scene.patches.len(),
        budget,
        seconds,
        patch_error: measured.lit_error.ok_or_else(unmeasured)?,
        point_error: measured.point_error.ok_or_else(unmeasured)?,
        point_resolution: measured.point_resolution.ok_or_else(unmeasured)?,
        patch_l2_error: measured.patch_l2_error.ok_or_else(unmeasured)?,
        reference_noise: measured.reference_noise.ok_or_else(unmeasured)?,
        bias: measured.bias.ok_or_else(unmeasured)?,
        estimated_noise: measured.estimated_noise.ok_or_else(unmeasured)?,
        coverage: measured.coverage.ok_or_else(unmeasured)?,
        reference_calibration: measured.reference_calibration.ok_or_else(unmeasured)?,
        worst,
    })
}

/// The scenes `bench-patches` measures, each with the ways of making patches it tries: the
/// source's triangles, three uniform sizes a factor 2 apart, and `auto`.
#[must_use]
pub fn patch_scenes() -> Vec<(&'static str, Vec<crate::params::PatchSize>)> {
    use crate::params::PatchSize::{Auto, Length, Source};
    vec![
        (
            "cornell_box.gltf",
            vec![Source, Length(0.2), Length(0.1), Length(0.05), Auto],
        ),
        (
            "panel_room.gltf",
            vec![Source, Length(1.0), Length(0.5), Length(0.25), Auto],
        ),
        (
            "level.gltf",
            vec![Source, Length(0.5), Length(0.25), Length(0.125), Auto],
        ),
        (
            "level_lamps.gltf",
            vec![Source, Length(0.5), Length(0.25), Length(0.125), Auto],
        ),
    ]
}

/// The scenes `bench-accuracy` measures.
pub const ACCURACY_SCENES: [&str; 7] = [
    "furnace.gltf",
    "parallel_squares.gltf",
    "cornell_moving.gltf",
    "level.gltf",
    "level_lamps.gltf",
    "lamp_room.gltf",
    "panel_room.gltf",
];

/// A sample scene of the directory `scenes` loaded with `options`; the error names the file.
///
/// # Errors
/// The file cannot be read or loaded.
pub fn load_sample(
    scenes: &std::path::Path,
    name: &str,
    options: &crate::loader::LoadOptions,
) -> Result<Scene, crate::loader::FileError> {
    crate::loader::load_file(&scenes.join(name), options)
}

/// What `bench-patches` measures and how.
#[derive(Clone, Debug)]
pub struct PatchBench {
    /// Lines of every bake, and their seed.
    pub lines: (u64, u64),
    /// Paths of each bake's reference.
    pub reference_paths: usize,
    /// Only this scene (file name).
    pub only: Option<String>,
    /// Only these ways of making patches; each scene's own list ([`patch_scenes`]) if empty.
    pub sizes: Vec<crate::params::PatchSize>,
    /// With `auto`: the patch budget (one per 200 lines by default).
    pub patch_budget: Option<usize>,
    /// Solve the patches whole rather than on their pieces.
    pub whole: bool,
}

/// Every [`PatchPoint`] of `bench` on the sample scenes of the directory `scenes`, each given
/// to `measured` as soon as it is: each scene's ways of making patches, then (with no
/// `sizes` chosen) the yardstick, `auto` with a budget of a third of the patches of
/// the best uniform way (the source's triangles or a length) by per-patch error.
///
/// # Errors
/// A scene cannot be read, loaded, traced or cut.
pub fn patch_points(
    scenes: &std::path::Path,
    bench: &PatchBench,
    mut measured: impl FnMut(&PatchPoint),
) -> Result<Vec<PatchPoint>, String> {
    use crate::params::PatchSize::Auto;
    let mut points = Vec::new();
    for (name, sizes) in patch_scenes() {
        if bench.only.as_ref().is_some_and(|o| o != name) {
            continue;
        }
        let sizes = if bench.sizes.is_empty() {
            sizes
        } else {
            bench.sizes.clone()
        };
        let first = points.len();
        let mut run = |size: crate::params::PatchSize, budget: Option<usize>| {
            let options = crate::loader::LoadOptions {
                patch_size: size.length(),
                ..crate::loader::LoadOptions::default()
            };
            let scene = load_sample(scenes, name, &options).map_err(|e| e.to_string())?;
            let auto = crate::adaptive::Adaptive::for_lines(bench.lines.0, scene.patches.len())
                .with_budget(budget);
            let point = patch_point(
                name,
                scene,
                size,
                bench.lines,
                bench.reference_paths,
                Some(auto),
                !bench.whole,
            )?;
            measured(&point);
            Ok::<_, String>(point)
        };
        for size in sizes {
            points.push(run(size, bench.patch_budget)?);
        }
        if bench.sizes.is_empty() {
            let best = (points[first..].iter())
                .filter(|p| p.patch_size != Auto)
                .min_by(|a, b| a.patch_error.total_cmp(&b.patch_error))
                .map(|p| p.patches);
            if let Some(best) = best {
                points.push(run(Auto, Some(best / 3))?);
            }
        }
    }
    Ok(points)
}
