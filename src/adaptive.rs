//! Adaptive patches (`patch_size=auto`): patches cut where the light needs them and merged
//! where it does not, decided from the lines already traced.
//!
//! A patch holds one radiance; where the light arriving on it differs across it, the light it
//! sends on is misplaced (a ceiling triangle lit in a 1 cm gap behind a lamp re-emits that
//! light into the room) and its one value hides the difference. Every segment of a line
//! gathers, at the crossing it leaves a patch from, the radiance of the patch (or sky) at its
//! other end. Each patch is scored on the pieces its next [`DEPTH`] longest-edge bisections
//! would make: the segments leaving each piece estimate the radiance that piece gathers, with
//! their own standard error, and the light that reaches it straight from the punctual lights
//! and the sampled emitters (which the lines do not carry) is sampled on the piece itself, a
//! few shadow rays each: a lamp's pool of light on a wall and the gradient under a ceiling
//! panel count. A node of that tree whose pieces gather differently beyond their
//! noise (a χ² test at [`Adaptive::significance`]) is cut, those that would misplace the most
//! reflected flux (area × reflectance × the spread of their pieces' light) first, up to the
//! patch budget (the cuts neighbours need counted). Each round solves a few
//! frames, scores, cuts, and moves the crossings to the new patches ([`Bake::cut`]): no line
//! is traced again. The pieces take their patch's direct light for the next round's solves;
//! it is sampled again once, for the final patches. The rounds stop when one adds under 1% of
//! the patches, or at the budget.
//!
//! Then coplanar neighbours are merged into patches of several faces (`merges`) where the
//! same rule would not cut them apart and what they face is no closer than they are wide, and
//! while the patches are over the budget (a scene of more triangles than it): a wall lit
//! smoothly is a few large patches, each crossed by more lines (less noise), and the patches
//! freed are not spent where nothing changes.
//!
//! One set of patches serves the whole timeline (patch ids are stable across frames): the
//! scores are taken at up to [`FRAMES`] frames spread over it, and a patch is cut if any of
//! them needs it.

use std::time::Instant;

use glam::{DVec3, Vec3};
use rayon::prelude::*;
use serde::Serialize;

use crate::bake::{Bake, Lights};
use crate::control::{Control, TraceError};
use crate::direct::{Part, parts_irradiance};
use crate::output::tonemap::{LUMINANCE, luminance};
use crate::scene::refine::{self, Corners, barycentric, longest_edge};
use crate::scene::subdivide::normal_and_area;
use crate::solve::SolveParams;
use crate::solve::tally::{FixedLight, walk_from};
use crate::trace::coincident::mix;

/// Frames scored per round at most, spread over the distinct frames of the timeline.
pub const FRAMES: usize = 3;

/// How adaptive patches are chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Adaptive {
    /// Most patches the cuts may reach, the cuts neighbours need to leave no T-junction
    /// included.
    pub budget: usize,
    /// Rounds of solving, scoring and cutting at most; each can cut a patch [`DEPTH`] times.
    pub rounds: usize,
    /// A node is cut when the radiance its pieces gather varies beyond their noise: the χ²
    /// of their differences above its mean by this many of its standard deviations.
    pub significance: f64,
    /// ... and each of its halves has at least this many crossings times the square of the
    /// share of its light the lines carry (below it the estimates say too little, and the
    /// halves would be noisier still; a half lit mostly straight from a lamp is known from its
    /// direct light, sampled on it, and the lines' noise is their share of its value).
    pub min_crossings: f64,
    /// ... and each half's mean gathered radiance has a relative standard error of at most
    /// this: where the lines cannot yet tell a half's light to this precision, its pieces
    /// would show more noise than the variation they resolve (measured: 0.05 cuts too little
    /// on the level, no limit too much on the Cornell box's dim corners).
    pub precision: f64,
    /// Coplanar neighbours are merged into one patch while the merged patch spans at most this
    /// (its box's diagonal, in the scene's normalised units: its bounding sphere has radius 1)
    /// and the cut rule would not cut it again (`merges`, in [`adapt`]); 0 merges nothing.
    pub merge_extent: f64,
}

impl Adaptive {
    /// The standard choice for a bake of `lines` lines: a budget of one patch per
    /// [`LINES_PER_PATCH`] lines (at least the scene's own patches), six rounds, cuts beyond
    /// 3σ with 32 crossings per half, each half known to 10% (`bench-patches` measures the
    /// choice).
    #[must_use]
    pub fn for_lines(lines: u64, patches: usize) -> Self {
        Self {
            budget: ((lines / LINES_PER_PATCH) as usize).max(patches),
            rounds: 6,
            significance: 3.0,
            min_crossings: 32.0,
            precision: 0.1,
            merge_extent: MERGE_EXTENT,
        }
    }

    /// The same with `budget` as the budget, if given (`patch_budget`).
    #[must_use]
    pub fn with_budget(self, budget: Option<usize>) -> Self {
        Self {
            budget: budget.unwrap_or(self.budget),
            ..self
        }
    }

    /// The same with the budget at most `max_patches` (a server's or a load's limit).
    #[must_use]
    pub fn within(self, max_patches: usize) -> Self {
        Self {
            budget: self.budget.min(max_patches),
            ..self
        }
    }
}

