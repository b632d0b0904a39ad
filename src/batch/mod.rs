//! Batch baking: what a build pipeline runs overnight (`radiosity bake`).
//!
//! Each scene bakes into `OUT/<scene name>/`:
//! - `radiance.bin`: every frame's radiance per patch (layout in docs/outputs.md and beside
//!   `write_radiance`);
//! - `patches.json`: the patch table ([`crate::output::patch_table`]), each patch's source and
//!   material;
//! - `summary.json`: frames, patches, parameters, error figures, warnings and the content hash
//!   that makes re-runs incremental;
//! - `baked/frame_NNNN.glb`: the baked glTF of the chosen frames (see [`crate::output::glb`]);
//! - `preview/frame_NNNN.png`: previews of the chosen frames, and `preview.gif`, the whole
//!   timeline (see [`crate::output::preview`]);
//! - `timings.json`: wall times (the one output that changes from run to run).
//!
//! Everything but `timings.json` is byte-identical for the same scene, parameters and seed,
//! whatever the thread count.
//!
//! A scene's outputs are written into a hidden staging directory that replaces the old one
//! only when complete: an interrupted bake leaves the previous outputs (or none), never a mix.
//! A scene whose content and parameters are unchanged since its last bake is skipped unless
//! forced; a scene that fails does not stop the others. A frame whose solve does not converge
//! fails its scene before anything is written.

pub mod shard;

use std::collections::HashMap;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::{Arc, PoisonError};
use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::adaptive;
use crate::bake::Bake;
use crate::control::{Control, Stop};
use crate::direct::area::Poses;
use crate::direct::points::Lighting;
use crate::loader;
use crate::output::{self, FrameSpec, ToneMap};
use crate::params::{BakeSettings, PatchSize};
use crate::progress::Progress;
use crate::solve::{FrameSolution, SolveParams};

/// What to bake with; the same names as the service's parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct BatchParams {
    /// What each scene is baked with: what to load, how patches are made, lines and seed, the
    /// sky ([`crate::params::BakeRequest::validate`]).
    pub settings: BakeSettings,
    /// The baked glTF and previews to write.
    pub outputs: Outputs,
    /// Bake even if the outputs are up to date.
    pub force: bool,
    /// Iteration cap of each frame's solve ([`SolveParams::max_iterations`]): a frame that
    /// reaches it fails the scene.
    pub max_iterations: usize,
}

/// Which baked glTF files and previews to write besides `radiance.bin` and `summary.json`.
#[derive(Clone, Debug, PartialEq)]
pub struct Outputs {
    /// Frames written as baked `.glb` files.
    pub glb_frames: FrameSpec,
    /// Frames rendered as PNG previews.
    pub preview_frames: FrameSpec,
    /// Width and height of the PNG previews in pixels (the GIF is half that).
    pub preview_size: (u32, u32),
    /// Whether to write `preview.gif` (for timelines of more than one frame).
    pub gif: bool,
    /// The tone map's exposure for the previews and the baked glTF's `COLOR_0`; `None` takes
    /// it from the lit surfaces ([`ToneMap::for_timeline`]).
    pub exposure: Option<f64>,
    /// How the previews shade the patches.
    pub shading: output::Shading,
    /// Lightmaps at this many texels per scene unit, if any (`lightmaps/`,
    /// [`output::lightmap`]).
    pub lightmaps: Option<f64>,
    /// What the lightmaps' texels hold.
    pub lightmap_quantity: output::lightmap::Quantity,
    /// Light probes, if any (`probes/`, [`output::probes`]), at this spacing in scene units
    /// (`None`: the default for the scene).
    pub probes: Option<Option<f64>>,
}

impl Default for Outputs {
    /// Every frame's `.glb`, PNGs of the first, middle and last frames at 640×480, the GIF.
    fn default() -> Self {
        Self {
            glb_frames: FrameSpec::All,
            preview_frames: FrameSpec::List(vec![
                output::FrameItem::First,
                output::FrameItem::Middle,
                output::FrameItem::Last,
            ]),
            preview_size: (640, 480),
            gif: true,
            exposure: None,
            shading: output::Shading::Smooth,
            lightmaps: None,
            lightmap_quantity: output::lightmap::Quantity::Radiance,
            probes: None,
        }
    }
}

/// Memory the previews of one scene may hold at once, bytes.
const RENDER_MEMORY: usize = 1 << 30;

/// Most frames in `preview.gif`; longer timelines are shown every k-th frame.
pub const GIF_MAX_FRAMES: usize = 240;

/// Shortest GIF frame delay, ms: browsers show faster frames at 100 ms.
const GIF_MIN_DELAY_MS: f64 = 20.0;

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
/// The gaps' denser lines in `summary.json`: how many regions, how many times denser, and the
/// lines drawn there (counted in `lines`).
#[derive(Serialize)]
struct GapLines {
    regions: usize,
    factor: u32,
    lines: usize,
}

