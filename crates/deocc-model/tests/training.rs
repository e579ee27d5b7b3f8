//! Training: the sampler, overfitting, checkpoints, the fused AdamW step.

mod common;

use candle_core::{Device, Tensor, Var};
use common::{max_abs_diff, rng, tiny_pairs};
use deocc_model::config::GlDotConfig;
use deocc_model::data::PairData;
use deocc_model::flow::{euler_sample, interpolate, time_grid};
use deocc_model::infer::GlDotCompleter;
use deocc_model::init::randn;
use deocc_model::train::{TrainConfig, Trainer};

#[test]
fn sampler_with_the_exact_velocity_recovers_x0() {
    let dev = Device::Cpu;
    let mut g = rng(6);
    let x0 = randn((3, 4, 4, 5), &mut g, &dev).unwrap();
    let noise = randn((3, 4, 4, 5), &mut g, &dev).unwrap();
    for steps in [1, 2, 4, 8] {
        for shift in [1.0f32, 3.0] {
            // On the straight path through x0, v(x, t) = (x - x0) / t.
            let out = euler_sample(&noise, steps, shift, |x, t| (x - &x0)? / t as f64).unwrap();
            assert!(
                max_abs_diff(&out, &x0) < 1e-5,
                "steps {steps} shift {shift}"
            );
        }
    }
    let grid = time_grid(4, 1.0);
    assert_eq!(grid, vec![1.0, 0.75, 0.5, 0.25, 0.0]);
    let t = Tensor::new(&[0.0f32, 1.0, 0.5], &dev).unwrap();
    let xt = interpolate(&x0, &noise, &t).unwrap();
    assert!(max_abs_diff(&xt.narrow(0, 0, 1).unwrap(), &x0.narrow(0, 0, 1).unwrap()) < 1e-7);
    assert!(
        max_abs_diff(
            &xt.narrow(0, 1, 1).unwrap(),
            &noise.narrow(0, 1, 1).unwrap()
        ) < 1e-7
    );
}

