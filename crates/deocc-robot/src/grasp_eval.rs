//! Analytic grasp evaluation against ground-truth geometry, after graspnetAPI's protocol
//! (reimplemented, not ported): an analytic stand-in for robot trials.
//!
//! A grasp fails by **collision** when a ground-truth scene point lies inside a finger or the
//! palm, and is **empty** when fewer than `min_points` ground-truth points of the target lie
//! between the jaws. Otherwise each jaw is closed along the closing axis onto the target's
//! ground-truth surface as a flat plate: it meets the target's points of the largest (resp.
//! smallest) closing coordinate in the closing region first, and presses the patch within
//! [`JAW_PATCH_M`] of them; the contact is the patch's centroid with its mean normal. The grasp is in force closure at friction
//! `mu` when both contact angles `arccos(|n . (p_other - p)| / |p_other - p|)` are at most
//! `atan(mu)`; its score is the smallest `mu` of {0.2, 0.4, ..., 1.2} that holds.

use deocc_geometry::KdIndex;
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::grasp::{closure_angle, jaw_contacts};
use crate::gripper::{classify, Grasp, GripperConfig, Part};
use crate::RobotError;

/// How far behind a jaw's first contact (along the closing axis) the surface it presses reaches.
pub const JAW_PATCH_M: f32 = 0.002;

/// The friction coefficients of the protocol.
pub const FRICTIONS: [f32; 6] = [0.2, 0.4, 0.6, 0.8, 1.0, 1.2];

/// How one grasp fares on the ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "outcome")]
pub enum GraspOutcome {
    /// A ground-truth point of instance `with` lies inside a finger or the palm.
    Collision {
        with: u32,
    },
    Empty,
    /// Not in force closure at the largest friction of [`FRICTIONS`].
    NoClosure,
    /// In force closure from friction `mu` up.
    Closure {
        mu: f32,
        /// The two ground-truth contacts.
        contacts: [[f32; 3]; 2],
    },
}

impl GraspOutcome {
    /// Success at friction `mu`.
    pub fn holds_at(&self, mu: f32) -> bool {
        matches!(self, GraspOutcome::Closure { mu: m, .. } if *m <= mu + 1e-6)
    }
}

/// Ground truth of one scene for grasp evaluation: surface samples with normals and instance ids.
pub struct GroundTruthScene<'a> {
    pub points: &'a [Point3<f32>],
    pub normals: &'a [Vector3<f32>],
    pub instance: &'a [u32],
    index: KdIndex,
}

impl<'a> GroundTruthScene<'a> {
    pub fn new(
        points: &'a [Point3<f32>],
        normals: &'a [Vector3<f32>],
        instance: &'a [u32],
    ) -> Result<Self, RobotError> {
        if normals.len() != points.len() || instance.len() != points.len() {
            return Err(RobotError::Input(format!(
                "ground truth: {} points but {} normals and {} instance ids",
                points.len(),
                normals.len(),
                instance.len()
            )));
        }
        Ok(Self {
            points,
            normals,
            instance,
            index: KdIndex::build(points)?,
        })
    }

    /// The ground-truth points of instance `id`.
    pub fn target_points(&self, id: u32) -> Vec<Point3<f32>> {
        self.points
            .iter()
            .zip(self.instance)
            .filter(|(_, &i)| i == id)
            .map(|(p, _)| *p)
            .collect()
    }

