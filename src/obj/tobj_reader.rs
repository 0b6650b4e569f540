//! The reference OBJ reader, through `tobj`, with faults located by line.

use std::io::Cursor;
use std::path::Path;

use crate::error::MeshError;
use crate::mesh::{Geometry, MeshFile};

pub fn parse(bytes: &[u8], path: &Path) -> Result<MeshFile, MeshError> {
    let options = tobj::LoadOptions {
        single_index: false,
        triangulate: false,
        ignore_points: true,
        ignore_lines: true,
    };
    // Materials are not needed for geometry; an absent .mtl file must not fail the load.
    let no_materials = |_: &Path| -> tobj::MTLLoadResult { Ok(Default::default()) };
    let (models, _) =
        tobj::load_obj_buf(&mut Cursor::new(bytes), &options, no_materials).map_err(|error| {
            MeshError::Obj {
                path: path.to_path_buf(),
                line: locate_error(bytes, &error),
                message: describe(&error),
            }
        })?;

    let mut geometry = Geometry::default();
    for model in &models {
        let mesh = &model.mesh;
        let base = geometry.positions.len() as u32;
        geometry
            .positions
            .extend(mesh.positions.chunks_exact(3).map(|p| [p[0], p[1], p[2]]));
        let index = |i: u32| base.saturating_add(i);
        if mesh.face_arities.is_empty() {
            geometry.triangles.extend(
                mesh.indices
                    .chunks_exact(3)
                    .map(|t| [index(t[0]), index(t[1]), index(t[2])]),
            );
        } else {
            let mut corners = mesh.indices.as_slice();
            for &arity in &mesh.face_arities {
                let Some((face, rest)) = corners.split_at_checked(arity as usize) else {
                    break;
                };
                corners = rest;
                for k in 1..face.len().saturating_sub(1) {
                    geometry
                        .triangles
                        .push([index(face[0]), index(face[k]), index(face[k + 1])]);
                }
            }
        }
    }
    Ok(MeshFile::one_geometry(geometry))
}

fn describe(error: &tobj::LoadError) -> String {
    use tobj::LoadError as E;
    match error {
        E::PositionParseError => "a vertex (`v`) needs three numbers".to_string(),
        E::ScalingByZeroError => "a vertex (`v`) has a w of 0".to_string(),
        E::NormalParseError => "a normal (`vn`) needs three numbers".to_string(),
        E::TexcoordParseError => "a texture coordinate (`vt`) needs two numbers".to_string(),
        E::FaceParseError => "a face (`f`) has an index that is not a number".to_string(),
        E::FaceVertexOutOfBounds => {
            "a face (`f`) refers to a vertex that does not exist".to_string()
        }
        E::FaceTexCoordOutOfBounds | E::FaceNormalOutOfBounds | E::FaceColorOutOfBounds => {
            "a face (`f`) refers to a texture coordinate or normal that does not exist".to_string()
        }
        E::ReadError => "not a text file (invalid UTF-8)".to_string(),
        other => other.to_string(),
    }
}

/// tobj reports what went wrong but not where; find the first line with that fault.
fn locate_error(bytes: &[u8], error: &tobj::LoadError) -> Option<usize> {
    use tobj::LoadError as E;
    let (mut positions, mut texcoords, mut normals) = (0usize, 0usize, 0usize);
    for (number, line) in bytes.split(|&b| b == b'\n').enumerate() {
        let Ok(line) = std::str::from_utf8(line) else {
            return matches!(error, E::ReadError).then_some(number + 1);
        };
        let mut words = line.split_whitespace();
        let keyword = words.next();
        let numbers = |n: usize| {
            let values: Vec<Option<f32>> = line
                .split_whitespace()
                .skip(1)
                .map(|w| w.parse().ok())
                .collect();
            values.len() >= n && values[..n].iter().all(Option::is_some)
        };
        let faulty = match keyword {
            Some("v") => {
                positions += 1;
                matches!(error, E::PositionParseError | E::ColorParseError) && !numbers(3)
                    || matches!(error, E::ScalingByZeroError)
                        && line
                            .split_whitespace()
                            .nth(4)
                            .and_then(|w| w.parse::<f32>().ok())
                            == Some(0.0)
                    || matches!(error, E::ColorParseError)
                        && matches!(line.split_whitespace().count(), 6 | 8..)
            }
            Some("vt") => {
                texcoords += 1;
                matches!(error, E::TexcoordParseError) && !numbers(2)
            }
            Some("vn") => {
                normals += 1;
                matches!(error, E::NormalParseError) && !numbers(3)
            }
            Some("f") | Some("l") => words.any(|corner| {
                let fault = corner_fault(corner, [positions, texcoords, normals]);
                match error {
                    E::FaceParseError => fault == Some(CornerFault::NotANumber),
                    E::FaceVertexOutOfBounds => fault == Some(CornerFault::OutOfRange(0)),
                    E::FaceTexCoordOutOfBounds => fault == Some(CornerFault::OutOfRange(1)),
                    E::FaceNormalOutOfBounds => fault == Some(CornerFault::OutOfRange(2)),
                    _ => false,
                }
            }),
            _ => false,
        };
        if faulty {
            return Some(number + 1);
        }
    }
    None
}

