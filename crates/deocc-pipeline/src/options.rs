//! What a run may be told: every field has a default, a JSON file may set any of them
//! (`deocc run --options FILE`), unknown fields are refused and every value is range-checked.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::PipelineError;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineOptions {
    /// Denoising steps of a generative completer.
    pub steps: usize,
    /// Weight of the other views in cross-view conditioning, in [0, 1] (0 = single view).
    pub rho: f32,
    /// Give every completer what the other frames observed of the object, reprojected into its
    /// crop (`crate::crops::seen_elsewhere`): the rules and GL-DoT keep those points in the
    /// mask, with their colour and depth. On by default: on the test pairs where some are
    /// kept it takes the hidden colour error from 14.8 to 6.3, the near side from 0.076 to
    /// 0.029 crop widths and adds 0.038 mIoU; in 3-D the fused clouds hardly change
    /// (docs/decisions.md).
    pub use_other_views: bool,
    /// A further view of an instance is completed only if it looks at it from at least this many
    /// degrees away from every view already chosen.
    pub view_delta_deg: f32,
    pub max_views_per_instance: usize,
    /// Voxel of the observed cloud (de-duplicates the views), metres.
    pub observed_voxel_m: f64,
    /// Voxel of the fusion of generated points, metres.
    pub fusion_voxel_m: f64,
    /// Crops per completer call.
    pub batch: usize,
    pub seed: u64,
    /// Also complete objects no other object hides: their far side is hidden in every view, and
    /// the completer's far-side depth fills it. On by default (issue 18: every object's far side
    /// is completed, occluded or not): on bench-v1 it raises the objects' hidden recall from
    /// 0.354 to 0.443 with the shipped chain, at the same share of generated points on a true
    /// surface (docs/decisions.md).
    pub complete_unoccluded: bool,
    /// Do not complete instances that lie in one of the scene's bounding planes
    /// ([`Self::plane_piece_min_fraction`] of their points within 1.5 cm of a large plane with every camera on one side and nothing observed
    /// behind it: the floor and the walls, and the pieces a segmenter cut them into): they have
    /// no far side, and the plane fill completes their plane ([`crate::planes::plane_pieces`]).
    /// A table top is completed (its underside is a surface).
    pub skip_plane_pieces: bool,
    /// The share of an instance's points that must lie in a bounding plane for it to be a plane
    /// piece, in (0, 1]. 0.8 (was 0.9): floor and wall segments that hold a little of something
    /// else are left to the fill too; chosen on bench-v1-like tuning scenes (docs/decisions.md).
    pub plane_piece_min_fraction: f32,
    /// Extend completed objects whose bottom is hidden down to the surface they stand on
    /// ([`crate::support`]; posed scenes only).
    pub extend_to_support: bool,
    /// Replace the completion of an object whose observed side is an upright solid of
    /// revolution (a can, a bottle) by that surface ([`crate::revolve`]; posed scenes only).
    pub revolve_upright: bool,
    /// Replace the completion of an object whose observed faces are an upright box seen at an
    /// angle (two side faces) by that box ([`crate::cuboid`]; posed scenes only).
    pub cuboid_upright: bool,
    /// Gravity's opposite in the scene's world frame (for the support stage).
    pub up: [f32; 3],
    /// Fill the hidden parts of large planes (floor, walls) where the views agree they are
    /// hidden ([`crate::planes`]).
    pub complete_planes: bool,
    /// The plane fill takes a plane's smallest enclosing rectangle instead of its observed
    /// part's convex hull when that hull fills at least this share of it (tables and rooms are
    /// rectangles; a table's corner hidden behind things at its edge is filled), in [0, 2]
    /// (above 1: hulls only). What the views see through is not filled either way.
    pub plane_min_rectangularity: f32,
    /// Keep a generated point only if every view agrees it is hidden ([`crate::carve`]).
    pub carve_generated: bool,
    /// Drop generated points more than this far (metres; 0 = off) behind one of the scene's
    /// bounding planes, under the floor or behind a wall ([`crate::planes::keep_inside`];
    /// [`CARVE_OUTSIDE_BOUNDING_PLANES_M`]).
    pub carve_outside_bounding_planes_m: f32,
    /// Every camera must lie within this distance of the cameras' median position (metres): one
    /// scene seen from one place. A pose far from the others is a mistake that would spread the
    /// reconstruction over kilometres.
    pub max_scene_radius_m: f32,
    /// Quality gate ([`crate::gate`]): a completion whose points' mean confidence is below this
    /// is dropped whole (0 = never).
    pub gate_min_mean_confidence: f32,
    /// Quality gate: a completion more than this share of whose points lie where a view saw
    /// through (measured something behind them) is dropped whole (1 = never).
    pub gate_max_seen_through_fraction: f32,
    /// Mirror check (metres; 0 = off): every crop is also completed mirrored left to right (in
    /// the same completer call, so a batched model pays little more), and a generated point is
    /// left out where the two answers' depths, in metres through the depth fit, differ by more
    /// than this ([`crate::complete::DepthSpread`]). A point-wise quality gate: where the answer
    /// depends on which way the crop faces, the completer does not know the depth.
    pub gate_max_depth_spread_m: f32,
    /// Median filter radius, pixels of the crop (0 = off), of a learned completer's near and
    /// far depth over its amodal mask before fusion ([`crate::fuse::median_within`]): its
    /// per-pixel depth is rough, and a rough hidden side gives a grasp planner normals that
    /// point anywhere. Completions of model provenance only (the rules' are smooth).
    pub generated_depth_median_px: usize,
    /// The median filter applies only to crops no wider than this (metres at the object's
    /// median visible depth; 0 = every crop): table-top objects, whose rough hidden side a
    /// grasp planner meets, not furniture, where it costs hidden recall (docs/decisions.md).
    pub generated_depth_median_max_crop_m: f32,
    /// Thickness cap (metres; 0 = off) of a learned completer's far side: a far-side point more
    /// than this behind its near side (observed or generated) is not generated. The model's
    /// deep far sides are mostly furniture rays that leave through a far leg or edge, and most
    /// of them miss every true surface (docs/decisions.md).
    pub generated_max_thickness_m: f32,
    /// Thickness cap of a learned completer's far side relative to the silhouette (0 = off): a
    /// far-side point more than this many times the width of its amodal row run (in metres)
    /// behind its near side is not generated ([`GENERATED_MAX_THICKNESS_PER_WIDTH`]): the
    /// model gives thin legs, posts and fragments deep backs that lie in empty space.
    pub generated_max_thickness_per_width: f32,
    /// The same cap (metres; 0 = off) on the rules completer's far side, its near side
    /// mirrored ([`RULES_MAX_THICKNESS_M`]): a mirror of a chair's or a table's near side puts
    /// most of its points in empty space.
    pub rules_max_thickness_m: f32,
    /// The silhouette-relative cap (0 = off) on the rules completer's far side
    /// ([`RULES_MAX_THICKNESS_PER_WIDTH`]): its mirrored back no deeper behind the near side than
    /// this many times the width of its amodal row run, as for a learned completer.
    pub rules_max_thickness_per_width: f32,
    /// A learned completer's revealed pixels (hidden here, no other view's observation) whose
    /// mask probability is below this generate no point, near side or far (0 = every pixel of
    /// the amodal mask): a stricter cut for 3-D points than the mask threshold
    /// ([`GENERATED_MIN_REVEALED_CONFIDENCE`]).
    pub generated_min_revealed_confidence: f32,
    /// A learned completer that estimates its own depth error (GL-DoT's error head) generates no
    /// point it expects further off than this, in metres through the depth fit (0 = off; no
    /// effect on completers without an estimate): the model's own precision per pixel, where a
    /// crop width cut treats a well-known table top like a chair's open seat
    /// ([`GENERATED_MAX_EXPECTED_ERROR_M`]).
    pub generated_max_expected_error_m: f32,
    /// With that limit set, the pixels it leaves out are completed by the rules completer
    /// instead (its near and far side there, as rules points), so that the model abstains where
    /// it expects to be off rather than leaving a hole ([`GENERATED_UNCERTAIN_TO_RULES`]; with
    /// the limit at 0 nothing is left out and it has nothing to do).
    pub generated_uncertain_to_rules: bool,
    /// No far-side point is generated where another frame observed the object's back along the
    /// pixel's ray (its surface there faces away from this view; [`crate::crops::Elsewhere`]):
    /// that part of the back is in the cloud as an observation, and a generated copy of it can
    /// only be as good or worse ([`SKIP_OBSERVED_FAR_SIDE`]).
    pub skip_observed_far_side: bool,
    /// Before anything else, fill the depth the sensor did not measure between two measured
    /// pixels of a row or column at most this many pixels apart ([`crate::depth::InterpolatedDepth`];
    /// 0 = off, the default; `deocc run --fill-depth` sets 8). Measured pixels never change.
    pub fill_depth_max_gap_px: u32,
    /// The depth front end ([`crate::depth_clean`]): outliers, flying pixels and specks
    /// removed, surfaces smoothed without crossing edges, in units of each frame's own noise.
    pub depth_clean: crate::depth_clean::DepthCleanOptions,
}

