//! `deocc bench`: our speed against a peer on the same data in the same run, written to a report
//! (the harness is `deocc_eval::bench`).

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, Subcommand};
use deocc_eval::bench;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Geometry core against Open3D: kd-tree, nearest neighbours, Chamfer, voxels, normals, ICP,
    /// in alternating rounds (needs `bash scripts/setup-peers.sh`).
    Geometry(GeometryArgs),
    /// Synthetic benchmark speed: views rendered per second at 640x480 with every output written,
    /// and training pairs per second.
    Synth(SynthArgs),
    /// GL-DoT speed: training step, forward, 4-step completions, token scaling (linear against
    /// softmax attention), and the same model in PyTorch timed in the same run.
    Model(ModelArgs),
    /// Peak resident memory of `deocc run` against the number of views.
    Memory(MemoryArgs),
    /// The gRPC service on loopback: overhead against the in-process pipeline (alternating
    /// rounds), serialisation share, a 1M-point cloud's encode + decode, and a load test
    /// (concurrent clients, every status counted, p50 / p99 latency, peak RSS).
    Service(ServiceArgs),
    /// `deocc serve` (this binary, as a child process) under normal traffic mixed with abuse on
    /// loopback: stalled uploads, slow readers, cancels, 1 ms deadlines, oversized and malformed
    /// messages, pathological options. Checks every normal answer, the server's peak memory,
    /// Health back at zero, and that SIGTERM ends it within the grace period; exits non-zero if
    /// any failed.
    Soak(SoakArgs),
}

#[derive(Args)]
pub struct SoakArgs {
    #[arg(long, default_value = "bench/soak.json")]
    json: PathBuf,
    /// How long the traffic runs, seconds.
    #[arg(long, default_value_t = 600.0)]
    seconds: f64,
    /// The server's completers.
    #[arg(long, default_value = "gldot,rules")]
    completer: String,
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=64))]
    clients: u32,
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(0..=64))]
    abusers: u32,
    /// The bound on the server's peak resident memory, MiB.
    #[arg(long, default_value_t = 1536.0)]
    max_rss_mib: f64,
}

#[derive(Args)]
pub struct ServiceArgs {
    #[arg(long, default_value = "bench/service.json")]
    json: PathBuf,
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=256))]
    clients: u32,
    /// Requests per client.
    #[arg(long, default_value_t = 25, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    requests: u32,
    /// Alternating rounds of the overhead comparison.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100))]
    rounds: u32,
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    workers: u32,
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(0..=10_000))]
    queue: u32,
    #[command(flatten)]
    completers: crate::completers::CompleterArgs,
}

#[derive(Args)]
pub struct MemoryArgs {
    #[arg(long, default_value = "bench/memory.json")]
    json: PathBuf,
    /// Numbers of views, comma-separated.
    #[arg(long, default_value = "10,50,100,200,500", value_delimiter = ',')]
    views: Vec<usize>,
    #[arg(long, default_value_t = 640)]
    width: u32,
    #[arg(long, default_value_t = 480)]
    height: u32,
    #[arg(long, default_value = "gldot")]
    completer: String,
}

#[derive(Args)]
pub struct GeometryArgs {
    /// Report file (JSON); a Markdown table is written beside it (.md).
    #[arg(long, default_value = "bench/geometry.json")]
    json: PathBuf,
    /// Points in cloud A (B gets half).
    #[arg(long, default_value_t = 1_000_000, value_parser = clap::value_parser!(u64).range(1000..=20_000_000))]
    points: u64,
    /// Rounds, each timing our side and then Open3D's; the report gives the median ratio.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=20))]
    rounds: u32,
    /// Python interpreter with open3d installed.
    #[arg(long, default_value = "python3")]
    python: String,
    /// Time our side only (a smoke run on a machine without Open3D; its columns are NaN).
    #[arg(long)]
    no_open3d: bool,
}

