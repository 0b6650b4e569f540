//! Benchmarks users can run (`raybatch bench`): trace throughput, build and load times,
//! memory, and whole jobs, on scenes made here (and the scanned models when given). With
//! the `embree` feature the very same rays go through the Embree reference (robust scene,
//! `rtcIntersect1`/`rtcOccluded1`) in the same run, and ratios are reported; the whole
//! jobs (read, build, render, write) of the torus and of a manifest listing 100,000
//! spheres also run through the Embree backend, in turns with ours.
//!
//! Our triangle tree is built as a job tracing as many rays would build it
//! ([`Scene::build_for_rays`]); where that is not the default preset, the default's build
//! (what a job of fewer rays per triangle builds) is timed too. Every figure is the median
//! of several runs. Trace passes run in rounds, every query of both tracers once per
//! round, so that a slow spell of the machine lands on all columns alike instead of on
//! one. Timing is never asserted in tests; the figures go to BENCHMARKS.md with the
//! command that produced them.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::DVec3;
use rayon::prelude::*;
use serde_json::json;

use crate::bvh::BuildPreset;
use crate::camera::{Camera, ThinLens, look_at_frame};
use crate::hint::AnyHitHint;
use crate::job::{Backend, Batch, JobOptions};
use crate::manifest::{CameraDesc, SamplerDesc, SamplerKind};
use crate::ray::Ray;
use crate::sampler::Sampler;
use crate::scene::{Scene, SceneGeometry, Tracer};
use crate::sphere::Sphere;

/// What to run.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    /// Smaller images and fewer repetitions (for CI smoke runs).
    pub quick: bool,
    /// Folder of the scanned models (`stanford-bunny.obj`, `nefertiti.obj`, `ogre.obj`).
    pub models: Option<PathBuf>,
    /// Thread counts to trace with.
    pub threads: Vec<usize>,
    /// Only scenes whose name contains one of these (all when empty).
    pub only: Vec<String>,
    /// Also trace with Embree (needs the feature).
    pub embree: bool,
    /// Our packets test leaves eight rays at a time even where the CPU has AVX-512 (to
    /// compare the two widths; the trace rows only).
    pub eight_lane_packets: bool,
}

impl BenchOptions {
    /// Whether the scene or job `name` is to be run (`only` is empty, or one of its
    /// entries is part of `name`).
    pub fn wants(&self, name: &str) -> bool {
        self.only.is_empty() || self.only.iter().any(|o| name.contains(o.as_str()))
    }

    /// Whether a wanted scene reads the scanned model `model` (one of [`SCANNED_MODELS`]):
    /// its own view, or for ogre also the close-up.
    pub fn reads_model(&self, model: &str) -> bool {
        self.wants(model) || model == CLOSE_UP_MODEL && self.wants(CLOSE_UP)
    }
}

/// The close-up scene, and the scanned model it views.
const CLOSE_UP: &str = "ogre close up";
const CLOSE_UP_MODEL: &str = "ogre";

/// The scanned models the bench traces when `models` holds them, by file stem (`.obj`).
pub const SCANNED_MODELS: [&str; 3] = ["stanford-bunny", "nefertiti", "ogre"];

/// Throughput at one thread count, in millions of rays per second: one ray per query
/// (`closest_hit`, `any_hit_hinted`: Embree's `rtcIntersect1`, `rtcOccluded1`), and the
/// batch queries on runs of 64 neighbouring rays (`closest_hits`, `any_hits`: our
/// packets, Embree's coherent streams `rtcIntersect1M`, `rtcOccluded1M`).
#[derive(Debug, Clone, Copy)]
pub struct Throughput {
    pub threads: usize,
    pub closest: f64,
    pub closest_batch: f64,
    /// Any hit, one ray per query, each thread carrying an [`AnyHitHint`] from ray to ray
    /// (Embree's tracer ignores it).
    pub any: f64,
    /// Any hit, one ray per query, without a hint (`any_hit`).
    pub any_unhinted: f64,
    pub any_batch: f64,
    /// `closest` and `any` over the rays that hit alone (in their order, the misses left
    /// out; 0 where none hits): what any hit saves on a hit, apart from the misses, which
    /// cost both queries alike.
    pub closest_on_hits: f64,
    pub any_on_hits: f64,
}

/// One tracer's figures for one scene.
#[derive(Debug, Clone)]
pub struct TracerFigures {
    pub build_s: f64,
    pub throughput: Vec<Throughput>,
}

/// Figures for one trace scene.
#[derive(Debug, Clone)]
pub struct SceneFigures {
    pub name: String,
    pub triangles: usize,
    pub spheres: usize,
    pub rays: usize,
    /// Hits of the closest-hit pass (both tracers must agree on the count).
    pub hits: usize,
    /// The preset our triangle tree was built with ([`crate::bvh::BuildPreset::name`]),
    /// chosen as a job tracing as many rays would choose it
    /// ([`crate::bvh::BuildPreset::for_triangles`]); `None` without triangles.
    pub triangle_tree_preset: Option<&'static str>,
    /// Our build with the default preset ([`crate::bvh::BuildPreset::Fastest`], what a job
    /// tracing fewer rays per triangle builds) where the traced tree's preset is another:
    /// seconds, the median as for [`TracerFigures::build_s`]. `None` otherwise.
    pub default_build_s: Option<f64>,
    /// Reading the mesh file, when there is one: seconds and MB/s.
    pub load: Option<(f64, f64)>,
    /// Peak resident memory added by loading and building, per triangle (Linux only): the
    /// rise of the process's peak resident size from just before the mesh is read (the
    /// memory earlier scenes freed handed back first) to the end of the first build.
    pub peak_bytes_per_triangle: Option<f64>,
    /// What the built scene keeps (triangle blocks, spheres and tree nodes), per triangle
    /// or sphere.
    pub scene_bytes_per_primitive: f64,
    pub raybatch: TracerFigures,
    pub embree: Option<TracerFigures>,
    /// For each thread count traced (in the order of the tracers' throughputs), how much
    /// faster [`crate::compute_loop`] ran on it than on one thread, timed in the same
    /// rounds as the tracers: the median of the rounds' ratios. `None` when one thread is
    /// not among the counts, or for one thread itself.
    pub compute_loop_scaling: Vec<Option<f64>>,
}

/// Figures for a whole-job benchmark.
#[derive(Debug, Clone)]
pub struct JobFigures {
    pub name: String,
    pub jobs: usize,
    pub seconds: f64,
    /// The same jobs through the Embree backend, when asked for and compared.
    pub embree_seconds: Option<f64>,
}

/// Everything one run measured.
#[derive(Debug, Clone)]
pub struct BenchReport {
    pub scenes: Vec<SceneFigures>,
    pub jobs: Vec<JobFigures>,
}

/// A scene to trace: geometry, a camera, an image size.
struct TraceScene {
    name: String,
    geometry: SceneGeometry,
    load: Option<(f64, f64)>,
    peak_baseline: Option<u64>,
    eye: DVec3,
    target: DVec3,
    vfov: f64,
    size: (u32, u32),
    /// A thin lens focused on `target`, of this radius: each camera ray then starts at its
    /// own point of the lens (of the lens grid's first cell, where the lens job's first
    /// sample takes it), so a group's rays share no origin.
    lens_radius: Option<f64>,
    /// A point light: the traced rays are then shadow rays, from each camera ray's closest
    /// hit toward it (see [`shadow_rays`]), instead of the camera rays.
    light: Option<DVec3>,
}

