//! Single rays traced side by side: several searches of the triangle tree advanced in
//! turns, a node or leaf of each at a time, so that one ray's wait for memory overlaps the
//! others' work. The batch queries use it where packets proved wasteful over rays that
//! share no leaves ([`crate::scene::Grouping::Paced`]).
//!
//! Where rays share few nodes (a mesh finer than the pixels) a single ray's search is a
//! chain of cache misses: each node's address is known only once its parent is tested,
//! and the CPU cannot look far enough ahead to reach the next ray. Here each step ends by
//! asking the cache for the node or leaf its ray visits next (`simd::prefetch_child`) and
//! turns to another ray; by the time the first ray's turn comes back, its memory has
//! usually arrived.
//!
//! A closest-hit search visits the same nodes and leaves in the same order as
//! [`crate::simd::closest`], with the same tests, so its hits are bit-identical; an
//! any-hit search answers as [`crate::simd::any`] does (whether some triangle has
//! `tmin < t < tmax`, which no order changes).

use std::arch::x86_64::*;
use std::mem::MaybeUninit;

use crate::bvh::{Bounds, Bvh, LEAF, Node, leaf_range};
use crate::scene::TriangleRay;
use crate::simd::{
    Lanes, STACK, block_pair_test, block_test, distance, enters, inverse, lane8, lanes, node_test,
    pack, prefetch_child, push_sorted, ray_constants, triangle_lanes,
};
use crate::triangle::{BLOCK, Nearest, TriangleBlock, TriangleHit};

/// Rays in flight at once. On the million-triangle torus at 320x180 (a probe, one
/// thread): two gained half as much as four, eight a little more, but eight lost more on
/// coherent rays (DEVELOPERS.md, "Rays that share no leaves are traced side by side").
pub const IN_FLIGHT: usize = 4;

/// A search in progress, one per slot of the rays in flight.
trait Search: Sized {
    /// One step: a node or leaf, then the choice of what comes next, whose memory is
    /// asked for. Returns whether the search is over.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    unsafe fn step(&mut self, nodes: &[Node<f32>], blocks: &[TriangleBlock]) -> bool;
}

/// The rays of one call and what is done with their answers.
trait Batch {
    type Search: Search;
    /// Sets up in `slot` (number `i` of the rays in flight) the search of ray `index`,
    /// and says whether one is needed (a ray may be answered at once).
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    unsafe fn start(
        &mut self,
        slot: &mut MaybeUninit<Self::Search>,
        i: usize,
        index: usize,
    ) -> bool;
    /// Takes the answer of a search that is over.
    fn finish(&mut self, search: &Self::Search);
}

/// Runs the searches of rays `0..len`, [`IN_FLIGHT`] at a time, each slot taking the next
/// ray as its search ends.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn run_in_turns<B: Batch>(
    batch: &mut B,
    len: usize,
    nodes: &[Node<f32>],
    blocks: &[TriangleBlock],
) {
    let mut searches = [const { MaybeUninit::<B::Search>::uninit() }; IN_FLIGHT];
    let mut next = 0;
    let mut active = 0;
    // SAFETY (for `refill` and `step`): AVX2 is enabled in the caller.
    while active < IN_FLIGHT
        && unsafe { refill(batch, &mut searches[active], active, &mut next, len) }
    {
        active += 1;
    }
    let mut i = 0;
    while active > 0 {
        // SAFETY: slots below `active` hold searches set up by `start`.
        let search = unsafe { searches[i].assume_init_mut() };
        if unsafe { search.step(nodes, blocks) } {
            batch.finish(search);
            if !unsafe { refill(batch, &mut searches[i], i, &mut next, len) } {
                // The last slot's search moves into this one, which is taken next.
                active -= 1;
                searches.swap(i, active);
                if i == active {
                    i = 0;
                }
                continue;
            }
        }
        i += 1;
        if i == active {
            i = 0;
        }
    }
}

/// Sets up `slot` (number `i`) with the search of the next ray from `*next` on that needs
/// one; false when none is left. (A function, not a closure: a closure would not inherit
/// the caller's AVX2.)
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn refill<B: Batch>(
    batch: &mut B,
    slot: &mut MaybeUninit<B::Search>,
    i: usize,
    next: &mut usize,
    len: usize,
) -> bool {
    while *next < len {
        *next += 1;
        // SAFETY: AVX2 is enabled in the caller.
        if unsafe { batch.start(slot, i, *next - 1) } {
            return true;
        }
    }
    false
}

