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

use glam::{DAffine3, DMat3, DQuat, DVec3};
use serde_json::{Value, json};

use super::OutputError;
use super::geometry::NodeMesh;
use super::tonemap::ToneMap;
use crate::scene::{Material, Motion, Projection, Scene, SceneCamera};

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

    /// Appends `bytes` as a bufferView of their own (an embedded image), returning its index.
    fn view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.views.push(json!({
            "buffer": 0,
            "byteOffset": offset,
            "byteLength": bytes.len(),
        }));
        self.views.len() - 1
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
/// `TEXCOORD_0` the same, glTF's sets counting from 0), one primitive per material on the
/// node's vertices, each material diffuse with the reflectance and emission of `materials`
/// (the scene's, as relit), each node's source node in `extras`; the states' lightmaps are the
/// files beside it (`manifest.json`): a material shows its albedo times the `light` lightmap,
/// plus its emission.
///
/// A rigid moving node (`extras.moving` `"rigid"`) follows its motion in the animation
/// `"baked motion"`: its transform at every frame's time, interpolated linearly between them,
/// so that an engine plays the geometry the lightmaps were baked for. A deforming one
/// (`"deforming"`: skinned or morphing) stays in its rest pose: its texels are evaluated where
/// it is at each state, but its shape at a frame is the per-vertex files'.
///
/// # Errors
/// [`OutputError::TooLarge`] if the file would pass GLB's 4 GiB limit.
pub fn lightmap_glb(
    scene: &Scene,
    materials: &[Material],
    lightmap: &super::lightmap::Lightmap,
    embedded: Option<&Embedded>,
) -> Result<Vec<u8>, OutputError> {
    let radius = scene.normalisation.radius;
    let centre = scene.normalisation.center;
    let mut buffers = Buffers::default();
    let mut nodes = Vec::new();
    let mut gltf_meshes = Vec::new();
    let mut moving = Vec::new();
    // The scene's materials used, in the order of first use: a glTF material's index is its
    // place here.
    let mut order: Vec<u32> = Vec::new();
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
        let attributes = json!({
            "POSITION": position,
            "NORMAL": normal,
            "TEXCOORD_0": texcoord,
            "TEXCOORD_1": texcoord,
        });
        // One primitive per material, on the same vertices.
        let mut by_material: std::collections::BTreeMap<u32, (Vec<[u32; 3]>, Vec<u32>)> =
            Default::default();
        for (t, &patch) in uv.triangles.iter().zip(&mesh.patches) {
            let material = scene.patches[patch as usize].material;
            let (triangles, patches) = by_material.entry(material).or_default();
            triangles.push(*t);
            patches.push(patch);
        }
        let primitives: Vec<Value> = (by_material.iter())
            .map(|(&material, (triangles, patches))| {
                let used = (order.iter().position(|&m| m == material)).unwrap_or_else(|| {
                    order.push(material);
                    order.len() - 1
                });
                json!({
                    "attributes": attributes,
                    "indices": buffers.indices(triangles),
                    "material": used,
                    "extras": { "patches": buffers.per_triangle(patches) },
                })
            })
            .collect();
        let name = node_name(scene, mesh.node);
        gltf_meshes.push(json!({
            "name": format!("{name} lightmapped"),
            "primitives": primitives,
        }));
        let mut node = mesh_node(name, gltf_meshes.len() - 1, centre, mesh.node);
        let object = scene.objects.iter().find(|o| o.node == mesh.node);
        if let Some(object) = object {
            let kind = match &object.motion {
                Motion::Rigid { poses } => {
                    moving.push((nodes.len(), poses));
                    "rigid"
                }
                Motion::Deforming(_) => "deforming",
            };
            node["extras"]["moving"] = kind.into();
        }
        nodes.push(node);
    }
    let animation = baked_motion(scene, &mut buffers, &mut nodes, &moving);
    let mut document = json!({
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
        "materials": order.iter().map(|&m| lit_material(scene, materials, m)).collect::<Vec<_>>(),
    });
    let mut extensions = Vec::new();
    let strong = |&m: &u32| (material_of(scene, materials, m).emission.iter()).any(|&e| e > 1.0);
    if order.iter().any(strong) {
        extensions.push("KHR_materials_emissive_strength");
    }
    if let Some(embedded) = embedded {
        let view = buffers.view(&embedded.png);
        document["images"] = json!([{
            "name": format!("light of lighting state {}", embedded.state),
            "bufferView": view,
            "mimeType": "image/png",
        }]);
        // Linear filtering, no mipmaps: a texel's neighbours across a chart's padding are
        // its own dilated light, not another chart's.
        document["samplers"] = json!([{ "magFilter": 9729, "minFilter": 9729 }]);
        document["textures"] = json!([{ "source": 0, "sampler": 0 }]);
        let intensity = std::f64::consts::PI * f64::from(embedded.scale);
        for material in document["materials"].as_array_mut().into_iter().flatten() {
            material["extensions"]["MOZ_lightmap"] =
                json!({ "index": 0, "texCoord": 1, "intensity": intensity });
        }
        document["scenes"][0]["extras"]["lightmap"]["embedded"] = json!({
            "state": embedded.state,
            "quantity": "light",
            "encoding": "8-bit sRGB PNG of light / scale, clamped at 1; MOZ_lightmap's intensity is pi * scale (three.js's lightMapIntensity)",
            "scale": embedded.scale,
        });
        extensions.push("MOZ_lightmap");
    }
    if !extensions.is_empty() {
        document["extensionsUsed"] = json!(extensions);
    }
    if let Some(animation) = animation {
        document["animations"] = json!([animation]);
    }
    buffers.finish(document)
}

