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
//!   distance), each with a shadow ray to the light. A patch that faces away, or lies outside
//!   a spot's cone or beyond the light's range, costs nothing. (Black patches are lit too: a
//!   relighting may give them a reflectance.)
//! - **Directional lights** are a bundle of parallel lines (METHOD.md §1's construction with
//!   one direction), about 256 per patch of median area. A patch facing the light at θ gets
//!   `E⊥·cos θ` times the fraction of the lines crossing it whose first crossing it is: exact
//!   where nothing shadows it, line-sampled where a shadow edge crosses it.
//!
//! Each light's result is kept per distinct state (its pose, and the moving geometry's): a
//! fixed lamp over static geometry is computed once for the whole timeline.

pub mod area;
pub mod points;
pub mod reference;

use std::collections::HashMap;
use std::hash::{Hash, Hasher};

use glam::{DVec3, Vec3};
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;

use crate::control::{Control, TraceError};
use crate::lines::{LINE_LENGTH, parallel_bundle};
use crate::scene::subdivide::normal_and_area;
use crate::scene::{Faces, Light, LightKind, Scene};
use crate::trace::coincident::{COINCIDENT, mix, resolve};
use crate::trace::{FrameMeshes, Hit, Line, SceneTracer};

/// Lines of a directional light per patch of median area: they resolve shadow edges to about
/// 1/16 of such a patch's side.
const LINES_PER_PATCH: f64 = 256.0;

/// Most lines of one directional light at one frame.
const MAX_DIRECTIONAL_LINES: f64 = 4.0e6;

/// A shadow ray ignores crossings this close to its end (normalised units): the surface of an
/// emitter it ends on, and surfaces touching the light. At its start only the crossings within
/// [`COINCIDENT`] are examined apart (the surface it starts on, its neighbours across an edge
/// through the point): a surface crossed just beyond, such as the wall meeting a floor at a
/// point a hair from their corner, shadows it.
const SHADOW_EPSILON: f32 = 1e-5;

/// The direct irradiance of every frame, per light and patch, shared between frames where
/// nothing it depends on changes.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct DirectLight {
    /// Per light: for each frame, its entry in that light's `terms`. A light that does not move
    /// over static geometry has one entry for the whole timeline, whatever the others do.
    frame_term: Vec<Vec<u32>>,
    /// Per light, per distinct state: the irradiance of each patch per unit of light power
    /// (f32: far finer than the sampling of the patch).
    terms: Vec<Vec<Vec<f32>>>,
    /// The variance of each value of `terms`, from its sampling.
    variances: Vec<Vec<Vec<f32>>>,
    /// For each frame, the index of its combination of every light's state: frames with equal
    /// states have equal direct light.
    frame_state: Vec<u32>,
    /// Whether the states after frame 0's are still to be computed ([`area::Poses::First`]).
    #[serde(default)]
    pending: bool,
}

impl DirectLight {
    /// Computes the direct light of every frame of `scene` (nothing if it has no lights),
    /// counting one unit of `control`'s stage per light state computed and stopping early if
    /// it is cancelled. Frames where a light and the moving geometry are posed alike share
    /// that light's computation.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` was cancelled.
    pub fn compute(
        scene: &Scene,
        tracer: &SceneTracer,
        control: &Control,
    ) -> Result<Self, TraceError> {
        Self::compute_poses(scene, tracer, area::Poses::All, control)
    }

    /// [`DirectLight::compute`] at the `poses` given: with [`area::Poses::First`], each light's
    /// state at frame 0 alone (the same values), the others left [`DirectLight::pending`].
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` was cancelled.
    pub fn compute_poses(
        scene: &Scene,
        tracer: &SceneTracer,
        poses: area::Poses,
        control: &Control,
    ) -> Result<Self, TraceError> {
        if scene.lights.is_empty() {
            return Ok(Self::default());
        }
        let frames = scene.frames.count;
        let moving = !scene.objects.is_empty();
        let geometry: Vec<u64> = (0..frames)
            .map(|f| if moving { geometry_key(scene, f) } else { 0 })
            .collect();
        // Per light: each frame's state and the first frame of every distinct state.
        let mut frame_term = Vec::with_capacity(scene.lights.len());
        let mut jobs: Vec<(usize, usize)> = Vec::new();
        for (l, light) in scene.lights.iter().enumerate() {
            let mut first_of: HashMap<(u64, u64), u32> = HashMap::new();
            let mut states = Vec::with_capacity(frames);
            let mut count = 0;
            for (f, &g) in geometry.iter().enumerate() {
                let key = (pose_key(light, f), g);
                let state = *first_of.entry(key).or_insert_with(|| {
                    jobs.push((l, f));
                    count += 1;
                    count - 1
                });
                states.push(state);
            }
            frame_term.push(states);
        }
        control.add_work(jobs.len() as u64);
        // Frame 0 is the first of its states: each light's state 0.
        let pending = poses == area::Poses::First && jobs.iter().any(|&(_, f)| f > 0);
        if pending {
            control.advance(jobs.iter().filter(|&&(_, f)| f > 0).count() as u64);
            jobs.retain(|&(_, f)| f == 0);
        }
        // One posed scene per frame that needs one, shared by its lights. In frame order, so
        // each light's states come out in the order they were numbered.
        let mut grouped: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
        for &(l, f) in &jobs {
            grouped.entry(f).or_default().push(l);
        }
        let by_frame: Vec<(usize, Vec<usize>)> = grouped.into_iter().collect();
        let computed: Vec<Vec<(usize, Term)>> = by_frame
            .par_iter()
            .map(|(f, lights)| {
                if control.is_cancelled() {
                    return Vec::new();
                }
                let out = frame_irradiance(scene, tracer, *f, lights);
                control.advance(lights.len() as u64);
                out
            })
            .collect();
        if control.is_cancelled() {
            return Err(TraceError::Cancelled);
        }
        let mut terms: Vec<Vec<Vec<f32>>> = vec![Vec::new(); scene.lights.len()];
        let mut variances = terms.clone();
        for (l, (term, variance)) in computed.into_iter().flatten() {
            terms[l].push(term);
            variances[l].push(variance);
        }
        let mut combos: HashMap<Vec<u32>, u32> = HashMap::new();
        let frame_state = (0..frames)
            .map(|f| {
                let combo: Vec<u32> = frame_term.iter().map(|states| states[f]).collect();
                let next = combos.len() as u32;
                *combos.entry(combo).or_insert(next)
            })
            .collect();
        Ok(Self {
            frame_term,
            terms,
            variances,
            frame_state,
            pending,
        })
    }

    /// Whether the states after frame 0's are still to be computed ([`area::Poses::First`]).
    #[must_use]
    pub fn pending(&self) -> bool {
        self.pending
    }

    /// Computes the states [`area::Poses::First`] left pending (all of them again, as
    /// [`DirectLight::compute`] does: the same values).
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` was cancelled (the light is left as it was).
    pub fn complete(
        &mut self,
        scene: &Scene,
        tracer: &SceneTracer,
        control: &Control,
    ) -> Result<(), TraceError> {
        if self.pending {
            *self = Self::compute(scene, tracer, control)?;
        }
        Ok(())
    }

