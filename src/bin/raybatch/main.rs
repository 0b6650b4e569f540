//! The `raybatch` command: a thin layer over the library's batch runner that parses the
//! command line, reports each job, and sets the exit status at the end.

mod args;

use std::io::Write;
use std::process::ExitCode;

use anyhow::Context;
use clap::Parser;

use args::{Cli, Command, RenderArgs};
use raybatch::job::{Batch, JobOptions, manifests_in};

/// Exit status for a bad command line (clap uses the same for its own errors).
const USAGE: u8 = 2;

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Render(args) => render(args),
    };
    match result {
        Ok(code) => code,
        Err(error) => {
            eprintln!("raybatch: {}", one_line(&format!("{error:#}")));
            ExitCode::from(USAGE)
        }
    }
}

/// `raybatch render`: every job runs even when some fail; 0 when all succeeded, else 1.
/// Errors returned here stop the command before any job runs (exit status 2).
fn render(args: RenderArgs) -> anyhow::Result<ExitCode> {
    let mut pool = rayon::ThreadPoolBuilder::new();
    if let Some(threads) = args.threads {
        pool = pool.num_threads(threads.get());
    }
    let pool = pool.build().context("cannot start the worker threads")?;
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the output folder {}", dir.display()))?;
    }
    let mut stats = match &args.stats {
        Some(path) => Some(std::io::BufWriter::new(
            std::fs::File::create(path)
                .with_context(|| format!("cannot create the stats file {}", path.display()))?,
        )),
        None => None,
    };

    let mut failures = 0usize;
    let mut jobs = Vec::new();
    for path in &args.paths {
        match manifests_in(path) {
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

    let bar = progress_bar(args.quiet);
    let mut batch = Batch::new(JobOptions {
        out_dir: args.out.clone(),
    });
    let job_count = jobs.len();
    for (i, manifest) in jobs.iter().enumerate() {
        bar.reset();
        bar.set_length(0);
        bar.set_prefix(format!("[{}/{job_count}]", i + 1));
        bar.set_message(manifest.display().to_string());
        let report = pool.install(|| batch.run(manifest, &|pixels| bar.inc(pixels)));
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
                println!(
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
    Ok(if failures == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
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

/// Messages are printed one per line, whatever a lower layer put in them.
fn one_line(message: &str) -> String {
    message.split_whitespace().collect::<Vec<_>>().join(" ")
}
