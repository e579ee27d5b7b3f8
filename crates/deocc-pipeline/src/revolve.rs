//! Stage: revolve. Much of what a robot picks up is a solid of revolution standing upright: cans,
//! bottles, cups, jars, vases. Their observed side is an arc of circles about one vertical axis,
//! and that arc fixes the hidden back to a few millimetres, far better than a completer working
//! on a 64-pixel crop (on pickup-v1 the completers' generated points lie a median 1.3-1.9 cm
//! from the true surface, and the cans they complete come out 1-3 cm too wide).
//!
//! For each instance a completer of the chain completed (at least one accepted completion), its
//! observed points are levelled (`up` becomes +z) and get PCA
//! normals; the side points (normals within 60 degrees of horizontal) are cut into `slice_m`
//! slices. One vertical axis and a radius per slice are fitted by robust (Huber) Gauss-Newton
//! with the radii projected out (each slice's radius is its mean distance to the axis). The fit
//! is accepted only when it is a solid of revolution beyond doubt:
//! - at least `min_points` side points in at least two slices,
//! - the 80th percentile of the side points' distance to the surface at most `max_rms_m` or
//!   `max_rms_fraction` of the radius, whichever is larger,
//! - the normals point away from the axis: median angle to the radial direction at most
//!   `max_median_angle_deg` and its 80th percentile at most `max_p80_angle_deg` (a box's faces
//!   fit a circle loosely, but their normals do not turn with it),
//! - the observed arc spans at least `min_arc_deg` about the axis (a short arc leaves the radius
//!   uncertain), and every radius lies in `[min_radius_m, max_radius_m]`.
//!
//! With fewer side points than `min_points` (only the top shows: a can behind a taller box),
//! the top's rim is fitted instead (`fit_top`) and the object taken for a straight cylinder,
//! when the rim is at least `min_top_radius_m` in radius and spans `min_top_arc_deg`.
//!
//! With `revolve_outline` (off by default: docs/decisions.md, "A revolved solid no wider than
//! its outline", has why) an accepted fit wider than the object's outline is narrowed to it. A
//! sensor's axial noise, smoothed by the depth front end, flattens the arc on a can's flanks and
//! fits it several millimetres too wide (cans +4.9 mm median on pickup-v2's tuning scenes under
//! the structured-light model; a 35 mm can then no longer fits an 85 mm gripper), but the mask's
//! edge against the background behind it does not move with the depth. The rays from the
//! cameras past that edge ([`outline_rays`]) lie one radius from the axis; [`refit_to_outline`]
//! fits the axis and one offset to every radius to them and to the side points facing a camera
//! (where the smoothing does not bias the depth), and keeps a narrower fit only: the outline
//! bounds the body from outside, and a mug's handle widens it.
//!
//! An accepted instance's generated points (the completer's, the support stage's) are replaced by
//! the fitted surface, sampled every `sample_m` from what it stands on to its highest observed
//! point. What it stands on is [`support::support_height`] under the solid's widest radius (plus
//! [`SUPPORT_MARGIN_M`]) among other objects' observed points and the planes' fill: a table seen
//! or filled under a bottle of which only the neck shows, where a completer's points may stop
//! short of it or reach below it; without such a support, the instance's lowest observed or
//! generated point; a height
//! without observed side points takes the radius of the nearest slice that has them, except below
//! a lowest slice narrower than `min_top_radius_m` (a bottle's neck: it says nothing of the body),
//! where the completer's points at that height, about the fitted axis, may widen it. The samples
//! carry the rules provenance, the colour of the nearest observed point and confidence
//! [`REVOLVE_CONFIDENCE`]; the carving stage then keeps only those every view agrees are hidden.
//! Other objects' generated points more than [`INSIDE_M`] inside an accepted solid are dropped
//! (an occluder's guessed far side reaching into the can behind it).
//! Posed scenes only (it needs gravity).

use std::collections::{BTreeMap, BTreeSet};

use deocc_geometry::normals::estimate_normals;
use deocc_geometry::{KdIndex, PointCloud, Provenance};
use nalgebra::{Point2, Point3, Rotation3, Vector2, Vector3};

use crate::support::Ground;
use serde::{Deserialize, Serialize};

/// How far inside an accepted solid another object's generated point must lie to be dropped.
pub const INSIDE_M: f32 = 0.003;

/// A solid's support is searched under its widest radius plus this.
pub const SUPPORT_MARGIN_M: f32 = 0.02;

/// The least inset of a fitted surface's samples towards the axis before the views check it
/// ([`RevolveOptions::max_seen_through_fraction`]).
pub const SEEN_THROUGH_INSET_M: f32 = 0.004;

/// Confidence of a point on an accepted surface of revolution.
pub const REVOLVE_CONFIDENCE: f32 = 0.9;

/// Settings of the revolve stage (metres, degrees).
#[derive(Debug, Clone, Copy)]
pub struct RevolveOptions {
    pub slice_m: f32,
    pub min_points: usize,
    pub max_rms_m: f32,
    pub max_rms_fraction: f32,
    pub max_median_angle_deg: f32,
    pub max_p80_angle_deg: f32,
    pub min_arc_deg: f32,
    pub min_radius_m: f32,
    pub max_radius_m: f32,
    pub sample_m: f32,
    /// Neighbours per normal estimate.
    pub normal_neighbours: usize,
    /// Without enough side points, the top's rim: at least this radius (a narrow top says
    /// nothing of the body below it: a bottle's neck), ...
    pub min_top_radius_m: f32,
    /// ... this residual (80th percentile, or `max_rms_fraction` of the radius),
    pub max_top_residual_m: f32,
    /// ... and an observed rim spanning this many degrees about the axis.
    pub min_top_arc_deg: f32,
    /// How far inside the true rim the observed cloud's rim points lie (its voxels' centroids
    /// sit about a quarter voxel inside an edge).
    pub rim_inset_m: f32,
    /// The support under a solid is searched at most this far below its observed bottom.
    pub max_drop_m: f32,
    /// A fit whose sampled surface, pulled in by 10% of its radius (at least
    /// [`SEEN_THROUGH_INSET_M`]), the views see through at more than this share of its samples
    /// is refused (1 = never): the sensor measured the table or the wall behind where the solid
    /// would be. A flask's broad face fits a circle far wider than the flask.
    pub max_seen_through_fraction: f32,
    /// With the views' outline ([`outline_rays`]), an accepted fit's axis and radii are refitted
    /// to at least this many outline rays at its side's heights and its side points within
    /// `front_deg` of facing a camera ([`refit_to_outline`]); 0 = never.
    pub min_outline_rays: usize,
    pub front_deg: f32,
}

impl Default for RevolveOptions {
    fn default() -> Self {
        Self {
            slice_m: 0.01,
            min_points: 40,
            max_rms_m: 0.003,
            max_rms_fraction: 0.08,
            max_median_angle_deg: 8.0,
            max_p80_angle_deg: 15.0,
            min_arc_deg: 40.0,
            min_radius_m: 0.008,
            max_radius_m: 0.2,
            sample_m: 0.004,
            normal_neighbours: 16,
            min_top_radius_m: 0.02,
            max_top_residual_m: 0.002,
            min_top_arc_deg: 90.0,
            rim_inset_m: 0.00125,
            max_drop_m: 0.5,
            max_seen_through_fraction: 1.0,
            min_outline_rays: 0,
            front_deg: 35.0,
        }
    }
}

/// A fitted upright solid of revolution, in the levelled frame (`up` = +z).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Revolution {
    /// The axis' position on the levelled ground plane (x, y).
    pub axis: [f32; 2],
    /// (slice bottom z, radius) of each slice with observed side points, bottom up.
    pub radii: Vec<(f32, f32)>,
    /// The 80th percentile of the side points' distance to the surface.
    pub residual_m: f32,
    pub median_angle_deg: f32,
    pub p80_angle_deg: f32,
    pub arc_deg: f32,
    pub side_points: usize,
    /// Fitted to the top's rim (too little side observed): one radius for the whole height.
    pub from_top: bool,
    /// The share of the sampled surface the views see through, when it was measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seen_through_fraction: Option<f32>,
    /// The offset the views' outline gave every radius (the axis moved with it), when it was
    /// refitted ([`RevolveOptions::min_outline_rays`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outline_offset_m: Option<f32>,
}

