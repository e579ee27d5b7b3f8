//! The tuning behind `deocc_geometry::cell_grid::TARGET_OCCUPANCY`: on the clouds of
//! `deocc bench geometry`, the time of a batch nearest-neighbour query (index build included)
//! through the k-d tree and through cell grids of several occupancies, and whether all agree.
//!
//! `cargo run --release -p deocc-eval --example cell_grid_occupancy -- [POINTS] [OCCUPANCY ...]`

use std::time::Instant;

use deocc_geometry::{CellGrid, KdIndex};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let points: usize = args.next().map_or(Ok(1_000_000), |s| s.parse())?;
    let mut occupancies: Vec<f64> = args.map(|s| s.parse()).collect::<Result<_, _>>()?;
    if occupancies.is_empty() {
        occupancies = vec![4.0, 8.0, 16.0, 32.0];
    }
    let (a, b) = deocc_eval::bench::geometry::bench_clouds(points)?;
    let mean = |d: Vec<f32>| d.iter().map(|&x| x as f64).sum::<f64>() / d.len() as f64;
    for round in 1..=3 {
        let t = Instant::now();
        let reference = mean(KdIndex::build(&a)?.nearest_distances(&b));
        let mut line = format!("round {round}: k-d tree {:.3} s", t.elapsed().as_secs_f64());
        for &occupancy in &occupancies {
            let t = Instant::now();
            let grid = CellGrid::build_with_occupancy(&a, occupancy)?;
            let built = t.elapsed().as_secs_f64();
            let d = mean(grid.nearest_distances(&b));
            line += &format!(
                " | occupancy {occupancy}: {built:.3} + {:.3} s, cell {:.1} mm, same answer {}",
                t.elapsed().as_secs_f64() - built,
                grid.cell_size() * 1e3,
                (d - reference).abs() <= 1e-9 * reference.max(1.0)
            );
        }
        println!("{line}");
    }
    Ok(())
}
