//! The baked glTF: one binary glTF (`.glb`) per frame.
//!
//! Each file is the scene posed at its frame, one node and mesh per source node (its index in
//! `extras.source_node`), one triangle per face of a traced triangle, with per-vertex:
//! - `_RADIANCE`: the HDR radiance at the vertex (f32 RGB, the scene's emission units),
//!   evaluated at the vertex itself ([`super::light_vertices`]);
//! - `_RADIANCE_STDERR`: its standard error;
//! - `COLOR_0`: the same tone-mapped to [0, 1] ([`ToneMap`]), which ordinary viewers show;
//! - `NORMAL`;
//!
//! and per triangle the patch it draws (u32, the service's patch ids), in an accessor that the
//! primitive's `extras.patches` names: a viewer colours or picks patches by it.
//!
//! The scene's cameras are camera nodes posed at the frame, the one the previews are seen from
//! first.
//!
//! The material is `KHR_materials_unlit`, white: the colour a viewer shows is the baked light,
//! not re-lit. Positions are in the scene's units, relative to the scene's centre, which the
//! node's translation restores: `f32` keeps its precision for a scene far from the origin.
//!
//! One file per frame rather than morph targets switched by STEP weights: every viewer shows a
//! plain mesh's `COLOR_0`, while colour morph targets are ignored by most importers (Blender's
//! among them); moving geometry carries its pose without re-creating the scene's animation; and
//! a mesh's own morph targets and animated weights stay out of the way. A pipeline also loads
//! only the frames it needs. The cost is that static geometry is repeated in every file.

use glam::DQuat;
use serde_json::{Value, json};

use super::OutputError;
use super::geometry::NodeMesh;
use super::tonemap::ToneMap;
use crate::scene::{Projection, Scene, SceneCamera};

/// glTF component type of a 32-bit float.
const FLOAT: u32 = 5126;
/// glTF component type of a 32-bit unsigned integer.
const UNSIGNED_INT: u32 = 5125;
/// bufferView target for vertex attributes.
const ARRAY_BUFFER: u32 = 34962;
/// bufferView target for indices.
const ELEMENT_ARRAY_BUFFER: u32 = 34963;

