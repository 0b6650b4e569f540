//! An 8-wide bounding volume hierarchy: the binary tree comes from PLOC over obvhs' node
//! types (our passes for the job presets' search radius 1, [`crate::ploc`]; obvhs'
//! builder for wider searches); its collapse into wide nodes, the nodes, the box test and
//! the traversal are ours.
//!
//! Why not obvhs' own traversal: its CWBVH node test clamps the entry distance to a fixed
//! 1e-4 instead of the ray's `tmin`, its box tests are not conservative, its `safe_inverse`
//! replaces small direction components by ±1/ε (and then misses real hits), and its CWBVH
//! stack holds 32 entries and silently drops the rest. Here:
//!
//! - boxes are exact unions of the primitives' own bounds in the scalar type of the test
//!   (float32 for triangles, float64 for spheres), never quantized;
//! - the slab test uses `1/d` as IEEE gives it (±∞ for a zero component) with NaN-ignoring
//!   min/max, so rays parallel to a slab or starting on its plane are handled exactly;
//! - exit distances are widened by a factor that bounds the rounding of the test (Ize,
//!   "Robust BVH Ray Traversal", JCGT 2013; see [`Scalar::EXIT_SCALE`]), so no box a ray
//!   truly enters is culled;
//! - the entry distance starts at the ray's `tmin`, and the exit at the current `tmax`;
//! - the traversal stack is sized from the tree's actual depth at build time, so it can
//!   never overflow (deep trees use a heap stack instead of a fixed one).

use std::mem::MaybeUninit;

use obvhs::BvhBuildParams;
use obvhs::aabb::Aabb;
use obvhs::bvh2::Bvh2;

use rayon::prelude::*;

use crate::collapse::{Collapse, LeafCost};

/// Children per node.
pub const WIDTH: usize = 8;

/// A child reference: an inner node index, or with [`LEAF`] set a leaf's item range.
pub type ChildRef = u32;
/// Marks a leaf reference.
pub const LEAF: u32 = 1 << 31;
const LEAF_COUNT_SHIFT: u32 = 27;
const LEAF_FIRST_MASK: u32 = (1 << LEAF_COUNT_SHIFT) - 1;
/// Most items one leaf can hold.
pub const MAX_LEAF_ITEMS: u32 = 16;
/// Most items a tree can hold (leaf ranges are 27-bit offsets).
pub const MAX_ITEMS: usize = 1 << LEAF_COUNT_SHIFT;

/// Entries of the fixed traversal stack; deeper trees get a heap stack.
const INLINE_STACK: usize = 192;

/// The item range `(first, count)` of a leaf reference.
#[inline(always)]
pub fn leaf_range(child: ChildRef) -> (u32, u32) {
    (
        child & LEAF_FIRST_MASK,
        ((child & !LEAF) >> LEAF_COUNT_SHIFT) + 1,
    )
}

fn leaf_ref(first: u32, count: u32) -> ChildRef {
    debug_assert!((1..=MAX_LEAF_ITEMS).contains(&count));
    debug_assert!((first as usize) < MAX_ITEMS);
    LEAF | ((count - 1) << LEAF_COUNT_SHIFT) | first
}

/// The scalar of a tree's boxes: `f32` or `f64`.
pub trait Scalar:
    Copy
    + PartialOrd
    + Default
    + Send
    + Sync
    + std::fmt::Debug
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + 'static
{
    const INFINITY: Self;
    const NEG_INFINITY: Self;
    /// The factor that widens every exit distance (it scales the far planes' reciprocal
    /// directions). With `u` the unit roundoff and `γ(n) = nu / (1 − nu)`, an entry is
    /// computed within `γ(3)` of the truth (subtraction, reciprocal, product) and an exit
    /// within `γ(4)` (one more rounding for the scaled reciprocal), so any factor of at
    /// least `(1 + γ(3)) / (1 − γ(4))`, about `1 + 7u`, keeps a truly entered box entered
    /// (Ize, "Robust BVH Ray Traversal", JCGT 2013). We use `1 + 16u`.
    const EXIT_SCALE: Self;
    fn recip(self) -> Self;
    fn from_f32(x: f32) -> Self;
    /// Whether the sign bit is set (true for −0.0).
    fn sign_bit(self) -> bool;
}

impl Scalar for f32 {
    const INFINITY: f32 = f32::INFINITY;
    const NEG_INFINITY: f32 = f32::NEG_INFINITY;
    // u = 2^-24 and EPSILON = 2u: 1 + 16u.
    const EXIT_SCALE: f32 = 1.0 + 8.0 * f32::EPSILON;
    #[inline(always)]
    fn recip(self) -> f32 {
        1.0 / self
    }
    #[inline(always)]
    fn from_f32(x: f32) -> f32 {
        x
    }
    #[inline(always)]
    fn sign_bit(self) -> bool {
        self.is_sign_negative()
    }
}

impl Scalar for f64 {
    const INFINITY: f64 = f64::INFINITY;
    const NEG_INFINITY: f64 = f64::NEG_INFINITY;
    // u = 2^-53 and EPSILON = 2u: 1 + 16u.
    const EXIT_SCALE: f64 = 1.0 + 8.0 * f64::EPSILON;
    #[inline(always)]
    fn recip(self) -> f64 {
        1.0 / self
    }
    #[inline(always)]
    fn from_f32(x: f32) -> f64 {
        f64::from(x)
    }
    #[inline(always)]
    fn sign_bit(self) -> bool {
        self.is_sign_negative()
    }
}

/// An axis-aligned box in the tree's scalar.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds<T> {
    pub min: [T; 3],
    pub max: [T; 3],
}

impl<T: Scalar> Bounds<T> {
    /// The empty box, which no ray enters.
    pub const EMPTY: Bounds<T> = Bounds {
        min: [T::INFINITY; 3],
        max: [T::NEG_INFINITY; 3],
    };

    pub fn union(&self, other: &Bounds<T>) -> Bounds<T> {
        let mut out = *self;
        for axis in 0..3 {
            if other.min[axis] < out.min[axis] {
                out.min[axis] = other.min[axis];
            }
            if other.max[axis] > out.max[axis] {
                out.max[axis] = other.max[axis];
            }
        }
        out
    }
}

/// A node: the boxes of up to [`WIDTH`] children, stored plane by plane so one child per
/// lane is tested at once. Unused slots hold [`Bounds::EMPTY`].
#[derive(Debug, Clone, Copy)]
#[repr(C, align(64))]
pub struct Node<T> {
    /// `planes[0][axis]` are the children's minima along `axis`, `planes[1][axis]` maxima.
    pub planes: [[[T; WIDTH]; 3]; 2],
    pub children: [ChildRef; WIDTH],
}

impl<T: Scalar> Node<T> {
    fn empty() -> Node<T> {
        Node {
            planes: [[[T::INFINITY; WIDTH]; 3], [[T::NEG_INFINITY; WIDTH]; 3]],
            children: [0; WIDTH],
        }
    }

    /// Moves a node of a [`Part`] into the whole tree: inner references (other than to the
    /// part's root, which nothing inside the part refers to) shift by `node_offset`, and
    /// leaves from positions in the part's order to positions in the whole tree's, by
    /// `first_primitive`.
    fn relocate(&mut self, node_offset: u32, first_primitive: u32) {
        for child in &mut self.children {
            // Empty slots keep reference 0 (never followed: their boxes are empty).
            if *child == 0 {
                continue;
            }
            if *child & LEAF == 0 {
                *child += node_offset;
            } else {
                let (first, count) = leaf_range(*child);
                *child = leaf_ref(first_primitive + first, count);
            }
        }
    }

    fn set_bounds(&mut self, slot: usize, b: &Bounds<T>) {
        for axis in 0..3 {
            self.planes[0][axis][slot] = b.min[axis];
            self.planes[1][axis][slot] = b.max[axis];
        }
    }
}

