//! Global lines against integral geometry's identities (METHOD.md §1–§2), the tracer against
//! brute force and closed meshes, and the multiframe list against tracing each frame alone.
//!
//! Statistical checks use fixed seeds and report a z-score (error over its standard deviation);
//! they pass below 4. The wrong generator of METHOD.md §2 (a uniform point on the bounding sphere
//! plus an independent uniform direction) must fail the same checks.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use common::Doc;
use glam::{DVec3, Vec3};
use radiosity::lines::{Batch, LINE_LENGTH, ORIGIN_OFFSET};
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::Scene;
use radiosity::timeline::stats::SceneStats;
use radiosity::timeline::{IntersectionList, LineParams};
use radiosity::trace::{FrameMeshes, Hit, Line, ParallelLines, SceneTracer, Scratch};
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use serde_json::json;

/// A closed box of `size` centred at `center`, faces outward: 8 vertices, 12 triangles.
fn cube(size: [f32; 3], center: [f32; 3]) -> (Vec<[f32; 3]>, Vec<u32>) {
    common::cuboid(size, center, false)
}

/// An icosphere of radius `r` (level-2 subdivision: 320 faces), faces outward.
fn sphere(r: f32) -> (Vec<[f32; 3]>, Vec<u32>) {
    common::icosphere(2, r, false)
}

/// Lines from the correct generator: `bundles` bundles, about `lines` lines.
fn good_lines(scene: &Scene, lines: u64, bundles: u32, seed: u64) -> Vec<Line> {
    let batch = Batch::for_budget(lines, Some(bundles), &scene.bounds, seed, 0);
    (0..bundles)
        .flat_map(|k| {
            let b = batch.bundle(k, &scene.bounds);
            b.origins.into_iter().map(move |origin| Line {
                origin,
                direction: b.direction,
            })
        })
        .collect()
}

/// Lines from the wrong generator: a uniform point on the box's circumsphere and an independent
/// uniform direction, kept if the line meets the box.
fn wrong_lines(scene: &Scene, lines: usize, seed: u64) -> Vec<Line> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let b = scene.bounds;
    let (c, r) = ((b.min + b.max) * 0.5, (b.max - b.min).length() * 0.5);
    let mut unit = || loop {
        let p = DVec3::new(
            rng.random::<f64>() * 2.0 - 1.0,
            rng.random::<f64>() * 2.0 - 1.0,
            rng.random::<f64>() * 2.0 - 1.0,
        );
        if p.length_squared() <= 1.0 && p.length_squared() > 1e-6 {
            return p.normalize();
        }
    };
    let mut out = Vec::new();
    while out.len() < lines {
        let (p, w) = (c + unit() * r, unit());
        // Keep the part of the line that meets the box, starting outside the scene.
        let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
        for a in 0..3 {
            let (t0, t1) = ((b.min[a] - p[a]) / w[a], (b.max[a] - p[a]) / w[a]);
            near = near.max(t0.min(t1));
            far = far.min(t0.max(t1));
        }
        if near <= far {
            let foot = p - w * p.dot(w);
            out.push(Line {
                origin: (foot - w * f64::from(ORIGIN_OFFSET)).as_vec3(),
                direction: w.as_vec3(),
            });
        }
    }
    out
}

fn trace_all(tracer: &SceneTracer, lines: &[Line]) -> Vec<Vec<Hit>> {
    lines
        .iter()
        .map(|l| {
            let mut h = Vec::new();
            tracer.trace_frame(l, 0, &FrameMeshes::none(), &mut h);
            h
        })
        .collect()
}

fn mean_and_sigma(xs: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    let mean = xs.iter().sum::<f64>() / n;
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, (var / n).sqrt())
}

/// z-score of the mean chord of a single convex body against 4V/A.
fn chord_z(scene: &Scene, lines: &[Line], volume: f64, area: f64) -> f64 {
    let hits = trace_all(&SceneTracer::new(scene), lines);
    let chords: Vec<f64> = hits
        .iter()
        .filter(|h| h.len() == 2)
        .map(|h| f64::from(h[1].t - h[0].t) * scene.normalisation.radius)
        .collect();
    let (mean, sigma) = mean_and_sigma(&chords);
    (mean - 4.0 * volume / area) / sigma
}

