//! No light where there is none: contacts between surfaces, coplanar overlaps (issue 11).
//!
//! The scene is a closed room 2 units wide, lit by an emissive panel under its ceiling, with a box
//! of side 0.6 on its floor. Where the box touches the floor no light passes: the box's bottom and
//! the floor under it are dark, and a floor patch partly under the box is the area average of its
//! lit and dark parts, which a bake with the floor cut along the box's outline measures.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use common::Doc;
use radiosity::bake::Bake;
use radiosity::loader::{LoadOptions, load};
use radiosity::scene::{Scene, Side};
use radiosity::solve::{FrameSolution, SolveParams};
use radiosity::timeline::LineParams;
use serde_json::json;

/// Half the room's side.
const ROOM: f32 = 1.0;
/// Half the box's side.
const BOX: f32 = 0.3;
/// The floor's grid step: cells at the box's edges are partly under it.
const STEP: f32 = 0.125;
/// A coarser step, whose cells under the box's edges are mostly lit.
const COARSE: f32 = 0.4;

/// How the test room is built.
#[derive(Clone, Copy)]
struct Room {
    /// The box's bottom above the floor (negative: sunk into it).
    lift: f32,
    /// Every material double-sided (as Blender exports them).
    double_sided: bool,
    /// The floor also cut along the box's outline.
    cut: bool,
    /// Every coordinate multiplied by this.
    scale: f32,
    /// The floor's grid step.
    step: f32,
    /// The box moves: at rest on the floor at frame 0, `lift` above it at frame 1.
    moving: bool,
    /// The box's centre along x (0: the middle of the room; `ROOM - BOX`: against the wall).
    x: f32,
    /// A point light at this x, at the box's height, instead of the emissive panel.
    point_light: Option<f32>,
    /// Copies of a double-sided card standing in the room (coplanar, overlapping exactly).
    cards: usize,
    /// The copies of the card are triangles of one mesh (else one node each).
    cards_in_one_mesh: bool,
    /// A double-sided table top at y = -0.4 (1.2 wide), under the box's centre.
    table: bool,
}

impl Default for Room {
    fn default() -> Self {
        Self {
            lift: 0.0,
            double_sided: false,
            cut: false,
            scale: 1.0,
            step: STEP,
            moving: false,
            x: 0.0,
            point_light: None,
            cards: 0,
            cards_in_one_mesh: false,
            table: false,
        }
    }
}

/// A horizontal grid at height `y` over the cells between `coords` (both axes), facing up or down.
fn grid(coords: &[f32], y: f32, up: bool) -> (Vec<[f32; 3]>, Vec<u32>) {
    let n = coords.len();
    let positions = coords
        .iter()
        .flat_map(|&z| coords.iter().map(move |&x| [x, y, z]))
        .collect();
    let mut indices = Vec::new();
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let k = (j * n + i) as u32;
            let (a, b, c, d) = (k, k + 1, k + 1 + n as u32, k + n as u32);
            // Counter-clockwise seen from +y is a → d → c (x to the right, z towards the viewer).
            if up {
                indices.extend([a, d, c, a, c, b]);
            } else {
                indices.extend([a, b, c, a, c, d]);
            }
        }
    }
    (positions, indices)
}

impl Room {
    fn floor_coords(&self) -> Vec<f32> {
        let cells = (2.0 * ROOM / self.step).round() as usize;
        let mut xs: Vec<f32> = (0..=cells).map(|k| -ROOM + k as f32 * self.step).collect();
        if self.cut {
            xs.extend([-BOX, BOX]);
            xs.sort_by(f32::total_cmp);
        }
        xs
    }

