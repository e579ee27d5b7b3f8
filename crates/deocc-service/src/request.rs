//! A `CompleteRequest` into a scene, checked as strictly as a scene folder is read: every error
//! names the field (`frames[2].depth.data`), and nothing is allocated beyond the request's own
//! size before the sizes agree.

use deocc_geometry::distortion::Distortion;
use std::path::PathBuf;

use deocc_geometry::camera::{Camera, Intrinsics};
use deocc_geometry::DepthMap;
use deocc_io::images::InstanceMap;
use deocc_pipeline::{Frame, PipelineOptions, SceneInput};
use image::RgbImage;
use nalgebra::Isometry3;

use crate::proto::{CameraInfo, CompleteRequest, Frame as Frame2, Image};
use crate::FieldError;

/// What a request may hold.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_frames: usize,
    /// Pixels of one frame.
    pub max_pixels: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_frames: 32,
            max_pixels: 4096 * 4096,
        }
    }
}

fn bad(field: impl Into<String>, msg: impl Into<String>) -> FieldError {
    FieldError::new(field, msg)
}

/// The rows of `img` (`bpp` bytes a pixel), checked against the frame's size.
fn rows<'a>(
    img: &'a Image,
    at: &str,
    size: (u32, u32),
    encodings: &[&str],
    bpp: usize,
) -> Result<impl Iterator<Item = &'a [u8]>, FieldError> {
    if !encodings.contains(&img.encoding.as_str()) {
        return Err(bad(
            format!("{at}.encoding"),
            format!("{:?} is not one of {encodings:?}", img.encoding),
        ));
    }
    if (img.width, img.height) != size {
        return Err(bad(
            at,
            format!(
                "is {}x{}, but camera_info says {}x{}",
                img.width, img.height, size.0, size.1
            ),
        ));
    }
    if img.is_bigendian && bpp > 1 {
        return Err(bad(
            format!("{at}.is_bigendian"),
            "big-endian images are not supported",
        ));
    }
    let (w, h) = (img.width as usize, img.height as usize);
    let step = img.step as usize;
    if step < w * bpp {
        return Err(bad(
            format!("{at}.step"),
            format!("{step} is less than width {w} x {bpp} bytes"),
        ));
    }
    if img.data.len() != step * h {
        return Err(bad(
            format!("{at}.data"),
            format!(
                "{} bytes, expected step {step} x height {h} = {}",
                img.data.len(),
                step * h
            ),
        ));
    }
    Ok(img
        .data
        .chunks_exact(step.max(1))
        .map(move |r| &r[..w * bpp]))
}

fn intrinsics(info: &CameraInfo, at: &str, limits: &Limits) -> Result<Intrinsics, FieldError> {
    if info.k.len() != 9 {
        return Err(bad(
            format!("{at}.k"),
            format!("has {} values, expected 9 (row-major 3x3)", info.k.len()),
        ));
    }
    if info.width as usize * info.height as usize > limits.max_pixels {
        return Err(bad(
            at,
            format!(
                "{}x{} is more than {} pixels",
                info.width, info.height, limits.max_pixels
            ),
        ));
    }
    let k = &info.k;
    if k.iter().any(|v| !v.is_finite()) {
        return Err(bad(format!("{at}.k"), format!("{k:?} is not finite")));
    }
    check_pinhole_k(k).map_err(|e| bad(format!("{at}.k"), format!("{k:?}: {e}")))?;
    let i = Intrinsics::new(
        k[0] as f32,
        k[4] as f32,
        k[2] as f32,
        k[5] as f32,
        info.width,
        info.height,
    )
    .and_then(|i| i.check_plausible().map(|_| i))
    .map_err(|e| bad(format!("{at}.k"), e.to_string()))?;
    Ok(i)
}

/// Median measured depth above which float depth cannot be metres (no RGB-D camera measures a
/// scene whose middle is this far).
pub const MAX_MEDIAN_DEPTH_M: f32 = 50.0;

