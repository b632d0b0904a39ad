//! The scene at one frame as drawable geometry: one triangle per face of a traced triangle
//! (a patch merged from several faces draws them all), facing the patch's side,
//! with per-vertex radiance averaged (area-weighted) over the patches around each vertex.
//!
//! A vertex is shared only by patches of the same source node, on the same side, whose planes
//! meet at less than [`CREASE_DEGREES`]: where a floor meets a wall the vertex is split, so the
//! wall's light does not bleed onto the floor (the "smoothing groups" of modelling tools).

use std::collections::HashMap;

use glam::{DVec3, Vec3};

use crate::scene::{Scene, TriangleMesh};

/// Patches meeting at a larger angle than this get their own copy of a shared vertex.
pub const CREASE_DEGREES: f64 = 30.0;

/// The drawable triangles of one source node at one frame.
#[derive(Clone, Debug, Default)]
pub struct NodeMesh {
    /// The source node (glTF node index) the triangles come from.
    pub node: u32,
    /// Vertex positions, normalised space.
    pub positions: Vec<DVec3>,
    /// Unit vertex normals: the area-weighted mean of the faces sharing the vertex.
    pub normals: Vec<Vec3>,
    /// Area-weighted mean radiance of the patches sharing each vertex.
    pub radiance: Vec<[f64; 3]>,
    /// Vertex indices, counter-clockwise seen from the patch's side.
    pub triangles: Vec<[u32; 3]>,
    /// The patch each triangle draws.
    pub patches: Vec<u32>,
}

/// One face to place: which mesh vertices, which patch, and its geometry at the frame.
struct Face {
    corners: [u32; 3],
    back: bool,
    patch: u32,
    normal: DVec3,
    area: f64,
}

/// The scene posed at `frame`, grouped by source node (in node order), with each vertex's
/// radiance averaged from `radiance` (per patch) over the faces that share it.
#[must_use]
pub fn frame_geometry(scene: &Scene, frame: usize, radiance: &[[f64; 3]]) -> Vec<NodeMesh> {
    let mut by_node: std::collections::BTreeMap<u32, NodeMesh> = Default::default();
    let mut add = |positions: &[DVec3], mesh: &TriangleMesh| {
        let mut faces: HashMap<u32, Vec<Face>> = HashMap::new();
        for (t, f) in mesh.triangles.iter().zip(&mesh.faces) {
            let [a, b, c] = t.map(|i| positions[i as usize]);
            let cross = (b - a).cross(c - a);
            let area = 0.5 * cross.length();
            let normal = cross.normalize_or_zero();
            let node = scene.patches[f.front as usize].source.node;
            let list = faces.entry(node).or_default();
            list.push(Face {
                corners: *t,
                back: false,
                patch: f.front,
                normal,
                area,
            });
            if let Some(back) = f.back {
                list.push(Face {
                    corners: [t[0], t[2], t[1]],
                    back: true,
                    patch: back,
                    normal: -normal,
                    area,
                });
            }
        }
        let mut nodes: Vec<(u32, Vec<Face>)> = faces.into_iter().collect();
        nodes.sort_unstable_by_key(|(n, _)| *n);
        for (node, faces) in nodes {
            let out = by_node.entry(node).or_insert_with(|| NodeMesh {
                node,
                ..NodeMesh::default()
            });
            place(out, positions, &faces, radiance);
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

/// Sums towards one output vertex.
#[derive(Default)]
struct Accumulator {
    weight: f64,
    radiance: [f64; 3],
    normal: DVec3,
    /// Unweighted sums, for a vertex whose faces all have zero area at this frame.
    count: f64,
    plain: [f64; 3],
}

/// Appends `faces` (all of one node) to `out`, splitting vertices at creases.
fn place(out: &mut NodeMesh, positions: &[DVec3], faces: &[Face], radiance: &[[f64; 3]]) {
    let crease = CREASE_DEGREES.to_radians().cos();
    // Per (mesh vertex, side): the output vertices made for it, each with the normal of the
    // face that made it.
    let mut made: HashMap<(u32, bool), Vec<(DVec3, u32)>> = HashMap::new();
    let first = out.positions.len();
    let mut sums: Vec<Accumulator> = Vec::new();
    for face in faces {
        let l = radiance[face.patch as usize];
        let mut tri = [0u32; 3];
        for (k, &v) in face.corners.iter().enumerate() {
            let copies = made.entry((v, face.back)).or_default();
            // A face without a normal (zero area at this frame) joins any copy.
            let found = copies
                .iter()
                .find(|(n, _)| face.normal == DVec3::ZERO || n.dot(face.normal) >= crease)
                .map(|&(_, i)| i);
            let index = found.unwrap_or_else(|| {
                let i = (first + sums.len()) as u32;
                copies.push((face.normal, i));
                out.positions.push(positions[v as usize]);
                sums.push(Accumulator::default());
                i
            });
            let s = &mut sums[index as usize - first];
            s.weight += face.area;
            s.normal += face.normal * face.area;
            s.count += 1.0;
            for ((sum, plain), &c) in s.radiance.iter_mut().zip(&mut s.plain).zip(&l) {
                *sum += face.area * c;
                *plain += c;
            }
            tri[k] = index;
        }
        out.triangles.push(tri);
        out.patches.push(face.patch);
    }
    for s in sums {
        out.radiance.push(if s.weight > 0.0 {
            s.radiance.map(|x| x / s.weight)
        } else {
            s.plain.map(|x| x / s.count)
        });
        out.normals.push(unit_normal(s.normal));
    }
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
