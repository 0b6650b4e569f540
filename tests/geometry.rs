//! Hit rules: spheres, planes, triangles, the strict `(tmin, tmax)` interval, transforms.
//! Images with odd sizes put the centre pixel's ray exactly on the +z axis, so distances
//! along it are exact.

use crate::util::Dir;

/// A depth render (PFM) of `body` (extra manifest keys) with an 11 × 11 default camera.
fn depth(dir: &Dir, body: &str) -> crate::util::Pfm {
    let json = format!(
        r#"{{"image": {{"width": 11, "height": 11}}, "output": "d.pfm",
            "integrator": {{"type": "depth"}}, "background": [0, 0, 0], {body}}}"#
    );
    dir.pfm_of("d.json", &json, "d.pfm")
}

#[test]
fn spheres_are_hit_at_the_near_side_or_from_inside_at_the_far_side() {
    let dir = Dir::new();
    let outside = depth(&dir, r#""spheres": [{"center": [0, 0, 5], "radius": 2}]"#);
    assert_eq!(outside.at(5, 5)[0], 3.0);
    let inside = depth(&dir, r#""spheres": [{"center": [0, 0, 1], "radius": 2}]"#);
    assert_eq!(inside.at(5, 5)[0], 3.0);
    // From the centre every ray leaves at exactly the radius.
    let centred = depth(&dir, r#""spheres": [{"center": [0, 0, 0], "radius": 2}]"#);
    for p in &centred.pixels {
        assert!((p[0] - 2.0).abs() <= 2.0 * f32::EPSILON, "{p:?}");
    }
}

#[test]
fn a_ray_that_only_grazes_a_sphere_misses() {
    // The centre ray runs along +z and touches the sphere of radius 1 around (1, 0, 5) at
    // (0, 0, 5): discriminant exactly 0. A radius one ulp larger is a real hit.
    let dir = Dir::new();
    let tangent = depth(&dir, r#""spheres": [{"center": [1, 0, 5], "radius": 1}]"#);
    assert_eq!(tangent.at(5, 5)[0], 0.0);
    let r = 1.0f64.next_up();
    let crossing = depth(
        &dir,
        &format!(r#""spheres": [{{"center": [1, 0, 5], "radius": {r:?}}}]"#),
    );
    assert!((crossing.at(5, 5)[0] - 5.0).abs() < 1e-6);
}

#[test]
fn the_interval_is_strict_at_both_ends() {
    let dir = Dir::new();
    let sphere = r#""spheres": [{"center": [0, 0, 4], "radius": 1}]"#;
    // Near side at t = 3, far side at t = 5.
    let at_tmin = depth(&dir, &format!(r#""tmin": 3, {sphere}"#));
    assert_eq!(at_tmin.at(5, 5)[0], 5.0, "t = tmin does not count");
    let past_tmin = depth(&dir, &format!(r#""tmin": 2.999, {sphere}"#));
    assert_eq!(past_tmin.at(5, 5)[0], 3.0);
    let at_tmax = depth(&dir, &format!(r#""tmax": 3, {sphere}"#));
    assert_eq!(at_tmax.at(5, 5)[0], 0.0, "t = tmax does not count");
    let null_tmax = depth(&dir, &format!(r#""tmin": null, "tmax": null, {sphere}"#));
    assert_eq!(null_tmax.at(5, 5)[0], 3.0);

    // The same for a triangle (float32 path) at t = 2, with bounds that are not floats.
    dir.write("tri.obj", "v -1 -1 2\nv 1 -1 2\nv 0 1 2\nf 1 2 3\n");
    let mesh = r#""meshes": [{"file": "tri.obj"}]"#;
    assert_eq!(
        depth(&dir, &format!(r#""tmin": 2, {mesh}"#)).at(5, 5)[0],
        0.0
    );
    assert_eq!(
        depth(&dir, &format!(r#""tmax": 2, {mesh}"#)).at(5, 5)[0],
        0.0
    );
    let just_below = 2.0f64 - 1e-12;
    let just_above = 2.0f64 + 1e-12;
    assert_eq!(
        depth(&dir, &format!(r#""tmin": {just_below}, {mesh}"#)).at(5, 5)[0],
        2.0
    );
    assert_eq!(
        depth(&dir, &format!(r#""tmax": {just_above}, {mesh}"#)).at(5, 5)[0],
        2.0
    );
}

#[test]
fn the_interval_defaults_to_zero_and_infinity() {
    let dir = Dir::new();
    // Far beyond any finite bound one might pick: a sphere whose near side is at
    // t = 1e12 − 1e9, and a triangle at t = 1e12.
    let far_sphere = depth(
        &dir,
        r#""spheres": [{"center": [0, 0, 1e12], "radius": 1e9}]"#,
    );
    assert_eq!(far_sphere.at(5, 5)[0], 9.99e11);
    dir.write(
        "far.obj",
        "v -1e12 -1e12 1e12\nv 1e12 -1e12 1e12\nv 0 1e12 1e12\nf 1 2 3\n",
    );
    let far_triangle = depth(&dir, r#""meshes": [{"file": "far.obj"}]"#);
    assert_eq!(far_triangle.at(5, 5)[0], 1e12);
    // From inside a sphere of radius 1e-6, its far side counts: `tmin` is 0.
    let near = depth(
        &dir,
        r#""spheres": [{"center": [0, 0, 0], "radius": 1e-6}]"#,
    );
    assert_eq!(near.at(5, 5)[0], 1e-6);
}

#[test]
fn planes_are_hit_from_both_sides_and_the_nearest_primitive_wins() {
    let dir = Dir::new();
    let front = depth(
        &dir,
        r#""planes": [{"point": [0, 0, 7], "normal": [0, 0, -1]}]"#,
    );
    let back = depth(
        &dir,
        r#""planes": [{"point": [0, 0, 7], "normal": [0, 0, 1]}]"#,
    );
    assert_eq!(front.at(5, 5)[0], 7.0);
    assert_eq!(back.at(5, 5)[0], 7.0);
    let both = depth(
        &dir,
        r#""planes": [{"point": [0, 0, 7], "normal": [0, 0, 1]}],
           "spheres": [{"center": [0, 0, 9], "radius": 1}, {"center": [0, 0, 4], "radius": 1}]"#,
    );
    assert_eq!(both.at(5, 5)[0], 3.0);
}

#[test]
fn triangles_are_hit_on_both_faces() {
    let dir = Dir::new();
    dir.write("ccw.obj", "v -1 -1 2\nv 1 -1 2\nv 0 1 2\nf 1 2 3\n");
    dir.write("cw.obj", "v -1 -1 2\nv 0 1 2\nv 1 -1 2\nf 1 2 3\n");
    for file in ["ccw.obj", "cw.obj"] {
        let image = depth(&dir, &format!(r#""meshes": [{{"file": "{file}"}}]"#));
        assert_eq!(image.at(5, 5)[0], 2.0, "{file}");
    }
}

#[test]
fn vertices_and_edges_on_pixel_rays_leave_no_gaps() {
    // A grid of triangles on the plane z = 1 whose vertices are exactly the points where
    // pixel-centre rays of a 64 × 64 default camera cross it ((u, v) are dyadic): every
    // ray passes through a vertex shared by six triangles; none may slip through.
    let dir = Dir::new();
    let grid = raybatch::procedural::pixel_grid(64);
    // The grid's vertices are the exact crossing points: (2i − 1 − 64)/64 etc.
    assert_eq!(grid.positions[1], [-63.0 / 64.0, 65.0 / 64.0, 1.0]);
    let obj = raybatch::procedural::to_obj(&grid, "");
    dir.write("grid.obj", obj);
    let image = dir.ppm_of(
        "g.json",
        r#"{"image": {"width": 64, "height": 64}, "meshes": [{"file": "grid.obj"}]}"#,
        "g.ppm",
    );
    assert_eq!(
        image.count([255; 3]),
        64 * 64,
        "rays leaked through shared vertices"
    );
}

#[test]
fn a_matrix_and_the_equivalent_scale_rotate_translate_agree() {
    let dir = Dir::new();
    dir.write(
        "ico.obj",
        raybatch::procedural::to_obj(&raybatch::procedural::icosphere(2), ""),
    );
    let render = |name: &str, transform: &str| {
        let json = format!(
            r#"{{"image": {{"width": 48, "height": 48}}, "output": "{name}.pfm",
                "integrator": {{"type": "depth"}},
                "meshes": [{{"file": "ico.obj", "transform": {transform}}}]}}"#
        );
        dir.pfm_of(&format!("{name}.json"), &json, &format!("{name}.pfm"))
    };
    // scale 2 along x, then a quarter turn about +z (x → y), then translate to
    // (0.25, 0, 6): off the rotation's axis, so that the order of the three shows.
    let srt = render(
        "srt",
        r#"{"scale": [2, 1, 1], "rotate": {"axis": [0, 0, 1], "degrees": 90}, "translate": [0.25, 0, 6]}"#,
    );
    let matrix = render(
        "m",
        r#"{"matrix": [0, -1, 0, 0.25,  2, 0, 0, 0,  0, 0, 1, 6,  0, 0, 0, 1]}"#,
    );
    assert_eq!(srt, matrix);
    // The stretched axis now runs along y: the image is taller than wide.
    let hit = |img: &crate::util::Pfm, x: usize, y: usize| img.at(x, y)[0] > 0.0;
    let tall = (0..48).filter(|&y| hit(&srt, 24, y)).count();
    let wide = (0..48).filter(|&x| hit(&srt, x, 24)).count();
    assert!(tall * 2 >= wide * 3, "tall {tall}, wide {wide}");
    // On the view axis, 0.25 from the centre along x (where the radius is still 1): the
    // surface at z = 6 − √(1 − 0.25²).
    let expected = 6.0 - (1.0f64 - 0.0625).sqrt();
    assert!(
        (f64::from(srt.at(24, 24)[0]) - expected).abs() < 0.05,
        "{} against {expected}",
        srt.at(24, 24)[0]
    );
}

#[test]
fn manifest_numbers_are_the_float64s_they_denote() {
    // Random float64s across twenty binary orders of magnitude, written as Rust (and
    // Python) print them, the shortest decimal that reads back as the same float; and
    // one that a fast but inexact decimal reader takes a unit in the last place low.
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut values = vec![1.6764843644182825, -0.1, 2.0e-3, 123456.789];
    while values.len() < 4000 {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let unit = (state >> 11) as f64 / (1u64 << 53) as f64;
        values.push((2.0 * unit - 1.0) * 2f64.powi((state & 31) as i32 - 10));
    }
    // Four numbers per sphere: a centre and a radius (made positive).
    let radius = |r: f64| r.abs().max(1e-3);
    let spheres: Vec<String> = values
        .chunks(4)
        .map(|v| {
            format!(
                r#"{{"center": [{}, {}, {}], "radius": {}}}"#,
                v[0],
                v[1],
                v[2],
                radius(v[3])
            )
        })
        .collect();
    let json = format!(
        r#"{{"image": {{"width": 2, "height": 2}}, "camera": {{"look_from": [{}, {}, {}], "look_at": [0, 0, 0]}},
            "spheres": [{}]}}"#,
        values[0],
        values[1],
        values[2],
        spheres.join(", ")
    );
    let manifest = raybatch::Manifest::parse(json.as_bytes(), std::path::Path::new("m.json"))
        .expect("a valid manifest");
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for (i, (sphere, v)) in manifest.spheres.iter().zip(values.chunks(4)).enumerate() {
        let read = [
            sphere.center.x,
            sphere.center.y,
            sphere.center.z,
            sphere.radius,
        ];
        let written = [v[0], v[1], v[2], radius(v[3])];
        assert_eq!(
            bits(&read),
            bits(&written),
            "sphere {i}: {spheres}",
            spheres = spheres[i]
        );
    }
    assert_eq!(manifest.spheres.len(), values.len() / 4);
    // With `look_at`, the camera sits exactly at `look_from`.
    let origin = manifest.camera.frame.origin;
    assert_eq!(bits(&origin.to_array()), bits(&values[..3]));
}

#[test]
fn instances_small_and_large_are_placed_where_float64_puts_them_in_order() {
    use glam::{DMat4, DQuat, DVec3};
    use raybatch::SceneGeometry;
    use raybatch::mesh::{Geometry, Instance, MeshFile};
    use std::sync::Arc;

    // Two geometries: a few vertices, and more than are placed one by one (placing goes
    // parallel from 16,384), each as an instance of the file and under the manifest's
    // transform.
    let grid = |n: u32| Geometry {
        positions: (0..n)
            .map(|i| [i as f32 * 0.25, (i % 7) as f32 - 3.0, (i % 13) as f32 * 0.5])
            .collect(),
        triangles: (0..n - 2).map(|i| [i, i + 1, i + 2]).collect(),
    };
    let own = DMat4::from_scale_rotation_translation(
        DVec3::new(1.0, 2.0, 0.5),
        DQuat::from_axis_angle(DVec3::new(1.0, 1.0, 0.0).normalize(), 0.7),
        DVec3::new(-4.0, 2.0, 9.0),
    );
    let mesh = Arc::new(MeshFile {
        geometries: vec![grid(10), grid(20_000)],
        instances: vec![
            Instance {
                geometry: 1,
                transform: own,
            },
            Instance {
                geometry: 0,
                transform: DMat4::IDENTITY,
            },
            Instance {
                geometry: 0,
                transform: own,
            },
        ],
        warnings: Vec::new(),
    });
    let outer =
        DMat4::from_translation(DVec3::new(0.5, 0.0, -1.0)) * DMat4::from_scale(DVec3::splat(3.0));
    let mut geometry = SceneGeometry::default();
    geometry.add_mesh(&mesh, outer, "grid".as_ref()).unwrap();

    // Row by row in float64: `outer · own · p`, rounded to float32.
    let apply = |m: &DMat4, p: [f64; 3]| -> [f64; 3] {
        let r = m.to_cols_array_2d();
        [0, 1, 2].map(|row| (0..3).map(|k| r[k][row] * p[k]).sum::<f64>() + r[3][row])
    };
    let mut expected = Vec::new();
    for instance in &mesh.instances {
        let g = &mesh.geometries[instance.geometry];
        let world: Vec<[f64; 3]> = g
            .positions
            .iter()
            .map(|p| apply(&outer, apply(&instance.transform, p.map(f64::from))))
            .collect();
        expected.extend(g.triangles.iter().map(|t| t.map(|i| world[i as usize])));
    }
    assert_eq!(geometry.triangles.len(), expected.len());
    for (k, (got, want)) in geometry.triangles.iter().zip(&expected).enumerate() {
        for (g, w) in got.iter().flatten().zip(want.iter().flatten()) {
            // Float64 sums in another order differ by far less than half a float32 step.
            let step = f64::from((*w as f32).abs()).max(1e-30) * f64::from(f32::EPSILON);
            assert!(
                (f64::from(*g) - w).abs() <= step,
                "triangle {k}: {got:?} against {want:?}"
            );
        }
    }

    // A vertex out of range is named, the first in order, in either kind of instance.
    for (n, far) in [(10u32, [3usize, 7]), (20_000, [17_000, 18_000])] {
        let mut g = grid(n);
        g.positions[far[0]] = [1e30, 0.0, 0.0];
        g.positions[far[1]] = [2e30, 0.0, 0.0];
        let bad = Arc::new(MeshFile::one_geometry(g));
        let error = SceneGeometry::default()
            .add_mesh(&bad, DMat4::IDENTITY, "far".as_ref())
            .unwrap_err()
            .to_string();
        assert!(error.contains("vertex [1e30, 0, 0] lands"), "{n}: {error}");
    }
}
