//! Global lines: bundles of parallel lines whose directions cover the sphere uniformly
//! (METHOD.md §1–§2).
//!
//! A bundle is a direction `w` and a square grid of cell area Δ, with a uniformly random offset,
//! on the plane orthogonal to `w`. The grid covers only the projection of the scene's box, and
//! only the lines that meet the box are kept: a line that misses the box carries nothing. Each
//! grid point is one line, so a patch of area A and normal n is crossed `A |n·w| / Δ` times per
//! bundle in expectation, `A / (2Δ)` averaged over directions.
//!
//! Directions of a batch of B bundles are a spherical Fibonacci lattice on the half sphere (lines
//! are unoriented) under a uniformly random rotation: every direction is uniform on the sphere,
//! and together they are stratified. More lines are added later as further batches, each with
//! its own rotation. Everything derives from the seed, the batch and the bundle index, so the
//! lines do not depend on the number of threads.

use glam::{DQuat, DVec3, Vec3};
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};

use crate::scene::Bounds;

/// Distance from the plane through the origin to each line's starting point: the scene lies
/// inside the unit sphere (normalised space), so every hit has `t` in (1, 3).
pub const ORIGIN_OFFSET: f32 = 2.0;
/// Length of every line from its starting point.
pub const LINE_LENGTH: f32 = 4.0;
/// Direction components smaller than this are pushed to it: the BVH's slab test takes
/// `1 / d` and would lose precision on near-zero components. The bias is a rotation of at most
/// 1e-6 radians on a set of directions of measure ~1e-6.
const MIN_COMPONENT: f64 = 1e-6;

/// The fewest lines a bundle of denser lines holds on average ([`Batch::dense`]): a bundle
/// stratifies its lines over the region's projection, which fewer lines do less well, and
/// each bundle costs its setting up (the panel room, four seeds: 1.01% per patch at 16, 0.98%
/// at 32 and 64, 0.95% in √ of the lines' directions, within the noise; its bake 1.80 s at 16,
/// 1.69 s at 32, 1.70 s at 64, 1.63 s before, the means of single runs).
pub const DENSE_BUNDLE_LINES: f64 = 32.0;

/// Independent replicas of the direction lattice in a batch (see [`Batch::direction`]).
pub const REPLICAS: u32 = 16;

/// A batch of bundles: B directions and a grid cell area.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Batch {
    /// Seed of the whole line set.
    pub seed: u64,
    /// Index of this batch within the line set (0 for the first, then one per refinement).
    pub index: u32,
    /// Number of bundles (directions).
    pub bundles: u32,
    /// Area Δ of a grid cell, in normalised units: one line per Δ of projected area.
    pub cell_area: f64,
    /// For a batch of denser lines ([`Batch::dense`]): the region's index and box, the lines
    /// kept being those that meet it. `None`: the lines that meet the scene's box.
    pub region: Option<(u32, Bounds)>,
}

impl Batch {
    /// The batch that puts about `lines` lines through `bounds`: with B bundles, the mean
    /// projected area of a convex box is A(W)/4 (Cauchy), so Δ = B·A(W) / (4·lines).
    /// `bundles` defaults to √lines (at least 8): as many directions as lines per direction.
    #[must_use]
    pub fn for_budget(
        lines: u64,
        bundles: Option<u32>,
        bounds: &Bounds,
        seed: u64,
        index: u32,
    ) -> Self {
        let lines = lines.max(1) as f64;
        let bundles = bundles
            .unwrap_or_else(|| (lines.sqrt().round() as u32).max(8))
            .max(1);
        let cell_area = f64::from(bundles) * bounds.surface_area() / (4.0 * lines);
        Self {
            seed,
            index,
            bundles,
            cell_area,
            region: None,
        }
    }

