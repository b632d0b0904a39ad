//! Direct light of emitting surfaces: small bright emitters (ceiling panels, screens, lamps
//! modelled as emissive geometry) sampled explicitly, as area lights, instead of being found by
//! the few global lines that happen to join them to each patch.
//!
//! A patch's direct light from an emitting face is `ρ·Le·F`, with `F` the patch's form factor
//! to that face. Lines estimate `F` from the fraction of their segments that end on the emitter:
//! for a ceiling panel seen under a few percent of a wall patch's lines, a few dozen crossings,
//! the 5–10% noise of a wall lit by such a panel. Here the coplanar emitting source triangles of
//! one material, one object and one side are one light (a *cluster*; each source triangle's
//! subdivided patches are one flat triangle), and a patch's form factor to it,
//! `F = (1/A) ∫_patch ∫_light cos θ cos θ' V / (π r²)`, is estimated as the mean over g × g
//! stratified points `x_k` of the patch of
//!
//! `(Ω_k / π) · cos θ_k · V(x_k, y_k)`,
//!
//! with `Ω_k` the solid angle of the light's part above the patch's plane seen from `x_k`, `θ_k`
//! the angle of one stratified direction drawn uniformly in that solid angle (Arvo's method),
//! and `V` its shadow ray to the light at `y_k`. Unbiased; exactly 0 where every ray is
//! blocked; where none is, only the variation of cos θ over the light (and the patch's own
//! irradiance gradient, through its stratified points) leaves any noise. The variance comes
//! from pairs of neighbouring strata, never below the binomial variance of the visible fraction
//! across a shadow's edge (conservative).
//!
//! The light is kept per unit radiance of each sampled emitting *material* (so relighting an
//! emitter stays linear and needs no tracing), and the solve subtracts these materials'
//! emission from what the lines carry (`L = Le + ρE/π + ρ Σ_j F_ij (L_j − Le_j)`, METHOD.md's
//! equation with the first bounce taken out): nothing is counted twice.
//!
//! **Which emitters.** Sampling costs shadow rays per patch and per cluster; the lines cost
//! nothing more. A material is sampled when its emitting faces cover at most
//! [`MAX_AREA_SHARE`] of the scene's area (there the lines' estimate is poor: a patch's
//! fraction of lines that reach it is small) and the sampled source triangles stay within
//! [`MAX_CLUSTERS`], smallest share first. A room whose every wall glows stays with the lines,
//! and costs what it did.
//!
//! **Frames.** The static geometry's shadows are computed once, and every shadow ray's verdict
//! is kept (a bit). At each distinct pose of the moving geometry, only the pairs (patch,
//! cluster) it can change are traced again: those with a moving end (whole), and those whose
//! convex hull (patch and light together, which holds every shadow ray between them) meets a
//! moving object's box (through the moving objects only, along the rays the static geometry let
//! through). The rest of the frame reuses the static result; cost and memory grow with what
//! moves.

use std::collections::HashMap;

use glam::{DAffine3, DVec3};
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;

use super::{Face, Frame, Occluders, Posed, geometry_key, triangle_point};
use crate::control::{Control, TraceError};
use crate::scene::subdivide::normal_and_area;
use crate::scene::{Faces, Material, Motion, Scene};
use crate::trace::coincident::mix;
use crate::trace::{FrameMeshes, SceneTracer};

/// Emitting materials whose faces cover more than this share of the scene's area are left to
/// the lines: most lines from most patches reach them, and the lines estimate them well.
pub const MAX_AREA_SHARE: f64 = 0.25;

/// Most emitting source triangles (each face counted) sampled explicitly: the cost of a point
/// is a solid angle per triangle of its light.
pub const MAX_CLUSTERS: usize = 64;

/// How densely, and with which random numbers, the emitters are sampled.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sampling {
    /// Seeds the sampling: two bakes with different seeds are independent (the bake's line
    /// seed).
    pub seed: u64,
    /// Shadow rays per pair (patch, emitter) relative to the standard 16 to 256 (never fewer
    /// than 16, at most 16 times as many): a bake with more lines per patch samples its emitters
    /// more densely too, and one with fewer less densely, so that neither error hides the
    /// other.
    pub density: f64,
}

/// Lines per patch at which emitters get the standard sampling: about the sample level's at
/// 1M lines, where the direct light's error is well below the lines'.
const LINES_PER_PATCH: f64 = 500.0;

/// The most [`Sampling::density`]: 16 times the standard rays per pair (the grid's side at
/// most 64 in any case). A scene of few patches gets thousands of lines per patch cheaply, and
/// as many shadow rays per pair would cost far more than its lines; at 4 the Cornell box's
/// error stopped falling at 0.6% from 1M to 10M lines, its direct light's.
const MAX_DENSITY: f64 = 16.0;

impl Sampling {
    /// The sampling of a bake with `lines` lines over `patches` patches and `seed`: density
    /// grows with the lines per patch (their error falls as 1/√ of it, and so does the direct
    /// light's with the rays).
    #[must_use]
    pub fn for_lines(lines: u64, patches: usize, seed: u64) -> Self {
        let density = lines as f64 / patches.max(1) as f64 / LINES_PER_PATCH;
        Self {
            seed,
            density: density.min(MAX_DENSITY),
        }
    }
}

/// A value per colour channel.
pub type Rgb = [f64; 3];

/// The direct light of the sampled emitting materials, per patch and per frame.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct AreaLights {
    /// The sampled emitting materials (indices into the scene's).
    materials: Vec<u32>,
    /// For each of the scene's materials, its position in `materials`.
    slot: Vec<Option<u16>>,
    /// Each cluster's position of its material in `materials`.
    cluster_slot: Vec<u16>,
    /// Start of each patch's pairs in `pairs` (patches + 1 values).
    offsets: Vec<u32>,
    /// Per patch, its non-zero form factors to the static clusters with the static geometry as
    /// the only occluder (static patches only: a moving patch is computed at every pose).
    pairs: Vec<Pair>,
    /// For each of `pairs`, one bit per shadow ray: whether the static geometry let it through.
    /// A pose of the moving geometry traces only the moving objects along the rays set here (a
    /// pair that no ray reaches stays dark whatever moves).
    visible: Vec<u64>,
    /// For each frame, its pose of the moving geometry (an index into `states`).
    frame_state: Vec<u32>,
    /// Per distinct pose of the moving geometry: the pairs it changes, by patch (the first
    /// pose's alone while [`AreaLights::pending`]).
    states: Vec<Vec<(u32, Pair)>>,
    /// Whether the poses after the first are still to be computed ([`Poses::First`]:
    /// the light of a split bake's patches, read at frame 0 only).
    #[serde(default)]
    pending: bool,
}

/// Which poses of the moving geometry [`AreaLights::compute`] computes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Poses {
    /// Every pose: the light of every frame.
    All,
    /// Frame 0's alone (the first pose); the others are computed by
    /// [`AreaLights::complete`] if they turn out to be needed.
    First,
}

impl Poses {
    /// The poses a new bake needs its patches' light at: every one if `auto`'s rounds will
    /// solve the patches at every frame, else the first (the patches are split into pieces
    /// next, and solved whole at frame 0 alone).
    #[must_use]
    pub fn for_bake(auto: bool) -> Self {
        if auto { Self::All } else { Self::First }
    }
}

/// A patch's form factor to one cluster.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
struct Pair {
    cluster: u32,
    value: f32,
    variance: f32,
    /// Where its rays' static verdicts start in [`AreaLights::visible`] (static pairs only).
    visible: u32,
}

/// One light: the emitting faces of one material, one side, in one plane of one object (a
/// panel of several triangles is one light). Each source triangle's subdivided patches are one
/// flat triangle.
#[derive(Clone, Debug)]
struct Cluster {
    /// Position of its material in [`AreaLights::materials`].
    slot: usize,
    /// Its source triangles, each as the traced triangles (global indices) it was cut into.
    triangles: Vec<Vec<u32>>,
    /// Whether it is their back face that emits.
    back: bool,
    /// Whether it belongs to a moving object.
    moving: bool,
}

/// A cluster as posed at one frame.
#[derive(Clone, Debug)]
pub(super) struct Emitter {
    /// Its source triangles' corners.
    triangles: Vec<[DVec3; 3]>,
    /// The convex hull of their corners, in their plane.
    hull: Vec<DVec3>,
    /// Unit normal of the emitting face (zero if degenerate).
    normal: DVec3,
    centre: DVec3,
    /// Its diameter: the longest distance between two corners of the hull.
    edge: f64,
}

impl AreaLights {
    /// Chooses the emitting materials to sample and computes their direct light at every frame
    /// with `sampling`, counting one unit of `control`'s stage per pose of the moving geometry.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` was cancelled.
    pub fn compute(
        scene: &Scene,
        tracer: &SceneTracer,
        sampling: Sampling,
        control: &Control,
    ) -> Result<Self, TraceError> {
        Self::compute_poses(scene, tracer, (sampling, Poses::All), control)
    }

    /// [`AreaLights::compute`] of the `poses` given: with [`Poses::First`], the light of frame
    /// 0 alone (the same values as [`Poses::All`] computes for it), the poses after it left
    /// [`AreaLights::pending`].
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` was cancelled.
    pub fn compute_poses(
        scene: &Scene,
        tracer: &SceneTracer,
        (sampling, poses): (Sampling, Poses),
        control: &Control,
    ) -> Result<Self, TraceError> {
        let materials = choose(scene, tracer);
        if materials.is_empty() {
            return Ok(Self::default());
        }
        let mut slot = vec![None; scene.materials.len()];
        for (k, &m) in materials.iter().enumerate() {
            slot[m as usize] = Some(k as u16);
        }
        let triangles = scene.triangles_at(0);
        let clusters = clusters(scene, tracer, &triangles, &slot);
        let patches = scene.patches.len();
        let statics = scene.statics.triangles.len();
        let frames = scene.frames.count;

        // Poses of the moving geometry: frames with equal ones share their light.
        let mut first_of: HashMap<u64, u32> = HashMap::new();
        let mut firsts = Vec::new();
        let frame_state: Vec<u32> = (0..frames)
            .map(|f| {
                let key = if scene.objects.is_empty() {
                    0
                } else {
                    geometry_key(scene, f)
                };
                *first_of.entry(key).or_insert_with(|| {
                    firsts.push(f);
                    firsts.len() as u32 - 1
                })
            })
            .collect();
        control.add_work(1 + firsts.len() as u64);

        // The static part: static patches lit by static clusters, static occluders.
        let none = FrameMeshes::none();
        let at = Frame {
            scene,
            tracer,
            deformed: &none,
            triangles: &triangles,
            frame: 0,
            occluders: Occluders::Static,
        };
        let emitters: Vec<Emitter> = clusters.iter().map(|c| pose(c, &triangles)).collect();
        let receivers: Vec<Receiver> = receivers(&triangles, statics)
            .into_iter()
            .filter(|r| !r.moving)
            .collect();
        let mut rows: Vec<(u32, Pair, Vec<u64>)> = receivers
            .par_iter()
            .map(|receiver| {
                let mut rows = Vec::new();
                for (c, emitter) in emitters.iter().enumerate() {
                    if !clusters[c].moving {
                        let mut bits = Vec::new();
                        let pair =
                            pair(&at, receiver, c, emitter, sampling, Rays::Record(&mut bits));
                        if pair.value > 0.0 {
                            rows.push((receiver.patch, pair, bits));
                        }
                    }
                }
                rows
            })
            .flatten()
            .collect();
        rows.sort_unstable_by_key(|(p, pair, _)| (*p, pair.cluster));
        let mut offsets = vec![0u32; patches + 1];
        rows.iter()
            .for_each(|(p, _, _)| offsets[*p as usize + 1] += 1);
        (0..patches).for_each(|p| offsets[p + 1] += offsets[p]);
        let mut visible = Vec::new();
        let pairs: Vec<Pair> = rows
            .into_iter()
            .map(|(_, mut pair, bits)| {
                pair.visible = visible.len() as u32;
                visible.extend(bits);
                pair
            })
            .collect();
        let mut out = Self {
            materials,
            slot,
            cluster_slot: clusters.iter().map(|c| c.slot as u16).collect(),
            offsets,
            pairs,
            visible,
            frame_state,
            states: Vec::new(),
            pending: poses == Poses::First && firsts.len() > 1,
        };
        control.advance(1);

        // Each pose of the moving geometry: the pairs it can change, traced again, the static
        // pairs that any pose may change from their rays kept once.
        let kept = if scene.objects.is_empty() || firsts.len() < 2 {
            KeptPairs::new()
        } else {
            let swept = swept_block(scene, &firsts);
            keep_pairs(&out, &receivers, &emitters, &clusters, &swept, sampling)
        };
        let computed = if out.pending { 1 } else { firsts.len() };
        control.advance((firsts.len() - computed) as u64);
        for &frame in &firsts[..computed] {
            if control.is_cancelled() {
                return Err(TraceError::Cancelled);
            }
            let changed = if scene.objects.is_empty() {
                Vec::new()
            } else {
                changed_pairs(&out, scene, tracer, frame, (&clusters, &kept), sampling)
            };
            out.states.push(changed);
            control.advance(1);
        }
        Ok(out)
    }

    /// Whether the poses after the first are still to be computed ([`Poses::First`]).
    #[must_use]
    pub fn pending(&self) -> bool {
        self.pending
    }

    /// Computes the poses [`Poses::First`] left pending (all of them again, as
    /// [`AreaLights::compute`] does: the same values), with `sampling`, the sampling they were
    /// computed with.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` was cancelled (the lights are left as they were).
    pub fn complete(
        &mut self,
        scene: &Scene,
        tracer: &SceneTracer,
        sampling: Sampling,
        control: &Control,
    ) -> Result<(), TraceError> {
        if self.pending {
            *self = Self::compute(scene, tracer, sampling, control)?;
        }
        Ok(())
    }