/// The closest hit of each of `rays` (`tmin < t < tmax` in float32, under the tie rule of
/// [`Nearest`]), reported as `report(index, nearest, hit)` for the rays that hit, in no
/// particular order: the hits [`crate::simd::closest`] gives ray by ray.
///
/// # Safety
/// The CPU must have what [`crate::simd::available`] checks: AVX2 and its bit
/// instructions.
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
pub unsafe fn closest(
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    rays: &[TriangleRay],
    report: impl FnMut(usize, Nearest, TriangleHit),
) {
    assert!(
        bvh.stack_bound() <= STACK,
        "the scalar path handles deeper trees"
    );
    let nodes = bvh.nodes();
    if nodes.is_empty() {
        return;
    }
    let mut batch = ClosestBatch {
        rays,
        bounds: bvh.bounds(),
        report,
    };
    // SAFETY: AVX2 is enabled in this function.
    unsafe { run_in_turns(&mut batch, rays.len(), nodes, blocks) };
}

/// Whether each of `rays` hits some triangle with `tmin < t < tmax`, into `out` (`true`
/// is written, `false` left as it was): [`crate::simd::any`]'s answers. Each slot first
/// tests the block that stopped its previous ray, as [`crate::simd::any`] tests its
/// hint's.
///
/// # Safety
/// The CPU must have what [`crate::simd::available`] checks: AVX2 and its bit
/// instructions.
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
pub unsafe fn any(
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    rays: &[TriangleRay],
    out: &mut [bool],
) {
    assert!(
        bvh.stack_bound() <= STACK,
        "the scalar path handles deeper trees"
    );
    assert_eq!(rays.len(), out.len());
    let nodes = bvh.nodes();
    if nodes.is_empty() {
        return;
    }
    let mut batch = AnyBatch {
        rays,
        bounds: bvh.bounds(),
        blocks,
        hints: [None; IN_FLIGHT],
        out,
    };
    // SAFETY: AVX2 is enabled in this function.
    unsafe { run_in_turns(&mut batch, rays.len(), nodes, blocks) };
}

struct ClosestBatch<'a, F> {
    rays: &'a [TriangleRay],
    bounds: Bounds<f32>,
    report: F,
}

impl<F: FnMut(usize, Nearest, TriangleHit)> Batch for ClosestBatch<'_, F> {
    type Search = Closest;

    #[inline(always)]
    unsafe fn start(&mut self, slot: &mut MaybeUninit<Closest>, _: usize, index: usize) -> bool {
        // SAFETY: AVX2 is enabled in the caller.
        unsafe { Closest::start(slot, &self.rays[index], index, &self.bounds) }
    }

    #[inline(always)]
    fn finish(&mut self, search: &Closest) {
        if let Some(hit) = search.found {
            (self.report)(search.ray, search.nearest, hit);
        }
    }
}

struct AnyBatch<'a> {
    rays: &'a [TriangleRay],
    bounds: Bounds<f32>,
    blocks: &'a [TriangleBlock],
    /// The block that stopped the last search started in each slot, if it found one.
    hints: [Option<u32>; IN_FLIGHT],
    out: &'a mut [bool],
}

impl Batch for AnyBatch<'_> {
    type Search = Any;

    #[inline(always)]
    unsafe fn start(&mut self, slot: &mut MaybeUninit<Any>, i: usize, index: usize) -> bool {
        let ray = &self.rays[index];
        // SAFETY: AVX2 is enabled in the caller.
        match unsafe {
            Any::start(
                slot,
                i,
                ray,
                index,
                &self.bounds,
                self.blocks,
                self.hints[i],
            )
        } {
            Started::Search => true,
            Started::Hit(block) => {
                self.out[index] = true;
                self.hints[i] = Some(block);
                false
            }
            Started::Miss => false,
        }
    }

    #[inline(always)]
    fn finish(&mut self, search: &Any) {
        self.out[search.ray] |= search.found.is_some();
        self.hints[search.hint] = search.found;
    }
}

/// A closest-hit search: [`crate::simd::closest`]'s variables.
struct Closest {
    r: Lanes,
    nearest: Nearest,
    found: Option<TriangleHit>,
    t_box: __m256,
    t_tri: __m128,
    /// The node or leaf to visit next.
    current: u32,
    sp: usize,
    /// The ray's index in the caller's slice.
    ray: usize,
    stack: [MaybeUninit<u64>; STACK],
}

