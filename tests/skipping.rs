//! What a job does not do because its scene does not need it: no mesh read or triangle
//! tree without meshes, no sphere tree without spheres, no closest-hit search or normals
//! for `hit`, no ray traced in a tile whose rays all pass outside the scene's box, a mesh
//! shared by a batch read and built once, the last job's meshes let go before its build,
//! no reinsertion in a triangle tree that too few rays will cross. (glTF images never
//! being decoded is `meshes::glb_external_and_sparse_buffers_and_unread_images`.)

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};

use glam::DVec3;
use raybatch::bvh::BuildPreset;
use raybatch::job::{Batch, JobOptions};
use raybatch::mesh::MeshCache;
use raybatch::scene::{Extent, Hit, SceneCounts, Tracer};
use raybatch::{Manifest, Ray, Scene, SceneGeometry};

use crate::util::Dir;

const TETRAHEDRON: &str =
    "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";

fn scene_of(dir: &Dir, json: &str) -> (Manifest, Scene) {
    let path = dir.write("scene.json", json);
    let manifest = Manifest::load(&path).unwrap();
    let geometry = SceneGeometry::load(&manifest, &mut MeshCache::new()).unwrap();
    let scene = Scene::build(&geometry);
    (manifest, scene)
}

#[test]
fn a_scene_without_meshes_builds_no_triangle_tree_and_one_without_spheres_no_sphere_tree() {
    let dir = Dir::new();
    dir.write("tetra.obj", TETRAHEDRON);
    let (_, spheres_only) = scene_of(
        &dir,
        r#"{"image": {"width": 4, "height": 4},
            "spheres": [{"center": [0, 0, 5], "radius": 1}, {"center": [2, 0, 5], "radius": 1}]}"#,
    );
    assert!(spheres_only.triangle_bvh().is_empty());
    assert_eq!(spheres_only.triangle_tree().memory_bytes(), 0);
    assert!(!spheres_only.sphere_bvh().is_empty());

    let (_, mesh_only) = scene_of(
        &dir,
        r#"{"image": {"width": 4, "height": 4}, "meshes": [{"file": "tetra.obj"}]}"#,
    );
    assert!(mesh_only.sphere_bvh().is_empty());
    let counts = mesh_only.counts();
    assert_eq!((counts.triangles, counts.spheres), (4, 0));
    // Everything the scene holds is the triangles' tree.
    assert_eq!(counts.accel_bytes, mesh_only.triangle_tree().memory_bytes());
}

/// A tracer that counts what the render loop asks of the scene it wraps: rays asked
/// about in batches, rays asked about one by one, normals.
struct Counting<'a> {
    scene: &'a Scene,
    closest: AtomicUsize,
    any: AtomicUsize,
    single: AtomicUsize,
    normals: AtomicUsize,
    /// Whether the render loop is told what the scene holds ([`Tracer::extent`]).
    bounded: bool,
}

impl<'a> Counting<'a> {
    fn new(scene: &'a Scene, bounded: bool) -> Counting<'a> {
        Counting {
            scene,
            closest: AtomicUsize::new(0),
            any: AtomicUsize::new(0),
            single: AtomicUsize::new(0),
            normals: AtomicUsize::new(0),
            bounded,
        }
    }

    /// Rays asked about, in batches or one by one.
    fn rays(&self) -> usize {
        [&self.closest, &self.any, &self.single]
            .iter()
            .map(|count| count.load(Relaxed))
            .sum()
    }
}

impl Tracer for Counting<'_> {
    fn closest_hit(&self, ray: &Ray) -> Option<Hit> {
        self.single.fetch_add(1, Relaxed);
        self.scene.closest_hit(ray)
    }
    fn any_hit(&self, ray: &Ray) -> bool {
        self.single.fetch_add(1, Relaxed);
        self.scene.any_hit(ray)
    }
    fn closest_hits(&self, rays: &[Ray], out: &mut [Option<Hit>]) {
        self.closest.fetch_add(rays.len(), Relaxed);
        self.scene.closest_hits(rays, out)
    }
    fn any_hits(&self, rays: &[Ray], out: &mut [bool]) {
        self.any.fetch_add(rays.len(), Relaxed);
        self.scene.any_hits(rays, out)
    }
    fn normal(&self, ray: &Ray, hit: &Hit) -> DVec3 {
        self.normals.fetch_add(1, Relaxed);
        Tracer::normal(self.scene, ray, hit)
    }
    fn triangle_id(&self, slot: u32) -> u32 {
        self.scene.triangle_id(slot)
    }
    fn counts(&self) -> SceneCounts {
        self.scene.counts()
    }
    fn extent(&self) -> Option<&Extent> {
        self.bounded.then(|| self.scene.extent()).flatten()
    }
}

