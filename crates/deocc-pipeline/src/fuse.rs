//! Stage: alignment and fusion of one completion. The completion's relative near-side depth is
//! fitted to the observed depth on the visible pixels (robust Huber scale and shift); a poor fit
//! is rejected. Then what was hidden is back-projected into world points: the near side where
//! the object is revealed (amodal minus visible, and only where something in front hid it) and
//! the far side (its back) wherever the object is. Every generated point carries the completer's
//! probability that its pixel belongs to the object as its confidence. A learned completer's
//! depth may first be median-filtered over its amodal mask ([`median_within`]). With the mirror check,
//! a point whose depth the completion of the mirrored crop puts more than a limit away (in
//! metres, through the same fit) is not generated. With the thickness cap, neither is a far-side
//! point more than a limit behind its near side. With the error gate, neither is a point the
//! completer expects further off than a limit; those pixels are returned
//! ([`fuse_completion_detailed`]) so that another completer may fill exactly them
//! ([`FuseOptions::only`]). Where another frame observed the object's back along a pixel's ray
//! ([`FuseOptions::seen_behind`]), no far-side point is generated: the observation is in the
//! cloud already.

use deocc_completion::{CropCompletion, Provenance};
use deocc_geometry::robust::{huber_affine_fit, HuberOptions};
use deocc_geometry::PointCloud;
use deocc_io::scene::Frame;

use crate::complete::DepthSpread;
use crate::crops::CropWindow;
use crate::report::CompletionRecord;

/// Tolerance of the free-space test: a generated point must lie at least this far behind the
/// observed surface at its pixel (something in front hid it), else the sensor saw empty space there.
const FREE_SPACE_MARGIN_M: f32 = 0.01;

/// A far side closer than this to the near side is the same surface.
const MIN_THICKNESS_M: f32 = 0.005;

/// A fit is rejected when its scale is not positive, fewer than this fraction of the visible
/// pixels are inliers, or its residual scale is above [`MAX_FIT_RESIDUAL_M`].
const MIN_FIT_INLIERS: f64 = 0.5;
const MAX_FIT_RESIDUAL_M: f64 = 0.03;

/// The mirror check of one completion: the spread of its depths and the largest spread (metres)
/// a generated point may have.
#[derive(Debug, Clone, Copy)]
pub struct SpreadLimit<'a> {
    pub spread: &'a DepthSpread,
    pub max_m: f32,
}

/// How a completion is fused besides its alignment.
#[derive(Debug, Clone, Copy, Default)]
pub struct FuseOptions<'a> {
    /// The mirror check: points whose depth the mirrored completion contradicts are left out
    /// (counted in the record's `spread_dropped`).
    pub spread: Option<SpreadLimit<'a>>,
    /// Median filter radius (pixels; 0 = off) of the generated depth: each amodal pixel's near
    /// and far depth become the median over the amodal pixels of its (2r+1)^2 window, before
    /// the fit is applied ([`median_within`]).
    pub median_px: usize,
    /// Thickness cap (metres; 0 = off): a far-side point more than this behind its near side
    /// is not generated.
    pub max_thickness_m: f32,
    /// Thickness cap relative to the silhouette (0 = off): a far-side point more than this
    /// many times the width of its amodal row run (the contiguous amodal pixels of its image
    /// row, in metres at the crop's scale) behind its near side is not generated
    /// ([`row_run_widths_m`]). A leg or a post 3 cm wide is not 10 cm deep.
    pub max_thickness_per_width: f32,
    /// (r*r) relative depth where other frames observed the object (the crop's
    /// `seen_elsewhere`, infinite elsewhere): the near side there is their observation, already in
    /// the cloud, so no near-side point is generated; the far side is placed behind it.
    pub seen_elsewhere: Option<&'a [f32]>,
    /// (r*r) relative depth where other frames observed the object's back along the pixel's ray
    /// (the crop's [`crate::crops::Elsewhere::back`], infinite elsewhere): where it lies behind
    /// the near side, the far side is observed, so none is generated (counted in the record's
    /// `far_side_observed`). (This view cannot see past it: a pixel it sees beyond the near
    /// side generates nothing.)
    pub seen_behind: Option<&'a [f32]>,
    /// Revealed pixels (neither visible nor seen elsewhere) whose mask probability is below
    /// this generate no point (0 = off).
    pub min_revealed_confidence: f32,
    /// Points whose depth the completer itself expects to be further off than this (metres,
    /// its [`deocc_completion::ExpectedDepthError`] through the depth fit's scale) are not
    /// generated (0 = off; completions without an estimate are not affected): a revealed
    /// pixel's near side takes its far side with it, as in the mirror check. Counted in the
    /// record's `uncertain_dropped`.
    pub max_expected_error_m: f32,
    /// The expected error (metres) given to each generated point whose completion carries no
    /// estimate of its own ([`deocc_completion::FusePolicy::stated_error_m`]); a completion with
    /// one gives each point its own, through the depth fit's scale and combined with the fit's
    /// residual scale. It becomes the cloud's `expected_error`, which the planners read.
    pub stated_error_m: f32,
    /// Only these pixels generate points (`None`: every pixel): how a fallback completer fills
    /// the pixels another completer left out as too uncertain ([`UncertainPixels`]).
    pub only: Option<&'a UncertainPixels>,
}

