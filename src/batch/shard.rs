//! One scene's bake over several machines (`radiosity bake SCENE --shard K/N`, then
//! `radiosity merge`): each machine traces the bundles of lines `b ≡ K mod N`
//! ([`IntersectionList::build_shard`]) and writes them as a part file; the merge puts the parts
//! together into the list one machine traces ([`IntersectionList::merge`], to the bit) and
//! bakes on from there as `bake` does, so its outputs are byte-identical to a single machine's
//! (`timings.json` aside).
//!
//! A part, `OUT/<scene>/shard-K-of-N.part`, is a checked file ([`crate::checked`]) whose payload is
//! `RADPART1`, the build that wrote it ([`checked::build`]: the encoding does not describe itself,
//! so only the same build reads it), then the scene's name, what the bake is asked for (the
//! settings and the solver's cap: the merge takes them from the parts, and only its outputs from
//! its own options), a hash of those and the scene's bytes, the shard, the scene's bytes and the
//! part's crossings (the intersection list of its lines: the patches are cut after tracing where
//! the light needs them, `patch_size=auto`, so the parts carry crossings, not tallies of patches
//! not made yet).

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::{BatchParams, Outcome, Outputs, Timings, content_hash, finish, write_scene};
use crate::bake::Bake;
use crate::checked;
use crate::control::{Control, Stop};
use crate::loader;
use crate::params::BakeSettings;
use crate::timeline::{IntersectionList, Shard};
use crate::trace::SceneTracer;

/// The kind of a part file ([`checked::stamped`]).
const PART: &[u8; 8] = b"RADPART1";

/// A part as written.
#[derive(Serialize)]
struct Written<'a> {
    name: &'a str,
    settings: &'a BakeSettings,
    max_iterations: usize,
    hash: &'a str,
    shard: Shard,
    scene: &'a [u8],
    list: &'a IntersectionList,
}

/// A part as read.
#[derive(Deserialize)]
struct Part {
    name: String,
    settings: BakeSettings,
    max_iterations: usize,
    hash: String,
    shard: Shard,
    scene: Vec<u8>,
    list: IntersectionList,
}

/// The name of shard `shard`'s part.
#[must_use]
pub fn part_name(shard: Shard) -> String {
    format!("shard-{}-of-{}.part", shard.index, shard.count)
}

/// What tells the parts of one bake from others': the content hash of the scene's `bytes` and
/// what the bake is asked for, whatever the outputs.
fn bake_hash(bytes: &[u8], settings: &BakeSettings, max_iterations: usize) -> String {
    let params = BatchParams {
        settings: settings.clone(),
        outputs: Outputs::default(),
        force: false,
        max_iterations,
    };
    content_hash(bytes, &params)
}

/// The scene's name (its file's stem) and bytes, as a bake names and reads it.
fn read_scene(path: &Path) -> Result<(String, Vec<u8>), String> {
    let name = path
        .file_stem()
        .map_or_else(|| "scene".to_string(), |s| s.to_string_lossy().into_owned());
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok((name, bytes))
}

/// Traces `shard`'s lines of the scene at `path` with `params` into
/// `out/<scene>/shard-K-of-N.part` (skipped if that part is there for the same content and
/// build, unless forced). `log` receives a line as each stage starts.
pub fn trace_part(
    path: &Path,
    out: &Path,
    shard: Shard,
    params: &BatchParams,
    control: &Control,
    log: &mut dyn FnMut(&str),
) -> Outcome {
    let (name, bytes) = match read_scene(path) {
        Ok(read) => read,
        Err(e) => return Outcome::Failed(e),
    };
    let hash = bake_hash(&bytes, &params.settings, params.max_iterations);
    let file = out.join(&name).join(part_name(shard));
    if !params.force && read_part(&file).is_ok_and(|p| p.hash == hash && p.shard == shard) {
        return Outcome::Skipped(file);
    }
    let traced = (|| {
        control.start_stage(0);
        log(&format!("{name}: loading"));
        let scene =
            loader::load(&bytes, &params.settings.load).map_err(|e| Stop::Failed(e.to_string()))?;
        let lines = &params.settings.lines;
        log(&format!(
            "{name}: tracing part {}/{} of {} lines through {} frames",
            shard.index, shard.count, lines.lines, scene.frames.count
        ));
        let tracer = SceneTracer::new(&scene);
        Ok(IntersectionList::build_shard(
            &scene, &tracer, lines, shard, control,
        )?)
    })();
    let list = match traced {
        Ok(list) => list,
        Err(Stop::Cancelled) => return Outcome::Cancelled,
        Err(Stop::Failed(e)) => return Outcome::Failed(e),
    };
    let written = Written {
        name: &name,
        settings: &params.settings,
        max_iterations: params.max_iterations,
        hash: &hash,
        shard,
        scene: &bytes,
        list: &list,
    };
    match write_part(&file, &written) {
        Ok(()) => Outcome::Baked(file),
        Err(e) => Outcome::Failed(format!("{}: {e}", file.display())),
    }
}

