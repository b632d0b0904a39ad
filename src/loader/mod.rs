//! glTF 2.0 in, [`Scene`] out.
//!
//! The loader reads `.glb` and `.gltf` files from memory, validates everything once, evaluates
//! the chosen animations over the frames, decides what is static and what moves, normalises
//! the scene to its bounding sphere and makes the patches. Nothing here panics on any input:
//! every problem is a [`LoadError`] naming the offending object.

mod accessor;
mod animation;
mod container;
mod material;
mod mesh;
mod meshopt;
mod nodes;

use glam::{DAffine3, DMat4, DVec3, Vec3};

use crate::scene::subdivide::{self, Subdivision, triangle_area};
use crate::scene::{
    Bounds, Deformation, Faces, Frames, Light, LightKind, Material, Motion, MovingObject,
    Normalisation, Origin, Patch, Projection, Provenance, Scene, SceneCamera, Side, SkinBinding,
    TriangleMesh,
};
pub use animation::{Interpolation, Sampler};

/// The default [`LoadOptions::max_reflectance`]. At reflectance 1 a closed scene keeps all the
/// light it receives and has no steady state (METHOD.md §4); at 0.999 a surface loses 0.1% of
/// the light per bounce and the solve still converges in tens to a few hundred iterations.
pub const MAX_REFLECTANCE: f64 = 0.999;

/// Most frames a load gives by default ([`LoadOptions::max_frames`]; the limit of both front
/// ends, [`crate::params::Limits`]).
pub const MAX_FRAMES: usize = 10_000;

/// Most patches a load gives by default ([`LoadOptions::max_patches`]).
pub const MAX_PATCHES: usize = 2_000_000;

/// What to load from a file, and the limits that keep a hostile file from exhausting memory.
/// The same names are used by the CLI and the HTTP API.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LoadOptions {
    /// Frames per second of the timeline.
    pub fps: f64,
    /// The animation to play, by name or index; `None` plays all of them together.
    pub animation: Option<String>,
    /// The camera the previews are seen from: a camera node by name or node index, or `auto`
    /// for the automatic view; `None` takes the scene's first camera (in hierarchy order), or
    /// the automatic view without one.
    pub camera: Option<String>,
    /// Time of the first frame, seconds; defaults to the first keyframe.
    pub start: Option<f64>,
    /// Time of the last frame, seconds; defaults to the last keyframe.
    pub end: Option<f64>,
    /// Subdivide triangles until every edge is at most this long (scene units); `None` keeps
    /// one patch per triangle side.
    pub patch_size: Option<f64>,
    /// Most frames a timeline may have.
    pub max_frames: usize,
    /// Most patches a scene may have.
    pub max_patches: usize,
    /// Most per-frame evaluations a load may do: animated node transforms and deformed vertices
    /// (and their bounds and area checks), each counted once per frame. Bounds the time and
    /// memory a file with many frames and many moving parts can take.
    pub max_work: u64,
    /// Largest diffuse reflectance a material keeps, in (0, 1]: higher ones (the glTF default
    /// material's 1 among them) are lowered to it, with a warning naming them. 1 keeps every
    /// reflectance; a closed scene that reflects everything then fails to converge.
    pub max_reflectance: f64,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            fps: 24.0,
            animation: None,
            camera: None,
            start: None,
            end: None,
            patch_size: None,
            max_frames: MAX_FRAMES,
            max_patches: MAX_PATCHES,
            max_work: 200_000_000,
            max_reflectance: MAX_REFLECTANCE,
        }
    }
}

impl LoadOptions {
    fn check(&self) -> Result<(), LoadError> {
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(LoadError::Option(format!(
                "fps must be a positive number, not {}",
                self.fps
            )));
        }
        for (name, value) in [("start", self.start), ("end", self.end)] {
            if value.is_some_and(|v| !v.is_finite()) {
                return Err(LoadError::Option(format!(
                    "{name} must be a finite time in seconds"
                )));
            }
        }
        if let Some(size) = self.patch_size
            && !(size.is_finite() && size > 0.0)
        {
            return Err(LoadError::Option(format!(
                "patch_size must be a positive length, not {size}"
            )));
        }
        if !(self.max_reflectance > 0.0 && self.max_reflectance <= 1.0) {
            return Err(LoadError::Option(format!(
                "max_reflectance must be in (0, 1], not {}",
                self.max_reflectance
            )));
        }
        Ok(())
    }
}