    /// Whether there is any direct light.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.terms.is_empty()
    }

    /// Which combination of light states frame `frame` is in: frames with equal states have
    /// equal direct light.
    #[must_use]
    pub fn state(&self, frame: usize) -> Option<usize> {
        self.frame_state.get(frame).map(|&s| s as usize)
    }

    /// Irradiance of every patch at `frame` (RGB, lux) with the lights at `power` (colour ×
    /// intensity per light, in the scene's order); `None` without lights.
    #[must_use]
    pub fn irradiance(&self, frame: usize, power: &[[f64; 3]]) -> Option<Vec<[f64; 3]>> {
        self.sum(frame, &self.terms, power, |p| p)
    }

    /// The variance of [`DirectLight::irradiance`] from its sampling (lux²); `None` without
    /// lights. The lights are sampled independently: their variances add.
    #[must_use]
    pub fn variance(&self, frame: usize, power: &[[f64; 3]]) -> Option<Vec<[f64; 3]>> {
        self.sum(frame, &self.variances, power, |p| p * p)
    }

    /// The same lights for patches cut from these: new patch `k` takes the irradiance of patch
    /// `parents[k]` (its average over the parent, not its own), until computed again.
    #[must_use]
    pub fn inherit(&self, parents: &[u32]) -> Self {
        let map = |per_light: &[Vec<Vec<f32>>]| -> Vec<Vec<Vec<f32>>> {
            per_light
                .iter()
                .map(|states| {
                    states
                        .iter()
                        .map(|unit| parents.iter().map(|&p| unit[p as usize]).collect())
                        .collect()
                })
                .collect()
        };
        Self {
            frame_term: self.frame_term.clone(),
            terms: map(&self.terms),
            variances: map(&self.variances),
            frame_state: self.frame_state.clone(),
            pending: self.pending,
        }
    }

    /// Σ over lights of `weight(power)` times the light's unit value per patch in `per_light`
    /// (its terms or their variances) at `frame`; `None` without lights.
    fn sum(
        &self,
        frame: usize,
        per_light: &[Vec<Vec<f32>>],
        power: &[[f64; 3]],
        weight: fn(f64) -> f64,
    ) -> Option<Vec<[f64; 3]>> {
        self.state(frame)?;
        let patches = per_light.first()?.first().map_or(0, Vec::len);
        let mut out = vec![[0.0; 3]; patches];
        for ((states, values), p) in self.frame_term.iter().zip(per_light).zip(power) {
            let Some(unit) = values.get(states[frame] as usize) else {
                panic!("the direct light of frame {frame} was not computed (states pending)");
            };
            let w = p.map(weight);
            for (e, &u) in out.iter_mut().zip(unit) {
                for c in 0..3 {
                    e[c] += w[c] * f64::from(u);
                }
            }
        }
        Some(out)
    }

    /// Memory held, bytes.
    #[must_use]
    pub fn memory(&self) -> usize {
        let terms: usize = 2 * self
            .terms
            .iter()
            .flatten()
            .map(|v| v.len() * 4)
            .sum::<usize>();
        terms + 4 * (self.frame_term.iter().map(Vec::len).sum::<usize>() + self.frame_state.len())
    }
}

/// The bits of a light's pose at `frame`, hashed.
fn pose_key(light: &Light, frame: usize) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    light
        .pose(frame)
        .to_cols_array()
        .iter()
        .for_each(|v| v.to_bits().hash(&mut h));
    h.finish()
}

