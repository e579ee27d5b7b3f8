//! Where an object of footprint `w x d` and height `h` can be put down.
//!
//! On each support plane (a horizontal surface within `max_tilt_deg` of level; gravity is `up`),
//! a grid of `cell_m` cells. A cell is
//! - **supported** when some point lies within `support_tolerance_m` of the plane in it;
//! - **occupied** when some point lies over it from `gap_m` above the plane up to `overhead_m`
//!   (the band the object needs is plane + 0.5 cm .. plane + h + 1 cm; a surface above the band
//!   blocks it too, because a point cloud samples only the surfaces of solids: the object would
//!   be inside or under that solid).
//!
//! A cell is **placeable** when the footprint centred on it lies inside the workspace (the
//! plane's extent), at least `min_support` of the footprint's cells are supported, and no cell
//! of the footprint dilated by `dilation_m` is occupied. The chosen placement maximises
//! `min(clearance, clearance_cap_m) / clearance_cap_m - distance_weight * distance to the robot`
//! (clearance: the distance from the cell to the nearest occupied cell; the robot: the first
//! camera's position). The footprint is axis-aligned with the grid (x = width, y = depth).
//!
//! Cells where the cloud has no point at all were not seen; [`UnseenSpace`] says what to assume
//! there: free and supported (optimistic), occupied (conservative), or nothing (as the points
//! say: unsupported, not occupied), which completed clouds use. Given the camera the points were
//! seen from ([`build_map_seen_from`]), a cell the sight line to a point below the plane crossed
//! at the plane's height was seen too, and seen empty: the floor seen past a table's edge says
//! there is no table there, so even the optimistic map does not stand an object on it.

