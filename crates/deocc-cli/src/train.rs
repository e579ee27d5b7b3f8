//! `deocc train`: start or resume training GL-DoT in a run directory.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use deocc_model::data::shards;
use deocc_model::train::{train_run, TrainConfig, TrainRunOptions};
use deocc_model::GlDotConfig;

use crate::progress::bar;

#[derive(Args)]
pub struct TrainArgs {
    /// Run directory: created if new, resumed if it holds a checkpoint.
    #[arg(long)]
    pub run: PathBuf,
    /// A whole recipe (configs/gldot-small-sensors.json is the shipped model's): make its training
    /// pairs, train its phases in order and export, resumable; the run directory holds one
    /// folder per phase and `export/`. The recipe's entries are this command's flags.
    #[arg(long, conflicts_with_all = RECIPE_CONFLICTS)]
    pub config: Option<PathBuf>,
    /// With --config: the folder the recipe's paths are relative to.
    #[arg(long, default_value = ".", requires = "config")]
    pub data_root: PathBuf,
    /// Folder with train-*.safetensors pair shards (from `deocc synth pairs --split train`).
    #[arg(long, default_value = "data/pairs")]
    data: PathBuf,
    /// Also train on this folder's train-*.safetensors shards, drawn with --data's (e.g.
    /// sensor-measured pairs beside clean ones: each shard is drawn alike, so the mix is the
    /// folders' shard counts).
    #[arg(long)]
    extra_data: Option<PathBuf>,
    /// Model preset: tiny, small (shipped), large.
    #[arg(long, default_value = "small")]
    preset: String,
    /// The mask the residual starts from and condition channel 6 carries: visible,
    /// hull_in_front, ellipse_in_front or ellipse_or_box_in_front. Default: the preset's
    /// (ellipse_or_box_in_front). A run resumes only with the prior it started with (hull_in_front
    /// or ellipse_in_front for runs made before the current preset).
    #[arg(long)]
    mask_prior: Option<String>,
    /// Total optimisation steps (a resumed run continues up to this).
    #[arg(long, default_value_t = 20_000)]
    steps: usize,
    #[arg(long, default_value_t = 16)]
    batch_size: usize,
    #[arg(long, default_value_t = 5e-4)]
    learning_rate: f64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Steps of linear learning-rate warm-up before the cosine decay.
    #[arg(long, default_value_t = 300)]
    warmup_steps: usize,
    /// Timestep shift used in training and sampling.
    #[arg(long, default_value_t = 1.0)]
    timestep_shift: f32,
    #[arg(long, default_value_t = 200)]
    checkpoint_every: usize,
    /// Start a new run from these weights (a folder with ema.safetensors, e.g. weights/gldot-small)
    /// instead of a random initialisation.
    #[arg(long)]
    init: Option<PathBuf>,
    /// Loss weight per target channel: R,G,B,mask,near depth,far depth (normalised to mean 1).
    /// Default: uniform.
    #[arg(long, value_delimiter = ',', num_args = 1..)]
    channel_loss_weights: Vec<f32>,
    /// Use only the first N shards (for quick experiments).
    #[arg(long)]
    limit_shards: Option<usize>,
    /// At most this many pairs in memory (about 100 KB each at 64 px): a seeded draw of shards,
    /// drawn again every --reshuffle-every steps, so a larger set is used whole over a run.
    #[arg(long, default_value_t = 60_000)]
    resident_pairs: usize,
    #[arg(long, default_value_t = 2_000)]
    reshuffle_every: usize,
    /// Weight of the mask head's classification loss against the flow loss.
    #[arg(long, default_value_t = 1.0)]
    mask_loss_weight: f32,
    /// Add the mean head (colour and depth residuals read at the first step, trained with L1);
    /// with --init from a model without it, its channels start at zero (the base).
    #[arg(long)]
    mean_head: bool,
    /// Weight of the mean head's L1 loss against the flow loss.
    #[arg(long, default_value_t = 1.0)]
    mean_loss_weight: f32,
    /// Add the error head (the mean head's expected near- and far-side depth error, trained with
    /// a Laplace likelihood, the mean held fixed); needs --mean-head. The pipeline leaves out
    /// points expected further off than `completers.gldot.max_expected_error_m`.
    #[arg(long, requires = "mean_head")]
    error_head: bool,
    /// Weight of the error head's loss against the flow loss.
    #[arg(long, default_value_t = 1.0)]
    error_loss_weight: f32,
    /// The share of training conditions (0-1) that carry what the other views observed of
    /// each object (pairs made since they store it), as the pipeline gives them with several
    /// frames; the rest train the one-view case. 0: the shipped weights were trained without.
    #[arg(long, default_value_t = 0.0)]
    other_views_observed: f32,
    /// Metric depth loss: the mean head's depth loss weighs each pair by its crop's width over
    /// this many metres, clamped to [1, 2.5], so that wide crops (furniture), where the same
    /// relative error is more centimetres, count more. 0 = off.
    #[arg(long, default_value_t = 0.0)]
    depth_loss_metric_width: f32,
    /// The mean head's far side weighs visible pixels fully (1, not 0.25 as the visible colour
    /// and near side): an object's back is hidden behind every visible pixel.
    #[arg(long)]
    far_side_full_weight: bool,
}

