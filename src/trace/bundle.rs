//! Tracing a bundle's parallel lines together.
//!
//! Lines that share a direction are points on any plane they cross: sheared along the
//! direction (the watertight test's own shear, [`Shear`]), a BVH node's box becomes a hexagon
//! (a rectangle with two corners cut along the shear) and the lines through the box are the
//! points inside it. One walk of an 8-wide BVH per bundle carries down, from each node to its
//! children, the list of the lines inside the node's hexagon: a node is read once per bundle,
//! not once per line, and testing a line against eight children is six comparisons with eight
//! lanes each (one instruction each with AVX2; the walk is compiled for it too, and chosen at
//! run time). The walk goes level by level, so that the reads of a level's nodes from memory
//! overlap.
//!
//! Nearly all triangles are in blocks (`wide::Block`): the triangles of a node whose
//! children would all be single triangles, side by side, each line that reaches the block
//! tested against its eight lanes at once with the plain f32 rejection, on the same numbers
//! as the test of one triangle, with no boxes; the few lanes it leaves go to the exact test.
//! At a leaf of its own, each line inside a triangle's box gets the exact test on the same
//! numbers as a line traced alone ([`ShearedLine::intersect_projected`]), so both find the
//! same crossings bit for bit. No line is lost to rounding on the way: the test works on the
//! corners' and the line's projections, the same f32 numbers the rectangles are made of, and
//! rounding is monotonic, so a box's rectangle holds the projection of every point of the box;
//! the band between the cut corners is widened by a margin larger than its rounding.

use glam::Vec3;

use super::triangle::{Shear, ShearedLine, certainly_outside4};
use super::wide::{self, INNER};
use super::{Hit, TraceMesh, Triangle};
use crate::lines::LINE_LENGTH;

/// A line's projected point, and the line's index in the bundle's starting points.
#[derive(Clone, Copy, Debug, Default)]
pub struct Point {
    x: f32,
    y: f32,
    /// [`Shear::diagonal`] of (x, y).
    d: f32,
    line: u32,
}

/// Lines along one direction, ready to be traced together: the shear of their direction, their
/// starting points and each one's projected point.
#[derive(Clone, Debug)]
pub struct ParallelLines {
    direction: Vec3,
    shear: Shear,
    origins: Vec<Vec3>,
    points: Vec<Point>,
    /// The largest coordinate of any starting point, for [`ParallelLines::through_box`]'s
    /// rounding margin.
    reach: f32,
}

impl ParallelLines {
    /// The lines from each of `origins` along `direction`.
    #[must_use]
    pub fn new(direction: Vec3, origins: Vec<Vec3>) -> Self {
        let shear = Shear::new(direction);
        let points = origins
            .iter()
            .enumerate()
            .map(|(line, &o)| {
                let [x, y] = shear.project(o);
                Point {
                    x,
                    y,
                    d: shear.diagonal([x, y]),
                    line: line as u32,
                }
            })
            .collect();
        let reach = origins
            .iter()
            .fold(0.0f32, |m, o| m.max(o.abs().max_element()));
        Self {
            direction,
            shear,
            origins,
            points,
            reach,
        }
    }

    /// The lines' common direction.
    #[must_use]
    pub fn direction(&self) -> Vec3 {
        self.direction
    }

    /// Their starting points.
    #[must_use]
    pub fn origins(&self) -> &[Vec3] {
        &self.origins
    }

    /// Number of lines.
    #[must_use]
    pub fn len(&self) -> usize {
        self.origins.len()
    }

    /// Whether there are none.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }

    /// The indices of the lines that may meet the box from `min` to `max`, widened by a
    /// rounding margin: a superset, never missing a line that meets the box, even moved into
    /// a rigid object's space after this test.
    pub fn through_box(&self, min: Vec3, max: Vec3, out: &mut Vec<u32>) {
        let holds = self.image(min, max);
        out.extend(self.points.iter().filter(|p| holds(p)).map(|p| p.line));
    }

    /// [`ParallelLines::through_box`] among the lines `among` only (indices, as it gives
    /// them): the same test, line by line.
    pub fn through_box_among(&self, min: Vec3, max: Vec3, among: &[u32], out: &mut Vec<u32>) {
        let holds = self.image(min, max);
        out.extend(among.iter().filter(|&&i| holds(&self.points[i as usize])));
    }

