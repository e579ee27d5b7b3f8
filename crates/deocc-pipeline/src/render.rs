//! Pictures of a cloud: z-buffered point splats from a camera, generated points highlighted.

use deocc_geometry::camera::Camera;
use deocc_geometry::{PointCloud, Provenance};
use image::RgbImage;

/// Colour of generated object points in pictures.
pub const GENERATED_COLOR: [u8; 3] = [255, 0, 200];

/// Share of [`GENERATED_COLOR`] in a plane-fill point's own colour: the filled floor and table
/// tops read as tinted, so the completed objects in front of them stand out.
pub const PLANE_FILL_TINT: f32 = 0.35;

/// Renders `cloud` from `camera` with square splats of `radius` pixels; generated object points
/// in [`GENERATED_COLOR`] and plane fill tinted with it when `highlight` is set.
pub fn splat(cloud: &PointCloud, camera: &Camera, radius: i64, highlight: bool) -> RgbImage {
    let k = &camera.intrinsics;
    let (w, h) = (k.width() as i64, k.height() as i64);
    let mut z = vec![f32::INFINITY; (w * h) as usize];
    let mut img = RgbImage::from_pixel(k.width(), k.height(), image::Rgb([20, 20, 28]));
    for (i, p) in cloud.positions.iter().enumerate() {
        let Some((px, d)) = camera.project_world(p) else {
            continue;
        };
        let code = cloud.generated.as_ref().map_or(0, |g| g[i]);
        let own = cloud
            .colors
            .as_ref()
            .map(|c| c[i])
            .unwrap_or([200, 200, 200]);
        let color = if !highlight || code == Provenance::Observed.code() {
            own
        } else if code == Provenance::PlaneFill.code() {
            let mix = |a: u8, b: u8| {
                (a as f32 * (1.0 - PLANE_FILL_TINT) + b as f32 * PLANE_FILL_TINT) as u8
            };
            [
                mix(own[0], GENERATED_COLOR[0]),
                mix(own[1], GENERATED_COLOR[1]),
                mix(own[2], GENERATED_COLOR[2]),
            ]
        } else {
            GENERATED_COLOR
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

#[cfg(test)]
mod tests {
    use super::*;
    use deocc_geometry::camera::Intrinsics;
    use nalgebra::{Isometry3, Point3};

    /// Observed points keep their colour, object completions are magenta, plane fill is tinted:
    /// a completed object stands out against the filled table behind it.
    #[test]
    fn completions_stand_out_against_plane_fill() {
        let camera = Camera {
            intrinsics: Intrinsics::new(50.0, 50.0, 16.0, 16.0, 32, 32).unwrap(),
            world_from_camera: Isometry3::identity(),
        };
        let mut cloud = PointCloud::from_positions(vec![
            Point3::new(-0.2, 0.0, 1.0),
            Point3::new(0.0, 0.0, 1.0),
            Point3::new(0.2, 0.0, 1.0),
        ]);
        cloud.colors = Some(vec![[200, 30, 30]; 3]);
        cloud.generated = Some(vec![
            Provenance::Observed.code(),
            Provenance::Model.code(),
            Provenance::PlaneFill.code(),
        ]);
        let img = splat(&cloud, &camera, 0, true);
        let at = |x: f32| {
            let (px, _) = camera.project_world(&Point3::new(x, 0.0, 1.0)).unwrap();
            img.get_pixel(px.x as u32, px.y as u32).0
        };
        assert_eq!(at(-0.2), [200, 30, 30]);
        assert_eq!(at(0.0), GENERATED_COLOR);
        let tint = at(0.2);
        assert!(tint != [200, 30, 30] && tint != GENERATED_COLOR, "{tint:?}");
        assert!(
            tint[2] > 30,
            "plane fill carries some of the highlight: {tint:?}"
        );
        // Without highlighting, every point keeps its own colour.
        let plain = splat(&cloud, &camera, 0, false);
        let (px, _) = camera.project_world(&Point3::new(0.0, 0.0, 1.0)).unwrap();
        assert_eq!(plain.get_pixel(px.x as u32, px.y as u32).0, [200, 30, 30]);
    }
}
