//! Recordings as input: an MCAP file of camera images, calibration and transforms, read into the
//! same checked [`SceneInput`] a scene folder gives (`deocc run RECORDING.mcap`).
//!
//! Two message encodings are read:
//! - `json` in Foxglove's schemas (`foxglove.RawImage`, `foxglove.CameraCalibration`,
//!   `foxglove.FrameTransform`), as `deocc run --mcap` writes them;
//! - `cdr`, ROS 2's (`sensor_msgs/msg/Image`, `sensor_msgs/msg/CameraInfo`,
//!   `tf2_msgs/msg/TFMessage`), as `ros2 bag record -s mcap` writes them.
//!
//! Topics are given by name, with at most one `*` standing for one path segment so that one
//! pattern covers a camera per view: `--rgb '/deocc/camera/*/rgb'` pairs each view's colour with
//! `/deocc/camera/<same>/depth`. Without `--info` the calibration is the sibling topic
//! `calibration` or `camera_info`; instance maps are read from a sibling `instances` topic when
//! there is one. Colour and depth pair by header stamp within 20 ms; the pose of a view is the
//! transform whose child frame is the image's `frame_id` (or `--poses FRAME`), nearest in time
//! within 20 ms. Frames are then picked as in a TUM sequence (every n-th, or keyframes by
//! motion). Bad topics and stamps are named in the error, with the topics the file has.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use base64::Engine;
use deocc_geometry::camera::{Camera, Intrinsics};
use deocc_geometry::distortion::Distortion;
use deocc_geometry::DepthMap;
use deocc_io::cameras::Lens;
use deocc_io::images::InstanceMap;
use deocc_io::tum::{FramePick, MAX_PAIR_GAP_S};
use image::RgbImage;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde_json::Value;

use crate::{Frame, PipelineError, SceneInput};

/// What to read from a recording.
#[derive(Debug, Clone, Default)]
pub struct RecordingOptions {
    /// Colour topic (or pattern); default `/deocc/camera/*/rgb` when the file has it.
    pub rgb: Option<String>,
    /// Depth topic (or pattern); default the colour topic's sibling `depth`.
    pub depth: Option<String>,
    /// Calibration topic (or pattern); default the sibling `calibration` or `camera_info`.
    pub info: Option<String>,
    /// The camera pose: a `geometry_msgs/PoseStamped` topic, or the TF child frame whose
    /// transform it is; default each image's `frame_id` in `/tf`.
    pub poses: Option<String>,
    pub pick: FramePick,
}

struct Img {
    stamp: i64,
    frame_id: String,
    width: u32,
    height: u32,
    encoding: String,
    step: u32,
    data: Vec<u8>,
}

struct Info {
    width: u32,
    height: u32,
    k: [f64; 9],
    model: String,
    d: Vec<f64>,
}

/// A topic pattern's match: `Some(capture)` ("" without `*`).
fn capture(pattern: &str, topic: &str) -> Option<String> {
    match pattern.split_once('*') {
        None => (pattern == topic).then(String::new),
        Some((pre, post)) => {
            let mid = topic.strip_prefix(pre)?.strip_suffix(post)?;
            (!mid.is_empty() && !mid.contains('/')).then(|| mid.to_string())
        }
    }
}

fn sibling(pattern: &str, leaf: &str) -> String {
    match pattern.rsplit_once('/') {
        Some((parent, _)) => format!("{parent}/{leaf}"),
        None => leaf.to_string(),
    }
}

// ---- CDR (ROS 2's encoding: 4-byte encapsulation header, then aligned fields) ----

struct Cdr<'a> {
    buf: &'a [u8],
    pos: usize,
    le: bool,
}