/// Runs the benchmarks. `temp` is a scratch folder for files written on the way.
pub fn run(options: &BenchOptions, temp: &Path) -> Result<BenchReport, String> {
    let wanted = |name: &str| options.wants(name);
    let (width, height) = if options.quick {
        (480, 270)
    } else {
        (1920, 1080)
    };
    // Each scene is loaded just before it is traced, so its memory figures are its own.
    let mut scenes: Vec<Box<dyn FnOnce() -> Result<TraceScene, String>>> = Vec::new();
    let mut torus_file = None;

    let (rings, sides) = if options.quick {
        (200, 100)
    } else {
        (1000, 500)
    };
    let name = format!("torus-{}k", 2 * rings * sides / 1000);
    let small_name = format!("{name} at {}x{}", width / 6, height / 6);
    let lens_name = format!("{name} through a lens");
    let shadow_name = format!("{name} shadow rays");
    if [&name, &small_name, &lens_name, &shadow_name]
        .into_iter()
        .any(|n| wanted(n))
    {
        let file = temp.join(format!("{name}.obj"));
        write_torus(&file, rings, sides)?;
        torus_file = Some(file.clone());
        if wanted(&name) {
            let file = file.clone();
            scenes.push(Box::new(move || mesh_scene(&name, &file, (width, height))));
        }
        // The same view through the lens job's lens, focused on the torus's centre: one
        // ray a pixel, from the lens point of the lens job's first sample, so the rays
        // are the pinhole's but for their origins.
        if wanted(&lens_name) {
            let file = file.clone();
            scenes.push(Box::new(move || {
                let scene = mesh_scene(&lens_name, &file, (width, height))?;
                Ok(TraceScene {
                    lens_radius: Some(LENS_JOB.aperture),
                    ..scene
                })
            }));
        }
        // Rays toward a light from the points the full-HD view's camera rays hit, what an
        // any-hit query is for: a point facing away from the light sends its ray into the
        // tube, to be stopped by the tube's far wall, and parts of the ring shadow others.
        if wanted(&shadow_name) {
            let file = file.clone();
            scenes.push(Box::new(move || {
                Ok(toward_shadow_light(mesh_scene(
                    &shadow_name,
                    &file,
                    (width, height),
                )?))
            }));
        }
        // The same mesh at a sixth of the resolution: about 17 triangles per pixel, where
        // packets would waste work and rays go one by one.
        if wanted(&small_name) {
            scenes.push(Box::new(move || {
                mesh_scene(&small_name, &file, (width / 6, height / 6))
            }));
        }
    }
    if let Some(models) = &options.models {
        for model in SCANNED_MODELS {
            let file = models.join(format!("{model}.obj"));
            if wanted(model) && file.exists() {
                scenes.push(Box::new(move || mesh_scene(model, &file, (width, height))));
            }
        }
        // The ogre from the same place through a field of view of 6° instead of 40°: a
        // close-up, where nearly every ray hits and the visible triangles are each many
        // pixels wide, so all the rays of a packet meet the same few.
        let file = models.join(format!("{CLOSE_UP_MODEL}.obj"));
        if wanted(CLOSE_UP) && file.exists() {
            scenes.push(Box::new(move || {
                let scene = mesh_scene(CLOSE_UP, &file, (width, height))?;
                Ok(TraceScene {
                    vfov: CLOSE_UP_VFOV,
                    ..scene
                })
            }));
        }
    }
    if wanted("spheres") {
        scenes.push(Box::new(move || Ok(sphere_field(10_000, (width, height)))));
    }
    if wanted("canonical") {
        scenes.push(Box::new(|| {
            Ok(TraceScene {
                name: "canonical".to_string(),
                geometry: SceneGeometry {
                    spheres: vec![Sphere {
                        center: DVec3::new(0.0, 0.0, 3.0),
                        radius: 1.0,
                    }],
                    ..SceneGeometry::default()
                },
                load: None,
                peak_baseline: None,
                eye: DVec3::ZERO,
                target: DVec3::Z,
                vfov: 90.0,
                size: (640, 480),
                lens_radius: None,
                light: None,
            })
        }));
    }

    let runs = if options.quick { 3 } else { 7 };
    let mut figures = Vec::new();
    for scene in scenes {
        figures.push(trace_scene(scene()?, options, runs)?);
    }

    let mut jobs = Vec::new();
    if wanted("batch") {
        jobs.push(batch_of_small_jobs(
            temp,
            if options.quick { 20 } else { 100 },
        )?);
    }
    if wanted("canonical") {
        jobs.push(canonical_job(temp)?);
    }
    if wanted("spheres") {
        let count = if options.quick { 10_000 } else { 100_000 };
        jobs.push(sphere_job(temp, count, (width, height), options.embree)?);
    }
    if let Some(file) = torus_file {
        for lens in [None, Some(LENS_JOB)] {
            if wanted(&mesh_job_name(&file, (width, height), lens)) {
                jobs.push(mesh_job(
                    temp,
                    &file,
                    (width, height),
                    lens,
                    options.embree,
                )?);
            }
        }
    }
    Ok(BenchReport {
        scenes: figures,
        jobs,
    })
}

/// The close-up's vertical field of view, degrees.
const CLOSE_UP_VFOV: f64 = 6.0;

/// Writes the bench's torus (major radius 1, minor 0.35) of `rings × sides` quads to
/// `file` as OBJ.
fn write_torus(file: &Path, rings: u32, sides: u32) -> Result<(), String> {
    let torus = crate::procedural::torus(1.0, 0.35, rings, sides);
    std::fs::write(file, crate::procedural::to_obj(&torus, ""))
        .map_err(|e| format!("{}: {e}", file.display()))
}

fn mesh_scene(name: &str, file: &Path, size: (u32, u32)) -> Result<TraceScene, String> {
    let peak_baseline = reset_peak_memory();
    let bytes = std::fs::metadata(file).map_err(|e| e.to_string())?.len() as f64;
    let start = Instant::now();
    let mesh = crate::mesh::load(file).map_err(|e| e.to_string())?;
    let load_s = start.elapsed().as_secs_f64();
    let mut geometry = SceneGeometry::default();
    geometry
        .add_mesh(&std::sync::Arc::new(mesh), glam::DMat4::IDENTITY, file)
        .map_err(|e| e.to_string())?;
    let (lo, hi) = geometry.triangles.iter().flatten().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), v| {
            let p = DVec3::from_array(v.map(f64::from));
            (lo.min(p), hi.max(p))
        },
    );
    let (centre, radius) = ((lo + hi) / 2.0, (hi - lo).length() / 2.0);
    Ok(TraceScene {
        name: name.to_string(),
        geometry,
        load: Some((load_s, bytes / 1e6 / load_s)),
        peak_baseline,
        eye: centre + DVec3::new(0.3, 0.5, 1.0).normalize() * radius * 2.2,
        target: centre,
        vfov: 40.0,
        size,
        lens_radius: None,
        light: None,
    })
}

/// `count` spheres of radius 0.05 to 0.3 scattered in the cube of side 20 around the
/// origin, the same every time (a fixed seed): the bench's sphere field.
pub fn scattered_spheres(count: usize) -> Vec<Sphere> {
    let mut state = 12345u64;
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..count)
        .map(|_| Sphere {
            center: DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * 20.0,
            radius: 0.05 + 0.25 * next(),
        })
        .collect()
}

/// Where the sphere field is seen from (looking at the origin), and the vertical field of
/// view in degrees: the trace scene's view and the sphere job's.
const SPHERE_FIELD_EYE: [f64; 3] = [8.0, 12.0, 30.0];
const SPHERE_FIELD_VFOV: f64 = 45.0;

/// `count` spheres of varied sizes scattered in a cube, seen from outside.
fn sphere_field(count: usize, size: (u32, u32)) -> TraceScene {
    let spheres = scattered_spheres(count);
    TraceScene {
        name: format!("spheres-{}k", count / 1000),
        geometry: SceneGeometry {
            spheres,
            ..SceneGeometry::default()
        },
        load: None,
        peak_baseline: None,
        eye: DVec3::from_array(SPHERE_FIELD_EYE),
        target: DVec3::ZERO,
        vfov: SPHERE_FIELD_VFOV,
        size,
        lens_radius: None,
        light: None,
    }
}

/// Builds per tracer and scene, at least; the median is reported. A tracer builds again
/// while its builds have taken less than [`BUILD_SECONDS`] together, up to
/// [`MOST_BUILDS`]: a build of a millisecond or two swings by half from one to the next on
/// a shared machine, and a median of five of them swung as much from run to run.
const BUILDS: usize = 5;
/// See [`BUILDS`].
const BUILD_SECONDS: f64 = 0.25;
/// See [`BUILDS`].
const MOST_BUILDS: usize = 200;
/// How long a tracer's turn of timed builds lasts, at least (one build, however long).
/// Short, so that a slow spell of the machine, which lasts tens of milliseconds to
/// minutes, lands on every tracer's builds rather than on one's.
const BUILD_TURN_SECONDS: f64 = 0.05;

/// Whether `times` (seconds) are builds enough ([`BUILDS`]).
fn builds_enough(times: &[f64]) -> bool {
    times.len() >= MOST_BUILDS
        || (times.len() >= BUILDS && times.iter().sum::<f64>() >= BUILD_SECONDS)
}

