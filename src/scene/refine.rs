//! Adaptive patches: chosen traced triangles bisected after the lines are traced, without
//! tracing them again.
//!
//! A triangle is cut at the midpoint of its longest edge (Rivara's longest-edge bisection).
//! To leave no T-junction, the triangles across that edge are cut there too; one whose own
//! longest edge is another is first cut at that one (the longest-edge propagation path,
//! LEPP), which keeps every triangle's angles bounded below however often it is cut. Edges
//! are matched by their corners' positions, so a flat-shaded export that repeats a vertex per
//! face is cut without cracks as well.
//!
//! Patches can also be merged: coplanar faces of one mesh and material made one patch
//! ([`merge`]), which changes no triangle.
//!
//! Every cut is recorded: a crossing of a triangle before the cuts finds the triangle it lies
//! in after them from its barycentric coordinates ([`Refinement::locate`]), which is how the
//! intersection list follows the patches without a line traced again.

use std::collections::HashMap;

use glam::{DVec3, Vec3};
use smallvec::SmallVec;

use super::{Faces, Motion, MovingObject, Origin, Patch, Scene, TriangleMesh};

/// A node of the cut tree of one traced triangle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Node {
    /// Not cut: the triangle's global index after the refinement.
    Leaf(u32),
    /// Cut at the midpoint of edge `edge` (from corner `edge` to corner `edge + 1`): `children`
    /// are the half at corner `edge`, then the half at corner `edge + 1`.
    Cut { edge: u8, children: [u32; 2] },
}

/// How the traced triangles of a scene map to those of its refinement.
#[derive(Clone, Debug)]
pub struct Refinement {
    /// The cut trees; node `g` is the root of the old triangle with global index `g`.
    nodes: Vec<Node>,
    /// The old triangles (the roots of `nodes`).
    roots: usize,
    /// The old patch each new patch was cut from (or is).
    parents: Vec<u32>,
}

impl Refinement {
    /// The old patch each new patch was cut from (or is, when not cut), by new patch.
    #[must_use]
    pub fn parents(&self) -> &[u32] {
        &self.parents
    }

    /// Each old triangle not cut, with its new global index.
    pub fn kept(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        (self.nodes[..self.roots].iter().enumerate()).filter_map(|(old, node)| match node {
            Node::Leaf(new) => Some((old as u32, *new)),
            Node::Cut { .. } => None,
        })
    }

    /// The pairs of new triangles that are the two halves of one cut and not cut further
    /// (siblings that are both leaves of the cut trees), by their new global indices.
    fn sibling_leaves(&self) -> impl Iterator<Item = [u32; 2]> + '_ {
        self.nodes.iter().filter_map(|node| match *node {
            Node::Cut { children, .. } => match children.map(|c| self.nodes[c as usize]) {
                [Node::Leaf(a), Node::Leaf(b)] => Some([a, b]),
                _ => None,
            },
            Node::Leaf(_) => None,
        })
    }

    /// Whether old triangle `old` was cut.
    #[must_use]
    pub fn is_cut(&self, old: u32) -> bool {
        matches!(self.nodes[old as usize], Node::Cut { .. })
    }

    /// The new global index of the triangle holding the point of old triangle `old` at
    /// barycentric coordinates `bary` (of its corners in order; they need not be normalised).
    /// A point on a cut goes to the half at the cut edge's first corner.
    #[must_use]
    pub fn locate(&self, old: u32, bary: [f64; 3]) -> u32 {
        self.locate_in(old, bary).0
    }

    /// [`Refinement::locate`], with the point's barycentric coordinates in the new triangle
    /// (of its corners in order).
    #[must_use]
    pub fn locate_in(&self, old: u32, bary: [f64; 3]) -> (u32, [f64; 3]) {
        let mut node = old as usize;
        let mut l = bary;
        loop {
            match self.nodes[node] {
                Node::Leaf(id) => return (id, l),
                Node::Cut { edge, children } => {
                    let k = usize::from(edge);
                    let (a, b, c) = (l[k], l[(k + 1) % 3], l[(k + 2) % 3]);
                    // A point of the triangle (a, b, c) in the half (a, m, c) or (m, b, c),
                    // m = (a + b) / 2: its coordinates there follow from b = 2m − a
                    // (respectively a = 2m − b). The halves keep their corners in that order.
                    (node, l) = if a >= b {
                        (children[0] as usize, [a - b, 2.0 * b, c])
                    } else {
                        (children[1] as usize, [2.0 * a, b - a, c])
                    };
                }
            }
        }
    }
}

/// The corner index where a triangle's longest edge starts (the first one on ties): the edge
/// bisection cuts.
#[must_use]
pub fn longest_edge(corners: [Vec3; 3]) -> usize {
    let lengths = [0, 1, 2]
        .map(|k| (corners[(k + 1) % 3].as_dvec3() - corners[k].as_dvec3()).length_squared());
    (0..3).fold(
        0,
        |best, k| if lengths[k] > lengths[best] { k } else { best },
    )
}

/// Barycentric coordinates of `p` in the triangle `corners` (projected on its plane), or
/// `None` for a degenerate triangle.
#[must_use]
pub fn barycentric(corners: [DVec3; 3], p: DVec3) -> Option<[f64; 3]> {
    let [a, b, c] = corners;
    let n = (b - a).cross(c - a);
    let area2 = n.length_squared();
    if area2 <= 0.0 || !area2.is_finite() {
        return None;
    }
    let la = (c - b).cross(p - b).dot(n) / area2;
    let lb = (a - c).cross(p - c).dot(n) / area2;
    Some([la, lb, 1.0 - la - lb])
}