/// Writes `part` to `file` whole or not at all (a temporary file, flushed, renamed).
fn write_part(file: &Path, part: &Written) -> std::io::Result<()> {
    let Some(out) = checked::stamped(PART) else {
        return Err(std::io::Error::other(
            "this build cannot read its own executable, which identifies its parts",
        ));
    };
    let out = checked::sealed(postcard::to_extend(part, out).map_err(std::io::Error::other)?);
    if let Some(dir) = file.parent() {
        std::fs::create_dir_all(dir)?;
    }
    checked::write_whole(file, &out)
}

/// The part in `file`.
fn read_part(file: &Path) -> Result<Part, String> {
    let bytes = std::fs::read(file).map_err(|e| format!("{}: {e}", file.display()))?;
    let what = |e: &dyn std::fmt::Display| format!("{}: {e}", file.display());
    let kind = (PART, "a part file (made by `radiosity bake --shard`)");
    match checked::unstamped("the part", &bytes, kind).map_err(|e| what(&e))? {
        checked::Stamp::Ours(rest) => {
            postcard::from_bytes(rest).map_err(|e| what(&format!("the part is damaged: {e}")))
        }
        checked::Stamp::OtherBuild => Err(what(
            &"made by another build of radiosity: parts are merged by the build that traced \
              them (the same image on every machine)",
        )),
    }
}

/// Merges the parts in `files` (every part of one scene's lines, once each, in any order) and
/// bakes on as [`super::bake_one`] does with the parameters the parts were traced with, into
/// `out/<scene>/` with `outputs` (`force`: even if they are up to date). `log` receives a line
/// as each stage starts.
pub fn merge(
    files: &[PathBuf],
    out: &Path,
    (outputs, force): (&Outputs, bool),
    control: &Control,
    log: &mut dyn FnMut(&str),
) -> Outcome {
    let started = Instant::now();
    let mut parts = Vec::with_capacity(files.len());
    for file in files {
        match read_part(file) {
            Ok(part) => parts.push((file, part)),
            Err(e) => return Outcome::Failed(e),
        }
    }
    let Some((first_file, first)) = parts.first() else {
        return Outcome::Failed("no part to merge".into());
    };
    let (name, hash) = (first.name.clone(), first.hash.clone());
    for (file, part) in &parts {
        if part.hash != hash {
            return Outcome::Failed(format!(
                "{} and {} are parts of different bakes (another scene, or other parameters)",
                first_file.display(),
                file.display()
            ));
        }
    }
    let (first_file, first) = &mut parts[0];
    let scene_bytes = std::mem::take(&mut first.scene);
    if bake_hash(&scene_bytes, &first.settings, first.max_iterations) != hash {
        return Outcome::Failed(format!("{}: the part is damaged", first_file.display()));
    }
    let params = &BatchParams {
        settings: first.settings.clone(),
        outputs: outputs.clone(),
        force,
        max_iterations: first.max_iterations,
    };
    let dir = out.join(&name);
    let hash = content_hash(&scene_bytes, params);
    if !force && super::up_to_date(&dir, &hash) {
        return Outcome::Skipped(dir);
    }
    let lists = parts.into_iter().map(|(_, p)| (p.shard, p.list)).collect();
    let list = match IntersectionList::merge(lists) {
        Ok(list) => list,
        Err(e) => return Outcome::Failed(format!("{name}: {e}")),
    };
    let mut log = |line: String| log(&format!("{name}: {line}"));
    let baked = (|| {
        control.start_stage(0);
        log(format!("merged {} lines; loading", list.lines()));
        let scene = loader::load(&scene_bytes, &params.settings.load)
            .map_err(|e| Stop::Failed(e.to_string()))?;
        let seed = params.settings.lines.seed;
        let poses = super::poses_for(&params.settings, &scene);
        let bake = Bake::of_merged_list(scene, list, (seed, poses), control)?;
        let timings = Timings {
            trace: started.elapsed().as_secs_f64(),
            ..Timings::default()
        };
        finish(bake, timings, params, control, &mut log)
    })();
    match baked.and_then(|baked| write_scene(&dir, (&name, hash), baked, params, control, &mut log))
    {
        Ok(()) => Outcome::Baked(dir),
        Err(Stop::Cancelled) => Outcome::Cancelled,
        Err(Stop::Failed(reason)) => Outcome::Failed(reason),
    }
}
