//! Inference: the completer's mask rules and the condition channels it is given.

mod common;

use candle_core::Device;
use common::{completer_after_one_step, completer_after_one_step_of, tiny_pairs};
use deocc_model::config::{GlDotConfig, MaskPrior, ResidualBase};
use deocc_model::data::PairData;

#[test]
fn free_space_constraint_keeps_hidden_pixels_only_where_the_scene_is_in_front() {
    use deocc_model::data::{COND_CHANNELS, DEPTH_SCALE};
    use deocc_model::infer::FREE_SPACE_MARGIN;
    let data = tiny_pairs();
    // The flow model's constraint: the scene in front of the predicted near side.
    let flow_only = GlDotConfig {
        mask_head: false,
        base: ResidualBase::Visible,
        ..GlDotConfig::tiny()
    };
    let (_dir, mut completer) = completer_after_one_step_of(&data, flow_only);
    // A threshold every score passes, so that only the constraint decides.
    completer.mask_threshold = f32::MIN;
    let idx: Vec<usize> = (0..data.len().min(4)).collect();
    let (_, cond) = data
        .batch(&idx, &vec![false; idx.len()], &Device::Cpu)
        .unwrap();
    let with = completer.complete(&cond, &[], 0.0, 2, 3).unwrap();
    let without = completer
        .complete_with(&cond, &[], 0.0, 2, 3, false)
        .unwrap();
    let cond = cond.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let n = data.set.pixels();
    let (mut ruled_out, mut kept) = (0, 0);
    for (k, (a, b)) in with.iter().zip(&without).enumerate() {
        for p in 0..n {
            let c = &cond[(k * n + p) * COND_CHANNELS..(k * n + p + 1) * COND_CHANNELS];
            assert!(
                b.amodal[p],
                "the lowest threshold keeps every pixel without the constraint"
            );
            let visible = c[3] > 0.0;
            let behind = c[5] > a.depth_rel[p] * DEPTH_SCALE + FREE_SPACE_MARGIN * DEPTH_SCALE;
            assert_eq!(a.amodal[p], visible || !behind, "pair {k} pixel {p}");
            if a.amodal[p] {
                kept += 1;
            } else {
                ruled_out += 1;
            }
        }
    }
    assert!(
        ruled_out > 0 && kept > 0,
        "{ruled_out} ruled out, {kept} kept"
    );
}

#[test]
fn completer_keeps_the_prior_when_asked_and_averages_more_samples() {
    use deocc_model::data::COND_CHANNELS;
    let data = tiny_pairs();
    let (_dir, mut completer) = completer_after_one_step(&data);
    // A threshold no score passes: the mask is the visible mask, plus the prior when kept.
    completer.mask_threshold = f32::MAX;
    let idx: Vec<usize> = (0..data.len().min(3)).collect();
    let (_, cond) = data
        .batch(&idx, &vec![false; idx.len()], &Device::Cpu)
        .unwrap();
    let plain = completer.complete(&cond, &[], 0.0, 2, 5).unwrap();
    completer.keep_prior = true;
    let kept = completer.complete(&cond, &[], 0.0, 2, 5).unwrap();
    let c = cond.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let n = data.set.pixels();
    let mut prior_only = 0;
    for k in 0..idx.len() {
        for p in 0..n {
            let px = &c[(k * n + p) * COND_CHANNELS..(k * n + p + 1) * COND_CHANNELS];
            let (visible, prior) = (px[3] > 0.0, px[6] > 0.0);
            assert_eq!(plain[k].amodal[p], visible, "pair {k} pixel {p}");
            assert_eq!(kept[k].amodal[p], visible || prior, "pair {k} pixel {p}");
            prior_only += (prior && !visible) as usize;
        }
    }
    assert!(prior_only > 0, "the test pairs have hidden prior pixels");
    // Two samples (the second on the mirrored crop) average into other scores.
    completer.samples = 2;
    let two = completer.complete(&cond, &[], 0.0, 2, 5).unwrap();
    assert_eq!(two.len(), idx.len());
    completer.samples = 1;
    let again = completer.complete(&cond, &[], 0.0, 2, 5).unwrap();
    for (a, b) in plain.iter().zip(&again) {
        assert_eq!(a.mask_score, b.mask_score, "one sample is deterministic");
    }
    let differs = two
        .iter()
        .zip(&plain)
        .any(|(a, b)| a.mask_score.iter().zip(&b.mask_score).any(|(x, y)| x != y));
    assert!(differs, "averaging a second sample changes the scores");
}