/// Times each of `builders` (each builds a scene and drops it) until [`builds_enough`],
/// in turns: a turn is one untimed build, then timed builds for at least
/// [`BUILD_TURN_SECONDS`]. A build straight after the other tracer's can read slow, for
/// reasons not found: without the untimed build, Embree's torus builds (one a turn) read
/// 0.18–0.31 s; with it, 0.17–0.24 s after the first turn (DEVELOPERS.md, "How the bench
/// measures"). Returns each builder's times, in seconds.
fn time_builds_in_turns(
    builders: &mut [&mut dyn FnMut() -> Result<(), String>],
) -> Result<Vec<Vec<f64>>, String> {
    let mut times = vec![Vec::new(); builders.len()];
    while times.iter().any(|t| !builds_enough(t)) {
        for (build, times) in builders.iter_mut().zip(&mut times) {
            if builds_enough(times) {
                continue;
            }
            build()?;
            let turn = Instant::now();
            loop {
                let start = Instant::now();
                build()?;
                times.push(start.elapsed().as_secs_f64());
                if turn.elapsed().as_secs_f64() >= BUILD_TURN_SECONDS || builds_enough(times) {
                    break;
                }
            }
        }
    }
    Ok(times)
}

/// The pixel-centre rays, in 8 × 8 groups of neighbouring pixels (as the renderer traces
/// them), the same order for every tracer; through the scene's lens when it has one.
fn camera_rays(scene: &TraceScene) -> Vec<Ray> {
    let frame = look_at_frame(scene.eye, scene.target, DVec3::Y, scene.vfov).expect("a valid view");
    let (w, h) = scene.size;
    let lens = scene.lens_radius.map(|radius| ThinLens {
        radius,
        focus_distance: (scene.target - scene.eye).length(),
    });
    let camera = Camera::new(&CameraDesc { frame, lens }, w, h);
    // Lens points as the lens job's first sample takes them (the pinhole ignores them):
    // stratified, each from the lens grid's first cell.
    let sampler = Sampler::new(&SamplerDesc {
        kind: SamplerKind::Stratified,
        spp: LENS_JOB.spp,
        seed: 1,
    })
    .with_lens(lens.is_some());
    let side = crate::render::PACKET_SIDE;
    let mut pixels: Vec<(u32, u32)> = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).collect();
    pixels.sort_by_key(|&(x, y)| (y / side, x / side, y % side, x % side));
    pixels
        .into_iter()
        .map(|(x, y)| camera.ray(x, y, 0.5, 0.5, sampler.lens(x, y, 0)))
        .collect()
}

/// Where the shadow rays' light is, from the view's target, in units of the eye's distance
/// to it: low and to the left behind the torus, so that much of what the eye sees faces
/// away from it or lies in another part's shadow.
const SHADOW_LIGHT: DVec3 = DVec3::new(-0.8, 0.35, -0.5);

/// `scene` tracing shadow rays toward its light at [`SHADOW_LIGHT`] instead of its camera
/// rays.
fn toward_shadow_light(scene: TraceScene) -> TraceScene {
    let light = scene.target + SHADOW_LIGHT * (scene.eye - scene.target).length();
    TraceScene {
        light: Some(light),
        ..scene
    }
}

/// How far along a shadow ray its search begins: past the surface the ray leaves (the hit
/// point comes from a float32 distance of a few units, a few 10⁻⁷ off), well short of
/// any other surface.
const SHADOW_TMIN: f64 = 1e-4;

/// Shadow rays toward `light`: from each of `camera`'s rays with a closest hit in `scene`,
/// from that hit, in the camera rays' order (neighbouring points toward one light, as
/// [`AnyHitHint`] expects), with `tmin` [`SHADOW_TMIN`] and `tmax` the light's distance.
fn shadow_rays(scene: &Scene, camera: &[Ray], light: DVec3) -> Vec<Ray> {
    camera
        .par_iter()
        .filter_map(|ray| {
            let origin = ray.at(scene.closest_hit(ray)?.t);
            let to_light = light - origin;
            Some(Ray {
                origin,
                direction: to_light.normalize(),
                tmin: SHADOW_TMIN,
                tmax: to_light.length(),
            })
        })
        .collect()
}

fn trace_scene(
    scene: TraceScene,
    options: &BenchOptions,
    runs: usize,
) -> Result<SceneFigures, String> {
    let triangles = scene.geometry.triangles.len();
    let spheres = scene.geometry.spheres.len();
    // Built as a job tracing as many rays as the passes below would be: every ray, every
    // query over every ray, every thread count, every round (the passes over the rays that
    // hit, known only once a tree is built, trace some of them again). Counted as camera
    // rays for shadow rays too: a job tracing them traces the camera rays that find their
    // origins as well.
    let (width, height) = scene.size;
    let traced = u64::from(width)
        * u64::from(height)
        * (Query::OVER_EVERY_RAY * options.threads.len() * (runs.max(1) + 1)) as u64;
    let build = || Scene::build_for_rays(&scene.geometry, traced);

    // The first build sets the peak (loading and building); later ones reuse the memory.
    // Not timed: the timed builds are all warm, Embree's too.
    let first = build();
    let traced_preset = (triangles > 0).then(|| first.triangle_tree().preset());
    let peak_bytes_per_triangle = scene.peak_baseline.and_then(|base| {
        Some((peak_memory()?.saturating_sub(base)) as f64 / triangles.max(1) as f64)
    });
    let rays = camera_rays(&scene);
    let rays = match scene.light {
        Some(light) => shadow_rays(&first, &rays, light),
        None => rays,
    };
    let hit_rays = rays_that_hit(&first, &rays);
    let hits = hit_rays.len();
    let scene_bytes_per_primitive =
        first.counts().accel_bytes as f64 / (triangles + spheres).max(1) as f64;
    drop(first);
    let pools = options
        .threads
        .iter()
        .map(|&n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| e.to_string())
        })
        .collect::<Result<Vec<_>, _>>()?;

    #[cfg(not(feature = "embree"))]
    if options.embree {
        return Err("this build has no Embree backend (build with --features embree)".to_string());
    }
    let compute_loop_scaling;
    let mut default_build_s = None;
    let (raybatch, embree) = {
        // Each build is dropped before the next, so that no other scene is alive.
        let default = BuildPreset::default();
        let mut traced_build = || {
            drop(build());
            Ok(())
        };
        let mut default_build = || {
            drop(Scene::build_with(&scene.geometry, default));
            Ok(())
        };
        let mut builders: Vec<&mut dyn FnMut() -> Result<(), String>> = vec![&mut traced_build];
        let with_default = traced_preset.is_some_and(|preset| preset != default);
        if with_default {
            builders.push(&mut default_build);
        }
        #[cfg(feature = "embree")]
        let mut embree_build = || {
            crate::embree::EmbreeScene::build(&scene.geometry)
                .map(drop)
                .map_err(|e| e.to_string())
        };
        #[cfg(feature = "embree")]
        if options.embree {
            builders.push(&mut embree_build);
        }
        let mut times = time_builds_in_turns(&mut builders)?.into_iter();
        let traced_times = times.next().expect("ours is timed");
        if with_default {
            default_build_s = times.next().map(median_of);
        }
        let build_times = std::iter::once(traced_times).chain(times);
        #[cfg(feature = "embree")]
        let reference = if options.embree {
            Some(crate::embree::EmbreeScene::build(&scene.geometry).map_err(|e| e.to_string())?)
        } else {
            None
        };
        let mut ours = build();
        if options.eight_lane_packets {
            ours.set_wide_leaves(false);
        }
        let ours_pass = |query: Query| trace_pass(&ours, query.rays(&rays, &hit_rays), query);
        #[cfg(feature = "embree")]
        let reference_pass = reference.as_ref().map(|reference| {
            let reference_hits = count_hits(reference, &rays, |t, r| t.closest_hit(r).is_some());
            if reference_hits != hits {
                eprintln!(
                    "note: {}: raybatch hits {hits} rays, Embree {reference_hits}",
                    scene.name
                );
            }
            // Without the backend's check of each ray (these are all finite), as a
            // program calling Embree traces them.
            let (reference, rays, hit_rays) =
                (crate::embree::Unchecked(reference), &rays, &hit_rays);
            move |query: Query| trace_pass(&reference, query.rays(rays, hit_rays), query)
        });
        #[cfg(not(feature = "embree"))]
        let reference_pass: Option<fn(Query) -> usize> = None;
        let tracers: Vec<&(dyn Fn(Query) -> usize + Sync)> = std::iter::once(&ours_pass as _)
            .chain(reference_pass.as_ref().map(|pass| pass as _))
            .collect();
        let (throughputs, scaling) =
            throughputs(&tracers, (&rays, &hit_rays), &options.threads, &pools, runs);
        compute_loop_scaling = scaling;
        let mut figures = throughputs
            .into_iter()
            .zip(build_times)
            .map(|(throughput, times)| TracerFigures {
                build_s: median_of(times),
                throughput,
            });
        (figures.next().expect("ours is traced"), figures.next())
    };

    Ok(SceneFigures {
        name: scene.name,
        triangles,
        spheres,
        rays: rays.len(),
        hits,
        triangle_tree_preset: traced_preset.map(BuildPreset::name),
        default_build_s,
        load: scene.load,
        peak_bytes_per_triangle,
        scene_bytes_per_primitive,
        raybatch,
        embree,
        compute_loop_scaling,
    })
}

