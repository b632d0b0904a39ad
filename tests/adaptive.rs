//! Adaptive patches: cutting patches after tracing moves every crossing where a fresh trace
//! would put it, and `auto` cuts where the light needs it.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use glam::DVec3;
use radiosity::adaptive::{Adaptive, adapt};
use radiosity::bake::{Bake, Lights};
use radiosity::control::Control;
use radiosity::direct::reference::path_traced;
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::Scene;
use radiosity::solve::SolveParams;
use radiosity::timeline::LineParams;
use serde_json::json;

fn sample(name: &str, options: &LoadOptions) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    load(&std::fs::read(path).unwrap(), options).unwrap()
}

fn lines(n: u64) -> LineParams {
    LineParams { lines: n, seed: 3 }
}

/// The moving Cornell box at 4 frames per second.
fn sample_moving() -> Scene {
    sample(
        "cornell_moving.gltf",
        &LoadOptions {
            fps: 4.0,
            ..LoadOptions::default()
        },
    )
}

#[test]
fn cut_patches_hold_the_crossings_a_fresh_trace_finds() {
    // Static walls and a rigid box that moves: crossings of both are moved to the pieces.
    let scene = sample_moving();
    let params = lines(20_000);
    let mut bake = Bake::trace(scene, &params).unwrap();
    let triangles = bake.tracer().triangles();
    // Some triangles cut once, some into four, some left whole.
    let cuts: Vec<u32> = (0..triangles).map(|t| [0b10, 0, 0b1110][t % 3]).collect();
    let before = bake.scene.patches.len();
    let counted = radiosity::scene::refine::patches_after(&bake.scene, &cuts);
    // Every new patch names the patch it was cut from: same material, and the pieces' areas
    // add up to their patch's.
    let (refined, refinement) = radiosity::scene::refine::cut(&bake.scene, &cuts);
    let mut area = vec![0.0; before];
    for (piece, &parent) in refined.patches.iter().zip(refinement.parents()) {
        let parent = parent as usize;
        assert_eq!(piece.material, bake.scene.patches[parent].material);
        area[parent] += piece.area;
    }
    for (patch, area) in bake.scene.patches.iter().zip(&area) {
        assert!(
            (area / patch.area - 1.0).abs() < 1e-9,
            "{area} of {}",
            patch.area
        );
    }
    let added = bake
        .cut(&cuts, Lights::Sample, &Control::default())
        .unwrap();
    assert_eq!(bake.scene.patches.len(), before + added);
    assert_eq!(counted, before + added, "patches counted before the cut");
    assert!(added > triangles / 2, "{added} patches added");
    let fresh = Bake::trace(bake.scene.clone(), &params).unwrap();
    for frame in 0..bake.scene.frames.count {
        assert_eq!(
            bake.frame_tally(frame),
            fresh.frame_tally(frame),
            "frame {frame}"
        );
    }
    // Cut with the pieces lit as their patches were, then sampled once: the same bake.
    let mut inheriting = Bake::trace(sample_moving(), &params).unwrap();
    inheriting
        .cut(&cuts, Lights::Inherit, &Control::default())
        .unwrap();
    let solve = SolveParams::default();
    let last = bake.scene.frames.count - 1;
    let coarse = inheriting.solve_frame(last, &bake.scene.materials, &solve);
    inheriting.sample_lights(&Control::default()).unwrap();
    let (sampled, resampled) = (
        bake.solve_frame(last, &bake.scene.materials, &solve),
        inheriting.solve_frame(last, &bake.scene.materials, &solve),
    );
    assert_eq!(sampled.radiance, resampled.radiance);
    assert_ne!(coarse.radiance, sampled.radiance, "the light was inherited");
}

/// `scene` traced with `params` and made `auto` with the standard choice: the bake, the choice
/// and its rounds.
fn adapted(scene: Scene, params: &LineParams) -> (Bake, Adaptive, Vec<radiosity::adaptive::Round>) {
    let mut bake = Bake::trace(scene, params).unwrap();
    let auto = Adaptive::for_lines(params.lines, bake.scene.patches.len());
    let rounds = adapt(
        &mut bake,
        &auto,
        &SolveParams::default(),
        &Control::default(),
    )
    .unwrap();
    (bake, auto, rounds)
}

