//! Shipping a training run: its EMA weights in half precision with its config, into a folder that
//! `GlDotCompleter::from_dir` (and `deocc run --weights`) loads.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};

use crate::train::{Result, TrainConfig, TrainError};

/// What to ship with the weights: the mask rule chosen on the validation pairs.
#[derive(Debug, Clone, Default)]
pub struct ExportOptions {
    /// Mask threshold: in [0, 1] (a probability) for models with a mask head, in [-1, 1] (the
    /// mask channel) otherwise.
    pub mask_threshold: Option<f32>,
    /// `Some(None)` ships no seen-elsewhere threshold, `Some(Some(th))` ships `th`, `None` keeps
    /// the run's.
    pub mask_threshold_seen_elsewhere: Option<Option<f32>>,
    pub keep_prior: Option<bool>,
    /// Samples averaged per completion (odd ones mirrored), in 1..=16.
    pub samples: Option<usize>,
}

fn file_err(path: &Path, msg: impl std::fmt::Display) -> TrainError {
    TrainError::File {
        path: path.to_path_buf(),
        msg: msg.to_string(),
    }
}

/// Exports `run` into `out`: `ema.safetensors` in f16, `train.json` with the options applied,
/// `state.json`. `out` may not be the run itself (the export would replace its f32 EMA and its
/// state). Each file is written to a temporary name and renamed into place.
pub fn export_run(run: &Path, out: &Path, opts: &ExportOptions) -> Result<PathBuf> {
    let ema = run.join("ema.safetensors");
    let cfg_path = run.join("train.json");
    let state = run.join("state.json");
    for f in [&ema, &cfg_path, &state] {
        if !f.exists() {
            return Err(file_err(
                f,
                format!(
                    "missing; is {} a training run with a checkpoint?",
                    run.display()
                ),
            ));
        }
    }
    if let (Ok(a), Ok(b)) = (run.canonicalize(), out.canonicalize()) {
        if a == b {
            return Err(file_err(
                out,
                "is the run itself: exporting into it would replace the run's f32 EMA and state; \
                 choose another --out",
            ));
        }
    }
    let mut config = TrainConfig::read(&cfg_path)?;
    if let Some(th) = opts.mask_threshold {
        let range = if config.model.mask_head {
            0.0..=1.0
        } else {
            -1.0..=1.0
        };
        if !range.contains(&th) {
            return Err(TrainError::Config(format!(
                "--mask-threshold {th} is outside [{}, {}] for this model",
                range.start(),
                range.end()
            )));
        }
        config.mask_threshold = th;
    }
    if let Some(th) = opts.mask_threshold_seen_elsewhere {
        config.mask_threshold_seen_elsewhere = th;
    }
    if let Some(keep) = opts.keep_prior {
        config.mask_keeps_prior = keep;
    }
    if let Some(n) = opts.samples {
        config.inference_samples = n;
    }
    config
        .validate()
        .map_err(|e| TrainError::Config(format!("exported config: {e}")))?;
    let tensors =
        candle_core::safetensors::load(&ema, &Device::Cpu).map_err(|e| file_err(&ema, e))?;
    for (name, t) in &tensors {
        let values = t.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()?;
        if values.iter().any(|v| !v.is_finite()) {
            return Err(file_err(
                &ema,
                format!("tensor {name} has non-finite values"),
            ));
        }
    }
    let half: HashMap<String, Tensor> = tensors
        .into_iter()
        .map(|(k, v)| Ok((k, v.to_dtype(DType::F16)?)))
        .collect::<candle_core::Result<_>>()?;
    std::fs::create_dir_all(out).map_err(|e| file_err(out, e))?;
    let tmp = out.join("ema.safetensors.tmp");
    candle_core::safetensors::save(&half, &tmp).map_err(|e| file_err(&tmp, e))?;
    std::fs::rename(&tmp, out.join("ema.safetensors")).map_err(|e| file_err(out, e))?;
    let text = serde_json::to_string_pretty(&config).map_err(|e| file_err(out, e))? + "\n";
    deocc_io::atomic::write_bytes_atomic(&out.join("train.json"), text.as_bytes())
        .map_err(|e| file_err(out, e))?;
    let state_text = std::fs::read(&state).map_err(|e| file_err(&state, e))?;
    deocc_io::atomic::write_bytes_atomic(&out.join("state.json"), &state_text)
        .map_err(|e| file_err(out, e))?;
    Ok(out.to_path_buf())
}