#[derive(Debug, PartialEq, Eq)]
enum CornerFault {
    NotANumber,
    /// Which of `v/vt/vn` is out of range.
    OutOfRange(usize),
}

/// What is wrong with one face corner `v`, `v/vt`, `v//vn` or `v/vt/vn`, given the counts
/// of each kind read so far (negative indices count back from them).
fn corner_fault(corner: &str, counts: [usize; 3]) -> Option<CornerFault> {
    for (kind, part) in corner.split('/').enumerate() {
        // tobj takes a corner without a vertex index (`//1`) as one out of range.
        if part.is_empty() {
            if kind == 0 {
                return Some(CornerFault::OutOfRange(0));
            }
            continue;
        }
        if kind > 2 {
            return Some(CornerFault::NotANumber);
        }
        let Ok(index) = part.parse::<isize>() else {
            return Some(CornerFault::NotANumber);
        };
        let count = counts[kind] as isize;
        let resolved = if index < 0 { count + index } else { index - 1 };
        if resolved < 0 || resolved >= count {
            return Some(CornerFault::OutOfRange(kind));
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn load(text: &str) -> Result<MeshFile, MeshError> {
        parse(text.as_bytes(), Path::new("test.obj"))
    }

    #[test]
    fn polygons_become_fans_from_their_first_vertex() {
        let mesh = load("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv -1 1 0\nf 1 2 3 4 5\n").unwrap();
        assert_eq!(
            mesh.geometries[0].triangles,
            vec![[0, 1, 2], [0, 2, 3], [0, 3, 4]]
        );
    }

    #[test]
    fn objects_and_groups_are_all_kept_in_file_order() {
        let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\no a\nf 1 2 3\ng b\nf 1 2 4\nf 2 3 4\n";
        let mesh = load(text).unwrap();
        let g = &mesh.geometries[0];
        assert_eq!(g.triangles.len(), 3);
        let corners: Vec<[[f32; 3]; 3]> = g
            .triangles
            .iter()
            .map(|t| t.map(|i| g.positions[i as usize]))
            .collect();
        assert_eq!(
            corners[0],
            [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
        );
        assert_eq!(
            corners[1],
            [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
        );
        assert_eq!(
            corners[2],
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        );
    }

    #[test]
    fn relative_indices_and_texture_normal_forms_are_read() {
        let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\nf -3/1/1 -2/1/1 -1//1\n";
        let mesh = load(text).unwrap();
        assert_eq!(mesh.geometries[0].triangles, vec![[0, 1, 2]]);
    }

    #[test]
    fn faults_are_reported_with_their_line() {
        let cases = [
            ("v 0 0 0\nv 1 x 0\n", 2, "three numbers"),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 7\n",
                5,
                "does not exist",
            ),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 three\n",
                4,
                "not a number",
            ),
            ("v 0 0 0\nvn 1 0\n", 2, "three numbers"),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1 2 3\nf //1 2 3\n",
                6,
                "does not exist",
            ),
        ];
        for (text, line, words) in cases {
            let error = load(text).unwrap_err();
            let message = error.to_string();
            assert!(message.contains(&format!("line {line}")), "{message}");
            assert!(message.contains(words), "{message}");
        }
    }
}
