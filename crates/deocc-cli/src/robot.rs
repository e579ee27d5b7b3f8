//! `deocc grasp` and `deocc place`: the robot tasks on a scene folder's completed cloud.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use deocc_geometry::camera::Camera;
use deocc_geometry::PointCloud;
use deocc_pipeline::output::Staging;
use deocc_pipeline::segment::ConvexitySegmenter;
use deocc_pipeline::{read_scene, PipelineOptions};
use deocc_robot::picture::{draw_grasp, place_map_image};
use deocc_robot::place::{PlaceOptions, UnseenSpace};
use deocc_robot::{AntipodalPlanner, GraspOptions, GraspPlanner, GridPlacer, PlacePlanner};

use crate::completers::CompleterArgs;

#[derive(Args)]
pub struct SceneArgs {
    /// Scene folder (as for `deocc run`).
    scene: PathBuf,
    /// Output folder for the JSON answer and its picture; without it the JSON goes to stdout.
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    completers: CompleterArgs,
    #[command(flatten)]
    depth: crate::depth::DepthArgs,
    /// Plan on the observed points only (no completion, no plane fill).
    #[arg(long)]
    observed: bool,
}

/// Where an instance is in the masks: per view its name, mask pixels and those with depth.
type MaskPresence = Vec<(String, usize, usize)>;

fn presence(scene: &deocc_pipeline::SceneInput, id: u32) -> MaskPresence {
    scene
        .frames
        .iter()
        .filter_map(|f| {
            let m = f.instances.as_ref()?;
            let (mut px, mut measured) = (0, 0);
            for (i, &v) in m.ids.iter().enumerate() {
                if u32::from(v) == id {
                    px += 1;
                    measured += usize::from(f.depth.data()[i] > 0.0);
                }
            }
            (px > 0).then(|| (f.name.clone(), px, measured))
        })
        .collect()
}

/// A completed cloud, the frames' names and cameras, the scene as the run used it, and the
/// instances whose completion is a fitted surface ([`deocc_pipeline::RunReport::fitted_instances`]).
type Completed = (
    PointCloud,
    Vec<(String, Camera)>,
    deocc_pipeline::SceneInput,
    Vec<u32>,
);

/// The scene's completed cloud (or observed with `--observed`) with `options`, its frames'
/// names and cameras, and the scene itself (with the instance maps the run used).
fn completed(a: &SceneArgs, options: &PipelineOptions) -> Result<Completed> {
    let mut scene = read_scene(&a.scene)?;
    let mut options = options.clone();
    a.depth.apply(&mut options);
    let options = &options;
    let model = a.depth.model()?;
    let prepared = deocc_pipeline::front::prepare(
        &mut scene,
        options,
        model
            .as_ref()
            .map(|m| m as &dyn deocc_pipeline::depth::DepthSource),
        &ConvexitySegmenter::default(),
        false,
    )?;
    let chain = if a.observed {
        deocc_completion::CompleterChain::default()
    } else {
        crate::completers::chain(&a.completers)?
    };
    let out = deocc_pipeline::run_prepared(
        &scene,
        &chain,
        options,
        prepared,
        &deocc_pipeline::Unobserved,
    )?;
    crate::depth::print_depth_fill(&out.report.depth_fill);
    let cameras = scene
        .frames
        .iter()
        .map(|f| (f.name.clone(), f.camera))
        .collect();
    let fitted = out.report.fitted_instances();
    Ok((
        if a.observed {
            out.observed
        } else {
            out.completed
        },
        cameras,
        scene,
        fitted,
    ))
}

/// Writes `json` and `picture` into `out` atomically (or the JSON to stdout).
fn answer(
    out: Option<&Path>,
    input: &Path,
    name: &str,
    json: &impl serde::Serialize,
    picture: &image::RgbImage,
) -> Result<()> {
    let text = serde_json::to_string_pretty(json)?;
    let Some(out) = out else {
        println!("{text}");
        return Ok(());
    };
    let staging = Staging::begin(out, Some(input))?;
    std::fs::write(staging.dir().join(format!("{name}.json")), text + "\n")
        .with_context(|| format!("writing {name}.json"))?;
    picture
        .save(staging.dir().join(format!("{name}.png")))
        .with_context(|| format!("writing {name}.png"))?;
    let dir = staging.commit()?;
    println!("wrote {}", dir.display());
    Ok(())
}

