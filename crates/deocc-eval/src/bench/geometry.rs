//! `deocc bench geometry`: the geometry core against Open3D on the same clouds, in rounds that
//! alternate our side and Open3D's (the shared host's load drifts over seconds); the report gives
//! the median of the per-round ratios.

use std::path::Path;
use std::process::Command;

use deocc_geometry::align::{icp, IcpMethod, IcpOptions, IcpTarget};
use deocc_geometry::metrics::chamfer;
use deocc_geometry::normals::estimate_normals;
use deocc_geometry::voxel::voxel_downsample;
use deocc_geometry::{CellGrid, KdIndex, PointCloud};
use deocc_io::{write_point_cloud, PlyEncoding};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};
use rand::{Rng, SeedableRng};
use serde::Serialize;

use super::timing::{median, median_time, peer_script, TempDir};
use crate::EvalError;

/// The Open3D side, built into the binary.
const BENCH_OPEN3D_PY: &str = include_str!("../../../../scripts/bench_open3d.py");

#[derive(Serialize)]
pub struct Row {
    pub operation: String,
    /// Medians over the rounds.
    pub ours_seconds: f64,
    pub open3d_seconds: f64,
    /// ours / Open3D, the median of the per-round ratios: below 1 means we are faster.
    pub ratio: f64,
    /// Every round's ratio, in order.
    pub ratio_per_round: Vec<f64>,
    pub ours_value: Option<f64>,
    pub open3d_value: Option<f64>,
    pub relative_difference: Option<f64>,
}

#[derive(Serialize)]
pub struct GeometryReport {
    /// The machine and its load when the figures were taken.
    pub machine: super::timing::Machine,
    pub points_a: usize,
    pub points_b: usize,
    pub threads: usize,
    pub rounds: usize,
    pub open3d_version: String,
    pub rows: Vec<Row>,
}

/// Surface points of a benchmark scene (so normals and ICP see real structure), `n` of them, and a
/// half-size subset moved by 1 degree / 1 cm with 1 mm noise.
/// Target and source clouds of the benchmark.
type CloudPair = (Vec<Point3<f32>>, Vec<Point3<f32>>);

