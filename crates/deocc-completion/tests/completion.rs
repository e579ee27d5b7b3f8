use deocc_completion::crop::mirror;
use deocc_completion::priors::{ellipse_or_box_prior, ellipse_prior, hull_prior, mask_prior};
use deocc_completion::rules::{
    fit_plane_huber, nearest_seed, plane_near_side, symmetric_far_side, RulesCompleter,
};
use deocc_completion::{
    Completer, CompleterChain, CompletionError, CompletionOptions, CropCompletion, CropCondition,
    CropRequest, MaskPrior, Provenance,
};
use deocc_geometry::mask2d::iou;
use proptest::prelude::*;

proptest! {
    /// The two-pass propagation finds a nearest seed (by squared distance) on random masks.
    #[test]
    fn nearest_seed_matches_brute_force(bits in proptest::collection::vec(0u8..12, 16 * 16)) {
        let r = 16;
        let seeds: Vec<bool> = bits.iter().map(|&b| b == 0).collect();
        let near = nearest_seed(&seeds, r);
        let d2 = |p: usize, s: usize| {
            let (du, dv) = ((p % r) as i64 - (s % r) as i64, (p / r) as i64 - (s / r) as i64);
            du * du + dv * dv
        };
        for (p, &found) in near.iter().enumerate() {
            let best = (0..r * r).filter(|&s| seeds[s]).map(|s| d2(p, s)).min();
            match (best, found) {
                (None, None) => {}
                (Some(b), Some(s)) => {
                    prop_assert!(seeds[s]);
                    // Two-pass propagation may be off by a little in rare configurations.
                    prop_assert!(d2(p, s) as f64 <= b as f64 * 1.25 + 2.0, "pixel {p}: {} vs {b}", d2(p, s));
                }
                other => prop_assert!(false, "pixel {p}: {other:?}"),
            }
        }
    }

    /// Mirroring twice is the identity.
    #[test]
    fn mirror_is_an_involution(x in proptest::collection::vec(any::<u8>(), 5 * 5 * 3)) {
        prop_assert_eq!(mirror(&mirror(&x, 5, 3), 5, 3), x);
    }
}

#[test]
fn plane_fit_recovers_a_plane_despite_outliers() {
    let mut pts = Vec::new();
    for i in 0..20 {
        for j in 0..20 {
            let (x, y) = (i as f64 / 20.0, j as f64 / 20.0);
            pts.push((x, y, 0.3 * x - 0.2 * y + 0.05));
        }
    }
    // 10% gross outliers.
    for p in pts.iter_mut().step_by(10) {
        p.2 += 0.5;
    }
    let [a, b, c] = fit_plane_huber(&pts);
    assert!((a - 0.3).abs() < 0.01, "a = {a}");
    assert!((b + 0.2).abs() < 0.01, "b = {b}");
    assert!((c - 0.05).abs() < 0.01, "c = {c}");
    // Too few points: the median.
    assert_eq!(
        fit_plane_huber(&[(0.0, 0.0, 1.0), (1.0, 0.0, 3.0)]),
        [0.0, 0.0, 3.0]
    );
}

#[test]
fn near_side_keeps_visible_depth_and_extends_the_plane() {
    let r = 8;
    let visible: Vec<bool> = (0..r * r).map(|p| p % r < 4).collect();
    let depth: Vec<f32> = (0..r * r)
        .map(|p| {
            if visible[p] {
                0.1 * ((p % r) as f32 + 0.5) / r as f32
            } else {
                0.0
            }
        })
        .collect();
    let near = plane_near_side(&depth, &visible, r);
    for (p, &z) in near.iter().enumerate() {
        let expected = 0.1 * ((p % r) as f32 + 0.5) / r as f32;
        assert!((z - expected).abs() < 1e-4, "pixel {p}");
    }
}

#[test]
fn far_side_of_a_cylinder_mirrors_its_front() {
    // A cylinder of radius 0.25 crop widths seen from the side: the front at each column is
    // z_c - sqrt(R^2 - x^2); the back should be z_c + sqrt(R^2 - x^2).
    let r = 32;
    let (radius, zc) = (0.25f32, 0.1f32);
    let mut amodal = vec![false; r * r];
    let mut near = vec![0f32; r * r];
    for v in 4..28 {
        for u in 8..24 {
            let p = v * r + u;
            amodal[p] = true;
            let x = (u as f32 + 0.5) / r as f32 - 0.5;
            near[p] = zc - (radius * radius - x * x).max(0.0).sqrt();
        }
    }
    let back = symmetric_far_side(&near, &amodal, r);
    for p in (0..r * r).filter(|&p| amodal[p]) {
        let x = ((p % r) as f32 + 0.5) / r as f32 - 0.5;
        let expected = zc + (radius * radius - x * x).max(0.0).sqrt();
        assert!(
            (back[p] - expected).abs() < 0.01,
            "pixel {p}: {} vs {expected}",
            back[p]
        );
        assert!(back[p] >= near[p]);
    }
    assert!(back.iter().zip(&amodal).all(|(&b, &a)| a || b == 0.0));
}

