//! Output files: names and places, PPM/PFM layouts, the sRGB curve, `--out` and `--stats`.

use crate::util::{Dir, pfm, ppm};

const TINY: &str = r#""image": {"width": 4, "height": 2}"#;

#[test]
fn the_default_output_is_the_manifest_stem_beside_it() {
    let dir = Dir::new();
    dir.write("sub/scene.v2.json", format!("{{{TINY}}}"));
    let run = dir.raybatch(&["render", "sub/scene.v2.json"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    assert_eq!(dir.files(), ["sub/scene.v2.json", "sub/scene.v2.ppm"]);
}

#[test]
fn a_relative_output_is_resolved_against_the_manifest_folder() {
    let dir = Dir::new();
    dir.write(
        "sub/a.json",
        format!(r#"{{{TINY}, "output": "renders/a.pfm"}}"#),
    );
    let run = dir.raybatch(&["render", "sub/a.json"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    assert!(dir.exists("sub/renders/a.pfm"), "{:?}", dir.files());
}

#[test]
fn out_dir_takes_the_file_name_only_and_writes_nowhere_else() {
    let dir = Dir::new();
    dir.write(
        "scenes/a.json",
        format!(r#"{{{TINY}, "output": "renders/deep/a.pfm"}}"#),
    );
    dir.write("scenes/b.json", format!("{{{TINY}}}"));
    let run = dir.raybatch(&["render", "scenes", "--out", "out"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    assert_eq!(
        dir.files(),
        ["out/a.pfm", "out/b.ppm", "scenes/a.json", "scenes/b.json"]
    );
}

#[test]
fn the_srgb_curve_is_applied_before_quantizing_and_never_to_pfm() {
    let dir = Dir::new();
    // Background only: linear 0.5 -> 1.055 * 0.5^(1/2.4) - 0.055 = 0.7354 -> 188;
    // 0.002 is on the linear segment: 12.92 * 0.002 * 256 = 6.6 -> 6; 1 -> 255.
    let srgb = dir.ppm_of(
        "s.json",
        &format!(r#"{{{TINY}, "encoding": "srgb", "background": [0.5, 0.002, 1]}}"#),
        "s.ppm",
    );
    assert_eq!(srgb.at(0, 0), [188, 6, 255]);
    let linear = dir.ppm_of(
        "l.json",
        &format!(r#"{{{TINY}, "background": [0.5, 0.002, 1]}}"#),
        "l.ppm",
    );
    assert_eq!(linear.at(0, 0), [128, 0, 255]);
    let float = dir.pfm_of(
        "f.json",
        &format!(
            r#"{{{TINY}, "output": "f.pfm", "encoding": "srgb", "background": [0.5, 0.002, 1]}}"#
        ),
        "f.pfm",
    );
    assert_eq!(float.at(3, 1), [0.5, 0.002, 1.0]);
}

#[test]
fn pfm_stores_the_bottom_row_first() {
    // A plane seen from above fills only the lower half; the file starts with that half.
    let dir = Dir::new();
    dir.write(
        "p.json",
        r#"{"image": {"width": 2, "height": 4}, "output": "p.pfm", "background": [0.25, 0.25, 0.25],
            "camera": {"forward": [0, 0, 1]},
            "planes": [{"point": [0, -1, 0], "normal": [0, 1, 0]}]}"#,
    );
    dir.render_ok("p.json");
    let bytes = dir.read("p.pfm");
    assert!(bytes.starts_with(b"PF\n2 4\n-1.0\n"));
    let first = f32::from_le_bytes(bytes[12..16].try_into().unwrap());
    let last = f32::from_le_bytes(bytes[bytes.len() - 4..].try_into().unwrap());
    assert_eq!(first, 1.0, "bottom row (hits the plane) first");
    assert_eq!(last, 0.25, "top row (background) last");
    let image = pfm(&bytes);
    assert_eq!(image.at(0, 0), [0.25; 3]);
    assert_eq!(image.at(0, 3), [1.0; 3]);
}

#[test]
fn plain_ppm_is_text_with_the_seed_header() {
    let dir = Dir::new();
    dir.write("a.json", format!("{{{TINY}}}"));
    dir.render_ok("a.json");
    let bytes = dir.read("a.ppm");
    assert!(bytes.starts_with(b"P3\n4 2\n255\n"));
    assert_eq!(ppm(&bytes).pixels, vec![[0, 0, 0]; 8]);
}

#[test]
fn stats_has_one_json_line_per_job_with_the_documented_keys() {
    let dir = Dir::new();
    dir.write(
        "jobs/a.json",
        r#"{"image": {"width": 8, "height": 6}, "spheres": [{"center": [0, 0, 3], "radius": 1}]}"#,
    );
    dir.write("jobs/b.json", r#"{"image": {"width": 8}}"#);
    dir.write("jobs/tri.obj", "v 0 0 5\nv 1 0 5\nv 0 1 5\nf 1 2 3\n");
    dir.write(
        "jobs/c.json",
        r#"{"image": {"width": 4, "height": 4}, "sampler": {"type": "independent", "spp": 3},
            "meshes": [{"file": "tri.obj"}]}"#,
    );
    let run = dir.raybatch(&["render", "jobs", "--stats", "stats.jsonl"]);
    assert_eq!(run.status, 1);
    let text = String::from_utf8(dir.read("stats.jsonl")).unwrap();
    let lines: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    for line in &lines {
        for key in [
            "manifest",
            "output",
            "ok",
            "error",
            "triangles",
            "spheres",
            "width",
            "height",
            "spp",
            "load_s",
            "build_s",
            "render_s",
            "write_s",
        ] {
            assert!(line.get(key).is_some(), "{key} missing from {line}");
        }
    }
    assert_eq!(lines[0]["ok"], true);
    assert_eq!(lines[0]["spheres"], 1);
    assert_eq!(lines[0]["triangles"], 0);
    assert_eq!(lines[0]["width"], 8);
    assert!(lines[0]["error"].is_null());
    assert!(lines[0]["output"].as_str().unwrap().ends_with("a.ppm"));
    assert_eq!(lines[1]["ok"], false);
    assert!(lines[1]["error"].as_str().unwrap().contains("height"));
    assert_eq!(lines[2]["triangles"], 1);
    assert_eq!(lines[2]["spp"], 3);
    assert!(lines[2]["render_s"].as_f64().unwrap() >= 0.0);

    // A second run replaces the file (as `--help` and the README say), not appends to it.
    dir.raybatch(&["render", "jobs/a.json", "--stats", "stats.jsonl"]);
    let text = String::from_utf8(dir.read("stats.jsonl")).unwrap();
    assert_eq!(text.lines().count(), 1, "{text}");
}