    fn gltf(&self) -> Vec<u8> {
        let mut doc = Doc::new();
        let material = |doc: &mut Doc, name: &str, grey: f32, emission: f32| {
            doc.push(
                "materials",
                json!({"name": name, "doubleSided": self.double_sided,
                       "emissiveFactor": [emission, emission, emission],
                       "pbrMetallicRoughness": {"baseColorFactor": [grey, grey, grey, 1.0],
                                                "metallicFactor": 0.0}}),
            )
        };
        let wall = material(&mut doc, "wall", 0.5, 0.0);
        let lamp = material(
            &mut doc,
            "lamp",
            0.0,
            if self.point_light.is_some() { 0.0 } else { 1.0 },
        );
        let box_material = material(&mut doc, "box", 0.5, 0.0);
        let s = self.scale;
        let scaled = |p: Vec<[f32; 3]>| -> Vec<[f32; 3]> {
            p.into_iter().map(|v| v.map(|c| c * s)).collect()
        };
        let mut roots = Vec::new();
        let (p, i) = grid(&self.floor_coords(), -ROOM, true);
        let m = doc.mesh(&scaled(p), Some(&i), Some(wall));
        roots.push(doc.node(json!({"name": "floor", "mesh": m})));
        // Ceiling and walls: the room's box without its floor.
        let (p, i) = common::cuboid([2.0 * ROOM; 3], [0.0; 3], true);
        let floor_quad = 2; // the quad at y = -ROOM (vertices 0, 1, 5, 4)
        let i: Vec<u32> = i
            .chunks(6)
            .enumerate()
            .filter(|&(q, _)| q != floor_quad)
            .flat_map(|(_, c)| c.to_vec())
            .collect();
        let m = doc.mesh(&scaled(p), Some(&i), Some(wall));
        roots.push(doc.node(json!({"name": "walls", "mesh": m})));
        let (p, i) = grid(&[-0.4, 0.0, 0.4], 0.95 * ROOM, false);
        let m = doc.mesh(&scaled(p), Some(&i), Some(lamp));
        roots.push(doc.node(json!({"name": "lamp", "mesh": m})));
        let (p, i) = common::cuboid([2.0 * BOX; 3], [0.0; 3], false);
        let m = doc.mesh(&scaled(p), Some(&i), Some(box_material));
        let rest = [
            s * self.x,
            s * (-ROOM + BOX + if self.moving { 0.0 } else { self.lift }),
            0.0,
        ];
        let node = doc.node(json!({"name": "box", "mesh": m, "translation": rest}));
        roots.push(node);
        if self.moving {
            let lifted = [rest[0], rest[1] + s * self.lift, rest[2]];
            let values: Vec<f32> = rest.iter().chain(&lifted).copied().collect();
            doc.animation(
                "lift",
                &[(node, "translation", &[0.0, 1.0], &values, "STEP")],
            );
        }
        if self.cards > 0 {
            let card = doc.push(
                "materials",
                json!({"name": "card", "doubleSided": true,
                       "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1.0],
                                                "metallicFactor": 0.0}}),
            );
            // A vertical card facing +x at x = -0.5: 2 × 2 cells.
            let coords = [-0.4f32, 0.0, 0.4];
            let positions: Vec<[f32; 3]> = coords
                .iter()
                .flat_map(|&z| coords.iter().map(move |&y| [-0.5, y - 0.2, z]))
                .collect();
            let mut one = Vec::new();
            for j in 0..2u32 {
                for i in 0..2u32 {
                    let k = j * 3 + i;
                    one.extend([k, k + 1, k + 4, k, k + 4, k + 3]);
                }
            }
            let copies = if self.cards_in_one_mesh {
                self.cards
            } else {
                1
            };
            let indices: Vec<u32> = one
                .iter()
                .copied()
                .cycle()
                .take(one.len() * copies)
                .collect();
            let m = doc.mesh(&scaled(positions), Some(&indices), Some(card));
            for k in 0..self.cards / copies {
                roots.push(doc.node(json!({"name": format!("card {k}"), "mesh": m})));
            }
        }
        if self.table {
            let top = doc.push(
                "materials",
                json!({"name": "table", "doubleSided": true,
                       "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1.0],
                                                "metallicFactor": 0.0}}),
            );
            let (p, i) = grid(&[-0.6, -0.3, 0.0, 0.3, 0.6], -0.4, true);
            let m = doc.mesh(&scaled(p), Some(&i), Some(top));
            roots.push(doc.node(json!({"name": "table", "mesh": m})));
        }
        if let Some(x) = self.point_light {
            doc.json["extensionsUsed"] = json!(["KHR_lights_punctual"]);
            doc.json["extensions"] = json!({"KHR_lights_punctual": {"lights": [
                {"type": "point", "intensity": 100.0}]}});
            roots.push(doc.node(json!({"name": "outside",
                "translation": [s * x, s * (-ROOM + BOX), 0.0],
                "extensions": {"KHR_lights_punctual": {"light": 0}}})));
        }
        doc.scene(&roots);
        doc.gltf()
    }

    fn scene(&self) -> Scene {
        let options = LoadOptions {
            fps: 1.0,
            ..LoadOptions::default()
        };
        load(&self.gltf(), &options).unwrap()
    }
}

/// Bakes `scene` with `lines` lines and solves every frame.
fn bake(scene: Scene, lines: u64, seed: u64) -> (Bake, Vec<FrameSolution>) {
    bake_under_sky(scene, lines, seed, 0.0)
}

/// [`bake`] with a sky of radiance `sky` around the room (lighting its outside).
fn bake_under_sky(scene: Scene, lines: u64, seed: u64, sky: f64) -> (Bake, Vec<FrameSolution>) {
    let params = SolveParams {
        sky: [sky; 3],
        ..SolveParams::default()
    };
    let bake = Bake::trace(scene, &LineParams { lines, seed }).unwrap();
    let solved = (0..bake.scene.frames.count)
        .map(|f| bake.solve_frame(f, &bake.scene.materials, &params))
        .collect();
    (bake, solved)
}

