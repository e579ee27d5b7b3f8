//! Lens distortion as ROS `CameraInfo` and OpenCV state it, and its removal.
//!
//! deocc's stages assume pinhole images. Real colour cameras are not pinhole: an Azure Kinect's
//! colour camera, a wide-angle RealSense and most webcams bend straight lines by tens of pixels at
//! the image corners. The input readers (scene folders, gRPC, Python, ROS 2) call
//! [`undistort_depth`] and [`undistort_rgb`] once at read time, so every later stage sees an ideal
//! pinhole image with the same `K`.
//!
//! Models, on normalised image coordinates `(x, y) = (X/Z, Y/Z)`, `r^2 = x^2 + y^2`:
//! - `plumb_bob` (Brown-Conrady, `D = [k1, k2, p1, p2, k3]`; `k3` may be left out):
//!   radial `1 + k1 r^2 + k2 r^4 + k3 r^6` and tangential `p1`, `p2`;
//! - `rational_polynomial` (`D = [k1, k2, p1, p2, k3, k4, k5, k6]`): radial
//!   `(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)`, tangential as above (the
//!   Azure Kinect's colour camera);
//! - `equidistant` (fisheye, Kannala-Brandt, `D = [k1, k2, k3, k4]`): `theta = atan(r)`,
//!   `theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`, scaled by
//!   `theta_d / r`.
//!
//! Removal builds, for each pixel of the pinhole image, where it lies in the distorted image (the
//! forward model, closed form: no iteration, as OpenCV's `initUndistortRectifyMap`), then samples
//! there: colour bilinearly, depth bilinearly only where the four neighbours lie on one surface
//! and from the nearest neighbour otherwise (averaging across a depth edge invents a point in
//! mid-air). Depth is the z of the 3-D point, which distortion does not change.
//!
//! Pixel centres are at `(u + 0.5, v + 0.5)`, as everywhere in deocc.

use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
use crate::depth::DepthMap;

/// A distortion model with its coefficients.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "DistortionFields", into = "DistortionFields")]
pub enum Distortion {
    /// No distortion (a pinhole camera, or images already rectified).
    #[default]
    None,
    /// `[k1, k2, p1, p2, k3]`.
    PlumbBob([f64; 5]),
    /// `[k1, k2, p1, p2, k3, k4, k5, k6]`.
    RationalPolynomial([f64; 8]),
    /// `[k1, k2, k3, k4]`.
    Equidistant([f64; 4]),
}

/// The JSON form: `{"model": "plumb_bob", "coefficients": [k1, k2, p1, p2, k3]}`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DistortionFields {
    pub model: String,
    #[serde(default)]
    pub coefficients: Vec<f64>,
}

impl TryFrom<DistortionFields> for Distortion {
    type Error = String;
    fn try_from(f: DistortionFields) -> Result<Self, String> {
        Distortion::from_ros(&f.model, &f.coefficients)
    }
}

impl From<Distortion> for DistortionFields {
    fn from(d: Distortion) -> Self {
        DistortionFields {
            model: d.model_name().to_string(),
            coefficients: d.coefficients(),
        }
    }
}

/// Largest magnitude accepted for any coefficient: real lenses stay far below it; beyond it a
/// value is a unit or ordering mistake.
pub const MAX_COEFFICIENT: f64 = 1e3;

