//! # deocc-completion
//!
//! The seam between the pipeline and whatever completes an occluded object. The pipeline crops a
//! view around an object's visible mask ([`CropCondition`]: colour, visible mask, relative depth
//! of the object and of the scene, the geometric prior), hands batches of crops to a
//! [`Completer`], and fuses the [`CropCompletion`]s it returns (amodal mask with a probability,
//! colour, near and far depth) back into the cloud.
//!
//! Two completers ship:
//! - [`rules::RulesCompleter`], here: the geometric prior, the nearest visible colour, a plane
//!   through the visible near side and a symmetric far side. No weights, no ML dependency; the
//!   baseline every model figure is compared with.
//! - GL-DoT (`deocc_model::GlDotCompleter`), the learned one.
//!
//! A completer may decline a crop ([`Completer::decline`], e.g. too wide for its resolution); a
//! [`CompleterChain`] hands it to the next completer. This crate has no ML dependency: a robot
//! that runs the rules completer does not build candle.
//!
//! ```
//! use deocc_completion::{Completer, CompletionOptions, CropCondition, CropRequest};
//! use deocc_completion::rules::RulesCompleter;
//!
//! // An 8x8 crop whose left half shows the object and whose right half an occluder in front.
//! let r = 8;
//! let visible: Vec<bool> = (0..r * r).map(|p| p % r < 4).collect();
//! let scene: Vec<f32> = (0..r * r).map(|p| if p % r < 4 { 0.0 } else { -0.3 }).collect();
//! let crop = CropCondition::new(r, vec![200; r * r * 3], visible, vec![0.0; r * r], scene, None);
//! let out = RulesCompleter { resolution: r, ..Default::default() }
//!     .complete(&[CropRequest { condition: &crop, other_views: &[] }], &CompletionOptions::default())
//!     .unwrap();
//! assert!(out[0].amodal.iter().zip(&crop.visible).all(|(&a, &v)| a || !v));
//! ```

pub mod crop;
pub mod policy;
pub mod priors;
pub mod rules;

pub use crop::{
    CompletionOptions, CropCompletion, CropCondition, CropRequest, ExpectedDepthError, Observed,
    SeenElsewhere,
};
pub use deocc_geometry::Provenance;
pub use policy::{FusePatch, FusePolicy};
pub use priors::MaskPrior;

/// Why a completer could not complete a batch.
#[derive(Debug, thiserror::Error)]
pub enum CompletionError {
    /// The crops do not fit the completer (resolution, channels).
    #[error("{completer}: {msg}")]
    Input { completer: String, msg: String },
    /// The completer failed (a numerical error, a device error).
    #[error("{completer}: {msg}")]
    Failed { completer: String, msg: String },
}

/// Completes crops of occluded objects. Implementations are cheap to share across threads.
pub trait Completer: Send + Sync {
    /// A short name for reports and the command line (`gldot`, `rules`).
    fn name(&self) -> &str;
    /// The provenance of the points generated from its completions.
    fn provenance(&self) -> Provenance;
    /// The crop side it wants, in pixels.
    fn resolution(&self) -> usize;
    /// `Some(reason)` when it will not complete this crop, which then goes to the next completer
    /// of a chain.
    fn decline(&self, _condition: &CropCondition) -> Option<String> {
        None
    }
    /// Whether [`CompletionOptions::steps`] changes its answer (a sampler that integrates a flow
    /// in steps); `false` for completers that answer in one pass, so a caller can say that a
    /// steps setting has no effect.
    fn uses_steps(&self) -> bool {
        false
    }
    /// How its answers are fused ([`FusePolicy`]): the caps, floors and fallbacks that suit its
    /// errors. By default the policy of its provenance ([`FusePolicy::for_provenance`]).
    fn fuse_policy(&self) -> FusePolicy {
        FusePolicy::for_provenance(self.provenance())
    }
    /// Completes a batch of crops at [`Completer::resolution`], one completion per request, in
    /// order. Deterministic for given options.
    fn complete(
        &self,
        batch: &[CropRequest<'_>],
        opts: &CompletionOptions,
    ) -> Result<Vec<CropCompletion>, CompletionError>;
}

/// Completers tried in order: each crop goes to the first that does not decline it. Each link
/// carries its own [`FusePolicy`], its completer's unless changed ([`CompleterChain::patch`]).
#[derive(Default)]
pub struct CompleterChain {
    links: Vec<Box<dyn Completer>>,
    policies: Vec<FusePolicy>,
}

impl CompleterChain {
    pub fn new(links: Vec<Box<dyn Completer>>) -> Self {
        let policies = links.iter().map(|c| c.fuse_policy()).collect();
        Self { links, policies }
    }