use deocc_geometry::normals::estimate_normals;
use deocc_geometry::voxel::voxel_downsample;
use deocc_geometry::PointCloud;
use nalgebra::{Point3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::RobotError;

/// Most cells one placement map may have (a 20 x 20 m plane at 1 cm cells): a map costs tens of
/// bytes a cell, and a plane larger than a room is no table to put an object on.
pub const MAX_MAP_CELLS: usize = 4_000_000;

/// Most cells all of one call's maps may have together.
pub const MAX_TOTAL_MAP_CELLS: usize = 8_000_000;

/// What to assume in cells without any point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UnseenSpace {
    /// Supported and free: the optimistic reading of an observed cloud.
    Free,
    /// Occupied: the conservative reading of an observed cloud.
    Occupied,
    /// Only what the points say (no support, no obstacle): for completed clouds.
    AsPoints,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlaceOptions {
    /// Object footprint, width (grid x) and depth (grid y), metres.
    pub footprint: [f32; 2],
    /// Object height, metres.
    pub height: f32,
    pub cell_m: f32,
    pub support_tolerance_m: f32,
    pub min_support: f32,
    pub gap_m: f32,
    /// The gap grows to this many times the surface's own depth noise when that is larger
    /// (0 = off): in each cell, the robust spread (1.4826 x the median absolute deviation) of the
    /// points within `support_tolerance_m` of the plane in it and its 8 neighbours, over their
    /// median. A sensor whose noise grows with distance puts points of a far table top a
    /// centimetre over it; they are the table, not obstacles.
    pub gap_noise_sigmas: f32,
    /// Extra clearance above the object's height.
    pub headroom_m: f32,
    /// Surfaces up to this high over the plane block a cell (see the module docs).
    pub overhead_m: f32,
    pub dilation_m: f32,
    pub max_tilt_deg: f32,
    pub up: [f32; 3],
    /// Points a plane needs to count as a support surface.
    pub min_plane_points: usize,
    /// Gaps in the support up to this wide are closed (dilation then erosion): a table seen at a
    /// grazing angle has rows of cells no pixel lands in.
    pub support_closing_m: f32,
    pub clearance_cap_m: f32,
    pub distance_weight: f32,
    /// The envelope of generated space: a point with an expected error (the cloud's
    /// `expected_error`, observed points 0) occupies every cell within this many times its
    /// error of it, not only its own: an object may be wherever its completion could be
    /// (0 = off; a cloud without expected errors is read as it is). 1 (the expected error
    /// itself) was chosen on place-v1's tuning scenes under the structured-light model: the
    /// shipped chain's false-placeable share 0.052 -> 0.042 at 1, 0.035 at 2, its IoU 0.588 ->
    /// 0.565 -> 0.515, success 0.948 throughout (docs/decisions.md).
    pub expected_error_scale: f32,
    /// The envelope on the hidden side: seen from one camera (the map's `eye`), a generated
    /// point (expected error above 0) that occupies its cell also occupies the cells up to this
    /// far behind it along the sight line, levelled: the side no view sees is where a completion
    /// falls short (0 = off; no eye, no growth: several views have no one hidden side).
    pub hidden_side_m: f32,
}

impl Default for PlaceOptions {
    fn default() -> Self {
        Self {
            footprint: [0.08, 0.08],
            height: 0.12,
            cell_m: 0.01,
            support_tolerance_m: 0.01,
            min_support: 0.9,
            gap_m: 0.005,
            gap_noise_sigmas: 4.0,
            headroom_m: 0.01,
            overhead_m: 0.6,
            dilation_m: 0.01,
            max_tilt_deg: 10.0,
            up: [0.0, 0.0, 1.0],
            min_plane_points: 300,
            support_closing_m: 0.02,
            clearance_cap_m: 0.1,
            distance_weight: 0.5,
            expected_error_scale: 1.0,
            hidden_side_m: 0.0,
        }
    }
}

impl PlaceOptions {
    /// Every setting in its stated range (the error names it); see [`crate::range`].
    pub fn validate(&self) -> Result<(), RobotError> {
        use crate::range::{count, direction, real};
        let [w, d] = self.footprint;
        real("footprint width", w, 0.005, 5.0, " m")?;
        real("footprint depth", d, 0.005, 5.0, " m")?;
        real("height", self.height, 0.001, 5.0, " m")?;
        real("cell_m", self.cell_m, 0.002, 0.2, " m")?;
        real(
            "support_tolerance_m",
            self.support_tolerance_m,
            0.0,
            0.1,
            " m",
        )?;
        real("min_support", self.min_support, 0.01, 1.0, "")?;
        real("gap_m", self.gap_m, 0.0, 0.1, " m")?;
        real("gap_noise_sigmas", self.gap_noise_sigmas, 0.0, 20.0, "")?;
        real("headroom_m", self.headroom_m, 0.0, 1.0, " m")?;
        real("overhead_m", self.overhead_m, 0.0, 5.0, " m")?;
        real("dilation_m", self.dilation_m, 0.0, 0.5, " m")?;
        real("max_tilt_deg", self.max_tilt_deg, 0.0, 45.0, " degrees")?;
        direction("up", self.up)?;
        count("min_plane_points", self.min_plane_points, 3, 10_000_000)?;
        real("support_closing_m", self.support_closing_m, 0.0, 0.5, " m")?;
        real("clearance_cap_m", self.clearance_cap_m, 0.0, 5.0, " m")?;
        real(
            "expected_error_scale",
            self.expected_error_scale,
            0.0,
            10.0,
            "",
        )?;
        real("distance_weight", self.distance_weight, 0.0, 100.0, "")?;
        real("hidden_side_m", self.hidden_side_m, 0.0, 0.5, " m")?;
        Ok(())
    }

    /// The rotation taking `up` to +z (the frame the maps are built in).
    pub fn level(&self) -> Rotation3<f32> {
        let up = Vector3::from(self.up).normalize();
        Rotation3::rotation_between(&up, &Vector3::z()).unwrap_or_else(|| {
            // up = -z: a half turn about x.
            Rotation3::from_axis_angle(&Vector3::x_axis(), std::f32::consts::PI)
        })
    }
}

/// A horizontal support surface in the levelled frame: its height and extent.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SupportPlane {
    pub height: f32,
    /// `[x_min, y_min, x_max, y_max]`.
    pub bounds: [f32; 4],
    pub points: usize,
}

