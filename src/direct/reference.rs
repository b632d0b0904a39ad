//! A path-traced reference to judge the solver against physics rather than against itself
//! (METHOD.md §10; issue 13): per patch, the area average of the true outgoing radiance,
//! `L̄_i = Le_i + (ρ_i/π) Ē_i`, with `Ē_i` the mean irradiance over the patch estimated from
//! uniformly random points on it. Points where a surface touches the patch (under a box on the
//! floor) are drawn again: the mean is over what can be seen of the patch, as the bake answers,
//! and [`Estimate::visible`] says how much that is.
//!
//! At each point the irradiance is estimated from two samples, combined by multiple importance
//! sampling (the balance heuristic): next-event estimation alone has infinite variance where an
//! emitter meets the receiver at a corner (`1/r²`), cosine sampling alone misses small bright
//! emitters.
//! - **Next-event estimation**: one emitting patch picked in proportion to its area times its
//!   brightest channel, one uniform point on it, one shadow ray.
//! - **The path**: one cosine-weighted direction; the first surface it meets gives its
//!   emission (weighted against next-event estimation's density of the same direction) and
//!   reflects `ρ` times its own irradiance, estimated the same way on from there; the sky gives
//!   `π·L_sky`; the back of a one-sided face absorbs. Russian roulette from the third bounce,
//!   surviving with the largest reflectance.
//!
//! Every estimate is unbiased for the radiance of the continuous scene, not of a discretisation
//! of it, which is the point: no patch-constant model, no contact or leak the solver's tallies
//! share. Each patch's standard error is its samples' spread.
//!
//! Punctual lights (`KHR_lights_punctual`) cannot be hit by a path: at every vertex of a path
//! each adds its exact irradiance there (`I·cos θ / d²` with the spot's cone and the range's
//! window for point and spot lights, `E⊥·cos θ` for directional ones), behind one shadow ray;
//! the same per-point value [`super::DirectLight`] averages over its sample points.

use glam::DVec3;
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;

use super::points::{
    PointRadiance, Points, Probe, Site, kernel, sh_basis, site_point, site_seed, sphere_direction,
};
use super::{
    Frame, Occluders, Posed, inset, into_inset, range_window, spot_attenuation, triangle_point,
};
use crate::lines::LINE_LENGTH;
use crate::scene::subdivide::normal_and_area;
use crate::scene::{LightKind, Scene};
use crate::trace::coincident::{COINCIDENT, resolve};
use crate::trace::{Hit, Line, SceneTracer};

/// The reference radiance of one patch.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    /// Area-mean outgoing radiance, RGB.
    pub radiance: [f64; 3],
    /// Its standard error.
    pub stderr: [f64; 3],
    /// The variance of the true radiance over the patch's points (an unbiased estimate, which
    /// may come out below zero when the patch is nearly uniform): what one radiance per patch
    /// cannot show, however exact.
    pub spread: [f64; 3],
    /// The share of the patch's area that no surface touches (its points not under a box on
    /// the floor): the estimate is the mean over that part, what can be seen of the patch.
    pub visible: f64,
}

/// One emitting face, for next-event estimation.
struct Emitter {
    /// Its place.
    place: usize,
    corners: [DVec3; 3],
    /// Unit normal on its emitting side.
    normal: DVec3,
    area: f64,
    emission: [f64; 3],
    /// Cumulative pick probability up to and including this one.
    cumulative: f64,
    /// Its own pick probability.
    probability: f64,
}

impl Emitter {
    /// What a sample of this emitter's light in a direction at `cos_x` from the receiver's
    /// normal, `cos_y` from the emitter's and `r2` away adds to the irradiance per unit of
    /// emission, by the balance heuristic: `cos_x / (p_light + p_cosine)`, with both densities
    /// of the direction per solid angle (the pick of a point on this emitter, and the cosine
    /// sampling's `cos_x/π`). The same whichever sampled it.
    fn weight(&self, cos_x: f64, cos_y: f64, r2: f64) -> f64 {
        let p_light = self.probability / self.area * r2 / cos_y;
        let p_cosine = cos_x * std::f64::consts::FRAC_1_PI;
        cos_x / (p_light + p_cosine)
    }
}

