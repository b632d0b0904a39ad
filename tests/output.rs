//! The baked outputs: per-vertex radiance, the baked glTF, the previews.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use common::Doc;
use glam::DVec3;
use radiosity::loader::{LoadOptions, load};
use radiosity::output::{Shading, ToneMap, frame_geometry, frame_glb, preview_image};
use radiosity::scene::Scene;
use serde_json::json;
use std::f32::consts::FRAC_PI_2;

/// A floor (facing +Y) and a wall (facing +Z) meeting at a right angle along a shared edge, in
/// one primitive with shared vertex indices: triangles 0 and 1 are the floor, 2 and 3 the wall.
fn corner(double_sided: bool) -> Scene {
    let positions = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 0.0, 1.0],
        [0.0, 0.0, 1.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ];
    let indices = [0, 3, 2, 0, 2, 1, 0, 1, 4, 0, 4, 5];
    let mut d = Doc::new();
    let material = d.push("materials", json!({"doubleSided": double_sided}));
    let mesh = d.mesh(&positions, Some(&indices), Some(material));
    let node = d.node(json!({"mesh": mesh, "translation": [1e6, 0.0, 0.0]}));
    d.scene(&[node]);
    load(&d.gltf(), &LoadOptions::default()).unwrap()
}

/// Radiance per patch: floor triangles 1 and 3, wall triangles 10 and 20 (back faces 100×).
fn radiance(scene: &Scene) -> Vec<[f64; 3]> {
    scene
        .patches
        .iter()
        .map(|p| {
            let base = [1.0, 3.0, 10.0, 20.0][p.source.triangle as usize];
            let side = if p.side == radiosity::scene::Side::Back {
                100.0
            } else {
                1.0
            };
            [base * side, 2.0 * base * side, 0.5 * base * side]
        })
        .collect()
}

/// The output vertex at `corner` (scene units) whose normal is `normal`: the faces' corners
/// it stands for, as (triangle, back).
fn vertex(
    scene: &Scene,
    mesh: &radiosity::output::NodeMesh,
    corner: DVec3,
    normal: DVec3,
) -> Vec<(u32, bool)> {
    let found: Vec<usize> = (0..mesh.positions.len())
        .filter(|&v| {
            scene
                .normalisation
                .to_scene(mesh.positions[v])
                .distance(corner)
                < 1e-6
                && mesh.normals[v].as_dvec3().distance(normal) < 1e-6
        })
        .collect();
    assert_eq!(found.len(), 1, "vertices at {corner} facing {normal}");
    let mut corners: Vec<(u32, bool)> = (mesh.corners_of(found[0]).iter())
        .map(|c| (c.triangle, c.back))
        .collect();
    corners.sort_unstable();
    corners
}

#[test]
fn vertices_are_split_at_creases_and_stand_for_their_own_faces() {
    let scene = corner(false);
    let meshes = frame_geometry(&scene, 0);
    assert_eq!(meshes.len(), 1);
    let mesh = &meshes[0];
    // 6 source vertices; the two on the crease are split: 8.
    assert_eq!(mesh.positions.len(), 8);
    assert_eq!(mesh.triangles.len(), 4);
    let at = |x: f64, y: f64, z: f64| DVec3::new(1e6 + x, y, z);
    let (up, out) = (DVec3::Y, DVec3::Z);
    // Floor: vertices 0 and 2 are shared by both floor triangles; the others by one.
    let floor = |t: &[u32]| t.iter().map(|&t| (t, false)).collect::<Vec<_>>();
    assert_eq!(vertex(&scene, mesh, at(0.0, 0.0, 0.0), up), floor(&[0, 1]));
    assert_eq!(vertex(&scene, mesh, at(1.0, 0.0, 1.0), up), floor(&[0, 1]));
    assert_eq!(vertex(&scene, mesh, at(0.0, 0.0, 1.0), up), floor(&[0]));
    assert_eq!(vertex(&scene, mesh, at(1.0, 0.0, 0.0), up), floor(&[1]));
    // Wall: the crease vertices have their own copies, standing for the wall's faces only
    // (their light is evaluated on the wall, never averaged with the floor's).
    assert_eq!(vertex(&scene, mesh, at(0.0, 0.0, 0.0), out), floor(&[2, 3]));
    assert_eq!(vertex(&scene, mesh, at(1.0, 0.0, 0.0), out), floor(&[2]));
    assert_eq!(vertex(&scene, mesh, at(1.0, 1.0, 0.0), out), floor(&[2, 3]));
    assert_eq!(vertex(&scene, mesh, at(0.0, 1.0, 0.0), out), floor(&[3]));
    // Every triangle faces its patch's side: its winding agrees with its vertices' normals.
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize]);
        let n = (b - a).cross(c - a).normalize();
        assert!(n.dot(mesh.normals[t[0] as usize].as_dvec3()) > 0.99);
    }
    // Each corner's angle is the face's at that vertex: a right angle at the floor's corner
    // (0, 0, 1), half of one at (0, 0, 0) on each of the two triangles there.
    let v = (0..mesh.positions.len())
        .find(|&v| mesh.corners_of(v).len() == 2 && mesh.normals[v].as_dvec3() == up)
        .unwrap();
    let angles: f64 = mesh.corners_of(v).iter().map(|c| c.angle).sum();
    assert!(
        (angles - std::f64::consts::FRAC_PI_2).abs() < 1e-9,
        "{angles}"
    );
}

