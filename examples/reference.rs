//! The bake against physics: per-patch error of lit, non-emitting patches at frame 0 against
//! the path-traced reference (`radiosity::direct::reference`), with the reference's own error.
//!
//!     cargo run --release --example reference [LINES] [PATHS] [PATCH_SIZE, - or auto] [SCENE...]

use std::time::Instant;

use radiosity::adaptive::{Adaptive, adapt};
use radiosity::bake::Bake;
use radiosity::direct::reference::path_traced;
use radiosity::loader::{LoadOptions, load};
use radiosity::solve::SolveParams;
use radiosity::timeline::{Control, LineParams};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let lines: u64 = args.next().map_or(Ok(1_000_000), |a| a.parse())?;
    let paths: usize = args.next().map_or(Ok(256), |a| a.parse())?;
    let size = args.next().unwrap_or_else(|| "-".into());
    let auto = size == "auto";
    let patch_size: Option<f64> = (size != "-" && !auto).then(|| size.parse()).transpose()?;
    let mut scenes: Vec<String> = args.collect();
    if scenes.is_empty() {
        scenes = ["cornell_box", "cornell_moving", "level"]
            .map(|s| format!("scenes/{s}.gltf"))
            .to_vec();
    }
    println!(
        "scene\tpatches\tbake s\treference s\tlit error\treference error\tbake error\timage error\tmean (bake/ref − 1)"
    );
    for name in scenes {
        let options = LoadOptions {
            patch_size,
            ..LoadOptions::default()
        };
        let scene = load(&std::fs::read(&name)?, &options)?;
        let t = Instant::now();
        let mut bake = Bake::trace(
            scene,
            &LineParams {
                lines,
                bundles: None,
                seed: 1,
            },
        )?;
        if auto {
            let mut auto = Adaptive::for_lines(lines, bake.scene.patches.len());
            if let Ok(r) = std::env::var("AUTO_ROUNDS") {
                auto.rounds = r.parse()?;
            }
            if let Ok(b) = std::env::var("AUTO_BUDGET") {
                auto.budget = b.parse()?;
            }
            if let Ok(z) = std::env::var("AUTO_Z") {
                auto.significance = z.parse()?;
            }
            if let Ok(n) = std::env::var("AUTO_MIN") {
                auto.min_crossings = n.parse()?;
            }
            let rounds = adapt(
                &mut bake,
                &auto,
                &SolveParams::default(),
                &Control::default(),
            )?;
            for r in rounds {
                eprintln!("{r:?}");
            }
        }
        let scene = &bake.scene;
        let solved = bake.solve_frame(0, &scene.materials, &SolveParams::default());
        let bake_seconds = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let reference = path_traced(scene, bake.tracer(), 0, paths, [0.0; 3], 7)?;
        let reference_seconds = t.elapsed().as_secs_f64();
        // Area-weighted RMS of the relative error over lit, non-emitting patches and channels.
        let (mut sum, mut sum_ref, mut weight, mut bias, mut bias_weight) =
            (0.0, 0.0, 0.0, 0.0, 0.0);
        // What one sees: the squared difference between the patch's radiance and the true
        // radiance at each point, area-weighted, over the mean square radiance.
        let (mut seen, mut square) = (0.0, 0.0);
        let mut dump = String::new();
        for (i, p) in scene.patches.iter().enumerate() {
            let m = &scene.materials[p.material as usize];
            if m.is_emitter() {
                continue;
            }
            for c in 0..3 {
                let r = reference[i].radiance[c];
                // Lit: the reference sees light there beyond its own noise (a relative error
                // against a reference of zero ± noise measures nothing).
                if m.reflectance[c] == 0.0 || r <= 3.0 * reference[i].stderr[c] {
                    continue;
                }
                let e = solved.radiance[i][c] / r - 1.0;
                if c == 1 {
                    dump += &format!(
                        "{i}\t{}\t{}\t{}\t{}\t{}\t{}\n",
                        p.area,
                        solved.samples[i],
                        solved.radiance[i][c],
                        r,
                        reference[i].stderr[c],
                        solved.stderr[i].map_or(0.0, |s| s[c])
                    );
                }
                if std::env::var("WORST").is_ok() && e.abs() > 0.3 && c == 0 {
                    eprintln!(
                        "patch {i} {:?} {:?} area {:.5} samples {} bake {:.4} ref {:.4} ± {:.4} stderr {:?}",
                        p.source,
                        p.side,
                        p.area,
                        solved.samples[i],
                        solved.radiance[i][c],
                        r,
                        reference[i].stderr[c],
                        solved.stderr[i]
                    );
                }
                sum += p.area * e * e;
                let (se, spread) = (reference[i].stderr[c], reference[i].spread[c]);
                seen += p.area * ((solved.radiance[i][c] - r).powi(2) - se * se + spread);
                square += p.area * r * r;
                sum_ref += p.area * (reference[i].stderr[c] / r).powi(2);
                weight += p.area;
                bias += p.area * solved.radiance[i][c];
                bias_weight += p.area * r;
            }
        }
        if let Ok(path) = std::env::var("DUMP") {
            std::fs::write(path, &dump)?;
        }
        println!(
            "{name}\t{}\t{bake_seconds:.2}\t{reference_seconds:.2}\t{:.4}\t{:.4}\t{:.4}\t{:.4}\t{:+.4}",
            scene.patches.len(),
            (sum / weight).sqrt(),
            (sum_ref / weight).sqrt(),
            // The bake's own error: the reference's noise taken out in quadrature (the two
            // are independent).
            ((sum - sum_ref).max(0.0) / weight).sqrt(),
            (seen.max(0.0) / square).sqrt(),
            bias / bias_weight - 1.0
        );
    }
    Ok(())
}
