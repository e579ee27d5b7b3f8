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

fn union_box(a: Option<PixelBox>, b: PixelBox) -> PixelBox {
    match a {
        None => b,
        Some(a) => [
            a[0].min(b[0]),
            a[1].min(b[1]),
            a[2].max(b[2]),
            a[3].max(b[3]),
        ],
    }
}

/// floor / ceil to i32 without libm calls (the baseline x86-64 target has no rounding
/// instruction, and these run once per triangle row). Saturating, NaN -> 0.
#[inline]
pub(crate) fn floor_i32(x: f32) -> i32 {
    let i = x as i32;
    if (i as f32) > x {
        i - 1
    } else {
        i
    }
}
#[inline]
fn ceil_i32(x: f32) -> i32 {
    let i = x as i32;
    if (i as f32) < x {
        i + 1
    } else {
        i
    }
}

/// A screen-space vertex: pixel x, pixel y, 1 / depth.
type ScreenVertex = (f32, f32, f32);

/// Projects and near-clips the triangles in `range`, calling `f(triangle index, screen vertices)`
/// for each screen triangle (a triangle cut by the near plane gives one or two). Triangles whose
/// screen box misses the image are dropped before `f`.
fn for_each_screen_triangle(
    camera: &Camera,
    tris: &SceneTriangles,
    range: std::ops::Range<usize>,
    mut f: impl FnMut(usize, [ScreenVertex; 3]),
) {
    let projector = camera.projector();
    let (w, h) = (
        camera.intrinsics.width() as f32,
        camera.intrinsics.height() as f32,
    );
    for ti in range {
        let c = &tris.corners[ti];
        let p = [
            projector.homogeneous(&c[0]),
            projector.homogeneous(&c[1]),
            projector.homogeneous(&c[2]),
        ];
        let in_front = p.iter().filter(|q| q[2] >= NEAR_M).count();
        if in_front == 0 {
            continue;
        }
        // Sutherland-Hodgman against z = NEAR in homogeneous image space (linear in the world
        // point, so interpolating there is exact): at most 4 vertices.
        let mut poly = [[0f32; 3]; 4];
        let mut n = 0;
        if in_front == 3 {
            poly[..3].copy_from_slice(&p);
            n = 3;
        } else {
            for i in 0..3 {
                let (a, b) = (p[i], p[(i + 1) % 3]);
                if a[2] >= NEAR_M {
                    poly[n] = a;
                    n += 1;
                }
                if (a[2] >= NEAR_M) != (b[2] >= NEAR_M) {
                    let t = (NEAR_M - a[2]) / (b[2] - a[2]);
                    poly[n] = std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t);
                    n += 1;
                }
            }
        }
        let mut screen = [(0f32, 0f32, 0f32); 4];
        let (mut lo_x, mut hi_x, mut lo_y, mut hi_y) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        for (sv, q) in screen.iter_mut().zip(&poly[..n]) {
            let inv_z = 1.0 / q[2];
            *sv = (q[0] * inv_z, q[1] * inv_z, inv_z);
            lo_x = lo_x.min(sv.0);
            hi_x = hi_x.max(sv.0);
            lo_y = lo_y.min(sv.1);
            hi_y = hi_y.max(sv.1);
        }
        // Pixel centres are at +0.5: a triangle entirely left of 0.5 or right of w - 0.5 covers
        // none of them.
        if hi_x < 0.5 || hi_y < 0.5 || lo_x > w - 0.5 || lo_y > h - 0.5 {
            continue;
        }
        for j in 1..n.saturating_sub(1) {
            f(ti, [screen[0], screen[j], screen[j + 1]]);
        }
    }
}

