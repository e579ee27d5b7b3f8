//! Stage: support. Objects stand on something: an object whose bottom is hidden behind what
//! stands in front of it (a bottle behind a box, of which only the neck shows) is extended down
//! to the surface it stands on.
//!
//! For each completed instance, its points (observed and generated) are taken; the support below
//! it is the highest point of another instance (the table, or its plane fill) under the object's
//! footprint (its box on the ground plane, 2 cm larger), at least 1 cm below the object's lowest
//! point and at most `max_drop_m` below it. The object's lowest 2 cm slice is then copied down in
//! `step_m` steps to just above that support. The copies carry the rules provenance; the carving
//! stage then removes those any view contradicts (where a view sees the table through them).
//! Needs gravity: posed scenes in a z-up world frame (`up` in the options); pose-free input
//! (registered to the first camera) is left as it is.

use std::collections::{BTreeMap, BTreeSet};

use deocc_geometry::{PointCloud, Provenance};
use nalgebra::{Point3, Rotation3, Vector3};

/// Settings of the support stage.
#[derive(Debug, Clone, Copy)]
pub struct SupportOptions {
    pub up: Vector3<f32>,
    pub step_m: f32,
    pub slice_m: f32,
    pub max_drop_m: f32,
    pub footprint_margin_m: f32,
}

impl Default for SupportOptions {
    fn default() -> Self {
        Self {
            up: Vector3::z(),
            step_m: 0.005,
            slice_m: 0.02,
            max_drop_m: 0.5,
            footprint_margin_m: 0.02,
        }
    }
}

/// New points extending the instances `ids` of `cloud` down to their support (see the module
/// docs), with colour, instance and [`Provenance::Rules`].
pub fn extend_to_support(
    cloud: &PointCloud,
    ids: &BTreeSet<u16>,
    opts: &SupportOptions,
) -> PointCloud {
    let (mut positions, mut colors, mut instance, mut generated) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let empty = PointCloud::default();
    let Some(inst) = cloud.instance.as_deref() else {
        return empty;
    };
    let Some(up) = opts.up.try_normalize(1e-9) else {
        return empty;
    };
    // Work in a frame where `up` is +z.
    let level = Rotation3::rotation_between(&up, &Vector3::z())
        .unwrap_or_else(|| Rotation3::from_axis_angle(&Vector3::x_axis(), std::f32::consts::PI));
    let back = level.inverse();
    let pts: Vec<Point3<f32>> = cloud.positions.iter().map(|p| level * p).collect();
    let mut by_id: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
    for (i, &id) in inst.iter().enumerate() {
        if ids.contains(&(id as u16)) {
            by_id.entry(id).or_default().push(i);
        }
    }
    for (&id, own) in &by_id {
        let (mut lo, mut hi) = (
            Point3::new(f32::MAX, f32::MAX, f32::MAX),
            Point3::new(f32::MIN, f32::MIN, f32::MIN),
        );
        for &i in own {
            lo = lo.inf(&pts[i]);
            hi = hi.sup(&pts[i]);
        }
        let m = opts.footprint_margin_m;
        let support = pts
            .iter()
            .zip(inst)
            .filter(|(p, &other)| {
                other != id
                    && p.x >= lo.x - m
                    && p.x <= hi.x + m
                    && p.y >= lo.y - m
                    && p.y <= hi.y + m
                    && p.z < lo.z - 0.01
                    && p.z >= lo.z - opts.max_drop_m
            })
            .map(|(p, _)| p.z)
            .fold(f32::NEG_INFINITY, f32::max);
        if !support.is_finite() {
            continue;
        }
        let slice: Vec<usize> = own
            .iter()
            .copied()
            .filter(|&i| pts[i].z <= lo.z + opts.slice_m)
            .collect();
        let steps = ((lo.z - support) / opts.step_m).floor() as usize;
        for &i in &slice {
            let c = cloud.colors.as_ref().map(|c| c[i]).unwrap_or([128; 3]);
            for k in 1..steps {
                let q = Point3::new(pts[i].x, pts[i].y, lo.z - k as f32 * opts.step_m);
                positions.push(back * q);
                colors.push(c);
                instance.push(id);
                generated.push(Provenance::Rules.code());
            }
        }
    }
    PointCloud {
        positions,
        colors: Some(colors),
        instance: Some(instance),
        generated: Some(generated),
        ..Default::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ring of points 10-12 cm above a table (another instance) is extended down to just above
    /// the table, and nothing is added for an object that already reaches it.
    #[test]
    fn a_floating_bottom_is_extended_to_the_table() {
        let mut positions = Vec::new();
        let mut instance = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                positions.push(Point3::new(
                    i as f32 * 0.01 - 0.2,
                    j as f32 * 0.01 - 0.2,
                    0.7,
                ));
                instance.push(1);
            }
        }
        for k in 0..36 {
            let a = k as f32 * std::f32::consts::TAU / 36.0;
            for z in [0.80, 0.81, 0.82] {
                positions.push(Point3::new(0.03 * a.cos(), 0.03 * a.sin(), z));
                instance.push(2);
                // A second object standing on the table already.
                positions.push(Point3::new(0.15 + 0.02 * a.cos(), 0.02 * a.sin(), z - 0.1));
                instance.push(3);
            }
        }
        let cloud = PointCloud {
            positions,
            instance: Some(instance),
            ..Default::default()
        };
        let ids: BTreeSet<u16> = [2, 3].into_iter().collect();
        let ext = extend_to_support(&cloud, &ids, &SupportOptions::default());
        let ids_out = ext.instance.as_deref().unwrap();
        assert!(!ext.is_empty());
        assert!(ids_out.iter().all(|&i| i == 2), "object 3 already stands");
        let zmin = ext.positions.iter().map(|p| p.z).fold(f32::MAX, f32::min);
        let zmax = ext.positions.iter().map(|p| p.z).fold(f32::MIN, f32::max);
        assert!(zmin > 0.7 && zmin < 0.71, "{zmin}");
        assert!(zmax < 0.8, "{zmax}");
        assert!(ext
            .generated
            .as_deref()
            .unwrap()
            .iter()
            .all(|&g| g == Provenance::Rules.code()));
    }
}
