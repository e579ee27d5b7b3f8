//! Exact nearest-neighbour search over 3-D points, on kiddo's immutable k-d tree.

use std::num::NonZero;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::Point3;
use rayon::prelude::*;

use crate::error::{GeometryError, Result};

/// A static k-d tree over a point set. Built once, queried many times (metrics, ICP, normals).
pub struct KdIndex {
    tree: ImmutableKdTree<f32, 3>,
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
        if points.is_empty() {
            return Err(GeometryError::Empty {
                what: "point set for the k-d tree",
            });
        }
        if let Some(index) = points
            .iter()
            .position(|p| !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()))
        {
            return Err(GeometryError::NonFinite {
                what: "point set for the k-d tree",
                index,
            });
        }
        let arrays = crate::cloud::as_arrays(points);
        let tree = ImmutableKdTree::new_from_slice_parallel(&arrays)
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

    /// The nearest indexed point of every query, in parallel; result `i` belongs to `queries[i]`.
    pub fn nearest_batch(&self, queries: &[Point3<f32>]) -> Vec<Neighbour> {
        queries
            .par_iter()
            .with_min_len(1024)
            .map(|q| self.nearest(q))
            .collect()
    }

    /// Euclidean distance from every query to its nearest indexed point, in parallel.
    pub fn nearest_distances(&self, queries: &[Point3<f32>]) -> Vec<f32> {
        queries
            .par_iter()
            .with_min_len(1024)
            .map(|q| self.nearest(q).distance_sq.sqrt())
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