/// Reads planner settings from a JSON file, or the defaults.
pub fn grasp_options(path: Option<&Path>) -> Result<GraspOptions> {
    let o: GraspOptions = match path {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            deocc_io::cameras::options_from_json(&text)
                .map_err(|e| anyhow::anyhow!("{}: grasp options: {e}", p.display()))?
        }
        None => GraspOptions::default(),
    };
    o.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(o)
}

#[derive(Args)]
pub struct GraspArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Instance id of the object to grasp (as in the instance maps or a run's instances.png).
    #[arg(long, required_unless_present_any = ["target_pixel", "target_box"])]
    target: Option<u32>,
    /// The object to grasp is the one seen at pixel `U,V` of `--target-view` (pixels of the
    /// image as the camera gave it: a stated lens distortion is accounted for).
    #[arg(long, value_name = "U,V", conflicts_with_all = ["target", "target_box"])]
    target_pixel: Option<String>,
    /// The object to grasp is the one filling most of box `U0,V0,U1,V1` in `--target-view`.
    #[arg(long, value_name = "U0,V0,U1,V1", conflicts_with = "target")]
    target_box: Option<String>,
    /// The frame `--target-pixel` / `--target-box` refer to (its name in cameras.json);
    /// default the first frame.
    #[arg(long, value_name = "FRAME")]
    target_view: Option<String>,
    /// Planner settings (JSON of the grasp options: gripper geometry, seeds, friction, top_k).
    #[arg(long)]
    options: Option<PathBuf>,
}

#[derive(serde::Serialize)]
struct GraspAnswer<'a> {
    target: u32,
    /// How the target was chosen when not by id (`--target-pixel 320,240 in frame "000000"`).
    #[serde(skip_serializing_if = "Option::is_none")]
    target_picked_by: Option<String>,
    target_points: usize,
    planner: &'a str,
    gripper: deocc_robot::GripperConfig,
    grasps: Vec<deocc_robot::Grasp>,
    /// When there is no grasp: the check that turned most candidates down, in words.
    #[serde(skip_serializing_if = "Option::is_none")]
    why_none: Option<&'static str>,
    /// Every candidate pose and why each was turned down.
    plan_stats: deocc_robot::PlanStats,
}

/// The instance `--target-pixel` / `--target-box` point at, with how it was found.
fn picked_target(
    a: &GraspArgs,
    cloud: &PointCloud,
    cameras: &[(String, Camera)],
) -> Result<(u32, Option<String>)> {
    let (flag, text) = match (&a.target_pixel, &a.target_box, a.target) {
        (Some(p), _, _) => ("--target-pixel", p),
        (None, Some(b), _) => ("--target-box", b),
        (None, None, Some(id)) => return Ok((id, None)),
        (None, None, None) => bail!("give --target ID, --target-pixel U,V or --target-box"),
    };
    let mut pick =
        deocc_robot::target::Pick::parse(text).map_err(|e| anyhow::anyhow!("{flag} {e}"))?;
    let (name, camera) = match &a.target_view {
        Some(v) => cameras.iter().find(|(n, _)| n == v).ok_or_else(|| {
            let names: Vec<&str> = cameras.iter().map(|(n, _)| n.as_str()).collect();
            anyhow::anyhow!("--target-view {v:?}: no such frame (frames: {names:?})")
        })?,
        None => &cameras[0],
    };
    // Pixels of the image as given: through the frame's lens, if cameras.json states one.
    let lens = deocc_io::cameras::read_cameras_json(&a.scene.scene.join("cameras.json"))
        .ok()
        .and_then(|c| c.into_iter().find(|f| &f.name == name))
        .map(|f| f.lens.distortion)
        .unwrap_or_default();
    pick = pick
        .through_lens(&lens, &camera.intrinsics)
        .ok_or_else(|| anyhow::anyhow!("{flag} {text}: outside the lens model's range"))?;
    let id = deocc_robot::target::instance_at(cloud, camera, pick)
        .map_err(|e| anyhow::anyhow!("{flag} {text} in frame {name:?}: {e}"))?;
    Ok((id, Some(format!("{flag} {text} in frame {name:?}"))))
}

