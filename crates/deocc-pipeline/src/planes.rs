//! Stage: planes. Completing the support planes (floor, walls, large flat tops) behind what
//! stands in front of them. Objects are completed by a completer; the largest hidden surfaces of a scene are the floor
//! under a table and the walls behind furniture, and for those a plane is the right prior.
//!
//! Each large planar instance is fitted with a plane; instances on the same plane (a floor split
//! by a table into several segments) are filled together. Fill candidates are the cells of a grid
//! on the plane inside the convex hull of the observed plane points that no observed point covers,
//! or inside the hull's smallest enclosing rectangle when the hull nearly fills it (a table's
//! corner hidden behind the things at its edge).
//! A candidate is kept only if the views agree that it is hidden: every view with a measurement
//! where it projects sees something in front of it (none sees it, none sees through it). Points so
//! made carry [`Provenance::PlaneFill`] in the cloud's `generated` property.

use std::collections::{BTreeMap, HashSet};

use deocc_geometry::camera::Projector;
use deocc_geometry::normals::smallest_eigenvector;
use deocc_geometry::{PointCloud, Provenance};
use deocc_io::scene::SceneInput;
use nalgebra::{Matrix3, Point2, Point3, Vector3};

use crate::carve::{evidence, in_a_frame, Evidence};

#[derive(Debug, Clone)]
pub struct PlaneOptions {
    /// Grid spacing of the filled points, metres.
    pub spacing_m: f32,
    /// Planar: this fraction of an instance's points within `inlier_m` of a plane (the plane is
    /// refitted on its inliers, so a table top with its legs counts, the top filled).
    pub inlier_m: f32,
    pub min_inlier_fraction: f32,
    /// Planes per instance, each fitted to the points the ones before left (a table's top and
    /// the vertical plane of its front legs).
    pub max_planes: usize,
    /// A plane is not filled when the views see through more than this share of the cells its
    /// points span and do not observe (a table's front legs and apron make a plane; the floor
    /// shows between the legs).
    pub max_seen_through: f32,
    /// Tables, shelves and rooms are rectangles: when the observed part of a plane fills at least
    /// this share of its smallest enclosing rectangle, the rectangle is filled instead of the
    /// observed part's convex hull (corners hidden behind things at the edge). What the views see
    /// through is never filled either way. Above 1: hulls only.
    pub min_rectangularity: f32,
    /// Only planes at least this large (box diagonal of their points, metres) are filled.
    pub min_extent_m: f32,
    /// Pixels sampled per view and instance: every `stride`-th row and column.
    pub stride: usize,
    /// A plane whose fill grid would exceed this many cells is not filled (memory and time
    /// stay bounded whatever the poses say): 25M cells is 50 x 50 m at 1 cm.
    pub max_cells: u64,
    /// Cells inside the observed part's hull that no view measures (drop-outs, shadows) are
    /// filled as hidden ones are ([`crate::PipelineOptions::plane_fill_unmeasured`]).
    pub fill_unmeasured: bool,
    /// Pixels of a plane's instance that have no depth (a sensor's drop-outs, a projector's
    /// shadow) are filled where their sight line meets the plane, when most of the instance's
    /// measured pixels around them (within this many pixels) lie on it; 0 = off. The mask says
    /// the surface is there; the plane says where.
    pub mask_window_px: usize,
    /// Only planes within 30 degrees of level (this is up) get their masked pixels without depth:
    /// support surfaces, where a planner needs them; a far wall's plane is fitted to depth too
    /// noisy to put pixels on it (3 cm off at 3.5 m under a structured-light sensor).
    pub up: [f32; 3],
}

impl Default for PlaneOptions {
    fn default() -> Self {
        Self {
            spacing_m: 0.01,
            inlier_m: 0.015,
            min_inlier_fraction: 0.25,
            max_planes: 3,
            max_seen_through: 0.3,
            min_rectangularity: 0.8,
            min_extent_m: 0.8,
            stride: 3,
            max_cells: 25_000_000,
            fill_unmeasured: true,
            mask_window_px: 8,
            up: [0.0, 0.0, 1.0],
        }
    }
}

struct Plane {
    instance_id: u16,
    normal: Vector3<f32>,
    offset: f32, // normal . p = offset
    points: Vec<Point3<f32>>,
    color: [u8; 3],
}

/// Sampled points of every instance (every `stride`-th row and column of each view) and the sum
/// of their colours.
type InstancePoints = BTreeMap<u16, (Vec<Point3<f32>>, [u64; 3])>;

fn instance_points(scene: &SceneInput, stride: usize) -> InstancePoints {
    let mut per: InstancePoints = BTreeMap::new();
    for f in &scene.frames {
        let Some(map) = &f.instances else { continue };
        let (w, h) = (map.width as usize, map.height as usize);
        let rgb = f.rgb.as_raw();
        for v in (0..h).step_by(stride.max(1)) {
            for u in (0..w).step_by(stride.max(1)) {
                let i = v * w + u;
                let (id, d) = (map.ids[i], f.depth.data()[i]);
                if id == 0 || d <= 0.0 {
                    continue;
                }
                let e = per.entry(id).or_default();
                e.0.push(f.camera.unproject_pixel(u as u32, v as u32, d));
                for c in 0..3 {
                    e.1[c] += rgb[3 * i + c] as u64;
                }
            }
        }
    }
    per
}

/// The plane as a normal pointing to the cameras and its offset, when every camera is on one side
/// of it (a wall, the floor, a table top seen from above).
fn facing_cameras(
    normal: Vector3<f32>,
    offset: f32,
    centres: &[Point3<f32>],
) -> Option<(Vector3<f32>, f32)> {
    let sides: Vec<f32> = centres
        .iter()
        .map(|c| normal.dot(&c.coords) - offset)
        .collect();
    if !sides.is_empty() && sides.iter().all(|d| *d > 0.0) {
        Some((normal, offset))
    } else if !sides.is_empty() && sides.iter().all(|d| *d < 0.0) {
        Some((-normal, -offset))
    } else {
        None
    }
}