#[derive(Serialize)]
struct Summary<'a> {
    scene: &'a str,
    /// Hash of the scene's bytes and the parameters: an equal hash means nothing to redo.
    content_hash: String,
    frames: usize,
    frame_times: Vec<f64>,
    patches: usize,
    /// The pieces the frames were solved on (`Bake::split`; the patches if none was cut).
    pieces: usize,
    lines: usize,
    /// The gaps' denser lines ([`crate::timeline::IntersectionList::add_dense`]).
    gap_lines: GapLines,
    seed: u64,
    fps: f64,
    /// `auto`, `source` or the length asked for.
    patch_size: PatchSize,
    /// What each round of `auto` did (empty otherwise).
    adaptive: Vec<crate::adaptive::Round>,
    animation: Option<&'a str>,
    sky: [f64; 3],
    /// Worst relative residual of the solver over frames and channels.
    worst_residual: f64,
    /// Conjugate-gradient iterations of each frame's solve, most over the channels (frames
    /// that share a solution show the same count).
    iterations: Vec<usize>,
    /// Whether every frame converged.
    converged: bool,
    /// Patches no line crossed (their radiance is their emission only).
    unsampled_patches: usize,
    /// The bake's own estimate of its per-patch error: the area-weighted RMS of σ / L over lit,
    /// non-emitting patches (channels that reflect, L > 0, sampled by the lines) and frames
    /// (`bench::estimated_error`), what the README's preset table measures against a
    /// reference. `null` when no patch qualifies (a scene where everything emits).
    mean_relative_error: Option<f64>,
    /// The emitting materials (index and name) whose direct light is sampled as area lights
    /// rather than carried by the lines (`direct::area`): small ones; empty if none.
    area_lights: Vec<(u32, Option<&'a str>)>,
    /// The tone map's exposure: `COLOR_0` and previews show `exposure · radiance` through
    /// Reinhard's curve.
    exposure: f64,
    /// Frames written as `baked/frame_NNNN.glb`.
    glb_frames: Vec<usize>,
    /// Frames written as `preview/frame_NNNN.png`.
    preview_frames: Vec<usize>,
    /// Frames shown in `preview.gif` (empty when there is none).
    gif_frames: Vec<usize>,
    warnings: &'a [String],
    /// The visibility information the lines measure at frame 0 (`I_c`, `I_d`, their gap),
    /// with the patches that lose the most of it (`solve::information`).
    information: crate::solve::information::Report,
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

/// The content hash of a scene and its parameters: SHA-256 over a version tag, the scene's
/// bytes (length-prefixed) and a canonical JSON of every parameter that changes the outputs
/// (keys sorted, numbers as `serde_json` writes them: the shortest text that reads
/// back to the same `f64`) with the crate's version, in hexadecimal. Stable across builds,
/// platforms and Rust versions, unlike a hash of `{:?}` output (issue 14).
fn content_hash(bytes: &[u8], params: &BatchParams) -> String {
    use sha2::{Digest, Sha256};
    let settings = &params.settings;
    let load = &settings.load;
    let outputs = &params.outputs;
    let mut described = serde_json::json!({
        "version": env!("CARGO_PKG_VERSION"),
        "load": {
            "fps": load.fps,
            "animation": load.animation,
            "camera": load.camera,
            "start": load.start,
            "end": load.end,
            "patch_size": load.patch_size,
            "max_frames": load.max_frames,
            "max_patches": load.max_patches,
            "max_work": load.max_work,
            "max_reflectance": load.max_reflectance,
        },
        "auto": settings.patch_size == PatchSize::Auto,
        "patch_budget": settings.patch_budget,
        "lines": settings.lines.lines,
        "seed": settings.lines.seed,
        "sky": settings.sky,
        "max_iterations": params.max_iterations,
        "outputs": {
            "glb_frames": outputs.glb_frames.to_string(),
            "preview_frames": outputs.preview_frames.to_string(),
            "preview_size": [outputs.preview_size.0, outputs.preview_size.1],
            "gif": outputs.gif,
            "exposure": outputs.exposure,
            "shading": outputs.shading,
        },
    });
    // Only when asked for: the bakes made before lightmaps keep their hash. With the files
    // the lightmaps are written as: a lightmap bake made before the RGBM PNGs (or the KTX2
    // textures) is made again.
    if let Some(density) = outputs.lightmaps {
        described["outputs"]["lightmaps"] = serde_json::json!({
            "texels_per_unit": density,
            "files": ["exr", "rgbm png", "ktx2"],
        });
        // The light in place of the radiance: a bake asked for the radiance keeps its hash.
        if outputs.lightmap_quantity != output::lightmap::Quantity::Radiance {
            described["outputs"]["lightmaps"]["quantity"] =
                serde_json::json!(outputs.lightmap_quantity);
        }
    }
    if let Some(spacing) = outputs.probes {
        described["outputs"]["probes"] = serde_json::json!({ "spacing": spacing });
    }
    let mut h = Sha256::new();
    h.update(b"radiosity content hash 2\0");
    h.update((bytes.len() as u64).to_le_bytes());
    h.update(bytes);
    h.update(described.to_string().as_bytes());
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
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
    std::fs::write(path, &out)
}

/// The file name of frame `f` among `count`: zero-padded to at least 4 digits, so names sort.
fn frame_name(f: usize, count: usize, extension: &str) -> String {
    let digits = count.saturating_sub(1).to_string().len().max(4);
    format!("frame_{f:0digits$}.{extension}")
}

/// The frames of the GIF and each one's delay in ms: every frame, or every k-th one so that
/// there are at most [`GIF_MAX_FRAMES`] and none is shorter than browsers allow.
fn gif_frames(count: usize, fps: f64) -> (Vec<usize>, u32) {
    let frame_ms = 1000.0 / fps;
    let fast = (GIF_MIN_DELAY_MS / frame_ms).ceil().min(count as f64) as usize;
    let step = count.div_ceil(GIF_MAX_FRAMES).max(fast).max(1);
    let delay = (step as f64 * frame_ms)
        .round()
        .clamp(GIF_MIN_DELAY_MS, f64::from(u16::MAX) * 10.0) as u32;
    ((0..count).step_by(step).collect(), delay)
}

/// Writes the baked glTF files and the previews into `dir`, counting one unit of `control`'s
/// stage per frame written. The light at the vertices is evaluated once per frame any of them
/// needs (once for frames that share their solution, [`Bake::representatives`]), with the
/// scene's materials and lights under `sky`. Returns the GIF's frames.
fn write_outputs(
    dir: &Path,
    (bake, sky): (&Bake, [f64; 3]),
    frames: &[std::sync::Arc<FrameSolution>],
    outputs: &Outputs,
    tone: &ToneMap,
    control: &Control,
) -> Result<Vec<usize>, String> {
    let scene = bake.shown();
    let count = frames.len();
    let glbs = outputs.glb_frames.frames(count);
    let pngs = outputs.preview_frames.frames(count);
    let (gif, delay) = if outputs.gif && count > 1 {
        gif_frames(count, scene.frames.fps)
    } else {
        (Vec::new(), 0)
    };
    let representatives = bake.representatives();
    let mut wanted: Vec<usize> = glbs.iter().chain(&pngs).chain(&gif).copied().collect();
    // Lightmaps: one per lighting state (each distinct frame), the geometry once.
    let lightmap = match outputs.lightmaps {
        Some(density) => {
            let lightmap = output::lightmap::Lightmap::new(bake, density)?;
            std::fs::create_dir_all(dir.join("lightmaps"))
                .map_err(|e| format!("writing {}: {e}", dir.display()))?;
            wanted.extend((0..count).filter(|&f| representatives[f] == f));
            Some(lightmap)
        }
        None => None,
    };
    let probes = match outputs.probes {
        Some(spacing) => {
            let grid = output::probes::ProbeGrid::new(bake, spacing)?;
            std::fs::create_dir_all(dir.join("probes"))
                .map_err(|e| format!("writing {}: {e}", dir.display()))?;
            wanted.extend((0..count).filter(|&f| representatives[f] == f));
            Some(grid)
        }
        None => None,
    };
    wanted.sort_unstable();
    wanted.dedup();
    control.start_stage(wanted.len() as u64);
    let io = |e: std::io::Error| format!("writing {}: {e}", dir.display());
    if !glbs.is_empty() {
        std::fs::create_dir_all(dir.join("baked")).map_err(io)?;
    }
    if !pngs.is_empty() {
        std::fs::create_dir_all(dir.join("preview")).map_err(io)?;
    }
    let power = bake.light_power();
    let lighting = Lighting {
        materials: &bake.scene.materials,
        power: &power,
        sky,
    };
    // The frames after which each distinct frame's light is needed no more.
    let mut last_use: HashMap<usize, usize> = HashMap::new();
    for &f in &wanted {
        last_use.insert(representatives[f], f);
    }
    let mut lit: HashMap<usize, Arc<Vec<output::NodeMesh>>> = HashMap::new();
    let embedded: std::sync::Mutex<Option<output::Embedded>> = Default::default();
    let (width, height) = outputs.preview_size;
    let small = ((width / 2).max(1), (height / 2).max(1));
    // Frames at once: each render holds its sample buffers, so large previews take turns.
    let bytes = output::preview::render_bytes(width, height).max(1);
    let at_once = (RENDER_MEMORY / bytes).clamp(1, 4 * rayon::current_num_threads());
    let mut gif_images = Vec::with_capacity(gif.len());
    // The first frame alone (its points on every core), so that what the light at the points
    // keeps across frames ([`Bake::radiance_at`]) is found once, not by every frame of the
    // first batch at the same time.
    let (first, rest) = wanted.split_at(wanted.len().min(1));
    for batch in std::iter::once(first).chain(rest.chunks(at_once)) {
        let needed = unlit(batch, &representatives, |r| lit.contains_key(&r));
        let computed: Vec<Result<LitFrame, String>> = (needed.par_iter())
            .filter(|_| !control.is_cancelled())
            .map(|&r| {
                let meshes = output::lit_geometry(bake, r, &frames[r], lighting);
                if let Some(lightmap) = &lightmap {
                    let texels = lightmap.texels(bake, r, Some(&meshes), (&frames[r], lighting));
                    if r == 0 {
                        // The first state's light, embedded in the geometry for MOZ_lightmap.
                        let light = output::Embedded::light(&texels, 0)?;
                        *embedded.lock().unwrap_or_else(PoisonError::into_inner) = Some(light);
                    }
                    let texels = texels.holding(outputs.lightmap_quantity);
                    let bytes = texels.exr(1.0)?;
                    let name = frame_name(r, count, "exr");
                    std::fs::write(dir.join("lightmaps").join(name), bytes).map_err(io)?;
                    let bytes = texels.rgbm_png(1.0)?;
                    let name = frame_name(r, count, "png");
                    std::fs::write(dir.join("lightmaps").join(name), bytes).map_err(io)?;
                    let bytes = texels.ktx2(1.0)?;
                    let name = frame_name(r, count, "ktx2");
                    std::fs::write(dir.join("lightmaps").join(name), bytes).map_err(io)?;
                }
                if let Some(grid) = &probes {
                    let values = grid.probes(bake, r, (&frames[r], lighting));
                    let document = output::probes::ProbeGrid::state_document(&values);
                    let bytes = serde_json::to_vec(&document).map_err(|e| e.to_string())?;
                    let name = frame_name(r, count, "json");
                    std::fs::write(dir.join("probes").join(name), bytes).map_err(io)?;
                }
                Ok((r, Arc::new(meshes)))
            })
            .collect();
        if control.is_cancelled() {
            return Err("cancelled".to_string());
        }
        for one in computed {
            let (r, meshes) = one?;
            lit.insert(r, meshes);
        }
        let made: Vec<Result<Option<image::RgbImage>, String>> = batch
            .par_iter()
            .map(|&f| {
                if control.is_cancelled() {
                    return Err("cancelled".to_string());
                }
                let meshes = &lit[&representatives[f]];
                if glbs.binary_search(&f).is_ok() {
                    let bytes =
                        output::frame_glb(scene, f, meshes, tone).map_err(|e| e.to_string())?;
                    let name = frame_name(f, count, "glb");
                    std::fs::write(dir.join("baked").join(name), bytes).map_err(io)?;
                }
                let look = (tone, outputs.shading);
                let shown = (&meshes[..], &frames[f].radiance[..]);
                if pngs.binary_search(&f).is_ok() {
                    let image = output::preview_image(scene, f, shown, look, width, height);
                    let bytes = output::preview::encode_png(&image).map_err(|e| e.to_string())?;
                    let name = frame_name(f, count, "png");
                    std::fs::write(dir.join("preview").join(name), bytes).map_err(io)?;
                }
                let image = (gif.binary_search(&f).is_ok())
                    .then(|| output::preview_image(scene, f, shown, look, small.0, small.1));
                control.advance(1);
                Ok(image)
            })
            .collect();
        for image in made {
            gif_images.extend(image?);
        }
        let done = batch.last().copied().unwrap_or_default();
        lit.retain(|r, _| last_use.get(r).is_some_and(|&last| last > done));
    }
    if let Some(lightmap) = &lightmap {
        let materials = &bake.scene.materials;
        let embedded = embedded
            .into_inner()
            .unwrap_or_else(PoisonError::into_inner);
        let bytes = output::lightmap_glb(scene, materials, lightmap, embedded.as_ref())
            .map_err(|e| e.to_string())?;
        std::fs::write(dir.join("lightmaps").join("scene.glb"), bytes).map_err(io)?;
        let geometry = ("scene.glb", outputs.lightmap_quantity);
        let manifest = lightmap.manifest(scene, geometry, &representatives, |r, kind| {
            frame_name(r, count, kind)
        });
        std::fs::write(
            dir.join("lightmaps").join("manifest.json"),
            serde_json::to_vec_pretty(&manifest).map_err(|e| e.to_string())?,
        )
        .map_err(io)?;
    }
    if let Some(grid) = &probes {
        let frames = (0..count)
            .map(|f| {
                serde_json::json!({
                    "frame": f,
                    "time": scene.frames.time(f),
                    "probes": frame_name(representatives[f], count, "json"),
                })
            })
            .collect();
        let document = grid.document(bake, frames);
        std::fs::write(
            dir.join("probes").join("probes.json"),
            serde_json::to_vec_pretty(&document).map_err(|e| e.to_string())?,
        )
        .map_err(io)?;
    }
    if !gif.is_empty() {
        if control.is_cancelled() {
            return Err("cancelled".to_string());
        }
        let bytes = output::preview::encode_gif(&gif_images, delay).map_err(|e| e.to_string())?;
        std::fs::write(dir.join("preview.gif"), bytes).map_err(io)?;
    }
    Ok(gif)
}

/// A distinct frame and its drawn geometry, lit.
type LitFrame = (usize, Arc<Vec<output::NodeMesh>>);

/// The distinct frames whose light at the vertices `batch` (frames to write) needs and `lit`
/// does not hold, each once, in order: a still stretch of the timeline is one distinct frame
/// ([`Bake::representatives`]), however many frames of a batch show it.
fn unlit(batch: &[usize], representatives: &[usize], lit: impl Fn(usize) -> bool) -> Vec<usize> {
    let mut needed: Vec<usize> = (batch.iter())
        .map(|&f| representatives[f])
        .filter(|&r| !lit(r))
        .collect();
    needed.sort_unstable();
    needed.dedup();
    needed
}

/// Replaces `dir` with the complete `staging` directory: the old outputs are moved aside, the
/// new ones renamed into place, then the old ones removed. Parts of a sharded bake
/// ([`shard`]) in `dir` are not outputs: they are kept, moved into the new directory.
fn swap_in(staging: &Path, dir: &Path) -> std::io::Result<()> {
    let old = hidden(dir, "old");
    if old.exists() {
        std::fs::remove_dir_all(&old)?;
    }
    for file in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        if file.path().extension().is_some_and(|e| e == "part") {
            std::fs::rename(file.path(), staging.join(file.file_name()))?;
        }
    }
    if dir.exists() {
        std::fs::rename(dir, &old)?;
    }
    std::fs::rename(staging, dir)?;
    if old.exists() {
        std::fs::remove_dir_all(&old)?;
    }
    Ok(())
}

