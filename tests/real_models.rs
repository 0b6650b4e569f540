//! Real data, outside the repository: the scanned and CAD models of `../shared/models`
//! (set `RAYBATCH_MODELS` to that folder) and Debian's `assimp-testmodels` glTF files (set
//! `RAYBATCH_GLTF`, e.g. to /usr/share/assimp/models/glTF2) and the OBJ files beside them.
//! Ignored by default so `cargo test` passes on a fresh clone; `.ci/run` runs them with
//! `--include-ignored`.

use std::path::{Path, PathBuf};

use glam::DVec3;
use raybatch::bvh::BuildPreset;
use raybatch::mesh::MeshCache;
use raybatch::{Manifest, Ray, Scene, SceneGeometry};

use crate::util::{Dir, folder};

/// The files under `root`, in every folder below it, whose extension is one of
/// `extensions` (lower case; the files' may be in any case), sorted.
fn files_with(root: &Path, extensions: &[&str]) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if path
                .extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| extensions.contains(&e.to_ascii_lowercase().as_str()))
            {
                found.push(path);
            }
        }
    }
    found.sort();
    found
}

/// The geometry of a manifest holding the mesh file `model` and nothing else.
fn scene_of(model: &Path) -> SceneGeometry {
    let dir = Dir::new();
    dir.write(
        "m.json",
        format!(
            r#"{{"image": {{"width": 8, "height": 8}}, "meshes": [{{"file": {:?}}}]}}"#,
            model.display().to_string()
        ),
    );
    let manifest = Manifest::load(&dir.join("m.json")).unwrap();
    SceneGeometry::load(&manifest, &mut MeshCache::new()).unwrap()
}

#[test]
#[ignore = "needs RAYBATCH_MODELS (the scanned models of ../shared/models)"]
fn scanned_models_trace_exactly_like_brute_force() {
    let models = files_with(&folder("RAYBATCH_MODELS"), &["obj"]);
    assert!(models.len() >= 5, "{models:?}");
    for model in models {
        let geometry = scene_of(&model);
        let triangles = geometry.triangles.clone();
        let scene = Scene::build(&geometry);
        let (lo, hi) = triangles.iter().flatten().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), v| {
                let p = DVec3::from_array(v.map(f64::from));
                (lo.min(p), hi.max(p))
            },
        );
        let (centre, radius) = ((lo + hi) / 2.0, (hi - lo).length() / 2.0);
        let (mut hits, count) = (0usize, 400u32);
        for i in 0..count {
            // From a sphere around the model toward points inside its box; some rays start
            // inside the model's box.
            let a = f64::from(i) * 2.399963;
            let z = 1.0 - 2.0 * (f64::from(i) + 0.5) / f64::from(count);
            let s = (1.0 - z * z).sqrt();
            let around = DVec3::new(s * a.cos(), z, s * a.sin());
            let start = if i % 5 == 0 { 0.2 } else { 1.6 };
            let origin = centre + around * radius * start;
            let target = lo
                + (hi - lo)
                    * DVec3::new(
                        (a * 1.7).sin().abs(),
                        (a * 0.3).cos().abs(),
                        (a * 2.9).sin().abs(),
                    );
            let r = Ray {
                origin,
                direction: (target - origin).normalize(),
                tmin: 0.0,
                tmax: f64::INFINITY,
            };
            let best = crate::robustness::brute_force(&triangles, &r);
            let got = scene.closest_hit(&r).map(|h| h.t as f32);
            assert_eq!(got, best, "{}: ray {i}", model.display());
            assert_eq!(
                scene.any_hit(&r),
                best.is_some(),
                "{}: ray {i}",
                model.display()
            );
            hits += usize::from(best.is_some());
        }
        assert!(
            hits > count as usize / 4,
            "{}: only {hits} hits",
            model.display()
        );
    }
}

#[test]
#[ignore = "needs RAYBATCH_MODELS (the scanned models of ../shared/models)"]
fn scanned_models_get_obvhs_own_binary_tree_from_our_radius_1_passes() {
    // Our radius-1 PLOC passes pair up long runs of nodes that no mutual choice merged,
    // where obvhs' merge one pair a pass; no pass over a scan has such a run, so the
    // tree must be obvhs' own, node for node, for both presets that search radius 1.
    let models = files_with(&folder("RAYBATCH_MODELS"), &["obj"]);
    assert!(models.len() >= 5, "{models:?}");
    let fields = |bvh: &obvhs::bvh2::Bvh2| -> Vec<_> {
        (bvh.nodes.iter())
            .map(|n| {
                let b = n.aabb();
                let bits = |v: glam::Vec3A| v.to_array().map(f32::to_bits);
                (bits(b.min), bits(b.max), n.prim_count, n.first_index)
            })
            .collect()
    };
    for model in models {
        let boxes: Vec<obvhs::aabb::Aabb> = (scene_of(&model).triangles.iter())
            .map(|t| {
                let [a, b, c] = t.map(glam::Vec3A::from);
                obvhs::aabb::Aabb::new(a.min(b).min(c), a.max(b).max(c))
            })
            .collect();
        // Our passes take the leaves in `raybatch::morton`'s order, which differs from
        // obvhs' where Morton codes are equal (its sort is unstable); obvhs is given the
        // boxes in that order, which its sort keeps.
        let leaves: Vec<_> = (boxes.iter().zip(0..))
            .map(|(b, i)| obvhs::bvh2::node::Bvh2Node::new(*b, 1, i))
            .collect();
        let total = boxes
            .iter()
            .fold(obvhs::aabb::Aabb::empty(), |all, b| all.union(b));
        let order: Vec<u32> = (raybatch::morton::sorted_leaves(&leaves, total).iter())
            .map(|leaf| leaf.first_index)
            .collect();
        let sorted_boxes: Vec<_> = order.iter().map(|&i| boxes[i as usize]).collect();
        for preset in [BuildPreset::Fastest, BuildPreset::VeryFast] {
            let params = preset.params(4);
            let ours = raybatch::bvh::binary_tree(boxes.len(), |i| boxes[i], &params);
            let theirs = obvhs::ploc::PlocBuilder::new().build(
                params.ploc_search_distance,
                &sorted_boxes,
                order.clone(),
                params.sort_precision,
                params.search_depth_threshold,
            );
            assert!(
                fields(&ours) == fields(&theirs),
                "{}, {preset:?}: the trees differ",
                model.display()
            );
            // A leaf names its primitive; obvhs keeps the list of indices it was given.
            assert!(
                ours.primitive_indices
                    .iter()
                    .copied()
                    .eq(0..boxes.len() as u32)
            );
            assert_eq!(theirs.primitive_indices, order);
        }
    }
}

