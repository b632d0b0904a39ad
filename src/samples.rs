//! Deterministic generator of the sample glTF 2.0 scenes (`radiosity samples`).
//!
//! Every surface is built on a `Lattice`, an axis-aligned grid of planes: a volume is the set of
//! lattice cells a predicate marks as inside, and its boundary becomes one indexed mesh with one
//! quad per boundary cell face. Every vertex is a lattice point stored once per mesh, so faces
//! that meet share their vertices bit for bit, whatever their material: closed shells are
//! watertight (every edge in exactly two triangles) and free of T-junctions by construction.
//! A small `Builder` packs the arrays into one embedded buffer and writes the glTF JSON.
//!
//! Units are metres and Y is up. Front faces are counter-clockwise seen from the side they face,
//! so the geometric normal `(v1 - v0) × (v2 - v0)` points to the side that is lit. Materials are
//! what the radiosity engine reads: `baseColorFactor` is the diffuse reflectance (metallic 0,
//! roughness 1), `emissiveFactor` the emission, scaled by `KHR_materials_emissive_strength` when
//! it exceeds 1. Every material is one-sided.

use std::collections::{BTreeMap, HashMap};

use base64::Engine as _;
use base64::engine::general_purpose::STANDARD as BASE64;
use glam::{Quat, Vec3};
use serde_json::{Value, json};

/// One generated sample scene.
pub struct Sample {
    /// File name, e.g. "cornell_box.gltf".
    pub file_name: &'static str,
    /// One-line description for the README.
    pub description: &'static str,
    /// The complete .gltf JSON text (buffers embedded as data: URIs, base64), ending in a newline.
    pub gltf: String,
}

/// Every sample scene, in a fixed order. Deterministic: same output bytes every call.
pub fn all() -> Vec<Sample> {
    vec![
        Sample {
            file_name: "cornell_box.gltf",
            description: "Closed 1 m Cornell box (red left wall, green right wall, light in the \
                          centre cell of a 3x3 ceiling) with a short and a tall white block; static.",
            gltf: cornell_box(false),
        },
        Sample {
            file_name: "cornell_moving.gltf",
            description: "The Cornell box with the short block sliding 10 cm along x and back while \
                          turning 90 degrees about Y over 2 s (LINEAR); the tall block is static.",
            gltf: cornell_box(true),
        },
        Sample {
            file_name: "furnace.gltf",
            description: "White furnace: closed 1 m cube, 4x4 quads per face, reflectance 0.999 and \
                          emission 1 everywhere, so the exact radiosity is 1/(1-0.999) = 1000.",
            gltf: furnace(),
        },
        Sample {
            file_name: "parallel_squares.gltf",
            description: "Two coaxial parallel 1 m squares 1 m apart facing each other, the lower \
                          one emitting; analytic form factor between them 0.19982 (open scene).",
            gltf: parallel_squares(),
        },
        Sample {
            file_name: "level.gltf",
            description: "Three 4 m x 3 m x 4 m rooms in a row joined by 1 m x 2 m doorways, one \
                          ceiling light each, and a door swinging 0-90-0 degrees over 2 s.",
            gltf: level(false),
        },
        Sample {
            file_name: "level_lamps.gltf",
            description: "The level lit by KHR_lights_punctual lamps instead of glowing panels: a \
                          warm point light, a spot light pointing down and a point light swinging \
                          on a 1 m pendulum (+-30 degrees over 2 s), with the door swinging.",
            gltf: level(true),
        },
        Sample {
            file_name: "morph_box.gltf",
            description: "A 0.5 m box on a 4 m floor under an emissive panel; one morph target \
                          raises its top 0.5 m and back over 2 s (animated weights).",
            gltf: morph_box(),
        },
        Sample {
            file_name: "panel_room.gltf",
            description: "A room as Blender exports one: a closed 4 m x 2.7 m x 4 m box of 12 \
                          large triangles and a 1 m square emissive panel hanging 1 cm below the \
                          ceiling, every material double-sided (Blender's default), so the \
                          panel's back lights the ceiling through the 1 cm gap; static.",
            gltf: panel_room(),
        },
        Sample {
            file_name: "lamp_room.gltf",
            description: "A lamp-lit room as Blender exports one: a closed 5 m x 2.7 m x 4 m room, \
                          a pillar and a box, every material double-sided, a 100 W point lamp and \
                          a 200 W spot in Blender's units (W / 4 pi x 683 cd), and the box sliding \
                          1 m and back from Blender's frame 1 (t = 1/24 s) to 49 at 24 fps.",
            gltf: lamp_room(),
        },
        Sample {
            file_name: "spheres.gltf",
            description: "Closed 6 m x 3 m x 6 m room lit by a 1 m square ceiling panel, with 12 \
                          icospheres (1,280 triangles each), 2 bobbing and 2 sliding over 1 s \
                          (LINEAR): the large benchmark, 207,616 patches at --patch-size 0.0695.",
            gltf: spheres(),
        },
    ]
}

// ---------------------------------------------------------------------------------------------
// Scenes
// ---------------------------------------------------------------------------------------------

/// Where the Cornell blocks stand (centre of their bottom face) and how far they are turned
/// about Y: the classic scene scaled to a 1 m box, tall block left-back, short block
/// right-front. Their circumscribed circles (radius 0.3/√2 ≈ 0.212 m) stay clear of each other
/// and of the walls, also along the short block's slide, so nothing ever interpenetrates.
const SHORT_BLOCK: Vec3 = Vec3::new(0.17, 0.0, 0.2);
const SHORT_TURN_DEG: f32 = -17.0;
const TALL_BLOCK: Vec3 = Vec3::new(-0.165, 0.0, -0.13);
const TALL_TURN_DEG: f32 = 17.0;
/// How far the short block of `cornell_moving` slides along +x (and back).
const SHORT_SLIDE: f32 = 0.1;

/// The Cornell box; with `moving`, the short block slides and turns.
fn cornell_box(moving: bool) -> String {
    let mut b = Builder::default();
    let white = b.material(Material::diffuse("white", [0.75; 3]));
    let red = b.material(Material::diffuse("red", [0.63, 0.065, 0.05]));
    let green = b.material(Material::diffuse("green", [0.14, 0.45, 0.09]));
    let light = b.material(Material::emitter("light", [0.78; 3], 15.0));

    // All six walls on one 3x3 grid, so the light (the ceiling's centre cell) and every wall
    // meet vertex to vertex: the room is one watertight shell, front wall included.
    let grid = Lattice::uniform(Vec3::new(-0.5, 0.0, -0.5), Vec3::new(0.5, 1.0, 0.5), [3; 3]);
    let room = shell(
        &grid,
        |_| true,
        Facing::Inward,
        |face| match face.normal {
            [1, 0, 0] => red,    // the left wall, at x = -0.5, looks toward +x
            [-1, 0, 0] => green, // the right wall, at x = +0.5
            [0, -1, 0] if face.cell[0] == 1 && face.cell[2] == 1 => light,
            _ => white,
        },
    );
    let room = b.mesh("cornell_room", &room);
    b.node("cornell_room", room, Vec3::ZERO, Quat::IDENTITY);

    // Block meshes have their origin at the centre of the bottom face, so a node rotation turns
    // a block in place and the block rests on the floor (y = 0).
    let short = b.mesh("short_block", &block(Vec3::splat(0.3), white));
    let tall = b.mesh("tall_block", &block(Vec3::new(0.3, 0.6, 0.3), white));
    let short = b.node("short_block", short, SHORT_BLOCK, turn_y(SHORT_TURN_DEG));
    b.node("tall_block", tall, TALL_BLOCK, turn_y(TALL_TURN_DEG));

    if moving {
        let times = b.key_times(&[0.0, 1.0, 2.0]);
        let slid = SHORT_BLOCK + Vec3::X * SHORT_SLIDE;
        let translations = b.vec3s(&[SHORT_BLOCK, slid, SHORT_BLOCK]);
        // 90 degrees in two 45-degree steps: slerp takes the short way, so each step must stay
        // under 180 degrees. A cube turned by 90 degrees looks as it started: the loop is seamless.
        let rotations = b.quats(&[
            turn_y(SHORT_TURN_DEG),
            turn_y(SHORT_TURN_DEG + 45.0),
            turn_y(SHORT_TURN_DEG + 90.0),
        ]);
        let channels = [
            (short, "translation", translations),
            (short, "rotation", rotations),
        ];
        b.animation("short_block_slide", times, &channels);
    }
    let name = if moving {
        "cornell_moving"
    } else {
        "cornell_box"
    };
    b.finish(name)
}

