//! Tracing global lines through the scene: every crossing along a line, not just the first.
//!
//! One BVH (obvhs) over the static triangles; one per rigid moving object, in the object's own
//! space, traced by moving the line into that space at each frame; deforming objects get a BVH
//! per frame ([`FrameMeshes`]). Each crossing is a [`Hit`]: where along the line, which traced
//! triangle, and from which side.

pub mod bundle;
pub mod coincident;
pub(crate) mod pages;
pub mod triangle;
mod wide;

use std::time::Duration;

use glam::{Affine3A, DAffine3, DVec3, Vec3, Vec3A, Vec4};
use obvhs::BvhBuildParams;
use obvhs::aabb::Aabb;
use obvhs::bvh2::builder::build_bvh2;
use obvhs::ray::Ray;

use crate::lines::LINE_LENGTH;
use crate::scene::{Faces, Motion, Scene};
pub use bundle::{ParallelLines, Scratch};
pub use coincident::Surfaces;
use pages::Pages;
use triangle::{Shear, ShearedLine};

/// One crossing of a line with a traced triangle: 8 bytes.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Hit {
    /// Distance along the line from its starting point (normalised units).
    pub t: f32,
    /// The traced triangle (its global index, see [`SceneTracer::faces`]) in the low 31 bits;
    /// the top bit is set when the line arrives at the triangle's back face.
    code: u32,
}

const BACK: u32 = 1 << 31;

impl Hit {
    /// A crossing of triangle `surface` at `t`, arriving at its front face if `front`.
    #[must_use]
    pub fn new(t: f32, surface: u32, front: bool) -> Self {
        debug_assert!(surface < BACK);
        Self {
            t,
            code: surface | if front { 0 } else { BACK },
        }
    }

    /// The traced triangle crossed.
    #[must_use]
    pub fn surface(self) -> u32 {
        self.code & !BACK
    }

    /// Whether the line arrives at the triangle's front face (travelling against its normal).
    #[must_use]
    pub fn front(self) -> bool {
        self.code & BACK == 0
    }

    /// A number whose order is [`Hit::order`]'s among crossings at `t >= 0` (every crossing
    /// is at `t > 0`): the bits of a float that is not negative grow with it.
    #[must_use]
    pub fn key(self) -> u64 {
        debug_assert!(self.t >= 0.0);
        u64::from(self.t.to_bits()) << 32 | u64::from(self.code)
    }

    /// Orders hits along the line; equal distances (coincident surfaces) by triangle, so the
    /// order never depends on traversal order.
    #[must_use]
    pub fn order(a: &Self, b: &Self) -> std::cmp::Ordering {
        a.t.total_cmp(&b.t).then(a.code.cmp(&b.code))
    }
}

/// A line to trace: a starting point and a unit direction, running [`LINE_LENGTH`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Line {
    /// Starting point, outside the scene.
    pub origin: Vec3,
    /// Unit direction.
    pub direction: Vec3,
}

/// A traced triangle: its corners and global index, read together.
#[derive(Clone, Copy, Debug)]
struct Triangle {
    corners: [Vec3; 3],
    id: u32,
}

/// A `found` for the `any_` walks that appends every crossing to `out` and never stops them.
fn pushed(out: &mut Vec<Hit>) -> impl FnMut(Hit) -> bool + '_ {
    |hit| {
        out.push(hit);
        false
    }
}

/// A line's slab test of boxes, as obvhs's ([`Aabb::intersect_ray`], the same arithmetic on
/// four lanes): a box is met where the line's spans between its planes on the three axes
/// overlap at or past 0 and start before `t_max`. The boxes are padded ([`BOX_PADDING`]) so
/// that rounding never loses a triangle the line crosses.
struct Slabs {
    origin: [Vec4; 3],
    inverse: [Vec4; 3],
    t_max: Vec4,
}

impl Slabs {
    fn new(origin: Vec3, direction: Vec3, t_max: f32) -> Self {
        let ray = Ray::new(origin.into(), direction.into(), 0.0, t_max);
        Self {
            origin: std::array::from_fn(|a| Vec4::splat(ray.origin[a])),
            inverse: std::array::from_fn(|a| Vec4::splat(ray.inv_direction[a])),
            t_max: Vec4::splat(t_max),
        }
    }

    /// The children of `node` (bit i for child i) whose boxes the line meets.
    #[inline]
    fn children(&self, node: &wide::Node) -> u32 {
        [0, 4].into_iter().fold(0, |mask, half| {
            let (mut near, mut far) = (Vec4::NEG_INFINITY, Vec4::INFINITY);
            for a in 0..3 {
                let t1 = (Vec4::from_slice(&node.lo[a][half..]) - self.origin[a]) * self.inverse[a];
                let t2 = (Vec4::from_slice(&node.hi[a][half..]) - self.origin[a]) * self.inverse[a];
                near = near.max(t1.min(t2));
                far = far.min(t1.max(t2));
            }
            let met = far.cmpge(near) & far.cmpge(Vec4::ZERO) & near.cmplt(self.t_max);
            mask | met.bitmask() << half
        })
    }
}

