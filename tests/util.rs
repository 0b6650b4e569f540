//! The test harness: temp folders, the real binary, and image readers written
//! independently of the crate's own writers.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// A temporary folder, removed when dropped.
pub struct Dir {
    tmp: tempfile::TempDir,
}

/// How the binary starts a warning line on stderr.
const WARNING: &str = "raybatch: warning:";

/// A finished run of the binary.
#[derive(Debug)]
pub struct Run {
    pub status: i32,
    pub stdout: String,
    pub stderr: String,
}

impl Run {
    /// Lines on stderr that report an error (warnings excluded).
    pub fn error_lines(&self) -> Vec<&str> {
        self.stderr
            .lines()
            .filter(|l| !l.starts_with(WARNING))
            .collect()
    }

    /// Lines on stderr that give a warning.
    pub fn warning_lines(&self) -> Vec<&str> {
        self.stderr
            .lines()
            .filter(|l| l.starts_with(WARNING))
            .collect()
    }
}

impl Dir {
    pub fn new() -> Dir {
        Dir {
            tmp: tempfile::tempdir().expect("temp dir"),
        }
    }

    pub fn path(&self) -> &Path {
        self.tmp.path()
    }

    pub fn join(&self, name: &str) -> PathBuf {
        self.path().join(name)
    }

    /// Writes `contents` to `name` (creating folders), returning its path.
    pub fn write(&self, name: &str, contents: impl AsRef<[u8]>) -> PathBuf {
        let path = self.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).unwrap();
        }
        std::fs::write(&path, contents).unwrap();
        path
    }

    pub fn exists(&self, name: &str) -> bool {
        self.join(name).exists()
    }

    pub fn read(&self, name: &str) -> Vec<u8> {
        std::fs::read(self.join(name)).unwrap_or_else(|e| panic!("reading {name}: {e}"))
    }

    /// Every file below the folder, relative paths sorted.
    pub fn files(&self) -> Vec<String> {
        let mut out = Vec::new();
        let mut stack = vec![self.path().to_path_buf()];
        while let Some(dir) = stack.pop() {
            for entry in std::fs::read_dir(dir).unwrap() {
                let path = entry.unwrap().path();
                if path.is_dir() {
                    stack.push(path);
                } else {
                    let relative = path.strip_prefix(self.path()).unwrap();
                    out.push(relative.to_string_lossy().into_owned());
                }
            }
        }
        out.sort();
        out
    }

    /// Runs `raybatch ARGS...` with this folder as the working directory.
    pub fn raybatch(&self, args: &[&str]) -> Run {
        let output = Command::new(env!("CARGO_BIN_EXE_raybatch"))
            .args(args)
            .current_dir(self.path())
            .output()
            .expect("run raybatch");
        Run {
            status: output.status.code().unwrap_or(-1),
            stdout: String::from_utf8_lossy(&output.stdout).into_owned(),
            stderr: String::from_utf8_lossy(&output.stderr).into_owned(),
        }
    }

    /// Runs `raybatch ARGS...` as [`Dir::raybatch`] does, its standard output a pipe whose
    /// reader has already gone away (as in `raybatch ... | head -1` once `head` is done):
    /// every write to it fails. `stdout` is empty.
    pub fn raybatch_unread(&self, args: &[&str]) -> Run {
        let (reader, writer) = std::io::pipe().expect("a pipe");
        drop(reader);
        let output = Command::new(env!("CARGO_BIN_EXE_raybatch"))
            .args(args)
            .current_dir(self.path())
            .stdout(writer)
            .output()
            .expect("run raybatch");
        Run {
            status: output.status.code().unwrap_or(-1),
            stdout: String::new(),
            stderr: String::from_utf8_lossy(&output.stderr).into_owned(),
        }
    }

    /// Renders `manifest` (a file name in this folder) and insists it succeeds.
    pub fn render_ok(&self, manifest: &str) -> Run {
        let run = self.raybatch(&["render", manifest]);
        assert_eq!(run.status, 0, "render {manifest} failed: {}", run.stderr);
        run
    }

    /// Writes `json` as `name`, renders it and reads the PPM it produced at `output`.
    pub fn ppm_of(&self, name: &str, json: &str, output: &str) -> Ppm {
        self.write(name, json);
        self.render_ok(name);
        ppm(&self.read(output))
    }

    /// As [`Dir::ppm_of`] for PFM output.
    pub fn pfm_of(&self, name: &str, json: &str, output: &str) -> Pfm {
        self.write(name, json);
        self.render_ok(name);
        pfm(&self.read(output))
    }
}

/// A decoded PPM (P3 or P6), pixels row-major from the top-left.
#[derive(Debug, PartialEq)]
pub struct Ppm {
    pub magic: String,
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<[u8; 3]>,
}

impl Ppm {
    pub fn at(&self, x: usize, y: usize) -> [u8; 3] {
        self.pixels[y * self.width + x]
    }

    pub fn count(&self, value: [u8; 3]) -> usize {
        self.pixels.iter().filter(|&&p| p == value).count()
    }
}

