//! Every `deocc bench` and `deocc eval` command at a smoke size, so none can rot: each runs, writes
//! its JSON report, and a benchmark's report records the machine it ran on (CPU model, cores,
//! load average). (eval perception, reconstruction and grasp and bench soak have their smoke
//! runs in cli.rs, robot.rs and hostile.rs.)

use std::path::Path;
use std::process::Command;

fn deocc() -> Command {
    Command::new(env!("CARGO_BIN_EXE_deocc"))
}

/// Runs `deocc ARGS --json DIR/NAME.json` and returns the report.
fn report(dir: &Path, name: &str, args: &[&str]) -> serde_json::Value {
    let json = dir.join(format!("{name}.json"));
    let o = deocc()
        .args(args)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "deocc {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_str(&std::fs::read_to_string(&json).unwrap())
        .unwrap_or_else(|e| panic!("{name}.json: {e}"))
}

fn machine(r: &serde_json::Value, name: &str) {
    let m = &r["machine"];
    assert!(
        m["cores"].as_u64().unwrap_or(0) >= 1 && m["cpu_model"].is_string(),
        "{name}: no machine in the report: {m}"
    );
}

#[test]
fn every_benchmark_runs_at_smoke_size_and_names_its_machine() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let g = report(
        d,
        "geometry",
        &[
            "bench",
            "geometry",
            "--points",
            "2000",
            "--rounds",
            "1",
            "--no-open3d",
        ],
    );
    machine(&g, "geometry");
    assert!(g["rows"].as_array().unwrap().len() >= 6);
    let s = report(d, "synth", &["bench", "synth", "--scenes", "1"]);
    machine(&s, "synth");
    let m = report(
        d,
        "model",
        &["bench", "model", "--no-torch", "--rounds", "1"],
    );
    machine(&m, "model");
    assert!(m["completions_per_second_batch_1"].as_f64().unwrap() > 0.0);
    let mem = report(
        d,
        "memory",
        &[
            "bench",
            "memory",
            "--views",
            "1",
            "--width",
            "160",
            "--height",
            "120",
            "--completer",
            "rules",
        ],
    );
    machine(&mem, "memory");
    let svc = report(
        d,
        "service",
        &[
            "bench",
            "service",
            "--clients",
            "1",
            "--requests",
            "1",
            "--rounds",
            "1",
            "--completer",
            "rules",
        ],
    );
    machine(&svc, "service");
}

#[test]
fn every_evaluation_runs_at_smoke_size() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let o = deocc()
        .args([
            "synth", "pairs", "--split", "test", "--scenes", "1", "--out",
        ])
        .arg(d.join("pairs"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let pairs = d.join("pairs");
    let a = report(
        d,
        "amodal",
        &[
            "eval",
            "amodal",
            "--data",
            pairs.to_str().unwrap(),
            "--split",
            "test",
            "--pairs",
            "4",
            "--sweep-pairs",
            "0",
            "--bootstrap",
            "50",
        ],
    );
    assert!(a.is_object());
    let obj = report(d, "objects", &["eval", "objects", "--scenes", "1"]);
    assert!(obj.is_object());
    let place = report(d, "place", &["eval", "place", "--scenes", "1"]);
    assert!(place.is_object());
    // pickup-v2 under a sensor: its first seed's target is a mug (the seed fixes the kind), and
    // every row reports it by kind and visibility, with the planner's reasons per scene.
    let v2 = report(
        d,
        "pickup-v2",
        &[
            "eval",
            "grasp",
            "--preset",
            "pickup-v2",
            "--scenes",
            "1",
            "--sensor",
            "structured-light",
        ],
    );
    assert!(v2["benchmark"].as_str().unwrap().starts_with("pickup-v2"));
    for row in v2["rows"].as_array().unwrap() {
        assert_eq!(row["by_target"]["mug"]["scenes"], 1, "{row}");
        assert_eq!(row["by_visibility"].as_array().unwrap().len(), 3);
    }
    let scene = &v2["per_scene"][1][1][0];
    assert!(
        scene["visible_fraction"].as_f64().unwrap() <= 0.5,
        "{scene}"
    );
    assert!(scene["plan_stats"]["candidates"].is_u64(), "{scene}");
    // Every completed row says what the shape stages made of the target; the observed and
    // true clouds have no shape stages.
    let rows = v2["per_scene"].as_array().unwrap();
    for (k, row) in rows.iter().enumerate() {
        let s = &row[1][0];
        let cuboid = s["target_cuboid"].as_str().unwrap();
        let revolve = s["target_revolve"].as_str().unwrap();
        let revolved = s["target_revolved"].as_bool().unwrap();
        if k == 0 || k == rows.len() - 1 {
            assert!(!revolved && cuboid.is_empty() && revolve.is_empty(), "{s}");
        } else {
            assert!(revolved || !cuboid.is_empty(), "{s}");
            // "fit" exactly when it was revolved, else why not.
            assert_eq!(revolved, revolve == "fit", "{s}");
            assert!(!revolve.is_empty(), "{s}");
        }
    }
    let depth = report(
        d,
        "depth",
        &["eval", "depth", "--scenes", "1", "--views", "1"],
    );
    assert!(depth.is_object());
}