pub fn grasp(a: GraspArgs) -> Result<()> {
    let options = grasp_options(a.options.as_deref())?;
    let (cloud, cameras, scene, fitted) = completed(&a.scene, &PipelineOptions::default())?;
    let camera = cameras[0].1;
    let (target_id, picked) = picked_target(&a, &cloud, &cameras)?;
    if let Some(how) = &picked {
        eprintln!("target: instance {target_id} ({how})");
    }
    let ids = cloud.instance.clone().unwrap_or_default();
    let target: Vec<_> = cloud
        .positions
        .iter()
        .zip(&ids)
        .filter(|(_, &i)| i == target_id)
        .map(|(p, _)| *p)
        .collect();
    let seen = presence(&scene, target_id);
    if target.is_empty() && !seen.is_empty() {
        // In the masks but no point at all: the sensor measured no depth on it (a projector's
        // shadow, a dark or shiny surface) and nothing was completed. An answer, not an error.
        let views: Vec<String> = seen
            .iter()
            .map(|(n, px, d)| format!("{n} ({px} px, {d} with depth)"))
            .collect();
        let why = format!(
            "instance {target_id} is in the masks of {} but has no measured depth there and \
             nothing was completed for it: there is nothing to grasp (move the camera, or give \
             its depth)",
            views.join(", ")
        );
        eprintln!("{why}");
        let answer = serde_json::json!({
            "target": target_id, "target_picked_by": picked, "target_points": 0,
            "planner": "antipodal", "grasps": [], "why": why,
        });
        let text = serde_json::to_string_pretty(&answer)?;
        match a.scene.out.as_deref() {
            None => println!("{text}"),
            Some(out) => {
                let staging = Staging::begin(out, Some(&a.scene.scene))?;
                std::fs::write(staging.dir().join("grasps.json"), text + "\n")
                    .context("writing grasps.json")?;
                let dir = staging.commit()?;
                println!("wrote {}", dir.display());
            }
        }
        return Ok(());
    }
    if target.is_empty() {
        let mut present: Vec<u32> = ids.iter().copied().filter(|&i| i != 0).collect();
        present.sort_unstable();
        present.dedup();
        bail!(
            "--target {}: no such instance in {} (instances: {:?})",
            target_id,
            a.scene.scene.display(),
            present
        );
    }
    let planner = AntipodalPlanner {
        options: options.clone(),
    };
    // The planner's envelope: the cloud's expected errors (`expected_error_scale`) or the
    // stated one (`generated_error_m`).
    let errors = deocc_robot::grasp::envelope_errors(
        cloud.generated.as_deref(),
        cloud.expected_error.as_deref(),
        Some(&ids),
        &fitted,
        &options,
    );
    let target_errors: Option<Vec<f32>> = errors.as_ref().map(|e| {
        e.iter()
            .zip(&ids)
            .filter(|(_, &i)| i == target_id)
            .map(|(e, _)| *e)
            .collect()
    });
    let (grasps, stats) = planner
        .plan_with_errors(
            &cloud.positions,
            errors.as_deref(),
            &target,
            target_errors.as_deref(),
        )
        .map_err(|e| anyhow::anyhow!("--target {}: {e}", target_id))?;
    let why_none = stats.main_reason().filter(|_| grasps.is_empty());
    if let Some(why) = why_none {
        eprintln!(
            "no grasp on instance {target_id}: {why} ({} candidate poses tried)",
            stats.candidates
        );
    }
    let mut img = deocc_pipeline::render::splat(&cloud, &camera, 1, true);
    let project = |p: &nalgebra::Point3<f32>| camera.project_world(p).map(|(px, _)| [px.x, px.y]);
    for (k, g) in grasps.iter().enumerate().rev() {
        let color = if k == 0 {
            [40, 255, 80]
        } else {
            [255, 220, 40]
        };
        draw_grasp(&mut img, g, &options.gripper, &project, color);
    }
    if a.scene.out.is_some() {
        eprintln!(
            "{} grasps on instance {} ({} points); best score {:.3}",
            grasps.len(),
            target_id,
            target.len(),
            grasps.first().map(|g| g.score).unwrap_or(0.0)
        );
    }
    answer(
        a.scene.out.as_deref(),
        &a.scene.scene,
        "grasps",
        &GraspAnswer {
            target: target_id,
            target_picked_by: picked,
            target_points: target.len(),
            planner: planner.name(),
            gripper: options.gripper,
            grasps,
            why_none,
            plan_stats: stats,
        },
        &img,
    )
}