/// Horizontal planes of `points` (levelled by `opts.up`), largest first.
pub fn find_support_planes(
    points: &[Point3<f32>],
    opts: &PlaceOptions,
) -> Result<Vec<SupportPlane>, RobotError> {
    opts.validate()?;
    let level = opts.level();
    let cloud = PointCloud::from_positions(points.iter().map(|p| level * p).collect());
    let thin = voxel_downsample(&cloud, 0.01)?;
    if thin.len() < 3 {
        return Ok(Vec::new());
    }
    let normals = estimate_normals(&thin.positions, 12)?;
    let cos = opts.max_tilt_deg.to_radians().cos();
    let flat: Vec<Point3<f32>> = thin
        .positions
        .iter()
        .zip(&normals)
        .filter(|(_, n)| n.z.abs() >= cos)
        .map(|(p, _)| *p)
        .collect();
    if flat.is_empty() {
        return Ok(Vec::new());
    }
    let zmin = flat.iter().map(|p| p.z).fold(f32::INFINITY, f32::min);
    let bin = |z: f32| ((z - zmin) / 0.01) as usize;
    let nbins = bin(flat.iter().map(|p| p.z).fold(f32::MIN, f32::max)) + 1;
    if nbins > 100_000 {
        return Err(RobotError::Input(format!(
            "the cloud spans {:.0} m vertically; is `up` right?",
            nbins as f32 * 0.01
        )));
    }
    let mut hist = vec![0usize; nbins];
    for p in &flat {
        hist[bin(p.z)] += 1;
    }
    let mut planes = Vec::new();
    for b in 0..nbins {
        let c = hist[b];
        let left = if b > 0 { hist[b - 1] } else { 0 };
        let right = hist.get(b + 1).copied().unwrap_or(0);
        // A peak: the first of equal neighbours wins.
        if c == 0 || c <= left || c < right {
            continue;
        }
        let centre = zmin + (b as f32 + 0.5) * 0.01;
        let members: Vec<&Point3<f32>> = flat
            .iter()
            .filter(|p| (p.z - centre).abs() <= 0.015)
            .collect();
        if members.len() < opts.min_plane_points / 10 {
            // Thinned to 1 cm voxels: a plane of `min_plane_points` 3-5 mm points holds about a
            // tenth as many voxels.
            continue;
        }
        let height = members.iter().map(|p| p.z).sum::<f32>() / members.len() as f32;
        let mut xs: Vec<f32> = members.iter().map(|p| p.x).collect();
        let mut ys: Vec<f32> = members.iter().map(|p| p.y).collect();
        xs.sort_by(f32::total_cmp);
        ys.sort_by(f32::total_cmp);
        let q = |v: &[f32], f: f32| v[((v.len() - 1) as f32 * f) as usize];
        planes.push(SupportPlane {
            height,
            bounds: [q(&xs, 0.01), q(&ys, 0.01), q(&xs, 0.99), q(&ys, 0.99)],
            points: members.len(),
        });
    }
    planes.sort_by_key(|p| std::cmp::Reverse(p.points));
    Ok(planes)
}

/// The median of `v` (reordered); 0 when empty.
fn median(v: &mut [f32]) -> f32 {
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// A placement map over one support plane (levelled frame).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PlaceMap {
    pub plane: SupportPlane,
    pub cell_m: f32,
    pub nx: usize,
    pub ny: usize,
    /// Row-major (y rows, x columns).
    pub support: Vec<bool>,
    pub occupied: Vec<bool>,
    /// Some point fell in the cell, or a sight line crossed it at the plane's height on its way
    /// to a point below ([`build_map_seen_from`]).
    pub seen: Vec<bool>,
    /// Some occupied cell lies under the dilated footprint centred here.
    pub blocked: Vec<bool>,
    pub placeable: Vec<bool>,
}

impl PlaceMap {
    /// Centre of cell `i` (levelled frame, on the plane).
    pub fn cell_center(&self, i: usize) -> Point3<f32> {
        let (x, y) = (i % self.nx, i / self.nx);
        Point3::new(
            self.plane.bounds[0] + (x as f32 + 0.5) * self.cell_m,
            self.plane.bounds[1] + (y as f32 + 0.5) * self.cell_m,
            self.plane.height,
        )
    }

    pub fn placeable_cells(&self) -> usize {
        self.placeable.iter().filter(|&&p| p).count()
    }
}

/// Summed-area table of a boolean grid: `sum(x0..x1, y0..y1)` counts true cells.
struct Integral {
    nx: usize,
    s: Vec<u32>,
}

