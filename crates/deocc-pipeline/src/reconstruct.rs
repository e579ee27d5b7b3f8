//! Stage: reconstruction. Every frame's depth back-projected into one observed cloud with colour
//! and instance ids, voxel de-duplicated across views. Frames are fused into the voxel grid one
//! at a time (`VoxelGrid`), so memory holds one frame's points and the occupied voxels, whatever
//! the number of views; the result is the same, bit for bit, as voxel-downsampling all frames'
//! points at once.

use deocc_geometry::depth::backproject;
use deocc_geometry::voxel::VoxelGrid;
use deocc_geometry::PointCloud;
use deocc_io::scene::{Frame, SceneInput};
use nalgebra::Point3;

use crate::PipelineError;

/// One frame's observed points with colour, instance id and the observed provenance.
fn frame_cloud(f: &Frame) -> Result<PointCloud, PipelineError> {
    let (mut cloud, pixels) = backproject(&f.depth, &f.camera)?;
    let rgb = f.rgb.as_raw();
    cloud.colors = Some(
        pixels
            .iter()
            .map(|&i| {
                let i = 3 * i as usize;
                [rgb[i], rgb[i + 1], rgb[i + 2]]
            })
            .collect(),
    );
    if let Some(inst) = &f.instances {
        cloud.instance = Some(
            pixels
                .iter()
                .map(|&i| inst.ids[i as usize] as u32)
                .collect(),
        );
    }
    cloud.generated = Some(vec![0; cloud.len()]);
    Ok(cloud)
}

/// The observed cloud of a scene at `voxel_m` (provenance: observed).
pub fn reconstruct(scene: &SceneInput, voxel_m: f64) -> Result<PointCloud, PipelineError> {
    // The grid is anchored at the min bound of every frame's points: a first pass finds it.
    let mut lo: Option<Point3<f32>> = None;
    for f in &scene.frames {
        let (cloud, _) = backproject(&f.depth, &f.camera)?;
        if let Some((a, _)) = cloud.bounds() {
            lo = Some(lo.map_or(a, |l| l.inf(&a)));
        }
    }
    let Some(lo) = lo else {
        return Ok(PointCloud::default());
    };
    let mut grid = VoxelGrid::new(&lo, voxel_m)?;
    for f in &scene.frames {
        grid.add(&frame_cloud(f)?)?;
    }
    Ok(grid.into_cloud())
}
