//! Camera intrinsics and `world_from_camera` poses as JSON.
//!
//! ```json
//! { "frames": [ { "name": "000000",
//!                 "intrinsics": { "fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5,
//!                                 "width": 640, "height": 480 },
//!                 "world_from_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]] } ] }
//! ```
//! Poses are row-major 4x4 rigid transforms; the rotation part must be orthonormal (to 1e-3).
//! `world_from_camera` may be omitted when poses are unknown (to be registered later).
//!
//! What a real camera delivers beyond a pinhole, each optional per frame:
//! ```json
//! { "distortion": { "model": "rational_polynomial",
//!                   "coefficients": [0.447, -2.5, 0.00094, -0.00053, 1.432, 0.329, -2.332, 1.363] },
//!   "depth_scale": 0.000125,
//!   "depth_camera": { "intrinsics": { "fx": 504.0, "fy": 504.1, "cx": 320.0, "cy": 288.0,
//!                                     "width": 640, "height": 576 },
//!                     "distortion": { "model": "plumb_bob", "coefficients": [0.1, -0.05, 0, 0, 0] },
//!                     "color_from_depth": [[1,0,0,-0.032],[0,1,0,0.002],[0,0,1,0.004],[0,0,0,1]] } }
//! ```
//! - `distortion`: the colour camera's lens (ROS `CameraInfo` names: `plumb_bob`,
//!   `rational_polynomial`, `equidistant`); removed once at read time, so `intrinsics` is then the
//!   pinhole `K` every stage uses. Without `depth_camera` the depth image is registered to the
//!   colour image and shares its lens.
//! - `depth_scale`: metres per unit of a 16-bit depth PNG (default 0.001, millimetres; a
//!   RealSense SR300 counts 1/8 mm, TUM RGB-D 1/5000 m). Float32 depth (`depth/NAME.npy`) is
//!   metres and ignores it.
//! - `depth_camera`: depth from its own camera (own size, intrinsics and lens), registered to the
//!   colour camera at read time with a z-buffer; `color_from_depth` moves depth-camera points
//!   into the colour camera's frame.

use std::path::Path;

use deocc_geometry::camera::{Camera, Intrinsics};
use deocc_geometry::distortion::Distortion;
use nalgebra::{Isometry3, Matrix3, Matrix4, Translation3};
use serde::{Deserialize, Serialize};

use crate::atomic::write_bytes_atomic;
use crate::error::{IoError, IoErrorKind, Result};

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FrameJson {
    pub name: String,
    pub intrinsics: Intrinsics,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub world_from_camera: Option<[[f64; 4]; 4]>,
    #[serde(default, skip_serializing_if = "Distortion::is_none")]
    pub distortion: Distortion,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_scale: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_camera: Option<DepthCameraJson>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthCameraJson {
    pub intrinsics: Intrinsics,
    #[serde(default, skip_serializing_if = "Distortion::is_none")]
    pub distortion: Distortion,
    pub color_from_depth: [[f64; 4]; 4],
}

/// Metres per unit of a 16-bit depth image when nothing else is said: millimetres.
pub const DEFAULT_DEPTH_SCALE: f64 = 0.001;
/// The range a `depth_scale` may take: a micrometre to a metre per unit.
pub const DEPTH_SCALE_RANGE: (f64, f64) = (1e-6, 1.0);

/// A separate depth camera: its own intrinsics and lens, and where it sits.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthCamera {
    pub intrinsics: Intrinsics,
    pub distortion: Distortion,
    pub color_from_depth: Isometry3<f32>,
}

/// How a frame's images relate to the pinhole camera deocc works in.
#[derive(Debug, Clone, PartialEq)]
pub struct Lens {
    /// The colour camera's distortion (and the depth's, without `depth_camera`).
    pub distortion: Distortion,
    /// Metres per unit of 16-bit depth.
    pub depth_scale: f64,
    pub depth_camera: Option<DepthCamera>,
}

