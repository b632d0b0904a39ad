//! The timeline's intersection list (METHOD.md §5): one list of global-line crossings for the
//! whole animation.
//!
//! Static geometry is intersected once; moving objects once per frame, each crossing tagged with
//! its frame. The crossings of frame f along a line are the static ones plus those tagged f, in
//! order along the line ([`IntersectionList::frame_hits`]). Storage is two CSR arrays (one offset
//! per line, hits of all lines in one array): 8 bytes per static crossing, 12 per moving one.
//! Memory grows with the static crossings plus the moving crossings summed over frames, never
//! with frames × scene.

pub mod stats;

use crate::control::{Control, TraceError};

use rayon::prelude::*;

use crate::lines::{Batch, Bundle};
use crate::scene::{Bounds, Motion, Scene};
use crate::trace::pages::reserve_in_huge_pages;
use crate::trace::{Hit, Line, ParallelLines, SceneTracer, Scratch, sort_by_line};

/// How many lines to trace, and from which seed.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LineParams {
    /// Total number of lines (approximately: the grids' random offsets move it by a fraction of
    /// a percent).
    pub lines: u64,
    /// Seed of the line set: the same seed gives the same lines, whatever the thread count.
    pub seed: u64,
}

/// Named line budgets, chosen from the measured speed/accuracy trade (README, "Presets"): the
/// same names in the CLI and the API.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Preset {
    /// 100,000 lines: previews (the sample level's 25 frames in about 5 s; against the path
    /// tracer, 8.5% at points; the README's preset table).
    Draft,
    /// 1,000,000 lines: everyday bakes, and what a bake asks for by default (about 25 s for the
    /// level's 25 frames at 1.9% per patch, 5.6% at points; the moving Cornell box at 1.0% per
    /// patch, 5.0% at points).
    #[default]
    Default,
    /// 10,000,000 lines: final bakes (about 4 minutes for 25 frames; the moving Cornell box at
    /// 0.8% per patch, 3.9% at points).
    Final,
}

impl Preset {
    /// The line budget of the preset.
    #[must_use]
    pub fn lines(self) -> u64 {
        match self {
            Self::Draft => 100_000,
            Self::Default => 1_000_000,
            Self::Final => 10_000_000,
        }
    }
}

impl std::str::FromStr for Preset {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "draft" => Ok(Self::Draft),
            "default" => Ok(Self::Default),
            "final" => Ok(Self::Final),
            other => Err(format!("unknown preset {other:?}: draft, default or final")),
        }
    }
}

/// A crossing with a moving object, tagged with its frame: 12 bytes.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FrameHit {
    /// The frame the crossing belongs to.
    pub frame: u32,
    /// The crossing.
    pub hit: Hit,
}

/// Which crossings [`IntersectionList::relabel`] gives new triangles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Crossings {
    /// Every crossing.
    All,
    /// The static crossings and the moving ones at frame 0: the list as frame 0 reads it.
    AtFrameZero,
    /// The moving crossings at the frames after the first.
    Later,
}

/// A batch of lines in the list and where its lines start.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
struct BatchLines {
    batch: Batch,
    /// Number of lines of each bundle, in bundle order.
    bundle_lines: Vec<u32>,
}

/// The intersection list of a timeline.
#[derive(Clone, serde::Serialize, serde::Deserialize)]
pub struct IntersectionList {
    batches: Vec<BatchLines>,
    /// The first line of every bundle of every batch, in line order, with the bundle's
    /// direction: a line's direction by binary search.
    bundle_starts: Vec<(u32, glam::Vec3)>,
    frames: usize,
    /// `static_hits[static_offsets[l]..static_offsets[l + 1]]` are line l's static crossings,
    /// sorted along the line.
    static_offsets: Vec<u32>,
    static_hits: Vec<Hit>,
    /// `dynamic_hits[dynamic_offsets[l]..dynamic_offsets[l + 1]]` are line l's moving crossings,
    /// sorted by frame, then along the line.
    dynamic_offsets: Vec<u32>,
    dynamic_hits: Vec<FrameHit>,
    /// Regions whose lines are denser ([`IntersectionList::add_dense`]), and by how much.
    dense: Vec<Bounds>,
    factor: u32,
    /// Every line's weight ([`IntersectionList::line_weights`]), kept as lines and regions
    /// are added.
    weights: Vec<u8>,
    /// The scene's box the global lines were drawn against.
    bounds: Bounds,
}

/// A part of a batch of lines for one machine of several: the bundles `b` with
/// `b % count == index` ([`IntersectionList::build_shard`]); [`IntersectionList::merge`] puts
/// the parts together again.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Shard {
    /// Which part, from 0.
    pub index: u32,
    /// How many parts (at least 1).
    pub count: u32,
}

impl Shard {
    /// The whole batch.
    pub const WHOLE: Self = Self { index: 0, count: 1 };

    /// Whether bundle `bundle` is this part's.
    #[must_use]
    pub fn owns(self, bundle: u32) -> bool {
        bundle % self.count == self.index
    }
}

/// What the list holds and the memory it takes.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Memory {
    /// Lines in the list.
    pub lines: usize,
    /// Crossings with static geometry (stored once for all frames).
    pub static_hits: usize,
    /// Crossings with moving objects, summed over frames.
    pub moving_hits: usize,
    /// Bytes of all the arrays.
    pub bytes: usize,
}

impl Memory {
    /// Crossings stored: static ones once, moving ones once per frame.
    #[must_use]
    pub fn hits(&self) -> usize {
        self.static_hits + self.moving_hits
    }

