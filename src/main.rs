//! The command line: a thin layer over the library.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context as _;
use clap::{Parser, Subcommand};
use radiosity::loader::{self, LoadOptions};
use radiosity::params::{BakeRequest, BakeSettings, Limits};
use radiosity::timeline::LineParams;
use radiosity::trace::{BuildEffort, SceneTracer};

#[derive(Parser)]
#[command(version, about = "Radiosity baking for animated glTF scenes")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// What `radiosity scene` says a bake with its options would take.
#[derive(serde::Serialize)]
struct Plan {
    lines: u64,
    seed: u64,
    patch_size: radiosity::params::PatchSize,
    /// With `auto`, the most patches its cuts may reach.
    patch_budget: Option<usize>,
    sky: [f64; 3],
    /// The memory the service estimates before tracing (and refuses a job over its budget by).
    estimated_bytes: u64,
}

impl std::fmt::Display for Plan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "bake            {} lines (seed {}), patches {}",
            self.lines, self.seed, self.patch_size
        )?;
        if let Some(budget) = self.patch_budget {
            write!(f, " (at most {budget})")?;
        }
        let [r, g, b] = self.sky;
        write!(
            f,
            ", sky {r},{g},{b}: about {:.2} GiB before tracing",
            self.estimated_bytes as f64 / f64::from(1u32 << 30)
        )
    }
}

/// Prints `value` as pretty JSON if `json`, else `text`.
fn print_report(
    json: bool,
    value: &impl serde::Serialize,
    text: impl std::fmt::Display,
) -> anyhow::Result<()> {
    if json {
        println!("{}", serde_json::to_string_pretty(value)?);
    } else {
        print!("{text}");
    }
    Ok(())
}

/// The bake a command asks for, checked as the service checks it.
fn settings(request: BakeRequest) -> anyhow::Result<BakeSettings> {
    Ok(request.validate(&Limits::default())?)
}

#[derive(Subcommand)]
enum Command {
    /// Bake scenes (files, or every .glb/.gltf of a directory) into OUT/<scene>/: radiance.bin,
    /// summary.json, timings.json. Unchanged scenes are skipped; one failure does not stop the
    /// others; the exit status is non-zero if any failed.
    Bake(BakeArgs),
    /// Merge the parts of a scene's bake traced on several machines (`bake SCENE --shard K/N`)
    /// and bake on with what the parts were asked for: the outputs `bake` writes for the
    /// scene, byte for byte (timings.json aside); the outputs' options are merge's own.
    Merge(MergeArgs),
    /// Run the HTTP service (see api/ and the README).
    Serve(ServeArgs),
    /// Print a summary of a glTF scene: triangles, patches, static and moving objects, frames,
    /// emitters, warnings; and what a bake with the same options would take (lines, patches,
    /// estimated memory), checked as `bake` checks them.
    Scene(SceneArgs),
    /// Measure tracing on a scene: the multiframe intersection list against tracing every frame
    /// independently (throughput, bytes per crossing, time and memory ratios).
    Bench(BenchArgs),
    /// Measure the speed/accuracy trade on the sample scenes against physics: error against
    /// lines and seconds (bakes made as the bake command makes them: patches, pieces, every
    /// frame), error-bar coverage, and the multiframe gain at equal error.
    BenchAccuracy(BenchAccuracyArgs),
    /// Measure how patches are made against a path-traced reference: per-patch error, the
    /// error at points (what a lightmap shows), bias, error-bar coverage, patches and seconds
    /// of the source's triangles, uniform sizes and auto, on the Cornell box, the panel room,
    /// the level and the level lit by lamps (docs/engine.md, "Against physics").
    BenchPatches(BenchPatchesArgs),
    /// Measure the light the baked glTF shows at its vertices against a path tracer evaluated
    /// at the same points, beside the per-vertex averaging of patches outputs carried before:
    /// error (RMS, on creases, median, 90th percentile), bias, error-bar coverage, the light
    /// left where none arrives, and what evaluating every frame's vertices costs.
    BenchVertices(BenchVerticesArgs),
    /// Write the sample scenes (deterministic) into a directory.
    Samples(SamplesArgs),
}

/// The options of `radiosity bake`.
#[derive(clap::Args)]
struct BakeArgs {
    /// Scenes or directories of scenes.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Bake only part K of N (K from 0): with one scene file, trace only its lines' part K
    /// (bundles b with b mod N = K) into OUT/<scene>/shard-K-of-N.part, for `radiosity merge`;
    /// with directories or several files, bake only the scenes i (in sorted order, from 0)
    /// with i mod N = K.
    #[arg(long, value_name = "K/N", value_parser = parse_shard)]
    shard: Option<radiosity::timeline::Shard>,
    #[command(flatten)]
    baking: BakingArgs,
}

