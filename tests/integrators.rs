//! What `hit`, `depth` and `normal` write, against values computed here in float64.

use crate::util::{Dir, default_camera_direction};

#[test]
fn hit_writes_white_on_hits_and_the_background_elsewhere() {
    let dir = Dir::new();
    let image = dir.ppm_of(
        "h.json",
        r#"{"image": {"width": 9, "height": 9}, "background": [0.25, 0.5, 0.75],
            "spheres": [{"center": [0, 0, 5], "radius": 0.2}]}"#,
        "h.ppm",
    );
    assert_eq!(image.at(4, 4), [255, 255, 255]);
    assert_eq!(image.at(0, 0), [64, 128, 192]);
}

#[test]
fn depth_is_the_distance_along_the_unit_ray_divided_by_scale() {
    // Against the float64 near root of |o + t d − c|² = r² for every pixel.
    let dir = Dir::new();
    let (w, h) = (32u32, 24u32);
    let (c, r) = ([0.3, -0.2, 3.0], 1.5);
    let json = format!(
        r#"{{"image": {{"width": {w}, "height": {h}}}, "output": "d.pfm",
            "integrator": {{"type": "depth", "scale": 2.5}}, "background": [0, 0, 0],
            "spheres": [{{"center": [{}, {}, {}], "radius": {r}}}]}}"#,
        c[0], c[1], c[2]
    );
    let image = dir.pfm_of("d.json", &json, "d.pfm");
    let mut hits = 0;
    for y in 0..h {
        for x in 0..w {
            let d = default_camera_direction(x, y, w, h);
            let b: f64 = (0..3).map(|k| d[k] * c[k]).sum();
            let cc: f64 = (0..3).map(|k| c[k] * c[k]).sum::<f64>() - r * r;
            let disc = b * b - cc;
            let got = image.at(x as usize, y as usize);
            if disc > 1e-9 {
                hits += 1;
                let t = (b - disc.sqrt()) / 2.5;
                for v in got {
                    assert!(
                        (f64::from(v) - t).abs() <= 1e-6 * t,
                        "({x}, {y}): {v} vs {t}"
                    );
                }
            } else if disc < -1e-9 {
                assert_eq!(got, [0.0; 3], "({x}, {y})");
            }
        }
    }
    assert!(hits > 80, "{hits}");
}

#[test]
fn depth_in_a_ppm_is_quantized_by_the_seed_rule() {
    // Centre ray along +z, plane at z = 0.3: floor(0.3 * 256) = 76.
    let dir = Dir::new();
    let image = dir.ppm_of(
        "q.json",
        r#"{"image": {"width": 3, "height": 3}, "integrator": {"type": "depth"},
            "planes": [{"point": [0, 0, 0.3], "normal": [0, 0, 1]}]}"#,
        "q.ppm",
    );
    assert_eq!(image.at(1, 1), [76, 76, 76]);
}

#[test]
fn normals_are_geometric_unit_vectors_never_flipped_toward_the_ray() {
    let dir = Dir::new();
    // Plane: its normal normalized, seen from either side: (0, 2, 0) -> (0.5, 1, 0.5).
    for normal in ["[0, 2, 0]", "[0, -2, 0]"] {
        let json = format!(
            r#"{{"image": {{"width": 5, "height": 5}}, "integrator": {{"type": "normal"}},
                "camera": {{"look_from": [0, 3, 0], "look_at": [0, 0, 0], "up": [0, 0, -1]}},
                "planes": [{{"point": [0, 0, 0], "normal": {normal}}}]}}"#
        );
        let image = dir.ppm_of("p.json", &json, "p.ppm");
        let expected = if normal.contains('-') {
            [128, 0, 128]
        } else {
            [128, 255, 128]
        };
        assert_eq!(image.at(2, 2), expected, "{normal}");
    }

    // Triangle: cross(v1 − v0, v2 − v0) in stored order. Seen from the front (−z side of
    // this one is its back): the normal points away from the camera, +z: (0.5, 0.5, 1).
    dir.write("t.obj", "v -1 -1 2\nv 0 1 2\nv 1 -1 2\nf 1 3 2\n");
    dir.write("u.obj", "v -1 -1 2\nv 0 1 2\nv 1 -1 2\nf 1 2 3\n");
    for (file, expected) in [("t.obj", [128, 128, 255]), ("u.obj", [128, 128, 0])] {
        let json = format!(
            r#"{{"image": {{"width": 5, "height": 5}}, "integrator": {{"type": "normal"}},
                "meshes": [{{"file": "{file}"}}]}}"#
        );
        assert_eq!(
            dir.ppm_of("t.json", &json, "t.ppm").at(2, 2),
            expected,
            "{file}"
        );
    }

    // Sphere, per pixel, against (p − c)/r computed here.
    let (w, h) = (24u32, 24u32);
    let (c, r) = ([0.2, 0.1, 3.0], 1.0);
    let json = format!(
        r#"{{"image": {{"width": {w}, "height": {h}}}, "output": "s.pfm",
            "integrator": {{"type": "normal"}},
            "spheres": [{{"center": [{}, {}, {}], "radius": {r}}}]}}"#,
        c[0], c[1], c[2]
    );
    let image = dir.pfm_of("s.json", &json, "s.pfm");
    let mut checked = 0;
    for y in 0..h {
        for x in 0..w {
            let d = default_camera_direction(x, y, w, h);
            let b: f64 = (0..3).map(|k| d[k] * c[k]).sum();
            let disc = b * b - ((0..3).map(|k| c[k] * c[k]).sum::<f64>() - r * r);
            if disc < 1e-6 {
                continue;
            }
            let t = b - disc.sqrt();
            let n: Vec<f64> = (0..3).map(|k| (t * d[k] - c[k]) / r).collect();
            let got = image.at(x as usize, y as usize);
            for k in 0..3 {
                let expected = 0.5 * (n[k] + 1.0);
                assert!(
                    (f64::from(got[k]) - expected).abs() < 1e-6,
                    "({x}, {y})[{k}]"
                );
            }
            checked += 1;
        }
    }
    assert!(checked > 50);
}
