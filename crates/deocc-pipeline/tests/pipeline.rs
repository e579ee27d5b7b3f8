use deocc_completion::rules::RulesCompleter;
use deocc_completion::{
    Completer, CompleterChain, CompletionError, CompletionOptions, CropCompletion, CropCondition,
    CropRequest, ExpectedDepthError, Provenance,
};
use deocc_pipeline::{read_scene, PipelineOptions};
use deocc_synth::dataset::{render_full_scene, write_scene};
use deocc_synth::scene::SceneConfig;
use nalgebra::Point3;

fn config() -> SceneConfig {
    SceneConfig {
        width: 320,
        height: 240,
        views: 4,
        gt_points_per_m2: 1000.0,
        ..SceneConfig::default()
    }
}

#[test]
fn scene_folder_errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let e = read_scene(dir.path()).err().unwrap().to_string();
    assert!(e.contains("cameras.json"), "{e}");
    let r = render_full_scene(&config(), 5).unwrap();
    write_scene(dir.path(), &config(), &r).unwrap();
    assert_eq!(read_scene(dir.path()).unwrap().frames.len(), 4);
    // A depth frame of the wrong size.
    let depth = dir.path().join("depth/000002.png");
    deocc_io::images::write_depth_png(&depth, &deocc_geometry::DepthMap::zeros(10, 10)).unwrap();
    let e = read_scene(dir.path()).err().unwrap().to_string();
    assert!(e.contains("000002.png"), "{e}");
    // A missing RGB frame.
    std::fs::remove_file(dir.path().join("rgb/000001.png")).unwrap();
    let e = read_scene(dir.path()).err().unwrap().to_string();
    assert!(e.contains("000001.png"), "{e}");
}

/// Frame names are plain file names, each once: no frame reads another's images or a file
/// outside the scene folder.
#[test]
fn frame_names_with_paths_or_duplicates_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let r = render_full_scene(&config(), 5).unwrap();
    write_scene(dir.path(), &config(), &r).unwrap();
    let path = dir.path().join("cameras.json");
    let original = std::fs::read_to_string(&path).unwrap();
    for (bad, expect) in [
        ("../../../x", "not a plain file name"),
        ("/abs/path", "not a plain file name"),
        ("000000", "appears twice"),
    ] {
        let mut json: serde_json::Value = serde_json::from_str(&original).unwrap();
        json["frames"][1]["name"] = serde_json::Value::String(bad.into());
        std::fs::write(&path, serde_json::to_string(&json).unwrap()).unwrap();
        let e = read_scene(dir.path()).err().unwrap().to_string();
        assert!(
            e.contains("cameras.json") && e.contains(expect),
            "{bad}: {e}"
        );
    }
}

/// Pose-free input: frame-to-frame point-to-plane ICP recovers the camera motion of bench-v1's
/// robot-head sweep (10 views, 10 degrees and ~25 cm between frames) to within half a degree and
/// a centimetre per frame (measured: under 0.01 degree and 0.5 mm), and the recovered world has
/// gravity along -z.
#[test]
fn frame_to_frame_icp_recovers_the_camera_path() {
    use deocc_pipeline::registration::register_unposed;
    let cfg = SceneConfig {
        views: 10,
        ..config()
    };
    let rendered = render_full_scene(&cfg, 11).unwrap();
    let mut scene = rendered.scene_input();
    let truth: Vec<_> = scene
        .frames
        .iter()
        .map(|f| f.camera.world_from_camera)
        .collect();
    for f in &mut scene.frames {
        f.camera.world_from_camera = nalgebra::Isometry3::identity();
    }
    assert!(
        register_unposed(&mut scene).unwrap().is_empty(),
        "posed input is left alone"
    );
    scene.posed = false;
    let reports = register_unposed(&mut scene).unwrap();
    assert!(scene.posed);
    assert_eq!(reports.len(), 10);
    for k in 1..10 {
        let est = scene.frames[k - 1].camera.world_from_camera.inverse()
            * scene.frames[k].camera.world_from_camera;
        let gt = truth[k - 1].inverse() * truth[k];
        let err = gt.inverse() * est;
        let angle = err.rotation.angle().to_degrees();
        let shift = err.translation.vector.norm();
        assert!(
            angle < 0.5 && shift < 0.01,
            "frame {k}: {angle:.2} deg, {shift:.3} m off (fitness {:.2})",
            reports[k].fitness
        );
        assert!(reports[k].fitness > 0.5, "{:?}", reports[k]);
    }
    // Gravity: the world z of frame 0 agrees with the true up within a few degrees.
    let up_true_cam0 = truth[0].inverse_transform_vector(&nalgebra::Vector3::z());
    let up_est_cam0 = scene.frames[0]
        .camera
        .world_from_camera
        .inverse_transform_vector(&nalgebra::Vector3::z());
    let tilt = up_true_cam0.angle(&up_est_cam0).to_degrees();
    assert!(tilt < 5.0, "gravity estimated {tilt:.1} deg off");
}

/// A `cameras.json` where only some frames have poses is refused with the file named.
#[test]
fn partly_posed_input_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let r = render_full_scene(&config(), 5).unwrap();
    write_scene(dir.path(), &config(), &r).unwrap();
    let path = dir.path().join("cameras.json");
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let frames = json
        .get_mut("frames")
        .and_then(|f| f.as_array_mut())
        .expect("cameras.json has a frames array");
    frames[1]
        .as_object_mut()
        .unwrap()
        .remove("world_from_camera");
    std::fs::write(&path, serde_json::to_string(&json).unwrap()).unwrap();
    let e = read_scene(dir.path()).err().unwrap().to_string();
    assert!(e.contains("cameras.json") && e.contains("3 of 4"), "{e}");
}

/// The plane fill puts points where the ground truth has hidden surface: nearly all of them
/// within 2 cm of a ground-truth point no view sees, and none where a view sees free space.
#[test]
fn plane_fill_lands_on_hidden_ground_truth() {
    use deocc_pipeline::planes::{complete_planes, PlaneOptions};
    let cfg = SceneConfig {
        gt_points_per_m2: 10_000.0,
        ..config()
    };
    let rendered = render_full_scene(&cfg, 5).unwrap();
    let scene = rendered.scene_input();
    let fill = complete_planes(&scene, &PlaneOptions::default());
    assert!(fill.len() > 500, "only {} points filled", fill.len());
    assert!(fill
        .generated
        .as_deref()
        .unwrap()
        .iter()
        .all(|&g| g == Provenance::PlaneFill.code()));
    let gt = &rendered.ground_truth;
    let hidden: Vec<_> = gt
        .cloud
        .positions
        .iter()
        .zip(&gt.seen)
        .filter(|(_, &s)| !s)
        .map(|(p, _)| *p)
        .collect();
    let share_near = |points: &[nalgebra::Point3<f32>]| {
        let index = deocc_geometry::KdIndex::build(points).unwrap();
        let near = fill
            .positions
            .iter()
            .filter(|p| index.nearest(p).distance_sq < 0.015 * 0.015)
            .count();
        near as f64 / fill.len() as f64
    };
    let on_surface = share_near(&gt.cloud.positions);
    assert!(
        on_surface > 0.95,
        "{on_surface:.3} of the filled points lie on a surface"
    );
    let on_hidden = share_near(&hidden);
    assert!(
        on_hidden > 0.8,
        "{on_hidden:.3} of the filled points lie on hidden surface"
    );
}

