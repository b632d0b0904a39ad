//! Tallies of the intersection list (METHOD.md §3, §5): per patch, the crossings `N_i`, and per
//! pair of patches the segments `S_ij` that leave i's face and enter j's.
//!
//! Every segment between two consecutive crossings is used in both directions, and the segments
//! before the first and after the last crossing of a line see the sky. A segment that arrives at
//! the back of a one-sided triangle is absorbed there. `N_i` is the row sum of `S` (sky and
//! absorbed columns included), so the two can never disagree, except for the crossings where a
//! surface touches the patch (a box standing on a floor, [`HIDDEN`]): they are counted apart,
//! and `N_i` counts the crossings of the patch's visible part only, so that a patch partly
//! under a box answers the radiance of what can be seen of it, and sends that on.
//!
//! Where the list's lines are denser in some regions ([`IntersectionList::add_dense`]), every
//! segment counts its line's weight ([`IntersectionList::line_weights`]) rather than one, so
//! that each part of the line space counts at one density; [`FrameTally::unit`] is then what
//! a global line's segment counts.
//!
//! The static segments are tallied once. A frame stores only what its moving objects change:
//! for each line that crosses a moving object at frame f, its static segments are removed and
//! the segments of its frame-f list added (`S^f = S^static − R^f + D^f`). Memory grows with the
//! lines the moving objects touch, not with frames × scene.

use std::collections::HashMap;
use std::ops::Range;
use std::sync::Arc;

use rayon::prelude::*;

use crate::timeline::IntersectionList;
use crate::trace::coincident::{is_contact, resolve};
use crate::trace::{Hit, Surfaces};

/// Column of the segments that leave the scene.
pub const SKY: u32 = (1 << 27) - 1;
/// Column of the segments that carry no light: absorbed by the back of a one-sided triangle.
pub const ABSORBED: u32 = (1 << 27) - 2;
/// Column of the zero-length segments across a contact (two faces touching,
/// [`crate::trace::coincident`]): the crossing lies on a part of the patch that a surface
/// covers, which no light reaches and no one sees. Not counted in `N_i`
/// ([`FrameTally::crossings`]) but in [`FrameTally::hidden`].
pub const HIDDEN: u32 = (1 << 27) - 3;

/// The luminance a segment brings from its far end, in fixed point: a whole number of 2^-31 of
/// the brightest (the sky included), so that sums of them do not depend on the order threads
/// add them in (what is decided from them, cuts and so patch ids, is the same on any machine).
pub struct FixedLight<F> {
    /// Luminance of patch `j`.
    patch: F,
    sky: f64,
    /// The luminance of one unit.
    pub unit: f64,
}

impl<F: Fn(u32) -> f64> FixedLight<F> {
    /// For `patches` patches of luminance `patch(j)` under a sky of luminance `sky`.
    pub fn new(patch: F, patches: usize, sky: f64) -> Self {
        let brightest = (0..patches as u32)
            .map(&patch)
            .fold(sky, f64::max)
            .max(f64::MIN_POSITIVE);
        Self {
            patch,
            sky,
            unit: brightest / f64::from(1u32 << 31),
        }
    }

    /// What a segment to `to` (a patch, [`SKY`] or [`ABSORBED`]) brings, in units.
    pub fn value(&self, to: u32) -> u64 {
        let g = match to {
            SKY => self.sky,
            ABSORBED | HIDDEN => 0.0,
            j => (self.patch)(j),
        };
        (g / self.unit).round().max(0.0) as u64
    }
}
/// Patches are numbered below this (the columns have 27 bits in a key).
pub const MAX_PATCHES: usize = HIDDEN as usize;
/// Lines fall into this many groups, the independent replicas of the line set
/// ([`crate::lines::REPLICAS`]): the spread of the estimates between them measures the error
/// honestly, stratification included (METHOD.md §6).
pub const GROUPS: u32 = crate::lines::REPLICAS;

/// Sorted (row, column, group) keys with counts.
type Entries = Vec<(u64, i64)>;

fn key(row: u32, column: u32, group: u8) -> u64 {
    debug_assert!(column <= SKY && u32::from(group) < GROUPS);
    (u64::from(row) << 32) | (u64::from(column) << 4) | u64::from(group)
}

/// The row, column and group of a key.
#[must_use]
pub fn unkey(k: u64) -> (u32, u32, u8) {
    ((k >> 32) as u32, ((k >> 4) as u32) & SKY, (k & 15) as u8)
}

/// Calls `visit(from, to)` for every segment of a line in both directions, `from` being a patch
/// and `to` a patch, [`SKY`], [`ABSORBED`] or [`HIDDEN`]. Coincident crossings are resolved
/// first ([`resolve`]); the segment across a contact is [`HIDDEN`] both ways.
fn walk(hits: &[Hit], surfaces: &Surfaces<'_>, mut visit: impl FnMut(u32, u32)) {
    walk_from(hits, surfaces, |from, to, _, _| visit(from, to));
}

/// `walk`, also giving the crossing the segment leaves `from` at and the segment's length
/// (infinite to the sky, 0 across a contact).
pub fn walk_from(hits: &[Hit], surfaces: &Surfaces<'_>, mut visit: impl FnMut(u32, u32, Hit, f32)) {
    let faces = surfaces.faces;
    let reordered = resolve(hits, surfaces);
    let hits = reordered.as_deref().unwrap_or(hits);
    let Some(first) = hits.first() else { return };
    // The face the line arrives at, and the face it leaves from, at a crossing.
    let entry = |h: &Hit| {
        let f = faces[h.surface() as usize];
        if h.front() { Some(f.front) } else { f.back }
    };
    let exit = |h: &Hit| {
        let f = faces[h.surface() as usize];
        if h.front() { f.back } else { Some(f.front) }
    };
    if let Some(a) = entry(first) {
        visit(a, SKY, *first, f32::INFINITY);
    }
    for w in hits.windows(2) {
        // `a` faces the segment from one end, `b` from the other; a missing face absorbs.
        let (a, b) = (exit(&w[0]), entry(&w[1]));
        if is_contact(&w[0], &w[1]) {
            if let Some(a) = a {
                visit(a, HIDDEN, w[0], 0.0);
            }
            if let Some(b) = b {
                visit(b, HIDDEN, w[1], 0.0);
            }
            continue;
        }
        let length = w[1].t - w[0].t;
        if let Some(a) = a {
            visit(a, b.unwrap_or(ABSORBED), w[0], length);
        }
        if let Some(b) = b {
            visit(b, a.unwrap_or(ABSORBED), w[1], length);
        }
    }
    if let Some(last) = hits.last()
        && let Some(a) = exit(last)
    {
        visit(a, SKY, *last, f32::INFINITY);
    }
}