impl Integral {
    fn new(grid: &[bool], nx: usize, ny: usize) -> Self {
        let w = nx + 1;
        let mut s = vec![0u32; w * (ny + 1)];
        for y in 0..ny {
            let mut row = 0u32;
            for x in 0..nx {
                row += grid[y * nx + x] as u32;
                s[(y + 1) * w + x + 1] = s[y * w + x + 1] + row;
            }
        }
        Self { nx, s }
    }

    /// True cells in the half-open box, clipped to the grid.
    fn sum(&self, x0: isize, y0: isize, x1: isize, y1: isize) -> u32 {
        let w = self.nx + 1;
        let ny = self.s.len() / w - 1;
        let cx = |v: isize| v.clamp(0, self.nx as isize) as usize;
        let cy = |v: isize| v.clamp(0, ny as isize) as usize;
        let (x0, x1, y0, y1) = (cx(x0), cx(x1), cy(y0), cy(y1));
        if x1 <= x0 || y1 <= y0 {
            return 0;
        }
        self.s[y1 * w + x1] + self.s[y0 * w + x0] - self.s[y0 * w + x1] - self.s[y1 * w + x0]
    }
}

/// Morphological closing of a grid with a (2k+1)^2 box: gaps up to 2k cells wide are filled,
/// outer edges stay where they were.
fn close(grid: &[bool], nx: usize, ny: usize, k: isize) -> Vec<bool> {
    let box_any = |g: &[bool]| -> Vec<bool> {
        let s = Integral::new(g, nx, ny);
        (0..nx * ny)
            .map(|i| {
                let (x, y) = ((i % nx) as isize, (i / nx) as isize);
                s.sum(x - k, y - k, x + k + 1, y + k + 1) > 0
            })
            .collect()
    };
    let dilated = box_any(grid);
    let outside: Vec<bool> = dilated.iter().map(|&d| !d).collect();
    // Erosion of the dilation = complement of the dilation of its complement; cells beyond the
    // grid count as support so the table's own edge survives where the grid ends.
    box_any(&outside).iter().map(|&o| !o).collect()
}

/// The map of `points` over `plane` (see the module docs).
pub fn build_map(
    points: &[Point3<f32>],
    plane: &SupportPlane,
    opts: &PlaceOptions,
    unseen: UnseenSpace,
) -> Result<PlaceMap, RobotError> {
    build_map_seen_from(points, plane, opts, unseen, None)
}

/// [`build_map`] for points seen from `eye` (world frame; one camera: the points of a single
/// frame, or of frames taken from about the same place): the cells where a sight line to a point
/// below the plane crosses the plane's height count as seen and empty (no support), whatever
/// [`UnseenSpace`] says (the module docs). `None`: [`build_map`].
pub fn build_map_seen_from(
    points: &[Point3<f32>],
    plane: &SupportPlane,
    opts: &PlaceOptions,
    unseen: UnseenSpace,
    eye: Option<&Point3<f32>>,
) -> Result<PlaceMap, RobotError> {
    build_map_with_errors(points, None, plane, opts, unseen, eye)
}