/// The node index of the scene's node named `name` (roots in the order [`Room::gltf`] makes,
/// for a room without cards: the table follows the box).
fn node(name: &str) -> u32 {
    ["floor", "walls", "lamp", "box", "table"]
        .iter()
        .position(|&n| n == name)
        .unwrap() as u32
}

/// Each patch's corners in scene units at `frame`, with the patch's id and side.
fn patch_corners(scene: &Scene, frame: usize) -> Vec<(u32, [glam::DVec3; 3])> {
    let n = &scene.normalisation;
    scene
        .triangles_at(frame)
        .iter()
        .flat_map(|(corners, faces)| {
            let c = corners.map(|p| n.to_scene(p.as_dvec3()));
            std::iter::once((faces.front, c)).chain(faces.back.map(|b| (b, c)))
        })
        .collect()
}

/// Area-weighted mean radiance (grey: channel 0) of the patches `chosen`, and its standard error
/// (patches taken as independent).
fn mean(scene: &Scene, s: &FrameSolution, chosen: &[u32]) -> (f64, f64) {
    let area: f64 = chosen.iter().map(|&p| scene.patches[p as usize].area).sum();
    let m = chosen
        .iter()
        .map(|&p| scene.patches[p as usize].area * s.radiance[p as usize][0])
        .sum::<f64>()
        / area;
    let var = chosen
        .iter()
        .map(|&p| {
            let e = s.stderr[p as usize].map_or(0.0, |e| e[0]);
            (scene.patches[p as usize].area * e / area).powi(2)
        })
        .sum::<f64>();
    (m, var.sqrt())
}

/// Area-weighted mean radiance of every non-emitting patch facing into the room.
fn scene_mean(scene: &Scene, s: &FrameSolution) -> f64 {
    let lit: Vec<u32> = (0..scene.patches.len() as u32)
        .filter(|&p| {
            let patch = &scene.patches[p as usize];
            !scene.materials[patch.material as usize].is_emitter()
                && s.radiance[p as usize][0] > 0.0
        })
        .collect();
    mean(scene, s, &lit).0
}

/// The box's bottom face (front side, facing the floor) at `frame`.
fn box_bottom(scene: &Scene, frame: usize) -> Vec<u32> {
    let faces: Vec<(u32, [glam::DVec3; 3])> = patch_corners(scene, frame)
        .into_iter()
        .filter(|&(p, _)| {
            let patch = &scene.patches[p as usize];
            patch.source.node == node("box") && patch.side == Side::Front
        })
        .collect();
    let low = faces
        .iter()
        .flat_map(|(_, c)| c.iter().map(|v| v.y))
        .fold(f64::INFINITY, f64::min);
    let tolerance = 1e-6 * scene.normalisation.radius;
    faces
        .into_iter()
        .filter(|(_, c)| c.iter().all(|v| v.y - low < tolerance))
        .map(|(p, _)| p)
        .collect()
}

/// Floor patches (front, facing up) whose corners all lie within `inside` of the centre
/// (in x and z, scene units).
fn floor_within(scene: &Scene, inside: f64) -> Vec<u32> {
    patch_corners(scene, 0)
        .into_iter()
        .filter(|&(p, c)| {
            let patch = &scene.patches[p as usize];
            patch.source.node == node("floor")
                && patch.side == Side::Front
                && c.iter().all(|v| v.x.abs() <= inside && v.z.abs() <= inside)
        })
        .map(|(p, _)| p)
        .collect()
}

#[test]
fn a_box_on_the_floor_leaves_its_contact_dark() {
    let room = Room::default();
    let (bake, solved) = bake(room.scene(), 400_000, 1);
    let (scene, s) = (&bake.scene, &solved[0]);
    let reference = scene_mean(scene, s);
    let bottom = box_bottom(scene, 0);
    assert_eq!(bottom.len(), 2);
    let under = floor_within(scene, f64::from(BOX) + 1e-6);
    assert_eq!(under.len(), 32, "the 4 × 4 floor cells under the box");
    for (what, patches) in [("box bottom", &bottom), ("floor under the box", &under)] {
        for &p in patches.iter() {
            assert!(s.samples[p as usize] > 0, "{what}: patch {p} unsampled");
            let l = s.radiance[p as usize][0];
            assert!(
                l <= 0.01 * reference,
                "{what}: patch {p} has radiance {l}, the scene's mean is {reference}"
            );
        }
    }
    // Only the contact is dark: the box's other faces and the floor around it are lit.
    let (around, _) = mean(scene, s, &floor_within(scene, 0.6));
    assert!(around > 0.3 * reference, "{around} {reference}");
}