/// How far the panel of `panel_room` hangs below the ceiling.
const PANEL_GAP: f32 = 0.01;

/// A room as a Blender export has it: large triangles, double-sided materials, and a thin
/// emissive panel just below the ceiling (issue 13: the light its back sends into the gap is
/// trapped there physically, not in a model with one radiance per ceiling triangle).
fn panel_room() -> String {
    let mut b = Builder::default();
    let wall = b.material(Material::diffuse("wall", [0.8; 3]).double_sided());
    let panel = b.material(Material::emitter("panel", [0.8; 3], 10.0).double_sided());
    let height = 2.7;
    let grid = Lattice::uniform(
        Vec3::new(-2.0, 0.0, -2.0),
        Vec3::new(2.0, height, 2.0),
        [1; 3],
    );
    let room = shell(&grid, |_| true, Facing::Inward, |_| wall);
    let room = b.mesh("room", &room);
    b.node("room", room, Vec3::ZERO, Quat::IDENTITY);
    let light = square(
        Vec3::new(0.0, height - PANEL_GAP, 0.0),
        1.0,
        Look::Down,
        panel,
    );
    let light = b.mesh("panel", &light);
    b.node("panel", light, Vec3::ZERO, Quat::IDENTITY);
    b.finish("panel_room")
}

/// Candela of a Blender point or spot lamp of `watts` as Blender's glTF exporter writes it
/// (its standard lighting mode: W / 4π × 683 lm/W).
fn blender_candela(watts: f32) -> f32 {
    watts / (4.0 * std::f32::consts::PI) * 683.0
}

/// A lamp-lit room as a Blender 4 export has it (issue 15): large triangles, every material
/// double-sided, `KHR_lights_punctual` lamps in Blender's units, and an animation that starts
/// at Blender's frame 1 (t = 1/24 s), not 0. Seen from outside, every wall's outer side is
/// unlit.
fn lamp_room() -> String {
    let mut b = Builder::default();
    let floor = b.material(Material::diffuse("Floor", [0.45, 0.4, 0.35]).double_sided());
    let wall = b.material(Material::diffuse("Wall", [0.75; 3]).double_sided());
    let ceiling = b.material(Material::diffuse("Ceiling", [0.8; 3]).double_sided());
    let wood = b.material(Material::diffuse("Wood", [0.55, 0.35, 0.2]).double_sided());
    let height = 2.7;
    let grid = Lattice::uniform(
        Vec3::new(-2.5, 0.0, -2.0),
        Vec3::new(2.5, height, 2.0),
        [1; 3],
    );
    let room = shell(
        &grid,
        |_| true,
        Facing::Inward,
        |face| match face.normal {
            [0, 1, 0] => floor,
            [0, -1, 0] => ceiling,
            _ => wall,
        },
    );
    let room = b.mesh("Room", &room);
    b.node("Room", room, Vec3::ZERO, Quat::IDENTITY);
    // A pillar from floor to ceiling, and a box on the floor that slides.
    let pillar = b.mesh("Pillar", &block(Vec3::new(0.3, height, 0.3), wall));
    b.node("Pillar", pillar, Vec3::new(1.4, 0.0, -1.0), Quat::IDENTITY);
    let crate_mesh = b.mesh("Box", &block(Vec3::splat(0.6), wood));
    let start = Vec3::new(-1.2, 0.0, 0.6);
    let node = b.node("Box", crate_mesh, start, turn_y(20.0));
    let fps = 24.0;
    let times = b.key_times(&[1.0 / fps, 25.0 / fps, 49.0 / fps]);
    let slid = start + Vec3::X;
    let path = b.vec3s(&[start, slid, start]);
    b.animation("BoxAction", times, &[(node, "translation", path)]);
    // A 100 W bulb under the ceiling and a 200 W spot on the box's path, as Blender writes them.
    let bulb = b.light(json!({"name": "Bulb", "type": "point",
        "color": [1.0, 0.9, 0.8], "intensity": num(blender_candela(100.0))}));
    b.light_node("Bulb", bulb, Vec3::new(0.3, 2.3, 0.2), Quat::IDENTITY);
    let spot = b.light(
        json!({"name": "Spot", "type": "spot", "intensity": num(blender_candela(200.0)),
        "spot": {"innerConeAngle": 0.3, "outerConeAngle": 0.6}}),
    );
    let down = Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2);
    b.light_node("Spot", spot, Vec3::new(-0.7, 2.5, 0.6), down);
    b.finish("lamp_room")
}

/// The white furnace test.
fn furnace() -> String {
    let mut b = Builder::default();
    // Every patch of a closed furnace sees only furnace walls, so the exact radiosity is
    // E / (1 - rho) = 1000 on every patch whatever the form factors: any deviation is the
    // estimator's error. Reflectance stays below 1 so the solution exists.
    let furnace = b.material(Material::emitter("furnace", [0.999; 3], 1.0));
    let grid = Lattice::uniform(Vec3::new(-0.5, 0.0, -0.5), Vec3::new(0.5, 1.0, 0.5), [4; 3]);
    let walls = shell(&grid, |_| true, Facing::Inward, |_| furnace);
    let mesh = b.mesh("furnace", &walls);
    b.node("furnace", mesh, Vec3::ZERO, Quat::IDENTITY);
    b.finish("furnace")
}

/// Two unit squares facing each other, the textbook form factor case.
fn parallel_squares() -> String {
    let mut b = Builder::default();
    // A black emitter: what the receiver reflects back is absorbed, so the receiver's
    // radiosity is exactly 0.5 x F with F = 0.19982 and no interreflection term.
    let emitter = b.material(Material::emitter("emitter", [0.0; 3], 1.0));
    let white = b.material(Material::diffuse("white", [0.5; 3]));
    let lower = b.mesh("emitter", &square(Vec3::ZERO, 1.0, Look::Up, emitter));
    let upper = b.mesh("receiver", &square(Vec3::Y, 1.0, Look::Down, white));
    b.node("emitter", lower, Vec3::ZERO, Quat::IDENTITY);
    b.node("receiver", upper, Vec3::ZERO, Quat::IDENTITY);
    b.finish("parallel_squares")
}

/// The rooms' extents along x: 4 m each, separated by 0.2 m partition walls, centred on x = 0.
const ROOMS_X: [(f32, f32); 3] = [(-6.2, -2.2), (-2.0, 2.0), (2.2, 6.2)];
/// Partition walls lie between these |x| (both partitions, by symmetry).
const PARTITION: (f32, f32) = (2.0, 2.2);
/// Rooms span z in [-ROOM_HALF_DEPTH, ROOM_HALF_DEPTH] and y in [0, ROOM_HEIGHT].
const ROOM_HALF_DEPTH: f32 = 2.0;
const ROOM_HEIGHT: f32 = 3.0;
/// Doorways: |z| < DOOR_HALF_WIDTH, y < DOOR_HEIGHT, through both partitions.
const DOOR_HALF_WIDTH: f32 = 0.5;
const DOOR_HEIGHT: f32 = 2.0;
/// Ceiling lights: 0.8 m square, 2 cm thick, hanging 2 cm below the ceiling.
const LIGHT_SIZE: f32 = 0.8;
const LIGHT_THICKNESS: f32 = 0.02;
const LIGHT_GAP: f32 = 0.02;
/// Door leaf thickness.
const DOOR_THICKNESS: f32 = 0.04;

