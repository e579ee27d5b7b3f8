mod common;

use deocc_geometry::align::{icp, umeyama, IcpMethod, IcpOptions, IcpTarget};
use deocc_geometry::camera::{look_at, Camera, Intrinsics};
use deocc_geometry::cloud::PointCloud;
use deocc_geometry::depth::{backproject, render_depth, DepthMap};
use deocc_geometry::metrics::{chamfer, mean_median, reconstruction_metrics, MetricOptions};
use deocc_geometry::normals::{estimate_normals, smallest_eigenvector};
use deocc_geometry::robust::{huber_affine_fit, least_squares_affine_fit, HuberOptions};
use deocc_geometry::voxel::{fuse_generated, voxel_downsample};
use deocc_geometry::{GeometryError, KdIndex};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use proptest::prelude::*;
use rand::Rng;

#[test]
fn nearest_neighbours_match_brute_force() {
    let data = common::random_points(5000, 1, 2.0);
    let queries = common::random_points(500, 2, 2.5);
    let index = KdIndex::build(&data).unwrap();
    let batch = index.nearest_batch(&queries);
    for (q, got) in queries.iter().zip(&batch) {
        let best = data
            .iter()
            .map(|p| (p - q).norm_squared())
            .fold(f32::INFINITY, f32::min);
        assert!(
            (got.distance_sq - best).abs() <= 1e-6 * best.max(1e-6),
            "{got:?} vs {best}"
        );
        assert!(((data[got.index as usize] - q).norm_squared() - best).abs() < 1e-5);
    }
    // k nearest: the same set of distances as sorting all.
    for q in queries.iter().take(50) {
        let mut all: Vec<f32> = data.iter().map(|p| (p - q).norm_squared()).collect();
        all.sort_by(f32::total_cmp);
        let knn = index.k_nearest(q, 30);
        assert_eq!(knn.len(), 30);
        for (a, b) in knn.iter().zip(&all) {
            assert!((a.distance_sq - b).abs() < 1e-5);
        }
        let r = 0.3;
        let within = index.within(q, r);
        assert_eq!(within.len(), all.iter().filter(|d| **d <= r * r).count());
    }
}

#[test]
fn kd_tree_rejects_empty_and_non_finite() {
    assert!(matches!(
        KdIndex::build(&[]),
        Err(GeometryError::Empty { .. })
    ));
    let bad = vec![Point3::new(0.0, f32::NAN, 0.0)];
    assert!(matches!(
        KdIndex::build(&bad),
        Err(GeometryError::NonFinite { index: 0, .. })
    ));
}

fn random_rotation(r: &mut impl Rng, max_angle: f64) -> Rotation3<f64> {
    let axis = Vector3::new(
        r.random_range(-1.0..1.0),
        r.random_range(-1.0..1.0),
        r.random_range(-1.0..1.0),
    )
    .normalize();
    Rotation3::from_axis_angle(
        &nalgebra::Unit::new_normalize(axis),
        r.random_range(-max_angle..max_angle),
    )
}

#[test]
fn umeyama_recovers_known_similarity() {
    let mut r = common::rng(7);
    for trial in 0..20 {
        let src: Vec<Point3<f64>> = (0..200)
            .map(|_| {
                Point3::new(
                    r.random_range(-1.0..1.0),
                    r.random_range(-1.0..1.0),
                    r.random_range(-1.0..1.0),
                )
            })
            .collect();
        let rotation = random_rotation(&mut r, std::f64::consts::PI);
        let scale = r.random_range(0.5..2.0);
        let t = Vector3::new(
            r.random_range(-3.0..3.0),
            r.random_range(-3.0..3.0),
            r.random_range(-3.0..3.0),
        );
        let dst: Vec<Point3<f64>> = src
            .iter()
            .map(|p| Point3::from(scale * (rotation * p.coords) + t))
            .collect();
        let sim = umeyama(&src, &dst, true).unwrap();
        assert!((sim.scale - scale).abs() < 1e-6, "trial {trial}");
        assert!((sim.rotation.matrix() - rotation.matrix()).abs().max() < 1e-6);
        assert!((sim.translation - t).abs().max() < 1e-6);
        assert!(sim.rotation.matrix().determinant() > 0.0);
    }
}

