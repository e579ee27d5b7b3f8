//! Depth sensor models: what a real RGB-D camera measures of a rendered scene.
//!
//! A [`Sensor`] is a list of effects, each its own function of the rendered geometry (the frame's
//! depth, which triangle each pixel sees, the camera), applied in the order a sensor produces
//! them:
//!
//! 1. [`emitter_shadow`]: pixels the projector (structured light) or the second camera (active
//!    stereo) cannot see get no depth. Computed from the scene: the scene is rendered from the
//!    emitter and a pixel whose surface point lies behind the emitter's nearest surface is in
//!    shadow. This is the band without depth beside every near edge.
//! 2. [`range_limits`]: nothing nearer than the minimum or farther than the maximum range.
//! 3. [`grazing_dropout`]: no depth where the surface is seen at a grazing angle (certain beyond
//!    `drop_deg`, a linear ramp of probability from `ramp_deg`).
//! 4. [`lateral_edge_noise`]: depth edges jitter sideways (each pixel reads its depth from a
//!    neighbour `N(0, sigma_px)` pixels away, rounded).
//! 5. [`flying_pixels`]: time of flight mixes the foreground and background returns along every
//!    depth edge: a pixel there measures a depth between the two.
//! 6. [`axial_noise`]: Gaussian noise along the ray whose sigma grows with depth and incidence.
//! 7. [`quantise_disparity`]: triangulating sensors measure disparity in sub-pixel steps, so depth
//!    comes in steps that grow with z^2 (1/8 px over 7.5 cm at 580 px: about 1 cm at 2 m).
//! 8. [`speckle_holes`]: small holes where the pattern or the correlation fails, and single
//!    pixels dropped at random.
//!
//! The named sensors ([`SensorKind`]) take their parameters from the literature and from real
//! frames (the sources beside each preset); [`Sensor::randomised`] draws each parameter within a
//! documented range around them, for training on sensors the project has never seen.
//! [`colour_realism`] gives the colour image matching realism (noise, exposure, white balance,
//! blur).

use deocc_geometry::camera::{Camera, Intrinsics};
use image::RgbImage;
use nalgebra::{Isometry3, Translation3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::render::{rasterize, Frame, SceneTriangles};

pub use crate::sensor_kind::SensorKind;

/// Axial noise: `sigma(z, theta) = a + b (z - z0)^2 + c z + d / sqrt(z) * theta^2 / (pi/2 - theta)^2`
/// metres, theta the angle of incidence (Nguyen, Izadi and Lovell 2012 for structured light).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AxialNoise {
    pub a: f32,
    pub b: f32,
    pub z0: f32,
    pub c: f32,
    pub d: f32,
}

impl AxialNoise {
    pub fn sigma(&self, z: f32, theta: f32) -> f32 {
        let theta = theta.clamp(0.0, 1.5);
        let grazing = theta * theta / ((std::f32::consts::FRAC_PI_2 - theta).powi(2));
        self.a + self.b * (z - self.z0).powi(2) + self.c * z + self.d / z.max(0.05).sqrt() * grazing
    }
}

/// Every parameter of a sensor (zero or `None` turns an effect off).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sensor {
    pub kind: SensorKind,
    /// Emitter (projector or second camera) offset along the camera's +x, metres; 0 = none.
    pub emitter_baseline_m: f32,
    pub min_range_m: f32,
    pub max_range_m: f32,
    /// Incidence (degrees from the surface normal) from which depth starts to drop out, and
    /// beyond which none is measured.
    pub ramp_deg: f32,
    pub drop_deg: f32,
    pub lateral_sigma_px: f32,
    /// Share of the pixels along a depth edge that measure a mix of both sides.
    pub flying_fraction: f32,
    pub axial: AxialNoise,
    /// Disparity: `fx * baseline / z` pixels, measured in steps of `1 / disparity_steps_per_px`
    /// with Gaussian sub-pixel noise `disparity_sigma_px`; baseline 0 = not a triangulating
    /// sensor.
    pub disparity_baseline_m: f32,
    pub disparity_steps_per_px: f32,
    pub disparity_sigma_px: f32,
    /// Speckle holes per pixel and their radius range, pixels.
    pub speckle_density: f32,
    pub speckle_radius_px: [f32; 2],
    /// Single pixels dropped at random.
    pub dropout: f32,
}