/// The quality gate's default limits (see the fields of [`PipelineOptions`]): off. On 20
/// bench-v1-like tuning scenes (`deocc eval objects --tuning`, `scripts/gate_study.py`) neither
/// signal separates accurate completions from inaccurate ones (the 3-D error is the hidden
/// side's depth, a few centimetres everywhere): the suggested limits, 0.5 and 0.5, reject 9 of
/// 200 GL-DoT completions, raise the share of its points within 2 cm of a true surface from
/// 37.0% to 37.4% and lose 2% of those, and on bench-v1 they reject 164 of the rules
/// completer's completions; tighter limits lose more than they gain. Set them in the options
/// file to drop completions the views contradict.
pub const GATE_MIN_MEAN_CONFIDENCE: f32 = 0.0;
pub const GATE_MAX_SEEN_THROUGH_FRACTION: f32 = 1.0;

/// [`PipelineOptions::skip_observed_far_side`]'s default.
pub const SKIP_OBSERVED_FAR_SIDE: bool = false;

/// The thickness cap's default ([`PipelineOptions::generated_max_thickness_m`]), chosen on 20
/// bench-v1-like tuning scenes (`deocc eval objects --tuning --scenes 20`): GL-DoT's points
/// within 2 cm of a true surface and the shipped chain's hidden recall, off 55.3% / 0.499,
/// 0.15 m 59.8% / 0.497, 0.10 m 64.6% / 0.490, 0.08 m 66.5% / 0.480, 0.05 m 67.2% / 0.439.
pub const GENERATED_MAX_THICKNESS_M: f32 = 0.10;

