//! Stage: cuboid. An upright box seen at an angle (two side faces and the top) shows its whole
//! footprint, but its far faces are hidden, and a completer leaves them sparse or misplaced; a
//! gripper reaching behind the box for what it hides then passes through them. Such a box is
//! completed as the cuboid its visible faces fix.
//!
//! For each completed instance the revolve stage did not take: its observed side points (normal
//! within 30 degrees of horizontal) give the box's heading as the circular mean of four times
//! their normals' yaw, accepted when
//! - the normals agree with one rectangle (mean resultant length at least `min_concentration`;
//!   a cylinder's normals turn with its arc and do not), with at least `min_axis_share` of them
//!   within `face_deg` of one of its axes (a faceted bottle's facets lie between them),
//! - the footprint is seen: at least `min_face_points` side points whose normal lies within
//!   `face_deg` of each of the two axes, or a top seen from above that spans `min_top_span` of
//!   the footprint along both; one face seen head-on, without the top, leaves the depth to the
//!   completer: its points of the object give the extent across that face (between their 5% and
//!   95% quantiles, at least `min_completed_depth_m`), and the box makes their far side flat,
//! - the side points lie on the rectangle through the observed extents: 80th percentile of their
//!   distance to its nearest side at most `max_residual_m`,
//! - the box is at most `max_side_m` on a side.
//!
//! The instance's generated points are then replaced by the four sides and the top, sampled every
//! `sample_m` from what it stands on ([`support::support_height`]; else its lowest observed
//! point) to its highest observed point, with the rules provenance, the nearest observed colour
//! and confidence [`CUBOID_CONFIDENCE`]; carving keeps only what every view agrees is hidden.
//! Posed scenes only (it needs gravity).

use std::collections::BTreeSet;

use deocc_geometry::normals::estimate_normals;
use deocc_geometry::PointCloud;
use nalgebra::{Point2, Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::revolve::fitted_surface;
use crate::support::Ground;

/// Confidence of a point on an accepted cuboid.
pub const CUBOID_CONFIDENCE: f32 = 0.9;

/// Share of a completion's points left out at each end of its extent across a face seen
/// head-on (a completer's stray points).
pub const COMPLETION_TRIM: f32 = 0.05;

/// Settings of the cuboid stage (metres, degrees).
#[derive(Debug, Clone, Copy)]
pub struct CuboidOptions {
    pub min_concentration: f32,
    pub face_deg: f32,
    /// Least share of the side points whose normal lies within `face_deg` of one of the
    /// rectangle's two axes: a faceted body's facets between the axes are not a box's faces.
    pub min_axis_share: f32,
    pub min_face_points: usize,
    pub max_residual_m: f32,
    pub max_side_m: f32,
    /// Share of the footprint's extent along each axis the top must span to stand in for an
    /// unseen pair of faces.
    pub min_top_span: f32,
    pub sample_m: f32,
    pub normal_neighbours: usize,
    /// The support is searched at most this far below the observed bottom.
    pub max_drop_m: f32,
    /// Least depth a completion must give a box seen head-on (one face, no top).
    pub min_completed_depth_m: f32,
}

impl Default for CuboidOptions {
    fn default() -> Self {
        Self {
            // A sensor's axial noise on 5 mm voxels turns a face's PCA normals by several
            // degrees: with 16 neighbours and 0.9, 3 mm and 15 degrees, no box of pickup-v2's
            // tuning scenes was fitted under the structured-light model (concentration
            // 0.79-0.87, residuals above 3 mm), and few on clean depth (0.85-0.89). Flasks and
            // cylinders stay below 0.7; a faceted bottle reached 0.75, so `min_axis_share`
            // (facets between the axes) and the residual keep faceted bodies out
            // (docs/decisions.md, "The cuboid stage under a sensor's noise").
            min_concentration: 0.75,
            face_deg: 20.0,
            min_axis_share: 0.6,
            min_face_points: 30,
            max_residual_m: 0.008,
            max_side_m: 0.4,
            min_top_span: 0.9,
            sample_m: 0.004,
            normal_neighbours: 16,
            max_drop_m: 0.5,
            min_completed_depth_m: 0.01,
        }
    }
}

/// A fitted upright cuboid in the levelled frame (`up` = +z).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Cuboid {
    /// Footprint centre (x, y).
    pub center: [f32; 2],
    /// Heading of the first side's axis, radians in [0, pi/2).
    pub yaw: f32,
    /// Footprint extents along the heading and across it.
    pub size: [f32; 2],
    /// Bottom and top heights.
    pub z: [f32; 2],
    /// Mean resultant length of four times the side normals' yaw.
    pub concentration: f32,
    /// Side points whose normal lies along each axis.
    pub face_points: [usize; 2],
    /// The 80th percentile of the side points' distance to the footprint's nearest side.
    pub residual_m: f32,
    /// One face was seen head-on without the top: the depth across it is the completer's.
    #[serde(default)]
    pub depth_from_completion: bool,
}

