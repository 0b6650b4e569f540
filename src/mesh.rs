//! Triangle meshes read from files, before they are placed in a scene.
//!
//! ```json
//! "meshes": [
//!   {"file": "models/bunny.obj"},
//!   {"file": "models/boxes.gltf", "transform": {"scale": 0.5}, "material": "red"}
//! ]
//! ```
//!
//! A file becomes shared vertex arrays ([`Geometry`]) placed by file-internal transforms
//! ([`Instance`], the glTF node hierarchy; identity for OBJ). The scene then applies the
//! manifest's transform on top, in float64, and rounds each vertex to float32 once.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::SystemTime;

use glam::DMat4;

use crate::error::MeshError;

/// Mesh file formats, picked by extension (case-insensitive).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    Obj,
    Gltf,
    Glb,
}

impl MeshFormat {
    pub fn from_path(path: &Path) -> Option<MeshFormat> {
        let extension = path.extension()?.to_str()?.to_ascii_lowercase();
        match extension.as_str() {
            "obj" => Some(MeshFormat::Obj),
            "gltf" => Some(MeshFormat::Gltf),
            "glb" => Some(MeshFormat::Glb),
            _ => None,
        }
    }
}

/// Vertices and the triangles that index them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Geometry {
    pub positions: Vec<[f32; 3]>,
    /// Vertex indices in stored order; every index is `< positions.len()`.
    pub triangles: Vec<[u32; 3]>,
}

/// One placement of a [`Geometry`] within its file.
#[derive(Debug, Clone, PartialEq)]
pub struct Instance {
    pub geometry: usize,
    /// File-internal transform (glTF node to root), object to file space.
    pub transform: DMat4,
}

/// Everything a mesh file contributes to a scene.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MeshFile {
    pub geometries: Vec<Geometry>,
    pub instances: Vec<Instance>,
    /// Things skipped on the way (such as glTF points and lines), for the user to see.
    pub warnings: Vec<String>,
}

impl MeshFile {
    /// A file of one geometry, placed as it is (one instance, identity transform).
    pub fn one_geometry(geometry: Geometry) -> MeshFile {
        MeshFile {
            geometries: vec![geometry],
            instances: vec![Instance {
                geometry: 0,
                transform: DMat4::IDENTITY,
            }],
            warnings: Vec::new(),
        }
    }

    /// Triangles once every instance is placed.
    pub fn triangle_count(&self) -> usize {
        self.instances
            .iter()
            .map(|i| self.geometries[i.geometry].triangles.len())
            .sum()
    }

    /// Bytes of the file read, for load-rate figures.
    pub fn memory_bytes(&self) -> usize {
        self.geometries
            .iter()
            .map(|g| g.positions.len() * 12 + g.triangles.len() * 12)
            .sum()
    }
}

/// Reads a mesh file of any supported format.
pub fn load(path: &Path) -> Result<MeshFile, MeshError> {
    let format = MeshFormat::from_path(path).ok_or_else(|| MeshError::Format {
        path: path.to_path_buf(),
    })?;
    let bytes = crate::file_bytes::FileBytes::open(path).map_err(|source| MeshError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let mut mesh = match format {
        MeshFormat::Obj => crate::obj::parse(&bytes, path)?,
        MeshFormat::Gltf | MeshFormat::Glb => crate::gltf_mesh::parse(&bytes, path)?,
    };
    for geometry in &mesh.geometries {
        check_geometry(geometry, path)?;
    }
    // Valid, but most likely not what was meant (an empty export, a glTF scene of no nodes).
    if mesh.triangle_count() == 0 {
        mesh.warnings.push(format!(
            "{}: no triangles; the mesh adds nothing",
            path.display()
        ));
    }
    Ok(mesh)
}

/// Loaders must not hand out a triangle that indexes past the vertices or a vertex that is
/// not a finite number; this is the last line of that defence.
fn check_geometry(geometry: &Geometry, path: &Path) -> Result<(), MeshError> {
    let range = |message: String| MeshError::Range {
        path: path.to_path_buf(),
        message,
    };
    if let Some(i) = geometry
        .positions
        .iter()
        .position(|p| !p.iter().all(|c| c.is_finite()))
    {
        return Err(range(format!(
            "vertex {} is not finite: {:?}",
            i + 1,
            geometry.positions[i]
        )));
    }
    let n = geometry.positions.len();
    if let Some(t) = geometry
        .triangles
        .iter()
        .position(|t| t.iter().any(|&v| v as usize >= n))
    {
        return Err(range(format!(
            "triangle {} refers to a vertex past the {n} vertices",
            t + 1
        )));
    }
    Ok(())
}

/// Mesh files already read in this batch, so a mesh shared by several manifests is read
/// once. An entry is reused only while the file's size and modification time are unchanged.
#[derive(Debug, Default)]
pub struct MeshCache {
    entries: HashMap<PathBuf, (FileStamp, Arc<MeshFile>)>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct FileStamp {
    len: u64,
    modified: Option<SystemTime>,
}

impl MeshCache {
    pub fn new() -> MeshCache {
        MeshCache::default()
    }

    /// The mesh at `path`, read now or earlier in this batch.
    pub fn load(&mut self, path: &Path) -> Result<Arc<MeshFile>, MeshError> {
        let metadata = std::fs::metadata(path).map_err(|source| MeshError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let stamp = FileStamp {
            len: metadata.len(),
            modified: metadata.modified().ok(),
        };
        let key = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
        if let Some((cached, mesh)) = self.entries.get(&key)
            && *cached == stamp
        {
            return Ok(Arc::clone(mesh));
        }
        let mesh = Arc::new(load(path)?);
        self.entries.insert(key, (stamp, Arc::clone(&mesh)));
        Ok(mesh)
    }

    /// Files read so far (each once).
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}