#[test]
fn pair_data_carries_the_prior_of_the_model_in_channel_6() {
    use deocc_model::data::COND_CHANNELS;
    let channel6 = |data: &PairData| -> Vec<bool> {
        let (_, cond) = data.batch(&[0], &[false], &Device::Cpu).unwrap();
        let c: Vec<f32> = cond.flatten_all().unwrap().to_vec1().unwrap();
        c.chunks_exact(COND_CHANNELS).map(|p| p[6] > 0.0).collect()
    };
    // From the pair's own view (its other views' points join the prior, below).
    let data = tiny_pairs().with_seen_elsewhere(false);
    assert_eq!(channel6(&data), data.hull_prior(0));
    let data = data.with_mask_prior(MaskPrior::EllipseInFront);
    assert_eq!(channel6(&data), data.ellipse_prior(0));
    assert_eq!(data.condition_prior(0), data.ellipse_prior(0));
    let data = data.with_mask_prior(MaskPrior::EllipseOrBoxInFront);
    let visible: Vec<bool> = data.visible_mask(0).iter().map(|&m| m > 0).collect();
    let n = visible.len();
    let expected = deocc_completion::priors::ellipse_or_box_prior(
        &visible,
        &data.set.scene_depth[..n],
        data.resolution(),
    );
    assert_eq!(channel6(&data), expected);
    assert_eq!(data.condition_prior(0), expected);
    // With the other views' observations the prior takes in the points they keep.
    data.set_seen_elsewhere(true);
    let cond = data.condition(0);
    let with = channel6(&data);
    assert_eq!(with, cond.prior);
    assert!(with.iter().zip(&expected).all(|(&w, &e)| w || !e));
    if let Some(seen) = &cond.seen_elsewhere {
        assert!(seen
            .depth
            .iter()
            .zip(&with)
            .all(|(d, &w)| w || !d.is_finite()));
    }
}

/// With a mask head the constraint is the candidate region (not visible, the scene observed in
/// front of the object's median depth); the head's probabilities lie in [0, 1].
#[test]
fn a_mask_head_adds_pixels_only_where_a_hidden_part_can_be() {
    use deocc_model::data::COND_CHANNELS;
    let data = tiny_pairs();
    let (_dir, mut completer) = completer_after_one_step(&data);
    assert!(completer.model.config.mask_head);
    completer.mask_threshold = f32::MIN;
    let idx: Vec<usize> = (0..data.len().min(4)).collect();
    let (_, cond) = data
        .batch(&idx, &vec![false; idx.len()], &Device::Cpu)
        .unwrap();
    let done = completer.complete(&cond, &[], 0.0, 2, 3).unwrap();
    let cond = cond.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let n = data.set.pixels();
    let mut added = 0;
    for (k, comp) in done.iter().enumerate() {
        let visible: Vec<bool> = (0..n)
            .map(|p| cond[(k * n + p) * COND_CHANNELS + 3] > 0.0)
            .collect();
        for p in 0..n {
            let c = &cond[(k * n + p) * COND_CHANNELS..(k * n + p + 1) * COND_CHANNELS];
            let candidate = c[3] <= 0.0 && c[5] < 0.0;
            assert_eq!(
                comp.amodal[p],
                c[3] > 0.0 || candidate,
                "pair {k} pixel {p}"
            );
            added += (candidate && comp.amodal[p]) as usize;
        }
        let plain = comp.clone().into_crop_completion(&visible, true);
        assert!(plain
            .mask_probability
            .iter()
            .all(|&q| (0.0..=1.0).contains(&q)));
    }
    assert!(added > 0);
}

#[test]
fn crops_carrying_other_views_points_take_their_own_threshold() {
    use deocc_completion::SeenElsewhere;
    use deocc_model::encode::condition_tensor;
    let data = tiny_pairs();
    let (_dir, mut completer) = completer_after_one_step(&data);
    // Every score passes the plain threshold, none the seen-elsewhere one.
    completer.mask_threshold = f32::MIN;
    completer.mask_threshold_seen_elsewhere = Some(f32::MAX);
    let plain = data.condition(0);
    let n = plain.pixels();
    let hidden = (0..n)
        .find(|&k| !plain.visible[k])
        .expect("a pixel the view does not see");
    let mut depth = vec![f32::INFINITY; n];
    depth[hidden] = 0.0;
    let mut seen = plain.clone();
    seen.seen_elsewhere = Some(SeenElsewhere {
        rgb: vec![7; 3 * n],
        depth,
    });
    for (cond, carries) in [(&plain, false), (&seen, true)] {
        assert_eq!(deocc_model::infer::has_seen_elsewhere(cond), carries);
        let t = condition_tensor(&[cond], completer.model.config.mask_prior, &Device::Cpu).unwrap();
        let mut done = completer.complete(&t, &[], 0.0, 2, 9).unwrap().remove(0);
        let before = done.amodal.clone();
        completer.finish(&mut done, cond);
        if carries {
            // The visible pixels and the other view's point; nothing the model added.
            for k in 0..n {
                assert_eq!(done.amodal[k], cond.visible[k] || k == hidden, "pixel {k}");
            }
            assert_eq!(&done.rgb[3 * hidden..3 * hidden + 3], &[7, 7, 7]);
            assert_eq!(done.depth_rel[hidden], 0.0);
        } else {
            assert_eq!(
                done.amodal, before,
                "a one-view crop keeps the plain threshold"
            );
            assert!(
                done.amodal.iter().filter(|&&a| a).count() > cond.visible_px(),
                "the lowest threshold adds pixels to the visible mask"
            );
        }
    }
}