/// Three rooms, three lights, one swinging door.
/// The level; with `lamps`, lit by punctual lights under non-emissive fixtures.
fn level(lamps: bool) -> String {
    let mut b = Builder::default();
    let floor = b.material(Material::diffuse("floor", [0.5; 3]));
    let wall = b.material(Material::diffuse("wall", [0.7; 3]));
    let ceiling = b.material(Material::diffuse("ceiling", [0.8; 3]));
    let lamp = if lamps {
        b.material(Material::diffuse("lamp_shade", [0.8; 3]))
    } else {
        b.material(Material::emitter("lamp", [0.8; 3], 10.0))
    };
    let housing = b.material(Material::diffuse("lamp_housing", [0.8; 3]));
    let door = b.material(Material::diffuse("door", [0.55, 0.4, 0.25]));

    // The shell is the boundary of the air: every room on a 0.5 m grid along x, y and z, which
    // puts the doorway edges (z = ±0.5, y = 2) on grid lines; each partition wall is one
    // 0.2 m cell along x, solid except for the doorway cells. The rooms, partitions and the
    // doorways' jambs, lintels and sills then form one closed, T-junction-free surface.
    let mut xs = Vec::new();
    for (x0, x1) in ROOMS_X {
        xs.extend(steps(x0, x1, 8));
    }
    let grid = Lattice {
        axes: [
            xs,
            steps(0.0, ROOM_HEIGHT, 6),
            steps(-ROOM_HALF_DEPTH, ROOM_HALF_DEPTH, 8),
        ],
    };
    let top = grid.cells(1) - 1;
    let air = |cell| {
        let p = grid.centre(cell);
        let in_partition = p.x.abs() > PARTITION.0 && p.x.abs() < PARTITION.1;
        let in_doorway = p.z.abs() < DOOR_HALF_WIDTH && p.y < DOOR_HEIGHT;
        !in_partition || in_doorway
    };
    let shell_mesh = shell(&grid, air, Facing::Inward, |face| match face.normal {
        [0, 1, 0] => floor,
        // The room tops are ceilings; the doorways' lintels count as wall.
        [0, -1, 0] if face.cell[1] == top => ceiling,
        _ => wall,
    });
    let shell_mesh = b.mesh("level_shell", &shell_mesh);
    b.node("level_shell", shell_mesh, Vec3::ZERO, Quat::IDENTITY);

    // A light is a thin closed box (so it is watertight too) whose bottom face emits; the gap
    // above it keeps its top face off the ceiling plane. One mesh, instanced in every room.
    let half = LIGHT_SIZE / 2.0;
    let light = solid_box(
        Vec3::new(-half, 0.0, -half),
        Vec3::new(half, LIGHT_THICKNESS, half),
        |face| match face.normal {
            [0, -1, 0] => lamp,
            _ => housing,
        },
    );
    let light = b.mesh("ceiling_light", &light);
    let names = ["light_0", "light_1", "light_2"];
    for (name, (x0, x1)) in names.into_iter().zip(ROOMS_X) {
        let hanging = ROOM_HEIGHT - LIGHT_GAP - LIGHT_THICKNESS;
        b.node(
            name,
            light,
            Vec3::new((x0 + x1) / 2.0, hanging, 0.0),
            Quat::IDENTITY,
        );
    }

    // The door hangs in the first doorway on the middle room's side: its node's origin is the
    // hinge (the doorway's -z jamb edge on the partition face x = -2), the leaf extends along
    // local +z across the opening and along local +x into the middle room. Turning about +Y
    // swings it into the middle room, so it never cuts the partition; closed, it covers the
    // opening exactly.
    let leaf = solid_box(
        Vec3::ZERO,
        Vec3::new(DOOR_THICKNESS, DOOR_HEIGHT, 2.0 * DOOR_HALF_WIDTH),
        |_| door,
    );
    let leaf = b.mesh("door", &leaf);
    let hinge = Vec3::new(-PARTITION.0, 0.0, -DOOR_HALF_WIDTH);
    let door = b.node("door", leaf, hinge, Quat::IDENTITY);
    let times = b.key_times(&[0.0, 1.0, 2.0]);
    let rotations = b.quats(&[Quat::IDENTITY, turn_y(90.0), Quat::IDENTITY]);
    b.animation("door_swing", times, &[(door, "rotation", rotations)]);
    if !lamps {
        return b.finish("level");
    }

    // Lamps 0.3 m under the fixtures: a warm point light, a spot pointing down (−Z turned to
    // −Y), and a point light on a 1 m pendulum from the third fixture.
    let centre = |(x0, x1): (f32, f32)| (x0 + x1) / 2.0;
    let below = ROOM_HEIGHT - LIGHT_GAP - LIGHT_THICKNESS - 0.3;
    let warm = b.light(
        json!({"name": "warm_lamp", "type": "point", "color": [1.0, 0.85, 0.7], "intensity": 60.0}),
    );
    b.light_node(
        "warm_lamp",
        warm,
        Vec3::new(centre(ROOMS_X[0]), below, 0.0),
        Quat::IDENTITY,
    );
    let spot = b.light(json!({"name": "spot", "type": "spot", "intensity": 150.0,
        "spot": {"innerConeAngle": 0.4, "outerConeAngle": 0.7}}));
    let down = Quat::from_rotation_x(-std::f32::consts::FRAC_PI_2);
    b.light_node(
        "spot",
        spot,
        Vec3::new(centre(ROOMS_X[1]), below, 0.0),
        down,
    );
    let swinging = b.light(json!({"name": "swinging_lamp", "type": "point", "intensity": 60.0}));
    let pivot = Vec3::new(
        centre(ROOMS_X[2]),
        ROOM_HEIGHT - LIGHT_GAP - LIGHT_THICKNESS,
        1.0,
    );
    let swing = |t: f32| {
        let angle = 30f32.to_radians() * (std::f32::consts::PI * t).sin();
        pivot + Vec3::new(angle.sin(), -angle.cos(), 0.0)
    };
    let node = b.light_node("swinging_lamp", swinging, swing(0.0), Quat::IDENTITY);
    let keys: Vec<f32> = (0..=16).map(|k| k as f32 / 8.0).collect();
    let times = b.key_times(&keys);
    let path: Vec<Vec3> = keys.iter().map(|&t| swing(t)).collect();
    let positions = b.vec3s(&path);
    b.animation("lamp_swing", times, &[(node, "translation", positions)]);
    b.finish("level_lamps")
}

/// A box that grows by a morph target.
fn morph_box() -> String {
    let mut b = Builder::default();
    let floor = b.material(Material::diffuse("floor", [0.5; 3]));
    let panel = b.material(Material::emitter("panel", [0.8; 3], 5.0));
    let white = b.material(Material::diffuse("white", [0.7; 3]));
    let floor_mesh = b.mesh("floor", &square(Vec3::ZERO, 4.0, Look::Up, floor));
    let panel_mesh = b.mesh("panel", &square(3.0 * Vec3::Y, 1.0, Look::Down, panel));
    b.node("floor", floor_mesh, Vec3::ZERO, Quat::IDENTITY);
    b.node("panel", panel_mesh, Vec3::ZERO, Quat::IDENTITY);

    // The box has only its 8 corners as vertices, shared by the top and the sides: the target
    // moves the top four up and the sides stretch with them, so the box stays closed at every
    // weight.
    let cube = block(Vec3::splat(0.5), white);
    let lift: Vec<Vec3> = (cube.positions.iter())
        .map(|p| Vec3::new(0.0, if p.y > 0.25 { 0.5 } else { 0.0 }, 0.0))
        .collect();
    let cube = b.morph_mesh("morph_box", &cube, &[lift]);
    let node = b.node("morph_box", cube, Vec3::ZERO, Quat::IDENTITY);
    let times = b.key_times(&[0.0, 1.0, 2.0]);
    // One weight per key (the mesh has one target).
    let weights = b.scalars(&[0.0, 1.0, 0.0]);
    b.animation("morph_box_rise", times, &[(node, "weights", weights)]);
    b.finish("morph_box")
}

/// The spheres room spans x and z in [-SPHERES_HALF_WIDTH, SPHERES_HALF_WIDTH], y in
/// [0, SPHERES_HEIGHT].
const SPHERES_HALF_WIDTH: f32 = 3.0;
const SPHERES_HEIGHT: f32 = 3.0;
/// Icosphere subdivision level of every sphere: 20 x 4^3 = 1,280 triangles.
const SPHERE_LEVEL: usize = 3;
/// How far the lowest vertex of a sphere standing on the floor is above it: close enough to look
/// like it rests there, far enough that no surface touches another.
const SPHERE_GAP: f32 = 0.01;

