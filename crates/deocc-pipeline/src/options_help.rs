//! Every pipeline option with its range and one line of meaning: what `deocc options` prints
//! and `docs/options.md` holds (generated from this table by `deocc options --markdown`; a test
//! keeps the file equal to it). The table is checked against the options themselves: every
//! serialised field has exactly one row, and every stated range is the one
//! [`PipelineOptions::validate`] enforces (a value just outside is refused, the ends are taken).

use serde::Serialize;

use crate::PipelineOptions;

/// The values an option may take.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Range {
    Bool,
    /// Integers in `[min, max]`.
    Int {
        min: u64,
        max: u64,
    },
    /// Numbers in `[min, max]` (`(min, max]` when `min_open`).
    Float {
        min: f64,
        max: f64,
        min_open: bool,
    },
    /// Any non-zero finite 3-vector.
    Direction,
    /// Any finite positive number.
    Positive,
    /// Any value of its type.
    Any,
}

impl Range {
    pub fn describe(&self) -> String {
        match *self {
            Range::Bool => "true / false".into(),
            Range::Int { min, max } => format!("{min} ..= {max}"),
            Range::Float { min, max, min_open } => {
                format!("{}{min}, {max}]", if min_open { "(" } else { "[" })
            }
            Range::Direction => "non-zero [x, y, z]".into(),
            Range::Positive => "> 0".into(),
            Range::Any => "any".into(),
        }
    }
}

/// One option: its JSON name (nested ones as `parent.child`; a chain link's fusion policy as
/// `completers.NAME.field`, NAME a link's name or `*`), range and meaning.
#[derive(Debug, Clone, Serialize)]
pub struct OptionHelp {
    pub name: &'static str,
    pub range: Range,
    pub meaning: &'static str,
}

const fn f(min: f64, max: f64) -> Range {
    Range::Float {
        min,
        max,
        min_open: false,
    }
}

const fn i(min: u64, max: u64) -> Range {
    Range::Int { min, max }
}

macro_rules! row {
    ($name:literal, $range:expr, $meaning:literal) => {
        OptionHelp {
            name: $name,
            range: $range,
            meaning: $meaning,
        }
    };
}

