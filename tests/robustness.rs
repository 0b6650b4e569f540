//! Watertightness and traversal robustness, each against an independent truth: rays that
//! must hit a closed surface, brute force over every primitive, float64 formulas. Each
//! obvhs trap named in DEVELOPERS.md has a test here showing ours does not have it.

use std::sync::Arc;

use glam::{DMat4, DVec3};
use raybatch::bvh::{BuildPreset, Bvh};
use raybatch::collapse::LeafCost;
use raybatch::mesh::{Geometry, MeshFile};
use raybatch::procedural;
use raybatch::scene::{Grouping, Tracer};
use raybatch::sphere::Sphere;
use raybatch::triangle::{self, ShearedRay};
use raybatch::{AnyHitHint, Ray, Scene, SceneGeometry};

fn placed(geometry: &Geometry, transform: DMat4) -> SceneGeometry {
    let mesh = Arc::new(MeshFile::one_geometry(geometry.clone()));
    let mut scene = SceneGeometry::default();
    scene.add_mesh(&mesh, transform, "test".as_ref()).unwrap();
    scene
}

fn ray(origin: DVec3, toward: DVec3) -> Ray {
    Ray {
        origin,
        direction: (toward - origin).normalize(),
        tmin: 0.0,
        tmax: f64::INFINITY,
    }
}

fn point(p: [f32; 3]) -> DVec3 {
    DVec3::from_array(p.map(f64::from))
}

/// Every vertex and five points along every edge of every triangle (as placed in the
/// world, so they lie exactly on the shared float32 geometry).
fn shared_targets(triangles: &[[[f32; 3]; 3]]) -> Vec<DVec3> {
    let mut targets = Vec::new();
    for t in triangles {
        for k in 0..3 {
            let (a, b) = (point(t[k]), point(t[(k + 1) % 3]));
            targets.push(a);
            for f in [0.5, 0.25, 1.0 / 3.0, 0.7, 0.9] {
                targets.push(a + (b - a) * f);
            }
        }
    }
    targets
}

/// Closed meshes, interior points of each, and the scales and offsets they are placed at.
#[test]
fn rays_through_shared_vertices_and_edges_of_closed_meshes_never_leak() {
    let torus = procedural::torus(1.0, 0.4, 24, 12);
    let meshes: [(&str, Geometry, Vec<DVec3>); 3] = [
        (
            "icosphere",
            procedural::icosphere(3),
            vec![DVec3::ZERO, DVec3::new(0.3, -0.2, 0.1)],
        ),
        (
            "cube",
            procedural::cube(),
            vec![DVec3::ZERO, DVec3::new(0.1, 0.2, -0.3)],
        ),
        (
            "torus",
            torus,
            vec![DVec3::new(1.0, 0.0, 0.0), DVec3::new(0.0, 0.1, -1.05)],
        ),
    ];
    let placements = [
        (1.0, DVec3::ZERO),
        (3.7, DVec3::new(0.3, -1.1, 2.0)),
        (1e-3, DVec3::new(1e-3, 0.0, -2e-3)),
        (1e4, DVec3::new(1e5, -2e5, 3e4)),
    ];
    let mut rays = 0u64;
    for (name, geometry, interior) in &meshes {
        for &(scale, offset) in &placements {
            let transform =
                DMat4::from_translation(offset) * DMat4::from_scale(DVec3::splat(scale));
            let world = placed(geometry, transform);
            let triangles = world.triangles.clone();
            let scene = Scene::build(&world);
            let (mut leaks, mut control_leaks) = (0, 0);
            // Carried from ray to ray: each is tried first against its neighbour's triangle.
            let mut hint = AnyHitHint::default();
            for inside in interior {
                let origin = offset + *inside * scale;
                for target in shared_targets(&triangles) {
                    let r = ray(origin, target);
                    rays += 1;
                    if scene.closest_hit(&r).is_none()
                        || !scene.any_hit(&r)
                        || !scene.any_hit_hinted(&r, &mut hint)
                    {
                        leaks += 1;
                    }
                    if !moller_trumbore_hits(&triangles, &r) {
                        control_leaks += 1;
                    }
                }
            }
            assert_eq!(leaks, 0, "{name} at scale {scale}: rays leaked");
            // The same rays through obvhs' Möller–Trumbore test (brute force, no tree)
            // do leak: the rays really are on the shared edges and vertices.
            assert!(
                control_leaks > 0,
                "{name} at scale {scale}: the control did not leak"
            );
        }
    }
    assert!(rays > 200_000, "{rays}");
}

fn moller_trumbore_hits(triangles: &[[[f32; 3]; 3]], r: &Ray) -> bool {
    let ray = obvhs::ray::Ray::new_inf(r.origin.as_vec3().into(), r.direction.as_vec3().into());
    triangles.iter().any(|t| {
        let tri = obvhs::triangle::Triangle {
            v0: t[0].into(),
            v1: t[1].into(),
            v2: t[2].into(),
        };
        tri.intersect(&ray) < f32::INFINITY
    })
}

/// A deterministic stream of numbers in [0, 1).
struct Numbers(u64);

impl Numbers {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
    fn vector(&mut self, size: f64) -> DVec3 {
        DVec3::new(
            self.range(-size, size),
            self.range(-size, size),
            self.range(-size, size),
        )
    }
}

/// Random triangles of many sizes (some needles and degenerate ones), random rays
/// (including axis-aligned and nearly axis-aligned ones).
fn soup(numbers: &mut Numbers, count: usize) -> (Vec<[[f32; 3]; 3]>, Vec<Ray>) {
    let mut triangles = Vec::new();
    for i in 0..count {
        let centre = numbers.vector(10.0);
        let size = [0.01, 0.3, 2.0, 8.0][i % 4];
        let mut t = [0; 3].map(|_| (centre + numbers.vector(size)).as_vec3().to_array());
        match i % 50 {
            0 => t[2] = t[1], // degenerate
            1 => {
                t[2] = (point(t[0]) + (point(t[1]) - point(t[0])) * 0.5)
                    .as_vec3()
                    .to_array()
            } // needle
            2 => t[1][2] = t[0][2], // axis-aligned edge
            _ => {}
        }
        triangles.push(t);
    }
    let mut rays = Vec::new();
    for i in 0..3000 {
        let origin = numbers.vector(14.0);
        let mut direction = numbers.vector(1.0);
        match i % 6 {
            0 => direction = DVec3::new(0.0, 0.0, if i % 12 == 0 { 1.0 } else { -1.0 }),
            1 => direction = DVec3::new(1e-9, 1.0, -0.0),
            2 => direction.x = 0.0,
            _ => {}
        }
        let tmin = if i % 7 == 0 {
            numbers.range(0.0, 5.0)
        } else {
            0.0
        };
        let tmax = if i % 5 == 0 {
            numbers.range(5.0, 20.0)
        } else {
            f64::INFINITY
        };
        rays.push(Ray {
            origin,
            direction: direction.normalize(),
            tmin,
            tmax,
        });
    }
    (triangles, rays)
}

/// A scene of `triangles` alone, its tree built with `preset`.
fn triangle_scene(triangles: &[[[f32; 3]; 3]], preset: BuildPreset) -> Scene {
    let geometry = SceneGeometry {
        triangles: triangles.to_vec(),
        ..SceneGeometry::default()
    };
    Scene::build_with(&geometry, preset)
}

/// The closest hit's distance over every triangle, tested one by one with the float32
/// watertight test and reported as the tracer reports it: on a thin triangle
/// ([`triangle::is_thin`]) the float64 distance to its plane, where that lies inside the
/// ray's interval.
pub fn brute_force(triangles: &[[[f32; 3]; 3]], r: &Ray) -> Option<f32> {
    let sheared = ShearedRay::new(r.origin.as_vec3(), r.direction.as_vec3());
    let tmin = raybatch::bvh::f32_at_most(r.tmin);
    let mut tmax = raybatch::bvh::f32_at_least(r.tmax);
    let mut best = None;
    for t in triangles {
        if let Some(hit) = triangle::intersect(&sheared, t[0], t[1], t[2], tmin, tmax) {
            tmax = hit.t;
            best = Some((hit.t, t));
        }
    }
    let (t, nearest) = best?;
    if triangle::is_thin(nearest) {
        let plane = triangle::plane_distance(*nearest, r.origin, r.direction);
        if plane > r.tmin && plane < r.tmax {
            return Some(plane as f32);
        }
    }
    Some(t)
}

#[test]
fn traversal_finds_what_brute_force_finds_with_every_preset() {
    let mut numbers = Numbers(7);
    let (triangles, rays) = soup(&mut numbers, 4000);
    let truth: Vec<Option<f32>> = rays.iter().map(|r| brute_force(&triangles, r)).collect();
    assert!(
        truth.iter().filter(|t| t.is_some()).count() > 500,
        "the rays must hit often"
    );
    for preset in BuildPreset::ALL {
        let scene = triangle_scene(&triangles, preset);
        assert_single_rays_find(&scene, &rays, &truth, &format!("{preset:?}"));
    }
}

