//! The cell grid gives the k-d tree's answers: exact nearest neighbours for every kind of cloud
//! and query (near, far, outside the grid, on cell faces, in a dense patch), and the same cut-off
//! semantics as a bounded search.

use deocc_geometry::{CellGrid, GeometryError};
use nalgebra::Point3;
use proptest::prelude::*;
use rand::{Rng, SeedableRng};

fn brute(points: &[Point3<f32>], q: &Point3<f32>) -> f32 {
    points
        .iter()
        .map(|p| {
            let (dx, dy, dz) = (p.x - q.x, p.y - q.y, p.z - q.z);
            dx * dx + dy * dy + dz * dz
        })
        .fold(f32::INFINITY, f32::min)
}

/// Checks every answer against a brute-force search: the distance is the least one, and the named
/// point is at that distance.
fn assert_exact(points: &[Point3<f32>], queries: &[Point3<f32>], grid: &CellGrid) {
    let got = grid.nearest_batch(queries);
    assert_eq!(got.len(), queries.len());
    for (k, (q, nb)) in queries.iter().zip(&got).enumerate() {
        let best = brute(points, q);
        assert!(
            (nb.distance_sq - best).abs() <= 1e-6 * best.max(1e-12),
            "query {k} {q:?}: got {} (point {}), brute force {best}",
            nb.distance_sq,
            nb.index
        );
        let named = brute(&points[nb.index as usize..nb.index as usize + 1], q);
        assert!((named - nb.distance_sq).abs() <= 1e-6 * best.max(1e-12));
    }
}

fn surface_cloud(n: usize, seed: u64) -> Vec<Point3<f32>> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            let (u, v): (f32, f32) = (rng.random(), rng.random());
            match i % 3 {
                0 => Point3::new(u * 2.0, v * 1.5, 0.0),
                1 => Point3::new(u * 2.0, 0.0, v),
                _ => {
                    let t = u * std::f32::consts::TAU;
                    Point3::new(1.0 + 0.1 * t.cos(), 0.7 + 0.1 * t.sin(), v * 0.3)
                }
            }
        })
        .collect()
}

#[test]
fn answers_match_brute_force_on_a_surface_with_near_far_and_outside_queries() {
    let points = surface_cloud(20_000, 1);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
    let mut queries: Vec<Point3<f32>> = points[..3000]
        .iter()
        .map(|p| p + nalgebra::Vector3::new(rng.random_range(-0.03..0.03), 0.01, 0.02))
        .collect();
    // Far from the surface, and outside the grid's box on every side.
    queries.extend((0..300).map(|_| {
        Point3::new(
            rng.random_range(-3.0..5.0),
            rng.random_range(-3.0..5.0),
            rng.random_range(-3.0..5.0),
        )
    }));
    // Exactly on indexed points.
    queries.extend_from_slice(&points[5000..5100]);
    for occupancy in [1.0, 4.0, 16.0, 64.0] {
        let grid = CellGrid::build_with_occupancy(&points, occupancy).unwrap();
        assert_eq!(grid.len(), points.len());
        assert!(grid.occupied_cells() > 0 && grid.cell_size() > 0.0);
        assert_exact(&points, &queries, &grid);
    }
}

#[test]
fn a_dense_patch_and_a_lone_point_are_answered_exactly() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    // A sparse volume, a cluster of 5000 points inside a 0.1 mm cube (over the scan's limit for
    // any cell size the sparse part asks for), and one point far away.
    let mut points: Vec<Point3<f32>> = (0..4000)
        .map(|_| Point3::new(rng.random(), rng.random(), rng.random()))
        .collect();
    points.extend((0..5000).map(|_| {
        Point3::new(
            0.5 + rng.random::<f32>() * 1e-4,
            0.5 + rng.random::<f32>() * 1e-4,
            0.5 + rng.random::<f32>() * 1e-4,
        )
    }));
    points.push(Point3::new(10.0, -4.0, 3.0));
    let mut queries: Vec<Point3<f32>> = (0..500)
        .map(|_| {
            Point3::new(
                0.5 + rng.random::<f32>() * 2e-4,
                0.5 + rng.random::<f32>() * 2e-4,
                0.5 + rng.random::<f32>() * 2e-4,
            )
        })
        .collect();
    queries.extend((0..500).map(|_| {
        Point3::new(
            rng.random_range(-1.0..11.0),
            rng.random_range(-5.0..2.0),
            rng.random_range(-1.0..4.0),
        )
    }));
    let grid = CellGrid::build(&points).unwrap();
    assert_exact(&points, &queries, &grid);
}

