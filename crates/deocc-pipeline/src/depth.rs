//! Depth source: fills what the depth sensor did not measure (holes at grazing angles, on dark,
//! shiny or far surfaces, or sparse depth from a LiDAR) from an estimate put at the sensor's
//! metric scale.
//!
//! A [`DepthSource`] answers a frame with a [`DepthEstimate`]: metric depth, or relative inverse
//! depth (what monocular models such as Depth Anything give: affine-invariant disparity). The
//! stage fits the estimate to the frame's measured pixels robustly (metric depth:
//! `z = alpha * e + beta`; disparity: `1 / z = alpha * d + beta`, the usual alignment of
//! affine-invariant disparity; a Theil-Sen start, 29% breakdown, then the Huber fit that puts
//! generated depth at the observed scale over the samples that start agrees with) and writes the aligned estimate into the pixels the sensor left empty only: a measured
//! pixel is never changed. A frame whose fit is poor (the estimate disagrees with what was
//! measured) is left as it is and the report says why.
//!
//! Sources: [`SensorDepth`] (the default: the sensor's depth as it is, nothing filled),
//! [`InterpolatedDepth`] (no weights: each small hole interpolated from the nearest measured
//! pixels of its row and column, linearly within a surface and from one side across an edge), and
//! learned ones handed in by the caller (`deocc_model::depth_anything::DepthAnything`), as the
//! completer is.

use deocc_geometry::robust::{huber_affine_fit, median, AffineFit, HuberOptions};
use deocc_geometry::DepthMap;
use deocc_io::scene::{Frame, SceneInput};
use serde::{Deserialize, Serialize};

use crate::error::PipelineError;

pub use deocc_io::depth_source::{DepthEstimate, DepthSource, DepthSourceError};

/// The default depth source: the sensor's depth as it is.
#[derive(Debug, Clone, Copy, Default)]
pub struct SensorDepth;

impl DepthSource for SensorDepth {
    fn name(&self) -> &str {
        "sensor"
    }
    fn estimate(&self, _frame: &Frame) -> Result<Option<DepthEstimate>, DepthSourceError> {
        Ok(None)
    }
}

/// Which side an interpolated hole takes where its two measured neighbours lie on different
/// surfaces.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EdgeSide {
    /// The nearer surface: a sensor that loses depth at grazing angles loses it on the near
    /// object's silhouette, where its surface turns away (the renderer's sensor model).
    Nearer,
    /// The farther surface: a structured-light camera's projector shadow lies on the background
    /// beside the near object.
    Farther,
}

/// Holes filled from the sensor's own depth, no weights: along the hole's row and its column,
/// the nearest measured pixels on either side (up to `max_gap_px` apart) are interpolated
/// linearly when their depths differ by at most `edge_relative` (one surface continues behind
/// the hole), and `edge_side` is taken otherwise; the row's and the column's answers are
/// averaged when they agree, and `edge_side` decides when they do not. A hole measured on one
/// side only, or wider, stays empty: a whole object the sensor lost is not a hole to
/// interpolate over (it would become a false surface at its surroundings' depth).
#[derive(Debug, Clone, Copy)]
pub struct InterpolatedDepth {
    pub max_gap_px: u32,
    pub edge_relative: f32,
    pub edge_side: EdgeSide,
}

/// [`InterpolatedDepth`]'s gap limit by default, and what `deocc run --fill-depth` sets: chosen
/// on tuning scenes (`deocc eval depth --tuning`; docs/decisions.md).
pub const DEFAULT_MAX_GAP_PX: u32 = 8;

impl Default for InterpolatedDepth {
    fn default() -> Self {
        Self {
            max_gap_px: DEFAULT_MAX_GAP_PX,
            edge_relative: 0.03,
            edge_side: EdgeSide::Nearer,
        }
    }
}

/// The nearest measured pixel along a row or column from a hole.
#[derive(Debug, Clone, Copy)]
struct Neighbour {
    z: f32,
    distance: u32,
    /// The next pixel out, when measured.
    beyond: Option<f32>,
}

impl InterpolatedDepth {
    fn pick(&self, a: f32, b: f32) -> f32 {
        match self.edge_side {
            EdgeSide::Nearer => a.min(b),
            EdgeSide::Farther => a.max(b),
        }
    }