/// `OUT/.<name>.<suffix>` beside `OUT/<name>`.
fn hidden(dir: &Path, suffix: &str) -> PathBuf {
    let name = dir
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    dir.with_file_name(format!(".{name}.{suffix}"))
}

/// Bakes one scene into `out/<stem>/`. `log` receives a line as each stage starts; `control`
/// measures each stage from zero (so a progress bar can follow it) and cancels.
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
    // A bake killed between the two renames of `swap_in` left its previous outputs aside.
    let old = hidden(&dir, "old");
    if !dir.exists() && old.exists() {
        let _ = std::fs::rename(&old, &dir);
    }
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) => return Outcome::Failed(format!("{}: {e}", path.display())),
    };
    let hash = content_hash(&bytes, params);
    if !params.force && up_to_date(&dir, &hash) {
        return Outcome::Skipped(dir);
    }
    let mut log = |line: String| log(&format!("{name}: {line}"));
    let baked = bake_scene(&bytes, params, control, &mut log);
    match baked.and_then(|baked| write_scene(&dir, (&name, hash), baked, params, control, &mut log))
    {
        Ok(()) => Outcome::Baked(dir),
        Err(Stop::Cancelled) => Outcome::Cancelled,
        Err(Stop::Failed(reason)) => Outcome::Failed(reason),
    }
}

