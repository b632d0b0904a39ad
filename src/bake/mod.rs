//! A bake: a scene, its timeline's lines and tallies, and the radiosity of any frame.
//!
//! Tracing happens once (and again only for refinement); relighting — new emission or
//! reflectance per material — re-solves from the kept tallies without tracing a line.

pub mod gaps;
mod points;
mod stored;

use std::ops::ControlFlow;
use std::sync::Arc;

use rayon::prelude::*;

use crate::control::{Control, Stop, TraceError};
use crate::direct::DirectLight;
use crate::direct::area::{AreaLights, Poses, Sampling};
use crate::scene::{Light, Material, Scene};
use crate::solve::tally::{FrameTally, Tallies};
use crate::solve::{
    Direct, FrameSolution, Groups, SolveParams, Spread, solve_answer, solve_grouped,
};
use crate::timeline::{Crossings, IntersectionList, LineParams};
use crate::trace::{SceneTracer, SurfaceTable};

/// A traced scene, ready to solve any frame with any materials.
pub struct Bake {
    /// The scene (its materials are the defaults for [`Bake::solve_frame`]).
    pub scene: Scene,
    tracer: SceneTracer,
    list: IntersectionList,
    tallies: Tallies,
    /// Direct light of the punctual lights per frame (per unit power, so lights can change
    /// without tracing).
    direct: DirectLight,
    /// Direct light of the emitting surfaces sampled as area lights (per unit radiance of each
    /// such material, so emitters can change without tracing).
    area: AreaLights,
    /// Seed of the line set, reused (with the next batch index) by refinement.
    seed: u64,
    /// What the lines found that the user should know (see [`Bake::warnings`]).
    warnings: Vec<String>,
    /// Whether the last cut's pieces inherited their direct light ([`Lights::Inherit`]).
    inherited: bool,
    /// The finer pieces the frames are solved on, once [`Bake::split`].
    pieces: Option<Pieces>,
    /// The scene as it was before [`Bake::split`] cut its triangles for the pieces: the same
    /// patches, drawn with their own triangles ([`Bake::shown`]).
    shown: Option<Scene>,
    /// What the light at the outputs' points keeps across frames ([`Bake::radiance_at`]).
    gathered: crate::direct::points::GatherCache,
    /// The patches' visible shares kept across frames.
    shares: crate::direct::KeptShares,
}

/// The direct light of a bake's patches at a frame, and its variance.
type LightOf<'a> = dyn Fn(usize) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) + Sync + 'a;

/// What a set of patches is solved with ([`Bake::solve_frame`]): the scene they are in, its
/// tracer, their direct light from lamps and from emitters, and their visible shares kept
/// across frames.
type State<'a> = (
    &'a Scene,
    &'a SceneTracer,
    &'a DirectLight,
    &'a AreaLights,
    &'a crate::direct::KeptShares,
);

/// What [`Bake::split`] solves: every face of the patches, cut finer where the lines cross it
/// often enough, each a patch of its own with its own tallies and direct light; the answer for
/// a patch is the mean of its pieces ([`Groups`]).
struct Pieces {
    scene: Scene,
    tracer: SceneTracer,
    tallies: Tallies,
    direct: DirectLight,
    area: AreaLights,
    groups: Groups,
    /// Where the pieces lie, for the outputs' points ([`Bake::piece_map`]).
    map: crate::direct::points::PieceMap,
    /// The pieces' visible shares kept across frames.
    shares: crate::direct::KeptShares,
    /// The pieces one level coarser, for the error bars' shape term.
    coarse: Coarse,
}

/// A split bake's pieces one level coarser: each pair of sibling pieces (the two halves of a
/// cut that no later cut split again, [`crate::scene::refine::Chain::siblings`]) merged back
/// into the piece they were cut from. Solved at a run's first frame beside the pieces, on the
/// same lines: how far the last level of cuts moved each patch's answer is Richardson's
/// estimate of how far the pieces still are from the light's shape ([`SHAPE_ERROR`]).
struct Coarse {
    /// The pieces' triangles with their faces merged: its shadow rays are the pieces'
    /// tracer's, over the same triangles.
    scene: Scene,
    /// Each piece's coarse piece (with the pieces' areas): the coarse pieces' tallies are
    /// their pieces' merged ([`FrameTally::merged`]), their direct light their pieces'
    /// area-weighted mean.
    of_pieces: Groups,
    /// Each coarse piece's patch (with the coarse pieces' areas).
    groups: Groups,
    shares: crate::direct::KeptShares,
}

impl Coarse {
    /// The coarse level of `pieces` (piece `k` of patch `of[k]`, of `patches` patches), whose
    /// sibling triangles are `siblings`.
    fn new(pieces: &Scene, (of, patches): (&[u32], usize), siblings: &[[u32; 2]]) -> Self {
        use crate::scene::refine;
        // Merge the faces of each pair of sibling triangles, side by side, into the first's.
        let mut into: Vec<u32> = (0..pieces.patches.len() as u32).collect();
        let corners = refine::Corners::new(pieces);
        for &[a, b] in siblings {
            let (fa, fb) = (corners.faces(a), corners.faces(b));
            for (p, q) in [(Some(fa.front), Some(fb.front)), (fa.back, fb.back)] {
                if let (Some(p), Some(q)) = (p, q)
                    && p != q
                    && into[p as usize] == p
                    && into[q as usize] == q
                {
                    into[q as usize] = p;
                }
            }
        }
        Self::with_map(pieces, (of, patches), refine::dense_ids(into))
    }

    /// The coarse level of `pieces` (piece `k` of patch `of[k]`, of `patches` patches) in
    /// which piece `k` is coarse piece `dense[k]` (dense ids from 0, each within one patch).
    fn with_map(pieces: &Scene, (of, patches): (&[u32], usize), dense: Vec<u32>) -> Self {
        let scene = crate::scene::refine::merge(pieces, &dense);
        let count = dense.iter().map(|&c| c as usize + 1).max().unwrap_or(0);
        let mut coarse_of = vec![0u32; count];
        for (k, &c) in dense.iter().enumerate() {
            coarse_of[c as usize] = of[k];
        }
        let areas: Vec<f64> = scene.patches.iter().map(|p| p.area).collect();
        let piece_areas = pieces.patches.iter().map(|p| p.area).collect();
        Self {
            of_pieces: Groups::new(dense, piece_areas, count),
            groups: Groups::new(coarse_of, areas, patches),
            scene,
            shares: Default::default(),
        }
    }

    fn bytes(&self) -> usize {
        self.of_pieces.bytes() + self.groups.bytes()
    }
}

impl Pieces {
    /// Tallies the lines `list` holds beyond those the pieces' tallies hold
    /// ([`Tallies::update_like`]), `like` the patches' (the same lines).
    fn update_tallies(&mut self, list: &IntersectionList, like: &Tallies) {
        let count = self.scene.patches.len();
        (self.tallies).update_like(list, &self.tracer.surfaces(), count, Some(like));
    }

    /// What the pieces are solved with ([`Bake::state`]'s for the pieces).
    fn state(&self) -> State<'_> {
        (
            &self.scene,
            &self.tracer,
            &self.direct,
            &self.area,
            &self.shares,
        )
    }
}

/// How much of the move from the pieces one level coarser ([`Coarse`]) to the pieces the error
/// bar of a split bake takes as the pieces' own error from the light's shape
/// ([`Bake::split`]): Richardson's estimate for an error of the first order in a piece's size,
/// `1 / (√2 − 1)` (a cut halves a piece's area, so its size by √2). Measured against the path
/// tracer (`docs/engine.md`, "The error bars' shape term").
pub const SHAPE_ERROR: f64 = 1.0 + std::f64::consts::SQRT_2;

/// Levels of bisection [`Bake::split`] cuts a face into at most (2^3 = 8 pieces).
pub const SPLIT_DEPTH: u32 = 3;

/// The fewest crossings [`Bake::split`] expects of a piece at frame 0: a face is cut no finer.
pub const PIECE_CROSSINGS: f64 = 8.0;

/// Lines per piece of [`Bake::split`]'s budget: at most one piece per this many lines
/// (100,000 for a million lines), the most crossed triangles cut first; a scene with as many
/// patches is not split. A bound on the cost, not on the error: more pieces measured better
/// wherever they were tried (`bench-patches`, 1M lines: the Cornell box at 0.1 m read 2.5%
/// unbounded and 4.9% with one piece per 50 lines; the level at 0.25 m 8.5% unbounded and
/// 14.2% at one per 10, though the Cornell box at 0.05 m read 8.0% unbounded, 17.1% at one per
/// 50 and 4.6% at one per 10, its most crossed triangles cut), but the spheres
/// sample at 4M lines (207,616 patches) made 903,428 pieces unbounded, baked in 3.3 times the
/// time and 2.4 times the memory, for an estimated error of 8.6% against 9.8%.
pub const LINES_PER_PIECE: usize = 10;

