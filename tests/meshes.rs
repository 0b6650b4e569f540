//! Mesh files written by the tests: OBJ polygons and groups; glTF node hierarchies, scene
//! selection, strips and fans, skipped points and lines, positions without bounds, GLB,
//! external and sparse buffers.

use base64::Engine;
use raybatch::mesh::MeshCache;
use raybatch::{Manifest, SceneGeometry};
use serde_json::{Value, json};

use crate::util::{Dir, Pfm, assert_close};

/// Bytes for a glTF buffer, and the bufferViews/accessors describing them.
#[derive(Default)]
struct Buffer {
    bytes: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Buffer {
    /// Adds float VEC3 positions; returns the accessor index.
    fn positions(&mut self, points: &[[f32; 3]]) -> usize {
        let offset = self.bytes.len();
        for p in points {
            for c in p {
                self.bytes.extend_from_slice(&c.to_le_bytes());
            }
        }
        let lo = [0, 1, 2].map(|k| points.iter().map(|p| p[k]).fold(f32::INFINITY, f32::min));
        let hi = [0, 1, 2].map(|k| {
            points
                .iter()
                .map(|p| p[k])
                .fold(f32::NEG_INFINITY, f32::max)
        });
        self.view(offset, None);
        self.accessor(json!({"componentType": 5126, "count": points.len(), "type": "VEC3", "min": lo, "max": hi}))
    }

    /// Adds u16 indices; returns the accessor index.
    fn indices(&mut self, indices: &[u16]) -> usize {
        let offset = self.bytes.len();
        for i in indices {
            self.bytes.extend_from_slice(&i.to_le_bytes());
        }
        self.view(offset, None);
        self.accessor(json!({"componentType": 5123, "count": indices.len(), "type": "SCALAR"}))
    }

    fn view(&mut self, offset: usize, stride: Option<usize>) {
        let mut view =
            json!({"buffer": 0, "byteOffset": offset, "byteLength": self.bytes.len() - offset});
        if let Some(stride) = stride {
            view["byteStride"] = json!(stride);
        }
        self.views.push(view);
        while !self.bytes.len().is_multiple_of(4) {
            self.bytes.push(0);
        }
    }

    fn accessor(&mut self, mut accessor: Value) -> usize {
        if accessor.get("bufferView").is_none() {
            accessor["bufferView"] = json!(self.views.len() - 1);
        }
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    /// The glTF document: `rest` supplies meshes, nodes, scenes; the buffer is embedded.
    fn document(&self, mut rest: Value) -> Value {
        let uri = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&self.bytes)
        );
        rest["asset"] = json!({"version": "2.0"});
        rest["buffers"] = json!([{"byteLength": self.bytes.len(), "uri": uri}]);
        rest["bufferViews"] = json!(self.views);
        rest["accessors"] = json!(self.accessors);
        rest
    }
}

/// A unit right triangle in the xy plane: covers the centre ray when placed on the axis
/// with a small offset.
const TRIANGLE: [[f32; 3]; 3] = [[-0.5, -0.5, 0.0], [1.0, -0.5, 0.0], [-0.5, 1.0, 0.0]];

/// Depth (PFM) of a 9 × 9 default-camera render of `mesh_file`.
fn depth_of(dir: &Dir, mesh_file: &str) -> Pfm {
    let json = format!(
        r#"{{"image": {{"width": 9, "height": 9}}, "output": "d.pfm",
            "integrator": {{"type": "depth"}}, "meshes": [{{"file": "{mesh_file}"}}]}}"#
    );
    dir.pfm_of("d.json", &json, "d.pfm")
}

#[test]
fn node_transforms_compose_from_the_root_down() {
    // root: translate z=5, scale 2; child: translate z=1 (in the root's frame: z = 5 + 2),
    // grandchild: rotate 180° about x (flips the triangle), carrying the mesh.
    let mut buffer = Buffer::default();
    let positions = buffer.positions(&TRIANGLE);
    let document = buffer.document(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": positions}}]}],
        "nodes": [
            {"translation": [0, 0, 5], "scale": [2, 2, 2], "children": [1]},
            {"translation": [0, 0, 1], "children": [2]},
            {"rotation": [1, 0, 0, 0], "mesh": 0}
        ],
        "scenes": [{"nodes": [0]}],
        "scene": 0
    }));
    let dir = Dir::new();
    dir.write("tree.gltf", document.to_string());
    assert_close(depth_of(&dir, "tree.gltf").at(4, 4)[0], 7.0);
}