/// The flags a recipe sets itself.
const RECIPE_CONFLICTS: &[&str] = &[
    "data",
    "extra_data",
    "preset",
    "mask_prior",
    "steps",
    "batch_size",
    "learning_rate",
    "seed",
    "warmup_steps",
    "timestep_shift",
    "checkpoint_every",
    "init",
    "channel_loss_weights",
    "limit_shards",
    "resident_pairs",
    "reshuffle_every",
    "mask_loss_weight",
    "mean_head",
    "mean_loss_weight",
    "error_head",
    "error_loss_weight",
    "other_views_observed",
    "depth_loss_metric_width",
    "far_side_full_weight",
];

impl TrainArgs {
    /// Total optimisation steps asked for.
    pub fn steps(&self) -> usize {
        self.steps
    }
}

/// One training run from its flags (`--config` runs go to [`crate::recipe::run_command`]).
pub fn run(a: TrainArgs) -> Result<()> {
    let Some(mut model) = GlDotConfig::preset(&a.preset) else {
        bail!("unknown preset '{}' (known: tiny, small, large)", a.preset);
    };
    if let Some(name) = &a.mask_prior {
        model.mask_prior = serde_json::from_value(serde_json::Value::String(name.clone()))
            .map_err(|_| {
                anyhow::anyhow!(
                    "unknown --mask-prior '{name}' (known: visible, hull_in_front, ellipse_in_front, ellipse_or_box_in_front)"
                )
            })?;
        model
            .validate()
            .map_err(|e| anyhow::anyhow!("--mask-prior {name}: {e}"))?;
    }
    if a.mean_head {
        model.mean_head = true;
        model
            .validate()
            .map_err(|e| anyhow::anyhow!("--mean-head: {e}"))?;
    }
    if a.error_head {
        model.error_head = true;
        model
            .validate()
            .map_err(|e| anyhow::anyhow!("--error-head: {e}"))?;
    }
    let mut shards = shards(&a.data, "train")
        .with_context(|| format!("{}: cannot list training pairs", a.data.display()))?;
    if shards.is_empty() {
        bail!("{}: no train-*.safetensors shards; make them with `deocc synth pairs --split train --out {}`", a.data.display(), a.data.display());
    }
    if let Some(extra) = &a.extra_data {
        let more = deocc_model::data::shards(extra, "train")
            .with_context(|| format!("{}: cannot list training pairs", extra.display()))?;
        if more.is_empty() {
            bail!(
                "--extra-data {}: no train-*.safetensors shards",
                extra.display()
            );
        }
        shards.extend(more);
    }
    if let Some(n) = a.limit_shards {
        shards.truncate(n.max(1));
    }
    for (name, v) in [
        ("--batch-size", a.batch_size),
        ("--steps", a.steps),
        ("--checkpoint-every", a.checkpoint_every),
        ("--resident-pairs", a.resident_pairs),
        ("--reshuffle-every", a.reshuffle_every),
    ] {
        if v == 0 {
            bail!("{name} must be at least 1");
        }
    }
    if !(a.learning_rate.is_finite() && a.learning_rate > 0.0 && a.learning_rate < 1.0) {
        bail!("--learning-rate {} is outside (0, 1)", a.learning_rate);
    }
    if !(0.0..=1.0).contains(&a.other_views_observed) {
        bail!(
            "--other-views-observed {} is outside [0, 1] (a share of the training pairs)",
            a.other_views_observed
        );
    }
    if !(a.mean_loss_weight.is_finite() && a.mean_loss_weight >= 0.0) {
        bail!(
            "--mean-loss-weight {} must be finite and non-negative",
            a.mean_loss_weight
        );
    }
    if !(a.depth_loss_metric_width.is_finite() && a.depth_loss_metric_width >= 0.0) {
        bail!(
            "--depth-loss-metric-width {} must be finite and non-negative (metres; 0 = off)",
            a.depth_loss_metric_width
        );
    }
    if !(a.error_loss_weight.is_finite() && a.error_loss_weight >= 0.0) {
        bail!(
            "--error-loss-weight {} must be finite and non-negative",
            a.error_loss_weight
        );
    }
    if !(a.mask_loss_weight.is_finite() && a.mask_loss_weight >= 0.0) {
        bail!(
            "--mask-loss-weight {} must be finite and non-negative",
            a.mask_loss_weight
        );
    }
    let config = TrainConfig {
        mask_threshold: if model.mask_head { 0.5 } else { 0.0 },
        model,
        seed: a.seed,
        batch_size: a.batch_size,
        steps: a.steps,
        learning_rate: a.learning_rate,
        warmup_steps: a.warmup_steps,
        timestep_shift: a.timestep_shift,
        checkpoint_every: a.checkpoint_every,
        channel_loss_weights: a.channel_loss_weights,
        mask_loss_weight: a.mask_loss_weight,
        mean_loss_weight: a.mean_loss_weight,
        error_loss_weight: a.error_loss_weight,
        other_views_observed: a.other_views_observed,
        depth_loss_metric_width_m: a.depth_loss_metric_width,
        far_side_full_weight: a.far_side_full_weight,
        ..TrainConfig::default()
    };
    let opts = TrainRunOptions {
        run: a.run.clone(),
        config,
        init: a.init.clone(),
        shards,
        resident_pairs: a.resident_pairs,
        reshuffle_every: a.reshuffle_every,
    };
    let device = candle_core::Device::Cpu;
    let mut pb: Option<indicatif::ProgressBar> = None;
    let mut recent: Vec<f32> = Vec::new();
    let state = train_run(&opts, &device, &mut |trainer, r| {
        let pb = pb.get_or_insert_with(|| {
            let start = trainer.state.step.saturating_sub(1);
            eprintln!(
                "training {} parameters, step {start} -> {}, run {}",
                deocc_model::model::parameter_count(&trainer.varmap),
                trainer.config.steps,
                a.run.display()
            );
            bar((trainer.config.steps - start) as u64, "train")
        });
        recent.push(r.loss);
        if recent.len() > 50 {
            recent.remove(0);
        }
        pb.set_message(format!(
            "loss {:.4}",
            recent.iter().sum::<f32>() / recent.len() as f32
        ));
        pb.inc(1);
    })?;
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    println!(
        "trained to step {} (last loss {:.4}); run in {}",
        state.step,
        state.last_loss,
        a.run.display()
    );
    Ok(())
}