/// The table, in the order the options appear in a run report.
pub const OPTIONS: &[OptionHelp] = &[
    row!("steps", i(1, 1000), "denoising steps of a generative completer"),
    row!("rho", f(0.0, 1.0), "weight of the other views in cross-view conditioning (0 = single view)"),
    row!("use_other_views", Range::Bool, "give completers what other frames observed of the object, reprojected into the crop"),
    row!("view_delta_deg", f(0.0, 180.0), "a further view of an instance is completed only this many degrees from every chosen one"),
    row!("max_views_per_instance", i(1, 64), "most views an instance is completed in"),
    row!("observed_voxel_m", f(1e-4, 1.0), "voxel of the observed cloud (de-duplicates the views), metres"),
    row!("fusion_voxel_m", f(1e-4, 1.0), "voxel of the fusion of generated points, metres"),
    row!("batch", i(1, 1024), "crops per completer call"),
    row!("seed", Range::Any, "seed of a generative completer's noise"),
    row!("complete_unoccluded", Range::Bool, "also complete objects nothing hides (their far side is hidden in every view)"),
    row!("occlusion_max_band_across_rows_px", i(0, 64), "the occlusion stage crosses a band without depth across the image's rows at most this far, pixels (0 = as far as along them)"),
    row!("skip_plane_pieces", Range::Bool, "leave floor and wall pieces to the plane fill instead of a completer"),
    row!("plane_piece_min_fraction", Range::Float { min: 0.0, max: 1.0, min_open: true }, "share of an instance's points in a bounding plane that makes it a plane piece"),
    row!("extend_to_support", Range::Bool, "extend hidden bottoms down to the surface below (posed scenes)"),
    row!("revolve_upright", Range::Bool, "an object whose seen side is an upright solid of revolution gets that surface"),
    row!("revolve_outline", Range::Bool, "narrow a revolved object fitted wider than its outline in the views (the masks' edges)"),
    row!("revolve_min_arc_deg", f(0.0, 360.0), "the revolve stage needs at least this arc of the side seen about the axis, degrees"),
    row!("revolve_max_residual_m", f(0.0, 0.05), "the revolve stage's side points at most this far off the fitted surface (80th percentile), metres ..."),
    row!("revolve_max_residual_fraction", f(0.0, 1.0), "... or this share of the radius, whichever is larger"),
    row!("cuboid_upright", Range::Bool, "an object whose seen faces are an upright box gets that box"),
    row!("up", Range::Direction, "gravity's opposite in the world frame"),
    row!("complete_planes", Range::Bool, "fill the hidden parts of the floor, walls and table tops"),
    row!("plane_min_rectangularity", f(0.0, 2.0), "fill a plane's enclosing rectangle when its hull fills this share of it (above 1: hulls only)"),
    row!("plane_fill_unmeasured", Range::Bool, "the plane fill also fills what no view measures: cells inside a plane's hull that a view frames, and a level plane's masked pixels without depth (drop-outs, shadows)"),
    row!("carve_generated", Range::Bool, "keep a generated point only where every view agrees it is hidden"),
    row!("carve_outside_bounding_planes_m", f(0.0, 10.0), "drop generated points this far under the floor or behind a wall (0 = off), metres"),
    row!("max_scene_radius_m", Range::Positive, "every camera within this distance of the cameras' median position, metres"),
    row!("gate_min_mean_confidence", f(0.0, 1.0), "quality gate: drop a completion whose mean confidence is below this (0 = never)"),
    row!("gate_max_seen_through_fraction", f(0.0, 1.0), "quality gate: drop a completion the views saw through more than this share of (1 = never)"),
    row!("gate_max_depth_spread_m", f(0.0, 10.0), "mirror check: leave out points whose mirrored answer's depth differs by more (0 = off), metres"),
    row!("completers.NAME.depth_median_px", i(0, 16), "median filter radius of the link's depth, crop pixels (0 = off)"),
    row!("completers.NAME.depth_median_max_crop_m", f(0.0, 10.0), "the median filter only on crops no wider than this (0 = every crop), metres"),
    row!("completers.NAME.max_thickness_m", f(0.0, 10.0), "the link's far side at most this far behind its near side (0 = off), metres"),
    row!("completers.NAME.max_thickness_per_width", f(0.0, 100.0), "... and at most this many times its silhouette's row width behind (0 = off)"),
    row!("completers.NAME.min_revealed_confidence", f(0.0, 1.0), "revealed pixels below this mask probability generate nothing"),
    row!("completers.NAME.max_expected_error_m", f(0.0, 10.0), "leave out generated points expected further off than this (error head; 0 = off), metres"),
    row!("completers.NAME.uncertain_to_rules", Range::Bool, "the rules completer fills the pixels the expected-error limit leaves out"),
    row!("completers.NAME.stated_error_m", f(0.0, 1.0), "the expected error each generated point carries when the completer gives none of its own, metres"),
    row!("skip_observed_far_side", Range::Bool, "generate no far side where another frame saw the object's back"),
    row!("fill_depth_max_gap_px", i(0, 64), "fill unmeasured depth between measured pixels at most this far apart (0 = off)"),
    row!("burst.enabled", Range::Bool, "burst fusion: frames of a posed scene taken from one pose become one frame (median depth, mean colour)"),
    row!("burst.max_translation_m", f(0.0, 0.1), "frames whose camera centres are this close are one burst ..., metres"),
    row!("burst.max_rotation_deg", f(0.0, 10.0), "... and whose orientations differ by at most this, degrees"),
    row!("burst.min_valid_fraction", f(0.0, 1.0), "a fused pixel has depth when at least this share of the burst measured it"),
    row!("depth_clean.enabled", Range::Bool, "the depth front end: outliers, flying pixels and specks removed, surfaces smoothed"),
    row!("depth_clean.agree_sigmas", f(0.5, 50.0), "a pixel is an outlier unless it continues a neighbour's surface within this many sigmas"),
    row!("depth_clean.connect_sigmas", f(0.5, 50.0), "neighbours within this many sigmas belong to one surface (speck regions)"),
    row!("depth_clean.min_region_px", i(0, 10_000), "surface regions smaller than this are specks and removed, pixels"),
    row!("depth_clean.smooth_sigmas", f(0.5, 50.0), "smoothing fits a plane to the window's pixels within this many sigmas (never across an edge)"),
    row!("depth_clean.radius", i(0, 8), "smoothing window radius, pixels"),
    row!("mask_rims.enabled", Range::Bool, "given instance masks lose the rims whose depth belongs to something else"),
    row!("mask_rims.connect_sigmas", f(0.5, 50.0), "neighbours within this many sigmas (plus 2% of depth) are one surface"),
    row!("mask_rims.min_piece_px", i(0, 10_000), "a mask's depth pieces smaller than this are rims, pixels"),
    row!("mask_rims.rim_fraction", f(0.0, 1.0), "a piece with this share of its pixels on the mask's border is a rim"),
    row!("mask_holes.enabled", Range::Bool, "a given mask's pixels without depth take the depth of its own measured pixels around them"),
    row!("mask_holes.window_px", i(1, 64), "the window the mask-hole fit is made in first, pixels each way"),
    row!("mask_holes.max_window_px", i(1, 64), "the wider window tried when the first has too few samples, pixels each way"),
    row!("mask_holes.min_samples", i(3, 10_000), "measured pixels of the instance a mask-hole fit needs"),
    row!("mask_holes.max_instance_fraction", f(0.0, 1.0), "instances covering more of the frame (a table top, a wall) keep their holes"),
];

