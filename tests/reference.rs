//! The path-traced reference (`radiosity::direct::reference`) against closed forms: it is what
//! the solver is judged against, so it is judged first.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use radiosity::direct::reference::{Estimate, path_traced};
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::{Material, Scene};
use radiosity::solve::analytic::triangle_to_parallel_rectangle;
use radiosity::trace::SceneTracer;

fn sample(name: &str, patch_size: Option<f64>) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    let options = LoadOptions {
        patch_size,
        ..LoadOptions::default()
    };
    load(&std::fs::read(path).unwrap(), &options).unwrap()
}

/// Per-patch checks against `expected` (red channel): at least 90% of the patches within 2σ,
/// none beyond 5σ, and the mean of the z-scores within 5/√n of 0 (a bias shared by every
/// patch shows there, where one patch's noise hides it).
fn check(estimates: &[Estimate], expected: &[Option<f64>]) {
    let mut z = Vec::new();
    for (e, x) in estimates.iter().zip(expected) {
        let Some(x) = *x else { continue };
        assert!(e.stderr[0] > 0.0, "{e:?}");
        z.push((e.radiance[0] - x) / e.stderr[0]);
    }
    let n = z.len() as f64;
    let within = z.iter().filter(|z| z.abs() <= 2.0).count() as f64;
    let worst = z.iter().fold(0.0f64, |m, z| m.max(z.abs()));
    let mean = z.iter().sum::<f64>() / n;
    eprintln!("{n} patches: {within} within 2σ, worst {worst:.2}σ, mean z {mean:.3}");
    assert!(within >= 0.9 * n, "{within} of {n} within 2σ");
    assert!(worst <= 5.0, "worst {worst}σ");
    assert!(mean.abs() <= 5.0 / n.sqrt(), "mean z {mean}");
}

#[test]
fn in_the_furnace_every_patch_is_le_over_one_minus_rho() {
    let mut scene = sample("furnace.gltf", None);
    let rho = 0.7;
    for m in &mut scene.materials {
        m.reflectance = [rho; 3];
    }
    let tracer = SceneTracer::new(&scene);
    let estimates = path_traced(&scene, &tracer, 0, 64, [0.0; 3], 1);
    let expected = 1.0 / (1.0 - rho);
    let mean = estimates.iter().map(|e| e.radiance[0]).sum::<f64>() / estimates.len() as f64;
    eprintln!("furnace mean {mean} against {expected}");
    check(&estimates, &vec![Some(expected); estimates.len()]);
}

#[test]
fn a_closed_box_lit_from_part_of_its_walls_keeps_its_energy() {
    // Whatever emits in a closed scene of uniform reflectance ρ, the area-mean radiance is the
    // area-mean emission over 1 − ρ (every bit of light is reflected ρ times per bounce until
    // absorbed). One patch in three emits here: the field is far from uniform, so a path that
    // samples directions with the wrong density, or loses or double counts the emitters' light,
    // misses the balance.
    let mut scene = sample("furnace.gltf", None);
    let rho = 0.6;
    scene.materials[0].reflectance = [rho; 3];
    scene.materials.push(Material {
        name: Some("dark".into()),
        emission: [0.0; 3],
        ..scene.materials[0].clone()
    });
    for (i, p) in scene.patches.iter_mut().enumerate() {
        if i % 3 != 0 {
            p.material = 1;
        }
    }
    let tracer = SceneTracer::new(&scene);
    let estimates = path_traced(&scene, &tracer, 0, 1024, [0.0; 3], 2);
    let area: f64 = scene.patches.iter().map(|p| p.area).sum();
    let emitted: f64 = scene
        .patches
        .iter()
        .map(|p| p.area * scene.materials[p.material as usize].emission[0])
        .sum::<f64>()
        / area;
    let mean: f64 = scene
        .patches
        .iter()
        .zip(&estimates)
        .map(|(p, e)| p.area * e.radiance[0])
        .sum::<f64>()
        / area;
    let sigma = scene
        .patches
        .iter()
        .zip(&estimates)
        .map(|(p, e)| (p.area * e.stderr[0]).powi(2))
        .sum::<f64>()
        .sqrt()
        / area;
    let expected = emitted / (1.0 - rho);
    eprintln!("mean {mean} ± {sigma} against {expected}");
    assert!(
        (mean - expected).abs() <= 4.0 * sigma,
        "{mean} ± {sigma} against {expected}"
    );
    assert!(sigma < 0.01 * expected, "{sigma}");
}

