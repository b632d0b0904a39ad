//! A batch of lines traced in parts ([`IntersectionList::build_shard`], one per machine) and
//! put together again ([`IntersectionList::merge`]): the list, and the bake made of it, are the
//! ones a single machine makes, to the bit; parts that do not make one set are refused.

use radiosity::bake::Bake;
use radiosity::control::Control;
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::Scene;
use radiosity::timeline::{IntersectionList, LineParams, Shard};
use radiosity::trace::SceneTracer;

fn sample(name: &str) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name);
    load(&std::fs::read(path).unwrap(), &LoadOptions::default()).unwrap()
}

fn bytes(list: &IntersectionList) -> Vec<u8> {
    postcard::to_allocvec(list).unwrap()
}

/// The parts of `params`' lines through `scene` in `count` parts, in order.
fn parts(scene: &Scene, params: &LineParams, count: u32) -> Vec<(Shard, IntersectionList)> {
    let tracer = SceneTracer::new(scene);
    (0..count)
        .map(|index| {
            let shard = Shard { index, count };
            let control = Control::default();
            let list = IntersectionList::build_shard(scene, &tracer, params, shard, &control);
            (shard, list.unwrap())
        })
        .collect()
}

#[test]
fn parts_merged_in_any_order_are_the_list_one_machine_traces() {
    for (name, lines) in [("cornell_moving.gltf", 30_000), ("level.gltf", 20_000)] {
        let scene = sample(name);
        let params = LineParams { lines, seed: 9 };
        let tracer = SceneTracer::new(&scene);
        let whole = IntersectionList::build(&scene, &tracer, &params, &Control::default());
        let whole = bytes(&whole.unwrap());
        for count in 1..=3 {
            let mut parts = parts(&scene, &params, count);
            // Each part holds about its share of the lines.
            for (_, part) in &parts {
                let share = part.lines() as f64 / params.lines as f64;
                assert!(
                    (share * f64::from(count) - 1.0).abs() < 0.1,
                    "{name}: {share}"
                );
            }
            parts.reverse();
            let merged = IntersectionList::merge(parts).unwrap();
            assert!(
                bytes(&merged) == whole,
                "{name}: {count} parts merged differ"
            );
        }
    }
}

#[test]
fn a_bake_of_merged_parts_is_the_bake_of_one_machine() {
    let scene = sample("cornell_moving.gltf");
    let params = LineParams {
        lines: 20_000,
        seed: 4,
    };
    let alone = Bake::trace(scene.clone(), &params).unwrap();
    let merged = IntersectionList::merge(parts(&scene, &params, 2)).unwrap();
    let control = Control::default();
    let all = radiosity::direct::area::Poses::All;
    let of_parts = Bake::of_merged_list(scene, merged, (params.seed, all), &control).unwrap();
    assert!(of_parts.write_bytes(Vec::new()).unwrap() == alone.write_bytes(Vec::new()).unwrap());
}

#[test]
fn parts_missing_repeated_or_of_other_lines_are_refused() {
    let scene = sample("cornell_box.gltf");
    let params = LineParams {
        lines: 5_000,
        seed: 1,
    };
    let three = parts(&scene, &params, 3);
    let error = |parts: Vec<(Shard, IntersectionList)>| match IntersectionList::merge(parts) {
        Ok(_) => panic!("merged"),
        Err(e) => e,
    };
    let missing = error(three[..2].to_vec());
    assert!(missing.contains("0/3, 1/3"), "{missing}");
    let repeated = error(vec![three[0].clone(), three[1].clone(), three[1].clone()]);
    assert!(repeated.contains("1/3, 1/3"), "{repeated}");
    let reseeded = parts(&scene, &LineParams { seed: 2, ..params }, 3);
    let mixed = error(vec![
        three[0].clone(),
        reseeded[1].clone(),
        three[2].clone(),
    ]);
    assert!(mixed.contains("part 1/3 is not of the lines"), "{mixed}");
    // A part claimed for another index: it holds lines of other parts.
    let claimed = vec![
        three[0].clone(),
        three[1].clone(),
        (three[2].0, three[1].1.clone()),
    ];
    assert!(error(claimed).contains("holds lines of other parts"));
    assert!(error(Vec::new()).contains("no part"));
}