/// Each leaf tests blocks of its own: its triangles in order, four to a block, the last
/// block padded with its last triangle. Every triangle with area is in exactly one leaf,
/// each lane holds its triangle's own vertices, and no block serves two leaves (a shared
/// block would have a ray test a neighbour's triangles). Over every preset, on a soup with
/// degenerate triangles (left out) and on a closed mesh.
#[test]
fn each_leaf_has_blocks_of_its_own_holding_exactly_its_triangles() {
    let mut numbers = Numbers(5);
    let (soup, _) = soup(&mut numbers, 3000);
    let sphere = placed(&procedural::icosphere(4), DMat4::IDENTITY).triangles;
    for (name, triangles) in [("soup", soup), ("icosphere", sphere)] {
        let with_area: Vec<u32> = (0..triangles.len() as u32)
            .filter(|&i| !triangle::is_degenerate(&triangles[i as usize]))
            .collect();
        assert!(with_area.len() < triangles.len() || name == "icosphere");
        for preset in BuildPreset::ALL {
            let context = format!("{name}, {preset:?}");
            let tree = raybatch::scene::TriangleTree::build(&triangles, preset);
            let blocks = tree.blocks();
            let mut block_leaves = vec![0; blocks.len()];
            let mut leaves_of_triangle = vec![0; triangles.len()];
            for (first, count) in tree.bvh().leaves() {
                let range = first as usize..(first + count) as usize;
                for b in range.clone() {
                    block_leaves[b] += 1;
                }
                let ids: Vec<u32> = blocks[range].iter().flat_map(|b| b.ids).collect();
                // The leaf's triangles, then repeats of the last to fill its last block.
                let mut own = ids.clone();
                own.dedup();
                let last = *own.last().unwrap();
                assert_eq!(count as usize, own.len().div_ceil(4), "{context}");
                assert!(ids[own.len()..].iter().all(|&id| id == last), "{context}");
                for id in own {
                    leaves_of_triangle[id as usize] += 1;
                }
            }
            assert!(block_leaves.iter().all(|&n| n == 1), "{context}");
            for (id, &n) in leaves_of_triangle.iter().enumerate() {
                let expected = usize::from(with_area.binary_search(&(id as u32)).is_ok());
                assert_eq!(n, expected, "{context}: triangle {id}");
            }
            for block in blocks {
                for lane in 0..4 {
                    let id = block.ids[lane] as usize;
                    let vertices = [0, 1, 2].map(|k| block.vertex(lane, k));
                    assert_eq!(vertices, triangles[id], "{context}: triangle {id}");
                }
            }
        }
    }
}

/// Thousands of copies of one triangle, among other triangles: obvhs' PLOC passes chain
/// them. Our radius-1 passes pair them up and the wider searches' trees are built again;
/// either way the tree must stay within the vector kernels' stack and find what brute
/// force finds, ray by ray and in batches.
#[test]
fn copies_of_one_triangle_are_found_as_brute_force_finds_them() {
    let mut numbers = Numbers(11);
    let (mut triangles, mut rays) = soup(&mut numbers, 300);
    let copy = [[-6.0, -6.0, 1.0], [6.0, -4.0, -2.0], [0.0, 7.0, 3.0]];
    // Rays aimed at points of the copies (and a little past their edges).
    let [a, b, c] = copy.map(point);
    for _ in 0..1000 {
        let (u, v) = (numbers.range(-0.1, 1.0), numbers.range(-0.1, 1.0));
        let target = a + (b - a) * u + (c - a) * v * (1.0 - u);
        rays.push(ray(numbers.vector(14.0), target));
    }
    triangles.extend(std::iter::repeat_n(copy, 3000));
    let truth: Vec<Option<f32>> = rays.iter().map(|r| brute_force(&triangles, r)).collect();
    let on_copy = rays
        .iter()
        .zip(&truth)
        .filter(|(r, t)| t.is_some() && brute_force(&[copy], r) == **t)
        .count();
    assert!(on_copy > 200, "the copies must be hit often: {on_copy}");
    for preset in BuildPreset::ALL {
        let scene = triangle_scene(&triangles, preset);
        let bvh = scene.triangle_tree().bvh();
        assert!(
            bvh.stack_bound() <= raybatch::bvh::KERNEL_STACK,
            "{preset:?}: depth {}",
            bvh.depth()
        );
        assert_single_rays_find(&scene, &rays, &truth, &format!("{preset:?}"));
        assert_batches_find(&scene, &rays, &truth, &format!("{preset:?} batch"));
    }
}

/// Asserts that each ray's closest hit, any hit, and any hit with one hint carried from
/// ray to ray (mostly naming a block and subtree the next ray misses) are `truth`'s.
fn assert_single_rays_find(scene: &Scene, rays: &[Ray], truth: &[Option<f32>], label: &str) {
    let mut hint = AnyHitHint::default();
    for (r, expected) in rays.iter().zip(truth) {
        let got = scene.closest_hit(r).map(|h| h.t as f32);
        assert_eq!(got, *expected, "{label}: {r:?}");
        assert_eq!(
            scene.any_hit(r),
            expected.is_some(),
            "{label} any-hit: {r:?}"
        );
        let hinted = scene.any_hit_hinted(r, &mut hint);
        assert_eq!(hinted, expected.is_some(), "{label} hinted any-hit: {r:?}");
    }
}

#[test]
fn ten_thousand_spheres_trace_like_brute_force() {
    let mut numbers = Numbers(3);
    let spheres: Vec<Sphere> = (0..10_000)
        .map(|_| Sphere {
            center: numbers.vector(50.0),
            radius: numbers.range(0.01, 1.5),
        })
        .collect();
    let scene = Scene::build(&SceneGeometry {
        spheres: spheres.clone(),
        ..SceneGeometry::default()
    });
    let brute_any = |r: &Ray| spheres.iter().any(|s| s.intersect(r, r.tmax).is_some());
    let mut hits = 0;
    let mut hint = AnyHitHint::default();
    for _ in 0..2000 {
        let r = ray(numbers.vector(60.0), numbers.vector(20.0));
        let mut best: Option<(f64, u32)> = None;
        for (i, s) in spheres.iter().enumerate() {
            if let Some(t) = s.intersect(&r, best.map_or(r.tmax, |b| b.0)) {
                best = Some((t, i as u32));
            }
        }
        let got = scene.closest_hit(&r).map(|h| h.t);
        assert_eq!(got, best.map(|b| b.0));
        assert_eq!(scene.any_hit(&r), best.is_some());
        assert_eq!(scene.any_hit_hinted(&r, &mut hint), best.is_some());
        hits += usize::from(best.is_some());
        // The hint now names a sphere this ray hits: the same ray stopped short of every
        // hit, or started past the nearest, must still get the brute-force answer.
        if let Some((t, _)) = best {
            for part in [
                Ray {
                    tmax: t * 0.999,
                    ..r
                },
                Ray {
                    tmin: t * 1.001,
                    ..r
                },
            ] {
                let mut h = hint;
                assert_eq!(scene.any_hit_hinted(&part, &mut h), brute_any(&part));
            }
        }
    }
    assert!(hits > 200, "{hits}");
}

#[test]
fn a_deep_tree_never_overflows_the_traversal_stack() {
    // obvhs' CWBVH stack has 32 entries and drops the rest. Build a degenerate binary tree
    // by hand (each inner node: a leaf and the rest of the chain), so the wide tree is
    // hundreds of levels deep, and aim a ray through every box: it misses every triangle
    // but the last one, which lies deepest.
    use obvhs::aabb::Aabb;
    use obvhs::bvh2::{Bvh2, node::Bvh2Node};
    let n = 3000;
    let mut triangles = Vec::new();
    for k in 0..n {
        let z = 1.0 + k as f32;
        // Its box contains the z axis, the triangle does not (x + y ≥ 0.5 inside).
        triangles.push([[1.0, -0.5, z], [-0.5, 1.0, z], [1.0, 1.0, z]]);
    }
    let last = n as f32 + 1.0;
    triangles.push([[-1.0, -1.0, last], [1.0, -1.0, last], [0.0, 1.0, last]]);
    let bounds: Vec<raybatch::bvh::Bounds<f32>> = triangles
        .iter()
        .map(|t| raybatch::bvh::Bounds {
            min: [0, 1, 2].map(|a| t.iter().map(|v| v[a]).fold(f32::INFINITY, f32::min)),
            max: [0, 1, 2].map(|a| t.iter().map(|v| v[a]).fold(f32::NEG_INFINITY, f32::max)),
        })
        .collect();
    let aabb = |b: &raybatch::bvh::Bounds<f32>| Aabb::new(b.min.into(), b.max.into());
    // Node 2k: inner (children 2k+1, 2k+2); node 2k+1: leaf of triangle k.
    let mut bvh2 = Bvh2::default();
    let m = triangles.len();
    for k in 0..m - 1 {
        let rest = bounds[k..]
            .iter()
            .fold(aabb(&bounds[k]), |acc, b| acc.union(&aabb(b)));
        bvh2.nodes.push(Bvh2Node::new(rest, 0, 2 * k as u32 + 1));
        bvh2.nodes
            .push(Bvh2Node::new(aabb(&bounds[k]), 1, k as u32));
    }
    bvh2.nodes
        .push(Bvh2Node::new(aabb(&bounds[m - 1]), 1, (m - 1) as u32));
    bvh2.primitive_indices = (0..m as u32).collect();

    let (bvh, order): (Bvh<f32>, _) = Bvh::from_bvh2(&bvh2, 1, LeafCost::ONE_BY_ONE);
    assert!(bvh.stack_bound() > 1000, "bound {}", bvh.stack_bound());

    let origin = glam::Vec3::new(0.0, 0.0, 0.0);
    let direction = glam::Vec3::Z;
    let boxes = raybatch::bvh::BoxRay::new(origin.to_array(), direction.to_array(), 0.0);
    let sheared = ShearedRay::new(origin, direction);
    let test = |i: u32, tmax: f32| {
        let t = &triangles[order[i as usize] as usize];
        triangle::intersect(&sheared, t[0], t[1], t[2], 0.0, tmax)
    };
    let mut tmax = f32::INFINITY;
    let mut visited = 0;
    bvh.closest(&boxes, &mut tmax, |first, _, tmax| {
        visited += 1;
        if let Some(hit) = test(first, *tmax) {
            *tmax = hit.t;
        }
    });
    assert!(
        (tmax - last).abs() <= last * 1e-6,
        "the deepest triangle must be found: {tmax}"
    );
    assert_eq!(visited, m, "every leaf box is entered");
    assert!(bvh.any(&boxes, f32::INFINITY, |first, _| {
        test(first, f32::INFINITY).is_some()
    }));
}

