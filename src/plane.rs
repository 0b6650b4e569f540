//! Infinite planes, hit from both sides.

use glam::DVec3;

use crate::ray::Ray;

/// The plane through `point` with unit `normal`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    pub point: DVec3,
    pub normal: DVec3,
}

impl Plane {
    /// The `t` with `tmin < t < tmax` where the ray crosses the plane, or `None`; a ray
    /// parallel to the plane (including one lying in it) misses.
    #[inline]
    pub fn intersect(&self, ray: &Ray, tmax: f64) -> Option<f64> {
        let denominator = ray.direction.dot(self.normal);
        if denominator == 0.0 {
            return None;
        }
        let t = (self.point - ray.origin).dot(self.normal) / denominator;
        (t > ray.tmin && t < tmax).then_some(t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hit_from_both_sides_and_parallel_rays_miss() {
        let p = Plane {
            point: DVec3::new(0.0, -1.0, 0.0),
            normal: DVec3::Y,
        };
        let mut ray = Ray {
            origin: DVec3::ZERO,
            direction: DVec3::NEG_Y,
            tmin: 0.0,
            tmax: f64::INFINITY,
        };
        assert_eq!(p.intersect(&ray, f64::INFINITY), Some(1.0));
        ray.origin = DVec3::new(0.0, -3.0, 0.0);
        ray.direction = DVec3::Y;
        assert_eq!(p.intersect(&ray, f64::INFINITY), Some(2.0));
        ray.direction = DVec3::X;
        assert_eq!(p.intersect(&ray, f64::INFINITY), None);
        ray.origin = DVec3::new(0.0, -1.0, 0.0);
        assert_eq!(p.intersect(&ray, f64::INFINITY), None, "a ray in the plane");
    }
}
