//! AVX2 kernels for the float32 triangle tree, chosen at run time
//! (`is_x86_feature_detected!`, never `-C target-cpu`): the 8-wide slab test of a node, the
//! 4-wide watertight test of a triangle block, and the closest-hit and any-hit traversals
//! built on them.
//!
//! Every arithmetic operation is the scalar path's ([`crate::bvh::intersect_node`],
//! [`crate::triangle::intersect`]), in the same order and without fused multiply-add, so
//! both paths return bit-identical hits and an image does not depend on the CPU it was
//! rendered on. Trees deeper than the inline stack allows are left to the scalar path.

use std::arch::x86_64::*;
use std::mem::MaybeUninit;

use crate::bvh::{Bounds, BoxRay, Bvh, ChildRef, LEAF, Node, WIDTH, leaf_range};
use crate::hint::AnyHitHint;
use crate::ray::Ray;
use crate::scene::TriangleRay;
use crate::triangle::{BLOCK, Nearest, TriangleBlock, TriangleHit, edge_functions_f64};

/// Stack entries of the AVX2 traversals; trees that may need more use the scalar path.
pub const STACK: usize = crate::bvh::KERNEL_STACK;

/// Whether this CPU can run the kernels: AVX2, and the bit instructions every AVX2 CPU
/// also has (BMI1, BMI2, LZCNT, POPCNT), which the traversals enable beside it. Without
/// them `count_ones` is a dozen instructions and `m &= m - 1` three, at every node and
/// leaf a packet visits.
pub fn available() -> bool {
    is_x86_feature_detected!("avx2")
        && is_x86_feature_detected!("bmi1")
        && is_x86_feature_detected!("bmi2")
        && is_x86_feature_detected!("lzcnt")
        && is_x86_feature_detected!("popcnt")
}

/// A ray's constants, broadcast once.
pub(crate) struct Lanes {
    origin: [__m256; 3],
    inv_dir: [__m256; 3],
    inv_dir_far: [__m256; 3],
    /// Offsets, in floats from a node's start, of each axis's near and far planes.
    near: &'static [usize; 3],
    far: &'static [usize; 3],
    tmin8: __m256,
    pub(crate) tri: TriLanes<__m128>,
    /// `tri` in eight lanes, for two blocks at once ([`block_pair_test`]).
    pub(crate) tri8: TriLanes<__m256>,
}

/// Rays' constants for the watertight test: one ray in every lane (`__m128`, a ray against
/// a block's four triangles), or a ray per lane (`__m256`, a row of a packet against one
/// triangle, or `__m512`, two rows; all its rays then share the axes `k`).
#[derive(Clone, Copy)]
pub(crate) struct TriLanes<V> {
    pub(crate) kx: usize,
    pub(crate) ky: usize,
    pub(crate) kz: usize,
    /// The origin's coordinates on the axes `kx`, `ky`, `kz`, in that order: indexed by
    /// constants, so that the test reads them from registers rather than by axis.
    pub(crate) origin_k: [V; 3],
    pub(crate) sx: V,
    pub(crate) sy: V,
    pub(crate) sz: V,
    pub(crate) tmin: V,
}

/// The four lanes of `x`.
#[inline(always)]
pub(crate) fn lanes4(x: __m128) -> [f32; 4] {
    let mut out = [0f32; 4];
    // SAFETY: `out` holds four floats; SSE is part of x86-64.
    unsafe { _mm_storeu_ps(out.as_mut_ptr(), x) };
    out
}

/// The first three lanes of `x`.
///
/// # Safety
/// Only from a function with AVX enabled.
#[inline(always)]
pub(crate) unsafe fn lanes3(x: __m256d) -> [f64; 3] {
    let mut out = [0f64; 4];
    // SAFETY: `out` holds four doubles; AVX is enabled in the caller.
    unsafe { _mm256_storeu_pd(out.as_mut_ptr(), x) };
    [out[0], out[1], out[2]]
}

// The helpers below are `#[inline(always)] unsafe fn` without `#[target_feature]` (the two
// cannot be combined): they are called only from the AVX2 traversals, into which they and
// their intrinsics inline.

/// A ray's division results, in registers: `inv` holds `1/d` (lanes 0–2), `inv_far` the
/// same times [`EXIT_SCALE`](crate::bvh::Scalar::EXIT_SCALE), `shear` holds
/// `d[kx]/d[kz], d[ky]/d[kz], 1/d[kz]` (lanes 0–2) for the axes `k = [kx, ky, kz]`.
#[derive(Clone, Copy)]
pub(crate) struct RayConstants {
    pub(crate) inv: __m128,
    pub(crate) inv_far: __m128,
    pub(crate) shear: __m128,
    pub(crate) k: [usize; 3],
    /// The permutation of a vector `(x, y, z, w)` into `(kx, ky, kz, w)`.
    pub(crate) order: __m128i,
}

/// The same IEEE divisions and products as [`ShearedRay::new`](crate::triangle::ShearedRay::new)
/// and [`BoxRay::new`](crate::bvh::BoxRay::new) (so bit-identical), but as one 8-lane
/// division and permutes instead of six dependent scalar divisions and indexed reloads:
/// a ray's setup is most of the cost of a ray that misses the scene.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn ray_constants([dx, dy, dz]: [f32; 3]) -> RayConstants {
    // SAFETY: AVX2 is enabled in the caller.
    unsafe {
        let one = _mm_set1_ps(1.0);
        let d = _mm_setr_ps(dx, dy, dz, 1.0);
        // The comparisons `ShearedRay::new` makes, |dx| > |dy|, |dx| > |dz|, |dy| > |dz|
        // (false with a NaN), at once; their bits pick the axes from a table.
        let abs = _mm_andnot_ps(_mm_set1_ps(-0.0), d);
        let greater = _mm_cmp_ps::<_CMP_GT_OQ>(
            _mm_permute_ps::<0b11_01_00_00>(abs),
            _mm_permute_ps::<0b11_10_10_01>(abs),
        );
        let comparisons = (_mm_movemask_ps(greater) & 0b111) as usize;
        let k = AXES[comparisons];
        let order = _mm_loadu_si128(AXIS_ORDER[comparisons].as_ptr().cast());
        let dk = _mm_permutevar_ps(d, order);
        let d_kz = _mm_permute_ps::<0b10_10_10_10>(dk);
        // Lanes 0–3: d[kx]/d[kz], d[ky]/d[kz], 1/d[kz], 1; lanes 4–7: 1/d, 1.
        let numerator = _mm256_set_m128(one, _mm_blend_ps::<0b1100>(dk, one));
        let denominator = _mm256_set_m128(d, _mm_blend_ps::<0b1000>(d_kz, one));
        let quotient = _mm256_div_ps(numerator, denominator);
        let inv = _mm256_extractf128_ps::<1>(quotient);
        RayConstants {
            inv,
            inv_far: _mm_mul_ps(inv, _mm_set1_ps(<f32 as crate::bvh::Scalar>::EXIT_SCALE)),
            shear: _mm256_castps256_ps128(quotient),
            k,
            order,
        }
    }
}

/// Eight rays' constants, a ray per lane: what [`ray_constants`] gives each of them, with
/// origin and `tmin`.
pub(crate) struct RowConstants {
    pub(crate) origin: [__m256; 3],
    pub(crate) tmin: __m256,
    pub(crate) inv: [__m256; 3],
    pub(crate) inv_far: [__m256; 3],
    /// `d[kx]/d[kz]`, `d[ky]/d[kz]`, `1/d[kz]`, each lane with its own ray's axes.
    pub(crate) shear: [__m256; 3],
    /// Masks of the lanes where `|dx| > |dy|`, `|dx| > |dz|` and `|dy| > |dz|`.
    comparisons: [u32; 3],
}

impl RowConstants {
    /// The axes `[kx, ky, kz]` of the ray in lane `lane`.
    #[inline(always)]
    pub(crate) fn axes(&self, lane: usize) -> [usize; 3] {
        let [xy, xz, yz] = self.comparisons.map(|mask| (mask as usize >> lane) & 1);
        AXES[xy | xz << 1 | yz << 2]
    }
}