    /// The same lights for patches cut from these: new patch `k` takes the form factors of
    /// patch `parents[k]` (its average over the parent, not its own), until sampled again.
    #[must_use]
    pub fn inherit(&self, parents: &[u32]) -> Self {
        if self.is_empty() {
            return self.clone();
        }
        let row = |p: usize| &self.pairs[self.offsets[p] as usize..self.offsets[p + 1] as usize];
        let mut offsets = Vec::with_capacity(parents.len() + 1);
        let mut pairs = Vec::new();
        offsets.push(0);
        for &p in parents {
            pairs.extend_from_slice(row(p as usize));
            offsets.push(pairs.len() as u32);
        }
        let mut children = vec![Vec::new(); self.offsets.len() - 1];
        for (k, &p) in parents.iter().enumerate() {
            children[p as usize].push(k as u32);
        }
        let states = self
            .states
            .iter()
            .map(|changed| {
                let mut out: Vec<(u32, Pair)> = changed
                    .iter()
                    .flat_map(|&(p, pair)| children[p as usize].iter().map(move |&k| (k, pair)))
                    .collect();
                out.sort_by_key(|e| e.0);
                out
            })
            .collect();
        Self {
            offsets,
            pairs,
            states,
            ..self.clone()
        }
    }

    /// The sampled emitters posed with `triangles` (every traced triangle at one frame), each
    /// with π times `emission` of its material (a material index): a unit form factor to it
    /// is that irradiance. Emitters of no emission are left out.
    pub(super) fn posed(
        &self,
        scene: &Scene,
        tracer: &SceneTracer,
        triangles: &[([glam::Vec3; 3], Faces)],
        emission: impl Fn(u32) -> f64,
    ) -> Vec<(Emitter, f64)> {
        (self.posed_materials(scene, tracer, triangles).into_iter())
            .filter_map(|(emitter, m)| {
                let le = emission(m);
                (le > 0.0).then_some((emitter, std::f64::consts::PI * le))
            })
            .collect()
    }

    /// The sampled emitters posed with `triangles` (every traced triangle at one frame), each
    /// with its material (an index into the scene's).
    pub(super) fn posed_materials(
        &self,
        scene: &Scene,
        tracer: &SceneTracer,
        triangles: &[([glam::Vec3; 3], Faces)],
    ) -> Vec<(Emitter, u32)> {
        if self.is_empty() {
            return Vec::new();
        }
        (clusters(scene, tracer, triangles, &self.slot).iter())
            .map(|c| (pose(c, triangles), self.materials[c.slot]))
            .collect()
    }

    /// The static result of the pair (`patch`, `cluster`), if not dark.
    fn static_pair(&self, patch: u32, cluster: usize) -> Option<&Pair> {
        let p = patch as usize;
        self.pairs[self.offsets[p] as usize..self.offsets[p + 1] as usize]
            .iter()
            .find(|e| e.cluster as usize == cluster)
    }

    /// Whether no emitter is sampled.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.materials.is_empty()
    }

    /// The sampled emitting materials (indices into the scene's materials).
    #[must_use]
    pub fn materials(&self) -> &[u32] {
        &self.materials
    }

    /// Whether material `material`'s light reaches the patches through this term rather than
    /// the lines.
    #[must_use]
    pub fn samples(&self, material: u32) -> bool {
        self.slot
            .get(material as usize)
            .is_some_and(Option::is_some)
    }

    /// Which pose of the moving geometry frame `frame` is in: frames with equal poses have
    /// equal light.
    #[must_use]
    pub fn state(&self, frame: usize) -> Option<usize> {
        if self.is_empty() {
            return None;
        }
        self.frame_state.get(frame).map(|&s| s as usize)
    }

    /// The poses of the moving geometry whose changes to the pairs were sampled: one per
    /// distinct pose, however many frames hold it.
    #[must_use]
    pub fn poses(&self) -> usize {
        self.states.len()
    }

    /// Form factors of every patch to every sampled material at `frame`, and their variances
    /// (patch-major, [`AreaLights::materials`] order).
    #[must_use]
    pub fn form_factors(&self, frame: usize) -> (Vec<f64>, Vec<f64>) {
        let slots = self.materials.len();
        let patches = self.offsets.len().saturating_sub(1);
        let (mut values, mut variances) = (vec![0.0; patches * slots], vec![0.0; patches * slots]);
        let Some(state) = self.state(frame) else {
            return (values, variances);
        };
        assert!(
            state < self.states.len(),
            "the area lights of frame {frame} were not computed (poses pending)"
        );
        let row = |p: usize| &self.pairs[self.offsets[p] as usize..self.offsets[p + 1] as usize];
        let mut changed = self.states[state].iter().peekable();
        let mut buffer: Vec<Pair> = Vec::new();
        for p in 0..patches {
            buffer.clear();
            buffer.extend_from_slice(row(p));
            while let Some((_, pair)) = changed.next_if(|(q, _)| *q as usize == p) {
                match buffer.iter_mut().find(|e| e.cluster == pair.cluster) {
                    Some(e) => *e = *pair,
                    None => buffer.push(*pair),
                }
            }
            for e in &buffer {
                let k = p * slots + usize::from(self.cluster_slot[e.cluster as usize]);
                values[k] += f64::from(e.value);
                variances[k] += f64::from(e.variance);
            }
        }
        (values, variances)
    }

    /// Irradiance of every patch at `frame` from the sampled emitters with `materials`'
    /// emission (the scene's, or a relighting's), RGB, in emission units × π, and its
    /// variance; `None` if no emitter is sampled.
    #[must_use]
    pub fn irradiance(&self, frame: usize, materials: &[Material]) -> Option<(Vec<Rgb>, Vec<Rgb>)> {
        self.state(frame)?;
        let (values, variances) = self.form_factors(frame);
        let slots = self.materials.len();
        let emission: Vec<[f64; 3]> = self
            .materials
            .iter()
            .map(|&m| materials.get(m as usize).map_or([0.0; 3], |m| m.emission))
            .collect();
        let pi = std::f64::consts::PI;
        let patches = values.len() / slots;
        let mut e = vec![[0.0; 3]; patches];
        let mut var = vec![[0.0; 3]; patches];
        for p in 0..patches {
            for (s, le) in emission.iter().enumerate() {
                let (f, v) = (values[p * slots + s], variances[p * slots + s]);
                for c in 0..3 {
                    e[p][c] += pi * le[c] * f;
                    var[p][c] += (pi * le[c]).powi(2) * v;
                }
            }
        }
        Some((e, var))
    }

    /// The pairs (patch, cluster) lit with the static geometry alone, and those the poses of
    /// the moving geometry traced again (summed over the poses).
    #[must_use]
    pub fn pair_counts(&self) -> (usize, usize) {
        (self.pairs.len(), self.states.iter().map(Vec::len).sum())
    }

    /// Memory held, bytes.
    #[must_use]
    pub fn memory(&self) -> usize {
        let pair = std::mem::size_of::<Pair>();
        let changed: usize = self.states.iter().map(|s| s.len() * (4 + pair)).sum();
        4 * (self.offsets.len() + self.frame_state.len())
            + self.pairs.len() * pair
            + 8 * self.visible.len()
            + changed
    }
}

/// The emitting materials to sample: those whose emitting faces cover at most
/// [`MAX_AREA_SHARE`] of the scene's area, smallest share first, while their clusters stay
/// within [`MAX_CLUSTERS`].
fn choose(scene: &Scene, tracer: &SceneTracer) -> Vec<u32> {
    let total: f64 = scene.patches.iter().map(|p| p.area).sum();
    if total <= 0.0 {
        return Vec::new();
    }
    let mut area = vec![0.0; scene.materials.len()];
    let mut sources: Vec<std::collections::HashSet<_>> =
        vec![Default::default(); scene.materials.len()];
    for faces in tracer.faces() {
        for p in [Some(faces.front), faces.back].into_iter().flatten() {
            let patch = &scene.patches[p as usize];
            let m = patch.material as usize;
            if scene.materials[m].is_emitter() {
                area[m] += patch.area;
                sources[m].insert((patch.source, patch.side));
            }
        }
    }
    let mut candidates: Vec<usize> = (0..scene.materials.len())
        .filter(|&m| area[m] > 0.0 && area[m] <= MAX_AREA_SHARE * total)
        .collect();
    candidates.sort_by(|&a, &b| area[a].total_cmp(&area[b]));
    let mut chosen = Vec::new();
    let mut count = 0;
    for m in candidates {
        if count + sources[m].len() <= MAX_CLUSTERS {
            count += sources[m].len();
            chosen.push(m as u32);
        }
    }
    chosen.sort_unstable();
    chosen
}

/// The clusters of the sampled materials: the emitting source triangles (each face apart) of
/// one material, one object and one side that lie in one plane make one light; a deforming
/// object's triangles are lights of their own (their plane does not stay shared).
fn clusters(
    scene: &Scene,
    tracer: &SceneTracer,
    triangles: &[([glam::Vec3; 3], Faces)],
    slot: &[Option<u16>],
) -> Vec<Cluster> {
    let spaces = tracer.surfaces().spaces;
    // The source triangles: (source, side) → its traced triangles.
    let mut index = HashMap::new();
    let mut sources: Vec<(usize, bool, u32, Vec<u32>)> = Vec::new();
    for (t, faces) in tracer.faces().iter().enumerate() {
        for (p, back) in [(Some(faces.front), false), (faces.back, true)] {
            let Some(p) = p else { continue };
            let patch = &scene.patches[p as usize];
            let Some(s) = slot[patch.material as usize] else {
                continue;
            };
            let k = *index.entry((patch.source, back)).or_insert_with(|| {
                sources.push((usize::from(s), back, spaces[t], Vec::new()));
                sources.len() - 1
            });
            sources[k].3.push(t as u32);
        }
    }
    let deforming = |space: u32| {
        space > 0
            && matches!(
                scene.objects[space as usize - 1].motion,
                Motion::Deforming(_)
            )
    };
    let mut out: Vec<(Cluster, u32, DVec3, f64)> = Vec::new();
    for (slot, back, space, pieces) in sources {
        let corners = source_corners(&pieces, triangles);
        let normal = face_normal(triangles, pieces[0], back);
        let offset = normal.dot(corners[0]);
        let size = longest_edge(&corners).max(f64::MIN_POSITIVE);
        let same = out.iter_mut().find(|(c, s, n, d)| {
            c.slot == slot
                && c.back == back
                && *s == space
                && !deforming(space)
                && n.dot(normal) > 1.0 - 1e-9
                && corners
                    .iter()
                    .all(|p| (n.dot(*p) - d).abs() <= 1e-9 * size.max(1.0))
        });
        match same {
            Some((cluster, ..)) => cluster.triangles.push(pieces),
            None => out.push((
                Cluster {
                    slot,
                    triangles: vec![pieces],
                    back,
                    moving: space > 0,
                },
                space,
                normal,
                offset,
            )),
        }
    }
    out.into_iter().map(|(c, ..)| c).collect()
}