/// The pixels (r*r) whose points a completion left out because it expected them too far off
/// ([`FuseOptions::max_expected_error_m`]): the revealed near sides (their far sides go with
/// them) and the far sides. Another completer may fill exactly these ([`FuseOptions::only`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct UncertainPixels {
    pub near: Vec<bool>,
    pub far: Vec<bool>,
}

impl UncertainPixels {
    fn new(n: usize) -> Self {
        Self {
            near: vec![false; n],
            far: vec![false; n],
        }
    }

    /// How many pixels left out a near side or a far side.
    pub fn count(&self) -> usize {
        self.near
            .iter()
            .zip(&self.far)
            .filter(|(&a, &b)| a || b)
            .count()
    }
}

/// Each pixel's amodal row run width in metres (an `r x r` mask whose crop is `crop_m` wide):
/// the number of contiguous `mask` pixels in its row that include it, times the pixel size;
/// infinite outside the mask.
pub fn row_run_widths_m(mask: &[bool], r: usize, crop_m: f32) -> Vec<f32> {
    let px_m = crop_m / r as f32;
    let mut out = vec![f32::INFINITY; r * r];
    for v in 0..r {
        let row = &mask[v * r..(v + 1) * r];
        let mut u = 0;
        while u < r {
            if !row[u] {
                u += 1;
                continue;
            }
            let start = u;
            while u < r && row[u] {
                u += 1;
            }
            let w = (u - start) as f32 * px_m;
            out[v * r + start..v * r + u].fill(w);
        }
    }
    out
}

/// The median of `values` over the `mask` pixels of each mask pixel's (2 radius + 1)^2 window
/// (an `r x r` image); pixels outside the mask keep their value.
pub fn median_within(values: &[f32], mask: &[bool], r: usize, radius: usize) -> Vec<f32> {
    if radius == 0 {
        return values.to_vec();
    }
    let mut out = values.to_vec();
    let mut window = Vec::with_capacity((2 * radius + 1) * (2 * radius + 1));
    for v in 0..r {
        for u in 0..r {
            let k = v * r + u;
            if !mask[k] {
                continue;
            }
            window.clear();
            for y in v.saturating_sub(radius)..(v + radius + 1).min(r) {
                for x in u.saturating_sub(radius)..(u + radius + 1).min(r) {
                    let q = y * r + x;
                    if mask[q] && values[q].is_finite() {
                        window.push(values[q]);
                    }
                }
            }
            if !window.is_empty() {
                let mid = window.len() / 2;
                out[k] = *window.select_nth_unstable_by(mid, f32::total_cmp).1;
            }
        }
    }
    out
}

/// Aligns a completion's depth to the observed depth and back-projects what was hidden, each
/// point carrying `provenance` ([`FuseOptions`]: the mirror check, the median filter).
pub fn fuse_completion(
    window: &CropWindow,
    visible: &[bool],
    completion: &CropCompletion,
    frame: &Frame,
    completer: &str,
    provenance: Provenance,
    opts: &FuseOptions<'_>,
) -> (PointCloud, CompletionRecord) {
    let (cloud, record, _) = fuse_completion_detailed(
        window, visible, completion, frame, completer, provenance, opts,
    );
    (cloud, record)
}