impl Sensor {
    /// The clean renderer.
    pub fn clean() -> Self {
        Self {
            kind: SensorKind::Clean,
            emitter_baseline_m: 0.0,
            min_range_m: 0.0,
            max_range_m: f32::INFINITY,
            ramp_deg: 90.0,
            drop_deg: 90.0,
            lateral_sigma_px: 0.0,
            flying_fraction: 0.0,
            axial: AxialNoise {
                a: 0.0,
                b: 0.0,
                z0: 0.0,
                c: 0.0,
                d: 0.0,
            },
            disparity_baseline_m: 0.0,
            disparity_steps_per_px: 0.0,
            disparity_sigma_px: 0.0,
            speckle_density: 0.0,
            speckle_radius_px: [0.0, 0.0],
            dropout: 0.0,
        }
    }

    /// Kinect v1-class structured light. Axial noise: Nguyen, Izadi and Lovell (2012),
    /// `0.0012 + 0.0019 (z - 0.4)^2` below 60 degrees with their incidence term; lateral 0.8 px
    /// (ibid.); disparity in 1/8-pixel steps over the 7.5 cm projector baseline (Khoshelham and
    /// Elberink 2012); range 0.5-4.5 m; holes and drop-outs so that a frame at 2.3 m lacks about
    /// a tenth of its pixels, as the Kinect-class frame in Debian's mrpt-common does (11%).
    pub fn structured_light() -> Self {
        Self {
            kind: SensorKind::StructuredLight,
            emitter_baseline_m: 0.075,
            min_range_m: 0.5,
            max_range_m: 4.5,
            ramp_deg: 65.0,
            drop_deg: 80.0,
            lateral_sigma_px: 0.8,
            flying_fraction: 0.0,
            axial: AxialNoise {
                a: 0.0012,
                b: 0.0019,
                z0: 0.4,
                c: 0.0,
                d: 0.0001,
            },
            disparity_baseline_m: 0.075,
            disparity_steps_per_px: 8.0,
            disparity_sigma_px: 0.0,
            speckle_density: 4e-4,
            speckle_radius_px: [1.0, 3.0],
            dropout: 0.005,
        }
    }

    /// RealSense D4xx-class active stereo: sub-pixel disparity noise of 0.08 px over a 5 cm
    /// baseline (Intel's D400 tuning guide: RMS error `z^2 * 0.08 / (f * b)`), disparity
    /// reported in 1/32-pixel steps; the second camera's shadow is the invalid band beside near
    /// edges; range 0.2-6 m; fewer holes than structured light.
    pub fn active_stereo() -> Self {
        Self {
            kind: SensorKind::ActiveStereo,
            emitter_baseline_m: 0.05,
            min_range_m: 0.2,
            max_range_m: 6.0,
            ramp_deg: 70.0,
            drop_deg: 82.0,
            lateral_sigma_px: 0.5,
            flying_fraction: 0.0,
            axial: AxialNoise {
                a: 0.0005,
                b: 0.0,
                z0: 0.0,
                c: 0.0,
                d: 0.0,
            },
            disparity_baseline_m: 0.05,
            disparity_steps_per_px: 32.0,
            disparity_sigma_px: 0.08,
            speckle_density: 2e-4,
            speckle_radius_px: [1.0, 2.5],
            dropout: 0.003,
        }
    }