/// A ray prepared for box tests.
#[derive(Debug, Clone, Copy)]
pub struct BoxRay<T> {
    pub origin: [T; 3],
    /// `1/d` per axis; ±∞ for a zero component.
    pub inv_dir: [T; 3],
    /// `inv_dir · EXIT_SCALE`, for the far planes (see [`Scalar::EXIT_SCALE`]).
    pub inv_dir_far: [T; 3],
    /// Per axis, 1 when the direction is negative (the near plane is then the maximum).
    pub near: [usize; 3],
    pub tmin: T,
}

impl<T: Scalar> BoxRay<T> {
    #[inline(always)]
    pub fn new(origin: [T; 3], direction: [T; 3], tmin: T) -> BoxRay<T> {
        let inv_dir = direction.map(Scalar::recip);
        BoxRay {
            origin,
            inv_dir,
            inv_dir_far: inv_dir.map(|i| i * T::EXIT_SCALE),
            near: direction.map(|d| usize::from(d.sign_bit())),
            tmin,
        }
    }
}

/// `max(a, b)` that ignores a NaN `a` (a ray starting exactly on a plane it runs along).
#[inline(always)]
fn max_keep<T: Scalar>(a: T, b: T) -> T {
    if a > b { a } else { b }
}

/// `min(a, b)` that ignores a NaN `a`.
#[inline(always)]
fn min_keep<T: Scalar>(a: T, b: T) -> T {
    if a < b { a } else { b }
}

/// The conservative slab test of all children: a bit per child the ray enters within
/// `[tmin, tmax]`, and each child's entry distance.
#[inline(always)]
pub fn intersect_node<T: Scalar>(node: &Node<T>, ray: &BoxRay<T>, tmax: T) -> (u32, [T; WIDTH]) {
    let near = [
        &node.planes[ray.near[0]][0],
        &node.planes[ray.near[1]][1],
        &node.planes[ray.near[2]][2],
    ];
    let far = [
        &node.planes[1 - ray.near[0]][0],
        &node.planes[1 - ray.near[1]][1],
        &node.planes[1 - ray.near[2]][2],
    ];
    let [ox, oy, oz] = ray.origin;
    let [ix, iy, iz] = ray.inv_dir;
    let [fx, fy, fz] = ray.inv_dir_far;
    let mut entry = [T::default(); WIDTH];
    let mut mask = 0u32;
    for i in 0..WIDTH {
        let enter = max_keep(
            (near[0][i] - ox) * ix,
            max_keep(
                (near[1][i] - oy) * iy,
                max_keep((near[2][i] - oz) * iz, ray.tmin),
            ),
        );
        let exit = min_keep(
            (far[0][i] - ox) * fx,
            min_keep((far[1][i] - oy) * fy, min_keep((far[2][i] - oz) * fz, tmax)),
        );
        entry[i] = enter;
        mask |= u32::from(enter <= exit) << i;
    }
    (mask, entry)
}

/// Camera rays per triangle from which a job's triangle tree is built with
/// [`BuildPreset::VeryFast`] ([`BuildPreset::for_triangles`]).
pub const REINSERTION_FROM_RAYS_PER_TRIANGLE: u64 = 64;

/// Named build presets, from fastest build to fastest traversal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BuildPreset {
    /// obvhs' `fastest_build`: PLOC with the smallest search radius and no reinsertion;
    /// the default. `VeryFast`'s 1% reinsertion was a fifth of a scanned model's build
    /// and a third of a sphere field's, for single rays 1–9% faster (depending on the
    /// mesh and the CPU) and camera-ray packets no faster (DEVELOPERS.md, "Build").
    #[default]
    Fastest,
    /// obvhs' `very_fast_build`: the smallest search radius and a little reinsertion.
    /// Against `Fast` it builds about a quarter faster and traces camera rays a few per
    /// cent slower. A job builds its triangle tree with it when it traces enough rays
    /// per triangle ([`BuildPreset::for_triangles`]), and so does `raybatch bench`,
    /// counting all its passes.
    VeryFast,
    /// obvhs' `fast_build`: a wider PLOC search.
    Fast,
    /// obvhs' `medium_build`: more reinsertion.
    Medium,
    /// obvhs' `slow_build` without spatial splits (split boxes would not bound whole
    /// triangles, which the robust test relies on).
    Slow,
}

impl BuildPreset {
    pub const ALL: [BuildPreset; 5] = [
        BuildPreset::Fastest,
        BuildPreset::VeryFast,
        BuildPreset::Fast,
        BuildPreset::Medium,
        BuildPreset::Slow,
    ];

    pub fn name(self) -> &'static str {
        match self {
            BuildPreset::Fastest => "fastest",
            BuildPreset::VeryFast => "very fast",
            BuildPreset::Fast => "fast",
            BuildPreset::Medium => "medium",
            BuildPreset::Slow => "slow",
        }
    }

    /// The preset for the triangle tree of a job that traces about `rays` camera rays
    /// through `triangles` triangles: [`BuildPreset::VeryFast`] from
    /// [`REINSERTION_FROM_RAYS_PER_TRIANGLE`] rays per triangle, else the default. The
    /// reinsertion costs time in proportion to the triangles and saves it in proportion to
    /// the rays: on a mesh of long thin triangles (the fandisk CAD part, 13k triangles, at
    /// full HD) a sixth of the job's instructions, elsewhere about as much as it costs
    /// (DEVELOPERS.md, "Build effort follows the rays"). Images do not depend on it.
    pub fn for_triangles(triangles: usize, rays: u64) -> BuildPreset {
        let per_triangle = REINSERTION_FROM_RAYS_PER_TRIANGLE;
        if triangles > 0 && rays / per_triangle >= triangles as u64 {
            BuildPreset::VeryFast
        } else {
            BuildPreset::default()
        }
    }

    /// The obvhs parameters, with at most `max_leaf` primitives per leaf.
    pub fn params(self, max_leaf: u32) -> BvhBuildParams {
        let mut params = match self {
            BuildPreset::Fastest => BvhBuildParams::fastest_build(),
            BuildPreset::VeryFast => BvhBuildParams::very_fast_build(),
            BuildPreset::Fast => BvhBuildParams::fast_build(),
            BuildPreset::Medium => BvhBuildParams::medium_build(),
            BuildPreset::Slow => BvhBuildParams::slow_build(),
        };
        params.pre_split = false;
        params.max_prims_per_leaf = max_leaf.clamp(1, MAX_LEAF_ITEMS);
        params
    }
}

/// A built tree over some primitives. Leaves refer to ranges of *items*: as built, the
/// primitives' positions in leaf order; the owner may lay its items out otherwise and
/// rewrite the ranges to match (triangle blocks: `Bvh::map_leaves`).
#[derive(Debug, Clone)]
pub struct Bvh<T> {
    nodes: Vec<Node<T>>,
    /// The union of the root's slot boxes ([`Bounds::EMPTY`] for an empty tree).
    bounds: Bounds<T>,
    /// Stack entries a traversal can need: `(WIDTH − 1) · depth + 1`.
    stack_bound: usize,
    depth: usize,
}

impl<T: Scalar> Bvh<T> {
    /// Builds the tree over primitives with boxes `boxes`: PLOC ([`binary_tree`], one
    /// primitive per leaf) and, where `params` asks for it, obvhs' reinsertion optimizer
    /// shape a binary tree, which is collapsed into 8-wide nodes with leaves of at most
    /// `params.max_prims_per_leaf` primitives, each leaf costing `leaf_cost`
    /// ([`crate::collapse`]). A tree that would need a longer traversal stack than
    /// [`KERNEL_STACK`] (obvhs' wider searches chain many equal boxes) is built again
    /// over a balanced binary tree of median splits. Each slot's box is the union of its
    /// primitives' boxes, exactly.
    ///
    /// Returns the tree and the primitives in leaf order: a leaf refers to the range
    /// `first..first + count` of that order (at most [`MAX_LEAF_ITEMS`]).
    pub fn build(
        boxes: &[Aabb],
        params: BvhBuildParams,
        leaf_cost: LeafCost,
    ) -> (Bvh<T>, Vec<u32>) {
        Bvh::build_from(boxes.len(), |i| boxes[i], params, leaf_cost)
    }