/// [`fuse_completion`], also returning the pixels left out as too uncertain (all false when the
/// gate is off or the completion has no estimate).
pub fn fuse_completion_detailed(
    window: &CropWindow,
    visible: &[bool],
    completion: &CropCompletion,
    frame: &Frame,
    completer: &str,
    provenance: Provenance,
    opts: &FuseOptions<'_>,
) -> (PointCloud, CompletionRecord, UncertainPixels) {
    let spread = opts.spread;
    let n = window.resolution * window.resolution;
    let vis: Vec<usize> = (0..n).filter(|&k| visible[k]).collect();
    let mut left_out = UncertainPixels::new(n);
    let allowed = |k: usize, far: bool| {
        opts.only.is_none_or(|o| {
            let m = if far { &o.far } else { &o.near };
            m.get(k).copied().unwrap_or(false)
        })
    };
    let amodal_px = completion.amodal.iter().filter(|&&a| a).count();
    let mut record = new_record(window, completer, vis.len(), amodal_px);
    let (fit, why) = fit_to_observed(&vis, completion, window);
    record.fit = fit;
    let Some(fit) = fit.filter(|_| why.is_none()) else {
        record.reason = why.unwrap_or_default();
        return (PointCloud::default(), record, left_out);
    };
    let r = window.resolution;
    let near_depth = median_within(&completion.depth, &completion.amodal, r, opts.median_px);
    let back_depth = median_within(
        &completion.back_depth,
        &completion.amodal,
        r,
        opts.median_px,
    );
    // Relative depth to metres is the fit's scale; a spread above the limit there is a point
    // the completer does not know.
    let metres = fit.alpha.abs() as f32;
    let doubtful = |k: usize, far: bool| {
        spread.is_some_and(|s| {
            let d = if far { &s.spread.far } else { &s.spread.near };
            d.get(k).is_some_and(|&x| x * metres > s.max_m)
        })
    };
    let estimate = completion.expected_error.as_ref();
    let error_m = point_error(estimate, metres, fit.scale as f32, opts.stated_error_m);
    let expected = estimate.filter(|_| opts.max_expected_error_m > 0.0);
    let uncertain = |k: usize, far: bool| {
        expected.is_some_and(|e| {
            let d = if far { &e.far } else { &e.near };
            // A NaN estimate is no estimate: leave the point out.
            d.get(k)
                .is_some_and(|&x| x.is_nan() || x * metres > opts.max_expected_error_m)
        })
    };
    let mut uncertain_dropped = 0;
    let (max_thick, run_cap) = thickness_caps(opts, completion, window);
    let mut spread_dropped = 0;
    let mut far_side_observed = 0;
    let mut out = Emitted::default();
    let mut push = |k: usize, z: f32, shade: f32, error: f32| {
        out.push(window, frame, completion, k, z, shade, error)
    };
    for (k, &is_visible) in visible.iter().enumerate().take(n) {
        if !completion.amodal[k] || window.source_pixel[k].is_none() {
            continue;
        }
        let obs = window.observed_depth_m[k];
        let elsewhere = opts
            .seen_elsewhere
            .and_then(|d| d.get(k).copied())
            .filter(|d| d.is_finite());
        // Near side: observed where visible or seen by another frame, generated where revealed.
        let front = if is_visible {
            obs
        } else if let Some(rel) = elsewhere {
            window.median_depth_m + rel * window.metric_scale_m
        } else {
            let p = completion.mask_probability.get(k).copied().unwrap_or(1.0);
            if p < opts.min_revealed_confidence {
                continue;
            }
            let z = fit.apply(near_depth[k] as f64) as f32;
            if !(z.is_finite() && z > 0.05) {
                continue;
            }
            if obs > 0.0 && obs > z - FREE_SPACE_MARGIN_M {
                continue; // the sensor saw this pixel at or beyond the generated depth: nothing hides it
            }
            if doubtful(k, false) {
                // Neither side is placed: the far side hangs on this near side.
                spread_dropped += 1;
                continue;
            }
            if uncertain(k, false) {
                uncertain_dropped += 1;
                left_out.near[k] = true;
                left_out.far[k] = true;
                continue;
            }
            if allowed(k, false) {
                push(k, z, 1.0, error_m(k, false));
            }
            z
        };
        // Far side (the object's back), behind the near side: another frame may have seen it.
        let observed_back = opts
            .seen_behind
            .and_then(|d| d.get(k).copied())
            .filter(|d| d.is_finite())
            .map(|rel| window.median_depth_m + rel * window.metric_scale_m)
            .filter(|&b| b > front + MIN_THICKNESS_M);
        if observed_back.is_some() {
            far_side_observed += 1;
            continue;
        }
        let back = fit.apply(back_depth[k] as f64) as f32;
        if back.is_finite()
            && back > front + MIN_THICKNESS_M
            && back - front <= max_thick
            && run_cap.as_ref().is_none_or(|c| back - front <= c[k])
            && !(obs > 0.0 && obs > back + FREE_SPACE_MARGIN_M)
        {
            if doubtful(k, true) {
                spread_dropped += 1;
            } else if uncertain(k, true) {
                uncertain_dropped += 1;
                left_out.far[k] = true;
            } else if allowed(k, true) {
                push(k, back, 0.75, error_m(k, true));
            }
        }
    }
    record.spread_dropped = spread_dropped;
    record.uncertain_dropped = uncertain_dropped;
    record.far_side_observed = far_side_observed;
    record.new_points = out.positions.len();
    record.accepted = true;
    record.reason = "ok".into();
    (
        out.into_cloud(window.instance_id, provenance),
        record,
        left_out,
    )
}