/// Lines per patch of the standard budget ([`Adaptive::for_lines`]).
pub const LINES_PER_PATCH: u64 = 200;

/// The standard [`Adaptive::merge_extent`]: as wide as the scene's radius, so that the rule,
/// not the size, decides. Measured with `bench-patches` at 1M lines (an earlier rule, on the
/// radiances alone): 0.25 gave the level 963 patches at 24.4% per-patch error, 0.5 797 at
/// 22.9%, 1 776 at 23.0%; the Cornell box 368 at 2.4% with 0.5, 352 at 2.3% with 1; the panel
/// room 420 at 1.8% and 284 at 1.7%.
pub const MERGE_EXTENT: f64 = 1.0;

/// What one round did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Round {
    /// Patches before the round.
    pub patches: usize,
    /// Cuts decided (at most [`DEPTH`] levels per patch): nodes whose pieces differ beyond
    /// their noise, within the budget.
    pub significant: usize,
    /// Patches added by the round's cuts.
    pub added: usize,
    /// Patches merged away by the round (the last one merges).
    pub removed: usize,
    /// Seconds the round took (solve, scores, cuts, direct light); not serialised with the
    /// rest, which is the same on every run (`timings.json` has them).
    #[serde(skip)]
    pub seconds: f64,
}

/// Cuts `bake`'s patches where the light needs them ([`Adaptive`]); `solve` gives the sky and
/// the stopping rule of the scoring solves. Returns what each round did.
///
/// # Errors
/// [`TraceError::Cancelled`] when `control` is cancelled (the bake is then left with the cuts
/// of the rounds already done).
pub fn adapt(
    bake: &mut Bake,
    auto: &Adaptive,
    solve: &SolveParams,
    control: &Control,
) -> Result<Vec<Round>, TraceError> {
    // The rounds solve the patches at every frame.
    bake.complete_lights(control)?;
    let mut rounds = Vec::new();
    // Cuts, then merges; once more if the merges freed budget the cuts had used up (the
    // patches they freed go where the light needs them).
    for cycle in 0..CYCLES {
        let bound = cut_rounds(bake, auto, solve, control, &mut rounds)?;
        if auto.merge_extent <= 0.0 {
            break;
        }
        control.check()?;
        let started = Instant::now();
        let patches = bake.scene.patches.len();
        let into = merges(bake, auto, solve);
        let removed = bake.merge(&into, control)?;
        rounds.push(Round {
            patches,
            significant: 0,
            added: 0,
            removed,
            seconds: started.elapsed().as_secs_f64(),
        });
        let left = bake.scene.patches.len();
        if !bound || removed < patches / 100 || left + left / 100 >= auto.budget || cycle > 0 {
            break;
        }
    }
    Ok(rounds)
}

/// Cut-and-merge cycles of [`adapt`] at most: the second only when the merges freed budget that
/// the cuts had used up.
const CYCLES: usize = 2;

/// The rounds of cuts of [`adapt`], then the pieces' own direct light; whether they stopped at
/// the budget (rather than for want of cuts worth making).
fn cut_rounds(
    bake: &mut Bake,
    auto: &Adaptive,
    solve: &SolveParams,
    control: &Control,
    rounds: &mut Vec<Round>,
) -> Result<bool, TraceError> {
    let mut bound = false;
    for _ in 0..auto.rounds {
        control.check()?;
        let started = Instant::now();
        let patches = bake.scene.patches.len();
        // A round costs solves and a pass over the lines: not for the last 1% of the budget.
        if patches + patches / 100 >= auto.budget {
            bound = true;
            break;
        }
        let ranked = mark(bake, auto, solve);
        let marked = refine::within_budget(&bake.scene, &ranked, auto.budget);
        let significant: usize = marked.iter().map(|m| m.count_ones() as usize).sum();
        bound = significant < ranked.len();
        let added = if significant == 0 {
            0
        } else {
            bake.cut(&marked, Lights::Inherit, control)?
        };
        rounds.push(Round {
            patches,
            significant,
            added,
            removed: 0,
            seconds: started.elapsed().as_secs_f64(),
        });
        // Rounds find fewer cuts as they go: after one that added under 1%, another is not
        // worth its solves.
        if added == 0 || added < patches / 100 {
            break;
        }
    }
    // The rounds scored with each piece lit as its patch was; the pieces' own light once.
    let started = Instant::now();
    bake.sample_lights(control)?;
    if let Some(last) = rounds.last_mut() {
        last.seconds += started.elapsed().as_secs_f64();
    }
    Ok(bound)
}

