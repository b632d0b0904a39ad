//! Where a piece holds light that one radiance per piece misplaces: the pieces [`super::Bake::split`]
//! cuts further (issue 13: light trapped in a 1 cm gap escaping into the room).
//!
//! A piece is solved as one radiance sent evenly from all of it. Where part of it faces
//! something closer than the piece is wide (a panel 1 cm below a ceiling, a box resting on a
//! floor) and the rest faces the room, the two parts gather different light, and the light the
//! near part reflects goes back to what is near, physically; solved as one piece, the mean of
//! both is sent everywhere, so the near part's light leaks into the room (or the room's into
//! the gap). Every segment of a line leaving a piece tells both what it faces and how far:
//! split at the piece's width into `near` and `far`, with shares `s` and `1 − s` and mean
//! gathered luminances `L_n` and `L_f`, the flux the piece sends to the far side in the wrong
//! amount is about
//!
//!   `A · ρ · s (1 − s) · |L_n − L_f|`
//!
//! (the near part, area ≈ `s·A`, sends `ρ·L̄` where it physically sends its own `ρ·L_n` to what
//! is near; the share `1 − s` of it that the model sends far is misplaced). The difference is
//! taken less three times its standard error ([`SIGNIFICANCE`]), so that noise alone seldom
//! scores. A piece's score falls
//! with its area as it is cut, while the share across a gap's rim stays: the cuts follow the
//! rim down until its pieces hold too little flux to matter.
//!
//! Inside a gap the light falls off over about the gap's height, and pieces that small need
//! more crossings than the global lines give them: [`regions`] finds the gaps, where
//! [`super::Bake::split`] makes the lines denser and cuts every piece as far as its crossings
//! allow.

use glam::DVec3;
use rayon::prelude::*;

use super::PIECE_CROSSINGS;
use crate::lines::Bundle;
use crate::output::tonemap::luminance;
use crate::scene::refine::{Corners, Refinement};
use crate::scene::{Bounds, Scene};
use crate::solve::tally::{FixedLight, HIDDEN, MAX_PATCHES, walk_from};
use crate::timeline::IntersectionList;
use crate::trace::SurfaceTable;

/// Standard errors a piece's near and far light must differ by before any of it counts: noise
/// alone passes 3σ in about one piece in 370 (a side whose segments all meet one neighbour
/// shows no spread, hence at least [`PIECE_CROSSINGS`] segments on each side).
pub const SIGNIFICANCE: f64 = 3.0;

/// Per piece, the segments leaving it split by length at its width, near then far: the
/// segments that count (their line's weight is not 0), and in fixed point the weighted sums of
/// one, the gathered luminance and its square, and of the weight squared (for the weighted
/// mean's variance); and the segments across a contact.
#[derive(Clone, Copy, Default)]
struct Sides {
    count: [u64; 2],
    weight: [u64; 2],
    sum: [u128; 2],
    square: [u128; 2],
    weight2: [u64; 2],
    hidden: u64,
    /// The near segments that meet a face turned back towards the piece ([`FACING`]), and
    /// their lengths in fixed point ([`LENGTH_UNIT`]).
    facing: u64,
    near_length: u128,
}

/// The most the cosine between a piece's normal and that of the face a near segment meets may
/// be for the segment to cross a gap ([`Piece::near`]): faces turned back towards each other
/// (a ceiling over a housing's top, cosine −1), not the two walls of a corner (0).
pub const FACING: f64 = -0.5;

/// The unit of [`Sides::near_length`]: sums of lengths in whole units do not depend on the
/// order threads add them in.
const LENGTH_UNIT: f64 = (1u64 << 40) as f64;

impl Sides {
    fn add(&mut self, other: &Self) {
        for k in 0..2 {
            self.count[k] += other.count[k];
            self.weight[k] += other.weight[k];
            self.sum[k] += other.sum[k];
            self.square[k] += other.square[k];
            self.weight2[k] += other.weight2[k];
        }
        self.hidden += other.hidden;
        self.facing += other.facing;
        self.near_length += other.near_length;
    }
}

/// What the lines say of a piece at frame 0 ([`misplaced`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Piece {
    /// The flux it misplaces (module docs).
    pub score: f64,
    /// The segments leaving it that count, as so many of equal weight (Kish's effective
    /// sample size: a piece crossed by a gap's dense lines and a few global ones counts about
    /// as the global ones).
    pub segments: u64,
    /// The share of those, contacts apart, shorter than the piece is wide and meeting a face
    /// turned back towards it ([`FACING`]): what faces something that close across a gap
    /// ([`regions`]).
    pub near: f64,
    /// The mean length of those near segments (normalised units): about twice the distance
    /// to what the piece faces, for a gap of parallel faces.
    pub near_length: f64,
}