/// Calls `span(v, u_first, u_last, y)` for every image row `v` the triangle covers, with the run
/// of pixel centres inside it (edges included); returns the box of the spans, if any.
#[inline]
fn for_each_span(
    s: [ScreenVertex; 3],
    w: i32,
    h: i32,
    mut span: impl FnMut(i32, i32, i32, f32),
) -> Option<PixelBox> {
    let min_y = s[0].1.min(s[1].1).min(s[2].1);
    let max_y = s[0].1.max(s[1].1).max(s[2].1);
    let min_x = s[0].0.min(s[1].0).min(s[2].0);
    let max_x = s[0].0.max(s[1].0).max(s[2].0);
    let u0 = ceil_i32(min_x - 0.5).max(0);
    let u1 = floor_i32(max_x - 0.5).min(w - 1);
    let v0 = ceil_i32(min_y - 0.5).max(0);
    let v1 = floor_i32(max_y - 0.5).min(h - 1);
    if u0 > u1 || v0 > v1 {
        return None;
    }
    let area = (s[1].0 - s[0].0) * (s[2].1 - s[0].1) - (s[1].1 - s[0].1) * (s[2].0 - s[0].0);
    if area.abs() < 1e-12 {
        return None;
    }
    // Barycentric weight of vertex i as a plane a x + b y + c (the edge function of the opposite
    // edge over the area): a pixel is inside when all three are >= 0.
    let inv_area = 1.0 / area;
    let edge = |a: ScreenVertex, b: ScreenVertex| {
        let (ea, eb) = (-(b.1 - a.1) * inv_area, (b.0 - a.0) * inv_area);
        (ea, eb, -(ea * a.0 + eb * a.1))
    };
    let e = [edge(s[1], s[2]), edge(s[2], s[0]), edge(s[0], s[1])];
    let mut bounds: Option<PixelBox> = None;
    for v in v0..=v1 {
        let y = v as f32 + 0.5;
        // Each edge bounds x on one side: solve a x + (b y + c) >= 0 for x.
        let (mut lo, mut hi) = (u0 as f32 + 0.5, u1 as f32 + 0.5);
        let mut empty = false;
        for &(a, b, c) in &e {
            let rest = b * y + c;
            if a > 0.0 {
                lo = lo.max(-rest / a);
            } else if a < 0.0 {
                hi = hi.min(-rest / a);
            } else if rest < 0.0 {
                empty = true;
            }
        }
        if empty || lo > hi {
            continue;
        }
        let ua = ceil_i32(lo - 0.5).max(u0);
        let ub = floor_i32(hi - 0.5).min(u1);
        if ua > ub {
            continue;
        }
        span(v, ua, ub, y);
        bounds = Some(union_box(
            bounds,
            [ua as u32, v as u32, ub as u32, v as u32],
        ));
    }
    bounds
}

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
    let (w, h) = (frame.width as i32, frame.height as i32);
    let farthest = frame.farthest;
    let Frame {
        depth_m,
        instance,
        triangle,
        ..
    } = frame;
    for_each_screen_triangle(camera, tris, range, |ti, s| {
        let inst = instance_of(ti);
        // 1/z is affine in screen space: the same plane form as the barycentric weights.
        let area = (s[1].0 - s[0].0) * (s[2].1 - s[0].1) - (s[1].1 - s[0].1) * (s[2].0 - s[0].0);
        if area.abs() < 1e-12 {
            return;
        }
        let inv_area = 1.0 / area;
        let (dx1, dy1, dz1) = (s[1].0 - s[0].0, s[1].1 - s[0].1, s[1].2 - s[0].2);
        let (dx2, dy2, dz2) = (s[2].0 - s[0].0, s[2].1 - s[0].1, s[2].2 - s[0].2);
        let za = (dz1 * dy2 - dz2 * dy1) * inv_area;
        let zb = (dz2 * dx1 - dz1 * dx2) * inv_area;
        let zc = s[0].2 - za * s[0].0 - zb * s[0].1;
        let drawn = for_each_span(s, w, h, |v, ua, ub, y| {
            let row = v as usize * w as usize;
            let base = zb * y + zc;
            for u in ua..=ub {
                let inv_z = za * (u as f32 + 0.5) + base;
                let idx = row + u as usize;
                let cur = depth_m[idx];
                // z < cur  <=>  cur / z > 1: the depth test without a division; only the pixels
                // that win (not every covered one, overdraw included) pay for 1 / inv_z.
                if cur == 0.0 || (cur * inv_z > 1.0) != farthest {
                    depth_m[idx] = 1.0 / inv_z;
                    instance[idx] = inst;
                    triangle[idx] = ti as u32;
                }
            }
        });
        if let Some(b) = drawn {
            bounds = Some(union_box(bounds, b));
        }
    });
    bounds
}