/// 32FC1 depth is metres (REP 118); millimetres in a float image would be read as a scene a
/// thousand times too large. Refused with what to do when the median measured value cannot be
/// metres.
pub fn check_metres(depth: &[f32]) -> Result<(), String> {
    let mut valid: Vec<f32> = depth.iter().copied().filter(|&d| d > 0.0).collect();
    if valid.is_empty() {
        return Ok(());
    }
    let mid = valid.len() / 2;
    let (_, median, _) = valid.select_nth_unstable_by(mid, f32::total_cmp);
    if *median > MAX_MEDIAN_DEPTH_M {
        return Err(format!(
            "32FC1 depth is in metres (REP 118), but the median measured value is {median}: \
             millimetres? Divide by 1000, or send 16UC1 millimetres"
        ));
    }
    Ok(())
}

/// A row-major K must be `[fx, 0, cx, 0, fy, cy, 0, 0, 1]`: only four entries are read, so a
/// transposed matrix (cx, cy in the last row), a skewed one or one with `K[8] != 1` would
/// otherwise be read as another camera without a word.
pub fn check_pinhole_k(k: &[f64]) -> Result<(), String> {
    let scale = k[0].abs().max(k[4].abs()).max(1.0);
    for (i, want, what) in [
        (1, 0.0, "the skew K[1]"),
        (3, 0.0, "K[3]"),
        (6, 0.0, "K[6]"),
        (7, 0.0, "K[7]"),
        (8, 1.0, "K[8]"),
    ] {
        let tol = if i == 8 { 1e-9 } else { 1e-9 * scale };
        if (k[i] - want).abs() > tol {
            let hint = if i == 6 || i == 7 {
                " (is it transposed? K is row-major: [fx, 0, cx, 0, fy, cy, 0, 0, 1])"
            } else {
                " (a pinhole K is row-major [fx, 0, cx, 0, fy, cy, 0, 0, 1])"
            };
            return Err(format!("{what} is {}, must be {want}{hint}", k[i]));
        }
    }
    Ok(())
}

fn pose(m: &[f64], at: &str) -> Result<Isometry3<f32>, FieldError> {
    if m.len() != 16 {
        return Err(bad(
            at,
            format!("has {} values, expected 16 (row-major 4x4)", m.len()),
        ));
    }
    let rows: [[f64; 4]; 4] = std::array::from_fn(|r| std::array::from_fn(|c| m[r * 4 + c]));
    // The same parser as cameras.json's: a request and a scene folder give the same pose.
    deocc_io::cameras::pose_from_rows(&rows).map_err(|e| bad(at, e))
}