impl Piece {
    /// Whether it lies in a gap: enough of its segments ([`NEAR_SEGMENTS`]) and most of them
    /// ([`NEAR_SHARE`]) near and facing back.
    #[must_use]
    pub fn in_gap(&self) -> bool {
        self.segments >= NEAR_SEGMENTS && self.near >= NEAR_SHARE
    }
}

/// Each piece's misplaced flux (module docs) and the segments leaving it, at frame 0, with
/// `gathered(j)` the luminance of piece `j` (the patches' solution will do: the score needs
/// what each piece faces, not its own detail) and `sky` the sky's luminance. Segments count
/// their line's weight ([`IntersectionList::line_weights`]).
pub fn misplaced(
    scene: &Scene,
    table: &SurfaceTable,
    list: &IntersectionList,
    gathered: &(dyn Fn(u32) -> f64 + Sync),
    sky: f64,
) -> Vec<Piece> {
    Walked::new((scene, table), (list, None), gathered, sky).pieces(scene)
}

/// The segments leaving every piece of a scene, walked from the lines at frame 0: what
/// [`misplaced`] scores. A round of [`super::Bake::split`] cuts a few triangles; the pieces
/// of the others leave by the same segments to the same patches (a piece's score reads the
/// luminance of the patch a segment meets, not of its piece), so [`Walked::after`] walks
/// only the lines that cross a cut triangle, for its halves.
pub struct Walked {
    sides: Vec<Sides>,
    /// The luminance of one unit of the sides' sums ([`FixedLight::unit`]).
    unit: f64,
}

impl Walked {
    /// Every piece of `scene` (its triangles in `table`) walked along the lines of `list`
    /// (their bundles, if already generated, in line order), `gathered` and `sky` as for
    /// [`misplaced`].
    pub fn new(
        (scene, table): (&Scene, &SurfaceTable),
        (list, bundles): (&IntersectionList, Option<&[Bundle]>),
        gathered: &(dyn Fn(u32) -> f64 + Sync),
        sky: f64,
    ) -> Self {
        let (sides, unit) = walk_sides((scene, table), (list, bundles), (gathered, sky), None);
        Self { sides, unit }
    }

    /// The pieces of `scene` (the scene these were walked on, cut by `refinement`, its
    /// triangles in `table`): the sides of the pieces of triangles not cut are carried over,
    /// the halves of the cut ones walked along the lines that cross them. The same as
    /// [`Walked::new`] on the cut scene, at the cost of the lines the cuts touch.
    pub fn after(
        &self,
        (scene, table): (&Scene, &SurfaceTable),
        (list, bundles): (&IntersectionList, Option<&[Bundle]>),
        (gathered, sky): (&(dyn Fn(u32) -> f64 + Sync), f64),
        refinement: &Refinement,
    ) -> Self {
        // The pieces on a cut triangle's halves (a merged patch with one among its
        // triangles), walked again; the others carried over.
        let faces = table.faces();
        let mut cut = vec![true; faces.len()];
        for (_, new) in refinement.kept() {
            cut[new as usize] = false;
        }
        let mut fresh = vec![false; scene.patches.len()];
        for (f, _) in faces.iter().zip(&cut).filter(|(_, cut)| **cut) {
            [Some(f.front), f.back]
                .into_iter()
                .flatten()
                .for_each(|p| fresh[p as usize] = true);
        }
        let (mut sides, unit) = walk_sides(
            (scene, table),
            (list, bundles),
            (gathered, sky),
            Some(&fresh),
        );
        // The same patches' luminances: the same unit.
        debug_assert_eq!(unit, self.unit);
        let parents = refinement.parents();
        for (p, fresh) in fresh.iter().enumerate() {
            if !fresh {
                sides[p] = self.sides[parents[p] as usize];
            }
        }
        Self { sides, unit }
    }

    /// What the walked segments say of each piece of `scene` (the scene they were walked on).
    pub fn pieces(&self, scene: &Scene) -> Vec<Piece> {
        (scene.patches.iter())
            .zip(&self.sides)
            .map(|(p, s)| {
                let rho = luminance(scene.materials[p.material as usize].reflectance);
                s.piece(p.area, rho, self.unit)
            })
            .collect()
    }
}