/// The silhouette-relative thickness cap's default
/// ([`PipelineOptions::generated_max_thickness_per_width`]), chosen on 20 bench-v1-like tuning
/// scenes (`deocc eval objects --tuning --scenes 20 --options F`): GL-DoT's points, their share
/// within 2 cm of a true surface and the shipped chain's hidden recall, off 16.4k 77.5% 0.490,
/// 1.5 15.6k 78.5% 0.488, 1.0 14.0k 79.7% 0.487, 0.75 11.9k 79.0% 0.481 (docs/decisions.md).
pub const GENERATED_MAX_THICKNESS_PER_WIDTH: f32 = 1.0;

/// The outside-the-room carve's default margin ([`PipelineOptions::carve_outside_bounding_planes_m`]),
/// measured on 20 bench-v1-like tuning scenes (`deocc eval objects --tuning --scenes 20`): GL-DoT's
/// points within 2 cm of a true surface 71.0% -> 72.5%, the rules' 65.5% -> 67.3%, the shipped
/// chain's hidden recall 0.492 either way.
pub const CARVE_OUTSIDE_BOUNDING_PLANES_M: f32 = 0.02;

/// The rules completer's silhouette-relative thickness cap
/// ([`PipelineOptions::rules_max_thickness_per_width`]).
pub const RULES_MAX_THICKNESS_PER_WIDTH: f32 = 0.0;