/// The moving geometry's vertices at `frame`, hashed: a shadow can change only with them.
fn geometry_key(scene: &Scene, frame: usize) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for object in &scene.objects {
        object
            .positions_at(frame)
            .iter()
            .for_each(|p| p.to_array().map(f32::to_bits).hash(&mut h));
    }
    h.finish()
}

/// A light's unit irradiance per patch, and its variance.
type Term = (Vec<f32>, Vec<f32>);

/// Unit irradiance per patch at `frame` of each light in `lights` (indices into the scene's),
/// with its variance.
fn frame_irradiance(
    scene: &Scene,
    tracer: &SceneTracer,
    frame: usize,
    lights: &[usize],
) -> Vec<(usize, Term)> {
    let posed = Posed::at(scene, tracer, frame);
    let at = posed.frame(scene, tracer, Occluders::All);
    lights
        .iter()
        .map(|&l| {
            let light = &scene.lights[l];
            let unit = match light.kind {
                LightKind::Directional => directional(&at, light),
                _ => point(&at, light, l),
            };
            let values = unit.iter().map(|e| e.0 as f32).collect();
            (l, (values, unit.iter().map(|e| e.1 as f32).collect()))
        })
        .collect()
}

/// What a [`Frame`] borrows: the scene's triangles and deforming meshes at one frame.
struct Posed {
    frame: usize,
    deformed: FrameMeshes,
    triangles: Vec<([Vec3; 3], Faces)>,
}

impl Posed {
    fn at(scene: &Scene, tracer: &SceneTracer, frame: usize) -> Self {
        Self {
            frame,
            deformed: tracer.deformed_at(scene, frame),
            triangles: scene.triangles_at(frame),
        }
    }

    /// The posed scene with `occluders` for its shadow rays.
    fn frame<'a>(
        &'a self,
        scene: &'a Scene,
        tracer: &'a SceneTracer,
        occluders: Occluders,
    ) -> Frame<'a> {
        Frame {
            scene,
            tracer,
            deformed: &self.deformed,
            triangles: &self.triangles,
            frame: self.frame,
            occluders,
        }
    }
}

/// The scene posed at one frame, ready for shadow rays.
struct Frame<'a> {
    scene: &'a Scene,
    tracer: &'a SceneTracer,
    deformed: &'a FrameMeshes,
    /// Every traced triangle at the frame (index = global triangle id) with its faces.
    triangles: &'a [([Vec3; 3], Faces)],
    frame: usize,
    /// What occludes.
    occluders: Occluders,
}

/// What a [`Frame`]'s shadow rays are tested against.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Occluders {
    /// The whole scene as posed at the frame.
    All,
    /// The static geometry only: what every frame shares (see [`area`]).
    Static,
    /// The moving objects only (where the static geometry's verdict is known).
    Moving,
}

impl Frame<'_> {
    /// Every crossing of `line` with the occluders, sorted along it.
    fn trace(&self, line: &Line, hits: &mut Vec<Hit>) {
        self.trace_until(line, LINE_LENGTH, hits);
    }

    /// [`Frame::trace`] for `0 < t < t_max` only.
    fn trace_until(&self, line: &Line, t_max: f32, hits: &mut Vec<Hit>) {
        let (tracer, frame, deformed) = (self.tracer, self.frame, self.deformed);
        match self.occluders {
            Occluders::All => tracer.trace_frame_until(line, frame, deformed, t_max, hits),
            Occluders::Static => {
                hits.clear();
                tracer.trace_static(line, t_max, hits);
                hits.sort_unstable_by(Hit::order);
            }
            Occluders::Moving => {
                hits.clear();
                tracer.trace_moving(line, frame, deformed, t_max, hits);
                hits.sort_unstable_by(Hit::order);
            }
        }
    }

    /// Whether `found` holds for a crossing of `line` with the occluders, `0 < t < t_max`,
    /// looked at in no particular order: the walk stops at the first it holds for.
    fn any_until(&self, line: &Line, t_max: f32, found: &mut impl FnMut(Hit) -> bool) -> bool {
        let (tracer, frame, deformed) = (self.tracer, self.frame, self.deformed);
        match self.occluders {
            Occluders::All => tracer.any_frame_until(line, (frame, deformed), t_max, found),
            Occluders::Static => tracer.any_static(line, t_max, found),
            Occluders::Moving => tracer.any_moving(line, (frame, deformed), t_max, found),
        }
    }

    /// Whether anything but triangle `own` crosses the segment from `from`, a point on one of
    /// `own`'s faces (its back if `back`), to `to`. A surface touching that face (a contact,
    /// [`crate::trace::coincident`]) blocks it too: a face pressed against a wall is not lit
    /// through the wall. The walk stops at the first blocker.
    fn blocked(&self, from: DVec3, to: DVec3, own: u32, back: bool) -> bool {
        let d = to - from;
        let length = d.length();
        let (line, t_max) = from_behind(from, d / length, length);
        let (start, end) = (BEHIND as f32, (BEHIND + length) as f32 - SHADOW_EPSILON);
        self.any_until(&line, t_max, &mut |h| {
            (h.surface() != own && h.t > start + COINCIDENT && h.t < end)
                || self.touching_at(h, start, (own, back))
        })
    }

    /// Whether anything crosses the segment from `from`, a point on no surface (a light
    /// probe's), to `to`, short of `to` itself.
    fn blocked_between(&self, from: DVec3, to: DVec3) -> bool {
        let d = to - from;
        let length = d.length();
        if length <= 0.0 || !length.is_finite() {
            return false;
        }
        let (line, t_max) = from_behind(from, d / length, length);
        let (start, end) = (BEHIND as f32, (BEHIND + length) as f32 - SHADOW_EPSILON);
        self.any_until(&line, t_max, &mut |h| h.t > start && h.t < end)
    }

    /// Whether a surface touches face `back` (or the front) of triangle `own`, of unit normal
    /// `n` on that side, at `x` (a box standing on a floor covers the floor under it): the
    /// touching surface [`Frame::blocked`] finds at the start of every shadow ray from there,
    /// looked for along the normal.
    fn covered(&self, x: DVec3, n: DVec3, face: (u32, bool)) -> bool {
        let (line, t_max) = from_behind(x, n, 0.0);
        self.any_until(&line, t_max, &mut |h| {
            self.touching_at(h, BEHIND as f32, face)
        })
    }

    /// Whether crossing `h` of a line from [`from_behind`], whose start is at
    /// `start`, is a surface touching face `back` (or the front) of triangle `own` there.
    fn touching_at(&self, h: Hit, start: f32, (own, back): (u32, bool)) -> bool {
        h.surface() != own
            && (h.t - start).abs() <= COINCIDENT
            && self.tracer.surfaces().touching(own, back, h)
    }
}