    /// Whether a line's point is in the image of the box from `min` to `max` (the rectangle
    /// and the diagonal band), widened by the margin of a move into another space and, for
    /// the band, its own rounding as well.
    fn image(&self, min: Vec3, max: Vec3) -> impl Fn(&Point) -> bool {
        let scale = self
            .reach
            .max(min.abs().max_element())
            .max(max.abs().max_element());
        let pad = margin(scale);
        let (lo, hi) = (
            min.to_array().map(|v| [v; 8]),
            max.to_array().map(|v| [v; 8]),
        );
        let image = self
            .shear
            .project_boxes(&lo, &hi, 2.0 * pad)
            .map(|side| side[0]);
        let rect = padded([image[0], image[1], image[2], image[3]], pad);
        let (d0, d1) = (image[4], image[5]);
        move |p| inside(&rect, p) & (p.d >= d0) & (p.d <= d1)
    }

    /// Gives back the starting points, for their buffer to be used again.
    #[must_use]
    pub fn into_origins(self) -> Vec<Vec3> {
        self.origins
    }
}

/// Reusable buffers for [`TraceMesh::trace_parallel`].
#[derive(Default)]
pub struct Scratch {
    /// The lists of lines inside the nodes of the level being walked.
    points: Lists,
    /// Those of the next level.
    next_points: Lists,
    /// The level's nodes, with their list's range in `points`.
    nodes: Vec<(u32, u32, u32)>,
    /// The next level's.
    next_nodes: Vec<(u32, u32, u32)>,
    /// Triangles reached at this level, with their list's range in `next_points`.
    leaves: Vec<(u32, u32, u32)>,
    /// Blocks reached at this level: the block, its lanes, and its list's range.
    blocks: Vec<(u32, u32, u32, u32)>,
    /// For [`super::sort_by_line`]: where each line's crossings start, and the sorted pairs.
    line_starts: Vec<u32>,
    sorted: Vec<(u32, Hit)>,
}

/// Lists of lines, one after another, in places kept from one use to the next, so that a place
/// is written once, with no value put there first.
#[derive(Default)]
struct Lists {
    places: Vec<Point>,
    /// The places in use.
    len: usize,
}

impl Lists {
    fn clear(&mut self) {
        self.len = 0;
    }

    /// The places in use.
    fn as_slice(&self) -> &[Point] {
        &self.places[..self.len]
    }

    /// The `n` places after those in use, to be written (not yet in use).
    fn after(&mut self, n: usize) -> &mut [Point] {
        let end = self.len + n;
        if self.places.len() < end {
            self.places
                .resize(end.max(2 * self.places.len()), Point::default());
        }
        &mut self.places[self.len..end]
    }

    fn push(&mut self, p: Point) {
        self.after(1)[0] = p;
        self.len += 1;
    }
}

impl Scratch {
    /// The buffers of [`super::sort_by_line`].
    pub(super) fn sort_buffers(&mut self) -> (&mut Vec<u32>, &mut Vec<(u32, Hit)>) {
        (&mut self.line_starts, &mut self.sorted)
    }
}

/// Whether the processor has the instructions [`TraceMesh::walk_avx2`] is compiled for (looked
/// up once, then read from a cache).
#[cfg(target_arch = "x86_64")]
#[inline]
fn wide_instructions() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
        && std::arch::is_x86_feature_detected!("bmi1")
        && std::arch::is_x86_feature_detected!("bmi2")
        && std::arch::is_x86_feature_detected!("lzcnt")
        && std::arch::is_x86_feature_detected!("popcnt")
}

/// How many nodes or triangles ahead of the one being tested the walk asks memory for.
const PREFETCH_AHEAD: usize = 16;

/// A rounding margin for coordinates up to `scale`: of a box moved into another space (a rigid
/// object's), whose lines moved with it are within a few units in the last place of the
/// largest coordinate (about 6e-8 relative), and of a box's diagonal band
/// ([`Shear::project_boxes`]); 1e-5 of it is ample.
fn margin(scale: f32) -> f32 {
    1e-5 * scale.max(f32::MIN_POSITIVE)
}

fn padded([x0, y0, x1, y1]: [f32; 4], pad: f32) -> [f32; 4] {
    [x0 - pad, y0 - pad, x1 + pad, y1 + pad]
}

