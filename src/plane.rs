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

/// Rays tested side by side against each plane by the batch searches: one float64 vector
/// of AVX2. A room of six planes cost a full-HD render a third of its time ray by ray,
/// each test waiting on its own division.
const LANES: usize = 4;

/// For each ray `rays[k]`, the nearest plane it crosses with `tmin < t < tmax`, as
/// `hit(t, index in planes)`, into `out[k]` (`None` where it crosses none): what
/// [`Plane::intersect`] over the planes in order, each below the nearest `t` so far, finds
/// (the same `t`, the first of equal ones). `hit` makes the caller's own record, so that
/// nothing is copied from one form to another per ray.
pub fn nearest_planes<T>(
    planes: &[Plane],
    rays: &[Ray],
    out: &mut [Option<T>],
    hit: impl Fn(f64, u32) -> T,
) {
    assert_eq!(rays.len(), out.len());
    // Scenes of spheres alone come here too: no lanes to fill.
    if planes.is_empty() {
        out.fill_with(|| None);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2.
        unsafe { nearest_planes_avx2(planes, rays, out, hit) };
        return;
    }
    nearest_in_lanes(planes, rays, out, hit);
}

/// [`nearest_planes`] compiled for AVX2.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn nearest_planes_avx2<T>(
    planes: &[Plane],
    rays: &[Ray],
    out: &mut [Option<T>],
    hit: impl Fn(f64, u32) -> T,
) {
    nearest_in_lanes(planes, rays, out, hit);
}

/// [`nearest_planes`]'s body: whole groups of [`LANES`] rays side by side, the rest one
/// by one.
#[inline(always)]
fn nearest_in_lanes<T>(
    planes: &[Plane],
    rays: &[Ray],
    out: &mut [Option<T>],
    hit: impl Fn(f64, u32) -> T,
) {
    let mut groups = rays.chunks_exact(LANES);
    let mut outs = out.chunks_exact_mut(LANES);
    for (group, out) in (&mut groups).zip(&mut outs) {
        let lanes = Lanes::of(group);
        let mut tmax = lanes.tmax;
        let mut nearest = [u32::MAX; LANES];
        for (i, plane) in planes.iter().enumerate() {
            let crossed = lanes.crossings(plane, &tmax);
            for l in 0..LANES {
                let crosses = crossed.hit[l];
                tmax[l] = if crosses { crossed.t[l] } else { tmax[l] };
                nearest[l] = if crosses { i as u32 } else { nearest[l] };
            }
        }
        for l in 0..LANES {
            out[l] = (nearest[l] != u32::MAX).then(|| hit(tmax[l], nearest[l]));
        }
    }
    for (ray, out) in groups.remainder().iter().zip(outs.into_remainder()) {
        *out = nearest_plane(planes, ray).map(|(t, i)| hit(t, i));
    }
}

/// The nearest of `planes` that `ray` crosses with `tmin < t < tmax`, as `(t, index in
/// planes)`, the planes one by one (the first of equal `t`s).
#[inline]
pub fn nearest_plane(planes: &[Plane], ray: &Ray) -> Option<(f64, u32)> {
    let mut nearest = None;
    let mut tmax = ray.tmax;
    for (i, plane) in planes.iter().enumerate() {
        if let Some(t) = plane.intersect(ray, tmax) {
            tmax = t;
            nearest = Some((t, i as u32));
        }
    }
    nearest
}

/// Whether `ray` crosses some plane of `planes` with `tmin < t < tmax`.
#[inline]
pub fn any_plane(planes: &[Plane], ray: &Ray) -> bool {
    planes.iter().any(|p| p.intersect(ray, ray.tmax).is_some())
}

/// For each ray, whether it crosses some plane with `tmin < t < tmax`, into `out`.
pub fn any_planes(planes: &[Plane], rays: &[Ray], out: &mut [bool]) {
    assert_eq!(rays.len(), out.len());
    if planes.is_empty() {
        out.fill(false);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2.
        unsafe { any_planes_avx2(planes, rays, out) };
        return;
    }
    any_in_lanes(planes, rays, out);
}

/// [`any_planes`] compiled for AVX2.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn any_planes_avx2(planes: &[Plane], rays: &[Ray], out: &mut [bool]) {
    any_in_lanes(planes, rays, out);
}

/// [`any_planes`]'s body: whole groups of [`LANES`] rays side by side (stopping once all
/// have crossed a plane), the rest one by one.
#[inline(always)]
fn any_in_lanes(planes: &[Plane], rays: &[Ray], out: &mut [bool]) {
    let mut groups = rays.chunks_exact(LANES);
    let mut outs = out.chunks_exact_mut(LANES);
    for (group, out) in (&mut groups).zip(&mut outs) {
        let lanes = Lanes::of(group);
        let mut found = [false; LANES];
        for plane in planes {
            let crossed = lanes.crossings(plane, &lanes.tmax);
            for (found, hit) in found.iter_mut().zip(crossed.hit) {
                *found |= hit;
            }
            if found == [true; LANES] {
                break;
            }
        }
        out.copy_from_slice(&found);
    }
    for (ray, out) in groups.remainder().iter().zip(outs.into_remainder()) {
        *out = any_plane(planes, ray);
    }
}