    /// Azure Kinect-class time of flight (NFOV): low axial noise (about 1.1 mm at 0.9 m, as the
    /// frame in PyPI's arcor2-kinect-azure shows), flying pixels along every depth edge, no
    /// triangulation (no disparity steps, the illuminator beside the lens casts no shadow worth
    /// modelling), range 0.25-5.5 m.
    pub fn time_of_flight() -> Self {
        Self {
            kind: SensorKind::TimeOfFlight,
            emitter_baseline_m: 0.0,
            min_range_m: 0.25,
            max_range_m: 5.5,
            ramp_deg: 70.0,
            drop_deg: 84.0,
            lateral_sigma_px: 0.3,
            flying_fraction: 0.7,
            axial: AxialNoise {
                a: 0.0005,
                b: 0.0,
                z0: 0.0,
                c: 0.0007,
                d: 0.00005,
            },
            disparity_baseline_m: 0.0,
            disparity_steps_per_px: 0.0,
            disparity_sigma_px: 0.0,
            speckle_density: 5e-5,
            speckle_radius_px: [1.0, 2.0],
            dropout: 0.002,
        }
    }

    /// The project's first model (see [`SensorKind::Gaussian`]).
    pub fn gaussian() -> Self {
        Self {
            kind: SensorKind::Gaussian,
            // acos(0.15): the old model's grazing cut, without a ramp.
            ramp_deg: 81.37,
            drop_deg: 81.37,
            axial: AxialNoise {
                a: 0.0,
                b: 0.0012,
                z0: 0.0,
                c: 0.0,
                d: 0.0,
            },
            ..Self::clean()
        }
    }

    /// The preset of a named kind; `Random` draws one with `seed` ([`Sensor::randomised`]).
    pub fn of(kind: SensorKind, seed: u64) -> Self {
        match kind {
            SensorKind::Clean => Self::clean(),
            SensorKind::Gaussian => Self::gaussian(),
            SensorKind::StructuredLight => Self::structured_light(),
            SensorKind::ActiveStereo => Self::active_stereo(),
            SensorKind::TimeOfFlight => Self::time_of_flight(),
            SensorKind::Random => Self::randomised(&mut ChaCha8Rng::seed_from_u64(seed)),
        }
    }

    /// One of the three real sensors with its parameters drawn within these ranges around the
    /// preset: noise terms x [0.6, 1.6], lateral sigma x [0.5, 1.5], emitter baseline x [0.7,
    /// 1.3], drop-out angles -8..+4 degrees, speckle density x [0.3, 3], random drop-out x
    /// [0.3, 3], flying pixels' share [0.3, 1], disparity steps 4, 8, 16 or 32 per pixel
    /// (triangulating sensors), disparity noise x [0.5, 2].
    pub fn randomised(rng: &mut impl Rng) -> Self {
        let mut s = match rng.random_range(0..3) {
            0 => Self::structured_light(),
            1 => Self::active_stereo(),
            _ => Self::time_of_flight(),
        };
        let k = rng.random_range(0.6..1.6f32);
        s.axial.a *= k;
        s.axial.b *= k;
        s.axial.c *= k;
        s.axial.d *= k;
        s.lateral_sigma_px *= rng.random_range(0.5..1.5f32);
        s.emitter_baseline_m *= rng.random_range(0.7..1.3f32);
        let shift = rng.random_range(-8.0..4.0f32);
        s.ramp_deg += shift;
        s.drop_deg = (s.drop_deg + shift).min(89.0);
        s.speckle_density *= rng.random_range(0.3..3.0f32);
        s.dropout *= rng.random_range(0.3..3.0f32);
        if s.flying_fraction > 0.0 {
            s.flying_fraction = rng.random_range(0.3..1.0f32);
        }
        if s.disparity_baseline_m > 0.0 {
            s.disparity_baseline_m = s.emitter_baseline_m;
            s.disparity_steps_per_px = [4.0, 8.0, 16.0, 32.0][rng.random_range(0..4)];
            s.disparity_sigma_px *= rng.random_range(0.5..2.0f32);
        }
        s
    }