/// The options of `radiosity merge`.
#[derive(clap::Args)]
struct MergeArgs {
    /// The parts of one scene's bake (`bake SCENE --shard K/N`), every K from 0 to N - 1
    /// once, in any order: they carry what the bake was asked for (lines, seed, frames,
    /// patches...).
    #[arg(required = true)]
    parts: Vec<PathBuf>,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
    /// Merge even if the outputs are up to date.
    #[arg(long)]
    force: bool,
    #[command(flatten)]
    outputs: OutputArgs,
}

/// What `bake` bakes with and writes.
#[derive(clap::Args)]
struct BakingArgs {
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    request: BakeRequest,
    /// Bake even scenes whose outputs are up to date.
    #[arg(long)]
    force: bool,
    #[command(flatten)]
    outputs: OutputArgs,
}

/// The outputs `bake` and `merge` write besides `radiance.bin` and `summary.json`.
#[derive(clap::Args)]
struct OutputArgs {
    /// Frames written as baked glTF (baked/frame_NNNN.glb): all, none, or a list such as
    /// 0,10-20,middle,last.
    #[arg(long, default_value = "all")]
    glb_frames: radiosity::output::FrameSpec,
    /// Frames rendered as PNG previews (preview/frame_NNNN.png), same syntax.
    #[arg(long, default_value = "first,middle,last")]
    preview_frames: radiosity::output::FrameSpec,
    /// Size of the PNG previews, WIDTHxHEIGHT (the GIF is half that).
    #[arg(long, default_value = "640x480", value_parser = parse_size)]
    preview_size: (u32, u32),
    /// Do not write preview.gif.
    #[arg(long)]
    no_gif: bool,
    /// Also write lightmaps (lightmaps/: the geometry with its lightmap coordinates, one
    /// linear half-float EXR per lighting state, manifest.json)
    #[arg(long)]
    lightmaps: bool,
    /// The lightmaps' texel density, texels per scene unit (with --lightmaps)
    #[arg(long, default_value_t = radiosity::output::lightmap::TEXELS_PER_UNIT, requires = "lightmaps")]
    texels_per_unit: f64,
    /// What the lightmaps hold: radiance (what the surface shows, albedo and emission
    /// included) or light (the irradiance over π, which an engine's material multiplies by
    /// its albedo: Unity's, Godot's and three.js's lightmaps) (with --lightmaps)
    #[arg(long, value_enum, default_value_t, requires = "lightmaps")]
    lightmap_quantity: radiosity::output::lightmap::Quantity,
    /// Also write light probes (probes/: a grid of order-2 spherical-harmonic probes of the
    /// light arriving in the scene's empty space, one file per lighting state, probes.json)
    #[arg(long)]
    probes: bool,
    /// The probes' spacing in scene units (with --probes; by default one unit, or wider to
    /// keep at least 4 cells along the longest side and at most 4096 probes)
    #[arg(long, requires = "probes", allow_negative_numbers = true)]
    probe_spacing: Option<f64>,
    /// Exposure of the previews and of the baked glTF's vertex colours (radiance is
    /// multiplied by it before the tone curve); by default the one that maps the lit
    /// surfaces' log-average to middle grey (summary.json records it).
    #[arg(long, value_parser = parse_exposure, allow_negative_numbers = true)]
    exposure: Option<f64>,
    /// How previews shade the patches: smooth (the baked glTF's per-vertex radiance, what
    /// an engine shows) or flat (one colour per patch, to inspect them).
    #[arg(long, default_value = "smooth")]
    preview_shading: radiosity::output::Shading,
}