#[derive(Clone, Copy, ValueEnum)]
pub enum Unseen {
    Free,
    Occupied,
    AsPoints,
}

#[derive(Args)]
pub struct PlaceArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Object footprint: width and depth in metres, comma-separated (W,D; no space).
    #[arg(long, value_delimiter = ',', default_value = "0.08,0.08")]
    footprint: Vec<f32>,
    /// Object height in metres.
    #[arg(long, default_value_t = 0.12)]
    height: f32,
    /// What cells without any point are: free (optimistic), occupied (conservative) or neither
    /// (as the points say). Default: as-points for completed clouds, free with --observed.
    #[arg(long, value_enum)]
    unseen: Option<Unseen>,
    /// Gravity's opposite in the scene's world frame, comma-separated (X,Y,Z; no space).
    #[arg(long, value_delimiter = ',', default_value = "0,0,1")]
    up: Vec<f32>,
}

pub fn place(a: PlaceArgs) -> Result<()> {
    // `--footprint 0.1 0.1 SCENE` reads the second size as the scene: say what was meant.
    let scene = &a.scene.scene;
    if !scene.exists() && scene.to_str().is_some_and(|s| s.parse::<f32>().is_ok()) {
        bail!(
            "{} is a number, not a scene folder: --footprint and --up take comma-separated \
             values without spaces (--footprint 0.1,0.1 --up 0,0,1)",
            scene.display()
        );
    }
    if a.footprint.len() != 2 {
        bail!(
            "--footprint takes two sizes, W,D in metres (got {:?})",
            a.footprint
        );
    }
    if a.up.len() != 3 {
        bail!("--up takes three numbers, X,Y,Z (got {:?})", a.up);
    }
    let options = PlaceOptions {
        footprint: [a.footprint[0], a.footprint[1]],
        height: a.height,
        up: [a.up[0], a.up[1], a.up[2]],
        ..PlaceOptions::default()
    };
    options
        .validate()
        .map_err(|e| anyhow::anyhow!("--footprint / --height / --up: {e}"))?;
    let unseen = match (a.unseen, a.scene.observed) {
        (Some(Unseen::Free), _) | (None, true) => UnseenSpace::Free,
        (Some(Unseen::Occupied), _) => UnseenSpace::Occupied,
        (Some(Unseen::AsPoints), _) | (None, false) => UnseenSpace::AsPoints,
    };
    // The pipeline's defaults, not `PipelineOptions::for_placing`'s thin far sides: under the
    // structured-light model those doubled the false-placeable share and lost placements behind
    // the clutter (docs/decisions.md, "deocc place keeps the far sides").
    let (cloud, cameras, _, _) = completed(&a.scene, &PipelineOptions::default())?;
    let (camera, frames) = (cameras[0].1, cameras.len());
    let robot = nalgebra::Point3::from(camera.world_from_camera.translation.vector);
    let placer = GridPlacer {
        options: options.clone(),
        unseen,
        // One frame: the sight lines from its camera tell empty space past a table's edge.
        eye: (frames == 1).then_some(robot),
    };
    let (maps, best) = placer
        .plan_with_errors(&cloud.positions, cloud.expected_error.as_deref(), &robot)
        .map_err(|e| anyhow::anyhow!("{}: {e}", a.scene.scene.display()))?;
    let Some(best) = best else {
        bail!(
            "no placeable spot for a {} x {} x {} m object on any of the {} support surfaces",
            a.footprint[0],
            a.footprint[1],
            a.height,
            maps.len()
        );
    };
    let map = &maps[best.plane];
    let cells = [
        (options.footprint[0] / options.cell_m).round() as usize,
        (options.footprint[1] / options.cell_m).round() as usize,
    ];
    let img = place_map_image(map, Some(&best), cells, 4);
    #[derive(serde::Serialize)]
    struct PlaceAnswer<'a> {
        placement: &'a deocc_robot::place::Placement,
        plane: deocc_robot::place::SupportPlane,
        placeable_cells: usize,
        planes: Vec<deocc_robot::place::SupportPlane>,
        options: &'a PlaceOptions,
    }
    answer(
        a.scene.out.as_deref(),
        &a.scene.scene,
        "placement",
        &PlaceAnswer {
            placement: &best,
            plane: map.plane,
            placeable_cells: map.placeable_cells(),
            planes: maps.iter().map(|m| m.plane).collect(),
            options: &options,
        },
        &img,
    )
}

