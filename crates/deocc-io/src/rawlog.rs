//! MRPT rawlogs (`.rawlog`, gzip-compressed or not): the RGB-D observations of a file in MRPT's
//! "observations only" form, a sequence of serialized `mrpt::obs::CObservation3DRangeScan`
//! objects (Kinect, Xtion, RealSense through OpenNI2 and MRPT's grabbers).
//!
//! Each observation gives a depth image (16-bit, `rangeUnits` metres per unit, depth along the
//! optical axis or range along the ray), the depth camera's calibration (`cameraParams`), a
//! colour image (raw BGR or JPEG) with its own calibration (`cameraParamsIntensity`) and the
//! colour camera's pose relative to the depth camera (`relativePoseIntensityWRTDepth`). They
//! become a frame with a separate depth camera, registered to colour by
//! [`crate::lens::to_pinhole`] like every other input. MRPT's observation frame has x forward
//! and z up, so the frame's pose (`sensorPose` times the colour camera's relative pose) puts
//! the scene in a z-up world as deocc expects; the rawlog is read as posed.
//!
//! The layout read is the one MRPT 2.x writes: `CObservation3DRangeScan` version 9, `CImage`
//! 9, `TCamera` 4 to 6, `CPose3D` 3 (the layouts as MRPT's `serializeFrom` reads them). Anything
//! else (other observation classes, sensory-frame rawlogs, images kept in external files,
//! other versions) is refused with the class, version and byte offset named.

use std::io::Read;
use std::path::Path;

use deocc_geometry::camera::{Camera, Intrinsics};
use deocc_geometry::distortion::Distortion;
use deocc_geometry::DepthMap;
use image::RgbImage;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::cameras::{DepthCamera, Lens};
use crate::error::{IoError, Result};
use crate::scene::{Frame, SceneInput};
use crate::tum::FramePick;

/// Whether `path` names a rawlog (by its extension).
pub fn is_rawlog(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("rawlog"))
}

/// MRPT's end-of-object marker.
const END: u8 = 0x88;

/// One RGB-D observation as the rawlog stores it.
#[derive(Debug, Clone)]
pub struct RangeScan {
    /// The observation frame's pose on the robot (x forward, z up).
    pub sensor_pose: Isometry3<f64>,
    /// Depth in metres (0 = none), `depth_size` pixels, in the depth camera.
    pub depth: Vec<f32>,
    pub depth_size: (u32, u32),
    /// Whether `depth` is along the optical axis (else along each pixel's ray).
    pub range_is_depth: bool,
    pub rgb: RgbImage,
    /// `fx, fy, cx, cy`, the 8 distortion coefficients (OpenCV's order), `width, height`.
    pub depth_camera: TCamera,
    pub color_camera: TCamera,
    /// The colour camera (optical axes) in the depth camera's observation frame.
    pub color_in_depth: Isometry3<f64>,
    pub timestamp: u64,
    pub label: String,
}

/// MRPT's `TCamera`.
#[derive(Debug, Clone, PartialEq)]
pub struct TCamera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub dist: [f64; 8],
    pub width: u32,
    pub height: u32,
}

impl TCamera {
    fn intrinsics(&self, path: &Path, what: &str) -> Result<Intrinsics> {
        Intrinsics::new(
            self.fx as f32,
            self.fy as f32,
            self.cx as f32,
            self.cy as f32,
            self.width,
            self.height,
        )
        .and_then(|k| k.check_plausible().map(|_| k))
        .map_err(|e| IoError::invalid(path, format!("{what}: {e}")))
    }

    /// OpenCV's plumb_bob (k1 k2 p1 p2 k3), or rational_polynomial when k4..k6 are set.
    fn distortion(&self) -> Distortion {
        let model = if self.dist[5..].iter().any(|&v| v != 0.0) {
            "rational_polynomial"
        } else {
            "plumb_bob"
        };
        Distortion::from_ros(model, &self.dist).unwrap_or(Distortion::None)
    }
}

/// The optical frame (x right, y down, z forward) in MRPT's observation frame (x forward, y
/// left, z up).
fn observation_from_optical() -> Isometry3<f64> {
    let r = Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
    Isometry3::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)),
    )
}

