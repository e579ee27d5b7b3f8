//! Completer chains by name (`"gldot"`, `"rules"`, `"gldot,rules"`), GL-DoT loaded from a
//! weights folder or the built-in model: one spelling for the CLI's `--completer`, the Python
//! package and the ROS 2 bridge.

use std::path::Path;

use deocc_completion::rules::RulesCompleter;
use deocc_completion::{Completer, CompleterChain};

use crate::GlDotCompleter;

/// The completers a chain may name.
pub const KNOWN: &str = "gldot, rules";

/// Loads GL-DoT from `weights` (train.json + safetensors), or the built-in model.
pub fn load_gldot(weights: Option<&Path>) -> Result<GlDotCompleter, String> {
    let device = candle_core::Device::Cpu;
    match weights {
        Some(dir) => GlDotCompleter::from_dir(dir, &device)
            .map_err(|e| format!("loading the model from {}: {e}", dir.display())),
        None => {
            crate::builtin::load(&device).map_err(|e| format!("loading the built-in model: {e}"))
        }
    }
}

/// The chain of `names` in order (each crop goes to the first that takes it).
pub fn build<S: AsRef<str>>(names: &[S], weights: Option<&Path>) -> Result<CompleterChain, String> {
    if names.is_empty() {
        return Err(format!("no completer named (known: {KNOWN})"));
    }
    let mut links: Vec<Box<dyn Completer>> = Vec::new();
    for name in names {
        match name.as_ref().trim() {
            "gldot" => links.push(Box::new(load_gldot(weights)?)),
            "rules" => links.push(Box::new(RulesCompleter::default())),
            other => return Err(format!("unknown completer {other:?} (known: {KNOWN})")),
        }
    }
    Ok(CompleterChain::new(links))
}

/// Which completers and which weights, for health answers and logs: e.g.
/// `gldot,rules (built-in gldot-small fnv64 1f3a...)`.
pub fn describe<S: AsRef<str>>(names: &[S], weights: Option<&Path>) -> String {
    let list: Vec<&str> = names.iter().map(|n| n.as_ref().trim()).collect();
    let joined = list.join(",");
    if !list.contains(&"gldot") {
        return joined;
    }
    match weights {
        Some(dir) => format!("{joined} (weights {})", dir.display()),
        None => format!("{joined} (built-in {})", crate::builtin::fingerprint()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_build_chains_and_unknown_names_are_refused() {
        assert!(build(&["rules"], None).is_ok());
        let e = build(&["rules", "magic"], None).err().unwrap();
        assert!(e.contains("\"magic\"") && e.contains(KNOWN), "{e}");
        assert!(build::<&str>(&[], None).is_err());
        let e = build(&["gldot"], Some(Path::new("/no/such/dir")))
            .err()
            .unwrap();
        assert!(e.contains("/no/such/dir"), "{e}");
        assert_eq!(describe(&["rules"], None), "rules");
        assert!(
            describe(&["gldot", "rules"], None).starts_with("gldot,rules (built-in gldot-small")
        );
    }
}