/// How far behind a point its shadow rays start ([`from_behind`]).
const BEHIND: f64 = (4.0 * COINCIDENT) as f64;

/// The line through `x` along unit `direction` from [`BEHIND`] behind `x`, so that a surface
/// touching the face `x` lies on is crossed whichever side of `x` rounding puts it, and how
/// far to walk it: `reach` past `x` and a little more. (`x` is at [`BEHIND`] along it.)
fn from_behind(x: DVec3, direction: DVec3, reach: f64) -> (Line, f32) {
    let line = Line {
        origin: (x - direction * BEHIND).as_vec3(),
        direction: direction.as_vec3(),
    };
    let t_max = (BEHIND + reach) as f32 + 4.0 * COINCIDENT;
    (line, t_max.min(LINE_LENGTH))
}

/// Subdivision level of [`visible_shares`]' points: 64 per face (one per stratum).
const VISIBLE_LEVEL: u32 = 3;

/// Per patch of `scene` at `frame`, the share of its area that no surface touches (a floor
/// patch partly under a box: what can be seen of it, and what light reaches), for the patches
/// `which` marks (those whose crossings met a contact); 1 for the others. Each face is tested
/// at 64 stratified points (deterministic), a merged patch's faces weighed by their areas.
/// The direct light sampled over a patch is its visible part's times this share (a covered
/// point's shadow rays are blocked where they start), so dividing by it gives the visible
/// part's, as the lines' tallies do ([`crate::solve::tally::HIDDEN`]). Each share comes with
/// the variance of its estimate (by collapsed strata, as the direct light's: only strata an
/// outline crosses add to it), 0 for the unmarked patches.
///
/// `kept` holds the shares of static faces that no moving object came near at the frames
/// they were measured at (their shares are then the static geometry's, the same at every
/// such frame): each is measured once per timeline, where every frame measured them all.
#[must_use]
pub fn visible_shares(
    scene: &Scene,
    tracer: &SceneTracer,
    frame: usize,
    which: &[bool],
    kept: &KeptShares,
) -> Vec<(f64, f64)> {
    let patches = scene.patches.len();
    if !which.iter().any(|&w| w) {
        return vec![(1.0, 0.0); patches];
    }
    let posed = Posed::at(scene, tracer, frame);
    let at = posed.frame(scene, tracer, Occluders::All);
    let statics = scene.statics.triangles.len();
    // Where the moving objects are at the frame, grown by more than a coverage test reaches
    // ([`Frame::covered`]: 8·COINCIDENT from its point).
    let now = points::Swept::at(scene, frame, false);
    let known = kept.read(statics);
    // Per face of a marked patch: (patch, area, share of its points covered by nothing and
    // the variance of that share), and whether it is to be kept.
    let faces: Vec<(u32, f64, Share, Option<FaceKey>)> = (at.triangles.par_iter().enumerate())
        .flat_map_iter(|(t, (corners, faces))| {
            let corners = corners.map(Vec3::as_dvec3);
            let (normal, area) = normal_and_area(corners);
            let (at, now, known) = (&at, &now, &known);
            [(Some(faces.front), false), (faces.back, true)]
                .into_iter()
                .filter_map(move |(patch, back)| {
                    let p = patch?;
                    if !which[p as usize] || area <= 0.0 {
                        return None;
                    }
                    let key = (t as u32, back);
                    let (lo, hi) = (corners.iter())
                        .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &c| {
                            (lo.min(c), hi.max(c))
                        });
                    let alone = t < statics && !now.meets_box(lo, hi);
                    if alone && let Some(&share) = known.get(&key) {
                        return Some((p, area, share, None));
                    }
                    let n = if back { -normal } else { normal };
                    let mut rng =
                        Xoshiro256PlusPlus::seed_from_u64(mix(2 * t as u64 + u64::from(back)));
                    let mut points = Vec::new();
                    sample_points(inset(&corners), VISIBLE_LEVEL, &mut rng, &mut points);
                    let open: Vec<f64> = (points.iter())
                        .map(|&x| f64::from(u8::from(!at.covered(x, n, key))))
                        .collect();
                    Some((p, area, collapsed_variance(&open), alone.then_some(key)))
                })
        })
        .collect();
    drop(known);
    kept.keep(
        statics,
        faces
            .iter()
            .filter_map(|&(_, _, share, key)| Some((key?, share))),
    );
    let mut sums = vec![[0.0; 3]; patches];
    for (p, area, (share, variance), _) in faces {
        let s = &mut sums[p as usize];
        s[0] += area * share;
        s[1] += area * area * variance;
        s[2] += area;
    }
    sums.into_iter()
        .map(|[open, variance, area]| {
            if area > 0.0 {
                (open / area, variance / (area * area))
            } else {
                (1.0, 0.0)
            }
        })
        .collect()
}

