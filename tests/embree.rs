//! The Embree reference backend (cargo feature `embree`): verification of every shipped and
//! stress scene, `render --backend embree` (the canonical image, the strict interval, the
//! contract's normals), watertightness cross-checked with Embree, the rays the backend
//! must keep from Embree or bound for it (NaN, huge, starting on a surface), and `verify`
//! tracing the tree a render builds.

use std::sync::Arc;

use glam::{DMat4, DVec3};
use raybatch::embree::EmbreeScene;
use raybatch::mesh::MeshFile;
use raybatch::scene::Tracer;
use raybatch::{Ray, Scene, SceneGeometry, procedural};
use serde_json::Value;

use crate::util::{Dir, assert_normal_colour, default_camera_direction, pfm, ppm, repo};

#[test]
fn every_shipped_and_stress_scene_agrees_with_embree() {
    let dir = Dir::new();
    let (scenes, stress) = (repo("scenes"), repo("scenes/stress"));
    let run = dir.raybatch(&[
        "verify",
        scenes.to_str().unwrap(),
        stress.to_str().unwrap(),
        "--json",
        "--max-mask-fraction",
        "0",
        "--max-depth-p999",
        "2e-6",
    ]);
    assert_eq!(run.status, 0, "{}\n{}", run.stdout, run.stderr);
    let lines: Vec<Value> = run
        .stdout
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert!(lines.len() >= 13, "{}", run.stdout);
    for line in &lines {
        assert_eq!(line["ok"], true, "{line}");
        assert_eq!(line["depth"]["mask_disagreements"], 0, "{line}");
        assert!(line["rays"].as_u64().unwrap() > 1000);
        assert!(line["depth"]["both_hit"].as_u64().unwrap() > 0, "{line}");
    }
}

#[test]
fn verify_fails_past_its_limits() {
    let dir = Dir::new();
    let canonical = repo("scenes/canonical.json");
    let run = dir.raybatch(&[
        "verify",
        canonical.to_str().unwrap(),
        "--max-depth-p999",
        "1e-9",
    ]);
    assert_eq!(run.status, 1, "{}", run.stderr);
    assert!(
        run.stderr.contains("limit exceeded") && run.stderr.contains("p99.9"),
        "{}",
        run.stderr
    );
}

#[test]
fn verify_times_its_median_pass_and_compares_the_first() {
    // Three passes each: the same rays and the same comparison as one pass (the tracers
    // are deterministic, and only the first pass's distances are compared), and the
    // passes are reported.
    let dir = Dir::new();
    let canonical = repo("scenes/canonical.json");
    let mut runs = Vec::new();
    for passes in ["1", "3"] {
        let run = dir.raybatch(&[
            "verify",
            canonical.to_str().unwrap(),
            "--json",
            "--passes",
            passes,
        ]);
        assert_eq!(run.status, 0, "{}\n{}", run.stdout, run.stderr);
        let line: Value = serde_json::from_str(run.stdout.trim()).unwrap();
        assert_eq!(line["passes"].to_string(), passes, "{line}");
        for tracer in ["raybatch", "embree", "embree_single"] {
            let seconds = &line[format!("trace_{tracer}_s")];
            assert!(seconds.as_f64().unwrap() > 0.0, "{line}");
        }
        runs.push(line);
    }
    assert_eq!(runs[0]["rays"], 640 * 480);
    assert_eq!(runs[0]["rays"], runs[1]["rays"]);
    assert_eq!(runs[0]["depth"], runs[1]["depth"]);
    assert_eq!(runs[1]["depth"]["samples"], 640 * 480, "{}", runs[1]);
    // The summary line names the passes only when there are several, and each way timed.
    let text = dir.raybatch(&["verify", canonical.to_str().unwrap(), "--passes", "3"]);
    assert_eq!(text.status, 0, "{}", text.stderr);
    for words in [
        "(median of 3 passes)",
        "embree streams",
        "embree single rays",
    ] {
        assert!(text.stdout.contains(words), "{words}: {}", text.stdout);
    }
}