/// z-score of P(meets inner | meets outer) against A1/A2 for two nested convex bodies given as
/// the first (inner) and second (outer) node.
fn cauchy_z(scene: &Scene, lines: &[Line], ratio: f64) -> f64 {
    let tracer = SceneTracer::new(scene);
    let inner_triangles = scene.patches.iter().filter(|p| p.source.node == 0).count() as u32;
    let hits = trace_all(&tracer, lines);
    let outer: Vec<&Vec<Hit>> = hits
        .iter()
        .filter(|h| h.iter().any(|x| x.surface() >= inner_triangles))
        .collect();
    let both = outer
        .iter()
        .filter(|h| h.iter().any(|x| x.surface() < inner_triangles))
        .count();
    let n = outer.len() as f64;
    let p = both as f64 / n;
    (p - ratio) / (ratio * (1.0 - ratio) / n).sqrt()
}

/// z-score of the mean number of crossings per line against 2 A(K) / A(W).
fn hits_per_line_z(scene: &Scene, lines: &[Line], total_area: f64) -> f64 {
    let hits = trace_all(&SceneTracer::new(scene), lines);
    let counts: Vec<f64> = hits.iter().map(|h| h.len() as f64).collect();
    let (mean, sigma) = mean_and_sigma(&counts);
    let r2 = scene.normalisation.radius.powi(2);
    let predicted = 2.0 * total_area / (scene.bounds.surface_area() * r2);
    (mean - predicted) / sigma
}

#[test]
fn mean_chord_of_a_convex_body_is_4v_over_a() {
    // A 1 × 2 × 0.5 box: V = 1, A = 7.
    let scene = common::static_scene(&[cube([1.0, 2.0, 0.5], [0.3, 0.0, 0.0])], None);
    let good = chord_z(&scene, &good_lines(&scene, 40_000, 200, 1), 1.0, 7.0);
    assert!(good.abs() < 4.0, "correct generator: z = {good}");
    let bad = chord_z(&scene, &wrong_lines(&scene, 40_000, 1), 1.0, 7.0);
    assert!(bad.abs() > 4.0, "the wrong generator passed: z = {bad}");
}

#[test]
fn nested_convex_bodies_follow_cauchy() {
    // A sphere of radius 0.4 inside a unit cube: A1/A2 = 4π·0.16·(polyhedral factor) / 6.
    let inner = sphere(0.4);
    let a1: f64 = inner
        .1
        .chunks(3)
        .map(|t| {
            let p = |i: u32| Vec3::from_array(inner.0[i as usize]).as_dvec3();
            0.5 * (p(t[1]) - p(t[0])).cross(p(t[2]) - p(t[0])).length()
        })
        .sum();
    let scene = common::static_scene(&[inner, cube([1.0; 3], [0.0; 3])], None);
    let ratio = a1 / 6.0;
    let good = cauchy_z(&scene, &good_lines(&scene, 40_000, 200, 2), ratio);
    assert!(good.abs() < 4.0, "correct generator: z = {good}");
    let bad = cauchy_z(&scene, &wrong_lines(&scene, 40_000, 2), ratio);
    assert!(bad.abs() > 4.0, "the wrong generator passed: z = {bad}");
}

#[test]
fn mean_crossings_per_line_is_2a_over_aw() {
    let scene = common::static_scene(&[sphere(0.3), cube([1.0, 1.0, 1.0], [0.0; 3])], None);
    let area: f64 = scene.patches.iter().map(|p| p.area).sum();
    let good = hits_per_line_z(&scene, &good_lines(&scene, 40_000, 200, 3), area);
    assert!(good.abs() < 4.0, "correct generator: z = {good}");
    let bad = hits_per_line_z(&scene, &wrong_lines(&scene, 40_000, 3), area);
    assert!(bad.abs() > 4.0, "the wrong generator passed: z = {bad}");
}

