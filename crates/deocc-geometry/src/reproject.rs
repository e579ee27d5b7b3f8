//! Other views' observations of one object, seen from another camera.
//!
//! The pixels of a source view that belong to the object are put into 3-D, dropped where their
//! surface faces away from the target camera (the target would see the object's other side
//! there), and splatted into the target image with a z-buffer, each point covering its pixel's
//! footprint. What comes out is what the target camera would see of the object's observed
//! surface if nothing stood in front of it: the part of a hidden object another view saw.

use nalgebra::{Point3, Vector3};

use crate::camera::Camera;

/// One view's observation of an object.
#[derive(Debug, Clone, Copy)]
pub struct SourceView<'a> {
    pub camera: &'a Camera,
    /// (w*h) metric depth along the optical axis, 0 where nothing was measured.
    pub depth_m: &'a [f32],
    /// (w*h*3) colour.
    pub rgb: &'a [u8],
    /// Indices of the object's pixels (with depth).
    pub pixels: &'a [u32],
}

/// What the target camera would see of the sources' points: per target pixel, the nearest
/// point's depth along the target's axis (0 where no point lands) and colour.
#[derive(Debug, Clone, PartialEq)]
pub struct Reprojection {
    pub depth_m: Vec<f32>,
    pub rgb: Vec<u8>,
    /// Per target pixel, the depth of the farthest source point whose surface faces away from
    /// the target (0 where none lands): the object's back along that pixel's ray, observed.
    /// Empty unless asked for ([`reproject_views_and_backs`]).
    pub back_depth_m: Vec<f32>,
}

impl Reprojection {
    /// Target pixels some point landed in.
    pub fn hits(&self) -> usize {
        self.depth_m.iter().filter(|&&d| d > 0.0).count()
    }

    /// Target pixels some point facing away from the target landed in.
    pub fn back_hits(&self) -> usize {
        self.back_depth_m.iter().filter(|&&d| d > 0.0).count()
    }
}

/// One source point in the target image: continuous pixel, depth, footprint half-side, colour.
struct Splat {
    x: f32,
    y: f32,
    z: f32,
    half: f32,
    rgb: [u8; 3],
}

/// Smallest splat half-side in target pixels: a pixel takes the points within a quarter pixel
/// of its centre (denser sources have several there; a pixel whose centre lies off the object by
/// more than that takes none, so the outline does not grow by the pixels its edge crosses).
const MIN_SPLAT_HALF_PX: f32 = 0.25;
/// Largest splat half-side in target pixels (a source pixel seen much closer in the target).
const MAX_SPLAT_HALF_PX: f32 = 2.0;
/// Neighbours farther apart in depth than this share of the depth are not the same surface.
const SURFACE_JUMP: f32 = 0.03;
/// Step to the neighbours the normal is taken from, pixels (2: a little sensor noise averages).
const NORMAL_STEP: i64 = 2;