    pub fn single(completer: impl Completer + 'static) -> Self {
        Self::new(vec![Box::new(completer)])
    }

    /// Appends a completer that takes what the others decline.
    pub fn then(mut self, completer: impl Completer + 'static) -> Self {
        self.policies.push(completer.fuse_policy());
        self.links.push(Box::new(completer));
        self
    }

    pub fn links(&self) -> &[Box<dyn Completer>] {
        &self.links
    }

    /// Link `k`'s fusion policy.
    pub fn policy(&self, k: usize) -> FusePolicy {
        self.policies[k]
    }

    /// Changes the policy of every link named `name` (`*`: every link) by `patch`; returns how
    /// many links it changed.
    pub fn patch(&mut self, name: &str, patch: &FusePatch) -> usize {
        let mut n = 0;
        for (link, policy) in self.links.iter().zip(&mut self.policies) {
            if name == "*" || link.name() == name {
                *policy = patch.apply(*policy);
                n += 1;
            }
        }
        n
    }

    pub fn is_empty(&self) -> bool {
        self.links.is_empty()
    }

    /// `gldot,rules`: the names in order.
    pub fn describe(&self) -> String {
        self.links
            .iter()
            .map(|c| c.name())
            .collect::<Vec<_>>()
            .join(",")
    }

    /// The first link that takes the crop built by `crop_at(resolution)` (`None` when it cannot
    /// be built at that resolution), or every link's reason for declining.
    pub fn route(
        &self,
        mut crop_at: impl FnMut(usize) -> Option<CropCondition>,
    ) -> Result<(usize, CropCondition), Vec<String>> {
        let mut reasons = Vec::new();
        for (k, link) in self.links.iter().enumerate() {
            let Some(crop) = crop_at(link.resolution()) else {
                reasons.push(format!(
                    "{}: no crop at {} px",
                    link.name(),
                    link.resolution()
                ));
                continue;
            };
            match link.decline(&crop) {
                None => return Ok((k, crop)),
                Some(why) => reasons.push(format!("{}: {why}", link.name())),
            }
        }
        Err(reasons)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rules::RulesCompleter;

    /// Each link carries its completer's policy; a patch by name changes that link only, `*`
    /// every link, and an unknown name none.
    #[test]
    fn links_carry_their_policies_and_patches_find_them_by_name() {
        let mut chain = CompleterChain::single(RulesCompleter::default());
        assert_eq!(chain.policy(0), FusePolicy::RULES);
        let thin = FusePatch {
            max_thickness_m: Some(0.02),
            ..Default::default()
        };
        assert_eq!(chain.patch("gldot", &thin), 0);
        assert_eq!(chain.policy(0), FusePolicy::RULES);
        assert_eq!(chain.patch("rules", &thin), 1);
        assert_eq!(chain.policy(0).max_thickness_m, 0.02);
        assert_eq!(
            chain.patch(
                "*",
                &FusePatch {
                    max_thickness_per_width: Some(0.5),
                    ..Default::default()
                }
            ),
            1
        );
        assert_eq!(chain.policy(0).max_thickness_per_width, 0.5);
        assert_eq!(chain.policy(0).max_thickness_m, 0.02);
    }
}
