//! Radiance at points: what the outputs people look at show (the baked glTF's vertices; lightmap
//! texels next), each value evaluated at its own point rather than averaged from the patches
//! around it (issue 46), the way production radiosity renders a solution:
//!
//! `L(x) = Le + (ρ/π) (E_direct(x) + E_gathered(x))`
//!
//! - **Direct light at the point.** Each punctual light exactly (`I·cos θ/d²` behind one shadow
//!   ray, [`Sight::punctual`]); each emitter the bake samples as an area light
//!   ([`super::area`]) by its unoccluded form factor in closed form (Lambert's formula) times
//!   the share of it `g × g` stratified shadow rays get through ([`super::area::Seen`]): exact
//!   where no static triangle is in the volume between the point and the emitter (found by a
//!   walk of the BVH, no ray traced) and where every ray or none gets through; noisy only in a
//!   penumbra. Contact shadows, penumbrae and the edge of a light are resolved at the point,
//!   not averaged over a patch.
//! - **The rest gathered from the solution** (a final gather): stratified cosine-weighted rays
//!   from the point, each reading the solved radiance of the patch it meets first, less the
//!   emission of the sampled emitters (their light is the direct term above: nothing is counted
//!   twice), or the sky's if it leaves the scene; the back of a one-sided face absorbs. A ray
//!   that lands nearer than its patch's size (a corner, a gap) reads the light where it lands
//!   instead, followed on ([`NEAR_BOUNCES`]); more batches of rays while they leave the
//!   value uncertain ([`GATHER_PRECISION`]).
//!
//! Frames (the multiframe method at the points): at a static point, a ray whose whole path stays
//! clear of where the moving objects go over the timeline is kept as a linear form of the
//! solution, and the direct light likewise; the other rays keep their first static crossing and
//! trace only the moving objects at each frame ([`GatherCache`]).
//!
//! A point where a surface touches its face (under a box resting on the floor) gets no light.
//! A point sits a hair inside its face ([`super::into_inset`]), so that rays from a vertex do
//! not start on the edges through it; an output vertex is the weighted mean of its **sites**,
//! one per face around it on its side of a crease (each face's corner angle its weight): the
//! mean of the light over a tiny disc about the vertex, which is the light at the vertex where
//! the light is continuous and the mean of the two sides where a shadow's or a contact's edge
//! runs through it.
//!
//! Each value carries its standard error: the sampling's (pairs of neighbouring strata, as the
//! bake's direct light) in quadrature, plus the error of the patches the gather read, taken as
//! wholly correlated between them (the mean of their error bars, added linearly: the patches of
//! one neighbourhood share their lines' noise). The directions at a point are the same at every
//! frame (its seed does not depend on the frame): a still surface does not flicker between
//! frames whose light is the same.

use glam::DVec3;
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;

mod probes;

pub use probes::{AXES, COSINE_LOBE, PROBE_GATHER_RAYS, Probe, inside, probes_at, reach, sh_basis};
pub(super) use probes::{kernel, sphere_direction};

use super::area::{AreaLights, PointRays, Seen, point_form_factor, point_grid};
use super::reference::{Met, Place, Sight, cosine_direction_at, places};
use super::{Occluders, Posed, into_inset, strata};
use crate::scene::{Material, Scene};
use crate::trace::coincident::mix;
use crate::trace::{Hit, SceneTracer};

/// A point on one face of a traced triangle, with its share of an output point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Site {
    /// The traced triangle (global index: the static triangles first, then each object's).
    pub triangle: u32,
    /// Whether the point is on the triangle's back face.
    pub back: bool,
    /// The point in barycentric coordinates of the triangle's corners: it moves with the
    /// triangle.
    pub bary: [f64; 3],
    /// Its share of the output point's value (the shares of a point sum to 1).
    pub weight: f64,
}

/// A corner of a face of the scene as drawn (a patch's own triangles, [`crate::bake::Bake::shown`]),
/// around an output vertex: where the vertex's light is evaluated
/// ([`crate::bake::Bake::points_at_corners`] places it on the traced triangles).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Corner {
    /// The triangle (global index in the scene drawn: the static triangles first, then each
    /// object's).
    pub triangle: u32,
    /// Whether it is the triangle's back face.
    pub back: bool,
    /// Which of the triangle's corners (in the triangle's own order).
    pub corner: u8,
    /// The face's angle at the corner, radians: its share of the light about the vertex.
    pub angle: f64,
}

/// How far towards its face's centroid a corner's point is taken, as a share of the way: a
/// vertex's light is its faces' limit at the vertex, not at the vertex itself, where rays
/// would start on the edges of every face around it.
pub const NEAR_CORNER: f64 = 1e-3;

/// Output points, each a weighted set of [`Site`]s.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Points {
    /// Where each point's sites start in `sites` (points + 1 values).
    pub offsets: Vec<u32>,
    /// Every point's sites, point after point.
    pub sites: Vec<Site>,
}

impl Points {
    /// Number of points.
    #[must_use]
    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// Whether there are no points.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The sites of point `i`.
    #[must_use]
    pub fn point(&self, i: usize) -> &[Site] {
        &self.sites[self.offsets[i] as usize..self.offsets[i + 1] as usize]
    }

    /// Appends a point of `sites` (their weights are scaled to sum to 1; equal if they sum to
    /// nothing).
    pub fn push(&mut self, sites: impl IntoIterator<Item = Site>) {
        if self.offsets.is_empty() {
            self.offsets.push(0);
        }
        let start = self.sites.len();
        self.sites.extend(sites);
        let added = &mut self.sites[start..];
        let total: f64 = added.iter().map(|s| s.weight).sum();
        let count = added.len() as f64;
        for s in added.iter_mut() {
            s.weight = if total > 0.0 {
                s.weight / total
            } else {
                1.0 / count
            };
        }
        self.offsets.push(self.sites.len() as u32);
    }
}

/// How densely a point is sampled.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gather {
    /// Gather rays per point (shared among its sites by weight, at least 16 per site, on a
    /// square grid of strata).
    pub rays: usize,
    /// Shadow rays per sampled emitter relative to the standard 16 to 256
    /// ([`super::area::Sampling::density`]).
    pub density: f64,
    /// Seeds the sampling (with each site's place, not the frame).
    pub seed: u64,
}

/// Gather rays per point of [`Gather::standard`].
pub const GATHER_RAYS: usize = 256;

impl Gather {
    /// The standard sampling with `seed`: [`GATHER_RAYS`] gather rays per point, and each
    /// emitter sampled with the standard grid.
    #[must_use]
    pub fn standard(seed: u64) -> Self {
        Self {
            rays: GATHER_RAYS,
            density: 1.0,
            seed,
        }
    }
}

/// What a frame is lit with: materials (the scene's or a relighting's), the punctual lights'
/// power (colour × intensity, in the scene's order) and the sky's radiance.
#[derive(Clone, Copy, Debug)]
pub struct Lighting<'a> {
    /// Reflectance and emission per material.
    pub materials: &'a [Material],
    /// Colour × intensity per punctual light.
    pub power: &'a [[f64; 3]],
    /// Radiance of everything outside the scene.
    pub sky: [f64; 3],
}

/// A frame's solved patches, as the gather reads them.
#[derive(Clone, Copy, Debug)]
pub struct Solved<'a> {
    /// Outgoing radiance per patch.
    pub radiance: &'a [[f64; 3]],
    /// Its standard error (`None`: no line crossed the patch).
    pub stderr: &'a [Option<[f64; 3]>],
    /// The radiance of the pieces the frame was solved on, if it was
    /// ([`crate::bake::Bake::split`]), each patch's error bar from the lines alone
    /// ([`crate::solve::FrameSolution::pieces_stderr`]), and where the pieces are: a gather ray
    /// reads the piece it lands on rather than its patch's mean.
    pub pieces: Option<PiecesRead<'a>>,
}

