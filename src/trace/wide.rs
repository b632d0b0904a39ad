//! A wide BVH for tracing bundles: the binary BVH collapsed so that a node holds the boxes of
//! up to eight children side by side, tested against a line all eight at once. A third of the
//! depth of the binary tree, and a node is four cache lines read together.

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
/// meets. (Every triangle has a slot of its own whatever the choice, so the triangles' tests
/// are the same in every choice and left out.) On the spheres of the benchmark: 39,000 nodes
/// with six children each, where opening the widest child first made 59,000 with four.
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
}

impl Plan {
    fn new(bvh: &Bvh2) -> Self {
        let mut split = vec![[0; WIDTH]; bvh.nodes.len()];
        // Children before their parents, a post-order walk from the root; the costs of the
        // subtrees walked whose parent is not yet, on a stack (as deep as the tree).
        let mut costs: Vec<[f32; WIDTH]> = Vec::new();
        let mut stack = vec![(0, false)];
        while let Some((i, opened)) = stack.pop() {
            let node = &bvh.nodes[i];
            if node.prim_count != 0 {
                // A triangle's slot: no node to test.
                costs.push([0.0; WIDTH]);
            } else if !opened {
                let first = node.first_index as usize;
                stack.extend([(i, true), (first, false), (first + 1, false)]);
            } else {
                // The first child was walked last.
                let (l, r) = (costs.pop(), costs.pop());
                let (l, r) = (l.expect("walked"), r.expect("walked"));
                let (cost, best) = spread(node.aabb.half_area(), &l, &r);
                costs.push(cost);
                split[i] = best;
            }
        }
        Self { split }
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
fn spread(area: f32, l: &[f32; WIDTH], r: &[f32; WIDTH]) -> ([f32; WIDTH], [u8; WIDTH]) {
    // Over `k` slots: the best division of them between the two children.
    let divide = |k: usize| {
        (1..k)
            .map(|a| (l[a - 1] + r[k - a - 1], a as u8))
            .min_by(|x, y| x.0.total_cmp(&y.0))
    };
    let (whole, _) = divide(WIDTH).expect("eight slots divide");
    let mut cost = [area + whole; WIDTH];
    let mut split = [0; WIDTH];
    for k in 2..=WIDTH {
        (cost[k - 1], split[k - 1]) = (cost[k - 2], split[k - 2]);
        if let Some((c, a)) = divide(k)
            && c < cost[k - 1]
        {
            (cost[k - 1], split[k - 1]) = (c, a);
        }
    }
    (cost, split)
}

/// Appends the wide node standing for inner binary node `at` (and its subtrees); its index.
fn build(bvh: &Bvh2, plan: &Plan, at: usize, nodes: &mut Vec<Node>) -> u32 {
    let slot = nodes.len();
    nodes.push(Node::UNUSED);
    let first = bvh.nodes[at].first_index as usize;
    let a = usize::from(plan.split[at][WIDTH - 1]).max(1);
    let mut kids = Vec::with_capacity(WIDTH);
    plan.slots(bvh, first, a, &mut kids);
    plan.slots(bvh, first + 1, WIDTH - a, &mut kids);
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
            node.count[i] = u16::try_from(binary[k].prim_count).expect("small leaves");
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
            let mut time = std::time::Duration::ZERO;
            let params = BvhBuildParams {
                max_prims_per_leaf: 1,
                ..BvhBuildParams::medium_build()
            };
            let bvh = build_bvh2(&boxes, params, &mut time);
            let nodes = collapse(&bvh);
            let mut seen = vec![0; n];
            check(&nodes, 0, None, &mut seen);
            assert!(seen.iter().all(|&s| s == 1), "{n} triangles");
            // The expected cost of a line (sum of the wide nodes' areas) is the least there
            // is: no more than that of opening the widest child first (the collapse before).
            let area = |at: u32| {
                let node = &nodes[at as usize];
                let mut whole = Aabb::empty();
                for i in 0..WIDTH {
                    if node.used >> i & 1 == 1 {
                        let (lo, hi) = (&node.lo, &node.hi);
                        whole.extend(Vec3A::new(lo[0][i], lo[1][i], lo[2][i]));
                        whole.extend(Vec3A::new(hi[0][i], hi[1][i], hi[2][i]));
                    }
                }
                whole.half_area()
            };
            let cost: f32 = (1..nodes.len() as u32).map(area).sum();
            let widest_first = widest_first_cost(&bvh, 0);
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

    /// The sum of the areas of the wide nodes below the root made by opening the widest inner
    /// child until there are eight.
    fn widest_first_cost(bvh: &Bvh2, at: usize) -> f32 {
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
        kids.iter()
            .filter(|&&k| binary[k].prim_count == 0)
            .map(|&k| binary[k].aabb.half_area() + widest_first_cost(bvh, k))
            .sum()
    }
}