    /// Measures `frame` (rendered from `camera` of `tris`) as this sensor would, in place: its
    /// depth changes; instances and triangles stay the renderer's (the truth of what each pixel
    /// shows).
    pub fn measure(&self, frame: &mut Frame, camera: &Camera, tris: &SceneTriangles, seed: u64) {
        self.measure_at(frame, camera, tris, seed, camera.intrinsics.fx());
    }

    /// [`Sensor::measure`] for a frame rendered through a zoomed camera (a training pair's crop)
    /// of an image whose focal length is `image_fx`: the effects measured in pixels (edge jitter,
    /// hole sizes and density, disparity steps) stay in the image's pixels.
    pub fn measure_at(
        &self,
        frame: &mut Frame,
        camera: &Camera,
        tris: &SceneTriangles,
        seed: u64,
        image_fx: f32,
    ) {
        if self.kind == SensorKind::Clean {
            return;
        }
        if self.kind == SensorKind::Gaussian {
            // The old model exactly (its random stream too): older figures reproduce.
            crate::render::add_sensor_noise(frame, camera, tris, seed);
            return;
        }
        // Frame pixels per image pixel.
        let zoom = (camera.intrinsics.fx() / image_fx).max(1e-3);
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5e25_0a11);
        if self.emitter_baseline_m > 0.0 {
            emitter_shadow(frame, camera, tris, self.emitter_baseline_m);
        }
        range_limits(frame, self.min_range_m, self.max_range_m);
        let incidence = incidence_deg(frame, camera, tris);
        grazing_dropout(frame, &incidence, self.ramp_deg, self.drop_deg, &mut rng);
        if self.lateral_sigma_px > 0.0 {
            lateral_edge_noise(frame, self.lateral_sigma_px * zoom, &mut rng);
        }
        if self.flying_fraction > 0.0 {
            flying_pixels(frame, self.flying_fraction, &mut rng);
        }
        axial_noise(frame, &incidence, &self.axial, &mut rng);
        if self.disparity_baseline_m > 0.0 && self.disparity_steps_per_px > 0.0 {
            quantise_disparity(
                frame,
                image_fx,
                self.disparity_baseline_m,
                self.disparity_steps_per_px,
                self.disparity_sigma_px,
                &mut rng,
            );
        }
        speckle_holes(
            frame,
            self.speckle_density / (zoom * zoom),
            [
                self.speckle_radius_px[0] * zoom,
                self.speckle_radius_px[1] * zoom,
            ],
            self.dropout,
            &mut rng,
        );
    }
}

/// Measures one render of a scene with the sensor `kind`: the sensor's parameters are drawn
/// from `scene_seed` (one camera per scene under [`SensorKind::Random`]), its noise from
/// `render_seed`. `image_fx`: see [`Sensor::measure_at`].
pub fn apply(
    kind: SensorKind,
    frame: &mut Frame,
    camera: &Camera,
    tris: &SceneTriangles,
    scene_seed: u64,
    render_seed: u64,
    image_fx: f32,
) {
    Sensor::of(kind, scene_seed).measure_at(frame, camera, tris, render_seed, image_fx);
}

/// The colour camera's realism for a scene under `kind`: drawn from `scene_seed` under
/// [`SensorKind::Random`], none otherwise (the named sensors keep the renderer's colour, so
/// figures under them compare depth effects alone).
pub fn scene_colour(kind: SensorKind, scene_seed: u64) -> Option<ColourRealism> {
    (kind == SensorKind::Random)
        .then(|| ColourRealism::randomised(&mut ChaCha8Rng::seed_from_u64(scene_seed ^ 0xc0c0)))
}

/// A standard normal draw (Box-Muller on the seeded generator: portable across platforms).
fn gauss(rng: &mut impl Rng) -> f32 {
    let (a, b): (f32, f32) = (rng.random_range(1e-7..1.0), rng.random_range(0.0..1.0));
    (-2.0 * a.ln()).sqrt() * (std::f32::consts::TAU * b).cos()
}

