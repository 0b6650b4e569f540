//! Trace throughput on procedural scenes (no downloads): closest-hit and any-hit camera
//! rays through a torus mesh; and, in the `packets` groups, batches of 64 neighbouring
//! camera rays (`Scene::closest_hits`) paced, always as packets, always side by side (single
//! rays traced in turns), and ray by ray, on an
//! 82k-triangle icosphere and a 10,000-sphere field at a low and a high resolution, and
//! at the high one through a thin lens; and the whole icosphere in a 16 × 16 view. The
//! `camera` group makes a full-HD image's camera rays 64 at a time, through a pinhole and
//! through a thin lens, tracing nothing.
//!
//!     cargo bench --bench trace
//!     cargo bench --bench trace -- packets
//!     cargo bench --bench trace -- camera

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::{DMat4, DVec3};
use raybatch::camera::{Camera, ThinLens, look_at_frame};
use raybatch::manifest::{CameraDesc, SamplerDesc, SamplerKind};
use raybatch::mesh::{Geometry, MeshFile};
use raybatch::sampler::Sampler;
use raybatch::scene::Grouping;
use raybatch::{AnyHitHint, Ray, Scene, SceneGeometry, procedural};
use std::sync::Arc;

/// The scene of one procedural mesh, placed as it is.
fn mesh_scene(mesh: Geometry) -> Scene {
    let mesh = Arc::new(MeshFile::one_geometry(mesh));
    let mut geometry = SceneGeometry::default();
    geometry
        .add_mesh(&mesh, DMat4::IDENTITY, "procedural".as_ref())
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
    let scene = mesh_scene(procedural::torus(1.0, 0.35, 400, 250));
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

/// Camera rays of a `size` × `size` view from `eye` toward the origin (a field of `vfov`
/// degrees), in 8 × 8 tiles of neighbouring pixels, as the renderer groups them; with `lens`, through
/// a thin lens of that radius focused on the origin, lens points as a render's first
/// sample takes them.
fn tiled_rays(eye: DVec3, size: u32, vfov: f64, lens: Option<f64>) -> Vec<Ray> {
    let frame = look_at_frame(eye, DVec3::ZERO, DVec3::Y, vfov).unwrap();
    let lens = lens.map(|radius| ThinLens {
        radius,
        focus_distance: eye.length(),
    });
    let camera = Camera::new(&CameraDesc { frame, lens }, size, size);
    let sampler = Sampler::new(&SamplerDesc {
        kind: SamplerKind::Independent,
        spp: 1,
        seed: 1,
    });
    let mut pixels: Vec<(u32, u32)> = (0..size)
        .flat_map(|y| (0..size).map(move |x| (x, y)))
        .collect();
    pixels.sort_by_key(|&(x, y)| (y / 8, x / 8, y % 8, x % 8));
    pixels
        .into_iter()
        .map(|(x, y)| camera.ray(x, y, 0.5, 0.5, sampler.lens(x, y, 0)))
        .collect()
}

/// `closest_hits` in groups of 64 (paced, always as packets but for packets that give up,
/// always side by side) against `closest_hit` ray by ray.
fn batch_against_single(c: &mut Criterion, name: &str, scene: &mut Scene, rays: &[Ray]) {
    let mut out = vec![None; rays.len()];
    let mut group = c.benchmark_group(name);
    group.throughput(Throughput::Elements(rays.len() as u64));
    group.sample_size(20);
    for (label, grouping) in [
        ("batch-paced", Grouping::Paced),
        ("batch-always-packets", Grouping::Packets),
        ("batch-side-by-side", Grouping::SideBySide),
    ] {
        scene.set_grouping(grouping);
        group.bench_function(label, |b| {
            b.iter(|| {
                for (rays, out) in rays.chunks(64).zip(out.chunks_mut(64)) {
                    scene.closest_hits(rays, out);
                }
            })
        });
    }
    scene.set_grouping(Grouping::Paced);
    group.bench_function("single", |b| {
        b.iter(|| {
            rays.iter()
                .filter(|r| scene.closest_hit(r).is_some())
                .count()
        })
    });
    group.finish();
}

fn packets(c: &mut Criterion) {
    let mut scene = mesh_scene(procedural::icosphere(6));
    let eye = DVec3::new(1.5, 0.9, 1.5);
    for size in [128, 1024] {
        let name = format!("packets/icosphere-82k-{size}");
        batch_against_single(c, &name, &mut scene, &tiled_rays(eye, size, 90.0, None));
    }
    // A lens three times as wide as a tile's footprint at the focus (DEVELOPERS.md, "Lens
    // packets are bounded from where their rays meet").
    let rays = tiled_rays(eye, 1024, 90.0, Some(0.05));
    batch_against_single(c, "packets/icosphere-82k-1024-lens", &mut scene, &rays);
    // The whole mesh in a 16 × 16 view (a quarter of it to a packet, whose rays are some
    // forty triangles apart): packets that give up (DEVELOPERS.md, "A packet that
    // reaches thousands of leaves gives up").
    let rays = tiled_rays(DVec3::splat(1.3), 16, 50.0, None);
    batch_against_single(c, "packets/icosphere-82k-16-whole", &mut scene, &rays);

    let mut scene = Scene::build(&SceneGeometry {
        spheres: raybatch::bench::scattered_spheres(10_000),
        ..SceneGeometry::default()
    });
    let eye = DVec3::new(8.0, 12.0, 30.0) * 0.6;
    for size in [64, 1024] {
        let name = format!("packets/spheres-10k-{size}");
        batch_against_single(c, &name, &mut scene, &tiled_rays(eye, size, 90.0, None));
    }
    // Through a lens, sphere packets are bounded from where their rays meet, as triangle
    // packets are.
    let rays = tiled_rays(eye, 1024, 90.0, Some(0.3));
    batch_against_single(c, "packets/spheres-10k-1024-lens", &mut scene, &rays);
}

/// Camera rays made 64 at a time, as the renderer makes a group's (`Camera::pinhole_rays`,
/// `Camera::lens_rays`), from a full-HD image's pixel centres and independent lens points
/// (DEVELOPERS.md, "Lens rays are made in phases").
fn camera(c: &mut Criterion) {
    let (width, height) = (1920, 1080);
    let eye = DVec3::new(0.0, 2.0, 2.5);
    let frame = look_at_frame(eye, DVec3::ZERO, DVec3::Y, 45.0).unwrap();
    let thin_lens = ThinLens {
        radius: 0.05,
        focus_distance: eye.length(),
    };
    let sampler = Sampler::new(&SamplerDesc {
        kind: SamplerKind::Independent,
        spp: 1,
        seed: 1,
    });
    let pinhole = Camera::new(&CameraDesc { frame, lens: None }, width, height);
    let lens = Camera::new(
        &CameraDesc {
            frame,
            lens: Some(thin_lens),
        },
        width,
        height,
    );
    let pixels: Vec<(u32, u32)> = (0..height)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .collect();
    let u: Vec<f64> = pixels
        .iter()
        .map(|&(x, _)| pinhole.screen_u(x, 0.5))
        .collect();
    let v: Vec<f64> = pixels
        .iter()
        .map(|&(_, y)| pinhole.screen_v(y, 0.5))
        .collect();
    let points: Vec<(f64, f64)> = pixels.iter().map(|&(x, y)| sampler.lens(x, y, 0)).collect();
    let mut out = vec![pinhole.ray(0, 0, 0.5, 0.5, (0.5, 0.5)); 64];
    let mut group = c.benchmark_group("camera");
    group.throughput(Throughput::Elements(pixels.len() as u64));
    group.sample_size(20);
    group.bench_function("pinhole-rays", |b| {
        b.iter(|| {
            for (u, v) in u.chunks(64).zip(v.chunks(64)) {
                pinhole.pinhole_rays(u, v, &mut out[..u.len()]);
                std::hint::black_box(&out);
            }
        })
    });
    group.bench_function("lens-rays", |b| {
        b.iter(|| {
            for ((u, v), points) in u.chunks(64).zip(v.chunks(64)).zip(points.chunks(64)) {
                lens.lens_rays(u, v, points, &mut out[..u.len()]);
                std::hint::black_box(&out);
            }
        })
    });
    group.finish();
}

criterion_group!(benches, trace, packets, camera);
criterion_main!(benches);
