//! Batches for GL-DoT from the training pairs (`deocc_io::pairs` shards, made by `deocc synth
//! pairs`). Each pair becomes a plain [`CropCondition`] and a [`TargetView`], encoded into
//! channels by [`crate::encode`], the same code inference uses.

use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use candle_core::{Device, Result, Tensor};
use deocc_completion::priors::{ellipse_prior, hull_prior};
use deocc_completion::{CropCondition, MaskPrior, SeenElsewhere};
use deocc_io::pairs::{load_pairs, PairSet};
use rand::Rng;

use crate::config::ResidualBase;
use crate::encode::{base_outside_object, write_condition, write_target, TargetView};
pub use crate::encode::{COND_CHANNELS, DEPTH_SCALE, TARGET_CHANNELS};

/// Pairs plus an index of which pairs show the same object.
pub struct PairData {
    pub set: PairSet,
    groups: HashMap<u32, Vec<usize>>,
    /// Which prior condition channel 6 carries (set it to the model's, see [`condition_prior`]).
    mask_prior: MaskPrior,
    /// The residual base of the model the batches are for.
    base: ResidualBase,
    /// Whether conditions carry the other views' reprojected observations (when the set has
    /// them), as the pipeline's do with several views.
    seen_elsewhere: AtomicBool,
    /// The share of pairs (a fixed hash of the pair's index) whose conditions carry them when
    /// on: 1 for evaluation, less in training so the model also learns the one-view case.
    seen_elsewhere_share: f32,
}

impl PairData {
    pub fn new(set: PairSet) -> Self {
        let mut groups: HashMap<u32, Vec<usize>> = HashMap::new();
        for (i, &g) in set.group.iter().enumerate() {
            groups.entry(g).or_default().push(i);
        }
        Self {
            set,
            groups,
            mask_prior: MaskPrior::HullInFront,
            base: ResidualBase::Visible,
            seen_elsewhere: AtomicBool::new(true),
            seen_elsewhere_share: 1.0,
        }
    }

    /// The same pairs with (`true`, the default) or without the other views' reprojected
    /// observations in their conditions.
    pub fn with_seen_elsewhere(self, on: bool) -> Self {
        self.set_seen_elsewhere(on);
        self
    }

    /// The same pairs with the other views' observations in the conditions of about this share
    /// of them (0 = none, 1 = all that have some).
    pub fn with_seen_elsewhere_share(mut self, share: f32) -> Self {
        self.seen_elsewhere_share = share.clamp(0.0, 1.0);
        self.set_seen_elsewhere(share > 0.0);
        self
    }

    /// Switches the other views' observations on or off (for comparing the two on one set).
    pub fn set_seen_elsewhere(&self, on: bool) {
        self.seen_elsewhere.store(on, Ordering::Relaxed);
    }

    /// Whether conditions carry the other views' observations (when the set has them).
    pub fn seen_elsewhere(&self) -> bool {
        self.seen_elsewhere.load(Ordering::Relaxed)
    }

    /// The same pairs with targets made for a model with this residual base (outside the object
    /// a `rules` model's target is its base, [`crate::encode::base_outside_object`]).
    pub fn with_base(mut self, base: ResidualBase) -> Self {
        self.base = base;
        self
    }

    /// The same pairs with condition channel 6 made for a model with this residual prior.
    pub fn with_mask_prior(mut self, kind: MaskPrior) -> Self {
        self.mask_prior = kind;
        self
    }

    /// Loads and concatenates shards (group ids are made unique per shard file).
    pub fn load(paths: &[impl AsRef<Path>]) -> deocc_io::Result<Self> {
        let mut all = PairSet::default();
        for (k, p) in paths.iter().enumerate() {
            let mut s = load_pairs(p.as_ref())?;
            for g in &mut s.group {
                *g = g.wrapping_add((k as u32) << 24);
            }
            all.extend(&s);
        }
        Ok(Self::new(all))
    }

    pub fn len(&self) -> usize {
        self.set.len()
    }
    pub fn is_empty(&self) -> bool {
        self.set.is_empty()
    }
    pub fn resolution(&self) -> usize {
        self.set.resolution as usize
    }

    /// Other pairs of the same object (other views).
    pub fn other_views(&self, i: usize) -> Vec<usize> {
        self.groups
            .get(&self.set.group[i])
            .map(|v| v.iter().copied().filter(|&j| j != i).collect())
            .unwrap_or_default()
    }

    /// A random other view of pair `i`, if there is one.
    pub fn random_other_view(&self, i: usize, rng: &mut impl Rng) -> Option<usize> {
        let others = self.other_views(i);
        (!others.is_empty()).then(|| others[rng.random_range(0..others.len())])
    }