/// The instances that are pieces of the scene's bounding planes: at least `min_fraction` of their
/// sampled points lie within `opts.inlier_m` of one plane of a large planar instance that has
/// every camera on one side and (almost) nothing observed behind it (the floor and the walls, and
/// the pieces a segmenter cut them into). They have no far side for a completer to add, and the
/// plane fill completes their plane. A table top is no bounding plane (its legs and the floor
/// lie below it): its underside is completed.
pub fn plane_pieces(found: &ScenePlanes, opts: &PlaneOptions, min_fraction: f32) -> Vec<u16> {
    let planes = &found.bounding;
    if planes.is_empty() {
        return Vec::new();
    }
    found
        .points
        .iter()
        .filter(|(_, (points, _))| {
            !points.is_empty()
                && planes.iter().any(|&(n, o)| {
                    let on = points
                        .iter()
                        .filter(|p| (n.dot(&p.coords) - o).abs() <= opts.inlier_m)
                        .count();
                    on as f32 >= min_fraction * points.len() as f32
                })
        })
        .map(|(id, _)| *id)
        .collect()
}

/// The scene's bounding planes (`n . p = o`, the cameras on the positive side): the planes of
/// large planar instances with every camera on one side and (almost) nothing observed more than
/// 3 cm behind them (the floor and the walls).
fn bounding_planes(
    scene: &SceneInput,
    points: &InstancePoints,
    planes: &[Plane],
) -> Vec<(Vector3<f32>, f32)> {
    let centres: Vec<Point3<f32>> = scene.frames.iter().map(|f| f.camera.center()).collect();
    let all: Vec<Point3<f32>> = points
        .values()
        .flat_map(|(p, _)| p.iter().copied())
        .collect();
    planes
        .iter()
        .filter_map(|pl| facing_cameras(pl.normal, pl.offset, &centres))
        .filter(|&(n, o)| {
            let behind = all.iter().filter(|p| n.dot(&p.coords) - o < -0.03).count();
            behind as f32 <= 0.005 * all.len() as f32
        })
        .collect()
}

/// Drops the points more than `margin_m` behind a bounding plane ([`ScenePlanes::bounding`]): under
/// the floor or behind a wall, where the views show nothing can be. Returns the kept cloud and
/// how many points were dropped.
pub fn keep_inside(
    cloud: &PointCloud,
    planes: &[(Vector3<f32>, f32)],
    margin_m: f32,
) -> (PointCloud, usize) {
    let keep: Vec<usize> = (0..cloud.len())
        .filter(|&i| {
            let p = cloud.positions[i];
            planes
                .iter()
                .all(|&(n, o)| n.dot(&p.coords) - o >= -margin_m)
        })
        .collect();
    let dropped = cloud.len() - keep.len();
    (cloud.select(&keep), dropped)
}

/// The scene's large planar instances' planes, and every instance's sampled points: found once
/// per run, for [`plane_pieces`] and [`complete_found_planes`].
pub struct ScenePlanes {
    points: InstancePoints,
    planes: Vec<Plane>,
    /// The scene's bounding planes (`n . p = o`, the cameras on the positive side): the floor
    /// and the walls, for [`plane_pieces`] and [`keep_inside`].
    pub bounding: Vec<(Vector3<f32>, f32)>,
}

impl ScenePlanes {
    /// Fits the planes (only `opts`' sampling and fitting fields matter).
    pub fn find(scene: &SceneInput, opts: &PlaneOptions) -> Self {
        let points = instance_points(scene, opts.stride);
        let planes = planes_of(points.clone(), opts);
        let bounding = bounding_planes(scene, &points, &planes);
        Self {
            points,
            planes,
            bounding,
        }
    }
}

fn planes_of(per: InstancePoints, opts: &PlaneOptions) -> Vec<Plane> {
    per.into_iter()
        .filter_map(|(id, (points, color_sum))| {
            if points.len() < 50 {
                return None;
            }
            let (lo, hi) = points
                .iter()
                .fold((points[0], points[0]), |(lo, hi), p| (lo.inf(p), hi.sup(p)));
            if (hi - lo).norm() < opts.min_extent_m {
                return None;
            }
            let n = points.len();
            let color = color_sum.map(|s| (s / n as u64) as u8);
            let planes = instance_planes(points, opts)
                .into_iter()
                .map(|(normal, offset, inliers)| Plane {
                    instance_id: id,
                    normal,
                    offset,
                    color,
                    points: inliers,
                })
                .collect::<Vec<_>>();
            Some(planes)
        })
        .flatten()
        .collect()
}

/// The planes of an instance's points: up to `max_planes`, each fitted to what the ones before
/// left and holding at least `min_inlier_fraction` of all the points, those at least
/// `min_extent_m` across. A cluttered table seen from afar shows more of its legs and front than
/// of its top, and the plane holding most of its points can be the vertical one through its
/// front legs: with one plane per instance (and 40% of the points on it) no table top of 7 in 100
/// place-v1 scenes was filled.
fn instance_planes(
    mut left: Vec<Point3<f32>>,
    opts: &PlaneOptions,
) -> Vec<(Vector3<f32>, f32, Vec<Point3<f32>>)> {
    let n = left.len();
    let mut planes = Vec::new();
    for _ in 0..opts.max_planes {
        let Some((normal, offset, inliers)) = fit_plane(&left, opts.inlier_m) else {
            break;
        };
        // The next plane is fitted to what this one leaves, whether it is kept or not: the
        // densest plane within 4 cm can be a table's front (apron and legs) and still hold less
        // than the top does within 1.5 cm.
        left.retain(|p| (normal.dot(&p.coords) - offset).abs() > opts.inlier_m);
        let (lo, hi) = inliers
            .iter()
            .fold((inliers[0], inliers[0]), |(lo, hi), p| {
                (lo.inf(p), hi.sup(p))
            });
        if (inliers.len() as f32) >= opts.min_inlier_fraction * n as f32
            && (hi - lo).norm() >= opts.min_extent_m
        {
            planes.push((normal, offset, inliers));
        }
        if left.len() < 50 {
            break;
        }
    }
    planes
}