/// [`ray_constants`] of eight rays at once, with the same IEEE divisions and products lane
/// by lane (so bit-identical): the rays are transposed into a register per component, and
/// each lane's axes are chosen by selects instead of a table.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn row_constants(rays: [&TriangleRay; 8]) -> RowConstants {
    // SAFETY: AVX2 is enabled in the caller; a `TriangleRay` is eight floats (`repr(C)`).
    unsafe {
        let load = |ray: &TriangleRay| _mm256_loadu_ps((ray as *const TriangleRay).cast());
        let [r0, r1, r2, r3, r4, r5, r6, r7] = rays.map(load);
        // An 8 × 8 transpose: component `c` of ray `l` to lane `l` of `c`.
        let (t0, t1) = (_mm256_unpacklo_ps(r0, r1), _mm256_unpackhi_ps(r0, r1));
        let (t2, t3) = (_mm256_unpacklo_ps(r2, r3), _mm256_unpackhi_ps(r2, r3));
        let (t4, t5) = (_mm256_unpacklo_ps(r4, r5), _mm256_unpackhi_ps(r4, r5));
        let (t6, t7) = (_mm256_unpacklo_ps(r6, r7), _mm256_unpackhi_ps(r6, r7));
        let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let u1 = _mm256_shuffle_ps::<0xee>(t0, t2);
        let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let u3 = _mm256_shuffle_ps::<0xee>(t1, t3);
        let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
        let u5 = _mm256_shuffle_ps::<0xee>(t4, t6);
        let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
        let u7 = _mm256_shuffle_ps::<0xee>(t5, t7);
        let [ox, oy, oz, dx, dy, dz, tmin] = [
            _mm256_permute2f128_ps::<0x20>(u0, u4),
            _mm256_permute2f128_ps::<0x20>(u1, u5),
            _mm256_permute2f128_ps::<0x20>(u2, u6),
            _mm256_permute2f128_ps::<0x20>(u3, u7),
            _mm256_permute2f128_ps::<0x31>(u0, u4),
            _mm256_permute2f128_ps::<0x31>(u1, u5),
            _mm256_permute2f128_ps::<0x31>(u2, u6),
        ];
        let one = _mm256_set1_ps(1.0);
        let inv = [dx, dy, dz].map(|d| _mm256_div_ps(one, d));
        let exit_scale = _mm256_set1_ps(<f32 as crate::bvh::Scalar>::EXIT_SCALE);
        // The comparisons of `ray_constants` (false with a NaN), and from them, as its
        // table [`AXES`] has it: `kz` is x where |dx| > |dy| and |dx| > |dz|, y where
        // |dy| >= |dx| and |dy| > |dz|, z elsewhere; `kx` and `ky` follow it cyclically.
        let abs = |d: __m256| _mm256_andnot_ps(_mm256_set1_ps(-0.0), d);
        let (ax, ay, az) = (abs(dx), abs(dy), abs(dz));
        let xy = _mm256_cmp_ps::<_CMP_GT_OQ>(ax, ay);
        let xz = _mm256_cmp_ps::<_CMP_GT_OQ>(ax, az);
        let yz = _mm256_cmp_ps::<_CMP_GT_OQ>(ay, az);
        let kz_x = _mm256_and_ps(xy, xz);
        let kz_y = _mm256_andnot_ps(xy, yz);
        // `pick(z, x, y)`: the first where `kz` is z, the second where x, the third where y.
        let pick = |z: __m256, x: __m256, y: __m256| {
            _mm256_blendv_ps(_mm256_blendv_ps(z, x, kz_x), y, kz_y)
        };
        let d_kz = pick(dz, dx, dy);
        let d_kx = pick(dx, dy, dz);
        let d_ky = pick(dy, dz, dx);
        RowConstants {
            origin: [ox, oy, oz],
            tmin,
            inv,
            inv_far: inv.map(|i| _mm256_mul_ps(i, exit_scale)),
            shear: [
                _mm256_div_ps(d_kx, d_kz),
                _mm256_div_ps(d_ky, d_kz),
                _mm256_div_ps(one, d_kz),
            ],
            comparisons: [xy, xz, yz].map(|m| _mm256_movemask_ps(m) as u32),
        }
    }
}

/// The watertight test's axes `[kx, ky, kz]` as [`ShearedRay::new`](crate::triangle::ShearedRay::new) chooses them, for each
/// outcome of its comparisons: bit 0 `|dx| > |dy|`, bit 1 `|dx| > |dz|`, bit 2 `|dy| > |dz|`.
static AXES: [[usize; 3]; 8] = {
    let mut table = [[0; 3]; 8];
    let mut bits = 0;
    while bits < 8 {
        let kz = if bits & 1 != 0 {
            if bits & 2 != 0 { 0 } else { 2 }
        } else if bits & 4 != 0 {
            1
        } else {
            2
        };
        let kx = (kz + 1) % 3;
        table[bits] = [kx, (kx + 1) % 3, kz];
        bits += 1;
    }
    table
};

/// [`AXES`] as a permutation of a vector `(x, y, z, w)` into `(kx, ky, kz, w)`.
static AXIS_ORDER: [[i32; 4]; 8] = {
    let mut table = [[0; 4]; 8];
    let mut bits = 0;
    while bits < 8 {
        let [kx, ky, kz] = AXES[bits];
        table[bits] = [kx as i32, ky as i32, kz as i32, 3];
        bits += 1;
    }
    table
};

/// `1/d` of the ray's direction in lanes 0–2, the same division as [`ray_constants`]
/// (bit-identical), alone.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn inverse([dx, dy, dz]: [f32; 3]) -> __m128 {
    // SAFETY: AVX2 is enabled in the caller.
    unsafe { _mm_div_ps(_mm_set1_ps(1.0), _mm_setr_ps(dx, dy, dz, 1.0)) }
}

/// Whether the ray enters `bounds` with `tmin <= t <= tmax`, by [`node_test`]'s arithmetic
/// (the same reciprocals, products and NaN-ignoring order). For the tree's bounds this is
/// conservative: they are the union of the root's slot boxes, and every operation is
/// monotone in the planes, so a ray that enters some child of the root passes. It costs
/// a rejected ray one division and a 4-lane test instead of the full set-up of its lanes.
/// `inv` is `1/d` in lanes 0–2 (from [`inverse`] or [`ray_constants`]).
///
/// A ray whose origin or direction is not finite never enters. It hits no triangle, but
/// its slabs are NaN, which the test passes over (as it must for a ray along a face), and
/// the node tests would take it into every slot, the empty ones too, whose reference
/// leads back to the root: round the tree until the stack overflowed.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn enters(
    bounds: &Bounds<f32>,
    ray: &TriangleRay,
    inv: __m128,
    tmax: f32,
) -> bool {
    let ([ox, oy, oz], [dx, dy, dz]) = (ray.origin, ray.direction);
    let (lo, hi) = (bounds.min, bounds.max);
    // SAFETY: AVX2 is enabled in the caller.
    unsafe {
        let d = _mm_setr_ps(dx, dy, dz, 1.0);
        let o = _mm_setr_ps(ox, oy, oz, 0.0);
        // `x − x` is 0 where `x` is finite, NaN where it is infinite or NaN.
        let finite = _mm_movemask_ps(_mm_cmpunord_ps(_mm_sub_ps(o, o), _mm_sub_ps(d, d))) == 0;
        let inv_far = _mm_mul_ps(inv, _mm_set1_ps(<f32 as crate::bvh::Scalar>::EXIT_SCALE));
        let lo = _mm_setr_ps(lo[0], lo[1], lo[2], 0.0);
        let hi = _mm_setr_ps(hi[0], hi[1], hi[2], 0.0);
        // Near planes by the direction's sign bit, as `lanes` picks them.
        let near = _mm_mul_ps(_mm_sub_ps(_mm_blendv_ps(lo, hi, d), o), inv);
        let far = _mm_mul_ps(_mm_sub_ps(_mm_blendv_ps(hi, lo, d), o), inv_far);
        macro_rules! lane {
            ($v:expr, $i:literal) => {
                _mm_permute_ps::<$i>($v)
            };
        }
        let enter = _mm_max_ss(
            near,
            _mm_max_ss(
                lane!(near, 1),
                _mm_max_ss(lane!(near, 2), _mm_set_ss(ray.tmin)),
            ),
        );
        let exit = _mm_min_ss(
            far,
            _mm_min_ss(lane!(far, 1), _mm_min_ss(lane!(far, 2), _mm_set_ss(tmax))),
        );
        finite & (_mm_cvtss_f32(enter) <= _mm_cvtss_f32(exit))
    }
}