#[test]
fn back_faces_get_their_own_triangles_and_vertices() {
    let scene = corner(true);
    let meshes = frame_geometry(&scene, 0);
    let mesh = &meshes[0];
    assert_eq!(mesh.triangles.len(), 8);
    assert_eq!(mesh.positions.len(), 16);
    let at = |x: f64, y: f64, z: f64| DVec3::new(1e6 + x, y, z);
    let origin = at(0.0, 0.0, 0.0);
    assert_eq!(
        vertex(&scene, mesh, origin, -DVec3::Y),
        vec![(0, true), (1, true)]
    );
    assert_eq!(
        vertex(&scene, mesh, origin, DVec3::Y),
        vec![(0, false), (1, false)]
    );
    assert_eq!(
        vertex(&scene, mesh, at(0.0, 1.0, 0.0), -DVec3::Z),
        vec![(3, true)]
    );
}

#[test]
fn the_baked_glb_loads_back_with_colours_per_vertex() {
    let mut scene = corner(true);
    let mut meshes = frame_geometry(&scene, 0);
    // Values of any kind, one per vertex: the file carries what it is given.
    let mesh = &mut meshes[0];
    for (v, (l, e)) in (mesh.radiance.iter_mut()).zip(&mut mesh.stderr).enumerate() {
        *l = [v as f64, 2.0 * v as f64, 0.5];
        *e = [0.1 * v as f64, 0.2, 0.3];
    }
    let tone = ToneMap { exposure: 0.01 };
    let unnamed = frame_glb(&scene, 0, &meshes, &tone).unwrap();
    let unnamed = gltf::Gltf::from_slice(&unnamed).unwrap();
    assert_eq!(unnamed.nodes().next().unwrap().name(), Some("node 0"));
    // Baked nodes keep their source names.
    scene.node_names[0] = Some("Corner".into());
    let bytes = frame_glb(&scene, 0, &meshes, &tone).unwrap();
    let gltf = gltf::Gltf::from_slice(&bytes).unwrap();
    let blob = gltf.blob.as_deref().unwrap();
    let node = gltf.nodes().next().unwrap();
    assert_eq!(node.name(), Some("Corner"));
    assert_eq!(node.mesh().unwrap().name(), Some("Corner baked"));
    // The scene sits 1e6 from the origin: the node carries the offset, the vertices are small.
    let (translation, _, _) = node.transform().decomposed();
    assert!((f64::from(translation[0]) - 1e6).abs() < 1.0);
    let primitive = node.mesh().unwrap().primitives().next().unwrap();
    let reader = primitive.reader(|_| Some(blob));
    let positions: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
    let colours: Vec<[f32; 3]> = reader.read_colors(0).unwrap().into_rgb_f32().collect();
    assert_eq!(positions.len(), meshes[0].positions.len());
    assert_eq!(colours.len(), positions.len());
    for (c, l) in colours.iter().zip(&meshes[0].radiance) {
        assert_eq!(*c, tone.apply(*l));
    }
    let radiance_attribute = primitive
        .attributes()
        .find(|(s, _)| *s == gltf::Semantic::Extras("RADIANCE".into()))
        .expect("a _RADIANCE attribute");
    assert_eq!(radiance_attribute.1.count(), positions.len());
    let stderr_attribute = primitive
        .attributes()
        .find(|(s, _)| *s == gltf::Semantic::Extras("RADIANCE_STDERR".into()))
        .expect("a _RADIANCE_STDERR attribute");
    assert_eq!(stderr_attribute.1.count(), positions.len());
    assert!(positions.iter().flatten().all(|c| c.abs() <= 1.0 + 1e-6));
    let indices: Vec<u32> = reader.read_indices().unwrap().into_u32().collect();
    assert_eq!(indices.len(), 3 * meshes[0].triangles.len());
    // Our own loader reads it back (custom attributes and the unlit extension included): one
    // patch per baked triangle, since back faces are now triangles of their own.
    let again = load(&bytes, &LoadOptions::default()).unwrap();
    assert_eq!(again.patches.len(), meshes[0].triangles.len());
}

