//! raybatch's integration tests: one test binary (one link, one run) with a module per
//! area. Each checks behaviour against truth computed independently of the code under
//! test: integer pixel masks, float64 formulas, brute-force searches, hand-written files.
//!
//! - `util`: the harness: a temp folder, the real `raybatch` binary run inside it, and
//!   independent PPM/PFM readers.
//! - `canonical`: the seed's scene pixel for pixel; P3/P6; thread counts; shipped scenes;
//!   `raybatch bench`'s report of it, and of each scene's own memory.
//! - `camera`: the pixel-to-ray mapping of both camera forms.
//! - `geometry`: hit rules for spheres, planes and triangles; the strict interval and its
//!   defaults; transforms.
//! - `integrators`: what `hit`, `depth` and `normal` write.
//! - `output`: file formats, encodings, output paths, `--out`, `--stats`.
//! - `compare`: `raybatch compare` figures, limits and refusals; a reader gone away
//!   (`| head -1`) changes no command's work or exit status.
//! - `embree` (feature `embree`): every shipped and stress scene verified against Embree,
//!   `render --backend embree`, watertightness cross-checked, rays Embree would abort on,
//!   no hit at `t = 0`, the strict interval and the normals through the Embree backend,
//!   `verify` tracing the tree a render builds and timing its median pass.
//! - `meshes`: OBJ and glTF fixtures written by the tests.
//! - `errors`: bad manifests and mesh files refused with a place and cause, no partial
//!   files, batches going on, exit statuses.
//! - `mutations`: mutated mesh files and manifests (deterministic) are read, rendered or
//!   refused, never a panic.
//! - `robustness`: watertightness, traversal against brute force, deep trees, tiny
//!   direction components, tiny far spheres.
//! - `stress`: the stress suite (scale sweeps, leaks, offsets, needles, …) against its
//!   references, and proof that it catches rays started without an offset.
//! - `skipping`: work a scene does not need is not done (trees, closest-hit searches,
//!   normals, rays of tiles that miss the scene's box, rereading and rebuilding a batch's
//!   shared mesh, reinsertion).
//! - `real_models`: the scanned models of `../shared/models` and Debian's glTF and OBJ test
//!   files; ignored by default (run by `.ci/run` with `--include-ignored`).

mod util;

mod camera;
mod canonical;
mod compare;
#[cfg(feature = "embree")]
mod embree;
mod errors;
mod geometry;
mod integrators;
mod meshes;
mod mutations;
mod output;
mod real_models;
mod robustness;
mod skipping;
mod stress;