struct Reader<'a> {
    b: &'a [u8],
    at: usize,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn err(&self, msg: impl std::fmt::Display) -> IoError {
        IoError::invalid(self.path, format!("at byte {}: {msg}", self.at))
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.b.len());
        let Some(end) = end else {
            return Err(self.err(format!(
                "the file ends inside a field ({n} bytes wanted, {} left)",
                self.b.len() - self.at
            )));
        };
        let s = &self.b[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }
    fn bool(&mut self) -> Result<bool> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            v => Err(self.err(format!("a boolean is {v}, neither 0 nor 1"))),
        }
    }
    fn u16s(&mut self, n: usize) -> Result<Vec<u16>> {
        let b = self.take(n.checked_mul(2).ok_or_else(|| self.err("size overflow"))?)?;
        Ok(b.chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect())
    }
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn i32(&mut self) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    fn f32(&mut self) -> Result<f32> {
        Ok(f32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    fn string(&mut self) -> Result<String> {
        let n = self.u32()? as usize;
        Ok(String::from_utf8_lossy(self.take(n)?).into_owned())
    }
    /// An object's header: its class name and version.
    fn header(&mut self) -> Result<(String, u8)> {
        let start = self.at;
        let len = self.u8()?;
        if len & 0x80 == 0 {
            return Err(self
                .err("not an MRPT 2.x object header (rawlogs written by MRPT 1.x are not read)"));
        }
        let name = String::from_utf8_lossy(self.take((len & 0x7f) as usize)?).into_owned();
        let version = self.u8()?;
        if name.is_empty() {
            self.at = start;
            return Err(self.err("an empty class name"));
        }
        Ok((name, version))
    }
    fn expect(&mut self, class: &str, versions: std::ops::RangeInclusive<u8>) -> Result<u8> {
        let at = self.at;
        let (name, version) = self.header()?;
        if name != class || !versions.contains(&version) {
            self.at = at;
            return Err(self.err(format!(
                "{name} version {version} where {class} version {}..={} was expected",
                versions.start(),
                versions.end()
            )));
        }
        Ok(version)
    }
    fn end(&mut self, class: &str) -> Result<()> {
        let v = self.u8()?;
        if v != END {
            self.at -= 1;
            return Err(self.err(format!("{class} does not end where its layout says")));
        }
        Ok(())
    }

    fn pose3d(&mut self) -> Result<Isometry3<f64>> {
        self.expect("mrpt::poses::CPose3D", 3..=3)?;
        let t = Vector3::new(self.f64()?, self.f64()?, self.f64()?);
        let mut m = [0.0; 9];
        for v in &mut m {
            *v = self.f64()?;
        }
        self.end("CPose3D")?;
        let r = Matrix3::from_row_slice(&m);
        if !(r.transpose() * r - Matrix3::identity())
            .iter()
            .all(|e| e.abs() < 1e-6)
        {
            return Err(self.err("a CPose3D whose rotation is not orthonormal"));
        }
        Ok(Isometry3::from_parts(
            Translation3::from(t),
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)),
        ))
    }

    fn tcamera(&mut self) -> Result<TCamera> {
        let version = self.expect("mrpt::img::TCamera", 4..=6)?;
        let _focal_length_m = self.f64()?;
        let mut dist = [0.0; 8];
        for v in &mut dist {
            *v = self.f64()?;
        }
        let (fx, fy, cx, cy) = (self.f64()?, self.f64()?, self.f64()?, self.f64()?);
        let height = self.u32()?;
        let width = self.u32()?;
        if version >= 5 {
            let _name = self.string()?;
        }
        if version >= 6 {
            let _model = self.u8()?;
        }
        self.end("TCamera")?;
        Ok(TCamera {
            fx,
            fy,
            cx,
            cy,
            dist,
            width,
            height,
        })
    }

    /// A colour `CImage` (raw BGR or JPEG), as RGB.
    fn image(&mut self) -> Result<RgbImage> {
        self.expect("mrpt::img::CImage", 9..=9)?;
        if self.bool()? {
            let file = self.string()?;
            return Err(self.err(format!(
                "the image is stored in an external file ({file}); only images inside the \
                 rawlog are read"
            )));
        }
        if !self.bool()? {
            return Err(self.err("a grey-level intensity image; only colour images are read"));
        }
        let (w, h) = (self.i32()?, self.i32()?);
        let rgb = if w < 0 && h < 0 {
            let (w, h) = (w.unsigned_abs(), h.unsigned_abs());
            let bgr = self.take(w as usize * h as usize * 3)?;
            let rgb: Vec<u8> = bgr
                .chunks_exact(3)
                .flat_map(|p| [p[2], p[1], p[0]])
                .collect();
            RgbImage::from_raw(w, h, rgb).expect("w * h * 3 bytes")
        } else if w > 0 && h > 0 {
            let n = self.u32()? as usize;
            let jpeg = self.take(n)?;
            let img = image::load_from_memory_with_format(jpeg, image::ImageFormat::Jpeg)
                .map_err(|e| self.err(format!("its JPEG image: {e}")))?
                .to_rgb8();
            if img.dimensions() != (w as u32, h as u32) {
                return Err(self.err(format!(
                    "its JPEG is {}x{}, the header says {w}x{h}",
                    img.width(),
                    img.height()
                )));
            }
            img
        } else {
            return Err(self.err(format!("an image of {w}x{h} pixels")));
        };
        self.end("CImage")?;
        Ok(rgb)
    }

    fn range_scan(&mut self) -> Result<RangeScan> {
        let _max_range = self.f32()?;
        let sensor_pose = self.pose3d()?;
        if self.bool()? {
            let n = self.u32()? as usize;
            // x, y, z (f32) and the pixel of each point (u16 column, u16 row).
            self.take(n.checked_mul(16).ok_or_else(|| self.err("size overflow"))?)?;
        }
        let has_depth = self.bool()?;
        let units = self.f32()?;
        if !has_depth {
            return Err(self.err("an observation without a depth image"));
        }
        if !(units.is_finite() && units > 0.0 && units <= 1.0) {
            return Err(self.err(format!("rangeUnits {units} is not in (0, 1] metres")));
        }
        let rows = self.u32()?;
        let cols = self.u32()?;
        let raw = self.u16s(rows as usize * cols as usize)?;
        let depth: Vec<f32> = raw.iter().map(|&v| v as f32 * units).collect();
        if !self.bool()? {
            return Err(self.err("an observation without a colour image"));
        }
        let rgb = self.image()?;
        if self.bool()? {
            self.image()?; // the confidence image, not used
        }
        let depth_camera = self.tcamera()?;
        let color_camera = self.tcamera()?;
        let color_in_depth = self.pose3d()?;
        let _std_error = self.f32()?;
        let timestamp = self.u64()?;
        let label = self.string()?;
        for what in ["points", "depth image"] {
            if self.bool()? {
                let file = self.string()?;
                return Err(self.err(format!(
                    "the {what} is stored in an external file ({file}); only rawlogs that hold \
                     their data are read"
                )));
            }
            let _ = self.string()?;
        }
        let range_is_depth = self.bool()?;
        let _intensity_channel = self.u8()?;
        if self.bool()? {
            return Err(self.err("pixel labels are not read"));
        }
        self.end("CObservation3DRangeScan")?;
        if (cols, rows) != (depth_camera.width, depth_camera.height) {
            return Err(self.err(format!(
                "the depth image is {cols}x{rows}, its camera {}x{}",
                depth_camera.width, depth_camera.height
            )));
        }
        if rgb.dimensions() != (color_camera.width, color_camera.height) {
            return Err(self.err(format!(
                "the colour image is {}x{}, its camera {}x{}",
                rgb.width(),
                rgb.height(),
                color_camera.width,
                color_camera.height
            )));
        }
        Ok(RangeScan {
            sensor_pose,
            depth,
            depth_size: (cols, rows),
            range_is_depth,
            rgb,
            depth_camera,
            color_camera,
            color_in_depth,
            timestamp,
            label,
        })
    }
}