    /// The interpolated value between two measured neighbours `a` (at distance `da`, with the
    /// measured pixel beyond it, if any) and `b`; `None` when either is missing or they are too
    /// far apart.
    fn between(&self, a: Option<Neighbour>, b: Option<Neighbour>) -> Option<f32> {
        let (a, b) = (a?, b?);
        if a.distance + b.distance > self.max_gap_px + 1 {
            return None;
        }
        if (a.z - b.z).abs() <= self.edge_relative * a.z.min(b.z) {
            let t = a.distance as f32 / (a.distance + b.distance) as f32;
            return Some(a.z + t * (b.z - a.z));
        }
        Some(match self.edge_side {
            EdgeSide::Farther => a.z.max(b.z),
            EdgeSide::Nearer => {
                // The near surface continues at its own slope where it turns away from the
                // camera, up to the far side.
                let (near, far) = if a.z < b.z { (a, b) } else { (b, a) };
                match near.beyond {
                    Some(z2) if near.z > z2 => {
                        (near.z + (near.z - z2) * near.distance as f32).min(far.z)
                    }
                    _ => near.z,
                }
            }
        })
    }

    /// Fills `depth` (row-major `w x h`, 0 = hole).
    pub fn fill(&self, depth: &DepthMap) -> DepthMap {
        let (w, h) = (depth.width(), depth.height());
        let data = depth.data();
        let at = |u: u32, v: u32| data[v as usize * w as usize + u as usize];
        let mut out = depth.clone();
        for v in 0..h {
            for u in 0..w {
                if at(u, v) > 0.0 {
                    continue;
                }
                let reach = self.max_gap_px as usize;
                let find = |steps: &mut dyn Iterator<Item = (u32, u32)>| {
                    let mut distance = 0u32;
                    let mut found: Option<Neighbour> = None;
                    for (x, y) in steps.take(reach + 1) {
                        distance += 1;
                        let z = at(x, y);
                        match &mut found {
                            None if distance as usize > reach => return None,
                            None if z > 0.0 => {
                                found = Some(Neighbour {
                                    z,
                                    distance,
                                    beyond: None,
                                })
                            }
                            None => {}
                            Some(n) => {
                                n.beyond = (z > 0.0).then_some(z);
                                break;
                            }
                        }
                    }
                    found
                };
                let left = find(&mut (0..u).rev().map(|x| (x, v)));
                let right = find(&mut (u + 1..w).map(|x| (x, v)));
                let up = find(&mut (0..v).rev().map(|y| (u, y)));
                let down = find(&mut (v + 1..h).map(|y| (u, y)));
                let z = match (self.between(left, right), self.between(up, down)) {
                    (Some(a), Some(b)) => {
                        if (a - b).abs() <= self.edge_relative * a.min(b) {
                            0.5 * (a + b)
                        } else {
                            // The row and the column see different surfaces.
                            self.pick(a, b)
                        }
                    }
                    (Some(a), None) | (None, Some(a)) => a,
                    (None, None) => continue,
                };
                out.set(u, v, z);
            }
        }
        out
    }
}

impl DepthSource for InterpolatedDepth {
    fn name(&self) -> &str {
        "interpolated"
    }
    fn estimate(&self, frame: &Frame) -> Result<Option<DepthEstimate>, DepthSourceError> {
        Ok(Some(DepthEstimate::SensorScale(self.fill(&frame.depth))))
    }
}

/// Settings of [`fill_depth`].
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DepthFillOptions {
    /// Measured pixels a frame needs (as a share of its pixels, and at least 100) to set an
    /// estimate's scale.
    pub min_measured_fraction: f32,
    /// A fit whose robust residual exceeds this share of the median measured value (depth, or
    /// inverse depth) is poor: the frame is left as it is.
    pub max_relative_residual: f32,
    /// Filled depth stays within this factor of the farthest measured depth (no invented far
    /// geometry).
    pub max_depth_factor: f32,
    /// Measured pixels used for the fit, at most (an even subsample).
    pub max_fit_samples: usize,
}

impl Default for DepthFillOptions {
    fn default() -> Self {
        Self {
            min_measured_fraction: 0.005,
            max_relative_residual: 0.05,
            max_depth_factor: 1.25,
            max_fit_samples: 20_000,
        }
    }
}