/// Several views' observations of a floor span, together, ground that none of them frames (the
/// floor between two views' footprints). The plane fill's cells no view measures are a sensor's
/// drop-outs only inside some view's image: every filled point lies in a view's frame. (Filling
/// the rest cost the completed cloud 10% of its accuracy on bench-v1.)
#[test]
fn the_plane_fill_stays_inside_the_views_frames() {
    use deocc_pipeline::planes::{complete_planes, PlaneOptions};
    for seed in [5, 6, 7] {
        let rendered = render_full_scene(&config(), seed).unwrap();
        let scene = rendered.scene_input();
        let fill = complete_planes(&scene, &PlaneOptions::default());
        assert!(
            fill.len() > 500,
            "seed {seed}: {} points filled",
            fill.len()
        );
        // The benchmarks' own frustum test (its cameras' images, in front of them).
        let cams: Vec<_> = scene.frames.iter().map(|f| f.camera).collect();
        let framed =
            deocc_pipeline::ground_truth::in_frustum(&fill, &vec![false; fill.len()], &cams);
        let outside = fill.len() - framed.cloud.len();
        assert_eq!(
            outside,
            0,
            "seed {seed}: {outside} of {} filled points in no view's frame",
            fill.len()
        );
    }
}

/// Under a structured-light sensor a table or floor seen at a grazing angle loses much of its
/// depth; its instance mask still covers those pixels. The plane fill puts them where their sight
/// line meets the plane: more points than without them, and they lie on true surfaces.
#[test]
fn the_plane_fill_puts_masked_pixels_without_depth_on_their_plane() {
    use deocc_pipeline::planes::{complete_planes, PlaneOptions};
    let cfg = SceneConfig {
        gt_points_per_m2: 10_000.0,
        views: 1,
        sensor: deocc_synth::sensor::SensorKind::StructuredLight,
        ..config()
    };
    let rendered = render_full_scene(&cfg, 5).unwrap();
    let scene = rendered.scene_input();
    let depthless = scene.frames[0]
        .depth
        .data()
        .iter()
        .zip(&scene.frames[0].instances.as_ref().unwrap().ids)
        .filter(|(&d, &id)| d <= 0.0 && id != 0)
        .count();
    assert!(
        depthless > 1000,
        "only {depthless} masked pixels without depth"
    );
    let with = complete_planes(&scene, &PlaneOptions::default());
    let without = complete_planes(
        &scene,
        &PlaneOptions {
            mask_window_px: 0,
            fill_unmeasured: false,
            ..PlaneOptions::default()
        },
    );
    assert!(
        with.len() > without.len() + 300,
        "{} points with the masked pixels, {} without",
        with.len(),
        without.len()
    );
    let index = deocc_geometry::KdIndex::build(&rendered.ground_truth.cloud.positions).unwrap();
    let on_surface = |c: &deocc_geometry::PointCloud| {
        c.positions
            .iter()
            .filter(|p| index.nearest(p).distance_sq < 0.015 * 0.015)
            .count() as f64
            / c.len() as f64
    };
    let (a, b) = (on_surface(&with), on_surface(&without));
    assert!(
        a > 0.95,
        "{a:.3} of the filled points lie on a surface ({b:.3} without the masked pixels)"
    );
}

/// A completer with no weights: every crop candidate pixel joins the object at the object's median
/// visible depth, in one colour, with probability [`STUB_PROBABILITY`]; it declines crops wider
/// than `max_width_m`. Its far side lies 0.3 crop widths behind the near side, plus `lopsided`
/// times the pixel's column over the crop's width: a completer whose answer depends on which way
/// the crop faces.
struct Stub {
    max_width_m: f32,
    lopsided: f32,
    /// The depth error it expects everywhere (relative), as GL-DoT's error head would say;
    /// `None`: no estimate.
    expected_error: Option<f32>,
}

const STUB_COLOUR: [u8; 3] = [1, 2, 3];
/// Above the default floor of revealed pixels (`generated_min_revealed_confidence`, 0.9), so the
/// stub's revealed pixels are fused.
const STUB_PROBABILITY: f32 = 0.95;