#[test]
fn each_patch_is_crossed_a_over_2_delta_times_per_bundle() {
    let scene = common::static_scene(&[cube([1.0, 0.6, 0.8], [0.0; 3])], Some(0.25));
    let tracer = SceneTracer::new(&scene);
    let bundles = 400;
    let batch = Batch::for_budget(200_000, Some(bundles), &scene.bounds, 4, 0);
    let patches = scene.patches.len();
    // Crossings of each patch per bundle.
    let mut per_bundle = vec![vec![0f64; bundles as usize]; patches];
    let mut hits = Vec::new();
    for k in 0..bundles {
        let b = batch.bundle(k, &scene.bounds);
        for &origin in &b.origins {
            hits.clear();
            tracer.trace_static(
                &Line {
                    origin,
                    direction: b.direction,
                },
                LINE_LENGTH,
                &mut hits,
            );
            for h in &hits {
                per_bundle[scene.statics.faces[h.surface() as usize].front as usize][k as usize] +=
                    1.0;
            }
        }
    }
    let r2 = scene.normalisation.radius.powi(2);
    let mut worst = 0f64;
    for (i, counts) in per_bundle.iter().enumerate() {
        let area = scene.patches[i].area / r2;
        let expected = f64::from(bundles) * area / (2.0 * batch.cell_area);
        // Per-bundle counts vary with the direction and the grid offset; treating them as
        // independent over-estimates the spread of their stratified sum (a conservative σ).
        let (mean, sigma) = mean_and_sigma(counts);
        let total = mean * f64::from(bundles);
        let z = (total - expected) / (sigma * f64::from(bundles)).max(1e-9);
        worst = worst.max(z.abs());
    }
    assert!(
        worst < 4.5,
        "worst patch z = {worst} over {patches} patches"
    );
}

#[test]
fn the_bvh_agrees_with_brute_force() {
    let scene = common::static_scene(
        &[
            sphere(0.45),
            cube([1.0; 3], [0.0; 3]),
            cube([0.2; 3], [0.2, 0.1, 0.0]),
        ],
        Some(0.2),
    );
    let lines = good_lines(&scene, 20_000, 100, 5);
    let mesh = radiosity::trace::TraceMesh::new(
        scene
            .statics
            .triangles
            .iter()
            .map(|t| t.map(|i| scene.statics.positions[i as usize])),
        0,
    )
    .unwrap();
    let (mut a, mut b) = (Vec::new(), Vec::new());
    let mut total = 0;
    for l in &lines {
        a.clear();
        b.clear();
        mesh.trace(l.origin, l.direction, &mut a);
        mesh.trace_brute_force(l.origin, l.direction, &mut b);
        a.sort_unstable_by(Hit::order);
        b.sort_unstable_by(Hit::order);
        assert_eq!(a, b);
        total += a.len();
    }
    assert!(total > 40_000, "{total}");
}