#[test]
fn umeyama_never_returns_a_reflection() {
    // Points mirrored in x: the best proper rotation, not the reflection.
    let src: Vec<Point3<f64>> = common::random_points(100, 3, 1.0)
        .iter()
        .map(|p| p.cast())
        .collect();
    let dst: Vec<Point3<f64>> = src.iter().map(|p| Point3::new(-p.x, p.y, p.z)).collect();
    let sim = umeyama(&src, &dst, true).unwrap();
    assert!((sim.rotation.matrix().determinant() - 1.0).abs() < 1e-9);
}

fn offset_10deg_5cm() -> Isometry3<f64> {
    let axis = nalgebra::Unit::new_normalize(Vector3::new(0.3, -0.5, 0.8));
    Isometry3::from_parts(
        Translation3::new(0.03, -0.03, 0.028), // |t| = 5 cm
        UnitQuaternion::from_axis_angle(&axis, 10f64.to_radians()),
    )
}

fn icp_pair(method: IcpMethod) -> (deocc_geometry::align::IcpResult, Isometry3<f64>) {
    let (target, target_normals) = common::sphere_on_box(20_000, 11);
    let (source_true, _) = common::sphere_on_box(10_000, 12);
    let truth = offset_10deg_5cm(); // source = truth * target-frame points
    let source: Vec<Point3<f32>> = source_true
        .iter()
        .map(|p| truth.transform_point(&p.cast()).cast())
        .collect();
    let tgt = IcpTarget::new(&target, Some(&target_normals)).unwrap();
    let opts = IcpOptions {
        method,
        max_correspondence_m: 0.1,
        max_iterations: 100,
        ..Default::default()
    };
    let res = icp(&source, &tgt, &Isometry3::identity(), &opts).unwrap();
    (res, truth.inverse())
}

#[test]
fn icp_converges_from_10_degrees_and_5_cm() {
    for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
        let (res, expected) = icp_pair(method);
        let err = res.target_from_source.inverse() * expected;
        let angle = err.rotation.angle().to_degrees();
        let dist = err.translation.vector.norm();
        assert!(
            angle < 0.5 && dist < 0.005,
            "{method:?}: residual {angle} deg, {dist} m"
        );
        assert!(res.fitness > 0.99, "{method:?}: fitness {}", res.fitness);
    }
}

#[test]
fn point_to_plane_converges_in_fewer_iterations() {
    let (p2p, _) = icp_pair(IcpMethod::PointToPoint);
    let (p2l, _) = icp_pair(IcpMethod::PointToPlane);
    assert!(
        p2l.iterations < p2p.iterations,
        "point-to-plane {} iterations, point-to-point {}",
        p2l.iterations,
        p2p.iterations
    );
}

#[test]
fn icp_rejects_missing_normals_for_point_to_plane() {
    let pts = common::random_points(100, 5, 1.0);
    let tgt = IcpTarget::new(&pts, None).unwrap();
    let opts = IcpOptions {
        method: IcpMethod::PointToPlane,
        ..Default::default()
    };
    assert!(icp(&pts, &tgt, &Isometry3::identity(), &opts).is_err());
}

#[test]
fn huber_fit_survives_30_percent_gross_outliers() {
    let mut r = common::rng(21);
    let (alpha, beta) = (1.7f64, 0.35f64);
    let n = 2000;
    let mut x = Vec::new();
    let mut y = Vec::new();
    for i in 0..n {
        let xi = r.random_range(0.2..1.0f64);
        let mut yi = alpha * xi + beta + r.random_range(-0.002..0.002);
        if i % 10 < 3 {
            // Gross outliers: an occluder in front or background behind, up to a metre off.
            yi += r.random_range(-1.0..1.0) + 0.5f64.copysign(r.random_range(-1.0..1.0));
        }
        x.push(xi as f32);
        y.push(yi as f32);
    }
    let fit = huber_affine_fit(&x, &y, &HuberOptions::default()).unwrap();
    assert!(
        (fit.alpha - alpha).abs() / alpha < 0.01,
        "alpha {}",
        fit.alpha
    );
    assert!((fit.beta - beta).abs() / beta < 0.01, "beta {}", fit.beta);
    assert!(fit.inlier_fraction > 0.6 && fit.inlier_fraction < 0.8);
    let (la, lb) = least_squares_affine_fit(&x, &y).unwrap();
    assert!(
        (la - alpha).abs() / alpha > 0.01 || (lb - beta).abs() / beta > 0.01,
        "least squares should be dragged by the outliers: {la} {lb}"
    );
}

