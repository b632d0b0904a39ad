//! A 4-wide BVH for tracing bundles: the binary BVH collapsed so that a node holds the boxes of
//! up to four children side by side, tested against a bundle's lines four at a time. Half the
//! depth of the binary tree, and a node is two cache lines read together.

use obvhs::bvh2::Bvh2;

/// A node of the 4-wide BVH: its children's boxes by axis and child (`lo[axis][child]`), and
/// what each child is.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Node {
    /// Lower corners of the children's boxes.
    pub lo: [[f32; 4]; 3],
    /// Upper corners.
    pub hi: [[f32; 4]; 3],
    /// An inner child's node index, or a leaf's first triangle.
    pub child: [u32; 4],
    /// A leaf's triangle count; [`INNER`] for an inner child, 0 for an unused slot.
    pub count: [u16; 4],
    /// The slots in use, bit i for child i.
    pub used: u32,
}

/// [`Node::count`] of an inner child.
pub const INNER: u16 = u16::MAX;

impl Node {
    const UNUSED: Self = Self {
        lo: [[f32::INFINITY; 4]; 3],
        hi: [[f32::NEG_INFINITY; 4]; 3],
        child: [0; 4],
        count: [0; 4],
        used: 0,
    };
}

/// Collapses `bvh` into 4-wide nodes, root first, each node's subtrees after it in depth-first
/// order. Leaves keep the binary BVH's triangles (`first_index`, `prim_count`). Empty if the
/// BVH is.
#[must_use]
pub fn collapse(bvh: &Bvh2) -> Vec<Node> {
    let mut nodes = Vec::new();
    if !bvh.nodes.is_empty() {
        build(bvh, 0, &mut nodes);
    }
    nodes
}

/// Appends the 4-wide node standing for binary node `at` (and its subtrees); its index.
fn build(bvh: &Bvh2, at: usize, nodes: &mut Vec<Node>) -> u32 {
    let slot = nodes.len();
    nodes.push(Node::UNUSED);
    let binary = &bvh.nodes;
    // The children: start from `at` (or its two children), then open the largest inner one
    // until there are four.
    let mut kids = if binary[at].prim_count == 0 {
        let first = binary[at].first_index as usize;
        vec![first, first + 1]
    } else {
        vec![at]
    };
    while kids.len() < 4 {
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
    let mut node = Node::UNUSED;
    for (i, &k) in kids.iter().enumerate() {
        let aabb = &binary[k].aabb;
        for axis in 0..3 {
            node.lo[axis][i] = aabb.min[axis];
            node.hi[axis][i] = aabb.max[axis];
        }
        node.used |= 1 << i;
        if binary[k].prim_count == 0 {
            node.child[i] = build(bvh, k, nodes);
            node.count[i] = INNER;
        } else {
            node.child[i] = binary[k].first_index;
            // The builder makes leaves of at most `max_prims_per_leaf` (8) triangles.
            node.count[i] = u16::try_from(binary[k].prim_count).expect("small leaves");
        }
    }
    nodes[slot] = node;
    slot as u32
}
