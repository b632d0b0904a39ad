//! The glTF loader against hand-built files: what is read, what is static or moving, and what
//! is refused.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use common::{Doc, QUAD, QUAD_INDICES};
use glam::DVec3;
use radiosity::loader::{LoadError, LoadOptions, load};
use radiosity::scene::{Motion, Scene, Side};
use serde_json::json;

fn opts() -> LoadOptions {
    LoadOptions::default()
}

fn load_ok(doc: &Doc) -> Scene {
    let gltf = load(&doc.gltf(), &opts()).unwrap();
    let glb = load(&doc.glb(), &opts()).unwrap();
    assert_eq!(
        gltf.patches.len(),
        glb.patches.len(),
        ".gltf and .glb disagree"
    );
    gltf
}

fn err(bytes: &[u8], options: &LoadOptions) -> String {
    match load(bytes, options) {
        Ok(_) => panic!("accepted"),
        Err(e) => e.to_string(),
    }
}

/// A quad node, a second quad child of an animated node, and a third quad under a node whose
/// "animation" keeps the same value at every key.
fn three_quads() -> Doc {
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let still = d.node(json!({"mesh": mesh, "translation": [5.0, 0.0, 0.0]}));
    let child = d.node(json!({"mesh": mesh, "translation": [0.0, 0.0, 1.0]}));
    let mover = d.node(json!({"children": [child]}));
    let fake = d.node(json!({"mesh": mesh, "translation": [-5.0, 0.0, 0.0]}));
    d.scene(&[still, mover, fake]);
    d.animation(
        "walk",
        &[
            (
                mover,
                "translation",
                &[0.0, 1.0, 2.0],
                &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 3.0, 0.0, 0.0],
                "LINEAR",
            ),
            (
                fake,
                "translation",
                &[0.0, 2.0],
                &[-5.0, 0.0, 0.0, -5.0, 0.0, 0.0],
                "LINEAR",
            ),
            (
                fake,
                "rotation",
                &[0.0, 0.7, 2.0],
                &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                "LINEAR",
            ),
        ],
    );
    d
}

#[test]
fn static_and_moving_are_told_apart_by_evaluating_the_frames() {
    let scene = load_ok(&three_quads());
    // Only the child of the animated node moves; the constant channels move nothing.
    assert_eq!(scene.objects.len(), 1);
    assert_eq!(scene.objects[0].node, 1);
    assert!(scene.objects[0].is_rigid());
    assert_eq!(scene.statics.triangles.len(), 4);
    assert_eq!(scene.frames.count, 49); // 2 s at 24 fps, both ends included
    let moving = scene.patches.iter().filter(|p| p.object.is_some()).count();
    assert_eq!(moving, 2);
}

#[test]
fn rigid_poses_follow_the_interpolated_animation() {
    let scene = load_ok(&three_quads());
    let n = scene.normalisation;
    let object = &scene.objects[0];
    for (frame, expected_x) in [(0, 0.0), (12, 0.5), (24, 1.0), (36, 2.0), (48, 3.0)] {
        let posed = object.positions_at(frame);
        let lowest = posed
            .iter()
            .map(|p| n.to_scene(p.as_dvec3()))
            .fold(DVec3::INFINITY, DVec3::min);
        assert!(
            lowest.abs_diff_eq(DVec3::new(expected_x, 0.0, 1.0), 1e-5),
            "frame {frame}: {lowest}"
        );
    }
}

#[test]
fn a_channel_without_a_target_node_is_ignored_with_a_warning() {
    // The specification allows a channel whose target has no node (an extension animates
    // something else): the rest of the animation plays, and the warning names the channel.
    let mut doc = three_quads();
    doc.json["animations"][0]["channels"][1]["target"]
        .as_object_mut()
        .unwrap()
        .remove("node");
    let scene = load_ok(&doc);
    assert!(
        scene
            .warnings
            .iter()
            .any(|w| w.contains("animations[0].channels[1]") && w.contains("no target node")),
        "{:?}",
        scene.warnings
    );
    let reference = load_ok(&three_quads());
    assert_eq!(scene.frames.count, reference.frames.count);
    assert_eq!(
        scene.objects[0].positions_at(24),
        reference.objects[0].positions_at(24)
    );
}

#[test]
fn frames_follow_fps_and_overrides_and_animation_choice() {
    let doc = three_quads();
    let bytes = doc.gltf();
    let frames = |o: LoadOptions| load(&bytes, &o).unwrap().frames;
    let f = frames(LoadOptions {
        fps: 10.0,
        ..opts()
    });
    assert_eq!((f.start, f.count), (0.0, 21));
    let f = frames(LoadOptions {
        start: Some(0.5),
        end: Some(1.0),
        ..opts()
    });
    assert_eq!((f.start, f.count), (0.5, 13));
    assert_eq!(f.time(12), 1.0);
    assert_eq!(
        frames(LoadOptions {
            animation: Some("walk".into()),
            ..opts()
        })
        .count,
        49
    );
    assert_eq!(
        frames(LoadOptions {
            animation: Some("0".into()),
            ..opts()
        })
        .count,
        49
    );
    let e = err(
        &bytes,
        &LoadOptions {
            animation: Some("run".into()),
            ..opts()
        },
    );
    assert!(e.contains("\"run\"") && e.contains("walk"), "{e}");
    let e = err(&bytes, &LoadOptions { fps: 0.0, ..opts() });
    assert!(e.contains("fps"), "{e}");
    let e = err(&bytes, &LoadOptions { fps: 1e9, ..opts() });
    assert!(e.contains("limit"), "{e}");
    let e = err(
        &bytes,
        &LoadOptions {
            start: Some(2.0),
            end: Some(1.0),
            ..opts()
        },
    );
    assert!(e.contains("before"), "{e}");
}

