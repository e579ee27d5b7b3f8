//! Stage: support. Objects stand on something: an object whose bottom is hidden behind what
//! stands in front of it (a bottle behind a box, of which only the neck shows) is extended down
//! to the surface it stands on.
//!
//! For each completed instance, its points (observed and generated) are taken; the support below
//! it ([`support_height`]) is the highest horizontal sheet of other instances' observed or
//! plane-fill points under the object's footprint (its box on the ground plane, 2 cm larger): a
//! 1 cm band of heights whose points cover at least [`MIN_SUPPORT_COVER`] of the footprint's 1 cm
//! cells, at most `max_drop_m` below the object's lowest point (within 1 cm of it, the object
//! stands already and is left as it is). A
//! vertical face (the box in front of a bottle) covers one row of cells, not a third of them, and
//! a completer's guess of another object's hidden side is no support. The object's lowest 2 cm
//! slice is then copied down in `step_m` steps to just above that support. The copies carry the rules provenance; the carving
//! stage then removes those any view contradicts (where a view sees the table through them).
//! Needs gravity: posed scenes in a z-up world frame (`up` in the options); pose-free input
//! (registered to the first camera) is left as it is.

use std::collections::{BTreeMap, BTreeSet};

use deocc_geometry::{PointCloud, Provenance};
use nalgebra::{Point2, Point3, Rotation3, Vector3};

/// The rotation taking `up` to +z (a half turn about x when `up` is -z); `None` for a zero `up`.
pub fn leveller(up: Vector3<f32>) -> Option<Rotation3<f32>> {
    let up = up.try_normalize(1e-9)?;
    Some(
        Rotation3::rotation_between(&up, &Vector3::z()).unwrap_or_else(|| {
            Rotation3::from_axis_angle(&Vector3::x_axis(), std::f32::consts::PI)
        }),
    )
}

/// What completed objects may stand on, levelled once for the stages that stand them up (revolve,
/// cuboid): the observed points and the planes' fill, each with its instance (`u32::MAX` where
/// the cloud has none).
pub struct Ground {
    level: Rotation3<f32>,
    points: Vec<Point3<f32>>,
    instance: Vec<u32>,
    observed: usize,
}

impl Ground {
    /// `None` for a zero `up`.
    pub fn new(observed: &PointCloud, fill: &PointCloud, up: Vector3<f32>) -> Option<Self> {
        let level = leveller(up)?;
        let ids = |c: &PointCloud| -> Vec<u32> {
            c.instance
                .clone()
                .unwrap_or_else(|| vec![u32::MAX; c.len()])
        };
        let mut instance = ids(observed);
        instance.extend(ids(fill));
        Some(Self {
            points: observed
                .positions
                .iter()
                .chain(&fill.positions)
                .map(|p| level * p)
                .collect(),
            instance,
            observed: observed.len(),
            level,
        })
    }

    /// World to levelled (`up` = +z).
    pub fn level(&self) -> &Rotation3<f32> {
        &self.level
    }

    /// The `i`-th observed point, levelled.
    pub fn observed(&self, i: usize) -> Point3<f32> {
        self.points[i]
    }

    /// Indices of the observed points of each instance of `ids`.
    pub fn observed_by_instance(&self, ids: &BTreeSet<u16>) -> BTreeMap<u16, Vec<usize>> {
        let mut own: BTreeMap<u16, Vec<usize>> = BTreeMap::new();
        for (i, &id) in self.instance[..self.observed].iter().enumerate() {
            if id <= u16::MAX as u32 && ids.contains(&(id as u16)) {
                own.entry(id as u16).or_default().push(i);
            }
        }
        own
    }

    /// [`support_height`] under the levelled box `lo..hi` among the points of instances other
    /// than `id`.
    pub fn support_under(
        &self,
        id: u32,
        lo: Point2<f32>,
        hi: Point2<f32>,
        floor: f32,
        ceiling: f32,
    ) -> Option<f32> {
        support_height(
            self.points
                .iter()
                .zip(&self.instance)
                .filter(|(_, &i)| i != id)
                .map(|(p, _)| *p),
            lo,
            hi,
            floor,
            ceiling,
        )
    }
}

/// Share of a footprint's 1 cm cells a horizontal sheet must cover to count as its support.
pub const MIN_SUPPORT_COVER: f32 = 0.3;

/// Cell size of the footprint grid and height step of [`support_height`]'s search.
const CELL_M: f32 = 0.01;
const BIN_M: f32 = 0.005;

