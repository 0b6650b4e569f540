//! The packet's leaf kernels sixteen rays wide, for CPUs with AVX-512: a leaf's box and
//! one triangle against two rows of a packet at once ([`crate::packet`]). The same
//! macros as the AVX2 kernels ([`crate::simd`]) with 512-bit intrinsics, so the same IEEE
//! operations in the same order in every lane, bit-identical to the scalar tests;
//! comparisons give mask registers, which the macros combine and read as bit masks.
//!
//! Like those of `simd`, the helpers here are `#[inline(always)] unsafe fn` without
//! `#[target_feature]`: they are called only from the AVX-512 traversal, into which they
//! and their intrinsics inline.

use std::arch::x86_64::*;

use crate::packet::GroupLanes;
use crate::simd::{Hits, TriLanes, exact_edge_lanes, slab_test, watertight_test};
use crate::triangle::TriangleBlock;

/// Whether this CPU can run the sixteen-lane kernels (AVX-512 Foundation; the packet
/// traversal around them needs what [`crate::simd::available`] checks as well).
pub fn available() -> bool {
    is_x86_feature_detected!("avx512f") && crate::simd::available()
}

/// A float32 at `p` in all sixteen lanes.
///
/// # Safety
/// `p` must be valid to read; only from a function with AVX-512F enabled.
#[inline(always)]
unsafe fn broadcast(p: *const f32) -> __m512 {
    // SAFETY: as required of the caller.
    unsafe { _mm512_set1_ps(*p) }
}

/// Mask registers combined as the macros combine comparison results.
#[inline(always)]
fn and(a: __mmask16, b: __mmask16) -> __mmask16 {
    a & b
}

#[inline(always)]
fn or(a: __mmask16, b: __mmask16) -> __mmask16 {
    a | b
}

/// A mask register as the lane bits `movemask` gives for narrower vectors.
#[inline(always)]
fn bits(mask: __mmask16) -> u32 {
    u32::from(mask)
}

/// The leaf box in `slot` of the node whose planes start at `planes`, against sixteen
/// rays (`r`, a ray per lane): a bit per ray entering it with `tmin <= t <= tmax`, as
/// [`slab_test!`] decides for each.
///
/// # Safety
/// `planes` must be a node's planes and `slot` below its width; only from a function
/// with AVX-512F enabled.
#[inline(always)]
pub(crate) unsafe fn leaf_box_test(
    r: &GroupLanes<__m512>,
    planes: *const f32,
    slot: usize,
    tmin: __m512,
    tmax: __m512,
) -> u32 {
    // SAFETY: as required of the caller.
    unsafe {
        let (_, entered) = slab_test! { r, planes, slot, tmin, tmax,
        broadcast, _mm512_sub_ps, _mm512_mul_ps, _mm512_max_ps, _mm512_min_ps,
        _mm512_cmp_ps_mask };
        bits(entered)
    }
}

/// The watertight test of triangle `lane` of `block` against sixteen rays (which share
/// the axes `k`): a bit per ray with `tmin < t < tmax`, and the rays' values, as
/// [`crate::simd::row_test`] gives them for eight.
///
/// # Safety
/// `lane` must be below [`crate::triangle::BLOCK`]; only from a function with AVX-512F
/// enabled.
#[inline(always)]
pub(crate) unsafe fn row_test(
    block: &TriangleBlock,
    lane: usize,
    r: &TriLanes<__m512>,
    tmax: __m512,
) -> (u32, Hits<__m512>) {
    // SAFETY: as required of the caller.
    unsafe {
        let vertex = |v: usize, axis: usize| _mm512_set1_ps(block.v[v][axis][lane]);
        watertight_test! { r, vertex, tmax, exact_edges,
        _mm512_setzero_ps, _mm512_sub_ps, _mm512_mul_ps, _mm512_add_ps, _mm512_div_ps,
        and, or, _mm512_min_ps, _mm512_max_ps, _mm512_cmp_ps_mask, bits }
    }
}