#[test]
fn node_matrices_are_column_major_and_rotations_turn_counter_clockwise() {
    // glTF 2.0: a node's `matrix` is column-major (the translation in elements 12–14), and
    // its `rotation` a unit quaternion [x, y, z, w]: a quarter turn about +z takes +x to +y.
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let mut buffer = Buffer::default();
    let positions = buffer.positions(&TRIANGLE);
    let document = buffer.document(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": positions}}]}],
        "nodes": [
            {"matrix": [1, 0, 0, 0,  0, 1, 0, 0,  0, 0, 1, 0,  0.5, 0, 6, 1], "mesh": 0},
            {"rotation": [0, 0, h, h], "translation": [0, 0, 9], "mesh": 0}
        ],
        "scenes": [{"nodes": [0, 1]}]
    }));
    let dir = Dir::new();
    dir.write("nodes.gltf", document.to_string());
    dir.write(
        "nodes.json",
        r#"{"image": {"width": 1, "height": 1}, "meshes": [{"file": "nodes.gltf"}]}"#,
    );
    let manifest = Manifest::load(&dir.join("nodes.json")).unwrap();
    let geometry = SceneGeometry::load(&manifest, &mut MeshCache::new()).unwrap();
    let moved = TRIANGLE.map(|[x, y, z]| [x + 0.5, y, z + 6.0]);
    let turned = TRIANGLE.map(|[x, y, z]| [-y, x, z + 9.0]);
    assert_eq!(geometry.triangles.len(), 2);
    for (got, expected) in geometry.triangles.iter().zip([moved, turned]) {
        for (g, e) in got.iter().flatten().zip(expected.iter().flatten()) {
            assert!((g - e).abs() < 1e-6, "{got:?} against {expected:?}");
        }
    }
}

#[test]
fn the_default_scene_is_read_else_scene_0_else_every_root() {
    let mut buffer = Buffer::default();
    let positions = buffer.positions(&TRIANGLE);
    let base = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": positions}}]}],
        "nodes": [
            {"translation": [0, 0, 9], "mesh": 0},
            {"translation": [0, 0, 3], "mesh": 0},
            {"translation": [0, 0, 1], "mesh": 0, "children": [3]},
            {"translation": [0, 0, 1], "mesh": 0}
        ]
    });
    let dir = Dir::new();
    let cases = [
        (
            json!({"scenes": [{"nodes": [1]}, {"nodes": [0]}], "scene": 1}),
            9.0,
        ),
        (json!({"scenes": [{"nodes": [0]}, {"nodes": [1]}]}), 9.0),
        // No scenes: nodes 0, 1 and 2 are roots (3 is a child of 2, at z = 2).
        (json!({}), 1.0),
    ];
    for (scenes, expected) in cases {
        let mut document = base.clone();
        for (k, v) in scenes.as_object().unwrap() {
            document[k] = v.clone();
        }
        dir.write("s.gltf", buffer.document(document).to_string());
        assert_close(depth_of(&dir, "s.gltf").at(4, 4)[0], expected);
    }
    let stats = dir.raybatch(&["render", "d.json", "--stats", "stats.json"]);
    assert_eq!(stats.status, 0);
    let line: Value = serde_json::from_slice(&dir.read("stats.json")).unwrap();
    assert_eq!(line["triangles"], 4, "every root and its children");
}