/// The rays of `rays` with a closest hit in `scene`, in their order.
fn rays_that_hit(scene: &Scene, rays: &[Ray]) -> Vec<Ray> {
    rays.par_iter()
        .filter(|r| scene.closest_hit(r).is_some())
        .copied()
        .collect()
}

/// The queries a throughput column times.
#[derive(Debug, Clone, Copy)]
enum Query {
    Closest,
    ClosestBatch,
    AnyHinted,
    Any,
    AnyBatch,
    /// `Closest` and `AnyHinted` over the rays that hit alone.
    ClosestOnHits,
    AnyHintedOnHits,
}

impl Query {
    const ALL: [Query; 7] = [
        Query::Closest,
        Query::ClosestBatch,
        Query::AnyHinted,
        Query::Any,
        Query::AnyBatch,
        Query::ClosestOnHits,
        Query::AnyHintedOnHits,
    ];

    /// How many of the queries trace every ray (the others trace again the rays that hit).
    const OVER_EVERY_RAY: usize = {
        let (mut count, mut i) = (0, 0);
        while i < Query::ALL.len() {
            if !Query::ALL[i].on_hits() {
                count += 1;
            }
            i += 1;
        }
        count
    };

    /// Whether the query traces the rays that hit alone.
    const fn on_hits(self) -> bool {
        matches!(self, Query::ClosestOnHits | Query::AnyHintedOnHits)
    }

    /// The rays the query traces: `hit_rays` (those of `rays` that hit, in order) or all.
    fn rays<'a>(self, rays: &'a [Ray], hit_rays: &'a [Ray]) -> &'a [Ray] {
        if self.on_hits() { hit_rays } else { rays }
    }
}

// Each query's figures are kept at its place in `Query::ALL`, which `query as usize` names.
const _: () = {
    let mut i = 0;
    while i < Query::ALL.len() {
        assert!(Query::ALL[i] as usize == i);
        i += 1;
    }
};

/// Traces every ray once with `query`; returns the hit count (so the work is not elided).
fn trace_pass<T: Tracer>(tracer: &T, rays: &[Ray], query: Query) -> usize {
    match query {
        Query::Closest | Query::ClosestOnHits => {
            count_hits(tracer, rays, |t, r| t.closest_hit(r).is_some())
        }
        Query::ClosestBatch => count_batch_hits(tracer, rays, false),
        Query::AnyHinted | Query::AnyHintedOnHits => count_hinted_hits(tracer, rays),
        Query::Any => count_hits(tracer, rays, |t, r| t.any_hit(r)),
        Query::AnyBatch => count_batch_hits(tracer, rays, true),
    }
}

fn count_hits<T: Tracer>(tracer: &T, rays: &[Ray], hit: impl Fn(&T, &Ray) -> bool + Sync) -> usize {
    tasks(rays)
        .map(|chunk| count_prefetched(chunk, |r| hit(tracer, r)))
        .sum()
}

/// A pass's rays cut into tasks of [`task_len`] rays, each task a job of its own that an
/// idle thread may take. Left to rayon's own splitting, a thread ran runs of neighbouring
/// tasks as one job that the other thread could not share: where rays cost unevenly
/// along the pass (the shadow rays that reach the light cost several times those
/// stopped), two threads traced the shadow rays 1.55–1.72x as fast as one (hinted any
/// hit) against 1.91–2.03x with a job per task (DEVELOPERS.md, "Every task of a bench
/// pass is a job of its own").
fn tasks<T: Sync>(items: &[T]) -> impl IndexedParallelIterator<Item = &[T]> {
    items.par_chunks(task_len(items.len())).with_max_len(1)
}

/// Rays per task of a pass over `rays` rays: whole groups of 64 (the batch passes' unit),
/// about 4096 of them, in an even number of tasks, so that two threads can share them
/// evenly. (The 320x180 image's 57,600 rays made 15 tasks of 4096, which capped two
/// threads at 1.88x one.)
fn task_len(rays: usize) -> usize {
    const GROUP: usize = 64;
    const GROUPS_PER_TASK: usize = 64;
    let groups = rays.div_ceil(GROUP);
    let tasks = groups.div_ceil(GROUPS_PER_TASK).max(1).next_multiple_of(2);
    groups.div_ceil(tasks).max(1) * GROUP
}

/// Any hits counted one ray at a time, with a hint carried through each chunk's rays.
fn count_hinted_hits<T: Tracer>(tracer: &T, rays: &[Ray]) -> usize {
    tasks(rays)
        .map(|chunk| {
            let mut hint = AnyHitHint::default();
            count_prefetched(chunk, |r| tracer.any_hit_hinted(r, &mut hint))
        })
        .sum()
}

/// How many rays ahead of the one being traced the single-ray passes ask the cache for
/// the next (16 rays: a kilobyte). A renderer makes its camera rays in registers; the
/// bench reads them from an array of 130 MB at full HD, and one ray's query is too long
/// for the CPU to reach the next ray's load on its own. Unasked, the array's memory
/// latency was a cost shared by every column, and on the Intel host of BENCHMARKS.md
/// most of the cost of a ray that misses the mesh's box (27 against 10 ns on ogre).
const RAYS_AHEAD: usize = 16;

/// How many rays of `chunk` `hit` holds for, one by one in order, each ray asked of the
/// cache [`RAYS_AHEAD`] rays before its turn (the same for every tracer).
#[inline(always)]
fn count_prefetched(chunk: &[Ray], mut hit: impl FnMut(&Ray) -> bool) -> usize {
    ask_cache_for(&chunk[..chunk.len().min(RAYS_AHEAD)]);
    let mut count = 0;
    for (i, ray) in chunk.iter().enumerate() {
        if let Some(next) = chunk.get(i + RAYS_AHEAD) {
            ask_cache_for(std::slice::from_ref(next));
        }
        count += usize::from(hit(ray));
    }
    count
}