#[inline]
fn inside(rect: &[f32; 4], p: &Point) -> bool {
    (p.x >= rect[0]) & (p.y >= rect[1]) & (p.x <= rect[2]) & (p.y <= rect[3])
}

/// The images of a node's children: their rectangles' lower x, lower y, upper x and upper y,
/// and the range of their diagonals, child by child ([`Shear::project_boxes`]).
type Rects = [[f32; wide::WIDTH]; 6];

/// The children (bit i for child i) whose images hold `p`; with `AVX`, eight at once.
#[inline(always)]
fn children_around<const AVX: bool>(rects: &Rects, p: &Point) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if AVX {
        // SAFETY: `AVX` is set only in the walk compiled for AVX2 ([`TraceMesh::walk_avx2`]).
        return unsafe { children_around_avx(rects, p) };
    }
    let (x, y, d) = (
        glam::Vec4::splat(p.x),
        glam::Vec4::splat(p.y),
        glam::Vec4::splat(p.d),
    );
    [0, 4].into_iter().fold(0, |mask, half| {
        let side = |k: usize| glam::Vec4::from_slice(&rects[k][half..]);
        let inside = x.cmpge(side(0))
            & y.cmpge(side(1))
            & x.cmple(side(2))
            & y.cmple(side(3))
            & d.cmpge(side(4))
            & d.cmple(side(5));
        mask | inside.bitmask() << half
    })
}

/// [`children_around`] in one AVX instruction per side.
///
/// # Safety
/// The processor must have AVX.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx")]
unsafe fn children_around_avx(rects: &Rects, p: &Point) -> u32 {
    use std::arch::x86_64::{
        _CMP_GE_OQ, _CMP_LE_OQ, _mm256_and_ps, _mm256_cmp_ps, _mm256_loadu_ps, _mm256_movemask_ps,
        _mm256_set1_ps,
    };
    // SAFETY: the eight-float loads stay inside the rectangles' arrays.
    unsafe {
        let (x, y, d) = (
            _mm256_set1_ps(p.x),
            _mm256_set1_ps(p.y),
            _mm256_set1_ps(p.d),
        );
        let side = |k: usize| _mm256_loadu_ps(rects[k].as_ptr());
        let inside = _mm256_and_ps(
            _mm256_and_ps(
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GE_OQ>(x, side(0)),
                    _mm256_cmp_ps::<_CMP_GE_OQ>(y, side(1)),
                ),
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_LE_OQ>(x, side(2)),
                    _mm256_cmp_ps::<_CMP_LE_OQ>(y, side(3)),
                ),
            ),
            _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(d, side(4)),
                _mm256_cmp_ps::<_CMP_LE_OQ>(d, side(5)),
            ),
        );
        _mm256_movemask_ps(inside) as u32
    }
}

/// The images of `node`'s children, their diagonal bands widened by `margin`; with `AVX`,
/// eight at once.
#[inline(always)]
fn rects_of<const AVX: bool>(shear: &Shear, node: &wide::Node, margin: f32) -> Rects {
    #[cfg(target_arch = "x86_64")]
    if AVX {
        // SAFETY: as in [`children_around`].
        return unsafe { shear.project_boxes_avx(&node.lo, &node.hi, margin) };
    }
    shear.project_boxes(&node.lo, &node.hi, margin)
}

/// Appends to `next` the lines of `list` (of several lines) inside each child's image
/// (`rects`, see [`children_around`]; `used`, the children there are), child after child: the
/// children reached (bit i for child i), and each one's range in `next`.
///
/// Child i's list goes in the i-th of eight runs of `list.len()` places, in one pass: each
/// line is written at every child's next place, and the places of the children that hold it
/// move on (a write where none moves on is written over by the next line, or left out).
/// There is no branch on which children hold a line, no count first, no mask kept.
#[inline(always)]
fn split<const AVX: bool>(
    list: &[Point],
    rects: &Rects,
    used: u32,
    next: &mut Lists,
) -> (u32, [(u32, u32); wide::WIDTH]) {
    let n = list.len();
    let base = next.len;
    let places = next.after(wide::WIDTH * n);
    let mut at: [usize; wide::WIDTH] = std::array::from_fn(|i| i * n);
    let mut reached = 0;
    for p in list {
        let m = children_around::<AVX>(rects, p) & used;
        reached |= m;
        for (i, at) in at.iter_mut().enumerate() {
            debug_assert!(*at < (i + 1) * n);
            // SAFETY: `*at` is below the end of child i's run, so inside `places`: it started
            // at the run's start, `i * n`, and has moved on at most once for each line before
            // this one, which are fewer than `n`. (Unchecked, as eight writes a line, the
            // walk takes 3-7% less time.)
            unsafe { *places.get_unchecked_mut(*at) = *p };
            *at += (m >> i) as usize & 1;
        }
    }
    // Up to the end of the last child reached's run.
    next.len = base + (u32::BITS - reached.leading_zeros()) as usize * n;
    let ranges = std::array::from_fn(|i| ((base + i * n) as u32, (base + at[i]) as u32));
    (reached, ranges)
}

