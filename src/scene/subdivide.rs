//! Patch subdivision: split triangles until every edge is at most a given length.
//!
//! Longest-edge bisection: a triangle whose longest edge is too long is cut at that edge's
//! midpoint, and both halves are examined again. An edge is cut if and only if it is longer than
//! the limit, always at its midpoint, so the two triangles that share an edge cut it into the
//! same pieces: the result has no T-junctions and shared vertices stay shared (watertight). A
//! needle of length L becomes O((L / limit)^1.58) pieces (each halving triples them), fewer
//! than the O((L / limit)²) of a uniform grid.

use std::collections::HashMap;

use glam::DVec3;

use super::midpoint;

/// The result of subdividing an indexed triangle list.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Subdivision {
    /// New vertices, each the midpoint of two earlier ones (original vertices first, then these
    /// in order: vertex `n + i` is `midpoints[i]`).
    pub midpoints: Vec<[u32; 2]>,
    /// The resulting triangles, same winding as their source.
    pub triangles: Vec<[u32; 3]>,
    /// For each resulting triangle, the index of the source triangle it came from.
    pub sources: Vec<u32>,
    /// For each resulting triangle, where its corners lie on its source triangle
    /// ([`super::Origin::corners`]).
    pub corners: Vec<[[f32; 2]; 3]>,
}

/// Subdivision would create more triangles than allowed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("subdivision would create more than {limit} triangles")]
pub struct TooManyTriangles {
    /// The limit that was reached.
    pub limit: usize,
}

/// Subdivides `triangles` (indices into `positions`) until every edge is at most `max_edge`
/// long. `positions` decide the lengths; the caller places the new vertices in any affine image
/// of them with [`apply_midpoints`]. Fails once the output would exceed `limit` triangles.
pub fn subdivide(
    positions: &[DVec3],
    triangles: &[[u32; 3]],
    max_edge: f64,
    limit: usize,
) -> Result<Subdivision, TooManyTriangles> {
    debug_assert!(max_edge > 0.0 && max_edge.is_finite());
    let max_sq = max_edge * max_edge;
    let mut points: Vec<DVec3> = positions.to_vec();
    let mut out = Subdivision::default();
    let mut cut: HashMap<(u32, u32), u32> = HashMap::new();
    // Each triangle with its corners' coordinates on its source triangle (halves of halves:
    // exact in binary).
    let mut stack: Vec<([u32; 3], [[f64; 2]; 3])> = Vec::new();
    for (source, &triangle) in triangles.iter().enumerate() {
        stack.push((triangle, super::Origin::WHOLE));
        while let Some((t, at)) = stack.pop() {
            // Edge k runs from t[k] to t[(k + 1) % 3]; the first longest one wins ties.
            let lengths = [0, 1, 2].map(|k| {
                (points[t[k] as usize] - points[t[(k + 1) % 3] as usize]).length_squared()
            });
            let k = (0..3).fold(
                0,
                |best, k| if lengths[k] > lengths[best] { k } else { best },
            );
            if lengths[k] <= max_sq {
                if out.triangles.len() == limit {
                    return Err(TooManyTriangles { limit });
                }
                out.triangles.push(t);
                out.sources.push(source as u32);
                out.corners.push(at.map(|c| c.map(|x| x as f32)));
                continue;
            }
            let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
            let key = (a.min(b), a.max(b));
            let m = *cut.entry(key).or_insert_with(|| {
                out.midpoints.push([key.0, key.1]);
                points.push(midpoint(points[key.0 as usize], points[key.1 as usize]));
                (points.len() - 1) as u32
            });
            let (ua, ub, uc) = (at[k], at[(k + 1) % 3], at[(k + 2) % 3]);
            let um = [0.5 * (ua[0] + ub[0]), 0.5 * (ua[1] + ub[1])];
            // Push the second half first so the first half comes out first (stable order).
            stack.push(([m, b, c], [um, ub, uc]));
            stack.push(([a, m, c], [ua, um, uc]));
        }
    }
    Ok(out)
}

/// Appends the subdivision's new vertices to `positions`, placed as midpoints in that space.
pub fn apply_midpoints(positions: &mut Vec<DVec3>, midpoints: &[[u32; 2]]) {
    for &[a, b] in midpoints {
        let m = midpoint(positions[a as usize], positions[b as usize]);
        positions.push(m);
    }
}

/// Area of a triangle.
#[must_use]
pub fn triangle_area(a: DVec3, b: DVec3, c: DVec3) -> f64 {
    0.5 * (b - a).cross(c - a).length()
}