    /// [`Bvh::build`] over `count` primitives, the box of primitive `i` being
    /// `box_of(i)`, computed once each as the binary tree's leaves are made, so no list of
    /// boxes is held beside them. Gives the tree [`Bvh::build`] gives for those boxes.
    pub fn build_from(
        count: usize,
        box_of: impl Fn(usize) -> Aabb + Sync,
        params: BvhBuildParams,
        leaf_cost: LeafCost,
    ) -> (Bvh<T>, Vec<u32>) {
        if count == 0 {
            let empty = Bvh {
                nodes: Vec::new(),
                bounds: Bounds::EMPTY,
                stack_bound: 0,
                depth: 0,
            };
            return (empty, Vec::new());
        }
        let mut bvh2 = binary_tree(count, &box_of, &params);
        obvhs::bvh2::reinsertion::ReinsertionOptimizer::default().run(
            &mut bvh2,
            params.reinsertion_batch_ratio,
            None,
        );
        let built = Bvh::from_bvh2(&bvh2, params.max_prims_per_leaf, leaf_cost);
        if built.0.stack_bound <= KERNEL_STACK {
            return built;
        }
        // A chain from obvhs' wider PLOC searches (many equal boxes), or any tree too
        // deep: balanced instead, so that the vector kernels take it and no ray walks
        // the chain. The first tree goes first.
        drop((built, bvh2));
        let bvh2 = median_split(count, &box_of);
        Bvh::from_bvh2(&bvh2, params.max_prims_per_leaf, leaf_cost)
    }

    /// Collapses a binary obvhs tree into 8-wide nodes ([`crate::collapse`]), with leaves
    /// of at most `max_leaf` primitives (a binary leaf with more stays whole); returns the
    /// tree and the primitives in leaf order, as [`Bvh::build`] does. Slot boxes are the
    /// binary nodes' boxes, which obvhs keeps as exact unions of the primitives'
    /// (`bvh::tests::slot_boxes_are_exact_unions_of_their_primitives`).
    ///
    /// Nodes are laid out depth first, each node's inner children side by side. The top of
    /// the tree is laid out first; subtrees below [`PARALLEL_SUBTREE`] primitives are laid
    /// out in parallel and appended in order. Iterative, so a degenerate (very deep) tree
    /// cannot exhaust the call stack.
    pub fn from_bvh2(bvh2: &Bvh2, max_leaf: u32, leaf_cost: LeafCost) -> (Bvh<T>, Vec<u32>) {
        let collapse = Collapse::new(bvh2, max_leaf.max(1), leaf_cost);
        let total = bvh2.primitive_indices.len();
        assert!(
            total < MAX_ITEMS,
            "at most {MAX_ITEMS} primitives in one tree"
        );
        let mut top = Part::default();
        let mut deferred = Vec::new();
        top.lay_out(&collapse, bvh2, 0, 1, |child, wide, level| {
            let small = collapse.primitives(child) < PARALLEL_SUBTREE;
            if small {
                deferred.push((child, wide, level));
            }
            small
        });
        let parts: Vec<(Part<T>, usize, usize)> = deferred
            .into_par_iter()
            .map(|(root, wide, level)| {
                let mut part = Part::default();
                part.lay_out(&collapse, bvh2, root, level, |_, _, _| false);
                (part, wide, level)
            })
            .collect();

        // Appended after the top: a part's root goes to the slot the top reserved for it,
        // its other nodes after the nodes so far, its primitives after those so far.
        let Part {
            mut nodes,
            mut order,
            mut depth,
        } = top;
        for node in &mut nodes {
            node.relocate(0, 0);
        }
        nodes.reserve(parts.iter().map(|p| p.0.nodes.len() - 1).sum());
        order.reserve(total - order.len());
        for (part, wide, _) in parts {
            let node_offset = (nodes.len() - 1) as u32;
            let first_primitive = order.len() as u32;
            let mut part_nodes = part.nodes;
            for node in &mut part_nodes {
                node.relocate(node_offset, first_primitive);
            }
            nodes[wide] = part_nodes[0];
            nodes.extend_from_slice(&part_nodes[1..]);
            order.extend_from_slice(&part.order);
            depth = depth.max(part.depth);
        }
        let bounds = (0..WIDTH).fold(Bounds::EMPTY, |all, slot| {
            let planes = &nodes[0].planes;
            all.union(&Bounds {
                min: [0, 1, 2].map(|axis| planes[0][axis][slot]),
                max: [0, 1, 2].map(|axis| planes[1][axis][slot]),
            })
        });
        let bvh = Bvh {
            nodes,
            bounds,
            stack_bound: (WIDTH - 1) * depth + 1,
            depth,
        };
        (bvh, order)
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Every leaf's item range `(first, count)`, in node order.
    pub fn leaves(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        (self.nodes.iter())
            .flat_map(|node| node.children)
            .filter(|&child| child & LEAF != 0)
            .map(leaf_range)
    }

    /// Rewrites every leaf's item range `(first, count)` as `items(first, count)` (at most
    /// [`MAX_LEAF_ITEMS`] items), for an owner that lays its items out otherwise than
    /// one per primitive in leaf order.
    pub(crate) fn map_leaves(&mut self, items: impl Fn(u32, u32) -> (u32, u32)) {
        for child in self.nodes.iter_mut().flat_map(|node| &mut node.children) {
            if *child & LEAF != 0 {
                let (first, count) = leaf_range(*child);
                let (first, count) = items(first, count);
                *child = leaf_ref(first, count);
            }
        }
    }

    pub fn nodes(&self) -> &[Node<T>] {
        &self.nodes
    }

    /// The box around the whole tree: the union of the root's slot boxes, exactly
    /// ([`Bounds::EMPTY`] when the tree is empty).
    pub fn bounds(&self) -> Bounds<T> {
        self.bounds
    }

    /// Levels of nodes on the deepest path.
    pub fn depth(&self) -> usize {
        self.depth
    }

    /// The most stack entries a traversal of this tree can hold.
    pub fn stack_bound(&self) -> usize {
        self.stack_bound
    }

    /// Bytes held by the nodes.
    pub fn memory_bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<Node<T>>()
    }

    /// Closest-hit traversal: visits leaves front to back while `leaf(first, count, tmax)`
    /// shrinks `tmax` to the nearest hit found so far.
    #[inline]
    pub fn closest(&self, ray: &BoxRay<T>, tmax: &mut T, leaf: impl FnMut(u32, u32, &mut T)) {
        self.closest_by(|node, tmax| intersect_node(node, ray, tmax), tmax, leaf);
    }

    /// [`Bvh::closest`] with another node test, which must return what
    /// [`intersect_node`] returns for the ray (the AVX2 kernels pass their own).
    #[inline(always)]
    pub fn closest_by(
        &self,
        node_test: impl Fn(&Node<T>, T) -> (u32, [T; WIDTH]),
        tmax: &mut T,
        leaf: impl FnMut(u32, u32, &mut T),
    ) {
        if self.nodes.is_empty() {
            return;
        }
        if self.stack_bound <= INLINE_STACK {
            let mut stack = InlineStack::<T, INLINE_STACK>::new();
            self.closest_with(&mut stack, node_test, tmax, leaf);
        } else {
            let mut stack = Vec::with_capacity(self.stack_bound);
            self.closest_with(&mut stack, node_test, tmax, leaf);
        }
    }

