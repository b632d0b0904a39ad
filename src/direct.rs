//! Direct light from punctual lights (`KHR_lights_punctual`): the irradiance each patch receives
//! straight from each light at a frame, shadows included, traced through the same BVHs as the
//! global lines. It starts the interreflection solve: a patch of reflectance ρ under direct
//! irradiance E leaves with ρ·E/π more radiance, and the global lines carry that light on.
//!
//! Irradiances are computed per unit of the light's power (colour × intensity = 1), so a light
//! can be dimmed or recoloured without tracing again. Units are in [`crate::scene::Light`].
//!
//! - **Point and spot lights**: each patch is sampled at the centroids of 1, 4, 16 or 64 equal
//!   sub-triangles, more as the patch looks larger from the light (its longest edge against its
//!   distance), each with a shadow ray to the light. A patch that faces away, lies outside a
//!   spot's cone or beyond the light's range, or does not reflect, costs nothing.
//! - **Directional lights** are a bundle of parallel lines (METHOD.md §1's construction with
//!   one direction): each line carries the flux of its cell, `E⊥·Δ`, to the first surface it
//!   meets, so a patch receives `E⊥·cos θ` on average and nothing in shadow.

use std::collections::HashMap;
use std::hash::{Hash, Hasher};

use glam::{DVec3, Vec3};
use rayon::prelude::*;

use crate::lines::parallel_bundle;
use crate::scene::{Faces, Light, LightKind, Scene};
use crate::trace::{FrameMeshes, Hit, Line, SceneTracer};

/// Lines of a directional light per patch of median area. A patch's share of a jittered grid
/// errs by about the lines along its boundary: a few per cent at 256.
const LINES_PER_PATCH: f64 = 256.0;

/// Most lines of one directional light at one frame.
const MAX_DIRECTIONAL_LINES: f64 = 4.0e6;

/// A shadow ray ignores crossings this close to either end (normalised units): the surface it
/// starts on, and surfaces touching the light.
const SHADOW_EPSILON: f32 = 1e-5;

/// The direct irradiance of every frame, per light and patch, shared between frames where
/// nothing it depends on changes.
#[derive(Clone, Debug, Default)]
pub struct DirectLight {
    /// For each frame, its entry in `terms`.
    frame_term: Vec<usize>,
    /// Per distinct state: per light, the irradiance of each patch per unit of light power.
    terms: Vec<Vec<Vec<f64>>>,
}

impl DirectLight {
    /// Computes the direct light of every frame of `scene` (nothing if it has no lights).
    /// Frames whose moving geometry and lights are posed alike share one computation.
    #[must_use]
    pub fn compute(scene: &Scene, tracer: &SceneTracer) -> Self {
        if scene.lights.is_empty() {
            return Self::default();
        }
        let mut first_of: HashMap<u64, usize> = HashMap::new();
        let mut frame_term = Vec::with_capacity(scene.frames.count);
        let mut distinct = Vec::new();
        for f in 0..scene.frames.count {
            let key = state_key(scene, f);
            let term = *first_of.entry(key).or_insert_with(|| {
                distinct.push(f);
                distinct.len() - 1
            });
            frame_term.push(term);
        }
        let terms = distinct
            .par_iter()
            .map(|&f| frame_irradiance(scene, tracer, f))
            .collect();
        Self { frame_term, terms }
    }

    /// Whether there is any direct light.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.terms.is_empty()
    }

    /// Which distinct state frame `frame` is in: frames with equal states have equal direct
    /// light.
    #[must_use]
    pub fn state(&self, frame: usize) -> Option<usize> {
        self.frame_term.get(frame).copied()
    }

    /// Irradiance of every patch at `frame` (RGB, lux) with the lights at `power` (colour ×
    /// intensity per light, in the scene's order); `None` without lights.
    #[must_use]
    pub fn irradiance(&self, frame: usize, power: &[[f64; 3]]) -> Option<Vec<[f64; 3]>> {
        let per_light = &self.terms[self.state(frame)?];
        let patches = per_light.first().map_or(0, Vec::len);
        let mut out = vec![[0.0; 3]; patches];
        for (unit, p) in per_light.iter().zip(power) {
            for (e, &u) in out.iter_mut().zip(unit) {
                for c in 0..3 {
                    e[c] += p[c] * u;
                }
            }
        }
        Some(out)
    }

    /// Memory held, bytes.
    #[must_use]
    pub fn memory(&self) -> usize {
        self.terms
            .iter()
            .flatten()
            .map(|v| v.len() * 8)
            .sum::<usize>()
            + self.frame_term.len() * std::mem::size_of::<usize>()
    }
}

