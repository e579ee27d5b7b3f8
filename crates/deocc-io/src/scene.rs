//! The scene folder: deocc's input format, written by the benchmark renderer and by `deocc run
//! --example`, read by the pipeline.
//!
//! ```text
//! SCENE/
//!   cameras.json          intrinsics and (optional) world_from_camera poses per frame
//!   rgb/NAME.png          8-bit RGB (or rgb/NAME.jpg)
//!   depth/NAME.png        16-bit depth in millimetres (or units of `depth_scale`), 0 = no
//!                         measurement; or depth/NAME.npy, float32 metres
//!   instances/NAME.png    optional: u16 instance ids consistent across views, 0 = background
//!   scene.json            optional: which instances are room structure, their categories
//!   ground_truth.ply      optional: dense ground-truth surface samples with a `seen` flag
//! ```
//!
//! Reading checks everything before returning: every file exists and decodes, sizes agree with
//! `cameras.json`, frame names are plain file names and unique, poses are given for every frame
//! or for none. Lens distortion and a separate depth camera (see [`crate::cameras`]) are removed
//! here, once, so a frame is always a pinhole RGB-D frame registered to colour. It has no side effects: pose-free input is registered by the pipeline's
//! registration stage, explicitly.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use deocc_geometry::camera::Camera;
use deocc_geometry::DepthMap;
use image::RgbImage;
use serde::{Deserialize, Serialize};

use crate::cameras::{read_cameras_json, read_json, write_cameras_json, FrameCamera};
use crate::error::{IoError, Result};
use crate::images::{
    read_depth_expecting, read_instance_png_expecting, read_rgb_png_expecting, write_depth_png,
    write_instance_png, write_rgb_png, InstanceMap,
};

/// One RGB-D frame with its camera and (optional) instance map.
#[derive(Debug, Clone)]
pub struct Frame {
    pub name: String,
    pub camera: Camera,
    pub rgb: RgbImage,
    pub depth: DepthMap,
    pub instances: Option<InstanceMap>,
}

/// A scene: its frames and what its metadata says.
#[derive(Debug, Clone)]
pub struct SceneInput {
    /// Where it was read from (or a description for a scene made in memory).
    pub dir: PathBuf,
    pub frames: Vec<Frame>,
    /// Instance ids that are room structure (floor, walls): never completed.
    pub structure_ids: Vec<u16>,
    /// Whether `cameras.json` gave poses. Without them every frame's pose is the identity until
    /// the pipeline's registration stage estimates them.
    pub posed: bool,
}

/// The parts of `scene.json` deocc reads; other fields (the renderer's config, visibility) are
/// ignored.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct SceneMeta {
    #[serde(default)]
    pub objects: Vec<ObjectMeta>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ObjectMeta {
    pub instance_id: u16,
    /// Category name (`bottle`, `chair`, ...).
    pub category: String,
    /// Room structure (floor, walls).
    #[serde(default)]
    pub structure: bool,
    /// A shape family held out of training.
    #[serde(default)]
    pub held_out: bool,
}

/// Paths of a frame's files inside a scene folder.
pub fn frame_paths(dir: &Path, name: &str) -> [PathBuf; 3] {
    [
        dir.join("rgb").join(format!("{name}.png")),
        dir.join("depth").join(format!("{name}.png")),
        dir.join("instances").join(format!("{name}.png")),
    ]
}

/// A frame name must be a plain file name: not empty, no path separators, not `.` or `..`, no
/// leading dot, no control characters (so no frame can read a file outside the scene folder).
pub fn check_frame_name(name: &str) -> std::result::Result<(), String> {
    let bad = name.is_empty()
        || name.starts_with('.')
        || name
            .chars()
            .any(|c| c == '/' || c == '\\' || c == ':' || c.is_control());
    if bad {
        Err(format!(
            "frame name {name:?} is not a plain file name (letters, digits, '-', '_'; no path)"
        ))
    } else {
        Ok(())
    }
}

/// Reads `scene.json`.
pub fn read_scene_meta(path: &Path) -> Result<SceneMeta> {
    read_json(path)
}

/// Reads a scene folder (see the module documentation), checking everything first.
pub fn read_scene(dir: &Path) -> Result<SceneInput> {
    if !dir.is_dir() {
        return Err(IoError::invalid(
            dir,
            "not a folder (expected rgb/, depth/ and cameras.json inside)",
        ));
    }
    let cams_path = dir.join("cameras.json");
    if !cams_path.exists() {
        return Err(IoError::invalid(
            &cams_path,
            "missing: the intrinsics and poses of the frames",
        ));
    }
    let cams = read_cameras_json(&cams_path)?;
    let posed = cams
        .iter()
        .filter(|c| c.world_from_camera.is_some())
        .count();
    if posed != 0 && posed != cams.len() {
        return Err(IoError::invalid(
            &cams_path,
            format!(
                "{posed} of {} frames have a world_from_camera pose: give every frame a pose, or \
                 none (then the frames are registered by ICP in file order)",
                cams.len()
            ),
        ));
    }
    let mut names = BTreeSet::new();
    for c in &cams {
        check_frame_name(&c.name).map_err(|e| IoError::invalid(&cams_path, e))?;
        if !names.insert(c.name.as_str()) {
            return Err(IoError::invalid(
                &cams_path,
                format!("frame name {:?} appears twice", c.name),
            ));
        }
    }
    let mut frames = Vec::with_capacity(cams.len());
    for fc in &cams {
        frames.push(read_frame(dir, fc)?);
    }
    let meta_path = dir.join("scene.json");
    let structure_ids = if meta_path.exists() {
        read_scene_meta(&meta_path)?
            .objects
            .iter()
            .filter(|o| o.structure)
            .map(|o| o.instance_id)
            .collect()
    } else {
        Vec::new()
    };
    Ok(SceneInput {
        dir: dir.to_path_buf(),
        frames,
        structure_ids,
        posed: posed > 0,
    })
}

