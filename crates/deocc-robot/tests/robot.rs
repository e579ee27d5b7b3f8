//! Grasp planner, analytic evaluator and placement maps on hand-built ground truth.

use deocc_robot::grasp::frame;
use deocc_robot::grasp_eval::{affordance_iou, precision, GraspOutcome, GroundTruthScene};
use deocc_robot::place::{
    build_map, build_map_seen_from, build_map_with_errors, choose_placement, compare_maps,
    find_support_planes, PlacePlanner, SupportPlane,
};
use deocc_robot::{
    AntipodalPlanner, Grasp, GraspPlanner, GripperConfig, PlaceOptions, UnseenSpace,
};
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Surface samples with normals and an instance id.
#[derive(Default)]
struct Samples {
    points: Vec<Point3<f32>>,
    normals: Vec<Vector3<f32>>,
    instance: Vec<u32>,
}

impl Samples {
    fn push(&mut self, p: Point3<f32>, n: Vector3<f32>, id: u32) {
        self.points.push(p);
        self.normals.push(n);
        self.instance.push(id);
    }

    /// A rectangle spanned by `u` and `v` from `origin`, `density` points per m^2.
    fn rect(
        &mut self,
        r: &mut impl Rng,
        origin: Point3<f32>,
        u: Vector3<f32>,
        v: Vector3<f32>,
        id: u32,
        density: f32,
    ) {
        let n = u.cross(&v).normalize();
        let count = (u.cross(&v).norm() * density) as usize;
        for _ in 0..count {
            self.push(
                origin + u * r.random::<f32>() + v * r.random::<f32>(),
                n,
                id,
            );
        }
    }

    /// A closed axis-aligned box from `lo` to `hi`.
    fn cuboid(&mut self, r: &mut impl Rng, lo: Point3<f32>, hi: Point3<f32>, id: u32) {
        let d = hi - lo;
        let (x, y, z) = (
            Vector3::new(d.x, 0.0, 0.0),
            Vector3::new(0.0, d.y, 0.0),
            Vector3::new(0.0, 0.0, d.z),
        );
        let k = 150_000.0;
        self.rect(r, lo, y, x, id, k); // bottom, normal -z
        self.rect(r, lo + z, x, y, id, k); // top
        self.rect(r, lo, x, z, id, k); // front (-y)
        self.rect(r, lo + y, z, x, id, k); // back (+y)
        self.rect(r, lo, z, y, id, k); // left (-x)
        self.rect(r, lo + x, y, z, id, k); // right (+x)
    }

    /// An upright closed cylinder standing on z = z0.
    fn cylinder(&mut self, r: &mut impl Rng, c: Point3<f32>, radius: f32, h: f32, id: u32) {
        let side = (std::f32::consts::TAU * radius * h * 150_000.0) as usize;
        for _ in 0..side {
            let a: f32 = r.random::<f32>() * std::f32::consts::TAU;
            let n = Vector3::new(a.cos(), a.sin(), 0.0);
            self.push(
                c + n * radius + Vector3::z() * (h * r.random::<f32>()),
                n,
                id,
            );
        }
        let cap = (std::f32::consts::PI * radius * radius * 150_000.0) as usize;
        for top in [false, true] {
            for _ in 0..cap {
                let (a, s): (f32, f32) = (r.random::<f32>() * std::f32::consts::TAU, r.random());
                let p = c + Vector3::new(a.cos(), a.sin(), 0.0) * (radius * s.sqrt());
                let (z, n) = if top {
                    (h, Vector3::z())
                } else {
                    (0.0, -Vector3::z())
                };
                self.push(p + Vector3::z() * z, n, id);
            }
        }
    }

    /// A table top (instance 1) at height `h` over [-0.5, 0.5]^2.
    fn table(&mut self, r: &mut impl Rng, h: f32) {
        self.rect(
            r,
            Point3::new(-0.5, -0.5, h),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(0.0, 1.0, 0.0),
            1,
            150_000.0,
        );
    }

    fn of(&self, id: u32) -> Vec<Point3<f32>> {
        self.points
            .iter()
            .zip(&self.instance)
            .filter(|(_, &i)| i == id)
            .map(|(p, _)| *p)
            .collect()
    }
}