/// Why a file could not be loaded. Every variant names what is wrong; none carries internal
/// state.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// Not a glTF file, or a broken GLB container or JSON.
    #[error("{0}")]
    Container(String),
    /// The `gltf` crate's validation failed (dangling indices, missing required fields,
    /// unsupported required extensions).
    #[error("invalid glTF: {0}")]
    Validation(String),
    /// A buffer or image refers to a file or URL; the loader reads nothing on a scene's behalf.
    #[error(
        "{object}: external URI {uri:?} refused; embed the data (a .glb, or data: URIs in a .gltf)"
    )]
    ExternalUri {
        /// The object holding the URI, e.g. "buffer 0".
        object: String,
        /// The URI (cut to 120 characters).
        uri: String,
    },
    /// An object's content is wrong.
    #[error("{object}: {reason}")]
    Malformed {
        /// The object, e.g. "accessor 3" or "mesh 0 primitive 1".
        object: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A load option is invalid or names something the file does not have.
    #[error("{0}")]
    Option(String),
    /// The scene would exceed a limit (frames, patches).
    #[error("{0}")]
    Limit(String),
    /// Nothing to light.
    #[error("the scene has no triangles with an area")]
    Empty,
}

/// What is left of [`LoadOptions::max_work`].
struct Budget(u64);

impl Budget {
    fn spend(&mut self, amount: u64, what: impl FnOnce() -> String) -> Result<(), LoadError> {
        self.0 = self.0.checked_sub(amount).ok_or_else(|| {
            LoadError::Limit(format!(
                "{} would exceed the evaluation budget; use fewer frames (lower fps or a \
                 shorter start..end)",
                what()
            ))
        })?;
        Ok(())
    }
}

impl LoadError {
    fn malformed(object: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Malformed {
            object: object.into(),
            reason: reason.into(),
        }
    }
}

/// A file that could not be read or loaded ([`load_file`]), named.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    /// The file cannot be read.
    #[error("{}: {reason}", path.display())]
    Read {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        reason: std::io::Error,
    },
    /// Its scene cannot be loaded.
    #[error("{}: {reason}", path.display())]
    Load {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        reason: LoadError,
    },
}

/// The scene of the file at `path` ([`load`]); the error, reading or loading, names the file.
///
/// # Errors
/// The file cannot be read, or its scene loaded.
pub fn load_file(path: &std::path::Path, options: &LoadOptions) -> Result<Scene, FileError> {
    let path_buf = || path.to_path_buf();
    let bytes = std::fs::read(path).map_err(|reason| FileError::Read {
        path: path_buf(),
        reason,
    })?;
    load(&bytes, options).map_err(|reason| FileError::Load {
        path: path_buf(),
        reason,
    })
}

