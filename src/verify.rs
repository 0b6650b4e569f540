//! `raybatch verify`: every camera ray of a manifest (every pixel, every sample) traced by
//! raybatch (through the tree a render of the manifest builds) and by the Embree
//! reference, closest hit only, and the distances compared:
//! hit-mask agreement, relative depth error, and the trace times side by side: ours,
//! Embree's coherent streams and Embree's single rays (`rtcIntersect1`), the rays sent as
//! the renderer sends them and made before the clocks start; with several passes, the
//! median time of a whole pass, the tracers taking turns.

use std::num::NonZeroU32;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use serde_json::json;

use crate::bench::median_of;
use crate::compare::DepthComparison;
use crate::embree::EmbreeScene;
use crate::error::{Error, JobError};
use crate::manifest::Manifest;
use crate::mesh::MeshCache;
use crate::ray::Ray;
use crate::render::{GROUP, PACKET_SIDE, TILE, View, groups};
use crate::sampler::MOST_LENS_CELLS;
use crate::scene::{Hit, Scene, SceneGeometry, Tracer};

/// The outcome of verifying one manifest.
#[derive(Debug, Clone)]
pub struct Verification {
    pub manifest: PathBuf,
    pub triangles: usize,
    pub spheres: usize,
    pub rays: u64,
    /// The preset of our triangle tree ([`crate::bvh::BuildPreset::name`]), as a render
    /// of the manifest chooses it; `None` without triangles.
    pub triangle_tree_preset: Option<&'static str>,
    pub depth: DepthComparison,
    /// Seconds building each tree (ours as a render of the manifest builds it).
    pub build_raybatch_s: f64,
    pub build_embree_s: f64,
    /// Seconds tracing all rays (closest hit), on the current rayon pool: with several
    /// passes, the median pass. Ours as a render traces them, Embree's by coherent streams
    /// (`rtcIntersect1M` over each group), and Embree's one ray at a time
    /// (`rtcIntersect1`, as a program calling Embree per pixel does).
    pub trace_raybatch_s: f64,
    pub trace_embree_s: f64,
    pub trace_embree_single_s: f64,
    /// Passes over every ray ([`VerifyOptions::passes`]).
    pub passes: u32,
}

/// How [`verify_with`] times the tracers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VerifyOptions {
    /// Passes over every ray. A pass traces each round of rays with ours, one of Embree's
    /// ways (streams, single rays), ours again and Embree's other way, which goes first
    /// alternating, so that no way follows another through the same tree. A way's time is
    /// its median pass (ours: the mean of its two traces in each), and the answers
    /// compared are the first pass's (the tracers are deterministic). One pass (the
    /// default) times cold caches and a single spell of the machine; on a small image that
    /// is a few milliseconds, which a busy neighbour or a thread's wake-up moves by a tenth
    /// or more.
    pub passes: NonZeroU32,
}

impl Default for VerifyOptions {
    fn default() -> VerifyOptions {
        VerifyOptions {
            passes: NonZeroU32::MIN,
        }
    }
}

impl Verification {
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "manifest": self.manifest.display().to_string(),
            "triangles": self.triangles,
            "spheres": self.spheres,
            "rays": self.rays,
            "triangle_tree_preset": self.triangle_tree_preset,
            "depth": self.depth.to_json(),
            "build_raybatch_s": self.build_raybatch_s,
            "build_embree_s": self.build_embree_s,
            "trace_raybatch_s": self.trace_raybatch_s,
            "trace_embree_s": self.trace_embree_s,
            "trace_embree_single_s": self.trace_embree_single_s,
            "passes": self.passes,
        })
    }

    /// One line for people.
    pub fn summary(&self) -> String {
        let rate = |s: f64| self.rays as f64 / s.max(1e-12) / 1e6;
        let passes = match self.passes {
            1 => String::new(),
            n => format!(" (median of {n} passes)"),
        };
        format!(
            "{}: {} rays; {}; trace{passes} raybatch {:.3} s ({:.2} Mrays/s), embree streams {:.3} s ({:.2} Mrays/s), embree single rays {:.3} s ({:.2} Mrays/s)",
            self.manifest.display(),
            self.rays,
            self.depth.summary(),
            self.trace_raybatch_s,
            rate(self.trace_raybatch_s),
            self.trace_embree_s,
            rate(self.trace_embree_s),
            self.trace_embree_single_s,
            rate(self.trace_embree_single_s),
        )
    }
}

