//! Each effect of the sensor models shows on geometry with a known answer: axial noise grows with
//! depth and incidence as the model says, disparity comes in its steps, the emitter's shadow is
//! the band the geometry predicts beside a near edge (on the side away from the emitter), edges
//! jitter while surfaces stay, flying pixels lie between the two sides of an edge, grazing,
//! random and speckle drop-outs have their rates, and randomised sensors stay in their ranges.

use deocc_geometry::camera::{Camera, Intrinsics};
use deocc_synth::render::{rasterize, Frame, SceneTriangles};
use deocc_synth::sensor::{
    axial_noise, emitter_shadow, flying_pixels, grazing_dropout, incidence_deg, lateral_edge_noise,
    quantise_disparity, speckle_holes, AxialNoise, ColourRealism, Sensor, SensorKind,
};
use nalgebra::{Isometry3, Point3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const W: u32 = 160;
const H: u32 = 120;
const FX: f32 = 150.0;

fn camera() -> Camera {
    Camera {
        intrinsics: Intrinsics::new(FX, FX, W as f32 / 2.0, H as f32 / 2.0, W, H).unwrap(),
        world_from_camera: Isometry3::identity(),
    }
}

/// Quads (two triangles each) given by their four corners, one object per quad.
fn quads(qs: &[[Point3<f32>; 4]]) -> SceneTriangles {
    let mut t = SceneTriangles {
        corners: Vec::new(),
        normals: Vec::new(),
        object: Vec::new(),
        object_ranges: Vec::new(),
    };
    for (k, q) in qs.iter().enumerate() {
        let start = t.corners.len();
        for tri in [[q[0], q[1], q[2]], [q[0], q[2], q[3]]] {
            let n = (tri[1] - tri[0]).cross(&(tri[2] - tri[0])).normalize();
            t.corners.push(tri);
            t.normals.push(n);
            t.object.push(k as u16);
        }
        t.object_ranges.push(start..t.corners.len());
    }
    t
}

/// A wall facing the camera at depth `z`, `half` metres each way.
fn wall(z: f32, half: f32) -> [Point3<f32>; 4] {
    [
        Point3::new(-half, -half, z),
        Point3::new(half, -half, z),
        Point3::new(half, half, z),
        Point3::new(-half, half, z),
    ]
}

/// A wall through (0, 0, z) turned by `deg` about the y axis.
fn tilted_wall(z: f32, deg: f32) -> [Point3<f32>; 4] {
    let (s, c) = deg.to_radians().sin_cos();
    let x = Vector3::new(c, 0.0, s) * 20.0;
    let y = Vector3::new(0.0, 20.0, 0.0);
    let o = Point3::new(0.0, 0.0, z);
    [o - x - y, o + x - y, o + x + y, o - x + y]
}

/// A plate at 1 m covering x > 0 (the right half of the image).
fn plate() -> [Point3<f32>; 4] {
    [
        Point3::new(0.0, -3.0, 1.0),
        Point3::new(3.0, -3.0, 1.0),
        Point3::new(3.0, 3.0, 1.0),
        Point3::new(0.0, 3.0, 1.0),
    ]
}

fn render(tris: &SceneTriangles) -> Frame {
    let mut f = Frame::new(W, H);
    rasterize(
        &camera(),
        tris,
        0..tris.corners.len(),
        &|ti| tris.object[ti] + 1,
        &mut f,
    );
    f
}

fn std_dev(v: &[f32]) -> f32 {
    let m = v.iter().sum::<f32>() / v.len() as f32;
    (v.iter().map(|x| (x - m).powi(2)).sum::<f32>() / v.len() as f32).sqrt()
}

#[test]
fn axial_noise_grows_with_depth_and_incidence_as_the_model_says() {
    let model = Sensor::structured_light().axial;
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut measured = Vec::new();
    for z in [1.0f32, 2.0, 3.5] {
        let tris = quads(&[wall(z, 50.0)]);
        let clean = render(&tris);
        let mut f = clean.clone();
        let inc = incidence_deg(&f, &camera(), &tris);
        axial_noise(&mut f, &inc, &model, &mut rng);
        // Near the image centre the incidence is under 10 degrees.
        let errs: Vec<f32> = (0..f.depth_m.len())
            .filter(|&i| inc[i] < 10.0)
            .map(|i| f.depth_m[i] - clean.depth_m[i])
            .collect();
        let s = std_dev(&errs);
        let want = model.sigma(z, 5f32.to_radians());
        assert!(
            (s / want - 1.0).abs() < 0.15,
            "z {z}: measured sigma {s}, model {want}"
        );
        measured.push(s);
    }
    assert!(
        measured[0] < measured[1] && measured[1] < measured[2],
        "{measured:?}"
    );
    // 2 m, Nguyen et al.'s figure: 0.0012 + 0.0019 * 1.6^2 = 6.1 mm.
    assert!((model.sigma(2.0, 0.0) - 0.00606).abs() < 1e-4);
    // Incidence: the published term is small until near grazing (+14% at 70 degrees, +75% at
    // 80 at 2 m).
    let at = |deg: f32| model.sigma(2.0, deg.to_radians()) / model.sigma(2.0, 0.0);
    assert!((at(70.0) - 1.14).abs() < 0.02, "{}", at(70.0));
    assert!((at(80.0) - 1.75).abs() < 0.05, "{}", at(80.0));
    let tris = quads(&[tilted_wall(2.0, 78.0)]);
    let clean = render(&tris);
    let mut f = clean.clone();
    let inc = incidence_deg(&f, &camera(), &tris);
    axial_noise(&mut f, &inc, &model, &mut rng);
    let errs: Vec<f32> = (0..f.depth_m.len())
        .filter(|&i| (clean.depth_m[i] - 2.0).abs() < 0.1 && inc[i] > 76.0)
        .map(|i| f.depth_m[i] - clean.depth_m[i])
        .collect();
    assert!(errs.len() > 50, "{}", errs.len());
    assert!(
        std_dev(&errs) > 1.25 * measured[1],
        "{} vs {}",
        std_dev(&errs),
        measured[1]
    );
}

#[test]
fn disparity_comes_in_its_steps() {
    // A wall turned 40 degrees: smooth depth from about 1.3 to 3.5 m across the image.
    let tris = quads(&[tilted_wall(2.0, 40.0)]);
    let mut f = render(&tris);
    let (b, steps) = (0.075f32, 8.0f32);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    quantise_disparity(&mut f, FX, b, steps, 0.0, &mut rng);
    let mut values: Vec<f32> = f.depth_m.iter().copied().filter(|&d| d > 0.0).collect();
    for &z in &values {
        let d = FX * b / z * steps;
        assert!((d - d.round()).abs() < 2e-3, "disparity {d} not on a step");
    }
    values.sort_by(f32::total_cmp);
    values.dedup();
    // At 2 m the step is z^2 / (f b steps) = 4 / 90 = 4.4 cm; the image holds a few dozen steps.
    let near_2m = values
        .windows(2)
        .find(|w| w[0] <= 2.0 && w[1] > 2.0)
        .unwrap();
    let step = near_2m[1] - near_2m[0];
    assert!(
        (step / (4.0 / 90.0) - 1.0).abs() < 0.1,
        "step at 2 m {step}"
    );
    assert!(
        values.len() > 10 && values.len() < 200,
        "{} levels",
        values.len()
    );
}

#[test]
fn the_emitters_shadow_is_the_band_the_geometry_predicts() {
    // A plate at 1 m covering x > 0, a wall at 2 m. The emitter at +x sees past the plate's
    // left edge: the wall is shadowed in a band fx * b * (1/1 - 1/2) pixels wide just left of
    // the plate (5.6 px at b = 7.5 cm), and nowhere else.
    let plate = plate();
    let tris = quads(&[wall(2.0, 50.0), plate]);
    let clean = render(&tris);
    for b in [0.075f32, 0.05] {
        let mut f = clean.clone();
        let removed = emitter_shadow(&mut f, &camera(), &tris, b);
        let want = FX * b * 0.5;
        let mut widths = Vec::new();
        for v in 20..100usize {
            let row = &f.depth_m[v * W as usize..(v + 1) * W as usize];
            let clean_row = &clean.depth_m[v * W as usize..(v + 1) * W as usize];
            let edge = (0..W as usize).find(|&u| clean_row[u] < 1.5).unwrap();
            let band: Vec<usize> = (0..W as usize).filter(|&u| row[u] == 0.0).collect();
            // Every shadowed pixel is on the wall, just left of the edge.
            for &u in &band {
                assert!(
                    u < edge && edge - u <= (want.ceil() as usize + 1),
                    "b {b}: pixel {u}, edge {edge}"
                );
            }
            widths.push(band.len() as f32);
        }
        let mean = widths.iter().sum::<f32>() / widths.len() as f32;
        assert!(
            (mean - want).abs() < 1.0,
            "b {b}: band {mean} px, geometry says {want}"
        );
        assert!(removed > 0);
    }
    // An emitter at the camera casts no shadow.
    let mut f = clean.clone();
    assert_eq!(emitter_shadow(&mut f, &camera(), &tris, 0.0), 0);
}

#[test]
fn edges_jitter_sideways_while_surfaces_stay() {
    let plate = plate();
    let clean = render(&quads(&[wall(2.0, 50.0), plate]));
    let mut f = clean.clone();
    lateral_edge_noise(&mut f, 0.8, &mut ChaCha8Rng::seed_from_u64(3));
    let w = W as usize;
    let edge = (0..w).find(|&u| clean.depth_m[60 * w + u] < 1.5).unwrap();
    let (mut near, mut far) = (0, 0);
    for v in 0..H as usize {
        for u in 0..w {
            let i = v * w + u;
            if f.depth_m[i] != clean.depth_m[i] {
                if u.abs_diff(edge) <= 4 {
                    near += 1;
                } else {
                    far += 1;
                }
            }
        }
    }
    assert_eq!(far, 0, "pixels away from the edge changed");
    // About half the pixels beside the edge take the other side's depth.
    assert!(
        near > H as usize / 2,
        "the edge did not move ({near} pixels)"
    );
    // The edge's position varies along it.
    let cols: Vec<usize> = (0..H as usize)
        .map(|v| (0..w).find(|&u| f.depth_m[v * w + u] < 1.5).unwrap())
        .collect();
    assert!(cols.iter().any(|&c| c != cols[0]));
}

#[test]
fn flying_pixels_lie_between_the_two_sides_of_an_edge() {
    let plate = plate();
    let clean = render(&quads(&[wall(2.0, 50.0), plate]));
    let mut f = clean.clone();
    flying_pixels(&mut f, 0.7, &mut ChaCha8Rng::seed_from_u64(4));
    let changed: Vec<f32> = (0..f.depth_m.len())
        .filter(|&i| f.depth_m[i] != clean.depth_m[i])
        .map(|i| f.depth_m[i])
        .collect();
    // Two columns (one each side) of 120 rows, 70% of them.
    assert!(
        (changed.len() as f32 - 0.7 * 240.0).abs() < 40.0,
        "{} flying pixels",
        changed.len()
    );
    assert!(changed.iter().all(|&d| (1.0..=2.0).contains(&d)));
    assert!(changed.iter().filter(|&&d| d > 1.1 && d < 1.9).count() > changed.len() / 2);
}

#[test]
fn grazing_random_and_speckle_dropouts_have_their_rates() {
    let s = Sensor::structured_light();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for (deg, lost_min, lost_max) in [(10.0f32, 0.0, 0.0), (72.5, 0.3, 0.7), (85.0, 1.0, 1.0)] {
        let tris = quads(&[tilted_wall(2.0, deg)]);
        let mut f = render(&tris);
        let inc = incidence_deg(&f, &camera(), &tris);
        // Only the pixels whose incidence is near the wall's angle (the centre column).
        let idx: Vec<usize> = (0..f.depth_m.len())
            .filter(|&i| f.depth_m[i] > 0.0 && (inc[i] - deg).abs() < 2.5)
            .collect();
        assert!(idx.len() > 20, "{deg}: {} pixels", idx.len());
        grazing_dropout(&mut f, &inc, s.ramp_deg, s.drop_deg, &mut rng);
        let lost = idx.iter().filter(|&&i| f.depth_m[i] == 0.0).count() as f32 / idx.len() as f32;
        assert!(
            (lost_min..=lost_max).contains(&lost),
            "{deg} degrees: {lost} lost"
        );
    }
    // Speckles: density x pixels holes of radius 1-3: about density * N * pi * 2^2 pixels.
    let mut f = render(&quads(&[wall(2.0, 50.0)]));
    let n = f.depth_m.len() as f32;
    speckle_holes(&mut f, 1e-3, [1.0, 3.0], 0.0, &mut rng);
    let lost = f.depth_m.iter().filter(|&&d| d == 0.0).count() as f32;
    let want = 1e-3 * n * std::f32::consts::PI * 4.3;
    assert!(lost > 0.4 * want && lost < 2.0 * want, "{lost} vs {want}");
    let mut f = render(&quads(&[wall(2.0, 50.0)]));
    speckle_holes(&mut f, 0.0, [1.0, 1.0], 0.05, &mut rng);
    let lost = f.depth_m.iter().filter(|&&d| d == 0.0).count() as f32 / n;
    assert!((lost - 0.05).abs() < 0.01, "{lost}");
}

#[test]
fn randomised_sensors_stay_in_their_ranges_and_every_kind_is_drawn() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let mut kinds = std::collections::BTreeSet::new();
    for _ in 0..300 {
        let s = Sensor::randomised(&mut rng);
        let preset = Sensor::of(s.kind, 0);
        kinds.insert(s.kind.name());
        let ratio = |a: f32, b: f32| if b == 0.0 { 1.0 } else { a / b };
        let k = ratio(s.axial.a, preset.axial.a);
        assert!((0.6..=1.6).contains(&k), "{s:?}");
        assert!((0.5..=1.5).contains(&ratio(s.lateral_sigma_px, preset.lateral_sigma_px)));
        assert!((0.7..=1.3).contains(&ratio(s.emitter_baseline_m, preset.emitter_baseline_m)));
        assert!(s.drop_deg <= 89.0 && s.ramp_deg < s.drop_deg);
        assert!((0.3..=3.0).contains(&ratio(s.speckle_density, preset.speckle_density)));
        assert!(matches!(
            s.kind,
            SensorKind::StructuredLight | SensorKind::ActiveStereo | SensorKind::TimeOfFlight
        ));
    }
    assert_eq!(kinds.len(), 3, "{kinds:?}");
    for name in SensorKind::NAMES {
        assert_eq!(SensorKind::parse(name).unwrap().name(), name);
    }
    assert!(SensorKind::parse("lidar")
        .unwrap_err()
        .contains("structured-light"));
}

