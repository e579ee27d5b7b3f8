//! ROS 2 messages to and from deocc's service messages. The service's Image, CameraInfo and
//! PointCloud2 are the sensor_msgs ones without headers, so this is field-for-field; every check
//! of the content (encodings, sizes, intrinsics, poses) is the service's own
//! (`deocc_service::request::scene_from_request`), so the bridge refuses what the server refuses,
//! with the same messages.

use deocc_service::proto;
use nalgebra::{Quaternion, UnitQuaternion};

use crate::msgs;

/// One synchronised RGB-D view: colour, depth, calibration and (if a pose topic is used) the
/// camera's pose at the same stamp.
#[derive(Debug, Clone)]
pub struct View {
    pub rgb: msgs::Image,
    pub depth: msgs::Image,
    pub info: msgs::CameraInfo,
    pub pose: Option<msgs::PoseStamped>,
}

impl View {
    /// The depth image's stamp, nanoseconds.
    pub fn stamp(&self) -> i64 {
        self.depth.header.stamp.nanos()
    }
}

fn image(m: &msgs::Image) -> proto::Image {
    proto::Image {
        height: m.height,
        width: m.width,
        encoding: m.encoding.clone(),
        is_bigendian: m.is_bigendian != 0,
        step: m.step,
        data: m.data.clone(),
    }
}

/// World-from-camera as row-major 4x4, or why not (named as the message's field).
pub fn pose_rows(p: &msgs::PoseStamped) -> Result<Vec<f64>, String> {
    let o = p.pose.orientation;
    let q = Quaternion::new(o.w, o.x, o.y, o.z);
    let n = q.norm();
    if !n.is_finite() || (n - 1.0).abs() > 1e-3 {
        return Err(format!(
            "pose.orientation: not a unit quaternion (norm {n})"
        ));
    }
    let t = p.pose.position;
    if ![t.x, t.y, t.z].iter().all(|v| v.is_finite()) {
        return Err("pose.position: not finite".into());
    }
    let r = UnitQuaternion::from_quaternion(q).to_rotation_matrix();
    let m = r.matrix();
    Ok(vec![
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        t.x, //
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        t.y, //
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
        t.z, //
        0.0,
        0.0,
        0.0,
        1.0,
    ])
}

/// The service request for `views` (named `view0`, `view1`, ... in order), or the first pose
/// that is not a rigid transform.
pub fn request(views: &[View], options_json: &str) -> Result<proto::CompleteRequest, String> {
    let frames = views
        .iter()
        .enumerate()
        .map(|(k, v)| {
            let world_from_camera = match &v.pose {
                Some(p) => pose_rows(p).map_err(|e| format!("view {k}: {e}"))?,
                None => Vec::new(),
            };
            Ok(proto::Frame {
                name: format!("view{k}"),
                rgb: Some(image(&v.rgb)),
                depth: Some(image(&v.depth)),
                camera_info: Some(proto::CameraInfo {
                    height: v.info.height,
                    width: v.info.width,
                    k: v.info.k.to_vec(),
                    distortion_model: v.info.distortion_model.clone(),
                    d: v.info.d.clone(),
                }),
                world_from_camera,
                instances: None,
            })
        })
        .collect::<Result<_, String>>()?;
    Ok(proto::CompleteRequest {
        frames,
        options_json: options_json.to_string(),
        segment: true,
        structure_ids: Vec::new(),
    })
}

fn ros_image(m: &proto::Image, header: &msgs::Header) -> msgs::Image {
    msgs::Image {
        header: header.clone(),
        height: m.height,
        width: m.width,
        encoding: m.encoding.clone(),
        is_bigendian: u8::from(m.is_bigendian),
        step: m.step,
        data: m.data.clone(),
    }
}

/// The pose message of a row-major 4x4 world-from-camera (its rotation re-orthonormalised).
pub fn pose_msg(rows: &[f64], header: msgs::Header) -> msgs::PoseStamped {
    let r = nalgebra::Matrix3::from_fn(|i, j| rows[4 * i + j]);
    // Closed form: nalgebra's iterative `from_matrix` returns the identity for half-turns.
    let q = deocc_geometry::rotation::nearest_unit_quaternion(&r);
    msgs::PoseStamped {
        header,
        pose: msgs::Pose {
            position: msgs::Point {
                x: rows[3],
                y: rows[7],
                z: rows[11],
            },
            orientation: msgs::Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        },
    }
}