/// Each generated point's expected error for the planners, by crop pixel and side: the
/// completer's own estimate (NaN: none) through the fit's scale `metres`, combined with the
/// fit's residual scale `fit_m`, or `stated_m` without one.
fn point_error(
    estimate: Option<&deocc_completion::ExpectedDepthError>,
    metres: f32,
    fit_m: f32,
    stated_m: f32,
) -> impl Fn(usize, bool) -> f32 + '_ {
    let fit_m = fit_m.max(0.0);
    move |k: usize, far: bool| -> f32 {
        estimate
            .and_then(|e| (if far { &e.far } else { &e.near }).get(k).copied())
            .filter(|x| x.is_finite())
            .map_or(stated_m, |x| (x * metres).hypot(fit_m))
    }
}

/// A completion's record before fusion: nothing accepted yet.
fn new_record(
    window: &CropWindow,
    completer: &str,
    visible_px: usize,
    amodal_px: usize,
) -> CompletionRecord {
    CompletionRecord {
        visible_px,
        amodal_px,
        metric_scale_m: window.metric_scale_m,
        ..CompletionRecord::pending(window.instance_id, window.view, completer, String::new())
    }
}

/// The completer's relative depth fitted to the observed depth over the visible pixels (Huber
/// scale and shift), and why it is refused if it is: a poor fit would put generated geometry at
/// the wrong depth, so the completion is rejected rather than allowed to pollute the cloud.
fn fit_to_observed(
    vis: &[usize],
    completion: &CropCompletion,
    window: &CropWindow,
) -> (Option<deocc_geometry::robust::AffineFit>, Option<String>) {
    let x: Vec<f32> = vis.iter().map(|&k| completion.depth[k]).collect();
    let y: Vec<f32> = vis.iter().map(|&k| window.observed_depth_m[k]).collect();
    let fit = match huber_affine_fit(&x, &y, &HuberOptions::default()) {
        Ok(f) => f,
        Err(e) => return (None, Some(format!("depth fit failed: {e}"))),
    };
    if fit.alpha <= 0.0 || fit.inlier_fraction < MIN_FIT_INLIERS || fit.scale > MAX_FIT_RESIDUAL_M {
        let why = format!(
            "poor depth fit (alpha {:.3}, inliers {:.2}, residual scale {:.3} m)",
            fit.alpha, fit.inlier_fraction, fit.scale
        );
        return (Some(fit), Some(why));
    }
    (Some(fit), None)
}

/// The far side's thickness caps: metres (infinite when off), and per pixel the silhouette-
/// relative cap when it is on.
fn thickness_caps(
    opts: &FuseOptions<'_>,
    completion: &CropCompletion,
    window: &CropWindow,
) -> (f32, Option<Vec<f32>>) {
    let max_thick = if opts.max_thickness_m > 0.0 {
        opts.max_thickness_m
    } else {
        f32::INFINITY
    };
    let run_cap = (opts.max_thickness_per_width > 0.0).then(|| {
        row_run_widths_m(&completion.amodal, window.resolution, window.metric_scale_m)
            .into_iter()
            .map(|w| w * opts.max_thickness_per_width)
            .collect()
    });
    (max_thick, run_cap)
}

/// Generated points as they are made: position, colour (shaded), the completer's probability.
#[derive(Default)]
struct Emitted {
    positions: Vec<nalgebra::Point3<f32>>,
    colors: Vec<[u8; 3]>,
    confidence: Vec<f32>,
    expected_error: Vec<f32>,
}

impl Emitted {
    #[allow(clippy::too_many_arguments)]
    fn push(
        &mut self,
        window: &CropWindow,
        frame: &Frame,
        completion: &CropCompletion,
        k: usize,
        z: f32,
        shade: f32,
        error_m: f32,
    ) {
        self.expected_error.push(error_m);
        let (u, v) = window.pixel_centre(k);
        let p_cam = frame.camera.intrinsics.unproject(u, v, z);
        self.positions
            .push(frame.camera.world_from_camera.transform_point(&p_cam));
        self.colors.push(std::array::from_fn(|c| {
            (completion.rgb[3 * k + c] as f32 * shade) as u8
        }));
        self.confidence.push(
            completion
                .mask_probability
                .get(k)
                .copied()
                .unwrap_or(0.5)
                .clamp(0.0, 1.0),
        );
    }