#[test]
fn verify_traces_the_tree_a_render_builds() {
    // The torus's 2,304 triangles: 49,152 camera rays are too few for reinsertion, four
    // samples a pixel enough (64 rays a triangle). `verify` must check the tree the render
    // traces, whichever it is.
    let dir = Dir::new();
    let torus = repo("models/torus.obj");
    for (name, spp) in [("few.json", 1), ("many.json", 4)] {
        dir.write(
            name,
            format!(
                r#"{{"image": {{"width": 256, "height": 192}}, "integrator": {{"type": "depth"}},
                    "camera": {{"look_from": [0, 3, 4], "look_at": [0, 0, 0], "vfov": 40}},
                    "sampler": {{"type": "independent", "spp": {spp}}},
                    "meshes": [{{"file": {:?}}}]}}"#,
                torus.display().to_string()
            ),
        );
    }
    let mut presets = Vec::new();
    for name in ["few.json", "many.json"] {
        let render = dir.raybatch(&["render", name, "--stats", "stats.jsonl"]);
        assert_eq!(render.status, 0, "{}", render.stderr);
        let stats: Value = serde_json::from_slice(&dir.read("stats.jsonl")).unwrap();
        let verify = dir.raybatch(&["verify", name, "--json"]);
        assert_eq!(verify.status, 0, "{}\n{}", verify.stdout, verify.stderr);
        let verified: Value = serde_json::from_str(verify.stdout.trim()).unwrap();
        assert_eq!(
            verified["triangle_tree_preset"], stats["triangle_tree_preset"],
            "{name}"
        );
        presets.push(stats["triangle_tree_preset"].clone());
    }
    assert_eq!(presets, ["fastest", "very fast"]);
}

#[test]
fn the_embree_backend_renders_the_canonical_scene_exactly() {
    let dir = Dir::new();
    dir.write(
        "canonical.json",
        r#"{"image": {"width": 640, "height": 480}, "spheres": [{"center": [0, 0, 3], "radius": 1}]}"#,
    );
    let run = dir.raybatch(&[
        "render",
        "canonical.json",
        "--backend",
        "embree",
        "--stats",
        "s.json",
    ]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    assert_eq!(ppm(&dir.read("canonical.ppm")).count([255; 3]), 22_632);
    let stats: Value = serde_json::from_slice(&dir.read("s.json")).unwrap();
    assert_eq!(stats["backend"], "embree");
}

#[test]
fn the_embree_backend_keeps_the_strict_interval_and_the_contract_s_normals() {
    let dir = Dir::new();
    let render = |name: &str, body: &str| {
        dir.write(&format!("{name}.json"), body);
        let run = dir.raybatch(&["render", &format!("{name}.json"), "--backend", "embree"]);
        assert_eq!(run.status, 0, "{name}: {}", run.stderr);
        pfm(&dir.read(&format!("{name}.pfm")))
    };
    // A triangle at exactly t = 2 on the centre ray: outside the interval at either end.
    dir.write("tri.obj", "v -1 -1 2\nv 1 -1 2\nv 0 1 2\nf 1 2 3\n");
    for (name, interval, expected) in [
        ("at-tmin", r#""tmin": 2"#, 0.0),
        ("at-tmax", r#""tmax": 2"#, 0.0),
        ("inside", r#""tmin": 1.999, "tmax": 2.001"#, 2.0),
    ] {
        let body = format!(
            r#"{{"image": {{"width": 11, "height": 11}}, "output": "{name}.pfm",
                "integrator": {{"type": "depth"}}, {interval},
                "meshes": [{{"file": "tri.obj"}}]}}"#
        );
        assert_eq!(render(name, &body).at(5, 5)[0], expected, "{name}");
    }
    // Normals, one primitive at a time, against the contract's formulas in float64: a
    // sphere's (p − c)/r, a plane's normal normalized, a triangle's cross(v1 − v0, v2 − v0)
    // in stored order (pointing away from the camera, not flipped toward it).
    let (w, h) = (24u32, 18u32);
    const CENTER: DVec3 = DVec3::new(0.3, 0.1, 4.0);
    const POINT: DVec3 = DVec3::new(0.0, -1.0, 0.0);
    const NORMAL: DVec3 = DVec3::new(0.0, 3.0, -0.7);
    type Expected = fn(DVec3) -> Option<DVec3>;
    let scenes: [(&str, &str, Expected); 3] = [
        (
            "sphere",
            r#""spheres": [{"center": [0.3, 0.1, 4], "radius": 2}]"#,
            |d| {
                let b = d.dot(CENTER);
                let disc = b * b - (CENTER.length_squared() - 4.0);
                (disc > 1e-6).then(|| (d * (b - disc.sqrt()) - CENTER) / 2.0)
            },
        ),
        (
            "plane",
            r#""planes": [{"point": [0, -1, 0], "normal": [0, 3, -0.7]}]"#,
            |d| {
                // Rays nearly parallel to the plane are left out.
                let t = NORMAL.dot(POINT) / NORMAL.dot(d);
                (t > 1e-3 && t < 1e3).then(|| NORMAL.normalize())
            },
        ),
        (
            "triangle",
            r#""meshes": [{"file": "tri.obj", "transform": {"scale": 3}}]"#,
            |d| {
                // The scaled triangle at z = 6: (−3, −3), (3, −3), (0, 3).
                let p = d * (6.0 / d.z);
                let inside = p.y > -3.0 + 1e-3 && p.y < 3.0 - 2.0 * p.x.abs() - 1e-3;
                let edges = (DVec3::new(6.0, 0.0, 0.0), DVec3::new(3.0, 6.0, 0.0));
                inside.then(|| edges.0.cross(edges.1).normalize())
            },
        ),
    ];
    for (name, primitive, expected) in scenes {
        let body = format!(
            r#"{{"image": {{"width": {w}, "height": {h}}}, "output": "{name}.pfm",
                "integrator": {{"type": "normal"}}, {primitive}}}"#
        );
        let image = render(name, &body);
        let mut checked = 0;
        for y in 0..h {
            for x in 0..w {
                let d = DVec3::from_array(default_camera_direction(x, y, w, h));
                let Some(n) = expected(d) else { continue };
                let got = image.at(x as usize, y as usize);
                assert_normal_colour(got, n.to_array(), 1e-5, &format!("{name} ({x}, {y})"));
                checked += 1;
            }
        }
        assert!(checked > 30, "{name}: {checked} pixels");
    }
}