/// Asks the cache for the memory of `rays` without waiting for it.
#[inline(always)]
fn ask_cache_for(rays: &[Ray]) {
    #[cfg(target_arch = "x86_64")]
    {
        let range = rays.as_ptr_range();
        crate::simd::prefetch(range.start as usize, range.end as usize);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = rays;
}

/// Hits counted with the batch queries, 64 rays at a time.
fn count_batch_hits<T: Tracer>(tracer: &T, rays: &[Ray], any: bool) -> usize {
    tasks(rays)
        .map(|chunk| {
            let mut count = 0;
            let mut groups = chunk.chunks(64).peekable();
            while let Some(group) = groups.next() {
                // The next group's rays are fetched while this one is traced.
                if let Some(next) = groups.peek() {
                    ask_cache_for(next);
                }
                if any {
                    let mut hits = [false; 64];
                    tracer.any_hits(group, &mut hits[..group.len()]);
                    count += hits.iter().filter(|&&h| h).count();
                } else {
                    let mut hits = [None; 64];
                    tracer.closest_hits(group, &mut hits[..group.len()]);
                    count += hits.iter().filter(|h| h.is_some()).count();
                }
            }
            count
        })
        .sum()
}

/// Each tracer's throughput at each thread count, and the compute loop's scaling at each
/// (see [`SceneFigures::compute_loop_scaling`]). Passes run in rounds: one round times
/// every query at every thread count once, the tracers in turns for each, then the compute
/// loop, so a neighbour that slows the machine for a while slows the columns alike rather
/// than one of them. The first round warms up and is not counted; each figure is the
/// median of `runs`.
fn throughputs(
    tracers: &[&(dyn Fn(Query) -> usize + Sync)],
    (rays, hit_rays): (&[Ray], &[Ray]),
    threads: &[usize],
    pools: &[rayon::ThreadPool],
    runs: usize,
) -> (Vec<Vec<Throughput>>, Vec<Option<f64>>) {
    // times[tracer][thread count][query]
    let mut times = vec![vec![Query::ALL.map(|_| Vec::new()); threads.len()]; tracers.len()];
    // compute[thread count][round]
    let mut compute = vec![Vec::new(); threads.len()];
    for round in 0..=runs.max(1) {
        for (p, pool) in pools.iter().enumerate() {
            wake(pool);
            for (q, &query) in Query::ALL.iter().enumerate() {
                for (t, pass) in tracers.iter().enumerate() {
                    let start = Instant::now();
                    pool.install(|| std::hint::black_box(pass(query)));
                    if round > 0 {
                        times[t][p][q].push(start.elapsed().as_secs_f64());
                    }
                }
            }
            let start = Instant::now();
            pool.install(|| std::hint::black_box(crate::compute_loop::pass()));
            if round > 0 {
                compute[p].push(start.elapsed().as_secs_f64());
            }
        }
    }
    let one = threads.iter().position(|&n| n == 1);
    let scaling = (0..threads.len())
        .map(|p| {
            let one = one.filter(|&one| one != p)?;
            let ratios = compute[one].iter().zip(&compute[p]).map(|(a, b)| a / b);
            Some(median_of(ratios.collect()))
        })
        .collect();
    let throughputs = times
        .into_iter()
        .map(|per_thread| {
            per_thread
                .into_iter()
                .zip(threads)
                .map(|(columns, &threads)| {
                    let mrays = |query: Query| match query.rays(rays, hit_rays).len() {
                        0 => 0.0,
                        traced => traced as f64 / median_of(columns[query as usize].clone()) / 1e6,
                    };
                    Throughput {
                        threads,
                        closest: mrays(Query::Closest),
                        closest_batch: mrays(Query::ClosestBatch),
                        any: mrays(Query::AnyHinted),
                        any_unhinted: mrays(Query::Any),
                        any_batch: mrays(Query::AnyBatch),
                        closest_on_hits: mrays(Query::ClosestOnHits),
                        any_on_hits: mrays(Query::AnyHintedOnHits),
                    }
                })
                .collect()
        })
        .collect();
    (throughputs, scaling)
}

/// Keeps every thread of `pool` busy for a few milliseconds. A pool left idle while the
/// other one traced has its threads asleep, and on a virtual machine a sleeping core can
/// take milliseconds to come back: the first pass timed after the switch, always ours
/// closest-hit single rays, read up to half as fast as the same pass in other rounds.
fn wake(pool: &rayon::ThreadPool) {
    pool.broadcast(|_| {
        let start = Instant::now();
        while start.elapsed().as_secs_f64() < WAKE_S {
            std::hint::spin_loop();
        }
    });
}

/// How long [`wake`] keeps the threads busy, in seconds.
const WAKE_S: f64 = 0.005;

/// The median duration of `runs` calls, in seconds (after one warm-up call).
pub fn median(runs: usize, mut f: impl FnMut()) -> f64 {
    f();
    median_of(
        (0..runs.max(1))
            .map(|_| {
                let start = Instant::now();
                f();
                start.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

/// The median of some durations (the upper one of an even count).
pub(crate) fn median_of(mut times: Vec<f64>) -> f64 {
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

/// `count` small manifests sharing one 82k-triangle mesh placed alike, rendered as one
/// batch: the mesh is read once and its tree built once, then reused by every job.
fn batch_of_small_jobs(temp: &Path, count: usize) -> Result<JobFigures, String> {
    let folder = temp.join("batch");
    std::fs::create_dir_all(&folder).map_err(|e| e.to_string())?;
    let mesh = folder.join("ico.obj");
    std::fs::write(
        &mesh,
        crate::procedural::to_obj(&crate::procedural::icosphere(6), ""),
    )
    .map_err(|e| e.to_string())?;
    let integrators = ["hit", "depth", "normal"];
    for i in 0..count {
        let a = i as f64 * 0.37;
        let manifest = format!(
            r#"{{"image": {{"width": 160, "height": 120}}, "output": "job{i:03}.ppm",
                "camera": {{"look_from": [{}, 1.2, {}], "look_at": [0, 0, 0], "vfov": 50}},
                "integrator": {{"type": "{}"}},
                "spheres": [{{"center": [1.5, 0, 0], "radius": 0.4}}],
                "planes": [{{"point": [0, -1, 0], "normal": [0, 1, 0]}}],
                "meshes": [{{"file": "ico.obj"}}]}}"#,
            3.0 * a.cos(),
            3.0 * a.sin(),
            integrators[i % 3]
        );
        std::fs::write(folder.join(format!("job{i:03}.json")), manifest)
            .map_err(|e| e.to_string())?;
    }
    let manifests = crate::job::manifests_in(&folder).map_err(|e| e.to_string())?;
    let seconds = median(3, || {
        let mut batch = Batch::new(JobOptions::default());
        for manifest in &manifests {
            let report = batch.run(manifest, &|_| {});
            assert!(report.ok(), "{:?}", report.error);
        }
        assert_eq!(batch.triangle_tree_builds(), 1);
    });
    Ok(JobFigures {
        name: format!("batch of {count} small jobs (160x120, one shared 82k-triangle mesh)"),
        jobs: count,
        seconds,
        embree_seconds: None,
    })
}

/// One `depth` job of the mesh in `file` (through `lens` when given), from reading the
/// manifest to writing the image, each run in a fresh batch (so the mesh is read and its
/// tree built every time); with `embree`, the same job through the Embree backend in turns
/// with ours.
fn mesh_job(
    temp: &Path,
    file: &Path,
    (width, height): (u32, u32),
    lens: Option<LensJob>,
    embree: bool,
) -> Result<JobFigures, String> {
    let manifest = temp.join("mesh-job.json");
    let mut text = serde_json::json!({
        "image": {"width": width, "height": height},
        "camera": {"look_from": [0, 2, 2.5], "look_at": [0, 0, 0], "vfov": 45},
        "integrator": {"type": "depth"},
        "meshes": [{"file": file}],
        "output": "mesh-job.pfm",
    });
    if let Some(lens) = lens {
        text["camera"]["aperture"] = json!(lens.aperture);
        text["camera"]["focus_distance"] = json!(lens.focus_distance);
        text["sampler"] = json!({"type": "stratified", "spp": lens.spp, "seed": 1});
    }
    std::fs::write(&manifest, text.to_string()).map_err(|e| e.to_string())?;
    let (seconds, embree_seconds) = job_in_turns(&manifest, embree);
    Ok(JobFigures {
        name: mesh_job_name(file, (width, height), lens),
        jobs: 1,
        seconds,
        embree_seconds,
    })
}

/// [`mesh_job`]'s row name.
fn mesh_job_name(file: &Path, (width, height): (u32, u32), lens: Option<LensJob>) -> String {
    let name = file
        .file_stem()
        .map_or_else(String::new, |s| s.to_string_lossy().into_owned());
    let lens = lens.map_or_else(String::new, |lens| {
        format!(
            ", {} spp through a lens of radius {}",
            lens.spp, lens.aperture
        )
    });
    format!("{name} job ({width}x{height} depth{lens}, load + build + render + write)")
}

/// A thin lens for [`mesh_job`]: camera rays from points spread over the lens, so a
/// group's rays share no origin and meet only near the focus plane.
#[derive(Debug, Clone, Copy)]
struct LensJob {
    aperture: f64,
    focus_distance: f64,
    spp: u32,
}

/// The lens of the bench's second torus job: focused on the torus's centre (3.2 away).
const LENS_JOB: LensJob = LensJob {
    aperture: 0.05,
    focus_distance: 3.2,
    spp: 4,
};

/// One `depth` job of `count` spheres listed in its manifest ([`scattered_spheres`], the
/// sphere field's view), from reading the manifest to writing the image, as
/// [`mesh_job`] runs it: a scene whose reading is all JSON.
fn sphere_job(
    temp: &Path,
    count: usize,
    (width, height): (u32, u32),
    embree: bool,
) -> Result<JobFigures, String> {
    let manifest = temp.join("sphere-job.json");
    let spheres: Vec<serde_json::Value> = scattered_spheres(count)
        .iter()
        .map(|s| json!({"center": s.center.to_array(), "radius": s.radius}))
        .collect();
    let text = json!({
        "image": {"width": width, "height": height},
        "camera": {"look_from": SPHERE_FIELD_EYE, "look_at": [0, 0, 0], "vfov": SPHERE_FIELD_VFOV},
        "integrator": {"type": "depth"},
        "spheres": spheres,
        "output": "sphere-job.pfm",
    });
    std::fs::write(&manifest, text.to_string()).map_err(|e| e.to_string())?;
    let (seconds, embree_seconds) = job_in_turns(&manifest, embree);
    Ok(JobFigures {
        name: format!(
            "{}k spheres job ({width}x{height} depth, read + build + render + write)",
            count / 1000
        ),
        jobs: 1,
        seconds,
        embree_seconds,
    })
}

/// The median time of the job of `manifest`, each run in a fresh batch, and with
/// `embree` the same job's through the Embree backend: a warm-up of each, then runs in
/// turns, so that drift hits both alike.
fn job_in_turns(manifest: &Path, embree: bool) -> (f64, Option<f64>) {
    let run = |backend: Backend| {
        let report = Batch::new(JobOptions {
            backend,
            ..JobOptions::default()
        })
        .run_last(manifest, &|_| {});
        assert!(report.ok(), "{:?}", report.error);
    };
    let backends: &[Backend] = if embree {
        &[Backend::Raybatch, Backend::Embree]
    } else {
        &[Backend::Raybatch]
    };
    let mut times = vec![Vec::new(); backends.len()];
    for round in 0..6 {
        for (b, &backend) in backends.iter().enumerate() {
            let start = Instant::now();
            run(backend);
            if round > 0 {
                times[b].push(start.elapsed().as_secs_f64());
            }
        }
    }
    let mut times = times.into_iter().map(median_of);
    (times.next().unwrap_or_default(), times.next())
}

fn canonical_job(temp: &Path) -> Result<JobFigures, String> {
    let manifest = temp.join("canonical.json");
    std::fs::write(
        &manifest,
        r#"{"image": {"width": 640, "height": 480}, "spheres": [{"center": [0, 0, 3], "radius": 1}]}"#,
    )
    .map_err(|e| e.to_string())?;
    let seconds = median(5, || {
        let report = Batch::new(JobOptions::default()).run(&manifest, &|_| {});
        assert!(report.ok(), "{:?}", report.error);
    });
    Ok(JobFigures {
        name: "canonical job (640x480, load + build + render + write)".to_string(),
        jobs: 1,
        seconds,
        embree_seconds: None,
    })
}

/// Hands the memory the process has freed back to the system, then resets the process's
/// peak resident size and returns the current one, in bytes. The command keeps freed
/// memory for reuse (`src/bin/raybatch/memory.rs`): without handing it back, a scene
/// loaded after another would grow into the memory the earlier one freed, and its peak
/// would show only what it needed beyond that.
fn reset_peak_memory() -> Option<u64> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` only returns free pages of the allocator's heaps.
    unsafe {
        libc::malloc_trim(0);
    }
    std::fs::write("/proc/self/clear_refs", "5").ok()?;
    status_kb("VmRSS:").map(|kb| kb * 1024)
}

/// The process's peak resident size since the last reset, in bytes.
fn peak_memory() -> Option<u64> {
    status_kb("VmHWM:").map(|kb| kb * 1024)
}

fn status_kb(key: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// How our packets test leaves in the trace rows, for reports.
pub fn packet_lanes(options: &BenchOptions) -> &'static str {
    #[cfg(target_arch = "x86_64")]
    match crate::packet::LeafLanes::widest() {
        Some(crate::packet::LeafLanes::Sixteen) if !options.eight_lane_packets => {
            return "leaves tested sixteen rays at a time (AVX-512)";
        }
        Some(_) => return "leaves tested eight rays at a time (AVX2)",
        None => {}
    }
    let _ = options;
    "none (no AVX2: rays one by one)"
}

/// The CPU's model name (Linux), for reports.
pub fn cpu_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|info| {
            info.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".to_string())
}

impl BenchReport {
    pub fn to_json(&self) -> serde_json::Value {
        let tracer = |t: &TracerFigures| {
            json!({
                "build_s": t.build_s,
                "throughput": t.throughput.iter().map(|x| json!({
                    "threads": x.threads,
                    "closest_mrays": x.closest, "closest_batch_mrays": x.closest_batch,
                    "any_mrays": x.any, "any_unhinted_mrays": x.any_unhinted,
                    "any_batch_mrays": x.any_batch,
                    "closest_on_hits_mrays": x.closest_on_hits,
                    "any_on_hits_mrays": x.any_on_hits,
                })).collect::<Vec<_>>(),
            })
        };
        json!({
            "cpu": cpu_name(),
            "scenes": self.scenes.iter().map(|s| json!({
                "name": s.name, "triangles": s.triangles, "spheres": s.spheres, "rays": s.rays,
                "hits": s.hits,
                "triangle_tree_preset": s.triangle_tree_preset,
                "default_build_s": s.default_build_s,
                "load_s": s.load.map(|l| l.0), "load_mb_per_s": s.load.map(|l| l.1),
                "peak_bytes_per_triangle": s.peak_bytes_per_triangle,
                "scene_bytes_per_primitive": s.scene_bytes_per_primitive,
                "raybatch": tracer(&s.raybatch),
                "embree": s.embree.as_ref().map(tracer),
                "compute_loop_scaling": s.compute_loop_scaling,
            })).collect::<Vec<_>>(),
            "jobs": self.jobs.iter().map(|j| json!({
                "name": j.name, "jobs": j.jobs, "seconds": j.seconds,
                "embree_seconds": j.embree_seconds,
            })).collect::<Vec<_>>(),
        })
    }

    /// Markdown tables, as BENCHMARKS.md shows them.
    pub fn to_markdown(&self) -> String {
        use std::fmt::Write;
        // `-` where there is nothing to compare (no ray hit).
        let ratio = |a: f64, b: f64| {
            if a > 0.0 && b > 0.0 {
                format!("{:.2}x", a / b)
            } else {
                "-".to_string()
            }
        };
        let mut out = String::new();
        let with_embree = self.scenes.iter().any(|s| s.embree.is_some());
        let _ = writeln!(
            out,
            "Mrays/s. `1`: one ray per query; `64`: batches of 64 neighbouring rays (our packets, Embree's coherent streams). Our `any 1` carries an any-hit hint from ray to ray on each thread (Embree has none); `any 1 no hint` is the same query without it. `rays that hit`: the share of the scene's rays with a closest hit (camera rays, one per pixel; for `shadow rays`, rays toward a light from the points the full-HD view's camera rays hit); a miss costs any hit as much as closest hit, so where few rays hit, `any 1 / closest 1` stays near 1. `on hits`: the same two queries over the rays that hit alone, in their order: what any hit saves on a hit, which the hint makes most of; where neighbouring rays hit far apart (the torus at 320x180), little, a hit costing either query one descent of the tree. `compute loop / 1 thread`: how much faster a loop of floating-point work that touches no memory ran on these threads than on one, in the same rounds: what the machine's cores allowed then.\n"
        );
        let _ = writeln!(
            out,
            "| scene | primitives | rays that hit | threads | closest 1 | closest 64 | any 1 | any 1 no hint | any 64 | any 1 / closest 1 | any 1 / closest 1 on hits |{} compute loop / 1 thread |",
            if with_embree {
                " Embree closest 1 | Embree closest 64 | Embree any 1 | Embree any 64 | closest 1 / Embree 1 | closest 64 / Embree 1 | closest 64 / Embree 64 |"
            } else {
                ""
            }
        );
        let _ = writeln!(
            out,
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|{}---:|",
            if with_embree {
                "---:|---:|---:|---:|---:|---:|---:|"
            } else {
                ""
            }
        );
        for s in &self.scenes {
            let primitives = if s.triangles > 0 {
                format!("{} triangles", s.triangles)
            } else {
                format!("{} spheres", s.spheres)
            };
            for (i, t) in s.raybatch.throughput.iter().enumerate() {
                let _ = write!(
                    out,
                    "| {} | {} | {:.1}% | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2}x | {} |",
                    s.name,
                    primitives,
                    100.0 * s.hits as f64 / s.rays.max(1) as f64,
                    t.threads,
                    t.closest,
                    t.closest_batch,
                    t.any,
                    t.any_unhinted,
                    t.any_batch,
                    t.any / t.closest,
                    ratio(t.any_on_hits, t.closest_on_hits)
                );
                if let Some(e) = s.embree.as_ref().and_then(|e| e.throughput.get(i)) {
                    let _ = write!(
                        out,
                        " {:.2} | {:.2} | {:.2} | {:.2} | {:.2}x | {:.2}x | {:.2}x |",
                        e.closest,
                        e.closest_batch,
                        e.any,
                        e.any_batch,
                        t.closest / e.closest,
                        t.closest_batch / e.closest,
                        t.closest_batch / e.closest_batch
                    );
                }
                let scaling = s.compute_loop_scaling.get(i).copied().flatten();
                let _ = writeln!(
                    out,
                    " {} |",
                    scaling.map_or("-".to_string(), |x| format!("{x:.2}x"))
                );
            }
        }
        let _ = writeln!(out);
        let _ = writeln!(
            out,
            "| scene | triangle tree preset | build s | Embree build s | build / Embree | `{default}` build s | `{default}` / Embree | load s | load MB/s | scene bytes/primitive | peak RSS growth bytes/triangle |",
            default = BuildPreset::default().name()
        );
        let _ = writeln!(
            out,
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
        );
        for s in &self.scenes {
            let over_embree = |build_s: f64| {
                s.embree
                    .as_ref()
                    .map_or("-".to_string(), |e| format!("{:.2}x", build_s / e.build_s))
            };
            let _ = writeln!(
                out,
                // Build seconds to a tenth of a millisecond: the sphere field's take one or two.
                "| {} | {} | {:.4} | {} | {} | {} | {} | {} | {} | {:.0} | {} |",
                s.name,
                s.triangle_tree_preset.unwrap_or("-"),
                s.raybatch.build_s,
                s.embree
                    .as_ref()
                    .map_or("-".to_string(), |e| format!("{:.4}", e.build_s)),
                over_embree(s.raybatch.build_s),
                s.default_build_s
                    .map_or("-".to_string(), |b| format!("{b:.4}")),
                s.default_build_s.map_or("-".to_string(), over_embree),
                s.load.map_or("-".to_string(), |l| format!("{:.3}", l.0)),
                s.load.map_or("-".to_string(), |l| format!("{:.0}", l.1)),
                s.scene_bytes_per_primitive,
                s.peak_bytes_per_triangle
                    .map_or("-".to_string(), |b| format!("{b:.0}")),
            );
        }
        let _ = writeln!(out);
        let _ = writeln!(
            out,
            "| job | jobs | seconds | per job ms | Embree backend seconds | Embree / raybatch |"
        );
        let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|");
        for j in &self.jobs {
            let (embree, ratio) = j.embree_seconds.map_or(("-".into(), "-".into()), |e| {
                (format!("{e:.3}"), format!("{:.2}x", e / j.seconds))
            });
            let _ = writeln!(
                out,
                "| {} | {} | {:.3} | {:.2} | {embree} | {ratio} |",
                j.name,
                j.jobs,
                j.seconds,
                1e3 * j.seconds / j.jobs as f64
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two threads taking turns at a pass's tasks share its rays within 2% of evenly, for
    /// images from 160x120 to full HD, and every task is whole 64-ray groups, at most 4096
    /// rays.
    #[test]
    fn two_threads_share_a_pass_evenly() {
        for (width, height) in [
            (160, 120),
            (320, 180),
            (640, 480),
            (1280, 720),
            (1920, 1080),
        ] {
            let rays = width * height;
            let len = task_len(rays);
            assert!(
                len.is_multiple_of(64) && len <= 4096,
                "{width}x{height}: {len}"
            );
            let tasks = rays.div_ceil(len);
            let busiest = (tasks.div_ceil(2) * len).min(rays);
            let share = busiest as f64 / (rays as f64 / 2.0);
            assert!(share <= 1.02, "{width}x{height}: {tasks} tasks, {share}");
        }
        for rays in [0, 1, 63, 64, 65, 4097] {
            let len = task_len(rays);
            assert!(
                len >= 64 && len.is_multiple_of(64) && len <= 4096,
                "{rays}: {len}"
            );
        }
    }

    /// Builds are timed in turns, each turn one untimed build and then timed ones, until
    /// every builder has builds enough: builders of 10 ms each take several turns (a turn
    /// lasts 50 ms), every run of one builder's calls holds at least two, and each builder
    /// reports at least one time fewer than its calls per run. (A run may hold two turns,
    /// when the other builder had enough first.)
    #[test]
    fn builds_are_timed_in_turns_each_after_an_untimed_build() {
        let calls = std::cell::RefCell::new(Vec::new());
        let builder = |who: usize| {
            let calls = &calls;
            move || {
                calls.borrow_mut().push(who);
                std::thread::sleep(std::time::Duration::from_millis(10));
                Ok(())
            }
        };
        let (mut a, mut b) = (builder(0), builder(1));
        let times = time_builds_in_turns(&mut [&mut a, &mut b]).unwrap();
        let calls = calls.into_inner();
        let mut turns = [0; 2];
        for run in calls.chunk_by(|x, y| x == y) {
            assert!(run.len() >= 2, "a turn of one call: {calls:?}");
            turns[run[0]] += 1;
        }
        for who in 0..2 {
            assert!(builds_enough(&times[who]), "{who}: {:?}", times[who]);
            assert!(turns[who] >= 2, "{who} built in one turn: {calls:?}");
            let made = calls.iter().filter(|&&c| c == who).count();
            assert!(times[who].len() <= made - turns[who], "{calls:?}");
        }
    }

    /// No task of a pass waits on another held by a busy thread: on two threads, the
    /// task holding the first ray waits until every other task is done, which they can
    /// be only if the other thread takes each of them (had rayon run the first task's
    /// neighbours in one job with it, they would never be).
    #[test]
    fn a_busy_thread_holds_no_task_but_its_own() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        // Eight tasks of 4096.
        let items = vec![0u8; 8 * 4096];
        let others = items.len().div_ceil(task_len(items.len())) - 1;
        assert_eq!(others, 7);
        let done = AtomicUsize::new(0);
        let waited = pool.install(|| {
            tasks(&items)
                .map(|task| {
                    if !std::ptr::eq(task.as_ptr(), items.as_ptr()) {
                        done.fetch_add(1, Ordering::SeqCst);
                        return true;
                    }
                    let start = Instant::now();
                    while done.load(Ordering::SeqCst) < others {
                        if start.elapsed().as_secs() >= 20 {
                            return false;
                        }
                        std::thread::yield_now();
                    }
                    true
                })
                .all(|finished| finished)
        });
        assert!(waited, "{} of {others} other tasks done", done.into_inner());
    }

    /// A shadow ray starts where its camera ray hit and ends at the light: camera rays
    /// straight down onto a floor at y = 0 (two triangles, x and z in [-4, 4]) make rays
    /// from (x, 0, z) toward a light at (0, 10, 0), which the floor they leave never
    /// stops (though their float32 hits lie a little below it, where a search from t = 0
    /// would meet it) and a square at y = 5 over x, z in [-1, 1] stops exactly where the
    /// line to the light crosses it (|x|, |z| < 2). A camera ray that misses makes none.
    #[test]
    fn shadow_rays_leave_the_hit_surface_for_the_light() {
        let square = |y: f32, half: f32| {
            let [a, b, c, d] = [[-1, -1], [1, -1], [1, 1], [-1, 1]]
                .map(|[x, z]| [x as f32 * half, y, z as f32 * half]);
            [[a, b, c], [a, c, d]]
        };
        let light = DVec3::new(0.0, 10.0, 0.0);
        let down = |x: f64, z: f64| Ray {
            // 2.7 rounds up in float32, and so does the float32 hit's distance.
            origin: DVec3::new(x, 2.7, z),
            direction: DVec3::NEG_Y,
            tmin: 0.0,
            tmax: f64::INFINITY,
        };
        let camera: Vec<Ray> = [-3.5, -2.5, -1.5, -0.5, 0.5, 1.5, 2.5, 3.5, 4.5]
            .into_iter()
            .flat_map(|x| [-1.25, 0.75, 2.25].map(|z| down(x, z)))
            .collect();
        for blocker in [false, true] {
            let mut geometry = SceneGeometry::default();
            geometry.triangles.extend(square(0.0, 4.0));
            if blocker {
                geometry.triangles.extend(square(5.0, 1.0));
            }
            let scene = Scene::build(&geometry);
            let shadows = shadow_rays(&scene, &camera, light);
            let hitting: Vec<&Ray> = camera.iter().filter(|r| r.origin.x < 4.0).collect();
            assert_eq!(shadows.len(), hitting.len(), "blocker {blocker}");
            for (shadow, ray) in shadows.iter().zip(hitting) {
                let floor = DVec3::new(ray.origin.x, 0.0, ray.origin.z);
                assert!((shadow.origin - floor).length() < 1e-6, "{shadow:?}");
                assert!(
                    (shadow.at(shadow.tmax) - light).length() < 1e-6,
                    "{shadow:?}"
                );
                let crossing = (floor.x.abs().max(floor.z.abs())) < 2.0;
                assert_eq!(
                    scene.any_hit(shadow),
                    blocker && crossing,
                    "blocker {blocker}: {shadow:?}"
                );
            }
        }
    }

    /// The shadow rays' row traces one ray for each camera ray of its view that hits (as
    /// many as the plain view's closest-hit pass counts), and its light is placed so that
    /// some of them are stopped and some reach it.
    #[test]
    fn the_shadow_row_traces_a_ray_for_each_camera_ray_that_hits() {
        let dir = tempfile::tempdir().unwrap();
        let options = quick_options(&[1]);
        let file = torus_file(dir.path(), 40, 20);
        let view = || mesh_scene("torus", &file, (48, 32)).unwrap();
        let plain = trace_scene(view(), &options, 1).unwrap();
        let shadow = trace_scene(toward_shadow_light(view()), &options, 1).unwrap();
        assert!(
            plain.hits > 100 && plain.hits < plain.rays,
            "{}",
            plain.hits
        );
        assert_eq!(shadow.rays, plain.hits);
        assert!(
            shadow.hits > shadow.rays / 4 && shadow.hits < shadow.rays * 9 / 10,
            "{} of {}",
            shadow.hits,
            shadow.rays
        );
    }

    /// Many of the shadow rays' any-hit packets are judged better left to hinted single
    /// rays ([`crate::packet::Visits::hints_pay`]), the camera rays' of the same view
    /// hardly ever: the bench's view of a 160,000-triangle torus at 640x360, each group
    /// of 64 rays as the batch queries take them, of the packets that reach enough
    /// leaves to be judged. The batch queries, switching between the two ways, answer as
    /// the scalar path does ray by ray.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn shadow_rays_give_their_any_hit_packets_to_hints_and_camera_rays_do_not() {
        if !crate::simd::available() {
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let file = torus_file(dir.path(), 400, 200);
        let view = toward_shadow_light(mesh_scene("torus", &file, (640, 360)).unwrap());
        let mut scene = Scene::build(&view.geometry);
        let camera = camera_rays(&view);
        let shadow = shadow_rays(&scene, &camera, view.light.unwrap());
        scene.set_simd(false);
        let scalar: Vec<bool> = shadow.iter().map(|r| scene.any_hit(r)).collect();
        scene.set_simd(true);
        let mut batch = vec![false; shadow.len()];
        scene.any_hits(&shadow, &mut batch);
        assert!(batch == scalar, "the batch queries' answers differ");
        // (packets judged, and how many of them the hint pays for)
        let judged = |rays: &[Ray]| {
            let judged: Vec<_> = (rays.chunks(crate::packet::PACKET))
                .filter_map(|group| scene.any_hit_packet_visits(group))
                .filter(|visits| visits.leaves >= crate::packet::Visits::JUDGED_FROM)
                .collect();
            let pay = judged.iter().filter(|visits| visits.hints_pay()).count();
            (judged.len(), pay)
        };
        let (shadow_judged, shadow_pay) = judged(&shadow);
        let (camera_judged, camera_pay) = judged(&camera);
        // Here 391 of 756 and 16 of 634 (on the bench's full-HD view of its
        // million-triangle torus, 3,275 of 6,800 shadow rays' packets and 18 of 4,480
        // camera rays': a probe, not kept, DEVELOPERS.md "Hinted single rays take over
        // from some any-hit packets").
        assert!(
            shadow_judged > 100 && 3 * shadow_pay > shadow_judged,
            "shadow rays: {shadow_pay} of {shadow_judged}"
        );
        assert!(
            camera_judged > 100 && 20 * camera_pay < camera_judged,
            "camera rays: {camera_pay} of {camera_judged}"
        );
    }

    /// The bench builds its triangle tree as a job tracing all its passes' rays would: at
    /// 32x32, two thread counts and one counted round (plus the warm-up), 1024 rays × 5
    /// queries × 2 × 2 = 20,480 rays, enough for reinsertion (64 rays per triangle) on 240
    /// triangles and not on 400. Counting one pass, or leaving out the queries, the thread
    /// counts or the warm-up round, gives 240 triangles the default.
    #[test]
    fn the_bench_builds_its_tree_for_every_ray_it_traces() {
        let dir = tempfile::tempdir().unwrap();
        let options = quick_options(&[1, 2]);
        for ((rings, sides), preset) in [((12, 10), "very fast"), ((20, 10), "fastest")] {
            let file = torus_file(dir.path(), rings, sides);
            let scene = mesh_scene("torus", &file, (32, 32)).unwrap();
            let figures = trace_scene(scene, &options, 1).unwrap();
            assert_eq!(figures.triangles, 2 * (rings * sides) as usize);
            assert_eq!(
                figures.triangle_tree_preset,
                Some(preset),
                "{rings}x{sides}"
            );
            // The default preset's build is timed too where the traced tree is another.
            assert_eq!(
                figures.default_build_s.is_some(),
                preset != "fastest",
                "{rings}x{sides}"
            );
        }
    }

    /// The `on hits` passes trace the rays that hit and no other, once each, and the
    /// other passes every ray: a tracer that counts its queries, over a torus seen at
    /// 96x54, as the bench sees its torus (a fifth of the rays hit).
    #[test]
    fn the_on_hits_passes_trace_the_rays_that_hit_alone() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        // (closest-hit queries, any-hit queries)
        struct Counting<'a> {
            scene: &'a Scene,
            queries: [AtomicUsize; 2],
        }
        impl Tracer for Counting<'_> {
            fn closest_hit(&self, ray: &Ray) -> Option<crate::Hit> {
                self.queries[0].fetch_add(1, Ordering::Relaxed);
                self.scene.closest_hit(ray)
            }
            fn any_hit(&self, ray: &Ray) -> bool {
                self.queries[1].fetch_add(1, Ordering::Relaxed);
                self.scene.any_hit(ray)
            }
            fn normal(&self, ray: &Ray, hit: &crate::Hit) -> DVec3 {
                self.scene.normal(ray, hit)
            }
            fn triangle_id(&self, slot: u32) -> u32 {
                self.scene.triangle_id(slot)
            }
            fn counts(&self) -> crate::scene::SceneCounts {
                self.scene.counts()
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let view = mesh_scene("torus", &torus_file(dir.path(), 40, 20), (96, 54)).unwrap();
        let scene = Scene::build(&view.geometry);
        let rays = camera_rays(&view);
        let hit_rays = rays_that_hit(&scene, &rays);
        // The same rays, found one by one in order by the scalar path.
        let mut scalar = Scene::build(&view.geometry);
        scalar.set_simd(false);
        let expected: Vec<Ray> = rays
            .iter()
            .filter(|r| scalar.closest_hit(r).is_some())
            .copied()
            .collect();
        assert!(hit_rays == expected, "not the rays that hit, in order");
        assert!(
            8 * hit_rays.len() > rays.len() && 2 * hit_rays.len() < rays.len(),
            "{} of {} rays hit",
            hit_rays.len(),
            rays.len()
        );
        let tracer = Counting {
            scene: &scene,
            queries: [AtomicUsize::new(0), AtomicUsize::new(0)],
        };
        let (hits, all) = (hit_rays.len(), rays.len());
        for (query, expected) in [
            (Query::ClosestOnHits, [hits, 0]),
            (Query::AnyHintedOnHits, [0, hits]),
            (Query::Closest, [all, 0]),
            (Query::AnyHinted, [0, all]),
            (Query::Any, [0, all]),
        ] {
            let found = trace_pass(&tracer, query.rays(&rays, &hit_rays), query);
            let queries = tracer
                .queries
                .each_ref()
                .map(|q| q.swap(0, Ordering::Relaxed));
            assert_eq!((found, queries), (hits, expected), "{query:?}");
        }
    }

    /// `--quick` options tracing on `threads`, without Embree.
    fn quick_options(threads: &[usize]) -> BenchOptions {
        BenchOptions {
            quick: true,
            models: None,
            threads: threads.to_vec(),
            only: Vec::new(),
            embree: false,
            eight_lane_packets: false,
        }
    }

    /// The bench's torus of `rings × sides` quads ([`write_torus`]), as a file in `dir`.
    fn torus_file(dir: &Path, rings: u32, sides: u32) -> PathBuf {
        let file = dir.join(format!("torus-{rings}-{sides}.obj"));
        write_torus(&file, rings, sides).unwrap();
        file
    }
}