fn frame(
    req: &crate::proto::Frame,
    k: usize,
    limits: &Limits,
) -> Result<(Frame, bool), FieldError> {
    let at = format!("frames[{k}]");
    let info = req
        .camera_info
        .as_ref()
        .ok_or_else(|| bad(format!("{at}.camera_info"), "missing"))?;
    let intr = intrinsics(info, &format!("{at}.camera_info"), limits)?;
    let size = (info.width, info.height);
    let rgb_msg = req
        .rgb
        .as_ref()
        .ok_or_else(|| bad(format!("{at}.rgb"), "missing"))?;
    let bgr = rgb_msg.encoding == "bgr8";
    let mut rgb = Vec::with_capacity(size.0 as usize * size.1 as usize * 3);
    for row in rows(rgb_msg, &format!("{at}.rgb"), size, &["rgb8", "bgr8"], 3)? {
        if bgr {
            for px in row.chunks_exact(3) {
                rgb.extend_from_slice(&[px[2], px[1], px[0]]);
            }
        } else {
            rgb.extend_from_slice(row);
        }
    }
    let rgb = RgbImage::from_raw(size.0, size.1, rgb)
        .ok_or_else(|| bad(format!("{at}.rgb"), "size mismatch"))?;
    let depth_msg = req
        .depth
        .as_ref()
        .ok_or_else(|| bad(format!("{at}.depth"), "missing"))?;
    let mut depth = Vec::with_capacity(size.0 as usize * size.1 as usize);
    let mm = depth_msg.encoding == "16UC1";
    let bpp = if mm { 2 } else { 4 };
    for row in rows(
        depth_msg,
        &format!("{at}.depth"),
        size,
        &["16UC1", "32FC1"],
        bpp,
    )? {
        if mm {
            depth.extend(
                row.chunks_exact(2)
                    .map(|b| f32::from(u16::from_le_bytes([b[0], b[1]])) / 1000.0),
            );
        } else {
            // REP-118: NaN and +-inf mean no measurement, as 0 does.
            depth.extend(row.chunks_exact(4).map(|b| {
                let d = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                if d.is_finite() && d > 0.0 {
                    d
                } else {
                    0.0
                }
            }));
        }
    }
    if depth.iter().all(|&d| d == 0.0) {
        return Err(bad(
            format!("{at}.depth"),
            "has no valid measurement (every pixel 0 or NaN)",
        ));
    }
    if !mm {
        check_metres(&depth).map_err(|e| bad(format!("{at}.depth"), e))?;
    }
    let depth = DepthMap::new(size.0, size.1, depth)
        .map_err(|e| bad(format!("{at}.depth"), e.to_string()))?;
    let instances = match &req.instances {
        Some(img) => {
            let mut ids = Vec::with_capacity(size.0 as usize * size.1 as usize);
            for row in rows(
                img,
                &format!("{at}.instances"),
                size,
                &["16UC1", "mono16"],
                2,
            )? {
                ids.extend(
                    row.chunks_exact(2)
                        .map(|b| u16::from_le_bytes([b[0], b[1]])),
                );
            }
            Some(InstanceMap {
                width: size.0,
                height: size.1,
                ids,
            })
        }
        None => None,
    };
    let posed = !req.world_from_camera.is_empty();
    let world_from_camera = if posed {
        pose(&req.world_from_camera, &format!("{at}.world_from_camera"))?
    } else {
        Isometry3::identity()
    };
    // Lens distortion, removed once here as a scene folder's is at read time.
    let distortion = Distortion::from_ros(&info.distortion_model, &info.d)
        .map_err(|e| bad(format!("{at}.camera_info.d"), e))?;
    let lens = deocc_io::cameras::Lens {
        distortion,
        ..Default::default()
    };
    let (rgb, depth, instances) = deocc_io::lens::to_pinhole(rgb, depth, instances, &intr, &lens);
    let name = if req.name.is_empty() {
        format!("frame{k}")
    } else {
        deocc_io::scene::check_frame_name(&req.name).map_err(|e| bad(format!("{at}.name"), e))?;
        req.name.clone()
    };
    Ok((
        Frame {
            name,
            camera: Camera {
                intrinsics: intr,
                world_from_camera,
            },
            rgb,
            depth,
            instances,
        },
        posed,
    ))
}

/// The scene and options of a request, or the first problem, naming its field.
pub fn scene_from_request(
    req: &CompleteRequest,
    limits: &Limits,
) -> Result<(SceneInput, PipelineOptions), FieldError> {
    if req.frames.is_empty() {
        return Err(bad("frames", "no frame"));
    }
    if req.frames.len() > limits.max_frames {
        return Err(bad(
            "frames",
            format!(
                "{} frames, more than this server takes ({})",
                req.frames.len(),
                limits.max_frames
            ),
        ));
    }
    let opts = if req.options_json.trim().is_empty() {
        PipelineOptions::default()
    } else {
        let o: PipelineOptions = deocc_io::cameras::options_from_json(&req.options_json)
            .map_err(|e| bad("options_json", e))?;
        o.validate()
            .map_err(|e| bad("options_json", e.to_string()))?;
        o
    };
    let mut frames = Vec::with_capacity(req.frames.len());
    let mut posed = Vec::with_capacity(req.frames.len());
    let mut names = std::collections::BTreeSet::new();
    for (k, f) in req.frames.iter().enumerate() {
        let (frame, p) = frame(f, k, limits)?;
        if !names.insert(frame.name.clone()) {
            return Err(bad(
                format!("frames[{k}].name"),
                format!("{:?} is used by an earlier frame", frame.name),
            ));
        }
        frames.push(frame);
        posed.push(p);
    }
    if posed.iter().any(|&p| p) && !posed.iter().all(|&p| p) {
        let k = posed.iter().position(|&p| !p).unwrap_or(0);
        return Err(bad(
            format!("frames[{k}].world_from_camera"),
            "missing: give every frame a pose, or none",
        ));
    }
    let structure_ids = req
        .structure_ids
        .iter()
        .map(|&id| u16::try_from(id).map_err(|_| bad("structure_ids", format!("{id} > 65535"))))
        .collect::<Result<_, _>>()?;
    Ok((
        SceneInput {
            dir: PathBuf::from("request"),
            frames,
            structure_ids,
            posed: posed[0],
        },
        opts,
    ))
}

