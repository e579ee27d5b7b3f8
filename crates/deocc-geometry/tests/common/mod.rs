//! Seeded shapes shared by the geometry tests.
#![allow(dead_code)]

use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

pub fn random_points(n: usize, seed: u64, extent: f32) -> Vec<Point3<f32>> {
    let mut r = rng(seed);
    (0..n)
        .map(|_| {
            Point3::new(
                r.random_range(-extent..extent),
                r.random_range(-extent..extent),
                r.random_range(-extent..extent),
            )
        })
        .collect()
}

/// Points with normals on an asymmetric object: a sphere (r 0.3 m) sitting on one face of a box
/// (0.8 x 0.5 x 0.2 m), seen from all sides. Asymmetric so that rigid registration is unique.
pub fn sphere_on_box(n: usize, seed: u64) -> (Vec<Point3<f32>>, Vec<Vector3<f32>>) {
    let mut r = rng(seed);
    let mut points = Vec::with_capacity(n);
    let mut normals = Vec::with_capacity(n);
    let half = Vector3::new(0.4f32, 0.25, 0.1);
    let sphere_center = Point3::new(0.15f32, 0.0, 0.1 + 0.3);
    while points.len() < n {
        if r.random_bool(0.45) {
            // Sphere surface, upper part only (the part above the box).
            let v = Vector3::new(
                r.random_range(-1.0f32..1.0),
                r.random_range(-1.0f32..1.0),
                r.random_range(-1.0f32..1.0),
            );
            let Some(v) = v.try_normalize(1e-6) else {
                continue;
            };
            if v.z < -0.9 {
                continue;
            }
            points.push(sphere_center + v * 0.3);
            normals.push(v);
        } else {
            let face = r.random_range(0..6usize);
            let axis = face / 2;
            let sign = if face % 2 == 0 { 1.0 } else { -1.0 };
            let mut p = Vector3::new(
                r.random_range(-half.x..half.x),
                r.random_range(-half.y..half.y),
                r.random_range(-half.z..half.z),
            );
            p[axis] = sign * half[axis];
            let mut n = Vector3::zeros();
            n[axis] = sign;
            points.push(Point3::from(p));
            normals.push(n);
        }
    }
    (points, normals)
}