/// Sorts and merges equal keys, dropping zero counts.
fn aggregate(mut raw: Vec<(u64, i64)>) -> Entries {
    let mut out: Entries = Vec::with_capacity(raw.len() / 2);
    add_sorted(&mut raw, &mut out);
    out
}

/// Sorts `entries` by key and appends them to `out`, equal keys added and zero counts dropped.
fn add_sorted(entries: &mut [(u64, i64)], out: &mut Entries) {
    entries.sort_unstable_by_key(|e| e.0);
    let mut k = 0;
    while k < entries.len() {
        let (key, mut count) = entries[k];
        k += 1;
        while k < entries.len() && entries[k].0 == key {
            count += entries[k].1;
            k += 1;
        }
        if count != 0 {
            out.push((key, count));
        }
    }
}

/// [`aggregate`] of the entries of `chunks` together, in any order: a counting sort by row,
/// then each row's entries sorted and added where they sit in cache, the rows in parallel.
/// A frame's changes are a few hundred thousand entries over thousands of rows: sorting each
/// chunk of lines and merging the chunks in rounds copied every entry five times or more.
fn by_rows(chunks: Vec<Vec<(u64, i64)>>) -> Entries {
    let row = |e: &(u64, i64)| (e.0 >> 32) as usize;
    let rows = (chunks.iter().flatten())
        .map(|e| row(e) + 1)
        .max()
        .unwrap_or(0);
    let mut starts = vec![0usize; rows + 1];
    for e in chunks.iter().flatten() {
        starts[row(e) + 1] += 1;
    }
    for r in 0..rows {
        starts[r + 1] += starts[r];
    }
    let mut placed = vec![(0u64, 0i64); starts[rows]];
    let mut next = starts[..rows].to_vec();
    for e in chunks.into_iter().flatten() {
        let r = row(&e);
        placed[next[r]] = e;
        next[r] += 1;
    }
    // Runs of whole rows of about equal entries, each sorted and added on its own.
    let per_run = (placed.len() / (8 * rayon::current_num_threads()).max(1)).max(4096);
    let mut runs = Vec::new();
    let mut from = 0;
    for r in 1..=rows {
        if starts[r] - starts[from] >= per_run || r == rows {
            runs.push(from..r);
            from = r;
        }
    }
    let mut slices = Vec::with_capacity(runs.len());
    let mut rest = &mut placed[..];
    for rows in runs {
        let (run, after) = rest.split_at_mut(starts[rows.end] - starts[rows.start]);
        slices.push((rows, run));
        rest = after;
    }
    let parts: Vec<Entries> = slices
        .into_par_iter()
        .map(|(rows, placed)| {
            let mut out: Entries = Vec::with_capacity(placed.len());
            let mut at = 0;
            for r in rows {
                let len = starts[r + 1] - starts[r];
                add_sorted(&mut placed[at..at + len], &mut out);
                at += len;
            }
            out
        })
        .collect();
    parts.concat()
}

/// Adds two sorted entry lists.
fn merge(a: &[(u64, i64)], b: &[(u64, i64)]) -> Entries {
    let mut out = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => {
                out.push(a[i]);
                i += 1;
            }
            std::cmp::Ordering::Greater => {
                out.push(b[j]);
                j += 1;
            }
            std::cmp::Ordering::Equal => {
                if a[i].1 + b[j].1 != 0 {
                    out.push((a[i].0, a[i].1 + b[j].1));
                }
                i += 1;
                j += 1;
            }
        }
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
    out
}

/// The tallies of a timeline: the static counts, and what each frame's moving objects change,
/// recomputed when a frame is solved from the lines they touch (cheaper to redo than to keep:
/// a frame's changes take more memory than the moving crossings they come from).
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct Tallies {
    /// Segment counts of every line's static crossings: the tallies of a frame without its
    /// moving objects.
    statics: FrameTally,
    /// Lines crossing a moving object at frame f: `touched[touched_offsets[f]..touched_offsets[f + 1]]`,
    /// each with where the frame's crossings start among the line's moving ones
    /// ([`IntersectionList::moving_hits`]).
    touched_offsets: Vec<u32>,
    touched: Vec<(u32, u32)>,
    /// Per frame, a 128-bit fingerprint of its changes: frames with equal changes have equal
    /// solutions.
    fingerprints: Vec<u128>,
    /// Group of each line (see [`GROUPS`]).
    groups: Vec<u8>,
    /// Weight of each line ([`IntersectionList::line_weights`]): its segments count this many
    /// times.
    weights: Vec<u8>,
    /// The dense regions of the list when it was tallied: when they change, every line's
    /// weight may, and everything is tallied again.
    dense: usize,
    /// Lines tallied so far.
    lines: usize,
}