/// The visible shares ([`visible_shares`]) of static faces measured where nothing moving came
/// near them, by (triangle, back face): the same at every frame where nothing moving comes
/// near. Emptied when the static triangles they were measured on change (by their number:
/// a cut only adds triangles).
#[derive(Debug, Default)]
pub struct KeptShares {
    inner: std::sync::RwLock<(usize, std::sync::Arc<SharesByFace>)>,
}

/// A face: (triangle, back face).
type FaceKey = (u32, bool);

/// A visible share and the variance of its estimate.
type Share = (f64, f64);

/// Visible shares by face.
type SharesByFace = HashMap<FaceKey, Share>;

impl KeptShares {
    /// The shares kept for a scene of `statics` static triangles (none if they were kept
    /// for another).
    fn read(&self, statics: usize) -> std::sync::Arc<SharesByFace> {
        let kept = self
            .inner
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if kept.0 == statics {
            kept.1.clone()
        } else {
            std::sync::Arc::default()
        }
    }

    /// Keeps `shares` of a scene of `statics` static triangles.
    fn keep(&self, statics: usize, shares: impl Iterator<Item = (FaceKey, Share)>) {
        let mut shares = shares.peekable();
        if shares.peek().is_none() {
            return;
        }
        let mut kept = self
            .inner
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if kept.0 != statics {
            *kept = (statics, std::sync::Arc::default());
        }
        std::sync::Arc::make_mut(&mut kept.1).extend(shares);
    }

    /// Bytes held, about.
    #[must_use]
    pub fn bytes(&self) -> usize {
        let kept = self
            .inner
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        kept.1.capacity() * (size_of::<FaceKey>() + size_of::<Share>() + 1)
    }
}

/// The points a patch is sampled at: one uniformly random point in each of the 4^level
/// equal-area triangles of `level` midpoint subdivisions (stratified: unbiased for the patch's
/// mean). Consecutive pairs are siblings, the strata [`collapsed_variance`] pairs.
fn sample_points(
    corners: [DVec3; 3],
    level: u32,
    rng: &mut Xoshiro256PlusPlus,
    out: &mut Vec<DVec3>,
) {
    if level == 0 {
        out.push(triangle_point(&corners, rng.random(), rng.random()));
        return;
    }
    let [a, b, c] = corners;
    let (ab, bc, ca) = ((a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5);
    for t in [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]] {
        sample_points(t, level - 1, rng, out);
    }
}

/// Triangle `t` shrunk towards its centroid so that every point of it lies at least
/// `8·COINCIDENT` from its edges (at most halfway): a shadow ray from a point a hair from an
/// edge could cross the neighbouring face inside the window where crossings at its start are
/// taken for the surface it starts on, and leak. The mean over the shrunk triangle differs from
/// the whole one's by far less than the sampling's error (4e-6 of the radius in 5e-5 of it).
fn inset(t: &[DVec3; 3]) -> [DVec3; 3] {
    let (centre, scale) = inset_scale(t);
    t.map(|p| centre + (p - centre) * scale)
}

/// The `g × g` strata of the unit square, row after row, each point jittered uniformly within
/// its stratum by a generator seeded with `seed`: the same points for the same seed.
pub(super) fn strata(g: usize, seed: u64) -> impl Iterator<Item = (f64, f64)> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    (0..g * g).map(move |k| {
        let u = ((k / g) as f64 + rng.random::<f64>()) / g as f64;
        let v = ((k % g) as f64 + rng.random::<f64>()) / g as f64;
        (u, v)
    })
}

/// Point `p` of triangle `t` moved as [`inset`] moves the triangle's corners.
fn into_inset(p: DVec3, t: &[DVec3; 3]) -> DVec3 {
    let (centre, scale) = inset_scale(t);
    centre + (p - centre) * scale
}

/// The centroid [`inset`] shrinks triangle `t` towards, and the factor.
fn inset_scale(t: &[DVec3; 3]) -> (DVec3, f64) {
    let centre = (t[0] + t[1] + t[2]) / 3.0;
    let area2 = (t[1] - t[0]).cross(t[2] - t[0]).length();
    let perimeter: f64 = (0..3).map(|k| t[k].distance(t[(k + 1) % 3])).sum();
    let inradius = area2 / perimeter.max(f64::MIN_POSITIVE);
    let shrink = (8.0 * f64::from(COINCIDENT) / inradius.max(f64::MIN_POSITIVE)).min(0.5);
    (centre, 1.0 - shrink)
}