/// [`LANES`] rays, a coordinate per array.
struct Lanes {
    origin: [[f64; LANES]; 3],
    direction: [[f64; LANES]; 3],
    tmin: [f64; LANES],
    tmax: [f64; LANES],
}

/// Where [`LANES`] rays cross one plane.
struct Crossings {
    t: [f64; LANES],
    hit: [bool; LANES],
}

impl Lanes {
    #[inline(always)]
    fn of(rays: &[Ray]) -> Lanes {
        let lane = |f: fn(&Ray) -> f64| std::array::from_fn(|l| f(&rays[l]));
        Lanes {
            origin: [
                lane(|r| r.origin.x),
                lane(|r| r.origin.y),
                lane(|r| r.origin.z),
            ],
            direction: [
                lane(|r| r.direction.x),
                lane(|r| r.direction.y),
                lane(|r| r.direction.z),
            ],
            tmin: lane(|r| r.tmin),
            tmax: lane(|r| r.tmax),
        }
    }

    /// [`Plane::intersect`] in every lane, below `tmax`: the same operations in the same
    /// order (glam's dot products, unfused), so the same `t`.
    #[inline(always)]
    fn crossings(&self, plane: &Plane, tmax: &[f64; LANES]) -> Crossings {
        let ([ox, oy, oz], [dx, dy, dz]) = (&self.origin, &self.direction);
        let (p, n) = (plane.point, plane.normal);
        let mut t = [0.0; LANES];
        let mut hit = [false; LANES];
        for l in 0..LANES {
            let denominator = dx[l] * n.x + dy[l] * n.y + dz[l] * n.z;
            let numerator = (p.x - ox[l]) * n.x + (p.y - oy[l]) * n.y + (p.z - oz[l]) * n.z;
            t[l] = numerator / denominator;
            // `&`, not `&&`: no branch per lane.
            hit[l] = (denominator != 0.0) & (t[l] > self.tmin[l]) & (t[l] < tmax[l]);
        }
        Crossings { t, hit }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn planes_side_by_side_find_what_one_by_one_finds() {
        // Ties between equal planes, rays parallel to planes and lying in them, each ray
        // with its own interval; every group size around the lanes; through the dispatch
        // (AVX2 here) and the plain lanes.
        let mut random = crate::test_random::XorShift::new(7);
        let mut coordinate = || random.unit_f64() * 6.0 - 3.0;
        let floor = Plane {
            point: DVec3::new(0.0, -1.0, 0.0),
            normal: DVec3::Y,
        };
        let mut planes = vec![
            floor,
            floor,
            Plane {
                point: DVec3::new(0.0, 0.0, 2.0),
                normal: DVec3::NEG_Z,
            },
        ];
        for _ in 0..5 {
            let point = DVec3::new(coordinate(), coordinate(), coordinate());
            let normal = DVec3::new(coordinate(), coordinate(), coordinate()).normalize();
            planes.push(Plane { point, normal });
        }
        let mut rays = Vec::new();
        for k in 0..40 {
            let origin = DVec3::new(coordinate(), coordinate(), coordinate());
            let direction = match k % 5 {
                0 => DVec3::X,
                1 => DVec3::new(coordinate(), 0.0, coordinate()).normalize(),
                _ => DVec3::new(coordinate(), coordinate(), coordinate()).normalize(),
            };
            let (tmin, tmax) = match k % 3 {
                0 => (0.0, f64::INFINITY),
                1 => (0.5, 2.5),
                _ => (1e-9, 1.0 + coordinate().abs()),
            };
            rays.push(Ray {
                origin,
                direction,
                tmin,
                tmax,
            });
        }
        // A ray lying in the floor.
        rays[3].origin.y = -1.0;
        let mut hits = 0;
        for n in 0..=rays.len() {
            let rays = &rays[..n];
            let (mut nearest, mut plain) = (vec![None; n], vec![None; n]);
            let pair = |t, i| (t, i);
            nearest_planes(&planes, rays, &mut nearest, pair);
            nearest_in_lanes(&planes, rays, &mut plain, pair);
            let (mut any, mut plain_any) = (vec![false; n], vec![false; n]);
            any_planes(&planes, rays, &mut any);
            any_in_lanes(&planes, rays, &mut plain_any);
            for (k, ray) in rays.iter().enumerate() {
                let expected = nearest_plane(&planes, ray);
                let bits = |x: Option<(f64, u32)>| x.map(|(t, i)| (t.to_bits(), i));
                assert_eq!(bits(nearest[k]), bits(expected), "{n} rays, ray {k}");
                assert_eq!(bits(plain[k]), bits(expected), "{n} rays, ray {k}");
                assert_eq!(any[k], expected.is_some());
                assert_eq!(plain_any[k], expected.is_some());
                hits += usize::from(expected.is_some());
                // The first of the two equal floors wins.
                assert_ne!(expected.map(|(_, i)| i), Some(1));
            }
        }
        assert!(hits > 100, "the rays must cross planes: {hits}");
    }

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