#[test]
fn hit_asks_only_whether_anything_is_hit_all_ask_in_batches_and_only_normal_computes_normals() {
    let dir = Dir::new();
    dir.write("tetra.obj", TETRAHEDRON);
    let base = r#""image": {"width": 16, "height": 12}, "sampler": {"type": "stratified", "spp": 2},
        "spheres": [{"center": [0, 0, 5], "radius": 1}],
        "meshes": [{"file": "tetra.obj", "transform": {"translate": [1, 0, 4]}}]"#;
    let rays = 16 * 12 * 2;
    for (integrator, closest, any, normals) in [
        ("hit", 0, rays, false),
        ("depth", rays, 0, false),
        ("normal", rays, 0, true),
    ] {
        let (manifest, scene) = scene_of(
            &dir,
            &format!(r#"{{{base}, "integrator": {{"type": "{integrator}"}}}}"#),
        );
        // Told no box, so every tile is traced.
        let counting = Counting::new(&scene, false);
        raybatch::render::render(&counting, &manifest, &|_| {}).unwrap();
        assert_eq!(counting.closest.into_inner(), closest, "{integrator}");
        assert_eq!(counting.any.into_inner(), any, "{integrator}");
        // Every camera ray is asked about in batches, which the tracer traces as packets.
        assert_eq!(counting.single.into_inner(), 0, "{integrator}");
        assert_eq!(counting.normals.into_inner() > 0, normals, "{integrator}");
    }
}

/// Renders `json` through its scene told what it holds ([`Tracer::extent`]) and told
/// nothing; asserts the same bytes both ways and returns how many rays each traced.
fn rays_traced_with_and_without_extent(dir: &Dir, json: &str) -> (usize, usize) {
    let (manifest, scene) = scene_of(dir, json);
    let bounded = Counting::new(&scene, true);
    let image = raybatch::render::render(&bounded, &manifest, &|_| {}).unwrap();
    let everything = Counting::new(&scene, false);
    let reference = raybatch::render::render(&everything, &manifest, &|_| {}).unwrap();
    assert!(image.to_bytes() == reference.to_bytes(), "{json}");
    (bounded.rays(), everything.rays())
}

#[test]
fn tiles_whose_rays_all_pass_outside_the_scene_are_not_traced() {
    let dir = Dir::new();
    dir.write("tetra.obj", TETRAHEDRON);
    let (width, height) = (64, 48);
    let pixels = width * height;
    let sphere = r#""spheres": [{"center": [0, 0, 5], "radius": 0.5}]"#;
    let cases: [(String, &dyn Fn(usize) -> bool); 3] = [
        // The objects cover about a twentieth of the image; the tiles around them, a fifth.
        (
            format!(
                r#"{sphere}, "meshes": [{{"file": "tetra.obj", "transform": {{"translate": [0.5, 0, 4]}}}}]"#
            ),
            &|traced| traced > 0 && traced * 4 < pixels,
        ),
        // The rays of the upper half leave a floor below behind, and but for the tiles
        // round the sphere are not traced.
        (
            format!(r#"{sphere}, "planes": [{{"point": [0, -100, 0], "normal": [0, 1, 0]}}]"#),
            &|traced| traced * 2 > pixels && traced * 8 < 7 * pixels,
        ),
        // Every ray meets a wall ahead.
        (
            format!(r#"{sphere}, "planes": [{{"point": [0, 0, 100], "normal": [0, 0, -1]}}]"#),
            &|traced| traced == pixels,
        ),
    ];
    // The same through a lens focused on the sphere, four samples a pixel: the same
    // bounds hold on the pixels traced.
    let lens = r#""camera": {"aperture": 0.05, "focus_distance": 5},
                  "sampler": {"type": "stratified", "spp": 4},"#;
    for (camera, spp) in [("", 1), (lens, 4)] {
        for integrator in ["hit", "depth", "normal"] {
            for (objects, expected) in &cases {
                let json = format!(
                    r#"{{"image": {{"width": {width}, "height": {height}}}, {camera}
                        "integrator": {{"type": "{integrator}"}}, {objects}}}"#
                );
                let (traced, all) = rays_traced_with_and_without_extent(&dir, &json);
                assert_eq!(all, pixels * spp, "{json}");
                assert!(expected(traced / spp), "{traced} of {all} rays: {json}");
            }
        }
    }
}

/// Untraced tiles change no pixel: random views of a mesh and spheres, half of them over a
/// floor, at scales from a thousandth to a thousand and ten thousand units from the
/// origin, partly outside the image, through every integrator and sampler, with a lens
/// and without, render the same bytes whether or not the render loop is told what the
/// scene holds. Most views have tiles of both kinds (through a lens, over a third).
#[test]
fn untraced_tiles_give_the_bytes_traced_ones_give() {
    let dir = Dir::new();
    let mesh = raybatch::procedural::to_obj(&raybatch::procedural::icosphere(2), "");
    dir.write("ball.obj", mesh);
    let integrators = ["hit", "depth", "normal"];
    let samplers = [
        r#"{"type": "center"}"#,
        r#"{"type": "stratified", "spp": 3, "seed": 4}"#,
        r#"{"type": "independent", "spp": 2, "seed": 9}"#,
    ];
    // SplitMix64, for numbers that are the same on every run.
    let mut state = 0xb0c5_1de5_u64;
    let mut uniform = |low: f64, high: f64| {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        low + (high - low) * ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    // Views with tiles of both kinds, without a lens and with one.
    let mut mixed = [0; 2];
    // Every scale, distance, sampler, integrator and lens with every other.
    let cases = 3 * 2 * 3 * 3 * 2;
    for case in 0..cases {
        let scale = [1e-3, 1.0, 1e3][case % 3];
        let offset = [0.0, 1e4][case / 3 % 2] * scale;
        let place = |x: f64| offset + x * scale;
        let at = [0.0, 0.0, 0.0].map(|_| place(uniform(-1.5, 1.5)));
        let from = [0.0, 0.0, 0.0].map(|_| place(uniform(-6.0, 6.0)));
        let vfov = uniform(20.0, 100.0);
        // Half the views through a lens, focused near the objects or away from them.
        let with_lens = case / 54 % 2 == 1;
        let lens = if with_lens {
            let to = (0..3)
                .map(|k| (at[k] - from[k]).powi(2))
                .sum::<f64>()
                .sqrt();
            let aperture = uniform(0.01, 0.3) * scale;
            let focus = to * uniform(0.3, 2.0);
            format!(r#", "aperture": {aperture}, "focus_distance": {focus}"#)
        } else {
            String::new()
        };
        let spheres = (0..2)
            .map(|_| {
                let c = [0.0, 0.0, 0.0].map(|_| place(uniform(-2.0, 2.0)));
                let r = uniform(0.05, 0.5) * scale;
                format!(
                    r#"{{"center": [{}, {}, {}], "radius": {r}}}"#,
                    c[0], c[1], c[2]
                )
            })
            .collect::<Vec<_>>()
            .join(", ");
        // Half the views have a floor under the objects, tilted a little.
        let floor = place(-1.5);
        let planes = if case % 2 == 1 {
            format!(r#"{{"point": [0, {floor}, 0], "normal": [0.1, 1, 0.05]}}"#)
        } else {
            String::new()
        };
        let json = format!(
            r#"{{"image": {{"width": 45, "height": 31}},
                "camera": {{"look_from": [{}, {}, {}], "look_at": [{}, {}, {}], "vfov": {vfov}{lens}}},
                "integrator": {{"type": "{}"}}, "sampler": {},
                "spheres": [{spheres}], "planes": [{planes}],
                "meshes": [{{"file": "ball.obj",
                             "transform": {{"scale": {scale}, "translate": [{offset}, {offset}, {offset}]}}}}]}}"#,
            from[0],
            from[1],
            from[2],
            at[0],
            at[1],
            at[2],
            integrators[case / 18 % 3],
            samplers[case / 6 % 3],
        );
        let (traced, all) = rays_traced_with_and_without_extent(&dir, &json);
        mixed[usize::from(with_lens)] += usize::from(traced > 0 && traced < all);
    }
    let [pinhole, lens] = mixed;
    assert!(
        pinhole * 4 > cases && lens * 6 > cases,
        "{mixed:?} of {cases} views with tiles of both kinds"
    );
}

fn manifest(mesh: &str, translate: f64, camera_x: f64, output: &str) -> String {
    format!(
        r#"{{"image": {{"width": 24, "height": 16}}, "integrator": {{"type": "depth"}},
            "camera": {{"origin": [{camera_x}, 0.3, -3]}},
            "meshes": [{{"file": "{mesh}", "transform": {{"translate": [{translate}, 0, 2]}}}}],
            "output": "{output}"}}"#
    )
}