#[test]
fn strips_and_fans_follow_the_gltf_vertex_order() {
    // Strip over a unit square at z = 2: p0 = (v0, v1, v2), p1 = (v1, v3, v2), both facing
    // +z. A fan around v0: p_i = (v_{i+1}, v_{i+2}, v0), also facing +z.
    let square = [
        [-1.0, -1.0, 2.0],
        [1.0, -1.0, 2.0],
        [-1.0, 1.0, 2.0],
        [1.0, 1.0, 2.0],
    ];
    let fan = [
        [0.0, 0.0, 2.0],
        [1.0, -1.0, 2.0],
        [1.0, 1.0, 2.0],
        [-1.0, 1.0, 2.0],
        [-1.0, -1.0, 2.0],
        [1.0, -1.0, 2.0],
    ];
    let dir = Dir::new();
    for (name, points, mode, triangles) in [("strip", &square[..], 5, 2), ("fan", &fan[..], 6, 4)] {
        let mut buffer = Buffer::default();
        let positions = buffer.positions(points);
        let document = buffer.document(json!({
            "meshes": [{"primitives": [{"attributes": {"POSITION": positions}, "mode": mode}]}],
            "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]
        }));
        dir.write(&format!("{name}.gltf"), document.to_string());
        let json = format!(
            r#"{{"image": {{"width": 8, "height": 8}}, "integrator": {{"type": "normal"}},
                "camera": {{"forward": [0, 0, 2]}}, "meshes": [{{"file": "{name}.gltf"}}]}}"#
        );
        dir.write(&format!("{name}.json"), json);
        let run = dir.raybatch(&["render", &format!("{name}.json"), "--stats", "s.json"]);
        assert_eq!(run.status, 0, "{}", run.stderr);
        let image = crate::util::ppm(&dir.read(&format!("{name}.ppm")));
        assert_eq!(
            image.count([128, 128, 255]),
            64,
            "{name}: every pixel sees a +z normal"
        );
        let stats: Value = serde_json::from_slice(&dir.read("s.json")).unwrap();
        assert_eq!(stats["triangles"], triangles, "{name}");
        // The vertices in the specification's order, which the contract's normals follow
        // (a rotation of a triangle's corners changes its normal's rounding).
        let corners: Vec<[usize; 3]> = (0..triangles)
            .map(|i| match name {
                "strip" if i % 2 == 1 => [i, i + 2, i + 1],
                "strip" => [i, i + 1, i + 2],
                _ => [i + 1, i + 2, 0],
            })
            .collect();
        let manifest = Manifest::load(&dir.join(&format!("{name}.json"))).unwrap();
        let geometry = SceneGeometry::load(&manifest, &mut MeshCache::new()).unwrap();
        let expected: Vec<[[f32; 3]; 3]> = corners.iter().map(|c| c.map(|k| points[k])).collect();
        assert_eq!(geometry.triangles, expected, "{name}");
    }
}

#[test]
fn points_and_lines_are_skipped_with_a_warning() {
    let mut buffer = Buffer::default();
    let positions = buffer.positions(&TRIANGLE);
    let document = buffer.document(json!({
        "meshes": [{"primitives": [
            {"attributes": {"POSITION": positions}, "mode": 0},
            {"attributes": {"POSITION": positions}, "mode": 1},
            {"attributes": {"POSITION": positions}, "mode": 3},
            {"attributes": {"POSITION": positions}, "mode": 4}
        ]}],
        "nodes": [{"translation": [0, 0, 4], "mesh": 0}], "scenes": [{"nodes": [0]}]
    }));
    let dir = Dir::new();
    dir.write("mixed.gltf", document.to_string());
    dir.write(
        "m.json",
        r#"{"image": {"width": 9, "height": 9}, "meshes": [{"file": "mixed.gltf"}]}"#,
    );
    let run = dir.raybatch(&["render", "m.json"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    let warnings = run.warning_lines();
    assert_eq!(warnings.len(), 2, "{}", run.stderr);
    assert!(
        warnings.iter().any(|w| w.contains("1 point primitive")),
        "{warnings:?}"
    );
    assert!(
        warnings.iter().any(|w| w.contains("2 line primitives")),
        "{warnings:?}"
    );
    assert!(
        warnings
            .iter()
            .all(|w| w.contains("m.json") && w.contains("mixed.gltf"))
    );
}

#[test]
fn a_mesh_file_without_triangles_renders_with_a_warning() {
    let mut buffer = Buffer::default();
    let positions = buffer.positions(&TRIANGLE);
    // A glTF whose only primitive is points, and whose scene has no nodes.
    let points = buffer.document(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": positions}, "mode": 0}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": []}]
    }));
    let dir = Dir::new();
    dir.write("points.gltf", points.to_string());
    dir.write("empty.obj", "# exported from an empty scene\nv 0 0 1\n");
    dir.write("one.obj", "v 0 0 1\nv 1 0 1\nv 0 1 1\nf 1 2 3\n");
    for (file, warned) in [
        ("points.gltf", true),
        ("empty.obj", true),
        ("one.obj", false),
    ] {
        dir.write(
            "m.json",
            format!(
                r#"{{"image": {{"width": 4, "height": 4}}, "meshes": [{{"file": "{file}"}}]}}"#
            ),
        );
        let run = dir.raybatch(&["render", "m.json"]);
        assert_eq!(run.status, 0, "{}", run.stderr);
        let warnings = run.warning_lines();
        assert_eq!(
            warnings
                .iter()
                .any(|w| w.contains(file) && w.contains("no triangles")),
            warned,
            "{file}: {warnings:?}"
        );
    }
}