/// The sides of every piece of `scene` ([`Walked::new`]); with `fresh`, only of the pieces it
/// marks, from the lines crossing one of them at frame 0 (the others' are left empty).
fn walk_sides(
    (scene, table): (&Scene, &SurfaceTable),
    (list, bundles): (&IntersectionList, Option<&[Bundle]>),
    (gathered, sky): (&(dyn Fn(u32) -> f64 + Sync), f64),
    fresh: Option<&[bool]>,
) -> (Vec<Sides>, f64) {
    let (width, normal) = geometry(scene, table);
    // Sums in fixed point: the cuts are the same on any machine.
    let pieces = scene.patches.len();
    let light = FixedLight::new(gathered, pieces, sky);
    let value = |to| light.value(to);
    let surfaces = table.surfaces();
    let weights = list.line_weights();
    // Each piece walked: its place among those summed (every piece, or the fresh ones alone,
    // whose sums then take little memory however many pieces the scene has).
    let (slot, walked): (Option<Vec<u32>>, usize) = match fresh {
        None => (None, pieces),
        Some(fresh) => {
            let mut next = 0;
            let slot = (fresh.iter())
                .map(|&f| {
                    if f {
                        next += 1;
                        next - 1
                    } else {
                        u32::MAX
                    }
                })
                .collect();
            (Some(slot), next as usize)
        }
    };
    let slot_of = |piece: u32| match &slot {
        None => Some(piece as usize),
        Some(slot) => Some(slot[piece as usize] as usize).filter(|&k| k != u32::MAX as usize),
    };
    let walks = |piece: u32| slot_of(piece).is_some();
    // The triangles with a face to walk.
    let crossed: Option<Vec<bool>> = fresh.map(|_| {
        (table.faces().iter())
            .map(|f| walks(f.front) || f.back.is_some_and(walks))
            .collect()
    });
    // Whether line `l` crosses a triangle with a face to walk at frame 0 (its moving
    // crossings at frame 0 come first), read where the crossings are.
    let crosses = |l: usize, crossed: &[bool]| {
        let moving = list.moving_hits(l).iter().take_while(|h| h.frame == 0);
        (list.static_hits(l).iter()).any(|h| crossed[h.surface() as usize])
            || moving.map(|h| h.hit).any(|h| crossed[h.surface() as usize])
    };
    let summed = list
        .bundles_kept(scene, bundles)
        .fold(
            || (vec![Sides::default(); walked], Vec::new()),
            |(mut acc, mut hits), (first, bundle)| {
                let surfaces = surfaces.along(bundle.direction);
                for i in 0..bundle.origins.len() {
                    let w = u64::from(weights[first + i]);
                    if w == 0 {
                        continue;
                    }
                    if let Some(crossed) = &crossed
                        && !crosses(first + i, crossed)
                    {
                        continue;
                    }
                    list.frame_hits(first + i, 0, &mut hits);
                    walk_from(&hits, &surfaces, |from, to, at, length| {
                        let Some(k) = slot_of(from) else {
                            return;
                        };
                        let side = usize::from(length >= width[at.surface() as usize]);
                        let g = value(to);
                        let s = &mut acc[k];
                        s.hidden += u64::from(to == HIDDEN);
                        // Near, and facing back: across a gap, not into a corner.
                        let facing = (to as usize) < MAX_PATCHES
                            && normal[from as usize].dot(normal[to as usize]) < FACING;
                        if side == 0 && facing {
                            s.facing += 1;
                            s.near_length += (f64::from(length) * LENGTH_UNIT) as u128;
                        }
                        s.count[side] += 1;
                        s.weight[side] += w;
                        s.sum[side] += u128::from(w * g);
                        s.square[side] += u128::from(w * g) * u128::from(g);
                        s.weight2[side] += w * w;
                    });
                }
                (acc, hits)
            },
        )
        .map(|(acc, _)| acc)
        .reduce(
            || vec![Sides::default(); walked],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(x, y)| x.add(y));
                a
            },
        );
    let sides = match &slot {
        None => summed,
        Some(slot) => (slot.iter())
            .map(|&k| summed.get(k as usize).copied().unwrap_or_default())
            .collect(),
    };
    (sides, light.unit)
}

