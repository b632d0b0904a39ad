//! Awkward files real exporters write (issue 48's corpus), built in code: overlapping split
//! quads, unindexed and degenerate triangles, sparse accessors, matrix nodes, non-unit
//! quaternions, scenes of cameras only, several scenes, skins without animation, extreme
//! scales and coordinates, materials that leave things out, primitives that are not
//! triangles... Each [`Case`] says what a bake of it must give: baked, or refused with a
//! message naming what is wrong.

use std::f32::consts::{FRAC_PI_2, FRAC_PI_4};

use glam::{Mat4, Quat, Vec3};
use serde_json::{Value, json};

use crate::common::{Doc, cuboid, quad};

/// What baking a case must give.
#[derive(Clone, Copy, Debug)]
pub enum Expect {
    /// Baked: patches, and finite radiance ≥ 0 in every frame.
    Bakes,
    /// Baked, with a warning containing this text.
    Warns(&'static str),
    /// Refused with an error containing this text.
    Refused(&'static str),
}

/// One file of the corpus and what baking it must give.
pub struct Case {
    /// The file's name, without extension.
    pub name: String,
    /// The file's bytes.
    pub bytes: Vec<u8>,
    /// `gltf` or `glb`.
    pub extension: &'static str,
    /// What its bake must give.
    pub expect: Expect,
    /// Whether the Khronos validator finds no error in it: some exporters write what the
    /// specification forbids (non-unit quaternions), and such files are kept apart to check the
    /// others by hand (`node scenes/validate.mjs` over the valid ones).
    pub valid: bool,
    /// Frames per second to bake it at: its animation in 1 to 3 frames.
    pub fps: f64,
    /// The sky's radiance: white unless the case is about the scene's own light.
    pub sky: [f64; 3],
}

impl Case {
    /// A valid `.gltf` (data: URIs) baked at 1 fps under a white sky.
    pub fn gltf(name: &str, doc: &Doc, expect: Expect) -> Self {
        Self::bytes(name, doc.gltf(), "gltf", expect)
    }

    /// A valid `.glb` baked at 1 fps under a white sky.
    pub fn glb(name: &str, doc: &Doc, expect: Expect) -> Self {
        Self::bytes(name, doc.glb(), "glb", expect)
    }

    /// A valid file of these bytes baked at 1 fps under a white sky.
    pub fn bytes(name: &str, bytes: Vec<u8>, extension: &'static str, expect: Expect) -> Self {
        Self {
            name: name.to_string(),
            bytes,
            extension,
            expect,
            valid: true,
            fps: 1.0,
            sky: [1.0; 3],
        }
    }

    /// The file breaks a rule of the specification.
    #[must_use]
    pub fn invalid(self) -> Self {
        Self {
            valid: false,
            ..self
        }
    }

    /// Baked under a black sky: the scene's own light only.
    #[must_use]
    pub fn dark(self) -> Self {
        Self {
            sky: [0.0; 3],
            ..self
        }
    }

    /// Baked at `fps` frames per second.
    #[must_use]
    pub fn at_fps(self, fps: f64) -> Self {
        Self { fps, ..self }
    }
}

/// Every generated case.
pub fn cases() -> Vec<Case> {
    use Expect::{Bakes, Refused, Warns};
    const EMPTY: &str = "no triangles with an area";
    vec![
        Case::glb("split_quads_box", &split_quads_box(), Bakes),
        Case::gltf("unindexed_triangles", &unindexed_triangles(), Bakes),
        Case::gltf("sparse_positions", &sparse_positions(), Bakes),
        Case::glb("sparse_morph_target", &sparse_morph_target(), Bakes),
        Case::gltf("matrix_nodes", &matrix_nodes(), Bakes),
        Case::gltf("non_unit_quaternions", &non_unit_quaternions(), Bakes).invalid(),
        Case::gltf(
            "zero_quaternion",
            &zero_quaternion(),
            Refused("zero quaternion"),
        )
        .invalid(),
        Case::gltf("camera_only", &camera_only(), Refused(EMPTY)),
        Case::gltf("multiple_scenes", &multiple_scenes(), Bakes),
        Case::gltf("scenes_without_default", &scenes_without_default(), Bakes),
        Case::gltf("no_scene", &no_scene(), Warns("no scene")),
        // Valid glTF (a scene's `nodes` is optional), refused by the `gltf` crate's parser.
        Case::gltf(
            "empty_scene",
            &empty_scene(),
            Refused("missing field `nodes`"),
        ),
        Case::glb("skin_without_animation", &skin(true, true), Bakes),
        Case::gltf("skin_without_inverse_binds", &skin(false, true), Bakes),
        Case::gltf(
            "skin_without_joint_attributes",
            &skin(true, false),
            Refused("no joint weight"),
        )
        .invalid(),
        Case::gltf(
            "degenerate_triangles",
            &degenerate_triangles(),
            Warns("zero-area"),
        ),
        Case::gltf(
            "only_degenerate_triangles",
            &only_degenerate(),
            Refused(EMPTY),
        ),
        Case::gltf("t_junction", &t_junction(), Bakes),
        Case::gltf(
            "duplicate_triangles",
            &duplicate_triangles(),
            Warns("overlap in one plane"),
        ),
        Case::gltf(
            "coplanar_decal",
            &coplanar_decal(),
            Warns("overlap in one plane"),
        ),
        Case::gltf("interpenetrating_boxes", &interpenetrating(), Bakes),
        Case::gltf("inconsistent_winding", &inconsistent_winding(), Bakes),
        Case::gltf("needle_triangles", &needle_triangles(), Bakes),
        Case::gltf("huge_scale", &scaled(1e6), Bakes),
        Case::gltf("tiny_scale", &scaled(1e-6), Bakes),
        Case::gltf("zero_scale_node", &odd_scale([0.0; 3]), Warns("zero-area")),
        Case::gltf(
            "flat_scale_node",
            &odd_scale([1.0, 0.0, 1.0]),
            Warns("zero-area"),
        ),
        Case::gltf("negative_scale", &odd_scale([-1.0, 1.0, 1.0]), Bakes),
        Case::gltf(
            "georeferenced",
            &offset_positions([5e5, 100.0, -3e5]),
            Bakes,
        ),
        Case::gltf("node_far_from_origin", &far_node(), Bakes),
        Case::gltf(
            "stray_triangle",
            &stray_triangle(),
            Warns("crossed by no line"),
        ),
        Case::gltf("far_apart", &far_apart(), Bakes),
        Case::gltf("huge_coordinates", &resized_positions(1e30), Bakes),
        Case::gltf("tiny_coordinates", &resized_positions(1e-30), Bakes),
        Case::gltf(
            "materials_without_base_color",
            &no_base_color(),
            Warns("fully metallic"),
        ),
        Case::gltf("alpha_blend_and_mask", &alpha(), Bakes),
        Case::glb("base_color_texture", &texture(true), Bakes),
        Case::gltf(
            "undecodable_texture",
            &texture(false),
            Warns("could not be decoded"),
        ),
        Case::gltf("emissive_only", &emissive_only(), Bakes).dark(),
        Case::gltf("everything_emits", &everything_emits(), Bakes).dark(),
        Case::gltf("unlit", &unlit(), Bakes).dark(),
        Case::gltf("punctual_lights", &punctual_lights(), Bakes).dark(),
        Case::gltf(
            "points_and_lines",
            &points_and_lines(),
            Warns("carry no area"),
        ),
        Case::gltf("lines_only", &lines_only(), Refused(EMPTY)),
        Case::gltf("strips_and_fans", &strips_and_fans(), Bakes),
        // Valid glTF (the validator warns), refused by the `gltf` crate's validation.
        Case::gltf(
            "mesh_without_positions",
            &no_positions(),
            Refused("\"POSITION\""),
        ),
        Case::gltf("empty_primitive", &empty_primitive(), Bakes).invalid(),
        Case::glb("interleaved_vertices", &interleaved(), Bakes),
        Case::gltf("mixed_index_types", &mixed_index_types(), Bakes),
        Case::glb("quantized_positions", &quantized(), Bakes),
        Case::gltf(
            "draco_required",
            &draco(),
            Refused("KHR_draco_mesh_compression"),
        ),
        Case::gltf("unknown_extension_used", &unknown_extension(), Bakes),
        Case::gltf("vanishing_object", &vanishing(), Bakes),
        Case::gltf("cubic_spline_and_step", &spline_and_step(), Bakes),
        Case::gltf("single_keyframe", &single_keyframe(), Bakes),
        Case::gltf("instanced_mesh", &instanced(), Bakes),
        Case::gltf("node_cycle", &node_cycle(), Refused("cycle")).invalid(),
    ]
}

/// A diffuse grey (metallic 0) reflecting `rho`.
fn grey(d: &mut Doc, rho: f32) -> usize {
    d.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [rho, rho, rho, 1.0], "metallicFactor": 0.0}}),
    )
}