    /// Bytes per stored crossing, offsets included.
    #[must_use]
    pub fn bytes_per_hit(&self) -> f64 {
        self.bytes as f64 / self.hits().max(1) as f64
    }
}

impl IntersectionList {
    /// Traces a first batch of lines through the whole timeline of `scene`.
    pub fn build(
        scene: &Scene,
        tracer: &SceneTracer,
        params: &LineParams,
        control: &Control,
    ) -> Result<Self, TraceError> {
        Self::build_shard(scene, tracer, params, Shard::WHOLE, control)
    }

    /// Whether the list's arrays agree with each other: as many lines as its batches count,
    /// each line's crossings within the arrays, in order, and frames within the timeline. What
    /// this build wrote always does; a list read from elsewhere is checked before it is used.
    fn is_whole(&self) -> bool {
        let lines: usize = (self.batches.iter())
            .flat_map(|b| &b.bundle_lines)
            .map(|&n| n as usize)
            .sum();
        let csr = |offsets: &[u32], len: usize| {
            offsets.len() == lines + 1
                && offsets.first() == Some(&0)
                && offsets.windows(2).all(|w| w[0] <= w[1])
                && offsets.last().is_some_and(|&last| last as usize == len)
        };
        csr(&self.static_offsets, self.static_hits.len())
            && csr(&self.dynamic_offsets, self.dynamic_hits.len())
            && (self.dynamic_hits.iter()).all(|h| (h.frame as usize) < self.frames)
    }

    /// Whether every crossing is of one of the first `triangles` traced triangles.
    #[must_use]
    pub fn crosses_only(&self, triangles: usize) -> bool {
        let within = |h: &Hit| (h.surface() as usize) < triangles;
        self.static_hits.iter().all(within) && self.dynamic_hits.iter().all(|h| within(&h.hit))
    }

    /// A list of no lines yet, of `frames` frames, its lines drawn against `bounds`.
    fn empty(frames: usize, bounds: Bounds) -> Self {
        Self {
            batches: Vec::new(),
            bundle_starts: Vec::new(),
            frames,
            static_offsets: vec![0],
            static_hits: Vec::new(),
            dynamic_offsets: vec![0],
            dynamic_hits: Vec::new(),
            dense: Vec::new(),
            factor: 1,
            weights: Vec::new(),
            bounds,
        }
    }

    /// [`IntersectionList::build`] for `shard`'s bundles only: the others are in the list
    /// without lines. [`IntersectionList::merge`] makes the whole list of the parts.
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled.
    pub fn build_shard(
        scene: &Scene,
        tracer: &SceneTracer,
        params: &LineParams,
        shard: Shard,
        control: &Control,
    ) -> Result<Self, TraceError> {
        let mut list = Self::empty(scene.frames.count, scene.bounds);
        let global = Batch::for_budget(params.lines, None, &scene.bounds, params.seed, 0);
        list.add_batches(&[global], shard, scene, tracer, control)?;
        list.weights = list.weights_of_lines();
        Ok(list)
    }

    /// The list of a whole batch of lines from the lists of its `parts`
    /// ([`IntersectionList::build_shard`] of one scene with the same lines, each part once, in
    /// any order): the same list, to the bit, as [`IntersectionList::build`] makes.
    ///
    /// # Errors
    /// What does not fit: parts of other lines or scenes, a part missing or given twice, a
    /// list that is not a part.
    pub fn merge(mut parts: Vec<(Shard, Self)>) -> Result<Self, String> {
        parts.sort_by_key(|(shard, _)| shard.index);
        let count = parts.len();
        for (k, (shard, _)) in parts.iter().enumerate() {
            if shard.count as usize != count || shard.index as usize != k {
                let have: Vec<String> = (parts.iter())
                    .map(|(s, _)| format!("{}/{}", s.index, s.count))
                    .collect();
                return Err(format!(
                    "the parts are not each part of one set once: {} (part K/N for every K \
                     from 0 to N - 1 is needed)",
                    have.join(", ")
                ));
            }
        }
        let Some((_, first)) = parts.first() else {
            return Err("no part to merge".into());
        };
        let Some(batch) = first.batches.first().filter(|_| first.batches.len() == 1) else {
            return Err("a part holds other than one batch of lines".into());
        };
        let (batch, frames, bounds) = (batch.batch, first.frames, first.bounds);
        let bundles = batch.bundles as usize;
        for (shard, part) in &parts {
            let fits = part.batches.len() == 1
                && part.batches[0].batch == batch
                && part.batches[0].bundle_lines.len() == bundles
                && part.bundle_starts.len() == bundles
                && part.frames == frames
                && part.bounds == bounds
                && part.dense.is_empty();
            if !fits {
                return Err(format!(
                    "part {}/{} is not of the lines or the scene of part 0/{count}",
                    shard.index, shard.count
                ));
            }
            let foreign = (0..batch.bundles)
                .any(|b| !shard.owns(b) && part.batches[0].bundle_lines[b as usize] != 0);
            if foreign {
                return Err(format!(
                    "part {}/{} holds lines of other parts",
                    shard.index, shard.count
                ));
            }
            if !part.is_whole() {
                return Err(format!(
                    "part {}/{} is damaged: its lines and crossings do not agree",
                    shard.index, shard.count
                ));
            }
        }
        let mut list = Self::empty(frames, bounds);
        let mut next = vec![0usize; count];
        let mut bundle_lines = Vec::with_capacity(bundles);
        let too_many = |_| "the parts hold more crossings than a list can".to_string();
        for b in 0..bundles {
            let (owner, part) = (b % count, &parts[b % count].1);
            let lines = part.batches[0].bundle_lines[b] as usize;
            list.bundle_starts
                .push((list.lines() as u32, part.bundle_starts[b].1));
            for l in next[owner]..next[owner] + lines {
                let statics = &part.static_hits
                    [part.static_offsets[l] as usize..part.static_offsets[l + 1] as usize];
                let moving = &part.dynamic_hits
                    [part.dynamic_offsets[l] as usize..part.dynamic_offsets[l + 1] as usize];
                append_csr(&mut list.static_offsets, &[statics.len() as u32]).map_err(too_many)?;
                append_csr(&mut list.dynamic_offsets, &[moving.len() as u32]).map_err(too_many)?;
                list.static_hits.extend_from_slice(statics);
                list.dynamic_hits.extend_from_slice(moving);
            }
            next[owner] += lines;
            bundle_lines.push(lines as u32);
        }
        list.batches.push(BatchLines {
            batch,
            bundle_lines,
        });
        list.weights = list.weights_of_lines();
        Ok(list)
    }