/// Whether `dir` holds a finished bake whose content hash is `hash`.
fn up_to_date(dir: &Path, hash: &str) -> bool {
    dir.join("radiance.bin").exists()
        && std::fs::read(dir.join("summary.json"))
            .ok()
            .and_then(|s| serde_json::from_slice::<serde_json::Value>(&s).ok())
            .is_some_and(|s| s["content_hash"] == hash)
}

/// The seconds each stage of a bake took (`timings.json`).
#[derive(Default, Serialize)]
struct Timings {
    adapt: f64,
    adapt_rounds: Vec<f64>,
    load: f64,
    outputs: f64,
    solve: f64,
    split: f64,
    trace: f64,
}

/// A scene baked, before its outputs are written.
struct Baked {
    bake: Bake,
    /// Every frame's solution.
    frames: Vec<std::sync::Arc<FrameSolution>>,
    /// `auto`'s rounds (none without it).
    rounds: Vec<crate::adaptive::Round>,
    /// The pieces the frames were solved on.
    pieces: usize,
    timings: Timings,
}

/// Seconds since the last call (the first: since it was made).
fn stopwatch() -> impl FnMut() -> f64 {
    let mut started = Instant::now();
    move || {
        std::mem::replace(&mut started, Instant::now())
            .elapsed()
            .as_secs_f64()
    }
}