/// One frame's tallies, assembled: `S` row by row, with each row's per-group entries.
///
/// A frame's rows are its timeline's static rows where its moving objects change nothing,
/// shared with them rather than copied ([`Tallies::frame`]): a door seen from one room changes
/// that room's rows. (The moving Cornell box's block, seen from almost every one of its 10,000
/// pieces, changes 450,000 of their 1.3 million static entries, over most rows.)
#[derive(Clone, Debug, Default)]
pub struct FrameTally {
    /// Crossings of each patch's visible part (the row sums of `S` without [`HIDDEN`]): its
    /// `N_i`.
    pub crossings: Vec<u64>,
    /// Crossings of each patch where a surface touches it (the [`HIDDEN`] column).
    pub hidden: Vec<u64>,
    /// The rows (every one, or those `changed` does not replace).
    rows: Arc<Rows>,
    /// The rows a frame's moving objects change: row `r` is `changed.1`'s row `changed.0[r]`
    /// where that is not [`UNCHANGED`].
    changed: Option<(Vec<u32>, Rows)>,
    /// What one global line's segment counts (the dense factor of the list's regions,
    /// [`IntersectionList::line_weights`]; 1 without them): counts over it are in global
    /// lines.
    pub unit: u64,
}

/// A row of a [`FrameTally`] that its static rows hold.
const UNCHANGED: u32 = u32::MAX;

/// Rows of `S` in compressed form, each with its per-group entries.
#[derive(Clone, Debug)]
struct Rows {
    /// Row starts in `columns` / `counts` (one per row, and the end).
    offsets: Vec<usize>,
    /// Column of each entry: a patch, [`SKY`], [`ABSORBED`] or [`HIDDEN`].
    columns: Vec<u32>,
    /// Segment count of each entry, each segment its line's weight (> 0; below 2^32: the dense
    /// factor is chosen so by [`crate::bake::Bake::split`]).
    counts: Vec<u32>,
    /// Row starts of the per-group entries.
    group_offsets: Vec<usize>,
    /// Per-group entries of each row: (column, group, count), for the error estimate.
    group_entries: Vec<(u32, u8, u32)>,
}

impl Default for Rows {
    fn default() -> Self {
        Self::with_capacity(0)
    }
}

impl Rows {
    /// No rows yet, room for `entries`.
    fn with_capacity(entries: usize) -> Self {
        Self {
            offsets: vec![0],
            columns: Vec::with_capacity(entries),
            counts: Vec::with_capacity(entries),
            group_offsets: vec![0],
            group_entries: Vec::with_capacity(entries),
        }
    }

    /// Row `r`'s columns and counts.
    fn row(&self, r: usize) -> (&[u32], &[u32]) {
        let range = self.offsets[r]..self.offsets[r + 1];
        (&self.columns[range.clone()], &self.counts[range])
    }

    /// Row `r`'s per-group entries.
    fn group_row(&self, r: usize) -> &[(u32, u8, u32)] {
        &self.group_entries[self.group_offsets[r]..self.group_offsets[r + 1]]
    }

    /// Appends `count` segments of group `group` to `column` in the open row, keys in
    /// increasing order.
    fn push(&mut self, column: u32, group: u8, count: u32) {
        self.push_column(column, count);
        self.group_entries.push((column, group, count));
    }

    /// Appends `count` segments to `column` in the open row, without per-group entries.
    fn push_column(&mut self, column: u32, count: u32) {
        let open = self.offsets.last().copied().unwrap_or_default();
        match self.counts.last_mut() {
            Some(last) if self.columns.len() > open && self.columns.last() == Some(&column) => {
                *last += count;
            }
            _ => {
                self.columns.push(column);
                self.counts.push(count);
            }
        }
    }

    /// Closes the open row (the next entries go to the next row).
    fn close(&mut self) {
        self.offsets.push(self.columns.len());
        self.group_offsets.push(self.group_entries.len());
    }

    fn bytes(&self) -> usize {
        (self.offsets.len() + self.group_offsets.len()) * size_of::<usize>()
            + (self.columns.len() + self.counts.len()) * size_of::<u32>()
            + self.group_entries.len() * size_of::<(u32, u8, u32)>()
    }
}

/// [`FrameTally`] as it is stored: every row in place.
#[derive(serde::Deserialize)]
struct StoredTally {
    crossings: Vec<u64>,
    hidden: Vec<u64>,
    offsets: Vec<usize>,
    columns: Vec<u32>,
    counts: Vec<u32>,
    group_offsets: Vec<usize>,
    group_entries: Vec<(u32, u8, u32)>,
    unit: u64,
}

/// [`StoredTally`], borrowed: the same fields in the same order.
#[derive(serde::Serialize)]
struct StoredTallyRef<'a> {
    crossings: &'a [u64],
    hidden: &'a [u64],
    offsets: &'a [usize],
    columns: &'a [u32],
    counts: &'a [u32],
    group_offsets: &'a [usize],
    group_entries: &'a [(u32, u8, u32)],
    unit: u64,
}

impl serde::Serialize for FrameTally {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let whole;
        let rows = match self.changed {
            None => &*self.rows,
            Some(_) => {
                whole = self.whole_rows();
                &whole
            }
        };
        StoredTallyRef {
            crossings: &self.crossings,
            hidden: &self.hidden,
            offsets: &rows.offsets,
            columns: &rows.columns,
            counts: &rows.counts,
            group_offsets: &rows.group_offsets,
            group_entries: &rows.group_entries,
            unit: self.unit,
        }
        .serialize(serializer)
    }
}

impl<'de> serde::Deserialize<'de> for FrameTally {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let t = StoredTally::deserialize(deserializer)?;
        let patches = t.crossings.len();
        if t.hidden.len() != patches
            || t.offsets.len() != patches + 1
            || t.group_offsets.len() != patches + 1
            || t.offsets.last() != Some(&t.columns.len())
            || t.counts.len() != t.columns.len()
            || t.group_offsets.last() != Some(&t.group_entries.len())
            || !t.offsets.is_sorted()
            || !t.group_offsets.is_sorted()
        {
            return Err(serde::de::Error::custom(
                "a frame tally's rows do not fit together",
            ));
        }
        Ok(Self {
            crossings: t.crossings,
            hidden: t.hidden,
            rows: Arc::new(Rows {
                offsets: t.offsets,
                columns: t.columns,
                counts: t.counts,
                group_offsets: t.group_offsets,
                group_entries: t.group_entries,
            }),
            changed: None,
            unit: t.unit,
        })
    }
}