/// Grasps (the best three on each completed object) and the placement map (default footprint)
/// planned on a run's completed cloud, for its recording. `robot` is where the robot stands (the
/// first camera). A task that finds nothing (no support surface, no grasp) is left out.
pub fn recording_annotations(
    cloud: &PointCloud,
    robot: nalgebra::Point3<f32>,
) -> deocc_pipeline::record::RobotAnnotations {
    use deocc_pipeline::record::{RecordedGrasp, RobotAnnotations};
    let ids = cloud.instance.as_deref().unwrap_or_default();
    let generated = cloud.generated.as_deref().unwrap_or_default();
    let mut completed: Vec<u32> = ids
        .iter()
        .zip(generated)
        .filter(|&(&i, &g)| i != 0 && g != 0)
        .map(|(&i, _)| i)
        .collect();
    completed.sort_unstable();
    completed.dedup();
    let planner = AntipodalPlanner {
        options: GraspOptions::default(),
    };
    let g = &planner.options.gripper;
    let finger = [g.depth, g.finger_width, g.finger_height];
    let mut grasps = Vec::new();
    for id in completed {
        let target: Vec<_> = cloud
            .positions
            .iter()
            .zip(ids)
            .filter(|(_, &i)| i == id)
            .map(|(p, _)| *p)
            .collect();
        if let Ok(found) = planner.plan(&cloud.positions, &target) {
            grasps.extend(found.iter().take(3).map(|g| RecordedGrasp {
                instance: id,
                position: g.position,
                rotation: g.rotation,
                width: g.width,
                finger,
            }));
        }
    }
    let options = PlaceOptions::default();
    let (w, d, h, up) = (
        options.footprint[0],
        options.footprint[1],
        options.height,
        options.up,
    );
    let placer = GridPlacer {
        options,
        unseen: UnseenSpace::AsPoints,
        eye: None,
    };
    let (mut placeable, mut placement) = (Vec::new(), None);
    if let Ok((maps, best)) =
        placer.plan_with_errors(&cloud.positions, cloud.expected_error.as_deref(), &robot)
    {
        let to_world = placer.options.level().inverse();
        for m in &maps {
            for (i, _) in m.placeable.iter().enumerate().filter(|(_, &p)| p) {
                placeable.push((to_world * m.cell_center(i)).coords.into());
            }
        }
        placement = best.map(|b| b.position);
    }
    RobotAnnotations {
        grasps,
        placeable,
        placement,
        object: [w, d, h],
        up,
    }
}