/// Loads the scene of `bytes`, traces it, cuts its patches (`auto`), splits them into pieces
/// and solves every frame, stage by stage on `control`, each stage named on `log`.
fn bake_scene(
    bytes: &[u8],
    params: &BatchParams,
    control: &Control,
    log: &mut dyn FnMut(String),
) -> Result<Baked, Stop> {
    let settings = &params.settings;
    let mut timings = Timings::default();
    let mut lap = stopwatch();
    control.start_stage(0);
    log("loading".into());
    let scene = loader::load(bytes, &settings.load).map_err(|e| Stop::Failed(e.to_string()))?;
    timings.load = lap();
    let frames = scene.frames.count;
    log(format!(
        "tracing {} lines through {frames} frame{}, {} patches",
        settings.lines.lines,
        if frames == 1 { "" } else { "s" },
        scene.patches.len()
    ));
    let poses = poses_for(settings, &scene);
    let bake = Bake::trace_with(scene, (&settings.lines, poses), control)?;
    timings.trace = lap();
    finish(bake, timings, params, control, log)
}

/// The poses of the moving geometry a bake of `scene` with `settings` needs its patches'
/// sampled emitters' light at, from the start: the first alone when its patches are split into
/// pieces (solved whole at frame 0 alone), every one for `auto`'s rounds.
pub(crate) fn poses_for(settings: &BakeSettings, scene: &crate::scene::Scene) -> Poses {
    Poses::for_bake(settings.adaptive(scene.patches.len()).is_some())
}

