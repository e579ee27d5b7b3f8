//! Stage: record. A run as an MCAP file (`deocc run --mcap`), for Foxglove Studio or any MCAP
//! reader: each frame's camera (calibration and its transform from `world`), colour, depth and
//! instance images, and the completed cloud split by provenance into separate topics (observed,
//! model, rules, plane fill), all in Foxglove's JSON schemas.
//!
//! Topics: `/deocc/camera/NAME/{rgb,depth,instances,calibration}`, `/tf`,
//! `/deocc/points/{observed,model,rules,plane_fill}`, and, when the caller planned robot tasks on
//! the cloud ([`RobotAnnotations`]), `/deocc/grasps` (grippers as boxes: palm and two fingers,
//! a colour per instance) and `/deocc/placeable` (the placeable cells as points) with
//! `/deocc/placement` (the chosen spot, the object's box). Frame k is logged at k x 0.1 s (scrub
//! through the views); the clouds and robot results at 0.

use std::collections::BTreeMap;
use std::io::{BufWriter, Seek, Write};
use std::path::Path;

use base64::Engine;
use deocc_geometry::{PointCloud, Provenance};
use serde_json::{json, Value};

use crate::{PipelineError, SceneInput};

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

fn stamp(ns: u64) -> Value {
    json!({ "sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000 })
}

struct Recorder<W: Write + Seek> {
    w: mcap::Writer<W>,
    channels: BTreeMap<String, u16>,
}

impl<W: Write + Seek> Recorder<W> {
    fn log(&mut self, topic: &str, schema: &str, t_ns: u64, msg: &Value) -> mcap::McapResult<()> {
        let id = match self.channels.get(topic) {
            Some(&id) => id,
            None => {
                let body = json!({ "title": schema, "type": "object" }).to_string();
                let sid = self.w.add_schema(schema, "jsonschema", body.as_bytes())?;
                let id = self.w.add_channel(sid, topic, "json", &BTreeMap::new())?;
                self.channels.insert(topic.to_string(), id);
                id
            }
        };
        let data = serde_json::to_vec(msg).unwrap_or_default();
        self.w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: id,
                sequence: 0,
                log_time: t_ns,
                publish_time: t_ns,
            },
            &data,
        )
    }
}

fn image(t: u64, frame_id: &str, w: u32, h: u32, encoding: &str, bpp: u32, data: &[u8]) -> Value {
    json!({
        "timestamp": stamp(t), "frame_id": frame_id, "width": w, "height": h,
        "encoding": encoding, "step": w * bpp, "data": b64(data),
    })
}

/// `cloud`'s points of provenance `p` as a foxglove.PointCloud (x y z float32, r g b a uint8).
fn points(cloud: &PointCloud, p: Provenance) -> (usize, Value) {
    let codes = cloud.generated.as_deref();
    let mut data = Vec::new();
    let mut n = 0;
    for (i, q) in cloud.positions.iter().enumerate() {
        if codes.map_or(0, |c| c[i]) != p.code() {
            continue;
        }
        let c = cloud.colors.as_ref().map_or([128; 3], |c| c[i]);
        for v in [q.x, q.y, q.z] {
            data.extend_from_slice(&v.to_le_bytes());
        }
        data.extend_from_slice(&[c[0], c[1], c[2], 255]);
        n += 1;
    }
    (n, cloud_msg(&data))
}

/// A foxglove.PointCloud in `world` of 16-byte points: x y z float32, r g b a uint8.
fn cloud_msg(data: &[u8]) -> Value {
    let field =
        |name: &str, offset: u32, ty: u32| json!({"name": name, "offset": offset, "type": ty});
    json!({
        "timestamp": stamp(0), "frame_id": "world",
        "pose": {"position": {"x": 0, "y": 0, "z": 0}, "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}},
        "point_stride": 16,
        // foxglove.NumericType: UINT8 = 1, FLOAT32 = 7.
        "fields": [field("x", 0, 7), field("y", 4, 7), field("z", 8, 7),
                   field("red", 12, 1), field("green", 13, 1), field("blue", 14, 1), field("alpha", 15, 1)],
        "data": b64(data),
    })
}

/// One planned grasp, as the recording draws it.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedGrasp {
    pub instance: u32,
    /// Centre of the palm's front face, world frame.
    pub position: [f32; 3],
    /// World-from-gripper rotation, row-major; columns approach, closing, height.
    pub rotation: [[f32; 3]; 3],
    /// Opening between the fingers, metres.
    pub width: f32,
    /// Finger size: along the approach, across (closing axis), along the height axis, metres.
    pub finger: [f32; 3],
}