/// Two tallies are equal when every row is, however they hold them.
impl PartialEq for FrameTally {
    fn eq(&self, other: &Self) -> bool {
        self.crossings == other.crossings
            && self.hidden == other.hidden
            && self.unit == other.unit
            && (0..self.patches())
                .all(|i| self.row(i) == other.row(i) && self.group_row(i) == other.group_row(i))
    }
}

impl Tallies {
    /// Tallies the lines `list` holds beyond those already tallied (all of them the first
    /// time): call again after [`IntersectionList::add_lines`] to refine.
    pub fn update(&mut self, list: &IntersectionList, surfaces: &Surfaces<'_>, patches: usize) {
        self.update_like(list, surfaces, patches, None);
    }

    /// [`Tallies::update`], the lines each frame touches and the frames' fingerprints taken
    /// from `like` where it has tallied the same lines of `list` (other patches on the same
    /// triangles: a split bake's patches and pieces), rather than read from the list again.
    pub fn update_like(
        &mut self,
        list: &IntersectionList,
        surfaces: &Surfaces<'_>,
        patches: usize,
        like: Option<&Self>,
    ) {
        if list.dense().0.len() != self.dense {
            *self = Self::default();
            self.dense = list.dense().0.len();
        }
        let new = self.lines..list.lines();
        self.groups = list.line_groups(GROUPS);
        self.weights = list.line_weights().to_vec();
        let statics = tally_static(list, surfaces, new.clone(), (&self.groups, &self.weights));
        let entries = if self.lines == 0 {
            statics
        } else {
            merge(&self.statics.entries(), &statics)
        };
        self.statics = assemble(entries, patches);
        self.statics.unit = u64::from(list.dense().1);
        self.lines = new.end;
        let same = |like: &&Self| {
            like.lines == list.lines()
                && like.dense == self.dense
                && like.weights == self.weights
                && like.touched_offsets.len() == list.frames() + 1
        };
        if let Some(like) = like.filter(same) {
            self.touched_offsets.clone_from(&like.touched_offsets);
            self.touched.clone_from(&like.touched);
            self.fingerprints.clone_from(&like.fingerprints);
            return;
        }
        // Which lines each frame's moving objects touch, over all lines that count.
        // Each line's frames in line order, placed by frame (a counting sort: line order kept).
        let starts = |l: usize| {
            let moving = list.moving_hits(l);
            (0..moving.len())
                .filter(move |&k| k == 0 || moving[k - 1].frame != moving[k].frame)
                .map(move |k| (moving[k].frame as usize, k as u32))
        };
        let counted = (0..list.lines()).filter(|&l| self.weights[l] > 0);
        self.touched_offsets = vec![0; list.frames() + 1];
        for l in counted.clone() {
            for (f, _) in starts(l) {
                self.touched_offsets[f + 1] += 1;
            }
        }
        for f in 0..list.frames() {
            self.touched_offsets[f + 1] += self.touched_offsets[f];
        }
        let mut next: Vec<u32> = self.touched_offsets[..list.frames()].to_vec();
        self.touched = vec![(0, 0); self.touched_offsets[list.frames()] as usize];
        for l in counted {
            for (f, k) in starts(l) {
                self.touched[next[f] as usize] = (l as u32, k);
                next[f] += 1;
            }
        }
        self.fingerprints = moving_fingerprints(list);
    }

    /// Lines tallied.
    #[must_use]
    pub fn lines(&self) -> usize {
        self.lines
    }

    /// What the moving objects change at `frame`: minus the static segments of the lines they
    /// touch, plus those lines' frame segments.
    fn changes(&self, list: &IntersectionList, surfaces: &Surfaces<'_>, frame: usize) -> Entries {
        let touched = &self.touched
            [self.touched_offsets[frame] as usize..self.touched_offsets[frame + 1] as usize];
        // In chunks on every core; sums of integers, so the same whatever the split.
        let chunks: Vec<Entries> = touched
            .par_chunks(4096)
            .map(|chunk| {
                let (mut raw, mut merged, mut line) = (Vec::new(), Vec::new(), Vec::new());
                let mut directions = list.directions();
                for (k, &(l, start)) in chunk.iter().enumerate() {
                    // The lines are scattered over the list: their places asked for two
                    // lines' work ahead of their crossings, and those one ahead.
                    if let Some(&(l, _)) = chunk.get(k + 2 * AHEAD) {
                        list.prefetch_offsets(l as usize);
                        crate::prefetch(&self.weights[l as usize], 1);
                        crate::prefetch(&self.groups[l as usize], 1);
                    }
                    if let Some(&(l, start)) = chunk.get(k + AHEAD) {
                        list.prefetch_hits(l as usize, start as usize);
                    }
                    let l = l as usize;
                    let (g, w) = (self.groups[l], i64::from(self.weights[l]));
                    if w == 0 {
                        continue;
                    }
                    list.frame_hits_from(l, frame, start as usize, &mut merged);
                    let surfaces = surfaces.along(directions.of(l));
                    line.clear();
                    walk(list.static_hits(l), &surfaces, |a, b| {
                        line.push((key(a, b, g), -w));
                    });
                    walk(&merged, &surfaces, |a, b| line.push((key(a, b, g), w)));
                    // The line's segments away from the moving crossings are the same in both
                    // walks: they cancel here, where the line's few entries sort in cache,
                    // rather than in the frame's sort.
                    add_sorted(&mut line, &mut raw);
                }
                raw
            })
            .collect();
        by_rows(chunks)
    }

