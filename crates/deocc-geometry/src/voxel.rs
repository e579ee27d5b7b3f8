//! Voxel-grid downsampling and provenance-preserving fusion of clouds.

use std::collections::HashSet;

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::cloud::PointCloud;
use crate::error::{GeometryError, Result};

/// Integer voxel coordinates of a point on a grid with its corner at `origin`, computed in f64 as
/// Open3D does, so both form exactly the same voxels.
fn voxel_key(p: &Point3<f32>, origin: &Point3<f64>, voxel_m: f64) -> [i32; 3] {
    [
        ((p.x as f64 - origin.x) / voxel_m).floor() as i32,
        ((p.y as f64 - origin.y) / voxel_m).floor() as i32,
        ((p.z as f64 - origin.z) / voxel_m).floor() as i32,
    ]
}

fn check_voxel(voxel_m: f64) -> Result<f64> {
    if voxel_m.is_finite() && voxel_m > 0.0 {
        Ok(voxel_m)
    } else {
        Err(GeometryError::InvalidArgument(format!(
            "voxel size must be positive and finite, got {voxel_m}"
        )))
    }
}

/// One point per occupied voxel: the mean position (and mean colour and normal, where present),
/// the most frequent instance id, and "generated" only if every point of the voxel was generated:
/// an observed point always wins over a generated one.
///
/// The grid is anchored as Open3D anchors it (min bound minus half a voxel), so the same voxels
/// are formed. Output order is by voxel key, deterministic.
pub fn voxel_downsample(cloud: &PointCloud, voxel_m: f64) -> Result<PointCloud> {
    let voxel = check_voxel(voxel_m)?;
    let Some((lo, _)) = cloud.bounds() else {
        return Ok(PointCloud::default());
    };
    let origin = lo.cast::<f64>() - Vector3::repeat(voxel * 0.5);
    let mut keyed: Vec<([i32; 3], u32)> = cloud
        .positions
        .par_iter()
        .enumerate()
        .map(|(i, p)| (voxel_key(p, &origin, voxel), i as u32))
        .collect();
    keyed.par_sort_unstable();
    // Group boundaries.
    let mut starts = vec![0usize];
    for i in 1..keyed.len() {
        if keyed[i].0 != keyed[i - 1].0 {
            starts.push(i);
        }
    }
    starts.push(keyed.len());
    let groups: Vec<&[([i32; 3], u32)]> = starts.windows(2).map(|w| &keyed[w[0]..w[1]]).collect();

    let positions = groups
        .par_iter()
        .map(|g| {
            let s = g.iter().fold(Vector3::<f64>::zeros(), |a, (_, i)| {
                a + cloud.positions[*i as usize].coords.cast::<f64>()
            });
            Point3::from((s / g.len() as f64).cast::<f32>())
        })
        .collect();
    let colors = cloud.colors.as_ref().map(|c| {
        groups
            .par_iter()
            .map(|g| {
                let mut s = [0u32; 3];
                for (_, i) in g.iter() {
                    for (acc, v) in s.iter_mut().zip(c[*i as usize]) {
                        *acc += v as u32;
                    }
                }
                let n = g.len() as u32;
                s.map(|v| ((v + n / 2) / n) as u8)
            })
            .collect()
    });
    let normals = cloud.normals.as_ref().map(|nrm| {
        groups
            .par_iter()
            .map(|g| {
                let s = g
                    .iter()
                    .fold(Vector3::<f32>::zeros(), |a, (_, i)| a + nrm[*i as usize]);
                s.try_normalize(1e-12).unwrap_or_default()
            })
            .collect()
    });
    let generated = cloud.generated.as_ref().map(|gen| {
        groups
            .par_iter()
            .map(|g| g.iter().map(|(_, i)| gen[*i as usize]).min().unwrap_or(0))
            .collect()
    });
    let instance = cloud.instance.as_ref().map(|ids| {
        groups
            .par_iter()
            .map(|g| {
                let mut v: Vec<u32> = g.iter().map(|(_, i)| ids[*i as usize]).collect();
                v.sort_unstable();
                let mut best = (v[0], 0usize);
                let mut run = (v[0], 0usize);
                for &x in &v {
                    run = if x == run.0 { (x, run.1 + 1) } else { (x, 1) };
                    if run.1 > best.1 {
                        best = run;
                    }
                }
                best.0
            })
            .collect()
    });
    Ok(PointCloud {
        positions,
        colors,
        normals,
        instance,
        generated,
    })
}

/// Adds `generated` points to `observed` without duplicating surfaces: generated points are
/// voxel-downsampled, and any that falls into a voxel already holding an observed point is dropped
/// (the sensor wins). Observed points are kept as they are; the result carries the provenance code
/// ([`crate::Provenance`]): 0 for observed points, the generated points' own code, or
/// [`crate::Provenance::Model`] for generated points that carry none (or carry 0).
pub fn fuse_generated(
    observed: &PointCloud,
    generated: &PointCloud,
    voxel_m: f64,
) -> Result<PointCloud> {
    let voxel = check_voxel(voxel_m)?;
    let mut out = observed.clone();
    if out.generated.is_none() {
        out.generated = Some(vec![0; out.len()]);
    }
    if generated.is_empty() {
        return Ok(out);
    }
    let origin = Point3::<f64>::origin();
    let occupied: HashSet<[i32; 3]> = observed
        .positions
        .iter()
        .map(|p| voxel_key(p, &origin, voxel))
        .collect();
    let mut gen = generated.clone();
    // A generated point keeps its provenance code; one without (or with the observed code) is Model.
    gen.generated = Some(match &generated.generated {
        Some(g) => g.iter().map(|&x| x.max(1)).collect(),
        None => vec![1; gen.len()],
    });
    let gen = voxel_downsample(&gen, voxel_m)?;
    let fresh = gen.filter(|i| !occupied.contains(&voxel_key(&gen.positions[i], &origin, voxel)));
    out.append(&fresh);
    Ok(out)
}
