//! The camera: the contract's exact mapping from pixel samples to rays, in float64.
//!
//! ```json
//! {"origin": [0, 0, 0], "right": [1, 0, 0], "up": [0, 1, 0], "forward": [0, 0, 1]}
//! {"look_from": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "vfov": 90}
//! {"look_from": [0, 0, 5], "look_at": [0, 0, 0], "aperture": 0.1, "focus_distance": 5}
//! ```
//!
//! Both forms reduce to a [`CameraFrame`]. For pixel `(x, y)` of a `W × H` image and an
//! offset `(sx, sy)` in `[0, 1)²`:
//!
//! ```text
//! u = (W / H) * (2 * (x + sx) / W - 1)
//! v = 1 - 2 * (y + sy) / H
//! direction = normalize(u * right + v * up + forward)
//! ```

use glam::DVec3;

use crate::manifest::CameraDesc;
use crate::ray::Ray;

/// The basis camera: vectors used as given (their lengths zoom the film).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraFrame {
    pub origin: DVec3,
    pub right: DVec3,
    pub up: DVec3,
    pub forward: DVec3,
}

/// A thin lens: a uniform disk of `radius` (the manifest's `aperture`) focused at
/// `focus_distance` along the view direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThinLens {
    pub radius: f64,
    pub focus_distance: f64,
}

/// The frame of a look-at camera, or `None` when `up` is parallel to the view direction.
/// `vfov` is the vertical field of view in degrees; the image's right is
/// `cross(forward, up)` (OpenGL's `gluLookAt` handedness).
pub fn look_at_frame(from: DVec3, at: DVec3, up: DVec3, vfov: f64) -> Option<CameraFrame> {
    let forward = (at - from).normalize();
    let side = forward.cross(up);
    if side.length() == 0.0 || !side.is_finite() {
        return None;
    }
    let half_height = (vfov.to_radians() / 2.0).tan();
    let right = side.normalize() * half_height;
    let true_up = right.normalize().cross(forward) * half_height;
    Some(CameraFrame {
        origin: from,
        right,
        up: true_up,
        forward,
    })
}

/// A camera bound to an image size.
#[derive(Debug, Clone, Copy)]
pub struct Camera {
    frame: CameraFrame,
    width: f64,
    height: f64,
    lens: Option<Lens>,
}

#[derive(Debug, Clone, Copy)]
struct Lens {
    radius: f64,
    focus_distance: f64,
    /// Unit vectors spanning the lens disk, and the unit view direction.
    lens_x: DVec3,
    lens_y: DVec3,
    axis: DVec3,
}

impl Camera {
    pub fn new(desc: &CameraDesc, width: u32, height: u32) -> Camera {
        let frame = desc.frame;
        let lens = desc.lens.map(|lens| Lens {
            radius: lens.radius,
            focus_distance: lens.focus_distance,
            lens_x: frame.right.normalize(),
            lens_y: frame.up.normalize(),
            axis: frame.forward.normalize(),
        });
        Camera {
            frame,
            width: f64::from(width),
            height: f64::from(height),
            lens,
        }
    }

    /// Whether rays depend on a lens sample (see [`Camera::ray`]).
    pub fn has_lens(&self) -> bool {
        self.lens.is_some()
    }

    /// The ray through offset `(sx, sy)` of pixel `(x, y)`. `lens` is a point of `[0, 1)²`
    /// mapped onto the lens disk; a pinhole camera ignores it, and `(0.5, 0.5)` is the
    /// lens centre.
    #[inline]
    pub fn ray(&self, x: u32, y: u32, sx: f64, sy: f64, lens: (f64, f64)) -> Ray {
        self.ray_at(self.screen_u(x, sx), self.screen_v(y, sy), lens)
    }