/// The point of triangle `t` at `(u, v)` in the unit square, area-preserving.
fn triangle_point(t: &[DVec3; 3], u: f64, v: f64) -> DVec3 {
    let s = u.sqrt();
    t[0] * (1.0 - s) + t[1] * (s * (1.0 - v)) + t[2] * (s * v)
}

/// The mean of `values`, one per stratum of equal weight, and its variance by collapsed strata:
/// each pair of neighbouring strata (0 and 1, 2 and 3, …) as one stratum of two samples,
/// `Σ (a − b)² / n²`. Conservative: the pair's difference of means adds to it.
fn collapsed_variance(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let spread: f64 = values.chunks_exact(2).map(|p| (p[0] - p[1]).powi(2)).sum();
    (mean, spread / (n * n))
}

/// Subdivision level for a patch of longest edge `edge` seen from `distance`: 4 points while
/// the patch looks tiny from the light (its light varies little over it, and a large scene has
/// many such patches), 16 while small, 64 when it fills a wide angle.
fn sample_level(edge: f64, distance: f64) -> u32 {
    let ratio = edge / distance.max(f64::MIN_POSITIVE);
    match ratio {
        r if r < 0.05 => 1,
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

/// Unit irradiance per patch from a point or spot light (the scene's light `index`), and its
/// variance.
fn point(at: &Frame<'_>, light: &Light, index: usize) -> Vec<(f64, f64)> {
    let position = light.position(at.frame);
    let axis = light.direction(at.frame);
    let radius = at.scene.normalisation.radius;
    // Per face: its patch, its area and its (value, variance).
    type Sample = Option<(u32, f64, (f64, f64))>;
    let per_triangle: Vec<[Sample; 2]> = at
        .triangles
        .par_iter()
        .enumerate()
        .map(|(t, (corners, faces))| {
            let corners = corners.map(|c| c.as_dvec3());
            let (normal, area) = normal_and_area(corners);
            let sides = [(Some(faces.front), false), (faces.back, true)];
            sides.map(|(patch, back)| {
                let patch = patch?;
                let face = Face {
                    own: t as u32,
                    back,
                    corners,
                    n: if back { -normal } else { normal },
                };
                let seed = mix((u64::from(patch) << 32) ^ index as u64);
                let (value, variance) =
                    patch_irradiance(at, light, &face, (position, axis), (seed, None));
                let r2 = radius * radius;
                Some((patch, area, (value / r2, variance / (r2 * r2))))
            })
        })
        .collect();
    per_patch(
        at.scene.patches.len(),
        per_triangle.into_iter().flatten().flatten(),
    )
}

/// Per patch, the mean over its faces of their (value, variance), weighted by their areas:
/// `faces` gives each face's patch, area and values. A patch of one face takes its face's
/// values as they are; one merged from several faces ([`crate::scene::refine::merge`]) their
/// area average (the variance of a weighted sum of independent estimates).
fn per_patch(
    patches: usize,
    faces: impl IntoIterator<Item = (u32, f64, (f64, f64))>,
) -> Vec<(f64, f64)> {
    // Per patch: faces, Σ area, Σ area·value, Σ area²·variance, the last face's values.
    let mut sums = vec![(0u32, 0.0, 0.0, 0.0, (0.0, 0.0)); patches];
    for (p, area, (value, variance)) in faces {
        let s = &mut sums[p as usize];
        *s = (
            s.0 + 1,
            s.1 + area,
            s.2 + area * value,
            s.3 + area * area * variance,
            (value, variance),
        );
    }
    sums.into_iter()
        .map(|(n, area, value, variance, last)| match n {
            0 => (0.0, 0.0),
            1 => last,
            _ if area > 0.0 => (value / area, variance / (area * area)),
            _ => (0.0, 0.0),
        })
        .collect()
}

/// One face of a traced triangle, as a receiver of direct light.
struct Face {
    /// The triangle (global index).
    own: u32,
    /// Whether it is the triangle's back face.
    back: bool,
    corners: [DVec3; 3],
    /// The face's unit normal (zero if degenerate).
    n: DVec3,
}

/// Mean irradiance over `face` from a point or spot light at `position`, in units of
/// 1/(normalised distance)², and its variance; 0 for a face the light cannot reach. Sampled
/// with `seed` at the subdivision `level` given, or at [`sample_level`]'s for the face's size
/// and distance.
fn patch_irradiance(
    at: &Frame<'_>,
    light: &Light,
    face: &Face,
    (position, axis): (DVec3, DVec3),
    (seed, level): (u64, Option<u32>),
) -> (f64, f64) {
    let Face {
        own,
        back,
        corners,
        n,
    } = *face;
    // The light behind the face's plane: nothing (exact, the face is flat).
    if n == DVec3::ZERO || (position - corners[0]).dot(n) <= 0.0 {
        return (0.0, 0.0);
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
        return (0.0, 0.0);
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
            return (0.0, 0.0);
        }
    }
    let edge = (0..3)
        .map(|k| corners[k].distance(corners[(k + 1) % 3]))
        .fold(0.0, f64::max);
    let mut points = Vec::new();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    sample_points(
        inset(&corners),
        level.unwrap_or_else(|| sample_level(edge, distance)),
        &mut rng,
        &mut points,
    );
    let values: Vec<f64> = points
        .iter()
        .map(|&x| {
            let to_light = position - x;
            let d = to_light.length();
            let cos_surface = n.dot(to_light) / d;
            if cos_surface <= 0.0 {
                return 0.0;
            }
            let mut e = cos_surface / (d * d) * range_window(d, light.range);
            if let LightKind::Spot { inner, outer } = light.kind {
                e *= spot_attenuation(axis.dot(-to_light / d), inner, outer);
            }
            if e > 0.0 && !at.blocked(x, position, own, back) {
                e
            } else {
                -e
            }
        })
        .collect();
    shadowed_mean(&values)
}

/// The mean of `values`, one per stratum of [`sample_points`] (negative: the point is lit but
/// shadowed, its unshadowed value), and its variance.
fn shadowed_mean(values: &[f64]) -> (f64, f64) {
    let shadowed = values.iter().filter(|&&v| v < 0.0).count();
    let lit = values.iter().filter(|&&v| v > 0.0).count();
    let squares: f64 = values.iter().map(|v| v * v).sum();
    let values: Vec<f64> = values.iter().map(|&v| v.max(0.0)).collect();
    let (mean, collapsed) = collapsed_variance(&values);
    // Across a shadow's edge the pairs of strata are unreliable (see `area`): never less than
    // the binomial variance of the lit fraction there.
    let binomial = if lit > 0 && shadowed > 0 {
        let p = lit as f64 / (lit + shadowed) as f64;
        p * (1.0 - p) * squares / (values.len() * values.len()) as f64
    } else {
        0.0
    };
    (mean, collapsed.max(binomial))
}

/// A part of one face of a traced triangle, lit by [`parts_irradiance`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Part {
    /// The traced triangle (global index).
    pub triangle: u32,
    /// Whether the part is on the triangle's back face.
    pub back: bool,
    /// The part's corners in barycentric coordinates of the triangle's corners.
    pub corners: [[f64; 3]; 3],
    /// Seeds its sampling.
    pub seed: u64,
}