/// The options of `radiosity serve`.
#[derive(clap::Args)]
struct ServeArgs {
    /// Address to bind.
    #[arg(long, default_value = "127.0.0.1:8080")]
    addr: String,
    /// Jobs traced or solved at once; the others wait `queued`.
    #[arg(long, default_value_t = 1)]
    max_running: usize,
    /// Largest accepted scene, MiB (1 to 1,048,576).
    #[arg(long, default_value_t = 64, value_parser = parse_body_mib)]
    max_body_mib: usize,
    /// Memory budget of one job, GiB (estimated before tracing; above 0).
    #[arg(long, default_value_t = 8.0, value_parser = parse_budget_gib)]
    memory_budget_gib: f64,
    /// Where finished results are kept across restarts.
    #[arg(long, default_value = "./data")]
    data_dir: PathBuf,
    /// Traced state (lines, tallies, direct light) and solved frames all timelines may keep in
    /// memory, GiB; over it, finished timelines' are dropped, least recently used first: frames
    /// are then read from the data directory, and the traced state read back (or traced again
    /// from the stored scene) when needed. Default: half the machine's memory.
    #[arg(long, value_parser = parse_budget_gib)]
    resident_gib: Option<f64>,
    /// Removes finished timelines (memory and data directory) this many days after they
    /// ended (fractions allowed). Default: kept until deleted.
    #[arg(long, value_parser = parse_days)]
    retain_days: Option<f64>,
    /// Keeps only this many finished timelines, the most recently ended; older ones are
    /// removed (memory and data directory). Default: all.
    #[arg(long)]
    retain_count: Option<usize>,
    /// Does not write timelines' traced state to the data directory (traced.bin, about two
    /// thirds of its bytes in memory: 94 MB for the sample level at the default preset):
    /// a timeline dropped from memory or restored after a restart is then traced again from
    /// its stored scene when needed, which takes the trace's time.
    #[arg(long)]
    no_traced_files: bool,
}

/// A number of days above 0 (at most a million).
fn parse_days(s: &str) -> Result<f64, String> {
    s.trim()
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite() && *v > 0.0 && *v <= 1e6)
        .ok_or_else(|| format!("{s:?} is not a number of days above 0 and at most 1,000,000"))
}

/// Half the machine's memory (Linux's `/proc/meminfo`), if known.
fn half_the_memory() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024 / 2)
}

/// The options of `radiosity scene`.
#[derive(clap::Args)]
struct SceneArgs {
    /// A .glb, or a .gltf with embedded (data:) buffers.
    file: PathBuf,
    #[command(flatten)]
    request: BakeRequest,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

/// The options of `radiosity bench`.
#[derive(clap::Args)]
struct BenchArgs {
    /// A .glb, or a .gltf with embedded (data:) buffers.
    file: PathBuf,
    #[command(flatten)]
    request: BakeRequest,
    /// Also trace frame 0 alone with this tracer and with native Embree (Debian's
    /// libembree-dev; bench/embree/trace.c is built into target/embree), on the same lines,
    /// and print the ratio.
    #[arg(long)]
    embree: bool,
    /// The BVHs' build effort; by default the one a bake of as many lines would choose
    /// (high from 130 lines per static or rigid triangle).
    #[arg(long, value_enum)]
    bvh: Option<BuildEffort>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

/// The options of `radiosity bench-accuracy`.
#[derive(clap::Args)]
struct BenchAccuracyArgs {
    /// Directory of the sample scenes.
    #[arg(long, default_value = "scenes")]
    scenes: PathBuf,
    /// Line budgets to sweep, comma-separated.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "30000,100000,300000,1000000"
    )]
    budgets: Vec<u64>,
    /// How patches are made: source (the default), auto, or a length.
    #[arg(long, default_value = "source")]
    patch_size: radiosity::params::PatchSize,
    /// Paths of the path-traced reference per measured frame, over all of a bake's patches
    /// (at least 64 per patch), for the scenes without a closed form.
    #[arg(long, default_value_t = 4_000_000)]
    reference_paths: usize,
    /// Frames measured against the path tracer, spread over the timeline from frame 0 (four:
    /// at 25 frames, 0, 6, 12 and 18, three of them frames that carry their run's first
    /// frame's error-bar terms).
    #[arg(long, default_value_t = 4)]
    reference_frames: usize,
    /// Measure only this scene (a file name in --scenes).
    #[arg(long)]
    only: Option<String>,
    /// Frames per second for the animated scenes.
    #[arg(long, default_value_t = 12.0)]
    fps: f64,
    /// Lines for the multiframe gain measurement (0: not measured; nor with --only).
    #[arg(long, default_value_t = 100_000)]
    gain_lines: u64,
    /// Scene of the multiframe gain measurement (60 frames over its 2 s animation).
    #[arg(long, default_value = "level.gltf")]
    gain_scene: String,
}