/// The spheres' materials: name and diffuse reflectance.
const BALL_COLOURS: [(&str, [f64; 3]); 5] = [
    ("white", [0.75; 3]),
    ("green", [0.15, 0.55, 0.15]),
    ("red", [0.7, 0.15, 0.1]),
    ("blue", [0.15, 0.25, 0.7]),
    ("yellow", [0.8, 0.65, 0.2]),
];

/// One sphere of the spheres room.
struct Ball {
    /// Where its centre stands over the floor (x, z) at t = 0 and t = 1 s.
    at: [f32; 2],
    radius: f32,
    /// Index into the room's ball colours.
    colour: usize,
    /// How far the centre travels out (x, y, z), reached at t = 0.5 s, LINEAR there and back;
    /// zero for a static sphere.
    travel: Vec3,
}

/// The spheres room's layout: a back row (z = -2.1) and a front row (z = 2.1) of four static
/// spheres each, 0.5 m and 0.6 m in radius; between them two spheres bob 1.2 m and 0.8 m up by
/// the side walls, and two slide 2.4 m along x in opposite directions at z = -0.7 and z = 0.7.
/// `spheres_keep_clear_of_each_other_and_the_room` checks that no two ever come closer than
/// 0.15 m, nor a sphere to a wall or the ceiling.
const BALLS: [Ball; 12] = {
    const fn fixed(x: f32, z: f32, radius: f32, colour: usize) -> Ball {
        moving(x, z, radius, colour, Vec3::ZERO)
    }
    const fn moving(x: f32, z: f32, radius: f32, colour: usize, travel: Vec3) -> Ball {
        Ball {
            at: [x, z],
            radius,
            colour,
            travel,
        }
    }
    [
        fixed(-2.2, -2.1, 0.6, 0),
        fixed(-0.75, -2.1, 0.5, 2),
        fixed(0.75, -2.1, 0.6, 1),
        fixed(2.2, -2.1, 0.5, 3),
        fixed(-2.2, 2.1, 0.5, 3),
        fixed(-0.75, 2.1, 0.6, 1),
        fixed(0.75, 2.1, 0.5, 2),
        fixed(2.2, 2.1, 0.6, 0),
        moving(-2.2, 0.0, 0.5, 4, Vec3::new(0.0, 1.2, 0.0)),
        moving(2.2, 0.0, 0.5, 4, Vec3::new(0.0, 0.8, 0.0)),
        moving(-1.2, -0.7, 0.4, 0, Vec3::new(2.4, 0.0, 0.0)),
        moving(1.2, 0.7, 0.4, 4, Vec3::new(-2.4, 0.0, 0.0)),
    ]
};

/// The large benchmark: a closed room of 12 spheres under a small ceiling panel, 4 of them
/// moving. The file stays small (16,512 triangles: 1,152 for the room's 0.5 m grid, 1,280 per
/// sphere); the patches come from subdivision at load time: `--patch-size 0.0695` makes 207,616
/// (147,456 of them the room's, each 0.5 m cell cut into 256 triangles; the count is the same
/// for any patch size from 0.0692 to 0.0698), and over 1 s the timeline has 11 frames at
/// `--fps 10`.
fn spheres() -> String {
    let mut b = Builder::default();
    let floor = b.material(Material::diffuse("floor", [0.45; 3]));
    let wall = b.material(Material::diffuse("wall", [0.7; 3]));
    let accent = b.material(Material::diffuse("accent_wall", [0.65, 0.5, 0.3]));
    let ceiling = b.material(Material::diffuse("ceiling", [0.8; 3]));
    let panel = b.material(Material::emitter("panel", [0.78; 3], 40.0));

    // The room on a 0.5 m grid: the panel is the ceiling's centre 2 x 2 cells, so it meets the
    // rest of the ceiling vertex to vertex and the room is one watertight shell.
    let half = SPHERES_HALF_WIDTH;
    let grid = Lattice::uniform(
        Vec3::new(-half, 0.0, -half),
        Vec3::new(half, SPHERES_HEIGHT, half),
        [12, 6, 12],
    );
    let top = grid.cells(1) - 1;
    let centre = |i: usize| i == 5 || i == 6;
    let room = shell(
        &grid,
        |_| true,
        Facing::Inward,
        |face| match face.normal {
            [0, 1, 0] => floor,
            [0, -1, 0] if face.cell[1] == top && centre(face.cell[0]) && centre(face.cell[2]) => {
                panel
            }
            [0, -1, 0] => ceiling,
            [0, 0, 1] => accent, // the back wall, at z = -3, looks toward +z
            _ => wall,
        },
    );
    let room = b.mesh("spheres_room", &room);
    b.node("spheres_room", room, Vec3::ZERO, Quat::IDENTITY);

    let colours =
        BALL_COLOURS.map(|(name, reflectance)| b.material(Material::diffuse(name, reflectance)));
    // One mesh per (radius, colour) in use, instanced by every sphere that has both: the file
    // holds 7 sphere meshes for 12 spheres.
    let mut meshes: Vec<((u32, usize), usize)> = Vec::new();
    let mut moving = Vec::new();
    for (i, ball) in BALLS.iter().enumerate() {
        let key = (ball.radius.to_bits(), ball.colour);
        let mesh = match meshes.iter().find(|(k, _)| *k == key) {
            Some(&(_, mesh)) => mesh,
            None => {
                let sphere = icosphere(SPHERE_LEVEL, ball.radius, colours[ball.colour]);
                let (colour, _) = BALL_COLOURS[ball.colour];
                let name = format!("sphere_{}cm_{colour}", (ball.radius * 100.0).round());
                let mesh = b.mesh(&name, &sphere);
                meshes.push((key, mesh));
                mesh
            }
        };
        let rest = ball_rest(ball);
        let node = b.node(&format!("sphere_{i}"), mesh, rest, Quat::IDENTITY);
        if ball.travel != Vec3::ZERO {
            moving.push((node, rest, ball.travel));
        }
    }
    let times = b.key_times(&[0.0, 0.5, 1.0]);
    let channels: Vec<(usize, &str, usize)> = (moving.iter())
        .map(|&(node, rest, travel)| {
            let path = b.vec3s(&[rest, rest + travel, rest]);
            (node, "translation", path)
        })
        .collect();
    b.animation("spheres_move", times, &channels);
    b.finish("spheres")
}

/// Where a sphere's centre is at t = 0: over its spot, with its lowest vertex `SPHERE_GAP` above
/// the floor.
fn ball_rest(ball: &Ball) -> Vec3 {
    let sphere = icosphere(SPHERE_LEVEL, ball.radius, 0);
    let lowest = sphere.positions.iter().map(|p| p.y).fold(0.0, f32::min);
    Vec3::new(ball.at[0], SPHERE_GAP - lowest, ball.at[1])
}

/// A rotation of `degrees` about +Y.
fn turn_y(degrees: f32) -> Quat {
    Quat::from_rotation_y(degrees.to_radians())
}

// ---------------------------------------------------------------------------------------------
// Geometry
// ---------------------------------------------------------------------------------------------

/// Indexed triangles sharing one vertex array, grouped by material index.
#[derive(Default)]
struct Geometry {
    positions: Vec<Vec3>,
    /// Three vertex indices per triangle, per material index (ordered, so output is stable).
    triangles: BTreeMap<usize, Vec<u32>>,
}

/// An axis-aligned grid: the planes x = `axes[0][i]`, y = `axes[1][j]`, z = `axes[2][k]`, each
/// list strictly increasing. Cell `[i, j, k]` lies between planes i and i + 1 on x, and so on.
struct Lattice {
    axes: [Vec<f32>; 3],
}

impl Lattice {
    /// The box from `min` to `max` cut into `cells` equal cells per axis.
    fn uniform(min: Vec3, max: Vec3, cells: [usize; 3]) -> Lattice {
        Lattice {
            axes: [
                steps(min.x, max.x, cells[0]),
                steps(min.y, max.y, cells[1]),
                steps(min.z, max.z, cells[2]),
            ],
        }
    }

    /// Number of cells along `axis`.
    fn cells(&self, axis: usize) -> usize {
        self.axes[axis].len() - 1
    }

    /// The lattice point with plane indices `index`.
    fn point(&self, index: [usize; 3]) -> Vec3 {
        Vec3::new(
            self.axes[0][index[0]],
            self.axes[1][index[1]],
            self.axes[2][index[2]],
        )
    }