#[test]
fn a_preview_shows_the_scene_lit_from_its_automatic_camera() {
    let scene = corner(false);
    let radiance = radiance(&scene);
    let tone = ToneMap { exposure: 0.05 };
    let meshes = frame_geometry(&scene, 0);
    let shown = (&meshes[..], &radiance[..]);
    let image = preview_image(&scene, 0, shown, (&tone, Shading::Flat), 160, 120);
    assert_eq!(image.dimensions(), (160, 120));
    let background = *image.get_pixel(0, 0);
    let lit = image.pixels().filter(|p| **p != background).count();
    assert!(lit > 160 * 120 / 20, "only {lit} pixels show the scene");
    // The wall (radiance 10–20) is brighter than the floor (1–3).
    let brightest = image.pixels().map(|p| p[1]).max().unwrap();
    assert!(brightest > 100);
}

/// A sample scene baked at 20,000 lines, and its preview of frame 0 (160 × 120, smooth, the
/// timeline's exposure) with the pixels that show the scene (not the background).
fn sample_preview(name: &str) -> (Scene, Vec<[u8; 3]>) {
    let sample = (radiosity::samples::all().into_iter())
        .find(|s| s.file_name == name)
        .unwrap();
    let scene = load(sample.gltf.as_bytes(), &LoadOptions::default()).unwrap();
    let params = radiosity::timeline::LineParams {
        lines: 20_000,
        seed: 1,
    };
    let bake = radiosity::bake::Bake::trace(scene, &params).unwrap();
    let solved =
        std::sync::Arc::new(bake.solve_frame(0, &bake.scene.materials, &Default::default()));
    let scene = bake.shown();
    let tone = ToneMap::for_timeline(scene, std::slice::from_ref(&solved));
    let look = (&tone, Shading::Smooth);
    let power = bake.light_power();
    let lighting = radiosity::direct::points::Lighting {
        materials: &bake.scene.materials,
        power: &power,
        sky: [0.0; 3],
    };
    let meshes = radiosity::output::lit_geometry(&bake, 0, &solved, lighting);
    let image = preview_image(scene, 0, (&meshes, &solved.radiance), look, 160, 120);
    let background = *image.get_pixel(0, 0);
    let drawn: Vec<[u8; 3]> = (image.pixels())
        .filter(|p| **p != background)
        .map(|p| p.0)
        .collect();
    assert!(
        drawn.len() > 160 * 120 / 10,
        "{name}: {} pixels drawn",
        drawn.len()
    );
    (scene.clone(), drawn)
}

#[test]
fn a_closed_room_of_double_sided_walls_previews_its_lit_inside() {
    let (_, drawn) = sample_preview("panel_room.gltf");
    // The walls' outer sides are black (no light reaches them): drawn, they hid the room (every
    // pixel black). Cut away, the lit inside shows.
    let black = drawn.iter().filter(|p| p.iter().all(|&c| c < 8)).count();
    assert!(
        black * 10 < drawn.len(),
        "{black} of {} drawn pixels black",
        drawn.len()
    );
}

#[test]
fn a_blender_style_lamp_room_previews_lit_and_exposed() {
    let (scene, drawn) = sample_preview("lamp_room.gltf");
    // Blender's frame 1 at 24 fps.
    assert!((scene.frames.start - 1.0 / 24.0).abs() < 1e-6);
    // Neither black (the walls' unlit outer sides drawn) nor washed out (an exposure taken
    // from them: 15 times too bright): the drawn pixels' mean in the middle of the range.
    let mean =
        drawn.iter().flatten().map(|&c| f64::from(c)).sum::<f64>() / (3 * drawn.len()) as f64;
    assert!((50.0..200.0).contains(&mean), "mean {mean:.0} of 255");
    let white = drawn.iter().filter(|p| p.iter().all(|&c| c > 245)).count();
    assert!(
        white * 20 < drawn.len(),
        "{white} of {} pixels white",
        drawn.len()
    );
}

