//! Stage: carving. Multi-view free-space carving of generated geometry.
//!
//! A point that no input view sees must be hidden in every view: each view with a depth
//! measurement where the point projects must see something in front of it. If a view measures the
//! point's own depth, the point is observed already (a generated copy adds nothing); if a view
//! measures beyond it, the sensor saw through empty space there and the point is wrong. The
//! completion's own view is checked at fusion time ([`crate::fuse::fuse_completion`]); this
//! test adds the other views, which a segmenter's mistakes (a mask spanning two objects, a
//! completion running into the background) most often contradict.

use deocc_geometry::camera::Projector;
use deocc_geometry::PointCloud;
use deocc_io::scene::SceneInput;
use nalgebra::Point3;
use rayon::prelude::*;

/// Depth tolerance of the test at distance `z` (sensor noise grows with range): a point counts as
/// hidden behind a measurement only if it is this much farther than it.
pub fn hidden_tolerance_m(z: f32) -> f32 {
    0.02 + 0.01 * z
}

/// What the views say of a point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Evidence {
    /// Every view with a measurement there sees something in front of it (and one view does).
    Hidden,
    /// Some view measures the point's own depth (within [`hidden_tolerance_m`]) and none sees
    /// through it: the sensor agrees with it.
    Observed,
    /// Some view measures beyond it: the sensor saw empty space where the point is.
    SeenThrough,
    /// No view has a measurement where it projects.
    Unmeasured,
}

/// What the views of `scene` say of `p` (see [`Evidence`]).
pub fn evidence(p: &Point3<f32>, scene: &SceneInput, projectors: &[Projector]) -> Evidence {
    let mut out = Evidence::Unmeasured;
    for (f, proj) in scene.frames.iter().zip(projectors) {
        let Some((x, y, z)) = proj.project(p) else {
            continue;
        };
        let (w, h) = (f.depth.width() as f32, f.depth.height() as f32);
        if x < 0.0 || y < 0.0 || x >= w || y >= h {
            continue;
        }
        let d = f.depth.data()[y as usize * w as usize + x as usize];
        if d <= 0.0 {
            continue;
        }
        let tol = hidden_tolerance_m(z);
        if d > z + tol {
            return Evidence::SeenThrough;
        }
        if d >= z - tol {
            out = Evidence::Observed;
        } else if out == Evidence::Unmeasured {
            out = Evidence::Hidden;
        }
    }
    out
}

/// Whether `p` lies in front of some view's camera and inside its image: a point no view could
/// have measured is out of every frame, not a drop-out (see [`Evidence::Unmeasured`]).
pub fn in_a_frame(p: &Point3<f32>, scene: &SceneInput, projectors: &[Projector]) -> bool {
    scene.frames.iter().zip(projectors).any(|(f, proj)| {
        proj.project(p).is_some_and(|(x, y, _)| {
            x >= 0.0 && y >= 0.0 && x < f.depth.width() as f32 && y < f.depth.height() as f32
        })
    })
}

/// Every view that has a measurement where `p` projects sees something in front of it, and at
/// least one view does.
pub fn hidden_in_views(p: &Point3<f32>, scene: &SceneInput, projectors: &[Projector]) -> bool {
    evidence(p, scene, projectors) == Evidence::Hidden
}

/// The points of `cloud` hidden in every view of `scene` (see [`hidden_in_views`]), and how many
/// were removed.
pub fn keep_hidden(cloud: &PointCloud, scene: &SceneInput) -> (PointCloud, usize) {
    let projectors: Vec<Projector> = scene.frames.iter().map(|f| f.camera.projector()).collect();
    let keep: Vec<bool> = cloud
        .positions
        .par_iter()
        .map(|p| hidden_in_views(p, scene, &projectors))
        .collect();
    let kept = cloud.filter(|i| keep[i]);
    let removed = cloud.len() - kept.len();
    (kept, removed)
}