/// The BVH's walk of a convex region (a shadow volume: a point and a quad's pyramid) finds
/// exactly the triangles that clipping every triangle by the region's planes finds, for
/// pyramids of every size from points all over the scene; and a triangle wholly inside, beside
/// or around one is or is not found.
#[test]
fn the_bvh_finds_the_triangles_in_a_convex_region_as_brute_force_does() {
    use radiosity::trace::convex_meets_triangle;
    let scene = common::static_scene(
        &[
            sphere(0.45),
            cube([1.0; 3], [0.0; 3]),
            cube([0.2; 3], [0.2, 0.1, 0.0]),
        ],
        Some(0.2),
    );
    let corners: Vec<[Vec3; 3]> = (scene.statics.triangles.iter())
        .map(|t| t.map(|i| scene.statics.positions[i as usize]))
        .collect();
    let mesh = radiosity::trace::TraceMesh::new(corners.iter().copied(), 0).unwrap();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(11);
    let (mut found, mut empty) = (0, 0);
    for _ in 0..2000 {
        let apex = DVec3::new(
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
            rng.random::<f64>() - 0.5,
        ) * 1.2;
        let centre = apex + any_direction(&mut rng) * rng.random::<f64>() * 0.8;
        let (u, v) = (any_direction(&mut rng), any_direction(&mut rng));
        let size = 0.2 * rng.random::<f64>().powi(2);
        let quad = [u + v, u - v, -u - v, -u + v].map(|d| centre + d * size);
        let mut planes: Vec<(DVec3, f64)> = Vec::new();
        let middle = quad.iter().sum::<DVec3>() / 4.0;
        for k in 0..4 {
            let m = (quad[k] - apex).cross(quad[(k + 1) % 4] - apex).normalize();
            let m = if m.dot(middle - apex) > 0.0 { -m } else { m };
            planes.push((m, m.dot(apex)));
        }
        let far = (middle - apex).normalize();
        planes.push((far, far.dot(middle)));
        let mut walked = Vec::new();
        mesh.any_in_convex(&planes, &mut |id| {
            walked.push(id);
            false
        });
        walked.sort_unstable();
        let brute: Vec<u32> = (0..corners.len() as u32)
            .filter(|&i| convex_meets_triangle(&planes, corners[i as usize].map(Vec3::as_dvec3)))
            .collect();
        assert_eq!(walked, brute, "apex {apex}");
        if brute.is_empty() {
            empty += 1;
        } else {
            found += brute.len();
        }
    }
    assert!(found > 1000 && empty > 100, "{found} found, {empty} empty");
    // A unit cube's region against triangles inside, beside and around it.
    let planes: Vec<(DVec3, f64)> = [DVec3::X, DVec3::Y, DVec3::Z]
        .into_iter()
        .flat_map(|a| [(a, 1.0), (-a, 0.0)])
        .collect();
    let t = |a: [f64; 3], b: [f64; 3], c: [f64; 3]| [a, b, c].map(DVec3::from);
    assert!(convex_meets_triangle(
        &planes,
        t([0.2, 0.2, 0.5], [0.8, 0.2, 0.5], [0.5, 0.8, 0.5])
    ));
    assert!(!convex_meets_triangle(
        &planes,
        t([1.2, 0.2, 0.5], [1.8, 0.2, 0.5], [1.5, 0.8, 0.5])
    ));
    // Corners all outside, but cutting through the cube.
    assert!(convex_meets_triangle(
        &planes,
        t([-5.0, -5.0, 0.5], [5.0, -5.0, 0.5], [0.5, 5.0, 0.5])
    ));
    // All beyond one plane.
    assert!(!convex_meets_triangle(
        &planes,
        t([1.5, -1.0, 0.5], [3.0, 0.5, 0.5], [1.5, 0.5, 3.0])
    ));
}

/// A direction drawn from `rng` (the cube's, normalised: any direction, not uniformly).
fn any_direction(rng: &mut Xoshiro256PlusPlus) -> DVec3 {
    DVec3::new(
        rng.random::<f64>() - 0.5,
        rng.random::<f64>() - 0.5,
        rng.random::<f64>() - 0.5,
    )
    .normalize()
}