/// Subdivision level of [`sample_points`] a [`Part`] is sampled at: a point in each of 16
/// equal sub-triangles (eight pairs of strata for its variance), a shadow ray each per light.
/// Measured with `bench-patches --sizes auto` at 1M lines: with 4 points the parts' noise
/// steered `auto` on the level (1,715 patches at 6.0% at points, against 1,891 at 3.8% with
/// 16), and their cost is small beside the rounds' solves (0.35 s per scored frame on the
/// level's 2,950 patches).
const PART_LEVEL: u32 = 2;

/// Side of the grid of strata a [`Part`] is sampled at per sampled emitter ([`area`]): 16
/// points, as for the punctual lights.
const PART_GRID: usize = 4;

/// The irradiance straight from the lights over each of `parts` at `frame`, weighed over the
/// colour channels by `weight` (a luminance's coefficients, say), with the variance of its
/// estimate: the punctual lights at `power` (colour × intensity per light) and the emitters
/// `area` samples, with `materials`' emission. Each part is sampled at 16 stratified points,
/// whatever its size: enough to tell where the direct light varies over a patch (adaptive
/// patches), coarser than the patches' own direct light.
#[must_use]
pub fn parts_irradiance(
    (scene, tracer, area): (&Scene, &SceneTracer, &area::AreaLights),
    (frame, materials, power): (usize, &[crate::scene::Material], &[[f64; 3]]),
    weight: [f64; 3],
    parts: &[Part],
) -> Vec<(f64, f64)> {
    let dot = |c: [f64; 3]| weight[0] * c[0] + weight[1] * c[1] + weight[2] * c[2];
    let lights: Vec<(&Light, f64, (DVec3, DVec3))> = (scene.lights.iter().zip(power))
        .map(|(light, &p)| {
            (
                light,
                dot(p),
                (light.position(frame), light.direction(frame)),
            )
        })
        .filter(|l| l.1 > 0.0)
        .collect();
    if parts.is_empty() || (lights.is_empty() && area.is_empty()) {
        return vec![(0.0, 0.0); parts.len()];
    }
    let posed = Posed::at(scene, tracer, frame);
    let at = posed.frame(scene, tracer, Occluders::All);
    let emitters = area.posed(scene, tracer, &posed.triangles, |m| {
        materials.get(m as usize).map_or(0.0, |m| dot(m.emission))
    });
    let r2 = scene.normalisation.radius.powi(2);
    parts
        .par_iter()
        .map(|part| {
            let triangle = posed.triangles[part.triangle as usize]
                .0
                .map(|c| c.as_dvec3());
            let (normal, _) = normal_and_area(triangle);
            let corners = part
                .corners
                .map(|b| triangle[0] * b[0] + triangle[1] * b[1] + triangle[2] * b[2]);
            let face = Face {
                own: part.triangle,
                back: part.back,
                corners,
                n: if part.back { -normal } else { normal },
            };
            let mut sum = (0.0, 0.0);
            let mut add = |(value, variance): (f64, f64), w: f64| {
                sum = (sum.0 + w * value, sum.1 + w * w * variance);
            };
            for (k, &(light, w, pose)) in lights.iter().enumerate() {
                let seed = mix(part.seed ^ k as u64);
                match light.kind {
                    LightKind::Directional => add(sunlit(&at, pose.1, &face, seed), w),
                    _ => {
                        let sampling = (seed, Some(PART_LEVEL));
                        add(patch_irradiance(&at, light, &face, pose, sampling), w / r2);
                    }
                }
            }
            for (k, (emitter, w)) in emitters.iter().enumerate() {
                let seed = mix(part.seed ^ (lights.len() + k) as u64);
                let rays = area::Rays::Trace;
                let f = area::form_factor(&at, &face, emitter, (seed, PART_GRID), rays);
                add(f, *w);
            }
            sum
        })
        .collect()
}

