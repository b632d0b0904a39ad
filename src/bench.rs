//! Benchmarks run by the `bench` command: what the engine costs on a given scene, measured in
//! one run so that ratios are meaningful on a shared machine.

use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::scene::Scene;
use crate::timeline::{Control, IntersectionList, LineParams, TraceError};
use crate::trace::{Hit, Line, SceneTracer};

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
}

/// Measures tracing on `scene` with about `lines` lines.
pub fn trace(scene: &Scene, lines: u64, seed: u64) -> Result<TraceReport, TraceError> {
    let start = Instant::now();
    let tracer = SceneTracer::new(scene);
    let bvh_seconds = start.elapsed().as_secs_f64();

    let start = Instant::now();
    let list = IntersectionList::build(
        scene,
        &tracer,
        &LineParams {
            lines,
            bundles: None,
            seed,
        },
        &Control::default(),
    )?;
    let list_seconds = start.elapsed().as_secs_f64();
    let memory = list.memory();
    let all_lines: Vec<Line> = list.regenerate_lines(scene).collect();
    // Every moving crossing belongs to one frame; every static one to all of them.
    let frame_hits = memory.static_hits * scene.frames.count + memory.moving_hits;

    // The alternative to the multiframe list: one list per frame (CSR: an offset per line and
    // the sorted crossings), each traced from scratch.
    let start = Instant::now();
    let mut independent_hits = 0;
    for frame in 0..scene.frames.count {
        let deformed = tracer.deformed_at(scene, frame);
        let chunks: Vec<(Vec<u32>, Vec<Hit>)> = all_lines
            .par_chunks(1024)
            .map(|chunk| {
                let (mut offsets, mut hits, mut scratch) = (Vec::new(), Vec::new(), Vec::new());
                for line in chunk {
                    tracer.trace_frame(line, frame, &deformed, &mut scratch);
                    hits.extend_from_slice(&scratch);
                    offsets.push(hits.len() as u32);
                }
                (offsets, hits)
            })
            .collect();
        let mut offsets = Vec::with_capacity(all_lines.len() + 1);
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
        list_seconds,
        list_hits: memory.static_hits + memory.moving_hits,
        list_hits_per_second: (memory.static_hits + memory.moving_hits) as f64 / list_seconds,
        frame_hits_per_second: frame_hits as f64 / list_seconds,
        list_bytes: memory.bytes,
        bytes_per_hit: memory.bytes_per_hit(),
        independent_seconds,
        independent_hits,
        independent_bytes,
        independent_hits_per_second: independent_hits as f64 / independent_seconds,
        time_ratio: independent_seconds / list_seconds,
        memory_ratio: independent_bytes as f64 / memory.bytes as f64,
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
        writeln!(f, "BVH build        {:.3} s", self.bvh_seconds)?;
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
        )
    }
}

/// One point of the speed/accuracy trade: a scene baked with a line budget.
#[derive(Clone, Debug, Serialize)]
pub struct AccuracyPoint {
    /// Scene file.
    pub scene: String,
    /// What the error is measured against.
    pub reference: String,
    /// Frames baked.
    pub frames: usize,
    /// Lines traced.
    pub lines: usize,
    /// Wall time: tracing, tallying and solving every frame.
    pub seconds: f64,
    /// Relative RMS error of the radiance (area-weighted, over patches, channels and frames).
    pub rms_error: f64,
    /// Fraction of (patch, channel, frame) values within 2σ of the reference (σ combining the
    /// reported errors of the bake and of a reference run).
    pub coverage: f64,
    /// Median of |error| / σ: about 0.67 for honest Gaussian error bars, less when they are
    /// conservative.
    pub median_z: f64,
}

/// A scene's reference radiance per frame, with its own standard error (0 for closed forms).
struct Reference {
    name: String,
    values: Vec<Vec<[f64; 3]>>,
    sigma: Vec<Vec<[f64; 3]>>,
}

/// A bake timed from tracing to the last frame solved.
struct Timed {
    solved: Vec<crate::solve::FrameSolution>,
    lines: usize,
    seconds: f64,
}

/// Bakes `scene` with `lines` lines and solves every frame.
fn timed_bake(scene: &Scene, lines: u64, seed: u64) -> Result<Timed, TraceError> {
    let start = Instant::now();
    let bake = crate::bake::Bake::trace(
        scene.clone(),
        &LineParams {
            lines,
            bundles: None,
            seed,
        },
    )?;
    let solved = bake.solve_all(&scene.materials, &crate::solve::SolveParams::default());
    let seconds = start.elapsed().as_secs_f64();
    Ok(Timed {
        solved: solved.iter().map(|s| (**s).clone()).collect(),
        lines: bake.list().lines(),
        seconds,
    })
}