/// The share of floor triangle `c` (scene units) outside the square `|x|, |z| ≤ half` that a
/// box standing on it covers: its triangle clipped to the square (Sutherland–Hodgman) in the
/// floor's plane.
fn open_share(c: &[glam::DVec3; 3], half: f64) -> f64 {
    let area = |p: &[glam::DVec2]| {
        let n = p.len();
        0.5 * (0..n)
            .map(|k| p[k].perp_dot(p[(k + 1) % n]))
            .sum::<f64>()
            .abs()
    };
    let triangle: Vec<glam::DVec2> = c.iter().map(|v| glam::DVec2::new(v.x, v.z)).collect();
    let mut inside = triangle.clone();
    // Each side of the square as (axis, sign): keep sign·p[axis] ≤ half.
    for (axis, sign) in [(0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)] {
        let d = |p: glam::DVec2| sign * p[axis] - half;
        let mut out = Vec::new();
        for k in 0..inside.len() {
            let (a, b) = (inside[k], inside[(k + 1) % inside.len()]);
            if d(a) <= 0.0 {
                out.push(a);
            }
            if (d(a) <= 0.0) != (d(b) <= 0.0) {
                out.push(a + (b - a) * (d(a) / (d(a) - d(b))));
            }
        }
        inside = out;
        if inside.is_empty() {
            break;
        }
    }
    1.0 - area(&inside) / area(&triangle)
}

#[test]
fn a_floor_patch_partly_under_the_box_answers_for_what_can_be_seen_of_it() {
    let (lines, seed) = (1_000_000, 2);
    let coarse = Room {
        step: COARSE,
        ..Room::default()
    };
    let (whole, whole_s) = bake(coarse.scene(), lines, seed);
    let cut_room = Room {
        cut: true,
        ..coarse
    };
    let (cut, cut_s) = bake(cut_room.scene(), lines, seed + 1);
    // Per floor cell of the grid that the box's edge crosses: the mean over what can be seen
    // (the part the box does not cover) of the whole bake's two triangles, each answering for
    // its visible part, against that of the cut bake's pieces in the cell (those under the box
    // weigh nothing). Taking the whole triangles' answers as area averages, dark under the box,
    // reads 11 to 25 standard errors off.
    let cell_of = |c: &[glam::DVec3; 3]| {
        let centre = (c[0] + c[1] + c[2]) / 3.0;
        let k = |v: f64| ((v + f64::from(ROOM)) / f64::from(COARSE)).floor() as i32;
        (k(centre.x), k(centre.z))
    };
    let per_cell = |scene: &Scene, s: &FrameSolution| {
        type Cell = Vec<(u32, f64)>;
        let mut cells: std::collections::BTreeMap<(i32, i32), Cell> = Default::default();
        for (p, c) in patch_corners(scene, 0) {
            let patch = &scene.patches[p as usize];
            if patch.source.node == node("floor") && patch.side == Side::Front {
                let seen = patch.area * open_share(&c, f64::from(BOX));
                cells.entry(cell_of(&c)).or_default().push((p, seen));
            }
        }
        let mean = |patches: Cell| {
            let total: f64 = patches.iter().map(|q| q.1).sum();
            let (mut m, mut var) = (0.0, 0.0);
            for (p, seen) in patches {
                let w = seen / total;
                m += w * s.radiance[p as usize][0];
                var += (w * s.stderr[p as usize].map_or(0.0, |e| e[0])).powi(2);
            }
            (m, var.sqrt())
        };
        cells
            .into_iter()
            .map(|(k, patches)| (k, mean(patches)))
            .collect::<std::collections::BTreeMap<_, _>>()
    };
    let (a, b) = (
        per_cell(&whole.scene, &whole_s[0]),
        per_cell(&cut.scene, &cut_s[0]),
    );
    // The 8 cells around the middle one, which the box's outline crosses.
    let edge: Vec<(i32, i32)> = a
        .keys()
        .copied()
        .filter(|&(i, j)| (1..=3).contains(&i) && (1..=3).contains(&j) && (i, j) != (2, 2))
        .collect();
    assert_eq!(edge.len(), 8);
    let z: Vec<f64> = edge
        .iter()
        .map(|cell| {
            let ((la, ea), (lb, eb)) = (a[cell], b[cell]);
            (la - lb) / (ea * ea + eb * eb).sqrt()
        })
        .collect();
    // Each cell within 4 combined standard errors. (Not their sum: the cells see the same
    // walls, so their errors are correlated; and a cell's two triangles are combined as if
    // independent, which if anything widens its error bar.)
    let worst = z.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(
        worst < 4.0,
        "a cell off by {worst:.1} standard errors: {z:.1?}"
    );
}

