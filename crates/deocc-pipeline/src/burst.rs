//! Stage: burst fusion, the first of the front half. A robot that holds still takes several
//! frames from one pose; a sensor's noise, its random drop-outs and its flying pixels differ from
//! frame to frame while the scene does not. Frames of a posed scene whose poses agree (within
//! `max_translation_m` and `max_rotation_deg`) and whose intrinsics are the same become one frame:
//! - depth: per pixel, the median of the frames that measured it, when at least
//!   `min_valid_fraction` of them did (else no depth): axial noise falls as the square root of
//!   the frames, a pixel one frame dropped is filled by the others, and a flying pixel in one frame
//!   is outvoted;
//! - colour: the per-pixel mean;
//! - instance map: the first frame's that has one;
//! - name and pose: the first frame's.
//!
//! Frames of an unposed scene are never fused (their poses are the identity until the
//! registration stage estimates them), nor frames whose sizes differ.

use deocc_geometry::DepthMap;
use deocc_io::scene::{Frame, SceneInput};
use serde::{Deserialize, Serialize};

use crate::PipelineError;

/// The stage's settings.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct BurstOptions {
    /// Run the stage at all.
    pub enabled: bool,
    /// Frames whose camera centres are this close (metres) ...
    pub max_translation_m: f32,
    /// ... and whose orientations differ by at most this many degrees are one burst.
    pub max_rotation_deg: f32,
    /// A pixel of the fused frame has depth when at least this share of the burst measured it.
    pub min_valid_fraction: f32,
}

impl Default for BurstOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            max_translation_m: 0.002,
            max_rotation_deg: 0.2,
            min_valid_fraction: 0.3,
        }
    }
}

impl BurstOptions {
    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad = |field: &'static str, msg: String| PipelineError::Option { field, msg };
        for (field, v, hi) in [
            ("burst.max_translation_m", self.max_translation_m, 0.1),
            ("burst.max_rotation_deg", self.max_rotation_deg, 10.0),
            ("burst.min_valid_fraction", self.min_valid_fraction, 1.0),
        ] {
            if !(0.0..=hi).contains(&v) {
                return Err(bad(field, format!("{v} is outside [0, {hi}]")));
            }
        }
        Ok(())
    }
}

/// What the stage did: how many frames came in and how many went on.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BurstRecord {
    pub frames_in: usize,
    pub frames_out: usize,
    /// The frames fused into each frame that went on, by name (one entry per burst of two or
    /// more).
    pub bursts: Vec<Vec<String>>,
}

/// Whether frames `a` and `b` were taken from one pose with one camera.
fn same_pose(a: &Frame, b: &Frame, opts: &BurstOptions) -> bool {
    let (pa, pb) = (&a.camera.world_from_camera, &b.camera.world_from_camera);
    let moved = (pa.translation.vector - pb.translation.vector).norm();
    let turned = pa.rotation.angle_to(&pb.rotation).to_degrees();
    a.camera.intrinsics == b.camera.intrinsics
        && a.depth.width() == b.depth.width()
        && a.depth.height() == b.depth.height()
        && a.rgb.dimensions() == b.rgb.dimensions()
        && moved <= opts.max_translation_m
        && turned <= opts.max_rotation_deg
}

/// One frame from a burst (see the module docs).
fn fuse_frames(burst: &[Frame], min_valid_fraction: f32) -> Frame {
    let first = &burst[0];
    let (w, h) = (first.depth.width(), first.depth.height());
    let need = ((min_valid_fraction * burst.len() as f32).ceil() as usize).max(1);
    let mut values = Vec::with_capacity(burst.len());
    let depth: Vec<f32> = (0..(w * h) as usize)
        .map(|k| {
            values.clear();
            values.extend(
                burst
                    .iter()
                    .map(|f| f.depth.data()[k])
                    .filter(|d| d.is_finite() && *d > 0.0),
            );
            if values.len() < need {
                return 0.0;
            }
            values.sort_by(f32::total_cmp);
            let m = values.len() / 2;
            if values.len() % 2 == 1 {
                values[m]
            } else {
                0.5 * (values[m - 1] + values[m])
            }
        })
        .collect();
    let mut rgb = first.rgb.clone();
    for (k, px) in rgb.pixels_mut().enumerate() {
        let (x, y) = (
            (k as u32) % first.rgb.width(),
            (k as u32) / first.rgb.width(),
        );
        for c in 0..3 {
            let sum: u32 = burst
                .iter()
                .map(|f| u32::from(f.rgb.get_pixel(x, y)[c]))
                .sum();
            px[c] = ((sum + burst.len() as u32 / 2) / burst.len() as u32) as u8;
        }
    }
    Frame {
        name: first.name.clone(),
        camera: first.camera,
        rgb,
        depth: DepthMap::new(w, h, depth).expect("the first frame's size"),
        instances: burst.iter().find_map(|f| f.instances.clone()),
    }
}

