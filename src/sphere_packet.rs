//! Packets of coherent rays (the camera rays of an 8 × 8 tile) traced together through
//! the spheres' float64 tree with AVX2: [`crate::packet`]'s scheme in float64.
//!
//! Inner nodes are tested once per packet, with bounds on the packet's entry and exit
//! distances from the corners of its ranges of origin and reciprocal direction (computed
//! in float64, they bound every ray's own float64 values, rounding being monotonic). A
//! node is therefore skipped only if every ray's own robust test would skip it. Rays from
//! different origins (through a thin lens) are bounded from where they come closest
//! together instead, with both ends of the node test widened by what each ray's own test
//! rounds (`Ranges::shift_to_waist`, `Ranges::enters`). A leaf's box is then tested ray
//! by ray, four rays per instruction, with exactly the single-ray test, and its spheres
//! against the entering rays four at a time, with the operations of [`Sphere::intersect`]
//! lane by lane (so the same bits). Each ray gets the hit its own traversal finds, except
//! that of two spheres at the same `t` (to within rounding) which one is reported may
//! differ, as the visiting order does.

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
/// origin, reciprocal direction (near and far planes), `tmin`; and for the spheres' test,
/// direction and its squared length.
#[repr(C)]
struct RayLanes {
    origin: [Groups; 3],
    inv: [Groups; 3],
    inv_far: [Groups; 3],
    tmin: Groups,
    direction: [Groups; 3],
    length2: Groups,
}

