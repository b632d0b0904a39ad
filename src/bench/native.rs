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
use crate::trace::{BuildEffort, ParallelLines, SceneTracer, Scratch};

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
    /// The multiframe list's build, crossings traced per second: the median of builds run
    /// between the passes of the rest (issue 16 asks it of Embree's rate for one frame).
    pub list_crossings_per_second: Option<f64>,
    /// That rate over Embree's for frame 0: the median over builds and passes run one after the
    /// other.
    pub list_ratio: Option<f64>,
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
/// (built from `bench/embree` into `build_dir` if it is not there), on `threads` threads,
/// Embree's BVH built with the `quality` this tracer's was (its medium or high build quality).
///
/// Embree's modes are tried first; then a run of its fastest, a pass of this tracer and a call
/// of `list` (a build of the multiframe list: crossings traced and seconds, `None` if it
/// failed) alternate, five times, so that all three see the same moments of a shared, noisy
/// machine; each ratio is the median of the passes'.
pub fn compare(
    scene: &Scene,
    tracer: &SceneTracer,
    bundles: &[ParallelLines],
    build_dir: &Path,
    threads: usize,
    quality: BuildEffort,
    list: &dyn Fn() -> Option<(usize, f64)>,
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
        .and_then(|program| run(program, &file, threads, None, quality))
        .map(|fastest| fastest.mode);
    let mut embree = mode.as_ref().map(|_| Vec::new()).map_err(Clone::clone);
    let mut ours = Vec::with_capacity(REPEATS);
    let mut lists = Vec::with_capacity(REPEATS);
    for _ in 0..REPEATS {
        if let (Ok(program), Ok(mode)) = (&program, &mode) {
            let pass = run(program, &file, threads, Some(mode), quality);
            embree = embree.and_then(|mut runs| {
                runs.push(pass?);
                Ok(runs)
            });
        }
        ours.push(trace_once());
        lists.extend(list());
    }
    let _ = std::fs::remove_file(&file);
    finish(&ours, &lists, triangles.len(), embree)
}

/// The median of `values` (not empty).
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// The comparison from this tracer's passes (crossings, seconds), the list's builds (the same)
/// and Embree's, pass for pass, or why there are none.
fn finish(
    ours: &[(usize, f64)],
    lists: &[(usize, f64)],
    triangles: usize,
    embree: Result<Vec<EmbreeRun>, String>,
) -> NativeComparison {
    let seconds = median(ours.iter().map(|&(_, s)| s).collect());
    let crossings = ours[0].0;
    let rate = |&(n, s): &(usize, f64)| n as f64 / s;
    let list_crossings_per_second =
        (lists.len() == ours.len()).then(|| median(lists.iter().map(rate).collect()));
    // Rates over Embree's, pass for pass.
    let over = |passes: &[(usize, f64)], runs: &[EmbreeRun]| {
        median(
            (passes.iter().zip(runs))
                .map(|(pass, e)| rate(pass) / (e.mcps * 1e6))
                .collect(),
        )
    };
    let (embree, embree_missing, ratio, list_ratio) = match embree {
        Ok(runs) if runs.len() == ours.len() => {
            let ratio = over(ours, &runs);
            let list_ratio = (lists.len() == runs.len()).then(|| over(lists, &runs));
            let mut runs = runs;
            runs.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
            (
                Some(runs.swap_remove(ours.len() / 2)),
                None,
                Some(ratio),
                list_ratio,
            )
        }
        Ok(_) => (None, Some("Embree reported no pass".to_owned()), None, None),
        Err(why) => (None, Some(why), None, None),
    };
    NativeComparison {
        triangles,
        crossings,
        seconds,
        crossings_per_second: crossings as f64 / seconds,
        embree,
        embree_missing,
        ratio,
        list_crossings_per_second,
        list_ratio,
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
    quality: BuildEffort,
) -> Result<EmbreeRun, String> {
    let out = Command::new(program)
        .arg(file)
        .args(["--threads", &threads.to_string()])
        .args(["--quality", quality.name()])
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
            )?,
            (None, Some(why)) => writeln!(f, "native Embree    none: {why}")?,
            (None, None) => {}
        }
        if let Some(rate) = self.list_crossings_per_second {
            write!(
                f,
                "list vs Embree   {:.1} M crossings/s traced into the list (median of {REPEATS} builds between the passes above)",
                rate / 1e6
            )?;
            match self.list_ratio {
                Some(ratio) => writeln!(f, ": {ratio:.2}x Embree's rate for frame 0")?,
                None => writeln!(f)?,
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn embree(mcps: f64) -> EmbreeRun {
        EmbreeRun {
            mode: "occluded1".to_owned(),
            crossings: 1_000_000,
            seconds: 1.0 / mcps,
            mcps,
        }
    }

    #[test]
    fn the_ratios_pair_each_pass_with_the_embree_run_beside_it() {
        // Embree's rate moves with the machine; this tracer's passes keep at twice it and the
        // list's builds at half of it, pass for pass, but for one stalled pass and one fast
        // build: the medians of the pairs are 2 and 0.5, not the ratios of the medians (4/3 and
        // 2/3).
        let moments = [1.0, 4.0, 2.0, 8.0, 3.0];
        let runs: Vec<EmbreeRun> = moments.map(embree).to_vec();
        let mut ours: Vec<(usize, f64)> = moments.map(|m| (2_000_000, 1.0 / m)).to_vec();
        ours[3].1 = 2.0;
        let mut lists: Vec<(usize, f64)> = moments.map(|m| (500_000, 1.0 / m)).to_vec();
        lists[0].1 = 0.5 / 9.0;
        let c = finish(&ours, &lists, 12, Ok(runs.clone()));
        assert!((c.ratio.unwrap() - 2.0).abs() < 1e-12, "{c:?}");
        assert!((c.list_ratio.unwrap() - 0.5).abs() < 1e-12, "{c:?}");
        assert!(
            (c.list_crossings_per_second.unwrap() - 2e6).abs() < 1e-3,
            "{c:?}"
        );
        assert_eq!(c.embree.unwrap().mcps, 3.0, "the median run");

        // A list build that failed: no list figures, the frame's still.
        let c = finish(&ours, &lists[..4], 12, Ok(runs));
        assert!(c.ratio.is_some() && c.list_ratio.is_none());
        assert!(c.list_crossings_per_second.is_none());
        // No Embree: the list's own rate, no ratios.
        let c = finish(&ours, &lists, 12, Err("not installed".to_owned()));
        assert!(c.ratio.is_none() && c.list_ratio.is_none());
        assert!(c.list_crossings_per_second.is_some());
    }
}