/// What [`Solved::pieces`] holds: the pieces' radiance, each patch's error bar from the lines
/// alone, and where the pieces lie.
pub type PiecesRead<'a> = (&'a [[f32; 3]], &'a [[f32; 3]], &'a PieceMap);

/// Where the pieces of a split bake lie on its traced triangles ([`crate::bake::Bake::split`]).
#[derive(Clone, Debug, Default)]
pub struct PieceMap {
    /// The piece of each traced face (`2 × triangle + back`, global triangles), `u32::MAX`
    /// where the triangle has no such face.
    pub face: Vec<u32>,
    /// The patch each piece is part of.
    pub patch: Vec<u32>,
    /// Each piece's size (the square root of its area), in normalised units.
    pub size: Vec<f64>,
}

impl PieceMap {
    /// The map of `pieces`, a scene whose patches are pieces, piece `k` of patch `of[k]`.
    #[must_use]
    pub fn new(pieces: &Scene, of: &[u32]) -> Self {
        let meshes = std::iter::once(&pieces.statics).chain(pieces.objects.iter().map(|o| &o.mesh));
        let face = (meshes.flat_map(|m| &m.faces))
            .flat_map(|f| [f.front, f.back.unwrap_or(u32::MAX)])
            .collect();
        let radius = pieces.normalisation.radius;
        Self {
            face,
            patch: of.to_vec(),
            size: (pieces.patches.iter())
                .map(|p| p.area.sqrt() / radius)
                .collect(),
        }
    }
}

/// The radiance at one output point and its standard error.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PointRadiance {
    /// Outgoing radiance, RGB, in the scene's emission units.
    pub radiance: [f64; 3],
    /// Its standard error.
    pub stderr: [f64; 3],
    /// The irradiance its gather read from the solution (the light that is not the emitters'
    /// and lamps' directly), its sites' weighted mean: what a lightmap's texels interpolate
    /// between vertices ([`crate::output::lightmap`]). 0 with no gather rays.
    pub gathered: [f64; 3],
    /// The weighted share of its sites that reflect light and that no surface touches: 0
    /// under a box resting on the floor, where a lightmap's texel takes no gathered light from
    /// its lit neighbours either.
    pub reached: f64,
    /// The whole irradiance arriving (the direct light's and the gathered), its sites' weighted
    /// mean; over π, what a white diffuse surface there would reflect (a lightmap's `light`).
    /// 0 where the surface reflects nothing (no light is evaluated there).
    pub irradiance: [f64; 3],
}

/// The point of `site` on `place` (its face at the frame), a hair inside the face's edges.
pub(super) fn site_point(site: &Site, place: &Place) -> DVec3 {
    let [a, b, c] = place.corners;
    let x = a * site.bary[0] + b * site.bary[1] + c * site.bary[2];
    into_inset(x, &place.corners)
}

/// A gather ray that meets a patch closer than this many times the patch's size (the square
/// root of its area) reads the light where it lands rather than the patch's mean
/// ([`NEAR_BOUNCES`]): in a corner, the wall beside a floor's vertex is lit unlike its mean
/// (darker, or in a lamp's pool), and the wall's part the vertex sees is that one.
pub const NEAR_HIT: f64 = 1.0;

/// The relative standard error a site's radiance is gathered to: batches of gather rays are
/// added until it is reached, or [`GATHER_BATCHES`] are traced.
pub const GATHER_PRECISION: f64 = 0.05;

/// Batches of gather rays a site gets at most (each about its share of [`Gather::rays`]).
/// Measured on the level at 1M lines (`bench-vertices`, one run each, RMS at the vertices and
/// every frame's vertices against the bake's time): at most 2 at 5%, 3.6% and 24%; 4 at 4%,
/// 3.5% and 30%; 8 at 3%, 3.1% and 41%. Four took the spheres' outputs from 21 s to 33 s.
pub const GATHER_BATCHES: usize = 2;

/// Bounces at most that [`NEAR_HIT`] follows on from a gather ray's point before reading a
/// patch's solved radiance (Russian roulette ends most paths long before: in a 1 cm gap
/// between a ceiling and a panel, where every surface is near, the path goes on until it
/// leaves the gap or is absorbed, as light does).
pub const NEAR_BOUNCES: usize = 64;

/// The seed of `site`'s sampling: its place, whatever the frame.
pub(super) fn site_seed(seed: u64, site: &Site) -> u64 {
    let bary = (site.bary[1] * f64::from(1u32 << 30)) as u64
        ^ ((site.bary[2] * f64::from(1u32 << 30)) as u64) << 30;
    mix(seed ^ mix((u64::from(site.triangle) << 1 | u64::from(site.back)) ^ mix(bary)))
}

/// The radiance at each of `points` at `frame`: the scene and its tracer, the bake's sampled
/// emitters `area`, the frame's solved patches `solved` and the `lighting` they were solved
/// with, sampled as `gather` says (module docs).
#[must_use]
pub fn radiance_at(
    state: (&Scene, &SceneTracer, &AreaLights),
    frame: usize,
    points: &Points,
    read: (Solved<'_>, Lighting<'_>),
    sampling: (Gather, &GatherCache),
) -> Vec<PointRadiance> {
    with_gatherer(state, frame, read, sampling, |gatherer| {
        (0..points.len())
            .into_par_iter()
            .map_init(Vec::new, |hits, i| gatherer.point(points.point(i), hits))
            .collect()
    })
}