/// Marks in `mask` (row-major, the camera's image size) every pixel the triangles in `range`
/// cover, without depth: an object's amodal mask needs only its coverage. Returns the box of the
/// pixels marked, if any.
pub fn rasterize_coverage(
    camera: &Camera,
    tris: &SceneTriangles,
    range: std::ops::Range<usize>,
    mask: &mut [bool],
) -> Option<PixelBox> {
    let (w, h) = (
        camera.intrinsics.width() as i32,
        camera.intrinsics.height() as i32,
    );
    assert_eq!(mask.len(), (w * h) as usize, "mask size != image size");
    let mut bounds: Option<PixelBox> = None;
    for_each_screen_triangle(camera, tris, range, |_, s| {
        let drawn = for_each_span(s, w, h, |v, ua, ub, _| {
            let row = v as usize * w as usize;
            mask[row + ua as usize..=row + ub as usize].fill(true);
        });
        if let Some(b) = drawn {
            bounds = Some(union_box(bounds, b));
        }
    });
    bounds
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
pub fn light() -> Vector3<f32> {
    Vector3::new(0.35, -0.45, 1.0).normalize()
}

/// Lattice hash of a corner from its per-axis parts (`x * A ^ y * B ^ z * C ^ seed * D`, split so
/// that the eight corners of a cell share the products), in [0, 1].
#[inline]
fn hash_mix(h: u32) -> f32 {
    let mut h = h;
    h ^= h >> 15;
    h = h.wrapping_mul(0x2c1b_3c6d);
    h ^= h >> 12;
    (h & 0xffff) as f32 * (1.0 / 65535.0)
}

/// Trilinear value noise with smoothstep weights.
#[inline]
fn value_noise(p: Vector3<f32>, seed: u32) -> f32 {
    let (x, y, z) = (floor_i32(p.x), floor_i32(p.y), floor_i32(p.z));
    let smooth = |v: f32| v * v * (3.0 - 2.0 * v);
    let (sx, sy, sz) = (
        smooth(p.x - x as f32),
        smooth(p.y - y as f32),
        smooth(p.z - z as f32),
    );
    let hx = [x, x + 1].map(|v| (v as u32).wrapping_mul(0x8da6_b343));
    let hy = [y, y + 1].map(|v| (v as u32).wrapping_mul(0xd816_3841));
    let hs = seed.wrapping_mul(0x9e37_79b9);
    let hz = [z, z + 1].map(|v| (v as u32).wrapping_mul(0xcb1a_b31f) ^ hs);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let plane = |hz: u32| {
        let row = |hy: u32| lerp(hash_mix(hx[0] ^ hy ^ hz), hash_mix(hx[1] ^ hy ^ hz), sx);
        lerp(row(hy[0]), row(hy[1]), sy)
    };
    lerp(plane(hz[0]), plane(hz[1]), sz)
}

/// Albedo of an object at a world point.
#[inline]
pub fn albedo(app: &Appearance, p: &Point3<f32>, seed: u32) -> [f32; 3] {
    let mix = match app.texture {
        Texture::Solid => 0.0,
        Texture::Stripes { period_m, axis } => {
            floor_i32(p[axis as usize % 3] / period_m).rem_euclid(2) as f32
        }
        Texture::Checker { period_m } => {
            let q = p.coords / period_m;
            (floor_i32(q.x) + floor_i32(q.y) + floor_i32(q.z)).rem_euclid(2) as f32
        }
        Texture::Noise { period_m } => value_noise(p.coords / period_m, seed),
    };
    let (a, b) = (app.color_a, app.color_b);
    std::array::from_fn(|c| (a[c] as f32 * (1.0 - mix) + b[c] as f32 * mix) / 255.0)
}

/// Shades a frame: Lambertian with ambient light; `background` for empty pixels.
///
/// The hot loop of the synthetic benchmark (every pixel of every view): it runs row by row with
/// the per-column ray factors computed once, and reads appearances from a compact table instead
/// of the scene's objects. Every value is computed with the same operations in the same order as
/// the plain per-pixel formula, so the output is bit-identical to it.
pub fn shade(
    frame: &Frame,
    camera: &Camera,
    scene: &Scene,
    tris: &SceneTriangles,
    background: [u8; 3],
) -> RgbImage {
    let (w, h) = (frame.width as usize, frame.height as usize);
    let mut buf: Vec<u8> = Vec::with_capacity(w * h * 3);
    let l = light();
    let eye = camera.center();
    // unproject_pixel per pixel, with the rotation as a matrix (a quaternion rotation per pixel
    // cost more than the shading).
    let rot = camera.world_from_camera.rotation.to_rotation_matrix();
    let k = &camera.intrinsics;
    let (fx, fy, cx, cy) = (k.fx(), k.fy(), k.cx(), k.cy());
    let column: Vec<f32> = (0..w).map(|u| (u as f32 + 0.5 - cx) / fx).collect();
    let appearances: Vec<Appearance> = scene.objects.iter().map(|o| o.appearance).collect();
    for v in 0..h {
        let row_factor = (v as f32 + 0.5 - cy) / fy;
        let row = v * w;
        for (u, &col_factor) in column.iter().enumerate() {
            let i = row + u;
            let ti = frame.triangle[i];
            if ti == u32::MAX {
                buf.extend_from_slice(&background);
                continue;
            }
            let z = frame.depth_m[i];
            let p = eye + rot * Vector3::new(col_factor * z, row_factor * z, z);
            let obj = tris.object[ti as usize] as usize;
            let mut n = tris.normals[ti as usize];
            if n.dot(&(eye - p)) < 0.0 {
                n = -n;
            }
            let a = albedo(&appearances[obj], &p, obj as u32 + 1);
            let lum = 0.35 + 0.65 * n.dot(&l).max(0.0);
            // Round half up on a non-negative value: + 0.5 and truncate (no libm call).
            buf.extend_from_slice(&a.map(|c| ((c * lum * 255.0).clamp(0.0, 255.0) + 0.5) as u8));
        }
    }
    RgbImage::from_raw(frame.width, frame.height, buf).expect("w * h * 3 bytes")
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
