//! `deocc grasp` and `deocc place` on a pickup-v1 scene: answers with pictures, and clear errors.

use std::path::{Path, PathBuf};
use std::process::Command;

fn deocc() -> Command {
    Command::new(env!("CARGO_BIN_EXE_deocc"))
}

/// The first pickup-v1 scene, written to `dir`, and its target id.
fn pickup_scene(dir: &Path) -> (PathBuf, u64) {
    let o = deocc()
        .args([
            "synth",
            "scenes",
            "--preset",
            "pickup-v1",
            "--first",
            "1",
            "--out",
        ])
        .arg(dir)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let scene = dir.join("scene_000000");
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("scene.json")).unwrap()).unwrap();
    (
        scene,
        info["target"]
            .as_u64()
            .expect("pickup scenes name a target"),
    )
}

#[test]
fn grasp_and_place_answer_with_json_and_pictures_and_refuse_bad_requests() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, target) = pickup_scene(&tmp.path().join("pickup"));
    let out = tmp.path().join("grasps");
    let o = deocc()
        .arg("grasp")
        .arg(&scene)
        .args([
            "--target",
            &target.to_string(),
            "--completer",
            "rules",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let answer: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("grasps.json")).unwrap()).unwrap();
    let grasps = answer["grasps"].as_array().unwrap();
    assert!(!grasps.is_empty(), "no grasp on the completed target");
    let scores: Vec<f64> = grasps
        .iter()
        .map(|g| g["score"].as_f64().unwrap())
        .collect();
    assert!(scores.windows(2).all(|w| w[0] >= w[1]), "{scores:?}");
    assert!(grasps
        .iter()
        .all(|g| g["width"].as_f64().unwrap() <= 0.085 + 1e-6));
    assert!(out.join("grasps.png").exists());

    // A target that is not in the scene: the ids that are.
    let o = deocc()
        .arg("grasp")
        .arg(&scene)
        .args(["--target", "999", "--completer", "rules"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--target 999") && err.contains("instances"),
        "{err}"
    );

    let out = tmp.path().join("place");
    let o = deocc()
        .arg("place")
        .arg(&scene)
        .args([
            "--footprint",
            "0.08,0.06",
            "--height",
            "0.1",
            "--completer",
            "rules",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let answer: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("placement.json")).unwrap())
            .unwrap();
    let z = answer["placement"]["position"][2].as_f64().unwrap();
    assert!(
        (0.6..0.85).contains(&z),
        "placed at height {z}, not on the table"
    );
    assert!(answer["placeable_cells"].as_u64().unwrap() > 0);
    assert!(out.join("placement.png").exists());

    // A footprint larger than every surface.
    let o = deocc()
        .arg("place")
        .arg(&scene)
        .args(["--footprint", "3,3", "--completer", "rules"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("larger than every support surface") || err.contains("no placeable spot"),
        "{err}"
    );
}

/// `eval grasp` takes the pipeline's options (`--options`) and the planner's (`--grasp-options`)
/// under two names, and a missing file of either is named before anything runs.
#[test]
fn eval_grasp_names_each_options_file() {
    let dir = tempfile::tempdir().unwrap();
    for (flag, name) in [
        ("--options", "no_pipeline.json"),
        ("--grasp-options", "no_planner.json"),
    ] {
        let out = deocc()
            .args(["eval", "grasp", "--scenes", "1", "--json"])
            .arg(dir.path().join("grasp.json"))
            .arg(flag)
            .arg(dir.path().join(name))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{flag}: {err}");
        assert!(err.contains(name), "{flag}: {err}");
        assert!(!dir.path().join("grasp.json").exists());
    }
}

/// `--target-pixel` on the example scene (bench-v1 scene 0): a pixel well inside an object's
/// visible mask in the first view is answered with that object; a pixel on nothing says where
/// the instances are.
#[test]
fn grasp_takes_the_target_by_pixel_on_the_example() {
    let tmp = tempfile::tempdir().unwrap();
    let o = deocc()
        .args([
            "synth", "scenes", "--preset", "bench-v1", "--first", "1", "--out",
        ])
        .arg(tmp.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let scene = tmp.path().join("scene_000000");
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("scene.json")).unwrap()).unwrap();
    let structure: Vec<u64> = info["objects"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|o| o["structure"].as_bool() == Some(true))
        .map(|o| o["instance_id"].as_u64().unwrap())
        .collect();
    let ids = image::open(scene.join("instances/000000.png"))
        .unwrap()
        .into_luma16();
    // The object pixel deepest inside its own mask (largest all-same square around it).
    let (w, h) = ids.dimensions();
    let mut best = (0u32, 0u32, 0u32, 0u16);
    for v in 0..h {
        for u in 0..w {
            let id = ids.get_pixel(u, v).0[0];
            if id == 0 || structure.contains(&(id as u64)) {
                continue;
            }
            let mut r = 0;
            while r < 40
                && u > r
                && v > r
                && u + r + 1 < w
                && v + r + 1 < h
                && [
                    (u - r - 1, v),
                    (u + r + 1, v),
                    (u, v - r - 1),
                    (u, v + r + 1),
                ]
                .iter()
                .all(|&(a, b)| ids.get_pixel(a, b).0[0] == id)
            {
                r += 1;
            }
            if r > best.2 {
                best = (u, v, r, id);
            }
        }
    }
    let (u, v, r, id) = best;
    assert!(r >= 5, "no object is visible in the first view");
    let o = deocc()
        .arg("grasp")
        .arg(&scene)
        .args([
            "--target-pixel",
            &format!("{u},{v}"),
            "--completer",
            "rules",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let answer: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(answer["target"].as_u64(), Some(id as u64), "{answer}");
    assert!(answer["target_picked_by"]
        .as_str()
        .unwrap()
        .contains("--target-pixel"));
    assert!(answer["target_points"].as_u64().unwrap() > 0);
    // Outside the image: refused, naming the flag and the view's size.
    let o = deocc()
        .arg("grasp")
        .arg(&scene)
        .args(["--target-pixel", "5000,10", "--completer", "rules"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--target-pixel") && err.contains("outside"),
        "{err}"
    );
    // An unknown view is named with the ones there are.
    let o = deocc()
        .arg("grasp")
        .arg(&scene)
        .args([
            "--target-pixel",
            "1,1",
            "--target-view",
            "nope",
            "--completer",
            "rules",
        ])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("\"nope\"") && err.contains("000000"), "{err}");
}

/// A target in the masks whose depth the sensor never measured (a projector's shadow over all
/// of it) is answered, not refused: no grasp, and why.
#[test]
fn a_target_without_depth_is_answered_with_why() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, target) = pickup_scene(&tmp.path().join("pickup"));
    let cams: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join("cameras.json")).unwrap())
            .unwrap();
    for f in cams["frames"].as_array().unwrap() {
        let name = f["name"].as_str().unwrap();
        let ids = image::open(scene.join(format!("instances/{name}.png")))
            .unwrap()
            .into_luma16();
        let path = scene.join(format!("depth/{name}.png"));
        let mut depth = image::open(&path).unwrap().into_luma16();
        for (x, y, p) in depth.enumerate_pixels_mut() {
            if u64::from(ids.get_pixel(x, y).0[0]) == target {
                p.0[0] = 0;
            }
        }
        depth.save(&path).unwrap();
    }
    let o = deocc()
        .arg("grasp")
        .arg(&scene)
        .args(["--target", &target.to_string(), "--observed"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let answer: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(answer["grasps"].as_array().map(Vec::len), Some(0));
    let why = answer["why"].as_str().unwrap();
    assert!(
        why.contains("no measured depth") && why.contains("nothing to grasp"),
        "{why}"
    );
}
