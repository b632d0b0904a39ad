//! The scene at one frame as drawable geometry: one triangle per face of a traced triangle
//! (a patch merged from several faces draws them all), facing the patch's side, with the
//! radiance evaluated at each vertex ([`light_vertices`]: the direct light from the vertex
//! itself, the rest gathered from the solved patches, [`crate::direct::points`]), never the
//! mean of the patches around it.
//!
//! A vertex is shared only by faces of the same source node, on the same side, of the same
//! material, whose planes meet at less than [`CREASE_DEGREES`]: where a floor meets a wall the
//! vertex is split, so each side of the crease carries its own light (the "smoothing groups"
//! of modelling tools), and each copy is evaluated on its own faces.

use std::collections::HashMap;

use glam::{DVec3, Vec3};

use crate::bake::Bake;
pub use crate::direct::points::Corner;
use crate::direct::points::{Gather, Lighting, PointRadiance, Points, Probe, Solved};
use crate::scene::{Scene, TriangleMesh};
use crate::solve::FrameSolution;

/// Patches meeting at a larger angle than this get their own copy of a shared vertex.
pub const CREASE_DEGREES: f64 = 30.0;

/// The drawable triangles of one source node at one frame.
#[derive(Clone, Debug, Default)]
pub struct NodeMesh {
    /// The source node (glTF node index) the triangles come from.
    pub node: u32,
    /// Vertex positions, normalised space.
    pub positions: Vec<DVec3>,
    /// Unit vertex normals: the mean of the faces sharing the vertex, weighed by their angles
    /// at it.
    pub normals: Vec<Vec3>,
    /// Radiance at each vertex ([`light_vertices`]; zero until then).
    pub radiance: Vec<[f64; 3]>,
    /// Its standard error.
    pub stderr: Vec<[f64; 3]>,
    /// The irradiance each vertex's gather read from the solution
    /// ([`crate::direct::points::PointRadiance::gathered`]; empty until [`light_vertices`]).
    pub gathered: Vec<[f64; 3]>,
    /// The face corners each vertex stands for (where its light is evaluated): vertex `v`'s are
    /// `corners[corner_offsets[v]..corner_offsets[v + 1]]`.
    pub corners: Vec<Corner>,
    /// Where each vertex's corners start in `corners` (vertices + 1 values).
    pub corner_offsets: Vec<u32>,
    /// Vertex indices, counter-clockwise seen from the patch's side.
    pub triangles: Vec<[u32; 3]>,
    /// The patch each triangle draws.
    pub patches: Vec<u32>,
    /// The face each triangle draws: its drawn triangle (global index in the scene drawn) and
    /// whether it is the triangle's back face.
    pub faces: Vec<(u32, bool)>,
}

/// One face to place: which mesh vertices, which patch, and its geometry at the frame.
struct Face {
    /// The triangle's global index.
    triangle: u32,
    corners: [u32; 3],
    back: bool,
    patch: u32,
    material: u32,
    normal: DVec3,
    /// The face's angles at its corners (in `corners`' order).
    angles: [f64; 3],
}