/// Every `CObservation3DRangeScan` of a rawlog's bytes (decompressed), in order.
pub fn parse_rawlog(bytes: &[u8], path: &Path) -> Result<Vec<RangeScan>> {
    let mut r = Reader {
        b: bytes,
        at: 0,
        path,
    };
    let mut scans = Vec::new();
    while r.at < bytes.len() {
        let at = r.at;
        let (class, version) = r.header()?;
        match (class.as_str(), version) {
            ("mrpt::obs::CObservation3DRangeScan", 9) => scans.push(r.range_scan()?),
            ("mrpt::obs::CObservation3DRangeScan", v) => {
                r.at = at;
                return Err(r.err(format!(
                    "CObservation3DRangeScan version {v}: only version 9 (MRPT 2.x) is read"
                )));
            }
            (other, _) => {
                r.at = at;
                return Err(r.err(format!(
                    "a {other}: only rawlogs of CObservation3DRangeScan observations are read \
                     (for a sensory-frame rawlog, extract them with MRPT's rawlog-edit \
                     --export-... or convert it to a scene folder)"
                )));
            }
        }
    }
    if scans.is_empty() {
        return Err(IoError::invalid(path, "no observation in this rawlog"));
    }
    Ok(scans)
}

/// Reads a rawlog file (gzip-compressed or plain) as a posed scene: the observations `pick`
/// keeps, each a frame in its colour camera with depth registered to it.
pub fn read_rawlog(path: &Path, pick: &FramePick) -> Result<SceneInput> {
    let raw = std::fs::read(path).map_err(|e| IoError::new(path, e))?;
    let bytes = if raw.starts_with(&[0x1f, 0x8b]) {
        let mut out = Vec::new();
        flate2::read::GzDecoder::new(&raw[..])
            .read_to_end(&mut out)
            .map_err(|e| IoError::invalid(path, format!("not a valid gzip file: {e}")))?;
        out
    } else {
        raw
    };
    let scans = parse_rawlog(&bytes, path)?;
    let poses: Vec<Option<Isometry3<f32>>> = scans
        .iter()
        .map(|s| Some(world_from_color(s).cast::<f32>()))
        .collect();
    let mut frames = Vec::new();
    for k in pick.pick(scans.len(), &poses) {
        frames.push(to_frame(&scans[k], k, path)?);
    }
    Ok(SceneInput {
        dir: path.to_path_buf(),
        frames,
        structure_ids: Vec::new(),
        posed: true,
    })
}

