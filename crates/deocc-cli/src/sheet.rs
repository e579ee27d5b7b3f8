//! `deocc synth sheet`: contact sheets of a scene or of training pairs.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;
use deocc_synth::dataset::render_full_scene;

use crate::scene_options::SceneOptions;

#[derive(Args)]
pub struct SheetArgs {
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Show training pairs from this shard instead of a scene (crop | visible | whole | amodal | depth).
    #[arg(long)]
    pairs: Option<PathBuf>,
    /// Show the default RGB-D segmenter's segments in the last column instead of amodal masks.
    #[arg(long)]
    segments: bool,
    /// Views shown (rows).
    #[arg(long, default_value_t = 3)]
    rows: usize,
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    options: SceneOptions,
}

pub fn sheet(a: SheetArgs) -> Result<()> {
    if let Some(path) = &a.pairs {
        let set = deocc_synth::pairs::load_pairs(path)?;
        if set.is_empty() {
            bail!("{}: no pairs", path.display());
        }
        let step = (set.len() / a.rows.max(1)).max(1);
        let idx: Vec<usize> = (0..set.len()).step_by(step).take(a.rows.max(1)).collect();
        deocc_io::images::write_rgb_png(&a.out, &deocc_synth::sheet::pair_sheet(&set, &idx))?;
        println!("wrote {}", a.out.display());
        return Ok(());
    }
    let config = a.options.config()?;
    let rendered = render_full_scene(&config, a.seed)?;
    let n = a.rows.clamp(1, rendered.views.len());
    let step = (rendered.views.len() / n).max(1);
    let mut picked: Vec<_> = rendered.views.into_iter().step_by(step).take(n).collect();
    if a.segments {
        use deocc_pipeline::segment::ConvexitySegmenter;
        let seg = ConvexitySegmenter::default();
        for v in &mut picked {
            let map = seg.segment_depth(&v.depth, &v.camera);
            // Draw segments as "amodal masks" of every segment id: the sheet colours them by id.
            v.amodal = Vec::new();
            v.frame.instance = map.ids;
        }
    }
    let img = deocc_synth::sheet::contact_sheet(&picked);
    deocc_io::images::write_rgb_png(&a.out, &img)?;
    println!("wrote {}", a.out.display());
    Ok(())
}