/// A hash of everything the direct light at `frame` depends on that can change: the poses of
/// the lights and of the moving geometry (its vertices).
fn state_key(scene: &Scene, frame: usize) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for light in &scene.lights {
        light
            .pose(frame)
            .to_cols_array()
            .iter()
            .for_each(|v| v.to_bits().hash(&mut h));
    }
    for object in &scene.objects {
        object
            .positions_at(frame)
            .iter()
            .for_each(|p| p.to_array().map(f32::to_bits).hash(&mut h));
    }
    h.finish()
}

/// Unit irradiance per light and patch at `frame`.
fn frame_irradiance(scene: &Scene, tracer: &SceneTracer, frame: usize) -> Vec<Vec<f64>> {
    let deformed = tracer.deformed_at(scene, frame);
    let triangles = scene.triangles_at(frame);
    let at = Frame {
        scene,
        tracer,
        deformed: &deformed,
        triangles: &triangles,
        frame,
    };
    scene
        .lights
        .iter()
        .map(|light| match light.kind {
            LightKind::Directional => directional(&at, light),
            _ => point(&at, light),
        })
        .collect()
}

/// The scene posed at one frame, ready for shadow rays.
struct Frame<'a> {
    scene: &'a Scene,
    tracer: &'a SceneTracer,
    deformed: &'a FrameMeshes,
    /// Every traced triangle at the frame (index = global triangle id) with its faces.
    triangles: &'a [([Vec3; 3], Faces)],
    frame: usize,
}

impl Frame<'_> {
    /// Whether the patch reflects any light (a black patch needs no direct light).
    fn reflects(&self, patch: u32) -> bool {
        let material = self.scene.patches[patch as usize].material;
        self.scene.materials[material as usize]
            .reflectance
            .iter()
            .any(|&r| r > 0.0)
    }

    /// Whether anything but triangle `own` crosses the segment from `from` to `to`.
    fn blocked(&self, from: DVec3, to: DVec3, own: u32, hits: &mut Vec<Hit>) -> bool {
        let d = to - from;
        let length = d.length();
        let line = Line {
            origin: from.as_vec3(),
            direction: (d / length).as_vec3(),
        };
        self.tracer
            .trace_frame(&line, self.frame, self.deformed, hits);
        let end = length as f32 - SHADOW_EPSILON;
        hits.iter()
            .any(|h| h.t > SHADOW_EPSILON && h.t < end && h.surface() != own)
    }
}

/// The points a patch is sampled at: centroids of the 4^level triangles of `level` midpoint
/// subdivisions.
fn sample_points(corners: [DVec3; 3], level: u32, out: &mut Vec<DVec3>) {
    if level == 0 {
        out.push((corners[0] + corners[1] + corners[2]) / 3.0);
        return;
    }
    let [a, b, c] = corners;
    let (ab, bc, ca) = ((a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5);
    for t in [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]] {
        sample_points(t, level - 1, out);
    }
}

/// Subdivision level for a patch of longest edge `edge` seen from `distance`: one point while
/// the patch looks small from the light, up to 64 when it fills a wide angle.
fn sample_level(edge: f64, distance: f64) -> u32 {
    let ratio = edge / distance.max(f64::MIN_POSITIVE);
    match ratio {
        r if r < 0.05 => 0,
        r if r < 0.25 => 1,
        r if r < 1.0 => 2,
        _ => 3,
    }
}

/// A spot's angular attenuation at `cos_angle` from its axis: the extension's recommended
/// smooth step between the cone angles, squared.
#[must_use]
pub fn spot_attenuation(cos_angle: f64, inner: f64, outer: f64) -> f64 {
    let scale = 1.0 / (inner.cos() - outer.cos()).max(1e-3);
    let offset = -outer.cos() * scale;
    let a = (cos_angle * scale + offset).clamp(0.0, 1.0);
    a * a
}

/// The extension's recommended range window at distance `d` (same units as `range`).
#[must_use]
pub fn range_window(d: f64, range: Option<f64>) -> f64 {
    range.map_or(1.0, |r| (1.0 - (d / r).powi(4)).clamp(0.0, 1.0))
}

/// Unit irradiance per patch from a point or spot light.
fn point(at: &Frame<'_>, light: &Light) -> Vec<f64> {
    let position = light.position(at.frame);
    let axis = light.direction(at.frame);
    let radius = at.scene.normalisation.radius;
    let per_triangle: Vec<[Option<(u32, f64)>; 2]> = at
        .triangles
        .par_iter()
        .enumerate()
        .map_init(Vec::new, |hits, (t, (corners, faces))| {
            let corners = corners.map(|c| c.as_dvec3());
            let normal = (corners[1] - corners[0])
                .cross(corners[2] - corners[0])
                .normalize_or_zero();
            let sides = [(Some(faces.front), normal), (faces.back, -normal)];
            sides.map(|(patch, n)| {
                let patch = patch.filter(|&p| at.reflects(p))?;
                let value = patch_irradiance(at, light, t as u32, corners, n, position, axis, hits);
                Some((patch, value / (radius * radius)))
            })
        })
        .collect();
    let mut out = vec![0.0; at.scene.patches.len()];
    for (patch, value) in per_triangle.into_iter().flatten().flatten() {
        out[patch as usize] = value;
    }
    out
}

