//! `deocc`: fast generative scene de-occlusion. A thin layer over the library crates: parse the
//! arguments, call one library function, decide the exit code here and nowhere else.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod bench;
mod eval;
mod progress;
mod report;
mod run;
mod synth;
mod train;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
#[command(
    name = "deocc",
    version,
    about = "Fast generative scene de-occlusion for vision and robotics"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Complete the occluded objects of a scene and fuse them into its point cloud.
    Run(run::RunArgs),
    /// Make synthetic scenes, training pairs and contact sheets.
    #[command(subcommand)]
    Synth(synth::SynthCommand),
    /// Train GL-DoT (starts or resumes a run directory).
    Train(train::TrainArgs),
    /// Export a training run's EMA weights (f16) for shipping.
    Export(train::ExportArgs),
    /// Evaluate on held-out data and write a report.
    #[command(subcommand)]
    Eval(eval::EvalCommand),
    /// Measure speed against a peer and write a report.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("DEOCC_LOG")
                .unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Run(a) => run::run(a),
        Command::Synth(c) => synth::run(c),
        Command::Bench(c) => bench::run(c),
        Command::Train(a) => train::run(a),
        Command::Eval(c) => eval::run(c),
        Command::Export(a) => train::export(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