impl TraceMesh {
    /// Appends `(line, crossing)` for every crossing of every line of `lines` with the mesh,
    /// in no particular order; the crossings of each line are exactly those
    /// [`TraceMesh::trace`] finds.
    pub fn trace_parallel(
        &self,
        lines: &ParallelLines,
        scratch: &mut Scratch,
        out: &mut Vec<(u32, Hit)>,
    ) {
        #[cfg(target_arch = "x86_64")]
        if wide_instructions() {
            // SAFETY: the processor has every feature the function is compiled for.
            unsafe { self.walk_avx2(lines, scratch, out) };
            return;
        }
        self.walk::<false>(lines, scratch, out);
    }

    /// [`TraceMesh::walk`] compiled for the instructions of x86-64-v3 (AVX2, FMA, BMI), which
    /// the processor was found to have. The same operations on the same numbers: Rust never
    /// fuses a multiply and an add that the code does not ask to fuse, so the crossings are
    /// the same bit for bit.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    fn walk_avx2(&self, lines: &ParallelLines, scratch: &mut Scratch, out: &mut Vec<(u32, Hit)>) {
        self.walk::<true>(lines, scratch, out);
    }

    /// The walk of [`TraceMesh::trace_parallel`]; `AVX` only in [`TraceMesh::walk_avx2`].
    #[inline(always)]
    fn walk<const AVX: bool>(
        &self,
        lines: &ParallelLines,
        scratch: &mut Scratch,
        out: &mut Vec<(u32, Hit)>,
    ) {
        let shear = &lines.shear;
        // The diagonal's rounding: a few units in the last place of the largest coordinate of
        // a line's start or of the mesh ([`Shear::project_boxes`]).
        let bounds = self.bounds();
        let scale = lines
            .reach
            .max(Vec3::from(bounds.min).abs().max_element())
            .max(Vec3::from(bounds.max).abs().max_element());
        let diagonal_margin = margin(scale);
        let Scratch {
            points,
            next_points,
            nodes,
            next_nodes,
            leaves,
            blocks,
            ..
        } = scratch;
        nodes.clear();
        if !self.wide.is_empty() {
            nodes.push((0, 0, lines.points.len() as u32));
        }
        // Level by level: the nodes of a level are independent, so their reads from memory
        // overlap (each is asked for a few nodes ahead). The root's list is the bundle's own.
        let mut root = true;
        while !nodes.is_empty() {
            let level: &[Point] = if root {
                &lines.points
            } else {
                points.as_slice()
            };
            root = false;
            next_points.clear();
            next_nodes.clear();
            leaves.clear();
            blocks.clear();
            for (n, &(node, start, end)) in nodes.iter().enumerate() {
                if let Some(&(ahead, _, _)) = nodes.get(n + PREFETCH_AHEAD) {
                    crate::prefetch(&self.wide[ahead as usize], size_of::<wide::Node>());
                }
                let node = &self.wide[node as usize];
                let rects = rects_of::<AVX>(shear, node, diagonal_margin);
                let list = &level[start as usize..end as usize];
                let (mut reached, ranges) = if let [p] = list {
                    // Most lists deep in the tree: one line, whose children share one copy.
                    let reached = children_around::<AVX>(&rects, p) & node.used;
                    let at = next_points.len as u32;
                    if reached != 0 {
                        next_points.push(*p);
                    }
                    (reached, [(at, at + 1); wide::WIDTH])
                } else {
                    split::<AVX>(list, &rects, node.used, next_points)
                };
                while reached != 0 {
                    let i = reached.trailing_zeros() as usize;
                    reached &= reached - 1;
                    let (from, to) = ranges[i];
                    match node.count[i] {
                        INNER => next_nodes.push((node.child[i], from, to)),
                        count if count & wide::BLOCK != 0 => {
                            blocks.push((node.child[i], u32::from(count & !wide::BLOCK), from, to));
                        }
                        count => {
                            let first = node.child[i];
                            for k in first..first + u32::from(count) {
                                leaves.push((k, from, to));
                            }
                        }
                    }
                }
            }
            for (n, &(k, from, to)) in leaves.iter().enumerate() {
                if let Some(&(ahead, _, _)) = leaves.get(n + PREFETCH_AHEAD) {
                    crate::prefetch(&self.triangles[ahead as usize], size_of::<Triangle>());
                }
                let list = &next_points.as_slice()[from as usize..to as usize];
                self.cross_triangle(k as usize, lines, list, out);
            }
            for (n, &(b, lanes, from, to)) in blocks.iter().enumerate() {
                if let Some(&(ahead, _, _, _)) = blocks.get(n + PREFETCH_AHEAD) {
                    crate::prefetch(&self.blocks[ahead as usize], size_of::<wide::Block>());
                }
                let list = &next_points.as_slice()[from as usize..to as usize];
                self.cross_block::<AVX>(b as usize, lanes, lines, list, out);
            }
            std::mem::swap(points, next_points);
            std::mem::swap(nodes, next_nodes);
        }
    }

    /// Appends the crossings of triangle `k` by the lines of `points`.
    #[inline(always)]
    fn cross_triangle(
        &self,
        k: usize,
        lines: &ParallelLines,
        points: &[Point],
        out: &mut Vec<(u32, Hit)>,
    ) {
        let Triangle { corners, id } = self.triangles[k];
        let shear = &lines.shear;
        let [a, b, c] = corners;
        let projected = [shear.project(a), shear.project(b), shear.project(c)];
        let mut cross = |p: &Point| cross_one(lines, corners, projected, id, p, out);
        if let [p] = points {
            // Most lists at the leaves of a fine mesh: one line, straight to the f32 test (a
            // test of the triangle's rectangle first, a branch as hard to predict as the
            // answer, made it slower).
            cross(p);
            return;
        }
        // Four lines at a time through the plain f32 rejection; the rest one by one.
        for chunk in points.chunks(4) {
            let (mut x, mut y) = ([0.0; 4], [0.0; 4]);
            for (i, p) in chunk.iter().enumerate() {
                (x[i], y[i]) = (p.x, p.y);
            }
            let outside = certainly_outside4(projected, x.into(), y.into());
            let mut maybe = !outside & ((1 << chunk.len()) - 1);
            while maybe != 0 {
                let i = maybe.trailing_zeros() as usize;
                maybe &= maybe - 1;
                cross(&chunk[i]);
            }
        }
    }

    /// Appends the crossings of the triangles of block `b` (its first `lanes`) by the lines of
    /// `points`: the f32 rejection eight lanes at once, the same operations on the same
    /// numbers as [`ShearedLine::intersect_projected`]'s, then the exact test of the lanes
    /// left.
    #[inline(always)]
    fn cross_block<const AVX: bool>(
        &self,
        b: usize,
        lanes: u32,
        lines: &ParallelLines,
        points: &[Point],
        out: &mut Vec<(u32, Hit)>,
    ) {
        let block = &self.blocks[b];
        let shear = &lines.shear;
        #[cfg(target_arch = "x86_64")]
        let projected = if AVX {
            // SAFETY: as in [`children_around`].
            unsafe { shear.project_block_avx(&block.corner) }
        } else {
            shear.project_block(&block.corner)
        };
        #[cfg(not(target_arch = "x86_64"))]
        let projected = shear.project_block(&block.corner);
        let used = (1u32 << lanes) - 1;
        for p in points {
            let mut maybe = !outside8::<AVX>(&projected, [p.x, p.y]) & used;
            while maybe != 0 {
                let l = maybe.trailing_zeros() as usize;
                maybe &= maybe - 1;
                let pc = |c: usize| [projected[c][0][l], projected[c][1][l]];
                cross_one(
                    lines,
                    block.corners(l),
                    [pc(0), pc(1), pc(2)],
                    block.id[l],
                    p,
                    out,
                );
            }
        }
    }
}