/// A material reflecting nothing and emitting `e`.
fn lamp(d: &mut Doc, e: f32) -> usize {
    d.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 1.0], "metallicFactor": 0.0},
               "emissiveFactor": [e, e, e]}),
    )
}

type Geometry = (Vec<[f32; 3]>, Vec<u32>);

/// A node showing `geometry` in `material`; `node` gives its other fields (a transform).
fn object(d: &mut Doc, (positions, indices): &Geometry, material: usize, mut node: Value) -> usize {
    let mesh = d.mesh(positions, Some(indices), Some(material));
    node["mesh"] = json!(mesh);
    d.node(node)
}

/// The floor of every open scene: 4 m square at y = 0, facing up.
fn floor() -> Geometry {
    quad(2.0, 0.0, true)
}

/// A 1 m box standing on the floor at the origin.
fn unit_box() -> Geometry {
    cuboid([1.0; 3], [0.0, 0.5, 0.0], false)
}

/// The floor and a box on it, grey: nodes.
fn stage(d: &mut Doc) -> [usize; 2] {
    let m = grey(d, 0.5);
    [
        object(d, &floor(), m, json!({})),
        object(d, &unit_box(), m, json!({})),
    ]
}

/// A closed 4 m room, faces inward, in `material`: a node.
fn room(d: &mut Doc, material: usize) -> usize {
    object(
        d,
        &cuboid([4.0, 3.0, 4.0], [0.0, 1.5, 0.0], true),
        material,
        json!({}),
    )
}

/// `geometry` with every position through `f`.
fn map(geometry: Geometry, f: impl Fn([f32; 3]) -> [f32; 3]) -> Geometry {
    (geometry.0.into_iter().map(f).collect(), geometry.1)
}

/// A buffer view of `bytes` (4-byte aligned), with `stride` if given.
fn view(d: &mut Doc, bytes: &[u8], stride: Option<usize>) -> usize {
    while !d.bin.len().is_multiple_of(4) {
        d.bin.push(0);
    }
    let offset = d.bin.len();
    d.bin.extend_from_slice(bytes);
    let mut v = json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()});
    if let Some(stride) = stride {
        v["byteStride"] = json!(stride);
    }
    d.push("bufferViews", v)
}

/// The buffer view of accessor `a`.
fn view_of(d: &Doc, a: usize) -> Value {
    d.json["accessors"][a]["bufferView"].clone()
}

/// Adds `primitive` to mesh `mesh`.
fn push_primitive(d: &mut Doc, mesh: usize, primitive: Value) {
    if let Some(primitives) = d.json["meshes"][mesh]["primitives"].as_array_mut() {
        primitives.push(primitive);
    }
}

/// Componentwise (min, max) of `points`.
fn bounds(points: &[[f32; 3]]) -> ([f32; 3], [f32; 3]) {
    points
        .iter()
        .fold(([f32::MAX; 3], [f32::MIN; 3]), |(lo, hi), p| {
            (
                std::array::from_fn(|k| lo[k].min(p[k])),
                std::array::from_fn(|k| hi[k].max(p[k])),
            )
        })
}

fn bytes_f32(values: impl IntoIterator<Item = f32>) -> Vec<u8> {
    values.into_iter().flat_map(f32::to_le_bytes).collect()
}