/// How much a BVH's build does to lower the cost of walking it: the same crossings either way.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum BuildEffort {
    /// obvhs's medium build (PLOC, a few reinsertion passes).
    #[value(help = "obvhs's medium build")]
    Medium,
    /// A wider PLOC search, finer Morton codes and reinsertion over all nodes. On the 207,616
    /// triangles of `spheres.gltf` (`--patch-size 0.0695`) it built in 0.69 s instead of
    /// 0.13 s (static and rigid meshes) and a bundle's walk of the static ones took 20% less
    /// (0.076 s instead of 0.095 s for a million lines): worth it from about 130 lines traced
    /// per triangle ([`BuildEffort::for_lines`]).
    #[value(
        help = "a wider search and reinsertion over all nodes: about 5x the build, 20% faster walks"
    )]
    High,
}

impl BuildEffort {
    /// Lines traced per triangle from which [`BuildEffort::High`]'s longer build is paid back
    /// by the faster walks (measured on `spheres.gltf`; see [`BuildEffort::High`]).
    pub const HIGH_FROM_LINES_PER_TRIANGLE: u64 = 130;

    /// The effort for tracing `lines` lines through `triangles` triangles.
    #[must_use]
    pub fn for_lines(lines: u64, triangles: usize) -> Self {
        if lines >= Self::HIGH_FROM_LINES_PER_TRIANGLE.saturating_mul(triangles as u64) {
            Self::High
        } else {
            Self::Medium
        }
    }

    /// Its name, as `radiosity bench --bvh` and the report spell it.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Medium => "medium",
            Self::High => "high",
        }
    }

    fn params(self) -> BvhBuildParams {
        match self {
            Self::Medium => BvhBuildParams::medium_build(),
            Self::High => BvhBuildParams {
                ploc_search_distance: obvhs::ploc::PlocSearchDistance::High,
                search_depth_threshold: 2,
                reinsertion_batch_ratio: 1.0,
                sort_precision: obvhs::ploc::SortPrecision::U128,
                ..BvhBuildParams::medium_build()
            },
        }
    }
}

/// Triangles with a BVH over them, in BVH order.
pub struct TraceMesh {
    /// The triangles in slots of their own (few: most are in `blocks`), in the BVH's order.
    triangles: Pages<Triangle>,
    /// The box around them (padded like the BVH's).
    bounds: Aabb,
    /// The BVH, 8 wide, for bundles ([`TraceMesh::trace_parallel`]) and single lines
    /// ([`TraceMesh::any_until`]).
    wide: Pages<wide::Node>,
    /// How many levels of nodes it has.
    depth: usize,
    /// The triangles of the nodes whose children were all single triangles, eight lanes side
    /// by side.
    blocks: Pages<wide::Block>,
}

/// Boxes are padded by this much (normalised units, the scale of the whole scene being 1) so
/// that the BVH's float slab test never misses a triangle that a line touches at the edge of
/// its box.
const BOX_PADDING: f32 = 1e-6;

impl TraceMesh {
    /// Builds a BVH over `triangles` (corners in any space), which have global indices
    /// `first_id..`, with [`BuildEffort::Medium`]. `None` when there are no triangles.
    #[must_use]
    pub fn new(triangles: impl Iterator<Item = [Vec3; 3]>, first_id: u32) -> Option<Self> {
        Self::with_effort(triangles, first_id, BuildEffort::Medium)
    }

    /// [`TraceMesh::new`] with the build's `effort`.
    #[must_use]
    pub fn with_effort(
        triangles: impl Iterator<Item = [Vec3; 3]>,
        first_id: u32,
        effort: BuildEffort,
    ) -> Option<Self> {
        let corners: Vec<[Vec3; 3]> = triangles.collect();
        if corners.is_empty() {
            return None;
        }
        let pad = Vec3A::splat(BOX_PADDING);
        let boxes: Vec<Aabb> = corners
            .iter()
            .map(|c| {
                let (lo, hi) = (c[0].min(c[1]).min(c[2]), c[0].max(c[1]).max(c[2]));
                Aabb::new(Vec3A::from(lo) - pad, Vec3A::from(hi) + pad)
            })
            .collect();
        let mut build_time = Duration::ZERO;
        // One triangle per leaf: a bundle's walk tests a leaf's box with its siblings' and
        // reads a triangle only for the lines inside its box (measured best of 1, 2 and 4).
        let params = BvhBuildParams {
            max_prims_per_leaf: 1,
            ..effort.params()
        };
        let bvh = build_bvh2(&boxes, params, &mut build_time);
        let order = &bvh.primitive_indices;
        let wide = wide::collapse(&bvh);
        let triangle = |k: u32| {
            let i = order[k as usize];
            (corners[i as usize], first_id + i)
        };
        let (wide, blocks, singles) = wide::into_blocks(&wide, triangle);
        let triangles: Vec<Triangle> = (singles.into_iter())
            .map(|k| {
                let (corners, id) = triangle(k);
                Triangle { corners, id }
            })
            .collect();
        Some(Self {
            triangles: triangles.into(),
            bounds: bvh.nodes[0].aabb,
            depth: wide::depth(&wide),
            wide: wide.into(),
            blocks: blocks.into(),
        })
    }