/// Fuses the bursts of `scene` in place (see the module docs).
pub fn fuse_bursts(scene: &mut SceneInput, opts: &BurstOptions) -> BurstRecord {
    let frames_in = scene.frames.len();
    let mut record = BurstRecord {
        frames_in,
        frames_out: frames_in,
        bursts: Vec::new(),
    };
    if !opts.enabled || !scene.posed || frames_in < 2 {
        return record;
    }
    // Each frame joins the first earlier group whose first frame shares its pose.
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for i in 0..frames_in {
        match groups
            .iter_mut()
            .find(|g| same_pose(&scene.frames[g[0]], &scene.frames[i], opts))
        {
            Some(g) => g.push(i),
            None => groups.push(vec![i]),
        }
    }
    if groups.len() == frames_in {
        return record;
    }
    let frames = std::mem::take(&mut scene.frames);
    let mut slots: Vec<Option<Frame>> = frames.into_iter().map(Some).collect();
    for g in &groups {
        let burst: Vec<Frame> = g.iter().filter_map(|&i| slots[i].take()).collect();
        if burst.len() > 1 {
            record
                .bursts
                .push(burst.iter().map(|f| f.name.clone()).collect());
            scene
                .frames
                .push(fuse_frames(&burst, opts.min_valid_fraction));
        } else {
            scene.frames.extend(burst);
        }
    }
    record.frames_out = scene.frames.len();
    record
}

#[cfg(test)]
mod tests {
    use super::*;
    use deocc_geometry::camera::{Camera, Intrinsics};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};
    use rand::{Rng, SeedableRng};

    fn frame(name: &str, pose: Isometry3<f32>, depth: Vec<f32>, grey: u8) -> Frame {
        Frame {
            name: name.into(),
            camera: Camera {
                intrinsics: Intrinsics::new(20.0, 20.0, 8.0, 8.0, 16, 16).unwrap(),
                world_from_camera: pose,
            },
            rgb: image::RgbImage::from_pixel(16, 16, image::Rgb([grey; 3])),
            depth: DepthMap::new(16, 16, depth).unwrap(),
            instances: None,
        }
    }

    /// Five noisy frames of a wall at 2 m from one pose, each missing a different tenth of its
    /// pixels and one with flying pixels, and a sixth frame from elsewhere: the five become one
    /// frame with less noise than any of them, every pixel measured and no flying pixel; the
    /// sixth goes on alone; an unposed scene or the stage switched off keeps every frame.
    #[test]
    fn a_burst_from_one_pose_becomes_one_quieter_frame() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let here = Isometry3::identity();
        let mut frames = Vec::new();
        for f in 0..5 {
            let depth: Vec<f32> = (0..256)
                .map(|k| {
                    if k % 10 == f * 2 {
                        0.0
                    } else if f == 1 && k % 37 == 0 {
                        0.7 // a flying pixel
                    } else {
                        2.0 + rng.random_range(-0.02f32..0.02)
                    }
                })
                .collect();
            frames.push(frame(&format!("{f}"), here, depth, 10 * f as u8));
        }
        let tiny = UnitQuaternion::from_euler_angles(0.0, 0.0005, 0.0);
        frames[3].camera.world_from_camera =
            Isometry3::from_parts(Translation3::new(0.001, 0.0, 0.0), tiny);
        let away = Isometry3::translation(0.5, 0.0, 0.0);
        frames.push(frame("away", away, vec![1.5; 256], 200));
        let err = |f: &Frame| {
            let d: Vec<f32> = f
                .depth
                .data()
                .iter()
                .copied()
                .filter(|&d| d > 0.0)
                .collect();
            (d.iter().map(|x| (x - 2.0).powi(2)).sum::<f32>() / d.len() as f32).sqrt()
        };
        let single = err(&frames[0]);
        let mut scene = SceneInput {
            dir: "burst".into(),
            frames: frames.clone(),
            structure_ids: Vec::new(),
            posed: true,
        };
        let record = fuse_bursts(&mut scene, &BurstOptions::default());
        assert_eq!((record.frames_in, record.frames_out), (6, 2));
        assert_eq!(record.bursts, vec![vec!["0", "1", "2", "3", "4"]]);
        let fused = &scene.frames[0];
        assert_eq!(fused.name, "0");
        assert!(fused.depth.data().iter().all(|&d| d > 1.9 && d < 2.1));
        assert!(err(fused) < 0.7 * single, "{} vs {single}", err(fused));
        assert_eq!(fused.rgb.get_pixel(0, 0)[0], 20, "the mean colour");
        assert_eq!(scene.frames[1].name, "away");
        // Too few measurements at a pixel: no depth there.
        let mut strict = SceneInput {
            frames: frames.clone(),
            ..scene.clone()
        };
        let opts = BurstOptions {
            min_valid_fraction: 1.0,
            ..Default::default()
        };
        fuse_bursts(&mut strict, &opts);
        assert!(strict.frames[0].depth.data().contains(&0.0));
        for (posed, enabled) in [(false, true), (true, false)] {
            let mut kept = SceneInput {
                frames: frames.clone(),
                posed,
                ..scene.clone()
            };
            let opts = BurstOptions {
                enabled,
                ..Default::default()
            };
            let r = fuse_bursts(&mut kept, &opts);
            assert_eq!((r.frames_out, kept.frames.len()), (6, 6));
        }
        let bad = BurstOptions {
            max_rotation_deg: -1.0,
            ..Default::default()
        };
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("burst.max_rotation_deg"));
    }
}
