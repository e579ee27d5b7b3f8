//! The fuzzer's targets: every reader of untrusted input, with seed inputs to mutate.

use std::path::Path;

/// A target: its file name, its seed inputs, and the reader under test.
pub struct Target {
    pub name: &'static str,
    pub file: &'static str,
    pub seeds: Vec<Vec<u8>>,
    pub read: fn(&Path),
}

fn ply_seeds() -> Vec<Vec<u8>> {
    use deocc_geometry::PointCloud;
    use deocc_io::{write_point_cloud, PlyEncoding};
    let dir = std::env::temp_dir().join(format!("deocc-fuzz-seed-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let mut cloud = PointCloud::from_positions(
        (0..40)
            .map(|i| nalgebra::Point3::new(i as f32 * 0.1, 1.0, -2.0))
            .collect(),
    );
    cloud.colors = Some((0..40).map(|i| [i as u8, 2, 3]).collect());
    cloud.instance = Some((0..40).collect());
    cloud.generated = Some(vec![1; 40]);
    let mut seeds = Vec::new();
    for enc in [
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        let p = dir.join("s.ply");
        if write_point_cloud(&p, &cloud, enc).is_ok() {
            seeds.push(std::fs::read(&p).unwrap_or_default());
        }
    }
    seeds.push(
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
            .to_vec(),
    );
    let _ = std::fs::remove_dir_all(&dir);
    seeds
}

fn png_seeds() -> Vec<Vec<u8>> {
    let dir = std::env::temp_dir().join(format!("deocc-fuzz-png-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let mut seeds = Vec::new();
    let p = dir.join("s.png");
    let depth = deocc_geometry::DepthMap::new(8, 6, (0..48).map(|i| i as f32 * 0.01).collect());
    if let Ok(d) = depth {
        if deocc_io::images::write_depth_png(&p, &d).is_ok() {
            seeds.push(std::fs::read(&p).unwrap_or_default());
        }
    }
    let rgb = image::RgbImage::from_fn(7, 5, |x, y| image::Rgb([x as u8 * 30, y as u8 * 40, 9]));
    if deocc_io::images::write_rgb_png(&p, &rgb).is_ok() {
        seeds.push(std::fs::read(&p).unwrap_or_default());
    }
    let _ = std::fs::remove_dir_all(&dir);
    seeds
}

fn safetensors_seeds() -> Vec<Vec<u8>> {
    let dev = candle_core::Device::Cpu;
    let mut map = std::collections::HashMap::new();
    if let (Ok(a), Ok(b)) = (
        candle_core::Tensor::arange(0f32, 12.0, &dev).and_then(|t| t.reshape((3, 4))),
        candle_core::Tensor::zeros(5, candle_core::DType::F16, &dev),
    ) {
        map.insert("w".to_string(), a);
        map.insert("b".to_string(), b);
    }
    let p = std::env::temp_dir().join(format!("deocc-fuzz-st-{}.safetensors", std::process::id()));
    let mut seeds = Vec::new();
    if candle_core::safetensors::save(&map, &p).is_ok() {
        seeds.push(std::fs::read(&p).unwrap_or_default());
    }
    let _ = std::fs::remove_file(&p);
    seeds
}

fn pair_seeds() -> Vec<Vec<u8>> {
    let set = deocc_synth::pairs::split_scene_pairs(
        deocc_synth::pairs::Split::Train,
        0,
        &deocc_synth::pairs::PairConfig {
            resolution: 16,
            views_per_scene: 3,
            keep_unoccluded: 1.0,
            ..Default::default()
        },
    );
    let mut seeds = Vec::new();
    if let Ok(mut set) = set.map_err(|e| eprintln!("pairs seed: {e}")) {
        set.truncate(2);
        let p = std::env::temp_dir().join(format!("deocc-fuzz-pairs-{}", std::process::id()));
        if deocc_io::pairs::save_pairs(&p, &set).is_ok() {
            seeds.push(std::fs::read(&p).unwrap_or_default());
        }
        let _ = std::fs::remove_file(&p);
    }
    seeds
}

fn train_json_seed() -> Vec<u8> {
    let cfg = deocc_model::train::TrainConfig {
        model: deocc_model::GlDotConfig::tiny(),
        mask_threshold: 0.5,
        ..Default::default()
    };
    serde_json::to_vec_pretty(&cfg).unwrap_or_default()
}

pub fn targets() -> Vec<Target> {
    let cameras = br#"{"frames": [{"name": "000000", "intrinsics": {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480}, "world_from_camera": [[1,0,0,0.5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}, {"name": "000001", "intrinsics": {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480}}]}"#.to_vec();
    vec![
        Target {
            name: "ply",
            file: "x.ply",
            seeds: ply_seeds(),
            read: |p| {
                let _ = deocc_io::ply::read_ply(p);
            },
        },
        Target {
            name: "obj",
            file: "x.obj",
            seeds: vec![
                b"# cube\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nvn 0 0 1\nf 1 2 3 4\nf 1//1 2//1 5//1\nf -1 -2 -3\n".to_vec(),
            ],
            read: |p| {
                let _ = deocc_io::mesh::read_mesh(p);
            },
        },
        Target {
            name: "stl",
            file: "x.stl",
            seeds: vec![
                b"solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n".to_vec(),
                {
                    let mut b = vec![0u8; 80];
                    b.extend_from_slice(&1u32.to_le_bytes());
                    for v in [0f32, 0., 1., 0., 0., 0., 1., 0., 0., 0., 1., 0.] {
                        b.extend_from_slice(&v.to_le_bytes());
                    }
                    b.extend_from_slice(&[0, 0]);
                    b
                },
            ],
            read: |p| {
                let _ = deocc_io::mesh::read_mesh(p);
            },
        },
        Target {
            name: "png",
            file: "x.png",
            seeds: png_seeds(),
            read: |p| {
                let _ = deocc_io::images::read_depth_png_expecting(p, Some((8, 6)));
                let _ = deocc_io::images::read_rgb_png(p);
                let _ = deocc_io::images::read_instance_png(p);
            },
        },
        Target {
            name: "cameras",
            file: "cameras.json",
            seeds: vec![cameras],
            read: |p| {
                let _ = deocc_io::cameras::read_cameras_json(p);
            },
        },
        Target {
            name: "scene_json",
            file: "scene.json",
            seeds: vec![br#"{"objects": [{"instance_id": 3, "category": "floor", "structure": true}, {"instance_id": 7, "category": "mug"}]}"#.to_vec()],
            read: |p| {
                let _ = deocc_io::scene::read_scene_meta(p);
            },
        },
        Target {
            name: "train_json",
            file: "train.json",
            seeds: vec![train_json_seed()],
            read: |p| {
                let _ = deocc_model::train::TrainConfig::read(p);
            },
        },
        Target {
            name: "safetensors",
            file: "w.safetensors",
            seeds: safetensors_seeds(),
            read: |p| {
                if let Ok(t) = candle_core::safetensors::load(p, &candle_core::Device::Cpu) {
                    let _ = deocc_model::GlDotCompleter::from_tensors(
                        t,
                        &deocc_model::GlDotConfig::tiny(),
                        1.0,
                        &candle_core::Device::Cpu,
                    );
                }
            },
        },
        Target {
            name: "pairs",
            file: "p.safetensors",
            seeds: pair_seeds(),
            read: |p| {
                let _ = deocc_io::pairs::load_pairs(p);
                let _ = deocc_io::pairs::count_pairs(p);
            },
        },
    ]
}