/// The options of `radiosity bench-patches`.
#[derive(clap::Args)]
struct BenchPatchesArgs {
    /// Directory of the sample scenes.
    #[arg(long, default_value = "scenes")]
    scenes: PathBuf,
    /// Lines of every bake.
    #[arg(long, default_value_t = 1_000_000)]
    lines: u64,
    /// Paths of each bake's reference, over all its patches (at least 64 per patch).
    #[arg(long, default_value_t = 8_000_000)]
    reference_paths: usize,
    /// Where to write the points as JSON.
    #[arg(long, default_value = "docs/patches.json")]
    out: PathBuf,
    /// Only this scene (file name).
    #[arg(long)]
    only: Option<String>,
    /// Only these ways of making patches (auto, source, lengths), comma-separated.
    #[arg(long, value_delimiter = ',')]
    sizes: Vec<radiosity::params::PatchSize>,
    /// With auto: the patch budget (default: one per 200 lines).
    #[arg(long)]
    patch_budget: Option<usize>,
    /// Seed of the bakes' lines (the reference's paths take another from it): repeat
    /// with other seeds to see how much the figures themselves vary.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Solve the patches whole rather than on their pieces (as bakes did before pieces):
    /// to see what the pieces change.
    #[arg(long)]
    whole: bool,
}

