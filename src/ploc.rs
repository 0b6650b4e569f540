//! PLOC with search radius 1, the binary tree under both of the job presets
//! ([`crate::bvh::BuildPreset::Fastest`] and `VeryFast`): leaves in Morton order, then
//! passes that merge each pair of neighbours that choose each other, as obvhs'
//! `PlocBuilder` does, with one change: a pass that leaves [`LONG_RUN`] or more nodes
//! in a row unmerged pairs them up itself.
//!
//! Why: with radius 1 a node takes its right neighbour unless the left one's merged box
//! costs strictly less, so two neighbours choose each other only at a local minimum of
//! the merge costs along the Morton order. Where costs are all equal (copies of one
//! triangle) or rise steadily, a pass merges one pair or a few: the build takes
//! quadratic time, and with equal costs the tree is a chain. A million copies of a
//! triangle did not build in two minutes; a fan of 200,000 triangles took seconds.
//! Paired up, such a run halves each pass. On the scans of `../shared/models`, the bench's
//! torus and random boxes no pass has a run that long, so there the tree is the one
//! obvhs' `PlocBuilder` makes from the leaves in the same order, node for node
//! (`bvh::tests::leaves_made_from_a_box_function_give_obvhs_own_binary_tree`,
//! `real_models::scanned_models_get_obvhs_own_binary_tree_from_our_radius_1_passes`).
//! The order is [`crate::morton`]'s: obvhs' Morton codes, with leaves of equal codes in
//! their own order, where obvhs' unstable sort may take them in another.

use std::ops::Range;

use obvhs::aabb::Aabb;
use obvhs::bvh2::node::Bvh2Node;
use obvhs::bvh2::{Bvh2, DEFAULT_MAX_STACK_DEPTH};
use rayon::prelude::*;

/// Nodes left unmerged in a row by a pass's mutual choices from which the pass pairs
/// them up in order itself (a left-over odd one stays). Long enough that real meshes do
/// not show one (the longest seen: 23 nodes, on beast; 35 in the random boxes of
/// `bvh::tests`), so their trees stay those of obvhs' passes. Short enough that a pass
/// of `n` nodes leaves about `n · LONG_RUN / (LONG_RUN + 1)` at most, since runs shorter
/// than this are kept whole only beside merged pairs: all passes together handle at most
/// about `LONG_RUN + 1` times the leaves. Where every merge costs the same, the tree is
/// at most `log2(n) + LONG_RUN + 1` deep.
pub const LONG_RUN: usize = 48;

/// Elements one parallel task takes at least. A pass's choices are made, and its nodes
/// merged, in parallel from two such pieces on ([`plan`]).
const PARALLEL_MIN: usize = 1 << 14;

