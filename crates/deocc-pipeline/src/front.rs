//! The front half: a scene as read, made ready for the run. One function for every caller (the
//! CLI's `run`, `batch`, `grasp` and `place`, the service, Python, ROS 2), in this order:
//!
//! 0. frames taken from one pose (a burst) become one frame ([`crate::burst`]);
//! 1. a learned depth source (when the caller has one) fills the pixels the sensor did not
//!    measure ([`crate::depth::fill_scene_depth`]);
//! 2. the depth front end cleans every frame in units of its own noise ([`crate::depth_clean`]);
//! 3. the rims of given instance masks whose depth belongs to something else lose their
//!    instance ([`crate::mask_rims`]);
//! 4. the holes of given instance masks take their own instance's depth
//!    ([`crate::mask_holes`]);
//! 5. frames without poses are registered ([`crate::registration::register_unposed`]);
//! 6. frames without instance maps (every frame with `segment`) are segmented
//!    ([`crate::instances::ensure_instances`]).
//!
//! Then [`crate::run_prepared`] runs the pipeline and puts what the front half did into the
//! report.

use deocc_io::scene::SceneInput;

use crate::depth::{DepthFillOptions, DepthFillReport, DepthSource};
use crate::depth_clean::{clean_depth, DepthCleanRecord};
use crate::mask_holes::{fill_mask_holes, MaskHoleRecord};
use crate::mask_rims::{unlabel_mask_rims, MaskRimRecord};
use crate::segment::Segmenter;
use crate::{PipelineError, PipelineOptions, Registration};

/// What the front half did.
#[derive(Debug, Clone, Default)]
pub struct Prepared {
    pub registration: Registration,
    pub burst: crate::burst::BurstRecord,
    pub depth_fill: Vec<DepthFillReport>,
    pub depth_clean: Vec<DepthCleanRecord>,
    /// One record per frame (all zero for a frame without a given map, or with `segment`).
    pub mask_rims: Vec<MaskRimRecord>,
    /// One record per frame, as `mask_rims`.
    pub mask_holes: Vec<MaskHoleRecord>,
    /// Instances the segmenter found across views (0 when every frame came with masks).
    pub segmented: usize,
}

/// Makes `scene` ready for the run (see the module docs).
pub fn prepare(
    scene: &mut SceneInput,
    opts: &PipelineOptions,
    depth: Option<&dyn DepthSource>,
    segmenter: &dyn Segmenter,
    segment: bool,
) -> Result<Prepared, PipelineError> {
    prepare_observed(scene, opts, depth, segmenter, segment, &crate::Unobserved)
}

/// [`prepare`], telling `observer` of the depth front end before each frame (so that Ctrl-C,
/// a client gone or a deadline stops a long front half too, not only the run after it).
pub fn prepare_observed(
    scene: &mut SceneInput,
    opts: &PipelineOptions,
    depth: Option<&dyn DepthSource>,
    segmenter: &dyn Segmenter,
    segment: bool,
    observer: &dyn crate::Observer,
) -> Result<Prepared, PipelineError> {
    opts.validate()?;
    crate::enter(observer, "burst")?;
    let burst = crate::burst::fuse_bursts(scene, &opts.burst);
    let depth_fill = match depth {
        Some(source) => {
            crate::depth::fill_scene_depth(scene, source, &DepthFillOptions::default())?
        }
        None => Vec::new(),
    };
    let mut depth_clean = Vec::with_capacity(scene.frames.len());
    for f in &mut scene.frames {
        crate::enter(observer, "depth_clean")?;
        depth_clean.push(clean_depth(&mut f.depth, &opts.depth_clean));
    }
    if segment {
        for f in &mut scene.frames {
            f.instances = None;
        }
    }
    let mask_rims = scene
        .frames
        .iter_mut()
        .map(|f| unlabel_mask_rims(f, &opts.mask_rims))
        .collect();
    let mask_holes = scene
        .frames
        .iter_mut()
        .map(|f| fill_mask_holes(f, &opts.mask_holes))
        .collect();
    let registration = crate::registration::register_unposed(scene)?;
    let segmented = crate::instances::ensure_instances(scene, segmenter)?;
    Ok(Prepared {
        registration,
        burst,
        depth_fill,
        depth_clean,
        mask_rims,
        mask_holes,
        segmented,
    })
}