    #[inline(always)]
    fn closest_with(
        &self,
        stack: &mut impl Stack<T>,
        node_test: impl Fn(&Node<T>, T) -> (u32, [T; WIDTH]),
        tmax: &mut T,
        mut leaf: impl FnMut(u32, u32, &mut T),
    ) {
        let mut current: ChildRef = 0;
        loop {
            if current & LEAF != 0 {
                let (first, count) = leaf_range(current);
                leaf(first, count, tmax);
            } else {
                let node = &self.nodes[current as usize];
                let (mut mask, entry) = node_test(node, *tmax);
                if mask != 0 {
                    let mut hits = [(0 as ChildRef, T::default()); WIDTH];
                    let mut n = 0;
                    while mask != 0 {
                        let i = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        // Insertion sort by (entry, child), farthest first: children
                        // are visited nearest first, the smaller reference on a tie (as
                        // the AVX2 traversal does, so both meet equal hits in one order).
                        let item = (node.children[i], entry[i]);
                        let mut j = n;
                        while j > 0 && (hits[j - 1].1, hits[j - 1].0) < (item.1, item.0) {
                            hits[j] = hits[j - 1];
                            j -= 1;
                        }
                        hits[j] = item;
                        n += 1;
                    }
                    for &h in &hits[..n - 1] {
                        stack.push(h);
                    }
                    current = hits[n - 1].0;
                    continue;
                }
            }
            loop {
                let Some((child, enter)) = stack.pop() else {
                    return;
                };
                if enter <= *tmax {
                    current = child;
                    break;
                }
            }
        }
    }

    /// Any-hit traversal: stops as soon as `leaf(first, count)` reports a hit.
    #[inline]
    pub fn any(&self, ray: &BoxRay<T>, tmax: T, leaf: impl FnMut(u32, u32) -> bool) -> bool {
        self.any_by(|node| intersect_node(node, ray, tmax).0, leaf)
    }

    /// [`Bvh::any`] over the subtree under node `start` only (`0` is the root), which
    /// also names where the hit was found: the node one level above the node holding the
    /// leaf that `leaf` stopped at ([`crate::scene::HINT_LEVELS`]), or `None` when nothing
    /// was hit. `above` stands for the node above `start` (unknown to the search; `start`
    /// itself will do), named for a leaf held by `start` itself.
    #[inline]
    pub fn any_below(
        &self,
        start: u32,
        above: u32,
        ray: &BoxRay<T>,
        tmax: T,
        leaf: impl FnMut(u32, u32) -> bool,
    ) -> Option<u32> {
        self.any_from(start, above, |node| intersect_node(node, ray, tmax).0, leaf)
    }

    /// For each item, the node `levels` levels above the node whose leaf holds it (the
    /// root where the tree is shallower): what [`Bvh::any_below`] names for a hit in that
    /// leaf when `levels` is 1. An item in several leaves gets one of them. (The tests'
    /// reference: the traversals find it on their way down.)
    #[cfg(test)]
    pub(crate) fn leaf_ancestors(&self, items: usize, levels: usize) -> Vec<u32> {
        let mut parents = vec![0u32; self.nodes.len()];
        let mut ancestors = vec![0u32; items];
        for (index, node) in self.nodes.iter().enumerate() {
            for &child in &node.children {
                if child & LEAF != 0 {
                    let (first, count) = leaf_range(child);
                    ancestors[first as usize..(first + count) as usize].fill(index as u32);
                } else if child != 0 {
                    parents[child as usize] = index as u32;
                }
            }
        }
        for node in &mut ancestors {
            for _ in 0..levels {
                *node = parents[*node as usize];
            }
        }
        ancestors
    }

    /// [`Bvh::any`] with another node test, which must return the child mask
    /// [`intersect_node`] returns for the ray and its `tmax`.
    #[inline(always)]
    pub fn any_by(
        &self,
        node_test: impl Fn(&Node<T>) -> u32,
        leaf: impl FnMut(u32, u32) -> bool,
    ) -> bool {
        self.any_from(0, 0, node_test, leaf).is_some()
    }

    #[inline(always)]
    fn any_from(
        &self,
        start: u32,
        above: u32,
        node_test: impl Fn(&Node<T>) -> u32,
        leaf: impl FnMut(u32, u32) -> bool,
    ) -> Option<u32> {
        if self.nodes.is_empty() {
            return None;
        }
        if self.stack_bound <= INLINE_STACK {
            let mut stack = InlineStack::<u32, INLINE_STACK>::new();
            self.any_with(start, above, &mut stack, node_test, leaf)
        } else {
            let mut stack = Vec::with_capacity(self.stack_bound);
            self.any_with(start, above, &mut stack, node_test, leaf)
        }
    }

    /// The any-hit loop. Each stack entry carries, beside the child, the node
    /// [`Bvh::any_below`] names for a hit under it: an inner child's parent, or, for a
    /// leaf, its node's parent.
    #[inline(always)]
    fn any_with(
        &self,
        start: u32,
        above: u32,
        stack: &mut impl Stack<u32>,
        node_test: impl Fn(&Node<T>) -> u32,
        mut leaf: impl FnMut(u32, u32) -> bool,
    ) -> Option<u32> {
        let (mut current, mut up): (ChildRef, u32) = (start, above);
        loop {
            if current & LEAF != 0 {
                let (first, count) = leaf_range(current);
                if leaf(first, count) {
                    return Some(up);
                }
            } else {
                let node = &self.nodes[current as usize];
                let mut mask = node_test(node);
                if mask != 0 {
                    let above_child =
                        |child: ChildRef| if child & LEAF != 0 { up } else { current };
                    let first = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    while mask != 0 {
                        let i = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        stack.push((node.children[i], above_child(node.children[i])));
                    }
                    (current, up) = (node.children[first], above_child(node.children[first]));
                    continue;
                }
            }
            (current, up) = stack.pop()?;
        }
    }
}

/// The binary tree over `count` (> 0) primitives, primitive `i` having the box
/// `box_of(i)`, one primitive per leaf, before any reinsertion: PLOC over the leaves in
/// Morton order. With search radius 1 (the `Fastest` and `VeryFast` presets) the sort
/// and passes are ours ([`crate::morton`], [`crate::ploc`]): the tree obvhs' passes make
/// from the leaves in the same order wherever no pass leaves [`crate::ploc::LONG_RUN`]
/// nodes in a row unmerged, and no quadratic build or chain where one does. Wider
/// searches are obvhs' `PlocBuilder`, the tree its `build` gives for those boxes.
///
/// The leaves are made here straight from `box_of`, in parallel. (`build` wants a list of
/// boxes, which for a million triangles is 32 MB written and read once, and from 500k
/// boxes gathers its leaves' parallel work into a list of its own, another 24 MB; page
/// faults on fresh memory are dear.)
pub fn binary_tree(
    count: usize,
    box_of: impl Fn(usize) -> Aabb + Sync,
    params: &BvhBuildParams,
) -> Bvh2 {
    use obvhs::bvh2::node::Bvh2Node;
    use obvhs::ploc::{PlocBuilder, PlocSearchDistance, SortPrecision};

    // `Bvh2::zeroed(count)`, but with its arrays made here. obvhs writes the nodes, and
    // sizes and fills its work arrays, one thread at a time; first touching a page costs
    // the kernel more than writing it, so the pages are touched here in parallel instead
    // (with obvhs' own starting values: zeros). A million triangles touch about 112 MB.
    // Our radius-1 passes make the nodes themselves, once the leaves are sorted.
    let zeros = |len: usize| -> Vec<Bvh2Node> {
        (0..len)
            .into_par_iter()
            .with_min_len(PARALLEL_LEAVES)
            .map(|_| Bvh2Node::default())
            .collect()
    };
    let mut bvh2 = Bvh2::zeroed(0);
    bvh2.primitive_indices = (0..count as u32)
        .into_par_iter()
        .with_min_len(PARALLEL_LEAVES)
        .collect();
    // Room for the whole tree: our radius-1 passes make the leaves' array the tree's.
    let minimum = matches!(params.ploc_search_distance, PlocSearchDistance::Minimum);
    let mut leaves = Vec::with_capacity(if minimum {
        (2 * count).saturating_sub(1)
    } else {
        count
    });
    leaves.par_extend(
        (0..count)
            .into_par_iter()
            .with_min_len(PARALLEL_LEAVES)
            .map(|i| Bvh2Node::new(box_of(i), 1, i as u32)),
    );
    // The union of the leaves' boxes, as obvhs takes it (exact: only minima and maxima).
    let total = (leaves.par_iter().with_min_len(PARALLEL_LEAVES))
        .fold(Aabb::empty, |mut total, leaf| {
            total.extend(leaf.aabb().min);
            total.extend(leaf.aabb().max);
            total
        })
        .reduce(Aabb::empty, |a, b| a.union(&b));
    if let PlocSearchDistance::Minimum = params.ploc_search_distance {
        crate::ploc::build(&mut bvh2, leaves, total);
        return bvh2;
    }
    bvh2.nodes = zeros((2 * count).saturating_sub(1));
    let mut builder = PlocBuilder::new();
    builder.current_nodes = leaves;
    builder.next_nodes = zeros(count);
    // As obvhs sizes its Morton codes: two 64-bit codes to an element, or one 128-bit.
    let mortons = match params.sort_precision {
        SortPrecision::U64 => count.div_ceil(2),
        SortPrecision::U128 => count,
    };
    builder.mortons = (0..mortons)
        .into_par_iter()
        .with_min_len(PARALLEL_LEAVES)
        .map(|_| [0u128; 2])
        .collect();
    let (precision, threshold) = (params.sort_precision, params.search_depth_threshold);
    // obvhs takes the search distance as a const parameter.
    macro_rules! build_with_distance {
        ($distance:literal) => {
            builder
                .build_ploc_from_leaves::<$distance, false>(&mut bvh2, total, precision, threshold)
        };
    }
    match params.ploc_search_distance {
        PlocSearchDistance::Minimum => build_with_distance!(1),
        PlocSearchDistance::VeryLow => build_with_distance!(2),
        PlocSearchDistance::Low => build_with_distance!(6),
        PlocSearchDistance::Medium => build_with_distance!(14),
        PlocSearchDistance::High => build_with_distance!(24),
        PlocSearchDistance::VeryHigh => build_with_distance!(32),
    }
    bvh2
}

