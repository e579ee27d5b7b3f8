//! Views as a ROS 2 bag in MCAP (`deocc-ros2 play SCENE --record FILE.mcap`): what `play` would
//! publish, written as `ros2 bag record -s mcap` writes it (CDR messages, `ros2msg` schemas), so
//! `deocc run FILE.mcap --rgb ... --poses POSE_TOPIC` can read a bag without a ROS installation.

use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::Path;

use byteorder::LittleEndian;
use serde::Serialize;

use crate::convert::View;

/// The topics a bag is written under.
#[derive(Debug, Clone)]
pub struct BagTopics {
    pub rgb: String,
    pub depth: String,
    pub info: String,
    /// geometry_msgs/PoseStamped of the camera (views without a pose write none).
    pub pose: Option<String>,
}

/// CDR little-endian with the 4-byte encapsulation header ROS 2 puts before every message.
fn cdr<T: Serialize>(msg: &T) -> Result<Vec<u8>, String> {
    let body = cdr_encoding::to_vec::<T, LittleEndian>(msg).map_err(|e| e.to_string())?;
    let mut out = vec![0u8, 1, 0, 0];
    out.extend(body);
    Ok(out)
}

/// Writes `views` to `path` as a ROS 2 bag in MCAP.
pub fn write_bag(path: &Path, views: &[View], topics: &BagTopics) -> Result<(), String> {
    let file = std::fs::File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut w = mcap::Writer::new(BufWriter::new(file)).map_err(|e| e.to_string())?;
    let mut channels = BTreeMap::<String, u16>::new();
    let mut channel = |w: &mut mcap::Writer<_>, topic: &str, ty: &str| -> Result<u16, String> {
        if let Some(&id) = channels.get(topic) {
            return Ok(id);
        }
        let sid = w
            .add_schema(ty, "ros2msg", b"")
            .map_err(|e| e.to_string())?;
        let id = w
            .add_channel(sid, topic, "cdr", &BTreeMap::new())
            .map_err(|e| e.to_string())?;
        channels.insert(topic.to_string(), id);
        Ok(id)
    };
    for (seq, v) in views.iter().enumerate() {
        let t = v.stamp().max(0) as u64;
        let mut log = |topic: &str, ty: &str, data: Vec<u8>| -> Result<(), String> {
            let id = channel(&mut w, topic, ty)?;
            w.write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: id,
                    sequence: seq as u32,
                    log_time: t,
                    publish_time: t,
                },
                &data,
            )
            .map_err(|e| e.to_string())
        };
        log(&topics.info, "sensor_msgs/msg/CameraInfo", cdr(&v.info)?)?;
        log(&topics.rgb, "sensor_msgs/msg/Image", cdr(&v.rgb)?)?;
        log(&topics.depth, "sensor_msgs/msg/Image", cdr(&v.depth)?)?;
        if let (Some(topic), Some(p)) = (&topics.pose, &v.pose) {
            log(topic, "geometry_msgs/msg/PoseStamped", cdr(p)?)?;
        }
    }
    w.finish().map_err(|e| e.to_string())?;
    Ok(())
}