/// The rules completer's thickness cap ([`PipelineOptions::rules_max_thickness_m`]), chosen on
/// the same 20 tuning scenes (`--options` with `{"rules_max_thickness_m": X}`): the rules row's
/// points, their share within 2 cm of a true surface and its hidden recall, off 62.8k 41.6%
/// 0.424, 0.15 m 38.4k 63.0% 0.422, 0.10 m 34.8k 67.3% 0.417, 0.08 m 29.4k 70.6% 0.407: the
/// largest cap that keeps the baseline's recall. The shipped chain's rules points (crops over
/// 0.6 m) 35.7% -> 66.3% within 2 cm at 0.15 m, its recall 0.490 at every cap.
pub const RULES_MAX_THICKNESS_M: f32 = 0.15;

/// The confidence floor of a learned completer's revealed pixels
/// ([`PipelineOptions::generated_min_revealed_confidence`]), chosen on 20 bench-v1-like tuning
/// scenes (`deocc eval objects --tuning --scenes 20 --options F`): GL-DoT's points, their share
/// within 2 cm of the true surface and the shipped chain's hidden recall (furniture's), off 25.6k
/// 74.7% 0.492 (0.115), 0.9 17.5k 77.5% 0.489 (0.108), 0.97 13.7k 78.4% 0.488 (0.105). The
/// revealed pixels the model doubts are mostly the open space of chairs and tables (over a
/// seat, under a top between the legs); 0.9 keeps furniture's recall above the rules' (+9.2%
/// [+3.6%, +15.9%]), 0.97 does not (+5.8% [-0.4%, +13.0%]).
pub const GENERATED_MIN_REVEALED_CONFIDENCE: f32 = 0.9;

/// The error head's limit ([`PipelineOptions::generated_max_expected_error_m`]), 3 cm, with the
/// rules completing what it leaves out ([`GENERATED_UNCERTAIN_TO_RULES`]). Measured with v19
/// (v18 with the error head; docs/decisions.md): alone, at 0.03 m GL-DoT's points within 2 cm
/// of a true surface 80.4% -> 82.2% on the test split, the chain's recall over the rules
/// +12.6% -> +10.2%, furniture's from above the rules to 2.1% under. With the
/// silhouette-relative thickness cap and the rules' fallback: 82.9% -> 86.5%, +11.9% -> +10.2%,
/// furniture level with the rules: both of issue 18's goals.
pub const GENERATED_MAX_EXPECTED_ERROR_M: f32 = 0.03;

/// [`PipelineOptions::generated_uncertain_to_rules`]'s default: on.
pub const GENERATED_UNCERTAIN_TO_RULES: bool = true;

impl Default for PipelineOptions {
    fn default() -> Self {
        Self {
            steps: 4,
            rho: 0.5,
            use_other_views: true,
            view_delta_deg: 90.0,
            max_views_per_instance: 3,
            observed_voxel_m: 0.005,
            fusion_voxel_m: 0.01,
            batch: 8,
            seed: 0,
            complete_unoccluded: true,
            skip_plane_pieces: true,
            plane_piece_min_fraction: 0.8,
            extend_to_support: true,
            revolve_upright: true,
            cuboid_upright: true,
            up: [0.0, 0.0, 1.0],
            complete_planes: true,
            plane_min_rectangularity: 0.8,
            carve_generated: true,
            carve_outside_bounding_planes_m: CARVE_OUTSIDE_BOUNDING_PLANES_M,
            max_scene_radius_m: 50.0,
            gate_min_mean_confidence: GATE_MIN_MEAN_CONFIDENCE,
            gate_max_seen_through_fraction: GATE_MAX_SEEN_THROUGH_FRACTION,
            gate_max_depth_spread_m: 0.0,
            generated_depth_median_px: 0,
            generated_depth_median_max_crop_m: 0.0,
            generated_max_thickness_m: GENERATED_MAX_THICKNESS_M,
            generated_max_thickness_per_width: GENERATED_MAX_THICKNESS_PER_WIDTH,
            rules_max_thickness_m: RULES_MAX_THICKNESS_M,
            rules_max_thickness_per_width: RULES_MAX_THICKNESS_PER_WIDTH,
            generated_min_revealed_confidence: GENERATED_MIN_REVEALED_CONFIDENCE,
            generated_max_expected_error_m: GENERATED_MAX_EXPECTED_ERROR_M,
            generated_uncertain_to_rules: GENERATED_UNCERTAIN_TO_RULES,
            skip_observed_far_side: SKIP_OBSERVED_FAR_SIDE,
            fill_depth_max_gap_px: 0,
            depth_clean: crate::depth_clean::DepthCleanOptions::default(),
        }
    }
}

