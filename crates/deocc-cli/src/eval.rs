//! `deocc eval`: figures on held-out data, written to a JSON report.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use deocc_eval::amodal::{evaluate_amodal, AmodalEvalOptions};
use deocc_model::data::{shards, PairData};
use deocc_model::infer::Completer;
use deocc_synth::pairs::{split_scene_pairs, PairConfig, PairSet, Split};

#[derive(Subcommand)]
pub enum EvalCommand {
    /// 2-D amodal completion on held-out test pairs: mIoU per step count and baselines, occlusion
    /// levels, held-out shapes, cross-view gain, hidden-part depth error, completions per second.
    Amodal(AmodalArgs),
}

#[derive(Args)]
pub struct AmodalArgs {
    #[arg(long, default_value = "bench/amodal.json")]
    json: PathBuf,
    /// Model folder (train.json + ema.safetensors or model.safetensors).
    #[arg(long, default_value = "weights/gldot-small")]
    weights: PathBuf,
    /// Folder with test-*.safetensors shards; without it, test pairs are rendered on the fly.
    #[arg(long)]
    data: Option<PathBuf>,
    /// Number of test pairs.
    #[arg(long, default_value_t = 120)]
    pairs: usize,
    /// Step counts to evaluate, comma-separated.
    #[arg(long, default_value = "1,2,4,8,50", value_delimiter = ',')]
    steps: Vec<usize>,
}

pub fn run(cmd: EvalCommand) -> Result<()> {
    match cmd {
        EvalCommand::Amodal(a) => amodal(a),
    }
}

/// Test pairs: from shards if given, else rendered from the test split's first scenes.
fn test_pairs(data: Option<&PathBuf>, want: usize) -> Result<PairData> {
    if let Some(dir) = data {
        let files = shards(dir, "test")
            .with_context(|| format!("{}: cannot list test pairs", dir.display()))?;
        if files.is_empty() {
            bail!("{}: no test-*.safetensors shards", dir.display());
        }
        return Ok(PairData::load(&files)?);
    }
    let mut set = PairSet::default();
    let mut scene = 0;
    while set.len() < want && scene < 10_000 {
        set.extend(&split_scene_pairs(
            Split::Test,
            scene,
            &PairConfig::default(),
        )?);
        scene += 1;
    }
    Ok(PairData::new(set))
}

fn amodal(a: AmodalArgs) -> Result<()> {
    if !a.weights.join("train.json").exists() {
        bail!(
            "{}: no train.json; give --weights a run directory or the shipped weights/gldot-small",
            a.weights.display()
        );
    }
    let completer = Completer::from_dir(&a.weights, &candle_core::Device::Cpu)?;
    let data = test_pairs(a.data.as_ref(), a.pairs)?;
    if data.resolution() != completer.resolution() {
        bail!(
            "test pairs are {0}x{0} but the model expects {1}x{1}",
            data.resolution(),
            completer.resolution()
        );
    }
    let opts = AmodalEvalOptions {
        pairs: a.pairs,
        steps: a.steps.clone(),
        ..AmodalEvalOptions::default()
    };
    eprintln!(
        "evaluating {} test pairs at steps {:?}",
        opts.pairs.min(data.len()),
        opts.steps
    );
    let report = evaluate_amodal(&completer, &data, &opts)?;
    if let Some(parent) = a.json.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("{}: cannot create", parent.display()))?;
    }
    deocc_io::cameras::write_json(&a.json, &report)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