/// The height of the surface something with footprint `lo..hi` (ground-plane box) stands on,
/// from `points` (a z-up frame; the caller keeps only other objects' observed or plane-fill
/// points) with heights in `[floor, ceiling)`: the highest 1 cm band whose points cover at least
/// [`MIN_SUPPORT_COVER`] of the footprint's 1 cm cells, as the median height of its points.
/// `None` when no band covers enough.
pub fn support_height(
    points: impl Iterator<Item = Point3<f32>>,
    lo: Point2<f32>,
    hi: Point2<f32>,
    floor: f32,
    ceiling: f32,
) -> Option<f32> {
    let nx = (((hi.x - lo.x) / CELL_M).ceil() as usize).max(1);
    let ny = (((hi.y - lo.y) / CELL_M).ceil() as usize).max(1);
    // Height bins of half a band, each with its points' heights and cells.
    let mut bins: BTreeMap<i32, Vec<(f32, usize)>> = BTreeMap::new();
    for p in points.filter(|p| {
        p.x >= lo.x && p.x <= hi.x && p.y >= lo.y && p.y <= hi.y && p.z >= floor && p.z < ceiling
    }) {
        let cx = (((p.x - lo.x) / CELL_M) as usize).min(nx - 1);
        let cy = (((p.y - lo.y) / CELL_M) as usize).min(ny - 1);
        bins.entry((p.z / BIN_M).floor() as i32)
            .or_default()
            .push((p.z, cy * nx + cx));
    }
    let need = (MIN_SUPPORT_COVER * (nx * ny) as f32).ceil() as usize;
    let mut cells = BTreeSet::new();
    // Each band is a bin and the one below it (1 cm), highest first.
    for (&b, upper) in bins.iter().rev() {
        let lower = bins.get(&(b - 1)).map(Vec::as_slice).unwrap_or(&[]);
        cells.clear();
        cells.extend(upper.iter().chain(lower).map(|&(_, c)| c));
        if cells.len() >= need {
            let mut z: Vec<f32> = upper.iter().chain(lower).map(|&(z, _)| z).collect();
            z.sort_by(f32::total_cmp);
            return Some(z[z.len() / 2]);
        }
    }
    None
}

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

/// The expected error of an extension's points, metres: the lowest observed ring continued
/// straight down, as uncertain as that ring's own spread.
pub const SUPPORT_ERROR_M: f32 = 0.005;

/// New points extending the instances `ids` of `cloud` down to their support (see the module
/// docs), with colour, instance, [`Provenance::Rules`] and [`SUPPORT_ERROR_M`].
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
    // Work in a frame where `up` is +z.
    let Some(level) = leveller(opts.up) else {
        return empty;
    };
    let back = level.inverse();
    let pts: Vec<Point3<f32>> = cloud.positions.iter().map(|p| level * p).collect();
    // What may support: observed points and plane fill (a cloud without provenance is observed).
    let seen_or_plane = |i: usize| {
        cloud.generated.as_deref().is_none_or(|g| {
            g[i] == Provenance::Observed.code() || g[i] == Provenance::PlaneFill.code()
        })
    };
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
        let Some(support) = support_height(
            (0..pts.len())
                .filter(|&i| inst[i] != id && seen_or_plane(i))
                .map(|i| pts[i]),
            Point2::new(lo.x - m, lo.y - m),
            Point2::new(hi.x + m, hi.y + m),
            lo.z - opts.max_drop_m,
            lo.z + 0.01,
        ) else {
            continue;
        };
        if support > lo.z - 0.01 {
            // It stands already.
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
    let n = positions.len();
    PointCloud {
        positions,
        colors: Some(colors),
        instance: Some(instance),
        generated: Some(generated),
        expected_error: Some(vec![SUPPORT_ERROR_M; n]),
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

    /// A box's vertical front face and a completer's guess of its hidden side are no support;
    /// the table's sheet below them is.
    #[test]
    fn only_a_horizontal_sheet_of_observed_or_fill_points_supports() {
        let (lo, hi) = (Point2::new(-0.05, -0.05), Point2::new(0.05, 0.05));
        let face = (0..50).flat_map(|k| {
            (0..25)
                .map(move |j| Point3::new(-0.05 + j as f32 * 0.004, -0.045, 0.7 + k as f32 * 0.004))
        });
        let table = (0..400).map(|j| {
            Point3::new(
                -0.05 + (j % 20) as f32 * 0.005,
                -0.05 + (j / 20) as f32 * 0.005,
                0.7,
            )
        });
        let z = support_height(face.clone().chain(table), lo, hi, 0.3, 0.9).unwrap();
        assert!((z - 0.7).abs() < 0.005, "{z}");
        assert_eq!(support_height(face, lo, hi, 0.3, 0.9), None);

        // A neck at 0.85-0.9 behind the face; the completer guessed the box's far side at 0.75
        // under it; the table's fill lies at 0.7.
        let mut positions: Vec<Point3<f32>> = (0..36)
            .flat_map(|k| {
                let a = k as f32 * std::f32::consts::TAU / 36.0;
                [0.85, 0.87, 0.89].map(|z| Point3::new(0.012 * a.cos(), 0.012 * a.sin(), z))
            })
            .collect();
        let mut generated = vec![Provenance::Observed.code(); positions.len()];
        let mut instance = vec![2; positions.len()];
        for j in 0..100 {
            positions.push(Point3::new(
                -0.02 + (j % 10) as f32 * 0.004,
                -0.02 + (j / 10) as f32 * 0.004,
                0.75,
            ));
            generated.push(Provenance::Model.code());
            instance.push(3);
        }
        for j in 0..400 {
            positions.push(Point3::new(
                -0.1 + (j % 20) as f32 * 0.01,
                -0.1 + (j / 20) as f32 * 0.01,
                0.7,
            ));
            generated.push(Provenance::PlaneFill.code());
            instance.push(1);
        }
        let cloud = PointCloud {
            positions,
            instance: Some(instance),
            generated: Some(generated),
            ..Default::default()
        };
        let ext = extend_to_support(&cloud, &[2].into(), &SupportOptions::default());
        let zmin = ext.positions.iter().map(|p| p.z).fold(f32::MAX, f32::min);
        assert!(zmin > 0.7 && zmin < 0.71, "{zmin}");
    }
}