#[test]
fn huber_fit_rejects_bad_samples() {
    assert!(huber_affine_fit(&[1.0], &[1.0], &HuberOptions::default()).is_err());
    assert!(huber_affine_fit(&[1.0, 2.0], &[1.0], &HuberOptions::default()).is_err());
    assert!(huber_affine_fit(&[1.0, f32::NAN], &[1.0, 2.0], &HuberOptions::default()).is_err());
    assert!(
        huber_affine_fit(&[1.0, 1.0, 1.0], &[1.0, 2.0, 3.0], &HuberOptions::default()).is_err()
    );
}

#[test]
fn intrinsics_reject_bad_values() {
    assert!(Intrinsics::new(0.0, 500.0, 320.0, 240.0, 640, 480).is_err());
    assert!(Intrinsics::new(500.0, -1.0, 320.0, 240.0, 640, 480).is_err());
    assert!(Intrinsics::new(f32::NAN, 500.0, 320.0, 240.0, 640, 480).is_err());
    assert!(Intrinsics::new(500.0, 500.0, 320.0, 240.0, 0, 480).is_err());
}

proptest! {
    #[test]
    fn unproject_inverts_project(x in -2.0f32..2.0, y in -2.0f32..2.0, z in 0.1f32..10.0,
                                 fx in 100.0f32..1000.0, fy in 100.0f32..1000.0) {
        let k = Intrinsics::new(fx, fy, 320.0, 240.0, 640, 480).unwrap();
        let p = Point3::new(x, y, z);
        let px = k.project(&p).unwrap();
        let back = k.unproject(px.x, px.y, z);
        prop_assert!((back - p).norm() <= 1e-5 * (1.0 + p.coords.norm()));
    }

    #[test]
    fn world_projection_round_trips(x in -1.0f32..1.0, y in -1.0f32..1.0, z in 0.5f32..3.0,
                                    yaw in -3.0f32..3.0) {
        let k = Intrinsics::new(500.0, 500.0, 320.0, 240.0, 640, 480).unwrap();
        let pose = Isometry3::from_parts(Translation3::new(0.3, -0.2, 1.0),
                                         UnitQuaternion::from_euler_angles(0.1, yaw, 0.2));
        let cam = Camera { intrinsics: k, world_from_camera: pose };
        let p_world = pose.transform_point(&Point3::new(x, y, z));
        let (px, depth) = cam.project_world(&p_world).unwrap();
        prop_assert!((depth - z).abs() < 1e-4);
        let back = pose.transform_point(&k.unproject(px.x, px.y, depth));
        prop_assert!((back - p_world).norm() < 1e-4);
    }

    #[test]
    fn rigid_inverse_is_identity(a in -3.0f64..3.0, b in -3.0f64..3.0, c in -3.0f64..3.0, t in -5.0f64..5.0) {
        let iso = Isometry3::from_parts(Translation3::new(t, -t, 0.5 * t), UnitQuaternion::from_euler_angles(a, b, c));
        let id = iso.inverse() * iso;
        prop_assert!(id.translation.vector.norm() < 1e-9);
        prop_assert!(id.rotation.angle() < 1e-7);
    }
}