/// The corners of a source triangle cut into the traced triangles `pieces`: the hull of the
/// pieces, whose three extreme points are the source's corners.
fn source_corners(pieces: &[u32], triangles: &[([glam::Vec3; 3], Faces)]) -> [DVec3; 3] {
    let points: Vec<DVec3> = pieces
        .iter()
        .flat_map(|&t| triangles[t as usize].0.map(|c| c.as_dvec3()))
        .collect();
    let centroid = points.iter().sum::<DVec3>() / points.len() as f64;
    let farthest = |key: &dyn Fn(DVec3) -> f64| {
        points
            .iter()
            .copied()
            .max_by(|a, b| key(*a).total_cmp(&key(*b)))
            .unwrap_or(centroid)
    };
    let a = farthest(&|p| p.distance_squared(centroid));
    let b = farthest(&|p| p.distance_squared(a));
    let ab = (b - a).normalize_or_zero();
    let c = farthest(&|p| (p - a).reject_from_normalized(ab).length_squared());
    [a, b, c]
}

/// The unit normal of the emitting face of traced triangle `t` (its back if `back`).
fn face_normal(triangles: &[([glam::Vec3; 3], Faces)], t: u32, back: bool) -> DVec3 {
    let [p0, p1, p2] = triangles[t as usize].0.map(|c| c.as_dvec3());
    let normal = (p1 - p0).cross(p2 - p0).normalize_or_zero();
    if back { -normal } else { normal }
}

/// A cluster posed with `triangles` (every traced triangle at one frame).
fn pose(cluster: &Cluster, triangles: &[([glam::Vec3; 3], Faces)]) -> Emitter {
    let sources: Vec<[DVec3; 3]> = cluster
        .triangles
        .iter()
        .map(|pieces| source_corners(pieces, triangles))
        .collect();
    let normal = face_normal(triangles, cluster.triangles[0][0], cluster.back);
    let hull = planar_hull(sources.iter().flatten().copied(), normal);
    let centre = hull.iter().sum::<DVec3>() / hull.len().max(1) as f64;
    let edge = hull
        .iter()
        .flat_map(|a| hull.iter().map(move |b| a.distance(*b)))
        .fold(0.0, f64::max);
    Emitter {
        triangles: sources,
        hull,
        normal,
        centre,
        edge,
    }
}

