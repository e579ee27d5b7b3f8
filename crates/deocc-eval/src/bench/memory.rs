//! `deocc bench memory`: peak resident memory of `deocc run` against the number of views. Each
//! scene is rendered to a temporary folder and run in a child process (its own peak), whose
//! report gives `peak_rss_mib`.

use std::path::Path;
use std::process::Command;

use serde::Serialize;

use super::timing::TempDir;
use crate::EvalError;

#[derive(Debug, Clone, Serialize)]
pub struct MemoryRow {
    pub views: usize,
    pub width: u32,
    pub height: u32,
    pub peak_rss_mib: f64,
    pub run_seconds: f64,
    pub points_observed: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct MemoryReport {
    /// The machine and its load when the figures were taken.
    pub machine: super::timing::Machine,
    pub completer: String,
    pub rows: Vec<MemoryRow>,
}

/// Renders a bench-v1-like scene with each number of `views` (robot-head sweep, `width` x
/// `height`) and runs `deocc` (the binary at `exe`) on it with `completer`.
pub fn memory_bench(
    exe: &Path,
    views: &[usize],
    width: u32,
    height: u32,
    completer: &str,
) -> Result<MemoryReport, EvalError> {
    let tmp = TempDir::new("bench-memory")?;
    let mut rows = Vec::new();
    for &n in views {
        let config = deocc_synth::scene::SceneConfig {
            views: n,
            width,
            height,
            gt_points_per_m2: 100.0,
            ..deocc_synth::scene::SceneConfig::default()
        };
        let scene = tmp.0.join(format!("scene-{n}"));
        let rendered = deocc_synth::dataset::render_full_scene(&config, 9_000_000)?;
        deocc_synth::dataset::write_scene(&scene, &config, &rendered)?;
        drop(rendered);
        // Without ground truth the run is the pipeline alone.
        let _ = std::fs::remove_file(scene.join("ground_truth.ply"));
        let out = tmp.0.join(format!("out-{n}"));
        eprintln!("{n} views: running deocc");
        let o = Command::new(exe)
            .arg("run")
            .arg(&scene)
            .arg("--out")
            .arg(&out)
            .args(["--completer", completer])
            .output()
            .map_err(|e| EvalError::Data(format!("cannot run {}: {e}", exe.display())))?;
        if !o.status.success() {
            return Err(EvalError::Data(format!(
                "deocc run on {n} views failed: {}",
                String::from_utf8_lossy(&o.stderr)
            )));
        }
        let report_path = out.join("report.json");
        let text = std::fs::read_to_string(&report_path)
            .map_err(|e| deocc_io::IoError::new(&report_path, e))?;
        let r: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| EvalError::Data(format!("{}: {e}", report_path.display())))?;
        rows.push(MemoryRow {
            views: n,
            width,
            height,
            peak_rss_mib: r["peak_rss_mib"].as_f64().unwrap_or(f64::NAN),
            run_seconds: r["timings"]["total_s"].as_f64().unwrap_or(f64::NAN),
            points_observed: r["points_observed"].as_u64().unwrap_or(0),
        });
        let _ = std::fs::remove_dir_all(&scene);
        let _ = std::fs::remove_dir_all(&out);
    }
    Ok(MemoryReport {
        machine: super::timing::Machine::now(),
        completer: completer.into(),
        rows,
    })
}