    /// Appends every crossing of the line `origin + t·direction`, `0 < t < LINE_LENGTH`, in
    /// traversal order.
    pub fn trace(&self, origin: Vec3, direction: Vec3, out: &mut Vec<Hit>) {
        self.trace_until(origin, direction, LINE_LENGTH, out);
    }

    /// [`TraceMesh::trace`] for `0 < t < t_max` only: the nodes beyond are not visited.
    pub fn trace_until(&self, origin: Vec3, direction: Vec3, t_max: f32, out: &mut Vec<Hit>) {
        self.any_until(origin, direction, t_max, &mut pushed(out));
    }

    /// Whether `found` holds for a crossing of the line `origin + t·direction`,
    /// `0 < t < t_max`: the crossings are given to it in the order the walk meets them, and
    /// the walk stops at the first it holds for (a shadow ray's first blocker).
    ///
    /// The walk is of the wide BVH, eight children's boxes tested at once by their slabs
    /// (obvhs's slab test on four lanes): a line walked alone, without its bundle's hexagons,
    /// so that the nodes past `t_max` are left out.
    pub fn any_until(
        &self,
        origin: Vec3,
        direction: Vec3,
        t_max: f32,
        found: &mut impl FnMut(Hit) -> bool,
    ) -> bool {
        if self.wide.is_empty() {
            return false;
        }
        let (mut small, mut large) = ([0u32; 192], Vec::new());
        let stack = self.stack(&mut small, &mut large);
        let shear = Shear::new(direction);
        let sheared = ShearedLine::with_shear(origin, shear);
        let seen = shear.project(origin);
        let slabs = Slabs::new(origin, direction, t_max);
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let node = &self.wide[stack[top] as usize];
            let mut reached = slabs.children(node) & node.used;
            while reached != 0 {
                let i = reached.trailing_zeros() as usize;
                reached &= reached - 1;
                let first = node.child[i];
                match node.count[i] {
                    wide::INNER => {
                        stack[top] = first;
                        top += 1;
                    }
                    count if count & wide::BLOCK != 0 => {
                        // The lanes the plain f32 rejection leaves, eight at once: the same
                        // test as the first of each lane's own.
                        let block = &self.blocks[first as usize];
                        let projected = shear.project_block(&block.corner);
                        let lanes = (1 << (count & !wide::BLOCK)) - 1;
                        let mut maybe = !bundle::outside8::<false>(&projected, seen) & lanes;
                        while maybe != 0 {
                            let lane = maybe.trailing_zeros() as usize;
                            maybe &= maybe - 1;
                            let [a, b, c] = block.corners(lane);
                            if let Some((t, front)) = sheared.intersect(a, b, c, t_max)
                                && found(Hit::new(t, block.id[lane], front))
                            {
                                return true;
                            }
                        }
                    }
                    count => {
                        for k in first..first + u32::from(count) {
                            let Triangle { corners, id } = self.triangles[k as usize];
                            let [a, b, c] = corners;
                            if let Some((t, front)) = sheared.intersect(a, b, c, t_max)
                                && found(Hit::new(t, id, front))
                            {
                                return true;
                            }
                        }
                    }
                }
            }
        }
        false
    }

    /// A walk's stack of nodes (a node's children on it in place of the node: 7 more a level at
    /// most): `small` when the BVH is shallow enough, `large` sized for it otherwise.
    fn stack<'a>(&self, small: &'a mut [u32; 192], large: &'a mut Vec<u32>) -> &'a mut [u32] {
        let size = (wide::WIDTH - 1) * self.depth + 1;
        if size <= small.len() {
            small
        } else {
            large.resize(size, 0);
            large
        }
    }

    /// Whether `found` holds for a triangle that meets the convex region inside every one of
    /// `planes` (each `(m, d)` the points `p` with `m · p ≤ d`): each such triangle's global
    /// index is given to it, and the walk stops at the first it holds for. A node whose box is
    /// wholly outside one of the planes is skipped; a triangle is clipped by every plane in
    /// `f64` and given if anything of it is left ([`convex_meets_triangle`]).
    pub fn any_in_convex(
        &self,
        planes: &[(DVec3, f64)],
        found: &mut impl FnMut(u32) -> bool,
    ) -> bool {
        if self.wide.is_empty() {
            return false;
        }
        let (mut small, mut large) = ([0u32; 192], Vec::new());
        let stack = self.stack(&mut small, &mut large);
        // A box is outside a plane when its corner least along the normal is beyond it.
        let outside = |lo: [f32; 3], hi: [f32; 3]| {
            planes.iter().any(|&(m, d)| {
                let near = |a: usize| {
                    let (l, h) = (f64::from(lo[a]), f64::from(hi[a]));
                    m[a] * if m[a] > 0.0 { l } else { h }
                };
                near(0) + near(1) + near(2) > d
            })
        };
        let meets = |c: [Vec3; 3]| convex_meets_triangle(planes, c.map(Vec3::as_dvec3));
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let node = &self.wide[stack[top] as usize];
            let mut used = node.used;
            while used != 0 {
                let i = used.trailing_zeros() as usize;
                used &= used - 1;
                let lo = [node.lo[0][i], node.lo[1][i], node.lo[2][i]];
                let hi = [node.hi[0][i], node.hi[1][i], node.hi[2][i]];
                if outside(lo, hi) {
                    continue;
                }
                let first = node.child[i];
                match node.count[i] {
                    wide::INNER => {
                        stack[top] = first;
                        top += 1;
                    }
                    count if count & wide::BLOCK != 0 => {
                        let block = &self.blocks[first as usize];
                        for lane in 0..usize::from(count & !wide::BLOCK) {
                            if meets(block.corners(lane)) && found(block.id[lane]) {
                                return true;
                            }
                        }
                    }
                    count => {
                        for k in first..first + u32::from(count) {
                            let Triangle { corners, id } = self.triangles[k as usize];
                            if meets(corners) && found(id) {
                                return true;
                            }
                        }
                    }
                }
            }
        }
        false
    }

    /// The box around all the triangles (padded like the BVH's).
    fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// The same crossings found by testing every triangle, for checking the BVH path.
    pub fn trace_brute_force(&self, origin: Vec3, direction: Vec3, out: &mut Vec<Hit>) {
        let sheared = ShearedLine::new(origin, direction);
        let lanes = (self.blocks.iter())
            .flat_map(|block| (0..wide::WIDTH).map(|lane| (block.corners(lane), block.id[lane])));
        // A block's unused lanes are zero: triangles of no area, which no line crosses.
        let singles = self.triangles.iter().map(|t| (t.corners, t.id));
        for ([a, b, c], id) in singles.chain(lanes) {
            if let Some((t, front)) = sheared.intersect(a, b, c, LINE_LENGTH) {
                out.push(Hit::new(t, id, front));
            }
        }
    }
}