    /// The lines that meet `region` (box number `number` of a list's dense regions),
    /// `factor` times as dense as the lines of `global`: a batch's density in the space of
    /// lines is its bundles over its cell area (B/Δ lines per unit of projected area and of
    /// solid angle), so Δ' = B'·Δ / (factor·B). About `factor · lines(global) · A(region) /
    /// A(scene box)` lines, in `factor` times the global bundles (the lines of `factor` global
    /// line sets that meet the region, each bundle on the global grid), or fewer where a bundle
    /// would hold fewer than [`DENSE_BUNDLE_LINES`] (at least 4 per replica).
    ///
    /// The directions matter as much as the lines: every line from the room that meets a
    /// fixture's gap is one of these (the fixture's lit shade lies in the gap's box), so a
    /// floor under it sees the fixture along the region's directions alone. In √ of the lines'
    /// bundles (300 against the global lines' 1,000 on the level under lamps at 1M lines), the
    /// floor under the lamp-lit shade was 3.7% noisy per patch, falling as the lines' fourth
    /// root; in the new directions (3,250 of 32 lines), 0.67% (docs/engine.md, "Pieces").
    #[must_use]
    pub fn dense(
        global: &Self,
        (number, region): (u32, Bounds),
        factor: u32,
        scene: &Bounds,
        index: u32,
    ) -> Self {
        let global_lines =
            f64::from(global.bundles) * scene.surface_area() / (4.0 * global.cell_area);
        let lines = f64::from(factor) * global_lines * region.surface_area() / scene.surface_area();
        let directions = f64::from(factor) * f64::from(global.bundles);
        let bundles = (directions.min(lines / DENSE_BUNDLE_LINES).round() as u32).max(4 * REPLICAS);
        let cell_area =
            f64::from(bundles) * global.cell_area / (f64::from(factor) * f64::from(global.bundles));
        Self {
            seed: global.seed,
            index,
            bundles,
            cell_area,
            region: Some((number, region)),
        }
    }

    /// The uniformly random rotation of one replica's direction lattice (Shoemake's method).
    fn rotation(&self, replica: u32) -> DQuat {
        let stream = u64::MAX - u64::from(replica);
        let mut rng =
            Xoshiro256PlusPlus::seed_from_u64(mix(self.seed, u64::from(self.index), stream));
        let (u1, u2, u3): (f64, f64, f64) = (rng.random(), rng.random(), rng.random());
        let tau = std::f64::consts::TAU;
        let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
        DQuat::from_xyzw(
            a * (tau * u2).sin(),
            a * (tau * u2).cos(),
            b * (tau * u3).sin(),
            b * (tau * u3).cos(),
        )
        .normalize()
    }

    /// Direction of bundle `k`. The bundles form [`REPLICAS`] independent replicas (bundle k
    /// belongs to replica k mod REPLICAS), each a spherical Fibonacci lattice on the half sphere
    /// (uniform in z, golden-angle steps in azimuth) under its own random rotation. Every
    /// replica is an unbiased, stratified estimate on its own; the spread between them is an
    /// honest measure of the error (randomised quasi-Monte Carlo).
    #[must_use]
    pub fn direction(&self, k: u32) -> DVec3 {
        let replica = k % REPLICAS;
        let in_replica = self.bundles / REPLICAS + u32::from(replica < self.bundles % REPLICAS);
        direction(self.rotation(replica), k / REPLICAS, in_replica)
    }

    /// Bundle `k` of this batch: its direction and the lines of its grid that meet `bounds`
    /// (or its region, for a dense batch).
    #[must_use]
    pub fn bundle(&self, k: u32, bounds: &Bounds) -> Bundle {
        let mut rng =
            Xoshiro256PlusPlus::seed_from_u64(mix(self.seed, u64::from(self.index), u64::from(k)));
        let offset: (f64, f64) = (rng.random(), rng.random());
        let within = self.region.as_ref().map_or(bounds, |(_, r)| r);
        parallel_bundle(self.direction(k), self.cell_area, offset, within)
    }
}

