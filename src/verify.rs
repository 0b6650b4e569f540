//! `raybatch verify`: every camera ray of a manifest (every pixel, every sample) traced by
//! raybatch and by the Embree reference, closest hit only, and the distances compared:
//! hit-mask agreement, relative depth error, and the two trace times side by side.

use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use serde_json::json;

use crate::compare::DepthComparison;
use crate::embree::EmbreeScene;
use crate::error::{Error, JobError};
use crate::manifest::Manifest;
use crate::mesh::MeshCache;
use crate::render::View;
use crate::scene::{Scene, SceneGeometry, Tracer};

/// The outcome of verifying one manifest.
#[derive(Debug, Clone)]
pub struct Verification {
    pub manifest: PathBuf,
    pub triangles: usize,
    pub spheres: usize,
    pub rays: u64,
    pub depth: DepthComparison,
    /// Seconds building each tree.
    pub build_raybatch_s: f64,
    pub build_embree_s: f64,
    /// Seconds tracing all rays (closest hit), on the current rayon pool.
    pub trace_raybatch_s: f64,
    pub trace_embree_s: f64,
}

impl Verification {
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "manifest": self.manifest.display().to_string(),
            "triangles": self.triangles,
            "spheres": self.spheres,
            "rays": self.rays,
            "depth": self.depth.to_json(),
            "build_raybatch_s": self.build_raybatch_s,
            "build_embree_s": self.build_embree_s,
            "trace_raybatch_s": self.trace_raybatch_s,
            "trace_embree_s": self.trace_embree_s,
        })
    }

    /// One line for people.
    pub fn summary(&self) -> String {
        let rate = |s: f64| self.rays as f64 / s.max(1e-12) / 1e6;
        format!(
            "{}: {} rays; {}; trace raybatch {:.3} s ({:.2} Mrays/s), embree {:.3} s ({:.2} Mrays/s)",
            self.manifest.display(),
            self.rays,
            self.depth.summary(),
            self.trace_raybatch_s,
            rate(self.trace_raybatch_s),
            self.trace_embree_s,
            rate(self.trace_embree_s),
        )
    }
}

/// Verifies the manifest at `path` (meshes through `cache`).
pub fn verify(path: &Path, cache: &mut MeshCache) -> Result<Verification, JobError> {
    verify_inner(path, cache).map_err(|error| JobError {
        manifest: path.to_path_buf(),
        error,
    })
}

fn verify_inner(path: &Path, cache: &mut MeshCache) -> Result<Verification, Error> {
    let manifest = Manifest::load(path)?;
    let geometry = SceneGeometry::load(&manifest, cache)?;
    let (triangles, spheres) = (geometry.triangles.len(), geometry.spheres.len());

    let start = Instant::now();
    let ours = Scene::build(&geometry);
    let build_raybatch_s = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let reference = EmbreeScene::build(&geometry).map_err(|e| Error::Backend(e.to_string()))?;
    let build_embree_s = start.elapsed().as_secs_f64();

    let view = View::new(&manifest);
    let (ours_t, trace_raybatch_s) = trace_all(&ours, &view, &manifest);
    let (reference_t, trace_embree_s) = trace_all(&reference, &view, &manifest);
    let as_option = |t: f64| (!t.is_nan()).then_some(t);
    let depth = DepthComparison::from_pairs(
        ours_t
            .iter()
            .zip(&reference_t)
            .map(|(&a, &b)| (as_option(a), as_option(b))),
    );
    Ok(Verification {
        manifest: path.to_path_buf(),
        triangles,
        spheres,
        rays: ours_t.len() as u64,
        depth,
        build_raybatch_s,
        build_embree_s,
        trace_raybatch_s,
        trace_embree_s,
    })
}

/// The closest-hit distance of every camera ray (NaN for a miss), row by row, and the
/// seconds it took.
fn trace_all<T: Tracer>(tracer: &T, view: &View, manifest: &Manifest) -> (Vec<f64>, f64) {
    let (width, spp) = (manifest.width, manifest.sampler.spp);
    let row = width as usize * spp as usize;
    let mut t = vec![f64::NAN; row * manifest.height as usize];
    let start = Instant::now();
    t.par_chunks_mut(row).enumerate().for_each(|(y, out)| {
        for x in 0..width {
            for s in 0..spp {
                let ray = view.ray(x, y as u32, s);
                if let Some(hit) = tracer.closest_hit(&ray) {
                    out[(x * spp + s) as usize] = hit.t;
                }
            }
        }
    });
    (t, start.elapsed().as_secs_f64())
}