/// Robot-task results planned on the completed cloud (by the caller: the pipeline does not
/// plan), drawn in the recording.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RobotAnnotations {
    pub grasps: Vec<RecordedGrasp>,
    /// Centres of the placeable cells, world frame.
    pub placeable: Vec<[f32; 3]>,
    /// The chosen placement: the footprint's centre on the support, world frame.
    pub placement: Option<[f32; 3]>,
    /// The placed object's footprint (w, d) and height, metres; `up` is gravity's opposite.
    pub object: [f32; 3],
    pub up: [f32; 3],
}

fn quat(r: &nalgebra::Rotation3<f32>) -> Value {
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(r);
    json!({"x": q.i, "y": q.j, "z": q.k, "w": q.w})
}

fn cube(
    centre: nalgebra::Point3<f32>,
    r: &nalgebra::Rotation3<f32>,
    size: [f32; 3],
    rgba: [f32; 4],
) -> Value {
    json!({
        "pose": {"position": {"x": centre.x, "y": centre.y, "z": centre.z}, "orientation": quat(r)},
        "size": {"x": size[0], "y": size[1], "z": size[2]},
        "color": {"r": rgba[0], "g": rgba[1], "b": rgba[2], "a": rgba[3]},
    })
}

fn entity(id: &str, cubes: Vec<Value>) -> Value {
    json!({
        "timestamp": stamp(0), "frame_id": "world", "id": id,
        "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": false, "metadata": [],
        "arrows": [], "cubes": cubes, "spheres": [], "cylinders": [], "lines": [],
        "triangles": [], "texts": [], "models": [],
    })
}

