//! `deocc train --config`: the CI recipe (configs/gldot-tiny.json) end to end, from no data to
//! exported weights: the loss falls, a second call resumes (nothing redone), and a run directory
//! refuses another recipe.

use std::path::{Path, PathBuf};
use std::process::Command;

fn deocc() -> Command {
    Command::new(env!("CARGO_BIN_EXE_deocc"))
}

fn recipe() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/gldot-tiny.json")
}

/// The losses of a phase's `loss.csv` (step, loss, ...).
fn losses(phase: &Path) -> Vec<f64> {
    let text = std::fs::read_to_string(phase.join("loss.csv")).unwrap();
    text.lines()
        .skip(1)
        .map(|l| l.split(',').nth(1).unwrap().parse().unwrap())
        .collect()
}

fn train(run: &Path, root: &Path, config: &Path) -> std::process::Output {
    deocc()
        .args(["train", "--config"])
        .arg(config)
        .arg("--run")
        .arg(run)
        .arg("--data-root")
        .arg(root)
        .output()
        .unwrap()
}

#[test]
fn the_ci_recipe_trains_resumes_and_exports() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run");
    let o = train(&run, tmp.path(), &recipe());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(tmp.path().join("pairs/train-manifest.json").exists());
    // The second pair set, measured by a sensor drawn per scene, feeds the second phase.
    let sensors = std::fs::read_to_string(tmp.path().join("pairs-sensors/train-manifest.json"))
        .expect("the sensor-measured pairs are made");
    assert!(sensors.contains("\"sensor\": \"random\""), "{sensors}");
    assert!(sensors.contains("\"grasp_families\": true"), "{sensors}");
    assert!(err.contains("--extra-data"), "{err}");
    let main = run.join("01-main");
    let l = losses(&main);
    assert_eq!(l.len(), 150, "one loss line a step");
    let mean = |s: &[f64]| s.iter().sum::<f64>() / s.len() as f64;
    let (first, last) = (mean(&l[..10]), mean(&l[l.len() - 20..]));
    assert!(
        last < 0.8 * first,
        "the loss should fall: first ten steps {first:.4}, last twenty {last:.4}"
    );
    // The second phase started from the first's weights and grew the mean head.
    let heads = std::fs::read_to_string(run.join("02-heads/train.json")).unwrap();
    assert!(heads.contains("\"mean_head\": true"), "{heads}");
    assert_eq!(losses(&run.join("02-heads")).len(), 20);
    let exported = std::fs::read_to_string(run.join("export/train.json")).unwrap();
    assert!(exported.contains("\"mean_head\": true"), "{exported}");
    assert!(run.join("export/ema.safetensors").exists());

    // Again: every part is found done; nothing is trained twice.
    let o = train(&run, tmp.path(), &recipe());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("data 1: made already"), "{err}");
    assert!(err.contains("data 2: made already"), "{err}");
    assert!(err.contains("finished already"), "{err}");
    assert_eq!(losses(&main).len(), 150, "resumed, not retrained");

    // Another recipe into the same run directory is refused, naming the kept one.
    let other = tmp.path().join("other.json");
    let text = std::fs::read_to_string(recipe()).unwrap();
    std::fs::write(&other, text.replace("\"steps\": 150", "\"steps\": 151")).unwrap();
    let o = train(&run, tmp.path(), &other);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("another recipe"), "{err}");
}

/// A recipe's mistakes are named: an unknown flag in a phase, a phase without a name.
#[test]
fn bad_recipes_are_refused_with_the_entry_named() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = tmp.path().join("bad.json");
    std::fs::write(
        &bad,
        r#"{"about": "x", "phases": [{"name": "main", "stepz": 3}]}"#,
    )
    .unwrap();
    let o = train(&tmp.path().join("run"), tmp.path(), &bad);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("phase 1") && err.contains("--stepz"), "{err}");
    std::fs::write(&bad, r#"{"about": "x", "phases": [{"steps": 3}]}"#).unwrap();
    let o = train(&tmp.path().join("run2"), tmp.path(), &bad);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("bad.json") && err.contains("name"), "{err}");
    // --config with a flag the recipe sets is a usage error.
    let o = deocc()
        .args(["train", "--steps", "5", "--config"])
        .arg(recipe())
        .arg("--run")
        .arg(tmp.path().join("run3"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--steps"));
}