/// Per pixel, the angle between the viewing ray and the surface normal, degrees (NaN where
/// nothing was rendered).
pub fn incidence_deg(frame: &Frame, camera: &Camera, tris: &SceneTriangles) -> Vec<f32> {
    let eye = camera.center();
    let w = frame.width as usize;
    (0..frame.depth_m.len())
        .map(|i| {
            let ti = frame.triangle[i];
            let z = frame.depth_m[i];
            if ti == u32::MAX || z <= 0.0 {
                return f32::NAN;
            }
            let p = camera.unproject_pixel((i % w) as u32, (i / w) as u32, z);
            let ray = (p - eye).normalize();
            let cos = tris.normals[ti as usize].dot(&ray).abs().min(1.0);
            cos.acos().to_degrees()
        })
        .collect()
}

/// The emitter's view: the camera moved `baseline_m` along its own +x, with a margin of an
/// eighth of the image on every side (its field of view is wider than the camera's).
pub fn emitter_camera(camera: &Camera, baseline_m: f32) -> Camera {
    let k = &camera.intrinsics;
    let (mw, mh) = (k.width() / 8, k.height() / 8);
    let intrinsics = Intrinsics::new(
        k.fx(),
        k.fy(),
        k.cx() + mw as f32,
        k.cy() + mh as f32,
        k.width() + 2 * mw,
        k.height() + 2 * mh,
    )
    .unwrap_or(*k);
    Camera {
        intrinsics,
        world_from_camera: camera.world_from_camera
            * Isometry3::from_parts(
                Translation3::new(baseline_m, 0.0, 0.0),
                nalgebra::UnitQuaternion::identity(),
            ),
    }
}

/// Removes the depth of every pixel the emitter (at `baseline_m` along the camera's +x) cannot
/// see: its surface point is farther from the emitter than the emitter's nearest surface along
/// that ray (by more than 1 cm + 1% of the distance, the rasteriser's own tolerance), or falls
/// outside the emitter's view. Returns the pixels removed.
pub fn emitter_shadow(
    frame: &mut Frame,
    camera: &Camera,
    tris: &SceneTriangles,
    baseline_m: f32,
) -> usize {
    let emitter = emitter_camera(camera, baseline_m);
    let mut seen = Frame::new(emitter.intrinsics.width(), emitter.intrinsics.height());
    rasterize(&emitter, tris, 0..tris.corners.len(), &|_| 1, &mut seen);
    let proj = emitter.projector();
    let (ew, eh) = (seen.width as i64, seen.height as i64);
    let w = frame.width as usize;
    let mut removed = 0;
    for i in 0..frame.depth_m.len() {
        let z = frame.depth_m[i];
        if z <= 0.0 {
            continue;
        }
        let p = camera.unproject_pixel((i % w) as u32, (i / w) as u32, z);
        let shadowed = match proj.project(&p) {
            Some((u, v, ze)) => {
                let (ui, vi) = (u.floor() as i64, v.floor() as i64);
                if ui < 0 || vi < 0 || ui >= ew || vi >= eh {
                    true
                } else {
                    // The nearest surface the emitter lights along that ray.
                    let lit = seen.depth_m[(vi * ew + ui) as usize];
                    lit > 0.0 && ze > lit + 0.01 + 0.01 * ze
                }
            }
            None => true,
        };
        if shadowed {
            frame.depth_m[i] = 0.0;
            removed += 1;
        }
    }
    removed
}

/// No depth nearer than `min_m` or farther than `max_m`.
pub fn range_limits(frame: &mut Frame, min_m: f32, max_m: f32) {
    for d in &mut frame.depth_m {
        if *d > 0.0 && (*d < min_m || *d > max_m) {
            *d = 0.0;
        }
    }
}