    /// The horizontal screen coordinate `u` of offset `sx` in column `x`.
    #[inline]
    pub fn screen_u(&self, x: u32, sx: f64) -> f64 {
        let (w, h) = (self.width, self.height);
        (w / h) * (2.0 * (f64::from(x) + sx) / w - 1.0)
    }

    /// The vertical screen coordinate `v` of offset `sy` in row `y`.
    #[inline]
    pub fn screen_v(&self, y: u32, sy: f64) -> f64 {
        1.0 - 2.0 * (f64::from(y) + sy) / self.height
    }

    /// The ray through screen coordinates `(u, v)` ([`Camera::screen_u`],
    /// [`Camera::screen_v`]); `lens` as for [`Camera::ray`].
    #[inline]
    pub fn ray_at(&self, u: f64, v: f64, lens: (f64, f64)) -> Ray {
        let f = &self.frame;
        let direction = (u * f.right + v * f.up + f.forward).normalize();
        let mut ray = Ray {
            origin: f.origin,
            direction,
            tmin: 0.0,
            tmax: f64::INFINITY,
        };
        if let Some(l) = &self.lens {
            let (dx, dy) = concentric_disk(lens.0, lens.1);
            let focus = f.origin + direction * (l.focus_distance / direction.dot(l.axis));
            let origin = f.origin + l.radius * (dx * l.lens_x + dy * l.lens_y);
            ray.origin = origin;
            ray.direction = (focus - origin).normalize();
        }
        ray
    }

    /// The rays of a pinhole camera through screen coordinates `(u[i], v[i])`, into
    /// `out[i]`: bit for bit the rays of [`Camera::ray_at`] (lens sample at the centre),
    /// computed four at a time with AVX where the CPU has it, so that four rays share each
    /// square root and division.
    pub fn pinhole_rays(&self, u: &[f64], v: &[f64], out: &mut [Ray]) {
        assert!(u.len() == out.len() && v.len() == out.len());
        #[cfg(target_arch = "x86_64")]
        let done = if self.lens.is_none() && std::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU has AVX.
            unsafe { self.pinhole_rays_avx(u, v, out) }
        } else {
            0
        };
        #[cfg(not(target_arch = "x86_64"))]
        let done = 0;
        for ((ray, &u), &v) in out[done..].iter_mut().zip(&u[done..]).zip(&v[done..]) {
            *ray = self.ray_at(u, v, crate::sampler::CENTER);
        }
    }

    /// The rays of [`Camera::pinhole_rays`] for the whole groups of four, and how many that
    /// is: glam's operations in glam's order, none fused, so the same bits as
    /// [`Camera::ray_at`]. Each direction is stored straight from the vector registers
    /// (reading the lanes back from memory stalled every ray on store forwarding).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn pinhole_rays_avx(&self, u: &[f64], v: &[f64], out: &mut [Ray]) -> usize {
        use std::arch::x86_64::*;
        let f = &self.frame;
        let lanes = |r: f64, up: f64, forward: f64| {
            (
                _mm256_set1_pd(r),
                _mm256_set1_pd(up),
                _mm256_set1_pd(forward),
            )
        };
        let axes = [
            lanes(f.right.x, f.up.x, f.forward.x),
            lanes(f.right.y, f.up.y, f.forward.y),
            lanes(f.right.z, f.up.z, f.forward.z),
        ];
        let groups = out
            .chunks_exact_mut(4)
            .zip(u.chunks_exact(4))
            .zip(v.chunks_exact(4));
        for ((rays, u), v) in groups {
            // SAFETY: each chunk holds four values.
            let (u, v) = unsafe { (_mm256_loadu_pd(u.as_ptr()), _mm256_loadu_pd(v.as_ptr())) };
            let [x, y, z] = axes.map(|(r, up, forward)| {
                let sum = _mm256_add_pd(_mm256_mul_pd(u, r), _mm256_mul_pd(v, up));
                _mm256_add_pd(sum, forward)
            });
            let squared = _mm256_add_pd(
                _mm256_add_pd(_mm256_mul_pd(x, x), _mm256_mul_pd(y, y)),
                _mm256_mul_pd(z, z),
            );
            let scale = _mm256_div_pd(_mm256_set1_pd(1.0), _mm256_sqrt_pd(squared));
            let (x, y, z) = (
                _mm256_mul_pd(x, scale),
                _mm256_mul_pd(y, scale),
                _mm256_mul_pd(z, scale),
            );
            // (x0 y0 x2 y2), (x1 y1 x3 y3), and the z pairs (z0 z1), (z2 z3).
            let (even, odd) = (_mm256_unpacklo_pd(x, y), _mm256_unpackhi_pd(x, y));
            let xy = [
                _mm256_castpd256_pd128(even),
                _mm256_castpd256_pd128(odd),
                _mm256_extractf128_pd::<1>(even),
                _mm256_extractf128_pd::<1>(odd),
            ];
            let (z01, z23) = (_mm256_castpd256_pd128(z), _mm256_extractf128_pd::<1>(z));
            let zs = [
                z01,
                _mm_unpackhi_pd(z01, z01),
                z23,
                _mm_unpackhi_pd(z23, z23),
            ];
            for ((ray, xy), z) in rays.iter_mut().zip(xy).zip(zs) {
                ray.origin = f.origin;
                ray.tmin = 0.0;
                ray.tmax = f64::INFINITY;
                let direction = (&mut ray.direction as *mut DVec3).cast::<f64>();
                // SAFETY: a DVec3 is three f64s, x, y, z in order (`repr(C)`).
                unsafe {
                    _mm_storeu_pd(direction, xy);
                    _mm_store_sd(direction.add(2), z);
                }
            }
        }
        out.len() - out.len() % 4
    }
}

