//! The network: shapes, presets, patch layout, growing by a condition channel, the residual base.

mod common;

use candle_core::{Device, Tensor, D};
use common::{max_abs_diff, model, rng, tiny_pairs};
use deocc_model::config::{AttentionKind, GlDotConfig, MaskPrior, ResidualBase};
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
        assert_eq!(v.dims(), &[2, r, r, cfg.out_channels()], "{name}");
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
    assert_eq!(v.dims(), &[1, 16, 16, cfg.out_channels()]);
    assert_eq!(
        cfg.out_channels(),
        cfg.target_channels + 1,
        "tiny has a mask head"
    );
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
        base: ResidualBase::Visible,
        mask_head: false,
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
        base: ResidualBase::Visible,
        mask_head: false,
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
    let base = ResidualBase::Visible;
    let visible = residual_prior(&cond, MaskPrior::Visible, base).unwrap();
    let hull = residual_prior(&cond, MaskPrior::HullInFront, base).unwrap();
    assert_eq!(channel(&visible, 3), channel(&cond, 3));
    assert_eq!(channel(&hull, 3), channel(&cond, 6));
    // The prior is a superset of the visible mask, and the pairs have hidden parts it adds.
    let (v, h) = (channel(&cond, 3), channel(&cond, 6));
    assert!(v.iter().zip(&h).all(|(v, h)| *v <= 0.0 || *h > 0.0));
    assert!(v.iter().zip(&h).any(|(v, h)| *v <= 0.0 && *h > 0.0));
    // Everything but the mask is the visible prior in both.
    for c in [0, 1, 2, 4, 5] {
        assert_eq!(channel(&visible, c), channel(&hull, c));
    }
    // The rules base: the rules completion carried in channels 7-11, the prior's mask.
    let rules = residual_prior(&cond, MaskPrior::EllipseOrBoxInFront, ResidualBase::Rules).unwrap();
    for (target, source) in [(0, 7), (1, 8), (2, 9), (3, 6), (4, 10), (5, 11)] {
        assert_eq!(channel(&rules, target), channel(&cond, source));
    }
    assert_eq!(cond.dim(3).unwrap(), COND_CHANNELS);
    // Inside the prior the rules' near side is the visible depth on visible pixels.
    let (near, vis_depth) = (channel(&cond, 10), channel(&cond, 4));
    for ((n, d), v) in near.iter().zip(&vis_depth).zip(&v) {
        if *v > 0.0 {
            assert_eq!(n, d);
        }
    }
    let too_few = GlDotConfig {
        cond_channels: 6,
        base: ResidualBase::Visible,
        mask_head: false,
        ..GlDotConfig::tiny()
    };
    assert!(too_few.validate().unwrap_err().contains("channel 6"));
    let rules_too_few = GlDotConfig {
        cond_channels: 7,
        ..GlDotConfig::tiny()
    };
    assert!(rules_too_few.validate().unwrap_err().contains("7-11"));
}

/// A model grown by the mask head keeps its velocity, and its zero head gives the prior: on
/// candidate pixels sigmoid(+-PRIOR_LOGIT) as the prior says.
#[test]
fn a_model_grown_by_the_mask_head_keeps_its_velocity_and_starts_at_the_prior() {
    use deocc_model::encode::PRIOR_LOGIT;
    let data = tiny_pairs();
    let no_head = GlDotConfig {
        mask_head: false,
        ..GlDotConfig::tiny()
    };
    let cfg = |model: GlDotConfig| TrainConfig {
        model,
        batch_size: 2,
        steps: 2,
        ..TrainConfig::default()
    };
    let (a, b, cond, _, _dirs) = grow_and_complete(&data, cfg(no_head), cfg(GlDotConfig::tiny()));
    let c: Vec<f32> = cond.flatten_all().unwrap().to_vec1().unwrap();
    let cc = deocc_model::encode::COND_CHANNELS;
    let (on, off) = (
        1.0 / (1.0 + (-PRIOR_LOGIT).exp()),
        1.0 / (1.0 + PRIOR_LOGIT.exp()),
    );
    let mut candidates = 0;
    for (k, (x, y)) in a.iter().zip(&b).enumerate() {
        let d = x
            .depth_rel
            .iter()
            .zip(&y.depth_rel)
            .map(|(p, q)| (p - q).abs())
            .fold(0f32, f32::max);
        assert!(d < 1e-4, "grown model's depth differs by {d}");
        assert_eq!(x.rgb, y.rgb);
        let n = y.mask_score.len();
        for (p, &score) in y.mask_score.iter().enumerate() {
            let ch = &c[(k * n + p) * cc..(k * n + p + 1) * cc];
            if ch[3] <= 0.0 && ch[5] < 0.0 {
                candidates += 1;
                let expected = if ch[6] > 0.0 { on } else { off };
                assert!((score - expected).abs() < 1e-5, "pixel {p}: {score}");
            }
        }
    }
    assert!(candidates > 0);
}