/// [`bake_scene`] from its traced `bake` on (`timings` of the stages before it): its patches
/// cut (`auto`), split into pieces, every frame solved.
fn finish(
    mut bake: Bake,
    mut timings: Timings,
    params: &BatchParams,
    control: &Control,
    log: &mut dyn FnMut(String),
) -> Result<Baked, Stop> {
    let settings = &params.settings;
    let mut lap = stopwatch();
    let solve = SolveParams {
        sky: settings.sky,
        max_iterations: params.max_iterations,
        ..SolveParams::default()
    };
    let rounds = match settings.adaptive(bake.scene.patches.len()) {
        Some(auto) => {
            let most = auto.budget;
            log(format!(
                "cutting patches where the light needs them (at most {most})"
            ));
            adaptive::adapt(&mut bake, &auto, &solve, control)?
        }
        None => Vec::new(),
    };
    timings.adapt = lap();
    timings.adapt_rounds = rounds.iter().map(|r| r.seconds).collect();
    // The frames are solved on finer pieces of the patches ([`Bake::split`]).
    let pieces = bake.split(&solve, control)?;
    timings.split = lap();
    control.start_stage(0);
    let count = bake.scene.frames.count;
    log(format!(
        "solving {count} frame{}",
        if count == 1 { "" } else { "s" }
    ));
    let frames = solve_all(&bake, &solve, control)?;
    timings.solve = lap();
    Ok(Baked {
        bake,
        frames,
        rounds,
        pieces,
        timings,
    })
}

/// Every frame of `bake` solved ([`Bake::solve_frames`]), each distinct one a unit of
/// `control`'s stage; the first that does not converge fails the bake.
fn solve_all(
    bake: &Bake,
    solve: &SolveParams,
    control: &Control,
) -> Result<Vec<std::sync::Arc<FrameSolution>>, Stop> {
    let (mut frames, mut failed) = (Vec::with_capacity(bake.scene.frames.count), None);
    let power = bake.light_power();
    let solving = (&bake.scene.materials[..], &power[..], solve);
    control.add_work(bake.solve_runs().iter().map(Vec::len).sum::<usize>() as u64);
    let progress = |n: usize| control.advance(n as u64);
    bake.solve_frames(solving, (usize::MAX, control), &progress, |f, s| {
        if let Err(e) = s.ensure_converged(f, solve) {
            failed = Some(e);
            return ControlFlow::Break(());
        }
        frames.push(s.clone());
        ControlFlow::Continue(())
    });
    if control.is_cancelled() {
        return Err(Stop::Cancelled);
    }
    match failed {
        Some(e) => Err(Stop::Failed(e.to_string())),
        None => Ok(frames),
    }
}

/// The warnings for frames `outputs` asks for past the timeline's `count`.
fn past_end_warnings(outputs: &Outputs, count: usize) -> Vec<String> {
    let asked = [
        ("--glb-frames", &outputs.glb_frames),
        ("--preview-frames", &outputs.preview_frames),
    ];
    let has = match count {
        1 => "frame 0 only".to_string(),
        _ => format!("frames 0 to {}", count.saturating_sub(1)),
    };
    (asked.into_iter())
        .filter(|(_, spec)| !spec.past_end(count).is_empty())
        .map(|(option, spec)| {
            format!(
                "{option} {spec}: the timeline has {has}; the frames asked past them are left out"
            )
        })
        .collect()
}

/// Writes `baked`'s outputs into a staging directory beside `dir` and swaps it in whole:
/// `radiance.bin`, `patches.json`, the baked glTF and previews, `summary.json` (with `name`
/// and the content `hash`) and `timings.json`. Nothing of it is left if it fails or is
/// cancelled.
fn write_scene(
    dir: &Path,
    (name, hash): (&str, String),
    baked: Baked,
    params: &BatchParams,
    control: &Control,
    log: &mut dyn FnMut(String),
) -> Result<(), Stop> {
    let Baked {
        bake,
        frames,
        rounds,
        pieces,
        mut timings,
    } = baked;
    let scene = bake.shown();
    let times: Vec<f64> = (0..scene.frames.count)
        .map(|f| scene.frames.time(f))
        .collect();
    log("writing outputs".into());
    let started = Instant::now();
    let staging = hidden(dir, "partial");
    let tone = match params.outputs.exposure {
        Some(exposure) => ToneMap { exposure },
        None => ToneMap::for_timeline(scene, &frames),
    };
    let written = (|| -> Result<Vec<usize>, String> {
        let io = |e: std::io::Error| format!("writing {}: {e}", staging.display());
        if staging.exists() {
            std::fs::remove_dir_all(&staging).map_err(io)?;
        }
        std::fs::create_dir_all(&staging).map_err(io)?;
        write_radiance(&staging.join("radiance.bin"), &times, &frames).map_err(io)?;
        let table = serde_json::to_vec(&output::patch_table(scene)).map_err(|e| e.to_string())?;
        std::fs::write(staging.join("patches.json"), table).map_err(io)?;
        write_outputs(
            &staging,
            (&bake, params.settings.sky),
            &frames,
            &params.outputs,
            &tone,
            control,
        )
    })();
    let gif = written.map_err(|e| {
        let _ = std::fs::remove_dir_all(&staging);
        if control.is_cancelled() {
            Stop::Cancelled
        } else {
            Stop::Failed(e)
        }
    })?;
    let count = frames.len();
    let mut found = bake.findings(&frames);
    found.extend(past_end_warnings(&params.outputs, count));
    for w in &found {
        log(format!("warning: {w}"));
    }
    let warnings: Vec<String> = scene.warnings.iter().cloned().chain(found).collect();
    let settings = &params.settings;
    let summary = Summary {
        scene: name,
        content_hash: hash,
        frames: count,
        frame_times: times,
        patches: scene.patches.len(),
        pieces,
        lines: bake.list().lines(),
        gap_lines: GapLines {
            regions: bake.list().dense().0.len(),
            factor: bake.list().dense().1,
            lines: bake.list().dense_lines(),
        },
        seed: settings.lines.seed,
        fps: settings.load.fps,
        patch_size: settings.patch_size,
        adaptive: rounds,
        animation: settings.load.animation.as_deref(),
        sky: settings.sky,
        worst_residual: frames.iter().map(|f| f.residual).fold(0.0, f64::max),
        iterations: frames.iter().map(|f| f.iterations).collect(),
        converged: frames.iter().all(|f| f.converged),
        unsampled_patches: frames
            .first()
            .map_or(0, |f| f.samples.iter().filter(|&&n| n == 0).count()),
        mean_relative_error: crate::bench::estimated_error(scene, &frames),
        area_lights: bake
            .area_lights()
            .materials()
            .iter()
            .map(|&m| (m, scene.materials[m as usize].name.as_deref()))
            .collect(),
        exposure: tone.exposure,
        glb_frames: params.outputs.glb_frames.frames(count),
        preview_frames: params.outputs.preview_frames.frames(count),
        gif_frames: gif,
        warnings: &warnings,
        information: bake.information(0).report(false),
    };
    timings.outputs = started.elapsed().as_secs_f64();
    let finished = serde_json::to_vec_pretty(&summary)
        .map_err(std::io::Error::other)
        .and_then(|json| std::fs::write(staging.join("summary.json"), json))
        .and_then(|()| serde_json::to_vec(&timings).map_err(std::io::Error::other))
        .and_then(|json| std::fs::write(staging.join("timings.json"), json))
        .and_then(|()| swap_in(&staging, dir));
    finished.map_err(|e| {
        let _ = std::fs::remove_dir_all(&staging);
        Stop::Failed(format!("writing {}: {e}", dir.display()))
    })
}

