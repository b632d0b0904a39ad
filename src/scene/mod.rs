//! The scene model the engine works on: patches, the static triangles, the moving objects and
//! the frames of the timeline.
//!
//! It knows nothing of glTF or HTTP: the loader (`crate::loader`) builds it from a file, and the
//! engine reads it. A `Scene` is known-good once built: every position is finite, every index is
//! in range, every traced triangle has a non-zero area at some frame.
//!
//! Geometry lives in *normalised* space: the scene's bounding sphere (over every frame) mapped to
//! the unit sphere, so that tracing in `f32` keeps the same relative precision for a scene of a
//! millimetre and one of a kilometre placed far from the origin. [`Normalisation`] takes results
//! back to the scene's own units.

pub mod refine;
pub mod subdivide;

use glam::{DAffine3, DVec3, Vec3};
use serde::Serialize;

/// Which face of a surface a patch is. A one-sided material gives only a front patch; a
/// double-sided one gives a front and a back patch (METHOD.md §3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Side {
    /// The face the triangle's winding points to (counter-clockwise seen from it).
    Front,
    /// The other face; present only for double-sided materials.
    Back,
}

/// Where a patch came from in the source file, so that clients can map results back.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, serde::Deserialize)]
pub struct Provenance {
    /// Index of the node that instances the mesh.
    pub node: u32,
    /// Index of the mesh.
    pub mesh: u32,
    /// Index of the primitive within the mesh.
    pub primitive: u32,
    /// Index of the triangle within the primitive (its position in the primitive's triangle list,
    /// after strips and fans are unrolled).
    pub triangle: u32,
}

/// A patch: one face of one (possibly subdivided) triangle, or of several coplanar ones merged
/// ([`refine::merge`]); the unit radiosity is solved for.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Patch {
    /// The source triangle this patch is (part of); a merged patch's first member's.
    pub source: Provenance,
    /// Which face of the triangle.
    pub side: Side,
    /// Index into [`Scene::materials`].
    pub material: u32,
    /// Area in the scene's own units squared, at frame 0 (a scaled or deforming object's patches
    /// change area over time; the engine measures area from the lines, not from this field).
    pub area: f64,
    /// The moving object the patch belongs to, `None` for static geometry.
    pub object: Option<u32>,
    /// A patch merged from several source triangles ([`refine::merge`]; all of one node, mesh
    /// and primitive): the others' indices within the primitive, ascending; empty otherwise.
    pub merged: Vec<u32>,
}

/// The optical properties the radiosity solve needs, per material.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct Material {
    /// The material's name in the source file, if any.
    pub name: Option<String>,
    /// Diffuse reflectance per RGB channel, in [0, 1].
    pub reflectance: [f64; 3],
    /// Emitted radiance per RGB channel, in the units of the source's emissive colour (≥ 0).
    pub emission: [f64; 3],
    /// Whether each triangle has a back patch too.
    pub double_sided: bool,
}

impl Material {
    /// The glTF default material: white, not metallic (so reflectance 1), no emission, one-sided.
    #[must_use]
    pub fn gltf_default() -> Self {
        Self {
            name: None,
            reflectance: [1.0; 3],
            emission: [0.0; 3],
            double_sided: false,
        }
    }

    /// Whether the material emits light in any channel.
    #[must_use]
    pub fn is_emitter(&self) -> bool {
        self.emission.iter().any(|&e| e > 0.0)
    }

    /// Whether a channel's reflectance is above `max` by more than `f32` rounding: glTF's factors
    /// are `f32`, so a file's 0.999 (0.99900001… once read) is not above a cap of 0.999.
    #[must_use]
    pub fn reflects_above(&self, max: f64) -> bool {
        self.reflectance.iter().any(|&r| r as f32 > max as f32)
    }
}

/// The patches on the two faces of a traced triangle. A line hitting the front face of the
/// triangle deposits on `front`; hitting the back, on `back`, or nowhere (absorbed) when the
/// material is one-sided.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Faces {
    /// Patch on the front face.
    pub front: u32,
    /// Patch on the back face, for double-sided materials.
    pub back: Option<u32>,
}