/// Offsets, in floats from a node's start, of the near planes (`[0]`) and far planes
/// (`[1]`) of each axis, for each octant (bit `a` set where the direction's component `a`
/// has its sign bit set). Looked up, not computed, in each ray's set-up.
static PLANE_OFFSETS: [[[usize; 3]; 2]; 8] = {
    let mut table = [[[0; 3]; 2]; 8];
    let mut octant = 0;
    while octant < 8 {
        let mut axis = 0;
        while axis < 3 {
            let negative = (octant >> axis) & 1;
            table[octant][0][axis] = (negative * 3 + axis) * WIDTH;
            table[octant][1][axis] = ((1 - negative) * 3 + axis) * WIDTH;
            axis += 1;
        }
        octant += 1;
    }
    table
};

/// [`TriangleRay::new`]: the ray in float32 with `(tmin, tmax)` rounded outward, as
/// [`f32_at_most`](crate::bvh::f32_at_most) and [`f32_at_least`](crate::bvh::f32_at_least)
/// round them (the same conversions and integer steps, bit for bit), both bounds in one
/// register instead of one after the other.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn triangle_ray(ray: &Ray, tmax: f64) -> TriangleRay {
    // SAFETY: AVX2 is enabled in the caller.
    let [tmin, tmax] = unsafe { interval_f32(ray.tmin, tmax) };
    TriangleRay::rounded(ray, (tmin, tmax))
}

/// `[f32_at_most(tmin), f32_at_least(tmax)]`, computed side by side.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn interval_f32(tmin: f64, tmax: f64) -> [f32; 2] {
    // SAFETY: AVX2 is enabled in the caller.
    unsafe {
        let exact = _mm_setr_pd(tmin, tmax);
        let rounded = _mm_cvtpd_ps(exact);
        let back = _mm_cvtps_pd(rounded);
        // All ones where the bound must step outward: tmin rounded up, tmax rounded down
        // (never with a NaN).
        let step = _mm_castpd_si128(_mm_blend_pd::<0b10>(
            _mm_cmp_pd::<_CMP_GT_OQ>(back, exact),
            _mm_cmp_pd::<_CMP_LT_OQ>(back, exact),
        ));
        // As 32-bit lanes 0 and 1: −1 (one float down) for tmin, +1 (one up) for tmax.
        let step = _mm_sign_epi32(
            _mm_shuffle_epi32::<0b10_10_10_00>(step),
            _mm_setr_epi32(1, -1, 0, 0),
        );
        // `ordered` of crate::bvh, lane by lane: float bits as integers in float order.
        let ordered = |bits: __m128i| {
            _mm_xor_si128(
                bits,
                _mm_and_si128(_mm_srai_epi32::<31>(bits), _mm_set1_epi32(i32::MAX)),
            )
        };
        let stepped = ordered(_mm_add_epi32(ordered(_mm_castps_si128(rounded)), step));
        let lanes = lanes4(_mm_castsi128_ps(stepped));
        [lanes[0], lanes[1]]
    }
}

/// A ray's constants for the block test, broadcast from [`ray_constants`].
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn triangle_lanes(
    ray: &TriangleRay,
    constants: &RayConstants,
) -> TriLanes<__m128> {
    let [kx, ky, kz] = constants.k;
    let shear = constants.shear;
    // SAFETY: AVX2 is enabled in the caller.
    unsafe {
        let [ox, oy, oz] = ray.origin;
        let origin_k = _mm_permutevar_ps(_mm_setr_ps(ox, oy, oz, 0.0), constants.order);
        TriLanes {
            kx,
            ky,
            kz,
            origin_k: [
                _mm_permute_ps::<0b00_00_00_00>(origin_k),
                _mm_permute_ps::<0b01_01_01_01>(origin_k),
                _mm_permute_ps::<0b10_10_10_10>(origin_k),
            ],
            sx: _mm_permute_ps::<0b00_00_00_00>(shear),
            sy: _mm_permute_ps::<0b01_01_01_01>(shear),
            sz: _mm_permute_ps::<0b10_10_10_10>(shear),
            tmin: _mm_set1_ps(ray.tmin),
        }
    }
}

/// A ray's constants for the node and block tests, broadcast from [`ray_constants`];
/// `tri` from [`triangle_lanes`].
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn lanes(
    ray: &TriangleRay,
    constants: &RayConstants,
    tri: TriLanes<__m128>,
) -> Lanes {
    let RayConstants { inv, inv_far, .. } = *constants;
    // SAFETY: AVX2 is enabled in the caller.
    unsafe {
        // A macro, not a closure: a closure would not inherit the caller's AVX2.
        macro_rules! splat8 {
            ($v:expr, $lane:literal) => {{
                let lane = _mm_permute_ps::<{ $lane * 0b01_01_01_01 }>($v);
                _mm256_set_m128(lane, lane)
            }};
        }
        let [ox, oy, oz] = ray.origin;
        let [dx, dy, dz] = ray.direction;
        let octant = _mm_movemask_ps(_mm_setr_ps(dx, dy, dz, 0.0)) as usize & 0b111;
        let [near, far] = &PLANE_OFFSETS[octant];
        Lanes {
            origin: [_mm256_set1_ps(ox), _mm256_set1_ps(oy), _mm256_set1_ps(oz)],
            inv_dir: [splat8!(inv, 0), splat8!(inv, 1), splat8!(inv, 2)],
            inv_dir_far: [
                splat8!(inv_far, 0),
                splat8!(inv_far, 1),
                splat8!(inv_far, 2),
            ],
            near,
            far,
            tmin8: _mm256_set1_ps(ray.tmin),
            tri8: TriLanes {
                kx: tri.kx,
                ky: tri.ky,
                kz: tri.kz,
                origin_k: tri.origin_k.map(|x| _mm256_set_m128(x, x)),
                sx: _mm256_set_m128(tri.sx, tri.sx),
                sy: _mm256_set_m128(tri.sy, tri.sy),
                sz: _mm256_set_m128(tri.sz, tri.sz),
                tmin: _mm256_set_m128(tri.tmin, tri.tmin),
            },
            tri,
        }
    }
}

/// The slab test's arithmetic, one lane per child, for float32 (`_ps`) or float64 (`_pd`)
/// lanes: `(entry, entered)` for the children whose planes start `first` lanes into each
/// plane row. `max(a, b)` returns `b` when `a` is NaN, as the scalar `max_keep(a, b)` does,
/// so the operand order matters. A macro, so that it inlines into the AVX2 functions.
macro_rules! slab_test {
    ($r:expr, $planes:expr, $first:expr, $tmin:expr, $tmax:expr,
     $load:ident, $sub:ident, $mul:ident, $max:ident, $min:ident, $cmp:ident) => {{
        let r = $r;
        let slab = |offset: usize, axis: usize, inv| {
            $mul(
                $sub($load($planes.add(offset + $first)), r.origin[axis]),
                inv,
            )
        };
        let nx = slab(r.near[0], 0, r.inv_dir[0]);
        let ny = slab(r.near[1], 1, r.inv_dir[1]);
        let nz = slab(r.near[2], 2, r.inv_dir[2]);
        let fx = slab(r.far[0], 0, r.inv_dir_far[0]);
        let fy = slab(r.far[1], 1, r.inv_dir_far[1]);
        let fz = slab(r.far[2], 2, r.inv_dir_far[2]);
        let enter = $max(nx, $max(ny, $max(nz, $tmin)));
        let exit = $min(fx, $min(fy, $min(fz, $tmax)));
        (enter, $cmp::<_CMP_LE_OQ>(enter, exit))
    }};
}
pub(crate) use slab_test;

/// The slab test of all eight children: a hit bit per child and the entry distances.
/// Operand order matters: `max(a, b)` returns `b` when `a` is NaN, as the scalar test's
/// NaN-ignoring `max_keep(a, b)` does.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn node_test(node: &Node<f32>, r: &Lanes, tmax: __m256) -> (u32, __m256) {
    let planes = node.planes.as_ptr().cast::<f32>();
    // SAFETY: the offsets are below 6 × 8 floats, and nodes are 64-byte aligned so every
    // 8-float plane starts on a 32-byte boundary; AVX2 is enabled in the caller.
    unsafe {
        let (enter, hit) = slab_test! { r, planes, 0, r.tmin8, tmax,
        _mm256_load_ps, _mm256_sub_ps, _mm256_mul_ps, _mm256_max_ps, _mm256_min_ps, _mm256_cmp_ps };
        (_mm256_movemask_ps(hit) as u32, enter)
    }
}

