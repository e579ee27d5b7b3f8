//! A z-buffer rasteriser: perspective-correct depth, near-plane clipping, no back-face culling (open
//! objects such as mugs and bowls show their insides), deferred Lambertian shading of procedural
//! textures. Pixel (u, v) samples the ray through its centre (u + 0.5, v + 0.5).

use deocc_geometry::camera::Camera;
use image::RgbImage;
use nalgebra::{Point3, Vector3};

use crate::scene::{Appearance, Scene, Texture};

const NEAR_M: f32 = 0.05;

/// What a camera sees of a set of triangles: per pixel the nearest depth (0 = nothing), the
/// instance id (0 = nothing) and the index of the winning triangle in the scene's triangle list.
#[derive(Debug, Clone)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub depth_m: Vec<f32>,
    pub instance: Vec<u16>,
    pub triangle: Vec<u32>,
    /// Keep the farthest surface instead of the nearest (the back of an object rendered alone).
    pub farthest: bool,
}

impl Frame {
    pub fn new(width: u32, height: u32) -> Self {
        let n = width as usize * height as usize;
        Self {
            width,
            height,
            depth_m: vec![0.0; n],
            instance: vec![0; n],
            triangle: vec![u32::MAX; n],
            farthest: false,
        }
    }
}

/// All triangles of a scene in the world frame, flattened once so views can share them.
pub struct SceneTriangles {
    pub corners: Vec<[Point3<f32>; 3]>,
    pub normals: Vec<Vector3<f32>>,
    /// Index into `Scene::objects` of each triangle.
    pub object: Vec<u16>,
    /// Range of triangle indices of each object.
    pub object_ranges: Vec<std::ops::Range<usize>>,
}

impl SceneTriangles {
    pub fn new(scene: &Scene) -> Self {
        let mut s = SceneTriangles {
            corners: Vec::new(),
            normals: Vec::new(),
            object: Vec::new(),
            object_ranges: Vec::new(),
        };
        for (k, o) in scene.objects.iter().enumerate() {
            let start = s.corners.len();
            for i in 0..o.mesh.triangles.len() {
                let t = o.mesh.triangle(i);
                let n = (t[1] - t[0]).cross(&(t[2] - t[0]));
                let Some(n) = n.try_normalize(1e-12) else {
                    continue;
                };
                s.corners.push(t);
                s.normals.push(n);
                s.object.push(k as u16);
            }
            s.object_ranges.push(start..s.corners.len());
        }
        s
    }
}

/// Pixel rectangle `[u0, v0, u1, v1]`, inclusive.
pub type PixelBox = [u32; 4];

/// Rasterises the triangles in `range` (indices into `tris`) into `frame`. Returns a rectangle
/// holding every pixel written (None if none was), so that a caller rendering one object can
/// read and clear just that part of the frame.
pub fn rasterize(
    camera: &Camera,
    tris: &SceneTriangles,
    range: std::ops::Range<usize>,
    instance_of: &dyn Fn(usize) -> u16,
    frame: &mut Frame,
) -> Option<PixelBox> {
    let mut bounds: Option<PixelBox> = None;
    let k = &camera.intrinsics;
    let cam_from_world = camera.world_from_camera.inverse();
    let (w, h) = (frame.width as i32, frame.height as i32);
    let (fx, fy, cx, cy) = (k.fx(), k.fy(), k.cx(), k.cy());
    let mut poly: Vec<Point3<f32>> = Vec::with_capacity(5);
    for ti in range {
        let c = tris.corners[ti];
        let p = c.map(|q| cam_from_world.transform_point(&q));
        if p.iter().all(|q| q.z < NEAR_M) {
            continue;
        }
        poly.clear();
        if p.iter().all(|q| q.z >= NEAR_M) {
            poly.extend_from_slice(&p);
        } else {
            // Sutherland-Hodgman against z = NEAR.
            for i in 0..3 {
                let (a, b) = (p[i], p[(i + 1) % 3]);
                if a.z >= NEAR_M {
                    poly.push(a);
                }
                if (a.z >= NEAR_M) != (b.z >= NEAR_M) {
                    let t = (NEAR_M - a.z) / (b.z - a.z);
                    poly.push(a + (b - a) * t);
                }
            }
        }
        let screen: Vec<(f32, f32, f32)> = poly
            .iter()
            .map(|q| (fx * q.x / q.z + cx, fy * q.y / q.z + cy, 1.0 / q.z))
            .collect();
        let inst = instance_of(ti);
        for j in 1..screen.len().saturating_sub(1) {
            if let Some(b) = raster_triangle(
                [screen[0], screen[j], screen[j + 1]],
                w,
                h,
                ti as u32,
                inst,
                frame,
            ) {
                bounds = Some(match bounds {
                    None => b,
                    Some(a) => [
                        a[0].min(b[0]),
                        a[1].min(b[1]),
                        a[2].max(b[2]),
                        a[3].max(b[3]),
                    ],
                });
            }
        }
    }
    bounds
}

