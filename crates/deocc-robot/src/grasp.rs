//! Antipodal grasp candidates on a target's points, checked for collision against the whole
//! scene: GPD's candidate generation without its learned classifier.
//!
//! 1. The target's points are thinned to a voxel grid (3 mm) and get PCA normals (about 1 cm
//!    neighbourhoods).
//! 2. At each of up to `seeds` points the closing axis is the point's normal; the approach turns
//!    about it in `approaches` steps (approaches from below the horizon's `max_upward` are not
//!    tried) and the palm stands at `depths` from the seed.
//! 3. The target's points inside the closing region fix the opening (their extent along the
//!    closing axis plus `open_margin_m` each side, at most the aperture, at least `margin_m` each
//!    side) and the centring.
//!    No target point may come closer to the palm than `palm_clearance_m`.
//! 4. Each jaw needs `min_jaw_points` points within `jaw_band_m` of where it touches, and a share
//!    of them whose normal lies inside the friction cone (`friction_deg`) around the closing axis.
//! 5. No scene point may lie inside a finger or the palm, each grown by `collision_margin_m`
//!    (outwards and at the tips; the opening between the jaws stays as it is).
//! 6. The contact angle ([`closure_angle`], the evaluator's criterion on the planning cloud)
//!    must be inside the cone.
//! 7. Score = the geometric mean of the two jaws' in-cone shares, times a support term
//!    (min(1, points between the jaws / 60)), times 1 - angle / cone; sorted, non-maximum suppressed (3 cm and 30
//!    degrees) and cut to the top `top_k`.

use deocc_geometry::voxel::voxel_downsample;
use deocc_geometry::{normals::estimate_normals_with_index, KdIndex, PointCloud};
use nalgebra::{Point3, Rotation3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::gripper::{classify, Grasp, GripperConfig, Part};
use crate::RobotError;

/// Plans grasps on a target inside a scene. Implement it to plug in another planner.
pub trait GraspPlanner: Send + Sync {
    fn name(&self) -> &str;
    /// Grasps on `target` (its points, world frame), best first, checked against `scene` (every
    /// point of the scene, the target's included).
    fn plan(&self, scene: &[Point3<f32>], target: &[Point3<f32>])
        -> Result<Vec<Grasp>, RobotError>;
}

/// Why the antipodal planner's candidates were turned down: what a caller shows when a plan comes
/// back empty ("nothing to grasp, and why").
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PlanStats {
    /// Seed points tried (those with a usable normal).
    pub seeds: usize,
    /// Candidate poses scored: seeds x approaches x depths, less approaches from below.
    pub candidates: usize,
    /// No target point between the open jaws.
    pub no_contact: usize,
    /// The target's extent across the jaws is wider than the opening allows or thinner than a
    /// sheet.
    pub too_wide_or_thin: usize,
    /// A target point closer to the palm than the clearance.
    pub palm: usize,
    /// A jaw touches fewer points than it needs.
    pub jaw_points: usize,
    /// Under a quarter of a jaw's points have their normal inside the friction cone.
    pub friction_share: usize,
    /// The contact line leaves the friction cone.
    pub closure_angle: usize,
    /// A scene point inside a finger or the palm.
    pub collision: usize,
    /// Candidates that passed every check (before non-maximum suppression).
    pub accepted: usize,
}

impl PlanStats {
    fn add(mut self, o: Self) -> Self {
        self.seeds += o.seeds;
        self.candidates += o.candidates;
        self.no_contact += o.no_contact;
        self.too_wide_or_thin += o.too_wide_or_thin;
        self.palm += o.palm;
        self.jaw_points += o.jaw_points;
        self.friction_share += o.friction_share;
        self.closure_angle += o.closure_angle;
        self.collision += o.collision;
        self.accepted += o.accepted;
        self
    }

    fn count(&mut self, r: Reject) {
        match r {
            Reject::NoContact => self.no_contact += 1,
            Reject::WidthOrThin => self.too_wide_or_thin += 1,
            Reject::Palm => self.palm += 1,
            Reject::JawPoints => self.jaw_points += 1,
            Reject::FrictionShare => self.friction_share += 1,
            Reject::ClosureAngle => self.closure_angle += 1,
            Reject::Collision => self.collision += 1,
        }
    }

    /// The check that turned down most candidates, in words; `None` when nothing was tried or
    /// something passed.
    pub fn main_reason(&self) -> Option<&'static str> {
        if self.accepted > 0 {
            return None;
        }
        if self.candidates == 0 {
            return Some("no target point has a usable surface normal");
        }
        [
            (self.no_contact, "no target point between the jaws"),
            (
                self.too_wide_or_thin,
                "the target is wider than the gripper opens (or a thin sheet) across every closing axis tried",
            ),
            (self.palm, "the palm would touch the target"),
            (self.jaw_points, "too few target points under a jaw"),
            (
                self.friction_share,
                "the surface under the jaws is not facing them (normals outside the friction cone)",
            ),
            (self.closure_angle, "the contact line leaves the friction cone"),
            (
                self.collision,
                "every grasp that holds would collide with the scene (fingers or palm inside other points)",
            ),
        ]
        .into_iter()
        .max_by_key(|(n, _)| *n)
        .map(|(_, why)| why)
    }
}

