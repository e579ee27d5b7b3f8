//! The stage list: every stage of deocc in order, the one source of the stage maps.
//! ARCHITECTURE.md's table is [`markdown_table`]'s output (a test keeps them equal and checks
//! that every file and item named here exists); the stages an [`crate::Observer`] sees are the
//! ones with a `progress` share, in this order.

/// One stage: what it does, where it lives, what to call.
#[derive(Debug, Clone, Copy)]
pub struct Stage {
    /// Short name; the name an [`crate::Observer`] is given.
    pub name: &'static str,
    /// What it does, with the options that steer it.
    pub what: &'static str,
    /// Its files, relative to `crates/`.
    pub files: &'static [&'static str],
    /// Its public functions and types (`Type::method` for methods), defined in `files`.
    pub functions: &'static [&'static str],
    /// For the stages of [`crate::run_observed`] an observer sees: the share of a run's time
    /// before the stage begins (bench-v1 means).
    pub progress: Option<f32>,
}

/// Every stage, in the order a run meets them: the front half ([`crate::front::prepare`]), the
/// run ([`crate::run_observed`]), then what the callers write.
pub const STAGES: &[Stage] = &[
    Stage {
        name: "read",
        what: "read the input (no side effects): a scene folder, a TUM RGB-D sequence, an MCAP recording (Foxglove JSON or ROS 2 CDR, topic patterns, stamp pairing, poses from `/tf` or a PoseStamped topic, frame picking) or an MRPT rawlog (`CObservation3DRangeScan` v9: depth and colour cameras with their own calibrations, a z-up world from MRPT's x-forward observation frame)",
        files: &["deocc-io/src/scene.rs", "deocc-io/src/tum.rs", "deocc-io/src/rawlog.rs", "deocc-pipeline/src/recording.rs"],
        functions: &["read_scene", "read_tum", "read_rawlog", "read_mcap", "read_input"],
        progress: None,
    },
    Stage {
        name: "camera_model",
        what: "the camera model, once at read time: lens distortion removed (plumb_bob, rational_polynomial, equidistant; same K), depth units (`depth_scale`, float32 `.npy`), a separate depth camera registered to colour with a z-buffer",
        files: &["deocc-geometry/src/distortion.rs", "deocc-geometry/src/depth.rs", "deocc-io/src/lens.rs", "deocc-io/src/cameras.rs", "deocc-io/src/npy.rs"],
        functions: &["Distortion", "register_depth", "to_pinhole"],
        progress: None,
    },
    Stage {
        name: "burst",
        what: "burst fusion: frames of a posed scene taken from one pose (a robot holding still) become one frame: per pixel the median of the frames that measured it, the mean colour",
        files: &["deocc-pipeline/src/burst.rs"],
        functions: &["fuse_bursts"],
        progress: None,
    },
    Stage {
        name: "depth_fill",
        what: "depth the sensor did not measure, filled from a depth source put at the measured scale (measured pixels never change): a learned source by the caller before the run (`deocc run --depth-model`), the interpolation as the run's first stage when `fill_depth_max_gap_px` is set",
        files: &["deocc-pipeline/src/depth.rs"],
        functions: &["fill_depth", "fill_scene_depth"],
        progress: None,
    },
    Stage {
        name: "depth_clean",
        what: "the depth front end: each frame's noise `sigma(z) = a + b z^2` estimated from the frame itself; outliers and flying pixels (continuing none of their sides' surfaces), specks, and smoothing (a least-squares plane through each window's pixels within 4 sigma, read at its centre) without crossing edges",
        files: &["deocc-pipeline/src/depth_clean.rs", "deocc-geometry/src/noise.rs"],
        functions: &["clean_depth", "DepthNoise::estimate"],
        progress: None,
    },
    Stage {
        name: "mask_rims",
        what: "masks meet depth: inside each given instance mask, depth-connected pieces (4 sigma + 2% z); a piece other than the largest that is tiny or lies mostly on the mask's border (the wall behind or the occluder in front seen through a mask edge a pixel off) loses its instance",
        files: &["deocc-pipeline/src/mask_rims.rs"],
        functions: &["unlabel_mask_rims"],
        progress: None,
    },
    Stage {
        name: "mask_holes",
        what: "a given mask's holes take its own depth: a mask pixel the sensor did not measure (a shadow, a grazing drop-out) is read off the inverse-depth plane through its instance's measured pixels around it, within their depth range",
        files: &["deocc-pipeline/src/mask_holes.rs"],
        functions: &["fill_mask_holes"],
        progress: None,
    },
    Stage {
        name: "registration",
        what: "register pose-free frames (explicit)",
        files: &["deocc-pipeline/src/registration.rs"],
        functions: &["register_unposed"],
        progress: None,
    },
    Stage {
        name: "instances",
        what: "instances: given, segmented, or mixed (distinct ids); the default segmenter's tolerances grow by 3 sigma of the frame's noise",
        files: &["deocc-pipeline/src/instances.rs", "deocc-pipeline/src/segment.rs"],
        functions: &["ensure_instances", "Segmenter"],
        progress: None,
    },
    Stage {
        name: "matching",
        what: "cross-view matching (3-D centroids, adaptive tau), inside the instances stage: one instance id across views",
        files: &["deocc-pipeline/src/matching.rs"],
        functions: &["match_masks"],
        progress: None,
    },
    Stage {
        name: "front",
        what: "the front half in one function for every caller: learned depth fill, depth front end, mask rims, mask holes, registration, instances (`prepare_observed`: the observer may stop it before each frame's depth front end)",
        files: &["deocc-pipeline/src/front.rs", "deocc-pipeline/src/lib.rs"],
        functions: &["prepare", "prepare_observed", "run_prepared"],
        progress: None,
    },
    Stage {
        name: "reconstruct",
        what: "reconstruction",
        files: &["deocc-pipeline/src/reconstruct.rs"],
        functions: &["reconstruct"],
        progress: Some(0.0),
    },
    Stage {
        name: "occlusion",
        what: "occlusion per view (the depth order judged across a band without depth between two masks: an emitter's shadow, wherever the band begins, in no mask or inside the farther one's), instances to complete",
        files: &["deocc-pipeline/src/occlusion.rs"],
        functions: &["analyse_view_with", "instances_to_complete"],
        progress: Some(0.47),
    },
    Stage {
        name: "stats",
        what: "per-(view, instance) statistics, once",
        files: &["deocc-pipeline/src/stats.rs"],
        functions: &["view_stats"],
        progress: None,
    },
    Stage {
        name: "select_views",
        what: "view selection",
        files: &["deocc-pipeline/src/views.rs"],
        functions: &["select_views"],
        progress: Some(0.5),
    },
    Stage {
        name: "complete",
        what: "crops and completion through the chain; with several frames each crop also carries what the other frames observed of its instance, reprojected into it (back-facing points dropped, z-buffered, the point nearest each pixel centre; `use_other_views`, on)",
        files: &["deocc-pipeline/src/crops.rs", "deocc-pipeline/src/complete.rs", "deocc-geometry/src/reproject.rs"],
        functions: &["make_crop", "seen_elsewhere", "reproject_views", "complete_instances"],
        progress: Some(0.53),
    },
    Stage {
        name: "fuse",
        what: "alignment and fusion (each generated point carries the completer's probability as its confidence and its expected error in metres: GL-DoT's error head through the depth fit, or the link's stated `completers.NAME.stated_error_m`; optional median filter of a learned completer's depth; a thickness cap on a learned completer's far side, in metres and relative to the width of its silhouette's row (`completers.gldot.max_thickness_per_width`), and, looser, on the rules'; a confidence floor on a learned completer's revealed pixels (`completers.gldot.min_revealed_confidence`); a gate on the completer's own expected depth error, for a model with GL-DoT's error head (`completers.gldot.max_expected_error_m`, 3 cm), the rules completing the pixels it leaves out (`completers.gldot.uncertain_to_rules`, on); no far side where another frame saw the object's back (`skip_observed_far_side`, off); optional mirror check: points whose depth the mirrored crop's completion contradicts are left out)",
        files: &["deocc-pipeline/src/fuse.rs", "deocc-pipeline/src/complete.rs"],
        functions: &["fuse_completion", "median_within", "DepthSpread"],
        progress: Some(0.69),
    },
    Stage {
        name: "gate",
        what: "quality gate (off by default): a completion dropped whole on low mean confidence or when the views saw through most of it",
        files: &["deocc-pipeline/src/gate.rs"],
        functions: &["gate_completion"],
        progress: None,
    },
    Stage {
        name: "support",
        what: "support: hidden bottoms extended down to the surface below: the highest horizontal sheet of other objects' observed or plane-fill points under the footprint (posed, z up)",
        files: &["deocc-pipeline/src/support.rs"],
        functions: &["extend_to_support", "support_height"],
        progress: None,
    },
    Stage {
        name: "revolve",
        what: "revolve: a completed object whose observed side is an upright solid of revolution (a can, a bottle) gets that surface, standing on the support below, instead of its completion, unless the views see through more than 6% of the fitted solid (a flask's broad face fits a circle far wider than the flask); with `revolve_outline` (off) a fit wider than the object's outline in the views (its masks' edges against what lies behind) is narrowed to it (posed, z up; `revolve_upright`)",
        files: &["deocc-pipeline/src/revolve.rs"],
        functions: &["revolve_instances", "fit_revolution", "outline_rays"],
        progress: None,
    },
    Stage {
        name: "cuboid",
        what: "cuboid: a completed object whose observed faces are an upright box gets that box, standing on the support below: its footprint from two side faces or one and the top, or from one face seen head-on and the completion's depth behind it (posed, z up; `cuboid_upright`)",
        files: &["deocc-pipeline/src/cuboid.rs"],
        functions: &["cuboid_instances", "fit_cuboid"],
        progress: None,
    },
    Stage {
        name: "carve",
        what: "carving against every view, and of what lies under the floor or behind a wall (`carve_outside_bounding_planes_m`)",
        files: &["deocc-pipeline/src/carve.rs", "deocc-pipeline/src/planes.rs"],
        functions: &["keep_hidden", "bounding_planes", "keep_inside"],
        progress: None,
    },
    Stage {
        name: "planes",
        what: "plane fill (up to three planes per instance: RANSAC start, PCA refits down to a robust 2 mm band; a plane's observed hull, or its smallest enclosing rectangle when the hull fills >= 80% of it, whose added corners stay on the cameras' side of the walls and floor; what the views see through is never filled; a level plane's masked pixels without depth, a sensor's drop-outs and shadows, put where their sight line meets it when the instance's measured pixels around them lie on it, and the hull's cells no view measures filled only where some view's image holds them); plane pieces (instances with 80% of their points in a bounding plane, the floor or a wall: not completed, the fill is their completion; a table top is completed) (`ScenePlanes::find` once a run)",
        files: &["deocc-pipeline/src/planes.rs"],
        functions: &["ScenePlanes::find", "plane_pieces", "complete_found_planes"],
        progress: Some(0.77),
    },
    Stage {
        name: "report",
        what: "the run report: options, timings, one record per instance and per completion",
        files: &["deocc-pipeline/src/report.rs", "deocc-pipeline/src/lib.rs"],
        functions: &["RunReport", "CompletionRecord", "make_report"],
        progress: Some(0.99),
    },
    Stage {
        name: "output",
        what: "output folder (staged, locked, swapped in)",
        files: &["deocc-pipeline/src/output.rs"],
        functions: &["Staging", "write_output"],
        progress: None,
    },
    Stage {
        name: "pictures",
        what: "pictures of each completed object (observed only beside observed + generated, from a view of the hidden side; captions and legend in a 5x7 bitmap font)",
        files: &["deocc-pipeline/src/pictures.rs"],
        functions: &["object_panel", "captioned"],
        progress: None,
    },
    Stage {
        name: "report_html",
        what: "`report.html`: one self-contained page (interactive canvas view with a z-buffer, toggles, the pictures, the figures), checked in headless Chromium by `scripts/test_browser.sh`",
        files: &["deocc-pipeline/src/report_html.rs"],
        functions: &["write_report_html"],
        progress: None,
    },
    Stage {
        name: "record",
        what: "MCAP recording of a run (`--mcap`), with the robot tasks the caller planned",
        files: &["deocc-pipeline/src/record.rs"],
        functions: &["write_mcap", "RobotAnnotations"],
        progress: None,
    },
    Stage {
        name: "run",
        what: "all of it: `run_observed` calls the stages in this order (an `Observer` sees each stage with a progress share, and each batch of the completion, and may stop the run); `run_in_memory` is `front::prepare`, then `run_prepared`: what the service, the Python package and ROS 2 call; the CLI's run, batch, grasp and place call the same two",
        files: &["deocc-pipeline/src/lib.rs"],
        functions: &["run", "run_observed", "run_in_memory", "Observer"],
        progress: None,
    },
];

