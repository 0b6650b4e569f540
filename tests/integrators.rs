//! What `hit`, `depth` and `normal` write, against values computed here in float64.

use crate::util::{Dir, assert_normal_colour, default_camera_direction};

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
            "integrator": {{"type": "depth", "scale": 2.5}}, "background": [0.25, 0.5, 0.75],
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
                assert_eq!(got, [0.25, 0.5, 0.75], "({x}, {y}): the background");
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
            "integrator": {{"type": "normal"}}, "background": [0.25, 0.5, 0.75],
            "spheres": [{{"center": [{}, {}, {}], "radius": {r}}}]}}"#,
        c[0], c[1], c[2]
    );
    let image = dir.pfm_of("s.json", &json, "s.pfm");
    let (mut checked, mut misses) = (0, 0);
    for y in 0..h {
        for x in 0..w {
            let d = default_camera_direction(x, y, w, h);
            let b: f64 = (0..3).map(|k| d[k] * c[k]).sum();
            let disc = b * b - ((0..3).map(|k| c[k] * c[k]).sum::<f64>() - r * r);
            if disc < -1e-6 {
                let got = image.at(x as usize, y as usize);
                assert_eq!(got, [0.25, 0.5, 0.75], "({x}, {y}): the background");
                misses += 1;
            }
            if disc < 1e-6 {
                continue;
            }
            let t = b - disc.sqrt();
            let n = [0, 1, 2].map(|k| (t * d[k] - c[k]) / r);
            let got = image.at(x as usize, y as usize);
            assert_normal_colour(got, n, 1e-6, &format!("({x}, {y})"));
            checked += 1;
        }
    }
    assert!(
        checked > 50 && misses > 50,
        "{checked} hits, {misses} misses"
    );

    // From the centre of a sphere every ray meets its inside, where (p − c)/r is the ray's
    // own direction: pointing away from the camera, not flipped toward it.
    let json = format!(
        r#"{{"image": {{"width": {w}, "height": {h}}}, "output": "i.pfm",
            "integrator": {{"type": "normal"}},
            "spheres": [{{"center": [0, 0, 0], "radius": 2}}]}}"#
    );
    let image = dir.pfm_of("i.json", &json, "i.pfm");
    for y in 0..h {
        for x in 0..w {
            let d = default_camera_direction(x, y, w, h);
            let got = image.at(x as usize, y as usize);
            assert_normal_colour(got, d, 1e-6, &format!("inside ({x}, {y})"));
        }
    }
}

/// The `normal` integrator asks for a run's normals at once, and the scene takes
/// triangles' four at a time with AVX2. Every value must still be its own ray's:
/// for a triangle, `normalize(cross(v1 − v0, v2 − v0))` computed here in float64 from
/// the placed triangle, bit for bit; for spheres and planes, the scene's one-ray
/// normal. The rays meet a torus, a sphere and a plane and miss, in runs of 64 whose
/// triangle hits are seldom a multiple of four, with the kernels on and off.
#[test]
fn normals_of_a_run_taken_together_are_each_rays_own() {
    use glam::{DMat4, DVec3};
    use raybatch::integrator::{Integrator, NormalIntegrator};
    use raybatch::mesh::MeshFile;
    use raybatch::plane::Plane;
    use raybatch::scene::{Primitive, Tracer};
    use raybatch::sphere::Sphere;
    use raybatch::{Ray, Scene, SceneGeometry};
    use std::sync::Arc;

    let mut geometry = SceneGeometry {
        spheres: vec![Sphere {
            center: DVec3::new(1.7, 0.3, 0.0),
            radius: 0.7,
        }],
        planes: vec![Plane {
            point: DVec3::new(0.0, -1.0, 0.0),
            normal: DVec3::Y,
        }],
        ..SceneGeometry::default()
    };
    let torus = Arc::new(MeshFile::one_geometry(raybatch::procedural::torus(
        1.0, 0.35, 40, 20,
    )));
    let tilt = DMat4::from_rotation_x(0.7) * DMat4::from_rotation_z(0.3);
    geometry.add_mesh(&torus, tilt, "torus".as_ref()).unwrap();
    // A 61 × 47 grid of rays from one eye, row by row: runs of 64 cross rows and objects.
    let eye = DVec3::new(0.2, 1.5, 4.5);
    let rays: Vec<Ray> = (0..61 * 47)
        .map(|i| {
            let (x, y) = ((i % 61) as f64 / 60.0, (i / 61) as f64 / 46.0);
            let toward = DVec3::new(-2.5 + 5.0 * x, 3.0 - 4.5 * y, 0.0);
            Ray {
                origin: eye,
                direction: (toward - eye).normalize(),
                tmin: 0.0,
                tmax: f64::INFINITY,
            }
        })
        .collect();
    let integrator = NormalIntegrator {
        background: [0.25; 3],
    };
    for simd in [true, false] {
        let mut scene = Scene::build(&geometry);
        scene.set_simd(simd);
        let mut values = vec![[f64::NAN; 3]; rays.len()];
        integrator.values(&scene, &rays, &mut values);
        let mut counts = [0; 4];
        for (i, (ray, value)) in rays.iter().zip(&values).enumerate() {
            let expected = match scene.closest_hit(ray) {
                None => {
                    counts[0] += 1;
                    integrator.background
                }
                Some(hit) => {
                    let n = match hit.primitive {
                        Primitive::Triangle { slot, .. } => {
                            counts[1] += 1;
                            let t = geometry.triangles[scene.triangle_id(slot) as usize];
                            let [p0, p1, p2] = t.map(|v| DVec3::from_array(v.map(f64::from)));
                            (p1 - p0).cross(p2 - p0).normalize()
                        }
                        Primitive::Sphere(_) => {
                            counts[2] += 1;
                            scene.normal(ray, &hit)
                        }
                        Primitive::Plane(_) => {
                            counts[3] += 1;
                            scene.normal(ray, &hit)
                        }
                    };
                    [0.5 * (n.x + 1.0), 0.5 * (n.y + 1.0), 0.5 * (n.z + 1.0)]
                }
            };
            let bits = |v: &[f64; 3]| v.map(f64::to_bits);
            assert_eq!(bits(value), bits(&expected), "simd {simd}, ray {i}");
        }
        assert!(
            counts.iter().all(|&n| n > 100),
            "misses, triangles, spheres, planes: {counts:?}"
        );
    }
}