/// The area-weighted mean radiance of the lit, non-emitting patches of frame 0 over the
/// path-traced reference's, minus 1.
fn bias_against_the_path_tracer(bake: &Bake) -> f64 {
    let scene = &bake.scene;
    let solved = bake.solve_frame(0, &scene.materials, &SolveParams::default());
    let reference = path_traced(scene, bake.tracer(), 0, 64, [0.0; 3], 11);
    let (mut baked, mut traced) = (0.0, 0.0);
    for (i, p) in scene.patches.iter().enumerate() {
        if scene.materials[p.material as usize].is_emitter() {
            continue;
        }
        baked += p.area * solved.radiance[i][1];
        traced += p.area * reference[i].radiance[1];
    }
    baked / traced - 1.0
}

#[test]
fn auto_patches_keep_the_light_trapped_behind_a_panel_where_it_is() {
    // A double-sided emissive panel 1 cm below a ceiling of two large triangles: one radiance
    // per ceiling triangle spreads the light caught in the gap over the whole ceiling and
    // sends it into the room. Measured here: +16% with the source's triangles, −0.9% once cut
    // (288 patches of a budget of 1,500).
    let scene = sample("panel_room.gltf", &LoadOptions::default());
    let params = lines(300_000);
    let source = Bake::trace(scene.clone(), &params).unwrap();
    let before = bias_against_the_path_tracer(&source);
    assert!(before > 0.1, "the source's triangles are {before:+.3} off");
    let (bake, auto, rounds) = adapted(scene, &params);
    let patches = bake.scene.patches.len();
    assert!(
        patches <= auto.budget,
        "{patches} patches for a budget of {}",
        auto.budget
    );
    let after = bias_against_the_path_tracer(&bake);
    // The statistical error of this comparison is about 0.5% (both sides' noise over ~800
    // lit patches): 3% is over 4σ from the truth and far from the uncut +16%.
    assert!(after.abs() < 0.03, "{after:+.4} after {rounds:?}");
}

/// Each pair of consecutive static triangles (t = 2k, 2k + 1) of one material that does not
/// emit made one patch per side: old patch → new patch, for [`Bake::merge`]; and each new
/// patch's members.
fn pairs_merged(bake: &Bake) -> (Vec<u32>, Vec<Vec<u32>>) {
    let scene = &bake.scene;
    let faces = bake.tracer().faces();
    let statics = scene.statics.triangles.len();
    let mut into: Vec<Option<u32>> = vec![None; scene.patches.len()];
    let mut members: Vec<Vec<u32>> = Vec::new();
    let mut put = |group: &[u32]| {
        for &p in group {
            into[p as usize] = Some(members.len() as u32);
        }
        members.push(group.to_vec());
    };
    let emits = |p: u32| scene.materials[scene.patches[p as usize].material as usize].is_emitter();
    for t in (0..statics).step_by(2) {
        let (a, b) = (faces[t], faces.get(t + 1).filter(|_| t + 1 < statics));
        let alike = b.is_some_and(|b| {
            let (pa, pb) = (
                &scene.patches[a.front as usize],
                &scene.patches[b.front as usize],
            );
            pa.material == pb.material && !emits(a.front) && a.back.is_some() == b.back.is_some()
        });
        match b {
            Some(b) if alike => {
                put(&[a.front, b.front]);
                if let (Some(x), Some(y)) = (a.back, b.back) {
                    put(&[x, y]);
                }
            }
            _ => {
                for f in std::iter::once(a).chain(b.copied()) {
                    put(&[f.front]);
                    f.back.iter().for_each(|&x| put(&[x]));
                }
            }
        }
    }
    for f in &faces[statics..] {
        put(&[f.front]);
        f.back.iter().for_each(|&x| put(&[x]));
    }
    // `put` numbered the groups in order of their first triangle: the ids of `merge`.
    (into.into_iter().map(Option::unwrap).collect(), members)
}

/// Over the merged patches with a variance: the mean of z² for the merged patch's value
/// against its members' area mean (the two estimated apart, so their variances add), and the
/// largest |difference| where both sides are exact (no variance).
fn against_area_means(
    merged: &[(f64, f64)],
    apart: &[(f64, f64)],
    members: &[Vec<u32>],
    areas: &[f64],
) -> (f64, f64, usize) {
    let (mut z2, mut exact_gap, mut n) = (0.0, 0.0f64, 0);
    for (q, group) in members.iter().enumerate() {
        if group.len() < 2 {
            continue;
        }
        let total: f64 = group.iter().map(|&p| areas[p as usize]).sum();
        let (mut mean, mut variance) = (0.0, 0.0);
        for &p in group {
            let w = areas[p as usize] / total;
            mean += w * apart[p as usize].0;
            variance += w * w * apart[p as usize].1;
        }
        let (value, own) = merged[q];
        let v = variance + own;
        if v > 0.0 {
            z2 += (value - mean).powi(2) / v;
            n += 1;
        } else {
            exact_gap = exact_gap.max((value - mean).abs());
        }
    }
    (z2 / n.max(1) as f64, exact_gap, n)
}

