//! Runs training steps of the shipped configuration on random data, for profiling:
//! `cargo build --release -p deocc-model --example train_steps &&
//!  perf record -g target/release/examples/train_steps 20`
//! (`train_steps N forward`: N batch-1 forwards with plain weights, as inference runs them).
//! Prints the median step time; `deocc bench model` is the benchmark of record.

use std::collections::BTreeMap;
use std::time::Instant;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use deocc_model::config::GlDotConfig;
use deocc_model::init::{randn, SeededInit};
use deocc_model::model::GlDot;
use deocc_model::train::{random_batch_loss, AdamW};
use rand::SeedableRng;

// As in the `deocc` binary; run with MIMALLOC_PURGE_DELAY=-1 MIMALLOC_ALLOW_LARGE_OS_PAGES=0 to
// match its allocator settings.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> candle_core::Result<()> {
    let steps: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(20);
    let dev = Device::Cpu;
    let cfg = GlDotConfig::small();
    let vm = VarMap::new();
    let vb = VarBuilder::from_backend(
        Box::new(SeededInit::new(vm.clone(), 0)),
        DType::F32,
        dev.clone(),
    );
    let model = GlDot::new(&cfg, vb)?;
    let vars: BTreeMap<String, Var> = vm
        .data()
        .lock()
        .map(|d| d.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
        .unwrap_or_default();
    if std::env::args().nth(2).as_deref() == Some("forward") {
        return forwards(&cfg, &vars, steps);
    }
    let mut opt = AdamW::new(&vars)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut times = Vec::with_capacity(steps);
    let mut phases = Vec::with_capacity(steps);
    for step in 1..=steps {
        let start = Instant::now();
        let loss = random_batch_loss(&model, 8, &mut rng, &dev)?;
        let forward_done = start.elapsed().as_secs_f64();
        let grads = loss.backward()?;
        let backward_done = start.elapsed().as_secs_f64();
        let g: BTreeMap<String, Tensor> = vars
            .iter()
            .filter_map(|(k, v)| grads.get(v).map(|t| (k.clone(), t.clone())))
            .collect();
        opt.step(&vars, &g, step, 1e-4, 0.0)?;
        let total = start.elapsed().as_secs_f64();
        times.push(total);
        phases.push([
            forward_done,
            backward_done - forward_done,
            total - backward_done,
        ]);
    }
    times.sort_by(f64::total_cmp);
    let median = |k: usize| {
        let mut v: Vec<f64> = phases.iter().map(|p: &[f64; 3]| p[k]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    println!(
        "median step {:.3} s over {steps} (forward {:.3}, backward {:.3}, optimizer {:.3})",
        times[steps / 2],
        median(0),
        median(1),
        median(2)
    );
    Ok(())
}

/// `n` batch-1 forwards (condition encoding included) on plain tensors, as `Completer` runs them.
fn forwards(cfg: &GlDotConfig, vars: &BTreeMap<String, Var>, n: usize) -> candle_core::Result<()> {
    let dev = Device::Cpu;
    let tensors: std::collections::HashMap<String, Tensor> = vars
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
        .collect();
    let model = GlDot::new(cfg, VarBuilder::from_tensors(tensors, DType::F32, &dev))?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let r = cfg.resolution;
    let mut times = Vec::with_capacity(n);
    for _ in 0..n {
        let start = Instant::now();
        let cond = randn((1, r, r, cfg.cond_channels), &mut rng, &dev)?;
        let toks = model.encode(&cond)?;
        let x = randn((1, r, r, cfg.target_channels), &mut rng, &dev)?;
        model.forward(&x, &Tensor::full(0.5f32, 1, &dev)?, &cond, &toks)?;
        times.push(start.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    println!("median forward {:.2} ms over {n}", 1e3 * times[n / 2]);
    Ok(())
}