/// A distinct colour for instance `id`.
fn instance_colour(id: u32) -> [f32; 4] {
    let h = (id.wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32;
    let c = |k: f32| ((h + k).fract() * 6.0 - 3.0).abs().clamp(1.0, 2.0) - 1.0;
    [c(0.0), c(2.0 / 3.0), c(1.0 / 3.0), 0.8]
}

/// The gripper of `g` as three boxes: the palm behind the front face and the two fingers.
fn gripper_cubes(g: &RecordedGrasp) -> Vec<Value> {
    let m = nalgebra::Matrix3::from_fn(|i, j| g.rotation[i][j]);
    let r = deocc_geometry::rotation::nearest_rotation(&m);
    let (approach, closing) = (m.column(0).into_owned(), m.column(1).into_owned());
    let p = nalgebra::Point3::from(g.position);
    let [depth, fw, fh] = g.finger;
    let colour = instance_colour(g.instance);
    let palm_t = fw;
    let mut out = vec![cube(
        p - approach * (palm_t / 2.0),
        &r,
        [palm_t, g.width + 2.0 * fw, fh],
        colour,
    )];
    for side in [-1.0f32, 1.0] {
        out.push(cube(
            p + approach * (depth / 2.0) + closing * (side * (g.width + fw) / 2.0),
            &r,
            [depth, fw, fh],
            colour,
        ));
    }
    out
}

fn record_robot<W: Write + Seek>(
    r: &mut Recorder<W>,
    a: &RobotAnnotations,
) -> mcap::McapResult<()> {
    if !a.grasps.is_empty() {
        let entities: Vec<Value> = a
            .grasps
            .iter()
            .enumerate()
            .map(|(k, g)| entity(&format!("grasp_{}_{k}", g.instance), gripper_cubes(g)))
            .collect();
        r.log(
            "/deocc/grasps",
            "foxglove.SceneUpdate",
            0,
            &json!({"deletions": [], "entities": entities}),
        )?;
    }
    if !a.placeable.is_empty() {
        let mut data = Vec::with_capacity(a.placeable.len() * 16);
        for c in &a.placeable {
            for v in c {
                data.extend_from_slice(&v.to_le_bytes());
            }
            data.extend_from_slice(&[40, 200, 80, 255]);
        }
        r.log(
            "/deocc/placeable",
            "foxglove.PointCloud",
            0,
            &cloud_msg(&data),
        )?;
    }
    if let Some(p) = a.placement {
        let up = nalgebra::Vector3::from(a.up).normalize();
        let level = nalgebra::Rotation3::rotation_between(&nalgebra::Vector3::z(), &up)
            .unwrap_or_else(nalgebra::Rotation3::identity);
        let centre = nalgebra::Point3::from(p) + up * (a.object[2] / 2.0);
        r.log(
            "/deocc/placement",
            "foxglove.SceneUpdate",
            0,
            &json!({"deletions": [], "entities": [entity("placement", vec![cube(centre, &level, a.object, [0.1, 0.9, 0.3, 0.6])])]}),
        )?;
    }
    Ok(())
}

fn record<W: Write + Seek>(
    out: W,
    scene: &SceneInput,
    completed: &PointCloud,
    robot: Option<&RobotAnnotations>,
) -> mcap::McapResult<()> {
    let mut r = Recorder {
        w: mcap::Writer::new(out)?,
        channels: BTreeMap::new(),
    };
    // What a scene folder's scene.json says, for `deocc run RECORDING.mcap`.
    let structure: Vec<String> = scene.structure_ids.iter().map(|i| i.to_string()).collect();
    r.w.write_metadata(&mcap::records::Metadata {
        name: "deocc.scene".into(),
        metadata: BTreeMap::from([
            ("structure_ids".to_string(), structure.join(",")),
            ("posed".to_string(), scene.posed.to_string()),
        ]),
    })?;
    for (k, f) in scene.frames.iter().enumerate() {
        let t = k as u64 * 100_000_000;
        let id = format!("camera_{}", f.name);
        let base = format!("/deocc/camera/{}", f.name);
        let i = &f.camera.intrinsics;
        let (w, h) = (i.width(), i.height());
        let (fx, fy, cx, cy) = (i.fx(), i.fy(), i.cx(), i.cy());
        r.log(
            &format!("{base}/calibration"),
            "foxglove.CameraCalibration",
            t,
            &json!({
                "timestamp": stamp(t), "frame_id": id, "width": w, "height": h,
                "distortion_model": "plumb_bob", "D": [0, 0, 0, 0, 0],
                "K": [fx, 0, cx, 0, fy, cy, 0, 0, 1],
                "R": [1, 0, 0, 0, 1, 0, 0, 0, 1],
                "P": [fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0],
            }),
        )?;
        let pose = &f.camera.world_from_camera;
        let (tr, q) = (pose.translation.vector, pose.rotation);
        r.log(
            "/tf",
            "foxglove.FrameTransform",
            t,
            &json!({
                "timestamp": stamp(t), "parent_frame_id": "world", "child_frame_id": id,
                "translation": {"x": tr.x, "y": tr.y, "z": tr.z},
                "rotation": {"x": q.i, "y": q.j, "z": q.k, "w": q.w},
            }),
        )?;
        r.log(
            &format!("{base}/rgb"),
            "foxglove.RawImage",
            t,
            &image(t, &id, w, h, "rgb8", 3, f.rgb.as_raw()),
        )?;
        let mm: Vec<u8> = f
            .depth
            .data()
            .iter()
            .flat_map(|&d| ((d * 1000.0).round().clamp(0.0, 65535.0) as u16).to_le_bytes())
            .collect();
        r.log(
            &format!("{base}/depth"),
            "foxglove.RawImage",
            t,
            &image(t, &id, w, h, "16UC1", 2, &mm),
        )?;
        if let Some(m) = &f.instances {
            let ids: Vec<u8> = m.ids.iter().flat_map(|v| v.to_le_bytes()).collect();
            r.log(
                &format!("{base}/instances"),
                "foxglove.RawImage",
                t,
                &image(t, &id, w, h, "mono16", 2, &ids),
            )?;
        }
    }
    for (p, topic) in [
        (Provenance::Observed, "observed"),
        (Provenance::Model, "model"),
        (Provenance::Rules, "rules"),
        (Provenance::PlaneFill, "plane_fill"),
    ] {
        let (n, msg) = points(completed, p);
        if n > 0 {
            r.log(
                &format!("/deocc/points/{topic}"),
                "foxglove.PointCloud",
                0,
                &msg,
            )?;
        }
    }
    if let Some(a) = robot {
        record_robot(&mut r, a)?;
    }
    r.w.finish().map(|_| ())
}

/// Writes the recording of a run to `path` (see the module docs).
pub fn write_mcap(
    path: &Path,
    scene: &SceneInput,
    completed: &PointCloud,
    robot: Option<&RobotAnnotations>,
) -> Result<(), PipelineError> {
    let file = std::fs::File::create(path)
        .map_err(|e| PipelineError::input(path, format!("cannot write: {e}")))?;
    record(BufWriter::new(file), scene, completed, robot).map_err(|e| {
        PipelineError::input(
            path,
            format!("writing the MCAP recording: {}", mcap_why(&e)),
        )
    })
}

/// The cause of an MCAP error in words: mcap's own text for I/O errors ("I/O error from
/// writing, or reading a compression stream") hides the cause, such as a full disk.
fn mcap_why(e: &mcap::McapError) -> String {
    match e {
        mcap::McapError::Io(io) => match io.raw_os_error() {
            Some(28) => format!("the disk is full ({io})"),
            _ => io.to_string(),
        },
        other => other.to_string(),
    }
}

#[cfg(test)]
mod why_tests {
    use super::*;

    #[test]
    fn a_full_disk_is_named_not_hidden_behind_mcaps_words() {
        let full = mcap::McapError::Io(std::io::Error::from_raw_os_error(28));
        let why = mcap_why(&full);
        assert!(why.contains("the disk is full"), "{why}");
        assert!(!why.contains("compression stream"), "{why}");
        let denied =
            mcap::McapError::Io(std::io::Error::from(std::io::ErrorKind::PermissionDenied));
        assert!(mcap_why(&denied).to_lowercase().contains("permission"));
    }
}
