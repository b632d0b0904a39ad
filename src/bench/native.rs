//! The same tracing, measured against native Embree in one run: the scene as posed at frame 0
//! and the list's lines go to a file, `bench/embree/trace.c` (built with Debian's
//! `libembree-dev` when asked for) finds every crossing of every line, and this tracer traces
//! the same lines through the same triangles, bundle by bundle, on as many threads.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::scene::Scene;
use crate::trace::{ParallelLines, SceneTracer, Scratch};

/// Repeats of each measurement; the median counts.
const REPEATS: usize = 5;

/// Passes per run of the Embree program, which reports their median: a run's first pass is
/// cold (a new process, a new BVH), and three passes leave it out.
const EMBREE_PASSES: usize = 3;

/// One frame traced alone by this tracer and by native Embree, on the same lines.
#[derive(Clone, Debug, Serialize)]
pub struct NativeComparison {
    /// Triangles traced (the scene at frame 0, moving objects included).
    pub triangles: usize,
    /// Crossings found per pass by this tracer.
    pub crossings: usize,
    /// This tracer, median seconds of a pass.
    pub seconds: f64,
    /// This tracer, crossings per second.
    pub crossings_per_second: f64,
    /// Native Embree's fastest mode, if it could be built and run.
    pub embree: Option<EmbreeRun>,
    /// Why there is no Embree figure, if there is none.
    pub embree_missing: Option<String>,
    /// This tracer's rate over Embree's: the median over passes run one after the other.
    pub ratio: Option<f64>,
}

/// What the Embree program reports for one mode (one JSON line).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EmbreeRun {
    /// `occluded8`, `occluded1` or `intersect1`.
    pub mode: String,
    /// Crossings found per pass.
    pub crossings: usize,
    /// Seconds of a pass (in a comparison, the median pass).
    pub seconds: f64,
    /// Million crossings per second.
    pub mcps: f64,
}

/// Traces `bundles` through the scene at frame 0 with this tracer and with native Embree
/// (built from `bench/embree` into `build_dir` if it is not there), on `threads` threads.
///
/// Embree's modes are tried first; then a run of its fastest and a pass of this tracer
/// alternate, five times, so that both see the same moments of a shared, noisy machine;
/// the ratio is the median of the pairs'.
pub fn compare(
    scene: &Scene,
    tracer: &SceneTracer,
    bundles: &[ParallelLines],
    build_dir: &Path,
    threads: usize,
) -> NativeComparison {
    let triangles = scene.triangles_at(0);
    let deformed = tracer.deformed_at(scene, 0);
    let trace_once = || {
        let start = Instant::now();
        let crossings: usize = bundles
            .par_iter()
            .map_init(
                || (Scratch::default(), Vec::new()),
                |(scratch, found), lines| {
                    tracer.trace_frame_parallel(lines, 0, &deformed, scratch, found);
                    found.len()
                },
            )
            .sum();
        (crossings, start.elapsed().as_secs_f64())
    };
    let _warm_up = trace_once();
    let file = build_dir.join("lines.rlines");
    let program = build(build_dir).and_then(|program| {
        write_lines(&file, triangles.iter().map(|(c, _)| c), bundles)
            .map_err(|e| format!("could not write {}: {e}", file.display()))?;
        Ok(program)
    });
    let mode = program
        .as_ref()
        .map_err(Clone::clone)
        .and_then(|program| run(program, &file, threads, None))
        .map(|fastest| fastest.mode);
    let mut embree = mode.as_ref().map(|_| Vec::new()).map_err(Clone::clone);
    let mut ours = Vec::with_capacity(REPEATS);
    for _ in 0..REPEATS {
        if let (Ok(program), Ok(mode)) = (&program, &mode) {
            let pass = run(program, &file, threads, Some(mode));
            embree = embree.and_then(|mut runs| {
                runs.push(pass?);
                Ok(runs)
            });
        }
        ours.push(trace_once());
    }
    let _ = std::fs::remove_file(&file);
    finish(&ours, triangles.len(), embree)
}

