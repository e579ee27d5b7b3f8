//! Pinhole cameras in the OpenCV convention (x right, y down, z forward) and their poses.

use nalgebra::{Isometry3, Point2, Point3};
use serde::{Deserialize, Serialize};

use crate::error::{GeometryError, Result};

/// Pinhole intrinsics in pixels, with the image size they belong to.
///
/// The constructor rejects zero, negative or non-finite focal lengths and empty images, so every
/// `Intrinsics` value can project and back-project without producing NaN.
///
/// ```
/// use deocc_geometry::camera::Intrinsics;
/// use nalgebra::Point3;
/// let k = Intrinsics::new(500.0, 500.0, 320.0, 240.0, 640, 480).unwrap();
/// let pixel = k.project(&Point3::new(0.1, -0.2, 2.0)).unwrap();
/// let back = k.unproject(pixel.x, pixel.y, 2.0);
/// assert!((back - Point3::new(0.1, -0.2, 2.0)).norm() < 1e-6);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "IntrinsicsFields")]
pub struct Intrinsics {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: u32,
    height: u32,
}

/// The raw JSON form of [`Intrinsics`]; validated on the way in.
#[derive(Deserialize)]
struct IntrinsicsFields {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: u32,
    height: u32,
}

impl TryFrom<IntrinsicsFields> for Intrinsics {
    type Error = GeometryError;
    fn try_from(f: IntrinsicsFields) -> Result<Self> {
        Intrinsics::new(f.fx, f.fy, f.cx, f.cy, f.width, f.height)
    }
}

/// Largest image side a camera may have (pixels).
pub const MAX_IMAGE_SIDE: u32 = 16_384;

impl Intrinsics {
    /// Checked intrinsics: finite, positive focal lengths, a finite principal point, an image of
    /// 1 to [`MAX_IMAGE_SIDE`] pixels a side.
    pub fn new(fx: f32, fy: f32, cx: f32, cy: f32, width: u32, height: u32) -> Result<Self> {
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "focal lengths must be finite and positive, got fx={fx}, fy={fy}"
            )));
        }
        if !(cx.is_finite() && cy.is_finite()) {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "principal point must be finite, got cx={cx}, cy={cy}"
            )));
        }
        if width == 0 || height == 0 || width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "image size must be between 1 and {MAX_IMAGE_SIDE} pixels a side, got {width}x{height}"
            )));
        }
        Ok(Self {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        })
    }

    /// Checks that a camera given by a user is plausible: a focal length of 1/1000 to 1000
    /// image sides (fields of view of about 179.9 down to 0.06 degrees), the principal point
    /// within one image size of the image. Anything else is a unit mistake (metres for pixels)
    /// that would collapse or explode every back-projected point. (Crop cameras, whose principal
    /// point lies far outside the crop, are legitimate and not checked.)
    pub fn check_plausible(&self) -> Result<()> {
        let (fx, fy, cx, cy, width, height) =
            (self.fx, self.fy, self.cx, self.cy, self.width, self.height);
        let side = width.max(height) as f32;
        for (name, f) in [("fx", fx), ("fy", fy)] {
            if !(side * 1e-3..=side * 1e3).contains(&f) {
                return Err(GeometryError::InvalidIntrinsics(format!(
                    "{name} = {f} px is implausible for a {width}x{height} image (expected \
                     {:.3} to {:.0} px)",
                    side * 1e-3,
                    side * 1e3
                )));
            }
        }
        let (w, h) = (width as f32, height as f32);
        if !(-w..=2.0 * w).contains(&cx) || !(-h..=2.0 * h).contains(&cy) {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "principal point ({cx}, {cy}) is more than an image size outside the {width}x{height} image"
            )));
        }
        Ok(())
    }

    /// Intrinsics from a horizontal field of view, principal point at the image centre.
    pub fn from_fov(width: u32, height: u32, hfov_deg: f32) -> Result<Self> {
        if !(hfov_deg > 0.0 && hfov_deg < 180.0) {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "horizontal field of view must be in (0, 180) degrees, got {hfov_deg}"
            )));
        }
        let f = width as f32 / 2.0 / (hfov_deg.to_radians() / 2.0).tan();
        Self::new(f, f, width as f32 / 2.0, height as f32 / 2.0, width, height)
    }

    pub fn fx(&self) -> f32 {
        self.fx
    }
    pub fn fy(&self) -> f32 {
        self.fy
    }
    pub fn cx(&self) -> f32 {
        self.cx
    }
    pub fn cy(&self) -> f32 {
        self.cy
    }
    pub fn width(&self) -> u32 {
        self.width
    }
    pub fn height(&self) -> u32 {
        self.height
    }
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Continuous pixel coordinates (pixel centres at +0.5 offsets are the caller's concern:
    /// pixel (u, v) covers [u, u+1) x [v, v+1) and its centre is (u + 0.5, v + 0.5)).
    /// `None` for points at or behind the camera plane.
    pub fn project(&self, p_camera: &Point3<f32>) -> Option<Point2<f32>> {
        if p_camera.z <= 0.0 {
            return None;
        }
        Some(Point2::new(
            self.fx * p_camera.x / p_camera.z + self.cx,
            self.fy * p_camera.y / p_camera.z + self.cy,
        ))
    }

    /// The camera-frame point at depth `depth_m` (along z) seen at continuous pixel (u, v).
    pub fn unproject(&self, u: f32, v: f32, depth_m: f32) -> Point3<f32> {
        Point3::new(
            (u - self.cx) / self.fx * depth_m,
            (v - self.cy) / self.fy * depth_m,
            depth_m,
        )
    }

    /// The same camera looking at an image scaled by `factor` (e.g. 0.5 for half resolution).
    pub fn scaled(&self, factor: f32) -> Result<Self> {
        let w = (self.width as f32 * factor).round() as u32;
        let h = (self.height as f32 * factor).round() as u32;
        Self::new(
            self.fx * factor,
            self.fy * factor,
            self.cx * factor,
            self.cy * factor,
            w,
            h,
        )
    }
}

