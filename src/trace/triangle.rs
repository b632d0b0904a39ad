//! The watertight line–triangle test (Woop, Benthin, Wald, "Watertight Ray/Triangle
//! Intersection", JCGT 2013), with a tie rule so that a line through a shared edge or vertex
//! hits exactly one of the triangles there.
//!
//! The line is sheared so that it runs along +z through the origin; each triangle is projected
//! onto that plane and tested with three 2D edge functions. Neighbouring triangles compute the
//! edge functions of a shared edge from the same two projected vertices, exactly (in f64), so
//! their values are exact negations of each other: no line slips between them. An edge function
//! exactly zero means the line passes through the edge; the hit then counts only
//! for the triangle that *owns* the edge under a top-left rule applied to the edge as traversed
//! counter-clockwise in projection. Across an edge where the surface continues, exactly one of
//! the two triangles owns it; at a silhouette edge (the line grazes a fold) both or neither do,
//! which keeps the number of crossings of a closed surface even.

use glam::Vec3;

/// The shear that maps a direction to +z: what every line of a bundle shares.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shear {
    kx: usize,
    ky: usize,
    kz: usize,
    sx: f32,
    sy: f32,
    sz: f32,
}

impl Shear {
    /// The shear for lines along `direction`.
    #[must_use]
    pub fn new(direction: Vec3) -> Self {
        let kz = direction.abs().max_position();
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        // Keep the winding: a negative dominant component mirrors the projection.
        if direction[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        Self {
            kx,
            ky,
            kz,
            sx: direction[kx] / direction[kz],
            sy: direction[ky] / direction[kz],
            sz: 1.0 / direction[kz],
        }
    }

    /// Where the line along this shear's direction through `p` meets the plane of the two
    /// minor axes, in their coordinates: lines of a bundle are points there, and a line
    /// crosses a triangle where its point is inside the triangle's image.
    #[must_use]
    #[inline]
    pub fn project(&self, p: Vec3) -> [f32; 2] {
        let (x, y, z) = (axis(&p, self.kx), axis(&p, self.ky), axis(&p, self.kz));
        [x - self.sx * z, y - self.sy * z]
    }

    /// [`Shear::project`] of the corners of eight triangles side by side
    /// (`corner[c][axis][lane]`): `[corner][x or y][lane]`, the same operations lane by lane.
    #[must_use]
    #[inline(always)]
    pub fn project_block(&self, corner: &[[[f32; 8]; 3]; 3]) -> [[[f32; 8]; 2]; 3] {
        corner.map(|c| {
            let (x, y, z) = (&c[self.kx], &c[self.ky], &c[self.kz]);
            [
                std::array::from_fn(|l| x[l] - self.sx * z[l]),
                std::array::from_fn(|l| y[l] - self.sy * z[l]),
            ]
        })
    }

    /// [`Shear::project_block`] in AVX: the same operations on the same numbers.
    ///
    /// # Safety
    /// The processor must have AVX.
    #[cfg(target_arch = "x86_64")]
    #[must_use]
    #[inline]
    #[target_feature(enable = "avx")]
    pub unsafe fn project_block_avx(&self, corner: &[[[f32; 8]; 3]; 3]) -> [[[f32; 8]; 2]; 3] {
        use std::arch::x86_64::{
            _mm256_loadu_ps, _mm256_mul_ps, _mm256_set1_ps, _mm256_storeu_ps, _mm256_sub_ps,
        };
        let mut out = [[[0.0; 8]; 2]; 3];
        // SAFETY: the eight-float loads and stores stay inside the arrays.
        unsafe {
            let (sx, sy) = (_mm256_set1_ps(self.sx), _mm256_set1_ps(self.sy));
            for (c, o) in corner.iter().zip(&mut out) {
                let z = _mm256_loadu_ps(c[self.kz].as_ptr());
                let x = _mm256_sub_ps(_mm256_loadu_ps(c[self.kx].as_ptr()), _mm256_mul_ps(sx, z));
                let y = _mm256_sub_ps(_mm256_loadu_ps(c[self.ky].as_ptr()), _mm256_mul_ps(sy, z));
                _mm256_storeu_ps(o[0].as_mut_ptr(), x);
                _mm256_storeu_ps(o[1].as_mut_ptr(), y);
            }
        }
        out
    }

    /// What the two corners cut off a box's image are measured by: `sy·x − sx·y` of a point's
    /// coordinates on the minor axes, or equally of its projection (the shear adds the same
    /// to both terms).
    #[must_use]
    #[inline]
    pub fn diagonal(&self, [x, y]: [f32; 2]) -> f32 {
        self.sy * x - self.sx * y
    }

    /// The images under [`Shear::project`] of eight boxes at once, given as their lower and
    /// upper corners' coordinates per axis (`lo[axis][box]`): the rectangles' lower x, lower
    /// y, upper x and upper y (each holding the projection of every point of its box as
    /// [`Shear::project`] rounds it: rounding is monotonic), then the least and the greatest
    /// [`Shear::diagonal`] of the boxes' points, widened by `margin`; one box per lane, four
    /// lanes at a time.
    ///
    /// A box's image is a hexagon: its rectangle with two corners cut off along the
    /// direction of the shear. The diagonal's range is the band between those cuts; a point
    /// outside it is outside the hexagon, its line misses the box. Its rounding is not
    /// monotonic like the rectangle's: `margin` must exceed a few units in the last place of
    /// the largest coordinate in play.
    #[must_use]
    #[inline]
    pub fn project_boxes(
        &self,
        lo: &[[f32; 8]; 3],
        hi: &[[f32; 8]; 3],
        margin: f32,
    ) -> [[f32; 8]; 6] {
        use glam::Vec4;
        let mut out = [[0.0; 8]; 6];
        for half in [0, 4] {
            let lanes = |axes: &[[f32; 8]; 3], k: usize| Vec4::from_slice(&axes[k][half..]);
            let (lo_z, hi_z) = (lanes(lo, self.kz), lanes(hi, self.kz));
            let (zx0, zx1) = (lo_z * self.sx, hi_z * self.sx);
            let (zy0, zy1) = (lo_z * self.sy, hi_z * self.sy);
            let (x0, y0) = (lanes(lo, self.kx), lanes(lo, self.ky));
            let (x1, y1) = (lanes(hi, self.kx), lanes(hi, self.ky));
            let (ax0, ax1) = (x0 * self.sy, x1 * self.sy);
            let (by0, by1) = (y0 * self.sx, y1 * self.sx);
            let rect = [
                x0 - zx0.max(zx1),
                y0 - zy0.max(zy1),
                x1 - zx0.min(zx1),
                y1 - zy0.min(zy1),
                ax0.min(ax1) - by0.max(by1) - Vec4::splat(margin),
                ax0.max(ax1) - by0.min(by1) + Vec4::splat(margin),
            ];
            for (side, lanes) in out.iter_mut().zip(rect) {
                lanes.write_to_slice(&mut side[half..]);
            }
        }
        out
    }

    /// [`Shear::project_boxes`], eight lanes in one instruction: the same operations on the
    /// same numbers, so the same rectangles.
    ///
    /// # Safety
    /// The processor must have AVX.
    #[cfg(target_arch = "x86_64")]
    #[must_use]
    #[inline]
    #[target_feature(enable = "avx")]
    pub unsafe fn project_boxes_avx(
        &self,
        lo: &[[f32; 8]; 3],
        hi: &[[f32; 8]; 3],
        margin: f32,
    ) -> [[f32; 8]; 6] {
        use std::arch::x86_64::{
            _mm256_add_ps, _mm256_loadu_ps, _mm256_max_ps, _mm256_min_ps, _mm256_mul_ps,
            _mm256_set1_ps, _mm256_storeu_ps, _mm256_sub_ps,
        };
        // SAFETY: the eight-float loads and stores stay inside the arrays.
        unsafe {
            let lanes = |axes: &[[f32; 8]; 3], k: usize| _mm256_loadu_ps(axes[k].as_ptr());
            let (sx, sy) = (_mm256_set1_ps(self.sx), _mm256_set1_ps(self.sy));
            let (lo_z, hi_z) = (lanes(lo, self.kz), lanes(hi, self.kz));
            let (zx0, zx1) = (_mm256_mul_ps(lo_z, sx), _mm256_mul_ps(hi_z, sx));
            let (zy0, zy1) = (_mm256_mul_ps(lo_z, sy), _mm256_mul_ps(hi_z, sy));
            let (x0, y0) = (lanes(lo, self.kx), lanes(lo, self.ky));
            let (x1, y1) = (lanes(hi, self.kx), lanes(hi, self.ky));
            let (ax0, ax1) = (_mm256_mul_ps(x0, sy), _mm256_mul_ps(x1, sy));
            let (by0, by1) = (_mm256_mul_ps(y0, sx), _mm256_mul_ps(y1, sx));
            let margin = _mm256_set1_ps(margin);
            let rect = [
                _mm256_sub_ps(x0, _mm256_max_ps(zx0, zx1)),
                _mm256_sub_ps(y0, _mm256_max_ps(zy0, zy1)),
                _mm256_sub_ps(x1, _mm256_min_ps(zx0, zx1)),
                _mm256_sub_ps(y1, _mm256_min_ps(zy0, zy1)),
                _mm256_sub_ps(
                    _mm256_sub_ps(_mm256_min_ps(ax0, ax1), _mm256_max_ps(by0, by1)),
                    margin,
                ),
                _mm256_add_ps(
                    _mm256_sub_ps(_mm256_max_ps(ax0, ax1), _mm256_min_ps(by0, by1)),
                    margin,
                ),
            ];
            let mut out = [[0.0; 8]; 6];
            for (side, lanes) in out.iter_mut().zip(rect) {
                _mm256_storeu_ps(side.as_mut_ptr(), lanes);
            }
            out
        }
    }
}

/// Coordinate `k` (0, 1 or 2) of `p`: a branch taken the same way for every point of a bundle,
/// where indexing would go through memory.
#[inline(always)]
fn axis(p: &Vec3, k: usize) -> f32 {
    match k {
        0 => p.x,
        1 => p.y,
        _ => p.z,
    }
}

/// A line prepared for the watertight test: its starting point and the shear that maps its
/// direction to +z.
#[derive(Clone, Copy, Debug)]
pub struct ShearedLine {
    origin: Vec3,
    shear: Shear,
}

impl ShearedLine {
    /// Prepares the line `origin + t·direction`.
    #[must_use]
    pub fn new(origin: Vec3, direction: Vec3) -> Self {
        Self::with_shear(origin, Shear::new(direction))
    }