impl Revolution {
    /// The radius at height `z`: that of the slice holding `z`, else of the nearest slice.
    pub fn radius_at(&self, z: f32, slice_m: f32) -> f32 {
        self.radii
            .iter()
            .min_by(|a, b| {
                let da = (z - (a.0 + slice_m / 2.0)).abs();
                let db = (z - (b.0 + slice_m / 2.0)).abs();
                da.total_cmp(&db)
            })
            .map(|r| r.1)
            .unwrap_or(0.0)
    }
}

/// An accepted solid while the stage runs: its instance, axis and (height, radius) rows bottom up.
type Solid = (u32, Vector2<f32>, Vec<(f32, f32)>);

/// What the stage made of one instance, for the run report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RevolveRecord {
    pub instance_id: u16,
    /// The fit, when it was accepted.
    pub fit: Option<Revolution>,
    /// Why it was not, or what replaced what.
    pub reason: String,
}

/// The axis (x, y) of circles about one centre through `xy`, a radius per slice (`slices[i]` of
/// `n_slices`): Kasa's algebraic circle to start, then robust (Huber, 2 mm) Gauss-Newton with the
/// radii projected out (each slice's radius is its weighted mean distance to the axis).
fn fit_axis(
    xy: &[Vector2<f32>],
    slices: &[usize],
    n_slices: usize,
) -> Result<Vector2<f32>, String> {
    // x^2 + y^2 = 2ax + 2by + c.
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for q in xy {
        let row = nalgebra::Vector3::new(q.x as f64, q.y as f64, 1.0);
        ata += row * row.transpose();
        atb += row * (q.norm_squared() as f64);
    }
    let sol = ata.lu().solve(&atb).ok_or("the points are collinear")?;
    let mut c = Vector2::new((sol.x / 2.0) as f32, (sol.y / 2.0) as f32);
    if !(c.x.is_finite() && c.y.is_finite()) {
        return Err("no circle through the points".into());
    }

    let delta = 0.002f32;
    let mut weights = vec![1.0f32; xy.len()];
    let mut radius = vec![0.0f32; n_slices];
    for _ in 0..30 {
        // Radii and mean radial directions per slice at the current axis (weighted).
        let mut sum_d = vec![0.0f32; n_slices];
        let mut sum_u = vec![Vector2::zeros(); n_slices];
        let mut sum_w = vec![0.0f32; n_slices];
        let us: Vec<(f32, Vector2<f32>)> = xy
            .iter()
            .map(|q| {
                let v = q - c;
                let d = v.norm().max(1e-9);
                (d, v / d)
            })
            .collect();
        for (i, &(d, u)) in us.iter().enumerate() {
            let k = slices[i];
            sum_d[k] += weights[i] * d;
            sum_u[k] += u * weights[i];
            sum_w[k] += weights[i];
        }
        for k in 0..n_slices {
            radius[k] = if sum_w[k] > 0.0 {
                sum_d[k] / sum_w[k]
            } else {
                0.0
            };
        }
        // Gauss-Newton on the axis with the radii projected out: residual d_i - r_k,
        // Jacobian -(u_i - mean u_k).
        let mut h = nalgebra::Matrix2::<f32>::zeros();
        let mut g = Vector2::<f32>::zeros();
        for (i, &(d, u)) in us.iter().enumerate() {
            let k = slices[i];
            let e = d - radius[k];
            weights[i] = if e.abs() <= delta {
                1.0
            } else {
                delta / e.abs()
            };
            let j = -(u - sum_u[k] / sum_w[k].max(1e-9));
            h += j * j.transpose() * weights[i];
            g += j * (weights[i] * e);
        }
        let Some(step) = (h + nalgebra::Matrix2::identity() * 1e-9).lu().solve(&(-g)) else {
            break;
        };
        c += step;
        if step.norm() < 1e-6 {
            break;
        }
    }
    if !(c.x.is_finite() && c.y.is_finite()) {
        return Err("the axis fit diverged".into());
    }
    Ok(c)
}

/// Fits an upright solid of revolution to `points` (levelled: +z up); `Err(why)` when they are
/// not one beyond doubt (see the module docs).
pub fn fit_revolution(
    points: &[Point3<f32>],
    cameras: &[Point3<f32>],
    o: &RevolveOptions,
) -> Result<Revolution, String> {
    if points.len() < 12 {
        return Err(format!("{} observed points", points.len()));
    }
    let normals = estimate_normals(points, o.normal_neighbours).map_err(|e| e.to_string())?;
    let side: Vec<(Point3<f32>, Vector2<f32>)> = points
        .iter()
        .zip(&normals)
        .filter(|(_, n)| n.norm_squared() > 0.5 && n.z.abs() < 0.5)
        .map(|(p, n)| (*p, Vector2::new(n.x, n.y).normalize()))
        .collect();
    if side.len() < o.min_points {
        return fit_top(points, &normals, cameras, o)
            .map_err(|why| format!("{} side points, and the top: {why}", side.len()));
    }
    let z0 = side.iter().map(|(p, _)| p.z).fold(f32::MAX, f32::min);
    let slice_of = |z: f32| ((z - z0) / o.slice_m).floor().max(0.0) as usize;
    let slices: Vec<usize> = side.iter().map(|(p, _)| slice_of(p.z)).collect();
    let n_slices = slices.iter().max().map(|m| m + 1).unwrap_or(0);
    let xy: Vec<Vector2<f32>> = side.iter().map(|(p, _)| Vector2::new(p.x, p.y)).collect();

    let c = fit_axis(&xy, &slices, n_slices)?;

    // Final residuals, angles and arc at the fitted axis.
    let mut counts = vec![0usize; n_slices];
    let mut sum_d = vec![0.0f32; n_slices];
    for (i, q) in xy.iter().enumerate() {
        counts[slices[i]] += 1;
        sum_d[slices[i]] += (q - c).norm();
    }
    let radii: Vec<(f32, f32)> = (0..n_slices)
        .filter(|&k| counts[k] >= 3)
        .map(|k| (z0 + k as f32 * o.slice_m, sum_d[k] / counts[k] as f32))
        .collect();
    if radii.len() < 2 {
        return Err(format!("side points in {} slice(s)", radii.len()));
    }
    let r_of = |k: usize| sum_d[k] / counts[k].max(1) as f32;
    // The 80th percentile of the absolute residual: a slice across a bottle's shoulder mixes two
    // radii, which an RMS would count against the whole fit.
    let mut abs_res: Vec<f32> = xy
        .iter()
        .enumerate()
        .map(|(i, q)| ((q - c).norm() - r_of(slices[i])).abs())
        .collect();
    let rms = percentile(&mut abs_res, 0.8);
    let mut angles: Vec<f32> = xy
        .iter()
        .zip(&side)
        .map(|(q, (_, n))| {
            let u = (q - c).normalize();
            n.dot(&u).abs().min(1.0).acos().to_degrees()
        })
        .collect();
    let (median_angle, p80_angle) = (percentile(&mut angles, 0.5), percentile(&mut angles, 0.8));
    let arc = arc_deg(&xy, c, 2);
    let r_med = {
        let mut r: Vec<f32> = radii.iter().map(|r| r.1).collect();
        r.sort_by(f32::total_cmp);
        r[r.len() / 2]
    };
    let fit = Revolution {
        axis: [c.x, c.y],
        radii,
        residual_m: rms,
        median_angle_deg: median_angle,
        p80_angle_deg: p80_angle,
        arc_deg: arc,
        side_points: side.len(),
        from_top: false,
        seen_through_fraction: None,
        outline_offset_m: None,
    };
    if let Some(&(_, r)) = fit
        .radii
        .iter()
        .find(|(_, r)| !(*r >= o.min_radius_m && *r <= o.max_radius_m))
    {
        return Err(format!(
            "a radius of {:.3} m (allowed {}-{} m)",
            r, o.min_radius_m, o.max_radius_m
        ));
    }
    let rms_limit = o.max_rms_m.max(o.max_rms_fraction * r_med);
    if rms > rms_limit {
        return Err(format!(
            "residual (80th percentile) {:.1} mm over {:.1} mm",
            rms * 1e3,
            rms_limit * 1e3
        ));
    }
    if median_angle > o.max_median_angle_deg || p80_angle > o.max_p80_angle_deg {
        return Err(format!(
            "normals {median_angle:.0} deg (median) / {p80_angle:.0} deg (80%) off the radial \
             direction"
        ));
    }
    if arc < o.min_arc_deg {
        return Err(format!(
            "an observed arc of {arc:.0} deg (at least {} needed)",
            o.min_arc_deg
        ));
    }
    Ok(fit)
}

