//! Which completers a command uses: `--completer gldot|rules|gldot,rules` and `--weights`. The
//! shipped GL-DoT weights are built into the binary, so `deocc` works from any folder; `--weights
//! DIR` loads another model.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use deocc_completion::CompleterChain;

#[derive(Args, Clone, Debug)]
pub struct CompleterArgs {
    /// Completers tried in order, comma-separated: each crop goes to the first that takes it
    /// (GL-DoT declines crops wider than 0.6 m, furniture, which the rules then complete).
    /// `gldot` (the learned model), `rules` (geometric prior, nearest colour, plane and
    /// symmetric depth). The default is the shipped chain every benchmark's shipped row runs.
    #[arg(long, default_value = "gldot,rules", value_delimiter = ',')]
    pub completer: Vec<String>,
    /// GL-DoT model folder (train.json + ema.safetensors or model.safetensors). Default: the
    /// shipped model built into this binary.
    #[arg(long)]
    pub weights: Option<PathBuf>,
}

/// Loads GL-DoT from `weights`, or the built-in model.
#[cfg(feature = "lab")]
pub fn load_gldot(weights: Option<&std::path::Path>) -> Result<deocc_model::GlDotCompleter> {
    deocc_model::chain::load_gldot(weights).map_err(anyhow::Error::msg)
}

/// The chain named by `--completer`.
pub fn chain(a: &CompleterArgs) -> Result<CompleterChain> {
    deocc_model::chain::build(&a.completer, a.weights.as_deref())
        .map_err(|e| anyhow::anyhow!("--completer: {e}"))
}

/// Says so when `--steps` cannot change the answer: no completer of `chain` samples in steps
/// (the shipped GL-DoT reads its mean head in one forward pass). Returns whether it warned.
pub fn warn_unused_steps(chain: &CompleterChain, steps: usize) -> bool {
    if chain.links().iter().any(|c| c.uses_steps()) {
        return false;
    }
    let names: Vec<&str> = chain.links().iter().map(|c| c.name()).collect();
    eprintln!(
        "warning: --steps {steps} has no effect: {} answer in one pass (the shipped GL-DoT \
         reads its mean head at the first step)",
        names.join(", ")
    );
    true
}

/// Which completers and which weights `a` names, for a server's Health answer and logs: e.g.
/// `gldot,rules (built-in gldot-small, fnv64 1f3a...)`.
pub fn describe_model(a: &CompleterArgs) -> String {
    deocc_model::chain::describe(&a.completer, a.weights.as_deref())
}

/// Named chains for a benchmark's rows: each entry a chain spelled as `--completer` would
/// (`"gldot,rules"`), all loading GL-DoT from `weights` (or the built-in model).
#[cfg(feature = "lab")]
pub fn named_chains(
    weights: Option<&std::path::Path>,
    names: &[&str],
) -> Result<Vec<(String, CompleterChain)>> {
    names
        .iter()
        .map(|&name| {
            let c = chain(&CompleterArgs {
                completer: name.split(',').map(str::to_string).collect(),
                weights: weights.map(std::path::Path::to_path_buf),
            })?;
            Ok((name.to_string(), c))
        })
        .collect()
}

/// The pipeline options of a benchmark command: the defaults, or `--options FILE`, with
/// `--steps` on top.
#[derive(Args, Clone, Debug)]
pub struct PipelineArgs {
    /// Denoising steps of a generative completer (default: 4, or the options file's).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Pipeline options as JSON (the fields of `deocc run --options`); missing fields take
    /// their defaults.
    #[arg(long)]
    pub options: Option<PathBuf>,
}

impl PipelineArgs {
    /// The options, validated; errors name the file or `--steps`.
    pub fn options(&self) -> Result<deocc_pipeline::PipelineOptions> {
        let mut opts = match &self.options {
            Some(path) => deocc_pipeline::PipelineOptions::from_json_file(path)?,
            None => deocc_pipeline::PipelineOptions::default(),
        };
        if let Some(steps) = self.steps {
            opts.steps = steps;
            opts.validate()
                .map_err(|e| anyhow::anyhow!("{e} (from --steps)"))?;
        }
        Ok(opts)
    }
}