/// The binary tree over `leaves` (at least one; leaf `i` holds primitive `i`, as
/// [`Bvh2Node::new`]`(box, 1, i)`) whose union box is `total`, written into `bvh2`,
/// whose `primitive_indices` must be `0..leaves.len()`. The root is node 0 and children
/// come after their parents. Returns the number of passes made.
///
/// The leaves' array becomes the tree's `2 · leaves.len() − 1` nodes (give it room for
/// them: with less, the tree takes a new array), once the leaves are sorted into an
/// array of their own. The passes then take turns between that array and the tree's
/// nodes not yet written: a pass writes its pairs from the end of those down and the
/// next pass's nodes from their start up, where they fit, since the nodes not yet
/// written always number one fewer than twice the nodes left. No array of leaves is
/// kept beside the tree and the sorted ones (DEVELOPERS.md, "The build holds as little
/// as it can at once").
pub fn build(bvh2: &mut Bvh2, leaves: Vec<Bvh2Node>, total: Aabb) -> usize {
    let count = leaves.len();
    debug_assert!(count > 0);
    let mut sorted = crate::morton::sorted_leaves(&leaves, total);
    // First touching a page costs the kernel more than writing it: the nodes are written
    // (with zeros) in parallel.
    let mut nodes = leaves;
    nodes.clear();
    nodes.par_extend(
        (0..2 * count - 1)
            .into_par_iter()
            .with_min_len(PARALLEL_MIN)
            .map(|_| Bvh2Node::default()),
    );
    bvh2.nodes = nodes;
    let mut choices = vec![0i8; count];
    // Pairs are written from the end of the nodes down, the root last to node 0.
    let mut free = bvh2.nodes.len();
    let mut passes = 0;
    let mut live = count;
    // Whether this pass's nodes are the first `live` of the tree's (else of `sorted`).
    let mut in_tree = false;
    while live > 1 {
        let nodes: &[Bvh2Node] = if in_tree {
            &bvh2.nodes[..live]
        } else {
            &sorted[..live]
        };
        choose(nodes, &mut choices[..live]);
        let plan = plan(&choices[..live], PARALLEL_MIN);
        let merges: usize = plan.iter().map(|(_, output)| output.merges).sum();
        // The pairs (`free = 2 · live − 1` down) reach into the nodes this pass reads,
        // the tree's first `live`, only when every node pairs up: these are then read
        // from `sorted`, and the next pass's nodes go into the tree, as on the other turn.
        if in_tree && 2 * merges > free - live {
            sorted[..live].copy_from_slice(&bvh2.nodes[..live]);
            in_tree = false;
        }
        let kept = if in_tree {
            let (nodes, tree) = bvh2.nodes[..free].split_at_mut(live);
            let out = Out {
                tree,
                start: live,
                next: Next::Apart(&mut sorted),
            };
            walk(nodes, &choices[..live], &plan, out)
        } else {
            let out = Out {
                tree: &mut bvh2.nodes[..free],
                start: 0,
                next: Next::BelowPairs,
            };
            walk(&sorted[..live], &choices[..live], &plan, out)
        };
        free -= 2 * merges;
        live = kept;
        in_tree = !in_tree;
        passes += 1;
    }
    debug_assert_eq!(free, 1);
    if !in_tree {
        bvh2.nodes[0] = sorted[0];
    }
    bvh2.max_depth = DEFAULT_MAX_STACK_DEPTH.max(passes + 1);
    bvh2.children_are_ordered_after_parents = true;
    passes
}

/// How a pass over `choices` is walked: ranges of the nodes, each with what its walk
/// writes, in order.
///
/// From two pieces of at least `piece` nodes on, there are several, walked in parallel.
/// Each piece but the first starts where a mutual pair does: a pair is the same whatever
/// the walk's start (its right node chose left, so it cannot start another pair), and
/// every run of unmerged nodes then lies in one piece. Counted first, each piece knows
/// where its output goes, so the tree and the next pass's nodes are those of one walk,
/// node for node.
fn plan(choices: &[i8], piece: usize) -> Vec<(Range<usize>, Output)> {
    if choices.len() < 2 * piece {
        return vec![(0..choices.len(), Output::of(choices))];
    }
    // A piece starts at the first pair from each multiple of `piece` on; where the next
    // `piece` nodes hold none, the piece before runs on.
    let starts: Vec<usize> = (0..choices.len())
        .step_by(piece)
        .filter_map(|from| {
            let to = (from + piece).min(choices.len() - 1);
            (from..to).find(|&i| from == 0 || pair_at(choices, i))
        })
        .collect();
    let ends = starts.iter().skip(1).copied().chain([choices.len()]);
    let ranges: Vec<Range<usize>> = starts.iter().zip(ends).map(|(&s, e)| s..e).collect();
    (ranges.into_par_iter())
        .map(|range| (range.clone(), Output::of(&choices[range])))
        .collect()
}

/// Where a pass writes.
struct Out<'a> {
    /// The tree's nodes not yet written, from node `start` on: the pass's pairs go into
    /// its end, from the last node down.
    tree: &'a mut [Bvh2Node],
    start: usize,
    next: Next<'a>,
}