/// Reads a PPM by the Netpbm definition (whitespace-separated header, `#` comments, one
/// whitespace byte before P6 data).
pub fn ppm(bytes: &[u8]) -> Ppm {
    let mut pos = 0;
    let mut token = || {
        loop {
            while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
                pos += 1;
            }
            if pos < bytes.len() && bytes[pos] == b'#' {
                while pos < bytes.len() && bytes[pos] != b'\n' {
                    pos += 1;
                }
                continue;
            }
            break;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        String::from_utf8(bytes[start..pos].to_vec()).unwrap()
    };
    let magic = token();
    let width: usize = token().parse().unwrap();
    let height: usize = token().parse().unwrap();
    assert_eq!(token(), "255");
    let mut pixels = Vec::with_capacity(width * height);
    match magic.as_str() {
        "P3" => {
            for _ in 0..width * height {
                let mut p = [0u8; 3];
                for c in &mut p {
                    *c = token().parse().unwrap();
                }
                pixels.push(p);
            }
            assert!(token().is_empty(), "trailing data after P3 pixels");
        }
        "P6" => {
            let data = &bytes[pos + 1..];
            assert_eq!(data.len(), width * height * 3, "P6 data size");
            pixels.extend(data.chunks_exact(3).map(|c| [c[0], c[1], c[2]]));
        }
        other => panic!("not a PPM: {other}"),
    }
    Ppm {
        magic,
        width,
        height,
        pixels,
    }
}

/// A decoded PFM, pixels row-major from the *top*-left (the file stores bottom first).
#[derive(Debug, PartialEq)]
pub struct Pfm {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<[f32; 3]>,
}

impl Pfm {
    pub fn at(&self, x: usize, y: usize) -> [f32; 3] {
        self.pixels[y * self.width + x]
    }
}

pub fn pfm(bytes: &[u8]) -> Pfm {
    let text_end = {
        // Three header lines: "PF", "W H", scale.
        let mut newlines = 0;
        bytes
            .iter()
            .position(|&b| {
                newlines += usize::from(b == b'\n');
                newlines == 3
            })
            .unwrap()
    };
    let header = std::str::from_utf8(&bytes[..text_end]).unwrap();
    let lines: Vec<&str> = header.lines().collect();
    assert_eq!(lines[0], "PF");
    let dims: Vec<usize> = lines[1]
        .split_whitespace()
        .map(|s| s.parse().unwrap())
        .collect();
    let scale: f64 = lines[2].trim().parse().unwrap();
    assert!(scale < 0.0, "little-endian PFM has a negative scale");
    let (width, height) = (dims[0], dims[1]);
    let data = &bytes[text_end + 1..];
    assert_eq!(data.len(), width * height * 12);
    let floats: Vec<f32> = data
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let mut pixels = vec![[0.0f32; 3]; width * height];
    for (row_in_file, row) in floats.chunks_exact(width * 3).enumerate() {
        let y = height - 1 - row_in_file;
        for x in 0..width {
            pixels[y * width + x] = [row[x * 3], row[x * 3 + 1], row[x * 3 + 2]];
        }
    }
    Pfm {
        width,
        height,
        pixels,
    }
}

/// The direction, in float64, of the default camera's ray through the centre of pixel
/// `(x, y)` of a `w × h` image: `(u, v, 1)` normalized.
pub fn default_camera_direction(x: u32, y: u32, w: u32, h: u32) -> [f64; 3] {
    let (w, h) = (f64::from(w), f64::from(h));
    let u = (w / h) * (2.0 * (f64::from(x) + 0.5) / w - 1.0);
    let v = 1.0 - 2.0 * (f64::from(y) + 0.5) / h;
    let n = (u * u + v * v + 1.0).sqrt();
    [u / n, v / n, 1.0 / n]
}

/// The path of a file in the repository.
pub fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// Asserts `got` (a float32 from an image) is within a few float32 ulps of `expected`.
#[track_caller]
pub fn assert_close(got: f32, expected: f64) {
    let tolerance = 4.0 * f64::from(f32::EPSILON) * expected.abs().max(1e-30);
    assert!(
        (f64::from(got) - expected).abs() <= tolerance,
        "{got} is not within 4 ulps of {expected}"
    );
}

/// Asserts that `got`, a pixel of a `normal` render, is the contract's colour
/// `0.5 · (n + 1)` of the unit normal `n`, each channel within `tolerance`.
pub fn assert_normal_colour(got: [f32; 3], n: [f64; 3], tolerance: f64, place: &str) {
    for k in 0..3 {
        let expected = 0.5 * (n[k] + 1.0);
        assert!(
            (f64::from(got[k]) - expected).abs() < tolerance,
            "{place}: {got:?} is not the colour of the normal {n:?}"
        );
    }
}

/// The folder an environment variable names, made absolute (tests write manifests
/// elsewhere that refer to it). A missing variable fails the test rather than letting it
/// pass without looking at anything.
pub fn folder(variable: &str) -> PathBuf {
    let value = std::env::var_os(variable)
        .unwrap_or_else(|| panic!("set {variable} to run this test (see tests/real_models.rs)"));
    let path = PathBuf::from(value);
    assert!(
        path.is_dir(),
        "{variable}={} is not a folder",
        path.display()
    );
    std::fs::canonicalize(path).unwrap()
}
