//! The path-traced values `tests/points.rs` compares a sample scene's vertices with:
//! `SCENE=panel_room.gltf cargo run --release --example vertex_reference -- X,Y,Z,NX,NY,NZ ...`
//! (the scene cut into patches of 0.25 m, frame 0, 200,000 paths a vertex; a minute).
use glam::DVec3;
use radiosity::bake::Bake;
use radiosity::loader::{LoadOptions, load};
use radiosity::timeline::LineParams;

fn main() {
    let sample = (radiosity::samples::all().into_iter())
        .find(|s| s.file_name == std::env::var("SCENE").unwrap_or("panel_room.gltf".into()))
        .unwrap();
    let options = LoadOptions {
        patch_size: Some(0.25),
        ..LoadOptions::default()
    };
    let scene = load(sample.gltf.as_bytes(), &options).unwrap();
    let bake = Bake::trace(
        scene,
        &LineParams {
            lines: 200_000,
            seed: 1,
        },
    )
    .unwrap();
    let meshes = radiosity::output::frame_geometry(bake.shown(), 0);
    let points = radiosity::output::geometry::vertex_points(&bake, &meshes);
    let wanted: Vec<(DVec3, DVec3)> = std::env::args()
        .skip(1)
        .map(|a| {
            let v: Vec<f64> = a.split(',').map(|x| x.parse().unwrap()).collect();
            (DVec3::new(v[0], v[1], v[2]), DVec3::new(v[3], v[4], v[5]))
        })
        .collect();
    let shown = bake.shown();
    let mut i = 0;
    let mut chosen = radiosity::direct::points::Points::default();
    let mut names = Vec::new();
    for mesh in &meshes {
        for v in 0..mesh.positions.len() {
            let at = shown.normalisation.to_scene(mesh.positions[v]);
            let n = mesh.normals[v].as_dvec3();
            if let Some((p, m)) = wanted
                .iter()
                .find(|(p, m)| p.distance(at) < 1e-4 && m.dot(n) > 0.99)
            {
                chosen.push(points.point(i).iter().copied());
                names.push((*p, *m));
            }
            i += 1;
        }
    }
    let reference = radiosity::direct::reference::path_traced_points(
        (&bake.scene, bake.tracer(), 0),
        &chosen,
        200_000,
        [0.0; 3],
        99,
    );
    for ((p, m), r) in names.iter().zip(&reference) {
        println!("{p} facing {m}: {:.5} ± {:.5}", r.radiance[0], r.stderr[0]);
    }
}