    /// The line from `origin` along the direction `shear` was made for.
    #[must_use]
    #[inline]
    pub fn with_shear(origin: Vec3, shear: Shear) -> Self {
        Self { origin, shear }
    }

    /// The crossing of this line with triangle (a, b, c), as `(t, front)`: `t` along the line
    /// (in units of its direction's length) and whether the line arrives at the triangle's front
    /// face (the side its counter-clockwise winding faces). `None` if it does not cross, or if
    /// `t` is outside `(0, t_max)`.
    #[must_use]
    #[inline]
    pub fn intersect(&self, a: Vec3, b: Vec3, c: Vec3, t_max: f32) -> Option<(f32, bool)> {
        let s = &self.shear;
        let corners = [s.project(a), s.project(b), s.project(c)];
        self.intersect_projected([a, b, c], corners, s.project(self.origin), t_max)
    }

    /// [`ShearedLine::intersect`] given the corners' and the line's starting point's
    /// [`Shear::project`]ions (which a bundle's lines share: a triangle's are worked out once
    /// for all of them).
    #[must_use]
    #[inline(always)]
    pub fn intersect_projected(
        &self,
        [a, b, c]: [Vec3; 3],
        [[pax, pay], [pbx, pby], [pcx, pcy]]: [[f32; 2]; 3],
        [ox, oy]: [f32; 2],
        t_max: f32,
    ) -> Option<(f32, bool)> {
        // The corners seen from the line: each corner's coordinates depend on it and the line
        // alone, so the triangles sharing it see it at the same place.
        let seen = [
            [pax - ox, pay - oy],
            [pbx - ox, pby - oy],
            [pcx - ox, pcy - oy],
        ];
        // Most lines tested miss, and most misses are plain in f32.
        if certainly_outside(seen) {
            return None;
        }
        self.crossing([a, b, c], seen, t_max)
    }