impl Completer for Stub {
    fn name(&self) -> &str {
        "stub"
    }
    fn provenance(&self) -> Provenance {
        Provenance::Model
    }
    fn resolution(&self) -> usize {
        32
    }
    fn decline(&self, c: &CropCondition) -> Option<String> {
        let w = c.crop_width_m?;
        (w > self.max_width_m).then(|| format!("{w:.2} m wide"))
    }
    fn complete(
        &self,
        batch: &[CropRequest<'_>],
        _: &CompletionOptions,
    ) -> Result<Vec<CropCompletion>, CompletionError> {
        Ok(batch
            .iter()
            .map(|req| {
                let c = req.condition;
                let n = c.pixels();
                let amodal: Vec<bool> = (0..n).map(|p| c.visible[p] || c.prior[p]).collect();
                CropCompletion {
                    mask_probability: (0..n)
                        .map(|p| match (c.visible[p], amodal[p]) {
                            (true, _) => 1.0,
                            (false, true) => STUB_PROBABILITY,
                            (false, false) => 0.0,
                        })
                        .collect(),
                    rgb: (0..n).flat_map(|_| STUB_COLOUR).collect(),
                    depth: c.visible_depth.clone(),
                    back_depth: c
                        .visible_depth
                        .iter()
                        .enumerate()
                        .map(|(p, d)| {
                            let column = (p % c.resolution) as f32 / c.resolution as f32;
                            d + 0.3 + self.lopsided * column
                        })
                        .collect(),
                    amodal,
                    expected_error: self.expected_error.map(|e| ExpectedDepthError {
                        near: vec![e; n],
                        far: vec![e; n],
                    }),
                }
            })
            .collect())
    }
}

fn small_scene() -> deocc_synth::dataset::RenderedScene {
    let cfg = SceneConfig {
        views: 4,
        gt_points_per_m2: 10.0,
        ..SceneConfig::default()
    };
    render_full_scene(&cfg, 3).unwrap()
}

/// `pipeline::run` with a completer that needs no weights: every generated object point carries
/// the completer's provenance, colour and the instance of its crop, and the report says so.
#[test]
fn run_completes_with_a_stub_completer() {
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let chain = CompleterChain::single(Stub {
        max_width_m: 100.0,
        lopsided: 0.0,
        expected_error: None,
    });
    let opts = PipelineOptions {
        complete_planes: false,
        revolve_upright: false,
        cuboid_upright: false,
        gate_min_mean_confidence: 0.5,
        gate_max_seen_through_fraction: 0.5,
        ..Default::default()
    };
    let out = deocc_pipeline::run(&scene, &chain, &opts, &Vec::new()).unwrap();
    let r = &out.report;
    assert_eq!(r.completers, "stub");
    assert!(!r.instances.is_empty());
    assert!(r.points_model > 0, "{r:?}");
    assert_eq!(r.points_model, r.points_generated);
    assert_eq!(r.points_rules + r.points_plane_fill, 0);
    let gen = out.completed.generated.as_deref().unwrap();
    let ids = out.completed.instance.as_deref().unwrap();
    let colours = out.completed.colors.as_deref().unwrap();
    let completed_ids: Vec<u32> = r.instances.iter().map(|i| i.instance_id as u32).collect();
    for i in (0..out.completed.len()).filter(|&i| gen[i] != 0) {
        assert_eq!(gen[i], Provenance::Model.code());
        assert!(
            completed_ids.contains(&ids[i]),
            "point of instance {}",
            ids[i]
        );
        // Near side in the stub's colour, far side shaded at 0.75 of it.
        let c = colours[i];
        assert!(c == STUB_COLOUR || c == [0, 1, 2], "colour {c:?}");
    }
    assert!(r.completions.iter().all(|c| c.completer == "stub"));
    // The observed part is the reconstruction, untouched.
    assert_eq!(gen.iter().filter(|&&g| g == 0).count(), out.observed.len());
    // Every point carries a confidence: 1 observed; generated, the completer's probability of
    // its pixel (1 for the back of a visible pixel, the stub's probability for a hidden one).
    let conf = out.completed.confidence.as_deref().unwrap();
    for (i, &c) in conf.iter().enumerate() {
        let ok = if gen[i] == 0 {
            c == 1.0
        } else {
            (STUB_PROBABILITY..=1.0).contains(&c)
        };
        assert!(ok, "point {i}: {c} (provenance {})", gen[i]);
    }
    assert!(conf
        .iter()
        .zip(gen)
        .any(|(&c, &g)| g != 0 && (c - STUB_PROBABILITY).abs() < 1e-5));
    // The gate (limits 0.5, 0.5) measured every fused completion; what it rejected it says, and
    // adds nothing of.
    assert_eq!(
        r.completions_gated,
        r.completions.iter().filter(|c| c.gated).count()
    );
    for c in r.completions.iter().filter(|c| c.mean_confidence.is_some()) {
        assert!((STUB_PROBABILITY..=1.0).contains(&c.mean_confidence.unwrap()));
        let x = c.seen_through_fraction.unwrap();
        assert!((0.0..=1.0).contains(&x));
        assert_eq!(c.gated, x > 0.5, "{c:?}");
        assert_eq!(c.accepted, !c.gated);
    }
}

/// The quality gate drops whole completions: every one with a hidden pixel when the confidence
/// limit is 1, and a "completion" made of points in the free space in front of
/// what the views see; points the views observe agree with a completion.
#[test]
fn the_quality_gate_rejects_doubtful_and_contradicted_completions() {
    use deocc_pipeline::gate::gate_completion;
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let chain = CompleterChain::single(Stub {
        max_width_m: 100.0,
        lopsided: 0.0,
        expected_error: None,
    });
    let strict = PipelineOptions {
        complete_planes: false,
        extend_to_support: false,
        gate_min_mean_confidence: 1.0,
        gate_max_seen_through_fraction: 1.0,
        ..Default::default()
    };
    let out = deocc_pipeline::run(&scene, &chain, &strict, &Vec::new()).unwrap();
    let r = &out.report;
    let doubtful: Vec<_> = r
        .completions
        .iter()
        .filter(|c| c.mean_confidence.is_some_and(|m| m < 1.0))
        .collect();
    assert!(!doubtful.is_empty(), "{r:?}");
    assert!(doubtful.iter().all(|c| c.gated
        && !c.accepted
        && c.new_points == 0
        && c.reason.starts_with("quality gate: mean confidence")));
    assert_eq!(
        r.completions_gated,
        r.completions.iter().filter(|c| c.gated).count()
    );
    // Observed surface points agree with the views; the same points pulled 30 cm towards the
    // first camera float in space it saw through.
    let projectors: Vec<_> = scene.frames.iter().map(|f| f.camera.projector()).collect();
    let seen = out.observed.filter(|i| i % 50 == 0);
    let v = gate_completion(&seen, &scene, &projectors, 0.0, 0.5);
    assert!(v.seen_through_fraction < 0.1, "{v:?}");
    assert!(v.rejected.is_none());
    assert_eq!(v.mean_confidence, 1.0);
    let eye = scene.frames[0].camera.world_from_camera.translation.vector;
    let mut floating = seen.clone();
    for p in &mut floating.positions {
        let towards = (eye - p.coords).normalize();
        *p += towards * 0.3;
    }
    let v = gate_completion(&floating, &scene, &projectors, 0.0, 0.5);
    assert!(v.seen_through_fraction > 0.6, "{v:?}");
    assert!(v.rejected.unwrap().contains("seen through"));
    // What the pipeline generated and kept is hidden in every view (the default gate is off).
    assert_eq!(
        PipelineOptions::default().gate_max_seen_through_fraction,
        1.0
    );
    let default = PipelineOptions {
        complete_planes: false,
        extend_to_support: false,
        ..Default::default()
    };
    let out = deocc_pipeline::run(&scene, &chain, &default, &Vec::new()).unwrap();
    let gen = out.completed.generated.as_deref().unwrap();
    let kept = out.completed.filter(|i| gen[i] != 0);
    assert!(!kept.is_empty());
    let v = gate_completion(&kept, &scene, &projectors, 0.0, 0.5);
    assert!(v.seen_through_fraction < 0.05, "{v:?}");
    assert!(v.rejected.is_none());
}

/// The default options with only the completer's own points: no plane fill, support extension,
/// revolve or cuboid stage.
/// `pipeline::run` with the stub that declines nothing and answers the same either way a crop
/// faces.
fn run_plain_stub(
    scene: &deocc_io::scene::SceneInput,
    opts: &PipelineOptions,
) -> deocc_pipeline::PipelineOutput {
    let chain = CompleterChain::single(Stub {
        max_width_m: 100.0,
        lopsided: 0.0,
        expected_error: None,
    });
    deocc_pipeline::run(scene, &chain, opts, &Vec::new()).unwrap()
}

/// `opts` with link `name`'s fusion policy patched.
fn patched(
    mut opts: PipelineOptions,
    name: &str,
    patch: deocc_completion::FusePatch,
) -> PipelineOptions {
    opts.completers.insert(name.into(), patch);
    opts
}

fn completion_only() -> PipelineOptions {
    PipelineOptions {
        complete_planes: false,
        extend_to_support: false,
        revolve_upright: false,
        cuboid_upright: false,
        ..Default::default()
    }
}

/// The mirror check leaves out the points whose depth the completion of the mirrored crop
/// contradicts, and nothing of a completer whose answer does not depend on the crop's facing.
#[test]
fn the_mirror_check_drops_points_the_mirrored_crop_contradicts() {
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let base = completion_only();
    let checked = PipelineOptions {
        gate_max_depth_spread_m: 0.02,
        ..base.clone()
    };
    let run = |lopsided: f32, opts: &PipelineOptions| {
        let chain = CompleterChain::single(Stub {
            max_width_m: 100.0,
            lopsided,
            expected_error: None,
        });
        deocc_pipeline::run(&scene, &chain, opts, &Vec::new()).unwrap()
    };
    // A mirror-symmetric answer: the same cloud with the check on or off.
    let (off, on) = (run(0.0, &base), run(0.0, &checked));
    assert!(off.report.points_model > 0);
    assert_eq!(on.report.points_spread_dropped, 0);
    assert_eq!(on.completed.positions, off.completed.positions);
    // A lopsided one: points where the two answers differ by more than 2 cm are left out, and
    // the records add up to the report's count.
    let (off, on) = (run(0.5, &base), run(0.5, &checked));
    let r = &on.report;
    assert_eq!(off.report.points_spread_dropped, 0);
    assert!(r.points_spread_dropped > 0, "{r:?}");
    assert_eq!(
        r.points_spread_dropped,
        r.completions
            .iter()
            .map(|c| c.spread_dropped)
            .sum::<usize>()
    );
    assert!(
        r.points_model < off.report.points_model,
        "{} of {}",
        r.points_model,
        off.report.points_model
    );
    // A limit no spread reaches keeps everything.
    let loose = PipelineOptions {
        gate_max_depth_spread_m: 10.0,
        ..base.clone()
    };
    let all = run(0.5, &loose);
    assert_eq!(all.report.points_spread_dropped, 0);
    assert_eq!(all.completed.positions, off.completed.positions);
}

/// The thickness cap leaves out a learned completer's far side deeper than the cap behind its
/// near side, and nothing else; a cap no far side reaches changes nothing. The stub's far side
/// lies 0.3 crop widths behind its near side and is shaded (its colour times 0.75), which tells
/// the two sides apart in the cloud.
#[test]
fn the_thickness_cap_drops_deep_far_sides_only() {
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let base = completion_only();
    let run = |cap: f32| {
        let opts = patched(
            base.clone(),
            "stub",
            deocc_completion::FusePatch {
                max_thickness_m: Some(cap),
                ..Default::default()
            },
        );
        run_plain_stub(&scene, &opts)
    };
    let far_colour = STUB_COLOUR.map(|c| (c as f32 * 0.75) as u8);
    let count = |out: &deocc_pipeline::PipelineOutput, colour: [u8; 3]| {
        let c = &out.completed;
        (0..c.len())
            .filter(|&i| {
                c.generated.as_ref().unwrap()[i] == Provenance::Model.code()
                    && c.colors.as_ref().unwrap()[i] == colour
            })
            .count()
    };
    let (off, capped) = (run(0.0), run(0.01));
    assert!(count(&off, far_colour) > 0, "no far side to cap");
    assert_eq!(count(&capped, far_colour), 0, "a deep far side survived");
    assert_eq!(count(&capped, STUB_COLOUR), count(&off, STUB_COLOUR));
    assert_eq!(run(10.0).completed.positions, off.completed.positions);
}

/// The median filter of a learned completer's depth changes its points, and its crop-width
/// limit confines it: under a limit no crop is narrow enough for, the points are those of no
/// filter; under a limit every crop is within, those of the filter everywhere.
#[test]
fn the_depth_median_applies_to_crops_within_its_width_limit_only() {
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let base = completion_only();
    let run = |radius: usize, limit_m: f32| {
        let opts = patched(
            base.clone(),
            "*",
            deocc_completion::FusePatch {
                depth_median_px: Some(radius),
                depth_median_max_crop_m: Some(limit_m),
                ..Default::default()
            },
        );
        run_plain_stub(&scene, &opts).completed.positions
    };
    let (plain, filtered) = (run(0, 0.0), run(2, 0.0));
    assert_ne!(plain, filtered, "the median changed nothing to test with");
    assert_eq!(run(2, 0.001), plain);
    assert_eq!(run(2, 10.0), filtered);
    let policy = deocc_completion::FusePolicy {
        depth_median_px: 2,
        depth_median_max_crop_m: 0.5,
        ..deocc_completion::FusePolicy::LEARNED
    };
    assert_eq!(
        (policy.depth_median_for(0.5), policy.depth_median_for(0.51)),
        (2, 0)
    );
}

/// The centre of a rendered scene's target, which must be a can, and its radius (its mesh's
/// box).
fn target_can(rendered: &deocc_synth::dataset::RenderedScene) -> (Point3<f32>, f32) {
    let target = rendered.scene.target.unwrap();
    let truth = rendered
        .scene
        .objects
        .iter()
        .find(|o| o.instance_id == target)
        .unwrap();
    assert_eq!(truth.category.name(), "can");
    let (lo, hi) = truth.mesh.vertices.iter().fold(
        (Point3::from([f32::MAX; 3]), Point3::from([f32::MIN; 3])),
        |(lo, hi), p| (lo.inf(p), hi.sup(p)),
    );
    (
        Point3::from((lo.coords + hi.coords) / 2.0),
        (hi.x - lo.x + hi.y - lo.y) / 4.0,
    )
}

/// pickup-v1's first scene: a can behind a box. Its completion is replaced by a surface of
/// revolution on the can's true axis and radius, which the rules completer alone misses by
/// centimetres, and the box keeps its completion.
#[test]
fn an_occluded_can_is_completed_on_its_axis() {
    let preset = deocc_synth::dataset::pickup_v1();
    let rendered = render_full_scene(&preset.config, preset.seeds[0]).unwrap();
    let target = rendered.scene.target.unwrap();
    let (axis, radius) = target_can(&rendered);
    let scene = rendered.scene_input();
    let chain = CompleterChain::single(RulesCompleter::default());
    let opts = PipelineOptions {
        complete_unoccluded: true,
        ..Default::default()
    };
    let spread = |revolve: bool| {
        let out = deocc_pipeline::run(
            &scene,
            &chain,
            &PipelineOptions {
                revolve_upright: revolve,
                ..opts.clone()
            },
            &Vec::new(),
        )
        .unwrap();
        let gen = out.completed.generated.as_deref().unwrap();
        let ids = out.completed.instance.as_deref().unwrap();
        let errors: Vec<f32> = (0..out.completed.len())
            .filter(|&i| gen[i] != 0 && ids[i] == target as u32)
            .map(|i| {
                let p = out.completed.positions[i];
                (((p.x - axis.x).powi(2) + (p.y - axis.y).powi(2)).sqrt() - radius).abs()
            })
            .collect();
        assert!(!errors.is_empty());
        let mean = errors.iter().sum::<f32>() / errors.len() as f32;
        (mean, out.report)
    };
    let (without, _) = spread(false);
    let (with, report) = spread(true);
    let rec = |id: u16| {
        report
            .instances
            .iter()
            .find(|i| i.instance_id == id)
            .and_then(|i| i.revolve.clone())
            .unwrap()
    };
    let fit = rec(target).fit.expect("the can is a solid of revolution");
    assert!(((fit.axis[0] - axis.x).powi(2) + (fit.axis[1] - axis.y).powi(2)).sqrt() < 0.003);
    assert!(
        with < 0.004,
        "generated can points {with} m off its surface"
    );
    assert!(
        without > 2.0 * with,
        "rules alone {without} m, revolved {with} m"
    );
    let boxes: Vec<u16> = rendered
        .scene
        .objects
        .iter()
        .filter(|o| o.category.name() == "box")
        .map(|o| o.instance_id)
        .collect();
    assert!(!boxes.is_empty());
    for b in boxes {
        if let Some(i) = report.instances.iter().find(|i| i.instance_id == b) {
            assert!(i.revolve.as_ref().is_none_or(|r| r.fit.is_none()), "{i:?}");
        }
    }
}

/// The revolve stage's gates are the pipeline's options: pickup-v1's first can is revolved at
/// the defaults and turned down for its arc when the options ask for the whole circle.
#[test]
fn the_revolve_gates_are_options() {
    let preset = deocc_synth::dataset::pickup_v1();
    let rendered = render_full_scene(&preset.config, preset.seeds[0]).unwrap();
    let target = rendered.scene.target.unwrap();
    let scene = rendered.scene_input();
    let chain = CompleterChain::single(RulesCompleter::default());
    let record = |opts: PipelineOptions| {
        let out = deocc_pipeline::run(&scene, &chain, &opts, &Vec::new()).unwrap();
        out.report
            .instances
            .iter()
            .find(|i| i.instance_id == target)
            .and_then(|i| i.revolve.clone())
            .unwrap()
    };
    assert!(record(PipelineOptions::default()).fit.is_some());
    let refused = record(PipelineOptions {
        revolve_min_arc_deg: 359.0,
        ..Default::default()
    });
    assert!(refused.fit.is_none(), "{refused:?}");
    assert!(refused.reason.contains("arc"), "{}", refused.reason);
}

/// A can behind a box under the structured-light model (pickup-v2's tuning scene 9,450,027):
/// the depth front end's smoothing flattens the arc on its flanks and the side's fit comes out
/// several millimetres too wide, more than the gripper's margins; the outline in the view puts
/// it back within a millimetre or two.
#[test]
fn the_outline_narrows_a_can_the_sensor_widened() {
    let mut preset = deocc_synth::dataset::pickup_v2();
    preset.config.sensor = deocc_synth::sensor::SensorKind::StructuredLight;
    preset.config.sensor_noise = false;
    let rendered = render_full_scene(&preset.config, 9_450_027).unwrap();
    let target = rendered.scene.target.unwrap();
    let (_, radius) = target_can(&rendered);
    let chain = CompleterChain::single(RulesCompleter::default());
    let fitted = |outline: bool| {
        let opts = PipelineOptions {
            revolve_outline: outline,
            ..Default::default()
        };
        let mut scene = rendered.scene_input();
        let segmenter = deocc_pipeline::segment::ConvexitySegmenter::default();
        let prepared =
            deocc_pipeline::front::prepare(&mut scene, &opts, None, &segmenter, false).unwrap();
        let out = deocc_pipeline::run_prepared(
            &scene,
            &chain,
            &opts,
            prepared,
            &deocc_pipeline::Unobserved,
        )
        .unwrap();
        let rec = out
            .report
            .instances
            .iter()
            .find(|i| i.instance_id == target)
            .and_then(|i| i.revolve.clone())
            .unwrap();
        let fit = rec.fit.expect("the can is revolved");
        let mut r: Vec<f32> = fit.radii.iter().map(|r| r.1).collect();
        r.sort_by(f32::total_cmp);
        (r[r.len() / 2], fit.outline_offset_m, rec.reason)
    };
    let (wide, none, _) = fitted(false);
    let (narrowed, offset, reason) = fitted(true);
    assert!(none.is_none());
    assert!(
        wide - radius > 0.004,
        "without the outline {wide} m for a {radius} m can: nothing to narrow"
    );
    assert!(offset.is_some_and(|d| d < 0.0), "{reason}");
    assert!(reason.contains("to its outline"), "{reason}");
    assert!(
        (narrowed - radius).abs() < 0.002,
        "with the outline {narrowed} m for a {radius} m can ({reason})"
    );
}

/// The box in front of a can, seen face on with its top (pickup-v1's 23rd scene), is completed
/// as the box it is: heading, footprint and bottom within millimetres of the truth, and every
/// generated point of it near the true box's faces.
#[test]
fn an_occluding_box_is_completed_as_a_box() {
    let preset = deocc_synth::dataset::pickup_v1();
    let rendered = render_full_scene(&preset.config, preset.seeds[22]).unwrap();
    let target = rendered.scene.target.unwrap();
    let scene = rendered.scene_input();
    let chain = CompleterChain::single(RulesCompleter::default());
    let opts = PipelineOptions {
        complete_unoccluded: true,
        ..Default::default()
    };
    let out = deocc_pipeline::run(&scene, &chain, &opts, &Vec::new()).unwrap();
    let boxes: Vec<_> = rendered
        .scene
        .objects
        .iter()
        .filter(|o| o.category.name() == "box" && o.instance_id != target)
        .collect();
    let mut fitted = 0;
    for truth in boxes {
        let Some(fit) = out
            .report
            .instances
            .iter()
            .find(|i| i.instance_id == truth.instance_id)
            .and_then(|i| i.cuboid.as_ref())
            .and_then(|c| c.fit.clone())
        else {
            continue;
        };
        fitted += 1;
        // The true box's extents along the fitted heading and across it.
        let (u, v) = (
            [fit.yaw.cos(), fit.yaw.sin()],
            [-fit.yaw.sin(), fit.yaw.cos()],
        );
        let along = |d: [f32; 2], p: &Point3<f32>| d[0] * p.x + d[1] * p.y;
        let extent = |d: [f32; 2]| {
            truth
                .mesh
                .vertices
                .iter()
                .fold((f32::MAX, f32::MIN), |(a, b), p| {
                    (a.min(along(d, p)), b.max(along(d, p)))
                })
        };
        let (eu, ev) = (extent(u), extent(v));
        assert!(
            (eu.1 - eu.0 - fit.size[0]).abs() < 0.006,
            "{eu:?} vs {fit:?}"
        );
        assert!(
            (ev.1 - ev.0 - fit.size[1]).abs() < 0.006,
            "{ev:?} vs {fit:?}"
        );
        let zmin = truth
            .mesh
            .vertices
            .iter()
            .map(|p| p.z)
            .fold(f32::MAX, f32::min);
        assert!(
            (fit.z[0] - zmin).abs() < 0.005,
            "bottom {} vs {zmin}",
            fit.z[0]
        );
        // Every generated point of the box lies on one of its true faces.
        let gen = out.completed.generated.as_deref().unwrap();
        let ids = out.completed.instance.as_deref().unwrap();
        let mut n = 0;
        for i in
            (0..out.completed.len()).filter(|&i| gen[i] != 0 && ids[i] == truth.instance_id as u32)
        {
            let p = out.completed.positions[i];
            let (a, b) = (along(u, &p), along(v, &p));
            let off = (a - eu.0)
                .abs()
                .min((a - eu.1).abs())
                .min((b - ev.0).abs())
                .min((b - ev.1).abs());
            let inside =
                a > eu.0 - 0.006 && a < eu.1 + 0.006 && b > ev.0 - 0.006 && b < ev.1 + 0.006;
            assert!(
                inside && (off < 0.006 || p.z > fit.z[1] - 0.006),
                "a box point {off} m off its faces"
            );
            n += 1;
        }
        assert!(n > 0);
    }
    assert_eq!(fitted, 1, "{:?}", out.report.instances);
}

/// Crops a completer declines go to the next one in the chain; crops every completer declines are
/// reported as declined.
#[test]
fn declined_crops_go_to_the_rules_completer() {
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let opts = PipelineOptions {
        complete_planes: false,
        ..Default::default()
    };
    let chain = CompleterChain::single(Stub {
        max_width_m: 0.0,
        lopsided: 0.0,
        expected_error: None,
    })
    .then(RulesCompleter::default());
    let out = deocc_pipeline::run(&scene, &chain, &opts, &Vec::new()).unwrap();
    let r = &out.report;
    assert_eq!(r.completers, "stub,rules");
    assert_eq!(r.points_model, 0);
    assert!(r.points_rules > 0);
    assert!(r.completions.iter().all(|c| c.completer == "rules"));
    assert_eq!(r.crops_declined, 0);
    let only_stub = CompleterChain::single(Stub {
        max_width_m: 0.0,
        lopsided: 0.0,
        expected_error: None,
    });
    let out = deocc_pipeline::run(&scene, &only_stub, &opts, &Vec::new()).unwrap();
    assert_eq!(out.report.points_generated, 0);
    assert!(out.report.crops_declined > 0);
    assert!(out
        .report
        .completions
        .iter()
        .all(|c| !c.accepted && c.reason.starts_with("declined")));
}

/// With some frames carrying instance maps and others segmented, the segmented instances get ids
/// that no given instance has.
#[test]
fn mixed_instance_input_gets_distinct_ids() {
    use deocc_pipeline::instances::ensure_instances;
    use deocc_pipeline::segment::ConvexitySegmenter;
    let rendered = small_scene();
    let mut scene = rendered.scene_input();
    let given: std::collections::BTreeSet<u16> = scene.frames[1..]
        .iter()
        .flat_map(|f| f.instances.as_ref().unwrap().ids.iter().copied())
        .filter(|&id| id != 0)
        .collect();
    scene.frames[0].instances = None;
    let made = ensure_instances(&mut scene, &ConvexitySegmenter::default()).unwrap();
    assert!(made > 0);
    let segmented: std::collections::BTreeSet<u16> = scene.frames[0]
        .instances
        .as_ref()
        .unwrap()
        .ids
        .iter()
        .copied()
        .filter(|&id| id != 0)
        .collect();
    assert!(!segmented.is_empty());
    assert!(
        segmented.is_disjoint(&given),
        "segmented {segmented:?} collide with given {given:?}"
    );
    // The given maps are untouched.
    for (f, v) in scene.frames[1..].iter().zip(&rendered.views[1..]) {
        assert_eq!(f.instances.as_ref().unwrap().ids, v.frame.instance);
    }
}

/// Options read from JSON: missing fields default, unknown fields and bad values are refused with
/// the file and the field named.
#[test]
fn options_from_json_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("options.json");
    std::fs::write(&path, r#"{"steps": 8, "rho": 0.25}"#).unwrap();
    let o = PipelineOptions::from_json_file(&path).unwrap();
    assert_eq!((o.steps, o.rho), (8, 0.25));
    assert_eq!(o.batch, PipelineOptions::default().batch);
    for (text, field) in [
        (r#"{"stpes": 8}"#, "stpes"),
        (r#"{"steps": 0}"#, "steps"),
        (r#"{"rho": 1e30}"#, "rho"),
        (r#"{"fusion_voxel_m": -1}"#, "fusion_voxel_m"),
        (
            r#"{"gate_min_mean_confidence": 1.5}"#,
            "gate_min_mean_confidence",
        ),
        (
            r#"{"gate_max_seen_through_fraction": -0.1}"#,
            "gate_max_seen_through_fraction",
        ),
        (
            r#"{"plane_min_rectangularity": 3}"#,
            "plane_min_rectangularity",
        ),
        (
            r#"{"plane_piece_min_fraction": 0}"#,
            "plane_piece_min_fraction",
        ),
        (
            r#"{"gate_max_depth_spread_m": -0.01}"#,
            "gate_max_depth_spread_m",
        ),
        (
            r#"{"completers": {"gldot": {"depth_median_px": 17}}}"#,
            "completers.gldot.depth_median_px",
        ),
        (
            r#"{"completers": {"*": {"max_thickness_m": -1}}}"#,
            "completers.*.max_thickness_m",
        ),
        (
            r#"{"completers": {"rules": {"max_thickness_m": 11}}}"#,
            "completers.rules.max_thickness_m",
        ),
        (
            r#"{"completers": {"rules": {"max_thickness_per_width": -1}}}"#,
            "completers.rules.max_thickness_per_width",
        ),
        (
            r#"{"completers": {"gldot": {"depth_median_max_crop_m": -0.5}}}"#,
            "completers.gldot.depth_median_max_crop_m",
        ),
        (
            r#"{"completers": {"gldot": {"max_thicknes_m": 0.1}}}"#,
            "max_thicknes_m",
        ),
    ] {
        std::fs::write(&path, text).unwrap();
        let e = PipelineOptions::from_json_file(&path)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("options.json") && e.contains(field),
            "{text}: {e}"
        );
    }
}

/// A frame whose pose puts it far from the others is refused before anything is reconstructed
/// (it would spread the scene, and the plane fill's grid, over kilometres), naming the frame.
#[test]
fn a_frame_far_from_the_others_is_refused() {
    let rendered = small_scene();
    let mut scene = rendered.scene_input();
    let chain = CompleterChain::single(RulesCompleter::default());
    let name = scene.frames[2].name.clone();
    scene.frames[2]
        .camera
        .world_from_camera
        .translation
        .vector
        .x += 1000.0;
    let e = deocc_pipeline::run(&scene, &chain, &PipelineOptions::default(), &Vec::new())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("cameras.json") && e.contains(&name), "{e}");
    // Within the radius it runs.
    let mut near = rendered.scene_input();
    near.frames[2].camera.world_from_camera.translation.vector.x += 0.5;
    assert!(deocc_pipeline::run(&near, &chain, &PipelineOptions::default(), &Vec::new()).is_ok());
}

/// Frames fused into the voxel grid one at a time give the same cloud, bit for bit, as
/// downsampling every frame's points at once.
#[test]
fn incremental_fusion_equals_downsampling_everything() {
    use deocc_geometry::depth::backproject;
    use deocc_geometry::voxel::voxel_downsample;
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let incremental = deocc_pipeline::reconstruct::reconstruct(&scene, 0.005).unwrap();
    let mut all = deocc_geometry::PointCloud::default();
    for f in &scene.frames {
        let (mut c, px) = backproject(&f.depth, &f.camera).unwrap();
        let rgb = f.rgb.as_raw();
        c.colors = Some(
            px.iter()
                .map(|&i| {
                    [
                        rgb[3 * i as usize],
                        rgb[3 * i as usize + 1],
                        rgb[3 * i as usize + 2],
                    ]
                })
                .collect(),
        );
        let ids = &f.instances.as_ref().unwrap().ids;
        c.instance = Some(px.iter().map(|&i| ids[i as usize] as u32).collect());
        c.generated = Some(vec![0; c.len()]);
        all.append(&c);
    }
    let at_once = voxel_downsample(&all, 0.005).unwrap();
    assert!(incremental.len() > 1000);
    assert_eq!(incremental, at_once);
}

/// An observer sees every stage in order with rising fractions, and one that says stop at
/// `complete` ends the run there with `Cancelled`, no completer called.
#[test]
fn an_observer_sees_each_stage_and_can_stop_the_run() {
    use std::sync::Mutex;
    struct Record(Mutex<Vec<(&'static str, f32)>>, Option<&'static str>);
    impl deocc_pipeline::Observer for Record {
        fn stage(&self, stage: &'static str, fraction: f32) -> bool {
            self.0.lock().unwrap().push((stage, fraction));
            Some(stage) != self.1
        }
    }
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let chain = CompleterChain::single(RulesCompleter::default());
    let opts = PipelineOptions::default();
    let all = Record(Mutex::new(Vec::new()), None);
    deocc_pipeline::run_observed(&scene, &chain, &opts, &Vec::new(), &all).unwrap();
    let seen = all.0.into_inner().unwrap();
    let mut names: Vec<&str> = seen.iter().map(|s| s.0).collect();
    // The completion stage also asks between its batches (a deadline inside the longest stage).
    names.dedup();
    let expected: Vec<&str> = deocc_pipeline::stages::observed().map(|s| s.0).collect();
    assert_eq!(names, expected);
    assert!(seen.windows(2).all(|w| w[0].1 <= w[1].1));
    assert!(seen.first().unwrap().1 < seen.last().unwrap().1);
    let stop = Record(Mutex::new(Vec::new()), Some("complete"));
    let e = deocc_pipeline::run_observed(&scene, &chain, &opts, &Vec::new(), &stop)
        .err()
        .unwrap();
    assert!(matches!(
        e,
        deocc_pipeline::PipelineError::Cancelled { stage: "complete" }
    ));
    assert_eq!(stop.0.into_inner().unwrap().len(), 4);

    // Stopped inside the completion stage: after its second batch of one crop, the completer
    // is not called again, while the whole run calls it more often.
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;
    struct StopMidway(AtomicUsize);
    impl deocc_pipeline::Observer for StopMidway {
        fn stage(&self, stage: &'static str, _: f32) -> bool {
            stage != "complete" || self.0.fetch_add(1, Ordering::SeqCst) < 2
        }
    }
    struct Counting(RulesCompleter, Arc<AtomicUsize>);
    impl deocc_completion::Completer for Counting {
        fn name(&self) -> &str {
            "rules"
        }
        fn provenance(&self) -> deocc_completion::Provenance {
            self.0.provenance()
        }
        fn resolution(&self) -> usize {
            self.0.resolution()
        }
        fn complete(
            &self,
            batch: &[deocc_completion::CropRequest<'_>],
            opts: &deocc_completion::CompletionOptions,
        ) -> Result<Vec<deocc_completion::CropCompletion>, deocc_completion::CompletionError>
        {
            self.1.fetch_add(1, Ordering::SeqCst);
            self.0.complete(batch, opts)
        }
    }
    let one_at_a_time = PipelineOptions {
        batch: 1,
        ..PipelineOptions::default()
    };
    let (whole, stopped) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
    let chain = CompleterChain::single(Counting(RulesCompleter::default(), whole.clone()));
    deocc_pipeline::run_observed(
        &scene,
        &chain,
        &one_at_a_time,
        &Vec::new(),
        &deocc_pipeline::Unobserved,
    )
    .unwrap();
    assert!(
        whole.load(Ordering::SeqCst) > 1,
        "the scene needs two crops"
    );
    let chain = CompleterChain::single(Counting(RulesCompleter::default(), stopped.clone()));
    let e = deocc_pipeline::run_observed(
        &scene,
        &chain,
        &one_at_a_time,
        &Vec::new(),
        &StopMidway(AtomicUsize::new(0)),
    )
    .err()
    .unwrap();
    assert!(matches!(
        e,
        deocc_pipeline::PipelineError::Cancelled { stage: "complete" }
    ));
    assert_eq!(stopped.load(Ordering::SeqCst), 1);
}

/// A plane the views see through is not filled (the vertical plane of a table's front legs and
/// apron, with the floor showing between the legs): over 12 small scenes, fewer than 0.5% of the
/// fill's points lie 2 cm or more from every true surface, under half as many as when every
/// plane is filled.
#[test]
fn planes_the_views_see_through_are_not_filled() {
    use deocc_pipeline::planes::{complete_planes, PlaneOptions};
    let (mut filled, mut off, mut off_unchecked) = (0usize, 0usize, 0usize);
    for seed in 0..12u64 {
        let cfg = SceneConfig {
            gt_points_per_m2: 10_000.0,
            ..config()
        };
        let rendered = render_full_scene(&cfg, seed).unwrap();
        let scene = rendered.scene_input();
        let index = deocc_geometry::KdIndex::build(&rendered.ground_truth.cloud.positions).unwrap();
        let off_surface = |opts: &PlaneOptions| {
            let fill = complete_planes(&scene, opts);
            let off = fill
                .positions
                .iter()
                .filter(|p| index.nearest(p).distance_sq > 0.02 * 0.02)
                .count();
            (fill.len(), off)
        };
        let (n, o) = off_surface(&PlaneOptions::default());
        filled += n;
        off += o;
        off_unchecked += off_surface(&PlaneOptions {
            max_seen_through: 1.0,
            ..PlaneOptions::default()
        })
        .1;
    }
    assert!(filled > 100_000, "{filled} points filled");
    assert!(
        (off as f64) < 0.005 * filled as f64,
        "{off} of {filled} off every surface"
    );
    assert!(
        2 * off < off_unchecked,
        "{off} against {off_unchecked} unchecked"
    );
}

/// Plane pieces on rendered scenes with ground-truth masks: the floor and the walls that show are
/// pieces (nothing lies behind them), tables are not (their legs and the floor lie below the
/// top), nor is any table-top object.
#[test]
fn floors_and_walls_are_plane_pieces_tables_are_not() {
    use deocc_pipeline::planes::{plane_pieces, PlaneOptions, ScenePlanes};
    let (mut structure, mut structure_found, mut tables) = (0, 0, 0);
    for seed in 0..6u64 {
        let rendered = render_full_scene(&config(), seed).unwrap();
        let scene = rendered.scene_input();
        let opts = PlaneOptions::default();
        let pieces = plane_pieces(&ScenePlanes::find(&scene, &opts), &opts, 0.9);
        for o in &rendered.scene.objects {
            let name = o.category.name();
            let seen = scene.frames.iter().any(|f| {
                f.instances
                    .as_ref()
                    .is_some_and(|m| m.ids.iter().filter(|&&i| i == o.instance_id).count() > 2000)
            });
            if (name == "floor" || name == "wall") && seen {
                structure += 1;
                structure_found += pieces.contains(&o.instance_id) as usize;
            } else if name != "floor" && name != "wall" {
                tables += (name == "table") as usize;
                assert!(
                    !pieces.contains(&o.instance_id),
                    "seed {seed}: {name} {} taken for a plane piece",
                    o.instance_id
                );
            }
        }
    }
    assert!(tables >= 3, "{tables} tables");
    assert!(
        structure >= 6 && structure_found == structure,
        "{structure_found} of {structure} floors and walls found"
    );
}

/// Other frames' observations reprojected into a crop (`crops::seen_elsewhere`): a frame seen
/// again from its own camera lands on its own visible pixels at their depth, so crop window,
/// crop camera and reprojection agree; and another frame of the scene adds pixels this view
/// does not see.
#[test]
fn a_frame_reprojected_into_its_own_crop_lands_on_its_visible_pixels() {
    use deocc_pipeline::crops::{instance_pixels, make_crop, seen_elsewhere};
    use deocc_pipeline::stats::view_stats;
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let frame = &scene.frames[0];
    let stats = view_stats(frame);
    // The largest instance that is not room structure.
    let (&id, st) = stats
        .iter()
        .filter(|(id, _)| !scene.structure_ids.contains(id))
        .max_by_key(|(_, s)| s.pixels)
        .unwrap();
    let (window, cond) = make_crop(frame, 0, id, st, 32).unwrap();
    let twice = vec![frame.clone(), frame.clone()];
    let mut again = window.clone();
    again.view = 1; // the same camera as "another" frame
    let elsewhere = seen_elsewhere(&twice, &instance_pixels(&twice), &again, true);
    // Its own surface faces its own camera: nothing of it is the object's back.
    assert!(elsewhere.back.is_none(), "a back seen from the front");
    let seen = elsewhere.front.expect("lands");
    let (mut on_visible, mut at_depth, mut off_visible) = (0, 0, 0);
    for k in 0..32 * 32 {
        let d = seen.depth[k];
        if !d.is_finite() {
            continue;
        }
        if cond.visible[k] {
            on_visible += 1;
            // The crop samples one image pixel at its centre; the reprojection the nearest
            // surface anywhere in it, which differs where the object's own depth steps.
            at_depth += ((d - cond.visible_depth[k]).abs() < 0.02) as usize;
        } else {
            off_visible += 1;
        }
    }
    let visible = cond.visible_px();
    assert!(on_visible * 10 >= visible * 9, "{on_visible} of {visible}");
    assert!(
        at_depth * 10 >= on_visible * 9,
        "{at_depth} of {on_visible} at their depth"
    );
    // Only the mask's edge ring may be covered without being visible at the pixel centre.
    assert!(off_visible * 4 <= visible, "{off_visible} beyond {visible}");

    // The scene's other frames see parts of it this crop does not.
    let pixels = instance_pixels(&scene.frames);
    if let Some(other) = seen_elsewhere(&scene.frames, &pixels, &window, false).front {
        let with = cond.clone().with_seen_elsewhere(other);
        let added = with
            .seen_elsewhere
            .as_ref()
            .map_or(0, |s| s.depth.iter().filter(|d| d.is_finite()).count());
        assert!(added <= 32 * 32 - visible);
        assert!(
            with.prior.iter().filter(|&&p| p).count() >= cond.prior.iter().filter(|&&p| p).count()
        );
    }
}

/// With the error gate on, a model that expects every point too far off generates none; with the
/// fallback on, the rules complete those pixels instead (rules points, their own records), and a
/// model without an estimate is left alone.
#[test]
fn the_rules_complete_what_the_model_expects_to_be_off() {
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let run = |expected_error: Option<f32>, limit: f32, fallback: bool| {
        let opts = patched(
            completion_only(),
            "stub",
            deocc_completion::FusePatch {
                max_expected_error_m: Some(limit),
                uncertain_to_rules: Some(fallback),
                ..Default::default()
            },
        );
        let chain = CompleterChain::single(Stub {
            max_width_m: 100.0,
            lopsided: 0.0,
            expected_error,
        });
        deocc_pipeline::run(&scene, &chain, &opts, &Vec::new())
            .unwrap()
            .report
    };
    let plain = run(None, 0.0, false);
    assert!(plain.points_model > 0);
    assert_eq!(plain.points_rules, 0);
    // No estimate: the gate and the fallback change nothing.
    let no_estimate = run(None, 0.01, true);
    assert_eq!(no_estimate.points_model, plain.points_model);
    assert_eq!(no_estimate.points_rules, 0);
    // Unsure everywhere (10 crop widths): nothing from the model.
    let gated = run(Some(10.0), 0.01, false);
    assert_eq!(gated.points_model, 0);
    assert_eq!(gated.points_rules, 0);
    assert!(gated.points_uncertain_dropped > 0);
    let filled = run(Some(10.0), 0.01, true);
    assert_eq!(filled.points_model, 0);
    assert!(filled.points_rules > 0);
    assert_eq!(
        filled.points_uncertain_dropped,
        gated.points_uncertain_dropped
    );
    let fallback_records = filled
        .completions
        .iter()
        .filter(|c| c.completer.starts_with("rules"))
        .count();
    let model_records = filled
        .completions
        .iter()
        .filter(|c| c.completer == "stub" && c.accepted)
        .count();
    assert!(fallback_records > 0 && fallback_records <= model_records);
    // Without a limit nothing is left out, and the fallback has nothing to do.
    let unlimited = run(Some(10.0), 0.0, true);
    assert_eq!(unlimited.points_model, plain.points_model);
    assert_eq!(unlimited.points_rules, 0);
    assert_eq!(unlimited.points_uncertain_dropped, 0);
    // Sure everywhere: the fallback has nothing to do.
    let sure = run(Some(0.0), 0.01, true);
    assert_eq!(sure.points_model, plain.points_model);
    assert_eq!(sure.points_rules, 0);
}

/// The rules completer's silhouette-relative cap reaches its far side: at a ratio far under any
/// object's depth over width it keeps fewer rules points than with the cap off, and at a ratio no
/// object reaches (the 15 cm cap binds first) it changes nothing. The placing settings (thin far
/// sides) keep fewer too, and are valid options.
#[test]
fn the_rules_far_side_follows_its_silhouette_cap() {
    let scene = small_scene().scene_input();
    let chain = CompleterChain::single(RulesCompleter::default());
    let rules_points = |opts: PipelineOptions| {
        opts.validate().unwrap();
        let out = deocc_pipeline::run(&scene, &chain, &opts, &Vec::new()).unwrap();
        out.completed
            .generated
            .unwrap()
            .iter()
            .filter(|&&g| g == Provenance::Rules.code())
            .count()
    };
    let ratio = |r: f32| {
        patched(
            PipelineOptions::default(),
            "rules",
            deocc_completion::FusePatch {
                max_thickness_per_width: Some(r),
                ..Default::default()
            },
        )
    };
    let off = rules_points(ratio(0.0));
    assert!(off > 0);
    let tight = rules_points(ratio(0.05));
    assert!(tight < off, "{tight} vs {off}");
    assert_eq!(rules_points(ratio(100.0)), off);
    let placing = PipelineOptions::default().for_placing();
    assert_eq!(placing.steps, PipelineOptions::default().steps);
    let thin = rules_points(placing);
    assert!(thin < off, "{thin} vs {off}");
}

/// With `fill_depth_max_gap_px`, the run fills the sensor's small holes before anything else
/// (on a copy: the caller's frames stay as they were) and reports it; without it, nothing.
#[test]
fn the_run_fills_small_depth_holes_when_asked() {
    let rendered = small_scene();
    let mut scene = rendered.scene_input();
    for f in &mut scene.frames {
        let (w, h) = (f.depth.width(), f.depth.height());
        let mut d = f.depth.clone().into_data();
        for (i, z) in d.iter_mut().enumerate() {
            if (i % w as usize) % 10 == 0 {
                *z = 0.0; // a lost column every 10 pixels
            }
        }
        f.depth = deocc_geometry::DepthMap::new(w, h, d).unwrap();
    }
    let before: Vec<usize> = scene.frames.iter().map(|f| f.depth.valid_count()).collect();
    let plain = run_plain_stub(&scene, &completion_only());
    assert!(plain.report.depth_fill.is_empty());
    let filled = run_plain_stub(
        &scene,
        &PipelineOptions {
            fill_depth_max_gap_px: 8,
            ..completion_only()
        },
    );
    let fills = &filled.report.depth_fill;
    assert_eq!(fills.len(), scene.frames.len());
    for (r, &n) in fills.iter().zip(&before) {
        assert_eq!(r.measured, n);
        assert!(r.filled > 0 && r.skipped.is_none(), "{r:?}");
    }
    let after: Vec<usize> = scene.frames.iter().map(|f| f.depth.valid_count()).collect();
    assert_eq!(before, after, "the caller's frames are not changed");
    assert!(filled.report.points_observed > plain.report.points_observed);
    let e = PipelineOptions {
        fill_depth_max_gap_px: 65,
        ..Default::default()
    }
    .validate()
    .unwrap_err();
    assert!(e.to_string().contains("fill_depth_max_gap_px"), "{e}");
}

/// A fusion patch for a link the chain does not have is refused, naming it and the chain; the
/// link's own name and `*` are taken.
#[test]
fn a_patch_for_a_link_the_chain_lacks_is_refused() {
    let scene = small_scene().scene_input();
    let chain = CompleterChain::single(RulesCompleter::default());
    let patch = deocc_completion::FusePatch {
        max_thickness_m: Some(0.1),
        ..Default::default()
    };
    let Err(e) = deocc_pipeline::run(
        &scene,
        &chain,
        &patched(completion_only(), "gldott", patch),
        &Vec::new(),
    ) else {
        panic!("a patch for a link that does not exist was taken");
    };
    let e = e.to_string();
    assert!(
        e.contains("completers.gldott") && e.contains("(rules)"),
        "{e}"
    );
    for name in ["rules", "*"] {
        deocc_pipeline::run(
            &scene,
            &chain,
            &patched(completion_only(), name, patch),
            &Vec::new(),
        )
        .unwrap();
    }
}

/// The front half asks the observer before its burst fusion and before each frame's depth front
/// end: one that says stop there ends `run_in_memory` with `Cancelled` at that stage, before any
/// run stage; one that lets it go sees `burst`, `depth_clean` once per frame, then the run's
/// stages.
#[test]
fn an_observer_can_stop_the_front_half() {
    use std::sync::Mutex;
    struct Record(Mutex<Vec<&'static str>>, Option<&'static str>);
    impl deocc_pipeline::Observer for Record {
        fn stage(&self, stage: &'static str, _: f32) -> bool {
            self.0.lock().unwrap().push(stage);
            Some(stage) != self.1
        }
    }
    let rendered = small_scene();
    let scene = rendered.scene_input();
    let frames = scene.frames.len();
    let chain = CompleterChain::single(RulesCompleter::default());
    let opts = PipelineOptions::default();
    let segmenter = deocc_pipeline::segment::ConvexitySegmenter::default();
    let stop = Record(Mutex::new(Vec::new()), Some("depth_clean"));
    let e = deocc_pipeline::run_in_memory(scene.clone(), &chain, &opts, &segmenter, false, &stop)
        .err()
        .unwrap();
    assert!(matches!(
        e,
        deocc_pipeline::PipelineError::Cancelled {
            stage: "depth_clean"
        }
    ));
    assert_eq!(stop.0.into_inner().unwrap(), vec!["burst", "depth_clean"]);
    let early = Record(Mutex::new(Vec::new()), Some("burst"));
    let e = deocc_pipeline::run_in_memory(scene.clone(), &chain, &opts, &segmenter, false, &early)
        .err()
        .unwrap();
    assert!(matches!(
        e,
        deocc_pipeline::PipelineError::Cancelled { stage: "burst" }
    ));
    let all = Record(Mutex::new(Vec::new()), None);
    deocc_pipeline::run_in_memory(scene, &chain, &opts, &segmenter, false, &all).unwrap();
    let seen = all.0.into_inner().unwrap();
    assert_eq!(seen[0], "burst");
    assert_eq!(seen.iter().filter(|s| **s == "depth_clean").count(), frames);
    assert!(seen[1..=frames].iter().all(|s| *s == "depth_clean"));
    assert!(seen.len() > frames + 1);
}