/// The first of `candidates` that exists, else the first (so the error names the usual file).
fn first_existing(candidates: Vec<PathBuf>) -> PathBuf {
    candidates
        .iter()
        .find(|p| p.exists())
        .cloned()
        .unwrap_or_else(|| candidates[0].clone())
}

fn read_frame(dir: &Path, fc: &FrameCamera) -> Result<Frame> {
    let camera = Camera {
        intrinsics: fc.intrinsics,
        world_from_camera: fc
            .world_from_camera
            .unwrap_or_else(nalgebra::Isometry3::identity),
    };
    let [rgb_path, depth_path, inst_path] = frame_paths(dir, &fc.name);
    // Colour as PNG or as the camera's own JPEG; depth as 16-bit PNG or a NumPy array.
    let rgb_path = first_existing(vec![
        rgb_path.clone(),
        rgb_path.with_extension("jpg"),
        rgb_path.with_extension("jpeg"),
    ]);
    let depth_path = first_existing(vec![depth_path.clone(), depth_path.with_extension("npy")]);
    let (w, h) = (fc.intrinsics.width(), fc.intrinsics.height());
    // Sizes are checked against cameras.json from the image headers, before decoding.
    let rgb = read_rgb_png_expecting(&rgb_path, Some((w, h)))?;
    let depth = read_depth_expecting(
        &depth_path,
        Some(fc.lens.depth_size(&fc.intrinsics)),
        fc.lens.depth_scale,
    )?;
    if depth.valid_count() == 0 {
        return Err(IoError::invalid(
            &depth_path,
            "no valid depth in this frame",
        ));
    }
    let instances = if inst_path.exists() {
        Some(read_instance_png_expecting(&inst_path, Some((w, h)))?)
    } else {
        None
    };
    let (rgb, depth, instances) =
        crate::lens::to_pinhole(rgb, depth, instances, &fc.intrinsics, &fc.lens);
    if depth.valid_count() == 0 {
        return Err(IoError::invalid(
            &depth_path,
            "no depth falls inside the colour image after registration: check \
             depth_camera.color_from_depth",
        ));
    }
    Ok(Frame {
        name: fc.name.clone(),
        camera,
        rgb,
        depth,
        instances,
    })
}

/// Writes a frame's images (`rgb/`, `depth/` and, if it has one, `instances/`) into a scene
/// folder, creating the sub-folders.
pub fn write_frame(dir: &Path, frame: &Frame) -> Result<()> {
    check_frame_name(&frame.name).map_err(|e| IoError::invalid(dir, e))?;
    let [rgb_path, depth_path, inst_path] = frame_paths(dir, &frame.name);
    for p in [&rgb_path, &depth_path, &inst_path] {
        if let Some(parent) = p.parent() {
            std::fs::create_dir_all(parent).map_err(|e| IoError::new(parent, e))?;
        }
    }
    write_rgb_png(&rgb_path, &frame.rgb)?;
    write_depth_png(&depth_path, &frame.depth)?;
    if let Some(inst) = &frame.instances {
        write_instance_png(&inst_path, inst)?;
    }
    Ok(())
}

/// Writes `cameras.json` for frames, with their poses when `posed`.
pub fn write_cameras(dir: &Path, frames: &[Frame], posed: bool) -> Result<()> {
    let cams: Vec<FrameCamera> = frames
        .iter()
        .map(|f| FrameCamera {
            name: f.name.clone(),
            intrinsics: f.camera.intrinsics,
            world_from_camera: posed.then_some(f.camera.world_from_camera),
            lens: Default::default(),
        })
        .collect();
    write_cameras_json(&dir.join("cameras.json"), &cams)
}

/// Writes a whole scene folder that [`read_scene`] reads back (frames, cameras, and `scene.json`
/// listing the structure ids when there are any).
pub fn write_scene(dir: &Path, scene: &SceneInput) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| IoError::new(dir, e))?;
    for f in &scene.frames {
        write_frame(dir, f)?;
    }
    write_cameras(dir, &scene.frames, scene.posed)?;
    if !scene.structure_ids.is_empty() {
        let meta = SceneMeta {
            objects: scene
                .structure_ids
                .iter()
                .map(|&id| ObjectMeta {
                    instance_id: id,
                    category: "structure".into(),
                    structure: true,
                    held_out: false,
                })
                .collect(),
        };
        crate::cameras::write_json(&dir.join("scene.json"), &meta)?;
    }
    Ok(())
}