/// Verifies the manifest at `path` (meshes through `cache`), one pass of each tracer.
pub fn verify(path: &Path, cache: &mut MeshCache) -> Result<Verification, JobError> {
    verify_with(path, cache, VerifyOptions::default())
}

/// [`verify`] with `options`.
pub fn verify_with(
    path: &Path,
    cache: &mut MeshCache,
    options: VerifyOptions,
) -> Result<Verification, JobError> {
    verify_inner(path, cache, options).map_err(|error| JobError {
        manifest: path.to_path_buf(),
        error,
    })
}

fn verify_inner(
    path: &Path,
    cache: &mut MeshCache,
    options: VerifyOptions,
) -> Result<Verification, Error> {
    let manifest = Manifest::load(path)?;
    let geometry = SceneGeometry::load(&manifest, cache)?;
    let (triangles, spheres) = (geometry.triangles.len(), geometry.spheres.len());

    // The tree a render of the manifest builds: its preset follows the camera rays.
    let start = Instant::now();
    let ours = Scene::build_for_rays(&geometry, manifest.camera_rays());
    let build_raybatch_s = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let reference = EmbreeScene::build(&geometry).map_err(|e| Error::Backend(e.to_string()))?;
    let build_embree_s = start.elapsed().as_secs_f64();

    let view = View::new(&manifest);
    let traced = trace_all(&ours, &reference, &view, &manifest, options.passes.get());
    let (ours_t, reference_t) = (traced.ours_t, traced.reference_t);
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
        triangle_tree_preset: (triangles > 0).then(|| ours.triangle_tree().preset().name()),
        depth,
        build_raybatch_s,
        build_embree_s,
        trace_raybatch_s: traced.seconds[Way::Ours as usize],
        trace_embree_s: traced.seconds[Way::Streams as usize],
        trace_embree_single_s: traced.seconds[Way::Single as usize],
        passes: options.passes.get(),
    })
}

/// Rays made and traced at a time, about: their rays and hits take tens of megabytes.
const RAYS_PER_ROUND: usize = 1 << 19;
/// Pieces of work per round (a band of rows, or part of one), so that both threads have
/// several.
const PIECES_PER_ROUND: usize = 16;

/// What [`trace_all`] returns.
struct Traced {
    /// The closest-hit distance of every camera ray (NaN for a miss), ours and Embree's
    /// streams', the same rays in the same order.
    ours_t: Vec<f64>,
    reference_t: Vec<f64>,
    /// The median pass's seconds: ours, Embree's streams, Embree's single rays.
    seconds: [f64; TIMED],
}

/// The ways of tracing timed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Way {
    /// Our batch queries, as a render makes them.
    Ours,
    /// Embree's coherent streams.
    Streams,
    /// Embree's single rays.
    Single,
}

/// How many [`Way`]s there are.
const TIMED: usize = 3;

/// The ways in the order pass `pass` traces them: ours before each of Embree's, so that
/// every trace follows the other tracer's. A way traced right after another through the
/// same tree finds that tree's upper levels in the core's own cache: Embree's single rays
/// ran 3–7% faster after its streams than after ours. Which of Embree's ways goes first
/// alternates.
fn turns(pass: usize) -> [Way; 4] {
    match pass % 2 {
        0 => [Way::Ours, Way::Streams, Way::Ours, Way::Single],
        _ => [Way::Ours, Way::Single, Way::Ours, Way::Streams],
    }
}

