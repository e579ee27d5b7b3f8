//! Stage: the quality gate. A completion is dropped whole, not point by point, when what it
//! generated is unlikely as a whole: the completer itself doubts it (the mean confidence of its
//! points is low) or the views contradict it (a large share of its points lies where some view
//! measured something behind them: the sensor saw empty space there). Points a view measures at
//! their own depth agree with the completion and do not count against it. The depth fit is gated
//! earlier, at fusion ([`crate::fuse`]). Carving ([`crate::carve`]) later removes the single
//! points of the completions the gate lets through that a view sees or sees through.

use deocc_geometry::camera::Projector;
use deocc_geometry::PointCloud;
use deocc_io::scene::SceneInput;
use rayon::prelude::*;

use crate::carve::{evidence, Evidence};

/// What the gate measured of one completion, and its verdict.
#[derive(Debug, Clone, PartialEq)]
pub struct GateVerdict {
    /// Mean confidence of the completion's generated points (1 when it has none).
    pub mean_confidence: f32,
    /// Share of its points some view sees through ([`Evidence::SeenThrough`]).
    pub seen_through_fraction: f32,
    /// Why it is rejected, or `None` when it passes.
    pub rejected: Option<String>,
}

/// Measures one completion's points and judges them against the two limits: rejected when the
/// mean confidence is below `min_mean_confidence` or the seen-through share above
/// `max_seen_through_fraction`.
pub fn gate_completion(
    cloud: &PointCloud,
    scene: &SceneInput,
    projectors: &[Projector],
    min_mean_confidence: f32,
    max_seen_through_fraction: f32,
) -> GateVerdict {
    let n = cloud.len();
    if n == 0 {
        return GateVerdict {
            mean_confidence: 1.0,
            seen_through_fraction: 0.0,
            rejected: None,
        };
    }
    let mean_confidence = cloud.confidence.as_ref().map_or(1.0, |c| {
        (c.iter().map(|&x| f64::from(x)).sum::<f64>() / n as f64) as f32
    });
    let seen_through = cloud
        .positions
        .par_iter()
        .filter(|p| evidence(p, scene, projectors) == Evidence::SeenThrough)
        .count();
    let seen_through_fraction = seen_through as f32 / n as f32;
    let rejected = if mean_confidence < min_mean_confidence {
        Some(format!(
            "mean confidence {mean_confidence:.2} below {min_mean_confidence:.2}"
        ))
    } else if seen_through_fraction > max_seen_through_fraction {
        Some(format!(
            "{:.0}% of its points seen through by the views (limit {:.0}%)",
            100.0 * seen_through_fraction,
            100.0 * max_seen_through_fraction
        ))
    } else {
        None
    };
    GateVerdict {
        mean_confidence,
        seen_through_fraction,
        rejected,
    }
}