#[test]
fn a_sensor_is_deterministic_in_its_seed_and_clean_changes_nothing() {
    let plate = plate();
    let tris = quads(&[wall(2.0, 50.0), plate]);
    let clean = render(&tris);
    for kind in [
        SensorKind::StructuredLight,
        SensorKind::ActiveStereo,
        SensorKind::TimeOfFlight,
        SensorKind::Gaussian,
        SensorKind::Random,
    ] {
        let s = Sensor::of(kind, 11);
        let (mut a, mut b, mut c) = (clean.clone(), clean.clone(), clean.clone());
        s.measure(&mut a, &camera(), &tris, 7);
        s.measure(&mut b, &camera(), &tris, 7);
        s.measure(&mut c, &camera(), &tris, 8);
        assert_eq!(a.depth_m, b.depth_m, "{kind:?}");
        assert_ne!(a.depth_m, c.depth_m, "{kind:?}");
        assert_ne!(a.depth_m, clean.depth_m, "{kind:?}");
        assert_eq!(
            a.instance, clean.instance,
            "{kind:?}: the truth must not change"
        );
    }
    let mut f = clean.clone();
    Sensor::clean().measure(&mut f, &camera(), &tris, 1);
    assert_eq!(f.depth_m, clean.depth_m);
    // The model's own noise check: structured light loses more of a frame than time of flight.
    let lost = |kind| {
        let mut f = clean.clone();
        Sensor::of(kind, 0).measure(&mut f, &camera(), &tris, 3);
        f.depth_m.iter().filter(|&&d| d == 0.0).count()
    };
    assert!(lost(SensorKind::StructuredLight) > lost(SensorKind::TimeOfFlight));
}