/// The `f` quantile of `v` (sorted in place; not empty).
fn percentile(v: &mut [f32], f: f32) -> f32 {
    v.sort_by(f32::total_cmp);
    v[((v.len() - 1) as f32 * f).round() as usize]
}

/// Degrees about `c` covered by `xy`: the 10-degree sectors holding at least `min_points`.
fn arc_deg(xy: &[Vector2<f32>], c: Vector2<f32>, min_points: usize) -> f32 {
    let mut bins = [0usize; 36];
    for q in xy {
        let v = q - c;
        bins[(((v.y.atan2(v.x).to_degrees() + 180.0) / 10.0) as usize).min(35)] += 1;
    }
    bins.iter().filter(|&&b| b >= min_points).count() as f32 * 10.0
}

/// An upright cylinder from the rim of a flat top (levelled `points` with their `normals`), for
/// an object of which little more than the top shows (a can behind a box). In each view (camera
/// centres, levelled) the rim is what the top's points reach farthest from the camera in 4 mm
/// lanes across the line of sight: the near part of the top's outline may be an occluder's edge,
/// the far part is the rim.
fn fit_top(
    points: &[Point3<f32>],
    normals: &[Vector3<f32>],
    cameras: &[Point3<f32>],
    o: &RevolveOptions,
) -> Result<Revolution, String> {
    let z_top = points.iter().map(|p| p.z).fold(f32::MIN, f32::max);
    let top: Vec<Vector2<f32>> = points
        .iter()
        .zip(normals)
        .filter(|(p, n)| n.z.abs() > 0.9 && p.z >= z_top - o.slice_m)
        .map(|(p, _)| Vector2::new(p.x, p.y))
        .collect();
    if top.len() < 12 {
        return Err(format!("{} points on it", top.len()));
    }
    let centroid = top.iter().sum::<Vector2<f32>>() / top.len() as f32;
    let lane = 0.004f32;
    let mut rim: BTreeSet<usize> = BTreeSet::new();
    for cam in cameras {
        let Some(d) = (centroid - Vector2::new(cam.x, cam.y)).try_normalize(1e-6) else {
            continue;
        };
        let across = Vector2::new(-d.y, d.x);
        let mut far: BTreeMap<i64, (f32, usize)> = BTreeMap::new();
        for (i, q) in top.iter().enumerate() {
            let l = (q.dot(&across) / lane).floor() as i64;
            let depth = q.dot(&d);
            let e = far.entry(l).or_insert((f32::MIN, i));
            if depth > e.0 {
                *e = (depth, i);
            }
        }
        rim.extend(far.values().map(|&(_, i)| i));
    }
    if rim.len() < 6 {
        return Err(format!("{} rim points", rim.len()));
    }
    let xy: Vec<Vector2<f32>> = rim.iter().map(|&i| top[i]).collect();
    let c = fit_axis(&xy, &vec![0; xy.len()], 1)?;
    let dist: Vec<f32> = xy.iter().map(|q| (q - c).norm()).collect();
    let r = dist.iter().sum::<f32>() / dist.len() as f32 + o.rim_inset_m;
    let mut res: Vec<f32> = dist.iter().map(|d| (d + o.rim_inset_m - r).abs()).collect();
    let p80 = percentile(&mut res, 0.8);
    let arc = arc_deg(&xy, c, 1);
    if !(r >= o.min_top_radius_m && r <= o.max_radius_m) {
        return Err(format!(
            "a rim of radius {r:.3} m (allowed {}-{} m)",
            o.min_top_radius_m, o.max_radius_m
        ));
    }
    let limit = o.max_top_residual_m.max(o.max_rms_fraction * r);
    if p80 > limit {
        return Err(format!(
            "rim residual {:.1} mm over {:.1} mm",
            p80 * 1e3,
            limit * 1e3
        ));
    }
    if arc < o.min_top_arc_deg {
        return Err(format!(
            "a rim arc of {arc:.0} deg (at least {} needed)",
            o.min_top_arc_deg
        ));
    }
    if (centroid - c).norm() > r {
        return Err("the top's points lie outside its rim".into());
    }
    Ok(Revolution {
        axis: [c.x, c.y],
        radii: vec![(z_top - o.slice_m, r)],
        residual_m: p80,
        median_angle_deg: 0.0,
        p80_angle_deg: 0.0,
        arc_deg: arc,
        side_points: 0,
        from_top: true,
        seen_through_fraction: None,
        outline_offset_m: None,
    })
}

/// A ray past an object's outline (world frame): from a camera's centre through the boundary
/// between the outermost pixel of the object's mask in an image row and the background beside it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutlineRay {
    pub origin: Point3<f32>,
    pub dir: Vector3<f32>,
    /// The angle one pixel spans there (radians): the outline's own uncertainty.
    pub pixel_rad: f32,
}

/// The outline rays of an instance in every view ([`outline_rays`]): what the revolve stage
/// refits a solid's radius to.
pub type Outline<'a> = &'a (dyn Fn(u16) -> Vec<OutlineRay> + Sync);

/// How far (pixels) outward from a mask's outermost pixel the background is looked for.
pub const OUTLINE_LOOK_PX: u32 = 8;

/// A measured pixel beside the outline this much nearer than the object's own depth in that row
/// is an occluder's edge, not the object's outline.
pub const OUTLINE_OCCLUDER_M: f32 = 0.02;

/// The outline rays of instance `id` in `frames` (their instance maps, depth and cameras): in
/// each image row, the leftmost and the rightmost pixel of its mask, where the first measured
/// pixel outward (within [`OUTLINE_LOOK_PX`], not of the object) is no nearer than the object's
/// median depth in the row less [`OUTLINE_OCCLUDER_M`]: the object's own outline against what
/// lies behind it. Where an occluder cuts the mask, or the image's edge, or nothing is measured
/// beside it (a shadow band whose far side is unknown), the row's side gives no ray. Each ray
/// passes through the pixel boundary (a mask of pixel centres puts the true outline there on
/// average).
pub fn outline_rays(frames: &[deocc_io::scene::Frame], id: u16) -> Vec<OutlineRay> {
    let mut out = Vec::new();
    for f in frames {
        let Some(map) = f.instances.as_ref() else {
            continue;
        };
        let (w, h) = (map.width, map.height);
        if (f.depth.width(), f.depth.height()) != (w, h) {
            continue;
        }
        let rot = f.camera.world_from_camera.rotation;
        let centre = f.camera.center();
        for v in 0..h {
            let row: Vec<u32> = (0..w).filter(|&u| map.get(u, v) == id).collect();
            let (Some(&first), Some(&last)) = (row.first(), row.last()) else {
                continue;
            };
            let mut own: Vec<f32> = row
                .iter()
                .map(|&u| f.depth.get(u, v))
                .filter(|&z| z > 0.0)
                .collect();
            if own.is_empty() {
                continue;
            }
            own.sort_by(f32::total_cmp);
            let z_own = own[own.len() / 2];
            for (edge, step, boundary) in
                [(first, -1i64, first as f32), (last, 1, last as f32 + 1.0)]
            {
                let mut clear = false;
                for k in 1..=OUTLINE_LOOK_PX as i64 {
                    let u = edge as i64 + step * k;
                    if u < 0 || u >= w as i64 {
                        break;
                    }
                    let z = f.depth.get(u as u32, v);
                    if map.get(u as u32, v) == id || z <= 0.0 {
                        continue;
                    }
                    clear = z >= z_own - OUTLINE_OCCLUDER_M;
                    break;
                }
                if clear {
                    let p = f.camera.intrinsics.unproject(boundary, v as f32 + 0.5, 1.0);
                    out.push(OutlineRay {
                        origin: centre,
                        dir: rot * p.coords,
                        pixel_rad: 1.0 / f.camera.intrinsics.fx(),
                    });
                }
            }
        }
    }
    out
}