/// The planner on the ground-truth cloud of lone boxes and cylinders: its best grasp holds at
/// mu 0.4 on at least 90% of them (the evaluator's and planner's upper bound).
#[test]
fn ground_truth_cloud_grasps_unoccluded_boxes_and_cylinders() {
    let planner = AntipodalPlanner::default();
    let g = GripperConfig::default();
    let mut r = ChaCha8Rng::seed_from_u64(5);
    let (mut ok, mut total) = (0, 0);
    for k in 0..20 {
        let mut s = Samples::default();
        let table = 0.75;
        s.table(&mut r, table);
        if k % 2 == 0 {
            let (w, d, h) = (
                r.random_range(0.03..0.07),
                r.random_range(0.03..0.07),
                r.random_range(0.05..0.2),
            );
            let c = Point3::new(r.random_range(-0.2..0.2), r.random_range(-0.2..0.2), table);
            s.cuboid(
                &mut r,
                Point3::new(c.x - w / 2.0, c.y - d / 2.0, table),
                Point3::new(c.x + w / 2.0, c.y + d / 2.0, table + h),
                2,
            );
        } else {
            let c = Point3::new(r.random_range(-0.2..0.2), r.random_range(-0.2..0.2), table);
            let (radius, h) = (r.random_range(0.015..0.035), r.random_range(0.06..0.25));
            s.cylinder(&mut r, c, radius, h, 2);
        }
        let gt = GroundTruthScene::new(&s.points, &s.normals, &s.instance).unwrap();
        let grasps = planner.plan(&s.points, &s.of(2)).unwrap();
        assert!(!grasps.is_empty(), "object {k}: no grasp");
        assert!(grasps.windows(2).all(|w| w[0].score >= w[1].score));
        total += 1;
        let out = gt.evaluate(&grasps[0], 2, &g, 10);
        if out.holds_at(0.4) {
            ok += 1;
        }
    }
    assert!(
        ok * 10 >= total * 9,
        "{ok} of {total} top grasps hold at mu 0.4"
    );
}

fn lone_box() -> (Samples, Point3<f32>) {
    let mut r = ChaCha8Rng::seed_from_u64(9);
    let mut s = Samples::default();
    s.table(&mut r, 0.75);
    let c = Point3::new(0.0, 0.0, 0.75);
    s.cuboid(
        &mut r,
        Point3::new(-0.025, -0.025, 0.75),
        Point3::new(0.025, 0.025, 0.85),
        2,
    );
    (s, c)
}

/// A top-down grasp across the box holds; the same grasp pushed down into the table collides, a
/// finger through the box collides, and one in the air beside it is empty.
#[test]
fn evaluator_catches_collisions_and_empty_grasps() {
    let (s, _) = lone_box();
    let g = GripperConfig::default();
    let gt = GroundTruthScene::new(&s.points, &s.normals, &s.instance).unwrap();
    let down = -Vector3::z();
    let across = Vector3::x();
    let grasp = |z: f32, x: f32, width: f32| {
        let r = frame(down, across);
        Grasp::new(
            Point3::new(x, 0.0, z),
            r.matrix().column(0).into(),
            r.matrix().column(1).into(),
            width,
            1.0,
            [Point3::origin(); 2],
        )
    };
    // Palm 3 cm above the top: fingers reach 2 cm down the box's sides.
    let good = gt.evaluate(&grasp(0.88, 0.0, 0.07), 2, &g, 10);
    assert!(good.holds_at(0.2), "{good:?}");
    // Palm at the table: the fingers go through the table top.
    assert!(matches!(
        gt.evaluate(&grasp(0.79, 0.0, 0.07), 2, &g, 10),
        GraspOutcome::Collision { .. }
    ));
    // Too narrow: the fingers stand inside the box.
    assert_eq!(
        gt.evaluate(&grasp(0.88, 0.0, 0.03), 2, &g, 10),
        GraspOutcome::Collision { with: 2 }
    );
    // 20 cm to the side, over the table: nothing between the jaws.
    assert_eq!(
        gt.evaluate(&grasp(0.88, 0.2, 0.07), 2, &g, 10),
        GraspOutcome::Empty
    );
    // A grasp along a diagonal slice of the box's corner: the contact normals are 45 degrees off
    // the closing line, so it holds only at mu >= 1.
    let diag = Vector3::new(1.0, 1.0, 0.0).normalize();
    let r = frame(down, diag);
    let corner = Grasp::new(
        Point3::new(0.02, -0.02, 0.88),
        r.matrix().column(0).into(),
        r.matrix().column(1).into(),
        0.05,
        1.0,
        [Point3::origin(); 2],
    );
    match gt.evaluate(&corner, 2, &g, 10) {
        GraspOutcome::Closure { mu, .. } => assert!(mu >= 1.0 - 1e-6, "mu {mu}"),
        other => assert!(matches!(other, GraspOutcome::NoClosure), "{other:?}"),
    }
}

#[test]
fn precision_counts_missing_grasps_as_failures() {
    let hold = GraspOutcome::Closure {
        mu: 0.4,
        contacts: [[0.0; 3]; 2],
    };
    let p = precision(&[hold, GraspOutcome::Collision { with: 1 }], 4);
    assert!(p.top1_at_04 && p.top1_at_08);
    // precision@k for k = 1..4: 1, 1/2, 1/3, 1/4.
    let expect = (1.0 + 0.5 + 1.0 / 3.0 + 0.25) / 4.0;
    assert!((p.ap_04 - expect).abs() < 1e-9, "{}", p.ap_04);
    // At mu 0.2 nothing holds.
    assert!((p.ap - expect * 5.0 / 6.0).abs() < 1e-9, "{}", p.ap);
    let none = precision(&[], 50);
    assert!(!none.top1_at_04 && none.ap == 0.0);
}