    /// Traces another batch of lines (progressive refinement): the lines already traced are
    /// kept as they are. Batch `i` of a list uses the seed's `i`-th independent rotation. With
    /// dense regions ([`IntersectionList::add_dense`]), each region gets its batch of denser
    /// lines beside the new one, so that every region stays as many times denser.
    pub fn add_lines(
        &mut self,
        scene: &Scene,
        tracer: &SceneTracer,
        params: &LineParams,
        control: &Control,
    ) -> Result<(), TraceError> {
        let index = self.batches.len() as u32;
        let global = Batch::for_budget(params.lines, None, &scene.bounds, params.seed, index);
        let mut batches = vec![global];
        for (number, &region) in self.dense.iter().enumerate() {
            let index = index + batches.len() as u32;
            let region = (number as u32, region);
            batches.push(Batch::dense(
                &global,
                region,
                self.factor,
                &scene.bounds,
                index,
            ));
        }
        self.add_batches(&batches, Shard::WHOLE, scene, tracer, control)?;
        self.weights = self.weights_of_lines();
        Ok(())
    }

    /// Makes the lines that meet `regions` (boxes in normalised space) `factor` times as dense
    /// as the rest: a batch of lines among those that meet each region, `factor` times as dense
    /// as each batch of global lines, is traced and added. The line space is then cut in parts,
    /// each estimated by one set of lines at one density ([`IntersectionList::line_weights`]):
    /// the lines that meet no region by the global lines, those whose first region is `b` by
    /// region b's lines. Regions can be made dense once (the list's first call).
    ///
    /// # Errors
    /// [`TraceError::Cancelled`] if `control` is cancelled: the list is then as it was.
    pub fn add_dense(
        &mut self,
        scene: &Scene,
        tracer: &SceneTracer,
        (regions, factor): (&[Bounds], u32),
        control: &Control,
    ) -> Result<(), TraceError> {
        assert!(
            self.dense.is_empty(),
            "the list's regions are already dense"
        );
        assert!(
            factor >= 2 && factor <= u32::from(u8::MAX),
            "a dense factor of {factor}"
        );
        let globals: Vec<Batch> = self.batches.iter().map(|b| b.batch).collect();
        let mut index = globals.len() as u32;
        let mut batches = Vec::new();
        for global in &globals {
            for (number, &region) in regions.iter().enumerate() {
                let region = (number as u32, region);
                batches.push(Batch::dense(global, region, factor, &scene.bounds, index));
                index += 1;
            }
        }
        self.add_batches(&batches, Shard::WHOLE, scene, tracer, control)?;
        (self.dense, self.factor) = (regions.to_vec(), factor);
        self.weights = self.weights_of_lines();
        Ok(())
    }

    /// The regions made dense, and how many times denser ([`IntersectionList::add_dense`]).
    #[must_use]
    pub fn dense(&self) -> (&[Bounds], u32) {
        (&self.dense, self.factor)
    }

    /// How many of the lines are the dense regions' ([`IntersectionList::add_dense`]).
    #[must_use]
    pub fn dense_lines(&self) -> usize {
        (self.batches.iter())
            .filter(|b| b.batch.region.is_some())
            .map(|b| b.bundle_lines.iter().map(|&n| n as usize).sum::<usize>())
            .sum()
    }

    /// The weight of every line in the tallies, in units of a region's line: with no dense
    /// regions, 1 for every line; with them, a global line that meets no region weighs the
    /// factor and one that meets a region 0 (its part of the line space is estimated by the
    /// region's lines), and a region's line weighs 1 if that region is the first (by number)
    /// it meets, else 0. Each part of the line space is so counted once, at one density, and
    /// every segment in both directions with its line's weight: `S` stays symmetric and its
    /// expectation is that of global lines alone, times the factor.
    #[must_use]
    pub fn line_weights(&self) -> &[u8] {
        &self.weights
    }