#[test]
fn tiny_model_overfits_a_few_pairs() {
    let data = tiny_pairs();
    let cfg = TrainConfig {
        model: GlDotConfig::tiny(),
        batch_size: 4,
        steps: 300,
        learning_rate: 3e-3,
        warmup_steps: 20,
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::new(cfg, &Device::Cpu).unwrap();
    let probe: Vec<usize> = (0..4).collect();
    let eval = |t: &Trainer| -> f32 {
        // Average over a few fixed noise draws so the comparison is not luck.
        (0..4)
            .map(|s| {
                t.loss(&data, &probe, &mut rng(100 + s))
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap()
            })
            .sum::<f32>()
            / 4.0
    };
    let before = eval(&trainer);
    let mut first = data.set.clone();
    first.truncate(4);
    let small = PairData::new(first);
    for _ in 0..500 {
        trainer.step(&small).unwrap();
    }
    let after = eval(&trainer);
    // The residual target is mostly zero, so the loss starts near the noise's variance (~1) and
    // falls to ~0.77 here (the old full target started twice as high and halved).
    assert!(after < 0.75 * before, "loss {before} -> {after}");
}

#[test]
fn save_then_load_gives_identical_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_pairs();
    let cfg = TrainConfig {
        model: GlDotConfig::tiny(),
        batch_size: 2,
        steps: 3,
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::open(dir.path(), cfg.clone(), &Device::Cpu).unwrap();
    for _ in 0..3 {
        trainer.step(&data).unwrap();
    }
    trainer.checkpoint(dir.path()).unwrap();
    let (_, cond) = data.batch(&[0, 1], &[false, false], &Device::Cpu).unwrap();
    let a = GlDotCompleter::from_dir(dir.path(), &Device::Cpu)
        .unwrap()
        .complete(&cond, &[], 0.0, 2, 7)
        .unwrap();
    let b = GlDotCompleter::from_dir(dir.path(), &Device::Cpu)
        .unwrap()
        .complete(&cond, &[], 0.0, 2, 7)
        .unwrap();
    assert_eq!(a[0].depth_rel, b[0].depth_rel);
    assert_eq!(a[1].rgb, b[1].rgb);
    // Resuming continues from the saved step with the same weights.
    let resumed = Trainer::open(dir.path(), cfg, &Device::Cpu).unwrap();
    assert_eq!(resumed.state.step, 3);
    let w1 = trainer.ema_weights();
    let w2 = resumed.ema_weights();
    for (k, v) in w1 {
        assert_eq!(max_abs_diff(v, &w2[k]), 0.0, "{k}");
    }
}

#[test]
fn fused_adamw_step_follows_the_adamw_formulas() {
    use deocc_model::train::AdamW;
    use std::collections::BTreeMap;
    let dev = Device::Cpu;
    let mut g = rng(21);
    let mut vars = BTreeMap::new();
    vars.insert(
        "w".to_string(),
        Var::from_tensor(&randn((3, 4), &mut g, &dev).unwrap()).unwrap(),
    );
    vars.insert(
        "b".to_string(),
        Var::from_tensor(&randn(4, &mut g, &dev).unwrap()).unwrap(),
    );
    let w0: BTreeMap<String, Vec<f32>> = vars
        .iter()
        .map(|(k, v)| (k.clone(), v.flatten_all().unwrap().to_vec1().unwrap()))
        .collect();
    let mut opt = AdamW::new(&vars).unwrap();
    let (lr, wd, scale) = (0.01, 0.1, 0.5);
    let grads: Vec<BTreeMap<String, Tensor>> = (0..2)
        .map(|_| {
            vars.iter()
                .map(|(k, v)| (k.clone(), randn(v.shape().clone(), &mut g, &dev).unwrap()))
                .collect()
        })
        .collect();
    for (s, gr) in grads.iter().enumerate() {
        opt.step_scaled(&vars, gr, scale, s + 1, lr, wd).unwrap();
    }
    // The same two steps written out per element in f64.
    for (name, var) in &vars {
        let decay = if name == "w" { wd } else { 0.0 };
        let got: Vec<f32> = var.flatten_all().unwrap().to_vec1().unwrap();
        for (i, &w_init) in w0[name].iter().enumerate() {
            let (mut w, mut m, mut v) = (f64::from(w_init), 0.0, 0.0);
            for (s, gr) in grads.iter().enumerate() {
                let gi: Vec<f32> = gr[name].flatten_all().unwrap().to_vec1().unwrap();
                let gi = f64::from(gi[i]) * scale;
                m = 0.9 * m + 0.1 * gi;
                v = 0.999 * v + 0.001 * gi * gi;
                let t = (s + 1) as i32;
                let update =
                    (m / (1.0 - 0.9f64.powi(t))) / ((v / (1.0 - 0.999f64.powi(t))).sqrt() + 1e-8);
                w = w * (1.0 - lr * decay) - lr * update;
            }
            assert!(
                (f64::from(got[i]) - w).abs() < 1e-5,
                "{name}[{i}]: {} vs {w}",
                got[i]
            );
        }
        assert_ne!(got, w0[name], "{name} moved");
    }
}

/// A `train.json` must name its model, may hold no unknown field, and every value is in range.
#[test]
fn train_configs_are_checked() {
    let good = serde_json::to_value(TrainConfig {
        model: GlDotConfig::tiny(),
        mask_threshold: 0.5,
        ..TrainConfig::default()
    })
    .unwrap();
    assert!(TrainConfig::from_json(&good.to_string()).is_ok());
    let e = TrainConfig::from_json("{}").unwrap_err();
    assert!(e.contains("model"), "{e}");
    let with = |key: &str, value: serde_json::Value| {
        let mut v = good.clone();
        v[key] = value;
        TrainConfig::from_json(&v.to_string()).unwrap_err()
    };
    assert!(with("mask_treshold", 1.0.into()).contains("mask_treshold"));
    assert!(with("inference_samples", 100_000.into()).contains("inference_samples"));
    assert!(with("checkpoint_every", 0.into()).contains("checkpoint_every"));
    assert!(with("batch_size", 0.into()).contains("batch_size"));
    assert!(with("learning_rate", serde_json::Value::from(-1.0)).contains("learning_rate"));
    let mut v = good.clone();
    v["model"]["patch"] = 0.into();
    assert!(TrainConfig::from_json(&v.to_string())
        .unwrap_err()
        .contains("patch"));
    let mut v = good.clone();
    v["model"]["cond_patch"] = 0.into();
    assert!(TrainConfig::from_json(&v.to_string())
        .unwrap_err()
        .contains("cond_patch"));
}

/// Weights with NaN values, and a checkpoint whose EMA lacks a tensor, are refused at load and
/// at resume, naming the file.
#[test]
fn broken_weights_are_refused() {
    let data = tiny_pairs();
    let dir = tempfile::tempdir().unwrap();
    let cfg = TrainConfig {
        model: GlDotConfig::tiny(),
        batch_size: 2,
        steps: 1,
        mask_threshold: 0.5,
        ..TrainConfig::default()
    };
    let mut t = Trainer::open(dir.path(), cfg.clone(), &Device::Cpu).unwrap();
    t.step(&data).unwrap();
    t.checkpoint(dir.path()).unwrap();
    let ema = dir.path().join("ema.safetensors");
    let mut tensors = candle_core::safetensors::load(&ema, &Device::Cpu).unwrap();
    let original = tensors.clone();
    let name = tensors.keys().next().unwrap().clone();
    let nan = (tensors[&name].zeros_like().unwrap() + f64::NAN).unwrap();
    tensors.insert(name.clone(), nan);
    candle_core::safetensors::save(&tensors, &ema).unwrap();
    let e = GlDotCompleter::from_dir(dir.path(), &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("non-finite") && e.contains(&name), "{e}");
    let e = Trainer::open(dir.path(), cfg.clone(), &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("ema.safetensors") && e.contains("non-finite"),
        "{e}"
    );
    let mut missing = original.clone();
    missing.remove(&name);
    candle_core::safetensors::save(&missing, &ema).unwrap();
    let e = Trainer::open(dir.path(), cfg, &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("ema.safetensors") && e.contains("missing tensor"),
        "{e}"
    );
}

/// The other views' observations reach the conditions of the share of pairs asked for: all of
/// them by default, none when switched off, about half at 0.5 (the training mix).
#[test]
fn the_other_views_observations_reach_the_share_of_conditions_asked_for() {
    let (n, r) = (200usize, 4usize);
    let px = r * r;
    let mut set = deocc_io::pairs::PairSet {
        resolution: r as u32,
        crop_rgb: vec![50; n * px * 3],
        visible_mask: (0..n * px).map(|i| (i % px < 4) as u8).collect(),
        visible_depth: vec![0.0; n * px],
        scene_depth: vec![0.0; n * px],
        whole_rgb: vec![255; n * px * 3],
        amodal_mask: vec![1; n * px],
        whole_depth: vec![0.0; n * px],
        whole_back_depth: vec![0.1; n * px],
        group: (0..n as u32).collect(),
        category: vec![0; n],
        held_out: vec![0; n],
        occlusion: vec![0.5; n],
        crop_width_m: vec![0.3; n],
        elsewhere_rgb: vec![9; n * px * 3],
        // Each pair: pixel 10 (hidden) seen elsewhere.
        elsewhere_depth: (0..n * px)
            .map(|i| if i % px == 10 { 0.05 } else { f32::INFINITY })
            .collect(),
    };
    let count = |data: &PairData| {
        (0..n)
            .filter(|&i| data.condition(i).seen_elsewhere.is_some())
            .count()
    };
    assert_eq!(count(&PairData::new(set.clone())), n);
    assert_eq!(
        count(&PairData::new(set.clone()).with_seen_elsewhere(false)),
        0
    );
    let half = count(&PairData::new(set.clone()).with_seen_elsewhere_share(0.5));
    assert!((70..=130).contains(&half), "{half} of {n}");
    assert_eq!(
        count(&PairData::new(set.clone()).with_seen_elsewhere_share(0.0)),
        0
    );
    // A condition with them takes their colour at that pixel; one without, the visible colour.
    let data = PairData::new(set.clone());
    assert_eq!(data.condition(0).observed().rgb[30..33], [9, 9, 9]);
    set.elsewhere_depth.clear();
    set.elsewhere_rgb.clear();
    assert_eq!(count(&PairData::new(set)), 0);
}
