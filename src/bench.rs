//! Benchmarks run by the `bench` command: what the engine costs on a given scene, measured in
//! one run so that ratios are meaningful on a shared machine.

use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::scene::Scene;
use crate::timeline::{IntersectionList, LineParams, TooManyHits};
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
pub fn trace(scene: &Scene, lines: u64, seed: u64) -> Result<TraceReport, TooManyHits> {
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
        triangles: tracer.surfaces(),
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