/// Edge key: its corners' position bits, in order.
type EdgeKey = ([u32; 3], [u32; 3]);

/// One mesh being cut.
struct MeshCutter {
    positions: Vec<Vec3>,
    /// Triangles by leaf id: a cut triangle's first half keeps its id, the second is appended.
    triangles: Vec<[u32; 3]>,
    /// The cut-tree node of each leaf (local node ids).
    leaf_node: Vec<u32>,
    /// Local cut-tree nodes; `Leaf` holds a leaf id here. Roots are `0..triangles`.
    nodes: Vec<Node>,
    /// Where each leaf lies on its source triangle, by leaf id (empty if the mesh's origins are
    /// unknown).
    origins: Vec<Origin>,
    /// The leaves on each edge (two, but for an exported mesh's odd edges).
    edges: FastMap<EdgeKey, SmallVec<[u32; 2]>>,
    /// The midpoint vertex of each cut edge, by its corners' indices.
    midpoints: FastMap<(u32, u32), u32>,
}

/// A map only looked up (never iterated: its order would be the hasher's) with a fast,
/// fixed hasher: a cutter links every edge of the scene's triangles, a few hundred thousand
/// in a round of the split, where the standard hasher took most of the cutter's time.
type FastMap<K, V> = HashMap<K, V, foldhash::fast::FixedState>;

/// Propagation paths longer than this cut the neighbours at the shared edge instead (still
/// without T-junctions; only the shape guarantee is lost). Never reached in practice: a path
/// ends where the longest edges stop growing.
const MAX_PATH: usize = 64;

impl MeshCutter {
    fn new(mesh: &TriangleMesh) -> Self {
        let mut cutter = Self {
            positions: mesh.positions.clone(),
            triangles: mesh.triangles.clone(),
            leaf_node: (0..mesh.triangles.len() as u32).collect(),
            origins: if mesh.origins.len() == mesh.triangles.len() {
                mesh.origins.clone()
            } else {
                Vec::new()
            },
            nodes: (0..mesh.triangles.len() as u32).map(Node::Leaf).collect(),
            edges: FastMap::default(),
            midpoints: FastMap::default(),
        };
        for t in 0..cutter.triangles.len() as u32 {
            cutter.link(t);
        }
        cutter
    }

    fn key(&self, a: u32, b: u32) -> EdgeKey {
        let bits = |v: u32| self.positions[v as usize].to_array().map(f32::to_bits);
        let (pa, pb) = (bits(a), bits(b));
        if pa <= pb { (pa, pb) } else { (pb, pa) }
    }

    fn edge_key(&self, t: u32, k: usize) -> EdgeKey {
        let tri = self.triangles[t as usize];
        self.key(tri[k], tri[(k + 1) % 3])
    }

    fn longest(&self, t: u32) -> usize {
        longest_edge(self.triangles[t as usize].map(|v| self.positions[v as usize]))
    }

    fn link(&mut self, t: u32) {
        for k in 0..3 {
            let key = self.edge_key(t, k);
            self.edges.entry(key).or_default().push(t);
        }
    }

    fn unlink(&mut self, t: u32) {
        for k in 0..3 {
            let key = self.edge_key(t, k);
            if let Some(list) = self.edges.get_mut(&key) {
                list.retain(|o| *o != t);
            }
        }
    }

    /// Cuts leaf `t` at its longest edge, and whatever the propagation path needs. Meshes as
    /// exported hold edges shared by more than two triangles, overlapping, duplicated and
    /// degenerate ones: every leaf on the edge is cut once (a degenerate one may hold the edge
    /// twice), and a leaf the propagation has cut meanwhile is done.
    fn bisect(&mut self, t: u32, depth: usize) {
        let node = self.leaf_node[t as usize];
        for round in 0.. {
            if self.leaf_node[t as usize] != node {
                // Cut by a neighbour's propagation: done.
                return;
            }
            let k = self.longest(t);
            let key = self.edge_key(t, k);
            let mut others: Vec<u32> = (self.edges.get(&key).into_iter().flatten())
                .copied()
                .filter(|&o| o != t)
                .collect();
            others.sort_unstable();
            others.dedup();
            let off_path: Vec<u32> = others
                .iter()
                .copied()
                .filter(|&o| self.edge_key(o, self.longest(o)) != key)
                .collect();
            if off_path.is_empty() || depth >= MAX_PATH || round >= MAX_PATH {
                self.cut(t, k);
                for o in others {
                    if let Some(edge) = (0..3).find(|&e| self.edge_key(o, e) == key) {
                        self.cut(o, edge);
                    }
                }
                return;
            }
            for o in off_path {
                // Cutting `o` at its longer edge leaves `key` on one of its halves; that half
                // may still have another longest edge: the loop looks again. An earlier one's
                // propagation may have cut `o` off the edge already.
                if self.edges.get(&key).is_some_and(|on| on.contains(&o)) {
                    self.bisect(o, depth + 1);
                }
            }
        }
    }

    /// The cutter of `mesh` with each triangle cut as its heap-ordered tree in `cuts` says.
    fn with_cuts(mesh: &TriangleMesh, cuts: &[u32]) -> Self {
        let mut cutter = Self::new(mesh);
        for (t, &c) in cuts.iter().enumerate() {
            cutter.cut_tree(t as u32, c);
        }
        cutter
    }

    /// Cuts root `root` as the heap-ordered tree `cuts` says ([`cut`]).
    fn cut_tree(&mut self, root: u32, cuts: u32) {
        let mut stack = vec![(root, 1u32)];
        while let Some((node, heap)) = stack.pop() {
            if heap >= 32 || cuts & (1 << heap) == 0 {
                continue;
            }
            if let Node::Leaf(leaf) = self.nodes[node as usize] {
                self.bisect(leaf, 0);
            }
            if let Node::Cut { children, .. } = self.nodes[node as usize] {
                stack.push((children[0], 2 * heap));
                stack.push((children[1], 2 * heap + 1));
            }
        }
    }