#[test]
fn hits_closer_than_1e_4_count_when_tmin_is_zero() {
    // obvhs' CWBVH node test starts every box at t = 1e-4 whatever the ray's tmin.
    let tri = [[-1.0, -1.0, 5e-5], [1.0, -1.0, 5e-5], [0.0, 1.0, 5e-5]];
    let scene = Scene::build(&SceneGeometry {
        triangles: vec![tri],
        ..SceneGeometry::default()
    });
    let mut r = ray(DVec3::ZERO, DVec3::Z);
    let hit = scene.closest_hit(&r).expect("hit at 5e-5");
    assert!((hit.t - 5e-5).abs() < 5e-5 * 1e-6, "{}", hit.t);
    r.tmin = 1e-4;
    assert!(scene.closest_hit(&r).is_none());
    assert!(!scene.any_hit(&r));
}

#[test]
fn tiny_and_zero_direction_components_find_real_hits() {
    // Tiny: obvhs' safe_inverse turns 1e-9 into ±1/ε and misses this triangle, reached at
    // x = 1e8 where y has climbed to 0.1.
    let far = [[1.0e8, 0.05, -1.0], [1.0e8, 0.15, -1.0], [1.0e8, 0.1, 1.0]];
    let scene = Scene::build(&SceneGeometry {
        triangles: vec![far],
        ..SceneGeometry::default()
    });
    let r = Ray {
        origin: DVec3::ZERO,
        direction: DVec3::new(1.0, 1e-9, 0.0).normalize(),
        tmin: 0.0,
        tmax: f64::INFINITY,
    };
    let hit = scene.closest_hit(&r).expect("tiny component");
    assert!((hit.t - 1.0e8).abs() < 10.0, "{}", hit.t);

    // Zero: rays along +z starting exactly in the plane of a cube face (so ∞·0 appears in
    // the box test) and through the cube's edges: each must hit the near face at z = -1.
    let scene = Scene::build(&placed(
        &procedural::cube(),
        DMat4::from_scale(DVec3::splat(2.0)),
    ));
    for x in [-1.0, -0.5, 0.0, 0.5, 1.0] {
        for y in [-1.0, -0.25, 0.0, 1.0] {
            for dz in [1.0, -1.0] {
                let r = Ray {
                    origin: DVec3::new(x, y, -5.0 * dz),
                    direction: DVec3::new(0.0, -0.0, dz),
                    tmin: 0.0,
                    tmax: f64::INFINITY,
                };
                let hit = scene
                    .closest_hit(&r)
                    .unwrap_or_else(|| panic!("({x}, {y}) {dz}"));
                assert_eq!(hit.t, 4.0, "({x}, {y}) {dz}");
            }
        }
    }
}

#[test]
fn rays_grazing_or_ending_on_the_tree_bounds_find_what_brute_force_finds() {
    // Every hit here lies on the faces of the boxes around it (a cube, a flat grid whose
    // box has no thickness, a lone triangle), where a triangle's computed distance can
    // round below its box's computed entry distance. Rays aim at the box's corners, edges
    // and faces from every side and along them, and some end at the hit (tmax 4): those
    // find it only if every search enters boxes up to the horizon just past tmax, as
    // closest-hit searches after a first hit do. The scalar closest-hit search and both
    // any-hit searches entered only up to tmax, and missed hits such a ray found.
    // Single rays and packets are also first tested against the box around the whole
    // tree, and end there if they miss it: that test must never turn away a ray the
    // tree's own node tests admit, here where every hit lies on that box.
    let grid = placed(&procedural::pixel_grid(4), DMat4::IDENTITY);
    let cube = placed(&procedural::cube(), DMat4::from_scale(DVec3::splat(2.0)));
    let lone = vec![[[0.25, -1.0, 3.0], [1.0, 0.5, 3.0], [-0.5, 0.75, 3.0]]];
    let mut numbers = Numbers(41);
    for (name, triangles) in [
        ("grid", grid.triangles),
        ("cube", cube.triangles),
        ("lone", lone),
    ] {
        let (lo, hi) = triangles
            .iter()
            .flatten()
            .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(point(v)), hi.max(point(v)))
            });
        // The box's corners, edge and face points, and the triangles' own vertices and
        // edge points (on the box too for the grid and the cube).
        let mut targets = shared_targets(&triangles);
        for i in 0..27 {
            let f = [i % 3, i / 3 % 3, i / 9].map(|k| k as f64 / 2.0);
            targets.push(lo + (hi - lo) * DVec3::from_array(f));
        }
        let mut directions: Vec<DVec3> = vec![
            DVec3::X,
            DVec3::NEG_X,
            DVec3::Y,
            DVec3::NEG_Y,
            DVec3::Z,
            DVec3::NEG_Z,
            DVec3::new(-0.0, 0.0, 1.0),
            DVec3::new(1.0, 1.0, 0.0),
            DVec3::new(0.0, -1.0, 1.0),
            DVec3::ONE,
            DVec3::new(1.0, -1.0, -1.0),
        ];
        for _ in 0..8 {
            directions.push(numbers.vector(1.0));
        }
        let mut rays = Vec::new();
        for &target in &targets {
            for &d in &directions {
                let d = d.normalize();
                // Toward the target from outside, from the target outward, and ending
                // at the target (tmax at the hit).
                rays.push(Ray {
                    origin: target - d * 4.0,
                    direction: d,
                    tmin: 0.0,
                    tmax: f64::INFINITY,
                });
                rays.push(Ray {
                    origin: target,
                    direction: d,
                    tmin: 0.0,
                    tmax: f64::INFINITY,
                });
                rays.push(Ray {
                    origin: target - d * 4.0,
                    direction: d,
                    tmin: 0.0,
                    tmax: 4.0,
                });
            }
        }
        let truth: Vec<Option<f32>> = rays.iter().map(|r| brute_force(&triangles, r)).collect();
        let hits = truth.iter().filter(|t| t.is_some()).count();
        assert!(
            hits > rays.len() / 10,
            "{name}: {hits} of {} rays hit",
            rays.len()
        );
        let mut scene = Scene::build(&SceneGeometry {
            triangles: triangles.clone(),
            ..SceneGeometry::default()
        });
        for simd in [true, false] {
            scene.set_simd(simd);
            assert_single_rays_find(&scene, &rays, &truth, &format!("{name} simd {simd}"));
        }
        // Packets, which test that box first too: each ray above alone (a packet's bounds
        // are then exactly its own), and parallel rays toward up to 64 targets each,
        // ending at them or not.
        scene.set_simd(true);
        scene.set_grouping(Grouping::Packets);
        for (r, expected) in rays.iter().zip(&truth) {
            assert!(!scene.uses_simd() || scene.traces_as_packet(std::slice::from_ref(r)));
            let (closest, any) = batch_queries(&scene, std::slice::from_ref(r));
            assert_eq!(
                closest[0].map(|h| h.t as f32),
                *expected,
                "{name} packet of one: {r:?}"
            );
            assert_eq!(
                any[0],
                expected.is_some(),
                "{name} packet of one, any: {r:?}"
            );
        }
        for &d in &directions {
            let d = d.normalize();
            for chunk in targets.chunks(64) {
                for tmax in [f64::INFINITY, 4.0] {
                    let group: Vec<Ray> = chunk
                        .iter()
                        .map(|&target| Ray {
                            origin: target - d * 4.0,
                            direction: d,
                            tmin: 0.0,
                            tmax,
                        })
                        .collect();
                    assert!(!scene.uses_simd() || scene.traces_as_packet(&group));
                    let truth: Vec<Option<f32>> =
                        group.iter().map(|r| brute_force(&triangles, r)).collect();
                    assert_batches_find(&scene, &group, &truth, &format!("{name} packet"));
                }
            }
        }
    }
}

#[test]
fn a_tiny_far_sphere_matches_float64_where_the_naive_float32_formula_fails() {
    // Radius 1 at distance 1e4, seen by a camera zoomed 5000x: about 800 pixels.
    let (w, h) = (64u32, 64u32);
    let (c, r) = ([0.0, 0.0, 1.0e4], 1.0);
    let dir = crate::util::Dir::new();
    let image = dir.ppm_of(
        "tiny.json",
        r#"{"image": {"width": 64, "height": 64},
            "camera": {"right": [2e-4, 0, 0], "up": [0, 2e-4, 0]},
            "spheres": [{"center": [0, 0, 10000], "radius": 1}]}"#,
        "tiny.ppm",
    );
    let (mut reference_hits, mut naive_hits, mut compared) = (0, 0, 0);
    for y in 0..h {
        for x in 0..w {
            let u = 2.0 * (f64::from(x) + 0.5) / f64::from(w) - 1.0;
            let v = 1.0 - 2.0 * (f64::from(y) + 0.5) / f64::from(h);
            let d = DVec3::new(u * 2e-4, v * 2e-4, 1.0).normalize();
            // Float64: squared distance from the centre to the ray's line.
            let cv = DVec3::from_array(c);
            let distance2 = cv.cross(d).length_squared();
            let margin = (distance2 - r * r).abs();
            let hit = distance2 < r * r;
            if margin > 1e-9 {
                compared += 1;
                let got = image.at(x as usize, y as usize) == [255; 3];
                assert_eq!(got, hit, "pixel ({x}, {y})");
            }
            reference_hits += usize::from(hit);
            // The tutorial's formula in float32.
            let d32 = d.as_vec3();
            let oc = -glam::Vec3::from_array([c[0] as f32, c[1] as f32, c[2] as f32]);
            let b = oc.dot(d32);
            let discriminant = b * b - (oc.dot(oc) - 1.0);
            naive_hits += usize::from(discriminant > 0.0 && -b > 0.0);
        }
    }
    assert!(reference_hits > 500, "{reference_hits}");
    assert!(compared > 4000);
    assert_eq!(
        naive_hits, 0,
        "the naive formula was expected to see nothing"
    );
}

/// Asserts that the batch queries (64 rays at a time) give each of `rays` `truth`'s
/// closest-hit distance and any hit.
fn assert_batches_find(scene: &Scene, rays: &[Ray], truth: &[Option<f32>], label: &str) {
    let (closest, any) = batch_queries(scene, rays);
    for ((r, expected), (got, got_any)) in rays.iter().zip(truth).zip(closest.iter().zip(&any)) {
        assert_eq!(got.map(|h| h.t as f32), *expected, "{label}: {r:?}");
        assert_eq!(*got_any, expected.is_some(), "{label} any: {r:?}");
    }
}