/// glTF 2.0 requires `min` and `max` on `POSITION` accessors, but some exporters leave
/// them out; the gltf crate's validator refuses such a file. It is read (nothing needs the
/// bounds) with a warning naming the accessor, and renders the triangle's depth.
#[test]
fn positions_without_min_and_max_are_read_with_a_warning() {
    let mut buffer = Buffer::default();
    let positions = buffer.positions(&TRIANGLE);
    for key in ["min", "max"] {
        buffer.accessors[positions]
            .as_object_mut()
            .unwrap()
            .remove(key);
    }
    let document = buffer.document(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": positions}}]}],
        "nodes": [{"translation": [0, 0, 6], "mesh": 0}], "scenes": [{"nodes": [0]}]
    }));
    let dir = Dir::new();
    dir.write("bare.gltf", document.to_string());
    dir.write(
        "b.json",
        r#"{"image": {"width": 9, "height": 9}, "output": "d.pfm",
            "integrator": {"type": "depth"}, "meshes": [{"file": "bare.gltf"}]}"#,
    );
    let run = dir.raybatch(&["render", "b.json"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    let warnings = run.warning_lines();
    assert_eq!(warnings.len(), 1, "{}", run.stderr);
    assert!(
        warnings[0].contains("bare.gltf")
            && warnings[0].contains(&format!("accessors[{positions}]"))
            && warnings[0].contains("min and max"),
        "{warnings:?}"
    );
    assert_close(crate::util::pfm(&dir.read("d.pfm")).at(4, 4)[0], 6.0);
}

#[test]
fn glb_external_and_sparse_buffers_and_unread_images() {
    let dir = Dir::new();
    let mut buffer = Buffer::default();
    let positions = buffer.positions(&TRIANGLE);
    let indices = buffer.indices(&[0, 1, 2]);
    let scene = json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": positions}, "indices": indices}]}],
        "nodes": [{"translation": [0, 0, 6], "mesh": 0}], "scenes": [{"nodes": [0]}],
        // Images are never read: a missing file and a broken data URI must not matter.
        "images": [{"uri": "missing.png"}, {"uri": "data:image/png;base64,@@@"}]
    });
    let embedded = buffer.document(scene.clone());
    dir.write("embedded.gltf", embedded.to_string());
    assert_close(depth_of(&dir, "embedded.gltf").at(4, 4)[0], 6.0);

    // The same buffer in a file beside it, with a percent-encoded name.
    let mut external = embedded.clone();
    external["buffers"][0]["uri"] = json!("my%20data.bin");
    dir.write("my data.bin", &buffer.bytes);
    dir.write("external.gltf", external.to_string());
    assert_close(depth_of(&dir, "external.gltf").at(4, 4)[0], 6.0);

    // GLB: 12-byte header, a JSON chunk and a BIN chunk, each 4-byte aligned.
    let mut json_chunk = embedded.clone();
    json_chunk["buffers"] = json!([{"byteLength": buffer.bytes.len()}]);
    let mut json_bytes = json_chunk.to_string().into_bytes();
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    let mut bin = buffer.bytes.clone();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json_bytes.len() + 8 + bin.len();
    let mut glb = Vec::new();
    glb.extend_from_slice(b"glTF");
    glb.extend_from_slice(&2u32.to_le_bytes());
    glb.extend_from_slice(&(total as u32).to_le_bytes());
    glb.extend_from_slice(&(json_bytes.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"JSON");
    glb.extend_from_slice(&json_bytes);
    glb.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"BIN\0");
    glb.extend_from_slice(&bin);
    dir.write("binary.glb", glb);
    assert_close(depth_of(&dir, "binary.glb").at(4, 4)[0], 6.0);

    // Sparse: positions start as all zeros (no bufferView) and two of the three vertices
    // are substituted; an interleaved view (byteStride 16) holds the substitutes.
    let mut sparse = Buffer::default();
    let offset = sparse.bytes.len();
    for i in [1u16, 2] {
        sparse.bytes.extend_from_slice(&i.to_le_bytes());
    }
    sparse.view(offset, None);
    let index_view = sparse.views.len() - 1;
    let offset = sparse.bytes.len();
    for p in [[2.0f32, -1.0, 0.0], [-1.0, 2.0, 0.0]] {
        for c in p {
            sparse.bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    sparse.view(offset, None);
    let value_view = sparse.views.len() - 1;
    sparse.accessors.push(json!({
        "componentType": 5126, "count": 3, "type": "VEC3",
        "min": [-1, -1, 0], "max": [2, 2, 0],
        "sparse": {"count": 2, "indices": {"bufferView": index_view, "componentType": 5123},
                   "values": {"bufferView": value_view}}
    }));
    let mut document = sparse.document(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"translation": [-0.5, -0.5, 3], "mesh": 0}], "scenes": [{"nodes": [0]}]
    }));
    dir.write("sparse.gltf", document.to_string());
    assert_close(depth_of(&dir, "sparse.gltf").at(4, 4)[0], 3.0);

    // Interleaved positions: every vertex followed by 4 unrelated bytes.
    let mut interleaved = Buffer::default();
    for p in TRIANGLE {
        for c in p {
            interleaved.bytes.extend_from_slice(&c.to_le_bytes());
        }
        interleaved.bytes.extend_from_slice(&f32::NAN.to_le_bytes());
    }
    interleaved.view(0, Some(16));
    interleaved.accessor(json!({"componentType": 5126, "count": 3, "type": "VEC3", "min": [-0.5, -0.5, 0], "max": [1, 1, 0]}));
    document = interleaved.document(json!({
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"translation": [0, 0, 2.5], "mesh": 0}], "scenes": [{"nodes": [0]}]
    }));
    dir.write("interleaved.gltf", document.to_string());
    assert_close(depth_of(&dir, "interleaved.gltf").at(4, 4)[0], 2.5);
}