#[inline]
fn raster_triangle(
    s: [(f32, f32, f32); 3],
    w: i32,
    h: i32,
    tri: u32,
    inst: u16,
    frame: &mut Frame,
) -> Option<PixelBox> {
    let min_x = s.iter().map(|v| v.0).fold(f32::INFINITY, f32::min);
    let max_x = s.iter().map(|v| v.0).fold(f32::NEG_INFINITY, f32::max);
    let min_y = s.iter().map(|v| v.1).fold(f32::INFINITY, f32::min);
    let max_y = s.iter().map(|v| v.1).fold(f32::NEG_INFINITY, f32::max);
    let u0 = ((min_x - 0.5).ceil() as i32).max(0);
    let u1 = ((max_x - 0.5).floor() as i32).min(w - 1);
    let v0 = ((min_y - 0.5).ceil() as i32).max(0);
    let v1 = ((max_y - 0.5).floor() as i32).min(h - 1);
    if u0 > u1 || v0 > v1 {
        return None;
    }
    let area = (s[1].0 - s[0].0) * (s[2].1 - s[0].1) - (s[1].1 - s[0].1) * (s[2].0 - s[0].0);
    if area.abs() < 1e-12 {
        return None;
    }
    let inv_area = 1.0 / area;
    let edge = |a: (f32, f32, f32), b: (f32, f32, f32), x: f32, y: f32| {
        (b.0 - a.0) * (y - a.1) - (b.1 - a.1) * (x - a.0)
    };
    for v in v0..=v1 {
        let y = v as f32 + 0.5;
        let row = v as usize * w as usize;
        for u in u0..=u1 {
            let x = u as f32 + 0.5;
            let b0 = edge(s[1], s[2], x, y) * inv_area;
            let b1 = edge(s[2], s[0], x, y) * inv_area;
            let b2 = edge(s[0], s[1], x, y) * inv_area;
            if b0 < 0.0 || b1 < 0.0 || b2 < 0.0 {
                continue;
            }
            let inv_z = b0 * s[0].2 + b1 * s[1].2 + b2 * s[2].2;
            let z = 1.0 / inv_z;
            let idx = row + u as usize;
            let cur = frame.depth_m[idx];
            if cur == 0.0 || (z < cur) != frame.farthest {
                frame.depth_m[idx] = z;
                frame.instance[idx] = inst;
                frame.triangle[idx] = tri;
            }
        }
    }
    Some([u0 as u32, v0 as u32, u1 as u32, v1 as u32])
}

/// Renders the whole scene.
pub fn render_scene(camera: &Camera, scene: &Scene, tris: &SceneTriangles) -> Frame {
    let k = &camera.intrinsics;
    let mut frame = Frame::new(k.width(), k.height());
    let inst = |ti: usize| scene.objects[tris.object[ti] as usize].instance_id;
    rasterize(camera, tris, 0..tris.corners.len(), &inst, &mut frame);
    frame
}

/// Renders one object alone (its amodal view).
pub fn render_object(
    camera: &Camera,
    scene: &Scene,
    tris: &SceneTriangles,
    object_index: usize,
) -> Frame {
    let k = &camera.intrinsics;
    let mut frame = Frame::new(k.width(), k.height());
    let id = scene.objects[object_index].instance_id;
    rasterize(
        camera,
        tris,
        tris.object_ranges[object_index].clone(),
        &|_| id,
        &mut frame,
    );
    frame
}

/// Light direction (towards the light) shared by all scenes.
fn light() -> Vector3<f32> {
    Vector3::new(0.35, -0.45, 1.0).normalize()
}