/// The stages an observer sees, in order, with their progress shares.
pub fn observed() -> impl Iterator<Item = (&'static str, f32)> {
    STAGES
        .iter()
        .filter_map(|s| s.progress.map(|p| (s.name, p)))
}

/// The progress share before stage `name` (0 for a stage without one).
pub fn progress(name: &str) -> f32 {
    STAGES
        .iter()
        .find(|s| s.name == name)
        .and_then(|s| s.progress)
        .unwrap_or(0.0)
}

/// ARCHITECTURE.md's stage table.
pub fn markdown_table() -> String {
    let mut t = String::from("| stage | file | function |\n|---|---|---|\n");
    for s in STAGES {
        let quote = |items: &[&str]| {
            items
                .iter()
                .map(|i| format!("`{i}`"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        t.push_str(&format!(
            "| **{}**: {} | {} | {} |\n",
            s.name,
            s.what,
            quote(s.files),
            quote(s.functions)
        ));
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn crates() -> &'static Path {
        Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
    }

    /// ARCHITECTURE.md's table is this list (regenerate it with
    /// `DEOCC_BLESS=1 cargo test -p deocc-pipeline stages`).
    #[test]
    fn architecture_map_is_the_stage_list() {
        let path = crates().join("../ARCHITECTURE.md");
        let text = std::fs::read_to_string(&path).unwrap();
        let (begin, end) = ("<!-- stages:begin -->\n", "<!-- stages:end -->");
        let i = text
            .find(begin)
            .expect("ARCHITECTURE.md: no stages:begin marker")
            + begin.len();
        let j = text
            .find(end)
            .expect("ARCHITECTURE.md: no stages:end marker");
        let table = markdown_table();
        if text[i..j] != table && std::env::var_os("DEOCC_BLESS").is_some() {
            std::fs::write(&path, format!("{}{table}{}", &text[..i], &text[j..])).unwrap();
            return;
        }
        assert_eq!(
            text[i..j],
            table,
            "ARCHITECTURE.md's stage table differs from deocc_pipeline::stages::STAGES; \
             DEOCC_BLESS=1 rewrites it"
        );
    }

    /// Every file a stage names exists and defines every item it names.
    #[test]
    fn every_named_file_and_item_exists() {
        for s in STAGES {
            let mut code = String::new();
            for f in s.files {
                let path = crates().join(f);
                code += &std::fs::read_to_string(&path)
                    .unwrap_or_else(|e| panic!("stage {}: {}: {e}", s.name, path.display()));
            }
            for item in s.functions {
                let name = item.rsplit("::").next().unwrap();
                let defined = ["fn", "struct", "trait", "enum", "type", "const"]
                    .iter()
                    .any(|kw| {
                        code.match_indices(&format!("{kw} {name}")).any(|(k, m)| {
                            code[k + m.len()..]
                                .chars()
                                .next()
                                .is_some_and(|c| !c.is_alphanumeric() && c != '_')
                        })
                    });
                assert!(
                    defined,
                    "stage {}: `{item}` is not defined in {:?}",
                    s.name, s.files
                );
            }
        }
        let mut names: Vec<_> = STAGES.iter().map(|s| s.name).collect();
        names.sort();
        names.dedup();
        assert_eq!(names.len(), STAGES.len(), "stage names are unique");
    }

    /// The run enters the observed stages in the list's order, and no other.
    #[test]
    fn the_run_enters_the_observed_stages_in_order() {
        let lib = std::fs::read_to_string(crates().join("deocc-pipeline/src/lib.rs")).unwrap();
        let entered: Vec<&str> = lib
            .split("enter(observer, \"")
            .skip(1)
            .map(|rest| rest.split('"').next().unwrap())
            .collect();
        let listed: Vec<&str> = observed().map(|s| s.0).collect();
        assert_eq!(entered, listed);
        assert!(observed()
            .collect::<Vec<_>>()
            .windows(2)
            .all(|w| w[0].1 < w[1].1));
    }

    /// Function lengths, from a line starting `fn`/`pub fn` to its closing brace at the same
    /// indent: (lines, file, name).
    fn function_lengths(file: &str, text: &str) -> Vec<(usize, String, String)> {
        let lines: Vec<&str> = text.lines().collect();
        let mut out = Vec::new();
        let mut i = 0;
        while i < lines.len() {
            let l = lines[i];
            let indent = l.len() - l.trim_start().len();
            let t = l.trim_start();
            let head = t
                .strip_prefix("pub(crate) fn ")
                .or_else(|| t.strip_prefix("pub fn "))
                .or_else(|| t.strip_prefix("fn "));
            if let Some(rest) = head.filter(|_| !l.trim_end().ends_with(';')) {
                let name: String = rest
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                let close = format!("{}}}", " ".repeat(indent));
                let end = (i + 1..lines.len())
                    .find(|&j| lines[j].starts_with(&close) && lines[j].trim() == "}");
                if let Some(end) = end {
                    out.push((end - i + 1, file.to_string(), name));
                    i = end;
                }
            }
            i += 1;
        }
        out
    }

    /// Issue 45's limits: the run is a short list of stage calls (under 80 lines) and no function
    /// of the pipeline is over 150 lines.
    #[test]
    fn the_run_and_every_pipeline_function_stay_short() {
        let dir = crates().join("deocc-pipeline/src");
        let mut all = Vec::new();
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "rs") {
                let text = std::fs::read_to_string(&path).unwrap();
                let name = path.file_name().unwrap().to_string_lossy().to_string();
                all.extend(function_lengths(&name, &text));
            }
        }
        let run = all
            .iter()
            .find(|f| f.2 == "run_observed")
            .expect("run_observed");
        assert!(run.0 < 80, "run_observed is {} lines", run.0);
        let long: Vec<_> = all.iter().filter(|f| f.0 > 150).collect();
        assert!(long.is_empty(), "over 150 lines: {long:?}");
        assert!(all.len() > 100, "only {} functions found", all.len());
    }
}