/// The plane of an instance's points (`normal . p = offset`) and the points within `inlier_m` of
/// it; `None` when fewer than 50 points support it.
fn fit_plane(
    points: &[Point3<f32>],
    inlier_m: f32,
) -> Option<(Vector3<f32>, f32, Vec<Point3<f32>>)> {
    // The plane with most points within 4 cm (a deterministic RANSAC), then PCA refits on its
    // inliers: a table's top wins over its legs even where the legs fill more pixels than the top
    // (a table seen from afar at a grazing angle). The 1.5 cm band still holds the top's edge and
    // the legs' upper ends, and a fit on it tilted a table top by up to 1 cm per metre, which
    // lifted its fill into the space over the table; so the plane with most of those points
    // within 3 mm is taken, and refitted three times on the points within three robust standard
    // deviations of it (2 mm at least, for noiseless depth).
    let mut inliers: Vec<Point3<f32>> = ransac_inliers(points, 0.04);
    let within = |normal: Vector3<f32>, offset: f32, band: f32| -> Vec<Point3<f32>> {
        points
            .iter()
            .filter(|p| (normal.dot(&p.coords) - offset).abs() <= band)
            .copied()
            .collect()
    };
    for band in [0.04, inlier_m] {
        let (normal, offset) = pca_plane(&inliers)?;
        inliers = within(normal, offset, band);
        if inliers.len() < 50 {
            return None;
        }
    }
    let (mut normal, mut offset) = pca_plane(&ransac_inliers(&inliers, 0.003))?;
    for _ in 0..3 {
        let residuals: Vec<f32> = inliers
            .iter()
            .map(|p| normal.dot(&p.coords) - offset)
            .collect();
        let band = (3.0 * 1.4826 * median_abs_deviation(residuals)).clamp(0.002, inlier_m);
        let tight = within(normal, offset, band);
        if tight.len() < 50 {
            return None;
        }
        (normal, offset) = pca_plane(&tight)?;
    }
    let inliers = within(normal, offset, inlier_m);
    Some((normal, offset, inliers))
}

/// The plane through the centroid of `points` normal to their direction of least spread
/// (`normal . p = offset`).
fn pca_plane(points: &[Point3<f32>]) -> Option<(Vector3<f32>, f32)> {
    let c = deocc_geometry::cloud::centroid(points)?;
    let mut cov = Matrix3::<f64>::zeros();
    for p in points {
        let d = (p - c).cast::<f64>();
        cov += d * d.transpose();
    }
    let normal = smallest_eigenvector(&cov)
        .cast::<f32>()
        .try_normalize(1e-9)?;
    Some((normal, normal.dot(&c.coords)))
}

/// Median of |r - median(r)|.
fn median_abs_deviation(mut r: Vec<f32>) -> f32 {
    if r.is_empty() {
        return 0.0;
    }
    let mid = r.len() / 2;
    let m = *r.select_nth_unstable_by(mid, f32::total_cmp).1;
    let mut d: Vec<f32> = r.iter().map(|x| (x - m).abs()).collect();
    *d.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// The points within `band` of the plane through three of them that holds the most points, over
/// 200 triples drawn by a fixed generator (a deterministic RANSAC; inliers counted on at most
/// 4000 evenly spaced points).
fn ransac_inliers(points: &[Point3<f32>], band: f32) -> Vec<Point3<f32>> {
    let n = points.len();
    let step = n.div_ceil(4000).max(1);
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((state >> 33) as usize) % n
    };
    let mut best: Option<(usize, Vector3<f32>, f32)> = None;
    for _ in 0..200 {
        let (a, b, c) = (points[next()], points[next()], points[next()]);
        let Some(normal) = (b - a).cross(&(c - a)).try_normalize(1e-9) else {
            continue;
        };
        let offset = normal.dot(&a.coords);
        let count = points
            .iter()
            .step_by(step)
            .filter(|p| (normal.dot(&p.coords) - offset).abs() <= band)
            .count();
        if best.is_none_or(|b| count > b.0) {
            best = Some((count, normal, offset));
        }
    }
    match best {
        Some((_, normal, offset)) => points
            .iter()
            .filter(|p| (normal.dot(&p.coords) - offset).abs() <= band)
            .copied()
            .collect(),
        None => points.to_vec(),
    }
}