/// The scene posed at `frame`, grouped by source node (in node order), its vertices' radiance
/// zero until [`light_vertices`].
#[must_use]
pub fn frame_geometry(scene: &Scene, frame: usize) -> Vec<NodeMesh> {
    let mut by_node: std::collections::BTreeMap<u32, NodeMesh> = Default::default();
    let mut first = 0u32;
    let mut add = |positions: &[DVec3], mesh: &TriangleMesh| {
        let mut faces: HashMap<u32, Vec<Face>> = HashMap::new();
        for (k, (t, f)) in mesh.triangles.iter().zip(&mesh.faces).enumerate() {
            let [a, b, c] = t.map(|i| positions[i as usize]);
            let normal = (b - a).cross(c - a).normalize_or_zero();
            let angle = |p: DVec3, q: DVec3, r: DVec3| (q - p).angle_between(r - p);
            let angles = [angle(a, b, c), angle(b, c, a), angle(c, a, b)]
                .map(|x| if x.is_finite() { x } else { 0.0 });
            let patch = &scene.patches[f.front as usize];
            let list = faces.entry(patch.source.node).or_default();
            let triangle = first + k as u32;
            list.push(Face {
                triangle,
                corners: *t,
                back: false,
                patch: f.front,
                material: patch.material,
                normal,
                angles,
            });
            if let Some(back) = f.back {
                list.push(Face {
                    triangle,
                    corners: [t[0], t[2], t[1]],
                    back: true,
                    patch: back,
                    material: scene.patches[back as usize].material,
                    normal: -normal,
                    angles: [angles[0], angles[2], angles[1]],
                });
            }
        }
        first += mesh.triangles.len() as u32;
        let mut nodes: Vec<(u32, Vec<Face>)> = faces.into_iter().collect();
        nodes.sort_unstable_by_key(|(n, _)| *n);
        for (node, faces) in nodes {
            let out = by_node.entry(node).or_insert_with(|| NodeMesh {
                node,
                ..NodeMesh::default()
            });
            place(out, positions, &faces);
        }
    };
    let statics: Vec<DVec3> = scene
        .statics
        .positions
        .iter()
        .map(|p| p.as_dvec3())
        .collect();
    add(&statics, &scene.statics);
    for object in &scene.objects {
        let posed: Vec<DVec3> = object
            .positions_at(frame)
            .iter()
            .map(|p| p.as_dvec3())
            .collect();
        add(&posed, &object.mesh);
    }
    by_node.into_values().collect()
}

/// Appends `faces` (all of one node) to `out`, splitting vertices at creases and between
/// materials.
fn place(out: &mut NodeMesh, positions: &[DVec3], faces: &[Face]) {
    let crease = CREASE_DEGREES.to_radians().cos();
    // Per (mesh vertex, side, material): the output vertices made for it, each with the normal
    // of the face that made it.
    let mut made: HashMap<(u32, bool, u32), Vec<(DVec3, u32)>> = HashMap::new();
    let first = out.positions.len();
    // Per output vertex: the sum of its faces' normals weighed by their angles, and its corners.
    let mut sums: Vec<(DVec3, Vec<Corner>)> = Vec::new();
    for face in faces {
        let mut tri = [0u32; 3];
        for (k, &v) in face.corners.iter().enumerate() {
            let copies = made.entry((v, face.back, face.material)).or_default();
            // A face without a normal (zero area at this frame) joins any copy.
            let found = copies
                .iter()
                .find(|(n, _)| face.normal == DVec3::ZERO || n.dot(face.normal) >= crease)
                .map(|&(_, i)| i);
            let index = found.unwrap_or_else(|| {
                let i = (first + sums.len()) as u32;
                copies.push((face.normal, i));
                out.positions.push(positions[v as usize]);
                sums.push((DVec3::ZERO, Vec::new()));
                i
            });
            let (normal, corners) = &mut sums[index as usize - first];
            *normal += face.normal * face.angles[k];
            // The triangle's own corner (a back face lists its corners 0, 2, 1).
            let corner = if face.back { [0, 2, 1][k] } else { k as u8 };
            corners.push(Corner {
                triangle: face.triangle,
                back: face.back,
                corner,
                angle: face.angles[k],
            });
            tri[k] = index;
        }
        out.triangles.push(tri);
        out.patches.push(face.patch);
        out.faces.push((face.triangle, face.back));
    }
    if out.corner_offsets.is_empty() {
        out.corner_offsets.push(0);
    }
    for (normal, corners) in sums {
        out.normals.push(unit_normal(normal));
        out.corners.extend(corners);
        out.corner_offsets.push(out.corners.len() as u32);
        out.radiance.push([0.0; 3]);
        out.stderr.push([0.0; 3]);
    }
}

impl NodeMesh {
    /// The face corners vertex `v` stands for.
    #[must_use]
    pub fn corners_of(&self, v: usize) -> &[Corner] {
        &self.corners[self.corner_offsets[v] as usize..self.corner_offsets[v + 1] as usize]
    }
}

/// The points where the light at every vertex of `meshes` (of `bake`'s scene as shown) is
/// evaluated, in the meshes' order ([`Bake::points_at_corners`]).
#[must_use]
pub fn vertex_points(bake: &Bake, meshes: &[NodeMesh]) -> Points {
    bake.points_at_corners(
        (meshes.iter()).flat_map(|mesh| (0..mesh.positions.len()).map(|v| mesh.corners_of(v))),
    )
}