impl Sides {
    /// What these segments say of a piece of `area` and luminous reflectance `rho`.
    fn piece(&self, area: f64, rho: f64, unit: f64) -> Piece {
        let s = self;
        // The segments as so many of equal weight (Kish's effective sample size): a piece
        // beside a gap is crossed by many of its dense lines, each weighing a fraction.
        let effective = |k: usize| {
            let w = s.weight[k] as f64;
            if w > 0.0 {
                w * w / s.weight2[k] as f64
            } else {
                0.0
            }
        };
        let segments = (effective(0) + effective(1)).round() as u64;
        let seen = s.count[0] + s.count[1] - s.hidden;
        let near_count = s.facing;
        let near = if seen > 0 {
            near_count as f64 / seen as f64
        } else {
            0.0
        };
        let near_length = if near_count > 0 {
            s.near_length as f64 / LENGTH_UNIT / near_count as f64
        } else {
            0.0
        };
        // Both sides known from a piece's worth of segments, or no score.
        if (0..2).any(|k| effective(k) < PIECE_CROSSINGS) || rho <= 0.0 {
            return Piece {
                score: 0.0,
                segments,
                near,
                near_length,
            };
        }
        let (mean, variance): (Vec<f64>, Vec<f64>) = (0..2)
            .map(|k| {
                let (n, w) = (s.count[k] as f64, s.weight[k] as f64);
                let mean = s.sum[k] as f64 * unit / w;
                let square = s.square[k] as f64 * unit * unit / w;
                // The variance of the weighted mean: the sample variance (unbiased for
                // equal weights) times Σw² / (Σw)².
                let spread = (square - mean * mean).max(0.0) * n / (n - 1.0);
                (mean, spread * s.weight2[k] as f64 / (w * w))
            })
            .unzip();
        let difference =
            (mean[0] - mean[1]).abs() - SIGNIFICANCE * (variance[0] + variance[1]).sqrt();
        let share = s.weight[0] as f64 / (s.weight[0] + s.weight[1]) as f64;
        Piece {
            score: area * rho * share * (1.0 - share) * difference.max(0.0),
            segments,
            near,
            near_length,
        }
    }
}

/// Each triangle's width (its longest edge) and each patch's normal (its front face's, or
/// the opposite for a back face; a merged patch's last face's), at frame 0 in normalised
/// space.
fn geometry(scene: &Scene, table: &SurfaceTable) -> (Vec<f32>, Vec<DVec3>) {
    let corners = Corners::new(scene);
    let faces = table.faces();
    let mut normals = vec![DVec3::ZERO; scene.patches.len()];
    let width = (0..table.triangles() as u32)
        .map(|g| {
            let c = corners
                .posed(g, Some(0))
                .unwrap_or_else(|| corners.own(g).map(|p| p.as_dvec3()));
            let n = (c[1] - c[0]).cross(c[2] - c[0]).normalize_or_zero();
            let f = faces[g as usize];
            normals[f.front as usize] = n;
            if let Some(back) = f.back {
                normals[back as usize] = -n;
            }
            let edge = |a: DVec3, b: DVec3| a.distance(b);
            edge(c[0], c[1]).max(edge(c[1], c[2])).max(edge(c[2], c[0])) as f32
        })
        .collect();
    (width, normals)
}

/// The share of a piece's segments (contacts apart) that must be shorter than the piece is
/// wide for it to lie in a gap ([`regions`]): it faces, over most of what it sees, something
/// closer than its own size, so one radiance over it cannot hold the light's fall into the gap.
pub const NEAR_SHARE: f64 = 0.75;

/// The fewest segments a piece needs for its near share to count ([`regions`]).
pub const NEAR_SEGMENTS: u64 = 4;

/// The most dense regions a bake makes ([`regions`]): every line is tested against each.
pub const MAX_REGIONS: usize = 64;

/// How many times denser the lines through a gap are, at most ([`regions`]).
pub const MAX_FACTOR: u32 = 16;

/// The most a bake's dense lines may add to its lines ([`regions`]), as a share of them.
pub const DENSE_SHARE: f64 = 0.5;