/// A lightmap to embed in the lightmapped geometry for `MOZ_lightmap` (Mozilla Hubs' and
/// gltf-transform's extension, which three.js-based viewers read as the material's `lightMap`
/// on `TEXCOORD_1` at `lightMapIntensity` = its `intensity`): one lighting state's light
/// ([`super::lightmap::Quantity::Light`]) as an 8-bit sRGB PNG of the light over `scale`
/// ([`super::lightmap::Texels::srgb_png`]).
#[derive(Clone, Debug)]
pub struct Embedded {
    /// The PNG.
    pub png: Vec<u8>,
    /// The light the PNG's white stands for.
    pub scale: f32,
    /// The lighting state (its first frame).
    pub state: usize,
}

impl Embedded {
    /// Lighting state `state`'s light from its `texels` as [`super::lightmap::Lightmap::texels`]
    /// makes them (holding the radiance), scaled to its brightest texel.
    ///
    /// # Errors
    /// The PNG encoder's, as text.
    pub fn light(texels: &super::lightmap::Texels, state: usize) -> Result<Self, String> {
        let light = texels.clone().holding(super::lightmap::Quantity::Light);
        let scale = light.peak().max(f32::MIN_POSITIVE);
        Ok(Self {
            png: light.srgb_png(scale)?,
            scale,
            state,
        })
    }
}

/// Material `m` (a patch's) of `materials` (the scene's as relit), or of the scene if they
/// lack it.
fn material_of<'a>(scene: &'a Scene, materials: &'a [Material], m: u32) -> &'a Material {
    materials
        .get(m as usize)
        .unwrap_or(&scene.materials[m as usize])
}

/// Material `m` of `materials` (the scene's, as relit) as glTF: its reflectance the base
/// colour, diffuse (no metal, fully rough), its emission the emissive colour (with
/// `KHR_materials_emissive_strength` past 1).
fn lit_material(scene: &Scene, materials: &[Material], m: u32) -> Value {
    let material = material_of(scene, materials, m);
    let [r, g, b] = material.reflectance;
    let strongest = material.emission.iter().copied().fold(0.0, f64::max);
    let mut out = json!({
        "pbrMetallicRoughness": {
            "baseColorFactor": [r, g, b, 1.0],
            "metallicFactor": 0.0,
            "roughnessFactor": 1.0,
        },
        "extras": { "source_material": m },
    });
    if let Some(name) = &material.name {
        out["name"] = name.as_str().into();
    }
    if strongest > 0.0 {
        let scale = strongest.max(1.0);
        out["emissiveFactor"] = json!(material.emission.map(|e| e / scale));
        if scale > 1.0 {
            out["extensions"] =
                json!({ "KHR_materials_emissive_strength": { "emissiveStrength": scale } });
        }
    }
    out
}