#[test]
fn the_last_job_lets_its_meshes_go_and_what_runs_after_it_reads_them_again() {
    let dir = Dir::new();
    dir.write("tetra.obj", TETRAHEDRON);
    let a = dir.write("a.json", manifest("tetra.obj", 0.0, 0.0, "a.pfm"));
    let b = dir.write("b.json", manifest("tetra.obj", 0.0, 0.5, "b.pfm"));
    let spheres = dir.write(
        "spheres.json",
        r#"{"image": {"width": 24, "height": 16}, "integrator": {"type": "depth"},
            "spheres": [{"center": [0, 0, 5], "radius": 1}], "output": "spheres.pfm"}"#,
    );
    // Each alone, as references.
    let alone = Dir::new();
    alone.write("tetra.obj", TETRAHEDRON);
    for (name, path) in [("a", &a), ("b", &b), ("spheres", &spheres)] {
        let copy = alone.write(
            &format!("{name}.json"),
            std::fs::read_to_string(path).unwrap(),
        );
        assert!(Batch::new(JobOptions::default()).run(&copy, &|_| {}).ok());
    }

    let mut batch = Batch::new(JobOptions::default());
    let report = batch.run_last(&a, &|_| {});
    assert!(report.ok(), "{:?}", report.error);
    assert!(batch.meshes().is_empty(), "the mesh is let go");
    // Jobs after a last one still work: a meshless job gets no triangles from it, and a
    // mesh job reads its mesh again and builds its own tree.
    assert!(!run(&mut batch, &spheres));
    assert!(!run(&mut batch, &b));
    assert_eq!(batch.meshes().len(), 1);
    assert_eq!(batch.triangle_tree_builds(), 2);
    for name in ["a.pfm", "b.pfm", "spheres.pfm"] {
        assert_eq!(dir.read(name), alone.read(name), "{name}");
    }
}