#[test]
fn the_share_of_a_floor_patch_the_box_leaves_open_is_known_within_its_error_bar() {
    let room = Room::default();
    let bake = Bake::trace(
        room.scene(),
        &LineParams {
            lines: 1000,
            seed: 1,
        },
    )
    .unwrap();
    let scene = &bake.scene;
    let floor: Vec<(u32, [glam::DVec3; 3])> = (patch_corners(scene, 0).into_iter())
        .filter(|&(p, _)| {
            let patch = &scene.patches[p as usize];
            patch.source.node == node("floor") && patch.side == Side::Front
        })
        .collect();
    let mut which = vec![false; scene.patches.len()];
    for &(p, _) in &floor {
        which[p as usize] = true;
    }
    let shares =
        radiosity::direct::visible_shares(scene, bake.tracer(), 0, &which, &Default::default());
    // Against the share of each floor triangle outside the box's outline: exact where the
    // outline does not cross it, within the estimate's own error bar where it does.
    let mut z = Vec::new();
    for (p, c) in floor {
        let (share, variance) = shares[p as usize];
        let exact = open_share(&c, f64::from(BOX));
        if exact == 0.0 || exact == 1.0 {
            assert!(
                share == exact && variance == 0.0,
                "{p}: {share} {variance} against {exact}"
            );
        } else {
            z.push((share - exact) / variance.sqrt());
        }
    }
    assert!(z.len() >= 24, "{} triangles under the outline", z.len());
    // Collapsed strata are conservative: the mean z² is at most about 1 (it reads 0.24 here:
    // the error bars twice the errors), and no triangle is far out. With no error bar for the
    // share (its variance 0, as before), no z is finite.
    let mean_square = z.iter().map(|z| z * z).sum::<f64>() / z.len() as f64;
    let worst = z.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(
        mean_square < 2.0 && worst < 4.0,
        "mean z² {mean_square:.2}: {z:.2?}"
    );
}

#[test]
fn a_slit_under_the_box_lets_light_through_at_any_scale() {
    for scale in [1e-4, 1.0, 1e5] {
        let touching = Room {
            scale,
            ..Room::default()
        };
        let lifted = Room {
            lift: 2e-3 * ROOM,
            scale,
            ..Room::default()
        };
        let (bake_t, solved_t) = bake(touching.scene(), 100_000, 3);
        let (bake_l, solved_l) = bake(lifted.scene(), 100_000, 3);
        let dark = mean(&bake_t.scene, &solved_t[0], &box_bottom(&bake_t.scene, 0)).0;
        let (lit, sigma) = mean(&bake_l.scene, &solved_l[0], &box_bottom(&bake_l.scene, 0));
        assert_eq!(dark, 0.0, "scale {scale}: the touching box's bottom");
        assert!(
            lit > 5.0 * sigma && lit > 0.0,
            "scale {scale}: the lifted box's bottom {lit} ± {sigma}"
        );
        // A slit of 2.5 times the tolerance (1e-5 of the bounding radius) is no contact: no
        // segment leaving the box's bottom is dark.
        let radius = (3.0f32).sqrt() * ROOM;
        let thin = Room {
            lift: 1e-5 * radius,
            scale,
            ..Room::default()
        };
        let (bake_s, _) = bake(thin.scene(), 100_000, 3);
        let tally = bake_s.frame_tally(0);
        for p in box_bottom(&bake_s.scene, 0) {
            assert!(tally.crossings[p as usize] > 0);
            assert!(
                !(tally.row(p as usize).0).contains(&radiosity::solve::tally::ABSORBED),
                "scale {scale}: patch {p} sees a contact through a slit of 1e-5"
            );
        }
    }
}

/// Regression: a line through the seam where a static box's side meets the floor crosses both at
/// one place; taken for a graze, both crossings were dropped and the box's inside saw beyond the
/// floor. With a bright sky outside the room, the inside of a box standing on the floor or sunk
/// halfway into it, and the floor inside the sunk box, get no light at all. (The floor is cut
/// along the box's outline: a floor patch reaching out of the sunk box would carry the room's
/// light inside, as one radiance for the whole patch.)
#[test]
fn no_light_gets_inside_a_box_on_or_in_the_floor_under_a_bright_sky() {
    for lift in [0.0, -BOX] {
        let room = Room {
            lift,
            double_sided: true,
            cut: true,
            ..Room::default()
        };
        let (bake, solved) = bake_under_sky(room.scene(), 400_000, 4, 1.0);
        let (scene, s) = (&bake.scene, &solved[0]);
        let inside =
            |p: &radiosity::scene::Patch| p.source.node == node("box") && p.side == Side::Back;
        let mut hidden: Vec<u32> = (0..scene.patches.len() as u32)
            .filter(|&p| inside(&scene.patches[p as usize]))
            .collect();
        if lift < 0.0 {
            // The floor's upper face inside the sunk box.
            hidden.extend(floor_within(scene, f64::from(BOX) - 1e-6));
        }
        assert!(hidden.len() >= 12);
        for p in hidden {
            assert_eq!(s.radiance[p as usize], [0.0; 3], "lift {lift}: patch {p}");
        }
        // The sky does light the room's outside (the test can see a leak's source).
        let outside = (0..scene.patches.len()).find(|&p| {
            let patch = &scene.patches[p];
            patch.source.node == node("walls") && patch.side == Side::Back
        });
        assert!(s.radiance[outside.unwrap()][0] > 0.1);
    }
}