/// Why one candidate was turned down.
#[derive(Debug, Clone, Copy)]
enum Reject {
    NoContact,
    WidthOrThin,
    Palm,
    JawPoints,
    FrictionShare,
    ClosureAngle,
    Collision,
}

/// The antipodal planner's settings (metres, degrees).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GraspOptions {
    pub gripper: GripperConfig,
    /// Voxel size the target is thinned to before sampling.
    pub voxel_m: f32,
    /// Neighbours per normal estimate (at 3 mm voxels about a 1 cm neighbourhood).
    pub normal_neighbours: usize,
    /// Seed points sampled on the target.
    pub seeds: usize,
    /// Approach directions tried about each closing axis.
    pub approaches: usize,
    /// Distances from the palm to the seed along the approach.
    pub depths: Vec<f32>,
    /// Half-angle of the friction cone a jaw's normals must fall in.
    pub friction_deg: f32,
    /// Points each jaw needs where it touches.
    pub min_jaw_points: usize,
    /// How far from a jaw's first contact a point still counts as under that jaw.
    pub jaw_band_m: f32,
    /// Least free space between each jaw and the target's points when the grasp is opened.
    pub margin_m: f32,
    /// Share of the target's points between the jaws, on each side, left out when the planner
    /// measures the target's extent across the jaws and places the jaws' contacts, and share
    /// that may come nearer the palm than `palm_clearance_m`: a sensor's
    /// axial noise puts a few points millimetres outside the true surface, and the extreme
    /// point alone would make a can that fits the gripper look wider than its opening
    /// (0.02 on pickup-v1 tuning scenes under the structured-light model).
    pub extent_trim: f32,
    /// The opening aimed for each side (up to the aperture): a cloud's hidden side is uncertain,
    /// so the gripper opens wider than the points need when it can.
    pub open_margin_m: f32,
    /// Least distance from the palm to the target's points between the jaws.
    pub palm_clearance_m: f32,
    /// Clearance kept between the fingers and palm and any scene point: the cloud samples a
    /// surface every few millimetres and a completed side is uncertain by as much, so a finger
    /// that slips between the points of an occluder's face would hit the face itself.
    pub collision_margin_m: f32,
    /// The expected error of a generated point where the cloud carries no better estimate
    /// ([`stated_errors`]; observed points: 0), metres. The planner treats each point as a ball
    /// of its expected error: the target's extent across the jaws is that of the balls (a
    /// finger may not close where the object could be) and no finger or palm may touch another
    /// point's ball, while the contacts are scored on the points themselves. 0 = off.
    pub generated_error_m: f32,
    /// The envelope from the cloud's own expected errors (its `expected_error`: GL-DoT's error
    /// head, a fitted surface's residual, a completer's stated estimate): each point is grown by
    /// this many times its expected error, in place of `generated_error_m` (0 = off; a cloud
    /// without expected errors falls back to `generated_error_m`).
    pub expected_error_scale: f32,
    /// Gravity's opposite in the cloud's frame (z up for the renderer's scenes).
    pub up: [f32; 3],
    /// Approaches with a larger upward component (moving up into the object) are not tried.
    pub max_upward: f32,
    /// Non-maximum suppression: a grasp closer than this and `nms_angle_deg` to a better one goes.
    pub nms_distance_m: f32,
    pub nms_angle_deg: f32,
    /// Grasps returned.
    pub top_k: usize,
}