#[test]
fn a_scene_without_animation_has_one_frame() {
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, None, None);
    let n = d.node(json!({"mesh": mesh}));
    d.scene(&[n]);
    let scene = load_ok(&d);
    assert_eq!(scene.frames.count, 1);
    assert!(scene.objects.is_empty());
    // Without indices: vertices in order, 4 vertices = 1 triangle and 1 leftover index.
    assert_eq!(scene.patches.len(), 1);
    assert!(
        scene.warnings.iter().any(|w| w.contains("trailing")),
        "{:?}",
        scene.warnings
    );
}

#[test]
fn materials_give_reflectance_emission_and_sides() {
    let mut d = Doc::new();
    let lamp = d.push(
        "materials",
        json!({"name": "lamp", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.25, 1.0, 1.0], "metallicFactor": 0.5},
               "emissiveFactor": [1.0, 0.5, 0.0], "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 4.0}},
               "doubleSided": true}),
    );
    d.json["extensionsUsed"] = json!(["KHR_materials_emissive_strength"]);
    let lit = d.mesh(&QUAD, Some(&QUAD_INDICES), Some(lamp));
    let plain = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let a = d.node(json!({"mesh": lit}));
    let b = d.node(json!({"mesh": plain, "translation": [0.0, 0.0, 2.0]}));
    d.scene(&[a, b]);
    let scene = load_ok(&d);
    let m = &scene.materials[0];
    assert_eq!(m.name.as_deref(), Some("lamp"));
    assert_eq!(m.reflectance, [0.25, 0.125, 0.5]);
    assert_eq!(m.emission, [4.0, 2.0, 0.0]);
    // The default material: white, not metallic, one-sided; its reflectance 1 is lowered to the
    // cap, with a warning.
    assert_eq!(scene.materials[1].reflectance, [0.999; 3]);
    assert!(
        scene
            .warnings
            .iter()
            .any(|w| w.contains("glTF default material")),
        "{:?}",
        scene.warnings
    );
    assert_eq!(scene.materials[1].emission, [0.0; 3]);
    // Two double-sided triangles (front and back) and two one-sided ones.
    assert_eq!(scene.patches.len(), 6);
    let sides: Vec<Side> = scene.patches.iter().map(|p| p.side).collect();
    assert_eq!(
        sides,
        [
            Side::Front,
            Side::Back,
            Side::Front,
            Side::Back,
            Side::Front,
            Side::Front
        ]
    );
    assert_eq!(scene.summary().emitters, 4);
    assert_eq!(scene.statics.faces[0].back, Some(1));
    assert_eq!(scene.statics.faces[2].back, None);
}

#[test]
fn provenance_and_areas_map_back_to_the_file() {
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let n = d.node(json!({"mesh": mesh, "scale": [2.0, 3.0, 1.0]}));
    d.scene(&[n]);
    let scene = load_ok(&d);
    for (k, p) in scene.patches.iter().enumerate() {
        assert_eq!(
            (
                p.source.node,
                p.source.mesh,
                p.source.primitive,
                p.source.triangle
            ),
            (0, 0, 0, k as u32)
        );
        assert!((p.area - 3.0).abs() < 1e-12, "{}", p.area);
    }
}

#[test]
fn subdivision_keeps_area_and_provenance() {
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let n = d.node(json!({"mesh": mesh, "scale": [10.0, 3.0, 1.0]}));
    d.scene(&[n]);
    let options = LoadOptions {
        patch_size: Some(0.5),
        ..opts()
    };
    let scene = load(&d.gltf(), &options).unwrap();
    assert!(scene.patches.len() > 100, "{}", scene.patches.len());
    for source in 0..2 {
        let area: f64 = scene
            .patches
            .iter()
            .filter(|p| p.source.triangle == source)
            .map(|p| p.area)
            .sum();
        assert!((area - 15.0).abs() < 1e-9, "triangle {source}: {area}");
    }
    // Every edge of the result is at most 0.5 in scene units.
    let n = scene.normalisation;
    for t in &scene.statics.triangles {
        for k in 0..3 {
            let a = scene.statics.positions[t[k] as usize].as_dvec3() * n.radius;
            let b = scene.statics.positions[t[(k + 1) % 3] as usize].as_dvec3() * n.radius;
            assert!((a - b).length() <= 0.5 + 1e-5);
        }
    }
    let e = err(
        &d.gltf(),
        &LoadOptions {
            patch_size: Some(1e-4),
            max_patches: 10_000,
            ..opts()
        },
    );
    assert!(e.contains("patch_size"), "{e}");
}

