//! A ROS 2 bag (MCAP, CDR as rosbag2 writes it, serialised by cdr-encoding, the ROS 2 client's
//! own serialiser) of what `deocc-ros2 play` publishes reads back through `deocc run`'s recording
//! reader as the scene it came from: the same images, intrinsics, lens and poses.

use deocc_pipeline::recording::{read_mcap, RecordingOptions};
use deocc_ros2::bag::{write_bag, BagTopics};
use deocc_ros2::convert;
use deocc_service::request::request_from_scene;

#[test]
fn a_played_scene_recorded_as_a_bag_reads_back_as_the_scene() {
    let config = deocc_synth::scene::SceneConfig {
        views: 3,
        width: 160,
        height: 120,
        gt_points_per_m2: 100.0,
        ..Default::default()
    };
    let scene = deocc_synth::dataset::render_full_scene(&config, 7)
        .unwrap()
        .scene_input();
    let mut req = request_from_scene(&scene, "");
    // A driver's lens on the colour camera (the images themselves are the pinhole ones, so the
    // read-back is compared against the scene undistorted by the same coefficients).
    for f in &mut req.frames {
        let info = f.camera_info.as_mut().unwrap();
        info.distortion_model = "plumb_bob".into();
        info.d = vec![-0.05, 0.01, 0.0, 0.0, 0.0];
    }
    let views = convert::views_from_request(&req, 1_000_000_000, 100_000_000, "cam", "world");
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("bag.mcap");
    let topics = BagTopics {
        rgb: "/camera/color/image_raw".into(),
        depth: "/camera/aligned_depth_to_color/image_raw".into(),
        info: "/camera/color/camera_info".into(),
        pose: Some("/camera/pose".into()),
    };
    write_bag(&path, &views, &topics).unwrap();
    let opts = RecordingOptions {
        rgb: Some(topics.rgb.clone()),
        depth: Some(topics.depth.clone()),
        info: Some(topics.info.clone()),
        poses: topics.pose.clone(),
        ..Default::default()
    };
    let back = read_mcap(&path, &opts).unwrap();
    assert!(back.posed);
    assert_eq!(back.frames.len(), scene.frames.len());
    let lens = deocc_io::cameras::Lens {
        distortion: deocc_geometry::distortion::Distortion::from_ros(
            "plumb_bob",
            &[-0.05, 0.01, 0.0, 0.0, 0.0],
        )
        .unwrap(),
        ..Default::default()
    };
    for (a, b) in scene.frames.iter().zip(&back.frames) {
        assert_eq!(a.camera.intrinsics, b.camera.intrinsics);
        let (rgb, depth, _) = deocc_io::lens::to_pinhole(
            a.rgb.clone(),
            a.depth.clone(),
            None,
            &a.camera.intrinsics,
            &lens,
        );
        assert_eq!(rgb, b.rgb, "colour differs");
        assert_eq!(depth.data(), b.depth.data(), "depth differs");
        let d = a.camera.world_from_camera.inverse() * b.camera.world_from_camera;
        assert!(d.translation.vector.norm() < 1e-5 && d.rotation.angle() < 1e-5);
    }
    // A pose topic that is not in the bag is named, with the bag's topics.
    let e = read_mcap(
        &path,
        &RecordingOptions {
            poses: Some("/nope".into()),
            ..opts
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("/nope") && e.contains("/camera/pose"), "{e}");
}