/// Traces every camera ray of the view with ours and with the reference. The rays go as the
/// renderer sends them, the same sample of each group of pixels together
/// ([`Tracer::closest_hits`]: our packets, Embree's coherent streams), and the reference
/// also traces them one at a time ([`Tracer::closest_hit`]: `rtcIntersect1`). They go in
/// rounds: each round's rays are made first, then traced `passes` times, each pass ours,
/// one of Embree's ways, ours again and Embree's other way (which goes first alternating),
/// our pass time the mean of our two; only the tracing is timed, and the distances kept
/// are the first pass's.
fn trace_all<A: Tracer, B: Tracer>(
    ours: &A,
    reference: &B,
    view: &View,
    manifest: &Manifest,
    passes: u32,
) -> Traced {
    let (width, height, spp) = (manifest.width, manifest.height, view.spp());
    // Pieces: a band's groups from one index to another, at most a piece's share of a
    // round's rays (but one group at least).
    let rays_per_group = GROUP * spp as usize;
    let groups_per_piece = (RAYS_PER_ROUND / PIECES_PER_ROUND / rays_per_group).max(1);
    let pieces: Vec<(u32, usize, usize)> = (0..height.div_ceil(TILE))
        .flat_map(|band| {
            let rows = TILE.min(height - band * TILE);
            let count = (width.div_ceil(PACKET_SIDE) * rows.div_ceil(PACKET_SIDE)) as usize;
            (0..count)
                .step_by(groups_per_piece)
                .map(move |first| (band, first, (first + groups_per_piece).min(count)))
        })
        .collect();
    let (mut ours_t, mut reference_t) = (Vec::new(), Vec::new());
    // Each pass's seconds each way, summed over the rounds.
    let mut seconds = vec![[0.0; TIMED]; passes as usize];
    for round in pieces.chunks(PIECES_PER_ROUND) {
        let rays: Vec<Vec<Ray>> = round
            .par_iter()
            .map(|&(band, first, end)| {
                let y0 = band * TILE;
                let rows = TILE.min(height - y0);
                let mut rays = Vec::with_capacity((end - first) * rays_per_group);
                let mut group = [view.ray(0, 0, 0); GROUP];
                let mut pixels = [(0, 0); GROUP];
                let mut shuffles = [[0; MOST_LENS_CELLS as usize]; GROUP];
                for tile in groups(width, rows).skip(first).take(end - first) {
                    let n = tile.pixels(&mut pixels);
                    let (hashes, shuffles) = view.group_numbers(&pixels[..n], y0, &mut shuffles);
                    for s in 0..spp {
                        let numbers = (&pixels[..n], y0, &hashes, shuffles);
                        view.rays_hashed(numbers, s, &mut group[..n]);
                        rays.extend_from_slice(&group[..n]);
                    }
                }
                rays
            })
            .collect();
        for (pass, pass_seconds) in seconds.iter_mut().enumerate() {
            // The first pass's distances are the ones compared.
            let first = pass == 0;
            for (turn, way) in turns(pass).into_iter().enumerate() {
                pass_seconds[way as usize] += match way {
                    // Ours twice a pass: its pass time is the mean of the two.
                    Way::Ours => {
                        let out = (first && turn == 0).then_some(&mut ours_t);
                        0.5 * trace_round(&rays, out, |rays, hits| ours.closest_hits(rays, hits))
                    }
                    Way::Streams => {
                        trace_round(&rays, first.then_some(&mut reference_t), |rays, hits| {
                            reference.closest_hits(rays, hits)
                        })
                    }
                    Way::Single => trace_round(&rays, None, |rays, hits| {
                        for (ray, hit) in rays.iter().zip(hits) {
                            *hit = reference.closest_hit(ray);
                        }
                    }),
                };
            }
        }
    }
    Traced {
        ours_t,
        reference_t,
        seconds: std::array::from_fn(|way| median_of(seconds.iter().map(|s| s[way]).collect())),
    }
}

/// Traces a round's rays a group at a time with `trace`, each piece on its own thread, and
/// appends their distances to `t` if given; returns the seconds spent tracing.
fn trace_round(
    round: &[Vec<Ray>],
    t: Option<&mut Vec<f64>>,
    trace: impl Fn(&[Ray], &mut [Option<Hit>]) + Sync,
) -> f64 {
    let mut hits: Vec<Vec<Option<Hit>>> = round.iter().map(|rays| vec![None; rays.len()]).collect();
    let start = Instant::now();
    hits.par_iter_mut().zip(round).for_each(|(hits, rays)| {
        for (rays, hits) in rays.chunks(GROUP).zip(hits.chunks_mut(GROUP)) {
            trace(rays, hits);
        }
    });
    let seconds = start.elapsed().as_secs_f64();
    if let Some(t) = t {
        t.extend(
            hits.iter()
                .flatten()
                .map(|hit| hit.map_or(f64::NAN, |hit| hit.t)),
        );
    }
    seconds
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_way_follows_another_through_the_same_tree() {
        let order: Vec<Way> = (0..6).flat_map(turns).collect();
        for pair in order.windows(2) {
            let embree = |way: Way| way != Way::Ours;
            assert!(!(embree(pair[0]) && embree(pair[1])), "{order:?}");
        }
        for pass in 0..6 {
            let ways = turns(pass);
            for way in [Way::Ours, Way::Streams, Way::Single] {
                let count = ways.iter().filter(|&&w| w == way).count();
                assert_eq!(count, if way == Way::Ours { 2 } else { 1 }, "{ways:?}");
            }
            // Embree's first way alternates.
            assert_ne!(turns(pass)[1], turns(pass + 1)[1]);
        }
    }
}