/// The convex hull of `points`, which lie in a plane of normal `normal` (monotone chain in
/// the plane's coordinates; all the points if the normal is degenerate).
fn planar_hull(points: impl Iterator<Item = DVec3>, normal: DVec3) -> Vec<DVec3> {
    let points: Vec<DVec3> = points.collect();
    if normal == DVec3::ZERO || points.len() <= 3 {
        return points;
    }
    let (u, v) = normal.any_orthonormal_pair();
    let mut flat: Vec<(f64, f64, DVec3)> =
        points.iter().map(|&p| (u.dot(p), v.dot(p), p)).collect();
    flat.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    flat.dedup_by(|a, b| a.0 == b.0 && a.1 == b.1);
    if flat.len() <= 3 {
        return flat.into_iter().map(|f| f.2).collect();
    }
    let cross = |o: &(f64, f64, DVec3), a: &(f64, f64, DVec3), b: &(f64, f64, DVec3)| {
        (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
    };
    let mut hull: Vec<(f64, f64, DVec3)> = Vec::with_capacity(2 * flat.len());
    for pass in 0..2 {
        let start = hull.len();
        let ordered: Box<dyn Iterator<Item = &(f64, f64, DVec3)>> = if pass == 0 {
            Box::new(flat.iter())
        } else {
            Box::new(flat.iter().rev())
        };
        for p in ordered {
            while hull.len() >= start + 2
                && cross(&hull[hull.len() - 2], &hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(*p);
        }
        hull.pop();
    }
    hull.into_iter().map(|f| f.2).collect()
}

fn longest_edge(corners: &[DVec3; 3]) -> f64 {
    (0..3)
        .map(|k| corners[k].distance(corners[(k + 1) % 3]))
        .fold(0.0, f64::max)
}

impl Emitter {
    /// The bounding box of its corners.
    pub(super) fn bounds(&self) -> (DVec3, DVec3) {
        bounds(self.hull.iter().copied())
    }

    /// Its triangles' corners.
    pub(super) fn triangles(&self) -> &[[DVec3; 3]] {
        &self.triangles
    }

    /// Whether `x` is in front of the emitting face (by more than rounding): it sends `x`
    /// light.
    pub(super) fn faces(&self, x: DVec3) -> bool {
        let e = self.normal;
        e != DVec3::ZERO && !self.hull.is_empty() && in_front(e.dot(x - self.hull[0]))
    }

    /// Whether the ray from `x`, in front of the emitter ([`Emitter::faces`]), along unit `w`
    /// meets one of its triangles: whether `w` is in the solid angle it subtends from `x`.
    pub(super) fn covers(&self, x: DVec3, w: DVec3) -> bool {
        let e = self.normal;
        let towards = e.dot(w);
        if towards >= 0.0 {
            return false;
        }
        let t = e.dot(self.hull[0] - x) / towards;
        if !(t.is_finite() && t > 0.0) {
            return false;
        }
        let p = x + w * t;
        self.triangles.iter().any(|[a, b, c]| {
            let inside = |u: DVec3, v: DVec3| (v - u).cross(p - u).dot(e);
            let (s0, s1, s2) = (inside(*a, *b), inside(*b, *c), inside(*c, *a));
            (s0 >= 0.0 && s1 >= 0.0 && s2 >= 0.0) || (s0 <= 0.0 && s1 <= 0.0 && s2 <= 0.0)
        })
    }

    /// `g × g` stratified samples of the emitter as seen from `x`, a point on no surface (a
    /// light probe's), jittered by `seed`: each a unit direction from `x`, the point of the
    /// emitter it meets, and a one-sample estimate of the solid angle the emitter subtends
    /// (uniform in solid angle, the estimate that angle itself, with `u` picking the triangle
    /// by its share; by area where the angle is too small to measure, `A cos θ' / r²`), or
    /// `None` for a sample that misses (by rounding). Empty unless `x` is in front of the
    /// emitting face.
    pub(super) fn seen_from(
        &self,
        x: DVec3,
        (seed, g): (u64, usize),
    ) -> Vec<Option<(DVec3, DVec3, f64)>> {
        let e = self.normal;
        if !self.faces(x) {
            return Vec::new();
        }
        let area = |[a, b, c]: &[DVec3; 3]| 0.5 * (b - a).cross(c - a).length();
        let angles: Vec<f64> = self.triangles.iter().map(|t| solid_angle(x, t)).collect();
        let total: f64 = angles.iter().sum();
        let by_angle = total >= TINY_SOLID_ANGLE && total.is_finite();
        let weights: Vec<f64> = if by_angle {
            angles
        } else {
            self.triangles.iter().map(area).collect()
        };
        let sum: f64 = weights.iter().sum();
        if sum <= 0.0 {
            return Vec::new();
        }
        let mut out = Vec::with_capacity(g * g);
        for (u, v) in super::strata(g, seed) {
            let (t, u) = pick(weights.iter().copied(), sum, u);
            let t = &self.triangles[t];
            if by_angle {
                let sample = sample_spherical_triangle(x, t, u, v).and_then(|w| {
                    let along = e.dot(t[0] - x) / e.dot(w);
                    (along.is_finite() && along > 0.0).then(|| (w, x + w * along, total))
                });
                out.push(sample);
            } else {
                let y = triangle_point(t, u, v);
                let d = y - x;
                let r2 = d.length_squared();
                let cos = -e.dot(d) / r2.sqrt();
                out.push((r2 > 0.0 && cos > 0.0).then(|| (d / r2.sqrt(), y, sum * cos / r2)));
            }
        }
        out
    }
}

impl Face {
    /// Whether some of the face is in front of the emitter and some of the emitter in front of
    /// the face: otherwise nothing passes between them (both are flat).
    fn may_see(&self, emitter: &Emitter) -> bool {
        let (n, e) = (self.n, emitter.normal);
        n != DVec3::ZERO
            && e != DVec3::ZERO
            && self
                .corners
                .iter()
                .any(|&c| e.dot(c - emitter.hull[0]) > 0.0)
            && emitter
                .hull
                .iter()
                .any(|&c| n.dot(c - self.corners[0]) > 0.0)
    }
}

/// A receiving patch: the faces of traced triangles it covers (one, or several merged by
/// [`crate::scene::refine::merge`]), each with its area.
struct Receiver {
    patch: u32,
    faces: Vec<(Face, f64)>,
    /// Whether its triangles are a moving object's.
    moving: bool,
}

/// Every patch's faces at a pose (`triangles`, the static ones first: `statics` of them), by
/// patch; a patch with no face of non-zero area is left out.
fn receivers(triangles: &[([glam::Vec3; 3], Faces)], statics: usize) -> Vec<Receiver> {
    let mut by_patch: Vec<Option<Receiver>> = Vec::new();
    for (t, (corners, faces)) in triangles.iter().enumerate() {
        let corners = corners.map(|c| c.as_dvec3());
        let (normal, area) = normal_and_area(corners);
        for (patch, back) in [(Some(faces.front), false), (faces.back, true)] {
            let Some(patch) = patch else { continue };
            let face = Face {
                own: t as u32,
                back,
                corners,
                n: if back { -normal } else { normal },
            };
            if by_patch.len() <= patch as usize {
                by_patch.resize_with(patch as usize + 1, || None);
            }
            by_patch[patch as usize]
                .get_or_insert_with(|| Receiver {
                    patch,
                    faces: Vec::new(),
                    moving: t >= statics,
                })
                .faces
                .push((face, area));
        }
    }
    by_patch.into_iter().flatten().collect()
}

/// The form factor of `receiver` to cluster `c` (posed as `emitter`) with `at`'s occluders: the
/// area average of its faces' ([`form_factor`]), the rays of each face after the previous
/// face's, each face's starting on a whole word of bits.
fn pair(
    at: &Frame<'_>,
    receiver: &Receiver,
    c: usize,
    emitter: &Emitter,
    sampling: Sampling,
    mut rays: Rays<'_>,
) -> Pair {
    let seed = mix(sampling.seed ^ mix((u64::from(receiver.patch) << 32) ^ c as u64));
    let total: f64 = receiver.faces.iter().map(|(_, a)| a).sum();
    let (mut value, mut variance) = (0.0, 0.0);
    let (mut own, mut word) = (Vec::new(), 0);
    if let Rays::Record(bits) = &mut rays {
        bits.clear();
    }
    for (k, (face, area)) in receiver.faces.iter().enumerate() {
        let seed = if k == 0 { seed } else { mix(seed ^ k as u64) };
        let g = grid(face, emitter, sampling.density);
        let words = (g * g).div_ceil(64);
        let face_rays = match &rays {
            Rays::Trace => Rays::Trace,
            Rays::Record(_) => {
                own.clear();
                Rays::Record(&mut own)
            }
            Rays::Known(bits) => Rays::Known(&bits[word..]),
        };
        let (v, var) = form_factor(at, face, emitter, (seed, g), face_rays);
        if let Rays::Record(bits) = &mut rays {
            own.resize(words, 0);
            bits.extend_from_slice(&own);
        }
        word += words;
        // A patch of one face takes its value as it is (weight 1 exactly).
        let w = if total > 0.0 { area / total } else { 0.0 };
        value += w * v;
        variance += w * w * var;
    }
    Pair {
        cluster: c as u32,
        value: value as f32,
        variance: variance as f32,
        visible: u32::MAX,
    }
}

/// What a pair's shadow rays know of the static geometry.
pub(super) enum Rays<'a> {
    /// Nothing: they are traced through `at`'s occluders.
    Trace,
    /// They are traced through `at`'s (static) occluders, and their verdicts recorded here, a
    /// bit per ray.
    Record(&'a mut Vec<u64>),
    /// The static geometry's verdicts, a bit per ray: only the rays it let through are traced,
    /// through `at`'s (moving) occluders.
    Known(&'a [u64]),
}

/// The pairs (patch, cluster) a pose of the moving geometry (`frame`'s) changes, computed at
/// that pose: every pair with a moving end, and every pair whose hull (the convex hull of the
/// face and the cluster's triangle, which holds every shadow ray between them) meets a moving
/// object's box. A pair that the static result holds as non-zero is listed even when it is now
/// zero.
fn changed_pairs(
    lights: &AreaLights,
    scene: &Scene,
    tracer: &SceneTracer,
    frame: usize,
    (clusters, kept): (&[Cluster], &KeptPairs),
    sampling: Sampling,
) -> Vec<(u32, Pair)> {
    let posed = Posed::at(scene, tracer, frame);
    let at = posed.frame(scene, tracer, Occluders::All);
    let moving_only = posed.frame(scene, tracer, Occluders::Moving);
    let triangles = &posed.triangles;
    let emitters: Vec<Emitter> = clusters.iter().map(|c| pose(c, triangles)).collect();
    let statics = scene.statics.triangles.len();
    // The moving objects' boxes at this frame: a rigid object's own box carried by its pose
    // (a door stays a thin slab however it turns), a deforming one's box around its triangles.
    let boxes = moving_blocks(scene, frame, triangles);
    let mut changed: Vec<(u32, Pair)> = receivers(triangles, statics)
        .par_iter()
        .map_init(Vec::new, |hull, receiver| {
            let mut out = Vec::new();
            for (c, emitter) in emitters.iter().enumerate() {
                if receiver.moving || clusters[c].moving {
                    let pair = pair(&at, receiver, c, emitter, sampling, Rays::Trace);
                    if pair.value > 0.0 {
                        out.push((receiver.patch, pair));
                    }
                    continue;
                }
                // Dark with the static geometry alone: dark whatever moves.
                let Some(base) = lights.static_pair(receiver.patch, c) else {
                    continue;
                };
                hull.clear();
                let corners = receiver.faces.iter().flat_map(|(f, _)| &f.corners);
                hull.extend(corners.chain(&emitter.hull));
                if !boxes.iter().any(|b| b.meets_hull(hull)) {
                    continue;
                }
                let pair = match kept.get(&(receiver.patch, c as u32)) {
                    Some(faces) => kept_pair(&moving_only, faces, c),
                    None => {
                        let rays = Rays::Known(&lights.visible[base.visible as usize..]);
                        pair(&moving_only, receiver, c, emitter, sampling, rays)
                    }
                };
                if pair.value != base.value {
                    out.push((receiver.patch, pair));
                }
            }
            out
        })
        .flatten()
        .collect();
    changed.sort_unstable_by_key(|&(p, pair)| (p, pair.cluster));
    changed
}

/// The moving objects' boxes at `frame` (`triangles`: the scene posed there): a rigid
/// object's own box carried by its pose (a door stays a thin slab however it turns), a
/// deforming one's box around its triangles.
fn moving_blocks(
    scene: &Scene,
    frame: usize,
    triangles: &[([glam::Vec3; 3], Faces)],
) -> Vec<Block> {
    let mut boxes = Vec::with_capacity(scene.objects.len());
    let mut start = scene.statics.triangles.len();
    for object in &scene.objects {
        let end = start + object.mesh.triangles.len();
        boxes.push(match &object.motion {
            Motion::Rigid { poses } => {
                let (lo, hi) = bounds(object.mesh.positions.iter().map(|p| p.as_dvec3()));
                Block::new(&poses[frame], lo, hi)
            }
            Motion::Deforming(_) => {
                let (lo, hi) = bounds(
                    triangles[start..end]
                        .iter()
                        .flat_map(|(c, _)| c.map(|p| p.as_dvec3())),
                );
                Block::new(&DAffine3::IDENTITY, lo, hi)
            }
        });
        start = end;
    }
    boxes
}

/// The box around every moving object's box ([`moving_blocks`]) at each of `frames`.
fn swept_block(scene: &Scene, frames: &[usize]) -> Block {
    let deforms = (scene.objects.iter()).any(|o| matches!(o.motion, Motion::Deforming(_)));
    let corners: Vec<DVec3> = (frames.iter())
        .flat_map(|&f| {
            let triangles = if deforms {
                scene.triangles_at(f)
            } else {
                Vec::new()
            };
            moving_blocks(scene, f, &triangles)
        })
        .flat_map(|b| {
            let [a, b2, c] = b.half;
            (0..8).map(move |k| {
                let sign = |bit: usize| if k >> bit & 1 == 0 { -1.0 } else { 1.0 };
                b.centre + a * sign(0) + b2 * sign(1) + c * sign(2)
            })
        })
        .collect();
    let (lo, hi) = bounds(corners.into_iter());
    Block::new(&DAffine3::IDENTITY, lo, hi)
}

/// Bytes of shadow rays [`keep_pairs`] keeps at most: past them, the pairs not kept sample
/// their rays again at each pose.
const KEPT_RAYS_BYTES: usize = 256 << 20;

/// One face of a kept pair ([`keep_pairs`]): what its shadow rays are, the static geometry's
/// verdicts taken.
struct KeptFace {
    own: u32,
    back: bool,
    /// Its share of the patch's area.
    weight: f64,
    /// Whether it can see the emitter at all ([`Face::may_see`]).
    may_see: bool,
    /// Its shadow rays, eligible ones (that can carry light if unblocked), and the sum of the
    /// squares of their values.
    count: usize,
    eligible: usize,
    squares: f64,
    /// The rays the static geometry lets through: (index, point on the face, point on the
    /// emitter, value).
    rays: Vec<(u32, DVec3, DVec3, f64)>,
}

/// Kept pairs' faces by (patch, cluster).
type KeptPairs = HashMap<(u32, u32), Vec<KeptFace>>;

/// The static pairs (static patch, static cluster, lit with the static geometry alone) whose
/// hull meets `swept`, where the moving objects are at some pose, with their shadow rays
/// sampled once: each pose then traces the moving objects along them ([`kept_pair`]) where it
/// sampled them again, the same rays, its value the same to the bit. In receiver order, up to
/// [`KEPT_RAYS_BYTES`].
fn keep_pairs(
    lights: &AreaLights,
    receivers: &[Receiver],
    emitters: &[Emitter],
    clusters: &[Cluster],
    swept: &Block,
    sampling: Sampling,
) -> KeptPairs {
    // The candidates, and the rays each may keep at most.
    let candidates: Vec<(usize, usize, usize)> = (receivers.par_iter().enumerate())
        .flat_map_iter(|(r, receiver)| {
            let mut hull = Vec::new();
            let mut out = Vec::new();
            for (c, emitter) in emitters.iter().enumerate() {
                if clusters[c].moving || lights.static_pair(receiver.patch, c).is_none() {
                    continue;
                }
                hull.clear();
                let corners = receiver.faces.iter().flat_map(|(f, _)| &f.corners);
                hull.extend(corners.chain(&emitter.hull));
                if swept.meets_hull(&hull) {
                    let rays = (receiver.faces.iter())
                        .map(|(face, _)| grid(face, emitter, sampling.density).pow(2))
                        .sum();
                    out.push((r, c, rays));
                }
            }
            out
        })
        .collect();
    let per_ray = size_of::<(u32, DVec3, DVec3, f64)>();
    let mut budget = KEPT_RAYS_BYTES / per_ray;
    let chosen: Vec<(usize, usize)> = (candidates.into_iter())
        .take_while(|&(_, _, rays)| {
            let fits = rays <= budget;
            budget = budget.saturating_sub(rays);
            fits
        })
        .map(|(r, c, _)| (r, c))
        .collect();
    chosen
        .into_par_iter()
        .map(|(r, c)| {
            let receiver = &receivers[r];
            let (emitter, patch) = (&emitters[c], receiver.patch);
            let Some(base) = lights.static_pair(patch, c) else {
                return ((patch, c as u32), Vec::new());
            };
            let bits = &lights.visible[base.visible as usize..];
            (
                (patch, c as u32),
                keep_faces(receiver, c, emitter, sampling, bits),
            )
        })
        .collect()
}

/// The faces of the pair (`receiver`, cluster `c`) as [`pair`] samples them with the static
/// geometry's verdicts `bits`, their rays kept rather than traced.
fn keep_faces(
    receiver: &Receiver,
    c: usize,
    emitter: &Emitter,
    sampling: Sampling,
    bits: &[u64],
) -> Vec<KeptFace> {
    let seed = mix(sampling.seed ^ mix((u64::from(receiver.patch) << 32) ^ c as u64));
    let total: f64 = receiver.faces.iter().map(|(_, a)| a).sum();
    let mut word = 0;
    let mut faces = Vec::with_capacity(receiver.faces.len());
    for (k, (face, area)) in receiver.faces.iter().enumerate() {
        let seed = if k == 0 { seed } else { mix(seed ^ k as u64) };
        let g = grid(face, emitter, sampling.density);
        let bits = &bits[word..];
        word += (g * g).div_ceil(64);
        let mut kept = KeptFace {
            own: face.own,
            back: face.back,
            weight: if total > 0.0 { area / total } else { 0.0 },
            may_see: face.may_see(emitter),
            count: g * g,
            eligible: 0,
            squares: 0.0,
            rays: Vec::new(),
        };
        if kept.may_see {
            each_ray(face, emitter, (seed, g), |k, x, y, f| {
                kept.squares += f * f;
                kept.eligible += 1;
                if bits[k / 64] >> (k % 64) & 1 == 1 {
                    kept.rays.push((k as u32, x, y, f));
                }
            });
        }
        faces.push(kept);
    }
    faces
}

/// The pair of `faces` ([`keep_faces`]) to cluster `c` with `at`'s occluders (the moving
/// objects): what [`pair`] gives with the static verdicts known.
fn kept_pair(at: &Frame<'_>, faces: &[KeptFace], c: usize) -> Pair {
    let (mut value, mut variance) = (0.0, 0.0);
    for face in faces {
        let (v, var) = if face.may_see {
            let rays = face.rays.iter().copied();
            kept_estimate(
                at,
                (face.own, face.back),
                (face.count, face.eligible, face.squares),
                rays,
            )
        } else {
            (0.0, 0.0)
        };
        value += face.weight * v;
        variance += face.weight * face.weight * var;
    }
    Pair {
        cluster: c as u32,
        value: value as f32,
        variance: variance as f32,
        visible: u32::MAX,
    }
}

/// A box as posed: a parallelepiped, its centre and three half-edges.
struct Block {
    centre: DVec3,
    half: [DVec3; 3],
}

impl Block {
    /// The box `(lo, hi)` of an object's own space carried to normalised space by `pose`,
    /// padded by [`PAD`] (a flat object gets that thickness).
    fn new(pose: &DAffine3, lo: DVec3, hi: DVec3) -> Self {
        let extent = (hi - lo) * 0.5;
        let half = [0, 1, 2].map(|i| {
            let axis = pose.matrix3.col(i);
            let h = axis * extent[i];
            let length = h.length();
            if length > 0.0 {
                h * ((length + PAD) / length)
            } else {
                axis.normalize_or(DVec3::X) * PAD
            }
        });
        Self {
            centre: pose.transform_point3((lo + hi) * 0.5),
            half,
        }
    }

    /// Whether it meets the convex hull of `points`: the separating-axis test with its face
    /// normals, the normals of every plane through three of the points (the hull's faces are
    /// among them) and the cross products of its edges with every segment between two of them
    /// (the hull's edges are among them). Exact for touching or not; degenerate axes never
    /// separate.
    fn meets_hull(&self, points: &[DVec3]) -> bool {
        let [a, b, c] = self.half;
        let separates = |axis: DVec3| {
            if axis.length_squared() <= 1e-30 {
                return false;
            }
            let r = a.dot(axis).abs() + b.dot(axis).abs() + c.dot(axis).abs();
            let centre = axis.dot(self.centre);
            let (min, max) =
                points
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                        let d = axis.dot(*p);
                        (lo.min(d), hi.max(d))
                    });
            min > centre + r || max < centre - r
        };
        if [b.cross(c), c.cross(a), a.cross(b)]
            .into_iter()
            .any(separates)
        {
            return false;
        }
        let count = points.len();
        for i in 0..count {
            for j in i + 1..count {
                let edge = points[j] - points[i];
                if self.half.iter().any(|h| separates(edge.cross(*h))) {
                    return false;
                }
                for k in j + 1..count {
                    if separates(edge.cross(points[k] - points[i])) {
                        return false;
                    }
                }
            }
        }
        true
    }
}

/// Padding of the moving objects' boxes (normalised units): well beyond the tracer's
/// tolerances.
const PAD: f64 = 1e-4;

/// The bounding box of `points`.
fn bounds(points: impl Iterator<Item = DVec3>) -> (DVec3, DVec3) {
    points.fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(p), hi.max(p)),
    )
}