/// What the stage made of one instance, for the run report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CuboidRecord {
    pub instance_id: u16,
    pub fit: Option<Cuboid>,
    pub reason: String,
}

/// The footprint rectangle of `pts` (levelled, with their normals), or why not.
pub fn fit_cuboid(
    pts: &[Point3<f32>],
    normals: &[Vector3<f32>],
    completion: &[Point3<f32>],
    o: &CuboidOptions,
) -> Result<Cuboid, String> {
    let side: Vec<usize> = (0..pts.len())
        .filter(|&i| normals[i].norm_squared() > 0.5 && normals[i].z.abs() < 0.5)
        .collect();
    if side.len() < 2 * o.min_face_points {
        return Err(format!("{} side points", side.len()));
    }
    let (mut c, mut s) = (0.0f32, 0.0f32);
    for &i in &side {
        let t = 4.0 * normals[i].y.atan2(normals[i].x);
        c += t.cos();
        s += t.sin();
    }
    let concentration = (c * c + s * s).sqrt() / side.len() as f32;
    if concentration < o.min_concentration {
        return Err(format!(
            "side normals agree with a rectangle to {concentration:.2} (at least {:.2} needed)",
            o.min_concentration
        ));
    }
    let yaw = (s.atan2(c) / 4.0).rem_euclid(std::f32::consts::FRAC_PI_2);
    let (u, v) = (
        Vector2::new(yaw.cos(), yaw.sin()),
        Vector2::new(-yaw.sin(), yaw.cos()),
    );
    let cos_face = o.face_deg.to_radians().cos();
    let mut face_points = [0usize; 2];
    for &i in &side {
        let n = Vector2::new(normals[i].x, normals[i].y).normalize();
        if n.dot(&u).abs() >= cos_face {
            face_points[0] += 1;
        } else if n.dot(&v).abs() >= cos_face {
            face_points[1] += 1;
        }
    }
    let on_axes = (face_points[0] + face_points[1]) as f32 / side.len() as f32;
    if on_axes < o.min_axis_share {
        return Err(format!(
            "{:.0}% of the side normals within {} degrees of the rectangle's axes (at least {:.0}% \
             needed: facets between them)",
            on_axes * 100.0,
            o.face_deg,
            o.min_axis_share * 100.0
        ));
    }
    let local = |p: &Point3<f32>| Vector2::new(p.coords.xy().dot(&u), p.coords.xy().dot(&v));
    let (mut lo, mut hi) = (Vector2::repeat(f32::MAX), Vector2::repeat(f32::MIN));
    for p in pts {
        let l = local(p);
        lo = lo.inf(&l);
        hi = hi.sup(&l);
    }
    let mut size = hi - lo;
    // The top (points facing up within 1 cm of the highest) spans the footprint when it is seen
    // from above: then it fixes the depth that one face seen head-on leaves open.
    let ztop = pts.iter().map(|p| p.z).fold(f32::MIN, f32::max);
    let top: Vec<Vector2<f32>> = (0..pts.len())
        .filter(|&i| normals[i].z.abs() > 0.9 && pts[i].z > ztop - 0.01)
        .map(|i| local(&pts[i]))
        .collect();
    let top_spans = top.len() >= o.min_face_points
        && (0..2).all(|k| {
            let (a, b) = top
                .iter()
                .fold((f32::MAX, f32::MIN), |(a, b), l| (a.min(l[k]), b.max(l[k])));
            b - a >= o.min_top_span * size[k]
        });
    let mut depth_from_completion = false;
    if !top_spans && face_points.iter().any(|&k| k < o.min_face_points) {
        // One face seen head-on: its normal's axis is the depth the views leave open. The
        // completer's points of the object give it, between their `COMPLETION_TRIM` quantiles.
        let seen = (0..2).find(|&k| face_points[k] >= o.min_face_points);
        let depth = seen.and_then(|k| {
            let along: Vec<f32> = completion.iter().map(|p| local(p)[k]).collect();
            completed_extent(along, (lo[k], hi[k]), o).map(|(a, b)| (k, a, b))
        });
        let Some((k, a, b)) = depth else {
            return Err(format!(
                "faces seen with {} and {} points (both need {}) and the top not seen across: \
                 the depth is unknown{}",
                face_points[0],
                face_points[1],
                o.min_face_points,
                if seen.is_some() {
                    " and the completion does not give it"
                } else {
                    ""
                }
            ));
        };
        lo[k] = a;
        hi[k] = b;
        size = hi - lo;
        depth_from_completion = true;
    }
    if size.max() > o.max_side_m {
        return Err(format!(
            "{:.2} m on a side (at most {:.2})",
            size.max(),
            o.max_side_m
        ));
    }
    let mut d: Vec<f32> = side
        .iter()
        .map(|&i| {
            let l = local(&pts[i]);
            (l.x - lo.x)
                .abs()
                .min((hi.x - l.x).abs())
                .min((l.y - lo.y).abs())
                .min((hi.y - l.y).abs())
        })
        .collect();
    d.sort_by(f32::total_cmp);
    let residual_m = d[(d.len() * 4 / 5).min(d.len() - 1)];
    if residual_m > o.max_residual_m {
        return Err(format!(
            "side points {:.1} mm off the rectangle (80%; at most {:.1})",
            residual_m * 1e3,
            o.max_residual_m * 1e3
        ));
    }
    let mid = (lo + hi) / 2.0;
    let centre = u * mid.x + v * mid.y;
    let (zlo, zhi) = pts
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), p| (a.min(p.z), b.max(p.z)));
    Ok(Cuboid {
        center: [centre.x, centre.y],
        yaw,
        size: [size.x, size.y],
        z: [zlo, zhi],
        concentration,
        face_points,
        residual_m,
        depth_from_completion,
    })
}