/// Refits an accepted fit's axis and one offset to all its radii to the outline rays (levelled)
/// and the side points facing a camera (levelled `points`, `cameras`): the rays' distance to the
/// axis is the radius at their height, and the points on the front of the arc lie on it. Both
/// stay true under a sensor's axial noise, which the depth front end's smoothing turns into a
/// flatter arc on the flanks and a fit too wide; the outline does not depend on depth at all.
/// Robust (Huber, 2 mm) Gauss-Newton, each group weighing as much as the other. The outline
/// bounds the body from outside (a mug's handle widens it, nothing narrows it) to within half a
/// pixel, so a fit is only narrowed, and only to the outline plus half a pixel at the rays'
/// distance (a bottle fitted 1-2 mm wide on pickup-v2's tuning scenes was otherwise narrowed
/// 1 mm below its true radius, median). `None` (the fit left as it is) with fewer than
/// `min_outline_rays` rays at the side slices' heights, a fit within half a pixel of the
/// outline or wider, or one narrower by more than a third of the median radius.
fn refit_to_outline(
    fit: &Revolution,
    points: &[Point3<f32>],
    rays: &[OutlineRay],
    cameras: &[Point3<f32>],
    o: &RevolveOptions,
) -> Option<(Vector2<f32>, f32)> {
    if fit.from_top || fit.radii.is_empty() || cameras.is_empty() {
        return None;
    }
    let c0 = Vector2::new(fit.axis[0], fit.axis[1]);
    let z_lo = fit.radii[0].0;
    let z_hi = fit.radii[fit.radii.len() - 1].0 + o.slice_m;
    // Rays: the 2-D line (origin, unit direction), the side of it the axis lies on, the height
    // of their closest approach to the axis.
    let mut slack: Vec<f32> = Vec::new();
    let lines: Vec<(Vector2<f32>, Vector2<f32>, f32, f32)> = rays
        .iter()
        .filter_map(|ray| {
            let (org, d) = (&ray.origin, &ray.dir);
            let dxy = Vector2::new(d.x, d.y);
            let n2 = dxy.norm_squared();
            if n2 < 1e-6 {
                return None;
            }
            let oxy = Vector2::new(org.x, org.y);
            let lambda = (c0 - oxy).dot(&dxy) / n2;
            let z = org.z + lambda * d.z;
            let t = dxy / n2.sqrt();
            let s = t.x * (c0.y - oxy.y) - t.y * (c0.x - oxy.x);
            // Rows across the top's far rim or the base's near rim pass inside the solid, and
            // nearest to the axis above or below its side.
            let side_height = z >= z_lo && z <= z_hi;
            if !(lambda > 0.0 && side_height) {
                return None;
            }
            slack.push(0.5 * ray.pixel_rad * lambda * d.norm());
            Some((oxy, t, s.signum(), z))
        })
        .collect();
    if lines.len() < o.min_outline_rays {
        return None;
    }
    let r_of = |z: f32| fit.radius_at(z, o.slice_m);
    let cos_front = o.front_deg.to_radians().cos();
    let front: Vec<(Vector2<f32>, f32)> = points
        .iter()
        .filter(|p| p.z >= z_lo && p.z <= z_hi)
        .filter_map(|p| {
            let q = Vector2::new(p.x, p.y);
            let radial = (q - c0).try_normalize(1e-6)?;
            if ((q - c0).norm() - r_of(p.z)).abs() > 0.01 {
                return None;
            }
            cameras
                .iter()
                .any(|cam| {
                    (Vector2::new(cam.x, cam.y) - q)
                        .try_normalize(1e-6)
                        .is_some_and(|to_cam| radial.dot(&to_cam) >= cos_front)
                })
                .then_some((q, p.z))
        })
        .collect();
    if front.len() < o.min_points / 2 {
        return None;
    }
    let (wl, wp) = (1.0 / lines.len() as f32, 1.0 / front.len() as f32);
    let huber = |e: f32| {
        if e.abs() <= 0.002 {
            1.0
        } else {
            0.002 / e.abs()
        }
    };
    let (mut c, mut delta) = (c0, 0.0f32);
    for _ in 0..30 {
        let mut hm = nalgebra::Matrix3::<f32>::zeros();
        let mut g = Vector3::<f32>::zeros();
        let mut add = |j: Vector3<f32>, e: f32, w: f32| {
            let w = w * huber(e);
            hm += j * j.transpose() * w;
            g += j * (w * e);
        };
        for &(oxy, t, side, z) in &lines {
            let s = side * (t.x * (c.y - oxy.y) - t.y * (c.x - oxy.x));
            add(
                Vector3::new(-side * t.y, side * t.x, -1.0),
                s - (r_of(z) + delta),
                wl,
            );
        }
        for &(q, z) in &front {
            let v = q - c;
            let d = v.norm().max(1e-9);
            add(
                Vector3::new(-v.x / d, -v.y / d, -1.0),
                d - (r_of(z) + delta),
                wp,
            );
        }
        let step = (hm + nalgebra::Matrix3::identity() * 1e-7)
            .lu()
            .solve(&(-g))?;
        c += Vector2::new(step.x, step.y);
        delta += step.z;
        if step.norm() < 1e-6 {
            break;
        }
    }
    let r_min = fit.radii.iter().map(|r| r.1).fold(f32::MAX, f32::min);
    let r_med = {
        let mut r: Vec<f32> = fit.radii.iter().map(|r| r.1).collect();
        r.sort_by(f32::total_cmp);
        r[r.len() / 2]
    };
    if !(c.x.is_finite()
        && c.y.is_finite()
        && -delta <= r_med / 3.0
        && (c - c0).norm() <= r_med / 2.0)
    {
        return None;
    }
    // The outline is known to half a pixel: narrower by less says nothing. Beyond it, the fit
    // is narrowed to the outline plus that half pixel, its axis moved in proportion.
    slack.sort_by(f32::total_cmp);
    let half_pixel = slack[slack.len() / 2];
    let kept = delta + half_pixel;
    if kept >= 0.0 || r_min + kept < o.min_radius_m {
        return None;
    }
    Some((c0 + (c - c0) * (kept / delta), kept))
}

/// [`refit_to_outline`] on the world-frame `rays` (levelled here by `level`, like `points` and
/// `cameras`), applied to `fit` when it narrows it.
fn narrow_to_outline(
    fit: &mut Revolution,
    points: &[Point3<f32>],
    rays: &[OutlineRay],
    (level, cameras): (&Rotation3<f32>, &[Point3<f32>]),
    o: &RevolveOptions,
) {
    let rays: Vec<OutlineRay> = rays
        .iter()
        .map(|r| OutlineRay {
            origin: level * r.origin,
            dir: level * r.dir,
            ..*r
        })
        .collect();
    if let Some((c, delta)) = refit_to_outline(fit, points, &rays, cameras, o) {
        fit.axis = [c.x, c.y];
        for r in &mut fit.radii {
            r.1 += delta;
        }
        fit.outline_offset_m = Some(delta);
    }
}

