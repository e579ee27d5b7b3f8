//! How a completer's answers become points: the settings that belong to one completer, not to
//! the pipeline. Each link of a [`crate::CompleterChain`] carries its own [`FusePolicy`] (from
//! [`crate::Completer::fuse_policy`]): a learned completer's rough depth gets a thickness cap
//! relative to its silhouette, a confidence floor and a gate on its own expected error with the
//! rules as fallback; the rules' mirrored far side gets a looser cap. A run may change any field
//! of any link by name ([`FusePatch`]), never by provenance.

use serde::{Deserialize, Serialize};

/// The shipped completers' names (`deocc_model::GlDotCompleter`'s and
/// [`crate::rules::RulesCompleter`]'s): an options file may patch their policies whether or not
/// a given chain has them (one file serves every row of a benchmark); any other name must be a
/// link of the chain it runs with.
pub const SHIPPED_LINKS: &[&str] = &["gldot", "rules"];

/// The fusion settings of one completer (a chain link).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FusePolicy {
    /// Median filter radius, pixels of the crop (0 = off), of the completer's near and far
    /// depth over its amodal mask before fusion: a learned completer's per-pixel depth is rough,
    /// and a rough hidden side gives a grasp planner normals that point anywhere.
    pub depth_median_px: usize,
    /// The median filter applies only to crops no wider than this (metres at the object's
    /// median visible depth; 0 = every crop).
    pub depth_median_max_crop_m: f32,
    /// Thickness cap (metres; 0 = off): a far-side point more than this behind its near side
    /// (observed or generated) is not generated.
    pub max_thickness_m: f32,
    /// Thickness cap relative to the silhouette (0 = off): a far-side point more than this many
    /// times the width of its amodal row run (in metres) behind its near side is not generated.
    pub max_thickness_per_width: f32,
    /// Revealed pixels (hidden here, no other view's observation) whose mask probability is
    /// below this generate no point, near side or far (0 = every pixel of the amodal mask).
    pub min_revealed_confidence: f32,
    /// A completer that estimates its own depth error (GL-DoT's error head) generates no point
    /// it expects further off than this, metres through the depth fit (0 = off; no effect on a
    /// completer without an estimate).
    pub max_expected_error_m: f32,
    /// With that limit set, the pixels it leaves out are completed by the rules completer
    /// instead, so that the model abstains where it expects to be off rather than leaving a
    /// hole.
    pub uncertain_to_rules: bool,
    /// The expected error (metres) each generated point of this completer carries when the
    /// completion has no estimate of its own (a completer with one, GL-DoT's error head, gives
    /// each point its own). The cloud's `expected_error`, which the grasp and place planners
    /// may grow the hidden side by.
    pub stated_error_m: f32,
}

impl FusePolicy {
    /// Nothing capped, filtered or gated.
    pub const NONE: FusePolicy = FusePolicy {
        depth_median_px: 0,
        depth_median_max_crop_m: 0.0,
        max_thickness_m: 0.0,
        max_thickness_per_width: 0.0,
        min_revealed_confidence: 0.0,
        max_expected_error_m: 0.0,
        uncertain_to_rules: false,
        stated_error_m: 0.0,
    };

    /// A learned completer's policy (GL-DoT's), each value measured on bench-v1-like tuning
    /// scenes (`deocc eval objects --tuning --scenes 20`; docs/decisions.md):
    /// - thickness cap 0.10 m: GL-DoT's points within 2 cm of a true surface and the chain's
    ///   hidden recall, off 55.3% / 0.499, 0.15 m 59.8% / 0.497, 0.10 m 64.6% / 0.490, 0.08 m
    ///   66.5% / 0.480, 0.05 m 67.2% / 0.439 (deep far sides are mostly furniture rays that leave
    ///   through a far leg or edge);
    /// - relative cap 1.0 x the row width: off 16.4k points 77.5% 0.490, 1.5 15.6k 78.5% 0.488,
    ///   1.0 14.0k 79.7% 0.487, 0.75 11.9k 79.0% 0.481 (thin legs and fragments get no deep back);
    /// - revealed confidence 0.9: off 25.6k 74.7% 0.492, 0.9 17.5k 77.5% 0.489, 0.97 13.7k
    ///   78.4% 0.488; 0.9 keeps furniture's recall above the rules' (+9.2% [+3.6%, +15.9%]);
    /// - expected error 3 cm with the rules' fallback: 82.9% -> 86.5% within 2 cm, the chain's
    ///   recall over the rules +11.9% -> +10.2%, furniture level with the rules;
    /// - no median filter (it cost furniture's hidden recall; docs/decisions.md);
    /// - stated error 1 cm for a model without the error head (64-80% of its points within 2 cm
    ///   of a true surface above).
    pub const LEARNED: FusePolicy = FusePolicy {
        depth_median_px: 0,
        depth_median_max_crop_m: 0.0,
        max_thickness_m: 0.10,
        max_thickness_per_width: 1.0,
        min_revealed_confidence: 0.9,
        max_expected_error_m: 0.03,
        uncertain_to_rules: true,
        stated_error_m: 0.01,
    };

