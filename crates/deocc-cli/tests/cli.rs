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