impl Distortion {
    /// Reads a ROS `CameraInfo` pair (`distortion_model`, `D`). An empty model with all-zero (or
    /// no) coefficients is no distortion. Unknown models and wrong counts are refused with what
    /// is expected.
    pub fn from_ros(model: &str, d: &[f64]) -> Result<Self, String> {
        if let Some(bad) = d
            .iter()
            .find(|v| !v.is_finite() || v.abs() > MAX_COEFFICIENT)
        {
            return Err(format!(
                "distortion coefficient {bad} is not finite or beyond +-{MAX_COEFFICIENT}"
            ));
        }
        let all_zero = d.iter().all(|&v| v == 0.0);
        let take = |n: usize, min: usize| -> Result<Vec<f64>, String> {
            // ROS drivers pad to more entries with zeros (OpenCV's 12- and 14-term models).
            if d.len() < min || d[n.min(d.len())..].iter().any(|&v| v != 0.0) {
                return Err(format!(
                    "distortion model {model:?} takes {n} coefficients{}, got {} ({d:?})",
                    if min < n {
                        format!(" (or {min})")
                    } else {
                        String::new()
                    },
                    d.len()
                ));
            }
            let mut out = vec![0.0; n];
            out[..d.len().min(n)].copy_from_slice(&d[..d.len().min(n)]);
            Ok(out)
        };
        let dist = match model {
            "" | "none" if all_zero => Distortion::None,
            "" | "none" => {
                return Err(format!(
                    "distortion coefficients {d:?} given without a model (plumb_bob, \
                     rational_polynomial or equidistant)"
                ))
            }
            "plumb_bob" | "radtan" | "brown_conrady" => {
                let v = take(5, 4)?;
                Distortion::PlumbBob([v[0], v[1], v[2], v[3], v[4]])
            }
            "rational_polynomial" => {
                let v = take(8, 8)?;
                Distortion::RationalPolynomial(std::array::from_fn(|i| v[i]))
            }
            "equidistant" | "fisheye" | "kannala_brandt" => {
                let v = take(4, 4)?;
                Distortion::Equidistant([v[0], v[1], v[2], v[3]])
            }
            other => {
                return Err(format!(
                    "unknown distortion model {other:?}: expected plumb_bob, rational_polynomial \
                     or equidistant (fisheye)"
                ))
            }
        };
        Ok(if dist.coefficients().iter().all(|&v| v == 0.0) {
            Distortion::None
        } else {
            dist
        })
    }

    /// The ROS name of the model.
    pub fn model_name(&self) -> &'static str {
        match self {
            Distortion::None => "none",
            Distortion::PlumbBob(_) => "plumb_bob",
            Distortion::RationalPolynomial(_) => "rational_polynomial",
            Distortion::Equidistant(_) => "equidistant",
        }
    }

    /// The coefficients in ROS order.
    pub fn coefficients(&self) -> Vec<f64> {
        match self {
            Distortion::None => Vec::new(),
            Distortion::PlumbBob(k) => k.to_vec(),
            Distortion::RationalPolynomial(k) => k.to_vec(),
            Distortion::Equidistant(k) => k.to_vec(),
        }
    }

    pub fn is_none(&self) -> bool {
        matches!(self, Distortion::None)
    }

    /// The forward model: where the ray through normalised pinhole coordinates `(x, y)` lands in
    /// the distorted image, in normalised coordinates.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let brown = |radial: f64, p1: f64, p2: f64| {
            (
                x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
            )
        };
        match *self {
            Distortion::None => (x, y),
            Distortion::PlumbBob([k1, k2, p1, p2, k3]) => {
                brown(1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)), p1, p2)
            }
            Distortion::RationalPolynomial([k1, k2, p1, p2, k3, k4, k5, k6]) => {
                let num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                let den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6));
                brown(num / den, p1, p2)
            }
            Distortion::Equidistant([k1, k2, k3, k4]) => {
                let r = r2.sqrt();
                if r < 1e-12 {
                    return (x, y);
                }
                let t = r.atan();
                let t2 = t * t;
                let td = t * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))));
                (x * td / r, y * td / r)
            }
        }
    }

    /// The inverse of [`Distortion::distort`] by Gauss-Newton from the distorted point (the
    /// model has no closed-form inverse): the pinhole coordinates of a pixel a user picked in the
    /// image as the camera gave it. `None` where it does not converge to 1e-9 (outside the
    /// region where the model is one-to-one).
    pub fn undistort(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        if self.is_none() {
            return Some((xd, yd));
        }
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let (fx, fy) = self.distort(x, y);
            let (ex, ey) = (fx - xd, fy - yd);
            if ex.abs().max(ey.abs()) < 1e-12 {
                return Some((x, y));
            }
            let h = 1e-7;
            let (ax, ay) = self.distort(x + h, y);
            let (bx, by) = self.distort(x, y + h);
            let (j00, j10, j01, j11) = ((ax - fx) / h, (ay - fy) / h, (bx - fx) / h, (by - fy) / h);
            let det = j00 * j11 - j01 * j10;
            if det.abs() < 1e-12 {
                return None;
            }
            x -= (j11 * ex - j01 * ey) / det;
            y -= (-j10 * ex + j00 * ey) / det;
            if !x.is_finite() || !y.is_finite() {
                return None;
            }
        }
        let (fx, fy) = self.distort(x, y);
        ((fx - xd).abs().max((fy - yd).abs()) < 1e-9).then_some((x, y))
    }

    /// A pixel of the distorted image, as pinhole pixel coordinates of the same `K`.
    pub fn undistort_pixel(&self, k: &Intrinsics, u: f64, v: f64) -> Option<(f64, f64)> {
        let (fx, fy, cx, cy) = (k.fx() as f64, k.fy() as f64, k.cx() as f64, k.cy() as f64);
        let (x, y) = self.undistort((u - cx) / fx, (v - cy) / fy)?;
        Some((x * fx + cx, y * fy + cy))
    }

    /// For every pixel centre of the pinhole image with intrinsics `k`, the continuous position
    /// in the distorted image that it samples (pixel-centre convention).
    pub fn source_map(&self, k: &Intrinsics) -> Vec<(f32, f32)> {
        let (fx, fy, cx, cy) = (k.fx() as f64, k.fy() as f64, k.cx() as f64, k.cy() as f64);
        let (w, h) = (k.width(), k.height());
        let mut map = Vec::with_capacity(k.pixel_count());
        for v in 0..h {
            for u in 0..w {
                let (x, y) = ((u as f64 + 0.5 - cx) / fx, (v as f64 + 0.5 - cy) / fy);
                let (xd, yd) = self.distort(x, y);
                map.push(((xd * fx + cx) as f32, (yd * fy + cy) as f32));
            }
        }
        map
    }
}

