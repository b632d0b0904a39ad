//! The numerical extremes of METHOD.md §8: reflectance from 0 to 1, emission from 1e-30 to
//! 1e30, scenes from 1e-4 to 1e6 in size, needle triangles and 10,000 frames. Each case gives
//! the known answer or a clear refusal, never a silent wrong one.
//!
//! Most cases are furnaces: a closed, watertight box whose every patch emits `Le` and reflects
//! ρ has `L = Le / (1 − ρ)` exactly, for any lines (METHOD.md §7), since every row of the
//! estimated form factors sums to 1. The errors left: none from the lines; from the solver,
//! rounding only, because with uniform ρ and `Le` the first conjugate-gradient step lands on the
//! uniform solution (measured: at most 5e-14); from `radiance.bin`, the f32 rounding of 6e-8.
//! `FURNACE_TOLERANCE` = 1e-6 covers those and is ten times below the smallest error these tests
//! must see: a reflectance off by the f32 rounding of the cap (1.3e-5 at ρ = 0.999). A leak of
//! one segment in 10⁴ would cost about 10⁻⁴/(1 − ρ) = 10% (§7).

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use std::path::{Path, PathBuf};

use common::Doc;
use radiosity::bake::Bake;
use radiosity::batch::{BatchParams, Outcome, Outputs, bake_one};
use radiosity::control::Control;
use radiosity::loader::{LoadError, LoadOptions, MAX_REFLECTANCE, load};
use radiosity::output::{FrameItem, FrameSpec};
use radiosity::params::{BakeSettings, PatchSize};
use radiosity::scene::Scene;
use radiosity::solve::{FrameSolution, SolveParams};
use radiosity::timeline::LineParams;
use serde_json::json;

/// Relative error allowed on a furnace's answer (see the module's comment).
const FURNACE_TOLERANCE: f64 = 1e-6;

fn lines(n: u64) -> LineParams {
    LineParams { lines: n, seed: 1 }
}

/// A material named `name` reflecting ρ (metallic 0) and emitting `strength` (white, through
/// `KHR_materials_emissive_strength`).
fn material(doc: &mut Doc, name: &str, rho: f32, strength: f32) -> usize {
    doc.json["extensionsUsed"] = json!(["KHR_materials_emissive_strength"]);
    doc.push(
        "materials",
        json!({"name": name,
               "pbrMetallicRoughness": {"baseColorFactor": [rho, rho, rho, 1.0], "metallicFactor": 0.0},
               "emissiveFactor": [1.0, 1.0, 1.0],
               "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": strength}}}),
    )
}

/// A closed 1 m box, faces inward, of one material ("wall") under a root node scaled by `scale`.
fn furnace_doc(rho: f32, strength: f32, scale: f64) -> Doc {
    let mut d = Doc::new();
    let wall = material(&mut d, "wall", rho, strength);
    let (positions, indices) = common::cuboid([1.0; 3], [0.0; 3], true);
    let mesh = d.mesh(&positions, Some(&indices), Some(wall));
    let node = d.node(json!({"mesh": mesh}));
    let root = d.node(json!({"children": [node], "scale": [scale, scale, scale]}));
    d.scene(&[root]);
    d
}

/// Options splitting the box's faces into a few dozen patches each.
fn patch_size(size: f64) -> LoadOptions {
    LoadOptions {
        patch_size: Some(size),
        ..LoadOptions::default()
    }
}

fn solve(scene: Scene, n: u64) -> FrameSolution {
    let bake = Bake::trace(scene, &lines(n)).unwrap();
    bake.solve_frame(0, &bake.scene.materials, &SolveParams::default())
}