/// The lanes (bit i for lane i) of the triangles projected as `projected` (`[corner][x or
/// y][lane]`) that the line through `(x, y)` certainly misses: [`certainly_outside`]'s test,
/// eight lanes at once.
#[inline(always)]
pub(super) fn outside8<const AVX: bool>(projected: &[[[f32; 8]; 2]; 3], [x, y]: [f32; 2]) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if AVX {
        // SAFETY: as in [`children_around`].
        return unsafe { outside8_avx(projected, x, y) };
    }
    [0, 4].into_iter().fold(0, |mask, half| {
        let (ox, oy) = (glam::Vec4::splat(x), glam::Vec4::splat(y));
        let lanes = |c: usize, k: usize| glam::Vec4::from_slice(&projected[c][k][half..]);
        let (ax, ay) = (lanes(0, 0) - ox, lanes(0, 1) - oy);
        let (bx, by) = (lanes(1, 0) - ox, lanes(1, 1) - oy);
        let (cx, cy) = (lanes(2, 0) - ox, lanes(2, 1) - oy);
        let u = cx * by - cy * bx;
        let v = ax * cy - ay * cx;
        let w = bx * ay - by * ax;
        let zero = glam::Vec4::ZERO;
        let outside = (u.cmplt(zero) | v.cmplt(zero) | w.cmplt(zero))
            & (u.cmpgt(zero) | v.cmpgt(zero) | w.cmpgt(zero));
        mask | outside.bitmask() << half
    })
}