/// Indexed triangles with the patches on their faces. Triangles that share an edge share the
/// vertex indices of that edge, so the tracer sees bit-identical edge positions (watertightness).
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct TriangleMesh {
    /// Vertex positions; their space depends on the owner (normalised space for static geometry,
    /// object space for a rigid object, unused for a deforming one).
    pub positions: Vec<Vec3>,
    /// Vertex indices of each triangle, counter-clockwise seen from the front face.
    pub triangles: Vec<[u32; 3]>,
    /// Patches on the faces of each triangle (same length as `triangles`).
    pub faces: Vec<Faces>,
    /// Where each triangle lies on the source triangle it was made from (same length as
    /// `triangles`; empty for a mesh built otherwise than from a file, whose triangles are
    /// then taken for their patches' source triangles whole).
    #[serde(default)]
    pub origins: Vec<Origin>,
}

/// Where a triangle of the scene lies on a triangle of the source file: the source triangle
/// (within its patch's primitive) and its corners there, in order. Subdivision and cuts make
/// a triangle part of its source triangle; merges make a patch of several source triangles'.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Origin {
    /// The source triangle's index within its primitive ([`Provenance::triangle`]).
    pub triangle: u32,
    /// Each corner's barycentric coordinates on the source triangle: the weights `(u, v)` of
    /// its second and third corners (the first's is `1 − u − v`).
    pub corners: [[f32; 2]; 3],
}

impl Origin {
    /// The corners of a whole source triangle.
    pub const WHOLE: [[f64; 2]; 3] = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];

    /// Whether this is its source triangle whole, corners in the source's order.
    #[must_use]
    pub fn is_whole(&self) -> bool {
        self.corners == Self::WHOLE.map(|c| c.map(|x| x as f32))
    }

    /// The halves of a triangle at this origin cut at the midpoint of its edge `k` (from
    /// corner `k` to corner `k + 1`), with the corners `[a, m, c]` and `[m, b, c]` the cut
    /// gives them ([`refine`]).
    #[must_use]
    pub fn halves(&self, k: usize) -> [Self; 2] {
        let (a, b, c) = (
            self.corners[k],
            self.corners[(k + 1) % 3],
            self.corners[(k + 2) % 3],
        );
        let m = [0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1])];
        let triangle = self.triangle;
        [
            Self {
                triangle,
                corners: [a, m, c],
            },
            Self {
                triangle,
                corners: [m, b, c],
            },
        ]
    }
}

/// A transform-animated or deforming part of the scene (one node of the source file).
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct MovingObject {
    /// The node this object is.
    pub node: u32,
    /// Its triangles. For a rigid object, `positions` are in object space; for a deforming object
    /// they are the frame-0 positions in normalised space (use [`MovingObject::positions_at`]).
    pub mesh: TriangleMesh,
    /// How its geometry changes over the frames.
    pub motion: Motion,
}

/// How a moving object's geometry changes with the frame.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub enum Motion {
    /// One set of triangles and a transform per frame.
    Rigid {
        /// Object space to normalised space, per frame (f64: composed from the source's
        /// transforms and the normalisation without loss).
        poses: Vec<DAffine3>,
    },
    /// Skinned or morphing: vertex positions are evaluated per frame.
    Deforming(Box<Deformation>),
}

/// Everything needed to pose a skinned or morphing mesh at any frame, without storing frames ×
/// vertices: the memory grows with the vertices and with joints × frames.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Deformation {
    /// Rest positions of the source vertices, in the mesh's own space.
    pub base: Vec<DVec3>,
    /// Morph target position deltas: `targets[t][v]`.
    pub targets: Vec<Vec<DVec3>>,
    /// Morph weights per frame, `frames × targets.len()` values.
    pub weights: Vec<f64>,
    /// Skinning, if the mesh is skinned; otherwise `node_poses` places the mesh.
    pub skin: Option<SkinBinding>,
    /// Mesh space to normalised space per frame, for a morphing mesh that is not skinned.
    pub node_poses: Vec<DAffine3>,
    /// Vertices added by subdivision: each is the midpoint of two earlier vertices.
    pub midpoints: Vec<[u32; 2]>,
}