/// No depth beyond `drop_deg` of incidence; between `ramp_deg` and `drop_deg` a pixel drops with
/// a probability rising linearly from 0 to 1.
pub fn grazing_dropout(
    frame: &mut Frame,
    incidence_deg: &[f32],
    ramp_deg: f32,
    drop_deg: f32,
    rng: &mut impl Rng,
) {
    for (d, &a) in frame.depth_m.iter_mut().zip(incidence_deg) {
        if *d <= 0.0 || !a.is_finite() {
            continue;
        }
        let p = if a >= drop_deg {
            1.0
        } else if a > ramp_deg {
            (a - ramp_deg) / (drop_deg - ramp_deg).max(1e-3)
        } else {
            0.0
        };
        if p > 0.0 && rng.random_range(0.0..1.0f32) < p {
            *d = 0.0;
        }
    }
}

/// Depth edges jitter sideways: each pixel reads the depth of the pixel `round(N(0, sigma_px))`
/// away in x and in y. Inside a smooth surface this changes almost nothing; at an edge it moves
/// the boundary by a pixel or two, differently along it.
pub fn lateral_edge_noise(frame: &mut Frame, sigma_px: f32, rng: &mut impl Rng) {
    let (w, h) = (frame.width as i64, frame.height as i64);
    let src = frame.depth_m.clone();
    for v in 0..h {
        for u in 0..w {
            let du = (gauss(rng) * sigma_px).round() as i64;
            let dv = (gauss(rng) * sigma_px).round() as i64;
            if du == 0 && dv == 0 {
                continue;
            }
            let (x, y) = ((u + du).clamp(0, w - 1), (v + dv).clamp(0, h - 1));
            let here = src[(v * w + u) as usize];
            let there = src[(y * w + x) as usize];
            // Only across an edge (a jump of more than 2% of the depth, or a hole's edge):
            // within a surface the neighbour's depth is the same surface's.
            if (here - there).abs() > 0.02 * here.max(there) {
                frame.depth_m[(v * w + u) as usize] = there;
            }
        }
    }
}

/// Time of flight's mixed returns: a share `fraction` of the pixels beside a depth edge of more
/// than 3 cm measure `t z_near + (1 - t) z_far`, `t` uniform: points float between the surfaces.
pub fn flying_pixels(frame: &mut Frame, fraction: f32, rng: &mut impl Rng) {
    let (w, h) = (frame.width as usize, frame.height as usize);
    let src = frame.depth_m.clone();
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            let z = src[i];
            if z <= 0.0 {
                continue;
            }
            // The neighbour across the largest jump, if one is over 3 cm.
            let (mut other, mut gap) = (0.0f32, 0.03f32);
            for (du, dv) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let (x, y) = (u as i64 + du, v as i64 + dv);
                if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
                    continue;
                }
                let n = src[y as usize * w + x as usize];
                if n > 0.0 && (n - z).abs() > gap {
                    (other, gap) = (n, (n - z).abs());
                }
            }
            if other > 0.0 && rng.random_range(0.0..1.0f32) < fraction {
                let t = rng.random_range(0.0..1.0f32);
                frame.depth_m[i] = t * z + (1.0 - t) * other;
            }
        }
    }
}

/// Gaussian noise along the ray with `model`'s sigma at each pixel's depth and incidence.
pub fn axial_noise(
    frame: &mut Frame,
    incidence_deg: &[f32],
    model: &AxialNoise,
    rng: &mut impl Rng,
) {
    for (d, &a) in frame.depth_m.iter_mut().zip(incidence_deg) {
        if *d <= 0.0 {
            continue;
        }
        let theta = if a.is_finite() { a.to_radians() } else { 0.0 };
        let s = model.sigma(*d, theta);
        if s > 0.0 {
            *d = (*d + gauss(rng) * s).max(1e-3);
        }
    }
}

