//! Packets of coherent rays (the camera rays of an 8 × 8 tile) traced together through
//! the spheres' float64 tree with AVX2: [`crate::packet`]'s scheme in float64.
//!
//! Inner nodes are tested once per packet, with bounds on the packet's entry and exit
//! distances from the corners of its ranges of origin and reciprocal direction (computed
//! in float64, they bound every ray's own float64 values, rounding being monotonic). A
//! node is therefore skipped only if every ray's own robust test would skip it. A leaf's
//! box is then tested ray by ray, four rays per instruction, with exactly the single-ray
//! test, and the spheres of each entering ray with [`Sphere::intersect`]. Each ray gets the
//! hit its own traversal finds, except that of two spheres at the same `t` (to within
//! rounding) which one is reported may differ, as the visiting order does.

use std::arch::x86_64::*;
use std::mem::MaybeUninit;

use crate::bvh::{Bvh, LEAF, WIDTH, f32_at_least, f32_at_most, leaf_range};
use crate::packet::{
    Bound, GroupLanes, PACKET, Visits, corner_bound, leaf_entry, leaf_parent, pop_within,
};
use crate::ray::Ray;
use crate::simd::{STACK, pack, push_sorted, slab_test};
use crate::sphere::Sphere;

/// Groups of four rays (one float64 lane each).
const GROUPS: usize = PACKET / 4;

/// One ray per lane, four rays per group.
#[repr(C, align(32))]
struct Groups([[f64; 4]; GROUPS]);

impl Groups {
    const ZERO: Groups = Groups([[0.0; 4]; GROUPS]);

    /// Group `g`'s four lanes.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    unsafe fn load(&self, g: usize) -> __m256d {
        // SAFETY: groups are 32-byte aligned arrays of four doubles.
        unsafe { _mm256_load_pd(self.0[g].as_ptr()) }
    }
}

/// A packet's per-ray values that stay fixed while it is traced, four lanes per group:
/// origin, reciprocal direction (near and far planes), `tmin`.
#[repr(C)]
struct RayLanes {
    origin: [Groups; 3],
    inv: [Groups; 3],
    inv_far: [Groups; 3],
    tmin: Groups,
}

/// A float64 at `p` in all four lanes.
///
/// # Safety
/// `p` must be valid to read; only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn broadcast_pd(p: *const f64) -> __m256d {
    // SAFETY: as required of the caller.
    unsafe { _mm256_broadcast_sd(&*p) }
}

/// Closest sphere hits of up to [`PACKET`] rays traced together, ray `k` looking for
/// `rays[k].tmin < t < tmax[k]`: `found(k, t, position)` is called for each ray with a
/// hit, `position` indexing `spheres` (the tree's leaf order). Returns what the traversal
/// visited, or `None`, calling nothing, when the rays' directions differ in sign on some
/// axis.
///
/// # Safety
/// The CPU must support AVX2, and `bvh.stack_bound() <= STACK`.
#[target_feature(enable = "avx2")]
pub unsafe fn closest(
    bvh: &Bvh<f64>,
    spheres: &[Sphere],
    rays: &[Ray],
    tmax: &[f64],
    found: impl FnMut(usize, f64, u32),
) -> Option<Visits> {
    // SAFETY: as required of the caller.
    unsafe { trace::<false>(bvh, spheres, rays, tmax, found) }
}

/// Whether each of up to [`PACKET`] rays hits a sphere with `rays[k].tmin < t < tmax[k]`,
/// traced together: `found(k, t, position)` is called for each ray that does, with some
/// hit (not necessarily the nearest); rays leave the packet at their first hit. Returns
/// what the traversal visited, or `None`, calling nothing, when the rays' directions
/// differ in sign on some axis.
///
/// # Safety
/// As for [`closest`].
#[target_feature(enable = "avx2")]
pub unsafe fn any(
    bvh: &Bvh<f64>,
    spheres: &[Sphere],
    rays: &[Ray],
    tmax: &[f64],
    found: impl FnMut(usize, f64, u32),
) -> Option<Visits> {
    // SAFETY: as required of the caller.
    unsafe { trace::<true>(bvh, spheres, rays, tmax, found) }
}