    fn into_cloud(self, instance_id: u16, provenance: Provenance) -> PointCloud {
        let len = self.positions.len();
        PointCloud {
            positions: self.positions,
            colors: Some(self.colors),
            instance: Some(vec![instance_id as u32; len]),
            generated: Some(vec![provenance.code(); len]),
            confidence: Some(self.confidence),
            expected_error: Some(self.expected_error),
            normals: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::median_within;

    /// The median removes a lone spike and keeps a step; pixels outside the mask neither change
    /// nor vote.
    #[test]
    fn the_median_removes_spikes_keeps_steps_and_reads_only_the_mask() {
        let r = 7;
        // Left 4 columns at 1, the rest at 2 (a step), one spike at (3, 1), a masked-out column 6
        // at 100.
        let mut values: Vec<f32> = (0..r * r)
            .map(|k| match k % r {
                6 => 100.0,
                u if u < 4 => 1.0,
                _ => 2.0,
            })
            .collect();
        values[3 * r + 1] = 50.0;
        let mask: Vec<bool> = (0..r * r).map(|k| k % r != 6).collect();
        let out = median_within(&values, &mask, r, 1);
        assert_eq!(out[3 * r + 1], 1.0, "spike kept");
        for v in 1..r - 1 {
            assert_eq!(out[v * r], 1.0);
            assert_eq!(
                out[v * r + 5],
                2.0,
                "row {v}: {:?}",
                &out[v * r..(v + 1) * r]
            );
            assert_eq!(out[v * r + 6], 100.0, "outside the mask changed");
        }
        assert_eq!(median_within(&values, &mask, r, 0), values);
    }
}

#[cfg(test)]
mod seen_elsewhere_tests {
    use deocc_completion::{CropCompletion, Provenance};
    use deocc_geometry::camera::{Camera, Intrinsics};
    use deocc_geometry::DepthMap;
    use deocc_io::scene::Frame;

    use super::{fuse_completion, fuse_completion_detailed, FuseOptions};
    use crate::crops::CropWindow;

    /// An 8x8 view: the object's left half visible (depth 1 m + 1 cm a column), its right half
    /// behind an occluder at 0.5 m; the crop is the whole image, one relative unit a metre.
    fn setup() -> (CropWindow, Vec<bool>, CropCompletion, Frame) {
        let r = 8;
        let visible: Vec<bool> = (0..r * r).map(|k| k % r < 4).collect();
        let near = |k: usize| 1.0 + 0.01 * (k % r) as f32;
        let observed: Vec<f32> = (0..r * r)
            .map(|k| if visible[k] { near(k) } else { 0.5 })
            .collect();
        let window = CropWindow {
            instance_id: 1,
            view: 0,
            x0: 0.0,
            y0: 0.0,
            side: r as f32,
            resolution: r,
            observed_depth_m: observed.clone(),
            source_pixel: (0..r * r).map(Some).collect(),
            metric_scale_m: 1.0,
            median_depth_m: 1.0,
        };
        let completion = CropCompletion {
            amodal: vec![true; r * r],
            mask_probability: vec![1.0; r * r],
            rgb: vec![100; 3 * r * r],
            depth: (0..r * r).map(|k| near(k) - 1.0).collect(),
            back_depth: (0..r * r).map(|k| near(k) - 1.0 + 0.055).collect(),
            expected_error: None,
        };
        let frame = Frame {
            name: "f".into(),
            camera: Camera {
                intrinsics: Intrinsics::new(8.0, 8.0, 4.0, 4.0, 8, 8).unwrap(),
                world_from_camera: nalgebra::Isometry3::identity(),
            },
            rgb: image::RgbImage::new(8, 8),
            depth: DepthMap::new(8, 8, observed).unwrap(),
            instances: None,
        };
        (window, visible, completion, frame)
    }

    /// The setup's completion fused as a model's, and its record.
    fn fuse_model_recorded(
        (window, visible, completion, frame): &(CropWindow, Vec<bool>, CropCompletion, Frame),
        opts: &FuseOptions<'_>,
    ) -> (deocc_geometry::PointCloud, crate::report::CompletionRecord) {
        fuse_completion(
            window,
            visible,
            completion,
            frame,
            "t",
            Provenance::Model,
            opts,
        )
    }

    /// The setup's completion fused as a model's.
    fn fuse_model(
        setup: &(CropWindow, Vec<bool>, CropCompletion, Frame),
        opts: &FuseOptions<'_>,
    ) -> deocc_geometry::PointCloud {
        fuse_model_recorded(setup, opts).0
    }

    /// The setup's completion fused as a model's, with the default options changed by `set`.
    fn fuse_model_with(
        setup: &(CropWindow, Vec<bool>, CropCompletion, Frame),
        set: impl Fn(&mut FuseOptions<'static>),
    ) -> deocc_geometry::PointCloud {
        let mut opts = FuseOptions::default();
        set(&mut opts);
        fuse_model(setup, &opts)
    }

    /// Where another frame saw the object, fusion places no near-side point (that frame's point
    /// is in the cloud) but puts the far side behind the observed one.
    #[test]
    fn no_near_side_point_where_another_frame_saw_the_object() {
        let setup = setup();
        let completion = &setup.2;
        let fuse = |seen: Option<&[f32]>| {
            fuse_model(
                &setup,
                &FuseOptions {
                    seen_elsewhere: seen,
                    ..Default::default()
                },
            )
        };
        let alone = fuse(None);
        // Hidden pixel (row 3, column 6) seen by another frame 2 cm nearer than generated.
        let p = 3 * 8 + 6;
        let mut seen = vec![f32::INFINITY; 64];
        seen[p] = completion.depth[p] - 0.02;
        let with = fuse(Some(&seen));
        // 32 visible pixels give far sides, 32 hidden ones near and far sides: one near side
        // fewer with the other frame's observation.
        assert_eq!(alone.len(), 32 + 64);
        assert_eq!(with.len(), alone.len() - 1);
        let z = |c: &deocc_geometry::PointCloud| -> Vec<f32> {
            c.positions.iter().map(|q| q.z).collect()
        };
        let generated_near = 1.0 + 0.01 * 6.0;
        let at = |zs: &[f32], d: f32| zs.iter().filter(|&&x| (x - d).abs() < 1e-4).count();
        // Column 6 has a near point at 1.06 m in each of 8 rows; with the observation, 7.
        assert_eq!(at(&z(&alone), generated_near), 8);
        assert_eq!(at(&z(&with), generated_near), 7);
        // The far side stays where it was (5.5 cm behind the generated near side).
        assert_eq!(at(&z(&with), generated_near + 0.055), 8);
    }

    /// Where another frame observed the object's back behind the near side, no far-side point
    /// is generated (counted); an observation in front of the near side is no back, and the far
    /// side stays.
    #[test]
    fn no_far_side_point_where_another_frame_saw_the_back() {
        let setup = setup();
        let completion = &setup.2;
        let fuse = |behind: Option<&[f32]>| {
            fuse_model_recorded(
                &setup,
                &FuseOptions {
                    seen_behind: behind,
                    ..Default::default()
                },
            )
        };
        let (alone, rec) = fuse(None);
        assert_eq!(alone.len(), 32 + 64);
        assert_eq!(rec.far_side_observed, 0);
        let mut behind = vec![f32::INFINITY; 64];
        // Visible pixel (row 2, column 1): its back seen 4 cm behind its observed front.
        let visible_px = 2 * 8 + 1;
        behind[visible_px] = completion.depth[visible_px] + 0.04;
        // Hidden pixel (row 5, column 6): its back seen 3 cm behind the generated near side.
        let hidden_px = 5 * 8 + 6;
        behind[hidden_px] = completion.depth[hidden_px] + 0.03;
        // Hidden pixel (row 6, column 6): an "observation" in front of the near side is no back.
        behind[6 * 8 + 6] = completion.depth[6 * 8 + 6] - 0.03;
        let (with, rec) = fuse(Some(&behind));
        assert_eq!(rec.far_side_observed, 2);
        assert_eq!(with.len(), alone.len() - 2);
        // The two far sides are gone (5.5 cm behind their near sides), the near side stays.
        let has = |c: &deocc_geometry::PointCloud, z: f32| {
            c.positions.iter().any(|q| (q.z - z).abs() < 1e-4)
        };
        let near_hidden = 1.0 + completion.depth[hidden_px];
        assert!(has(&with, near_hidden));
        let count = |c: &deocc_geometry::PointCloud, z: f32| {
            c.positions
                .iter()
                .filter(|q| (q.z - z).abs() < 1e-4)
                .count()
        };
        // Column 6's far sides sit at 1.115 m in 8 rows; one is observed.
        assert_eq!(count(&alone, near_hidden + 0.055), 8);
        assert_eq!(count(&with, near_hidden + 0.055), 7);
    }

    /// The silhouette-relative cap drops the far side of a narrow row run (a leg two pixels
    /// wide, 0.25 m here: a cap of 2.5 cm at 0.1 under its 5.5 cm back) and keeps the wide
    /// rows' (1 m: a 10 cm cap); 0 is off.
    #[test]
    fn far_sides_deeper_than_the_row_run_allows_are_left_out() {
        let (window, visible, mut completion, frame) = setup();
        // Row 7: only columns 0 and 1 belong to the object.
        for u in 2..8 {
            completion.amodal[7 * 8 + u] = false;
        }
        let setup = (window, visible, completion, frame);
        let fuse = |ratio: f32| fuse_model_with(&setup, |o| o.max_thickness_per_width = ratio);
        let off = fuse(0.0);
        // 7 full rows (4 visible: far side; 4 hidden: near and far) and row 7's 2 visible.
        assert_eq!(off.len(), 7 * 12 + 2);
        let capped = fuse(0.1);
        assert_eq!(capped.len(), off.len() - 2);
        // Row 7 (its pixel centres at y = 0.4375 z) keeps no point.
        let bottom =
            |c: &deocc_geometry::PointCloud| c.positions.iter().filter(|p| p.y > 0.4 * p.z).count();
        assert_eq!(bottom(&off), 2);
        assert_eq!(bottom(&capped), 0);
        // A ratio under 5.5 cm a metre leaves out every far side.
        assert_eq!(fuse(0.05).len(), 7 * 4);
    }

    /// The row runs: widths of contiguous mask pixels, infinite outside the mask.
    #[test]
    fn row_runs_are_the_contiguous_mask_widths() {
        let mask = [
            true, true, false, true, //
            false, false, false, false, //
            true, true, true, true, //
            false, true, false, false,
        ];
        let w = super::row_run_widths_m(&mask, 4, 2.0);
        let expect = [
            1.0,
            1.0,
            f32::INFINITY,
            0.5, //
            f32::INFINITY,
            f32::INFINITY,
            f32::INFINITY,
            f32::INFINITY, //
            2.0,
            2.0,
            2.0,
            2.0, //
            f32::INFINITY,
            0.5,
            f32::INFINITY,
            f32::INFINITY,
        ];
        assert_eq!(w, expect);
    }

    /// A revealed pixel below the confidence floor generates neither side; visible pixels keep
    /// their far side whatever their probability, and a floor of 0 keeps everything.
    #[test]
    fn revealed_pixels_below_the_confidence_floor_generate_nothing() {
        let (window, visible, mut completion, frame) = setup();
        // Column 6's pixels (hidden) and column 1's (visible) are unsure.
        for k in 0..64 {
            if k % 8 == 6 || k % 8 == 1 {
                completion.mask_probability[k] = 0.6;
            }
        }
        let setup = (window, visible, completion, frame);
        let fuse = |floor: f32| fuse_model_with(&setup, |o| o.min_revealed_confidence = floor);
        let all = fuse(0.0);
        let strict = fuse(0.9);
        assert_eq!(all.len(), 32 + 64);
        // Column 6: 8 near and 8 far points gone; column 1's far sides stay.
        assert_eq!(strict.len(), all.len() - 16);
        let confidence = strict.confidence.as_deref().unwrap();
        assert_eq!(confidence.iter().filter(|&&c| c < 0.9).count(), 8);
    }

    /// Points the completer expects further off than the limit (its relative error times the
    /// fit's scale, here 1 m a unit) are not generated: a revealed pixel's near side takes its
    /// far side with it, a visible pixel loses only its far side; no limit, no estimate or a
    /// loose limit keep everything.
    #[test]
    fn points_expected_too_far_off_are_left_out() {
        let (window, visible, mut completion, frame) = setup();
        let base = fuse_model(
            &(
                window.clone(),
                visible.clone(),
                completion.clone(),
                frame.clone(),
            ),
            &Default::default(),
        );
        // 1 cm expected everywhere; 4 cm on the near side of column 6 (hidden) and on the far
        // side of column 1 (visible) and of column 5 (hidden).
        let mut near = vec![0.01; 64];
        let mut far = vec![0.01; 64];
        for k in 0..64 {
            match k % 8 {
                6 => near[k] = 0.04,
                1 | 5 => far[k] = 0.04,
                _ => {}
            }
        }
        completion.expected_error = Some(deocc_completion::ExpectedDepthError { near, far });
        let setup = (window, visible, completion, frame);
        let fuse = |limit: f32| {
            let opts = FuseOptions {
                max_expected_error_m: limit,
                ..Default::default()
            };
            fuse_completion(
                &setup.0,
                &setup.1,
                &setup.2,
                &setup.3,
                "t",
                Provenance::Model,
                &opts,
            )
        };
        let (off, off_record) = fuse(0.0);
        let (strict, record) = fuse(0.02);
        let (loose, _) = fuse(0.05);
        assert_eq!(base.len(), 32 + 64);
        assert_eq!(off.len(), base.len());
        assert_eq!(off_record.uncertain_dropped, 0);
        assert_eq!(loose.len(), base.len());
        // Column 6: 8 near and (with them) 8 far points; columns 1 and 5: 8 far points each.
        assert_eq!(strict.len(), base.len() - 32);
        assert_eq!(record.uncertain_dropped, 8 + 8 + 8);
        assert_eq!(record.new_points, strict.len());

        // The pixels left out are named; a fallback completion fused over exactly them fills
        // what the gate took out (here the same depths, as a completer without an estimate).
        let (_, _, left_out) = fuse_completion_detailed(
            &setup.0,
            &setup.1,
            &setup.2,
            &setup.3,
            "t",
            Provenance::Model,
            &FuseOptions {
                max_expected_error_m: 0.02,
                ..Default::default()
            },
        );
        let col = |m: &[bool], c: &[usize]| (0..64).all(|k| m[k] == c.contains(&(k % 8)));
        assert!(col(&left_out.near, &[6]), "{:?}", left_out.near);
        assert!(col(&left_out.far, &[1, 5, 6]), "{:?}", left_out.far);
        assert_eq!(left_out.count(), 24);
        let mut fallback = setup.2.clone();
        fallback.expected_error = None;
        let (filled, filled_record) = fuse_completion(
            &setup.0,
            &setup.1,
            &fallback,
            &setup.3,
            "rules",
            Provenance::Rules,
            &FuseOptions {
                max_expected_error_m: 0.02,
                only: Some(&left_out),
                ..Default::default()
            },
        );
        assert_eq!(filled.len(), 32);
        assert_eq!(filled_record.uncertain_dropped, 0);
        let mut both: Vec<[i64; 3]> = strict
            .positions
            .iter()
            .chain(&filled.positions)
            .map(|p| [p.x, p.y, p.z].map(|v| (v * 1e5).round() as i64))
            .collect();
        let mut all: Vec<[i64; 3]> = base
            .positions
            .iter()
            .map(|p| [p.x, p.y, p.z].map(|v| (v * 1e5).round() as i64))
            .collect();
        both.sort_unstable();
        all.sort_unstable();
        assert_eq!(both, all, "gate plus fallback is the ungated cloud");
    }

    /// Each generated point carries an expected error: the completer's own through the fit's
    /// scale (near or far side, as estimated; the exact fit adds nothing), the stated one where
    /// the completion has none or a pixel's estimate is NaN.
    #[test]
    fn generated_points_carry_their_expected_error() {
        let (window, visible, mut completion, frame) = setup();
        let stated = FuseOptions {
            stated_error_m: 0.02,
            ..Default::default()
        };
        let without = fuse_model(
            &(
                window.clone(),
                visible.clone(),
                completion.clone(),
                frame.clone(),
            ),
            &stated,
        );
        let e = without.expected_error.as_deref().unwrap();
        assert_eq!(e.len(), without.len());
        assert!(e.iter().all(|&x| x == 0.02), "{e:?}");
        let mut near = vec![0.01; 64];
        let mut far = vec![0.01; 64];
        for k in 0..64 {
            if k % 8 == 5 {
                far[k] = 0.04;
            }
            if k % 8 == 7 {
                near[k] = f32::NAN;
            }
        }
        completion.expected_error = Some(deocc_completion::ExpectedDepthError { near, far });
        let with = fuse_model(&(window, visible, completion, frame), &stated);
        assert_eq!(with.len(), without.len());
        let e = with.expected_error.as_deref().unwrap();
        // Points are pushed pixel by pixel: a hidden pixel's near side, then its far side.
        let (mut big, mut stated_n, mut small) = (0, 0, 0);
        for &x in e {
            if (x - 0.04).abs() < 1e-4 {
                big += 1;
            } else if x == 0.02 {
                stated_n += 1;
            } else if (x - 0.01).abs() < 1e-4 {
                small += 1;
            }
        }
        assert_eq!(big, 8, "column 5's far sides: {e:?}");
        assert_eq!(stated_n, 8, "column 7's near sides have no estimate: {e:?}");
        assert_eq!(big + stated_n + small, e.len(), "{e:?}");
    }
}