    /// Cuts leaf `t` at the midpoint of its edge `k`.
    fn cut(&mut self, t: u32, k: usize) {
        self.unlink(t);
        let tri = self.triangles[t as usize];
        let (a, b, c) = (tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]);
        let positions = &mut self.positions;
        let m = *self
            .midpoints
            .entry((a.min(b), a.max(b)))
            .or_insert_with(|| {
                let p = super::midpoint(
                    positions[a as usize].as_dvec3(),
                    positions[b as usize].as_dvec3(),
                );
                positions.push(p.as_vec3());
                (positions.len() - 1) as u32
            });
        let second = self.triangles.len() as u32;
        self.triangles[t as usize] = [a, m, c];
        self.triangles.push([m, b, c]);
        if let Some(origin) = self.origins.get(t as usize) {
            let [first_half, second_half] = origin.halves(k);
            self.origins[t as usize] = first_half;
            self.origins.push(second_half);
        }
        let parent = self.leaf_node[t as usize] as usize;
        let children = [self.nodes.len() as u32, self.nodes.len() as u32 + 1];
        self.nodes[parent] = Node::Cut {
            edge: k as u8,
            children,
        };
        self.nodes.push(Node::Leaf(t));
        self.nodes.push(Node::Leaf(second));
        self.leaf_node[t as usize] = children[0];
        self.leaf_node.push(children[1]);
        self.link(t);
        self.link(second);
    }
}

/// The traced meshes in global order (the static one, then each moving object's), each with
/// whether it deforms (its triangles are kept as they are).
fn traced_meshes(scene: &Scene) -> Vec<(&TriangleMesh, bool)> {
    std::iter::once((&scene.statics, false))
        .chain(scene.objects.iter().map(|o| (&o.mesh, !o.is_rigid())))
        .collect()
}

/// Each traced triangle's cuts (a heap-ordered bisection tree per triangle, as [`cut`] takes
/// them) from the longest prefix of `order` (traced triangle, node of its tree) whose patches,
/// the cuts the neighbours need included, stay within `budget`.
#[must_use]
pub fn within_budget(scene: &Scene, order: &[(u32, u32)], budget: usize) -> Vec<u32> {
    let all = masks(scene, order);
    if patches_after(scene, &all) <= budget {
        return all;
    }
    longest_within(scene, order, budget)
}

/// Each traced triangle's cuts for the (triangle, node) pairs of `order`.
fn masks(scene: &Scene, order: &[(u32, u32)]) -> Vec<u32> {
    let triangles: usize = traced_meshes(scene)
        .iter()
        .map(|(m, _)| m.triangles.len())
        .sum();
    let mut cuts = vec![0u32; triangles];
    for &(t, heap) in order {
        cuts[t as usize] |= 1 << heap;
    }
    cuts
}

/// [`within_budget`] where the whole of `order` is known not to fit: more cuts never make
/// fewer patches, so the longest prefix that fits is found by bisection.
fn longest_within(scene: &Scene, order: &[(u32, u32)], budget: usize) -> Vec<u32> {
    let fits = |k: usize| patches_after(scene, &masks(scene, &order[..k])) <= budget;
    let (mut fit, mut over) = (0, order.len());
    while over - fit > 1 {
        let mid = fit + (over - fit) / 2;
        if fits(mid) {
            fit = mid;
        } else {
            over = mid;
        }
    }
    masks(scene, &order[..fit])
}

/// [`cut`] of `scene` by [`within_budget`]'s cuts, and those cuts: the whole of `order` cut
/// at once where its patches are within `budget` (as in most of the split's rounds), one
/// cutting where counting them first and then cutting took two.
#[must_use]
pub fn cut_within_budget(
    scene: &Scene,
    order: &[(u32, u32)],
    budget: usize,
) -> (Vec<u32>, (Scene, Refinement)) {
    let all = masks(scene, order);
    let whole = cut(scene, &all);
    if whole.0.patches.len() <= budget {
        return (all, whole);
    }
    let cuts = longest_within(scene, order, budget);
    let fitted = cut(scene, &cuts);
    (cuts, fitted)
}

/// How many patches [`cut`] would make of `scene` with `cuts`, the cuts the neighbours need
/// included, without building the scene (to keep a budget).
#[must_use]
pub fn patches_after(scene: &Scene, cuts: &[u32]) -> usize {
    let members = members(scene);
    let shared: Vec<bool> = members.iter().map(|&m| m > 1).collect();
    let mut first = 0;
    let mut patches = 0;
    for (mesh, deforming) in traced_meshes(scene) {
        let count = mesh.triangles.len();
        let faces = |t: usize| 1 + usize::from(mesh.faces[t].back.is_some());
        let mine = &cuts[first..first + count];
        if deforming || mine.iter().all(|&c| c & !1 == 0) {
            patches += (0..count).map(faces).sum::<usize>();
        } else {
            let cutter = MeshCutter::with_cuts(mesh, mine);
            for root in 0..count {
                let mut leaves = 0;
                let mut stack = vec![root as u32];
                while let Some(node) = stack.pop() {
                    match cutter.nodes[node as usize] {
                        Node::Leaf(_) => leaves += 1,
                        Node::Cut { children, .. } => stack.extend(children),
                    }
                }
                let f = mesh.faces[root];
                patches += [Some(f.front), f.back]
                    .into_iter()
                    .flatten()
                    .map(|p| if shared[p as usize] { 1 } else { leaves })
                    .sum::<usize>();
            }
        }
        first += count;
    }
    // A merged patch counted once per face above: once in all.
    patches
        - shared
            .iter()
            .zip(&members)
            .filter(|&(&s, _)| s)
            .map(|(_, &m)| m as usize - 1)
            .sum::<usize>()
}