#[test]
fn depth_backprojection_and_rendering_agree() {
    let k = Intrinsics::new(100.0, 100.0, 32.0, 24.0, 64, 48).unwrap();
    let pose = look_at(
        &Point3::new(0.0, -1.0, 1.0),
        &Point3::origin(),
        &Vector3::z(),
    )
    .unwrap();
    let cam = Camera {
        intrinsics: k,
        world_from_camera: pose,
    };
    let mut depth = DepthMap::zeros(64, 48);
    for v in 0..48 {
        for u in 0..64 {
            if (u + v) % 7 != 0 {
                depth.set(u, v, 1.0 + 0.01 * u as f32);
            }
        }
    }
    let (cloud, pixels) = backproject(&depth, &cam).unwrap();
    assert_eq!(cloud.len(), depth.valid_count());
    assert_eq!(pixels.len(), cloud.len());
    let rendered = render_depth(&cloud.positions, &cam, 0);
    for (i, &d) in depth.data().iter().enumerate() {
        assert!(
            (rendered.data()[i] - d).abs() < 1e-4,
            "pixel {i}: {} vs {d}",
            rendered.data()[i]
        );
    }
    // Wrong size is an error, not a panic.
    let small = DepthMap::zeros(10, 10);
    assert!(backproject(&small, &cam).is_err());
}

#[test]
fn depth_map_rejects_nan_and_wrong_size() {
    assert!(DepthMap::new(2, 2, vec![1.0, f32::NAN, 1.0, 1.0]).is_err());
    assert!(DepthMap::new(2, 2, vec![1.0, f32::INFINITY, 1.0, 1.0]).is_err());
    assert!(DepthMap::new(2, 2, vec![1.0; 3]).is_err());
    assert!(DepthMap::new(2, 2, vec![1.0, -1.0, 1.0, 1.0]).is_err());
}

#[test]
fn metrics_of_a_shifted_copy() {
    let gt = common::random_points(20_000, 31, 1.0);
    let shift = 0.01f32;
    let pred: Vec<Point3<f32>> = gt
        .iter()
        .map(|p| p + Vector3::new(0.0, 0.0, shift))
        .collect();
    let m =
        reconstruction_metrics(&pred, None, &gt, None, None, &MetricOptions::default()).unwrap();
    // Every point's nearest is at most `shift` away; on a dense cloud it is close to shift.
    assert!(m.accuracy_mean <= shift as f64 + 1e-6 && m.accuracy_mean > 0.5 * shift as f64);
    assert!((m.chamfer - (m.accuracy_mean + m.completeness_mean) / 2.0).abs() < 1e-12);
    assert_eq!(m.precision, 1.0);
    assert_eq!(m.fscore, 1.0);
    let (ab, ba, c) = chamfer(&pred, &gt).unwrap();
    assert!((ab - m.accuracy_mean).abs() < 1e-9 && (ba - m.completeness_mean).abs() < 1e-9);
    assert!((c - m.chamfer).abs() < 1e-9);
}

#[test]
fn completeness_on_a_subset_sees_the_hole() {
    // Ground truth: two clusters far apart; prediction: only the first. Completeness over the whole
    // GT is poor, over the first cluster perfect, over the second about the gap.
    let a = common::random_points(2000, 41, 0.5);
    let b: Vec<Point3<f32>> = a.iter().map(|p| p + Vector3::new(5.0, 0.0, 0.0)).collect();
    let gt: Vec<Point3<f32>> = a.iter().chain(&b).copied().collect();
    let first: Vec<bool> = (0..gt.len()).map(|i| i < a.len()).collect();
    let second: Vec<bool> = first.iter().map(|f| !f).collect();
    let opts = MetricOptions::default();
    let m1 = reconstruction_metrics(&a, None, &gt, None, Some(&first), &opts).unwrap();
    let m2 = reconstruction_metrics(&a, None, &gt, None, Some(&second), &opts).unwrap();
    assert_eq!(m1.completeness_mean, 0.0);
    assert_eq!(m1.recall, 1.0);
    assert!(m2.completeness_mean > 4.0 && m2.recall == 0.0);
    assert!(reconstruction_metrics(&a, None, &gt, None, Some(&first[..10]), &opts).is_err());
}

