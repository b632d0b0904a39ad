//! What the direct light costs: for each scene, the seconds of the tracer's BVHs, of the
//! punctual lights, of the emitters sampled as area lights (the static part and every pose of
//! the moving geometry) and of the global lines, with how many pairs (patch, emitter) the
//! static part holds and how many the poses trace again.
//!
//!     cargo run --release --example direct [FPS] [PATCH_SIZE or -] [LINES] [SCENE...]

use std::time::Instant;

use radiosity::control::Control;
use radiosity::direct::DirectLight;
use radiosity::direct::area::{AreaLights, Sampling};
use radiosity::loader::{LoadOptions, load};
use radiosity::timeline::{IntersectionList, LineParams};
use radiosity::trace::SceneTracer;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let fps: f64 = args.next().map_or(Ok(12.0), |a| a.parse())?;
    let patch_size: Option<f64> = args
        .next()
        .filter(|a| a != "-")
        .map(|a| a.parse())
        .transpose()?;
    let lines: u64 = args.next().map_or(Ok(1_000_000), |a| a.parse())?;
    let mut scenes: Vec<String> = args.collect();
    if scenes.is_empty() {
        scenes = ["level", "level_lamps", "cornell_moving"]
            .map(|s| format!("scenes/{s}.gltf"))
            .to_vec();
    }
    println!("scene\tpatches\tframes\tbvh s\tpunctual s\tarea s\tpairs\tretraced\tlines s");
    for name in scenes {
        let options = LoadOptions {
            fps,
            patch_size: patch_size.or(LoadOptions::default().patch_size),
            ..LoadOptions::default()
        };
        let scene = load(&std::fs::read(&name)?, &options)?;
        let control = Control::default();
        let t = Instant::now();
        let tracer = SceneTracer::new(&scene);
        let bvh = t.elapsed().as_secs_f64();
        let t = Instant::now();
        DirectLight::compute(&scene, &tracer, &control)?;
        let punctual = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let area = AreaLights::compute(
            &scene,
            &tracer,
            Sampling::for_lines(lines, scene.patches.len(), 1),
            &control,
        )?;
        let area_time = t.elapsed().as_secs_f64();
        let (pairs, retraced) = area.pair_counts();
        let t = Instant::now();
        let params = LineParams { lines, seed: 1 };
        IntersectionList::build(&scene, &tracer, &params, &control)?;
        let line_time = t.elapsed().as_secs_f64();
        println!(
            "{name}\t{}\t{}\t{bvh:.3}\t{punctual:.3}\t{area_time:.3}\t{pairs}\t{retraced}\t{line_time:.3}",
            scene.patches.len(),
            scene.frames.count,
        );
    }
    Ok(())
}
