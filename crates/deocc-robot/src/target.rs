//! Choosing the target by where it is in a picture: a robot is told "the bottle", a user points
//! at it. A pixel or a box in one view of the scene is answered with the instance found there:
//! the cloud's points (observed and completed, with their instance ids) are drawn into that view
//! with a z-buffer, so the answer is the surface in front, as the camera saw it.
//!
//! - a **pixel** `(u, v)`: the instance of the nearest surface drawn within
//!   [`PIXEL_SEARCH_RADIUS`] pixels of it (points are sparse at a distance), nearest pixel first;
//! - a **box** `(u0, v0, u1, v1)`: the instance with the largest share of its own drawn pixels
//!   inside the box (an object wholly inside scores 1, the table it stands on far less), ties by
//!   pixel count.
//!
//! Coordinates are pinhole pixels of the view (continuous; pixel `(u, v)` covers `[u, u+1)`);
//! callers that hold a raw image with lens distortion map the pixel through the lens first.

use deocc_geometry::camera::Camera;
use deocc_geometry::PointCloud;

/// How far from the given pixel a point may be drawn and still be what the user pointed at.
pub const PIXEL_SEARCH_RADIUS: i64 = 4;

/// Where the target is in the view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pick {
    Pixel { u: f32, v: f32 },
    Box { u0: f32, v0: f32, u1: f32, v1: f32 },
}

impl Pick {
    /// Parses `U,V` (pixel) or `U0,V0,U1,V1` (box).
    pub fn parse(text: &str) -> Result<Pick, String> {
        let v: Vec<f32> = text
            .split(',')
            .map(|t| t.trim().parse::<f32>())
            .collect::<Result<_, _>>()
            .map_err(|_| format!("{text:?}: expected U,V or U0,V0,U1,V1 (numbers)"))?;
        if v.iter().any(|x| !x.is_finite()) {
            return Err(format!("{text:?}: not finite"));
        }
        match v[..] {
            [u, v] => Ok(Pick::Pixel { u, v }),
            [u0, v0, u1, v1] if u1 > u0 && v1 > v0 => Ok(Pick::Box { u0, v0, u1, v1 }),
            [_, _, _, _] => Err(format!("{text:?}: a box needs U0 < U1 and V0 < V1")),
            _ => Err(format!(
                "{text:?}: expected two numbers (a pixel) or four (a box)"
            )),
        }
    }
}

impl Pick {
    /// The pick in pinhole pixels of a camera with intrinsics `k` whose raw image has lens
    /// `lens`: the pixels a user picked in the image as the camera gave it, moved through the
    /// lens. `None` outside the region where the lens model is one-to-one.
    pub fn through_lens(
        self,
        lens: &deocc_geometry::distortion::Distortion,
        k: &deocc_geometry::camera::Intrinsics,
    ) -> Option<Pick> {
        let through = |u: f32, v: f32| {
            lens.undistort_pixel(k, u as f64, v as f64)
                .map(|(u, v)| (u as f32, v as f32))
        };
        Some(match self {
            Pick::Pixel { u, v } => {
                let (u, v) = through(u, v)?;
                Pick::Pixel { u, v }
            }
            Pick::Box { u0, v0, u1, v1 } => {
                let ((u0, v0), (u1, v1)) = (through(u0, v0)?, through(u1, v1)?);
                Pick::Box { u0, v0, u1, v1 }
            }
        })
    }
}

/// Which instance of `cloud` the user pointed at in `camera`'s view; the error says what was
/// there instead (nothing, background) and where the instances are.
pub fn instance_at(cloud: &PointCloud, camera: &Camera, pick: Pick) -> Result<u32, String> {
    let k = &camera.intrinsics;
    let (w, h) = (k.width() as i64, k.height() as i64);
    let ids = cloud
        .instance
        .as_ref()
        .ok_or("the cloud has no instance ids")?;
    let check = |u: f32, v: f32| {
        if u < 0.0 || v < 0.0 || u > w as f32 || v > h as f32 {
            Err(format!("({u}, {v}) is outside the {w}x{h} view"))
        } else {
            Ok(())
        }
    };
    match pick {
        Pick::Pixel { u, v } => check(u, v)?,
        Pick::Box { u0, v0, u1, v1 } => {
            check(u0, v0)?;
            check(u1, v1)?;
        }
    }
    // Z-buffer of instance ids, one pixel per point.
    let mut depth = vec![f32::INFINITY; (w * h) as usize];
    let mut label = vec![0u32; (w * h) as usize];
    for (p, &id) in cloud.positions.iter().zip(ids) {
        let Some((px, z)) = camera.project_world(p) else {
            continue;
        };
        let (pu, pv) = (px.x.floor() as i64, px.y.floor() as i64);
        if pu < 0 || pv < 0 || pu >= w || pv >= h {
            continue;
        }
        let i = (pv * w + pu) as usize;
        if z < depth[i] {
            depth[i] = z;
            label[i] = id;
        }
    }
    match pick {
        Pick::Pixel { u, v } => {
            let (cu, cv) = (u.floor() as i64, v.floor() as i64);
            let mut best: Option<(i64, u32)> = None;
            for dv in -PIXEL_SEARCH_RADIUS..=PIXEL_SEARCH_RADIUS {
                for du in -PIXEL_SEARCH_RADIUS..=PIXEL_SEARCH_RADIUS {
                    let (pu, pv) = (cu + du, cv + dv);
                    if pu < 0 || pv < 0 || pu >= w || pv >= h {
                        continue;
                    }
                    let i = (pv * w + pu) as usize;
                    let d2 = du * du + dv * dv;
                    if depth[i].is_finite() && best.is_none_or(|(b, _)| d2 < b) {
                        best = Some((d2, label[i]));
                    }
                }
            }
            match best {
                Some((_, id)) if id != 0 => Ok(id),
                Some(_) => Err(format!(
                    "pixel ({u}, {v}) shows background (no instance); {}",
                    where_instances_are(&label, w)
                )),
                None => Err(format!(
                    "no point of the scene is drawn within {PIXEL_SEARCH_RADIUS} pixels of ({u}, \
                     {v}); {}",
                    where_instances_are(&label, w)
                )),
            }
        }
        Pick::Box { u0, v0, u1, v1 } => {
            let mut total = std::collections::BTreeMap::<u32, (usize, usize)>::new();
            for (i, &id) in label.iter().enumerate() {
                if id == 0 || !depth[i].is_finite() {
                    continue;
                }
                let (pu, pv) = ((i as i64 % w) as f32 + 0.5, (i as i64 / w) as f32 + 0.5);
                let e = total.entry(id).or_default();
                e.1 += 1;
                if pu >= u0 && pu < u1 && pv >= v0 && pv < v1 {
                    e.0 += 1;
                }
            }
            total
                .iter()
                .filter(|(_, &(inside, _))| inside > 0)
                .max_by(|a, b| {
                    let share = |&(i, t): &(usize, usize)| i as f64 / t as f64;
                    share(a.1).total_cmp(&share(b.1)).then(a.1 .0.cmp(&b.1 .0))
                })
                .map(|(&id, _)| id)
                .ok_or_else(|| {
                    format!(
                        "no instance is drawn inside the box ({u0}, {v0})-({u1}, {v1}); {}",
                        where_instances_are(&label, w)
                    )
                })
        }
    }
}