impl Default for GraspOptions {
    fn default() -> Self {
        Self {
            gripper: GripperConfig::default(),
            voxel_m: 0.003,
            normal_neighbours: 16,
            seeds: 160,
            approaches: 12,
            depths: vec![0.015, 0.03, 0.045],
            friction_deg: 20.0,
            min_jaw_points: 6,
            jaw_band_m: 0.004,
            margin_m: 0.005,
            extent_trim: 0.02,
            open_margin_m: 0.02,
            palm_clearance_m: 0.01,
            collision_margin_m: 0.005,
            generated_error_m: 0.0,
            expected_error_scale: 0.0,
            up: [0.0, 0.0, 1.0],
            max_upward: 0.3,
            nms_distance_m: 0.03,
            nms_angle_deg: 30.0,
            top_k: 50,
        }
    }
}

impl GraspOptions {
    /// Most candidate grasps one call may score: `seeds x approaches x depths` (the defaults
    /// give 5,760). Beyond it a call would run for minutes to hours.
    pub const MAX_CANDIDATES: usize = 100_000;

    /// Every setting in its stated range (the error names it); see [`crate::range`].
    pub fn validate(&self) -> Result<(), RobotError> {
        use crate::range::{count, direction, real};
        self.gripper.validate()?;
        direction("up", self.up)?;
        real("voxel_m", self.voxel_m, 0.0005, 0.05, " m")?;
        count("normal_neighbours", self.normal_neighbours, 3, 64)?;
        count("seeds", self.seeds, 1, 5000)?;
        count("approaches", self.approaches, 1, 72)?;
        count("depths (entries)", self.depths.len(), 1, 16)?;
        for (k, &d) in self.depths.iter().enumerate() {
            real(
                &format!("depths[{k}]"),
                d,
                0.0,
                self.gripper.depth,
                " m (the finger's depth)",
            )?;
        }
        let candidates = self.seeds * self.approaches * self.depths.len();
        if candidates > Self::MAX_CANDIDATES {
            return Err(RobotError::Config(format!(
                "seeds x approaches x depths = {} x {} x {} = {candidates}: at most {} \
                 candidate grasps a call",
                self.seeds,
                self.approaches,
                self.depths.len(),
                Self::MAX_CANDIDATES
            )));
        }
        real("friction_deg", self.friction_deg, 0.1, 89.9, " degrees")?;
        count("min_jaw_points", self.min_jaw_points, 1, 1000)?;
        real("jaw_band_m", self.jaw_band_m, 0.0, 0.05, " m")?;
        real("margin_m", self.margin_m, 0.0, 0.05, " m")?;
        real("extent_trim", self.extent_trim, 0.0, 0.2, "")?;
        real("open_margin_m", self.open_margin_m, 0.0, 0.1, " m")?;
        real("palm_clearance_m", self.palm_clearance_m, 0.0, 0.1, " m")?;
        real(
            "collision_margin_m",
            self.collision_margin_m,
            0.0,
            0.049,
            " m",
        )?;
        real("generated_error_m", self.generated_error_m, 0.0, 0.05, " m")?;
        real(
            "expected_error_scale",
            self.expected_error_scale,
            0.0,
            10.0,
            "",
        )?;
        real("max_upward", self.max_upward, -1.0, 1.0, "")?;
        real("nms_distance_m", self.nms_distance_m, 0.0, 1.0, " m")?;
        real("nms_angle_deg", self.nms_angle_deg, 0.0, 180.0, " degrees")?;
        count("top_k", self.top_k, 1, 1000)?;
        Ok(())
    }
}