/// Where a face lies: its triangle (global id), the side, its corners and the unit normal on
/// its side, at one frame.
pub(super) struct Place {
    pub(super) triangle: u32,
    pub(super) back: bool,
    pub(super) corners: [DVec3; 3],
    pub(super) normal: DVec3,
}

/// The path-traced reference of every patch at `frame`, from `paths` paths per patch (in pairs
/// from `paths / 2` uniform points, see [`Estimate::spread`]), with
/// `sky` the radiance of everything outside the scene. Deterministic for a seed.
pub fn path_traced(
    scene: &Scene,
    tracer: &SceneTracer,
    frame: usize,
    paths: usize,
    sky: [f64; 3],
    seed: u64,
) -> Vec<Estimate> {
    path_traced_each(scene, tracer, frame, &|_| paths, sky, seed)
}

/// [`path_traced`] with `paths(i)` paths for patch `i` (none: a patch of 0 paths answers
/// nothing, all zeros).
#[must_use]
pub fn path_traced_each(
    scene: &Scene,
    tracer: &SceneTracer,
    frame: usize,
    paths: &(dyn Fn(usize) -> usize + Sync),
    sky: [f64; 3],
    seed: u64,
) -> Vec<Estimate> {
    with_tracer((scene, tracer, frame, sky), |tracer| {
        (0..scene.patches.len())
            .into_par_iter()
            .map(|i| {
                let mut rng = Xoshiro256PlusPlus::seed_from_u64(
                    seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
                );
                match paths(i) {
                    0 => Estimate {
                        radiance: [0.0; 3],
                        stderr: [0.0; 3],
                        spread: [0.0; 3],
                        visible: 0.0,
                    },
                    n => tracer.patch(i, n.max(2), &mut rng),
                }
            })
            .collect()
    })
}

/// The path-traced reference at `points` at `frame`: each site's outgoing radiance at its
/// point ([`super::points`], the same point the bake's outputs are evaluated at) from
/// `paths` times its weight paths (at least 2), the point's the sites' weighted mean, with
/// its standard error. A point a surface touches gets its emission alone.
#[must_use]
pub fn path_traced_points(
    (scene, tracer, frame): (&Scene, &SceneTracer, usize),
    points: &Points,
    paths: usize,
    sky: [f64; 3],
    seed: u64,
) -> Vec<PointRadiance> {
    with_tracer((scene, tracer, frame, sky), |tracer| {
        (0..points.len())
            .into_par_iter()
            .map_init(Vec::new, |hits, i| {
                let (mut radiance, mut variance) = ([0.0; 3], [0.0; 3]);
                for site in points.point(i) {
                    let (l, v) = tracer.site(site, paths, seed, hits);
                    for c in 0..3 {
                        radiance[c] += site.weight * l[c];
                        variance[c] += site.weight * site.weight * v[c];
                    }
                }
                PointRadiance {
                    radiance,
                    stderr: variance.map(f64::sqrt),
                    ..PointRadiance::default()
                }
            })
            .collect()
    })
}

/// The path-traced reference of light probes at `positions` (normalised space, on no surface)
/// at `frame`: each probe's coefficients ([`super::points::sh_basis`]) from `rays` directions
/// uniform over the sphere, each reading the radiance arriving along it (the emission of the
/// surface it meets, and the light that surface reflects, estimated as a patch's point's is);
/// the punctual lights exactly. Each coefficient's standard error is its rays' spread.
#[must_use]
pub fn path_traced_probes(
    (scene, tracer, frame): (&Scene, &SceneTracer, usize),
    positions: &[DVec3],
    rays: usize,
    sky: [f64; 3],
    seed: u64,
) -> Vec<Probe> {
    with_tracer((scene, tracer, frame, sky), |tracer| {
        (positions.par_iter().enumerate())
            .map_init(Vec::new, |hits, (i, &x)| {
                let mut rng = Xoshiro256PlusPlus::seed_from_u64(
                    seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
                );
                tracer.probe(x, rays.max(2), &mut rng, hits)
            })
            .collect()
    })
}

