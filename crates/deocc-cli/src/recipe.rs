//! `deocc train --config RECIPE.json --run DIR`: a shipped model's whole recipe, from no data to
//! exported weights, in one resumable command.
//!
//! A recipe names the training pairs to make (each entry is a `deocc synth pairs` call), the
//! phases of training (each a `deocc train` call; a phase starts from the previous phase's EMA
//! weights) and the export. Every entry is a map from a flag's name (`snake_case` or
//! `kebab-case`) to its value, parsed by the same argument parser as the command line, so a
//! recipe has the command line's defaults, checks and help (`deocc train --help`), and an
//! unknown key is refused as an unknown flag is. Paths in the recipe are resolved against
//! `--data-root` (default: the working directory).
//!
//! The run directory holds `recipe.json` (the recipe it was started with; another recipe is
//! refused), one folder per phase (`01-main/`, ...; each an ordinary run directory) and
//! `export/` (the shipped form). Stopped anywhere, the same command resumes: pairs whose
//! manifest exists are kept, finished phases are skipped, a started phase resumes from its
//! last checkpoint.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, FromArgMatches};
use serde::Deserialize;
use serde_json::{Map, Value};

/// A recipe file (see the module documentation; `configs/gldot-small-sensors.json` is the shipped
/// model's).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recipe {
    /// What the recipe makes (a line for people).
    pub about: String,
    /// `deocc synth pairs` calls, in order.
    #[serde(default)]
    pub data: Vec<Map<String, Value>>,
    /// `deocc train` calls, in order; each needs a `name`.
    pub phases: Vec<Map<String, Value>>,
    /// `deocc export` flags (besides `--run` and `--out`).
    #[serde(default)]
    pub export: Map<String, Value>,
}

impl Recipe {
    pub fn read(path: &Path) -> Result<Recipe> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read the recipe", path.display()))?;
        let recipe: Recipe = serde_json::from_str(&text)
            .with_context(|| format!("{}: not a training recipe", path.display()))?;
        if recipe.phases.is_empty() {
            bail!("{}: `phases` is empty", path.display());
        }
        for (k, p) in recipe.phases.iter().enumerate() {
            for key in ["config", "run", "init", "data_root"] {
                if p.contains_key(key) {
                    bail!(
                        "{}: phase {}: `{key}` is the recipe's to set",
                        path.display(),
                        k + 1
                    );
                }
            }
            match p.get("name") {
                Some(Value::String(n)) if valid_name(n) => {}
                _ => bail!(
                    "{}: phase {} needs a `name` of letters, digits, '-' and '_'",
                    path.display(),
                    k + 1
                ),
            }
        }
        Ok(recipe)
    }

    /// The folder of phase `k` (0-based) under the run directory.
    pub fn phase_dir(&self, run: &Path, k: usize) -> PathBuf {
        let name = self.phases[k]["name"].as_str().unwrap_or("phase");
        run.join(format!("{:02}-{name}", k + 1))
    }
}

