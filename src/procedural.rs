//! Meshes made by formula: the project's own models (`models/`), test fixtures and
//! benchmark scenes, so nothing needs to be downloaded.

use crate::mesh::Geometry;

/// A closed icosphere of unit radius: the icosahedron with each triangle split in four
/// `subdivisions` times and the vertices pushed onto the sphere. Shared vertices are
/// stored once, so neighbouring triangles use bit-identical coordinates.
pub fn icosphere(subdivisions: u32) -> Geometry {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut positions: Vec<[f64; 3]> = vec![
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ];
    let mut triangles: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut midpoints = std::collections::HashMap::new();
        let mut midpoint = |a: u32, b: u32, positions: &mut Vec<[f64; 3]>| -> u32 {
            *midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
                let (p, q) = (positions[a as usize], positions[b as usize]);
                positions.push([0, 1, 2].map(|k| (p[k] + q[k]) / 2.0));
                positions.len() as u32 - 1
            })
        };
        let mut next = Vec::with_capacity(triangles.len() * 4);
        for [a, b, c] in triangles {
            let ab = midpoint(a, b, &mut positions);
            let bc = midpoint(b, c, &mut positions);
            let ca = midpoint(c, a, &mut positions);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        triangles = next;
    }
    Geometry {
        positions: positions
            .iter()
            .map(|p| {
                let length = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                p.map(|x| (x / length) as f32)
            })
            .collect(),
        triangles,
    }
}

/// A closed torus around the y axis: `major` radius to the tube's centre, `minor` tube
/// radius, a `rings × sides` grid of quads split into two triangles each.
pub fn torus(major: f64, minor: f64, rings: u32, sides: u32) -> Geometry {
    let mut positions = Vec::with_capacity((rings * sides) as usize);
    for i in 0..rings {
        let u = f64::from(i) / f64::from(rings) * std::f64::consts::TAU;
        for j in 0..sides {
            let v = f64::from(j) / f64::from(sides) * std::f64::consts::TAU;
            let r = major + minor * v.cos();
            positions.push([
                (r * u.cos()) as f32,
                (minor * v.sin()) as f32,
                (r * u.sin()) as f32,
            ]);
        }
    }
    let triangles = quads(rings, sides, |i, j| (i % rings) * sides + (j % sides));
    Geometry {
        positions,
        triangles,
    }
}

