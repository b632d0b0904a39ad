//! Punctual lights (KHR_lights_punctual) against closed forms: point, spot and directional
//! irradiance, shadows, moving lights, relighting by intensity.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use common::Doc;
use glam::DVec3;
use radiosity::bake::Bake;
use radiosity::direct::reference::path_traced;
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::Scene;
use radiosity::solve::SolveParams;
use radiosity::timeline::LineParams;
use serde_json::{Value, json};

/// Half the side of the floor, metres.
const HALF: f32 = 10.0;
/// Reflectance of the floor.
const RHO: f64 = 0.5;

/// A square floor (y = 0, facing +Y) of side 2·HALF, subdivided into patches of `patch` m, the
/// lights `lights` at the nodes `light_nodes`, and optional extra meshes.
fn floor_scene(lights: Value, light_nodes: &[Value], extra: &[(Vec<[f32; 3]>, Vec<u32>)]) -> Doc {
    let mut d = Doc::new();
    let material = d.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [RHO, RHO, RHO, 1.0], "metallicFactor": 0.0}}),
    );
    let floor = [
        [-HALF, 0.0, -HALF],
        [HALF, 0.0, -HALF],
        [HALF, 0.0, HALF],
        [-HALF, 0.0, HALF],
    ];
    let mesh = d.mesh(&floor, Some(&[0, 3, 2, 0, 2, 1]), Some(material));
    let mut roots = vec![d.node(json!({"mesh": mesh}))];
    for (positions, indices) in extra {
        let mesh = d.mesh(positions, Some(indices), Some(material));
        roots.push(d.node(json!({"mesh": mesh})));
    }
    for node in light_nodes {
        roots.push(d.node(node.clone()));
    }
    d.json["extensions"] = json!({"KHR_lights_punctual": {"lights": lights}});
    d.json["extensionsUsed"] = json!(["KHR_lights_punctual"]);
    d.scene(&roots);
    d
}

fn light_node(light: usize, translation: [f64; 3], rotation: [f64; 4]) -> Value {
    json!({
        "translation": translation,
        "rotation": rotation,
        "extensions": {"KHR_lights_punctual": {"light": light}},
    })
}

/// −Z turned to −Y: a quarter turn about +X, clockwise seen from +X.
const DOWN: [f64; 4] = [
    -std::f64::consts::FRAC_1_SQRT_2,
    0.0,
    0.0,
    std::f64::consts::FRAC_1_SQRT_2,
];

fn load_with(doc: &Doc, patch: f64, fps: f64) -> Scene {
    let options = LoadOptions {
        patch_size: Some(patch),
        fps,
        ..LoadOptions::default()
    };
    load(&doc.gltf(), &options).unwrap()
}

fn bake(scene: Scene) -> Bake {
    Bake::trace(
        scene,
        &LineParams {
            lines: 20_000,
            seed: 3,
        },
    )
    .unwrap()
}

/// Centroid of each patch's triangle at frame 0, scene units, for the front patches of the
/// floor (node 0).
fn floor_centroids(scene: &Scene) -> Vec<(usize, DVec3)> {
    floor_triangles(scene)
        .into_iter()
        .map(|(p, [a, b, c])| (p, (a + b + c) / 3.0))
        .collect()
}

/// Each front patch of the floor (node 0) with its triangle at frame 0, scene units.
fn floor_triangles(scene: &Scene) -> Vec<(usize, [DVec3; 3])> {
    let triangles = scene.triangles_at(0);
    triangles
        .iter()
        .filter(|(_, faces)| scene.patches[faces.front as usize].source.node == 0)
        .map(|(c, faces)| {
            let corners = c.map(|p| scene.normalisation.to_scene(p.as_dvec3()));
            (faces.front as usize, corners)
        })
        .collect()
}

/// The mean of `f` over triangle `t`: the midpoint rule on its 4^4 sub-triangles.
fn mean_over(t: [DVec3; 3], f: &dyn Fn(DVec3) -> f64) -> f64 {
    common::mean_over_triangle(t, 4, f)
}