/// A rigid moving object ready for tracing: its BVH in object space and, per frame, the map from
/// normalised space into object space.
struct RigidTracer {
    mesh: TraceMesh,
    /// Per frame: the object's box in normalised space, and the map from normalised space to
    /// object space; `None` where the pose is singular (scaled to nothing), which no line can
    /// hit. Most lines miss a small moving object: the box test spares them the transform and
    /// the traversal.
    frames: Vec<Option<(Aabb, Affine3A)>>,
}

/// Whether anything of triangle `corners` is inside every one of `planes` (each `(m, d)` the
/// points `p` with `m · p ≤ d`): the triangle clipped by each plane in turn (Sutherland and
/// Hodgman) keeps a point.
#[must_use]
pub fn convex_meets_triangle(planes: &[(DVec3, f64)], corners: [DVec3; 3]) -> bool {
    // A triangle clipped by k planes has at most 3 + k corners: past the buffers' room, the
    // triangle is said to meet the region (the answer errs on the safe side).
    const ROOM: usize = 32;
    if planes.len() + 3 > ROOM {
        return true;
    }
    let (mut polygon, mut next) = ([DVec3::ZERO; ROOM], [DVec3::ZERO; ROOM]);
    polygon[..3].copy_from_slice(&corners);
    let mut len = 3;
    for &(m, d) in planes {
        let mut kept = 0;
        for k in 0..len {
            let (a, b) = (polygon[k], polygon[(k + 1) % len]);
            let (da, db) = (m.dot(a) - d, m.dot(b) - d);
            if da <= 0.0 {
                next[kept] = a;
                kept += 1;
            }
            if (da <= 0.0) != (db <= 0.0) {
                next[kept] = a + (b - a) * (da / (da - db));
                kept += 1;
            }
        }
        std::mem::swap(&mut polygon, &mut next);
        len = kept;
        if len == 0 {
            return false;
        }
    }
    true
}

/// Everything needed to trace lines through a scene at any frame.
pub struct SceneTracer {
    /// The static triangles, global indices `0..statics`.
    statics: Option<TraceMesh>,
    /// Per moving object: its tracer if rigid and not empty (deforming objects are in
    /// [`FrameMeshes`]).
    rigid: Vec<Option<RigidTracer>>,
    /// First global triangle index of each moving object.
    first_ids: Vec<u32>,
    /// What the tallies and shadow rays know of every traced triangle.
    table: SurfaceTable,
}

/// What the tallies and shadow rays need to know of a scene's traced triangles, by global
/// index (the static triangles, then each moving object's), without the BVHs: what a walk of
/// the lines' crossings reads ([`Surfaces`]).
#[derive(Clone, Debug)]
pub struct SurfaceTable {
    /// The faces (patches) of every traced triangle.
    faces: Vec<Faces>,
    /// The node every traced triangle comes from.
    nodes: Vec<u32>,
    /// The space of every traced triangle's normal (see [`Surfaces::spaces`]).
    spaces: Vec<u32>,
    /// Unit normal of every traced triangle in its space.
    normals: Vec<Vec3>,
    /// Every traced triangle's corners in its space, hashed (see [`Surfaces::corners`]).
    corners: Vec<[u32; 3]>,
}