/// The default planner (see the module docs).
#[derive(Debug, Clone, Default)]
pub struct AntipodalPlanner {
    pub options: GraspOptions,
}

/// Each point's expected error for the planner from its provenance code
/// (`deocc_geometry::Provenance`) and instance: 0 for an observed point (code 0) and for the
/// points of an instance in `fitted` (a surface of revolution or a box fitted to its observed
/// side, as exact as the observation), `generated_error_m` for any other generated one. The
/// stated estimate for clouds whose completer gave no error of its own.
pub fn stated_errors(
    provenance: &[u8],
    instance: Option<&[u32]>,
    fitted: &[u32],
    options: &GraspOptions,
) -> Vec<f32> {
    provenance
        .iter()
        .enumerate()
        .map(|(k, &p)| {
            let exact = instance.is_some_and(|ids| fitted.contains(&ids[k]));
            if p == 0 || exact {
                0.0
            } else {
                options.generated_error_m
            }
        })
        .collect()
}

/// Each point's expected error for the planner's envelope, or `None` when the envelope is off:
/// the cloud's own expected errors (`expected`, metres) times
/// [`GraspOptions::expected_error_scale`] when that is on and the cloud has them (observed
/// points, provenance 0, count 0 whatever they carry), else [`stated_errors`] when
/// [`GraspOptions::generated_error_m`] is on.
pub fn envelope_errors(
    provenance: Option<&[u8]>,
    expected: Option<&[f32]>,
    instance: Option<&[u32]>,
    fitted: &[u32],
    options: &GraspOptions,
) -> Option<Vec<f32>> {
    let provenance = provenance?;
    match expected {
        Some(e) if options.expected_error_scale > 0.0 => Some(
            provenance
                .iter()
                .zip(e)
                .map(|(&p, &x)| {
                    if p == 0 {
                        0.0
                    } else {
                        x * options.expected_error_scale
                    }
                })
                .collect(),
        ),
        _ => (options.generated_error_m > 0.0)
            .then(|| stated_errors(provenance, instance, fitted, options)),
    }
}

/// Any unit vector perpendicular to `n`.
fn perpendicular(n: &Vector3<f32>) -> Vector3<f32> {
    let helper = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    n.cross(&helper).normalize()
}

/// A grasp's jaw contacts on a cloud: the indices of the points the upper and lower jaw meet
/// first, and every point of the closing region with its gripper-frame coordinates.
pub type JawContacts = (usize, usize, Vec<(usize, Vector3<f32>)>);

/// The jaws' first contacts on `points` for a grasp: the point with the largest and the
/// smallest closing coordinate inside the closing region, and the local coordinates of every
/// point in the region. `None` when the region is empty.
pub fn jaw_contacts(
    grasp: &Grasp,
    gripper: &GripperConfig,
    points: &[Point3<f32>],
    candidates: impl Iterator<Item = usize>,
) -> Option<JawContacts> {
    let mut inside = Vec::new();
    for i in candidates {
        let l = grasp.to_local(&points[i]);
        if classify(&l, grasp.width, gripper) == Part::Closing {
            inside.push((i, l));
        }
    }
    let hi = inside.iter().max_by(|a, b| a.1.y.total_cmp(&b.1.y))?.0;
    let lo = inside.iter().min_by(|a, b| a.1.y.total_cmp(&b.1.y))?.0;
    Some((hi, lo, inside))
}