/// Evaluates the light at every vertex of `meshes` (frame `frame` of `bake`'s scene as shown,
/// [`frame_geometry`]) from `solution`, solved with `lighting`, sampled as `gather` says:
/// each vertex at its own faces' corners ([`Bake::radiance_at`]), into the meshes' `radiance`
/// and `stderr`.
pub fn light_vertices(
    bake: &Bake,
    frame: usize,
    meshes: &mut [NodeMesh],
    (solution, lighting): (&FrameSolution, Lighting<'_>),
    gather: Gather,
) {
    let points = vertex_points(bake, meshes);
    let values = light_points(bake, frame, &points, (solution, lighting), gather);
    let mut values = values.into_iter();
    for mesh in meshes {
        mesh.gathered.clear();
        for (l, e) in mesh.radiance.iter_mut().zip(&mut mesh.stderr) {
            let PointRadiance {
                radiance,
                stderr,
                gathered,
                ..
            } = values.next().unwrap_or_default();
            (*l, *e) = (radiance, stderr);
            mesh.gathered.push(gathered);
        }
    }
}

/// The light at `points` (of `bake`'s scene as traced, frame `frame`) from `solution`, solved
/// with `lighting`, sampled as `gather` says ([`Bake::radiance_at`]).
#[must_use]
pub fn light_points(
    bake: &Bake,
    frame: usize,
    points: &Points,
    (solution, lighting): (&FrameSolution, Lighting<'_>),
    gather: Gather,
) -> Vec<PointRadiance> {
    read_solution(
        bake,
        frame,
        (solution, lighting),
        gather.rays > 0,
        |solved| bake.radiance_at(frame, points, (solved, lighting), gather),
    )
}

/// The light probes at `positions` (normalised space) at frame `frame`, from `solution`, solved
/// with `lighting`, sampled as `gather` says ([`Bake::probes_at`]).
#[must_use]
pub fn light_probes(
    bake: &Bake,
    frame: usize,
    positions: &[DVec3],
    (solution, lighting): (&FrameSolution, Lighting<'_>),
    gather: Gather,
) -> Vec<Probe> {
    read_solution(
        bake,
        frame,
        (solution, lighting),
        gather.rays > 0,
        |solved| bake.probes_at(frame, positions, (solved, lighting), gather),
    )
}

/// Runs `f` with what a gather reads of `solution` (frame `frame`, solved with `lighting`):
/// its patches, and its pieces if the bake was split and a gather will read them (`gathers`).
fn read_solution<R>(
    bake: &Bake,
    frame: usize,
    (solution, lighting): (&FrameSolution, Lighting<'_>),
    gathers: bool,
    f: impl FnOnce(Solved<'_>) -> R,
) -> R {
    let has_pieces = |s: &FrameSolution, map: &crate::direct::points::PieceMap| {
        map.patch.len() == s.pieces.len() && s.pieces_stderr.len() == s.radiance.len()
    };
    // A split bake's solution without its pieces (read back from disk: they are not stored) is
    // solved again for them, with the lighting it was solved with; its patches keep their
    // answer. Not needed without gather rays: the direct light reads no solution.
    let again = (bake.piece_map())
        .filter(|map| gathers && !has_pieces(solution, map))
        .map(|_| {
            let params = crate::solve::SolveParams {
                sky: lighting.sky,
                ..crate::solve::SolveParams::default()
            };
            bake.solve_frame_lit(frame, lighting.materials, lighting.power, &params)
        });
    let read = again.as_ref().unwrap_or(solution);
    let pieces = (bake.piece_map())
        .filter(|map| has_pieces(read, map))
        .map(|map| (&read.pieces[..], &read.pieces_stderr[..], map));
    f(Solved {
        radiance: &solution.radiance,
        stderr: &solution.stderr,
        pieces,
    })
}

/// A unit normal in `f32` (glTF requires unit length), +Y for a vertex with no area around it.
fn unit_normal(n: DVec3) -> Vec3 {
    let n = n.normalize_or_zero().as_vec3();
    if n == Vec3::ZERO {
        Vec3::Y
    } else {
        n.normalize()
    }
}
