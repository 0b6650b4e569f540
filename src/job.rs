//! Jobs and batches: one manifest in, one image out, and a report either way.
//!
//! A [`Batch`] runs jobs one after another (each renders on all threads), shares mesh files
//! between them (and the triangle tree, while consecutive jobs place the same meshes the
//! same way), and refuses to let two jobs write the same file. A failed job writes
//! nothing and does not stop the batch.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use serde_json::json;

use crate::bvh::BuildPreset;
use crate::error::{Error, JobError};
use crate::manifest::Manifest;
use crate::mesh::MeshCache;
use crate::render;
use crate::scene::{MeshPlacement, Scene, SceneGeometry, Tracer, TriangleTree};

/// Settings shared by every job of a batch.
#[derive(Debug, Clone, Default)]
pub struct JobOptions {
    /// Write every output as `DIR/<file name of its output>` instead of where the manifest
    /// says.
    pub out_dir: Option<PathBuf>,
    /// Which tracer answers the rays.
    pub backend: Backend,
}

/// The tracer behind a job's rays.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Backend {
    /// raybatch's own BVH and intersection tests.
    #[default]
    Raybatch,
    /// Embree 3 in robust mode, the reference (needs the `embree` cargo feature).
    Embree,
}

impl Backend {
    pub fn name(self) -> &'static str {
        match self {
            Backend::Raybatch => "raybatch",
            Backend::Embree => "embree",
        }
    }

    /// Whether this build can use the backend.
    pub fn available(self) -> bool {
        match self {
            Backend::Raybatch => true,
            Backend::Embree => cfg!(feature = "embree"),
        }
    }
}

/// What happened to one job. Figures that were not reached are `None`.
#[derive(Debug)]
pub struct JobReport {
    pub manifest: PathBuf,
    pub output: Option<PathBuf>,
    pub error: Option<JobError>,
    /// Things skipped on the way that the user should know about.
    pub warnings: Vec<String>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub spp: Option<u32>,
    pub integrator: Option<&'static str>,
    pub backend: &'static str,
    pub triangles: Option<usize>,
    pub spheres: Option<usize>,
    pub planes: Option<usize>,
    /// Whether the triangle tree was the previous job's (same meshes, same transforms).
    pub triangle_tree_reused: bool,
    /// The build preset of the triangle tree ([`BuildPreset::name`]; the previous job's
    /// when reused); `None` without triangles or with the Embree backend.
    pub triangle_tree_preset: Option<&'static str>,
    /// Seconds reading the manifest and meshes, building trees, rendering, writing.
    pub load_s: f64,
    pub build_s: f64,
    pub render_s: f64,
    pub write_s: f64,
}

impl JobReport {
    fn new(manifest: &Path) -> JobReport {
        JobReport {
            manifest: manifest.to_path_buf(),
            output: None,
            error: None,
            warnings: Vec::new(),
            width: None,
            height: None,
            spp: None,
            integrator: None,
            backend: Backend::Raybatch.name(),
            triangles: None,
            spheres: None,
            planes: None,
            triangle_tree_reused: false,
            triangle_tree_preset: None,
            load_s: 0.0,
            build_s: 0.0,
            render_s: 0.0,
            write_s: 0.0,
        }
    }

    pub fn ok(&self) -> bool {
        self.error.is_none()
    }

    /// Camera rays traced (pixels × samples).
    pub fn camera_rays(&self) -> Option<u64> {
        Some(u64::from(self.width?) * u64::from(self.height?) * u64::from(self.spp?))
    }

    /// One line of `--stats` output.
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "manifest": self.manifest.display().to_string(),
            "output": self.output.as_ref().map(|p| p.display().to_string()),
            "ok": self.ok(),
            "error": self.error.as_ref().map(|e| e.error.to_string()),
            "integrator": self.integrator,
            "backend": self.backend,
            "triangles": self.triangles,
            "spheres": self.spheres,
            "planes": self.planes,
            "triangle_tree_reused": self.triangle_tree_reused,
            "triangle_tree_preset": self.triangle_tree_preset,
            "width": self.width,
            "height": self.height,
            "spp": self.spp,
            "camera_rays": self.camera_rays(),
            "load_s": self.load_s,
            "build_s": self.build_s,
            "render_s": self.render_s,
            "write_s": self.write_s,
            "warnings": self.warnings,
        })
    }
}

