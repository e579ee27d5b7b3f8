//! `deocc batch`: a sharded run writes the same outputs as a serial one, complete outputs are
//! skipped, failures are recorded and make the exit code non-zero.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn deocc() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_deocc"));
    for v in [
        "JOB_COMPLETION_INDEX",
        "SLURM_ARRAY_TASK_ID",
        "SLURM_ARRAY_TASK_COUNT",
    ] {
        c.env_remove(v);
    }
    c
}

fn ok(o: std::process::Output) -> String {
    assert!(
        o.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Every file under `dir` (relative path -> bytes); report.json without its timings, which are
/// the one thing two identical runs do not share.
fn outputs(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    fn strip_times(v: &mut serde_json::Value) {
        if let Some(m) = v.as_object_mut() {
            m.retain(|k, _| {
                !(k.ends_with("_s")
                    || k == "timings"
                    || k.contains("per_second")
                    || k == "peak_rss_mib")
            });
            m.values_mut().for_each(strip_times);
        } else if let Some(a) = v.as_array_mut() {
            a.iter_mut().for_each(strip_times);
        }
    }
    let mut files = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
                continue;
            }
            let rel = p.strip_prefix(dir).unwrap().to_path_buf();
            let mut bytes = std::fs::read(&p).unwrap();
            if rel.file_name().unwrap() == "report.json" {
                let mut v: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
                strip_times(&mut v);
                bytes = serde_json::to_vec(&v).unwrap();
            }
            if rel.file_name().unwrap() == "report.html" {
                // The figures table holds the run's timings; the rest must match.
                let text = String::from_utf8(bytes).unwrap();
                let (a, b) = (
                    text.find("<h2>Figures</h2>").unwrap(),
                    text.find("<h2>Instances</h2>").unwrap(),
                );
                bytes = format!("{}{}", &text[..a], &text[b..]).into_bytes();
            }
            files.insert(rel, bytes);
        }
    }
    files
}

fn summary(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

#[test]
fn sharded_batch_equals_serial_and_skips_complete_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = dir.path().join("scenes");
    ok(deocc()
        .args([
            "synth", "scenes", "--count", "3", "--seed", "9000000", "--views", "2",
        ])
        .args([
            "--width",
            "160",
            "--height",
            "120",
            "--gt-density",
            "300",
            "--out",
        ])
        .arg(&scenes)
        .output()
        .unwrap());
    let manifest = scenes.join("scenes.txt");
    std::fs::write(
        &manifest,
        "# three scenes\nscene_000000\n\nscene_000001\nscene_000002\n",
    )
    .unwrap();
    let batch = |out: &Path| {
        let mut c = deocc();
        c.arg("batch")
            .arg("--manifest")
            .arg(&manifest)
            .arg("--out")
            .arg(out)
            .args(["--completer", "rules"]);
        c
    };
    let serial = dir.path().join("serial");
    ok(batch(&serial).output().unwrap());
    let sharded = dir.path().join("sharded");
    ok(batch(&sharded)
        .args(["--shard-index", "0", "--shard-count", "2"])
        .output()
        .unwrap());
    // The second shard takes its index from the Kubernetes Indexed Job's environment.
    ok(batch(&sharded)
        .args(["--shard-count", "2"])
        .env("JOB_COMPLETION_INDEX", "1")
        .output()
        .unwrap());
    let (a, b) = (outputs(&serial), outputs(&sharded));
    let scene_files = |m: &BTreeMap<PathBuf, Vec<u8>>| {
        m.iter()
            .filter(|(k, _)| k.to_string_lossy().starts_with("scene_00000"))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect::<BTreeMap<_, _>>()
    };
    let (a, b) = (scene_files(&a), scene_files(&b));
    assert!(a.contains_key(Path::new("scene_000002/completed.ply")));
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (k, v) in &a {
        assert!(
            v == &b[k],
            "{} differs between serial and sharded",
            k.display()
        );
    }
    let s0 = summary(&sharded.join("summary-0-of-2.jsonl"));
    let s1 = summary(&sharded.join("summary-1-of-2.jsonl"));
    assert_eq!(
        (s0.len(), s1.len()),
        (2, 1),
        "scenes 0 and 2 in shard 0, scene 1 in shard 1"
    );
    assert!(s1[0]["scene"].as_str().unwrap().ends_with("scene_000001"));
    // Run again: everything is complete already and skipped.
    let again = ok(batch(&serial).output().unwrap());
    assert!(again.contains("0 done, 3 skipped"), "{again}");
    let s = summary(&serial.join("summary-0-of-1.jsonl"));
    assert_eq!(s.len(), 6);
    assert!(s[3..].iter().all(|l| l["status"] == "skipped"));
}

#[test]
fn a_failing_scene_is_recorded_and_the_others_still_run() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = dir.path().join("scenes");
    ok(deocc()
        .args([
            "synth", "scenes", "--count", "1", "--seed", "9000001", "--views", "2",
        ])
        .args([
            "--width",
            "96",
            "--height",
            "72",
            "--gt-density",
            "200",
            "--out",
        ])
        .arg(&scenes)
        .output()
        .unwrap());
    let manifest = dir.path().join("m.txt");
    std::fs::write(&manifest, "missing_scene\nscenes/scene_000000\n").unwrap();
    let out = dir.path().join("out");
    let o = deocc()
        .arg("batch")
        .arg("--manifest")
        .arg(&manifest)
        .arg("--out")
        .arg(&out)
        .args(["--completer", "rules"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing_scene"));
    let s = summary(&out.join("summary-0-of-1.jsonl"));
    assert_eq!(s[0]["status"], "failed");
    assert!(s[0]["error"].as_str().unwrap().contains("missing_scene"));
    assert_eq!(s[1]["status"], "done");
    assert!(out.join("scene_000000/completed.ply").is_file());
    assert!(!out.join("missing_scene").exists());
}

#[test]
fn bad_manifests_and_shards_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = dir.path().join("m.txt");
    let run = |args: &[&str]| {
        let o = deocc()
            .arg("batch")
            .arg("--manifest")
            .arg(&manifest)
            .arg("--out")
            .arg(dir.path().join("out"))
            .args(args)
            .output()
            .unwrap();
        assert!(!o.status.success());
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    std::fs::write(&manifest, "a/scene\nb/scene\n").unwrap();
    let e = run(&[]);
    assert!(e.contains("m.txt:2") && e.contains("\"scene\""), "{e}");
    std::fs::write(&manifest, "# nothing\n").unwrap();
    assert!(run(&[]).contains("names no scene"));
    std::fs::write(&manifest, "a\n").unwrap();
    assert!(run(&["--shard-index", "2", "--shard-count", "2"]).contains("--shard-index"));
    assert!(run(&["--shard-count", "0"]).contains("--shard-count"));
    assert!(!dir.path().join("out").exists());
}