#[test]
fn a_merged_patch_is_lit_as_the_area_mean_of_its_faces() {
    // Punctual lights (the level under lamps), area lights and the path-traced reference (the
    // Cornell box): each merged patch's estimate against its faces' estimated apart. A merged
    // patch that took one face's light for the whole (the last face's, say) is off by many σ
    // wherever light changes from face to face. Measured: mean z² 0.26 (punctual), 0.19 (area
    // lights: their variance is conservative), 0.94 (reference); with one face's light taken
    // for the whole, 27, 87 and 8.3.
    let green = |v: &[[f64; 3]]| v.iter().map(|x| x[1]).collect::<Vec<f64>>();
    let params = lines(20_000);
    for name in ["level_lamps.gltf", "cornell_box.gltf"] {
        let scene = sample(name, &LoadOptions::default());
        let apart = Bake::trace(scene.clone(), &params).unwrap();
        let (into, members) = pairs_merged(&apart);
        let mut merged = Bake::trace(scene, &params).unwrap();
        let removed = merged.merge(&into, &Control::default()).unwrap();
        assert_eq!(removed, apart.scene.patches.len() - members.len());
        assert!(removed > 10, "{removed} patches merged away in {name}");
        let areas: Vec<f64> = apart.scene.patches.iter().map(|p| p.area).collect();
        for (q, group) in members.iter().enumerate() {
            let sum: f64 = group.iter().map(|&p| areas[p as usize]).sum();
            assert!((merged.scene.patches[q].area / sum - 1.0).abs() < 1e-12);
        }
        let frame = 0;
        let mut checked = 0;
        if !merged.scene.lights.is_empty() {
            let light = |b: &Bake| {
                let power = b.light_power();
                let e = green(&b.direct().irradiance(frame, &power).unwrap());
                let v = green(&b.direct().variance(frame, &power).unwrap());
                e.into_iter().zip(v).collect::<Vec<_>>()
            };
            let (z2, gap, n) =
                against_area_means(&light(&merged), &light(&apart), &members, &areas);
            assert!(
                z2 < 1.5 && gap < 1e-6,
                "{name} punctual: z² {z2} over {n}, gap {gap}"
            );
            checked += n;
        }
        if !merged.area_lights().is_empty() {
            let light = |b: &Bake| {
                let (e, v) = b
                    .area_lights()
                    .irradiance(frame, &b.scene.materials)
                    .unwrap();
                green(&e).into_iter().zip(green(&v)).collect::<Vec<_>>()
            };
            let (z2, gap, n) =
                against_area_means(&light(&merged), &light(&apart), &members, &areas);
            assert!(
                z2 < 1.5 && gap < 1e-6,
                "{name} area lights: z² {z2} over {n}, gap {gap}"
            );
            checked += n;
            let traced = |b: &Bake, seed| {
                path_traced(&b.scene, b.tracer(), frame, 512, [0.0; 3], seed)
                    .iter()
                    .map(|e| (e.radiance[1], e.stderr[1].powi(2)))
                    .collect::<Vec<_>>()
            };
            let (z2, _, n) =
                against_area_means(&traced(&merged, 5), &traced(&apart, 6), &members, &areas);
            assert!(z2 < 1.5, "{name} reference: z² {z2} over {n}");
        }
        assert!(checked > 10, "{name}: {checked} merged patches checked");
    }
}

