//! Depth Anything V2 behind the depth-source seam, with random weights (no checkpoint can be
//! downloaded here): the presets build and run, a checkpoint in the original layout (no
//! classifier head) loads and answers as the network it was saved from, bad files are refused
//! naming the file, and the pipeline's depth stage takes the model's answer.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use deocc_geometry::camera::{Camera, Intrinsics};
use deocc_geometry::DepthMap;
use deocc_io::scene::Frame;
use deocc_model::depth_anything::{DepthAnything, DepthAnythingShape};
use deocc_pipeline::depth::{fill_depth, DepthFillOptions};
use image::RgbImage;

fn tiny() -> DepthAnythingShape {
    DepthAnythingShape {
        name: "tiny".into(),
        blocks: 4,
        embed_dim: 32,
        heads: 2,
        out_channels: [8, 16, 32, 64],
        features: 16,
        layer_ids: vec![0, 1, 2, 3],
    }
}

fn random(shape: DepthAnythingShape) -> (DepthAnything, VarMap) {
    let dev = Device::Cpu;
    let vm = VarMap::new();
    let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
    (DepthAnything::build(shape, vb, &dev).unwrap(), vm)
}

fn image(w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |u, v| {
        image::Rgb([
            (u * 255 / w) as u8,
            (v * 255 / h) as u8,
            ((u ^ v) & 255) as u8,
        ])
    })
}

/// The varmap's tensors without the encoder's classifier, as the depth checkpoints are.
fn save_like_a_checkpoint(vm: &VarMap, path: &std::path::Path) {
    let data = vm.data().lock().unwrap();
    let tensors: HashMap<String, Tensor> = data
        .iter()
        .filter(|(k, _)| !k.starts_with("pretrained.head."))
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect();
    assert!(tensors.keys().any(|k| k.starts_with("depth_head.")));
    assert!(tensors.contains_key("pretrained.cls_token"));
    candle_core::safetensors::save(&tensors, path).unwrap();
}

#[test]
fn a_checkpoint_in_the_original_layout_loads_and_answers_as_saved() {
    let (model, vm) = random(tiny());
    let img = image(64, 48);
    let d = model.disparity(&img).unwrap();
    assert_eq!(d.len(), 64 * 48);
    assert!(d.iter().all(|v| v.is_finite() && *v >= 0.0));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tiny.safetensors");
    save_like_a_checkpoint(&vm, &path);
    let loaded = DepthAnything::load_shaped(&path, tiny(), &Device::Cpu).unwrap();
    let e = loaded.disparity(&img).unwrap();
    let worst = d
        .iter()
        .zip(&e)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(worst < 1e-5, "{worst}");
    // The size is read from the file; this one is none of the presets.
    let err = DepthAnything::load(&path, &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.contains("tiny.safetensors") && err.contains("encoder width 32"),
        "{err}"
    );
}

#[test]
fn bad_files_are_refused_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("none.safetensors");
    let err = DepthAnything::load(&missing, &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.contains("none.safetensors") && err.contains("no such file"),
        "{err}"
    );
    let other = dir.path().join("other.safetensors");
    let t = HashMap::from([(
        "x".to_string(),
        Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
    )]);
    candle_core::safetensors::save(&t, &other).unwrap();
    let err = DepthAnything::load(&other, &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.contains("other.safetensors") && err.contains("cls_token"),
        "{err}"
    );
    let garbage = dir.path().join("garbage.safetensors");
    std::fs::write(&garbage, b"not a safetensors file").unwrap();
    let err = DepthAnything::load(&garbage, &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("garbage.safetensors"), "{err}");
    // A checkpoint of another shape does not fit.
    let (_, vm) = random(tiny());
    let path = dir.path().join("tiny.safetensors");
    save_like_a_checkpoint(&vm, &path);
    let mut wrong = tiny();
    wrong.features = 24;
    let err = DepthAnything::load_shaped(&path, wrong, &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("do not fit"), "{err}");
}

#[test]
fn the_small_preset_builds_and_runs() {
    assert_eq!(
        DepthAnythingShape::for_embed_dim(384),
        Some(DepthAnythingShape::small())
    );
    assert_eq!(
        DepthAnythingShape::for_embed_dim(1024),
        Some(DepthAnythingShape::large())
    );
    let (model, _) = random(DepthAnythingShape::small());
    let d = model.disparity(&image(40, 30)).unwrap();
    assert_eq!(d.len(), 40 * 30);
    assert!(d.iter().all(|v| v.is_finite()));
}

#[test]
fn the_depth_stage_takes_the_models_answer() {
    let (model, _) = random(tiny());
    let (w, h) = (64, 48);
    let mut depth = DepthMap::zeros(w, h);
    for v in 0..h {
        for u in 0..w {
            if u % 8 != 0 {
                depth.set(u, v, 1.0 + 0.01 * v as f32);
            }
        }
    }
    let before = depth.clone();
    let mut frame = Frame {
        name: "left".into(),
        camera: Camera {
            intrinsics: Intrinsics::new(50.0, 50.0, 32.0, 24.0, w, h).unwrap(),
            world_from_camera: nalgebra::Isometry3::identity(),
        },
        rgb: image(w, h),
        depth,
        instances: None,
    };
    let report = fill_depth(&mut frame, &model, &DepthFillOptions::default())
        .unwrap()
        .unwrap();
    assert_eq!(report.frame, "left");
    assert_eq!(report.source, "depth-anything-v2-tiny");
    assert_eq!(report.measured, before.valid_count());
    for v in 0..h {
        for u in 0..w {
            if before.get(u, v) > 0.0 {
                assert_eq!(before.get(u, v), frame.depth.get(u, v));
            }
        }
    }
    assert_eq!(frame.depth.valid_count(), report.measured + report.filled);
}

/// The header is checked before the file is read: a 3 GB file of zeros (sparse, so it costs no
/// disk) took 3.1 GB of memory to be refused; now it is refused at once, naming the file.
#[test]
fn a_huge_file_that_is_not_weights_is_refused_without_reading_it() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("huge.safetensors");
    std::fs::File::create(&path)
        .unwrap()
        .set_len(3 << 30)
        .unwrap();
    let t = std::time::Instant::now();
    let err = DepthAnything::load(&path, &Device::Cpu)
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.contains("huge.safetensors") && err.contains("not a safetensors file"),
        "{err}"
    );
    assert!(t.elapsed().as_secs_f32() < 2.0, "{:?}", t.elapsed());
}