/// [`build_map_seen_from`] with each point's expected error (metres; the cloud's
/// `expected_error`): with [`PlaceOptions::expected_error_scale`] on, a point that occupies its
/// cell occupies every cell within that many times its error too.
pub fn build_map_with_errors(
    points: &[Point3<f32>],
    errors: Option<&[f32]>,
    plane: &SupportPlane,
    opts: &PlaceOptions,
    unseen: UnseenSpace,
    eye: Option<&Point3<f32>>,
) -> Result<PlaceMap, RobotError> {
    opts.validate()?;
    if let Some(e) = errors {
        if e.len() != points.len() {
            return Err(RobotError::Input(format!(
                "{} expected errors for {} points",
                e.len(),
                points.len()
            )));
        }
        if let Some(bad) = e.iter().find(|x| !(x.is_finite() && **x >= 0.0)) {
            return Err(RobotError::Input(format!(
                "a point's expected error is {bad}: must be finite and >= 0"
            )));
        }
    }
    let [x0, y0, x1, y1] = plane.bounds;
    let cell = opts.cell_m;
    let nx = ((x1 - x0) / cell).ceil().max(0.0) as usize;
    let ny = ((y1 - y0) / cell).ceil().max(0.0) as usize;
    if nx == 0 || ny == 0 {
        return Err(RobotError::Input(format!(
            "support plane {:?} gives an empty grid at {cell} m cells",
            plane.bounds
        )));
    }
    if nx * ny > MAX_MAP_CELLS {
        return Err(RobotError::Input(format!(
            "a support plane spans {:.1} x {:.1} m: {nx} x {ny} cells of {cell} m, more than the \
             limit of {MAX_MAP_CELLS} cells a plane (raise cell_m or crop the cloud to the workspace)",
            x1 - x0,
            y1 - y0
        )));
    }
    let level = opts.level();
    let mut support = vec![false; nx * ny];
    let mut occupied = vec![false; nx * ny];
    let mut seen = vec![false; nx * ny];
    let cell_of = |x: f32, y: f32| {
        let (fx, fy) = ((x - x0) / cell, (y - y0) / cell);
        (fx >= 0.0 && fy >= 0.0 && fx < nx as f32 && fy < ny as f32)
            .then(|| fy as usize * nx + fx as usize)
    };
    let eye = eye.map(|e| level * e).filter(|e| e.z > plane.height);
    // The gap per cell: `gap_noise_sigmas` times the surface's noise around it (the points
    // within `support_tolerance_m` of the plane in the cell and its 8 neighbours) where that
    // exceeds `gap_m`. Local, because a completed cloud mixes noisy observed points with
    // generated ones lying exactly on the plane.
    let gap: Vec<f32> = if opts.gap_noise_sigmas > 0.0 {
        // The points within the tolerance, grouped by cell (counting sort: one flat array and
        // an offset per cell, not a vector per cell).
        let near_points: Vec<(usize, f32)> = points
            .iter()
            .filter_map(|p| {
                let p = level * p;
                let dz = p.z - plane.height;
                (dz.abs() <= opts.support_tolerance_m)
                    .then(|| cell_of(p.x, p.y).map(|i| (i, dz)))
                    .flatten()
            })
            .collect();
        let mut start = vec![0u32; nx * ny + 1];
        for &(i, _) in &near_points {
            start[i + 1] += 1;
        }
        for i in 0..nx * ny {
            start[i + 1] += start[i];
        }
        let mut next = start.clone();
        let mut flat = vec![0f32; near_points.len()];
        for &(i, dz) in &near_points {
            flat[next[i] as usize] = dz;
            next[i] += 1;
        }
        let near = |i: usize| &flat[start[i] as usize..start[i + 1] as usize];
        let mut block = Vec::new();
        (0..nx * ny)
            .map(|i| {
                let (cx, cy) = ((i % nx) as isize, (i / nx) as isize);
                block.clear();
                for y in (cy - 1).max(0)..=(cy + 1).min(ny as isize - 1) {
                    for x in (cx - 1).max(0)..=(cx + 1).min(nx as isize - 1) {
                        block.extend_from_slice(near(y as usize * nx + x as usize));
                    }
                }
                if block.len() < 3 {
                    return opts.gap_m;
                }
                let centre = median(&mut block);
                let mut dev: Vec<f32> = block.iter().map(|d| (d - centre).abs()).collect();
                opts.gap_m
                    .max(centre + opts.gap_noise_sigmas * 1.4826 * median(&mut dev))
            })
            .collect()
    } else {
        vec![opts.gap_m; nx * ny]
    };
    for (k, p) in points.iter().enumerate() {
        let p = level * p;
        let dz = p.z - plane.height;
        if let (Some(e), true) = (eye, dz < -opts.support_tolerance_m) {
            // Where the sight line to a point below the plane crosses the plane's height.
            let t = (plane.height - e.z) / (p.z - e.z);
            let c = e + (p - e) * t;
            if let Some(i) = cell_of(c.x, c.y) {
                seen[i] = true;
            }
        }
        let Some(i) = cell_of(p.x, p.y) else {
            continue;
        };
        if dz.abs() <= opts.support_tolerance_m {
            support[i] = true;
        }
        if dz > gap[i] && dz <= opts.overhead_m.max(opts.height + opts.headroom_m) {
            occupied[i] = true;
            // The envelope: every cell within the point's scaled expected error.
            let grow = errors.map_or(0.0, |e| e[k] * opts.expected_error_scale);
            let r = (grow / cell).round() as isize;
            if r > 0 {
                let (cx, cy) = ((i % nx) as isize, (i / nx) as isize);
                for y in (cy - r).max(0)..=(cy + r).min(ny as isize - 1) {
                    for x in (cx - r).max(0)..=(cx + r).min(nx as isize - 1) {
                        let (dx, dy) = ((x - cx) as f32 * cell, (y - cy) as f32 * cell);
                        if dx.hypot(dy) <= grow {
                            occupied[y as usize * nx + x as usize] = true;
                        }
                    }
                }
            }
            // The hidden side: on along the sight line, away from the camera.
            let generated = errors.is_some_and(|e| e[k] > 0.0);
            if let (Some(e), true) = (eye, generated && opts.hidden_side_m > 0.0) {
                let away = Vector3::new(p.x - e.x, p.y - e.y, 0.0);
                if let Some(d) = away.try_normalize(1e-6) {
                    let steps = (opts.hidden_side_m / (0.5 * cell)).ceil() as usize;
                    for s in 1..=steps {
                        let t = (s as f32 * 0.5 * cell).min(opts.hidden_side_m);
                        if let Some(j) = cell_of(p.x + d.x * t, p.y + d.y * t) {
                            occupied[j] = true;
                        }
                    }
                }
            }
        }
    }
    let k = (opts.support_closing_m / cell).round() as isize;
    if k > 0 {
        support = close(&support, nx, ny, k);
    }
    for i in 0..nx * ny {
        seen[i] |= support[i] || occupied[i];
    }
    for i in 0..nx * ny {
        if !seen[i] {
            match unseen {
                UnseenSpace::Free => support[i] = true,
                UnseenSpace::Occupied => occupied[i] = true,
                UnseenSpace::AsPoints => {}
            }
        }
    }
    let fw = (opts.footprint[0] / cell).round().max(1.0) as isize;
    let fd = (opts.footprint[1] / cell).round().max(1.0) as isize;
    let dil = (opts.dilation_m / cell).round() as isize;
    let sup = Integral::new(&support, nx, ny);
    let occ = Integral::new(&occupied, nx, ny);
    let need = (opts.min_support * (fw * fd) as f32).ceil() as u32;
    let mut blocked = vec![false; nx * ny];
    let mut placeable = vec![false; nx * ny];
    for y in 0..ny as isize {
        for x in 0..nx as isize {
            let (ax, ay) = (x - fw / 2, y - fd / 2);
            let (bx, by) = (ax + fw, ay + fd);
            let i = y as usize * nx + x as usize;
            blocked[i] = occ.sum(ax - dil, ay - dil, bx + dil, by + dil) > 0;
            let inside = ax >= 0 && ay >= 0 && bx <= nx as isize && by <= ny as isize;
            placeable[i] = inside && !blocked[i] && sup.sum(ax, ay, bx, by) >= need;
        }
    }
    Ok(PlaceMap {
        plane: *plane,
        cell_m: cell,
        nx,
        ny,
        support,
        occupied,
        seen,
        blocked,
        placeable,
    })
}