/// Runs `f` with the path tracer of `scene` posed at `frame` under `sky`.
fn with_tracer<R>(
    (scene, tracer, frame, sky): (&Scene, &SceneTracer, usize, [f64; 3]),
    f: impl FnOnce(&Tracer<'_>) -> R,
) -> R {
    let posed = Posed::at(scene, tracer, frame);
    let view = posed.frame(scene, tracer, Occluders::All);
    let (places, members) = places(scene, &view);
    let emitters = emitters(scene, &view, &places);
    let mut emitter_of = vec![None; places.len()];
    for (k, e) in emitters.iter().enumerate() {
        emitter_of[e.place] = Some(k);
    }
    let power: Vec<[f64; 3]> = scene
        .lights
        .iter()
        .map(crate::scene::Light::power)
        .collect();
    f(&Tracer {
        scene,
        view: &view,
        sight: Sight::new(scene, &view, frame, &power),
        places: &places,
        members: &members,
        emitters: &emitters,
        emitter_of,
        sky,
    })
}

/// A punctual light as posed at the frame.
struct Punctual {
    kind: LightKind,
    position: DVec3,
    /// Unit direction it travels in (spot's axis, directional's rays).
    direction: DVec3,
    /// Colour × intensity.
    power: [f64; 3],
    /// Range, normalised units.
    range: Option<f64>,
}

/// Every face's place at the frame (face `2t + back` of triangle `t`; a face no patch covers
/// has triangle `u32::MAX`), and each patch's faces with their cumulative share of its area
/// (one face, or several merged by [`crate::scene::refine::merge`]).
pub(super) fn places(scene: &Scene, view: &Frame<'_>) -> (Vec<Place>, Vec<Vec<(usize, f64)>>) {
    let mut places = Vec::with_capacity(2 * view.triangles.len());
    let mut members: Vec<Vec<(usize, f64)>> = vec![Vec::new(); scene.patches.len()];
    for (t, (corners, faces)) in view.triangles.iter().enumerate() {
        let corners = corners.map(|c| c.as_dvec3());
        let (normal, area) = normal_and_area(corners);
        for (patch, back) in [(Some(faces.front), false), (faces.back, true)] {
            if let Some(p) = patch {
                members[p as usize].push((places.len(), area));
            }
            places.push(Place {
                triangle: if patch.is_some() { t as u32 } else { u32::MAX },
                back,
                corners,
                normal: if back { -normal } else { normal },
            });
        }
    }
    for faces in &mut members {
        let total: f64 = faces.iter().map(|f| f.1).sum();
        let mut sum = 0.0;
        for f in faces.iter_mut() {
            sum += f.1;
            f.1 = if total > 0.0 { sum / total } else { 1.0 };
        }
    }
    (places, members)
}

/// The emitting faces, with their pick probabilities (area × brightest channel).
fn emitters(scene: &Scene, view: &Frame<'_>, places: &[Place]) -> Vec<Emitter> {
    let mut out: Vec<Emitter> = places
        .iter()
        .enumerate()
        .filter_map(|(k, place)| {
            let faces = view.triangles.get(place.triangle as usize)?.1;
            let patch = if place.back { faces.back? } else { faces.front };
            let emission =
                scene.materials[scene.patches[patch as usize].material as usize].emission;
            let area = 0.5
                * (place.corners[1] - place.corners[0])
                    .cross(place.corners[2] - place.corners[0])
                    .length();
            (emission.iter().any(|&e| e > 0.0) && area > 0.0).then_some(Emitter {
                place: k,
                corners: place.corners,
                normal: place.normal,
                area,
                emission,
                cumulative: area * emission.iter().fold(0.0f64, |m, &e| m.max(e)),
                probability: 0.0,
            })
        })
        .collect();
    let mut sum = 0.0;
    for e in &mut out {
        sum += e.cumulative;
        e.cumulative = sum;
    }
    let mut before = 0.0;
    for e in &mut out {
        e.cumulative /= sum;
        e.probability = e.cumulative - before;
        before = e.cumulative;
    }
    out
}

/// What a ray meets first.
pub(super) enum Met {
    /// Nothing: it leaves the scene.
    Sky,
    /// The back of a one-sided face, which absorbs.
    Nothing,
    /// A face (its place) of a patch, at this distance.
    Patch(usize, usize, f64),
}

/// How many times its pairs a patch's points are drawn at most, covered points drawn again
/// ([`Tracer::patch`]): a patch three quarters under a box still gets all its paths.
const COVERED_DRAWS: usize = 4;

/// Bounces after which Russian roulette starts.
const ROULETTE: usize = 2;
/// Bounces after which a path stops whatever: at reflectance 0.999 the light left after them
/// is 0.999^100000 ≈ 4e-44 of it.
const MAX_BOUNCES: usize = 100_000;

struct Tracer<'a> {
    scene: &'a Scene,
    view: &'a Frame<'a>,
    /// What a point sees: the punctual lights and the first surface along a ray.
    sight: Sight<'a>,
    places: &'a [Place],
    /// Per patch, its faces' places with their cumulative share of its area.
    members: &'a [Vec<(usize, f64)>],
    emitters: &'a [Emitter],
    /// Per face's place, its index among the emitters.
    emitter_of: Vec<Option<usize>>,
    sky: [f64; 3],
}

