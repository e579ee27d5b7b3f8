//! Exact nearest-neighbour search over 3-D points, on kiddo's immutable k-d tree.

use std::num::NonZero;

use kiddo::kd_tree::KdTree;
use kiddo::leaf_strategy::VecOfArenas;
use kiddo::{Eytzinger, SquaredEuclidean};
use nalgebra::Point3;
use rayon::prelude::*;

use crate::error::{GeometryError, Result};

/// Points per leaf. kiddo's `ImmutableKdTree` alias takes 32; 16 answers this project's queries
/// (surface clouds, queries on or near the surface, in Morton order) faster at the same build
/// time, and 8 or 4 no faster by enough to matter (a one-off comparison of leaf sizes;
/// `deocc bench geometry` gives the end-to-end figures, docs/benchmarks.md).
const BUCKET: usize = 16;

/// kiddo's immutable tree (Eytzinger stems, arena leaves) with [`BUCKET`] points per leaf.
type Tree = KdTree<f32, u32, Eytzinger, VecOfArenas<f32, u32, 3, BUCKET>, 3, BUCKET>;

/// A static k-d tree over a point set. Built once, queried many times (metrics, ICP, normals).
pub struct KdIndex {
    tree: Tree,
    len: usize,
}

/// One neighbour: the index of the point in the indexed set and its squared distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Neighbour {
    pub index: u32,
    pub distance_sq: f32,
}

impl KdIndex {
    /// Builds the tree. Errors on an empty set, non-finite coordinates, or more than u32::MAX points.
    pub fn build(points: &[Point3<f32>]) -> Result<Self> {
        check_index_input(points, "point set for the k-d tree")?;
        let arrays = crate::cloud::as_arrays(points);
        let tree = Tree::new_from_slice_parallel(&arrays)
            .map_err(|e| GeometryError::InvalidArgument(format!("k-d tree construction: {e:?}")))?;
        Ok(Self {
            tree,
            len: points.len(),
        })
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The nearest indexed point to `query`.
    pub fn nearest(&self, query: &Point3<f32>) -> Neighbour {
        let r = self
            .tree
            .query(&[query.x, query.y, query.z])
            .nearest_one::<SquaredEuclidean<f32>>()
            .execute();
        Neighbour {
            index: r.item,
            distance_sq: r.distance,
        }
    }

    /// The nearest indexed point within squared distance `max_d2` (inclusive), if any. A known
    /// bound prunes the walk from the start: far queries with a candidate in hand cost a fraction
    /// of [`KdIndex::nearest`].
    pub fn nearest_within(&self, query: &Point3<f32>, max_d2: f32) -> Option<Neighbour> {
        if max_d2.is_infinite() {
            return Some(self.nearest(query));
        }
        self.tree
            .query(&[query.x, query.y, query.z])
            .nearest_n::<SquaredEuclidean<f32>>(NonZero::<usize>::MIN)
            .within(max_d2)
            .execute()
            .into_iter()
            .next()
            .map(|r| Neighbour {
                index: r.item,
                distance_sq: r.distance,
            })
    }

    /// The nearest indexed point of every query, in parallel; result `i` belongs to `queries[i]`.
    /// Queries are answered in Morton order ([`morton_order`]): neighbouring queries walk the same
    /// tree nodes, which stay in cache (on a shuffled 500k-point cloud about twice as fast as in
    /// the given order); the answers are the same.
    pub fn nearest_batch(&self, queries: &[Point3<f32>]) -> Vec<Neighbour> {
        let order = morton_order(queries);
        let answered: Vec<Neighbour> = order
            .par_iter()
            .with_min_len(1024)
            .map(|&i| self.nearest(&queries[i as usize]))
            .collect();
        let mut out = vec![
            Neighbour {
                index: 0,
                distance_sq: 0.0
            };
            queries.len()
        ];
        for (&i, nb) in order.iter().zip(answered) {
            out[i as usize] = nb;
        }
        out
    }

    /// Euclidean distance from every query to its nearest indexed point, in parallel.
    pub fn nearest_distances(&self, queries: &[Point3<f32>]) -> Vec<f32> {
        self.nearest_batch(queries)
            .into_iter()
            .map(|nb| nb.distance_sq.sqrt())
            .collect()
    }

    /// The `k` nearest indexed points, nearest first (fewer if the set is smaller).
    pub fn k_nearest(&self, query: &Point3<f32>, k: usize) -> Vec<Neighbour> {
        let Some(k) = NonZero::new(k.min(self.len)) else {
            return Vec::new();
        };
        self.tree
            .query(&[query.x, query.y, query.z])
            .nearest_n::<SquaredEuclidean<f32>>(k)
            .execute()
            .into_iter()
            .map(|r| Neighbour {
                index: r.item,
                distance_sq: r.distance,
            })
            .collect()
    }

    /// Every indexed point within `radius` of `query` (unsorted).
    pub fn within(&self, query: &Point3<f32>, radius: f32) -> Vec<Neighbour> {
        self.tree
            .query(&[query.x, query.y, query.z])
            .within::<SquaredEuclidean<f32>>(radius * radius)
            .unsorted()
            .execute()
            .into_iter()
            .map(|r| Neighbour {
                index: r.item,
                distance_sq: r.distance,
            })
            .collect()
    }
}

/// The input of a nearest-neighbour index ([`KdIndex`], [`crate::CellGrid`]): not empty, every
/// coordinate finite, indices that fit in u32. `what` names the set in the error.
pub(crate) fn check_index_input(points: &[Point3<f32>], what: &'static str) -> Result<()> {
    if points.is_empty() {
        return Err(GeometryError::Empty { what });
    }
    if points.len() > u32::MAX as usize {
        return Err(GeometryError::InvalidArgument(format!(
            "{what}: {} points are more than an index holds (u32)",
            points.len()
        )));
    }
    if let Some(index) = points
        .iter()
        .position(|p| !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()))
    {
        return Err(GeometryError::NonFinite { what, index });
    }
    Ok(())
}