/// The colour camera's optical frame in the world (the robot frame the rawlog's sensor poses
/// are in; z up).
pub fn world_from_color(s: &RangeScan) -> Isometry3<f64> {
    s.sensor_pose * s.color_in_depth
}

/// One observation as a frame: the colour camera's lens and the depth camera removed by
/// [`crate::lens::to_pinhole`].
fn to_frame(s: &RangeScan, k: usize, path: &Path) -> Result<Frame> {
    let color = s
        .color_camera
        .intrinsics(path, &format!("observation {k}: cameraParamsIntensity"))?;
    let depth_k = s
        .depth_camera
        .intrinsics(path, &format!("observation {k}: cameraParams"))?;
    let (w, h) = s.depth_size;
    let mut depth = s.depth.clone();
    if !s.range_is_depth {
        // Range along each pixel's ray to depth along the optical axis.
        for v in 0..h as usize {
            for u in 0..w as usize {
                let x = (u as f64 - s.depth_camera.cx) / s.depth_camera.fx;
                let y = (v as f64 - s.depth_camera.cy) / s.depth_camera.fy;
                depth[v * w as usize + u] /= (1.0 + x * x + y * y).sqrt() as f32;
            }
        }
    }
    let depth = DepthMap::new(w, h, depth).map_err(|e| IoError::invalid(path, e.to_string()))?;
    let color_from_depth = s.color_in_depth.inverse() * observation_from_optical();
    let lens = Lens {
        distortion: s.color_camera.distortion(),
        depth_scale: crate::cameras::DEFAULT_DEPTH_SCALE,
        depth_camera: Some(DepthCamera {
            intrinsics: depth_k,
            distortion: s.depth_camera.distortion(),
            color_from_depth: color_from_depth.cast::<f32>(),
        }),
    };
    let (rgb, depth, _) = crate::lens::to_pinhole(s.rgb.clone(), depth, None, &color, &lens);
    if depth.valid_count() == 0 {
        return Err(IoError::invalid(
            path,
            format!("observation {k}: no depth lands in the colour image"),
        ));
    }
    Ok(Frame {
        name: format!("{k:06}"),
        camera: Camera {
            intrinsics: color,
            world_from_camera: world_from_color(s).cast::<f32>(),
        },
        rgb,
        depth,
        instances: None,
    })
}