/// A camera: intrinsics and its `world_from_camera` pose. (On disk the pose is a row-major 4x4
/// matrix; see deocc-io.)
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    pub world_from_camera: Isometry3<f32>,
}

impl Camera {
    /// World point -> continuous pixel and depth along the optical axis.
    pub fn project_world(&self, p_world: &Point3<f32>) -> Option<(Point2<f32>, f32)> {
        let p_camera = self.world_from_camera.inverse_transform_point(p_world);
        self.intrinsics
            .project(&p_camera)
            .map(|px| (px, p_camera.z))
    }

    /// The world-to-pixel projection as one 3x4 matrix, for projecting many points: a
    /// [`Projector`] is several times faster per point than [`Camera::project_world`].
    pub fn projector(&self) -> Projector {
        let k = &self.intrinsics;
        let kmat = nalgebra::Matrix3::new(k.fx(), 0.0, k.cx(), 0.0, k.fy(), k.cy(), 0.0, 0.0, 1.0);
        let cam_from_world = self.world_from_camera.inverse();
        let r = cam_from_world.rotation.to_rotation_matrix();
        let m = kmat * r.matrix();
        let t = kmat * cam_from_world.translation.vector;
        Projector {
            rows: std::array::from_fn(|i| [m[(i, 0)], m[(i, 1)], m[(i, 2)], t[i]]),
        }
    }

    /// The world point seen at pixel centre (u, v) (integer pixel indices) at depth `depth_m`.
    pub fn unproject_pixel(&self, u: u32, v: u32, depth_m: f32) -> Point3<f32> {
        let p = self
            .intrinsics
            .unproject(u as f32 + 0.5, v as f32 + 0.5, depth_m);
        self.world_from_camera.transform_point(&p)
    }

    /// Camera centre in the world frame.
    pub fn center(&self) -> Point3<f32> {
        Point3::from(self.world_from_camera.translation.vector)
    }

    /// The camera that sees the square window (`x0`, `y0`, `side`; image pixels) of this one's
    /// image at `res` x `res` pixels: same pose, intrinsics scaled and shifted.
    pub fn crop(&self, x0: f32, y0: f32, side: f32, res: u32) -> Result<Camera> {
        let k = &self.intrinsics;
        let s = res as f32 / side;
        let intrinsics = Intrinsics::new(
            k.fx() * s,
            k.fy() * s,
            (k.cx() - x0) * s,
            (k.cy() - y0) * s,
            res,
            res,
        )?;
        Ok(Camera {
            intrinsics,
            world_from_camera: self.world_from_camera,
        })
    }
}

/// A `world_from_camera` pose for a camera at `eye` looking at `target`, with image "up" as close
/// as possible to `world_up` (OpenCV camera: +y is down in the image, so camera y = -up).
pub fn look_at(
    eye: &Point3<f32>,
    target: &Point3<f32>,
    world_up: &nalgebra::Vector3<f32>,
) -> Result<Isometry3<f32>> {
    let forward = target - eye;
    if forward.norm() < 1e-9 {
        return Err(GeometryError::Degenerate(
            "look_at: eye and target coincide".into(),
        ));
    }
    let z = forward.normalize();
    let x = z.cross(world_up);
    if x.norm() < 1e-6 {
        return Err(GeometryError::Degenerate(
            "look_at: viewing direction is parallel to the up vector".into(),
        ));
    }
    let x = x.normalize();
    let y = z.cross(&x);
    let rotation =
        nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(&[x, y, z]));
    Ok(Isometry3::from_parts(
        nalgebra::Translation3::from(eye.coords),
        nalgebra::UnitQuaternion::from_rotation_matrix(&rotation),
    ))
}

/// `K [R | t]` of a camera (see [`Camera::projector`]).
#[derive(Debug, Clone, Copy)]
pub struct Projector {
    rows: [[f32; 4]; 3],
}

impl Projector {
    /// Continuous pixel (x, y) and depth z of a world point; None behind the camera.
    #[inline]
    pub fn project(&self, p: &Point3<f32>) -> Option<(f32, f32, f32)> {
        let r = &self.rows;
        let dot = |i: usize| r[i][0] * p.x + r[i][1] * p.y + r[i][2] * p.z + r[i][3];
        let z = dot(2);
        (z > 0.0).then(|| (dot(0) / z, dot(1) / z, z))
    }

    /// Homogeneous image coordinates `(z x, z y, z)` of a world point, with z its camera depth
    /// (any sign). Linear in the point, so a rasteriser can clip edges against a near plane in
    /// this space before dividing.
    #[inline]
    pub fn homogeneous(&self, p: &Point3<f32>) -> [f32; 3] {
        let r = &self.rows;
        std::array::from_fn(|i| r[i][0] * p.x + r[i][1] * p.y + r[i][2] * p.z + r[i][3])
    }
}