#[test]
fn strips_fans_matrices_and_index_sizes() {
    let mut d = Doc::new();
    let pos: Vec<f32> = QUAD.iter().flatten().copied().collect();
    let p = d.floats(&pos, "VEC3");
    let strip = d.indices(&[0, 1, 3, 2], 5121);
    let fan = d.indices(&[0, 1, 2, 3], 5125);
    let mesh = d.push(
        "meshes",
        json!({"primitives": [
            {"attributes": {"POSITION": p}, "indices": strip, "mode": 5},
            {"attributes": {"POSITION": p}, "indices": fan, "mode": 6},
            {"attributes": {"POSITION": p}, "mode": 1}
        ]}),
    );
    // A matrix moving the mesh by (0, 0, 7).
    let m = d.node(json!({"mesh": mesh, "matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,7,1]}));
    d.scene(&[m]);
    let scene = load_ok(&d);
    assert_eq!(scene.patches.len(), 4);
    assert!(
        scene.warnings.iter().any(|w| w.contains("Lines")),
        "{:?}",
        scene.warnings
    );
    let prims: Vec<(u32, u32)> = scene
        .patches
        .iter()
        .map(|p| (p.source.primitive, p.source.triangle))
        .collect();
    assert_eq!(prims, [(0, 0), (0, 1), (1, 0), (1, 1)]);
    assert!((scene.normalisation.center.z - 7.0).abs() < 1e-12);
    // Every triangle faces +Z: strips and fans keep the winding.
    for t in &scene.statics.triangles {
        let [a, b, c] = t.map(|i| scene.statics.positions[i as usize]);
        assert!((b - a).cross(c - a).z > 0.0);
    }
}

#[test]
fn the_default_scene_is_chosen() {
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let a = d.node(json!({"mesh": mesh}));
    let b = d.node(json!({"mesh": mesh, "translation": [0, 0, 3]}));
    let c = d.node(json!({"mesh": mesh, "translation": [0, 0, 6]}));
    d.push("scenes", json!({"nodes": [a]}));
    d.push("scenes", json!({"nodes": [b, c]}));
    d.json["scene"] = json!(1);
    assert_eq!(load_ok(&d).patches.len(), 4);
    d.json.as_object_mut().unwrap().remove("scene");
    assert_eq!(load_ok(&d).patches.len(), 2);
}

#[test]
fn zero_area_triangles_are_dropped_and_counted() {
    let mut d = Doc::new();
    let pts = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [2.0, 0.0, 0.0],
    ];
    let mesh = d.mesh(&pts, Some(&[0, 1, 2, 0, 1, 3, 2, 2, 1]), None);
    let n = d.node(json!({"mesh": mesh}));
    d.scene(&[n]);
    let scene = load_ok(&d);
    assert_eq!(scene.patches.len(), 1);
    assert_eq!(scene.summary().triangles, 1);
    assert!(
        scene
            .warnings
            .iter()
            .any(|w| w.contains("dropped 2 zero-area")),
        "{:?}",
        scene.warnings
    );
    // The bounds ignore vertices only dropped triangles use.
    assert!((scene.normalisation.center.x - 0.5).abs() < 1e-12);
}

#[test]
fn a_scene_of_any_size_and_place_normalises_to_the_same_geometry() {
    let make = |scale: f64, offset: f64| {
        let mut d = Doc::new();
        let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
        let n = d.node(json!({"mesh": mesh, "scale": [scale, scale, scale], "translation": [offset, 0.0, 0.0]}));
        let m = d.node(json!({"mesh": mesh, "scale": [scale, scale, scale], "translation": [offset, 0.0, scale]}));
        d.scene(&[n, m]);
        load(&d.glb(), &opts()).unwrap()
    };
    let reference = make(1.0, 0.0);
    for (scale, offset) in [(1e-4, 0.0), (1e5, 0.0), (1.0, 1e6), (1e-3, -1e6)] {
        let scene = make(scale, offset);
        // The scale goes through f32 in the file: relative 1e-7.
        assert!(
            (scene.normalisation.radius / reference.normalisation.radius / scale - 1.0).abs()
                < 1e-6
        );
        for (a, b) in scene
            .statics
            .positions
            .iter()
            .zip(&reference.statics.positions)
        {
            assert!(
                a.abs_diff_eq(*b, 1e-6),
                "scale {scale} offset {offset}: {a} vs {b}"
            );
        }
        let area: f64 = scene.patches.iter().map(|p| p.area).sum();
        assert!((area / (scale * scale) - 2.0).abs() < 1e-6);
    }
}

#[test]
fn malformed_files_are_refused_naming_the_object() {
    // Index out of range.
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&[0, 1, 9]), None);
    let n = d.node(json!({"mesh": mesh}));
    d.scene(&[n]);
    let e = err(&d.gltf(), &opts());
    assert!(
        e.contains("mesh 0 primitive 0") && e.contains("index 9"),
        "{e}"
    );

    // An accessor reaching past its buffer view.
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let n = d.node(json!({"mesh": mesh}));
    d.scene(&[n]);
    d.json["accessors"][0]["count"] = json!(5);
    let e = err(&d.gltf(), &opts());
    assert!(e.contains("accessor 0") && e.contains("overrun"), "{e}");
    d.json["accessors"][0]["count"] = json!(4);
    d.json["bufferViews"][0]["byteLength"] = json!(4096);
    let e = err(&d.gltf(), &opts());
    assert!(e.contains("bufferView 0") && e.contains("outside"), "{e}");

    // A cycle in the node graph.
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let a = d.node(json!({"mesh": mesh, "children": [1]}));
    d.node(json!({"children": [2]}));
    d.node(json!({"children": [1]}));
    d.scene(&[a]);
    let e = err(&d.gltf(), &opts());
    assert!(e.contains("node 1") || e.contains("node 2"), "{e}");

    // Non-finite positions.
    let mut d = Doc::new();
    let mesh = d.mesh(
        &[[0.0, 0.0, 0.0], [f32::NAN, 0.0, 0.0], [0.0, 1.0, 0.0]],
        None,
        None,
    );
    let n = d.node(json!({"mesh": mesh}));
    d.scene(&[n]);
    let e = err(&d.gltf(), &opts());
    assert!(e.contains("accessor 0") && e.contains("finite"), "{e}");

    // A sampler whose output does not match its input.
    let mut d = three_quads();
    let bad = d.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0], "VEC3");
    d.json["animations"][0]["samplers"][0]["output"] = json!(bad);
    let e = err(&d.gltf(), &opts());
    assert!(
        e.contains("animation 0 sampler 0") && e.contains("3 input keys"),
        "{e}"
    );

    // A dangling reference, caught by validation.
    let mut d = three_quads();
    d.json["scenes"][0]["nodes"] = json!([42]);
    let e = err(&d.gltf(), &opts());
    assert!(e.contains("scenes[0].nodes[0]"), "{e}");

    // Nothing with an area.
    let mut d = Doc::new();
    let n = d.node(json!({}));
    d.scene(&[n]);
    assert!(matches!(load(&d.gltf(), &opts()), Err(LoadError::Empty)));
}