fn hash3(x: i32, y: i32, z: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ (z as u32).wrapping_mul(0xcb1a_b31f)
        ^ seed.wrapping_mul(0x9e37_79b9);
    h ^= h >> 15;
    h = h.wrapping_mul(0x2c1b_3c6d);
    h ^= h >> 12;
    (h & 0xffff) as f32 / 65535.0
}

fn value_noise(p: Vector3<f32>, seed: u32) -> f32 {
    let f = p.map(f32::floor);
    let t = p - f;
    let s = t.map(|v| v * v * (3.0 - 2.0 * v));
    let (x, y, z) = (f.x as i32, f.y as i32, f.z as i32);
    let mut acc = 0.0;
    for dz in 0..2 {
        for dy in 0..2 {
            for dx in 0..2 {
                let wgt = (if dx == 1 { s.x } else { 1.0 - s.x })
                    * (if dy == 1 { s.y } else { 1.0 - s.y })
                    * (if dz == 1 { s.z } else { 1.0 - s.z });
                acc += wgt * hash3(x + dx, y + dy, z + dz, seed);
            }
        }
    }
    acc
}

/// Albedo of an object at a world point.
pub fn albedo(app: &Appearance, p: &Point3<f32>, seed: u32) -> [f32; 3] {
    let mix = match app.texture {
        Texture::Solid => 0.0,
        Texture::Stripes { period_m, axis } => {
            ((p[axis as usize % 3] / period_m).floor() as i64).rem_euclid(2) as f32
        }
        Texture::Checker { period_m } => {
            let q = p.coords / period_m;
            ((q.x.floor() + q.y.floor() + q.z.floor()) as i64).rem_euclid(2) as f32
        }
        Texture::Noise { period_m } => value_noise(p.coords / period_m, seed),
    };
    let (a, b) = (app.color_a, app.color_b);
    std::array::from_fn(|c| (a[c] as f32 * (1.0 - mix) + b[c] as f32 * mix) / 255.0)
}

/// Shades a frame: Lambertian with ambient light; `background` for empty pixels.
pub fn shade(
    frame: &Frame,
    camera: &Camera,
    scene: &Scene,
    tris: &SceneTriangles,
    background: [u8; 3],
) -> RgbImage {
    let mut img = RgbImage::from_pixel(frame.width, frame.height, image::Rgb(background));
    let l = light();
    let eye = camera.center();
    for (i, px) in img.pixels_mut().enumerate() {
        let ti = frame.triangle[i];
        if ti == u32::MAX {
            continue;
        }
        let (u, v) = (
            (i % frame.width as usize) as u32,
            (i / frame.width as usize) as u32,
        );
        let p = camera.unproject_pixel(u, v, frame.depth_m[i]);
        let obj = tris.object[ti as usize] as usize;
        let mut n = tris.normals[ti as usize];
        if n.dot(&(eye - p)) < 0.0 {
            n = -n;
        }
        let a = albedo(&scene.objects[obj].appearance, &p, obj as u32 + 1);
        let lum = 0.35 + 0.65 * n.dot(&l).max(0.0);
        *px = image::Rgb(a.map(|c| (c * lum * 255.0).round().clamp(0.0, 255.0) as u8));
    }
    img
}

/// Sensor realism: depth noise growing with z^2 and no depth at grazing angles (|cos| < 0.15),
/// deterministic from `seed`.
pub fn add_sensor_noise(frame: &mut Frame, camera: &Camera, tris: &SceneTriangles, seed: u64) {
    use rand::{Rng, SeedableRng};
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let eye = camera.center();
    for i in 0..frame.depth_m.len() {
        let ti = frame.triangle[i];
        if ti == u32::MAX {
            continue;
        }
        let z = frame.depth_m[i];
        let (u, v) = (
            (i % frame.width as usize) as u32,
            (i / frame.width as usize) as u32,
        );
        let p = camera.unproject_pixel(u, v, z);
        let ray = (p - eye).normalize();
        let cos = tris.normals[ti as usize].dot(&ray).abs();
        // Box-Muller for a Gaussian from the seeded generator.
        let (a, b): (f32, f32) = (r.random_range(1e-7..1.0), r.random_range(0.0..1.0));
        let g = (-2.0 * a.ln()).sqrt() * (std::f32::consts::TAU * b).cos();
        if cos < 0.15 {
            frame.depth_m[i] = 0.0;
        } else {
            frame.depth_m[i] = (z + g * 0.0012 * z * z).max(0.0);
        }
    }
}
