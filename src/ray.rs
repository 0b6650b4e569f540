//! Rays in float64, as the camera makes them.

use glam::DVec3;

/// A ray `origin + t * direction`. `direction` has unit length, so `t` is a distance.
/// A hit counts only for `tmin < t < tmax` (both strict).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: DVec3,
    pub direction: DVec3,
    pub tmin: f64,
    pub tmax: f64,
}

impl Ray {
    /// The point at distance `t`.
    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + self.direction * t
    }
}