/// The worse of the two contact angles of a grasp whose jaws first meet points `hi` and `lo`
/// (from [`jaw_contacts`]): each jaw is a flat plate pressing the patch of points within `band`
/// of its first contact along the closing axis; the contact is the patch's centroid, its normal
/// the patch's mean normal (each turned to face the jaw), and the angle is that between the
/// normal and the line joining the two contacts (radians). `None` when the contacts coincide.
pub fn closure_angle(
    grasp: &Grasp,
    points: &[Point3<f32>],
    normals: &[Vector3<f32>],
    inside: &[(usize, Vector3<f32>)],
    hi: usize,
    lo: usize,
    band: f32,
) -> Option<f32> {
    let closing = grasp.closing();
    let patch = |edge: f32, sign: f32| -> (Point3<f32>, Vector3<f32>) {
        let mut c = Vector3::zeros();
        let mut n = Vector3::zeros();
        let mut k = 0.0f32;
        for &(i, l) in inside {
            if (l.y - edge).abs() <= band {
                c += points[i].coords;
                let ni = normals[i];
                n += if ni.dot(&closing) * sign >= 0.0 {
                    ni
                } else {
                    -ni
                };
                k += 1.0;
            }
        }
        (Point3::from(c / k.max(1.0)), n)
    };
    let (yh, yl) = (grasp.to_local(&points[hi]).y, grasp.to_local(&points[lo]).y);
    let (p, np) = patch(yh, 1.0);
    let (q, nq) = patch(yl, -1.0);
    let d = q - p;
    let len = d.norm();
    if len < 1e-6 {
        return None;
    }
    let angle = |n: &Vector3<f32>| {
        (n.dot(&d).abs() / (n.norm().max(1e-12) * len))
            .min(1.0)
            .acos()
    };
    Some(angle(&np).max(angle(&nq)))
}

impl GraspPlanner for AntipodalPlanner {
    fn name(&self) -> &str {
        "antipodal"
    }

    fn plan(
        &self,
        scene: &[Point3<f32>],
        target: &[Point3<f32>],
    ) -> Result<Vec<Grasp>, RobotError> {
        self.plan_with_stats(scene, target).map(|(g, _)| g)
    }
}

impl AntipodalPlanner {
    /// [`GraspPlanner::plan`], also counting why candidates were turned down.
    pub fn plan_with_stats(
        &self,
        scene: &[Point3<f32>],
        target: &[Point3<f32>],
    ) -> Result<(Vec<Grasp>, PlanStats), RobotError> {
        self.plan_with_errors(scene, None, target, None)
    }