/// The watertight test's arithmetic ([`crate::triangle::intersect`]), lane by lane, for
/// four triangles against one ray (`_mm_`), eight (two blocks) against one ray or one
/// triangle against eight rays (`_mm256_`): `(mask, Hits)` with a bit per lane where
/// `tmin < t < tmax`. The same IEEE operations in the same order in every lane, so every
/// variant is bit-identical to the scalar test. A macro, so that it inlines into the AVX2
/// functions; `$vertex(v, axis)` gives the lanes of coordinate `axis` of vertex `v`.
macro_rules! watertight_test {
    ($r:expr, $vertex:expr, $tmax:expr, $exact_edges:expr,
     $zero:ident, $sub:ident, $mul:ident, $add:ident, $div:ident, $and:ident, $or:ident,
     $min:ident, $max:ident, $cmp:ident, $movemask:ident) => {{
        let r = $r;
        let vertex = $vertex;
        let (kx, ky, kz) = (r.kx, r.ky, r.kz);
        let [okx, oky, okz] = r.origin_k;
        let relative = |v: usize, axis: usize, o| $sub(vertex(v, axis), o);
        let (az, bz, cz) = (
            relative(0, kz, okz),
            relative(1, kz, okz),
            relative(2, kz, okz),
        );
        let shear = |v: usize, axis: usize, o, s, z| $sub(relative(v, axis, o), $mul(s, z));
        let (ax, ay) = (shear(0, kx, okx, r.sx, az), shear(0, ky, oky, r.sy, az));
        let (bx, by) = (shear(1, kx, okx, r.sx, bz), shear(1, ky, oky, r.sy, bz));
        let (cx, cy) = (shear(2, kx, okx, r.sx, cz), shear(2, ky, oky, r.sy, cz));
        let mut u = $sub($mul(cx, by), $mul(cy, bx));
        let mut v = $sub($mul(ax, cy), $mul(ay, cx));
        let mut w = $sub($mul(bx, ay), $mul(by, ax));

        let zero = $zero();
        let on_edge = $or(
            $cmp::<_CMP_EQ_OQ>(u, zero),
            $or($cmp::<_CMP_EQ_OQ>(v, zero), $cmp::<_CMP_EQ_OQ>(w, zero)),
        );
        if $movemask(on_edge) != 0 {
            (u, v, w) = $exact_edges(on_edge, [ax, ay, bx, by, cx, cy], (u, v, w));
        }

        // Not some edge function negative and another positive: the least is not below
        // zero or the greatest not above. (Where one is NaN, so are `det` and `t`, and the
        // lane misses in the range test whatever is decided here.)
        let det = $add($add(u, v), w);
        let same_side = $or(
            $cmp::<_CMP_GE_OQ>($min(u, $min(v, w)), zero),
            $cmp::<_CMP_LE_OQ>($max(u, $max(v, w)), zero),
        );
        let inside = $and(same_side, $cmp::<_CMP_NEQ_UQ>(det, zero));
        // Most lanes miss: their division is skipped.
        if $movemask(inside) == 0 {
            (
                0,
                Hits {
                    t: zero,
                    u,
                    v,
                    w,
                    det,
                },
            )
        } else {
            let t_scaled = $add(
                $add($mul(u, $mul(r.sz, az)), $mul(v, $mul(r.sz, bz))),
                $mul(w, $mul(r.sz, cz)),
            );
            let t = $div(t_scaled, det);
            let in_range = $and($cmp::<_CMP_GT_OS>(t, r.tmin), $cmp::<_CMP_LT_OS>(t, $tmax));
            let mask = $movemask($and(inside, in_range)) as u32;
            (mask, Hits { t, u, v, w, det })
        }
    }};
}
pub(crate) use watertight_test;

/// The watertight test of a block's four triangles against one ray: a bit per lane with
/// `tmin < t < tmax`, and the lanes' distance, edge functions and determinant (meaningless
/// where the bit is clear).
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn block_test(
    block: &TriangleBlock,
    r: &TriLanes<__m128>,
    tmax: __m128,
) -> (u32, Hits<__m128>) {
    // SAFETY: blocks are 16-byte aligned and each lane array is 16 bytes at a multiple
    // of 16; AVX2 (and so SSE and AVX) is enabled in the caller.
    unsafe {
        let vertex = |v: usize, axis: usize| _mm_load_ps(block.v[v][axis].as_ptr());
        watertight_test! { r, vertex, tmax, exact_edges,
        _mm_setzero_ps, _mm_sub_ps, _mm_mul_ps, _mm_add_ps, _mm_div_ps, _mm_and_ps, _mm_or_ps,
        _mm_min_ps, _mm_max_ps, _mm_cmp_ps, _mm_movemask_ps }
    }
}

/// The watertight test of two neighbouring blocks' eight triangles against one ray (`r`
/// in every lane): `blocks[b]`'s in lanes 0–3, `blocks[b + 1]`'s in lanes 4–7, so that
/// lane `l` is slot `4b + l`; otherwise as [`block_test`]. A leaf of several blocks takes
/// half the tests (DEVELOPERS.md, "Single rays test two blocks at once").
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn block_pair_test(
    blocks: &[TriangleBlock],
    b: usize,
    r: &TriLanes<__m256>,
    tmax: __m256,
) -> (u32, Hits<__m256>) {
    let (low, high) = (&blocks[b], &blocks[b + 1]);
    // SAFETY: AVX2 is enabled in the caller; the loads read 16 bytes each from lane arrays
    // of 16 bytes.
    unsafe {
        let vertex = |v: usize, axis: usize| {
            _mm256_loadu2_m128(high.v[v][axis].as_ptr(), low.v[v][axis].as_ptr())
        };
        watertight_test! { r, vertex, tmax, exact_edges8,
        _mm256_setzero_ps, _mm256_sub_ps, _mm256_mul_ps, _mm256_add_ps, _mm256_div_ps,
        _mm256_and_ps, _mm256_or_ps, _mm256_min_ps, _mm256_max_ps, _mm256_cmp_ps, _mm256_movemask_ps }
    }
}

/// The watertight test of triangle `lane` of `block` against a row of eight rays (which
/// share the axes `k`): a bit per ray with `tmin < t < tmax`, and the rays' values, as
/// [`block_test`] gives them.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn row_test(
    block: &TriangleBlock,
    lane: usize,
    r: &TriLanes<__m256>,
    tmax: __m256,
) -> (u32, Hits<__m256>) {
    // SAFETY: `lane` is below `BLOCK`; AVX2 is enabled in the caller.
    unsafe {
        let vertex = |v: usize, axis: usize| _mm256_broadcast_ss(&block.v[v][axis][lane]);
        watertight_test! { r, vertex, tmax, exact_edges8,
        _mm256_setzero_ps, _mm256_sub_ps, _mm256_mul_ps, _mm256_add_ps, _mm256_div_ps,
        _mm256_and_ps, _mm256_or_ps, _mm256_min_ps, _mm256_max_ps, _mm256_cmp_ps, _mm256_movemask_ps }
    }
}

/// A watertight test's per-lane values: `__m128` for a block's four triangles, `__m256` for
/// a row's eight rays, `__m512` for two rows ([`crate::simd512`]).
pub(crate) struct Hits<V> {
    pub(crate) t: V,
    pub(crate) u: V,
    pub(crate) v: V,
    pub(crate) w: V,
    pub(crate) det: V,
}

/// Folds the hits in lanes `mask` of a test starting at block `block` (distances `t`, lane
/// `l` being slot `4 · block + l`) into `nearest` and `found`, under the tie rule of
/// [`Nearest`]; whether any lane improved on it.
#[inline(always)]
fn keep_nearest<const N: usize>(
    t: &[f32; N],
    mask: u32,
    block: u32,
    nearest: &mut Nearest,
    found: &mut Option<TriangleHit>,
    hit: impl Fn(usize) -> TriangleHit,
) -> bool {
    let mut improved = false;
    let mut m = mask;
    while m != 0 {
        let lane = m.trailing_zeros() as usize;
        m &= m - 1;
        let slot = block * BLOCK as u32 + lane as u32;
        if nearest.improves(t[lane], slot) {
            *nearest = Nearest { t: t[lane], slot };
            *found = Some(hit(lane));
            improved = true;
        }
    }
    improved
}