#[test]
fn affordance_iou_of_the_same_contacts_is_one_and_of_far_ones_zero() {
    let (s, _) = lone_box();
    let target = s.of(2);
    let c = [[0.025, 0.0, 0.8], [-0.025, 0.0, 0.8]];
    assert_eq!(affordance_iou(&target, &c, &c, 0.01).unwrap(), Some(1.0));
    let far = [[0.0, 0.025, 0.76]];
    let iou = affordance_iou(&target, &c, &far, 0.01).unwrap().unwrap();
    assert!(iou < 0.05, "{iou}");
    assert_eq!(affordance_iou(&target, &[], &[], 0.01).unwrap(), None);
}

/// A bad target (too few points) and a bad gripper are refused with the reason.
#[test]
fn planner_refuses_bad_input() {
    let (s, _) = lone_box();
    let err = AntipodalPlanner::default()
        .plan(&s.points, &s.of(2)[..5])
        .unwrap_err();
    assert!(err.to_string().contains("5 points"), "{err}");
    let mut p = AntipodalPlanner::default();
    p.options.gripper.depth = -1.0;
    let err = p.plan(&s.points, &s.of(2)).unwrap_err();
    assert!(err.to_string().contains("gripper.depth"), "{err}");
}

/// Placement: the table is found at its height; cells over the box are not placeable, open
/// table is; unseen cells follow the convention asked for; the chosen cell is valid.
#[test]
fn placement_map_over_a_table_with_a_box() {
    let (s, _) = lone_box();
    let opts = PlaceOptions {
        footprint: [0.06, 0.04],
        height: 0.1,
        ..Default::default()
    };
    let planes = find_support_planes(&s.points, &opts).unwrap();
    let table = planes[0];
    assert!((table.height - 0.75).abs() < 0.005, "{table:?}");
    assert!(
        table.bounds[0] < -0.45 && table.bounds[2] > 0.45,
        "{table:?}"
    );
    let map = build_map(&s.points, &table, &opts, UnseenSpace::AsPoints).unwrap();
    let cell_at = |x: f32, y: f32| {
        let cx = ((x - table.bounds[0]) / map.cell_m) as usize;
        let cy = ((y - table.bounds[1]) / map.cell_m) as usize;
        cy * map.nx + cx
    };
    assert!(!map.placeable[cell_at(0.0, 0.0)], "on the box");
    assert!(!map.placeable[cell_at(0.05, 0.0)], "touching the box");
    assert!(map.placeable[cell_at(0.2, 0.2)], "open table");
    assert!(
        !map.placeable[cell_at(0.485, 0.0)],
        "footprint over the edge"
    );
    let robot = Point3::new(0.0, -1.5, 1.3);
    let p = choose_placement(&map, &robot, &opts).unwrap();
    assert!(map.placeable[p.cell]);
    assert!(p.clearance_m > 0.03, "{p:?}");
    // Remove the table points around (0.3, 0.3): unseen there.
    let hole: Vec<Point3<f32>> = s
        .points
        .iter()
        .filter(|q| (q.x - 0.3).hypot(q.y - 0.3) > 0.08)
        .copied()
        .collect();
    let free = build_map(&hole, &table, &opts, UnseenSpace::Free).unwrap();
    let occupied = build_map(&hole, &table, &opts, UnseenSpace::Occupied).unwrap();
    let as_points = build_map(&hole, &table, &opts, UnseenSpace::AsPoints).unwrap();
    assert!(free.placeable[cell_at(0.3, 0.3)]);
    assert!(!occupied.placeable[cell_at(0.3, 0.3)] && !as_points.placeable[cell_at(0.3, 0.3)]);
    let workspace = vec![true; map.placeable.len()];
    let same = compare_maps(&map, &map, &workspace).unwrap();
    assert_eq!(same.iou, 1.0);
    assert_eq!(same.false_placeable_rate, 0.0);
    assert_eq!((same.missed_blocked, same.missed_unsupported), (0, 0));
    // Why the hole's cells are missed: nothing to stand on (as the points say), or taken
    // (unseen space occupied).
    let unsupported = compare_maps(&as_points, &map, &workspace).unwrap();
    assert!(unsupported.missed_unsupported > 0, "{unsupported:?}");
    assert_eq!(unsupported.missed_blocked, 0, "{unsupported:?}");
    let taken = compare_maps(&occupied, &map, &workspace).unwrap();
    assert!(taken.missed_blocked > 0, "{taken:?}");
    assert_eq!(
        taken.missed_blocked + taken.missed_unsupported,
        taken.true_placeable_cells
            - occupied
                .placeable
                .iter()
                .zip(&map.placeable)
                .filter(|(&p, &t)| p && t)
                .count(),
        "every missed cell has one reason"
    );
    // A map that forgot the box: placeable over it, all of those false.
    let no_box: Vec<Point3<f32>> = s.of(1);
    let blind = build_map(&no_box, &table, &opts, UnseenSpace::AsPoints).unwrap();
    let sc = compare_maps(&blind, &map, &workspace).unwrap();
    assert!(sc.iou < 1.0 && sc.false_placeable_rate > 0.0, "{sc:?}");
}

