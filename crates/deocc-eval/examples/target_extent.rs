//! What the completed grasp target of pickup-v2 looks like against its true surface, by target
//! kind: the diagnosis behind the grasp planner's empty plans under a sensor model.
//!
//! `cargo run --release -p deocc-eval --example target_extent -- [SENSOR] [SCENES] [CHAIN]`
//! (`PRESET=pickup-v1` for the other grasp benchmark, `FIRST=K` to start at the K-th scene)
//!
//! For each tuning scene (seeds 9,450,000 on): the target's completed points (the chain's cloud
//! as the grasp benchmark plans on it), the share of its true surface within 1 cm of a completed
//! point on the near and on the far half (split at the true centre along the sight line), the
//! share of completed points within 1 cm of the true surface, and the target's depth along the
//! sight line and width across it (5th to 95th percentile), true and completed.

use deocc_geometry::KdIndex;
use nalgebra::{Point3, Vector3};

fn spread(v: &mut [f32]) -> f32 {
    if v.len() < 2 {
        return 0.0;
    }
    v.sort_by(f32::total_cmp);
    let q = |f: f32| v[((v.len() - 1) as f32 * f) as usize];
    q(0.95) - q(0.05)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let sensor = args.next().unwrap_or_else(|| "structured-light".into());
    let scenes: usize = args.next().map_or(Ok(12), |s| s.parse())?;
    let chain_name = args.next().unwrap_or_else(|| "gldot,rules".into());
    let mut preset =
        deocc_synth::dataset::preset(&std::env::var("PRESET").unwrap_or("pickup-v2".into()))?;
    let kind = deocc_synth::sensor_kind::SensorKind::parse(&sensor)?;
    deocc_eval::with_sensor(&mut preset, kind);
    let first =
        preset.seeds[0] + 50_000 + std::env::var("FIRST").map_or(Ok(0), |s| s.parse::<u64>())?;
    let names: Vec<String> = chain_name.split(',').map(str::to_string).collect();
    let chain = deocc_model::chain::build(&names, None)?;
    let opts = deocc_pipeline::PipelineOptions {
        complete_unoccluded: true,
        ..Default::default()
    };
    println!(
        "{:>8} {:>15} {:>5} {:>6} {:>6} | {:>5} {:>5} {:>5} | depth true/done cm | width true/done cm",
        "seed", "kind", "vis", "pts", "gen", "near", "far", "prec"
    );
    for seed in first..first + scenes as u64 {
        let r = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        let target = r.scene.target.ok_or("no target")? as u32;
        let gt = deocc_synth::ground_truth::object_surfaces(&r.scene, 100_000.0, seed);
        let ids = gt.instance.clone().unwrap_or_default();
        let truth: Vec<Point3<f32>> = gt
            .positions
            .iter()
            .zip(&ids)
            .filter(|(_, &i)| i == target)
            .map(|(p, _)| *p)
            .collect();
        let input = r.scene_input();
        let eye = Point3::from(input.frames[0].camera.world_from_camera.translation.vector);
        let out = deocc_eval::run_as_product(&input, &chain, &opts)?;
        let c = &out.completed;
        let cids = c.instance.as_deref().unwrap_or(&[]);
        let gen = c.generated.as_deref().unwrap_or(&[]);
        let done: Vec<(Point3<f32>, bool)> = (0..c.len())
            .filter(|&k| cids.get(k) == Some(&target))
            .map(|k| (c.positions[k], gen.get(k).is_some_and(|&g| g != 0)))
            .collect();
        let centre = truth.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / truth.len() as f32;
        let mut sight = centre - eye.coords;
        sight.z = 0.0;
        let sight = sight.normalize();
        let across = Vector3::new(-sight.y, sight.x, 0.0);
        let along = |p: &Point3<f32>| (p.coords - centre).dot(&sight);
        let side = |p: &Point3<f32>| (p.coords - centre).dot(&across);
        let category = r
            .scene
            .objects
            .iter()
            .find(|o| u32::from(o.instance_id) == target)
            .map(|o| o.category.name().to_string())
            .unwrap_or_default();
        let visible = r.views[0]
            .visibility
            .iter()
            .find(|v| u32::from(v.instance_id) == target)
            .map_or(0.0, |v| 1.0 - v.occlusion());
        let (mut near, mut far, mut prec) = (f32::NAN, f32::NAN, f32::NAN);
        if !done.is_empty() {
            let pts: Vec<Point3<f32>> = done.iter().map(|d| d.0).collect();
            let index = KdIndex::build(&pts)?;
            let covered = |p: &Point3<f32>| index.nearest(p).distance_sq.sqrt() <= 0.01;
            let share = |front: bool| {
                let half: Vec<&Point3<f32>> =
                    truth.iter().filter(|p| (along(p) < 0.0) == front).collect();
                half.iter().filter(|p| covered(p)).count() as f32 / half.len().max(1) as f32
            };
            near = share(true);
            far = share(false);
            let tindex = KdIndex::build(&truth)?;
            prec = pts
                .iter()
                .filter(|p| tindex.nearest(p).distance_sq.sqrt() <= 0.01)
                .count() as f32
                / pts.len() as f32;
        }
        let mut td: Vec<f32> = truth.iter().map(along).collect();
        let mut tw: Vec<f32> = truth.iter().map(side).collect();
        let mut cd: Vec<f32> = done.iter().map(|d| along(&d.0)).collect();
        let mut cw: Vec<f32> = done.iter().map(|d| side(&d.0)).collect();
        let revolve = out
            .report
            .instances
            .iter()
            .find(|i| u32::from(i.instance_id) == target)
            .and_then(|i| i.revolve.as_ref())
            .map_or("-".to_string(), |r| match &r.fit {
                Some(f) => format!(
                    "revolved, seen through {:.2}",
                    f.seen_through_fraction.unwrap_or(f32::NAN)
                ),
                None => r.reason.clone(),
            });
        println!(
            "{seed:>8} {category:>15} {visible:>5.2} {:>6} {:>6} | {near:>5.2} {far:>5.2} {prec:>5.2} | {:>5.1} {:>5.1} | {:>5.1} {:>5.1} | {revolve}",
            done.len(),
            done.iter().filter(|d| d.1).count(),
            spread(&mut td) * 100.0,
            spread(&mut cd) * 100.0,
            spread(&mut tw) * 100.0,
            spread(&mut cw) * 100.0,
        );
    }
    Ok(())
}
