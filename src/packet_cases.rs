//! Test cases shared by the packet traversals' tests ([`crate::packet`] for triangles,
//! [`crate::sphere_packet`] for spheres): packets of camera rays, from a pinhole and
//! through lenses, and boxes at the edge of what each ray's own node test admits. A
//! packet must admit every box one of its rays admits, or packets and single rays would
//! find different hits.

use crate::bvh::{Bounds, WIDTH};
use crate::test_random::XorShift;
use glam::DVec3;

/// Where the rays of [`lens_packets`]' last packet meet, 4 along each.
pub const MEETING_POINT: DVec3 = DVec3::new(1.5, 2.25, 3.0);

/// A ray of a test packet, in float64: origin and direction.
pub type TestRay = (DVec3, DVec3);

/// Packets of 64 rays, each with the distance where its rays meet (or would): camera rays
/// through 8 × 8 pixels of a 256² image with a 40° field, or all through one pixel, from a
/// pinhole or a lens focused at 3 (times the scale), at four scales and places, in a view
/// whose directions are positive on every axis; and rays that meet exactly at one point 4
/// along each (their origins `p − 4d` are exact in float32 and float64), for which a
/// packet's bounds from there are as narrow as they can be. `round` maps each ray to the
/// precision under test (the directions are unit vectors before it).
pub fn lens_packets(
    random: &mut XorShift,
    round: impl Fn(TestRay) -> TestRay,
) -> Vec<(Vec<TestRay>, f64)> {
    let mut packets = Vec::new();
    for (scale, eye) in [
        (1.0, DVec3::ZERO),
        (1e-3, DVec3::new(0.2, -0.1, 0.3)),
        (1e4, DVec3::new(3e4, -1e4, 2e4)),
        (1.0, DVec3::new(700.0, 300.0, -900.0)),
    ] {
        let focus = 3.0 * scale;
        let forward = DVec3::new(0.4, 0.5, 0.77).normalize();
        let right = forward.cross(DVec3::Y).normalize();
        let up = right.cross(forward);
        let half = 20f64.to_radians().tan();
        for (aperture, pixels) in [(0.0, 8), (0.02, 8), (0.2, 8), (0.02, 1), (0.2, 1)] {
            let rays = (0..64).map(|i| {
                let (x, y) = (f64::from(i % pixels + 40), f64::from(i / 8 % pixels + 90));
                let pixel = forward
                    + right * half * (2.0 * (x + 0.5) / 256.0 - 1.0)
                    + up * half * (1.0 - 2.0 * (y + 0.5) / 256.0);
                let target = eye + pixel * (focus / pixel.dot(forward));
                let r = random.unit_f64().sqrt() * aperture * scale;
                let angle = random.unit_f64() * std::f64::consts::TAU;
                let origin = eye + (right * angle.cos() + up * angle.sin()) * r;
                round((origin, (target - origin).normalize()))
            });
            packets.push((rays.collect(), focus));
        }
    }
    let p = MEETING_POINT;
    let exact = (0..64).map(|_| {
        let mut grid = |base: f64| base + random.below(400) as f64 / 4096.0;
        let d = DVec3::new(grid(0.25), grid(0.5), grid(0.75));
        (p - 4.0 * d, d)
    });
    packets.push((exact.collect(), 4.0));
    packets
}

/// Boxes at the edge of what `ray` enters, [`WIDTH`] at a time with their `k`: the ray
/// leaves one slab at `t0` and enters another `k` units `ulp` (relative) later, `k` from
/// −8 to 55, for `t0` before, at and past `focus` and each pair of axes. Each box spans
/// its slabs over these distances, computed in float64 (a float32 test rounds them).
pub fn edge_boxes((o, d): TestRay, focus: f64, ulp: f64) -> Vec<Vec<(Bounds<f64>, i32)>> {
    let point = |t: f64| o + t * d;
    let mut chunks = Vec::new();
    for t0 in [0.3, 0.7, 0.95, 1.0, 1.02, 1.3, 3.0].map(|f| f * focus) {
        for (leave, enter) in [(0, 1), (1, 2), (2, 0), (1, 0)] {
            let third = 3 - leave - enter;
            for ks in (-8..56).collect::<Vec<i32>>().chunks(WIDTH) {
                let boxes = ks.iter().map(|&k| {
                    let t1 = t0 * (1.0 + f64::from(k) * ulp);
                    let mut b = Bounds::<f64>::EMPTY;
                    let spans = [
                        (leave, 0.5 * t0, t0),
                        (enter, t1, 2.0 * t1),
                        (third, 0.5 * t0, 2.0 * t1),
                    ];
                    for (axis, from, to) in spans {
                        let (p, q) = (point(from)[axis], point(to)[axis]);
                        (b.min[axis], b.max[axis]) = (p.min(q), p.max(q));
                    }
                    (b, k)
                });
                chunks.push(boxes.collect());
            }
        }
    }
    chunks
}