    /// Frames whose tallies equal an earlier frame's: `representative[f]` is the first frame
    /// with the same tallies (itself if none). Such frames have the same solution. Frames are
    /// matched by the fingerprints of their moving crossings ([`moving_fingerprints`]): 128
    /// bits, so that two different frames of a timeline of n frames match by chance with a
    /// probability below n²·2^-129 (10^-31 for 10,000 frames). Frames whose moving objects
    /// cross the lines differently but leave the same tallies are not matched.
    #[must_use]
    pub fn representatives(&self) -> Vec<usize> {
        let mut first: HashMap<u128, usize> = HashMap::new();
        (0..self.fingerprints.len())
            .map(|f| *first.entry(self.fingerprints[f]).or_insert(f))
            .collect()
    }

    /// Bytes held: the static entries, the touched lines per frame, the line groups.
    #[must_use]
    pub fn bytes(&self) -> usize {
        self.statics.bytes()
            + self.touched.len() * size_of::<(u32, u32)>()
            + self.touched_offsets.len() * size_of::<u32>()
            + self.fingerprints.len() * size_of::<u128>()
            + self.groups.len()
            + self.weights.len()
    }

    /// The tallies of `frame` (over the patches [`Tallies::update`] was given).
    #[must_use]
    pub fn frame(
        &self,
        list: &IntersectionList,
        surfaces: &Surfaces<'_>,
        frame: usize,
    ) -> FrameTally {
        Self::with(&self.statics, &self.changes(list, surfaces, frame))
    }

    /// `statics` with `changes`.
    fn with(statics: &FrameTally, changes: &[(u64, i64)]) -> FrameTally {
        if changes.is_empty() {
            return statics.clone();
        }
        statics.with_changes(changes)
    }
}

/// How many touched lines ahead of the one walked [`Tallies::changes`] asks memory for.
const AHEAD: usize = 8;

/// Lines per chunk of [`moving_fingerprints`].
const FINGERPRINT_LINES: usize = 1 << 16;

/// A 128-bit fingerprint of each frame's moving crossings (every line's crossings of the
/// moving objects tagged with the frame, in line order): frames with equal fingerprints have
/// equal moving crossings, hence equal tallies (the static crossings are every frame's). Read
/// once from the list, each crossing hashed once, where hashing each frame's tallies walked
/// the lines the moving objects touch at every frame. Two independent 64-bit hashes (different
/// prefixes) per chunk of lines, then over the chunks in order: the same whatever the threads.
fn moving_fingerprints(list: &IntersectionList) -> Vec<u128> {
    use std::hash::{Hash, Hasher};
    type Hashers = Vec<[std::collections::hash_map::DefaultHasher; 2]>;
    let frames = list.frames();
    let fresh = || -> Hashers {
        (0..frames)
            .map(|_| {
                [0u8, 1].map(|prefix| {
                    let mut h = std::collections::hash_map::DefaultHasher::new();
                    prefix.hash(&mut h);
                    h
                })
            })
            .collect()
    };
    let chunks: Vec<Vec<[u64; 2]>> = (0..list.lines().div_ceil(FINGERPRINT_LINES))
        .into_par_iter()
        .map(|c| {
            let mut hashers = fresh();
            let end = ((c + 1) * FINGERPRINT_LINES).min(list.lines());
            for l in c * FINGERPRINT_LINES..end {
                for h in list.moving_hits(l) {
                    // The line (below 2^32), the distance, the triangle (below 2^31) and the
                    // side, in one word: one hasher call, not four.
                    let code = u128::from(h.hit.surface()) | (u128::from(h.hit.front()) << 31);
                    let word = ((l as u128) << 64) | (u128::from(h.hit.t.to_bits()) << 32) | code;
                    for hasher in &mut hashers[h.frame as usize] {
                        hasher.write_u128(word);
                    }
                }
            }
            hashers
                .iter()
                .map(|h| h.each_ref().map(Hasher::finish))
                .collect()
        })
        .collect();
    let mut hashers = fresh();
    for chunk in &chunks {
        for (hasher, halves) in hashers.iter_mut().zip(chunk) {
            hasher[0].write_u64(halves[0]);
            hasher[1].write_u64(halves[1]);
        }
    }
    (hashers.iter())
        .map(|[a, b]| (u128::from(a.finish()) << 64) | u128::from(b.finish()))
        .collect()
}

/// A frame's CSR from its sorted entries.
fn assemble(entries: Entries, patches: usize) -> FrameTally {
    let mut t = Builder::new(patches, entries.len());
    let mut row = 0;
    for (k, c) in entries {
        let (r, col, group) = unkey(k);
        debug_assert!(c > 0, "a frame's segment count went negative");
        while row < r as usize {
            t.rows.close();
            row += 1;
        }
        t.push(r as usize, col, group, c as u32);
    }
    while row < patches {
        t.rows.close();
        row += 1;
    }
    t.finish(1)
}

/// A [`FrameTally`] being written row after row.
struct Builder {
    crossings: Vec<u64>,
    hidden: Vec<u64>,
    rows: Rows,
}

impl Builder {
    /// `patches` rows to come, with room for `entries`.
    fn new(patches: usize, entries: usize) -> Self {
        Self {
            crossings: vec![0; patches],
            hidden: vec![0; patches],
            rows: Rows::with_capacity(entries),
        }
    }

    /// Appends `count` segments of group `group` from `row` (the open row) to `column`, keys
    /// in increasing order.
    fn push(&mut self, row: usize, column: u32, group: u8, count: u32) {
        self.rows.push(column, group, count);
        count_into((&mut self.crossings, &mut self.hidden), row, column, count);
    }

    fn finish(self, unit: u64) -> FrameTally {
        FrameTally {
            crossings: self.crossings,
            hidden: self.hidden,
            rows: Arc::new(self.rows),
            changed: None,
            unit,
        }
    }
}

/// Counts `count` crossings of `row` whose segment goes to `column` into its crossings or
/// (for [`HIDDEN`]) its hidden ones.
fn count_into((crossings, hidden): (&mut [u64], &mut [u64]), row: usize, column: u32, count: u32) {
    if column == HIDDEN {
        hidden[row] += u64::from(count);
    } else {
        crossings[row] += u64::from(count);
    }
}

