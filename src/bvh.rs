//! An 8-wide bounding volume hierarchy: the tree comes from obvhs' PLOC builder, the nodes,
//! the box test and the traversal are ours.
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

/// Named build presets, from fastest build to fastest traversal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BuildPreset {
    /// PLOC with the smallest search radius and no reinsertion.
    Fastest,
    /// obvhs' `fast_build`.
    Fast,
    /// obvhs' `medium_build`: about Embree's build time, better trees.
    #[default]
    Medium,
    /// obvhs' `slow_build` without spatial splits (split boxes would not bound whole
    /// triangles, which the robust test relies on).
    Slow,
}

impl BuildPreset {
    pub const ALL: [BuildPreset; 4] = [
        BuildPreset::Fastest,
        BuildPreset::Fast,
        BuildPreset::Medium,
        BuildPreset::Slow,
    ];

    pub fn name(self) -> &'static str {
        match self {
            BuildPreset::Fastest => "fastest",
            BuildPreset::Fast => "fast",
            BuildPreset::Medium => "medium",
            BuildPreset::Slow => "slow",
        }
    }

    /// The obvhs parameters, with at most `max_leaf` primitives per leaf.
    pub fn params(self, max_leaf: u32) -> BvhBuildParams {
        let mut params = match self {
            BuildPreset::Fastest => BvhBuildParams::fastest_build(),
            BuildPreset::Fast => BvhBuildParams::fast_build(),
            BuildPreset::Medium => BvhBuildParams::medium_build(),
            BuildPreset::Slow => BvhBuildParams::slow_build(),
        };
        params.pre_split = false;
        params.max_prims_per_leaf = max_leaf.clamp(1, MAX_LEAF_ITEMS);
        params
    }
}

/// A built tree over some primitives. Leaves refer to ranges of *items*, which the owner
/// lays out in leaf order (triangle blocks, spheres).
#[derive(Debug, Clone)]
pub struct Bvh<T> {
    nodes: Vec<Node<T>>,
    /// Stack entries a traversal can need: `(WIDTH − 1) · depth + 1`.
    stack_bound: usize,
    depth: usize,
}

impl<T: Scalar> Bvh<T> {
    /// Builds the tree over primitives with exact bounds `bounds` (in `T`). obvhs decides
    /// the topology from float32 boxes (`bounds` rounded outward); `emit_leaf` receives
    /// each leaf's primitive indices and returns the `(first, count)` of the items it laid
    /// out for them (`count` ≤ [`MAX_LEAF_ITEMS`]).
    pub fn build(
        bounds: &[Bounds<T>],
        topology_boxes: &[Aabb],
        params: BvhBuildParams,
        emit_leaf: impl FnMut(&[u32]) -> (u32, u32),
    ) -> Bvh<T> {
        assert_eq!(bounds.len(), topology_boxes.len());
        if bounds.is_empty() {
            return Bvh {
                nodes: Vec::new(),
                stack_bound: 0,
                depth: 0,
            };
        }
        let bvh2 = build_bvh2(topology_boxes, params);
        Bvh::from_bvh2(&bvh2, bounds, emit_leaf)
    }

    /// Builds the tree with obvhs' wide-BVH pipeline: PLOC with one primitive per leaf,
    /// reinsertion, then the SAH-optimal collapse to 8-wide nodes with leaves of at most
    /// `max_leaf` (≤ 3) primitives (Ylitie, Karras and Laine 2017). Only the grouping is
    /// kept: obvhs' quantized boxes are replaced by exact ones computed from `bounds`.
    pub fn build_wide(
        bounds: &[Bounds<T>],
        topology_boxes: &[Aabb],
        mut params: BvhBuildParams,
        emit_leaf: impl FnMut(&[u32]) -> (u32, u32),
    ) -> Bvh<T> {
        assert_eq!(bounds.len(), topology_boxes.len());
        if bounds.is_empty() {
            return Bvh {
                nodes: Vec::new(),
                stack_bound: 0,
                depth: 0,
            };
        }
        let max_leaf = params.max_prims_per_leaf.clamp(1, 3);
        params.max_prims_per_leaf = 1;
        let mut bvh2 = obvhs::ploc::PlocBuilder::with_capacity(topology_boxes.len()).build(
            params.ploc_search_distance,
            topology_boxes,
            (0..topology_boxes.len() as u32).collect(),
            params.sort_precision,
            params.search_depth_threshold,
        );
        obvhs::bvh2::reinsertion::ReinsertionOptimizer::default().run(
            &mut bvh2,
            params.reinsertion_batch_ratio,
            None,
        );
        let wide = obvhs::cwbvh::bvh2_to_cwbvh::bvh2_to_cwbvh(&bvh2, max_leaf, false, false);
        Bvh::from_cwbvh(&wide, bounds, emit_leaf)
    }