/// [`outside8`] in AVX.
///
/// # Safety
/// The processor must have AVX.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx")]
unsafe fn outside8_avx(projected: &[[[f32; 8]; 2]; 3], x: f32, y: f32) -> u32 {
    use std::arch::x86_64::{
        _CMP_GT_OQ, _CMP_LT_OQ, _mm256_and_ps, _mm256_cmp_ps, _mm256_loadu_ps, _mm256_movemask_ps,
        _mm256_mul_ps, _mm256_or_ps, _mm256_set1_ps, _mm256_setzero_ps, _mm256_sub_ps,
    };
    // SAFETY: the eight-float loads stay inside the arrays.
    unsafe {
        let (ox, oy) = (_mm256_set1_ps(x), _mm256_set1_ps(y));
        let lanes = |c: usize, k: usize| _mm256_loadu_ps(projected[c][k].as_ptr());
        let (ax, ay) = (
            _mm256_sub_ps(lanes(0, 0), ox),
            _mm256_sub_ps(lanes(0, 1), oy),
        );
        let (bx, by) = (
            _mm256_sub_ps(lanes(1, 0), ox),
            _mm256_sub_ps(lanes(1, 1), oy),
        );
        let (cx, cy) = (
            _mm256_sub_ps(lanes(2, 0), ox),
            _mm256_sub_ps(lanes(2, 1), oy),
        );
        let u = _mm256_sub_ps(_mm256_mul_ps(cx, by), _mm256_mul_ps(cy, bx));
        let v = _mm256_sub_ps(_mm256_mul_ps(ax, cy), _mm256_mul_ps(ay, cx));
        let w = _mm256_sub_ps(_mm256_mul_ps(bx, ay), _mm256_mul_ps(by, ax));
        let zero = _mm256_setzero_ps();
        let below = _mm256_or_ps(
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_LT_OQ>(u, zero),
                _mm256_cmp_ps::<_CMP_LT_OQ>(v, zero),
            ),
            _mm256_cmp_ps::<_CMP_LT_OQ>(w, zero),
        );
        let above = _mm256_or_ps(
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(u, zero),
                _mm256_cmp_ps::<_CMP_GT_OQ>(v, zero),
            ),
            _mm256_cmp_ps::<_CMP_GT_OQ>(w, zero),
        );
        _mm256_movemask_ps(_mm256_and_ps(below, above)) as u32
    }
}

/// Appends the crossing, if any, of the line of `p` with the triangle of `corners` (projected:
/// `projected`) and global index `id`.
#[inline(always)]
fn cross_one(
    lines: &ParallelLines,
    corners: [Vec3; 3],
    projected: [[f32; 2]; 3],
    id: u32,
    p: &Point,
    out: &mut Vec<(u32, Hit)>,
) {
    let line = ShearedLine::with_shear(lines.origins[p.line as usize], lines.shear);
    if let Some((t, front)) = line.intersect_projected(corners, projected, [p.x, p.y], LINE_LENGTH)
    {
        out.push((p.line, Hit::new(t, id, front)));
    }
}