/// A 32x32 crop: a disk whose right part is hidden behind an occluder in front of it.
fn occluded_disk() -> CropCondition {
    let r = 32;
    let (cx, cy, rad) = (14.0f32, 16.0f32, 9.0f32);
    let disk: Vec<bool> = (0..r * r)
        .map(|p| {
            let (u, v) = ((p % r) as f32 + 0.5, (p / r) as f32 + 0.5);
            (u - cx).powi(2) + (v - cy).powi(2) <= rad * rad
        })
        .collect();
    let occluder = |p: usize| p % r >= 16;
    let visible: Vec<bool> = (0..r * r).map(|p| disk[p] && !occluder(p)).collect();
    let scene: Vec<f32> = (0..r * r)
        .map(|p| {
            if occluder(p) {
                -0.4
            } else if disk[p] {
                0.0
            } else {
                0.6
            }
        })
        .collect();
    let rgb: Vec<u8> = (0..r * r)
        .flat_map(|p| {
            if visible[p] {
                [200, 40, 10]
            } else {
                [90, 90, 90]
            }
        })
        .collect();
    let depth = vec![0f32; r * r];
    CropCondition::new(r, rgb, visible, depth, scene, Some(0.3))
}

#[test]
fn rules_completer_fills_the_hidden_part_of_a_disk() {
    let crop = occluded_disk();
    let rules = RulesCompleter {
        resolution: 32,
        ..Default::default()
    };
    let out = rules
        .complete(
            &[CropRequest {
                condition: &crop,
                other_views: &[],
            }],
            &CompletionOptions::default(),
        )
        .unwrap();
    let c = &out[0];
    let hidden_added = (0..crop.pixels())
        .filter(|&p| c.amodal[p] && !crop.visible[p])
        .count();
    assert!(
        hidden_added > 20,
        "the prior continues the disk: {hidden_added} px"
    );
    for p in 0..crop.pixels() {
        if crop.visible[p] {
            assert!(c.amodal[p]);
            assert_eq!(c.mask_probability[p], 1.0);
        }
        if c.amodal[p] && !crop.visible[p] {
            // Hidden pixels take the object's colour, not the occluder's.
            assert_eq!(&c.rgb[3 * p..3 * p + 3], &[200, 40, 10]);
            assert!(c.back_depth[p] >= c.depth[p]);
        }
        if !c.amodal[p] {
            assert_eq!(c.mask_probability[p], 0.0);
        }
    }
    assert_eq!(rules.provenance(), Provenance::Rules);
}

#[test]
fn the_default_prior_is_the_ellipse_or_box_prior_and_mirrors_with_the_crop() {
    let crop = occluded_disk();
    let r = crop.resolution;
    assert_eq!(
        crop.prior,
        ellipse_or_box_prior(&crop.visible, &crop.scene_depth, r)
    );
    assert_eq!(
        crop.prior_of(MaskPrior::HullInFront),
        hull_prior(&crop.visible, &crop.scene_depth, r)
    );
    assert_eq!(
        mask_prior(
            MaskPrior::EllipseInFront,
            &crop.visible,
            &crop.scene_depth,
            r
        ),
        ellipse_prior(&crop.visible, &crop.scene_depth, r)
    );
    let m = crop.mirrored();
    assert_eq!(m.mirrored(), crop);
    assert_eq!(m.visible_px(), crop.visible_px());
    // Candidates: not visible and the scene in front.
    let cand = crop.candidates();
    assert!(cand
        .iter()
        .enumerate()
        .all(|(p, &c)| c == (!crop.visible[p] && crop.scene_depth[p] < 0.0)));
}

/// Declines crops wider than a limit; completes the rest with an empty mask.
struct Narrow(f32);

