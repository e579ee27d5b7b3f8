//! The TUM RGB-D layout, the format most public RGB-D sequences use
//! (<https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats>):
//!
//! ```text
//! SEQUENCE/
//!   rgb.txt          "timestamp rgb/NAME.png" per line, '#' comments
//!   depth.txt        "timestamp depth/NAME.png": 16-bit PNG, 5000 units per metre, 0 = none
//!   groundtruth.txt  optional: "timestamp tx ty tz qx qy qz qw" (world from camera)
//!   camera.json      optional (deocc's addition): {"fx", "fy", "cx", "cy"[, "distortion",
//!                    "depth_scale"]}; without it the TUM default 525 / 525 / 319.5 / 239.5
//! ```
//!
//! Colour and depth are paired by nearest timestamp within [`MAX_PAIR_GAP_S`] (TUM's own
//! `associate.py` default), poses by nearest ground-truth stamp within the same gap. Frames are
//! then picked (every n-th, or keyframes by motion) into the same checked [`SceneInput`] a scene
//! folder gives.

use std::path::{Path, PathBuf};

use deocc_geometry::camera::{Camera, Intrinsics};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde::Deserialize;

use crate::cameras::{FrameCamera, Lens};
use crate::error::{IoError, Result};
use crate::scene::{Frame, SceneInput};

/// Largest gap between paired colour, depth and pose stamps (seconds).
pub const MAX_PAIR_GAP_S: f64 = 0.02;
/// TUM depth: 5000 units per metre.
pub const TUM_DEPTH_SCALE: f64 = 1.0 / 5000.0;

/// Which frames of a sequence become the scene's views.
#[derive(Debug, Clone, PartialEq)]
pub struct FramePick {
    /// Take every n-th paired frame (1 = all).
    pub every: usize,
    /// With poses: a frame becomes a view once the camera has moved this far (metres) or turned
    /// this much (degrees) since the last view; overrides `every`.
    pub keyframes: Option<(f32, f32)>,
    /// At most this many views (the first ones picked).
    pub max_frames: usize,
}

impl Default for FramePick {
    fn default() -> Self {
        FramePick {
            every: 1,
            keyframes: None,
            max_frames: 10,
        }
    }
}

impl FramePick {
    /// Picks among `n` frames with optional poses: indices in order.
    pub fn pick(&self, n: usize, poses: &[Option<Isometry3<f32>>]) -> Vec<usize> {
        let mut out = Vec::new();
        let mut last: Option<Isometry3<f32>> = None;
        for i in 0..n {
            if out.len() >= self.max_frames {
                break;
            }
            let take = match (self.keyframes, poses.get(i).copied().flatten()) {
                (Some((metres, degrees)), Some(p)) => match last {
                    None => true,
                    Some(l) => {
                        let d = l.inverse() * p;
                        d.translation.vector.norm() >= metres
                            || d.rotation.angle().to_degrees() >= degrees
                    }
                },
                _ => i % self.every.max(1) == 0,
            };
            if take {
                out.push(i);
                last = poses.get(i).copied().flatten();
            }
        }
        out
    }
}

/// Whether `dir` is in the TUM layout.
pub fn is_tum(dir: &Path) -> bool {
    dir.join("rgb.txt").is_file() && dir.join("depth.txt").is_file()
}

/// `camera.json` of a TUM folder.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TumCamera {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    #[serde(default)]
    distortion: deocc_geometry::distortion::Distortion,
    #[serde(default)]
    depth_scale: Option<f64>,
}

/// (timestamp, rest of the line) of a TUM list file, naming the line of any problem.
fn read_list(path: &Path) -> Result<Vec<(f64, Vec<String>)>> {
    let text = std::fs::read_to_string(path).map_err(|e| IoError::new(path, e))?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut parts = line.split_whitespace();
        let t: f64 = parts
            .next()
            .and_then(|t| t.parse().ok())
            .filter(|t: &f64| t.is_finite())
            .ok_or_else(|| {
                IoError::invalid(path, format!("line {}: no timestamp in {line:?}", n + 1))
            })?;
        out.push((t, parts.map(str::to_string).collect()));
    }
    if out.is_empty() {
        return Err(IoError::invalid(path, "no entries"));
    }
    if out.windows(2).any(|w| w[1].0 < w[0].0) {
        return Err(IoError::invalid(
            path,
            "timestamps are not in increasing order",
        ));
    }
    Ok(out)
}

/// Index of the entry of `list` nearest to `t`, if within [`MAX_PAIR_GAP_S`].
fn nearest<T>(list: &[(f64, T)], t: f64) -> Option<usize> {
    let i = list.partition_point(|(s, _)| *s < t);
    [i.checked_sub(1), Some(i)]
        .into_iter()
        .flatten()
        .filter(|&j| j < list.len())
        .min_by(|&a, &b| (list[a].0 - t).abs().total_cmp(&(list[b].0 - t).abs()))
        .filter(|&j| (list[j].0 - t).abs() <= MAX_PAIR_GAP_S)
}

fn file_in(dir: &Path, list: &Path, line: &[String]) -> Result<PathBuf> {
    let name = line
        .first()
        .ok_or_else(|| IoError::invalid(list, "an entry has a timestamp but no file name"))?;
    if name.contains("..") || Path::new(name).is_absolute() {
        return Err(IoError::invalid(
            list,
            format!("{name:?} is not a path inside the sequence folder"),
        ));
    }
    Ok(dir.join(name))
}

