use deocc_io::images::InstanceMap;
use deocc_pipeline::input::read_scene;
use deocc_pipeline::occlusion::analyse_view;
use deocc_synth::dataset::{render_full_scene, write_scene};
use deocc_synth::scene::SceneConfig;

fn config() -> SceneConfig {
    SceneConfig {
        width: 320,
        height: 240,
        views: 4,
        gt_points_per_m2: 1000.0,
        ..SceneConfig::default()
    }
}

/// Occlusion detection with ground-truth masks against the benchmark's definition (amodal area more
/// than 5% above visible), over a few scenes: precision and recall both high.
#[test]
fn occlusion_detection_agrees_with_ground_truth() {
    let (mut tp, mut fp, mut fneg) = (0, 0, 0);
    for seed in 0..4 {
        let r = render_full_scene(&config(), 100 + seed).unwrap();
        let structure: Vec<u16> = r
            .scene
            .objects
            .iter()
            .filter(|o| o.category.is_structure())
            .map(|o| o.instance_id)
            .collect();
        for view in &r.views {
            let map = InstanceMap {
                width: view.frame.width,
                height: view.frame.height,
                ids: view.frame.instance.clone(),
            };
            let found = analyse_view(&map, &view.depth);
            for vis in &view.visibility {
                if structure.contains(&vis.instance_id) || vis.truncated || vis.visible_px < 50 {
                    continue;
                }
                let truth = vis.is_occluded();
                let predicted = found
                    .iter()
                    .any(|m| m.instance_id == vis.instance_id && m.is_occluded());
                match (predicted, truth) {
                    (true, true) => tp += 1,
                    (true, false) => fp += 1,
                    (false, true) => fneg += 1,
                    _ => {}
                }
            }
        }
    }
    let precision = tp as f64 / (tp + fp).max(1) as f64;
    let recall = tp as f64 / (tp + fneg).max(1) as f64;
    let f1 = 2.0 * precision * recall / (precision + recall);
    assert!(tp > 20, "too few occluded masks to judge: {tp}");
    assert!(
        f1 > 0.8,
        "precision {precision:.3}, recall {recall:.3}, F1 {f1:.3}"
    );
}

#[test]
fn scene_folder_errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let e = read_scene(dir.path()).err().unwrap().to_string();
    assert!(e.contains("cameras.json"), "{e}");
    let r = render_full_scene(&config(), 5).unwrap();
    write_scene(dir.path(), &config(), &r).unwrap();
    assert_eq!(read_scene(dir.path()).unwrap().frames.len(), 4);
    // A depth frame of the wrong size.
    let depth = dir.path().join("depth/000002.png");
    deocc_io::images::write_depth_png(&depth, &deocc_geometry::DepthMap::zeros(10, 10)).unwrap();
    let e = read_scene(dir.path()).err().unwrap().to_string();
    assert!(e.contains("000002.png"), "{e}");
    // A missing RGB frame.
    std::fs::remove_file(dir.path().join("rgb/000001.png")).unwrap();
    let e = read_scene(dir.path()).err().unwrap().to_string();
    assert!(e.contains("000001.png"), "{e}");
}