/// The mask head's loss: finite, lower for logits that agree with the target, and its gradient
/// finite even for saturated logits.
#[test]
fn mask_head_loss_prefers_the_right_mask() {
    use candle_core::Var;
    use deocc_model::train::mask_head_loss;
    let data = tiny_pairs();
    let (target, cond) = data.batch(&[0, 1], &[false, false], &Device::Cpu).unwrap();
    let mask = target.narrow(3, 3, 1).unwrap(); // +-1
    let prior = cond.narrow(3, 6, 1).unwrap();
    let prior_logit = (prior * f64::from(deocc_model::encode::PRIOR_LOGIT)).unwrap();
    // A head that turns the logit into +-8 where the truth says: the right mask.
    let right = ((mask.clone() * 8.0).unwrap() - &prior_logit).unwrap();
    let wrong = ((mask * -8.0).unwrap() - &prior_logit).unwrap();
    let l_right = mask_head_loss(&right, &cond, &target)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    let l_wrong = mask_head_loss(&wrong, &cond, &target)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    assert!(l_right.is_finite() && l_wrong.is_finite());
    assert!(l_right < 0.1 && l_wrong > 5.0, "{l_right} vs {l_wrong}");
    let saturated = Var::from_tensor(&(wrong * 100.0).unwrap()).unwrap();
    let loss = mask_head_loss(saturated.as_tensor(), &cond, &target).unwrap();
    let grads = loss.backward().unwrap();
    let g: Vec<f32> = grads
        .get(&saturated)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert!(g.iter().all(|v| v.is_finite()));
    assert!(g.iter().any(|&v| v != 0.0));
}

/// A rules-base model's training target is its base outside the object (zero residual there),
/// and the base covers the whole crop: the nearest visible colour everywhere.
#[test]
fn rules_base_targets_are_the_base_outside_the_object() {
    use deocc_model::encode::{residual_prior, COND_CHANNELS, TARGET_CHANNELS};
    let data = tiny_pairs().with_base(ResidualBase::Rules);
    let (target, cond) = data.batch(&[0, 1], &[false, true], &Device::Cpu).unwrap();
    let base = residual_prior(&cond, MaskPrior::EllipseOrBoxInFront, ResidualBase::Rules).unwrap();
    let residual: Vec<f32> = (&target - &base)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    let t: Vec<f32> = target.flatten_all().unwrap().to_vec1().unwrap();
    let c: Vec<f32> = cond.flatten_all().unwrap().to_vec1().unwrap();
    let (mut outside, mut inside_nonzero) = (0, 0);
    for (p, (res, tp)) in residual
        .chunks_exact(TARGET_CHANNELS)
        .zip(t.chunks_exact(TARGET_CHANNELS))
        .enumerate()
    {
        let cp = &c[p * COND_CHANNELS..(p + 1) * COND_CHANNELS];
        if tp[3] <= 0.0 {
            outside += 1;
            for ch in [0, 1, 2, 4, 5] {
                assert_eq!(res[ch], 0.0, "pixel {p} channel {ch}");
            }
        } else if res[..3].iter().any(|&v| v != 0.0) {
            inside_nonzero += 1;
        }
        // The base colour is a visible colour (never the white of "no object").
        assert!(cp[7..10].iter().all(|v| (-1.0..=1.0).contains(v)));
    }
    assert!(outside > 0 && inside_nonzero > 0);
    // Without the rules base, the target outside the object is white and zero depth.
    let (legacy, _) = tiny_pairs().batch(&[0], &[false], &Device::Cpu).unwrap();
    let l: Vec<f32> = legacy.flatten_all().unwrap().to_vec1().unwrap();
    assert!(l
        .chunks_exact(TARGET_CHANNELS)
        .filter(|p| p[3] <= 0.0)
        .all(|p| p[0] == 1.0 && p[4] == 0.0));
}