fn valid_name(n: &str) -> bool {
    !n.is_empty()
        && n.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// Keys whose values are paths, resolved against the data root.
const PATH_KEYS: &[&str] = &["out", "data", "extra_data"];

/// A recipe entry as command-line words: `{"steps": 100, "mean_head": true}` ->
/// `--steps 100 --mean-head`. `false` leaves a switch out; a list is joined with commas; paths
/// (`out`, `data`, `extra_data`) are resolved against `root`. Keys in `skip` are left out.
pub fn to_words(entry: &Map<String, Value>, root: &Path, skip: &[&str]) -> Result<Vec<String>> {
    let mut words = Vec::new();
    for (key, value) in entry {
        if skip.contains(&key.as_str()) {
            continue;
        }
        let flag = format!("--{}", key.replace('_', "-"));
        let text = match value {
            Value::Bool(true) => {
                words.push(flag);
                continue;
            }
            Value::Bool(false) | Value::Null => continue,
            Value::Number(n) => n.to_string(),
            Value::String(s) if PATH_KEYS.contains(&key.as_str()) => {
                root.join(s).to_string_lossy().into_owned()
            }
            Value::String(s) => s.clone(),
            Value::Array(items) => items
                .iter()
                .map(|v| match v {
                    Value::Number(n) => Ok(n.to_string()),
                    Value::String(s) => Ok(s.clone()),
                    other => bail!("`{key}`: a list of numbers or words, not {other}"),
                })
                .collect::<Result<Vec<_>>>()?
                .join(","),
            Value::Object(_) => bail!("`{key}`: a value, not a map"),
        };
        words.push(flag);
        words.push(text);
    }
    Ok(words)
}

/// Parses `words` as the flags of the command whose arguments are `A` (`what` names it in
/// errors: "phase 1 (main)").
pub fn parse<A: Args + FromArgMatches>(what: &str, words: &[String]) -> Result<A> {
    let cmd = A::augment_args(clap::Command::new("deocc").no_binary_name(true));
    let matches = cmd
        .try_get_matches_from(words)
        .map_err(|e| anyhow::anyhow!("{what}: {}", e.render().to_string().trim()))?;
    A::from_arg_matches(&matches).map_err(|e| anyhow::anyhow!("{what}: {e}"))
}

/// Whether a pairs folder already holds a finished `split` (its manifest is written last).
fn pairs_made(entry: &Map<String, Value>, root: &Path) -> bool {
    let (Some(Value::String(out)), Some(Value::String(split))) =
        (entry.get("out"), entry.get("split"))
    else {
        return false;
    };
    root.join(out)
        .join(format!("{split}-manifest.json"))
        .exists()
}

/// `deocc train --config RECIPE`: the recipe, then where its weights are.
pub fn run_command(recipe: &Path, run: &Path, root: &Path) -> Result<()> {
    let out = run_recipe(recipe, run, root)?;
    println!(
        "recipe {} done: weights in {} (judge them with `deocc eval amodal --weights {}`)",
        recipe.display(),
        out.display(),
        out.display()
    );
    Ok(())
}

/// Runs (or resumes) `recipe` into `run`: data, phases, export. Returns the export folder.
pub fn run_recipe(recipe_path: &Path, run: &Path, root: &Path) -> Result<PathBuf> {
    let recipe = Recipe::read(recipe_path)?;
    eprintln!("recipe {}: {}", recipe_path.display(), recipe.about);
    std::fs::create_dir_all(run)
        .with_context(|| format!("{}: cannot create the run directory", run.display()))?;
    let kept = run.join("recipe.json");
    let text = std::fs::read_to_string(recipe_path)?;
    let canonical = |t: &str| serde_json::from_str::<Value>(t).map(|v| v.to_string());
    match std::fs::read_to_string(&kept) {
        Ok(old) if canonical(&old)? != canonical(&text)? => bail!(
            "{} was started with another recipe ({}); use a new --run directory",
            run.display(),
            kept.display()
        ),
        Ok(_) => {}
        Err(_) => deocc_io::atomic::write_bytes_atomic(&kept, text.as_bytes())?,
    }
    for (k, entry) in recipe.data.iter().enumerate() {
        if pairs_made(entry, root) {
            eprintln!("data {}: made already", k + 1);
            continue;
        }
        let words = to_words(entry, root, &[])?;
        eprintln!("data {}: deocc synth pairs {}", k + 1, words.join(" "));
        let args: crate::synth::PairsArgs = parse(&format!("data {}", k + 1), &words)?;
        crate::synth::run(crate::synth::SynthCommand::Pairs(args))?;
    }
    for k in 0..recipe.phases.len() {
        let dir = recipe.phase_dir(run, k);
        let what = format!("phase {} ({})", k + 1, recipe.phases[k]["name"]);
        let mut words = to_words(&recipe.phases[k], root, &["name"])?;
        words.extend(["--run".into(), dir.to_string_lossy().into_owned()]);
        let started = dir.join("state.json").exists();
        if k > 0 && !started {
            let prev = recipe.phase_dir(run, k - 1);
            words.extend(["--init".into(), prev.to_string_lossy().into_owned()]);
        }
        let args: crate::train::TrainArgs = parse(&what, &words)?;
        if deocc_model::train::finished(&dir, args.steps())? {
            eprintln!("{what}: finished already");
            continue;
        }
        eprintln!("{what}: deocc train {}", words.join(" "));
        crate::train::run(args).with_context(|| what.clone())?;
    }
    let last = recipe.phase_dir(run, recipe.phases.len() - 1);
    let out = run.join("export");
    let mut words = to_words(&recipe.export, root, &[])?;
    words.extend([
        "--run".into(),
        last.to_string_lossy().into_owned(),
        "--out".into(),
        out.to_string_lossy().into_owned(),
    ]);
    let args: crate::train::ExportArgs = parse("export", &words)?;
    crate::train::export(args)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(v: Value) -> Map<String, Value> {
        v.as_object().unwrap().clone()
    }

    /// Values become the command line's words: switches, numbers, lists, resolved paths.
    #[test]
    fn entries_become_flags() {
        let e = entry(serde_json::json!({
            "steps": 100, "mean_head": true, "error_head": false,
            "channel_loss_weights": [1, 0.25], "data": "pairs", "name": "main",
            "extra_data": "more"
        }));
        let words = to_words(&e, Path::new("/root"), &["name"]).unwrap();
        let line = words.join(" ");
        assert!(line.contains("--steps 100"), "{line}");
        assert!(line.contains("--mean-head"), "{line}");
        assert!(!line.contains("error-head"), "{line}");
        assert!(line.contains("--channel-loss-weights 1,0.25"), "{line}");
        assert!(line.contains("--data /root/pairs"), "{line}");
        assert!(line.contains("--extra-data /root/more"), "{line}");
        assert!(!line.contains("main"), "{line}");
        let bad = entry(serde_json::json!({"steps": {"a": 1}}));
        assert!(to_words(&bad, Path::new("."), &[]).is_err());
    }

    /// Recipe entries go through the command line's parser: unknown keys and bad values are
    /// refused with the entry named.
    #[test]
    fn entries_are_checked_like_flags() {
        let words: Vec<String> = ["--run", "r", "--steps", "5"].map(String::from).to_vec();
        let a: crate::train::TrainArgs = parse("phase 1 (main)", &words).unwrap();
        assert_eq!(a.steps(), 5);
        let words: Vec<String> = ["--run", "r", "--stepz", "5"].map(String::from).to_vec();
        let e = parse::<crate::train::TrainArgs>("phase 1 (main)", &words)
            .err()
            .expect("an unknown flag is refused")
            .to_string();
        assert!(e.contains("phase 1 (main)") && e.contains("--stepz"), "{e}");
        let words: Vec<String> = ["--run", "r", "--steps", "many"].map(String::from).to_vec();
        assert!(parse::<crate::train::TrainArgs>("p", &words).is_err());
    }

    /// The shipped recipes parse, name their phases, and every entry is a valid command.
    #[test]
    fn shipped_recipes_parse() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
        let mut n = 0;
        for f in std::fs::read_dir(&dir).unwrap() {
            let path = f.unwrap().path();
            if path.extension().is_none_or(|e| e != "json") {
                continue;
            }
            let r = Recipe::read(&path).unwrap();
            for (k, d) in r.data.iter().enumerate() {
                let words = to_words(d, Path::new("/d"), &[]).unwrap();
                parse::<crate::synth::PairsArgs>(&format!("data {k}"), &words)
                    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            }
            for (k, p) in r.phases.iter().enumerate() {
                let mut words = to_words(p, Path::new("/d"), &["name"]).unwrap();
                words.extend(["--run".into(), "/r".into()]);
                parse::<crate::train::TrainArgs>(&format!("phase {k}"), &words)
                    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            }
            let mut words = to_words(&r.export, Path::new("/d"), &[]).unwrap();
            words.extend(["--run", "/r", "--out", "/o"].map(String::from));
            parse::<crate::train::ExportArgs>("export", &words)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            n += 1;
        }
        assert!(
            n >= 2,
            "expected the shipped and the CI recipe in {}",
            dir.display()
        );
    }
}