/// The links' own policies, as the defaults of the `completers.NAME.*` rows.
fn link_defaults() -> serde_json::Value {
    serde_json::json!({
        "gldot": deocc_completion::FusePolicy::LEARNED,
        "rules": deocc_completion::FusePolicy::RULES,
    })
}

/// Every option's name, range, default (as JSON) and meaning; a link policy's row gives each
/// shipped link's own value (`{"gldot": .., "rules": ..}`).
pub fn table() -> Vec<(OptionHelp, serde_json::Value)> {
    let defaults = serde_json::to_value(PipelineOptions::default()).expect("options serialise");
    let links = link_defaults();
    OPTIONS
        .iter()
        .map(|o| {
            if let Some(field) = o.name.strip_prefix("completers.NAME.") {
                let by_link = serde_json::json!({
                    "gldot": links["gldot"][field],
                    "rules": links["rules"][field],
                });
                return (o.clone(), by_link);
            }
            let mut v = &defaults;
            for part in o.name.split('.') {
                v = &v[part];
            }
            (o.clone(), as_f32(v.clone()))
        })
        .collect()
}

/// The options hold `f32`s; serialised they widen to `f64` (0.003 shows as
/// 0.003000000026077032). Each float is shown as the shortest decimal that reads back as the
/// same `f32`.
fn as_f32(v: serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match v {
        Value::Number(n) if n.is_f64() => {
            let x = n.as_f64().unwrap_or_default() as f32;
            format!("{x}")
                .parse::<f64>()
                .ok()
                .and_then(serde_json::Number::from_f64)
                .map_or(Value::Number(n), Value::Number)
        }
        Value::Array(a) => Value::Array(a.into_iter().map(as_f32).collect()),
        Value::Object(m) => Value::Object(m.into_iter().map(|(k, v)| (k, as_f32(v))).collect()),
        other => other,
    }
}

