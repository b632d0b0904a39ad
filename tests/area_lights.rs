//! Emitting surfaces as area lights (`radiosity::direct::area`), against closed forms.
//!
//! The scene: a 0.5 m square emitter facing down, 1 m over a 4 × 4 m floor of reflectance 0.5
//! cut into 0.5 m cells, open to a black sky; the emitter is black. The floor sees only the
//! emitter, so its radiance is exactly `ρ·Le·F`, with `F` the patch's form factor to the square:
//! Howell's closed form for a point under a parallel rectangle, integrated over the patch (a
//! 1,024-point midpoint rule, far finer than the bake's sampling). With a square plate between
//! them, the umbra is exactly black, the floor beyond the penumbra is the closed form again,
//! and the penumbra is checked against a brute-force double integral with an exact segment–plate
//! visibility.
//!
//! Tolerances: each patch within 4 of its own reported σ (plus the reference's quadrature
//! error), and the mean of z² over the patches below 2 (honest error bars give 1): an error
//! bar too narrow, a direct term counted twice, or light through the plate, fails.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use common::Doc;
use glam::DVec3;
use radiosity::bake::Bake;
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::Scene;
use radiosity::solve::analytic::point_to_parallel_rectangle;
use radiosity::solve::{FrameSolution, SolveParams};
use radiosity::timeline::LineParams;
use serde_json::json;

const RHO: f64 = 0.5;
const LE: f64 = 3.0;
/// The emitter: [-0.25, 0.25]² at this height, facing down.
const HEIGHT: f64 = 1.0;
const HALF: f64 = 0.25;
/// The floor: [-2, 2]² at y = 0 in cells of this side.
const CELL: f64 = 0.5;
const CELLS: usize = 8;

/// The floor's triangles in file coordinates, in the order of its primitive.
fn floor_triangles() -> Vec<[DVec3; 3]> {
    let mut out = Vec::new();
    let origin = -(CELLS as f64) * CELL / 2.0;
    for i in 0..CELLS {
        for k in 0..CELLS {
            let (x0, z0) = (origin + i as f64 * CELL, origin + k as f64 * CELL);
            let (x1, z1) = (x0 + CELL, z0 + CELL);
            let p = |x: f64, z: f64| DVec3::new(x, 0.0, z);
            // Counter-clockwise seen from above (+y).
            out.push([p(x0, z0), p(x0, z1), p(x1, z1)]);
            out.push([p(x0, z0), p(x1, z1), p(x1, z0)]);
        }
    }
    out
}

/// A square `[-h, h]²` at height `y`, as two triangles facing down (or up).
fn square(h: f64, y: f64, down: bool) -> Vec<[f32; 3]> {
    let p = |x: f64, z: f64| [x as f32, y as f32, z as f32];
    let (a, b, c, d) = (p(-h, -h), p(h, -h), p(h, h), p(-h, h));
    if down {
        vec![a, b, c, a, c, d]
    } else {
        vec![a, c, b, a, d, c]
    }
}