/// Runs `f` with the [`Gatherer`] of `frame`: what [`radiance_at`] and the light probes
/// ([`probes_at`]) read.
fn with_gatherer<R>(
    (scene, tracer, area): (&Scene, &SceneTracer, &AreaLights),
    frame: usize,
    (solved, lighting): (Solved<'_>, Lighting<'_>),
    (gather, cache): (Gather, &GatherCache),
    f: impl FnOnce(&Gatherer<'_>) -> R,
) -> R {
    let posed = Posed::at(scene, tracer, frame);
    let view = posed.frame(scene, tracer, Occluders::All);
    let statics = posed.frame(scene, tracer, Occluders::Static);
    let moving = posed.frame(scene, tracer, Occluders::Moving);
    let statics_count = scene.statics.triangles.len();
    cache.keep_for(statics_count);
    let swept = cache.swept(scene);
    let now = Swept::at(scene, frame, swept.lights_move);
    let (places, _) = places(scene, &view);
    let emitters: Vec<_> = (area
        .posed_materials(scene, tracer, &posed.triangles)
        .into_iter())
    .filter_map(|(emitter, m)| {
        let le = lighting.materials.get(m as usize)?.emission;
        le.iter().any(|&e| e > 0.0).then_some((emitter, le))
    })
    .collect();
    // The emission the gather leaves out: the sampled emitters', which the direct term has.
    let seen: Vec<[f64; 3]> = (scene.patches.iter())
        .map(|p| match lighting.materials.get(p.material as usize) {
            Some(m) if area.samples(p.material) => m.emission,
            _ => [0.0; 3],
        })
        .collect();
    // Each patch's size, in normalised units, for [`NEAR_HIT`].
    let radius = scene.normalisation.radius;
    let sizes: Vec<f64> = (scene.patches.iter())
        .map(|p| p.area.sqrt() / radius)
        .collect();
    let gatherer = Gatherer {
        scene,
        sight: Sight::new(scene, &view, frame, lighting.power),
        statics: Sight::new(scene, &statics, frame, lighting.power),
        moving: (!scene.objects.is_empty())
            .then(|| Sight::new(scene, &moving, frame, lighting.power)),
        statics_count,
        cache,
        moving_lights: swept.lights_move,
        swept,
        now,
        lighting_key: lighting_key(lighting) ^ u64::from(solved.pieces.is_some()),
        places: &places,
        emitters: &emitters,
        seen: &seen,
        sizes: &sizes,
        solved,
        lighting,
        gather,
    };
    f(&gatherer)
}

/// Probe rays per point of [`closeness`] (a 4 × 4 grid of strata).
pub const PROBE_RAYS: usize = 16;

/// How near the geometry around each of `points` is at `frame`: the mean over [`PROBE_RAYS`]
/// stratified cosine-weighted rays from each site of the inverse of the distance to the first
/// surface they meet (0 for a ray that leaves the scene), its sites' weighted mean: `1/R`,
/// with `R` the harmonic mean distance that irradiance caching bounds a gather's reach by (a
/// point in a narrow gap or a corner reads a large value; a point in the open a small one).
/// The same rays at every call (seeded by `seed` and each site's place).
#[must_use]
pub fn closeness(
    (scene, tracer): (&Scene, &SceneTracer),
    frame: usize,
    points: &Points,
    seed: u64,
) -> Vec<f64> {
    let posed = Posed::at(scene, tracer, frame);
    let view = posed.frame(scene, tracer, Occluders::All);
    let (places, _) = places(scene, &view);
    let sight = Sight::new(scene, &view, frame, &[]);
    let g = PROBE_RAYS.isqrt();
    (0..points.len())
        .into_par_iter()
        .map_init(Vec::new, |hits, i| {
            let mut sum = 0.0;
            for site in points.point(i) {
                let place = &places[2 * site.triangle as usize + usize::from(site.back)];
                if place.normal == DVec3::ZERO {
                    continue;
                }
                let x = site_point(site, place);
                let mut inverse = 0.0;
                for (u, v) in strata(g, mix(site_seed(seed, site))) {
                    let w = cosine_direction_at(place.normal, u, v);
                    let t = met_distance(&sight.first_hit(x, w, place, hits));
                    inverse += 1.0 / t.max(f64::MIN_POSITIVE);
                }
                sum += site.weight * inverse / (g * g) as f64;
            }
            sum
        })
        .collect()
}

/// What a point's evaluation reads.
struct Gatherer<'a> {
    scene: &'a Scene,
    sight: Sight<'a>,
    /// The static geometry alone, and the moving geometry alone (if any).
    statics: Sight<'a>,
    moving: Option<Sight<'a>>,
    /// Traced triangles below this index are static.
    statics_count: usize,
    /// The static crossings of the static sites' gather rays, and their linear forms.
    cache: &'a GatherCache,
    /// Where the moving geometry can be at any frame.
    swept: std::sync::Arc<Swept>,
    /// Where the moving geometry is at this frame: a static site's direct light none of whose
    /// shadow rays can meet it is the same as at any other frame where none can.
    now: Swept,
    /// Whether a punctual light moves: no linear form is kept.
    moving_lights: bool,
    /// The lighting the linear forms are traced with (materials, lights' power, sky).
    lighting_key: u64,
    places: &'a [Place],
    /// The sampled emitters posed at the frame, with their emission.
    emitters: &'a [(super::area::Emitter, [f64; 3])],
    /// Per patch, the emission the gather leaves out.
    seen: &'a [[f64; 3]],
    /// Per patch, its size (normalised units).
    sizes: &'a [f64],
    /// The frame's solution: a gather ray reads its pieces if it has them, its patches
    /// otherwise (a ray's "unit", [`Read::Patch`]).
    solved: Solved<'a>,
    lighting: Lighting<'a>,
    gather: Gather,
}