impl Default for Lens {
    fn default() -> Self {
        Lens {
            distortion: Distortion::None,
            depth_scale: DEFAULT_DEPTH_SCALE,
            depth_camera: None,
        }
    }
}

impl Lens {
    /// Whether the images are already what a pinhole camera registered to colour would give.
    pub fn is_pinhole(&self) -> bool {
        self.distortion.is_none() && self.depth_camera.is_none()
    }

    /// The size the depth image must have.
    pub fn depth_size(&self, color: &Intrinsics) -> (u32, u32) {
        let k = self.depth_camera.as_ref().map_or(color, |d| &d.intrinsics);
        (k.width(), k.height())
    }

    /// Checks `depth_scale` against [`DEPTH_SCALE_RANGE`].
    pub fn check(&self) -> std::result::Result<(), String> {
        let (lo, hi) = DEPTH_SCALE_RANGE;
        if !(self.depth_scale >= lo && self.depth_scale <= hi) {
            return Err(format!(
                "depth_scale {} is not between {lo} and {hi} metres per unit (0.001 for \
                 millimetres)",
                self.depth_scale
            ));
        }
        if let Some(d) = &self.depth_camera {
            d.intrinsics
                .check_plausible()
                .map_err(|e| format!("depth_camera.intrinsics: {e}"))?;
        }
        Ok(())
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CamerasJson {
    pub frames: Vec<FrameJson>,
}

/// A frame's camera, with its pose if the file has one.
#[derive(Debug, Clone)]
pub struct FrameCamera {
    pub name: String,
    pub intrinsics: Intrinsics,
    pub world_from_camera: Option<Isometry3<f32>>,
    /// Distortion, depth units and a separate depth camera; removed at read time.
    pub lens: Lens,
}

impl FrameCamera {
    /// The full camera; errors if the pose is unknown.
    pub fn camera(&self) -> Option<Camera> {
        self.world_from_camera.map(|p| Camera {
            intrinsics: self.intrinsics,
            world_from_camera: p,
        })
    }
}

pub fn pose_to_rows(pose: &Isometry3<f32>) -> [[f64; 4]; 4] {
    let m = pose.cast::<f64>().to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// Farthest a camera may be from the world origin (metres): beyond it f32 coordinates lose the
/// millimetres a scene needs.
pub const MAX_TRANSLATION_M: f64 = 1e5;

/// Parses a row-major 4x4 rigid transform, rejecting non-rigid or non-finite matrices.
pub fn pose_from_rows(rows: &[[f64; 4]; 4]) -> std::result::Result<Isometry3<f32>, String> {
    let m = Matrix4::from_fn(|r, c| rows[r][c]);
    if m.iter().any(|v| !v.is_finite()) {
        return Err("pose has a non-finite entry".into());
    }
    if (m.fixed_view::<1, 4>(3, 0) - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0))
        .abs()
        .max()
        > 1e-6
    {
        return Err("pose's last row is not [0, 0, 0, 1]".into());
    }
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
    if (r.transpose() * r - Matrix3::identity()).abs().max() > 1e-3 || r.determinant() < 0.0 {
        return Err("pose's rotation is not a proper orthonormal matrix".into());
    }
    // Closed form: nalgebra's iterative `from_matrix` returns the identity for half-turns.
    let rot = deocc_geometry::rotation::nearest_unit_quaternion(&r);
    let t = Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]);
    if t.vector.norm() > MAX_TRANSLATION_M {
        return Err(format!(
            "pose's translation is {:.3e} m from the origin, more than {MAX_TRANSLATION_M:.0e} m",
            t.vector.norm()
        ));
    }
    Ok(Isometry3::from_parts(t, rot).cast::<f32>())
}