/// A model grown by the mean head keeps its mask head's scores, and its zero mean head gives the
/// base exactly: the nearest visible colour and the rules' near and far sides (condition
/// channels 7-11). Training then lowers the mean head's loss.
#[test]
fn a_model_grown_by_the_mean_head_starts_at_the_base_and_learns() {
    use deocc_model::encode::{COND_CHANNELS, DEPTH_SCALE};
    let data = tiny_pairs();
    let cfg = grow_config;
    let with_mean = tiny_with_mean_head();
    let (a, b, cond, mut grown, _dirs) =
        grow_and_complete(&data, cfg(GlDotConfig::tiny(), 2), cfg(with_mean, 200));
    let c: Vec<f32> = cond.flatten_all().unwrap().to_vec1().unwrap();
    for (k, (x, y)) in a.iter().zip(&b).enumerate() {
        assert_eq!(x.mask_score, y.mask_score, "the mask head is untouched");
        let n = y.depth_rel.len();
        for p in 0..n {
            let ch = &c[(k * n + p) * COND_CHANNELS..(k * n + p + 1) * COND_CHANNELS];
            for j in 0..3 {
                let base = ((ch[7 + j] + 1.0) * 127.5).round().clamp(0.0, 255.0) as u8;
                assert_eq!(y.rgb[3 * p + j], base, "pixel {p} channel {j}");
            }
            assert!((y.depth_rel[p] - ch[10] / DEPTH_SCALE).abs() < 1e-6);
            assert!((y.back_depth_rel[p] - ch[11] / DEPTH_SCALE).abs() < 1e-6);
        }
    }
    // The mean head's loss falls with training (the flow and mask losses train beside it).
    let mean_loss = |t: &Trainer| {
        use deocc_model::train::mean_head_loss;
        let HeadBatch {
            out,
            residual,
            target,
            cond,
        } = head_batch(t, &data);
        let mean = out.narrow(3, 7, 5).unwrap();
        mean_head_loss(&mean, &residual, &target, &cond, &Default::default())
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    };
    let before = mean_loss(&grown);
    for _ in 0..200 {
        grown.step(&data).unwrap();
    }
    let after = mean_loss(&grown);
    assert!(after < before * 0.9, "mean-head loss {before} -> {after}");
    let no_mask = GlDotConfig {
        mask_head: false,
        mean_head: true,
        ..GlDotConfig::tiny()
    };
    assert!(no_mask.validate().unwrap_err().contains("mean_head needs"));
}