/// Which patches to merge: old patch `p` becomes patch `into[p]` (dense, in the order of each
/// merged patch's first member). Faces are merged with a neighbour across an edge when both
/// are of one source primitive (of one node), one material that does not emit, and one
/// plane facing one way, while the merged patch spans at most [`Adaptive::merge_extent`] and,
/// at every scored frame, the cut rule would not cut it again: its members' radiances (each
/// with its standard error from the solve's replicas) do not differ beyond their noise, or
/// differ by less than the noise they would show apart (as [`variation`] decides a cut).
/// Most alike neighbours first (least z² between their radiances, most over the frames); and
/// while the patches are more than [`Adaptive::budget`], the most alike whatever the rule.
fn merges(bake: &Bake, auto: &Adaptive, solve: &SolveParams) -> Vec<u32> {
    let scene = &bake.scene;
    let faces = bake.tracer().faces();
    let corners = Corners::new(scene);
    let patches = scene.patches.len();
    // Per scored frame and patch, two (value, variance of its estimate) to compare between
    // neighbours (variance infinite when unsampled): the patch's luminance, with its standard
    // error from the solve's replicas; and the mean luminance its crossings gather, the cut
    // rule's own measure, which sees light a patch-constant solution spreads about (the
    // light a ceiling piece in a fixture's gap gathers, against its neighbour's in the room).
    let mut nears = Vec::new();
    let frames: Vec<Vec<[(f64, f64); 2]>> = scored_frames(bake)
        .into_iter()
        .map(|frame| {
            let solution = bake.solve_frame(frame, &scene.materials, solve);
            let (stats, near) = gathered(bake, frame, &solution.radiance, solve.sky);
            nears.push(near);
            (solution.radiance.iter().zip(&solution.stderr))
                .zip(stats.chunks_exact(3 * LEAVES))
                .map(|((&l, e), leaves)| {
                    let v = e.map_or(f64::INFINITY, |e| luminance(e).powi(2));
                    let [n, sum, square] = leaves
                        .chunks_exact(3)
                        .fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]]);
                    let gathered = if n >= 2.0 {
                        let mean = sum / n;
                        (mean, (square / n - mean * mean).max(0.0) / (n - 1.0))
                    } else {
                        (0.0, f64::INFINITY)
                    };
                    [(luminance(l), v), gathered]
                })
                .collect()
        })
        .collect();
    // Each face that may merge: its patch, its plane (unit normal on its side, offset) and its
    // corners at frame 0 in normalised space; and the faces on each edge.
    let mergeable = |p: u32| {
        let m = &scene.materials[scene.patches[p as usize].material as usize];
        !m.is_emitter()
    };
    let mut area = vec![0.0f64; patches];
    let mut boxes = vec![(DVec3::INFINITY, DVec3::NEG_INFINITY); patches];
    let mut planes: Vec<Option<(DVec3, f64)>> = vec![None; patches];
    // Edges keyed by their corners' position bits, in order.
    type Edge = ([u64; 3], [u64; 3]);
    let mut edges: std::collections::HashMap<Edge, Vec<u32>> = Default::default();
    for (g, f) in faces.iter().enumerate() {
        let Some(c) = corners.posed(g as u32, Some(0)) else {
            continue;
        };
        let (normal, a) = normal_and_area(c);
        if normal == DVec3::ZERO {
            continue;
        }
        for (patch, back) in [(Some(f.front), false), (f.back, true)] {
            let Some(p) = patch.filter(|&p| mergeable(p)) else {
                continue;
            };
            let n = if back { -normal } else { normal };
            planes[p as usize] = Some((n, n.dot(c[0])));
            area[p as usize] += a;
            let (lo, hi) = &mut boxes[p as usize];
            for x in c {
                (*lo, *hi) = (lo.min(x), hi.max(x));
            }
            for k in 0..3 {
                let bits = |v: DVec3| v.to_array().map(f64::to_bits);
                let (a, b) = (bits(c[k]), bits(c[(k + 1) % 3]));
                let key = if a <= b { (a, b) } else { (b, a) };
                edges.entry(key).or_default().push(p);
            }
        }
    }
    // Candidate pairs: neighbours across an edge, same object and material, one plane.
    let coplanar = |a: u32, b: u32| {
        let (Some((na, da)), Some((nb, db))) = (planes[a as usize], planes[b as usize]) else {
            return false;
        };
        na.dot(nb) >= 1.0 - 1e-6 && (da - db).abs() <= 1e-6
    };
    // One source primitive (one node: the baked glTF draws a patch with its node), material
    // and object.
    let same = |a: u32, b: u32| {
        let (pa, pb) = (&scene.patches[a as usize], &scene.patches[b as usize]);
        let (sa, sb) = (pa.source, pb.source);
        pa.material == pb.material
            && pa.object == pb.object
            && (sa.node, sa.mesh, sa.primitive) == (sb.node, sb.mesh, sb.primitive)
    };
    let mut pairs: Vec<(f64, u32, u32)> = Vec::new();
    for on_edge in edges.values() {
        for (i, &a) in on_edge.iter().enumerate() {
            for &b in &on_edge[i + 1..] {
                if a != b && same(a, b) && coplanar(a, b) {
                    let z = frames
                        .iter()
                        .flat_map(|f| {
                            (0..2).map(move |k| {
                                let ((ma, va), (mb, vb)) = (f[a as usize][k], f[b as usize][k]);
                                (ma - mb).powi(2) / (va + vb).max(f64::MIN_POSITIVE)
                            })
                        })
                        .fold(0.0, f64::max);
                    pairs.push((z, a.min(b), a.max(b)));
                }
            }
        }
    }
    pairs.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)).then(x.2.cmp(&y.2)));
    pairs.dedup_by(|x, y| (x.1, x.2) == (y.1, y.2));
    // Greedy union, most alike first.
    let mut root: Vec<u32> = (0..patches as u32).collect();
    let mut members: Vec<Vec<u32>> = (0..patches as u32).map(|p| vec![p]).collect();
    fn find(root: &mut [u32], mut p: u32) -> u32 {
        while root[p as usize] != p {
            root[p as usize] = root[root[p as usize] as usize];
            p = root[p as usize];
        }
        p
    }
    // Then, while over the budget (the source's own triangles can be more than it), the most
    // alike neighbours whatever the rule says.
    let mut count = patches;
    for forced in [false, true] {
        for &(_, a, b) in &pairs {
            if forced && count <= auto.budget {
                break;
            }
            let (ra, rb) = (find(&mut root, a), find(&mut root, b));
            let size = members[ra as usize].len() + members[rb as usize].len();
            if ra == rb || size > MAX_MEMBERS {
                continue;
            }
            let union: Vec<u32> = members[ra as usize]
                .iter()
                .chain(&members[rb as usize])
                .copied()
                .collect();
            let (lo, hi) = union
                .iter()
                .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &p| {
                    (lo.min(boxes[p as usize].0), hi.max(boxes[p as usize].1))
                });
            // Not where what the members face is closer than the merged patch is wide: there
            // the light changes over that distance (a fixture's gap under a ceiling), and the
            // lines' own estimates cannot show it (the gap's patches exchange their light
            // with each other, alike whatever its true shape).
            let diameter = lo.distance(hi);
            if diameter > auto.merge_extent
                || union.iter().any(|&p| {
                    nears
                        .iter()
                        .any(|n| n[p as usize].closer_than(diameter) > NEAR_SHARE)
                })
            {
                continue;
            }
            let alike = forced
                || frames.iter().all(|f| {
                    (0..2).all(|k| {
                        let pieces: Vec<(f64, f64, f64)> = union
                            .iter()
                            .map(|&p| (area[p as usize], f[p as usize][k].0, f[p as usize][k].1))
                            .collect();
                        !worth_apart(&pieces, auto)
                    })
                });
            if alike {
                let (keep, gone) = (ra.min(rb), ra.max(rb));
                root[gone as usize] = keep;
                members[keep as usize] = union;
                members[gone as usize] = Vec::new();
                count -= 1;
            }
        }
    }
    // Dense new ids, in the order of each merged patch's first member.
    let roots: Vec<u32> = (0..patches as u32).map(|p| find(&mut root, p)).collect();
    crate::scene::refine::dense_ids(roots)
}

