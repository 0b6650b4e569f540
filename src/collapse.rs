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

use std::sync::atomic::{AtomicU32, Ordering};

use obvhs::bvh2::Bvh2;
use rayon::prelude::*;

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
    /// single primitive. Each leaf has blocks of its own, so a leaf of `n` takes `⌈n / 4⌉`
    /// block tests. Counting blocks rather than triangles gives the 1M-triangle torus
    /// about a third of the nodes, and three times the triangles per leaf (Embree's
    /// builder: 3.8 per leaf; DEVELOPERS.md, "A triangle leaf costs the blocks its test
    /// takes").
    pub const TRIANGLE_BLOCKS: LeafCost = LeafCost {
        group: 4,
        per_group: 0.3,
    };

    /// The cost of a leaf of `primitives` with box half-area `area`.
    fn of(self, primitives: u32, area: f32) -> f32 {
        area * self.per_group * primitives.div_ceil(self.group) as f32
    }
}

/// Entries of the choice arrays one task fills at least.
const PARALLEL_FILL: usize = 1 << 14;

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
    /// The choice in `byte`: its kind in the top two bits (`KIND_…`), then three bits for
    /// each child's slots (see [`split_slots`]).
    fn unpack(byte: u8) -> Choice {
        Choice {
            kind: match byte & 0xc0 {
                KIND_LEAF => Kind::Leaf,
                KIND_NODE => Kind::Node,
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
    /// Each binary node's decisions, at its index.
    entries: Vec<Entry>,
}

/// What the collapse keeps of a binary node: its seven choices (packed, the low and high
/// halves), and the primitives under it. Kept together, so that writing a node's touches
/// one line, often shared with its sibling's.
struct Entry {
    choices: [AtomicU32; 2],
    primitives: AtomicU32,
}

impl<'a> Collapse<'a> {
    /// Runs the dynamic programme over `bvh2` (its leaves may hold several primitives; a
    /// leaf is never split, and a subtree becomes a leaf only if it holds at most
    /// `max_leaf` primitives), leaves costing `leaf_cost`.
    pub fn new(bvh2: &'a Bvh2, max_leaf: u32, leaf_cost: LeafCost) -> Collapse<'a> {
        // Filled in parallel: first touching their pages is most of the cost.
        let len = bvh2.nodes.len();
        let entries = (0..len)
            .into_par_iter()
            .with_min_len(PARALLEL_FILL)
            .map(|_| Entry {
                choices: [AtomicU32::new(0), AtomicU32::new(0)],
                primitives: AtomicU32::new(0),
            })
            .collect();
        let collapse = Collapse {
            bvh2,
            max_leaf,
            leaf_cost,
            entries,
        };
        if !bvh2.nodes.is_empty() {
            collapse.cost_parallel(0, 0);
        }
        collapse
    }

    /// The number of primitives under binary node `n`.
    pub fn primitives(&self, n: usize) -> u32 {
        let node = &self.bvh2.nodes[n];
        if node.is_leaf() {
            node.prim_count
        } else {
            self.entries[n].primitives.load(Ordering::Relaxed)
        }
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
        let [low, high] = &self.entries[n].choices;
        let packed =
            u64::from(low.load(Ordering::Relaxed)) | u64::from(high.load(Ordering::Relaxed)) << 32;
        Choice::unpack((packed >> (8 * i)) as u8)
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
        self.prefetch_children(first + 1);
        let left = self.cost_recursive(first, level + 1);
        let right = self.cost_recursive(first + 1, level + 1);
        self.combine(n, &left, &right)
    }

    /// Asks the cache for the children of binary node `n` ahead of their use. The costing
    /// walks the tree depth first, waiting on each node it reads; asked for as the left
    /// subtree is entered, a right subtree's children arrive meanwhile. A pair of 32-byte
    /// nodes starts at an odd index in obvhs' layout, so it may span two lines. (Asking for the
    /// left subtree's children as well, or for a wide node's children before laying them
    /// out, gained nothing.)
    #[inline(always)]
    fn prefetch_children(&self, n: usize) {
        #[cfg(target_arch = "x86_64")]
        {
            let node = &self.bvh2.nodes[n];
            if !node.is_leaf() {
                let nodes = self.bvh2.nodes.as_ptr();
                let pair = nodes.wrapping_add(node.first_index as usize);
                crate::simd::prefetch(pair as usize, pair.wrapping_add(2) as usize);
            }
        }
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

    /// A binary leaf's costs. Nothing is stored for it: readers ask the binary tree first
    /// whether a node is a leaf, and take a leaf's primitive count from there.
    fn leaf(&self, n: usize) -> Costs {
        let node = &self.bvh2.nodes[n];
        let cost = self.leaf_cost.of(node.prim_count, node.aabb().half_area());
        Costs {
            cost: [cost; SLOTS - 1],
            primitives: node.prim_count,
        }
    }

    fn combine(&self, n: usize, left: &Costs, right: &Costs) -> Costs {
        let area = self.bvh2.nodes[n].aabb().half_area();
        let primitives = left.primitives + right.primitives;
        let shares = share(&left.cost, &right.cost);
        let mut cost = [0f32; SLOTS - 1];
        // Each choice packed as `Choice::unpack` reads it. Candidates are compared with `<`
        // in a fixed order, so a tie keeps the one held: a wide node over a leaf, fewer
        // slots over more, an earlier split over a later one ([`share`]).
        let mut choices = [0u8; SLOTS - 1];

        // One slot: a leaf, or a wide node sharing its eight slots between the children.
        let as_leaf = if primitives <= self.max_leaf {
            self.leaf_cost.of(primitives, area)
        } else {
            f32::INFINITY
        };
        let (shared, slots) = shares[SLOTS - 1];
        let as_node = shared + area;
        (cost[0], choices[0]) = if as_leaf < as_node {
            (as_leaf, KIND_LEAF | slots)
        } else {
            (as_node, KIND_NODE | slots)
        };

        // More slots: share them between the children, or do as with one fewer.
        for i in 1..SLOTS - 1 {
            let (split, slots) = shares[i];
            (cost[i], choices[i]) = if split < cost[i - 1] {
                (split, KIND_SPLIT | slots)
            } else {
                (cost[i - 1], choices[i - 1])
            };
        }
        let entry = &self.entries[n];
        let packed = u64::from_le_bytes(pad(choices));
        entry.choices[0].store(packed as u32, Ordering::Relaxed);
        entry.choices[1].store((packed >> 32) as u32, Ordering::Relaxed);
        entry.primitives.store(primitives, Ordering::Relaxed);
        Costs { cost, primitives }
    }
}

/// For each `i` in `1..8`, the cheapest way to share `i + 1` slots between two children,
/// `k + 1` to the left and the rest to the right: the least `left[k] + right[i − 1 − k]`
/// below infinity, the first `k` on ties, and the slots packed as a choice's
/// (`split_slots(u8::MAX, u8::MAX)` and infinity if none). Entry 0 is unused.
///
/// (Skipping most candidates where a child is a binary leaf, whose costs are all the same,
/// was slower: which nodes have a leaf child is unpredictable.)
#[inline(always)]
fn share(left: &[f32; SLOTS - 1], right: &[f32; SLOTS - 1]) -> [(f32, u8); SLOTS] {
    let none = (f32::INFINITY, split_slots(u8::MAX, u8::MAX));
    let mut shares = [none; SLOTS];
    for (i, share) in shares.iter_mut().enumerate().skip(1) {
        // Compared in a fixed order and selected without branches (which of them wins is
        // unpredictable).
        let (mut best, mut slots) = none;
        for k in 0..i {
            let c = left[k] + right[i - 1 - k];
            let better = c < best;
            best = if better { c } else { best };
            slots = if better {
                split_slots(k as u8, (i - 1 - k) as u8)
            } else {
                slots
            };
        }
        *share = (best, slots);
    }
    shares
}

/// The kinds of packed choices ([`Choice::unpack`]).
const KIND_LEAF: u8 = 0;
const KIND_NODE: u8 = 1 << 6;
const KIND_SPLIT: u8 = 2 << 6;

/// A packed choice's slot fields, three bits each (`u8::MAX`, no sharing found, packs
/// as 7).
fn split_slots(left: u8, right: u8) -> u8 {
    (left << 3 | right & 7) & 0x3f
}

/// Seven choices and a zero byte, in the order [`Collapse::choice`] reads them.
fn pad(choices: [u8; SLOTS - 1]) -> [u8; 8] {
    let mut bytes = [0; 8];
    bytes[..SLOTS - 1].copy_from_slice(&choices);
    bytes
}

/// A subtree's cost for each number of slots, and its primitive count.
struct Costs {
    cost: [f32; SLOTS - 1],
    primitives: u32,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::{BuildPreset, Bvh, LEAF, leaf_range};
    use obvhs::aabb::Aabb;
    use std::collections::HashMap;

    fn half_area(min: [f32; 3], max: [f32; 3]) -> f64 {
        let d = [0, 1, 2].map(|a| f64::from(max[a]) - f64::from(min[a]));
        d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
    }

    /// A leaf's cost in float64, counted independently of [`LeafCost::of`]: whole groups,
    /// a part-full last group tested all the same.
    fn leaf_cost(cost: LeafCost, primitives: u32, area: f64) -> f64 {
        let groups = (0..primitives).step_by(cost.group as usize).count() as f64;
        area * f64::from(cost.per_group) * groups
    }

    /// The cheapest wide tree under binary node `n` made a wide node, found by listing
    /// every set of at most eight descendants that can fill its slots (float64).
    struct Exhaustive<'a> {
        bvh2: &'a Bvh2,
        max_leaf: u32,
        cost: LeafCost,
        wide: HashMap<usize, f64>,
    }

    impl Exhaustive<'_> {
        fn area(&self, n: usize) -> f64 {
            let b = self.bvh2.nodes[n].aabb();
            half_area(b.min.to_array(), b.max.to_array())
        }

        fn primitives(&self, n: usize) -> u32 {
            let node = &self.bvh2.nodes[n];
            if node.is_leaf() {
                return node.prim_count;
            }
            let first = node.first_index as usize;
            self.primitives(first) + self.primitives(first + 1)
        }

        /// Every set of at most eight descendants of inner node `n` that covers its
        /// primitives, each set drawn from both children.
        fn fillings(&self, n: usize) -> Vec<Vec<usize>> {
            let first = self.bvh2.nodes[n].first_index as usize;
            let sides = [first, first + 1].map(|c| {
                let mut options = vec![vec![c]];
                if !self.bvh2.nodes[c].is_leaf() {
                    options.extend(self.fillings(c));
                }
                options
            });
            let mut all = Vec::new();
            for a in &sides[0] {
                for b in &sides[1] {
                    if a.len() + b.len() <= SLOTS {
                        all.push([a.clone(), b.clone()].concat());
                    }
                }
            }
            all
        }

        fn slot(&mut self, n: usize) -> f64 {
            let node = &self.bvh2.nodes[n];
            let primitives = self.primitives(n);
            let as_leaf = if node.is_leaf() || primitives <= self.max_leaf {
                leaf_cost(self.cost, primitives, self.area(n))
            } else {
                f64::INFINITY
            };
            let as_node = if node.is_leaf() {
                f64::INFINITY
            } else {
                self.wide(n)
            };
            as_leaf.min(as_node)
        }

        fn wide(&mut self, n: usize) -> f64 {
            if let Some(&cost) = self.wide.get(&n) {
                return cost;
            }
            let best = (self.fillings(n).into_iter())
                .map(|set| set.into_iter().map(|f| self.slot(f)).sum::<f64>())
                .fold(f64::INFINITY, f64::min);
            let cost = self.area(n) + best;
            self.wide.insert(n, cost);
            cost
        }
    }

    /// What the wide tree under `child` costs: each node's box area, each leaf's cost.
    fn wide_tree_cost(bvh: &Bvh<f32>, child: u32, cost: LeafCost, node_area: f64) -> f64 {
        let node = &bvh.nodes()[child as usize];
        let mut total = node_area;
        for slot in 0..crate::bvh::WIDTH {
            let reference = node.children[slot];
            if reference == 0 {
                continue;
            }
            let min = [0, 1, 2].map(|a| node.planes[0][a][slot]);
            let max = [0, 1, 2].map(|a| node.planes[1][a][slot]);
            let area = half_area(min, max);
            total += if reference & LEAF != 0 {
                leaf_cost(cost, leaf_range(reference).1, area)
            } else {
                wide_tree_cost(bvh, reference, cost, area)
            };
        }
        total
    }

    #[test]
    fn small_trees_collapse_into_the_cheapest_wide_tree() {
        // Against every way of filling every wide node's slots, listed one by one: a
        // choice packed or read back wrong, a cost or a tie taken wrong, builds a dearer
        // tree (or a broken one) here.
        let mut random = crate::test_random::XorShift::new(0x2545_f491_4f6c_dd1d);
        let mut next = move || random.unit_f32();
        for count in [9, 12, 17, 24] {
            for trial in 0..6 {
                let boxes: Vec<Aabb> = (0..count)
                    .map(|_| {
                        let lo = glam::Vec3A::new(next(), next(), next());
                        let size = glam::Vec3A::new(next(), next(), next()) * 0.3;
                        Aabb::new(lo, lo + size)
                    })
                    .collect();
                let bvh2 = obvhs::ploc::PlocBuilder::new().build(
                    obvhs::ploc::PlocSearchDistance::Minimum,
                    &boxes,
                    (0..count as u32).collect(),
                    obvhs::ploc::SortPrecision::U64,
                    0,
                );
                for (max_leaf, cost) in [1, 3, 4, 8]
                    .into_iter()
                    .flat_map(|m| [(m, LeafCost::ONE_BY_ONE), (m, LeafCost::TRIANGLE_BLOCKS)])
                {
                    let (bvh, _): (Bvh<f32>, _) = Bvh::from_bvh2(&bvh2, max_leaf, cost);
                    let root = bvh2.nodes[0].aabb();
                    let root_area = half_area(root.min.to_array(), root.max.to_array());
                    let built = wide_tree_cost(&bvh, 0, cost, root_area);
                    let mut exhaustive = Exhaustive {
                        bvh2: &bvh2,
                        max_leaf,
                        cost,
                        wide: HashMap::new(),
                    };
                    let best = exhaustive.wide(0);
                    let context = format!("{count} boxes, trial {trial}, {max_leaf}, {cost:?}");
                    assert!(built <= best * (1.0 + 1e-5), "{context}: {built} > {best}");
                    assert!(built >= best * (1.0 - 1e-5), "{context}: {built} < {best}");
                }
            }
        }
    }

    #[test]
    fn a_leaf_costs_the_whole_blocks_its_triangles_fill() {
        for n in 1..=16u32 {
            // Four triangles to a block, the last block perhaps part full.
            let blocks = (0..n).step_by(4).count();
            let expected = 0.3 * blocks as f32;
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
            let params = BuildPreset::default().params(16);
            let (bvh, _): (Bvh<f32>, _) = Bvh::build(&boxes, params, cost);
            let per_leaf = boxes.len() as f64 / bvh.leaves().count() as f64;
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