/// The animation `"baked motion"` of the rigid moving nodes `moving` (index in `nodes`, poses
/// by frame), whose meshes are drawn at frame 0: each node's transform at each frame is
/// `pose(f) · pose(0)⁻¹` in scene units about the node's translation, as translation, rotation
/// and scale channels (the latter two only where they change). A node whose transform has a
/// shear (which glTF's nodes cannot hold) or whose frame-0 pose is singular is left still and
/// says so in `extras.motion`. `None` if nothing is animated.
fn baked_motion(
    scene: &Scene,
    buffers: &mut Buffers,
    nodes: &mut [Value],
    moving: &[(usize, &Vec<DAffine3>)],
) -> Option<Value> {
    let frames = scene.frames.count;
    if frames < 2 || moving.is_empty() {
        return None;
    }
    let radius = scene.normalisation.radius;
    let centre = scene.normalisation.center;
    let times: Vec<f32> = (0..frames)
        .map(|f| (scene.frames.time(f) - scene.frames.start.min(0.0)) as f32)
        .collect();
    let mut samplers = Vec::new();
    let mut channels = Vec::new();
    let mut input = None;
    for &(index, poses) in moving {
        let Some(rest) = poses
            .first()
            .filter(|p| p.matrix3.determinant().abs() > 1e-300)
        else {
            nodes[index]["extras"]["motion"] = "left still: its first pose is singular".into();
            continue;
        };
        let to_rest = rest.inverse();
        let parts: Option<Vec<(DVec3, DQuat, DVec3)>> = (0..frames)
            .map(|f| {
                let m = poses[f.min(poses.len() - 1)] * to_rest;
                let (scale, rotation, _) = m.to_scale_rotation_translation();
                let rebuilt = DMat3::from_quat(rotation) * DMat3::from_diagonal(scale);
                let sheared = (rebuilt - m.matrix3)
                    .to_cols_array()
                    .iter()
                    .any(|d| d.abs() > 1e-6);
                let translation = centre + m.translation * radius;
                (!sheared && scale.is_finite() && rotation.is_finite()).then_some((
                    translation,
                    rotation.normalize(),
                    scale,
                ))
            })
            .collect();
        let Some(parts) = parts else {
            nodes[index]["extras"]["motion"] =
                "left still: its motion shears it, which a glTF node cannot".into();
            continue;
        };
        let input = *input.get_or_insert_with(|| {
            let (first, last) = (times[0], times[frames - 1]);
            let words = times.iter().map(|t| t.to_le_bytes());
            let extra = json!({ "min": [first], "max": [last] });
            buffers.push(words, None, (FLOAT, "SCALAR", frames), extra)
        });
        let mut channel = |path: &str, words: Vec<f32>, kind: &str| {
            let count = frames;
            let output = buffers.push(
                words.into_iter().map(f32::to_le_bytes),
                None,
                (FLOAT, kind, count),
                json!({}),
            );
            samplers.push(json!({ "input": input, "output": output, "interpolation": "LINEAR" }));
            channels.push(json!({
                "sampler": samplers.len() - 1,
                "target": { "node": index, "path": path },
            }));
        };
        let narrow = |v: DVec3| v.to_array().map(|x| x as f32);
        channel(
            "translation",
            parts.iter().flat_map(|p| narrow(p.0)).collect(),
            "VEC3",
        );
        if parts
            .iter()
            .any(|p| !p.1.abs_diff_eq(DQuat::IDENTITY, 1e-9))
        {
            // Each quaternion on the same side as the one before: linear interpolation takes
            // the short way.
            let mut previous = DQuat::IDENTITY;
            let rotations: Vec<f32> = (parts.iter())
                .flat_map(|p| {
                    let q = if p.1.dot(previous) < 0.0 { -p.1 } else { p.1 };
                    previous = q;
                    q.to_array().map(|x| x as f32)
                })
                .collect();
            channel("rotation", rotations, "VEC4");
        }
        if parts.iter().any(|p| !p.2.abs_diff_eq(DVec3::ONE, 1e-9)) {
            channel(
                "scale",
                parts.iter().flat_map(|p| narrow(p.2)).collect(),
                "VEC3",
            );
        }
    }
    (!channels.is_empty()).then(|| {
        json!({
            "name": "baked motion",
            "samplers": samplers,
            "channels": channels,
            "extras": { "time_of_frame_0": times[0], "fps": scene.frames.fps },
        })
    })
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
