//! The built binary against a hostile but realistic user: outputs that would overwrite or
//! delete the input, exports into their own run, killed runs, bad options. Each case must fail
//! with a message naming what is wrong, and lose nothing.

use std::path::{Path, PathBuf};
use std::process::Command;

fn deocc() -> Command {
    Command::new(env!("CARGO_BIN_EXE_deocc"))
}

/// A small scene folder (4 views at 320x240, ground truth included).
fn small_scene(dir: &Path) -> PathBuf {
    let scenes = dir.join("scenes");
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
            "2000",
            "--out",
        ])
        .arg(&scenes)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    scenes.join("scene_000000")
}

/// Every file under `dir` with its bytes (to prove a folder untouched).
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.clone(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

fn run(input: &Path, out: &Path) -> std::process::Output {
    deocc()
        .arg("run")
        .arg(input)
        .arg("--out")
        .arg(out)
        .arg("--completer")
        .arg("rules")
        .output()
        .unwrap()
}

#[test]
fn an_output_never_is_contains_or_lies_inside_the_input() {
    let dir = tempfile::tempdir().unwrap();
    let scene = small_scene(dir.path());
    let before = snapshot(&scene);
    // The scene itself, a folder inside it, and the folder that holds it.
    for (out, expect) in [
        (scene.clone(), "inside the input"),
        (scene.join("sub"), "inside the input"),
        (scene.parent().unwrap().to_path_buf(), "contains the input"),
    ] {
        let o = run(&scene, &out);
        assert!(!o.status.success(), "--out {}", out.display());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(expect), "--out {}: {err}", out.display());
        assert_eq!(snapshot(&scene), before, "the input changed");
    }
    // The input folder `run --example` writes inside its output, run into that output.
    let prev = dir.path().join("prev");
    let o = run(&scene, &prev);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(prev.join("report.json")).unwrap()).unwrap();
    // report.json names where the input is, not a staging folder.
    assert_eq!(report["input"].as_str().unwrap(), scene.to_str().unwrap());
    std::fs::create_dir_all(prev.join("input")).unwrap();
    std::fs::copy(scene.join("cameras.json"), prev.join("input/cameras.json")).unwrap();
    let o = run(&prev.join("input"), &prev);
    assert!(!o.status.success());
    assert!(prev.join("input/cameras.json").exists());
    // `--out .` would replace the current folder.
    let o = deocc()
        .current_dir(dir.path())
        .args(["run", "--example", "--completer", "rules", "--out", "."])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("current folder"));
    assert!(scene.join("cameras.json").exists());
}

#[test]
fn a_killed_run_leaves_the_old_or_the_new_output_and_no_staging() {
    let dir = tempfile::tempdir().unwrap();
    let scene = small_scene(dir.path());
    let out = dir.path().join("out");
    assert!(run(&scene, &out).status.success());
    let complete = |out: &Path| {
        let report = std::fs::read_to_string(out.join("report.json")).unwrap();
        serde_json::from_str::<serde_json::Value>(&report).unwrap();
        deocc_io::ply::read_ply(&out.join("completed.ply")).unwrap();
    };
    complete(&out);
    for delay_ms in [50, 300, 800, 1500, 2500] {
        let mut child = deocc()
            .arg("run")
            .arg(&scene)
            .arg("--out")
            .arg(&out)
            .arg("--completer")
            .arg("rules")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(delay_ms));
        let _ = child.kill(); // SIGKILL
        let _ = child.wait();
        // Between the two renames of the swap the output is set aside: the next run puts it
        // back. Either way a complete version exists.
        let aside: Vec<PathBuf> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.to_string_lossy().contains(".out.old-"))
            .collect();
        if out.exists() {
            complete(&out);
        } else {
            assert_eq!(
                aside.len(),
                1,
                "after {delay_ms} ms: no output and nothing set aside"
            );
            complete(&aside[0]);
        }
    }
    // The next run cleans up what the killed ones left (staging, locks, set-aside outputs).
    assert!(run(&scene, &out).status.success());
    complete(&out);
    let left: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".out."))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

#[test]
fn bad_options_are_refused_naming_the_option() {
    let dir = tempfile::tempdir().unwrap();
    let scene = small_scene(dir.path());
    for (args, expect) in [
        (vec!["--steps", "0"], "steps"),
        (vec!["--rho", "NaN"], "rho"),
        (vec!["--rho", "1e30"], "rho"),
        (vec!["--completer", "magic"], "magic"),
    ] {
        let o = deocc()
            .arg("run")
            .arg(&scene)
            .arg("--out")
            .arg(dir.path().join("o"))
            .args(&args)
            .output()
            .unwrap();
        assert!(!o.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(expect), "{args:?}: {err}");
        assert!(!dir.path().join("o").exists());
    }
    // An options file with a typo names the file and the field.
    let opts = dir.path().join("opts.json");
    std::fs::write(&opts, r#"{"stpes": 8}"#).unwrap();
    let o = deocc()
        .arg("run")
        .arg(&scene)
        .arg("--out")
        .arg(dir.path().join("o"))
        .arg("--options")
        .arg(&opts)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("opts.json") && err.contains("stpes"), "{err}");
    let o = deocc()
        .args(["train", "--batch-size", "0", "--run"])
        .arg(dir.path().join("r"))
        .arg("--data")
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!o.status.success());
}

/// `deocc run` from any folder: the shipped weights are built in.
#[test]
fn run_works_from_any_folder_without_the_repository() {
    let dir = tempfile::tempdir().unwrap();
    let scene = small_scene(dir.path());
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir_all(&elsewhere).unwrap();
    let o = deocc()
        .current_dir(&elsewhere)
        .arg("run")
        .arg(&scene)
        .arg("--out")
        .arg("result")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(elsewhere.join("result/completed.ply").exists());
}