impl FrameTally {
    /// Rows (patches) tallied.
    #[must_use]
    pub fn patches(&self) -> usize {
        self.crossings.len()
    }

    /// The rows holding row `i`, and its index there.
    fn rows_of(&self, i: usize) -> (&Rows, usize) {
        match &self.changed {
            Some((slots, rows)) if slots[i] != UNCHANGED => (rows, slots[i] as usize),
            _ => (&self.rows, i),
        }
    }

    /// Row `i` of `S`: its columns (a patch, [`SKY`], [`ABSORBED`] or [`HIDDEN`]), in
    /// increasing order, and their segment counts (each segment its line's weight).
    #[must_use]
    pub fn row(&self, i: usize) -> (&[u32], &[u32]) {
        let (rows, r) = self.rows_of(i);
        rows.row(r)
    }

    /// Row `i`'s per-group entries: (column, group, count), in increasing (column, group).
    #[must_use]
    pub fn group_row(&self, i: usize) -> &[(u32, u8, u32)] {
        let (rows, r) = self.rows_of(i);
        rows.group_row(r)
    }

    /// Every row in place, whether or not some are a frame's changes to static ones.
    fn whole_rows(&self) -> Rows {
        let mut rows = Rows::with_capacity(self.rows.columns.len());
        for i in 0..self.patches() {
            let (columns, counts) = self.row(i);
            rows.columns.extend_from_slice(columns);
            rows.counts.extend_from_slice(counts);
            rows.group_entries.extend_from_slice(self.group_row(i));
            rows.close();
        }
        rows
    }

    /// These tallies over merged patches: patch `k` becomes `into.of()[k]` (one of
    /// `into.len()`), as a walk of the same lines over the merged patches tallies them (it
    /// reads a crossing's patch and nothing else of it, so each segment's ends are only
    /// renamed).
    #[must_use]
    pub fn merged(&self, into: &super::Groups) -> Self {
        let rename = |j: u32| {
            if j >= HIDDEN {
                j
            } else {
                into.of()[j as usize]
            }
        };
        let count = into.len();
        let mut t = Builder::new(count, self.rows.columns.len());
        let mut row: Vec<(u32, u8, u32)> = Vec::new();
        for r in 0..count {
            row.clear();
            for &k in into.members(r) {
                let renamed =
                    (self.group_row(k as usize).iter()).map(|&(j, g, c)| (rename(j), g, c));
                row.extend(renamed);
            }
            row.sort_unstable_by_key(|&(j, g, _)| (j, g));
            for same in row.chunk_by(|a, b| (a.0, a.1) == (b.0, b.1)) {
                let (j, g, _) = same[0];
                t.push(r, j, g, same.iter().map(|e| e.2).sum());
            }
            t.rows.close();
        }
        t.finish(self.unit)
    }

    /// The sorted entries these tallies were assembled from.
    fn entries(&self) -> Entries {
        let mut out = Vec::with_capacity(self.rows.group_entries.len());
        for row in 0..self.patches() {
            for &(column, group, count) in self.group_row(row) {
                out.push((key(row as u32, column, group), i64::from(count)));
            }
        }
        out
    }

    /// Bytes held (the static rows a frame shares with its timeline's counted once, there).
    #[must_use]
    pub fn bytes(&self) -> usize {
        let own = match &self.changed {
            None => self.rows.bytes(),
            Some((slots, rows)) => slots.len() * size_of::<u32>() + rows.bytes(),
        };
        (self.crossings.len() + self.hidden.len()) * size_of::<u64>() + own
    }

    /// These tallies plus `changes` (sorted keys, counts that never take an entry below 0):
    /// the rows without changes shared, the others merged with their changes.
    fn with_changes(&self, changes: &[(u64, i64)]) -> Self {
        let patches = self.patches();
        let rows = match self.changed {
            None => Arc::clone(&self.rows),
            Some(_) => Arc::new(self.whole_rows()),
        };
        let mut slots = vec![UNCHANGED; patches];
        let mut own = Rows::with_capacity(2 * changes.len());
        let (mut crossings, mut hidden) = (self.crossings.clone(), self.hidden.clone());
        let mut next = 0;
        while next < changes.len() {
            let row = unkey(changes[next].0).0 as usize;
            // The changed row: its per-group entries merged with its changes, in key order.
            // A row's changes are few: a scan, not a binary search over the rest.
            let end = next
                + (changes[next..].iter())
                    .position(|&(k, _)| unkey(k).0 as usize != row)
                    .unwrap_or(changes.len() - next);
            slots[row] = (own.offsets.len() - 1) as u32;
            crossings[row] = 0;
            hidden[row] = 0;
            // Both sides sorted by (column, group): a merge, equal keys added.
            let (old, new) = (rows.group_row(row), &changes[next..end]);
            let (mut i, mut j) = (0, 0);
            while i < old.len() || j < new.len() {
                let (column, group, count) = match (old.get(i), new.get(j)) {
                    (Some(&(c, g, n)), Some(&(k, d))) => {
                        let (_, column, group) = unkey(k);
                        match (c, g).cmp(&(column, group)) {
                            std::cmp::Ordering::Less => {
                                i += 1;
                                (c, g, i64::from(n))
                            }
                            std::cmp::Ordering::Greater => {
                                j += 1;
                                (column, group, d)
                            }
                            std::cmp::Ordering::Equal => {
                                (i, j) = (i + 1, j + 1);
                                (c, g, i64::from(n) + d)
                            }
                        }
                    }
                    (Some(&(c, g, n)), None) => {
                        i += 1;
                        (c, g, i64::from(n))
                    }
                    (None, Some(&(k, d))) => {
                        j += 1;
                        let (_, column, group) = unkey(k);
                        (column, group, d)
                    }
                    (None, None) => break,
                };
                debug_assert!(count >= 0, "a frame's segment count went negative");
                if count > 0 {
                    own.push(column, group, count as u32);
                    count_into((&mut crossings, &mut hidden), row, column, count as u32);
                }
            }
            own.close();
            next = end;
        }
        Self {
            crossings,
            hidden,
            rows,
            changed: Some((slots, own)),
            unit: self.unit,
        }
    }