/// Linear-blend skinning data of a deforming mesh.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SkinBinding {
    /// Start of each source vertex's influences in `influences` (length = vertices + 1).
    pub offsets: Vec<u32>,
    /// (joint, weight) pairs; weights of a vertex sum to 1.
    pub influences: Vec<(u32, f64)>,
    /// Number of joints of the skin.
    pub joints: usize,
    /// Joint matrices composed with the normalisation, `frames × joints`:
    /// normalise ∘ world(joint) ∘ inverse bind matrix.
    pub joint_poses: Vec<DAffine3>,
}

impl Deformation {
    /// Vertex positions at `frame` in normalised space, subdivision midpoints included.
    #[must_use]
    pub fn positions_at(&self, frame: usize) -> Vec<DVec3> {
        let n_targets = self.targets.len();
        let weights = &self.weights[frame * n_targets..(frame + 1) * n_targets];
        let mut out = Vec::with_capacity(self.base.len() + self.midpoints.len());
        for (v, &rest) in self.base.iter().enumerate() {
            let mut p = rest;
            for (target, &w) in self.targets.iter().zip(weights) {
                if w != 0.0 {
                    p += target[v] * w;
                }
            }
            let posed = match &self.skin {
                Some(skin) => {
                    let poses = &skin.joint_poses[frame * skin.joints..(frame + 1) * skin.joints];
                    let range = skin.offsets[v] as usize..skin.offsets[v + 1] as usize;
                    skin.influences[range]
                        .iter()
                        .map(|&(joint, w)| poses[joint as usize].transform_point3(p) * w)
                        .sum()
                }
                None => self.node_poses[frame].transform_point3(p),
            };
            out.push(posed);
        }
        for &[a, b] in &self.midpoints {
            let m = midpoint(out[a as usize], out[b as usize]);
            out.push(m);
        }
        out
    }
}

/// The midpoint used by subdivision. Symmetric in its arguments to the bit (IEEE addition is
/// commutative), which keeps shared edges of neighbouring triangles identical.
#[must_use]
pub fn midpoint(a: DVec3, b: DVec3) -> DVec3 {
    (a + b) * 0.5
}

impl MovingObject {
    /// Vertex positions of the object at `frame`, in normalised space.
    #[must_use]
    pub fn positions_at(&self, frame: usize) -> Vec<Vec3> {
        match &self.motion {
            Motion::Rigid { poses } => {
                let pose = poses[frame];
                self.mesh
                    .positions
                    .iter()
                    .map(|p| pose.transform_point3(p.as_dvec3()).as_vec3())
                    .collect()
            }
            Motion::Deforming(d) => d.positions_at(frame).iter().map(|p| p.as_vec3()).collect(),
        }
    }

    /// Whether the object is rigid (one set of triangles and a pose per frame).
    #[must_use]
    pub fn is_rigid(&self) -> bool {
        matches!(self.motion, Motion::Rigid { .. })
    }
}

/// The frames of the timeline: frame `f` is at time `start + f / fps`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Frames {
    /// Time of frame 0, in seconds.
    pub start: f64,
    /// Frames per second.
    pub fps: f64,
    /// Number of frames (at least 1).
    pub count: usize,
}

impl Frames {
    /// Time of frame `f`, in seconds.
    #[must_use]
    pub fn time(&self, f: usize) -> f64 {
        self.start + f as f64 / self.fps
    }
}

/// The map between the scene's own units and normalised space, where the bounding sphere of the
/// whole animation is the unit sphere: `p_normalised = (p - center) / radius`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalisation {
    /// Centre of the bounding sphere, in scene units.
    pub center: DVec3,
    /// Radius of the bounding sphere, in scene units (> 0).
    pub radius: f64,
}

impl Normalisation {
    /// The affine map from scene units to normalised space.
    #[must_use]
    pub fn to_normalised(&self) -> DAffine3 {
        DAffine3::from_scale(DVec3::splat(1.0 / self.radius))
            * DAffine3::from_translation(-self.center)
    }

