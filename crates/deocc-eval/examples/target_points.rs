//! How far the target's points of pickup-v1 lie from its true surface, observed and completed by
//! the rules, under a sensor model: the diagnosis behind the grasp planner's empty plans.
//!
//! `cargo run --release -p deocc-eval --example target_points -- [SENSOR] [SCENES]`

use deocc_completion::CompleterChain;
use deocc_geometry::KdIndex;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let sensor = args.next().unwrap_or_else(|| "structured-light".into());
    let scenes: usize = args.next().map_or(Ok(10), |s| s.parse())?;
    let mut preset = deocc_synth::dataset::pickup_v1();
    use deocc_synth::sensor_kind::SensorKind;
    let kind = SensorKind::parse(&sensor)?;
    deocc_eval::with_sensor(&mut preset, kind);
    let mut opts = deocc_pipeline::PipelineOptions {
        complete_unoccluded: true,
        ..Default::default()
    };
    if let Ok(r) = std::env::var("SMOOTH_RADIUS") {
        opts.depth_clean.radius = r.parse()?;
    }
    let rules = CompleterChain::single(deocc_completion::rules::RulesCompleter::default());
    let first: usize = std::env::var("FIRST").map_or(Ok(0), |s| s.parse())?;
    for &seed in &preset.seeds[first..first + scenes] {
        let r = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        let target = r.scene.target.unwrap() as u32;
        let gt = deocc_synth::ground_truth::object_surfaces(&r.scene, 100_000.0, seed);
        let ids = gt.instance.clone().unwrap();
        let tgt: Vec<_> = gt
            .positions
            .iter()
            .zip(&ids)
            .filter(|(_, &i)| i == target)
            .map(|(p, _)| *p)
            .collect();
        let index = KdIndex::build(&tgt)?;
        let out = deocc_eval::run_as_product(&r.scene_input(), &rules, &opts)?;
        {
            let mut input = r.scene_input();
            let f = &mut input.frames[0];
            deocc_pipeline::depth_clean::clean_depth(&mut f.depth, &opts.depth_clean);
            let before = f.instances.clone().unwrap().ids;
            deocc_pipeline::mask_rims::unlabel_mask_rims(f, &opts.mask_rims);
            let after = &f.instances.as_ref().unwrap().ids;
            let mut lost = std::collections::BTreeMap::<u16, usize>::new();
            for (a, b) in before.iter().zip(after) {
                if a != b {
                    *lost.entry(*a).or_default() += 1;
                }
            }
            println!("seed {seed}: target {target}, pixels unlabelled by instance {lost:?}");
        }
        for i in &out.report.instances {
            if u32::from(i.instance_id) == target {
                if let Some(r) = &i.revolve {
                    let radii: Vec<String> = r
                        .fit
                        .iter()
                        .flat_map(|f| f.radii.iter().map(|(z, r)| format!("{:.3}@{:.2}", r, z)))
                        .collect();
                    println!("  revolve: {} radii {}", r.reason, radii.join(" "));
                }
            }
        }
        let truth: Vec<String> = r
            .scene
            .objects
            .iter()
            .filter(|o| u32::from(o.instance_id) == target)
            .map(|o| {
                let (lo, hi) = o.mesh.bounds().unwrap();
                format!(
                    "{:?} {:.3} x {:.3} x {:.3}",
                    o.category,
                    hi.x - lo.x,
                    hi.y - lo.y,
                    hi.z - lo.z
                )
            })
            .collect();
        println!("  truth: {}", truth.join(", "));
        let mut line = format!(
            "seed {seed} rims {:?} clean: outliers {} specks {}",
            out.report.mask_rims,
            out.report.depth_clean[0].outliers_removed,
            out.report.depth_clean[0].specks_removed
        );
        for (name, cloud) in [("observed", &out.observed), ("rules", &out.completed)] {
            let ids = cloud.instance.as_deref().unwrap_or(&[]);
            let gen = cloud.generated.as_deref();
            let mut d: Vec<(f32, bool)> = cloud
                .positions
                .iter()
                .enumerate()
                .filter(|(k, _)| ids[*k] == target)
                .map(|(k, p)| {
                    (
                        index.nearest(p).distance_sq.sqrt(),
                        gen.is_some_and(|g| g[k] != 0),
                    )
                })
                .collect();
            d.sort_by(|a, b| a.0.total_cmp(&b.0));
            let q = |f: f64| {
                d.get(((d.len() as f64 - 1.0) * f) as usize)
                    .map_or(f32::NAN, |x| x.0)
            };
            let far = d.iter().filter(|x| x.0 > 0.02).count();
            let far_gen = d.iter().filter(|x| x.0 > 0.02 && x.1).count();
            line += &format!(
                " | {name}: {} pts, median {:.1} mm, p95 {:.1} mm, max {:.0} mm, >2 cm {far} ({far_gen} generated)",
                d.len(),
                q(0.5) * 1e3,
                q(0.95) * 1e3,
                q(1.0) * 1e3
            );
        }
        println!("{line}");
    }
    Ok(())
}