    /// [`IntersectionList::line_weights`] worked out from the batches and regions.
    fn weights_of_lines(&self) -> Vec<u8> {
        if self.dense.is_empty() {
            return vec![1; self.lines()];
        }
        let factor = self.factor as u8;
        let first_met = |origin: glam::Vec3, w: glam::DVec3| {
            let point = origin.as_dvec3() + w * f64::from(crate::lines::ORIGIN_OFFSET);
            (self.dense.iter()).position(|r| crate::lines::meets_box(point, w, r))
        };
        let ranges = self.bundle_ranges();
        let per_bundle: Vec<Vec<u8>> = ranges
            .par_iter()
            .map(|&(b, k, _, n)| {
                let batch = &self.batches[b].batch;
                let bundle = batch.bundle(k, &self.bounds);
                debug_assert_eq!(bundle.origins.len(), n);
                let w = bundle.direction.as_dvec3();
                (bundle.origins.iter())
                    .map(|&o| match (batch.region, first_met(o, w)) {
                        (None, None) => factor,
                        (None, Some(_)) => 0,
                        (Some((number, _)), met) => {
                            u8::from(met.is_none_or(|m| m == number as usize))
                        }
                    })
                    .collect()
            })
            .collect();
        per_bundle.concat()
    }

    /// Traces `batches` through the whole timeline and appends them, all or none.
    fn add_batches(
        &mut self,
        batches: &[Batch],
        shard: Shard,
        scene: &Scene,
        tracer: &SceneTracer,
        control: &Control,
    ) -> Result<(), TraceError> {
        let mut traced = Vec::with_capacity(batches.len());
        for batch in batches {
            traced.push(self.trace_batch(batch, shard, scene, tracer, control)?);
        }
        // Nothing is appended to the list until everything is traced: a cancelled or failed
        // batch leaves the list as it was.
        let kept = (
            self.static_offsets.len(),
            self.dynamic_offsets.len(),
            self.bundle_starts.len(),
            self.batches.len(),
        );
        for (batch, (bundles, statics, moving)) in batches.iter().zip(traced) {
            if let Err(e) = self.append(&bundles, &statics, moving) {
                let (s, d, starts, count) = kept;
                self.static_offsets.truncate(s);
                self.dynamic_offsets.truncate(d);
                self.static_hits
                    .truncate(*self.static_offsets.last().unwrap_or(&0) as usize);
                self.dynamic_hits
                    .truncate(*self.dynamic_offsets.last().unwrap_or(&0) as usize);
                self.bundle_starts.truncate(starts);
                self.batches.truncate(count);
                return Err(e);
            }
            let mut start = self.lines() as u32;
            for b in bundles.iter().rev() {
                start -= b.len() as u32;
                self.bundle_starts.push((start, b.direction()));
            }
            let added = self.bundle_starts.len() - bundles.len();
            self.bundle_starts[added..].reverse();
            self.batches.push(BatchLines {
                batch: *batch,
                bundle_lines: bundles.iter().map(|b| b.len() as u32).collect(),
            });
        }
        Ok(())
    }

    /// Traces one batch through the whole timeline: its bundles (ready for tracing), each
    /// bundle's lines' counts and static crossings, and its moving crossings per bundle (line
    /// within the bundle, crossing) in no particular order.
    #[allow(clippy::type_complexity)]
    fn trace_batch(
        &self,
        batch: &Batch,
        shard: Shard,
        scene: &Scene,
        tracer: &SceneTracer,
        control: &Control,
    ) -> Result<
        (
            Vec<ParallelLines>,
            Vec<(Vec<u32>, Vec<Hit>)>,
            Vec<Vec<(u32, FrameHit)>>,
        ),
        TraceError,
    > {
        let bundles: Vec<ParallelLines> = (0..batch.bundles)
            .into_par_iter()
            .map(|k| {
                let Bundle { direction, origins } = if control.is_cancelled() {
                    Bundle {
                        direction: glam::Vec3::Z,
                        origins: Vec::new(),
                    }
                } else {
                    batch.bundle(k, &scene.bounds)
                };
                // Another part's bundle: in the list, without lines.
                let origins = if shard.owns(k) { origins } else { Vec::new() };
                ParallelLines::new(direction, origins)
            })
            .collect();
        control.check()?;
        let lines: u64 = bundles.iter().map(|b| b.len() as u64).sum();
        let frames = self.frames as u64;
        let rigid = tracer.moves_rigidly();
        let deforms = (scene.objects.iter()).any(|o| matches!(o.motion, Motion::Deforming(_)));
        control.add_work(lines * (1 + frames * (u64::from(rigid) + u64::from(deforms))));

        let traced: Vec<(Vec<u32>, Vec<Hit>)> = bundles
            .par_iter()
            .map_init(
                || (Scratch::default(), Vec::new()),
                |(scratch, found), lines| {
                    if control.is_cancelled() {
                        return (Vec::new(), Vec::new());
                    }
                    control.advance(lines.len() as u64);
                    found.clear();
                    tracer.trace_static_parallel(lines, scratch, found);
                    let starts = sort_by_line(found, lines.len(), scratch);
                    let counts = starts.windows(2).map(|w| w[1] - w[0]).collect();
                    let hits = found.iter().map(|&(_, hit)| hit).collect();
                    (counts, hits)
                },
            )
            .collect();
        control.check()?;

        // Moving objects: the rigid ones every frame at once, a bundle at a time; the deforming
        // ones frame by frame (a frame's meshes are built once for all bundles). Per bundle,
        // (line within bundle, crossing).
        let mut moving: Vec<Vec<(u32, FrameHit)>> = if rigid {
            bundles
                .par_iter()
                .map_init(
                    || (Scratch::default(), Vec::new()),
                    |(scratch, found), lines| {
                        found.clear();
                        // A few frames at a time, between which a cancel is seen.
                        for start in (0..self.frames).step_by(RIGID_FRAMES) {
                            if control.is_cancelled() {
                                return Vec::new();
                            }
                            let end = (start + RIGID_FRAMES).min(self.frames);
                            tracer.trace_rigid_frames(lines, start..end, scratch, found);
                            control.advance((lines.len() * (end - start)) as u64);
                        }
                        (found.iter())
                            .map(|&(line, frame, hit)| (line, FrameHit { frame, hit }))
                            .collect()
                    },
                )
                .collect()
        } else {
            vec![Vec::new(); bundles.len()]
        };
        control.check()?;
        if deforms {
            for frame in 0..self.frames {
                let deformed = tracer.deformed_at(scene, frame);
                control.check()?;
                let frame = frame as u32;
                (moving.par_iter_mut().zip(&bundles)).for_each_init(
                    || (Scratch::default(), Vec::new()),
                    |(scratch, found), (all, lines)| {
                        if control.is_cancelled() {
                            return;
                        }
                        control.advance(lines.len() as u64);
                        found.clear();
                        tracer.trace_deformed_parallel(lines, &deformed, scratch, found);
                        all.extend(
                            found
                                .iter()
                                .map(|&(line, hit)| (line, FrameHit { frame, hit })),
                        );
                    },
                );
            }
        }
        control.check()?;
        Ok((bundles, traced, moving))
    }