#[test]
fn a_point_light_above_a_floor_gives_i_cos_over_d_squared() {
    let intensity = 50.0;
    let height = 3.0;
    let doc = floor_scene(
        json!([{"type": "point", "intensity": intensity, "color": [1.0, 0.5, 0.25]}]),
        &[light_node(0, [0.0, height, 0.0], [0.0, 0.0, 0.0, 1.0])],
        &[],
    );
    let scene = load_with(&doc, 0.5, 1.0);
    assert_eq!(scene.lights.len(), 1);
    let bake = bake(scene);
    let power = bake.light_power();
    assert_eq!(power, vec![[intensity, intensity * 0.5, intensity * 0.25]]);
    let direct = bake.direct().irradiance(0, &power).unwrap();
    let variance = bake.direct().variance(0, &power).unwrap();
    let solution = bake.solve_frame(0, &bake.scene.materials, &SolveParams::default());
    let mut checked = 0;
    let (mut z2, mut covered) = (0.0, 0);
    for (patch, t) in floor_triangles(&bake.scene) {
        // The patch's mean of I·cos/d² (the bake samples it at stratified random points).
        let expected = mean_over(t, &|p| {
            let d2 = p.x * p.x + p.z * p.z + height * height;
            intensity * height / d2.sqrt() / d2
        });
        let (e, sigma) = (direct[patch][0], variance[patch][0].sqrt());
        assert!(
            (e - expected).abs() < 0.05 * expected,
            "patch at {:?}: {e} against {expected} (σ {})",
            t[0],
            variance[patch][0].sqrt()
        );
        // Never a zero error bar where the sampling has an error: I·cos/d² varies over every
        // patch.
        assert!(sigma > 0.0 && sigma < 0.05 * expected, "σ {sigma}");
        let z = (e - expected) / sigma;
        z2 += z * z;
        covered += usize::from(z.abs() <= 2.0);
        // The bake's error bar includes it.
        if let Some(reported) = solution.stderr[patch] {
            assert!(reported[0] >= RHO * sigma / std::f64::consts::PI * (1.0 - 1e-9));
        }
        assert!((direct[patch][1] - 0.5 * e).abs() < 1e-12 * e);
        // A lone floor has nothing to interreflect with: its radiance is exactly ρ·E/π.
        let l = solution.radiance[patch][0];
        assert!((l - RHO * e / std::f64::consts::PI).abs() < 1e-9 * l, "{l}");
        checked += 1;
    }
    assert!(checked > 1000, "{checked}");
    // Honest (or, from collapsed strata, wide) error bars: a mean z² of about 1 or less, and
    // 95% within 2σ.
    let z2 = z2 / f64::from(checked);
    eprintln!("mean z² {z2}, {covered} of {checked} within 2σ");
    assert!(z2 < 1.5, "mean z² {z2}");
    assert!(
        covered as f64 >= 0.9 * f64::from(checked),
        "{covered} of {checked} within 2σ"
    );
}

#[test]
fn a_spot_light_is_dark_outside_its_outer_cone() {
    let (inner, outer) = (0.3f64, 0.5f64);
    let (intensity, height) = (80.0, 4.0);
    let doc = floor_scene(
        json!([{"type": "spot", "intensity": intensity, "spot": {"innerConeAngle": inner, "outerConeAngle": outer}}]),
        &[light_node(0, [0.0, height, 0.0], DOWN)],
        &[],
    );
    let bake = bake(load_with(&doc, 0.5, 1.0));
    let direct = bake.direct().irradiance(0, &bake.light_power()).unwrap();
    let (mut dark, mut full) = (0, 0);
    for (patch, centre) in floor_centroids(&bake.scene) {
        let r = centre.x.hypot(centre.z);
        let angle = r.atan2(height);
        let e = direct[patch][0];
        // Half a patch diagonal of margin around the cone's edges.
        let margin = (0.36f64).atan2(height);
        if angle > outer + margin {
            assert_eq!(e, 0.0, "outside the cone at {centre}");
            dark += 1;
        } else if angle < inner - margin {
            let d2 = r * r + height * height;
            let expected = intensity * (height / d2.sqrt()) / d2;
            assert!(
                (e - expected).abs() < 0.01 * expected,
                "{e} against {expected}"
            );
            full += 1;
        }
    }
    assert!(dark > 1000 && full > 20, "{dark} dark, {full} fully lit");
}