/// How many traced faces each patch of `scene` covers: 1, or more for a patch merged from
/// several ([`merge`]).
#[must_use]
pub fn members(scene: &Scene) -> Vec<u32> {
    let mut count = vec![0u32; scene.patches.len()];
    for (mesh, _) in traced_meshes(scene) {
        for f in &mesh.faces {
            for p in [Some(f.front), f.back].into_iter().flatten() {
                count[p as usize] += 1;
            }
        }
    }
    count
}

/// Dense ids from 0 for groups given by a representative per item (`root[p]`, an item of the
/// group): each group numbered in the order of its first item, as [`merge`] takes them.
#[must_use]
pub fn dense_ids(root: Vec<u32>) -> Vec<u32> {
    let mut id = vec![u32::MAX; root.iter().map(|&r| r as usize + 1).max().unwrap_or(0)];
    let mut next = 0;
    (root.into_iter())
        .map(|r| {
            if id[r as usize] == u32::MAX {
                id[r as usize] = next;
                next += 1;
            }
            id[r as usize]
        })
        .collect()
}

/// Merges `scene`'s patches: old patch `p` becomes new patch `into[p]` (the new ids dense
/// from 0). The patches merged into one must be faces of coplanar traced triangles of one
/// source primitive (one node, mesh and primitive) with one material and side, which the
/// caller decides ([`crate::adaptive`]); the merged patch keeps its first member's source,
/// the others' source triangles ([`Patch::merged`]) and the sum of their areas. No triangle changes: the intersection list stays as it is.
#[must_use]
pub fn merge(scene: &Scene, into: &[u32]) -> Scene {
    let count = into.iter().map(|&n| n as usize + 1).max().unwrap_or(0);
    let mut patches: Vec<Option<Patch>> = vec![None; count];
    for (old, &new) in scene.patches.iter().zip(into) {
        match &mut patches[new as usize] {
            Some(patch) => {
                patch.area += old.area;
                let triangles = std::iter::once(old.source.triangle).chain(old.merged.clone());
                patch
                    .merged
                    .extend(triangles.filter(|&t| t != patch.source.triangle));
            }
            slot => *slot = Some(old.clone()),
        }
    }
    for patch in patches.iter_mut().flatten() {
        patch.merged.sort_unstable();
        patch.merged.dedup();
    }
    let mut merged = scene.clone();
    merged.patches = patches
        .into_iter()
        .map(|p| p.expect("merge: every new patch has a member"))
        .collect();
    let remap = |mesh: &mut TriangleMesh| {
        for f in &mut mesh.faces {
            f.front = into[f.front as usize];
            f.back = f.back.map(|b| into[b as usize]);
        }
    };
    remap(&mut merged.statics);
    for object in &mut merged.objects {
        remap(&mut object.mesh);
    }
    merged
}

/// Makes every face of `scene` a patch of its own: a patch merged from several faces
/// ([`merge`]) is taken apart (each face with its share of the patch's area, by the areas of
/// their triangles, and the patch's source); the others stay as they are. Returns the new
/// scene and, for each of its patches, the patch of `scene` it is (part of). No triangle
/// changes.
#[must_use]
pub fn apart(scene: &Scene) -> (Scene, Vec<u32>) {
    let members = members(scene);
    // Each merged patch's triangles' total area in their meshes' own space, to share its area.
    let mut own_area = vec![0.0f64; scene.patches.len()];
    let area = |mesh: &TriangleMesh, t: usize| {
        let [a, b, c] = mesh.triangles[t].map(|v| mesh.positions[v as usize].as_dvec3());
        crate::scene::subdivide::triangle_area(a, b, c)
    };
    for (mesh, _) in traced_meshes(scene) {
        for (t, f) in mesh.faces.iter().enumerate() {
            for p in [Some(f.front), f.back].into_iter().flatten() {
                own_area[p as usize] += area(mesh, t);
            }
        }
    }
    let mut patches = Vec::with_capacity(scene.patches.len());
    let mut parents = Vec::with_capacity(scene.patches.len());
    let mut apart = scene.clone();
    let meshes =
        std::iter::once(&mut apart.statics).chain(apart.objects.iter_mut().map(|o| &mut o.mesh));
    for mesh in meshes {
        for t in 0..mesh.triangles.len() {
            let share = area(mesh, t);
            let mut piece = |p: u32| {
                let mut patch = scene.patches[p as usize].clone();
                if members[p as usize] > 1 {
                    patch.area *= if own_area[p as usize] > 0.0 {
                        share / own_area[p as usize]
                    } else {
                        1.0 / f64::from(members[p as usize])
                    };
                    patch.merged = Vec::new();
                }
                patches.push(patch);
                parents.push(p);
                (patches.len() - 1) as u32
            };
            let f = mesh.faces[t];
            let front = piece(f.front);
            let back = f.back.map(&mut piece);
            mesh.faces[t] = Faces { front, back };
        }
    }
    apart.patches = patches;
    (apart, parents)
}