impl Gatherer<'_> {
    /// The weighted mean of `sites`' radiance.
    fn point(&self, sites: &[Site], hits: &mut Vec<Hit>) -> PointRadiance {
        let (mut radiance, mut variance, mut read) = ([0.0; 3], [0.0; 3], [0.0; 3]);
        let (mut gathered, mut reached, mut irradiance) = ([0.0; 3], 0.0, [0.0; 3]);
        for site in sites {
            let ((l, v, r, g, e), reaches) = self.site(site, hits);
            if reaches {
                reached += site.weight;
            }
            for c in 0..3 {
                radiance[c] += site.weight * l[c];
                variance[c] += site.weight * site.weight * v[c];
                read[c] += site.weight * r[c];
                gathered[c] += site.weight * g[c];
                irradiance[c] += site.weight * e[c];
            }
        }
        PointRadiance {
            radiance,
            stderr: std::array::from_fn(|c| (variance[c] + read[c] * read[c]).sqrt()),
            gathered,
            reached,
            irradiance,
        }
    }

    /// The radiance at `site`, the variance of its sampling, the error of the patches its
    /// gather read (a standard error, correlated between sites), and the irradiance gathered;
    /// and whether light reaches it (its face reflects, and no surface touches it there).
    fn site(&self, site: &Site, hits: &mut Vec<Hit>) -> (SiteLight, bool) {
        let place = &self.places[2 * site.triangle as usize + usize::from(site.back)];
        let faces = self.sight.view.triangles[site.triangle as usize].1;
        let patch = if site.back {
            faces.back
        } else {
            Some(faces.front)
        };
        let Some(material) = patch
            .and_then(|p| self.scene.patches.get(p as usize))
            .and_then(|p| self.lighting.materials.get(p.material as usize))
        else {
            return (([0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3]), false);
        };
        let (le, rho) = (material.emission, material.reflectance);
        let x = site_point(site, place);
        let (n, own) = (place.normal, (place.triangle, place.back));
        if rho == [0.0; 3] || n == DVec3::ZERO || self.sight.view.covered(x, n, own) {
            return ((le, [0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3]), false);
        }
        let seed = site_seed(self.gather.seed, site);
        let pi = std::f64::consts::PI;
        let (mut e, mut variance) = self.direct(site, (x, place), seed, hits);
        // The rest, gathered from the solution along stratified cosine-weighted rays, a batch
        // at a time: more batches while the site's radiance is known to worse than
        // [`GATHER_PRECISION`] by their noise (in a gap, where light arrives by rare paths),
        // each batch with its own strata; the batches' means pooled.
        let (mut gathered, mut spread, mut read, mut count) = ([0.0; 3], [0.0; 3], [0.0; 3], 0.0);
        let mut batches = 0;
        // No gather rays: the direct light alone.
        let most = if self.gather.rays == 0 {
            0
        } else {
            GATHER_BATCHES
        };
        while batches < most {
            let batch_seed = if batches == 0 {
                seed
            } else {
                mix(seed ^ batches as u64)
            };
            let (mean, var, r, n_rays) =
                self.gather_batch(site, (x, place), (batch_seed, batches), hits);
            batches += 1;
            let b = batches as f64;
            for c in 0..3 {
                // Running means of equal batches: the pooled variance is Σ var / B².
                gathered[c] += (mean[c] - gathered[c]) / b;
                spread[c] += var[c];
                read[c] += r[c];
            }
            count += n_rays;
            let known = (0..3).all(|c| {
                let total = le[c] + rho[c] / pi * (e[c] + gathered[c]);
                let sigma = rho[c] / pi * spread[c].sqrt() / b;
                sigma <= GATHER_PRECISION * total || rho[c] == 0.0
            });
            if known {
                break;
            }
        }
        let b = (batches as f64).max(1.0);
        for c in 0..3 {
            e[c] += gathered[c];
            variance[c] += spread[c] / (b * b);
        }
        let to_radiance = |c: usize| rho[c] * std::f64::consts::FRAC_1_PI;
        let light = (
            std::array::from_fn(|c| le[c] + to_radiance(c) * e[c]),
            std::array::from_fn(|c| to_radiance(c).powi(2) * variance[c]),
            std::array::from_fn(|c| to_radiance(c) * read[c] / count.max(1.0)),
            gathered,
            e,
        );
        (light, true)
    }

    /// The irradiance at `site`'s point `x` (on `place`) straight from the punctual lights and
    /// the sampled emitters, and its variance. An emitter's light at a static site none of
    /// whose shadow rays to it can meet the moving geometry at this frame is its light with
    /// the static geometry alone: kept from the first such frame (with the lighting it was
    /// traced with), read at the others, so that only the emitters a moving object may shadow
    /// are sampled again, along the rays the static geometry lets through (kept as a bit per
    /// ray), and not at all when the static geometry is clear of them.
    fn direct(
        &self,
        site: &Site,
        (x, place): (DVec3, &Place),
        seed: u64,
        hits: &mut Vec<Hit>,
    ) -> DirectLight {
        let pi = std::f64::consts::PI;
        let (n, own) = (place.normal, (place.triangle, place.back));
        let mut e = self.sight.punctual(x, place, hits);
        let mut variance = [0.0; 3];
        let keeps = (site.triangle as usize) < self.statics_count && !self.moving_lights;
        // The sampled emitters, by solid angle.
        let scale = site.weight.sqrt();
        for (k, (emitter, emission)) in self.emitters.iter().enumerate() {
            let clear = keeps && self.now.hull_clear(x, emitter);
            let kept = clear
                .then(|| self.cache.direct((site, k), self.lighting_key))
                .flatten();
            let (f, v) = kept.unwrap_or_else(|| {
                let Some(seen) = Seen::new((x, n), emitter) else {
                    return (0.0, 0.0);
                };
                let g = point_grid(x, emitter, self.gather.density);
                let g = ((g as f64 * scale).round() as usize).max(4);
                let sample = (mix(seed ^ k as u64), g);
                // Something moving may shadow the site: its rays' verdicts through the static
                // geometry are kept, and each frame traces the moving objects along them.
                if keeps
                    && !clear
                    && let Some(moving) = &self.moving
                {
                    let rays = self.cache.direct_rays((site, k), self.lighting_key, || {
                        PointRays::sample(self.statics.view, (&seen, emitter), own, sample)
                    });
                    return rays.form_factor(moving.view, &seen, own, sample);
                }
                // The moving geometry is tested too unless it cannot be in the way.
                let moving = self.moving.as_ref().filter(|_| !clear).map(|m| m.view);
                let statics = seen.statics_clear(self.statics.view, emitter, own.0);
                let lit = seen.visible_through((self.sight.view, moving), statics, own, sample);
                if clear {
                    self.cache.keep_direct((site, k), self.lighting_key, lit);
                }
                lit
            });
            for c in 0..3 {
                e[c] += pi * emission[c] * f;
                variance[c] += (pi * emission[c]).powi(2) * v;
            }
        }
        (e, variance)
    }

    /// One batch of gather rays from `x` on `place` (the site's `batch`-th, seeded by `seed`):
    /// the mean of π times the radiance they read, its variance (pairs of neighbouring
    /// strata), the sum of π times the error bars of the patches read, and the rays.
    fn gather_batch(
        &self,
        site: &Site,
        (x, place): (DVec3, &Place),
        (seed, batch): (u64, usize),
        hits: &mut Vec<Hit>,
    ) -> ([f64; 3], [f64; 3], [f64; 3], f64) {
        let pi = std::f64::consts::PI;
        let directions = self.directions(site, place.normal, seed);
        // On static geometry, the rays' static crossings are the same at every frame: traced
        // once, and each frame traces the moving objects alone, as far as the static crossing.
        let crossings = (site.triangle as usize) < self.statics_count;
        let crossings = crossings.then(|| {
            self.cache.crossings((site, batch), || {
                (directions.iter())
                    .map(|&w| Crossing::of(self.statics.first_hit(x, w, place, hits)))
                    .collect()
            })
        });
        // Rays whose form is clear of the moving geometry are kept as their linear form of the
        // solution (with the lighting they were traced with): a later frame reads them.
        let keeps = crossings.is_some() && !self.moving_lights;
        let kept = keeps
            .then(|| self.cache.forms((site, batch), self.lighting_key))
            .flatten();
        // The others' forms kept with their paths, each from a frame where no moving object
        // came near its path: they hold at every frame where none does.
        let paths = keeps
            .then(|| self.cache.paths((site, batch), self.lighting_key))
            .flatten();
        let mut found: Vec<Option<KeptPath>> = Vec::new();
        let mut path = Vec::new();
        let mut values = vec![[0.0; 3]; directions.len()];
        let mut read = [0.0; 3];
        let mut forms: Vec<Option<Linear>> = Vec::new();
        for (k, (value, &w)) in values.iter_mut().zip(&directions).enumerate() {
            let kept_path = (paths.as_ref())
                .and_then(|paths| paths.get(k).cloned().flatten())
                .filter(|(tests, _)| self.path_clear(tests));
            let linear = match (kept.as_ref().and_then(|kept| kept[k]), kept_path) {
                (Some(linear), _) => linear,
                (None, Some((_, form))) => Linear {
                    clear: false,
                    ..form.linear()
                },
                (None, None) => {
                    path.clear();
                    let met = match &crossings {
                        Some(crossings) => self.with_moving(crossings[k], (x, w, place), hits),
                        None => self.sight.first_hit(x, w, place, hits),
                    };
                    let mut linear = match met {
                        Met::Sky => Linear::read(Read::Sky),
                        Met::Nothing => Linear::read(Read::Nothing),
                        Met::Patch(face, p, t) => {
                            let on = (mix(seed ^ k as u64), &mut *hits, &mut path);
                            self.reflected(p, (face, x + w * t), (t, 0), on)
                        }
                    };
                    linear.clear &= self.swept.ray_clear(x, w, met_distance(&met));
                    path.push(PathTest::Ray(x, w, met_distance(&met)));
                    // A form that may be kept is read as kept (in `f32`), whether or not it is;
                    // so is one whose path nothing moving comes near at this frame.
                    if linear.clear && keeps {
                        Form::of(&linear).linear()
                    } else if keeps && self.path_clear(&path) {
                        let form = Form::of(&linear);
                        found.resize(directions.len(), None);
                        found[k] = Some((path.as_slice().into(), form));
                        Linear {
                            clear: false,
                            ..form.linear()
                        }
                    } else {
                        linear
                    }
                }
            };
            if kept.is_none() {
                forms.push(linear.clear.then_some(linear));
            }
            if let Read::Patch(q) = linear.read
                && let Some(s) = self.read_error(q)
            {
                (0..3).for_each(|c| read[c] += pi * linear.weight[c] * s[c]);
            }
            *value = self.value(&linear).map(|l| pi * l);
        }
        if keeps && kept.is_none() {
            self.cache
                .keep_forms((site, batch), self.lighting_key, forms);
        }
        if !found.is_empty() {
            self.cache
                .keep_paths((site, batch), self.lighting_key, found);
        }
        let (mut mean, mut variance) = ([0.0; 3], [0.0; 3]);
        for c in 0..3 {
            let channel: Vec<f64> = values.iter().map(|v| v[c]).collect();
            (mean[c], variance[c]) = super::collapsed_variance(&channel);
        }
        (mean, variance, read, directions.len() as f64)
    }

    /// Whether nothing moving comes near a gather ray's `path` at this frame: its segments
    /// miss the moving objects' boxes, and so do the shadow rays from its bounces to the lights
    /// ([`Swept::lights_clear`], [`Swept::hull_clear`]).
    fn path_clear(&self, path: &[PathTest]) -> bool {
        path.iter().all(|test| match *test {
            PathTest::Ray(a, w, reach) => self.now.ray_clear(a, w, reach),
            PathTest::Point(y) => {
                self.now.lights_clear(&self.sight, y)
                    && (self.emitters.iter()).all(|(emitter, _)| self.now.hull_clear(y, emitter))
            }
        })
    }

    /// The gather rays' directions at `site` (normal `n`): a square grid of strata of the
    /// cosine-weighted hemisphere, of about the site's share of [`Gather::rays`] (at least
    /// 16), jittered by `seed`: the same at every frame.
    fn directions(&self, site: &Site, n: DVec3, seed: u64) -> Vec<DVec3> {
        let g = ((self.gather.rays as f64 * site.weight).sqrt().ceil() as usize).max(4);
        strata(g, mix(seed ^ 0x6761_7468))
            .map(|(u, v)| cosine_direction_at(n, u, v))
            .collect()
    }

    /// What the ray from `x` (on `place`) along `w`, whose first static crossing is
    /// `crossing`, meets first at this frame: a moving object before it, or it.
    fn with_moving(
        &self,
        crossing: Crossing,
        (x, w, place): (DVec3, DVec3, &Place),
        hits: &mut Vec<Hit>,
    ) -> Met {
        let fixed = crossing.met(self.sight.view);
        let Some(moving) = &self.moving else {
            return fixed;
        };
        let reach = match fixed {
            Met::Patch(_, _, t) => t,
            _ => f64::INFINITY,
        };
        match moving.first_hit_within(x, w, place, hits, reach) {
            Met::Patch(face, p, t) if t < reach => Met::Patch(face, p, t),
            Met::Nothing => Met::Nothing,
            _ => fixed,
        }
    }

    /// The radiance patch `p` sends back along a gather ray that meets its face `face` at
    /// `y`, `t` from the point, less the sampled emitters' emission, as a linear form of the
    /// frame's solution: the patch's solved radiance; or, closer than [`NEAR_HIT`] times the
    /// patch's size, its emission plus the light reflected at `y` itself, from one sample of
    /// each light (one stratum, `seed`) and one cosine-weighted ray on from `y`, itself read the
    /// same way up to [`NEAR_BOUNCES`] times with Russian roulette (in a gap or a corner, where
    /// the light falls off within a patch, the next surface is near too, and a patch's mean is
    /// far from the light where the ray lands): unbiased for the light at `y` given the solution
    /// far from it, and the many rays of a point average it. The form is clear when none of its
    /// rays can meet the moving geometry at any frame.
    fn reflected(
        &self,
        p: usize,
        (face, y): (usize, DVec3),
        (t, depth): (f64, usize),
        (seed, hits, path): (u64, &mut Vec<Hit>, &mut Vec<PathTest>),
    ) -> Linear {
        let material = (self.scene.patches.get(p))
            .and_then(|patch| self.lighting.materials.get(patch.material as usize));
        let (unit, size) = match self.solved.pieces {
            Some((_, _, map)) => {
                let k = map.face.get(face).copied().unwrap_or(u32::MAX);
                match map.size.get(k as usize) {
                    Some(&size) => (k, size),
                    None => (p as u32, self.sizes[p]),
                }
            }
            None => (p as u32, self.sizes[p]),
        };
        let near = depth < NEAR_BOUNCES && t < NEAR_HIT * size;
        let Some(material) = material.filter(|_| near) else {
            return Linear::read(Read::Patch(unit));
        };
        let pi = std::f64::consts::PI;
        let place = &self.places[face];
        let y = into_inset(y, &place.corners);
        let (n, tri, back) = (place.normal, place.triangle, place.back);
        let mut e = self.sight.punctual(y, place, hits);
        let mut clear = self.swept.lights_clear(&self.sight, y);
        path.push(PathTest::Point(y));
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        for (k, (emitter, emission)) in self.emitters.iter().enumerate() {
            let sample = (mix(seed ^ k as u64), 1);
            let (f, _) = point_form_factor(self.sight.view, (y, n, tri, back), emitter, sample);
            (0..3).for_each(|c| e[c] += pi * emission[c] * f);
            clear &= self.swept.hull_clear(y, emitter);
        }
        // Russian roulette after the first bounces: the path goes on with the largest
        // reflectance's probability, and what it brings back is divided by it.
        let rho = material.reflectance;
        let survive = if depth >= 2 {
            rho.iter().fold(0.0f64, |m, &r| m.max(r)).min(1.0)
        } else {
            1.0
        };
        let w = cosine_direction_at(n, rng.random(), rng.random());
        let on = if survive > 0.0 && rng.random::<f64>() < survive {
            let met = self.sight.first_hit(y, w, place, hits);
            let mut next = match met {
                Met::Sky => Linear::read(Read::Sky),
                Met::Nothing => Linear::read(Read::Nothing),
                Met::Patch(next, q, t) => {
                    let on = (mix(seed ^ 0x6e65_6172), &mut *hits, &mut *path);
                    self.reflected(q, (next, y + w * t), (t, depth + 1), on)
                }
            };
            next.clear &= self.swept.ray_clear(y, w, met_distance(&met));
            path.push(PathTest::Ray(y, w, met_distance(&met)));
            next.scale(1.0 / survive)
        } else {
            Linear::read(Read::Nothing)
        };
        let own: [f64; 3] = std::array::from_fn(|c| {
            let le = material.emission[c] - self.seen[p][c];
            le.max(0.0) + rho[c] / pi * e[c]
        });
        Linear {
            constant: std::array::from_fn(|c| own[c] + rho[c] * on.constant[c]),
            weight: std::array::from_fn(|c| rho[c] * on.weight[c]),
            read: on.read,
            clear: clear && on.clear,
        }
    }

    /// The patch of a unit the gather reads ([`Read::Patch`]): itself, or a piece's patch.
    fn patch_of(&self, unit: u32) -> u32 {
        match self.solved.pieces {
            Some((_, _, map)) => map.patch.get(unit as usize).copied().unwrap_or(u32::MAX),
            None => unit,
        }
    }

    /// The error bar of what a gather ray reads of `unit` ([`Read::Patch`]), shared by the
    /// rays that read the same patch: its patch's; when the unit is a piece, its patch's from
    /// the lines alone (a piece's own noise, independent between pieces, is in the spread of
    /// the rays' values).
    fn read_error(&self, unit: u32) -> Option<[f64; 3]> {
        let p = self.patch_of(unit) as usize;
        match self.solved.pieces {
            Some((_, errors, _)) => errors.get(p).map(|e| e.map(f64::from)),
            None => self.solved.stderr.get(p).copied().flatten(),
        }
    }

    /// The value of `linear` with this frame's solution.
    fn value(&self, linear: &Linear) -> [f64; 3] {
        let read = match linear.read {
            Read::Patch(q) => {
                let l = match self.solved.pieces {
                    Some((radiance, _, _)) => (radiance.get(q as usize))
                        .map(|l| l.map(f64::from))
                        .unwrap_or_default(),
                    None => (self.solved.radiance.get(q as usize))
                        .copied()
                        .unwrap_or_default(),
                };
                let seen = self.seen.get(self.patch_of(q) as usize).copied();
                let seen = seen.unwrap_or_default();
                std::array::from_fn(|c| (l[c] - seen[c]).max(0.0))
            }
            Read::Sky => self.lighting.sky,
            Read::Nothing => [0.0; 3],
        };
        std::array::from_fn(|c| linear.constant[c] + linear.weight[c] * read[c])
    }
}

