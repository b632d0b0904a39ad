//! A bake's traced state written as bytes and read back ([`Bake::write_bytes`],
//! [`Bake::from_bytes`]): the service keeps it on disk so that a timeline dropped from memory
//! (or restored after a restart) is refined and relit without tracing its lines again. What is
//! read back must be the same bake to the bit: the same bytes when written again, the same
//! frames, and the same frames again after a refinement, which traces new lines with the
//! tracers built again from the scenes read back.

use radiosity::adaptive::{Adaptive, adapt};
use radiosity::bake::Bake;
use radiosity::control::Control;
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::Scene;
use radiosity::solve::SolveParams;
use radiosity::timeline::LineParams;

fn sample(name: &str) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    load(&std::fs::read(path).unwrap(), &LoadOptions::default()).unwrap()
}

/// `scene` traced with `lines`, made `auto`, and split, as the service bakes it.
fn baked(scene: Scene, lines: u64) -> Bake {
    let params = LineParams { lines, seed: 7 };
    let solve = SolveParams::default();
    let mut bake = Bake::trace(scene, &params).unwrap();
    let auto = Adaptive::for_lines(lines, bake.scene.patches.len());
    adapt(&mut bake, &auto, &solve, &Control::default()).unwrap();
    bake.split(&solve, &Control::default()).unwrap();
    bake
}

/// The first, middle and last frames of `bake` solved with its scene's materials.
fn frames(bake: &Bake) -> Vec<radiosity::solve::FrameSolution> {
    let solve = SolveParams::default();
    let last = bake.scene.frames.count - 1;
    [0, last / 2, last]
        .map(|f| bake.solve_frame(f, &bake.scene.materials, &solve))
        .to_vec()
}

fn round_trip(name: &str, lines: u64) {
    let mut kept = baked(sample(name), lines);
    assert!(kept.pieces().is_some(), "{name}: the bake was not split");
    let bytes = kept.write_bytes(Vec::new()).unwrap();
    let mut read = Bake::from_bytes(&bytes).unwrap();
    assert!(
        read.write_bytes(Vec::new()).unwrap() == bytes,
        "{name}: the bake read back writes other bytes"
    );
    assert_eq!(frames(&read), frames(&kept), "{name}: other frames");
    // New lines, traced by the tracers built again from the scenes read back.
    kept.refine(lines / 2, &Control::default()).unwrap();
    read.refine(lines / 2, &Control::default()).unwrap();
    assert!(
        read.write_bytes(Vec::new()).unwrap() == kept.write_bytes(Vec::new()).unwrap(),
        "{name}: the refinements differ"
    );
    assert_eq!(frames(&read), frames(&kept), "{name}: other frames refined");
}

#[test]
fn a_moving_box_with_an_area_light_reads_back_to_the_bit() {
    round_trip("cornell_moving.gltf", 30_000);
}

#[test]
fn a_level_with_punctual_lights_reads_back_to_the_bit() {
    round_trip("level_lamps.gltf", 40_000);
}

#[test]
fn a_morphing_mesh_reads_back_to_the_bit() {
    round_trip("morph_box.gltf", 40_000);
}

#[test]
fn bytes_cut_short_or_of_another_kind_are_refused_not_read() {
    let bake = baked(sample("cornell_box.gltf"), 20_000);
    let bytes = bake.write_bytes(Vec::new()).unwrap();
    for cut in [0, 1, bytes.len() / 3, bytes.len() - 1] {
        assert!(Bake::from_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
    }
    assert!(Bake::from_bytes(b"{\"not\": \"a bake\"}").is_err());
}