/// Closed-form references where the sample scenes have one: the furnace (L = Le / (1 − ρ)) and
/// the parallel squares' receiver (ρ · F, the emitter being black).
fn closed_form(name: &str, scene: &Scene) -> Option<Reference> {
    let frames = scene.frames.count;
    let per_patch: Vec<[f64; 3]> = match name {
        "furnace.gltf" => scene
            .patches
            .iter()
            .map(|p| {
                let m = &scene.materials[p.material as usize];
                [0, 1, 2].map(|c| m.emission[c] / (1.0 - m.reflectance[c]))
            })
            .collect(),
        "parallel_squares.gltf" => scene
            .patches
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let m = &scene.materials[p.material as usize];
                if m.is_emitter() {
                    return m.emission;
                }
                let n = scene.normalisation;
                let t = scene.statics.triangles[i];
                let corners = t.map(|v| n.to_scene(scene.statics.positions[v as usize].as_dvec3()));
                let f = crate::solve::analytic::triangle_to_parallel_rectangle(
                    corners,
                    (-0.5, 0.5),
                    (-0.5, 0.5),
                    0.0,
                );
                m.reflectance.map(|r| r * f)
            })
            .collect(),
        _ => return None,
    };
    Some(Reference {
        name: "closed form".into(),
        sigma: vec![vec![[0.0; 3]; per_patch.len()]; frames],
        values: vec![per_patch; frames],
    })
}

/// Error, error-bar coverage and median |z| of `solved` against `reference`, over patches
/// that reflect.
fn compare(
    scene: &Scene,
    solved: &[crate::solve::FrameSolution],
    reference: &Reference,
) -> (f64, f64, f64) {
    let (mut num, mut den, mut within, mut total) = (0.0, 0.0, 0usize, 0usize);
    let mut z = Vec::new();
    for (f, s) in solved.iter().enumerate() {
        for (i, p) in scene.patches.iter().enumerate() {
            let m = &scene.materials[p.material as usize];
            for c in 0..3 {
                if m.reflectance[c] == 0.0 {
                    continue;
                }
                let (l, r) = (s.radiance[i][c], reference.values[f][i][c]);
                num += p.area * (l - r).powi(2);
                den += p.area * r * r;
                let sigma = s.stderr[i]
                    .map_or(f64::INFINITY, |e| e[c])
                    .hypot(reference.sigma[f][i][c]);
                within += usize::from((l - r).abs() <= 2.0 * sigma + 1e-9 * r.abs());
                total += 1;
                if sigma > 0.0 {
                    z.push((l - r).abs() / sigma);
                }
            }
        }
    }
    z.sort_by(f64::total_cmp);
    let median = z.get(z.len() / 2).copied().unwrap_or(0.0);
    (
        (num / den.max(f64::MIN_POSITIVE)).sqrt(),
        within as f64 / total.max(1) as f64,
        median,
    )
}

/// Sweeps the line budget on each scene and measures error against time. Scenes without a
/// closed form are measured against a bake with `reference_factor` times the largest budget
/// (another seed).
pub fn accuracy(
    scenes: &[(String, Scene)],
    budgets: &[u64],
    reference_factor: u64,
    mut progress: impl FnMut(&AccuracyPoint),
) -> Result<Vec<AccuracyPoint>, TraceError> {
    let mut points = Vec::new();
    for (name, scene) in scenes {
        let reference = match closed_form(name, scene) {
            Some(r) => r,
            None => {
                let lines = reference_factor * budgets.iter().copied().max().unwrap_or(1);
                let solved = timed_bake(scene, lines, 0x5EED)?.solved;
                Reference {
                    name: format!("{lines} lines"),
                    values: solved.iter().map(|s| s.radiance.clone()).collect(),
                    sigma: solved
                        .iter()
                        .map(|s| s.stderr.iter().map(|e| e.unwrap_or([0.0; 3])).collect())
                        .collect(),
                }
            }
        };
        for &lines in budgets {
            let run = timed_bake(scene, lines, 1)?;
            let (rms_error, coverage, median_z) = compare(scene, &run.solved, &reference);
            let point = AccuracyPoint {
                scene: name.clone(),
                reference: reference.name.clone(),
                frames: scene.frames.count,
                lines: run.lines,
                seconds: run.seconds,
                rms_error,
                coverage,
                median_z,
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
    let whole = timed_bake(scene, lines, 1)?;
    let start = Instant::now();
    for f in 0..scene.frames.count {
        let Some(single) = load_frame(scene.frames.time(f)) else {
            return Ok(None);
        };
        timed_bake(&single, lines, 1)?;
    }
    let independent_seconds = start.elapsed().as_secs_f64();
    Ok(Some(MultiframeGain {
        frames: scene.frames.count,
        lines: whole.lines,
        multiframe_seconds: whole.seconds,
        independent_seconds,
        ratio: independent_seconds / whole.seconds,
    }))
}
