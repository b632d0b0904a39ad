//! Mesh primitives to indexed triangles, with their morph targets and skinning attributes.

use glam::{DAffine3, DMat4, DVec3};
use gltf::Document;
use gltf::mesh::{Mode, Semantic};

use super::{LoadError, accessor};

/// The geometry of one mesh as instanced by one node: every triangle primitive's vertices
/// concatenated, in the mesh's own space.
pub struct MeshGeometry {
    /// Vertex positions in mesh space.
    pub positions: Vec<DVec3>,
    /// Triangles (indices into `positions`).
    pub triangles: Vec<[u32; 3]>,
    /// Per triangle: (primitive index, triangle index within the primitive, material index).
    pub origin: Vec<(u32, u32, u32)>,
    /// Morph target position deltas, `targets[t][v]` (zero for primitives without them).
    pub targets: Vec<Vec<DVec3>>,
    /// Per vertex (joint, weight) influences when the node is skinned, weights summing to 1.
    pub influences: Option<Vec<Vec<(u32, f64)>>>,
}

/// Number of morph targets of a mesh (its first primitive's count; glTF requires all
/// primitives of a mesh to have the same).
#[must_use]
pub fn morph_target_count(mesh: &gltf::Mesh<'_>) -> usize {
    mesh.primitives()
        .next()
        .map_or(0, |p| p.morph_targets().len())
}

/// Reads a mesh's triangle primitives. `default_material` is the index given to primitives
/// without a material; `joints` is the number of joints of the node's skin, if skinned.
pub fn read(
    document: &Document,
    buffers: &[Vec<u8>],
    mesh: &gltf::Mesh<'_>,
    default_material: u32,
    joints: Option<usize>,
    warnings: &mut Vec<String>,
) -> Result<MeshGeometry, LoadError> {
    let target_count = morph_target_count(mesh);
    let mut g = MeshGeometry {
        positions: Vec::new(),
        triangles: Vec::new(),
        origin: Vec::new(),
        targets: vec![Vec::new(); target_count],
        influences: joints.map(|_| Vec::new()),
    };
    for primitive in mesh.primitives() {
        let what = || format!("mesh {} primitive {}", mesh.index(), primitive.index());
        let mode = primitive.mode();
        if !matches!(
            mode,
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
        ) {
            warnings.push(format!(
                "{}: {mode:?} primitives carry no area, skipped",
                what()
            ));
            continue;
        }
        let Some(position) = primitive.get(&Semantic::Positions) else {
            warnings.push(format!("{}: no POSITION attribute, skipped", what()));
            continue;
        };
        let positions = accessor::read_exact(document, buffers, position.index(), 3, "POSITION")?;
        let vertex_count = positions.len();
        let indices = match primitive.indices() {
            Some(a) => accessor::read_indices(document, buffers, a.index())?,
            None => (0..vertex_count as u32).collect(),
        };
        if let Some(&bad) = indices.iter().find(|&&i| i as usize >= vertex_count) {
            return Err(LoadError::malformed(
                what(),
                format!("index {bad} is out of range ({vertex_count} vertices)"),
            ));
        }
        let (triangles, leftover) = unroll(mode, &indices);
        if leftover > 0 {
            warnings.push(format!(
                "{}: {leftover} trailing indices do not make a triangle, ignored",
                what()
            ));
        }
        let base = g.positions.len() as u32;
        g.positions
            .extend((0..vertex_count).map(|v| DVec3::from_slice(positions.get(v))));
        let material = primitive
            .material()
            .index()
            .map_or(default_material, |m| m as u32);
        for (k, t) in triangles.into_iter().enumerate() {
            g.triangles.push(t.map(|i| base + i));
            g.origin
                .push((primitive.index() as u32, k as u32, material));
        }
        let targets: Vec<_> = primitive.morph_targets().collect();
        if targets.len() != target_count {
            return Err(LoadError::malformed(
                what(),
                format!(
                    "has {} morph targets where the mesh's first primitive has {target_count}",
                    targets.len()
                ),
            ));
        }
        for (t, target) in targets.iter().enumerate() {
            match target.positions() {
                Some(a) => {
                    let deltas =
                        accessor::read_exact(document, buffers, a.index(), 3, "morph POSITION")?;
                    if deltas.len() != vertex_count {
                        return Err(LoadError::malformed(
                            what(),
                            format!(
                                "morph target {t} has {} positions for {vertex_count} vertices",
                                deltas.len()
                            ),
                        ));
                    }
                    g.targets[t]
                        .extend((0..vertex_count).map(|v| DVec3::from_slice(deltas.get(v))));
                }
                None => g.targets[t].extend(std::iter::repeat_n(DVec3::ZERO, vertex_count)),
            }
        }
        if let (Some(joints), Some(influences)) = (joints, &mut g.influences) {
            influences.extend(read_influences(
                document,
                buffers,
                &primitive,
                vertex_count,
                joints,
                &what,
            )?);
        }
    }
    Ok(g)
}