/// Runs jobs and remembers what they share.
#[derive(Debug, Default)]
pub struct Batch {
    options: JobOptions,
    meshes: MeshCache,
    /// Output files written so far, and the manifest that wrote each.
    written: HashMap<PathBuf, PathBuf>,
    /// The last triangle tree built and the meshes it was built from, reused while jobs
    /// place the same meshes the same way (only the last, so memory stays one scene's).
    last_tree: Option<(Vec<MeshPlacement>, Arc<TriangleTree>)>,
    tree_builds: usize,
}

impl Batch {
    pub fn new(options: JobOptions) -> Batch {
        Batch {
            options,
            ..Batch::default()
        }
    }

    /// Mesh files read so far.
    pub fn meshes(&self) -> &MeshCache {
        &self.meshes
    }

    /// Triangle trees built so far (jobs that reuse the previous job's do not count).
    pub fn triangle_tree_builds(&self) -> usize {
        self.tree_builds
    }

    /// The scene of `geometry`: around `reused` (the previous job's triangle tree, when
    /// it has the same triangles, which may then be left unplaced), or with a new tree.
    fn build_scene(
        &mut self,
        geometry: &SceneGeometry,
        camera_rays: u64,
        reused: Option<Arc<TriangleTree>>,
        report: &mut JobReport,
    ) -> Scene {
        // Spheres keep the default: reinsertion did not speed up a sphere field's tracing
        // (DEVELOPERS.md, "Build").
        let spheres = BuildPreset::default();
        if let Some(tree) = reused {
            report.triangle_tree_reused = true;
            report.triangle_tree_preset = Some(tree.preset().name());
            return Scene::build_around(geometry, spheres, tree);
        }
        if geometry.triangles.is_empty() {
            // Nothing to build, and the last tree stays for the jobs after this one.
            return Scene::build_with(geometry, spheres);
        }
        // Drop the old tree before building the new one, so two are never held at once.
        self.last_tree = None;
        let scene = Scene::build_for_rays(geometry, camera_rays);
        report.triangle_tree_preset = Some(scene.triangle_tree().preset().name());
        self.tree_builds += 1;
        // Kept for the next job only while its meshes are (not after the last job).
        if !geometry.sources.is_empty() {
            self.last_tree = Some((geometry.sources.clone(), Arc::clone(scene.triangle_tree())));
        }
        scene
    }

    /// The previous job's triangle tree, if `geometry` has the same triangles.
    fn reusable_tree(&self, geometry: &SceneGeometry) -> Option<Arc<TriangleTree>> {
        let (sources, tree) = self.last_tree.as_ref()?;
        geometry
            .same_triangles_as(sources)
            .then(|| Arc::clone(tree))
    }

    /// Renders the manifest at `path`. `progress` receives finished pixel counts.
    pub fn run(&mut self, path: &Path, progress: &(dyn Fn(u64) + Sync)) -> JobReport {
        self.run_job(path, progress, false)
    }

    /// [`Batch::run`] for the batch's last job: no job after it can share its meshes, so
    /// once its triangles are placed the meshes read so far are let go, and its tree is
    /// built without them in memory (a million-triangle OBJ's vertices and faces are 18 MB).
    /// The batch can still run jobs after it; they read their meshes again.
    pub fn run_last(&mut self, path: &Path, progress: &(dyn Fn(u64) + Sync)) -> JobReport {
        self.run_job(path, progress, true)
    }

    fn run_job(&mut self, path: &Path, progress: &(dyn Fn(u64) + Sync), last: bool) -> JobReport {
        let mut report = JobReport::new(path);
        report.backend = self.options.backend.name();
        if let Err(error) = self.run_inner(path, &mut report, progress, last) {
            report.error = Some(JobError {
                manifest: path.to_path_buf(),
                error,
            });
        }
        report
    }

