//! The sample scenes in `scenes/`: reproducible from the generator, loaded as intended, and
//! watertight for the lines at every frame.

use radiosity::loader::{LoadOptions, load};
use radiosity::samples;
use radiosity::scene::Scene;
use radiosity::timeline::{IntersectionList, LineParams};
use radiosity::trace::SceneTracer;

fn scenes_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes")
}

fn load_sample(name: &str, options: &LoadOptions) -> Scene {
    let bytes = std::fs::read(scenes_dir().join(name)).unwrap();
    load(&bytes, options).unwrap()
}

#[test]
fn the_checked_in_scenes_are_what_the_generator_writes() {
    for sample in samples::all() {
        let on_disk = std::fs::read_to_string(scenes_dir().join(sample.file_name)).unwrap();
        assert!(
            on_disk == sample.gltf,
            "scenes/{} differs from the generator: run `radiosity samples --out scenes`",
            sample.file_name
        );
    }
}

#[test]
fn each_scene_loads_as_intended() {
    let options = LoadOptions::default();
    // (file, rigid objects, deforming objects, frames)
    for (name, rigid, deforming, frames) in [
        ("cornell_box.gltf", 0, 0, 1),
        ("cornell_moving.gltf", 1, 0, 49),
        ("furnace.gltf", 0, 0, 1),
        ("parallel_squares.gltf", 0, 0, 1),
        ("level.gltf", 1, 0, 49),
        ("level_lamps.gltf", 1, 0, 49),
        ("morph_box.gltf", 0, 1, 49),
        ("spheres.gltf", 4, 0, 25),
        ("panel_room.gltf", 0, 0, 1),
        ("lamp_room.gltf", 1, 0, 49),
    ] {
        let s = load_sample(name, &options).summary();
        assert_eq!(
            (s.rigid_objects, s.deforming_objects, s.frames),
            (rigid, deforming, frames),
            "{name}"
        );
        assert!(s.warnings.is_empty(), "{name}: {:?}", s.warnings);
        assert!(s.emitters + s.lights > 0, "{name} has no light");
    }
    let lamps = load_sample("level_lamps.gltf", &options).summary();
    assert_eq!(
        (lamps.emitters, lamps.lights, lamps.moving_lights),
        (0, 3, 1)
    );
    // Blender-style: 12 room triangles and 2 panel triangles, every one with a patch per face.
    let panel = load_sample("panel_room.gltf", &options);
    assert_eq!(panel.patches.len(), 2 * 14);
    let furnace = load_sample("furnace.gltf", &options);
    assert_eq!(furnace.summary().emitters, furnace.patches.len());
    assert_eq!(furnace.materials[0].reflectance, [0.999f32 as f64; 3]);
}

/// Every line crosses a closed scene an even number of times, at every frame: no leaks, no
/// double counts, with and without subdivision.
#[test]
fn closed_scenes_are_watertight_at_every_frame() {
    for (name, patch_size) in [
        ("furnace.gltf", None),
        ("furnace.gltf", Some(0.07)),
        ("cornell_box.gltf", Some(0.1)),
        ("cornell_moving.gltf", None),
        ("level.gltf", None),
        ("spheres.gltf", None),
        ("lamp_room.gltf", None),
    ] {
        let options = LoadOptions {
            fps: 6.0,
            patch_size,
            ..LoadOptions::default()
        };
        let scene = load_sample(name, &options);
        let tracer = SceneTracer::new(&scene);
        let list = IntersectionList::build(
            &scene,
            &tracer,
            &LineParams {
                lines: 20_000,
                seed: 3,
            },
            &radiosity::control::Control::default(),
        )
        .unwrap();
        let mut hits = Vec::new();
        for frame in 0..scene.frames.count {
            for line in 0..list.lines() {
                list.frame_hits(line, frame, &mut hits);
                assert!(
                    hits.len() % 2 == 0,
                    "{name} ({patch_size:?}) frame {frame} line {line}: {} crossings",
                    hits.len()
                );
            }
        }
    }
}