impl DepthFillOptions {
    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad = |field, msg: &str| {
            Err(PipelineError::Option {
                field,
                msg: msg.into(),
            })
        };
        if !(self.min_measured_fraction > 0.0 && self.min_measured_fraction <= 1.0) {
            return bad("min_measured_fraction", "must be in (0, 1]");
        }
        if self.max_relative_residual.is_nan() || self.max_relative_residual <= 0.0 {
            return bad("max_relative_residual", "must be positive");
        }
        if self.max_depth_factor.is_nan() || self.max_depth_factor < 1.0 {
            return bad("max_depth_factor", "must be at least 1");
        }
        if self.max_fit_samples < 100 {
            return bad("max_fit_samples", "must be at least 100");
        }
        Ok(())
    }
}

/// What [`fill_depth`] did to one frame.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DepthFillReport {
    pub frame: String,
    pub source: String,
    /// Pixels the sensor measured.
    pub measured: usize,
    /// Pixels filled from the estimate.
    pub filled: usize,
    /// The fit `y = alpha * x + beta` (identity for an estimate at the sensor's scale).
    pub alpha: f64,
    pub beta: f64,
    /// Robust residual of the fit relative to the median measured value.
    pub relative_residual: f64,
    /// Why nothing was filled, if nothing was.
    pub skipped: Option<String>,
}

/// `y = alpha * x + beta` robust to a share of wrong estimates far from the others (a learned
/// depth's outliers carry leverage): a Theil-Sen start (the median slope over pairs of samples,
/// 29% breakdown), then the Huber fit over the samples within three robust deviations of it.
fn robust_affine_fit(x: &[f32], y: &[f32]) -> deocc_geometry::Result<AffineFit> {
    let n = x.len();
    let mut slopes = Vec::with_capacity(4096);
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = |m: usize| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((state >> 33) as usize) % m
    };
    for _ in 0..16_384 {
        let (i, j) = (next(n), next(n));
        let dx = x[j] as f64 - x[i] as f64;
        if dx.abs() > 1e-9 {
            slopes.push((y[j] as f64 - y[i] as f64) / dx);
        }
        if slopes.len() == 4096 {
            break;
        }
    }
    if slopes.len() < 16 {
        return Err(deocc_geometry::GeometryError::Degenerate(
            "the estimate has no spread over the measured pixels".into(),
        ));
    }
    let alpha = median(&mut slopes);
    let beta = median(
        &mut x
            .iter()
            .zip(y)
            .map(|(&a, &b)| b as f64 - alpha * a as f64)
            .collect::<Vec<_>>(),
    );
    let residual = |a: f32, b: f32| (b as f64 - (alpha * a as f64 + beta)).abs();
    let spread = 1.4826
        * median(
            &mut x
                .iter()
                .zip(y)
                .map(|(&a, &b)| residual(a, b))
                .collect::<Vec<_>>(),
        );
    let keep = (3.0 * spread).max(1e-9 * beta.abs().max(1.0));
    let (xi, yi): (Vec<f32>, Vec<f32>) = x
        .iter()
        .zip(y)
        .filter(|(&a, &b)| residual(a, b) <= keep)
        .map(|(&a, &b)| (a, b))
        .unzip();
    if xi.len() < 2 {
        return Ok(AffineFit {
            alpha,
            beta,
            scale: spread,
            inlier_fraction: xi.len() as f64 / n as f64,
            iterations: 0,
        });
    }
    huber_affine_fit(&xi, &yi, &HuberOptions::default())
}

