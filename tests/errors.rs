//! Refusals: every bad manifest or mesh is reported on one line naming the manifest, the
//! place and the cause; nothing partial is written; the rest of the batch renders; exit
//! statuses are 0, 1 and 2.

use crate::util::Dir;

const IMAGE: &str = r#""image": {"width": 4, "height": 3}"#;

/// (manifest file name, contents, fragments its error line must contain).
fn bad_manifests() -> Vec<(&'static str, String, Vec<&'static str>)> {
    let m = |body: &str| format!("{{{IMAGE}, {body}}}");
    vec![
        (
            "syntax.json",
            format!("{{{IMAGE},}}"),
            vec!["line 1, column", "trailing comma"],
        ),
        ("empty.json", String::new(), vec!["line 1, column 0", "EOF"]),
        // Cut off where a key should come: the place is the last key that was read.
        (
            "cut-off.json",
            r#"{"image": {"width": 4,"#.to_string(),
            vec!["line 1, column", ": image: EOF"],
        ),
        (
            "cut-off-sphere.json",
            format!(r#"{{{IMAGE}, "spheres": [{{"center": [0, 0, 3], "#),
            vec![": spheres[0]: EOF"],
        ),
        (
            "trailing-text.json",
            format!("{{{IMAGE}}} {{}}"),
            vec!["line 1, column", "trailing characters"],
        ),
        (
            "array.json",
            "[1, 2]".to_string(),
            vec!["line 1", "expected a JSON object"],
        ),
        // serde would read an array as a struct's fields in order; objects must be objects.
        (
            "image-array.json",
            r#"{"image": [4, 3]}"#.to_string(),
            vec!["image", "expected a JSON object"],
        ),
        (
            "sphere-array.json",
            m(r#""spheres": [[[0, 0, 3], 1, null]]"#),
            vec!["spheres[0]", "expected a JSON object"],
        ),
        (
            "integrator-array.json",
            m(r#""integrator": ["depth", 2]"#),
            vec!["integrator", "expected a JSON object"],
        ),
        (
            "rotate-array.json",
            m(r#""meshes": [{"file": "m.obj", "transform": {"rotate": [[0, 1, 0], 30]}}]"#),
            vec!["meshes[0].transform.rotate", "expected a JSON object"],
        ),
        (
            "material-array.json",
            m(r#""materials": {"red": [[1, 0, 0], null]}"#),
            vec!["materials.red", "expected a JSON object"],
        ),
        (
            "unknown-key.json",
            m(r#""sphere": []"#),
            vec!["unknown field `sphere`", "line 1"],
        ),
        (
            "nested-key.json",
            m(r#""spheres": [{"center": [0, 0, 3], "radus": 1}]"#),
            vec!["spheres[0]", "unknown field `radus`"],
        ),
        (
            "negative-radius.json",
            m(
                r#""spheres": [{"center": [0, 0, 3], "radius": 1}, {"center": [0, 0, 3], "radius": -2}]"#,
            ),
            vec!["spheres[1].radius", "greater than 0", "-2"],
        ),
        (
            "wrong-type.json",
            m(r#""spheres": [{"center": [0, 0, 3], "radius": "1"}]"#),
            vec!["spheres[0].radius", "invalid type"],
        ),
        (
            "short-vector.json",
            m(r#""spheres": [{"center": [0, 3], "radius": 1}]"#),
            vec!["spheres[0].center", "invalid length 2"],
        ),
        // serde's own arrays called a longer one "trailing characters".
        (
            "long-vector.json",
            m(r#""spheres": [{"center": [0, 0, 3, 1], "radius": 1}]"#),
            vec!["spheres[0].center: invalid length 4, expected an array of 3 numbers"],
        ),
        (
            "long-matrix.json",
            m(
                r#""meshes": [{"file": "t.obj", "transform": {"matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]}}]"#,
            ),
            vec!["meshes[0].transform.matrix: invalid length 17"],
        ),
        // In objects named by their "type" the failing field is named too.
        (
            "sampler-spp-type.json",
            m(r#""sampler": {"type": "stratified", "spp": -4}"#),
            vec!["sampler.spp: invalid value: integer `-4`"],
        ),
        (
            "light-short-vector.json",
            m(r#""lights": [{"type": "point", "position": [0, 3], "intensity": [1, 1, 1]}]"#),
            vec!["lights[0].position: invalid length 2"],
        ),
        (
            "albedo-item.json",
            m(r#""materials": {"red": {"albedo": [1, "0", 0], "type": "diffuse"}}"#),
            vec!["materials.red.albedo[1]: invalid type: string"],
        ),
        (
            "light-missing.json",
            m(r#""lights": [{"type": "directional", "direction": [0, -1, 0]}]"#),
            vec!["lights[0]: missing field `irradiance`"],
        ),
        (
            "sampler-type.json",
            m(r#""sampler": {"spp": 4, "type": "halton"}"#),
            vec!["sampler.type: unknown variant `halton`"],
        ),
        (
            "integrator-type-number.json",
            m(r#""integrator": {"type": 2}"#),
            vec!["integrator.type: expected a string, got 2"],
        ),
        (
            "integrator-no-type.json",
            m(r#""integrator": {"scale": 2}"#),
            vec!["integrator: missing field `type`"],
        ),
        (
            "integrator-two-types.json",
            m(r#""integrator": {"type": "hit", "type": "depth"}"#),
            vec!["integrator: duplicate field `type`"],
        ),
        (
            "huge-number.json",
            m(r#""spheres": [{"center": [0, 0, 1e999], "radius": 1}]"#),
            vec!["number out of range", "line 1"],
        ),
        (
            "out-of-range.json",
            m(r#""spheres": [{"center": [0, 0, 1e300], "radius": 1}]"#),
            vec!["spheres[0].center[2]", "1e300 is out of range"],
        ),
        (
            "tiny-radius.json",
            m(r#""spheres": [{"center": [0, 0, 3], "radius": -1e-30}]"#),
            vec!["spheres[0].radius", "got -1e-30"],
        ),
        (
            "zero-width.json",
            r#"{"image": {"width": 0, "height": 3}}"#.to_string(),
            vec!["image.width", "between 1 and"],
        ),
        (
            "no-image.json",
            "{}".to_string(),
            vec!["missing field `image`"],
        ),
        (
            "duplicate.json",
            format!("{{{IMAGE}, {IMAGE}}}"),
            vec!["duplicate field `image`"],
        ),
        (
            "version.json",
            m(r#""version": 2"#),
            vec!["version", "unsupported version 2"],
        ),
        ("tmin.json", m(r#""tmin": -1"#), vec!["tmin", "at least 0"]),
        (
            "tmax.json",
            m(r#""tmin": 5, "tmax": 2"#),
            vec!["tmax", "greater than tmin"],
        ),
        (
            "background.json",
            m(r#""background": [0, -1, 0]"#),
            vec!["background[1]", "negative"],
        ),
        (
            "output-ext.json",
            m(r#""output": "image.png""#),
            vec!["output", ".ppm or .pfm"],
        ),
        (
            "ppm-style.json",
            m(r#""ppm": "ascii""#),
            vec!["ppm", "unknown variant `ascii`"],
        ),
        (
            "integrator.json",
            m(r#""integrator": {"type": "toon"}"#),
            vec!["integrator.type: unknown variant `toon`"],
        ),
        (
            "integrator-key.json",
            m(r#""integrator": {"type": "depth", "scael": 2}"#),
            vec!["integrator.scael: unknown field `scael`"],
        ),
        (
            "depth-scale.json",
            m(r#""integrator": {"type": "depth", "scale": 0}"#),
            vec!["integrator.scale"],
        ),
        (
            "center-spp.json",
            m(r#""sampler": {"type": "center", "spp": 4}"#),
            vec!["sampler.spp", "exactly 1"],
        ),
        (
            "spp-zero.json",
            m(r#""sampler": {"type": "independent", "spp": 0}"#),
            vec!["sampler.spp"],
        ),
        (
            "camera-mixed.json",
            m(r#""camera": {"look_from": [0, 0, 5], "look_at": [0, 0, 0], "origin": [1, 0, 0]}"#),
            vec!["camera.origin", "look_from/look_at"],
        ),
        (
            "camera-half.json",
            m(r#""camera": {"look_from": [0, 0, 5]}"#),
            vec!["camera.look_at", "required"],
        ),
        (
            "camera-vfov.json",
            m(r#""camera": {"look_from": [0, 0, 5], "look_at": [0, 0, 0], "vfov": 180}"#),
            vec!["camera.vfov", "between 0 and 180"],
        ),
        (
            "camera-up.json",
            m(r#""camera": {"look_from": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 0, 2]}"#),
            vec!["camera.up", "parallel"],
        ),
        (
            "camera-basis.json",
            m(r#""camera": {"right": [1, 0, 0], "up": [2, 0, 0]}"#),
            vec!["camera", "linearly independent"],
        ),
        (
            "camera-lens.json",
            m(r#""camera": {"aperture": 0.1}"#),
            vec!["camera.focus_distance", "required"],
        ),
        (
            "camera-aperture.json",
            m(r#""camera": {"aperture": 1e20, "focus_distance": 1}"#),
            vec!["camera.aperture", "1e20 is out of range"],
        ),
        (
            "camera-focus.json",
            m(r#""camera": {"aperture": 0.1, "focus_distance": 1e20}"#),
            vec!["camera.focus_distance", "1e20 is out of range"],
        ),
        (
            "material-name.json",
            m(
                r#""materials": {"red": {"type": "diffuse", "albedo": [1, 0, 0]}},
                 "spheres": [{"center": [0, 0, 3], "radius": 1, "material": "gold"}]"#,
            ),
            vec!["spheres[0].material", "unknown material `gold`", "red"],
        ),
        (
            "albedo.json",
            m(r#""materials": {"red": {"type": "diffuse", "albedo": [1.5, 0, 0]}}"#),
            vec!["materials.red.albedo[0]", "[0, 1]"],
        ),
        (
            "material-type.json",
            m(r#""materials": {"x": {"type": "metal", "albedo": [1, 0, 0]}}"#),
            vec!["materials", "unknown variant `metal`"],
        ),
        (
            "plane-normal.json",
            m(r#""planes": [{"point": [0, 0, 0], "normal": [0, 0, 0]}]"#),
            vec!["planes[0].normal", "zero"],
        ),
        (
            "light.json",
            m(r#""lights": [{"type": "point", "position": [0, 0, 0], "intensity": [1, -1, 1]}]"#),
            vec!["lights[0].intensity[1]", "negative"],
        ),
        (
            "mesh-ext.json",
            m(r#""meshes": [{"file": "bunny.stl"}]"#),
            vec!["meshes[0].file", "unsupported mesh format"],
        ),
        (
            "matrix-row.json",
            m(
                r#""meshes": [{"file": "t.obj", "transform": {"matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,1,1]}}]"#,
            ),
            vec!["meshes[0].transform.matrix", "bottom row"],
        ),
        (
            "matrix-and-scale.json",
            m(
                r#""meshes": [{"file": "t.obj", "transform": {"matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "scale": 2}}]"#,
            ),
            vec!["meshes[0].transform", "not both"],
        ),
        (
            "rotate-axis.json",
            m(
                r#""meshes": [{"file": "t.obj", "transform": {"rotate": {"axis": [0, 0, 0], "degrees": 10}}}]"#,
            ),
            vec!["meshes[0].transform.rotate.axis", "zero"],
        ),
        (
            "scale-shape.json",
            m(r#""meshes": [{"file": "t.obj", "transform": {"scale": [1, 2]}}]"#),
            vec!["meshes[0].transform.scale", "three numbers"],
        ),
        (
            "not-yet.json",
            m(r#""integrator": {"type": "path"}"#),
            vec!["integrator.type", "`path`", "not implemented"],
        ),
    ]
}

#[test]
fn every_bad_manifest_is_refused_on_one_line_with_its_place_and_cause() {
    let dir = Dir::new();
    dir.write("jobs/t.obj", "v 0 0 3\nv 1 0 3\nv 0 1 3\nf 1 2 3\n");
    dir.write("jobs/good.json", format!("{{{IMAGE}}}"));
    let cases = bad_manifests();
    for (name, text, _) in &cases {
        dir.write(&format!("jobs/{name}"), text);
    }
    let run = dir.raybatch(&["render", "jobs"]);
    assert_eq!(run.status, 1);
    let lines = run.error_lines();
    assert_eq!(
        lines.len(),
        cases.len(),
        "one line per failed job:\n{}",
        run.stderr
    );
    for (name, _, fragments) in &cases {
        let line = lines
            .iter()
            .find(|l| l.contains(&format!("jobs/{name}:")))
            .unwrap_or_else(|| panic!("no error line for {name}:\n{}", run.stderr));
        for fragment in fragments {
            assert!(
                line.contains(fragment),
                "{name}: `{fragment}` not in: {line}"
            );
        }
    }
    // The good job rendered; no failed job left any file.
    let mut expected: Vec<String> = cases.iter().map(|(n, _, _)| format!("jobs/{n}")).collect();
    expected.extend(["jobs/good.json", "jobs/good.ppm", "jobs/t.obj"].map(String::from));
    expected.sort();
    assert_eq!(dir.files(), expected);
}

#[test]
fn bad_mesh_files_are_refused_with_the_file_and_place() {
    let dir = Dir::new();
    let cases: Vec<(&str, &[u8], Vec<&str>)> = vec![
        ("vertex.obj", b"v 0 0 0\nv 1 oops 0\nv 0 1 0\nf 1 2 3\n", vec!["vertex.obj: line 2", "three numbers"]),
        ("face.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", vec!["face.obj: line 4", "does not exist"]),
        ("corner.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf //1 2 3\n", vec!["corner.obj: line 5", "does not exist"]),
        ("zero.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", vec!["zero.obj: line 4"]),
        ("nan.obj", b"v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", vec!["nan.obj", "vertex 2 is not finite"]),
        // A relative index far before the first texture coordinate: tobj multiplies it
        // unchecked (a panic in debug builds unless its overflow checks are off).
        (
            "relative.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/-2147483648 2/1 3/1\n",
            vec!["relative.obj: line 5", "does not exist"],
        ),
        ("binary.obj", b"v 0 0 0\n\xff\xfe\n", vec!["binary.obj: line 2", "UTF-8"]),
        ("text.gltf", b"this is not json", vec!["text.gltf"]),
        ("empty.glb", b"", vec!["empty.glb", "the file is empty"]),
        ("truncated.glb", b"glTF\x02\x00\x00\x00", vec!["truncated.glb"]),
        // A header whose length is shorter than the header: the gltf crate subtracts
        // without checking (a panic in debug builds).
        (
            "short.glb",
            b"glTF\x02\x00\x00\x00\x04\x00\x00\x00",
            vec!["short.glb", "GLB header", "length 4"],
        ),
        (
            "index.gltf",
            br#"{"asset": {"version": "2.0"},
                "buffers": [{"byteLength": 8, "uri": "data:application/octet-stream;base64,AAAAAAAAAAA="}],
                "bufferViews": [{"buffer": 0, "byteLength": 8}],
                "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0,0,0], "max": [0,0,0]}],
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
                "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]}"#,
            vec!["index.gltf", "accessors[0]", "reach past"],
        ),
        // gltf-json's validation indexed the accessors by POSITION unchecked (a panic).
        (
            "position.gltf",
            br#"{"asset": {"version": "2.0"},
                "accessors": [],
                "meshes": [{"primitives": [{"attributes": {"POSITION": 2}}]}],
                "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]}"#,
            vec!["position.gltf", "meshes[0].primitives[0]", "accessor 2 does not exist"],
        ),
        (
            "missing-bin.gltf",
            br#"{"asset": {"version": "2.0"}, "buffers": [{"byteLength": 36, "uri": "nowhere.bin"}]}"#,
            vec!["missing-bin.gltf", "buffers[0]", "nowhere.bin"],
        ),
        // glTF 1.0 has maps where 2.0 has arrays; the version is the cause to name.
        (
            "old.gltf",
            br#"{"asset": {"version": "1.0"}, "meshes": {"box": {"primitives": []}}}"#,
            vec!["old.gltf", "asset.version", "glTF 1.0", "only glTF 2.0"],
        ),
        (
            "old-number.gltf",
            br#"{"asset": {"version": 1}, "meshes": {"box": {"primitives": []}}}"#,
            vec!["old-number.gltf", "asset.version", "glTF 1;"],
        ),
        (
            "old.glb",
            b"glTF\x01\x00\x00\x00\x0c\x00\x00\x00",
            vec!["old.glb", "container version 1", "only glTF 2.0"],
        ),
        // A major version this reader does not know, in a document it could parse.
        (
            "future.gltf",
            br#"{"asset": {"version": "3.0"}}"#,
            vec!["future.gltf", "asset.version", "glTF 3.0"],
        ),
        (
            "cycle.gltf",
            br#"{"asset": {"version": "2.0"}, "nodes": [{"children": [1]}, {"children": [0]}],
                "scenes": [{"nodes": [0]}]}"#,
            vec!["cycle.gltf", "cycle"],
        ),
    ];
    for (file, bytes, _) in &cases {
        dir.write(file, bytes);
        let stem = file.replace('.', "-");
        dir.write(
            &format!("{stem}.json"),
            format!(r#"{{{IMAGE}, "meshes": [{{"file": "{file}"}}]}}"#),
        );
    }
    dir.write(
        "missing.json",
        format!(r#"{{{IMAGE}, "meshes": [{{"file": "absent.obj"}}]}}"#),
    );
    dir.write(
        "far.json",
        format!(r#"{{{IMAGE}, "meshes": [{{"file": "ok.obj", "transform": {{"scale": 1e15}}}}]}}"#),
    );
    dir.write("ok.obj", "v 0 0 3\nv 1 0 3\nv 0 1 3\nf 1 2 3\n");
    let run = dir.raybatch(&["render", "."]);
    assert_eq!(run.status, 1);
    let lines = run.error_lines();
    assert_eq!(lines.len(), cases.len() + 2, "{}", run.stderr);
    for (file, _, fragments) in &cases {
        let stem = file.replace('.', "-");
        let line = lines
            .iter()
            .find(|l| l.contains(&format!("{stem}.json:")))
            .unwrap_or_else(|| panic!("no line for {file}:\n{}", run.stderr));
        assert!(line.contains("meshes[0].file"), "{line}");
        for fragment in fragments {
            assert!(
                line.contains(fragment),
                "{file}: `{fragment}` not in: {line}"
            );
        }
    }
    let missing = lines.iter().find(|l| l.contains("missing.json")).unwrap();
    assert!(
        missing.contains("meshes[0].file") && missing.contains("absent.obj"),
        "{missing}"
    );
    let far = lines.iter().find(|l| l.contains("far.json")).unwrap();
    // The first vertex out of range, in the file's order, is the one named.
    assert!(
        far.contains("out of range") && far.contains("vertex [0, 0, 3] lands at [0, 0, 3e15]"),
        "{far}"
    );
    assert!(
        dir.files().iter().all(|f| !f.ends_with(".ppm")),
        "{:?}",
        dir.files()
    );
}

#[test]
fn a_failed_write_leaves_no_partial_or_temporary_file() {
    let dir = Dir::new();
    std::fs::create_dir_all(dir.join("taken.ppm")).unwrap();
    dir.write("taken.json", format!("{{{IMAGE}}}"));
    let run = dir.raybatch(&["render", "taken.json"]);
    assert_eq!(run.status, 1);
    assert!(
        run.stderr.contains("taken.json") && run.stderr.contains("cannot write"),
        "{}",
        run.stderr
    );
    assert_eq!(dir.files(), ["taken.json"], "no temporary file left");
}

#[test]
fn two_jobs_never_write_the_same_file() {
    let dir = Dir::new();
    dir.write("a/scene.json", format!("{{{IMAGE}}}"));
    dir.write(
        "b/scene.json",
        format!(r#"{{{IMAGE}, "background": [1, 1, 1]}}"#),
    );
    let run = dir.raybatch(&["render", "a", "b", "--out", "out"]);
    assert_eq!(run.status, 1);
    let lines = run.error_lines();
    assert_eq!(lines.len(), 1, "{}", run.stderr);
    assert!(
        lines[0].contains("b/scene.json") && lines[0].contains("also written by"),
        "{}",
        lines[0]
    );
    // The first job's image survives.
    assert_eq!(
        crate::util::ppm(&dir.read("out/scene.ppm")).at(0, 0),
        [0, 0, 0]
    );
    // The same manifest named twice is rendered once.
    let twice = dir.raybatch(&["render", "a", "a/scene.json"]);
    assert_eq!(twice.status, 0, "{}", twice.stderr);
}

#[test]
#[cfg(unix)]
fn a_dangling_link_in_a_folder_is_a_failed_job_and_a_folder_named_json_is_no_job() {
    let dir = Dir::new();
    dir.write("jobs/good.json", format!("{{{IMAGE}}}"));
    std::os::unix::fs::symlink("nowhere.json", dir.join("jobs/gone.json")).unwrap();
    std::fs::create_dir_all(dir.join("jobs/folder.json")).unwrap();
    let run = dir.raybatch(&["render", "jobs"]);
    assert_eq!(run.status, 1);
    let lines = run.error_lines();
    assert_eq!(lines.len(), 1, "{}", run.stderr);
    assert!(lines[0].contains("jobs/gone.json"), "{}", lines[0]);
    assert!(dir.exists("jobs/good.ppm"));
}

#[test]
fn a_stats_file_in_the_folder_being_rendered_is_not_a_manifest() {
    // Rendered twice: the second run finds the first's stats file in the folder, under
    // another name for the same file.
    let dir = Dir::new();
    dir.write("jobs/good.json", format!("{{{IMAGE}}}"));
    for stats in ["jobs/stats.json", "jobs/../jobs/stats.json"] {
        let run = dir.raybatch(&["render", "jobs", "--stats", stats]);
        assert_eq!(run.status, 0, "{}", run.stderr);
        let text = String::from_utf8(dir.read("jobs/stats.json")).unwrap();
        assert_eq!(text.lines().count(), 1, "{text}");
        assert!(text.contains("good.json"), "{text}");
    }
}

#[test]
fn exit_statuses_are_0_1_and_2() {
    let dir = Dir::new();
    dir.write("good.json", format!("{{{IMAGE}}}"));
    assert_eq!(dir.raybatch(&["render", "good.json"]).status, 0);
    assert_eq!(
        dir.raybatch(&["render", "good.json", "absent.json"]).status,
        1
    );
    std::fs::create_dir_all(dir.join("empty")).unwrap();
    let empty = dir.raybatch(&["render", "empty"]);
    assert_eq!(empty.status, 1);
    assert!(empty.stderr.contains("no *.json"), "{}", empty.stderr);
    for args in [
        vec!["render"],
        vec!["render", "good.json", "--threads", "0"],
        vec!["render", "good.json", "--threads", "many"],
        vec!["render", "good.json", "--frobnicate"],
        vec!["paint", "good.json"],
        vec!["render", "good.json", "--stats", "empty"],
        vec!["render", "good.json", "--backend", "ospray"],
        vec!["bench", "--quick", "--models", "absent"],
        vec!["bench", "--quick", "--only", "no-such-scene"],
        vec!["verify", "good.json", "--passes", "0"],
        #[cfg(not(feature = "embree"))]
        vec!["render", "good.json", "--backend", "embree"],
        #[cfg(not(feature = "embree"))]
        vec!["verify", "good.json"],
    ] {
        let run = dir.raybatch(&args);
        assert_eq!(run.status, 2, "{args:?}: {}", run.stderr);
        assert!(!run.stderr.is_empty());
    }
    // A scanned model missing from `--models` is named; with nothing else to measure,
    // the bench is refused rather than printing empty tables.
    let run = dir.raybatch(&["bench", "--quick", "--models", "empty", "--only", "bunny"]);
    assert_eq!(run.status, 2, "{}", run.stderr);
    assert!(
        run.stderr.contains("stanford-bunny.obj not found")
            && run.stderr.contains("nothing to measure")
            && !run.stderr.contains("ogre"),
        "{}",
        run.stderr
    );
}
