//! Stage: reconstruction. Every frame's depth back-projected into one observed cloud with colour
//! and instance ids, voxel de-duplicated across views.

use deocc_geometry::depth::backproject;
use deocc_geometry::voxel::voxel_downsample;
use deocc_geometry::PointCloud;
use deocc_io::scene::SceneInput;

use crate::PipelineError;

/// The observed cloud of a scene at `voxel_m` (provenance: observed).
pub fn reconstruct(scene: &SceneInput, voxel_m: f64) -> Result<PointCloud, PipelineError> {
    let mut all = PointCloud::default();
    for f in &scene.frames {
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
        all.append(&cloud);
    }
    Ok(voxel_downsample(&all, voxel_m)?)
}
