//! The `raybatch` command: a thin layer over the library that parses the command line,
//! reports each job, and sets the exit status at the end (0 all good, 1 a job failed or a
//! limit was exceeded, 2 the command itself could not run as given).

mod args;
mod memory;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, bail};
use clap::Parser;

use args::{BackendArg, BenchArgs, Cli, Command, CompareArgs, RenderArgs, StressArgs, VerifyArgs};
use raybatch::compare::{Limits, compare_images};
use raybatch::job::{Backend, Batch, JobOptions, manifests_in};

/// `println!` for the command's report on standard output, except that a reader gone
/// away (`raybatch compare a.pfm b.pfm | head -1`) changes nothing: the line is dropped,
/// and the work and the exit status stay what they would have been (`println!` panics).
macro_rules! outln {
    ($($arg:tt)*) => { write_out(format_args!("{}\n", format_args!($($arg)*))) };
}

/// `print!` as [`outln!`] does `println!`.
macro_rules! out {
    ($($arg:tt)*) => { write_out(format_args!($($arg)*)) };
}

/// Writes to standard output for [`outln!`] and [`out!`]: a closed pipe is ignored, any
/// other failure reported on standard error.
fn write_out(text: std::fmt::Arguments) {
    let mut stdout = std::io::stdout().lock();
    if let Err(error) = stdout.write_fmt(text).and_then(|()| stdout.flush())
        && error.kind() != std::io::ErrorKind::BrokenPipe
    {
        eprintln!("raybatch: cannot write to standard output: {error}");
    }
}

/// Exit status for a bad command line (clap uses the same for its own errors).
const USAGE: u8 = 2;

fn main() -> ExitCode {
    memory::keep_freed_memory();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Render(args) => render(args),
        Command::Compare(args) => compare(args),
        Command::Verify(args) => verify(args),
        Command::Bench(args) => bench(args),
        Command::Stress(args) => stress(args),
    };
    match result {
        Ok(code) => code,
        Err(error) => {
            eprintln!("raybatch: {}", one_line(&causes(&error)));
            ExitCode::from(USAGE)
        }
    }
}

/// `raybatch render`: every job runs even when some fail.
fn render(args: RenderArgs) -> anyhow::Result<ExitCode> {
    let backend = match args.backend {
        BackendArg::Raybatch => Backend::Raybatch,
        BackendArg::Embree => Backend::Embree,
    };
    if !backend.available() {
        bail!(
            "this build has no Embree backend; rebuild with `cargo build --release --features embree`"
        );
    }
    start_workers(args.threads)?;
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the output folder {}", dir.display()))?;
    }
    // Listed before the stats file is created, and without it: a stats file named
    // `*.json` in a folder being rendered is not a manifest.
    let (jobs, mut failures) = collect_manifests(&args.paths, args.stats.as_deref());
    let mut stats = match &args.stats {
        Some(path) => Some(std::io::BufWriter::new(
            std::fs::File::create(path)
                .with_context(|| format!("cannot create the stats file {}", path.display()))?,
        )),
        None => None,
    };

    let bar = progress_bar(args.quiet);
    let mut batch = Batch::new(JobOptions {
        out_dir: args.out.clone(),
        backend,
    });
    let job_count = jobs.len();
    for (i, manifest) in jobs.iter().enumerate() {
        bar.reset();
        bar.set_length(0);
        bar.set_prefix(format!("[{}/{job_count}]", i + 1));
        bar.set_message(manifest.display().to_string());
        let progress = |pixels| bar.inc(pixels);
        let report = if i + 1 == job_count {
            batch.run_last(manifest, &progress)
        } else {
            batch.run(manifest, &progress)
        };
        if let (Some(w), Some(h)) = (report.width, report.height) {
            bar.set_length(u64::from(w) * u64::from(h));
        }
        for warning in &report.warnings {
            bar.suspend(|| {
                eprintln!(
                    "raybatch: warning: {}: {}",
                    manifest.display(),
                    one_line(warning)
                )
            });
        }
        match &report.error {
            Some(error) => {
                failures += 1;
                bar.suspend(|| eprintln!("raybatch: {}", one_line(&error.to_string())));
            }
            None if !args.quiet => bar.suspend(|| {
                outln!(
                    "{} -> {} ({}x{}, {} spp, {:.3} s)",
                    manifest.display(),
                    report
                        .output
                        .as_ref()
                        .map_or(String::new(), |p| p.display().to_string()),
                    report.width.unwrap_or(0),
                    report.height.unwrap_or(0),
                    report.spp.unwrap_or(0),
                    report.load_s + report.build_s + report.render_s + report.write_s,
                )
            }),
            None => {}
        }
        if let Some(stats) = &mut stats {
            writeln!(stats, "{}", report.to_json())
                .and_then(|()| stats.flush())
                .context("cannot write the stats file")?;
        }
    }
    bar.finish_and_clear();
    Ok(status(failures))
}