/// [`Sphere::intersect`] of four rays at once, one per lane: whether each hits `sphere`
/// with `tmin < t < tmax`, as an all-ones lane, and that `t`. The same operations in the
/// same order as the scalar test (which has no fused operations), so the same bits;
/// `length2` is `direction · direction`, which the scalar test computes per call.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn sphere_hits(
    sphere: &Sphere,
    origin: &[__m256d; 3],
    direction: &[__m256d; 3],
    length2: __m256d,
    tmin: __m256d,
    tmax: __m256d,
) -> (__m256d, __m256d) {
    // Written out rather than in closures: closures here would not inherit AVX2.
    macro_rules! dot {
        ($u:expr, $v:expr) => {
            _mm256_add_pd(
                _mm256_add_pd(_mm256_mul_pd($u[0], $v[0]), _mm256_mul_pd($u[1], $v[1])),
                _mm256_mul_pd($u[2], $v[2]),
            )
        };
    }
    macro_rules! between {
        ($t:expr) => {
            _mm256_and_pd(
                _mm256_cmp_pd::<_CMP_GT_OQ>($t, tmin),
                _mm256_cmp_pd::<_CMP_LT_OQ>($t, tmax),
            )
        };
    }
    let centre = sphere.center;
    let r2 = sphere.radius * sphere.radius;
    // SAFETY: AVX2 is enabled in the caller.
    unsafe {
        let f = [
            _mm256_sub_pd(origin[0], _mm256_set1_pd(centre.x)),
            _mm256_sub_pd(origin[1], _mm256_set1_pd(centre.y)),
            _mm256_sub_pd(origin[2], _mm256_set1_pd(centre.z)),
        ];
        let b = dot!(f, direction);
        let along = _mm256_div_pd(b, length2);
        let l = [
            _mm256_sub_pd(f[0], _mm256_mul_pd(along, direction[0])),
            _mm256_sub_pd(f[1], _mm256_mul_pd(along, direction[1])),
            _mm256_sub_pd(f[2], _mm256_mul_pd(along, direction[2])),
        ];
        let r2 = _mm256_set1_pd(r2);
        let discriminant = _mm256_sub_pd(r2, dot!(l, l));
        // The scalar test goes on unless `discriminant <= 0`: greater, or NaN.
        let crosses = _mm256_cmp_pd::<_CMP_NLE_UQ>(discriminant, _mm256_setzero_pd());
        // Most tests miss: as the scalar test does, stop before the square root and the
        // divisions.
        if _mm256_movemask_pd(crosses) == 0 {
            return (crosses, crosses);
        }
        let c = _mm256_sub_pd(dot!(f, f), r2);
        let sign = _mm256_set1_pd(-0.0);
        let root = _mm256_sqrt_pd(_mm256_mul_pd(length2, discriminant));
        // `−b − root.copysign(b)`: negation and copysign act on the sign bit alone.
        let signed = _mm256_or_pd(_mm256_andnot_pd(sign, root), _mm256_and_pd(sign, b));
        let q = _mm256_sub_pd(_mm256_xor_pd(b, sign), signed);
        let (t0, t1) = (_mm256_div_pd(c, q), _mm256_div_pd(q, length2));
        let ordered = _mm256_cmp_pd::<_CMP_LE_OQ>(t0, t1);
        let near = _mm256_blendv_pd(t1, t0, ordered);
        let far = _mm256_blendv_pd(t0, t1, ordered);
        let (near_inside, far_inside) = (between!(near), between!(far));
        let t = _mm256_blendv_pd(far, near, near_inside);
        (
            _mm256_and_pd(crosses, _mm256_or_pd(near_inside, far_inside)),
            t,
        )
    }
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

/// How much a packet bounded from its waist widens each end of its node test, per unit
/// of distance: 64u, u = 2⁻⁵³ (see [`Ranges::enters`]).
const SHIFTED_SLACK: f64 = 32.0 * f64::EPSILON;

/// A packet's ranges over its rays, per axis `(smallest, largest)`, which its node test
/// reads: each ray's point at distance `shift` (its origin when `shift` is 0), reciprocal
/// direction for near planes and for far ones; the smallest `tmin`, less `shift`.
struct Ranges {
    /// Offsets of each axis's near and far planes in a node, by the octant all the rays'
    /// directions share.
    near: [usize; 3],
    far: [usize; 3],
    origin: [(f64, f64); 3],
    inv: [(f64, f64); 3],
    inv_far: [(f64, f64); 3],
    /// The smallest `tmin`, less `shift` (rounded down).
    tmin: f64,
    /// Where the rays come closest together, when their origins differ (a lens): the node
    /// test bounds distances from there, `t − shift`. Zero otherwise.
    shift: f64,
}

/// Writes each ray's fixed values into `fixed`, four rays per group (lanes past the rays
/// repeat the last one), and returns the packet's ranges; or `None` when the rays'
/// directions differ in sign on some axis, a ray's origin or direction is not finite, or
/// its `tmin` is NaN (such packets are left to the single-ray path: the ranges would skip
/// or widen past those values, and the corner bounds then admit every slot, empty ones
/// too). Every group of `fixed` is written, also when it returns `None`.
///
/// `rays` must not be empty.
#[target_feature(enable = "avx2")]
fn set_up(rays: &[Ray], fixed: &mut MaybeUninit<RayLanes>) -> Option<Ranges> {
    let n = rays.len();
    let lanes_of = fixed.as_mut_ptr();
    // The packet's ranges per axis over its rays (the repeated lanes change none):
    // origin, reciprocal direction (near and far planes); smallest tmin.
    let (mut lo, mut hi) = (
        [[_mm256_set1_pd(f64::INFINITY); 3]; 3],
        [[_mm256_set1_pd(f64::NEG_INFINITY); 3]; 3],
    );
    let mut tmin_lo = _mm256_set1_pd(f64::INFINITY);
    // Per axis, the direction signs seen in every lane: all rays must share them.
    let (mut signs_any, mut signs_all) = ([0i32; 3], [0xf_i32; 3]);
    let mut bad = _mm256_setzero_pd();
    let exit_scale = _mm256_set1_pd(<f64 as crate::bvh::Scalar>::EXIT_SCALE);
    for g in 0..GROUPS {
        // Made four rays at a time: `BoxRay::new`'s arithmetic (one division per axis,
        // IEEE-exact in every lane as in scalar code).
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
        // The sum of a lane's six components is finite only if they all are (it may also
        // overflow, which only sends the packet ray by ray); `x − x` is NaN exactly where
        // `x` is not finite.
        let sum = _mm256_add_pd(
            _mm256_add_pd(_mm256_add_pd(o[0], o[1]), _mm256_add_pd(o[2], d[0])),
            _mm256_add_pd(d[1], d[2]),
        );
        let zero = _mm256_sub_pd(sum, sum);
        bad = _mm256_or_pd(bad, _mm256_cmp_pd::<_CMP_UNORD_Q>(zero, t));
        let mut length2 = _mm256_setzero_pd();
        for a in 0..3 {
            let i = _mm256_div_pd(_mm256_set1_pd(1.0), d[a]);
            let f = _mm256_mul_pd(i, exit_scale);
            // SAFETY: in bounds of `fixed`; groups are 32-byte aligned arrays of four
            // doubles; no reference to the uninitialized memory is made.
            unsafe {
                _mm256_store_pd((&raw mut (*lanes_of).origin[a].0[g]).cast(), o[a]);
                _mm256_store_pd((&raw mut (*lanes_of).inv[a].0[g]).cast(), i);
                _mm256_store_pd((&raw mut (*lanes_of).inv_far[a].0[g]).cast(), f);
                _mm256_store_pd((&raw mut (*lanes_of).direction[a].0[g]).cast(), d[a]);
            }
            // `direction · direction` in the scalar sum's order: x² + y², then + z².
            let square = _mm256_mul_pd(d[a], d[a]);
            length2 = if a == 0 {
                square
            } else {
                _mm256_add_pd(length2, square)
            };
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
        unsafe {
            _mm256_store_pd((&raw mut (*lanes_of).tmin.0[g]).cast(), t);
            _mm256_store_pd((&raw mut (*lanes_of).length2.0[g]).cast(), length2);
        }
    }
    if (0..3).any(|a| signs_any[a] != signs_all[a]) || _mm256_movemask_pd(bad) != 0 {
        return None;
    }
    let octant = signs_all.map(|s| (s & 1) as usize);
    let offset = |side: usize, axis: usize| (side * 3 + axis) * WIDTH;
    // Per quantity (origin, reciprocal, far reciprocal), per axis: (smallest, largest).
    // SAFETY: AVX2 is enabled in the caller.
    let [origin, inv, inv_far] = [0, 1, 2].map(|k| {
        [0, 1, 2].map(|a| unsafe { (reduce(lo[k][a], f64::min), reduce(hi[k][a], f64::max)) })
    });
    let mut ranges = Ranges {
        near: [0, 1, 2].map(|a| offset(octant[a], a)),
        far: [0, 1, 2].map(|a| offset(1 - octant[a], a)),
        origin,
        inv,
        inv_far,
        // SAFETY: as above.
        tmin: unsafe { reduce(tmin_lo, f64::min) },
        shift: 0.0,
    };
    if origin.iter().any(|&(lo, hi)| lo != hi) {
        // SAFETY: every field's every group was written above.
        ranges.shift_to_waist(unsafe { fixed.assume_init_ref() });
    }
    Some(ranges)
}

/// `f` over the four lanes of `v`.
///
/// # Safety
/// Only from a function with AVX enabled.
#[inline(always)]
unsafe fn reduce(v: __m256d, f: fn(f64, f64) -> f64) -> f64 {
    let mut x = [0f64; 4];
    // SAFETY: `x` holds four doubles; AVX is enabled in the caller.
    unsafe { _mm256_storeu_pd(x.as_mut_ptr(), v) };
    f(f(x[0], x[1]), f(x[2], x[3]))
}

impl Ranges {
    /// Moves the packet's reference points from the rays' origins to where the rays come
    /// closest together (their waist: the focus plane, for a lens's rays), as
    /// [`crate::packet`] does for triangles: from the origins spread over a lens, the node
    /// test's bounds are several times wider than the rays' own spread near what they
    /// meet. The distance `s` minimizes the rays' spread (least squares; any `s` would be
    /// correct). Each ray's point `o + s·d` is computed within 2.01u(|o| + |s·d|)
    /// (u = 2⁻⁵³: one rounding of the product, one of the sum), so the ranges widened by
    /// 8u times the largest such size per axis, plus the smallest normal float for
    /// products that underflow, hold the exact points. Left unshifted where the rays
    /// spread from the start or a value overflows.
    #[target_feature(enable = "avx2")]
    fn shift_to_waist(&mut self, fixed: &RayLanes) {
        // SAFETY (all blocks): AVX2 is enabled here; groups are aligned.
        let zero = _mm256_setzero_pd();
        // Sums of differences from the first ray, which do not cancel.
        let first = |lanes: &[Groups; 3], a: usize| _mm256_set1_pd(lanes[a].0[0][0]);
        let (mut covariance, mut variance) = (0.0, 0.0);
        for a in 0..3 {
            let (o0, d0) = (first(&fixed.origin, a), first(&fixed.direction, a));
            let (mut sum_o, mut sum_d, mut sum_od, mut sum_dd) = (zero, zero, zero, zero);
            for g in 0..GROUPS {
                let (o, d) = unsafe { (fixed.origin[a].load(g), fixed.direction[a].load(g)) };
                let (o, d) = (_mm256_sub_pd(o, o0), _mm256_sub_pd(d, d0));
                sum_o = _mm256_add_pd(sum_o, o);
                sum_d = _mm256_add_pd(sum_d, d);
                sum_od = _mm256_add_pd(sum_od, _mm256_mul_pd(o, d));
                sum_dd = _mm256_add_pd(sum_dd, _mm256_mul_pd(d, d));
            }
            let sum = |v| unsafe { reduce(v, |x, y| x + y) };
            let (sum_o, sum_d) = (sum(sum_o), sum(sum_d));
            // Times the count: the covariance of origin and direction, the variance of
            // direction.
            covariance += sum(sum_od) - sum_o * sum_d / PACKET as f64;
            variance += sum(sum_dd) - sum_d * sum_d / PACKET as f64;
        }
        let s = -covariance / variance;
        // Only ahead of the origins: rays that spread from the start gain nothing.
        if !(s > 0.0 && s.is_finite()) {
            return;
        }
        let distance = _mm256_set1_pd(s);
        let sign = _mm256_set1_pd(-0.0);
        let mut shifted = self.origin;
        for (a, range) in shifted.iter_mut().enumerate() {
            let (mut lo, mut hi, mut size) = (
                _mm256_set1_pd(f64::INFINITY),
                _mm256_set1_pd(f64::NEG_INFINITY),
                zero,
            );
            for g in 0..GROUPS {
                let (o, d) = unsafe { (fixed.origin[a].load(g), fixed.direction[a].load(g)) };
                let along = _mm256_mul_pd(distance, d);
                let point = _mm256_add_pd(o, along);
                (lo, hi) = (_mm256_min_pd(lo, point), _mm256_max_pd(hi, point));
                let magnitude =
                    _mm256_add_pd(_mm256_andnot_pd(sign, o), _mm256_andnot_pd(sign, along));
                size = _mm256_max_pd(size, magnitude);
            }
            let (lo, hi, size) = unsafe {
                (
                    reduce(lo, f64::min),
                    reduce(hi, f64::max),
                    reduce(size, f64::max),
                )
            };
            let widen = 4.0 * f64::EPSILON * size + f64::MIN_POSITIVE;
            *range = (lo - widen, hi + widen);
            if !(range.0.is_finite() && range.1.is_finite()) {
                return;
            }
        }
        self.origin = shifted;
        self.tmin = (self.tmin - s).next_down();
        self.shift = s;
    }

    /// The node test's `tmax` for rays that search up to `horizon`: `horizon − shift`,
    /// rounded up.
    #[inline(always)]
    fn node_tmax(&self, horizon: f64) -> f64 {
        if self.shift == 0.0 {
            horizon
        } else {
            (horizon - self.shift).next_up()
        }
    }

    /// Which of the four boxes in slots `half..half + 4` of a node's `planes` some ray of
    /// the packet may enter with `tmin <= t <= tmax` (a lane mask), and the packet's
    /// lower bound on each entry distance from the rays' origins. `tmax` is
    /// [`Ranges::node_tmax`]'s. The corner bounds hold every ray's own float64 values
    /// (rounding is monotonic), so a box is skipped only if every ray's own robust test
    /// would skip it.
    ///
    /// # Safety
    /// `planes` must be a node's planes and `half` 0 or 4; only from a function with AVX2
    /// enabled.
    #[inline(always)]
    unsafe fn enters(&self, planes: *const f64, half: usize, tmax: f64) -> (u32, __m256d) {
        // SAFETY: AVX2 is enabled in the caller; plane offsets are below 6 × 8 doubles of a
        // 64-byte aligned node, so each group of four is 32-byte aligned.
        unsafe {
            let mut enter = _mm256_set1_pd(self.tmin);
            let mut exit = _mm256_set1_pd(tmax);
            for a in 0..3 {
                let (near, far) = (
                    _mm256_load_pd(planes.add(self.near[a] + half)),
                    _mm256_load_pd(planes.add(self.far[a] + half)),
                );
                macro_rules! bound {
                    ($plane:expr, $i:expr, $bound:expr) => {
                        corner_bound!(
                            $plane,
                            self.origin[a],
                            $i,
                            $bound,
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
                }
                enter = _mm256_max_pd(bound!(near, self.inv[a], Bound::Lower), enter);
                exit = _mm256_min_pd(bound!(far, self.inv_far[a], Bound::Upper), exit);
            }
            if self.shift == 0.0 {
                let mask = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(enter, exit)) as u32;
                return (mask, enter);
            }
            // The packet must admit every box a ray's own test admits, and that test rounds
            // in proportion to distances from the ray's origin, `|t| <= |t'| + shift`:
            // entries low by up to 2u|t| (u = 2⁻⁵³), exits high by up to 19u|t| (`EXIT_SCALE`
            // and rounding). From the waist, `t'` is within 2u|t'|, an exit behind the waist
            // up to 18u|t'| low (its scaled reciprocal narrows a negative `t'`), and the rays'
            // rounded reciprocals move `t'` by up to u·shift. Widening both ends by
            // 64u(|t'| + shift) covers each case, behind the origins too. The entry is then
            // returned as a distance from the origins, `t' + shift`, rounded down by 64u of
            // it.
            let sign = _mm256_set1_pd(-0.0);
            macro_rules! slack {
                ($x:expr, $from_origins:expr) => {
                    _mm256_mul_pd(
                        _mm256_add_pd(_mm256_andnot_pd(sign, $x), _mm256_set1_pd($from_origins)),
                        _mm256_set1_pd(SHIFTED_SLACK),
                    )
                };
            }
            enter = _mm256_sub_pd(enter, slack!(enter, self.shift));
            exit = _mm256_add_pd(exit, slack!(exit, self.shift));
            let mask = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(enter, exit)) as u32;
            let from_origin = _mm256_add_pd(enter, _mm256_set1_pd(self.shift));
            (mask, _mm256_sub_pd(from_origin, slack!(from_origin, 0.0)))
        }
    }
}

/// Closest sphere hits of up to [`PACKET`] rays traced together, ray `k` looking for
/// `rays[k].tmin < t < tmax[k]`: `found(k, t, position)` is called for each ray with a
/// hit, `position` indexing `spheres` (the tree's leaf order). Returns what the traversal
/// visited, or `None`, calling nothing, when the rays' directions differ in sign on some
/// axis, a ray's origin or direction is not finite, or its `tmin` is NaN. A packet that
/// [gave up](Visits::hopeless) has called nothing either.
///
/// # Safety
/// The CPU must have what [`crate::simd::available`] checks, and
/// `bvh.stack_bound() <= STACK`.
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
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
/// what the traversal visited, or `None`, calling nothing, as for [`closest`]. A packet
/// that gave up may have reported some rays: their hits hold, and the others are unknown.
///
/// # Safety
/// As for [`closest`].
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
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
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
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
    let mut fixed = MaybeUninit::<RayLanes>::uninit();
    let ranges = set_up(rays, &mut fixed)?;
    // SAFETY: `set_up` wrote every field's every group.
    let fixed = unsafe { fixed.assume_init_ref() };
    let RayLanes {
        origin,
        inv,
        inv_far,
        tmin,
        direction,
        length2,
    } = fixed;
    let (near, far) = (ranges.near, ranges.far);
    // Each ray's horizon: `tmax`, then its nearest hit so far; lanes past `n` never enter
    // a box (their horizon is −∞).
    let mut horizon = Groups::ZERO;
    let mut nearest = [u32::MAX; PACKET];
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
    let mut node_tmax = ranges.node_tmax(packet_tmax);

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
                // SAFETY: AVX2 is enabled in this function; `planes` is a node's.
                let (hit, enter) = unsafe { ranges.enters(planes, half, node_tmax) };
                mask |= hit << half;
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
            let entries_before = visits.entries;
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
                let entering = _mm256_movemask_pd(entered) as u32;
                visits.entries += entering.count_ones();
                if entering == 0 {
                    continue;
                }
                // Then the leaf's spheres in order against the entering rays, four at a
                // time, each ray's horizon following its hits as the scalar loop's would.
                let o = [0, 1, 2].map(|a| lane(&origin[a]));
                let d = [0, 1, 2].map(|a| lane(&direction[a]));
                let (length2, ray_tmin) = (lane(length2), lane(tmin));
                let mut best = lane(&horizon);
                for i in first..first + count {
                    // SAFETY: AVX2 is enabled in this function.
                    let (hit, t) = unsafe {
                        sphere_hits(&spheres[i as usize], &o, &d, length2, ray_tmin, best)
                    };
                    let hit = _mm256_and_pd(hit, entered);
                    let mut hits = _mm256_movemask_pd(hit) as u32;
                    if hits == 0 {
                        continue;
                    }
                    improved = true;
                    // A ray that found a hit with `ANY` is reported now and leaves the
                    // packet: its horizon, −∞, admits nothing more.
                    let next = if ANY {
                        _mm256_set1_pd(f64::NEG_INFINITY)
                    } else {
                        t
                    };
                    best = _mm256_blendv_pd(best, next, hit);
                    // With `ANY` the hits are reported now, else remembered for the end.
                    let mut ts = [0f64; 4];
                    if ANY {
                        // SAFETY: `ts` holds four doubles.
                        unsafe { _mm256_storeu_pd(ts.as_mut_ptr(), t) };
                    }
                    while hits != 0 {
                        let l = hits.trailing_zeros() as usize;
                        hits &= hits - 1;
                        let k = g * 4 + l;
                        if ANY {
                            found(k, ts[l], i);
                            live -= 1;
                        } else {
                            nearest[k] = i;
                        }
                    }
                }
                // SAFETY: group `g` is 32-byte aligned and four doubles.
                unsafe { _mm256_store_pd(horizon.0[g].as_mut_ptr(), best) };
            }
            visits.entered += u32::from(visits.entries > entries_before);
            if visits.hopeless() {
                // No closest hit is reported (any hits found so far have been: they hold).
                return Some(visits);
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
                node_tmax = ranges.node_tmax(packet_tmax);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::Node;
    use crate::test_random::XorShift;
    use glam::DVec3;

    /// [`sphere_hits`] of four rays (direction, squared length and `tmin` taken from
    /// each), as the scalar test's answers.
    #[target_feature(enable = "avx2")]
    fn four_at_once(sphere: &Sphere, rays: &[Ray; 4], tmax: [f64; 4]) -> [Option<f64>; 4] {
        let lanes = |x: &dyn Fn(&Ray) -> f64| {
            _mm256_setr_pd(x(&rays[0]), x(&rays[1]), x(&rays[2]), x(&rays[3]))
        };
        let origin = [
            lanes(&|r| r.origin.x),
            lanes(&|r| r.origin.y),
            lanes(&|r| r.origin.z),
        ];
        let direction = [
            lanes(&|r| r.direction.x),
            lanes(&|r| r.direction.y),
            lanes(&|r| r.direction.z),
        ];
        let length2 = lanes(&|r| r.direction.dot(r.direction));
        let tmin = lanes(&|r| r.tmin);
        let tmax = _mm256_setr_pd(tmax[0], tmax[1], tmax[2], tmax[3]);
        // SAFETY: AVX2 is enabled in this function.
        let (hit, t) = unsafe { sphere_hits(sphere, &origin, &direction, length2, tmin, tmax) };
        let (mut hits, mut ts) = ([0f64; 4], [0f64; 4]);
        // SAFETY: both hold four doubles.
        unsafe {
            _mm256_storeu_pd(hits.as_mut_ptr(), hit);
            _mm256_storeu_pd(ts.as_mut_ptr(), t);
        }
        [0, 1, 2, 3].map(|l| (hits[l].to_bits() != 0).then_some(ts[l]))
    }

    /// The packet's node test of the eight boxes of `node`, as its traversal takes it, for
    /// rays that search up to `horizon`: the child mask and the entry bounds.
    #[target_feature(enable = "avx2")]
    fn packet_test(ranges: &Ranges, node: &Node<f64>, horizon: f64) -> (u32, [f64; WIDTH]) {
        let planes = node.planes.as_ptr().cast::<f64>();
        let tmax = ranges.node_tmax(horizon);
        let mut entries = [0f64; WIDTH];
        let mut mask = 0;
        for half in [0, 4] {
            // SAFETY: AVX2 is enabled here; `planes` is a node's; `entries` holds eight
            // doubles.
            unsafe {
                let (hit, enter) = ranges.enters(planes, half, tmax);
                mask |= hit << half;
                _mm256_storeu_pd(entries.as_mut_ptr().add(half), enter);
            }
        }
        (mask, entries)
    }

    /// The lens packets of [`crate::packet_cases::lens_packets`] as float64 rays, each with
    /// its set-up ranges and the distance where its rays meet.
    fn packets_with_ranges(random: &mut XorShift) -> Vec<(Vec<Ray>, Ranges, f64)> {
        crate::packet_cases::lens_packets(random, |ray| ray)
            .into_iter()
            .map(|(rays, focus)| {
                let rays: Vec<Ray> = rays
                    .iter()
                    .map(|&(origin, direction)| Ray {
                        origin,
                        direction,
                        tmin: 0.0,
                        tmax: f64::INFINITY,
                    })
                    .collect();
                let mut fixed = MaybeUninit::uninit();
                // SAFETY: the callers check that the CPU has AVX2.
                let ranges = unsafe { set_up(&rays, &mut fixed) }.expect("one octant, finite");
                (rays, ranges, focus)
            })
            .collect()
    }

    /// Checks that `ranges` admit every box at the edge of what each of `rays` enters
    /// ([`crate::packet_cases::edge_boxes`]) that the ray's own node test admits
    /// ([`crate::bvh::intersect_node`] in float64), with an entry bound no later than the
    /// ray's own; returns how many of those boxes the ray enters only by its test's
    /// rounding (past the exit).
    fn check_edge_boxes(rays: &[Ray], ranges: &Ranges, focus: f64) -> usize {
        use crate::bvh::{BoxRay, intersect_node};
        let mut borderline = 0;
        for (i, ray) in rays.iter().enumerate() {
            let own = BoxRay::new(ray.origin.to_array(), ray.direction.to_array(), ray.tmin);
            let edge = (ray.origin, ray.direction);
            for boxes in crate::packet_cases::edge_boxes(edge, focus, 2f64.powi(-53)) {
                let mut node = Node {
                    planes: [[[f64::INFINITY; WIDTH]; 3], [[f64::NEG_INFINITY; WIDTH]; 3]],
                    children: [0; WIDTH],
                };
                for (lane, (b, _)) in boxes.iter().enumerate() {
                    for axis in 0..3 {
                        node.planes[0][axis][lane] = b.min[axis];
                        node.planes[1][axis][lane] = b.max[axis];
                    }
                }
                let (own_mask, own_entries) = intersect_node(&node, &own, ray.tmax);
                // SAFETY: the callers check that the CPU has AVX2.
                let (mask, entries) = unsafe { packet_test(ranges, &node, ray.tmax) };
                for (lane, &(b, k)) in boxes.iter().enumerate() {
                    if own_mask >> lane & 1 == 0 {
                        continue;
                    }
                    borderline += usize::from(k > 0);
                    assert!(
                        mask >> lane & 1 == 1 && entries[lane] <= own_entries[lane],
                        "ray {i} of {:?}… enters box {b:?} ({k} ulps past its exit) at {}; \
                         its packet (shift {}) admits it: {}, from {}",
                        rays[0],
                        own_entries[lane],
                        ranges.shift,
                        mask >> lane & 1 == 1,
                        entries[lane]
                    );
                }
            }
        }
        borderline
    }

    /// A packet admits every box that one of its rays' own node tests admits, and bounds
    /// the ray's entry into it from below, so that packets and single rays visit the same
    /// spheres and find the same hits. Lens packets are bounded from their waist
    /// ([`Ranges::shift`]), where distances are small, but a ray's own test rounds (and
    /// widens its exits) in proportion to its distance from its origin. Packets of rays
    /// that meet exactly at one point are also checked with their exact ranges there (a
    /// point per axis), which leave the node test's widening alone to cover that rounding.
    #[test]
    fn a_packet_admits_every_box_its_rays_own_tests_admit() {
        if !crate::simd::available() {
            return;
        }
        let (mut shifted, mut borderline) = (0, 0);
        for (rays, ranges, focus) in packets_with_ranges(&mut XorShift::new(23)) {
            shifted += usize::from(ranges.shift != 0.0);
            borderline += check_edge_boxes(&rays, &ranges, focus);
        }
        // Lens packets were bounded from their waist, and rays' own tests admitted boxes
        // they leave before entering (the rounding the packet must cover).
        assert_eq!(shifted, 17);
        assert!(
            borderline > 100,
            "{borderline} boxes admitted past the exit"
        );

        let point = crate::packet_cases::MEETING_POINT;
        let (rays, ranges, focus) = packets_with_ranges(&mut XorShift::new(29))
            .pop()
            .expect("the packet that meets at one point comes last");
        let exact = Ranges {
            origin: [0, 1, 2].map(|a| (point[a], point[a])),
            tmin: -focus,
            shift: focus,
            ..ranges
        };
        assert!(check_edge_boxes(&rays, &exact, focus) > 100);
    }

    /// `x` as `m · 2^e` with an integer `m` (exact).
    fn mantissa(x: f64) -> (i128, i32) {
        if x == 0.0 {
            return (0, i32::MAX);
        }
        let e = x.abs().log2().floor() as i32 - 52;
        let m = (x / 2f64.powi(e)) as i128;
        assert_eq!(m as f64 * 2f64.powi(e), x, "{x} = {m} · 2^{e}");
        (m, e)
    }

    /// `m · 2^e` as a multiple of `2^unit` (`unit <= e`), which must fit.
    fn at((m, e): (i128, i32), unit: i32) -> i128 {
        if m == 0 {
            return 0;
        }
        let shift = (e - unit) as u32;
        assert!(
            m.unsigned_abs().leading_zeros() > shift + 1,
            "{m} · 2^{e} at 2^{unit}"
        );
        m << shift
    }

    /// Each ray's exact point at the shift, `o + s·d` (computed in integers), lies in its
    /// packet's ranges: the rounding of the float64 points is covered. Rays far from the
    /// world's origin round most.
    #[test]
    fn a_packets_ranges_hold_each_rays_exact_point_at_the_waist() {
        if !crate::simd::available() {
            return;
        }
        let mut random = XorShift::new(31);
        let mut shifted = 0;
        for (rays, ranges, _) in packets_with_ranges(&mut random) {
            if ranges.shift == 0.0 {
                continue;
            }
            shifted += 1;
            let s = ranges.shift;
            for ray in &rays {
                for a in 0..3 {
                    let (o_a, d) = (ray.origin[a], ray.direction[a]);
                    let (lo, hi) = ranges.origin[a];
                    // In units of the smallest last bit of `o`, `s·d` and the range's ends
                    // (the values fit in 127 bits, asserted).
                    let ((ms, es), (md, ed)) = (mantissa(s), mantissa(d));
                    let product = (ms * md, es.saturating_add(ed));
                    let terms = [mantissa(o_a), product, mantissa(lo), mantissa(hi)];
                    let unit = terms.iter().map(|t| t.1).min().expect("four terms");
                    let [o, product, lo_at, hi_at] = terms.map(|t| at(t, unit));
                    let exact = o + product;
                    assert!(
                        lo_at <= exact && exact <= hi_at,
                        "axis {a}: {o_a} + {s} · {d} outside [{lo}, {hi}]"
                    );
                }
            }
        }
        assert_eq!(shifted, 17);
    }

    #[test]
    fn four_rays_at_once_hit_a_sphere_bit_for_bit_as_one_at_a_time() {
        if !crate::simd::available() {
            return;
        }
        let mut random = XorShift::new(11);
        let mut unit = || random.unit_f64();
        let (mut hits, mut checked) = (0, 0);
        for case in 0..40_000 {
            let scale = 10f64.powi((case % 7) as i32 - 3);
            let center = DVec3::new(unit() - 0.5, unit() - 0.5, unit() - 0.5) * 100.0 * scale;
            let sphere = Sphere {
                center,
                radius: (0.01 + unit()) * scale,
            };
            let mut rays = [Ray {
                origin: DVec3::ZERO,
                direction: DVec3::X,
                tmin: 0.0,
                tmax: f64::INFINITY,
            }; 4];
            let mut tmax = [f64::INFINITY; 4];
            for (l, ray) in rays.iter_mut().enumerate() {
                // Aimed at points around the sphere: through it, grazing it or beside it;
                // some from inside; directions not all of unit length, some with a zero.
                let origin = match (case + l) % 5 {
                    0 => center + (DVec3::new(unit(), unit(), unit()) - 0.5) * sphere.radius,
                    _ => DVec3::new(unit() - 0.5, unit() - 0.5, unit() - 0.5) * 400.0 * scale,
                };
                let aim =
                    center + (DVec3::new(unit(), unit(), unit()) - 0.5) * 2.0 * sphere.radius * 1.2;
                let mut direction = (aim - origin) * (0.5 + unit());
                if (case + l) % 11 == 0 {
                    direction.y = 0.0;
                }
                *ray = Ray {
                    origin,
                    direction,
                    tmin: if l == 3 { 1e-4 } else { 0.0 },
                    tmax: f64::INFINITY,
                };
                // Horizons at, just around and far from the roots.
                tmax[l] = match (case / 4 + l) % 4 {
                    0 => f64::INFINITY,
                    k => match sphere.roots(origin, direction) {
                        Some((near, far)) => {
                            let edge = if k == 3 { far } else { near };
                            [edge, edge.next_up(), edge.next_down()][case % 3]
                        }
                        None => 1.0,
                    },
                };
                if case % 13 == 0 {
                    ray.tmin = sphere
                        .roots(origin, direction)
                        .map_or(0.0, |(near, _)| near);
                }
            }
            // SAFETY: AVX2 is available (checked above).
            let got = unsafe { four_at_once(&sphere, &rays, tmax) };
            for l in 0..4 {
                let want = sphere.intersect(&rays[l], tmax[l]);
                assert_eq!(
                    got[l].map(f64::to_bits),
                    want.map(f64::to_bits),
                    "case {case} lane {l}: {sphere:?} {:?} tmax {}",
                    rays[l],
                    tmax[l]
                );
                hits += usize::from(want.is_some());
                checked += 1;
            }
        }
        // The cases must exercise both answers.
        assert!(
            hits > checked / 5 && hits < checked * 4 / 5,
            "{hits} of {checked}"
        );
    }
}
