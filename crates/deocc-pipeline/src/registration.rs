//! Stage: registration. The frames' poses are given with the input (the default), or registered
//! from the depth alone by frame-to-frame point-to-plane ICP ([`register_unposed`]), for a
//! hand-held or robot RGB-D stream that has no poses.

use deocc_geometry::align::{icp, IcpMethod, IcpOptions, IcpTarget};
use deocc_geometry::camera::Camera;
use deocc_geometry::depth::backproject;
use deocc_geometry::normals::{estimate_normals, orient_towards};
use deocc_geometry::voxel::voxel_downsample;
use deocc_io::scene::{Frame, SceneInput};
use nalgebra::{Isometry3, Point3, Rotation3, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::PipelineError;

/// Registers a scene read without poses (`cameras.json` gave none) with the default
/// [`FrameToFrameIcp`], in file order, and marks it posed; returns each frame's figures. A posed
/// scene is left as it is (an empty list).
pub fn register_unposed(scene: &mut SceneInput) -> Result<Vec<FrameRegistration>, PipelineError> {
    if scene.posed {
        return Ok(Vec::new());
    }
    let reports = FrameToFrameIcp::default().register(&mut scene.frames)?;
    scene.posed = true;
    Ok(reports)
}

/// How one frame was registered.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameRegistration {
    pub frame: String,
    /// Fraction of the frame's points with a partner in the previous frame at the finest level.
    pub fitness: f64,
    pub inlier_rmse_m: f64,
}

/// Frame-to-frame point-to-plane ICP, coarse to fine, with a constant-velocity initial guess.
#[derive(Debug, Clone)]
pub struct FrameToFrameIcp {
    /// Voxel size of the registered clouds, per level (coarse to fine), with the correspondence
    /// distance of each level.
    pub levels: Vec<(f64, f32)>,
    pub iterations: usize,
    /// A frame whose fitness falls below this is reported as a failed registration.
    pub min_fitness: f64,
}

impl Default for FrameToFrameIcp {
    fn default() -> Self {
        Self {
            levels: vec![(0.04, 0.25), (0.02, 0.08), (0.01, 0.03)],
            iterations: 30,
            min_fitness: 0.3,
        }
    }
}

/// Points with their unit normals.
type OrientedPoints = (Vec<Point3<f32>>, Vec<Vector3<f32>>);

/// The frame's points (camera frame) at a voxel size, with normals facing the camera.
fn camera_cloud(frame: &Frame, voxel_m: f64) -> Result<OrientedPoints, PipelineError> {
    let camera = Camera {
        intrinsics: frame.camera.intrinsics,
        world_from_camera: Isometry3::identity(),
    };
    let (cloud, _) = backproject(&frame.depth, &camera)?;
    let cloud = voxel_downsample(&cloud, voxel_m)?;
    let mut normals = estimate_normals(&cloud.positions, 20)?;
    orient_towards(&cloud.positions, &mut normals, &Point3::origin());
    Ok((cloud.positions, normals))
}

/// Gravity seen from a camera held roughly upright: the direction shared by most surface normals
/// (floor, table tops) within 60 degrees of the camera's up (-y). Returns up in the camera frame.
pub fn estimate_up(normals: &[Vector3<f32>]) -> Vector3<f32> {
    let camera_up = -Vector3::y();
    let candidates: Vec<&Vector3<f32>> =
        normals.iter().filter(|n| n.dot(&camera_up) > 0.5).collect();
    if candidates.is_empty() {
        return camera_up;
    }
    let cos_near = 10f32.to_radians().cos();
    let stride = (candidates.len() / 500).max(1);
    let best = candidates
        .iter()
        .step_by(stride)
        .max_by_key(|c| candidates.iter().filter(|n| n.dot(c) > cos_near).count())
        .copied()
        .copied()
        .unwrap_or(camera_up);
    let sum: Vector3<f32> = candidates
        .iter()
        .filter(|n| n.dot(&best) > cos_near)
        .fold(Vector3::zeros(), |s, n| s + **n);
    sum.try_normalize(1e-9).unwrap_or(best)
}

impl FrameToFrameIcp {
    /// Replaces every frame's pose: frame 0 defines the world (its camera centre at the origin,
    /// turned so that the estimated gravity points along -z, as the segmenter expects), each next
    /// frame is registered onto the one before it.
    pub fn register(&self, frames: &mut [Frame]) -> Result<Vec<FrameRegistration>, PipelineError> {
        let Some(first) = frames.first() else {
            return Ok(Vec::new());
        };
        if self.levels.is_empty() {
            return Err(PipelineError::Input {
                path: Default::default(),
                msg: "frame-to-frame ICP needs at least one level".into(),
            });
        }
        // Each frame's clouds at every level, built once: a frame is the source of one pair and
        // the target of the next.
        let clouds = |f: &Frame| -> Result<Vec<OrientedPoints>, PipelineError> {
            self.levels
                .iter()
                .map(|&(voxel, _)| camera_cloud(f, voxel))
                .collect()
        };
        let mut previous = clouds(first)?;
        let up = estimate_up(&previous[previous.len() - 1].1);
        let level = Rotation3::rotation_between(&up, &Vector3::z()).unwrap_or_else(|| {
            Rotation3::from_axis_angle(&Vector3::x_axis(), std::f32::consts::PI)
        });
        let mut world_from_camera = vec![Isometry3::from_parts(
            Default::default(),
            UnitQuaternion::from_rotation_matrix(&level),
        )];
        let mut reports = vec![FrameRegistration {
            frame: first.name.clone(),
            fitness: 1.0,
            inlier_rmse_m: 0.0,
        }];
        let mut velocity = Isometry3::<f64>::identity(); // previous from current, last pair
        for k in 1..frames.len() {
            let mut prev_from_current = velocity;
            let current = clouds(&frames[k])?;
            let mut last = None;
            for (((target_pts, target_normals), (source_pts, _)), &(_, max_corr)) in
                previous.iter().zip(&current).zip(&self.levels)
            {
                let target = IcpTarget::new(target_pts, Some(target_normals))?;
                let r = icp(
                    source_pts,
                    &target,
                    &prev_from_current,
                    &IcpOptions {
                        method: IcpMethod::PointToPlane,
                        max_correspondence_m: max_corr,
                        max_iterations: self.iterations,
                        ..IcpOptions::default()
                    },
                )?;
                prev_from_current = r.target_from_source;
                last = Some(r);
            }
            previous = current;
            let Some(r) = last else {
                unreachable!("levels checked non-empty above")
            };
            velocity = prev_from_current;
            let pose = world_from_camera[k - 1] * prev_from_current.cast::<f32>();
            world_from_camera.push(pose);
            reports.push(FrameRegistration {
                frame: frames[k].name.clone(),
                fitness: r.fitness,
                inlier_rmse_m: r.inlier_rmse,
            });
        }
        for (f, pose) in frames.iter_mut().zip(world_from_camera) {
            f.camera.world_from_camera = pose;
        }
        Ok(reports)
    }
}