/// What a point of the scene posed at one frame sees: the first surface along a ray, and the
/// punctual lights' exact irradiance (shared by the reference and by the final gather at the
/// outputs' points, [`super::points`]).
pub(super) struct Sight<'a> {
    pub(super) scene: &'a Scene,
    pub(super) view: &'a Frame<'a>,
    /// The punctual lights, posed.
    punctual: Vec<Punctual>,
}

impl<'a> Sight<'a> {
    /// The sight of `view`, the scene posed at `frame`, with the punctual lights at `power`
    /// (colour × intensity, in the scene's order).
    pub(super) fn new(
        scene: &'a Scene,
        view: &'a Frame<'a>,
        frame: usize,
        power: &[[f64; 3]],
    ) -> Self {
        let punctual = (scene.lights.iter().zip(power))
            .map(|(light, &power)| Punctual {
                kind: light.kind,
                position: light.position(frame),
                direction: light.direction(frame),
                power,
                range: light.range,
            })
            .collect();
        Self {
            scene,
            view,
            punctual,
        }
    }

    /// The irradiance at `x` (on `place`) from the punctual lights, shadows included.
    pub(super) fn punctual(&self, x: DVec3, place: &Place, hits: &mut Vec<Hit>) -> [f64; 3] {
        let mut total = [0.0; 3];
        // Point and spot lights' intensities are per square metre at a metre: distances in
        // normalised units are `radius` metres each.
        let radius = self.scene.normalisation.radius;
        for light in &self.punctual {
            let e = match light.kind {
                LightKind::Directional => {
                    let cos = -place.normal.dot(light.direction);
                    if cos <= 0.0 {
                        continue;
                    }
                    match self.first_hit(x, -light.direction, place, hits) {
                        Met::Sky => cos,
                        _ => continue,
                    }
                }
                LightKind::Point | LightKind::Spot { .. } => {
                    let to_light = light.position - x;
                    let d = to_light.length();
                    let cos = place.normal.dot(to_light) / d;
                    if d <= 0.0 || cos <= 0.0 {
                        continue;
                    }
                    let mut e = cos / (d * d) * range_window(d, light.range);
                    if let LightKind::Spot { inner, outer } = light.kind {
                        e *= spot_attenuation(light.direction.dot(-to_light / d), inner, outer);
                    }
                    if e <= 0.0
                        || self
                            .view
                            .blocked(x, light.position, place.triangle, place.back)
                    {
                        continue;
                    }
                    e / (radius * radius)
                }
            };
            (0..3).for_each(|c| total[c] += e * light.power[c]);
        }
        total
    }

