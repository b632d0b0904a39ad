//! The outputs' points on the traced scene: where a drawn vertex's light is evaluated, and its
//! value there ([`crate::direct::points`]).

use glam::DVec3;

use super::Bake;
use crate::direct::points::{
    Corner, Gather, Lighting, NEAR_CORNER, PointRadiance, Points, Probe, Site, Solved,
};

impl Bake {
    /// The points of `vertices`, each the face corners around a drawn vertex (of
    /// [`Bake::shown`]'s triangles), as sites on the traced triangles (which [`Bake::split`]
    /// may have cut finer): each corner a hair towards its face's centroid ([`NEAR_CORNER`]),
    /// on the traced triangle of the same patch and side that holds that point, weighed by the
    /// corner's angle. Located at frame 0; a site moves with its triangle.
    #[must_use]
    pub fn points_at_corners<'a>(
        &self,
        vertices: impl IntoIterator<Item = &'a [Corner]>,
    ) -> Points {
        let faces = Faces::new(self);
        let mut points = Points::default();
        for vertex in vertices {
            points.push(vertex.iter().filter_map(|c| {
                let triangle = faces.drawn(c.triangle);
                let centre = (triangle[0] + triangle[1] + triangle[2]) / 3.0;
                let k = usize::from(c.corner);
                let x = triangle[k] + (centre - triangle[k]) * NEAR_CORNER;
                faces.site((c.triangle, c.back), x, c.angle)
            }));
        }
        points
    }

    /// One point per entry of `at`, each a point `x` (normalised space, frame 0) on a face of
    /// the scene as drawn (its drawn triangle, global index, and whether the back face), placed
    /// on the traced triangle of the same patch and side that holds it, as
    /// [`Bake::points_at_corners`] places a corner; a point on no patch (a side that is not
    /// one) has no site, and reads dark.
    #[must_use]
    pub fn points_on_faces(&self, at: impl IntoIterator<Item = ((u32, bool), DVec3)>) -> Points {
        let faces = Faces::new(self);
        let mut points = Points::default();
        for (face, x) in at {
            points.push(faces.site(face, x, 1.0));
        }
        points
    }

    /// The radiance at `points` at `frame`, from `solved`, this frame's patches solved with
    /// `lighting`, sampled as `gather` says ([`crate::direct::points::radiance_at`]).
    #[must_use]
    pub fn radiance_at(
        &self,
        frame: usize,
        points: &Points,
        (solved, lighting): (Solved<'_>, Lighting<'_>),
        gather: Gather,
    ) -> Vec<PointRadiance> {
        let state = (&self.scene, &self.tracer, &self.area);
        let sampling = (gather, &self.gathered);
        let mut values =
            crate::direct::points::radiance_at(state, frame, points, (solved, lighting), sampling);
        // Radiance is never negative: a sum of gathered terms can round below 0 (by 1e-13).
        for v in &mut values {
            v.radiance = v.radiance.map(|c| c.max(0.0));
        }
        values
    }
}

impl Bake {
    /// The light probes at `positions` (normalised space) at `frame`, from `solved`, this
    /// frame's patches solved with `lighting`, `gather.rays` gather rays each
    /// ([`crate::direct::points::probes_at`]).
    #[must_use]
    pub fn probes_at(
        &self,
        frame: usize,
        positions: &[DVec3],
        (solved, lighting): (Solved<'_>, Lighting<'_>),
        gather: Gather,
    ) -> Vec<Probe> {
        let state = (&self.scene, &self.tracer, &self.area);
        let sampling = (gather, &self.gathered);
        crate::direct::points::probes_at(state, frame, positions, (solved, lighting), sampling)
    }
}

/// The faces of a bake's scene as drawn and as traced, at frame 0: where a point on a drawn face
/// lies on the traced triangles (which [`Bake::split`] may have cut finer).
struct Faces {
    shown: Vec<([glam::Vec3; 3], crate::scene::Faces)>,
    traced: Vec<([glam::Vec3; 3], crate::scene::Faces)>,
    /// The traced faces of each patch, when the drawn triangles are not the traced ones
    /// (empty when they are).
    by_patch: Vec<Vec<(u32, bool)>>,
}

impl Faces {
    fn new(bake: &Bake) -> Self {
        let shown = bake.shown().triangles_at(0);
        let traced = bake.scene.triangles_at(0);
        let mut by_patch: Vec<Vec<(u32, bool)>> = Vec::new();
        if bake.shown.is_some() {
            by_patch = vec![Vec::new(); bake.scene.patches.len()];
            for (t, (_, faces)) in traced.iter().enumerate() {
                by_patch[faces.front as usize].push((t as u32, false));
                if let Some(back) = faces.back {
                    by_patch[back as usize].push((t as u32, true));
                }
            }
        }
        Self {
            shown,
            traced,
            by_patch,
        }
    }

    /// The corners of drawn triangle `t`.
    fn drawn(&self, t: u32) -> [DVec3; 3] {
        self.shown[t as usize].0.map(|c| c.as_dvec3())
    }

    /// The site of point `x` on drawn face `(t, back)`, weighing `weight`.
    fn site(&self, (t, back): (u32, bool), x: DVec3, weight: f64) -> Option<Site> {
        let site = |triangle: u32, bary: [f64; 3]| Site {
            triangle,
            back,
            bary,
            weight,
        };
        if self.by_patch.is_empty() {
            return Some(site(t, barycentric(x, &self.drawn(t))));
        }
        let faces = self.shown.get(t as usize)?.1;
        let patch = if back { faces.back? } else { faces.front };
        // The face of the patch that holds x (the nearest, for rounding).
        let (best, bary) = (self.by_patch[patch as usize].iter())
            .filter(|&&(_, b)| b == back)
            .map(|&(u, _)| {
                let corners = self.traced[u as usize].0.map(|c| c.as_dvec3());
                (u, barycentric(x, &corners))
            })
            .max_by(|a, b| min3(a.1).total_cmp(&min3(b.1)))?;
        Some(site(best, clamped(bary)))
    }
}

/// The barycentric coordinates of `x` (projected onto the triangle's plane) in `t`; those of
/// the centroid if `t` is degenerate.
fn barycentric(x: DVec3, t: &[DVec3; 3]) -> [f64; 3] {
    let (e0, e1, d) = (t[1] - t[0], t[2] - t[0], x - t[0]);
    let (d00, d01, d11) = (e0.dot(e0), e0.dot(e1), e1.dot(e1));
    let (d20, d21) = (d.dot(e0), d.dot(e1));
    let det = d00 * d11 - d01 * d01;
    if det <= 0.0 || !det.is_finite() {
        return [1.0 / 3.0; 3];
    }
    let v = (d11 * d20 - d01 * d21) / det;
    let w = (d00 * d21 - d01 * d20) / det;
    [1.0 - v - w, v, w]
}

/// The smallest of three coordinates.
fn min3(b: [f64; 3]) -> f64 {
    b[0].min(b[1]).min(b[2])
}

/// Barycentric coordinates moved into the triangle (negative ones to 0, the rest rescaled).
fn clamped(b: [f64; 3]) -> [f64; 3] {
    let b = b.map(|x| x.max(0.0));
    let sum = b[0] + b[1] + b[2];
    if sum > 0.0 {
        b.map(|x| x / sum)
    } else {
        [1.0 / 3.0; 3]
    }
}