/// The metric depth loss: a pair's weight is its crop width over the reference, clamped to [1,
/// 2.5] (1 when unknown or off), and it multiplies only the depth terms of the mean head's loss,
/// linearly.
#[test]
fn the_metric_depth_weight_scales_only_the_depth_terms() {
    use deocc_model::train::{
        mean_head_loss, metric_depth_weight, MeanLossWeights, MAX_METRIC_DEPTH_WEIGHT,
        MEAN_VISIBLE_WEIGHT,
    };
    assert_eq!(metric_depth_weight(0.7, 0.35), 2.0);
    assert_eq!(
        metric_depth_weight(0.1, 0.35),
        1.0,
        "narrow crops keep weight 1"
    );
    assert_eq!(metric_depth_weight(9.0, 0.35), MAX_METRIC_DEPTH_WEIGHT);
    assert_eq!(metric_depth_weight(f32::NAN, 0.35), 1.0);
    assert_eq!(metric_depth_weight(0.7, 0.0), 1.0, "off");
    let data = tiny_pairs();
    let t = Trainer::new(
        TrainConfig {
            model: tiny_with_mean_head(),
            ..TrainConfig::default()
        },
        &Device::Cpu,
    )
    .unwrap();
    let HeadBatch {
        out,
        residual,
        target,
        cond,
    } = head_batch(&t, &data);
    // A mean that is off in every channel, so that colour and depth both have a loss.
    let mean = (out.narrow(3, 7, 5).unwrap() + 0.3).unwrap();
    let b = mean.dims4().unwrap().0;
    let loss = |w: Option<Vec<f32>>| {
        mean_head_loss(
            &mean,
            &residual,
            &target,
            &cond,
            &MeanLossWeights {
                depth: w.as_deref(),
                ..Default::default()
            },
        )
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
    };
    let plain = loss(None);
    let ones = loss(Some(vec![1.0; b]));
    let twos = loss(Some(vec![2.0; b]));
    let threes = loss(Some(vec![3.0; b]));
    assert!((plain - ones).abs() < 1e-6, "{plain} vs {ones}");
    // The depth part is what each unit of weight adds; the colour part stays.
    let depth = twos - ones;
    assert!(depth > 0.0 && depth < ones, "depth part {depth} of {ones}");
    assert!(((threes - twos) - depth).abs() < 1e-4 * ones, "not linear");
    // Weighting one pair moves the loss by less than weighting all of them.
    let mut one = vec![1.0; b];
    one[0] = 2.0;
    let single = loss(Some(one));
    assert!(single > ones && single < twos, "{ones} < {single} < {twos}");
    // The far side's visible weight: the default equals the plain loss, a full weight adds the
    // visible pixels' far-side error, and only that (a zero far-side error adds nothing).
    let far = |far_visible: f32, mean: &Tensor| {
        mean_head_loss(
            mean,
            &residual,
            &target,
            &cond,
            &MeanLossWeights {
                depth: None,
                far_visible,
            },
        )
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
    };
    assert!((far(MEAN_VISIBLE_WEIGHT, &mean) - plain).abs() < 1e-6);
    assert!(
        far(1.0, &mean) > plain,
        "a full far-side weight adds the visible pixels' error"
    );
    let want_far = residual.narrow(3, 5, 1).unwrap();
    let exact_far = Tensor::cat(&[mean.narrow(3, 0, 4).unwrap(), want_far], 3).unwrap();
    let base = far(MEAN_VISIBLE_WEIGHT, &exact_far);
    assert!(
        (far(1.0, &exact_far) - base).abs() < 1e-6,
        "no far-side error, no change"
    );
}

/// A mean-head model grown by the error head completes exactly as before, its zero head
/// expecting `exp(ERROR_LOG_OFFSET)` everywhere; training then lowers the head's likelihood loss,
/// and it refuses a model without a mean head.
#[test]
fn a_model_grown_by_the_error_head_keeps_its_answers_and_learns_its_error() {
    use deocc_model::config::{ERROR_CHANNELS, ERROR_LOG_OFFSET, MEAN_CHANNELS};
    let data = tiny_pairs();
    let cfg = grow_config;
    let with_mean = tiny_with_mean_head();
    let with_error = GlDotConfig {
        error_head: true,
        ..with_mean.clone()
    };
    let (a, b, _cond, mut grown, _dirs) =
        grow_and_complete(&data, cfg(with_mean, 2), cfg(with_error, 200));
    let zero = ERROR_LOG_OFFSET.exp();
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.mask_score, y.mask_score);
        assert_eq!(x.rgb, y.rgb);
        assert_eq!(x.depth_rel, y.depth_rel);
        assert_eq!(x.back_depth_rel, y.back_depth_rel);
        assert!(x.expected_error.is_none());
        let e = y
            .expected_error
            .as_ref()
            .expect("the error head's estimate");
        assert_eq!(e.near.len(), y.depth_rel.len());
        assert!(e
            .near
            .iter()
            .chain(&e.far)
            .all(|&v| (v - zero).abs() < 1e-6 * zero.max(1.0)));
    }
    let error_loss = |t: &Trainer| {
        use deocc_model::train::error_head_loss;
        let HeadBatch {
            out,
            residual,
            target,
            cond,
        } = head_batch(t, &data);
        let mean = out.narrow(3, 7, MEAN_CHANNELS).unwrap();
        let head = out.narrow(3, 7 + MEAN_CHANNELS, ERROR_CHANNELS).unwrap();
        error_head_loss(&head, &mean, &residual, &target, &cond)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    };
    let before = error_loss(&grown);
    for _ in 0..200 {
        grown.step(&data).unwrap();
    }
    let after = error_loss(&grown);
    assert!(after < before - 0.1, "error-head loss {before} -> {after}");
    let no_mean = GlDotConfig {
        error_head: true,
        ..GlDotConfig::tiny()
    };
    assert!(no_mean.validate().unwrap_err().contains("error_head needs"));
}