impl Closest {
    /// Sets up the search of `ray` in `slot`, unless it misses the tree's box.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    unsafe fn start(
        slot: &mut MaybeUninit<Closest>,
        ray: &TriangleRay,
        index: usize,
        bounds: &Bounds<f32>,
    ) -> bool {
        let nearest = Nearest::before(ray.tmax);
        // SAFETY (for every intrinsic and helper below): AVX2 is enabled in the caller;
        // `s` points to a `Closest` we own, whose fields (all but the stack, which is read
        // only below `sp`) are written once each before any is read.
        unsafe {
            if !enters(bounds, ray, inverse(ray.direction), nearest.horizon()) {
                return false;
            }
            let constants = ray_constants(ray.direction);
            let s = slot.as_mut_ptr();
            (&raw mut (*s).r).write(lanes(ray, &constants, triangle_lanes(ray, &constants)));
            (&raw mut (*s).nearest).write(nearest);
            (&raw mut (*s).found).write(None);
            (&raw mut (*s).t_box).write(_mm256_set1_ps(nearest.horizon()));
            (&raw mut (*s).t_tri).write(_mm_set1_ps(nearest.t.next_up()));
            (&raw mut (*s).current).write(0);
            (&raw mut (*s).sp).write(0);
            (&raw mut (*s).ray).write(index);
        }
        true
    }
}

impl Search for Closest {
    #[inline(always)]
    unsafe fn step(&mut self, nodes: &[Node<f32>], blocks: &[TriangleBlock]) -> bool {
        let s = self;
        let current = s.current;
        // SAFETY (for every intrinsic and helper below): AVX2 is enabled in the caller;
        // stack slots below `s.sp` are written before they are read.
        unsafe {
            if current & LEAF == 0 {
                let node = &nodes[current as usize];
                let (mask, enter) = node_test(node, &s.r, s.t_box);
                if mask != 0 {
                    let first = mask.trailing_zeros() as usize;
                    let rest = mask & (mask - 1);
                    let mut next = node.children[first];
                    if rest != 0 {
                        let second = rest.trailing_zeros() as usize;
                        let a = pack(lane8(enter, first), next);
                        let b = pack(lane8(enter, second), node.children[second]);
                        if rest & (rest - 1) == 0 {
                            // Two children: visit the nearer, push the farther.
                            let (near, far) = if a <= b { (a, b) } else { (b, a) };
                            s.stack[s.sp] = MaybeUninit::new(far);
                            s.sp += 1;
                            next = near as u32;
                        } else {
                            // More: a sorted run on the stack, the nearest taken back off.
                            let base = s.sp;
                            let mut m = mask;
                            while m != 0 {
                                let i = m.trailing_zeros() as usize;
                                m &= m - 1;
                                let entry = pack(lane8(enter, i), node.children[i]);
                                push_sorted(&mut s.stack, base, &mut s.sp, entry);
                            }
                            s.sp -= 1;
                            next = s.stack[s.sp].assume_init() as u32;
                        }
                    }
                    s.current = next;
                    prefetch_child(nodes, blocks, next);
                    return false;
                }
            } else {
                // The leaf's blocks two at a time, the last alone if their number is odd.
                let (first, count) = leaf_range(current);
                let end = first + count;
                let mut b = first;
                while b + 1 < end {
                    let limit = _mm256_set_m128(s.t_tri, s.t_tri);
                    let (mask, lanes) = block_pair_test(blocks, b as usize, &s.r.tri8, limit);
                    if mask != 0 && lanes.keep_nearest(mask, b, &mut s.nearest, &mut s.found) {
                        s.t_box = _mm256_set1_ps(s.nearest.horizon());
                        s.t_tri = _mm_set1_ps(s.nearest.t.next_up());
                    }
                    b += 2;
                }
                if b < end {
                    let (mask, lanes) = block_test(&blocks[b as usize], &s.r.tri, s.t_tri);
                    if mask != 0 && lanes.keep_nearest(mask, b, &mut s.nearest, &mut s.found) {
                        s.t_box = _mm256_set1_ps(s.nearest.horizon());
                        s.t_tri = _mm_set1_ps(s.nearest.t.next_up());
                    }
                }
            }
            // Pop the next entry that may still hold something as near.
            while s.sp > 0 {
                s.sp -= 1;
                let entry = s.stack[s.sp].assume_init();
                if distance(entry) <= s.nearest.horizon() {
                    s.current = entry as u32;
                    prefetch_child(nodes, blocks, s.current);
                    return false;
                }
            }
        }
        true
    }
}

