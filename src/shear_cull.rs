//! Which triangles of a leaf every ray of a packet surely misses, decided once per
//! triangle from the range of the rays' shears instead of once per ray.
//!
//! The watertight test ([`crate::simd`]'s `watertight_test!`, [`crate::triangle`])
//! moves a triangle into each ray's sheared frame, in which the ray is the `z` axis: a
//! vertex `v` becomes `x' = (v[kx] − o[kx]) − sx · (v[kz] − o[kz])` (and `y'` with `ky`,
//! `sy`), each operation rounded to float32. Its edge functions then decide exactly on
//! those rounded points: a float32 product difference never takes the sign opposite to
//! the exact one, and an exact zero is recomputed in float64. So a ray hits only if the
//! origin of its frame lies in the closed triangle of its rounded sheared vertices, and
//! it misses whenever all three `x'` (or all three `y'`) are of one strict sign.
//!
//! For rays that share their origin and their axes `k`, `x'` depends on the ray only
//! through `sx`, and monotonically (every operation is, and rounding is monotonic). The
//! same operations at the smallest and the largest `sx` of the rays therefore bound every
//! ray's own `x'`: where both are positive (or both negative) for each vertex, every ray
//! misses. No margin is needed, and a triangle this leaves out is one that each ray's own
//! test would have missed, so packets still find bit for bit what single rays find. A
//! NaN in a ray's own arithmetic makes it miss; one in the bounds makes the comparisons
//! false, which keeps the triangle.

use std::arch::x86_64::*;

use crate::triangle::{BLOCK, TriangleBlock};

/// The shared frame of a packet's rays and the range of their shears, as the
/// watertight test uses them (`simd::ray_constants`).
#[derive(Debug, Clone, Copy)]
pub(crate) struct ShearCull {
    /// The axes `[kx, ky, kz]` of every ray.
    axes: [usize; 3],
    /// The rays' common origin, on the world's axes.
    origin: [f32; 3],
    /// The smallest and largest `sx` over the rays, and of `sy`.
    sx: (f32, f32),
    sy: (f32, f32),
}

impl ShearCull {
    /// For rays that all start at `origin` and share the axes `axes`, with every ray's
    /// `sx` in `sx.0 ..= sx.1` and `sy` in `sy.0 ..= sy.1`.
    pub(crate) fn new(
        axes: [usize; 3],
        origin: [f32; 3],
        sx: (f32, f32),
        sy: (f32, f32),
    ) -> ShearCull {
        ShearCull {
            axes,
            origin,
            sx,
            sy,
        }
    }

    /// A bit per lane of `block` (bit `l` for lane `l`) whose triangle every ray misses.
    ///
    /// # Safety
    /// Only from a function with AVX2 enabled.
    #[inline(always)]
    pub(crate) unsafe fn missed(&self, block: &TriangleBlock) -> u32 {
        // SAFETY (this block): a block's lane arrays are 16 bytes at multiples of 16;
        // SSE is part of x86-64, and AVX2 is enabled in the caller.
        unsafe {
            let [kx, ky, kz] = self.axes;
            let relative = |v: usize, axis: usize| {
                _mm_sub_ps(
                    _mm_load_ps(block.v[v][axis].as_ptr()),
                    _mm_set1_ps(self.origin[axis]),
                )
            };
            let zero = _mm_setzero_ps();
            let all = _mm_castsi128_ps(_mm_set1_epi32(-1));
            // Lanes whose vertices so far all lie at x' > 0, at x' < 0, y' > 0, y' < 0 for
            // every shear in the range.
            let mut side = [all; 4];
            for v in 0..3 {
                let z = relative(v, kz);
                for (i, (axis, (lo, hi))) in [(kx, self.sx), (ky, self.sy)].into_iter().enumerate()
                {
                    let a = relative(v, axis);
                    let at_lo = _mm_sub_ps(a, _mm_mul_ps(_mm_set1_ps(lo), z));
                    let at_hi = _mm_sub_ps(a, _mm_mul_ps(_mm_set1_ps(hi), z));
                    let above = _mm_and_ps(
                        _mm_cmp_ps::<_CMP_GT_OQ>(at_lo, zero),
                        _mm_cmp_ps::<_CMP_GT_OQ>(at_hi, zero),
                    );
                    let below = _mm_and_ps(
                        _mm_cmp_ps::<_CMP_LT_OQ>(at_lo, zero),
                        _mm_cmp_ps::<_CMP_LT_OQ>(at_hi, zero),
                    );
                    side[2 * i] = _mm_and_ps(side[2 * i], above);
                    side[2 * i + 1] = _mm_and_ps(side[2 * i + 1], below);
                }
            }
            let either = _mm_or_ps(_mm_or_ps(side[0], side[1]), _mm_or_ps(side[2], side[3]));
            _mm_movemask_ps(either) as u32 & ((1 << BLOCK) - 1)
        }
    }