/// Measures `fit`'s sampled surface (levelled `samples`, `back` to the world) against the views
/// and records the share seen through in it; the record refusing it when the share is over the
/// limit.
fn check_seen_through(
    fit: &mut Revolution,
    id: u16,
    samples: &[Point3<f32>],
    back: &Rotation3<f32>,
    seen_through: Option<SeenThrough<'_>>,
    o: &RevolveOptions,
) -> Option<RevolveRecord> {
    let measure = seen_through?;
    // Each sample pulled towards the axis by 10% of its radius (at least 4 mm): a fit true to a
    // few millimetres puts its outline samples just outside the silhouette, where the views see
    // the table behind; a solid far wider than the object (a flask's broad face fitted with one
    // circle) stays outside it.
    let axis = Vector2::new(fit.axis[0], fit.axis[1]);
    let world: Vec<Point3<f32>> = samples
        .iter()
        .map(|p| {
            let d = Vector2::new(p.x, p.y) - axis;
            let r = d.norm();
            let pulled = if r > 1e-6 {
                axis + d * ((r - (0.1 * r).max(SEEN_THROUGH_INSET_M)).max(0.0) / r)
            } else {
                axis
            };
            back * Point3::new(pulled.x, pulled.y, p.z)
        })
        .collect();
    let share = measure(&world);
    fit.seen_through_fraction = Some(share);
    (share > o.max_seen_through_fraction).then(|| RevolveRecord {
        instance_id: id,
        fit: None,
        reason: format!(
            "kept the completion: the views see through {:.0}% of the fitted solid (radius \
             {:.3} m; limit {:.0}%)",
            100.0 * share,
            fit.radii[fit.radii.len() / 2].1,
            100.0 * o.max_seen_through_fraction
        ),
    })
}

/// The share of a fitted surface's samples (world frame) that the views see through: what the
/// revolve stage checks a fit against ([`RevolveOptions::max_seen_through_fraction`]).
pub type SeenThrough<'a> = &'a (dyn Fn(&[Point3<f32>]) -> f32 + Sync);

/// What the revolve stage knows of the views: the cameras' centres, and when given, how much of
/// a fit they see through and each instance's outline.
pub type Views<'a> = (
    &'a [Point3<f32>],
    Option<SeenThrough<'a>>,
    Option<Outline<'a>>,
);

/// Replaces the generated points of the instances `ids` that are upright solids of revolution
/// (see the module docs). `observed` gives the fit; `generated` holds what the completers and the
/// support stage made; `seen_through` (when given) measures a fit against the views. Returns the
/// new generated cloud and a record per instance.
pub fn revolve_instances(
    observed: &PointCloud,
    generated: &PointCloud,
    ground: &Ground,
    ids: &BTreeSet<u16>,
    (cameras, seen_through, outline): Views<'_>,
    o: &RevolveOptions,
) -> (PointCloud, Vec<RevolveRecord>) {
    let mut records = Vec::new();
    let level = *ground.level();
    let back = level.inverse();
    let cameras: Vec<Point3<f32>> = cameras.iter().map(|c| level * c).collect();
    let own = ground.observed_by_instance(ids);
    let gen_inst = generated.instance.as_deref().unwrap_or(&[]);
    let mut replaced: BTreeSet<u32> = BTreeSet::new();
    let mut solids: Vec<Solid> = Vec::new();
    let mut surface = PointCloud::default();
    for &id in ids {
        let idx = own.get(&id).map(Vec::as_slice).unwrap_or(&[]);
        let pts: Vec<Point3<f32>> = idx.iter().map(|&i| ground.observed(i)).collect();
        let mut fit = match fit_revolution(&pts, &cameras, o) {
            Ok(f) => f,
            Err(why) => {
                records.push(RevolveRecord {
                    instance_id: id,
                    fit: None,
                    reason: format!("kept the completion: {why}"),
                });
                continue;
            }
        };
        if let Some(outline) = outline.filter(|_| o.min_outline_rays > 0) {
            narrow_to_outline(&mut fit, &pts, &outline(id), (&level, &cameras), o);
        }
        let gen_pts: Vec<Point3<f32>> = generated
            .positions
            .iter()
            .zip(gen_inst)
            .filter(|(_, &g)| g == id as u32)
            .map(|(p, _)| level * p)
            .collect();
        let obs_z = pts.iter().map(|p| p.z);
        // The bottom is what the solid stands on when a support shows under it (the table below
        // a bottle of which only the neck shows; not a completer's guess, which may reach below
        // the table or stop short of it), else the lowest observed or generated point.
        let r_max = fit.radii.iter().map(|r| r.1).fold(0.0, f32::max) + SUPPORT_MARGIN_M;
        let seen_bottom = obs_z.clone().fold(f32::MAX, f32::min);
        let support = ground.support_under(
            id as u32,
            Point2::new(fit.axis[0] - r_max, fit.axis[1] - r_max),
            Point2::new(fit.axis[0] + r_max, fit.axis[1] + r_max),
            seen_bottom - o.max_drop_m,
            seen_bottom + SUPPORT_MARGIN_M / 2.0,
        );
        let bottom = support.unwrap_or_else(|| {
            obs_z
                .clone()
                .chain(gen_pts.iter().map(|p| p.z))
                .fold(f32::MAX, f32::min)
        });
        let top = obs_z.fold(f32::MIN, f32::max);
        // A narrow lowest slice (a bottle's neck) says nothing of the body below it: there the
        // completer's points, about the fitted axis, may widen the surface.
        let lowest = fit.radii[0];
        let neck = !fit.from_top && lowest.1 < o.min_top_radius_m;
        let axis = Vector2::new(fit.axis[0], fit.axis[1]);
        let below = |z: f32| -> Option<f32> {
            if !neck || z >= lowest.0 {
                return None;
            }
            let mut d: Vec<f32> = gen_pts
                .iter()
                .filter(|p| (p.z - z).abs() <= o.slice_m / 2.0)
                .map(|p| (Vector2::new(p.x, p.y) - axis).norm())
                .collect();
            if d.len() < 8 {
                return None;
            }
            d.sort_by(f32::total_cmp);
            Some(d[d.len() / 2].min(o.max_radius_m))
        };
        let (samples, rows) = sample_surface(&fit, bottom, top, &below, o);
        if let Some(refused) = check_seen_through(&mut fit, id, &samples, &back, seen_through, o) {
            records.push(refused);
            continue;
        }
        solids.push((id as u32, axis, rows));
        let n = samples.len();
        surface.append(&fitted_surface(
            &samples,
            &back,
            id,
            &pts,
            idx,
            observed,
            (REVOLVE_CONFIDENCE, fit.residual_m),
        ));
        replaced.insert(id as u32);
        let dropped = gen_inst.iter().filter(|&&g| g == id as u32).count();
        records.push(RevolveRecord {
            instance_id: id,
            reason: format!(
                "{dropped} generated points replaced by {n} on a surface of revolution{} (radius \
                 {:.3} m, residual {:.1} mm, arc {:.0} deg, from z {bottom:.3}{})",
                match (fit.from_top, fit.outline_offset_m) {
                    (true, _) => " fitted to the top's rim".to_string(),
                    (false, Some(d)) => format!(" narrowed {:.1} mm to its outline", -d * 1e3),
                    (false, None) => String::new(),
                },
                fit.radii[fit.radii.len() / 2].1,
                fit.residual_m * 1e3,
                fit.arc_deg,
                if support.is_some() {
                    " where it stands"
                } else {
                    ", its lowest point"
                }
            ),
            fit: Some(fit),
        });
    }
    if replaced.is_empty() {
        return (generated.clone(), records);
    }
    // Another object's generated points inside an accepted solid (more than `INSIDE_M` inside
    // its surface) are impossible: the solid was seen. They go too (an occluder's guessed far
    // side reaching into the can behind it).
    let inside = |i: usize| -> bool {
        let p = level * generated.positions[i];
        let own = gen_inst.get(i).copied();
        solids.iter().any(|(id, axis, rows)| {
            if Some(*id) == own || rows.is_empty() {
                return false;
            }
            let (lo, hi) = (rows[0].0, rows[rows.len() - 1].0);
            if p.z < lo || p.z > hi {
                return false;
            }
            let k = (((p.z - lo) / o.sample_m).round() as usize).min(rows.len() - 1);
            (Vector2::new(p.x, p.y) - axis).norm() < rows[k].1 - INSIDE_M
        })
    };
    let keep: Vec<usize> = (0..generated.len())
        .filter(|&i| !gen_inst.get(i).is_some_and(|g| replaced.contains(g)) && !inside(i))
        .collect();
    let mut out = generated.select(&keep);
    out.append(&surface);
    (out, records)
}