impl<'a> Cdr<'a> {
    fn new(buf: &'a [u8]) -> Result<Self, String> {
        if buf.len() < 4 {
            return Err("CDR message shorter than its header".into());
        }
        Ok(Cdr {
            buf,
            pos: 4,
            le: buf[1] & 1 == 1,
        })
    }
    fn take(&mut self, n: usize, align: usize) -> Result<&'a [u8], String> {
        let rel = self.pos - 4;
        self.pos += (align - rel % align) % align;
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        let end = end.ok_or("CDR message cut short")?;
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, String> {
        let b: [u8; 4] = self.take(4, 4)?.try_into().expect("4 bytes");
        Ok(if self.le {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }
    fn f64(&mut self) -> Result<f64, String> {
        let b: [u8; 8] = self.take(8, 8)?.try_into().expect("8 bytes");
        Ok(if self.le {
            f64::from_le_bytes(b)
        } else {
            f64::from_be_bytes(b)
        })
    }
    fn string(&mut self) -> Result<String, String> {
        let n = self.u32()? as usize;
        let b = self.take(n, 1)?;
        Ok(String::from_utf8_lossy(b.strip_suffix(&[0]).unwrap_or(b)).into_owned())
    }
    fn bytes(&mut self) -> Result<&'a [u8], String> {
        let n = self.u32()? as usize;
        self.take(n, 1)
    }
    /// std_msgs/Header: (stamp in ns, frame_id).
    fn header(&mut self) -> Result<(i64, String), String> {
        let sec = self.u32()? as i32 as i64;
        let nsec = self.u32()? as i64;
        Ok((sec * 1_000_000_000 + nsec, self.string()?))
    }
}

fn cdr_image(buf: &[u8]) -> Result<Img, String> {
    let mut c = Cdr::new(buf)?;
    let (stamp, frame_id) = c.header()?;
    let height = c.u32()?;
    let width = c.u32()?;
    let encoding = c.string()?;
    let big = c.take(1, 1)?[0] != 0;
    if big {
        return Err("big-endian image data is not supported".into());
    }
    let step = c.u32()?;
    let data = c.bytes()?.to_vec();
    Ok(Img {
        stamp,
        frame_id,
        width,
        height,
        encoding,
        step,
        data,
    })
}

fn cdr_info(buf: &[u8]) -> Result<Info, String> {
    let mut c = Cdr::new(buf)?;
    c.header()?;
    let height = c.u32()?;
    let width = c.u32()?;
    let model = c.string()?;
    let n = c.u32()? as usize;
    if n > 64 {
        return Err(format!("CameraInfo with {n} distortion coefficients"));
    }
    let d = (0..n).map(|_| c.f64()).collect::<Result<_, _>>()?;
    let mut k = [0.0; 9];
    for v in &mut k {
        *v = c.f64()?;
    }
    Ok(Info {
        width,
        height,
        k,
        model,
        d,
    })
}

/// geometry_msgs/PoseStamped: (stamp, world-from-camera).
fn cdr_pose(buf: &[u8]) -> Result<(i64, Isometry3<f32>), String> {
    let mut c = Cdr::new(buf)?;
    let (stamp, _) = c.header()?;
    let t: Vec<f64> = (0..3).map(|_| c.f64()).collect::<Result<_, _>>()?;
    let q: Vec<f64> = (0..4).map(|_| c.f64()).collect::<Result<_, _>>()?;
    Ok((stamp, iso(&t, &q)?))
}

/// TFMessage: (stamp, child frame, parent-from-child).
fn cdr_tf(buf: &[u8]) -> Result<Vec<(i64, String, Isometry3<f32>)>, String> {
    let mut c = Cdr::new(buf)?;
    let n = c.u32()? as usize;
    let mut out = Vec::new();
    for _ in 0..n.min(10_000) {
        let (stamp, _parent) = c.header()?;
        let child = c.string()?;
        let t: Vec<f64> = (0..3).map(|_| c.f64()).collect::<Result<_, _>>()?;
        let q: Vec<f64> = (0..4).map(|_| c.f64()).collect::<Result<_, _>>()?;
        out.push((stamp, child, iso(&t, &q)?));
    }
    Ok(out)
}

fn iso(t: &[f64], q: &[f64]) -> Result<Isometry3<f32>, String> {
    let quat = Quaternion::new(q[3], q[0], q[1], q[2]);
    if t.iter().chain(q).any(|v| !v.is_finite()) || (quat.norm() - 1.0).abs() > 1e-2 {
        return Err(format!("transform {t:?} {q:?} is not a rigid motion"));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_quaternion(quat),
    )
    .cast())
}

// ---- Foxglove JSON ----

fn json_stamp(v: &Value) -> i64 {
    let s = &v["timestamp"];
    s["sec"].as_i64().unwrap_or(0) * 1_000_000_000 + s["nsec"].as_i64().unwrap_or(0)
}

