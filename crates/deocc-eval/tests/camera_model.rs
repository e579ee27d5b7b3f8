//! Known-answer tests of the camera model (issue 49): a scene rendered through a pinhole camera,
//! and the same scene as a distorting lens would have given it (built from a render at twice the
//! resolution, so the distorted images carry no extra resampling error of their own), must give
//! the same cloud and the same completion once `cameras.json` states the lens.

use std::path::Path;

use deocc_completion::rules::RulesCompleter;
use deocc_completion::CompleterChain;
use deocc_geometry::camera::Camera;
use deocc_geometry::depth::backproject;
use deocc_geometry::distortion::Distortion;
use deocc_geometry::{DepthMap, KdIndex, PointCloud};
use deocc_io::cameras::{write_cameras_json, FrameCamera, Lens};
use deocc_io::images::{write_depth_png, write_instance_png, write_rgb_png, InstanceMap};
use deocc_io::scene::{frame_paths, read_scene, SceneInput};
use deocc_synth::render::{render_scene, shade, SceneTriangles};
use image::RgbImage;

struct Views {
    camera: Camera,
    rgb: RgbImage,
    depth: DepthMap,
    ids: Vec<u16>,
}

fn render(camera: Camera, scene: &deocc_synth::scene::Scene, tris: &SceneTriangles) -> Views {
    let f = render_scene(&camera, scene, tris);
    let rgb = shade(&f, &camera, scene, tris, [0, 0, 0]);
    Views {
        camera,
        rgb,
        depth: DepthMap::new(f.width, f.height, f.depth_m.clone()).unwrap(),
        ids: f.instance.clone(),
    }
}

/// The images a camera with `k` (of `fine`'s pose) and lens `dist` would give: each distorted
/// pixel looks up the pinhole ray it sees in the twice-as-fine render.
fn distorted(fine: &Views, k: &deocc_geometry::Intrinsics, dist: &Distortion) -> Views {
    let (w, h) = (k.width(), k.height());
    let fk = &fine.camera.intrinsics;
    let mut rgb = RgbImage::new(w, h);
    let mut depth = vec![0.0f32; (w * h) as usize];
    let mut ids = vec![0u16; (w * h) as usize];
    for v in 0..h {
        for u in 0..w {
            let xd = (u as f64 + 0.5 - k.cx() as f64) / k.fx() as f64;
            let yd = (v as f64 + 0.5 - k.cy() as f64) / k.fy() as f64;
            let Some((x, y)) = dist.undistort(xd, yd) else {
                continue;
            };
            let su = (x * fk.fx() as f64 + fk.cx() as f64).floor();
            let sv = (y * fk.fy() as f64 + fk.cy() as f64).floor();
            if su < 0.0 || sv < 0.0 || su >= fk.width() as f64 || sv >= fk.height() as f64 {
                continue;
            }
            let (su, sv) = (su as u32, sv as u32);
            let i = (v * w + u) as usize;
            depth[i] = fine.depth.get(su, sv);
            ids[i] = fine.ids[(sv * fk.width() + su) as usize];
            rgb.put_pixel(u, v, *fine.rgb.get_pixel(su, sv));
        }
    }
    Views {
        camera: Camera {
            intrinsics: *k,
            ..fine.camera
        },
        rgb,
        depth: DepthMap::new(w, h, depth).unwrap(),
        ids,
    }
}

fn write(dir: &Path, v: &Views, lens: Lens) {
    let [rgb, depth, inst] = frame_paths(dir, "000000");
    for p in [&rgb, &depth, &inst] {
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
    }
    write_rgb_png(&rgb, &v.rgb).unwrap();
    write_depth_png(&depth, &v.depth).unwrap();
    let k = &v.camera.intrinsics;
    write_instance_png(
        &inst,
        &InstanceMap {
            width: k.width(),
            height: k.height(),
            ids: v.ids.clone(),
        },
    )
    .unwrap();
    write_cameras_json(
        &dir.join("cameras.json"),
        &[FrameCamera {
            name: "000000".into(),
            intrinsics: *k,
            world_from_camera: Some(v.camera.world_from_camera),
            lens,
        }],
    )
    .unwrap();
}