/// A chosen placement.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Placement {
    /// Which map (support plane) of a planner's answer; 0 from [`choose_placement`].
    pub plane: usize,
    /// Cell index in that map.
    pub cell: usize,
    /// Where the footprint's centre goes (world frame, on the plane).
    pub position: [f32; 3],
    pub clearance_m: f32,
    pub score: f32,
}

/// The best placeable cell of `map` for a robot at `robot` (world frame), or `None`.
pub fn choose_placement(
    map: &PlaceMap,
    robot: &Point3<f32>,
    opts: &PlaceOptions,
) -> Option<Placement> {
    let level = opts.level();
    let r = level * robot;
    // Distance (cells) to the nearest occupied cell by a two-pass chamfer transform.
    let (nx, ny) = (map.nx, map.ny);
    let big = f32::INFINITY;
    let mut dist: Vec<f32> = map
        .occupied
        .iter()
        .map(|&o| if o { 0.0 } else { big })
        .collect();
    let diag = std::f32::consts::SQRT_2;
    for y in 0..ny {
        for x in 0..nx {
            let i = y * nx + x;
            let mut d = dist[i];
            if x > 0 {
                d = d.min(dist[i - 1] + 1.0);
            }
            if y > 0 {
                d = d.min(dist[i - nx] + 1.0);
                if x > 0 {
                    d = d.min(dist[i - nx - 1] + diag);
                }
                if x + 1 < nx {
                    d = d.min(dist[i - nx + 1] + diag);
                }
            }
            dist[i] = d;
        }
    }
    for y in (0..ny).rev() {
        for x in (0..nx).rev() {
            let i = y * nx + x;
            let mut d = dist[i];
            if x + 1 < nx {
                d = d.min(dist[i + 1] + 1.0);
            }
            if y + 1 < ny {
                d = d.min(dist[i + nx] + 1.0);
                if x + 1 < nx {
                    d = d.min(dist[i + nx + 1] + diag);
                }
                if x > 0 {
                    d = d.min(dist[i + nx - 1] + diag);
                }
            }
            dist[i] = d;
        }
    }
    let cap = opts.clearance_cap_m;
    (0..nx * ny)
        .filter(|&i| map.placeable[i])
        .map(|i| {
            let c = map.cell_center(i);
            let clearance = (dist[i] * map.cell_m).min(cap);
            let reach = (c.xy() - r.xy()).norm();
            let score = clearance / cap - opts.distance_weight * reach;
            (i, c, clearance, score)
        })
        .max_by(|a, b| a.3.total_cmp(&b.3).then(b.0.cmp(&a.0)))
        .map(|(cell, c, clearance_m, score)| Placement {
            plane: 0,
            cell,
            position: (level.inverse() * c).coords.into(),
            clearance_m,
            score,
        })
}

