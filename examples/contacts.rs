//! Measures light at contacts: the Cornell box's two blocks stand on its floor. Reports the
//! radiance of the blocks' bottom faces and of the floor patches whose centre lies under a
//! block, against the mean radiance of the lit, non-emitting patches. Physically both are 0.
//! Then the moving Cornell box (its short block slides on the floor) with every material
//! double-sided: the most light on any face no light can reach (inside the blocks, outside the
//! room, and the blocks' bottoms) over its 25 frames; and the static one, double-sided under a
//! sky of 1 (which lights the room's outside): the most light inside its blocks and on their
//! bottoms. Physically 0.
//!
//!     cargo run --release --example contacts [LINES] [PATCH_SIZE]

use glam::{DVec2, DVec3};
use radiosity::bake::Bake;
use radiosity::loader::{LoadOptions, load};
use radiosity::solve::SolveParams;
use radiosity::timeline::LineParams;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let lines: u64 = args.next().map_or(Ok(1_000_000), |a| a.parse())?;
    let patch_size: f64 = args.next().map_or(Ok(0.1), |a| a.parse())?;
    let options = LoadOptions {
        patch_size: Some(patch_size),
        ..LoadOptions::default()
    };
    let bake = trace(&std::fs::read("scenes/cornell_box.gltf")?, &options, lines)?;
    let scene = &bake.scene;
    let s = bake.solve_frame(0, &scene.materials, &SolveParams::default());
    let n = &scene.normalisation;
    let faces: Vec<(u32, [DVec3; 3])> = scene
        .triangles_at(0)
        .iter()
        .map(|(c, f)| (f.front, c.map(|p| n.to_scene(p.as_dvec3()))))
        .collect();
    let normal = |c: &[DVec3; 3]| (c[1] - c[0]).cross(c[2] - c[0]).normalize_or_zero();
    let floor_y = faces
        .iter()
        .flat_map(|(_, c)| c.iter().map(|v| v.y))
        .fold(f64::INFINITY, f64::min);
    let on_floor = |c: &[DVec3; 3]| c.iter().all(|v| (v.y - floor_y).abs() < 1e-6);
    // Block bottoms face down on the floor's plane; the floor faces up.
    let bottoms: Vec<&(u32, [DVec3; 3])> = faces
        .iter()
        .filter(|(_, c)| on_floor(c) && normal(c).y < -0.5)
        .collect();
    let xz = |v: DVec3| DVec2::new(v.x, v.z);
    let inside = |p: DVec2, c: &[DVec3; 3]| {
        let [a, b, d] = c.map(xz);
        let side = |u: DVec2, v: DVec2| (v - u).perp_dot(p - u);
        let (s1, s2, s3) = (side(a, b), side(b, d), side(d, a));
        (s1 >= 0.0 && s2 >= 0.0 && s3 >= 0.0) || (s1 <= 0.0 && s2 <= 0.0 && s3 <= 0.0)
    };
    let under: Vec<&(u32, [DVec3; 3])> = faces
        .iter()
        .filter(|(_, c)| {
            let centre = xz((c[0] + c[1] + c[2]) / 3.0);
            on_floor(c) && normal(c).y > 0.5 && bottoms.iter().any(|(_, b)| inside(centre, b))
        })
        .collect();
    let mean = |chosen: &[u32]| {
        let area: f64 = chosen.iter().map(|&p| scene.patches[p as usize].area).sum();
        chosen
            .iter()
            .map(|&p| scene.patches[p as usize].area * s.radiance[p as usize][1])
            .sum::<f64>()
            / area
    };
    let lit: Vec<u32> = (0..scene.patches.len() as u32)
        .filter(|&p| {
            let patch = &scene.patches[p as usize];
            !scene.materials[patch.material as usize].is_emitter()
        })
        .collect();
    let reference = mean(&lit);
    let ids = |v: &[&(u32, [DVec3; 3])]| v.iter().map(|(p, _)| *p).collect::<Vec<_>>();
    println!(
        "cornell_box, {lines} lines, patch size {patch_size} m, {} patches: mean radiance (green) \
         {reference:.4}",
        scene.patches.len()
    );
    println!(
        "  block bottoms ({} patches): {:.4} = {:.1}% of the mean",
        bottoms.len(),
        mean(&ids(&bottoms)),
        100.0 * mean(&ids(&bottoms)) / reference
    );
    println!(
        "  floor under the blocks ({} patches): {:.4} = {:.1}% of the mean",
        under.len(),
        mean(&ids(&under)),
        100.0 * mean(&ids(&under)) / reference
    );
    hidden_faces("cornell_moving", lines, 0.0)?;
    hidden_faces("cornell_box", lines, 1.0)
}

/// Loads a glTF file's bytes and traces `lines` lines (seed 1) through it.
fn trace(
    gltf: &[u8],
    options: &LoadOptions,
    lines: u64,
) -> Result<Bake, Box<dyn std::error::Error>> {
    let params = LineParams { lines, seed: 1 };
    Ok(Bake::trace(load(gltf, options)?, &params)?)
}

/// A Cornell box made double-sided, under a sky of radiance `sky`: the largest radiance on a
/// face no light can reach over every frame (inside a block; and outside the room if the sky
/// is black).
fn hidden_faces(name: &str, lines: u64, sky: f64) -> Result<(), Box<dyn std::error::Error>> {
    let mut doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(format!("scenes/{name}.gltf"))?)?;
    for m in doc["materials"].as_array_mut().ok_or("no materials")? {
        m["doubleSided"] = serde_json::json!(true);
    }
    let options = LoadOptions {
        fps: 12.0,
        ..LoadOptions::default()
    };
    let bake = trace(&serde_json::to_vec(&doc)?, &options, lines)?;
    let scene = &bake.scene;
    let params = SolveParams {
        sky: [sky; 3],
        ..SolveParams::default()
    };
    let solved = bake.solve_all(&scene.materials, &params);
    // Back faces, but for the lamp's, which emits (a double-sided emitter emits both ways), and
    // the room's (outside it) when the sky lights them.
    let room = scene.patches[0].source.node;
    let mut hidden: Vec<usize> = (0..scene.patches.len())
        .filter(|&p| {
            let patch = &scene.patches[p];
            patch.side == radiosity::scene::Side::Back
                && !scene.materials[patch.material as usize].is_emitter()
                && (sky == 0.0 || patch.source.node != room)
        })
        .collect();
    // And the blocks' bottoms, which stand (or slide) on the floor.
    let n = &scene.normalisation;
    for (corners, faces) in scene.triangles_at(0) {
        let c = corners.map(|p| n.to_scene(p.as_dvec3()));
        let down = (c[1] - c[0]).cross(c[2] - c[0]).y < 0.0;
        if down && c.iter().all(|v| v.y.abs() < 1e-6) {
            hidden.push(faces.front as usize);
        }
    }
    let (mut worst, mut lit) = (0.0f64, 0);
    for s in &solved {
        for &p in &hidden {
            worst = worst.max(s.radiance[p].iter().copied().fold(0.0, f64::max));
            lit += usize::from(s.radiance[p].iter().any(|&l| l > 0.0));
        }
    }
    println!(
        "{name} double-sided, sky {sky}, {lines} lines, {} frames: {} faces no light reaches; \
         the brightest gets {worst:.3e}, {lit} of {} (face, frame) pairs get any",
        solved.len(),
        hidden.len(),
        hidden.len() * solved.len()
    );
    Ok(())
}