/// Points on the fitted surface from `bottom` to `top`, every `sample_m` in height and around.
/// Below the observed slices `below(z)`, when it answers, widens the radius. Also returns each
/// row's (height, radius).
fn sample_surface(
    fit: &Revolution,
    bottom: f32,
    top: f32,
    below: &dyn Fn(f32) -> Option<f32>,
    o: &RevolveOptions,
) -> (Vec<Point3<f32>>, Vec<(f32, f32)>) {
    let mut out = Vec::new();
    let mut radii = Vec::new();
    if top.partial_cmp(&bottom) != Some(std::cmp::Ordering::Greater) {
        return (out, radii);
    }
    let rows = ((top - bottom) / o.sample_m).ceil() as usize + 1;
    for k in 0..rows {
        let z = (bottom + k as f32 * o.sample_m).min(top);
        let r = fit.radius_at(z, o.slice_m);
        let r = below(z).map_or(r, |b| b.max(r));
        radii.push((z, r));
        let around = ((std::f32::consts::TAU * r / o.sample_m).ceil() as usize).max(8);
        for j in 0..around {
            let t = j as f32 * std::f32::consts::TAU / around as f32;
            out.push(Point3::new(
                fit.axis[0] + r * t.cos(),
                fit.axis[1] + r * t.sin(),
                z,
            ));
        }
    }
    (out, radii)
}

/// A fitted surface's `samples` (levelled; `back` returns them to the world) as instance `id`'s
/// points: the rules provenance, `confidence`, the fit's residual `error_m` as each point's
/// expected error, and the colour of the instance's nearest observed point (levelled `pts`,
/// indices `idx` into `observed`).
pub(crate) fn fitted_surface(
    samples: &[Point3<f32>],
    back: &Rotation3<f32>,
    id: u16,
    pts: &[Point3<f32>],
    idx: &[usize],
    observed: &PointCloud,
    (confidence, error_m): (f32, f32),
) -> PointCloud {
    let n = samples.len();
    PointCloud {
        positions: samples.iter().map(|p| back * p).collect(),
        colors: Some(nearest_colors(pts, idx, observed, samples)),
        instance: Some(vec![id as u32; n]),
        generated: Some(vec![Provenance::Rules.code(); n]),
        confidence: Some(vec![confidence; n]),
        expected_error: Some(vec![error_m.max(0.0); n]),
        ..Default::default()
    }
}

