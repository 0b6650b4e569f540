//! Watertight ray–triangle intersection (Woop, Benthin and Wald, "Watertight Ray/Triangle
//! Intersection", JCGT 2013), in float32.
//!
//! The ray is made the +z axis of a sheared space: its largest direction component becomes
//! z, and the vertices are translated to the ray origin and sheared so the ray runs along z.
//! Whether the ray passes inside is then the sign of three 2D edge functions. An edge shared
//! by two triangles gets exactly opposite (or equal) values in both, because the same
//! products are subtracted in the opposite order, so a ray through a shared edge or vertex
//! always hits at least one of them. When an edge function is exactly zero it is recomputed
//! in float64, as the paper prescribes. Both faces are hit. The distance of a hit on a
//! thin triangle is taken on its plane instead ([`THIN_ASPECT`]).
//!
//! Consistency across triangles depends on never fusing multiply and add here: a fused
//! `a*b - c*d` is not the negation of `c*d - a*b`. Rust does not contract floating-point
//! expressions, and the SIMD kernels use separate multiplies and subtractions.

use glam::Vec3;

/// A ray prepared for the watertight test: the axis permutation and shear constants.
#[derive(Debug, Clone, Copy)]
pub struct ShearedRay {
    pub origin: [f32; 3],
    /// Axis indices: `kz` is the direction's largest component; `kx`, `ky` follow it.
    pub kx: usize,
    pub ky: usize,
    pub kz: usize,
    /// Shear constants `d[kx]/d[kz]`, `d[ky]/d[kz]` and `1/d[kz]`.
    pub sx: f32,
    pub sy: f32,
    pub sz: f32,
}

impl ShearedRay {
    /// Prepares `origin + t·direction`; `direction` must not be zero.
    #[inline(always)]
    pub fn new(origin: Vec3, direction: Vec3) -> ShearedRay {
        let d = direction.to_array();
        let abs = direction.abs();
        let kz = if abs.x > abs.y {
            if abs.x > abs.z { 0 } else { 2 }
        } else if abs.y > abs.z {
            1
        } else {
            2
        };
        let kx = (kz + 1) % 3;
        let ky = (kx + 1) % 3;
        ShearedRay {
            origin: origin.to_array(),
            kx,
            ky,
            kz,
            sx: d[kx] / d[kz],
            sy: d[ky] / d[kz],
            sz: 1.0 / d[kz],
        }
    }
}

/// Where a ray crosses a triangle: distance `t` and the barycentric weights of the three
/// vertices (`b0 + b1 + b2 = 1`, hit point `b0·v0 + b1·v1 + b2·v2`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangleHit {
    pub t: f32,
    pub b0: f32,
    pub b1: f32,
    pub b2: f32,
}

/// The watertight test for one triangle. Returns the hit when `tmin < t < tmax`.
#[inline]
pub fn intersect(
    ray: &ShearedRay,
    v0: [f32; 3],
    v1: [f32; 3],
    v2: [f32; 3],
    tmin: f32,
    tmax: f32,
) -> Option<TriangleHit> {
    let (kx, ky, kz) = (ray.kx, ray.ky, ray.kz);
    let o = ray.origin;
    // Vertices relative to the origin, sheared so the ray runs along +z.
    let (a_z, b_z, c_z) = (v0[kz] - o[kz], v1[kz] - o[kz], v2[kz] - o[kz]);
    let ax = (v0[kx] - o[kx]) - ray.sx * a_z;
    let ay = (v0[ky] - o[ky]) - ray.sy * a_z;
    let bx = (v1[kx] - o[kx]) - ray.sx * b_z;
    let by = (v1[ky] - o[ky]) - ray.sy * b_z;
    let cx = (v2[kx] - o[kx]) - ray.sx * c_z;
    let cy = (v2[ky] - o[ky]) - ray.sy * c_z;
    let (u, v, w) = edge_functions(ax, ay, bx, by, cx, cy);
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let t_scaled = u * (ray.sz * a_z) + v * (ray.sz * b_z) + w * (ray.sz * c_z);
    let t = t_scaled / det;
    if !(t > tmin && t < tmax) {
        return None;
    }
    Some(TriangleHit {
        t,
        b0: u / det,
        b1: v / det,
        b2: w / det,
    })
}