/// Regression: a shadow ray from the underside of a double-sided table top took the box
/// standing on the table's upper side for a surface touching the underside, and shadowed it
/// from a lamp below the table.
#[test]
fn a_box_on_a_table_does_not_shadow_the_tables_underside() {
    // The box's bottom on the table top at y = -0.4, or 0.05 above it; the lamp below.
    let direct = |lift: f32| {
        let room = Room {
            lift,
            table: true,
            point_light: Some(0.0),
            ..Room::default()
        };
        let (bake, _) = bake(room.scene(), 20_000, 11);
        let scene = &bake.scene;
        let e = bake.direct().irradiance(0, &bake.light_power()).unwrap();
        let table = scene
            .patches
            .iter()
            .position(|p| p.source.node == node("table"))
            .unwrap() as u32;
        let under: Vec<f64> = patch_corners(scene, 0)
            .into_iter()
            .filter(|&(p, c)| {
                let patch = &scene.patches[p as usize];
                patch.source.node == scene.patches[table as usize].source.node
                    && patch.side == Side::Back
                    && c.iter()
                        .all(|v| v.x.abs() <= 0.3 + 1e-6 && v.z.abs() <= 0.3 + 1e-6)
            })
            .map(|(p, _)| e[p as usize][0])
            .collect();
        under
    };
    let (touching, apart) = (direct(0.6), direct(0.65));
    assert_eq!(touching.len(), 8);
    assert!(apart.iter().all(|&e| e > 0.0));
    assert_eq!(touching, apart);
}

#[test]
fn double_sided_surfaces_in_contact_are_dark_too() {
    let room = Room {
        double_sided: true,
        ..Room::default()
    };
    let (bake, solved) = bake(room.scene(), 400_000, 5);
    let (scene, s) = (&bake.scene, &solved[0]);
    let reference = scene_mean(scene, s);
    for p in box_bottom(scene, 0)
        .into_iter()
        .chain(floor_within(scene, f64::from(BOX) + 1e-6))
    {
        let l = s.radiance[p as usize][0];
        assert!(l <= 0.01 * reference, "patch {p}: {l} against {reference}");
    }
}

#[test]
fn a_moving_box_is_dark_underneath_only_where_it_touches() {
    let room = Room {
        lift: 0.2,
        moving: true,
        ..Room::default()
    };
    let (bake, solved) = bake(room.scene(), 300_000, 6);
    let scene = &bake.scene;
    assert_eq!(scene.frames.count, 2);
    let touching = mean(scene, &solved[0], &box_bottom(scene, 0)).0;
    let (lifted, sigma) = mean(scene, &solved[1], &box_bottom(scene, 1));
    assert_eq!(touching, 0.0);
    assert!(lifted > 5.0 * sigma && lifted > 0.0, "{lifted} ± {sigma}");
    let under = floor_within(scene, f64::from(BOX) + 1e-6);
    for p in &under {
        assert_eq!(solved[0].radiance[*p as usize][0], 0.0, "floor patch {p}");
    }
}

/// Regression: a shadow ray from a face pressed against a wall ignored the wall, which it
/// crosses at its very start, so a lamp behind the wall lit the face.
#[test]
fn a_lamp_behind_a_wall_does_not_light_a_face_pressed_against_it() {
    let room = Room {
        x: ROOM - BOX,
        point_light: Some(ROOM + 0.5),
        ..Room::default()
    };
    let (baked, solved) = bake(room.scene(), 20_000, 7);
    let (scene, s) = (&baked.scene, &solved[0]);
    assert_eq!(scene.lights.len(), 1);
    // Nothing inside the closed room is lit: not the box's face against the wall either.
    for (p, l) in s.radiance.iter().enumerate() {
        assert_eq!(l[0], 0.0, "patch {p} ({:?})", scene.patches[p].source);
    }
    // The same lamp inside the room lights it (the test can see light).
    let inside = Room {
        point_light: Some(0.0),
        ..room
    };
    let (_, solved) = bake(inside.scene(), 20_000, 7);
    assert!(solved[0].radiance.iter().any(|l| l[0] > 0.0));
}