fn json_image(v: &Value) -> Result<Img, String> {
    let data = base64::engine::general_purpose::STANDARD
        .decode(v["data"].as_str().ok_or("image without data")?)
        .map_err(|e| format!("image data is not base64: {e}"))?;
    let num = |k: &str| v[k].as_u64().ok_or(format!("image without {k}"));
    Ok(Img {
        stamp: json_stamp(v),
        frame_id: v["frame_id"].as_str().unwrap_or_default().to_string(),
        width: num("width")? as u32,
        height: num("height")? as u32,
        encoding: v["encoding"].as_str().unwrap_or_default().to_string(),
        step: num("step")? as u32,
        data,
    })
}

fn json_info(v: &Value) -> Result<Info, String> {
    let k: Vec<f64> = v["K"]
        .as_array()
        .ok_or("calibration without K")?
        .iter()
        .filter_map(Value::as_f64)
        .collect();
    let k: [f64; 9] = k
        .try_into()
        .map_err(|_| "calibration's K is not 9 numbers")?;
    Ok(Info {
        width: v["width"].as_u64().unwrap_or(0) as u32,
        height: v["height"].as_u64().unwrap_or(0) as u32,
        k,
        model: v["distortion_model"].as_str().unwrap_or_default().into(),
        d: v["D"]
            .as_array()
            .map(|d| d.iter().filter_map(Value::as_f64).collect())
            .unwrap_or_default(),
    })
}

fn json_tf(v: &Value) -> Result<Vec<(i64, String, Isometry3<f32>)>, String> {
    let t = &v["translation"];
    let r = &v["rotation"];
    let f = |o: &Value, k: &str| o[k].as_f64().ok_or(format!("transform without {k}"));
    Ok(vec![(
        json_stamp(v),
        v["child_frame_id"].as_str().unwrap_or_default().to_string(),
        iso(
            &[f(t, "x")?, f(t, "y")?, f(t, "z")?],
            &[f(r, "x")?, f(r, "y")?, f(r, "z")?, f(r, "w")?],
        )?,
    )])
}

// ---- images into frames ----

fn rows(img: &Img, bpp: usize) -> Result<impl Iterator<Item = &[u8]>, String> {
    let row = img.width as usize * bpp;
    if (img.step as usize) < row || img.data.len() < img.step as usize * img.height as usize {
        return Err(format!(
            "{}x{} {} image has step {} and {} bytes",
            img.width,
            img.height,
            img.encoding,
            img.step,
            img.data.len()
        ));
    }
    Ok(img
        .data
        .chunks_exact(img.step as usize)
        .take(img.height as usize)
        .map(move |r| &r[..row]))
}

fn to_rgb(img: &Img) -> Result<RgbImage, String> {
    let (bpp, order): (usize, [usize; 3]) = match img.encoding.as_str() {
        "rgb8" => (3, [0, 1, 2]),
        "bgr8" => (3, [2, 1, 0]),
        "rgba8" => (4, [0, 1, 2]),
        "bgra8" => (4, [2, 1, 0]),
        "mono8" => (1, [0, 0, 0]),
        e => {
            return Err(format!(
                "colour encoding {e:?} (rgb8, bgr8, rgba8, bgra8, mono8)"
            ))
        }
    };
    let mut out = Vec::with_capacity(img.width as usize * img.height as usize * 3);
    for r in rows(img, bpp)? {
        for px in r.chunks_exact(bpp) {
            out.extend(order.map(|i| px[i]));
        }
    }
    RgbImage::from_raw(img.width, img.height, out).ok_or_else(|| "colour size".into())
}

fn to_depth(img: &Img) -> Result<DepthMap, String> {
    let mut out = Vec::with_capacity(img.width as usize * img.height as usize);
    match img.encoding.as_str() {
        "16UC1" | "mono16" => {
            for r in rows(img, 2)? {
                out.extend(
                    r.chunks_exact(2)
                        .map(|b| u16::from_le_bytes([b[0], b[1]]) as f32 / 1000.0),
                );
            }
        }
        "32FC1" => {
            for r in rows(img, 4)? {
                out.extend(r.chunks_exact(4).map(|b| {
                    let d = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                    if d.is_finite() && d > 0.0 {
                        d
                    } else {
                        0.0
                    }
                }));
            }
        }
        e => {
            return Err(format!(
                "depth encoding {e:?} (16UC1 millimetres or 32FC1 metres)"
            ))
        }
    }
    DepthMap::new(img.width, img.height, out).map_err(|e| e.to_string())
}

