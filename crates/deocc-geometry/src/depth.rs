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