#[test]
fn colour_realism_changes_exposure_noise_and_balance() {
    let mut img = image::RgbImage::from_pixel(40, 30, image::Rgb([100, 120, 140]));
    let c = ColourRealism {
        noise_levels: 3.0,
        exposure: 1.2,
        white_balance: [1.0, 1.0, 0.9],
        blur: true,
    };
    deocc_synth::sensor::colour_realism(&mut img, &c, 1);
    let mean = |k: usize| img.pixels().map(|p| f32::from(p[k])).sum::<f32>() / 1200.0;
    assert!((mean(0) - 120.0).abs() < 1.0, "{}", mean(0));
    assert!((mean(2) - 140.0 * 1.2 * 0.9).abs() < 1.0, "{}", mean(2));
    let reds: Vec<f32> = img.pixels().map(|p| f32::from(p[0])).collect();
    assert!((std_dev(&reds) - 3.0).abs() < 0.6, "{}", std_dev(&reds));
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for _ in 0..50 {
        let r = ColourRealism::randomised(&mut rng);
        assert!((1.0..=6.0).contains(&r.noise_levels) && (0.75..=1.3).contains(&r.exposure));
    }
}

#[test]
fn axial_model_terms_are_documented_values() {
    let m = AxialNoise {
        a: 0.001,
        b: 0.0,
        z0: 0.0,
        c: 0.001,
        d: 0.0,
    };
    assert!((m.sigma(1.0, 0.0) - 0.002).abs() < 1e-7);
    let tof = Sensor::time_of_flight().axial;
    // About 1.1 mm at 0.9 m (the Azure Kinect frame of arcor2-kinect-azure).
    assert!(
        (tof.sigma(0.9, 0.0) - 0.0011).abs() < 0.0002,
        "{}",
        tof.sigma(0.9, 0.0)
    );
}

