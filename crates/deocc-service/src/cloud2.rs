//! The sensor_msgs/PointCloud2 layout of a completed cloud: one row, little-endian, 32 bytes a
//! point, so a ROS node copies `data` into its message without repacking.
//!
//! | field      | offset | type    | meaning                                              |
//! |------------|--------|---------|------------------------------------------------------|
//! | x, y, z    | 0-11   | FLOAT32 | world frame, metres                                  |
//! | rgb        | 12     | FLOAT32 | packed 0x00RRGGBB (the PCL convention)               |
//! | instance   | 16     | UINT32  | instance id, 0 = background                          |
//! | confidence | 20     | FLOAT32 | 1 observed; generated: the cloud's own, see [`confidence`] |
//! | provenance | 24     | UINT8   | 0 observed, 1 model, 2 plane fill, 3 rules           |
//! | expected_error | 28 | FLOAT32 | metres: 0 observed; generated: how far off it may be  |
//!
//! Decoding accepts any layout with FLOAT32 x, y, z (and optionally rgb, a UINT32 or UINT16
//! instance, a UINT8 provenance, a FLOAT32 confidence and a FLOAT32 expected_error) at any
//! offsets, as other ROS nodes write them.

use deocc_geometry::{PointCloud, Provenance};
use nalgebra::Point3;

use crate::proto::{PointCloud2, PointField};
use crate::FieldError;

pub const POINT_STEP: u32 = 32;
const INT8: u32 = 1;
const UINT8: u32 = 2;
const UINT16: u32 = 4;
const UINT32: u32 = 6;
const FLOAT32: u32 = 7;
const FLOAT64: u32 = 8;

/// The confidence a point of provenance `code` carries when its cloud has none of its own: 1 for
/// observed points, 0.5 for generated ones. Clouds from the pipeline carry their own (the
/// completer's probability that the pixel belongs to the object).
pub fn confidence(code: u8) -> f32 {
    if code == Provenance::Observed.code() {
        1.0
    } else {
        0.5
    }
}

fn field(name: &str, offset: u32, datatype: u32) -> PointField {
    PointField {
        name: name.into(),
        offset,
        datatype,
        count: 1,
    }
}

/// The fields of deocc's layout, in order.
pub fn fields() -> Vec<PointField> {
    vec![
        field("x", 0, FLOAT32),
        field("y", 4, FLOAT32),
        field("z", 8, FLOAT32),
        field("rgb", 12, FLOAT32),
        field("instance", 16, UINT32),
        field("confidence", 20, FLOAT32),
        field("provenance", 24, UINT8),
        field("expected_error", 28, FLOAT32),
    ]
}

/// `cloud` in deocc's layout (missing colours are grey, missing instances 0, missing
/// provenance observed, missing expected errors 0).
pub fn encode(cloud: &PointCloud) -> PointCloud2 {
    let n = cloud.len();
    let mut data = Vec::with_capacity(n * POINT_STEP as usize);
    for i in 0..n {
        let p = cloud.positions[i];
        let c = cloud.colors.as_ref().map_or([128; 3], |c| c[i]);
        let id = cloud.instance.as_ref().map_or(0, |v| v[i]);
        let g = cloud.generated.as_ref().map_or(0, |v| v[i]);
        let k = cloud
            .confidence
            .as_ref()
            .map_or_else(|| confidence(g), |v| v[i]);
        let rgb = (u32::from(c[0]) << 16) | (u32::from(c[1]) << 8) | u32::from(c[2]);
        let mut point = [0u8; POINT_STEP as usize];
        point[0..4].copy_from_slice(&p.x.to_le_bytes());
        point[4..8].copy_from_slice(&p.y.to_le_bytes());
        point[8..12].copy_from_slice(&p.z.to_le_bytes());
        point[12..16].copy_from_slice(&rgb.to_le_bytes());
        point[16..20].copy_from_slice(&id.to_le_bytes());
        point[20..24].copy_from_slice(&k.to_le_bytes());
        point[24] = g;
        let e = cloud.expected_error.as_ref().map_or(0.0, |v| v[i]);
        point[28..32].copy_from_slice(&e.to_le_bytes());
        data.extend_from_slice(&point);
    }
    PointCloud2 {
        height: 1,
        width: n as u32,
        fields: fields(),
        is_bigendian: false,
        point_step: POINT_STEP,
        row_step: POINT_STEP * n as u32,
        data,
        is_dense: true,
    }
}

