//! Batch baking: what a build pipeline runs overnight (`radiosity bake`).
//!
//! Each scene bakes into `OUT/<scene name>/`:
//! - `radiance.bin`: every frame's radiance per patch (layout in [`write_radiance`]);
//! - `summary.json`: frames, patches, parameters, error figures, warnings and the content hash
//!   that makes re-runs incremental; byte-identical for the same scene, parameters and seed,
//!   whatever the thread count;
//! - `timings.json`: wall times (the one output that changes from run to run).
//!
//! Files are written under temporary names and renamed once complete: an interrupted bake
//! leaves no half-written output. A scene whose content and parameters are unchanged since its
//! last bake is skipped unless forced; a scene that fails does not stop the others.

use std::hash::Hasher;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

use crate::bake::Bake;
use crate::loader::{self, LoadOptions};
use crate::solve::{FrameSolution, SolveParams};
use crate::timeline::{Control, LineParams, TraceError};

/// What to bake with; the same names as the service's parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct BatchParams {
    /// What to load from each scene.
    pub load: LoadOptions,
    /// Lines and seed.
    pub lines: LineParams,
    /// Radiance of the sky.
    pub sky: [f64; 3],
    /// Bake even if the outputs are up to date.
    pub force: bool,
}

/// How one scene went.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    /// Baked into this directory.
    Baked(PathBuf),
    /// Up to date: nothing done.
    Skipped(PathBuf),
    /// Failed, with the reason.
    Failed(String),
    /// Stopped by Ctrl-C; nothing was written.
    Cancelled,
}

/// The deterministic summary of a bake.
#[derive(Serialize)]
struct Summary<'a> {
    scene: &'a str,
    /// Hash of the scene's bytes and the parameters: an equal hash means nothing to redo.
    content_hash: String,
    frames: usize,
    frame_times: Vec<f64>,
    patches: usize,
    lines: usize,
    seed: u64,
    fps: f64,
    patch_size: Option<f64>,
    animation: Option<&'a str>,
    sky: [f64; 3],
    /// Worst relative residual of the solver over frames and channels.
    worst_residual: f64,
    /// Whether every frame converged.
    converged: bool,
    /// Patches no line crossed (their radiance is their emission only).
    unsampled_patches: usize,
    /// Mean relative standard error of the radiance (area-weighted, over sampled patches,
    /// channels and frames).
    mean_relative_error: f64,
    warnings: &'a [String],
}

/// The scenes named by `inputs`: files as given, directories searched (not recursively) for
/// `.glb` and `.gltf`, sorted.
pub fn scenes(inputs: &[PathBuf]) -> std::io::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(input)?
                .filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|e| e == "glb" || e == "gltf"))
                .collect();
            found.sort();
            out.extend(found);
        } else {
            out.push(input.clone());
        }
    }
    Ok(out)
}

/// The content hash of a scene and its parameters (FNV-1a, 64 bits).
fn content_hash(bytes: &[u8], params: &BatchParams) -> String {
    struct Fnv(u64);
    impl Hasher for Fnv {
        fn finish(&self) -> u64 {
            self.0
        }
        fn write(&mut self, bytes: &[u8]) {
            for &b in bytes {
                self.0 = (self.0 ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
            }
        }
    }
    let mut h = Fnv(0xcbf2_9ce4_8422_2325);
    h.write(bytes);
    let described = format!(
        "{:?}|{:?}|{:?}|{}",
        params.load,
        params.lines,
        params.sky,
        env!("CARGO_PKG_VERSION")
    );
    h.write(described.as_bytes());
    format!("{:016x}", h.finish())
}

/// Writes `bytes` to `path` through a temporary file renamed once complete.
fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension("partial");
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}

/// `radiance.bin`, little-endian: the magic `RADB`, u32 version 1, u32 frames F, u32 patches P,
/// then per frame: f64 time, P×3 f32 radiance, P×3 f32 standard error (−1 where unsampled),
/// P u32 samples.
fn write_radiance(
    path: &Path,
    times: &[f64],
    frames: &[std::sync::Arc<FrameSolution>],
) -> std::io::Result<()> {
    let patches = frames.first().map_or(0, |f| f.radiance.len());
    let mut out = Vec::with_capacity(16 + frames.len() * (8 + patches * 28));
    out.extend_from_slice(b"RADB");
    for v in [1u32, frames.len() as u32, patches as u32] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for (s, t) in frames.iter().zip(times) {
        out.extend_from_slice(&t.to_le_bytes());
        s.write_f32(&mut out);
    }
    write_atomic(path, &out)
}