/// Rounds of [`Bake::split`]'s further cuts where pieces misplace light (a gap's rim, a
/// contact's edge: [`gaps`]), each bisecting a piece once.
pub const GAP_ROUNDS: usize = 8;

/// The misplaced flux ([`gaps`]) for which [`Bake::split`] cuts a piece further: this share of
/// all the light the scene's surfaces reflect (at frame 0). Measured with `bench-patches` at 1M
/// lines on the sources' own triangles (per-patch error against the path tracer, pieces,
/// seconds): the level 11.8% (15,702 pieces, 8.0 s) at 1e-5, 3.1% (18,868, 8.2 s) at 1e-6,
/// 1.8% (32,566, 9.7 s) at 1e-7; the level under lamps 9.2% (18,608, 9.2 s) at 1e-6, 3.8%
/// (31,850, 12.4 s) at 1e-7; the panel room 1.3% at 1e-4 and 1e-6.
pub const GAP_SHARE: f64 = 1e-7;

/// How [`Bake::cut`] gives the new patches their direct light.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lights {
    /// Sampled again for the new patches.
    Sample,
    /// Each piece takes its patch's (the average over the patch) until [`Bake::sample_lights`]:
    /// for rounds of cuts that sample once at the end. The light then drawn is the coarser
    /// one.
    Inherit,
}

impl Bake {
    /// Traces `params.lines` lines through the whole timeline and tallies them.
    pub fn trace(scene: Scene, params: &LineParams) -> Result<Self, TraceError> {
        Self::trace_with(scene, (params, Poses::All), &Control::default())
    }

    /// [`Bake::trace`] watched by `control` (progress, cancellation), the patches' sampled
    /// emitters' light computed at the `poses` given: [`Poses::First`] for a bake that is
    /// [`Bake::split`] next, whose patches are solved whole at frame 0 alone (the poses after
    /// it are computed if the split makes no pieces, or by [`Bake::complete_lights`]).
    pub fn trace_with(
        scene: Scene,
        (params, poses): (&LineParams, Poses),
        control: &Control,
    ) -> Result<Self, TraceError> {
        let tracer = SceneTracer::for_lines(&scene, params.lines);
        let list = IntersectionList::build(&scene, &tracer, params, control)?;
        Self::of_list((scene, tracer), list, (params.seed, poses), control)
    }

    /// The bake of `scene` whose lines, of `seed`, are `list` (traced here, or by several
    /// machines, [`IntersectionList::merge`]): the same bake as [`Bake::trace_with`] makes of
    /// the same lines.
    ///
    /// # Errors
    /// [`Stop::Cancelled`] if `control` is cancelled; [`Stop::Failed`] if the list crosses
    /// triangles the scene does not have (a list of another scene).
    pub fn of_merged_list(
        scene: Scene,
        list: IntersectionList,
        (seed, poses): (u64, Poses),
        control: &Control,
    ) -> Result<Self, Stop> {
        let tracer = SceneTracer::new(&scene);
        if !list.crosses_only(tracer.faces().len()) {
            return Err(Stop::Failed(
                "the lines cross triangles the scene does not have".into(),
            ));
        }
        Ok(Self::of_list(
            (scene, tracer),
            list,
            (seed, poses),
            control,
        )?)
    }

    /// [`Bake::of_merged_list`] with the scene's tracer.
    fn of_list(
        (scene, tracer): (Scene, SceneTracer),
        list: IntersectionList,
        (seed, poses): (u64, Poses),
        control: &Control,
    ) -> Result<Self, TraceError> {
        let mut tallies = Tallies::default();
        tallies.update(&list, &tracer.surfaces(), scene.patches.len());
        let sampling = (list.lines(), seed, poses);
        let (direct, area) = Self::sampled_lights(&scene, &tracer, sampling, control)?;
        let warnings = overlap_warnings(&scene, &tracer, &list);
        Ok(Self {
            scene,
            tracer,
            list,
            tallies,
            direct,
            area,
            seed,
            warnings,
            inherited: false,
            pieces: None,
            shown: None,
            gathered: Default::default(),
            shares: Default::default(),
        })
    }

    /// Progressive refinement: traces about `lines` more lines (a new batch of directions) and
    /// adds their tallies; the lines already traced are kept. The emitters sampled as area
    /// lights are sampled again as densely as a bake of all the lines samples them
    /// ([`Sampling::for_lines`]), so that their error falls with the lines' too.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled (lines added before it are kept;
    /// the area lights stay as they were).
    pub fn refine(&mut self, lines: u64, control: &Control) -> Result<(), TraceError> {
        let params = LineParams {
            lines,
            seed: self.seed,
        };
        let patches = self.scene.patches.len();
        let before = self.list.lines();
        self.list
            .add_lines(&self.scene, &self.tracer, &params, control)?;
        self.tallies
            .update(&self.list, &self.tracer.surfaces(), patches);
        self.warnings = overlap_warnings(&self.scene, &self.tracer, &self.list);
        let lines = (before, self.list.lines(), self.seed);
        if let Some(pieces) = &mut self.pieces {
            pieces.update_tallies(&self.list, &self.tallies);
            resample(
                &mut pieces.area,
                &pieces.scene,
                &pieces.tracer,
                lines,
                control,
            )?;
        }
        resample(&mut self.area, &self.scene, &self.tracer, lines, control)
    }

    /// Makes the lines through `regions` (boxes in normalised space) `factor` times as dense
    /// as elsewhere ([`IntersectionList::add_dense`]) and tallies everything again with the
    /// lines' weights: the same estimates, with `factor` times the crossings inside the
    /// regions. [`Bake::split`] does it for the gaps it finds.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled (the bake is then as it was).
    ///
    /// # Panics
    /// If the lines are dense somewhere already, or `factor` is not in 2..=255.
    pub fn densify(
        &mut self,
        (regions, factor): (&[crate::scene::Bounds], u32),
        control: &Control,
    ) -> Result<(), TraceError> {
        let dense = (regions, factor);
        (self.list).add_dense(&self.scene, &self.tracer, dense, control)?;
        let patches = self.scene.patches.len();
        (self.tallies).update(&self.list, &self.tracer.surfaces(), patches);
        if let Some(pieces) = &mut self.pieces {
            pieces.update_tallies(&self.list, &self.tallies);
        }
        Ok(())
    }

    /// Cuts the traced triangles as `cuts` says (a bisection tree per triangle by global index,
    /// [`crate::scene::refine::cut`]), with the cuts their neighbours need, and moves every
    /// crossing of the list to
    /// the piece it lies on: the same lines through finer patches, without tracing them again.
    /// The new patches' direct light is as `lights` says. Returns the patches added.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled while the light is sampled (the
    /// bake is then left as it was).
    pub fn cut(
        &mut self,
        cuts: &[u32],
        lights: Lights,
        control: &Control,
    ) -> Result<usize, TraceError> {
        let (scene, refinement) = crate::scene::refine::cut(&self.scene, cuts);
        let added = scene.patches.len() - self.scene.patches.len();
        if added == 0 {
            return Ok(0);
        }
        // What can fail (cancellation) first: the bake is left as it was.
        let tracer = SceneTracer::new(&scene);
        let (direct, area) = match lights {
            Lights::Sample => Self::sampled_lights(
                &scene,
                &tracer,
                (self.list.lines(), self.seed, Poses::All),
                control,
            )?,
            Lights::Inherit => (
                self.direct.inherit(refinement.parents()),
                self.area.inherit(refinement.parents()),
            ),
        };
        self.inherited = lights == Lights::Inherit;
        Self::move_crossings(
            &mut self.list,
            (&self.scene, None),
            &refinement,
            Crossings::All,
        );
        (self.pieces, self.shown) = (None, None);
        let mut tallies = Tallies::default();
        tallies.update(&self.list, &tracer.surfaces(), scene.patches.len());
        self.warnings = overlap_warnings(&scene, &tracer, &self.list);
        (self.scene, self.tracer, self.tallies) = (scene, tracer, tallies);
        (self.direct, self.area) = (direct, area);
        Ok(added)
    }

    /// Merges the patches as `into` says ([`crate::scene::refine::merge`]: old patch `p`
    /// becomes new patch `into[p]`) and samples their direct light. No triangle changes, so the
    /// list is kept as it is and only tallied again. Returns the patches removed.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled while the light is sampled (the
    /// bake is then left as it was).
    pub fn merge(&mut self, into: &[u32], control: &Control) -> Result<usize, TraceError> {
        let scene = crate::scene::refine::merge(&self.scene, into);
        let removed = self.scene.patches.len() - scene.patches.len();
        if removed == 0 {
            return Ok(0);
        }
        let tracer = SceneTracer::new(&scene);
        let (direct, area) = Self::sampled_lights(
            &scene,
            &tracer,
            (self.list.lines(), self.seed, Poses::All),
            control,
        )?;
        let mut tallies = Tallies::default();
        tallies.update(&self.list, &tracer.surfaces(), scene.patches.len());
        (self.scene, self.tracer, self.tallies) = (scene, tracer, tallies);
        (self.direct, self.area) = (direct, area);
        self.inherited = false;
        (self.pieces, self.shown) = (None, None);
        Ok(removed)
    }