/// Fills the frame's unmeasured pixels from `source` (see the module documentation). Returns
/// `None` when the source keeps the sensor's depth; an error names the frame when it has too few
/// measured pixels to set the estimate's scale or the estimate is not the frame's size.
pub fn fill_depth(
    frame: &mut Frame,
    source: &dyn DepthSource,
    opts: &DepthFillOptions,
) -> Result<Option<DepthFillReport>, PipelineError> {
    opts.validate()?;
    let estimate = source.estimate(frame).map_err(|e| {
        PipelineError::input(
            format!("frame {}", frame.name),
            format!("{}: {e}", source.name()),
        )
    })?;
    let Some(estimate) = estimate else {
        return Ok(None);
    };
    let (w, h) = (frame.depth.width(), frame.depth.height());
    let n = w as usize * h as usize;
    let what = |msg: String| PipelineError::input(format!("frame {}", frame.name), msg);
    let (values, inverse, at_scale) = match estimate {
        DepthEstimate::Metric(d) | DepthEstimate::SensorScale(d)
            if (d.width(), d.height()) != (w, h) =>
        {
            return Err(what(format!(
                "depth source {} answered {}x{} for a {w}x{h} frame",
                source.name(),
                d.width(),
                d.height()
            )));
        }
        DepthEstimate::Metric(d) => (d.into_data(), false, false),
        DepthEstimate::SensorScale(d) => (d.into_data(), false, true),
        DepthEstimate::Disparity(v) if v.len() != n => {
            return Err(what(format!(
                "depth source {} answered {} values for a {w}x{h} frame",
                source.name(),
                v.len()
            )));
        }
        DepthEstimate::Disparity(v) => (v, true, false),
    };
    let sensor = frame.depth.data();
    let measured: Vec<usize> = (0..n).filter(|&i| sensor[i] > 0.0).collect();
    let needed = ((opts.min_measured_fraction * n as f32).ceil() as usize).max(100);
    if measured.len() < needed {
        return Err(what(format!(
            "{} measured depth pixels; filling from depth source {} needs at least {needed} to \
             set its scale (sparse depth is enough)",
            measured.len(),
            source.name()
        )));
    }
    let mut report = DepthFillReport {
        frame: frame.name.clone(),
        source: source.name().to_string(),
        measured: measured.len(),
        filled: 0,
        alpha: 1.0,
        beta: 0.0,
        relative_residual: 0.0,
        skipped: None,
    };
    let target = |z: f32| if inverse { 1.0 / z } else { z };
    if !at_scale {
        let usable: Vec<usize> = measured
            .iter()
            .copied()
            .filter(|&i| values[i].is_finite() && values[i] > 0.0)
            .collect();
        let stride = usable.len().div_ceil(opts.max_fit_samples).max(1);
        let (x, y): (Vec<f32>, Vec<f32>) = usable
            .iter()
            .step_by(stride)
            .map(|&i| (values[i], target(sensor[i])))
            .unzip();
        if x.len() < 100 {
            report.skipped = Some(format!(
                "the estimate covers only {} measured pixels",
                x.len()
            ));
            return Ok(Some(report));
        }
        let fit = match robust_affine_fit(&x, &y) {
            Ok(f) => f,
            Err(e) => {
                report.skipped = Some(format!("no fit: {e}"));
                return Ok(Some(report));
            }
        };
        report.alpha = fit.alpha;
        report.beta = fit.beta;
        let typical = median(&mut y.iter().map(|&v| v as f64).collect::<Vec<_>>());
        let spread = 1.4826
            * median(
                &mut x
                    .iter()
                    .zip(&y)
                    .map(|(&a, &b)| (b as f64 - fit.apply(a as f64)).abs())
                    .collect::<Vec<_>>(),
            );
        report.relative_residual = spread / typical.max(1e-12);
        if report.relative_residual > opts.max_relative_residual as f64 {
            report.skipped = Some(format!(
                "the estimate disagrees with the measured depth (relative residual {:.3} > {})",
                report.relative_residual, opts.max_relative_residual
            ));
            return Ok(Some(report));
        }
        if inverse && fit.alpha <= 0.0 {
            report.skipped = Some("the estimate's disparity falls where depth falls".into());
            return Ok(Some(report));
        }
    }
    let far = measured.iter().map(|&i| sensor[i]).fold(0.0f32, f32::max) * opts.max_depth_factor;
    let mut depth = frame.depth.clone().into_data();
    for (i, z) in depth.iter_mut().enumerate() {
        if *z > 0.0 || !(values[i].is_finite() && values[i] > 0.0) {
            continue;
        }
        let y = report.alpha * values[i] as f64 + report.beta;
        let filled = if inverse {
            if y <= 0.0 {
                continue;
            }
            1.0 / y
        } else {
            y
        } as f32;
        if filled.is_finite() && filled > 0.0 && filled <= far {
            *z = filled;
            report.filled += 1;
        }
    }
    frame.depth = DepthMap::new(w, h, depth)?;
    Ok(Some(report))
}

/// [`fill_depth`] on every frame of a scene, in order.
pub fn fill_scene_depth(
    scene: &mut SceneInput,
    source: &dyn DepthSource,
    opts: &DepthFillOptions,
) -> Result<Vec<DepthFillReport>, PipelineError> {
    let mut reports = Vec::new();
    for frame in &mut scene.frames {
        if let Some(r) = fill_depth(frame, source, opts)? {
            reports.push(r);
        }
    }
    Ok(reports)
}

#[cfg(test)]
mod tests {
    use super::*;
    use deocc_geometry::camera::{Camera, Intrinsics};
    use image::RgbImage;

    const W: u32 = 96;
    const H: u32 = 72;