/// The side of the grid of strata for a pair: 4, 8 or 16 as the face and the emitter look small
/// or as large as their distance from each other (the irradiance varies more over the face,
/// and a shadow's edge is wider), times the square root of `density`; from 4 (8 pairs of
/// strata: a variance from fewer is itself too noisy) to 64.
fn grid(face: &Face, emitter: &Emitter, density: f64) -> usize {
    let centre = (face.corners[0] + face.corners[1] + face.corners[2]) / 3.0;
    let distance = centre.distance(emitter.centre).max(f64::MIN_POSITIVE);
    let ratio = (longest_edge(&face.corners) + emitter.edge) / distance;
    let base: f64 = match ratio {
        r if r < 0.1 => 4.0,
        r if r < 0.5 => 8.0,
        _ => 16.0,
    };
    (base * density.sqrt()).round().clamp(4.0, 64.0) as usize
}

/// The form factor from `face` to `emitter` with `at`'s occluders, and its variance: the mean
/// over `g × g` stratified points `x_k` of the face of `(Ω/π)·cos θ·V`, with Ω the solid angle
/// of the emitter's part above the face's plane seen from `x_k`, θ the angle from the face's
/// normal of one stratified direction into that part (uniform in solid angle, Arvo's method)
/// and V its shadow ray (strata paired at random). Unbiased; exactly 0 where every ray is
/// blocked, and only the variation of cos θ over the emitter left where none is.
pub(super) fn form_factor(
    at: &Frame<'_>,
    face: &Face,
    emitter: &Emitter,
    (seed, g): (u64, usize),
    mut rays: Rays<'_>,
) -> (f64, f64) {
    if !face.may_see(emitter) {
        return (0.0, 0.0);
    }
    let count = g * g;
    if let Rays::Record(bits) = &mut rays {
        bits.clear();
        bits.resize(count.div_ceil(64), 0);
    }
    let (mut eligible, mut seen, mut squares) = (0usize, 0usize, 0.0);
    let mut values = vec![0.0; count];
    each_ray(face, emitter, (seed, g), |k, x, y, f| {
        let visible = match &mut rays {
            Rays::Known(bits) if bits[k / 64] >> (k % 64) & 1 == 0 => false,
            _ => !at.blocked(x, y, face.own, face.back),
        };
        squares += f * f;
        (eligible, seen) = (eligible + 1, seen + usize::from(visible));
        if visible {
            values[k] = f;
            if let Rays::Record(bits) = &mut rays {
                bits[k / 64] |= 1 << (k % 64);
            }
        }
    });
    stratified_estimate(&values, (eligible, seen), squares)
}

/// Calls `ray(k, x, y, f)` for each of the `g × g` stratified shadow rays of [`form_factor`]
/// from `face` to `emitter` that can carry light: from point `x_k` of the face to `y` on the
/// emitter, of value `f` > 0 if unblocked.
fn each_ray(
    face: &Face,
    emitter: &Emitter,
    (seed, g): (u64, usize),
    mut ray: impl FnMut(usize, DVec3, DVec3, f64),
) {
    let (n, e) = (face.n, emitter.normal);
    let origin = emitter.hull[0];
    let count = g * g;
    let mut fans = Fans::default();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let mut strata: Vec<usize> = (0..count).collect();
    for k in (1..count).rev() {
        strata.swap(k, rng.random_range(0..=k));
    }
    let receiver = super::inset(&face.corners);
    for (k, &stratum) in strata.iter().enumerate() {
        let jitter: [f64; 4] = [rng.random(), rng.random(), rng.random(), rng.random()];
        let cell = |s: usize, a: f64, b: f64| {
            (
                ((s / g) as f64 + a) / g as f64,
                ((s % g) as f64 + b) / g as f64,
            )
        };
        let (u, v) = cell(k, jitter[0], jitter[1]);
        let x = triangle_point(&receiver, u, v);
        if !in_front(e.dot(x - origin)) {
            continue;
        }
        fans_above(&emitter.triangles, n, x, &mut fans.triangles);
        if fans.triangles.is_empty() {
            continue;
        }
        fans.measure(x);
        let (u, v) = cell(stratum, jitter[2], jitter[3]);
        let Some((y, f)) = fans.sample(x, (n, e), u, v) else {
            continue;
        };
        if f <= 0.0 {
            continue;
        }
        ray(k, x, y, f);
    }
}

/// Whether a point `height` above an emitter's plane (along its normal, normalised units) is
/// in front of it: by more than rounding. A point in the emitter's own plane (a double-sided
/// panel's other face, a coplanar neighbour) gets none of its light; by rounding a hair in
/// front, it would see the emitter under a whole hemisphere's solid angle at grazing angles,
/// and sampled there, a direction a hair out of the plane reads as a bright one.
fn in_front(height: f64) -> bool {
    height > f64::from(crate::trace::coincident::COINCIDENT)
}

/// The parts of an emitter's `triangles` in front of the plane through `x` with normal `n`, as
/// triangles, into `fans` (cleared first).
fn fans_above(triangles: &[[DVec3; 3]], n: DVec3, x: DVec3, fans: &mut Vec<[DVec3; 3]>) {
    fans.clear();
    for t in triangles {
        let mut polygon = [DVec3::ZERO; 4];
        match clip(t, n, x, &mut polygon) {
            3 => fans.push([polygon[0], polygon[1], polygon[2]]),
            4 => fans.extend([
                [polygon[0], polygon[1], polygon[2]],
                [polygon[0], polygon[2], polygon[3]],
            ]),
            _ => {}
        }
    }
}

/// The mean of `values` (one per stratum of a grid, 0 where a ray was blocked) and its
/// variance, of which `eligible` rays were traced, `seen` got through, and `squares` is the sum
/// of the squared values the traced rays would have had unblocked.
///
/// Neighbouring cells (k, k + 1 in a row of the grid) make the pairs. Across a shadow's edge
/// that estimate is unreliable (neighbouring strata on the same side of the edge agree, and the
/// strata the edge cuts are few): there, never less than the binomial variance of the visible
/// fraction, as if the rays were independent (wider than stratified sampling's).
fn stratified_estimate(
    values: &[f64],
    (eligible, seen): (usize, usize),
    squares: f64,
) -> (f64, f64) {
    let count = values.len();
    let (mean, collapsed) = super::collapsed_variance(values);
    let binomial = if seen > 0 && seen < eligible {
        let p = seen as f64 / eligible as f64;
        p * (1.0 - p) * squares / (count * count) as f64
    } else {
        0.0
    };
    (mean, collapsed.max(binomial))
}

/// The form factor from the point `x` of face `back` (or the front) of traced triangle `own`,
/// of unit normal `n` on that side, to `emitter` with `at`'s occluders, and its variance: the
/// mean over `g × g` stratified directions uniform in the solid angle of the emitter's part
/// above the point's plane of `(Ω/π)·cos θ·V` ([`form_factor`] at one point). Unbiased; 0 where
/// every ray is blocked, and only the variation of cos θ over the emitter left where none is.
pub(super) fn point_form_factor(
    at: &Frame<'_>,
    (x, n, own, back): (DVec3, DVec3, u32, bool),
    emitter: &Emitter,
    (seed, g): (u64, usize),
) -> (f64, f64) {
    let (mut eligible, mut seen, mut squares) = (0usize, 0usize, 0.0);
    let mut values = vec![0.0; g * g];
    let sampled = each_point_ray((x, n), emitter, (seed, g), |k, y, f| {
        squares += f * f;
        eligible += 1;
        if !at.blocked(x, y, own, back) {
            seen += 1;
            values[k] = f;
        }
    });
    if !sampled {
        return (0.0, 0.0);
    }
    stratified_estimate(&values, (eligible, seen), squares)
}

/// Calls `ray(k, y, f)` for each of the `g × g` stratified shadow rays of
/// [`point_form_factor`] from `x` (unit normal `n`) that can carry light: to `y` on the
/// emitter, of value `f` > 0 if unblocked. False where none can (the point behind the emitter,
/// or the emitter wholly behind the point's plane).
fn each_point_ray(
    (x, n): (DVec3, DVec3),
    emitter: &Emitter,
    (seed, g): (u64, usize),
    mut ray: impl FnMut(usize, DVec3, f64),
) -> bool {
    let Some(mut fans) = Fans::seen((x, n), emitter) else {
        return false;
    };
    // The fans' solid angles once for all the point's rays.
    fans.measure(x);
    for (k, (u, v)) in super::strata(g, seed).enumerate() {
        if let Some((y, f)) = fans.sample(x, (n, emitter.normal), u, v)
            && f > 0.0
        {
            ray(k, y, f);
        }
    }
    true
}

/// The stratified estimate of `count` shadow rays from face `back` of `own` of which
/// `eligible` could carry light (their values' squares summing to `squares`), `rays` those the
/// static geometry lets through (stratum, from, to, value), traced through `at`'s occluders.
fn kept_estimate(
    at: &Frame<'_>,
    (own, back): (u32, bool),
    (count, eligible, squares): (usize, usize, f64),
    rays: impl Iterator<Item = (u32, DVec3, DVec3, f64)>,
) -> (f64, f64) {
    let mut values = vec![0.0; count];
    let mut seen = 0;
    for (k, x, y, f) in rays {
        if !at.blocked(x, y, own, back) {
            values[k as usize] = f;
            seen += 1;
        }
    }
    stratified_estimate(&values, (eligible, seen), squares)
}