/// The ROS views of a service request's frames, as a camera would publish them: frame `k`
/// stamped `start_ns + k * step_ns`, images in `camera_frame`, poses in `world_frame`.
pub fn views_from_request(
    req: &proto::CompleteRequest,
    start_ns: i64,
    step_ns: i64,
    camera_frame: &str,
    world_frame: &str,
) -> Vec<View> {
    req.frames
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let stamp = msgs::Time::from_nanos(start_ns + k as i64 * step_ns);
            let header = msgs::Header {
                stamp,
                frame_id: camera_frame.to_string(),
            };
            let info = f.camera_info.clone().unwrap_or_default();
            let mut k9 = [0.0; 9];
            for (d, s) in k9.iter_mut().zip(&info.k) {
                *d = *s;
            }
            View {
                rgb: ros_image(&f.rgb.clone().unwrap_or_default(), &header),
                depth: ros_image(&f.depth.clone().unwrap_or_default(), &header),
                info: msgs::CameraInfo {
                    header: header.clone(),
                    height: info.height,
                    width: info.width,
                    distortion_model: if info.distortion_model.is_empty() {
                        "plumb_bob".into()
                    } else {
                        info.distortion_model.clone()
                    },
                    d: if info.distortion_model.is_empty() {
                        vec![0.0; 5]
                    } else {
                        info.d.clone()
                    },
                    k: k9,
                    r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    p: [
                        k9[0], k9[1], k9[2], 0.0, k9[3], k9[4], k9[5], 0.0, 0.0, 0.0, 1.0, 0.0,
                    ],
                    ..Default::default()
                },
                pose: (f.world_from_camera.len() == 16).then(|| {
                    pose_msg(
                        &f.world_from_camera,
                        msgs::Header {
                            stamp,
                            frame_id: world_frame.to_string(),
                        },
                    )
                }),
            }
        })
        .collect()
}

/// The ROS message of a service cloud, bytes unchanged.
pub fn cloud_msg(c: proto::PointCloud2, header: msgs::Header) -> msgs::PointCloud2 {
    msgs::PointCloud2 {
        header,
        height: c.height,
        width: c.width,
        fields: c
            .fields
            .into_iter()
            .map(|f| msgs::PointField {
                name: f.name,
                offset: f.offset,
                datatype: f.datatype as u8,
                count: f.count,
            })
            .collect(),
        is_bigendian: c.is_bigendian,
        point_step: c.point_step,
        row_step: c.row_step,
        data: c.data,
        is_dense: c.is_dense,
    }
}