/// Mean irradiance over `face` per lux of a directional light shining along `w`, and its
/// variance: [`PART_LEVEL`]'s points, a shadow ray each out of the scene.
fn sunlit(at: &Frame<'_>, w: DVec3, face: &Face, seed: u64) -> (f64, f64) {
    let cos = -face.n.dot(w);
    if face.n == DVec3::ZERO || cos <= 0.0 {
        return (0.0, 0.0);
    }
    let mut points = Vec::new();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    sample_points(inset(&face.corners), PART_LEVEL, &mut rng, &mut points);
    let away = w * f64::from(LINE_LENGTH);
    let values: Vec<f64> = points
        .iter()
        .map(|&x| {
            if at.blocked(x, x - away, face.own, face.back) {
                -cos
            } else {
                cos
            }
        })
        .collect();
    shadowed_mean(&values)
}

/// Unit irradiance per patch from a directional light: one bundle of parallel lines.
///
/// A patch facing the light at θ receives `cos θ` (per lux) where it is not in shadow; the
/// bundle measures the shadow: of the lines that cross the patch, the fraction whose first
/// crossing it is. An unshadowed patch is therefore exact, and the lines' only error is where
/// a shadow edge crosses a patch. A patch smaller than the grid, which no line crosses, is
/// tested with one shadow ray from its centroid.
fn directional(at: &Frame<'_>, light: &Light) -> Vec<(f64, f64)> {
    let scene = at.scene;
    let patches = scene.patches.len();
    let w = light.direction(at.frame);
    let out = vec![(0.0, 0.0); patches];
    if w == DVec3::ZERO {
        return out;
    }
    let geometry: Vec<(DVec3, f64)> = at
        .triangles
        .iter()
        .map(|(c, _)| normal_and_area(c.map(|p| p.as_dvec3())))
        .collect();
    let mut sorted: Vec<f64> = geometry
        .iter()
        .map(|&(_, area)| area)
        .filter(|&a| a > 0.0)
        .collect();
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
    // Per patch: lines crossing it towards its face, and those among them it stops first.
    // Integer sums, so the result does not depend on how the lines are split between threads.
    let (crossed, lit) = bundle
        .origins
        .par_iter()
        .fold(
            || (vec![0u32; patches], vec![0u32; patches], Vec::new()),
            |(mut crossed, mut lit, mut hits), &origin| {
                let line = Line {
                    origin,
                    direction: bundle.direction,
                };
                at.trace(&line, &mut hits);
                // The sun reaches the first crossing; coincident ones resolved as the tallies
                // do (a face in contact is in shadow, an overlap is shared).
                let resolved = resolve(&hits, &at.tracer.surfaces().along(bundle.direction));
                for (k, hit) in resolved.as_deref().unwrap_or(&hits).iter().enumerate() {
                    let faces = at.triangles[hit.surface() as usize].1;
                    let facing = if hit.front() {
                        Some(faces.front)
                    } else {
                        faces.back
                    };
                    if let Some(p) = facing {
                        crossed[p as usize] += 1;
                        lit[p as usize] += u32::from(k == 0);
                    }
                }
                (crossed, lit, hits)
            },
        )
        .map(|(crossed, lit, _)| (crossed, lit))
        .reduce(
            || (vec![0u32; patches], vec![0u32; patches]),
            |(mut a, mut b), (c, d)| {
                a.iter_mut().zip(c).for_each(|(x, y)| *x += y);
                b.iter_mut().zip(d).for_each(|(x, y)| *x += y);
                (a, b)
            },
        );
    let mut values = Vec::with_capacity(at.triangles.len());
    for (t, ((corners, faces), &(normal, area))) in at.triangles.iter().zip(&geometry).enumerate() {
        if area <= 0.0 {
            continue;
        }
        for (patch, back) in [(Some(faces.front), false), (faces.back, true)] {
            let n = if back { -normal } else { normal };
            let Some(p) = patch.map(|p| p as usize) else {
                continue;
            };
            let cos = -n.dot(w);
            if cos <= 0.0 {
                values.push((p as u32, area, (0.0, 0.0)));
                continue;
            }
            let (visible, variance) = if crossed[p] > 0 {
                let v = f64::from(lit[p]) / f64::from(crossed[p]);
                // Binomial: the grid's place against a shadow edge is as good as random (an
                // overestimate: the grid is stratified).
                (v, v * (1.0 - v) / f64::from(crossed[p]))
            } else {
                // Smaller than the grid: one shadow ray from the centroid, out of the scene.
                let centre = corners.iter().map(|c| c.as_dvec3()).sum::<DVec3>() / 3.0;
                let away = centre - w * f64::from(LINE_LENGTH);
                let visible = !at.blocked(centre, away, t as u32, back);
                (f64::from(u8::from(visible)), 0.0)
            };
            values.push((p as u32, area, (cos * visible, cos * cos * variance)));
        }
    }
    per_patch(patches, values)
}