/// An emitter as a point sees it: the parts of its triangles in front of the point's plane
/// (measured from the point, for its shadow rays) and its form factor from the point with
/// nothing in between, in closed form. Its shadow rays then estimate only the share of that
/// light that gets through ([`Seen::visible`]): no noise where every ray gets through or none
/// does, and where a shadow volume holds no static geometry at all
/// ([`Seen::statics_clear`]) no static ray is traced.
pub(super) struct Seen {
    x: DVec3,
    n: DVec3,
    /// The emitter's unit normal.
    e: DVec3,
    fans: Fans,
    /// Each fan triangle's area, and their sum.
    areas: Vec<f64>,
    area: f64,
    /// The unoccluded form factor from the point to the fans.
    unoccluded: f64,
}

/// How far the planes of a shadow volume ([`Seen::statics_clear`]) are moved, in normalised
/// units: its sides outwards (a triangle that grazes it counts), its ends inwards (the
/// receiver's own plane and the emitter's: the floor around a point and the ceiling around a
/// panel do not count, as the shadow rays' own tolerances leave them out).
const VOLUME_TOLERANCE: f64 = 1e-6;

impl Seen {
    /// What `x` (unit normal `n`) sees of `emitter`; `None` where no ray can carry light (the
    /// point behind the emitter, or the emitter wholly behind the point's plane).
    pub(super) fn new((x, n): (DVec3, DVec3), emitter: &Emitter) -> Option<Self> {
        let fans = Fans::seen((x, n), emitter)?;
        let unoccluded = unoccluded_form_factor(x, n, &fans.triangles);
        let areas: Vec<f64> = (fans.triangles.iter())
            .map(|[a, b, c]| 0.5 * (*b - *a).cross(*c - *a).length())
            .collect();
        let area = areas.iter().sum();
        Some(Self {
            x,
            n,
            e: emitter.normal,
            fans,
            areas,
            area,
            unoccluded,
        })
    }

    /// The form factor with nothing in between.
    #[cfg(test)]
    fn unoccluded(&self) -> f64 {
        self.unoccluded
    }

    /// Calls `ray(k, y, f)` for each of the `g × g` stratified rays (seeded by `seed`) that can
    /// carry light: to `y` uniform in the area of the fans (the first coordinate picking the
    /// triangle by its area), `f` > 0 its one-sample estimate of the unoccluded form factor,
    /// `A cos θ cos θ' / (π r²)`. By area, not by solid angle as [`point_form_factor`]: the
    /// rays estimate only the share of the light that gets through, and a point by area costs
    /// no trigonometry.
    fn each_ray(&self, (seed, g): (u64, usize), mut ray: impl FnMut(usize, DVec3, f64)) {
        for (k, (u, v)) in super::strata(g, seed).enumerate() {
            // The triangle whose share of the area holds u, and u rescaled within it.
            let (mut below, mut pick) = (0.0, None);
            for (t, &a) in self.areas.iter().enumerate() {
                if a > 0.0 {
                    pick = Some((t, ((u * self.area - below) / a).clamp(0.0, 1.0)));
                    if u * self.area < below + a {
                        break;
                    }
                }
                below += a;
            }
            let Some((t, u)) = pick else {
                return;
            };
            let [a, b, c] = self.fans.triangles[t];
            let s = u.sqrt();
            let y = a * (1.0 - s) + b * (s * (1.0 - v)) + c * (s * v);
            let d = y - self.x;
            let r2 = d.length_squared();
            let (cos_x, cos_y) = (self.n.dot(d), -self.e.dot(d));
            if r2 > 0.0 && cos_x > 0.0 && cos_y > 0.0 {
                let f = self.area * cos_x * cos_y / (std::f64::consts::PI * r2 * r2);
                ray(k, y, f);
            }
        }
    }

    /// Whether no static triangle but the point's own meets the volume between the point and
    /// the emitter (the convex hull of the point and the emitter's hull, above the point's
    /// plane): then no static geometry can block a ray from it to the emitter.
    pub(super) fn statics_clear(&self, statics: &Frame<'_>, emitter: &Emitter, own: u32) -> bool {
        let (x, n) = (self.x, self.n);
        let hull = &emitter.hull;
        let centre = hull.iter().copied().sum::<DVec3>() / hull.len() as f64;
        let mut planes: Vec<(DVec3, f64)> = Vec::with_capacity(hull.len() + 2);
        // The point's plane and the emitter's, moved in.
        planes.push((-n, -n.dot(x) - VOLUME_TOLERANCE));
        let e = if self.e.dot(x - hull[0]) > 0.0 {
            self.e
        } else {
            -self.e
        };
        planes.push((-e, -e.dot(hull[0]) - VOLUME_TOLERANCE));
        // The sides, through the point and each edge of the hull, moved out.
        for (k, &a) in hull.iter().enumerate() {
            let b = hull[(k + 1) % hull.len()];
            let Some(m) = (a - x).cross(b - x).try_normalize() else {
                continue;
            };
            let m = if m.dot(centre - x) > 0.0 { -m } else { m };
            planes.push((m, m.dot(x) + VOLUME_TOLERANCE));
        }
        !(statics.tracer).any_static_in_convex(&planes, &mut |id| id != own)
    }

    /// The form factor with `at`'s occluders between, and its variance: the unoccluded form
    /// factor times the share of the `g × g` rays' values (seeded by `seed`) that gets through
    /// (a ratio estimate: exact where all or none does). What `rays` knows of the static
    /// geometry is used or recorded as [`form_factor`]'s for a face.
    pub(super) fn visible(
        &self,
        at: &Frame<'_>,
        (own, back): (u32, bool),
        (seed, g): (u64, usize),
        mut rays: Rays<'_>,
    ) -> (f64, f64) {
        if let Rays::Record(bits) = &mut rays {
            bits.clear();
            bits.resize((g * g).div_ceil(64), 0);
        }
        let mut values = Visible::new(g);
        self.each_ray((seed, g), |k, y, f| {
            let clear = match &mut rays {
                Rays::Known(bits) if bits[k / 64] >> (k % 64) & 1 == 0 => false,
                _ => !at.blocked(self.x, y, own, back),
            };
            if clear && let Rays::Record(bits) = &mut rays {
                bits[k / 64] |= 1 << (k % 64);
            }
            values.add(k, f, clear);
        });
        values.estimate(self.unoccluded)
    }

    /// The form factor from the point on face `back` of `own` with `view`'s occluders, or where
    /// the static geometry is `clear` of its rays ([`Seen::statics_clear`]) with `moving`'s
    /// alone (none if `None`).
    pub(super) fn visible_through(
        &self,
        (view, moving): (&Frame<'_>, Option<&Frame<'_>>),
        clear: bool,
        (own, back): (u32, bool),
        sample: (u64, usize),
    ) -> (f64, f64) {
        match (clear, moving) {
            (true, None) => (self.unoccluded, 0.0),
            (true, Some(moving)) => self.visible(moving, (own, back), sample, Rays::Trace),
            (false, _) => self.visible(view, (own, back), sample, Rays::Trace),
        }
    }
}

/// A point's rays to an emitter, their values and which got through: what [`Seen::visible`]
/// and [`PointRays::form_factor`] estimate the visible share from.
struct Visible {
    /// Per stratum: the ray's value (0 if it could carry none), and 0 or it as it was blocked
    /// or not.
    all: Vec<f64>,
    seen: Vec<f64>,
    eligible: usize,
    through: usize,
    squares: f64,
}

impl Visible {
    fn new(g: usize) -> Self {
        Self {
            all: vec![0.0; g * g],
            seen: vec![0.0; g * g],
            eligible: 0,
            through: 0,
            squares: 0.0,
        }
    }

    fn add(&mut self, k: usize, f: f64, clear: bool) {
        self.all[k] = f;
        self.eligible += 1;
        self.squares += f * f;
        if clear {
            self.seen[k] = f;
            self.through += 1;
        }
    }

    /// `unoccluded` times the visible share of the values, and its variance: the ratio's by
    /// the delta method (the stratified variance of the residuals `seen − share × all`, never
    /// less than the binomial variance of the visible fraction: [`stratified_estimate`]),
    /// scaled from the rays' mean to the closed form.
    fn estimate(&self, unoccluded: f64) -> (f64, f64) {
        let total: f64 = self.all.iter().sum();
        if total <= 0.0 || self.through == 0 {
            return (0.0, 0.0);
        }
        if self.through == self.eligible {
            return (unoccluded, 0.0);
        }
        let share = self.seen.iter().sum::<f64>() / total;
        let residuals: Vec<f64> = (self.all.iter().zip(&self.seen))
            .map(|(&a, &s)| s - share * a)
            .collect();
        let (_, variance) =
            stratified_estimate(&residuals, (self.eligible, self.through), self.squares);
        let mean = total / self.all.len() as f64;
        (unoccluded * share, variance * (unoccluded / mean).powi(2))
    }
}

/// The unoccluded form factor from `x` (unit normal `n`) to the triangles `fans`, wholly in
/// front of its plane: Lambert's formula, per triangle `(1/2π) |Σ θ_i n · γ_i|` over its edges,
/// `θ_i` the angle an edge subtends at `x` and `γ_i` the unit normal of the plane through `x`
/// and the edge.
fn unoccluded_form_factor(x: DVec3, n: DVec3, fans: &[[DVec3; 3]]) -> f64 {
    let total: f64 = (fans.iter())
        .map(|t| {
            let r = t.map(|p| p - x);
            (0..3)
                .map(|i| {
                    let (a, b) = (r[i], r[(i + 1) % 3]);
                    let c = a.cross(b);
                    let length = c.length();
                    if length > 0.0 {
                        length.atan2(a.dot(b)) * n.dot(c) / length
                    } else {
                        0.0
                    }
                })
                .sum::<f64>()
                .abs()
        })
        .sum();
    total / std::f64::consts::TAU
}

/// A point's shadow rays to one emitter with the static geometry's verdicts: kept where the
/// moving geometry may shadow the point at some frames, so that each such frame samples the
/// same rays again and traces the moving objects alone along those the static geometry lets
/// through ([`PointRays::form_factor`]), the same value to the bit as [`Seen::visible`] with the
/// posed scene. Where no static triangle is in the way at all ([`Seen::statics_clear`]), no
/// static ray is traced.
#[derive(Debug)]
pub(super) struct PointRays {
    /// Whether the static geometry is clear of every ray.
    clear: bool,
    /// Otherwise the strata whose ray it lets through, a bit each.
    through: Vec<u64>,
}

impl PointRays {
    /// The rays of [`Seen::visible`] from what `seen` sees on face `back` of `own` to
    /// `emitter`, traced through `statics` (the static geometry alone).
    pub(super) fn sample(
        statics: &Frame<'_>,
        (seen, emitter): (&Seen, &Emitter),
        (own, back): (u32, bool),
        sample: (u64, usize),
    ) -> Self {
        let clear = seen.statics_clear(statics, emitter, own);
        let mut through = Vec::new();
        if !clear {
            seen.visible(statics, (own, back), sample, Rays::Record(&mut through));
        }
        Self { clear, through }
    }

    /// The form factor and its variance from what `seen` sees (on face `back` of `own`) with
    /// `moving`'s occluders (the moving geometry at a frame) along the rays the static geometry
    /// lets through.
    pub(super) fn form_factor(
        &self,
        moving: &Frame<'_>,
        seen: &Seen,
        (own, back): (u32, bool),
        sample: (u64, usize),
    ) -> (f64, f64) {
        let rays = if self.clear {
            Rays::Trace
        } else {
            Rays::Known(&self.through)
        };
        seen.visible(moving, (own, back), sample, rays)
    }

    /// Bytes held, about.
    pub(super) fn bytes(&self) -> usize {
        size_of::<Self>() + self.through.len() * size_of::<u64>()
    }
}