impl SurfaceTable {
    /// The table of `scene`'s triangles: a rigid object's in its own space, a deforming one's
    /// at frame 0.
    #[must_use]
    pub fn new(scene: &Scene) -> Self {
        let normal = |positions: &[Vec3], t: &[u32; 3]| {
            let [a, b, c] = t.map(|i| positions[i as usize].as_dvec3());
            (b - a).cross(c - a).normalize_or_zero().as_vec3()
        };
        let corner_keys = |positions: &[Vec3], t: &[u32; 3]| {
            t.map(|i| {
                let [x, y, z] = positions[i as usize].to_array().map(f32::to_bits);
                let h = coincident::mix(
                    u64::from(x) ^ coincident::mix(u64::from(y) ^ coincident::mix(u64::from(z))),
                );
                (h >> 32) as u32
            })
        };
        let meshes = std::iter::once((&scene.statics, 0))
            .chain((scene.objects.iter().enumerate()).map(|(k, o)| (&o.mesh, 1 + k as u32)));
        let (mut faces, mut spaces, mut normals, mut corners) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (mesh, space) in meshes {
            faces.extend_from_slice(&mesh.faces);
            spaces.extend(std::iter::repeat_n(space, mesh.faces.len()));
            normals.extend(mesh.triangles.iter().map(|t| normal(&mesh.positions, t)));
            corners.extend(
                mesh.triangles
                    .iter()
                    .map(|t| corner_keys(&mesh.positions, t)),
            );
        }
        let nodes = faces
            .iter()
            .map(|f| scene.patches[f.front as usize].source.node)
            .collect();
        Self {
            faces,
            nodes,
            spaces,
            normals,
            corners,
        }
    }

    /// The faces of every traced triangle, indexed by [`Hit::surface`].
    #[must_use]
    pub fn faces(&self) -> &[Faces] {
        &self.faces
    }

    /// The faces, spaces and normals of every traced triangle, for the tallies and shadow rays.
    #[must_use]
    pub fn surfaces(&self) -> Surfaces<'_> {
        Surfaces {
            faces: &self.faces,
            spaces: &self.spaces,
            normals: &self.normals,
            corners: &self.corners,
            direction: None,
        }
    }

    /// The source node of every traced triangle, by global index.
    #[must_use]
    pub fn nodes(&self) -> &[u32] {
        &self.nodes
    }

    /// Number of traced triangles (static and moving).
    #[must_use]
    pub fn triangles(&self) -> usize {
        self.faces.len()
    }
}

impl SceneTracer {
    /// Builds the BVHs of the static geometry and of every rigid object
    /// ([`BuildEffort::Medium`]).
    #[must_use]
    pub fn new(scene: &Scene) -> Self {
        Self::with_effort(scene, BuildEffort::Medium)
    }

    /// [`SceneTracer::new`] for tracing `lines` lines: the effort
    /// [`BuildEffort::for_lines`] chooses for the scene's static and rigid triangles.
    #[must_use]
    pub fn for_lines(scene: &Scene, lines: u64) -> Self {
        Self::with_effort(scene, Self::effort_for(scene, lines))
    }

    /// The effort [`SceneTracer::for_lines`] chooses: [`BuildEffort::for_lines`] for the
    /// static and rigid triangles (deforming ones are built anew at each frame, with
    /// [`BuildEffort::Medium`]).
    #[must_use]
    pub fn effort_for(scene: &Scene, lines: u64) -> BuildEffort {
        let rigid = (scene.objects.iter())
            .filter(|o| matches!(o.motion, Motion::Rigid { .. }))
            .map(|o| o.mesh.triangles.len());
        let triangles = scene.statics.triangles.len() + rigid.sum::<usize>();
        BuildEffort::for_lines(lines, triangles)
    }

    /// [`SceneTracer::new`] with the BVHs' build `effort`.
    #[must_use]
    pub fn with_effort(scene: &Scene, effort: BuildEffort) -> Self {
        let statics = &scene.statics;
        let corners = |positions: &[Vec3], t: &[u32; 3]| t.map(|i| positions[i as usize]);
        let mut first_ids = Vec::with_capacity(scene.objects.len());
        let mut rigid = Vec::with_capacity(scene.objects.len());
        let mut first = statics.faces.len() as u32;
        for object in &scene.objects {
            first_ids.push(first);
            rigid.push(match &object.motion {
                Motion::Rigid { poses } => TraceMesh::with_effort(
                    object
                        .mesh
                        .triangles
                        .iter()
                        .map(|t| corners(&object.mesh.positions, t)),
                    first,
                    effort,
                )
                .map(|mesh| {
                    let local = mesh.bounds();
                    let frames = poses
                        .iter()
                        .map(|pose| invert(pose).map(|inv| (world_box(&local, pose), inv)))
                        .collect();
                    RigidTracer { mesh, frames }
                }),
                Motion::Deforming(_) => None,
            });
            first += object.mesh.faces.len() as u32;
        }
        Self {
            statics: TraceMesh::with_effort(
                statics
                    .triangles
                    .iter()
                    .map(|t| corners(&statics.positions, t)),
                0,
                effort,
            ),
            rigid,
            first_ids,
            table: SurfaceTable::new(scene),
        }
    }