/// Khronos' `BoxAnimated` draws each quad of its box as three overlapping triangles: ABC, ACD
/// and ABD over them (edges shared by three and four triangles, faces overlapping in a plane).
fn split_quads_box() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.6);
    let (corners, two) = unit_box();
    let three: Vec<u32> = (two.chunks(6))
        .flat_map(|t| [t[0], t[1], t[2], t[3], t[4], t[5], t[0], t[1], t[5]])
        .collect();
    let nodes = [
        object(&mut d, &floor(), m, json!({})),
        object(&mut d, &(corners, three), m, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// Triangle soup: every triangle its own three vertices, no indices (STL-like exports).
fn unindexed_triangles() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let soup = |(v, i): Geometry| -> Vec<[f32; 3]> { i.iter().map(|&k| v[k as usize]).collect() };
    let nodes: Vec<usize> = [soup(floor()), soup(unit_box())]
        .iter()
        .map(|positions| {
            let mesh = d.mesh(positions, None, Some(m));
            d.node(json!({"mesh": mesh}))
        })
        .collect();
    d.scene(&nodes);
    d
}

/// A box whose positions are a sparse accessor: the top corners of one side raised over the
/// base buffer view (a wedge), indices as bytes.
fn sparse_positions() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let (mut corners, indices) = unit_box();
    let flat: Vec<f32> = corners.iter().flatten().copied().collect();
    let base = d.floats(&flat, "VEC3");
    let base_view = view_of(&d, base);
    // Corners 6 and 7 are the top ones at z = +0.5 (bits: 1 x, 2 y, 4 z).
    let raised: Vec<[f32; 3]> = [6, 7]
        .map(|k: usize| [corners[k][0], corners[k][1] + 0.5, corners[k][2]])
        .to_vec();
    corners[6] = raised[0];
    corners[7] = raised[1];
    let sparse_indices = view(&mut d, &[6, 7], None);
    let values = view(&mut d, &bytes_f32(raised.iter().flatten().copied()), None);
    let (min, max) = bounds(&corners);
    let positions = d.push(
        "accessors",
        json!({"bufferView": base_view, "componentType": 5126, "count": 8, "type": "VEC3",
               "min": min, "max": max,
               "sparse": {"count": 2, "indices": {"bufferView": sparse_indices, "componentType": 5121},
                          "values": {"bufferView": values}}}),
    );
    let idx = d.indices(&indices, 5123);
    let mesh = d.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": positions}, "indices": idx, "material": m}]}),
    );
    let nodes = [
        object(&mut d, &floor(), m, json!({})),
        d.node(json!({"mesh": mesh})),
    ];
    d.scene(&nodes);
    d
}

/// Blender's shape keys: a morph target as a sparse accessor without a buffer view (zeros but
/// the top corners), its weight animated from 0 to 1 over 2 s.
fn sparse_morph_target() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let mesh = d.mesh(&unit_box().0, Some(&unit_box().1), Some(m));
    let top: [u16; 4] = [2, 3, 6, 7];
    let sparse_indices = view(
        &mut d,
        &top.iter()
            .flat_map(|k| k.to_le_bytes())
            .collect::<Vec<u8>>(),
        None,
    );
    let values = view(
        &mut d,
        &bytes_f32(top.iter().flat_map(|_| [0.0, 0.5, 0.0])),
        None,
    );
    let target = d.push(
        "accessors",
        json!({"componentType": 5126, "count": 8, "type": "VEC3", "min": [0.0, 0.0, 0.0],
               "max": [0.0, 0.5, 0.0],
               "sparse": {"count": 4, "indices": {"bufferView": sparse_indices, "componentType": 5123},
                          "values": {"bufferView": values}}}),
    );
    d.json["meshes"][mesh]["primitives"][0]["targets"] = json!([{"POSITION": target}]);
    d.json["meshes"][mesh]["weights"] = json!([0.0]);
    let morphed = d.node(json!({"mesh": mesh}));
    let floor = object(&mut d, &floor(), m, json!({}));
    d.scene(&[floor, morphed]);
    d.animation(
        "grow",
        &[(morphed, "weights", &[0.0, 2.0], &[0.0, 1.0], "LINEAR")],
    );
    d
}

/// Column-major `matrix` of a node: scale, then rotation, then translation.
fn matrix(scale: [f32; 3], rotation: Quat, translation: [f32; 3]) -> Value {
    let m =
        Mat4::from_scale_rotation_translation(Vec3::from(scale), rotation, Vec3::from(translation));
    json!(m.to_cols_array())
}

/// Nodes placed by `matrix` (COLLADA and CAD converters): nested, non-uniformly scaled, one
/// mirrored (a negative determinant).
fn matrix_nodes() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let child = object(
        &mut d,
        &unit_box(),
        m,
        json!({"matrix": matrix([0.5, 0.5, 0.5], Quat::from_rotation_x(0.6), [0.0, 1.2, 0.0])}),
    );
    let parent = object(
        &mut d,
        &unit_box(),
        m,
        json!({"children": [child],
               "matrix": matrix([2.0, 1.0, 0.5], Quat::from_rotation_y(0.5), [-0.5, 0.0, 0.5])}),
    );
    let mirrored = object(
        &mut d,
        &unit_box(),
        m,
        json!({"matrix": matrix([-0.5, 0.5, 0.5], Quat::from_rotation_y(-0.3), [1.2, 0.0, -1.0])}),
    );
    let floor = object(&mut d, &floor(), m, json!({}));
    d.scene(&[floor, parent, mirrored]);
    d
}

/// Rotations whose quaternions are not of length 1, static and animated (hand-edited files and
/// older exporters write them; the specification requires unit quaternions).
fn non_unit_quaternions() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let floor = object(&mut d, &floor(), m, json!({}));
    let doubled = object(
        &mut d,
        &unit_box(),
        m,
        json!({"rotation": [0.0, 0.0, 0.0, 2.0], "translation": [-1.0, 0.0, 0.0]}),
    );
    let short = object(
        &mut d,
        &unit_box(),
        m,
        json!({"rotation": [0.0, 0.3, 0.0, 0.3], "scale": [0.5, 0.5, 0.5], "translation": [1.0, 0.0, 0.0]}),
    );
    d.scene(&[floor, doubled, short]);
    d.animation(
        "turn",
        &[(
            short,
            "rotation",
            &[0.0, 2.0],
            &[0.0, 0.3, 0.0, 0.3, 0.0, 2.0, 0.0, 0.5],
            "LINEAR",
        )],
    );
    d
}

/// A rotation of four zeros (a quaternion with no direction at all).
fn zero_quaternion() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let floor = object(&mut d, &floor(), m, json!({}));
    let b = object(
        &mut d,
        &unit_box(),
        m,
        json!({"rotation": [0.0, 0.0, 0.0, 0.0]}),
    );
    d.scene(&[floor, b]);
    d
}

/// The rotation of a camera or light looking straight down (-Y).
fn down() -> [f32; 4] {
    Quat::from_rotation_x(-FRAC_PI_2).to_array()
}