#[test]
fn external_uris_are_refused_for_buffers_and_images() {
    let mut d = three_quads();
    let good = d.gltf();
    let mut j: serde_json::Value = serde_json::from_slice(&good).unwrap();
    j["buffers"][0]["uri"] = json!("../../etc/passwd");
    let e = err(&serde_json::to_vec(&j).unwrap(), &opts());
    assert!(e.contains("buffer 0") && e.contains("external URI"), "{e}");

    let image = d.push("images", json!({"uri": "file:///etc/passwd"}));
    let texture = d.push("textures", json!({"source": image}));
    d.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": texture}}}),
    );
    d.json["meshes"][0]["primitives"][0]["material"] = json!(0);
    let e = err(&d.gltf(), &opts());
    assert!(e.contains("image 0") && e.contains("external URI"), "{e}");
}

#[test]
fn morph_targets_and_skins_from_the_khronos_samples_deform() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/gltf-samples");
    let morph = std::fs::read(dir.join("SimpleMorph.gltf")).unwrap();
    let scene = load(&morph, &opts()).unwrap();
    assert_eq!(scene.objects.len(), 1);
    let Motion::Deforming(_) = &scene.objects[0].motion else {
        panic!("not deforming")
    };
    assert_eq!(scene.frames.count, 97); // weights animated over 0–4 s
    // The triangle (0,0,0) (1,0,0) (0.5,0.5,0); target 0 moves vertex 2 by (−1, 1, 0), target 1
    // by (1, 1, 0); the weights are (0,0) (0,1) (1,1) (1,0) (0,0) at t = 0..4 s, LINEAR.
    let n = scene.normalisation;
    let vertex2 = |f: usize| n.to_scene(scene.objects[0].positions_at(f)[2].as_dvec3());
    for (frame, expected) in [
        (0, DVec3::new(0.5, 0.5, 0.0)),
        (24, DVec3::new(1.5, 1.5, 0.0)),
        (36, DVec3::new(1.0, 2.0, 0.0)), // weights (0.5, 1)
        (72, DVec3::new(-0.5, 1.5, 0.0)),
    ] {
        assert!(
            vertex2(frame).abs_diff_eq(expected, 1e-5),
            "frame {frame}: {}",
            vertex2(frame)
        );
    }

    let skin = std::fs::read(dir.join("SimpleSkin.gltf")).unwrap();
    let scene = load(&skin, &opts()).unwrap();
    assert_eq!(scene.objects.len(), 1);
    assert!(!scene.objects[0].is_rigid());
    assert_eq!(scene.frames.count, 133);
    let (a, b) = (
        scene.objects[0].positions_at(0),
        scene.objects[0].positions_at(24),
    );
    // At t = 1 s the second joint is turned 90°: the root vertices stay, the top ones move.
    assert!(a[0].abs_diff_eq(b[0], 1e-6));
    assert!(a.iter().zip(&b).any(|(p, q)| p.distance(*q) > 0.05));
}