#[test]
fn the_baked_glb_names_each_triangle_s_patch_and_carries_the_cameras_posed_at_its_frame() {
    let mut d = Doc::new();
    let (v, i) = common::cuboid([2.0, 2.0, 2.0], [0.0, 0.0, 0.0], true);
    let mesh = d.mesh(&v, Some(&i), None);
    let room = d.node(json!({"mesh": mesh, "translation": [100.0, 0.0, 0.0]}));
    d.push(
        "cameras",
        json!({"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.05, "zfar": 50.0, "aspectRatio": 1.5}}),
    );
    // A camera turned 90° about Y and scaled (glTF cameras ignore scale), under a parent that
    // moves 0.8 along +Z over one second.
    let half = std::f32::consts::FRAC_1_SQRT_2;
    let camera = d.node(
        json!({"camera": 0, "name": "eye", "translation": [100.0, 0.1, 0.2],
        "rotation": [0.0, half, 0.0, half], "scale": [2.0, 2.0, 2.0]}),
    );
    let rig = d.node(json!({"children": [camera]}));
    // A second camera, still, after the first in the hierarchy: carried too, second.
    d.push(
        "cameras",
        json!({"type": "orthographic", "orthographic": {"xmag": 2.0, "ymag": 1.5, "znear": 0.1, "zfar": 9.0}}),
    );
    let side = d.node(json!({"camera": 1, "name": "side", "translation": [103.0, 0.0, 0.0]}));
    d.scene(&[room, rig, side]);
    let dolly = [0.0, 0.0, 0.0, 0.0, 0.0, 0.8];
    d.animation(
        "dolly",
        &[(rig, "translation", &[0.0, 1.0], &dolly, "LINEAR")],
    );
    let options = LoadOptions {
        fps: 4.0,
        ..LoadOptions::default()
    };
    let scene = load(&d.gltf(), &options).unwrap();
    let tone = ToneMap { exposure: 1.0 };
    for frame in [0, 2, 4] {
        let meshes = frame_geometry(&scene, frame);
        let bytes = frame_glb(&scene, frame, &meshes, &tone).unwrap();
        let gltf = gltf::Gltf::from_slice(&bytes).unwrap();
        let blob = gltf.blob.as_deref().unwrap();
        // Each primitive's extras.patches: one u32 per triangle, the patch it draws.
        let node = gltf.nodes().find(|n| n.mesh().is_some()).unwrap();
        let primitive = node.mesh().unwrap().primitives().next().unwrap();
        let extras: serde_json::Value =
            serde_json::from_str(primitive.extras().as_ref().unwrap().get()).unwrap();
        let accessor = gltf
            .accessors()
            .nth(extras["patches"].as_u64().unwrap() as usize)
            .unwrap();
        assert_eq!(accessor.count(), meshes[0].triangles.len());
        let view = accessor.view().unwrap();
        let words = &blob[view.offset()..view.offset() + view.length()];
        let patches: Vec<u32> = (words.chunks_exact(4))
            .map(|w| u32::from_le_bytes(w.try_into().unwrap()))
            .collect();
        assert_eq!(patches, meshes[0].patches);
        // The camera nodes: the previews' first, then the other; each where it is at the frame,
        // turned as it is, no scale.
        let cameras: Vec<gltf::Node> = gltf.nodes().filter(|n| n.camera().is_some()).collect();
        assert_eq!(cameras.len(), 2);
        let side = &cameras[1];
        assert_eq!(side.name(), Some("side"));
        assert_eq!(side.camera().unwrap().index(), 1);
        assert_eq!(side.transform().decomposed().0, [103.0, 0.0, 0.0]);
        let eye = &cameras[0];
        assert_eq!(eye.name(), Some("eye"));
        assert_eq!(eye.camera().unwrap().index(), 0);
        let (t, r, s) = eye.transform().decomposed();
        let expected = [100.0, 0.1, 0.2 + 0.8 * frame as f32 / 4.0];
        for (a, b) in t.iter().zip(expected) {
            assert!((a - b).abs() < 1e-5, "frame {frame}: {t:?}");
        }
        let turn = glam::Quat::from_array(r).dot(glam::Quat::from_rotation_y(FRAC_PI_2));
        assert!(1.0 - turn.abs() < 1e-6, "frame {frame}: {r:?}");
        assert_eq!(s, [1.0; 3]);
        let camera = eye.camera().unwrap();
        let gltf::camera::Projection::Perspective(p) = camera.projection() else {
            panic!("not perspective");
        };
        assert!((p.yfov() - 0.8).abs() < 1e-6);
        assert!((p.znear() - 0.05).abs() < 1e-6 && (p.zfar().unwrap() - 50.0).abs() < 1e-4);
        assert_eq!(p.aspect_ratio(), Some(1.5));
    }
}