    /// A tilted wall at 1.5-1.7 m with a box at 0.8 m in front of its middle.
    fn truth(u: u32, v: u32) -> f32 {
        if (30..60).contains(&u) && (20..50).contains(&v) {
            0.8
        } else {
            1.5 + 0.002 * u as f32 + 0.001 * v as f32
        }
    }

    fn frame_with_holes(hole: impl Fn(u32, u32) -> bool) -> Frame {
        let mut depth = DepthMap::zeros(W, H);
        for v in 0..H {
            for u in 0..W {
                if !hole(u, v) {
                    depth.set(u, v, truth(u, v));
                }
            }
        }
        Frame {
            name: "f0".into(),
            camera: Camera {
                intrinsics: Intrinsics::new(80.0, 80.0, 48.0, 36.0, W, H).unwrap(),
                world_from_camera: nalgebra::Isometry3::identity(),
            },
            rgb: RgbImage::new(W, H),
            depth,
            instances: None,
        }
    }

    /// Blocks of 6x6 pixels missing across the image, some on the box's edge.
    fn blocks(u: u32, v: u32) -> bool {
        (u % 16) < 6 && (v % 12) < 6
    }

    /// A learned source's stand-in: the true disparity at an unknown affine, with every 11th
    /// pixel wrong.
    struct AffineDisparity;
    impl DepthSource for AffineDisparity {
        fn name(&self) -> &str {
            "affine"
        }
        fn estimate(&self, _f: &Frame) -> Result<Option<DepthEstimate>, DepthSourceError> {
            let d = (0..W * H)
                .map(|i| {
                    let (u, v) = (i % W, i / W);
                    if i % 11 == 0 {
                        7.0
                    } else {
                        3.7 / truth(u, v) - 0.2
                    }
                })
                .collect();
            Ok(Some(DepthEstimate::Disparity(d)))
        }
    }

    struct Noise;
    impl DepthSource for Noise {
        fn name(&self) -> &str {
            "noise"
        }
        fn estimate(&self, _f: &Frame) -> Result<Option<DepthEstimate>, DepthSourceError> {
            let d = (0..W * H)
                .map(|i| 1.0 + ((i * 2_654_435_761) % 1000) as f32 / 100.0)
                .collect();
            Ok(Some(DepthEstimate::Disparity(d)))
        }
    }

    fn filled_pixels(before: &Frame, after: &Frame) -> Vec<(u32, u32, f32)> {
        let mut out = Vec::new();
        for v in 0..H {
            for u in 0..W {
                let (a, b) = (before.depth.get(u, v), after.depth.get(u, v));
                if a > 0.0 {
                    assert_eq!(a, b, "a measured pixel changed at ({u}, {v})");
                } else if b > 0.0 {
                    out.push((u, v, b));
                }
            }
        }
        out
    }

    #[test]
    fn the_sensor_source_changes_nothing() {
        let mut f = frame_with_holes(blocks);
        let before = f.depth.clone();
        let r = fill_depth(&mut f, &SensorDepth, &DepthFillOptions::default()).unwrap();
        assert!(r.is_none());
        assert_eq!(f.depth, before);
    }

    #[test]
    fn interpolation_fills_surfaces_and_puts_no_pixel_between_two() {
        let before = frame_with_holes(blocks);
        let mut f = before.clone();
        let wide = InterpolatedDepth {
            max_gap_px: 16,
            ..Default::default()
        };
        let r = fill_depth(&mut f, &wide, &DepthFillOptions::default())
            .unwrap()
            .unwrap();
        let filled = filled_pixels(&before, &f);
        assert_eq!(r.filled, filled.len());
        // Every hole but the corner block's, which no row or column sees from both sides.
        let holes = (0..W * H)
            .filter(|i| blocks(i % W, i / W) && !(i % W < 6 && i / W < 6))
            .count();
        assert_eq!(filled.len(), holes);
        let mut on_surface = 0;
        for &(u, v, z) in &filled {
            let near_box = (z - 0.8).abs() < 0.005;
            let near_wall = (z - (1.5 + 0.002 * u as f32 + 0.001 * v as f32)).abs() < 0.01;
            assert!(near_box || near_wall, "a flying pixel {z} at ({u}, {v})");
            if (z - truth(u, v)).abs() < 0.002 {
                on_surface += 1;
            }
        }
        // Only the holes on the box's edge take the wrong side.
        assert!(
            on_surface as f32 > 0.9 * filled.len() as f32,
            "{on_surface}"
        );
        // Across an edge the nearer side by default, the farther on request.
        let edge = |side| {
            let mut f = frame_with_holes(|u, v| (28..32).contains(&u) && v == 30);
            let source = InterpolatedDepth {
                edge_side: side,
                ..Default::default()
            };
            fill_depth(&mut f, &source, &DepthFillOptions::default()).unwrap();
            f.depth.get(29, 30)
        };
        assert_eq!(edge(EdgeSide::Nearer), 0.8);
        assert!(edge(EdgeSide::Farther) > 1.5);
    }

