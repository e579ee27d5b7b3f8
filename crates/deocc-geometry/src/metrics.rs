//! Reconstruction metrics as the field's evaluation code computes them (Spann3R, CUT3R, Pi3):
//! accuracy (prediction -> ground truth), completeness (ground truth -> prediction), Chamfer,
//! normal consistency, and precision / recall / F-score at a distance threshold.

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::cell_grid::CellGrid;
use crate::error::{GeometryError, Result};

/// Options of [`reconstruction_metrics`].
#[derive(Debug, Clone, Copy)]
pub struct MetricOptions {
    /// Distance threshold of precision, recall and F-score, in metres (the protocol uses 5 cm).
    pub fscore_threshold_m: f32,
}

impl Default for MetricOptions {
    fn default() -> Self {
        Self {
            fscore_threshold_m: 0.05,
        }
    }
}

/// The figures of one prediction against one ground truth. Distances in metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReconstructionMetrics {
    pub accuracy_mean: f64,
    pub accuracy_median: f64,
    pub completeness_mean: f64,
    pub completeness_median: f64,
    /// (accuracy_mean + completeness_mean) / 2.
    pub chamfer: f64,
    /// Mean |n_gt . n_pred| over both directions; `None` unless both clouds carry normals.
    pub normal_consistency: Option<f64>,
    pub precision: f64,
    pub recall: f64,
    pub fscore: f64,
    pub fscore_threshold_m: f64,
    pub prediction_points: usize,
    pub ground_truth_points: usize,
}

/// Mean and median of distances (f64 accumulation; median of an even count is the mean of the
/// two middle values, as numpy does).
pub fn mean_median(values: &[f32]) -> (f64, f64) {
    if values.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let mean = values.iter().map(|&v| v as f64).sum::<f64>() / values.len() as f64;
    let mut sorted = values.to_vec();
    let n = sorted.len();
    let mid = n / 2;
    let (_, upper, _) = sorted.select_nth_unstable_by(mid, f32::total_cmp);
    let upper = *upper as f64;
    let median = if n % 2 == 1 {
        upper
    } else {
        let lower = sorted[..mid].iter().copied().fold(f32::MIN, f32::max) as f64;
        (lower + upper) / 2.0
    };
    (mean, median)
}

/// Symmetric Chamfer distance: (mean a->b, mean b->a, their average).
pub fn chamfer(a: &[Point3<f32>], b: &[Point3<f32>]) -> Result<(f64, f64, f64)> {
    let grid_a = CellGrid::build(a)?;
    let grid_b = CellGrid::build(b)?;
    let ab = mean_median(&grid_b.nearest_distances(a)).0;
    let ba = mean_median(&grid_a.nearest_distances(b)).0;
    Ok((ab, ba, (ab + ba) / 2.0))
}

/// All metrics of `prediction` against `ground_truth`.
///
/// `gt_subset`, when given, restricts completeness and recall to the ground-truth points where it is
/// true (e.g. the points no input view sees); accuracy and precision still use the whole ground
/// truth, because a predicted point near any true surface is accurate.
pub fn reconstruction_metrics(
    prediction: &[Point3<f32>],
    prediction_normals: Option<&[Vector3<f32>]>,
    ground_truth: &[Point3<f32>],
    ground_truth_normals: Option<&[Vector3<f32>]>,
    gt_subset: Option<&[bool]>,
    options: &MetricOptions,
) -> Result<ReconstructionMetrics> {
    if let Some(s) = gt_subset {
        if s.len() != ground_truth.len() {
            return Err(GeometryError::SizeMismatch {
                what: "ground-truth subset flags",
                expected: ground_truth.len(),
                got: s.len(),
            });
        }
    }
    let acc = CellGrid::build(ground_truth)?.nearest_batch(prediction);
    let gt_queries: Vec<usize> = match gt_subset {
        Some(s) => (0..ground_truth.len()).filter(|&i| s[i]).collect(),
        None => (0..ground_truth.len()).collect(),
    };
    if gt_queries.is_empty() {
        return Err(GeometryError::Empty {
            what: "ground-truth subset",
        });
    }
    let gt_points: Vec<Point3<f32>> = gt_queries.iter().map(|&i| ground_truth[i]).collect();
    let comp = CellGrid::build(prediction)?.nearest_batch(&gt_points);
    let acc_d: Vec<f32> = acc.iter().map(|n| n.distance_sq.sqrt()).collect();
    let comp_d: Vec<f32> = comp.iter().map(|n| n.distance_sq.sqrt()).collect();
    let (accuracy_mean, accuracy_median) = mean_median(&acc_d);
    let (completeness_mean, completeness_median) = mean_median(&comp_d);
    let th = options.fscore_threshold_m;
    let precision = acc_d.iter().filter(|&&d| d < th).count() as f64 / acc_d.len() as f64;
    let recall = comp_d.iter().filter(|&&d| d < th).count() as f64 / comp_d.len() as f64;
    let fscore = if precision + recall > 0.0 {
        2.0 * precision * recall / (precision + recall)
    } else {
        0.0
    };
    let normal_consistency = match (prediction_normals, ground_truth_normals) {
        (Some(pn), Some(gn)) => {
            if pn.len() != prediction.len() || gn.len() != ground_truth.len() {
                return Err(GeometryError::SizeMismatch {
                    what: "normals",
                    expected: prediction.len(),
                    got: pn.len(),
                });
            }
            let nc_acc = acc
                .iter()
                .enumerate()
                .map(|(i, n)| pn[i].dot(&gn[n.index as usize]).abs() as f64)
                .sum::<f64>()
                / acc.len() as f64;
            let nc_comp = comp
                .iter()
                .zip(&gt_queries)
                .map(|(n, &i)| gn[i].dot(&pn[n.index as usize]).abs() as f64)
                .sum::<f64>()
                / comp.len() as f64;
            Some((nc_acc + nc_comp) / 2.0)
        }
        _ => None,
    };
    Ok(ReconstructionMetrics {
        accuracy_mean,
        accuracy_median,
        completeness_mean,
        completeness_median,
        chamfer: (accuracy_mean + completeness_mean) / 2.0,
        normal_consistency,
        precision,
        recall,
        fscore,
        fscore_threshold_m: th as f64,
        prediction_points: prediction.len(),
        ground_truth_points: gt_queries.len(),
    })
}