/// Bakes every scene of `scenes` into `out` ([`bake_one`]), one after the other, showing each
/// stage and outcome on `progress`; once `control` is cancelled the scenes left are not baked.
/// The failures, each `path: reason` (an interrupted scene among them).
pub fn bake_all(
    scenes: &[PathBuf],
    out: &Path,
    params: &BatchParams,
    control: &Control,
    progress: &Progress,
) -> Vec<String> {
    let stage = |prefix: &str, line: &str| progress.stage(prefix, line);
    let show = |line: &str| progress.line(line);
    each_scene(scenes, control, (&stage, &show), |path, log| {
        bake_one(path, out, params, control, log)
    })
}

/// Where [`each_scene`] shows a scene's stages (with its prefix) and its outcome.
type Shown<'a> = (&'a dyn Fn(&str, &str), &'a dyn Fn(&str));

/// [`bake_all`]'s loop: `bake` each scene in turn (given a log for its stages), each stage
/// shown by `stage` (with the scene's `[k/n]` prefix) and each outcome by `show`. A bake that
/// panics (a bug) fails its scene alone: the scenes after it are baked.
fn each_scene(
    scenes: &[PathBuf],
    control: &Control,
    (stage, show): Shown<'_>,
    mut bake: impl FnMut(&Path, &mut dyn FnMut(&str)) -> Outcome,
) -> Vec<String> {
    let mut failures = Vec::new();
    for (k, path) in scenes.iter().enumerate() {
        if control.is_cancelled() {
            failures.push(format!("{}: not baked (interrupted)", path.display()));
            continue;
        }
        let prefix = format!("[{}/{}]", k + 1, scenes.len());
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            bake(path, &mut |line| stage(&prefix, line))
        }))
        .unwrap_or_else(|payload| Outcome::Failed(panicked(payload.as_ref())));
        match outcome {
            Outcome::Baked(dir) => show(&format!(
                "{prefix} baked {} -> {}",
                path.display(),
                dir.display()
            )),
            Outcome::Skipped(dir) => show(&format!("{prefix} up to date: {}", dir.display())),
            Outcome::Failed(reason) => {
                show(&format!("{prefix} FAILED {}: {reason}", path.display()));
                failures.push(format!("{}: {reason}", path.display()));
            }
            Outcome::Cancelled => {
                show(&format!(
                    "{prefix} interrupted {}: nothing written",
                    path.display()
                ));
                failures.push(format!("{}: interrupted", path.display()));
            }
        }
    }
    failures
}