fn to_ids(img: &Img) -> Result<InstanceMap, String> {
    let mut ids = Vec::with_capacity(img.width as usize * img.height as usize);
    for r in rows(img, 2)? {
        ids.extend(r.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])));
    }
    Ok(InstanceMap {
        width: img.width,
        height: img.height,
        ids,
    })
}

/// The topic patterns a recording is read with.
struct Patterns {
    rgb: String,
    depth: String,
    info: String,
    inst: String,
}

/// The messages of a recording, by pattern capture.
#[derive(Default)]
struct Messages {
    rgb: Vec<(String, Img)>,
    depth: BTreeMap<String, Vec<Img>>,
    inst: BTreeMap<String, Vec<Img>>,
    info: BTreeMap<String, Info>,
    tf: BTreeMap<String, Vec<(i64, Isometry3<f32>)>>,
    pose_topic: Option<String>,
    pose_msgs: Vec<(i64, Isometry3<f32>)>,
}

/// One colour image with the depth (and instance map) it pairs with, and its pose.
struct Candidate<'a> {
    key: &'a str,
    rgb: &'a Img,
    depth: &'a Img,
    inst: Option<&'a Img>,
    pose: Option<Isometry3<f32>>,
}

/// The file's topics and deocc's scene metadata, read before the messages to choose defaults
/// and to name the topics in errors.
fn scan(
    bytes: &[u8],
    bad: &dyn Fn(String) -> PipelineError,
) -> Result<(BTreeSet<String>, BTreeMap<String, String>), PipelineError> {
    let mut topics = BTreeSet::new();
    let mut meta = BTreeMap::new();
    for rec in
        mcap::read::ChunkFlattener::new(bytes).map_err(|e| bad(format!("not an MCAP file: {e}")))?
    {
        match rec.map_err(|e| bad(format!("reading the MCAP file: {e}")))? {
            mcap::records::Record::Channel(c) => {
                topics.insert(c.topic.clone());
            }
            mcap::records::Record::Metadata(m) if m.name == "deocc.scene" => meta = m.metadata,
            _ => {}
        }
    }
    Ok((topics, meta))
}

fn listing(topics: &BTreeSet<String>) -> String {
    let t: Vec<&str> = topics.iter().map(String::as_str).collect();
    format!("the file's topics: {}", t.join(", "))
}

/// The patterns given, or the defaults the file's topics allow; each must match a topic.
fn patterns(
    opts: &RecordingOptions,
    topics: &BTreeSet<String>,
    bad: &dyn Fn(String) -> PipelineError,
) -> Result<Patterns, PipelineError> {
    let listing = || listing(topics);
    let rgb_pat = match &opts.rgb {
        Some(t) => t.clone(),
        None if topics
            .iter()
            .any(|t| capture("/deocc/camera/*/rgb", t).is_some()) =>
        {
            "/deocc/camera/*/rgb".into()
        }
        None => {
            return Err(bad(format!(
                "which topic is colour? Give --rgb TOPIC; {}",
                listing()
            )))
        }
    };
    let depth_pat = opts
        .depth
        .clone()
        .unwrap_or_else(|| sibling(&rgb_pat, "depth"));
    let info_pat = opts.info.clone().unwrap_or_else(|| {
        ["calibration", "camera_info"]
            .map(|l| sibling(&rgb_pat, l))
            .into_iter()
            .find(|p| topics.iter().any(|t| capture(p, t).is_some()))
            .unwrap_or_else(|| sibling(&rgb_pat, "camera_info"))
    });
    let inst_pat = sibling(&rgb_pat, "instances");
    for (what, pat) in [
        ("--rgb", &rgb_pat),
        ("--depth", &depth_pat),
        ("calibration (--info)", &info_pat),
    ] {
        if !topics.iter().any(|t| capture(pat, t).is_some()) {
            return Err(bad(format!("{what} {pat:?}: no such topic; {}", listing())));
        }
    }
    Ok(Patterns {
        rgb: rgb_pat,
        depth: depth_pat,
        info: info_pat,
        inst: inst_pat,
    })
}