#[test]
fn facing_a_square_emitter_each_patch_gets_rho_times_its_form_factor() {
    // The sample's unit squares face each other 1 apart; the emitter is black, so a receiver
    // patch's radiance is ρ·F to the emitter, by the closed form of a triangle facing a
    // parallel rectangle.
    // Finer patches, so that each sees the emitter at its own angle; one-sided, so patch i is
    // triangle i.
    let scene = sample("parallel_squares.gltf", Some(0.25));
    assert_eq!(scene.patches.len(), scene.statics.triangles.len());
    let tracer = SceneTracer::new(&scene);
    let estimates = path_traced(&scene, &tracer, 0, 64, [0.0; 3], 3);
    let n = scene.normalisation;
    let expected: Vec<Option<f64>> = scene
        .patches
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let m = &scene.materials[p.material as usize];
            (!m.is_emitter()).then(|| {
                let t = scene.statics.triangles[i];
                let corners = t.map(|v| n.to_scene(scene.statics.positions[v as usize].as_dvec3()));
                m.reflectance[0]
                    * triangle_to_parallel_rectangle(corners, (-0.5, 0.5), (-0.5, 0.5), 0.0)
            })
        })
        .collect();
    check(&estimates, &expected);
}

/// Deep under a plate hanging 1 cm over a floor, open to the sky, light arrives only along the
/// rare paths that find the rim half a metre away: a few dozen paths mostly miss them, and the
/// estimate and its standard error come out far too low together. The bench's reference
/// (`bench::reference_halves`) draws more paths wherever its error is large against its
/// estimate, until it is believed: then it agrees with a long run within its error bar.
#[test]
fn the_bench_reference_draws_paths_until_a_gap_is_believed() {
    use common::quad;
    let mut scene =
        common::static_scene(&[quad(1.0, 0.0, true), quad(0.5, 0.01, false)], Some(0.2));
    for m in &mut scene.materials {
        m.reflectance = [0.8; 3];
    }
    let tracer = SceneTracer::new(&scene);
    // The floor patch nearest the middle, facing up.
    let centre = |p: usize| {
        let t = scene.statics.triangles[p];
        let c = t.map(|v| scene.statics.positions[v as usize].as_dvec3());
        let m = (c[0] + c[1] + c[2]) / 3.0;
        (m.x * m.x + m.z * m.z, m.y)
    };
    let deep = (0..scene.patches.len())
        .filter(|&p| centre(p).1 < scene.bounds.min.y + 1e-9)
        .min_by(|&a, &b| centre(a).0.total_cmp(&centre(b).0))
        .unwrap();
    let sky = [1.0; 3];
    let long = radiosity::direct::reference::path_traced_each(
        &scene,
        &tracer,
        0,
        &|p| if p == deep { 400_000 } else { 0 },
        sky,
        99,
    )[deep];
    let (a, b) = radiosity::bench::reference_halves((&scene, &tracer), 0, 32, sky, 5);
    let mean = 0.5 * (a[deep].radiance[0] + b[deep].radiance[0]);
    let sigma = 0.5 * a[deep].stderr[0].hypot(b[deep].stderr[0]);
    let z = (mean - long.radiance[0]) / sigma.hypot(long.stderr[0]);
    eprintln!(
        "deep floor patch {deep}: {mean:.5} ± {sigma:.5} against {:.5} ± {:.5} (z {z:.2})",
        long.radiance[0], long.stderr[0]
    );
    assert!(long.stderr[0] < 0.05 * long.radiance[0], "{long:?}");
    assert!(z.abs() < 3.0, "z = {z}");
    assert!(sigma < 0.5 * mean, "{mean} ± {sigma}");
}