    /// The faces of every traced triangle, indexed by [`Hit::surface`].
    #[must_use]
    pub fn faces(&self) -> &[Faces] {
        self.table.faces()
    }

    /// The faces, spaces and normals of every traced triangle, for the tallies and shadow rays.
    #[must_use]
    pub fn surfaces(&self) -> Surfaces<'_> {
        self.table.surfaces()
    }

    /// What the tallies know of every traced triangle.
    #[must_use]
    pub fn table(&self) -> &SurfaceTable {
        &self.table
    }

    /// The source node of every traced triangle, by global index.
    #[must_use]
    pub fn nodes(&self) -> &[u32] {
        self.table.nodes()
    }

    /// Number of traced triangles (static and moving).
    #[must_use]
    pub fn triangles(&self) -> usize {
        self.table.triangles()
    }

    /// Appends the crossings of `line` with the static geometry, `0 < t < t_max`
    /// ([`LINE_LENGTH`] for the whole line; less for a shadow ray, sparing the nodes beyond).
    pub fn trace_static(&self, line: &Line, t_max: f32, out: &mut Vec<Hit>) {
        self.any_static(line, t_max, &mut pushed(out));
    }

    /// Whether `found` holds for a crossing [`SceneTracer::trace_static`] finds; the walk stops
    /// at the first it holds for.
    pub fn any_static(&self, line: &Line, t_max: f32, found: &mut impl FnMut(Hit) -> bool) -> bool {
        (self.statics.as_ref())
            .is_some_and(|mesh| mesh.any_until(line.origin, line.direction, t_max, found))
    }

    /// Whether `found` holds for a static triangle that meets the convex region of `planes`
    /// ([`TraceMesh::any_in_convex`]); the walk stops at the first it holds for.
    pub fn any_static_in_convex(
        &self,
        planes: &[(DVec3, f64)],
        found: &mut impl FnMut(u32) -> bool,
    ) -> bool {
        (self.statics.as_ref()).is_some_and(|mesh| mesh.any_in_convex(planes, found))
    }

    /// Appends the crossings of `line` with the moving objects as posed at `frame`,
    /// `0 < t < t_max`; `deformed` holds the deforming objects' meshes for that frame.
    pub fn trace_moving(
        &self,
        line: &Line,
        frame: usize,
        deformed: &FrameMeshes,
        t_max: f32,
        out: &mut Vec<Hit>,
    ) {
        self.any_moving(line, (frame, deformed), t_max, &mut pushed(out));
    }

    /// Whether `found` holds for a crossing [`SceneTracer::trace_moving`] finds; the walk
    /// stops at the first it holds for.
    pub fn any_moving(
        &self,
        line: &Line,
        (frame, deformed): (usize, &FrameMeshes),
        t_max: f32,
        found: &mut impl FnMut(Hit) -> bool,
    ) -> bool {
        let ray = Ray::new(line.origin.into(), line.direction.into(), 0.0, t_max);
        for rigid in self.rigid.iter().flatten() {
            if let Some((bounds, inv)) = &rigid.frames[frame] {
                if bounds.intersect_ray(&ray) == f32::INFINITY {
                    continue;
                }
                // The same t along the line in the object's space: origin and direction move
                // together.
                let origin = inv.transform_point3(line.origin);
                let direction = inv.transform_vector3(line.direction);
                if rigid.mesh.any_until(origin, direction, t_max, found) {
                    return true;
                }
            }
        }
        (deformed.meshes.iter().flatten())
            .any(|mesh| mesh.any_until(line.origin, line.direction, t_max, found))
    }

    /// Appends `(line, crossing)` for every crossing of the static geometry by `lines`, in no
    /// particular order: per line, the crossings [`SceneTracer::trace_static`] finds.
    pub fn trace_static_parallel(
        &self,
        lines: &ParallelLines,
        scratch: &mut Scratch,
        out: &mut Vec<(u32, Hit)>,
    ) {
        if let Some(mesh) = &self.statics {
            mesh.trace_parallel(lines, scratch, out);
        }
    }

    /// Appends `(line, crossing)` for every crossing of the moving objects as posed at `frame`
    /// by `lines`, in no particular order: per line, the crossings
    /// [`SceneTracer::trace_moving`] finds.
    pub fn trace_moving_parallel(
        &self,
        lines: &ParallelLines,
        frame: usize,
        deformed: &FrameMeshes,
        scratch: &mut Scratch,
        out: &mut Vec<(u32, Hit)>,
    ) {
        let mut rigid = Vec::new();
        self.trace_rigid_frames(lines, frame..frame + 1, scratch, &mut rigid);
        out.extend(rigid.into_iter().map(|(line, _, hit)| (line, hit)));
        self.trace_deformed_parallel(lines, deformed, scratch, out);
    }

    /// The deforming objects' part of [`SceneTracer::trace_moving_parallel`].
    pub fn trace_deformed_parallel(
        &self,
        lines: &ParallelLines,
        deformed: &FrameMeshes,
        scratch: &mut Scratch,
        out: &mut Vec<(u32, Hit)>,
    ) {
        for mesh in deformed.meshes.iter().flatten() {
            mesh.trace_parallel(lines, scratch, out);
        }
    }

    /// Whether any moving object is rigid (and has triangles).
    #[must_use]
    pub fn moves_rigidly(&self) -> bool {
        self.rigid.iter().any(Option::is_some)
    }

    /// Appends `(line, frame, crossing)` for every crossing of the rigid moving objects, as
    /// posed at each of `frames`, by `lines`, in no particular order: per line and frame, the
    /// rigid objects' crossings [`SceneTracer::trace_moving`] finds, each line moved into an
    /// object's space as a line traced alone is. The lines near an object at any of the
    /// frames are found once; the frames in a row that see the lines along one direction in
    /// the object's space (all of them, for an object that moves without turning) are traced
    /// in one walk of its BVH, their lines side by side.
    pub fn trace_rigid_frames(
        &self,
        lines: &ParallelLines,
        frames: std::ops::Range<usize>,
        scratch: &mut Scratch,
        out: &mut Vec<(u32, u32, Hit)>,
    ) {
        let (mut around, mut near, mut tags) = (Vec::new(), Vec::new(), Vec::new());
        let (mut origins, mut found) = (Vec::new(), Vec::new());
        for rigid in self.rigid.iter().flatten() {
            let posed = &rigid.frames[frames.clone()];
            let Some(reach) = (posed.iter().flatten())
                .map(|(bounds, _)| *bounds)
                .reduce(|a, b| a.union(&b))
            else {
                continue;
            };
            // A superset of the lines near it at each frame, which each frame's test sorts out.
            around.clear();
            lines.through_box(reach.min.into(), reach.max.into(), &mut around);
            if around.is_empty() {
                continue;
            }
            let bits = |inv: &Affine3A| {
                (inv.transform_vector3(lines.direction()).to_array()).map(f32::to_bits)
            };
            let mut frame = frames.start;
            while frame < frames.end {
                let Some((_, inv)) = &rigid.frames[frame] else {
                    frame += 1;
                    continue;
                };
                let direction = inv.transform_vector3(lines.direction());
                let run = direction.to_array().map(f32::to_bits);
                tags.clear();
                origins.clear();
                while let Some(Some((bounds, inv))) = rigid.frames[..frames.end].get(frame)
                    && bits(inv) == run
                {
                    near.clear();
                    let (min, max) = (bounds.min.into(), bounds.max.into());
                    lines.through_box_among(min, max, &around, &mut near);
                    for &i in &near {
                        tags.push((i, frame as u32));
                        origins.push(inv.transform_point3(lines.origins()[i as usize]));
                    }
                    frame += 1;
                }
                if origins.is_empty() {
                    continue;
                }
                let local = ParallelLines::new(direction, std::mem::take(&mut origins));
                found.clear();
                rigid.mesh.trace_parallel(&local, scratch, &mut found);
                out.extend(found.iter().map(|&(k, hit)| {
                    let (line, frame) = tags[k as usize];
                    (line, frame, hit)
                }));
                origins = local.into_origins();
            }
        }
    }

    /// `(line, crossing)` for every crossing of `lines` with the scene as posed at `frame`,
    /// sorted by line and along each line: the scene traced alone at one frame, a bundle at a
    /// time (per line, what [`SceneTracer::trace_frame`] finds). Where each line's crossings
    /// start ([`sort_by_line`]).
    pub fn trace_frame_parallel<'s>(
        &self,
        lines: &ParallelLines,
        frame: usize,
        deformed: &FrameMeshes,
        scratch: &'s mut Scratch,
        out: &mut Vec<(u32, Hit)>,
    ) -> &'s [u32] {
        out.clear();
        self.trace_static_parallel(lines, scratch, out);
        self.trace_moving_parallel(lines, frame, deformed, scratch, out);
        sort_by_line(out, lines.len(), scratch)
    }

    /// Every crossing of `line` with the scene as posed at `frame`, sorted along the line: the
    /// scene traced alone at one frame.
    pub fn trace_frame(
        &self,
        line: &Line,
        frame: usize,
        deformed: &FrameMeshes,
        out: &mut Vec<Hit>,
    ) {
        self.trace_frame_until(line, frame, deformed, LINE_LENGTH, out);
    }

    /// [`SceneTracer::trace_frame`] for `0 < t < t_max` only.
    pub fn trace_frame_until(
        &self,
        line: &Line,
        frame: usize,
        deformed: &FrameMeshes,
        t_max: f32,
        out: &mut Vec<Hit>,
    ) {
        out.clear();
        self.trace_static(line, t_max, out);
        self.trace_moving(line, frame, deformed, t_max, out);
        out.sort_unstable_by(Hit::order);
    }

    /// Whether `found` holds for a crossing [`SceneTracer::trace_frame_until`] finds, in no
    /// particular order: the walks stop at the first it holds for (what a shadow ray needs).
    pub fn any_frame_until(
        &self,
        line: &Line,
        (frame, deformed): (usize, &FrameMeshes),
        t_max: f32,
        found: &mut impl FnMut(Hit) -> bool,
    ) -> bool {
        self.any_static(line, t_max, found)
            || self.any_moving(line, (frame, deformed), t_max, found)
    }

    /// Builds the BVHs of the deforming objects posed at `frame` (none if nothing deforms).
    #[must_use]
    pub fn deformed_at(&self, scene: &Scene, frame: usize) -> FrameMeshes {
        let meshes = scene
            .objects
            .iter()
            .zip(&self.first_ids)
            .map(|(object, &first)| match object.motion {
                Motion::Deforming(_) => {
                    let positions = object.positions_at(frame);
                    TraceMesh::new(
                        object
                            .mesh
                            .triangles
                            .iter()
                            .map(|t| t.map(|i| positions[i as usize])),
                        first,
                    )
                }
                Motion::Rigid { .. } => None,
            })
            .collect();
        FrameMeshes { meshes }
    }
}

