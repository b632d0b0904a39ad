//! A wide BVH for tracing bundles: the binary BVH collapsed so that a node holds the boxes of
//! up to eight children side by side, tested against a line all eight at once. A third of the
//! depth of the binary tree, and a node is four cache lines read together. Where a node's
//! children would all be single triangles, a [`Block`] holds the triangles themselves side by
//! side instead (five cache lines), tested against a line eight at once with no boxes.

use obvhs::bvh2::Bvh2;

/// Children per node.
pub const WIDTH: usize = 8;

/// A node of the wide BVH: its children's boxes side by side, by axis and child
/// (`lo[axis][child]`), as eight lanes a processor with AVX2 tests at once; and what each
/// child is.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Node {
    /// Lower corners.
    pub lo: [[f32; WIDTH]; 3],
    /// Upper corners.
    pub hi: [[f32; WIDTH]; 3],
    /// An inner child's node index, or a leaf's first triangle.
    pub child: [u32; WIDTH],
    /// A leaf's triangle count; [`INNER`] for an inner child, 0 for an unused slot.
    pub count: [u16; WIDTH],
    /// The slots in use, bit i for child i.
    pub used: u32,
}

/// [`Node::count`] of an inner child.
pub const INNER: u16 = u16::MAX;

/// [`Node::count`] of a child that is a [`Block`], with the block's triangle count in the low
/// bits: `BLOCK | lanes`; its [`Node::child`] is the block's index.
pub const BLOCK: u16 = 0x8000;

/// The triangles of a wide node whose children are all single triangles, side by side as
/// eight lanes (`corner[c][axis][lane]`), tested against a line all at once in place of the
/// node's boxes; and their global indices.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Block {
    /// The corners' coordinates.
    pub corner: [[[f32; WIDTH]; 3]; 3],
    /// Each lane's triangle, its global index.
    pub id: [u32; WIDTH],
}

impl Block {
    /// The corners of the triangle in `lane`.
    #[must_use]
    #[inline(always)]
    pub fn corners(&self, lane: usize) -> [glam::Vec3; 3] {
        // Indexed in place: `map` would copy all eight lanes' corners first.
        std::array::from_fn(|k| {
            let c = &self.corner[k];
            glam::Vec3::new(c[0][lane], c[1][lane], c[2][lane])
        })
    }
}

/// Replaces every wide node below the root whose children are all single triangles by a
/// [`Block`] of them (`triangle(k)` gives leaf triangle `k`'s corners and global index): the
/// nodes left, in the same order; the blocks; and the leaf triangles left in slots of their
/// own, whose slots now count from the start of that list.
#[must_use]
pub fn into_blocks(
    nodes: &[Node],
    triangle: impl Fn(u32) -> ([glam::Vec3; 3], u32),
) -> (Vec<Node>, Vec<Block>, Vec<u32>) {
    let all_leaves = single_triangles;
    let mut singles = Vec::new();
    let mut index = vec![u32::MAX; nodes.len()];
    let (mut kept, mut blocks) = (0u32, Vec::new());
    for (n, node) in nodes.iter().enumerate() {
        if n > 0 && all_leaves(node) {
            index[n] = blocks.len() as u32;
            let mut block = Block {
                corner: [[[0.0; WIDTH]; 3]; 3],
                id: [0; WIDTH],
            };
            for lane in 0..node.used.count_ones() as usize {
                let (corners, id) = triangle(node.child[lane]);
                for (c, corner) in corners.iter().enumerate() {
                    for axis in 0..3 {
                        block.corner[c][axis][lane] = corner[axis];
                    }
                }
                block.id[lane] = id;
            }
            blocks.push(block);
        } else {
            index[n] = kept;
            kept += 1;
        }
    }
    let mut out = Vec::with_capacity(kept as usize);
    for (n, node) in nodes.iter().enumerate() {
        if n > 0 && all_leaves(node) {
            continue;
        }
        let mut node = *node;
        for i in (0..WIDTH).filter(|&i| node.used >> i & 1 == 1) {
            let first = node.child[i];
            if node.count[i] == INNER {
                let child = &nodes[first as usize];
                if all_leaves(child) {
                    node.count[i] = BLOCK | child.used.count_ones() as u16;
                }
                node.child[i] = index[first as usize];
            } else {
                node.child[i] = singles.len() as u32;
                singles.extend(first..first + u32::from(node.count[i]));
            }
        }
        out.push(node);
    }
    (out, blocks, singles)
}