    /// A point in normalised space back in scene units.
    #[must_use]
    pub fn to_scene(&self, p: DVec3) -> DVec3 {
        self.center + p * self.radius
    }
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Bounds {
    /// Smallest corner.
    pub min: DVec3,
    /// Largest corner.
    pub max: DVec3,
}

impl Bounds {
    /// Surface area of the box (the `A(W)` of METHOD.md §1 when the box is the convex hull
    /// lines are drawn against).
    #[must_use]
    pub fn surface_area(&self) -> f64 {
        let d = self.max - self.min;
        2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
    }

    /// The eight corners.
    #[must_use]
    pub fn corners(&self) -> [DVec3; 8] {
        std::array::from_fn(|k| {
            DVec3::new(
                if k & 1 == 0 { self.min.x } else { self.max.x },
                if k & 2 == 0 { self.min.y } else { self.max.y },
                if k & 4 == 0 { self.min.z } else { self.max.z },
            )
        })
    }
}

/// How a camera projects, with glTF's conventions: the camera looks down its local −Z with +Y
/// up. Distances are in the space the camera is placed in.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Projection {
    /// Perspective.
    Perspective {
        /// Vertical field of view, radians.
        yfov: f64,
        /// Distance of the near plane (> 0).
        znear: f64,
        /// Distance of the far plane; `None` for an infinite projection.
        zfar: Option<f64>,
    },
    /// Orthographic.
    Orthographic {
        /// Half the width of the view volume.
        xmag: f64,
        /// Half the height of the view volume.
        ymag: f64,
        /// Distance of the near plane.
        znear: f64,
        /// Distance of the far plane.
        zfar: f64,
    },
}

/// The scene's camera (the first camera node of the scene), for previews: the viewpoint the
/// scene's author chose.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneCamera {
    /// Name of the camera node, if any.
    pub name: Option<String>,
    /// Projection, its distances in normalised space.
    pub projection: Projection,
    /// Width / height the camera asks for, if it fixes one.
    pub aspect: Option<f64>,
    /// Camera space to normalised space (may include the normalisation's uniform scale), per
    /// frame when the camera moves, otherwise a single pose for every frame.
    pub poses: Vec<DAffine3>,
}

impl SceneCamera {
    /// The same camera taken from scene units (as read) to normalised space.
    #[must_use]
    pub fn normalised(mut self, normalisation: &Normalisation) -> Self {
        let to = normalisation.to_normalised();
        let k = 1.0 / normalisation.radius;
        self.poses.iter_mut().for_each(|p| *p = to * *p);
        self.projection = match self.projection {
            Projection::Perspective { yfov, znear, zfar } => Projection::Perspective {
                yfov,
                znear: znear * k,
                zfar: zfar.map(|z| z * k),
            },
            Projection::Orthographic {
                xmag,
                ymag,
                znear,
                zfar,
            } => Projection::Orthographic {
                xmag: xmag * k,
                ymag: ymag * k,
                znear: znear * k,
                zfar: zfar * k,
            },
        };
        self
    }

    /// The camera's pose at `frame`.
    #[must_use]
    pub fn pose(&self, frame: usize) -> DAffine3 {
        self.poses[frame.min(self.poses.len() - 1)]
    }
}

/// A punctual light (glTF `KHR_lights_punctual`), placed by its node.
///
/// Units, as the extension defines them with the scene's units taken as metres: a point or spot
/// light's intensity is in candela (lm/sr), a directional light's in lux (lm/m²). A surface at
/// distance d from a point light of intensity I, tilted by θ, receives the irradiance
/// E = I·cos θ / d² (lux); a diffuse surface of reflectance ρ then leaves with the radiance
/// ρ·E/π (cd/m², nits), the unit the scene's emissive surfaces are read in.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Light {
    /// The node the light is attached to.
    pub node: u32,
    /// The light's name, if any.
    pub name: Option<String>,
    /// Point, spot or directional.
    pub kind: LightKind,
    /// Linear RGB colour (each channel ≥ 0), multiplied by the intensity.
    pub colour: [f64; 3],
    /// Candela for point and spot lights, lux for directional ones.
    pub intensity: f64,
    /// Distance beyond which a point or spot light has no effect, in normalised units; with the
    /// extension's recommended smooth falloff to zero there.
    pub range: Option<f64>,
    /// Light space to normalised space, per frame when the light moves, otherwise one pose for
    /// every frame. The light sits at the origin of its space and points along its −Z.
    pub poses: Vec<DAffine3>,
}