/// Reads a TUM sequence folder into a scene of the frames `pick` chooses.
pub fn read_tum(dir: &Path, pick: &FramePick) -> Result<SceneInput> {
    let rgb_list = read_list(&dir.join("rgb.txt"))?;
    let depth_list = read_list(&dir.join("depth.txt"))?;
    let gt_path = dir.join("groundtruth.txt");
    let gt = if gt_path.exists() {
        let list = read_list(&gt_path)?;
        let mut poses = Vec::with_capacity(list.len());
        for (t, v) in list {
            let x: Vec<f64> = v.iter().filter_map(|s| s.parse().ok()).collect();
            if x.len() != 7 || x.iter().any(|v| !v.is_finite()) {
                return Err(IoError::invalid(
                    &gt_path,
                    format!("stamp {t}: expected tx ty tz qx qy qz qw, got {v:?}"),
                ));
            }
            let q = Quaternion::new(x[6], x[3], x[4], x[5]);
            if (q.norm() - 1.0).abs() > 1e-2 {
                return Err(IoError::invalid(
                    &gt_path,
                    format!(
                        "stamp {t}: quaternion of norm {:.4}, not a rotation",
                        q.norm()
                    ),
                ));
            }
            let pose = Isometry3::from_parts(
                Translation3::new(x[0], x[1], x[2]),
                UnitQuaternion::from_quaternion(q),
            )
            .cast::<f32>();
            poses.push((t, pose));
        }
        Some(poses)
    } else {
        None
    };
    let cam_path = dir.join("camera.json");
    let (fx, fy, cx, cy, distortion, scale) = if cam_path.exists() {
        let c: TumCamera = crate::cameras::read_json(&cam_path)?;
        (
            c.fx,
            c.fy,
            c.cx,
            c.cy,
            c.distortion,
            c.depth_scale.unwrap_or(TUM_DEPTH_SCALE),
        )
    } else {
        (
            525.0,
            525.0,
            319.5,
            239.5,
            Default::default(),
            TUM_DEPTH_SCALE,
        )
    };
    // Pair colour with depth (and a pose).
    struct Pair {
        rgb: PathBuf,
        depth: PathBuf,
        pose: Option<Isometry3<f32>>,
        stamp: f64,
    }
    let mut pairs = Vec::new();
    for (t, rest) in &rgb_list {
        let Some(d) = nearest(&depth_list, *t) else {
            continue;
        };
        let pose = match &gt {
            Some(g) => match nearest(g, *t) {
                Some(j) => Some(g[j].1),
                None => continue, // posed sequences keep only frames with a pose
            },
            None => None,
        };
        pairs.push(Pair {
            rgb: file_in(dir, &dir.join("rgb.txt"), rest)?,
            depth: file_in(dir, &dir.join("depth.txt"), &depth_list[d].1)?,
            pose,
            stamp: *t,
        });
    }
    if pairs.is_empty() {
        return Err(IoError::invalid(
            dir,
            format!(
                "no colour frame has a depth frame{} within {MAX_PAIR_GAP_S} s",
                if gt.is_some() { " and a pose" } else { "" }
            ),
        ));
    }
    let poses: Vec<_> = pairs.iter().map(|p| p.pose).collect();
    let chosen = pick.pick(pairs.len(), &poses);
    let mut frames = Vec::with_capacity(chosen.len());
    for i in chosen {
        let p = &pairs[i];
        let (w, h) = crate::images::image_size(&p.rgb)?;
        let intrinsics = Intrinsics::new(fx, fy, cx, cy, w, h)
            .and_then(|k| k.check_plausible().map(|_| k))
            .map_err(|e| IoError::invalid(&cam_path, e.to_string()))?;
        let fc = FrameCamera {
            name: format!("{:.6}", p.stamp).replace('.', "_"),
            intrinsics,
            world_from_camera: p.pose,
            lens: Lens {
                distortion: distortion.clone(),
                depth_scale: scale,
                depth_camera: None,
            },
        };
        let rgb = crate::images::read_rgb_png_expecting(&p.rgb, Some((w, h)))?;
        let depth = crate::images::read_depth_expecting(&p.depth, Some((w, h)), scale)?;
        let (rgb, depth, _) = crate::lens::to_pinhole(rgb, depth, None, &intrinsics, &fc.lens);
        if depth.valid_count() == 0 {
            return Err(IoError::invalid(&p.depth, "no valid depth in this frame"));
        }
        frames.push(Frame {
            name: fc.name,
            camera: Camera {
                intrinsics,
                world_from_camera: p.pose.unwrap_or_else(Isometry3::identity),
            },
            rgb,
            depth,
            instances: None,
        });
    }
    Ok(SceneInput {
        dir: dir.to_path_buf(),
        frames,
        structure_ids: Vec::new(),
        posed: gt.is_some(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keyframes_follow_motion_and_every_nth_without_poses() {
        let poses: Vec<_> = (0..10)
            .map(|i| Some(Isometry3::translation(0.04 * i as f32, 0.0, 0.0)))
            .collect();
        let kf = FramePick {
            keyframes: Some((0.1, 10.0)),
            ..Default::default()
        };
        assert_eq!(kf.pick(10, &poses), vec![0, 3, 6, 9]);
        let every = FramePick {
            every: 4,
            max_frames: 2,
            ..Default::default()
        };
        assert_eq!(every.pick(10, &[]), vec![0, 4]);
    }

    #[test]
    fn nearest_stamps_within_the_gap() {
        let list = vec![(1.0, ()), (1.05, ()), (2.0, ())];
        assert_eq!(nearest(&list, 1.04), Some(1));
        assert_eq!(nearest(&list, 1.5), None);
        assert_eq!(nearest(&list, 2.01), Some(2));
    }
}