/// The card's patches: (copy, triangle within the copy, back side) → patch id.
fn card_patches(scene: &Scene) -> std::collections::BTreeMap<(u32, u32, bool), u32> {
    let first = scene
        .patches
        .iter()
        .filter(|p| p.source.node > node("box"))
        .map(|p| p.source.node)
        .min()
        .unwrap();
    scene
        .patches
        .iter()
        .enumerate()
        .filter(|(_, p)| p.source.node >= first)
        .map(|(i, p)| {
            let (copy, triangle) = (p.source.node - first, p.source.triangle);
            // Copies within one mesh follow each other: 8 triangles each.
            (
                (copy + triangle / 8, triangle % 8, p.side == Side::Back),
                i as u32,
            )
        })
        .collect()
}

/// Regression: a duplicated face (Khronos' BoxAnimated has 120 of 254 patches so) was never
/// crossed by any line and baked black, or hid its twin's other side.
#[test]
fn coplanar_overlapping_cards_share_their_crossings() {
    let (lines, seed) = (600_000, 8);
    let single = Room {
        cards: 1,
        ..Room::default()
    };
    let (one, one_s) = bake(single.scene(), lines, seed);
    // A card alone, and the box on the floor (a contact, not an overlap): no warning.
    assert_eq!(one.warnings(), &[] as &[String]);
    let reference = card_patches(&one.scene);
    assert_eq!(reference.len(), 16);
    for in_one_mesh in [false, true] {
        let doubled = Room {
            cards: 2,
            cards_in_one_mesh: in_one_mesh,
            ..Room::default()
        };
        let (two, two_s) = bake(doubled.scene(), lines, seed + 1);
        let expected = if in_one_mesh {
            r#"node 4 ("card 0") has faces"#
        } else {
            r#"node 4 ("card 0") and node 5 ("card 1") have faces"#
        };
        assert!(
            two.warnings().len() == 1 && two.warnings()[0].starts_with(expected),
            "{:?}",
            two.warnings()
        );
        let patches = card_patches(&two.scene);
        assert_eq!(patches.len(), 32);
        let mut z = Vec::new();
        for (&(copy, triangle, back), &p) in &patches {
            let r = reference[&(0, triangle, back)];
            let (s, t) = (&two_s[0], &one_s[0]);
            assert!(
                s.samples[p as usize] > 0,
                "copy {copy} triangle {triangle} (back: {back}): unsampled"
            );
            let (ea, eb) = (
                s.stderr[p as usize].unwrap()[0],
                t.stderr[r as usize].unwrap()[0],
            );
            z.push(
                (s.radiance[p as usize][0] - t.radiance[r as usize][0])
                    / (ea * ea + eb * eb).sqrt(),
            );
        }
        // 32 patches, each within 4.5 combined standard errors. (Not their sum: patches on one
        // side see the same wall, so their errors are correlated.)
        let worst = z.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(
            worst < 4.5,
            "one mesh: {in_one_mesh}; worst {worst:.1}σ: {z:.1?}"
        );
    }
}