/// The colour of the nearest observed point of the instance (levelled `pts`, indices `idx`
/// into `observed`) for each sample; grey without colours.
fn nearest_colors(
    pts: &[Point3<f32>],
    idx: &[usize],
    observed: &PointCloud,
    samples: &[Point3<f32>],
) -> Vec<[u8; 3]> {
    let (Some(colors), Ok(index)) = (observed.colors.as_deref(), KdIndex::build(pts)) else {
        return vec![[128; 3]; samples.len()];
    };
    samples
        .iter()
        .map(|s| colors[idx[index.nearest(s).index as usize]])
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a z-up test scene's objects stand on.
    fn ground(observed: &PointCloud, fill: &PointCloud) -> Ground {
        Ground::new(observed, fill, Vector3::z()).unwrap()
    }

    /// Points of the side of an upright solid whose radius at height z is `r(z)`, over the arc
    /// of angles [a0, a1] (degrees), every 4 mm.
    fn side(
        centre: (f32, f32),
        r: impl Fn(f32) -> f32,
        h: f32,
        a0: f32,
        a1: f32,
    ) -> Vec<Point3<f32>> {
        let mut out = Vec::new();
        let mut z = 0.0;
        while z <= h {
            let rz = r(z);
            let n = ((a1 - a0).to_radians() * rz / 0.004).ceil() as usize;
            for j in 0..=n {
                let t = (a0 + (a1 - a0) * j as f32 / n as f32).to_radians();
                out.push(Point3::new(
                    centre.0 + rz * t.cos(),
                    centre.1 + rz * t.sin(),
                    0.7 + z,
                ));
            }
            z += 0.004;
        }
        out
    }

    #[test]
    fn the_front_arc_of_a_can_fixes_its_axis_and_radius() {
        let pts = side((0.3, -0.2), |_| 0.033, 0.12, -150.0, -30.0);
        let fit = fit_revolution(&pts, &[], &RevolveOptions::default()).expect("a can");
        assert!((fit.axis[0] - 0.3).abs() < 0.001 && (fit.axis[1] + 0.2).abs() < 0.001);
        for &(_, r) in &fit.radii {
            assert!((r - 0.033).abs() < 0.001, "radius {r}");
        }
        assert!(fit.arc_deg >= 100.0, "arc {}", fit.arc_deg);
    }

    #[test]
    fn a_bottle_keeps_a_radius_per_height() {
        // A body, a shoulder from 7 to 9 cm and a neck.
        let bottle = |z: f32| 0.035 - 0.02 * ((z - 0.07) / 0.02).clamp(0.0, 1.0);
        let pts = side((0.0, 0.0), bottle, 0.14, -160.0, -20.0);
        let fit = fit_revolution(&pts, &[], &RevolveOptions::default()).expect("a bottle");
        let o = RevolveOptions::default();
        assert!((fit.radius_at(0.72, o.slice_m) - 0.035).abs() < 0.002);
        assert!((fit.radius_at(0.83, o.slice_m) - 0.015).abs() < 0.002);
    }

    #[test]
    fn a_box_corner_is_not_a_solid_of_revolution() {
        // Two faces of an 8 x 8 cm box seen across its corner.
        let mut pts = Vec::new();
        for k in 0..30 {
            let z = 0.7 + k as f32 * 0.004;
            for j in 0..20 {
                let s = j as f32 * 0.004;
                pts.push(Point3::new(s, 0.0, z));
                pts.push(Point3::new(0.0, s, z));
            }
        }
        let why = fit_revolution(&pts, &[], &RevolveOptions::default()).unwrap_err();
        assert!(
            why.contains("normals") || why.contains("residual") || why.contains("radius"),
            "{why}"
        );
    }

    /// The top of an upright cylinder of radius `r` at (0.2, 0.1), 12 cm high, as a 5 mm voxel
    /// grid (each cell's centroid), with what lies nearer the camera than `cut` m beyond the
    /// axis hidden (a box in front).
    fn top_only(r: f32, cut: f32) -> Vec<Point3<f32>> {
        let mut out = Vec::new();
        let n = 400;
        let mut cells: BTreeMap<(i32, i32), (Vector2<f32>, f32)> = BTreeMap::new();
        for i in 0..n {
            for j in 0..n {
                let q = Vector2::new(
                    -r + 2.0 * r * i as f32 / n as f32,
                    -r + 2.0 * r * j as f32 / n as f32,
                );
                // The camera looks along +y: the near side is y < cut.
                if q.norm() > r || q.y < cut {
                    continue;
                }
                let key = ((q.x / 0.005).floor() as i32, (q.y / 0.005).floor() as i32);
                let e = cells.entry(key).or_insert((Vector2::zeros(), 0.0));
                e.0 += q;
                e.1 += 1.0;
            }
        }
        for (sum, k) in cells.values() {
            out.push(Point3::new(0.2 + sum.x / k, 0.1 + sum.y / k, 0.82));
        }
        out
    }

    #[test]
    fn a_can_of_which_only_the_top_shows_is_fitted_to_its_rim() {
        let camera = [Point3::new(0.2, -1.1, 1.5)];
        let pts = top_only(0.033, -0.01);
        let fit = fit_revolution(&pts, &camera, &RevolveOptions::default()).expect("a can top");
        assert!(fit.from_top);
        let (dx, dy) = (fit.axis[0] - 0.2, fit.axis[1] - 0.1);
        assert!((dx * dx + dy * dy).sqrt() < 0.002, "axis off by {dx}, {dy}");
        let r = fit.radius_at(0.75, 0.01);
        assert!((r - 0.033).abs() < 0.002, "radius {r}");
        // A bottle's mouth says nothing of its body.
        let why = fit_revolution(&top_only(0.012, -0.01), &camera, &RevolveOptions::default())
            .unwrap_err();
        assert!(why.contains("radius"), "{why}");
        // Without a camera there is no rim to tell from an occluder's edge.
        assert!(fit_revolution(&pts, &[], &RevolveOptions::default()).is_err());
    }

    /// A bottle of which only the neck shows: the neck is revolved as seen, and below it the
    /// completer's wider body, about the fitted axis, sets the radius.
    #[test]
    fn below_a_neck_the_completers_body_sets_the_radius() {
        let neck = side((0.0, 0.0), |_| 0.014, 0.06, -160.0, -20.0);
        let mut observed = PointCloud::from_positions(
            neck.iter()
                .map(|p| Point3::new(p.x, p.y, p.z + 0.1))
                .collect(),
        );
        observed.instance = Some(vec![1; observed.len()]);
        // The completer's body: 3 cm, 1 to 9 cm above the table (at 0.7 m).
        let body = side((0.0, 0.0), |_| 0.03, 0.08, -180.0, 180.0);
        let mut generated = PointCloud::from_positions(
            body.iter()
                .map(|p| Point3::new(p.x, p.y, p.z + 0.01))
                .collect(),
        );
        generated.instance = Some(vec![1; generated.len()]);
        generated.generated = Some(vec![Provenance::Model.code(); generated.len()]);
        let (out, records) = revolve_instances(
            &observed,
            &generated,
            &ground(&observed, &PointCloud::default()),
            &[1].into(),
            (&[], None, None),
            &RevolveOptions::default(),
        );
        assert!(records[0].fit.is_some(), "{records:?}");
        let radius_near = |z: f32| {
            let d: Vec<f32> = out
                .positions
                .iter()
                .filter(|p| (p.z - z).abs() < 0.003)
                .map(|p| (p.x * p.x + p.y * p.y).sqrt())
                .collect();
            assert!(!d.is_empty(), "nothing at {z}");
            d.iter().sum::<f32>() / d.len() as f32
        };
        assert!((radius_near(0.75) - 0.03).abs() < 0.003);
        assert!((radius_near(0.83) - 0.014).abs() < 0.002);
    }

    /// A can of which only the upper part shows above the box in front of it stands on the
    /// table's fill, not on the box's face nor on a completer's guess of the box's far side.
    #[test]
    fn a_solid_stands_on_the_plane_below_it() {
        let mut observed = PointCloud::from_positions(
            side((0.0, 0.0), |_| 0.03, 0.06, -160.0, -20.0)
                .iter()
                .map(|p| Point3::new(p.x, p.y, p.z + 0.1))
                .collect(),
        );
        let n_can = observed.len();
        // The box's front face, a vertical sheet 4 cm in front of the can's axis.
        let face: Vec<Point3<f32>> = (0..30)
            .flat_map(|k| {
                (0..40).map(move |j| {
                    Point3::new(-0.08 + j as f32 * 0.004, -0.045, 0.7 + k as f32 * 0.004)
                })
            })
            .collect();
        let n_face = face.len();
        observed.append(&PointCloud::from_positions(face));
        observed.instance = Some(
            std::iter::repeat_n(1, n_can)
                .chain(std::iter::repeat_n(2, n_face))
                .collect(),
        );
        // The completer's guess of the box's far side, under the can's footprint at 0.75 m.
        let mut generated = PointCloud::from_positions(
            (0..400)
                .map(|j| {
                    Point3::new(
                        -0.04 + (j % 20) as f32 * 0.004,
                        -0.04 + (j / 20) as f32 * 0.002,
                        0.75,
                    )
                })
                .collect(),
        );
        generated.instance = Some(vec![2; generated.len()]);
        generated.generated = Some(vec![Provenance::Model.code(); generated.len()]);
        // The table's fill at 0.7 m.
        let mut fill = PointCloud::from_positions(
            (0..900)
                .map(|j| {
                    Point3::new(
                        -0.15 + (j % 30) as f32 * 0.01,
                        -0.15 + (j / 30) as f32 * 0.01,
                        0.7,
                    )
                })
                .collect(),
        );
        fill.instance = Some(vec![3; fill.len()]);
        let lowest = |fill: &PointCloud| {
            let (out, records) = revolve_instances(
                &observed,
                &generated,
                &ground(&observed, fill),
                &[1].into(),
                (&[], None, None),
                &RevolveOptions::default(),
            );
            assert!(records[0].fit.is_some(), "{records:?}");
            out.positions
                .iter()
                .zip(out.instance.as_deref().unwrap())
                .filter(|(_, &i)| i == 1)
                .map(|(p, _)| p.z)
                .fold(f32::MAX, f32::min)
        };
        let z = lowest(&fill);
        assert!((z - 0.7).abs() < 0.003, "the can starts at {z}");
        // Without the fill nothing under the can is a support: it starts where it was seen.
        let z = lowest(&PointCloud::default());
        assert!((z - 0.8).abs() < 0.003, "the can starts at {z}");
    }

    #[test]
    fn a_short_arc_is_refused() {
        let pts = side((0.0, 0.0), |_| 0.05, 0.1, -100.0, -80.0);
        let why = fit_revolution(&pts, &[], &RevolveOptions::default()).unwrap_err();
        assert!(why.contains("arc"), "{why}");
    }

    /// The stage replaces a can's generated points (too wide, as completers make them) by its
    /// true surface and leaves a box's alone.
    #[test]
    fn a_can_is_completed_on_its_axis_and_a_box_is_left_alone() {
        let mut observed =
            PointCloud::from_positions(side((0.3, 0.0), |_| 0.03, 0.1, -160.0, -20.0));
        let n_can = observed.len();
        let mut boxy = Vec::new();
        for k in 0..25 {
            for j in 0..20 {
                boxy.push(Point3::new(
                    -0.3 + j as f32 * 0.004,
                    -0.05,
                    0.7 + k as f32 * 0.004,
                ));
            }
        }
        let n_box = boxy.len();
        observed.append(&PointCloud::from_positions(boxy));
        observed.instance = Some(
            std::iter::repeat_n(1, n_can)
                .chain(std::iter::repeat_n(2, n_box))
                .collect(),
        );
        // The completer's guess: the far side 1.5 cm too far out, on both objects.
        let mut wrong = side((0.3, 0.0), |_| 0.045, 0.1, 20.0, 160.0);
        let n_wrong = wrong.len();
        wrong.extend((0..50).map(|j| Point3::new(-0.3 + j as f32 * 0.002, 0.02, 0.75)));
        // The box's guessed far side reaching into the can: impossible once the can is fitted.
        wrong.extend((0..5).map(|j| Point3::new(0.29 + j as f32 * 0.004, 0.0, 0.75)));
        let mut generated = PointCloud::from_positions(wrong);
        generated.instance = Some(
            std::iter::repeat_n(1, n_wrong)
                .chain(std::iter::repeat_n(2, 55))
                .collect(),
        );
        generated.generated = Some(vec![Provenance::Model.code(); generated.len()]);
        let ids: BTreeSet<u16> = [1, 2].into();
        let (out, records) = revolve_instances(
            &observed,
            &generated,
            &ground(&observed, &PointCloud::default()),
            &ids,
            (&[], None, None),
            &RevolveOptions::default(),
        );
        assert!(records[0].fit.is_some(), "{records:?}");
        assert!(records[1].fit.is_none(), "{records:?}");
        let inst = out.instance.as_deref().unwrap();
        let can: Vec<&Point3<f32>> = out
            .positions
            .iter()
            .zip(inst)
            .filter(|(_, &i)| i == 1)
            .map(|(p, _)| p)
            .collect();
        assert!(!can.is_empty());
        for p in &can {
            let r = ((p.x - 0.3).powi(2) + p.y.powi(2)).sqrt();
            assert!((r - 0.03).abs() < 0.002, "a can point at radius {r}");
        }
        // The back (y > 0) is there, and the box's generated points are untouched but for those
        // inside the can.
        assert!(can.iter().any(|p| p.y > 0.025));
        assert_eq!(inst.iter().filter(|&&i| i == 2).count(), 50);
        assert!(out
            .confidence
            .as_deref()
            .unwrap()
            .iter()
            .all(|c| (0.0..=1.0).contains(c)));
    }

    /// A frame of an upright can (instance 1, radius `r`, 12 cm high, axis at the origin)
    /// standing on a table (instance 2, z = 0), seen from 1.3 m up and 1.2 m away, ray-cast at
    /// pixel centres; with `occluder`, a box (instance 3) hides the can's left side.
    fn can_frame(r: f32, occluder: bool) -> deocc_io::scene::Frame {
        use deocc_geometry::camera::{look_at, Camera, Intrinsics};
        let intrinsics = Intrinsics::from_fov(640, 480, 40.0).unwrap();
        let pose = look_at(
            &Point3::new(0.0, -1.2, 1.3),
            &Point3::new(0.0, 0.0, 0.06),
            &Vector3::z(),
        )
        .unwrap();
        let camera = Camera {
            intrinsics,
            world_from_camera: pose,
        };
        let (w, h) = (intrinsics.width(), intrinsics.height());
        let eye = camera.center();
        let mut depth = vec![0.0f32; (w * h) as usize];
        let mut ids = vec![0u16; (w * h) as usize];
        for v in 0..h {
            for u in 0..w {
                let d = (camera.unproject_pixel(u, v, 1.0) - eye).normalize();
                let mut best = (f32::MAX, 0u16);
                // The table.
                if d.z < 0.0 {
                    best = (-eye.z / d.z, 2);
                }
                // The can's side and top.
                let (a, b, c) = (
                    d.x * d.x + d.y * d.y,
                    2.0 * (eye.x * d.x + eye.y * d.y),
                    eye.x * eye.x + eye.y * eye.y - r * r,
                );
                let disc = b * b - 4.0 * a * c;
                if disc >= 0.0 {
                    let t = (-b - disc.sqrt()) / (2.0 * a);
                    let z = eye.z + t * d.z;
                    if (0.0..=0.12).contains(&z) && t < best.0 {
                        best = (t, 1);
                    }
                }
                let t = (0.12 - eye.z) / d.z;
                let q = eye + d * t;
                if q.x * q.x + q.y * q.y <= r * r && t < best.0 {
                    best = (t, 1);
                }
                // A box in front, 5 cm wide and 40 cm high, covering x < -0.01.
                if occluder {
                    let t = (-0.1 - eye.y) / d.y;
                    let q = eye + d * t;
                    if (-0.06..=-0.01).contains(&q.x) && (0.0..=0.4).contains(&q.z) && t < best.0 {
                        best = (t, 3);
                    }
                }
                if best.1 != 0 {
                    let i = (v * w + u) as usize;
                    let p = eye + d * best.0;
                    depth[i] = camera.world_from_camera.inverse_transform_point(&p).z;
                    ids[i] = best.1;
                }
            }
        }
        deocc_io::scene::Frame {
            name: "can".into(),
            camera,
            rgb: image::RgbImage::new(w, h),
            depth: deocc_geometry::DepthMap::new(w, h, depth).unwrap(),
            instances: Some(deocc_io::images::InstanceMap {
                width: w,
                height: h,
                ids,
            }),
        }
    }

    /// The distance in the ground plane from the z axis to a ray's line (the radius of the
    /// upright cylinder about the origin it is tangent to), and the ray's height there.
    fn axis_distance(ray: &OutlineRay) -> (f32, f32) {
        let (o, d) = (&ray.origin, &ray.dir);
        let dxy = Vector2::new(d.x, d.y);
        let t = dxy.normalize();
        let lambda = -Vector2::new(o.x, o.y).dot(&dxy) / dxy.norm_squared();
        ((t.x * o.y - t.y * o.x).abs(), o.z + lambda * d.z)
    }

    /// The distances of the rays that pass the can's side (not its top's or its base's rim).
    fn side_distances(rays: &[OutlineRay]) -> Vec<f32> {
        rays.iter()
            .map(axis_distance)
            .filter(|&(_, z)| (0.0..=0.12).contains(&z))
            .map(|(d, _)| d)
            .collect()
    }

    #[test]
    fn outline_rays_graze_the_can_and_skip_an_occluders_edge() {
        let r = 0.035;
        let rays = outline_rays(&[can_frame(r, false)], 1);
        assert!(rays.len() >= 40, "{} rays", rays.len());
        let mut d = side_distances(&rays);
        let median = percentile(&mut d, 0.5);
        assert!(
            (median - r).abs() < 0.0008,
            "median distance {median} for radius {r}"
        );

        // Behind a box hiding its left side, the rays that remain are the right side's: none
        // passes through the can along the box's edge.
        let hidden = outline_rays(&[can_frame(r, true)], 1);
        assert!(
            !hidden.is_empty() && hidden.len() < rays.len() * 3 / 4,
            "{}",
            hidden.len()
        );
        for d in side_distances(&hidden) {
            assert!(d > r - 0.0025, "a ray {d} from the axis (2 mm pixels)");
        }
        // No instance, no rays.
        assert!(outline_rays(&[can_frame(r, false)], 7).is_empty());
    }

    #[test]
    fn the_outline_narrows_a_can_fitted_too_wide_and_never_widens_one() {
        let r = 0.035;
        let frame = can_frame(r, false);
        let cam = frame.camera.center();
        let rays = outline_rays(std::slice::from_ref(&frame), 1);
        let o = RevolveOptions {
            min_outline_rays: 6,
            ..Default::default()
        };
        // The front arc as a smoothed sensor leaves it: the flanks pulled towards the camera
        // (up to 6 mm), a flatter arc, which fits a wider can behind.
        let to_cam = Vector2::new(cam.x, cam.y).normalize();
        let mut pts = Vec::new();
        for p in side((0.0, 0.0), |_| r, 0.11, -160.0, -20.0) {
            let radial = Vector2::new(p.x, p.y).normalize();
            let off = 0.006 * (1.0 - radial.dot(&to_cam).max(0.0));
            pts.push(Point3::new(
                p.x + to_cam.x * off,
                p.y + to_cam.y * off,
                p.z - 0.7,
            ));
        }
        let fit = fit_revolution(&pts, &[cam], &o).expect("a can");
        let wide = fit.radius_at(0.05, o.slice_m);
        assert!(wide > r + 0.002, "the biased fit is {wide}, not too wide");
        let (c, delta) = refit_to_outline(&fit, &pts, &rays, &[cam], &o).expect("refitted");
        assert!(delta < 0.0);
        // To the outline plus half a pixel (1 mm here).
        let refitted = wide + delta;
        assert!(
            refitted > r - 0.0005 && refitted < r + 0.0015,
            "refitted {refitted} for {r}"
        );
        assert!(c.norm() < 0.002, "axis {c:?}");

        // A fit narrower than the outline (a mug's handle widens it) is left as it is.
        let narrow: Vec<Point3<f32>> = side((0.0, 0.0), |_| r - 0.004, 0.11, -160.0, -20.0)
            .into_iter()
            .map(|p| Point3::new(p.x, p.y, p.z - 0.7))
            .collect();
        let fit = fit_revolution(&narrow, &[cam], &o).expect("a narrow can");
        assert!(refit_to_outline(&fit, &narrow, &rays, &[cam], &o).is_none());
        // Too few rays: left as it is.
        assert!(refit_to_outline(&fit, &pts, &rays[..3], &[cam], &o).is_none());
    }
}
