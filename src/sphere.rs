//! Ray–sphere intersection by the formulation of Ray Tracing Gems, chapter 7 ("Precision
//! Improvements for Ray/Sphere Intersection", Haines, Günther and Akenine-Möller), in float64.
//!
//! The tutorial's `D = B² − C` subtracts two nearly equal large numbers when the sphere is
//! small and far away, and in float32 loses the sphere entirely. Here the discriminant is
//! `r² − |f − (f·d̂)d̂|²` (the squared distance from the centre to the ray's line,
//! subtracted from `r²`), and the roots come from the stable form `q = −b − sign(b)√Δ`.

use glam::DVec3;

use crate::ray::Ray;

/// A sphere of `radius > 0` around `center`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sphere {
    pub center: DVec3,
    pub radius: f64,
}

impl Sphere {
    /// The smallest `t` with `tmin < t < tmax` where the ray enters or leaves the sphere,
    /// or `None`. A ray whose line only touches the sphere (discriminant ≤ 0) misses.
    #[inline]
    pub fn intersect(&self, ray: &Ray, tmax: f64) -> Option<f64> {
        let (near, far) = self.roots(ray.origin, ray.direction)?;
        if near > ray.tmin && near < tmax {
            Some(near)
        } else if far > ray.tmin && far < tmax {
            Some(far)
        } else {
            None
        }
    }

    /// Both distances where the line `origin + t·direction` crosses the sphere, nearest
    /// first; `None` when the line misses or only grazes it.
    #[inline]
    pub fn roots(&self, origin: DVec3, direction: DVec3) -> Option<(f64, f64)> {
        let f = origin - self.center;
        let a = direction.dot(direction);
        let b = f.dot(direction);
        // l: from the centre to the line's closest point, without the B² − C cancellation.
        let l = f - (b / a) * direction;
        let r2 = self.radius * self.radius;
        let discriminant = r2 - l.dot(l);
        if discriminant <= 0.0 {
            return None;
        }
        let c = f.dot(f) - r2;
        let q = -b - (a * discriminant).sqrt().copysign(b);
        let (t0, t1) = (c / q, q / a);
        Some(if t0 <= t1 { (t0, t1) } else { (t1, t0) })
    }

    /// The outward unit normal at surface point `p`: `(p − c) / r`.
    pub fn normal(&self, p: DVec3) -> DVec3 {
        (p - self.center) / self.radius
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(origin: DVec3, direction: DVec3) -> Ray {
        Ray {
            origin,
            direction: direction.normalize(),
            tmin: 0.0,
            tmax: f64::INFINITY,
        }
    }

    #[test]
    fn hits_the_near_side_from_outside_and_the_far_side_from_inside() {
        let s = Sphere {
            center: DVec3::new(0.0, 0.0, 3.0),
            radius: 1.0,
        };
        assert_eq!(
            s.intersect(&ray(DVec3::ZERO, DVec3::Z), f64::INFINITY),
            Some(2.0)
        );
        let inside = ray(DVec3::new(0.0, 0.0, 3.0), DVec3::Z);
        assert_eq!(s.intersect(&inside, f64::INFINITY), Some(1.0));
        let behind = ray(DVec3::ZERO, DVec3::NEG_Z);
        assert_eq!(s.intersect(&behind, f64::INFINITY), None);
    }

    #[test]
    fn grazing_is_a_miss_and_just_inside_is_a_hit() {
        let s = Sphere {
            center: DVec3::ZERO,
            radius: 1.0,
        };
        let tangent = ray(DVec3::new(1.0, 0.0, -5.0), DVec3::Z);
        assert_eq!(s.roots(tangent.origin, tangent.direction), None);
        let inside = ray(DVec3::new(1.0 - 1e-9, 0.0, -5.0), DVec3::Z);
        assert!(s.roots(inside.origin, inside.direction).is_some());
    }

    #[test]
    fn the_interval_is_strict_at_both_ends() {
        let s = Sphere {
            center: DVec3::new(0.0, 0.0, 3.0),
            radius: 1.0,
        };
        let mut r = ray(DVec3::ZERO, DVec3::Z);
        r.tmin = 2.0;
        assert_eq!(
            s.intersect(&r, f64::INFINITY),
            Some(4.0),
            "t = tmin is not a hit"
        );
        r.tmin = 0.0;
        assert_eq!(s.intersect(&r, 2.0), None, "t = tmax is not a hit");
    }

    #[test]
    fn a_tiny_far_sphere_is_found_where_the_naive_float32_formula_sees_nothing() {
        let s = Sphere {
            center: DVec3::new(0.0, 0.0, 1.0e4),
            radius: 1.0e-2,
        };
        // Rays at lateral offsets 0, 0.5 r and 0.99 r at the sphere's distance.
        for offset in [0.0, 0.5e-2, 0.99e-2] {
            let r = ray(DVec3::ZERO, DVec3::new(offset, 0.0, 1.0e4));
            let t = s.intersect(&r, f64::INFINITY).expect("hit");
            // Exact: distance to the near surface along the ray.
            let d = r.direction;
            let b = -(s.center.dot(d));
            let expected = -b - (b * b - (s.center.dot(s.center) - 1.0e-4)).sqrt();
            assert!((t - expected).abs() < 1e-9 * expected, "{t} vs {expected}");

            // The tutorial's formula in float32 misses the same rays.
            let (o, c, d32) = (
                [0f32; 3],
                [0.0f32, 0.0, 1.0e4],
                [d.x as f32, d.y as f32, d.z as f32],
            );
            let oc: Vec<f32> = (0..3).map(|i| o[i] - c[i]).collect();
            let bb: f32 = (0..3).map(|i| oc[i] * d32[i]).sum();
            let cc: f32 = (0..3).map(|i| oc[i] * oc[i]).sum::<f32>() - 1.0e-4;
            assert!(
                bb * bb - cc <= 0.0,
                "naive float32 unexpectedly hits at {offset}"
            );
        }
    }
}