/// The optimistic map (unseen space free) given the camera: the floor seen past the table's front
/// edge says there is no table there, so no footprint hangs over that edge; the part of the table
/// the view does not see (behind a wall of points standing on it) stays free and supported, and
/// without the camera the cells past the edge are unseen and so supported.
#[test]
fn sight_lines_to_the_floor_past_an_edge_are_seen_empty_space() {
    let eye = Point3::new(0.0f32, -1.5, 1.6);
    let (h, half) = (0.75f32, [0.5f32, 0.3]);
    let on_table = |x: f32, y: f32| x.abs() <= half[0] && y.abs() <= half[1];
    let mut points = Vec::new();
    let step = 0.005;
    // The table top in view: not behind the wall at y = 0.1 (2 cm thick, 30 cm high).
    for i in 0..=200 {
        for j in 0..=120 {
            let (x, y) = (-0.5 + i as f32 * step, -0.3 + j as f32 * step);
            let hidden = y > 0.1 && {
                // Where the sight line to (x, y, h) meets y = 0.1.
                let t = (0.1 - eye.y) / (y - eye.y);
                eye.z + t * (h - eye.z) < h + 0.3
            };
            if !hidden {
                points.push(Point3::new(x, y, h));
            }
        }
    }
    for i in 0..=200 {
        for k in 0..=60 {
            points.push(Point3::new(
                -0.5 + i as f32 * step,
                0.1,
                h + k as f32 * step,
            ));
        }
    }
    // The floor, where a sight line reaches it past the table.
    for i in 0..=300 {
        for j in 0..=500 {
            let (x, y) = (-0.75 + i as f32 * step, -1.3 + j as f32 * step);
            let t = (h - eye.z) / (0.0 - eye.z);
            let (cx, cy) = (eye.x + t * (x - eye.x), eye.y + t * (y - eye.y));
            if !on_table(cx, cy) && cy < 0.1 {
                points.push(Point3::new(x, y, 0.0));
            }
        }
    }
    let plane = SupportPlane {
        height: h,
        bounds: [-0.6, -0.4, 0.6, 0.4],
        points: 0,
    };
    let opts = PlaceOptions::default();
    let blind = build_map(&points, &plane, &opts, UnseenSpace::Free).unwrap();
    let seeing =
        build_map_seen_from(&points, &plane, &opts, UnseenSpace::Free, Some(&eye)).unwrap();
    let cell_at = |x: f32, y: f32| {
        let cx = ((x - plane.bounds[0]) / opts.cell_m) as usize;
        let cy = ((y - plane.bounds[1]) / opts.cell_m) as usize;
        cy * blind.nx + cx
    };
    // A footprint centred 2 cm inside the front edge hangs 2 cm over it.
    let edge = cell_at(0.0, -0.28);
    assert!(blind.placeable[edge] && !blind.seen[cell_at(0.0, -0.35)]);
    assert!(!seeing.placeable[edge] && seeing.seen[cell_at(0.0, -0.35)]);
    assert!(!seeing.support[cell_at(0.0, -0.35)]);
    // In plain view, and behind the wall (never seen, no floor seen through it): placeable.
    for (x, y) in [(0.0, -0.15), (0.2, 0.22)] {
        assert!(seeing.placeable[cell_at(x, y)], "({x}, {y})");
    }
    assert!(!seeing.seen[cell_at(0.2, 0.22)]);
    // For the maps of completed clouds (as the points say) the camera changes nothing.
    let as_points = build_map(&points, &plane, &opts, UnseenSpace::AsPoints).unwrap();
    let as_points_eye =
        build_map_seen_from(&points, &plane, &opts, UnseenSpace::AsPoints, Some(&eye)).unwrap();
    assert_eq!(as_points.placeable, as_points_eye.placeable);
}