/// Bilinear taps at continuous position (`su`, `sv`) in a `w` x `h` image: the four pixel
/// indices and weights, or `None` outside the image.
fn taps(su: f32, sv: f32, w: u32, h: u32) -> Option<([usize; 4], [f32; 4])> {
    let (x, y) = (su - 0.5, sv - 0.5);
    if !(x >= -0.5 && y >= -0.5 && x <= w as f32 - 0.5 && y <= h as f32 - 0.5) {
        return None;
    }
    let x0 = (x.floor().max(0.0) as u32).min(w - 1);
    let y0 = (y.floor().max(0.0) as u32).min(h - 1);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (ax, ay) = (
        (x - x0 as f32).clamp(0.0, 1.0),
        (y - y0 as f32).clamp(0.0, 1.0),
    );
    let idx = |xx: u32, yy: u32| (yy * w + xx) as usize;
    Some((
        [idx(x0, y0), idx(x1, y0), idx(x0, y1), idx(x1, y1)],
        [
            (1.0 - ax) * (1.0 - ay),
            ax * (1.0 - ay),
            (1.0 - ax) * ay,
            ax * ay,
        ],
    ))
}

/// Relative depth spread under which four neighbours count as one surface (bilinear is safe).
pub const SAME_SURFACE_REL: f32 = 0.02;

/// The depth map as a pinhole camera with intrinsics `k` would have measured it (same size).
/// Pixels whose source falls outside the image, or on no measurement, are 0.
pub fn undistort_depth(depth: &DepthMap, k: &Intrinsics, dist: &Distortion) -> DepthMap {
    if dist.is_none() {
        return depth.clone();
    }
    let (w, h) = (depth.width(), depth.height());
    let src = depth.data();
    let out: Vec<f32> = dist
        .source_map(k)
        .iter()
        .map(|&(su, sv)| {
            let Some((idx, wt)) = taps(su, sv, w, h) else {
                return 0.0;
            };
            let d = idx.map(|i| src[i]);
            let (lo, hi) = d
                .iter()
                .fold((f32::MAX, 0.0f32), |(lo, hi), &v| (lo.min(v), hi.max(v)));
            if lo > 0.0 && hi - lo <= SAME_SURFACE_REL * lo {
                return d.iter().zip(wt).map(|(v, w)| v * w).sum();
            }
            // Nearest tap with a measurement, by weight.
            let best = (0..4)
                .filter(|&i| d[i] > 0.0)
                .max_by(|&a, &b| wt[a].total_cmp(&wt[b]));
            match best {
                Some(i) if wt[i] >= 0.25 => d[i],
                _ => 0.0,
            }
        })
        .collect();
    DepthMap::new(w, h, out).expect("same size as the input")
}

