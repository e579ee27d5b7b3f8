//! Reading a scene folder: `cameras.json`, `rgb/NAME.png`, `depth/NAME.png` (16-bit mm) and,
//! optionally, `instances/NAME.png` (u16 instance ids, consistent across views) and `scene.json`
//! (a benchmark scene's metadata: which instances are room structure).
//!
//! Poses are optional: when no frame of `cameras.json` has a `world_from_camera`, the frames are
//! registered by frame-to-frame point-to-plane ICP ([`crate::poses::FrameToFrameIcp`]) in file
//! order, which must then be the capture order.

use std::path::{Path, PathBuf};

use deocc_geometry::camera::Camera;
use deocc_geometry::DepthMap;
use deocc_io::cameras::read_cameras_json;
use deocc_io::images::{read_depth_png, read_instance_png, read_rgb_png, InstanceMap};
use image::RgbImage;

use crate::PipelineError;

/// One RGB-D frame with its camera and (optional) instance map.
pub struct Frame {
    pub name: String,
    pub camera: Camera,
    pub rgb: RgbImage,
    pub depth: DepthMap,
    pub instances: Option<InstanceMap>,
}

/// A scene as read from disk.
pub struct SceneInput {
    pub dir: PathBuf,
    pub frames: Vec<Frame>,
    /// Instance ids that are room structure (floor, walls): never completed.
    pub structure_ids: Vec<u16>,
    /// Per-frame ICP figures when the poses were registered here (pose-free input), else empty.
    pub registration: Vec<crate::poses::FrameRegistration>,
}

fn invalid(path: &Path, msg: impl Into<String>) -> PipelineError {
    PipelineError::Input {
        path: path.to_path_buf(),
        msg: msg.into(),
    }
}

pub fn read_scene(dir: &Path) -> Result<SceneInput, PipelineError> {
    if !dir.is_dir() {
        return Err(invalid(
            dir,
            "not a folder (expected rgb/, depth/ and cameras.json inside)",
        ));
    }
    let cams_path = dir.join("cameras.json");
    if !cams_path.exists() {
        return Err(invalid(
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
        return Err(invalid(
            &cams_path,
            format!(
                "{posed} of {} frames have a world_from_camera pose: give every frame a pose, or \
                 none (then the frames are registered by ICP in file order)",
                cams.len()
            ),
        ));
    }
    let mut frames = Vec::new();
    for fc in cams {
        let camera = Camera {
            intrinsics: fc.intrinsics,
            world_from_camera: fc
                .world_from_camera
                .unwrap_or_else(nalgebra::Isometry3::identity),
        };
        let rgb_path = dir.join("rgb").join(format!("{}.png", fc.name));
        let depth_path = dir.join("depth").join(format!("{}.png", fc.name));
        let rgb = read_rgb_png(&rgb_path)?;
        let depth = read_depth_png(&depth_path)?;
        let (w, h) = (fc.intrinsics.width(), fc.intrinsics.height());
        if (rgb.width(), rgb.height()) != (w, h) {
            return Err(invalid(
                &rgb_path,
                format!(
                    "image is {}x{} but cameras.json says {w}x{h}",
                    rgb.width(),
                    rgb.height()
                ),
            ));
        }
        if (depth.width(), depth.height()) != (w, h) {
            return Err(invalid(
                &depth_path,
                format!(
                    "depth is {}x{} but cameras.json says {w}x{h}",
                    depth.width(),
                    depth.height()
                ),
            ));
        }
        if depth.valid_count() == 0 {
            return Err(invalid(&depth_path, "no valid depth in this frame"));
        }
        let inst_path = dir.join("instances").join(format!("{}.png", fc.name));
        let instances = if inst_path.exists() {
            let m = read_instance_png(&inst_path)?;
            if (m.width, m.height) != (w, h) {
                return Err(invalid(
                    &inst_path,
                    format!(
                        "instance map is {}x{} but the frame is {w}x{h}",
                        m.width, m.height
                    ),
                ));
            }
            Some(m)
        } else {
            None
        };
        frames.push(Frame {
            name: fc.name,
            camera,
            rgb,
            depth,
            instances,
        });
    }
    let scene_json = dir.join("scene.json");
    let structure_ids = if scene_json.exists() {
        let info: deocc_synth::dataset::SceneInfo = deocc_io::cameras::read_json(&scene_json)?;
        info.objects
            .iter()
            .filter(|o| o.structure)
            .map(|o| o.instance_id)
            .collect()
    } else {
        Vec::new()
    };
    let registration = if posed == 0 {
        crate::poses::FrameToFrameIcp::default().register(&mut frames)?
    } else {
        Vec::new()
    };
    Ok(SceneInput {
        dir: dir.to_path_buf(),
        frames,
        structure_ids,
        registration,
    })
}

impl SceneInput {
    /// A rendered benchmark scene as pipeline input, without a round trip through files (depth is
    /// quantised to millimetres as the PNG files would store it, so results match `deocc run`).
    pub fn from_rendered(rendered: &deocc_synth::dataset::RenderedScene) -> Self {
        let frames = rendered
            .views
            .iter()
            .enumerate()
            .map(|(v, view)| {
                let mm: Vec<f32> = view
                    .depth
                    .data()
                    .iter()
                    .map(|&d| {
                        let q = (d * 1000.0).round();
                        if q > 0.0 && q <= 65535.0 {
                            q / 1000.0
                        } else {
                            0.0
                        }
                    })
                    .collect();
                let (w, h) = (view.frame.width, view.frame.height);
                Frame {
                    name: format!("{v:06}"),
                    camera: view.camera,
                    rgb: view.rgb.clone(),
                    depth: DepthMap::new(w, h, mm).unwrap_or_else(|_| DepthMap::zeros(w, h)),
                    instances: Some(InstanceMap {
                        width: w,
                        height: h,
                        ids: view.frame.instance.clone(),
                    }),
                }
            })
            .collect();
        let structure_ids = rendered.scene.structure_ids();
        Self {
            dir: PathBuf::from(format!("<scene seed {}>", rendered.scene.seed)),
            frames,
            structure_ids,
            registration: Vec::new(),
        }
    }
}