/// Why a bake that panicked failed: the panic's message, as a bug of the baker's.
fn panicked(payload: &(dyn std::any::Any + Send)) -> String {
    let message = crate::control::panic_message(payload);
    format!("the baker failed on this scene (a bug: please report it with the scene): {message}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::{BakeRequest, Limits};

    #[test]
    fn a_batch_lights_each_distinct_frame_it_shows_once() {
        // Frames 0–2 still (frame 0's light), 3–5 still (frame 3's), 6 its own.
        let representatives = [0, 0, 0, 3, 3, 3, 6];
        assert_eq!(
            unlit(&[1, 2, 3, 4, 5], &representatives, |_| false),
            vec![0, 3]
        );
        // What an earlier batch lit is not lit again.
        assert_eq!(
            unlit(&[2, 3, 4, 5, 6], &representatives, |r| r == 3),
            vec![0, 6]
        );
        assert!(unlit(&[4, 5], &representatives, |r| r == 3).is_empty());
    }

    #[test]
    fn the_gif_keeps_at_most_its_frame_budget_at_a_delay_browsers_honour() {
        assert_eq!(gif_frames(25, 12.0), ((0..25).collect(), 83));
        // 60 fps is faster than browsers show: every other frame.
        let (frames, delay) = gif_frames(10, 60.0);
        assert_eq!(frames, vec![0, 2, 4, 6, 8]);
        assert_eq!(delay, 33);
        let (frames, delay) = gif_frames(2001, 30.0);
        assert!(frames.len() <= GIF_MAX_FRAMES && frames.len() > GIF_MAX_FRAMES / 2);
        assert_eq!(delay, 9 * 1000 / 30);
        // Absurd rates end at once, with one frame.
        assert_eq!(gif_frames(1001, 1e12), (vec![0], 20));
        assert_eq!(frame_name(7, 25, "png"), "frame_0007.png");
        assert_eq!(frame_name(7, 100_000, "glb"), "frame_00007.glb");
    }

    /// A bake that panics on one scene (a bug) fails that scene with the panic's message;
    /// the scenes after it are baked, and the failures say which failed and why.
    #[test]
    fn a_scene_whose_bake_panics_fails_alone() {
        let scenes: Vec<PathBuf> = ["a.gltf", "b.gltf", "c.gltf"].map(PathBuf::from).into();
        let shown = std::sync::Mutex::new(Vec::new());
        let show = |line: &str| shown.lock().unwrap().push(line.to_string());
        let mut baked = Vec::new();
        let failures = each_scene(&scenes, &Control::default(), (&|_, _| {}, &show), |p, _| {
            assert!(p != Path::new("b.gltf"), "a bug in the cutter");
            baked.push(p.to_path_buf());
            Outcome::Baked(p.to_path_buf())
        });
        assert_eq!(baked, [PathBuf::from("a.gltf"), PathBuf::from("c.gltf")]);
        assert_eq!(failures.len(), 1, "{failures:?}");
        assert!(failures[0].starts_with("b.gltf: "), "{failures:?}");
        assert!(failures[0].contains("a bug in the cutter"), "{failures:?}");
        let shown = shown.lock().unwrap();
        assert!(shown[1].starts_with("[2/3] FAILED b.gltf"), "{shown:?}");
        assert!(shown[2].starts_with("[3/3] baked c.gltf"), "{shown:?}");
    }

    fn params() -> BatchParams {
        BatchParams {
            settings: BakeRequest::default().validate(&Limits::default()).unwrap(),
            outputs: Outputs::default(),
            force: false,
            max_iterations: SolveParams::default().max_iterations,
        }
    }

    #[test]
    fn the_content_hash_is_sha256_of_the_bytes_and_every_parameter_that_changes_the_outputs() {
        let base = content_hash(b"scene", &params());
        assert_eq!(base.len(), 64);
        assert!(base.bytes().all(|b| b.is_ascii_hexdigit()));
        // Deterministic, and not a hash of the bytes alone.
        assert_eq!(base, content_hash(b"scene", &params()));
        assert_ne!(base, content_hash(b"scenf", &params()));
        // The bytes are length-prefixed: moving a byte from the scene to the parameters'
        // text cannot give the same input.
        assert_ne!(content_hash(b"", &params()), content_hash(b"{", &params()));
        let changed: Vec<fn(&mut BatchParams)> = vec![
            |p| p.settings.load.fps += 1.0,
            |p| p.settings.load.animation = Some("door".into()),
            |p| p.settings.load.camera = Some("auto".into()),
            |p| p.settings.load.start = Some(0.5),
            |p| p.settings.load.end = Some(1.5),
            |p| p.settings.load.patch_size = Some(0.25),
            |p| p.settings.load.max_frames += 1,
            |p| p.settings.load.max_patches += 1,
            |p| p.settings.load.max_work += 1,
            |p| p.settings.load.max_reflectance = 0.99,
            |p| p.settings.patch_size = PatchSize::Auto,
            |p| p.settings.patch_budget = Some(500),
            |p| p.settings.lines.lines += 1,
            |p| p.settings.lines.seed = 2,
            |p| p.settings.sky = [0.0, 0.0, 1e-9],
            |p| p.max_iterations += 1,
            |p| p.outputs.glb_frames = FrameSpec::List(vec![output::FrameItem::First]),
            |p| p.outputs.preview_frames = FrameSpec::All,
            |p| p.outputs.preview_size = (640, 481),
            |p| p.outputs.gif = false,
            |p| p.outputs.exposure = Some(2.0),
            |p| p.outputs.shading = output::Shading::Flat,
            |p| p.outputs.lightmaps = Some(8.0),
            |p| {
                p.outputs.lightmaps = Some(8.0);
                p.outputs.lightmap_quantity = output::lightmap::Quantity::Light;
            },
            |p| p.outputs.probes = Some(None),
            |p| p.outputs.probes = Some(Some(0.5)),
        ];
        let mut seen = std::collections::HashSet::from([base.clone()]);
        for (k, change) in changed.iter().enumerate() {
            let mut p = params();
            change(&mut p);
            assert!(
                seen.insert(content_hash(b"scene", &p)),
                "change {k} left the hash"
            );
        }
        // Only `force` does not change what is written.
        let mut p = params();
        p.force = true;
        assert_eq!(content_hash(b"scene", &p), base);
    }
}