    /// Pair `i`'s condition as the pipeline would build it (no metric width: training sets do
    /// not need one), with the other views' observations when the set has them and they are on.
    pub fn condition(&self, i: usize) -> CropCondition {
        let n = self.set.pixels();
        let c = self.condition_without_elsewhere(i);
        // A fixed hash of the index picks the pairs that carry them (Knuth's multiplier).
        let draw = ((i as u32).wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32;
        let picked = self.seen_elsewhere_share >= 1.0 || draw < self.seen_elsewhere_share;
        if self.seen_elsewhere() && picked && self.set.has_elsewhere() {
            c.with_seen_elsewhere(SeenElsewhere {
                rgb: self.set.elsewhere_rgb[i * n * 3..(i + 1) * n * 3].to_vec(),
                depth: self.set.elsewhere_depth[i * n..(i + 1) * n].to_vec(),
            })
        } else {
            c
        }
    }

    /// Pair `i`'s condition from its own view alone.
    pub fn condition_without_elsewhere(&self, i: usize) -> CropCondition {
        let (n, r) = (self.set.pixels(), self.resolution());
        CropCondition::new(
            r,
            self.set.crop_rgb[i * n * 3..(i + 1) * n * 3].to_vec(),
            self.visible_mask(i).iter().map(|&m| m > 0).collect(),
            self.visible_depth(i).to_vec(),
            self.set.scene_depth[i * n..(i + 1) * n].to_vec(),
            None,
        )
    }

    /// Pair `i`'s target: the whole object.
    pub fn target(&self, i: usize) -> TargetView<'_> {
        let n = self.set.pixels();
        TargetView {
            rgb: &self.set.whole_rgb[i * n * 3..(i + 1) * n * 3],
            amodal: self.amodal_mask(i),
            depth: self.whole_depth(i),
            back_depth: self.whole_back_depth(i),
        }
    }

    /// (x0 (B, R, R, 6), cond image (B, R, R, 7)) for the given pairs; `flips[k]` mirrors sample k.
    pub fn batch(
        &self,
        indices: &[usize],
        flips: &[bool],
        device: &Device,
    ) -> Result<(Tensor, Tensor)> {
        let r = self.resolution();
        let n = r * r;
        let mut target = vec![0f32; indices.len() * n * TARGET_CHANNELS];
        let mut cond = vec![0f32; indices.len() * n * COND_CHANNELS];
        for (k, &i) in indices.iter().enumerate() {
            let flip = flips.get(k).copied().unwrap_or(false);
            let c = self.condition(i);
            let c = if flip { c.mirrored() } else { c };
            write_condition(
                &c,
                self.mask_prior,
                &mut cond[k * n * COND_CHANNELS..(k + 1) * n * COND_CHANNELS],
            );
            let t = &mut target[k * n * TARGET_CHANNELS..(k + 1) * n * TARGET_CHANNELS];
            write_target(&self.target(i), r, flip, t);
            if self.base == ResidualBase::Rules {
                base_outside_object(t, &cond[k * n * COND_CHANNELS..(k + 1) * n * COND_CHANNELS]);
            }
        }
        let b = indices.len();
        Ok((
            Tensor::from_vec(target, (b, r, r, TARGET_CHANNELS), device)?,
            Tensor::from_vec(cond, (b, r, r, COND_CHANNELS), device)?,
        ))
    }

    /// [`hull_prior`] of pair `i` (unmirrored).
    pub fn hull_prior(&self, i: usize) -> Vec<bool> {
        self.prior_of(i, hull_prior)
    }

    /// [`ellipse_prior`] of pair `i` (unmirrored).
    pub fn ellipse_prior(&self, i: usize) -> Vec<bool> {
        self.prior_of(i, ellipse_prior)
    }

    /// Condition channel 6 of pair `i` (unmirrored): the prior of [`PairData::with_mask_prior`].
    pub fn condition_prior(&self, i: usize) -> Vec<bool> {
        self.condition(i).prior_of(self.mask_prior)
    }

    fn prior_of(&self, i: usize, prior: impl Fn(&[bool], &[f32], usize) -> Vec<bool>) -> Vec<bool> {
        let n = self.set.pixels();
        let visible: Vec<bool> = self.visible_mask(i).iter().map(|&m| m > 0).collect();
        prior(
            &visible,
            &self.set.scene_depth[i * n..(i + 1) * n],
            self.resolution(),
        )
    }

    pub fn amodal_mask(&self, i: usize) -> &[u8] {
        let n = self.set.pixels();
        &self.set.amodal_mask[i * n..(i + 1) * n]
    }
    pub fn visible_mask(&self, i: usize) -> &[u8] {
        let n = self.set.pixels();
        &self.set.visible_mask[i * n..(i + 1) * n]
    }
    pub fn whole_depth(&self, i: usize) -> &[f32] {
        let n = self.set.pixels();
        &self.set.whole_depth[i * n..(i + 1) * n]
    }
    pub fn whole_back_depth(&self, i: usize) -> &[f32] {
        let n = self.set.pixels();
        &self.set.whole_back_depth[i * n..(i + 1) * n]
    }
    pub fn visible_depth(&self, i: usize) -> &[f32] {
        let n = self.set.pixels();
        &self.set.visible_depth[i * n..(i + 1) * n]
    }
}

/// Every `*.safetensors` shard of a split in a folder, sorted.
pub fn shards(dir: &Path, split: &str) -> std::io::Result<Vec<std::path::PathBuf>> {
    let mut v: Vec<_> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(&format!("{split}-")) && n.ends_with(".safetensors"))
        })
        .collect();
    v.sort();
    Ok(v)
}