/// `pieces` (a scene whose triangles are those of some scene, maybe cut finer) with its faces
/// put back in the patches they are parts of: piece `k` in `patches[of[k]]`.
#[must_use]
pub fn regroup(pieces: &Scene, of: &[u32], patches: Vec<Patch>) -> Scene {
    let mut grouped = pieces.clone();
    let meshes = std::iter::once(&mut grouped.statics)
        .chain(grouped.objects.iter_mut().map(|o| &mut o.mesh));
    for mesh in meshes {
        for f in &mut mesh.faces {
            f.front = of[f.front as usize];
            f.back = f.back.map(|b| of[b as usize]);
        }
    }
    grouped.patches = patches;
    grouped
}

/// Cuts the traced triangles of `scene` as `cuts` says (by global index: the static
/// triangles, then each moving object's), with the cuts their neighbours need. A triangle's
/// cuts are a bisection tree in heap order: bit 1 cuts the triangle, bits `2n` and `2n + 1`
/// the two halves of node `n` (the half at the cut edge's first corner, then the other), so
/// `0b10` cuts it once and `0b1110` into four. A half already cut for a neighbour is not cut
/// again. The triangles of deforming objects are kept as they are (their cuts are ignored):
/// their crossings at each frame would need the pose of every frame to be placed.
///
/// Returns the new scene, whose patches are those of the cut triangles' faces numbered in the
/// order of their triangles (a cut triangle's pieces in place of it, each with its share of
/// the area; a patch merged from several faces ([`merge`]) stays one patch, whatever its
/// triangles are cut into), and the map from old triangles to new.
pub fn cut(scene: &Scene, cuts: &[u32]) -> (Scene, Refinement) {
    let members = members(scene);
    // A merged patch's new id, once its first piece is numbered.
    let mut kept: HashMap<u32, u32> = HashMap::new();
    let meshes = traced_meshes(scene);
    let mut first = 0;
    let mut new_first = 0u32;
    let mut patches: Vec<Patch> = Vec::with_capacity(scene.patches.len());
    let mut parents: Vec<u32> = Vec::with_capacity(scene.patches.len());
    let mut nodes: Vec<Node> = Vec::new();
    let mut extra: Vec<Node> = Vec::new();
    let mut new_meshes = Vec::with_capacity(meshes.len());
    // Every old triangle is a root; the cut nodes are numbered after them all.
    let roots: usize = meshes.iter().map(|(m, _)| m.triangles.len()).sum();
    for (mesh, deforming) in meshes {
        let count = mesh.triangles.len();
        let cutter = if deforming {
            MeshCutter::new(mesh)
        } else {
            MeshCutter::with_cuts(mesh, &cuts[first..first + count])
        };
        // The leaves depth first from each root, with their depth and root: a triangle's
        // pieces stay together, in the source's order.
        let mut order = Vec::with_capacity(cutter.triangles.len());
        for root in 0..count {
            let mut stack = vec![(root as u32, 0u32)];
            while let Some((node, depth)) = stack.pop() {
                match cutter.nodes[node as usize] {
                    Node::Leaf(leaf) => order.push((leaf, depth, root)),
                    Node::Cut { children, .. } => {
                        stack.push((children[1], depth + 1));
                        stack.push((children[0], depth + 1));
                    }
                }
            }
        }
        // Leaf id → new global index.
        let mut global = vec![0u32; cutter.triangles.len()];
        let mut out = TriangleMesh {
            positions: cutter.positions.clone(),
            triangles: Vec::with_capacity(order.len()),
            faces: Vec::with_capacity(order.len()),
            origins: Vec::with_capacity(cutter.origins.len().min(order.len())),
        };
        for (i, &(leaf, depth, root)) in order.iter().enumerate() {
            global[leaf as usize] = new_first + i as u32;
            let faces = mesh.faces[root];
            let mut piece = |id: u32| {
                // A merged patch stays one: its pieces (cut for a neighbour) all in it.
                if members[id as usize] > 1 {
                    if let Some(&new) = kept.get(&id) {
                        return new;
                    }
                    kept.insert(id, patches.len() as u32);
                    patches.push(scene.patches[id as usize].clone());
                    parents.push(id);
                    return (patches.len() - 1) as u32;
                }
                let mut patch = scene.patches[id as usize].clone();
                patch.area /= f64::from(1u32 << depth.min(31));
                patches.push(patch);
                parents.push(id);
                (patches.len() - 1) as u32
            };
            let front = piece(faces.front);
            let back = faces.back.map(&mut piece);
            out.triangles.push(cutter.triangles[leaf as usize]);
            out.faces.push(Faces { front, back });
            if let Some(&origin) = cutter.origins.get(leaf as usize) {
                out.origins.push(origin);
            }
        }
        // This mesh's nodes in global numbering: roots at `first..first + count`, the rest
        // appended after every root.
        let offset = |local: u32, extra_base: usize| -> u32 {
            if (local as usize) < count {
                (first + local as usize) as u32
            } else {
                (roots + extra_base + local as usize - count) as u32
            }
        };
        let extra_base = extra.len();
        let translate = |node: Node| match node {
            Node::Leaf(leaf) => Node::Leaf(global[leaf as usize]),
            Node::Cut { edge, children } => Node::Cut {
                edge,
                children: children.map(|c| offset(c, extra_base)),
            },
        };
        nodes.extend(cutter.nodes[..count].iter().map(|&n| translate(n)));
        extra.extend(cutter.nodes[count..].iter().map(|&n| translate(n)));
        first += count;
        new_first += order.len() as u32;
        new_meshes.push(out);
    }
    nodes.extend(extra);
    let mut refined = scene.clone();
    let mut new_meshes = new_meshes.into_iter();
    refined.statics = new_meshes.next().expect("the static mesh");
    for (object, mesh) in refined.objects.iter_mut().zip(new_meshes) {
        if let Motion::Rigid { .. } = object.motion {
            object.mesh = mesh;
        } else {
            object.mesh.faces = mesh.faces;
        }
    }
    refined.patches = patches;
    (
        refined,
        Refinement {
            nodes,
            roots,
            parents,
        },
    )
}