/// Where a pass puts the nodes for the next one.
enum Next<'a> {
    /// From the start of this array.
    Apart(&'a mut [Bvh2Node]),
    /// From the start of [`Out::tree`], below the pass's pairs.
    BelowPairs,
}

/// Walks `nodes` with their `choices` as `plan` divides them, writing the merged pairs
/// and the next pass's nodes where `out` says. Returns the number of nodes for the next
/// pass.
fn walk(nodes: &[Bvh2Node], choices: &[i8], plan: &[(Range<usize>, Output)], out: Out) -> usize {
    let merges: usize = plan.iter().map(|(_, output)| output.merges).sum();
    let kept: usize = plan.iter().map(|(_, output)| output.kept).sum();
    let below = out.tree.len() - 2 * merges;
    let (low, pairs) = out.tree.split_at_mut(below);
    let next = match out.next {
        Next::Apart(next) => &mut next[..kept],
        Next::BelowPairs => &mut low[..kept],
    };
    // Each piece's share of the pairs (downwards) and of `next` (upwards), in order.
    let (mut pairs_left, mut next_left) = (pairs, next);
    let mut work = Vec::with_capacity(plan.len());
    for (range, output) in plan {
        let mine_from = pairs_left.len() - 2 * output.merges;
        let (lower, mine) = std::mem::take(&mut pairs_left).split_at_mut(mine_from);
        let (their_next, later) = std::mem::take(&mut next_left).split_at_mut(output.kept);
        let base = out.start + below + mine_from;
        work.push((range.clone(), Pass::new(mine, base, their_next)));
        (pairs_left, next_left) = (lower, later);
    }
    let each = |(range, mut pass): (Range<usize>, Pass)| {
        pass.walk(&nodes[range.clone()], &choices[range]);
        debug_assert!(pass.free == pass.base && pass.kept == pass.next.len());
    };
    if work.len() == 1 {
        work.into_iter().for_each(each);
    } else {
        work.into_par_iter().for_each(each);
    }
    kept
}

/// Whether a run of `len` nodes no mutual choice merged is paired up in order.
fn pairs_up(len: usize) -> bool {
    len >= LONG_RUN
}

/// Whether nodes `i` and `i + 1` choose each other.
fn pair_at(choices: &[i8], i: usize) -> bool {
    choices[i] == 1 && choices[i + 1] == -1
}

/// A stretch of a walk over a pass's choices.
enum Segment {
    /// Nodes no mutual choice merged (perhaps none).
    Run(std::ops::Range<usize>),
    /// Nodes `i` and `i + 1`, which chose each other.
    Pair(usize),
}

/// The segments of a walk over `choices` from its start, in order.
fn segments(choices: &[i8], mut each: impl FnMut(Segment)) {
    let mut run_start = 0;
    let mut i = 0;
    while i < choices.len() {
        if i + 1 < choices.len() && pair_at(choices, i) {
            each(Segment::Run(run_start..i));
            each(Segment::Pair(i));
            i += 2;
            run_start = i;
        } else {
            i += 1;
        }
    }
    each(Segment::Run(run_start..choices.len()));
}

/// What a walk writes: pairs into the tree, nodes for the next pass.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Output {
    merges: usize,
    kept: usize,
}

impl Output {
    /// What a walk over `choices` writes, counted without writing it.
    fn of(choices: &[i8]) -> Output {
        let mut output = Output::default();
        segments(choices, |segment| {
            let written = match segment {
                Segment::Run(run) => Output::carried(run.len()),
                Segment::Pair(_) => Output { merges: 1, kept: 1 },
            };
            output.merges += written.merges;
            output.kept += written.kept;
        });
        output
    }

    /// What [`Pass::carry`] writes for a run of `len` nodes.
    fn carried(len: usize) -> Output {
        if pairs_up(len) {
            Output {
                merges: len / 2,
                kept: len.div_ceil(2),
            }
        } else {
            Output {
                merges: 0,
                kept: len,
            }
        }
    }
}