fn bad(field: &str, msg: impl Into<String>) -> FieldError {
    FieldError::new(field, msg)
}

fn size_of(datatype: u32) -> Option<usize> {
    match datatype {
        INT8 | UINT8 => Some(1),
        3 | UINT16 => Some(2),
        5 | UINT32 | FLOAT32 => Some(4),
        FLOAT64 => Some(8),
        _ => None,
    }
}

/// A cloud from any PointCloud2 with FLOAT32 x, y, z; errors name `what` and the field.
pub fn decode(msg: &PointCloud2, what: &str) -> Result<PointCloud, FieldError> {
    if msg.is_bigendian {
        return Err(bad(
            &format!("{what}.is_bigendian"),
            "big-endian clouds are not supported",
        ));
    }
    let n = msg.width as usize * msg.height as usize;
    let step = msg.point_step as usize;
    if n > 0 && step == 0 {
        return Err(bad(&format!("{what}.point_step"), "is 0"));
    }
    if msg.row_step as usize != msg.width as usize * step {
        return Err(bad(
            &format!("{what}.row_step"),
            format!(
                "{} is not width {} x point_step {step} (padded rows are not supported)",
                msg.row_step, msg.width
            ),
        ));
    }
    if msg.data.len() != n * step {
        return Err(bad(
            &format!("{what}.data"),
            format!(
                "{} bytes for {n} points of {step} bytes (expected {})",
                msg.data.len(),
                n * step
            ),
        ));
    }
    let find = |name: &str, types: &[u32]| -> Result<Option<(usize, u32)>, FieldError> {
        let Some((k, f)) = msg.fields.iter().enumerate().find(|(_, f)| f.name == name) else {
            return Ok(None);
        };
        let at = format!("{what}.fields[{k}] ({name})");
        if !types.contains(&f.datatype) {
            return Err(bad(
                &at,
                format!("datatype {} is not supported here", f.datatype),
            ));
        }
        let size = size_of(f.datatype).unwrap_or(0);
        if f.offset as usize + size > step {
            return Err(bad(
                &at,
                format!(
                    "offset {} + {size} bytes lies outside point_step {step}",
                    f.offset
                ),
            ));
        }
        Ok(Some((f.offset as usize, f.datatype)))
    };
    let mut xyz = [0usize; 3];
    for (k, name) in ["x", "y", "z"].into_iter().enumerate() {
        xyz[k] = find(name, &[FLOAT32])?
            .ok_or_else(|| {
                bad(
                    &format!("{what}.fields"),
                    format!("no FLOAT32 field {name:?}"),
                )
            })?
            .0;
    }
    let rgb = find("rgb", &[FLOAT32, UINT32])?;
    let instance = find("instance", &[UINT32, UINT16])?;
    let provenance = find("provenance", &[UINT8])?;
    let conf = find("confidence", &[FLOAT32])?;
    let err = find("expected_error", &[FLOAT32])?;
    // One pass over the points, each a `step`-byte chunk.
    let rd4 = |p: &[u8], o: usize| [p[o], p[o + 1], p[o + 2], p[o + 3]];
    let mut positions = Vec::with_capacity(n);
    let mut colors = rgb.map(|_| Vec::with_capacity(n));
    let mut ids = instance.map(|_| Vec::with_capacity(n));
    let mut generated = provenance.map(|_| Vec::with_capacity(n));
    let mut confidence = conf.map(|_| Vec::with_capacity(n));
    let mut expected_error = err.map(|_| Vec::with_capacity(n));
    for (i, p) in msg.data.chunks_exact(step.max(1)).take(n).enumerate() {
        let q = Point3::new(
            f32::from_le_bytes(rd4(p, xyz[0])),
            f32::from_le_bytes(rd4(p, xyz[1])),
            f32::from_le_bytes(rd4(p, xyz[2])),
        );
        if !(q.x.is_finite() && q.y.is_finite() && q.z.is_finite()) {
            return Err(bad(
                &format!("{what}.data"),
                format!("point {i} is not finite ({}, {}, {})", q.x, q.y, q.z),
            ));
        }
        positions.push(q);
        if let (Some(c), Some((o, _))) = (colors.as_mut(), rgb) {
            let v = u32::from_le_bytes(rd4(p, o));
            c.push([(v >> 16) as u8, (v >> 8) as u8, v as u8]);
        }
        if let (Some(v), Some((o, t))) = (ids.as_mut(), instance) {
            v.push(if t == UINT16 {
                u32::from(u16::from_le_bytes([p[o], p[o + 1]]))
            } else {
                u32::from_le_bytes(rd4(p, o))
            });
        }
        if let (Some(g), Some((o, _))) = (generated.as_mut(), provenance) {
            g.push(p[o]);
        }
        if let (Some(k), Some((o, _))) = (confidence.as_mut(), conf) {
            let v = f32::from_le_bytes(rd4(p, o));
            if !(0.0..=1.0).contains(&v) {
                return Err(bad(
                    &format!("{what}.data"),
                    format!("point {i} has confidence {v}, outside [0, 1]"),
                ));
            }
            k.push(v);
        }
        if let (Some(k), Some((o, _))) = (expected_error.as_mut(), err) {
            let v = f32::from_le_bytes(rd4(p, o));
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(
                    &format!("{what}.data"),
                    format!("point {i} has expected_error {v}: it must be finite and >= 0"),
                ));
            }
            k.push(v);
        }
    }
    let instance = ids;
    Ok(PointCloud {
        positions,
        colors,
        instance,
        generated,
        confidence,
        expected_error,
        ..Default::default()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(n: usize) -> PointCloud {
        PointCloud {
            positions: (0..n)
                .map(|i| Point3::new(i as f32 * 0.001, -(i as f32), 0.5 + i as f32 * 1e-6))
                .collect(),
            colors: Some((0..n).map(|i| [i as u8, (i * 7) as u8, 255]).collect()),
            instance: Some((0..n).map(|i| (i % 5) as u32).collect()),
            generated: Some((0..n).map(|i| (i % 4) as u8).collect()),
            confidence: Some((0..n).map(|i| 1.0 - (i % 4) as f32 * 0.25).collect()),
            expected_error: Some((0..n).map(|i| (i % 3) as f32 * 0.004).collect()),
            ..Default::default()
        }
    }

    #[test]
    fn a_cloud_survives_encoding_bit_for_bit() {
        let c = cloud(1000);
        let msg = encode(&c);
        assert_eq!(msg.data.len(), 1000 * 32);
        assert_eq!(msg.row_step, 32_000);
        let back = decode(&msg, "cloud").unwrap();
        assert_eq!(back.positions, c.positions);
        assert_eq!(back.colors, c.colors);
        assert_eq!(back.instance, c.instance);
        assert_eq!(back.generated, c.generated);
        assert_eq!(back.confidence, c.confidence);
        assert_eq!(back.expected_error, c.expected_error);
        // The packed colour is where PCL reads it.
        let rgb = u32::from_le_bytes(msg.data[32 + 12..32 + 16].try_into().unwrap());
        assert_eq!(rgb, (1 << 16) | (7 << 8) | 255);
        assert_eq!(
            f32::from_le_bytes(msg.data[20..24].try_into().unwrap()),
            1.0
        );
    }

    #[test]
    fn foreign_layouts_decode_and_bad_ones_name_the_field() {
        // x y z only, 16-byte points with padding, as many drivers write.
        let mut data = Vec::new();
        for i in 0..3 {
            for v in [i as f32, 2.0, 3.0, 0.0] {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
        let mut msg = PointCloud2 {
            height: 1,
            width: 3,
            fields: vec![field("x", 0, 7), field("y", 4, 7), field("z", 8, 7)],
            is_bigendian: false,
            point_step: 16,
            row_step: 48,
            data,
            is_dense: true,
        };
        let c = decode(&msg, "cloud").unwrap();
        assert_eq!(c.positions[2], Point3::new(2.0, 2.0, 3.0));
        assert!(c.instance.is_none());
        msg.data.pop();
        assert!(decode(&msg, "cloud")
            .unwrap_err()
            .to_string()
            .starts_with("cloud.data"));
        msg.data.push(0);
        msg.fields[2].datatype = FLOAT64;
        let e = decode(&msg, "cloud").unwrap_err().to_string();
        assert!(e.contains("cloud.fields[2] (z)"), "{e}");
        msg.fields.pop();
        assert!(decode(&msg, "c")
            .unwrap_err()
            .to_string()
            .contains("no FLOAT32 field \"z\""));
        msg.fields.push(field("z", 14, 7));
        assert!(decode(&msg, "c")
            .unwrap_err()
            .to_string()
            .contains("outside point_step"));
        msg.fields[2].offset = 8;
        msg.data[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(decode(&msg, "c")
            .unwrap_err()
            .to_string()
            .contains("point 0"));
    }
}