/// The side of the grid of strata a point's shadow rays to `emitter` ([`Seen`]) sample it
/// with: 4 while the emitter looks small from `x`, 8 otherwise, times the square root of
/// `density`, from 4 to 64. The rays estimate only the share of the closed form that gets
/// through (not the variation of cos θ over the emitter, as [`grid`]'s for a face), so that the
/// 16 that a large emitter close by took before bought nothing: 8 × 8 put the level's texels'
/// direct light at a third of the time (issue 49).
pub(super) fn point_grid(x: DVec3, emitter: &Emitter, density: f64) -> usize {
    let distance = x.distance(emitter.centre).max(f64::MIN_POSITIVE);
    let base: f64 = match emitter.edge / distance {
        r if r < 0.1 => 4.0,
        r if r < 0.5 => 8.0,
        _ => 16.0,
    };
    (base * density.sqrt()).round().clamp(4.0, 64.0) as usize
}

/// Below this solid angle (steradians), a fan triangle of the emitter is sampled by area: the
/// spherical triangle's area `α + β + γ − π` loses its digits, and the emitter is so small from
/// the point that its weight `cos θ cos θ' / r²` is constant over it to far better than the
/// sampling.
const TINY_SOLID_ANGLE: f64 = 1e-9;

/// [`Fans::sample`] of the triangles `fans` from `x`.
#[cfg(test)]
fn sample_fans(
    x: DVec3,
    n: DVec3,
    e: DVec3,
    fans: &[[DVec3; 3]],
    u: f64,
    v: f64,
) -> Option<(DVec3, f64)> {
    let mut seen = Fans::default();
    seen.triangles.extend_from_slice(fans);
    seen.measure(x);
    seen.sample(x, (n, e), u, v)
}

/// The parts of an emitter's triangles in front of a point's plane ([`fans_above`]), with
/// their solid angles from the point: measured once, sampled by each of the point's rays.
#[derive(Default)]
struct Fans {
    triangles: Vec<[DVec3; 3]>,
    angles: Vec<f64>,
    total: f64,
}

impl Fans {
    /// The parts of `emitter` that `x` (unit normal `n`) sees in front of its plane, not yet
    /// measured; `None` where no ray can carry light (the point behind the emitter, or the
    /// emitter wholly behind the point's plane).
    fn seen((x, n): (DVec3, DVec3), emitter: &Emitter) -> Option<Self> {
        let e = emitter.normal;
        if n == DVec3::ZERO || e == DVec3::ZERO || !in_front(e.dot(x - emitter.hull[0])) {
            return None;
        }
        let mut fans = Self::default();
        fans_above(&emitter.triangles, n, x, &mut fans.triangles);
        (!fans.triangles.is_empty()).then_some(fans)
    }

    /// The solid angles of the triangles from `x`.
    fn measure(&mut self, x: DVec3) {
        self.angles.clear();
        (self.angles).extend(self.triangles.iter().map(|t| solid_angle(x, t)));
        self.total = self.angles.iter().sum();
    }

    /// A point `y` of the triangles (wholly in front of the plane through `x` with unit normal
    /// `n`, in the emitter's plane of normal `e`; `x` the point the angles were measured
    /// from) at `(u, v)` in the unit square, and the one-sample estimate `f` of the form
    /// factor from `x` to them if `y` is visible: uniform in their solid angle
    /// (f = Ω cos θ / π), `u` picking the triangle by its solid angle; by area where the
    /// solid angle is tiny (f = A cos θ cos θ' / (π r²)). Both are unbiased.
    fn sample(&self, x: DVec3, (n, e): (DVec3, DVec3), u: f64, v: f64) -> Option<(DVec3, f64)> {
        let fans = &self.triangles;
        let total = self.total;
        if total >= TINY_SOLID_ANGLE && total.is_finite() {
            let (t, u) = pick(self.angles.iter().copied(), total, u);
            let w = sample_spherical_triangle(x, &fans[t], u, v)?;
            // Where the direction meets the emitter's plane.
            let along = e.dot(fans[t][0] - x) / e.dot(w);
            if !(along.is_finite() && along > 0.0) {
                return None;
            }
            let cos = n.dot(w).max(0.0);
            return Some((x + w * along, total * cos / std::f64::consts::PI));
        }
        // By area.
        let area = |[a, b, c]: &[DVec3; 3]| 0.5 * (b - a).cross(c - a).length();
        let total: f64 = fans.iter().map(area).sum();
        if total <= 0.0 {
            return None;
        }
        let (t, u) = pick(fans.iter().map(area), total, u);
        let y = triangle_point(&fans[t], u, v);
        let d = y - x;
        let r2 = d.length_squared();
        if r2 <= 0.0 {
            return None;
        }
        let r = r2.sqrt();
        let cos = n.dot(d) / r;
        let cos_emitter = -e.dot(d) / r;
        (cos > 0.0 && cos_emitter > 0.0)
            .then(|| (y, total * cos * cos_emitter / (std::f64::consts::PI * r2)))
    }
}

/// The index of the weight (of `weights`, summing to `total`) whose share holds `u` in [0, 1),
/// and `u` rescaled to [0, 1] within that share: a stratified `u` picks each triangle of an
/// emitter in proportion to its weight and stays stratified within it.
fn pick(weights: impl Iterator<Item = f64>, total: f64, u: f64) -> (usize, f64) {
    let mut below = 0.0;
    let mut last = (0, 0.0);
    for (k, w) in weights.enumerate() {
        if w > 0.0 {
            last = (k, (u * total - below) / w);
            if u * total < below + w {
                break;
            }
        }
        below += w;
    }
    (last.0, last.1.clamp(0.0, 1.0))
}

/// The angle between unit vectors, accurate near 0 and π.
fn angle_between(a: DVec3, b: DVec3) -> f64 {
    if a.dot(b) < 0.0 {
        std::f64::consts::PI - 2.0 * ((a + b).length() / 2.0).min(1.0).asin()
    } else {
        2.0 * ((b - a).length() / 2.0).min(1.0).asin()
    }
}

/// The corners of triangle `t` seen from `x` (unit vectors) and its angles at them; `None` if
/// degenerate from `x`.
fn spherical(x: DVec3, t: &[DVec3; 3]) -> Option<([DVec3; 3], [f64; 3])> {
    let [a, b, c] = t.map(|p| (p - x).normalize_or_zero());
    let (ab, bc, ca) = (a.cross(b), b.cross(c), c.cross(a));
    if [a, b, c].contains(&DVec3::ZERO)
        || [ab, bc, ca]
            .iter()
            .any(|v| v.length_squared() <= f64::MIN_POSITIVE)
    {
        return None;
    }
    let (ab, bc, ca) = (ab.normalize(), bc.normalize(), ca.normalize());
    Some((
        [a, b, c],
        [
            angle_between(ab, -ca),
            angle_between(bc, -ab),
            angle_between(ca, -bc),
        ],
    ))
}

/// The solid angle of triangle `t` seen from `x` (0 if degenerate).
fn solid_angle(x: DVec3, t: &[DVec3; 3]) -> f64 {
    spherical(x, t).map_or(0.0, |(_, [a, b, c])| {
        (a + b + c - std::f64::consts::PI).max(0.0)
    })
}

/// A direction from `x` uniform in the solid angle of triangle `t`, at `(u, v)` in the unit
/// square (Arvo 1995, as in PBRT 4's `SampleSphericalTriangle`).
fn sample_spherical_triangle(x: DVec3, t: &[DVec3; 3], u: f64, v: f64) -> Option<DVec3> {
    let ([a, b, c], [alpha, beta, gamma]) = spherical(x, t)?;
    let pi = std::f64::consts::PI;
    // The sub-triangle of area u·Ω: its vertex c' on the arc from a to c.
    let area = pi + u * (alpha + beta + gamma - pi);
    let (sin_alpha, cos_alpha) = alpha.sin_cos();
    let (sin_area, cos_area) = area.sin_cos();
    let sin_phi = sin_area * cos_alpha - cos_area * sin_alpha;
    let cos_phi = cos_area * cos_alpha + sin_area * sin_alpha;
    let k1 = cos_phi + cos_alpha;
    let k2 = sin_phi - sin_alpha * a.dot(b);
    let cos_bp = ((k2 + (k2 * cos_phi - k1 * sin_phi) * cos_alpha)
        / ((k2 * sin_phi + k1 * cos_phi) * sin_alpha))
        .clamp(-1.0, 1.0);
    let sin_bp = (1.0 - cos_bp * cos_bp).max(0.0).sqrt();
    let cp = a * cos_bp + (c - a * c.dot(a)).normalize_or_zero() * sin_bp;
    // Then uniform in area along the arc from b to c'.
    let cos_theta = 1.0 - v * (1.0 - cp.dot(b));
    let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
    let w = b * cos_theta + (cp - b * cp.dot(b)).normalize_or_zero() * sin_theta;
    (w.is_finite() && w != DVec3::ZERO).then(|| w.normalize())
}