/// One walk's output: merged pairs go into the tree, and the nodes for the next pass
/// (new parents and carried nodes, in order) into `next`.
struct Pass<'a> {
    /// The tree's nodes from `base` on.
    tree: &'a mut [Bvh2Node],
    base: usize,
    /// The tree's nodes from here on are written.
    free: usize,
    next: &'a mut [Bvh2Node],
    /// The nodes written to `next` so far.
    kept: usize,
}

impl<'a> Pass<'a> {
    /// Writes pairs from the end of `tree` (the tree's nodes from `base` on) down.
    fn new(tree: &'a mut [Bvh2Node], base: usize, next: &'a mut [Bvh2Node]) -> Pass<'a> {
        Pass {
            free: base + tree.len(),
            tree,
            base,
            next,
            kept: 0,
        }
    }

    fn walk(&mut self, nodes: &[Bvh2Node], choices: &[i8]) {
        segments(choices, |segment| match segment {
            Segment::Run(run) => self.carry(&nodes[run]),
            // obvhs merges at the right node of the pair, which it puts first.
            Segment::Pair(i) => self.merge(nodes[i + 1], nodes[i]),
        });
    }

    fn merge(&mut self, left: Bvh2Node, right: Bvh2Node) {
        self.free -= 2;
        let at = self.free - self.base;
        self.tree[at] = left;
        self.tree[at + 1] = right;
        let parent = Bvh2Node::new(left.aabb().union(right.aabb()), 0, self.free as u32);
        self.keep(parent);
    }

    fn keep(&mut self, node: Bvh2Node) {
        self.next[self.kept] = node;
        self.kept += 1;
    }

    /// Carries `run`, nodes no mutual choice merged, into the next pass: as they are,
    /// or paired up in order when there are [`LONG_RUN`] or more of them.
    fn carry(&mut self, run: &[Bvh2Node]) {
        if !pairs_up(run.len()) {
            self.next[self.kept..self.kept + run.len()].copy_from_slice(run);
            self.kept += run.len();
            return;
        }
        let mut pairs = run.chunks_exact(2);
        for pair in &mut pairs {
            self.merge(pair[1], pair[0]);
        }
        if let [last] = pairs.remainder() {
            self.keep(*last);
        }
    }
}