#[test]
fn closed_meshes_are_watertight_even_at_shared_edges_and_vertices() {
    let (v, i) = sphere(0.5);
    let scene = common::static_scene(
        &[(v.clone(), i.clone()), cube([1.2; 3], [0.0; 3])],
        Some(0.3),
    );
    let tracer = SceneTracer::new(&scene);
    let n = scene.normalisation;
    // Lines aimed at every vertex and every edge midpoint of the sphere, in random directions.
    let mut targets: Vec<DVec3> = v.iter().map(|p| Vec3::from_array(*p).as_dvec3()).collect();
    for t in i.chunks(3) {
        for k in 0..3 {
            let (a, b) = (
                Vec3::from_array(v[t[k] as usize]),
                Vec3::from_array(v[t[(k + 1) % 3] as usize]),
            );
            targets.push(((a + b) * 0.5).as_dvec3());
        }
    }
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(6);
    let mut hits = Vec::new();
    for &target in &targets {
        let p = (target - n.center) / n.radius;
        for _ in 0..10 {
            let w = any_direction(&mut rng);
            let line = Line {
                origin: (p - w * f64::from(ORIGIN_OFFSET)).as_vec3(),
                direction: w.as_vec3(),
            };
            tracer.trace_frame(&line, 0, &FrameMeshes::none(), &mut hits);
            assert!(
                hits.len() % 2 == 0,
                "{} crossings through {target}",
                hits.len()
            );
        }
    }
    // The same targets as bundles: parallel lines through all of them at once, which must
    // find what each finds alone.
    let mut scratch = Scratch::default();
    let (mut together, mut alone) = (Vec::new(), Vec::new());
    for _ in 0..20 {
        let w = any_direction(&mut rng);
        let origins = targets
            .iter()
            .map(|&t| ((t - n.center) / n.radius - w * f64::from(ORIGIN_OFFSET)).as_vec3())
            .collect();
        let lines = ParallelLines::new(w.as_vec3(), origins);
        tracer.trace_frame_parallel(&lines, 0, &FrameMeshes::none(), &mut scratch, &mut together);
        for (l, &origin) in lines.origins().iter().enumerate() {
            let line = Line {
                origin,
                direction: lines.direction(),
            };
            tracer.trace_frame(&line, 0, &FrameMeshes::none(), &mut alone);
            assert_eq!(crossings_of(&together, l), alone, "line {l} along {w}");
            assert!(alone.len() % 2 == 0);
        }
    }
    // And the bulk of ordinary lines.
    for h in trace_all(&tracer, &good_lines(&scene, 20_000, 100, 7)) {
        assert!(h.len() % 2 == 0);
        assert!(h.iter().all(|x| x.t > 0.0 && x.t < LINE_LENGTH));
    }
}

/// A room (closed box, faces inward through double-sided material), a rigid cube that moves and
/// turns inside it, and a morphing closed box.
fn animated_scene(fps: f64, patch_size: Option<f64>) -> Scene {
    let mut d = Doc::new();
    let wall = d.push("materials", json!({"doubleSided": true}));
    let (rv, ri) = cube([4.0, 3.0, 4.0], [0.0, 1.5, 0.0]);
    let room = d.mesh(&rv, Some(&ri), Some(wall));
    let (cv, ci) = cube([0.5; 3], [0.0; 3]);
    let block = d.mesh(&cv, Some(&ci), None);
    let (mv, mi) = cube([0.6; 3], [0.0; 3]);
    let morph = d.mesh(&mv, Some(&mi), None);
    // A morph target raising the top four vertices.
    let deltas: Vec<f32> = mv
        .iter()
        .flat_map(|p| {
            if p[1] > 0.0 {
                [0.0, 0.8, 0.0]
            } else {
                [0.0; 3]
            }
        })
        .collect();
    let target = d.floats(&deltas, "VEC3");
    d.json["meshes"][morph]["primitives"][0]["targets"] = json!([{"POSITION": target}]);
    let r = d.node(json!({"mesh": room}));
    let b = d.node(json!({"mesh": block, "translation": [-1.0, 0.5, 0.0]}));
    let m = d.node(json!({"mesh": morph, "translation": [1.0, 0.3, 1.0]}));
    // One that slides without turning: its frames are traced in one walk.
    let s = d.node(json!({"mesh": block, "translation": [0.0, 2.0, -1.0]}));
    d.scene(&[r, b, m, s]);
    let q = (0.5f32).sin();
    d.animation(
        "move",
        &[
            (
                b,
                "translation",
                &[0.0, 1.0],
                &[-1.0, 0.5, 0.0, 1.0, 1.0, -1.0],
                "LINEAR",
            ),
            (
                b,
                "rotation",
                &[0.0, 1.0],
                &[0.0, 0.0, 0.0, 1.0, 0.0, q, 0.0, (0.5f32).cos()],
                "LINEAR",
            ),
            (m, "weights", &[0.0, 1.0], &[0.0, 1.0], "LINEAR"),
            (
                s,
                "translation",
                &[0.0, 1.0],
                &[0.0, 2.0, -1.0, 0.7, 1.2, 1.0],
                "LINEAR",
            ),
        ],
    );
    load(
        &d.glb(),
        &LoadOptions {
            fps,
            patch_size,
            ..LoadOptions::default()
        },
    )
    .unwrap()
}