#[test]
fn mean_median_matches_numpy_conventions() {
    assert_eq!(mean_median(&[3.0, 1.0, 2.0]), (2.0, 2.0));
    assert_eq!(mean_median(&[4.0, 1.0, 2.0, 3.0]), (2.5, 2.5));
}

#[test]
fn normals_of_known_surfaces() {
    let (pts, truth) = common::sphere_on_box(20_000, 51);
    let normals = estimate_normals(&pts, 30).unwrap();
    // Away from edges the PCA normal matches the analytic one up to sign.
    let good = normals
        .iter()
        .zip(&truth)
        .filter(|(n, t)| n.dot(t).abs() > 0.95)
        .count();
    assert!(
        good as f64 / pts.len() as f64 > 0.85,
        "{good} of {}",
        pts.len()
    );
    for n in &normals {
        assert!((n.norm() - 1.0).abs() < 1e-4);
    }
}

#[test]
fn closed_form_eigenvector_matches_general_solver() {
    let mut r = common::rng(61);
    for _ in 0..1000 {
        let m = Matrix3::from_fn(|_, _| r.random_range(-1.0..1.0f64));
        let a = m * m.transpose();
        let v = smallest_eigenvector(&a);
        let eig = a.symmetric_eigen();
        let i = eig.eigenvalues.imin();
        let truth = eig.eigenvectors.column(i);
        let gap = {
            let mut e: Vec<f64> = eig.eigenvalues.iter().copied().collect();
            e.sort_by(f64::total_cmp);
            e[1] - e[0]
        };
        if gap > 1e-6 {
            assert!(v.dot(&truth).abs() > 1.0 - 1e-6, "{v} vs {truth}");
        }
    }
}

#[test]
fn voxel_downsample_keeps_one_point_per_voxel_and_observed_wins() {
    let pts = common::random_points(50_000, 71, 1.0);
    let mut cloud = PointCloud::from_positions(pts.clone());
    cloud.generated = Some((0..pts.len()).map(|i| (i % 2) as u8).collect());
    cloud.instance = Some((0..pts.len()).map(|i| (i % 3) as u32).collect());
    let voxel = 0.2;
    let down = voxel_downsample(&cloud, voxel).unwrap();
    let (lo, _) = cloud.bounds().unwrap();
    let origin = lo.cast::<f64>() - Vector3::repeat(voxel * 0.5);
    let keys: std::collections::HashSet<[i32; 3]> = pts
        .iter()
        .map(|p| {
            let q = (p.cast::<f64>() - origin) / voxel;
            [q.x.floor() as i32, q.y.floor() as i32, q.z.floor() as i32]
        })
        .collect();
    assert_eq!(down.len(), keys.len());
    down.validate().unwrap();
    // Voxels hold ~50 points of both provenances, so every voxel keeps "observed".
    assert!(down.generated.as_ref().unwrap().iter().all(|&g| g == 0));
    assert!(voxel_downsample(&cloud, 0.0).is_err());
}