/// Shirley and Chiu's area-preserving map from the unit square to the unit disk.
fn concentric_disk(a: f64, b: f64) -> (f64, f64) {
    let (x, y) = (2.0 * a - 1.0, 2.0 * b - 1.0);
    if x == 0.0 && y == 0.0 {
        return (0.0, 0.0);
    }
    let (r, theta) = if x.abs() > y.abs() {
        (x, std::f64::consts::FRAC_PI_4 * (y / x))
    } else {
        (
            y,
            std::f64::consts::FRAC_PI_2 - std::f64::consts::FRAC_PI_4 * (x / y),
        )
    };
    (r * theta.cos(), r * theta.sin())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole(frame: CameraFrame) -> CameraDesc {
        CameraDesc { frame, lens: None }
    }

    #[test]
    fn look_at_right_is_world_plus_x_when_looking_down_minus_z() {
        let frame = look_at_frame(DVec3::new(0.0, 0.0, 5.0), DVec3::ZERO, DVec3::Y, 90.0).unwrap();
        assert!((frame.right - DVec3::X).length() < 1e-15, "{}", frame.right);
        assert!((frame.up - DVec3::Y).length() < 1e-15, "{}", frame.up);
        assert_eq!(frame.forward, DVec3::NEG_Z);
    }

    #[test]
    fn look_at_scales_right_and_up_by_half_the_field_of_view() {
        let frame = look_at_frame(DVec3::ZERO, DVec3::Z, DVec3::Y, 60.0).unwrap();
        let k = (30f64).to_radians().tan();
        assert!((frame.right.length() - k).abs() < 1e-15);
        assert!((frame.up.length() - k).abs() < 1e-15);
        // Looking down +z with up +y, the image's right is world -x: the mirror of the
        // default basis camera.
        assert!(frame.right.x < 0.0);
    }

    #[test]
    fn up_parallel_to_the_view_is_refused() {
        assert!(look_at_frame(DVec3::ZERO, DVec3::Y, DVec3::Y, 60.0).is_none());
        assert!(look_at_frame(DVec3::ZERO, DVec3::Y, DVec3::NEG_Y * 3.0, 60.0).is_none());
    }

    #[test]
    fn the_default_camera_maps_pixel_centres_as_the_contract_says() {
        let frame = CameraFrame {
            origin: DVec3::ZERO,
            right: DVec3::X,
            up: DVec3::Y,
            forward: DVec3::Z,
        };
        let camera = Camera::new(&pinhole(frame), 640, 480);
        for (x, y) in [(0, 0), (639, 479), (320, 240), (17, 400)] {
            let ray = camera.ray(x, y, 0.5, 0.5, (0.5, 0.5));
            // Integer form of the mapping: u = (2x + 1 - W) / H, v = (H - 2y - 1) / H.
            let u = (2.0 * x as f64 + 1.0 - 640.0) / 480.0;
            let v = (480.0 - 2.0 * y as f64 - 1.0) / 480.0;
            let expected = DVec3::new(u, v, 1.0).normalize();
            assert!((ray.direction - expected).length() < 1e-15, "({x}, {y})");
            assert_eq!(ray.origin, DVec3::ZERO);
        }
    }

    #[test]
    fn pinhole_rays_are_bit_for_bit_the_rays_one_by_one() {
        // Frames of every scale and orientation, and runs of every length around the
        // vector width (the rest goes one by one).
        let mut random = crate::test_random::XorShift::new(0x2545_f491_4f6c_dd1d);
        let mut next = || random.unit_f64() * 2.0 - 1.0;
        for scale in [1e-9, 0.37, 1.0, 3e4, 1e12] {
            let mut v3 = || DVec3::new(next(), next(), next()) * scale;
            let frame = CameraFrame {
                origin: v3(),
                right: v3(),
                up: v3(),
                forward: v3(),
            };
            let camera = Camera::new(&pinhole(frame), 1920, 1080);
            for n in 0..=9 {
                let u: Vec<f64> = (0..n).map(|_| next() * 2.0).collect();
                let v: Vec<f64> = (0..n).map(|_| next()).collect();
                let unused = camera.ray_at(0.0, 0.0, (0.5, 0.5));
                let mut rays = vec![unused; n];
                camera.pinhole_rays(&u, &v, &mut rays);
                for i in 0..n {
                    let one = camera.ray_at(u[i], v[i], (0.5, 0.5));
                    assert_eq!(
                        rays[i].origin.to_array().map(f64::to_bits),
                        one.origin.to_array().map(f64::to_bits)
                    );
                    assert_eq!(
                        rays[i].direction.to_array().map(f64::to_bits),
                        one.direction.to_array().map(f64::to_bits),
                        "scale {scale}, ray {i} of {n}"
                    );
                    assert_eq!((rays[i].tmin, rays[i].tmax), (one.tmin, one.tmax));
                }
            }
        }
    }

    #[test]
    fn a_thin_lens_keeps_the_focus_plane_sharp() {
        let frame = look_at_frame(DVec3::new(0.0, 0.0, 5.0), DVec3::ZERO, DVec3::Y, 50.0).unwrap();
        let desc = CameraDesc {
            frame,
            lens: Some(ThinLens {
                radius: 0.5,
                focus_distance: 5.0,
            }),
        };
        let camera = Camera::new(&desc, 64, 48);
        let centre = camera.ray(10, 20, 0.3, 0.7, (0.5, 0.5));
        for lens in [(0.0, 0.0), (0.9, 0.1), (0.25, 0.75)] {
            let ray = camera.ray(10, 20, 0.3, 0.7, lens);
            assert!((ray.origin - frame.origin).length() <= 0.5 + 1e-12);
            // Every lens position sees the same point of the plane z = 0.
            let t = -ray.origin.z / ray.direction.z;
            let t0 = -centre.origin.z / centre.direction.z;
            assert!((ray.at(t) - centre.at(t0)).length() < 1e-12, "{lens:?}");
        }
    }
}