/// The sources' object points as the `target` camera sees them (see the module docs). A point
/// covers the target pixels whose centres lie within its footprint (at least
/// [`MIN_SPLAT_HALF_PX`]); of the points on a pixel's nearest surface, the one nearest its
/// centre gives its colour and depth.
pub fn reproject_views(target: &Camera, sources: &[SourceView<'_>]) -> Reprojection {
    reproject(target, sources, false)
}

/// [`reproject_views`], and the surfaces that face away from the target as
/// [`Reprojection::back_depth_m`] (where the target's rays leave the object).
pub fn reproject_views_and_backs(target: &Camera, sources: &[SourceView<'_>]) -> Reprojection {
    reproject(target, sources, true)
}

fn reproject(target: &Camera, sources: &[SourceView<'_>], backs: bool) -> Reprojection {
    let k = &target.intrinsics;
    let (w, h) = (k.width() as i64, k.height() as i64);
    let mut depth_m = vec![0f32; (w * h) as usize];
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    let projector = target.projector();
    let eye = target.center();
    let mut splats: Vec<Splat> = Vec::new();
    let mut back_splats: Vec<Splat> = Vec::new();
    for src in sources {
        let sk = &src.camera.intrinsics;
        let (sw, sh) = (sk.width() as i64, sk.height() as i64);
        if src.depth_m.len() != (sw * sh) as usize || src.rgb.len() != (sw * sh * 3) as usize {
            continue;
        }
        let point_at = |u: i64, v: i64| -> Option<Point3<f32>> {
            if u < 0 || v < 0 || u >= sw || v >= sh {
                return None;
            }
            let d = src.depth_m[(v * sw + u) as usize];
            (d > 0.0).then(|| src.camera.unproject_pixel(u as u32, v as u32, d))
        };
        let src_eye = src.camera.center();
        for &i in src.pixels {
            let (u, v) = ((i as i64) % sw, (i as i64) / sw);
            let z = src.depth_m[i as usize];
            if z <= 0.0 {
                continue;
            }
            let p = src.camera.unproject_pixel(u as u32, v as u32, z);
            let same = |q: Option<Point3<f32>>| {
                q.filter(|q| {
                    let dz = (q - p).dot(&(p - src_eye).normalize()).abs();
                    dz <= SURFACE_JUMP * z
                })
            };
            // Tangents towards whichever neighbour on each axis lies on the same surface.
            let tangent =
                |a: Option<Point3<f32>>, b: Option<Point3<f32>>| -> Option<Vector3<f32>> {
                    match (same(a), same(b)) {
                        (Some(a), Some(b)) => Some(a - b),
                        (Some(a), None) => Some(a - p),
                        (None, Some(b)) => Some(p - b),
                        (None, None) => None,
                    }
                };
            let s = NORMAL_STEP;
            let (Some(tu), Some(tv)) = (
                tangent(point_at(u + s, v), point_at(u - s, v)),
                tangent(point_at(u, v + s), point_at(u, v - s)),
            ) else {
                continue;
            };
            let mut n = tu.cross(&tv);
            if n.norm_squared() == 0.0 {
                continue;
            }
            if n.dot(&(src_eye - p)) < 0.0 {
                n = -n;
            }
            // Facing away from the target: the target would see the object's other side here,
            // so this point is the object's back as the target's ray leaves it.
            let facing_away = n.dot(&(eye - p)) <= 0.0;
            if facing_away && !backs {
                continue;
            }
            let Some((x, y, zt)) = projector.project(&p) else {
                continue;
            };
            // The source pixel's footprint in target pixels.
            let half =
                (0.5 * (z / sk.fx()) * (k.fx() / zt)).clamp(MIN_SPLAT_HALF_PX, MAX_SPLAT_HALF_PX);
            let mut c = [0u8; 3];
            c.copy_from_slice(&src.rgb[3 * i as usize..3 * i as usize + 3]);
            let out = if facing_away {
                &mut back_splats
            } else {
                &mut splats
            };
            out.push(Splat {
                x,
                y,
                z: zt,
                half,
                rgb: c,
            });
        }
    }
    // The target pixels a splat covers: those whose centres lie within its footprint (pixel u's
    // centre is u + 0.5), as a renderer samples a pixel at its centre.
    let covered = |s: &Splat| {
        let u0 = ((s.x - s.half - 0.5).ceil() as i64).max(0);
        let u1 = ((s.x + s.half - 0.5).floor() as i64).min(w - 1);
        let v0 = ((s.y - s.half - 0.5).ceil() as i64).max(0);
        let v1 = ((s.y + s.half - 0.5).floor() as i64).min(h - 1);
        (v0..=v1).flat_map(move |v| (u0..=u1).map(move |u| (u, v)))
    };
    // Pass 1: the nearest surface at each pixel.
    let mut nearest = vec![f32::INFINITY; (w * h) as usize];
    for s in &splats {
        for (u, v) in covered(s) {
            let t = (v * w + u) as usize;
            nearest[t] = nearest[t].min(s.z);
        }
    }
    // Pass 2: of the points on that surface (within a pixel's worth of slant and 1% of the
    // depth), the one nearest the pixel's centre gives its colour and depth, so a fine texture
    // is sampled where the target pixel looks.
    let mut best = vec![f32::INFINITY; (w * h) as usize];
    for s in &splats {
        for (u, v) in covered(s) {
            let t = (v * w + u) as usize;
            let zmin = nearest[t];
            if s.z > zmin * (1.01 + 2.0 / k.fx()) {
                continue;
            }
            let d2 = (s.x - (u as f32 + 0.5)).powi(2) + (s.y - (v as f32 + 0.5)).powi(2);
            if d2 < best[t] {
                best[t] = d2;
                depth_m[t] = s.z;
                rgb[3 * t..3 * t + 3].copy_from_slice(&s.rgb);
            }
        }
    }
    let mut back_depth_m = vec![0f32; if backs { (w * h) as usize } else { 0 }];
    for s in &back_splats {
        for (u, v) in covered(s) {
            let t = (v * w + u) as usize;
            back_depth_m[t] = back_depth_m[t].max(s.z);
        }
    }
    Reprojection {
        depth_m,
        rgb,
        back_depth_m,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, Intrinsics};

    fn camera(eye: [f32; 3], w: u32) -> Camera {
        Camera {
            intrinsics: Intrinsics::new(100.0, 100.0, w as f32 / 2.0, w as f32 / 2.0, w, w)
                .unwrap(),
            world_from_camera: look_at(
                &Point3::from(eye),
                &Point3::origin(),
                &Vector3::new(0.0, 0.0, 1.0),
            )
            .unwrap(),
        }
    }

    /// The source's view of the plane x = 0 (its pixels that hit it, |y|, |z| < 0.2), by ray
    /// casting.
    fn plane_view(cam: &Camera) -> (Vec<f32>, Vec<u8>, Vec<u32>) {
        let w = cam.intrinsics.width();
        let mut depth = vec![0f32; (w * w) as usize];
        let mut pixels = Vec::new();
        for v in 0..w {
            for u in 0..w {
                let far = cam.unproject_pixel(u, v, 1.0);
                let dir = far - cam.center();
                let t = -cam.center().x / dir.x;
                let hit = cam.center() + dir * t;
                if t > 0.0 && hit.y.abs() < 0.2 && hit.z.abs() < 0.2 {
                    let i = v * w + u;
                    depth[i as usize] = t; // depth along z: unproject_pixel used depth 1
                    pixels.push(i);
                }
            }
        }
        let rgb = vec![200u8; (w * w * 3) as usize];
        (depth, rgb, pixels)
    }

    #[test]
    fn a_plane_seen_from_one_side_lands_at_its_depth_in_another_view() {
        let src = camera([1.0, 0.3, 0.1], 64);
        let tgt = camera([1.2, -0.4, 0.2], 64);
        let (depth, rgb, pixels) = plane_view(&src);
        assert!(pixels.len() > 200);
        let out = reproject_views(
            &tgt,
            &[SourceView {
                camera: &src,
                depth_m: &depth,
                rgb: &rgb,
                pixels: &pixels,
            }],
        );
        assert!(out.hits() > 200, "{} hits", out.hits());
        // Every hit's depth is where the target's own ray meets the plane.
        let mut checked = 0;
        for (t, &d) in out.depth_m.iter().enumerate() {
            if d == 0.0 {
                continue;
            }
            let (u, v) = ((t % 64) as u32, (t / 64) as u32);
            let far = tgt.unproject_pixel(u, v, 1.0);
            let dir = far - tgt.center();
            let truth = -tgt.center().x / dir.x;
            // A splat covers its footprint, so a pixel may take a neighbour's depth.
            assert!((d - truth).abs() < 0.02, "pixel {t}: {d} vs {truth}");
            assert_eq!(&out.rgb[3 * t..3 * t + 3], &[200, 200, 200]);
            checked += 1;
        }
        assert!(checked > 200);
    }

    #[test]
    fn a_surface_facing_away_from_the_target_is_dropped() {
        let src = camera([1.0, 0.3, 0.1], 64);
        // Behind the plane: it sees the plane's other side.
        let tgt = camera([-1.0, 0.2, 0.1], 64);
        let (depth, rgb, pixels) = plane_view(&src);
        let view = SourceView {
            camera: &src,
            depth_m: &depth,
            rgb: &rgb,
            pixels: &pixels,
        };
        assert_eq!(
            reproject_views(&tgt, &[view]).back_depth_m,
            Vec::<f32>::new()
        );
        let out = reproject_views_and_backs(&tgt, &[view]);
        assert_eq!(out.hits(), 0);
        // It is where the target's rays leave the (thin) object: its back, at the plane's depth.
        assert!(out.back_hits() > 200, "{} back hits", out.back_hits());
        for (t, &d) in out.back_depth_m.iter().enumerate() {
            if d == 0.0 {
                continue;
            }
            let (u, v) = ((t % 64) as u32, (t / 64) as u32);
            let dir = tgt.unproject_pixel(u, v, 1.0) - tgt.center();
            let truth = -tgt.center().x / dir.x;
            assert!((d - truth).abs() < 0.02, "pixel {t}: {d} vs {truth}");
        }
        // The same points from the source's side are kept, and are nobody's back.
        let front = camera([1.1, 0.0, 0.0], 64);
        let out = reproject_views_and_backs(&front, &[view]);
        assert!(out.hits() > 200);
        assert_eq!(out.back_hits(), 0);
    }
}