/// Two triangles `(a, b, c)`, `(a, c, d)` for each cell `(i, j)` of a `columns × rows` grid
/// of quads whose corners `a, b, c, d` are `index(i, j)`, `index(i+1, j)`,
/// `index(i+1, j+1)`, `index(i, j+1)`.
fn quads(columns: u32, rows: u32, index: impl Fn(u32, u32) -> u32) -> Vec<[u32; 3]> {
    let mut triangles = Vec::with_capacity(2 * columns as usize * rows as usize);
    for i in 0..columns {
        for j in 0..rows {
            let (a, b, c, d) = (
                index(i, j),
                index(i + 1, j),
                index(i + 1, j + 1),
                index(i, j + 1),
            );
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    triangles
}

/// The text of an OBJ file holding `geometry`, vertices written exactly (shortest
/// round-trip decimal form).
pub fn to_obj(geometry: &Geometry, comment: &str) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    for line in comment.lines() {
        let _ = writeln!(out, "# {line}");
    }
    for p in &geometry.positions {
        let _ = writeln!(out, "v {:?} {:?} {:?}", p[0], p[1], p[2]);
    }
    for t in &geometry.triangles {
        let _ = writeln!(out, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    out
}

/// A glTF node for [`to_gltf`]: an optional mesh, a local T·R·S transform, children.
#[derive(Debug, Clone)]
pub struct GltfNode {
    pub mesh: Option<usize>,
    pub translation: [f32; 3],
    /// Unit quaternion `[x, y, z, w]`.
    pub rotation: [f32; 4],
    pub scale: [f32; 3],
    pub children: Vec<usize>,
}

impl GltfNode {
    pub fn new(mesh: Option<usize>) -> GltfNode {
        GltfNode {
            mesh,
            translation: [0.0; 3],
            rotation: [0.0, 0.0, 0.0, 1.0],
            scale: [1.0; 3],
            children: Vec::new(),
        }
    }
}

/// One primitive of a glTF mesh: positions, optional `u16` indices, and the glTF mode
/// (4 triangles, 5 strip, 6 fan, 0 points, 1 lines).
#[derive(Debug, Clone)]
pub struct GltfPrimitive {
    pub positions: Vec<[f32; 3]>,
    pub indices: Option<Vec<u16>>,
    pub mode: u32,
}

/// A self-contained glTF 2.0 document (buffer embedded as a base64 data URI) with
/// `meshes` (lists of primitives), `nodes`, and one scene of the nodes `roots`.
pub fn to_gltf(meshes: &[Vec<GltfPrimitive>], nodes: &[GltfNode], roots: &[usize]) -> String {
    use base64::Engine;
    use serde_json::json;
    let mut buffer: Vec<u8> = Vec::new();
    let (mut views, mut accessors, mut json_meshes) = (Vec::new(), Vec::new(), Vec::new());
    for mesh in meshes {
        let mut primitives = Vec::new();
        for primitive in mesh {
            let offset = buffer.len();
            for p in &primitive.positions {
                for c in p {
                    buffer.extend_from_slice(&c.to_le_bytes());
                }
            }
            let (lo, hi) = primitive.positions.iter().fold(
                ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
                |(lo, hi), p| {
                    (
                        [0, 1, 2].map(|k| lo[k].min(p[k])),
                        [0, 1, 2].map(|k| hi[k].max(p[k])),
                    )
                },
            );
            views.push(
                json!({"buffer": 0, "byteOffset": offset, "byteLength": buffer.len() - offset}),
            );
            accessors.push(json!({
                "bufferView": views.len() - 1, "componentType": 5126,
                "count": primitive.positions.len(), "type": "VEC3", "min": lo, "max": hi
            }));
            let mut json_primitive =
                json!({"attributes": {"POSITION": accessors.len() - 1}, "mode": primitive.mode});
            if let Some(indices) = &primitive.indices {
                let offset = buffer.len();
                for i in indices {
                    buffer.extend_from_slice(&i.to_le_bytes());
                }
                views.push(
                    json!({"buffer": 0, "byteOffset": offset, "byteLength": buffer.len() - offset}),
                );
                accessors.push(json!({
                    "bufferView": views.len() - 1, "componentType": 5123,
                    "count": indices.len(), "type": "SCALAR"
                }));
                json_primitive["indices"] = json!(accessors.len() - 1);
            }
            while !buffer.len().is_multiple_of(4) {
                buffer.push(0);
            }
            primitives.push(json_primitive);
        }
        json_meshes.push(json!({"primitives": primitives}));
    }
    let json_nodes: Vec<_> = nodes
        .iter()
        .map(|n| {
            let mut node =
                json!({"translation": n.translation, "rotation": n.rotation, "scale": n.scale});
            if let Some(mesh) = n.mesh {
                node["mesh"] = json!(mesh);
            }
            if !n.children.is_empty() {
                node["children"] = json!(n.children);
            }
            node
        })
        .collect();
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&buffer)
    );
    let document = json!({
        "asset": {"version": "2.0", "generator": "raybatch procedural::to_gltf"},
        "scene": 0,
        "scenes": [{"nodes": roots}],
        "nodes": json_nodes,
        "meshes": json_meshes,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": buffer.len(), "uri": uri}],
    });
    let mut text = serde_json::to_string_pretty(&document).unwrap_or_default();
    text.push('\n');
    text
}

/// The unit cube `[-0.5, 0.5]³` as 8 vertices and 12 outward-wound triangles.
pub fn cube() -> Geometry {
    let positions = (0..8)
        .map(|i| [i & 1, (i >> 1) & 1, (i >> 2) & 1].map(|b| b as f32 - 0.5))
        .collect();
    let triangles = vec![
        [0, 2, 3],
        [0, 3, 1], // z = -0.5
        [4, 5, 7],
        [4, 7, 6], // z = +0.5
        [0, 1, 5],
        [0, 5, 4], // y = -0.5
        [2, 6, 7],
        [2, 7, 3], // y = +0.5
        [0, 4, 6],
        [0, 6, 2], // x = -0.5
        [1, 3, 7],
        [1, 7, 5], // x = +0.5
    ];
    Geometry {
        positions,
        triangles,
    }
}

/// A `cells × cells` grid of triangle pairs on the plane `z = 1` whose vertices sit
/// exactly where the pixel-centre rays of the default camera cross it, for a square image
/// of `cells` pixels (a power of two keeps the coordinates exact), plus one ring outside.
pub fn pixel_grid(cells: u32) -> Geometry {
    let n = f64::from(cells);
    let mut positions = Vec::new();
    for j in 0..=cells + 1 {
        for i in 0..=cells + 1 {
            let u = (2.0 * f64::from(i) - 1.0 - n) / n;
            let v = (n - 2.0 * f64::from(j) + 1.0) / n;
            positions.push([u as f32, v as f32, 1.0]);
        }
    }
    let triangles = quads(cells + 1, cells + 1, |i, j| j * (cells + 2) + i);
    Geometry {
        positions,
        triangles,
    }
}

/// A wedge of the unit disc cut into `slivers` triangles, each from the centre to two
/// neighbouring points of the rim `angle` radians apart (`longest edge² / (2 · area)` is
/// about `1 / angle`), tilted out of every axis plane: the disc `y = 0` turned by 30°
/// about x, then by 20° about z. The float32 test's distances are worst on such triangles
/// ([`crate::triangle::THIN_ASPECT`]).
pub fn sliver_wedge(slivers: u32, angle: f64) -> Geometry {
    let (a, b) = (30f64.to_radians(), 20f64.to_radians());
    let tilt = |[x, y, z]: [f64; 3]| {
        let (y, z) = (y * a.cos() - z * a.sin(), y * a.sin() + z * a.cos());
        let (x, y) = (x * b.cos() - y * b.sin(), x * b.sin() + y * b.cos());
        [x, y, z].map(|c| c as f32)
    };
    let rim = (0..=slivers).map(|i| {
        let u = f64::from(i) * angle;
        tilt([u.cos(), 0.0, u.sin()])
    });
    Geometry {
        positions: std::iter::once([0.0; 3]).chain(rim).collect(),
        triangles: (1..=slivers).map(|i| [0, i, i + 1]).collect(),
    }
}

/// The files of `models/`, by name: what `cargo run --example make_models` writes.
pub fn model_files() -> Vec<(&'static str, Vec<u8>)> {
    let icosphere = to_obj(
        &icosphere(2),
        "Unit icosphere, 2 subdivisions (320 triangles).\nMade by raybatch::procedural; regenerate with `cargo run --example make_models`.",
    );
    let torus = to_obj(
        &torus(1.0, 0.35, 48, 24),
        "Torus around y: major radius 1, tube radius 0.35, 48 x 24 quads.\nMade by raybatch::procedural; regenerate with `cargo run --example make_models`.",
    );
    (["icosphere.obj", "torus.obj"].into_iter())
        .zip([icosphere, torus])
        .map(|(name, text)| (name, text.into_bytes()))
        .chain([
            ("stack.gltf", stack_gltf().into_bytes()),
            (
                "pixel-grid.obj",
                to_obj(
                    &pixel_grid(64),
                    "Triangles on z = 1 with a vertex on every pixel-centre ray of a 64 x 64 default camera.\nMade by raybatch::procedural; regenerate with `cargo run --example make_models`.",
                )
                .into_bytes(),
            ),
            (
                "sliver-wedge.obj",
                to_obj(
                    &sliver_wedge(2000, std::f64::consts::TAU / 200_000.0),
                    "A wedge of the unit disc cut into 2000 slivers, each 1/200000 of a turn wide, tilted 30 degrees about x, then 20 about z.\nMade by raybatch::procedural; regenerate with `cargo run --example make_models`.",
                )
                .into_bytes(),
            ),
        ])
        .collect()
}

/// A glTF scene with a node hierarchy: a base cube carrying a rotated, scaled cube on top
/// (whose transform composes with its parent's), a hexagon as a triangle fan and a ribbon
/// as a triangle strip.
fn stack_gltf() -> String {
    let c = cube();
    let cube_primitive = GltfPrimitive {
        positions: c.positions,
        indices: Some(c.triangles.iter().flatten().map(|&i| i as u16).collect()),
        mode: 4,
    };
    let hexagon = GltfPrimitive {
        positions: std::iter::once([0.0, 0.0, 0.0])
            .chain((0..=6).map(|i| {
                let a = i as f32 * std::f32::consts::TAU / 6.0;
                [0.5 * a.cos(), 0.5 * a.sin(), 0.0]
            }))
            .collect(),
        indices: None,
        mode: 6,
    };
    let ribbon = GltfPrimitive {
        positions: (0..10)
            .map(|i| {
                [
                    (i / 2) as f32 * 0.25,
                    (i % 2) as f32 * 0.3,
                    0.1 * ((i / 2) as f32).sin(),
                ]
            })
            .collect(),
        indices: None,
        mode: 5,
    };
    let quarter_turn_y = [
        0.0,
        std::f32::consts::FRAC_1_SQRT_2,
        0.0,
        std::f32::consts::FRAC_1_SQRT_2,
    ];
    let mut base = GltfNode::new(Some(0));
    base.scale = [1.0, 0.5, 1.0];
    base.children = vec![1];
    let mut top = GltfNode::new(Some(0));
    // Local to the base: up one unit (half a unit once the base's y scale applies).
    top.translation = [0.0, 1.0, 0.0];
    top.rotation = [0.0, 0.38268343, 0.0, 0.9238795]; // 45 degrees about y
    top.scale = [0.6, 1.0, 0.6];
    let mut fan = GltfNode::new(Some(1));
    fan.translation = [-1.4, 0.0, 0.0];
    fan.rotation = quarter_turn_y;
    let mut strip = GltfNode::new(Some(2));
    strip.translation = [0.9, -0.25, 0.0];
    to_gltf(
        &[vec![cube_primitive], vec![hexagon], vec![ribbon]],
        &[base, top, fan, strip],
        &[0, 2, 3],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every edge of a closed, consistently wound mesh appears once in each direction.
    fn assert_closed(g: &Geometry) {
        let mut edges = std::collections::HashMap::new();
        for t in &g.triangles {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        for (&(a, b), &n) in &edges {
            assert_eq!(n, 1, "edge {a}-{b} used {n} times");
            assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}-{b} has no twin");
        }
    }

    #[test]
    fn icospheres_are_closed_with_the_expected_counts() {
        for n in 0..4 {
            let g = icosphere(n);
            assert_eq!(g.triangles.len(), 20 * 4usize.pow(n));
            assert_eq!(g.positions.len(), 10 * 4usize.pow(n) + 2);
            assert_closed(&g);
        }
    }

    #[test]
    fn the_cube_is_closed() {
        assert_closed(&cube());
    }

    #[test]
    fn tori_are_closed() {
        let g = torus(2.0, 0.5, 12, 8);
        assert_eq!(g.triangles.len(), 2 * 12 * 8);
        assert_closed(&g);
    }
}