    /// Evaluates `grasp` on target `target` (see the module docs).
    pub fn evaluate(
        &self,
        grasp: &Grasp,
        target: u32,
        gripper: &GripperConfig,
        min_points: usize,
    ) -> GraspOutcome {
        let near: Vec<usize> = self
            .index
            .within(&grasp.center(gripper), gripper.bounding_radius(grasp.width))
            .into_iter()
            .map(|nb| nb.index as usize)
            .collect();
        if let Some(&i) = near.iter().find(|&&i| {
            classify(&grasp.to_local(&self.points[i]), grasp.width, gripper) == Part::Body
        }) {
            return GraspOutcome::Collision {
                with: self.instance[i],
            };
        }
        let on_target = near.into_iter().filter(|&i| self.instance[i] == target);
        let Some((hi, lo, inside)) = jaw_contacts(grasp, gripper, self.points, on_target) else {
            return GraspOutcome::Empty;
        };
        if inside.len() < min_points {
            return GraspOutcome::Empty;
        }
        let Some(worst) = closure_angle(
            grasp,
            self.points,
            self.normals,
            &inside,
            hi,
            lo,
            JAW_PATCH_M,
        ) else {
            return GraspOutcome::NoClosure;
        };
        let (p, q) = (self.points[hi], self.points[lo]);
        match FRICTIONS.iter().find(|&&mu| worst <= mu.atan()) {
            Some(&mu) => GraspOutcome::Closure {
                mu,
                contacts: [p.coords.into(), q.coords.into()],
            },
            None => GraspOutcome::NoClosure,
        }
    }
}

/// graspnetAPI's precision figures of one ranked grasp list: for each friction, precision@k
/// averaged over k = 1..=`top_k` (a list shorter than k counts the missing grasps as failures).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct GraspPrecision {
    /// The best-ranked grasp holds at mu 0.4 / 0.8 (false without grasps).
    pub top1_at_04: bool,
    pub top1_at_08: bool,
    /// AP averaged over [`FRICTIONS`], and at mu 0.4 and 0.8.
    pub ap: f64,
    pub ap_04: f64,
    pub ap_08: f64,
}

pub fn precision(outcomes: &[GraspOutcome], top_k: usize) -> GraspPrecision {
    let ap_at = |mu: f32| -> f64 {
        let mut hits = 0usize;
        let mut sum = 0.0;
        for k in 0..top_k {
            if outcomes.get(k).is_some_and(|o| o.holds_at(mu)) {
                hits += 1;
            }
            sum += hits as f64 / (k + 1) as f64;
        }
        sum / top_k as f64
    };
    GraspPrecision {
        top1_at_04: outcomes.first().is_some_and(|o| o.holds_at(0.4)),
        top1_at_08: outcomes.first().is_some_and(|o| o.holds_at(0.8)),
        ap: FRICTIONS.iter().map(|&m| ap_at(m)).sum::<f64>() / FRICTIONS.len() as f64,
        ap_04: ap_at(0.4),
        ap_08: ap_at(0.8),
    }
}

/// Affordance IoU over the target's ground-truth points: the true graspable region (points
/// within `radius` of the contacts of grasps that hold on the ground truth) against the planned
/// one (points within `radius` of the planner's contacts). `None` when both regions are empty.
pub fn affordance_iou(
    target_gt: &[Point3<f32>],
    true_contacts: &[[f32; 3]],
    planned_contacts: &[[f32; 3]],
    radius: f32,
) -> Result<Option<f64>, RobotError> {
    if target_gt.is_empty() {
        return Err(RobotError::Input(
            "the target has no ground-truth points".into(),
        ));
    }
    let mark = |contacts: &[[f32; 3]]| -> Result<Vec<bool>, RobotError> {
        let mut m = vec![false; target_gt.len()];
        if contacts.is_empty() {
            return Ok(m);
        }
        let index = KdIndex::build(target_gt)?;
        for c in contacts {
            for nb in index.within(&Point3::from(*c), radius) {
                m[nb.index as usize] = true;
            }
        }
        Ok(m)
    };
    let (t, p) = (mark(true_contacts)?, mark(planned_contacts)?);
    let inter = t.iter().zip(&p).filter(|(a, b)| **a && **b).count();
    let union = t.iter().zip(&p).filter(|(a, b)| **a || **b).count();
    Ok((union > 0).then(|| inter as f64 / union as f64))
}