    /// [`Self::plan_with_stats`] with each point's expected error (metres; `None`: all 0): the
    /// uncertainty-aware plan of [`GraspOptions::generated_error_m`]'s docs.
    pub fn plan_with_errors(
        &self,
        scene: &[Point3<f32>],
        scene_error: Option<&[f32]>,
        target: &[Point3<f32>],
        target_error: Option<&[f32]>,
    ) -> Result<(Vec<Grasp>, PlanStats), RobotError> {
        let o = &self.options;
        for (what, err, n) in [
            ("scene", scene_error, scene.len()),
            ("target", target_error, target.len()),
        ] {
            if let Some(e) = err {
                if e.len() != n {
                    return Err(RobotError::Input(format!(
                        "{} expected errors for {n} {what} points",
                        e.len()
                    )));
                }
                if let Some(bad) = e.iter().find(|x| !(x.is_finite() && **x >= 0.0)) {
                    return Err(RobotError::Input(format!(
                        "a {what} point's expected error is {bad}: must be finite and >= 0"
                    )));
                }
            }
        }
        o.validate()?;
        let g = &o.gripper;
        if target.len() < 2 * o.min_jaw_points {
            return Err(RobotError::Input(format!(
                "the target has {} points; a grasp needs at least {}",
                target.len(),
                2 * o.min_jaw_points
            )));
        }
        let thin = voxel_downsample(
            &PointCloud::from_positions(target.to_vec()),
            o.voxel_m as f64,
        )?;
        let pts = thin.positions;
        // Each thinned point takes the expected error of the target point nearest it.
        let terr: Vec<f32> = match target_error {
            Some(e) => {
                let original = KdIndex::build(target)?;
                pts.iter()
                    .map(|p| e[original.nearest(p).index as usize])
                    .collect()
            }
            None => vec![0.0; pts.len()],
        };
        let index = KdIndex::build(&pts)?;
        let normals = estimate_normals_with_index(&pts, &index, o.normal_neighbours);
        // Only the scene near the target can touch the gripper.
        let (lo, hi) = bounds(&pts);
        let reach = g.depth + g.palm_thickness + g.max_aperture + g.finger_width;
        let near: Vec<usize> = (0..scene.len())
            .filter(|&i| {
                let p = &scene[i];
                (0..3).all(|k| p[k] >= lo[k] - reach && p[k] <= hi[k] + reach) && p.x.is_finite()
            })
            .collect();
        let near_scene: Vec<Point3<f32>> = near.iter().map(|&i| scene[i]).collect();
        let serr: Vec<f32> = near
            .iter()
            .map(|&i| scene_error.map_or(0.0, |e| e[i]))
            .collect();
        let scene_index = if near_scene.is_empty() {
            None
        } else {
            Some(KdIndex::build(&near_scene)?)
        };
        let up = Vector3::from(o.up).normalize();
        let cos_cone = o.friction_deg.to_radians().cos();
        let stride = (pts.len() / o.seeds).max(1);
        let seeds: Vec<usize> = (0..pts.len()).step_by(stride).take(o.seeds).collect();
        let search = g.max_aperture + g.depth + g.finger_height;
        let per_seed: Vec<(Vec<Grasp>, PlanStats)> = seeds
            .par_iter()
            .map(|&s| {
                let mut out = Vec::new();
                let mut stats = PlanStats::default();
                let n = normals[s];
                if n.norm_squared() < 0.5 {
                    return (out, stats);
                }
                stats.seeds = 1;
                let local_ids: Vec<usize> = index
                    .within(&pts[s], search)
                    .into_iter()
                    .map(|nb| nb.index as usize)
                    .collect();
                let u = perpendicular(&n);
                let v = n.cross(&u);
                for k in 0..o.approaches {
                    let th = k as f32 * std::f32::consts::TAU / o.approaches as f32;
                    let a = u * th.cos() + v * th.sin();
                    if a.dot(&up) > o.max_upward {
                        continue;
                    }
                    for &d in &o.depths {
                        stats.candidates += 1;
                        match self.candidate(
                            &pts,
                            &normals,
                            &local_ids,
                            pts[s] - a * d,
                            a,
                            n,
                            cos_cone,
                            &near_scene,
                            scene_index.as_ref(),
                            &terr,
                            &serr,
                        ) {
                            Ok(gr) => {
                                stats.accepted += 1;
                                out.push(gr);
                            }
                            Err(r) => stats.count(r),
                        }
                    }
                }
                (out, stats)
            })
            .collect();
        let mut stats = PlanStats::default();
        let mut candidates = Vec::new();
        for (c, s) in per_seed {
            candidates.extend(c);
            stats = stats.add(s);
        }
        candidates.sort_by(|a, b| b.score.total_cmp(&a.score));
        let kept = non_maximum_suppression(
            candidates,
            o.nms_distance_m,
            o.nms_angle_deg.to_radians(),
            o.top_k,
            g,
        );
        Ok((kept, stats))
    }