#[test]
fn the_first_camera_is_read_with_its_animation_in_normalised_space() {
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let quad = d.node(json!({"mesh": mesh, "scale": [10.0, 10.0, 1.0]}));
    d.push(
        "cameras",
        json!({"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.5, "aspectRatio": 1.5}}),
    );
    // The camera sits under a parent that moves along +X from 0 to 4 over one second.
    let camera = d.node(json!({"camera": 0, "translation": [5.0, 5.0, 10.0]}));
    let rig = d.node(json!({"children": [camera]}));
    d.scene(&[quad, rig]);
    d.animation(
        "dolly",
        &[(
            rig,
            "translation",
            &[0.0, 1.0],
            &[0.0, 0.0, 0.0, 4.0, 0.0, 0.0],
            "LINEAR",
        )],
    );
    let options = LoadOptions { fps: 4.0, ..opts() };
    let scene = load(&d.gltf(), &options).unwrap();
    let camera = scene.camera.as_ref().expect("a camera");
    assert_eq!(camera.poses.len(), scene.frames.count);
    assert_eq!(camera.aspect, Some(1.5));
    let n = scene.normalisation;
    let radius = n.radius;
    for f in 0..scene.frames.count {
        let expected = DVec3::new(5.0 + 4.0 * f as f64 / 4.0, 5.0, 10.0);
        let at = n.to_scene(camera.pose(f).translation);
        assert!(at.distance(expected) < 1e-9, "frame {f}: {at}");
    }
    match camera.projection {
        radiosity::scene::Projection::Perspective { yfov, znear, zfar } => {
            assert!((yfov - 0.8).abs() < 1e-6);
            assert!((znear - f64::from(0.5f32) / radius).abs() < 1e-12);
            assert_eq!(zfar, None);
        }
        other => panic!("{other:?}"),
    }

    // A camera whose projection is unusable is ignored with a warning; the scene still loads.
    d.json["cameras"][0] =
        json!({"type": "perspective", "perspective": {"yfov": 0.0, "znear": 0.5}});
    let scene = load(&d.gltf(), &options).unwrap();
    assert!(scene.camera.is_none());
    assert!(scene.warnings.iter().any(|w| w.contains("camera 0")));
    // The type says orthographic but only a perspective object is given: the perspective is
    // used (gltf-rs would panic on this file).
    d.json["cameras"][0] =
        json!({"type": "orthographic", "perspective": {"yfov": 0.5, "znear": 0.5}});
    assert!(load(&d.gltf(), &options).unwrap().camera.is_some());
}

#[test]
fn custom_vertex_attributes_are_accepted() {
    // Application-specific attributes start with an underscore (glTF 2.0 §3.7.2.1); a baked
    // glTF carries _RADIANCE, exporters add _BATCHID and the like.
    let mut d = Doc::new();
    let flat: Vec<f32> = QUAD.iter().flatten().copied().collect();
    let positions = d.floats(&flat, "VEC3");
    let custom = d.floats(&[1.0, 2.0, 3.0, 4.0], "SCALAR");
    let indices = d.indices(&QUAD_INDICES, 5123);
    let mesh = d.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": positions, "_BATCHID": custom}, "indices": indices}]}),
    );
    let node = d.node(json!({"mesh": mesh}));
    d.scene(&[node]);
    assert_eq!(load_ok(&d).patches.len(), 2);
}

#[test]
fn a_mirrored_node_keeps_its_faces_facing_the_same_way() {
    // glTF §3.7.2.1: a negative determinant turns the front face to the clockwise side. The quad
    // faces +Z; mirrored in x it still faces +Z (static) and so does its moving copy.
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let still = d.node(json!({"mesh": mesh, "scale": [-1.0, 1.0, 1.0]}));
    let moving =
        d.node(json!({"mesh": mesh, "scale": [-1.0, 1.0, 1.0], "translation": [3.0, 0.0, 0.0]}));
    d.scene(&[still, moving]);
    d.animation(
        "slide",
        &[(
            moving,
            "translation",
            &[0.0, 1.0],
            &[3.0, 0.0, 0.0, 4.0, 0.0, 0.0],
            "LINEAR",
        )],
    );
    let scene = load_ok(&d);
    assert_eq!(scene.objects.len(), 1);
    for (corners, _) in scene.triangles_at(0) {
        let [a, b, c] = corners;
        let normal = (b - a).cross(c - a);
        assert!(normal.z > 0.0, "a mirrored quad faces {normal}");
    }
}

#[test]
fn the_summary_names_what_can_be_relit_and_played() {
    let sample = (radiosity::samples::all().into_iter())
        .find(|s| s.file_name == "level_lamps.gltf")
        .unwrap();
    let names = |named: &[radiosity::scene::Named]| -> Vec<String> {
        named.iter().map(ToString::to_string).collect()
    };
    let scene = load(sample.gltf.as_bytes(), &opts()).unwrap();
    let summary = scene.summary();
    let materials = names(&summary.materials);
    assert_eq!(materials.len(), scene.materials.len());
    assert_eq!(materials[4], "4 \"lamp_housing\"");
    assert_eq!(
        names(&summary.light_names),
        [
            "0 \"warm_lamp\" (point)",
            "1 \"spot\" (spot)",
            "2 \"swinging_lamp\" (point, moving)"
        ]
    );
    assert_eq!(
        names(&summary.animations),
        ["0 \"door_swing\" (played)", "1 \"lamp_swing\" (played)"]
    );
    assert_eq!(summary.camera, None);
    // One animation chosen, by index: the other is listed, not played.
    let one = LoadOptions {
        animation: Some("1".into()),
        ..opts()
    };
    let summary = load(sample.gltf.as_bytes(), &one).unwrap().summary();
    assert_eq!(
        names(&summary.animations),
        ["0 \"door_swing\"", "1 \"lamp_swing\" (played)"]
    );
    let text = summary.to_string();
    assert!(
        text.contains("materials       0 \"floor\", 1 \"wall\""),
        "{text}"
    );
}

#[test]
fn quantized_positions_load_as_their_floats_do() {
    // The unit quad as gltfpack writes it (KHR_mesh_quantization): u16 positions, not
    // normalised, 6-byte elements padded to a stride of 8, the node's scale and translation
    // taking them back to metres.
    let (scale, offset) = (1.0 / 1000.0, [-0.5f32, 0.0, -0.5]);
    let quantized: Vec<[u16; 3]> = (QUAD.iter())
        .map(|p| std::array::from_fn(|k| ((p[k] - offset[k]) / scale).round() as u16))
        .collect();
    let mut d = Doc::new();
    while !d.bin.len().is_multiple_of(4) {
        d.bin.push(0);
    }
    let start = d.bin.len();
    for q in &quantized {
        q.iter()
            .for_each(|c| d.bin.extend_from_slice(&c.to_le_bytes()));
        d.bin.extend_from_slice(&[0, 0]);
    }
    let view = d.push(
        "bufferViews",
        json!({"buffer": 0, "byteOffset": start, "byteLength": d.bin.len() - start, "byteStride": 8}),
    );
    let (min, max) = (
        (0..3)
            .map(|k| quantized.iter().map(|q| q[k]).min().unwrap())
            .collect::<Vec<_>>(),
        (0..3)
            .map(|k| quantized.iter().map(|q| q[k]).max().unwrap())
            .collect::<Vec<_>>(),
    );
    let position = d.push(
        "accessors",
        json!({"bufferView": view, "componentType": 5123, "count": 4, "type": "VEC3",
               "min": min, "max": max}),
    );
    let indices = d.indices(&QUAD_INDICES, 5123);
    let mesh = d.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": position}, "indices": indices}]}),
    );
    let node = d.node(json!({"mesh": mesh, "scale": [scale, scale, scale], "translation": offset}));
    d.scene(&[node]);
    d.json["extensionsUsed"] = json!(["KHR_mesh_quantization"]);
    d.json["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
    let scene = load_ok(&d);
    // Against the float quad.
    let mut f = Doc::new();
    let mesh = f.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let node = f.node(json!({"mesh": mesh}));
    f.scene(&[node]);
    let floats = load_ok(&f);
    assert_eq!(scene.patches.len(), floats.patches.len());
    for (q, p) in scene.patches.iter().zip(&floats.patches) {
        assert!(
            (q.area - p.area).abs() < 1e-6 * p.area,
            "{} {}",
            q.area,
            p.area
        );
    }
    let centre = |s: &Scene| s.normalisation.center;
    assert!((centre(&scene) - centre(&floats)).length() < 1e-6);
}

#[test]
fn the_previews_camera_is_the_one_asked_for() {
    let mut d = three_quads();
    let perspective = json!({"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.1}});
    let camera = d.push("cameras", perspective);
    let front = d.node(json!({"name": "Front", "camera": camera, "translation": [0.0, 0.5, 5.0]}));
    let side = d.node(json!({"name": "Side", "camera": camera, "translation": [5.0, 0.5, 0.0]}));
    let roots: Vec<usize> = d.json["scenes"][0]["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_u64().unwrap() as usize)
        .chain([front, side])
        .collect();
    d.json["scenes"][0]["nodes"] = json!(roots);
    let with = |camera: Option<&str>| LoadOptions {
        camera: camera.map(str::to_owned),
        ..opts()
    };
    let name = |options: LoadOptions| {
        let scene = load(&d.gltf(), &options).unwrap();
        scene.camera.map(|c| c.name.unwrap())
    };
    assert_eq!(
        name(with(None)),
        Some("Front".into()),
        "the first by default"
    );
    assert_eq!(name(with(Some("Side"))), Some("Side".into()));
    assert_eq!(name(with(Some(&side.to_string()))), Some("Side".into()));
    assert_eq!(name(with(Some("auto"))), None);
    let message = err(&d.gltf(), &with(Some("Top")));
    assert!(
        message.contains("no camera node named or numbered \"Top\"")
            && message.contains(&format!("cameras (or auto): {front} (\"Front\")")),
        "{message}"
    );
}

/// The unit quad as `gltfpack -c` writes it: its views compressed by meshoptimizer
/// (`EXT_meshopt_compression`) into buffer 0, decoded into a fallback buffer 1 that has no
/// bytes of its own. Positions as u16 (stride 8) or, with `exponential`, as floats through the
/// EXPONENTIAL filter (stride 12); indices as TRIANGLES.
fn meshopt_quad(exponential: bool, mode: &str) -> Vec<u8> {
    let (vertices, stride, component, scale) = if exponential {
        let floats: Vec<[f32; 3]> = QUAD.to_vec();
        let filtered = meshopt::encode_filter_exp(&floats, 24, meshopt::EncodeExpMode::Separate);
        (
            meshopt::encode_vertex_buffer(&filtered).unwrap(),
            12,
            5126,
            1.0,
        )
    } else {
        let shorts: Vec<[u16; 4]> = (QUAD.iter())
            .map(|p| [0, 1, 2, 3].map(|k| if k < 3 { (p[k] * 1000.0) as u16 } else { 0 }))
            .collect();
        (
            meshopt::encode_vertex_buffer(&shorts).unwrap(),
            8,
            5123,
            0.001,
        )
    };
    let indices = meshopt::encode_index_buffer(&QUAD_INDICES, 4).unwrap();
    let mut d = Doc::new();
    let mut place = |bytes: &[u8]| {
        while !d.bin.len().is_multiple_of(4) {
            d.bin.push(0);
        }
        let at = d.bin.len();
        d.bin.extend_from_slice(bytes);
        at
    };
    let (v_at, i_at) = (place(&vertices), place(&indices));
    let positions = 4 * stride;
    let ext = |at: usize, length: usize, stride: usize, count: usize, mode: &str| {
        let mut e = json!({"buffer": 0, "byteOffset": at, "byteLength": length,
            "byteStride": stride, "count": count, "mode": mode});
        if exponential && mode == "ATTRIBUTES" {
            e["filter"] = json!("EXPONENTIAL");
        }
        json!({ "EXT_meshopt_compression": e })
    };
    let v_view = d.push(
        "bufferViews",
        json!({"buffer": 1, "byteLength": positions, "byteStride": stride,
            "extensions": ext(v_at, vertices.len(), stride, 4, mode)}),
    );
    let i_view = d.push(
        "bufferViews",
        json!({"buffer": 1, "byteOffset": positions, "byteLength": 12,
            "extensions": ext(i_at, indices.len(), 2, 6, "TRIANGLES")}),
    );
    let max = if exponential {
        json!([1.0, 1.0, 0.0])
    } else {
        json!([1000, 1000, 0])
    };
    let position = d.push(
        "accessors",
        json!({"bufferView": v_view, "componentType": component, "count": 4, "type": "VEC3",
            "min": [0, 0, 0], "max": max}),
    );
    let index = d.push(
        "accessors",
        json!({"bufferView": i_view, "componentType": 5123, "count": 6, "type": "SCALAR"}),
    );
    let mesh = d.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": position}, "indices": index}]}),
    );
    let node = d.node(json!({"mesh": mesh, "scale": [scale, scale, scale]}));
    d.scene(&[node]);
    let used = ["EXT_meshopt_compression", "KHR_mesh_quantization"];
    d.json["extensionsUsed"] = json!(used);
    d.json["extensionsRequired"] = json!(used);
    let data = format!(
        "data:application/octet-stream;base64,{}",
        base64::Engine::encode(&base64::engine::general_purpose::STANDARD, &d.bin)
    );
    d.json["buffers"] = json!([
        {"byteLength": d.bin.len(), "uri": data},
        {"byteLength": positions + 12,
         "extensions": {"EXT_meshopt_compression": {"fallback": true}}},
    ]);
    serde_json::to_vec(&d.json).unwrap()
}

#[test]
fn meshopt_compressed_views_load_as_their_plain_bytes_do() {
    let mut f = Doc::new();
    let mesh = f.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let node = f.node(json!({"mesh": mesh}));
    f.scene(&[node]);
    let plain = load_ok(&f);
    for exponential in [false, true] {
        let scene = load(&meshopt_quad(exponential, "ATTRIBUTES"), &opts()).unwrap();
        assert_eq!(scene.patches.len(), plain.patches.len());
        for (q, p) in scene.patches.iter().zip(&plain.patches) {
            assert!(
                (q.area - p.area).abs() < 1e-6 * p.area,
                "{} {}",
                q.area,
                p.area
            );
        }
        assert!((scene.normalisation.center - plain.normalisation.center).length() < 1e-6);
    }
    // A hostile file cannot make the loader allocate what it does not hold: a fallback buffer
    // larger than its views, or a view decoding to far more than its compressed bytes.
    let mut json: serde_json::Value =
        serde_json::from_slice(&meshopt_quad(false, "ATTRIBUTES")).unwrap();
    json["buffers"][1]["byteLength"] = json!(1u64 << 50);
    let message = err(&serde_json::to_vec(&json).unwrap(), &opts());
    assert!(message.contains("beyond the views"), "{message}");
    let mut json: serde_json::Value =
        serde_json::from_slice(&meshopt_quad(false, "ATTRIBUTES")).unwrap();
    let huge = 1u64 << 40;
    json["bufferViews"][0]["byteLength"] = json!(huge * 8);
    json["bufferViews"][0]["extensions"]["EXT_meshopt_compression"]["count"] = json!(huge);
    let message = err(&serde_json::to_vec(&json).unwrap(), &opts());
    assert!(message.contains("at most 128 times"), "{message}");
    // A view that is not as the extension defines it: refused, naming it.
    let message = err(&meshopt_quad(false, "STRIPS"), &opts());
    assert!(
        message.contains("bufferViews[0].extensions.EXT_meshopt_compression")
            && message.contains("STRIPS"),
        "{message}"
    );
}

/// A material that leaves `metallicFactor` out is fully metallic by glTF's rule (Khronos'
/// `Box`, `BoxTextured`: COLLADA2GLTF leaves it out), so its diffuse reflectance is 0 and it
/// bakes black: the loader says so, naming the material (issue 48). One with metallicFactor 0
/// says nothing.
#[test]
fn a_material_that_leaves_metallic_out_is_named_in_a_warning() {
    let mut d = three_quads();
    d.push(
        "materials",
        json!({"name": "Red", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.0, 0.0, 1.0]}}),
    );
    d.json["meshes"][0]["primitives"][0]["material"] = json!(0);
    let scene = load_ok(&d);
    assert_eq!(scene.materials[0].reflectance, [0.0; 3]);
    let metallic = |w: &&String| w.contains("material 0 (Red)") && w.contains("metallicFactor");
    assert_eq!(
        scene.warnings.iter().filter(metallic).count(),
        1,
        "{:?}",
        scene.warnings
    );
    d.json["materials"][0]["pbrMetallicRoughness"]["metallicFactor"] = json!(0.0);
    let scene = load_ok(&d);
    assert!((scene.materials[0].reflectance[0] - 0.8).abs() < 1e-6);
    assert!(
        !scene.warnings.iter().any(|w| w.contains("metallic")),
        "{:?}",
        scene.warnings
    );
}

/// Every triangle of a scene knows where it lies on the source triangle it was made from,
/// through subdivision and cuts: its corners, rebuilt from its origin and its source
/// triangle's corners, are its own (the moving Cornell box: static walls and a rigid block);
/// and the patch table's parts say what each patch is, merged patches included: shares that
/// sum to 1, source triangles among the patch's own.
#[test]
fn every_triangle_knows_where_it_lies_on_its_source_triangle() {
    use radiosity::scene::{TriangleMesh, refine};
    use std::collections::HashMap;
    let load = |patch_size: Option<f64>| {
        let sample = (radiosity::samples::all().into_iter())
            .find(|s| s.file_name == "cornell_moving.gltf")
            .unwrap();
        let options = LoadOptions {
            fps: 2.0,
            patch_size,
            ..LoadOptions::default()
        };
        load(sample.gltf.as_bytes(), &options).unwrap()
    };
    // The traced meshes: the static one, then each object's (its index + 1).
    let meshes = |s: &Scene| -> Vec<TriangleMesh> {
        std::iter::once(s.statics.clone())
            .chain(s.objects.iter().map(|o| o.mesh.clone()))
            .collect()
    };
    let whole = load(None);
    // Each source triangle's corners, by mesh and provenance.
    let mut sources = HashMap::new();
    for (m, mesh) in meshes(&whole).iter().enumerate() {
        for (t, f) in mesh.triangles.iter().zip(&mesh.faces) {
            let s = whole.patches[f.front as usize].source;
            let corners = t.map(|v| mesh.positions[v as usize].as_dvec3());
            sources.insert((m, s.node, s.mesh, s.primitive, s.triangle), corners);
        }
    }
    let fine = load(Some(0.15));
    assert!(fine.patches.len() > 4 * whole.patches.len());
    let triangles: usize = meshes(&fine).iter().map(|m| m.triangles.len()).sum();
    let cuts: Vec<u32> = (0..triangles)
        .map(|t| if t % 3 == 0 { 0b1110 } else { 0 })
        .collect();
    let (cut, _) = refine::cut(&fine, &cuts);
    for (name, scene) in [("subdivided", &fine), ("cut", &cut)] {
        let mut checked = 0;
        for (m, mesh) in meshes(scene).iter().enumerate() {
            assert_eq!(mesh.origins.len(), mesh.triangles.len(), "{name}: mesh {m}");
            for ((t, f), o) in mesh.triangles.iter().zip(&mesh.faces).zip(&mesh.origins) {
                let s = scene.patches[f.front as usize].source;
                let [a, b, c] = sources[&(m, s.node, s.mesh, s.primitive, o.triangle)];
                for (k, &[u, v]) in o.corners.iter().enumerate() {
                    let (u, v) = (f64::from(u), f64::from(v));
                    let rebuilt = a * (1.0 - u - v) + b * u + c * v;
                    let own = mesh.positions[t[k] as usize].as_dvec3();
                    assert!(
                        (rebuilt - own).length() < 1e-5,
                        "{name}: mesh {m}, corner {own} rebuilt at {rebuilt} from {o:?}"
                    );
                }
                checked += 1;
            }
        }
        assert_eq!(
            checked,
            meshes(scene)
                .iter()
                .map(|m| m.triangles.len())
                .sum::<usize>()
        );
    }
    // Merged: each static patch with the next one of its primitive and side.
    let mut into = Vec::with_capacity(cut.patches.len());
    let mut next = 0u32;
    for (p, patch) in cut.patches.iter().enumerate() {
        let same = |q: &radiosity::scene::Patch| {
            (q.source.node, q.source.primitive, q.side, q.object)
                == (patch.source.node, patch.source.primitive, patch.side, None)
        };
        if p % 2 == 1 && same(&cut.patches[p - 1]) && patch.object.is_none() {
            into.push(next - 1);
        } else {
            into.push(next);
            next += 1;
        }
    }
    let merged = refine::merge(&cut, &into);
    let table = radiosity::output::patch_table(&merged);
    let (mut with_parts, mut of_two) = (0, 0);
    for entry in table["patches"].as_array().unwrap() {
        let Some(parts) = entry["parts"].as_array() else {
            continue;
        };
        with_parts += 1;
        let share: f64 = parts.iter().map(|p| p["share"].as_f64().unwrap()).sum();
        assert!((share - 1.0).abs() < 1e-9, "{entry}");
        let mut own = vec![entry["triangle"].as_u64().unwrap()];
        own.extend(
            entry["merged"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|t| t.as_u64().unwrap()),
        );
        let triangles: std::collections::HashSet<u64> = parts
            .iter()
            .map(|p| p["triangle"].as_u64().unwrap())
            .collect();
        assert!(triangles.iter().all(|t| own.contains(t)), "{entry}");
        of_two += usize::from(triangles.len() == 2);
        for part in parts {
            for corner in part["corners"].as_array().unwrap() {
                let sum: f64 = corner
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|w| w.as_f64().unwrap())
                    .sum();
                assert!((sum - 1.0).abs() < 1e-6, "{entry}");
            }
        }
    }
    assert!(
        with_parts > merged.patches.len() / 2 && of_two > 0,
        "{with_parts} {of_two}"
    );
    // The source's triangles whole need no parts.
    let table = radiosity::output::patch_table(&whole);
    assert!(
        table["patches"]
            .as_array()
            .unwrap()
            .iter()
            .all(|e| e.get("parts").is_none())
    );
}