fn bad(field: &'static str, msg: impl Into<String>) -> PipelineError {
    PipelineError::Option {
        field,
        msg: msg.into(),
    }
}

/// The median filter's rule: `radius_px` for a crop no wider than `max_crop_m` (0 = any
/// width), else 0 (a crop of unknown width, NaN, is filtered only without a limit).
pub fn depth_median_radius(radius_px: usize, max_crop_m: f32, crop_width_m: f32) -> usize {
    if max_crop_m <= 0.0 || crop_width_m <= max_crop_m {
        radius_px
    } else {
        0
    }
}

/// The far-side caps of [`PipelineOptions::for_placing`]: every completer's far side (learned and
/// rules) no deeper than this many times its amodal row run's width, and no deeper than
/// [`PLACING_MAX_THICKNESS_M`].
pub const PLACING_MAX_THICKNESS_PER_WIDTH: f32 = 0.35;
/// See [`PLACING_MAX_THICKNESS_PER_WIDTH`].
pub const PLACING_MAX_THICKNESS_M: f32 = 0.03;

impl PipelineOptions {
    /// These options with the settings for planning placements on the completed cloud (`deocc
    /// place`): every completer's far side thin ([`PLACING_MAX_THICKNESS_PER_WIDTH`],
    /// [`PLACING_MAX_THICKNESS_M`]). A placement map needs where things stand, not how deep they
    /// are: a far side put too deep blocks a footprint's worth of free table around it, one put
    /// too shallow costs only the strip behind the object. Chosen on place-v1 tuning scenes
    /// (docs/decisions.md); for grasping, where the planner needs the back, the defaults stay.
    pub fn for_placing(self) -> Self {
        Self {
            generated_max_thickness_per_width: PLACING_MAX_THICKNESS_PER_WIDTH,
            generated_max_thickness_m: PLACING_MAX_THICKNESS_M,
            rules_max_thickness_per_width: PLACING_MAX_THICKNESS_PER_WIDTH,
            rules_max_thickness_m: PLACING_MAX_THICKNESS_M,
            ..self
        }
    }

    /// The median filter's radius for a learned completion of a crop `crop_width_m` wide
    /// (`generated_depth_median_px` within `generated_depth_median_max_crop_m`, else 0).
    pub fn generated_depth_median_for(&self, crop_width_m: f32) -> usize {
        depth_median_radius(
            self.generated_depth_median_px,
            self.generated_depth_median_max_crop_m,
            crop_width_m,
        )
    }