/// The deforming objects' meshes as posed at one frame (rebuilt for every frame).
pub struct FrameMeshes {
    /// Per moving object: its mesh at this frame if it deforms.
    meshes: Vec<Option<TraceMesh>>,
}

impl FrameMeshes {
    /// No deforming meshes: for scenes where nothing deforms.
    #[must_use]
    pub fn none() -> Self {
        Self { meshes: Vec::new() }
    }
}

/// The box around `local` (object space) moved by `pose`, padded.
fn world_box(local: &Aabb, pose: &DAffine3) -> Aabb {
    let pad = Vec3A::splat(BOX_PADDING);
    let mut out = Aabb::empty();
    for k in 0..8 {
        let corner = glam::DVec3::new(
            f64::from(if k & 1 == 0 { local.min.x } else { local.max.x }),
            f64::from(if k & 2 == 0 { local.min.y } else { local.max.y }),
            f64::from(if k & 4 == 0 { local.min.z } else { local.max.z }),
        );
        out.extend(Vec3A::from(pose.transform_point3(corner).as_vec3()));
    }
    Aabb::new(out.min - pad, out.max + pad)
}

/// Object space to normalised space, inverted and narrowed to f32; `None` if singular.
fn invert(pose: &DAffine3) -> Option<Affine3A> {
    let det = pose.matrix3.determinant();
    let scale = pose
        .matrix3
        .to_cols_array()
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    if det.is_nan() || det.abs() <= 1e-12 * scale.powi(3) {
        return None;
    }
    let inv = pose.inverse();
    inv.is_finite()
        .then(|| Affine3A::from_mat4(glam::DMat4::from(inv).as_mat4()))
}