/// "instances at: 3 near (120, 88), 5 near (300, 140)": each drawn instance's pixel centroid, so
/// an error points the user somewhere useful.
fn where_instances_are(label: &[u32], w: i64) -> String {
    let mut sums = std::collections::BTreeMap::<u32, (f64, f64, usize)>::new();
    for (i, &id) in label.iter().enumerate() {
        if id != 0 {
            let e = sums.entry(id).or_default();
            e.0 += (i as i64 % w) as f64;
            e.1 += (i as i64 / w) as f64;
            e.2 += 1;
        }
    }
    if sums.is_empty() {
        return "no instance is drawn in this view".into();
    }
    let list: Vec<String> = sums
        .iter()
        .map(|(id, (su, sv, n))| {
            format!("{id} near ({:.0}, {:.0})", su / *n as f64, sv / *n as f64)
        })
        .collect();
    format!("instances in this view: {}", list.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;
    use deocc_geometry::camera::Intrinsics;
    use nalgebra::{Isometry3, Point3};

    /// A wall (instance 1) at 2 m with a small box face (instance 7) at 1 m in front of its
    /// middle, seen by a camera at the origin.
    fn scene() -> (PointCloud, Camera) {
        let camera = Camera {
            intrinsics: Intrinsics::new(100.0, 100.0, 50.0, 50.0, 100, 100).unwrap(),
            world_from_camera: Isometry3::identity(),
        };
        let mut pts = Vec::new();
        let mut ids = Vec::new();
        for i in 0..200 {
            for j in 0..200 {
                pts.push(Point3::new(
                    -1.0 + i as f32 * 0.01,
                    -1.0 + j as f32 * 0.01,
                    2.0,
                ));
                ids.push(1);
            }
        }
        for i in 0..20 {
            for j in 0..20 {
                pts.push(Point3::new(
                    -0.1 + i as f32 * 0.01,
                    -0.1 + j as f32 * 0.01,
                    1.0,
                ));
                ids.push(7);
            }
        }
        let mut cloud = PointCloud::from_positions(pts);
        cloud.instance = Some(ids);
        (cloud, camera)
    }

    #[test]
    fn a_pixel_finds_the_surface_in_front() {
        let (cloud, camera) = scene();
        assert_eq!(
            instance_at(&cloud, &camera, Pick::Pixel { u: 50.0, v: 50.0 }),
            Ok(7)
        );
        assert_eq!(
            instance_at(&cloud, &camera, Pick::Pixel { u: 10.0, v: 80.0 }),
            Ok(1)
        );
        let e = instance_at(&cloud, &camera, Pick::Pixel { u: 150.0, v: 5.0 }).unwrap_err();
        assert!(e.contains("outside"), "{e}");
    }

    #[test]
    fn a_box_prefers_the_object_wholly_inside() {
        // The box holds all of instance 7 and more wall pixels than 7 has, but a small share of
        // the wall.
        let (cloud, camera) = scene();
        let pick = Pick::parse("30,30,70,70").unwrap();
        assert_eq!(instance_at(&cloud, &camera, pick), Ok(7));
        let pick = Pick::parse("0,0,20,20").unwrap();
        assert_eq!(instance_at(&cloud, &camera, pick), Ok(1));
    }

    #[test]
    fn background_and_empty_views_say_where_instances_are() {
        let (mut cloud, camera) = scene();
        cloud
            .instance
            .as_mut()
            .unwrap()
            .iter_mut()
            .take(40_000)
            .for_each(|i| *i = 0);
        let e = instance_at(&cloud, &camera, Pick::Pixel { u: 5.0, v: 5.0 }).unwrap_err();
        assert!(
            e.contains("background") && e.contains("7 near (50, 50)"),
            "{e}"
        );
        assert!(Pick::parse("1,2,3").is_err());
        assert!(Pick::parse("5,5,1,1").is_err());
        assert!(Pick::parse("a,b").is_err());
    }
}