/// The service message of a ROS cloud (for `Grasp` / `Place` on a cloud received over ROS).
pub fn cloud_proto(c: &msgs::PointCloud2) -> proto::PointCloud2 {
    proto::PointCloud2 {
        height: c.height,
        width: c.width,
        fields: c
            .fields
            .iter()
            .map(|f| proto::PointField {
                name: f.name.clone(),
                offset: f.offset,
                datatype: u32::from(f.datatype),
                count: f.count,
            })
            .collect(),
        is_bigendian: c.is_bigendian,
        point_step: c.point_step,
        row_step: c.row_step,
        data: c.data.clone(),
        is_dense: c.is_dense,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    fn pose(q: UnitQuaternion<f64>, t: [f64; 3]) -> msgs::PoseStamped {
        msgs::PoseStamped {
            header: Default::default(),
            pose: msgs::Pose {
                position: msgs::Point {
                    x: t[0],
                    y: t[1],
                    z: t[2],
                },
                orientation: msgs::Quaternion {
                    x: q.i,
                    y: q.j,
                    z: q.k,
                    w: q.w,
                },
            },
        }
    }

    #[test]
    fn pose_rows_are_the_rotation_and_translation() {
        let q = UnitQuaternion::from_euler_angles(0.3, -1.1, 2.0);
        let rows = pose_rows(&pose(q, [1.0, -2.0, 0.5])).unwrap();
        let r: Rotation3<f64> = q.to_rotation_matrix();
        let v = Vector3::new(0.2, 0.7, -0.4);
        let want = r * v + Vector3::new(1.0, -2.0, 0.5);
        for i in 0..3 {
            let got: f64 = (0..3).map(|j| rows[4 * i + j] * v[j]).sum::<f64>() + rows[4 * i + 3];
            assert!(
                (got - want[i]).abs() < 1e-12,
                "row {i}: {got} vs {}",
                want[i]
            );
        }
        assert_eq!(&rows[12..], &[0.0, 0.0, 0.0, 1.0]);
    }

    #[test]
    fn half_turn_poses_survive_the_round_trip() {
        // A camera turned half about its y axis: nalgebra's iterative `from_matrix` read it as
        // the identity and the bridge published a pose 180 degrees off.
        let rows = vec![
            -1.0, 0.0, 0.0, 0.4, //
            0.0, 1.0, 0.0, -0.2, //
            0.0, 0.0, -1.0, 1.5, //
            0.0, 0.0, 0.0, 1.0,
        ];
        let back = pose_rows(&pose_msg(&rows, Default::default())).unwrap();
        for (k, (a, b)) in rows.iter().zip(&back).enumerate() {
            assert!((a - b).abs() < 1e-9, "entry {k}: {a} became {b}");
        }
    }

    #[test]
    fn bad_poses_are_named() {
        let mut p = pose(UnitQuaternion::identity(), [0.0; 3]);
        p.pose.orientation.w = 2.0;
        assert!(pose_rows(&p).unwrap_err().contains("pose.orientation"));
        let mut p = pose(UnitQuaternion::identity(), [0.0; 3]);
        p.pose.position.y = f64::NAN;
        assert!(pose_rows(&p).unwrap_err().contains("pose.position"));
    }

    #[test]
    fn views_and_requests_are_inverse() {
        let q = UnitQuaternion::from_euler_angles(0.1, 0.2, -0.3);
        let v = pose(q, [0.5, 0.25, 2.0]);
        let rows = pose_rows(&v).unwrap();
        let frame = proto::Frame {
            name: "view0".into(),
            rgb: Some(proto::Image {
                height: 1,
                width: 2,
                encoding: "rgb8".into(),
                is_bigendian: false,
                step: 6,
                data: vec![1, 2, 3, 4, 5, 6],
            }),
            depth: Some(proto::Image {
                height: 1,
                width: 2,
                encoding: "16UC1".into(),
                is_bigendian: false,
                step: 4,
                data: vec![0, 1, 2, 3],
            }),
            camera_info: Some(proto::CameraInfo {
                height: 1,
                width: 2,
                k: vec![100.0, 0.0, 1.0, 0.0, 100.0, 0.5, 0.0, 0.0, 1.0],
                ..Default::default()
            }),
            world_from_camera: rows.clone(),
            instances: None,
        };
        let req = proto::CompleteRequest {
            frames: vec![frame.clone(), frame],
            options_json: "{}".into(),
            segment: true,
            structure_ids: vec![],
        };
        let views = views_from_request(&req, 5, 100, "cam", "world");
        assert_eq!(views[1].stamp(), 105);
        let back = request(&views, "{}").unwrap();
        assert_eq!(back.frames[0].rgb, req.frames[0].rgb);
        assert_eq!(back.frames[1].depth, req.frames[1].depth);
        // A request without a lens becomes ROS's zero plumb_bob, which reads back as no lens.
        let (b, r) = (
            back.frames[0].camera_info.as_ref().unwrap(),
            req.frames[0].camera_info.as_ref().unwrap(),
        );
        assert_eq!((b.width, b.height, &b.k), (r.width, r.height, &r.k));
        assert!(
            deocc_geometry::distortion::Distortion::from_ros(&b.distortion_model, &b.d)
                .unwrap()
                .is_none()
        );
        for (a, b) in back.frames[0].world_from_camera.iter().zip(&rows) {
            assert!((a - b).abs() < 1e-12);
        }
        assert_eq!(back.frames[1].name, "view1");
    }

    #[test]
    fn clouds_cross_unchanged() {
        let c = proto::PointCloud2 {
            height: 1,
            width: 2,
            fields: deocc_service::cloud2::fields(),
            is_bigendian: false,
            point_step: 28,
            row_step: 56,
            data: (0..56).collect(),
            is_dense: true,
        };
        let ros = cloud_msg(c.clone(), msgs::Header::default());
        assert_eq!(ros.data, c.data);
        assert_eq!(cloud_proto(&ros), c);
    }
}
