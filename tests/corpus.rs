//! The corpus test (issue 48): awkward files real exporters write ([`awkward`], built
//! in code) and the Khronos conformance samples (`../shared/gltf-samples`) are each baked the
//! way `radiosity bake` bakes them ([`bake_one`]: load, trace, cut (`auto`), split, solve,
//! write the outputs) with a few tens of thousands of lines and one to three frames, once with
//! the default patches (`source`) and once with `auto`. Every one bakes (patches, finite
//! radiance ≥ 0 in every frame) or fails with a message naming what is wrong; none panics or
//! hangs. Each bake runs on its own thread and thread pool, under `catch_unwind` and a time
//! limit, and the one assertion lists every case that went wrong, with the panic's message and
//! location.
//!
//! `CORPUS_DIR=dir` keeps the files (`dir/valid/`, `dir/invalid/`: those the specification
//! allows and those it does not) and the outputs (`dir/out/`), to look at or to check with
//! the Khronos validator: `node scenes/validate.mjs dir/valid/*`.

#[path = "corpus/awkward.rs"]
mod awkward;
#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};

use awkward::{Case, Expect};
use radiosity::batch::{BatchParams, Outcome, Outputs, bake_one};
use radiosity::control::Control;
use radiosity::output::{FrameItem, FrameSpec};
use radiosity::params::{BakeRequest, Limits, PatchSize};
use radiosity::solve::SolveParams;

/// Lines per bake: enough for every patch of these small scenes to be crossed, few enough
/// for the corpus to bake in seconds.
const LINES: u64 = 20_000;

/// A bake still running after this long hangs: it is cancelled and reported. The slowest case
/// takes under a second in release builds.
const HANG: Duration = Duration::from_secs(15);

/// The Khronos samples, each with the frame rate that gives its animation three frames at
/// most.
fn khronos_samples() -> Vec<Case> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/gltf-samples");
    [
        ("Cameras", 1.0),
        ("MultipleScenes", 1.0),
        ("OrientationTest", 1.0),
        ("SimpleMorph", 0.5),
        ("SimpleSkin", 0.4),
        ("SimpleSparseAccessor", 1.0),
        ("TriangleWithoutIndices", 1.0),
    ]
    .into_iter()
    .map(|(name, fps)| {
        let path = dir.join(format!("{name}.gltf"));
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        Case::bytes(&format!("khronos_{name}"), bytes, "gltf", Expect::Bakes).at_fps(fps)
    })
    .collect()
}

/// What `radiosity bake --lines 20000 --fps F --sky R,G,B --patch-size P --force --glb-frames
/// all --preview-frames first --preview-size 48x36` asks for.
fn params(case: &Case, patch_size: PatchSize) -> BatchParams {
    let sky = case.sky.map(|c| c.to_string()).join(",");
    let request = BakeRequest {
        fps: Some(case.fps),
        lines: Some(LINES),
        sky: Some(sky.parse().unwrap()),
        patch_size: Some(patch_size),
        ..BakeRequest::default()
    };
    BatchParams {
        settings: request.validate(&Limits::default()).unwrap(),
        outputs: Outputs {
            glb_frames: FrameSpec::All,
            preview_frames: FrameSpec::List(vec![FrameItem::First]),
            preview_size: (48, 36),
            ..Outputs::default()
        },
        force: true,
        max_iterations: SolveParams::default().max_iterations,
    }
}

/// The panics seen, `message at file:line:column`, recorded by the panic hook on whichever
/// thread panicked (a rayon worker's location is lost once its panic is carried to the
/// caller).
static PANICS: Mutex<Vec<String>> = Mutex::new(Vec::new());

/// Records every panic's message and location in [`PANICS`], then prints it as usual.
fn record_panics() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let location = info.location().map_or("?".to_string(), ToString::to_string);
            let message = text(info.payload());
            if let Ok(mut panics) = PANICS.lock() {
                panics.push(format!("{message:?} at {location}"));
            }
            default(info);
        }));
    });
}

/// A panic payload's message.
fn text(payload: &(dyn std::any::Any + Send)) -> String {
    (payload.downcast_ref::<&str>().map(ToString::to_string))
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".to_string())
}