/// Every message the patterns, `/tf` and the pose topic select, decoded.
fn collect(
    bytes: &[u8],
    p: &Patterns,
    opts: &RecordingOptions,
    topics: &BTreeSet<String>,
    bad: &dyn Fn(String) -> PipelineError,
) -> Result<Messages, PipelineError> {
    let (rgb_pat, depth_pat, inst_pat, info_pat) = (&p.rgb, &p.depth, &p.inst, &p.info);
    let mut rgb: Vec<(String, Img)> = Vec::new();
    let mut depth: BTreeMap<String, Vec<Img>> = BTreeMap::new();
    let mut inst: BTreeMap<String, Vec<Img>> = BTreeMap::new();
    let mut info: BTreeMap<String, Info> = BTreeMap::new();
    let mut tf: BTreeMap<String, Vec<(i64, Isometry3<f32>)>> = BTreeMap::new();
    let pose_topic = opts.poses.as_ref().filter(|p| topics.contains(*p)).cloned();
    let mut pose_msgs: Vec<(i64, Isometry3<f32>)> = Vec::new();
    for m in mcap::MessageStream::new(bytes).map_err(|e| bad(format!("not an MCAP file: {e}")))? {
        let m = m.map_err(|e| bad(format!("reading the MCAP file: {e}")))?;
        let topic = &m.channel.topic;
        let cdr = match m.channel.message_encoding.as_str() {
            "cdr" => true,
            "json" => false,
            _ => continue,
        };
        let at = |e: String| bad(format!("topic {topic} at {} ns: {e}", m.log_time));
        let json = || -> Result<Value, String> {
            serde_json::from_slice(&m.data).map_err(|e| format!("not JSON: {e}"))
        };
        let image = || {
            if cdr {
                cdr_image(&m.data)
            } else {
                json_image(&json()?)
            }
        };
        if pose_topic.as_ref() == Some(topic) {
            if cdr {
                pose_msgs.push(cdr_pose(&m.data).map_err(at)?);
            }
        } else if let Some(k) = capture(rgb_pat, topic) {
            rgb.push((k, image().map_err(at)?));
        } else if let Some(k) = capture(depth_pat, topic) {
            depth.entry(k).or_default().push(image().map_err(at)?);
        } else if let Some(k) = capture(inst_pat, topic) {
            inst.entry(k).or_default().push(image().map_err(at)?);
        } else if let Some(k) = capture(info_pat, topic) {
            let i = if cdr {
                cdr_info(&m.data)
            } else {
                json().and_then(|v| json_info(&v))
            };
            info.insert(k, i.map_err(at)?);
        } else if topic == "/tf" || topic == "/tf_static" {
            let t = if cdr {
                cdr_tf(&m.data)
            } else {
                json().and_then(|v| json_tf(&v))
            };
            for (stamp, child, pose) in t.map_err(at)? {
                tf.entry(child).or_default().push((stamp, pose));
            }
        }
    }
    Ok(Messages {
        rgb,
        depth,
        inst,
        info,
        tf,
        pose_topic,
        pose_msgs,
    })
}