#[test]
#[ignore = "needs RAYBATCH_MODELS (the scanned models of ../shared/models)"]
fn scanned_models_render_as_a_batch_with_shared_loads() {
    let models = files_with(&folder("RAYBATCH_MODELS"), &["obj"]);
    let dir = Dir::new();
    for (i, model) in models.iter().enumerate() {
        for integrator in ["hit", "depth", "normal"] {
            dir.write(
                &format!("jobs/{i:02}-{integrator}.json"),
                format!(
                    r#"{{"image": {{"width": 64, "height": 48}}, "output": "{i:02}-{integrator}.pfm",
                        "camera": {{"look_from": [0, 0.5, 3], "look_at": [0, 0, 0]}},
                        "integrator": {{"type": "{integrator}"}},
                        "meshes": [{{"file": {:?}}}]}}"#,
                    model.display().to_string()
                ),
            );
        }
    }
    let run = dir.raybatch(&["render", "jobs", "--out", "out", "--stats", "stats.jsonl"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    assert_eq!(
        dir.files().iter().filter(|f| f.starts_with("out/")).count(),
        models.len() * 3
    );
}

#[test]
#[ignore = "needs RAYBATCH_MODELS (the scanned models of ../shared/models)"]
fn scanned_models_read_fast_exactly_as_tobj_reads_them() {
    let models = files_with(&folder("RAYBATCH_MODELS"), &["obj"]);
    assert_most_read_fast_as_tobj_reads_them(&models, 5);
}

#[test]
#[ignore = "needs RAYBATCH_GLTF (Debian's assimp-testmodels glTF2 folder)"]
fn obj_files_beside_the_debian_gltf_folder_read_fast_exactly_as_tobj_reads_them() {
    // assimp's own OBJ tests: long lines, no final line end, runs of spaces, points,
    // lines, vertex colours, other number forms, UTF-16 and malformed files.
    let files = files_with(&folder("RAYBATCH_GLTF").join("../OBJ"), &["obj"]);
    assert_most_read_fast_as_tobj_reads_them(&files, 15);
}

/// Reads each of `files` (at least `at_least` of them) with the fast reader and with
/// `tobj`: where the fast reader takes a file, `tobj` must read it and give the same
/// mesh; and the fast reader must take more than half of them (real files are what it
/// is for).
fn assert_most_read_fast_as_tobj_reads_them(files: &[PathBuf], at_least: usize) {
    assert!(files.len() >= at_least, "{files:?}");
    let mut fast = 0;
    for file in files {
        let bytes = std::fs::read(file).unwrap();
        if let Some(mesh) = raybatch::obj::fast::parse(&bytes) {
            let reference = raybatch::obj::parse_with_tobj(&bytes, file);
            let reference = reference.unwrap_or_else(|e| panic!("{}: {e}", file.display()));
            assert!(mesh == reference, "{} differs from tobj", file.display());
            fast += 1;
        }
    }
    assert!(
        fast * 2 > files.len(),
        "only {fast} of {} read fast",
        files.len()
    );
}

#[test]
#[ignore = "needs RAYBATCH_GLTF (Debian's assimp-testmodels glTF2 folder)"]
fn every_debian_gltf_file_loads_or_is_refused_cleanly() {
    let files = files_with(&folder("RAYBATCH_GLTF"), &["gltf", "glb"]);
    assert!(files.len() >= 20, "{}", files.len());
    let dir = Dir::new();
    for (i, file) in files.iter().enumerate() {
        dir.write(
            &format!("jobs/{i:03}.json"),
            format!(
                r#"{{"image": {{"width": 16, "height": 16}}, "output": "{i:03}.ppm",
                    "camera": {{"look_from": [2, 2, 4], "look_at": [0, 0, 0]}},
                    "integrator": {{"type": "normal"}}, "meshes": [{{"file": {:?}}}]}}"#,
                file.display().to_string()
            ),
        );
    }
    let run = dir.raybatch(&["render", "jobs", "--out", "out"]);
    // Some of these files are broken on purpose: a job may fail, the process may not.
    assert!(run.status == 0 || run.status == 1, "{}", run.stderr);
    let failed = run.error_lines();
    let rendered = dir.files().iter().filter(|f| f.starts_with("out/")).count();
    assert_eq!(failed.len() + rendered, files.len(), "{}", run.stderr);
    assert!(
        rendered > files.len() / 2,
        "only {rendered} of {} rendered",
        files.len()
    );
    for line in failed {
        assert!(line.contains("meshes[0].file"), "{line}");
    }
}