    /// Reads options from a JSON file: missing fields take their defaults, unknown fields and
    /// out-of-range values are errors naming the file and the field.
    pub fn from_json_file(path: &Path) -> Result<Self, PipelineError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| PipelineError::input(path, format!("cannot read: {e}")))?;
        let opts: Self = deocc_io::cameras::options_from_json(&text)
            .map_err(|e| PipelineError::input(path, format!("pipeline options: {e}")))?;
        opts.validate()
            .map_err(|e| PipelineError::input(path, e.to_string()))?;
        Ok(opts)
    }

    /// Checks every field's range.
    pub fn validate(&self) -> Result<(), PipelineError> {
        self.depth_clean.validate()?;
        if self.fill_depth_max_gap_px > 64 {
            return Err(bad(
                "fill_depth_max_gap_px",
                format!(
                    "{} is over 64 pixels: a hole that wide is a lost object, not a gap",
                    self.fill_depth_max_gap_px
                ),
            ));
        }
        if !(1..=1000).contains(&self.steps) {
            return Err(bad("steps", format!("{} is outside 1..=1000", self.steps)));
        }
        if !(0.0..=1.0).contains(&self.rho) {
            return Err(bad("rho", format!("{} is outside [0, 1]", self.rho)));
        }
        if !(0.0..=180.0).contains(&self.view_delta_deg) {
            return Err(bad(
                "view_delta_deg",
                format!("{} is outside [0, 180]", self.view_delta_deg),
            ));
        }
        if !(self.plane_piece_min_fraction > 0.0 && self.plane_piece_min_fraction <= 1.0) {
            return Err(bad(
                "plane_piece_min_fraction",
                format!("{} is outside (0, 1]", self.plane_piece_min_fraction),
            ));
        }
        if !(0.0..=2.0).contains(&self.plane_min_rectangularity) {
            return Err(bad(
                "plane_min_rectangularity",
                format!("{} is outside [0, 2]", self.plane_min_rectangularity),
            ));
        }
        if !(1..=64).contains(&self.max_views_per_instance) {
            return Err(bad(
                "max_views_per_instance",
                format!("{} is outside 1..=64", self.max_views_per_instance),
            ));
        }
        for (field, v) in [
            ("observed_voxel_m", self.observed_voxel_m),
            ("fusion_voxel_m", self.fusion_voxel_m),
        ] {
            if !(1e-4..=1.0).contains(&v) {
                return Err(bad(field, format!("{v} m is outside [0.0001, 1] m")));
            }
        }
        if !(1..=1024).contains(&self.batch) {
            return Err(bad("batch", format!("{} is outside 1..=1024", self.batch)));
        }
        if !(self.max_scene_radius_m.is_finite() && self.max_scene_radius_m > 0.0) {
            return Err(bad(
                "max_scene_radius_m",
                format!("{} must be positive and finite", self.max_scene_radius_m),
            ));
        }
        let up = nalgebra::Vector3::from(self.up);
        if !(up.norm().is_finite() && up.norm() > 1e-6) {
            return Err(bad(
                "up",
                format!("{:?} must be a non-zero finite vector", self.up),
            ));
        }
        for (field, v) in [
            ("gate_min_mean_confidence", self.gate_min_mean_confidence),
            (
                "generated_min_revealed_confidence",
                self.generated_min_revealed_confidence,
            ),
            (
                "gate_max_seen_through_fraction",
                self.gate_max_seen_through_fraction,
            ),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(bad(field, format!("{v} is outside [0, 1]")));
            }
        }
        for (field, v) in [
            ("gate_max_depth_spread_m", self.gate_max_depth_spread_m),
            ("generated_max_thickness_m", self.generated_max_thickness_m),
            ("rules_max_thickness_m", self.rules_max_thickness_m),
            (
                "generated_max_expected_error_m",
                self.generated_max_expected_error_m,
            ),
            (
                "carve_outside_bounding_planes_m",
                self.carve_outside_bounding_planes_m,
            ),
            (
                "generated_depth_median_max_crop_m",
                self.generated_depth_median_max_crop_m,
            ),
        ] {
            if !(0.0..=10.0).contains(&v) {
                return Err(bad(field, format!("{v} m is outside [0, 10] m (0 = off)")));
            }
        }
        for (field, w) in [(
            "rules_max_thickness_per_width",
            self.rules_max_thickness_per_width,
        )] {
            if !(0.0..=100.0).contains(&w) {
                return Err(bad(field, format!("{w} is outside [0, 100] (0 = off)")));
            }
        }
        let w = self.generated_max_thickness_per_width;
        if !(0.0..=100.0).contains(&w) {
            return Err(bad(
                "generated_max_thickness_per_width",
                format!("{w} is outside [0, 100] (0 = off)"),
            ));
        }
        if self.generated_depth_median_px > 16 {
            return Err(bad(
                "generated_depth_median_px",
                format!("{} is outside 0..=16", self.generated_depth_median_px),
            ));
        }
        Ok(())
    }
}
