//! `raybatch compare`: figures checked against values worked out by hand, limits, errors.

use serde_json::Value;

use crate::util::Dir;

fn p3(width: usize, height: usize, values: &[u8]) -> String {
    let body: Vec<String> = values.iter().map(u8::to_string).collect();
    format!("P3\n{width} {height}\n255\n{}\n", body.join(" "))
}

/// A PFM from rows given top first (the file stores them bottom first).
fn pfm(width: usize, rows: &[Vec<f32>]) -> Vec<u8> {
    let mut out = format!("PF\n{width} {}\n-1.0\n", rows.len()).into_bytes();
    for row in rows.iter().rev() {
        for v in row {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

fn json_of(run: &crate::util::Run) -> Value {
    serde_json::from_str(run.stdout.trim()).unwrap_or_else(|e| panic!("{e}: {}", run.stdout))
}

#[test]
fn pixel_figures_match_a_hand_computation() {
    let dir = Dir::new();
    dir.write("a.ppm", p3(2, 1, &[10, 20, 30, 0, 0, 0]));
    dir.write("b.ppm", p3(2, 1, &[10, 20, 30, 3, 0, 4]));
    let run = dir.raybatch(&["compare", "a.ppm", "b.ppm", "--json"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    let line = json_of(&run);
    assert_eq!(line["differing"], 1);
    assert_eq!(line["max_abs"], 4.0);
    // RMSE over 6 channel values: sqrt((3² + 4²) / 6); PSNR = 20 log10(255 / RMSE).
    let rmse = (25.0f64 / 6.0).sqrt();
    assert!((line["rmse"].as_f64().unwrap() - rmse).abs() < 1e-12);
    let psnr = 20.0 * (255.0 / rmse).log10();
    assert!((line["psnr"].as_f64().unwrap() - psnr).abs() < 1e-9);
    assert!(line["depth"].is_null());
    assert_eq!(line["ok"], true);

    let text = dir.raybatch(&["compare", "a.ppm", "b.ppm"]);
    assert!(
        text.stdout.contains("1 differing pixels") && text.stdout.contains("dB"),
        "{}",
        text.stdout
    );
}

#[test]
fn limits_fail_the_command_with_a_reason() {
    let dir = Dir::new();
    dir.write("a.ppm", p3(2, 1, &[10, 20, 30, 0, 0, 0]));
    dir.write("b.ppm", p3(2, 1, &[10, 20, 30, 3, 0, 4]));
    for (flag, value) in [
        ("--max-differing", "0"),
        ("--max-abs", "3.5"),
        ("--min-psnr", "60"),
    ] {
        let run = dir.raybatch(&["compare", "a.ppm", "b.ppm", flag, value]);
        assert_eq!(run.status, 1, "{flag}");
        assert!(run.stderr.contains("limit exceeded"), "{}", run.stderr);
    }
    let loose = dir.raybatch(&[
        "compare",
        "a.ppm",
        "b.ppm",
        "--max-differing",
        "1",
        "--max-abs",
        "4",
    ]);
    assert_eq!(loose.status, 0, "{}", loose.stderr);
}

#[test]
fn depth_renders_report_the_hit_mask_and_relative_error() {
    let dir = Dir::new();
    // 1000 pixels in one row: 997 agree exactly, one differs by 1e-3 relative, one is a
    // hit in A only, one a hit in B only.
    let mut a = vec![2.0f32; 1000];
    let mut b = vec![2.0f32; 1000];
    a[10] = 2.002;
    a[20] = 0.0;
    b[30] = 0.0;
    let gray = |v: &[f32]| vec![v.iter().flat_map(|&x| [x, x, x]).collect::<Vec<f32>>()];
    dir.write("a.pfm", pfm(1000, &gray(&a)));
    dir.write("b.pfm", pfm(1000, &gray(&b)));
    let run = dir.raybatch(&["compare", "a.pfm", "b.pfm", "--json"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    let depth = &json_of(&run)["depth"];
    assert_eq!(depth["mask_disagreements"], 2);
    assert_eq!(depth["mask_fraction"], 0.002);
    assert_eq!(depth["both_hit"], 998);
    assert_eq!(depth["median"], 0.0);
    // Nearest rank: p99.9 of 998 values is the 998th, the largest.
    let expected = (2.002f32 as f64 - 2.0) / 2.0;
    assert!((depth["max"].as_f64().unwrap() - expected).abs() < 1e-9);
    assert!((depth["p999"].as_f64().unwrap() - expected).abs() < 1e-9);
    assert_eq!(depth["p99"], 0.0);

    let strict = dir.raybatch(&["compare", "a.pfm", "b.pfm", "--max-mask-fraction", "1e-3"]);
    assert_eq!(strict.status, 1);
    assert!(strict.stderr.contains("hit-mask"), "{}", strict.stderr);
    let strict = dir.raybatch(&["compare", "a.pfm", "b.pfm", "--max-depth-p999", "1e-5"]);
    assert_eq!(strict.status, 1);

    // A non-zero background marks the misses instead.
    let c: Vec<f32> = a.iter().map(|&x| if x == 0.0 { 0.5 } else { x }).collect();
    dir.write("c.pfm", pfm(1000, &gray(&c)));
    let run = dir.raybatch(&["compare", "c.pfm", "b.pfm", "--json", "--background", "0.5"]);
    assert_eq!(
        json_of(&run)["depth"]["mask_disagreements"],
        1,
        "b's 0 is now a hit"
    );
}

#[test]
fn unreadable_or_mismatched_images_are_refused() {
    let dir = Dir::new();
    dir.write("a.ppm", p3(2, 1, &[0; 6]));
    dir.write("b.ppm", p3(1, 2, &[0; 6]));
    dir.write("bad.ppm", "P3\n2 1\n255\n1 2\n");
    for (args, fragment) in [
        (
            ["compare", "a.ppm", "b.ppm"],
            "differ in size: 2 x 1 and 1 x 2",
        ),
        (["compare", "a.ppm", "absent.ppm"], "absent.ppm"),
        (
            ["compare", "bad.ppm", "a.ppm"],
            "bad.ppm: the file ends early",
        ),
    ] {
        let run = dir.raybatch(&args);
        assert_eq!(run.status, 2, "{args:?}");
        assert!(run.stderr.contains(fragment), "{args:?}: {}", run.stderr);
        assert_eq!(run.stderr.lines().count(), 1);
        // The cause is named once, not once by the message and again by the chain.
        assert!(
            run.stderr.matches("os error").count() <= 1,
            "{}",
            run.stderr
        );
    }
}

#[test]
fn renders_from_the_same_manifest_compare_identical() {
    let dir = Dir::new();
    dir.write(
        "s.json",
        r#"{"image": {"width": 40, "height": 30}, "output": "s.pfm", "integrator": {"type": "depth"},
            "spheres": [{"center": [0, 0, 4], "radius": 1.5}]}"#,
    );
    for threads in ["1", "2"] {
        let run = dir.raybatch(&["render", "s.json", "--threads", threads, "--out", threads]);
        assert_eq!(run.status, 0, "{}", run.stderr);
    }
    let run = dir.raybatch(&[
        "compare",
        "1/s.pfm",
        "2/s.pfm",
        "--json",
        "--max-differing",
        "0",
    ]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    let line = json_of(&run);
    assert_eq!(line["differing"], 0);
    assert!(
        line["psnr"].is_null(),
        "identical images have no finite PSNR"
    );
    assert_eq!(
        line["depth"]["mask_disagreements"], 0,
        "gray PFMs are compared as depth"
    );
}

#[test]
fn a_reader_gone_away_changes_neither_the_work_nor_the_exit_status() {
    // `raybatch ... | head -1`: standard output closed before the first line. Before,
    // `println!` panicked there (exit 101, a panic message on stderr).
    let dir = Dir::new();
    dir.write("a.ppm", p3(2, 1, &[10, 20, 30, 0, 0, 0]));
    dir.write("b.ppm", p3(2, 1, &[10, 20, 30, 3, 0, 4]));
    let same = dir.raybatch_unread(&["compare", "a.ppm", "a.ppm"]);
    assert_eq!((same.status, same.stderr.as_str()), (0, ""));
    let over = dir.raybatch_unread(&["compare", "a.ppm", "b.ppm", "--max-abs", "3.5"]);
    assert_eq!(over.status, 1, "{}", over.stderr);
    assert_eq!(over.error_lines().len(), 1, "{}", over.stderr);
    assert!(over.stderr.contains("limit exceeded"), "{}", over.stderr);

    // A batch renders every job and reports none of its lines.
    for name in ["one", "two"] {
        dir.write(
            &format!("scenes/{name}.json"),
            format!(r#"{{"image": {{"width": 4, "height": 3}}, "output": "{name}.ppm"}}"#),
        );
    }
    let render = dir.raybatch_unread(&["render", "scenes"]);
    assert_eq!((render.status, render.stderr.as_str()), (0, ""));
    assert!(
        dir.exists("scenes/one.ppm") && dir.exists("scenes/two.ppm"),
        "{:?}",
        dir.files()
    );
}