    /// Takes the node grouping of an obvhs compressed wide BVH: slot `i` of node `n` is an
    /// inner node when bit `i` of `imask` is set (inner children follow `child_base_idx` in
    /// slot order), else a leaf whose `child_meta` gives its primitives' offset (low 5
    /// bits) and count (unary, high 3 bits) from `primitive_base_idx`.
    pub fn from_cwbvh(
        wide: &obvhs::cwbvh::CwBvh,
        bounds: &[Bounds<T>],
        mut emit_leaf: impl FnMut(&[u32]) -> (u32, u32),
    ) -> Bvh<T> {
        let mut nodes = vec![Node::empty(); wide.nodes.len()];
        let mut slot_bounds = vec![[Bounds::EMPTY; WIDTH]; wide.nodes.len()];
        let mut level = vec![0usize; wide.nodes.len()];
        level[0] = 1;
        for (n, source) in wide.nodes.iter().enumerate() {
            let mut inner = 0;
            for (slot, &meta) in source.child_meta.iter().enumerate() {
                if source.imask & (1 << slot) != 0 {
                    let child = source.child_base_idx as usize + inner;
                    inner += 1;
                    nodes[n].children[slot] = child as ChildRef;
                    level[child] = level[n] + 1;
                } else if meta != 0 {
                    let count = (meta >> 5).count_ones() as usize;
                    let first = source.primitive_base_idx as usize + (meta & 0b1_1111) as usize;
                    let prims = &wide.primitive_indices[first..first + count];
                    slot_bounds[n][slot] = prims
                        .iter()
                        .fold(Bounds::EMPTY, |acc, &p| acc.union(&bounds[p as usize]));
                    let (first, count) = emit_leaf(prims);
                    nodes[n].children[slot] = leaf_ref(first, count);
                }
            }
        }
        let depth = level.iter().copied().max().unwrap_or(1);
        fill_bounds(&mut nodes, &mut slot_bounds);
        Bvh {
            nodes,
            stack_bound: (WIDTH - 1) * depth + 1,
            depth,
        }
    }