impl Hits<__m128> {
    /// Folds the hits of block `block` (lanes set in `mask`) into `nearest` and `found`
    /// under the tie rule of [`Nearest`]; whether any lane improved on it.
    #[inline(always)]
    pub(crate) fn keep_nearest(
        &self,
        mask: u32,
        block: u32,
        nearest: &mut Nearest,
        found: &mut Option<TriangleHit>,
    ) -> bool {
        keep_nearest(&lanes4(self.t), mask, block, nearest, found, |lane| {
            self.hit(lane)
        })
    }

    /// Lane `lane` as a [`TriangleHit`].
    #[inline(always)]
    pub(crate) fn hit(&self, lane: usize) -> TriangleHit {
        self.hit_in(|x| lanes4(x)[lane])
    }
}

impl Hits<__m256> {
    /// [`Hits::keep_nearest`] for the eight lanes of [`block_pair_test`], from block
    /// `block`.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    pub(crate) unsafe fn keep_nearest(
        &self,
        mask: u32,
        block: u32,
        nearest: &mut Nearest,
        found: &mut Option<TriangleHit>,
    ) -> bool {
        // SAFETY: AVX2 is enabled in the caller.
        let t = unsafe { lanes8(self.t) };
        // SAFETY: as above.
        keep_nearest(&t, mask, block, nearest, found, |lane| unsafe {
            self.hit(lane)
        })
    }

    /// Lane `lane` as a [`TriangleHit`].
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    pub(crate) unsafe fn hit(&self, lane: usize) -> TriangleHit {
        // SAFETY: AVX2 is enabled in the caller.
        self.hit_in(|x| unsafe { lanes8(x) }[lane])
    }
}

impl<V: Copy> Hits<V> {
    /// The [`TriangleHit`] of the lane `get` reads, barycentrics divided as the scalar test
    /// divides.
    #[inline(always)]
    pub(crate) fn hit_in(&self, get: impl Fn(V) -> f32) -> TriangleHit {
        let det = get(self.det);
        TriangleHit {
            t: get(self.t),
            b0: get(self.u) / det,
            b1: get(self.v) / det,
            b2: get(self.w) / det,
        }
    }
}

/// The eight lanes of `x`.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn lanes8(x: __m256) -> [f32; 8] {
    let mut out = [0f32; 8];
    // SAFETY: `out` holds eight floats; AVX2 is enabled in the caller.
    unsafe { _mm256_storeu_ps(out.as_mut_ptr(), x) };
    out
}

/// The float64 recomputation of the edge functions, for the lanes where one is exactly 0.
#[cold]
#[inline(never)]
fn exact_edges(
    on_edge: __m128,
    sheared: [__m128; 6],
    (u, v, w): (__m128, __m128, __m128),
) -> (__m128, __m128, __m128) {
    // SAFETY: SSE is part of x86-64.
    let mask = unsafe { _mm_movemask_ps(on_edge) } as u32;
    let (u, v, w) = exact_edge_lanes(mask, sheared.map(lanes4), [u, v, w].map(lanes4));
    // SAFETY: each array holds four floats.
    unsafe {
        (
            _mm_loadu_ps(u.as_ptr()),
            _mm_loadu_ps(v.as_ptr()),
            _mm_loadu_ps(w.as_ptr()),
        )
    }
}

/// [`exact_edges`] for eight lanes.
///
/// # Safety
/// The CPU must support AVX2.
#[cold]
#[inline(never)]
#[target_feature(enable = "avx2")]
unsafe fn exact_edges8(
    on_edge: __m256,
    sheared: [__m256; 6],
    (u, v, w): (__m256, __m256, __m256),
) -> (__m256, __m256, __m256) {
    // SAFETY: AVX2 is enabled in this function.
    let lanes = |x| unsafe { lanes8(x) };
    let mask = _mm256_movemask_ps(on_edge) as u32;
    let (u, v, w) = exact_edge_lanes(mask, sheared.map(lanes), [u, v, w].map(lanes));
    // SAFETY: each array holds eight floats.
    unsafe {
        (
            _mm256_loadu_ps(u.as_ptr()),
            _mm256_loadu_ps(v.as_ptr()),
            _mm256_loadu_ps(w.as_ptr()),
        )
    }
}

/// The edge functions `[u, v, w]`, recomputed in float64 in the lanes whose bit is set
/// in `mask`.
#[inline(always)]
pub(crate) fn exact_edge_lanes<const N: usize>(
    mask: u32,
    [ax, ay, bx, by, cx, cy]: [[f32; N]; 6],
    [mut u, mut v, mut w]: [[f32; N]; 3],
) -> ([f32; N], [f32; N], [f32; N]) {
    for lane in 0..N {
        if mask >> lane & 1 == 1 {
            (u[lane], v[lane], w[lane]) =
                edge_functions_f64(ax[lane], ay[lane], bx[lane], by[lane], cx[lane], cy[lane]);
        }
    }
    (u, v, w)
}

/// Lane `i` of `x`, taken in registers (a store and reloads of single lanes would wait on
/// store forwarding).
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
pub(crate) unsafe fn lane8(x: __m256, i: usize) -> f32 {
    // SAFETY: AVX2 is enabled in the caller.
    unsafe { _mm256_cvtss_f32(_mm256_permutevar8x32_ps(x, _mm256_set1_epi32(i as i32))) }
}

/// A stack entry: `(entry distance, child)` in a `u64`, distance in the high half.
/// Distances are never negative, so integer order is the order of `(distance, child)`,
/// the order in which both the scalar and the AVX2 traversals visit children.
#[inline(always)]
pub(crate) fn pack(distance: f32, child: u32) -> u64 {
    (u64::from(distance.to_bits()) << 32) | u64::from(child)
}

#[inline(always)]
pub(crate) fn distance(entry: u64) -> f32 {
    f32::from_bits((entry >> 32) as u32)
}

/// Closest-hit traversal of the triangle tree: the nearest hit with `tmin < t < tmax`,
/// under the tie rule of [`Nearest`].
///
/// # Safety
/// The CPU must have what [`available`] checks: AVX2 and its bit instructions.
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
pub unsafe fn closest(
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    ray: &Ray,
    tmax: f64,
) -> Option<(Nearest, TriangleHit)> {
    assert!(
        bvh.stack_bound() <= STACK,
        "the scalar path handles deeper trees"
    );
    let nodes = bvh.nodes();
    if nodes.is_empty() {
        return None;
    }
    // Rounded here rather than by the caller: passed in, the float32 ray would be stored
    // field by field and reloaded whole, stalling every ray on store forwarding.
    // SAFETY: AVX2 is enabled in this function.
    let ray = unsafe { triangle_ray(ray, tmax) };
    let mut nearest = Nearest::before(ray.tmax);
    // SAFETY (for every helper called below): AVX2 is enabled in this function.
    if !unsafe {
        enters(
            &bvh.bounds(),
            &ray,
            inverse(ray.direction),
            nearest.horizon(),
        )
    } {
        return None;
    }
    let r = unsafe {
        let constants = ray_constants(ray.direction);
        lanes(&ray, &constants, triangle_lanes(&ray, &constants))
    };
    let mut stack = [const { MaybeUninit::<u64>::uninit() }; STACK];
    let mut sp = 0usize;
    let mut found = None;
    // Boxes are kept when entered up to the search horizon just past the nearest hit (ties
    // may still win), and triangles tested up to it inclusive: `t < next_up(nearest.t)`.
    let mut t_box = _mm256_set1_ps(nearest.horizon());
    let mut t_tri = _mm_set1_ps(nearest.t.next_up());
    let mut current = 0u32;
    'trace: loop {
        // Down the tree until a leaf, or until no child is entered.
        let reached_leaf = loop {
            if current & LEAF != 0 {
                break true;
            }
            let node = &nodes[current as usize];
            let (mask, enter) = unsafe { node_test(node, &r, t_box) };
            if mask == 0 {
                break false;
            }
            let first = mask.trailing_zeros() as usize;
            let rest = mask & (mask - 1);
            current = node.children[first];
            prefetch_child(nodes, blocks, current);
            if rest == 0 {
                continue;
            }
            let second = rest.trailing_zeros() as usize;
            let a = pack(unsafe { lane8(enter, first) }, current);
            let b = pack(unsafe { lane8(enter, second) }, node.children[second]);
            if rest & (rest - 1) == 0 {
                // Two children: visit the nearer, push the farther.
                let (near, far) = if a <= b { (a, b) } else { (b, a) };
                stack[sp] = MaybeUninit::new(far);
                sp += 1;
                current = near as u32;
                continue;
            }
            // More: insert them all into a run on the stack, farthest first, and take the
            // nearest back off its top.
            let base = sp;
            let mut m = mask;
            while m != 0 {
                let i = m.trailing_zeros() as usize;
                m &= m - 1;
                let entry = pack(unsafe { lane8(enter, i) }, node.children[i]);
                push_sorted(&mut stack, base, &mut sp, entry);
            }
            sp -= 1;
            // SAFETY: written above.
            current = unsafe { stack[sp].assume_init() } as u32;
        };
        let (first, count) = if reached_leaf {
            leaf_range(current)
        } else {
            (0, 0)
        };
        // The leaf's blocks two at a time, then the last alone if their number is odd.
        let end = first + count;
        let mut b = first;
        while b + 1 < end {
            let limit = _mm256_set_m128(t_tri, t_tri);
            let (mask, lanes) = unsafe { block_pair_test(blocks, b as usize, &r.tri8, limit) };
            if mask != 0 && unsafe { lanes.keep_nearest(mask, b, &mut nearest, &mut found) } {
                t_box = _mm256_set1_ps(nearest.horizon());
                t_tri = _mm_set1_ps(nearest.t.next_up());
            }
            b += 2;
        }
        if b < end {
            let (mask, lanes) = unsafe { block_test(&blocks[b as usize], &r.tri, t_tri) };
            if mask != 0 && lanes.keep_nearest(mask, b, &mut nearest, &mut found) {
                t_box = _mm256_set1_ps(nearest.horizon());
                t_tri = _mm_set1_ps(nearest.t.next_up());
            }
        }
        // Pop the next entry that may still hold something as near.
        loop {
            if sp == 0 {
                break 'trace;
            }
            sp -= 1;
            // SAFETY: every slot below `sp` was written above.
            let entry = unsafe { stack[sp].assume_init() };
            if distance(entry) <= nearest.horizon() {
                current = entry as u32;
                continue 'trace;
            }
        }
    }
    found.map(|hit| (nearest, hit))
}