/// What kind of punctual light.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum LightKind {
    /// Emits equally in every direction from a point.
    Point,
    /// A point light limited to a cone around −Z, with a smooth edge between the angles.
    Spot {
        /// Angle from the axis where the falloff starts, radians.
        inner: f64,
        /// Angle from the axis beyond which there is no light, radians.
        outer: f64,
    },
    /// Parallel light travelling along −Z, as from an infinitely far source (the sun).
    Directional,
}

impl Light {
    /// The light's pose at `frame`.
    #[must_use]
    pub fn pose(&self, frame: usize) -> DAffine3 {
        self.poses[frame.min(self.poses.len() - 1)]
    }

    /// Position at `frame`, normalised space.
    #[must_use]
    pub fn position(&self, frame: usize) -> DVec3 {
        self.pose(frame).translation
    }

    /// Unit direction the light travels in at `frame` (its −Z), normalised space.
    #[must_use]
    pub fn direction(&self, frame: usize) -> DVec3 {
        self.pose(frame)
            .transform_vector3(DVec3::NEG_Z)
            .normalize_or_zero()
    }

    /// Colour × intensity: what the direct light of a unit light is scaled by.
    #[must_use]
    pub fn power(&self) -> [f64; 3] {
        self.colour.map(|c| c * self.intensity)
    }

    /// Whether the light's pose changes over the frames.
    #[must_use]
    pub fn moves(&self) -> bool {
        self.poses.len() > 1
    }
}

/// A loaded scene, ready for the engine.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Scene {
    /// Materials, indexed by [`Patch::material`].
    pub materials: Vec<Material>,
    /// Every patch; a patch's id is its index here.
    pub patches: Vec<Patch>,
    /// Geometry that never moves, in normalised space: traced once for the whole timeline.
    pub statics: TriangleMesh,
    /// Geometry that moves or deforms.
    pub objects: Vec<MovingObject>,
    /// The frames of the timeline.
    pub frames: Frames,
    /// Scene units to normalised space.
    pub normalisation: Normalisation,
    /// Box around all geometry over all frames, in normalised space (inside the unit sphere):
    /// lines are drawn against it.
    pub bounds: Bounds,
    /// Source triangles kept (before subdivision), for the summary.
    pub source_triangles: usize,
    /// Things the loader ignored or repaired, one line each.
    pub warnings: Vec<String>,
    /// The source file's node names, by node index (for messages).
    pub node_names: Vec<Option<String>>,
    /// The scene's camera, if it has one (used only for previews).
    pub camera: Option<SceneCamera>,
    /// The scene's other cameras, in hierarchy order: the baked glTF carries them after
    /// `camera`, so a viewer can offer them all.
    pub other_cameras: Vec<SceneCamera>,
    /// Punctual lights: the direct light they give starts the interreflection solve.
    pub lights: Vec<Light>,
    /// The source file's animations, by index: each one's name, and whether it is played.
    pub animations: Vec<(Option<String>, bool)>,
}

/// One named thing of a scene as [`Summary`] lists it: its index in the source file (or in the
/// scene's list), its name, and what more there is to say of it.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Named {
    /// Index (materials and animations: the file's; lights: the scene's, in the order
    /// relighting numbers them).
    pub index: usize,
    /// Name in the source file, if any.
    pub name: Option<String>,
    /// What kind it is or what it does (`emits`, `double-sided`, `point`, `played`...).
    pub notes: Vec<&'static str>,
}

impl std::fmt::Display for Named {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.index)?;
        if let Some(name) = &self.name {
            write!(f, " {name:?}")?;
        }
        if !self.notes.is_empty() {
            write!(f, " ({})", self.notes.join(", "))?;
        }
        Ok(())
    }
}