    /// The centre of a cell.
    fn centre(&self, cell: [usize; 3]) -> Vec3 {
        (self.point(cell) + self.point(cell.map(|i| i + 1))) / 2.0
    }
}

/// `n` equal steps from `a` to `b` (n + 1 planes). Computed in f64 and rounded once, so decimal
/// grids land on the nearest f32; both ends are exact.
fn steps(a: f32, b: f32, n: usize) -> Vec<f32> {
    let (a64, b64) = (f64::from(a), f64::from(b));
    (0..=n)
        .map(|i| match i {
            0 => a,
            i if i == n => b,
            i => (a64 + (b64 - a64) * i as f64 / n as f64) as f32,
        })
        .collect()
}

/// Which way the faces of a [`shell`] look.
#[derive(Clone, Copy, PartialEq)]
enum Facing {
    /// Into the volume: the inside of a room.
    Inward,
    /// Out of the volume: the skin of a solid.
    Outward,
}

/// One cell-sized quad of a shell, as seen by the material chooser.
struct Face {
    /// The axis-aligned unit direction the face looks to.
    normal: [i32; 3],
    /// The inside cell the face bounds.
    cell: [usize; 3],
}

/// The boundary of the union of the lattice cells for which `inside` holds (cells beyond the
/// lattice are outside): one quad, two triangles, per cell face between an inside and an
/// outside cell, facing as `facing` says, with the material `material` picks for it.
///
/// The volume must not touch itself along an edge only (two inside cells diagonal across an
/// edge, the other two outside), or that edge would belong to four triangles.
fn shell(
    lattice: &Lattice,
    inside: impl Fn([usize; 3]) -> bool,
    facing: Facing,
    material: impl Fn(&Face) -> usize,
) -> Geometry {
    let mut geometry = Geometry::default();
    // Lattice point -> vertex index: each point becomes one vertex, shared by every quad that
    // touches it, which is what makes the shell watertight.
    let mut vertices: HashMap<[usize; 3], u32> = HashMap::new();
    let cells = [lattice.cells(0), lattice.cells(1), lattice.cells(2)];
    for axis in 0..3 {
        // (axis, u, v) is a right-handed frame: e_u x e_v = e_axis.
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        for plane in 0..=cells[axis] {
            for cu in 0..cells[u] {
                for cv in 0..cells[v] {
                    let at = |along: usize, du: usize, dv: usize| {
                        let mut index = [0; 3];
                        index[axis] = along;
                        index[u] = cu + du;
                        index[v] = cv + dv;
                        index
                    };
                    let below = plane > 0 && inside(at(plane - 1, 0, 0));
                    let above = plane < cells[axis] && inside(at(plane, 0, 0));
                    if below == above {
                        continue;
                    }
                    // An inward face looks toward the inside cell, an outward one away from it.
                    let looks_up_axis = above == (facing == Facing::Inward);
                    let mut normal = [0; 3];
                    normal[axis] = if looks_up_axis { 1 } else { -1 };
                    let cell = if above {
                        at(plane, 0, 0)
                    } else {
                        at(plane - 1, 0, 0)
                    };
                    let slot = material(&Face { normal, cell });

                    // Counter-clockwise around +axis, since e_u x e_v = e_axis.
                    let mut quad = [
                        at(plane, 0, 0),
                        at(plane, 1, 0),
                        at(plane, 1, 1),
                        at(plane, 0, 1),
                    ]
                    .map(|point| {
                        *vertices.entry(point).or_insert_with(|| {
                            geometry.positions.push(lattice.point(point));
                            (geometry.positions.len() - 1) as u32
                        })
                    });
                    if !looks_up_axis {
                        quad.reverse();
                    }
                    let [a, b, c, d] = quad;
                    geometry
                        .triangles
                        .entry(slot)
                        .or_default()
                        .extend([a, b, c, a, c, d]);
                }
            }
        }
    }
    geometry
}

/// A closed axis-aligned box from `min` to `max` facing outward, one quad per side.
fn solid_box(min: Vec3, max: Vec3, material: impl Fn(&Face) -> usize) -> Geometry {
    shell(
        &Lattice::uniform(min, max, [1; 3]),
        |_| true,
        Facing::Outward,
        material,
    )
}

/// A closed box of `size` facing outward, with its origin at the centre of its bottom face.
fn block(size: Vec3, material: usize) -> Geometry {
    let half = Vec3::new(size.x / 2.0, 0.0, size.z / 2.0);
    solid_box(-half, size - half, |_| material)
}

/// A sphere of `radius` about the origin, facing outward: an icosahedron whose triangles are each
/// cut in four, `level` times over, every new vertex pushed out onto the sphere. Each edge's midpoint is
/// made once and shared by both triangles on that edge, so the sphere is watertight.
pub fn icosphere_mesh(level: usize, radius: f32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    // The 12 vertices (0, ±1, ±φ) cyclically, and 20 faces counter-clockwise seen from outside.
    let phi = (1.0 + 5f32.sqrt()) / 2.0;
    let mut unit: Vec<Vec3> = [
        [-1.0, phi, 0.0],
        [1.0, phi, 0.0],
        [-1.0, -phi, 0.0],
        [1.0, -phi, 0.0],
        [0.0, -1.0, phi],
        [0.0, 1.0, phi],
        [0.0, -1.0, -phi],
        [0.0, 1.0, -phi],
        [phi, 0.0, -1.0],
        [phi, 0.0, 1.0],
        [-phi, 0.0, -1.0],
        [-phi, 0.0, 1.0],
    ]
    .map(|p| Vec3::from_array(p).normalize())
    .to_vec();
    let mut triangles: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..level {
        let mut midpoints: HashMap<(u32, u32), u32> = HashMap::new();
        let mut middle = |a: u32, b: u32| {
            *midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
                let m = (unit[a as usize] + unit[b as usize]).normalize();
                unit.push(m);
                (unit.len() - 1) as u32
            })
        };
        triangles = (triangles.iter())
            .flat_map(|&[a, b, c]| {
                let (ab, bc, ca) = (middle(a, b), middle(b, c), middle(c, a));
                [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
            })
            .collect();
    }
    (unit.into_iter().map(|p| p * radius).collect(), triangles)
}

/// [`icosphere_mesh`] of one material.
fn icosphere(level: usize, radius: f32, material: usize) -> Geometry {
    let (positions, triangles) = icosphere_mesh(level, radius);
    Geometry {
        positions,
        triangles: BTreeMap::from([(material, triangles.into_iter().flatten().collect())]),
    }
}

/// Which way a horizontal [`square`] faces.
#[derive(Clone, Copy, PartialEq)]
enum Look {
    Up,
    Down,
}

/// A horizontal square of side `size` centred on `centre`, two triangles, facing `look`.
fn square(centre: Vec3, size: f32, look: Look, material: usize) -> Geometry {
    let h = size / 2.0;
    // Counter-clockwise seen from above: (-x,-z) -> (-x,+z) -> (+x,+z) -> (+x,-z), since
    // e_z x e_x = e_y.
    let mut positions = vec![
        centre + Vec3::new(-h, 0.0, -h),
        centre + Vec3::new(-h, 0.0, h),
        centre + Vec3::new(h, 0.0, h),
        centre + Vec3::new(h, 0.0, -h),
    ];
    if look == Look::Down {
        positions.reverse();
    }
    Geometry {
        positions,
        triangles: BTreeMap::from([(material, vec![0, 1, 2, 0, 2, 3])]),
    }
}

// ---------------------------------------------------------------------------------------------
// glTF builder
// ---------------------------------------------------------------------------------------------

const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
const TRIANGLES: u32 = 4;
const EMISSIVE_STRENGTH: &str = "KHR_materials_emissive_strength";

/// A diffuse material, as the radiosity engine reads it.
struct Material {
    name: &'static str,
    /// Diffuse reflectance per channel (baseColorFactor; metallic 0).
    reflectance: [f64; 3],
    /// Emission colour, each channel at most 1 (emissiveFactor).
    emission: [f64; 3],
    /// Multiplies `emission`; written as KHR_materials_emissive_strength when it is not 1.
    strength: f64,
    /// Both faces reflect (and emit): glTF's `doubleSided`, Blender's default.
    double_sided: bool,
}

