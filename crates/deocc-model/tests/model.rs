//! The network: shapes, presets, patch layout, growing by a condition channel, the residual base.

mod common;

use candle_core::{Device, Tensor, D};
use common::{max_abs_diff, model, rng, tiny_pairs};
use deocc_model::config::{AttentionKind, GlDotConfig, MaskPrior};
use deocc_model::infer::GlDotCompleter;
use deocc_model::init::randn;
use deocc_model::model::{patchify, unpatchify};
use deocc_model::train::{TrainConfig, Trainer};

#[test]
fn forward_shapes_for_runnable_presets() {
    for (name, cfg) in [
        ("tiny", GlDotConfig::tiny()),
        ("small", GlDotConfig::small()),
    ] {
        let (m, _) = model(&cfg, 1);
        let r = cfg.resolution;
        let mut g = rng(2);
        let x = randn((2, r, r, cfg.target_channels), &mut g, &Device::Cpu).unwrap();
        let c = randn((2, r, r, cfg.cond_channels), &mut g, &Device::Cpu).unwrap();
        let tokens = m.encode(&c).unwrap();
        assert_eq!(
            tokens.dims(),
            &[2, cfg.cond_grid() * cfg.cond_grid(), cfg.width],
            "{name}"
        );
        let t = Tensor::new(&[0.3f32, 0.9], &Device::Cpu).unwrap();
        let v = m.forward(&x, &t, &c, &tokens).unwrap();
        assert_eq!(v.dims(), &[2, r, r, cfg.target_channels], "{name}");
        // Zero-initialised final layer: the untrained model predicts exactly zero velocity.
        assert_eq!(
            v.abs()
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap(),
            0.0,
            "{name}"
        );
    }
}

#[test]
fn large_preset_is_consistent_with_sana_600m_shape() {
    // Too big to run in a test (about 0.6 B parameters); its shape arithmetic is checked instead.
    let cfg = GlDotConfig::large();
    cfg.validate().unwrap();
    assert_eq!(
        (cfg.width, cfg.depth, cfg.head_dim, cfg.heads()),
        (1152, 28, 32, 36)
    );
    assert_eq!(cfg.tokens(), 64 * 64);
    let per_block =
        4 * cfg.width * cfg.width + 4 * cfg.width * cfg.width + 3 * cfg.width * cfg.mlp_hidden();
    assert!((per_block * cfg.depth) as f64 > 5e8);
    assert!(GlDotConfig::preset("nope").is_none());
}

#[test]
fn patchify_round_trips() {
    let x = randn((2, 16, 16, 5), &mut rng(3), &Device::Cpu).unwrap();
    let p = patchify(&x, 4).unwrap();
    assert_eq!(p.dims(), &[2, 16, 80]);
    assert_eq!(max_abs_diff(&unpatchify(&p, 4, 5).unwrap(), &x), 0.0);
}

#[test]
fn softmax_attention_switch_builds_and_runs() {
    let mut cfg = GlDotConfig::tiny();
    cfg.attention = AttentionKind::Softmax;
    let (m, _) = model(&cfg, 9);
    let mut g = rng(10);
    let x = randn((1, 16, 16, cfg.target_channels), &mut g, &Device::Cpu).unwrap();
    let c = randn((1, 16, 16, cfg.cond_channels), &mut g, &Device::Cpu).unwrap();
    let tok = m.encode(&c).unwrap();
    let v = m
        .forward(&x, &Tensor::new(&[0.5f32], &Device::Cpu).unwrap(), &c, &tok)
        .unwrap();
    assert_eq!(v.dims(), &[1, 16, 16, cfg.target_channels]);
    assert!(v.mean(D::Minus1).is_ok());
}

#[test]
fn a_model_grown_by_a_condition_channel_computes_what_the_old_one_did() {
    let data = tiny_pairs();
    let old_dir = tempfile::tempdir().unwrap();
    let new_dir = tempfile::tempdir().unwrap();
    // Models before the prior channel started their residual from the visible mask; a warm start
    // keeps that until it is trained with another prior.
    let old_model = GlDotConfig {
        cond_channels: 5,
        mask_prior: MaskPrior::Visible,
        ..GlDotConfig::tiny()
    };
    let cfg = |model: GlDotConfig| TrainConfig {
        model,
        batch_size: 2,
        steps: 2,
        ..TrainConfig::default()
    };
    // A 5-channel model with trained (non-initial) weights...
    let mut old = Trainer::open(old_dir.path(), cfg(old_model), &Device::Cpu).unwrap();
    for _ in 0..2 {
        old.step(&data).unwrap();
    }
    old.checkpoint(old_dir.path()).unwrap();
    // ... warm-starts one with every condition channel of today's preset (two zero columns more).
    let grown_model = GlDotConfig {
        mask_prior: MaskPrior::Visible,
        ..GlDotConfig::tiny()
    };
    let mut grown = Trainer::open(new_dir.path(), cfg(grown_model), &Device::Cpu).unwrap();
    grown
        .init_from(&old_dir.path().join("ema.safetensors"))
        .unwrap();
    grown.checkpoint(new_dir.path()).unwrap();
    let (_, cond) = data.batch(&[0, 1], &[false, false], &Device::Cpu).unwrap();
    assert_eq!(cond.dim(3).unwrap(), deocc_model::data::COND_CHANNELS);
    assert_eq!(
        GlDotConfig::tiny().cond_channels,
        deocc_model::data::COND_CHANNELS
    );
    let a = GlDotCompleter::from_dir(old_dir.path(), &Device::Cpu)
        .unwrap()
        .complete(&cond, &[], 0.0, 2, 7)
        .unwrap();
    let b = GlDotCompleter::from_dir(new_dir.path(), &Device::Cpu)
        .unwrap()
        .complete(&cond, &[], 0.0, 2, 7)
        .unwrap();
    for (x, y) in a.iter().zip(&b) {
        let d = x
            .mask_score
            .iter()
            .zip(&y.mask_score)
            .map(|(p, q)| (p - q).abs())
            .fold(0f32, f32::max);
        assert!(d < 1e-4, "grown model differs by {d}");
    }
}

#[test]
fn the_residual_starts_from_the_configured_mask_prior() {
    use deocc_model::encode::{residual_prior, COND_CHANNELS};
    let data = tiny_pairs();
    let (_, cond) = data.batch(&[0, 1], &[false, false], &Device::Cpu).unwrap();
    let channel = |t: &Tensor, c: usize| -> Vec<f32> {
        t.narrow(3, c, 1)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
    };
    let visible = residual_prior(&cond, MaskPrior::Visible).unwrap();
    let hull = residual_prior(&cond, MaskPrior::HullInFront).unwrap();
    assert_eq!(channel(&visible, 3), channel(&cond, 3));
    assert_eq!(channel(&hull, 3), channel(&cond, COND_CHANNELS - 1));
    // The prior is a superset of the visible mask, and the pairs have hidden parts it adds.
    let (v, h) = (channel(&cond, 3), channel(&cond, COND_CHANNELS - 1));
    assert!(v.iter().zip(&h).all(|(v, h)| *v <= 0.0 || *h > 0.0));
    assert!(v.iter().zip(&h).any(|(v, h)| *v <= 0.0 && *h > 0.0));
    // Everything but the mask is the visible prior in both.
    for c in [0, 1, 2, 4, 5] {
        assert_eq!(channel(&visible, c), channel(&hull, c));
    }
    let too_few = GlDotConfig {
        cond_channels: 6,
        ..GlDotConfig::tiny()
    };
    assert!(too_few.validate().unwrap_err().contains("channel 6"));
}