/// Whether every child of `node` is a single triangle (a [`Block`] of them can stand for it).
fn single_triangles(node: &Node) -> bool {
    (0..WIDTH).all(|i| node.used >> i & 1 == 0 || node.count[i] == 1)
}

impl Node {
    pub(super) const UNUSED: Self = Self {
        lo: [[f32::INFINITY; WIDTH]; 3],
        hi: [[f32::NEG_INFINITY; WIDTH]; 3],
        child: [0; WIDTH],
        count: [0; WIDTH],
        used: 0,
    };
}

/// Collapses `bvh` into wide nodes, root first, each node's subtrees after it in depth-first
/// order. Leaves keep the binary BVH's triangles (`first_index`, `prim_count`). Empty if the
/// BVH is.
///
/// Which binary nodes become wide nodes and which are opened into their parent's slots is
/// chosen to make a line's expected cost least (Ylitie, Karras and Laine, "Efficient
/// incoherent ray traversal on GPUs through compressed wide BVHs", 2017): a line meets a box
/// with a probability proportional to its surface area and pays one test per wide node it
/// meets, per triangle whose own box it meets, and one per block of up to eight triangles
/// whose box it meets (a subtree of so few triangles kept whole may be all of them in one
/// node's slots, which [`into_blocks`] makes a block). On the spheres of the benchmark, 99% of
/// the static triangles end in 36,700 blocks, under 7,200 nodes.
#[must_use]
pub fn collapse(bvh: &Bvh2) -> Vec<Node> {
    let mut nodes = Vec::new();
    if bvh.nodes.is_empty() {
        return nodes;
    }
    let plan = Plan::new(bvh);
    if bvh.nodes[0].prim_count == 0 {
        build(bvh, &plan, 0, &mut nodes);
    } else {
        // A single leaf: a root holding it alone.
        nodes.push(Node::UNUSED);
        fill(bvh, &plan, &mut nodes, 0, &[0]);
    }
    nodes
}

/// How many levels of nodes the wide BVH `nodes` (from [`collapse`]) has.
#[must_use]
pub fn depth(nodes: &[Node]) -> usize {
    let mut deepest = 0;
    let mut stack = Vec::new();
    if !nodes.is_empty() {
        stack.push((0, 1));
    }
    while let Some((at, level)) = stack.pop() {
        deepest = deepest.max(level);
        let node: &Node = &nodes[at as usize];
        for i in 0..WIDTH {
            if node.used >> i & 1 == 1 && node.count[i] == INNER {
                stack.push((node.child[i], level + 1));
            }
        }
    }
    deepest
}

/// How each binary subtree is best spread over at most `k` slots of a wide node (`k` =
/// 1..=8), for the least expected cost: for an inner node, the slots given to its first child
/// (the rest to the second), or 0 for the subtree kept whole as one slot (a wide node of its
/// own). One byte per node and slot count; the costs are kept only while the walk needs them.
struct Plan {
    split: Vec<[u8; WIDTH]>,
    /// Whether a subtree kept whole becomes a block of its triangles (all of them in one wide
    /// node's slots, which [`into_blocks`] turns into a [`Block`]).
    block: Vec<bool>,
}

/// The cost of testing a line against a wide node's boxes, a block's triangles, or one
/// triangle reached through its own box, relative to each other. A triangle alone costs about
/// half a node (its test, timed), but counting it as a whole one put 99% of the spheres'
/// triangles in blocks instead of 90%, and the walk was 3% faster; 1.5, or blocks at 0.7 or
/// 0.8, were within 1% of that.
const NODE_COST: f32 = 1.0;
const BLOCK_COST: f32 = 1.0;
const TRIANGLE_COST: f32 = 1.0;