#[derive(Args)]
pub struct ExportArgs {
    /// Training run directory.
    #[arg(long)]
    run: PathBuf,
    /// Output folder: train.json + ema.safetensors (f16), loadable by `deocc run --weights`.
    #[arg(long)]
    out: PathBuf,
    /// Mask threshold to ship in the config (a probability in [0, 1] for models with a mask head,
    /// the mask channel in [-1, 1] otherwise); choose it on the validation pairs (`deocc eval
    /// amodal --split val --mask-thresholds ...`). Default: the run's.
    #[arg(long, allow_hyphen_values = true)]
    mask_threshold: Option<f32>,
    /// The threshold to ship for crops that carry other views' reprojected observations (`none`:
    /// the plain threshold everywhere); choose it on the validation pairs (`deocc eval amodal
    /// --split val --mask-thresholds-seen-elsewhere ...`). Default: the run's.
    #[arg(long, value_name = "THRESHOLD|none")]
    mask_threshold_seen_elsewhere: Option<String>,
    /// Ship the rule that keeps every pixel of the geometric prior in the amodal mask (the model
    /// only adds pixels); choose it on the validation pairs (`deocc eval amodal --split val
    /// --keep-prior true|false`).
    #[arg(long)]
    keep_prior: Option<bool>,
    /// Samples averaged per completion, odd ones on the crop mirrored left to right (test-time
    /// augmentation); choose it on the validation pairs (`deocc eval amodal --split val
    /// --samples N`). Default: the run's.
    #[arg(long)]
    samples: Option<usize>,
}

/// Ships a run's EMA weights in half precision (half the size, same completions to within f16
/// rounding) with the run's config.
pub fn export(a: ExportArgs) -> Result<()> {
    let out = deocc_model::export::export_run(
        &a.run,
        &a.out,
        &deocc_model::export::ExportOptions {
            mask_threshold: a.mask_threshold,
            mask_threshold_seen_elsewhere: a
                .mask_threshold_seen_elsewhere
                .as_deref()
                .map(parse_optional_threshold)
                .transpose()?,
            keep_prior: a.keep_prior,
            samples: a.samples,
        },
    )?;
    println!("exported {} -> {}", a.run.display(), out.display());
    Ok(())
}

/// `none`, or a threshold.
pub(crate) fn parse_optional_threshold(s: &str) -> Result<Option<f32>> {
    if s == "none" {
        return Ok(None);
    }
    let th = s.parse::<f32>().map_err(|e| {
        anyhow::anyhow!("--mask-threshold-seen-elsewhere {s:?} is neither a number nor `none`: {e}")
    })?;
    anyhow::ensure!(
        (0.0..=1.0).contains(&th),
        "--mask-threshold-seen-elsewhere {s:?}: a probability threshold lies in [0, 1] (or `none`)"
    );
    Ok(Some(th))
}

#[cfg(test)]
mod tests {
    use super::parse_optional_threshold;

    /// `none` and thresholds in [0, 1] are taken; anything else is refused with the flag named.
    #[test]
    fn optional_thresholds_are_none_or_a_probability() {
        assert_eq!(parse_optional_threshold("none").unwrap(), None);
        assert_eq!(parse_optional_threshold("0.8").unwrap(), Some(0.8));
        for bad in ["-1", "1.5", "high", ""] {
            let e = parse_optional_threshold(bad).unwrap_err().to_string();
            assert!(e.contains("--mask-threshold-seen-elsewhere"), "{bad}: {e}");
        }
    }
}