/// The scene, with a plate of half-side `plate.0` at height `plate.1` if any; the plate slides
/// by `slide` along x between 1 s and 2 s if given (STEP keys at 0, 1, 2 s).
fn scene(plate: Option<(f64, f64)>, slide: Option<f64>, fps: f64) -> Scene {
    let mut d = Doc::new();
    d.json["extensionsUsed"] = json!(["KHR_materials_emissive_strength"]);
    let floor_m = d.push(
        "materials",
        json!({"name": "floor",
               "pbrMetallicRoughness": {"baseColorFactor": [RHO, RHO, RHO, 1.0], "metallicFactor": 0.0}}),
    );
    let lamp_m = d.push(
        "materials",
        json!({"name": "lamp",
               "pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 1.0], "metallicFactor": 0.0},
               "emissiveFactor": [1.0, 1.0, 1.0],
               "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": LE}}}),
    );
    let black = d.push(
        "materials",
        json!({"name": "plate", "doubleSided": true,
               "pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 1.0], "metallicFactor": 0.0}}),
    );
    let floor: Vec<[f32; 3]> = floor_triangles()
        .iter()
        .flatten()
        .map(|p| p.as_vec3().to_array())
        .collect();
    let floor = d.mesh(&floor, None, Some(floor_m));
    let lamp = d.mesh(&square(HALF, HEIGHT, true), None, Some(lamp_m));
    let mut nodes = vec![
        d.node(json!({"name": "floor", "mesh": floor})),
        d.node(json!({"name": "lamp", "mesh": lamp})),
    ];
    if let Some((h, y)) = plate {
        let mesh = d.mesh(&square(h, 0.0, true), None, Some(black));
        let node = d.node(json!({"name": "plate", "mesh": mesh, "translation": [0.0, y, 0.0]}));
        if let Some(dx) = slide {
            let y = y as f32;
            let dx = dx as f32;
            let values = [0.0, y, 0.0, dx, y, 0.0, dx, y, 0.0];
            d.animation(
                "slide",
                &[(node, "translation", &[0.0, 1.0, 2.0], &values, "STEP")],
            );
        }
        nodes.push(node);
    }
    d.scene(&nodes);
    load(
        &d.gltf(),
        &LoadOptions {
            patch_size: Some(10.0),
            fps,
            ..LoadOptions::default()
        },
    )
    .unwrap()
}

fn bake(scene: Scene, lines: u64, seed: u64) -> Bake {
    Bake::trace(scene, &LineParams { lines, seed }).unwrap()
}

/// The mean over triangle `t` of `f`, by the midpoint rule on its 4^5 sub-triangles.
fn over_triangle(t: [DVec3; 3], f: &dyn Fn(DVec3) -> f64) -> f64 {
    common::mean_over_triangle(t, 5, f)
}

/// The unoccluded form factor from floor triangle `t` to the emitter (Howell C-11 integrated).
fn unoccluded(t: [DVec3; 3]) -> f64 {
    over_triangle(t, &|p| {
        point_to_parallel_rectangle((p.x, p.z), (-HALF, HALF), (-HALF, HALF), HEIGHT)
    })
}

/// The form factor from floor triangle `t` to the emitter with a plate of half-side `h` at
/// height `y` (centred at x = `dx`) in between, by brute force: 256 points of the triangle ×
/// 48 × 48 points of the emitter, each pair's segment tested against the plate exactly.
fn occluded(t: [DVec3; 3], (h, y): (f64, f64), dx: f64) -> f64 {
    let n = 48;
    let cell = 2.0 * HALF / n as f64;
    over_triangle(t, &|p| {
        let mut sum = 0.0;
        for i in 0..n {
            for k in 0..n {
                let q = DVec3::new(
                    -HALF + (i as f64 + 0.5) * cell,
                    HEIGHT,
                    -HALF + (k as f64 + 0.5) * cell,
                );
                let s = (y - p.y) / (q.y - p.y);
                let m = p + (q - p) * s;
                if (m.x - dx).abs() <= h && m.z.abs() <= h {
                    continue;
                }
                let d = q - p;
                let r2 = d.length_squared();
                // cos at the floor (+y) and at the emitter (−y), over π r².
                sum += (d.y / r2.sqrt()).powi(2) / (std::f64::consts::PI * r2);
            }
        }
        sum * cell * cell
    })
}

/// Per floor patch: its triangle and index, with its radiance and σ (red) in `s`.
fn floor(scene: &Scene) -> Vec<(usize, [DVec3; 3])> {
    let triangles = floor_triangles();
    (0..scene.patches.len())
        .filter(|&p| {
            scene
                .node_label(scene.patches[p].source.node)
                .contains("floor")
        })
        .map(|p| (p, triangles[scene.patches[p].source.triangle as usize]))
        .collect()
}

/// Checks every floor patch against `reference` (a form factor), within 4σ plus `slack` (the
/// reference's own error, as a form factor); returns the mean z².
fn check(
    scene: &Scene,
    s: &FrameSolution,
    reference: &dyn Fn([DVec3; 3]) -> f64,
    slack: f64,
) -> f64 {
    let mut z2 = 0.0;
    let patches = floor(scene);
    for &(p, t) in &patches {
        let expected = RHO * LE * reference(t);
        let (l, sigma) = (s.radiance[p][0], s.stderr[p].unwrap()[0]);
        let bound = 4.0 * sigma + RHO * LE * slack + 1e-12;
        assert!(
            (l - expected).abs() <= bound,
            "patch {p} {t:?}: {l} against {expected} (σ {sigma})"
        );
        if sigma > 0.0 {
            z2 += ((l - expected) / sigma).powi(2);
        }
    }
    let z2 = z2 / patches.len() as f64;
    eprintln!("mean z² {z2:.3} over {} patches", patches.len());
    z2
}

#[test]
fn a_square_emitter_lights_a_floor_as_the_closed_form_says() {
    // 500 lines per patch: the emitter's standard sampling (16 to 256 rays per patch).
    let bake = bake(scene(None, None, 1.0), 70_000, 1);
    let lamp = bake
        .scene
        .materials
        .iter()
        .position(|m| m.name.as_deref() == Some("lamp"));
    assert_eq!(bake.area_lights().materials(), [lamp.unwrap() as u32]);
    let s = bake.solve_frame(0, &bake.scene.materials, &SolveParams::default());
    let z2 = check(&bake.scene, &s, &unoccluded, 1e-6);
    assert!(z2 < 2.0, "mean z² {z2}");
    // Unoccluded, only the stratification of each patch is left: every patch to 1% at the
    // standard sampling.
    for (p, t) in floor(&bake.scene) {
        let expected = RHO * LE * unoccluded(t);
        assert!(
            (s.radiance[p][0] / expected - 1.0).abs() < 0.01,
            "patch {p}: {} against {expected}",
            s.radiance[p][0]
        );
    }
}

#[test]
fn a_plate_casts_an_exact_umbra_and_a_penumbra_within_its_error_bars() {
    let plate = (0.5, 0.5);
    let bake = bake(scene(Some(plate), None, 1.0), 20_000, 2);
    let s = bake.solve_frame(0, &bake.scene.materials, &SolveParams::default());
    // The umbra is [-0.75, 0.75]² and the penumbra reaches ±1.25: patches wholly inside the
    // umbra are black, those wholly outside the penumbra see the whole emitter.
    let inside = |t: &[DVec3; 3], r: f64| t.iter().all(|p| p.x.abs() <= r && p.z.abs() <= r);
    let outside = |t: &[DVec3; 3], r: f64| {
        t.iter().all(|p| p.x >= r)
            || t.iter().all(|p| p.x <= -r)
            || t.iter().all(|p| p.z >= r)
            || t.iter().all(|p| p.z <= -r)
    };
    let mut umbra = 0;
    for (p, t) in floor(&bake.scene) {
        if inside(&t, 0.75) {
            assert_eq!(s.radiance[p][0], 0.0, "patch {p} in the umbra");
            umbra += 1;
        }
    }
    assert_eq!(umbra, 8);
    let reference = |t: [DVec3; 3]| {
        if inside(&t, 0.75) {
            0.0
        } else if outside(&t, 1.25) {
            unoccluded(t)
        } else {
            occluded(t, plate, 0.0)
        }
    };
    // The brute-force reference resolves the shadow's edge to 1/48 of the emitter.
    let z2 = check(&bake.scene, &s, &reference, 2e-4);
    assert!(z2 < 2.0, "mean z² {z2}");
}

#[test]
fn a_moving_plate_changes_only_the_frames_and_patches_it_can_shadow() {
    // The plate rests at x = 0 for 1 s, then jumps to x = 1.25 (STEP keys): at 2 fps, frames
    // 0-1 have it at rest and frames 2-4 moved. (The plate is a moving object all along: the
    // static result is computed without it, and both of its places are traced again.)
    let plate = (0.25, 0.5);
    let bake = bake(scene(Some(plate), Some(1.25), 2.0), 20_000, 3);
    let area = bake.area_lights();
    let frames: Vec<(Vec<f64>, Vec<f64>)> = (0..bake.scene.frames.count)
        .map(|f| area.form_factors(f))
        .collect();
    assert_eq!(frames.len(), 5);
    assert_eq!(area.state(0), area.state(1));
    assert_ne!(area.state(1), area.state(2));
    assert_eq!(frames[0], frames[1]);
    assert_eq!(frames[2], frames[4]);
    let slots = area.materials().len();
    let (mut same, mut changed) = (0, 0);
    for (p, t) in floor(&bake.scene) {
        let (before, after) = (frames[0].0[p * slots], frames[2].0[p * slots]);
        // Patches whose every shadow ray misses both places of the plate keep their value
        // bit for bit: they are not traced again.
        let far = t.iter().all(|q| q.x <= -1.0)
            || t.iter().all(|q| q.z >= 1.0)
            || t.iter().all(|q| q.z <= -1.0);
        if far {
            assert_eq!(before, after, "patch {p} {t:?}");
            same += 1;
        } else if before != after {
            changed += 1;
        }
        // Each frame against its own reference.
        for (f, dx) in [(0, 0.0), (2, 1.25)] {
            let expected = occluded(t, plate, dx);
            let (value, variance) = (frames[f].0[p * slots], frames[f].1[p * slots]);
            assert!(
                (value - expected).abs() <= 4.0 * variance.sqrt() + 2e-4,
                "frame {f}, patch {p} {t:?}: {value} against {expected}"
            );
        }
    }
    assert!(
        same >= 40 && changed >= 20,
        "{same} kept, {changed} changed"
    );
}

#[test]
fn relighting_the_emitter_is_linear_and_needs_no_tracing() {
    let bake = bake(scene(Some((0.25, 0.5)), None, 1.0), 20_000, 4);
    let params = SolveParams::default();
    let s1 = bake.solve_frame(0, &bake.scene.materials, &params);
    let mut brighter = bake.scene.materials.clone();
    for m in &mut brighter {
        m.emission = m.emission.map(|e| e * 2.5);
    }
    let s2 = bake.solve_frame(0, &brighter, &params);
    for p in 0..s1.radiance.len() {
        for c in 0..3 {
            let (a, b) = (s1.radiance[p][c], s2.radiance[p][c]);
            assert!(
                (b - 2.5 * a).abs() <= 1e-9 * b.abs().max(1e-30),
                "patch {p}: {a}, {b}"
            );
        }
    }
}

#[test]
fn the_sampled_emitter_and_the_lines_agree_and_do_not_add_up() {
    // The same room bakes once with the lamp sampled, once with the lamp dark at bake time and
    // lit by relighting (so only the lines carry it): the two must agree within their error
    // bars everywhere, including second bounces off a reflecting lamp and the lamp itself.
    let build = |le: f64| {
        let mut d = Doc::new();
        d.json["extensionsUsed"] = json!(["KHR_materials_emissive_strength"]);
        let wall = d.push(
            "materials",
            json!({"name": "wall", "pbrMetallicRoughness": {"baseColorFactor": [0.7, 0.7, 0.7, 1.0], "metallicFactor": 0.0}}),
        );
        let lamp = d.push(
            "materials",
            json!({"name": "lamp",
                   "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1.0], "metallicFactor": 0.0},
                   "emissiveFactor": [1.0, 1.0, 1.0],
                   "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": le}}}),
        );
        let (positions, indices) = common::cuboid([2.0, 2.0, 2.0], [0.0; 3], true);
        let room = d.mesh(&positions, Some(&indices), Some(wall));
        let panel = d.mesh(&square(0.3, 0.99, true), None, Some(lamp));
        let nodes = [
            d.node(json!({"name": "room", "mesh": room})),
            d.node(json!({"name": "panel", "mesh": panel})),
        ];
        d.scene(&nodes);
        load(
            &d.gltf(),
            &LoadOptions {
                patch_size: Some(0.5),
                ..LoadOptions::default()
            },
        )
        .unwrap()
    };
    let sampled = bake(build(LE), 200_000, 5);
    let lines = bake(build(0.0), 200_000, 6);
    assert!(!sampled.area_lights().is_empty());
    assert!(lines.area_lights().is_empty());
    let params = SolveParams::default();
    let a = sampled.solve_frame(0, &sampled.scene.materials, &params);
    let b = lines.solve_frame(0, &sampled.scene.materials, &params);
    let mut z2 = 0.0;
    let mut count = 0;
    for p in 0..a.radiance.len() {
        let (Some(sa), Some(sb)) = (a.stderr[p], b.stderr[p]) else {
            continue;
        };
        let sigma = (sa[0] * sa[0] + sb[0] * sb[0]).sqrt();
        let z = (a.radiance[p][0] - b.radiance[p][0]) / sigma;
        assert!(
            z.abs() < 5.0,
            "patch {p}: {} against {} (σ {sigma})",
            a.radiance[p][0],
            b.radiance[p][0]
        );
        z2 += z * z;
        count += 1;
    }
    let z2 = z2 / f64::from(count);
    assert!(count > 100 && z2 < 2.0, "mean z² {z2} over {count}");
}

#[test]
fn an_emitter_as_large_as_the_scene_stays_with_the_lines() {
    // The furnace: every face emits. Sampling it would cost shadow rays for nothing.
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/furnace.gltf");
    let scene = load(&std::fs::read(path).unwrap(), &LoadOptions::default()).unwrap();
    let bake = bake(scene, 1_000, 7);
    assert!(bake.area_lights().is_empty());
}