/// The three edge functions of the sheared triangle, with the paper's float64 fallback
/// when any is exactly zero (the ray through an edge or vertex in float32).
#[inline(always)]
pub fn edge_functions(ax: f32, ay: f32, bx: f32, by: f32, cx: f32, cy: f32) -> (f32, f32, f32) {
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        return edge_functions_f64(ax, ay, bx, by, cx, cy);
    }
    (u, v, w)
}

#[cold]
#[inline(never)]
pub fn edge_functions_f64(ax: f32, ay: f32, bx: f32, by: f32, cx: f32, cy: f32) -> (f32, f32, f32) {
    let [ax, ay, bx, by, cx, cy] = [ax, ay, bx, by, cx, cy].map(f64::from);
    (
        (cx * by - cy * bx) as f32,
        (ax * cy - ay * cx) as f32,
        (bx * ay - by * ax) as f32,
    )
}

/// Triangles tested together; one leaf of the tree holds one or more blocks.
pub const BLOCK: usize = 4;

/// Four triangles stored lane by lane (`v[vertex][axis][lane]`) so one ray meets all four
/// at once. A leaf's last block repeats its last triangle in unused lanes.
#[derive(Debug, Clone, Copy)]
#[repr(C, align(16))]
pub struct TriangleBlock {
    pub v: [[[f32; BLOCK]; 3]; 3],
    /// Each lane's index into the scene's triangle list (input order).
    pub ids: [u32; BLOCK],
}

impl TriangleBlock {
    /// Vertex `k` of lane `lane`.
    pub fn vertex(&self, lane: usize, k: usize) -> [f32; 3] {
        [self.v[k][0][lane], self.v[k][1][lane], self.v[k][2][lane]]
    }

    /// Tests the four lanes and records in `nearest` any hit that improves on it (see
    /// [`Nearest`]); `block` is this block's index, so lane `l` is slot `4·block + l`.
    /// Returns the improving hit, if any.
    #[inline(always)]
    pub fn intersect(
        &self,
        ray: &ShearedRay,
        tmin: f32,
        block: u32,
        nearest: &mut Nearest,
    ) -> Option<TriangleHit> {
        let mut best = None;
        for lane in 0..BLOCK {
            // `t < next_up(nearest.t)` admits the ties that `Nearest::improves` decides.
            if let Some(hit) = intersect(
                ray,
                self.vertex(lane, 0),
                self.vertex(lane, 1),
                self.vertex(lane, 2),
                tmin,
                nearest.t.next_up(),
            ) {
                let slot = block * BLOCK as u32 + lane as u32;
                if nearest.improves(hit.t, slot) {
                    *nearest = Nearest { t: hit.t, slot };
                    best = Some(hit);
                }
            }
        }
        best
    }
}

/// How far past the nearest hit so far a search still enters boxes, as a factor on its
/// distance: `1 + 64u`. A triangle's computed distance can round below its box's computed
/// entry distance (by a few units in the last place for a triangle in front of the ray, as
/// at a shared vertex or edge); without the margin a traversal that found a hit first
/// would skip such a box and miss a hit that is as near or one ulp nearer, so the answer
/// would depend on the visiting order. The cost is a few more boxes entered at distances
/// within 4·10⁻⁶ of the hit.
pub const SEARCH_MARGIN: f32 = 1.0 + 32.0 * f32::EPSILON;

/// The nearest triangle hit so far: its distance and slot (`4·block + lane` in the tree's
/// layout). Among hits at exactly the same distance the lowest slot wins, and with the
/// search horizon ([`Nearest::horizon`]) every traversal finds all of them, so the result
/// does not depend on the order in which a traversal visits the blocks: the scalar, AVX2
/// and packet paths agree bit for bit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nearest {
    pub t: f32,
    pub slot: u32,
}