/// The corners of a scene's traced triangles by global index (the static triangles, then each
/// moving object's), as the intersection list numbers them.
pub struct Corners<'a> {
    scene: &'a Scene,
    /// First global index of each mesh: the static one, then each object's.
    firsts: Vec<usize>,
}

impl<'a> Corners<'a> {
    /// The corners of `scene`'s triangles.
    #[must_use]
    pub fn new(scene: &'a Scene) -> Self {
        let sizes = std::iter::once(scene.statics.triangles.len())
            .chain(scene.objects.iter().map(|o| o.mesh.triangles.len()));
        let firsts = sizes
            .scan(0, |first, n| {
                let start = *first;
                *first += n;
                Some(start)
            })
            .collect();
        Self { scene, firsts }
    }

    /// The moving object (`None`: static geometry), its mesh and the index within it of
    /// triangle `global`.
    fn find(&self, global: u32) -> (Option<&'a MovingObject>, &'a TriangleMesh, usize) {
        let m = self.firsts.partition_point(|&f| f <= global as usize) - 1;
        let t = global as usize - self.firsts[m];
        match m.checked_sub(1) {
            None => (None, &self.scene.statics, t),
            Some(k) => (Some(&self.scene.objects[k]), &self.scene.objects[k].mesh, t),
        }
    }

    /// Triangle `global`'s corners in its mesh's own space (normalised space for static
    /// geometry, object space for a rigid object, frame 0 for a deforming one): the space
    /// its cuts are decided in.
    #[must_use]
    pub fn own(&self, global: u32) -> [Vec3; 3] {
        let (_, mesh, t) = self.find(global);
        mesh.triangles[t].map(|v| mesh.positions[v as usize])
    }

    /// The faces (patches) of triangle `global`.
    #[must_use]
    pub fn faces(&self, global: u32) -> Faces {
        let (_, mesh, t) = self.find(global);
        mesh.faces[t]
    }

    /// Triangle `global`'s corners in normalised space at `frame` (`None`: a static triangle),
    /// or `None` for a deforming object's (posing one costs the whole mesh).
    #[must_use]
    pub fn posed(&self, global: u32, frame: Option<usize>) -> Option<[DVec3; 3]> {
        let (object, mesh, t) = self.find(global);
        posed(mesh, t, object.map(|o| &o.motion), frame)
    }
}

/// Triangle `t` of `mesh` in normalised space at `frame`, moved by `motion` (`None`: static
/// geometry, as it is), or `None` for a deforming object's.
fn posed(
    mesh: &TriangleMesh,
    t: usize,
    motion: Option<&Motion>,
    frame: Option<usize>,
) -> Option<[DVec3; 3]> {
    // Read only when posed: a deforming object's mesh may hold no triangles here.
    let own = || mesh.triangles[t].map(|v| mesh.positions[v as usize].as_dvec3());
    match (motion, frame) {
        (None, _) => Some(own()),
        (Some(Motion::Rigid { poses }), Some(f)) => {
            Some(own().map(|p| poses[f].transform_point3(p)))
        }
        _ => None,
    }
}

/// Refinements one after the other (each cutting the scene the one before it made), kept to
/// move the crossings of the rigid objects at the frames after the first through all of them
/// at once ([`Chain::locate`]): the same triangle, step by step, as moving them after each cut.
#[derive(Default)]
pub struct Chain {
    steps: Vec<Step>,
    /// Per step, each triangle's index after the last step if no step from this one on cuts
    /// it (`u32::MAX` if one does): a crossing is carried through the steps that only
    /// renumber its triangle at once. Made at the first [`Chain::locate`].
    through: std::sync::OnceLock<Vec<Vec<u32>>>,
}

/// One refinement of a [`Chain`] and the rigid objects' triangles it cut.
struct Step {
    refinement: Refinement,
    /// First global index of each moving object's triangles.
    firsts: Vec<usize>,
    /// Each moving object's triangles in object space (a deforming one's: none, its triangles
    /// are never cut).
    meshes: Vec<TriangleMesh>,
}

impl Chain {
    /// Adds `refinement`, which cut `scene`.
    pub fn push(&mut self, scene: &Scene, refinement: Refinement) {
        let corners = Corners::new(scene);
        let meshes = (scene.objects.iter())
            .map(|o| match o.motion {
                Motion::Rigid { .. } => o.mesh.clone(),
                Motion::Deforming(_) => TriangleMesh::default(),
            })
            .collect();
        self.steps.push(Step {
            refinement,
            firsts: corners.firsts[1..].to_vec(),
            meshes,
        });
    }

    /// [`Chain::through`], from the last step back.
    fn through(&self) -> Vec<Vec<u32>> {
        let mut out: Vec<Vec<u32>> = Vec::with_capacity(self.steps.len());
        for step in self.steps.iter().rev() {
            let r = &step.refinement;
            let after = out.last();
            let row = (0..r.roots as u32)
                .map(|g| match r.nodes[g as usize] {
                    Node::Leaf(new) => after.map_or(new, |a| a[new as usize]),
                    Node::Cut { .. } => u32::MAX,
                })
                .collect();
            out.push(row);
        }
        out.reverse();
        out
    }