/// Each node's choice of neighbour, as obvhs makes it with radius 1: `1` (right) unless
/// merging with the left one gives a box of strictly smaller half area (`-1`); the last
/// node chooses left.
fn choose(nodes: &[Bvh2Node], choices: &mut [i8]) {
    let cost = |i: usize| nodes[i].aabb().union(nodes[i + 1].aabb()).half_area();
    let last = nodes.len() - 1;
    let chunk = |(start, out): (usize, &mut [i8])| {
        let mut left = if start == 0 {
            f32::INFINITY
        } else {
            cost(start - 1)
        };
        for (i, choice) in (start..).zip(out.iter_mut()) {
            if i == last {
                *choice = -1;
                break;
            }
            let right = cost(i);
            *choice = if left < right { -1 } else { 1 };
            left = right;
        }
    };
    if nodes.len() < 2 * PARALLEL_MIN {
        chunk((0, choices));
    } else {
        let size = nodes
            .len()
            .div_ceil(rayon::current_num_threads())
            .max(PARALLEL_MIN);
        (choices.par_chunks_mut(size).enumerate()).for_each(|(n, out)| chunk((n * size, out)));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3A;

    /// The tree `build` makes over `boxes`, checked: in the leaves' array, every primitive
    /// in exactly one leaf, and every inner node's box the union of its children's.
    /// Returns its depth (a lone leaf: 1) and the passes made.
    fn checked_tree(boxes: &[Aabb]) -> (usize, usize) {
        let count = boxes.len();
        let mut bvh2 = Bvh2::zeroed(0);
        bvh2.primitive_indices = (0..count as u32).collect();
        let mut leaves = Vec::with_capacity(2 * count - 1);
        leaves.extend((boxes.iter().enumerate()).map(|(i, b)| Bvh2Node::new(*b, 1, i as u32)));
        let array = leaves.as_ptr();
        let total = boxes.iter().fold(Aabb::empty(), |all, b| all.union(b));
        let passes = build(&mut bvh2, leaves, total);
        assert_eq!(bvh2.nodes.len(), 2 * count - 1);
        assert!(
            bvh2.nodes.as_ptr() == array,
            "the leaves' array is the tree's"
        );
        let mut seen = vec![false; boxes.len()];
        let mut depth = 0;
        let mut stack = vec![(0usize, 1usize)];
        while let Some((index, level)) = stack.pop() {
            depth = depth.max(level);
            let node = &bvh2.nodes[index];
            if node.is_leaf() {
                assert_eq!(node.prim_count, 1);
                let primitive = bvh2.primitive_indices[node.first_index as usize] as usize;
                assert!(!seen[primitive], "primitive {primitive} twice");
                seen[primitive] = true;
                assert_eq!(*node.aabb(), boxes[primitive]);
                continue;
            }
            let (left, right) = (node.first_index as usize, node.first_index as usize + 1);
            let union = bvh2.nodes[left].aabb().union(bvh2.nodes[right].aabb());
            assert_eq!(*node.aabb(), union, "node {index}");
            stack.extend([(left, level + 1), (right, level + 1)]);
        }
        assert!(seen.iter().all(|&s| s), "a primitive is missing");
        (depth, passes)
    }

    /// The depth (and passes) a tree over `count` primitives may reach when every pass
    /// pairs up its long runs and no two choose each other: halving down to a run too
    /// short to pair, then one merge a pass.
    fn depth_bound(count: usize) -> usize {
        count.next_power_of_two().trailing_zeros() as usize + LONG_RUN + 1
    }

    #[test]
    fn a_pass_walked_in_pieces_writes_what_one_walk_writes() {
        // Random boxes with stretches of copies among them, so that a pass has mutual
        // pairs, short runs and long runs (paired up), some across the places where
        // pieces would start if they were not moved to a pair's start. Leaves, so that
        // the parents the pass makes (no primitives) are told apart.
        let mut random = crate::test_random::XorShift::new(7);
        let mut nodes = Vec::new();
        for stretch in 0.. {
            if nodes.len() >= 5000 {
                break;
            }
            let corner = Vec3A::new(random.unit_f32(), random.unit_f32(), random.unit_f32());
            let size = Vec3A::splat(0.01 + random.unit_f32());
            let copies = match stretch % 16 {
                5 => 2,
                9 => LONG_RUN - 1,
                12 => LONG_RUN,
                15 => 3 * LONG_RUN + 1,
                _ => 1,
            };
            let copy = Bvh2Node::new(Aabb::new(corner, corner + size), 1, nodes.len() as u32);
            nodes.extend(std::iter::repeat_n(copy, copies));
        }
        let bits = |nodes: &[Bvh2Node]| -> Vec<_> {
            (nodes.iter())
                .map(|n| {
                    let b = n.aabb();
                    let bits = |v: Vec3A| v.to_array().map(f32::to_bits);
                    (bits(b.min), bits(b.max), n.prim_count, n.first_index)
                })
                .collect()
        };
        let mut choices = vec![0i8; nodes.len()];
        choose(&nodes, &mut choices);
        // The pass's pairs and next nodes, walked in pieces of `piece`, its next nodes
        // in an array apart or below its pairs, its tree starting at node `start` (the
        // parents it makes refer to their pairs by the tree's numbering: given here as
        // if it started at 0).
        let written = |piece: usize, below_pairs: bool, start: usize| {
            let mut tree = vec![Bvh2Node::default(); 2 * nodes.len()];
            let mut apart = vec![Bvh2Node::default(); nodes.len()];
            let plan = plan(&choices, piece);
            let next = if below_pairs {
                Next::BelowPairs
            } else {
                Next::Apart(&mut apart)
            };
            let out = Out {
                tree: &mut tree,
                start,
                next,
            };
            let kept = walk(&nodes, &choices, &plan, out);
            let merges: usize = plan.iter().map(|(_, output)| output.merges).sum();
            let free = tree.len() - 2 * merges;
            let mut next = if below_pairs { &tree } else { &apart }[..kept].to_vec();
            for node in next.iter_mut().filter(|n| n.prim_count == 0) {
                node.first_index -= start as u32;
            }
            (free, bits(&tree[free..]), bits(&next))
        };
        let whole = written(nodes.len(), false, 0);
        let merges = (2 * nodes.len() - whole.0) / 2;
        let pairs = (1..nodes.len())
            .filter(|&i| pair_at(&choices, i - 1))
            .count();
        // Both kinds of merge, many times over.
        assert!(
            pairs >= 100 && merges >= pairs + 1000,
            "{pairs} pairs, {merges} merges"
        );
        for piece in [1, 2, 3, 5, LONG_RUN, 1000, nodes.len() / 2] {
            for (below_pairs, start) in [(false, 0), (true, 0), (false, 7)] {
                assert!(
                    written(piece, below_pairs, start) == whole,
                    "pieces of {piece}, below the pairs {below_pairs}, from {start}"
                );
            }
        }
    }

    #[test]
    fn passes_that_pair_every_node_make_the_tree_of_the_boxes_own_hierarchy() {
        // Unit boxes along x at the numbers whose base-4 digits are 0 or 1: each pair of
        // neighbours is nearer than the pairs beside it at every scale, so every pass
        // pairs every node, the passes reading from the tree's nodes too, where their
        // pairs reach into what they read: a tree (checked) as deep as a perfect one, in
        // as many passes.
        for levels in [1, 2, 3, 10] {
            let count = 1usize << levels;
            let boxes: Vec<Aabb> = (0..count)
                .map(|i| {
                    let x = (0..levels)
                        .map(|bit| (i >> bit & 1) << (2 * bit))
                        .sum::<usize>();
                    let min = Vec3A::new(x as f32, 0.0, 0.0);
                    Aabb::new(min, min + Vec3A::ONE)
                })
                .collect();
            let (depth, passes) = checked_tree(&boxes);
            assert_eq!((depth, passes), (levels + 1, levels), "{count} boxes");
        }
    }

    #[test]
    fn copies_of_one_box_are_paired_up_not_chained() {
        // Every neighbour's merged box costs the same, so every node chooses its right
        // neighbour and only the last pair chooses each other: obvhs' passes merge one
        // pair each, a chain as deep as the count, in quadratic time.
        let copy = Aabb::new(Vec3A::ZERO, Vec3A::new(1.0, 1.0, 0.0));
        for count in [1, 2, 3, LONG_RUN - 1, LONG_RUN, LONG_RUN + 1, 1000, 100_000] {
            let (depth, passes) = checked_tree(&vec![copy; count]);
            assert!(depth <= depth_bound(count), "{count}: depth {depth}");
            assert!(passes <= depth_bound(count), "{count}: {passes} passes");
        }
    }

    #[test]
    fn merges_that_cost_more_and_more_are_paired_up_not_chained() {
        // Boxes along x whose gaps grow: each node's merge with its right neighbour costs
        // more than with its left one, so only the first pair chooses each other (and
        // with the order reversed, only the last). A fan's merges grow so.
        for reversed in [false, true] {
            let count = 10_000;
            let boxes: Vec<Aabb> = (0..count)
                .map(|i| {
                    let i = if reversed { count - i } else { i } as f32;
                    let x = i * i;
                    Aabb::new(Vec3A::new(x, 0.0, 0.0), Vec3A::new(x + 1.0, 1.0, 1.0))
                })
                .collect();
            let (depth, passes) = checked_tree(&boxes);
            assert!(
                depth <= depth_bound(count),
                "reversed {reversed}: depth {depth}"
            );
            assert!(
                passes <= depth_bound(count),
                "reversed {reversed}: {passes} passes"
            );
        }
    }
}