impl Nearest {
    /// Nothing found yet; only hits with `t < tmax` (strictly) will improve on it.
    pub fn before(tmax: f32) -> Nearest {
        Nearest { t: tmax, slot: 0 }
    }

    /// The distance up to which boxes must still be entered: `t` widened by
    /// [`SEARCH_MARGIN`] (`t >= 0`; −∞ stays −∞ and stops the search).
    #[inline(always)]
    pub fn horizon(&self) -> f32 {
        self.t * SEARCH_MARGIN
    }

    #[inline(always)]
    pub fn improves(&self, t: f32, slot: u32) -> bool {
        t < self.t || (t == self.t && slot < self.slot)
    }
}

/// Whether a stored triangle has zero area: its edge vectors' cross product is exactly
/// zero in float64, where the differences of float32 coordinates and their products are
/// exact for any triangle whose coordinates are within 2²⁴ of each other in scale. A ray
/// can still meet such a triangle in float32 (the shear rounds its points off their
/// line), so the tree leaves these out: a triangle with no area is never hit.
pub fn is_degenerate(t: &[[f32; 3]; 3]) -> bool {
    let edge = |k: usize| [0, 1, 2].map(|axis| f64::from(t[k][axis]) - f64::from(t[0][axis]));
    let ([x1, y1, z1], [x2, y2, z2]) = (edge(1), edge(2));
    // The cross product's components one at a time: nearly every triangle is told by the
    // first, and a build asks this of every triangle (a quarter of the time `DVec3`'s
    // whole cross product took).
    y1 * z2 - z1 * y2 == 0.0 && z1 * x2 - x1 * z2 == 0.0 && x1 * y2 - y1 * x2 == 0.0
}

/// The thinnest a triangle may be, as `longest edge² / (2 · area)`, for the float32 test's
/// distance to stand; past it, a hit's distance is taken on the triangle's plane
/// ([`plane_distance`]). The float32 distance is a sum of edge functions over their sum,
/// whose rounding grows with this ratio. Over random rays at least 11.5° off the plane its
/// largest relative error was 4.3·10⁻⁷ at 16 (as at 2, a right triangle's ratio), 1·10⁻⁶ at
/// 64, 2·10⁻⁵ at 1024 and 8·10⁻⁴ at 32,768 (a probe of 100,000 rays each, not kept; a test
/// checks 16 and 1024). The scanned models of BENCHMARKS.md have at most 1.2% of their
/// triangles past 16.
pub const THIN_ASPECT: f64 = 16.0;

/// Whether `longest edge² > THIN_ASPECT · 2 · area` for a stored triangle (see
/// [`THIN_ASPECT`]), in float64. A triangle without area is thin.
pub fn is_thin(t: &[[f32; 3]; 3]) -> bool {
    let [p0, p1, p2] = t.map(|v| glam::DVec3::from_array(v.map(f64::from)));
    let (a, b) = (p1 - p0, p2 - p0);
    let longest = a
        .length_squared()
        .max(b.length_squared())
        .max((p2 - p1).length_squared());
    // Squared on both sides: `(2 · area)² = |a × b|²`.
    longest * longest > THIN_ASPECT * THIN_ASPECT * a.cross(b).length_squared()
}

/// The distance along `origin + t·direction` to the plane of the triangle `v` (its stored
/// float32 vertices), in float64: `n·(v0 − origin) / n·direction` with
/// `n = cross(v1 − v0, v2 − v0)`. Differences and products of float32 coordinates are
/// exact in float64, so `n` is the plane's normal to float64 rounding however thin the
/// triangle is. Infinite or NaN when the ray runs along the plane.
pub fn plane_distance(v: [[f32; 3]; 3], origin: glam::DVec3, direction: glam::DVec3) -> f64 {
    let [p0, p1, p2] = v.map(|v| glam::DVec3::from_array(v.map(f64::from)));
    let n = (p1 - p0).cross(p2 - p0);
    n.dot(p0 - origin) / n.dot(direction)
}