/// The stack entries the vector traversals hold (`simd::STACK`): 36 levels of wide nodes.
/// [`Bvh::build_from`] builds a tree that would need more again, by median splits.
pub const KERNEL_STACK: usize = 256;

/// A balanced binary tree over `count` (> 0) primitives, primitive `i` having the box
/// `box_of(i)`: each node's primitives split in half at the median of their boxes'
/// centres along the axis where those centres spread most, one primitive per leaf, each
/// node's box the exact union of its primitives'. Its depth is `ceil(log2(count))`
/// whatever the boxes, where obvhs' PLOC passes merge one pair each when every
/// neighbour's merged box costs the same (copies of one triangle: a chain, in quadratic
/// time; DEVELOPERS.md, "A tree too deep for the kernels is built again"). Our radius-1
/// passes do not chain so ([`crate::ploc`]); this is for obvhs' wider searches. Poorer
/// than PLOC's on ordinary meshes, so only the fallback.
fn median_split(count: usize, box_of: impl Fn(usize) -> Aabb) -> Bvh2 {
    use obvhs::bvh2::node::Bvh2Node;
    let boxes: Vec<Aabb> = (0..count).map(box_of).collect();
    let mut order: Vec<u32> = (0..count as u32).collect();
    let mut nodes = vec![Bvh2Node::default(); 2 * count - 1];
    let mut next_pair = 1;
    let mut work = vec![(0, 0, count)];
    while let Some((node, start, end)) = work.pop() {
        let part = &mut order[start..end];
        let bounds = part
            .iter()
            .fold(Aabb::empty(), |all, &p| all.union(&boxes[p as usize]));
        if part.len() == 1 {
            nodes[node] = Bvh2Node::new(bounds, 1, start as u32);
            continue;
        }
        let centre = |p: u32| boxes[p as usize].center();
        let spread = part.iter().fold(Aabb::empty(), |mut all, &p| {
            all.extend(centre(p));
            all
        });
        let axis = spread.diagonal().max_position();
        let half = part.len() / 2;
        part.select_nth_unstable_by(half, |&a, &b| centre(a)[axis].total_cmp(&centre(b)[axis]));
        nodes[node] = Bvh2Node::new(bounds, 0, next_pair as u32);
        work.push((next_pair + 1, start + half, end));
        work.push((next_pair, start, start + half));
        next_pair += 2;
    }
    let mut bvh2 = Bvh2::zeroed(0);
    bvh2.nodes = nodes;
    bvh2.primitive_indices = order;
    bvh2.children_are_ordered_after_parents = true;
    bvh2
}

/// Leaves made by one task of [`binary_tree`] at least (fewer would not repay the split).
const PARALLEL_LEAVES: usize = 1 << 14;

/// Subtrees of fewer primitives than this are laid out in parallel by
/// [`Bvh::from_bvh2`] (larger ones are split further first).
pub const PARALLEL_SUBTREE: u32 = 1 << 14;

/// Part of a tree being laid out: nodes (the first is the part's root), primitives in
/// leaf order, and the depth reached. Until [`Node::relocate`], inner references are
/// indices into `nodes` and leaves refer to positions in `order`.
struct Part<T> {
    nodes: Vec<Node<T>>,
    order: Vec<u32>,
    depth: usize,
}

impl<T> Default for Part<T> {
    fn default() -> Self {
        Part {
            nodes: Vec::new(),
            order: Vec::new(),
            depth: 0,
        }
    }
}

impl<T: Scalar> Part<T> {
    /// Lays out the wide subtree of binary node `root` (at `level`, the root's being 1),
    /// depth first. `defer(child, wide, level)` may take an inner child off this part: its
    /// slot then points at the reserved node `wide`, left empty for the caller to fill.
    fn lay_out(
        &mut self,
        collapse: &Collapse,
        bvh2: &Bvh2,
        root: usize,
        level: usize,
        mut defer: impl FnMut(usize, usize, usize) -> bool,
    ) {
        // Every primitive under `root` lands here, or (the top part's deferred ones) is
        // appended here later: one allocation instead of doublings and copies.
        self.order.reserve(collapse.primitives(root) as usize);
        self.nodes.push(Node::empty());
        let mut pending = vec![(root, 0usize, level)]; // (binary node, wide node, depth)
        let (mut children, mut walk) = (Vec::new(), Vec::new());
        while let Some((source, target, level)) = pending.pop() {
            self.depth = self.depth.max(level);
            collapse.children(source, &mut children);
            let base = self.nodes.len();
            let mut inner = 0;
            for (slot, &child) in children.iter().enumerate() {
                let aabb = bvh2.nodes[child].aabb();
                self.nodes[target].set_bounds(
                    slot,
                    &Bounds {
                        min: aabb.min.to_array().map(T::from_f32),
                        max: aabb.max.to_array().map(T::from_f32),
                    },
                );
                if !collapse.is_leaf(child) {
                    self.nodes[target].children[slot] = (base + inner) as ChildRef;
                    inner += 1;
                    continue;
                }
                // The subtree's primitives, left to right.
                let first = self.order.len();
                walk.push(child);
                while let Some(n) = walk.pop() {
                    let node = &bvh2.nodes[n];
                    let first = node.first_index as usize;
                    if node.is_leaf() {
                        self.order.extend_from_slice(
                            &bvh2.primitive_indices[first..first + node.prim_count as usize],
                        );
                    } else {
                        walk.extend([first + 1, first]);
                    }
                }
                let count = self.order.len() - first;
                self.nodes[target].children[slot] = leaf_ref(first as u32, count as u32);
            }
            self.nodes.resize(base + inner, Node::empty());
            // The first inner child is laid out next: depth-first order.
            for (slot, &child) in children.iter().enumerate().rev() {
                let wide = self.nodes[target].children[slot];
                if wide & LEAF == 0 && !defer(child, wide as usize, level + 1) {
                    pending.push((child, wide as usize, level + 1));
                }
            }
        }
    }
}