/// The table as Markdown (docs/options.md).
pub fn markdown() -> String {
    let mut s = String::from(
        "# Pipeline options\n\n\
         Generated by `deocc options --markdown` (a test keeps this file equal to it). Set any \
         of them in a JSON file for `deocc run --options FILE` (and `deocc batch`), in \
         `options_json` over gRPC, `options=` in Python or the ROS 2 bridge's `options` \
         parameter; missing fields keep their defaults, unknown ones are refused, every value \
         is range-checked. A chain link's fusion policy is changed by its name (`gldot`, \
         `rules`, or `*` for every link): `{\"completers\": {\"gldot\": {\"max_thickness_m\": \
         0.15}}}`; the default column gives each link's own value. The long reasons and measurements are in the field documentation of \
         `crates/deocc-pipeline/src/options.rs` and in docs/decisions.md.\n\n\
         | option | default | range | meaning |\n|---|---|---|---|\n",
    );
    for (o, default) in table() {
        s += &format!(
            "| `{}` | `{}` | {} | {} |\n",
            o.name,
            default,
            o.range.describe(),
            o.meaning
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every leaf of the serialised options, nested ones as `parent.child`.
    fn leaves(v: &serde_json::Value, prefix: &str, out: &mut Vec<String>) {
        match v {
            serde_json::Value::Object(m) => {
                for (k, x) in m {
                    let name = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix}.{k}")
                    };
                    leaves(x, &name, out);
                }
            }
            _ => out.push(prefix.to_string()),
        }
    }

    #[test]
    fn defaults_show_as_the_f32_they_are() {
        let shown: std::collections::HashMap<_, _> =
            table().into_iter().map(|(o, v)| (o.name, v)).collect();
        assert_eq!(shown["revolve_max_residual_m"].to_string(), "0.003");
        assert_eq!(shown["revolve_min_arc_deg"].to_string(), "40.0");
        // Integers stay integers.
        assert!(shown["steps"].is_u64(), "{}", shown["steps"]);
    }

    #[test]
    fn every_option_has_exactly_one_row() {
        let mut names = Vec::new();
        leaves(
            &serde_json::to_value(PipelineOptions::default()).unwrap(),
            "",
            &mut names,
        );
        // The links' policies: every field of a policy, under NAME.
        let mut policy = Vec::new();
        leaves(&link_defaults()["gldot"], "completers.NAME", &mut policy);
        names.extend(policy);
        names.sort();
        let mut rows: Vec<String> = OPTIONS.iter().map(|o| o.name.to_string()).collect();
        rows.sort();
        assert_eq!(rows, names, "the table and the options differ");
    }

    /// Sets option `name` to `value` in the default options' JSON and validates.
    fn with(name: &str, value: serde_json::Value) -> Result<(), String> {
        let mut v = serde_json::to_value(PipelineOptions::default()).unwrap();
        let mut at = &mut v;
        for part in name.replace(".NAME.", ".gldot.").split('.') {
            if at.is_null() {
                *at = serde_json::json!({});
            }
            at = &mut at[part];
        }
        *at = value;
        let o: PipelineOptions = serde_json::from_value(v).map_err(|e| e.to_string())?;
        o.validate().map_err(|e| e.to_string())
    }

    #[test]
    fn every_stated_range_is_the_one_enforced() {
        for o in OPTIONS {
            let ok = |v: serde_json::Value| {
                with(o.name, v.clone())
                    .unwrap_or_else(|e| panic!("{} = {v} is in its stated range: {e}", o.name))
            };
            let refused = |v: serde_json::Value| {
                let e = with(o.name, v.clone())
                    .expect_err(&format!("{} = {v} is outside its stated range", o.name));
                let named = o.name.replace(".NAME.", ".gldot.");
                assert!(e.contains(&named), "{}: {e}", o.name);
            };
            match o.range {
                Range::Int { min, max } => {
                    ok(min.into());
                    ok(max.into());
                    refused((max + 1).into());
                    if min > 0 {
                        refused((min - 1).into());
                    }
                }
                Range::Float { min, max, min_open } => {
                    ok(max.into());
                    refused((max * 1.01 + 1e-3).into());
                    if min_open {
                        refused(min.into());
                        ok((min + (max - min) * 1e-3).into());
                    } else {
                        ok(min.into());
                        refused((min - (max - min) * 1e-2 - 1e-6).into());
                    }
                }
                Range::Direction => {
                    ok(serde_json::json!([0.0, 1.0, 0.0]));
                    refused(serde_json::json!([0.0, 0.0, 0.0]));
                }
                Range::Positive => {
                    ok(1.0.into());
                    refused(0.0.into());
                }
                Range::Bool | Range::Any => {}
            }
        }
    }
}