    /// Moves the crossings of `list` that `which` says to the piece of its triangle each lies
    /// on, as `refinement` cut the triangles of `scene` (the scene the crossings are on).
    fn move_crossings(
        list: &mut IntersectionList,
        (scene, bundles): (&Scene, Option<&[crate::lines::Bundle]>),
        refinement: &crate::scene::refine::Refinement,
        which: Crossings,
    ) {
        use crate::scene::refine::{Corners, barycentric};
        let corners = Corners::new(scene);
        list.relabel((scene, bundles), which, |hit, frame, point| {
            let old = hit.surface();
            let bary = if refinement.is_cut(old) {
                corners
                    .posed(old, frame)
                    .and_then(|c| barycentric(c, point))
            } else {
                None
            };
            refinement.locate(old, bary.unwrap_or([1.0, 0.0, 0.0]))
        });
    }

    /// Solves the frames on finer pieces than the patches it answers for: every face of a
    /// patch (a merged patch's each) is cut by up to [`SPLIT_DEPTH`] levels of bisection, while
    /// its pieces would each have [`PIECE_CROSSINGS`] crossings at frame 0, and every piece is
    /// solved as a patch of its own, with its own direct light; a patch's answer is then the
    /// mean of its pieces, and its error bar the spread of that mean between the replicas.
    ///
    /// A patch holds one radiance, but the light it sends on is not even across it: the
    /// light a patch gathers from a neighbour depends on where on the neighbour it lands (the
    /// floor beside a box is brighter than the floor behind it). Solved patch against patch,
    /// that light is spread evenly over the neighbour, and every patch's answer carries the
    /// error; solved on pieces, each patch's mean gathers what its pieces see. The noise of
    /// a patch's mean is about that of the patch solved whole (it is made of the same
    /// crossings): measured with `bench-patches`, the per-patch error against the path
    /// tracer falls two to seven times on the sample scenes (docs/engine.md, "Pieces").
    ///
    /// First the lines through the gaps are made denser, once ([`gaps::regions`],
    /// [`Bake::densify`]): light trapped in a gap falls off over about the gap's height, and
    /// the pieces there need more crossings than the global lines give to be that small.
    ///
    /// Then, for up to [`GAP_ROUNDS`] rounds, the pieces that misplace light are bisected once
    /// more: where part of a piece faces something closer than the piece is wide (a gap under
    /// a panel or a fixture, a box resting on the floor) and gathers other light than the rest
    /// ([`gaps`]), those misplacing over [`GAP_SHARE`] of the scene's reflected light, most
    /// first, and then every piece in a dense region, within the same budget, while each half
    /// keeps [`PIECE_CROSSINGS`] crossings. The
    /// cuts follow a gap's rim down until its pieces hold too little light to matter: the
    /// panel room at its source's triangles went from +25% to the path tracer's brightness.
    ///
    /// The patches stay as they are (ids, areas, sources); their triangles are the pieces'
    /// (a patch draws all its pieces). Call it after the patches are final: a cut or merge
    /// afterwards solves whole patches again. Returns the pieces solved.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled while the pieces' light is sampled:
    /// the bake then answers as before (its patches whole, on the pieces' triangles).
    pub fn split(&mut self, solve: &SolveParams, control: &Control) -> Result<usize, TraceError> {
        use crate::scene::refine;
        if let Some(pieces) = &self.pieces {
            return Ok(pieces.scene.patches.len());
        }
        // Denser lines through the gaps, once: the patches that face something closer than
        // they are wide ([`gaps::regions`]). On cancellation the lines are left as they were.
        if self.list.dense().0.is_empty() {
            let table = self.tracer.table();
            let scores = gaps::misplaced(&self.scene, table, &self.list, &|_| 0.0, 0.0);
            let lines = self.list.lines();
            let (regions, factor) = gaps::regions(&self.scene, &scores, lines);
            if !regions.is_empty() {
                match self.densify((&regions, factor), control) {
                    Ok(()) | Err(TraceError::Cancelled) => {}
                    Err(e) => self
                        .warnings
                        .push(format!("the gaps' lines were not made denser: {e}")),
                }
            }
        }
        let (apart, of_apart) = refine::apart(&self.scene);
        // Each face's expected crossings: its patch's, by its share of the patch's area, in
        // the global lines' units (the tallies count a global line the dense factor times): a
        // gap's pieces are cut further by the rounds below, from the crossings they have.
        let tally = self.frame_tally(0);
        let crossings: Vec<f64> = (tally.crossings.iter())
            .map(|&c| c as f64 / tally.unit as f64)
            .collect();
        let expected = |p: u32| {
            let whole = &self.scene.patches[of_apart[p as usize] as usize];
            let share = if whole.area > 0.0 {
                apart.patches[p as usize].area / whole.area
            } else {
                0.0
            };
            crossings[of_apart[p as usize] as usize] * share
        };
        // The traced triangles' faces in global order (the static mesh's, then each object's):
        // each triangle's most crossings expected on one of its faces.
        let meshes = std::iter::once(&apart.statics).chain(apart.objects.iter().map(|o| &o.mesh));
        let most: Vec<f64> = meshes
            .flat_map(|m| &m.faces)
            .map(|f| {
                [Some(f.front), f.back]
                    .into_iter()
                    .flatten()
                    .map(expected)
                    .fold(0.0, f64::max)
            })
            .collect();
        // Each triangle cut as deep as its pieces keep `least` crossings each, at most
        // SPLIT_DEPTH levels.
        let depth = |most: f64, least: f64| {
            (0..=SPLIT_DEPTH)
                .take_while(|&d| most / f64::from(1u32 << d) >= least)
                .last()
                .unwrap_or(0)
        };
        let pieces = |least: f64| -> f64 {
            most.iter()
                .map(|&m| f64::from(1u32 << depth(m, least)))
                .sum::<f64>()
        };
        // The fewest crossings per piece: PIECE_CROSSINGS, or more while the triangles' pieces
        // would be over the budget (the most crossed are cut first; none, if the triangles
        // alone are).
        let budget = (self.list.lines() / LINES_PER_PIECE) as f64;
        let mut least = PIECE_CROSSINGS;
        if pieces(least) > budget {
            let (mut low, mut high) = (least, most.iter().copied().fold(least, f64::max) + 1.0);
            for _ in 0..60 {
                let mid = 0.5 * (low + high);
                if pieces(mid) > budget {
                    low = mid;
                } else {
                    high = mid;
                }
            }
            least = high;
        }
        let cuts: Vec<u32> = (most.iter())
            .map(|&m| {
                // Every node of the tree down to its depth (heap order, bit 1 the root).
                ((1u64 << (1u32 << depth(m, least))) - 1) as u32 & !1
            })
            .collect();
        // Nothing to split: the patches are their own pieces, solved at every frame.
        if cuts.iter().all(|&c| c == 0) && apart.patches.len() == self.scene.patches.len() {
            self.complete_lights(control)?;
            return Ok(self.scene.patches.len());
        }
        // The patches' answer at frame 0, for the gap scores: what each piece faces.
        let whole = self.whole_answer((0, &self.scene.materials, &self.light_power(), solve), None);
        let (mut scene, refinement) = refine::cut(&apart, &cuts);
        let mut of: Vec<u32> = (refinement.parents().iter())
            .map(|&q| of_apart[q as usize])
            .collect();
        // The apart scene has the bake's triangles: the crossings move to the pieces. The
        // rounds read frame 0 alone: the moving crossings at the later frames move once, after
        // them, through every round's cuts (`chain`).
        // The lines' bundles, generated once for every round's relabelling.
        let bundles = self.list.regenerate_bundles(&self.scene);
        let zero = (Some(&bundles[..]), Crossings::AtFrameZero);
        Self::move_crossings(&mut self.list, (&self.scene, zero.0), &refinement, zero.1);
        let mut chain = refine::Chain::default();
        chain.push(&self.scene, refinement.clone());
        let budget = budget as usize;
        // Each round walks the lines only for the pieces the last one cut.
        let mut last: Option<(gaps::Walked, refine::Refinement)> = None;
        for _ in 0..GAP_ROUNDS {
            if control.is_cancelled() {
                break;
            }
            let table = SurfaceTable::new(&scene);
            let light = (&whole.radiance[..], solve.sky);
            let before = last.as_ref().map(|(w, r)| (w, r));
            let walked = self.piece_scores((&scene, &table, &of), light, &bundles, before);
            let scores = walked.pieces(&scene);
            let Some((next, refinement)) =
                self.cut_gaps((&scene, &scores), &whole.radiance, budget)
            else {
                break;
            };
            of = (refinement.parents().iter())
                .map(|&q| of[q as usize])
                .collect();
            Self::move_crossings(&mut self.list, (&scene, zero.0), &refinement, zero.1);
            chain.push(&scene, refinement.clone());
            scene = next;
            last = Some((walked, refinement));
        }
        let siblings = chain.siblings();
        if self.scene.frames.count > 1 {
            (self.list).relabel(
                (&self.scene, Some(&bundles)),
                Crossings::Later,
                |hit, f, at| chain.locate(&scene, hit.surface(), f.unwrap_or_default(), at),
            );
        }
        drop((bundles, chain));
        // The bake's patches on the pieces' triangles from here on: if it is cancelled now,
        // the bake answers as before (the patches' tallies count the same crossings on the
        // same patches), without pieces.
        let grouped = refine::regroup(&scene, &of, self.scene.patches.clone());
        self.tracer = SceneTracer::new(&grouped);
        // The same crossings on the same patches, but the dense lines' weights: tallied again.
        let patches = grouped.patches.len();
        (self.tallies).update(&self.list, &self.tracer.surfaces(), patches);
        let before = std::mem::replace(&mut self.scene, grouped);
        self.shown.get_or_insert(before);
        if control.is_cancelled() {
            return Err(TraceError::Cancelled);
        }
        let tracer = SceneTracer::new(&scene);
        let sampling = (self.list.lines(), self.seed, Poses::All);
        let (direct, area) = Self::sampled_lights(&scene, &tracer, sampling, control)?;
        let mut tallies = Tallies::default();
        let like = Some(&self.tallies);
        tallies.update_like(&self.list, &tracer.surfaces(), scene.patches.len(), like);
        let areas = scene.patches.iter().map(|p| p.area).collect();
        let map = crate::direct::points::PieceMap::new(&scene, &of);
        let coarse = Coarse::new(&scene, (&of, self.scene.patches.len()), &siblings);
        let groups = Groups::new(of, areas, self.scene.patches.len());
        let count = scene.patches.len();
        self.pieces = Some(Pieces {
            scene,
            tracer,
            tallies,
            direct,
            area,
            groups,
            map,
            shares: Default::default(),
            coarse,
        });
        Ok(count)
    }