/// The median of `values` (not empty).
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// The comparison from this tracer's passes (crossings, seconds) and Embree's, pass for pass,
/// or why there are none.
fn finish(
    ours: &[(usize, f64)],
    triangles: usize,
    embree: Result<Vec<EmbreeRun>, String>,
) -> NativeComparison {
    let seconds = median(ours.iter().map(|&(_, s)| s).collect());
    let crossings = ours[0].0;
    let (embree, embree_missing, ratio) = match embree {
        Ok(runs) if runs.len() == ours.len() => {
            let ratio = median(
                ours.iter()
                    .zip(&runs)
                    .map(|(&(n, s), e)| n as f64 / s / (e.mcps * 1e6))
                    .collect(),
            );
            let mut runs = runs;
            runs.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
            (Some(runs.swap_remove(ours.len() / 2)), None, Some(ratio))
        }
        Ok(_) => (None, Some("Embree reported no pass".to_owned()), None),
        Err(why) => (None, Some(why), None),
    };
    NativeComparison {
        triangles,
        crossings,
        seconds,
        crossings_per_second: crossings as f64 / seconds,
        embree,
        embree_missing,
        ratio,
    }
}

/// Builds the comparison program into `dir`; why not, if it cannot be.
fn build(dir: &Path) -> Result<PathBuf, String> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("bench/embree/build.sh");
    let out = Command::new("bash")
        .arg(&script)
        .arg(dir)
        .output()
        .map_err(|e| format!("could not run {}: {e}", script.display()))?;
    if !out.status.success() {
        let said = String::from_utf8_lossy(&out.stderr);
        return Err(format!(
            "native Embree not built ({}): {}",
            script.display(),
            said.trim()
        ));
    }
    Ok(dir.join("trace"))
}

/// Runs the program on `file` in `mode`, or in every mode if none ([`EMBREE_PASSES`] passes
/// each): the fastest mode's median pass.
fn run(
    program: &Path,
    file: &Path,
    threads: usize,
    mode: Option<&str>,
) -> Result<EmbreeRun, String> {
    let out = Command::new(program)
        .arg(file)
        .args(["--threads", &threads.to_string()])
        .args(["--repeat", &EMBREE_PASSES.to_string()])
        .args(["--mode", mode.unwrap_or("all")])
        .output()
        .map_err(|e| format!("could not run {}: {e}", program.display()))?;
    if !out.status.success() {
        return Err(format!(
            "{} failed: {}",
            program.display(),
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|line| serde_json::from_str::<EmbreeRun>(line).ok())
        .max_by(|a, b| a.mcps.total_cmp(&b.mcps))
        .ok_or_else(|| format!("{} reported nothing", program.display()))
}

/// Writes triangles and bundles in the program's `RLINES1` format (bench/embree/README.md).
fn write_lines<'a>(
    path: &Path,
    triangles: impl ExactSizeIterator<Item = &'a [glam::Vec3; 3]>,
    bundles: &[ParallelLines],
) -> std::io::Result<()> {
    let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
    let count = |n: usize| u32::try_from(n).map_err(std::io::Error::other);
    out.write_all(b"RLINES1\0")?;
    out.write_all(&count(triangles.len())?.to_le_bytes())?;
    let floats = |out: &mut std::io::BufWriter<_>, v: glam::Vec3| {
        v.to_array()
            .iter()
            .try_for_each(|x| out.write_all(&x.to_le_bytes()))
    };
    for corners in triangles {
        for &c in corners {
            floats(&mut out, c)?;
        }
    }
    out.write_all(&count(bundles.len())?.to_le_bytes())?;
    for lines in bundles {
        floats(&mut out, lines.direction())?;
        out.write_all(&count(lines.len())?.to_le_bytes())?;
        for &o in lines.origins() {
            floats(&mut out, o)?;
        }
    }
    out.flush()
}

impl std::fmt::Display for NativeComparison {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "frame 0 alone    {} triangles, {} crossings in {:.3} s: {:.1} M crossings/s",
            self.triangles,
            self.crossings,
            self.seconds,
            self.crossings_per_second / 1e6
        )?;
        match (&self.embree, &self.embree_missing) {
            (Some(e), _) => writeln!(
                f,
                "native Embree    {} crossings in {:.3} s ({}): {:.1} M crossings/s; this tracer {:.2}x (median of alternated passes)",
                e.crossings,
                e.seconds,
                e.mode,
                e.mcps,
                self.ratio.unwrap_or(f64::NAN)
            ),
            (None, Some(why)) => writeln!(f, "native Embree    none: {why}"),
            (None, None) => Ok(()),
        }
    }
}