/// A table top measured with centimetre-scale depth noise is not an obstacle field: the gap over
/// the plane grows to three times the surface's own noise, and a box 4 cm high still blocks.
#[test]
fn a_noisy_table_top_is_a_surface_and_a_box_on_it_still_blocks() {
    let mut r = ChaCha8Rng::seed_from_u64(11);
    let h = 0.7;
    let mut points = Vec::new();
    for i in 0..120 {
        for j in 0..80 {
            let (x, y) = (-0.6 + i as f32 * 0.01, -0.4 + j as f32 * 0.01);
            for _ in 0..4 {
                // Gaussian noise of 5 mm (Box-Muller).
                let (a, b): (f32, f32) = (r.random_range(1e-7..1.0), r.random::<f32>());
                let g = (-2.0 * a.ln()).sqrt() * (std::f32::consts::TAU * b).cos();
                points.push(Point3::new(x, y, h + 0.005 * g));
            }
        }
    }
    // A box 10 x 10 x 4 cm at the table's centre: its top.
    for i in 0..10 {
        for j in 0..10 {
            points.push(Point3::new(
                -0.05 + i as f32 * 0.01,
                -0.05 + j as f32 * 0.01,
                h + 0.04,
            ));
        }
    }
    let plane = SupportPlane {
        height: h,
        bounds: [-0.6, -0.4, 0.6, 0.4],
        points: 0,
    };
    let adaptive = PlaceOptions::default();
    assert!(adaptive.gap_noise_sigmas > 0.0);
    let fixed = PlaceOptions {
        gap_noise_sigmas: 0.0,
        ..PlaceOptions::default()
    };
    let a = build_map(&points, &plane, &adaptive, UnseenSpace::AsPoints).unwrap();
    let f = build_map(&points, &plane, &fixed, UnseenSpace::AsPoints).unwrap();
    let share = |m: &[bool]| m.iter().filter(|&&o| o).count() as f32 / m.len() as f32;
    // With a fixed 5 mm gap, a noisy table is occupied nearly everywhere.
    assert!(share(&f.occupied) > 0.4, "{}", share(&f.occupied));
    assert!(share(&f.placeable) < 0.05);
    // Adaptive: the box's 100 cells and few others (under 1% of the table's cells).
    let occupied = a.occupied.iter().filter(|&&o| o).count();
    assert!((100..=196).contains(&occupied), "{occupied}");
    let centre = a.ny / 2 * a.nx + a.nx / 2;
    assert!(a.occupied[centre] && !a.placeable[centre]);
    assert!(share(&a.placeable) > 0.5, "{}", share(&a.placeable));
}

/// Every grasp setting has a range: values that hung the planner (10^12 approaches), scored a
/// grasp above every real one (normal_neighbours = u64::MAX), or quietly found nothing
/// (normal_neighbours 0, voxel_m 1e-30, a negative depth) are refused naming the setting, before
/// any work.
#[test]
fn grasp_settings_out_of_range_are_refused_by_name() {
    let (s, _) = lone_box();
    let target = s.of(2);
    type Set = Box<dyn Fn(&mut deocc_robot::GraspOptions)>;
    let cases: Vec<(&str, Set)> = vec![
        ("approaches", Box::new(|o| o.approaches = 1_000_000_000_000)),
        (
            "normal_neighbours",
            Box::new(|o| o.normal_neighbours = usize::MAX),
        ),
        ("normal_neighbours", Box::new(|o| o.normal_neighbours = 0)),
        ("voxel_m", Box::new(|o| o.voxel_m = 1e-30)),
        ("voxel_m", Box::new(|o| o.voxel_m = f32::NAN)),
        ("depths[0]", Box::new(|o| o.depths = vec![-1.0])),
        ("depths (entries)", Box::new(|o| o.depths = vec![0.01; 100])),
        (
            "seeds x approaches x depths",
            Box::new(|o| {
                o.seeds = 5000;
                o.approaches = 72;
            }),
        ),
        ("top_k", Box::new(|o| o.top_k = 0)),
        ("jaw_band_m", Box::new(|o| o.jaw_band_m = f32::INFINITY)),
        ("max_upward", Box::new(|o| o.max_upward = 2.0)),
        ("nms_angle_deg", Box::new(|o| o.nms_angle_deg = -1.0)),
    ];
    for (field, set) in cases {
        let mut p = AntipodalPlanner::default();
        set(&mut p.options);
        let t = std::time::Instant::now();
        let err = p.plan(&s.points, &target).unwrap_err().to_string();
        assert!(err.contains(field), "{field}: {err}");
        assert!(
            t.elapsed().as_secs_f32() < 1.0,
            "{field}: refused only after work"
        );
    }
    // The defaults still plan.
    assert!(!AntipodalPlanner::default()
        .plan(&s.points, &target)
        .unwrap()
        .is_empty());
}