pub fn bench_clouds(n: usize) -> Result<CloudPair, EvalError> {
    use deocc_synth::render::SceneTriangles;
    let scene = deocc_synth::generate::generate_scene(
        &deocc_synth::scene::SceneConfig::default(),
        9_000_000,
    )?;
    let tris = SceneTriangles::new(&scene);
    let area: f64 = tris
        .corners
        .iter()
        .map(|c| 0.5 * (c[1] - c[0]).cross(&(c[2] - c[0])).norm() as f64)
        .sum();
    // The sampler covers only the room-facing faces of the structure, so the density from the
    // whole area undershoots; double it until there are enough points.
    let mut density = (1.2 * n as f64 / area) as f32;
    let mut pts = Vec::new();
    for _ in 0..6 {
        pts = deocc_synth::ground_truth::sample_surfaces(&scene, &tris, density, 1).positions;
        if pts.len() >= n {
            break;
        }
        density *= 2.0;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    for i in (1..pts.len()).rev() {
        pts.swap(i, rng.random_range(0..=i));
    }
    if pts.len() < n {
        return Err(EvalError::Data(format!(
            "could only sample {} of {n} points",
            pts.len()
        )));
    }
    pts.truncate(n);
    let motion = Isometry3::from_parts(
        Translation3::new(0.01, -0.005, 0.005),
        UnitQuaternion::from_euler_angles(0.01, 0.0, 0.015),
    );
    let b = pts[..n / 2]
        .iter()
        .map(|p| {
            let q = motion.transform_point(p);
            q + nalgebra::Vector3::new(
                rng.random_range(-0.001..0.001),
                rng.random_range(-0.001..0.001),
                rng.random_range(-0.001..0.001),
            )
        })
        .collect();
    Ok((pts, b))
}

/// Our side of one round: (operation, seconds, result value).
type OurRound = Vec<(&'static str, f64, Option<f64>)>;

fn our_round(
    pa: &[Point3<f32>],
    pb: &[Point3<f32>],
) -> Result<(OurRound, Vec<nalgebra::Vector3<f32>>), EvalError> {
    let mut ours: OurRound = Vec::new();
    let (t, _) = median_time(3, || Ok(KdIndex::build(pa)?))?;
    ours.push(("kdtree_build", t, None));
    // Open3D's compute_point_cloud_distance: index the target, answer every query.
    let (t, d) = median_time(3, || {
        let d = CellGrid::build(pa)?.nearest_distances(pb);
        Ok(d.iter().map(|&x| x as f64).sum::<f64>() / d.len() as f64)
    })?;
    ours.push(("nearest_neighbour", t, Some(d)));
    let (t, c) = median_time(3, || Ok(chamfer(pa, pb)?.2))?;
    ours.push(("chamfer", t, Some(c)));
    let cloud_a = PointCloud::from_positions(pa.to_vec());
    let (t, down) = median_time(3, || Ok(voxel_downsample(&cloud_a, 0.01)?))?;
    ours.push(("voxel_downsample", t, Some(down.len() as f64)));
    let (t, normals) = median_time(1, || Ok(estimate_normals(pa, 30)?))?;
    ours.push(("normals", t, None));
    for (name, method) in [
        ("icp_point_to_point", IcpMethod::PointToPoint),
        ("icp_point_to_plane", IcpMethod::PointToPlane),
    ] {
        let opts = IcpOptions {
            method,
            max_correspondence_m: 0.05,
            max_iterations: 30,
            relative_fitness: 0.0,
            relative_rmse: 0.0,
        };
        let (t, r) = median_time(1, || {
            // The tree build is part of the registration, as in Open3D's registration_icp.
            let target = IcpTarget::new(pa, Some(&normals))?;
            Ok(icp(pb, &target, &Isometry3::identity(), &opts)?)
        })?;
        ours.push((name, t, Some(r.inlier_rmse)));
    }
    Ok((ours, normals))
}

/// Runs the Open3D side once on the files.
fn open3d_round(
    python: &str,
    script: &Path,
    files: [&Path; 4],
) -> Result<serde_json::Value, EvalError> {
    eprintln!("open3d: running bench_open3d.py");
    let status = Command::new(python)
        .arg(script)
        .args(files)
        .status()
        .map_err(|e| EvalError::Data(format!("cannot run {python}: {e}")))?;
    if status.code() == Some(3) {
        return Err(EvalError::Data(format!(
            "Open3D is not installed for {python}: run `bash scripts/setup-peers.sh` (pip install \
             open3d==0.20.0, apt libusb-1.0-0)"
        )));
    }
    if !status.success() {
        return Err(EvalError::Data(format!(
            "bench_open3d.py failed ({status})"
        )));
    }
    let out = files[3];
    let text = std::fs::read_to_string(out).map_err(|e| deocc_io::IoError::new(out, e))?;
    serde_json::from_str(&text).map_err(|e| EvalError::Data(format!("{}: {e}", out.display())))
}

/// Runs the benchmark: `points` in cloud A (B gets half), `rounds` alternating rounds; without
/// `python` (a smoke run without the peer) Open3D's columns are NaN.
pub fn geometry_bench(
    points: usize,
    rounds: usize,
    python: Option<&str>,
) -> Result<GeometryReport, EvalError> {
    let tmp = TempDir::new("bench-geometry")?;
    let dir = &tmp.0;
    let script = peer_script(dir, "bench_open3d.py", BENCH_OPEN3D_PY)?;
    let (pa, pb) = bench_clouds(points)?;
    let (path_a, path_b, path_n, o3d_json) = (
        dir.join("a.ply"),
        dir.join("b.ply"),
        dir.join("a_normals.ply"),
        dir.join("open3d.json"),
    );
    write_point_cloud(
        &path_a,
        &PointCloud::from_positions(pa.clone()),
        PlyEncoding::BinaryLittleEndian,
    )?;
    write_point_cloud(
        &path_b,
        &PointCloud::from_positions(pb.clone()),
        PlyEncoding::BinaryLittleEndian,
    )?;
    eprintln!(
        "deocc: {} and {} points, {} threads, {rounds} rounds",
        pa.len(),
        pb.len(),
        rayon::current_num_threads()
    );
    let mut ours_rounds = Vec::new();
    let mut o3d_rounds = Vec::new();
    for round in 0..rounds.max(1) {
        eprintln!("round {} of {rounds}: ours", round + 1);
        let (ours, normals) = our_round(&pa, &pb)?;
        if round == 0 {
            let mut with_normals = PointCloud::from_positions(pa.clone());
            with_normals.normals = Some(normals);
            write_point_cloud(&path_n, &with_normals, PlyEncoding::BinaryLittleEndian)?;
        }
        ours_rounds.push(ours);
        o3d_rounds.push(match python {
            Some(python) => open3d_round(python, &script, [&path_a, &path_b, &path_n, &o3d_json])?,
            None => serde_json::Value::Null,
        });
    }
    let mut rows = Vec::new();
    for (k, &(name, _, value)) in ours_rounds[0].iter().enumerate() {
        let mut ours_t = Vec::new();
        let mut o3d_t = Vec::new();
        let mut ratios = Vec::new();
        let mut ov = None;
        for (ours, o3d) in ours_rounds.iter().zip(&o3d_rounds) {
            let entry = &o3d[name];
            let ot = match python {
                None => f64::NAN,
                Some(_) => entry["seconds"]
                    .as_f64()
                    .ok_or_else(|| EvalError::Data(format!("open3d result lacks {name}")))?,
            };
            ours_t.push(ours[k].1);
            o3d_t.push(ot);
            ratios.push(ours[k].1 / ot);
            ov = entry["value"].as_f64();
        }
        // For normals Open3D's value is already the agreement (mean |dot|) with ours.
        let (value, ov) = if name == "normals" {
            (ov, Some(1.0))
        } else {
            (value, ov)
        };
        let rel = match (value, ov) {
            (Some(x), Some(y)) => Some((x - y).abs() / y.abs().max(1e-12)),
            _ => None,
        };
        rows.push(Row {
            operation: name.into(),
            ours_seconds: median(&ours_t),
            open3d_seconds: median(&o3d_t),
            ratio: median(&ratios),
            ratio_per_round: ratios,
            ours_value: value,
            open3d_value: ov,
            relative_difference: rel,
        });
    }
    Ok(GeometryReport {
        machine: super::timing::Machine::now(),
        points_a: pa.len(),
        points_b: pb.len(),
        threads: rayon::current_num_threads(),
        rounds: ours_rounds.len(),
        open3d_version: o3d_rounds[0]["open3d_version"]
            .as_str()
            .unwrap_or(if python.is_some() { "?" } else { "not run" })
            .into(),
        rows,
    })
}

impl GeometryReport {
    /// The Markdown table of bench/geometry.md.
    pub fn markdown(&self) -> String {
        let mut md = format!(
            "{} and {} points, {} threads, median of {} alternating rounds.\n\n| operation | deocc (s) | Open3D {} (s) | ratio | ratio per round | result difference |\n|---|---|---|---|---|---|\n",
            self.points_a, self.points_b, self.threads, self.rounds, self.open3d_version
        );
        for r in &self.rows {
            let diff = r
                .relative_difference
                .map(|d| format!("{d:.1e}"))
                .unwrap_or_else(|| "-".into());
            let per: Vec<String> = r
                .ratio_per_round
                .iter()
                .map(|x| format!("{x:.2}"))
                .collect();
            md.push_str(&format!(
                "| {} | {:.3} | {:.3} | {:.2} | {} | {} |\n",
                r.operation,
                r.ours_seconds,
                r.open3d_seconds,
                r.ratio,
                per.join(", "),
                diff
            ));
        }
        md
    }
}