/// Loads a `.glb` or `.gltf` (with embedded data) from memory.
pub fn load(bytes: &[u8], options: &LoadOptions) -> Result<Scene, LoadError> {
    options.check()?;
    let container::Container {
        document,
        buffers,
        warnings,
    } = container::parse(bytes)?;
    let mut warnings = warnings;
    let roots: Vec<usize> = match document
        .default_scene()
        .or_else(|| document.scenes().next())
    {
        Some(scene) => scene.nodes().map(|n| n.index()).collect(),
        None => {
            let mut is_child = vec![false; document.nodes().len()];
            document
                .nodes()
                .flat_map(|n| n.children())
                .for_each(|c| is_child[c.index()] = true);
            warnings.push("the file has no scene: every root node is used".to_string());
            (0..is_child.len()).filter(|&n| !is_child[n]).collect()
        }
    };
    let hierarchy = nodes::hierarchy(&document, &roots)?;
    let morph_targets: Vec<usize> = document
        .nodes()
        .map(|n| n.mesh().map_or(0, |m| mesh::morph_target_count(&m)))
        .collect();
    let timeline = nodes::timeline(&document, &buffers, options, &morph_targets, &mut warnings)?;
    let mut materials = material::convert(&document, &buffers, &mut warnings)?;
    let default_material = materials.len() as u32;
    materials.push(Material::gltf_default());

    let mesh_nodes: Vec<gltf::Node<'_>> = hierarchy
        .order
        .iter()
        .filter_map(|&n| document.nodes().nth(n))
        .filter(|n| n.mesh().is_some())
        .collect();
    let mut wanted = vec![false; document.nodes().len()];
    for node in &mesh_nodes {
        wanted[node.index()] = true;
        if let Some(skin) = node.skin() {
            skin.joints().for_each(|j| wanted[j.index()] = true);
        }
    }
    // The previews' viewpoint: the camera node asked for, or the scene's first (in hierarchy
    // order).
    let camera_nodes: Vec<usize> = (hierarchy.order.iter().copied())
        .filter(|&n| (document.nodes().nth(n)).is_some_and(|node| node.camera().is_some()))
        .collect();
    let camera_node = match options.camera.as_deref() {
        None => camera_nodes.first().copied(),
        Some("auto") => None,
        Some(wanted) => Some(find_camera(&document, &camera_nodes, wanted)?),
    };
    // Every camera is posed: the previews use one, the baked glTF carries all.
    camera_nodes.iter().for_each(|&n| wanted[n] = true);
    let light_nodes: Vec<(usize, usize)> = hierarchy
        .order
        .iter()
        .filter_map(|&n| {
            let node = document.as_json().nodes.get(n)?;
            let light = node.extensions.as_ref()?.khr_lights_punctual.as_ref()?;
            Some((n, light.light.value()))
        })
        .collect();
    light_nodes.iter().for_each(|&(n, _)| wanted[n] = true);
    let mut budget = Budget(options.max_work);
    let animated = nodes::animated(&hierarchy, &timeline.tracks);
    let frame_count = timeline.frames.count as u64;
    budget.spend(
        animated.iter().filter(|a| **a).count() as u64 * frame_count,
        || format!("animating the scene's nodes over {frame_count} frames"),
    )?;
    let poses = nodes::evaluate(&hierarchy, &timeline, &animated, &wanted);
    let frames = timeline.frames;

    let cx = Context {
        document: &document,
        buffers: &buffers,
        poses: &poses,
        frames,
        default_material,
    };
    let mut instances = Vec::with_capacity(mesh_nodes.len());
    for node in &mesh_nodes {
        instances.push(place(&cx, node, &mut budget, &mut warnings)?);
    }
    let default_used = materials_used(&instances, default_material);
    if !default_used {
        materials.pop();
    }
    warnings.extend(material::cap_reflectance(
        &mut materials,
        options.max_reflectance,
        default_used.then_some(default_material as usize),
    ));
    material::check_emission(&materials)?;
    let dropped: usize = instances
        .iter()
        .map(|i| i.kept.iter().filter(|k| !**k).count())
        .sum();
    if dropped > 0 {
        warnings.push(format!("dropped {dropped} zero-area triangles"));
    }
    let normalisation = bounds(&instances, frames.count).ok_or(LoadError::Empty)?;
    let camera = camera_node.and_then(|n| read_camera(&document, n, &poses, &mut warnings));
    let other_cameras: Vec<SceneCamera> = (camera_nodes.iter())
        .filter(|&&n| Some(n) != camera_node)
        .filter_map(|&n| read_camera(&document, n, &poses, &mut warnings))
        .collect();
    let mut scene = build(
        instances,
        materials,
        frames,
        normalisation,
        options,
        warnings,
    )?;
    if let Some(camera) = camera {
        scene.camera = Some(camera.normalised(&scene.normalisation));
    }
    scene.other_cameras = (other_cameras.into_iter())
        .map(|c| c.normalised(&scene.normalisation))
        .collect();
    scene.node_names = document
        .nodes()
        .map(|n| n.name().map(str::to_owned))
        .collect();
    // Every animation plays unless one is chosen (the timeline has checked that it exists).
    let chosen =
        (options.animation.as_deref()).and_then(|w| nodes::find_animation(&document, w).ok());
    scene.animations = document
        .animations()
        .map(|a| {
            let played = chosen.as_ref().is_none_or(|c| c.index() == a.index());
            (a.name().map(str::to_owned), played)
        })
        .collect();
    let to_norm = scene.normalisation.to_normalised();
    for &(n, index) in &light_nodes {
        let mut light = read_light(&document, n, index, &poses)?;
        light.poses.iter_mut().for_each(|p| *p = to_norm * *p);
        light.range = light.range.map(|r| r / scene.normalisation.radius);
        scene.lights.push(light);
    }
    Ok(scene)
}

/// Light `index` (of `KHR_lights_punctual`) at node `n`, posed in scene units. Its values are
/// checked here: gltf-rs would panic on a spot light without its `spot` object.
fn read_light(
    document: &gltf::Document,
    n: usize,
    index: usize,
    poses: &nodes::Poses,
) -> Result<Light, LoadError> {
    use gltf::json::extensions::scene::khr_lights_punctual::Type;
    let what = format!("light {index} (KHR_lights_punctual, node {n})");
    let bad = |why: &str| LoadError::malformed(what.clone(), why);
    let json = document
        .as_json()
        .extensions
        .as_ref()
        .and_then(|e| e.khr_lights_punctual.as_ref())
        .and_then(|l| l.lights.get(index))
        .ok_or_else(|| bad("does not exist"))?;
    let colour = json.color.map(f64::from);
    if colour.iter().any(|c| !c.is_finite() || *c < 0.0) {
        return Err(bad("has a colour that is not finite and non-negative"));
    }
    let intensity = f64::from(json.intensity);
    if !intensity.is_finite() || intensity < 0.0 {
        return Err(bad("has an intensity that is not finite and non-negative"));
    }
    let range = match json.range.map(f64::from) {
        Some(r) if !(r.is_finite() && r > 0.0) => {
            return Err(bad("has a range that is not a positive number"));
        }
        r => r,
    };
    let kind = match json.type_ {
        gltf::json::validation::Checked::Valid(Type::Point) => LightKind::Point,
        gltf::json::validation::Checked::Valid(Type::Directional) => LightKind::Directional,
        gltf::json::validation::Checked::Valid(Type::Spot) => {
            let spot = json
                .spot
                .as_ref()
                .ok_or_else(|| bad("is a spot light without its spot cone"))?;
            let (inner, outer) = (
                f64::from(spot.inner_cone_angle),
                f64::from(spot.outer_cone_angle),
            );
            if !(inner >= 0.0 && inner < outer && outer <= std::f64::consts::FRAC_PI_2) {
                return Err(bad(
                    "needs 0 <= innerConeAngle < outerConeAngle <= pi/2 for its cone",
                ));
            }
            LightKind::Spot { inner, outer }
        }
        gltf::json::validation::Checked::Invalid => return Err(bad("has an unknown type")),
    };
    Ok(Light {
        node: n as u32,
        name: json.name.clone(),
        kind,
        colour,
        intensity,
        range,
        poses: poses.placements(n),
    })
}