/// Spreads the low 21 bits of `v` to every third bit.
pub(crate) fn spread_bits(v: u64) -> u64 {
    let mut x = v & 0x1f_ffff;
    x = (x | x << 32) & 0x1f_0000_0000_ffff;
    x = (x | x << 16) & 0x1f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    x = (x | x << 2) & 0x1249_2492_4924_9249;
    x
}

/// The indices of `points` sorted along a Morton (Z-order) curve over their bounding box, 21
/// bits per axis: points close in space come close in the order. Non-finite points go last.
pub fn morton_order(points: &[Point3<f32>]) -> Vec<u32> {
    let finite = |p: &Point3<f32>| p.x.is_finite() && p.y.is_finite() && p.z.is_finite();
    let (lo, hi) = points.iter().filter(|p| finite(p)).fold(
        (
            Point3::new(f32::MAX, f32::MAX, f32::MAX),
            Point3::new(f32::MIN, f32::MIN, f32::MIN),
        ),
        |(lo, hi), p| (lo.inf(p), hi.sup(p)),
    );
    let extent = (hi - lo).max().max(1e-12) as f64;
    let scale = ((1u64 << 21) - 1) as f64 / extent;
    let code = |p: &Point3<f32>| -> u64 {
        if !finite(p) {
            return u64::MAX;
        }
        let q = |v: f32, l: f32| (((v - l) as f64 * scale) as u64).min((1 << 21) - 1);
        spread_bits(q(p.x, lo.x)) | spread_bits(q(p.y, lo.y)) << 1 | spread_bits(q(p.z, lo.z)) << 2
    };
    let mut keyed: Vec<(u64, u32)> = points
        .par_iter()
        .enumerate()
        .map(|(i, p)| (code(p), i as u32))
        .collect();
    keyed.par_sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}