    /// The rules completer's policy: its far side (the near side mirrored) no deeper than
    /// 0.15 m behind the near side, chosen on the same tuning scenes: the rules row's points,
    /// their share within 2 cm of a true surface and its hidden recall, off 62.8k 41.6% 0.424,
    /// 0.15 m 38.4k 63.0% 0.422, 0.10 m 34.8k 67.3% 0.417, 0.08 m 29.4k 70.6% 0.407: the largest
    /// cap that keeps the baseline's recall. Its depth is smooth already (planes and mirrored
    /// surfaces), so no median; its probability is its prior, so no confidence floor. Its stated
    /// error, 2 cm, is the distance within which 63% of its points lie.
    pub const RULES: FusePolicy = FusePolicy {
        max_thickness_m: 0.15,
        stated_error_m: 0.02,
        ..FusePolicy::NONE
    };

    /// The policy a completer of this provenance gets unless it says otherwise.
    pub fn for_provenance(p: crate::Provenance) -> FusePolicy {
        match p {
            crate::Provenance::Model => FusePolicy::LEARNED,
            crate::Provenance::Rules => FusePolicy::RULES,
            _ => FusePolicy::NONE,
        }
    }

    /// The median filter's radius for a crop `crop_width_m` wide: `depth_median_px` for a crop
    /// no wider than `depth_median_max_crop_m` (0 = any width), else 0 (a crop of unknown
    /// width, NaN, is filtered only without a limit).
    pub fn depth_median_for(&self, crop_width_m: f32) -> usize {
        depth_median_radius(
            self.depth_median_px,
            self.depth_median_max_crop_m,
            crop_width_m,
        )
    }

    /// Each field with its stated range, for validation and help: (name, value, min, max).
    pub fn numeric_fields(&self) -> [(&'static str, f64, f64, f64); 7] {
        [
            ("depth_median_px", self.depth_median_px as f64, 0.0, 16.0),
            (
                "depth_median_max_crop_m",
                self.depth_median_max_crop_m as f64,
                0.0,
                10.0,
            ),
            ("max_thickness_m", self.max_thickness_m as f64, 0.0, 10.0),
            (
                "max_thickness_per_width",
                self.max_thickness_per_width as f64,
                0.0,
                100.0,
            ),
            (
                "min_revealed_confidence",
                self.min_revealed_confidence as f64,
                0.0,
                1.0,
            ),
            (
                "max_expected_error_m",
                self.max_expected_error_m as f64,
                0.0,
                10.0,
            ),
            ("stated_error_m", self.stated_error_m as f64, 0.0, 1.0),
        ]
    }

    /// `Err("field: why")` for the first value outside its range (NaN included).
    pub fn validate(&self) -> Result<(), String> {
        for (name, v, lo, hi) in self.numeric_fields() {
            if !(lo..=hi).contains(&v) {
                return Err(format!("{name}: {v} is outside [{lo}, {hi}]"));
            }
        }
        Ok(())
    }
}

/// The median filter's rule: `radius_px` for a crop no wider than `max_crop_m` (0 = any
/// width), else 0.
pub fn depth_median_radius(radius_px: usize, max_crop_m: f32, crop_width_m: f32) -> usize {
    if max_crop_m <= 0.0 || crop_width_m <= max_crop_m {
        radius_px
    } else {
        0
    }
}

/// Changes to a link's [`FusePolicy`]: each field given replaces the link's own.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FusePatch {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth_median_px: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth_median_max_crop_m: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_thickness_m: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_thickness_per_width: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_revealed_confidence: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_expected_error_m: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub uncertain_to_rules: Option<bool>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stated_error_m: Option<f32>,
}