/// Whether the tetrahedron `p` meets the box `(lo, hi)`, by separating axes: the box's own
/// (the bounds), the tetrahedron's faces' normals and the cross products of its edges with the
/// box's axes. Conservative for a degenerate tetrahedron (axes of no length are skipped).
fn tetrahedron_meets_box(p: [DVec3; 4], (lo, hi): (DVec3, DVec3)) -> bool {
    let (plo, phi) = p.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(l, h), &q| (l.min(q), h.max(q)),
    );
    if (0..3).any(|k| phi[k] < lo[k] || plo[k] > hi[k]) {
        return false;
    }
    let (centre, half) = ((lo + hi) * 0.5, (hi - lo) * 0.5);
    let separates = |axis: DVec3| {
        if axis.length_squared() < 1e-300 {
            return false;
        }
        let (mut min, mut max) = (f64::INFINITY, f64::NEG_INFINITY);
        for q in p {
            let d = (q - centre).dot(axis);
            (min, max) = (min.min(d), max.max(d));
        }
        let r = half.dot(axis.abs());
        min > r || max < -r
    };
    const FACES: [[usize; 3]; 4] = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]];
    const EDGES: [[usize; 2]; 6] = [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]];
    let faces = FACES.map(|[a, b, c]| (p[b] - p[a]).cross(p[c] - p[a]));
    if faces.into_iter().any(separates) {
        return false;
    }
    !(EDGES.iter()).any(|&[a, b]| {
        let e = p[b] - p[a];
        [DVec3::X, DVec3::Y, DVec3::Z]
            .into_iter()
            .any(|axis| separates(e.cross(axis)))
    })
}