/// What the `scene` command and the service report about a loaded scene.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Summary {
    /// Source triangles kept (zero-area ones dropped).
    pub triangles: usize,
    /// Traced triangles after subdivision.
    pub traced_triangles: usize,
    /// Patches (a double-sided triangle has two).
    pub patches: usize,
    /// Triangles of the static geometry.
    pub static_triangles: usize,
    /// Moving objects, rigid and deforming.
    pub moving_objects: usize,
    /// Rigid moving objects among them.
    pub rigid_objects: usize,
    /// Deforming (skinned or morphing) objects among them.
    pub deforming_objects: usize,
    /// Triangles of the moving objects.
    pub moving_triangles: usize,
    /// Frames of the timeline.
    pub frames: usize,
    /// Time of the first frame, seconds.
    pub start: f64,
    /// Frames per second.
    pub fps: f64,
    /// Patches that emit light.
    pub emitters: usize,
    /// Punctual lights (KHR_lights_punctual).
    pub lights: usize,
    /// Punctual lights whose pose changes over the frames.
    pub moving_lights: usize,
    /// Centre of the bounding sphere, scene units.
    pub center: [f64; 3],
    /// Radius of the bounding sphere, scene units.
    pub radius: f64,
    /// Total area of the patches at frame 0, scene units squared.
    pub area: f64,
    /// The materials, by the names relighting takes.
    pub materials: Vec<Named>,
    /// The punctual lights, by the names relighting takes.
    pub light_names: Vec<Named>,
    /// The file's animations (`--animation` / `animation=` take a name or index).
    pub animations: Vec<Named>,
    /// The camera node the previews are seen from, if the scene has one.
    pub camera: Option<String>,
    /// Loader warnings.
    pub warnings: Vec<String>,
}

impl Scene {
    /// A node as messages name it: `node 4 ("Door")`, or `node 4` without a name.
    #[must_use]
    pub fn node_label(&self, node: u32) -> String {
        match self.node_names.get(node as usize).and_then(Option::as_ref) {
            Some(name) => format!("node {node} ({name:?})"),
            None => format!("node {node}"),
        }
    }

    /// The summary of this scene.
    #[must_use]
    pub fn summary(&self) -> Summary {
        let moving_triangles = self.objects.iter().map(|o| o.mesh.triangles.len()).sum();
        let rigid_objects = self.objects.iter().filter(|o| o.is_rigid()).count();
        Summary {
            triangles: self.source_triangles,
            traced_triangles: self.statics.triangles.len() + moving_triangles,
            patches: self.patches.len(),
            static_triangles: self.statics.triangles.len(),
            moving_objects: self.objects.len(),
            rigid_objects,
            deforming_objects: self.objects.len() - rigid_objects,
            moving_triangles,
            frames: self.frames.count,
            start: self.frames.start,
            fps: self.frames.fps,
            emitters: self
                .patches
                .iter()
                .filter(|p| self.materials[p.material as usize].is_emitter())
                .count(),
            lights: self.lights.len(),
            moving_lights: self.lights.iter().filter(|l| l.moves()).count(),
            center: self.normalisation.center.to_array(),
            radius: self.normalisation.radius,
            area: self.patches.iter().map(|p| p.area).sum(),
            materials: (self.materials.iter().enumerate())
                .map(|(index, m)| Named {
                    index,
                    name: m.name.clone(),
                    notes: [(m.is_emitter(), "emits"), (m.double_sided, "double-sided")]
                        .into_iter()
                        .filter_map(|(is, note)| is.then_some(note))
                        .collect(),
                })
                .collect(),
            light_names: (self.lights.iter().enumerate())
                .map(|(index, l)| Named {
                    index,
                    name: l.name.clone(),
                    notes: [
                        Some(match l.kind {
                            LightKind::Point => "point",
                            LightKind::Spot { .. } => "spot",
                            LightKind::Directional => "directional",
                        }),
                        l.moves().then_some("moving"),
                    ]
                    .into_iter()
                    .flatten()
                    .collect(),
                })
                .collect(),
            animations: (self.animations.iter().enumerate())
                .map(|(index, (name, played))| Named {
                    index,
                    name: name.clone(),
                    notes: if *played { vec!["played"] } else { Vec::new() },
                })
                .collect(),
            camera: self
                .camera
                .as_ref()
                .map(|c| c.name.clone().unwrap_or_else(|| "unnamed".into())),
            warnings: self.warnings.clone(),
        }
    }