    /// What the lines say of each piece of `scene` (piece `k` of patch `of[k]`, its triangles
    /// in `table`) at frame 0 ([`gaps::Walked`]), `radiance` being the patches' answer under
    /// `sky`: what each piece faces. With `before`, the walk of the scene `scene` was cut from
    /// by `refinement` (the previous round's): only the cut triangles' pieces are walked again.
    fn piece_scores(
        &self,
        (scene, table, of): (&Scene, &SurfaceTable, &[u32]),
        (radiance, sky): (&[[f64; 3]], [f64; 3]),
        bundles: &[crate::lines::Bundle],
        before: Option<(&gaps::Walked, &crate::scene::refine::Refinement)>,
    ) -> gaps::Walked {
        use crate::output::tonemap::luminance;
        let brightness: Vec<f64> = radiance.iter().map(|&l| luminance(l)).collect();
        let gathered = |j: u32| brightness[of[j as usize] as usize];
        let lines = (&self.list, Some(bundles));
        match before {
            Some((walked, refinement)) => walked.after(
                (scene, table),
                lines,
                (&gathered, luminance(sky)),
                refinement,
            ),
            None => gaps::Walked::new((scene, table), lines, &gathered, luminance(sky)),
        }
    }

    /// One round of [`Bake::split`]'s further cuts ([`gaps`]): the pieces of `scene` (piece `k`
    /// of patch `of[k]`) that misplace more than [`GAP_SHARE`] of the light the patches reflect
    /// (`radiance`, the patches' answer at frame 0 under `sky`), those that misplace the most
    /// first, then the pieces in a dense region of the lines (a gap: [`gaps::regions`]), the
    /// most crossed first: each bisected once, if it has the crossings of two pieces
    /// (deforming objects' are not cut), within `budget` pieces (the cuts neighbours need
    /// included). `None` when nothing is cut.
    fn cut_gaps(
        &self,
        (scene, scores): (&Scene, &[gaps::Piece]),
        radiance: &[[f64; 3]],
        budget: usize,
    ) -> Option<(Scene, crate::scene::refine::Refinement)> {
        use crate::output::tonemap::luminance;
        use crate::scene::refine;
        let reflected: f64 = (self.scene.patches.iter())
            .zip(radiance)
            .map(|(p, &l)| {
                let emitted = luminance(self.scene.materials[p.material as usize].emission);
                p.area * (luminance(l) - emitted).max(0.0)
            })
            .sum();
        // Each piece's triangle (global index), and whether it can be cut (not deforming).
        let meshes = std::iter::once((&scene.statics, true))
            .chain(scene.objects.iter().map(|o| (&o.mesh, o.is_rigid())));
        let mut triangle = vec![(0u32, false); scene.patches.len()];
        let faces = meshes.flat_map(|(m, cuttable)| m.faces.iter().map(move |f| (f, cuttable)));
        for (t, (f, cuttable)) in faces.enumerate() {
            for p in [Some(f.front), f.back].into_iter().flatten() {
                triangle[p as usize] = (t as u32, cuttable);
            }
        }
        // Whether a piece lies in a dense region: a static triangle whose centroid does.
        let (regions, _) = self.list.dense();
        let corners = refine::Corners::new(scene);
        let statics = scene.statics.triangles.len() as u32;
        let in_region = |t: u32| {
            t < statics && {
                let c = corners.own(t).map(|p| p.as_dvec3());
                let centroid = (c[0] + c[1] + c[2]) / 3.0;
                (regions.iter()).any(|r| centroid.cmpge(r.min).all() && centroid.cmple(r.max).all())
            }
        };
        // A piece in a region no wider than twice the gap's height is cut no further: the
        // light in a gap falls off over about its height, and smaller pieces only cost time.
        // Across parallel faces h apart, a segment's length is h / cos θ with cos θ of density
        // 2 cos θ, so the mean m of those shorter than the width W is 2h / (1 + h/W): h =
        // m / (2 − m/W).
        let small = |t: u32, m: f64| {
            let c = corners.own(t).map(|p| p.as_dvec3());
            let w = (c[0].distance(c[1]))
                .max(c[1].distance(c[2]))
                .max(c[2].distance(c[0]));
            m > 0.0 && w <= 2.0 * m / (2.0 - m / w)
        };
        let cuttable = |k: usize| {
            let (t, cuttable) = triangle[k];
            cuttable
                && scores[k].segments as f64 >= 2.0 * PIECE_CROSSINGS
                && !(in_region(t) && small(t, scores[k].near_length))
        };
        let mut order: Vec<(f64, u32)> = (scores.iter().enumerate())
            .filter(|&(k, q)| q.score > GAP_SHARE * reflected && cuttable(k))
            .map(|(k, q)| (q.score, k as u32))
            .collect();
        order.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let mut dense: Vec<(u64, u32)> = (0..scores.len())
            .filter(|&k| {
                let q = &scores[k];
                q.score <= GAP_SHARE * reflected
                    && q.in_gap()
                    && cuttable(k)
                    && in_region(triangle[k].0)
            })
            .map(|k| (scores[k].segments, k as u32))
            .collect();
        dense.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        // Each piece's triangle cut once: the root of its tree (heap order, node 1).
        let order: Vec<(u32, u32)> = (order.iter().map(|&(_, p)| p))
            .chain(dense.iter().map(|&(_, p)| p))
            .map(|p| (triangle[p as usize].0, 1))
            .collect();
        if order.is_empty() {
            return None;
        }
        let (cuts, (next, refinement)) = refine::cut_within_budget(scene, &order, budget);
        let cut = cuts.iter().any(|&c| c != 0) && next.patches.len() > scene.patches.len();
        cut.then_some((next, refinement))
    }

    /// The direct light of the punctual lights and the area lights of `scene`, sampled as a
    /// bake of `lines` lines from `seed` samples them.
    fn sampled_lights(
        scene: &Scene,
        tracer: &SceneTracer,
        (lines, seed, poses): (usize, u64, Poses),
        control: &Control,
    ) -> Result<(DirectLight, AreaLights), TraceError> {
        let direct = DirectLight::compute_poses(scene, tracer, poses, control)?;
        let sampling = Sampling::for_lines(lines as u64, scene.patches.len(), seed);
        let area = AreaLights::compute_poses(scene, tracer, (sampling, poses), control)?;
        Ok((direct, area))
    }

