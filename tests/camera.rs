//! The pixel-to-ray mapping of both camera forms, checked with small spheres placed on
//! rays computed here in float64 from the contract's formulas.

use crate::util::{Dir, default_camera_direction};

/// A manifest with a `w × h` image, `camera` JSON and one sphere.
fn one_sphere(w: u32, h: u32, camera: &str, center: [f64; 3], radius: f64) -> String {
    format!(
        r#"{{"image": {{"width": {w}, "height": {h}}}, "camera": {camera},
            "spheres": [{{"center": [{}, {}, {}], "radius": {radius}}}]}}"#,
        center[0], center[1], center[2]
    )
}

#[test]
fn the_default_camera_puts_x_right_and_y_down() {
    // A sphere on the ray through pixel (x, y) covers that pixel and none other.
    let dir = Dir::new();
    let (w, h) = (40, 30);
    for (x, y) in [(0u32, 0u32), (39, 0), (0, 29), (13, 7), (25, 22)] {
        let d = default_camera_direction(x, y, w, h);
        let center = d.map(|c| c * 50.0);
        let json = one_sphere(w, h, "{}", center, 0.2);
        let image = dir.ppm_of("s.json", &json, "s.ppm");
        assert_eq!(
            image.at(x as usize, y as usize),
            [255; 3],
            "pixel ({x}, {y})"
        );
        assert_eq!(image.count([255; 3]), 1, "only pixel ({x}, {y})");
    }
}

#[test]
fn basis_vectors_are_used_as_given_and_their_lengths_zoom() {
    // Doubling forward halves the film: a sphere covers about four times the pixels.
    let dir = Dir::new();
    let normal = dir.ppm_of(
        "a.json",
        &one_sphere(64, 64, "{}", [0.0, 0.0, 10.0], 1.0),
        "a.ppm",
    );
    let zoomed = dir.ppm_of(
        "b.json",
        &one_sphere(64, 64, r#"{"forward": [0, 0, 2]}"#, [0.0, 0.0, 10.0], 1.0),
        "b.ppm",
    );
    let ratio = zoomed.count([255; 3]) as f64 / normal.count([255; 3]) as f64;
    assert!((ratio - 4.0).abs() < 0.3, "ratio {ratio}");

    // A basis turned to look down -x with the camera moved: origin and axes as given.
    let camera =
        r#"{"origin": [5, 1, 0], "right": [0, 0, -1], "up": [0, 1, 0], "forward": [-1, 0, 0]}"#;
    let image = dir.ppm_of(
        "c.json",
        &one_sphere(32, 32, camera, [0.0, 1.0, -1.5], 1.0),
        "c.ppm",
    );
    // World -z is the image's right: the sphere sits right of centre.
    let right = (0..32).flat_map(|y| (16..32).map(move |x| (x, y)));
    let left = (0..32).flat_map(|y| (0..16).map(move |x| (x, y)));
    assert!(right.filter(|&(x, y)| image.at(x, y) == [255; 3]).count() > 10);
    assert_eq!(left.filter(|&(x, y)| image.at(x, y) == [255; 3]).count(), 0);
}

#[test]
fn look_at_follows_glu_look_at_and_the_default_basis_is_its_mirror() {
    let dir = Dir::new();
    // From +z looking at the origin, a sphere at +x is on the image's right.
    let look_at = r#"{"look_from": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "vfov": 60}"#;
    let image = dir.ppm_of(
        "a.json",
        &one_sphere(32, 32, look_at, [1.5, 0.0, 0.0], 0.5),
        "a.ppm",
    );
    let column_sum = |img: &crate::util::Ppm, range: std::ops::Range<usize>| {
        range
            .flat_map(|x| (0..32).map(move |y| (x, y)))
            .filter(|&(x, y)| img.at(x, y) == [255; 3])
            .count()
    };
    assert!(column_sum(&image, 16..32) > 10 && column_sum(&image, 0..16) == 0);

    // Same position and direction as the default camera (origin, looking down +z): the
    // look-at image is the mirror of the basis image.
    let sphere = [0.7, 0.3, 4.0];
    let basis = dir.ppm_of("b.json", &one_sphere(33, 21, "{}", sphere, 0.5), "b.ppm");
    let mirrored = dir.ppm_of(
        "c.json",
        &one_sphere(
            33,
            21,
            r#"{"look_from": [0, 0, 0], "look_at": [0, 0, 1]}"#,
            sphere,
            0.5,
        ),
        "c.ppm",
    );
    for y in 0..21 {
        for x in 0..33 {
            assert_eq!(basis.at(x, y), mirrored.at(32 - x, y), "({x}, {y})");
        }
    }
}

#[test]
fn vertical_field_of_view_reaches_the_top_edge() {
    // With vfov 90 and look_at down -z, up' has length tan(45°) = 1: the top row's centre
    // ray is (u, v, -1) with v = 1 - 1/H. A sphere on that ray lights exactly that pixel.
    let dir = Dir::new();
    let (w, h) = (21u32, 21u32);
    let v = 1.0 - 1.0 / f64::from(h);
    let n = (v * v + 1.0).sqrt();
    let center = [0.0, 40.0 * v / n, -40.0 / n];
    let camera = r#"{"look_from": [0, 0, 0], "look_at": [0, 0, -1]}"#;
    let image = dir.ppm_of("a.json", &one_sphere(w, h, camera, center, 0.3), "a.ppm");
    assert_eq!(image.at(10, 0), [255; 3]);
    assert_eq!(image.count([255; 3]), 1);
}