/// The options of `radiosity bench-vertices`.
#[derive(clap::Args)]
struct BenchVerticesArgs {
    /// Directory of the sample scenes.
    #[arg(long, default_value = "scenes")]
    scenes: PathBuf,
    /// Only these scenes (file names in --scenes), comma-separated; by default the level, the
    /// moving Cornell box, the lamp room and the panel room.
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Lines of every bake (the `default` preset's by default).
    #[arg(long, default_value_t = 1_000_000)]
    lines: u64,
    /// Seed of the bakes' lines (the reference's paths take others from it).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Frames per second for the animated scenes.
    #[arg(long, default_value_t = 12.0)]
    fps: f64,
    /// Frames measured, spread over the timeline from frame 0.
    #[arg(long, default_value_t = 1)]
    frames: usize,
    /// Paths of the reference per vertex, in each of its two halves.
    #[arg(long, default_value_t = 8192)]
    paths: usize,
    /// Also measure lightmaps at this many texels per scene unit (their texels against the
    /// reference at the texels' points).
    #[arg(long)]
    texels_per_unit: Option<f64>,
    /// Most texels measured per scene (evenly spread over the covered ones).
    #[arg(long, default_value_t = 4000, requires = "texels_per_unit")]
    texel_limit: usize,
    /// Paths of the reference per texel, in each of its two halves.
    #[arg(long, default_value_t = 2048, requires = "texels_per_unit")]
    texel_paths: usize,
    /// How the bakes' patches are made: source (the default), auto or a length.
    #[arg(long, default_value = "source")]
    patch_size: radiosity::params::PatchSize,
}

/// The options of `radiosity samples`.
#[derive(clap::Args)]
struct SamplesArgs {
    /// Output directory.
    #[arg(long, default_value = "scenes")]
    out: PathBuf,
}

/// Runs `work` (one scene's part or merge) with Ctrl-C cancelling it and its stages shown;
/// fails with its reason.
fn run_one(
    out: &std::path::Path,
    work: impl FnOnce(&radiosity::control::Control, &mut dyn FnMut(&str)) -> radiosity::batch::Outcome,
) -> anyhow::Result<()> {
    use radiosity::batch::Outcome;
    let control = std::sync::Arc::new(radiosity::control::Control::default());
    let handler = control.clone();
    ctrlc::set_handler(move || handler.cancel()).context("the Ctrl-C handler")?;
    let progress = radiosity::progress::Progress::new(control.clone());
    let outcome = work(&control, &mut |line| progress.stage("", line));
    progress.finish();
    match outcome {
        Outcome::Baked(path) => eprintln!("wrote {}", path.display()),
        Outcome::Skipped(path) => eprintln!("up to date: {}", path.display()),
        Outcome::Failed(reason) => anyhow::bail!("{reason}"),
        Outcome::Cancelled => anyhow::bail!("interrupted: nothing written in {}", out.display()),
    }
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::try_parse().unwrap_or_else(|e| with_suggestion(e).exit());
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

/// `error` with the option most like an unknown one suggested where clap suggests none (where a
/// subcommand's trailing inputs could take the unknown word, or a swap of two letters in a
/// short one: `bake --fsp 5`).
fn with_suggestion(mut error: clap::Error) -> clap::Error {
    use clap::CommandFactory;
    use clap::error::{ContextKind, ContextValue, ErrorKind};
    if error.kind() != ErrorKind::UnknownArgument || error.get(ContextKind::SuggestedArg).is_some()
    {
        return error;
    }
    let Some(ContextValue::String(unknown)) = error.get(ContextKind::InvalidArg).cloned() else {
        return error;
    };
    let Some(word) = unknown.strip_prefix("--") else {
        return error;
    };
    let word = word.split('=').next().unwrap_or(word);
    // The options of the subcommand named on the command line (the first argument that is one).
    let cli = Cli::command();
    let used = std::env::args()
        .skip(1)
        .find_map(|a| cli.find_subcommand(&a).cloned());
    let Some(command) = used else {
        return error;
    };
    // The fewest edits (a swap of neighbours counts one, which clap's Jaro measure misses in
    // short words: `--fsp`), at most one per three letters.
    let best = (command.get_arguments())
        .filter_map(|a| a.get_long())
        .map(|long| (strsim::osa_distance(word, long), long))
        .min();
    if let Some((edits, long)) = best
        && edits <= (word.chars().count() / 3).max(1)
    {
        error.insert(
            ContextKind::SuggestedArg,
            ContextValue::String(format!("--{long}")),
        );
    }
    error
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Bake(args) => args.run(),
        Command::Merge(args) => args.run(),
        Command::Serve(args) => args.run(),
        Command::Scene(args) => args.run(),
        Command::Bench(args) => args.run(),
        Command::BenchAccuracy(args) => args.run(),
        Command::BenchPatches(args) => args.run(),
        Command::BenchVertices(args) => args.run(),
        Command::Samples(args) => args.run(),
    }
}

impl BakeArgs {
    fn run(self) -> anyhow::Result<()> {
        let Self {
            inputs,
            shard,
            baking,
        } = self;
        let (out, params) = baking.params()?;
        match shard {
            Some(shard) if inputs.len() == 1 && inputs[0].is_file() => {
                run_one(&out, |control, log| {
                    radiosity::batch::shard::trace_part(
                        &inputs[0], &out, shard, &params, control, log,
                    )
                })
            }
            _ => bake(&inputs, shard, &out, &params),
        }
    }
}

impl MergeArgs {
    fn run(self) -> anyhow::Result<()> {
        let Self {
            parts,
            out,
            force,
            outputs,
        } = self;
        let outputs = outputs.outputs();
        run_one(&out, |control, log| {
            radiosity::batch::shard::merge(&parts, &out, (&outputs, force), control, log)
        })
    }
}

impl BakingArgs {
    /// The output directory and the parameters.
    fn params(self) -> anyhow::Result<(PathBuf, radiosity::batch::BatchParams)> {
        let Self {
            out,
            request,
            force,
            outputs,
        } = self;
        let params = radiosity::batch::BatchParams {
            settings: settings(request)?,
            outputs: outputs.outputs(),
            force,
            max_iterations: radiosity::solve::SolveParams::default().max_iterations,
        };
        Ok((out, params))
    }
}

impl OutputArgs {
    fn outputs(self) -> radiosity::batch::Outputs {
        let Self {
            glb_frames,
            preview_frames,
            preview_size,
            no_gif,
            exposure,
            preview_shading,
            lightmaps,
            texels_per_unit,
            lightmap_quantity,
            probes,
            probe_spacing,
        } = self;
        radiosity::batch::Outputs {
            glb_frames,
            preview_frames,
            preview_size,
            gif: !no_gif,
            exposure,
            shading: preview_shading,
            lightmaps: lightmaps.then_some(texels_per_unit),
            lightmap_quantity,
            probes: probes.then_some(probe_spacing),
        }
    }
}

impl ServeArgs {
    fn run(self) -> anyhow::Result<()> {
        let Self {
            addr,
            max_running,
            max_body_mib,
            memory_budget_gib,
            data_dir,
            resident_gib,
            retain_days,
            retain_count,
            no_traced_files,
        } = self;
        let gib = |g: f64| (g * f64::from(1u32 << 30)) as u64;
        let resident_budget = resident_gib.map(gib).or_else(half_the_memory);
        let config = radiosity::service::Config {
            data_dir: Some(data_dir),
            max_running,
            max_body_bytes: max_body_mib << 20,
            memory_budget: gib(memory_budget_gib),
            resident_budget,
            traced_files: !no_traced_files,
            retention: radiosity::service::Retention {
                days: retain_days,
                count: retain_count,
            },
            ..radiosity::service::Config::default()
        };
        serve(&addr, config)
    }
}

impl SceneArgs {
    fn run(self) -> anyhow::Result<()> {
        let Self {
            file,
            request,
            json,
        } = self;
        let settings = settings(request)?;
        let scene = loader::load_file(&file, &settings.load)?;
        let auto = settings.adaptive(scene.patches.len());
        let plan = Plan {
            lines: settings.lines.lines,
            seed: settings.lines.seed,
            patch_size: settings.patch_size,
            patch_budget: auto.map(|a| a.budget),
            sky: settings.sky,
            estimated_bytes: radiosity::bake::estimate_bytes(
                &scene,
                settings.lines.lines,
                auto.map(|a| a.budget),
            ),
        };
        let summary = scene.summary();
        let report = serde_json::json!({"scene": summary, "bake": plan});
        print_report(json, &report, format_args!("{summary}{plan}\n"))
    }
}

impl BenchArgs {
    fn run(self) -> anyhow::Result<()> {
        let Self {
            file,
            request,
            embree,
            bvh,
            json,
        } = self;
        let settings = settings(request)?;
        let scene = loader::load_file(&file, &settings.load)?;
        let LineParams { lines, seed } = settings.lines;
        let native = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/embree");
        let effort = bvh.unwrap_or_else(|| SceneTracer::effort_for(&scene, lines));
        let native = embree.then_some(&*native);
        let report = radiosity::bench::trace(&scene, lines, seed, native, effort)?;
        print_report(json, &report, &report)
    }
}

impl BenchAccuracyArgs {
    fn run(self) -> anyhow::Result<()> {
        let Self {
            scenes,
            budgets,
            patch_size,
            reference_paths,
            reference_frames,
            only,
            fps,
            gain_lines,
            gain_scene,
        } = self;
        let load_scene = |name: &str, options: LoadOptions| {
            radiosity::bench::load_sample(&scenes, name, &options)
        };
        let mut set = Vec::new();
        for name in radiosity::bench::ACCURACY_SCENES {
            if only.as_ref().is_some_and(|o| o != name) {
                continue;
            }
            let options = LoadOptions {
                fps,
                patch_size: patch_size.length(),
                ..LoadOptions::default()
            };
            set.push((name.to_string(), load_scene(name, options)?));
        }
        if set.is_empty() {
            anyhow::bail!("--only: no sample scene is named {only:?}");
        }
        let reference = radiosity::bench::PathReference {
            paths: reference_paths,
            frames: reference_frames,
        };
        let points = radiosity::bench::accuracy(&set, &budgets, patch_size, reference, |p| {
            let show = |x: Option<f64>, digits: usize| {
                x.map_or_else(|| "-".to_string(), |x| format!("{x:.digits$}"))
            };
            let e = &p.error;
            eprintln!(
                "{:<22} {:>9} lines {:>6} patches {:>8.3} s  per-patch {}  at points {} (resolved to {})  coverage {}  median |z| {}  estimated {}  emitters {}",
                p.scene,
                p.lines,
                p.patches,
                p.seconds,
                show(e.lit_error, 4),
                show(e.point_error, 4),
                show(e.point_resolution, 4),
                show(e.coverage, 3),
                show(e.median_z, 2),
                show(e.estimated_noise, 4),
                show(e.emitter_error, 4)
            );
        })?;
        // 60 frames: the samples' animations last 2 s. Not with --only or --gain-lines 0.
        let moving = LoadOptions {
            fps: 29.5,
            ..LoadOptions::default()
        };
        let gain = if only.is_some() || gain_lines == 0 {
            None
        } else {
            let scene = load_scene(&gain_scene, moving.clone())?;
            radiosity::bench::multiframe_gain(&scene, gain_lines, |t| {
                load_scene(
                    &gain_scene,
                    LoadOptions {
                        start: Some(t),
                        end: Some(t),
                        ..moving.clone()
                    },
                )
                .ok()
            })?
        };
        let report = serde_json::json!({ "points": points, "multiframe_gain": gain });
        println!("{}", serde_json::to_string_pretty(&report)?);
        Ok(())
    }
}

impl BenchVerticesArgs {
    fn run(self) -> anyhow::Result<()> {
        use radiosity::bench::vertices::{VERTEX_SCENES, VertexBench, vertex_points};
        let names: Vec<String> = if self.only.is_empty() {
            VERTEX_SCENES.iter().map(|s| (*s).to_string()).collect()
        } else {
            self.only.clone()
        };
        let options = LoadOptions {
            fps: self.fps,
            patch_size: self.patch_size.length(),
            ..LoadOptions::default()
        };
        let scenes = (names.iter())
            .map(|name| {
                radiosity::bench::load_sample(&self.scenes, name, &options)
                    .map(|scene| (name.clone(), scene))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let bench = VertexBench {
            lines: self.lines,
            seed: self.seed,
            frames: self.frames,
            paths: self.paths,
            auto: self.patch_size == radiosity::params::PatchSize::Auto,
            texels_per_unit: self.texels_per_unit,
            texel_limit: self.texel_limit,
            texel_paths: self.texel_paths,
        };
        let points = vertex_points(&scenes, bench, |p| {
            let show = |x: Option<f64>| {
                x.map_or_else(|| "-".to_string(), |x| format!("{:.2}%", 100.0 * x))
            };
            // One line of a measure; on creases where vertices have them.
            let line = |what: &str, m: &radiosity::bench::vertices::VertexMeasured, creases| {
                let creases = if creases {
                    format!(
                        "  creases {} ({} too bright)",
                        show(m.crease_rms),
                        show(m.crease_too_bright)
                    )
                } else {
                    String::new()
                };
                eprintln!(
                    "{:<20} {what}  RMS {}{creases}  median {}  p90 {}  bias {}  within 2σ {}  dark max {}  reference noise {}",
                    p.scene,
                    show(m.rms),
                    show(m.median),
                    show(m.p90),
                    show(m.bias),
                    show(m.coverage),
                    show(m.dark_max),
                    show(m.reference_noise),
                );
            };
            line("at vertices", &p.evaluated, true);
            line("averaged  ", &p.averaged, true);
            eprintln!(
                "{:<20} {} vertices, bake {:.2} s, every frame's vertices {:.2} s ({:.0}%)",
                p.scene,
                p.vertices,
                p.bake_seconds,
                p.vertex_seconds,
                100.0 * p.vertex_seconds / p.bake_seconds
            );
            if let Some(t) = &p.texels {
                line("at texels  ", &t.evaluated, false);
                line("patches    ", &t.patches, false);
                eprintln!(
                    "{:<20} {} of {} texels at {} per unit, every state's texels {:.2} s ({:.0}% of the bake)",
                    p.scene,
                    t.measured,
                    t.covered,
                    t.texels_per_unit,
                    t.texel_seconds,
                    100.0 * t.texel_seconds / p.bake_seconds
                );
            }
        })
        .map_err(anyhow::Error::msg)?;
        println!("{}", serde_json::to_string_pretty(&points)?);
        Ok(())
    }
}

impl BenchPatchesArgs {
    fn run(self) -> anyhow::Result<()> {
        let Self {
            scenes,
            lines,
            reference_paths,
            out,
            only,
            sizes: chosen,
            patch_budget,
            seed,
            whole,
        } = self;
        println!(
            "scene\tpatch_size\tpatches\tseconds\tpatch error\tpatch L2\tpoint error\t\
             resolved to\treference noise\tbias\testimated noise\tcoverage"
        );
        let bench = radiosity::bench::PatchBench {
            lines: (lines, seed),
            reference_paths,
            only,
            sizes: chosen,
            patch_budget,
            whole,
        };
        let points = radiosity::bench::patch_points(&scenes, &bench, |p| {
            println!(
                "{}\t{}\t{}\t{:.2}\t{:.4}\t{:.4}\t{:.4}\t{:.4}\t{:.4}\t{:+.4}\t{:.4}\t{:.3}",
                p.scene,
                p.patch_size,
                p.patches,
                p.seconds,
                p.patch_error,
                p.patch_l2_error,
                p.point_error,
                p.point_resolution,
                p.reference_noise,
                p.bias,
                p.estimated_noise,
                p.coverage
            );
            for w in &p.worst {
                println!(
                    "  patch {} {} area {:.4}: {:.0}% of the error, {:.4} ± {:.4} against {:.4}",
                    w.patch,
                    w.material,
                    w.area,
                    100.0 * w.share,
                    w.baked,
                    w.sigma,
                    w.reference
                );
            }
        })
        .map_err(anyhow::Error::msg)?;
        let json = serde_json::to_string_pretty(&points)?;
        std::fs::write(&out, json + "\n").with_context(|| out.display().to_string())?;
        Ok(())
    }
}

impl SamplesArgs {
    fn run(self) -> anyhow::Result<()> {
        let Self { out } = self;
        std::fs::create_dir_all(&out).with_context(|| out.display().to_string())?;
        for sample in radiosity::samples::all() {
            let path = out.join(sample.file_name);
            std::fs::write(&path, sample.gltf).with_context(|| path.display().to_string())?;
            println!("{}", path.display());
        }
        Ok(())
    }
}

/// Runs the service until ctrl-c or SIGTERM.
fn serve(addr: &str, config: radiosity::service::Config) -> anyhow::Result<()> {
    // Colours for a terminal only: a log written to a file or a pipe stays plain text.
    tracing_subscriber::fmt()
        .with_target(false)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stdout()))
        .init();
    let runtime = tokio::runtime::Runtime::new()?;
    runtime.block_on(async {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .with_context(|| addr.to_string())?;
        tracing::info!("listening on {}", listener.local_addr()?);
        let state = radiosity::service::AppState::new(config).context("the data directory")?;
        radiosity::service::serve(listener, state, shutdown_signal()).await?;
        Ok(())
    })
}

/// Completes on ctrl-c or SIGTERM.
async fn shutdown_signal() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    tokio::select! {
        () = ctrl_c => {},
        () = terminate => {},
    }
    tracing::info!("shutting down");
}