impl FusePatch {
    /// `policy` with this patch's fields in place of its own.
    pub fn apply(&self, mut policy: FusePolicy) -> FusePolicy {
        if let Some(v) = self.depth_median_px {
            policy.depth_median_px = v;
        }
        if let Some(v) = self.depth_median_max_crop_m {
            policy.depth_median_max_crop_m = v;
        }
        if let Some(v) = self.max_thickness_m {
            policy.max_thickness_m = v;
        }
        if let Some(v) = self.max_thickness_per_width {
            policy.max_thickness_per_width = v;
        }
        if let Some(v) = self.min_revealed_confidence {
            policy.min_revealed_confidence = v;
        }
        if let Some(v) = self.max_expected_error_m {
            policy.max_expected_error_m = v;
        }
        if let Some(v) = self.uncertain_to_rules {
            policy.uncertain_to_rules = v;
        }
        if let Some(v) = self.stated_error_m {
            policy.stated_error_m = v;
        }
        policy
    }

    /// This patch, then `other` over it (`other`'s fields win).
    pub fn then(&self, other: &FusePatch) -> FusePatch {
        FusePatch {
            depth_median_px: other.depth_median_px.or(self.depth_median_px),
            depth_median_max_crop_m: other
                .depth_median_max_crop_m
                .or(self.depth_median_max_crop_m),
            max_thickness_m: other.max_thickness_m.or(self.max_thickness_m),
            max_thickness_per_width: other
                .max_thickness_per_width
                .or(self.max_thickness_per_width),
            min_revealed_confidence: other
                .min_revealed_confidence
                .or(self.min_revealed_confidence),
            max_expected_error_m: other.max_expected_error_m.or(self.max_expected_error_m),
            uncertain_to_rules: other.uncertain_to_rules.or(self.uncertain_to_rules),
            stated_error_m: other.stated_error_m.or(self.stated_error_m),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_patch_changes_only_its_fields() {
        let p = FusePatch {
            max_thickness_m: Some(0.05),
            ..Default::default()
        };
        let out = p.apply(FusePolicy::LEARNED);
        assert_eq!(out.max_thickness_m, 0.05);
        assert_eq!(
            FusePolicy {
                max_thickness_m: FusePolicy::LEARNED.max_thickness_m,
                ..out
            },
            FusePolicy::LEARNED
        );
        assert_eq!(
            FusePatch::default().apply(FusePolicy::RULES),
            FusePolicy::RULES
        );
    }

    #[test]
    fn the_later_patch_wins() {
        let every = FusePatch {
            max_thickness_m: Some(0.03),
            max_thickness_per_width: Some(0.35),
            ..Default::default()
        };
        let named = FusePatch {
            max_thickness_m: Some(0.2),
            ..Default::default()
        };
        let both = every.then(&named);
        assert_eq!(both.max_thickness_m, Some(0.2));
        assert_eq!(both.max_thickness_per_width, Some(0.35));
    }

    #[test]
    fn out_of_range_and_nan_are_named() {
        for bad in [
            FusePolicy {
                max_thickness_m: -0.1,
                ..FusePolicy::NONE
            },
            FusePolicy {
                min_revealed_confidence: f32::NAN,
                ..FusePolicy::NONE
            },
            FusePolicy {
                depth_median_px: 17,
                ..FusePolicy::NONE
            },
        ] {
            let e = bad.validate().unwrap_err();
            assert!(e.contains("outside"), "{e}");
        }
        for good in [FusePolicy::NONE, FusePolicy::LEARNED, FusePolicy::RULES] {
            good.validate().unwrap();
        }
    }

    #[test]
    fn an_unknown_patch_field_is_refused() {
        let e = serde_json::from_str::<FusePatch>(r#"{"max_thicknes_m": 1}"#).unwrap_err();
        assert!(e.to_string().contains("max_thicknes_m"), "{e}");
    }

    #[test]
    fn the_median_applies_within_its_crop_width() {
        assert_eq!(depth_median_radius(2, 0.5, 0.5), 2);
        assert_eq!(depth_median_radius(2, 0.5, 0.51), 0);
        assert_eq!(depth_median_radius(2, 0.0, 9.0), 2);
        assert_eq!(depth_median_radius(2, 0.5, f32::NAN), 0);
    }
}