    /// The exact test, given the corners seen from the line (projected, relative to it).
    #[inline(always)]
    fn crossing(
        &self,
        [a, b, c]: [Vec3; 3],
        [[ax, ay], [bx, by], [cx, cy]]: [[f32; 2]; 3],
        t_max: f32,
    ) -> Option<(f32, bool)> {
        // Edge functions of the edges b→c, c→a and a→b, in f64: a product of two f32 is exact
        // in f64, so each sign is exact and a shared edge gives its two triangles exactly
        // opposite values. (Computing in f32 with an f64 fallback only at zero, as in the paper,
        // is not enough: one triangle may fall back for another edge while its neighbour keeps
        // a rounded f32 value of the wrong sign; 10 million lines found such a leak.)
        let f = f64::from;
        let u = f(cx) * f(by) - f(cy) * f(bx);
        let v = f(ax) * f(cy) - f(ay) * f(cx);
        let w = f(bx) * f(ay) - f(by) * f(ax);
        if ((u < 0.0) | (v < 0.0) | (w < 0.0)) & ((u > 0.0) | (v > 0.0) | (w > 0.0)) {
            return None;
        }
        let det = u + v + w;
        if det == 0.0 {
            return None;
        }
        let ccw = det > 0.0;
        if (u == 0.0 && !owns(bx, by, cx, cy, ccw))
            || (v == 0.0 && !owns(cx, cy, ax, ay, ccw))
            || (w == 0.0 && !owns(ax, ay, bx, by, ccw))
        {
            return None;
        }
        let Shear { kz, sz, .. } = self.shear;
        let depth = |p: Vec3| f(sz * (p[kz] - self.origin[kz]));
        let t = ((u * depth(a) + v * depth(b) + w * depth(c)) / det) as f32;
        (t > 0.0 && t < t_max).then_some((t, ccw))
    }
}

/// Whether the edge functions computed in f32 from the corners seen from the line have
/// opposite signs, so that the exact test finds the line outside too. An f32 edge function
/// that is not zero has the exact one's sign: rounding is monotonic, so rounded products keep
/// the order of the exact ones, and the difference of two f32 numbers has the exact sign.
#[inline]
fn certainly_outside([[ax, ay], [bx, by], [cx, cy]]: [[f32; 2]; 3]) -> bool {
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    // Without short cuts: the branches would be as hard to predict as the answer.
    ((u < 0.0) | (v < 0.0) | (w < 0.0)) & ((u > 0.0) | (v > 0.0) | (w > 0.0))
}

/// The plain f32 rejection of [`ShearedLine::intersect_projected`] for four lines at once,
/// through the points `(ox[i], oy[i])` of the plane the corners are [`Shear::project`]ed on:
/// bit i set when line i certainly misses. The same `f32` operations in the same order, lane
/// by lane, so the same answers.
#[must_use]
#[inline]
pub fn certainly_outside4(
    [[pax, pay], [pbx, pby], [pcx, pcy]]: [[f32; 2]; 3],
    ox: glam::Vec4,
    oy: glam::Vec4,
) -> u32 {
    use glam::Vec4;
    let (ax, ay) = (Vec4::splat(pax) - ox, Vec4::splat(pay) - oy);
    let (bx, by) = (Vec4::splat(pbx) - ox, Vec4::splat(pby) - oy);
    let (cx, cy) = (Vec4::splat(pcx) - ox, Vec4::splat(pcy) - oy);
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    let zero = Vec4::ZERO;
    let negative = u.cmplt(zero) | v.cmplt(zero) | w.cmplt(zero);
    let positive = u.cmpgt(zero) | v.cmpgt(zero) | w.cmpgt(zero);
    (negative & positive).bitmask()
}

/// Top-left rule: whether a triangle owns its edge from (px, py) to (qx, qy), taking the edge in
/// the triangle's counter-clockwise order in projection (reversed when the projection is
/// clockwise). Exactly one of an edge's two directions is owned.
#[inline]
fn owns(px: f32, py: f32, qx: f32, qy: f32, ccw: bool) -> bool {
    let (dx, dy) = if ccw {
        (qx - px, qy - py)
    } else {
        (px - qx, py - qy)
    };
    dy > 0.0 || (dy == 0.0 && dx < 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::Xoshiro256PlusPlus;
    use rand::{RngExt, SeedableRng};

    #[test]
    fn four_lines_at_once_are_rejected_exactly_as_one_by_one() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(5);
        let mut disagreements = 0;
        let mut rejected = 0;
        for _ in 0..100_000 {
            // Small integers make exact zeros (lines through edges and corners) common.
            let mut c = || f32::from(rng.random_range(-4i8..=4)) * 0.25;
            let corners = [[c(), c()], [c(), c()], [c(), c()]];
            let (ox, oy) = ([c(), c(), c(), c()], [c(), c(), c(), c()]);
            let mask = certainly_outside4(corners, ox.into(), oy.into());
            for i in 0..4 {
                let seen = corners.map(|[x, y]| [x - ox[i], y - oy[i]]);
                let one = certainly_outside(seen);
                rejected += usize::from(one);
                disagreements += usize::from(one != (mask >> i & 1 == 1));
            }
        }
        assert_eq!(disagreements, 0);
        assert!(rejected > 100_000, "{rejected}");
    }

    #[test]
    fn a_line_through_the_middle_hits_at_the_right_distance_and_side() {
        let (a, b, c) = (Vec3::ZERO, Vec3::X, Vec3::Y);
        let down = ShearedLine::new(Vec3::new(0.2, 0.2, 1.0), Vec3::NEG_Z);
        assert_eq!(down.intersect(a, b, c, 10.0), Some((1.0, true)));
        let up = ShearedLine::new(Vec3::new(0.2, 0.2, -2.0), Vec3::Z * 2.0);
        assert_eq!(up.intersect(a, b, c, 10.0), Some((1.0, false)));
        assert_eq!(up.intersect(a, b, c, 0.5), None);
        let miss = ShearedLine::new(Vec3::new(0.8, 0.8, 1.0), Vec3::NEG_Z);
        assert_eq!(miss.intersect(a, b, c, 10.0), None);
    }

    #[test]
    fn front_means_arriving_against_the_normal() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(1);
        let mut p = || {
            Vec3::new(
                rng.random::<f32>() - 0.5,
                rng.random::<f32>() - 0.5,
                rng.random::<f32>() - 0.5,
            )
        };
        let mut checked = 0;
        for _ in 0..20_000 {
            let (a, b, c) = (p(), p(), p());
            let target = (a + b + c) / 3.0;
            let d = p().normalize();
            let line = ShearedLine::new(target - d * 3.0, d);
            if let Some((t, front)) = line.intersect(a, b, c, 10.0) {
                let n = (b - a).cross(c - a);
                assert_eq!(front, n.dot(d) < 0.0);
                assert!((t - 3.0).abs() < 1e-3, "{t}");
                checked += 1;
            }
        }
        assert!(checked > 19_000, "{checked}");
    }

