use deocc_pipeline::input::read_scene;
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
