//! Which nodes of a binary tree become the nodes and leaves of an 8-wide one: the
//! SAH-optimal collapse of Ylitie, Karras and Laine ("Efficient Incoherent Ray Traversal
//! on GPUs Through Compressed Wide BVHs", HPG 2017), as obvhs' `bvh2_to_cwbvh` computes it
//! (with [`LeafCost::ONE_BY_ONE`], the same costs and tie-breaking, so the same trees), but
//! in parallel, without recursion deeper than a few levels, and without quantizing boxes
//! we do not use. A leaf's cost counts the groups of primitives its test takes
//! ([`LeafCost`]): triangles are tested four at a time, so their leaves grow larger.
//!
//! For each binary node `n` and each `i` in `0..7`, the dynamic programme finds the cheapest
//! way to represent `n`'s subtree as at most `i + 1` subtrees hanging from a wide node:
//! `i = 0` is one slot (a leaf of at most `max_leaf` primitives, or a wide node of its
//! own, whose eight slots are shared between the two children); `i > 0` shares `i + 1`
//! slots between the children or takes the answer for fewer slots.

use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};

use obvhs::bvh2::Bvh2;

/// Slots of a wide node.
const SLOTS: usize = 8;

/// What testing a leaf costs, per unit of its box's area, against 1 for testing a node's
/// children: `per_group` for each group of `group` primitives tested together.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LeafCost {
    /// Primitives tested together (1: one at a time).
    pub group: u32,
    /// The cost of testing one group.
    pub per_group: f32,
}

impl LeafCost {
    /// Primitives tested one at a time, at obvhs' cost (0.3 each): the spheres.
    pub const ONE_BY_ONE: LeafCost = LeafCost {
        group: 1,
        per_group: 0.3,
    };
    /// Triangles in blocks of four tested by one AVX2 sequence, at the cost obvhs gives a
    /// single primitive. A leaf's run of triangles may start anywhere in a block, so a run
    /// of `n` touches `1 + (n − 1) / 4` blocks on average. Counting blocks rather than
    /// triangles gives the 1M-triangle torus 31k nodes instead of 105k, and 4.6 triangles
    /// per leaf instead of 1.5 (Embree's builder: 52k nodes, 3.8 per leaf; DEVELOPERS.md,
    /// "Performance notes").
    pub const TRIANGLE_BLOCKS: LeafCost = LeafCost {
        group: 4,
        per_group: 0.3,
    };

    /// The cost of a leaf of `primitives` with box half-area `area`.
    fn of(self, primitives: u32, area: f32) -> f32 {
        let groups = 1.0 + primitives.saturating_sub(1) as f32 / self.group as f32;
        area * self.per_group * groups
    }
}

/// Levels of the binary tree below which subtrees are costed in parallel.
const PARALLEL_LEVELS: u32 = 10;
/// Levels costed by plain recursion; deeper subtrees (degenerate trees) use an explicit
/// stack.
const RECURSION_LEVELS: u32 = 64;

/// What a binary node does with `i + 1` available slots.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// Its whole subtree is one leaf.
    Leaf,
    /// It is a wide node of its own.
    Node,
    /// It hands its slots on to its two children (`left + 1` and `right + 1` each).
    Split,
}

/// One decision: the kind, and for `Node`/`Split` how many slots (minus one) each child
/// gets. Seven of them fit one `u64`, a byte each.
#[derive(Debug, Clone, Copy)]
struct Choice {
    kind: Kind,
    left: u8,
    right: u8,
}

impl Choice {
    fn pack(self) -> u8 {
        let kind = match self.kind {
            Kind::Leaf => 0,
            Kind::Node => 1,
            Kind::Split => 2,
        };
        kind << 6 | self.left << 3 | self.right
    }

    fn unpack(byte: u8) -> Choice {
        Choice {
            kind: match byte >> 6 {
                0 => Kind::Leaf,
                1 => Kind::Node,
                _ => Kind::Split,
            },
            left: byte >> 3 & 7,
            right: byte & 7,
        }
    }
}

/// The collapse of one binary tree: for each binary node, its seven choices.
pub struct Collapse<'a> {
    bvh2: &'a Bvh2,
    max_leaf: u32,
    leaf_cost: LeafCost,
    choices: Vec<AtomicU64>,
    /// Primitives under each binary node.
    primitives: Vec<AtomicU32>,
}