/// The floor under a sun of `lux` at `theta` from the vertical (−Z turned down, then tilted
/// about +Z, so the light travels along w = (sin θ, −cos θ, 0)), with a 2 m plate 1 m above
/// the floor: its shadow is the plate moved by tan θ along +x.
fn sun_over_a_plate(lux: f64, theta: f64) -> Doc {
    let tilt = glam::DQuat::from_rotation_z(theta) * glam::DQuat::from_array(DOWN);
    let plate = vec![
        [-1.0, 1.0, -1.0],
        [1.0, 1.0, -1.0],
        [1.0, 1.0, 1.0],
        [-1.0, 1.0, 1.0],
    ];
    floor_scene(
        json!([{"type": "directional", "intensity": lux}]),
        &[light_node(0, [0.0, 50.0, 0.0], tilt.to_array())],
        &[(plate, vec![0, 3, 2, 0, 2, 1])],
    )
}

#[test]
fn a_directional_light_gives_its_intensity_times_cos_theta_and_shadows() {
    let intensity = 1000.0;
    let theta = 30f64.to_radians();
    let bake = bake(load_with(&sun_over_a_plate(intensity, theta), 0.5, 1.0));
    let direct = bake.direct().irradiance(0, &bake.light_power()).unwrap();
    let expected = intensity * theta.cos();
    let shift = theta.tan();
    let (mut lit, mut dark, mut edge) = (0, 0, 0);
    for (patch, centre) in floor_centroids(&bake.scene) {
        let e = direct[patch][0];
        // Distance outside the shadow's square (negative inside), against half a patch
        // diagonal of margin.
        let outside = (centre.x - shift).abs().max(centre.z.abs()) - 1.0;
        if outside > 0.4 {
            // Unshadowed patches are exact: the lines only measure the shadow.
            assert!(
                (e - expected).abs() < 1e-6 * expected,
                "{e} against {expected}"
            );
            lit += 1;
        } else if outside < -0.4 {
            assert_eq!(e, 0.0, "lit in the shadow at {centre}");
            dark += 1;
        } else {
            assert!((0.0..=expected * (1.0 + 1e-6)).contains(&e));
            edge += 1;
        }
    }
    assert!(
        lit > 1000 && dark >= 4 && edge > 10,
        "{lit} lit, {dark} dark, {edge} on the edge"
    );
}

#[test]
fn an_occluder_casts_a_shadow() {
    // A 2 m square plate 1 m above the floor, under a point light at 3 m: the plate's shadow
    // on the floor is the plate scaled by 3 / (3 − 1) = 1.5 about the light's foot.
    let (p, h) = (1.0f32, 1.0f32);
    let plate = vec![[-p, h, -p], [p, h, -p], [p, h, p], [-p, h, p]];
    let doc = floor_scene(
        json!([{"type": "point", "intensity": 10.0}]),
        &[light_node(0, [0.0, 3.0, 0.0], [0.0, 0.0, 0.0, 1.0])],
        // Facing up (towards the light), so the floor side is its back: one-sided, it still
        // blocks.
        &[(plate, vec![0, 3, 2, 0, 2, 1])],
    );
    let bake = bake(load_with(&doc, 0.25, 1.0));
    let direct = bake.direct().irradiance(0, &bake.light_power()).unwrap();
    let (mut shadowed, mut lit) = (0, 0);
    for (patch, centre) in floor_centroids(&bake.scene) {
        let inside = centre.x.abs().max(centre.z.abs());
        if inside < 1.5 - 0.2 {
            assert_eq!(direct[patch][0], 0.0, "lit in the shadow at {centre}");
            shadowed += 1;
        } else if inside > 1.5 + 0.2 {
            assert!(
                direct[patch][0] > 0.0,
                "dark outside the shadow at {centre}"
            );
            lit += 1;
        }
    }
    assert!(shadowed > 50 && lit > 1000);
}