    #[test]
    fn lines_through_shared_edges_and_vertices_hit_exactly_one_triangle() {
        // A fan of triangles around the origin in the plane z = 0 covering the disc, plus a
        // square split along its diagonal: lines aimed exactly at vertices and edge points.
        let ring: Vec<Vec3> = (0..7)
            .map(|k| {
                let a = k as f32 / 7.0 * std::f32::consts::TAU;
                Vec3::new(a.cos(), a.sin(), 0.0)
            })
            .collect();
        let fan: Vec<[Vec3; 3]> = (0..7)
            .map(|k| [Vec3::ZERO, ring[k], ring[(k + 1) % 7]])
            .collect();
        let square = [
            [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0)],
            [Vec3::ZERO, Vec3::new(1.0, 1.0, 0.0), Vec3::Y],
        ];
        // Interior points only: the fan's centre and its spokes' midpoints; points of the
        // square's diagonal. (On an open mesh's boundary either answer is right.)
        let mut fan_targets = vec![Vec3::ZERO];
        fan_targets.extend(ring.iter().map(|&r| r * 0.5));
        let square_targets = [0.25f32, 0.5, 0.9].map(|x| Vec3::new(x, x, 0.0));
        let directions = [
            Vec3::NEG_Z,
            Vec3::new(0.3, -0.2, -1.0).normalize(),
            Vec3::new(-1.0, 0.0, -1e-3).normalize(),
            Vec3::new(1.0, 1.0, -0.5).normalize(),
        ];
        for d in directions {
            for (name, tris, targets) in [
                ("fan", &fan[..], &fan_targets[..]),
                ("square", &square[..], &square_targets[..]),
            ] {
                for &target in targets {
                    let line = ShearedLine::new(target - d * 2.0, d);
                    let hits = tris
                        .iter()
                        .filter(|t| line.intersect(t[0], t[1], t[2], 10.0).is_some())
                        .count();
                    assert_eq!(hits, 1, "{name}: line along {d} through {target}");
                }
            }
        }
    }

    #[test]
    fn the_f32_shortcut_rejects_only_what_the_exact_test_rejects() {
        // Lines through points a hair's breadth from an edge (or a corner) of random
        // triangles, where f32 edge functions round to the wrong sign if anything does.
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(11);
        let mut coordinate = || rng.random::<f32>() * 2.0 - 1.0;
        let (mut shortcuts, mut near) = (0, 0);
        for k in 0..200_000 {
            let corners: [[f32; 2]; 3] = std::array::from_fn(|_| [coordinate(), coordinate()]);
            let (p, q) = (corners[k % 3], corners[(k + 1) % 3]);
            let s = (coordinate() + 1.0) / 2.0;
            // From 1e-5 down to 1e-9: down to below f32's resolution of the coordinates.
            let nudge = coordinate() * 10f32.powf(-5.0 - 2.0 * (coordinate() + 1.0));
            let o = [
                p[0] + s * (q[0] - p[0]) + nudge,
                p[1] + s * (q[1] - p[1]) - nudge,
            ];
            let seen = corners.map(|[x, y]| [x - o[0], y - o[1]]);
            let line = ShearedLine::new(Vec3::new(0.0, 0.0, -2.0), Vec3::Z);
            let [a, b, c] = corners.map(|[x, y]| Vec3::new(x, y, 0.0));
            let exact = line.crossing([a, b, c], seen, 10.0);
            near += usize::from(exact.is_some());
            if certainly_outside(seen) {
                shortcuts += 1;
                assert_eq!(exact, None, "{corners:?} from {o:?}");
            }
        }
        // About half the lines are outside, and the shortcut takes most of them.
        assert!(shortcuts > 50_000 && near > 50_000, "{shortcuts} {near}");
    }

    #[test]
    fn a_closed_tetrahedron_is_crossed_an_even_number_of_times() {
        let v = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(0.0, 0.0, 1.0),
        ];
        let faces = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(5);
        // Lines aimed at vertices, edge midpoints and random points.
        let mut targets: Vec<Vec3> = v.to_vec();
        for i in 0..4 {
            for j in i + 1..4 {
                targets.push((v[i] + v[j]) * 0.5);
            }
        }
        for _ in 0..200 {
            targets.push(Vec3::new(rng.random(), rng.random(), rng.random()) * 0.4);
        }
        for &target in &targets {
            for _ in 0..50 {
                let d = Vec3::new(
                    rng.random::<f32>() - 0.5,
                    rng.random::<f32>() - 0.5,
                    rng.random::<f32>() - 0.5,
                )
                .normalize();
                let line = ShearedLine::new(target - d * 3.0, d);
                let hits: Vec<(f32, bool)> = faces
                    .iter()
                    .filter_map(|f| line.intersect(v[f[0]], v[f[1]], v[f[2]], 10.0))
                    .collect();
                assert!(
                    hits.len().is_multiple_of(2),
                    "{} hits through {target} along {d}",
                    hits.len()
                );
                if hits.len() == 2 {
                    // In through a front face, out through a back face (unless the line only
                    // grazes an edge or vertex, where both crossings are at the same point).
                    let (first, second) = if hits[0].0 < hits[1].0 {
                        (hits[0], hits[1])
                    } else {
                        (hits[1], hits[0])
                    };
                    assert!(
                        first.1 && !second.1 || second.0 - first.0 < 1e-5,
                        "{hits:?}"
                    );
                }
            }
        }
    }
}