/// The binary chunk and the bufferViews and accessors that describe it.
#[derive(Default)]
struct Buffers {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Buffers {
    /// Appends the 4-byte little-endian `words` as a bufferView for `target` and an accessor
    /// of `count` elements of `kind` over it, returning the accessor, to which `extra` fields
    /// are added.
    fn push(
        &mut self,
        words: impl Iterator<Item = [u8; 4]>,
        target: Option<u32>,
        (component, kind, count): (u32, &str, usize),
        extra: Value,
    ) -> usize {
        let offset = self.bin.len();
        words.for_each(|w| self.bin.extend_from_slice(&w));
        let mut view = json!({
            "buffer": 0,
            "byteOffset": offset,
            "byteLength": self.bin.len() - offset,
        });
        if let Some(target) = target {
            view["target"] = target.into();
        }
        self.views.push(view);
        let mut accessor = json!({
            "bufferView": self.views.len() - 1,
            "componentType": component,
            "count": count,
            "type": kind,
        });
        if let (Some(a), Value::Object(extra)) = (accessor.as_object_mut(), extra) {
            a.extend(extra);
        }
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    /// Appends `values` as a VEC3 float accessor (with bounds when `bounds`), returning its index.
    fn vec3(&mut self, values: &[[f32; 3]], bounds: bool) -> usize {
        let extra = if bounds {
            let mut min = [f32::INFINITY; 3];
            let mut max = [f32::NEG_INFINITY; 3];
            for v in values {
                for (c, &x) in v.iter().enumerate() {
                    min[c] = min[c].min(x);
                    max[c] = max[c].max(x);
                }
            }
            json!({ "min": min, "max": max })
        } else {
            json!({})
        };
        let words = values.iter().flatten().map(|c| c.to_le_bytes());
        let shape = (FLOAT, "VEC3", values.len());
        self.push(words, Some(ARRAY_BUFFER), shape, extra)
    }

    /// The GLB of `document` with these buffers (padded to 4 bytes) as its binary chunk.
    fn finish(mut self, mut document: Value) -> Result<Vec<u8>, OutputError> {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        if !self.bin.is_empty() {
            document["buffers"] = json!([{ "byteLength": self.bin.len() }]);
            document["bufferViews"] = Value::Array(self.views);
            document["accessors"] = Value::Array(self.accessors);
        }
        glb(&document, &self.bin)
    }

    /// Appends `values` as a VEC2 float accessor, returning its index.
    fn vec2(&mut self, values: &[[f32; 2]]) -> usize {
        let words = values.iter().flatten().map(|c| c.to_le_bytes());
        let shape = (FLOAT, "VEC2", values.len());
        self.push(words, Some(ARRAY_BUFFER), shape, json!({}))
    }

    /// Appends triangle indices, returning the accessor's index.
    fn indices(&mut self, triangles: &[[u32; 3]]) -> usize {
        let words = triangles.iter().flatten().map(|i| i.to_le_bytes());
        let shape = (UNSIGNED_INT, "SCALAR", triangles.len() * 3);
        self.push(words, Some(ELEMENT_ARRAY_BUFFER), shape, json!({}))
    }

    /// Appends one u32 per triangle (not a vertex attribute), returning the accessor's index.
    fn per_triangle(&mut self, values: &[u32]) -> usize {
        let words = values.iter().map(|i| i.to_le_bytes());
        let shape = (UNSIGNED_INT, "SCALAR", values.len());
        self.push(words, None, shape, json!({}))
    }
}

/// Source node `node`'s name, or its index.
fn node_name(scene: &Scene, node: u32) -> String {
    (scene.node_names.get(node as usize))
        .and_then(Option::as_deref)
        .map_or_else(|| format!("node {node}"), str::to_owned)
}

/// The node drawing glTF mesh `mesh`, source node `source`'s, at the normalisation's `centre`
/// (the meshes' positions are scaled about it).
fn mesh_node(name: String, mesh: usize, centre: glam::DVec3, source: u32) -> Value {
    json!({
        "name": name,
        "mesh": mesh,
        "translation": centre.to_array(),
        "extras": { "source_node": source },
    })
}

/// A glTF mesh of one primitive with `attributes` (accessor indices), its triangles' and
/// their patches' accessors, material 0.
fn drawn_mesh(name: String, attributes: Value, (indices, patches): (usize, usize)) -> Value {
    json!({
        "name": name,
        "primitives": [{
            "attributes": attributes,
            "indices": indices,
            "material": 0,
            "extras": { "patches": patches },
        }],
    })
}

/// An `f32` that glTF accepts (finite): radiance beyond `f32`'s range is clamped.
fn finite_f32(x: f64) -> f32 {
    (x as f32).clamp(f32::MIN, f32::MAX)
}

/// The `.glb` of frame `frame` of `scene`, from its geometry ([`super::frame_geometry`]).
///
/// # Errors
/// [`OutputError::TooLarge`] if the file would pass GLB's 4 GiB limit.
pub fn frame_glb(
    scene: &Scene,
    frame: usize,
    meshes: &[NodeMesh],
    tone: &ToneMap,
) -> Result<Vec<u8>, OutputError> {
    let radius = scene.normalisation.radius;
    let centre = scene.normalisation.center;
    let mut buffers = Buffers::default();
    let mut nodes = Vec::new();
    let mut gltf_meshes = Vec::new();
    for mesh in meshes.iter().filter(|m| !m.triangles.is_empty()) {
        let positions: Vec<[f32; 3]> = mesh
            .positions
            .iter()
            .map(|p| (*p * radius).as_vec3().to_array())
            .collect();
        let normals: Vec<[f32; 3]> = mesh.normals.iter().map(|n| n.to_array()).collect();
        let colours: Vec<[f32; 3]> = mesh.radiance.iter().map(|&l| tone.apply(l)).collect();
        let radiance: Vec<[f32; 3]> = mesh.radiance.iter().map(|l| l.map(finite_f32)).collect();
        let stderr: Vec<[f32; 3]> = mesh.stderr.iter().map(|e| e.map(finite_f32)).collect();
        let position = buffers.vec3(&positions, true);
        let normal = buffers.vec3(&normals, false);
        let colour = buffers.vec3(&colours, false);
        let hdr = buffers.vec3(&radiance, false);
        let hdr_error = buffers.vec3(&stderr, false);
        let indices = buffers.indices(&mesh.triangles);
        let patches = buffers.per_triangle(&mesh.patches);
        let name = node_name(scene, mesh.node);
        let attributes = json!({
            "POSITION": position,
            "NORMAL": normal,
            "COLOR_0": colour,
            "_RADIANCE": hdr,
            "_RADIANCE_STDERR": hdr_error,
        });
        gltf_meshes.push(drawn_mesh(
            format!("{name} baked"),
            attributes,
            (indices, patches),
        ));
        nodes.push(mesh_node(name, gltf_meshes.len() - 1, centre, mesh.node));
    }
    // The previews' camera first, then the scene's others.
    let cameras: Vec<(Value, Value)> = (scene.camera.iter().chain(&scene.other_cameras))
        .enumerate()
        .map(|(i, c)| camera(scene, c, frame, i))
        .collect();
    nodes.extend(cameras.iter().map(|(node, _)| node.clone()));
    let mut document = json!({
        "asset": {
            "version": "2.0",
            "generator": concat!("radiosity ", env!("CARGO_PKG_VERSION")),
        },
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{
            "nodes": (0..nodes.len()).collect::<Vec<_>>(),
            "extras": {
                "frame": frame,
                "time": scene.frames.time(frame),
                "exposure": tone.exposure,
                "tone_map": "COLOR_0 = x / (1 + Y(x)) clamped to [0, 1], x = exposure * _RADIANCE, Y = Rec. 709 luminance",
            },
        }],
        "nodes": nodes,
        "meshes": gltf_meshes,
        "materials": [{
            "name": "baked radiance (unlit)",
            "pbrMetallicRoughness": { "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0 },
            "extensions": { "KHR_materials_unlit": {} },
        }],
    });
    if !cameras.is_empty() {
        document["cameras"] = cameras
            .into_iter()
            .map(|(_, projection)| projection)
            .collect();
    }
    buffers.finish(document)
}

/// The `.glb` of a timeline's lightmapped geometry: the scene as drawn at frame 0 on the
/// lightmap's vertices (seams split them), `TEXCOORD_1` its coordinates in the atlas (and
/// `TEXCOORD_0` the same, glTF's sets counting from 0), each node's source node in `extras`;
/// the states' lightmaps are the EXR files beside it (`manifest.json`).
///
/// # Errors
/// [`OutputError::TooLarge`] if the file would pass GLB's 4 GiB limit.
pub fn lightmap_glb(
    scene: &Scene,
    lightmap: &super::lightmap::Lightmap,
) -> Result<Vec<u8>, OutputError> {
    let radius = scene.normalisation.radius;
    let centre = scene.normalisation.center;
    let mut buffers = Buffers::default();
    let mut nodes = Vec::new();
    let mut gltf_meshes = Vec::new();
    for (uv, mesh) in lightmap.meshes.iter().zip(lightmap.rest()) {
        if uv.triangles.is_empty() {
            continue;
        }
        let positions: Vec<[f32; 3]> = (uv.xref.iter())
            .map(|&v| (mesh.positions[v as usize] * radius).as_vec3().to_array())
            .collect();
        let normals: Vec<[f32; 3]> = (uv.xref.iter())
            .map(|&v| mesh.normals[v as usize].to_array())
            .collect();
        let position = buffers.vec3(&positions, true);
        let normal = buffers.vec3(&normals, false);
        let texcoord = buffers.vec2(&uv.uv);
        let indices = buffers.indices(&uv.triangles);
        let patches = buffers.per_triangle(&mesh.patches);
        let name = node_name(scene, mesh.node);
        let attributes = json!({
            "POSITION": position,
            "NORMAL": normal,
            "TEXCOORD_0": texcoord,
            "TEXCOORD_1": texcoord,
        });
        let named = format!("{name} lightmapped");
        gltf_meshes.push(drawn_mesh(named, attributes, (indices, patches)));
        nodes.push(mesh_node(name, gltf_meshes.len() - 1, centre, mesh.node));
    }
    let document = json!({
        "asset": {
            "version": "2.0",
            "generator": concat!("radiosity ", env!("CARGO_PKG_VERSION")),
        },
        "scene": 0,
        "scenes": [{
            "nodes": (0..nodes.len()).collect::<Vec<_>>(),
            "extras": {
                "lightmap": {
                    "width": lightmap.width,
                    "height": lightmap.height,
                    "texels_per_unit": lightmap.texels_per_unit,
                    "uv_set": 1,
                    "manifest": "manifest.json",
                },
            },
        }],
        "nodes": nodes,
        "meshes": gltf_meshes,
        "materials": [{
            "name": "lightmapped",
            "pbrMetallicRoughness": { "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0 },
        }],
    });
    buffers.finish(document)
}

/// A scene's camera at `frame` in scene units: its node (rotation and translation; the pose's
/// scale, which glTF's cameras ignore, left out) and its glTF camera (at `index`).
fn camera(scene: &Scene, camera: &SceneCamera, frame: usize, index: usize) -> (Value, Value) {
    let radius = scene.normalisation.radius;
    let pose = crate::output::preview::rigid(camera.pose(frame));
    let rotation = DQuat::from_mat3(&pose.matrix3).normalize().as_quat();
    let translation = scene.normalisation.to_scene(pose.translation).as_vec3();
    let node = json!({
        "name": camera.name.clone().unwrap_or_else(|| format!("camera {index}")),
        "camera": index,
        "rotation": rotation.to_array(),
        "translation": translation.to_array(),
    });
    let projection = match camera.projection {
        Projection::Perspective { yfov, znear, zfar } => {
            let mut p = json!({ "yfov": yfov, "znear": znear * radius });
            if let Some(far) = zfar {
                p["zfar"] = (far * radius).into();
            }
            if let Some(aspect) = camera.aspect {
                p["aspectRatio"] = aspect.into();
            }
            json!({ "type": "perspective", "perspective": p })
        }
        Projection::Orthographic {
            xmag,
            ymag,
            znear,
            zfar,
        } => json!({
            "type": "orthographic",
            "orthographic": {
                "xmag": xmag * radius,
                "ymag": ymag * radius,
                "znear": znear * radius,
                "zfar": zfar * radius,
            },
        }),
    };
    (node, projection)
}

/// A GLB container (the gltf crate's [`gltf::binary::Glb`]): 12-byte header, the JSON chunk
/// padded with spaces, the BIN chunk (if any) padded with zeros.
fn glb(document: &Value, bin: &[u8]) -> Result<Vec<u8>, OutputError> {
    let json = document.to_string().into_bytes();
    let padded = |n: usize| n.div_ceil(4) * 4;
    // The crate writes lengths as u32 without a check: GLB's limit is checked here.
    let total = 12
        + 8
        + padded(json.len())
        + if bin.is_empty() {
            0
        } else {
            8 + padded(bin.len())
        };
    let length = u32::try_from(total).map_err(|_| OutputError::TooLarge)?;
    let container = gltf::binary::Glb {
        header: gltf::binary::Header {
            magic: *b"glTF",
            version: 2,
            length,
        },
        json: json.into(),
        bin: (!bin.is_empty()).then(|| bin.into()),
    };
    container
        .to_vec()
        .map_err(|e| OutputError::Container(e.to_string()))
}