/// The packet traversal: closest hits, or with `ANY` first hits.
#[target_feature(enable = "avx2")]
unsafe fn trace<const ANY: bool>(
    bvh: &Bvh<f64>,
    spheres: &[Sphere],
    rays: &[Ray],
    tmax: &[f64],
    mut found: impl FnMut(usize, f64, u32),
) -> Option<Visits> {
    assert!(rays.len() <= PACKET && tmax.len() == rays.len());
    assert!(
        bvh.stack_bound() <= STACK,
        "the single-ray path handles deeper trees"
    );
    let n = rays.len();
    let mut visits = Visits::default();
    if n == 0 {
        return Some(visits);
    }
    // Per-ray values, four lanes per group; lanes past `n` repeat the last ray but never
    // enter a box (their horizon is −∞). Made four rays at a time: `BoxRay::new`'s
    // arithmetic (one division per axis, IEEE-exact in every lane as in scalar code).
    // Every group is written below, the repeated lanes too, so nothing is zeroed first.
    let mut fixed = MaybeUninit::<RayLanes>::uninit();
    let lanes_of = fixed.as_mut_ptr();
    // Each ray's horizon: `tmax`, then its nearest hit so far.
    let mut horizon = Groups::ZERO;
    let mut nearest = [u32::MAX; PACKET];
    // The packet's ranges per axis over its rays (the repeated lanes change none):
    // origin, reciprocal direction (near and far planes); smallest tmin.
    let (mut lo, mut hi) = (
        [[_mm256_set1_pd(f64::INFINITY); 3]; 3],
        [[_mm256_set1_pd(f64::NEG_INFINITY); 3]; 3],
    );
    let mut tmin_lo = _mm256_set1_pd(f64::INFINITY);
    // Per axis, the direction signs seen in every lane: all rays must share them.
    let (mut signs_any, mut signs_all) = ([0i32; 3], [0xf_i32; 3]);
    let exit_scale = _mm256_set1_pd(<f64 as crate::bvh::Scalar>::EXIT_SCALE);
    for g in 0..GROUPS {
        let four = [0, 1, 2, 3].map(|l| &rays[(4 * g + l).min(n - 1)]);
        let lanes =
            |x: fn(&Ray) -> f64| _mm256_setr_pd(x(four[0]), x(four[1]), x(four[2]), x(four[3]));
        let o = [
            lanes(|r| r.origin.x),
            lanes(|r| r.origin.y),
            lanes(|r| r.origin.z),
        ];
        let d = [
            lanes(|r| r.direction.x),
            lanes(|r| r.direction.y),
            lanes(|r| r.direction.z),
        ];
        let t = lanes(|r| r.tmin);
        for a in 0..3 {
            let i = _mm256_div_pd(_mm256_set1_pd(1.0), d[a]);
            let f = _mm256_mul_pd(i, exit_scale);
            // SAFETY: in bounds of `fixed`; groups are 32-byte aligned arrays of four
            // doubles; no reference to the uninitialized memory is made.
            unsafe {
                _mm256_store_pd((&raw mut (*lanes_of).origin[a].0[g]).cast(), o[a]);
                _mm256_store_pd((&raw mut (*lanes_of).inv[a].0[g]).cast(), i);
                _mm256_store_pd((&raw mut (*lanes_of).inv_far[a].0[g]).cast(), f);
            }
            let signs = _mm256_movemask_pd(d[a]);
            signs_any[a] |= signs;
            signs_all[a] &= signs;
            // `f64::min` and `max` keep the running value over a NaN, as these do with
            // the new values first.
            for (k, x) in [o[a], i, f].into_iter().enumerate() {
                lo[k][a] = _mm256_min_pd(x, lo[k][a]);
                hi[k][a] = _mm256_max_pd(x, hi[k][a]);
            }
        }
        tmin_lo = _mm256_min_pd(t, tmin_lo);
        // SAFETY: as above.
        unsafe { _mm256_store_pd((&raw mut (*lanes_of).tmin.0[g]).cast(), t) };
    }
    // SAFETY: every field's every group was written in the loop.
    let fixed = unsafe { fixed.assume_init_ref() };
    let RayLanes {
        origin,
        inv,
        inv_far,
        tmin,
    } = fixed;
    if (0..3).any(|a| signs_any[a] != signs_all[a]) {
        return None;
    }
    let octant = signs_all.map(|s| (s & 1) as usize);
    let reduce = |v: __m256d, f: fn(f64, f64) -> f64| {
        let mut x = [0f64; 4];
        // SAFETY: `x` holds four doubles.
        unsafe { _mm256_storeu_pd(x.as_mut_ptr(), v) };
        f(f(x[0], x[1]), f(x[2], x[3]))
    };
    // Per quantity (origin, reciprocal, far reciprocal), per axis: (smallest, largest).
    let [o_range, i_range, f_range] = [0, 1, 2]
        .map(|k| [0, 1, 2].map(|a| (reduce(lo[k][a], f64::min), reduce(hi[k][a], f64::max))));
    let tmin_lo = reduce(tmin_lo, f64::min);
    let mut packet_tmax = f64::NEG_INFINITY;
    // Rays that may still find a hit (for `ANY`).
    let mut live = 0;
    for k in 0..PACKET {
        horizon.0[k / 4][k % 4] = if k < n { tmax[k] } else { f64::NEG_INFINITY };
        if k < n {
            packet_tmax = packet_tmax.max(tmax[k]);
            live += usize::from(tmax[k] > rays[k].tmin);
        }
    }
    let nodes = bvh.nodes();
    if nodes.is_empty() || live == 0 {
        return Some(visits);
    }
    let offset = |side: usize, axis: usize| (side * 3 + axis) * WIDTH;
    let near: [usize; 3] = [0, 1, 2].map(|a| offset(octant[a], a));
    let far: [usize; 3] = [0, 1, 2].map(|a| offset(1 - octant[a], a));

    let mut stack = [const { MaybeUninit::<u64>::uninit() }; STACK];
    let mut sp = 0usize;
    let mut current = 0u32;
    loop {
        if current & LEAF == 0 {
            let node = &nodes[current as usize];
            let planes = node.planes.as_ptr().cast::<f64>();
            let mut entries = [0f64; WIDTH];
            let mut mask = 0u32;
            for half in [0, 4] {
                // SAFETY: plane offsets are below 6 × 8 doubles of a 64-byte aligned node,
                // so each group of four is 32-byte aligned.
                let load = |offset: usize| unsafe { _mm256_load_pd(planes.add(offset + half)) };
                let bound = |plane, o, i, bound| {
                    corner_bound!(
                        plane,
                        o,
                        i,
                        bound,
                        _mm256_set1_pd,
                        _mm256_sub_pd,
                        _mm256_mul_pd,
                        _mm256_min_pd,
                        _mm256_max_pd,
                        _mm256_cmp_pd,
                        _mm256_or_pd,
                        _mm256_blendv_pd
                    )
                };
                let mut enter = _mm256_set1_pd(tmin_lo);
                let mut exit = _mm256_set1_pd(packet_tmax);
                for a in 0..3 {
                    let lower = bound(load(near[a]), o_range[a], i_range[a], Bound::Lower);
                    let upper = bound(load(far[a]), o_range[a], f_range[a], Bound::Upper);
                    enter = _mm256_max_pd(lower, enter);
                    exit = _mm256_min_pd(upper, exit);
                }
                let hit = _mm256_cmp_pd::<_CMP_LE_OQ>(enter, exit);
                mask |= (_mm256_movemask_pd(hit) as u32) << half;
                // SAFETY: `entries` holds eight doubles.
                unsafe { _mm256_storeu_pd(entries.as_mut_ptr().add(half), enter) };
            }
            // Every entered child onto the stack, farthest first; leaves as their parent
            // and slot, so that their box can be read when they are reached.
            let base = sp;
            let mut m = mask;
            while m != 0 {
                let i = m.trailing_zeros() as usize;
                m &= m - 1;
                let child = node.children[i];
                let reference = if child & LEAF == 0 {
                    child
                } else {
                    leaf_entry(current, i)
                };
                // Rounded down, so the stack's order and the pop test stay conservative.
                let key = pack(f32_at_most(entries[i]), reference);
                push_sorted(&mut stack, base, &mut sp, key);
            }
        } else {
            // A leaf: its box against every ray, then each entering ray's spheres.
            let (parent, slot) = leaf_parent(current);
            let node = &nodes[parent];
            let planes = node.planes.as_ptr().cast::<f64>();
            let (first, count) = leaf_range(node.children[slot]);
            let mut improved = false;
            visits.leaves += 1;
            for g in 0..GROUPS {
                // SAFETY: AVX2 is enabled in this function.
                let lane = |groups: &Groups| unsafe { groups.load(g) };
                let group = GroupLanes::read([origin, inv, inv_far], (near, far), lane);
                // The single-ray test, the leaf's box against four rays.
                // SAFETY: plane offsets plus the slot stay within the node's 6 × 8 doubles.
                let (_, entered) = unsafe {
                    slab_test! { &group, planes, slot, lane(tmin), lane(&horizon),
                    broadcast_pd, _mm256_sub_pd, _mm256_mul_pd, _mm256_max_pd, _mm256_min_pd,
                    _mm256_cmp_pd }
                };
                let mut hits = _mm256_movemask_pd(entered) as u32;
                visits.entries += hits.count_ones();
                while hits != 0 {
                    let l = hits.trailing_zeros() as usize;
                    hits &= hits - 1;
                    let k = g * 4 + l;
                    for i in first..first + count {
                        let best = &mut horizon.0[g][l];
                        if let Some(t) = spheres[i as usize].intersect(&rays[k], *best) {
                            nearest[k] = i;
                            improved = true;
                            if ANY {
                                // Reported now: the ray leaves the packet.
                                found(k, t, i);
                                *best = f64::NEG_INFINITY;
                                live -= 1;
                                break;
                            }
                            *best = t;
                        }
                    }
                }
            }
            if improved {
                // SAFETY: AVX2 is enabled in this function.
                let mut widest = unsafe { horizon.load(0) };
                for g in 1..GROUPS {
                    // SAFETY: as above.
                    widest = _mm256_max_pd(widest, unsafe { horizon.load(g) });
                }
                let mut lanes = [0f64; 4];
                // SAFETY: `lanes` holds four doubles.
                unsafe { _mm256_storeu_pd(lanes.as_mut_ptr(), widest) };
                packet_tmax = lanes.into_iter().fold(f64::NEG_INFINITY, f64::max);
            }
        }
        // The next entry that some ray may still need: rounded up, the horizon keeps
        // every entry a ray may need (rounded down when pushed).
        // SAFETY: every slot below `sp` was written above.
        let next = if ANY && live == 0 {
            None
        } else {
            unsafe { pop_within(&stack, &mut sp, f32_at_least(packet_tmax)) }
        };
        let Some(next) = next else {
            if !ANY {
                for (k, &i) in nearest[..n].iter().enumerate() {
                    if i != u32::MAX {
                        found(k, horizon.0[k / 4][k % 4], i);
                    }
                }
            }
            return Some(visits);
        };
        current = next;
    }
}