/// Asks the cache for every 64-byte line from `start` up to `end`, without waiting for
/// them. (A prefetch never faults, so the addresses need not even be valid.) A plain loop:
/// an iterator's stepping added instructions at every node the traversals visit.
#[inline(always)]
pub(crate) fn prefetch(start: usize, end: usize) {
    const LINE: usize = 64;
    let mut line = start & !(LINE - 1);
    while line < end {
        // SAFETY: a prefetch never faults, whatever the address; SSE is part of x86-64.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(line as *const i8) };
        line += LINE;
    }
}

/// Asks the cache for the node or leaf blocks of `child`, so that they arrive while other
/// work goes on. A packet asks for every child it pushes (it visits nearly all of them).
/// The single-ray traversals ask for the entered child in the lowest slot at once, before
/// knowing which is nearest: the next visited when it is the only one (and always, in
/// any-hit traversal, which takes children unordered), and otherwise one of those the ray
/// entered; where neighbouring rays share few nodes (a fine mesh at low resolution) the
/// fetch runs while the other children are ordered and pushed. (Asking for the nearest
/// once ordered measured no better at 320x180 and 1–3% slower at full HD.)
#[inline(always)]
pub(crate) fn prefetch_child(nodes: &[Node<f32>], blocks: &[TriangleBlock], child: ChildRef) {
    if child & LEAF == 0 {
        // Nodes are whole lines: ask for each by a constant offset, without a loop.
        const LINES: usize = std::mem::size_of::<Node<f32>>() / 64;
        let node = nodes.as_ptr().wrapping_add(child as usize).cast::<i8>();
        for line in 0..LINES {
            // SAFETY: a prefetch never faults, whatever the address; SSE is part of x86-64.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(node.wrapping_add(line * 64)) };
        }
    } else {
        let (first, count) = leaf_range(child);
        let start = blocks.as_ptr().wrapping_add(first as usize);
        prefetch(start as usize, start.wrapping_add(count as usize) as usize);
    }
}

/// Any-hit traversal: whether some triangle has `tmin < t < tmax`. The hint's blocks are
/// tested first (the previous query's, then, out of line, the one [`AnyHitHint::ROWS`]
/// queries back), then the subtree around the first (under the node kept with it in the
/// hint), then the one around the second, then the whole tree; the hint then names the
/// triangle found and its subtree, or nothing.
///
/// # Safety
/// As for [`closest`].
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
pub unsafe fn any(
    bvh: &Bvh<f32>,
    blocks: &[TriangleBlock],
    ray: &Ray,
    hint: &mut AnyHitHint,
) -> bool {
    assert!(
        bvh.stack_bound() <= STACK,
        "the scalar path handles deeper trees"
    );
    let nodes = bvh.nodes();
    if nodes.is_empty() {
        return false;
    }
    // SAFETY (for every helper called below): AVX2 is enabled in this function.
    let ray = unsafe { triangle_ray(ray, ray.tmax) };
    // The hint's blocks first, before the tree's box and the node tests' set-up: a ray
    // that hits one (on coherent rays, most rays after a hit) needs neither. A ray without
    // a hint (after a miss) tests the tree's box before its set-up, as closest hit does.
    let hinted = hint.blocks()[0].filter(|&b| b < blocks.len());
    let hinted_constants = match hinted {
        Some(b) => {
            let constants = unsafe { ray_constants(ray.direction) };
            let tri = unsafe { triangle_lanes(&ray, &constants) };
            let [near, above] = hint.subtrees();
            if let Some(slot) = unsafe { block_hit(blocks, b as u32, &tri, ray.tmax) } {
                hint.remember_triangle(Some((slot, near)));
                return true;
            }
            if let Some(slot) = unsafe { second_guess(hint, blocks, &tri, ray.tmax) } {
                hint.remember_triangle(Some((slot, above)));
                return true;
            }
            Some(constants)
        }
        None => None,
    };
    // Boxes are entered up to the horizon past tmax: a triangle's computed distance can
    // round below its box's computed entry distance ([`crate::triangle::SEARCH_MARGIN`]).
    let horizon = Nearest::before(ray.tmax).horizon();
    let inv = match &hinted_constants {
        Some(constants) => constants.inv,
        None => unsafe { inverse(ray.direction) },
    };
    if !unsafe { enters(&bvh.bounds(), &ray, inv, horizon) } {
        hint.remember_triangle(None);
        return false;
    }
    let constants = match hinted_constants {
        Some(constants) => constants,
        None => unsafe { ray_constants(ray.direction) },
    };
    let r = unsafe { lanes(&ray, &constants, triangle_lanes(&ray, &constants)) };
    let found = 'search: {
        // The subtrees around the hint's blocks (the second's too: where neighbouring rays
        // scatter, through a lens, the ray above may have hit nearer this one's hit). Each
        // search written out: a loop over the two measured slower.
        let [near, far] = hint.subtrees_to_search(blocks.len(), nodes.len());
        if let Some(near) = near
            && let Some(found) = unsafe { any_below(nodes, blocks, near, &r, horizon, ray.tmax) }
        {
            break 'search Some(found);
        }
        if let Some(far) = far
            && let Some(found) = unsafe { any_below(nodes, blocks, far, &r, horizon, ray.tmax) }
        {
            break 'search Some(found);
        }
        unsafe { any_below(nodes, blocks, 0, &r, horizon, ray.tmax) }
    };
    hint.remember_triangle(found);
    found.is_some()
}

/// The slot of a triangle of the hint's second block ([`AnyHitHint::blocks`]) with
/// `tmin < t < tmax`, if any: tried when the first missed. Out of line, as inlined it cost
/// every query (the unhinted ones 10–14% on the torus and the scans).
///
/// # Safety
/// Only on a CPU with what [`available`] checks.
#[inline(never)]
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn second_guess(
    hint: &AnyHitHint,
    blocks: &[TriangleBlock],
    tri: &TriLanes<__m128>,
    tmax: f32,
) -> Option<u32> {
    let b = hint.blocks()[1].filter(|&b| b < blocks.len())?;
    unsafe { block_hit(blocks, b as u32, tri, tmax) }
}