/// `WIDTHxHEIGHT`, each side from 1 to [`radiosity::output::preview::MAX_PREVIEW_SIDE`].
/// An exposure: a finite number above 0.
fn parse_exposure(s: &str) -> Result<f64, String> {
    (s.trim().parse::<f64>().ok())
        .filter(|e| e.is_finite() && *e > 0.0)
        .ok_or_else(|| format!("{s:?} is not an exposure (a finite number above 0)"))
}

/// A part `K/N` of a bake: N from 1 to 65,536, K from 0 to N - 1.
fn parse_shard(s: &str) -> Result<radiosity::timeline::Shard, String> {
    let wrong = || format!("{s:?} is not K/N (part K of N, K from 0 to N - 1, such as 0/4)");
    let (k, n) = s.split_once('/').ok_or_else(wrong)?;
    let (index, count): (u32, u32) = (
        k.trim().parse().map_err(|_| wrong())?,
        n.trim().parse().map_err(|_| wrong())?,
    );
    if count == 0 || count > 65_536 || index >= count {
        return Err(wrong());
    }
    Ok(radiosity::timeline::Shard { index, count })
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let max = radiosity::output::preview::MAX_PREVIEW_SIDE;
    let side = |t: &str| {
        t.trim()
            .parse::<u32>()
            .ok()
            .filter(|v| (1..=max).contains(v))
            .ok_or_else(|| format!("{t:?} is not a side from 1 to {max} pixels"))
    };
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("{s:?} is not WIDTHxHEIGHT"))?;
    Ok((side(w)?, side(h)?))
}

