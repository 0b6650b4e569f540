//! The seed's scene, pixel for pixel, and the properties every image must have.

use crate::util::{Dir, ppm, repo};

const CANONICAL: &str =
    r#"{"image": {"width": 640, "height": 480}, "spheres": [{"center": [0, 0, 3], "radius": 1}]}"#;

/// The canonical mask in integers. The default camera's pixel-centre ray has direction
/// `(u, v, 1)` with `u = (2x + 1 − 640) / 480` and `v = (479 − 2y) / 480`; it passes within
/// distance 1 of `(0, 0, 3)` when `|c × d|² < |d|²`, i.e. `8(a² + b²) < 480²` with
/// `a = 2x − 639`, `b = 479 − 2y`.
fn canonical_mask(x: i64, y: i64) -> bool {
    let (a, b) = (2 * x - 639, 479 - 2 * y);
    8 * (a * a + b * b) < 480 * 480
}

#[test]
fn the_canonical_scene_is_exact_pixel_for_pixel() {
    let dir = Dir::new();
    let image = dir.ppm_of("canonical.json", CANONICAL, "canonical.ppm");
    assert_eq!(image.magic, "P3");
    assert_eq!((image.width, image.height), (640, 480));
    let mut white = 0;
    for y in 0..480 {
        for x in 0..640 {
            let expected = if canonical_mask(x as i64, y as i64) {
                white += 1;
                [255, 255, 255]
            } else {
                [0, 0, 0]
            };
            assert_eq!(image.at(x, y), expected, "pixel ({x}, {y})");
        }
    }
    assert_eq!(white, 22_632);
}