/// Cameras and an empty node, no mesh: nothing to bake.
fn camera_only() -> Doc {
    let mut d = Doc::new();
    let p = d.push(
        "cameras",
        json!({"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.1, "aspectRatio": 1.5}}),
    );
    let o = d.push(
        "cameras",
        json!({"type": "orthographic", "orthographic": {"xmag": 2.0, "ymag": 2.0, "znear": 0.0, "zfar": 50.0}}),
    );
    let a = d.node(json!({"camera": p, "translation": [0.0, 1.0, 5.0]}));
    let b = d.node(json!({"camera": o, "rotation": down(), "translation": [0.0, 10.0, 0.0]}));
    let empty = d.node(json!({"name": "empty"}));
    d.scene(&[a, b, empty]);
    d
}

/// Two scenes, the second the default: a box alone, and the floor with two boxes.
fn multiple_scenes() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let alone = object(&mut d, &unit_box(), m, json!({}));
    d.scene(&[alone]);
    let [floor, b] = stage(&mut d);
    let other = object(
        &mut d,
        &unit_box(),
        m,
        json!({"translation": [1.2, 0.0, 0.0]}),
    );
    d.scene(&[floor, b, other]);
    d
}

/// Two scenes and no `scene`: which one is shown is up to the reader.
fn scenes_without_default() -> Doc {
    let mut d = multiple_scenes();
    if let Some(root) = d.json.as_object_mut() {
        root.remove("scene");
    }
    d
}

/// Nodes and no scene at all.
fn no_scene() -> Doc {
    let mut d = Doc::new();
    stage(&mut d);
    d
}

/// A default scene without nodes (and a mesh node outside it).
fn empty_scene() -> Doc {
    let mut d = Doc::new();
    stage(&mut d);
    d.push("scenes", json!({"name": "nothing"}));
    d.json["scene"] = json!(0);
    d
}

/// Khronos' `SimpleSkin` strip (10 vertices, two joints, the upper joint bent) without an
/// animation: posed once. Without `inverse_binds` the joints' bind matrices are left out (the
/// identity); without `joint_attributes` the mesh has no `JOINTS_0`/`WEIGHTS_0` although its
/// node has a skin (which the specification forbids).
fn skin(inverse_binds: bool, joint_attributes: bool) -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let positions: Vec<[f32; 3]> = (0..10)
        .map(|v| {
            [
                if v % 2 == 0 { -0.5 } else { 0.5 },
                0.5 * (v / 2) as f32,
                0.0,
            ]
        })
        .collect();
    let indices: Vec<u32> = (0..4)
        .flat_map(|r| {
            let a = 2 * r;
            [a, a + 1, a + 3, a, a + 3, a + 2]
        })
        .collect();
    let mesh = d.mesh(&positions, Some(&indices), Some(m));
    if joint_attributes {
        // The upper joint's share rises from 0 at y = 0.5 to 1 at y = 1.5; a joint of weight
        // 0 is written as joint 0 (the validator warns of unused joints that are not).
        let upper = |p: &[f32; 3]| (p[1] - 0.5).clamp(0.0, 1.0);
        let joints: Vec<u8> = (positions.iter())
            .flat_map(|p| match upper(p) {
                0.0 => [0, 0, 0, 0],
                1.0 => [1, 0, 0, 0],
                _ => [0, 1, 0, 0],
            })
            .collect();
        let weights: Vec<f32> = (positions.iter())
            .flat_map(|p| match upper(p) {
                0.0 | 1.0 => [1.0, 0.0, 0.0, 0.0],
                u => [1.0 - u, u, 0.0, 0.0],
            })
            .collect();
        let joints = view(&mut d, &joints, None);
        let joints = d.push(
            "accessors",
            json!({"bufferView": joints, "componentType": 5121, "count": 10, "type": "VEC4"}),
        );
        let weights = d.floats(&weights, "VEC4");
        let attributes = &mut d.json["meshes"][mesh]["primitives"][0]["attributes"];
        attributes["JOINTS_0"] = json!(joints);
        attributes["WEIGHTS_0"] = json!(weights);
    }
    let bent = d.node(
        json!({"translation": [0.0, 1.0, 0.0], "rotation": Quat::from_rotation_z(FRAC_PI_4).to_array()}),
    );
    let root = d.node(json!({"children": [bent]}));
    let mut skin = json!({"joints": [root, bent]});
    if inverse_binds {
        let mut ibm: Vec<f32> = Mat4::IDENTITY.to_cols_array().to_vec();
        ibm.extend(Mat4::from_translation(Vec3::new(0.0, -1.0, 0.0)).to_cols_array());
        skin["inverseBindMatrices"] = json!(d.floats(&ibm, "MAT4"));
    }
    let skin = d.push("skins", skin);
    let skinned = d.node(json!({"mesh": mesh, "skin": skin}));
    let floor = object(&mut d, &quad(2.0, -0.01, true), m, json!({}));
    d.scene(&[skinned, root, floor]);
    d
}

/// The box's corners with two more (corner 0 again and the middle of the edge from corner 0
/// to 1), and triangles of no area over them: a repeated index, two corners at one position,
/// three corners on a line.
fn with_degenerates() -> Geometry {
    let (mut corners, indices) = unit_box();
    let (a, b) = (corners[0], corners[1]);
    corners.extend([a, std::array::from_fn(|k| 0.5 * (a[k] + b[k]))]);
    (corners, indices)
}

/// A box with zero-area triangles among its faces (exports of welded or collapsed edges).
fn degenerate_triangles() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let (corners, mut indices) = with_degenerates();
    indices.extend([0, 0, 1, 0, 1, 8, 0, 9, 1]);
    let nodes = [
        object(&mut d, &floor(), m, json!({})),
        object(&mut d, &(corners, indices), m, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// A mesh whose every triangle has no area.
fn only_degenerate() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let (corners, _) = with_degenerates();
    let node = object(
        &mut d,
        &(corners, vec![0, 0, 1, 0, 1, 8, 0, 9, 1]),
        m,
        json!({}),
    );
    d.scene(&[node]);
    d
}

/// Corners and two up-facing triangles of the rectangle from (x0, z0) to (x1, z1) at y = 0.
fn tile(x0: f32, z0: f32, x1: f32, z1: f32, base: u32) -> ([[f32; 3]; 4], [u32; 6]) {
    (
        [[x0, 0.0, z0], [x1, 0.0, z0], [x1, 0.0, z1], [x0, 0.0, z1]],
        [0, 2, 1, 0, 3, 2].map(|k| base + k),
    )
}

/// A floor of three tiles: the left one whole, the right half cut in two, so the middle of the
/// left tile's edge is a corner of two others (a T-junction); a box stands over it.
fn t_junction() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let tiles = [
        tile(-2.0, -2.0, 0.0, 2.0, 0),
        tile(0.0, -2.0, 2.0, 0.0, 4),
        tile(0.0, 0.0, 2.0, 2.0, 8),
    ];
    let positions: Vec<[f32; 3]> = tiles.iter().flat_map(|t| t.0).collect();
    let indices: Vec<u32> = tiles.iter().flat_map(|t| t.1).collect();
    let nodes = [
        object(&mut d, &(positions, indices), m, json!({})),
        object(
            &mut d,
            &cuboid([0.6; 3], [0.0, 0.3, 0.0], false),
            m,
            json!({}),
        ),
    ];
    d.scene(&nodes);
    d
}

