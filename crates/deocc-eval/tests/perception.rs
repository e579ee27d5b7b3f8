use deocc_eval::perception::{grouping, occlusion_counts, DetectionCounts};
use deocc_pipeline::matching::Threshold;
use deocc_synth::dataset::render_full_scene;
use deocc_synth::scene::SceneConfig;

fn config() -> SceneConfig {
    SceneConfig {
        width: 320,
        height: 240,
        views: 4,
        gt_points_per_m2: 100.0,
        ..SceneConfig::default()
    }
}

/// Occlusion detection with ground-truth masks against the benchmark's definition (amodal area more
/// than 5% above visible), over a few scenes: precision and recall both high.
#[test]
fn occlusion_detection_agrees_with_ground_truth() {
    let mut c = DetectionCounts::default();
    for seed in 0..4 {
        occlusion_counts(&render_full_scene(&config(), 100 + seed).unwrap(), &mut c);
    }
    assert!(
        c.true_positive > 20,
        "too few occluded masks to judge: {c:?}"
    );
    assert!(
        c.f1() > 0.8,
        "precision {:.3}, recall {:.3}, F1 {:.3}",
        c.precision(),
        c.recall(),
        c.f1()
    );
}

/// Cross-view grouping of ground-truth masks: the adaptive threshold recovers the instances, a
/// threshold far too small cannot.
#[test]
fn adaptive_grouping_recovers_instances() {
    let r = render_full_scene(&config(), 7).unwrap();
    let (ari, _, tau) = grouping(&r, Threshold::Adaptive);
    assert!(ari > 0.85, "ARI {ari} with tau {tau}");
    let (tiny, _, _) = grouping(&r, Threshold::Fixed(0.001));
    assert!(
        tiny < ari - 0.2,
        "a 1 mm threshold should split instances: {tiny}"
    );
}