/// The unit geometric normal `normalize(cross(v1 − v0, v2 − v0))` in float64, from the
/// stored float32 vertices.
pub fn geometric_normal(v0: [f32; 3], v1: [f32; 3], v2: [f32; 3]) -> glam::DVec3 {
    let [p0, p1, p2] = [v0, v1, v2].map(|v| glam::DVec3::from_array(v.map(f64::from)));
    (p1 - p0).cross(p2 - p0).normalize()
}

/// [`geometric_normal`] of four triangles at once, each given as a block and lane, a
/// triangle per float64 lane: glam's operations in glam's order (`cross`, then `dot`,
/// square root, `1 / length` and the product; nothing fused), so each lane's bits are
/// `geometric_normal`'s. The vertices are read from the blocks themselves: copied to the
/// stack first, they were read back wider than written and waited on every copy.
///
/// # Safety
/// Only from a function with AVX enabled.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) unsafe fn geometric_normals4(
    triangles: [(&TriangleBlock, usize); 4],
) -> [glam::DVec3; 4] {
    use std::arch::x86_64::*;
    let [(b0, l0), (b1, l1), (b2, l2), (b3, l3)] = triangles;
    // SAFETY (this block): AVX is enabled in the caller; stores go to local arrays.
    unsafe {
        // Coordinate `$c` of vertex `$k` of the four triangles, widened exactly.
        macro_rules! coordinate {
            ($k:expr, $c:expr) => {
                _mm256_cvtps_pd(_mm_setr_ps(
                    b0.v[$k][$c][l0],
                    b1.v[$k][$c][l1],
                    b2.v[$k][$c][l2],
                    b3.v[$k][$c][l3],
                ))
            };
        }
        let (x0, y0, z0) = (coordinate!(0, 0), coordinate!(0, 1), coordinate!(0, 2));
        // The edges `v1 − v0` and `v2 − v0`.
        let (ax, ay, az) = (
            _mm256_sub_pd(coordinate!(1, 0), x0),
            _mm256_sub_pd(coordinate!(1, 1), y0),
            _mm256_sub_pd(coordinate!(1, 2), z0),
        );
        let (bx, by, bz) = (
            _mm256_sub_pd(coordinate!(2, 0), x0),
            _mm256_sub_pd(coordinate!(2, 1), y0),
            _mm256_sub_pd(coordinate!(2, 2), z0),
        );
        // `a.cross(b)`: (a.y·b.z − b.y·a.z, a.z·b.x − b.z·a.x, a.x·b.y − b.x·a.y).
        let cx = _mm256_sub_pd(_mm256_mul_pd(ay, bz), _mm256_mul_pd(by, az));
        let cy = _mm256_sub_pd(_mm256_mul_pd(az, bx), _mm256_mul_pd(bz, ax));
        let cz = _mm256_sub_pd(_mm256_mul_pd(ax, by), _mm256_mul_pd(bx, ay));
        // `c.normalize()`: c · (1 / sqrt((x·x + y·y) + z·z)).
        let dot = _mm256_add_pd(
            _mm256_add_pd(_mm256_mul_pd(cx, cx), _mm256_mul_pd(cy, cy)),
            _mm256_mul_pd(cz, cz),
        );
        let recip = _mm256_div_pd(_mm256_set1_pd(1.0), _mm256_sqrt_pd(dot));
        let mut n = [[0f64; 4]; 3];
        _mm256_storeu_pd(n[0].as_mut_ptr(), _mm256_mul_pd(cx, recip));
        _mm256_storeu_pd(n[1].as_mut_ptr(), _mm256_mul_pd(cy, recip));
        _mm256_storeu_pd(n[2].as_mut_ptr(), _mm256_mul_pd(cz, recip));
        std::array::from_fn(|i| glam::DVec3::new(n[0][i], n[1][i], n[2][i]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hit(origin: [f32; 3], dir: [f32; 3], tri: [[f32; 3]; 3]) -> Option<TriangleHit> {
        let ray = ShearedRay::new(Vec3::from(origin), Vec3::from(dir));
        intersect(&ray, tri[0], tri[1], tri[2], 0.0, f32::INFINITY)
    }

    const TRI: [[f32; 3]; 3] = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]];

    #[test]
    fn both_faces_are_hit_with_the_same_distance() {
        let front = hit([0.2, 0.2, 0.0], [0.0, 0.0, 1.0], TRI).unwrap();
        let back = hit([0.2, 0.2, 2.0], [0.0, 0.0, -1.0], TRI).unwrap();
        assert_eq!(front.t, 1.0);
        assert_eq!(back.t, 1.0);
    }

    #[test]
    fn distance_is_scaled_by_the_direction_not_left_in_determinant_units() {
        // obvhs' `intersect_embree` returns t·det; ours must be the distance along the
        // unit direction whatever the triangle's size and orientation.
        for scale in [1e-3f32, 1.0, 1e3] {
            let tri = TRI.map(|v| [v[0] * scale, v[1] * scale, 1.0]);
            let d = Vec3::new(0.1 * scale, 0.1 * scale, 1.0).normalize();
            let h = hit([0.0; 3], d.to_array(), tri).unwrap();
            let expected = 1.0 / f64::from(d.z);
            assert!(
                (f64::from(h.t) - expected).abs() < 1e-6 * expected,
                "{scale}"
            );
        }
    }

    #[test]
    fn barycentrics_reconstruct_the_hit_point() {
        // obvhs' `compute_barycentric` is scaled wrong; ours must give weights that put the
        // point back where the ray crosses, checked in float64.
        let tri = [[0.3f32, -0.2, 2.0], [1.7, 0.1, 2.5], [-0.4, 1.9, 3.0]];
        let origin = [0.1f32, 0.2, -1.0];
        for weights in [[0.2f32, 0.3, 0.5], [0.7, 0.1, 0.2], [0.05, 0.05, 0.9]] {
            let target: Vec<f32> = (0..3)
                .map(|i| (0..3).map(|k| weights[k] * tri[k][i]).sum())
                .collect();
            let d = (Vec3::from_slice(&target) - Vec3::from(origin)).normalize();
            let h = hit(origin, d.to_array(), tri).unwrap();
            assert!((h.b0 + h.b1 + h.b2 - 1.0).abs() < 1e-6);
            for (k, b) in [h.b0, h.b1, h.b2].into_iter().enumerate() {
                assert!(
                    (b - weights[k]).abs() < 1e-5,
                    "weight {k}: {b} vs {}",
                    weights[k]
                );
            }
            let p = |i: usize| {
                f64::from(h.b0) * f64::from(tri[0][i])
                    + f64::from(h.b1) * f64::from(tri[1][i])
                    + f64::from(h.b2) * f64::from(tri[2][i])
            };
            for i in 0..3 {
                let on_ray = f64::from(origin[i]) + f64::from(h.t) * f64::from(d[i]);
                assert!(
                    (p(i) - on_ray).abs() < 1e-5,
                    "axis {i}: {} vs {on_ray}",
                    p(i)
                );
            }
        }
    }

    #[test]
    fn an_edge_function_that_rounds_to_zero_gets_its_exact_sign() {
        // cx·by = (1 + 2⁻²³)² = 1 + 2⁻²² + 2⁻⁴⁶ rounds to 1 + 2⁻²² = cy·bx in float32, so U
        // is 0 there; in float64 it is 2⁻⁴⁶ > 0, and the ray is not on that edge.
        let e = f32::EPSILON;
        let (bx, by) = (1.0, 1.0 + e);
        let (cx, cy) = (1.0 + e, 1.0 + 2.0 * e);
        assert_eq!(cx * by - cy * bx, 0.0);
        let (u, v, w) = edge_functions(-1.0, 0.5, bx, by, cx, cy);
        assert!(u > 0.0, "{u}");
        let exact = |p: f32, q: f32, r: f32, s: f32| {
            f64::from(p) * f64::from(q) - f64::from(r) * f64::from(s)
        };
        assert_eq!(f64::from(v).signum(), exact(-1.0, cy, 0.5, cx).signum());
        assert_eq!(f64::from(w).signum(), exact(bx, 0.5, by, -1.0).signum());
    }

    #[test]
    fn the_interval_is_strict() {
        let ray = ShearedRay::new(Vec3::new(0.2, 0.2, 0.0), Vec3::Z);
        let [a, b, c] = TRI;
        assert!(intersect(&ray, a, b, c, 0.0, 1.0).is_none(), "t = tmax");
        assert!(intersect(&ray, a, b, c, 1.0, 2.0).is_none(), "t = tmin");
        assert!(intersect(&ray, a, b, c, 0.999, 1.001).is_some());
    }

    #[test]
    fn degenerate_triangles_are_never_hit() {
        let needle = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]];
        let point = [[0.5, 0.5, 1.0]; 3];
        for tri in [needle, point] {
            for origin in [[0.5, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.5, 0.0]] {
                assert!(hit(origin, [0.0, 0.0, 1.0], tri).is_none());
            }
        }
    }

    #[test]
    fn zero_area_is_told_exactly_at_every_scale() {
        // Small integer vertices, many in a line by construction, scaled by powers of two
        // (which keeps every difference and product exact): the truth is the integer cross
        // product.
        let mut random = crate::test_random::XorShift::new(11);
        let mut coordinate = || random.below(9) as i64 - 4;
        let cases = 20_000;
        let mut degenerate = 0;
        for case in 0..cases {
            let a: [i64; 3] = std::array::from_fn(|_| coordinate());
            let b: [i64; 3] = std::array::from_fn(|_| coordinate());
            // Every third triangle has its third vertex on the line through the first two.
            let c: [i64; 3] = if case % 3 == 0 {
                let k = coordinate();
                std::array::from_fn(|i| a[i] + k * (b[i] - a[i]))
            } else {
                std::array::from_fn(|_| coordinate())
            };
            let (e1, e2) = (
                [0, 1, 2].map(|i| b[i] - a[i]),
                [0, 1, 2].map(|i| c[i] - a[i]),
            );
            let truth = e1[1] * e2[2] == e1[2] * e2[1]
                && e1[2] * e2[0] == e1[0] * e2[2]
                && e1[0] * e2[1] == e1[1] * e2[0];
            for scale in [
                1.0,
                2f32.powi(-100),
                2f32.powi(-40),
                2f32.powi(30),
                2f32.powi(55),
            ] {
                let t = [a, b, c].map(|v| v.map(|x| x as f32 * scale));
                assert_eq!(is_degenerate(&t), truth, "{t:?}");
            }
            degenerate += usize::from(truth);
        }
        // Both answers are well represented.
        assert!(
            degenerate > cases / 4 && degenerate < cases / 2,
            "{degenerate} of {cases}"
        );
    }

    #[test]
    fn every_ray_through_a_shared_edge_or_vertex_hits_a_neighbour() {
        // A fan of 8 triangles around the centre of a square; rays aimed exactly at the
        // shared vertices and at points of the shared edges, from many origins.
        let centre = [0.3f32, -0.1, 2.0];
        let rim: Vec<[f32; 3]> = (0..8)
            .map(|i| {
                let a = i as f32 * std::f32::consts::TAU / 8.0 + 0.1;
                [
                    centre[0] + a.cos(),
                    centre[1] + a.sin(),
                    2.0 + 0.3 * a.sin(),
                ]
            })
            .collect();
        let tris: Vec<[[f32; 3]; 3]> = (0..8).map(|i| [centre, rim[i], rim[(i + 1) % 8]]).collect();
        // The fan is open along its rim, so only the centre and the spokes are shared.
        let mut targets = vec![centre];
        for e in &rim {
            for f in [0.1f32, 0.37, 0.5, 0.81] {
                targets.push([0, 1, 2].map(|k| centre[k] + f * (e[k] - centre[k])));
            }
        }
        let mut rays = 0;
        for target in &targets {
            for ox in -5..=5 {
                for oy in -5..=5 {
                    let origin = [ox as f32 * 0.37, oy as f32 * 0.29, -1.0];
                    let d = Vec3::from(*target) - Vec3::from(origin);
                    let ray = ShearedRay::new(Vec3::from(origin), d);
                    let hits = tris
                        .iter()
                        .filter(|t| intersect(&ray, t[0], t[1], t[2], 0.0, f32::INFINITY).is_some())
                        .count();
                    assert!(hits >= 1, "ray from {origin:?} to {target:?} leaked");
                    rays += 1;
                }
            }
        }
        assert!(rays > 3000);
    }

    /// `is_thin` against triangles whose ratio is known exactly: a base of length 1 with
    /// its apex over the middle at height `h` has `longest² / (2 · area) = 1 / h`, a right
    /// triangle with unit legs 2. At every scale from 2⁻⁴⁰ to 2⁴⁰, with every vertex first
    /// and the base along each axis.
    #[test]
    fn thin_is_longest_edge_squared_over_twice_the_area_past_the_limit() {
        let cases: [(f32, f32, bool); 5] = [
            // (apex x, apex height, thin)
            (0.0, 1.0, false),
            (0.5, 0.125, false),
            (0.5, 1.0 / THIN_ASPECT as f32, false),
            (0.5, 1.0 / (2.0 * THIN_ASPECT as f32), true),
            (0.5, 1e-6, true),
        ];
        for (apex, height, thin) in cases {
            for exponent in (-40..=40).step_by(8) {
                let scale = 2f32.powi(exponent);
                for axis in 0..3 {
                    // The base along `axis`, the height along the next one.
                    let at = |along: f32, up: f32| {
                        let mut v = [0.0; 3];
                        v[axis] = along * scale;
                        v[(axis + 1) % 3] = up * scale;
                        v
                    };
                    let t = [at(0.0, 0.0), at(1.0, 0.0), at(apex, height)];
                    for first in 0..3 {
                        let turned = [t[first], t[(first + 1) % 3], t[(first + 2) % 3]];
                        assert_eq!(is_thin(&turned), thin, "{turned:?}");
                    }
                }
            }
        }
    }

    /// Why [`THIN_ASPECT`] is where it is: over random triangles and rays at least 11.5°
    /// off their planes, the float32 test's distance stays within 10⁻⁶ of float64
    /// Möller–Trumbore's up to that ratio, and goes past it on thinner triangles, where
    /// `plane_distance` stays within 10⁻¹¹.
    #[test]
    fn the_float32_distance_holds_up_to_the_thin_limit_and_the_planes_past_it() {
        let mut random = crate::test_random::XorShift::new(0x7417);
        let vector = |random: &mut crate::test_random::XorShift| {
            glam::DVec3::from_array([0; 3].map(|_| f64::from(random.unit_f32()) - 0.5))
        };
        for (aspect, float32_within) in [(2.0, true), (THIN_ASPECT, true), (1024.0, false)] {
            let (mut float32_worst, mut plane_worst) = (0f64, 0f64);
            for _ in 0..20_000 {
                // A base of length 1 along `a`, the apex `1 / aspect` off it along `b`.
                let a = vector(&mut random).normalize();
                let b = vector(&mut random).reject_from(a).normalize();
                let corner = vector(&mut random) * 20.0;
                let along = f64::from(random.unit_f32());
                let t = [corner, corner + a, corner + a * along + b / aspect]
                    .map(|v| v.as_vec3().to_array());
                let [p0, p1, p2] = t.map(|v| glam::DVec3::from_array(v.map(f64::from)));
                let normal = (p1 - p0).cross(p2 - p0).normalize();
                let (u, v) = (f64::from(random.unit_f32()), f64::from(random.unit_f32()));
                let (u, v) = if u + v > 1.0 {
                    (1.0 - u, 1.0 - v)
                } else {
                    (u, v)
                };
                let target = p0 + (p1 - p0) * u + (p2 - p0) * v;
                let direction = loop {
                    let d = vector(&mut random).normalize();
                    if d.dot(normal).abs() >= 0.2 {
                        break d.as_vec3();
                    }
                };
                let distance = 1.0 + 20.0 * f64::from(random.unit_f32());
                let origin = (target - direction.as_dvec3() * distance).as_vec3();
                let ray = ShearedRay::new(origin, direction);
                let Some(hit) = intersect(&ray, t[0], t[1], t[2], 0.0, f32::INFINITY) else {
                    continue;
                };
                // Float64 Möller–Trumbore on the stored vertices and the float32 ray.
                let (o, d) = (origin.as_dvec3(), direction.as_dvec3());
                let (e1, e2) = (p1 - p0, p2 - p0);
                let q = (o - p0).cross(e1);
                let exact = e2.dot(q) / e1.dot(d.cross(e2));
                let error = |t: f64| (t - exact).abs() / exact;
                float32_worst = float32_worst.max(error(f64::from(hit.t)));
                plane_worst = plane_worst.max(error(plane_distance(t, o, d)));
            }
            assert_eq!(
                float32_worst <= 1e-6,
                float32_within,
                "{aspect}: {float32_worst:e}"
            );
            assert!(plane_worst <= 1e-11, "{aspect}: {plane_worst:e}");
        }
    }

    /// Four triangles at a time must give `geometric_normal`'s bits in every lane: random
    /// triangles at scales from 2⁻⁶⁰ to 2⁶⁰, slivers, and degenerate ones (a repeated
    /// vertex or all three in a line, whose normal is NaN either way).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn normals_four_at_a_time_are_geometric_normal_bit_for_bit() {
        #[target_feature(enable = "avx")]
        unsafe fn four(triangles: [(&TriangleBlock, usize); 4]) -> [glam::DVec3; 4] {
            // SAFETY: AVX is enabled here.
            unsafe { geometric_normals4(triangles) }
        }
        if !std::arch::is_x86_feature_detected!("avx") {
            eprintln!("skipped: this CPU has no AVX, and the four-lane normals are not used");
            return;
        }
        let mut random = crate::test_random::XorShift::new(0x5eed_4041);
        let (mut finite, mut nan) = (0, 0);
        for case in 0..50_000 {
            let scale = 2f32.powi(random.below(121) as i32 - 60);
            let point = |random: &mut crate::test_random::XorShift| {
                [0; 3].map(|_| (random.unit_f32() - 0.5) * scale)
            };
            let triangles: [[[f32; 3]; 3]; 4] = std::array::from_fn(|_| {
                let [a, b, c] = [point(&mut random), point(&mut random), point(&mut random)];
                match random.below(8) {
                    // A repeated vertex.
                    0 => [a, b, a],
                    // Three points in a line: b halfway between a and c where exact.
                    1 => [a, std::array::from_fn(|i| a[i] + (c[i] - a[i]) * 0.5), c],
                    // A sliver: c one step from b.
                    2 => [a, b, b.map(|x| f32::from_bits(x.to_bits() + 1))],
                    _ => [a, b, c],
                }
            });
            // The four in one block, in lanes taken in a rotated order.
            let mut block = TriangleBlock {
                v: [[[0.0; BLOCK]; 3]; 3],
                ids: [0; BLOCK],
            };
            let lane_of = |i: usize| (i + case) % BLOCK;
            for (i, t) in triangles.iter().enumerate() {
                for (k, vertex) in t.iter().enumerate() {
                    for (c, &x) in vertex.iter().enumerate() {
                        block.v[k][c][lane_of(i)] = x;
                    }
                }
            }
            // SAFETY: the CPU has AVX (checked above).
            let lanes = unsafe { four(std::array::from_fn(|i| (&block, lane_of(i)))) };
            for (lane, (t, n)) in triangles.iter().zip(lanes).enumerate() {
                let expected = geometric_normal(t[0], t[1], t[2]);
                let bits = |v: glam::DVec3| v.to_array().map(f64::to_bits);
                assert_eq!(bits(n), bits(expected), "case {case}, lane {lane}: {t:?}");
                finite += usize::from(expected.is_finite());
                nan += usize::from(expected.is_nan());
            }
        }
        assert!(
            finite > 120_000 && nan > 20_000,
            "{finite} finite, {nan} NaN"
        );
    }
}