/// The largest float32 not above `x` (NaN for NaN; −∞ below `f32::MIN`).
pub fn f32_at_most(x: f64) -> f32 {
    let f = x as f32;
    // Without branches: on real coordinates the comparison, and the sign `next_down`
    // would branch on, are coin tosses, and mispredictions made this the sphere build's
    // largest cost.
    let step = i32::from(f64::from(f) > x);
    f32::from_bits(ordered(ordered(f.to_bits() as i32) - step) as u32)
}

/// The smallest float32 not below `x` (NaN for NaN; +∞ above `f32::MAX`).
pub fn f32_at_least(x: f64) -> f32 {
    let f = x as f32;
    let step = i32::from(f64::from(f) < x);
    f32::from_bits(ordered(ordered(f.to_bits() as i32) + step) as u32)
}

/// The largest float32 strictly below `x`: `f32_at_most(x.next_down())`, a lower bound on
/// any real value that `x` approximates to within an ulp, computed without
/// `f64::next_down`'s branches on sign and zero (on real coordinates they are coin tosses).
/// NaN for NaN; −∞ for −∞.
pub fn f32_below(x: f64) -> f32 {
    let f = x as f32;
    let bits = f.to_bits() as i32;
    // One step down unless `f` is already below `x` (or is −∞); from +0 two, over −0.
    let step = i32::from((f64::from(f) >= x) & (f != f32::NEG_INFINITY));
    let step = step + (step & i32::from(bits == 0));
    f32::from_bits(ordered(ordered(bits) - step) as u32)
}

/// The smallest float32 strictly above `x`: `f32_at_least(x.next_up())`, [`f32_below`]'s
/// mirror (negation is exact in both formats). NaN for NaN; +∞ for +∞.
pub fn f32_above(x: f64) -> f32 {
    -f32_below(-x)
}

/// Float32 bits as integers in the floats' order (−0 just below +0), and back: the map is
/// its own inverse, so one step in the integers is `next_up`/`next_down`. The stepping
/// callers never step from a zero across the other zero: the cast keeps the sign of `x`.
fn ordered(bits: i32) -> i32 {
    bits ^ ((bits >> 31) & i32::MAX)
}

/// A traversal stack of `(child, entry distance)`.
trait Stack<T> {
    fn push(&mut self, entry: (ChildRef, T));
    fn pop(&mut self) -> Option<(ChildRef, T)>;
}

impl<T> Stack<T> for Vec<(ChildRef, T)> {
    #[inline(always)]
    fn push(&mut self, entry: (ChildRef, T)) {
        Vec::push(self, entry);
    }
    #[inline(always)]
    fn pop(&mut self) -> Option<(ChildRef, T)> {
        Vec::pop(self)
    }
}

/// A fixed stack that is not zeroed per ray (that would cost more than a shallow
/// traversal). Used only when the tree's stack bound fits; a push past the end panics
/// rather than dropping entries.
struct InlineStack<T, const N: usize> {
    items: [MaybeUninit<(ChildRef, T)>; N],
    len: usize,
}

impl<T: Copy, const N: usize> InlineStack<T, N> {
    #[inline(always)]
    fn new() -> Self {
        InlineStack {
            items: [const { MaybeUninit::uninit() }; N],
            len: 0,
        }
    }
}