/// Geometry drawn twice: a box mesh under two nodes at one place, the floor's triangles three
/// times over in its mesh, and a card of one quad in both windings (back-to-back coincident
/// faces, as foliage exports are).
fn duplicate_triangles() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let (v, i) = floor();
    let thrice = i.repeat(3);
    let card_v = vec![
        [1.0, 0.0, 1.0],
        [1.8, 0.0, 1.0],
        [1.8, 0.8, 1.0],
        [1.0, 0.8, 1.0],
    ];
    let card_i = vec![0, 1, 2, 0, 2, 3, 0, 2, 1, 0, 3, 2];
    let mesh = d.mesh(&unit_box().0, Some(&unit_box().1), Some(m));
    let nodes = [
        object(&mut d, &(v, thrice), m, json!({})),
        d.node(json!({"mesh": mesh})),
        d.node(json!({"mesh": mesh})),
        object(&mut d, &(card_v, card_i), m, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// A decal: a quad of another material lying in the floor's plane over part of it, and a
/// second one exactly over one of the floor's triangles.
fn coplanar_decal() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let red = d.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.1, 0.1, 1.0], "metallicFactor": 0.0}}),
    );
    let (fv, fi) = floor();
    let over = (fv.clone(), fi[..3].to_vec());
    let nodes = [
        object(&mut d, &(fv, fi), m, json!({})),
        object(
            &mut d,
            &quad(0.7, 0.0, true),
            red,
            json!({"translation": [1.0, 0.0, 1.0]}),
        ),
        object(&mut d, &over, red, json!({})),
        object(
            &mut d,
            &unit_box(),
            m,
            json!({"translation": [-1.0, 0.0, -1.0]}),
        ),
    ];
    d.scene(&nodes);
    d
}

/// Boxes through each other and through the floor (a level's props pushed into the ground).
fn interpenetrating() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let nodes = [
        object(&mut d, &floor(), m, json!({})),
        object(
            &mut d,
            &unit_box(),
            m,
            json!({"translation": [0.0, -0.5, 0.0]}),
        ),
        object(
            &mut d,
            &unit_box(),
            m,
            json!({"translation": [0.4, -0.2, 0.3], "rotation": Quat::from_rotation_y(FRAC_PI_4).to_array()}),
        ),
    ];
    d.scene(&nodes);
    d
}

