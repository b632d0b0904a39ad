//! The command line: a thin layer over the library.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use radiosity::loader::{self, LoadOptions};

#[derive(Parser)]
#[command(version, about = "Radiosity baking for animated glTF scenes")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// Options that choose what is loaded from a scene, with the names the HTTP API uses.
#[derive(clap::Args)]
struct SceneArgs {
    /// Frames per second of the timeline.
    #[arg(long, default_value_t = 24.0)]
    fps: f64,
    /// Play only this animation (name or index); all play together by default.
    #[arg(long)]
    animation: Option<String>,
    /// Time of the first frame (seconds); defaults to the first keyframe.
    #[arg(long)]
    start: Option<f64>,
    /// Time of the last frame (seconds); defaults to the last keyframe.
    #[arg(long)]
    end: Option<f64>,
    /// Subdivide triangles until every edge is at most this long (scene units).
    #[arg(long)]
    patch_size: Option<f64>,
}

impl From<SceneArgs> for LoadOptions {
    fn from(a: SceneArgs) -> Self {
        Self {
            fps: a.fps,
            animation: a.animation,
            start: a.start,
            end: a.end,
            patch_size: a.patch_size,
            ..Self::default()
        }
    }
}

#[derive(Subcommand)]
enum Command {
    /// Print a summary of a glTF scene: triangles, patches, static and moving objects, frames,
    /// emitters, warnings.
    Scene {
        /// A .glb, or a .gltf with embedded (data:) buffers.
        file: PathBuf,
        #[command(flatten)]
        args: SceneArgs,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Measure tracing on a scene: the multiframe intersection list against tracing every frame
    /// independently (throughput, bytes per crossing, time and memory ratios).
    Bench {
        /// A .glb, or a .gltf with embedded (data:) buffers.
        file: PathBuf,
        #[command(flatten)]
        args: SceneArgs,
        /// Number of lines.
        #[arg(long, default_value_t = 1_000_000)]
        lines: u64,
        /// Seed of the lines.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Write the sample scenes (deterministic) into a directory.
    Samples {
        /// Output directory.
        #[arg(long, default_value = "scenes")]
        out: PathBuf,
    },
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<(), String> {
    match cli.command {
        Command::Scene { file, args, json } => {
            let bytes = std::fs::read(&file).map_err(|e| format!("{}: {e}", file.display()))?;
            let scene = loader::load(&bytes, &args.into())
                .map_err(|e| format!("{}: {e}", file.display()))?;
            let summary = scene.summary();
            if json {
                let text = serde_json::to_string_pretty(&summary).map_err(|e| e.to_string())?;
                println!("{text}");
            } else {
                print!("{summary}");
            }
            Ok(())
        }
        Command::Bench {
            file,
            args,
            lines,
            seed,
            json,
        } => {
            let bytes = std::fs::read(&file).map_err(|e| format!("{}: {e}", file.display()))?;
            let scene = loader::load(&bytes, &args.into())
                .map_err(|e| format!("{}: {e}", file.display()))?;
            let report = radiosity::bench::trace(&scene, lines, seed).map_err(|e| e.to_string())?;
            if json {
                let text = serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?;
                println!("{text}");
            } else {
                print!("{report}");
            }
            Ok(())
        }
        Command::Samples { out } => {
            std::fs::create_dir_all(&out).map_err(|e| format!("{}: {e}", out.display()))?;
            for sample in radiosity::samples::all() {
                let path = out.join(sample.file_name);
                std::fs::write(&path, sample.gltf)
                    .map_err(|e| format!("{}: {e}", path.display()))?;
                println!("{}", path.display());
            }
            Ok(())
        }
    }
}