/// An any-hit search: [`crate::simd::any`]'s variables for a search of the whole tree.
struct Any {
    r: Lanes,
    /// Boxes are entered up to the horizon past `tmax`, as in [`crate::simd::any`].
    t_far: __m256,
    tmax: f32,
    /// The block holding the triangle found.
    found: Option<u32>,
    current: u32,
    sp: usize,
    ray: usize,
    /// The slot it was started in: the hint it leaves is that slot's.
    hint: usize,
    stack: [MaybeUninit<u32>; STACK],
}

/// What setting up an any-hit search found.
enum Started {
    /// The search must run.
    Search,
    /// The ray hits a triangle of the hinted block, given.
    Hit(u32),
    /// The ray misses the tree's box.
    Miss,
}

impl Any {
    /// Sets up the search of `ray` in `slot` (slot number `i`), unless the ray hits a
    /// triangle of the `hint`ed block or misses the tree's box.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    unsafe fn start(
        slot: &mut MaybeUninit<Any>,
        i: usize,
        ray: &TriangleRay,
        index: usize,
        bounds: &Bounds<f32>,
        blocks: &[TriangleBlock],
        hint: Option<u32>,
    ) -> Started {
        let horizon = Nearest::before(ray.tmax).horizon();
        // SAFETY (for every intrinsic and helper below): AVX2 is enabled in the caller;
        // `s` points to an `Any` we own, whose fields (all but the stack, which is read
        // only below `sp`) are written once each before any is read.
        unsafe {
            let constants = ray_constants(ray.direction);
            let tri = triangle_lanes(ray, &constants);
            if let Some(b) = hint {
                let mask = block_test(&blocks[b as usize], &tri, _mm_set1_ps(ray.tmax)).0;
                if mask != 0 {
                    return Started::Hit(b);
                }
            }
            if !enters(bounds, ray, constants.inv, horizon) {
                return Started::Miss;
            }
            let s = slot.as_mut_ptr();
            (&raw mut (*s).r).write(lanes(ray, &constants, tri));
            (&raw mut (*s).t_far).write(_mm256_set1_ps(horizon));
            (&raw mut (*s).tmax).write(ray.tmax);
            (&raw mut (*s).found).write(None);
            (&raw mut (*s).current).write(0);
            (&raw mut (*s).sp).write(0);
            (&raw mut (*s).ray).write(index);
            (&raw mut (*s).hint).write(i);
        }
        Started::Search
    }
}

impl Search for Any {
    #[inline(always)]
    unsafe fn step(&mut self, nodes: &[Node<f32>], blocks: &[TriangleBlock]) -> bool {
        let s = self;
        let current = s.current;
        // SAFETY (for every intrinsic and helper below): AVX2 is enabled in the caller;
        // stack slots below `s.sp` are written before they are read.
        unsafe {
            if current & LEAF == 0 {
                let node = &nodes[current as usize];
                let (mut mask, _) = node_test(node, &s.r, s.t_far);
                if mask != 0 {
                    // Children in slot order, as `crate::simd::any` takes them.
                    let first = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    while mask != 0 {
                        s.stack[s.sp] =
                            MaybeUninit::new(node.children[mask.trailing_zeros() as usize]);
                        s.sp += 1;
                        mask &= mask - 1;
                    }
                    s.current = node.children[first];
                    prefetch_child(nodes, blocks, s.current);
                    return false;
                }
            } else {
                let (first, count) = leaf_range(current);
                let end = first + count;
                let mut b = first;
                while b + 1 < end {
                    let limit = _mm256_set1_ps(s.tmax);
                    let mask = block_pair_test(blocks, b as usize, &s.r.tri8, limit).0;
                    if mask != 0 {
                        // Lanes 4–7 are the second block's.
                        s.found = Some(b + mask.trailing_zeros() / BLOCK as u32);
                        return true;
                    }
                    b += 2;
                }
                if b < end && block_test(&blocks[b as usize], &s.r.tri, _mm_set1_ps(s.tmax)).0 != 0
                {
                    s.found = Some(b);
                    return true;
                }
            }
            if s.sp == 0 {
                return true;
            }
            s.sp -= 1;
            s.current = s.stack[s.sp].assume_init();
            prefetch_child(nodes, blocks, s.current);
        }
        false
    }
}