impl Plan {
    fn new(bvh: &Bvh2) -> Self {
        let mut split = vec![[0; WIDTH]; bvh.nodes.len()];
        let mut block = vec![false; bvh.nodes.len()];
        // Children before their parents, a post-order walk from the root; the costs of the
        // subtrees walked whose parent is not yet, on a stack (as deep as the tree).
        let mut costs: Vec<([f32; WIDTH], usize)> = Vec::new();
        let mut stack = vec![(0, false)];
        while let Some((i, opened)) = stack.pop() {
            let node = &bvh.nodes[i];
            if node.prim_count != 0 {
                // A triangle's slot: its own test.
                costs.push((
                    [TRIANGLE_COST * node.aabb.half_area(); WIDTH],
                    node.prim_count as usize,
                ));
            } else if !opened {
                let first = node.first_index as usize;
                stack.extend([(i, true), (first, false), (first + 1, false)]);
            } else {
                // The first child was walked last.
                let (l, r) = (costs.pop(), costs.pop());
                let (l, r) = (l.expect("walked"), r.expect("walked"));
                let leaves = l.1 + r.1;
                let (cost, best, as_block) =
                    spread(node.aabb.half_area(), leaves <= WIDTH, &l.0, &r.0);
                costs.push((cost, leaves));
                split[i] = best;
                block[i] = as_block;
            }
        }
        Self { split, block }
    }

    /// Appends the binary nodes that fill the (at most `k`) slots standing for subtree `i`.
    fn slots(&self, bvh: &Bvh2, i: usize, k: usize, out: &mut Vec<usize>) {
        let node = &bvh.nodes[i];
        let a = usize::from(self.split[i][k - 1]);
        if node.prim_count != 0 || a == 0 {
            out.push(i);
            return;
        }
        let l = node.first_index as usize;
        self.slots(bvh, l, a, out);
        self.slots(bvh, l + 1, k - a, out);
    }
}

/// The least expected cost of an inner node of box area `area` whose children cost `l` and
/// `r` (by slot count) spread over 1..=8 slots, and the slots its first child gets for each
/// (0: kept whole).
fn spread(
    area: f32,
    fits: bool,
    l: &[f32; WIDTH],
    r: &[f32; WIDTH],
) -> ([f32; WIDTH], [u8; WIDTH], bool) {
    // Over `k` slots: the best division of them between the two children.
    let divide = |k: usize| {
        (1..k)
            .map(|a| (l[a - 1] + r[k - a - 1], a as u8))
            .min_by(|x, y| x.0.total_cmp(&y.0))
    };
    let (whole, _) = divide(WIDTH).expect("eight slots divide");
    let node = NODE_COST * area + whole;
    let block = BLOCK_COST * area;
    let as_block = fits && block < node;
    let mut cost = [if as_block { block } else { node }; WIDTH];
    let mut split = [0; WIDTH];
    for k in 2..=WIDTH {
        (cost[k - 1], split[k - 1]) = (cost[k - 2], split[k - 2]);
        if let Some((c, a)) = divide(k)
            && c < cost[k - 1]
        {
            (cost[k - 1], split[k - 1]) = (c, a);
        }
    }
    (cost, split, as_block)
}

/// Appends the wide node standing for inner binary node `at` (and its subtrees); its index.
fn build(bvh: &Bvh2, plan: &Plan, at: usize, nodes: &mut Vec<Node>) -> u32 {
    let slot = nodes.len();
    nodes.push(Node::UNUSED);
    let first = bvh.nodes[at].first_index as usize;
    let mut kids = Vec::with_capacity(WIDTH);
    if plan.block[at] {
        // Every triangle of the subtree in a slot.
        let mut stack = vec![first + 1, first];
        while let Some(k) = stack.pop() {
            let node = &bvh.nodes[k];
            if node.prim_count != 0 {
                kids.push(k);
            } else {
                let f = node.first_index as usize;
                stack.extend([f + 1, f]);
            }
        }
    } else {
        let a = usize::from(plan.split[at][WIDTH - 1]).max(1);
        plan.slots(bvh, first, a, &mut kids);
        plan.slots(bvh, first + 1, WIDTH - a, &mut kids);
    }
    fill(bvh, plan, nodes, slot, &kids);
    slot as u32
}