#[test]
fn confidence_is_averaged_over_the_winning_provenance_and_filled_with_one() {
    use nalgebra::Point3;
    // One voxel: two generated points (0.2, 0.6) and, in a second voxel, generated points only.
    let mut cloud = PointCloud::from_positions(vec![
        Point3::new(0.01, 0.01, 0.01),
        Point3::new(0.02, 0.01, 0.01),
        Point3::new(0.03, 0.01, 0.01),
        Point3::new(0.51, 0.01, 0.01),
        Point3::new(0.52, 0.01, 0.01),
    ]);
    cloud.generated = Some(vec![1, 1, 0, 1, 1]);
    cloud.confidence = Some(vec![0.2, 0.6, 1.0, 0.2, 0.6]);
    let down = voxel_downsample(&cloud, 0.1).unwrap();
    assert_eq!(down.len(), 2);
    // The first voxel holds an observed point: observed, confidence 1 (not the mean 0.6).
    assert_eq!(down.generated.as_deref(), Some(&[0u8, 1][..]));
    let conf = down.confidence.as_deref().unwrap();
    assert_eq!(conf[0], 1.0);
    assert!((conf[1] - 0.4).abs() < 1e-6, "{conf:?}");
    // Appending a cloud without confidences gives its points 1 (they are observed).
    let mut both = PointCloud::from_positions(vec![Point3::origin()]);
    both.append(&down);
    assert_eq!(both.confidence.as_deref().unwrap()[0], 1.0);
    assert_eq!(both.confidence.as_ref().unwrap().len(), 3);
    // Fusion keeps the generated points' confidence and gives observed ones 1.
    let observed = PointCloud::from_positions(vec![Point3::new(5.0, 5.0, 5.0)]);
    let fused = fuse_generated(&observed, &cloud.filter(|i| i != 2), 0.1).unwrap();
    assert_eq!(fused.len(), 3);
    let conf = fused.confidence.as_deref().unwrap();
    assert_eq!(conf[0], 1.0);
    assert!(
        conf[1..].iter().all(|&c| (c - 0.4).abs() < 1e-6),
        "{conf:?}"
    );
    let mut bad = cloud.clone();
    bad.confidence = Some(vec![1.0; 2]);
    assert!(matches!(
        bad.validate(),
        Err(GeometryError::SizeMismatch {
            what: "confidences",
            ..
        })
    ));
}

/// A point's expected error travels with it: averaged like the confidence over the voxel's
/// winning provenance (observed points count 0), 0 for points appended without one, selected
/// with its point; a negative or non-finite error is refused by name.
#[test]
fn expected_errors_travel_with_their_points() {
    use nalgebra::Point3;
    let mut cloud = PointCloud::from_positions(vec![
        Point3::new(0.01, 0.01, 0.01),
        Point3::new(0.02, 0.01, 0.01),
        Point3::new(0.03, 0.01, 0.01),
        Point3::new(0.51, 0.01, 0.01),
        Point3::new(0.52, 0.01, 0.01),
    ]);
    cloud.generated = Some(vec![1, 1, 0, 1, 1]);
    cloud.expected_error = Some(vec![0.01, 0.03, 0.0, 0.02, 0.04]);
    cloud.validate().unwrap();
    let down = voxel_downsample(&cloud, 0.1).unwrap();
    let e = down.expected_error.as_deref().unwrap();
    assert_eq!(e[0], 0.0, "the observed point wins its voxel");
    assert!((e[1] - 0.03).abs() < 1e-6, "{e:?}");
    let picked = cloud.select(&[4, 1]);
    assert_eq!(picked.expected_error.as_deref(), Some(&[0.04f32, 0.03][..]));
    let observed = PointCloud::from_positions(vec![Point3::new(5.0, 5.0, 5.0)]);
    let fused = fuse_generated(&observed, &cloud.filter(|i| i != 2), 0.1).unwrap();
    let e = fused.expected_error.as_deref().unwrap();
    assert_eq!(e.len(), 3);
    assert_eq!(
        e[0], 0.0,
        "an observed point appended without errors is exact"
    );
    assert!(
        (e[1] - 0.02).abs() < 1e-6 && (e[2] - 0.03).abs() < 1e-6,
        "{e:?}"
    );
    let uniform = PointCloud::from_positions(vec![Point3::origin(); 2]).with_expected_error(0.005);
    assert_eq!(uniform.expected_error, Some(vec![0.005; 2]));
    for bad_value in [-0.01, f32::NAN, f32::INFINITY] {
        let mut bad = cloud.clone();
        bad.expected_error.as_mut().unwrap()[3] = bad_value;
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("expected error") && e.contains("index 3"), "{e}");
    }
    let mut short = cloud.clone();
    short.expected_error = Some(vec![0.0; 4]);
    assert!(matches!(
        short.validate(),
        Err(GeometryError::SizeMismatch {
            what: "expected errors",
            ..
        })
    ));
}