    /// Every traced triangle of the scene posed at `frame`, in normalised space, with its faces:
    /// the static triangles first, then each object's. This is the scene "traced alone" at one
    /// frame, the reference the multiframe list is checked against.
    #[must_use]
    pub fn triangles_at(&self, frame: usize) -> Vec<([Vec3; 3], Faces)> {
        let mut out = Vec::new();
        let mut push = |positions: &[Vec3], mesh: &TriangleMesh| {
            for (t, faces) in mesh.triangles.iter().zip(&mesh.faces) {
                let corners = t.map(|i| positions[i as usize]);
                out.push((corners, *faces));
            }
        };
        push(&self.statics.positions, &self.statics);
        for object in &self.objects {
            push(&object.positions_at(frame), &object.mesh);
        }
        out
    }
}

/// `x` to 6 significant digits without trailing zeros, and 0 when it is below 1e-9 of `scale`
/// (a centre at −2.2e-16 is rounding, not a place).
fn shown(x: f64, scale: f64) -> String {
    if x.abs() <= 1e-9 * scale.abs() || x == 0.0 || !x.is_finite() {
        return if x.is_finite() {
            "0".into()
        } else {
            x.to_string()
        };
    }
    let decimals = (5 - x.abs().log10().floor() as i32).max(0) as usize;
    let text = format!("{x:.decimals$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        text
    }
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "triangles       {} ({} traced after subdivision)",
            self.triangles, self.traced_triangles
        )?;
        writeln!(f, "patches         {}", self.patches)?;
        writeln!(f, "static          {} triangles", self.static_triangles)?;
        writeln!(
            f,
            "moving          {} objects ({} rigid, {} deforming), {} triangles",
            self.moving_objects, self.rigid_objects, self.deforming_objects, self.moving_triangles
        )?;
        writeln!(
            f,
            "frames          {} at {} fps from t = {} s",
            self.frames,
            shown(self.fps, self.fps),
            shown(self.start, 1.0)
        )?;
        writeln!(f, "emitters        {} patches", self.emitters)?;
        writeln!(
            f,
            "lights          {} punctual ({} moving)",
            self.lights, self.moving_lights
        )?;
        let length = |x: f64| shown(x, self.radius);
        writeln!(
            f,
            "bounds          centre [{}, {}, {}], radius {}",
            length(self.center[0]),
            length(self.center[1]),
            length(self.center[2]),
            length(self.radius)
        )?;
        writeln!(f, "area            {}", shown(self.area, self.area))?;
        let list = |named: &[Named]| {
            let items: Vec<String> = named.iter().map(Named::to_string).collect();
            if items.is_empty() {
                "none".to_string()
            } else {
                items.join(", ")
            }
        };
        writeln!(f, "materials       {}", list(&self.materials))?;
        writeln!(f, "light names     {}", list(&self.light_names))?;
        writeln!(f, "animations      {}", list(&self.animations))?;
        match &self.camera {
            Some(name) => writeln!(f, "camera          {name:?} (the previews' viewpoint)")?,
            None => writeln!(
                f,
                "camera          none (the previews use an automatic one)"
            )?,
        }
        if self.warnings.is_empty() {
            writeln!(f, "warnings        none")
        } else {
            writeln!(f, "warnings        {}", self.warnings.len())?;
            self.warnings
                .iter()
                .try_for_each(|w| writeln!(f, "  - {w}"))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::shown;

    #[test]
    fn the_summary_shows_lengths_to_six_digits_and_rounding_as_zero() {
        assert_eq!(shown(-2.220446049250313e-16, 1.0), "0");
        assert_eq!(shown(0.8660254037844386, 0.87), "0.866025");
        assert_eq!(shown(6.685057788447885, 6.7), "6.68506");
        assert_eq!(shown(1.5, 6.7), "1.5");
        assert_eq!(shown(242.67199400413085, 242.7), "242.672");
        assert_eq!(shown(1234567.0, 1e6), "1234567");
        assert_eq!(shown(-0.5, 1.0), "-0.5");
        assert_eq!(shown(3e-12, 1e-11), "0.000000000003");
    }
}