/// The slot of a triangle of block `b` with `tmin < t < tmax`, if any.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn block_hit(
    blocks: &[TriangleBlock],
    b: u32,
    r: &TriLanes<__m128>,
    tmax: f32,
) -> Option<u32> {
    // SAFETY: AVX2 is enabled in the caller.
    let mask = unsafe { block_test(&blocks[b as usize], r, _mm_set1_ps(tmax)) }.0;
    (mask != 0).then(|| b * BLOCK as u32 + mask.trailing_zeros())
}

/// Any-hit search of the subtree under node `start`: the slot of the first triangle found
/// with `tmin < t < tmax`, entering boxes up to `horizon`, and the node one level above
/// the node holding its leaf (`start` for a leaf `start` holds), as [`Bvh::any_below`]
/// names it.
///
/// # Safety
/// Only from a function with AVX2 enabled; the tree must fit [`STACK`].
#[inline(always)]
unsafe fn any_below(
    nodes: &[Node<f32>],
    blocks: &[TriangleBlock],
    start: u32,
    r: &Lanes,
    horizon: f32,
    tmax: f32,
) -> Option<(u32, u32)> {
    let t_far = unsafe { _mm256_set1_ps(horizon) };
    // Each entry: the child, and above it (bits 32–63) the node a hit under it is named by.
    let mut stack = [const { MaybeUninit::<u64>::uninit() }; STACK];
    let mut sp = 0usize;
    let (mut current, mut up) = (start, start);
    loop {
        if current & LEAF != 0 {
            let (first, count) = leaf_range(current);
            // As in `closest`: two blocks at a time, the last alone if their number is odd.
            let end = first + count;
            let mut b = first;
            while b + 1 < end {
                // SAFETY: AVX2 is enabled in the caller.
                let (mask, _) =
                    unsafe { block_pair_test(blocks, b as usize, &r.tri8, _mm256_set1_ps(tmax)) };
                if mask != 0 {
                    return Some((b * BLOCK as u32 + mask.trailing_zeros(), up));
                }
                b += 2;
            }
            // SAFETY: AVX2 is enabled in the caller.
            if b < end
                && let Some(slot) = unsafe { block_hit(blocks, b, &r.tri, tmax) }
            {
                return Some((slot, up));
            }
        } else {
            let node = &nodes[current as usize];
            // SAFETY: AVX2 is enabled in the caller.
            let (mut mask, _) = unsafe { node_test(node, r, t_far) };
            if mask != 0 {
                // A leaf is named by its node's parent, an inner child by its parent.
                let entry = |child: ChildRef| {
                    let above = if child & LEAF != 0 { up } else { current };
                    u64::from(above) << 32 | u64::from(child)
                };
                // Children in slot order: nearest first or leaves first measured slower
                // (DEVELOPERS.md, "A single any-hit ray takes the entered children ...").
                let first = mask.trailing_zeros() as usize;
                // Asked for before the others are pushed, as in `closest`.
                prefetch_child(nodes, blocks, node.children[first]);
                mask &= mask - 1;
                while mask != 0 {
                    stack[sp] =
                        MaybeUninit::new(entry(node.children[mask.trailing_zeros() as usize]));
                    sp += 1;
                    mask &= mask - 1;
                }
                let next = entry(node.children[first]);
                (current, up) = (next as u32, (next >> 32) as u32);
                continue;
            }
        }
        if sp == 0 {
            return None;
        }
        sp -= 1;
        // SAFETY: every slot below `sp` was written above.
        let next = unsafe { stack[sp].assume_init() };
        (current, up) = (next as u32, (next >> 32) as u32);
    }
}

/// Pushes `key` onto `stack[..sp]`, keeping the entries pushed since `base` in descending
/// order (so the nearest child is popped first). Slots `base..sp` must be initialized.
#[inline(always)]
pub(crate) fn push_sorted(stack: &mut [MaybeUninit<u64>], base: usize, sp: &mut usize, key: u64) {
    let mut j = *sp;
    // SAFETY: slots `base..sp` are initialized (the caller's contract).
    while j > base && unsafe { stack[j - 1].assume_init() } < key {
        stack[j] = stack[j - 1];
        j -= 1;
    }
    stack[j] = MaybeUninit::new(key);
    *sp += 1;
}

/// A float64 ray's constants for the 8-wide box test of the spheres' tree, broadcast once.
pub(crate) struct WideLanes {
    origin: [__m256d; 3],
    inv_dir: [__m256d; 3],
    inv_dir_far: [__m256d; 3],
    near: [usize; 3],
    far: [usize; 3],
    tmin: __m256d,
}

/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn wide_lanes(ray: &BoxRay<f64>) -> WideLanes {
    let offset = |side: usize, axis: usize| (side * 3 + axis) * WIDTH;
    // SAFETY: AVX2 is enabled in the caller.
    unsafe {
        WideLanes {
            origin: ray.origin.map(|o| _mm256_set1_pd(o)),
            inv_dir: ray.inv_dir.map(|d| _mm256_set1_pd(d)),
            inv_dir_far: ray.inv_dir_far.map(|d| _mm256_set1_pd(d)),
            near: [0, 1, 2].map(|a| offset(ray.near[a], a)),
            far: [0, 1, 2].map(|a| offset(1 - ray.near[a], a)),
            tmin: _mm256_set1_pd(ray.tmin),
        }
    }
}

/// [`crate::bvh::intersect_node`] for a float64 node, four children per instruction: the
/// same operations in the same order (`max(a, b)` returns `b` when `a` is NaN, as
/// `max_keep` does), so the same mask and entries.
///
/// # Safety
/// Only from a function with AVX2 enabled.
#[inline(always)]
unsafe fn wide_node_test(node: &Node<f64>, r: &WideLanes, tmax: f64) -> (u32, [f64; WIDTH]) {
    let planes = node.planes.as_ptr().cast::<f64>();
    let mut entry = [0f64; WIDTH];
    let mut mask = 0;
    // SAFETY: offsets are below 6 × 8 doubles, nodes are 64-byte aligned so each group of
    // four doubles is 32-byte aligned, and `entry` holds eight doubles.
    unsafe {
        let tmax = _mm256_set1_pd(tmax);
        for half in [0, 4] {
            let (enter, hit) = slab_test! { r, planes, half, r.tmin, tmax,
            _mm256_load_pd, _mm256_sub_pd, _mm256_mul_pd, _mm256_max_pd, _mm256_min_pd, _mm256_cmp_pd };
            mask |= (_mm256_movemask_pd(hit) as u32) << half;
            _mm256_storeu_pd(entry.as_mut_ptr().add(half), enter);
        }
    }
    (mask, entry)
}

/// [`Bvh::closest`] over a float64 tree with the AVX2 box test: the same visits in the
/// same order.
///
/// # Safety
/// The CPU must have what [`available`] checks: AVX2 and its bit instructions.
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
pub unsafe fn wide_closest(
    bvh: &Bvh<f64>,
    ray: &BoxRay<f64>,
    tmax: &mut f64,
    leaf: impl FnMut(u32, u32, &mut f64),
) {
    // SAFETY (for the helpers): AVX2 is enabled in this function.
    let r = unsafe { wide_lanes(ray) };
    bvh.closest_by(
        |node, tmax| unsafe { wide_node_test(node, &r, tmax) },
        tmax,
        leaf,
    );
}