    /// Appends a traced batch: static crossings per bundle, moving ones grouped by line.
    fn append(
        &mut self,
        bundles: &[ParallelLines],
        traced: &[(Vec<u32>, Vec<Hit>)],
        moving: Vec<Vec<(u32, FrameHit)>>,
    ) -> Result<(), TraceError> {
        for (counts, _) in traced {
            append_csr(&mut self.static_offsets, counts)?;
        }
        // Each bundle's crossings copied to their place, bundles side by side.
        let blocks = traced.iter().map(|(_, hits)| (hits.len(), hits)).collect();
        let blank = Hit::new(0.0, 0, true);
        fill_blocks(&mut self.static_hits, blank, blocks, |block, hits| {
            block.copy_from_slice(hits);
        });
        // Moving crossings grouped by line with a counting sort per bundle, then each line's
        // (a few) put in frame order, and along the line within a frame.
        let mut counts: Vec<Vec<u32>> = bundles.iter().map(|b| vec![0; b.len()]).collect();
        let blocks = (moving.iter().zip(counts.iter_mut()))
            .map(|(hits, counts)| (hits.len(), (hits, counts)))
            .collect();
        let blank = FrameHit {
            frame: 0,
            hit: Hit::new(0.0, 0, true),
        };
        fill_blocks(
            &mut self.dynamic_hits,
            blank,
            blocks,
            |block, (hits, counts)| {
                hits.iter()
                    .for_each(|&(line, _)| counts[line as usize] += 1);
                let mut next: Vec<usize> = (counts.iter())
                    .scan(0, |at, &c| {
                        let start = *at;
                        *at += c as usize;
                        Some(start)
                    })
                    .collect();
                for &(line, hit) in hits {
                    block[next[line as usize]] = hit;
                    next[line as usize] += 1;
                }
                // `next` now holds where each line's crossings end.
                let mut start = 0;
                for &end in &next {
                    block[start..end].sort_unstable_by_key(|h| (h.frame, h.hit.key()));
                    start = end;
                }
            },
        );
        for counts in &counts {
            append_csr(&mut self.dynamic_offsets, counts)?;
        }
        Ok(())
    }

    /// Number of lines.
    #[must_use]
    pub fn lines(&self) -> usize {
        self.static_offsets.len() - 1
    }

    /// The direction of `line` (unit).
    #[must_use]
    pub fn direction(&self, line: usize) -> glam::Vec3 {
        let k = self
            .bundle_starts
            .partition_point(|&(start, _)| start as usize <= line);
        self.bundle_starts[k.saturating_sub(1)].1
    }

