//! Where a model's amodal mask departs from its geometric prior, and whether it is right there.
//!
//! For each pair of a split: the prior's misses and false pixels, the candidate region (hidden
//! pixels where the observed scene is in front of the object, where a hidden part can be), and
//! the pixels the model adds to or removes from its prior, with how many of those changes are
//! right. The figures behind the mask paragraphs of ARCHITECTURE.md:
//!
//! ```text
//! cargo run --release -p deocc-eval --example mask_decisions -- weights/gldot-small val 300
//! ```
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use candle_core::Device;
use deocc_model::data::{shards, PairData};
use deocc_model::infer::GlDotCompleter;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (weights, split, pairs, steps) = match args.as_slice() {
        [w, s, p] => (w, s, p, "4"),
        [w, s, p, n] => (w, s, p, n.as_str()),
        _ => {
            bail!("usage: mask_decisions WEIGHTS_DIR SPLIT PAIRS [STEPS]  (pairs from data/pairs)")
        }
    };
    let pairs: usize = pairs.parse().context("PAIRS must be a number")?;
    let steps: usize = steps.parse().context("STEPS must be a number")?;
    let device = Device::Cpu;
    let completer = GlDotCompleter::from_dir(&PathBuf::from(weights), &device)?;
    let files = shards(std::path::Path::new("data/pairs"), split)?;
    if files.is_empty() {
        bail!("data/pairs: no {split}-*.safetensors shards");
    }
    let data = PairData::load(&files)?.with_mask_prior(completer.model.config.mask_prior);
    let n = pairs.min(data.len());
    let r = data.resolution();
    let idx: Vec<usize> = (0..n).collect();
    #[derive(Default)]
    struct Counts {
        prior_missed: usize,
        prior_false: usize,
        candidate: usize,
        truth_in_candidate: usize,
        added: usize,
        added_right: usize,
        removed: usize,
        removed_right: usize,
    }
    let mut c = Counts::default();
    // mIoU when the prior's pixels are kept unless the mask score is below `keep` and other
    // pixels are added where it is above `add` (one threshold for both is the completer's rule).
    const ADD: [f32; 7] = [-0.8, -0.4, 0.0, 0.4, 0.8, 1.2, f32::INFINITY];
    const KEEP: [f32; 6] = [f32::NEG_INFINITY, -1.6, -1.2, -0.8, -0.4, 0.0];
    let mut iou_sum = [[0f64; KEEP.len()]; ADD.len()];
    for chunk in idx.chunks(16) {
        let (_, cond) = data.batch(chunk, &vec![false; chunk.len()], &device)?;
        let out = completer.complete(&cond, &[], 0.0, steps, 0)?;
        for (&i, comp) in chunk.iter().zip(&out) {
            let truth = data.amodal_mask(i);
            let visible = data.visible_mask(i);
            let prior = data.condition_prior(i);
            let scene = &data.set.scene_depth[i * r * r..(i + 1) * r * r];
            for (a, &add) in ADD.iter().enumerate() {
                for (k, &keep) in KEEP.iter().enumerate() {
                    let (mut inter, mut union) = (0usize, 0usize);
                    for p in 0..r * r {
                        let score = comp.mask_score[p];
                        let m = visible[p] > 0
                            || if prior[p] {
                                keep == f32::NEG_INFINITY || score > keep
                            } else {
                                score > add
                            };
                        let t = truth[p] > 0;
                        inter += (m && t) as usize;
                        union += (m || t) as usize;
                    }
                    iou_sum[a][k] += if union == 0 {
                        1.0
                    } else {
                        inter as f64 / union as f64
                    };
                }
            }
            for p in 0..r * r {
                let (t, v, pr, m) = (truth[p] > 0, visible[p] > 0, prior[p], comp.amodal[p]);
                c.prior_missed += (t && !pr) as usize;
                c.prior_false += (!t && pr) as usize;
                let candidate = !pr && !v && scene[p] < 0.0;
                c.candidate += candidate as usize;
                c.truth_in_candidate += (candidate && t) as usize;
                if m && !pr {
                    c.added += 1;
                    c.added_right += t as usize;
                }
                if pr && !m {
                    c.removed += 1;
                    c.removed_right += (!t) as usize;
                }
            }
        }
    }
    let per = |x: usize| x as f64 / n as f64;
    println!("{n} {split} pairs, model {weights}, {steps} steps, per pair:");
    println!(
        "  prior: misses {:.1} object pixels, {:.1} false pixels",
        per(c.prior_missed),
        per(c.prior_false)
    );
    println!(
        "  candidate region (scene in front, outside the prior): {:.1} pixels, {:.1} of them object",
        per(c.candidate),
        per(c.truth_in_candidate)
    );
    println!(
        "  model adds {:.1} pixels ({:.1} right), removes {:.1} prior pixels ({:.1} right)",
        per(c.added),
        per(c.added_right),
        per(c.removed),
        per(c.removed_right)
    );
    println!("  mIoU by add threshold (rows) and keep threshold (columns; -inf: keep every prior pixel):");
    print!("  {:>8}", "");
    for keep in KEEP {
        print!(" {keep:>7.1}");
    }
    println!();
    for (a, add) in ADD.iter().enumerate() {
        print!("  {add:>8.1}");
        for sum in iou_sum[a] {
            print!(" {:>7.4}", sum / n as f64);
        }
        println!();
    }
    Ok(())
}