/// How a case's bake ended.
enum Ran {
    /// Baked into this directory.
    Baked(PathBuf),
    /// Failed with this message.
    Failed(String),
    /// Panicked: the panics recorded.
    Panicked(String),
    /// Still running after [`HANG`]; whether it stopped once cancelled.
    Hung { stopped: bool },
}

/// Bakes the file `input` with `params` into `out` on a thread and a thread pool of its own
/// (a bake that hangs keeps its own workers busy, not the next one's), under `catch_unwind`
/// and the [`HANG`] limit.
fn run(input: &Path, params: BatchParams, out: &Path) -> Ran {
    let control = Arc::new(Control::default());
    let (sender, receiver) = mpsc::channel();
    let (input, out, running) = (input.to_path_buf(), out.to_path_buf(), control.clone());
    PANICS.lock().unwrap().clear();
    std::thread::spawn(move || {
        let baked = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            let pool = rayon::ThreadPoolBuilder::new().build().unwrap();
            pool.install(|| bake_one(&input, &out, &params, &running, &mut |_| {}))
        }));
        let _ = sender.send(baked);
    });
    // A cancelled bake stops within a bundle of lines.
    let ended = receiver.recv_timeout(HANG).or_else(|_| {
        control.cancel();
        receiver.recv_timeout(Duration::from_secs(2))
    });
    match ended {
        Ok(Ok(Outcome::Baked(dir))) => Ran::Baked(dir),
        Ok(Ok(Outcome::Failed(message))) => Ran::Failed(message),
        Ok(Ok(Outcome::Skipped(dir))) => Ran::Failed(format!("skipped, {dir:?} up to date")),
        Ok(Ok(Outcome::Cancelled)) => Ran::Hung { stopped: true },
        Err(_) => Ran::Hung { stopped: false },
        Ok(Err(payload)) => {
            let recorded = PANICS.lock().unwrap().join("; ");
            Ran::Panicked(if recorded.is_empty() {
                text(payload.as_ref())
            } else {
                recorded
            })
        }
    }
}

/// What a bake wrote, checked: its patches, frames and warnings, or what is wrong with it.
fn check_outputs(dir: &Path) -> Result<(usize, usize, Vec<String>), String> {
    let bin = std::fs::read(dir.join("radiance.bin")).map_err(|e| format!("radiance.bin: {e}"))?;
    let word = |at: usize| -> Result<usize, String> {
        let bytes = bin.get(at..at + 4).ok_or("radiance.bin is cut short")?;
        Ok(u32::from_le_bytes(bytes.try_into().unwrap()) as usize)
    };
    if bin.get(..4) != Some(b"RADB") {
        return Err("radiance.bin has no RADB magic".into());
    }
    let (frames, patches) = (word(8)?, word(12)?);
    if patches == 0 || frames == 0 {
        return Err(format!("{frames} frames of {patches} patches"));
    }
    if frames > 3 {
        return Err(format!("{frames} frames, not 1 to 3: lower the case's fps"));
    }
    // Per frame: f64 time, P×3 f32 radiance, P×3 f32 standard error (−1: unsampled), P u32
    // samples.
    let size = 8 + patches * 28;
    if bin.len() != 16 + frames * size {
        return Err(format!("radiance.bin is {} bytes", bin.len()));
    }
    for f in 0..frames {
        let at = 16 + f * size + 8;
        let float =
            |k: usize| f32::from_le_bytes(bin[at + 4 * k..at + 4 * k + 4].try_into().unwrap());
        let radiance = (0..3 * patches).map(float);
        if let Some((k, l)) = radiance
            .enumerate()
            .find(|(_, l)| !(l.is_finite() && *l >= 0.0))
        {
            return Err(format!("frame {f}: patch {} has radiance {l}", k / 3));
        }
        let stderr = (3 * patches..6 * patches).map(float);
        if let Some((k, s)) = stderr
            .enumerate()
            .find(|(_, s)| !(s.is_finite() && (*s >= 0.0 || *s == -1.0)))
        {
            return Err(format!("frame {f}: patch {} has standard error {s}", k / 3));
        }
    }
    let summary: serde_json::Value = std::fs::read(dir.join("summary.json"))
        .ok()
        .and_then(|s| serde_json::from_slice(&s).ok())
        .ok_or("no summary.json")?;
    if summary["patches"].as_u64() != Some(patches as u64) {
        return Err(format!("summary.json: patches {}", summary["patches"]));
    }
    for f in 0..frames {
        let glb = dir.join("baked").join(format!("frame_{f:04}.glb"));
        if !glb.is_file() {
            return Err(format!("no {}", glb.display()));
        }
    }
    let warnings = (summary["warnings"].as_array().into_iter().flatten())
        .filter_map(|w| w.as_str().map(str::to_string))
        .collect();
    Ok((patches, frames, warnings))
}