#[test]
fn each_frame_extracted_from_the_list_equals_that_frame_traced_alone() {
    let scene = animated_scene(8.0, None);
    assert_eq!(scene.frames.count, 9);
    assert_eq!(scene.objects.len(), 3);
    let list = list_equals_frames(&scene, 5_000);
    // Static crossings are stored once, not once per frame.
    let memory = list.memory();
    let static_per_frame: usize = (0..list.lines()).map(|l| list.static_hits(l).len()).sum();
    assert_eq!(memory.static_hits, static_per_frame);
    assert!(memory.bytes_per_hit() <= 16.0, "{}", memory.bytes_per_hit());
}

#[test]
fn a_timeline_of_many_frames_is_traced_whole() {
    // More frames than the rigid movers are traced at once for a bundle.
    let scene = animated_scene(150.0, None);
    assert_eq!(scene.frames.count, 151);
    list_equals_frames(&scene, 1_000);
}

/// The list of `lines` lines through `scene`, after checking that each frame extracted from it
/// is that frame traced alone, line by line.
fn list_equals_frames(scene: &Scene, lines: u64) -> IntersectionList {
    let tracer = SceneTracer::new(scene);
    let list = IntersectionList::build(
        scene,
        &tracer,
        &LineParams { lines, seed: 11 },
        &radiosity::control::Control::default(),
    )
    .unwrap();
    let lines: Vec<Line> = list.regenerate_lines(scene).collect();
    assert_eq!(lines.len(), list.lines());
    let (mut from_list, mut alone) = (Vec::new(), Vec::new());
    let mut moving_seen = 0;
    for frame in 0..scene.frames.count {
        let deformed = tracer.deformed_at(scene, frame);
        for (l, line) in lines.iter().enumerate() {
            list.frame_hits(l, frame, &mut from_list);
            tracer.trace_frame(line, frame, &deformed, &mut alone);
            assert_eq!(from_list, alone, "line {l} frame {frame}");
            // Closed scene: every line crosses an even number of times.
            assert!(alone.len() % 2 == 0);
            moving_seen += alone.iter().filter(|h| h.surface() >= 12).count();
        }
    }
    assert!(moving_seen > 1000, "{moving_seen}");
    list
}

/// The crossings of line `l` among a bundle's `(line, crossing)` pairs sorted by line.
fn crossings_of(found: &[(u32, Hit)], l: usize) -> Vec<Hit> {
    found
        .iter()
        .filter(|&&(line, _)| line as usize == l)
        .map(|&(_, hit)| hit)
        .collect()
}

#[test]
fn bundles_find_exactly_what_their_lines_find_traced_alone() {
    // Fine triangles (deep BVHs), a block moving and turning, a box morphing.
    let scene = animated_scene(4.0, Some(0.2));
    let tracer = SceneTracer::new(&scene);
    assert!(tracer.triangles() > 2_000, "{}", tracer.triangles());
    let batch = Batch::for_budget(20_000, Some(48), &scene.bounds, 3, 0);
    let mut scratch = Scratch::default();
    let (mut together, mut alone) = (Vec::new(), Vec::new());
    let (mut lines_checked, mut moving) = (0, 0);
    for frame in 0..scene.frames.count {
        let deformed = tracer.deformed_at(&scene, frame);
        for k in 0..batch.bundles {
            let bundle = batch.bundle(k, &scene.bounds);
            let lines = ParallelLines::new(bundle.direction, bundle.origins.clone());
            tracer.trace_frame_parallel(&lines, frame, &deformed, &mut scratch, &mut together);
            assert!(together.is_sorted_by(|a, b| (a.0, a.1.t) <= (b.0, b.1.t)));
            let mut at = 0;
            for (l, &origin) in bundle.origins.iter().enumerate() {
                let line = Line {
                    origin,
                    direction: bundle.direction,
                };
                tracer.trace_frame(&line, frame, &deformed, &mut alone);
                let n = together[at..]
                    .iter()
                    .take_while(|&&(line, _)| line as usize == l)
                    .count();
                let mine: Vec<Hit> = together[at..at + n].iter().map(|&(_, h)| h).collect();
                assert_eq!(mine, alone, "frame {frame}, bundle {k}, line {l}");
                at += n;
                moving += alone.iter().filter(|h| h.surface() >= 12).count();
            }
            assert_eq!(at, together.len());
            lines_checked += bundle.origins.len();
        }
    }
    assert!(lines_checked > 90_000, "{lines_checked}");
    assert!(moving > 10_000, "{moving}");
}