/// Placement settings have ranges too; a robot position with NaN is refused (it returned
/// found = true with score NaN); a cloud of huge flat planes is refused by its map size before
/// any map is built (8 planes of 49 m took 1.7 GiB and 33 s).
#[test]
fn placement_refuses_bad_settings_nan_robots_and_maps_past_the_cell_limit() {
    use deocc_robot::{GridPlacer, PlacePlanner};
    let (s, _) = lone_box();
    for (field, set) in [
        (
            "cell_m",
            (|o: &mut PlaceOptions| o.cell_m = 1e-6) as fn(&mut PlaceOptions),
        ),
        ("gap_noise_sigmas", |o| o.gap_noise_sigmas = f32::NAN),
        ("min_plane_points", |o| o.min_plane_points = 0),
        ("max_tilt_deg", |o| o.max_tilt_deg = 90.0),
        ("distance_weight", |o| o.distance_weight = -1.0),
    ] {
        let mut o = PlaceOptions::default();
        set(&mut o);
        let err = o.validate().unwrap_err().to_string();
        assert!(err.contains(field), "{field}: {err}");
    }
    let placer = GridPlacer {
        options: PlaceOptions::default(),
        unseen: UnseenSpace::AsPoints,
        eye: None,
    };
    let err = placer
        .plan(&s.points, &Point3::new(f32::NAN, f32::NAN, f32::NAN))
        .unwrap_err()
        .to_string();
    assert!(err.contains("robot"), "{err}");
    assert!(placer.plan(&s.points, &Point3::origin()).is_ok());

    // Four flat 49 m planes at different heights, points about 10 cm apart.
    let mut planes = Vec::new();
    for level in 0..4 {
        for i in 0..500 {
            for j in 0..500 {
                if (i + j) % 3 == 0 {
                    planes.push(Point3::new(
                        i as f32 * 0.098 - 24.5,
                        j as f32 * 0.098 - 24.5,
                        level as f32,
                    ));
                }
            }
        }
    }
    let t = std::time::Instant::now();
    let err = placer
        .plan(&planes, &Point3::origin())
        .unwrap_err()
        .to_string();
    assert!(err.contains("limit"), "{err}");
    assert!(t.elapsed().as_secs_f32() < 20.0, "{:?}", t.elapsed());
}

/// Every candidate is counted once: accepted or turned down for one reason. A box wider than
/// the gripper opens across every side gets no grasp, and the plan says why.
#[test]
fn plan_stats_count_every_candidate_and_name_why_a_plan_is_empty() {
    let (s, _) = lone_box();
    let planner = AntipodalPlanner::default();
    let (grasps, st) = planner.plan_with_stats(&s.points, &s.of(2)).unwrap();
    assert!(!grasps.is_empty());
    let rejected = st.no_contact
        + st.too_wide_or_thin
        + st.palm
        + st.jaw_points
        + st.friction_share
        + st.closure_angle
        + st.collision;
    assert_eq!(rejected + st.accepted, st.candidates, "{st:?}");
    assert!(st.accepted >= grasps.len());
    assert_eq!(st.main_reason(), None);

    let mut r = ChaCha8Rng::seed_from_u64(3);
    let mut wide = Samples::default();
    wide.table(&mut r, 0.75);
    wide.cuboid(
        &mut r,
        Point3::new(-0.06, -0.06, 0.75),
        Point3::new(0.06, 0.06, 0.85),
        2,
    );
    let (grasps, st) = planner.plan_with_stats(&wide.points, &wide.of(2)).unwrap();
    assert!(grasps.is_empty(), "{} grasps on a 12 cm box", grasps.len());
    assert_eq!(st.accepted, 0);
    let why = st.main_reason().unwrap();
    assert!(why.contains("wider than the gripper opens"), "{why}");
}

/// A sensor's axial noise puts a few points of a can that fits the gripper outside its
/// surface: with the extent trimmed the planner still grasps it, measured on the extreme
/// points alone it is too wide.
#[test]
fn a_few_noisy_points_do_not_make_a_can_too_wide() {
    let mut r = ChaCha8Rng::seed_from_u64(21);
    let mut s = Samples::default();
    s.table(&mut r, 0.75);
    // A 7.4 cm can: 1.1 mm under the widest the default gripper takes with its margins.
    s.cylinder(&mut r, Point3::new(0.0, 0.0, 0.75), 0.037, 0.12, 2);
    // One point in a hundred pushed 6 mm out along its normal.
    for k in (0..s.points.len()).step_by(100) {
        if s.instance[k] == 2 {
            let n = s.normals[k];
            s.points[k] += n * 0.006;
        }
    }
    let trimmed = AntipodalPlanner::default();
    let (grasps, kept) = trimmed.plan_with_stats(&s.points, &s.of(2)).unwrap();
    assert!(!grasps.is_empty(), "no grasp with the trimmed extent");
    let extreme = AntipodalPlanner {
        options: deocc_robot::GraspOptions {
            extent_trim: 0.0,
            ..Default::default()
        },
    };
    let (_, st) = extreme.plan_with_stats(&s.points, &s.of(2)).unwrap();
    assert!(
        2 * kept.accepted >= 3 * st.accepted && st.too_wide_or_thin > 2 * kept.too_wide_or_thin,
        "trimmed {kept:?}\nextreme {st:?}"
    );
}