/// A hash of what the linear forms depend on beside the solution: every material's
/// reflectance and emission, every light's power, the sky.
fn lighting_key(lighting: Lighting<'_>) -> u64 {
    let mut key = 0x6c69_6768_7473u64;
    let mut add = |x: f64| key = mix(key ^ x.to_bits());
    for m in lighting.materials {
        m.reflectance
            .iter()
            .chain(&m.emission)
            .for_each(|&x| add(x));
    }
    lighting.power.iter().flatten().for_each(|&x| add(x));
    lighting.sky.iter().for_each(|&x| add(x));
    key
}

/// How far a ray went to what it met (infinitely to the sky or to nothing).
fn met_distance(met: &Met) -> f64 {
    match met {
        Met::Patch(_, _, t) => *t,
        _ => f64::INFINITY,
    }
}

/// What a gather ray's value reads of a frame's solution.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Read {
    /// A patch's radiance (or a piece's, when the solution has them: [`Solved::pieces`]),
    /// less its sampled emission.
    Patch(u32),
    /// The sky's radiance.
    Sky,
    /// Nothing.
    Nothing,
}

/// A gather ray's value as a linear form of the frame's solution: `constant + weight × read`,
/// per channel; `clear` when none of its rays can meet the moving geometry at any frame (the
/// form then holds at every frame with the same lighting).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Linear {
    constant: [f64; 3],
    weight: [f64; 3],
    read: Read,
    clear: bool,
}

impl Linear {
    /// `read` itself.
    fn read(read: Read) -> Self {
        Self {
            constant: [0.0; 3],
            weight: if read == Read::Nothing {
                [0.0; 3]
            } else {
                [1.0; 3]
            },
            read,
            clear: true,
        }
    }

    /// The form times `k`.
    fn scale(self, k: f64) -> Self {
        Self {
            constant: self.constant.map(|x| x * k),
            weight: self.weight.map(|x| x * k),
            ..self
        }
    }
}

/// Where the moving geometry can be at any frame, and whether any light moves: a ray that meets
/// none of these boxes meets the same surfaces at every frame.
#[derive(Debug, Default)]
pub(super) struct Swept {
    /// Each moving object's bounding box over every frame (normalised space), grown by a hair.
    boxes: Vec<(DVec3, DVec3)>,
    /// Whether a punctual light moves (its light then changes at points nothing moves near).
    lights_move: bool,
}

impl Swept {
    /// Whether the box `(lo, hi)` meets a moving object's box.
    pub(super) fn meets_box(&self, lo: DVec3, hi: DVec3) -> bool {
        (self.boxes.iter()).any(|&(a, b)| lo.cmple(b).all() && hi.cmpge(a).all())
    }

    /// Where the moving objects are at `frame` alone (`lights_move` as the timeline's).
    pub(super) fn at(scene: &Scene, frame: usize, lights_move: bool) -> Self {
        let boxes = (scene.objects.iter())
            .map(|object| Self::reach(object, frame..frame + 1))
            .collect();
        Self { boxes, lights_move }
    }

    fn of(scene: &Scene) -> Self {
        let boxes = (scene.objects.iter())
            .map(|object| Self::reach(object, 0..scene.frames.count))
            .collect();
        let lights_move = scene.lights.iter().any(|light| {
            (1..scene.frames.count).any(|f| {
                light.position(f) != light.position(0) || light.direction(f) != light.direction(0)
            })
        });
        Self { boxes, lights_move }
    }

    /// The box around `object` at `frames`, grown by a hair.
    fn reach(
        object: &crate::scene::MovingObject,
        frames: std::ops::Range<usize>,
    ) -> (DVec3, DVec3) {
        let pad = DVec3::splat(f64::from(16.0 * crate::trace::coincident::COINCIDENT));
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for f in frames {
            for p in object.positions_at(f) {
                lo = lo.min(p.as_dvec3());
                hi = hi.max(p.as_dvec3());
            }
        }
        (lo - pad, hi + pad)
    }

    /// Whether the ray from `a` along unit `w`, as far as `reach`, misses every box.
    fn ray_clear(&self, a: DVec3, w: DVec3, reach: f64) -> bool {
        self.boxes.iter().all(|&(lo, hi)| {
            let (mut t0, mut t1) = (0.0f64, reach);
            for k in 0..3 {
                if w[k].abs() < 1e-300 {
                    if a[k] < lo[k] || a[k] > hi[k] {
                        return true;
                    }
                    continue;
                }
                let (p, q) = ((lo[k] - a[k]) / w[k], (hi[k] - a[k]) / w[k]);
                t0 = t0.max(p.min(q));
                t1 = t1.min(p.max(q));
            }
            t0 > t1
        })
    }

    /// Whether every shadow ray from `y` to the punctual lights misses every box, and no light
    /// moves.
    fn lights_clear(&self, sight: &Sight<'_>, y: DVec3) -> bool {
        !self.lights_move
            && sight.lights().all(|(position, direction)| match position {
                Some(position) => {
                    let d = position - y;
                    let length = d.length();
                    length <= 0.0 || self.ray_clear(y, d / length, length)
                }
                None => self.ray_clear(y, -direction, f64::INFINITY),
            })
    }

    /// Whether every ray from `y` to `emitter` misses every box: the box around them both
    /// does, or each of the tetrahedra from `y` to the emitter's triangles (which hold those
    /// rays) does.
    fn hull_clear(&self, y: DVec3, emitter: &super::area::Emitter) -> bool {
        let (lo, hi) = emitter.bounds();
        let (lo, hi) = (lo.min(y), hi.max(y));
        (self.boxes.iter()).all(|&(a, b)| {
            (0..3).any(|k| hi[k] < a[k] || lo[k] > b[k])
                || (emitter.triangles().iter())
                    .all(|t| !tetrahedron_meets_box([y, t[0], t[1], t[2]], (a, b)))
        })
    }
}

/// The first static crossing of a gather ray: a face (`2 × triangle + back`) at a distance,
/// the sky, or nothing (a one-sided face's back, a contact).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Crossing {
    face: u32,
    t: f32,
}

impl Crossing {
    const SKY: u32 = u32::MAX;
    const NOTHING: u32 = u32::MAX - 1;

    fn of(met: Met) -> Self {
        match met {
            Met::Sky => Self {
                face: Self::SKY,
                t: 0.0,
            },
            Met::Nothing => Self {
                face: Self::NOTHING,
                t: 0.0,
            },
            Met::Patch(face, _, t) => Self {
                face: face as u32,
                t: t as f32,
            },
        }
    }