#[test]
fn auto_merges_coplanar_neighbours_of_one_material_and_keeps_every_crossing() {
    let scene = sample("cornell_box.gltf", &LoadOptions::default());
    let total: f64 = scene.patches.iter().map(|p| p.area).sum();
    let params = lines(100_000);
    let (bake, _, rounds) = adapted(scene, &params);
    let merging = rounds.last().unwrap();
    assert!(merging.removed > 0, "{rounds:?}");
    let scene = &bake.scene;
    let area: f64 = scene.patches.iter().map(|p| p.area).sum();
    assert!((area / total - 1.0).abs() < 1e-9);
    // Every merged patch: faces of one material, one object, one plane facing one way.
    let triangles = scene.triangles_at(0);
    let mut planes: Vec<Vec<(glam::DVec3, f64)>> = vec![Vec::new(); scene.patches.len()];
    for (corners, faces) in &triangles {
        let [a, b, c] = corners.map(|p| p.as_dvec3());
        let n = (b - a).cross(c - a).normalize();
        planes[faces.front as usize].push((n, n.dot(a)));
        if let Some(back) = faces.back {
            planes[back as usize].push((-n, -n.dot(a)));
        }
    }
    let merged = planes.iter().filter(|p| p.len() > 1).count();
    assert!(merged > 0);
    // A patch of several source triangles names the others (the walls' two triangles are
    // merged), in order, without its own.
    assert!(scene.patches.iter().any(|p| !p.merged.is_empty()));
    for (p, faces) in scene.patches.iter().zip(&planes) {
        assert!(p.merged.windows(2).all(|w| w[0] < w[1]));
        assert!(!p.merged.contains(&p.source.triangle));
        assert!(p.merged.len() < faces.len().max(1));
    }
    for faces in planes.iter().filter(|p| p.len() > 1) {
        for &(n, d) in &faces[1..] {
            assert!(n.dot(faces[0].0) > 1.0 - 1e-5 && (d - faces[0].1).abs() < 1e-5);
        }
    }
    // The same lines through the merged patches as a fresh trace of them.
    let fresh = Bake::trace(bake.scene.clone(), &params).unwrap();
    assert_eq!(bake.frame_tally(0), fresh.frame_tally(0));
    // Cut again, a merged patch stays one patch, and the count before the cut is exact.
    let cuts = vec![0b10u32; bake.tracer().triangles()];
    let counted = radiosity::scene::refine::patches_after(&bake.scene, &cuts);
    let (refined, refinement) = radiosity::scene::refine::cut(&bake.scene, &cuts);
    assert_eq!(counted, refined.patches.len());
    let mut pieces = vec![0; bake.scene.patches.len()];
    refinement
        .parents()
        .iter()
        .for_each(|&p| pieces[p as usize] += 1);
    for (p, faces) in planes.iter().enumerate() {
        if faces.len() > 1 {
            assert_eq!(pieces[p], 1, "merged patch {p} was cut");
        }
    }
}

/// Height of the lamp over the floor of [`lamp_over_a_floor`], metres.
const LAMP_HEIGHT: f64 = 1.0;
/// Where the lamp's foot is on that floor (x, z), metres: off the diagonal of its triangles.
const LAMP_FOOT: [f64; 2] = [4.0, -3.0];
/// Intensity of the lamp, candela.
const LAMP_INTENSITY: f64 = 20.0;
/// Reflectance of the floor.
const FLOOR_RHO: f64 = 0.5;

/// A lone floor (y = 0, facing +Y, 20 m square, two triangles) under a white point light
/// [`LAMP_HEIGHT`] above it, loaded with `patch_size`.
fn lamp_over_a_floor(patch_size: Option<f64>) -> Scene {
    let mut d = common::Doc::new();
    let rho = FLOOR_RHO;
    let material = d.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [rho, rho, rho, 1.0], "metallicFactor": 0.0}}),
    );
    let corners = [
        [-10.0, 0.0, -10.0],
        [10.0, 0.0, -10.0],
        [10.0, 0.0, 10.0],
        [-10.0, 0.0, 10.0],
    ];
    let mesh = d.mesh(&corners, Some(&[0, 3, 2, 0, 2, 1]), Some(material));
    let floor = d.node(json!({"mesh": mesh}));
    let lamp = d.node(json!({
        "translation": [LAMP_FOOT[0], LAMP_HEIGHT, LAMP_FOOT[1]],
        "extensions": {"KHR_lights_punctual": {"light": 0}},
    }));
    d.json["extensions"] = json!({"KHR_lights_punctual": {"lights": [
        {"type": "point", "intensity": LAMP_INTENSITY}
    ]}});
    d.json["extensionsUsed"] = json!(["KHR_lights_punctual"]);
    d.scene(&[floor, lamp]);
    let options = LoadOptions {
        patch_size,
        ..LoadOptions::default()
    };
    load(&d.gltf(), &options).unwrap()
}