/// A triangulating sensor's depth: disparity `fx * baseline / z` (pixels) with Gaussian noise
/// `sigma_px`, rounded to `1 / steps_per_px` of a pixel, back to depth.
pub fn quantise_disparity(
    frame: &mut Frame,
    fx: f32,
    baseline_m: f32,
    steps_per_px: f32,
    sigma_px: f32,
    rng: &mut impl Rng,
) {
    let fb = fx * baseline_m;
    for d in &mut frame.depth_m {
        if *d <= 0.0 {
            continue;
        }
        let mut disparity = fb / *d;
        if sigma_px > 0.0 {
            disparity += gauss(rng) * sigma_px;
        }
        let q = (disparity * steps_per_px).round() / steps_per_px;
        *d = if q > 0.0 { fb / q } else { 0.0 };
    }
}

/// Holes: `density` holes per pixel, each a disc of radius uniform in `radius_px`; and single
/// pixels dropped with probability `dropout`.
pub fn speckle_holes(
    frame: &mut Frame,
    density: f32,
    radius_px: [f32; 2],
    dropout: f32,
    rng: &mut impl Rng,
) {
    let (w, h) = (frame.width as i64, frame.height as i64);
    let n = (density * (w * h) as f32).round() as usize;
    for _ in 0..n {
        let (cu, cv) = (rng.random_range(0..w), rng.random_range(0..h));
        let r = if radius_px[1] > radius_px[0] {
            rng.random_range(radius_px[0]..radius_px[1])
        } else {
            radius_px[0]
        };
        let ri = r.ceil() as i64;
        for dv in -ri..=ri {
            for du in -ri..=ri {
                let (x, y) = (cu + du, cv + dv);
                if x >= 0 && y >= 0 && x < w && y < h && ((du * du + dv * dv) as f32) <= r * r {
                    frame.depth_m[(y * w + x) as usize] = 0.0;
                }
            }
        }
    }
    if dropout > 0.0 {
        for d in &mut frame.depth_m {
            if *d > 0.0 && rng.random_range(0.0..1.0f32) < dropout {
                *d = 0.0;
            }
        }
    }
}

/// How the colour camera differs from the renderer, drawn per image for training: read noise,
/// exposure, white balance, slight blur.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ColourRealism {
    /// Gaussian noise, 8-bit levels (drawn in [1, 6]).
    pub noise_levels: f32,
    /// Exposure gain (drawn in [0.75, 1.3]).
    pub exposure: f32,
    /// Per-channel white-balance gains (each drawn in [0.9, 1.1]).
    pub white_balance: [f32; 3],
    /// A 3x3 box blur (drawn with probability 0.5).
    pub blur: bool,
}

impl ColourRealism {
    pub fn randomised(rng: &mut impl Rng) -> Self {
        Self {
            noise_levels: rng.random_range(1.0..6.0),
            exposure: rng.random_range(0.75..1.3),
            white_balance: std::array::from_fn(|_| rng.random_range(0.9..1.1)),
            blur: rng.random_range(0.0..1.0f32) < 0.5,
        }
    }
}

/// Applies `c` to `rgb` in place, with noise from `seed`.
pub fn colour_realism(rgb: &mut RgbImage, c: &ColourRealism, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xc0_10a5);
    if c.blur {
        let src = rgb.clone();
        let (w, h) = (rgb.width() as i64, rgb.height() as i64);
        for y in 0..h {
            for x in 0..w {
                let mut acc = [0u32; 3];
                let mut n = 0;
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (xx, yy) = (x + dx, y + dy);
                        if xx >= 0 && yy >= 0 && xx < w && yy < h {
                            let p = src.get_pixel(xx as u32, yy as u32);
                            for k in 0..3 {
                                acc[k] += u32::from(p[k]);
                            }
                            n += 1;
                        }
                    }
                }
                let p = rgb.get_pixel_mut(x as u32, y as u32);
                for k in 0..3 {
                    p[k] = (acc[k] / n) as u8;
                }
            }
        }
    }
    for p in rgb.pixels_mut() {
        for k in 0..3 {
            let v = f32::from(p[k]) * c.exposure * c.white_balance[k]
                + gauss(&mut rng) * c.noise_levels;
            p[k] = v.round().clamp(0.0, 255.0) as u8;
        }
    }
}
