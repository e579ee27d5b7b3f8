//! Why the place maps of place-v1 go wrong under a sensor model, scene by scene: the table's
//! pixels by range (in the mask, with raw depth, after the front half) and their heights over
//! the true top; what the view shows at each table cell the completed cloud leaves without
//! support; each object's mask pixels with depth; the false-placeable cells by the true object in
//! the way, with that object's completion record; the plane fill by range and the points at the
//! table's height outside its top. `ASCII=1` draws the table top (`#` plane fill, `o` observed,
//! `r` generated within 1 cm of the top; `x`/`y` observed/generated 1-3 cm off; `^` above, `_`
//! below).
//!
//! `[TUNING=1] cargo run --release -p deocc-eval --example place_support -- [SENSOR] [SCENES]`

use deocc_completion::CompleterChain;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let sensor = args.next().unwrap_or_else(|| "structured-light".into());
    let scenes: usize = args.next().map_or(Ok(5), |s| s.parse())?;
    let mut preset = deocc_synth::dataset::place_v1();
    use deocc_synth::sensor_kind::SensorKind;
    let kind = SensorKind::parse(&sensor)?;
    deocc_eval::with_sensor(&mut preset, kind);
    let opts = deocc_pipeline::PipelineOptions::default();
    let rules = CompleterChain::single(deocc_completion::rules::RulesCompleter::default());
    // TUNING=1: the tuning scenes (`deocc eval place --tuning`), not the test split.
    if std::env::var_os("TUNING").is_some() {
        let first = preset.seeds[0] + 50_000;
        preset.seeds = (first..first + scenes as u64).collect();
    }
    for &seed in &preset.seeds[..scenes] {
        let r = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        let table = r.scene.table.unwrap();
        let h = table.size.z;
        let out = deocc_eval::run_as_product(&r.scene_input(), &rules, &opts)?;
        let hist = |pts: &[nalgebra::Point3<f32>]| {
            let mut bins = [0usize; 7];
            for p in pts {
                let (lx, ly) = {
                    let (dx, dy) = (p.x - table.x, p.y - table.y);
                    let (c, s) = (table.yaw.cos(), table.yaw.sin());
                    (c * dx + s * dy, -s * dx + c * dy)
                };
                if lx.abs() > table.size.x / 2.0 || ly.abs() > table.size.y / 2.0 {
                    continue;
                }
                let dz = (p.z - h).abs();
                let b = [0.0025, 0.005, 0.01, 0.02, 0.03, 0.05]
                    .iter()
                    .position(|&t| dz < t)
                    .unwrap_or(6);
                bins[b] += 1;
            }
            bins
        };
        {
            let input = r.scene_input();
            let f = &input.frames[0];
            let ids = &f.instances.as_ref().unwrap().ids;
            let tid = table.instance_id;
            let truth = &r.views[0].frame.depth_m;
            let count = |d: &[f32]| {
                let mut n = [0usize; 8];
                for (i, (&id, &z)) in ids.iter().zip(d).enumerate() {
                    let _ = i;
                    if id != tid {
                        continue;
                    }
                    let t = truth[i];
                    let b = ((t - 0.8) / 0.25).clamp(0.0, 7.0) as usize;
                    if z > 0.0 {
                        n[b] += 1;
                    }
                }
                n
            };
            let mut all = [0usize; 8];
            for (i, &id) in ids.iter().enumerate() {
                if id == tid && truth[i] > 0.0 {
                    all[((truth[i] - 0.8) / 0.25).clamp(0.0, 7.0) as usize] += 1;
                }
            }
            let raw = count(f.depth.data());
            let mut d = f.depth.clone();
            deocc_pipeline::depth_clean::clean_depth(&mut d, &opts.depth_clean);
            let cleaned = count(d.data());
            println!("  table pixels by true depth band: mask {all:?}, with raw depth {raw:?}, after depth_clean {cleaned:?}");
        }
        let eye = r.scene.cameras[0].world_from_camera.translation.vector;
        let mut bands = [[0usize; 3]; 8];
        for p in &out.observed.positions {
            let (dx, dy) = (p.x - table.x, p.y - table.y);
            let (c, s) = (table.yaw.cos(), table.yaw.sin());
            let (lx, ly) = (c * dx + s * dy, -s * dx + c * dy);
            if lx.abs() > table.size.x / 2.0 || ly.abs() > table.size.y / 2.0 {
                continue;
            }
            let d = (p.coords - eye).norm();
            let b = ((d - 0.8) / 0.25).clamp(0.0, 7.0) as usize;
            let dz = (p.z - h).abs();
            let k = if dz < 0.01 {
                0
            } else if dz < 0.05 {
                1
            } else {
                2
            };
            bands[b][k] += 1;
        }
        {
            // The table's cells with no completed point within 1 cm of the true top: what the
            // view shows at each.
            let near: Vec<nalgebra::Point3<f32>> = out
                .completed
                .positions
                .iter()
                .filter(|p| (p.z - h).abs() <= 0.01)
                .map(|p| nalgebra::Point3::new(p.x, p.y, 0.0))
                .collect();
            let index = deocc_geometry::KdIndex::build(&near)?;
            let mut input = r.scene_input();
            let cam = input.frames[0].camera;
            let raw = input.frames[0].depth.clone();
            let segmenter = deocc_pipeline::segment::ConvexitySegmenter::default();
            deocc_pipeline::front::prepare(&mut input, &opts, None, &segmenter, false)?;
            let f = &input.frames[0];
            let ids = &f.instances.as_ref().unwrap().ids;
            let w = f.depth.width() as usize;
            let mut why = std::collections::BTreeMap::<String, usize>::new();
            {
                let mut per = std::collections::BTreeMap::<u16, [usize; 3]>::new();
                let orig = r.scene_input();
                let oids = &orig.frames[0].instances.as_ref().unwrap().ids;
                for i in 0..oids.len() {
                    let e = per.entry(oids[i]).or_default();
                    e[0] += 1;
                    e[1] += (raw.data()[i] > 0.0) as usize;
                    e[2] += (f.depth.data()[i] > 0.0 && ids[i] == oids[i]) as usize;
                }
                println!(
                    "  instance: [mask px, with raw depth, kept after the front half] {per:?}"
                );
            }
            {
                // Table pixels' heights over the true top, raw and cleaned, by range band.
                let mut hist = [[[0usize; 5]; 8]; 2];
                for (k, d) in [raw.data(), f.depth.data()].iter().enumerate() {
                    for (i, &z) in d.iter().enumerate() {
                        if z <= 0.0 || ids[i] != table.instance_id {
                            continue;
                        }
                        let p = cam.unproject_pixel((i % w) as u32, (i / w) as u32, z);
                        let dz = p.z - h;
                        let b = ((z - 0.8) / 0.25).clamp(0.0, 7.0) as usize;
                        let c = if dz < -0.03 {
                            0
                        } else if dz < -0.01 {
                            1
                        } else if dz <= 0.01 {
                            2
                        } else if dz <= 0.03 {
                            3
                        } else {
                            4
                        };
                        hist[k][b][c] += 1;
                    }
                }
                println!(
                    "  table pixels' dz (< -3, -3..-1, +-1, 1..3, > 3 cm) by band, raw: {:?}",
                    &hist[0][3..]
                );
                println!("  cleaned: {:?}", &hist[1][3..]);
            }
            let (nx, ny) = ((table.size.x / 0.01) as i32, (table.size.y / 0.01) as i32);
            for a in 0..nx {
                for b in 0..ny {
                    let (lx, ly) = (
                        (a as f32 + 0.5) * 0.01 - table.size.x / 2.0,
                        (b as f32 + 0.5) * 0.01 - table.size.y / 2.0,
                    );
                    let (x, y) = table.to_world(lx, ly);
                    let q = nalgebra::Point3::new(x, y, 0.0);
                    if index.nearest_within(&q, 0.01 * 0.01).is_some() {
                        continue;
                    }
                    let key = match cam.project_world(&nalgebra::Point3::new(x, y, h)) {
                        None => "behind camera".to_string(),
                        Some((px, z)) => {
                            let (u, v) = (px.x as usize, px.y as usize);
                            if px.x < 0.0 || px.y < 0.0 || u >= w || v >= f.depth.height() as usize
                            {
                                "out of view".into()
                            } else {
                                let i = v * w + u;
                                let id = ids[i];
                                let rd = raw.data()[i];
                                let cd = f.depth.data()[i];
                                let band = ((z - 0.8) / 0.25).clamp(0.0, 7.0) as usize;
                                let dz = if cd > 0.0 {
                                    format!("{:+.0}cm", ((cd - z) * 100.0).clamp(-9.0, 9.0))
                                } else {
                                    "none".into()
                                };
                                format!(
                                    "band {band} id {} raw {} cleaned {dz}",
                                    if id == table.instance_id {
                                        "table"
                                    } else if id == 0 {
                                        "0"
                                    } else {
                                        "other"
                                    },
                                    if rd > 0.0 { "yes" } else { "no" },
                                )
                            }
                        }
                    };
                    *why.entry(key).or_default() += 1;
                }
            }
            let mut v: Vec<_> = why.into_iter().collect();
            v.sort_by_key(|x| std::cmp::Reverse(x.1));
            println!(
                "  cells without support ({}): {:?}",
                v.iter().map(|x| x.1).sum::<usize>(),
                &v[..v.len().min(14)]
            );
        }
        if std::env::var("ASCII").is_ok() {
            let c = 0.02;
            let (nx, ny) = ((table.size.x / c) as usize, (table.size.y / c) as usize);
            let mut grid = vec![b'.'; nx * ny];
            let gen = out.completed.generated.as_ref().unwrap();
            for (p, &g) in out.completed.positions.iter().zip(gen) {
                let (dx, dy) = (p.x - table.x, p.y - table.y);
                let (co, si) = (table.yaw.cos(), table.yaw.sin());
                let (lx, ly) = (
                    co * dx + si * dy + table.size.x / 2.0,
                    -si * dx + co * dy + table.size.y / 2.0,
                );
                if lx < 0.0 || ly < 0.0 || lx >= nx as f32 * c || ly >= ny as f32 * c {
                    continue;
                }
                let i = (ly / c) as usize * nx + (lx / c) as usize;
                let dz = p.z - h;
                let ch = if dz.abs() <= 0.01 {
                    if g == 2 {
                        b'#'
                    } else if g == 0 {
                        b'o'
                    } else {
                        b'r'
                    }
                } else if dz.abs() <= 0.03 {
                    if g == 0 {
                        b'x'
                    } else {
                        b'y'
                    }
                } else if dz > 0.03 {
                    b'^'
                } else {
                    b'_'
                };
                let rank = |c: u8| b"._yx^#ro".iter().position(|&k| k == c).unwrap();
                if rank(ch) > rank(grid[i]) {
                    grid[i] = ch;
                }
            }
            for y in (0..ny).rev() {
                println!("  {}", String::from_utf8_lossy(&grid[y * nx..(y + 1) * nx]));
            }
            let cam = r.scene.cameras[0].world_from_camera.translation.vector;
            let (dx, dy) = (cam.x - table.x, cam.y - table.y);
            let (co, si) = (table.yaw.cos(), table.yaw.sin());
            println!(
                "  camera at table-frame ({:.2}, {:.2})",
                co * dx + si * dy,
                -si * dx + co * dy
            );
        }
        {
            let mut per = std::collections::BTreeMap::<u32, (usize, f32, f32)>::new();
            for (p, &i) in out
                .observed
                .positions
                .iter()
                .zip(out.observed.instance.as_ref().unwrap())
            {
                let e = per.entry(i).or_insert((0, f32::MAX, f32::MIN));
                e.0 += 1;
                e.1 = e.1.min(p.z - h);
                e.2 = e.2.max(p.z - h);
            }
            let truth: Vec<String> = r
                .scene
                .objects
                .iter()
                .map(|o| {
                    let (lo, hi) = o.mesh.bounds().unwrap();
                    format!("{}: z {:.3}..{:.3}", o.instance_id, lo.z - h, hi.z - h)
                })
                .collect();
            println!("  observed per instance (n, z over the table lo..hi): {per:?}");
            println!("  truth: {truth:?}");
        }
        {
            // The false-placeable cells of the completed map: which true object each one's
            // footprint meets, and what the completed and observed clouds hold of it there.
            use deocc_robot::place::{build_map, PlaceOptions, SupportPlane, UnseenSpace};
            let popts = PlaceOptions {
                footprint: deocc_eval::place::FOOTPRINT_M,
                height: deocc_eval::place::HEIGHT_M,
                ..PlaceOptions::default()
            };
            let corners: Vec<(f32, f32)> = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
                .iter()
                .map(|&(sx, sy)| table.to_world(sx * table.size.x / 2.0, sy * table.size.y / 2.0))
                .collect();
            let plane = SupportPlane {
                height: h,
                bounds: [
                    corners.iter().map(|c| c.0).fold(f32::MAX, f32::min),
                    corners.iter().map(|c| c.1).fold(f32::MAX, f32::min),
                    corners.iter().map(|c| c.0).fold(f32::MIN, f32::max),
                    corners.iter().map(|c| c.1).fold(f32::MIN, f32::max),
                ],
                points: 0,
            };
            let gt = deocc_synth::ground_truth::object_surfaces(
                &r.scene,
                deocc_eval::place::GT_DENSITY,
                seed,
            );
            let truth = build_map(&gt.positions, &plane, &popts, UnseenSpace::AsPoints)?;
            let map = build_map(
                &out.completed.positions,
                &plane,
                &popts,
                UnseenSpace::AsPoints,
            )?;
            let gids = gt.instance.as_ref().unwrap();
            let mut blame = std::collections::BTreeMap::<u32, usize>::new();
            let r_m = 0.06f32;
            for i in 0..map.placeable.len() {
                if !map.placeable[i] || truth.placeable[i] {
                    continue;
                }
                let c = map.cell_center(i);
                let mut best: Option<(u32, f32)> = None;
                for (p, &id) in gt.positions.iter().zip(gids) {
                    if id == table.instance_id as u32 || p.z < h + 0.005 {
                        continue;
                    }
                    let d = ((p.x - c.x).powi(2) + (p.y - c.y).powi(2)).sqrt();
                    if d < r_m && best.is_none_or(|b| d < b.1) {
                        best = Some((id, d));
                    }
                }
                *blame.entry(best.map_or(0, |b| b.0)).or_default() += 1;
            }
            let near = |cloud: &deocc_geometry::PointCloud, id: u32| {
                cloud
                    .instance
                    .as_ref()
                    .unwrap()
                    .iter()
                    .filter(|&&i| i == id)
                    .count()
            };
            let rows: Vec<String> = blame
                .iter()
                .map(|(&id, n)| {
                    format!(
                        "object {id}: {n} cells (completed holds {} of its points, observed {})",
                        near(&out.completed, id),
                        near(&out.observed, id)
                    )
                })
                .collect();
            println!("  false-placeable cells by the true object in the way: {rows:?}");
            for &id in blame.keys().filter(|&&id| id > 0) {
                for i in out
                    .report
                    .instances
                    .iter()
                    .filter(|i| u32::from(i.instance_id) == id)
                {
                    println!(
                        "    instance {id}: occluded in {:?}, selected {:?}, generated {}",
                        i.occluded_in_views, i.selected_views, i.generated_points
                    );
                }
                for c in out
                    .report
                    .completions
                    .iter()
                    .filter(|c| u32::from(c.instance_id) == id)
                {
                    println!("    completion: {} visible {} amodal {} new {} gated {} seen-through {:?} spread-dropped {} uncertain-dropped {}", c.completer, c.visible_px, c.amodal_px, c.new_points, c.gated, c.seen_through_fraction, c.spread_dropped, c.uncertain_dropped);
                }
            }
        }
        {
            let gen = out.completed.generated.as_ref().unwrap();
            let mut outside = [0usize; 4];
            let mut by_prov = [0usize; 4];
            let mut sides = std::collections::BTreeMap::new();
            for (p, &g) in out.completed.positions.iter().zip(gen) {
                if (p.z - h).abs() > 0.01 {
                    continue;
                }
                let (dx, dy) = (p.x - table.x, p.y - table.y);
                let (co, si) = (table.yaw.cos(), table.yaw.sin());
                let (lx, ly) = (co * dx + si * dy, -si * dx + co * dy);
                let o = (lx.abs() - table.size.x / 2.0).max(ly.abs() - table.size.y / 2.0);
                if o > 0.0 && o < 0.03 && g == 2 {
                    let side = if lx.abs() - table.size.x / 2.0 > ly.abs() - table.size.y / 2.0 {
                        if lx > 0.0 {
                            "+x"
                        } else {
                            "-x"
                        }
                    } else if ly > 0.0 {
                        "+y"
                    } else {
                        "-y"
                    };
                    *sides.entry(side).or_insert(0usize) += 1;
                }
                if o > 0.0 {
                    outside[((o / 0.01) as usize).min(3)] += 1;
                    by_prov[g as usize] += 1;
                }
            }
            println!("  points at the table's height outside its top, by cm outside: {outside:?}, by provenance {by_prov:?}, fill by side {sides:?}");
        }
        let mut fill = [0usize; 8];
        let mut fill_dz = Vec::new();
        let gen = out.completed.generated.as_ref().unwrap();
        for (p, &g) in out.completed.positions.iter().zip(gen) {
            if g == 2 && (p.z - h).abs() < 0.05 {
                fill_dz.push(p.z - h);
            }
            if g != 2 || (p.z - h).abs() > 0.01 {
                continue;
            }
            let d = (p.coords - eye).norm();
            fill[((d - 0.8) / 0.25).clamp(0.0, 7.0) as usize] += 1;
        }
        fill_dz.sort_by(f32::total_cmp);
        let q = |f: f32| {
            fill_dz
                .get((f * fill_dz.len() as f32) as usize)
                .copied()
                .unwrap_or(f32::NAN)
        };
        println!("  plane fill at table height by range: {fill:?}; fill dz quantiles 5/50/95%: {:.4} {:.4} {:.4}", q(0.05), q(0.5), q(0.95));
        println!("  observed by range from 0.8 m in 0.25 m bands [<1 cm, 1-5 cm, more]: {bands:?}");
        println!(
            "seed {seed}: table h {h:.3}, plane fill {} pts, observed |dz| bins (<2.5,<5,<10,<20,<30,<50 mm,more) {:?}, completed {:?}",
            out.report.points_plane_fill,
            hist(&out.observed.positions),
            hist(&out.completed.positions)
        );
    }
    Ok(())
}