/// Most patches merged into one: each merge tests every member (a floor of a dense export,
/// all alike, would otherwise cost its faces squared).
const MAX_MEMBERS: usize = 256;

/// The largest share of a merged patch's view (its members' each) that may lie closer than
/// the merged patch is wide ([`merges`]). Measured with `bench-patches` at 1M lines, without
/// it and with it: the level 855 patches at 17.3% per-patch error and 1,448 at 13.5%; the
/// level under lamps 849 at 31.4% and 1,420 at 30.9%; the Cornell box 354 at 2.3% and 431 at
/// 2.3%; the panel room 310 at 1.7% and 355 at 1.8%.
const NEAR_SHARE: f64 = 0.5;

/// Whether `pieces` (area, radiance, variance of its estimate; infinite when unsampled) are
/// worth keeping apart by the rule that cuts ([`variation`]): they differ beyond their noise
/// (χ² at [`Adaptive::significance`]) and by more than the noise they show apart (weighed by
/// [`NOISE_COST`]). Unsampled pieces follow the others.
fn worth_apart(pieces: &[(f64, f64, f64)], auto: &Adaptive) -> bool {
    let sampled: Vec<&(f64, f64, f64)> = pieces.iter().filter(|p| p.2.is_finite()).collect();
    let total: f64 = sampled.iter().map(|p| p.0).sum();
    if sampled.len() < 2 || total <= 0.0 {
        return false;
    }
    let mean = sampled.iter().map(|p| p.0 * p.1).sum::<f64>() / total;
    let floor = f64::EPSILON * mean * mean + f64::MIN_POSITIVE;
    let chi2: f64 = sampled
        .iter()
        .map(|&&(_, m, v)| (m - mean).powi(2) / v.max(floor))
        .sum();
    let freedom = sampled.len() as f64 - 1.0;
    if chi2 <= freedom + auto.significance * (2.0 * freedom).sqrt() {
        return false;
    }
    let gain: f64 = sampled
        .iter()
        .map(|&&(a, m, v)| a / total * ((m - mean).powi(2) - NOISE_COST * v))
        .sum();
    gain > 0.0
}

/// Up to [`FRAMES`] distinct frames spread over the timeline.
fn scored_frames(bake: &Bake) -> Vec<usize> {
    let representatives = bake.representatives();
    let distinct: Vec<usize> = (0..representatives.len())
        .filter(|&f| representatives[f] == f)
        .collect();
    let n = distinct.len().min(FRAMES);
    let mut frames: Vec<usize> = (0..n)
        .map(|k| distinct[k * (distinct.len() - 1) / (n - 1).max(1)])
        .collect();
    frames.dedup();
    frames
}

/// Levels of cuts one round may decide for a patch: it is scored on the bisection tree of
/// this depth (2^DEPTH pieces), all from one solve.
pub const DEPTH: u32 = 3;
/// Pieces of a patch's scoring tree.
const LEAVES: usize = 1 << DEPTH;