/// The lines of direction `w` through a square grid of cells of `cell_area` (normalised units
/// squared), shifted by `offset` (fractions of a cell, in [0, 1)), over the projection of
/// `bounds`, keeping those that meet the box. Each line stands for the `cell_area` of the plane
/// around it: a bundle of global lines, or the light of a directional light.
///
/// Each row of the grid is walked only across the box's projection (a convex polygon), with a
/// cell's margin on either side, not across the rectangle around it: a thin box lying across
/// the bundle's plane (a scene of two objects far apart) projects to a sliver whose rectangle
/// holds far more cells than lines (10^10 in a bundle of a scene 10^9 wide), which were each
/// tested. The same lines either way.
#[must_use]
pub fn parallel_bundle(w: DVec3, cell_area: f64, offset: (f64, f64), bounds: &Bounds) -> Bundle {
    let (u, v) = w.any_orthonormal_pair();
    let (offset_u, offset_v) = offset;
    // The projection of the box onto the plane (u, v): a convex polygon, and the rectangle
    // around it.
    let corners = bounds.corners().map(|c| (c.dot(u), c.dot(v)));
    let hull = convex_hull(&corners);
    let (mut u0, mut u1, mut v0, mut v1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for &(x, y) in &corners {
        (u0, u1, v0, v1) = (u0.min(x), u1.max(x), v0.min(y), v1.max(y));
    }
    let step = cell_area.sqrt();
    let columns = ((u1 - u0) / step).ceil() as i64 + 1;
    let rows = ((v1 - v0) / step).ceil() as i64 + 1;
    let direction = w.as_vec3();
    let mut origins = Vec::new();
    for j in 0..rows {
        let y = v0 + (j as f64 + offset_v - 0.5) * step;
        // The row's stretch across the polygon, a cell wider on either side.
        let Some((from, to)) = across(&hull, y) else {
            continue;
        };
        let first = ((from - u0) / step - offset_u + 0.5).floor() as i64 - 1;
        let last = ((to - u0) / step - offset_u + 0.5).ceil() as i64 + 1;
        for i in first.max(0)..=last.min(columns - 1) {
            let x = u0 + (i as f64 + offset_u - 0.5) * step;
            let point = u * x + v * y;
            if meets_box(point, w, bounds) {
                origins.push((point - w * f64::from(ORIGIN_OFFSET)).as_vec3());
            }
        }
    }
    Bundle { direction, origins }
}

/// The convex hull of `points`, counter-clockwise (Andrew's monotone chain); collinear points
/// dropped.
fn convex_hull(points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut sorted = points.to_vec();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    sorted.dedup();
    if sorted.len() < 3 {
        return sorted;
    }
    let cross = |o: (f64, f64), a: (f64, f64), b: (f64, f64)| {
        (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
    };
    let mut hull: Vec<(f64, f64)> = Vec::with_capacity(2 * sorted.len());
    for pass in [
        &sorted[..],
        &sorted.iter().rev().copied().collect::<Vec<_>>()[..],
    ] {
        let base = hull.len();
        for &p in pass {
            while hull.len() >= base + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// Where the horizontal line at `y` crosses the convex polygon `hull` (its corners in order):
/// the least and greatest `x`, or `None` if it misses it.
fn across(hull: &[(f64, f64)], y: f64) -> Option<(f64, f64)> {
    let (mut from, mut to) = (f64::INFINITY, f64::NEG_INFINITY);
    for (k, &(xa, ya)) in hull.iter().enumerate() {
        let (xb, yb) = hull[(k + 1) % hull.len()];
        let (lo, hi) = (ya.min(yb), ya.max(yb));
        if y < lo || y > hi {
            continue;
        }
        let x = if yb == ya {
            from = from.min(xa.min(xb));
            xa.max(xb)
        } else {
            xa + (xb - xa) * (y - ya) / (yb - ya)
        };
        (from, to) = (from.min(x), to.max(x));
    }
    (from <= to).then_some((from, to))
}

/// Direction `k` of `n` on the rotated Fibonacci half-sphere lattice, with no component below
/// [`MIN_COMPONENT`] in magnitude.
fn direction(rotation: DQuat, k: u32, n: u32) -> DVec3 {
    let golden = (5f64.sqrt() - 1.0) / 2.0;
    let z = (f64::from(k) + 0.5) / f64::from(n);
    let phi = std::f64::consts::TAU * (f64::from(k) * golden).fract();
    let r = (1.0 - z * z).max(0.0).sqrt();
    let d = rotation * DVec3::new(r * phi.cos(), r * phi.sin(), z);
    let nudge = |c: f64| {
        if c.abs() < MIN_COMPONENT {
            MIN_COMPONENT.copysign(c)
        } else {
            c
        }
    };
    DVec3::new(nudge(d.x), nudge(d.y), nudge(d.z)).normalize()
}

/// Whether the line through `point` with direction `w` meets the box (slab test in f64).
pub fn meets_box(point: DVec3, w: DVec3, bounds: &Bounds) -> bool {
    let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
    for axis in 0..3 {
        let (o, d) = (point[axis], w[axis]);
        let (a, b) = ((bounds.min[axis] - o) / d, (bounds.max[axis] - o) / d);
        near = near.max(a.min(b));
        far = far.min(a.max(b));
    }
    near <= far
}

/// SplitMix64 of the three inputs: independent seeds for each (line set, batch, bundle).
fn mix(a: u64, b: u64, c: u64) -> u64 {
    let mut x = a;
    for v in [b, c] {
        x = x.wrapping_add(0x9E37_79B9_7F4A_7C15).wrapping_add(v);
        x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        x ^= x >> 31;
    }
    x
}

/// One bundle of parallel lines.
#[derive(Clone, Debug, PartialEq)]
pub struct Bundle {
    /// Unit direction shared by every line of the bundle.
    pub direction: Vec3,
    /// Starting point of each line, [`ORIGIN_OFFSET`] before the plane through the origin; the
    /// line runs [`LINE_LENGTH`] from there.
    pub origins: Vec<Vec3>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box() -> Bounds {
        Bounds {
            min: DVec3::splat(-0.5),
            max: DVec3::splat(0.5),
        }
    }

    /// A bundle walks each row across the box's projection only, and keeps the lines that
    /// testing every cell of the rectangle around it keeps: on cubes, slabs, needles and a
    /// flat box, in 200 directions each.
    #[test]
    fn a_bundle_keeps_the_lines_a_walk_of_every_cell_keeps() {
        let every_cell = |w: DVec3, cell_area: f64, (ou, ov): (f64, f64), b: &Bounds| {
            let (u, v) = w.any_orthonormal_pair();
            let range = |axis: DVec3| {
                (b.corners().iter()).fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), c| {
                    (lo.min(c.dot(axis)), hi.max(c.dot(axis)))
                })
            };
            let ((u0, u1), (v0, v1)) = (range(u), range(v));
            let step = cell_area.sqrt();
            let mut origins = Vec::new();
            for j in 0..((v1 - v0) / step).ceil() as i64 + 1 {
                for i in 0..((u1 - u0) / step).ceil() as i64 + 1 {
                    let x = u0 + (i as f64 + ou - 0.5) * step;
                    let point = u * x + v * (v0 + (j as f64 + ov - 0.5) * step);
                    if meets_box(point, w, b) {
                        origins.push((point - w * f64::from(ORIGIN_OFFSET)).as_vec3());
                    }
                }
            }
            origins
        };
        let boxes = [
            DVec3::splat(0.5),
            DVec3::new(0.5, 0.5, 0.01),
            DVec3::new(0.5, 0.002, 0.001),
            DVec3::new(0.3, 0.4, 0.0),
        ];
        let batch = Batch::for_budget(40_000, Some(200), &unit_box(), 9, 0);
        let mut kept = 0;
        for half in boxes {
            let b = Bounds {
                min: -half,
                max: half,
            };
            for k in 0..200 {
                let w = batch.direction(k);
                let offset = (f64::from(k % 7) / 7.0, f64::from(k % 5) / 5.0);
                let cell = 4e-4 * b.surface_area().max(1e-6);
                let bundle = parallel_bundle(w, cell, offset, &b);
                assert_eq!(
                    bundle.origins,
                    every_cell(w, cell, offset, &b),
                    "{half} {k}"
                );
                kept += bundle.origins.len();
            }
        }
        assert!(kept > 100_000, "{kept}");
    }

    #[test]
    fn a_budget_gives_about_that_many_lines() {
        let b = unit_box();
        let batch = Batch::for_budget(100_000, None, &b, 1, 0);
        assert_eq!(batch.bundles, 316);
        let total: usize = (0..batch.bundles)
            .map(|k| batch.bundle(k, &b).origins.len())
            .sum();
        // Only the grid's random offset varies the count: well within 2%.
        assert!((total as f64 / 100_000.0 - 1.0).abs() < 0.02, "{total}");
    }

    #[test]
    fn directions_are_unit_and_cover_the_sphere_evenly() {
        let batch = Batch::for_budget(1 << 20, Some(4096), &unit_box(), 7, 0);
        let dirs: Vec<DVec3> = (0..4096).map(|k| batch.direction(k)).collect();
        assert!(dirs.iter().all(|d| (d.length() - 1.0).abs() < 1e-12));
        // Lines are unoriented: ±d are the same line. The mean of |d·a| over the sphere is 1/2
        // for any axis a; the lattice is stratified, so it lands much closer than random points.
        for axis in [
            DVec3::X,
            DVec3::Y,
            DVec3::Z,
            DVec3::new(1.0, 2.0, 3.0).normalize(),
        ] {
            let mean = dirs.iter().map(|d| d.dot(axis).abs()).sum::<f64>() / 4096.0;
            assert!((mean - 0.5).abs() < 2e-3, "{axis}: {mean}");
        }
    }

    #[test]
    fn the_same_seed_gives_the_same_lines_and_another_seed_does_not() {
        let b = unit_box();
        let one = Batch::for_budget(10_000, None, &b, 3, 0);
        assert_eq!(one.bundle(5, &b), one.bundle(5, &b));
        let other = Batch::for_budget(10_000, None, &b, 4, 0);
        assert_ne!(one.bundle(5, &b), other.bundle(5, &b));
        let next = Batch::for_budget(10_000, None, &b, 3, 1);
        assert_ne!(one.direction(5), next.direction(5));
    }

    #[test]
    fn every_kept_line_meets_the_box_and_no_meeting_line_is_lost() {
        // Brute force: a much larger grid over the bounding disc, same offsets and step.
        let b = Bounds {
            min: DVec3::new(-0.7, -0.2, -0.1),
            max: DVec3::new(0.6, 0.3, 0.1),
        };
        let batch = Batch::for_budget(20_000, Some(50), &b, 9, 0);
        for k in 0..50 {
            let bundle = batch.bundle(k, &b);
            let w = bundle.direction.as_dvec3();
            for o in &bundle.origins {
                let p = o.as_dvec3() + w * f64::from(ORIGIN_OFFSET);
                assert!(meets_box(p, w, &b));
            }
            // Expected count: projected area of the box / Δ.
            let d = b.max - b.min;
            let projected = d.y * d.z * w.x.abs() + d.x * d.z * w.y.abs() + d.x * d.y * w.z.abs();
            let expected = projected / batch.cell_area;
            let n = bundle.origins.len() as f64;
            // The grid count differs from area/Δ by at most the cells along the outline.
            let perimeter_cells = 2.0 * (d.x + d.y + d.z) * 2.0 / batch.cell_area.sqrt();
            assert!(
                (n - expected).abs() <= perimeter_cells,
                "bundle {k}: {n} vs {expected}"
            );
        }
    }
}
