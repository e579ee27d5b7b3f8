//! Helpers shared by the model's tests.
#![allow(dead_code)]

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use deocc_model::config::GlDotConfig;
use deocc_model::data::PairData;
use deocc_model::infer::GlDotCompleter;
use deocc_model::init::{randn, SeededInit};
use deocc_model::model::GlDot;
use deocc_model::train::{TrainConfig, Trainer};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

pub fn model(cfg: &GlDotConfig, seed: u64) -> (GlDot, VarMap) {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_backend(
        Box::new(SeededInit::new(varmap.clone(), seed)),
        DType::F32,
        Device::Cpu,
    );
    (GlDot::new(cfg, vb).unwrap(), varmap)
}

pub fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

/// Asserts that two computations of the same function have the same gradient with respect to
/// each of `vars`, through a random linear probe of their outputs: every gradient nonzero and
/// within `tolerance` of the reference's, relative to the reference's largest entry when that is
/// above 1. The one gradient check of these tests.
pub fn assert_same_gradients(
    ours: Tensor,
    reference: Tensor,
    vars: &[&Var],
    tolerance: f32,
    seed: u64,
) {
    let probe = randn(ours.dims(), &mut rng(seed), ours.device()).unwrap();
    let grads = |out: Tensor| {
        out.mul(&probe)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap()
    };
    let (g_ours, g_ref) = (grads(ours), grads(reference));
    for (i, var) in vars.iter().enumerate() {
        let (a, r) = (g_ours.get(var).unwrap(), g_ref.get(var).unwrap());
        assert_eq!(a.dims(), var.dims());
        let scale = r
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(scale > 0.0, "gradient of input {i} is zero");
        let diff = max_abs_diff(a, r);
        assert!(
            diff < tolerance * scale.max(1.0),
            "gradient of input {i}: mismatch {diff} (largest {scale})"
        );
    }
}

/// A handful of 16x16 pairs from one synthetic scene.
pub fn tiny_pairs() -> PairData {
    use deocc_synth::generate::generate_scene;
    use deocc_synth::pairs::{scene_pairs, PairConfig};
    use deocc_synth::scene::SceneConfig;
    let scene = generate_scene(
        &SceneConfig {
            views: 3,
            ..SceneConfig::default()
        },
        42,
    )
    .unwrap();
    let set = scene_pairs(
        &scene,
        &PairConfig {
            resolution: 16,
            keep_unoccluded: 1.0,
            ..PairConfig::default()
        },
        0,
    )
    .unwrap();
    assert!(
        set.len() >= 4,
        "the scene should give a few pairs, got {}",
        set.len()
    );
    // As training reads them by default: from each pair's own view (the set carries the other
    // views' observations; a test switches them on with `set_seen_elsewhere`).
    PairData::new(set).with_seen_elsewhere(false)
}

/// A tiny model trained one step on `data`, loaded back as a completer (the run directory is
/// returned to keep it alive).
pub fn completer_after_one_step(data: &PairData) -> (tempfile::TempDir, GlDotCompleter) {
    completer_after_one_step_of(data, GlDotConfig::tiny())
}

/// [`completer_after_one_step`] of another model configuration.
pub fn completer_after_one_step_of(
    data: &PairData,
    model: GlDotConfig,
) -> (tempfile::TempDir, GlDotCompleter) {
    let dir = tempfile::tempdir().unwrap();
    let cfg = TrainConfig {
        model,
        batch_size: 2,
        steps: 1,
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::open(dir.path(), cfg, &Device::Cpu).unwrap();
    trainer.step(data).unwrap();
    trainer.checkpoint(dir.path()).unwrap();
    let completer = GlDotCompleter::from_dir(dir.path(), &Device::Cpu).unwrap();
    (dir, completer)
}