/// Sorts `(line, crossing)` pairs of `lines` lines by line, and each line's crossings along
/// it ([`Hit::order`]): a counting sort by line, then each line's few crossings. Where each
/// line's crossings start, and after the last line the end (`lines + 1` offsets from 0).
pub fn sort_by_line<'s>(
    found: &mut Vec<(u32, Hit)>,
    lines: usize,
    scratch: &'s mut Scratch,
) -> &'s [u32] {
    let (starts, sorted) = scratch.sort_buffers();
    // Each line's count two places on; summed, one place on: where each line's crossings go,
    // which the writes below move on to where the next line's start.
    starts.clear();
    starts.resize(lines + 2, 0);
    for &(line, _) in found.iter() {
        starts[line as usize + 2] += 1;
    }
    for i in 2..starts.len() {
        starts[i] += starts[i - 1];
    }
    // Every place is written below: only new places are filled first.
    if sorted.len() < found.len() {
        sorted.resize(found.len(), (0, Hit::new(0.0, 0, true)));
    }
    sorted.truncate(found.len());
    for &(line, hit) in found.iter() {
        let at = &mut starts[line as usize + 1];
        sorted[*at as usize] = (line, hit);
        *at += 1;
    }
    starts.pop();
    for w in starts.windows(2) {
        let run = &mut sorted[w[0] as usize..w[1] as usize];
        if run.len() > 1 {
            sort_along(run);
        }
    }
    std::mem::swap(found, sorted);
    starts
}

/// Sorts one line's crossings along it ([`Hit::order`], by [`Hit::key`]): a few, most often
/// two, in place by insertion; many by the library's sort.
#[inline]
fn sort_along(run: &mut [(u32, Hit)]) {
    if run.len() > 16 {
        run.sort_unstable_by_key(|&(_, hit)| hit.key());
        return;
    }
    for i in 1..run.len() {
        let item = run[i];
        let key = item.1.key();
        let mut j = i;
        while j > 0 && run[j - 1].1.key() > key {
            run[j] = run[j - 1];
            j -= 1;
        }
        run[j] = item;
    }
}