#[test]
fn obj_polygons_groups_and_objects_all_render() {
    // A quad and a pentagon in two groups: 2 + 3 triangles, covering the whole view.
    let dir = Dir::new();
    dir.write(
        "poly.obj",
        "o first\nv -4 -4 3\nv 0 -4 3\nv 0 4 3\nv -4 4 3\ng second\nv 0 -4 3\nv 4 -4 3\nv 4 0 3\nv 4 4 3\nv 0 4 3\n\
         usemtl missing\ng first\nf 1 2 3 4\ng second\nf 5 6 7 8 9\n",
    );
    dir.write(
        "p.json",
        r#"{"image": {"width": 16, "height": 16}, "meshes": [{"file": "poly.obj"}]}"#,
    );
    let run = dir.raybatch(&["render", "p.json", "--stats", "s.json"]);
    assert_eq!(run.status, 0, "{}", run.stderr);
    let stats: Value = serde_json::from_slice(&dir.read("s.json")).unwrap();
    assert_eq!(stats["triangles"], 5);
    let image = crate::util::ppm(&dir.read("p.ppm"));
    assert_eq!(image.count([255; 3]), 256);
}

#[test]
fn a_mesh_can_be_placed_several_times() {
    let dir = Dir::new();
    dir.write(
        "tri.obj",
        "v -0.5 -0.5 0\nv 1 -0.5 0\nv -0.5 1 0\nf 1 2 3\n",
    );
    let image = dir.pfm_of(
        "two.json",
        r#"{"image": {"width": 9, "height": 9}, "output": "two.pfm", "integrator": {"type": "depth"},
            "meshes": [{"file": "tri.obj", "transform": {"translate": [0, 0, 8]}},
                       {"file": "tri.obj", "transform": {"translate": [0, 0, 4]}}]}"#,
        "two.pfm",
    );
    assert_eq!(image.at(4, 4)[0], 4.0);
}

#[test]
fn quantized_positions_and_material_extensions_are_accepted_but_draco_is_refused() {
    // KHR_mesh_quantization: int16 positions (not normalized), scaled back by the node.
    let mut buffer = Buffer::default();
    let offset = buffer.bytes.len();
    for p in [[-50i16, -50, 0], [100, -50, 0], [-50, 100, 0]] {
        for c in p {
            buffer.bytes.extend_from_slice(&c.to_le_bytes());
        }
        buffer.bytes.extend_from_slice(&[0, 0]); // int16 VEC3 elements are padded to 8 bytes
    }
    buffer.view(offset, Some(8));
    buffer.accessor(json!({"componentType": 5122, "count": 3, "type": "VEC3", "min": [-50, -50, 0], "max": [100, 100, 0]}));
    let document = buffer.document(json!({
        "extensionsUsed": ["KHR_mesh_quantization", "KHR_materials_unlit"],
        "extensionsRequired": ["KHR_mesh_quantization", "KHR_materials_unlit"],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"translation": [0, 0, 5], "scale": [0.01, 0.01, 0.01], "mesh": 0}],
        "scenes": [{"nodes": [0]}]
    }));
    let dir = Dir::new();
    dir.write("quantized.gltf", document.to_string());
    assert_close(depth_of(&dir, "quantized.gltf").at(4, 4)[0], 5.0);

    let mut draco = document.clone();
    draco["extensionsRequired"] = json!(["KHR_draco_mesh_compression"]);
    dir.write("draco.gltf", draco.to_string());
    dir.write(
        "x.json",
        r#"{"image": {"width": 2, "height": 2}, "meshes": [{"file": "draco.gltf"}]}"#,
    );
    let run = dir.raybatch(&["render", "x.json"]);
    assert_eq!(run.status, 1);
    assert!(
        run.stderr.contains("KHR_draco_mesh_compression"),
        "{}",
        run.stderr
    );
}