impl<T: Copy, const N: usize> Stack<T> for InlineStack<T, N> {
    #[inline(always)]
    fn push(&mut self, entry: (ChildRef, T)) {
        self.items[self.len] = MaybeUninit::new(entry);
        self.len += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<(ChildRef, T)> {
        if self.len == 0 {
            return None;
        }
        self.len -= 1;
        // SAFETY: every slot below `len` was written by `push`, and entries are `Copy`.
        Some(unsafe { self.items[self.len].assume_init() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box(lo: [f32; 3], hi: [f32; 3]) -> Node<f32> {
        let mut node = Node::empty();
        node.set_bounds(0, &Bounds { min: lo, max: hi });
        node
    }

    #[test]
    fn f32_bounds_are_the_nearest_floats_on_their_side() {
        let mut xs = vec![
            0.0,
            -0.0,
            f64::MIN_POSITIVE,
            1e-300,
            1e-46,
            f64::from(f32::from_bits(1)),
            f64::from(f32::MAX),
            f64::from(f32::MAX) * (1.0 + 1e-12),
            1e39,
            f64::INFINITY,
            1.0,
            0.1,
            1.0 + 1e-12,
            f64::from(f32::MIN_POSITIVE),
        ];
        let mut random = crate::test_random::XorShift::new(0x2545_f491_4f6c_dd1d);
        for _ in 0..100_000 {
            let state = random.next_u64();
            // Any sign, exponents from 2^-160 to 2^160.
            let x =
                f64::from_bits(state & 0x800f_ffff_ffff_ffff | (863 + (state >> 54) % 320) << 52);
            xs.push(x);
        }
        let negated: Vec<f64> = xs.iter().map(|x| -x).collect();
        xs.extend(negated);
        for x in xs {
            let (below, above) = (f32_at_most(x), f32_at_least(x));
            assert!(
                f64::from(below) <= x && f64::from(below.next_up()) > x
                    || below == x as f32 && x == f64::INFINITY,
                "{x:e}: {below:e}"
            );
            assert!(
                f64::from(above) >= x && f64::from(above.next_down()) < x
                    || above == x as f32 && x == f64::NEG_INFINITY,
                "{x:e}: {above:e}"
            );
        }
        assert!(f32_at_most(f64::NAN).is_nan() && f32_at_least(f64::NAN).is_nan());
    }

    #[test]
    fn strict_f32_bounds_are_the_nearest_floats_past_the_next_float64() {
        let mut xs = vec![
            0.0,
            -0.0,
            f64::from_bits(1),
            f64::MIN_POSITIVE,
            1e-300,
            1e-46,
            f64::from(f32::from_bits(1)),
            f64::from(f32::from_bits(1)) / 2.0,
            f64::from(f32::MIN_POSITIVE),
            f64::from(f32::MAX),
            f64::from(f32::MAX) * (1.0 + 1e-12),
            f64::from(f32::MAX.next_down()),
            1e39,
            f64::MAX,
            f64::INFINITY,
            1.0,
            0.1,
            1.0 + 1e-12,
            f64::from(1.0f32.next_up()),
        ];
        let mut random = crate::test_random::XorShift::new(0x1234_5678_9abc_def1);
        for k in 0..200_000 {
            let state = random.next_u64();
            xs.push(match k % 4 {
                // Any sign, exponents from 2^-160 to 2^160.
                0 | 1 => f64::from_bits(
                    state & 0x800f_ffff_ffff_ffff | (863 + (state >> 54) % 320) << 52,
                ),
                // Float32 values and their float64 neighbours.
                2 => f64::from(f32::from_bits(state as u32 & 0x7f7f_ffff)),
                _ => f64::from(f32::from_bits(state as u32 & 0x7f7f_ffff)).next_up(),
            });
        }
        let negated: Vec<f64> = xs.iter().map(|x| -x).collect();
        xs.extend(negated);
        for x in xs {
            let (below, above) = (f32_below(x), f32_above(x));
            let want = (f32_at_most(x.next_down()), f32_at_least(x.next_up()));
            assert_eq!(below.to_bits(), want.0.to_bits(), "{x:e}: {below:e}");
            assert_eq!(above.to_bits(), want.1.to_bits(), "{x:e}: {above:e}");
        }
        assert!(f32_below(f64::NAN).is_nan() && f32_above(f64::NAN).is_nan());
    }

    /// Boxes scattered over many scales, with shared and repeated coordinates.
    fn scattered_boxes(count: usize) -> Vec<Aabb> {
        let mut random = crate::test_random::XorShift::new(0x9e37_79b9_7f4a_7c15);
        let mut next = move || random.unit_f32();
        (0..count)
            .map(|i| {
                let scale = [1e-3, 1.0, 1e4][i % 3];
                let lo = glam::Vec3A::new(next(), next(), next()) * scale;
                let size = glam::Vec3A::new(next(), next(), next()) * scale * 0.01;
                // Every seventh box is a point, every fifth (otherwise) flat.
                let size = match i {
                    _ if i % 7 == 0 => glam::Vec3A::ZERO,
                    _ if i % 5 == 0 => size * glam::Vec3A::new(1.0, 0.0, 1.0),
                    _ => size,
                };
                Aabb::new(lo, lo + size)
            })
            .collect()
    }

    /// The union of the primitives under `child`, checking every slot box on the way
    /// against it and marking each primitive seen (once).
    fn checked_union(
        bvh: &Bvh<f32>,
        child: ChildRef,
        order: &[u32],
        boxes: &[Aabb],
        seen: &mut [bool],
    ) -> Bounds<f32> {
        if child & LEAF != 0 {
            let (first, count) = leaf_range(child);
            let prims = &order[first as usize..(first + count) as usize];
            return prims.iter().fold(Bounds::EMPTY, |acc, &p| {
                assert!(!seen[p as usize], "primitive {p} in two leaves");
                seen[p as usize] = true;
                let b = &boxes[p as usize];
                acc.union(&Bounds {
                    min: b.min.to_array(),
                    max: b.max.to_array(),
                })
            });
        }
        let node = &bvh.nodes()[child as usize];
        let mut all = Bounds::EMPTY;
        for slot in 0..WIDTH {
            if node.children[slot] == 0 {
                continue;
            }
            let b = checked_union(bvh, node.children[slot], order, boxes, seen);
            let stored = Bounds {
                min: [0, 1, 2].map(|a| node.planes[0][a][slot]),
                max: [0, 1, 2].map(|a| node.planes[1][a][slot]),
            };
            assert_eq!(stored, b, "node {child} slot {slot}");
            all = all.union(&b);
        }
        all
    }

    #[test]
    fn slot_boxes_are_exact_unions_of_their_primitives() {
        // For every preset and leaf size: a box obvhs had padded or shrunk, or a slot
        // pointing at the wrong subtree, fails here. The larger set is split into parts
        // laid out in parallel, whose nodes and leaves are then moved into place.
        let (empty, _): (Bvh<f32>, _) =
            Bvh::build(&[], BuildPreset::default().params(4), LeafCost::ONE_BY_ONE);
        assert_eq!(empty.bounds(), Bounds::EMPTY);
        for (count, presets) in [
            (5000, &BuildPreset::ALL[..]),
            (
                20 * PARALLEL_SUBTREE as usize,
                &[BuildPreset::default()][..],
            ),
        ] {
            let boxes = scattered_boxes(count);
            for &preset in presets {
                for (max_leaf, cost) in [1, 3, 4, 16]
                    .into_iter()
                    .flat_map(|m| [(m, LeafCost::ONE_BY_ONE), (m, LeafCost::TRIANGLE_BLOCKS)])
                {
                    let (bvh, order): (Bvh<f32>, _) =
                        Bvh::build(&boxes, preset.params(max_leaf), cost);
                    for (_, count) in bvh.leaves() {
                        assert!(count <= max_leaf, "{preset:?}");
                    }
                    assert_eq!(order.len(), boxes.len());
                    let mut seen = vec![false; boxes.len()];
                    checked_union(&bvh, 0, &order, &boxes, &mut seen);
                    // The whole tree's box: every primitive's box united, exactly.
                    let all = boxes.iter().fold(Bounds::EMPTY, |acc, b| {
                        acc.union(&Bounds {
                            min: b.min.to_array(),
                            max: b.max.to_array(),
                        })
                    });
                    assert_eq!(bvh.bounds(), all, "{preset:?}");
                    assert!(
                        seen.iter().all(|&s| s),
                        "{preset:?}: a primitive is missing"
                    );
                }
            }
        }
    }

    #[test]
    fn many_equal_boxes_give_a_balanced_tree_the_kernels_can_take() {
        // Copies of one box, alone and among scattered ones: obvhs' PLOC passes merge one
        // pair of equal neighbours each and chain them, hundreds of levels deep. Our
        // radius-1 passes pair them up (`ploc`); the wider searches' chains are built
        // again (`median_split`). Either way the tree must come out within the kernels'
        // stack, with exact slot boxes.
        let copy = Aabb::new(glam::Vec3A::ZERO, glam::Vec3A::new(1.0, 1.0, 0.0));
        let mut mixed = scattered_boxes(3000);
        mixed.extend(std::iter::repeat_n(copy, 3000));
        for boxes in [vec![copy; 3000], mixed] {
            for preset in BuildPreset::ALL {
                for (max_leaf, cost) in [(1, LeafCost::ONE_BY_ONE), (16, LeafCost::TRIANGLE_BLOCKS)]
                {
                    let (bvh, order): (Bvh<f32>, _) =
                        Bvh::build(&boxes, preset.params(max_leaf), cost);
                    assert!(
                        bvh.stack_bound() <= KERNEL_STACK,
                        "{preset:?}: depth {}",
                        bvh.depth()
                    );
                    let mut seen = vec![false; boxes.len()];
                    checked_union(&bvh, 0, &order, &boxes, &mut seen);
                    assert!(
                        seen.iter().all(|&s| s),
                        "{preset:?}: a primitive is missing"
                    );
                }
            }
        }
    }

    #[test]
    fn reinsertion_is_chosen_from_64_camera_rays_per_triangle() {
        for triangles in [1usize, 400, 123_457] {
            let enough = 64 * triangles as u64;
            assert_eq!(
                BuildPreset::for_triangles(triangles, enough),
                BuildPreset::VeryFast
            );
            assert_eq!(
                BuildPreset::for_triangles(triangles, enough + 63),
                BuildPreset::VeryFast
            );
            assert_eq!(
                BuildPreset::for_triangles(triangles, enough - 1),
                BuildPreset::default()
            );
        }
        assert_eq!(
            BuildPreset::for_triangles(0, u64::MAX),
            BuildPreset::default()
        );
        assert_eq!(
            BuildPreset::for_triangles(usize::MAX, u64::MAX),
            BuildPreset::default()
        );
    }

    #[test]
    fn the_default_preset_is_very_fast_without_its_reinsertion() {
        // Of what the build reads (obvhs' own presets also differ in fields it does not
        // read), only the reinsertion differs.
        let read = |p: &BvhBuildParams| {
            format!(
                "{:?} {} {:?} {} {}",
                p.ploc_search_distance,
                p.search_depth_threshold,
                p.sort_precision,
                p.max_prims_per_leaf,
                p.pre_split
            )
        };
        let (default, very_fast) = (
            BuildPreset::default().params(4),
            BuildPreset::VeryFast.params(4),
        );
        assert_eq!(read(&default), read(&very_fast));
        assert_eq!(default.reinsertion_batch_ratio, 0.0);
        assert!(very_fast.reinsertion_batch_ratio > 0.0);
    }

    #[test]
    fn leaves_made_from_a_box_function_give_obvhs_own_binary_tree() {
        // `binary_tree` makes the leaves itself instead of handing obvhs a list of boxes,
        // and runs radius-1 passes of its own; on these boxes (no pass leaves
        // `ploc::LONG_RUN` nodes in a row unmerged) the tree must be the one obvhs'
        // `PlocBuilder::build` makes from that list, node for node, for every search
        // distance, and on both sides of the size (500k) at which obvhs makes its leaves
        // in parallel.
        for (count, presets) in [
            (1, &BuildPreset::ALL[..]),
            (2, &BuildPreset::ALL[..]),
            (3, &BuildPreset::ALL[..]),
            (100, &BuildPreset::ALL[..]),
            (5000, &BuildPreset::ALL[..]),
            (600_000, &[BuildPreset::default()][..]),
        ] {
            let boxes = scattered_boxes(count);
            for &preset in presets {
                let params = preset.params(4);
                let ours = binary_tree(count, |i| boxes[i], &params);
                // Our radius-1 passes take the leaves in `morton`'s order. Where codes are
                // equal (here the small boxes' centres often round to one code), obvhs'
                // unstable sort would pick an order of its own; given the boxes already
                // sorted, it leaves them as they are.
                let order: Vec<u32> = match params.ploc_search_distance {
                    obvhs::ploc::PlocSearchDistance::Minimum => morton_order(&boxes),
                    _ => (0..count as u32).collect(),
                };
                // (`PlocBuilder::new`, not `with_capacity`: the latter's zeroed per-thread
                // boxes put the origin into the total box obvhs takes from 500k boxes.)
                let theirs = obvhs::ploc::PlocBuilder::new().build(
                    params.ploc_search_distance,
                    &order.iter().map(|&i| boxes[i as usize]).collect::<Vec<_>>(),
                    order.clone(),
                    params.sort_precision,
                    params.search_depth_threshold,
                );
                let fields = |bvh: &Bvh2| -> Vec<_> {
                    (bvh.nodes.iter())
                        .map(|n| {
                            let b = n.aabb();
                            let (min, max) = (b.min.to_array(), b.max.to_array());
                            (
                                min.map(f32::to_bits),
                                max.map(f32::to_bits),
                                n.prim_count,
                                n.first_index,
                            )
                        })
                        .collect()
                };
                assert!(
                    fields(&ours) == fields(&theirs),
                    "{count} boxes, {preset:?}: the nodes differ"
                );
                // A leaf names its primitive; obvhs keeps the list of indices it was given.
                assert!(ours.primitive_indices.iter().copied().eq(0..count as u32));
                assert_eq!(theirs.primitive_indices, order);
                assert_eq!(ours.max_depth, theirs.max_depth);
            }
        }
    }

    /// The primitives in the order [`crate::morton::sorted_leaves`] puts their boxes.
    fn morton_order(boxes: &[Aabb]) -> Vec<u32> {
        let leaves: Vec<_> = (boxes.iter().zip(0..))
            .map(|(b, i)| obvhs::bvh2::node::Bvh2Node::new(*b, 1, i))
            .collect();
        let total = boxes.iter().fold(Aabb::empty(), |all, b| all.union(b));
        (crate::morton::sorted_leaves(&leaves, total).iter())
            .map(|leaf| leaf.first_index)
            .collect()
    }

    /// Records for each item the nodes from the root down to the node of its leaf.
    fn paths(bvh: &Bvh<f32>, node: u32, path: &mut Vec<u32>, out: &mut [Vec<u32>]) {
        path.push(node);
        for &child in &bvh.nodes()[node as usize].children {
            if child & LEAF != 0 {
                let (first, count) = leaf_range(child);
                for item in first..first + count {
                    out[item as usize] = path.clone();
                }
            } else if child != 0 {
                paths(bvh, child, path, out);
            }
        }
        path.pop();
    }

    #[test]
    fn leaf_ancestors_are_the_nodes_that_many_levels_above_each_items_leaf() {
        let boxes = scattered_boxes(5000);
        let (bvh, _): (Bvh<f32>, _) = Bvh::build(
            &boxes,
            BuildPreset::default().params(4),
            LeafCost::ONE_BY_ONE,
        );
        let mut expected = vec![Vec::new(); boxes.len()];
        paths(&bvh, 0, &mut Vec::new(), &mut expected);
        assert!(bvh.depth() >= 4);
        for levels in 0..=bvh.depth() + 1 {
            let ancestors = bvh.leaf_ancestors(boxes.len(), levels);
            for (item, path) in expected.iter().enumerate() {
                let want = path[path.len().saturating_sub(levels + 1)];
                assert_eq!(ancestors[item], want, "item {item}, {levels} levels up");
            }
        }
    }

    #[test]
    fn zero_direction_components_and_origins_on_a_slab_plane_are_exact() {
        let node = unit_box([0.0; 3], [1.0; 3]);
        // Along +z from inside the x and y slabs, from their boundary planes, and from
        // just outside: ∞·0 = NaN must not decide the test.
        let cases = [
            ([0.5, 0.5, -1.0], true),
            ([0.0, 0.0, -1.0], true),
            ([1.0, 1.0, -1.0], true),
            ([1.0, 0.0, -1.0], true),
            ([-1e-7, 0.5, -1.0], false),
            ([0.5, 1.0000001, -1.0], false),
        ];
        for (origin, expected) in cases {
            for dz in [1.0f32, -1.0] {
                for zero in [0.0f32, -0.0] {
                    let o = [origin[0], origin[1], if dz > 0.0 { -1.0 } else { 2.0 }];
                    let ray = BoxRay::new(o, [zero, zero, dz], 0.0);
                    let (mask, _) = intersect_node(&node, &ray, f32::INFINITY);
                    assert_eq!(
                        mask & 1 == 1,
                        expected,
                        "origin {o:?} dir [{zero}, {zero}, {dz}]"
                    );
                }
            }
        }
    }

    #[test]
    fn tiny_direction_components_keep_their_true_inverse() {
        // obvhs' safe_inverse turns 1e-9 into 1/ε ≈ 8.4e6 and misses this box, which the ray
        // reaches at x = 1e8 where y has risen to 0.1.
        let node = unit_box([1.0e8, 0.05, -1.0], [1.0e8 + 1.0, 0.15, 1.0]);
        let ray = BoxRay::new([0.0, 0.0, 0.0], [1.0, 1.0e-9, 0.0], 0.0);
        assert_eq!(intersect_node(&node, &ray, f32::INFINITY).0 & 1, 1);
    }

    #[test]
    fn entry_starts_at_the_rays_tmin_not_a_fixed_epsilon() {
        // obvhs' CWBVH test clamps the entry to 1e-4; a box ending 1e-5 ahead must be hit
        // when tmin is 0, and one ending before tmin must not.
        let node = unit_box([-1.0, -1.0, 0.0], [1.0, 1.0, 1.0e-5]);
        let ray = BoxRay::new([0.0; 3], [0.0, 0.0, 1.0], 0.0);
        assert_eq!(intersect_node(&node, &ray, f32::INFINITY).0 & 1, 1);
        let late = BoxRay::new([0.0; 3], [0.0, 0.0, 1.0], 2.0e-5);
        assert_eq!(intersect_node(&node, &late, f32::INFINITY).0 & 1, 0);
    }

    #[test]
    fn empty_slots_are_never_entered() {
        let node = Node::<f32>::empty();
        for d in [[1.0, 0.0, 0.0], [-0.0, 0.0, -1.0], [0.3, -0.4, 0.5]] {
            for o in [[0.0f32; 3], [f32::MAX, 0.0, 0.0], [-1e30, 1e30, 0.0]] {
                let ray = BoxRay::new(o, d, 0.0);
                assert_eq!(intersect_node(&node, &ray, f32::INFINITY).0, 0);
            }
        }
    }

    #[test]
    fn flat_boxes_are_entered_at_every_angle() {
        // A box of zero thickness (an axis-aligned triangle's bounds): the entry and exit
        // distances are equal up to rounding, which the exit widening must absorb.
        let mut misses = 0;
        for i in 0..20_000 {
            let z = 1.0 + (i % 97) as f32 * 0.731;
            let node = unit_box([-1.0, -1.0, z], [1.0, 1.0, z]);
            let a = i as f32 * 0.618_034;
            let (x, y) = (0.99 * (a * 3.1).sin(), 0.99 * (a * 1.7).cos());
            let origin = [0.37 * (a * 5.3).cos(), 0.41 * (a * 2.9).sin(), -3.3];
            let d = [x - origin[0], y - origin[1], z - origin[2]];
            let ray = BoxRay::new(origin, d, 0.0);
            if intersect_node(&node, &ray, f32::INFINITY).0 & 1 == 0 {
                misses += 1;
            }
        }
        assert_eq!(misses, 0);
    }
}
