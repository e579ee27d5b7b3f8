//! `deocc batch`: the pipeline over a manifest of scene folders, one shard of it per job.
//! Scene k of the manifest belongs to shard k mod N; each writes `OUT/<scene folder name>/`
//! exactly as `deocc run` would (atomically), scenes whose output is complete are skipped, and
//! every scene's outcome is appended to `OUT/summary-<I>-of-<N>.jsonl` as it ends.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde::Serialize;

use crate::completers::{CompleterArgs, PipelineArgs};

#[derive(Args)]
pub struct BatchArgs {
    /// Text file, one scene folder per line (relative paths are relative to the manifest's
    /// folder; blank lines and lines starting with # are skipped).
    #[arg(long)]
    manifest: PathBuf,
    /// Output folder: one sub-folder per scene, named as the scene's folder.
    #[arg(long)]
    out: PathBuf,
    /// This job's shard, 0-based. Default: $JOB_COMPLETION_INDEX (Kubernetes Indexed Jobs),
    /// else $SLURM_ARRAY_TASK_ID, else 0.
    #[arg(long)]
    shard_index: Option<usize>,
    /// Number of shards. Default: $SLURM_ARRAY_TASK_COUNT, else 1.
    #[arg(long)]
    shard_count: Option<usize>,
    #[command(flatten)]
    completers: CompleterArgs,
    #[command(flatten)]
    pipeline: PipelineArgs,
    #[command(flatten)]
    depth: crate::depth::DepthArgs,
    /// Ignore given instance maps and segment every frame with the default RGB-D segmenter.
    #[arg(long)]
    segment: bool,
}

/// One line of the JSONL summary.
#[derive(Serialize)]
struct SummaryLine<'a> {
    scene: &'a Path,
    out: &'a Path,
    /// `done`, `skipped` (a complete output was already there) or `failed`.
    status: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    error: Option<String>,
    seconds: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    points_observed: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    points_generated: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    objects_completed: Option<usize>,
}

/// The manifest's scene folders, in order; errors name the manifest and the line.
pub fn read_manifest(path: &Path) -> Result<Vec<PathBuf>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read the manifest", path.display()))?;
    let base = path.parent().unwrap_or(Path::new(""));
    let mut scenes: Vec<PathBuf> = Vec::new();
    let mut names: std::collections::HashMap<String, usize> = Default::default();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let scene = base.join(line);
        let Some(name) = scene.file_name().map(|n| n.to_string_lossy().into_owned()) else {
            bail!(
                "{}:{}: {line:?} does not end in a folder name",
                path.display(),
                i + 1
            );
        };
        if let Some(first) = names.insert(name.clone(), i + 1) {
            bail!(
                "{}:{}: a second scene named {name:?} (line {first}); outputs are named by \
                 the scene folder, so names must differ",
                path.display(),
                i + 1
            );
        }
        scenes.push(scene);
    }
    if scenes.is_empty() {
        bail!("{}: the manifest names no scene", path.display());
    }
    Ok(scenes)
}

fn env_usize(name: &str) -> Result<Option<usize>> {
    match std::env::var(name) {
        Ok(v) => v
            .trim()
            .parse()
            .map(Some)
            .with_context(|| format!("${name} = {v:?} is not a non-negative integer")),
        Err(_) => Ok(None),
    }
}

/// (index, count) of this job's shard from the options or the scheduler's environment.
fn shard(a: &BatchArgs) -> Result<(usize, usize)> {
    let index = match a.shard_index {
        Some(i) => i,
        None => env_usize("JOB_COMPLETION_INDEX")?
            .or(env_usize("SLURM_ARRAY_TASK_ID")?)
            .unwrap_or(0),
    };
    let count = match a.shard_count {
        Some(n) => n,
        None => env_usize("SLURM_ARRAY_TASK_COUNT")?.unwrap_or(1),
    };
    if count == 0 {
        bail!("--shard-count must be at least 1");
    }
    if index >= count {
        bail!("shard index {index} is not below the shard count {count} (--shard-index / --shard-count)");
    }
    Ok((index, count))
}

pub fn batch(a: BatchArgs) -> Result<()> {
    let scenes = read_manifest(&a.manifest)?;
    let (index, count) = shard(&a)?;
    let mut opts = a.pipeline.options()?;
    a.depth.apply(&mut opts);
    let chain = crate::completers::chain(&a.completers)?;
    let depth = a.depth.model()?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create the output folder", a.out.display()))?;
    let summary_path = a.out.join(format!("summary-{index}-of-{count}.jsonl"));
    let mut summary = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&summary_path)
        .with_context(|| format!("{}: cannot write", summary_path.display()))?;
    let mine: Vec<&PathBuf> = scenes.iter().skip(index).step_by(count).collect();
    let pb = crate::progress::bar(mine.len() as u64, "scenes");
    let (mut done, mut skipped, mut failed) = (0usize, 0usize, 0usize);
    for scene in mine {
        let name = scene.file_name().unwrap_or_default();
        let out = a.out.join(name);
        let t = Instant::now();
        let mut line = SummaryLine {
            scene,
            out: &out,
            status: "done",
            error: None,
            seconds: 0.0,
            points_observed: None,
            points_generated: None,
            objects_completed: None,
        };
        if deocc_pipeline::output::is_complete_output(&out) {
            line.status = "skipped";
            skipped += 1;
        } else {
            match crate::run::run_scene(
                Some(scene),
                &out,
                &chain,
                &opts,
                depth
                    .as_ref()
                    .map(|d| d as &dyn deocc_pipeline::depth::DepthSource),
                &crate::run::RunHow {
                    segment: a.segment,
                    ..Default::default()
                },
            ) {
                Ok(run) => {
                    let r = &run.result.report;
                    line.points_observed = Some(r.points_observed);
                    line.points_generated = Some(r.points_generated);
                    line.objects_completed = Some(r.objects_completed);
                    done += 1;
                }
                Err(e) => {
                    pb.suspend(|| eprintln!("{}: {e:#}", scene.display()));
                    line.status = "failed";
                    line.error = Some(format!("{e:#}"));
                    failed += 1;
                }
            }
        }
        line.seconds = t.elapsed().as_secs_f64();
        writeln!(summary, "{}", serde_json::to_string(&line)?)
            .and_then(|_| summary.flush())
            .with_context(|| format!("{}: cannot write", summary_path.display()))?;
        pb.inc(1);
    }
    pb.finish_and_clear();
    println!(
        "shard {index} of {count}: {done} done, {skipped} skipped (complete already), {failed} failed; summary in {}",
        summary_path.display()
    );
    if failed > 0 {
        bail!("{failed} scene(s) failed; see {}", summary_path.display());
    }
    Ok(())
}
