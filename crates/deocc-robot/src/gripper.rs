//! A parallel-jaw gripper and a grasp pose in its frame.
//!
//! The gripper frame (graspnetAPI's convention): **x** is the approach direction (from the palm
//! towards the object), **y** the closing axis (the jaws move along it), **z** = x × y, along the
//! fingers' height. The origin is the centre of the palm's front face. The closing region is the
//! box `0 <= x <= depth`, `|y| <= width / 2`, `|z| <= finger_height / 2`; each finger is a box
//! `finger_width` thick just outside it along y; the palm is a box `palm_thickness` deep behind
//! the origin spanning both fingers. The arm behind the palm is not modelled.

use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::RobotError;

/// Gripper geometry (metres, degrees). The defaults are a Franka-like hand.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GripperConfig {
    /// Thickness of a finger along the closing axis.
    pub finger_width: f32,
    /// Extent of a finger along z (the gripper's height).
    pub finger_height: f32,
    /// Finger length along the approach direction: how deep the closing region is.
    pub depth: f32,
    /// Largest opening between the fingers.
    pub max_aperture: f32,
    /// Depth of the palm box behind the fingers.
    pub palm_thickness: f32,
}

impl Default for GripperConfig {
    fn default() -> Self {
        Self {
            finger_width: 0.01,
            finger_height: 0.02,
            depth: 0.05,
            max_aperture: 0.085,
            palm_thickness: 0.01,
        }
    }
}

impl GripperConfig {
    /// Refuses sizes that are not positive and finite, naming the field.
    pub fn validate(&self) -> Result<(), RobotError> {
        for (name, v) in [
            ("finger_width", self.finger_width),
            ("finger_height", self.finger_height),
            ("depth", self.depth),
            ("max_aperture", self.max_aperture),
            ("palm_thickness", self.palm_thickness),
        ] {
            if !(v.is_finite() && v > 0.0 && v < 2.0) {
                return Err(RobotError::Config(format!(
                    "gripper.{name} = {v}: must be a positive size in metres below 2"
                )));
            }
        }
        Ok(())
    }

    /// The same gripper grown by `margin` outwards: fingers thicker and taller and longer,
    /// the palm deeper; the opening between the jaws is unchanged (for collision checks with a
    /// clearance).
    pub fn inflated(&self, margin: f32) -> Self {
        Self {
            finger_width: self.finger_width + margin,
            finger_height: self.finger_height + 2.0 * margin,
            depth: self.depth + margin,
            max_aperture: self.max_aperture,
            palm_thickness: self.palm_thickness + margin,
        }
    }

    /// Radius of a sphere around [`Grasp::center`] that holds the whole gripper at `width`.
    pub fn bounding_radius(&self, width: f32) -> f32 {
        let x = self.depth / 2.0 + self.palm_thickness;
        let y = width / 2.0 + self.finger_width;
        let z = self.finger_height / 2.0;
        (x * x + y * y + z * z).sqrt() + 1e-3
    }
}

/// Which part of the gripper a point (in the gripper frame) lies in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    /// Between the jaws: what the grasp holds.
    Closing,
    /// Inside a finger or the palm: a collision.
    Body,
    Outside,
}

/// A grasp: the palm's pose and the opening.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Grasp {
    /// Centre of the palm's front face, world frame.
    pub position: [f32; 3],
    /// World-from-gripper rotation, row-major; its columns are the approach, closing and height
    /// axes.
    pub rotation: [[f32; 3]; 3],
    /// Opening between the fingers.
    pub width: f32,
    /// The planner's score (higher is better; its own scale).
    pub score: f32,
    /// Where the jaws touch the cloud the grasp was planned on (world frame): the first points
    /// each jaw meets as it closes.
    pub contacts: [[f32; 3]; 2],
    /// How far the planner trusts the surface under the jaws, in [0, 1]: the share of the
    /// jaws' points whose expected error is under a millimetre (observed points, or generated
    /// ones the completer is sure of). 1 when the cloud came without expected errors.
    #[serde(default = "full_confidence")]
    pub confidence: f32,
}

fn full_confidence() -> f32 {
    1.0
}

impl Grasp {
    pub fn new(
        position: Point3<f32>,
        approach: Vector3<f32>,
        closing: Vector3<f32>,
        width: f32,
        score: f32,
        contacts: [Point3<f32>; 2],
    ) -> Self {
        let z = approach.cross(&closing);
        let m = Matrix3::from_columns(&[approach, closing, z]);
        let mut rotation = [[0.0; 3]; 3];
        for (r, row) in rotation.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = m[(r, c)];
            }
        }
        Self {
            position: position.coords.into(),
            rotation,
            width,
            score,
            contacts: contacts.map(|c| c.coords.into()),
            confidence: 1.0,
        }
    }

    pub fn origin(&self) -> Point3<f32> {
        Point3::from(self.position)
    }

    pub fn rotation(&self) -> Rotation3<f32> {
        let r = &self.rotation;
        Rotation3::from_matrix_unchecked(Matrix3::new(
            r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
        ))
    }

    pub fn approach(&self) -> Vector3<f32> {
        self.rotation().matrix().column(0).into()
    }

    pub fn closing(&self) -> Vector3<f32> {
        self.rotation().matrix().column(1).into()
    }

    /// Centre of the closing region, world frame.
    pub fn center(&self, gripper: &GripperConfig) -> Point3<f32> {
        self.origin() + self.approach() * (gripper.depth / 2.0)
    }

    /// `p` (world) in the gripper frame.
    pub fn to_local(&self, p: &Point3<f32>) -> Vector3<f32> {
        self.rotation().inverse() * (p - self.origin())
    }

    /// Angle (radians) between two grasps' rotations, the gripper being symmetric under a half
    /// turn about its approach axis.
    pub fn rotation_angle_to(&self, other: &Grasp) -> f32 {
        let a = self.rotation();
        let b = other.rotation();
        let flip = Rotation3::from_axis_angle(&Vector3::x_axis(), std::f32::consts::PI);
        let d1 = (a.inverse() * b).angle();
        let d2 = (a.inverse() * b * flip).angle();
        d1.min(d2)
    }
}

/// Where a gripper-frame point lies for an opening of `width`.
#[inline]
pub fn classify(local: &Vector3<f32>, width: f32, g: &GripperConfig) -> Part {
    let half_h = g.finger_height / 2.0;
    if local.z.abs() > half_h {
        return Part::Outside;
    }
    let half_w = width / 2.0;
    let outer = half_w + g.finger_width;
    if local.x >= 0.0 && local.x <= g.depth {
        let ay = local.y.abs();
        if ay <= half_w {
            return Part::Closing;
        }
        if ay <= outer {
            return Part::Body;
        }
        return Part::Outside;
    }
    if local.x < 0.0 && local.x >= -g.palm_thickness && local.y.abs() <= outer {
        return Part::Body;
    }
    Part::Outside
}
