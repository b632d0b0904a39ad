//! Adaptive patches: cutting patches after tracing moves every crossing where a fresh trace
//! would put it, and `auto` cuts where the light needs it.

use radiosity::bake::Bake;
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::Scene;
use radiosity::timeline::{Control, LineParams};

fn sample(name: &str, options: &LoadOptions) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    load(&std::fs::read(path).unwrap(), options).unwrap()
}

fn lines(n: u64) -> LineParams {
    LineParams {
        lines: n,
        bundles: None,
        seed: 3,
    }
}

#[test]
fn cut_patches_hold_the_crossings_a_fresh_trace_finds() {
    // Static walls and a rigid box that moves: crossings of both are moved to the pieces.
    let scene = sample(
        "cornell_moving.gltf",
        &LoadOptions {
            fps: 4.0,
            ..LoadOptions::default()
        },
    );
    let params = lines(20_000);
    let mut bake = Bake::trace(scene, &params).unwrap();
    let triangles = bake.tracer().triangles();
    // Some triangles cut once, some into four, some left whole.
    let cuts: Vec<u32> = (0..triangles).map(|t| [0b10, 0, 0b1110][t % 3]).collect();
    let before = bake.scene.patches.len();
    let added = bake.cut(&cuts, &Control::default()).unwrap();
    assert_eq!(bake.scene.patches.len(), before + added);
    assert!(added > triangles / 2, "{added} patches added");
    let fresh = Bake::trace(bake.scene.clone(), &params).unwrap();
    for frame in 0..bake.scene.frames.count {
        assert_eq!(
            bake.frame_tally(frame),
            fresh.frame_tally(frame),
            "frame {frame}"
        );
    }
}