    /// The tallies of arbitrary per-line crossing lists (each sorted along its line, with the
    /// line's group): for checking the multiframe tallies against a frame traced alone.
    #[must_use]
    pub fn from_lines<'h>(
        lines: impl Iterator<Item = (u8, &'h [Hit])>,
        surfaces: &Surfaces<'_>,
        patches: usize,
    ) -> Self {
        let mut raw = Vec::new();
        for (group, hits) in lines {
            walk(hits, surfaces, |a, b| raw.push((key(a, b, group), 1)));
        }
        assemble(aggregate(raw), patches)
    }

    /// The tallies of each replica of the lines alone (no per-group entries), in one pass over
    /// the per-group entries.
    #[must_use]
    pub fn replicas(&self) -> Vec<Self> {
        let patches = self.patches();
        let mut sizes = [0usize; GROUPS as usize];
        for i in 0..patches {
            (self.group_row(i).iter()).for_each(|&(_, g, _)| sizes[g as usize] += 1);
        }
        let mut replicas: Vec<Builder> = (sizes.iter())
            .map(|&size| Builder::new(patches, size))
            .collect();
        for i in 0..patches {
            for &(column, g, count) in self.group_row(i) {
                let t = &mut replicas[g as usize];
                t.rows.push_column(column, count);
                count_into((&mut t.crossings, &mut t.hidden), i, column, count);
            }
            replicas.iter_mut().for_each(|t| t.rows.close());
        }
        (replicas.into_iter())
            .map(|t| t.finish(self.unit))
            .collect()
    }

    /// Whether `S` is symmetric between patches (reciprocity, `A_i F_ij = A_j F_ji`): true by
    /// construction, since every segment is tallied in both directions.
    #[must_use]
    pub fn is_symmetric(&self) -> bool {
        let count = |i: usize, j: u32| {
            let (columns, counts) = self.row(i);
            columns.iter().position(|&c| c == j).map(|k| counts[k])
        };
        (0..self.patches()).all(|i| {
            let (columns, counts) = self.row(i);
            (columns.iter().zip(counts))
                .filter(|&(&j, _)| (j as usize) < MAX_PATCHES)
                .all(|(&j, &c)| count(j as usize, i as u32) == Some(c))
        })
    }
}