/// Bakes one scene into `out/<stem>/`; `log` receives progress lines.
pub fn bake_one(
    path: &Path,
    out: &Path,
    params: &BatchParams,
    control: &Control,
    log: &mut dyn FnMut(&str),
) -> Outcome {
    let name = path
        .file_stem()
        .map_or_else(|| "scene".to_string(), |s| s.to_string_lossy().into_owned());
    let dir = out.join(&name);
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) => return Outcome::Failed(format!("{}: {e}", path.display())),
    };
    let hash = content_hash(&bytes, params);
    let summary_path = dir.join("summary.json");
    if !params.force
        && dir.join("radiance.bin").exists()
        && std::fs::read(&summary_path)
            .ok()
            .and_then(|s| serde_json::from_slice::<serde_json::Value>(&s).ok())
            .is_some_and(|s| s["content_hash"] == hash.as_str())
    {
        return Outcome::Skipped(dir);
    }
    let started = Instant::now();
    log(&format!("{name}: loading"));
    let scene = match loader::load(&bytes, &params.load) {
        Ok(s) => s,
        Err(e) => return Outcome::Failed(e.to_string()),
    };
    let load_seconds = started.elapsed().as_secs_f64();
    log(&format!(
        "{name}: tracing {} lines through {} frames, {} patches",
        params.lines.lines,
        scene.frames.count,
        scene.patches.len()
    ));
    let started = Instant::now();
    let bake = match Bake::trace_with(scene, &params.lines, control) {
        Ok(b) => b,
        Err(TraceError::Cancelled) => return Outcome::Cancelled,
        Err(e) => return Outcome::Failed(e.to_string()),
    };
    let trace_seconds = started.elapsed().as_secs_f64();
    log(&format!(
        "{name}: solving {} frames",
        bake.scene.frames.count
    ));
    let started = Instant::now();
    let solve = SolveParams {
        sky: params.sky,
        ..SolveParams::default()
    };
    let frames = bake.solve_all(&bake.scene.materials, &solve);
    if control.is_cancelled() {
        return Outcome::Cancelled;
    }
    let solve_seconds = started.elapsed().as_secs_f64();
    let scene = &bake.scene;
    let times: Vec<f64> = (0..scene.frames.count)
        .map(|f| scene.frames.time(f))
        .collect();
    let (mut num, mut den) = (0.0, 0.0);
    for s in &frames {
        for (i, p) in scene.patches.iter().enumerate() {
            if let Some(e) = s.stderr[i] {
                for (error, radiance) in e.iter().zip(&s.radiance[i]) {
                    if *radiance > 0.0 {
                        num += p.area * error / radiance;
                        den += p.area;
                    }
                }
            }
        }
    }
    let summary = Summary {
        scene: &name,
        content_hash: hash,
        frames: frames.len(),
        frame_times: times.clone(),
        patches: scene.patches.len(),
        lines: bake.list().lines(),
        seed: params.lines.seed,
        fps: params.load.fps,
        patch_size: params.load.patch_size,
        animation: params.load.animation.as_deref(),
        sky: params.sky,
        worst_residual: frames.iter().map(|f| f.residual).fold(0.0, f64::max),
        converged: frames.iter().all(|f| f.converged),
        unsampled_patches: frames
            .first()
            .map_or(0, |f| f.samples.iter().filter(|&&n| n == 0).count()),
        mean_relative_error: if den > 0.0 { num / den } else { 0.0 },
        warnings: &scene.warnings,
    };
    let timings =
        serde_json::json!({"load": load_seconds, "trace": trace_seconds, "solve": solve_seconds});
    let written = std::fs::create_dir_all(&dir)
        .and_then(|()| write_radiance(&dir.join("radiance.bin"), &times, &frames))
        .and_then(|()| write_atomic(&dir.join("timings.json"), timings.to_string().as_bytes()))
        .and_then(|()| {
            let json = serde_json::to_vec_pretty(&summary).map_err(std::io::Error::other)?;
            // Last: its hash marks the outputs complete.
            write_atomic(&summary_path, &json)
        });
    match written {
        Ok(()) => Outcome::Baked(dir),
        Err(e) => Outcome::Failed(format!("writing {}: {e}", dir.display())),
    }
}
