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

use std::path::Path;

use deocc_geometry::camera::{Camera, Intrinsics};
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
            Ok(FrameCamera {
                name: f.name,
                intrinsics: f.intrinsics,
                world_from_camera,
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