/// Whole scenes: the old switch and `--sensor gaussian` give the same depth bit for bit (older
/// figures reproduce); a structured-light view of a room loses a share of its pixels like the
/// real Kinect-class frame (11% at 2.3 m), and more than a time-of-flight view; the colour
/// changes only under `random`.
#[test]
fn scenes_measured_by_each_sensor() {
    use deocc_synth::dataset::render_full_scene;
    use deocc_synth::scene::SceneConfig;
    let base = SceneConfig {
        views: 2,
        width: 320,
        height: 240,
        gt_points_per_m2: 10.0,
        ..Default::default()
    };
    let render = |c: &SceneConfig| render_full_scene(c, 9_000_003).unwrap();
    let old = render(&SceneConfig {
        sensor_noise: true,
        ..base.clone()
    });
    let new = render(&SceneConfig {
        sensor: SensorKind::Gaussian,
        ..base.clone()
    });
    for (a, b) in old.views.iter().zip(&new.views) {
        assert_eq!(a.depth.data(), b.depth.data());
    }
    let clean = render(&base);
    let missing = |r: &deocc_synth::dataset::RenderedScene| {
        let (mut lost, mut all) = (0usize, 0usize);
        for (v, c) in r.views.iter().zip(&clean.views) {
            for (d, dc) in v.depth.data().iter().zip(c.depth.data()) {
                if *dc > 0.0 {
                    all += 1;
                    lost += usize::from(*d == 0.0);
                }
            }
        }
        lost as f32 / all as f32
    };
    let sl = render(&SceneConfig {
        sensor: SensorKind::StructuredLight,
        ..base.clone()
    });
    let tof = render(&SceneConfig {
        sensor: SensorKind::TimeOfFlight,
        ..base.clone()
    });
    let (m_sl, m_tof) = (missing(&sl), missing(&tof));
    assert!((0.03..0.3).contains(&m_sl), "structured light loses {m_sl}");
    assert!(m_sl > m_tof, "{m_sl} vs {m_tof}");
    assert_eq!(sl.views[0].rgb, clean.views[0].rgb);
    let random = render(&SceneConfig {
        sensor: SensorKind::Random,
        ..base.clone()
    });
    assert_ne!(random.views[0].rgb, clean.views[0].rgb);
    assert_eq!(
        random.views[0].frame.instance,
        clean.views[0].frame.instance
    );
}