/// Plans a placement on a cloud. Implement it to plug in another placer.
pub trait PlacePlanner: Send + Sync {
    fn name(&self) -> &str;
    /// The map of every support plane (largest first) and the best placement over all of them.
    fn plan(
        &self,
        points: &[Point3<f32>],
        robot: &Point3<f32>,
    ) -> Result<(Vec<PlaceMap>, Option<Placement>), RobotError>;
    /// [`Self::plan`] with each point's expected error (metres; the cloud's `expected_error`),
    /// for a placer that keeps off uncertain generated space. By default the errors are ignored.
    fn plan_with_errors(
        &self,
        points: &[Point3<f32>],
        errors: Option<&[f32]>,
        robot: &Point3<f32>,
    ) -> Result<(Vec<PlaceMap>, Option<Placement>), RobotError> {
        let _ = errors;
        self.plan(points, robot)
    }
}

/// The default placer: the grid maps of the module docs on every support plane found.
#[derive(Debug, Clone)]
pub struct GridPlacer {
    pub options: PlaceOptions,
    pub unseen: UnseenSpace,
    /// The camera the points were seen from, when they come from one (see
    /// [`build_map_seen_from`]): for the observed maps (unseen space free or occupied), and for
    /// the hidden side's envelope ([`PlaceOptions::hidden_side_m`]).
    pub eye: Option<Point3<f32>>,
}

impl PlacePlanner for GridPlacer {
    fn name(&self) -> &str {
        "grid"
    }

    fn plan(
        &self,
        points: &[Point3<f32>],
        robot: &Point3<f32>,
    ) -> Result<(Vec<PlaceMap>, Option<Placement>), RobotError> {
        self.plan_with_errors(points, None, robot)
    }