fn run(batch: &mut Batch, path: &Path) -> bool {
    let report = batch.run(path, &|_| {});
    assert!(report.ok(), "{:?}", report.error);
    report.triangle_tree_reused
}

#[test]
fn a_mesh_shared_by_a_batch_is_read_once_and_its_tree_built_once_while_placed_alike() {
    let dir = Dir::new();
    dir.write("tetra.obj", TETRAHEDRON);
    let jobs = [
        // (name, translate, camera x, reuses the previous job's tree)
        ("a", 0.0, 0.0, false),
        ("b", 0.0, 0.5, true), // same placement, another camera
        ("c", 0.0, -0.5, true),
        ("d", 0.25, 0.0, false), // moved: other triangles
        ("e", 0.0, 0.0, false),  // back again, but only the last tree is kept
    ];
    let mut batch = Batch::new(JobOptions::default());
    for (name, translate, camera_x, reused) in jobs {
        let path = dir.write(
            &format!("{name}.json"),
            manifest("tetra.obj", translate, camera_x, &format!("{name}.pfm")),
        );
        assert_eq!(run(&mut batch, &path), reused, "job {name}");
    }
    assert_eq!(batch.meshes().len(), 1);
    assert_eq!(batch.triangle_tree_builds(), 3);

    // A job that reused a tree renders what it renders alone.
    let alone = Dir::new();
    alone.write("tetra.obj", TETRAHEDRON);
    let path = alone.write("b.json", manifest("tetra.obj", 0.0, 0.5, "b.pfm"));
    assert!(!run(&mut Batch::new(JobOptions::default()), &path));
    assert_eq!(alone.read("b.pfm"), dir.read("b.pfm"));

    // A meshless job in between keeps the tree; a changed file is read and built again.
    let mut batch = Batch::new(JobOptions::default());
    let a = dir.join("a.json");
    assert!(!run(&mut batch, &a));
    let spheres = dir.write(
        "spheres.json",
        r#"{"image": {"width": 4, "height": 4}, "spheres": [{"center": [0, 0, 5], "radius": 1}],
            "output": "spheres.ppm"}"#,
    );
    assert!(!run(&mut batch, &spheres));
    assert!(run(&mut batch, &dir.join("b.json")));
    dir.write("tetra.obj", format!("{TETRAHEDRON}# a longer file\n"));
    assert!(!run(&mut batch, &dir.join("c.json")));
    assert_eq!(batch.triangle_tree_builds(), 2);
}