impl<'a> Collapse<'a> {
    /// Runs the dynamic programme over `bvh2` (its leaves may hold several primitives; a
    /// leaf is never split, and a subtree becomes a leaf only if it holds at most
    /// `max_leaf` primitives), leaves costing `leaf_cost`.
    pub fn new(bvh2: &'a Bvh2, max_leaf: u32, leaf_cost: LeafCost) -> Collapse<'a> {
        let choices = (0..bvh2.nodes.len()).map(|_| AtomicU64::new(0)).collect();
        let primitives = (0..bvh2.nodes.len()).map(|_| AtomicU32::new(0)).collect();
        let collapse = Collapse {
            bvh2,
            max_leaf,
            leaf_cost,
            choices,
            primitives,
        };
        if !bvh2.nodes.is_empty() {
            collapse.cost_parallel(0, 0);
        }
        collapse
    }

    /// The number of primitives under binary node `n`.
    pub fn primitives(&self, n: usize) -> u32 {
        self.primitives[n].load(Ordering::Relaxed)
    }

    /// Whether binary node `n`, given a slot of its own, is a leaf.
    pub fn is_leaf(&self, n: usize) -> bool {
        self.bvh2.nodes[n].is_leaf() || self.choice(n, 0).kind == Kind::Leaf
    }

    /// The binary nodes that fill the slots of the wide node made of binary node `n`, in
    /// order (at most eight). A leaf `n` fills one slot itself.
    pub fn children(&self, n: usize, out: &mut Vec<usize>) {
        out.clear();
        if self.bvh2.nodes[n].is_leaf() {
            out.push(n);
        } else {
            self.gather(n, 0, out);
        }
        debug_assert!(out.len() <= SLOTS);
    }

    fn gather(&self, n: usize, i: u8, out: &mut Vec<usize>) {
        let choice = self.choice(n, i);
        let first = self.bvh2.nodes[n].first_index as usize;
        for (child, slots) in [(first, choice.left), (first + 1, choice.right)] {
            if !self.bvh2.nodes[child].is_leaf() && self.choice(child, slots).kind == Kind::Split {
                self.gather(child, slots, out);
            } else {
                out.push(child);
            }
        }
    }

    fn choice(&self, n: usize, i: u8) -> Choice {
        let packed = self.choices[n].load(Ordering::Relaxed);
        Choice::unpack((packed >> (8 * i)) as u8)
    }

    fn store(&self, n: usize, choices: &[Choice; SLOTS - 1]) {
        let packed = (choices.iter().enumerate())
            .fold(0u64, |acc, (i, c)| acc | u64::from(c.pack()) << (8 * i));
        self.choices[n].store(packed, Ordering::Relaxed);
    }

    /// Costs of node `n`'s subtree, the top levels in parallel.
    fn cost_parallel(&self, n: usize, level: u32) -> Costs {
        let node = &self.bvh2.nodes[n];
        if node.is_leaf() {
            return self.leaf(n);
        }
        if level >= PARALLEL_LEVELS {
            return self.cost_recursive(n, level);
        }
        let first = node.first_index as usize;
        let (left, right) = rayon::join(
            || self.cost_parallel(first, level + 1),
            || self.cost_parallel(first + 1, level + 1),
        );
        self.combine(n, &left, &right)
    }

    /// Costs of node `n`'s subtree by recursion, down to [`RECURSION_LEVELS`].
    fn cost_recursive(&self, n: usize, level: u32) -> Costs {
        let node = &self.bvh2.nodes[n];
        if node.is_leaf() {
            return self.leaf(n);
        }
        if level >= RECURSION_LEVELS {
            return self.cost_subtree(n);
        }
        let first = node.first_index as usize;
        let left = self.cost_recursive(first, level + 1);
        let right = self.cost_recursive(first + 1, level + 1);
        self.combine(n, &left, &right)
    }

    /// Costs of node `n`'s subtree, in post-order with an explicit stack (a degenerate
    /// tree may be as deep as it has primitives).
    fn cost_subtree(&self, root: usize) -> Costs {
        let mut pending = vec![(root, false)];
        let mut done: Vec<Costs> = Vec::new();
        while let Some((n, children_done)) = pending.pop() {
            let node = &self.bvh2.nodes[n];
            if node.is_leaf() {
                done.push(self.leaf(n));
            } else if children_done {
                let right = done.pop().expect("right child costed");
                let left = done.pop().expect("left child costed");
                done.push(self.combine(n, &left, &right));
            } else {
                let first = node.first_index as usize;
                pending.extend([(n, true), (first + 1, false), (first, false)]);
            }
        }
        done.pop().expect("root costed")
    }

    fn leaf(&self, n: usize) -> Costs {
        let node = &self.bvh2.nodes[n];
        let cost = self.leaf_cost.of(node.prim_count, node.aabb().half_area());
        // Every choice is `Leaf` (all zero bits).
        self.choices[n].store(0, Ordering::Relaxed);
        self.primitives[n].store(node.prim_count, Ordering::Relaxed);
        Costs {
            cost: [cost; SLOTS - 1],
            primitives: node.prim_count,
        }
    }

    fn combine(&self, n: usize, left: &Costs, right: &Costs) -> Costs {
        let area = self.bvh2.nodes[n].aabb().half_area();
        let primitives = left.primitives + right.primitives;
        let mut cost = [0f32; SLOTS - 1];
        let mut choices = [Choice {
            kind: Kind::Leaf,
            left: 0,
            right: 0,
        }; SLOTS - 1];

        // One slot: a leaf, or a wide node sharing its eight slots between the children.
        let as_leaf = if primitives <= self.max_leaf {
            self.leaf_cost.of(primitives, area)
        } else {
            f32::INFINITY
        };
        let mut shared = f32::INFINITY;
        let (mut l, mut r) = (u8::MAX, u8::MAX);
        for k in 0..SLOTS - 1 {
            let c = left.cost[k] + right.cost[SLOTS - 2 - k];
            if c < shared {
                shared = c;
                (l, r) = (k as u8, (SLOTS - 2 - k) as u8);
            }
        }
        let as_node = shared + area;
        (cost[0], choices[0]) = if as_leaf < as_node {
            (
                as_leaf,
                Choice {
                    kind: Kind::Leaf,
                    left: l,
                    right: r,
                },
            )
        } else {
            (
                as_node,
                Choice {
                    kind: Kind::Node,
                    left: l,
                    right: r,
                },
            )
        };

        // More slots: share them between the children, or do as with one fewer.
        for i in 1..SLOTS - 1 {
            cost[i] = cost[i - 1];
            choices[i] = choices[i - 1];
            for k in 0..i {
                let c = left.cost[k] + right.cost[i - k - 1];
                if c < cost[i] {
                    cost[i] = c;
                    choices[i] = Choice {
                        kind: Kind::Split,
                        left: k as u8,
                        right: (i - k - 1) as u8,
                    };
                }
            }
        }
        self.store(n, &choices);
        self.primitives[n].store(primitives, Ordering::Relaxed);
        Costs { cost, primitives }
    }
}

/// A subtree's cost for each number of slots, and its primitive count.
struct Costs {
    cost: [f32; SLOTS - 1],
    primitives: u32,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::{BuildPreset, Bvh};
    use obvhs::aabb::Aabb;