    #[test]
    fn holes_wider_than_the_limit_stay_empty() {
        let hole = |u: u32, v: u32| (10..30).contains(&u) && (10..30).contains(&v);
        let before = frame_with_holes(hole);
        let mut f = before.clone();
        fill_depth(
            &mut f,
            &InterpolatedDepth::default(),
            &DepthFillOptions::default(),
        )
        .unwrap();
        assert!(filled_pixels(&before, &f).is_empty());
        // A hole on the image's border is seen from one side only.
        let border = frame_with_holes(|u, v| u < 4 && v == 5);
        let mut f = border.clone();
        let source = InterpolatedDepth {
            max_gap_px: 64,
            ..Default::default()
        };
        fill_depth(&mut f, &source, &DepthFillOptions::default()).unwrap();
        // Its column still sees it from both sides.
        assert_eq!(filled_pixels(&border, &f).len(), 4);
        let wide = InterpolatedDepth {
            max_gap_px: 64,
            ..Default::default()
        };
        let mut f = before.clone();
        fill_depth(&mut f, &wide, &DepthFillOptions::default()).unwrap();
        assert_eq!(filled_pixels(&before, &f).len(), 400);
    }

    #[test]
    fn relative_disparity_is_put_at_the_measured_scale() {
        let before = frame_with_holes(blocks);
        let mut f = before.clone();
        let r = fill_depth(&mut f, &AffineDisparity, &DepthFillOptions::default())
            .unwrap()
            .unwrap();
        assert!(r.skipped.is_none(), "{:?} {r:?}", r.skipped);
        assert!((r.alpha - 1.0 / 3.7).abs() < 1e-3, "alpha {}", r.alpha);
        let filled = filled_pixels(&before, &f);
        assert!(!filled.is_empty());
        let good = filled
            .iter()
            .filter(|&&(u, v, z)| (z - truth(u, v)).abs() < 0.005 * truth(u, v))
            .count();
        // Every 11th pixel carries a wrong estimate; the rest land on the truth.
        assert!(
            good as f32 >= 0.88 * filled.len() as f32,
            "{good} of {}",
            filled.len()
        );
    }

    #[test]
    fn an_estimate_that_disagrees_with_the_sensor_fills_nothing() {
        let before = frame_with_holes(blocks);
        let mut f = before.clone();
        let r = fill_depth(&mut f, &Noise, &DepthFillOptions::default())
            .unwrap()
            .unwrap();
        assert_eq!(r.filled, 0);
        assert!(r.skipped.as_deref().unwrap().contains("disagrees"));
        assert_eq!(f.depth, before.depth);
    }

    #[test]
    fn too_few_measured_pixels_is_an_error_naming_the_frame() {
        let mut f = frame_with_holes(|u, v| u > 5 || v > 5);
        let e = fill_depth(&mut f, &AffineDisparity, &DepthFillOptions::default()).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains("frame f0") && msg.contains("36 measured"),
            "{msg}"
        );
    }

    #[test]
    fn an_estimate_of_the_wrong_size_is_an_error() {
        struct Small;
        impl DepthSource for Small {
            fn name(&self) -> &str {
                "small"
            }
            fn estimate(&self, _f: &Frame) -> Result<Option<DepthEstimate>, DepthSourceError> {
                Ok(Some(DepthEstimate::Metric(DepthMap::zeros(10, 10))))
            }
        }
        let mut f = frame_with_holes(blocks);
        let e = fill_depth(&mut f, &Small, &DepthFillOptions::default()).unwrap_err();
        assert!(e.to_string().contains("10x10 for a 96x72"), "{e}");
        let bad = DepthFillOptions {
            max_depth_factor: 0.5,
            ..Default::default()
        };
        let e = fill_depth(&mut f, &SensorDepth, &bad).unwrap_err();
        assert!(e.to_string().contains("max_depth_factor"), "{e}");
    }
}