/// Unit normal of a triangle (counter-clockwise corners; zero if degenerate) and its area.
#[must_use]
pub fn normal_and_area([a, b, c]: [DVec3; 3]) -> (DVec3, f64) {
    let cross = (b - a).cross(c - a);
    (cross.normalize_or_zero(), 0.5 * cross.length())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn area_of(positions: &[DVec3], t: [u32; 3]) -> f64 {
        triangle_area(
            positions[t[0] as usize],
            positions[t[1] as usize],
            positions[t[2] as usize],
        )
    }

    #[test]
    fn small_triangles_are_left_alone() {
        let p = [DVec3::ZERO, DVec3::X, DVec3::Y];
        let s = subdivide(&p, &[[0, 1, 2]], 2.0, 100).unwrap();
        assert_eq!(s.triangles, vec![[0, 1, 2]]);
        assert!(s.midpoints.is_empty());
    }

    #[test]
    fn a_sliver_grows_linearly_not_quadratically() {
        let pieces = |length: f64| {
            let p = [
                DVec3::ZERO,
                DVec3::new(length, 0.0, 0.0),
                DVec3::new(length / 2.0, 0.01, 0.0),
            ];
            subdivide(&p, &[[0, 1, 2]], 1.0, 10_000_000)
                .unwrap()
                .triangles
                .len()
        };
        // Sixteen times longer: a uniform grid makes 256 times the pieces; bisection makes
        // 3^4 = 81 times (every halving of a needle triples its pieces: O(L^1.58)).
        let (short, long) = (pieces(100.0), pieces(1600.0));
        assert!(long <= 100 * short, "{short} then {long} pieces");
    }

    #[test]
    fn the_limit_is_enforced() {
        let p = [DVec3::ZERO, DVec3::X * 1e6, DVec3::Y * 1e6];
        assert_eq!(
            subdivide(&p, &[[0, 1, 2]], 1.0, 1000),
            Err(TooManyTriangles { limit: 1000 })
        );
    }

    #[test]
    fn neighbours_share_their_cut_edges() {
        // Two triangles sharing the diagonal of a 4 × 1 rectangle: no T-junctions means every
        // interior edge is used by exactly two triangles and boundary edges by one.
        let p = [
            DVec3::ZERO,
            DVec3::new(4.0, 0.0, 0.0),
            DVec3::new(4.0, 1.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        ];
        let s = subdivide(&p, &[[0, 1, 2], [0, 2, 3]], 0.7, 10_000).unwrap();
        let mut edges: HashMap<(u32, u32), usize> = HashMap::new();
        for t in &s.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *edges.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        let mut points = p.to_vec();
        apply_midpoints(&mut points, &s.midpoints);
        for (&(a, b), &n) in &edges {
            let (pa, pb) = (points[a as usize], points[b as usize]);
            let on_boundary = (pa.x == pb.x && (pa.x == 0.0 || pa.x == 4.0))
                || (pa.y == pb.y && (pa.y == 0.0 || pa.y == 1.0));
            assert_eq!(n, if on_boundary { 1 } else { 2 }, "edge {pa} {pb}");
        }
    }

    proptest! {
        #[test]
        fn subdivision_keeps_area_provenance_and_edge_bound(
            coords in proptest::collection::vec(-10.0f64..10.0, 9),
            max_edge in 0.3f64..5.0,
        ) {
            let p: Vec<DVec3> = coords.chunks(3).map(|c| DVec3::new(c[0], c[1], c[2])).collect();
            let s = subdivide(&p, &[[0, 1, 2]], max_edge, 1_000_000).unwrap();
            let mut points = p.clone();
            apply_midpoints(&mut points, &s.midpoints);
            let source_area = area_of(&p, [0, 1, 2]);
            let total: f64 = s.triangles.iter().map(|&t| area_of(&points, t)).sum();
            prop_assert!((total - source_area).abs() <= 1e-9 * source_area.max(1e-300) + 1e-12,
                "area {} != {}", total, source_area);
            prop_assert!(s.sources.iter().all(|&src| src == 0));
            for t in &s.triangles {
                for k in 0..3 {
                    let len = (points[t[k] as usize] - points[t[(k + 1) % 3] as usize]).length();
                    prop_assert!(len <= max_edge * (1.0 + 1e-12));
                }
                // Winding is kept: normals point the same way as the source's.
                let n0 = (p[1] - p[0]).cross(p[2] - p[0]);
                let n = (points[t[1] as usize] - points[t[0] as usize])
                    .cross(points[t[2] as usize] - points[t[0] as usize]);
                prop_assert!(n.dot(n0) >= 0.0);
            }
        }
    }
}