/// Clips triangle `t` to the half-space in front of the plane through `x` with normal `n`;
/// writes the corners (at most 4) to `out` and returns their number.
fn clip(t: &[DVec3; 3], n: DVec3, x: DVec3, out: &mut [DVec3; 4]) -> usize {
    let d = t.map(|c| n.dot(c - x));
    let mut count = 0;
    for k in 0..3 {
        let (a, b) = (k, (k + 1) % 3);
        if d[a] >= 0.0 {
            out[count] = t[a];
            count += 1;
        }
        if (d[a] >= 0.0) != (d[b] >= 0.0) && count < 4 {
            let s = d[a] / (d[a] - d[b]);
            out[count] = t[a] + (t[b] - t[a]) * s;
            count += 1;
        }
    }
    count
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The incremental frames (static verdicts kept, only the moving objects traced along the
    /// rays they let through, only the pairs a moving box can reach) against every pair of the
    /// frame traced whole through the posed scene with the same rays: equal to the last bit.
    /// The level at 1.5 frames a second (its door moves), its tracer, the sampling of a bake
    /// of 1M lines, its area lights and their clusters.
    fn level_lights() -> (Scene, SceneTracer, Sampling, AreaLights, Vec<Cluster>) {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/level.gltf");
        let options = crate::loader::LoadOptions {
            fps: 1.5,
            ..Default::default()
        };
        let scene = crate::loader::load(&std::fs::read(path).unwrap(), &options).unwrap();
        let tracer = SceneTracer::new(&scene);
        let sampling = Sampling::for_lines(1_000_000, scene.patches.len(), 9);
        let lights = AreaLights::compute(&scene, &tracer, sampling, &Control::default()).unwrap();
        assert!(!lights.is_empty() && !scene.objects.is_empty());
        let mut slot = vec![None; scene.materials.len()];
        for (k, &m) in lights.materials.iter().enumerate() {
            slot[m as usize] = Some(k as u16);
        }
        let clusters = clusters(&scene, &tracer, &scene.triangles_at(0), &slot);
        (scene, tracer, sampling, lights, clusters)
    }

    #[test]
    fn each_pose_equals_its_frame_traced_whole() {
        let (scene, tracer, sampling, lights, clusters) = level_lights();
        let slots = lights.materials.len();
        let mut retraced = 0;
        for frame in 0..scene.frames.count {
            let posed = Posed::at(&scene, &tracer, frame);
            let at = posed.frame(&scene, &tracer, Occluders::All);
            let triangles = &posed.triangles;
            let emitters: Vec<Emitter> = clusters.iter().map(|c| pose(c, triangles)).collect();
            let mut whole = vec![0.0f64; scene.patches.len() * slots];
            for receiver in receivers(triangles, scene.statics.triangles.len()) {
                for (c, emitter) in emitters.iter().enumerate() {
                    let p = pair(&at, &receiver, c, emitter, sampling, Rays::Trace);
                    whole[receiver.patch as usize * slots + clusters[c].slot] += f64::from(p.value);
                }
            }
            let (values, _) = lights.form_factors(frame);
            assert_eq!(values, whole, "frame {frame}");
            retraced += lights.states[lights.frame_state[frame] as usize].len();
        }
        // The door moves: some pairs change, most do not.
        assert!(retraced > 0 && retraced < lights.pairs.len() * scene.frames.count / 2);
    }

    /// A point's shadow rays kept through the static geometry ([`PointRays`]), traced at each
    /// frame through the moving objects alone, give what tracing them through the posed scene
    /// gives ([`Seen::visible`]), to the last bit, at points of the level some of which the
    /// door shadows at some frames; and where a point's shadow volume holds no static triangle
    /// ([`Seen::statics_clear`]), no ray through the static geometry is blocked.
    #[test]
    fn a_points_kept_rays_equal_its_rays_traced_whole_at_every_frame() {
        let (scene, tracer, _, _, clusters) = level_lights();
        let triangles = scene.triangles_at(0);
        let emitters: Vec<Emitter> = (clusters.iter())
            .filter(|c| !c.moving)
            .map(|c| pose(c, &triangles))
            .collect();
        assert!(!emitters.is_empty());
        let statics = scene.statics.triangles.len();
        // The centroids of some static triangles' front faces, a hair in front.
        let points: Vec<(DVec3, DVec3, u32)> = (0..statics)
            .step_by(5)
            .filter_map(|t| {
                let corners = triangles[t].0.map(glam::Vec3::as_dvec3);
                let (n, area) = normal_and_area(corners);
                (area > 0.0).then(|| ((corners[0] + corners[1] + corners[2]) / 3.0, n, t as u32))
            })
            .collect();
        let rest = Posed::at(&scene, &tracer, 0);
        let static_view = rest.frame(&scene, &tracer, Occluders::Static);
        let sample = |x: DVec3, k: usize, e: &Emitter| (mix(k as u64), point_grid(x, e, 1.0));
        let (mut clear, mut sampled) = (0, 0);
        let kept: Vec<Vec<Option<(Seen, bool, PointRays)>>> = (points.iter())
            .map(|&(x, n, t)| {
                (emitters.iter().enumerate())
                    .map(|(k, e)| {
                        let seen = Seen::new((x, n), e)?;
                        let statics = seen.statics_clear(&static_view, e, t);
                        let rays = PointRays::sample(
                            &static_view,
                            (&seen, e),
                            (t, false),
                            sample(x, k, e),
                        );
                        if statics {
                            clear += 1;
                            // Every ray through the static geometry gets through.
                            let through = seen.visible_through(
                                (&static_view, None),
                                false,
                                (t, false),
                                sample(x, k, e),
                            );
                            assert_eq!(through, (seen.unoccluded(), 0.0), "at {x}");
                        } else {
                            sampled += 1;
                        }
                        Some((seen, statics, rays))
                    })
                    .collect()
            })
            .collect();
        // Both kinds are there.
        assert!(clear > 0 && sampled > 0, "{clear} clear, {sampled} sampled");
        let mut values: Vec<Vec<f64>> = Vec::new();
        for frame in 0..scene.frames.count {
            let posed = Posed::at(&scene, &tracer, frame);
            let (all, moving) = (
                posed.frame(&scene, &tracer, Occluders::All),
                posed.frame(&scene, &tracer, Occluders::Moving),
            );
            let mut frame_values = Vec::new();
            for (&(x, _, t), kept) in points.iter().zip(&kept) {
                for (k, (e, kept)) in emitters.iter().zip(kept).enumerate() {
                    let Some((seen, statics, rays)) = kept else {
                        continue;
                    };
                    let face = (t, false);
                    let whole = seen.visible_through((&all, None), false, face, sample(x, k, e));
                    assert_eq!(
                        rays.form_factor(&moving, seen, face, sample(x, k, e)),
                        whole,
                        "frame {frame}"
                    );
                    let through = (&all, Some(&moving));
                    assert_eq!(
                        seen.visible_through(through, *statics, face, sample(x, k, e)),
                        whole,
                        "frame {frame}"
                    );
                    frame_values.push(whole.0);
                }
            }
            values.push(frame_values);
        }
        // The door shadows some of the points at some frames.
        let changed = (0..values[0].len())
            .filter(|&i| values.iter().any(|v| v[i] != values[0][i]))
            .count();
        assert!(changed > 0, "of {}", values[0].len());
    }

    /// A quad as two triangles.
    fn fans(q: &[DVec3; 4]) -> [[DVec3; 3]; 2] {
        [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    }

    /// The form factor from the origin (facing +Z) to `square` (facing −Z) by [`sample_fans`]
    /// at the midpoints of a `g × g` grid, each sample's point given to `check`.
    fn midpoint_form_factor(square: &[DVec3; 4], g: usize, check: &dyn Fn(DVec3)) -> f64 {
        let mut sum = 0.0;
        for i in 0..g {
            for j in 0..g {
                let (u, v) = ((i as f64 + 0.5) / g as f64, (j as f64 + 0.5) / g as f64);
                let (y, f) = sample_fans(DVec3::ZERO, DVec3::Z, -DVec3::Z, &fans(square), u, v)
                    .expect("a sample");
                check(y);
                sum += f;
            }
        }
        sum / (g * g) as f64
    }

    /// Howell C-11: a point under the corner of a parallel a × b rectangle at height h.
    fn corner(a: f64, b: f64, h: f64) -> f64 {
        let (a, b) = (a / h, b / h);
        let (sa, sb) = ((1.0 + a * a).sqrt(), (1.0 + b * b).sqrt());
        (a / sa * (b / sa).atan() + b / sb * (a / sb).atan()) / std::f64::consts::TAU
    }

    #[test]
    fn an_octant_subtends_an_eighth_of_the_sphere() {
        let octant = [DVec3::X, DVec3::Y, DVec3::Z];
        let omega = solid_angle(DVec3::ZERO, &octant);
        assert!(
            (omega - std::f64::consts::FRAC_PI_2).abs() < 1e-14,
            "{omega}"
        );
    }

    #[test]
    fn sampling_in_solid_angle_integrates_the_form_factor_of_a_square() {
        // An off-centre square: the point under one corner of a 0.5 × 0.5 square at h = 0.5.
        let h = 0.5;
        let square = [
            DVec3::new(0.0, 0.0, h),
            DVec3::new(0.5, 0.0, h),
            DVec3::new(0.5, 0.5, h),
            DVec3::new(0.0, 0.5, h),
        ];
        let exact = corner(0.5, 0.5, h);
        let f = midpoint_form_factor(&square, 128, &|y| {
            assert!((y.z - h).abs() < 1e-12 && (0.0..=0.5).contains(&y.x), "{y}");
        });
        assert!((f / exact - 1.0).abs() < 1e-3, "{f} vs {exact}");
    }

    /// The closed form [`Seen`] reads a point's unoccluded light from is the rectangle's
    /// known form factor under a corner and under an edge from close by; it is what sampling
    /// integrates for a square perpendicular to the point's plane; and a tiny square far away
    /// is its area over π r².
    #[test]
    fn the_unoccluded_form_factor_is_lambert_s_closed_form() {
        let up = DVec3::Z;
        let square = |x0: f64, y0: f64, x1: f64, y1: f64, h: f64| {
            let (a, b, c, d) = (
                DVec3::new(x0, y0, h),
                DVec3::new(x1, y0, h),
                DVec3::new(x1, y1, h),
                DVec3::new(x0, y1, h),
            );
            [[a, b, c], [a, c, d]]
        };
        // The parts in front of the point's plane.
        let fans_of = |x: DVec3, n: DVec3, t: &[[DVec3; 3]]| {
            let mut fans = Vec::new();
            fans_above(t, n, x, &mut fans);
            fans
        };
        let form =
            |x: DVec3, n: DVec3, t: &[[DVec3; 3]]| unoccluded_form_factor(x, n, &fans_of(x, n, t));
        let close = |f: f64, exact: f64| assert!((f / exact - 1.0).abs() < 1e-12, "{f} vs {exact}");
        close(
            form(DVec3::ZERO, up, &square(0.0, 0.0, 0.5, 0.5, 0.5)),
            corner(0.5, 0.5, 0.5),
        );
        close(
            form(DVec3::ZERO, up, &square(-0.5, 0.0, 0.5, 1.0, 0.01)),
            2.0 * corner(0.5, 1.0, 0.01),
        );
        // A square made of two halves reads as the sum of their corners' form factors.
        close(
            form(DVec3::ZERO, up, &square(-1.0, 0.0, 1.0, 1.0, 1.0)),
            2.0 * corner(1.0, 1.0, 1.0),
        );
        // A point facing +x, the square above it perpendicular to its plane, half of it
        // in front: against the fans' own sampling on a 256 × 256 grid of midpoints.
        let tilted = square(-1.0, 0.0, 1.0, 1.0, 1.0);
        let x = DVec3::ZERO;
        let exact = form(x, DVec3::X, &tilted);
        let mut fans = Fans::default();
        fans.triangles.extend(fans_of(x, DVec3::X, &tilted));
        fans.measure(x);
        let g = 256;
        let mut sum = 0.0;
        for k in 0..g * g {
            let (u, v) = (
                ((k / g) as f64 + 0.5) / g as f64,
                ((k % g) as f64 + 0.5) / g as f64,
            );
            sum += fans
                .sample(x, (DVec3::X, -DVec3::Z), u, v)
                .map_or(0.0, |(_, f)| f);
        }
        let sampled = sum / (g * g) as f64;
        assert!((sampled / exact - 1.0).abs() < 1e-3, "{sampled} vs {exact}");
        // Tiny and far: the area formula A cos cos / (π r²).
        let s = 1e-5;
        let f = form(DVec3::ZERO, up, &square(0.0, 0.0, s, s, 1.0));
        assert!(
            (f / (s * s / std::f64::consts::PI) - 1.0).abs() < 1e-6,
            "{f}"
        );
    }

    #[test]
    fn sampling_in_solid_angle_integrates_a_large_square_seen_from_close_by() {
        // A point 1 cm under the middle of an edge of a 1 m square (a panel under a ceiling):
        // two rectangles of 0.5 × 1 under a corner, F = 0.4999.
        let h = 0.01;
        let square = [
            DVec3::new(-0.5, 0.0, h),
            DVec3::new(0.5, 0.0, h),
            DVec3::new(0.5, 1.0, h),
            DVec3::new(-0.5, 1.0, h),
        ];
        let exact = 2.0 * corner(0.5, 1.0, h);
        let f = midpoint_form_factor(&square, 256, &|_| {});
        assert!((f / exact - 1.0).abs() < 1e-3, "{f} vs {exact}");
    }

    #[test]
    fn a_tiny_emitter_is_sampled_by_area_and_still_integrates() {
        // Seen from 1e6 of its size away: below TINY_SOLID_ANGLE, so sampled by area.
        let (s, h) = (1e-6, 1.0);
        let square = [
            DVec3::new(0.0, 0.0, h),
            DVec3::new(s, 0.0, h),
            DVec3::new(s, s, h),
            DVec3::new(0.0, s, h),
        ];
        let (_, f) =
            sample_fans(DVec3::ZERO, DVec3::Z, -DVec3::Z, &fans(&square), 0.3, 0.6).unwrap();
        let exact = s * s / std::f64::consts::PI;
        assert!((f / exact - 1.0).abs() < 1e-5, "{f} vs {exact}");
    }

    #[test]
    fn clipping_keeps_the_part_in_front() {
        let t = [
            DVec3::new(-1.0, 0.0, 1.0),
            DVec3::new(1.0, 0.0, 1.0),
            DVec3::new(0.0, 0.0, -1.0),
        ];
        let mut out = [DVec3::ZERO; 4];
        let n = clip(&t, DVec3::Z, DVec3::ZERO, &mut out);
        assert_eq!(n, 4);
        assert!(out[..n].iter().all(|p| p.z >= -1e-12));
        let all = clip(&t, DVec3::Z, DVec3::new(0.0, 0.0, -2.0), &mut out);
        assert_eq!(all, 3);
        assert_eq!(clip(&t, DVec3::Z, DVec3::new(0.0, 0.0, 2.0), &mut out), 0);
    }
}
