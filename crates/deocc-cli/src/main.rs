//! `deocc`: fast generative scene de-occlusion. A thin layer over the library crates: parse the
//! arguments, call one library function, decide the exit code here and nowhere else.

use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod batch;
mod completers;
mod depth;
mod example;
mod input;
mod options;
mod progress;
mod robot;
mod run;
mod serve;

// The lab: the benchmark generator, training, evaluation and benchmarks (the `lab` feature).
#[cfg(feature = "lab")]
mod bench;
#[cfg(feature = "lab")]
mod eval;
#[cfg(feature = "lab")]
mod recipe;
#[cfg(feature = "lab")]
mod report;
#[cfg(feature = "lab")]
mod robot_eval;
#[cfg(feature = "lab")]
mod scene_options;
#[cfg(feature = "lab")]
mod sensor;
#[cfg(feature = "lab")]
mod sheet;
#[cfg(feature = "lab")]
mod synth;
#[cfg(feature = "lab")]
mod train;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// mimalloc hands freed memory back to the OS after 10 ms; our workloads free and reallocate the
/// same large buffers (frames, activations) all the time, so every reuse page-faulted freshly
/// zeroed pages (a quarter of a training step, a fifth of pair generation, measured with perf).
/// Keeping freed memory, and no 2 MiB pages to zero, is the default unless the user's
/// `MIMALLOC_*` environment says otherwise.
fn tune_allocator() {
    extern "C" {
        fn mi_option_set(option: std::os::raw::c_int, value: std::os::raw::c_long);
    }
    // Indices of `mi_option_e` in the mimalloc v3 header that libmimalloc-sys 0.1.49 (pinned in
    // Cargo.lock) builds.
    const MI_OPTION_ALLOW_LARGE_OS_PAGES: std::os::raw::c_int = 6;
    const MI_OPTION_PURGE_DELAY: std::os::raw::c_int = 15;
    for (name, option, value) in [
        ("MIMALLOC_PURGE_DELAY", MI_OPTION_PURGE_DELAY, -1),
        (
            "MIMALLOC_ALLOW_LARGE_OS_PAGES",
            MI_OPTION_ALLOW_LARGE_OS_PAGES,
            0,
        ),
    ] {
        if std::env::var_os(name).is_none() {
            // SAFETY: plain option setter of the linked allocator; valid option index and value.
            unsafe { mi_option_set(option, value) };
        }
    }
}

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
    /// Run the pipeline over a manifest of scene folders, one shard per job (Kubernetes Indexed
    /// Jobs, Slurm arrays); complete outputs are skipped, a JSONL summary is appended.
    Batch(batch::BatchArgs),
    /// Serve the pipeline, grasping and placing over gRPC (proto/deocc/v1/deocc.proto in
    /// crates/deocc-service).
    Serve(serve::ServeArgs),
    /// Make synthetic scenes, training pairs and contact sheets.
    #[command(subcommand)]
    #[cfg(feature = "lab")]
    Synth(synth::SynthCommand),
    /// Train GL-DoT (starts or resumes a run directory).
    #[cfg(feature = "lab")]
    Train(train::TrainArgs),
    /// Export a training run's EMA weights (f16) for shipping.
    #[cfg(feature = "lab")]
    Export(train::ExportArgs),
    /// Evaluate on held-out data and write a report.
    #[command(subcommand)]
    #[cfg(feature = "lab")]
    Eval(eval::EvalCommand),
    /// Measure speed against a peer and write a report.
    #[command(subcommand)]
    #[cfg(feature = "lab")]
    Bench(bench::BenchCommand),
    /// Grasps on one object of a scene: antipodal parallel-jaw grasps planned on the completed
    /// cloud, checked for collision against the whole scene; JSON (pose, width, score) and a
    /// picture of the gripper outlines.
    Grasp(robot::GraspArgs),
    /// Every pipeline option with its default, range and meaning (`--json`, `--markdown`).
    Options(options::OptionsArgs),
    /// Where an object of a given footprint and height can be put down: a placement map on each
    /// horizontal support surface of the completed cloud and the best spot; JSON and a picture.
    Place(robot::PlaceArgs),
}

fn main() -> ExitCode {
    tune_allocator();
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
        Command::Batch(a) => batch::batch(a),
        Command::Serve(a) => serve::serve(a),
        #[cfg(feature = "lab")]
        Command::Synth(c) => synth::run(c),
        #[cfg(feature = "lab")]
        Command::Bench(c) => bench::run(c),
        #[cfg(feature = "lab")]
        Command::Train(a) => match &a.config {
            Some(recipe) => recipe::run_command(recipe, &a.run, &a.data_root),
            None => train::run(a),
        },
        #[cfg(feature = "lab")]
        Command::Eval(c) => eval::run(c),
        #[cfg(feature = "lab")]
        Command::Export(a) => train::export(a),
        Command::Grasp(a) => robot::grasp(a),
        Command::Place(a) => robot::place(a),
        Command::Options(a) => options::run(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
