//! MRPT rawlogs: a rawlog written here byte by byte in MRPT 2.x's layout (a plane 1.5 m in front
//! of a Kinect-like pair of cameras) reads back as one posed frame in a z-up world, with its
//! depth registered to colour; broken and unsupported files are refused with the byte named.

use std::io::Write;
use std::path::Path;

use deocc_io::rawlog::{is_rawlog, parse_rawlog, read_rawlog};
use deocc_io::tum::FramePick;

/// Writes MRPT's serialization of the pieces a `CObservation3DRangeScan` v9 holds.
struct W(Vec<u8>);

impl W {
    fn header(&mut self, class: &str, version: u8) {
        self.0.push(0x80 | class.len() as u8);
        self.0.extend(class.as_bytes());
        self.0.push(version);
    }
    fn f32(&mut self, v: f32) {
        self.0.extend(v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.0.extend(v.to_le_bytes());
    }
    fn u32(&mut self, v: u32) {
        self.0.extend(v.to_le_bytes());
    }
    fn pose(&mut self, t: [f64; 3], r: [f64; 9]) {
        self.header("mrpt::poses::CPose3D", 3);
        for v in t.into_iter().chain(r) {
            self.f64(v);
        }
        self.0.push(0x88);
    }
    fn camera(&mut self, f: f64, (w, h): (u32, u32), k1: f64) {
        self.header("mrpt::img::TCamera", 4);
        self.f64(0.0);
        for d in [k1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0] {
            self.f64(d);
        }
        for v in [f, f, w as f64 / 2.0, h as f64 / 2.0] {
            self.f64(v);
        }
        self.u32(h);
        self.u32(w);
        self.0.push(0x88);
    }
}

const IDENTITY: [f64; 9] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
/// The colour camera's optical axes in the observation frame (x forward, y left, z up).
const OPTICAL: [f64; 9] = [0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0];

/// One observation: depth 1.5 m everywhere (in millimetres), a colour image whose left half is
/// red, the colour camera 2.5 cm to the left of the depth camera (`y` of the observation frame).
fn observation(w: &mut W, (dw, dh): (u32, u32), (cw, ch): (u32, u32)) {
    w.header("mrpt::obs::CObservation3DRangeScan", 9);
    w.f32(5.0);
    w.pose([0.0, 0.0, 0.4], IDENTITY); // the sensor 0.4 m up on the robot
    w.0.push(0); // no points
    w.0.push(1);
    w.f32(0.001);
    w.u32(dh);
    w.u32(dw);
    for _ in 0..dw * dh {
        w.0.extend(1500u16.to_le_bytes());
    }
    w.0.push(1);
    w.header("mrpt::img::CImage", 9);
    w.0.extend([0, 1]);
    w.0.extend((-(cw as i32)).to_le_bytes());
    w.0.extend((-(ch as i32)).to_le_bytes());
    for _v in 0..ch {
        for u in 0..cw {
            // BGR on disk.
            w.0.extend(if u < cw / 2 { [0, 0, 255] } else { [255, 0, 0] });
        }
    }
    w.0.push(0x88);
    w.0.push(0); // no confidence image
    w.camera(60.0, (dw, dh), 0.0);
    w.camera(80.0, (cw, ch), 0.01);
    w.pose([0.0, 0.025, 0.0], OPTICAL);
    w.f32(0.01);
    w.0.extend(42u64.to_le_bytes());
    w.u32(7);
    w.0.extend(b"OPENNI2");
    w.0.extend([0, 0, 0, 0, 0, 0, 0, 0, 0, 0]); // no external files
    w.0.push(1); // depth along the optical axis
    w.0.extend([0, 0]); // intensity channel, no pixel labels
    w.0.push(0x88);
}

fn write(dir: &Path, name: &str, bytes: &[u8], gzip: bool) -> std::path::PathBuf {
    let path = dir.join(name);
    if gzip {
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        e.write_all(bytes).unwrap();
        std::fs::write(&path, e.finish().unwrap()).unwrap();
    } else {
        std::fs::write(&path, bytes).unwrap();
    }
    path
}

#[test]
fn a_rawlog_reads_as_a_posed_frame_in_a_z_up_world() {
    let tmp = tempfile::tempdir().unwrap();
    let mut w = W(Vec::new());
    observation(&mut w, (80, 60), (160, 120));
    observation(&mut w, (80, 60), (160, 120));
    for gzip in [true, false] {
        let path = write(tmp.path(), "scan.rawlog", &w.0, gzip);
        assert!(is_rawlog(&path));
        let scene = read_rawlog(&path, &FramePick::default()).unwrap();
        assert!(scene.posed);
        assert_eq!(scene.frames.len(), 2);
        let f = &scene.frames[0];
        assert_eq!(f.camera.intrinsics.width(), 160);
        // The camera looks along +x of the world, 0.4 m up, 2.5 cm to the left (+y).
        let pose = f.camera.world_from_camera;
        let forward = pose.rotation * nalgebra::Vector3::z();
        assert!(
            (forward - nalgebra::Vector3::x()).norm() < 1e-6,
            "{forward}"
        );
        let down = pose.rotation * nalgebra::Vector3::y();
        assert!((down + nalgebra::Vector3::z()).norm() < 1e-6, "{down}");
        let t = pose.translation.vector;
        assert!(
            (t - nalgebra::Vector3::new(0.0, 0.025, 0.4)).norm() < 1e-6,
            "{t}"
        );
        // The plane lands in the colour image at 1.5 m (a pure sideways shift keeps depth).
        let d = f.depth.data();
        let valid: Vec<f32> = d.iter().copied().filter(|&v| v > 0.0).collect();
        assert!(valid.len() > d.len() / 3, "{} of {}", valid.len(), d.len());
        assert!(valid.iter().all(|&v| (v - 1.5).abs() < 0.01));
        // Colour read as RGB (BGR on disk): the left half red, the right half blue.
        assert_eq!(f.rgb.get_pixel(10, 60).0, [255, 0, 0]);
        assert_eq!(f.rgb.get_pixel(150, 60).0, [0, 0, 255]);
    }
    let only_one = FramePick {
        max_frames: 1,
        ..Default::default()
    };
    let path = write(tmp.path(), "one.rawlog", &w.0, true);
    assert_eq!(read_rawlog(&path, &only_one).unwrap().frames.len(), 1);
}

#[test]
fn broken_and_unsupported_rawlogs_are_refused_with_the_byte_named() {
    let tmp = tempfile::tempdir().unwrap();
    let mut w = W(Vec::new());
    observation(&mut w, (8, 6), (8, 6));
    let good = w.0.clone();
    let p = Path::new("x.rawlog");
    assert_eq!(parse_rawlog(&good, p).unwrap().len(), 1);
    // Cut short: every prefix is refused, never a panic.
    for cut in (0..good.len()).step_by(7) {
        let e = parse_rawlog(&good[..cut], p);
        if cut == 0 {
            assert!(e.unwrap_err().to_string().contains("no observation"));
        } else {
            let msg = e.unwrap_err().to_string();
            assert!(
                msg.contains("x.rawlog") && msg.contains("at byte"),
                "{cut}: {msg}"
            );
        }
    }
    // Another observation class.
    let mut other = W(Vec::new());
    other.header("mrpt::obs::CObservation2DRangeScan", 7);
    let msg = parse_rawlog(&other.0, p).unwrap_err().to_string();
    assert!(
        msg.contains("CObservation2DRangeScan") && msg.contains("at byte 0"),
        "{msg}"
    );
    // Another version of the observation.
    let mut v10 = good.clone();
    v10[1 + "mrpt::obs::CObservation3DRangeScan".len()] = 10;
    let msg = parse_rawlog(&v10, p).unwrap_err().to_string();
    assert!(msg.contains("version 10"), "{msg}");
    // A corrupt gzip file names the file.
    let path = write(
        tmp.path(),
        "bad.rawlog",
        &[0x1f, 0x8b, 8, 0, 1, 2, 3],
        false,
    );
    let msg = read_rawlog(&path, &FramePick::default())
        .unwrap_err()
        .to_string();
    assert!(msg.contains("bad.rawlog") && msg.contains("gzip"), "{msg}");
}