#[test]
fn rays_embree_does_not_take_hit_nothing_and_spoil_no_other_rays_answer() {
    // Embree asserts, aborting the process, on a NaN bound or an origin or direction
    // component beyond 1.844e18: a lens focused closer than its origin's precision made a
    // NaN direction, and `verify` and `render --backend embree` ended there.
    let mesh = Arc::new(MeshFile::one_geometry(procedural::icosphere(2)));
    let mut geometry = SceneGeometry::default();
    geometry
        .add_mesh(&mesh, DMat4::IDENTITY, "ico".as_ref())
        .unwrap();
    geometry.spheres.push(raybatch::sphere::Sphere {
        center: DVec3::new(0.0, 0.0, 3.0),
        radius: 0.5,
    });
    let reference = EmbreeScene::build(&geometry).unwrap();
    let good = |target: DVec3| {
        let origin = DVec3::new(0.1, 0.2, -4.0);
        Ray {
            origin,
            direction: (target - origin).normalize(),
            tmin: 0.0,
            tmax: f64::INFINITY,
        }
    };
    let (ico, sphere) = (good(DVec3::ZERO), good(DVec3::new(0.0, 0.0, 3.0)));
    assert!(reference.closest_hit(&ico).is_some() && reference.any_hit(&sphere));
    let spoilt = [
        Ray {
            direction: DVec3::NAN,
            ..ico
        },
        Ray {
            origin: DVec3::new(0.0, 1e19, 0.0),
            ..ico
        },
        Ray {
            direction: DVec3::new(2e18, 0.0, 0.0),
            ..ico
        },
        Ray {
            tmin: f64::NAN,
            ..ico
        },
        Ray {
            tmax: f64::NAN,
            ..sphere
        },
    ];
    for ray in &spoilt {
        assert_eq!(reference.closest_hit(ray), None, "{ray:?}");
        assert!(!reference.any_hit(ray), "{ray:?}");
    }
    // In streams, between rays that hit.
    let rays: Vec<Ray> = spoilt.iter().flat_map(|&r| [ico, r, sphere]).collect();
    let mut closest = vec![None; rays.len()];
    let mut any = vec![false; rays.len()];
    reference.closest_hits(&rays, &mut closest);
    reference.any_hits(&rays, &mut any);
    for (k, ray) in rays.iter().enumerate() {
        let hits = k % 3 != 1;
        assert_eq!(closest[k].is_some(), hits, "{k}: {ray:?}");
        assert_eq!(any[k], hits, "{k}: {ray:?}");
    }
}