/// One chosen candidate as a checked pinhole frame named `name`.
fn to_frame(
    c: &Candidate,
    name: String,
    posed: bool,
    m: &Messages,
    p: &Patterns,
    bad: &dyn Fn(String) -> PipelineError,
) -> Result<Frame, PipelineError> {
    let (rgb_pat, info_pat, info) = (&p.rgb, &p.info, &m.info);
    let at = |e: String| bad(format!("{rgb_pat} at {} ns: {e}", c.rgb.stamp));
    let inf = info
        .get(c.key)
        .ok_or_else(|| at(format!("no calibration on {info_pat:?} for this camera")))?;
    if (inf.width, inf.height) != (c.rgb.width, c.rgb.height) {
        return Err(at(format!(
            "calibration is {}x{} but the image is {}x{}",
            inf.width, inf.height, c.rgb.width, c.rgb.height
        )));
    }
    let k = &inf.k;
    let intr = Intrinsics::new(
        k[0] as f32,
        k[4] as f32,
        k[2] as f32,
        k[5] as f32,
        inf.width,
        inf.height,
    )
    .and_then(|i| i.check_plausible().map(|_| i))
    .map_err(|e| at(e.to_string()))?;
    let lens = Lens {
        distortion: Distortion::from_ros(&inf.model, &inf.d).map_err(at)?,
        ..Default::default()
    };
    let rgb_img = to_rgb(c.rgb).map_err(at)?;
    let d = to_depth(c.depth).map_err(at)?;
    if (d.width(), d.height()) != (intr.width(), intr.height()) {
        return Err(at(format!(
            "depth is {}x{}, colour {}x{}: depth must be registered to colour",
            d.width(),
            d.height(),
            intr.width(),
            intr.height()
        )));
    }
    let ids = c.inst.map(to_ids).transpose().map_err(at)?;
    let (rgb_img, d, ids) = deocc_io::lens::to_pinhole(rgb_img, d, ids, &intr, &lens);
    Ok(Frame {
        name,
        camera: Camera {
            intrinsics: intr,
            world_from_camera: if posed {
                c.pose.expect("posed")
            } else {
                Isometry3::identity()
            },
        },
        rgb: rgb_img,
        depth: d,
        instances: ids,
    })
}

/// Reads a recording into a scene (see the module documentation).
pub fn read_mcap(path: &Path, opts: &RecordingOptions) -> Result<SceneInput, PipelineError> {
    let bad = |msg: String| PipelineError::input(path, msg);
    let bytes = std::fs::read(path).map_err(|e| bad(format!("cannot read: {e}")))?;
    let (topics, meta) = scan(&bytes, &bad)?;
    let p = patterns(opts, &topics, &bad)?;
    let mut m = collect(&bytes, &p, opts, &topics, &bad)?;
    let (rgb_pat, depth_pat) = (&p.rgb, &p.depth);
    if m.rgb.is_empty() {
        return Err(bad(format!("no colour image on {rgb_pat:?}")));
    }
    m.rgb
        .sort_by(|a, b| a.1.stamp.cmp(&b.1.stamp).then(a.0.cmp(&b.0)));
    let gap = (MAX_PAIR_GAP_S * 1e9) as i64;
    let nearest = |list: &[Img], t: i64| -> Option<usize> {
        (0..list.len())
            .min_by_key(|&i| (list[i].stamp - t).abs())
            .filter(|&i| (list[i].stamp - t).abs() <= gap)
    };
    let (tf, pose_topic, pose_msgs) = (&m.tf, &m.pose_topic, &m.pose_msgs);
    let pose_of = |frame: &str, t: i64| -> Option<Isometry3<f32>> {
        if pose_topic.is_some() {
            return pose_msgs
                .iter()
                .min_by_key(|(s, _)| (s - t).abs())
                .filter(|(s, _)| (s - t).abs() <= gap)
                .map(|(_, p)| *p);
        }
        let child = opts.poses.as_deref().unwrap_or(frame);
        let list = tf.get(child)?;
        list.iter()
            .min_by_key(|(s, _)| (s - t).abs())
            .filter(|(s, _)| (s - t).abs() <= gap || list.len() == 1)
            .map(|(_, p)| *p)
    };
    let listing = || listing(&topics);
    if let Some(f) = &opts.poses {
        if pose_topic.is_none() && !tf.contains_key(f) {
            let have: Vec<&String> = tf.keys().collect();
            return Err(bad(format!(
                "--poses {f:?}: neither a PoseStamped topic nor a /tf child frame (frames in \
                 /tf: {have:?}; {})",
                listing()
            )));
        }
        if pose_topic.is_some() && pose_msgs.is_empty() {
            return Err(bad(format!(
                "--poses {f:?}: no CDR PoseStamped message on it"
            )));
        }
    }
    let mut cands = Vec::new();
    let mut unpaired = 0;
    for (key, img) in &m.rgb {
        let Some(ds) = m.depth.get(key) else {
            unpaired += 1;
            continue;
        };
        let Some(d) = nearest(ds, img.stamp) else {
            unpaired += 1;
            continue;
        };
        let inst = m
            .inst
            .get(key)
            .and_then(|l| nearest(l, img.stamp).map(|i| &l[i]));
        cands.push(Candidate {
            key,
            rgb: img,
            depth: &ds[d],
            inst,
            pose: pose_of(&img.frame_id, img.stamp),
        });
    }
    if cands.is_empty() {
        return Err(bad(format!(
            "no colour image on {rgb_pat:?} has a depth image on {depth_pat:?} within {} ms \
             ({unpaired} unpaired)",
            gap / 1_000_000
        )));
    }
    // Poses for all frames or none.
    let posed = cands.iter().all(|c| c.pose.is_some());
    let poses: Vec<_> = cands
        .iter()
        .map(|c| if posed { c.pose } else { None })
        .collect();
    let mut frames = Vec::new();
    let mut names = BTreeSet::new();
    for (n, &i) in opts.pick.pick(cands.len(), &poses).iter().enumerate() {
        let c = &cands[i];
        // A capture that is a plain, unused file name names the frame (`run --mcap`'s own).
        let name = if deocc_io::scene::check_frame_name(c.key).is_ok()
            && names.insert(c.key.to_string())
        {
            c.key.to_string()
        } else {
            format!("{n:06}")
        };
        frames.push(to_frame(c, name, posed, &m, &p, &bad)?);
    }
    let structure_ids = meta
        .get("structure_ids")
        .map(|s| s.split(',').filter_map(|v| v.trim().parse().ok()).collect())
        .unwrap_or_default();
    Ok(SceneInput {
        dir: path.to_path_buf(),
        frames,
        structure_ids,
        posed,
    })
}