/// The envelope: a box whose far half is generated with 2 cm of expected error. Every grasp
/// the planner returns opens around the grown far side (no finger where the box could be), a
/// grasp whose jaws touch generated points reports less than full confidence, and errors that
/// do not match the points are refused by name.
#[test]
fn expected_errors_grow_the_target_the_fingers_must_clear() {
    let mut r = ChaCha8Rng::seed_from_u64(8);
    let mut s = Samples::default();
    s.table(&mut r, 0.75);
    s.cuboid(
        &mut r,
        Point3::new(-0.025, -0.025, 0.75),
        Point3::new(0.025, 0.025, 0.87),
        2,
    );
    // The far half (y > 0, away from a camera at -y) is generated, 2 cm uncertain.
    let errors: Vec<f32> = s
        .points
        .iter()
        .zip(&s.instance)
        .map(|(p, &i)| if i == 2 && p.y > 0.0 { 0.02 } else { 0.0 })
        .collect();
    let target = s.of(2);
    let target_errors: Vec<f32> = errors
        .iter()
        .zip(&s.instance)
        .filter(|(_, &i)| i == 2)
        .map(|(e, _)| *e)
        .collect();
    let planner = AntipodalPlanner::default();
    let (plain, _) = planner.plan_with_stats(&s.points, &target).unwrap();
    assert!(plain.iter().all(|g| g.confidence == 1.0));
    let (grasps, _) = planner
        .plan_with_errors(&s.points, Some(&errors), &target, Some(&target_errors))
        .unwrap();
    assert!(!grasps.is_empty());
    let g = GripperConfig::default();
    // The share of the target's points between the fingers' extent whose grown point lies
    // under a finger.
    let under_finger = |grasp: &deocc_robot::Grasp| {
        let (mut between, mut under) = (0usize, 0usize);
        for (p, e) in target.iter().zip(&target_errors) {
            let l = grasp.to_local(p);
            if l.x >= 0.0 && l.x <= g.depth && l.z.abs() <= g.finger_height / 2.0 {
                between += 1;
                if l.y.abs() + e > grasp.width / 2.0 + 1e-4 {
                    under += 1;
                }
            }
        }
        under as f32 / between.max(1) as f32
    };
    for grasp in &grasps {
        let share = under_finger(grasp);
        assert!(share <= 0.05, "{share} of the grown points under a finger");
    }
    // Planned on the best estimate alone, some grasp closes a finger where the box could be.
    assert!(
        plain.iter().any(|g| under_finger(g) > 0.2),
        "the plain plan already clears the envelope: {:?}",
        plain.iter().map(under_finger).collect::<Vec<_>>()
    );
    assert!(
        grasps.iter().any(|g| g.confidence < 1.0),
        "no grasp touches the generated half"
    );
    let e = planner
        .plan_with_errors(&s.points, Some(&errors[..3]), &target, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("scene"), "{e}");
    let mut bad = target_errors.clone();
    bad[0] = f32::NAN;
    let e = planner
        .plan_with_errors(&s.points, None, &target, Some(&bad))
        .unwrap_err()
        .to_string();
    assert!(e.contains("target") && e.contains("NaN"), "{e}");
}

/// The envelope's errors: the cloud's own, scaled, when `expected_error_scale` is on (observed
/// points 0 whatever they carry); the stated `generated_error_m` otherwise, with fitted
/// instances exact; nothing when both are off.
#[test]
fn the_envelope_reads_the_clouds_own_errors_when_asked() {
    use deocc_robot::grasp::envelope_errors;
    let provenance = [0u8, 1, 3, 1];
    let expected = [0.5f32, 0.01, 0.02, 0.0];
    let ids = [1u32, 1, 2, 3];
    let mut o = deocc_robot::GraspOptions::default();
    assert_eq!(
        envelope_errors(Some(&provenance), Some(&expected), Some(&ids), &[], &o),
        None
    );
    o.expected_error_scale = 2.0;
    assert_eq!(
        envelope_errors(Some(&provenance), Some(&expected), Some(&ids), &[], &o),
        Some(vec![0.0, 0.02, 0.04, 0.0])
    );
    o.generated_error_m = 0.005;
    // Without the cloud's errors, the stated one (instance 3 fitted: exact).
    assert_eq!(
        envelope_errors(Some(&provenance), None, Some(&ids), &[3], &o),
        Some(vec![0.0, 0.005, 0.005, 0.0])
    );
    assert_eq!(
        envelope_errors(None, Some(&expected), Some(&ids), &[], &o),
        None
    );
    o.expected_error_scale = 11.0;
    assert!(o
        .validate()
        .unwrap_err()
        .to_string()
        .contains("expected_error_scale"));
}