    /// The light of each punctual light that reaches `x`, a point on no surface (a light
    /// probe's): the unit direction it arrives from, and its irradiance on a plane facing it
    /// (`I/d²` with the spot's cone and the range's window, `E⊥` for a directional light),
    /// behind one shadow ray.
    pub(super) fn punctual_toward(&self, x: DVec3, hits: &mut Vec<Hit>) -> Vec<(DVec3, [f64; 3])> {
        let radius = self.scene.normalisation.radius;
        let mut out = Vec::new();
        for light in &self.punctual {
            let (w, e) = match light.kind {
                LightKind::Directional => match self.free_hit(x, -light.direction, hits) {
                    Met::Sky => (-light.direction, 1.0),
                    _ => continue,
                },
                LightKind::Point | LightKind::Spot { .. } => {
                    let to_light = light.position - x;
                    let d = to_light.length();
                    if d <= 0.0 {
                        continue;
                    }
                    let mut e = range_window(d, light.range) / (d * d);
                    if let LightKind::Spot { inner, outer } = light.kind {
                        e *= spot_attenuation(light.direction.dot(-to_light / d), inner, outer);
                    }
                    if e <= 0.0 || self.view.blocked_between(x, light.position) {
                        continue;
                    }
                    (to_light / d, e / (radius * radius))
                }
            };
            out.push((w, light.power.map(|p| p * e)));
        }
        out
    }

    /// Each punctual light's position (`None` for a directional light) and direction, posed.
    pub(super) fn lights(&self) -> impl Iterator<Item = (Option<DVec3>, DVec3)> + '_ {
        self.punctual.iter().map(|light| {
            let position = (light.kind != LightKind::Directional).then_some(light.position);
            (position, light.direction)
        })
    }

    /// What the ray from `x` (on `place`) along unit `w` meets first.
    pub(super) fn first_hit(&self, x: DVec3, w: DVec3, place: &Place, hits: &mut Vec<Hit>) -> Met {
        self.first_hit_within(x, w, place, hits, f64::INFINITY)
    }

    /// [`Sight::first_hit`] among the surfaces within `reach` of `x` (normalised units): the
    /// sky beyond.
    pub(super) fn first_hit_within(
        &self,
        x: DVec3,
        w: DVec3,
        place: &Place,
        hits: &mut Vec<Hit>,
        reach: f64,
    ) -> Met {
        let behind = f64::from(4.0 * COINCIDENT);
        let line = Line {
            origin: (x - w * behind).as_vec3(),
            direction: w.as_vec3(),
        };
        let t_max = (behind + reach + f64::from(COINCIDENT)).min(f64::from(LINE_LENGTH));
        self.view.trace_until(&line, t_max as f32, hits);
        let start = behind as f32 + COINCIDENT;
        // A surface touching the point's face (a contact: a box resting on the floor) meets
        // the ray where it starts: nothing gets through (as for the lines and shadow rays).
        let surfaces = self.view.tracer.surfaces();
        if hits.iter().any(|&h| {
            h.surface() != place.triangle
                && (h.t - behind as f32).abs() <= COINCIDENT
                && surfaces.touching(place.triangle, place.back, h)
        }) {
            return Met::Nothing;
        }
        // The crossings past the point's own, coincident ones as the lines resolve them:
        // where two surfaces touch (a box on the floor), the ray meets the one it arrives in
        // first, never the floor's lit face from inside the box. (The point's own crossing is
        // left out first: along a ray that grazes its face, it and a wall meeting the face
        // would be taken for one seam.)
        hits.retain(|h| h.t > start && h.surface() != place.triangle);
        self.first_of(hits, line.direction, behind)
    }

    /// What the ray from `x`, a point on no surface (a light probe's), along unit `w` meets
    /// first.
    pub(super) fn free_hit(&self, x: DVec3, w: DVec3, hits: &mut Vec<Hit>) -> Met {
        let behind = f64::from(4.0 * COINCIDENT);
        let line = Line {
            origin: (x - w * behind).as_vec3(),
            direction: w.as_vec3(),
        };
        self.view.trace_until(&line, LINE_LENGTH, hits);
        hits.retain(|h| f64::from(h.t) > behind);
        self.first_of(hits, line.direction, behind)
    }

    /// The first of `hits`, the crossings of a line along `direction` that starts `behind`
    /// the point a ray leaves, as the lines resolve coincident crossings.
    fn first_of(&self, hits: &mut [Hit], direction: glam::Vec3, behind: f64) -> Met {
        let surfaces = self.view.tracer.surfaces();
        let resolved = resolve(hits, &surfaces.along(direction));
        let Some(hit) = resolved.as_deref().unwrap_or(hits).first() else {
            return Met::Sky;
        };
        let faces = self.view.triangles[hit.surface() as usize].1;
        let (patch, back) = if hit.front() {
            (Some(faces.front), false)
        } else {
            (faces.back, true)
        };
        match patch {
            Some(patch) => Met::Patch(
                2 * hit.surface() as usize + usize::from(back),
                patch as usize,
                f64::from(hit.t) - behind,
            ),
            None => Met::Nothing,
        }
    }
}