/// A trainer's raw output at t = 1 on the first (up to) eight pairs, with the residual target
/// and the batch it came from: what the heads' losses read.
struct HeadBatch {
    out: Tensor,
    residual: Tensor,
    target: Tensor,
    cond: Tensor,
}

fn head_batch(t: &Trainer, data: &deocc_model::data::PairData) -> HeadBatch {
    let idx: Vec<usize> = (0..data.len().min(8)).collect();
    let flips = vec![false; idx.len()];
    let (target, cond) = data.batch(&idx, &flips, &Device::Cpu).unwrap();
    let base =
        deocc_model::encode::residual_prior(&cond, t.config.model.mask_prior, t.config.model.base)
            .unwrap();
    let residual = (&target - base).unwrap();
    let b = idx.len();
    let r = t.config.model.resolution;
    let noise = randn((b, r, r, 6), &mut rng(5), &Device::Cpu).unwrap();
    let tt = Tensor::full(1f32, b, &Device::Cpu).unwrap();
    let tokens = t.model.encode(&cond).unwrap();
    let out = t.model.forward(&noise, &tt, &cond, &tokens).unwrap();
    HeadBatch {
        out,
        residual,
        target,
        cond,
    }
}

/// Trains `old` two steps, warm-starts a fresh run of `new` from its EMA weights (growing the
/// output layer), and completes pairs 0 and 1 with both: (old's, the grown one's, the condition,
/// the grown trainer). The run folders live as long as the returned guard.
#[allow(clippy::type_complexity)]
fn grow_and_complete(
    data: &deocc_model::data::PairData,
    old: TrainConfig,
    new: TrainConfig,
) -> (
    Vec<deocc_model::infer::Completion>,
    Vec<deocc_model::infer::Completion>,
    Tensor,
    Trainer,
    [tempfile::TempDir; 2],
) {
    let (old_dir, new_dir) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let mut first = Trainer::open(old_dir.path(), old, &Device::Cpu).unwrap();
    for _ in 0..2 {
        first.step(data).unwrap();
    }
    first.checkpoint(old_dir.path()).unwrap();
    let mut grown = Trainer::open(new_dir.path(), new, &Device::Cpu).unwrap();
    grown
        .init_from(&old_dir.path().join("ema.safetensors"))
        .unwrap();
    grown.checkpoint(new_dir.path()).unwrap();
    let (_, cond) = data.batch(&[0, 1], &[false, false], &Device::Cpu).unwrap();
    let complete = |dir: &std::path::Path| {
        GlDotCompleter::from_dir(dir, &Device::Cpu)
            .unwrap()
            .complete(&cond, &[], 0.0, 2, 7)
            .unwrap()
    };
    let (a, b) = (complete(old_dir.path()), complete(new_dir.path()));
    (a, b, cond, grown, [old_dir, new_dir])
}

/// The training set-up of the grown-model tests: small batches, a high rate, no warm-up.
fn grow_config(model: GlDotConfig, steps: usize) -> TrainConfig {
    TrainConfig {
        model,
        batch_size: 4,
        steps,
        learning_rate: 3e-3,
        warmup_steps: 1,
        ..TrainConfig::default()
    }
}

/// The tiny preset with the mean head.
fn tiny_with_mean_head() -> GlDotConfig {
    GlDotConfig {
        mean_head: true,
        ..GlDotConfig::tiny()
    }
}