#[derive(Args)]
pub struct SynthArgs {
    #[arg(long, default_value = "bench/synth.json")]
    json: PathBuf,
    /// Scenes rendered (10 views each) and scenes turned into pairs. Ten: with five the
    /// all-outputs figure moved by +-10% from run to run.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=1000))]
    scenes: u64,
}

#[derive(Args)]
pub struct ModelArgs {
    #[arg(long, default_value = "bench/model.json")]
    json: PathBuf,
    /// Python interpreter with torch installed (skip the comparison with --no-torch).
    #[arg(long, default_value = "python3")]
    python: String,
    #[arg(long)]
    no_torch: bool,
    /// Rounds, each timing our side and then PyTorch's: the shared host's load drifts over
    /// seconds, so the ratios are taken per round (neighbouring measurements) and the report
    /// gives their median.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=20))]
    rounds: u32,
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Geometry(a) => {
            let python = (!a.no_open3d).then_some(a.python.as_str());
            let report =
                bench::geometry::geometry_bench(a.points as usize, a.rounds as usize, python)?;
            crate::report::write_report(&a.json, &report)?;
            let md = report.markdown();
            deocc_io::atomic::write_bytes_atomic(&a.json.with_extension("md"), md.as_bytes())?;
            print!("{md}");
        }
        BenchCommand::Synth(a) => {
            let report = bench::synth::synth_bench(a.scenes as usize)?;
            crate::report::write_report(&a.json, &report)?;
        }
        BenchCommand::Memory(a) => {
            if a.views.is_empty() || a.views.iter().any(|&v| v == 0 || v > 2000) {
                anyhow::bail!("--views: each between 1 and 2000");
            }
            let exe = std::env::current_exe()?;
            let report =
                bench::memory::memory_bench(&exe, &a.views, a.width, a.height, &a.completer)?;
            crate::report::write_report(&a.json, &report)?;
        }
        BenchCommand::Service(a) => {
            let chain = crate::completers::chain(&a.completers)?;
            let total = u64::from(a.clients) * u64::from(a.requests);
            let pb = std::sync::Arc::new(crate::progress::bar(total, "requests"));
            let tick = {
                let pb = pb.clone();
                std::sync::Arc::new(move || pb.inc(1))
            };
            let report = bench::service::service_bench(
                chain,
                &bench::service::ServiceBenchOptions {
                    clients: a.clients as usize,
                    requests: a.requests as usize,
                    rounds: a.rounds as usize,
                    workers: a.workers as usize,
                    queue: a.queue as usize,
                },
                tick,
            )?;
            pb.finish_and_clear();
            crate::report::write_report(&a.json, &report)?;
        }
        BenchCommand::Soak(a) => {
            let exe = std::env::current_exe()?;
            eprintln!(
                "soak: {} s of traffic against deocc serve ({}), {} clients, {} abusers",
                a.seconds, a.completer, a.clients, a.abusers
            );
            let report = bench::soak::soak_bench(
                &exe,
                &bench::soak::SoakOptions {
                    seconds: a.seconds,
                    completer: a.completer,
                    clients: a.clients as usize,
                    abusers: a.abusers as usize,
                    max_rss_mib: a.max_rss_mib,
                },
            )?;
            crate::report::write_report(&a.json, &report)?;
            eprintln!(
                "normal: {} correct, {} busy, {} lost or wrong; peak RSS {:.0} MiB (bound {:.0}); \
                 Health at zero: {}; SIGTERM exit {:.2} s",
                report.normal_correct,
                report.normal_busy,
                report.normal_lost_or_wrong,
                report.peak_rss_mib,
                report.max_rss_mib,
                report.health_back_to_zero,
                report.sigterm_exit_s
            );
            if !report.passed {
                anyhow::bail!("the soak failed; see {}", a.json.display());
            }
        }
        BenchCommand::Model(a) => {
            let report = bench::model::model_bench(&bench::model::ModelBenchOptions {
                python: a.python,
                no_torch: a.no_torch,
                rounds: a.rounds as usize,
            })?;
            crate::report::write_report(&a.json, &report)?;
        }
    }
    Ok(())
}
