//! A wide BVH for tracing bundles: the binary BVH collapsed so that a node holds the boxes of
//! up to eight children side by side, tested against a bundle's lines four at a time. A third
//! of the depth of the binary tree, and a node is four cache lines read together.

use obvhs::bvh2::Bvh2;

/// Children per node.
pub const WIDTH: usize = 8;

/// Four children's boxes by axis and child (`lo[axis][child]`), side by side for SIMD.
#[derive(Clone, Copy, Debug)]
pub struct Boxes {
    /// Lower corners.
    pub lo: [[f32; 4]; 3],
    /// Upper corners.
    pub hi: [[f32; 4]; 3],
}

/// A node of the wide BVH: its children's boxes, four at a time, and what each child is.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Node {
    /// Children 0–3, 4–7.
    pub boxes: [Boxes; WIDTH / 4],
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
    const UNUSED: Self = Self {
        boxes: [Boxes {
            lo: [[f32::INFINITY; 4]; 3],
            hi: [[f32::NEG_INFINITY; 4]; 3],
        }; WIDTH / 4],
        child: [0; WIDTH],
        count: [0; WIDTH],
        used: 0,
    };
}

/// Collapses `bvh` into wide nodes, root first, each node's subtrees after it in depth-first
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

/// Appends the wide node standing for binary node `at` (and its subtrees); its index.
fn build(bvh: &Bvh2, at: usize, nodes: &mut Vec<Node>) -> u32 {
    let slot = nodes.len();
    nodes.push(Node::UNUSED);
    let binary = &bvh.nodes;
    // The children: start from `at` (or its two children), then open the largest inner one
    // until there are eight.
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
    let mut node = Node::UNUSED;
    for (i, &k) in kids.iter().enumerate() {
        let aabb = &binary[k].aabb;
        let boxes = &mut node.boxes[i / 4];
        for axis in 0..3 {
            boxes.lo[axis][i % 4] = aabb.min[axis];
            boxes.hi[axis][i % 4] = aabb.max[axis];
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