pub fn read_cameras_json(path: &Path) -> Result<Vec<FrameCamera>> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::new(path, e))?;
    let parsed: CamerasJson = serde_json::from_str(&text)
        .map_err(|e| IoError::new(path, IoErrorKind::Json(e.to_string())))?;
    if parsed.frames.is_empty() {
        return Err(IoError::invalid(path, "no frames"));
    }
    parsed
        .frames
        .into_iter()
        .map(|f| {
            f.intrinsics
                .check_plausible()
                .map_err(|e| IoError::invalid(path, format!("frame '{}': {e}", f.name)))?;
            let world_from_camera = match &f.world_from_camera {
                Some(rows) => Some(
                    pose_from_rows(rows)
                        .map_err(|e| IoError::invalid(path, format!("frame '{}': {e}", f.name)))?,
                ),
                None => None,
            };
            let at = |e: String| IoError::invalid(path, format!("frame '{}': {e}", f.name));
            let depth_camera = match &f.depth_camera {
                Some(d) => Some(DepthCamera {
                    intrinsics: d.intrinsics,
                    distortion: d.distortion.clone(),
                    color_from_depth: pose_from_rows(&d.color_from_depth)
                        .map_err(|e| at(format!("depth_camera.color_from_depth: {e}")))?,
                }),
                None => None,
            };
            let lens = Lens {
                distortion: f.distortion,
                depth_scale: f.depth_scale.unwrap_or(DEFAULT_DEPTH_SCALE),
                depth_camera,
            };
            lens.check().map_err(at)?;
            Ok(FrameCamera {
                name: f.name,
                intrinsics: f.intrinsics,
                world_from_camera,
                lens,
            })
        })
        .collect()
}

pub fn write_cameras_json(path: &Path, frames: &[FrameCamera]) -> Result<()> {
    let json = CamerasJson {
        frames: frames
            .iter()
            .map(|f| FrameJson {
                name: f.name.clone(),
                intrinsics: f.intrinsics,
                world_from_camera: f.world_from_camera.as_ref().map(pose_to_rows),
                distortion: f.lens.distortion.clone(),
                depth_scale: (f.lens.depth_scale != DEFAULT_DEPTH_SCALE)
                    .then_some(f.lens.depth_scale),
                depth_camera: f.lens.depth_camera.as_ref().map(|d| DepthCameraJson {
                    intrinsics: d.intrinsics,
                    distortion: d.distortion.clone(),
                    color_from_depth: pose_to_rows(&d.color_from_depth),
                }),
            })
            .collect(),
    };
    write_json(path, &json)
}

/// Pretty JSON, written atomically.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let mut text = serde_json::to_string_pretty(value)
        .map_err(|e| IoError::new(path, IoErrorKind::Json(e.to_string())))?;
    text.push('\n');
    write_bytes_atomic(path, text.as_bytes())
}

/// Reads any JSON document into `T`, naming the file on error.
pub fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::new(path, e))?;
    serde_json::from_str(&text).map_err(|e| IoError::new(path, IoErrorKind::Json(e.to_string())))
}

/// Parses an options document (pipeline, grasp or place settings) into `T`: it must be a JSON
/// object. serde reads a struct from an array too, field by field in order, so `[]` would be
/// "all defaults" and `[4]` would set whatever field comes first, without a word.
pub fn options_from_json<T: serde::de::DeserializeOwned>(
    text: &str,
) -> std::result::Result<T, String> {
    let value: serde_json::Value = serde_json::from_str(text).map_err(|e| e.to_string())?;
    if !value.is_object() {
        let kind = match value {
            serde_json::Value::Array(_) => "an array",
            serde_json::Value::Null => "null",
            serde_json::Value::Bool(_) => "a boolean",
            serde_json::Value::Number(_) => "a number",
            serde_json::Value::String(_) => "a string",
            serde_json::Value::Object(_) => "an object",
        };
        return Err(format!(
            "expected a JSON object of settings ({{\"field\": value, ...}}), got {kind}"
        ));
    }
    serde_json::from_value(value).map_err(|e| e.to_string())
}