/// The extent `seen` (observed) widened by a completion's coordinates `along` the same axis,
/// between their [`COMPLETION_TRIM`] quantiles; `None` when the completion has fewer than
/// `min_face_points` points or the extent stays under `min_completed_depth_m`.
fn completed_extent(
    mut along: Vec<f32>,
    seen: (f32, f32),
    o: &CuboidOptions,
) -> Option<(f32, f32)> {
    if along.len() < o.min_face_points {
        return None;
    }
    along.sort_by(f32::total_cmp);
    let at = |q: f32| along[((along.len() - 1) as f32 * q).round() as usize];
    let (a, b) = (
        seen.0.min(at(COMPLETION_TRIM)),
        seen.1.max(at(1.0 - COMPLETION_TRIM)),
    );
    (b - a >= o.min_completed_depth_m).then_some((a, b))
}

/// Points on the cuboid's four sides and top, every `step` (levelled frame).
fn sample_cuboid(b: &Cuboid, step: f32) -> Vec<Point3<f32>> {
    let (u, v) = (
        Vector2::new(b.yaw.cos(), b.yaw.sin()),
        Vector2::new(-b.yaw.sin(), b.yaw.cos()),
    );
    let c = Vector2::new(b.center[0], b.center[1]);
    let (hx, hy) = (b.size[0] / 2.0, b.size[1] / 2.0);
    let at = |a: f32, bb: f32, z: f32| {
        let p = c + u * a + v * bb;
        Point3::new(p.x, p.y, z)
    };
    let steps = |len: f32| ((len / step).ceil() as usize).max(1);
    let mut out = Vec::new();
    let (nz, nx, ny) = (steps(b.z[1] - b.z[0]), steps(b.size[0]), steps(b.size[1]));
    for k in 0..=nz {
        let z = b.z[0] + (b.z[1] - b.z[0]) * k as f32 / nz as f32;
        for i in 0..=nx {
            let a = -hx + b.size[0] * i as f32 / nx as f32;
            out.push(at(a, -hy, z));
            out.push(at(a, hy, z));
        }
        for j in 1..ny {
            let bb = -hy + b.size[1] * j as f32 / ny as f32;
            out.push(at(-hx, bb, z));
            out.push(at(hx, bb, z));
        }
    }
    for i in 1..nx {
        for j in 1..ny {
            out.push(at(
                -hx + b.size[0] * i as f32 / nx as f32,
                -hy + b.size[1] * j as f32 / ny as f32,
                b.z[1],
            ));
        }
    }
    out
}