#[test]
fn fusion_adds_only_new_surface() {
    let observed = PointCloud::from_positions(common::random_points(5000, 81, 0.5));
    let mut generated_pts = common::random_points(5000, 82, 0.5); // same region: duplicates
    generated_pts.extend(
        common::random_points(5000, 83, 0.5)
            .iter()
            .map(|p| p + Vector3::new(3.0, 0.0, 0.0)),
    );
    let generated = PointCloud::from_positions(generated_pts);
    // 0.2 m voxels hold ~40 observed points each, so every voxel of the first region is occupied.
    let fused = fuse_generated(&observed, &generated, 0.2).unwrap();
    let flags = fused.generated.as_ref().unwrap();
    assert_eq!(flags.iter().filter(|&&g| g == 0).count(), observed.len());
    // Every generated point kept lies in the new region.
    for (p, g) in fused.positions.iter().zip(flags) {
        if *g == 1 {
            assert!(p.x > 2.0);
        }
    }
    assert!(flags.iter().filter(|&&g| g == 1).count() > 100);
}

#[test]
fn cloud_validation_names_the_problem() {
    let mut c = PointCloud::from_positions(vec![Point3::origin(); 3]);
    c.colors = Some(vec![[0, 0, 0]; 2]);
    assert!(matches!(
        c.validate(),
        Err(GeometryError::SizeMismatch { what: "colors", .. })
    ));
    let c = PointCloud::from_positions(vec![Point3::new(f32::INFINITY, 0.0, 0.0)]);
    assert!(matches!(c.validate(), Err(GeometryError::NonFinite { .. })));
    assert!(PointCloud::default()
        .require_non_empty("prediction")
        .is_err());
}

#[test]
fn projector_agrees_with_project_world() {
    let camera = Camera {
        intrinsics: Intrinsics::new(525.0, 520.0, 319.5, 241.0, 640, 480).unwrap(),
        world_from_camera: look_at(
            &Point3::new(1.2, -0.7, 1.4),
            &Point3::new(0.1, 0.2, 0.6),
            &Vector3::z(),
        )
        .unwrap(),
    };
    let projector = camera.projector();
    let mut rng = rand::rng();
    for _ in 0..1000 {
        let p = Point3::new(
            rng.random_range(-1.0..1.5f32),
            rng.random_range(-1.0..1.5f32),
            rng.random_range(0.0..1.5f32),
        );
        match (camera.project_world(&p), projector.project(&p)) {
            // Right at the camera plane the pixel coordinates explode and any rounding shows.
            (Some((_, z)), _) if z < 0.05 => {}
            (Some((px, z)), Some((x, y, z2))) => {
                let tol = |a: f32| 1e-2 + 1e-5 * a.abs();
                assert!(
                    (px.x - x).abs() < tol(x) && (px.y - y).abs() < tol(y),
                    "{px} vs {x} {y}"
                );
                assert!((z - z2).abs() < 1e-5);
            }
            (None, None) => {}
            (a, b) => panic!("disagree at {p}: {a:?} vs {b:?}"),
        }
    }
}

/// Answering queries in Morton order changes nothing but the speed: every query gets the same
/// neighbour as a brute-force search, and the order is a permutation.
#[test]
fn nearest_batch_in_morton_order_matches_brute_force() {
    use deocc_geometry::knn::morton_order;
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let pts: Vec<nalgebra::Point3<f32>> = (0..2000)
        .map(|_| nalgebra::Point3::new(rng.random(), rng.random::<f32>() * 3.0, rng.random()))
        .collect();
    let queries: Vec<nalgebra::Point3<f32>> = (0..700)
        .map(|_| nalgebra::Point3::new(rng.random(), rng.random::<f32>() * 3.0, rng.random()))
        .collect();
    let mut order = morton_order(&queries);
    let index = deocc_geometry::KdIndex::build(&pts).unwrap();
    let got = index.nearest_batch(&queries);
    for (q, nb) in queries.iter().zip(&got) {
        let best = pts
            .iter()
            .map(|p| (p - q).norm_squared())
            .fold(f32::INFINITY, f32::min);
        assert!(
            (nb.distance_sq - best).abs() <= 1e-6,
            "{} vs {best}",
            nb.distance_sq
        );
    }
    order.sort_unstable();
    assert_eq!(order, (0..700).collect::<Vec<u32>>());
}
