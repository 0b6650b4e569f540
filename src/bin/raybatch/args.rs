//! The command line.

use std::num::{NonZeroU32, NonZeroUsize};
use std::path::PathBuf;

use clap::{Args, Parser, Subcommand, ValueEnum};

#[derive(Debug, Parser)]
#[command(
    name = "raybatch",
    version,
    about = "Render folders of JSON scene manifests to PPM/PFM images"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Render manifests: each PATH is a manifest, or a folder whose *.json files are
    /// rendered in sorted order. A failed job is reported and the others still run.
    Render(RenderArgs),
    /// Compare image A with the reference B (PPM or PFM, same size): differing pixels, max
    /// abs difference, RMSE, PSNR, and for depth renders the hit mask and relative depth
    /// error. Exits 1 when a limit is exceeded.
    Compare(CompareArgs),
    /// Trace every camera ray of each manifest with raybatch and with Embree (robust) and
    /// compare the closest hits: hit agreement, depth error, trace times. Needs a build
    /// with `--features embree`. Exits 1 when a limit is exceeded or a job fails.
    Verify(VerifyArgs),
    /// Measure trace throughput (closest and any hit, per thread count), build and load
    /// times, memory and whole jobs; with `--embree`, the same rays through Embree.
    Bench(BenchArgs),
    /// Run the stress suite: scale and translation sweeps, tiny far spheres, rays starting
    /// on surfaces, grazing rays, leaks through shared edges, needles, degenerate
    /// triangles, tiny direction components, interval ends, non-finite input; each ray
    /// checked against an independent reference. Prints wrong-ray counts per case and
    /// exits 1 if any ray is wrong. With `--accuracy DIR`, also measures run time against
    /// error for each speed/accuracy choice and writes DIR/accuracy.md with SVG plots.
    Stress(StressArgs),
}

#[derive(Debug, Args)]
pub struct StressArgs {
    /// Fewer rays per case (a smoke test).
    #[arg(long)]
    pub quick: bool,
    /// Print JSON instead of a Markdown table.
    #[arg(long)]
    pub json: bool,
    /// Also write DIR/accuracy.md and its plots (e.g. `--accuracy docs`).
    #[arg(long, value_name = "DIR")]
    pub accuracy: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Smaller images and fewer runs (a smoke test, not figures to quote).
    #[arg(long)]
    pub quick: bool,
    /// Folder with stanford-bunny.obj, nefertiti.obj and ogre.obj (e.g. ../shared/models).
    #[arg(long, value_name = "DIR")]
    pub models: Option<PathBuf>,
    /// Thread counts to trace with.
    #[arg(long, value_name = "N,...", value_delimiter = ',', default_values_t = [1, 2])]
    pub threads: Vec<usize>,
    /// Only the scenes whose names contain one of these words.
    #[arg(long, value_name = "NAME,...", value_delimiter = ',')]
    pub only: Vec<String>,
    /// Trace the same rays with Embree too (needs `--features embree`).
    #[arg(long)]
    pub embree: bool,
    /// Have our packets test leaves eight rays at a time even where the CPU has AVX-512,
    /// to compare the two widths (trace rows only).
    #[arg(long)]
    pub eight_lane_packets: bool,
    /// Print JSON instead of Markdown tables.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Manifests or folders of manifests.
    #[arg(required = true, value_name = "PATH")]
    pub paths: Vec<PathBuf>,
    /// Write every image into DIR (under its output file name) instead of beside its
    /// manifest.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Worker threads (default: all cores). The images do not depend on it.
    #[arg(long, value_name = "N")]
    pub threads: Option<NonZeroUsize>,
    /// Write one JSON object per job to FILE, one per line (timings, counts, errors); an
    /// existing FILE is replaced.
    #[arg(long, value_name = "FILE")]
    pub stats: Option<PathBuf>,
    /// The tracer: raybatch's own, or the Embree reference (`--features embree` builds).
    #[arg(long, value_enum, default_value_t = BackendArg::Raybatch)]
    pub backend: BackendArg,
    /// Print only errors and warnings.
    #[arg(long, short)]
    pub quiet: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum BackendArg {
    Raybatch,
    Embree,
}

/// Limits shared by `compare` and `verify`; a figure past its limit fails the command.
#[derive(Debug, Args)]
pub struct DepthLimits {
    /// Largest fraction of samples where exactly one side hits.
    #[arg(long, value_name = "F")]
    pub max_mask_fraction: Option<f64>,
    /// Largest 99th-percentile relative depth error.
    #[arg(long, value_name = "R")]
    pub max_depth_p99: Option<f64>,
    /// Largest 99.9th-percentile relative depth error.
    #[arg(long, value_name = "R")]
    pub max_depth_p999: Option<f64>,
    /// Largest relative depth error.
    #[arg(long, value_name = "R")]
    pub max_depth_error: Option<f64>,
}

#[derive(Debug, Args)]
pub struct CompareArgs {
    /// The image under test.
    pub a: PathBuf,
    /// The reference image.
    pub b: PathBuf,
    /// Also compare as depth renders (a pixel equal to the background is a miss). Implied
    /// when both images are PFM with equal channels everywhere.
    #[arg(long)]
    pub depth: bool,
    /// The background of depth renders, one value or three (default 0).
    #[arg(long, value_name = "V", num_args = 1..=3, value_delimiter = ',', allow_negative_numbers = true)]
    pub background: Vec<f64>,
    /// Largest number of differing pixels.
    #[arg(long, value_name = "N")]
    pub max_differing: Option<u64>,
    /// Largest absolute difference of any channel (in the images' units).
    #[arg(long, value_name = "X")]
    pub max_abs: Option<f64>,
    /// Smallest PSNR, in dB.
    #[arg(long, value_name = "DB")]
    pub min_psnr: Option<f64>,
    #[command(flatten)]
    pub depth_limits: DepthLimits,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct VerifyArgs {
    /// Manifests or folders of manifests.
    #[arg(required = true, value_name = "PATH")]
    pub paths: Vec<PathBuf>,
    /// Worker threads for both tracers (default: all cores).
    #[arg(long, value_name = "N")]
    pub threads: Option<NonZeroUsize>,
    /// Passes: each traces every ray with ours, one of Embree's ways (streams, single
    /// rays), ours again and Embree's other way. The trace times reported are each way's
    /// median pass. One pass times cold caches and one spell of the machine: on small
    /// images, take several.
    #[arg(long, value_name = "N", default_value = "1")]
    pub passes: NonZeroU32,
    /// Largest fraction of rays where exactly one tracer hits.
    #[arg(long, value_name = "F", default_value_t = 1e-4)]
    pub max_mask_fraction: f64,
    /// Largest 99.9th-percentile relative depth error.
    #[arg(long, value_name = "R", default_value_t = 1e-5)]
    pub max_depth_p999: f64,
    /// Largest 99th-percentile relative depth error.
    #[arg(long, value_name = "R")]
    pub max_depth_p99: Option<f64>,
    /// Largest relative depth error.
    #[arg(long, value_name = "R")]
    pub max_depth_error: Option<f64>,
    /// Print one JSON object per manifest instead of text.
    #[arg(long)]
    pub json: bool,
}
