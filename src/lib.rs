//! raybatch renders JSON scene manifests (spheres, planes, OBJ and glTF meshes) to PPM and
//! PFM images, one job per manifest, a folder at a time.
//!
//! The pieces, in the order a job uses them:
//!
//! - [`manifest`]: JSON text to a checked [`Manifest`] (no files besides the manifest read);
//! - [`scene`]: meshes loaded ([`mesh`], [`obj`], [`gltf_mesh`]) and placed, then the
//!   acceleration trees built ([`bvh`]) into a [`Scene`] that answers closest-hit and
//!   any-hit queries; intersection in [`sphere`], [`plane`] and [`triangle`];
//! - [`render`]: camera rays ([`camera`], [`sampler`]) through an [`integrator`] into an
//!   [`image`], written atomically;
//! - [`job`]: the above with timings and a report, and batches of jobs.
//!
//! ```no_run
//! use raybatch::{Manifest, Scene, SceneGeometry, mesh::MeshCache};
//!
//! let manifest = Manifest::load("scenes/canonical.json".as_ref())?;
//! let geometry = SceneGeometry::load(&manifest, &mut MeshCache::new())?;
//! let scene = Scene::build(&geometry);
//! let image = raybatch::render::render(&scene, &manifest, &|_| {})?;
//! image.write(&manifest.output)?;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod accuracy;
pub mod bench;
pub mod bvh;
pub mod camera;
pub mod collapse;
pub mod compare;
pub mod compute_loop;
#[cfg(feature = "embree")]
pub mod embree;
pub mod error;
pub mod file_bytes;
pub mod gltf_mesh;
pub mod hint;
pub mod image;
pub mod integrator;
#[cfg(target_arch = "x86_64")]
pub mod interleaved;
pub mod job;
pub mod manifest;
pub mod mesh;
pub mod morton;
pub mod obj;
pub mod offset;
#[cfg(target_arch = "x86_64")]
pub mod packet;
pub mod plane;
pub mod ploc;
pub mod procedural;
pub mod ray;
pub mod render;
pub mod sampler;
pub mod scene;
#[cfg(target_arch = "x86_64")]
mod shear_cull;
#[cfg(target_arch = "x86_64")]
pub mod simd;
#[cfg(target_arch = "x86_64")]
pub mod simd512;
pub mod sphere;
#[cfg(target_arch = "x86_64")]
pub mod sphere_packet;
pub mod stress;
pub mod transform;
pub mod triangle;
#[cfg(feature = "embree")]
pub mod verify;

#[cfg(all(test, target_arch = "x86_64"))]
mod packet_cases;
#[cfg(test)]
mod test_random;

pub use error::{Error, JobError, ManifestError, MeshError};
pub use hint::AnyHitHint;
pub use manifest::Manifest;
pub use ray::Ray;
pub use scene::{Hit, Scene, SceneGeometry};
