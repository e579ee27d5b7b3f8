//! Recordings and sequences as input (issue 49): `deocc run` on the MCAP recording that
//! `deocc run --mcap` wrote, and on the same scene in the TUM RGB-D layout, gives the same cloud
//! as on the scene folder.

use std::path::{Path, PathBuf};
use std::process::Command;

use deocc_geometry::{KdIndex, PointCloud};

fn deocc() -> Command {
    Command::new(env!("CARGO_BIN_EXE_deocc"))
}

fn ok(c: &mut Command) -> String {
    let o = c.output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The example scene (bench-v1 scene 0) cut to its first `views` frames.
fn example(dir: &Path, views: usize) -> PathBuf {
    ok(deocc()
        .args([
            "synth", "scenes", "--preset", "bench-v1", "--first", "1", "--out",
        ])
        .arg(dir));
    let scene = dir.join("scene_000000");
    let path = scene.join("cameras.json");
    let mut cams: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    cams["frames"].as_array_mut().unwrap().truncate(views);
    std::fs::write(&path, cams.to_string()).unwrap();
    scene
}

fn cloud(out: &Path) -> PointCloud {
    deocc_io::read_point_cloud(&out.join("completed.ply")).unwrap()
}

/// The completed clouds of two runs agree: over 99% of `a`'s points within 1 mm of `b`'s, point
/// counts within 0.5%.
fn assert_same_cloud(a: &Path, b: &Path) {
    let (a, b) = (cloud(a), cloud(b));
    let index = KdIndex::build(&b.positions).unwrap();
    let d = index.nearest_distances(&a.positions);
    let close = d.iter().filter(|&&x| x <= 0.001).count() as f64 / d.len() as f64;
    let ratio = a.len() as f64 / b.len() as f64;
    assert!(close > 0.99, "{close:.4} of the points within 1 mm");
    assert!(
        (ratio - 1.0).abs() < 0.005,
        "point counts differ: ratio {ratio}"
    );
}

#[test]
fn a_run_recording_reads_back_as_the_scene_it_recorded() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = example(&tmp.path().join("synth"), 3);
    let a = tmp.path().join("a");
    ok(deocc()
        .arg("run")
        .arg(&scene)
        .args(["--completer", "rules", "--mcap", "--out"])
        .arg(&a));
    let b = tmp.path().join("b");
    let said = ok(deocc()
        .arg("run")
        .arg(a.join("recording.mcap"))
        .args(["--completer", "rules", "--out"])
        .arg(&b));
    assert!(said.starts_with("3 frames"), "{said}");
    assert_same_cloud(&b, &a);

    // Bad topics are named, with the topics the file has.
    let o = deocc()
        .arg("run")
        .arg(a.join("recording.mcap"))
        .args([
            "--rgb",
            "/camera/color/image_raw",
            "--completer",
            "rules",
            "--out",
        ])
        .arg(tmp.path().join("c"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("/camera/color/image_raw") && err.contains("/deocc/camera/000000/rgb"),
        "{err}"
    );
}

/// Writes the scene folder `scene` in the TUM layout: colour PNGs, depth in 1/5000 m, poses as
/// quaternions, the intrinsics in camera.json.
fn to_tum(scene: &Path, tum: &Path) {
    std::fs::create_dir_all(tum.join("rgb")).unwrap();
    std::fs::create_dir_all(tum.join("depth")).unwrap();
    let cams = deocc_io::cameras::read_cameras_json(&scene.join("cameras.json")).unwrap();
    let (mut rgb, mut depth, mut gt) = (
        String::from("# colour images\n"),
        String::from("# depth images\n"),
        String::from("# timestamp tx ty tz qx qy qz qw\n"),
    );
    for (k, c) in cams.iter().enumerate() {
        let t = 1305031102.0 + k as f64 * 0.5;
        std::fs::copy(
            scene.join(format!("rgb/{}.png", c.name)),
            tum.join(format!("rgb/{t:.6}.png")),
        )
        .unwrap();
        let mm = image::open(scene.join(format!("depth/{}.png", c.name)))
            .unwrap()
            .into_luma16();
        let tum_units =
            image::ImageBuffer::<image::Luma<u16>, _>::from_fn(mm.width(), mm.height(), |u, v| {
                image::Luma([mm.get_pixel(u, v).0[0].saturating_mul(5)])
            });
        tum_units
            .save(tum.join(format!("depth/{t:.6}.png")))
            .unwrap();
        rgb += &format!("{t:.6} rgb/{t:.6}.png\n");
        // Depth stamped 5 ms later, as a real sensor's would be.
        depth += &format!("{:.6} depth/{t:.6}.png\n", t + 0.005);
        let p = c.world_from_camera.unwrap().cast::<f64>();
        let (tr, q) = (p.translation.vector, p.rotation);
        gt += &format!(
            "{t:.6} {:.9} {:.9} {:.9} {:.12} {:.12} {:.12} {:.12}\n",
            tr.x, tr.y, tr.z, q.i, q.j, q.k, q.w
        );
    }
    std::fs::write(tum.join("rgb.txt"), rgb).unwrap();
    std::fs::write(tum.join("depth.txt"), depth).unwrap();
    std::fs::write(tum.join("groundtruth.txt"), gt).unwrap();
    let k = &cams[0].intrinsics;
    std::fs::write(
        tum.join("camera.json"),
        serde_json::json!({"fx": k.fx(), "fy": k.fy(), "cx": k.cx(), "cy": k.cy()}).to_string(),
    )
    .unwrap();
}

#[test]
fn a_tum_sequence_gives_the_scene_folders_cloud() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = example(&tmp.path().join("synth"), 3);
    // The folder as a TUM sequence has: no instance maps, no scene.json (both segment).
    std::fs::remove_dir_all(scene.join("instances")).unwrap();
    std::fs::remove_file(scene.join("scene.json")).unwrap();
    let tum = tmp.path().join("tum");
    to_tum(&scene, &tum);
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    ok(deocc()
        .arg("run")
        .arg(&scene)
        .args(["--completer", "rules", "--out"])
        .arg(&a));
    let said = ok(deocc()
        .arg("run")
        .arg(&tum)
        .args(["--completer", "rules", "--out"])
        .arg(&b));
    assert!(said.starts_with("3 frames"), "{said}");
    assert_same_cloud(&b, &a);
    // Every second frame only.
    let said = ok(deocc()
        .arg("run")
        .arg(&tum)
        .args(["--every", "2", "--completer", "rules", "--out"])
        .arg(tmp.path().join("c")));
    assert!(said.starts_with("2 frames"), "{said}");
    // A broken list is named with its line.
    std::fs::write(tum.join("depth.txt"), "# x\nnot-a-stamp depth/a.png\n").unwrap();
    let o = deocc()
        .arg("run")
        .arg(&tum)
        .args(["--completer", "rules", "--out"])
        .arg(tmp.path().join("d"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("depth.txt") && err.contains("line 2"), "{err}");
}
