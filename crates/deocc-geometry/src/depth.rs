//! Depth maps: back-projection to point clouds and z-buffer rendering of clouds into depth.

use nalgebra::Point3;

use crate::camera::Camera;
use crate::cloud::PointCloud;
use crate::error::{GeometryError, Result};

/// A depth image in metres along the optical axis (z), row-major; 0 means "no measurement".
/// The constructor guarantees every value is finite and non-negative.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    width: u32,
    height: u32,
    depth_m: Vec<f32>,
}

impl DepthMap {
    pub fn new(width: u32, height: u32, depth_m: Vec<f32>) -> Result<Self> {
        let expected = width as usize * height as usize;
        if depth_m.len() != expected {
            return Err(GeometryError::SizeMismatch {
                what: "depth map pixels",
                expected,
                got: depth_m.len(),
            });
        }
        if let Some(index) = depth_m.iter().position(|d| !d.is_finite() || *d < 0.0) {
            return Err(GeometryError::NonFinite {
                what: "depth map (NaN, infinite or negative depth)",
                index,
            });
        }
        Ok(Self {
            width,
            height,
            depth_m,
        })
    }

    pub fn zeros(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            depth_m: vec![0.0; width as usize * height as usize],
        }
    }

    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn data(&self) -> &[f32] {
        &self.depth_m
    }
    pub fn into_data(self) -> Vec<f32> {
        self.depth_m
    }

    /// Depth at integer pixel (u, v); 0 where unmeasured.
    pub fn get(&self, u: u32, v: u32) -> f32 {
        self.depth_m[v as usize * self.width as usize + u as usize]
    }

    /// Sets a pixel; negative or non-finite values are stored as 0 (no measurement), keeping the
    /// invariant.
    pub fn set(&mut self, u: u32, v: u32, depth_m: f32) {
        let d = if depth_m.is_finite() && depth_m > 0.0 {
            depth_m
        } else {
            0.0
        };
        self.depth_m[v as usize * self.width as usize + u as usize] = d;
    }

    pub fn valid_count(&self) -> usize {
        self.depth_m.iter().filter(|d| **d > 0.0).count()
    }
}

/// Checks that a depth map has the size the camera expects.
pub fn check_size(depth: &DepthMap, camera: &Camera) -> Result<()> {
    let k = &camera.intrinsics;
    if depth.width != k.width() || depth.height != k.height() {
        return Err(GeometryError::InvalidArgument(format!(
            "depth map is {}x{} but the intrinsics are for {}x{}",
            depth.width,
            depth.height,
            k.width(),
            k.height()
        )));
    }
    Ok(())
}

/// Back-projects every measured pixel into the world frame. Returns the cloud and, per point, the
/// linear pixel index it came from (so masks and colours can be attached by the caller).
pub fn backproject(depth: &DepthMap, camera: &Camera) -> Result<(PointCloud, Vec<u32>)> {
    backproject_masked(depth, camera, |_| true)
}

/// Back-projects the measured pixels whose linear index passes `keep`.
pub fn backproject_masked(
    depth: &DepthMap,
    camera: &Camera,
    keep: impl Fn(usize) -> bool,
) -> Result<(PointCloud, Vec<u32>)> {
    check_size(depth, camera)?;
    let w = depth.width as usize;
    let mut positions = Vec::new();
    let mut pixels = Vec::new();
    for (i, &d) in depth.depth_m.iter().enumerate() {
        if d > 0.0 && keep(i) {
            let (u, v) = ((i % w) as u32, (i / w) as u32);
            positions.push(camera.unproject_pixel(u, v, d));
            pixels.push(i as u32);
        }
    }
    Ok((PointCloud::from_positions(positions), pixels))
}

/// Renders points into a depth map for `camera` with a z-buffer: each point covers the pixel it
/// projects into (and a square of `splat_radius_px` around it), nearest point wins.
pub fn render_depth(points: &[Point3<f32>], camera: &Camera, splat_radius_px: u32) -> DepthMap {
    let k = &camera.intrinsics;
    let (w, h) = (k.width() as i64, k.height() as i64);
    let mut out = DepthMap::zeros(k.width(), k.height());
    let r = splat_radius_px as i64;
    for p in points {
        let Some((px, z)) = camera.project_world(p) else {
            continue;
        };
        let (u0, v0) = (px.x.floor() as i64, px.y.floor() as i64);
        for v in (v0 - r).max(0)..=(v0 + r).min(h - 1) {
            for u in (u0 - r).max(0)..=(u0 + r).min(w - 1) {
                let idx = (v * w + u) as usize;
                let cur = out.depth_m[idx];
                if cur == 0.0 || z < cur {
                    out.depth_m[idx] = z;
                }
            }
        }
    }
    out
}