/// Static segments of `lines`, each counted its line's weight.
fn tally_static(
    list: &IntersectionList,
    surfaces: &Surfaces<'_>,
    lines: Range<usize>,
    (groups, weights): (&[u8], &[u8]),
) -> Entries {
    let chunks: Vec<Entries> = lines
        .collect::<Vec<_>>()
        .par_chunks(4096)
        .map(|chunk| {
            let mut raw = Vec::new();
            let mut directions = list.directions();
            for &l in chunk {
                let w = i64::from(weights[l]);
                if w == 0 {
                    continue;
                }
                let surfaces = surfaces.along(directions.of(l));
                walk(list.static_hits(l), &surfaces, |a, b| {
                    raw.push((key(a, b, groups[l]), w))
                });
            }
            aggregate(raw)
        })
        .collect();
    by_rows(chunks)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Faces;

    /// The (from, to) pairs [`walk`] visits along `hits`, sorted, over two triangles with these
    /// (front, back) patches, spaces and normals.
    fn walked(
        hits: &[Hit],
        faces: [(u32, Option<u32>); 2],
        spaces: [u32; 2],
        normals: [glam::Vec3; 2],
    ) -> Vec<(u32, u32)> {
        let faces = faces.map(|(front, back)| Faces { front, back });
        let surfaces = Surfaces {
            faces: &faces,
            spaces: &spaces,
            normals: &normals,
            corners: &[[0, 1, 2], [3, 4, 5]],
            direction: None,
        };
        let mut seen = Vec::new();
        walk(hits, &surfaces, |a, b| seen.push((a, b)));
        seen.sort_unstable();
        seen
    }

    #[test]
    fn segments_are_used_both_ways_and_the_ends_see_the_sky() {
        // Triangle 0 one-sided (patch 0), triangle 1 double-sided (patches 1, 2). The line
        // arrives at triangle 0's front, then at triangle 1's back.
        let hits = [Hit::new(1.0, 0, true), Hit::new(2.0, 1, false)];
        let seen = walked(&hits, [(0, None), (1, Some(2))], [0, 0], [glam::Vec3::Z; 2]);
        // Patch 0 sees the sky behind it; the segment between leaves 0's back (absorbed: it is
        // one-sided) and enters 1's back (patch 2); patch 1 (front) sees the sky beyond.
        assert_eq!(seen, vec![(0, SKY), (1, SKY), (2, ABSORBED)]);
    }

    #[test]
    fn a_contact_is_hidden_and_counted_apart_from_the_visible_crossings() {
        // A floor (triangle 0, facing up: patch 0) and a box's bottom resting on it (triangle
        // 1, facing down: patch 1), one-sided, crossed at one place by a line going up.
        let hits = [Hit::new(1.0, 0, false), Hit::new(1.0, 1, true)];
        let normals = [glam::Vec3::Z, glam::Vec3::NEG_Z];
        let seen = walked(&hits, [(0, None), (1, None)], [0, 0], normals);
        assert_eq!(seen, vec![(0, HIDDEN), (1, HIDDEN)]);
        // Tallied with a visible crossing of the floor: N_0 counts that one alone.
        let mut raw: Vec<(u64, i64)> = seen.iter().map(|&(a, b)| (key(a, b, 0), 1)).collect();
        raw.push((key(0, SKY, 1), 1));
        let t = assemble(aggregate(raw), 2);
        assert_eq!((t.crossings, t.hidden), (vec![1, 0], vec![1, 1]));
        let replicas = assemble(aggregate(vec![(key(0, HIDDEN, 3), 2)]), 2).replicas();
        assert_eq!((replicas[3].crossings[0], replicas[3].hidden[0]), (0, 2));
    }

    #[test]
    fn crossings_are_the_row_sums() {
        let hits = [Hit::new(1.0, 0, true), Hit::new(2.0, 1, true)];
        let faces = [(0, Some(1)), (2, Some(3))];
        let seen = walked(&hits, faces, [0, 1], [glam::Vec3::Z; 2]);
        let entries = aggregate(seen.iter().map(|&(a, b)| (key(a, b, 0), 1)).collect());
        // 0 sees the sky, 1 sees 2 and 2 sees 1, 3 sees the sky: each face crossed once.
        let expected = [(0, SKY), (1, 2), (2, 1), (3, SKY)].map(|(a, b)| (key(a, b, 0), 1));
        assert_eq!(entries, expected.to_vec());
    }

    #[test]
    fn a_frame_is_its_static_rows_with_the_changed_ones_merged() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(7);
        let patches = 40;
        let raw: Vec<(u64, i64)> = (0..600)
            .map(|_| {
                let column = if rng.random_bool(0.1) {
                    SKY
                } else {
                    rng.random_range(0..patches)
                };
                let k = key(
                    rng.random_range(0..patches),
                    column,
                    rng.random_range(0..GROUPS) as u8,
                );
                (k, rng.random_range(1..4))
            })
            .collect();
        let statics = aggregate(raw);
        // Remove some static segments (never more than there are) and add new ones.
        let mut raw = Vec::new();
        for &(k, c) in &statics {
            if rng.random_bool(0.2) {
                raw.push((k, -rng.random_range(1..=c)));
            }
        }
        raw.extend((0..100).map(|_| {
            let k = key(
                rng.random_range(0..patches),
                rng.random_range(0..patches),
                3,
            );
            (k, 1)
        }));
        let changes = aggregate(raw);
        let tally = assemble(statics.clone(), patches as usize);
        assert_eq!(tally.entries(), statics);
        let frame = tally.with_changes(&changes);
        let whole = assemble(merge(&statics, &changes), patches as usize);
        assert_eq!(frame, whole);
        assert_eq!(frame.entries(), whole.entries());
        // The changed rows held apart from the shared static ones, stored as every row in
        // place: the same bytes, and read back equal.
        assert!(frame.changed.is_some() && Arc::ptr_eq(&frame.rows, &tally.rows));
        let stored = postcard::to_stdvec(&frame).unwrap();
        assert_eq!(stored, postcard::to_stdvec(&whole).unwrap());
        assert_eq!(postcard::from_bytes::<FrameTally>(&stored).unwrap(), whole);
        // A frame's changes on top of another frame's: the rows in place first.
        let again = frame.with_changes(&[]);
        assert_eq!(again, whole);
    }

    /// Tallies over merged patches are those of the same segments with their ends renamed:
    /// rows and columns merged (into a patch of their own, into one another), the sky, the
    /// absorbed and the hidden columns kept, counts of the same (column, group) added.
    #[test]
    fn merged_tallies_are_the_segments_with_their_ends_renamed() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(13);
        let patches = 60u32;
        let columns = [SKY, ABSORBED, HIDDEN];
        let segments: Vec<(u32, u32, u8, i64)> = (0..2_000)
            .map(|_| {
                let to = if rng.random_bool(0.2) {
                    columns[rng.random_range(0..3)]
                } else {
                    rng.random_range(0..patches)
                };
                let group = rng.random_range(0..GROUPS) as u8;
                (
                    rng.random_range(0..patches),
                    to,
                    group,
                    rng.random_range(1..4),
                )
            })
            .collect();
        // Pairs merged (0 and 1 into 0, …), every fifth patch alone; dense new ids.
        let mut into: Vec<u32> = Vec::new();
        let mut count = 0;
        for p in 0..patches {
            // Patches 5k and 5k + 1 together, 5k + 2 and 5k + 3, 5k + 4 alone.
            if p % 5 != 1 && p % 5 != 3 {
                count += 1;
            }
            into.push(count as u32 - 1);
        }
        let rename = |j: u32| if j >= HIDDEN { j } else { into[j as usize] };
        let tally = |f: &dyn Fn(u32) -> u32, n: usize| {
            let raw = segments
                .iter()
                .map(|&(a, b, g, c)| (key(f(a), f(b), g), c))
                .collect();
            assemble(aggregate(raw), n)
        };
        let fine = tally(&|j| j, patches as usize);
        assert!(count < patches as usize);
        let groups = super::super::Groups::new(into.clone(), vec![1.0; into.len()], count);
        assert_eq!(fine.merged(&groups), tally(&rename, count));
    }

    /// The counting sort by row adds what a sort of all the entries adds: chunks in any order,
    /// keys repeated within and across chunks, counts that cancel to zero dropped, rows with
    /// no entries between others.
    #[test]
    fn entries_sorted_by_row_are_the_sorted_entries() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(11);
        let entry = |rng: &mut rand::rngs::Xoshiro256PlusPlus| {
            let row = 3 * rng.random_range(0..2_000);
            let k = key(
                row,
                rng.random_range(0..50),
                rng.random_range(0..GROUPS) as u8,
            );
            (k, rng.random_range(-2..3))
        };
        let chunks: Vec<Vec<(u64, i64)>> = (0..7)
            .map(|c| (0..c * 9_000).map(|_| entry(&mut rng)).collect())
            .collect();
        let all = aggregate(chunks.concat());
        assert!(all.len() > 20_000 && all.iter().all(|e| e.1 != 0));
        assert_eq!(by_rows(chunks), all);
        assert!(by_rows(Vec::new()).is_empty());
    }
}