    /// The directions of lines asked for in increasing order ([`Directions::of`]): a cursor
    /// over the bundles, where [`IntersectionList::direction`] searches them for every line.
    #[must_use]
    pub fn directions(&self) -> Directions<'_> {
        Directions {
            starts: &self.bundle_starts,
            at: 0,
        }
    }

    /// Hints that `line`'s place in the list will be read soon (its crossings' offsets): the
    /// lines a frame's moving objects touch are scattered over the list, each a cache miss.
    pub(crate) fn prefetch_offsets(&self, line: usize) {
        crate::prefetch(&self.static_offsets[line], 2 * size_of::<u32>());
        crate::prefetch(&self.dynamic_offsets[line], 2 * size_of::<u32>());
    }

    /// Hints that [`IntersectionList::frame_hits_from`] will soon read `line` from `start`.
    pub(crate) fn prefetch_hits(&self, line: usize, start: usize) {
        let (s, d) = (self.static_offsets[line], self.dynamic_offsets[line]);
        let statics = self.static_offsets[line + 1] - s;
        if let Some(h) = self.static_hits.get(s as usize) {
            crate::prefetch(h, statics as usize * size_of::<Hit>());
        }
        if let Some(h) = self.dynamic_hits.get(d as usize + start) {
            crate::prefetch(h, 2 * size_of::<FrameHit>());
        }
    }

    /// Number of frames of the timeline.
    #[must_use]
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The batches of lines, in the order their lines are numbered.
    #[must_use]
    pub fn batches(&self) -> Vec<Batch> {
        self.batches.iter().map(|b| b.batch).collect()
    }

    /// The group of every line: its bundle's index modulo `groups`. Every group is a stratified
    /// set of directions of its own (every `groups`-th point of each batch's lattice).
    #[must_use]
    pub fn line_groups(&self, groups: u32) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.lines());
        for b in &self.batches {
            for (k, &n) in b.bundle_lines.iter().enumerate() {
                out.extend(std::iter::repeat_n((k as u32 % groups) as u8, n as usize));
            }
        }
        out
    }

    /// The static crossings of `line`, sorted along it.
    #[must_use]
    pub fn static_hits(&self, line: usize) -> &[Hit] {
        &self.static_hits
            [self.static_offsets[line] as usize..self.static_offsets[line + 1] as usize]
    }

    /// The moving crossings of `line` at every frame, sorted by frame then along the line.
    #[must_use]
    pub fn moving_hits(&self, line: usize) -> &[FrameHit] {
        &self.dynamic_hits
            [self.dynamic_offsets[line] as usize..self.dynamic_offsets[line + 1] as usize]
    }

    /// The crossings of `line` at `frame`, sorted along the line, into `out` (cleared first):
    /// the static crossings merged with the moving ones tagged `frame`.
    pub fn frame_hits(&self, line: usize, frame: usize, out: &mut Vec<Hit>) {
        let moving = self.moving_hits(line);
        // Frame 0's crossings (the split's, the gaps') come first: no search.
        let start = match moving.first() {
            Some(h) if h.frame >= frame as u32 => 0,
            _ => moving.partition_point(|h| h.frame < frame as u32),
        };
        self.frame_hits_from(line, frame, start, out);
    }

    /// [`IntersectionList::frame_hits`] where the line's moving crossings at `frame` are known
    /// to start at `start` (an index into [`IntersectionList::moving_hits`]; the crossings of
    /// the frame follow it), without searching for them.
    pub fn frame_hits_from(&self, line: usize, frame: usize, start: usize, out: &mut Vec<Hit>) {
        out.clear();
        let statics = self.static_hits(line);
        let moving = &self.moving_hits(line)[start..];
        let frame = frame as u32;
        // A frame's crossings of one line are few: a scan, where a binary search over the
        // later frames' missed the cache at every step.
        let end = moving
            .iter()
            .position(|h| h.frame != frame)
            .unwrap_or(moving.len());
        let moving = &moving[..end];
        let (mut i, mut j) = (0, 0);
        while i < statics.len() && j < moving.len() {
            if Hit::order(&statics[i], &moving[j].hit).is_le() {
                out.push(statics[i]);
                i += 1;
            } else {
                out.push(moving[j].hit);
                j += 1;
            }
        }
        out.extend_from_slice(&statics[i..]);
        out.extend(moving[j..].iter().map(|h| h.hit));
    }

    /// The lines of the list, regenerated from their batches (they are not stored), in line
    /// order.
    pub fn regenerate_lines<'a>(&'a self, scene: &'a Scene) -> impl Iterator<Item = Line> + 'a {
        self.batches.iter().flat_map(move |b| {
            (0..b.batch.bundles).flat_map(move |k| {
                let bundle = b.batch.bundle(k, &scene.bounds);
                debug_assert_eq!(bundle.origins.len(), b.bundle_lines[k as usize] as usize);
                lines_of(&bundle).collect::<Vec<_>>()
            })
        })
    }

    /// Every bundle of the list regenerated, with the index of its first line, on every core.
    pub fn bundles<'a>(
        &'a self,
        scene: &'a Scene,
    ) -> impl ParallelIterator<Item = (usize, Bundle)> + 'a {
        self.bundle_ranges()
            .into_par_iter()
            .map(move |(b, k, first, _)| (first, self.batches[b].batch.bundle(k, &scene.bounds)))
    }

    /// [`IntersectionList::bundles`], borrowed from `kept` if given (the bundles
    /// [`IntersectionList::regenerate_bundles`] made, in line order).
    pub fn bundles_kept<'a>(
        &'a self,
        scene: &'a Scene,
        kept: Option<&'a [Bundle]>,
    ) -> impl ParallelIterator<Item = (usize, std::borrow::Cow<'a, Bundle>)> + 'a {
        let ranges = self.bundle_ranges();
        debug_assert!(kept.is_none_or(|k| k.len() == ranges.len()));
        (ranges.into_par_iter().enumerate()).map(move |(index, (b, k, first, _))| {
            (
                first,
                bundle_kept(&self.batches, (scene, kept), index, (b, k)),
            )
        })
    }

    /// (batch, bundle, first line, lines) of every bundle, in line order.
    fn bundle_ranges(&self) -> Vec<(usize, u32, usize, usize)> {
        let mut out = Vec::with_capacity(self.bundle_starts.len());
        let mut first = 0;
        for (b, batch) in self.batches.iter().enumerate() {
            for (k, &n) in batch.bundle_lines.iter().enumerate() {
                out.push((b, k as u32, first, n as usize));
                first += n as usize;
            }
        }
        out
    }

    /// Every bundle of the list's lines regenerated, in the list's order, to relabel it several
    /// times without generating them each time ([`IntersectionList::relabel`]): 12 bytes a
    /// line.
    #[must_use]
    pub fn regenerate_bundles(&self, scene: &Scene) -> Vec<Bundle> {
        (self.bundle_ranges().par_iter())
            .map(|&(b, k, _, _)| self.batches[b].batch.bundle(k, &scene.bounds))
            .collect()
    }

    /// Gives every crossing of `which` the traced triangle `surface(hit, frame, point)` (the
    /// frame of a moving crossing, `None` for a static one; the point crossed, in normalised
    /// space), then sorts each line's crossings again where that changed their order: the list
    /// of the same lines through a scene whose triangles were cut ([`crate::scene::refine`]),
    /// without tracing them again.
    pub fn relabel(
        &mut self,
        (scene, bundles): (&Scene, Option<&[Bundle]>),
        which: Crossings,
        surface: impl Fn(Hit, Option<usize>, glam::DVec3) -> u32 + Sync,
    ) {
        // Each bundle's crossings, split off the two arrays so bundles are relabelled apart.
        let ranges = self.bundle_ranges();
        let mut tasks = Vec::with_capacity(ranges.len());
        let (mut statics, mut moving) = (&mut self.static_hits[..], &mut self.dynamic_hits[..]);
        for (index, (b, k, first, n)) in ranges.into_iter().enumerate() {
            let s = (self.static_offsets[first + n] - self.static_offsets[first]) as usize;
            let d = (self.dynamic_offsets[first + n] - self.dynamic_offsets[first]) as usize;
            let (s_here, s_rest) = std::mem::take(&mut statics).split_at_mut(s);
            let (d_here, d_rest) = std::mem::take(&mut moving).split_at_mut(d);
            (statics, moving) = (s_rest, d_rest);
            tasks.push((index, (b, k, first, n), s_here, d_here));
        }
        let (batches, static_offsets, dynamic_offsets) =
            (&self.batches, &self.static_offsets, &self.dynamic_offsets);
        let moving_order =
            |a: &FrameHit, b: &FrameHit| a.frame.cmp(&b.frame).then(Hit::order(&a.hit, &b.hit));
        tasks
            .into_par_iter()
            .for_each(|(index, (b, k, first, n), s_hits, d_hits)| {
                let bundle = bundle_kept(batches, (scene, bundles), index, (b, k));
                debug_assert_eq!(bundle.origins.len(), n);
                let point = |line: &Line, t: f32| {
                    line.origin.as_dvec3() + line.direction.as_dvec3() * f64::from(t)
                };
                let (s0, d0) = (static_offsets[first], dynamic_offsets[first]);
                for (i, line) in lines_of(&bundle).enumerate() {
                    let l = first + i;
                    let range = |offsets: &[u32], base: u32| {
                        (offsets[l] - base) as usize..(offsets[l + 1] - base) as usize
                    };
                    if which != Crossings::Later {
                        let hits = &mut s_hits[range(static_offsets, s0)];
                        for h in hits.iter_mut() {
                            *h = Hit::new(h.t, surface(*h, None, point(&line, h.t)), h.front());
                        }
                        if !hits.is_sorted_by(|a, b| Hit::order(a, b).is_le()) {
                            hits.sort_unstable_by(Hit::order);
                        }
                    }
                    let hits = &mut d_hits[range(dynamic_offsets, d0)];
                    // A line's moving crossings are in frame order: frame 0's first.
                    let zero = hits.partition_point(|h| h.frame == 0);
                    let hits = match which {
                        Crossings::All => hits,
                        Crossings::AtFrameZero => &mut hits[..zero],
                        Crossings::Later => &mut hits[zero..],
                    };
                    for h in hits.iter_mut() {
                        let at = point(&line, h.hit.t);
                        let new = surface(h.hit, Some(h.frame as usize), at);
                        h.hit = Hit::new(h.hit.t, new, h.hit.front());
                    }
                    if !hits.is_sorted_by(|a, b| moving_order(a, b).is_le()) {
                        hits.sort_unstable_by(moving_order);
                    }
                }
            });
    }

    /// What the list holds and its size in bytes.
    #[must_use]
    pub fn memory(&self) -> Memory {
        use std::mem::size_of;
        Memory {
            lines: self.lines(),
            static_hits: self.static_hits.len(),
            moving_hits: self.dynamic_hits.len(),
            bytes: (self.static_offsets.len() + self.dynamic_offsets.len()) * size_of::<u32>()
                + self.static_hits.len() * size_of::<Hit>()
                + self.dynamic_hits.len() * size_of::<FrameHit>()
                + self.weights.len(),
        }
    }
}