/// Registers a depth map from a separate depth camera to the colour camera: every measured pixel
/// is back-projected through `depth_k`, moved by `color_from_depth` and drawn into a
/// `color_k`-sized map with a z-buffer (nearest surface wins, as the Azure Kinect SDK's and
/// librealsense's `align` do). Each depth pixel covers the colour pixels its footprint spans, so
/// a coarser depth camera leaves no pinholes; pixels the depth camera did not see are 0.
pub fn register_depth(
    depth: &DepthMap,
    depth_k: &crate::camera::Intrinsics,
    color_k: &crate::camera::Intrinsics,
    color_from_depth: &nalgebra::Isometry3<f32>,
) -> DepthMap {
    let (w, h) = (color_k.width() as i64, color_k.height() as i64);
    let mut out = DepthMap::zeros(color_k.width(), color_k.height());
    // Colour pixels per depth pixel at equal depth.
    let scale = (color_k.fx() / depth_k.fx()).max(color_k.fy() / depth_k.fy());
    for v in 0..depth.height() {
        for u in 0..depth.width() {
            let z = depth.get(u, v);
            if z <= 0.0 {
                continue;
            }
            let p = color_from_depth.transform_point(&depth_k.unproject(
                u as f32 + 0.5,
                v as f32 + 0.5,
                z,
            ));
            let Some(px) = color_k.project(&p) else {
                continue;
            };
            let half = 0.5 * scale * z / p.z;
            let (u0, u1) = ((px.x - half).round() as i64, (px.x + half).round() as i64);
            let (v0, v1) = ((px.y - half).round() as i64, (px.y + half).round() as i64);
            for cv in v0.max(0)..v1.max(v0 + 1).min(h) {
                for cu in u0.max(0)..u1.max(u0 + 1).min(w) {
                    let idx = (cv * w + cu) as usize;
                    let cur = out.depth_m[idx];
                    if cur == 0.0 || p.z < cur {
                        out.depth_m[idx] = p.z;
                    }
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use nalgebra::{Isometry3, Point3, Vector3};

    /// z of the first surface hit along a ray from `o` in direction `d` (colour frame): a wall at
    /// z = 2 m and a box face at z = 1 m for |x| < 0.2, |y| < 0.15.
    fn hit(o: Point3<f32>, d: Vector3<f32>) -> f32 {
        let t = (1.0 - o.z) / d.z;
        let p = o + d * t;
        if p.x.abs() < 0.2 && p.y.abs() < 0.15 {
            return 1.0;
        }
        2.0
    }

    #[test]
    fn registered_depth_matches_the_colour_cameras_own_view() {
        let color_k = Intrinsics::new(300.0, 300.0, 160.0, 120.0, 320, 240).unwrap();
        let depth_k = Intrinsics::new(140.0, 140.0, 80.0, 60.0, 160, 120).unwrap();
        // The depth camera sits 3.2 cm to the colour camera's left, turned 2 degrees.
        let color_from_depth = Isometry3::new(
            Vector3::new(-0.032, 0.002, 0.001),
            Vector3::new(0.0, 2f32.to_radians(), 0.0),
        );
        let mut d = DepthMap::zeros(160, 120);
        for v in 0..120 {
            for u in 0..160 {
                let ray_d = depth_k.unproject(u as f32 + 0.5, v as f32 + 0.5, 1.0);
                let o = color_from_depth.transform_point(&Point3::origin());
                let dir = color_from_depth.transform_vector(&ray_d.coords);
                let z_c = hit(o, dir);
                // Depth along the depth camera's own axis.
                let t = (z_c - o.z) / dir.z;
                d.set(u, v, t);
            }
        }
        let reg = register_depth(&d, &depth_k, &color_k, &color_from_depth);
        let (mut seen, mut good) = (0usize, 0usize);
        for v in 0..240 {
            for u in 0..320 {
                let z = reg.get(u, v);
                if z == 0.0 {
                    continue;
                }
                seen += 1;
                let dir = color_k
                    .unproject(u as f32 + 0.5, v as f32 + 0.5, 1.0)
                    .coords;
                if (z - hit(Point3::origin(), dir)).abs() < 0.005 {
                    good += 1;
                }
            }
        }
        let n = 320 * 240;
        assert!(
            seen as f32 > 0.85 * n as f32,
            "{seen} of {n} pixels have depth"
        );
        assert!(
            good as f32 > 0.98 * seen as f32,
            "{good} of {seen} registered pixels within 5 mm"
        );
    }
}
