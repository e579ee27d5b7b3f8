//! `deocc bench model`: GL-DoT's speed against the same model in PyTorch, in alternating rounds.

use std::path::Path;
use std::process::Command;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use deocc_model::config::{AttentionKind, GlDotConfig};
use deocc_model::flow::euler_sample;
use deocc_model::init::{randn, SeededInit};
use deocc_model::model::GlDot;
use deocc_model::train::AdamW;
use rand::SeedableRng;
use serde::Serialize;

use super::timing::{median, peer_script, warm_median_time, warm_median_time_after, TempDir};
use crate::EvalError;

/// The PyTorch twin of GL-DoT's benchmark, built into the binary.
const BENCH_TORCH_PY: &str = include_str!("../../../../scripts/bench_torch.py");

#[derive(Debug, Clone)]
pub struct ModelBenchOptions {
    /// Python interpreter with torch installed.
    pub python: String,
    /// Skip the comparison.
    pub no_torch: bool,
    /// Rounds, each timing our side and then PyTorch's.
    pub rounds: usize,
}

/// One round's times of our side, in seconds.
#[derive(Serialize, Clone, Copy)]
pub struct OurTimes {
    train_step_batch_8_s: f64,
    forward_batch_1_s: f64,
    complete_4_steps_batch_1_s: f64,
    complete_4_steps_batch_8_s: f64,
}

#[derive(Serialize)]
pub struct ModelRound {
    ours: OurTimes,
    torch: Option<serde_json::Value>,
    train_step_ratio: Option<f64>,
    forward_ratio: Option<f64>,
    complete_4_steps_batch_1_ratio: Option<f64>,
}

#[derive(Serialize)]
pub struct ModelReport {
    /// The machine and its load when the figures were taken.
    pub machine: super::timing::Machine,
    threads: usize,
    parameters: usize,
    rounds: usize,
    /// Our times: medians over the rounds.
    train_step_batch_8_s: f64,
    forward_batch_1_s: f64,
    complete_4_steps_batch_1_s: f64,
    complete_4_steps_batch_8_s: f64,
    completions_per_second_batch_1: f64,
    completions_per_second_batch_8: f64,
    /// Forward time at 128x128 (4x the tokens) over 64x64.
    scaling_128_over_64_linear: f64,
    scaling_128_over_64_softmax: f64,
    /// PyTorch's report of the round whose training-step ratio is the median.
    torch: Option<serde_json::Value>,
    /// ours / PyTorch: medians of the per-round ratios.
    train_step_ratio: Option<f64>,
    forward_ratio: Option<f64>,
    complete_4_steps_batch_1_ratio: Option<f64>,
    /// Every round, ours and PyTorch's, in the order they ran.
    per_round: Vec<ModelRound>,
}

fn torch_missing(python: &str) -> EvalError {
    EvalError::Data(format!(
        "PyTorch is not installed for {python}: `pip install torch` (or pass --no-torch)"
    ))
}