/// The cuts worth making this round, as (traced triangle, heap-ordered node of its bisection
/// tree), most worth first, each after its parent.
fn mark(bake: &Bake, auto: &Adaptive, solve: &SolveParams) -> Vec<(u32, u32)> {
    let scene = &bake.scene;
    let faces = bake.tracer().faces();
    // Each patch's face: its traced triangle, and whether it is the back face.
    let mut face_of = vec![(0u32, false); scene.patches.len()];
    for (g, f) in faces.iter().enumerate() {
        for (p, back) in [(Some(f.front), false), (f.back, true)] {
            if let Some(p) = p {
                face_of[p as usize] = (g as u32, back);
            }
        }
    }
    // A merged patch (more than one face) is not cut: its pieces would stay in it.
    let members = refine::members(scene);
    // Each node's area times its reflectance times the spread of its pieces' gathered
    // radiance (the flux it would send to the wrong places), when they differ significantly
    // (most over the frames); 0 otherwise. A black patch has no light to misplace. The order
    // matters only when the budget binds: at a third of the best uniform size's patches it
    // did as well as area × relative variance on the Cornell box and better on the panel
    // room (2.5% against 2.6% and 3.3% against 4.0% for two seeds, `bench-patches
    // --patch-budget 1034`, measured with the reference's own noise estimate, before the
    // bench measured it from two references).
    let nodes = LEAVES;
    let mut priority = vec![0.0f64; scene.patches.len() * nodes];
    let patch_faces = (face_of.as_slice(), members.as_slice());
    for frame in scored_frames(bake) {
        let solution = bake.solve_frame(frame, &scene.materials, solve);
        let (stats, direct) = leaf_light(bake, frame, &solution.radiance, solve.sky, patch_faces);
        priority
            .par_chunks_mut(nodes)
            .zip(stats.par_chunks(3 * LEAVES))
            .zip(direct.par_chunks(LEAVES))
            .enumerate()
            .for_each(|(i, ((priority, leaves), direct))| {
                if members[i] > 1 {
                    return;
                }
                let patch = &scene.patches[i];
                let rho = luminance(scene.materials[patch.material as usize].reflectance);
                let leaves: Vec<Leaf> = (leaves.chunks_exact(3).zip(direct))
                    .map(|(l, &direct)| Leaf {
                        crossings: l[0],
                        sum: l[1],
                        square: l[2],
                        direct,
                    })
                    .collect();
                for (heap, priority) in priority.iter_mut().enumerate().skip(1) {
                    let level = heap.ilog2();
                    let span = LEAVES >> level;
                    let first = (heap << (DEPTH - level)) - LEAVES;
                    let Some(gain) = variation(&leaves[first..first + span], auto) else {
                        continue;
                    };
                    // The light the node misplaces: its reflected flux's spread.
                    let area = patch.area / f64::from(1u32 << level);
                    *priority = priority.max(area * rho * gain.sqrt());
                }
            });
    }
    // Per traced triangle (both faces), each node's priority, at most its parent's: a node is
    // cut only below a cut parent, so it is worth no more than the cut that makes it.
    let mut worth = vec![0.0f64; faces.len() * nodes];
    for (i, p) in priority.chunks_exact(nodes).enumerate() {
        let t = face_of[i].0 as usize;
        for (w, &p) in worth[t * nodes..(t + 1) * nodes].iter_mut().zip(p) {
            *w = w.max(p);
        }
    }
    for tree in worth.chunks_exact_mut(nodes) {
        for heap in 2..nodes {
            tree[heap] = tree[heap].min(tree[heap / 2]);
        }
    }
    // Most worth first; a parent before its children (its heap index is smaller).
    let mut marked: Vec<(u32, u32)> = (0..worth.len())
        .filter(|&n| n % nodes > 0 && worth[n] > 0.0)
        .map(|n| ((n / nodes) as u32, (n % nodes) as u32))
        .collect();
    marked.sort_by(|a, b| {
        let w = |&(t, heap): &(u32, u32)| worth[t as usize * nodes + heap as usize];
        w(b).total_cmp(&w(a)).then(a.cmp(b))
    });
    marked
}

/// What a piece of a patch's scoring tree receives: the segments leaving it and the sum and
/// sum of squares of the radiance they gather (the light the lines carry), and the direct
/// light it receives from the punctual lights and the sampled emitters (irradiance / π, the
/// same units, and the variance of its estimate), which the lines do not carry.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Leaf {
    crossings: f64,
    sum: f64,
    square: f64,
    direct: (f64, f64),
}

/// The mean radiance pieces gather (the lines' mean with the direct light added) and the
/// variance of that estimate: the lines' pooled over their crossings, the direct light's
/// averaged over the pieces (of equal area).
fn gathered_mean(pieces: &[Leaf]) -> (f64, f64) {
    let [n, sum, square] = pieces.iter().fold([0.0; 3], |a, p| {
        [a[0] + p.crossings, a[1] + p.sum, a[2] + p.square]
    });
    let mean = sum / n;
    let k = pieces.len() as f64;
    let direct = pieces.iter().map(|p| p.direct.0).sum::<f64>() / k;
    let noise = pieces.iter().map(|p| p.direct.1).sum::<f64>() / (k * k);
    let lines = (square / n - mean * mean).max(0.0) / (n - 1.0);
    (mean + direct, lines + noise)
}