#[test]
fn a_moving_light_changes_its_frames_and_lights_relight_without_tracing() {
    let mut doc = floor_scene(
        json!([{"type": "point", "intensity": 20.0}]),
        &[light_node(0, [0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 1.0])],
        &[],
    );
    // The light slides 4 m along +X over one second, then stays.
    doc.animation(
        "slide",
        &[(
            1,
            "translation",
            &[0.0, 1.0, 2.0],
            &[0.0, 2.0, 0.0, 4.0, 2.0, 0.0, 4.0, 2.0, 0.0],
            "LINEAR",
        )],
    );
    let scene = load_with(&doc, 0.5, 2.0);
    assert_eq!(scene.frames.count, 5);
    assert!(scene.lights[0].moves() && scene.objects.is_empty());
    let bake = bake(scene);
    // Nothing moves but the light: one set of tallies; the frames differ by their direct
    // light only, and the last three (the light at rest at x = 4) share it.
    let representatives = bake.representatives();
    assert_eq!(representatives, vec![0, 1, 2, 2, 2]);
    let power = bake.light_power();
    for f in 0..5 {
        let x = (4.0 * f as f64 / 2.0).min(4.0);
        let direct = bake.direct().irradiance(f, &power).unwrap();
        let variance = bake.direct().variance(f, &power).unwrap();
        let (mut z2, mut covered, mut count) = (0.0, 0, 0);
        for (patch, t) in floor_triangles(&bake.scene) {
            let expected = mean_over(t, &|p| {
                let d2 = (p.x - x).powi(2) + p.z.powi(2) + 4.0;
                20.0 * 2.0 / d2.sqrt() / d2
            });
            let (e, sigma) = (direct[patch][0], variance[patch][0].sqrt());
            assert!(
                (e - expected).abs() <= 0.05 * expected && sigma > 0.0,
                "frame {f}: {e} against {expected} (σ {sigma})"
            );
            let z = (e - expected) / sigma;
            z2 += z * z;
            covered += usize::from(z.abs() <= 2.0);
            count += 1;
        }
        let z2 = z2 / f64::from(count);
        assert!(z2 < 1.5, "frame {f}: mean z² {z2}");
        assert!(
            covered as f64 >= 0.9 * f64::from(count),
            "frame {f}: {covered} of {count}"
        );
    }
    let all = bake.solve_all(&bake.scene.materials, &SolveParams::default());
    assert!(std::sync::Arc::ptr_eq(&all[2], &all[4]));
    assert!(all[0].radiance != all[1].radiance);
    // Twice the intensity, twice the light, no tracing. (Against frame 2 solved the same way,
    // from the emission: `solve_all` starts it from frame 1, which agrees only to within the
    // solve's stopping criterion, a twentieth of σ.)
    let doubled: Vec<[f64; 3]> = power.iter().map(|p| p.map(|c| 2.0 * c)).collect();
    let params = SolveParams::default();
    let twice = bake.solve_frame_lit(2, &bake.scene.materials, &doubled, &params);
    let once = bake.solve_frame_lit(2, &bake.scene.materials, &power, &params);
    for (a, b) in twice.radiance.iter().zip(&once.radiance) {
        assert!((a[0] - 2.0 * b[0]).abs() <= 1e-9 * a[0].max(1e-300));
    }
}