impl Material {
    /// A material that only reflects.
    fn diffuse(name: &'static str, reflectance: [f64; 3]) -> Material {
        Material {
            name,
            reflectance,
            emission: [0.0; 3],
            strength: 1.0,
            double_sided: false,
        }
    }

    /// A white emitter of the given strength that also reflects.
    fn emitter(name: &'static str, reflectance: [f64; 3], strength: f64) -> Material {
        Material {
            name,
            reflectance,
            emission: [1.0; 3],
            strength,
            double_sided: false,
        }
    }

    /// The same material on both faces.
    fn double_sided(self) -> Material {
        Material {
            double_sided: true,
            ..self
        }
    }
}

/// The accessor types used here.
#[derive(Clone, Copy)]
enum Kind {
    Scalar,
    Vec3,
    Vec4,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Scalar => "SCALAR",
            Kind::Vec3 => "VEC3",
            Kind::Vec4 => "VEC4",
        }
    }

    fn width(self) -> usize {
        match self {
            Kind::Scalar => 1,
            Kind::Vec3 => 3,
            Kind::Vec4 => 4,
        }
    }
}

/// Collects one scene's glTF objects and the bytes of its single embedded buffer.
#[derive(Default)]
struct Builder {
    bytes: Vec<u8>,
    buffer_views: Vec<Value>,
    accessors: Vec<Value>,
    materials: Vec<Value>,
    meshes: Vec<Value>,
    nodes: Vec<Value>,
    animations: Vec<Value>,
    lights: Vec<Value>,
    uses_emissive_strength: bool,
}

impl Builder {
    /// Adds a material; returns its index.
    fn material(&mut self, m: Material) -> usize {
        let [r, g, b] = m.reflectance;
        let mut material = json!({
            "name": m.name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [r, g, b, 1.0],
                "metallicFactor": 0.0,
                "roughnessFactor": 1.0,
            },
            "emissiveFactor": m.emission,
            "doubleSided": m.double_sided,
        });
        if m.strength != 1.0 {
            material["extensions"] =
                json!({ EMISSIVE_STRENGTH: { "emissiveStrength": m.strength } });
            self.uses_emissive_strength = true;
        }
        push(&mut self.materials, material)
    }

    /// Adds a mesh with one primitive per material of `geometry`; returns its index.
    fn mesh(&mut self, name: &str, geometry: &Geometry) -> usize {
        self.morph_mesh(name, geometry, &[])
    }

    /// Adds a mesh with POSITION morph targets (one displacement per vertex each); returns its
    /// index.
    fn morph_mesh(&mut self, name: &str, geometry: &Geometry, targets: &[Vec<Vec3>]) -> usize {
        // One POSITION accessor shared by every primitive: where two materials meet, the
        // triangles share the same vertices, not copies of them.
        let position = self.positions(&geometry.positions);
        let targets: Vec<Value> = targets
            .iter()
            .map(|t| json!({ "POSITION": self.positions(t) }))
            .collect();
        let mut primitives = Vec::new();
        for (&material, indices) in &geometry.triangles {
            let mut primitive = json!({
                "attributes": { "POSITION": position },
                "indices": self.indices(indices),
                "material": material,
                "mode": TRIANGLES,
            });
            if !targets.is_empty() {
                primitive["targets"] = json!(targets);
            }
            primitives.push(primitive);
        }
        let mut mesh = json!({ "name": name, "primitives": primitives });
        if !targets.is_empty() {
            mesh["weights"] = json!(vec![0.0; targets.len()]);
        }
        push(&mut self.meshes, mesh)
    }

    /// Adds a node showing `mesh`; returns its index. Identity transforms are left out.
    fn node(&mut self, name: &str, mesh: usize, translation: Vec3, rotation: Quat) -> usize {
        let mut node = json!({ "name": name, "mesh": mesh });
        if translation != Vec3::ZERO {
            node["translation"] = translation.to_array().into_iter().map(num).collect();
        }
        if rotation != Quat::IDENTITY {
            node["rotation"] = rotation.to_array().into_iter().map(num).collect();
        }
        push(&mut self.nodes, node)
    }

    /// Adds a `KHR_lights_punctual` light; returns its index.
    fn light(&mut self, light: Value) -> usize {
        push(&mut self.lights, light)
    }

    /// Adds a node carrying light `light`; returns its index.
    fn light_node(&mut self, name: &str, light: usize, translation: Vec3, rotation: Quat) -> usize {
        let mut node = json!({
            "name": name,
            "translation": translation.to_array().into_iter().map(num).collect::<Value>(),
            "extensions": { "KHR_lights_punctual": { "light": light } },
        });
        if rotation != Quat::IDENTITY {
            node["rotation"] = rotation.to_array().into_iter().map(num).collect();
        }
        push(&mut self.nodes, node)
    }

    /// Adds an animation: each channel `(node, path, output)` gets a LINEAR sampler from the key
    /// times accessor `input` to its `output` accessor.
    fn animation(&mut self, name: &str, input: usize, channels: &[(usize, &str, usize)]) {
        let samplers: Vec<Value> = (channels.iter())
            .map(|&(_, _, output)| json!({ "input": input, "output": output, "interpolation": "LINEAR" }))
            .collect();
        let channels: Vec<Value> = (channels.iter().enumerate())
            .map(|(i, &(node, path, _))| json!({ "sampler": i, "target": { "node": node, "path": path } }))
            .collect();
        let animation = json!({ "name": name, "channels": channels, "samplers": samplers });
        self.animations.push(animation);
    }

    /// A VEC3 vertex accessor with the min/max glTF requires of POSITION (and of targets).
    fn positions(&mut self, positions: &[Vec3]) -> usize {
        let flat: Vec<f32> = positions.iter().flat_map(|p| p.to_array()).collect();
        self.floats(Kind::Vec3, &flat, true, Some(ARRAY_BUFFER))
    }

    /// A triangle index accessor.
    fn indices(&mut self, indices: &[u32]) -> usize {
        let bytes: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
        let view = self.view(&bytes, Some(ELEMENT_ARRAY_BUFFER));
        let accessor = json!({
            "bufferView": view,
            "componentType": UNSIGNED_INT,
            "count": indices.len(),
            "type": Kind::Scalar.name(),
        });
        push(&mut self.accessors, accessor)
    }

    /// An animation input (key times in seconds), with the min/max glTF requires of inputs.
    fn key_times(&mut self, times: &[f32]) -> usize {
        self.floats(Kind::Scalar, times, true, None)
    }

    /// An animation output of scalars (morph weights).
    fn scalars(&mut self, values: &[f32]) -> usize {
        self.floats(Kind::Scalar, values, false, None)
    }

    /// An animation output of translations.
    fn vec3s(&mut self, values: &[Vec3]) -> usize {
        let flat: Vec<f32> = values.iter().flat_map(|v| v.to_array()).collect();
        self.floats(Kind::Vec3, &flat, false, None)
    }

    /// An animation output of rotations (x, y, z, w).
    fn quats(&mut self, values: &[Quat]) -> usize {
        let flat: Vec<f32> = values.iter().flat_map(|q| q.to_array()).collect();
        self.floats(Kind::Vec4, &flat, false, None)
    }

    /// A tightly packed f32 accessor of `kind` over `values`, with min/max when `bounds`.
    fn floats(&mut self, kind: Kind, values: &[f32], bounds: bool, target: Option<u32>) -> usize {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes, target);
        let width = kind.width();
        let mut accessor = json!({
            "bufferView": view,
            "componentType": FLOAT,
            "count": values.len() / width,
            "type": kind.name(),
        });
        if bounds {
            let mut min = vec![f32::INFINITY; width];
            let mut max = vec![f32::NEG_INFINITY; width];
            for element in values.chunks_exact(width) {
                for (c, &x) in element.iter().enumerate() {
                    min[c] = min[c].min(x);
                    max[c] = max[c].max(x);
                }
            }
            accessor["min"] = min.into_iter().map(num).collect();
            accessor["max"] = max.into_iter().map(num).collect();
        }
        push(&mut self.accessors, accessor)
    }

    /// Appends `bytes` to the buffer as a new buffer view; returns its index.
    fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        // Every view starts on a 4-byte boundary, as 4-byte components require.
        self.bytes.resize(self.bytes.len().next_multiple_of(4), 0);
        let mut view = json!({
            "buffer": 0,
            "byteOffset": self.bytes.len(),
            "byteLength": bytes.len(),
        });
        if let Some(target) = target {
            view["target"] = json!(target);
        }
        self.bytes.extend_from_slice(bytes);
        push(&mut self.buffer_views, view)
    }

    /// The finished glTF text, every node a root of the single scene.
    fn finish(self, scene: &str) -> String {
        let roots: Vec<usize> = (0..self.nodes.len()).collect();
        let uri = format!(
            "data:application/octet-stream;base64,{}",
            BASE64.encode(&self.bytes)
        );
        let mut doc = json!({
            "asset": { "version": "2.0", "generator": "radiosity samples" },
            "scene": 0,
            "scenes": [{ "name": scene, "nodes": roots }],
            "nodes": self.nodes,
            "meshes": self.meshes,
            "materials": self.materials,
            "accessors": self.accessors,
            "bufferViews": self.buffer_views,
            "buffers": [{ "byteLength": self.bytes.len(), "uri": uri }],
        });
        if !self.animations.is_empty() {
            doc["animations"] = Value::Array(self.animations);
        }
        let mut extensions = Vec::new();
        if self.uses_emissive_strength {
            extensions.push(EMISSIVE_STRENGTH);
        }
        if !self.lights.is_empty() {
            extensions.push("KHR_lights_punctual");
            doc["extensions"] = json!({ "KHR_lights_punctual": { "lights": self.lights } });
        }
        if !extensions.is_empty() {
            doc["extensionsUsed"] = json!(extensions);
        }
        let mut text =
            serde_json::to_string_pretty(&doc).expect("a serde_json::Value always serialises");
        text.push('\n');
        text
    }
}