/// Mean irradiance over one face of triangle `own` (normal `n`) from a point or spot light at
/// `position`, in units of 1/(normalised distance)²; 0 for a face the light cannot reach.
#[allow(clippy::too_many_arguments)] // one call site; a struct would only rename them
fn patch_irradiance(
    at: &Frame<'_>,
    light: &Light,
    own: u32,
    corners: [DVec3; 3],
    n: DVec3,
    position: DVec3,
    axis: DVec3,
    hits: &mut Vec<Hit>,
) -> f64 {
    // The light behind the face's plane: nothing (exact, the face is flat).
    if n == DVec3::ZERO || (position - corners[0]).dot(n) <= 0.0 {
        return 0.0;
    }
    let centre = (corners[0] + corners[1] + corners[2]) / 3.0;
    let reach = corners
        .iter()
        .map(|c| c.distance(centre))
        .fold(0.0, f64::max);
    let distance = centre.distance(position);
    if let Some(range) = light.range
        && distance - reach >= range
    {
        return 0.0;
    }
    if let LightKind::Spot { outer, .. } = light.kind
        && distance > reach
    {
        // The whole face outside the cone: its bounding sphere's angle from the axis.
        let angle = axis
            .dot((centre - position) / distance)
            .clamp(-1.0, 1.0)
            .acos();
        if angle - (reach / distance).asin() > outer {
            return 0.0;
        }
    }
    let edge = (0..3)
        .map(|k| corners[k].distance(corners[(k + 1) % 3]))
        .fold(0.0, f64::max);
    let mut points = Vec::new();
    sample_points(corners, sample_level(edge, distance), &mut points);
    let mut sum = 0.0;
    for &x in &points {
        let to_light = position - x;
        let d = to_light.length();
        let cos_surface = n.dot(to_light) / d;
        if cos_surface <= 0.0 {
            continue;
        }
        let mut e = cos_surface / (d * d) * range_window(d, light.range);
        if let LightKind::Spot { inner, outer } = light.kind {
            e *= spot_attenuation(axis.dot(-to_light / d), inner, outer);
        }
        if e > 0.0 && !at.blocked(x, position, own, hits) {
            sum += e;
        }
    }
    sum / points.len() as f64
}

/// Unit irradiance per patch from a directional light: one bundle of parallel lines.
fn directional(at: &Frame<'_>, light: &Light) -> Vec<f64> {
    let scene = at.scene;
    let w = light.direction(at.frame);
    let mut out = vec![0.0; scene.patches.len()];
    if w == DVec3::ZERO {
        return out;
    }
    let areas: Vec<f64> = at
        .triangles
        .iter()
        .map(|(c, _)| {
            let [a, b, c] = c.map(|p| p.as_dvec3());
            0.5 * (b - a).cross(c - a).length()
        })
        .collect();
    let mut sorted: Vec<f64> = areas.iter().copied().filter(|&a| a > 0.0).collect();
    if sorted.is_empty() {
        return out;
    }
    sorted.sort_unstable_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    let size = scene.bounds.max - scene.bounds.min;
    let projected =
        w.x.abs() * size.y * size.z + w.y.abs() * size.x * size.z + w.z.abs() * size.x * size.y;
    let cell = (median / LINES_PER_PATCH).max(projected / MAX_DIRECTIONAL_LINES);
    // A fixed grid offset: equal frames get equal light.
    let bundle = parallel_bundle(w, cell, (0.5, 0.5), &scene.bounds);
    let first: Vec<Option<u32>> = bundle
        .origins
        .par_iter()
        .map_init(Vec::new, |hits, &origin| {
            let line = Line {
                origin,
                direction: bundle.direction,
            };
            at.tracer.trace_frame(&line, at.frame, at.deformed, hits);
            let hit = hits.first()?;
            let faces = at.triangles[hit.surface() as usize].1;
            let patch = if hit.front() {
                Some(faces.front)
            } else {
                faces.back
            }?;
            at.reflects(patch).then_some(patch)
        })
        .collect();
    let faces_area: Vec<f64> = {
        let mut a = vec![0.0; scene.patches.len()];
        for ((_, faces), &area) in at.triangles.iter().zip(&areas) {
            a[faces.front as usize] = area;
            if let Some(b) = faces.back {
                a[b as usize] = area;
            }
        }
        a
    };
    for patch in first.into_iter().flatten() {
        out[patch as usize] += cell;
    }
    for (e, &area) in out.iter_mut().zip(&faces_area) {
        *e = if area > 0.0 { *e / area } else { 0.0 };
    }
    out
}