/// A request for `scene` (depth as 16UC1 millimetres, colour as rgb8, poses if the scene has
/// them, instance maps if the frames have them).
pub fn request_from_scene(scene: &SceneInput, options_json: &str) -> CompleteRequest {
    let frames = scene
        .frames
        .iter()
        .map(|f| {
            let (w, h) = (f.rgb.width(), f.rgb.height());
            let image = |encoding: &str, bpp: u32, data: Vec<u8>| Image {
                height: h,
                width: w,
                encoding: encoding.into(),
                is_bigendian: false,
                step: w * bpp,
                data,
            };
            let depth: Vec<u8> = f
                .depth
                .data()
                .iter()
                .flat_map(|&d| ((d * 1000.0).round().clamp(0.0, 65535.0) as u16).to_le_bytes())
                .collect();
            let i = &f.camera.intrinsics;
            let rows = deocc_io::cameras::pose_to_rows(&f.camera.world_from_camera);
            Frame2 {
                name: f.name.clone(),
                rgb: Some(image("rgb8", 3, f.rgb.as_raw().clone())),
                depth: Some(image("16UC1", 2, depth)),
                camera_info: Some(CameraInfo {
                    height: h,
                    width: w,
                    k: vec![
                        i.fx() as f64,
                        0.0,
                        i.cx() as f64,
                        0.0,
                        i.fy() as f64,
                        i.cy() as f64,
                        0.0,
                        0.0,
                        1.0,
                    ],
                    ..Default::default()
                }),
                world_from_camera: if scene.posed {
                    rows.iter().flatten().copied().collect()
                } else {
                    Vec::new()
                },
                instances: f.instances.as_ref().map(|m| {
                    image(
                        "16UC1",
                        2,
                        m.ids.iter().flat_map(|id| id.to_le_bytes()).collect(),
                    )
                }),
            }
        })
        .collect();
    CompleteRequest {
        frames,
        options_json: options_json.into(),
        segment: false,
        structure_ids: scene.structure_ids.iter().map(|&i| u32::from(i)).collect(),
    }
}

/// The view and pick of a `target_pick`: the camera (pinhole, pose) and the pixel or box moved
/// through the view's lens into pinhole pixels.
pub fn target_pick(
    p: &crate::proto::TargetPick,
) -> Result<(Camera, deocc_robot::target::Pick), FieldError> {
    use deocc_robot::target::Pick;
    let at = "target_pick";
    let info = p
        .camera_info
        .as_ref()
        .ok_or_else(|| bad(format!("{at}.camera_info"), "missing"))?;
    let intr = intrinsics(info, &format!("{at}.camera_info"), &Limits::default())?;
    let lens = Distortion::from_ros(&info.distortion_model, &info.d)
        .map_err(|e| bad(format!("{at}.camera_info.d"), e))?;
    let world_from_camera = if p.world_from_camera.is_empty() {
        Isometry3::identity()
    } else {
        pose(&p.world_from_camera, &format!("{at}.world_from_camera"))?
    };
    let text = p
        .pixel
        .iter()
        .map(|v| v.to_string())
        .collect::<Vec<_>>()
        .join(",");
    let pick = Pick::parse(&text).map_err(|e| bad(format!("{at}.pixel"), e))?;
    let pick = pick
        .through_lens(&lens, &intr)
        .ok_or_else(|| bad(format!("{at}.pixel"), "outside the lens model's range"))?;
    Ok((
        Camera {
            intrinsics: intr,
            world_from_camera,
        },
        pick,
    ))
}
