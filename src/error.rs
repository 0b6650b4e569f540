//! Typed errors. Every refusal names the place (a line and column, or a key path such as
//! `spheres[2].radius`) and the cause; [`JobError`] adds the manifest's own path.

use std::fmt;
use std::io;
use std::path::PathBuf;

/// A manifest that could not be read or breaks the format.
#[derive(Debug, thiserror::Error)]
pub enum ManifestError {
    /// The file could not be read at all.
    #[error("cannot read the manifest: {0}")]
    Read(#[source] io::Error),
    /// The text is not valid JSON, or a value has the wrong shape or an unknown key.
    #[error("line {line}, column {column}: {}", with_key(key, message))]
    Json {
        line: usize,
        column: usize,
        /// The key path where parsing stopped, such as `spheres[2].radius`, when there is
        /// one: the last key read in full when the text ends or breaks where a key should
        /// be.
        key: Option<String>,
        message: String,
    },
    /// Valid JSON whose values break the format: out of range, inconsistent, unknown names.
    #[error("{key}: {message}")]
    Invalid { key: String, message: String },
}

/// A number as an error message shows it: as Rust prints it, but in scientific notation
/// where that would run to many digits or zeros (`1e300`, not three hundred digits;
/// `3e15`; `1e-9`).
pub(crate) fn shown<T: Into<f64> + Copy + fmt::Display + fmt::LowerExp>(x: T) -> String {
    let magnitude = x.into().abs();
    if magnitude == 0.0 || !magnitude.is_finite() || (1e-4..1e6).contains(&magnitude) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

/// [`shown`] for each coordinate: `[x, y, z]`.
pub(crate) fn shown_point<T: Into<f64> + Copy + fmt::Display + fmt::LowerExp>(p: [T; 3]) -> String {
    format!("[{}, {}, {}]", shown(p[0]), shown(p[1]), shown(p[2]))
}

fn with_key(key: &Option<String>, message: &str) -> String {
    match key {
        Some(key) if !key.is_empty() && key != "." => format!("{key}: {message}"),
        _ => message.to_string(),
    }
}

impl ManifestError {
    pub(crate) fn invalid(key: impl Into<String>, message: impl Into<String>) -> Self {
        ManifestError::Invalid {
            key: key.into(),
            message: message.into(),
        }
    }
}

/// A mesh file that could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    #[error("{path}: unsupported mesh format (expected .obj, .gltf or .glb)")]
    Format { path: PathBuf },
    /// A malformed OBJ file; `line` is 1-based when the faulty line could be located.
    #[error("{}: {message}", at_line(path, *line))]
    Obj {
        path: PathBuf,
        line: Option<usize>,
        message: String,
    },
    /// A malformed glTF file or one of its buffers; `place` is a JSON-pointer-like location
    /// such as `accessors[3]` when one is known.
    #[error("{path}: {place}{message}")]
    Gltf {
        path: PathBuf,
        place: Place,
        message: String,
    },
    /// The transformed vertices do not fit the float32 geometry (overflow to infinity).
    #[error("{path}: {message}")]
    Range { path: PathBuf, message: String },
}

/// An optional location prefix inside a file, printed as `place: ` or nothing.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Place(pub Option<String>);

impl fmt::Display for Place {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.0 {
            Some(place) => write!(f, "{place}: "),
            None => Ok(()),
        }
    }
}

fn at_line(path: &std::path::Path, line: Option<usize>) -> String {
    match line {
        Some(line) => format!("{}: line {line}", path.display()),
        None => path.display().to_string(),
    }
}

/// Why a job failed, without the manifest's path (see [`JobError`]).
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(transparent)]
    Manifest(#[from] ManifestError),
    /// A mesh named at `key` (such as `meshes[1].file`) failed to load.
    #[error("{key}: {source}")]
    Mesh {
        key: String,
        #[source]
        source: MeshError,
    },
    /// The job's output could not be written.
    #[error("cannot write {path}: {source}")]
    Output {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    /// The tracer could not be built (Embree refused the scene, or is not in this build).
    #[error("{0}")]
    Backend(String),
    /// Two jobs of one batch would write the same output file.
    #[error("output {path} is also written by {other}; refusing to overwrite it")]
    OutputClash { path: PathBuf, other: PathBuf },
}

/// A failed job: the manifest it came from and what went wrong.
#[derive(Debug, thiserror::Error)]
#[error("{}: {error}", manifest.display())]
pub struct JobError {
    pub manifest: PathBuf,
    #[source]
    pub error: Error,
}