/// Checks a furnace's solution: every sampled patch within `FURNACE_TOLERANCE` of `expected`
/// (red channel), every unsampled one saying so (no error bar) and reporting its emission `le`.
/// Returns the number of sampled patches.
fn assert_furnace(s: &FrameSolution, expected: f64, le: f64, what: &str) -> usize {
    assert!(s.converged, "{what}: residual {}", s.residual);
    let mut sampled = 0;
    for (i, l) in s.radiance.iter().enumerate() {
        if s.samples[i] == 0 {
            assert!(s.stderr[i].is_none(), "{what}: patch {i}");
            assert_eq!(l[0], le, "{what}: unsampled patch {i}");
            continue;
        }
        sampled += 1;
        assert!(
            (l[0] / expected - 1.0).abs() <= FURNACE_TOLERANCE,
            "{what}: patch {i}: {} against {expected}",
            l[0]
        );
    }
    sampled
}

/// A fresh scratch directory.
fn scratch(name: &str) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("radiosity-extremes-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Batch parameters writing `radiance.bin`, `summary.json`, one `.glb` and one small preview.
fn batch(load: LoadOptions, n: u64) -> BatchParams {
    BatchParams {
        settings: BakeSettings {
            patch_size: load.patch_size.map_or(PatchSize::Source, PatchSize::Length),
            load,
            patch_budget: None,
            lines: lines(n),
            sky: [0.0; 3],
        },
        outputs: Outputs {
            glb_frames: FrameSpec::List(vec![FrameItem::First]),
            preview_frames: FrameSpec::List(vec![FrameItem::First]),
            preview_size: (32, 24),
            gif: false,
            exposure: None,
            shading: radiosity::output::Shading::Flat,
            lightmaps: None,
            lightmap_quantity: Default::default(),
            probes: None,
        },
        force: true,
        max_iterations: SolveParams::default().max_iterations,
    }
}

/// Bakes `doc` as `name.gltf` into `out`.
fn bake_doc(doc: &Doc, name: &str, out: &Path, params: &BatchParams) -> Outcome {
    let input = out.join(format!("{name}.gltf"));
    std::fs::write(&input, doc.gltf()).unwrap();
    bake_one(&input, out, params, &Control::default(), &mut |_| {})
}

/// Frame 0's red radiance per patch from a `radiance.bin`.
fn radiance_bin(path: &Path) -> Vec<f32> {
    let bin = std::fs::read(path).unwrap();
    let word = |at: usize| u32::from_le_bytes(bin[at..at + 4].try_into().unwrap()) as usize;
    assert_eq!(&bin[..4], b"RADB");
    let patches = word(12);
    let frame = &bin[16 + 8..];
    (0..patches)
        .map(|i| f32::from_le_bytes(frame[12 * i..12 * i + 4].try_into().unwrap()))
        .collect()
}

#[test]
fn reflectance_from_0_to_1_gives_le_over_1_minus_rho_and_1_is_capped_with_a_warning() {
    for rho in [0.0f32, 0.5, 0.9, 0.999, 1.0] {
        let scene = load(&furnace_doc(rho, 1.0, 1.0).gltf(), &patch_size(0.3)).unwrap();
        // A file's 0.999 is kept as read (f32), 1 is lowered to the cap and the warning says
        // which material.
        let kept = if rho == 1.0 {
            MAX_REFLECTANCE
        } else {
            f64::from(rho)
        };
        assert_eq!(scene.materials[0].reflectance, [kept; 3], "rho {rho}");
        let warned = scene
            .warnings
            .iter()
            .any(|w| w.contains("max_reflectance 0.999") && w.contains("\"wall\""));
        assert_eq!(warned, rho == 1.0, "rho {rho}: {:?}", scene.warnings);
        let count = scene.patches.len();
        let s = solve(scene, 3_000);
        let sampled = assert_furnace(&s, 1.0 / (1.0 - kept), 1.0, &format!("rho {rho}"));
        assert!(sampled * 10 >= count * 9, "rho {rho}: {sampled} of {count}");
    }
}

/// Energy balance of a closed scene of uniform reflectance ρ lit by a lamp face whose direct
/// light E is sampled explicitly (`crate::direct::area`), the lines carrying `L − Le` from it:
/// summing the estimated system's rows (`Σ_i S_ij = N_j`) gives
/// `(1 − ρ) Σ N_i L_i = (1 − ρ) Σ_lamp N_j Le_j + ρ Σ_i N_i E_i / π`, whatever the lines and
/// the shadow rays. The solver's residual r (relative to b) moves it by at most
/// `√P |r| ≤ √P · 1e-10 · Σ b`: a bound that holds for any light, not only a uniform one. And
/// the direct light the lamp sends equals what it emits (`ρ Σ N E/π ≈ ρ Σ_lamp N Le`, up to the
/// lines' sampling of the areas `N_i ∝ A_i`).
#[test]
fn a_room_of_reflectance_1_lit_by_one_face_converges_once_capped() {
    let mut d = Doc::new();
    let lamp = material(&mut d, "lamp", 1.0, 1.0);
    let wall = material(&mut d, "wall", 1.0, 0.0);
    let (positions, indices) = common::cuboid([1.0; 3], [0.0; 3], true);
    let lit = d.mesh(&positions, Some(&indices[..6]), Some(lamp));
    let rest = d.mesh(&positions, Some(&indices[6..]), Some(wall));
    let nodes = [d.node(json!({"mesh": lit})), d.node(json!({"mesh": rest}))];
    d.scene(&nodes);
    let scene = load(&d.gltf(), &patch_size(0.3)).unwrap();
    let warning = scene.warnings.join("; ");
    assert!(
        warning.contains("material 0 (\"lamp\")") && warning.contains("material 1 (\"wall\")"),
        "{warning}"
    );
    let rho = MAX_REFLECTANCE;
    let lamp_patches: Vec<bool> = scene.patches.iter().map(|p| p.material == 0).collect();
    let count = lamp_patches.len() as f64;
    let bake = Bake::trace(scene, &lines(5_000)).unwrap();
    assert_eq!(bake.area_lights().materials(), [0], "the lamp is sampled");
    let s = bake.solve_frame(0, &bake.scene.materials, &SolveParams::default());
    let (direct, _) = bake
        .area_lights()
        .irradiance(0, &bake.scene.materials)
        .unwrap();
    assert!(
        s.converged,
        "residual {} after {} iterations",
        s.residual, s.iterations
    );
    // Hard for the solver: solved to the tolerance alone (no early stop at the noise), it
    // takes many iterations.
    let exact = SolveParams {
        noise: 0.0,
        precision: 0.0,
        ..SolveParams::default()
    };
    let hard = bake.solve_frame(0, &bake.scene.materials, &exact);
    assert!(
        hard.iterations > 20,
        "{} iterations: not a hard case",
        hard.iterations
    );
    let n = |i: usize| s.samples[i] as f64;
    let emitted: f64 = (0..s.samples.len())
        .filter(|&i| lamp_patches[i])
        .map(n)
        .sum();
    let balance: f64 = (0..s.samples.len())
        .map(|i| (1.0 - rho) * n(i) * s.radiance[i][0])
        .sum();
    let reflected: f64 = (0..s.samples.len())
        .map(|i| rho * n(i) * direct[i][0] / std::f64::consts::PI)
        .sum();
    let source = (1.0 - rho) * emitted + reflected;
    // The balance is the sum of the rows of the system: its relative error is the residual's
    // sum over that of the right-hand side (all ≥ 0), at most √n times the relative residual
    // the solve stopped at (it stops once the answer is within a twentieth of its noise, not at
    // a fixed residual).
    let bound = count.sqrt() * s.residual;
    assert!(
        (balance / source - 1.0).abs() <= bound,
        "{balance} against {source} (bound {bound:e})"
    );
    // N_i samples A_i with a relative error of about 1/√N over the lamp's crossings.
    let spread = 3.0 / emitted.sqrt();
    assert!(
        (reflected / (rho * emitted) - 1.0).abs() <= spread,
        "the lamp's direct light {reflected} against its emission {}",
        rho * emitted
    );
}

#[test]
fn reflectance_1_without_the_cap_is_refused_not_answered() {
    let doc = furnace_doc(1.0, 1.0, 1.0);
    let uncapped = LoadOptions {
        max_reflectance: 1.0,
        ..LoadOptions::default()
    };
    let scene = load(&doc.gltf(), &uncapped).unwrap();
    assert_eq!(scene.materials[0].reflectance, [1.0; 3]);
    assert!(scene.warnings.is_empty(), "{:?}", scene.warnings);
    // All the light stays in the box: no steady state. The solve says so…
    let s = solve(scene, 3_000);
    assert!(!s.converged);
    let reason = s
        .ensure_converged(0, &SolveParams::default())
        .unwrap_err()
        .to_string();
    assert!(
        reason.contains("frame 0 did not converge") && reason.contains("max_reflectance"),
        "{reason}"
    );
    // … and a bake fails the scene instead of writing it.
    let out = scratch("uncapped");
    match bake_doc(&doc, "box", &out, &batch(uncapped, 3_000)) {
        Outcome::Failed(reason) => assert!(reason.contains("did not converge"), "{reason}"),
        other => panic!("{other:?}"),
    }
    assert!(!out.join("box").exists());
    // A cap outside (0, 1] is refused, naming the option.
    for max in [0.0, -0.5, 1.5, f64::NAN] {
        let options = LoadOptions {
            max_reflectance: max,
            ..LoadOptions::default()
        };
        match load(&doc.gltf(), &options) {
            Err(e @ LoadError::Option(_)) => {
                assert!(e.to_string().contains("max_reflectance"), "{e}")
            }
            other => panic!("{max}: {other:?}"),
        }
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn an_iteration_cap_of_one_fails_the_bake_and_keeps_the_previous_outputs() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell_box.gltf");
    let out = scratch("cap");
    let mut params = batch(LoadOptions::default(), 3_000);
    let good = bake_one(&path, &out, &params, &Control::default(), &mut |_| {});
    assert_eq!(good, Outcome::Baked(out.join("cornell_box")));
    let before = std::fs::read(out.join("cornell_box/radiance.bin")).unwrap();
    params.max_iterations = 1;
    match bake_one(&path, &out, &params, &Control::default(), &mut |_| {}) {
        Outcome::Failed(reason) => assert!(
            reason.contains("frame 0 did not converge")
                && reason.contains("residual")
                && reason.contains("after 1 iterations"),
            "{reason}"
        ),
        other => panic!("{other:?}"),
    }
    assert_eq!(
        std::fs::read(out.join("cornell_box/radiance.bin")).unwrap(),
        before
    );
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn emission_from_1e_minus_30_to_1e30_scales_the_answer_through_to_the_files() {
    let out = scratch("emission");
    for strength in [1e-30f32, 1.0, 1e30] {
        let le = f64::from(strength);
        let doc = furnace_doc(0.9, strength, 1.0);
        let scene = load(&doc.gltf(), &patch_size(0.3)).unwrap();
        let rho = scene.materials[0].reflectance[0];
        let exact = le / (1.0 - rho);
        assert_furnace(&solve(scene, 3_000), exact, le, &format!("Le {le}"));
        // radiance.bin holds f32: exact to its rounding.
        let name = format!("box{strength:e}");
        let baked = bake_doc(&doc, &name, &out, &batch(patch_size(0.3), 3_000));
        assert_eq!(baked, Outcome::Baked(out.join(&name)), "Le {le}");
        for l in radiance_bin(&out.join(&name).join("radiance.bin")) {
            assert!(
                (f64::from(l) / exact - 1.0).abs() <= FURNACE_TOLERANCE,
                "Le {le}: {l} against {exact}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// Emission whose radiance could overflow the `f32` outputs is refused by the loader, naming the
/// material, instead of being written as infinity.
#[test]
fn emission_the_outputs_cannot_hold_is_refused() {
    // 9e33 / (1 − 0.999) = 9e36, under the 1e37 the outputs take; 1e35 gives 1e38.
    assert!(
        load(
            &furnace_doc(0.999, 9e33, 1.0).gltf(),
            &LoadOptions::default()
        )
        .is_ok()
    );
    let error = load(
        &furnace_doc(0.999, 1e35, 1.0).gltf(),
        &LoadOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        error.contains("material 0 (\"wall\") emits") && error.contains("f32 outputs"),
        "{error}"
    );
}

#[test]
fn scenes_from_1e_minus_4_to_1e6_in_size_give_the_same_answer() {
    for scale in [1e-4, 1.0, 1e6] {
        let scene = load(
            &furnace_doc(0.999, 1.0, scale).gltf(),
            &patch_size(0.3 * scale),
        )
        .unwrap();
        let rho = scene.materials[0].reflectance[0];
        let count = scene.patches.len();
        let s = solve(scene, 3_000);
        let sampled = assert_furnace(&s, 1.0 / (1.0 - rho), 1.0, &format!("scale {scale}"));
        assert!(
            sampled * 10 >= count * 9,
            "scale {scale}: {sampled} of {count}"
        );
    }
}

/// A closed 1 m box whose top face is a fan of needles: its diagonal carries vertices at
/// `0.5 ± 2^-k` (k = 2…20, exact in f32) and each side of the diagonal joins consecutive ones
/// to its corner, so the thinnest needles are about 10⁻⁶ m wide and 0.7 m long. No
/// T-junctions: the box stays watertight.
fn needle_box() -> Doc {
    let mut positions: Vec<[f32; 3]> = Vec::new();
    let mut indices: Vec<u32> = Vec::new();
    let (cube, cube_indices) = common::cuboid([1.0; 3], [0.0; 3], true);
    // The cuboid's faces, less the top one (+Y: quad [2, 6, 7, 3], triangles 6 and 7).
    positions.extend(cube);
    indices.extend(
        cube_indices
            .chunks(3)
            .enumerate()
            .filter(|(t, _)| !(6..8).contains(t))
            .flat_map(|(_, t)| t.to_vec()),
    );
    let mut along = vec![0.0f32];
    along.extend((2..=20).map(|k| 0.5 - 0.5f32.powi(k)));
    along.push(0.5);
    along.extend((2..=20).rev().map(|k| 0.5 + 0.5f32.powi(k)));
    along.push(1.0);
    // The top face: y = 0.5, x and z in [-0.5, 0.5], facing down (into the box). Its diagonal
    // runs from (-0.5, -0.5) to (0.5, 0.5) in (x, z); corners (0.5, -0.5) and (-0.5, 0.5).
    let vertex = |positions: &mut Vec<[f32; 3]>, x: f32, z: f32| {
        positions.push([x, 0.5, z]);
        (positions.len() - 1) as u32
    };
    let diagonal: Vec<u32> = along
        .iter()
        .map(|&t| vertex(&mut positions, t - 0.5, t - 0.5))
        .collect();
    let right = vertex(&mut positions, 0.5, -0.5);
    let left = vertex(&mut positions, -0.5, 0.5);
    for pair in diagonal.windows(2) {
        // Wound to face −Y.
        indices.extend([right, pair[1], pair[0]]);
        indices.extend([left, pair[0], pair[1]]);
    }
    let mut d = Doc::new();
    let wall = material(&mut d, "wall", 0.999, 1.0);
    let flat: Vec<f32> = positions.iter().flatten().copied().collect();
    let position = d.floats(&flat, "VEC3");
    let index = d.indices(&indices, 5125);
    let mesh = d.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": position}, "indices": index, "material": wall}]}),
    );
    let node = d.node(json!({"mesh": mesh}));
    d.scene(&[node]);
    d
}

#[test]
fn needle_triangles_are_exact_or_say_they_were_not_sampled() {
    let doc = needle_box();
    let scene = load(&doc.gltf(), &LoadOptions::default()).unwrap();
    assert!(scene.warnings.is_empty(), "{:?}", scene.warnings);
    let areas: Vec<f64> = scene.patches.iter().map(|p| p.area).collect();
    let thinnest = areas.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(thinnest < 1e-6, "{thinnest}");
    let rho = scene.materials[0].reflectance[0];
    let s = solve(scene, 20_000);
    // Any leak between the needles would show as an error of about its rate / (1 − ρ).
    let sampled = assert_furnace(&s, 1.0 / (1.0 - rho), 1.0, "needles");
    let unsampled: Vec<f64> = (0..areas.len())
        .filter(|&i| s.samples[i] == 0)
        .map(|i| areas[i])
        .collect();
    eprintln!("{sampled} needles and faces sampled, unsampled areas {unsampled:?}");
    assert!(unsampled.iter().all(|&a| a < 1e-3), "{unsampled:?}");
    // Subdividing a needle finely would make millions of patches: refused at the limit.
    let fine = LoadOptions {
        patch_size: Some(1e-3),
        max_patches: 20_000,
        ..LoadOptions::default()
    };
    match load(&doc.gltf(), &fine) {
        Err(e @ LoadError::Limit(_)) => assert!(e.to_string().contains("patch_size"), "{e}"),
        other => panic!("{:?}", other.map(|s| s.patches.len())),
    }
}

#[test]
fn ten_thousand_frames_bake_at_the_cost_of_their_distinct_states() {
    // A closed room with a small box jumping between two places inside it (STEP keys), every
    // surface a furnace wall: L = 1 / (1 − 0.5) = 2 in every frame.
    let mut d = Doc::new();
    let wall = material(&mut d, "wall", 0.5, 1.0);
    let (room, room_indices) = common::cuboid([4.0; 3], [0.0; 3], true);
    let (cube, cube_indices) = common::cuboid([0.5; 3], [0.0; 3], false);
    let room = d.mesh(&room, Some(&room_indices), Some(wall));
    let cube = d.mesh(&cube, Some(&cube_indices), Some(wall));
    let room = d.node(json!({"mesh": room}));
    let cube = d.node(json!({"mesh": cube}));
    d.scene(&[room, cube]);
    d.animation(
        "jump",
        &[(
            cube,
            "translation",
            &[0.0, 5.0, 10.0],
            &[-1.0, 0.0, 0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 0.0],
            "STEP",
        )],
    );
    let at_1000_fps = |max_frames| LoadOptions {
        fps: 1000.0,
        max_frames,
        ..LoadOptions::default()
    };
    // Over a limit (the service's is 10,000 frames): refused, saying why.
    match load(&d.gltf(), &at_1000_fps(10_000)) {
        Err(e @ LoadError::Limit(_)) => {
            assert!(e.to_string().contains("10001 frames"), "{e}")
        }
        other => panic!("{:?}", other.map(|s| s.frames.count)),
    }
    let scene = load(&d.gltf(), &at_1000_fps(100_000)).unwrap();
    assert_eq!(scene.frames.count, 10_001);
    let bake = Bake::trace(scene, &lines(300)).unwrap();
    let all = bake.solve_all(&bake.scene.materials, &SolveParams::default());
    let mut distinct: Vec<*const FrameSolution> = all.iter().map(|s| &raw const **s).collect();
    distinct.sort_unstable();
    distinct.dedup();
    assert_eq!(distinct.len(), 2);
    for (f, s) in all.iter().enumerate().step_by(1_000) {
        assert_furnace(s, 2.0, 1.0, &format!("frame {f}"));
    }
    assert_furnace(&all[5_000], 2.0, 1.0, "frame 5000");
}