/// Bundle `k` of batch `b` of `batches`, the `index`-th in line order: borrowed from `kept` if
/// given, generated in `scene`'s bounds otherwise.
fn bundle_kept<'a>(
    batches: &[BatchLines],
    (scene, kept): (&Scene, Option<&'a [Bundle]>),
    index: usize,
    (b, k): (usize, u32),
) -> std::borrow::Cow<'a, Bundle> {
    match kept {
        Some(kept) => std::borrow::Cow::Borrowed(&kept[index]),
        None => std::borrow::Cow::Owned(batches[b].batch.bundle(k, &scene.bounds)),
    }
}

/// The lines of a bundle.
fn lines_of(bundle: &Bundle) -> impl Iterator<Item = Line> + '_ {
    bundle.origins.iter().map(|&origin| Line {
        origin,
        direction: bundle.direction,
    })
}

/// How many frames of the rigid movers are traced at once for a bundle
/// ([`SceneTracer::trace_rigid_frames`]): enough for the frames of an object that slides to
/// share the walks, few enough that a cancel is seen soon.
const RIGID_FRAMES: usize = 64;

/// Appends to `items` a block of each length of `sources`, and fills each block from its
/// source with `fill`, blocks in parallel; `blank` holds the places until then.
fn fill_blocks<T: Copy + Send, S: Send>(
    items: &mut Vec<T>,
    blank: T,
    sources: Vec<(usize, S)>,
    fill: impl Fn(&mut [T], S) + Sync,
) {
    let added = sources.iter().map(|&(len, _)| len).sum();
    let start = items.len();
    reserve_in_huge_pages(items, added);
    items.resize(start + added, blank);
    let mut rest = &mut items[start..];
    let mut blocks = Vec::with_capacity(sources.len());
    for (len, source) in sources {
        let (block, tail) = rest.split_at_mut(len);
        blocks.push((block, source));
        rest = tail;
    }
    blocks
        .into_par_iter()
        .for_each(|(block, source)| fill(block, source));
}

