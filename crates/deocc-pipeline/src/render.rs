//! Pictures of a cloud: z-buffered point splats from a camera, generated points highlighted.

use deocc_geometry::camera::Camera;
use deocc_geometry::PointCloud;
use image::RgbImage;

/// Colour of generated points in pictures.
pub const GENERATED_COLOR: [u8; 3] = [255, 0, 200];

/// Renders `cloud` from `camera` with square splats of `radius` pixels; generated points in
/// [`GENERATED_COLOR`] when `highlight` is set.
pub fn splat(cloud: &PointCloud, camera: &Camera, radius: i64, highlight: bool) -> RgbImage {
    let k = &camera.intrinsics;
    let (w, h) = (k.width() as i64, k.height() as i64);
    let mut z = vec![f32::INFINITY; (w * h) as usize];
    let mut img = RgbImage::from_pixel(k.width(), k.height(), image::Rgb([20, 20, 28]));
    for (i, p) in cloud.positions.iter().enumerate() {
        let Some((px, d)) = camera.project_world(p) else {
            continue;
        };
        let generated = cloud.generated.as_ref().is_some_and(|g| g[i] > 0);
        let color = if generated && highlight {
            GENERATED_COLOR
        } else {
            cloud
                .colors
                .as_ref()
                .map(|c| c[i])
                .unwrap_or([200, 200, 200])
        };
        let (u0, v0) = (px.x.floor() as i64, px.y.floor() as i64);
        for v in (v0 - radius).max(0)..=(v0 + radius).min(h - 1) {
            for u in (u0 - radius).max(0)..=(u0 + radius).min(w - 1) {
                let idx = (v * w + u) as usize;
                if d < z[idx] {
                    z[idx] = d;
                    img.put_pixel(u as u32, v as u32, image::Rgb(color));
                }
            }
        }
    }
    img
}

/// Two images side by side.
pub fn side_by_side(a: &RgbImage, b: &RgbImage) -> RgbImage {
    let mut out = RgbImage::new(a.width() + b.width(), a.height().max(b.height()));
    for (x, y, p) in a.enumerate_pixels() {
        out.put_pixel(x, y, *p);
    }
    for (x, y, p) in b.enumerate_pixels() {
        out.put_pixel(a.width() + x, y, *p);
    }
    out
}