#[test]
fn a_ray_starting_on_a_triangle_does_not_hit_it_at_t_zero_in_either_tracer() {
    // Hits count for `tmin < t` only. Embree's threads read subnormals as zero and its
    // test is inclusive, so a near bound of `next_up(0)` let these rays hit at `t = 0`
    // (random manifests found it: a camera placed on a glTF quad).
    let mesh = Arc::new(MeshFile::one_geometry(procedural::cube()));
    let mut geometry = SceneGeometry::default();
    geometry
        .add_mesh(&mesh, DMat4::IDENTITY, "cube".as_ref())
        .unwrap();
    let ours = Scene::build(&geometry);
    let reference = EmbreeScene::build(&geometry).unwrap();
    let (lo, hi) = geometry
        .triangles
        .iter()
        .flatten()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v[2]), hi.max(v[2]))
        });
    let mut checked = 0;
    for z in [lo, hi] {
        for (x, y) in [(0.0, 0.0), (0.1, -0.2), (-0.3, 0.05)] {
            // Leaving the cube through the face the ray starts on, and along it.
            for direction in [
                DVec3::new(0.1, 0.2, -1.0),
                DVec3::new(0.3, -0.1, 1.0),
                DVec3::X,
            ] {
                let outward = f64::from(z) * direction.z > 0.0 || direction.z == 0.0;
                if !outward {
                    continue;
                }
                let ray = Ray {
                    origin: DVec3::new(x, y, f64::from(z)),
                    direction: direction.normalize(),
                    tmin: 0.0,
                    tmax: f64::INFINITY,
                };
                let (a, b) = (
                    Tracer::closest_hit(&ours, &ray),
                    reference.closest_hit(&ray),
                );
                assert!(a.is_none_or(|h| h.t > 0.0), "raybatch: {a:?} for {ray:?}");
                assert!(b.is_none_or(|h| h.t > 0.0), "Embree: {b:?} for {ray:?}");
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 12);
}

#[test]
fn embree_in_robust_mode_agrees_that_nothing_leaks() {
    let mesh = Arc::new(MeshFile::one_geometry(procedural::icosphere(3)));
    let mut geometry = SceneGeometry::default();
    let transform =
        DMat4::from_translation(DVec3::new(0.3, -1.1, 2.0)) * DMat4::from_scale(DVec3::splat(3.7));
    geometry.add_mesh(&mesh, transform, "ico".as_ref()).unwrap();
    let targets: Vec<DVec3> = geometry
        .triangles
        .iter()
        .flat_map(|t| {
            let p = t.map(|v| DVec3::from_array(v.map(f64::from)));
            [p[0], (p[0] + p[1]) / 2.0, p[0] + (p[2] - p[0]) * 0.3]
        })
        .collect();
    let ours = Scene::build(&geometry);
    let reference = EmbreeScene::build(&geometry).unwrap();
    let origin = DVec3::new(0.3, -1.1, 2.0);
    for target in targets {
        let ray = Ray {
            origin,
            direction: (target - origin).normalize(),
            tmin: 0.0,
            tmax: f64::INFINITY,
        };
        let a = Tracer::closest_hit(&ours, &ray).expect("raybatch leaked");
        let b = reference.closest_hit(&ray).expect("Embree leaked");
        assert!((a.t - b.t).abs() <= 1e-5 * b.t, "{} vs {}", a.t, b.t);
        assert!(reference.any_hit(&ray));
    }
}

#[test]
#[ignore = "needs RAYBATCH_MODELS (the scanned models of ../shared/models)"]
fn scanned_models_agree_with_embree() {
    let models = crate::util::folder("RAYBATCH_MODELS");
    let dir = Dir::new();
    let mut count = 0;
    for entry in std::fs::read_dir(&models).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "obj") {
            continue;
        }
        // Frame each model from its bounds, from two sides.
        let mesh = raybatch::mesh::load(&path).unwrap();
        let points = mesh.geometries.iter().flat_map(|g| g.positions.iter());
        let (lo, hi) = points.fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), p| {
                let p = DVec3::from_array(p.map(f64::from));
                (lo.min(p), hi.max(p))
            },
        );
        let (centre, radius) = ((lo + hi) / 2.0, (hi - lo).length() / 2.0);
        for (side, eye) in [
            ("front", DVec3::new(0.4, 0.3, 1.0)),
            ("back", DVec3::new(-0.7, -0.2, -1.0)),
        ] {
            let from = centre + eye.normalize() * radius * 2.2;
            let stem = path.file_stem().unwrap().to_string_lossy();
            dir.write(
                &format!("{stem}-{side}.json"),
                format!(
                    r#"{{"image": {{"width": 256, "height": 192}}, "integrator": {{"type": "depth"}},
                        "camera": {{"look_from": [{}, {}, {}], "look_at": [{}, {}, {}], "vfov": 40}},
                        "meshes": [{{"file": {:?}}}]}}"#,
                    from.x, from.y, from.z, centre.x, centre.y, centre.z,
                    path.display().to_string()
                ),
            );
            count += 1;
        }
    }
    assert!(count >= 10);
    let run = dir.raybatch(&[
        "verify",
        ".",
        "--json",
        "--max-mask-fraction",
        "1e-4",
        "--max-depth-p999",
        "1e-5",
    ]);
    assert_eq!(run.status, 0, "{}\n{}", run.stdout, run.stderr);
    for line in run.stdout.lines() {
        let line: Value = serde_json::from_str(line).unwrap();
        assert!(
            line["depth"]["both_hit"].as_u64().unwrap() > 1000,
            "model not in view: {line}"
        );
    }
}