/// Closest and any hits of `rays` through the batch queries, 64 rays at a time (as the
/// renderer groups camera rays).
fn batch_queries(scene: &Scene, rays: &[Ray]) -> (Vec<Option<raybatch::Hit>>, Vec<bool>) {
    let mut closest = vec![None; rays.len()];
    let mut any = vec![false; rays.len()];
    for ((rays, closest), any) in rays
        .chunks(64)
        .zip(closest.chunks_mut(64))
        .zip(any.chunks_mut(64))
    {
        scene.closest_hits(rays, closest);
        scene.any_hits(rays, any);
    }
    (closest, any)
}

/// Whether the AVX2 paths run here (tests comparing them with the scalar path need them).
fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    if raybatch::simd::available() {
        return true;
    }
    eprintln!("this CPU has no AVX2: only the scalar path runs here");
    false
}

#[test]
fn the_avx2_kernels_and_packets_give_bit_identical_hits_to_the_scalar_path() {
    // Includes rays through shared edges (the pixel grid, the icosphere from inside), where
    // which of two triangles at exactly the same distance is reported depends on the
    // visiting order: the normal integrator would show a difference.
    if !has_avx2() {
        return;
    }
    let mut numbers = Numbers(99);
    let (soup_triangles, mut rays) = soup(&mut numbers, 3000);
    // Shift the soup's rays so whole 64-ray groups of them start at the tiled rays below.
    rays.truncate(rays.len() / 64 * 64);
    let grid = placed(&procedural::pixel_grid(64), DMat4::IDENTITY);
    let ico = placed(&procedural::icosphere(3), DMat4::IDENTITY);
    // Camera rays in 8 × 8 tiles (as the renderer traces them): packet-eligible groups.
    let tiled_start = rays.len();
    for tile in 0..64 {
        for i in 0..64 {
            let (x, y) = (tile % 8 * 8 + i % 8, tile / 8 * 8 + i / 8);
            let d = crate::util::default_camera_direction(x, y, 64, 64);
            rays.push(ray(
                DVec3::new(0.01, 0.02, -0.5),
                DVec3::from_array(d) + DVec3::new(0.01, 0.02, -0.5),
            ));
        }
    }
    // Rays through a thin lens, in 8 × 8 tiles: origins spread over a disk, meeting at a
    // focus plane in front of, among or behind the surfaces. Packets bound them from where
    // they meet, so boxes before that plane are at negative distances from it.
    let lens_start = rays.len();
    // The batch queries take 64 rays at a time from the first: each tile is a packet.
    assert_eq!(lens_start % 64, 0);
    let mut lens = Numbers(7);
    for (eye, focus, aperture, (tmin, tmax)) in [
        (
            DVec3::new(0.01, 0.02, -0.5),
            0.3,
            0.05,
            (0.0, f64::INFINITY),
        ),
        (
            DVec3::new(0.03, -0.04, -4.0),
            2.5,
            0.2,
            (0.0, f64::INFINITY),
        ),
        (
            DVec3::new(0.03, -0.04, -4.0),
            4.0,
            0.2,
            (3.5, f64::INFINITY),
        ),
        (DVec3::new(0.03, -0.04, -4.0), 9.0, 0.4, (0.0, 4.2)),
    ] {
        // A 32 × 32 corner of a 512² image off the axis: pixels narrow against the lens,
        // and directions of one sign on each axis.
        for tile in 0..16 {
            for i in 0..64 {
                let (x, y) = (288 + tile % 4 * 8 + i % 8, 288 + tile / 4 * 8 + i / 8);
                let d = DVec3::from_array(crate::util::default_camera_direction(x, y, 512, 512));
                let (radius, angle) = (
                    lens.range(0.0, 1.0).sqrt() * aperture,
                    lens.range(0.0, std::f64::consts::TAU),
                );
                let origin = eye + DVec3::new(radius * angle.cos(), radius * angle.sin(), 0.0);
                rays.push(Ray {
                    tmin,
                    tmax,
                    ..ray(origin, eye + d * (focus / d.z))
                });
            }
        }
    }
    let lens_end = rays.len();
    for target in shared_targets(&ico.triangles).into_iter().step_by(7) {
        rays.push(ray(DVec3::new(0.01, -0.02, 0.03), target));
    }
    // Directions whose setup takes the special branches: zero and negative-zero
    // components (infinite inverses), and ties for the largest component (which axis the
    // shear divides by).
    let special = [
        [0.0, 0.0, 1.0],
        [-0.0, 0.0, -1.0],
        [0.0, -1.0, -0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [-1.0, 1.0, 1.0],
        [1.0, -1.0, -1.0],
        [0.0, 1.0, -1.0],
        [1e-30, -1.0, 1e-30],
    ];
    for d in special {
        for k in 0..16 {
            let origin = DVec3::new(
                0.05 * k as f64 - 0.4,
                0.37 - 0.045 * k as f64,
                0.013 * k as f64,
            );
            rays.push(Ray {
                origin: origin - DVec3::from_array(d) * 2.0,
                direction: DVec3::from_array(d),
                tmin: 0.0,
                tmax: f64::INFINITY,
            });
        }
    }
    for triangles in [soup_triangles, grid.triangles, ico.triangles] {
        for preset in [BuildPreset::default(), BuildPreset::Medium] {
            let mut scene = Scene::build_with(
                &SceneGeometry {
                    triangles: triangles.clone(),
                    ..SceneGeometry::default()
                },
                preset,
            );
            assert!(scene.uses_simd());
            // Every group that can be a packet is one, wasteful or not.
            scene.set_grouping(Grouping::Packets);
            let fast: Vec<_> = rays
                .iter()
                .map(|r| (scene.closest_hit(r), scene.any_hit(r)))
                .collect();
            // The batch queries (packets of coherent rays, single rays otherwise) agree too,
            // with the packets' leaf tests eight rays wide and, where the CPU has AVX-512,
            // sixteen.
            assert!(
                rays[tiled_start..tiled_start + 64 * 64]
                    .chunks(64)
                    .all(|group| scene.traces_as_packet(group))
            );
            // Lens tiles off the axis keep their direction signs.
            let lens_groups = rays[lens_start..lens_end].chunks(64);
            let lens_packets = lens_groups.filter(|g| scene.traces_as_packet(g)).count();
            assert!(lens_packets >= 56, "{lens_packets} lens packets of 64");
            // Then every group as single rays traced side by side, as the pacing has them
            // after wasteful packets: four searches in turns, each slot taking the next ray
            // as its search ends, among rays that miss the tree's box or are stopped by the
            // block that stopped the slot's last ray.
            for (wide, grouping) in [
                (false, Grouping::Packets),
                (true, Grouping::Packets),
                (false, Grouping::SideBySide),
            ] {
                scene.set_wide_leaves(wide);
                scene.set_grouping(grouping);
                if wide && !scene.uses_wide_leaves() {
                    eprintln!("this CPU has no AVX-512: sixteen-lane packets do not run here");
                    continue;
                }
                let (closest, any) = batch_queries(&scene, &rays);
                for (i, ((c, a), f)) in closest.iter().zip(&any).zip(&fast).enumerate() {
                    assert_eq!(
                        (c, a),
                        (&f.0, &f.1),
                        "{preset:?}, wide leaves {wide}, {grouping:?}: batch ray {i}: {:?}",
                        rays[i]
                    );
                }
            }
            scene.set_simd(false);
            assert!(!scene.uses_simd());
            let scalar: Vec<_> = rays
                .iter()
                .map(|r| (scene.closest_hit(r), scene.any_hit(r)))
                .collect();
            assert!(fast.iter().filter(|h| h.0.is_some()).count() > 100);
            for (i, (a, b)) in fast.iter().zip(&scalar).enumerate() {
                assert_eq!(a, b, "{preset:?}: ray {i}: {:?}", rays[i]);
            }
        }
    }
}

#[test]
fn the_avx2_sphere_tree_gives_the_same_hits_as_the_scalar_path() {
    if !has_avx2() {
        return;
    }
    // Scattered spheres of many sizes, a row of spheres touching each other (rays along it
    // meet ties), and a cluster far from the origin.
    let mut numbers = Numbers(7);
    let mut spheres: Vec<Sphere> = (0..600)
        .map(|_| Sphere {
            center: numbers.vector(10.0),
            radius: numbers.range(0.01, 0.6),
        })
        .collect();
    spheres.extend((0..20).map(|i| Sphere {
        center: DVec3::new(f64::from(i) - 10.0, 0.25, 0.5),
        radius: 0.5,
    }));
    spheres.extend((0..50).map(|_| Sphere {
        center: DVec3::splat(1e6) + numbers.vector(1.0),
        radius: numbers.range(1e-4, 1e-2),
    }));
    let mut rays: Vec<Ray> = (0..4000)
        .map(|_| ray(numbers.vector(30.0), numbers.vector(8.0)))
        .collect();
    rays.extend((0..200).map(|_| {
        let origin = DVec3::splat(1e6) + numbers.vector(3.0);
        ray(origin, DVec3::splat(1e6) + numbers.vector(1.0))
    }));
    for d in [
        [1.0, 0.0, 0.0],
        [-1.0, -0.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 1.0, 0.0],
    ] {
        for k in 0..40 {
            let offset = DVec3::new(0.0, 0.02 * f64::from(k) - 0.4, 0.013 * f64::from(k));
            rays.push(Ray {
                origin: DVec3::new(-12.0, 0.25, 0.5) + offset,
                direction: DVec3::from_array(d).normalize(),
                tmin: 0.0,
                tmax: f64::INFINITY,
            });
        }
    }
    for preset in [BuildPreset::default(), BuildPreset::Medium] {
        let mut scene = Scene::build_with(
            &SceneGeometry {
                spheres: spheres.clone(),
                ..SceneGeometry::default()
            },
            preset,
        );
        let trace = |scene: &Scene| -> Vec<_> {
            rays.iter()
                .map(|r| (scene.closest_hit(r), scene.any_hit(r)))
                .collect()
        };
        let fast = trace(&scene);
        scene.set_simd(false);
        let scalar = trace(&scene);
        assert!(fast.iter().filter(|h| h.0.is_some()).count() > 1000);
        for (i, (a, b)) in fast.iter().zip(&scalar).enumerate() {
            assert_eq!(a, b, "{preset:?}: ray {i}: {:?}", rays[i]);
        }
    }
}

/// 8 × 8 tiles of camera rays from `eye` toward `target`, 64 rays per tile (as the
/// renderer groups them), for a `size` × `size` image with a 90° field of view.
fn tiled_camera_rays(eye: DVec3, target: DVec3, size: u32) -> Vec<Ray> {
    tiled_lens_rays(eye, target, size, 1.0, 0.0, &mut Numbers(0))
}

/// As [`tiled_camera_rays`], with the field's half-width scaled by `zoom` (its tangent),
/// through a thin lens of radius `aperture` focused on `target`: each ray starts at a
/// random point of the lens (a disk) and goes through the point its pixel's pinhole ray
/// meets on the focus plane.
fn tiled_lens_rays(
    eye: DVec3,
    target: DVec3,
    size: u32,
    zoom: f64,
    aperture: f64,
    numbers: &mut Numbers,
) -> Vec<Ray> {
    let focus = (target - eye).length();
    let forward = (target - eye) / focus;
    let right = forward.cross(DVec3::Y).normalize();
    let up = right.cross(forward);
    let tiles = size / 8;
    (0..tiles * tiles * 64)
        .map(|i| {
            let (tile, k) = (i / 64, i % 64);
            let (x, y) = (tile % tiles * 8 + k % 8, tile / tiles * 8 + k / 8);
            let [u, v, w] = crate::util::default_camera_direction(x, y, size, size);
            let pixel = (right * u + up * v) * zoom + forward * w;
            if aperture == 0.0 {
                return ray(eye, eye + pixel);
            }
            let (radius, angle) = (
                numbers.range(0.0, 1.0).sqrt() * aperture,
                numbers.range(0.0, std::f64::consts::TAU),
            );
            let origin = eye + (right * angle.cos() + up * angle.sin()) * radius;
            ray(origin, eye + pixel * (focus / w))
        })
        .collect()
}

#[test]
fn sphere_packets_find_what_single_rays_and_brute_force_find() {
    // Packets bound a whole group's box distances from its ranges of origin and inverse
    // direction; a wrong bound drops spheres some ray of the group hits. The truth here
    // is brute force over every sphere, and each ray traced alone.
    if !has_avx2() {
        return;
    }
    let mut numbers = Numbers(31);
    let mut spheres: Vec<Sphere> = (0..2000)
        .map(|_| Sphere {
            center: numbers.vector(10.0),
            radius: numbers.range(0.02, 0.5),
        })
        .collect();
    // A sphere whose box planes lie exactly on the axis-parallel rays' origins below.
    spheres.push(Sphere {
        center: DVec3::new(0.25, -0.5, 20.0),
        radius: 0.25,
    });
    let mut rays = Vec::new();
    // Camera tiles from outside the field, from inside it, and zoomed in on one sphere.
    for (eye, target, size) in [
        (DVec3::new(8.0, 12.0, 30.0), DVec3::ZERO, 96),
        (DVec3::new(0.3, -0.2, 0.1), DVec3::new(5.0, 1.0, -3.0), 64),
        (DVec3::new(-1.0, 0.5, -40.0), spheres[7].center, 32),
    ] {
        rays.extend(tiled_camera_rays(eye, target, size));
    }
    // Tiles through thin lenses wider than a tile's footprint on the focus plane (so
    // packets are bounded from where their rays meet): origins spread over the lens,
    // meeting among the spheres, behind them, or close in front of the eye, so that the
    // packets see boxes on both sides of that plane.
    let lens_start = rays.len();
    let mut lens = Numbers(37);
    for (eye, target, size, zoom, aperture) in [
        (DVec3::new(8.0, 12.0, 30.0), DVec3::ZERO, 64, 0.3, 2.0),
        (
            DVec3::new(8.0, 12.0, 30.0),
            DVec3::new(-2.0, -3.0, -8.0),
            32,
            0.2,
            3.0,
        ),
        (
            DVec3::new(0.3, -0.2, 0.1),
            DVec3::new(1.5, 0.1, -0.5),
            32,
            0.3,
            0.2,
        ),
    ] {
        rays.extend(tiled_lens_rays(
            eye, target, size, zoom, aperture, &mut lens,
        ));
    }
    let lens_end = rays.len();
    // Groups of rays with exactly zero components (infinite inverses) next to rays
    // without. The first: rays along +z, some starting on the last sphere's box planes
    // x = 0, x = 0.5, y = -0.75 (where `0 · ∞` is NaN in the group's bounds), the others
    // hitting the sphere. The second: rays parallel to x = -1 beside rays starting on the
    // plane x = 0 and crossing the sphere at a slant, whose group bound on that axis is
    // unbounded below only because of the NaN; and rays whose tmax ends short of the
    // sphere, which must not cut the others' search short.
    for k in 0..64 {
        let (x, y) = [(0.0, -0.75), (0.25, -0.5), (0.5, -0.6), (0.1, -0.55)][k % 4];
        rays.push(Ray {
            origin: DVec3::new(x, y, 10.0 + k as f64 * 0.01),
            direction: DVec3::Z,
            tmin: 0.0,
            tmax: f64::INFINITY,
        });
    }
    let slant = DVec3::new(0.1, 0.0, 1.0).normalize();
    let probe = spheres.len() - 1;
    let mut scene = Scene::build(&SceneGeometry {
        spheres: spheres.clone(),
        ..SceneGeometry::default()
    });
    // Every group that can be a packet is one, wasteful or not.
    scene.set_grouping(Grouping::Packets);
    // The plane x = x0 the tightest box around the last sphere starts at (its box is
    // rounded outward from x = 0).
    let x0 = scene
        .sphere_bvh()
        .nodes()
        .iter()
        .flat_map(|node| (0..8).map(move |slot| node.planes.map(|side| side.map(|a| a[slot]))))
        .filter(|[lo, hi]| {
            (0..3).all(|a| lo[a] <= spheres[probe].center[a] && spheres[probe].center[a] <= hi[a])
        })
        .map(|[lo, _]| lo[0])
        .fold(f64::NEG_INFINITY, f64::max);
    assert!(x0 <= 0.0 && x0 > -1e-6, "{x0}");
    for k in 0..64 {
        let z = 19.0 + k as f64 * 1e-3;
        let (origin, direction, tmax) = [
            (DVec3::new(-1.0, -0.5, z), DVec3::Z, f64::INFINITY),
            (DVec3::new(x0, -0.5, z), slant, f64::INFINITY),
            (DVec3::new(x0, -0.45, z), slant, 0.5),
            (DVec3::new(x0, -0.45, z), slant, f64::INFINITY),
        ][k % 4];
        rays.push(Ray {
            origin,
            direction,
            tmin: 0.0,
            tmax,
        });
    }
    let start = rays.len() - 128;
    let cut: Vec<Ray> = tiled_camera_rays(DVec3::new(8.0, 12.0, 30.0), DVec3::ZERO, 32)
        .into_iter()
        .enumerate()
        .map(|(i, mut r)| {
            r.tmin = [0.0, 30.0, 36.5][i % 3];
            r.tmax = [f64::INFINITY, 37.0, 40.0, 45.0][i % 4];
            r
        })
        .collect();
    rays.extend(cut);
    assert!(scene.uses_sphere_packets());
    // Groups straddling an axis of the view mix direction signs and go ray by ray.
    let packets = rays
        .chunks(64)
        .filter(|g| scene.traces_as_packet(g))
        .count();
    assert!(packets * 4 > rays.len() / 64 * 3, "{packets} packets");
    let lens_packets = rays[lens_start..lens_end]
        .chunks(64)
        .filter(|g| scene.traces_as_packet(g))
        .count();
    // (Tiles across an axis of the view mix direction signs, as above.)
    assert!(
        lens_packets * 2 > (lens_end - lens_start) / 64,
        "{lens_packets} lens packets"
    );
    assert!(scene.traces_as_packet(&rays[start..start + 64]));
    assert!(scene.traces_as_packet(&rays[start + 64..start + 128]));

    let (closest, any) = batch_queries(&scene, &rays);
    let mut hits = 0;
    for (i, r) in rays.iter().enumerate() {
        let brute = spheres
            .iter()
            .filter_map(|s| s.intersect(r, r.tmax))
            .min_by(f64::total_cmp);
        assert_eq!(closest[i].map(|h| h.t), brute, "ray {i}: {r:?}");
        assert_eq!(closest[i], scene.closest_hit(r), "ray {i}: {r:?}");
        assert_eq!(any[i], brute.is_some(), "ray {i}: {r:?}");
        hits += usize::from(brute.is_some());
    }
    assert!(
        hits > 1000 && hits < rays.len() - 1000,
        "{hits} of {}",
        rays.len()
    );
    let parallel_hits = (start..start + 128).filter(|&i| any[i]).count();
    assert_eq!(parallel_hits, 64, "the rays meant to hit the last sphere");
}

#[test]
fn non_finite_rays_find_nothing_alone_or_in_batches_and_spoil_no_other_rays_answer() {
    // A NaN drops out of a packet's ranges of origin and direction, and a ray non-finite
    // on every axis has a NaN slab on each (`∞ − ∞`, `0 · ∞`): box bounds then admit
    // every slot of a node, empty ones too, whose reference leads back to the root. Six
    // spheres leave some of their tree's root's slots empty; three are few enough for a
    // single ray to test one by one, without their tree. The icosphere adds triangle
    // packets, and the torus a triangle tree with empty slots (a NaN ray went round it
    // until the stack overflowed: a lens focused closer than its origin's precision made
    // one).
    let sphere = |x: f64, y: f64, z: f64, radius: f64| Sphere {
        center: DVec3::new(x, y, z),
        radius,
    };
    let spheres = vec![
        sphere(-0.8, 0.0, 0.0, 0.5),
        sphere(0.8, 0.0, 0.0, 0.5),
        sphere(0.0, 0.9, 0.5, 0.4),
    ];
    let with_mesh = placed(
        &procedural::icosphere(2),
        DMat4::from_scale(DVec3::splat(0.6)),
    );
    let few_spheres = SceneGeometry {
        spheres: spheres.clone(),
        ..SceneGeometry::default()
    };
    let only_spheres = SceneGeometry {
        spheres: [-DVec3::Y, DVec3::Y]
            .into_iter()
            .flat_map(|shift| {
                (spheres.iter()).map(move |&s| Sphere {
                    center: s.center + shift,
                    ..s
                })
            })
            .collect(),
        ..SceneGeometry::default()
    };
    let six = Scene::build(&only_spheres);
    assert!(
        six.sphere_bvh().nodes()[0].children.contains(&0),
        "the six spheres' root has an empty slot"
    );
    let both = SceneGeometry {
        spheres,
        ..with_mesh.clone()
    };
    let gapped = placed(&procedural::torus(1.0, 0.3, 200, 100), DMat4::IDENTITY);
    let tree = Scene::build(&gapped).triangle_tree().clone();
    assert!(
        (tree.bvh().nodes().iter()).any(|node| node.children.contains(&0)),
        "the torus's tree has an empty slot (the root is no node's child)"
    );
    // Rays from one eye to an 8 × 8 grid across the scene: their directions share signs.
    let eye = DVec3::new(3.0, 2.5, -4.0);
    let good: Vec<Ray> = (0..64)
        .map(|k| {
            let grid = |i: usize| (i as f64 - 3.5) * 0.35;
            ray(eye, DVec3::new(grid(k % 8), grid(k / 8), 0.0))
        })
        .collect();
    let kernels: &[bool] = if has_avx2() { &[true, false] } else { &[false] };
    for (geometry, &simd) in [&few_spheres, &only_spheres, &with_mesh, &both, &gapped]
        .into_iter()
        .flat_map(|g| kernels.iter().map(move |simd| (g, simd)))
    {
        let mut scene = Scene::build(geometry);
        scene.set_grouping(Grouping::Packets);
        scene.set_simd(simd);
        assert!(!simd || scene.traces_as_packet(&good));
        for (case, spoil) in [
            (
                "origin.y",
                (|r: &mut Ray| r.origin.y = f64::NAN) as fn(&mut Ray),
            ),
            ("origin", |r: &mut Ray| r.origin = DVec3::NAN),
            ("direction.x", |r: &mut Ray| r.direction.x = f64::NAN),
            ("direction", |r: &mut Ray| r.direction = DVec3::NAN),
            ("tmin", |r: &mut Ray| r.tmin = f64::NAN),
            ("origin ∞", |r: &mut Ray| r.origin = DVec3::INFINITY),
            ("direction ∞", |r: &mut Ray| {
                r.direction = DVec3::NEG_INFINITY
            }),
            // Finite, but not in float32, in which triangles are traced.
            ("origin 1e39", |r: &mut Ray| r.origin = DVec3::splat(1e39)),
        ] {
            for spoiled in [vec![0], vec![37], (0..64).collect()] {
                let mut rays = good.clone();
                for &k in &spoiled {
                    spoil(&mut rays[k]);
                }
                assert!(!scene.traces_as_packet(&rays), "{case}");
                let (closest, any) = batch_queries(&scene, &rays);
                let mut hits = 0;
                for (k, r) in rays.iter().enumerate() {
                    if spoiled.contains(&k) {
                        assert_eq!((closest[k], any[k]), (None, false), "{case} {k}");
                    } else {
                        assert_eq!(closest[k], scene.closest_hit(r), "{case} {k}");
                        assert_eq!(any[k], scene.any_hit(r), "{case} {k}");
                        hits += usize::from(any[k]);
                    }
                }
                assert!(
                    spoiled.len() == 64 || hits > 0,
                    "{case}: the view sees nothing"
                );
            }
        }
    }
}

/// Camera rays (from `t = 0` on) rounded to float32 for the packet kernels.
#[cfg(target_arch = "x86_64")]
fn rounded_for_packets(rays: &[Ray]) -> Vec<raybatch::scene::TriangleRay> {
    rays.iter()
        .map(|r| raybatch::scene::TriangleRay {
            origin: r.origin.as_vec3().to_array(),
            direction: r.direction.as_vec3().to_array(),
            tmin: 0.0,
            tmax: f32::INFINITY,
        })
        .collect()
}

#[test]
#[cfg(target_arch = "x86_64")]
fn packets_over_a_mesh_finer_than_the_pixels_are_judged_wasteful() {
    // A packet tests inner nodes for all its rays at once, so when each of its rays meets
    // other small triangles it reaches many leaves that no ray enters; such packets are
    // judged wasteful, and the rays near them go one by one. The same mesh filling a
    // large image gives packets whose rays share leaves.
    if !has_avx2() {
        return;
    }
    let scene = Scene::build(&placed(&procedural::icosphere(6), DMat4::IDENTITY));
    let eye = DVec3::new(2.0, 1.2, 2.0);
    // Of the packets that reach any leaf, the share judged wasteful (of some 200 tiles).
    let wasteful_share = |size: u32| {
        let rays = tiled_camera_rays(eye, DVec3::ZERO, size);
        let step = (rays.len() / 64 / 200).max(1);
        let (mut reaching, mut wasteful) = (0, 0);
        for group in rays.chunks(64).step_by(step) {
            let prepared = rounded_for_packets(group);
            // SAFETY: AVX2 is present, and the default tree fits the packet's stack.
            let visits = unsafe {
                raybatch::packet::closest(
                    raybatch::packet::LeafLanes::Eight,
                    scene.triangle_bvh(),
                    scene.triangle_tree().blocks(),
                    &prepared,
                    |_, _, _| (),
                )
            };
            // Tiles whose rays differ in direction signs are not packets.
            let Some(visits) = visits else { continue };
            if visits.leaves > 0 {
                reaching += 1;
                wasteful += usize::from(visits.wasteful());
            }
        }
        assert!(reaching > 10, "{reaching} packets reached a leaf");
        wasteful as f64 / reaching as f64
    };
    // 82k triangles, a few pixels each at 1024², several per pixel at 128².
    let coarse = wasteful_share(128);
    let fine = wasteful_share(1024);
    assert!(coarse > 0.5, "{coarse}");
    assert!(fine < 0.02, "{fine}");
}

#[test]
#[cfg(target_arch = "x86_64")]
fn sphere_packets_wider_than_the_spheres_send_the_next_groups_one_by_one() {
    // The sphere packets are paced on their own evidence: a packet over spheres much
    // smaller than its rays are apart sends the next groups through the spheres one by
    // one, and leaves the triangle packets' pacing alone.
    use raybatch::packet::{PacedTree, worth_trying};
    if !has_avx2() {
        return;
    }
    let scene = Scene::build(&SceneGeometry {
        spheres: raybatch::bench::scattered_spheres(10_000),
        ..SceneGeometry::default()
    });
    let eye = DVec3::new(4.8, 7.2, 18.0);
    // Of the groups traced as sphere packets, the share after which packets pause.
    let paused_share = |size: u32| {
        let rays = tiled_camera_rays(eye, DVec3::ZERO, size);
        let mut out = [None; 64];
        let (mut packets, mut paused) = (0, 0);
        for group in rays.chunks(64).filter(|g| scene.traces_as_packet(g)) {
            // Let any pause run out, so that this group is a packet.
            while !worth_trying(PacedTree::Spheres) {}
            scene.closest_hits(group, &mut out);
            packets += 1;
            paused += usize::from(!worth_trying(PacedTree::Spheres));
            assert!(worth_trying(PacedTree::Triangles));
        }
        assert!(packets > 5, "{packets} packets");
        paused as f64 / packets as f64
    };
    // 10,000 spheres: many per packet's footprint at 32², a few rays per sphere at 1024².
    let coarse = paused_share(32);
    let fine = paused_share(1024);
    assert!(coarse > 0.5, "{coarse}");
    assert!(fine < 0.02, "{fine}");
}

#[test]
#[cfg(target_arch = "x86_64")]
fn packets_far_wider_than_the_leaves_give_up_and_their_rays_go_one_by_one() {
    // A packet's work grows with the leaves its bounds reach, which over a small view of a
    // detailed mesh or a dense field of spheres is thousands. A packet still wasteful at
    // `Visits::GIVE_UP_FROM` leaves stops there and reports no hit, and the batch queries
    // trace its rays another way: the hits are those of single rays. The packets of a
    // large view of the same scene never give up.
    use raybatch::packet::LeafLanes;
    if !has_avx2() {
        return;
    }
    let mut lanes = vec![LeafLanes::Eight];
    if raybatch::simd512::available() {
        lanes.push(LeafLanes::Sixteen);
    }
    let mut mesh = Scene::build(&placed(&procedural::icosphere(6), DMat4::IDENTITY));
    let mut spheres = Scene::build(&SceneGeometry {
        spheres: raybatch::bench::scattered_spheres(100_000),
        ..SceneGeometry::default()
    });
    let (mesh_eye, spheres_eye) = (DVec3::new(2.0, 1.2, 2.0), DVec3::new(8.0, 12.0, 30.0));
    // Narrow views filled by the scene, `size` pixels square.
    let view = |eye, size| tiled_lens_rays(eye, DVec3::ZERO, size, 0.3, 0.0, &mut Numbers(0));
    // What the packets of some 200 groups of each view visited, and whether each reported a
    // hit: the mesh's at each width, then the spheres'.
    let packets = |size: u32| {
        let (mut through_mesh, mut through_spheres) = (Vec::new(), Vec::new());
        let rays = view(mesh_eye, size);
        let step = (rays.len() / 64 / 200).max(1);
        for group in rays.chunks(64).step_by(step) {
            let prepared = rounded_for_packets(group);
            for &lanes in &lanes {
                let mut reported = false;
                // SAFETY: AVX2 (and AVX-512F for sixteen lanes) is present, and the
                // default tree fits the packet's stack.
                let visits = unsafe {
                    raybatch::packet::closest(
                        lanes,
                        mesh.triangle_bvh(),
                        mesh.triangle_tree().blocks(),
                        &prepared,
                        |_, _, _| reported = true,
                    )
                };
                // Groups whose rays differ in direction signs are not packets.
                through_mesh.extend(visits.map(|v| (v, reported)));
            }
        }
        let rays = view(spheres_eye, size);
        for group in rays.chunks(64).step_by(step) {
            let mut reported = false;
            // SAFETY: AVX2 is present, and the default tree fits the packet's stack.
            let visits = unsafe {
                raybatch::sphere_packet::closest(
                    spheres.sphere_bvh(),
                    spheres.spheres_in_tree_order(),
                    group,
                    &vec![f64::INFINITY; group.len()],
                    |_, _, _| reported = true,
                )
            };
            through_spheres.extend(visits.map(|v| (v, reported)));
        }
        (through_mesh, through_spheres)
    };
    let (small_mesh, small_spheres) = packets(16);
    assert!(small_mesh.len() >= 4 && !small_spheres.is_empty());
    for (visits, reported) in small_mesh.iter().chain(&small_spheres) {
        assert!(visits.hopeless() && !reported, "{visits:?}");
    }
    let (large_mesh, large_spheres) = packets(1024);
    assert!(large_mesh.len() > 100 && large_spheres.len() > 100);
    for (visits, _) in large_mesh.iter().chain(&large_spheres) {
        assert!(!visits.hopeless(), "{visits:?}");
    }
    for packets in [&large_mesh, &large_spheres] {
        let reporting = packets.iter().filter(|(_, reported)| *reported).count();
        assert!(
            reporting > packets.len() / 2,
            "{reporting} of {}",
            packets.len()
        );
    }
    // The batch queries, made to try every group as a packet, answer as single rays do.
    for (scene, eye) in [(&mut mesh, mesh_eye), (&mut spheres, spheres_eye)] {
        scene.set_grouping(Grouping::Packets);
        let rays = view(eye, 16);
        let (mut closest, mut any) = (vec![None; rays.len()], vec![false; rays.len()]);
        scene.closest_hits(&rays, &mut closest);
        scene.any_hits(&rays, &mut any);
        for (k, ray) in rays.iter().enumerate() {
            assert_eq!(closest[k], scene.closest_hit(ray), "ray {k}");
            assert_eq!(any[k], scene.any_hit(ray), "ray {k}");
        }
        assert!(any.iter().filter(|&&hit| hit).count() > rays.len() / 2);
    }
}

#[test]
fn batch_queries_agree_with_single_rays_in_scenes_of_every_primitive_kind() {
    // Spheres in front of, behind and cutting through a mesh, over a plane: a batch must
    // keep the analytic hit where it is nearer and the triangle where that is nearer.
    let mut geometry = placed(&procedural::icosphere(3), DMat4::IDENTITY);
    geometry.spheres = vec![
        Sphere {
            center: DVec3::new(0.5, 0.3, -1.2),
            radius: 0.4,
        },
        Sphere {
            center: DVec3::new(-0.6, -0.2, 0.0),
            radius: 0.6,
        },
        Sphere {
            center: DVec3::new(0.0, 0.0, 2.0),
            radius: 2.5,
        },
    ];
    geometry.planes = vec![raybatch::plane::Plane {
        point: DVec3::new(0.0, -0.9, 0.0),
        normal: DVec3::Y,
    }];
    let mut scene = Scene::build(&geometry);
    let eye = DVec3::new(0.2, 0.4, -4.0);
    let rays: Vec<Ray> = (0..64 * 64)
        .map(|i| {
            let (tile, k) = (i / 64, i % 64);
            let (x, y) = (tile % 8 * 8 + k % 8, tile / 8 * 8 + k / 8);
            let d = crate::util::default_camera_direction(x, y, 64, 64);
            ray(eye, eye + DVec3::from_array(d))
        })
        .collect();
    // Packets, and rays side by side through the triangles (as after wasteful packets),
    // which start no search for a ray already stopped nearer.
    for grouping in [Grouping::Paced, Grouping::SideBySide] {
        scene.set_grouping(grouping);
        let (closest, any) = batch_queries(&scene, &rays);
        let mut kinds = [0; 3];
        for (i, r) in rays.iter().enumerate() {
            assert_eq!(closest[i], scene.closest_hit(r), "{grouping:?}: ray {i}");
            assert_eq!(any[i], scene.any_hit(r), "{grouping:?}: ray {i}");
            if let Some(hit) = closest[i] {
                kinds[match hit.primitive {
                    raybatch::scene::Primitive::Plane(_) => 0,
                    raybatch::scene::Primitive::Sphere(_) => 1,
                    raybatch::scene::Primitive::Triangle { .. } => 2,
                }] += 1;
            }
        }
        assert!(kinds.iter().all(|&k| k > 50), "hits per kind: {kinds:?}");
    }
}

#[test]
fn the_nearest_of_spheres_in_a_row_is_found_however_few_or_many_they_are() {
    // Spheres one behind the other in any order, so that a search that kept the last hit
    // rather than the nearest, or stopped at the first, would be caught: from one sphere
    // (a tree of one leaf) to several leaves. The truth is the smallest `t` of every
    // sphere's own test.
    let mut state = 0x2545_f491_4f6c_dd1d_u64;
    let mut unit = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut overlapping = 0;
    for count in 1..=7 {
        let geometry = SceneGeometry {
            spheres: (0..count)
                .map(|_| Sphere {
                    center: DVec3::new(unit() - 0.5, unit() - 0.5, 3.0 + 8.0 * unit()),
                    radius: 0.5 + unit(),
                })
                .collect(),
            ..SceneGeometry::default()
        };
        let scene = Scene::build(&geometry);
        let rays: Vec<Ray> = (0..256)
            .map(|_| ray(DVec3::ZERO, DVec3::new(unit() - 0.5, unit() - 0.5, 4.0)))
            .collect();
        let (closest, any) = batch_queries(&scene, &rays);
        for (k, r) in rays.iter().enumerate() {
            let ts: Vec<f64> = geometry
                .spheres
                .iter()
                .filter_map(|s| s.intersect(r, r.tmax))
                .collect();
            overlapping += usize::from(ts.len() > 1);
            let nearest = ts.iter().copied().reduce(f64::min);
            for hit in [closest[k], scene.closest_hit(r)] {
                assert_eq!(hit.map(|h| h.t), nearest, "{count} spheres, ray {k}");
                if let Some(hit) = hit {
                    let raybatch::scene::Primitive::Sphere(id) = hit.primitive else {
                        panic!("not a sphere");
                    };
                    let own = geometry.spheres[id as usize].intersect(r, r.tmax);
                    assert_eq!(own, Some(hit.t), "{count} spheres, ray {k}: sphere {id}");
                }
            }
            assert_eq!(any[k], nearest.is_some(), "{count} spheres, ray {k}");
            assert_eq!(
                scene.any_hit(r),
                nearest.is_some(),
                "{count} spheres, ray {k}"
            );
        }
    }
    assert!(
        overlapping > 300,
        "rays through more than one sphere: {overlapping}"
    );
}

#[test]
fn batch_queries_over_a_mesh_keep_each_rays_own_interval() {
    // Camera rays share their interval, and a batch over triangles alone rounds it once
    // for a run of rays; rays whose intervals change within a batch, in runs and one by
    // one, must each keep their own: the front face, the back face past a `tmin`, or
    // nothing before a `tmax`.
    let mut scene = Scene::build(&placed(&procedural::icosphere(3), DMat4::IDENTITY));
    let eye = DVec3::new(0.2, 0.4, -4.0);
    let intervals = [
        (0.0, f64::INFINITY),
        (0.0, 3.2),
        (3.9, f64::INFINITY),
        (4.1, 4.7),
        (2.0, 2.0),
    ];
    let rays: Vec<Ray> = (0..64 * 64)
        .map(|i| {
            let (tile, k) = (i / 64, i % 64);
            let (x, y) = (tile % 8 * 8 + k % 8, tile / 8 * 8 + k / 8);
            let d = crate::util::default_camera_direction(x, y, 64, 64);
            // Runs of three rays per interval in even tiles, a new interval every ray in
            // odd ones.
            let which = if tile % 2 == 0 { k / 3 } else { k * 7 };
            let (tmin, tmax) = intervals[which as usize % intervals.len()];
            Ray {
                tmin,
                tmax,
                ..ray(eye, eye + DVec3::from_array(d))
            }
        })
        .collect();
    for grouping in [Grouping::Paced, Grouping::SideBySide] {
        scene.set_grouping(grouping);
        let (closest, any) = batch_queries(&scene, &rays);
        let (mut front, mut back) = (0, 0);
        for (i, r) in rays.iter().enumerate() {
            assert_eq!(closest[i], scene.closest_hit(r), "{grouping:?}: ray {i}");
            assert_eq!(any[i], scene.any_hit(r), "{grouping:?}: ray {i}");
            match closest[i] {
                Some(hit) if hit.t < 3.9 => front += 1,
                Some(_) => back += 1,
                None => {}
            }
        }
        // Both faces are found, so the intervals decided the answers.
        assert!(front > 30 && back > 30, "front {front}, back {back}");
    }
}

#[test]
fn rays_side_by_side_keep_their_own_intervals_when_a_slots_last_block_is_tested_first() {
    // Traced side by side, each slot of the rays in flight first tests the block that
    // stopped its last ray. Rays along one line through the unit icosphere (faces within
    // 0.01 of the unit sphere), whose front face lies at 3.02–3.03 and back face at
    // 5.01–5.03: after a ray that hits, the next ones in the slot end before the front
    // face or start past it and end before the back face, and must not be stopped by the
    // block that stopped it.
    if !has_avx2() {
        return;
    }
    let mut scene = Scene::build(&placed(&procedural::icosphere(3), DMat4::IDENTITY));
    scene.set_grouping(Grouping::SideBySide);
    let eye = DVec3::new(0.2, 0.4, -4.0);
    let intervals = [(0.0, f64::INFINITY), (0.0, 2.9), (3.1, 4.9), (4.95, 5.1)];
    let rays: Vec<Ray> = (0..256)
        .map(|k| {
            let (tmin, tmax) = intervals[k % intervals.len()];
            Ray {
                tmin,
                tmax,
                ..ray(eye, DVec3::ZERO)
            }
        })
        .collect();
    let (closest, any) = batch_queries(&scene, &rays);
    for (k, r) in rays.iter().enumerate() {
        let expected = matches!(k % intervals.len(), 0 | 3);
        assert_eq!(any[k], expected, "ray {k}: {r:?}");
        assert_eq!(closest[k].is_some(), expected, "ray {k}: {r:?}");
        assert_eq!(closest[k], scene.closest_hit(r), "ray {k}");
    }
}

#[test]
fn rays_through_shared_vertices_find_the_same_nearest_hit_in_any_visiting_order() {
    // A computed triangle distance can round a few ulps below its box's computed entry:
    // a search that has already found a hit must still enter such boxes, or it misses a
    // tied (or one ulp nearer) triangle depending on the order it visits them. Camera
    // rays through the vertices of a grid, at every scale, traced by every path (packets,
    // single AVX2 rays, scalar) must give exactly the brute-force answer.
    let cells = 32u32;
    for scale in [1e-4, 1e-2, 1.0, 1e3, 1e7] {
        let geometry = placed(
            &procedural::pixel_grid(cells),
            DMat4::from_scale(DVec3::splat(scale)),
        );
        let mut rays = Vec::new();
        for tile in 0..(cells / 8) * (cells / 8) {
            for i in 0..64 {
                let (x, y) = (
                    tile % (cells / 8) * 8 + i % 8,
                    tile / (cells / 8) * 8 + i / 8,
                );
                let d = crate::util::default_camera_direction(x, y, cells, cells);
                rays.push(ray(DVec3::ZERO, DVec3::from_array(d)));
            }
        }
        let mut scene = Scene::build(&geometry);
        let mut paths = Vec::new();
        if scene.uses_simd() {
            // Packets with leaves tested eight rays wide and, with AVX-512, sixteen.
            for (wide, name) in [(false, "packets of 8 lanes"), (true, "packets of 16 lanes")] {
                scene.set_wide_leaves(wide);
                if wide && !scene.uses_wide_leaves() {
                    continue;
                }
                let mut batch = vec![None; rays.len()];
                for (r, out) in rays.chunks(64).zip(batch.chunks_mut(64)) {
                    assert!(scene.traces_as_packet(r));
                    scene.closest_hits(r, out);
                }
                paths.push((name, batch));
            }
            paths.push(("avx2", rays.iter().map(|r| scene.closest_hit(r)).collect()));
        }
        scene.set_simd(false);
        paths.push((
            "scalar",
            rays.iter().map(|r| scene.closest_hit(r)).collect(),
        ));
        for (i, r) in rays.iter().enumerate() {
            let truth = brute_force(&geometry.triangles, r).expect("every ray hits the grid");
            let hit = paths[0].1[i].expect("a hit");
            assert_eq!(hit.t as f32, truth, "scale {scale:e}: {} {r:?}", paths[0].0);
            for (name, hits) in &paths[1..] {
                assert_eq!(hits[i], Some(hit), "scale {scale:e}: {name} {r:?}");
            }
        }
    }
}

#[test]
fn an_any_hit_hint_names_the_triangle_that_stopped_the_ray_and_never_changes_an_answer() {
    // A grid of triangles on z = 1 with nothing behind it. A ray from the origin through a
    // triangle's centroid hits that triangle alone, and the hint it leaves must name it.
    // The same line with an interval that excludes the grid, or turned around, must miss
    // although its hint points right at the triangle: a hint is only where to look first.
    // The next ray aims at the next triangle, so the hint's block, the subtree around it
    // and the whole tree each find hits; hints left by a larger scene (slots past this
    // scene's end) must change nothing either. Both the AVX2 and the scalar paths.
    let geometry = placed(&procedural::pixel_grid(16), DMat4::IDENTITY);
    let other = Scene::build(&placed(&procedural::icosphere(4), DMat4::IDENTITY));
    assert!(other.counts().triangles > 4 * geometry.triangles.len());
    let mut scene = Scene::build(&geometry);
    let mut checked = 0;
    for simd in [true, false] {
        scene.set_simd(simd);
        let mut hint = AnyHitHint::default();
        for (i, t) in geometry.triangles.iter().enumerate() {
            let centroid = (point(t[0]) + point(t[1]) + point(t[2])) / 3.0;
            let toward = ray(DVec3::ZERO, centroid);
            let distance = centroid.length();
            let mut foreign = AnyHitHint::default();
            let around = DVec3::new((i as f64).cos(), (i as f64).sin(), 0.3 * (i % 7) as f64);
            assert!(other.any_hit_hinted(&ray(DVec3::ZERO, around), &mut foreign));
            for start in [hint, foreign, AnyHitHint::default()] {
                let mut h = start;
                assert!(scene.any_hit_hinted(&toward, &mut h), "{i} simd {simd}");
                let slot = h.triangle_slot().expect("a triangle stopped the ray");
                assert_eq!(scene.triangle_id(slot) as usize, i, "{i} simd {simd}");
            }
            assert!(scene.any_hit_hinted(&toward, &mut hint));
            let misses = [
                Ray {
                    tmax: distance * 0.999,
                    ..toward
                },
                Ray {
                    tmin: distance * 1.001,
                    ..toward
                },
                Ray {
                    direction: -toward.direction,
                    ..toward
                },
            ];
            for r in misses {
                for start in [hint, foreign] {
                    let mut h = start;
                    assert!(!scene.any_hit_hinted(&r, &mut h), "{i} simd {simd}: {r:?}");
                    assert_eq!(h.triangle_slot(), None, "a miss leaves no hint");
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 3000, "{checked}");
}

/// The distance along `r` to the triangle `t` (its stored float32 vertices) by
/// Möller–Trumbore in float64, where it is hit.
fn distance_f64(t: &[[f32; 3]; 3], r: &Ray) -> Option<f64> {
    let [a, b, c] = t.map(point);
    let (e1, e2) = (b - a, c - a);
    let p = r.direction.cross(e2);
    let det = e1.dot(p);
    let s = r.origin - a;
    let (u, q) = (s.dot(p) / det, s.cross(e1));
    let v = r.direction.dot(q) / det;
    (u >= 0.0 && v >= 0.0 && u + v <= 1.0).then(|| e2.dot(q) / det)
}

/// Hits on slivers some 32,000 times longer than wide are at the distances float64
/// Möller–Trumbore finds (itself good to about 10⁻¹⁶ times that aspect), ray by ray and in
/// batches of every grouping, with AVX2 or without, with and without a sphere in the scene
/// (which bounds the triangle search). The float32 test's own distances on them are off
/// by far more, as asserted first.
#[test]
fn slivers_are_hit_at_the_distance_of_their_planes_on_every_path() {
    let wedge = procedural::sliver_wedge(2000, std::f64::consts::TAU / 200_000.0);
    let mut geometry = placed(&wedge, DMat4::IDENTITY);
    // Rays from below the wedge, every direction component positive (packets take them),
    // toward points well inside random slivers: each hits its sliver and no other.
    let mut numbers = Numbers(5);
    let eye = DVec3::new(-0.3, -0.4, -0.5);
    let (mut rays, mut truth, mut float32_errors) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..32 * 64 {
        let sliver = geometry.triangles[(numbers.next() * 2000.0) as usize];
        let [a, b, c] = sliver.map(point);
        let (u, v) = (numbers.range(0.2, 0.4), numbers.range(0.2, 0.4));
        let r = ray(eye, a + (b - a) * u + (c - a) * v);
        let t = distance_f64(&sliver, &r).expect("aimed inside");
        let sheared = ShearedRay::new(r.origin.as_vec3(), r.direction.as_vec3());
        let [v0, v1, v2] = sliver;
        let float32 = triangle::intersect(&sheared, v0, v1, v2, 0.0, f32::INFINITY).unwrap();
        float32_errors.push((f64::from(float32.t) - t).abs() / t);
        rays.push(r);
        truth.push(t);
    }
    float32_errors.sort_by(f64::total_cmp);
    let float32_p90 = float32_errors[float32_errors.len() * 9 / 10];
    assert!(
        float32_p90 > 1e-6,
        "the float32 test's p90 error {float32_p90:e}"
    );
    let check = |hits: &[Option<f64>], label: &str| {
        for ((r, t), got) in rays.iter().zip(&truth).zip(hits) {
            let got = got.unwrap_or_else(|| panic!("{label}: {r:?} missed"));
            assert!(
                (got - t).abs() <= 1e-10 * t,
                "{label}: {got} for {t}, {r:?}"
            );
        }
    };
    for with_sphere in [false, true] {
        if with_sphere {
            geometry.spheres.push(Sphere {
                center: DVec3::new(5.0, 5.0, 5.0),
                radius: 0.5,
            });
        }
        let mut scene = Scene::build(&geometry);
        assert!(scene.triangle_tree().has_thin());
        for simd in [false, true] {
            scene.set_simd(simd);
            let one_by_one: Vec<_> = rays
                .iter()
                .map(|r| scene.closest_hit(r).map(|h| h.t))
                .collect();
            check(
                &one_by_one,
                &format!("sphere {with_sphere}, simd {simd}, one by one"),
            );
            for grouping in [Grouping::Paced, Grouping::Packets, Grouping::SideBySide] {
                scene.set_grouping(grouping);
                let (hits, _) = batch_queries(&scene, &rays);
                let hits: Vec<_> = hits.iter().map(|h| h.map(|h| h.t)).collect();
                check(
                    &hits,
                    &format!("sphere {with_sphere}, simd {simd}, {grouping:?}"),
                );
            }
        }
    }
}