/// An interleaved 8-bit image (`channels` per pixel) as the pinhole camera with intrinsics `k`
/// would have seen it; bilinear, black outside the source.
pub fn undistort_rgb(data: &[u8], channels: usize, k: &Intrinsics, dist: &Distortion) -> Vec<u8> {
    if dist.is_none() {
        return data.to_vec();
    }
    let (w, h) = (k.width(), k.height());
    let mut out = vec![0u8; data.len()];
    for (o, &(su, sv)) in dist.source_map(k).iter().enumerate() {
        let Some((idx, wt)) = taps(su, sv, w, h) else {
            continue;
        };
        for c in 0..channels {
            let v: f32 = (0..4)
                .map(|t| data[idx[t] * channels + c] as f32 * wt[t])
                .sum();
            out[o * channels + c] = v.round().clamp(0.0, 255.0) as u8;
        }
    }
    out
}

/// A label image (instance ids) as the pinhole camera would have seen it: nearest neighbour, 0
/// outside the source.
pub fn undistort_labels(ids: &[u16], k: &Intrinsics, dist: &Distortion) -> Vec<u16> {
    if dist.is_none() {
        return ids.to_vec();
    }
    let (w, h) = (k.width(), k.height());
    dist.source_map(k)
        .iter()
        .map(|&(su, sv)| {
            if su < 0.0 || sv < 0.0 || su >= w as f32 || sv >= h as f32 {
                0
            } else {
                ids[sv as usize * w as usize + su as usize]
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn models() -> Vec<Distortion> {
        vec![
            Distortion::PlumbBob([-0.28, 0.07, 0.001, -0.0005, 0.0]),
            // The Azure Kinect colour camera's published calibration.
            Distortion::RationalPolynomial([
                0.447, -2.5, 0.00094, -0.00053, 1.432, 0.329, -2.332, 1.363,
            ]),
            Distortion::Equidistant([-0.01, 0.05, -0.07, 0.03]),
        ]
    }

    #[test]
    fn undistort_inverts_distort_over_the_image() {
        for d in models() {
            for i in 0..21 {
                for j in 0..21 {
                    let (x, y) = (-0.6 + 0.06 * i as f64, -0.45 + 0.045 * j as f64);
                    let (xd, yd) = d.distort(x, y);
                    let (bx, by) = d.undistort(xd, yd).expect("converges");
                    assert!(
                        (bx - x).abs() < 1e-8 && (by - y).abs() < 1e-8,
                        "{d:?} at ({x}, {y}): back at ({bx}, {by})"
                    );
                }
            }
        }
    }

    #[test]
    fn plumb_bob_matches_a_hand_computed_point() {
        // k1 = -0.2 alone: x_d = x (1 - 0.2 r^2); at (0.5, 0) that is 0.5 * 0.95.
        let d = Distortion::from_ros("plumb_bob", &[-0.2, 0.0, 0.0, 0.0, 0.0]).unwrap();
        let (xd, yd) = d.distort(0.5, 0.0);
        assert!((xd - 0.475).abs() < 1e-12 && yd == 0.0);
        // Tangential p1 = 0.01 at (0.1, 0.2): dx = 2 p1 x y, dy = p1 (r^2 + 2 y^2).
        let t = Distortion::from_ros("plumb_bob", &[0.0, 0.0, 0.01, 0.0]).unwrap();
        let (xd, yd) = t.distort(0.1, 0.2);
        assert!((xd - (0.1 + 2.0 * 0.01 * 0.02)).abs() < 1e-12);
        assert!((yd - (0.2 + 0.01 * (0.05 + 0.08))).abs() < 1e-12);
    }

    #[test]
    fn equidistant_is_the_angle_for_zero_coefficients() {
        // theta_d = theta: a ray at 45 degrees lands at radius pi/4, not 1.
        let d = Distortion::Equidistant([1e-9, 0.0, 0.0, 0.0]);
        let (xd, _) = d.distort(1.0, 0.0);
        assert!((xd - std::f64::consts::FRAC_PI_4).abs() < 1e-6);
    }

    #[test]
    fn ros_forms_are_read_and_refused_as_stated() {
        assert_eq!(Distortion::from_ros("", &[]).unwrap(), Distortion::None);
        assert_eq!(
            Distortion::from_ros("plumb_bob", &[0.0; 5]).unwrap(),
            Distortion::None
        );
        // Zero padding to OpenCV's 14 terms is fine; a non-zero extra term is not.
        let mut d14 = vec![0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        d14.extend([0.0; 6]);
        assert!(Distortion::from_ros("rational_polynomial", &d14).is_ok());
        d14[10] = 0.3;
        assert!(Distortion::from_ros("rational_polynomial", &d14).is_err());
        let e = Distortion::from_ros("equidistant", &[0.1, 0.2]).unwrap_err();
        assert!(e.contains("takes 4"), "{e}");
        let e = Distortion::from_ros("kb8", &[0.1; 4]).unwrap_err();
        assert!(e.contains("unknown distortion model"), "{e}");
        assert!(Distortion::from_ros("", &[0.1]).is_err());
        assert!(Distortion::from_ros("plumb_bob", &[f64::NAN, 0.0, 0.0, 0.0]).is_err());
        let json = serde_json::json!({"model": "plumb_bob", "coefficients": [0.1, 0.0, 0.0, 0.0]});
        let d: Distortion = serde_json::from_value(json).unwrap();
        assert_eq!(d, Distortion::PlumbBob([0.1, 0.0, 0.0, 0.0, 0.0]));
    }

    #[test]
    fn a_plane_survives_distortion_and_removal() {
        // A tilted plane rendered through a distorting lens, then undistorted, gives the depth
        // the pinhole camera sees, except near the border the lens pulled inward.
        let k = Intrinsics::new(300.0, 300.0, 160.0, 120.0, 320, 240).unwrap();
        let plane = |x: f64, y: f64| 1.0 / (1.0 / 1.5 + 0.2 * x + 0.1 * y); // z of the ray (x, y)
        for d in models() {
            let mut distorted = vec![0.0f32; k.pixel_count()];
            for v in 0..240 {
                for u in 0..320 {
                    let xd = (u as f64 + 0.5 - 160.0) / 300.0;
                    let yd = (v as f64 + 0.5 - 120.0) / 300.0;
                    if let Some((x, y)) = d.undistort(xd, yd) {
                        distorted[v * 320 + u] = plane(x, y) as f32;
                    }
                }
            }
            let dm = DepthMap::new(320, 240, distorted).unwrap();
            let out = undistort_depth(&dm, &k, &d);
            let mut errs = Vec::new();
            for v in 20..220 {
                for u in 30..290 {
                    let z = out.get(u, v);
                    if z > 0.0 {
                        let x = (u as f64 + 0.5 - 160.0) / 300.0;
                        let y = (v as f64 + 0.5 - 120.0) / 300.0;
                        errs.push((z as f64 - plane(x, y)).abs());
                    }
                }
            }
            errs.sort_by(f64::total_cmp);
            assert!(errs.len() > 40_000, "{d:?}: {} pixels", errs.len());
            let p99 = errs[errs.len() * 99 / 100];
            assert!(p99 < 1e-3, "{d:?}: 99th percentile error {p99} m");
        }
    }

    #[test]
    fn depth_is_not_averaged_across_an_edge() {
        // A step from 1 m to 2 m: every undistorted pixel is one of the two, never between.
        let k = Intrinsics::new(200.0, 200.0, 50.0, 50.0, 100, 100).unwrap();
        let d = Distortion::PlumbBob([-0.3, 0.1, 0.0, 0.0, 0.0]);
        let src: Vec<f32> = (0..10_000)
            .map(|i| if i % 100 < 50 { 1.0 } else { 2.0 })
            .collect();
        let out = undistort_depth(&DepthMap::new(100, 100, src).unwrap(), &k, &d);
        for &z in out.data() {
            assert!(
                z == 0.0 || (z - 1.0).abs() < 1e-6 || (z - 2.0).abs() < 1e-6,
                "{z}"
            );
        }
    }
}