    /// Computes the poses of the patches' sampled emitters' light that [`Poses::First`] left
    /// pending: before the patches are solved at other frames than the first.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled (the light is then left as it was).
    pub fn complete_lights(&mut self, control: &Control) -> Result<(), TraceError> {
        let sampling = Sampling::for_lines(
            self.list.lines() as u64,
            self.scene.patches.len(),
            self.seed,
        );
        (self.area).complete(&self.scene, &self.tracer, sampling, control)?;
        (self.direct).complete(&self.scene, &self.tracer, control)
    }

    /// Samples the direct light again for the patches as they are, if the last cut let the
    /// pieces inherit theirs ([`Lights::Inherit`]); nothing otherwise.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled (the light is then left as it was).
    pub fn sample_lights(&mut self, control: &Control) -> Result<(), TraceError> {
        if self.inherited {
            let sampling = (self.list.lines(), self.seed, Poses::All);
            (self.direct, self.area) =
                Self::sampled_lights(&self.scene, &self.tracer, sampling, control)?;
            self.inherited = false;
        }
        Ok(())
    }

    /// The seed of the bake's lines, which also seeds its outputs' sampling.
    #[must_use]
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// What the lines found that the user should know: nodes with coplanar overlapping faces
    /// (duplicated faces, decals), whose crossings are shared between them
    /// ([`crate::trace::coincident`]).
    #[must_use]
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// What the bake found once its frames are solved (`frames`, all of them): the lines'
    /// [`Bake::warnings`], then the [`unsampled_warning`] if any. The loader's warnings are the
    /// scene's.
    #[must_use]
    pub fn findings(&self, frames: &[Arc<FrameSolution>]) -> Vec<String> {
        let mut found = self.warnings.clone();
        found.extend(unsampled_warning(&self.scene, frames));
        found
    }

    /// Bytes the bake keeps beyond its scene: the list, the tallies and the direct light, its
    /// pieces' included ([`Bake::split`]).
    #[must_use]
    pub fn bytes(&self) -> usize {
        let pieces = self.pieces.as_ref().map_or(0, |p| {
            p.tallies.bytes()
                + p.direct.memory()
                + p.area.memory()
                + p.groups.bytes()
                + p.coarse.bytes()
        });
        self.list.memory().bytes
            + self.tallies.bytes()
            + self.direct.memory()
            + self.area.memory()
            + pieces
            + self.gathered.bytes()
    }

    /// The scene to draw: the bake's patches on the triangles they had before [`Bake::split`]
    /// cut them for the pieces (the same patches, ids and areas as [`Bake::scene`], whose
    /// triangles are the pieces', with fewer triangles).
    #[must_use]
    pub fn shown(&self) -> &Scene {
        self.shown.as_ref().unwrap_or(&self.scene)
    }

    /// Where the pieces the frames are solved on lie on the traced triangles, once
    /// [`Bake::split`]: with a frame's [`FrameSolution::pieces`], what the outputs' points read.
    #[must_use]
    pub fn piece_map(&self) -> Option<&crate::direct::points::PieceMap> {
        self.pieces.as_ref().map(|p| &p.map)
    }

    /// The pieces the frames are solved on ([`Bake::split`]), if split.
    #[must_use]
    pub fn pieces(&self) -> Option<usize> {
        self.pieces.as_ref().map(|p| p.scene.patches.len())
    }

    /// The intersection list.
    #[must_use]
    pub fn list(&self) -> &IntersectionList {
        &self.list
    }

    /// The tallies.
    #[must_use]
    pub fn tallies(&self) -> &Tallies {
        &self.tallies
    }

    /// The tracer (BVHs and the faces of every traced triangle).
    #[must_use]
    pub fn tracer(&self) -> &SceneTracer {
        &self.tracer
    }

    /// The tallies of one frame.
    #[must_use]
    pub fn frame_tally(&self, frame: usize) -> FrameTally {
        self.tallies
            .frame(&self.list, &self.tracer.surfaces(), frame)
    }

    /// The visibility information the lines measure at `frame`
    /// ([`crate::solve::information`]).
    #[must_use]
    pub fn information(&self, frame: usize) -> crate::solve::information::Information {
        crate::solve::information::Information::measure(
            &self.scene,
            &self.list,
            &self.tracer.surfaces(),
            &self.frame_tally(frame),
            frame,
        )
    }

    /// Frames that share their solution: `representatives()[f]` is the first frame with the
    /// same tallies and the same direct light as f.
    #[must_use]
    pub fn representatives(&self) -> Vec<usize> {
        let by_tally = self.tallies.representatives();
        if self.direct.is_empty() && self.area.is_empty() {
            return by_tally;
        }
        let mut first: std::collections::HashMap<_, usize> = Default::default();
        (0..by_tally.len())
            .map(|f| {
                let key = (by_tally[f], self.direct.state(f), self.area.state(f));
                *first.entry(key).or_insert(f)
            })
            .collect()
    }

    /// The direct light of the punctual lights.
    #[must_use]
    pub fn direct(&self) -> &DirectLight {
        &self.direct
    }

    /// The direct light of the emitting surfaces sampled as area lights.
    #[must_use]
    pub fn area_lights(&self) -> &AreaLights {
        &self.area
    }

    /// The direct light of the emitting surfaces sampled on the pieces, once [`Bake::split`].
    #[must_use]
    pub fn piece_area_lights(&self) -> Option<&AreaLights> {
        self.pieces.as_ref().map(|p| &p.area)
    }

