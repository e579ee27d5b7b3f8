//! The built binary on real files in a temporary directory: exit codes and messages.

use std::process::Command;

fn deocc() -> Command {
    Command::new(env!("CARGO_BIN_EXE_deocc"))
}

#[test]
fn synth_scenes_writes_the_documented_layout() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scenes");
    let o = deocc()
        .args([
            "synth",
            "scenes",
            "--count",
            "2",
            "--seed",
            "3",
            "--views",
            "2",
            "--width",
            "96",
            "--height",
            "72",
            "--gt-density",
            "500",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in [
        "manifest.json",
        "stats.json",
        "scene_000001/cameras.json",
        "scene_000000/rgb/000001.png",
        "scene_000000/depth/000000.png",
        "scene_000000/instances/000000.png",
        "scene_000000/ground_truth.ply",
        "scene_000000/scene.json",
    ] {
        assert!(out.join(f).exists(), "missing {f}");
    }
    let gt = deocc_io::ply::read_ply(&out.join("scene_000000/ground_truth.ply")).unwrap();
    assert!(gt.extra("seen").is_some());
    assert!(gt.vertices.instance.is_some());
}

#[test]
fn bad_inputs_fail_with_the_file_named() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.safetensors");
    let o = deocc()
        .args(["synth", "sheet", "--out"])
        .arg(dir.path().join("x.png"))
        .arg("--pairs")
        .arg(&missing)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("nope.safetensors"), "{err}");

    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let o = deocc()
        .args(["train", "--run"])
        .arg(dir.path().join("run"))
        .arg("--data")
        .arg(&empty)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("no train-") && err.contains("empty"), "{err}");

    let o = deocc()
        .args(["train", "--mask-prior", "hull", "--run"])
        .arg(dir.path().join("run2"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--mask-prior 'hull'"), "{err}");
    assert!(!dir.path().join("run2").exists(), "nothing is written");

    let o = deocc()
        .args(["synth", "scenes", "--preset", "bench-v9", "--out"])
        .arg(dir.path().join("s"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown preset"));

    let o = deocc()
        .args(["synth", "scenes", "--mesh", "bunny.ply", "--out"])
        .arg(dir.path().join("m"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("PATH=SIZE_M"));
}

/// `--sensor` measures a preset's scenes too (it was once ignored beside `--preset`): the
/// structured-light sensor leaves pixels without depth that the clean render has.
#[test]
fn a_preset_is_measured_by_the_sensor_named() {
    let dir = tempfile::tempdir().unwrap();
    let holes = |sensor: &str| {
        let out = dir.path().join(sensor);
        let o = deocc()
            .args([
                "synth", "scenes", "--preset", "place-v1", "--first", "1", "--sensor", sensor,
                "--out",
            ])
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let d =
            deocc_io::images::read_depth_png(&out.join("scene_000000/depth/000000.png")).unwrap();
        d.data().iter().filter(|&&z| z <= 0.0).count() as f64 / d.data().len() as f64
    };
    let (clean, sensor) = (holes("clean"), holes("structured-light"));
    assert!(
        sensor > clean + 0.05,
        "pixels without depth: {clean:.3} clean, {sensor:.3} with the sensor"
    );
}

/// `--from-seed` renders a preset's kind of scene from other seeds (its tuning scenes), where a
/// study looks at one scene without looking at the test split.
#[test]
fn a_preset_renders_from_another_seed() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s");
    let o = deocc()
        .args([
            "synth",
            "scenes",
            "--preset",
            "place-v1",
            "--from-seed",
            "9350003",
            "--first",
            "2",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for (k, seed) in [(0, 9_350_003u64), (1, 9_350_004)] {
        let text = std::fs::read_to_string(out.join(format!("scene_{k:06}/scene.json"))).unwrap();
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v["seed"].as_u64(), Some(seed), "scene {k}");
        assert_eq!(v["config"]["kind"], "place", "scene {k}");
    }
    assert!(!out.join("scene_000002").exists());
    // Seeds past the last one are refused, naming the flag, before anything is written.
    let late = dir.path().join("late");
    let o = deocc()
        .args(["synth", "scenes", "--preset", "place-v1", "--from-seed"])
        .arg(u64::MAX.to_string())
        .arg("--out")
        .arg(&late)
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--from-seed"));
    assert!(!late.exists());
}

/// `--burst K` renders K frames from each pose, each with its own sensor noise; `deocc run` fuses
/// them into one frame (the report says which) with fewer pixels missing than any one of them;
/// a command that measures frames one at a time refuses `--burst` instead of ignoring it.
#[test]
fn a_burst_is_rendered_and_fused_into_one_frame() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = dir.path().join("scenes");
    let o = deocc()
        .args([
            "synth",
            "scenes",
            "--preset",
            "place-v1",
            "--first",
            "1",
            "--sensor",
            "structured-light",
            "--burst",
            "3",
            "--out",
        ])
        .arg(&scenes)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let scene = scenes.join("scene_000000");
    let holes = |d: &deocc_geometry::DepthMap| d.data().iter().filter(|&&z| z <= 0.0).count();
    let frames: Vec<_> = (0..3)
        .map(|k| {
            deocc_io::images::read_depth_png(&scene.join(format!("depth/{k:06}.png"))).unwrap()
        })
        .collect();
    assert_ne!(
        frames[0].data(),
        frames[1].data(),
        "each frame its own noise"
    );
    let run = |name: &str, options: &str| -> serde_json::Value {
        let out = dir.path().join(name);
        let opts = dir.path().join(format!("{name}.json"));
        std::fs::write(&opts, options).unwrap();
        let o = deocc()
            .arg("run")
            .arg(&scene)
            .args(["--completer", "rules", "--options"])
            .arg(&opts)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap()
    };
    let fused = run("fused", "{}");
    assert_eq!(fused["burst"]["frames_in"], 3, "{}", fused["burst"]);
    assert_eq!(fused["burst"]["frames_out"], 1);
    assert_eq!(fused["burst"]["bursts"][0].as_array().unwrap().len(), 3);
    let apart = run("apart", r#"{"burst": {"enabled": false}}"#);
    assert_eq!(apart["burst"]["frames_out"], 3);
    // The front end measures each frame's own noise: the fused frame's is lower.
    let sigma =
        |r: &serde_json::Value, k: usize| r["depth_clean"][k]["sigma_at_2m_mm"].as_f64().unwrap();
    let one = (0..3).map(|k| sigma(&apart, k)).fold(f64::MAX, f64::min);
    assert!(
        sigma(&fused, 0) < 0.8 * one,
        "{} mm fused, {one} mm alone",
        sigma(&fused, 0)
    );
    assert!(
        frames.iter().all(|d| holes(d) > 0),
        "a structured-light frame has holes"
    );
    let o = deocc()
        .args([
            "eval",
            "perception",
            "--scenes",
            "1",
            "--burst",
            "2",
            "--json",
        ])
        .arg(dir.path().join("p.json"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--burst 2") && err.contains("perception"),
        "{err}"
    );
}

/// The shipped model, relative to the workspace.
fn shipped_weights() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../weights/gldot-small")
}

#[test]
fn run_makes_a_scene_more_complete_and_writes_every_output() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = dir.path().join("scenes");
    let o = deocc()
        .args([
            "synth",
            "scenes",
            "--count",
            "1",
            "--seed",
            "9000000",
            "--views",
            "4",
            "--width",
            "320",
            "--height",
            "240",
            "--gt-density",
            "4000",
            "--out",
        ])
        .arg(&scenes)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.path().join("result");
    let o = deocc()
        .arg("run")
        .arg(scenes.join("scene_000000"))
        .arg("--out")
        .arg(&out)
        .arg("--weights")
        .arg(shipped_weights())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in [
        "completed.ply",
        "observed.ply",
        "report.json",
        "render_input_view.png",
        "render_novel_view.png",
        "report.html",
    ] {
        assert!(out.join(f).exists(), "missing {f}");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    // The occluders-removed picture exists exactly when, in the first view, a completed object
    // is hidden by an object that is neither completed nor room structure.
    let meta: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(scenes.join("scene_000000/scene.json")).unwrap(),
    )
    .unwrap();
    let structure: Vec<u64> = meta["objects"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|o| o["structure"] == true)
        .map(|o| o["instance_id"].as_u64().unwrap())
        .collect();
    let completed: Vec<u64> = report["instances"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|i| i["generated_points"].as_u64().unwrap() > 0)
        .map(|i| i["instance_id"].as_u64().unwrap())
        .collect();
    // A picture for every completed object (not room structure), and one page with it all:
    // no external resource, every picture embedded.
    let panels: Vec<_> = std::fs::read_dir(out.join("objects"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(!panels.is_empty());
    for p in &panels {
        let id: u64 = p[7..11].parse().unwrap();
        assert!(completed.contains(&id), "{p} is not a completed instance");
    }
    assert!(out.join("render_objects.png").exists());
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(
        !html.contains("http://") && !html.contains("https://"),
        "the page fetches nothing"
    );
    assert!(html.contains("data:image/png;base64,"));
    assert!(html.contains("\"total_points\""));
    let hidden_by_another = report["occlusion"][0]
        .as_array()
        .unwrap()
        .iter()
        .filter(|m| completed.contains(&m["instance_id"].as_u64().unwrap()))
        .flat_map(|m| m["occluded_by"].as_array().unwrap().clone())
        .any(|o| {
            let o = o.as_u64().unwrap();
            !completed.contains(&o) && !structure.contains(&o)
        });
    assert!(!completed.is_empty());
    assert_eq!(
        out.join("render_occluders_removed.png").exists(),
        hidden_by_another,
        "occluders-removed picture"
    );
    let e = &report["evaluation"];
    let before = e["visible_only"]["hidden_region"]["completeness_mean"]
        .as_f64()
        .unwrap();
    let after = e["with_deocclusion"]["hidden_region"]["completeness_mean"]
        .as_f64()
        .unwrap();
    assert!(
        after < before,
        "hidden-region completeness {before} -> {after}"
    );
    let completed = deocc_io::ply::read_ply(&out.join("completed.ply"))
        .unwrap()
        .vertices;
    assert!(completed.generated.unwrap().contains(&1));
    // No staging folder is left behind.
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains("partial"))
        .collect();
    assert!(leftovers.is_empty());
}

#[test]
fn run_rejects_bad_input_without_leaving_output() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    std::fs::create_dir_all(scene.join("rgb")).unwrap();
    std::fs::write(scene.join("cameras.json"), r#"{"frames":[{"name":"a","intrinsics":{"fx":500,"fy":500,"cx":32,"cy":24,"width":64,"height":48},"world_from_camera":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#).unwrap();
    let out = dir.path().join("out");
    let o = deocc()
        .arg("run")
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .arg("--weights")
        .arg(shipped_weights())
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("a.png"), "{err}");
    assert!(!out.exists());
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        1,
        "only the input folder remains"
    );
    // An output folder that holds something else is not overwritten.
    let busy = dir.path().join("busy");
    std::fs::create_dir_all(&busy).unwrap();
    std::fs::write(busy.join("thesis.tex"), "precious").unwrap();
    let o = deocc()
        .arg("run")
        .arg("--example")
        .arg("--out")
        .arg(&busy)
        .arg("--weights")
        .arg(shipped_weights())
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(busy.join("thesis.tex").exists());
}

/// `deocc serve` refuses bad settings before loading anything, naming the option.
#[test]
fn serve_refuses_bad_settings_naming_the_option() {
    for (args, needle) in [
        (vec!["--listen", "localhost"], "--listen"),
        (vec!["--workers", "0"], "--workers"),
        (vec!["--max-message-mib", "0"], "--max-message-mib"),
        (vec!["--max-deadline-s", "nan"], "--max-deadline-s"),
    ] {
        let o = deocc().arg("serve").args(&args).output().unwrap();
        assert!(!o.status.success(), "{args:?} was accepted");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
    }
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("token");
    std::fs::write(&token, "  \n").unwrap();
    let o = deocc()
        .args(["serve", "--listen", "127.0.0.1:0", "--token-file"])
        .arg(&token)
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("token is empty"));
}

/// `deocc run --mcap` writes a recording an MCAP reader opens: every frame's images and
/// calibration, the transforms, the cloud by provenance, and the grasps and placement map
/// planned on the completed cloud (a scene whose completed objects the planner can grasp at
/// 160 x 120: in seed 9000000's only the rules' uncapped far side of a chair gave antipodal
/// pairs, and since the depth front end 9000001's none; since the plane smoothing 9000003's
/// none either; 9000002's do).
#[test]
fn run_writes_an_mcap_recording() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = dir.path().join("scenes");
    let o = deocc()
        .args([
            "synth", "scenes", "--count", "1", "--seed", "9000002", "--views", "2",
        ])
        .args([
            "--width",
            "160",
            "--height",
            "120",
            "--gt-density",
            "200",
            "--out",
        ])
        .arg(&scenes)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.path().join("result");
    let o = deocc()
        .arg("run")
        .arg(scenes.join("scene_000000"))
        .args(["--completer", "rules", "--mcap", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bytes = std::fs::read(out.join("recording.mcap")).unwrap();
    assert!(bytes.starts_with(b"\x89MCAP0\r\n"));
    let mut topics = std::collections::BTreeMap::<String, usize>::new();
    let mut grasps = None;
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
        assert!(v.is_object());
        if m.channel.topic == "/deocc/grasps" {
            grasps = Some(v);
        }
        *topics.entry(m.channel.topic.clone()).or_default() += 1;
    }
    // Each grasp a gripper of three boxes (palm, two fingers), in the world frame.
    let grasps = grasps.expect("no /deocc/grasps message");
    let entities = grasps["entities"].as_array().unwrap();
    assert!(!entities.is_empty());
    for e in entities {
        assert_eq!(e["frame_id"], "world");
        assert_eq!(e["cubes"].as_array().unwrap().len(), 3, "{e}");
    }
    for t in [
        "/deocc/camera/000000/rgb",
        "/deocc/camera/000001/depth",
        "/deocc/camera/000000/instances",
        "/deocc/camera/000001/calibration",
        "/deocc/points/observed",
        "/deocc/points/rules",
        "/deocc/placeable",
        "/deocc/placement",
    ] {
        assert_eq!(topics.get(t), Some(&1), "{t} in {topics:?}");
    }
    assert_eq!(topics.get("/tf"), Some(&2));
}

/// `--fill-depth` fills the holes of a noisy sensor's frames and reports it; a depth model file
/// that is not there is refused before anything is written.
#[test]
fn run_fills_depth_holes_and_refuses_a_missing_depth_model() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = dir.path().join("scenes");
    let o = deocc()
        .args([
            "synth", "scenes", "--count", "1", "--seed", "5", "--views", "2",
        ])
        .args(["--width", "128", "--height", "96", "--gt-density", "500"])
        .arg("--sensor-noise")
        .arg("--out")
        .arg(&scenes)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let scene = scenes.join("scene_000000");
    let out = dir.path().join("out");
    let o = deocc()
        .arg("run")
        .arg(&scene)
        .args(["--completer", "rules", "--fill-depth", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("unmeasured depth pixels from interpolated"),
        "{err}"
    );
    let report: serde_json::Value = serde_json::from_slice(
        &std::fs::read(out.join(deocc_pipeline::output::REPORT_FILE)).unwrap(),
    )
    .unwrap();
    let fills = report["depth_fill"].as_array().unwrap();
    assert_eq!(fills.len(), 2);
    assert!(fills.iter().all(|f| f["source"] == "interpolated"));
    assert!(
        fills
            .iter()
            .map(|f| f["filled"].as_u64().unwrap())
            .sum::<u64>()
            > 0
    );
    // The scene's own files are not changed: what the fill saw measured is the file's measured
    // pixels less what the depth front end removed before it and with what the mask-hole stage
    // filled from the masks' own depth.
    let depth = deocc_io::images::read_depth_png(&scene.join("depth/000000.png")).unwrap();
    let cleaned = &report["depth_clean"][0];
    let removed =
        cleaned["outliers_removed"].as_u64().unwrap() + cleaned["specks_removed"].as_u64().unwrap();
    let from_masks = report["mask_holes"][0]["filled"].as_u64().unwrap();
    assert_eq!(
        depth.valid_count() as u64 + from_masks,
        fills[0]["measured"].as_u64().unwrap() + removed
    );

    // The robot tasks take the same flag.
    let o = deocc()
        .arg("place")
        .arg(&scene)
        .args(["--completer", "rules", "--fill-depth"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("unmeasured depth pixels from interpolated"),
        "{err}"
    );

    let out2 = dir.path().join("out2");
    let o = deocc()
        .arg("run")
        .arg(&scene)
        .arg("--depth-model")
        .arg(dir.path().join("da2.safetensors"))
        .arg("--out")
        .arg(&out2)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--depth-model") && err.contains("da2.safetensors"),
        "{err}"
    );
    assert!(!out2.exists());
}

/// `deocc eval reconstruction` and `deocc eval perception` under a sensor model, at smoke size:
/// they run, write their reports, and name the sensor; a bad sensor name is refused.
#[test]
fn eval_commands_run_under_a_sensor_model() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec.json");
    let o = deocc()
        .args([
            "eval",
            "reconstruction",
            "--scenes",
            "1",
            "--completer",
            "rules",
        ])
        .args(["--sensor", "structured-light", "--json"])
        .arg(&rec)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&rec).unwrap()).unwrap();
    assert!(r["benchmark"]
        .as_str()
        .unwrap()
        .contains("structured-light"));
    assert!(r["completeness_gain_whole_scene"]
        .as_f64()
        .unwrap()
        .is_finite());
    // Each row's wall time per scene, the front half included, and the machine it ran on.
    for key in ["seconds_per_scene", "seconds_per_scene_segmenter"] {
        let (mean, max) = (
            r[key]["mean"].as_f64().unwrap(),
            r[key]["max"].as_f64().unwrap(),
        );
        assert!(mean > 0.0 && max >= mean, "{key}: {}", r[key]);
    }
    assert!(r["machine"]["cores"].as_u64().unwrap() >= 1);
    let perc = dir.path().join("perc.json");
    let o = deocc()
        .args([
            "eval",
            "perception",
            "--scenes",
            "1",
            "--failure-scenes",
            "0",
        ])
        .args(["--sensor", "time-of-flight", "--json"])
        .arg(&perc)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&perc).unwrap()).unwrap();
    assert!(r["benchmark"].as_str().unwrap().contains("time-of-flight"));
    assert!(r["segmenter_miou"].as_f64().unwrap() > 0.0);
    let o = deocc()
        .args(["eval", "perception", "--scenes", "1", "--sensor", "lidar"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("structured-light"));
}

/// `deocc options` lists every option; docs/options.md is its Markdown, kept equal here
/// (regenerate with `deocc options --markdown > docs/options.md`).
#[test]
fn options_are_listed_and_the_docs_are_current() {
    let o = deocc().args(["options", "--json"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let list: Vec<serde_json::Value> = serde_json::from_slice(&o.stdout).unwrap();
    let names: Vec<&str> = list.iter().map(|r| r["name"].as_str().unwrap()).collect();
    for want in ["steps", "complete_planes", "depth_clean.radius"] {
        assert!(names.contains(&want), "{want} missing from {names:?}");
    }
    assert!(list
        .iter()
        .all(|r| !r["meaning"].as_str().unwrap().is_empty()));
    let o = deocc().args(["options", "--markdown"]).output().unwrap();
    assert!(o.status.success());
    let docs = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/options.md");
    assert_eq!(
        String::from_utf8(o.stdout).unwrap(),
        std::fs::read_to_string(&docs).unwrap(),
        "docs/options.md is stale: regenerate it with `deocc options --markdown > docs/options.md`"
    );
}