/// A box whose faces alternate between outward and inward winding.
fn inconsistent_winding() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let (v, i) = unit_box();
    let flipped: Vec<u32> = (i.chunks(3).enumerate())
        .flat_map(|(k, t)| {
            if k % 4 < 2 {
                [t[0], t[1], t[2]]
            } else {
                [t[0], t[2], t[1]]
            }
        })
        .collect();
    let nodes = [
        object(&mut d, &floor(), m, json!({})),
        object(&mut d, &(v, flipped), m, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// The floor as a fan of 400 slivers from one corner (long edges 4 m, short ones 1 to 3 cm)
/// and a wall of needles 1 µm wide.
fn needle_triangles() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let mut v = vec![[-2.0, 0.0, -2.0]];
    v.extend((0..=200).map(|k| [2.0, 0.0, -2.0 + 0.02 * k as f32]));
    v.extend((1..=200).map(|k| [2.0 - 0.02 * k as f32, 0.0, 2.0]));
    let fan: Vec<u32> = (1..v.len() as u32 - 1)
        .flat_map(|k| [0, k + 1, k])
        .collect();
    let needles_v: Vec<[f32; 3]> = (0..20)
        .flat_map(|k| {
            let x = -1.0 + 0.1 * k as f32;
            [[x, 0.0, 0.0], [x + 1e-6, 0.0, 0.0], [x, 1.5, 0.0]]
        })
        .collect();
    let needles_i: Vec<u32> = (0..60).collect();
    let nodes = [
        object(&mut d, &(v, fan), m, json!({})),
        object(&mut d, &(needles_v, needles_i), m, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// The stage under a root scaled by `s` (a file in the wrong units: km, µm).
fn scaled(s: f32) -> Doc {
    let mut d = Doc::new();
    let children = stage(&mut d);
    let root = d.node(json!({"children": children, "scale": [s, s, s]}));
    d.scene(&[root]);
    d
}

/// The stage and a second box whose node is scaled by `scale` (zero, flat, mirrored: how
/// animators hide, flatten and mirror things).
fn odd_scale(scale: [f32; 3]) -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let [floor, b] = stage(&mut d);
    let odd = object(
        &mut d,
        &unit_box(),
        m,
        json!({"scale": scale, "translation": [1.2, 0.5, 0.0]}),
    );
    d.scene(&[floor, b, odd]);
    d
}

/// The stage with its positions moved by `offset` in the accessors (CAD and GIS exports in
/// georeferenced coordinates: the box's corners rounded to f32's few centimetres there).
fn offset_positions(offset: [f32; 3]) -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let moved = |p: [f32; 3]| std::array::from_fn(|k| p[k] + offset[k]);
    let nodes = [
        object(&mut d, &map(floor(), moved), m, json!({})),
        object(&mut d, &map(unit_box(), moved), m, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// The stage under a node 10,000 km from the origin.
fn far_node() -> Doc {
    let mut d = Doc::new();
    let children = stage(&mut d);
    let root = d.node(json!({"children": children, "translation": [1e7, 0.0, -1e7]}));
    d.scene(&[root]);
    d
}

/// The stage and a stray triangle 10 km away (an object left at the origin of a
/// georeferenced model, or the other way round): the lines spread over the long box around
/// both, and the stage, a speck of it, draws few (the bake warns).
fn stray_triangle() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let [floor, b] = stage(&mut d);
    let stray = object(
        &mut d,
        &(
            vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            vec![0, 1, 2],
        ),
        m,
        json!({"translation": [1e4, 0.0, 0.0]}),
    );
    d.scene(&[floor, b, stray]);
    d
}

/// Two stages a million kilometres apart: each a speck of the scene's extent.
fn far_apart() -> Doc {
    let mut d = Doc::new();
    let near = stage(&mut d);
    let far = stage(&mut d);
    let root = d.node(json!({"children": far, "translation": [1e9, 0.0, 0.0]}));
    d.scene(&[near[0], near[1], root]);
    d
}

/// The stage with its positions multiplied by `s` in the accessors.
fn resized_positions(s: f32) -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let resize = |p: [f32; 3]| p.map(|x| x * s);
    let nodes = [
        object(&mut d, &map(floor(), resize), m, json!({})),
        object(&mut d, &map(unit_box(), resize), m, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// Materials that leave out what they can: nothing at all, a name only, an empty
/// `pbrMetallicRoughness`, and a metal (no diffuse reflection).
fn no_base_color() -> Doc {
    let mut d = Doc::new();
    let materials = [
        d.push("materials", json!({})),
        d.push("materials", json!({"name": "only a name"})),
        d.push("materials", json!({"pbrMetallicRoughness": {}})),
        d.push(
            "materials",
            json!({"pbrMetallicRoughness": {"metallicFactor": 1.0}}),
        ),
    ];
    let floor = object(&mut d, &floor(), materials[0], json!({}));
    let mut nodes = vec![floor];
    for (k, &material) in materials[1..].iter().enumerate() {
        let x = -1.2 + 1.2 * k as f32;
        nodes.push(object(
            &mut d,
            &unit_box(),
            material,
            json!({"translation": [x, 0.0, 0.0], "scale": [0.8, 0.8, 0.8]}),
        ));
    }
    // And a mesh whose primitive has no material at all.
    let mesh = d.mesh(&unit_box().0, Some(&unit_box().1), None);
    nodes.push(
        d.node(json!({"mesh": mesh, "translation": [0.0, 0.0, 1.2], "scale": [0.5, 0.5, 0.5]})),
    );
    d.scene(&nodes);
    d
}

/// Transparent materials: a blended box of alpha 0 and a masked one.
fn alpha() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let blend = d.push(
        "materials",
        json!({"alphaMode": "BLEND", "pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.9, 0.9, 0.0], "metallicFactor": 0.0}}),
    );
    let mask = d.push(
        "materials",
        json!({"alphaMode": "MASK", "alphaCutoff": 0.9, "doubleSided": true,
               "pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.8, 0.2, 0.5], "metallicFactor": 0.0}}),
    );
    let nodes = [
        object(&mut d, &floor(), m, json!({})),
        object(
            &mut d,
            &unit_box(),
            blend,
            json!({"translation": [-0.8, 0.0, 0.0]}),
        ),
        object(
            &mut d,
            &unit_box(),
            mask,
            json!({"translation": [0.8, 0.0, 0.0]}),
        ),
    ];
    d.scene(&nodes);
    d
}

/// The box's base colour from an embedded 2×2 PNG (with texture coordinates); or, without
/// `decodable`, from bytes that are no image although the file says PNG.
fn texture(decodable: bool) -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let bytes = if decodable {
        let img = image::RgbImage::from_pixel(2, 2, image::Rgb([200, 120, 40]));
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    } else {
        b"\x89PNG but not really an image".to_vec()
    };
    let image_view = view(&mut d, &bytes, None);
    let image = d.push(
        "images",
        json!({"bufferView": image_view, "mimeType": "image/png"}),
    );
    let texture = d.push("textures", json!({"source": image}));
    let textured = d.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": texture}, "metallicFactor": 0.0}}),
    );
    let (v, i) = unit_box();
    let uv: Vec<f32> = v.iter().flat_map(|p| [p[0] + 0.5, p[2] + 0.5]).collect();
    let mesh = d.mesh(&v, Some(&i), Some(textured));
    let uv = d.floats(&uv, "VEC2");
    d.json["meshes"][mesh]["primitives"][0]["attributes"]["TEXCOORD_0"] = json!(uv);
    let box_node = d.node(json!({"mesh": mesh}));
    let floor = object(&mut d, &floor(), m, json!({}));
    d.scene(&[floor, box_node]);
    d
}

/// A closed room lit only by an emissive panel under its ceiling, a box inside.
fn emissive_only() -> Doc {
    let mut d = Doc::new();
    let wall = grey(&mut d, 0.7);
    let light = lamp(&mut d, 1.0);
    let nodes = [
        room(&mut d, wall),
        object(&mut d, &quad(0.5, 2.95, false), light, json!({})),
        object(&mut d, &unit_box(), wall, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// A closed room whose every surface emits and reflects nothing.
fn everything_emits() -> Doc {
    let mut d = Doc::new();
    let light = lamp(&mut d, 0.5);
    let nodes = [
        room(&mut d, light),
        object(&mut d, &unit_box(), light, json!({})),
    ];
    d.scene(&nodes);
    d
}

/// The stage with no light at all (baked under a black sky).
fn unlit() -> Doc {
    let mut d = Doc::new();
    let nodes = stage(&mut d);
    d.scene(&nodes);
    d
}

/// A closed room lit by a point, a spot and a directional light (`KHR_lights_punctual`).
fn punctual_lights() -> Doc {
    let mut d = Doc::new();
    let wall = grey(&mut d, 0.6);
    d.json["extensionsUsed"] = json!(["KHR_lights_punctual"]);
    d.json["extensions"] = json!({"KHR_lights_punctual": {"lights": [
        {"type": "point", "intensity": 20.0, "color": [1.0, 0.9, 0.8]},
        {"type": "spot", "intensity": 40.0, "spot": {"innerConeAngle": 0.2, "outerConeAngle": 0.6}},
        {"type": "directional", "intensity": 3.0}
    ]}});
    let mut nodes = vec![
        room(&mut d, wall),
        object(&mut d, &unit_box(), wall, json!({})),
    ];
    for (k, at) in [[0.0, 2.5, 1.0], [1.0, 2.8, -1.0], [0.0, 2.0, 0.0]]
        .into_iter()
        .enumerate()
    {
        nodes.push(d.node(json!({"translation": at,
                                  "rotation": down(),
                                  "extensions": {"KHR_lights_punctual": {"light": k}}})));
    }
    d.scene(&nodes);
    d
}

/// A box with extra primitives of points, lines, a line loop and a line strip over its
/// corners.
fn points_and_lines() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let (v, i) = unit_box();
    let mesh = d.mesh(&v, Some(&i), Some(m));
    let position = d.json["meshes"][mesh]["primitives"][0]["attributes"]["POSITION"].clone();
    for (mode, list) in [
        (1, vec![0u32, 1, 2, 3, 4, 5]),
        (2, vec![0, 1, 3, 2]),
        (3, vec![4, 5, 7, 6]),
    ] {
        let indices = d.indices(&list, 5123);
        let line = json!({"attributes": {"POSITION": position}, "indices": indices, "mode": mode});
        push_primitive(&mut d, mesh, line);
    }
    let points = json!({"attributes": {"POSITION": position}, "mode": 0});
    push_primitive(&mut d, mesh, points);
    let nodes = [
        object(&mut d, &floor(), m, json!({})),
        d.node(json!({"mesh": mesh})),
    ];
    d.scene(&nodes);
    d
}

/// A wireframe: a mesh of lines only.
fn lines_only() -> Doc {
    let mut d = Doc::new();
    let mesh = d.mesh(&unit_box().0, Some(&unit_box().1), None);
    d.json["meshes"][mesh]["primitives"][0]["mode"] = json!(1);
    let node = d.node(json!({"mesh": mesh}));
    d.scene(&[node]);
    d
}

/// The floor as a triangle strip and the box's sides as triangle fans.
fn strips_and_fans() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let strip = d.mesh(
        &[
            [-2.0, 0.0, -2.0],
            [-2.0, 0.0, 2.0],
            [2.0, 0.0, -2.0],
            [2.0, 0.0, 2.0],
        ],
        Some(&[0, 1, 2, 3]),
        Some(m),
    );
    d.json["meshes"][strip]["primitives"][0]["mode"] = json!(5);
    let (v, i) = unit_box();
    // Each face's quad (a, b, c, d) from its two triangles (a, b, c) and (a, c, d).
    let fans: Vec<u32> = (i.chunks(6))
        .flat_map(|t| [t[0], t[1], t[2], t[5]])
        .collect();
    let fan = d.mesh(&v, Some(&fans[..4]), Some(m));
    let position = d.json["meshes"][fan]["primitives"][0]["attributes"]["POSITION"].clone();
    for face in fans[4..].chunks(4) {
        let indices = d.indices(face, 5123);
        let side = json!({"attributes": {"POSITION": position}, "indices": indices, "material": m});
        push_primitive(&mut d, fan, side);
    }
    if let Some(primitives) = d.json["meshes"][fan]["primitives"].as_array_mut() {
        primitives.iter_mut().for_each(|p| p["mode"] = json!(6));
    }
    let nodes = [d.node(json!({"mesh": strip})), d.node(json!({"mesh": fan}))];
    d.scene(&nodes);
    d
}

/// A mesh with a primitive of normals but no positions, beside the stage.
fn no_positions() -> Doc {
    let mut d = Doc::new();
    let [floor, b] = stage(&mut d);
    let normals = d.floats(&[0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0], "VEC3");
    let mesh = d.push(
        "meshes",
        json!({"primitives": [{"attributes": {"NORMAL": normals}}]}),
    );
    let odd = d.node(json!({"mesh": mesh}));
    d.scene(&[floor, b, odd]);
    d
}

/// A mesh whose primitive has no positions (count 0, which the specification forbids), beside
/// the stage.
fn empty_primitive() -> Doc {
    let mut d = Doc::new();
    let [floor, b] = stage(&mut d);
    let empty = view(&mut d, &[0; 12], None);
    let positions = d.push(
        "accessors",
        json!({"bufferView": empty, "componentType": 5126, "count": 0, "type": "VEC3",
               "min": [0, 0, 0], "max": [0, 0, 0]}),
    );
    let mesh = d.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": positions}}]}),
    );
    let empty = d.node(json!({"mesh": mesh}));
    d.scene(&[floor, b, empty]);
    d
}

/// Positions and normals interleaved in one strided buffer view (most engines' exports).
fn interleaved() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let mut nodes = Vec::new();
    for (v, i) in [floor(), unit_box()] {
        let data = bytes_f32(v.iter().flat_map(|p| {
            let n = Vec3::from(*p).normalize_or(Vec3::Y);
            [p[0], p[1], p[2], n.x, n.y, n.z]
        }));
        let vertices = view(&mut d, &data, Some(24));
        let (min, max) = bounds(&v);
        let position = d.push(
            "accessors",
            json!({"bufferView": vertices, "componentType": 5126, "count": v.len(), "type": "VEC3",
                   "min": min, "max": max}),
        );
        let normal = d.push(
            "accessors",
            json!({"bufferView": vertices, "byteOffset": 12, "componentType": 5126, "count": v.len(),
                   "type": "VEC3"}),
        );
        let indices = d.indices(&i, 5123);
        let mesh = d.push(
            "meshes",
            json!({"primitives": [{"attributes": {"POSITION": position, "NORMAL": normal},
                                   "indices": indices, "material": m}]}),
        );
        nodes.push(d.node(json!({"mesh": mesh})));
    }
    d.scene(&nodes);
    d
}

/// Indices as bytes for the box and as 32-bit words for the floor.
fn mixed_index_types() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let mut nodes = Vec::new();
    for ((v, i), component) in [(floor(), 5125), (unit_box(), 5121)] {
        let flat: Vec<f32> = v.iter().flatten().copied().collect();
        let position = d.floats(&flat, "VEC3");
        let indices = d.indices(&i, component);
        let mesh = d.push(
            "meshes",
            json!({"primitives": [{"attributes": {"POSITION": position}, "indices": indices, "material": m}]}),
        );
        nodes.push(d.node(json!({"mesh": mesh})));
    }
    d.scene(&nodes);
    d
}

/// gltfpack's output: positions as normalised 16-bit integers (`KHR_mesh_quantization`),
/// elements padded to 8 bytes, the node's scale turning them back into metres.
fn quantized() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    d.json["extensionsUsed"] = json!(["KHR_mesh_quantization"]);
    d.json["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
    let mut nodes = Vec::new();
    for (v, i) in [floor(), unit_box()] {
        // Metres in [-2, 2] to i16 in [-32767, 32767]: the node scales by 2.
        let q: Vec<[i16; 3]> = (v.iter())
            .map(|p| p.map(|x| (x / 2.0 * 32767.0).round() as i16))
            .collect();
        let data: Vec<u8> = (q.iter())
            .flat_map(|p| [p[0], p[1], p[2], 0].into_iter().flat_map(i16::to_le_bytes))
            .collect();
        let vertices = view(&mut d, &data, Some(8));
        let (min, max) = (q.iter()).fold(([i16::MAX; 3], [i16::MIN; 3]), |(lo, hi), p| {
            (
                std::array::from_fn(|k| lo[k].min(p[k])),
                std::array::from_fn(|k| hi[k].max(p[k])),
            )
        });
        let position = d.push(
            "accessors",
            json!({"bufferView": vertices, "componentType": 5122, "normalized": true,
                   "count": v.len(), "type": "VEC3", "min": min, "max": max}),
        );
        let indices = d.indices(&i, 5123);
        let mesh = d.push(
            "meshes",
            json!({"primitives": [{"attributes": {"POSITION": position}, "indices": indices, "material": m}]}),
        );
        nodes.push(d.node(json!({"mesh": mesh, "scale": [2.0, 2.0, 2.0]})));
    }
    d.scene(&nodes);
    d
}

/// A Draco-compressed mesh (`KHR_draco_mesh_compression` required): nothing this baker
/// decodes.
fn draco() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    d.json["extensionsUsed"] = json!(["KHR_draco_mesh_compression"]);
    d.json["extensionsRequired"] = json!(["KHR_draco_mesh_compression"]);
    let compressed = view(&mut d, b"DRACO\x02\x02\x01\x01\x00\x00\x00", None);
    let position = d.push(
        "accessors",
        json!({"componentType": 5126, "count": 8, "type": "VEC3", "min": [-0.5, 0.0, -0.5], "max": [0.5, 1.0, 0.5]}),
    );
    let indices = d.push(
        "accessors",
        json!({"componentType": 5123, "count": 36, "type": "SCALAR"}),
    );
    let mesh = d.push(
        "meshes",
        json!({"primitives": [{"attributes": {"POSITION": position}, "indices": indices, "material": m,
                               "extensions": {"KHR_draco_mesh_compression": {
                                   "bufferView": compressed, "attributes": {"POSITION": 0}}}}]}),
    );
    let node = d.node(json!({"mesh": mesh}));
    d.scene(&[node]);
    d
}

/// A vendor extension the baker does not know, used (not required) on a node and a material.
fn unknown_extension() -> Doc {
    let mut d = Doc::new();
    let [floor, b] = stage(&mut d);
    d.json["extensionsUsed"] = json!(["VENDOR_baked_thing"]);
    d.json["nodes"][b]["extensions"] = json!({"VENDOR_baked_thing": {"level": 3}});
    d.json["materials"][0]["extensions"] = json!({"VENDOR_baked_thing": {"glow": true}});
    d.scene(&[floor, b]);
    d
}

/// A box hidden by scaling it to nothing in the middle of its animation (frame 1 of 3).
fn vanishing() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let [floor, b] = stage(&mut d);
    let gone = object(
        &mut d,
        &unit_box(),
        m,
        json!({"translation": [1.2, 0.0, 0.0]}),
    );
    d.scene(&[floor, b, gone]);
    d.animation(
        "hide",
        &[(
            gone,
            "scale",
            &[0.0, 1.0, 2.0],
            &[1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
            "LINEAR",
        )],
    );
    d
}

/// A box sliding on a cubic spline (in-tangent, value, out-tangent per key) and turning in
/// steps.
fn spline_and_step() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let [floor, b] = stage(&mut d);
    let mover = object(&mut d, &unit_box(), m, json!({"scale": [0.4, 0.4, 0.4]}));
    d.scene(&[floor, b, mover]);
    // Per key (0, 1 and 2 s): in-tangent, value, out-tangent.
    let spline: Vec<f32> = [
        [[0.0, 0.0, 0.0], [-1.5, 0.0, 1.0], [1.0, 0.0, 0.0]],
        [[0.0, 2.0, 0.0], [0.0, 1.5, 1.5], [0.0, -2.0, 0.0]],
        [[-1.0, 0.0, 0.0], [1.5, 0.0, 1.0], [0.0, 0.0, 0.0]],
    ]
    .into_iter()
    .flatten()
    .flatten()
    .collect();
    let turn: Vec<f32> = [Quat::IDENTITY, Quat::from_rotation_y(FRAC_PI_2)]
        .iter()
        .flat_map(|q| q.to_array())
        .collect();
    d.animation(
        "slide",
        &[
            (
                mover,
                "translation",
                &[0.0, 1.0, 2.0],
                &spline,
                "CUBICSPLINE",
            ),
            (mover, "rotation", &[0.0, 1.0], &turn, "STEP"),
        ],
    );
    d
}

/// An animation of one keyframe (a pose exported as an action).
fn single_keyframe() -> Doc {
    let mut d = Doc::new();
    let [floor, b] = stage(&mut d);
    d.scene(&[floor, b]);
    d.animation(
        "pose",
        &[(b, "translation", &[0.5], &[0.3, 0.0, 0.2], "LINEAR")],
    );
    d
}

/// One box mesh under 64 nodes in a grid (a forest of instances).
fn instanced() -> Doc {
    let mut d = Doc::new();
    let m = grey(&mut d, 0.5);
    let floor = object(&mut d, &floor(), m, json!({}));
    let mesh = d.mesh(&unit_box().0, Some(&unit_box().1), Some(m));
    let mut nodes = vec![floor];
    for k in 0..64 {
        let (x, z) = ((k % 8) as f32 * 0.5 - 1.75, (k / 8) as f32 * 0.5 - 1.75);
        nodes.push(d.node(json!({"mesh": mesh, "translation": [x, 0.0, z], "scale": [0.2, 0.2 + 0.02 * k as f32, 0.2]})));
    }
    d.scene(&nodes);
    d
}

/// Two nodes each the other's child.
fn node_cycle() -> Doc {
    let mut d = Doc::new();
    let [floor, b] = stage(&mut d);
    let a = d.node(json!({"children": [b]}));
    d.json["nodes"][b]["children"] = json!([a]);
    d.scene(&[floor, a]);
    d
}