#[test]
fn a_large_patch_no_line_crossed_gets_a_warning() {
    let scene = Room::default().scene();
    let patches = scene.patches.len();
    let frame = |samples: Vec<u64>| {
        std::sync::Arc::new(FrameSolution {
            pieces: Vec::new(),
            pieces_stderr: Vec::new(),
            shape: Vec::new(),
            spread: Vec::new(),
            first: Vec::new(),
            radiance: vec![[0.0; 3]; patches],
            stderr: vec![None; patches],
            samples,
            iterations: 0,
            residual: 0.0,
            converged: true,
        })
    };
    // The wall triangles are large: with 1,000 crossings per patch, one of them should have had
    // hundreds; a floor cell (1/512 of the floor) at 1 crossing per patch would expect 0.3.
    let wall = scene
        .patches
        .iter()
        .position(|p| p.source.node == node("walls"))
        .unwrap();
    let mut samples = vec![1000; patches];
    samples[wall] = 0;
    let missed = frame(samples);
    let fine = frame(vec![1000; patches]);
    let warning =
        radiosity::bake::unsampled_warning(&scene, &[fine.clone(), missed.clone(), missed])
            .expect("a warning");
    // Hidden from the lines, not too small for them (the wall is over 1% of the room).
    assert!(
        warning.starts_with("1 patch was") && !warning.contains("too small"),
        "{warning}"
    );
    assert!(
        warning.contains(r#"in node 1 ("walls"))"#) && warning.contains("frame(s) 1, 2"),
        "{warning}"
    );
    let mut sparse = vec![1; patches];
    let floor = scene
        .patches
        .iter()
        .position(|p| p.source.node == node("floor"))
        .unwrap();
    sparse[floor] = 0;
    assert_eq!(
        radiosity::bake::unsampled_warning(&scene, &[fine.clone(), frame(sparse.clone())]),
        None
    );
    // Every floor cell missed (each expected 0.3 crossings, but together they are a sixth of
    // the room): too small for the lines, and said so.
    let floors: Vec<usize> = (0..patches)
        .filter(|&p| scene.patches[p].source.node == node("floor"))
        .collect();
    for &p in &floors {
        sparse[p] = 0;
    }
    let warning =
        radiosity::bake::unsampled_warning(&scene, &[fine, frame(sparse)]).expect("a warning");
    assert!(
        warning.starts_with(&format!("{} patches were", floors.len()))
            && warning.contains(r#"in node 0 ("floor"))"#)
            && warning.contains("frame(s) 1:")
            && warning.contains("too small for the lines"),
        "{warning}"
    );
}

/// Regression: surfaces no light can reach (inside a moving box, the outside of the closed room)
/// got 1e-11 to 7e-4 in some frames.
#[test]
fn no_light_reaches_inside_a_moving_box_or_outside_the_room() {
    let room = Room {
        lift: 0.2,
        moving: true,
        double_sided: true,
        ..Room::default()
    };
    let (bake, solved) = bake(room.scene(), 300_000, 9);
    let scene = &bake.scene;
    let hidden: Vec<usize> = (0..scene.patches.len())
        .filter(|&p| {
            let patch = &scene.patches[p];
            patch.side == Side::Back
                && [node("box"), node("walls"), node("floor")].contains(&patch.source.node)
        })
        .collect();
    assert!(hidden.len() > 500);
    for (f, s) in solved.iter().enumerate() {
        for &p in &hidden {
            assert_eq!(
                s.radiance[p][0], 0.0,
                "frame {f}, patch {p} ({:?})",
                scene.patches[p].source
            );
        }
    }
}

/// Regression: in the moving Cornell box made double-sided, faces no light can reach (inside the
/// blocks, outside the room) got up to 3e-5 in some frames: lines along the sliding block's
/// bottom edge cross its side, its bottom and the floor at one place, and the side's crossing
/// was shared with the floor's as if they overlapped.
#[test]
fn no_light_reaches_the_inside_of_the_sliding_cornell_block() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell_moving.gltf");
    let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    for m in doc["materials"].as_array_mut().unwrap() {
        m["doubleSided"] = json!(true);
    }
    let options = LoadOptions {
        fps: 12.0,
        ..LoadOptions::default()
    };
    let scene = load(&serde_json::to_vec(&doc).unwrap(), &options).unwrap();
    let (bake, solved) = bake(scene, 300_000, 10);
    let scene = &bake.scene;
    for (f, s) in solved.iter().enumerate() {
        for (p, patch) in scene.patches.iter().enumerate() {
            let emits = scene.materials[patch.material as usize].is_emitter();
            if patch.side == Side::Back && !emits {
                assert_eq!(
                    s.radiance[p], [0.0; 3],
                    "frame {f}, patch {p} ({:?})",
                    patch.source
                );
            }
        }
    }
}

/// The visible shares kept across frames ([`radiosity::direct::KeptShares`]: a static face no
/// moving object comes near keeps its share from the frame it was first measured at) equal
/// the shares measured afresh at every frame, on the moving Cornell box, whose block slides
/// over the floor: to the bit, at every frame, with the floor's shares changing as it slides.
#[test]
fn visible_shares_kept_across_frames_equal_those_measured_at_each_frame() {
    let bake = Bake::trace(
        common::sample_at("cornell_moving.gltf", 4.0),
        &LineParams {
            lines: 1000,
            seed: 1,
        },
    )
    .unwrap();
    let scene = &bake.scene;
    // Every patch of the floor and of the block.
    let which: Vec<bool> = (0..scene.patches.len()).map(|_| true).collect();
    let kept = radiosity::direct::KeptShares::default();
    let mut changed = 0;
    let first = radiosity::direct::visible_shares(scene, bake.tracer(), 0, &which, &kept);
    for frame in 0..scene.frames.count {
        let fresh = radiosity::direct::visible_shares(
            scene,
            bake.tracer(),
            frame,
            &which,
            &Default::default(),
        );
        let reused = radiosity::direct::visible_shares(scene, bake.tracer(), frame, &which, &kept);
        assert_eq!(reused, fresh, "frame {frame}");
        changed += fresh.iter().zip(&first).filter(|(a, b)| a != b).count();
    }
    assert!(kept.bytes() > 0);
    assert!(changed > 0, "the block's contact never moved");
}