    #[test]
    fn a_leaf_costs_the_blocks_its_run_touches_on_average() {
        for n in 1..=16u32 {
            // A run of `n` primitives starting at each offset within a block of four.
            let touched: u32 = (0..4).map(|start| (start + n - 1) / 4 + 1).sum();
            let expected = 0.3 * touched as f32 / 4.0;
            let cost = LeafCost::TRIANGLE_BLOCKS.of(n, 1.0);
            assert!(
                (cost - expected).abs() < 1e-6,
                "{n}: {cost} against {expected}"
            );
            let one_by_one = LeafCost::ONE_BY_ONE.of(n, 2.0);
            assert!(
                (one_by_one - 0.6 * n as f32).abs() < 1e-5,
                "{n}: {one_by_one}"
            );
        }
    }

    #[test]
    fn counting_blocks_gives_fewer_larger_leaves() {
        let mesh = crate::procedural::icosphere(5);
        let boxes: Vec<Aabb> = (mesh.triangles.iter())
            .map(|t| {
                let [a, b, c] = t.map(|i| glam::Vec3A::from(mesh.positions[i as usize]));
                Aabb::new(a.min(b).min(c), a.max(b).max(c))
            })
            .collect();
        // Triangles per leaf, and nodes.
        let shape = |cost| {
            let leaves = std::sync::atomic::AtomicUsize::new(0);
            let params = BuildPreset::default().params(16);
            let (bvh, _): (Bvh<f32>, _) = Bvh::build(&boxes, params, cost, |first, count| {
                leaves.fetch_add(1, Ordering::Relaxed);
                (first, count)
            });
            let per_leaf = boxes.len() as f64 / leaves.into_inner() as f64;
            (per_leaf, bvh.nodes().len())
        };
        let (one_by_one, nodes_one_by_one) = shape(LeafCost::ONE_BY_ONE);
        let (blocks, nodes_blocks) = shape(LeafCost::TRIANGLE_BLOCKS);
        assert!(one_by_one < 2.0, "{one_by_one}");
        assert!((3.0..8.0).contains(&blocks), "{blocks}");
        assert!(
            2 * nodes_blocks < nodes_one_by_one,
            "{nodes_blocks} {nodes_one_by_one}"
        );
    }
}