/// Runs the benchmark.
pub fn model_bench(a: &ModelBenchOptions) -> Result<ModelReport, EvalError> {
    if !a.no_torch {
        // Fail before our side's minute of timing, not after it.
        let importable = Command::new(&a.python)
            .args(["-c", "import torch"])
            .stderr(std::process::Stdio::null())
            .status()
            .map_err(|e| EvalError::Data(format!("cannot run {}: {e}", a.python)))?;
        if !importable.success() {
            return Err(torch_missing(&a.python));
        }
    }
    let dev = Device::Cpu;
    let build = |cfg: &GlDotConfig| -> Result<(GlDot, VarMap), EvalError> {
        let vm = VarMap::new();
        let vb = VarBuilder::from_backend(
            Box::new(SeededInit::new(vm.clone(), 0)),
            DType::F32,
            dev.clone(),
        );
        Ok((GlDot::new(cfg, vb)?, vm))
    };
    let cfg = GlDotConfig::small();
    let (model, vm) = build(&cfg)?;
    let vars: std::collections::BTreeMap<String, candle_core::Var> = vm
        .data()
        .lock()
        .map(|d| d.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
        .unwrap_or_default();
    let mut opt = AdamW::new(&vars)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let (r, tc, cc) = (cfg.resolution, cfg.target_channels, cfg.cond_channels);
    let mut step = 0;
    // Three warm-up steps on both sides: the allocator's arenas grow over the first steps (their
    // page faults showed in perf timelines for about five steps), and training is thousands of
    // steps in the steady state.
    let mut train_step = || -> Result<f64, EvalError> {
        Ok(warm_median_time_after(3, 9, || {
            let loss = deocc_model::train::random_batch_loss(&model, 8, &mut rng, &dev)?;
            let grads = loss.backward()?;
            let g: std::collections::BTreeMap<String, Tensor> = vars
                .iter()
                .filter_map(|(k, v)| grads.get(v).map(|t| (k.clone(), t.clone())))
                .collect();
            step += 1;
            opt.step(&vars, &g, step, 1e-4, 0.0)?;
            Ok(())
        })?
        .0)
    };
    let forward = |m: &GlDot,
                   cfg: &GlDotConfig,
                   b: usize,
                   rng: &mut rand_chacha::ChaCha8Rng|
     -> Result<(), EvalError> {
        let cond = randn(
            (b, cfg.resolution, cfg.resolution, cfg.cond_channels),
            rng,
            &dev,
        )?;
        let toks = m.encode(&cond)?;
        let x = randn(
            (b, cfg.resolution, cfg.resolution, cfg.target_channels),
            rng,
            &dev,
        )?;
        m.forward(&x, &Tensor::full(0.5f32, b, &dev)?, &cond, &toks)?;
        Ok(())
    };
    // Inference as users run it (`Completer`): the same weights as plain tensors, so candle
    // records no autograd graph (PyTorch's side runs under `torch.no_grad()`).
    let frozen = {
        let tensors: std::collections::HashMap<String, Tensor> = vars
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
            .collect();
        GlDot::new(&cfg, VarBuilder::from_tensors(tensors, DType::F32, &dev))?
    };
    let model = frozen;
    let mut infer_rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let rng2 = &mut infer_rng;
    let complete = |b: usize, rng: &mut rand_chacha::ChaCha8Rng| -> Result<f64, EvalError> {
        Ok(warm_median_time(5, || {
            let cond = randn((b, r, r, cc), rng, &dev)?;
            let toks = model.encode(&cond)?;
            let noise = randn((b, r, r, tc), rng, &dev)?;
            // The velocity is the first `tc` output channels; the heads (mask, mean, error)
            // follow them and are read once, as the completer does.
            euler_sample(&noise, 4, 1.0, |x, t| {
                model
                    .forward(x, &Tensor::full(t, b, &dev)?, &cond, &toks)?
                    .narrow(3, 0, tc)
            })?;
            Ok(())
        })?
        .0)
    };
    let torch_config = if a.no_torch {
        None
    } else {
        let dir = TempDir::new("bench-model")?;
        let mut j = serde_json::to_value(&cfg).map_err(|e| EvalError::Data(e.to_string()))?;
        j["threads"] = serde_json::json!(rayon::current_num_threads());
        let cfg_path = dir.0.join("config.json");
        std::fs::write(&cfg_path, j.to_string())
            .map_err(|e| deocc_io::IoError::new(&cfg_path, e))?;
        let script = peer_script(&dir.0, "bench_torch.py", BENCH_TORCH_PY)?;
        Some((dir, cfg_path, script))
    };
    let mut rounds = Vec::new();
    let mut run_rounds = || -> Result<(), EvalError> {
        for round in 0..a.rounds {
            eprintln!("round {} of {}: ours", round + 1, a.rounds);
            let ours = OurTimes {
                train_step_batch_8_s: train_step()?,
                forward_batch_1_s: warm_median_time(30, || forward(&model, &cfg, 1, rng2))?.0,
                complete_4_steps_batch_1_s: complete(1, rng2)?,
                complete_4_steps_batch_8_s: complete(8, rng2)?,
            };
            let torch = match &torch_config {
                Some((dir, cfg_path, script)) => {
                    Some(run_torch_bench(&a.python, &dir.0, script, cfg_path)?)
                }
                None => None,
            };
            let ratio = |ours: f64, key: &str| {
                torch
                    .as_ref()
                    .and_then(|t| t[key].as_f64())
                    .map(|x| ours / x)
            };
            rounds.push(ModelRound {
                train_step_ratio: ratio(ours.train_step_batch_8_s, "train_step_batch_8_s"),
                forward_ratio: ratio(ours.forward_batch_1_s, "forward_batch_1_s"),
                complete_4_steps_batch_1_ratio: ratio(
                    ours.complete_4_steps_batch_1_s,
                    "complete_4_steps_batch_1_s",
                ),
                ours,
                torch,
            });
        }
        Ok(())
    };
    // The temporary folder goes on every path, the failed ones too (TempDir's drop).
    run_rounds()?;
    let our_median =
        |f: fn(&OurTimes) -> f64| median(&rounds.iter().map(|r| f(&r.ours)).collect::<Vec<_>>());
    let ratio_median = |f: fn(&ModelRound) -> Option<f64>| -> Option<f64> {
        let v: Option<Vec<f64>> = rounds.iter().map(f).collect();
        v.map(|v| median(&v))
    };
    let train_s = our_median(|o| o.train_step_batch_8_s);
    let fwd_s = our_median(|o| o.forward_batch_1_s);
    let c1 = our_median(|o| o.complete_4_steps_batch_1_s);
    let c8 = our_median(|o| o.complete_4_steps_batch_8_s);
    let train_step_ratio = ratio_median(|r| r.train_step_ratio);
    // PyTorch's own figures from the round at the median training-step ratio.
    let torch = train_step_ratio.and_then(|m| {
        rounds
            .iter()
            .min_by(|x, y| {
                let d = |r: &ModelRound| (r.train_step_ratio.unwrap_or(f64::NAN) - m).abs();
                d(x).total_cmp(&d(y))
            })
            .and_then(|r| r.torch.clone())
    });
    let mut scaling = [0.0; 2];
    for (k, kind) in [AttentionKind::Linear, AttentionKind::Softmax]
        .into_iter()
        .enumerate()
    {
        let mut small = cfg.clone();
        small.attention = kind;
        let mut big = small.clone();
        big.resolution = 128;
        let (ms, _) = build(&small)?;
        let (mb, _) = build(&big)?;
        let (ts, _) = warm_median_time(5, || forward(&ms, &small, 1, rng2))?;
        let (tb, _) = warm_median_time(3, || forward(&mb, &big, 1, rng2))?;
        scaling[k] = tb / ts;
    }
    let report = ModelReport {
        machine: super::timing::Machine::now(),
        threads: rayon::current_num_threads(),
        parameters: deocc_model::model::parameter_count(&vm),
        rounds: rounds.len(),
        train_step_batch_8_s: train_s,
        forward_batch_1_s: fwd_s,
        complete_4_steps_batch_1_s: c1,
        complete_4_steps_batch_8_s: c8,
        completions_per_second_batch_1: 1.0 / c1,
        completions_per_second_batch_8: 8.0 / c8,
        scaling_128_over_64_linear: scaling[0],
        scaling_128_over_64_softmax: scaling[1],
        train_step_ratio,
        forward_ratio: ratio_median(|r| r.forward_ratio),
        complete_4_steps_batch_1_ratio: ratio_median(|r| r.complete_4_steps_batch_1_ratio),
        torch,
        per_round: rounds,
    };
    Ok(report)
}

/// Runs the PyTorch script once with the model configuration at `cfg_path`.
fn run_torch_bench(
    python: &str,
    dir: &Path,
    script: &Path,
    cfg_path: &Path,
) -> Result<serde_json::Value, EvalError> {
    let out = dir.join("torch.json");
    eprintln!("torch: running bench_torch.py");
    let status = Command::new(python)
        .arg(script)
        .arg(cfg_path)
        .arg(&out)
        .status()
        .map_err(|e| EvalError::Data(format!("cannot run {python}: {e}")))?;
    if status.code() == Some(3) {
        return Err(torch_missing(python));
    }
    if !status.success() {
        return Err(EvalError::Data(format!("bench_torch.py failed ({status})")));
    }
    let text = std::fs::read_to_string(&out).map_err(|e| deocc_io::IoError::new(&out, e))?;
    serde_json::from_str(&text).map_err(|e| EvalError::Data(format!("{}: {e}", out.display())))
}