/// Appends `value` to `list`; returns its index.
fn push(list: &mut Vec<Value>, value: Value) -> usize {
    list.push(value);
    list.len() - 1
}

/// An f32 as a JSON number with the shortest decimal that reads back as the same f32 (`0.15`,
/// not `0.15000000596046448`): glTF readers round JSON numbers to single precision.
fn num(x: f32) -> Value {
    json!(x.to_string().parse::<f64>().unwrap_or(f64::from(x)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sample read back from its own JSON, as a reader would.
    struct Doc {
        json: Value,
        bytes: Vec<u8>,
    }

    impl Doc {
        fn parse(sample: &Sample) -> Doc {
            let json: Value = serde_json::from_str(&sample.gltf).expect("valid JSON");
            let uri = json["buffers"][0]["uri"].as_str().expect("a buffer URI");
            let data = uri
                .strip_prefix("data:application/octet-stream;base64,")
                .expect("data URI");
            let bytes = BASE64.decode(data).expect("base64");
            assert_eq!(json["buffers"][0]["byteLength"], bytes.len());
            Doc { json, bytes }
        }

        /// The 4-byte little-endian words of an accessor (tightly packed, as written here).
        fn words(&self, accessor: &Value) -> Vec<[u8; 4]> {
            let accessor = &self.json["accessors"][accessor.as_u64().expect("index") as usize];
            let view =
                &self.json["bufferViews"][accessor["bufferView"].as_u64().expect("view") as usize];
            let width = match accessor["type"].as_str() {
                Some("SCALAR") => 1,
                Some("VEC3") => 3,
                Some("VEC4") => 4,
                other => panic!("unexpected type {other:?}"),
            };
            let start = view["byteOffset"].as_u64().expect("offset") as usize;
            let count = accessor["count"].as_u64().expect("count") as usize;
            assert_eq!(
                view["byteLength"].as_u64(),
                Some(4 * (width * count) as u64)
            );
            self.bytes[start..start + 4 * width * count]
                .chunks_exact(4)
                .map(|w| [w[0], w[1], w[2], w[3]])
                .collect()
        }

        fn vec3s(&self, accessor: &Value) -> Vec<Vec3> {
            let floats: Vec<f32> = self
                .words(accessor)
                .into_iter()
                .map(f32::from_le_bytes)
                .collect();
            floats.chunks_exact(3).map(Vec3::from_slice).collect()
        }

        /// The triangles of a mesh in its local space, all primitives together, with the first
        /// morph target (if any) applied at `weight`.
        fn triangles(&self, mesh: &Value, weight: f32) -> Vec<[Vec3; 3]> {
            let mut triangles = Vec::new();
            for primitive in mesh["primitives"].as_array().expect("primitives") {
                assert_eq!(primitive["mode"], TRIANGLES);
                let mut positions = self.vec3s(&primitive["attributes"]["POSITION"]);
                if let Some(target) = primitive["targets"].get(0) {
                    let offsets = self.vec3s(&target["POSITION"]);
                    for (p, d) in positions.iter_mut().zip(offsets) {
                        *p += weight * d;
                    }
                }
                let indices: Vec<u32> = self
                    .words(&primitive["indices"])
                    .into_iter()
                    .map(u32::from_le_bytes)
                    .collect();
                for t in indices.chunks_exact(3) {
                    triangles.push([0, 1, 2].map(|k| positions[t[k] as usize]));
                }
            }
            triangles
        }

        fn meshes(&self) -> impl Iterator<Item = (&str, &Value)> {
            self.json["meshes"]
                .as_array()
                .expect("meshes")
                .iter()
                .map(|m| (m["name"].as_str().expect("mesh name"), m))
        }
    }

    fn sample(name: &str) -> Doc {
        let all = all();
        let sample = all
            .iter()
            .find(|s| s.file_name == name)
            .expect("sample exists");
        Doc::parse(sample)
    }

    /// Checks that every undirected edge (by exact position bits) lies in exactly two
    /// triangles, which use it in opposite directions (consistent winding), and that no
    /// triangle is degenerate. Returns the signed volume enclosed: positive when the faces look
    /// outward.
    fn closed_volume(triangles: &[[Vec3; 3]]) -> Result<f32, String> {
        let key = |p: Vec3| p.to_array().map(f32::to_bits);
        let mut directed: HashMap<([u32; 3], [u32; 3]), usize> = HashMap::new();
        for t in triangles {
            if (t[1] - t[0]).cross(t[2] - t[0]).length() < 1e-6 {
                return Err(format!("degenerate triangle {t:?}"));
            }
            for (a, b) in [(0, 1), (1, 2), (2, 0)] {
                *directed.entry((key(t[a]), key(t[b]))).or_default() += 1;
            }
        }
        for (&(a, b), &n) in &directed {
            if n != 1 {
                return Err(format!("edge {a:?}-{b:?} used {n} times in one direction"));
            }
            if directed.get(&(b, a)) != Some(&1) {
                return Err(format!("edge {a:?}-{b:?} has no twin"));
            }
        }
        Ok(triangles
            .iter()
            .map(|t| t[0].dot(t[1].cross(t[2])) / 6.0)
            .sum())
    }

    fn assert_closed(name: &str, triangles: &[[Vec3; 3]]) -> f32 {
        closed_volume(triangles).unwrap_or_else(|e| panic!("{name} is not closed: {e}"))
    }

    /// The checker itself must see a T-junction, a flipped triangle and a hole.
    #[test]
    fn closed_volume_rejects_broken_meshes() {
        let cube = solid_box(Vec3::ZERO, Vec3::ONE, |_| 0);
        let triangles: Vec<[Vec3; 3]> = cube.triangles[&0]
            .chunks_exact(3)
            .map(|t| [0, 1, 2].map(|k| cube.positions[t[k] as usize]))
            .collect();
        assert_eq!(closed_volume(&triangles), Ok(1.0));

        let mut flipped = triangles.clone();
        flipped[0].swap(1, 2);
        assert!(closed_volume(&flipped).is_err());

        let mut holed = triangles.clone();
        holed.pop();
        assert!(closed_volume(&holed).is_err());

        // Split one triangle at the middle of an edge without splitting its neighbour.
        let mut t_junction = triangles.clone();
        let [a, b, c] = t_junction.remove(0);
        let m = (a + b) / 2.0;
        t_junction.extend([[a, m, c], [m, b, c]]);
        assert!(closed_volume(&t_junction).is_err());
    }

    #[test]
    fn scenes_are_deterministic_and_named_as_specified() {
        let (first, second) = (all(), all());
        let names: Vec<&str> = first.iter().map(|s| s.file_name).collect();
        assert_eq!(
            names,
            [
                "cornell_box.gltf",
                "cornell_moving.gltf",
                "furnace.gltf",
                "parallel_squares.gltf",
                "level.gltf",
                "level_lamps.gltf",
                "morph_box.gltf",
                "panel_room.gltf",
                "lamp_room.gltf",
                "spheres.gltf",
            ]
        );
        for (a, b) in first.iter().zip(&second) {
            assert_eq!(a.gltf, b.gltf, "{} differs between calls", a.file_name);
            assert!(a.gltf.ends_with("}\n"), "{}", a.file_name);
            assert!(!a.description.is_empty());
        }
    }

    #[test]
    fn closed_scenes_are_watertight_and_wound_toward_the_inside() {
        let inward = [
            "cornell_room",
            "furnace",
            "level_shell",
            "spheres_room",
            "Room",
        ];
        let expected_volume = [
            ("cornell_room", 1.0),
            ("furnace", 1.0),
            ("level_shell", 3.0 * 48.0 + 2.0 * 0.2 * 2.0),
            ("spheres_room", 6.0 * 3.0 * 6.0),
            ("Room", 5.0 * 2.7 * 4.0),
        ];
        for file in [
            "cornell_box.gltf",
            "cornell_moving.gltf",
            "furnace.gltf",
            "level.gltf",
            "spheres.gltf",
            "lamp_room.gltf",
        ] {
            let doc = sample(file);
            for (name, mesh) in doc.meshes() {
                let volume = assert_closed(name, &doc.triangles(mesh, 0.0));
                if inward.contains(&name) {
                    let (_, v) = expected_volume
                        .iter()
                        .find(|(n, _)| *n == name)
                        .expect("listed");
                    assert!((volume + v).abs() < 1e-3, "{file}/{name}: volume {volume}");
                } else {
                    assert!(
                        volume > 0.0,
                        "{file}/{name} must face outward: volume {volume}"
                    );
                }
            }
        }
    }

    #[test]
    fn morph_box_stays_closed_at_every_weight() {
        let doc = sample("morph_box.gltf");
        let (_, mesh) = doc
            .meshes()
            .find(|(n, _)| *n == "morph_box")
            .expect("the box");
        for (weight, height) in [(0.0, 0.5), (0.5, 0.75), (1.0, 1.0)] {
            let volume = assert_closed("morph_box", &doc.triangles(mesh, weight));
            assert!(
                (volume - 0.25 * height).abs() < 1e-5,
                "weight {weight}: volume {volume}"
            );
        }
    }

    #[test]
    fn open_surfaces_face_each_other() {
        let cases = [
            ("parallel_squares.gltf", "emitter", Vec3::Y),
            ("parallel_squares.gltf", "receiver", Vec3::NEG_Y),
            ("morph_box.gltf", "floor", Vec3::Y),
            ("morph_box.gltf", "panel", Vec3::NEG_Y),
        ];
        for (file, name, up) in cases {
            let doc = sample(file);
            let (_, mesh) = doc.meshes().find(|(n, _)| *n == name).expect("mesh");
            for t in doc.triangles(mesh, 0.0) {
                let normal = (t[1] - t[0]).cross(t[2] - t[0]).normalize();
                assert!(normal.abs_diff_eq(up, 1e-6), "{file}/{name}: {normal}");
            }
        }
    }

    #[test]
    fn required_bounds_are_present() {
        for s in all() {
            let doc = Doc::parse(&s);
            let accessors = &doc.json["accessors"];
            let bounded = |index: &Value| {
                let a = &accessors[index.as_u64().expect("index") as usize];
                a["min"].is_array() && a["max"].is_array()
            };
            for (name, mesh) in doc.meshes() {
                for p in mesh["primitives"].as_array().expect("primitives") {
                    assert!(
                        bounded(&p["attributes"]["POSITION"]),
                        "{}/{name}",
                        s.file_name
                    );
                    for t in p["targets"].as_array().into_iter().flatten() {
                        assert!(bounded(&t["POSITION"]), "{}/{name} target", s.file_name);
                    }
                }
            }
            for a in doc.json["animations"].as_array().into_iter().flatten() {
                for sampler in a["samplers"].as_array().expect("samplers") {
                    assert!(
                        bounded(&sampler["input"]),
                        "{} animation input",
                        s.file_name
                    );
                }
            }
        }
    }

    #[test]
    fn cornell_blocks_keep_clear_of_each_other_and_the_walls() {
        // Circumscribed circles of the 0.3 m footprints, over the short block's whole slide.
        let radius = 0.15 * std::f32::consts::SQRT_2;
        for step in 0..=10 {
            let short = SHORT_BLOCK + Vec3::X * SHORT_SLIDE * step as f32 / 10.0;
            assert!(short.distance(TALL_BLOCK) > 2.0 * radius);
            for c in [short, TALL_BLOCK] {
                assert!(c.x.abs() + radius < 0.5 && c.z.abs() + radius < 0.5, "{c}");
            }
        }
    }

    #[test]
    fn icospheres_are_round_closed_and_face_outward() {
        for level in 0..=SPHERE_LEVEL {
            let sphere = icosphere(level, 0.4, 0);
            let triangles: Vec<[Vec3; 3]> = sphere.triangles[&0]
                .chunks_exact(3)
                .map(|t| [0, 1, 2].map(|k| sphere.positions[t[k] as usize]))
                .collect();
            assert_eq!(triangles.len(), 20 << (2 * level));
            // Euler: V - E + F = 2 with E = 3F/2.
            assert_eq!(sphere.positions.len(), 2 + triangles.len() / 2);
            for p in &sphere.positions {
                assert!((p.length() - 0.4).abs() < 1e-6, "{p}");
            }
            let volume = assert_closed("icosphere", &triangles);
            let ball = 4.0 / 3.0 * std::f32::consts::PI * 0.4f32.powi(3);
            assert!(
                volume > 0.0 && volume < ball,
                "level {level}: volume {volume}"
            );
        }
    }

    /// Over the whole second (sampled every millisecond; the paths are straight between keys),
    /// no two spheres come closer than `SPHERE_CLEARANCE`, nor a sphere to a wall or the
    /// ceiling, and none dips below the floor; at rest, a sphere's lowest vertex is `SPHERE_GAP`
    /// above the floor.
    #[test]
    fn spheres_keep_clear_of_each_other_and_the_room() {
        /// The least distance between two spheres' surfaces, or a sphere and a wall or the
        /// ceiling.
        const SPHERE_CLEARANCE: f32 = 0.15;
        let rests: Vec<Vec3> = BALLS.iter().map(ball_rest).collect();
        let at = |i: usize, t: f32| rests[i] + BALLS[i].travel * (1.0 - (2.0 * t - 1.0).abs());
        for (rest, ball) in rests.iter().zip(&BALLS) {
            let bottom = rest.y - ball.radius;
            assert!(bottom > 0.0 && bottom <= SPHERE_GAP, "{bottom}");
        }
        assert_eq!(BALLS.iter().filter(|b| b.travel != Vec3::ZERO).count(), 4);
        for step in 0..=1000 {
            let t = step as f32 / 1000.0;
            for (i, a) in BALLS.iter().enumerate() {
                let p = at(i, t);
                let reach = p.x.abs().max(p.z.abs()) + a.radius;
                assert!(
                    reach + SPHERE_CLEARANCE <= SPHERES_HALF_WIDTH,
                    "sphere {i} at {t}: {p}"
                );
                assert!(
                    p.y + a.radius + SPHERE_CLEARANCE <= SPHERES_HEIGHT,
                    "sphere {i} at {t}: {p}"
                );
                assert!(p.y - a.radius >= 0.0, "sphere {i} at {t}: {p}");
                for (j, b) in BALLS.iter().enumerate().skip(i + 1) {
                    let gap = p.distance(at(j, t)) - a.radius - b.radius;
                    assert!(
                        gap >= SPHERE_CLEARANCE,
                        "spheres {i} and {j} at {t}: {gap} apart"
                    );
                }
            }
        }
    }
}