/// The camera node of `cameras` (the scene's, in hierarchy order) named `wanted`, or whose
/// node index it is; an error listing them otherwise.
fn find_camera(
    document: &gltf::Document,
    cameras: &[usize],
    wanted: &str,
) -> Result<usize, LoadError> {
    let nodes =
        (cameras.iter()).map(|&n| (n, document.nodes().nth(n).and_then(|node| node.name())));
    find_named(
        nodes,
        wanted,
        ("camera node", "the scene's cameras (or auto)"),
    )
}

/// The index of the item of `items` (index, name) named `wanted`, or whose index it is; else
/// an error naming `what` is asked for and listing the items after `listing`.
fn find_named<'a>(
    items: impl Iterator<Item = (usize, Option<&'a str>)> + Clone,
    wanted: &str,
    (what, listing): (&str, &str),
) -> Result<usize, LoadError> {
    if let Some((i, _)) = items.clone().find(|&(_, name)| name == Some(wanted)) {
        return Ok(i);
    }
    if let Some((i, _)) =
        (wanted.parse::<usize>().ok()).and_then(|w| items.clone().find(|&(i, _)| i == w))
    {
        return Ok(i);
    }
    let listed: Vec<String> = items
        .map(|(i, name)| match name {
            Some(name) => format!("{i} ({name:?})"),
            None => i.to_string(),
        })
        .collect();
    let listed = if listed.is_empty() {
        "none".to_string()
    } else {
        listed.join(", ")
    };
    Err(LoadError::Option(format!(
        "no {what} named or numbered {wanted:?}; {listing}: {listed}"
    )))
}

/// The camera of node `n`, placed in scene units; `None` (with a warning) if its projection is
/// unusable. Only previews use it, so a bad camera never fails a load.
fn read_camera(
    document: &gltf::Document,
    n: usize,
    poses: &nodes::Poses,
    warnings: &mut Vec<String>,
) -> Option<SceneCamera> {
    let node = document.nodes().nth(n)?;
    let index = node.camera()?.index();
    let json = document.as_json().cameras.get(index)?;
    let finite = |v: f32| v.is_finite().then_some(f64::from(v));
    let projection = match (&json.perspective, &json.orthographic) {
        (Some(p), _) => {
            let yfov = finite(p.yfov).filter(|&y| y > 0.0 && y < std::f64::consts::PI);
            let znear = finite(p.znear).filter(|&z| z > 0.0);
            let zfar = p.zfar.map(finite);
            match (yfov, znear, zfar) {
                (Some(yfov), Some(znear), None) => Some(Projection::Perspective {
                    yfov,
                    znear,
                    zfar: None,
                }),
                (Some(yfov), Some(znear), Some(Some(far))) if far > znear => {
                    Some(Projection::Perspective {
                        yfov,
                        znear,
                        zfar: Some(far),
                    })
                }
                _ => None,
            }
        }
        (None, Some(o)) => match (
            finite(o.xmag),
            finite(o.ymag),
            finite(o.znear),
            finite(o.zfar),
        ) {
            (Some(xmag), Some(ymag), Some(znear), Some(zfar))
                if xmag != 0.0 && ymag != 0.0 && znear >= 0.0 && zfar > znear =>
            {
                Some(Projection::Orthographic {
                    xmag: xmag.abs(),
                    ymag: ymag.abs(),
                    znear,
                    zfar,
                })
            }
            _ => None,
        },
        (None, None) => None,
    };
    let Some(projection) = projection else {
        warnings.push(format!(
            "camera {index} (node {n}) has an unusable projection: it is left out (previews without \
             a camera use an automatic one)"
        ));
        return None;
    };
    let aspect = json
        .perspective
        .as_ref()
        .and_then(|p| p.aspect_ratio)
        .and_then(finite)
        .filter(|&a| a > 0.0);
    Some(SceneCamera {
        name: node.name().map(str::to_string),
        projection,
        aspect,
        poses: poses.placements(n),
    })
}