    fn run_inner(
        &mut self,
        path: &Path,
        report: &mut JobReport,
        progress: &(dyn Fn(u64) + Sync),
        last: bool,
    ) -> Result<(), Error> {
        let start = Instant::now();
        let manifest = Manifest::load(path)?;
        report.width = Some(manifest.width);
        report.height = Some(manifest.height);
        report.spp = Some(manifest.sampler.spp);
        report.integrator = Some(manifest.integrator.name());
        render::check_supported(&manifest)?;

        let output = self.output_path(&manifest);
        report.output = Some(output.clone());
        let key = output_key(&output);
        if let Some(other) = self.written.get(&key) {
            return Err(Error::OutputClash {
                path: output,
                other: other.clone(),
            });
        }

        let mut geometry = SceneGeometry::load_unplaced(&manifest, &mut self.meshes)?;
        // Triangles the previous job's tree was built from need no placing again.
        let reused = match self.options.backend {
            Backend::Raybatch => self.reusable_tree(&geometry),
            Backend::Embree => None,
        };
        if reused.is_none() {
            geometry.place_triangles(&manifest)?;
            if last {
                // Placed, the triangles need their files no more, nor does any later job.
                geometry.sources.clear();
                self.meshes = MeshCache::default();
                self.last_tree = None;
            }
        }
        report.warnings = geometry.warnings.clone();
        report.load_s = start.elapsed().as_secs_f64();
        match self.options.backend {
            Backend::Raybatch => finish(
                |g, report| Ok(self.build_scene(g, manifest.camera_rays(), reused, report)),
                geometry,
                &manifest,
                &output,
                report,
                progress,
            )?,
            Backend::Embree => {
                #[cfg(feature = "embree")]
                finish(
                    |g, _| {
                        crate::embree::EmbreeScene::build(g)
                            .map_err(|e| Error::Backend(e.to_string()))
                    },
                    geometry,
                    &manifest,
                    &output,
                    report,
                    progress,
                )?;
                #[cfg(not(feature = "embree"))]
                return Err(Error::Backend(
                    "this build has no Embree backend (build with `--features embree`)".to_string(),
                ));
            }
        }
        self.written.insert(key, path.to_path_buf());
        Ok(())
    }

    /// Where this job's image goes: the manifest's `output` (resolved against its folder),
    /// or with `out_dir` that file's name inside `out_dir`.
    pub fn output_path(&self, manifest: &Manifest) -> PathBuf {
        match &self.options.out_dir {
            Some(dir) => dir.join(manifest.output.file_name().unwrap_or_default()),
            None => manifest.output.clone(),
        }
    }
}

/// Builds the tracer, renders and writes the image, recording the times in `report`.
fn finish<T: Tracer>(
    build: impl FnOnce(&SceneGeometry, &mut JobReport) -> Result<T, Error>,
    geometry: SceneGeometry,
    manifest: &Manifest,
    output: &Path,
    report: &mut JobReport,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<(), Error> {
    let start = Instant::now();
    let scene = build(&geometry, report)?;
    // The scene holds its own copies: the placed triangles are not needed while rendering.
    drop(geometry);
    let counts = scene.counts();
    report.triangles = Some(counts.triangles);
    report.spheres = Some(counts.spheres);
    report.planes = Some(counts.planes);
    report.build_s = start.elapsed().as_secs_f64();

    let start = Instant::now();
    let image = render::render(&scene, manifest, progress)?;
    report.render_s = start.elapsed().as_secs_f64();
    drop(scene);

    let start = Instant::now();
    image.write(output).map_err(|source| Error::Output {
        path: output.to_path_buf(),
        source,
    })?;
    report.write_s = start.elapsed().as_secs_f64();
    Ok(())
}

/// A path that names the same file however it was spelled (`a/../b`, `./b`, `b`).
fn output_key(path: &Path) -> PathBuf {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut key = PathBuf::new();
    for component in absolute.components() {
        match component {
            std::path::Component::ParentDir => {
                key.pop();
            }
            std::path::Component::CurDir => {}
            other => key.push(other),
        }
    }
    key
}

/// The manifests a command-line `PATH` names: the file itself, or every `*.json` directly
/// inside a folder, in sorted order. Folders named `*.json` are not manifests; a `*.json`
/// that cannot be looked at (a dangling link) is, so that its job fails and says why.
pub fn manifests_in(path: &Path) -> std::io::Result<Vec<PathBuf>> {
    if !path.is_dir() {
        return Ok(vec![path.to_path_buf()]);
    }
    let mut manifests = Vec::new();
    for entry in std::fs::read_dir(path)? {
        let entry = entry?;
        let file = entry.path();
        let readable_kind = std::fs::metadata(&file).map_or(true, |m| m.is_file());
        if file.extension().is_some_and(|e| e == "json") && readable_kind {
            manifests.push(file);
        }
    }
    manifests.sort();
    Ok(manifests)
}