    /// One candidate: the palm at `palm` (before centring), approach `a`, closing axis `n`.
    #[allow(clippy::too_many_arguments)]
    fn candidate(
        &self,
        pts: &[Point3<f32>],
        normals: &[Vector3<f32>],
        local_ids: &[usize],
        palm: Point3<f32>,
        a: Vector3<f32>,
        n: Vector3<f32>,
        cos_cone: f32,
        scene: &[Point3<f32>],
        scene_index: Option<&KdIndex>,
        terr: &[f32],
        serr: &[f32],
    ) -> Result<Grasp, Reject> {
        let o = &self.options;
        let g = &o.gripper;
        // Open fully, find the target's extent along the closing axis, then centre and close.
        let open = Grasp::new(palm, a, n, g.max_aperture * 2.0, 0.0, [palm; 2]);
        let (hi, lo, inside) =
            jaw_contacts(&open, g, pts, local_ids.iter().copied()).ok_or(Reject::NoContact)?;
        let (hi, lo) = trimmed_contacts(&inside, o.extent_trim).unwrap_or((hi, lo));
        let (mut yh, mut yl) = (open.to_local(&pts[hi]).y, open.to_local(&pts[lo]).y);
        // The envelope: each point a ball of its expected error, trimmed alike.
        if terr.iter().any(|&e| e > 0.0) {
            let k = (o.extent_trim * inside.len() as f32).floor() as usize;
            let rank = |mut ys: Vec<f32>, at: usize| {
                let at = at.min(ys.len() - 1);
                *ys.select_nth_unstable_by(at, |a, b| a.total_cmp(b)).1
            };
            let n = inside.len();
            let grown = inside.iter().map(|&(i, l)| l.y + terr[i]).collect();
            let shrunk = inside.iter().map(|&(i, l)| l.y - terr[i]).collect();
            yh = yh.max(rank(grown, n.saturating_sub(1 + k)));
            yl = yl.min(rank(shrunk, k));
        }
        // A sheet thinner than two voxels is no grasp (a pinch of a face's edge).
        if yh - yl + 2.0 * o.margin_m > g.max_aperture || yh - yl < 2.0 * o.voxel_m {
            return Err(Reject::WidthOrThin);
        }
        let width = (yh - yl + 2.0 * o.open_margin_m.max(o.margin_m)).min(g.max_aperture);
        let centred = palm + n * ((yh + yl) / 2.0);
        let grasp = Grasp::new(centred, a, n, width, 0.0, [pts[hi], pts[lo]]);
        let (hi, lo, inside) =
            jaw_contacts(&grasp, g, pts, local_ids.iter().copied()).ok_or(Reject::NoContact)?;
        let (hi, lo) = trimmed_contacts(&inside, o.extent_trim).unwrap_or((hi, lo));
        // The same share of stray points may come near the palm.
        let allowed = (o.extent_trim * inside.len() as f32).floor() as usize;
        if inside
            .iter()
            .filter(|(_, l)| l.x < o.palm_clearance_m)
            .count()
            > allowed
        {
            return Err(Reject::Palm);
        }
        let (yh, yl) = (grasp.to_local(&pts[hi]).y, grasp.to_local(&pts[lo]).y);
        let mut share = [0.0f32; 2];
        let (mut sure, mut jaw_points) = (0usize, 0usize);
        for (side, edge) in [(0usize, yh), (1, yl)] {
            let jaw: Vec<usize> = inside
                .iter()
                .filter(|(_, l)| (l.y - edge).abs() <= o.jaw_band_m)
                .map(|&(i, _)| i)
                .collect();
            if jaw.len() < o.min_jaw_points {
                return Err(Reject::JawPoints);
            }
            sure += jaw.iter().filter(|&&i| terr[i] < 1e-3).count();
            jaw_points += jaw.len();
            let good = jaw
                .iter()
                .filter(|&&i| normals[i].dot(&n).abs() >= cos_cone)
                .count();
            share[side] = good as f32 / jaw.len() as f32;
        }
        if share[0] < 0.25 || share[1] < 0.25 {
            return Err(Reject::FrictionShare);
        }
        // The evaluator's own criterion on the planning cloud: the contact angle must lie inside
        // the friction cone.
        let angle = closure_angle(&grasp, pts, normals, &inside, hi, lo, o.jaw_band_m)
            .ok_or(Reject::ClosureAngle)?;
        let cone = o.friction_deg.to_radians();
        if angle > cone {
            return Err(Reject::ClosureAngle);
        }
        if let Some(si) = scene_index {
            let c = grasp.center(g);
            let inflated = g.inflated(o.collision_margin_m);
            let most = serr.iter().copied().fold(0.0f32, f32::max);
            let r = inflated.bounding_radius(width) + o.collision_margin_m + most;
            let hit = si.within(&c, r).into_iter().any(|nb| {
                let k = nb.index as usize;
                let local = grasp.to_local(&scene[k]);
                if serr[k] > 0.0 {
                    classify(&local, width, &g.inflated(o.collision_margin_m + serr[k]))
                        == Part::Body
                } else {
                    classify(&local, width, &inflated) == Part::Body
                }
            });
            if hit {
                return Err(Reject::Collision);
            }
        }
        let support = (inside.len() as f32 / 60.0).min(1.0);
        let score = (share[0] * share[1]).sqrt() * support * (1.0 - angle / cone);
        let mut grasp = Grasp::new(centred, a, n, width, score, [pts[hi], pts[lo]]);
        grasp.confidence = sure as f32 / jaw_points.max(1) as f32;
        Ok(grasp)
    }
}