fn materials_used(instances: &[Instance], material: u32) -> bool {
    instances
        .iter()
        .any(|i| i.geometry.origin.iter().any(|o| o.2 == material))
}

/// One mesh node, placed: its geometry and how it sits in the world over the frames.
struct Instance {
    node: u32,
    mesh: u32,
    geometry: mesh::MeshGeometry,
    /// Whether each triangle has an area (at some frame); the others are dropped.
    kept: Vec<bool>,
    placement: Placement,
}

enum Placement {
    /// Never moves: vertex positions in scene units.
    Static(Vec<DVec3>),
    /// Moves rigidly: mesh space to scene units, per frame.
    Rigid(Vec<DMat4>),
    /// Deforms: evaluated per frame, poses in scene units (normalised later).
    Deforming(Box<Deformation>),
}

/// Relative tolerance below which a transform or position counts as unchanged: far below what
/// `f32` tracing in normalised space resolves.
const STILL: f64 = 1e-10;

fn same_matrix(a: &DMat4, b: &DMat4) -> bool {
    let scale = a.to_cols_array().iter().fold(1.0f64, |m, v| m.max(v.abs()));
    a.abs_diff_eq(*b, STILL * scale)
}

/// What placing a mesh node needs to know of the file and its timeline.
struct Context<'a> {
    document: &'a gltf::Document,
    buffers: &'a [Vec<u8>],
    poses: &'a nodes::Poses,
    frames: Frames,
    /// Material index of primitives without a material.
    default_material: u32,
}

fn place(
    cx: &Context<'_>,
    node: &gltf::Node<'_>,
    budget: &mut Budget,
    warnings: &mut Vec<String>,
) -> Result<Instance, LoadError> {
    let Context {
        document,
        buffers,
        poses,
        frames,
        default_material,
    } = *cx;
    let Some(gmesh) = node.mesh() else {
        return Err(LoadError::malformed(
            format!("node {}", node.index()),
            "has no mesh",
        ));
    };
    let n = node.index();
    let skin = node.skin();
    let mut geometry = mesh::read(
        document,
        buffers,
        &gmesh,
        default_material,
        skin.as_ref().map(|s| s.joints().len()),
        warnings,
    )?;
    let targets = geometry.targets.len();
    let animated_weights = poses.weights[n].is_some();
    let deforms =
        (skin.is_some() && geometry.influences.is_some()) || (targets > 0 && animated_weights);
    let frame_count = frames.count;
    let placement = if deforms || targets > 0 {
        // Posing every frame three times over (moves? bounds, areas), plus the joints.
        let joints = skin.as_ref().map_or(0, |s| s.joints().len());
        budget.spend(
            (3 * geometry.positions.len() + joints) as u64 * frame_count as u64,
            || format!("deforming node {n} over {frame_count} frames"),
        )?;
        // Morph targets with fixed weights still displace the mesh: evaluate them like a
        // deformation and keep the result static if it never changes.
        let default_weights: Vec<f64> = node
            .weights()
            .or_else(|| gmesh.weights())
            .map(|w| w.iter().map(|&x| f64::from(x)).collect())
            .unwrap_or_default();
        let mut fixed = vec![0.0; targets];
        for (slot, w) in fixed.iter_mut().zip(&default_weights) {
            *slot = *w;
        }
        if !default_weights.is_empty() && default_weights.len() != targets {
            warnings.push(format!(
                "node {n}: {} default morph weights for {targets} targets",
                default_weights.len()
            ));
        }
        let weights = match &poses.weights[n] {
            Some(w) => w.clone(),
            None => fixed.repeat(frame_count),
        };
        let skin_binding = match (&skin, &geometry.influences) {
            (Some(skin), Some(influences)) => {
                let ibm = mesh::inverse_bind_matrices(document, buffers, skin)?;
                let joints: Vec<usize> = skin.joints().map(|j| j.index()).collect();
                let mut joint_poses = Vec::with_capacity(frame_count * joints.len());
                for f in 0..frame_count {
                    for (j, &joint) in joints.iter().enumerate() {
                        joint_poses.push(DAffine3::from_mat4(poses.world(joint, f)) * ibm[j]);
                    }
                }
                let mut offsets = vec![0u32];
                let mut flat = Vec::new();
                for list in influences {
                    flat.extend_from_slice(list);
                    offsets.push(flat.len() as u32);
                }
                Some(SkinBinding {
                    offsets,
                    influences: flat,
                    joints: joints.len(),
                    joint_poses,
                })
            }
            (Some(_), None) => {
                warnings.push(format!(
                    "node {n} has a skin but its mesh has no JOINTS_0/WEIGHTS_0: placed rigidly"
                ));
                None
            }
            _ => None,
        };
        let node_poses = (0..frame_count)
            .map(|f| DAffine3::from_mat4(poses.world(n, f)))
            .collect();
        let deformation = Deformation {
            base: geometry.positions.clone(),
            targets: geometry.targets.clone(),
            weights,
            skin: skin_binding,
            node_poses,
            midpoints: Vec::new(),
        };
        let first = deformation.positions_at(0);
        let scale = first
            .iter()
            .fold(0.0f64, |m, p| m.max(p.abs().max_element()));
        let moves = (1..frame_count).any(|f| {
            deformation
                .positions_at(f)
                .iter()
                .zip(&first)
                .any(|(a, b)| !a.abs_diff_eq(*b, STILL * scale.max(f64::MIN_POSITIVE)))
        });
        if moves {
            Placement::Deforming(Box::new(deformation))
        } else {
            Placement::Static(first)
        }
    } else {
        let first = poses.world(n, 0);
        let moves = (1..frame_count).any(|f| !same_matrix(&poses.world(n, f), &first));
        if moves {
            Placement::Rigid((0..frame_count).map(|f| poses.world(n, f)).collect())
        } else {
            Placement::Static(
                geometry
                    .positions
                    .iter()
                    .map(|&p| first.transform_point3(p))
                    .collect(),
            )
        }
    };
    for p in positions_to_check(&placement, &geometry) {
        if !p.is_finite() {
            return Err(LoadError::malformed(
                format!("node {n}"),
                "its transforms give non-finite positions",
            ));
        }
    }
    // glTF 2.0 §3.7.2.1: under a global transform with a negative determinant (a mirror), a
    // triangle's front face is the one it winds clockwise round. Reversing the winding keeps
    // "counter-clockwise is front" for the rest of the engine. A skinned mesh ignores its node's
    // transform; its joints are taken as authored.
    let skinned = matches!(&placement, Placement::Deforming(d) if d.skin.is_some());
    if !skinned && poses.world(n, 0).determinant() < 0.0 {
        geometry.triangles.iter_mut().for_each(|t| t.swap(1, 2));
    }
    let kept = keep_triangles(&geometry, &placement, frame_count);
    Ok(Instance {
        node: n as u32,
        mesh: gmesh.index() as u32,
        geometry,
        kept,
        placement,
    })
}