/// Triangles of a primitive's index list (glTF 2.0 §3.7.2.1), and the count of trailing
/// indices that make no triangle.
fn unroll(mode: Mode, indices: &[u32]) -> (Vec<[u32; 3]>, usize) {
    let n = indices.len();
    match mode {
        Mode::Triangles => (
            indices
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
            n % 3,
        ),
        // p_i = {v_i, v_(i+(1+i%2)), v_(i+(2−i%2))}: odd triangles swap to keep the winding.
        Mode::TriangleStrip => (
            (0..n.saturating_sub(2))
                .map(|i| {
                    let odd = i % 2;
                    [indices[i], indices[i + 1 + odd], indices[i + 2 - odd]]
                })
                .collect(),
            0,
        ),
        // p_i = {v_(i+1), v_(i+2), v_0}.
        Mode::TriangleFan => (
            (0..n.saturating_sub(2))
                .map(|i| [indices[i + 1], indices[i + 2], indices[0]])
                .collect(),
            0,
        ),
        _ => (Vec::new(), n),
    }
}

/// Reads JOINTS_n / WEIGHTS_n pairs into per-vertex influences with weights normalised to 1.
fn read_influences(
    document: &Document,
    buffers: &[Vec<u8>],
    primitive: &gltf::Primitive<'_>,
    vertex_count: usize,
    joints: usize,
    what: &dyn Fn() -> String,
) -> Result<Vec<Vec<(u32, f64)>>, LoadError> {
    let mut influences = vec![Vec::new(); vertex_count];
    for set in 0.. {
        let (Some(j), Some(w)) = (
            primitive.get(&Semantic::Joints(set)),
            primitive.get(&Semantic::Weights(set)),
        ) else {
            break;
        };
        let j = accessor::read_exact(document, buffers, j.index(), 4, "JOINTS")?;
        let w = accessor::read_exact(document, buffers, w.index(), 4, "WEIGHTS")?;
        if j.len() != vertex_count || w.len() != vertex_count {
            return Err(LoadError::malformed(
                what(),
                format!("JOINTS_{set}/WEIGHTS_{set} do not have one element per vertex"),
            ));
        }
        for (v, list) in influences.iter_mut().enumerate() {
            for (&joint, &weight) in j.get(v).iter().zip(w.get(v)) {
                if weight == 0.0 {
                    continue;
                }
                if weight < 0.0 || joint < 0.0 || joint as usize >= joints {
                    return Err(LoadError::malformed(
                        what(),
                        format!(
                            "vertex {v} has joint {joint} with weight {weight} (skin has {joints} joints)"
                        ),
                    ));
                }
                list.push((joint as u32, weight));
            }
        }
    }
    for (v, list) in influences.iter_mut().enumerate() {
        let sum: f64 = list.iter().map(|&(_, w)| w).sum();
        if sum <= 0.0 {
            return Err(LoadError::malformed(
                what(),
                format!("vertex {v} of a skinned mesh has no joint weight"),
            ));
        }
        list.iter_mut().for_each(|(_, w)| *w /= sum);
    }
    Ok(influences)
}

/// Reads a skin's inverse bind matrices (identity when absent), one per joint.
pub fn inverse_bind_matrices(
    document: &Document,
    buffers: &[Vec<u8>],
    skin: &gltf::Skin<'_>,
) -> Result<Vec<DAffine3>, LoadError> {
    let joints = skin.joints().len();
    let Some(a) = skin.inverse_bind_matrices() else {
        return Ok(vec![DAffine3::IDENTITY; joints]);
    };
    let m = accessor::read_exact(document, buffers, a.index(), 16, "inverseBindMatrices")?;
    if m.len() < joints {
        return Err(LoadError::malformed(
            format!("skin {}", skin.index()),
            format!("{} inverse bind matrices for {joints} joints", m.len()),
        ));
    }
    Ok((0..joints)
        .map(|j| DAffine3::from_mat4(DMat4::from_cols_slice(m.get(j))))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strips_and_fans_unroll_with_consistent_winding() {
        let (t, rest) = unroll(Mode::TriangleStrip, &[0, 1, 2, 3, 4]);
        assert_eq!(t, vec![[0, 1, 2], [1, 3, 2], [2, 3, 4]]);
        assert_eq!(rest, 0);
        let (t, _) = unroll(Mode::TriangleFan, &[0, 1, 2, 3]);
        assert_eq!(t, vec![[1, 2, 0], [2, 3, 0]]);
        let (t, rest) = unroll(Mode::Triangles, &[0, 1, 2, 3, 4]);
        assert_eq!(t, vec![[0, 1, 2]]);
        assert_eq!(rest, 2);
        assert!(unroll(Mode::TriangleStrip, &[0, 1]).0.is_empty());
    }
}