    /// The irradiance of every patch straight from the punctual lights at `power` and the
    /// sampled emitters with `materials`' emission at `frame`, and its variance (both empty when
    /// there are none).
    #[must_use]
    pub fn direct_light(
        &self,
        frame: usize,
        materials: &[Material],
        power: &[[f64; 3]],
    ) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        direct_light(&self.direct, &self.area, frame, materials, power)
    }

    /// Each light's power (colour × intensity) as the scene gives it.
    #[must_use]
    pub fn light_power(&self) -> Vec<[f64; 3]> {
        self.scene.lights.iter().map(Light::power).collect()
    }

    /// Solves one frame with `materials` (the scene's own, or new ones for relighting) and the
    /// scene's lights.
    #[must_use]
    pub fn solve_frame(
        &self,
        frame: usize,
        materials: &[Material],
        params: &SolveParams,
    ) -> FrameSolution {
        self.solve_frame_lit(frame, materials, &self.light_power(), params)
    }

    /// Solves one frame with `materials` and the punctual lights at `power` (colour ×
    /// intensity per light, in the scene's order): relighting either needs no tracing.
    #[must_use]
    pub fn solve_frame_lit(
        &self,
        frame: usize,
        materials: &[Material],
        power: &[[f64; 3]],
        params: &SolveParams,
    ) -> FrameSolution {
        self.solve_frame_from(frame, materials, power, params, None)
    }

    /// [`Bake::solve_frame_lit`] starting from `start`, a nearby frame and its solution (with
    /// the same materials and lights): the same answer to within the solve's stopping criterion
    /// ([`SolveParams::noise`]), in fewer iterations. The start is first moved by what the
    /// direct light changes between the two frames (a shadow that moved), which the solve then
    /// need not find.
    #[must_use]
    pub fn solve_frame_from(
        &self,
        frame: usize,
        materials: &[Material],
        power: &[[f64; 3]],
        params: &SolveParams,
        start: Option<(usize, &FrameSolution)>,
    ) -> FrameSolution {
        match &self.pieces {
            Some(pieces) => {
                let surfaces = pieces.tracer.surfaces();
                let state = pieces.state();
                let solve = (frame, materials, power, params);
                // The shape term of the frame the coarse pieces were last solved at (a run's
                // first), carried along the run: a second solve at every frame cost as much
                // as the pieces' own.
                let carried =
                    start
                        .map(|(_, s)| (&s.shape, &s.spread))
                        .filter(|(shape, spread)| {
                            let patches = self.scene.patches.len();
                            shape.len() == patches && spread.len() == patches
                        });
                let tally = (pieces.tallies).frame(&self.list, &surfaces, frame);
                let (coarse_tally, spread) = match carried {
                    Some((_, spread)) => (None, Spread::Carried(spread)),
                    None => {
                        let coarse = tally.merged(&pieces.coarse.of_pieces);
                        (Some(coarse), Spread::Replicas)
                    }
                };
                let groups = Some(&pieces.groups);
                let mut solution = Self::solve_state_from(
                    &tally,
                    state,
                    (groups, None),
                    solve,
                    start,
                    Some(spread),
                );
                match (coarse_tally, carried) {
                    // The pieces one level coarser solved as well (the answer alone): how far
                    // the last level of cuts moved it says how far the pieces themselves may
                    // still be from the light's shape.
                    (Some(coarse_tally), _) => {
                        let coarse = Self::coarse_answer(pieces, &coarse_tally, solve);
                        solution.shape = (solution.radiance.iter())
                            .zip(&coarse.radiance)
                            .map(|(l, w)| [l.map(|x| x as f32), w.map(|x| x as f32)])
                            .collect();
                    }
                    (None, Some((shape, _))) => solution.shape.clone_from(shape),
                    (None, None) => {}
                }
                solution.pieces_stderr = (solution.stderr.iter())
                    .map(|e| e.unwrap_or_default().map(|x| x as f32))
                    .collect();
                for ((e, l), [l0, w0]) in (solution.stderr.iter_mut())
                    .zip(&solution.radiance)
                    .zip(&solution.shape)
                {
                    if let Some(e) = e {
                        for c in 0..3 {
                            // The move at the frame it was measured, scaled by how the
                            // patch's light has changed since.
                            let (l0, w0) = (f64::from(l0[c]), f64::from(w0[c]));
                            let scale = if l0 > 0.0 { l[c] / l0 } else { 1.0 };
                            e[c] = e[c].hypot(SHAPE_ERROR * (l0 - w0) * scale);
                        }
                    }
                }
                solution
            }
            None => self.solve_tally_from(
                &self.frame_tally(frame),
                frame,
                materials,
                power,
                params,
                start,
            ),
        }
    }

    /// [`Bake::solve_frame_lit`] from `tally`, frame `frame`'s tallies however obtained (the
    /// multiframe list's, or the frame traced alone): the direct light is the frame's.
    #[must_use]
    pub fn solve_tally(
        &self,
        tally: &FrameTally,
        frame: usize,
        materials: &[Material],
        power: &[[f64; 3]],
        params: &SolveParams,
    ) -> FrameSolution {
        self.solve_tally_from(tally, frame, materials, power, params, None)
    }

    /// [`Bake::solve_tally`] starting from `start` (see [`Bake::solve_frame_from`]): the
    /// patches solved whole, whether or not the bake is [`Bake::split`].
    fn solve_tally_from(
        &self,
        tally: &FrameTally,
        frame: usize,
        materials: &[Material],
        power: &[[f64; 3]],
        params: &SolveParams,
        start: Option<(usize, &FrameSolution)>,
    ) -> FrameSolution {
        let state = self.state();
        let solve = (frame, materials, power, params);
        // A run's later frames carry what the replicas made of the first bounce's spread.
        let spread = (start.map(|(_, s)| &s.spread[..]))
            .filter(|spread| spread.len() == self.scene.patches.len())
            .map_or(Spread::Replicas, Spread::Carried);
        Self::solve_state_from(tally, state, (None, None), solve, start, Some(spread))
    }

    /// What the bake's patches are solved with: the scene, its tracer, their direct light and
    /// visible shares.
    fn state(&self) -> State<'_> {
        (
            &self.scene,
            &self.tracer,
            &self.direct,
            &self.area,
            &self.shares,
        )
    }

    /// The answer alone (no replicas) for the bake's patches solved whole at a frame (`solve`:
    /// frame, materials, the lights' power, parameters), from `start` if given: before the
    /// split, its scores' light.
    fn whole_answer(
        &self,
        solve: (usize, &[Material], &[[f64; 3]], &SolveParams),
        start: Option<(usize, &FrameSolution)>,
    ) -> FrameSolution {
        let tally = self.frame_tally(solve.0);
        Self::solve_state_from(&tally, self.state(), (None, None), solve, start, None)
    }

    /// The answer alone (per patch: the first bounce's spread its only error bar) of
    /// `pieces`' coarse level ([`Coarse`]) from `tally`, its tallies at the frame (`solve`:
    /// frame, materials, the lights' power, parameters). Its direct light is the pieces'
    /// (each coarse piece's, its pieces' area-weighted mean): the move from it to the pieces
    /// is what the last cuts do to the transport, not a second sampling of the light.
    fn coarse_answer(
        pieces: &Pieces,
        tally: &FrameTally,
        solve: (usize, &[Material], &[[f64; 3]], &SolveParams),
    ) -> FrameSolution {
        let (_, materials, power, _) = solve;
        let coarse = &pieces.coarse;
        let light_of = |frame: usize| {
            let (e, v) = direct_light(&pieces.direct, &pieces.area, frame, materials, power);
            if e.is_empty() {
                return (e, v);
            }
            coarse.of_pieces.area_mean(&e, &v)
        };
        let state = (
            &coarse.scene,
            &pieces.tracer,
            &pieces.direct,
            &pieces.area,
            &coarse.shares,
        );
        let levels = (Some(&coarse.groups), Some(&light_of as &LightOf<'_>));
        let spread = Some(Spread::FirstBounce);
        Self::solve_state_from(tally, state, levels, solve, None, spread)
    }

    /// Solves `tally`, the tallies of `state`'s patches (the bake's, or its pieces' with their
    /// `groups`) and their direct light, at `frame` with `materials` and the lights at `power`,
    /// starting from `start` (the answer for the bake's patches at a nearby frame).
    /// `light_of` gives their direct light at a frame, if not `state`'s own (its direct light
    /// and visible shares are read at `frame` and at the start's).
    fn solve_state_from(
        tally: &FrameTally,
        (scene, tracer, direct, area, shares): State<'_>,
        (groups, light_of): (Option<&Groups>, Option<&LightOf<'_>>),
        (frame, materials, power, params): (usize, &[Material], &[[f64; 3]], &SolveParams),
        start: Option<(usize, &FrameSolution)>,
        spread: Option<Spread<'_>>,
    ) -> FrameSolution {
        let patch_materials: Vec<u32> = scene.patches.iter().map(|p| p.material).collect();
        let light = |frame| match light_of {
            Some(light_of) => light_of(frame),
            None => direct_light(direct, area, frame, materials, power),
        };
        let (mut irradiance, mut variance) = light(frame);
        // The direct light of what can be seen of each patch, as the tallies count only the
        // crossings of its visible part: sampled over the whole patch, it is the visible
        // part's times the share of it that no surface touches (a box on the floor blocks
        // every shadow ray from under it).
        let touched: Vec<bool> = tally.hidden.iter().map(|&h| h > 0).collect();
        // The share is estimated too: its variance adds (E / v)² · var(v) / v² to the
        // quotient's (to first order).
        let shares = (!irradiance.is_empty() && touched.contains(&true))
            .then(|| crate::direct::visible_shares(scene, tracer, frame, &touched, shares));
        let visible: Option<Vec<f64>> = (shares.as_ref()).map(|s| s.iter().map(|s| s.0).collect());
        let mut scales = vec![1.0; irradiance.len()];
        for (i, &(v, share_variance)) in shares.iter().flatten().enumerate() {
            if v < 1.0 {
                let scale = if v > 0.0 { 1.0 / v } else { 0.0 };
                scales[i] = scale;
                let relative = share_variance * scale * scale;
                irradiance[i] = irradiance[i].map(|e| e * scale);
                variance[i] = std::array::from_fn(|c| {
                    variance[i][c] * scale * scale + irradiance[i][c].powi(2) * relative
                });
            }
        }
        let sampled: Vec<bool> = patch_materials.iter().map(|&m| area.samples(m)).collect();
        let lit = (!irradiance.is_empty()).then_some(Direct {
            irradiance: &irradiance,
            variance: &variance,
            sampled: &sampled,
            visible: visible.as_deref(),
        });
        // The start's radiance (each piece its patch's), with this frame's direct light in
        // place of its own (both of the visible part, by this frame's shares).
        let start_solution = start.map(|(_, s)| s);
        let start = start.map(|(from, solution)| {
            // A split solution's own pieces where it has them (a patch's mean would start
            // every piece at its patch's light, the shape the solve has to find again).
            let mut radiance: Vec<[f64; 3]> = match groups {
                Some(g) if solution.pieces.len() == g.of().len() => {
                    (solution.pieces.iter()).map(|l| l.map(f64::from)).collect()
                }
                Some(g) => (g.of().iter())
                    .map(|&p| solution.radiance[p as usize])
                    .collect(),
                None => solution.radiance.clone(),
            };
            let state = |f: usize| (direct.state(f), area.state(f));
            if !irradiance.is_empty() && state(from) != state(frame) {
                let (before, _) = light(from);
                for (i, l) in radiance.iter_mut().enumerate() {
                    let rho = materials[patch_materials[i] as usize].reflectance;
                    for c in 0..3 {
                        let old = before.get(i).map_or(0.0, |e| e[c] * scales[i]);
                        l[c] += rho[c] * (irradiance[i][c] - old) * std::f64::consts::FRAC_1_PI;
                    }
                }
            }
            radiance
        });
        let start = start.as_deref();
        // What the start's noise test measured, if it answered for the same patches.
        let guess = start_solution.map(|s| &s.first[..]);
        match spread {
            Some(spread) => solve_grouped(
                tally,
                &patch_materials,
                materials,
                params,
                lit,
                start,
                (groups, spread, guess),
            ),
            None => solve_answer(tally, &patch_materials, materials, params, lit, start),
        }
    }

    /// Solves every frame; frames with identical tallies and direct light share one solution.
    /// Every frame is answered, converged or not (check [`FrameSolution::ensure_converged`]).
    #[must_use]
    pub fn solve_all(
        &self,
        materials: &[Material],
        params: &SolveParams,
    ) -> Vec<Arc<FrameSolution>> {
        let mut frames = Vec::with_capacity(self.scene.frames.count);
        let power = self.light_power();
        self.solve_frames(
            (materials, &power, params),
            (usize::MAX, &Control::default()),
            &|_| {},
            |_, s| {
                frames.push(s.clone());
                ControlFlow::Continue(())
            },
        );
        frames
    }

    /// The runs frames are solved in: the distinct frames (those that share no other's
    /// solution, [`Bake::representatives`]) in order, [`RUN`] at a time. Within a run each
    /// frame starts from the solution of the one before it (an animation changes little from
    /// frame to frame); a run's first frame starts cold. The bake command and the service both
    /// solve by these runs ([`Bake::solve_run`]), so a frame's answer depends neither on which
    /// of them solved it nor on the threads.
    #[must_use]
    pub fn solve_runs(&self) -> Vec<Vec<usize>> {
        let representatives = self.representatives();
        let distinct: Vec<usize> = (0..representatives.len())
            .filter(|&f| representatives[f] == f)
            .collect();
        distinct.chunks(RUN).map(<[usize]>::to_vec).collect()
    }

    /// Solves one run of [`Bake::solve_runs`] with `materials` and the lights at `power`:
    /// each frame with its solution. Each frame starts from the one before it, and the run's
    /// later frames carry the error bars' terms its first frame solved
    /// ([`FrameSolution::shape`], [`FrameSolution::spread`]), which the answers then drop.
    #[must_use]
    pub fn solve_run(
        &self,
        run: &[usize],
        materials: &[Material],
        power: &[[f64; 3]],
        params: &SolveParams,
    ) -> Vec<(usize, Arc<FrameSolution>)> {
        let mut solved: Vec<(usize, FrameSolution)> = Vec::with_capacity(run.len());
        for &f in run {
            let start = solved.last().map(|(p, s)| (*p, s));
            let solution = self.solve_frame_from(f, materials, power, params, start);
            solved.push((f, solution));
        }
        (solved.into_iter())
            .map(|(f, mut s)| {
                (s.shape, s.spread, s.first) = (Vec::new(), Vec::new(), Vec::new());
                (f, Arc::new(s))
            })
            .collect()
    }

    /// Solves every frame with `materials`, the lights at `power` and `params`, and gives each
    /// to `serve` in frame order: the one rule for which frames are solved, shared and served,
    /// that the bake command and the service both follow. The runs of [`Bake::solve_runs`] are
    /// solved `at_once` at a time in parallel (the service: one per thread, so that a stream
    /// sees its first frames soon; a bake: all of them), and after each batch every frame up
    /// to the next distinct frame not yet solved is served (a frame shares its
    /// representative's solution, which comes no later than it). `solved` is told, from any
    /// thread, how many distinct frames each run solved (a progress bar's work). Stops when
    /// `control` is cancelled or `serve` breaks (a frame that does not converge, say): the
    /// frames after it are neither solved nor served.
    pub fn solve_frames(
        &self,
        (materials, power, params): (&[Material], &[[f64; 3]], &SolveParams),
        (at_once, control): (usize, &Control),
        solved: &(dyn Fn(usize) + Sync),
        mut serve: impl FnMut(usize, &Arc<FrameSolution>) -> ControlFlow<()>,
    ) {
        let representatives = self.representatives();
        let runs = self.solve_runs();
        let count = representatives.len();
        let mut by_frame: Vec<Option<Arc<FrameSolution>>> = vec![None; count];
        let mut frame = 0;
        let at_once = at_once.max(1);
        for (k, batch) in runs.chunks(at_once).enumerate() {
            if control.is_cancelled() {
                return;
            }
            let frames: Vec<(usize, Arc<FrameSolution>)> = batch
                .par_iter()
                .flat_map_iter(|run| {
                    if control.is_cancelled() {
                        return Vec::new();
                    }
                    let frames = self.solve_run(run, materials, power, params);
                    solved(run.len());
                    frames
                })
                .collect();
            if control.is_cancelled() {
                return;
            }
            for (f, s) in frames {
                by_frame[f] = Some(s);
            }
            let next = runs.get((k + 1) * at_once).map_or(count, |run| run[0]);
            for f in frame..next {
                let Some(solution) = &by_frame[representatives[f]] else {
                    return;
                };
                if serve(f, solution).is_break() {
                    return;
                }
            }
            frame = next;
        }
    }
}

/// Samples `area`, the area lights of `scene`, again if a bake of `after` lines samples them
/// more densely than one of `before` (`(before, after, seed)`), as [`Bake::refine`] does.
fn resample(
    area: &mut AreaLights,
    scene: &Scene,
    tracer: &SceneTracer,
    (before, after, seed): (usize, usize, u64),
    control: &Control,
) -> Result<(), TraceError> {
    let patches = scene.patches.len();
    let before = Sampling::for_lines(before as u64, patches, seed);
    let after = Sampling::for_lines(after as u64, patches, seed);
    if after.density != before.density && !area.is_empty() {
        let poses = if area.pending() {
            Poses::First
        } else {
            Poses::All
        };
        *area = AreaLights::compute_poses(scene, tracer, (after, poses), control)?;
    }
    Ok(())
}

/// The irradiance straight from the punctual lights of `direct` at `power` and the sampled
/// emitters of `area` with `materials` at `frame`, and its variance (both empty when there are
/// none).
fn direct_light(
    direct: &DirectLight,
    area: &AreaLights,
    frame: usize,
    materials: &[Material],
    power: &[[f64; 3]],
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let punctual = direct
        .irradiance(frame, power)
        .zip(direct.variance(frame, power));
    let area = area.irradiance(frame, materials);
    match (punctual, area) {
        (None, None) => (Vec::new(), Vec::new()),
        (Some(one), None) | (None, Some(one)) => one,
        (Some((mut e, mut v)), Some((a, w))) => {
            for (i, (a, w)) in a.iter().zip(&w).enumerate() {
                for c in 0..3 {
                    e[i][c] += a[c];
                    v[i][c] += w[c];
                }
            }
            (e, v)
        }
    }
}

/// Distinct frames per run of [`Bake::solve_runs`]: a run's first frame starts cold and
/// solves its error bars' replicas and a split bake's shape term, the others start from the
/// frame before and carry them ([`crate::solve::Spread::Carried`]); runs are solved in
/// parallel. The moving Cornell box at 61 frames solved in 5.3 s with runs of 4, 4.8 s with 8.
pub const RUN: usize = 8;

/// Overlaps below this share of a node's crossings are chance coincidences (lines through the
/// seam where two surfaces meet), not overlapping faces.
const OVERLAP_SHARE: f64 = 0.01;

/// Warnings naming the nodes whose faces overlap coplanar: pairs of nodes (or a node with
/// itself) where more than [`OVERLAP_SHARE`] of the crossings of either land on both. Static
/// crossings count once; crossings with moving objects once per frame.
fn overlap_warnings(scene: &Scene, tracer: &SceneTracer, list: &IntersectionList) -> Vec<String> {
    use std::collections::BTreeMap;
    let nodes = tracer.nodes();
    let surfaces = tracer.surfaces();
    let spaces = surfaces.spaces;
    let node_count = nodes.iter().map(|&n| n as usize + 1).max().unwrap_or(0);
    type Counts = (Vec<u64>, BTreeMap<(u32, u32), u64>);
    let empty = || -> Counts { (vec![0; node_count], BTreeMap::new()) };
    let (crossings, shared) = (0..list.lines())
        .into_par_iter()
        .fold_with(
            (empty(), Vec::new()),
            |((mut crossings, mut shared), mut merged), l| {
                let mut pair = |a: u32, b: u32| {
                    let (a, b) = (nodes[a as usize], nodes[b as usize]);
                    *shared.entry((a.min(b), a.max(b))).or_insert(0) += 1;
                };
                let surfaces = surfaces.along(list.direction(l));
                let statics = list.static_hits(l);
                statics
                    .iter()
                    .for_each(|h| crossings[nodes[h.surface() as usize] as usize] += 1);
                crate::trace::coincident::overlaps(statics, &surfaces, &mut pair);
                let moving = list.moving_hits(l);
                moving
                    .iter()
                    .for_each(|h| crossings[nodes[h.hit.surface() as usize] as usize] += 1);
                let mut start = 0;
                for frame in moving.chunk_by(|a, b| a.frame == b.frame) {
                    list.frame_hits_from(l, frame[0].frame as usize, start, &mut merged);
                    start += frame.len();
                    crate::trace::coincident::overlaps(&merged, &surfaces, |a, b| {
                        // Static pairs were counted above.
                        if spaces[a as usize] != 0 || spaces[b as usize] != 0 {
                            pair(a, b);
                        }
                    });
                }
                ((crossings, shared), merged)
            },
        )
        .map(|(counts, _)| counts)
        .reduce(empty, |(mut ca, mut sa), (cb, sb)| {
            ca.iter_mut().zip(cb).for_each(|(a, b)| *a += b);
            sb.into_iter()
                .for_each(|(k, v)| *sa.entry(k).or_insert(0) += v);
            (ca, sa)
        });
    shared
        .into_iter()
        .filter_map(|((a, b), n)| {
            let (fewer, most) = if crossings[a as usize] <= crossings[b as usize] {
                (a, crossings[a as usize])
            } else {
                (b, crossings[b as usize])
            };
            let share = n as f64 / most.max(1) as f64;
            (n >= 4 && share >= OVERLAP_SHARE).then(|| {
                let which = if a == b {
                    format!("{} has faces", scene.node_label(a))
                } else {
                    format!(
                        "{} and {} have faces",
                        scene.node_label(a),
                        scene.node_label(b)
                    )
                };
                format!(
                    "{which} that overlap in one plane (duplicated faces or decals): {:.0}% of \
                     {}'s crossings land on two faces at once, and each gets a share \
                     of them, as if they were drawn in turn",
                    100.0 * share.min(1.0),
                    scene.node_label(fewer)
                )
            })
        })
        .collect()
}

/// The share of the scene's area that may bake black unannounced: patches no line crossed
/// (samples 0) that are each too small to have expected any crossing, together over this
/// share of the area, get a warning of their own.
const UNSAMPLED_SHARE: f64 = 0.01;

/// A warning for patches that no line crossed in some frame, which bake black (samples 0):
/// those whose area should have drawn at least 10 crossings (the chance of none is then below
/// 5e-5: geometry hidden from the lines), and patches too small for the lines when together
/// they are over [`UNSAMPLED_SHARE`] of the scene's area in a frame (a fine `--patch-size` on
/// few lines). A few tiny patches that the lines simply missed are not worth one.
#[must_use]
pub fn unsampled_warning(scene: &Scene, frames: &[Arc<FrameSolution>]) -> Option<String> {
    let total_area: f64 = scene.patches.iter().map(|p| p.area).sum();
    if total_area <= 0.0 {
        return None;
    }
    // Per patch: missed though it expected 10 crossings; missed, expecting fewer, in a frame
    // where such patches are over the share.
    let (mut hidden, mut sparse) = (
        vec![false; scene.patches.len()],
        vec![false; scene.patches.len()],
    );
    let (mut hidden_frames, mut sparse_frames) = (Vec::new(), Vec::new());
    // Frames that share a solution are checked once.
    let mut checked: std::collections::HashMap<*const FrameSolution, (bool, bool)> =
        Default::default();
    for (f, frame) in frames.iter().enumerate() {
        let (any_hidden, too_sparse) = *checked.entry(Arc::as_ptr(frame)).or_insert_with(|| {
            let crossings: u64 = frame.samples.iter().sum();
            let (mut any_hidden, mut missed_area) = (false, 0.0);
            let expected = |i: usize| crossings as f64 * scene.patches[i].area / total_area;
            for (i, patch) in scene.patches.iter().enumerate() {
                if frame.samples[i] == 0 {
                    if expected(i) >= 10.0 {
                        hidden[i] = true;
                        any_hidden = true;
                    } else {
                        missed_area += patch.area;
                    }
                }
            }
            let too_sparse = missed_area > UNSAMPLED_SHARE * total_area;
            if too_sparse {
                for (i, missed) in sparse.iter_mut().enumerate() {
                    *missed |= frame.samples[i] == 0 && expected(i) < 10.0;
                }
            }
            (any_hidden, too_sparse)
        });
        if any_hidden {
            hidden_frames.push(f as u32);
        }
        if too_sparse {
            sparse_frames.push(f as u32);
        }
    }
    let list = |v: &[u32], name: &dyn Fn(u32) -> String| {
        let shown: Vec<String> = v.iter().take(8).map(|&k| name(k)).collect();
        let more = if v.len() > 8 { ", …" } else { "" };
        format!("{}{more}", shown.join(", "))
    };
    // The patches marked, their share of the area and their nodes.
    let described = |marked: &[bool]| {
        let patches: Vec<usize> = (0..marked.len()).filter(|&i| marked[i]).collect();
        let area: f64 = patches.iter().map(|&i| scene.patches[i].area).sum();
        let mut nodes: Vec<u32> = (patches.iter())
            .map(|&i| scene.patches[i].source.node)
            .collect();
        nodes.sort_unstable();
        nodes.dedup();
        let was = if patches.len() == 1 {
            "patch was"
        } else {
            "patches were"
        };
        format!(
            "{} {was} ({:.2}% of the scene's area, in {})",
            patches.len(),
            100.0 * area / total_area,
            list(&nodes, &|n| scene.node_label(n)),
        )
    };
    let mut found = Vec::new();
    if !hidden_frames.is_empty() {
        found.push(format!(
            "{} crossed by no line in frame(s) {}, though their area should have drawn at \
             least 10 crossings each: they bake black (samples 0)",
            described(&hidden),
            list(&hidden_frames, &|f| f.to_string())
        ));
    }
    if !sparse_frames.is_empty() {
        found.push(format!(
            "{} crossed by no line in frame(s) {}: they bake black (samples 0), over {}% of \
             the scene's area; their patches are too small for the lines (bake with more \
             lines, or a larger patch size)",
            described(&sparse),
            list(&sparse_frames, &|f| f.to_string()),
            100.0 * UNSAMPLED_SHARE
        ));
    }
    (!found.is_empty()).then(|| found.join("; "))
}

/// Memory a job will need, estimated from the scene before tracing: crossings per line from
/// `2 A / A(W)` (static once, moving per frame), 8 and 12 bytes each, plus offsets and the
/// tallies and direct light of the patches and of the pieces they are solved on, the patches
/// adaptive cuts may add up to `budget` (their most patches, if they are made), and every
/// frame's solution, which is kept ([`FrameSolution::BYTES_PER_PATCH`] per patch and frame).
/// The service refuses a job over its memory budget from it; `radiosity scene` reports it.
#[must_use]
pub fn estimate_bytes(scene: &Scene, lines: u64, budget: Option<usize>) -> u64 {
    let aw = scene.bounds.surface_area().max(f64::MIN_POSITIVE);
    let r2 = scene.normalisation.radius.powi(2);
    let (mut static_area, mut moving_area) = (0.0, 0.0);
    for p in &scene.patches {
        // Each traced triangle once (its front patch), in normalised units.
        if p.side == crate::scene::Side::Front {
            if p.object.is_some() {
                moving_area += p.area / r2
            } else {
                static_area += p.area / r2
            }
        }
    }
    let frames = scene.frames.count as f64;
    let lines = lines as f64;
    let static_hits = lines * 2.0 * static_area / aw;
    let moving_hits = lines * frames * 2.0 * moving_area / aw;
    // The direct light of the punctual lights: 4 bytes per patch and state of each light, a
    // state per frame when it or the geometry moves (an upper bound: repeated poses share).
    let direct: f64 = scene
        .lights
        .iter()
        .map(|l| {
            let states = if l.moves() || !scene.objects.is_empty() {
                frames
            } else {
                1.0
            };
            states * scene.patches.len() as f64 * 4.0
        })
        .sum();
    // The pieces the frames are solved on (`Bake::split`): one per `PIECE_CROSSINGS`
    // crossings at most, within its budget of one per `LINES_PER_PIECE` lines (a gap's rim is
    // cut finer than eight per patch).
    let patches = scene.patches.len() as f64;
    let crossings = static_hits + moving_hits / frames;
    let pieces = (lines / LINES_PER_PIECE as f64)
        .min(patches + crossings / PIECE_CROSSINGS)
        .max(patches);
    // The list, plus the patches' and the pieces' tallies, each of about the same size as the
    // static crossings, plus the solvers, plus the direct light of patches and pieces.
    let bytes = lines * 8.0
        + static_hits * 8.0 * 3.0
        + moving_hits * 12.0
        + (patches + pieces) * 200.0
        + direct * (1.0 + pieces / patches.max(1.0));
    let cuts = budget.map_or(0.0, |b| {
        b.saturating_sub(scene.patches.len()) as f64 * 200.0
    });
    // Every frame's solution is kept (served, written), for every patch the cuts may make.
    let shown = budget.map_or(patches, |b| patches.max(b as f64));
    let solved = frames * shown * FrameSolution::BYTES_PER_PATCH as f64;
    (bytes + cuts + solved) as u64
}