/// Writes the wide node at `slot` with the binary nodes `kids` as its children, building the
/// wide nodes of the inner ones.
fn fill(bvh: &Bvh2, plan: &Plan, nodes: &mut Vec<Node>, slot: usize, kids: &[usize]) {
    let binary = &bvh.nodes;
    let mut node = Node::UNUSED;
    for (i, &k) in kids.iter().enumerate() {
        let aabb = &binary[k].aabb;
        for axis in 0..3 {
            node.lo[axis][i] = aabb.min[axis];
            node.hi[axis][i] = aabb.max[axis];
        }
        node.used |= 1 << i;
        if binary[k].prim_count == 0 {
            node.child[i] = build(bvh, plan, k, nodes);
            node.count[i] = INNER;
        } else {
            node.child[i] = binary[k].first_index;
            // The builder makes leaves of `max_prims_per_leaf` triangles (one).
            let count = u16::try_from(binary[k].prim_count).ok();
            node.count[i] = count.filter(|&c| c < BLOCK).expect("small leaves");
        }
    }
    nodes[slot] = node;
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3A;
    use obvhs::BvhBuildParams;
    use obvhs::aabb::Aabb;
    use obvhs::bvh2::builder::build_bvh2;
    use rand::rngs::Xoshiro256PlusPlus;
    use rand::{RngExt, SeedableRng};

    /// Every triangle reached once, through boxes that hold the boxes below them.
    fn check(nodes: &[Node], at: u32, outer: Option<Aabb>, seen: &mut [u32]) {
        let node = &nodes[at as usize];
        assert_ne!(node.used, 0);
        for i in 0..WIDTH {
            if node.used >> i & 1 == 0 {
                assert_eq!(node.count[i], 0);
                continue;
            }
            let (lo, hi) = (
                Vec3A::new(node.lo[0][i], node.lo[1][i], node.lo[2][i]),
                Vec3A::new(node.hi[0][i], node.hi[1][i], node.hi[2][i]),
            );
            if let Some(outer) = outer {
                assert!(lo.cmpge(outer.min).all() && hi.cmple(outer.max).all());
            }
            if node.count[i] == INNER {
                check(nodes, node.child[i], Some(Aabb::new(lo, hi)), seen);
            } else {
                for k in node.child[i]..node.child[i] + u32::from(node.count[i]) {
                    seen[k as usize] += 1;
                }
            }
        }
    }

    /// A binary BVH over `boxes`, built as [`super::super::TraceMesh`] builds its own.
    fn binary(boxes: &[Aabb]) -> Bvh2 {
        let mut time = std::time::Duration::ZERO;
        let params = BvhBuildParams {
            max_prims_per_leaf: 1,
            ..BvhBuildParams::medium_build()
        };
        build_bvh2(boxes, params, &mut time)
    }

    #[test]
    fn the_collapse_keeps_every_triangle_once_and_costs_least() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(8);
        for n in [1, 2, 7, 9, 100, 20_000] {
            let boxes: Vec<Aabb> = (0..n)
                .map(|_| {
                    let c = Vec3A::new(rng.random(), rng.random(), rng.random());
                    Aabb::new(c, c + rng.random_range(0.001..0.02))
                })
                .collect();
            let bvh = binary(&boxes);
            let nodes = collapse(&bvh);
            let mut seen = vec![0; n];
            check(&nodes, 0, None, &mut seen);
            assert!(seen.iter().all(|&s| s == 1), "{n} triangles");
            // The expected cost of a line (a test of a wide node, of a block or of a triangle
            // for each box it meets, as likely as the box's area) is the least there is: no
            // more than that of opening the widest child first (the collapse before), its
            // nodes of single triangles made blocks too.
            let slot_area = |node: &Node, i: usize| {
                let (lo, hi) = (&node.lo, &node.hi);
                Aabb::new(
                    Vec3A::new(lo[0][i], lo[1][i], lo[2][i]),
                    Vec3A::new(hi[0][i], hi[1][i], hi[2][i]),
                )
                .half_area()
            };
            let cost: f32 = (nodes.iter().enumerate())
                .map(|(at, node)| {
                    let slots = (0..WIDTH).filter(|&i| node.used >> i & 1 == 1);
                    let mut whole = Aabb::empty();
                    for i in slots.clone() {
                        let (lo, hi) = (&node.lo, &node.hi);
                        whole.extend(Vec3A::new(lo[0][i], lo[1][i], lo[2][i]));
                        whole.extend(Vec3A::new(hi[0][i], hi[1][i], hi[2][i]));
                    }
                    let block = at > 0 && single_triangles(node);
                    let own = match (at, block) {
                        (0, _) => 0.0,
                        (_, true) => BLOCK_COST,
                        _ => NODE_COST,
                    } * whole.half_area();
                    let triangles: f32 = (slots.filter(|&i| !block && node.count[i] != INNER))
                        .map(|i| TRIANGLE_COST * slot_area(node, i))
                        .sum();
                    own + triangles
                })
                .sum();
            let widest_first = widest_first_cost(&bvh, 0, true);
            assert!(
                cost <= widest_first * 1.0001,
                "{n}: {cost} > {widest_first}"
            );
            if n >= 10_000 {
                assert!(
                    cost < widest_first * 0.98,
                    "{n}: {cost} against {widest_first}"
                );
            }
        }
    }

    #[test]
    fn blocks_hold_every_triangle_once_with_its_corners() {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(12);
        for n in [1, 5, 9, 100, 5_000] {
            let triangles: Vec<[glam::Vec3; 3]> = (0..n)
                .map(|_| {
                    let c = glam::Vec3::new(rng.random(), rng.random(), rng.random());
                    let mut near = || c + rng.random_range(0.001..0.02) * glam::Vec3::ONE;
                    [c, near(), near()]
                })
                .collect();
            let boxes: Vec<Aabb> = (triangles.iter())
                .map(|t| {
                    Aabb::new(
                        t[0].min(t[1]).min(t[2]).into(),
                        t[0].max(t[1]).max(t[2]).into(),
                    )
                })
                .collect();
            let bvh = binary(&boxes);
            let order = &bvh.primitive_indices;
            let wide = collapse(&bvh);
            // Global index: 1000 past the triangle's.
            let (nodes, blocks, singles) = into_blocks(&wide, |k| {
                let i = order[k as usize];
                (triangles[i as usize], 1_000 + i)
            });
            let mut seen = vec![0; n];
            let mut stack = vec![0];
            while let Some(at) = stack.pop() {
                let node: &Node = &nodes[at];
                for i in (0..WIDTH).filter(|&i| node.used >> i & 1 == 1) {
                    match node.count[i] {
                        INNER => stack.push(node.child[i] as usize),
                        count if count & BLOCK != 0 => {
                            let block = &blocks[node.child[i] as usize];
                            let lanes = usize::from(count & !BLOCK);
                            assert!((2..=WIDTH).contains(&lanes) || n == 1, "{lanes}");
                            for lane in 0..lanes {
                                let t = (block.id[lane] - 1_000) as usize;
                                seen[t] += 1;
                                for (c, corner) in triangles[t].iter().enumerate() {
                                    for axis in 0..3 {
                                        assert_eq!(block.corner[c][axis][lane], corner[axis]);
                                    }
                                }
                            }
                        }
                        count => {
                            assert_eq!(count, 1);
                            let k = singles[node.child[i] as usize];
                            seen[order[k as usize] as usize] += 1;
                        }
                    }
                }
            }
            assert!(seen.iter().all(|&s| s == 1), "{n} triangles");
            if n >= 100 {
                // Most triangles end in blocks.
                let in_blocks = nodes
                    .iter()
                    .flat_map(|node| node.count)
                    .filter(|&c| c != INNER && c & BLOCK != 0);
                let in_blocks: usize = in_blocks.map(|c| usize::from(c & !BLOCK)).sum();
                assert!(in_blocks * 10 > n * 7, "{in_blocks} of {n}");
            }
        }
    }

    /// The expected cost of the wide nodes made by opening the widest inner child until there
    /// are eight, from the wide node standing for binary node `at` down (its own test left out
    /// at the `root`): a node of single triangles a block, other triangles tested alone.
    fn widest_first_cost(bvh: &Bvh2, at: usize, root: bool) -> f32 {
        let binary = &bvh.nodes;
        let mut kids = if binary[at].prim_count == 0 {
            let first = binary[at].first_index as usize;
            vec![first, first + 1]
        } else {
            vec![at]
        };
        while kids.len() < WIDTH {
            let widest = kids
                .iter()
                .enumerate()
                .filter(|&(_, &k)| binary[k].prim_count == 0)
                .max_by(|a, b| {
                    let area = |k: usize| binary[k].aabb.half_area();
                    area(*a.1).total_cmp(&area(*b.1))
                })
                .map(|(i, _)| i);
            let Some(i) = widest else { break };
            let first = binary[kids[i]].first_index as usize;
            kids[i] = first;
            kids.push(first + 1);
        }
        let block = !root && kids.iter().all(|&k| binary[k].prim_count == 1);
        let own = match (root, block) {
            (true, _) => 0.0,
            (_, true) => BLOCK_COST,
            _ => NODE_COST,
        } * binary[at].aabb.half_area();
        let below: f32 = (kids.iter())
            .map(|&k| match binary[k].prim_count {
                0 => widest_first_cost(bvh, k, false),
                _ if block => 0.0,
                _ => TRIANGLE_COST * binary[k].aabb.half_area(),
            })
            .sum();
        own + below
    }
}