#[test]
fn a_cut_off_gives_none_exactly_when_nothing_is_within_it() {
    let points = surface_cloud(10_000, 4);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let queries: Vec<Point3<f32>> = (0..2000)
        .map(|_| {
            Point3::new(
                rng.random_range(-0.2..2.2),
                rng.random_range(-0.2..1.7),
                rng.random_range(-0.2..1.2),
            )
        })
        .collect();
    let grid = CellGrid::build(&points).unwrap();
    for max in [0.005f32, 0.05, 0.3] {
        let got = grid.nearest_batch_within(&queries, max);
        let mut some = 0;
        for (q, nb) in queries.iter().zip(&got) {
            let best = brute(&points, q);
            match nb {
                Some(nb) => {
                    some += 1;
                    assert!(nb.distance_sq <= max * max);
                    assert!((nb.distance_sq - best).abs() <= 1e-6 * best.max(1e-12));
                }
                None => assert!(
                    best > max * max * (1.0 - 1e-6),
                    "{q:?}: {best} within {max}"
                ),
            }
        }
        // Each cut-off leaves some queries with and some without a neighbour.
        assert!(some > 0 && some < queries.len(), "{max}: {some}");
    }
}

#[test]
fn degenerate_clouds_and_queries() {
    // One point; every point the same (a zero-size box); a flat line.
    let one = vec![Point3::new(1.0f32, 2.0, 3.0)];
    let same = vec![Point3::new(-0.5f32, 0.25, 7.0); 50];
    let line: Vec<Point3<f32>> = (0..100)
        .map(|i| Point3::new(i as f32 * 0.01, 0.0, 0.0))
        .collect();
    let queries = vec![
        Point3::new(1.0f32, 2.0, 3.0),
        Point3::new(0.0, 0.0, 0.0),
        Point3::new(0.505, 0.001, -0.002),
        Point3::new(-100.0, 50.0, 1e4),
    ];
    for points in [&one, &same, &line] {
        let grid = CellGrid::build(points).unwrap();
        assert_exact(points, &queries, &grid);
    }
    // A non-finite query has no neighbour.
    let grid = CellGrid::build(&line).unwrap();
    let got = grid.nearest_batch(&[Point3::new(f32::NAN, 0.0, 0.0)]);
    assert!(got[0].distance_sq.is_infinite());
    assert_eq!(
        grid.nearest_batch_within(&[Point3::new(0.0, f32::INFINITY, 0.0)], 1.0),
        vec![None]
    );
    assert!(grid.nearest_batch(&[]).is_empty());
}

#[test]
fn bad_clouds_are_refused_naming_the_point() {
    assert!(matches!(
        CellGrid::build(&[]),
        Err(GeometryError::Empty { .. })
    ));
    let bad = vec![
        Point3::new(0.0f32, 0.0, 0.0),
        Point3::new(1.0, f32::NAN, 0.0),
    ];
    assert!(matches!(
        CellGrid::build(&bad),
        Err(GeometryError::NonFinite { index: 1, .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Points and queries on a coarse lattice land exactly on cell faces and tie often: the
    /// distances still match a brute-force search.
    #[test]
    fn lattice_points_on_cell_faces_match_brute_force(
        pts in prop::collection::vec((0i32..40, 0i32..40, 0i32..6), 1..400),
        qs in prop::collection::vec((-5i32..45, -5i32..45, -5i32..10), 1..100),
        step in prop::sample::select(vec![0.001f32, 0.01, 0.125, 1.0]),
        occupancy in prop::sample::select(vec![1.0f64, 4.0, 16.0]),
    ) {
        let p = |(x, y, z): (i32, i32, i32)| Point3::new(x as f32 * step, y as f32 * step, z as f32 * step);
        let points: Vec<Point3<f32>> = pts.into_iter().map(p).collect();
        let queries: Vec<Point3<f32>> = qs.into_iter().map(p).collect();
        let grid = CellGrid::build_with_occupancy(&points, occupancy).unwrap();
        assert_exact(&points, &queries, &grid);
    }
}
