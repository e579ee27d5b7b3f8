//! `deocc-fuzz`: a seeded mutation fuzzer for every reader of untrusted input (PLY, OBJ, STL, PNG,
//! cameras.json, scene.json, train.json, safetensors weights, pair shards). Valid seed files are
//! made in memory, mutated (bit flips, byte edits, boundary integers, truncation, duplication of
//! a block), written to a temporary file and read back. A reader may refuse an input; it must not
//! panic, and no single allocation may exceed the limit. A counting allocator records the
//! largest request.
//!
//! `deocc-fuzz [TARGET|all] [--seconds S] [--seed N] [--max-alloc-mb M]`; `scripts/fuzz.sh` runs
//! every target for a set time. Exit code 1 on the first failure, with the input saved.

use std::alloc::{GlobalAlloc, Layout, System};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The system allocator, recording the largest single request.
struct Counting;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LARGEST.fetch_max(layout.size(), Ordering::Relaxed);
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LARGEST.fetch_max(new_size, Ordering::Relaxed);
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// A target: its file name, its seed inputs, and the reader under test.
struct Target {
    name: &'static str,
    file: &'static str,
    seeds: Vec<Vec<u8>>,
    read: fn(&Path),
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

fn targets() -> Vec<Target> {
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

const INTERESTING: [u64; 10] = [
    0,
    1,
    0x7f,
    0xff,
    0xffff,
    0x7fff_ffff,
    0xffff_ffff,
    1 << 40,
    u64::MAX / 2,
    u64::MAX,
];

/// One mutation of `input`.
fn mutate(input: &[u8], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let mut b = input.to_vec();
    let rounds = 1 + rng.random_range(0..4);
    for _ in 0..rounds {
        if b.is_empty() {
            b.push(rng.random());
            continue;
        }
        let at = rng.random_range(0..b.len());
        match rng.random_range(0..9) {
            0 => b[at] ^= 1 << rng.random_range(0..8),
            1 => b[at] = rng.random(),
            2 => {
                b.remove(at);
            }
            3 => b.insert(at, rng.random()),
            4 => b.truncate(at),
            5 => {
                // A boundary integer, written as bytes or as text.
                let v = INTERESTING[rng.random_range(0..INTERESTING.len())];
                if rng.random_bool(0.5) {
                    let bytes = v.to_le_bytes();
                    let n = [1, 2, 4, 8][rng.random_range(0..4)];
                    for (k, &x) in bytes[..n].iter().enumerate() {
                        if at + k < b.len() {
                            b[at + k] = x;
                        }
                    }
                } else {
                    let text = v.to_string();
                    let end = (at + text.len()).min(b.len());
                    b.splice(at..end, text.bytes());
                }
            }
            6 => {
                // Duplicate a block.
                let len = rng.random_range(1..=64.min(b.len() - at));
                let block: Vec<u8> = b[at..at + len].to_vec();
                let to = rng.random_range(0..=b.len());
                b.splice(to..to, block);
            }
            7 => {
                // A digit changed into another, or a sign flipped (text formats).
                if b[at].is_ascii_digit() {
                    b[at] = b'0' + rng.random_range(0..10);
                } else if b[at] == b'-' {
                    b[at] = b'+';
                }
            }
            _ => {
                for x in ["nan", "inf", "-1", "1e39", "999999999999"] {
                    if rng.random_bool(0.2) {
                        let end = (at + x.len()).min(b.len());
                        b.splice(at..end, x.bytes());
                        break;
                    }
                }
            }
        }
    }
    b
}

struct Args {
    target: String,
    seconds: f64,
    seed: u64,
    max_alloc: usize,
}

fn parse_args() -> Result<Args, String> {
    let mut a = Args {
        target: "all".into(),
        seconds: 10.0,
        seed: 0,
        max_alloc: 1 << 30,
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().ok_or_else(|| format!("{name} needs a value"));
        match arg.as_str() {
            "--seconds" => {
                a.seconds = value("--seconds")?
                    .parse()
                    .map_err(|_| "--seconds takes a number")?
            }
            "--seed" => {
                a.seed = value("--seed")?
                    .parse()
                    .map_err(|_| "--seed takes an integer")?
            }
            "--max-alloc-mb" => {
                let mb: usize = value("--max-alloc-mb")?
                    .parse()
                    .map_err(|_| "--max-alloc-mb takes an integer")?;
                a.max_alloc = mb << 20;
            }
            "-h" | "--help" => {
                return Err(
                    "usage: deocc-fuzz [TARGET|all] [--seconds S] [--seed N] [--max-alloc-mb M]\n\
                     targets: ply obj stl png cameras scene_json train_json safetensors pairs"
                        .into(),
                )
            }
            t if !t.starts_with('-') => a.target = t.into(),
            other => return Err(format!("unknown option {other}")),
        }
    }
    if !(a.seconds.is_finite() && a.seconds > 0.0) {
        return Err("--seconds must be positive".into());
    }
    Ok(a)
}

fn main() -> std::process::ExitCode {
    let a = match parse_args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("{e}");
            return std::process::ExitCode::from(2);
        }
    };
    // A panic is a finding: report it ourselves.
    std::panic::set_hook(Box::new(|_| {}));
    let all = targets();
    let chosen: Vec<&Target> = all
        .iter()
        .filter(|t| a.target == "all" || t.name == a.target)
        .collect();
    if chosen.is_empty() {
        eprintln!("unknown target {}", a.target);
        return std::process::ExitCode::from(2);
    }
    let dir: PathBuf = std::env::temp_dir().join(format!("deocc-fuzz-{}", std::process::id()));
    if std::fs::create_dir_all(&dir).is_err() {
        eprintln!("{}: cannot create", dir.display());
        return std::process::ExitCode::from(2);
    }
    let per_target = Duration::from_secs_f64(a.seconds / chosen.len() as f64);
    let mut failed = false;
    for t in chosen {
        if t.seeds.is_empty() {
            eprintln!("{}: no seed input could be made", t.name);
            failed = true;
            continue;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(a.seed ^ t.name.len() as u64);
        let path = dir.join(t.file);
        let start = Instant::now();
        let (mut runs, mut largest) = (0u64, 0usize);
        while start.elapsed() < per_target {
            let seed = &t.seeds[rng.random_range(0..t.seeds.len())];
            let input = mutate(seed, &mut rng);
            if std::fs::write(&path, &input).is_err() {
                continue;
            }
            LARGEST.store(0, Ordering::Relaxed);
            let read = t.read;
            let outcome = std::panic::catch_unwind(|| read(&path));
            let peak = LARGEST.load(Ordering::Relaxed);
            largest = largest.max(peak);
            runs += 1;
            let problem = if outcome.is_err() {
                Some("panicked".to_string())
            } else if peak > a.max_alloc {
                Some(format!("allocated {} MB at once", peak >> 20))
            } else {
                None
            };
            if let Some(why) = problem {
                let keep = std::env::temp_dir().join(format!("deocc-fuzz-crash-{}", t.file));
                let _ = std::fs::write(&keep, &input);
                eprintln!("{}: {why} on input {} (run {runs})", t.name, keep.display());
                failed = true;
                break;
            }
        }
        println!(
            "{}: {runs} inputs, no panic, largest allocation {:.1} MB",
            t.name,
            largest as f64 / (1 << 20) as f64
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    if failed {
        std::process::ExitCode::FAILURE
    } else {
        std::process::ExitCode::SUCCESS
    }
}