/// Distances from each point of `a` to the nearest point of `b`, sorted.
fn distances(a: &PointCloud, b: &PointCloud) -> Vec<f32> {
    let index = KdIndex::build(&b.positions).unwrap();
    let mut d = index.nearest_distances(&a.positions);
    d.sort_by(f32::total_cmp);
    d
}

fn quantile(d: &[f32], q: f64) -> f32 {
    d[((d.len() - 1) as f64 * q) as usize]
}

fn scenes(dist: &Distortion) -> (SceneInput, SceneInput, Vec<u16>, PointCloud) {
    let p = deocc_synth::dataset::bench_v1();
    let scene = deocc_synth::generate::generate_scene(&p.config, p.seeds[0]).unwrap();
    let tris = SceneTriangles::new(&scene);
    let cam = scene.cameras[0];
    let reference = render(cam, &scene, &tris);
    let fine = render(
        Camera {
            intrinsics: cam.intrinsics.scaled(2.0).unwrap(),
            ..cam
        },
        &scene,
        &tris,
    );
    let bent = distorted(&fine, &cam.intrinsics, dist);
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("pinhole"), tmp.path().join("distorted"));
    write(&a, &reference, Lens::default());
    write(
        &b,
        &bent,
        Lens {
            distortion: dist.clone(),
            ..Default::default()
        },
    );
    // The distorted images read as if the camera were a pinhole.
    let naive = backproject(&bent.depth, &bent.camera).unwrap().0;
    (
        read_scene(&a).unwrap(),
        read_scene(&b).unwrap(),
        scene.structure_ids(),
        naive,
    )
}

#[test]
fn a_distorted_scene_gives_the_pinhole_cloud_and_completion() {
    for dist in [
        Distortion::PlumbBob([-0.28, 0.09, 0.0008, -0.0004, -0.01]),
        Distortion::RationalPolynomial([
            0.447, -2.5, 0.00094, -0.00053, 1.432, 0.329, -2.332, 1.363,
        ]),
        Distortion::Equidistant([0.02, -0.01, 0.004, -0.001]),
    ] {
        let (mut pin, mut bent, structure, naive) = scenes(&dist);
        // The observed clouds: the rendering's own error is the 2x render's half-pixel.
        let cloud = |s: &SceneInput| {
            backproject(&s.frames[0].depth, &s.frames[0].camera)
                .unwrap()
                .0
        };
        let (cp, cb) = (cloud(&pin), cloud(&bent));
        assert!(
            cb.len() as f32 > 0.9 * cp.len() as f32,
            "{}: {} of {} points survive undistortion",
            dist.model_name(),
            cb.len(),
            cp.len()
        );
        let d = distances(&cb, &cp);
        let (median, p95) = (quantile(&d, 0.5), quantile(&d, 0.95));
        eprintln!(
            "{}: observed median {median:.4} m, 95th {p95:.4} m",
            dist.model_name()
        );
        assert!(
            median < 0.001,
            "{}: observed median {median} m",
            dist.model_name()
        );
        assert!(
            p95 < 0.006,
            "{}: observed 95th percentile {p95} m",
            dist.model_name()
        );
        // Without the lens stated, the same images are measurably wrong (the test can fail).
        let wrong = quantile(&distances(&naive, &cp), 0.95);
        assert!(
            wrong > 3.0 * p95,
            "{}: ignoring the lens gives a 95th percentile of {wrong} m",
            dist.model_name()
        );
        // The completions, with the ground-truth instance maps.
        pin.structure_ids = structure.clone();
        bent.structure_ids = structure.clone();
        let chain = CompleterChain::new(vec![Box::new(RulesCompleter::default())]);
        let opts = deocc_pipeline::PipelineOptions::default();
        let run = |s: SceneInput| {
            deocc_pipeline::run_in_memory(
                s,
                &chain,
                &opts,
                &deocc_pipeline::segment::ConvexitySegmenter::default(),
                false,
                &deocc_pipeline::Unobserved,
            )
            .unwrap()
            .completed
        };
        let (a, b) = (run(pin), run(bent));
        let d = distances(&b, &a);
        let median = quantile(&d, 0.5);
        eprintln!(
            "{}: completed clouds {} / {} points, median {median:.4} m",
            dist.model_name(),
            a.len(),
            b.len()
        );
        assert!(
            median < 0.002,
            "{}: completed median {median} m",
            dist.model_name()
        );
    }
}
