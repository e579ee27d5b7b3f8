//! Timing helpers shared by the benchmarks: medians of repeated calls, after warm-ups, and
//! temporary folders for the peers' inputs.

use std::path::PathBuf;
use std::time::Instant;

use crate::EvalError;

/// The upper median (element `len / 2` after sorting), the convention of both sides' timers
/// (`median_time` here and in scripts/bench_torch.py); NaN when empty.
pub fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// [`median_time`] after one untimed warm-up call (first-touch page faults, lazily built thread
/// pools): the protocol of scripts/bench_torch.py's `median_time`, so the model comparison times
/// both sides alike.
pub fn warm_median_time<T>(
    repeats: usize,
    f: impl FnMut() -> Result<T, EvalError>,
) -> Result<(f64, T), EvalError> {
    warm_median_time_after(1, repeats, f)
}

/// [`median_time`] after `warm_ups` untimed calls.
pub fn warm_median_time_after<T>(
    warm_ups: usize,
    repeats: usize,
    mut f: impl FnMut() -> Result<T, EvalError>,
) -> Result<(f64, T), EvalError> {
    for _ in 0..warm_ups {
        f()?;
    }
    median_time(repeats, f)
}

/// Median wall time of `repeats` calls (the protocol of scripts/bench_open3d.py's `timed`).
pub fn median_time<T>(
    repeats: usize,
    mut f: impl FnMut() -> Result<T, EvalError>,
) -> Result<(f64, T), EvalError> {
    let mut times = Vec::new();
    let mut out = None;
    for _ in 0..repeats.max(1) {
        let t0 = Instant::now();
        out = Some(f()?);
        times.push(t0.elapsed().as_secs_f64());
    }
    let out = out.ok_or_else(|| EvalError::Data("no repetition ran".into()))?;
    Ok((median(&times), out))
}

/// A fresh temporary folder, removed when dropped.
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Result<Self, EvalError> {
        let dir = std::env::temp_dir().join(format!("deocc-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).map_err(|e| deocc_io::IoError::new(&dir, e))?;
        Ok(Self(dir))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Writes a peer script (embedded in the binary, so an installed `deocc` needs no checkout)
/// into `dir` and returns its path.
pub fn peer_script(dir: &std::path::Path, name: &str, text: &str) -> Result<PathBuf, EvalError> {
    let path = dir.join(name);
    std::fs::write(&path, text).map_err(|e| deocc_io::IoError::new(&path, e))?;
    Ok(path)
}

/// The machine a report was measured on: CPU model, cores, and the load average when it began
/// (a figure from a loaded machine is not a quiet machine's).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Machine {
    pub cpu_model: String,
    pub cores: usize,
    /// 1, 5 and 15 minute load averages (Linux; NaN elsewhere).
    pub load_average: [f64; 3],
}

impl Machine {
    pub fn now() -> Self {
        let cpu_model = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|t| {
                t.lines()
                    .find(|l| l.starts_with("model name"))
                    .and_then(|l| l.split_once(':'))
                    .map(|(_, v)| v.trim().to_string())
            })
            .unwrap_or_else(|| "unknown".into());
        let mut load_average = [f64::NAN; 3];
        if let Ok(t) = std::fs::read_to_string("/proc/loadavg") {
            for (slot, v) in load_average.iter_mut().zip(t.split_whitespace()) {
                *slot = v.parse().unwrap_or(f64::NAN);
            }
        }
        Self {
            cpu_model,
            cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
            load_average,
        }
    }
}