    /// [`ShearCull::missed`] for each block of a leaf, four bits per block from bit 0
    /// (a leaf holds at most sixteen blocks).
    ///
    /// # Safety
    /// As for [`ShearCull::missed`].
    #[inline(always)]
    pub(crate) unsafe fn missed_in(&self, blocks: &[TriangleBlock]) -> u64 {
        debug_assert!(blocks.len() * BLOCK <= 64);
        let mut missed = 0;
        for (b, block) in blocks.iter().enumerate() {
            // SAFETY: as required of the caller.
            missed |= u64::from(unsafe { self.missed(block) }) << (b * BLOCK);
        }
        missed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_random::XorShift;
    use crate::triangle::{ShearedRay, intersect};
    use glam::Vec3;

    /// A random float32 `x` moved by up to `steps` units in the last place either way.
    fn nudged(random: &mut XorShift, x: f32, steps: u64) -> f32 {
        let mut x = x;
        for _ in 0..random.below(steps + 1) {
            x = if random.below(2) == 0 {
                x.next_up()
            } else {
                x.next_down()
            };
        }
        x
    }

    #[test]
    fn a_triangle_left_out_is_missed_by_every_ray_and_most_far_ones_are_left_out() {
        if !crate::simd::available() {
            return;
        }
        let mut random = XorShift::new(0x5eed_c011);
        let (mut hit_by_some, mut beside_tile, mut left_out_beside) = (0u32, 0u32, 0u32);
        for case in 0..600 {
            // A pinhole's 8 × 8 tile, at every scale and distance from the world's origin.
            let scale = 10f32.powi(random.below(9) as i32 - 3);
            let origin = Vec3::from_array(std::array::from_fn(|_| {
                (random.unit_f32() - 0.5) * scale * 10f32.powi(random.below(4) as i32)
            }));
            let forward = loop {
                let v = Vec3::from_array(std::array::from_fn(|_| random.unit_f32() - 0.5));
                if v.length() > 0.1 {
                    break v.normalize();
                }
            };
            let right = forward.any_orthonormal_vector();
            let up = forward.cross(right);
            let spread = 10f32.powi(-(random.below(4) as i32) - 1);
            let directions: Vec<Vec3> = (0..64)
                .map(|k| {
                    let (i, j) = ((k % 8) as f32 - 3.5, (k / 8) as f32 - 3.5);
                    forward + (i * right + j * up) * spread
                })
                .collect();
            let rays: Vec<ShearedRay> = directions
                .iter()
                .map(|&d| ShearedRay::new(origin, d))
                .collect();
            let axes = [rays[0].kx, rays[0].ky, rays[0].kz];
            if rays.iter().any(|r| [r.kx, r.ky, r.kz] != axes) {
                continue;
            }
            let range = |s: fn(&ShearedRay) -> f32| {
                rays.iter()
                    .map(s)
                    .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), x| {
                        (lo.min(x), hi.max(x))
                    })
            };
            let cull = ShearCull::new(axes, origin.to_array(), range(|r| r.sx), range(|r| r.sy));
            for _ in 0..8 {
                // Triangles through the tile: vertices on or a few units in the last place
                // off its rays (the corner rays most often, whose shears bound the
                // range), or anywhere over it, and now and then at the origin itself,
                // which every ray passes.
                let through = |random: &mut XorShift| -> [f32; 3] {
                    match random.below(8) {
                        0 => origin.to_array(),
                        1 | 2 => {
                            let (i, j) = (random.unit_f32() - 0.5, random.unit_f32() - 0.5);
                            let d = forward + (i * right + j * up) * 10.0 * spread;
                            (origin + d * scale * (0.2 + random.unit_f32())).to_array()
                        }
                        pick => {
                            let k = if pick < 5 {
                                [0, 7, 56, 63][random.below(4) as usize]
                            } else {
                                random.below(64) as usize
                            };
                            let t = scale * (0.2 + random.unit_f32());
                            let p = origin + directions[k] * t;
                            p.to_array().map(|x| nudged(random, x, 3))
                        }
                    }
                };
                // Triangles wholly to one side of the range of shears: every vertex at a
                // slope past it on one axis, from a hundredth of the rays' spacing to ten
                // spacings (where rounding leaves the decision to the rays' own tests, a
                // few may stay).
                let (sx, sy) = (cull.sx, cull.sy);
                let dz = forward[axes[2]].signum();
                let (axis, high) = (random.below(2) as usize, random.below(2) == 0);
                let beside = |random: &mut XorShift| -> [f32; 3] {
                    let (range, other) = if axis == 0 { (sx, sy) } else { (sy, sx) };
                    let spacing = (range.1 - range.0) / 7.0;
                    let gap = (0.01 + 10.0 * random.unit_f32()) * spacing;
                    let slope = if high { range.1 + gap } else { range.0 - gap };
                    let width = other.1 - other.0;
                    let across = other.0 + (random.unit_f32() * 3.0 - 1.0) * width;
                    let mut d = [0.0; 3];
                    d[axes[axis]] = slope * dz;
                    d[axes[1 - axis]] = across * dz;
                    d[axes[2]] = dz;
                    let t = scale * (0.2 + random.unit_f32());
                    (origin + Vec3::from_array(d) * t).to_array()
                };
                let outside = random.below(2) == 0;
                let triangles: [[[f32; 3]; 3]; BLOCK] = std::array::from_fn(|_| {
                    std::array::from_fn(|_| {
                        if outside {
                            beside(&mut random)
                        } else {
                            through(&mut random)
                        }
                    })
                });
                let block = TriangleBlock {
                    v: std::array::from_fn(|v| {
                        std::array::from_fn(|a| std::array::from_fn(|l| triangles[l][v][a]))
                    }),
                    ids: [0, 1, 2, 3],
                };
                // SAFETY: AVX2 is available (checked above).
                let missed = unsafe { cull.missed(&block) };
                for (l, [v0, v1, v2]) in triangles.into_iter().enumerate() {
                    let hit = rays.iter().any(|ray| {
                        intersect(ray, v0, v1, v2, f32::NEG_INFINITY, f32::INFINITY).is_some()
                    });
                    assert!(
                        missed >> l & 1 == 0 || !hit,
                        "case {case}: triangle {l} {:?} left out but hit",
                        [v0, v1, v2]
                    );
                    hit_by_some += u32::from(hit);
                    if outside {
                        beside_tile += 1;
                        left_out_beside += missed >> l & 1;
                    }
                }
            }
        }
        // Not vacuous: many triangles are hit, and nearly all beside the range left out.
        assert!(hit_by_some > 2000, "{hit_by_some} hit");
        assert!(
            left_out_beside * 100 > beside_tile * 99,
            "{left_out_beside} of {beside_tile} triangles beside the range left out"
        );
    }
}