/// Reads any input deocc takes: a scene folder, a TUM RGB-D sequence folder (`rgb.txt`,
/// `depth.txt`), or an MCAP recording; all into the same checked scene.
pub fn read_input(path: &Path, opts: &RecordingOptions) -> Result<SceneInput, PipelineError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("mcap") if path.is_file() => read_mcap(path, opts),
        Some("db3") => Err(PipelineError::input(
            path,
            "a rosbag2 SQLite recording: convert it to MCAP first (`ros2 bag convert`, or record \
             with `ros2 bag record -s mcap`)",
        )),
        Some("rawlog") if path.is_file() => Ok(deocc_io::rawlog::read_rawlog(path, &opts.pick)?),
        _ if path.is_dir() && deocc_io::tum::is_tum(path) => {
            Ok(deocc_io::tum::read_tum(path, &opts.pick)?)
        }
        _ => Ok(deocc_io::scene::read_scene(path)?),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_capture_one_segment() {
        assert_eq!(
            capture("/deocc/camera/*/rgb", "/deocc/camera/000001/rgb"),
            Some("000001".into())
        );
        assert_eq!(
            capture("/deocc/camera/*/rgb", "/deocc/camera/a/b/rgb"),
            None
        );
        assert_eq!(
            capture("/camera/color", "/camera/color"),
            Some(String::new())
        );
        assert_eq!(
            sibling("/deocc/camera/*/rgb", "depth"),
            "/deocc/camera/*/depth"
        );
    }

    #[test]
    fn cdr_image_and_info_decode_with_alignment() {
        // Image: header (stamp 3 s + 5 ns, frame "cam"), 1x2 rgb8, step 6.
        let mut b = vec![0, 1, 0, 0];
        b.extend(3u32.to_le_bytes());
        b.extend(5u32.to_le_bytes());
        b.extend(4u32.to_le_bytes());
        b.extend(b"cam\0");
        b.extend(1u32.to_le_bytes());
        b.extend(2u32.to_le_bytes());
        b.extend(5u32.to_le_bytes());
        b.extend(b"rgb8\0");
        b.push(0); // is_bigendian, then padding to 4
        b.extend([0, 0]);
        b.extend(6u32.to_le_bytes());
        b.extend(6u32.to_le_bytes());
        b.extend([1, 2, 3, 4, 5, 6]);
        let img = cdr_image(&b).unwrap();
        assert_eq!((img.stamp, img.frame_id.as_str()), (3_000_000_005, "cam"));
        assert_eq!((img.width, img.height, img.step), (2, 1, 6));
        assert_eq!(to_rgb(&img).unwrap().as_raw(), &vec![1, 2, 3, 4, 5, 6]);
        assert!(cdr_image(&b[..b.len() - 1]).is_err());
    }
}