#[test]
fn a_job_builds_its_triangle_tree_with_reinsertion_only_from_64_rays_per_triangle() {
    // A torus of 400 triangles: 160x160 camera rays are exactly 64 per triangle, one
    // column fewer falls short. A second job reuses the first's tree, and its preset.
    let dir = Dir::new();
    let torus = raybatch::procedural::torus(1.0, 0.35, 20, 10);
    assert_eq!(torus.triangles.len(), 400);
    dir.write("torus.obj", raybatch::procedural::to_obj(&torus, ""));
    let job = |name: &str, width: u32, spp: u32| {
        dir.write(
            &format!("{name}.json"),
            format!(
                r#"{{"image": {{"width": {width}, "height": 160}}, "integrator": {{"type": "normal"}},
                    "sampler": {{"type": "stratified", "spp": {spp}}},
                    "camera": {{"look_from": [0.5, 2, 3], "look_at": [0, 0, 0], "vfov": 50}},
                    "meshes": [{{"file": "torus.obj"}}], "output": "{name}.pfm"}}"#
            ),
        )
    };
    let mut batch = Batch::new(JobOptions::default());
    for (name, width, spp, preset, reused) in [
        ("enough", 160, 1, "very fast", false),
        ("reused", 1, 1, "very fast", true),
        ("short", 159, 1, "fastest", false),
        ("sampled", 40, 4, "very fast", false),
    ] {
        if !reused {
            batch = Batch::new(JobOptions::default());
        }
        let report = batch.run(&job(name, width, spp), &|_| {});
        assert!(report.ok(), "{name}: {:?}", report.error);
        assert_eq!(report.triangle_tree_preset, Some(preset), "{name}");
        assert_eq!(report.triangle_tree_reused, reused, "{name}");
        let stats = report.to_json();
        assert_eq!(stats["triangle_tree_preset"], preset, "{name}");
    }

    // The image does not depend on the tree: the default tree renders the same bytes,
    // although reinsertion reordered the triangles.
    let manifest = Manifest::load(&dir.join("enough.json")).unwrap();
    let geometry = SceneGeometry::load(&manifest, &mut MeshCache::new()).unwrap();
    let [reinserted, default] = [BuildPreset::VeryFast, BuildPreset::default()]
        .map(|preset| Scene::build_with(&geometry, preset));
    let order = |scene: &Scene| -> Vec<u32> {
        scene
            .triangle_tree()
            .blocks()
            .iter()
            .flat_map(|b| b.ids)
            .collect()
    };
    assert_ne!(order(&reinserted), order(&default), "the trees must differ");
    let [a, b] = [&reinserted, &default]
        .map(|scene| raybatch::render::render(scene, &manifest, &|_| {}).unwrap());
    assert!(a == b, "the images differ");
    assert_eq!(dir.read("enough.pfm"), {
        let path = dir.join("default.pfm");
        b.write(&path).unwrap();
        std::fs::read(&path).unwrap()
    });
}
