//! The stress suite of `raybatch stress`, asserted: every ray of every case agrees with its
//! reference (see `raybatch::stress` for the cases and references), and the suite does
//! catch what it is meant to catch when the robust pieces are taken away.

use glam::DVec3;
use raybatch::Ray;
use raybatch::offset::SurfacePoint;
use raybatch::stress::{self, SCALES, StressOptions, Surface};

#[test]
fn every_stress_case_agrees_with_its_reference() {
    let report = stress::run(StressOptions::FULL);
    let wrong: Vec<_> = report.cases.iter().filter(|c| c.wrong > 0).collect();
    assert!(wrong.is_empty(), "{wrong:#?}");
    // The sweep and the leak count are what the report promises.
    for scale in SCALES {
        assert!(
            report
                .cases
                .iter()
                .any(|c| c.group == "offsets" && c.name.contains(&format!("scale {scale:.0e}"))),
            "{scale}"
        );
    }
    let leaks = report.cases.iter().find(|c| c.group == "leaks").unwrap();
    assert!(leaks.rays >= 1_000_000);
    assert!(
        report.cases.iter().all(|c| c.rays > 0),
        "{:#?}",
        report.cases
    );
}

/// A secondary ray from the computed hit point itself, as a renderer without offsets
/// would start it.
fn unoffset(at: &SurfacePoint, direction: DVec3) -> Ray {
    Ray {
        origin: at.point,
        direction,
        tmin: 0.0,
        tmax: f64::INFINITY,
    }
}

#[test]
fn without_the_offset_rays_hit_the_surface_they_leave_at_every_scale() {
    // The suite's self-intersection check fails when the offset is taken away, on every
    // kind of surface and at every scale: what the robust offset passes is not trivial.
    for kind in Surface::ALL {
        for scale in SCALES {
            let (wrong, rays) = stress::count_self_intersections(kind, scale, 0.0, 4000, unoffset);
            assert!(wrong > 0, "{kind:?} at {scale:e}: {wrong} of {rays}");
            let (wrong, _) =
                stress::count_self_intersections(kind, scale, 0.0, 4000, SurfacePoint::spawn);
            assert_eq!(wrong, 0, "{kind:?} at {scale:e}");
        }
    }
}