/// Positions whose finiteness the instance must guarantee (frame 0 is representative: every
/// pose is a product of finite matrices checked at load).
fn positions_to_check(placement: &Placement, geometry: &mesh::MeshGeometry) -> Vec<DVec3> {
    match placement {
        Placement::Static(p) => p.clone(),
        Placement::Rigid(poses) => {
            let ok = poses.iter().all(|m| m.is_finite());
            let mut v = geometry.positions.clone();
            if !ok {
                v.push(DVec3::NAN);
            }
            v
        }
        Placement::Deforming(d) => {
            let mut v = d.positions_at(0);
            if !d.node_poses.iter().all(|m| m.is_finite())
                || !d
                    .skin
                    .as_ref()
                    .is_none_or(|s| s.joint_poses.iter().all(|m| m.is_finite()))
            {
                v.push(DVec3::NAN);
            }
            v
        }
    }
}

/// A triangle is kept if it has an area: in scene units for static geometry, in mesh space for
/// a rigid object (a pose may scale it to nothing for a while), at some frame for a deforming
/// one. "No area" is relative: below 1e-12 of its longest edge squared, which is collinear to
/// within the precision of its input.
fn keep_triangles(
    geometry: &mesh::MeshGeometry,
    placement: &Placement,
    frames: usize,
) -> Vec<bool> {
    let has_area = |p: &[DVec3], t: &[u32; 3]| {
        let [a, b, c] = t.map(|i| p[i as usize]);
        let longest = (b - a)
            .length_squared()
            .max((c - b).length_squared())
            .max((a - c).length_squared());
        triangle_area(a, b, c) > 1e-12 * longest
    };
    match placement {
        Placement::Static(p) => geometry.triangles.iter().map(|t| has_area(p, t)).collect(),
        Placement::Rigid(_) => geometry
            .triangles
            .iter()
            .map(|t| has_area(&geometry.positions, t))
            .collect(),
        Placement::Deforming(d) => {
            let mut kept = vec![false; geometry.triangles.len()];
            for f in 0..frames {
                if kept.iter().all(|k| *k) {
                    break;
                }
                let p = d.positions_at(f);
                for (k, t) in kept.iter_mut().zip(&geometry.triangles) {
                    *k = *k || has_area(&p, t);
                }
            }
            kept
        }
    }
}