/// How much the light a node receives varies over its pieces (the node's leaves of the
/// scoring tree): the crossing-weighted variance of the pieces' true means, estimated without
/// bias as Σ w_k ((m_k − m̄)² − v_k), v_k the variance of piece k's mean, less the noise the
/// pieces would show once cut (Σ w_k v_k, weighed by [`NOISE_COST`]). A node left whole
/// shows m̄ over all its pieces; cut down to them, each shows its own, noisier. Looking at
/// every piece, not only the two halves, finds light that a first cut would split evenly (a
/// lamp centred on the cut). A piece's m_k is the radiance its segments gather plus the direct
/// light sampled on it: a lamp's pool of light on a wall, which no line carries, counts.
///
/// `None` unless each half of the node has [`Adaptive::min_crossings`] (as far as the lines
/// carry its light), is known to [`Adaptive::precision`], and the pieces differ
/// beyond their noise: Σ (m_k − m̄)² / v_k, χ² with K − 1 degrees of freedom when they do
/// not, above its mean by [`Adaptive::significance`] standard deviations.
fn variation(pieces: &[Leaf], auto: &Adaptive) -> Option<f64> {
    let (h0, h1) = pieces.split_at(pieces.len() / 2);
    // The crossings a half needs, as far as the lines carry its light: a half lit mostly
    // straight from a lamp is known from its direct light, and the lines' noise in its value
    // is their share of it times their own (a share s of the light needs s² the crossings for
    // the same noise).
    let enough = |h: &[Leaf]| {
        let [n, sum] = h
            .iter()
            .fold([0.0; 2], |a, p| [a[0] + p.crossings, a[1] + p.sum]);
        let direct = h.iter().map(|p| p.direct.0).sum::<f64>() / h.len() as f64;
        let carried = if n > 0.0 { sum / n } else { 0.0 };
        let share = if carried + direct > 0.0 {
            carried / (carried + direct)
        } else {
            1.0
        };
        n >= (auto.min_crossings * share * share).max(2.0)
    };
    if !enough(h0) || !enough(h1) {
        return None;
    }
    // Each half's light known to [`Adaptive::precision`]: a cut into halves whose light the
    // lines cannot tell makes pieces noisier than what they fix (a dim corner).
    let known = |h: &[Leaf]| {
        let (mean, variance) = gathered_mean(h);
        variance <= (auto.precision * mean).powi(2)
    };
    if !known(h0) || !known(h1) {
        return None;
    }
    // (n, mean, variance of the mean) of the pieces with a variance to speak of.
    let stats: Vec<(f64, f64, f64)> = pieces
        .iter()
        .filter(|p| p.crossings >= 2.0)
        .map(|p| {
            let (mean, variance) = gathered_mean(std::slice::from_ref(p));
            (p.crossings, mean, variance)
        })
        .collect();
    let total: f64 = stats.iter().map(|s| s.0).sum();
    let mean = stats.iter().map(|s| s.0 * s.1).sum::<f64>() / total;
    // A piece whose every crossing gathered the same radiance has no noise: keep the test's
    // denominators positive.
    let floor = f64::EPSILON * mean * mean + f64::MIN_POSITIVE;
    let chi2: f64 = stats
        .iter()
        .map(|&(_, m, v)| (m - mean).powi(2) / v.max(floor))
        .sum();
    let freedom = stats.len() as f64 - 1.0;
    if freedom < 1.0 || chi2 <= freedom + auto.significance * (2.0 * freedom).sqrt() {
        return None;
    }
    // What the pieces' own values would add: each shows its noise v_k instead of its share
    // of the node's. Cut only where the variation removed is larger.
    let gain: f64 = stats
        .iter()
        .map(|&(n, m, v)| n / total * ((m - mean).powi(2) - NOISE_COST * v))
        .sum();
    (gain > 0.0).then_some(gain)
}

/// How many times its noise variance a piece's estimate costs in [`variation`]'s gain: 1 for
/// the bias of (m_k − m̄)², 1 for the noise the piece will show once cut, and the rest because
/// only part of the variation removed becomes error removed: a patch's own value is an
/// average either way, and what a cut fixes is the light its pieces send on, while the noise
/// it adds is sent on in full. Measured with `bench-patches` at 1M lines (per-patch error,
/// patches): at 2, Cornell box 3.1% (1,554), panel room 1.4% (3,846), level 13.4% (5,000, the
/// budget); at 8, 2.6% (576), 1.7% (856), 15.2% (3,004); at 32, 2.5% (306), 2.5% (224).
const NOISE_COST: f64 = 8.0;