    /// The finest cuts of the chain: the pairs of triangles, after every refinement, that are
    /// the two halves of one cut (made by any step) that no later step cut again. Each
    /// triangle is in at most one pair. Merging each pair back into its cut triangle undoes
    /// one level of bisection where the cuts end: the pieces one level coarser.
    #[must_use]
    pub fn siblings(&self) -> Vec<[u32; 2]> {
        let through = self.through.get_or_init(|| self.through());
        let mut pairs = Vec::new();
        for (k, step) in self.steps.iter().enumerate() {
            // A step's new triangles are the next step's old ones.
            let after = through.get(k + 1);
            pairs.extend(
                step.refinement
                    .sibling_leaves()
                    .filter_map(|pair| match after {
                        None => Some(pair),
                        Some(after) => {
                            let pair = pair.map(|t| after[t as usize]);
                            (!pair.contains(&u32::MAX)).then_some(pair)
                        }
                    }),
            );
        }
        pairs
    }

    /// The triangle, after every refinement, holding `point` (in normalised space) of moving
    /// triangle `global` of the first refinement's scene at `frame`, the objects posed as in
    /// `scene` (any scene of the chain: cuts keep the poses). The point's barycentric
    /// coordinates are measured once, in the first triangle cut, and carried down through
    /// the cuts ([`Refinement::locate_in`]); a point within a rounding error of a cut may go
    /// to the other half than measuring them again in each piece would send it.
    #[must_use]
    pub fn locate(&self, scene: &Scene, global: u32, frame: usize, point: DVec3) -> u32 {
        let through = self.through.get_or_init(|| self.through());
        let mut g = global;
        let mut bary: Option<[f64; 3]> = None;
        for (step, through) in self.steps.iter().zip(through) {
            if through[g as usize] != u32::MAX {
                // Only renumbered from here on.
                return through[g as usize];
            }
            if bary.is_none() {
                let k = step.firsts.partition_point(|&f| f <= g as usize) - 1;
                let t = g as usize - step.firsts[k];
                let motion = Some(&scene.objects[k].motion);
                bary = posed(&step.meshes[k], t, motion, Some(frame))
                    .and_then(|corners| barycentric(corners, point));
            }
            match bary {
                Some(b) => {
                    let (next, b) = step.refinement.locate_in(g, b);
                    (g, bary) = (next, Some(b));
                }
                None => g = step.refinement.locate(g, [1.0, 0.0, 0.0]),
            }
        }
        g
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    /// An n × n grid of squares, each two triangles, on z = 0 over [0, 1]²: one static mesh.
    fn grid(n: u32) -> TriangleMesh {
        let mut mesh = TriangleMesh::default();
        for j in 0..=n {
            for i in 0..=n {
                mesh.positions
                    .push(Vec3::new(i as f32 / n as f32, j as f32 / n as f32, 0.0));
            }
        }
        let v = |i: u32, j: u32| j * (n + 1) + i;
        for j in 0..n {
            for i in 0..n {
                mesh.triangles.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
                mesh.triangles.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
            }
        }
        mesh
    }

    fn cutter_with(mesh: &TriangleMesh, marked: impl Fn(usize) -> bool) -> MeshCutter {
        let mut cutter = MeshCutter::new(mesh);
        for t in 0..mesh.triangles.len() {
            if marked(t) && matches!(cutter.nodes[t], Node::Leaf(_)) {
                cutter.bisect(t as u32, 0);
            }
        }
        cutter
    }

    fn area(c: [Vec3; 3]) -> f64 {
        let [a, b, c] = c.map(Vec3::as_dvec3);
        0.5 * (b - a).cross(c - a).length()
    }

    #[test]
    fn cuts_leave_no_t_junction_and_keep_the_area() {
        let mesh = grid(4);
        // Cut some triangles, then some of the pieces again (deeper cuts propagate further).
        let mut cutter = cutter_with(&mesh, |t| t % 3 == 0);
        for t in 0..cutter.triangles.len() as u32 {
            if t % 5 == 0 {
                cutter.bisect(t, 0);
            }
        }
        let corners = |t: &[u32; 3]| t.map(|v| cutter.positions[v as usize]);
        let total: f64 = cutter.triangles.iter().map(|t| area(corners(t))).sum();
        assert!((total - 1.0).abs() < 1e-9, "{total}");
        assert!(cutter.triangles.len() > 2 * mesh.triangles.len());
        // Every edge is shared by two triangles, except on the grid's outline: a T-junction
        // would leave an edge with one triangle inside the square.
        let mut uses: HashMap<EdgeKey, (u32, [Vec3; 2])> = HashMap::new();
        for t in &cutter.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let e = uses.entry(cutter.key(a, b)).or_insert((
                    0,
                    [cutter.positions[a as usize], cutter.positions[b as usize]],
                ));
                e.0 += 1;
            }
        }
        for (n, [a, b]) in uses.values() {
            let outline = [0, 1]
                .iter()
                .any(|&c| (a[c] == 0.0 && b[c] == 0.0) || (a[c] == 1.0 && b[c] == 1.0));
            assert_eq!(*n, if outline { 1 } else { 2 }, "edge {a} {b}");
        }
        // Longest-edge bisection keeps shapes: no angle below half the smallest one before
        // (45° here; Rivara's bound).
        for t in &cutter.triangles {
            let c = corners(t).map(Vec3::as_dvec3);
            for k in 0..3 {
                let (u, v) = (c[(k + 1) % 3] - c[k], c[(k + 2) % 3] - c[k]);
                let angle = u.angle_between(v).to_degrees();
                assert!(angle > 22.0, "{angle}° in {c:?}");
            }
        }
    }

    #[test]
    fn a_point_is_located_in_the_piece_that_holds_it() {
        let mesh = grid(2);
        let cutter = cutter_with(&mesh, |t| t != 5);
        // Leaves keep their leaf ids: locate names the cutter's triangles.
        let refinement = Refinement {
            nodes: cutter.nodes.clone(),
            roots: mesh.triangles.len(),
            parents: Vec::new(),
        };
        let mut state = 12345u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for old in 0..mesh.triangles.len() {
            let c = mesh.triangles[old].map(|v| mesh.positions[v as usize].as_dvec3());
            for _ in 0..200 {
                let (mut u, mut v) = (uniform(), uniform());
                if u + v > 1.0 {
                    (u, v) = (1.0 - u, 1.0 - v);
                }
                let p = c[0] + (c[1] - c[0]) * u + (c[2] - c[0]) * v;
                let bary = barycentric(c, p).unwrap();
                let leaf = refinement.locate(old as u32, bary);
                let piece = cutter.triangles[leaf as usize]
                    .map(|v| cutter.positions[v as usize].as_dvec3());
                let inside = barycentric(piece, p).unwrap();
                assert!(
                    inside.iter().all(|&l| l > -1e-6),
                    "{p} of {old} located in {leaf}: {inside:?}"
                );
            }
        }
    }

    /// A unit box whose every face, a quad ABCD, is drawn as three overlapping triangles
    /// (ABC, ACD and ABD: each edge of the quad shared by two of them, the diagonals by two
    /// or more), as Khronos' `BoxAnimated` draws its outer box (the cutter panicked on it,
    /// issue 48), with `extra` more awkward triangles from `seed`: duplicates, degenerate
    /// ones (two corners at one position, or all three on a line), T-junctions (a corner at
    /// the midpoint of another triangle's edge) and corners repeated under other indices (a
    /// flat-shaded export).
    fn awkward_box(seed: u64, extra: usize) -> TriangleMesh {
        let mut state = seed | 1;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut mesh = TriangleMesh::default();
        let corner = |k: u32| Vec3::new((k & 1) as f32, ((k >> 1) & 1) as f32, (k >> 2) as f32);
        mesh.positions.extend((0..8).map(corner));
        let faces = [
            [0, 1, 3, 2],
            [4, 6, 7, 5],
            [0, 4, 5, 1],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 5, 7, 3],
        ];
        for [a, b, c, d] in faces {
            mesh.triangles.extend([[a, b, c], [a, c, d], [a, b, d]]);
        }
        for _ in 0..extra {
            let t = mesh.triangles[next() as usize % mesh.triangles.len()];
            match next() % 4 {
                0 => mesh.triangles.push(t),
                1 => {
                    // Two corners at one position (another index), or three on a line.
                    let p = mesh.positions[t[0] as usize];
                    let q = mesh.positions[t[1] as usize];
                    mesh.positions.push(p);
                    mesh.positions.push((p + q) * 0.5);
                    let (same, middle) = (
                        mesh.positions.len() as u32 - 2,
                        mesh.positions.len() as u32 - 1,
                    );
                    mesh.triangles.push(if next() % 2 == 0 {
                        [t[0], t[1], same]
                    } else {
                        [t[0], middle, t[1]]
                    });
                }
                2 => {
                    // A T-junction: a triangle with a corner at the midpoint of t's first edge.
                    let [p, q, r] = t.map(|v| mesh.positions[v as usize]);
                    mesh.positions.push((p + q) * 0.5);
                    let m = mesh.positions.len() as u32 - 1;
                    let _ = r;
                    mesh.triangles.push([t[0], m, t[2]]);
                }
                _ => {
                    // t again on corners repeated under new indices.
                    let base = mesh.positions.len() as u32;
                    let copies = t.map(|v| mesh.positions[v as usize]);
                    mesh.positions.extend(copies);
                    mesh.triangles.push([base, base + 1, base + 2]);
                }
            }
        }
        mesh.faces = (0..mesh.triangles.len() as u32)
            .map(|t| super::Faces {
                front: t,
                back: None,
            })
            .collect();
        mesh
    }

    /// The leaves of root `root`'s cut tree.
    fn leaves(cutter: &MeshCutter, root: u32) -> Vec<u32> {
        let (mut out, mut stack) = (Vec::new(), vec![root]);
        while let Some(node) = stack.pop() {
            match cutter.nodes[node as usize] {
                Node::Leaf(leaf) => out.push(leaf),
                Node::Cut { children, .. } => stack.extend(children),
            }
        }
        out
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(256))]
        /// Any mesh a glTF file can hold is cut without a panic (edges shared by any number
        /// of triangles, overlapping, duplicated and degenerate triangles, T-junctions), and
        /// every triangle's pieces cover its area.
        #[test]
        fn awkward_meshes_are_cut_and_keep_their_area(
            seed in proptest::prelude::any::<u64>(),
            extra in 0usize..12,
            trees in proptest::collection::vec(0u32..(1 << 8), 1..40),
        ) {
            let mesh = awkward_box(seed, extra);
            let cuts: Vec<u32> = (0..mesh.triangles.len())
                .map(|t| trees[t % trees.len()] & !1)
                .collect();
            let cutter = MeshCutter::with_cuts(&mesh, &cuts);
            let corners = |t: &[u32; 3], positions: &[Vec3]| t.map(|v| positions[v as usize]);
            for (root, t) in mesh.triangles.iter().enumerate() {
                let whole = area(corners(t, &mesh.positions));
                let pieces: f64 = leaves(&cutter, root as u32)
                    .iter()
                    .map(|&l| area(corners(&cutter.triangles[l as usize], &cutter.positions)))
                    .sum();
                proptest::prop_assert!(
                    (pieces - whole).abs() <= 1e-6 * whole.max(1e-6),
                    "triangle {root}: pieces {pieces} of {whole}"
                );
            }
        }
    }
}