/// The place planner's envelope: a generated point with 5 cm of expected error occupies the
/// cells within 5 cm of it once `expected_error_scale` is on, and only then; errors that do not
/// match the points are refused.
#[test]
fn uncertain_generated_points_block_the_cells_they_could_occupy() {
    let (mut s, _) = lone_box();
    // A lone generated point 4 cm above the table at (0.2, 0.2).
    s.points.push(Point3::new(0.2, 0.2, 0.79));
    let mut errors = vec![0.0f32; s.points.len()];
    *errors.last_mut().unwrap() = 0.05;
    let mut opts = small_object_no_envelope();
    assert_eq!(
        PlaceOptions::default().expected_error_scale,
        1.0,
        "on by default"
    );
    let table = find_support_planes(&s.points, &opts).unwrap()[0];
    let map = |opts: &PlaceOptions, e: Option<&[f32]>| {
        build_map_with_errors(&s.points, e, &table, opts, UnseenSpace::AsPoints, None).unwrap()
    };
    let at = |m: &deocc_robot::place::PlaceMap, x: f32, y: f32| cell_at(&table, m, x, y);
    let off = map(&opts, Some(&errors));
    assert!(off.occupied[at(&off, 0.2, 0.2)]);
    assert!(!off.occupied[at(&off, 0.24, 0.2)] && off.placeable[at(&off, 0.27, 0.2)]);
    opts.expected_error_scale = 1.0;
    let on = map(&opts, Some(&errors));
    assert!(on.occupied[at(&on, 0.24, 0.2)] && on.occupied[at(&on, 0.2, 0.165)]);
    assert!(
        !on.occupied[at(&on, 0.24, 0.24)],
        "beyond 5 cm on the diagonal"
    );
    assert!(!on.placeable[at(&on, 0.27, 0.2)]);
    assert!(on.placeable[at(&on, 0.33, 0.2)]);
    // Without errors the scale changes nothing.
    assert_eq!(map(&opts, None).occupied, off.occupied);
    let e = build_map_with_errors(
        &s.points,
        Some(&errors[..3]),
        &table,
        &opts,
        UnseenSpace::AsPoints,
        None,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("3 expected errors"), "{e}");
    // The placer passes them on.
    let placer = deocc_robot::GridPlacer {
        options: opts.clone(),
        unseen: UnseenSpace::AsPoints,
        eye: None,
    };
    let robot = Point3::new(0.2, -1.0, 1.2);
    let (maps, _) = placer
        .plan_with_errors(&s.points, Some(&errors), &robot)
        .unwrap();
    assert_eq!(maps[0].occupied, on.occupied);
}

/// The hidden side's envelope: seen from one camera, a generated point occupies the cells behind
/// it along the sight line up to `hidden_side_m`, not the cells before it or beside it; an
/// observed point (no error) and a map without an eye grow nothing.
#[test]
fn generated_points_block_their_hidden_side_along_the_sight_line() {
    let (mut s, _) = lone_box();
    // A generated point 4 cm above the table at (0.2, 0.2) and an observed one at (-0.2, 0.2).
    s.points.push(Point3::new(0.2, 0.2, 0.79));
    s.points.push(Point3::new(-0.2, 0.2, 0.79));
    let mut errors = vec![0.0f32; s.points.len()];
    errors[s.points.len() - 2] = 0.005;
    let mut opts = small_object_no_envelope();
    assert_eq!(PlaceOptions::default().hidden_side_m, 0.0, "off by default");
    let table = find_support_planes(&s.points, &opts).unwrap()[0];
    // The camera looks along +y from in front of the table.
    let eye = Point3::new(0.2, -1.0, 1.5);
    let map = |opts: &PlaceOptions, eye: Option<&Point3<f32>>| {
        build_map_with_errors(
            &s.points,
            Some(&errors),
            &table,
            opts,
            UnseenSpace::AsPoints,
            eye,
        )
        .unwrap()
    };
    let at = |m: &deocc_robot::place::PlaceMap, x: f32, y: f32| cell_at(&table, m, x, y);
    let off = map(&opts, Some(&eye));
    assert!(off.occupied[at(&off, 0.2, 0.2)] && !off.occupied[at(&off, 0.2, 0.23)]);
    opts.hidden_side_m = 0.05;
    let on = map(&opts, Some(&eye));
    for y in [0.215, 0.23, 0.245] {
        assert!(on.occupied[at(&on, 0.2, y)], "behind the point, y = {y}");
    }
    assert!(!on.occupied[at(&on, 0.2, 0.265)], "beyond 5 cm");
    assert!(!on.occupied[at(&on, 0.2, 0.185)], "before the point");
    assert!(!on.occupied[at(&on, 0.225, 0.2)], "beside the point");
    assert!(
        !on.occupied[at(&on, -0.2, 0.23)],
        "observed points keep their cell"
    );
    assert_eq!(map(&opts, None).occupied, off.occupied, "no eye, no growth");
    opts.hidden_side_m = 0.6;
    assert!(opts
        .validate()
        .unwrap_err()
        .to_string()
        .contains("hidden_side_m"));
}

/// Placer settings for a 4 x 4 x 10 cm object, no dilation, no envelope.
fn small_object_no_envelope() -> PlaceOptions {
    PlaceOptions {
        footprint: [0.04, 0.04],
        height: 0.1,
        dilation_m: 0.0,
        expected_error_scale: 0.0,
        ..Default::default()
    }
}

/// The index of the cell of `m` (on `table`) holding `(x, y)`.
fn cell_at(
    table: &deocc_robot::place::SupportPlane,
    m: &deocc_robot::place::PlaceMap,
    x: f32,
    y: f32,
) -> usize {
    let cx = ((x - table.bounds[0]) / m.cell_m) as usize;
    let cy = ((y - table.bounds[1]) / m.cell_m) as usize;
    cy * m.nx + cx
}