/// Per patch, for each piece of its bisection tree of depth [`DEPTH`] (heap order of the
/// leaves), at `frame` with `radiance` (the solution's) and `sky`: the crossings whose segment
/// leaves the patch from that piece, and the sum and sum of squares of the luminance at the
/// segments' other ends, the sampled emitters' emission left out (`3 × LEAVES` numbers per
/// patch); and the direct light the piece receives, sampled on it ([`parts_irradiance`]): the
/// punctual lights' and the sampled emitters' irradiance / π (their luminance, and the
/// variance of its estimate; `LEAVES` per patch, 0 where the patch receives none). `face_of`
/// gives each patch's traced triangle and side, `members` its faces ([`refine::members`]);
/// merged and deforming patches get no direct light here (they are not cut).
fn leaf_light(
    bake: &Bake,
    frame: usize,
    radiance: &[[f64; 3]],
    sky: [f64; 3],
    (face_of, members): (&[(u32, bool)], &[u32]),
) -> (Vec<f64>, Vec<(f64, f64)>) {
    let scene = &bake.scene;
    let area = bake.area_lights();
    // The sampled emitters' light reaches the pieces through their direct light, not the
    // lines (as in the solve).
    let carried: Vec<[f64; 3]> = (radiance.iter().zip(&scene.patches))
        .map(|(l, p)| {
            if area.samples(p.material) {
                let e = scene.materials[p.material as usize].emission;
                [l[0] - e[0], l[1] - e[1], l[2] - e[2]]
            } else {
                *l
            }
        })
        .collect();
    let stats = gathered(bake, frame, &carried, sky).0;
    let mut direct = vec![(0.0, 0.0); scene.patches.len() * LEAVES];
    let power = bake.light_power();
    let (lit, _) = bake.direct_light(frame, &scene.materials, &power);
    if lit.is_empty() {
        return (stats, direct);
    }
    let corners = Corners::new(scene);
    let mut parts = Vec::new();
    let mut slots = Vec::new();
    for (i, &(t, back)) in face_of.iter().enumerate() {
        if members[i] > 1 || luminance(lit[i]) <= 0.0 || corners.posed(t, Some(frame)).is_none() {
            continue;
        }
        let own = corners.own(t).map(Vec3::as_dvec3);
        for (k, corners) in leaf_corners(own).into_iter().enumerate() {
            let seed = mix(((i as u64) << 8) ^ k as u64);
            parts.push(Part {
                triangle: t,
                back,
                corners,
                seed,
            });
            slots.push(i * LEAVES + k);
        }
    }
    let lights = (scene, bake.tracer(), area);
    let light = (frame, scene.materials.as_slice(), power.as_slice());
    let values = parts_irradiance(lights, light, LUMINANCE, &parts);
    let pi = std::f64::consts::PI;
    for (slot, (e, v)) in slots.into_iter().zip(values) {
        direct[slot] = (e / pi, v / (pi * pi));
    }
    (stats, direct)
}

/// The leaves of the bisection tree of depth [`DEPTH`] of the triangle `corners` (its own
/// space), in heap order, each as its corners' barycentric coordinates: the pieces [`piece`]
/// tells apart.
fn leaf_corners(corners: [DVec3; 3]) -> Vec<[[f64; 3]; 3]> {
    let mut nodes = vec![(corners, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])];
    for _ in 0..DEPTH {
        nodes = nodes
            .into_iter()
            .flat_map(|(c, b)| {
                let k = longest_edge(c.map(DVec3::as_vec3));
                let (i, j, o) = (k, (k + 1) % 3, (k + 2) % 3);
                let m = crate::scene::midpoint(c[i], c[j]);
                let bm = [0, 1, 2].map(|x| 0.5 * (b[i][x] + b[j][x]));
                [
                    ([c[i], m, c[o]], [b[i], bm, b[o]]),
                    ([m, c[j], c[o]], [bm, b[j], b[o]]),
                ]
            })
            .collect();
    }
    nodes.into_iter().map(|(_, b)| b).collect()
}

/// Bins of [`Near`]: segment lengths from 2^-[`NEAR_OFFSET`] (and shorter) to 2^3 (and longer),
/// in the scene's normalised units, one octave each.
const NEAR_BINS: usize = 20;
/// Octaves below 1 of [`Near`]'s first bin.
const NEAR_OFFSET: i32 = 16;

/// Per patch, how far what its segments meet lies: segments leaving it by length octave
/// ([`NEAR_BINS`]; contacts in the first, the sky in none), and all of them.
#[derive(Clone, Copy, Default)]
struct Near {
    bins: [u32; NEAR_BINS],
    segments: u32,
}

impl Near {
    fn add(&mut self, length: f32) {
        self.segments += 1;
        if length.is_finite() {
            let octave = if length > 0.0 {
                length.log2().floor() as i32 + NEAR_OFFSET
            } else {
                0
            };
            self.bins[octave.clamp(0, NEAR_BINS as i32 - 1) as usize] += 1;
        }
    }

    fn merge(&mut self, other: &Self) {
        self.segments += other.segments;
        for (a, b) in self.bins.iter_mut().zip(&other.bins) {
            *a += b;
        }
    }

    /// The share of the segments that meet something closer than `d` (whole octaves below it:
    /// an underestimate by at most one octave), 0 without segments. Lines are uniform, so the
    /// segments leaving a patch are cosine-distributed: this is its form factor to what lies
    /// that close.
    fn closer_than(&self, d: f64) -> f64 {
        if self.segments == 0 {
            return 0.0;
        }
        let below: u32 = (0..NEAR_BINS)
            .take_while(|&k| 2f64.powi(k as i32 + 1 - NEAR_OFFSET) <= d)
            .map(|k| self.bins[k])
            .sum();
        f64::from(below) / f64::from(self.segments)
    }
}