#[test]
fn bad_lights_are_refused_with_their_name() {
    for (light, why) in [
        (json!({"type": "spot", "intensity": 1.0}), "spot"),
        (
            json!({"type": "spot", "spot": {"innerConeAngle": 0.6, "outerConeAngle": 0.5}}),
            "innerConeAngle",
        ),
        (json!({"type": "point", "intensity": -1.0}), "intensity"),
        (json!({"type": "point", "range": 0.0}), "range"),
        (
            json!({"type": "point", "color": [1.0, -1.0, 0.0]}),
            "colour",
        ),
    ] {
        let doc = floor_scene(
            json!([light]),
            &[light_node(0, [0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0])],
            &[],
        );
        let error = load(&doc.gltf(), &LoadOptions::default())
            .err()
            .unwrap_or_else(|| panic!("accepted {why}"))
            .to_string();
        // gltf-json's own validation names it lights[0].
        let named = error.contains("light 0") || error.contains("lights[0]");
        assert!(named && error.contains(why), "{error}");
    }
}

#[test]
fn the_path_traced_reference_sees_point_and_directional_lights_as_the_closed_forms_do() {
    // The point light above the floor: each patch's reference is ρ/π times its mean of
    // I·cos/d², from random points (its only noise); nothing interreflects.
    let intensity = 50.0;
    let height = 3.0;
    let doc = floor_scene(
        json!([{"type": "point", "intensity": intensity}]),
        &[light_node(0, [0.0, height, 0.0], [0.0, 0.0, 0.0, 1.0])],
        &[],
    );
    let baked = bake(load_with(&doc, 1.0, 1.0));
    let reference = path_traced(&baked.scene, baked.tracer(), 0, 16, [0.0; 3], 5);
    let (mut z2, mut covered, mut checked) = (0.0, 0, 0);
    for (patch, t) in floor_triangles(&baked.scene) {
        let expected = RHO / std::f64::consts::PI
            * mean_over(t, &|p| {
                let d2 = p.x * p.x + p.z * p.z + height * height;
                intensity * height / d2.sqrt() / d2
            });
        let (l, sigma) = (reference[patch].radiance[0], reference[patch].stderr[0]);
        assert!(
            sigma > 0.0 && sigma < 0.1 * expected,
            "σ {sigma} of {expected}"
        );
        let z = (l - expected) / sigma;
        z2 += z * z;
        covered += usize::from(z.abs() <= 2.0);
        checked += 1;
    }
    // 8 point pairs per patch: z follows a Student t with 7 degrees of freedom (variance 1.4).
    let z2 = z2 / f64::from(checked);
    assert!(checked >= 800, "{checked}");
    assert!((0.9..1.9).contains(&z2), "mean z² {z2}");
    assert!(
        covered as f64 >= 0.85 * f64::from(checked),
        "{covered} of {checked} within 2σ"
    );

    // The sun 30° from the vertical over a plate 1 m above the floor: exact where it is lit,
    // black in the plate's shadow.
    let lux = 1000.0;
    let theta = 30f64.to_radians();
    let baked = bake(load_with(&sun_over_a_plate(lux, theta), 0.5, 1.0));
    let reference = path_traced(&baked.scene, baked.tracer(), 0, 8, [0.0; 3], 6);
    let expected = RHO / std::f64::consts::PI * lux * theta.cos();
    let (mut lit, mut dark) = (0, 0);
    for (patch, centre) in floor_centroids(&baked.scene) {
        let l = reference[patch].radiance[0];
        let outside = (centre.x - theta.tan()).abs().max(centre.z.abs()) - 1.0;
        if outside > 0.4 {
            // Exact to the f32 geometry.
            assert!(
                (l - expected).abs() < 1e-6 * expected,
                "{l} against {expected}"
            );
            lit += 1;
        } else if outside < -0.4 {
            assert_eq!(l, 0.0, "lit in the shadow at {centre}");
            dark += 1;
        }
    }
    assert!(lit > 1000 && dark >= 4, "{lit} lit, {dark} dark");
}
