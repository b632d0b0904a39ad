//! The visibility information measured by the lines (`solve::information`) against cases with
//! known answers.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use radiosity::bake::Bake;
use radiosity::scene::Scene;
use radiosity::solve::information::Information;
use radiosity::timeline::LineParams;

fn information(scene: Scene, lines: u64) -> Information {
    let bake = Bake::trace(
        scene,
        &LineParams {
            lines,
            bundles: None,
            seed: 5,
        },
    )
    .unwrap();
    Information::measure(
        &bake.scene,
        bake.list(),
        &bake.tracer().surfaces(),
        &bake.frame_tally(0),
        0,
    )
}

#[test]
fn inside_a_sphere_every_point_sees_every_other_alike() {
    // F(x, y) = 1/A_T between any two points of a sphere's inside: I_c = 0. Measured 0.0025
    // ± 0.0002 on this faceted sphere (its facets' normals are not the sphere's).
    let info = information(
        common::static_scene(&[common::icosphere(4, 1.0, true)], None),
        200_000,
    );
    assert!(
        info.continuous.abs() < 0.01 + 4.0 * info.continuous_stderr,
        "{}",
        info.continuous
    );
}

#[test]
fn finer_patches_lose_less_of_a_room_s_visibility() {
    // I_d grows towards I_c from below as the patches shrink (measured: 0.49, 0.76, 1.03 nats
    // under I_c = 1.12 for 1 m, 0.5 m and 0.25 m patches).
    let room = common::cuboid([1.0, 1.0, 1.0], [0.0, 0.0, 0.0], true);
    let mut last = f64::NEG_INFINITY;
    for size in [1.0, 0.5, 0.25] {
        let info = information(
            common::static_scene(std::slice::from_ref(&room), Some(size)),
            400_000,
        );
        assert!(info.discrete > last, "{size}: {}", info.discrete);
        assert!(info.discrete < info.continuous, "{size}");
        last = info.discrete;
        let shares: f64 = info.patch_gap.iter().sum();
        assert!((shares - info.gap).abs() < 1e-9 * info.gap.abs().max(1.0));
    }
}