    /// What it is in the scene `view` shows (its face's patch as the scene's faces say now).
    fn met(self, view: &super::Frame<'_>) -> Met {
        match self.face {
            Self::SKY => Met::Sky,
            Self::NOTHING => Met::Nothing,
            face => {
                let faces = view.triangles[face as usize / 2].1;
                let patch = if face % 2 == 1 {
                    faces.back
                } else {
                    Some(faces.front)
                };
                patch.map_or(Met::Nothing, |p| {
                    Met::Patch(face as usize, p as usize, f64::from(self.t))
                })
            }
        }
    }
}

/// What evaluating points keeps across frames: the first static crossing of every gather ray
/// of every site on static geometry, filled as sites are first evaluated, up to
/// [`GATHER_CACHE_BYTES`]. Cost and memory grow with the static sites (8 bytes a ray), not
/// with the frames; each later frame traces only the moving objects along them. Emptied when
/// the scene's static triangles change (a bake's cuts and pieces).
#[derive(Debug, Default)]
pub struct GatherCache {
    inner: std::sync::RwLock<Kept>,
}

/// Most bytes a [`GatherCache`] holds: past them, the sites not kept are traced whole at every
/// frame (a 2,913-vertex level keeps about 20 MB).
pub const GATHER_CACHE_BYTES: usize = 256 << 20;

/// What a [`GatherCache`] holds.
#[derive(Debug, Default)]
struct Kept {
    /// The static triangles the crossings were traced among.
    statics: usize,
    /// The crossings by site and batch.
    crossings: std::collections::HashMap<SiteKey, std::sync::Arc<[Crossing]>>,
    /// The lighting the forms were traced with ([`lighting_key`]), and the gather rays' linear
    /// forms by site and batch (`None` for a ray that may meet the moving geometry).
    forms: (u64, KeptForms),
    /// The form factor (and its variance) from static sites to each sampled emitter (by site
    /// and emitter) that nothing moving shadowed, with the lighting it was traced with.
    direct: (u64, std::collections::HashMap<SiteKey, (f64, f64)>),
    /// The shadow rays from static sites to each sampled emitter (by site and emitter) that
    /// something moving may shadow at some frame, with the lighting they were sampled with.
    rays: (u64, KeptRays),
    /// The forms of static sites' gather rays that something moving may meet at some frame, by
    /// site and batch, each kept with its path from a frame where nothing moving came near it
    /// (`None` until such a frame), with the lighting they were traced with.
    paths: (u64, KeptPaths),
    /// The moving geometry's reach over the timeline.
    swept: Option<std::sync::Arc<Swept>>,
    /// The bytes they take, about.
    bytes: usize,
}

/// The gather rays' forms kept with their paths, by site and batch.
type KeptPaths = std::collections::HashMap<SiteKey, std::sync::Arc<[Option<KeptPath>]>>;

/// The shadow rays of static sites to the sampled emitters, by site and emitter.
type KeptRays = std::collections::HashMap<SiteKey, std::sync::Arc<PointRays>>;

/// The linear forms of each site's batches of gather rays.
type KeptForms = std::collections::HashMap<SiteKey, std::sync::Arc<[Option<Form>]>>;

/// A site's direct irradiance and its variance, RGB.
type DirectLight = ([f64; 3], [f64; 3]);

/// A site's radiance, its sampling's variance, the error of the patches its gather read, the
/// irradiance gathered, and the whole irradiance arriving ([`Gatherer::site`]).
type SiteLight = ([f64; 3], [f64; 3], [f64; 3], [f64; 3], [f64; 3]);

/// A [`Linear`] as kept, in `f32` (a ray's value is always read from this form, whether just
/// traced or kept, so that frames agree to the bit whatever was evaluated before them).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Form {
    constant: [f32; 3],
    weight: [f32; 3],
    /// The patch read, or [`Form::SKY`], [`Form::NOTHING`].
    read: u32,
}

impl Form {
    const SKY: u32 = u32::MAX;
    const NOTHING: u32 = u32::MAX - 1;

    fn of(linear: &Linear) -> Self {
        Self {
            constant: linear.constant.map(|x| x as f32),
            weight: linear.weight.map(|x| x as f32),
            read: match linear.read {
                Read::Patch(q) => q,
                Read::Sky => Self::SKY,
                Read::Nothing => Self::NOTHING,
            },
        }
    }

    fn linear(self) -> Linear {
        Linear {
            constant: self.constant.map(f64::from),
            weight: self.weight.map(f64::from),
            read: match self.read {
                Self::SKY => Read::Sky,
                Self::NOTHING => Read::Nothing,
                q => Read::Patch(q),
            },
            clear: true,
        }
    }
}

/// What a gather ray's path must miss of the moving geometry for its form to be the static
/// geometry's ([`Gatherer::path_clear`]): a segment (from, direction, length), or a bounce's
/// point, whose shadow rays to the lights must miss it.
#[derive(Clone, Copy, Debug)]
enum PathTest {
    Ray(DVec3, DVec3, f64),
    Point(DVec3),
}

/// A gather ray's path tests and its form, kept from a frame where nothing moving came near.
type KeptPath = (std::sync::Arc<[PathTest]>, Form);

/// A site, exactly, and a batch of its gather rays.
type SiteKey = (u32, bool, usize, [u64; 3]);

/// The key of `site`'s `batch`-th rays.
fn site_key(site: &Site, batch: usize) -> SiteKey {
    (site.triangle, site.back, batch, site.bary.map(f64::to_bits))
}

impl GatherCache {
    /// Empties the cache if its crossings were traced among another number of static
    /// triangles than `statics`.
    fn keep_for(&self, statics: usize) {
        if let Ok(mut kept) = self.inner.write()
            && kept.statics != statics
        {
            *kept = Kept {
                statics,
                ..Kept::default()
            };
        }
    }

    /// The crossings of `site`'s `batch`-th rays, traced by `trace` if not kept.
    fn crossings(
        &self,
        (site, batch): (&Site, usize),
        trace: impl FnOnce() -> Vec<Crossing>,
    ) -> std::sync::Arc<[Crossing]> {
        let key = site_key(site, batch);
        if let Some(found) = (self.inner.read().ok()).and_then(|k| k.crossings.get(&key).cloned()) {
            return found;
        }
        let traced: std::sync::Arc<[Crossing]> = trace().into();
        let bytes = 64 + traced.len() * size_of::<Crossing>();
        if let Ok(mut kept) = self.inner.write()
            && kept.bytes + bytes <= GATHER_CACHE_BYTES
            && kept.crossings.insert(key, traced.clone()).is_none()
        {
            kept.bytes += bytes;
        }
        traced
    }

    /// The moving geometry's reach over the timeline of `scene` (computed once).
    fn swept(&self, scene: &Scene) -> std::sync::Arc<Swept> {
        if let Some(swept) = self.inner.read().ok().and_then(|k| k.swept.clone()) {
            return swept;
        }
        let swept = std::sync::Arc::new(Swept::of(scene));
        if let Ok(mut kept) = self.inner.write() {
            kept.swept = Some(swept.clone());
        }
        swept
    }

    /// The form factor from `site` to the sampled emitter `emitter` and its variance, if kept
    /// for the lighting `key`.
    fn direct(&self, (site, emitter): (&Site, usize), key: u64) -> Option<(f64, f64)> {
        let kept = self.inner.read().ok()?;
        (kept.direct.0 == key)
            .then(|| kept.direct.1.get(&site_key(site, emitter)).copied())
            .flatten()
    }