/// Largest `--max-body-mib`: 1 TiB (a larger value would overflow the byte count on 32-bit
/// targets, and no scene is that large).
const MAX_BODY_MIB: usize = 1 << 20;

/// `--max-body-mib`: whole MiB from 1 to [`MAX_BODY_MIB`].
fn parse_body_mib(s: &str) -> Result<usize, String> {
    s.trim()
        .parse::<usize>()
        .ok()
        .filter(|v| (1..=MAX_BODY_MIB).contains(v))
        .ok_or_else(|| format!("{s:?} is not a whole number of MiB from 1 to {MAX_BODY_MIB}"))
}

/// `--memory-budget-gib`: a finite number of GiB above 0, at most 2^30 (an exabyte).
fn parse_budget_gib(s: &str) -> Result<f64, String> {
    s.trim()
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite() && *v > 0.0 && *v <= f64::from(1u32 << 30))
        .ok_or_else(|| format!("{s:?} is not a number of GiB above 0 and at most 2^30"))
}

/// Bakes every scene, logging progress (a bar on a terminal), and fails if any scene failed or
/// was cancelled; Ctrl-C cancels.
fn bake(
    inputs: &[PathBuf],
    shard: Option<radiosity::timeline::Shard>,
    out: &std::path::Path,
    params: &radiosity::batch::BatchParams,
) -> anyhow::Result<()> {
    let mut scenes = radiosity::batch::scenes(inputs).context("listing the inputs")?;
    if scenes.is_empty() {
        anyhow::bail!("no .glb or .gltf scene in the inputs");
    }
    if let Some(shard) = shard {
        let all = scenes.len();
        scenes = (scenes.into_iter().enumerate())
            .filter(|&(i, _)| shard.owns(i as u32))
            .map(|(_, s)| s)
            .collect();
        eprintln!(
            "part {}/{}: {} of the {all} scenes",
            shard.index,
            shard.count,
            scenes.len()
        );
        if scenes.is_empty() {
            return Ok(());
        }
    }
    let control = std::sync::Arc::new(radiosity::control::Control::default());
    let handler = control.clone();
    ctrlc::set_handler(move || handler.cancel()).context("the Ctrl-C handler")?;
    let progress = radiosity::progress::Progress::new(control.clone());
    let failures = radiosity::batch::bake_all(&scenes, out, params, &control, &progress);
    progress.finish();
    anyhow::ensure!(
        failures.is_empty(),
        "{} of {} scenes failed:\n  {}",
        failures.len(),
        scenes.len(),
        failures.join("\n  ")
    );
    Ok(())
}
