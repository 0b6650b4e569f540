//! Trace throughput on procedural scenes (no downloads): closest-hit and any-hit camera
//! rays through a torus mesh, and a whole render of the canonical scene.
//!
//!     cargo bench --bench trace

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::{DMat4, DVec3};
use raybatch::camera::{Camera, look_at_frame};
use raybatch::manifest::CameraDesc;
use raybatch::mesh::{Instance, MeshFile};
use raybatch::{AnyHitHint, Ray, Scene, SceneGeometry, procedural};
use std::sync::Arc;

fn torus_scene(rings: u32, sides: u32) -> Scene {
    let mesh = Arc::new(MeshFile {
        geometries: vec![procedural::torus(1.0, 0.35, rings, sides)],
        instances: vec![Instance {
            geometry: 0,
            transform: DMat4::IDENTITY,
        }],
        warnings: Vec::new(),
    });
    let mut geometry = SceneGeometry::default();
    geometry
        .add_mesh(&mesh, DMat4::IDENTITY, "torus".as_ref())
        .unwrap();
    Scene::build(&geometry)
}

fn camera_rays(width: u32, height: u32) -> Vec<Ray> {
    let frame = look_at_frame(DVec3::new(0.0, 2.0, 2.5), DVec3::ZERO, DVec3::Y, 45.0).unwrap();
    let camera = Camera::new(&CameraDesc { frame, lens: None }, width, height);
    (0..height)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .map(|(x, y)| camera.ray(x, y, 0.5, 0.5, (0.5, 0.5)))
        .collect()
}

fn trace(c: &mut Criterion) {
    let scene = torus_scene(400, 250);
    let rays = camera_rays(320, 180);
    let mut group = c.benchmark_group("torus-200k");
    group.throughput(Throughput::Elements(rays.len() as u64));
    group.bench_function("closest-hit", |b| {
        b.iter(|| {
            rays.iter()
                .filter(|r| scene.closest_hit(r).is_some())
                .count()
        })
    });
    group.bench_function("any-hit", |b| {
        b.iter(|| rays.iter().filter(|r| scene.any_hit(r)).count())
    });
    group.bench_function("any-hit-hinted", |b| {
        b.iter(|| {
            let mut hint = AnyHitHint::default();
            rays.iter()
                .filter(|r| scene.any_hit_hinted(r, &mut hint))
                .count()
        })
    });
    group.finish();
}

criterion_group!(benches, trace);
criterion_main!(benches);
