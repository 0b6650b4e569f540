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
    let index = |i: u32, j: u32| (i % rings) * sides + (j % sides);
    let mut triangles = Vec::with_capacity((2 * rings * sides) as usize);
    for i in 0..rings {
        for j in 0..sides {
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
    Geometry {
        positions,
        triangles,
    }
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
    fn tori_are_closed() {
        let g = torus(2.0, 0.5, 12, 8);
        assert_eq!(g.triangles.len(), 2 * 12 * 8);
        assert_closed(&g);
    }
}