/// Replaces the generated points of each instance of `ids` that fits an upright cuboid (see the
/// module docs) by the cuboid's surface, standing on what `ground` shows under it.
pub fn cuboid_instances(
    observed: &PointCloud,
    generated: &PointCloud,
    ground: &Ground,
    ids: &BTreeSet<u16>,
    o: &CuboidOptions,
) -> (PointCloud, Vec<CuboidRecord>) {
    let mut records = Vec::new();
    let back = ground.level().inverse();
    let own = ground.observed_by_instance(ids);
    let gen_inst = generated.instance.as_deref().unwrap_or(&[]);
    let mut replaced: BTreeSet<u32> = BTreeSet::new();
    let mut surface = PointCloud::default();
    for &id in ids {
        let idx = own.get(&id).map(Vec::as_slice).unwrap_or(&[]);
        let pts: Vec<Point3<f32>> = idx.iter().map(|&i| ground.observed(i)).collect();
        let normals = if pts.len() > o.normal_neighbours {
            estimate_normals(&pts, o.normal_neighbours).unwrap_or_default()
        } else {
            Vec::new()
        };
        let normals = if normals.len() == pts.len() {
            normals
        } else {
            vec![Vector3::zeros(); pts.len()]
        };
        let completion: Vec<Point3<f32>> = gen_inst
            .iter()
            .zip(&generated.positions)
            .filter(|(&g, _)| g == id as u32)
            .map(|(_, p)| ground.level() * p)
            .collect();
        let mut fit = match fit_cuboid(&pts, &normals, &completion, o) {
            Ok(f) => f,
            Err(why) => {
                records.push(CuboidRecord {
                    instance_id: id,
                    fit: None,
                    reason: format!("kept the completion: {why}"),
                });
                continue;
            }
        };
        let r = fit.size[0].hypot(fit.size[1]) / 2.0;
        let support = ground.support_under(
            id as u32,
            Point2::new(fit.center[0] - r, fit.center[1] - r),
            Point2::new(fit.center[0] + r, fit.center[1] + r),
            fit.z[0] - o.max_drop_m,
            fit.z[0] + 0.01,
        );
        if let Some(z) = support {
            fit.z[0] = z.min(fit.z[0]);
        }
        let samples = sample_cuboid(&fit, o.sample_m);
        let n = samples.len();
        surface.append(&fitted_surface(
            &samples,
            &back,
            id,
            &pts,
            idx,
            observed,
            (CUBOID_CONFIDENCE, fit.residual_m),
        ));
        replaced.insert(id as u32);
        let dropped = gen_inst.iter().filter(|&&g| g == id as u32).count();
        records.push(CuboidRecord {
            instance_id: id,
            reason: format!(
                "{dropped} generated points replaced by {n} on a {:.3} x {:.3} x {:.3} m box \
                 (residual {:.1} mm{}{})",
                fit.size[0],
                fit.size[1],
                fit.z[1] - fit.z[0],
                fit.residual_m * 1e3,
                if support.is_some() {
                    ", standing on the surface below"
                } else {
                    ""
                },
                if fit.depth_from_completion {
                    ", the depth across its one seen face the completion's"
                } else {
                    ""
                }
            ),
            fit: Some(fit),
        });
    }
    if replaced.is_empty() {
        return (generated.clone(), records);
    }
    let keep: Vec<usize> = (0..generated.len())
        .filter(|&i| !gen_inst.get(i).is_some_and(|g| replaced.contains(g)))
        .collect();
    let mut out = generated.select(&keep);
    out.append(&surface);
    (out, records)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The observed faces of an upright box (centre, yaw, size) seen from the corner between
    /// its -u and -v faces, and its top, every 4 mm, with their normals.
    fn seen_box(
        c: (f32, f32),
        yaw: f32,
        size: (f32, f32, f32),
        both_faces: bool,
    ) -> (Vec<Point3<f32>>, Vec<Vector3<f32>>) {
        let (u, v) = (
            Vector2::new(yaw.cos(), yaw.sin()),
            Vector2::new(-yaw.sin(), yaw.cos()),
        );
        let c = Vector2::new(c.0, c.1);
        let (mut p, mut n) = (Vec::new(), Vec::new());
        let mut push = |a: f32, b: f32, z: f32, nn: Vector3<f32>| {
            let q = c + u * a + v * b;
            p.push(Point3::new(q.x, q.y, 0.7 + z));
            n.push(nn);
        };
        let grid = |len: f32| (0..=((len / 0.004) as usize)).map(move |k| k as f32 * 0.004);
        for z in grid(size.2) {
            for a in grid(size.0) {
                push(
                    a - size.0 / 2.0,
                    -size.1 / 2.0,
                    z,
                    Vector3::new(-v.x, -v.y, 0.0),
                );
            }
            if both_faces {
                for b in grid(size.1) {
                    push(
                        -size.0 / 2.0,
                        b - size.1 / 2.0,
                        z,
                        Vector3::new(-u.x, -u.y, 0.0),
                    );
                }
            }
        }
        for a in grid(size.0) {
            for b in grid(size.1) {
                push(a - size.0 / 2.0, b - size.1 / 2.0, size.2, Vector3::z());
            }
        }
        (p, n)
    }

    #[test]
    fn a_box_seen_at_an_angle_is_fitted_and_one_face_is_not_enough() {
        let o = CuboidOptions::default();
        let (p, n) = seen_box((0.1, -0.2), 0.5, (0.2, 0.07, 0.25), true);
        let b = fit_cuboid(&p, &n, &[], &o).expect("a box");
        assert!((b.yaw - 0.5).abs() < 0.01, "yaw {}", b.yaw);
        assert!((b.size[0] - 0.2).abs() < 0.005 && (b.size[1] - 0.07).abs() < 0.005);
        assert!((b.center[0] - 0.1).abs() < 0.003 && (b.center[1] + 0.2).abs() < 0.003);
        let (p, n) = seen_box((0.1, -0.2), 0.5, (0.2, 0.07, 0.25), false);
        // One face and the top: the top fixes the depth.
        let b = fit_cuboid(&p, &n, &[], &o).expect("a box from one face and its top");
        assert!((b.size[1] - 0.07).abs() < 0.005);
        // One face without the top (seen from level with it): no depth.
        let (p, n): (Vec<_>, Vec<_>) = p.iter().zip(&n).filter(|(_, m)| m.z < 0.5).unzip();
        let why = fit_cuboid(&p, &n, &[], &o).unwrap_err();
        assert!(why.contains("depth is unknown"), "{why}");
        // A completer's far side gives it: its points 6-7 cm behind the face, strays trimmed.
        let (u, v) = (
            Vector2::new(0.5f32.cos(), 0.5f32.sin()),
            Vector2::new(-0.5f32.sin(), 0.5f32.cos()),
        );
        let far: Vec<Point3<f32>> = (0..200)
            .map(|k| {
                let q = Vector2::new(0.1, -0.2)
                    + u * (-0.1 + 0.2 * (k % 20) as f32 / 19.0)
                    + v * (0.029 + 0.006 * (k % 7) as f32 / 6.0 + if k < 4 { 0.3 } else { 0.0 });
                Point3::new(q.x, q.y, 0.7 + 0.1 * (k / 20) as f32 / 10.0)
            })
            .collect();
        let b = fit_cuboid(&p, &n, &far, &o).expect("the completion's depth");
        assert!(b.depth_from_completion);
        assert!((b.size[1] - 0.07).abs() < 0.005, "{:?}", b.size);
        assert!((b.size[0] - 0.2).abs() < 0.005, "{:?}", b.size);
        // A completion no deeper than the face itself gives nothing.
        let flat: Vec<Point3<f32>> = p.iter().take(100).copied().collect();
        let why = fit_cuboid(&p, &n, &flat, &o).unwrap_err();
        assert!(why.contains("completion does not give it"), "{why}");
    }

    #[test]
    fn a_cylinder_is_no_box() {
        let (mut p, mut n) = (Vec::new(), Vec::new());
        for k in 0..60 {
            let t = (-170.0 + k as f32 * 2.7).to_radians();
            for j in 0..30 {
                p.push(Point3::new(
                    0.04 * t.cos(),
                    0.04 * t.sin(),
                    0.7 + j as f32 * 0.004,
                ));
                n.push(Vector3::new(t.cos(), t.sin(), 0.0));
            }
        }
        let why = fit_cuboid(&p, &n, &[], &CuboidOptions::default()).unwrap_err();
        assert!(why.contains("rectangle"), "{why}");
    }

    /// The stage puts the hidden far faces where the box is and stands it on the table's fill.
    #[test]
    fn the_hidden_faces_of_a_box_are_completed_to_the_table() {
        let (p, _) = seen_box((0.0, 0.0), 0.3, (0.16, 0.08, 0.2), true);
        // Seen from 0.75 m up: the lowest 5 cm hidden behind something in front.
        let p: Vec<Point3<f32>> = p.into_iter().filter(|q| q.z > 0.75).collect();
        let mut observed = PointCloud::from_positions(p);
        observed.instance = Some(vec![1; observed.len()]);
        let mut generated = PointCloud::from_positions(vec![Point3::new(0.3, 0.3, 0.8); 10]);
        generated.instance = Some(vec![1; 10]);
        let mut fill = PointCloud::from_positions(
            (0..1600)
                .map(|j| {
                    Point3::new(
                        -0.2 + (j % 40) as f32 * 0.01,
                        -0.2 + (j / 40) as f32 * 0.01,
                        0.7,
                    )
                })
                .collect(),
        );
        fill.instance = Some(vec![2; fill.len()]);
        let (out, records) = cuboid_instances(
            &observed,
            &generated,
            &Ground::new(&observed, &fill, Vector3::z()).unwrap(),
            &[1].into(),
            &CuboidOptions::default(),
        );
        assert!(records[0].fit.is_some(), "{records:?}");
        assert!(out
            .positions
            .iter()
            .all(|q| (q - Point3::new(0.3, 0.3, 0.8)).norm() > 0.01));
        let zmin = out.positions.iter().map(|q| q.z).fold(f32::MAX, f32::min);
        assert!((zmin - 0.7).abs() < 0.003, "{zmin}");
        // The far corner (+u, +v), never seen, is on the surface (the 4 mm grid of the seen
        // faces stops up to 4 mm short of their edges).
        let (u, v) = (
            Vector2::new(0.3f32.cos(), 0.3f32.sin()),
            Vector2::new(-0.3f32.sin(), 0.3f32.cos()),
        );
        let far = u * 0.08 + v * 0.04;
        assert!(out
            .positions
            .iter()
            .any(|q| (Vector2::new(q.x, q.y) - far).norm() < 0.006 && (q.z - 0.8).abs() < 0.004));
    }

    /// `pts` moved along the sight line from `eye` by noise of standard deviation `sigma`
    /// (a sensor's axial noise; a fixed pseudo-random sequence).
    fn axial_noise(pts: &[Point3<f32>], eye: Point3<f32>, sigma: f32) -> Vec<Point3<f32>> {
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut uniform = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f32 / (1u64 << 53) as f32
        };
        pts.iter()
            .map(|p| {
                // The sum of four uniforms: near enough a Gaussian, standard deviation 1.
                let g = ((0..4).map(|_| uniform()).sum::<f32>() - 2.0) * 3f32.sqrt();
                p + (p - eye).normalize() * (g * sigma)
            })
            .collect()
    }

    /// The structured-light model's axial noise at about 1.5 m (3 mm): the faces' normals turn
    /// by several degrees, and the box is still a box.
    #[test]
    fn a_box_under_a_sensors_axial_noise_is_fitted() {
        let (p, _) = seen_box((0.0, 0.0), 0.4, (0.06, 0.05, 0.15), true);
        let eye = Point3::new(-1.0, -0.8, 1.9);
        let noisy = axial_noise(&p, eye, 0.003);
        let o = CuboidOptions::default();
        let normals = estimate_normals(&noisy, o.normal_neighbours).unwrap();
        let b = fit_cuboid(&noisy, &normals, &[], &o).expect("a noisy box");
        assert!((b.yaw - 0.4).abs() < 0.05, "yaw {}", b.yaw);
        let mut size = b.size;
        size.sort_by(f32::total_cmp);
        assert!(
            (size[0] - 0.05).abs() < 0.012 && (size[1] - 0.06).abs() < 0.012,
            "{size:?}"
        );
    }

    /// A faceted (hexagonal or octagonal) bottle's body seen from one side, noisy alike: its
    /// faces' normals do not agree with one rectangle.
    #[test]
    fn a_faceted_body_under_noise_is_no_box() {
        for facets in [6usize, 8] {
            let (mut p, mut n) = (Vec::new(), Vec::new());
            let (r, step) = (0.035f32, 0.004f32);
            let half = std::f32::consts::PI / facets as f32;
            let apothem = r * half.cos();
            // The faces turned towards the camera at -y (a half-circle of them).
            for f in 0..facets {
                let a = f as f32 * 2.0 * half - std::f32::consts::FRAC_PI_2 + 0.2;
                let normal = Vector2::new(a.cos(), a.sin());
                if normal.y > 0.1 {
                    continue;
                }
                let along = Vector2::new(-normal.y, normal.x);
                let w = 2.0 * r * half.sin();
                let k = (w / step) as i32;
                for i in 0..=k {
                    let q = normal * apothem + along * (-w / 2.0 + i as f32 * step);
                    for j in 0..40 {
                        p.push(Point3::new(q.x, q.y, 0.7 + j as f32 * step));
                        n.push(Vector3::new(normal.x, normal.y, 0.0));
                    }
                }
            }
            let noisy = axial_noise(&p, Point3::new(0.0, -1.2, 1.9), 0.003);
            let o = CuboidOptions::default();
            let normals = estimate_normals(&noisy, o.normal_neighbours).unwrap();
            assert!(
                fit_cuboid(&noisy, &normals, &[], &o).is_err(),
                "{facets} facets"
            );
            assert!(
                fit_cuboid(&p, &n, &[], &o).is_err(),
                "{facets} facets, exact"
            );
        }
    }
}