#[test]
fn the_shipped_canonical_manifest_is_the_seed_scene() {
    let dir = Dir::new();
    let manifest = repo("scenes/canonical.json");
    let run = dir.raybatch(&["render", manifest.to_str().unwrap(), "--out", "out"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    let image = ppm(&dir.read("out/canonical.ppm"));
    assert_eq!(image.count([255, 255, 255]), 22_632);
    assert_eq!(image.count([0, 0, 0]), 640 * 480 - 22_632);
}

#[test]
fn binary_ppm_holds_the_same_pixels() {
    let dir = Dir::new();
    let plain = dir.ppm_of("plain.json", CANONICAL, "plain.ppm");
    let binary_json = CANONICAL.replacen('{', r#"{"ppm": "binary", "#, 1);
    let binary = dir.ppm_of("binary.json", &binary_json, "binary.ppm");
    assert_eq!(binary.magic, "P6");
    assert_eq!(binary.pixels, plain.pixels);
    assert!(dir.read("binary.ppm").starts_with(b"P6\n640 480\n255\n"));
}

#[test]
fn the_bytes_do_not_depend_on_the_thread_count() {
    let dir = Dir::new();
    dir.write(
        "models/ico.obj",
        raybatch::procedural::to_obj(&raybatch::procedural::icosphere(3), ""),
    );
    dir.write(
        "scene.json",
        r#"{
          "image": {"width": 97, "height": 61},
          "output": "scene.pfm",
          "camera": {"look_from": [1, 2, 4], "look_at": [0, 0, 0], "vfov": 50},
          "integrator": {"type": "normal"},
          "sampler": {"type": "independent", "spp": 5, "seed": 11},
          "spheres": [{"center": [1, 0, 0], "radius": 0.6}, {"center": [-1, 0.2, -0.5], "radius": 0.4}],
          "planes": [{"point": [0, -0.7, 0], "normal": [0, 1, 0.1]}],
          "meshes": [{"file": "models/ico.obj", "transform": {"scale": 0.8}}]
        }"#,
    );
    let mut outputs = Vec::new();
    for threads in ["1", "2", "3", "8"] {
        let out = format!("out{threads}");
        let run = dir.raybatch(&["render", "scene.json", "--threads", threads, "--out", &out]);
        assert_eq!(run.status, 0, "{}", run.stderr);
        outputs.push(dir.read(&format!("{out}/scene.pfm")));
    }
    for other in &outputs[1..] {
        assert!(other == &outputs[0], "thread count changed the bytes");
    }
}

#[test]
fn every_shipped_scene_renders() {
    let dir = Dir::new();
    let scenes = repo("scenes");
    let run = dir.raybatch(&["render", scenes.to_str().unwrap(), "--out", "out"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    let manifests = std::fs::read_dir(&scenes)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "json")
        })
        .count();
    assert_eq!(dir.files().len(), manifests, "{:?}", dir.files());
}

#[test]
fn the_committed_models_are_what_the_generator_writes() {
    // `cargo run --example make_models` regenerates models/; nothing there is hand-edited.
    let files = raybatch::procedural::model_files();
    assert!(!files.is_empty());
    for (name, bytes) in files {
        let committed = std::fs::read(repo(&format!("models/{name}"))).unwrap();
        assert!(
            committed == bytes,
            "models/{name} differs from the generator's output"
        );
    }
}

#[test]
fn bench_traces_the_canonical_scene_with_every_query_and_reports_its_exact_hits() {
    let report = quick_bench("canonical", "1,2");
    let scenes = report["scenes"].as_array().expect("scenes");
    assert_eq!(scenes.len(), 1, "{report}");
    let scene = &scenes[0];
    assert_eq!(scene["name"], "canonical");
    assert_eq!(scene["rays"], 640 * 480);
    assert_eq!(scene["hits"], 22_632);
    assert!(
        scene["triangle_tree_preset"].is_null(),
        "no triangles: {scene}"
    );
    let throughput = scene["raybatch"]["throughput"]
        .as_array()
        .expect("throughput");
    let threads: Vec<_> = throughput.iter().map(|t| t["threads"].clone()).collect();
    assert_eq!(threads, [1, 2]);
    for figures in throughput {
        for column in [
            "closest_mrays",
            "closest_batch_mrays",
            "any_mrays",
            "any_unhinted_mrays",
            "any_batch_mrays",
            "closest_on_hits_mrays",
            "any_on_hits_mrays",
        ] {
            let rate = figures[column].as_f64().unwrap_or(f64::NAN);
            assert!(rate.is_finite() && rate > 0.0, "{column}: {figures}");
        }
    }
    let jobs = report["jobs"].as_array().expect("jobs");
    assert_eq!(jobs.len(), 1, "{report}");
    assert!(
        jobs[0]["seconds"].as_f64().is_some_and(|s| s > 0.0),
        "{report}"
    );
}

/// Each scene's peak memory is its own: the same 40k-triangle torus loaded and built twice
/// in a row (through a lens, then at 80x45) grows the process's peak by about as much the
/// second time. Before the bench handed freed memory back between scenes, the second
/// scene grew into what the first had freed and read a fifth of the first (39 against
/// 207 bytes per triangle).
#[test]
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn bench_memory_figures_are_each_scene_s_own() {
    let report = quick_bench("torus-40k through,torus-40k at", "1");
    let peaks: Vec<f64> = report["scenes"]
        .as_array()
        .expect("scenes")
        .iter()
        .map(|s| {
            s["peak_bytes_per_triangle"]
                .as_f64()
                .unwrap_or_else(|| panic!("no peak: {s}"))
        })
        .collect();
    assert_eq!(peaks.len(), 2, "{report}");
    // At least the placed triangles (36 bytes each) and the built scene's blocks and nodes.
    assert!(peaks.iter().all(|&p| p > 80.0), "{peaks:?}");
    assert!(
        peaks[1] > 0.6 * peaks[0] && peaks[0] > 0.6 * peaks[1],
        "{peaks:?}"
    );
}

/// The bench's table gives the share of rays that hit, which bounds what any hit can gain:
/// for the canonical scene 22,632 of 640 × 480 rays, 7.4%.
#[test]
fn bench_table_shows_the_share_of_rays_that_hit() {
    let table = quick_bench_output(&["--only", "canonical", "--threads", "1"]);
    assert!(
        table.contains("| scene | primitives | rays that hit | threads | closest 1 |"),
        "{table}"
    );
    assert!(
        table.contains("\n| canonical | 1 spheres | 7.4% | 1 | "),
        "{table}"
    );
}

/// The JSON report of `raybatch bench --quick --only ONLY --threads THREADS`, which must
/// succeed.
fn quick_bench(only: &str, threads: &str) -> serde_json::Value {
    let output = quick_bench_output(&["--only", only, "--threads", threads, "--json"]);
    serde_json::from_str(&output).expect("JSON on stdout")
}

/// The standard output of `raybatch bench --quick ARGS...`, which must succeed.
fn quick_bench_output(args: &[&str]) -> String {
    let dir = Dir::new();
    let run = dir.raybatch(&[&["bench", "--quick"], args].concat());
    assert_eq!(run.status, 0, "{}", run.stderr);
    run.stdout
}