#[cfg(test)]
mod tests {
    use super::super::{BuildEffort, sort_by_line};
    use super::*;
    use rand::rngs::Xoshiro256PlusPlus;
    use rand::{RngExt, SeedableRng};

    /// `n` small triangles scattered in the unit cube, corners on a grid of 1/64 so that lines
    /// through edges and corners happen.
    fn scattered_triangles(n: usize, rng: &mut Xoshiro256PlusPlus) -> Vec<[Vec3; 3]> {
        let mut grid = || f32::from(rng.random_range(0u8..=64)) / 64.0;
        (0..n)
            .map(|_| {
                let a = Vec3::new(grid(), grid(), grid());
                let mut near = || a + Vec3::new(grid(), grid(), grid()) * 0.25 - 0.125;
                [a, near(), near()]
            })
            .collect()
    }

    /// A mesh of [`scattered_triangles`].
    fn scattered(n: usize, rng: &mut Xoshiro256PlusPlus) -> TraceMesh {
        TraceMesh::new(scattered_triangles(n, rng).into_iter(), 0).unwrap()
    }

    /// Bundles of `lines` lines on the grid of [`scattered_triangles`], from outside the cube.
    fn bundles(count: usize, lines: usize, rng: &mut Xoshiro256PlusPlus) -> Vec<ParallelLines> {
        (0..count)
            .map(|_| {
                let direction = Vec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                )
                .normalize();
                let origins = (0..lines)
                    .map(|_| {
                        let grid = |v: f32| (v * 64.0).round() / 64.0;
                        let p = Vec3::new(
                            grid(rng.random_range(-0.5..1.5)),
                            grid(rng.random_range(-0.5..1.5)),
                            grid(rng.random_range(-0.5..1.5)),
                        );
                        p - direction * 4.0
                    })
                    .collect();
                ParallelLines::new(direction, origins)
            })
            .collect()
    }

    #[test]
    fn a_bvh_built_with_high_effort_finds_what_a_medium_one_does() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(17);
        let triangles = scattered_triangles(5_000, &mut rng);
        let [medium, high] = [BuildEffort::Medium, BuildEffort::High]
            .map(|effort| TraceMesh::with_effort(triangles.iter().copied(), 0, effort).unwrap());
        let mut scratch = Scratch::default();
        let (mut a, mut b, mut crossings) = (Vec::new(), Vec::new(), 0);
        for lines in bundles(30, 2_000, &mut rng) {
            a.clear();
            b.clear();
            medium.trace_parallel(&lines, &mut scratch, &mut a);
            high.trace_parallel(&lines, &mut scratch, &mut b);
            sort_by_line(&mut a, lines.len(), &mut scratch);
            sort_by_line(&mut b, lines.len(), &mut scratch);
            assert_eq!(a, b);
            crossings += a.len();
        }
        assert!(crossings > 10_000, "{crossings}");
        // Another tree, walked differently: not the same number of nodes.
        assert_ne!(medium.wide.len(), high.wide.len());
    }

    #[test]
    fn the_high_effort_is_chosen_from_130_lines_a_triangle() {
        assert_eq!(BuildEffort::for_lines(129_999, 1_000), BuildEffort::Medium);
        assert_eq!(BuildEffort::for_lines(130_000, 1_000), BuildEffort::High);
        assert_eq!(
            BuildEffort::for_lines(u64::MAX, usize::MAX),
            BuildEffort::High
        );
    }

    #[test]
    fn a_line_walked_alone_finds_what_every_triangle_finds_and_stops_at_the_first_asked_for() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(21);
        let mesh = scattered(3_000, &mut rng);
        let (mut all, mut every, mut early, mut crossings) = (Vec::new(), Vec::new(), 0, 0);
        let tests: [fn(Hit, f32) -> bool; 3] = [
            |h, _| h.surface() % 2 == 0,
            |h, t_max| h.t > t_max / 2.0,
            |h, _| h.front() && h.surface() % 7 == 0,
        ];
        for _ in 0..1_000 {
            let grid = |v: f32| (v * 64.0).round() / 64.0;
            let mut c = || grid(rng.random_range(-0.5..1.5));
            let direction = Vec3::new(c(), c(), c()).normalize_or(Vec3::X);
            let origin = Vec3::new(c(), c(), c()) - direction * 2.0;
            let t_max = rng.random_range(1.0..5.0);
            all.clear();
            mesh.trace_until(origin, direction, t_max, &mut all);
            // The walk finds what testing every triangle finds up to `t_max`.
            every.clear();
            mesh.trace_brute_force(origin, direction, &mut every);
            every.retain(|h| h.t < t_max);
            every.sort_unstable_by(Hit::order);
            let mut sorted = all.clone();
            sorted.sort_unstable_by(Hit::order);
            assert_eq!(sorted, every);
            crossings += all.len();
            for test in tests {
                let mut looked = 0;
                let found = mesh.any_until(origin, direction, t_max, &mut |h| {
                    looked += 1;
                    test(h, t_max)
                });
                assert_eq!(found, all.iter().any(|&h| test(h, t_max)));
                // Every crossing looked at when none holds; fewer when one does and others
                // come after it.
                if !found {
                    assert_eq!(looked, all.len());
                }
                early += usize::from(looked < all.len());
            }
        }
        assert!(early > 300 && crossings > 1_500, "{early} {crossings}");
    }

    #[test]
    fn a_box_s_image_holds_every_corner_of_the_box_as_projected() {
        // The corners of a box projected as a triangle's corners are (rounded): each inside the
        // rectangle and the diagonal band of the box, even at the ends of the band, where the
        // rounding is not monotonic and the margin covers it.
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(3);
        let (mut outside, mut unmargined) = (0, 0);
        for _ in 0..20_000 {
            let mut c = || rng.random_range(-4.0f32..4.0);
            let (a, b) = (Vec3::new(c(), c(), c()), Vec3::new(c(), c(), c()));
            let (min, max) = (a.min(b), a.max(b));
            let direction = Vec3::new(c(), c(), c()).normalize();
            let shear = Shear::new(direction);
            let mut node = wide::Node::UNUSED;
            for axis in 0..3 {
                node.lo[axis][5] = min[axis];
                node.hi[axis][5] = max[axis];
            }
            let scale = min.abs().max(max.abs()).max_element();
            let rects = rects_of::<false>(&shear, &node, margin(scale));
            let tight = rects_of::<false>(&shear, &node, 0.0);
            for k in 0..8 {
                let corner = Vec3::select(
                    glam::BVec3::new(k & 1 != 0, k & 2 != 0, k & 4 != 0),
                    max,
                    min,
                );
                let [x, y] = shear.project(corner);
                let p = Point {
                    x,
                    y,
                    d: shear.diagonal([x, y]),
                    line: 0,
                };
                outside += usize::from(children_around::<false>(&rects, &p) >> 5 & 1 == 0);
                unmargined += usize::from(children_around::<false>(&tight, &p) >> 5 & 1 == 0);
            }
        }
        assert_eq!(outside, 0);
        // Without the margin some corners fall out: the margin is needed, and tested.
        assert!(unmargined > 0, "{unmargined}");
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_walk_compiled_for_avx2_finds_what_the_plain_one_does() {
        if !wide_instructions() {
            eprintln!("no AVX2 here: nothing to compare");
            return;
        }
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(16);
        let mesh = scattered(5_000, &mut rng);
        let mut scratch = Scratch::default();
        let (mut plain, mut avx2) = (Vec::new(), Vec::new());
        let mut crossings = 0;
        for lines in bundles(50, 2_000, &mut rng) {
            plain.clear();
            avx2.clear();
            mesh.walk::<false>(&lines, &mut scratch, &mut plain);
            // SAFETY: the processor has the features (checked above).
            unsafe { mesh.walk_avx2(&lines, &mut scratch, &mut avx2) };
            assert_eq!(plain.len(), avx2.len());
            for (a, b) in plain.iter().zip(&avx2) {
                assert_eq!(
                    (a.0, a.1.t.to_bits(), a.1.code),
                    (b.0, b.1.t.to_bits(), b.1.code)
                );
            }
            crossings += plain.len();
        }
        assert!(crossings > 10_000, "{crossings}");
    }
}