/// [`leaf_light`]'s lines, and each patch's [`Near`].
fn gathered(
    bake: &Bake,
    frame: usize,
    radiance: &[[f64; 3]],
    sky: [f64; 3],
) -> (Vec<f64>, Vec<Near>) {
    let scene = &bake.scene;
    let list = bake.list();
    // Every segment counts once: the patches are made before [`Bake::split`] makes the gaps'
    // lines denser (their lines weigh differently, `IntersectionList::line_weights`).
    debug_assert!(list.dense().0.is_empty(), "auto patches from dense lines");
    let surfaces = bake.tracer().surfaces();
    let corners = Corners::new(scene);
    // Sums in fixed point: the cuts, and so the patch ids, are the same on any machine.
    let light = FixedLight::new(
        |j| luminance(radiance[j as usize]),
        scene.patches.len(),
        luminance(sky),
    );
    let (unit, value) = (light.unit, |to| light.value(to));
    let size = scene.patches.len() * LEAVES;
    let patches = scene.patches.len();
    let (sums, near) = list
        .bundles(scene)
        .fold(
            || {
                let near = vec![Near::default(); patches];
                (vec![Sums::default(); size], near, Vec::new())
            },
            |(mut acc, mut near, mut hits), (first, bundle)| {
                let surfaces = surfaces.along(bundle.direction);
                let direction = bundle.direction.as_dvec3();
                for (i, origin) in bundle.origins.iter().enumerate() {
                    list.frame_hits(first + i, frame, &mut hits);
                    walk_from(&hits, &surfaces, |from, to, at, length| {
                        near[from as usize].add(length);
                        let Some(posed) = corners.posed(at.surface(), Some(frame)) else {
                            return;
                        };
                        let p = origin.as_dvec3() + direction * f64::from(at.t);
                        let Some(bary) = barycentric(posed, p) else {
                            return;
                        };
                        let own = corners.own(at.surface()).map(Vec3::as_dvec3);
                        let g = value(to);
                        let a = &mut acc[from as usize * LEAVES + piece(own, bary)];
                        a.count += 1;
                        a.sum += g;
                        a.square += u128::from(g) * u128::from(g);
                    });
                }
                (acc, near, hits)
            },
        )
        .map(|(acc, near, _)| (acc, near))
        .reduce(
            || (vec![Sums::default(); size], vec![Near::default(); patches]),
            |(mut a, mut an), (b, bn)| {
                for (x, y) in a.iter_mut().zip(&b) {
                    x.count += y.count;
                    x.sum += y.sum;
                    x.square += y.square;
                }
                an.iter_mut().zip(&bn).for_each(|(x, y)| x.merge(y));
                (a, an)
            },
        );
    let sums = sums
        .iter()
        .flat_map(|s| {
            [
                s.count as f64,
                s.sum as f64 * unit,
                s.square as f64 * unit * unit,
            ]
        })
        .collect();
    (sums, near)
}

/// A piece's crossings and the fixed-point sum and sum of squares of what they gather.
#[derive(Clone, Copy, Default)]
struct Sums {
    count: u64,
    sum: u64,
    square: u128,
}

/// The leaf of the bisection tree of depth [`DEPTH`] of the triangle `corners` (its own space)
/// holding the point at barycentric coordinates `bary`: the cuts
/// [`crate::scene::refine::cut`] makes, each at the piece's longest edge.
fn piece(corners: [DVec3; 3], bary: [f64; 3]) -> usize {
    let (mut c, mut l) = (corners, bary);
    let mut heap = 1;
    for _ in 0..DEPTH {
        let k = longest_edge(c.map(DVec3::as_vec3));
        let (i, j, o) = (k, (k + 1) % 3, (k + 2) % 3);
        let m = crate::scene::midpoint(c[i], c[j]);
        // As in `Refinement::locate`: the half at corner i, or the one at corner j.
        (c, l, heap) = if l[i] >= l[j] {
            ([c[i], m, c[o]], [l[i] - l[j], 2.0 * l[j], l[o]], 2 * heap)
        } else {
            (
                [m, c[j], c[o]],
                [2.0 * l[i], l[j] - l[i], l[o]],
                2 * heap + 1,
            )
        };
    }
    heap - LEAVES
}

#[cfg(test)]
mod tests {
    use glam::DVec3;
    use rand::rngs::Xoshiro256PlusPlus;
    use rand::{RngExt, SeedableRng};

    use super::{LEAVES, leaf_corners, piece};

    /// Every point of a leaf of [`leaf_corners`] is told to that leaf by [`piece`], on
    /// triangles of every shape (the direct light sampled on a piece is that piece's).
    #[test]
    fn leaf_corners_are_the_pieces_piece_tells_apart() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(7);
        for _ in 0..200 {
            let corners = [(); 3].map(|()| DVec3::new(rng.random(), rng.random(), rng.random()));
            let leaves = leaf_corners(corners);
            assert_eq!(leaves.len(), LEAVES);
            for (k, leaf) in leaves.iter().enumerate() {
                // A point well inside the leaf: its centroid pulled a little towards a random
                // corner.
                let w = [1.0 + rng.random::<f64>(), 1.0, 1.0];
                let total: f64 = w.iter().sum();
                let bary =
                    [0, 1, 2].map(|x| (0..3).map(|c| w[c] * leaf[c][x]).sum::<f64>() / total);
                assert_eq!(piece(corners, bary), k, "{corners:?} {bary:?}");
            }
        }
    }
}