    /// Converts a binary obvhs tree: each node takes up to [`WIDTH`] descendants, always
    /// opening the inner one with the largest surface area. Iterative, so a degenerate
    /// (very deep) tree cannot exhaust the call stack.
    pub fn from_bvh2(
        bvh2: &Bvh2,
        bounds: &[Bounds<T>],
        mut emit_leaf: impl FnMut(&[u32]) -> (u32, u32),
    ) -> Bvh<T> {
        let mut nodes = vec![Node::empty()];
        // Slot boxes are filled in a second, bottom-up pass.
        let mut slot_bounds: Vec<[Bounds<T>; WIDTH]> = vec![[Bounds::EMPTY; WIDTH]];
        let mut pending = vec![(0usize, 0usize, 1usize)]; // (bvh2 node, wide node, depth)
        let mut depth = 1;
        let mut leaf = |node: &obvhs::bvh2::node::Bvh2Node| -> (ChildRef, Bounds<T>) {
            let first = node.first_index as usize;
            let prims = &bvh2.primitive_indices[first..first + node.prim_count as usize];
            let b = prims
                .iter()
                .fold(Bounds::EMPTY, |acc, &p| acc.union(&bounds[p as usize]));
            let (first, count) = emit_leaf(prims);
            (leaf_ref(first, count), b)
        };

        let root = &bvh2.nodes[0];
        if root.is_leaf() {
            let (child, b) = leaf(root);
            nodes[0].children[0] = child;
            slot_bounds[0][0] = b;
        }
        while let Some((source, target, level)) = pending.pop() {
            let source_node = &bvh2.nodes[source];
            if source_node.is_leaf() {
                continue;
            }
            depth = depth.max(level);
            let mut open = vec![
                source_node.first_index as usize,
                source_node.first_index as usize + 1,
            ];
            while open.len() < WIDTH {
                let area = |n: usize| bvh2.nodes[n].aabb().half_area();
                let widest = (0..open.len())
                    .filter(|&i| !bvh2.nodes[open[i]].is_leaf())
                    .max_by(|&a, &b| area(open[a]).total_cmp(&area(open[b])));
                let Some(i) = widest else { break };
                let n = open.swap_remove(i);
                let first = bvh2.nodes[n].first_index as usize;
                open.extend([first, first + 1]);
            }
            for (slot, &n) in open.iter().enumerate() {
                let child = &bvh2.nodes[n];
                if child.is_leaf() {
                    let (child_ref, b) = leaf(child);
                    nodes[target].children[slot] = child_ref;
                    slot_bounds[target][slot] = b;
                } else {
                    let index = nodes.len();
                    nodes.push(Node::empty());
                    slot_bounds.push([Bounds::EMPTY; WIDTH]);
                    nodes[target].children[slot] = index as ChildRef;
                    pending.push((n, index, level + 1));
                }
            }
        }

        fill_bounds(&mut nodes, &mut slot_bounds);
        Bvh {
            nodes,
            stack_bound: (WIDTH - 1) * depth + 1,
            depth,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    pub fn nodes(&self) -> &[Node<T>] {
        &self.nodes
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
        if self.nodes.is_empty() {
            return;
        }
        if self.stack_bound <= INLINE_STACK {
            self.closest_with(&mut InlineStack::<T, INLINE_STACK>::new(), ray, tmax, leaf);
        } else {
            let mut stack = Vec::with_capacity(self.stack_bound);
            self.closest_with(&mut stack, ray, tmax, leaf);
        }
    }

    #[inline(always)]
    fn closest_with(
        &self,
        stack: &mut impl Stack<T>,
        ray: &BoxRay<T>,
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
                let (mut mask, entry) = intersect_node(node, ray, *tmax);
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
        if self.nodes.is_empty() {
            return false;
        }
        if self.stack_bound <= INLINE_STACK {
            self.any_with(&mut InlineStack::<T, INLINE_STACK>::new(), ray, tmax, leaf)
        } else {
            let mut stack = Vec::with_capacity(self.stack_bound);
            self.any_with(&mut stack, ray, tmax, leaf)
        }
    }

    #[inline(always)]
    fn any_with(
        &self,
        stack: &mut impl Stack<T>,
        ray: &BoxRay<T>,
        tmax: T,
        mut leaf: impl FnMut(u32, u32) -> bool,
    ) -> bool {
        let mut current: ChildRef = 0;
        loop {
            if current & LEAF != 0 {
                let (first, count) = leaf_range(current);
                if leaf(first, count) {
                    return true;
                }
            } else {
                let node = &self.nodes[current as usize];
                let (mut mask, _) = intersect_node(node, ray, tmax);
                if mask != 0 {
                    let first = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    while mask != 0 {
                        let i = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        stack.push((node.children[i], T::default()));
                    }
                    current = node.children[first];
                    continue;
                }
            }
            match stack.pop() {
                Some((child, _)) => current = child,
                None => return false,
            }
        }
    }
}

/// Writes every slot's box into its node. Leaf slots come with their boxes; an inner
/// slot's box is the union of its child's slots. Children always come after their parent,
/// so a reverse sweep sees every child's box before the parent needs it.
fn fill_bounds<T: Scalar>(nodes: &mut [Node<T>], slot_bounds: &mut [[Bounds<T>; WIDTH]]) {
    for index in (0..nodes.len()).rev() {
        for slot in 0..WIDTH {
            let child = nodes[index].children[slot];
            if child & LEAF == 0 && child != 0 {
                let b = slot_bounds[child as usize]
                    .iter()
                    .fold(Bounds::EMPTY, |acc, s| acc.union(s));
                slot_bounds[index][slot] = b;
            }
            let b = slot_bounds[index][slot];
            nodes[index].set_bounds(slot, &b);
        }
    }
}

/// Runs obvhs' PLOC builder, reinsertion and leaf collapse on the given boxes.
pub fn build_bvh2(boxes: &[Aabb], params: BvhBuildParams) -> Bvh2 {
    let mut bvh2 = obvhs::ploc::PlocBuilder::with_capacity(boxes.len()).build(
        params.ploc_search_distance,
        boxes,
        (0..boxes.len() as u32).collect(),
        params.sort_precision,
        params.search_depth_threshold,
    );
    let mut reinsertion = obvhs::bvh2::reinsertion::ReinsertionOptimizer::default();
    reinsertion.run(&mut bvh2, params.reinsertion_batch_ratio, None);
    obvhs::bvh2::leaf_collapser::collapse(
        &mut bvh2,
        params.max_prims_per_leaf,
        params.collapse_traversal_cost,
    );
    reinsertion.run(
        &mut bvh2,
        params.reinsertion_batch_ratio * params.post_collapse_reinsertion_batch_ratio_multiplier,
        None,
    );
    bvh2
}

/// The float32 box obvhs needs for a primitive, rounded outward from exact float64 bounds.
pub fn outward_f32(min: [f64; 3], max: [f64; 3]) -> Aabb {
    Aabb::new(
        glam::Vec3A::from_array(min.map(f32_at_most)),
        glam::Vec3A::from_array(max.map(f32_at_least)),
    )
}

/// The largest float32 not above `x`.
pub fn f32_at_most(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) > x { f.next_down() } else { f }
}

/// The smallest float32 not below `x`.
pub fn f32_at_least(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) < x { f.next_up() } else { f }
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
