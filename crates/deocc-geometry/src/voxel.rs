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
/// an observed point always wins over a generated one; the confidence is the mean over the
/// voxel's points of the provenance that wins (1 where an observed point is in it).
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
    // Confidences and expected errors: the mean over the points of the voxel's winning
    // provenance (the one its code reports).
    let winners_mean = |values: &Vec<f32>| -> Vec<f32> {
        groups
            .par_iter()
            .map(|g| {
                let gen = cloud.generated.as_ref();
                let best = gen.map(|gen| g.iter().map(|(_, j)| gen[*j as usize]).min());
                let wins = |i: usize| gen.is_none_or(|gen| Some(gen[i]) == best.flatten());
                let (s, n) = g
                    .iter()
                    .map(|(_, i)| *i as usize)
                    .filter(|&i| wins(i))
                    .fold((0f64, 0usize), |(s, n), i| {
                        (s + f64::from(values[i]), n + 1)
                    });
                (s / n.max(1) as f64) as f32
            })
            .collect()
    };
    let confidence = cloud.confidence.as_ref().map(winners_mean);
    let expected_error = cloud.expected_error.as_ref().map(winners_mean);
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
        confidence,
        expected_error,
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

/// Instance ids seen in one voxel with their counts (almost always one id).
#[derive(Debug, Clone)]
enum IdCounts {
    One(u32, u32),
    Many(Vec<(u32, u32)>),
}

impl IdCounts {
    fn add(&mut self, id: u32) {
        match self {
            IdCounts::One(i, n) if *i == id => *n += 1,
            IdCounts::One(i, n) => *self = IdCounts::Many(vec![(*i, *n), (id, 1)]),
            IdCounts::Many(v) => match v.iter_mut().find(|(i, _)| *i == id) {
                Some((_, n)) => *n += 1,
                None => v.push((id, 1)),
            },
        }
    }
    /// The most frequent id, the smallest among ties (what [`voxel_downsample`] picks).
    fn mode(&self) -> u32 {
        match self {
            IdCounts::One(i, _) => *i,
            IdCounts::Many(v) => v
                .iter()
                .min_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)))
                .map_or(0, |p| p.0),
        }
    }
}

#[derive(Debug, Clone)]
struct Cell {
    sum: Vector3<f64>,
    n: u32,
    color: [u32; 3],
    generated: u8,
    ids: IdCounts,
}

/// [`voxel_downsample`] of a cloud given in parts (frames) one at a time, so that memory holds
/// one part and the occupied voxels, never the whole concatenation: the same voxels (the grid
/// anchored at the union's min bound minus half a voxel, which the caller gives), the same means
/// accumulated in the same order, the same result bit for bit as [`voxel_downsample`] of the
/// concatenated parts.
pub struct VoxelGrid {
    origin: Point3<f64>,
    voxel: f64,
    cells: std::collections::HashMap<[i32; 3], Cell>,
    colors: Option<bool>,
    instance: Option<bool>,
    generated: Option<bool>,
}

impl VoxelGrid {
    /// A grid whose cells are anchored at `min_bound` (of everything that will be added) minus
    /// half a voxel, as [`voxel_downsample`] anchors them.
    pub fn new(min_bound: &Point3<f32>, voxel_m: f64) -> Result<Self> {
        let voxel = check_voxel(voxel_m)?;
        Ok(Self {
            origin: min_bound.cast::<f64>() - Vector3::repeat(voxel * 0.5),
            voxel,
            cells: Default::default(),
            colors: None,
            instance: None,
            generated: None,
        })
    }

    /// Adds a part. Every part must carry the same attributes (normals are not supported).
    pub fn add(&mut self, part: &PointCloud) -> Result<()> {
        let same = |seen: &mut Option<bool>, has: bool, what: &str| -> Result<()> {
            match seen {
                Some(s) if *s != has => Err(GeometryError::InvalidArgument(format!(
                    "voxel grid: a part {} {what} and another does not",
                    if has { "has" } else { "lacks" }
                ))),
                _ => {
                    *seen = Some(has);
                    Ok(())
                }
            }
        };
        same(&mut self.colors, part.colors.is_some(), "colours")?;
        same(&mut self.instance, part.instance.is_some(), "instance ids")?;
        same(&mut self.generated, part.generated.is_some(), "provenance")?;
        if part.normals.is_some() || part.confidence.is_some() || part.expected_error.is_some() {
            return Err(GeometryError::InvalidArgument(
                "voxel grid: normals, confidences and expected errors are not averaged here; use \
                 voxel_downsample"
                    .into(),
            ));
        }
        let keys: Vec<[i32; 3]> = part
            .positions
            .par_iter()
            .map(|p| voxel_key(p, &self.origin, self.voxel))
            .collect();
        for (i, key) in keys.into_iter().enumerate() {
            let id = part.instance.as_ref().map_or(0, |v| v[i]);
            let gen = part.generated.as_ref().map_or(0, |v| v[i]);
            let c = part.colors.as_ref().map_or([0; 3], |v| v[i]);
            let p = part.positions[i].coords.cast::<f64>();
            match self.cells.entry(key) {
                std::collections::hash_map::Entry::Occupied(mut e) => {
                    let cell = e.get_mut();
                    cell.sum += p;
                    cell.n += 1;
                    for (acc, v) in cell.color.iter_mut().zip(c) {
                        *acc += v as u32;
                    }
                    cell.generated = cell.generated.min(gen);
                    cell.ids.add(id);
                }
                std::collections::hash_map::Entry::Vacant(e) => {
                    e.insert(Cell {
                        sum: p,
                        n: 1,
                        color: c.map(u32::from),
                        generated: gen,
                        ids: IdCounts::One(id, 1),
                    });
                }
            }
        }
        Ok(())
    }

    /// Occupied voxels so far.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// One point per voxel, in voxel-key order, as [`voxel_downsample`] returns them.
    pub fn into_cloud(self) -> PointCloud {
        let mut cells: Vec<([i32; 3], Cell)> = self.cells.into_iter().collect();
        cells.par_sort_unstable_by_key(|(k, _)| *k);
        let positions = cells
            .iter()
            .map(|(_, c)| Point3::from((c.sum / c.n as f64).cast::<f32>()))
            .collect();
        let colors = self.colors.unwrap_or(false).then(|| {
            cells
                .iter()
                .map(|(_, c)| c.color.map(|v| ((v + c.n / 2) / c.n) as u8))
                .collect()
        });
        let instance = self
            .instance
            .unwrap_or(false)
            .then(|| cells.iter().map(|(_, c)| c.ids.mode()).collect());
        let generated = self
            .generated
            .unwrap_or(false)
            .then(|| cells.iter().map(|(_, c)| c.generated).collect());
        PointCloud {
            positions,
            colors,
            normals: None,
            instance,
            generated,
            confidence: None,
            expected_error: None,
        }
    }
}