/// `raybatch compare A B`.
fn compare(args: CompareArgs) -> anyhow::Result<ExitCode> {
    let a = raybatch::image::read(&args.a)?;
    let b = raybatch::image::read(&args.b)?;
    let background = match args.background.as_slice() {
        [] => [0.0; 3],
        [v] => [*v; 3],
        [r, g, b] => [*r, *g, *b],
        _ => bail!("--background takes one value or three"),
    };
    let gray_pfm = |d: &raybatch::image::Decoded| {
        d.maxval.is_none() && d.pixels.iter().all(|p| p[0] == p[1] && p[1] == p[2])
    };
    let depth = (args.depth || (gray_pfm(&a) && gray_pfm(&b))).then_some(background);
    let comparison = compare_images(&a, &b, depth)
        .map_err(|e| anyhow::anyhow!("{} and {}: {e}", args.a.display(), args.b.display()))?;
    let limits = Limits {
        max_differing: args.max_differing,
        max_abs: args.max_abs,
        min_psnr: args.min_psnr,
        max_mask_fraction: args.depth_limits.max_mask_fraction,
        max_depth_p99: args.depth_limits.max_depth_p99,
        max_depth_p999: args.depth_limits.max_depth_p999,
        max_depth_error: args.depth_limits.max_depth_error,
    };
    let failures = limits.check_image(&comparison);
    if args.json {
        let mut line = comparison.to_json();
        line["a"] = args.a.display().to_string().into();
        line["b"] = args.b.display().to_string().into();
        line["ok"] = failures.is_empty().into();
        line["failures"] = failures.clone().into();
        outln!("{line}");
    } else {
        let c = &comparison;
        let pixels = f64::from(c.width) * f64::from(c.height);
        outln!(
            "{} vs {} ({} x {}): {} differing pixels ({:.4}%), max abs difference {}, RMSE {:.6e}, PSNR {}",
            args.a.display(),
            args.b.display(),
            c.width,
            c.height,
            c.differing,
            100.0 * c.differing as f64 / pixels,
            c.max_abs,
            c.rmse,
            if c.psnr.is_finite() {
                format!("{:.2} dB", c.psnr)
            } else {
                "inf (identical)".to_string()
            },
        );
        if let Some(depth) = &c.depth {
            outln!("depth: {}", depth.summary());
        }
    }
    for failure in &failures {
        eprintln!("raybatch: {}: limit exceeded: {failure}", args.a.display());
    }
    Ok(status(failures.len()))
}

/// `raybatch verify`.
#[cfg(feature = "embree")]
fn verify(args: VerifyArgs) -> anyhow::Result<ExitCode> {
    start_workers(args.threads)?;
    let limits = Limits {
        max_mask_fraction: Some(args.max_mask_fraction),
        max_depth_p99: args.max_depth_p99,
        max_depth_p999: Some(args.max_depth_p999),
        max_depth_error: args.max_depth_error,
        ..Limits::default()
    };
    let (jobs, mut failures) = collect_manifests(&args.paths, None);
    let mut meshes = raybatch::mesh::MeshCache::new();
    let options = raybatch::verify::VerifyOptions {
        passes: args.passes,
    };
    for manifest in &jobs {
        match raybatch::verify::verify_with(manifest, &mut meshes, options) {
            Err(error) => {
                failures += 1;
                eprintln!("raybatch: {}", one_line(&error.to_string()));
            }
            Ok(v) => {
                let exceeded = limits.check_depth(&v.depth);
                if args.json {
                    let mut line = v.to_json();
                    line["ok"] = exceeded.is_empty().into();
                    line["failures"] = exceeded.clone().into();
                    outln!("{line}");
                } else {
                    outln!("{}", v.summary());
                }
                for failure in &exceeded {
                    eprintln!(
                        "raybatch: {}: limit exceeded: {failure}",
                        manifest.display()
                    );
                }
                failures += usize::from(!exceeded.is_empty());
            }
        }
    }
    Ok(status(failures))
}

#[cfg(not(feature = "embree"))]
fn verify(_: VerifyArgs) -> anyhow::Result<ExitCode> {
    bail!(
        "this build has no Embree backend; rebuild with `cargo build --release --features embree`"
    )
}