/// Bounding box of every kept triangle over every frame, in scene units.
fn bounds(instances: &[Instance], frames: usize) -> Option<Bounds> {
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    let mut grow = |p: DVec3| {
        lo = lo.min(p);
        hi = hi.max(p);
    };
    for inst in instances {
        let used = used_vertices(inst);
        match &inst.placement {
            Placement::Static(p) => used.iter().for_each(|&v| grow(p[v])),
            Placement::Rigid(poses) => {
                let local = local_box(&inst.geometry.positions, &used);
                for pose in poses {
                    local
                        .corners()
                        .iter()
                        .for_each(|&c| grow(pose.transform_point3(c)));
                }
            }
            Placement::Deforming(d) => {
                for f in 0..frames {
                    let p = d.positions_at(f);
                    used.iter().for_each(|&v| grow(p[v]));
                }
            }
        }
    }
    let radius = 0.5 * (hi - lo).length();
    (lo.x <= hi.x && radius > 0.0 && radius.is_finite()).then_some(Bounds { min: lo, max: hi })
}

/// Vertices referenced by kept triangles, sorted.
fn used_vertices(inst: &Instance) -> Vec<usize> {
    let mut used: Vec<usize> = inst
        .geometry
        .triangles
        .iter()
        .zip(&inst.kept)
        .filter(|(_, k)| **k)
        .flat_map(|(t, _)| t.map(|i| i as usize))
        .collect();
    used.sort_unstable();
    used.dedup();
    used
}

fn local_box(positions: &[DVec3], used: &[usize]) -> Bounds {
    used.iter().fold(
        Bounds {
            min: DVec3::INFINITY,
            max: DVec3::NEG_INFINITY,
        },
        |b, &v| Bounds {
            min: b.min.min(positions[v]),
            max: b.max.max(positions[v]),
        },
    )
}

impl Instance {
    /// Positions (scene units) that decide the subdivision, and where areas are measured: a
    /// rigid object's at its widest pose, a deforming one's at frame 0.
    fn measured_positions(&self) -> Vec<DVec3> {
        match &self.placement {
            Placement::Static(p) => p.clone(),
            Placement::Rigid(poses) => {
                let widest = poses
                    .iter()
                    .max_by(|a, b| a.determinant().abs().total_cmp(&b.determinant().abs()))
                    .copied()
                    .unwrap_or(DMat4::IDENTITY);
                (self.geometry.positions.iter())
                    .map(|&p| widest.transform_point3(p))
                    .collect()
            }
            Placement::Deforming(d) => d.positions_at(0),
        }
    }

    /// The area of each of `split`'s triangles: a rigid object's at its first pose, the others'
    /// on `measure` (the positions the split was made on, its midpoints included).
    fn areas(&self, split: &Subdivision, measure: &[DVec3]) -> Vec<f64> {
        let positions: Vec<DVec3> = match &self.placement {
            Placement::Rigid(poses) => {
                let mut local = self.geometry.positions.clone();
                subdivide::apply_midpoints(&mut local, &split.midpoints);
                (local.iter())
                    .map(|&p| poses[0].transform_point3(p))
                    .collect()
            }
            _ => measure.to_vec(),
        };
        (split.triangles.iter())
            .map(|t| {
                let [a, b, c] = t.map(|i| positions[i as usize]);
                triangle_area(a, b, c)
            })
            .collect()
    }
}

/// A rigid moving object of node `node`: `mesh` on `positions` (mesh space, with the split's
/// `midpoints`) recentred on their box, posed by `poses` (mesh space to scene units) carried
/// into normalised space by `to_norm`.
fn rigid(
    node: u32,
    positions: &[DVec3],
    mut mesh: TriangleMesh,
    (poses, midpoints): (&[DMat4], &[[u32; 2]]),
    to_norm: DAffine3,
) -> MovingObject {
    let used: Vec<usize> = (0..positions.len()).collect();
    let local_bounds = local_box(positions, &used);
    let centre = 0.5 * (local_bounds.min + local_bounds.max);
    let mut local = positions.to_vec();
    subdivide::apply_midpoints(&mut local, midpoints);
    mesh.positions = local.iter().map(|&p| (p - centre).as_vec3()).collect();
    let recentre = DMat4::from_translation(centre);
    let to_norm = DMat4::from(to_norm);
    let poses = (poses.iter())
        .map(|m| DAffine3::from_mat4(to_norm * *m * recentre))
        .collect();
    MovingObject {
        node,
        mesh,
        motion: Motion::Rigid { poses },
    }
}

/// A deforming object of node `node`: `mesh` with the deformation `d` (its poses carried into
/// normalised space by `to_norm`, the split's `midpoints` kept), posed at frame 0.
fn deforming(
    node: u32,
    mut d: Deformation,
    mut mesh: TriangleMesh,
    midpoints: Vec<[u32; 2]>,
    to_norm: DAffine3,
) -> MovingObject {
    d.node_poses.iter_mut().for_each(|m| *m = to_norm * *m);
    if let Some(skin) = &mut d.skin {
        skin.joint_poses.iter_mut().for_each(|m| *m = to_norm * *m);
    }
    d.midpoints = midpoints;
    mesh.positions = d.positions_at(0).iter().map(|p| p.as_vec3()).collect();
    MovingObject {
        node,
        mesh,
        motion: Motion::Deforming(Box::new(d)),
    }
}