/// Convex hull (counter-clockwise, Andrew's monotone chain) of 2-D points.
fn convex_hull(mut pts: Vec<Point2<f32>>) -> Vec<Point2<f32>> {
    pts.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    pts.dedup();
    if pts.len() < 3 {
        return pts;
    }
    let cross = |o: &Point2<f32>, a: &Point2<f32>, b: &Point2<f32>| {
        (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x)
    };
    let mut hull: Vec<Point2<f32>> = Vec::with_capacity(2 * pts.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &Point2<f32>>> = if pass == 0 {
            Box::new(pts.iter())
        } else {
            Box::new(pts.iter().rev())
        };
        for p in iter {
            while hull.len() >= start + 2
                && cross(&hull[hull.len() - 2], &hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(*p);
        }
        hull.pop();
    }
    hull
}

fn inside(hull: &[Point2<f32>], p: &Point2<f32>) -> bool {
    hull.len() >= 3
        && (0..hull.len()).all(|i| {
            let (a, b) = (hull[i], hull[(i + 1) % hull.len()]);
            (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x) >= 0.0
        })
}

/// The point a fill cell centred at `centre` (side `s`) gets in the convex region `poly`: its
/// centre when that lies inside; else, when the region's edge crosses the cell, the point of the
/// edge nearest the centre, 1 mm inwards (a table's last, partly covered row of cells: without
/// it the fill stops up to half a cell short of the edge); else none.
fn fill_point(poly: &[Point2<f32>], centre: &Point2<f32>, s: f32) -> Option<Point2<f32>> {
    if inside(poly, centre) {
        return Some(*centre);
    }
    let n = poly.len();
    if n < 3 {
        return None;
    }
    let nearest = (0..n)
        .map(|i| {
            let (a, b) = (poly[i], poly[(i + 1) % n]);
            let d = b - a;
            let t = ((centre - a).dot(&d) / d.norm_squared().max(1e-12)).clamp(0.0, 1.0);
            a + d * t
        })
        .min_by(|p, q| {
            (p - centre)
                .norm_squared()
                .total_cmp(&(q - centre).norm_squared())
        })?;
    if (nearest.x - centre.x).abs() > s / 2.0 || (nearest.y - centre.y).abs() > s / 2.0 {
        return None;
    }
    let centroid = Point2::from(
        poly.iter()
            .map(|p| p.coords)
            .sum::<nalgebra::Vector2<f32>>()
            / n as f32,
    );
    let q = nearest + (centroid - nearest).normalize() * 1e-3;
    inside(poly, &q).then_some(q)
}

/// Area of a counter-clockwise polygon.
fn polygon_area(poly: &[Point2<f32>]) -> f32 {
    let n = poly.len();
    (0..n)
        .map(|i| {
            let (a, b) = (poly[i], poly[(i + 1) % n]);
            a.x * b.y - b.x * a.y
        })
        .sum::<f32>()
        / 2.0
}

/// The smallest-area rectangle enclosing a convex hull (counter-clockwise corners): one of its
/// sides lies on a hull edge, so every edge's direction is tried.
fn min_area_rectangle(hull: &[Point2<f32>]) -> Option<[Point2<f32>; 4]> {
    let n = hull.len();
    if n < 3 {
        return None;
    }
    let mut best: Option<(f32, [Point2<f32>; 4])> = None;
    for i in 0..n {
        let d = hull[(i + 1) % n] - hull[i];
        let len = d.norm();
        if len <= 1e-9 {
            continue;
        }
        let u = d / len;
        let v = nalgebra::Vector2::new(-u.y, u.x);
        let (mut u0, mut u1, mut v0, mut v1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        for p in hull {
            let (a, b) = (p.coords.dot(&u), p.coords.dot(&v));
            (u0, u1, v0, v1) = (u0.min(a), u1.max(a), v0.min(b), v1.max(b));
        }
        let area = (u1 - u0) * (v1 - v0);
        if best.as_ref().is_none_or(|(a, _)| area < *a) {
            let at = |a: f32, b: f32| Point2::from(u * a + v * b);
            best = Some((area, [at(u0, v0), at(u1, v0), at(u1, v1), at(u0, v1)]));
        }
    }
    best.map(|(_, r)| r)
}

/// What of a plane is filled: the smallest rectangle around the hull when the hull fills at
/// least `min_rectangularity` of it, else the hull.
fn fill_region(hull: Vec<Point2<f32>>, min_rectangularity: f32) -> Vec<Point2<f32>> {
    let Some(r) = min_area_rectangle(&hull) else {
        return hull;
    };
    let (a, b) = (polygon_area(&hull), polygon_area(&r));
    tracing::debug!(
        "plane hull {a:.3} m2 of its rectangle's {b:.3} m2 ({:.2})",
        a / b.max(1e-9)
    );
    if a >= min_rectangularity * b {
        r.to_vec()
    } else {
        hull
    }
}

/// Points filling the hidden parts of the scene's support planes (see the module docs).
pub fn complete_planes(scene: &SceneInput, opts: &PlaneOptions) -> PointCloud {
    complete_found_planes(scene, &ScenePlanes::find(scene, opts), opts)
}

/// The plane fill of a run (stage 4b): the hidden parts of the planes found, as plane-fill
/// points with the fill's confidence and the planes' inlier tolerance as their expected error;
/// nothing when `enabled` is off or no planes were found.
pub fn plane_fill(
    scene: &SceneInput,
    enabled: bool,
    found: Option<&ScenePlanes>,
    opts: &PlaneOptions,
) -> PointCloud {
    match found {
        Some(found) if enabled => complete_found_planes(scene, found, opts)
            .with_confidence(deocc_geometry::cloud::FILL_CONFIDENCE)
            .with_expected_error(opts.inlier_m),
        _ => PointCloud::default(),
    }
}

/// Groups coplanar planes (normals within 5 degrees, offsets within 3 cm): each plane's group is
/// the index of the first plane of it.
fn coplanar_groups(planes: &[Plane]) -> Vec<usize> {
    let mut group: Vec<usize> = (0..planes.len()).collect();
    for i in 0..planes.len() {
        for j in 0..i {
            let same = planes[i].normal.dot(&planes[j].normal).abs() > 5f32.to_radians().cos()
                && (planes[i].offset
                    - planes[j].offset * planes[i].normal.dot(&planes[j].normal).signum())
                .abs()
                    < 0.03;
            if same {
                group[i] = group[j];
                break;
            }
        }
    }
    group
}

/// The hidden cells of a group of coplanar members to fill: all of them when every member is a
/// surface, else those inside the joint region of the members that are. A member the views see
/// through over much of what its points span is no surface (the vertical plane of a table's
/// front legs and apron): nothing of it is filled.
fn solid_part(
    hidden: Vec<(Point3<f32>, Point2<f32>)>,
    flats: &[Vec<Point2<f32>>],
    unobserved: &[usize],
    seen_through: &[usize],
    opts: &PlaneOptions,
) -> Vec<Point3<f32>> {
    let solid: Vec<usize> = (0..flats.len())
        .filter(|&k| seen_through[k] as f32 <= opts.max_seen_through * unobserved[k] as f32)
        .collect();
    if solid.len() == flats.len() {
        return hidden.into_iter().map(|(p, _)| p).collect();
    }
    let kept = fill_region(
        convex_hull(solid.iter().flat_map(|&k| flats[k].clone()).collect()),
        opts.min_rectangularity,
    );
    hidden
        .into_iter()
        .filter(|(_, q)| inside(&kept, q))
        .map(|(p, _)| p)
        .collect()
}

/// Grid cells of a plane's fill.
type Cells = HashSet<(i32, i32)>;

/// Each member's points in the plane's frame (`flat`): its measured inliers and its masked
/// pixels without depth. A member's own hull decides whether it is a surface, the joint hull of
/// the members that are is what gets filled (a floor that a segmenter cut into pieces is filled
/// between them). With them, the cells the measured inliers and their neighbours hold.
fn member_flats(
    members: &[&Plane],
    masked: &[Vec<Point3<f32>>],
    normal: Vector3<f32>,
    offset: f32,
    flat: &dyn Fn(&Point3<f32>) -> Point2<f32>,
    cell: &dyn Fn(&Point3<f32>) -> (i32, i32),
    opts: &PlaneOptions,
) -> (Vec<Vec<Point2<f32>>>, Cells) {
    let mut occupied: HashSet<(i32, i32)> = HashSet::new();
    let mut flats: Vec<Vec<Point2<f32>>> = Vec::new();
    for (m, masked) in members.iter().zip(masked) {
        let mut points: Vec<Point2<f32>> = masked.iter().map(flat).collect();
        for p in &m.points {
            if (normal.dot(&p.coords) - offset).abs() > opts.inlier_m {
                continue;
            }
            let (a, b) = cell(p);
            // Observed cells and their neighbours (the sampling stride leaves gaps).
            for da in -2..=2 {
                for db in -2..=2 {
                    occupied.insert((a + da, b + db));
                }
            }
            points.push(flat(p));
        }
        flats.push(points);
    }
    (flats, occupied)
}

/// Each of `members`' pixels without depth, where the plane `normal . p = offset` says they are
/// ([`mask_points`]), when the plane is within [`MASK_MAX_TILT_DEG`] of level: they tell the
/// plane's extent as its measured points do (a table top whose far half the sensor drops at a
/// grazing angle), and are filled when the member is a surface ([`add_masked_points`]).
fn members_masked_points(
    scene: &SceneInput,
    members: &[&Plane],
    normal: Vector3<f32>,
    offset: f32,
    opts: &PlaneOptions,
) -> Vec<Vec<Point3<f32>>> {
    let up = Vector3::from(opts.up).normalize();
    let level = normal.dot(&up).abs() >= MASK_MAX_TILT_DEG.to_radians().cos();
    members
        .iter()
        .take(64)
        .map(|m| {
            if opts.mask_window_px > 0 && level {
                mask_points(scene, &[m.instance_id], normal, offset, opts)
            } else {
                Vec::new()
            }
        })
        .collect()
}

/// Adds to `fill` the masked points of the members that are surfaces (what the views see
/// through of their hull stays within `max_seen_through`), one a cell, in the cells no measured
/// point and no filled point holds.
fn add_masked_points(
    fill: &mut Vec<Point3<f32>>,
    masked: Vec<Vec<Point3<f32>>>,
    occupied: &HashSet<(i32, i32)>,
    unobserved: &[usize],
    seen_through: &[usize],
    cell: &dyn Fn(&Point3<f32>) -> (i32, i32),
    opts: &PlaneOptions,
) {
    let mut taken: HashSet<(i32, i32)> = fill.iter().map(cell).collect();
    for (k, masked) in masked.into_iter().enumerate() {
        if seen_through[k] as f32 > opts.max_seen_through * unobserved[k] as f32 {
            continue;
        }
        for p in masked {
            let c = cell(&p);
            if !occupied.contains(&c) && taken.insert(c) {
                fill.push(p);
            }
        }
    }
}

/// The pixels of instances `ids` without depth whose sight line meets the plane
/// `normal . p = offset` in front of the camera, where most of the instances' measured pixels
/// within `opts.mask_window_px` lie on the plane (within `opts.inlier_m` or
/// [`MASK_NOISE_SIGMAS`] of the frame's noise) (so a table leg's
/// drop-out is not put on its top): the points where they meet it.
fn mask_points(
    scene: &SceneInput,
    ids: &[u16],
    normal: Vector3<f32>,
    offset: f32,
    opts: &PlaneOptions,
) -> Vec<Point3<f32>> {
    let r = opts.mask_window_px as isize;
    let mut out = Vec::new();
    for f in &scene.frames {
        let Some(map) = &f.instances else { continue };
        let (w, h) = (map.width as usize, map.height as usize);
        let depth = f.depth.data();
        let centre = f.camera.center();
        let noise = deocc_geometry::noise::DepthNoise::estimate(&f.depth);
        let on_plane = |x: usize, y: usize| {
            let j = y * w + x;
            let q = f.camera.unproject_pixel(x as u32, y as u32, depth[j]);
            let tol = opts.inlier_m.max(MASK_NOISE_SIGMAS * noise.sigma(depth[j]));
            (normal.dot(&q.coords) - offset).abs() <= tol
        };
        for v in 0..h {
            for u in 0..w {
                let i = v * w + u;
                if depth[i] > 0.0 || !ids.contains(&map.ids[i]) {
                    continue;
                }
                // The window, then one three times as wide (every third pixel) where the first
                // holds too few measured pixels of the instance to judge.
                let (mut on, mut off) = (0u32, 0u32);
                for (r, step) in [(r, 1usize), (3 * r, 3)] {
                    (on, off) = (0, 0);
                    for y in ((v as isize - r).max(0)..=(v as isize + r).min(h as isize - 1))
                        .step_by(step)
                    {
                        for x in ((u as isize - r).max(0)..=(u as isize + r).min(w as isize - 1))
                            .step_by(step)
                        {
                            let j = y as usize * w + x as usize;
                            if depth[j] <= 0.0 || !ids.contains(&map.ids[j]) {
                                continue;
                            }
                            if on_plane(x as usize, y as usize) {
                                on += 1;
                            } else {
                                off += 1;
                            }
                        }
                    }
                    if on + off >= 3 {
                        break;
                    }
                }
                if on == 0 || 4 * off > on {
                    continue;
                }
                let ray = f.camera.unproject_pixel(u as u32, v as u32, 1.0) - centre;
                let denom = normal.dot(&ray);
                if denom.abs() < 1e-6 {
                    continue;
                }
                let t = (offset - normal.dot(&centre.coords)) / denom;
                if t > 0.0 && t < MAX_MASK_DEPTH_M {
                    out.push(centre + ray * t);
                }
            }
        }
    }
    out
}

/// A measured pixel near one without depth is on the plane within `inlier_m` or this many of
/// the frame's depth noise sigmas at its depth, whichever is more.
const MASK_NOISE_SIGMAS: f32 = 3.0;

/// The most a plane may tilt from level for its masked pixels without depth to be filled.
const MASK_MAX_TILT_DEG: f32 = 30.0;

/// The farthest a pixel without depth is put on its plane (metres along the optical axis).
const MAX_MASK_DEPTH_M: f32 = 10.0;

/// Bounding planes among the groups: every camera on one side (a wall, the floor), as the
/// group, a normal pointing to the cameras and its offset. A rectangle's corner that a hull did
/// not reach must not lie behind one that stands across its own plane (a floor's corner through
/// a wall, a wall's below the floor).
fn group_bounds(
    planes: &[Plane],
    group: &[usize],
    scene: &SceneInput,
) -> Vec<(usize, Vector3<f32>, f32)> {
    let centres: Vec<Point3<f32>> = scene.frames.iter().map(|f| f.camera.center()).collect();
    (0..planes.len())
        .filter(|&i| group[i] == i)
        .filter_map(|i| {
            facing_cameras(planes[i].normal, planes[i].offset, &centres).map(|(n, o)| (i, n, o))
        })
        .collect()
}

/// [`complete_planes`] on planes already found.
pub fn complete_found_planes(
    scene: &SceneInput,
    found: &ScenePlanes,
    opts: &PlaneOptions,
) -> PointCloud {
    let planes = &found.planes;
    let group = coplanar_groups(planes);
    let projectors: Vec<Projector> = scene.frames.iter().map(|f| f.camera.projector()).collect();
    let bounds = group_bounds(planes, &group, scene);
    let mut out = PointCloud::default();
    let (mut positions, mut colors, mut ids) = (Vec::new(), Vec::new(), Vec::new());
    let groups: std::collections::BTreeSet<usize> = group.iter().copied().collect();
    for g in groups {
        let members: Vec<&Plane> = (0..planes.len())
            .filter(|&i| group[i] == g)
            .map(|i| &planes[i])
            .collect();
        let first = members[0];
        let normal = first.normal;
        let offset = first.offset;
        // In-plane basis.
        let helper = if normal.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let e1 = normal.cross(&helper).normalize();
        let e2 = normal.cross(&e1);
        let origin = Point3::from(normal * offset);
        let s = opts.spacing_m;
        let cell = |p: &Point3<f32>| {
            let d = p - origin;
            (
                (d.dot(&e1) / s).floor() as i32,
                (d.dot(&e2) / s).floor() as i32,
            )
        };
        let masked = members_masked_points(scene, &members, normal, offset, opts);
        let flat = |p: &Point3<f32>| {
            let d = p - origin;
            Point2::new(d.dot(&e1), d.dot(&e2))
        };
        let (flats, occupied) = member_flats(&members, &masked, normal, offset, &flat, &cell, opts);
        let hulls: Vec<Vec<Point2<f32>>> = flats.iter().map(|f| convex_hull(f.clone())).collect();
        let joint_hull = convex_hull(flats.concat());
        let joint = fill_region(joint_hull.clone(), opts.min_rectangularity);
        let across: Vec<(Vector3<f32>, f32)> = bounds
            .iter()
            .filter(|(i, n, _)| group[*i] != g && n.dot(&normal).abs() < 45f32.to_radians().cos())
            .map(|(_, n, o)| (*n, *o))
            .collect();
        // Outside the observed hull, only cells on the cameras' side of the planes across.
        // (The few planes across are checked before the hull's every edge.)
        let allowed = |p: &Point3<f32>, q: &Point2<f32>| {
            across
                .iter()
                .all(|(n, o)| n.dot(&p.coords) - o > -opts.inlier_m)
                || inside(&joint_hull, q)
        };
        if joint.len() < 3 {
            continue;
        }
        let (lo, hi) = joint.iter().fold(
            (
                Point2::new(f32::MAX, f32::MAX),
                Point2::new(f32::MIN, f32::MIN),
            ),
            |(lo, hi), p| (lo.inf(p), hi.sup(p)),
        );
        let (a0, a1) = ((lo.x / s).floor() as i32, (hi.x / s).ceil() as i32);
        let (b0, b1) = ((lo.y / s).floor() as i32, (hi.y / s).ceil() as i32);
        let cells = (a1 as i64 - a0 as i64 + 1) as u64 * (b1 as i64 - b0 as i64 + 1) as u64;
        if cells > opts.max_cells {
            tracing::warn!(
                "plane of instance {} spans {cells} cells of {s} m, more than {}: not filled",
                first.instance_id,
                opts.max_cells
            );
            continue;
        }
        // Per member: the unobserved cells its own hull spans and how many of them a view sees
        // through; the hidden cells of the joint hull.
        let (mut unobserved, mut seen_through) = (vec![0usize; hulls.len()], vec![0; hulls.len()]);
        let mut hidden: Vec<(Point3<f32>, Point2<f32>)> = Vec::new();
        for a in a0..=a1 {
            for b in b0..=b1 {
                if occupied.contains(&(a, b)) {
                    continue;
                }
                let centre = Point2::new((a as f32 + 0.5) * s, (b as f32 + 0.5) * s);
                let Some(q) = fill_point(&joint, &centre, s) else {
                    continue;
                };
                let p = origin + e1 * q.x + e2 * q.y;
                if !allowed(&p, &q) {
                    continue;
                }
                let e = evidence(&p, scene, &projectors);
                for (k, h) in hulls.iter().enumerate() {
                    if inside(h, &q) {
                        unobserved[k] += 1;
                        seen_through[k] += (e == Evidence::SeenThrough) as usize;
                    }
                }
                // A cell no view measures inside the observed hull: the sensor's drop-outs on
                // a surface seen at a grazing angle, or its projector's shadow on it. Only where
                // some view's image holds it: the joint hull of several views spans ground that
                // none of them frames (the floor between two views' footprints), and nothing
                // says a surface is there.
                let dropped = opts.fill_unmeasured
                    && e == Evidence::Unmeasured
                    && inside(&joint_hull, &q)
                    && in_a_frame(&p, scene, &projectors);
                if e == Evidence::Hidden || dropped {
                    hidden.push((p, q));
                }
            }
        }
        let mut fill = solid_part(hidden, &flats, &unobserved, &seen_through, opts);
        add_masked_points(
            &mut fill,
            masked,
            &occupied,
            &unobserved,
            &seen_through,
            &cell,
            opts,
        );
        tracing::debug!(
            "plane of instance {} ({:?}): {} filled; members' unobserved cells {:?}, seen through {:?}",
            first.instance_id,
            normal,
            fill.len(),
            unobserved,
            seen_through
        );
        colors.extend(std::iter::repeat_n(first.color, fill.len()));
        ids.extend(std::iter::repeat_n(first.instance_id as u32, fill.len()));
        positions.extend(fill);
    }
    out.generated = Some(vec![Provenance::PlaneFill.code(); positions.len()]);
    out.positions = positions;
    out.colors = Some(colors);
    out.instance = Some(ids);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cell whose centre lies in the region keeps its centre; a cell the region's edge crosses
    /// gets a point just inside the edge, within the cell; a cell wholly outside gets none.
    #[test]
    fn fill_points_reach_the_region_edge() {
        // The square [0, 0.953] x [0, 0.5] (counter-clockwise); 1 cm cells.
        let poly = [
            Point2::new(0.0f32, 0.0),
            Point2::new(0.953, 0.0),
            Point2::new(0.953, 0.5),
            Point2::new(0.0, 0.5),
        ];
        let s = 0.01;
        let c = Point2::new(0.505, 0.255);
        assert_eq!(fill_point(&poly, &c, s), Some(c));
        // The cell [0.95, 0.96]: its centre lies 2 mm past the edge at x = 0.953.
        let q = fill_point(&poly, &Point2::new(0.955, 0.255), s).unwrap();
        assert!(inside(&poly, &q));
        assert!(
            q.x > 0.95 && q.x < 0.953 && (q.y - 0.255).abs() < 1e-3,
            "{q:?}"
        );
        assert_eq!(fill_point(&poly, &Point2::new(0.965, 0.255), s), None);
    }

    #[test]
    fn keep_inside_drops_only_points_beyond_the_margin_behind_a_plane() {
        // The floor z = 0 and a wall x = 2, cameras on their positive sides.
        let planes = [
            (Vector3::new(0.0, 0.0, 1.0), 0.0),
            (Vector3::new(-1.0, 0.0, 0.0), -2.0),
        ];
        let cloud = PointCloud::from_positions(vec![
            Point3::new(0.5, 0.0, 0.3),   // in the room
            Point3::new(0.5, 0.0, -0.01), // within the margin under the floor
            Point3::new(0.5, 0.0, -0.05), // under the floor
            Point3::new(2.05, 0.0, 0.3),  // behind the wall
            Point3::new(1.99, 0.0, 0.0),  // at the corner, inside
        ]);
        let (kept, dropped) = keep_inside(&cloud, &planes, 0.02);
        assert_eq!(dropped, 2);
        assert_eq!(
            kept.positions,
            vec![
                Point3::new(0.5, 0.0, 0.3),
                Point3::new(0.5, 0.0, -0.01),
                Point3::new(1.99, 0.0, 0.0)
            ]
        );
        let (all, none) = keep_inside(&cloud, &[], 0.02);
        assert_eq!((all.len(), none), (5, 0));
    }

    /// `na x nb` points `origin + i a + j b`.
    fn lattice(
        origin: [f32; 3],
        a: [f32; 3],
        na: usize,
        b: [f32; 3],
        nb: usize,
    ) -> Vec<Point3<f32>> {
        let (o, a, b) = (Point3::from(origin), Vector3::from(a), Vector3::from(b));
        (0..na)
            .flat_map(|i| (0..nb).map(move |j| o + a * i as f32 + b * j as f32))
            .collect()
    }

    /// A table top seen at a grazing angle with its front edge (a 3 cm apron) and the upper ends
    /// of two legs in view: the fitted plane is the top's, level within 0.5 mm per metre and at
    /// its height within 0.5 mm. (A last refit on the 4 cm band tilted it by ~1 cm per metre.)
    #[test]
    fn a_table_top_is_fitted_without_its_edge_and_legs() {
        let top = 0.75f32;
        let mut points = lattice(
            [-0.6, -0.4, top],
            [0.01, 0.0, 0.0],
            120,
            [0.0, 0.02, 0.0],
            40,
        );
        // The apron along the near edge, sampled densely (it faces the camera).
        points.extend(lattice(
            [-0.6, -0.4, top],
            [0.005, 0.0, 0.0],
            240,
            [0.0, 0.0, -0.003],
            10,
        ));
        // Two legs' upper ends at the near corners.
        for x in [-0.55f32, 0.55] {
            points.extend(lattice(
                [x, -0.38, top - 0.03],
                [0.0, 0.0, -0.001],
                40,
                [0.0; 3],
                1,
            ));
        }
        let (normal, offset, inliers) = fit_plane(&points, 0.015).expect("a plane");
        let (normal, offset) = if normal.z < 0.0 {
            (-normal, -offset)
        } else {
            (normal, offset)
        };
        assert!(normal.xy().norm() < 5e-4, "tilt {:?}", normal);
        // Height of the plane over the table's centre.
        let height = offset / normal.z;
        assert!((height - top).abs() < 5e-4, "height {height}");
        assert!(inliers.len() >= 120 * 40, "{} inliers", inliers.len());
    }

    /// A table whose front (apron and two legs, one vertical plane) holds more of its points than
    /// its top: the top is found as well, at its height.
    #[test]
    fn a_table_top_is_found_behind_a_larger_front() {
        let top = 0.75f32;
        let mut points = lattice(
            [-0.5, -0.35, top],
            [0.01, 0.0, 0.0],
            100,
            [0.0, 0.075, 0.0],
            10,
        );
        // The front plane y = -0.4: the apron along the top and two legs to the floor.
        points.extend(lattice(
            [-0.5, -0.4, top],
            [0.005, 0.0, 0.0],
            200,
            [0.0, 0.0, -0.01],
            6,
        ));
        for x in [-0.48f32, 0.48] {
            points.extend(lattice(
                [x, -0.4, top - 0.06],
                [0.0, 0.0, -0.0008],
                800,
                [0.0; 3],
                1,
            ));
        }
        let opts = PlaneOptions::default();
        let planes = instance_planes(points, &opts);
        assert!(planes.len() >= 2, "{} planes", planes.len());
        let front = planes
            .iter()
            .find(|(n, _, _)| n.y.abs() > 0.999)
            .expect("the front is a plane");
        let horizontal = planes
            .iter()
            .find(|(n, _, _)| n.z.abs() > 0.999)
            .expect("the top is a plane");
        let height = horizontal.1 / horizontal.0.z;
        assert!((height - top).abs() < 1e-3, "top at {height}");
        assert!(
            front.2.len() > horizontal.2.len(),
            "the front holds more points"
        );
    }

    /// A rotated table top whose corner hides behind the things at its edge: its hull fills
    /// most of its smallest rectangle, which is the true top, and is filled; a round top's hull
    /// (pi / 4 of its square) stays a hull.
    #[test]
    fn a_rectangular_top_with_a_hidden_corner_is_filled_to_its_rectangle() {
        let (c, s) = (0.3f32.cos(), 0.3f32.sin());
        let at = |x: f32, y: f32| Point2::new(2.0 + c * x - s * y, -1.0 + s * x + c * y);
        // A 1.2 x 0.8 m top on a 2 cm grid, the corner x > 0.3, y > 0.1 unseen.
        let mut seen = Vec::new();
        for i in 0..=60 {
            for j in 0..=40 {
                let (x, y) = (-0.6 + 0.02 * i as f32, -0.4 + 0.02 * j as f32);
                if !(x > 0.3 && y > 0.1) {
                    seen.push(at(x, y));
                }
            }
        }
        let hull = convex_hull(seen);
        let rect = min_area_rectangle(&hull).expect("a rectangle");
        assert!((polygon_area(&rect) - 0.96).abs() < 0.01, "{rect:?}");
        let filled = fill_region(hull.clone(), 0.8);
        assert_eq!(filled.len(), 4);
        for corner in [at(0.6, 0.4), at(-0.6, 0.4), at(0.6, -0.4)] {
            assert!(
                filled.iter().any(|q| (q - corner).norm() < 1e-3),
                "{corner:?} not in {filled:?}"
            );
        }
        // The hidden corner is inside what gets filled, and not inside the hull.
        let hidden = at(0.5, 0.3);
        assert!(inside(&filled, &hidden) && !inside(&hull, &hidden));
        // Hulls only above 1.
        assert_eq!(fill_region(hull.clone(), 1.5), hull);
        // A round top.
        let disc: Vec<Point2<f32>> = (0..90)
            .map(|k| {
                let a = k as f32 * std::f32::consts::TAU / 90.0;
                Point2::new(0.4 * a.cos(), 0.4 * a.sin())
            })
            .collect();
        let disc_hull = convex_hull(disc);
        assert_eq!(fill_region(disc_hull.clone(), 0.8), disc_hull);
    }

    #[test]
    fn the_median_absolute_deviation_of_a_few_values() {
        assert_eq!(median_abs_deviation(vec![1.0, 2.0, 3.0, 4.0, 100.0]), 1.0);
        assert_eq!(median_abs_deviation(Vec::new()), 0.0);
    }
}
