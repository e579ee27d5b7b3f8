//! Dense ground truth: points sampled uniformly on every surface, with instance id, normal, and
//! whether any view of the scene sees them.

use deocc_geometry::camera::{Camera, Projector};
use deocc_geometry::PointCloud;
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::render::{Frame, SceneTriangles};
use crate::scene::Scene;

/// Ground-truth points of a scene and, per point, whether some view sees it.
pub struct GroundTruth {
    /// Positions, normals and instance ids.
    pub cloud: PointCloud,
    pub seen: Vec<bool>,
}

/// Samples `density` points per square metre uniformly over every triangle (area-weighted; the
/// fractional expected count decided by the seeded generator, so the sampling is deterministic).
pub fn sample_surfaces(
    scene: &Scene,
    tris: &SceneTriangles,
    density: f32,
    seed: u64,
) -> PointCloud {
    let mut r = ChaCha8Rng::seed_from_u64(seed ^ 0x67_7470_6f69_6e74);
    let mut positions = Vec::new();
    let mut normals = Vec::new();
    let mut instance = Vec::new();
    for (ti, c) in tris.corners.iter().enumerate() {
        let area = 0.5 * (c[1] - c[0]).cross(&(c[2] - c[0])).norm();
        let expected = area * density;
        let mut n = expected.floor() as usize;
        if r.random::<f32>() < expected - n as f32 {
            n += 1;
        }
        let id = scene.objects[tris.object[ti] as usize].instance_id as u32;
        for _ in 0..n {
            let (mut a, mut b): (f32, f32) = (r.random(), r.random());
            if a + b > 1.0 {
                a = 1.0 - a;
                b = 1.0 - b;
            }
            positions.push(c[0] + (c[1] - c[0]) * a + (c[2] - c[0]) * b);
            normals.push(tris.normals[ti]);
            instance.push(id);
        }
    }
    PointCloud {
        positions,
        normals: Some(normals),
        instance: Some(instance),
        ..Default::default()
    }
}

/// Is `p` (on object `id`) visible in `frame` rendered from `camera`? It must project inside the
/// image onto a pixel showing the same object at the same depth (within 1 cm + 1% of depth).
pub fn visible_in(p: &Point3<f32>, id: u16, camera: &Camera, frame: &Frame) -> bool {
    visible_through(p, id, &camera.projector(), frame)
}

#[inline]
fn visible_through(p: &Point3<f32>, id: u16, projector: &Projector, frame: &Frame) -> bool {
    let Some((x, y, z)) = projector.project(p) else {
        return false;
    };
    let (u, v) = (x.floor(), y.floor());
    if u < 0.0 || v < 0.0 || u >= frame.width as f32 || v >= frame.height as f32 {
        return false;
    }
    let i = v as usize * frame.width as usize + u as usize;
    frame.instance[i] == id && (frame.depth_m[i] - z).abs() < 0.01 + 0.01 * z
}

/// Marks the points any of the (noise-free) frames sees.
pub fn seen_flags(cloud: &PointCloud, cameras: &[Camera], frames: &[Frame]) -> Vec<bool> {
    let ids = cloud.instance.as_deref().unwrap_or(&[]);
    let projectors: Vec<Projector> = cameras.iter().map(Camera::projector).collect();
    use rayon::prelude::*;
    cloud
        .positions
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let id = ids.get(i).copied().unwrap_or(0) as u16;
            projectors
                .iter()
                .zip(frames)
                .any(|(c, f)| visible_through(p, id, c, f))
        })
        .collect()
}

/// The unit normal of a triangle (zero if degenerate).
pub fn triangle_normal(c: &[Point3<f32>; 3]) -> Vector3<f32> {
    (c[1] - c[0])
        .cross(&(c[2] - c[0]))
        .try_normalize(1e-12)
        .unwrap_or_default()
}