/// Whether `ran` is what `case` expects: `Ok` with a line for the table, or why not.
fn judge(case: &Case, ran: Ran) -> Result<String, String> {
    match (ran, case.expect) {
        (Ran::Panicked(panics), _) => Err(format!("PANICKED: {panics}")),
        (Ran::Hung { stopped }, _) => Err(format!(
            "HUNG: still running after {} s; cancelled, it {}",
            HANG.as_secs(),
            if stopped {
                "stopped"
            } else {
                "went on (its thread is left running)"
            }
        )),
        (Ran::Baked(dir), expect) => {
            let (patches, frames, warnings) = check_outputs(&dir)?;
            let baked = format!("baked: {patches} patches, {frames} frames, warnings {warnings:?}");
            match expect {
                Expect::Bakes => Ok(baked),
                Expect::Warns(w) if warnings.iter().any(|x| x.contains(w)) => Ok(baked),
                Expect::Warns(w) => Err(format!("{baked}; expected a warning with {w:?}")),
                Expect::Refused(r) => Err(format!("{baked}; expected an error with {r:?}")),
            }
        }
        (Ran::Failed(message), Expect::Refused(r)) if message.contains(r) => {
            Ok(format!("refused: {message}"))
        }
        (Ran::Failed(message), Expect::Refused(r)) => Err(format!(
            "refused with {message:?}, which does not say {r:?}"
        )),
        (Ran::Failed(message), _) => Err(format!("failed: {message}")),
    }
}

#[test]
fn every_awkward_file_bakes_or_is_refused_by_name_and_none_panics() {
    record_panics();
    let kept = std::env::var_os("CORPUS_DIR").map(PathBuf::from);
    let root = (kept.clone()).unwrap_or_else(|| {
        std::env::temp_dir().join(format!("radiosity-corpus-{}", std::process::id()))
    });
    let (valid, invalid, out) = (root.join("valid"), root.join("invalid"), root.join("out"));
    for dir in [&valid, &invalid, &out] {
        let _ = std::fs::remove_dir_all(dir);
        std::fs::create_dir_all(dir).unwrap();
    }
    let cases: Vec<Case> = (awkward::cases().into_iter())
        .chain(khronos_samples())
        .collect();
    let started = Instant::now();
    let mut failures = Vec::new();
    for case in &cases {
        let dir = if case.valid { &valid } else { &invalid };
        let input = dir.join(format!("{}.{}", case.name, case.extension));
        std::fs::write(&input, &case.bytes).unwrap();
        for patch_size in [PatchSize::Source, PatchSize::Auto] {
            let name = format!("{} ({patch_size})", case.name);
            let at = Instant::now();
            let out = out.join(patch_size.to_string());
            let verdict = judge(case, run(&input, params(case, patch_size), &out));
            let seconds = at.elapsed().as_secs_f64();
            match &verdict {
                Ok(line) => eprintln!("ok     {name:<38} {seconds:5.2} s  {line}"),
                Err(why) => eprintln!("FAILED {name:<38} {seconds:5.2} s  {why}"),
            }
            if let Err(why) = verdict {
                failures.push(format!("{name}: {why}"));
            }
        }
    }
    eprintln!(
        "{} cases in {:.1} s",
        cases.len(),
        started.elapsed().as_secs_f64()
    );
    if kept.is_none() {
        let _ = std::fs::remove_dir_all(&root);
    }
    assert!(
        failures.is_empty(),
        "{} of {} bakes went wrong:\n  {}",
        failures.len(),
        2 * cases.len(),
        failures.join("\n  ")
    );
}