/// `raybatch bench`: Markdown tables (or JSON) on stdout, with the date, CPU and command.
fn bench(args: BenchArgs) -> anyhow::Result<ExitCode> {
    if args.embree && !raybatch::job::Backend::Embree.available() {
        bail!("--embree needs a build with `--features embree`");
    }
    if args.threads.contains(&0) {
        bail!("--threads takes counts of 1 or more");
    }
    let options = raybatch::bench::BenchOptions {
        quick: args.quick,
        models: args.models.clone(),
        threads: args.threads.clone(),
        only: args.only.clone(),
        embree: args.embree,
        eight_lane_packets: args.eight_lane_packets,
    };
    if let Some(dir) = &args.models {
        if !dir.is_dir() {
            bail!("--models {}: not a folder", dir.display());
        }
        for model in raybatch::bench::SCANNED_MODELS {
            let file = dir.join(format!("{model}.obj"));
            if options.reads_model(model) && !file.is_file() {
                eprintln!(
                    "raybatch: warning: {} not found; its rows are left out",
                    file.display()
                );
            }
        }
    }
    let temp = std::env::temp_dir().join(format!("raybatch-bench-{}", std::process::id()));
    std::fs::create_dir_all(&temp).with_context(|| format!("cannot create {}", temp.display()))?;
    let report = raybatch::bench::run(&options, &temp);
    let _ = std::fs::remove_dir_all(&temp);
    let report = report.map_err(|e| anyhow::anyhow!(e))?;
    if report.scenes.is_empty() && report.jobs.is_empty() {
        bail!(
            "nothing to measure: --only {} names no scene or job the bench can run here",
            args.only.join(",")
        );
    }
    if args.json {
        outln!("{}", report.to_json());
    } else {
        let command: Vec<String> = std::env::args().skip(1).collect();
        outln!("CPU: {}  ", raybatch::bench::cpu_name());
        outln!("Packets: {}  ", raybatch::bench::packet_lanes(&options));
        outln!("Command: `raybatch {}`\n", command.join(" "));
        out!("{}", report.to_markdown());
    }
    Ok(ExitCode::SUCCESS)
}

/// `raybatch stress`: the report on stdout; exit 1 when any ray is wrong.
fn stress(args: StressArgs) -> anyhow::Result<ExitCode> {
    use raybatch::stress::{self, StressOptions};
    let options = if args.quick {
        StressOptions::QUICK
    } else {
        StressOptions::FULL
    };
    let report = stress::run(options);
    if args.json {
        outln!("{}", report.to_json());
    } else {
        out!("{}", report.to_markdown());
    }
    if let Some(dir) = &args.accuracy {
        let written = raybatch::accuracy::write(dir, args.quick)
            .with_context(|| format!("cannot write the accuracy report into {}", dir.display()))?;
        eprintln!("raybatch: wrote {}", written.display());
    }
    Ok(if report.wrong() == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// The manifests named by the command line (folders expanded, duplicates dropped, the
/// `stats` file left out of folders), and how many paths could not be read (each reported
/// on stderr).
fn collect_manifests(paths: &[PathBuf], stats: Option<&Path>) -> (Vec<PathBuf>, usize) {
    let (mut jobs, mut failures) = (Vec::new(), 0);
    let stats = stats.and_then(absolute_file);
    for path in paths {
        let listed = manifests_in(path).map(|mut found| {
            if path.is_dir() && stats.is_some() {
                found.retain(|manifest| absolute_file(manifest) != stats);
            }
            found
        });
        match listed {
            Ok(found) if found.is_empty() => {
                eprintln!(
                    "raybatch: {}: no *.json manifests in this folder",
                    path.display()
                );
                failures += 1;
            }
            Ok(found) => {
                for manifest in found {
                    if !jobs.contains(&manifest) {
                        jobs.push(manifest);
                    }
                }
            }
            Err(error) => {
                eprintln!(
                    "raybatch: {}: {}",
                    path.display(),
                    one_line(&error.to_string())
                );
                failures += 1;
            }
        }
    }
    (jobs, failures)
}

/// `path` made absolute through its folder's real path (the file itself need not exist),
/// so that two names of one file compare equal; `None` if the folder cannot be resolved.
fn absolute_file(path: &Path) -> Option<PathBuf> {
    let folder = match path.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => parent,
        _ => Path::new("."),
    };
    Some(folder.canonicalize().ok()?.join(path.file_name()?))
}

/// Starts the worker threads that every parallel part of a job runs on (`threads` of
/// them, or one per core). Jobs themselves run on the main thread, so that what they do
/// one step at a time (reading a mesh, parts of the tree build) allocates from the main
/// heap rather than a worker's: measured (`build_s` of `raybatch render --stats`), the
/// full-HD job of a million-triangle torus built in 0.25 s instead of 0.29 s.
fn start_workers(threads: Option<std::num::NonZeroUsize>) -> anyhow::Result<()> {
    let mut pool = rayon::ThreadPoolBuilder::new();
    if let Some(threads) = threads {
        pool = pool.num_threads(threads.get());
    }
    pool.build_global()
        .context("cannot start the worker threads")
}

fn status(failures: usize) -> ExitCode {
    if failures == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    }
}

/// A progress bar on stderr, drawn only when stderr is a terminal.
fn progress_bar(quiet: bool) -> indicatif::ProgressBar {
    if quiet {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{prefix} {wide_msg} {percent:>3}% {elapsed}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar
}

/// The error and its causes, `: `-separated, each cause left out when the message before
/// it already ends with it (the library's errors name their cause in their own message).
fn causes(error: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in error.chain() {
        let part = cause.to_string();
        if text.ends_with(&part) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&part);
    }
    text
}

/// Messages are printed one per line, whatever a lower layer put in them.
fn one_line(message: &str) -> String {
    message.split_whitespace().collect::<Vec<_>>().join(" ")
}