#[test]
fn export_refuses_to_write_into_its_own_run() {
    let dir = tempfile::tempdir().unwrap();
    let pairs = dir.path().join("pairs");
    let o = deocc()
        .args([
            "synth",
            "pairs",
            "--split",
            "train",
            "--scenes",
            "1",
            "--resolution",
            "16",
            "--out",
        ])
        .arg(&pairs)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let runs = dir.path().join("run");
    let o = deocc()
        .args([
            "train",
            "--preset",
            "tiny",
            "--steps",
            "1",
            "--batch-size",
            "2",
            "--run",
        ])
        .arg(&runs)
        .arg("--data")
        .arg(&pairs)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let before = snapshot(&runs);
    let o = deocc()
        .arg("export")
        .arg("--run")
        .arg(&runs)
        .arg("--out")
        .arg(&runs)
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("the run itself"));
    assert_eq!(snapshot(&runs), before, "the run changed");
    let shipped = dir.path().join("shipped");
    let o = deocc()
        .arg("export")
        .arg("--run")
        .arg(&runs)
        .arg("--out")
        .arg(&shipped)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(shipped.join("ema.safetensors").exists());
}

/// A short run of the mutation fuzzer over every reader: no panic, no allocation over 1 GB
/// (scripts/fuzz.sh runs each target for minutes).
#[test]
fn fuzz_smoke_run_finds_no_panic() {
    let o = Command::new(env!("CARGO_BIN_EXE_deocc-fuzz"))
        .args([
            "all",
            "--seconds",
            "9",
            "--seed",
            "7",
            "--max-alloc-mb",
            "1024",
        ])
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    for target in [
        "ply",
        "obj",
        "stl",
        "png",
        "cameras",
        "train_json",
        "safetensors",
        "pairs",
    ] {
        assert!(
            out.contains(&format!("{target}: ")),
            "{target} did not run: {out}"
        );
    }
}

/// Memory is bounded by construction: a 200-view scene runs with a peak under 2 GB (frames are
/// fused into the voxel grid one at a time; `deocc bench memory` reports 640x480 up to 500 views).
#[test]
fn two_hundred_views_run_under_two_gigabytes() {
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
            "200",
            "--width",
            "320",
            "--height",
            "240",
            "--gt-density",
            "10",
            "--out",
        ])
        .arg(&scenes)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let scene = scenes.join("scene_000000");
    std::fs::remove_file(scene.join("ground_truth.ply")).unwrap();
    let out = dir.path().join("out");
    let o = run(&scene, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["frames"].as_u64(), Some(200));
    let peak = report["peak_rss_mib"].as_f64().unwrap();
    assert!(peak < 2048.0, "peak RSS {peak:.0} MiB");
}

/// Round two of the hostile user (each case was mishandled before): options files that are
/// arrays, grasp settings that hung or lied, `--footprint` with a space, and `--steps` that the
/// shipped model ignores.
#[test]
fn round_two_options_cameras_and_words() {
    let dir = tempfile::tempdir().unwrap();
    let scene = small_scene(dir.path());
    let opts = dir.path().join("o.json");
    for (text, want) in [
        ("[]", "expected a JSON object"),
        ("[4]", "expected a JSON object"),
        (r#"{"approaches": 1000000000000}"#, "approaches"),
        (
            r#"{"normal_neighbours": 18446744073709551615}"#,
            "normal_neighbours",
        ),
        (r#"{"voxel_m": 1e-30}"#, "voxel_m"),
        (r#"{"depths": [-1]}"#, "depths[0]"),
    ] {
        std::fs::write(&opts, text).unwrap();
        let o = deocc()
            .args(["grasp", "--target", "1", "--options"])
            .arg(&opts)
            .arg(&scene)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{text}: accepted");
        assert!(err.contains(want), "{text}: {err}");
    }
    // Pipeline options files too.
    std::fs::write(&opts, "[]").unwrap();
    let o = deocc()
        .arg("run")
        .arg(&scene)
        .arg("--out")
        .arg(dir.path().join("never"))
        .arg("--options")
        .arg(&opts)
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("expected a JSON object"));
    assert!(!dir.path().join("never").exists());

    // `--footprint 0.1 0.1 SCENE`: the second size was read as the scene.
    let o = deocc()
        .args(["place", "--footprint", "0.1", "0.1"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("comma-separated"), "{err}");
    let help = deocc().args(["place", "--help"]).output().unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    assert!(help.contains("[default: 0.08,0.08]"), "{help}");

    // --steps with the shipped model: said to have no effect.
    let o = deocc()
        .arg("run")
        .arg(&scene)
        .arg("--out")
        .arg(dir.path().join("steps"))
        .args(["--steps", "8"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--steps 8 has no effect"), "{err}");
}

/// `deocc bench soak` at smoke size: a short run of normal traffic and abuse against the real
/// server, which must pass every check (the 10-minute run is `bench/soak.json`).
#[test]
fn soak_bench_smoke() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("soak.json");
    let o = deocc()
        .args(["bench", "soak", "--seconds", "12", "--completer", "rules"])
        .args(["--clients", "1", "--abusers", "3", "--json"])
        .arg(&json)
        .output()
        .unwrap();
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap_or_default())
            .unwrap_or_default();
    assert!(
        o.status.success(),
        "{}\n{report:#}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(report["passed"], true, "{report:#}");
    assert!(report["normal_correct"].as_u64().unwrap() > 0, "{report:#}");
    assert!(
        report["abuse"].as_object().unwrap().len() >= 3,
        "{report:#}"
    );
    assert!(report["sigterm_exit_s"].as_f64().unwrap() <= 30.0);
    assert!(report["machine"]["cores"].as_u64().unwrap() >= 1);
}