#[test]
fn the_list_does_not_depend_on_the_number_of_threads() {
    let scene = animated_scene(4.0, None);
    let build = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let tracer = SceneTracer::new(&scene);
            IntersectionList::build(
                &scene,
                &tracer,
                &LineParams {
                    lines: 3_000,
                    seed: 5,
                },
                &radiosity::control::Control::default(),
            )
            .unwrap()
        })
    };
    let (one, two) = (build(1), build(2));
    let (mut a, mut b) = (Vec::new(), Vec::new());
    assert_eq!(one.lines(), two.lines());
    for frame in 0..scene.frames.count {
        for l in 0..one.lines() {
            one.frame_hits(l, frame, &mut a);
            two.frame_hits(l, frame, &mut b);
            assert_eq!(a, b);
        }
    }
}

#[test]
fn refinement_adds_lines_without_touching_the_old_ones() {
    let scene = animated_scene(4.0, None);
    let tracer = SceneTracer::new(&scene);
    let params = LineParams {
        lines: 2_000,
        seed: 9,
    };
    let first = IntersectionList::build(
        &scene,
        &tracer,
        &params,
        &radiosity::control::Control::default(),
    )
    .unwrap();
    let mut more = IntersectionList::build(
        &scene,
        &tracer,
        &params,
        &radiosity::control::Control::default(),
    )
    .unwrap();
    more.add_lines(
        &scene,
        &tracer,
        &params,
        &radiosity::control::Control::default(),
    )
    .unwrap();
    assert!(more.lines() > first.lines() * 19 / 10);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for l in 0..first.lines() {
        first.frame_hits(l, 2, &mut a);
        more.frame_hits(l, 2, &mut b);
        assert_eq!(a, b);
    }
    // The new batch has new directions.
    assert_ne!(
        more.batches()[0].direction(0),
        more.batches()[1].direction(0)
    );
}

#[test]
fn scene_statistics_match_their_predictions() {
    let scene = common::static_scene(&[cube([1.0, 2.0, 0.5], [0.0; 3])], None);
    let tracer = SceneTracer::new(&scene);
    let list = IntersectionList::build(
        &scene,
        &tracer,
        &LineParams {
            lines: 20_000,
            seed: 1,
        },
        &radiosity::control::Control::default(),
    )
    .unwrap();
    let stats = SceneStats::measure(&scene, &list, 0);
    // The lines are drawn against the box itself: every line crosses it exactly twice.
    assert!((stats.predicted_hits_per_line - 2.0).abs() < 1e-6);
    assert_eq!(stats.mean_hits_per_line, 2.0);
    assert_eq!(stats.histogram[2], 1.0);
    // Mean chord 4V/A = 4/7 within a few percent.
    assert!(
        (stats.mean_segment / (4.0 / 7.0) - 1.0).abs() < 0.02,
        "{}",
        stats.mean_segment
    );
}

#[test]
fn a_cancelled_trace_leaves_the_list_as_it_was() {
    use radiosity::control::{Control, TraceError};
    let scene = animated_scene(4.0, None);
    let tracer = SceneTracer::new(&scene);
    let control = Control::default();
    let params = LineParams {
        lines: 2_000,
        seed: 1,
    };
    let mut list = IntersectionList::build(&scene, &tracer, &params, &control).unwrap();
    assert!(
        (control.fraction() - 1.0).abs() < 1e-12,
        "{}",
        control.fraction()
    );
    let before = list.memory();
    control.cancel();
    assert_eq!(
        list.add_lines(&scene, &tracer, &params, &control),
        Err(TraceError::Cancelled)
    );
    assert_eq!(list.memory(), before);
    assert_eq!(list.batches().len(), 1);
}