impl Tracer<'_> {
    /// Patch i's estimate from `paths` paths.
    fn patch(&self, i: usize, paths: usize, rng: &mut Xoshiro256PlusPlus) -> Estimate {
        let material = &self.scene.materials[self.scene.patches[i].material as usize];
        let members = &self.members[i];
        if members.is_empty() || material.reflectance == [0.0; 3] {
            return Estimate {
                radiance: material.emission,
                stderr: [0.0; 3],
                spread: [0.0; 3],
                visible: 1.0,
            };
        }
        let faces: Vec<(&Place, [DVec3; 3])> = members
            .iter()
            .map(|&(k, _)| (&self.places[k], inset(&self.places[k].corners)))
            .collect();
        let mut hits = Vec::new();
        // Paths in pairs from one point: the pairs' means are independent samples of the
        // area mean, and the two paths of a pair differ only by the paths' own noise, which
        // tells the spread of the true radiance over the patch from the noise.
        let pairs = (paths / 2).max(2);
        let (mut sum, mut sum_sq, mut apart) = ([0.0; 3], [0.0; 3], [0.0; 3]);
        // Points where a surface touches the patch (under a box on the floor) are nobody's to
        // see: drawn again, up to COVERED_DRAWS times the pairs, so that the estimate is the
        // mean over the patch's visible part, what the bake answers.
        let (mut n, mut draws) = (0usize, 0usize);
        while n < pairs && draws < COVERED_DRAWS * pairs {
            draws += 1;
            // A face picked by area (no draw for a patch of one face), a point on it.
            let k = if faces.len() == 1 {
                0
            } else {
                let u: f64 = rng.random();
                members.partition_point(|f| f.1 < u).min(faces.len() - 1)
            };
            let (place, corners) = faces[k];
            let x = triangle_point(&corners, rng.random(), rng.random());
            let face = (place.triangle, place.back);
            if self.view.covered(x, place.normal, face) {
                continue;
            }
            n += 1;
            let e = [0, 1].map(|_| self.irradiance(x, place, rng, &mut hits));
            for c in 0..3 {
                let l = e.map(|e| material.reflectance[c] * e[c] * std::f64::consts::FRAC_1_PI);
                let mean = 0.5 * (l[0] + l[1]);
                sum[c] += mean;
                sum_sq[c] += mean * mean;
                apart[c] += (l[0] - l[1]) * (l[0] - l[1]);
            }
        }
        let visible = n as f64 / draws as f64;
        if n < 2 {
            // Covered all over (or nearly): black, as the bake answers a patch a box hides.
            return Estimate {
                radiance: material.emission,
                stderr: [0.0; 3],
                spread: [0.0; 3],
                visible,
            };
        }
        let n = n as f64;
        // Variance of a pair's mean over points and paths (unbiased).
        let variance: [f64; 3] = std::array::from_fn(|c| {
            let mean = sum[c] / n;
            (sum_sq[c] - n * mean * mean).max(0.0) / (n - 1.0)
        });
        Estimate {
            radiance: std::array::from_fn(|c| material.emission[c] + sum[c] / n),
            stderr: variance.map(|v| (v / n).sqrt()),
            // Var(pair mean) = W + σ²/2 and E[(l₀ − l₁)²] = 2σ², σ² the paths' noise at a
            // point: W = Var(pair mean) − E[(l₀ − l₁)²] / 4.
            spread: std::array::from_fn(|c| variance[c] - apart[c] / n / 4.0),
            visible,
        }
    }

    /// The radiance at `site`'s point from `paths × weight` paths (at least 2), and the
    /// variance of that mean.
    fn site(
        &self,
        site: &Site,
        paths: usize,
        seed: u64,
        hits: &mut Vec<Hit>,
    ) -> ([f64; 3], [f64; 3]) {
        let place = &self.places[2 * site.triangle as usize + usize::from(site.back)];
        let faces = self.view.triangles[site.triangle as usize].1;
        let patch = if site.back {
            faces.back
        } else {
            Some(faces.front)
        };
        let Some(patch) = patch else {
            return ([0.0; 3], [0.0; 3]);
        };
        let material = &self.scene.materials[self.scene.patches[patch as usize].material as usize];
        let x = site_point(site, place);
        let own = (place.triangle, place.back);
        if material.reflectance == [0.0; 3] || self.view.covered(x, place.normal, own) {
            return (material.emission, [0.0; 3]);
        }
        let n = ((paths as f64 * site.weight).round() as usize).max(2);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(site_seed(seed, site));
        let (mut sum, mut squares) = ([0.0; 3], [0.0; 3]);
        for _ in 0..n {
            let e = self.irradiance(x, place, &mut rng, hits);
            for c in 0..3 {
                let l = material.reflectance[c] * e[c] * std::f64::consts::FRAC_1_PI;
                sum[c] += l;
                squares[c] += l * l;
            }
        }
        let n = n as f64;
        (
            std::array::from_fn(|c| material.emission[c] + sum[c] / n),
            std::array::from_fn(|c| {
                let mean = sum[c] / n;
                (squares[c] - n * mean * mean).max(0.0) / (n - 1.0) / n
            }),
        )
    }

    /// The probe at `x` from `rays` uniform directions ([`path_traced_probes`]).
    fn probe(
        &self,
        x: DVec3,
        rays: usize,
        rng: &mut Xoshiro256PlusPlus,
        hits: &mut Vec<Hit>,
    ) -> Probe {
        let mut sh = [[0.0; 3]; 9];
        for (w, e) in self.sight.punctual_toward(x, hits) {
            let y = sh_basis(w);
            (0..9).for_each(|k| (0..3).for_each(|c| sh[k][c] += e[c] * y[k]));
        }
        let (mut sum, mut squares) = ([[0.0; 3]; 15], [[0.0; 3]; 15]);
        for _ in 0..rays {
            let w = sphere_direction(rng.random(), rng.random());
            let l = self.arriving(x, w, rng, hits);
            let y = kernel(w);
            for k in 0..15 {
                for c in 0..3 {
                    let f = 4.0 * std::f64::consts::PI * l[c] * y[k];
                    sum[k][c] += f;
                    squares[k][c] += f * f;
                }
            }
        }
        let n = rays as f64;
        let error = |k: usize| -> [f64; 3] {
            std::array::from_fn(|c| {
                let mean = sum[k][c] / n;
                ((squares[k][c] - n * mean * mean).max(0.0) / (n - 1.0) / n).sqrt()
            })
        };
        Probe {
            sh: std::array::from_fn(|k| std::array::from_fn(|c| sh[k][c] + sum[k][c] / n)),
            stderr: std::array::from_fn(error),
            axes_stderr: std::array::from_fn(|a| error(9 + a)),
            inside: false,
        }
    }

    /// One estimate of the radiance arriving at `x`, on no surface, from direction `-w`: what
    /// the ray along `w` meets emits and reflects.
    fn arriving(
        &self,
        x: DVec3,
        w: DVec3,
        rng: &mut Xoshiro256PlusPlus,
        hits: &mut Vec<Hit>,
    ) -> [f64; 3] {
        let (face, patch, t) = match self.sight.free_hit(x, w, hits) {
            Met::Sky => return self.sky,
            Met::Nothing => return [0.0; 3],
            Met::Patch(face, patch, t) => (face, patch, t),
        };
        let material = &self.scene.materials[self.scene.patches[patch].material as usize];
        let place = &self.places[face];
        if material.reflectance == [0.0; 3] {
            return material.emission;
        }
        let y = into_inset(x + w * t, &place.corners);
        let e = self.irradiance(y, place, rng, hits);
        std::array::from_fn(|c| {
            material.emission[c] + material.reflectance[c] * e[c] * std::f64::consts::FRAC_1_PI
        })
    }

    /// An estimate of the irradiance at `x` on `place` (module docs).
    fn irradiance(
        &self,
        x: DVec3,
        place: &Place,
        rng: &mut Xoshiro256PlusPlus,
        hits: &mut Vec<Hit>,
    ) -> [f64; 3] {
        let (mut x, mut place) = (x, place);
        let mut total = [0.0; 3];
        let mut throughput = [1.0; 3];
        for bounce in 0..MAX_BOUNCES {
            let direct = self.next_event(x, place, rng);
            let punctual = self.sight.punctual(x, place, hits);
            (0..3).for_each(|c| total[c] += throughput[c] * (direct[c] + punctual[c]));
            // A cosine-weighted direction: the irradiance is π times the mean radiance coming
            // in along it.
            let w = cosine_direction(place.normal, rng);
            let (face, patch, t) = match self.sight.first_hit(x, w, place, hits) {
                Met::Sky => {
                    (0..3).for_each(|c| {
                        total[c] += throughput[c] * std::f64::consts::PI * self.sky[c];
                    });
                    break;
                }
                Met::Nothing => break,
                Met::Patch(face, patch, t) => (face, patch, t),
            };
            if let Some(k) = self.emitter_of[face] {
                // Its emission, weighted against next-event estimation's density of the same
                // direction ([`Emitter::weight`]).
                let light = &self.emitters[k];
                let cos_y = -light.normal.dot(w);
                let cos_x = place.normal.dot(w);
                if cos_y > 0.0 && cos_x > 0.0 {
                    let g = light.weight(cos_x, cos_y, t * t);
                    (0..3).for_each(|c| total[c] += throughput[c] * light.emission[c] * g);
                }
            }
            let rho = self.scene.materials[self.scene.patches[patch].material as usize].reflectance;
            let survive = if bounce >= ROULETTE {
                rho.iter().fold(0.0f64, |m, &r| m.max(r)).min(1.0)
            } else {
                1.0
            };
            if rho == [0.0; 3] || rng.random::<f64>() >= survive {
                break;
            }
            (0..3).for_each(|c| throughput[c] *= rho[c] / survive);
            place = &self.places[face];
            // The next point kept 8·COINCIDENT inside its patch's edges, as the first is (see
            // [`inset`]): a ray from a point a hair from a corner would meet the wall across it
            // inside the window where crossings are taken for its own surface, and escape.
            x = into_inset(x + w * t, &place.corners);
        }
        total
    }

    /// One next-event sample of the irradiance at `x` from the emitting patches.
    fn next_event(&self, x: DVec3, place: &Place, rng: &mut Xoshiro256PlusPlus) -> [f64; 3] {
        if self.emitters.is_empty() {
            return [0.0; 3];
        }
        let u: f64 = rng.random();
        let k = self
            .emitters
            .partition_point(|e| e.cumulative < u)
            .min(self.emitters.len() - 1);
        let light = &self.emitters[k];
        let y = triangle_point(&light.corners, rng.random(), rng.random());
        let d = y - x;
        let r2 = d.length_squared();
        if r2 <= 0.0 {
            return [0.0; 3];
        }
        let w = d / r2.sqrt();
        let (cos_x, cos_y) = (place.normal.dot(w), -light.normal.dot(w));
        if cos_x <= 0.0 || cos_y <= 0.0 {
            return [0.0; 3];
        }
        if self.view.blocked(x, y, place.triangle, place.back) {
            return [0.0; 3];
        }
        let g = light.weight(cos_x, cos_y, r2);
        light.emission.map(|le| le * g)
    }
}

/// A direction about unit `n` with density cos θ / π.
fn cosine_direction(n: DVec3, rng: &mut Xoshiro256PlusPlus) -> DVec3 {
    cosine_direction_at(n, rng.random(), rng.random())
}

/// The direction about unit `n` at `(u, v)` in the unit square, mapped so that uniform `(u, v)`
/// give density cos θ / π (equal areas of the square, equal shares of the cosine-weighted
/// hemisphere: a grid of strata in the square stratifies the hemisphere).
pub(super) fn cosine_direction_at(n: DVec3, u: f64, v: f64) -> DVec3 {
    let r = u.sqrt();
    let phi = 2.0 * std::f64::consts::PI * v;
    let (a, b) = n.any_orthonormal_pair();
    (a * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - u).sqrt()).normalize()
}