/// The relative L² error over the floor of [`lamp_over_a_floor`] of `bake`'s patch-constant
/// answer at frame 0 against the exact radiance, `ρ·I·h / (π d³)` (a lone floor has nothing
/// to interreflect with): what a lightmap of it shows. By the midpoint rule on 4³
/// sub-triangles of each of its triangles.
fn floor_error_at_points(bake: &Bake) -> f64 {
    let scene = &bake.scene;
    let solution = bake.solve_frame(0, &scene.materials, &SolveParams::default());
    let exact = |p: DVec3| {
        let (dx, dz) = (p.x - LAMP_FOOT[0], p.z - LAMP_FOOT[1]);
        let d2 = dx * dx + dz * dz + LAMP_HEIGHT * LAMP_HEIGHT;
        FLOOR_RHO * LAMP_INTENSITY * LAMP_HEIGHT / (std::f64::consts::PI * d2 * d2.sqrt())
    };
    let (mut error, mut norm) = (0.0, 0.0);
    for (corners, faces) in scene.triangles_at(0) {
        let t = corners.map(|c| scene.normalisation.to_scene(c.as_dvec3()));
        let area = 0.5 * (t[1] - t[0]).cross(t[2] - t[0]).length();
        let value = solution.radiance[faces.front as usize][0];
        error += area * common::mean_over_triangle(t, 3, &|p| (value - exact(p)).powi(2));
        norm += area * common::mean_over_triangle(t, 3, &|p| exact(p).powi(2));
    }
    (error / norm).sqrt()
}

#[test]
fn auto_cuts_where_a_lamps_light_falls_and_beats_uniform_patches_at_points() {
    // The lines carry nothing here (everything a floor segment meets is the black sky): only
    // the direct light sampled on the scored pieces shows auto where the light varies.
    let params = lines(100_000);
    let (bake, _, rounds) = adapted(lamp_over_a_floor(None), &params);
    let patches = bake.scene.patches.len();
    let auto = floor_error_at_points(&bake);
    // Uniform patches of 1 m, at least four times as many (measured: 256 patches at 36% at
    // points, 1,024 at 23%, 2,048 at 17.2%, 4,096 at 12.5%; auto 407 at 15.6%).
    let size = 1.0;
    let uniform = Bake::trace(lamp_over_a_floor(Some(size)), &params).unwrap();
    let flat = floor_error_at_points(&uniform);
    eprintln!(
        "auto: {patches} patches, {:.1}% at points; uniform {size:.2} m: {} patches, {:.1}%; {rounds:?}",
        100.0 * auto,
        uniform.scene.patches.len(),
        100.0 * flat
    );
    assert!(uniform.scene.patches.len() >= 4 * patches);
    assert!(
        patches > 20,
        "{patches} patches: auto did not cut where the lamp lights"
    );
    assert!(
        auto < flat,
        "auto {:.1}% at points against uniform patches' {:.1}%",
        100.0 * auto,
        100.0 * flat
    );
}

/// Cutting within a budget at once (the split's rounds) cuts what counting the patches first
/// and then cutting does: the whole order where it fits, its longest prefix that fits where
/// it does not.
#[test]
fn a_cut_within_budget_is_the_budgets_prefix_cut() {
    use radiosity::scene::refine::{cut, cut_within_budget, within_budget};
    let scene = sample_moving();
    let triangles: u32 = (scene.statics.triangles.len()
        + scene
            .objects
            .iter()
            .map(|o| o.mesh.triangles.len())
            .sum::<usize>()) as u32;
    let order: Vec<(u32, u32)> = (0..triangles).rev().step_by(2).map(|t| (t, 1)).collect();
    let whole = cut(&scene, &within_budget(&scene, &order, usize::MAX)).0;
    let patches = scene.patches.len();
    assert!(whole.patches.len() > patches + 10);
    for budget in [
        usize::MAX,
        whole.patches.len(),
        (patches + whole.patches.len()) / 2,
        patches,
    ] {
        let expected = within_budget(&scene, &order, budget);
        let (cuts, (next, refinement)) = cut_within_budget(&scene, &order, budget);
        assert_eq!(cuts, expected, "budget {budget}");
        let (fitted, fitted_refinement) = cut(&scene, &expected);
        assert_eq!(next.patches.len(), fitted.patches.len(), "budget {budget}");
        assert!(next.patches.len() <= budget);
        assert_eq!(refinement.parents(), fitted_refinement.parents());
    }
}
