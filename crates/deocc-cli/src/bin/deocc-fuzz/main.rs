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
use std::path::PathBuf;
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

mod targets;
use targets::{targets, Target};

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
        let (mut runs, mut largest, mut found) = (0u64, 0usize, false);
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
                found = true;
                break;
            }
        }
        println!(
            "{}: {runs} inputs in {:.0} s, {}, largest allocation {:.1} MB",
            t.name,
            start.elapsed().as_secs_f64(),
            if found { "FAILED" } else { "no panic" },
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
