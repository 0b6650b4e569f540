//! Secondary rays that start on a surface (reflections, refractions, shadow rays) without
//! hitting that surface again where they start, and with no epsilon for users to tune.
//!
//! The computed hit point is never exactly on the surface; pbrt-v4 (section 6.8, "Managing
//! Rounding Error") bounds how far off it can be, per axis, and moves the origin along the
//! normal by just over the box's extent in that direction, to the side the new ray leaves
//! on, rounding away from the surface. Here the bounds also cover what the triangle path
//! adds: the origin is rounded to float32 and tested against float32 vertices, so the
//! bound for a triangle's point includes float32 rounding at the point's magnitude. The
//! offset is then far below anything visible (about 10⁻⁷ of the point's distance from the
//! world origin for triangles, 10⁻¹⁵ for spheres and planes) and is shown free of self-intersection from 10⁻⁴ to 10⁷ by
//! `raybatch stress` and the stress tests.

use glam::DVec3;

use crate::ray::Ray;

/// `γ(n) = n·u / (1 − n·u)` for unit roundoff `u` (Higham): the relative error bound of
/// `n` successive roundings.
pub fn gamma(n: u32, unit_roundoff: f64) -> f64 {
    let nu = f64::from(n) * unit_roundoff;
    nu / (1.0 - nu)
}

/// Unit roundoff of float64 and float32.
pub const U64: f64 = f64::EPSILON / 2.0;
pub const U32: f64 = f32::EPSILON as f64 / 2.0;

/// A point on a surface where a ray hit it: the computed point, a per-axis bound on how far
/// the true surface point can be from it, and the surface's unit geometric normal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    pub point: DVec3,
    /// Non-negative per-axis bound on `|computed − exact|`.
    pub error: DVec3,
    pub normal: DVec3,
}

impl SurfacePoint {
    /// A point on a float64 surface (sphere, plane): `error` as computed.
    pub fn new(point: DVec3, error: DVec3, normal: DVec3) -> SurfacePoint {
        SurfacePoint {
            point,
            error,
            normal,
        }
    }

    /// A point on a float32 triangle: `error` widened by float32 rounding at the point's
    /// magnitude, since the triangle path rounds ray origins to float32.
    pub fn on_triangle(point: DVec3, error: DVec3, normal: DVec3) -> SurfacePoint {
        SurfacePoint::new(point, error + point.abs() * gamma(2, U32), normal)
    }

    /// The origin for a ray leaving along `direction`: just outside the error box, on the
    /// side of the surface `direction` points to. A direction in the tangent plane goes
    /// to the normal's side.
    pub fn offset_origin(&self, direction: DVec3) -> DVec3 {
        let distance = self.normal.abs().dot(self.error);
        let mut offset = self.normal * distance;
        if direction.dot(self.normal) < 0.0 {
            offset = -offset;
        }
        let moved = self.point + offset;
        // Round away from the surface, so the rounding of the sum cannot undo the offset.
        DVec3::from_array(std::array::from_fn(|i| {
            if offset[i] > 0.0 {
                moved[i].next_up()
            } else if offset[i] < 0.0 {
                moved[i].next_down()
            } else {
                moved[i]
            }
        }))
    }

    /// A ray leaving the surface along unit `direction`, unbounded (`tmin = 0`).
    pub fn spawn(&self, direction: DVec3) -> Ray {
        Ray {
            origin: self.offset_origin(direction),
            direction,
            tmin: 0.0,
            tmax: f64::INFINITY,
        }
    }

    /// A ray from the surface toward `target` (a light, say), stopping just short of it:
    /// `tmax` is the distance to `target` less its own rounding.
    pub fn spawn_toward(&self, target: DVec3) -> Ray {
        let origin = self.offset_origin(target - self.point);
        let to = target - origin;
        let distance = to.length();
        Ray {
            origin,
            direction: to / distance,
            tmin: 0.0,
            tmax: distance * (1.0 - gamma(4, U64)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_origin_moves_to_the_side_the_ray_leaves_on_by_at_least_the_error_box() {
        let p = SurfacePoint {
            point: DVec3::new(1.0, 2.0, 3.0),
            error: DVec3::new(1e-6, 2e-6, 3e-6),
            normal: DVec3::new(0.0, 0.6, 0.8),
        };
        let need = 0.6 * 2e-6 + 0.8 * 3e-6;
        for (direction, side) in [(DVec3::Z, 1.0), (DVec3::NEG_Z, -1.0), (DVec3::X, 1.0)] {
            let moved = (p.offset_origin(direction) - p.point).dot(p.normal);
            assert!(moved * side >= need, "{direction}: {moved}");
            assert!(moved * side < need * 1.001, "{direction}: {moved}");
        }
    }

    #[test]
    fn a_ray_toward_a_point_stops_short_of_it() {
        let p = SurfacePoint::new(DVec3::new(1.0, 0.0, 0.0), DVec3::splat(1e-9), DVec3::X);
        let target = DVec3::new(4.0, 4.0, 0.0);
        let r = p.spawn_toward(target);
        assert!((r.direction.length() - 1.0).abs() < 1e-15);
        assert!(
            r.origin.x > 1.0,
            "moved off the surface toward the target's side"
        );
        let reach = (target - r.origin).length();
        assert!(
            r.tmax < reach && r.tmax > reach * (1.0 - 1e-12),
            "{} {reach}",
            r.tmax
        );
    }
}