    /// Keeps `direct`, the form factor from `site` to the sampled emitter `emitter` and its
    /// variance with the lighting `key` (forgetting those of another lighting), within
    /// [`GATHER_CACHE_BYTES`].
    fn keep_direct(&self, (site, emitter): (&Site, usize), key: u64, direct: (f64, f64)) {
        let bytes = 64 + size_of::<(f64, f64)>();
        let Ok(mut kept) = self.inner.write() else {
            return;
        };
        if kept.direct.0 != key {
            let dropped = kept.direct.1.len() * bytes;
            kept.bytes -= dropped.min(kept.bytes);
            kept.direct = (key, std::collections::HashMap::new());
        }
        if kept.bytes + bytes <= GATHER_CACHE_BYTES
            && kept
                .direct
                .1
                .insert(site_key(site, emitter), direct)
                .is_none()
        {
            kept.bytes += bytes;
        }
    }

    /// The shadow rays from `site` to the sampled emitter `emitter` with the lighting `key`,
    /// sampled by `sample` if not kept (and kept, forgetting those of another lighting, within
    /// [`GATHER_CACHE_BYTES`]).
    fn direct_rays(
        &self,
        (site, emitter): (&Site, usize),
        key: u64,
        sample: impl FnOnce() -> PointRays,
    ) -> std::sync::Arc<PointRays> {
        let site_key = site_key(site, emitter);
        if let Some(found) = (self.inner.read().ok())
            .filter(|k| k.rays.0 == key)
            .and_then(|k| k.rays.1.get(&site_key).cloned())
        {
            return found;
        }
        let sampled = std::sync::Arc::new(sample());
        let bytes = 64 + sampled.bytes();
        if let Ok(mut kept) = self.inner.write() {
            if kept.rays.0 != key {
                let dropped: usize = (kept.rays.1.values()).map(|r| 64 + r.bytes()).sum();
                kept.bytes -= dropped.min(kept.bytes);
                kept.rays = (key, std::collections::HashMap::new());
            }
            if kept.bytes + bytes <= GATHER_CACHE_BYTES
                && kept.rays.1.insert(site_key, sampled.clone()).is_none()
            {
                kept.bytes += bytes;
            }
        }
        sampled
    }

    /// The linear forms of `site`'s `batch`-th rays, if kept for the lighting `key`.
    fn forms(&self, (site, batch): (&Site, usize), key: u64) -> Option<Vec<Option<Linear>>> {
        let kept = self.inner.read().ok()?;
        if kept.forms.0 != key {
            return None;
        }
        let forms = kept.forms.1.get(&site_key(site, batch))?;
        Some(forms.iter().map(|f| f.map(Form::linear)).collect())
    }

    /// Keeps `forms`, the linear forms of `site`'s `batch`-th rays with the lighting `key`
    /// (forgetting those of another lighting), within [`GATHER_CACHE_BYTES`].
    fn keep_forms(&self, (site, batch): (&Site, usize), key: u64, forms: Vec<Option<Linear>>) {
        let forms: std::sync::Arc<[Option<Form>]> =
            forms.iter().map(|f| f.as_ref().map(Form::of)).collect();
        let bytes = 64 + forms.len() * size_of::<Option<Form>>();
        let Ok(mut kept) = self.inner.write() else {
            return;
        };
        if kept.forms.0 != key {
            let dropped: usize = (kept.forms.1.values())
                .map(|f| 64 + f.len() * size_of::<Option<Form>>())
                .sum();
            kept.bytes -= dropped.min(kept.bytes);
            kept.forms = (key, std::collections::HashMap::new());
        }
        if kept.bytes + bytes <= GATHER_CACHE_BYTES
            && kept.forms.1.insert(site_key(site, batch), forms).is_none()
        {
            kept.bytes += bytes;
        }
    }

    /// The forms of `site`'s `batch`-th rays kept with their paths for the lighting `key`.
    fn paths(
        &self,
        (site, batch): (&Site, usize),
        key: u64,
    ) -> Option<std::sync::Arc<[Option<KeptPath>]>> {
        let kept = self.inner.read().ok()?;
        (kept.paths.0 == key)
            .then(|| kept.paths.1.get(&site_key(site, batch)).cloned())
            .flatten()
    }

    /// Keeps the forms and paths `found` of `site`'s `batch`-th rays with the lighting `key`
    /// where none is kept yet (forgetting those of another lighting), within
    /// [`GATHER_CACHE_BYTES`]. Any frame finds the same form for a ray whose path is clear.
    fn keep_paths(&self, (site, batch): (&Site, usize), key: u64, found: Vec<Option<KeptPath>>) {
        let size = |paths: &[Option<KeptPath>]| -> usize {
            64 + (paths.iter().flatten())
                .map(|(tests, _)| size_of::<KeptPath>() + tests.len() * size_of::<PathTest>())
                .sum::<usize>()
                + std::mem::size_of_val(paths)
        };
        let Ok(mut kept) = self.inner.write() else {
            return;
        };
        if kept.paths.0 != key {
            let dropped: usize = (kept.paths.1.values()).map(|p| size(p)).sum();
            kept.bytes -= dropped.min(kept.bytes);
            kept.paths = (key, std::collections::HashMap::new());
        }
        let site_key = site_key(site, batch);
        let mut merged: Vec<Option<KeptPath>> = match kept.paths.1.get(&site_key) {
            Some(old) => old.to_vec(),
            None => vec![None; found.len()],
        };
        let before = size(&merged);
        let mut added = false;
        for (slot, new) in merged.iter_mut().zip(found) {
            if slot.is_none() && new.is_some() {
                *slot = new;
                added = true;
            }
        }
        let after = size(&merged);
        let had = kept.paths.1.contains_key(&site_key);
        let grow = after - if had { before } else { 0 };
        if added && kept.bytes + grow <= GATHER_CACHE_BYTES {
            kept.paths.1.insert(site_key, merged.into());
            kept.bytes += grow;
        }
    }

    /// Bytes held.
    #[must_use]
    pub fn bytes(&self) -> usize {
        self.inner.read().map_or(0, |k| k.bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tetrahedron_meets_the_boxes_its_rays_cross_and_not_those_beside_it_in_its_bounds() {
        // From a point on the floor to a ceiling triangle over x ∈ [2, 3]: the rays rise
        // to the right, so a door standing at x = 0.5 left of the apex meets none of them,
        // though it is within the tetrahedron's bounds.
        let p = [
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(2.0, 2.0, -0.5),
            DVec3::new(3.0, 2.0, -0.5),
            DVec3::new(2.5, 2.0, 0.5),
        ];
        let beside = (DVec3::new(0.4, 1.5, -0.5), DVec3::new(0.6, 2.0, 0.5));
        let (lo, hi) = (DVec3::new(0.0, 0.0, -1.0), DVec3::new(3.0, 2.0, 1.0));
        assert!((0..3).all(|k| beside.0[k] >= lo[k] - 1.0 && beside.1[k] <= hi[k]));
        assert!(!tetrahedron_meets_box(p, beside));
        // Above the tetrahedron's lower face, left of its apex: outside, by a face's plane.
        assert!(!tetrahedron_meets_box(
            p,
            (DVec3::new(1.2, 1.2, -0.1), DVec3::new(1.4, 1.4, 0.1))
        ));
        // Across the rays, or holding the apex: met.
        let across = (DVec3::new(1.6, 0.9, -0.1), DVec3::new(1.8, 1.1, 0.1));
        assert!(tetrahedron_meets_box(p, across));
        let apex = (DVec3::new(0.9, -0.1, -0.1), DVec3::new(1.1, 0.1, 0.1));
        assert!(tetrahedron_meets_box(p, apex));
        // Beyond its bounds: not met.
        assert!(!tetrahedron_meets_box(
            p,
            (DVec3::new(4.0, 0.0, 0.0), DVec3::new(5.0, 1.0, 1.0))
        ));
    }
}