    /// The maps of [`build_map_with_errors`]: with `expected_error_scale` on, generated points
    /// occupy the cells within their scaled error.
    fn plan_with_errors(
        &self,
        points: &[Point3<f32>],
        errors: Option<&[f32]>,
        robot: &Point3<f32>,
    ) -> Result<(Vec<PlaceMap>, Option<Placement>), RobotError> {
        if !(robot.x.is_finite() && robot.y.is_finite() && robot.z.is_finite()) {
            return Err(RobotError::Config(format!(
                "robot = [{}, {}, {}]: must be three finite numbers",
                robot.x, robot.y, robot.z
            )));
        }
        let planes = find_support_planes(points, &self.options)?;
        if planes.is_empty() {
            return Err(RobotError::Input(format!(
                "no horizontal support surface (within {} degrees of level, at least {} points) \
                 in the cloud; check `up`",
                self.options.max_tilt_deg, self.options.min_plane_points
            )));
        }
        let [w, d] = self.options.footprint;
        let biggest = planes
            .iter()
            .map(|p| (p.bounds[2] - p.bounds[0]).max(p.bounds[3] - p.bounds[1]))
            .fold(0.0f32, f32::max);
        if w.min(d) > biggest {
            return Err(RobotError::Input(format!(
                "footprint {w} x {d} m is larger than every support surface (largest {biggest:.2} m)"
            )));
        }
        // Every map's size before the first is built: refused whole, not after minutes.
        let cell = self.options.cell_m;
        let cells: usize = planes
            .iter()
            .map(|p| {
                let nx = ((p.bounds[2] - p.bounds[0]) / cell).ceil().max(0.0) as usize;
                let ny = ((p.bounds[3] - p.bounds[1]) / cell).ceil().max(0.0) as usize;
                nx.saturating_mul(ny)
            })
            .fold(0usize, usize::saturating_add);
        if cells > MAX_TOTAL_MAP_CELLS {
            return Err(RobotError::Input(format!(
                "the cloud's {} support planes need {cells} cells of {cell} m, more than the limit \
                 of {MAX_TOTAL_MAP_CELLS} a call (raise cell_m or crop the cloud to the workspace)",
                planes.len()
            )));
        }
        let mut maps = Vec::new();
        let mut best: Option<Placement> = None;
        for (k, plane) in planes.iter().enumerate() {
            let map = build_map_with_errors(
                points,
                errors,
                plane,
                &self.options,
                self.unseen,
                self.eye.as_ref(),
            )?;
            if let Some(mut p) = choose_placement(&map, robot, &self.options) {
                if best.as_ref().is_none_or(|b| p.score > b.score) {
                    p.plane = k;
                    best = Some(p);
                }
            }
            maps.push(map);
        }
        Ok((maps, best))
    }
}

/// Scores of a predicted map against the ground-truth map over the same grid.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MapScores {
    /// IoU of the placeable cells over the workspace.
    pub iou: f64,
    /// Share of predicted placeable cells whose dilated footprint meets true geometry.
    pub false_placeable_rate: f64,
    pub placeable_cells: usize,
    pub true_placeable_cells: usize,
    /// Truly placeable cells the prediction misses because something it holds (a point over the
    /// plane) lies under the dilated footprint.
    pub missed_blocked: usize,
    /// Truly placeable cells the prediction misses with nothing in the way: too little of the
    /// footprint has support (no point on the plane).
    pub missed_unsupported: usize,
}

/// Compares `pred` with `truth` over the cells where `workspace` holds.
pub fn compare_maps(
    pred: &PlaceMap,
    truth: &PlaceMap,
    workspace: &[bool],
) -> Result<MapScores, RobotError> {
    if pred.nx != truth.nx || pred.ny != truth.ny || workspace.len() != pred.placeable.len() {
        return Err(RobotError::Input(format!(
            "maps of different grids: {} x {} against {} x {}",
            pred.nx, pred.ny, truth.nx, truth.ny
        )));
    }
    let (mut inter, mut union, mut pc, mut tc, mut bad) = (0usize, 0usize, 0usize, 0usize, 0);
    let (mut missed_blocked, mut missed_unsupported) = (0usize, 0usize);
    for (i, _) in workspace.iter().enumerate().filter(|(_, &w)| w) {
        let (p, t) = (pred.placeable[i], truth.placeable[i]);
        inter += (p && t) as usize;
        union += (p || t) as usize;
        pc += p as usize;
        tc += t as usize;
        bad += (p && truth.blocked[i]) as usize;
        if t && !p {
            if pred.blocked[i] {
                missed_blocked += 1;
            } else {
                missed_unsupported += 1;
            }
        }
    }
    Ok(MapScores {
        iou: if union == 0 {
            1.0
        } else {
            inter as f64 / union as f64
        },
        false_placeable_rate: if pc == 0 { 0.0 } else { bad as f64 / pc as f64 },
        placeable_cells: pc,
        true_placeable_cells: tc,
        missed_blocked,
        missed_unsupported,
    })
}