/// The sixteen lanes of `x`.
///
/// # Safety
/// Only from a function with AVX-512F enabled.
#[inline(always)]
pub(crate) unsafe fn lanes16(x: __m512) -> [f32; 16] {
    let mut out = [0f32; 16];
    // SAFETY: `out` holds sixteen floats; AVX-512F is enabled in the caller.
    unsafe { _mm512_storeu_ps(out.as_mut_ptr(), x) };
    out
}

/// The float64 recomputation of the edge functions in the lanes of `on_edge`
/// (`crate::simd`'s `exact_edges` for sixteen lanes).
///
/// # Safety
/// The CPU must support AVX-512F.
#[cold]
#[inline(never)]
#[target_feature(enable = "avx512f")]
unsafe fn exact_edges(
    on_edge: __mmask16,
    sheared: [__m512; 6],
    (u, v, w): (__m512, __m512, __m512),
) -> (__m512, __m512, __m512) {
    // SAFETY: AVX-512F is enabled in this function.
    let lanes = |x| unsafe { lanes16(x) };
    let (u, v, w) = exact_edge_lanes(bits(on_edge), sheared.map(lanes), [u, v, w].map(lanes));
    // SAFETY: each array holds sixteen floats.
    unsafe {
        (
            _mm512_loadu_ps(u.as_ptr()),
            _mm512_loadu_ps(v.as_ptr()),
            _mm512_loadu_ps(w.as_ptr()),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_random::XorShift;
    use crate::triangle::{BLOCK, ShearedRay, TriangleHit, intersect};
    use glam::Vec3;

    #[test]
    fn the_row_test_matches_the_scalar_test_lane_by_lane() {
        if !available() {
            eprintln!("this CPU has no AVX-512: the sixteen-lane kernels do not run here");
            return;
        }
        let mut random = XorShift::new(16);
        let coordinate = |random: &mut XorShift, scale: f32| random.unit_f32() * scale;
        let (mut hits, mut on_edges, mut fallbacks) = (0, 0, 0);
        // Whether float32 and float64 disagree on an edge function's sign (zero or not).
        let falls_back = |ray: &ShearedRay, v: &[[f32; 3]; 3]| {
            let sheared = v.map(|p| {
                let z = p[ray.kz] - ray.origin[ray.kz];
                let x = (p[ray.kx] - ray.origin[ray.kx]) - ray.sx * z;
                let y = (p[ray.ky] - ray.origin[ray.ky]) - ray.sy * z;
                (x, y)
            });
            let [(ax, ay), (bx, by), (cx, cy)] = sheared;
            let single = [cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax];
            let (u, v, w) = crate::triangle::edge_functions_f64(ax, ay, bx, by, cx, cy);
            single
                .iter()
                .zip([u, v, w])
                .any(|(s, d)| *s == 0.0 && d != 0.0)
        };
        for round in 0..4_000 {
            // Triangles on an integer grid in the plane z = 5, met by rays along +z from
            // integer points (whose edge functions are exactly zero on an edge), or random
            // triangles met by random rays along z, some aimed at their vertices and edges
            // (where a float32 edge function may round to zero and the float64 fallback
            // decides).
            let grid = round % 3 == 0;
            let v: [[f32; 3]; 3] = std::array::from_fn(|_| {
                if grid {
                    [random.below(5) as f32, random.below(5) as f32, 5.0]
                } else {
                    [
                        coordinate(&mut random, 4.0),
                        coordinate(&mut random, 4.0),
                        4.0 + coordinate(&mut random, 2.0),
                    ]
                }
            });
            let block = TriangleBlock {
                v: std::array::from_fn(|k| std::array::from_fn(|axis| [v[k][axis]; BLOCK])),
                ids: [0; BLOCK],
            };
            let rays: [ShearedRay; 16] = std::array::from_fn(|_| {
                let (origin, direction) = if grid {
                    let o = [random.below(5) as f32, random.below(5) as f32, 0.0];
                    (o, [0.0, 0.0, 1.0])
                } else if round % 3 == 1 {
                    let o = [0; 3].map(|_| coordinate(&mut random, 4.0));
                    let d = [
                        coordinate(&mut random, 0.5) - 0.25,
                        coordinate(&mut random, 0.5) - 0.25,
                        1.0,
                    ];
                    (o, d)
                } else {
                    let o = [
                        coordinate(&mut random, 4.0),
                        coordinate(&mut random, 4.0),
                        -2.0 - coordinate(&mut random, 2.0),
                    ];
                    let (a, b) = (random.below(3) as usize, random.below(3) as usize);
                    let s = random.below(5) as f32 / 4.0;
                    let target: [f32; 3] =
                        std::array::from_fn(|i| v[a][i] + s * (v[b][i] - v[a][i]));
                    (o, std::array::from_fn(|i| target[i] - o[i]))
                };
                ShearedRay::new(Vec3::from(origin), Vec3::from(direction))
            });
            let (tmin, tmax) = (0.5, 4.0 + coordinate(&mut random, 4.0));
            let lanes = |f: &dyn Fn(&ShearedRay) -> f32| {
                let values: [f32; 16] = std::array::from_fn(|l| f(&rays[l]));
                // SAFETY: sixteen floats.
                unsafe { _mm512_loadu_ps(values.as_ptr()) }
            };
            let row = TriLanes {
                kx: rays[0].kx,
                ky: rays[0].ky,
                kz: rays[0].kz,
                origin_k: [rays[0].kx, rays[0].ky, rays[0].kz]
                    .map(|axis| lanes(&|r| r.origin[axis])),
                sx: lanes(&|r| r.sx),
                sy: lanes(&|r| r.sy),
                sz: lanes(&|r| r.sz),
                tmin: lanes(&|_| tmin),
            };
            // SAFETY: AVX-512F is available (checked above).
            let (mask, found) = unsafe { row_test_avx512(&block, &row, lanes(&|_| tmax)) };
            for (l, ray) in rays.iter().enumerate() {
                assert_eq!([ray.kx, ray.ky, ray.kz], [row.kx, row.ky, row.kz]);
                let expected = intersect(ray, v[0], v[1], v[2], tmin, tmax);
                let why = format!("lane {l}: {v:?}, {ray:?}");
                assert_eq!(mask >> l & 1 == 1, expected.is_some(), "{why}");
                fallbacks += usize::from(falls_back(ray, &v));
                if let Some(expected) = expected {
                    // SAFETY: as above.
                    let hit = unsafe { hit_avx512(&found, l) };
                    let bits = |h: TriangleHit| [h.t, h.b0, h.b1, h.b2].map(f32::to_bits);
                    assert_eq!(bits(hit), bits(expected), "{why}");
                    hits += 1;
                    on_edges += usize::from([hit.b0, hit.b1, hit.b2].contains(&0.0));
                }
            }
        }
        assert!(
            hits > 5_000 && on_edges > 1_000 && fallbacks > 100,
            "{hits} hits, {on_edges} on edges, {fallbacks} decided in float64"
        );
    }

    #[target_feature(enable = "avx512f")]
    unsafe fn row_test_avx512(
        block: &TriangleBlock,
        row: &TriLanes<__m512>,
        tmax: __m512,
    ) -> (u32, Hits<__m512>) {
        // SAFETY: AVX-512F is enabled in this function; lane 0 is below `BLOCK`.
        unsafe { row_test(block, 0, row, tmax) }
    }

    #[target_feature(enable = "avx512f")]
    unsafe fn hit_avx512(found: &Hits<__m512>, lane: usize) -> TriangleHit {
        // SAFETY: AVX-512F is enabled in this function.
        found.hit_in(|x| unsafe { lanes16(x) }[lane])
    }
}