/// Where the lines should be denser, and by how much: the gaps, boxes around the static pieces
/// that lie in one ([`NEAR_SHARE`]), each box grown by the mean length of its near segments so
/// that the two faces of a gap meet, overlapping boxes merged. Light trapped in a gap falls off over about
/// the gap's height; a piece much wider than that spreads what enters at the rim over all of
/// it and sends it on, so light leaks in deep (a fixture's housing, the ceiling above it): the
/// pieces there must be about as small as the gap is high, and need the lines to be known.
///
/// The factor is the largest power of two up to [`MAX_FACTOR`] whose dense lines add at most
/// [`DENSE_SHARE`] of the lines (the lines meeting a box scale with its surface area), the
/// regions kept being the [`MAX_REGIONS`] holding the most gap area; none if even twice as
/// dense costs more. `lines` (the global lines) bounds it too: the tallies' counts, every
/// line's weight summed, stay below 2^32.
pub fn regions(scene: &Scene, pieces: &[Piece], lines: usize) -> (Vec<Bounds>, u32) {
    let corners = Corners::new(scene);
    let in_gap = |p: u32| pieces[p as usize].in_gap();
    // (box, gap area) of every static triangle with a face in a gap, grown by the mean length
    // of its near segments (about twice the gap's height): the faces across the gap meet.
    let mut boxes: Vec<(Bounds, f64)> = (scene.statics.faces.iter().enumerate())
        .filter_map(|(t, f)| {
            let pad = [Some(f.front), f.back]
                .into_iter()
                .flatten()
                .filter(|&p| in_gap(p))
                .map(|p| pieces[p as usize].near_length)
                .reduce(f64::max)?;
            let c = corners.own(t as u32).map(|p| p.as_dvec3());
            let area = 0.5 * (c[1] - c[0]).cross(c[2] - c[0]).length();
            let pad = DVec3::splat(pad);
            let min = c[0].min(c[1]).min(c[2]) - pad;
            let max = c[0].max(c[1]).max(c[2]) + pad;
            Some((Bounds { min, max }, area))
        })
        .collect();
    // Merge overlapping boxes until none overlap.
    let overlap = |a: &Bounds, b: &Bounds| a.min.cmple(b.max).all() && b.min.cmple(a.max).all();
    loop {
        boxes.sort_by(|a, b| a.0.min.x.total_cmp(&b.0.min.x));
        let mut merged: Vec<(Bounds, f64)> = Vec::with_capacity(boxes.len());
        let mut any = false;
        for (b, area) in boxes {
            match merged.iter_mut().rev().find(|(m, _)| overlap(m, &b)) {
                Some((m, a)) => {
                    *m = Bounds {
                        min: m.min.min(b.min),
                        max: m.max.max(b.max),
                    };
                    *a += area;
                    any = true;
                }
                None => merged.push((b, area)),
            }
        }
        boxes = merged;
        if !any {
            break;
        }
    }
    boxes.sort_by(|a, b| b.1.total_cmp(&a.1));
    boxes.truncate(MAX_REGIONS);
    // Clipped to the scene's box, where the lines are.
    let regions: Vec<Bounds> = boxes
        .iter()
        .map(|(b, _)| Bounds {
            min: b.min.max(scene.bounds.min),
            max: b.max.min(scene.bounds.max),
        })
        .collect();
    let measure: f64 = regions.iter().map(Bounds::surface_area).sum();
    let affordable = DENSE_SHARE * scene.bounds.surface_area() / measure.max(f64::MIN_POSITIVE);
    // The tallies count in u32: every line's weight summed stays below 2^32 for the lines
    // there are and as many again.
    let most = f64::from(u32::MAX) / (2.0 * lines.max(1) as f64);
    let factor = (1..=MAX_FACTOR.ilog2())
        .map(|k| 1u32 << k)
        .take_while(|&f| f64::from(f) <= affordable.min(most))
        .last();
    match factor {
        Some(f) if !regions.is_empty() => (regions, f),
        _ => (Vec::new(), 1),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::Bake;
    use crate::scene::refine;
    use crate::timeline::{Crossings, LineParams};

    /// The split moves the later frames' crossings once, through every round's cuts
    /// ([`refine::Chain`]), where it moved every frame's after each cut: on the moving Cornell
    /// box (a rigid block, 13 frames), three rounds of cuts (every third triangle, then every
    /// fifth piece twice), each moving crossing ends on the piece moving it after each cut
    /// puts it. Fails when the chain measures a point on the frame-0 pose.
    #[test]
    fn the_later_frames_moved_once_land_where_moving_them_after_each_cut_puts_them() {
        let path = format!("{}/scenes/cornell_moving.gltf", env!("CARGO_MANIFEST_DIR"));
        let options = crate::loader::LoadOptions {
            fps: 6.0,
            ..Default::default()
        };
        let scene = crate::loader::load(&std::fs::read(path).unwrap(), &options).unwrap();
        assert!(scene.frames.count > 10);
        let bake = Bake::trace(
            scene,
            &LineParams {
                lines: 40_000,
                seed: 3,
            },
        )
        .unwrap();
        let (mut each, mut once) = (bake.list.clone(), bake.list.clone());
        let mut scene = bake.scene.clone();
        let mut chain = refine::Chain::default();
        for step in [3, 5, 5] {
            let table = SurfaceTable::new(&scene);
            let order: Vec<(u32, u32)> = (0..table.triangles() as u32)
                .step_by(step)
                .map(|t| (t, 1))
                .collect();
            let cuts = refine::within_budget(&scene, &order, usize::MAX);
            let (next, refinement) = refine::cut(&scene, &cuts);
            Bake::move_crossings(&mut each, (&scene, None), &refinement, Crossings::All);
            let zero = Crossings::AtFrameZero;
            Bake::move_crossings(&mut once, (&scene, None), &refinement, zero);
            chain.push(&scene, refinement);
            scene = next;
        }
        once.relabel((&bake.scene, None), Crossings::Later, |hit, f, at| {
            chain.locate(&scene, hit.surface(), f.unwrap_or_default(), at)
        });
        let mut later = 0;
        for line in 0..each.lines() {
            assert_eq!(each.static_hits(line), once.static_hits(line));
            let (a, b) = (each.moving_hits(line), once.moving_hits(line));
            assert_eq!(a.len(), b.len());
            for (a, b) in a.iter().zip(b) {
                assert_eq!((a.frame, a.hit), (b.frame, b.hit), "line {line}");
                later += usize::from(a.frame > 0);
            }
        }
        eprintln!("{later} crossings at later frames");
        assert!(later > 10_000);
    }

    /// A round of the split walks the lines only for the pieces the last round cut and
    /// carries the others' sides over ([`Walked::after`]): every piece's score, segments and
    /// near share are those of a whole walk of the cut scene. On the moving Cornell box (a
    /// rigid block resting on the floor: contacts, moving crossings at frame 0) and the panel
    /// room (a gap under the panel), every third triangle cut with the cuts its neighbours
    /// need.
    #[test]
    fn a_rounds_walk_of_the_cut_pieces_scores_as_a_whole_walk_does() {
        for (name, lines) in [("cornell_moving", 60_000), ("panel_room", 60_000)] {
            let path = format!("{}/scenes/{name}.gltf", env!("CARGO_MANIFEST_DIR"));
            let options = crate::loader::LoadOptions {
                fps: 2.0,
                ..Default::default()
            };
            let scene = crate::loader::load(&std::fs::read(path).unwrap(), &options).unwrap();
            let mut bake = Bake::trace(scene, &LineParams { lines, seed: 5 }).unwrap();
            let scene = bake.scene.clone();
            // What each patch gathers: any fixed luminance per patch, the sky's its own.
            let light = |p: u32| f64::from(p % 7) * 0.3;
            let table = SurfaceTable::new(&scene);
            let walked = Walked::new((&scene, &table), (&bake.list, None), &light, 0.5);
            let order: Vec<(u32, u32)> = (0..table.triangles() as u32)
                .step_by(3)
                .map(|t| (t, 1))
                .collect();
            let cuts = refine::within_budget(&scene, &order, usize::MAX);
            let (next, refinement) = refine::cut(&scene, &cuts);
            Bake::move_crossings(&mut bake.list, (&scene, None), &refinement, Crossings::All);
            let parents = refinement.parents();
            let gathered = |k: u32| light(parents[k as usize]);
            let table = SurfaceTable::new(&next);
            let lines = (&bake.list, None);
            let carried = walked.after((&next, &table), lines, (&gathered, 0.5), &refinement);
            let whole = Walked::new((&next, &table), lines, &gathered, 0.5);
            let (carried, whole) = (carried.pieces(&next), whole.pieces(&next));
            let kept = refinement.kept().count();
            let scored = whole.iter().filter(|p| p.score > 0.0).count();
            eprintln!(
                "{name}: {} pieces, {kept} triangles kept whole, {scored} pieces scored",
                next.patches.len()
            );
            assert!(kept > 0 && kept < table.triangles() && scored > 0);
            for (k, (c, w)) in carried.iter().zip(&whole).enumerate() {
                assert_eq!(c, w, "{name}: piece {k} (of {})", parents[k]);
            }
        }
    }
}