/// The points at the `trim` quantiles of the closing coordinate among `inside` (upper, lower):
/// the jaws' contacts with the outermost `trim` share on each side left out. `None` when the
/// trim leaves out nothing (fewer than one point a side).
fn trimmed_contacts(inside: &[(usize, Vector3<f32>)], trim: f32) -> Option<(usize, usize)> {
    let k = (trim * inside.len() as f32).floor() as usize;
    if k == 0 || 2 * k >= inside.len() {
        return None;
    }
    let mut by_y: Vec<(f32, usize)> = inside.iter().map(|&(i, l)| (l.y, i)).collect();
    let n = by_y.len();
    by_y.select_nth_unstable_by(n - 1 - k, |a, b| a.0.total_cmp(&b.0));
    let hi = by_y[n - 1 - k].1;
    by_y.select_nth_unstable_by(k, |a, b| a.0.total_cmp(&b.0));
    Some((hi, by_y[k].1))
}

fn bounds(pts: &[Point3<f32>]) -> (Point3<f32>, Point3<f32>) {
    pts.iter().fold(
        (
            Point3::new(f32::MAX, f32::MAX, f32::MAX),
            Point3::new(f32::MIN, f32::MIN, f32::MIN),
        ),
        |(lo, hi), p| (lo.inf(p), hi.sup(p)),
    )
}

/// Keeps grasps best first, dropping one closer than `distance` (closing-region centres) and
/// `angle` (radians) to a kept one; at most `top_k`. `sorted` must be best first.
pub fn non_maximum_suppression(
    sorted: Vec<Grasp>,
    distance: f32,
    angle: f32,
    top_k: usize,
    gripper: &GripperConfig,
) -> Vec<Grasp> {
    let mut kept: Vec<Grasp> = Vec::new();
    for g in sorted {
        if kept.len() >= top_k {
            break;
        }
        let c = g.center(gripper);
        let close = kept
            .iter()
            .any(|k| (k.center(gripper) - c).norm() < distance && k.rotation_angle_to(&g) < angle);
        if !close {
            kept.push(g);
        }
    }
    kept
}

/// A rotation whose columns are approach, closing and height axes, for tests and callers that
/// build grasps by hand.
pub fn frame(approach: Vector3<f32>, closing: Vector3<f32>) -> Rotation3<f32> {
    let z = approach.cross(&closing);
    Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[approach, closing, z]))
}