/// Appends one offset per count to a CSR offset array.
fn append_csr(offsets: &mut Vec<u32>, counts: &[u32]) -> Result<(), TraceError> {
    let mut last = *offsets.last().unwrap_or(&0);
    for &c in counts {
        last = last.checked_add(c).ok_or(TraceError::TooManyHits)?;
        offsets.push(last);
    }
    Ok(())
}

/// The directions of lines in increasing order ([`IntersectionList::directions`]).
pub struct Directions<'a> {
    starts: &'a [(u32, glam::Vec3)],
    at: usize,
}

impl Directions<'_> {
    /// The direction of `line` (unit), no earlier a line than the last one asked for.
    pub fn of(&mut self, line: usize) -> glam::Vec3 {
        let next = |at: usize| {
            self.starts
                .get(at + 1)
                .is_some_and(|&(s, _)| s as usize <= line)
        };
        // A few bundles on, a step at a time; further, a search of what is left.
        let mut steps = 0;
        while next(self.at) {
            self.at += 1;
            steps += 1;
            if steps == 8 {
                self.at += self.starts[self.at..].partition_point(|&(s, _)| s as usize <= line) - 1;
                break;
            }
        }
        debug_assert!(
            self.starts[self.at].0 as usize <= line,
            "lines asked out of order"
        );
        self.starts[self.at].1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The parts of 3,000 lines through the Cornell box in `count` parts.
    fn parts(count: u32) -> (Scene, Vec<(Shard, IntersectionList)>) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell_box.gltf");
        let options = crate::loader::LoadOptions::default();
        let scene = crate::loader::load(&std::fs::read(path).unwrap(), &options).unwrap();
        let tracer = SceneTracer::new(&scene);
        let params = LineParams {
            lines: 3_000,
            seed: 2,
        };
        let parts = (0..count)
            .map(|index| {
                let shard = Shard { index, count };
                let control = Control::default();
                let list = IntersectionList::build_shard(&scene, &tracer, &params, shard, &control);
                (shard, list.unwrap())
            })
            .collect();
        (scene, parts)
    }

    #[test]
    fn the_directions_cursor_reads_each_line_s_bundle() {
        let (_, parts) = parts(1);
        let list = &parts[0].1;
        assert!(list.bundle_starts.len() > 20, "lines in many bundles");
        // Every line in order, and lines far apart (past the cursor's steps, into a search).
        for stride in [1, 3, 97, 1_001] {
            let mut directions = list.directions();
            for l in (0..list.lines()).step_by(stride) {
                assert_eq!(
                    directions.of(l),
                    list.direction(l),
                    "line {l}, stride {stride}"
                );
            }
        }
        // The first line of a bundle whose direction is not the one before's, at least ten
        // bundles on from the last line asked: past the cursor's steps, into its search.
        let starts = &list.bundle_starts;
        let mut directions = list.directions();
        let (mut asked, mut last) = (0, 0);
        for k in 1..starts.len() {
            if starts[k].1 != starts[k - 1].1 && k >= last + 10 {
                let l = starts[k].0 as usize;
                assert_eq!(directions.of(l), list.direction(l), "line {l}");
                (asked, last) = (asked + 1, k);
            }
        }
        assert!(asked > 0, "no turn ten bundles apart to ask at");
    }

    #[test]
    fn a_part_whose_arrays_disagree_is_refused_not_read_out_of_bounds() {
        let (_, whole) = parts(2);
        assert!(IntersectionList::merge(whole.clone()).is_ok());
        let damages: [fn(&mut IntersectionList); 4] = [
            |l| {
                l.static_offsets.pop();
            },
            |l| {
                let hit = Hit::new(0.0, 0, true);
                l.dynamic_hits.push(FrameHit { frame: 0, hit });
            },
            |l| *l.static_offsets.last_mut().unwrap() += 1,
            |l| {
                if let Some(h) = l.dynamic_hits.first_mut() {
                    h.frame = 99;
                } else {
                    l.static_offsets[1] = u32::MAX;
                }
            },
        ];
        for (k, damage) in damages.iter().enumerate() {
            let mut parts = whole.clone();
            damage(&mut parts[1].1);
            let error = IntersectionList::merge(parts).err().unwrap_or_default();
            assert!(
                error.contains("part 1/2 is damaged"),
                "damage {k}: {error:?}"
            );
        }
    }

    #[test]
    fn a_list_crossing_triangles_the_scene_lacks_is_told() {
        let (scene, parts) = parts(1);
        let list = IntersectionList::merge(parts).unwrap();
        let most = list.static_hits.iter().map(|h| h.surface()).max().unwrap() as usize;
        assert!(most < SceneTracer::new(&scene).faces().len());
        assert!(list.crosses_only(most + 1));
        assert!(!list.crosses_only(most));
    }
}