/// [`Bvh::any`] over a float64 tree with the AVX2 box test.
///
/// # Safety
/// The CPU must have what [`available`] checks: AVX2 and its bit instructions.
#[target_feature(enable = "avx2,bmi1,bmi2,lzcnt,popcnt")]
pub unsafe fn wide_any(
    bvh: &Bvh<f64>,
    ray: &BoxRay<f64>,
    tmax: f64,
    leaf: impl FnMut(u32, u32) -> bool,
) -> bool {
    // SAFETY (for the helpers): AVX2 is enabled in this function.
    let r = unsafe { wide_lanes(ray) };
    bvh.any_by(|node| unsafe { wide_node_test(node, &r, tmax) }.0, leaf)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvh::{f32_at_least, f32_at_most};
    use crate::test_random::XorShift;

    #[test]
    fn intervals_round_outward_bit_for_bit_as_the_scalar_functions() {
        if !available() {
            return;
        }
        let mut random = XorShift::new(7);
        let special = [
            0.0,
            -0.0,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            1e-4,
            f64::from(f32::MAX),
            f64::from(f32::MAX) * (1.0 + 1e-12),
            -f64::from(f32::MAX) * (1.0 + 1e-12),
            f64::from(f32::MIN_POSITIVE) / 3.0,
            -1e-50,
            1e-50,
            f64::MAX,
            0.1,
            -0.1,
        ];
        let random_values = (0..20_000).map(|_| {
            // Any bit pattern: every exponent, sign and NaN payload.
            f64::from_bits(random.next_u64())
        });
        let scaled = (0..20_000).map(|i| (XorShift::new(i).unit_f64() - 0.5) * 1e3);
        let values: Vec<f64> = special
            .into_iter()
            .chain(random_values)
            .chain(scaled)
            .collect();
        for pair in values.windows(2) {
            let (tmin, tmax) = (pair[0], pair[1]);
            // SAFETY: AVX2 is available (checked above).
            let [lo, hi] = unsafe { interval_avx2(tmin, tmax) };
            assert_eq!(lo.to_bits(), f32_at_most(tmin).to_bits(), "tmin {tmin:e}");
            assert_eq!(hi.to_bits(), f32_at_least(tmax).to_bits(), "tmax {tmax:e}");
        }
    }

    #[test]
    fn row_constants_match_the_scalar_set_up_lane_by_lane() {
        use crate::bvh::BoxRay;
        use crate::triangle::ShearedRay;
        if !available() {
            return;
        }
        // Components that take every branch of the axis choice: zeros of both signs,
        // ties of magnitude with either sign, tiny and huge values, NaN, and random ones.
        let special = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            0.5,
            -0.5,
            1e-30,
            -1e-30,
            3e38,
            f32::NAN,
        ];
        let mut random = XorShift::new(11);
        let pick = |random: &mut XorShift| {
            if random.below(3) == 0 {
                special[random.below(special.len() as u64) as usize]
            } else {
                random.unit_f32() * 2.0 - 1.0
            }
        };
        for _ in 0..5_000 {
            let rays: [TriangleRay; 8] = std::array::from_fn(|_| TriangleRay {
                origin: [0; 3].map(|_| random.unit_f32() * 8.0 - 4.0),
                direction: [0; 3].map(|_| pick(&mut random)),
                tmin: random.unit_f32(),
                tmax: random.unit_f32() + 1.0,
            });
            // SAFETY: AVX2 is available (checked above).
            let row = unsafe { row_avx2(&rays) };
            for (l, ray) in rays.iter().enumerate() {
                let at = |x: __m256| unsafe { lanes8(x) }[l].to_bits();
                let sheared = ShearedRay::new(ray.origin.into(), ray.direction.into());
                let boxes = BoxRay::new(ray.origin, ray.direction, ray.tmin);
                let why = format!("lane {l} of {rays:?}");
                assert_eq!(row.axes(l), [sheared.kx, sheared.ky, sheared.kz], "{why}");
                let shear = [sheared.sx, sheared.sy, sheared.sz].map(f32::to_bits);
                assert_eq!(row.shear.map(at), shear, "{why}");
                assert_eq!(row.inv.map(at), boxes.inv_dir.map(f32::to_bits), "{why}");
                assert_eq!(
                    row.inv_far.map(at),
                    boxes.inv_dir_far.map(f32::to_bits),
                    "{why}"
                );
                assert_eq!(row.origin.map(at), ray.origin.map(f32::to_bits), "{why}");
                assert_eq!(at(row.tmin), ray.tmin.to_bits(), "{why}");
            }
        }
    }

    #[test]
    fn two_blocks_at_once_give_each_lane_the_scalar_test_s_hit() {
        use crate::triangle::{ShearedRay, intersect};
        if !available() {
            return;
        }
        // Eight triangles of a grid in the plane z = 2, sharing edges and vertices, and
        // rays along z at grid points (every edge function exactly 0 on the edges, the
        // exact-edge path) and between them; then random triangles and rays.
        let grid: [[[f32; 3]; 3]; 8] = std::array::from_fn(|i| {
            // Two triangles to each cell of a 2 × 2 grid over [0, 2]².
            let (x, y) = ((i / 2 % 2) as f32, (i / 4) as f32);
            let corner = |dx: f32, dy: f32| [x + dx, y + dy, 2.0];
            if i % 2 == 0 {
                [corner(0.0, 0.0), corner(1.0, 0.0), corner(1.0, 1.0)]
            } else {
                [corner(0.0, 0.0), corner(1.0, 1.0), corner(0.0, 1.0)]
            }
        });
        let mut cases: Vec<([[[f32; 3]; 3]; 8], TriangleRay)> = Vec::new();
        for half_x in 0..=6 {
            for half_y in 0..=6 {
                let (x, y) = (half_x as f32 * 0.5 - 0.5, half_y as f32 * 0.5 - 0.5);
                for dz in [1.0, -1.0] {
                    let ray = TriangleRay {
                        origin: [x, y, 2.0 - 3.0 * dz],
                        direction: [0.0, 0.0, dz],
                        tmin: 0.0,
                        tmax: f32::INFINITY,
                    };
                    cases.push((grid, ray));
                }
            }
        }
        let grid_rays = cases.len();
        let mut random = XorShift::new(23);
        let mut point = || [0; 3].map(|_| random.unit_f32() * 2.0 - 1.0);
        for _ in 0..2_000 {
            let triangles = std::array::from_fn(|_| [point(), point(), point()]);
            let ray = TriangleRay {
                origin: point().map(|c| c * 4.0),
                direction: point(),
                tmin: 0.0,
                tmax: 10.0,
            };
            cases.push((triangles, ray));
        }
        let mut random_hits = 0;
        for (i, (triangles, ray)) in cases.iter().enumerate() {
            let blocks: [TriangleBlock; 2] = std::array::from_fn(|b| {
                let mut block = TriangleBlock {
                    v: [[[0.0; BLOCK]; 3]; 3],
                    ids: [0; BLOCK],
                };
                for lane in 0..BLOCK {
                    for (k, vertex) in triangles[b * BLOCK + lane].iter().enumerate() {
                        for (axis, &coordinate) in vertex.iter().enumerate() {
                            block.v[k][axis][lane] = coordinate;
                        }
                    }
                }
                block
            });
            // SAFETY: AVX2 is available (checked above).
            let (mask, lanes) = unsafe { pair_avx2(&blocks, ray) };
            let sheared = ShearedRay::new(ray.origin.into(), ray.direction.into());
            for (lane, [v0, v1, v2]) in triangles.iter().enumerate() {
                let expected = intersect(&sheared, *v0, *v1, *v2, ray.tmin, ray.tmax);
                let found = (mask >> lane & 1 == 1).then(|| lanes[lane]);
                assert_eq!(found, expected, "lane {lane} of {triangles:?}, {ray:?}");
            }
            if i < grid_rays {
                // Watertight: a grid ray within [0, 2]² hits some triangle (the lanes
                // were compared above, so this checks that the cases reach hits).
                let [x, y, _] = ray.origin;
                let inside = (0.0..=2.0).contains(&x) && (0.0..=2.0).contains(&y);
                assert_eq!(mask != 0, inside, "{ray:?}");
            } else {
                random_hits += usize::from(mask != 0);
            }
        }
        assert!(random_hits > 20, "{random_hits} random rays hit");
    }

    /// [`block_pair_test`] of `blocks` against `ray`: the hit mask and each lane's hit.
    #[target_feature(enable = "avx2")]
    unsafe fn pair_avx2(blocks: &[TriangleBlock; 2], ray: &TriangleRay) -> (u32, [TriangleHit; 8]) {
        // SAFETY: AVX2 is enabled in this function.
        unsafe {
            let constants = ray_constants(ray.direction);
            let r = lanes(ray, &constants, triangle_lanes(ray, &constants));
            let (mask, hits) = block_pair_test(blocks, 0, &r.tri8, _mm256_set1_ps(ray.tmax));
            (mask, std::array::from_fn(|lane| hits.hit(lane)))
        }
    }

    #[target_feature(enable = "avx2")]
    unsafe fn row_avx2(rays: &[TriangleRay; 8]) -> RowConstants {
        // SAFETY: AVX2 is enabled in this function.
        unsafe { row_constants(std::array::from_fn(|l| &rays[l])) }
    }

    #[target_feature(enable = "avx2")]
    unsafe fn interval_avx2(tmin: f64, tmax: f64) -> [f32; 2] {
        // SAFETY: AVX2 is enabled in this function.
        unsafe { interval_f32(tmin, tmax) }
    }
}