impl Completer for Narrow {
    fn name(&self) -> &str {
        "narrow"
    }
    fn provenance(&self) -> Provenance {
        Provenance::Model
    }
    fn resolution(&self) -> usize {
        16
    }
    fn decline(&self, c: &CropCondition) -> Option<String> {
        (c.crop_width_m.unwrap_or(0.0) > self.0).then(|| "too wide".to_string())
    }
    fn complete(
        &self,
        batch: &[CropRequest<'_>],
        _: &CompletionOptions,
    ) -> Result<Vec<CropCompletion>, CompletionError> {
        Err(CompletionError::Failed {
            completer: "narrow".into(),
            msg: format!("not used here ({} crops)", batch.len()),
        })
    }
}

#[test]
fn a_chain_hands_declined_crops_to_the_next_completer() {
    let chain = CompleterChain::single(Narrow(0.5)).then(RulesCompleter::default());
    assert_eq!(chain.describe(), "narrow,rules");
    let crop_of_width = |w: f32| {
        move |res: usize| {
            let mut c = occluded_disk();
            c.crop_width_m = Some(w);
            (res >= 16).then_some(c)
        }
    };
    let (k, crop) = chain.route(crop_of_width(0.3)).unwrap();
    assert_eq!(k, 0);
    assert_eq!(crop.crop_width_m, Some(0.3));
    let (k, _) = chain.route(crop_of_width(1.5)).unwrap();
    assert_eq!(k, 1, "a wide crop goes to the rules");
    let only_narrow = CompleterChain::single(Narrow(0.5));
    let reasons = only_narrow.route(crop_of_width(1.5)).unwrap_err();
    assert_eq!(reasons, vec!["narrow: too wide".to_string()]);
    let none_built = only_narrow.route(|_| None).unwrap_err();
    assert!(none_built[0].contains("no crop"));
}

/// A disk of radius 10 in a 32x32 crop whose right part is hidden by an occluder in front; the
/// rest of the crop is background behind the object.
fn occluded_disk_masks() -> (Vec<bool>, Vec<bool>, Vec<f32>) {
    let r = 32;
    let disk: Vec<bool> = (0..r * r)
        .map(|p| {
            let (x, y) = ((p % r) as f32 + 0.5 - 16.0, (p / r) as f32 + 0.5 - 16.0);
            x * x + y * y <= 100.0
        })
        .collect();
    let occluder = |p: usize| p % r >= 18;
    let visible: Vec<bool> = (0..r * r).map(|p| disk[p] && !occluder(p)).collect();
    let scene: Vec<f32> = (0..r * r)
        .map(|p| match (occluder(p), disk[p]) {
            (true, _) => -0.5,
            (false, true) => 0.0,
            (false, false) => 0.6,
        })
        .collect();
    (disk, visible, scene)
}

#[test]
fn ellipse_prior_continues_a_disk_behind_its_occluder() {
    let (disk, visible, scene) = occluded_disk_masks();
    let hull = hull_prior(&visible, &scene, 32);
    let ellipse = ellipse_prior(&visible, &scene, 32);
    let (iou_hull, iou_ellipse) = (iou(&hull, &disk), iou(&ellipse, &disk));
    // The contour is fitted through pixel centres, half a pixel inside the silhouette, so the
    // ellipse is a little smaller than the disk (0.94 here).
    assert!(iou_ellipse > 0.9, "ellipse prior IoU {iou_ellipse}");
    assert!(
        iou_ellipse > iou_hull + 0.2,
        "{iou_ellipse} vs hull {iou_hull}"
    );
    // It extends the hull and never where the scene is seen behind the object.
    for p in 0..32 * 32 {
        assert!(!hull[p] || ellipse[p]);
        assert!(!ellipse[p] || visible[p] || scene[p] < 0.0, "pixel {p}");
    }
    // A contour too short to fit leaves the hull as it is.
    let speck: Vec<bool> = (0..32 * 32).map(|p| p == 5 * 32 + 5).collect();
    assert_eq!(
        ellipse_prior(&speck, &scene, 32),
        hull_prior(&speck, &scene, 32)
    );
}

#[test]
fn ellipse_or_box_prior_fills_the_hidden_corner_of_a_rectangle() {
    let r = 32;
    let rect: Vec<bool> = (0..r * r)
        .map(|p| (6..26).contains(&(p % r)) && (8..24).contains(&(p / r)))
        .collect();
    // An occluder in front of the lower right corner.
    let occluder = |p: usize| p % r >= 18 && p / r >= 16;
    let visible: Vec<bool> = (0..r * r).map(|p| rect[p] && !occluder(p)).collect();
    let scene: Vec<f32> = (0..r * r)
        .map(|p| match (occluder(p), rect[p]) {
            (true, _) => -0.5,
            (false, true) => 0.0,
            (false, false) => 0.6,
        })
        .collect();
    let hull = hull_prior(&visible, &scene, r);
    let ellipse = ellipse_prior(&visible, &scene, r);
    let with_box = ellipse_or_box_prior(&visible, &scene, r);
    let (h, e, b) = (
        iou(&hull, &rect),
        iou(&ellipse, &rect),
        iou(&with_box, &rect),
    );
    // The seen outline spans the whole rectangle, so its box is the rectangle.
    assert!(b > 0.99, "ellipse-or-box prior IoU {b}");
    assert!(b > h + 0.05 && b > e, "{b} vs hull {h}, ellipse {e}");
    for p in 0..r * r {
        assert!(
            !ellipse[p] || with_box[p],
            "keeps the ellipse prior (pixel {p})"
        );
        assert!(!with_box[p] || visible[p] || scene[p] < 0.0, "pixel {p}");
    }
    let speck: Vec<bool> = (0..r * r).map(|p| p == 5 * r + 5).collect();
    assert_eq!(
        ellipse_or_box_prior(&speck, &scene, r),
        hull_prior(&speck, &scene, r)
    );
}

/// Another view saw the hidden right part of the disk: the rules keep those points' colour and
/// depth and put them in the mask; a point the crop's own measurement contradicts (the scene
/// seen behind it or at its depth) and points on visible pixels change nothing.
#[test]
fn points_other_views_saw_join_the_rules_completion_unless_the_crop_contradicts_them() {
    let crop = occluded_disk();
    let r = crop.resolution;
    let (cx, cy, rad) = (14.0f32, 16.0f32, 9.0f32);
    let in_disk = |p: usize| {
        let (u, v) = ((p % r) as f32 + 0.5, (p / r) as f32 + 0.5);
        (u - cx).powi(2) + (v - cy).powi(2) <= rad * rad
    };
    // Seen elsewhere: the hidden half of the disk at depth -0.1, green; one pixel outside the
    // disk where the crop sees the background behind it (scene 0.6 > -0.1 + tolerance); one
    // visible pixel.
    let hidden: Vec<usize> = (0..r * r)
        .filter(|&p| in_disk(p) && !crop.visible[p])
        .collect();
    let contradicted = 16 * r + 2; // left of the disk, background at 0.6
    assert!(!in_disk(contradicted) && crop.scene_depth[contradicted] > 0.5);
    let on_visible = 16 * r + 10;
    assert!(crop.visible[on_visible]);
    let mut depth = vec![f32::INFINITY; r * r];
    let mut rgb = vec![0u8; 3 * r * r];
    for &p in hidden.iter().chain([&contradicted, &on_visible]) {
        depth[p] = -0.1;
        rgb[3 * p..3 * p + 3].copy_from_slice(&[10, 200, 30]);
    }
    let with = crop
        .clone()
        .with_seen_elsewhere(deocc_completion::SeenElsewhere { rgb, depth });
    let kept = with.seen_elsewhere.as_ref().expect("kept");
    assert!(hidden.iter().all(|&p| kept.depth[p] == -0.1));
    assert!(!kept.depth[contradicted].is_finite());
    assert!(!kept.depth[on_visible].is_finite());
    assert!(hidden.iter().all(|&p| with.prior[p]), "prior covers them");
    assert!(!with.prior[contradicted]);

    let rules = RulesCompleter {
        resolution: r,
        ..Default::default()
    };
    let (alone, both) = (rules.complete_one(&crop), rules.complete_one(&with));
    for &p in &hidden {
        assert!(both.amodal[p]);
        assert_eq!(&both.rgb[3 * p..3 * p + 3], &[10, 200, 30]);
        assert_eq!(both.depth[p], -0.1);
    }
    // Alone, the hidden half is filled from the visible colour and the plane at 0.
    let p = hidden[hidden.len() / 2];
    assert_eq!(&alone.rgb[3 * p..3 * p + 3], &[200, 40, 10]);
    assert!(alone.depth[p].abs() < 1e-3);
    // Visible pixels keep what this view saw.
    assert_eq!(
        &both.rgb[3 * on_visible..3 * on_visible + 3],
        &[200, 40, 10]
    );
    assert_eq!(both.depth[on_visible], 0.0);
    // Where this view sees another surface at the point's own depth, the views disagree about
    // what is there: the point is dropped.
    let mut same_depth = crop.clone();
    same_depth.scene_depth[contradicted] = -0.1;
    let mut one = vec![f32::INFINITY; r * r];
    one[contradicted] = -0.1;
    let dropped = same_depth.with_seen_elsewhere(deocc_completion::SeenElsewhere {
        rgb: vec![0; 3 * r * r],
        depth: one,
    });
    assert!(dropped.seen_elsewhere.is_none());
    // Mirroring carries the observations along.
    let m = with.mirrored();
    let q = (p / r) * r + (r - 1 - p % r);
    assert_eq!(m.seen_elsewhere.as_ref().unwrap().depth[q], -0.1);
    assert_eq!(m.mirrored(), with);
}