/// Makes the patches and the engine's geometry from the placed instances.
fn build(
    instances: Vec<Instance>,
    materials: Vec<Material>,
    frames: Frames,
    bounds: Bounds,
    options: &LoadOptions,
    warnings: Vec<String>,
) -> Result<Scene, LoadError> {
    let normalisation = Normalisation {
        center: 0.5 * (bounds.min + bounds.max),
        radius: 0.5 * (bounds.max - bounds.min).length(),
    };
    let to_norm = normalisation.to_normalised();
    let mut patches: Vec<Patch> = Vec::new();
    let mut statics = TriangleMesh::default();
    let mut objects = Vec::new();
    let mut source_triangles = 0;
    let too_many = || {
        LoadError::Limit(format!(
            "the scene would have more than {} patches{}",
            options.max_patches,
            if options.patch_size.is_some() {
                "; use a larger patch_size"
            } else {
                ""
            }
        ))
    };
    for inst in instances {
        let kept: Vec<usize> = (0..inst.kept.len()).filter(|&t| inst.kept[t]).collect();
        if kept.is_empty() {
            continue;
        }
        source_triangles += kept.len();
        let triangles: Vec<[u32; 3]> = kept.iter().map(|&t| inst.geometry.triangles[t]).collect();
        let measure = inst.measured_positions();
        let budget = options.max_patches.saturating_sub(patches.len());
        let split = match options.patch_size {
            Some(size) => {
                subdivide::subdivide(&measure, &triangles, size, budget).map_err(|_| too_many())?
            }
            None => Subdivision {
                midpoints: Vec::new(),
                sources: (0..triangles.len() as u32).collect(),
                corners: vec![Origin::WHOLE.map(|c| c.map(|x| x as f32)); triangles.len()],
                triangles,
            },
        };
        let mut measure = measure;
        subdivide::apply_midpoints(&mut measure, &split.midpoints);
        let object = match inst.placement {
            Placement::Static(_) => None,
            _ => Some(objects.len() as u32),
        };
        let mut mesh = TriangleMesh::default();
        let areas = inst.areas(&split, &measure);
        let corners = split.corners.iter();
        for (((t, &src), area), &corners) in (split.triangles.iter())
            .zip(&split.sources)
            .zip(areas)
            .zip(corners)
        {
            let (primitive, triangle, material) = inst.geometry.origin[kept[src as usize]];
            let source = Provenance {
                node: inst.node,
                mesh: inst.mesh,
                primitive,
                triangle,
            };
            let mut patch = |side| {
                patches.push(Patch {
                    source,
                    side,
                    material,
                    area,
                    object,
                    merged: Vec::new(),
                });
                (patches.len() - 1) as u32
            };
            let front = patch(Side::Front);
            let back = materials[material as usize]
                .double_sided
                .then(|| patch(Side::Back));
            mesh.triangles.push(*t);
            mesh.faces.push(Faces { front, back });
            mesh.origins.push(Origin { triangle, corners });
        }
        if patches.len() > options.max_patches {
            return Err(too_many());
        }
        match inst.placement {
            Placement::Static(_) => {
                let base = statics.positions.len() as u32;
                statics.positions.extend(
                    measure
                        .iter()
                        .map(|&p| to_norm.transform_point3(p).as_vec3()),
                );
                statics
                    .triangles
                    .extend(mesh.triangles.iter().map(|t| t.map(|i| i + base)));
                statics.faces.extend(mesh.faces);
                statics.origins.extend(mesh.origins);
            }
            Placement::Rigid(poses) => {
                let positions = &inst.geometry.positions;
                objects.push(rigid(
                    inst.node,
                    positions,
                    mesh,
                    (&poses, &split.midpoints),
                    to_norm,
                ));
            }
            Placement::Deforming(d) => {
                objects.push(deforming(inst.node, *d, mesh, split.midpoints, to_norm));
            }
        }
    }
    debug_assert!(statics.positions.iter().all(|p: &Vec3| p.is_finite()));
    Ok(Scene {
        materials,
        patches,
        statics,
        objects,
        frames,
        normalisation,
        // Symmetric about the centre by construction, and independent of where the scene
        // sits: the same scene moved far from the origin gets bit-identical lines.
        bounds: {
            let half = 0.5 * (bounds.max - bounds.min) / normalisation.radius;
            Bounds {
                min: -half,
                max: half,
            }
        },
        source_triangles,
        warnings,
        node_names: Vec::new(),
        camera: None,
        other_cameras: Vec::new(),
        lights: Vec::new(),
        animations: Vec::new(),
    })
}
