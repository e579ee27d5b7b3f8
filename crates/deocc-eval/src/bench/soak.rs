//! `deocc bench soak`: `deocc serve` under normal traffic mixed with abuse, on loopback only,
//! bounded in time and count.
//!
//! The server runs as a child process (the real binary, its own memory). For `seconds`:
//! - normal clients loop Complete on a small scene and check every answer against the first one
//!   (the pipeline is deterministic), and call Grasp and Place on the answer;
//! - abusers send, in turn: uploads that stall before their last byte, calls whose answers are
//!   never read (slow readers, who hang up after a while), calls cancelled mid-run, 1 ms
//!   deadlines, oversized and malformed messages, pathological grasp options and a camera K that
//!   is not pinhole; each outcome's status code is checked.
//!
//! The server's resident memory is sampled every 200 ms. At the end Health must come back to
//! zero queued and running, and SIGTERM must end the process within the shutdown grace period.
//! The report says whether each held.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use deocc_service::client::Client;
use deocc_service::proto::{CompleteRequest, GraspRequest, PlaceRequest};
use deocc_service::raw::{frame, frame_header, RawCall};
use prost::Message;
use serde::Serialize;
use tonic::Code;

use super::timing::Machine;
use crate::EvalError;

/// What the soak runs.
#[derive(Debug, Clone)]
pub struct SoakOptions {
    pub seconds: f64,
    /// Completers of the server (`--completer`), comma-separated.
    pub completer: String,
    /// Normal clients looping Complete.
    pub clients: usize,
    /// Concurrent abusers.
    pub abusers: usize,
    /// The bound the server's peak resident memory must stay under, MiB.
    pub max_rss_mib: f64,
}

impl Default for SoakOptions {
    fn default() -> Self {
        Self {
            seconds: 600.0,
            completer: "gldot,rules".into(),
            clients: 2,
            abusers: 4,
            max_rss_mib: 1536.0,
        }
    }
}

/// Counts of one kind of call: answered as expected, and anything else.
#[derive(Debug, Default, Serialize)]
pub struct Tally {
    pub sent: u64,
    pub as_expected: u64,
    pub unexpected: u64,
    /// The first few unexpected outcomes, in words.
    pub examples: Vec<String>,
}

#[derive(Debug, Serialize)]
pub struct SoakReport {
    pub machine: Machine,
    pub seconds: f64,
    pub completer: String,
    pub clients: usize,
    pub abusers: usize,
    /// Normal Complete calls: correct answers, refusals for a busy server (RESOURCE_EXHAUSTED,
    /// an answer, not a loss) and anything else (lost or wrong).
    pub normal_correct: u64,
    pub normal_busy: u64,
    pub normal_lost_or_wrong: u64,
    pub normal_grasp_place_ok: u64,
    pub normal_grasp_place_failed: u64,
    pub normal_p50_s: f64,
    pub normal_max_s: f64,
    pub abuse: std::collections::BTreeMap<String, Tally>,
    pub peak_rss_mib: f64,
    pub max_rss_mib: f64,
    pub health_back_to_zero: bool,
    pub sigterm_exit_s: f64,
    pub shutdown_grace_s: f64,
    /// Every condition held: no lost or wrong normal answer, every abuse answered as expected,
    /// memory under its bound, Health at zero, SIGTERM within the grace period.
    pub passed: bool,
}

/// A scene small enough for many calls, as a request.
fn scene_request() -> Result<CompleteRequest, EvalError> {
    let config = deocc_synth::scene::SceneConfig {
        views: 2,
        width: 200,
        height: 150,
        gt_points_per_m2: 100.0,
        ..Default::default()
    };
    let scene = deocc_synth::dataset::render_full_scene(&config, 9_300_000)?.scene_input();
    Ok(deocc_service::request::request_from_scene(&scene, ""))
}

fn rss_mib(pid: u32) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

struct Server {
    child: Child,
    addr: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_server(exe: &Path, completer: &str) -> Result<Server, EvalError> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map_err(|e| EvalError::Data(format!("no free loopback port: {e}")))?
        .port();
    let addr = format!("127.0.0.1:{port}");
    let child = Command::new(exe)
        .args(["serve", "--listen", &addr, "--completer", completer])
        .args(["--workers", "1", "--queue", "4"])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| EvalError::Data(format!("cannot start {}: {e}", exe.display())))?;
    Ok(Server { child, addr })
}

fn note(t: &mut Tally, ok: bool, what: impl FnOnce() -> String) {
    t.sent += 1;
    if ok {
        t.as_expected += 1;
    } else {
        t.unexpected += 1;
        if t.examples.len() < 5 {
            t.examples.push(what());
        }
    }
}

type Tallies = Arc<std::sync::Mutex<std::collections::BTreeMap<String, Tally>>>;

fn record(tallies: &Tallies, kind: &str, ok: bool, what: impl FnOnce() -> String) {
    if let Ok(mut t) = tallies.lock() {
        note(t.entry(kind.to_string()).or_default(), ok, what);
    }
}

/// Opens `method` on `addr` with `headers`, sends `parts` (the last ends the body when `end`)
/// and waits up to `secs` for the answer's code; `None` when there was no connection or no
/// answer in time.
async fn code_of(
    addr: &str,
    method: &str,
    headers: &[(&str, &[u8])],
    parts: &[&[u8]],
    end: bool,
    secs: u64,
) -> Option<Code> {
    let mut c = RawCall::open(addr, method, headers).await.ok()?;
    for (k, part) in parts.iter().enumerate() {
        c.send(part, end && k + 1 == parts.len()).ok()?;
    }
    let answer = tokio::time::timeout(Duration::from_secs(secs), c.answer()).await;
    answer.ok()?.ok().map(|a| a.status.code())
}

/// One abuse of kind `k` (cycling through every kind); records its outcome.
async fn abuse(k: usize, addr: &str, good: &CompleteRequest, cloud: &GraspRequest, t: &Tallies) {
    use Code::{Cancelled, DeadlineExceeded, InvalidArgument, ResourceExhausted};
    let good_msg = frame(&good.encode_to_vec());
    let (kind, code, expected): (&str, Option<Code>, &[Code]) = match k % 9 {
        // An upload that stops before its last byte: timed out by the server.
        0 => {
            let head = frame_header(60 << 20);
            let part = vec![0u8; 1 << 20];
            let code = code_of(addr, "Complete", &[], &[&head, &part], false, 30).await;
            (
                "stalled_upload",
                code,
                &[DeadlineExceeded, ResourceExhausted],
            )
        }
        // A slow reader: a Complete whose answer is not read for 3 s, then hung up on; and a
        // call cancelled mid-run (RST_STREAM). Neither waits for an answer.
        1 | 2 => {
            let kind = if k % 9 == 1 {
                "slow_reader"
            } else {
                "cancelled"
            };
            let sent = match RawCall::open(addr, "Complete", &[]).await {
                Ok(mut c) => {
                    let ok = c.send(&good_msg, true).is_ok();
                    if k % 9 == 1 {
                        tokio::time::sleep(Duration::from_secs(3)).await;
                        drop(c);
                    } else {
                        tokio::time::sleep(Duration::from_millis(300)).await;
                        c.cancel();
                    }
                    ok
                }
                Err(_) => false,
            };
            return record(t, kind, sent, || "cannot connect or send".into());
        }
        3 => {
            let h: &[(&str, &[u8])] = &[("grpc-timeout", b"1m")];
            let code = code_of(addr, "Complete", h, &[&good_msg], true, 60).await;
            let ok: &[Code] = &[DeadlineExceeded, Cancelled, ResourceExhausted];
            ("deadline_1ms", code, ok)
        }
        // Announces 2 GiB.
        4 => {
            let head = frame_header(2 << 30);
            let code = code_of(addr, "Complete", &[], &[&head], false, 30).await;
            ("oversized", code, &[ResourceExhausted])
        }
        // Not protobuf.
        5 => {
            let code = code_of(addr, "Complete", &[], &[&frame(&[0xff; 200])], true, 30).await;
            ("malformed", code, &[InvalidArgument, ResourceExhausted])
        }
        // Pathological grasp options (the hang and the false best grasp of before).
        6 | 7 => {
            let options = if k % 9 == 6 {
                r#"{"approaches": 1000000000000}"#
            } else {
                r#"{"normal_neighbours": 18446744073709551615}"#
            };
            let msg = GraspRequest {
                options_json: options.into(),
                ..cloud.clone()
            };
            let code = code_of(
                addr,
                "Grasp",
                &[],
                &[&frame(&msg.encode_to_vec())],
                true,
                60,
            )
            .await;
            (
                "bad_grasp_options",
                code,
                &[InvalidArgument, ResourceExhausted],
            )
        }
        // A transposed K.
        _ => {
            let mut msg = good.clone();
            if let Some(info) = msg.frames[0].camera_info.as_mut() {
                let k = info.k.clone();
                info.k = vec![k[0], 0.0, 0.0, 0.0, k[4], 0.0, k[2], k[5], 1.0];
            }
            let code = code_of(
                addr,
                "Complete",
                &[],
                &[&frame(&msg.encode_to_vec())],
                true,
                30,
            )
            .await;
            ("bad_camera", code, &[InvalidArgument, ResourceExhausted])
        }
    };
    record(t, kind, code.is_some_and(|c| expected.contains(&c)), || {
        format!("{code:?}")
    });
}

/// Runs the soak against the `deocc` binary at `exe`.
pub fn soak_bench(exe: &Path, opts: &SoakOptions) -> Result<SoakReport, EvalError> {
    if !(opts.seconds.is_finite() && opts.seconds > 0.0 && opts.seconds <= 86_400.0) {
        return Err(EvalError::Data(format!(
            "--seconds {} must be in (0, 86400]",
            opts.seconds
        )));
    }
    let machine = Machine::now();
    let good = scene_request()?;
    let mut server = start_server(exe, &opts.completer)?;
    let pid = server.child.id();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| EvalError::Data(e.to_string()))?;
    let url = format!("http://{}", server.addr);
    let peak_rss = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));

    // The sampler: resident memory every 200 ms.
    let sampler = {
        let (peak, stop) = (peak_rss.clone(), stop.clone());
        std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                if let Some(m) = rss_mib(pid) {
                    peak.fetch_max((m * 1024.0) as u64, Ordering::Relaxed);
                }
                std::thread::sleep(Duration::from_millis(200));
            }
        })
    };

    let outcome = rt.block_on(async {
        // Up within 60 s.
        let t = Instant::now();
        let mut client = loop {
            if let Ok(mut c) = Client::connect(&url, None).await {
                if c.health().await.is_ok() {
                    break c;
                }
            }
            if t.elapsed() > Duration::from_secs(60) {
                return Err(EvalError::Data(
                    "deocc serve did not answer Health in 60 s".into(),
                ));
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        // The reference answer.
        let first = client
            .complete(good.clone(), None)
            .await
            .map_err(|e| EvalError::Data(format!("the first Complete failed: {e}")))?;
        let reference = first.result.cloud.clone();
        let target = first
            .cloud()
            .map_err(|e| EvalError::Data(e.to_string()))?
            .instance
            .unwrap_or_default()
            .into_iter()
            .find(|&i| i != 0)
            .unwrap_or(1);
        let grasp = GraspRequest {
            cloud: reference.clone(),
            target,
            options_json: String::new(),
            target_pick: None,
        };
        let tallies: Tallies = Arc::default();
        let deadline = Instant::now() + Duration::from_secs_f64(opts.seconds);
        let mut tasks = Vec::new();
        let latencies = Arc::new(std::sync::Mutex::new(Vec::<f64>::new()));
        let counts = Arc::new([
            AtomicU64::new(0),
            AtomicU64::new(0),
            AtomicU64::new(0),
            AtomicU64::new(0),
            AtomicU64::new(0),
        ]);
        for _ in 0..opts.clients {
            let (mut c, good, reference, grasp) = (
                client.clone(),
                good.clone(),
                reference.clone(),
                grasp.clone(),
            );
            let (counts, latencies) = (counts.clone(), latencies.clone());
            tasks.push(tokio::spawn(async move {
                let mut round = 0u64;
                while Instant::now() < deadline {
                    round += 1;
                    let t = Instant::now();
                    match c.complete(good.clone(), None).await {
                        Ok(done) if done.result.cloud == reference => {
                            counts[0].fetch_add(1, Ordering::Relaxed);
                            if let Ok(mut l) = latencies.lock() {
                                l.push(t.elapsed().as_secs_f64());
                            }
                        }
                        Err(e) if e.code() == Code::ResourceExhausted => {
                            counts[1].fetch_add(1, Ordering::Relaxed);
                            tokio::time::sleep(Duration::from_millis(200)).await;
                        }
                        _ => {
                            counts[2].fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    // Every third round, the robot calls on the answer.
                    if round % 3 == 0 {
                        let g = c.grasp(grasp.clone()).await;
                        let p = c
                            .place(PlaceRequest {
                                cloud: reference.clone(),
                                footprint_w: 0.06,
                                footprint_d: 0.06,
                                height: 0.1,
                                up: vec![],
                                robot: vec![],
                            })
                            .await;
                        let ok = |code: Option<Code>| {
                            matches!(
                                code,
                                None | Some(Code::ResourceExhausted | Code::InvalidArgument)
                            )
                        };
                        // A cloud may hold no grasp or no support plane (INVALID_ARGUMENT says
                        // why); anything else is a failure.
                        let fine = ok(g.as_ref().err().map(|e| e.code()))
                            && ok(p.as_ref().err().map(|e| e.code()));
                        counts[if fine { 3 } else { 4 }].fetch_add(1, Ordering::Relaxed);
                    }
                }
            }));
        }
        for a in 0..opts.abusers {
            let (addr, good, grasp, tallies) = (
                url.trim_start_matches("http://").to_string(),
                good.clone(),
                grasp.clone(),
                tallies.clone(),
            );
            tasks.push(tokio::spawn(async move {
                let mut k = a;
                while Instant::now() < deadline {
                    abuse(k, &addr, &good, &grasp, &tallies).await;
                    k += STRIDE;
                }
            }));
        }
        for t in tasks {
            let _ = t.await;
        }
        // Health back at zero within 30 s of the traffic ending.
        let t = Instant::now();
        let mut back = false;
        while t.elapsed() < Duration::from_secs(30) {
            if let Ok(h) = client.health().await {
                if h.queued == 0 && h.running == 0 {
                    back = true;
                    break;
                }
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let mut lat = latencies.lock().map(|l| l.clone()).unwrap_or_default();
        lat.sort_by(f64::total_cmp);
        let tallies = std::mem::take(
            &mut *tallies
                .lock()
                .map_err(|_| EvalError::Data("poisoned".into()))?,
        );
        Ok((
            [
                counts[0].load(Ordering::Relaxed),
                counts[1].load(Ordering::Relaxed),
                counts[2].load(Ordering::Relaxed),
                counts[3].load(Ordering::Relaxed),
                counts[4].load(Ordering::Relaxed),
            ],
            lat,
            tallies,
            back,
        ))
    });
    let (counts, lat, abuse, health_back_to_zero) = outcome?;

    // SIGTERM: the process must end within the grace period.
    let t = Instant::now();
    let _ = Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status();
    let grace = deocc_service::server::SHUTDOWN_GRACE.as_secs_f64();
    let mut sigterm_exit_s = f64::INFINITY;
    while t.elapsed().as_secs_f64() < grace + 5.0 {
        if let Ok(Some(_)) = server.child.try_wait() {
            sigterm_exit_s = t.elapsed().as_secs_f64();
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    stop.store(true, Ordering::Relaxed);
    let _ = sampler.join();
    let peak_rss_mib = peak_rss.load(Ordering::Relaxed) as f64 / 1024.0;
    let unexpected: u64 = abuse.values().map(|t| t.unexpected).sum();
    let passed = counts[2] == 0
        && counts[4] == 0
        && counts[0] > 0
        && unexpected == 0
        && peak_rss_mib < opts.max_rss_mib
        && health_back_to_zero
        && sigterm_exit_s <= grace;
    Ok(SoakReport {
        machine,
        seconds: opts.seconds,
        completer: opts.completer.clone(),
        clients: opts.clients,
        abusers: opts.abusers,
        normal_correct: counts[0],
        normal_busy: counts[1],
        normal_lost_or_wrong: counts[2],
        normal_grasp_place_ok: counts[3],
        normal_grasp_place_failed: counts[4],
        normal_p50_s: lat.get(lat.len() / 2).copied().unwrap_or(f64::NAN),
        normal_max_s: lat.last().copied().unwrap_or(f64::NAN),
        abuse,
        peak_rss_mib,
        max_rss_mib: opts.max_rss_mib,
        health_back_to_zero,
        sigterm_exit_s,
        shutdown_grace_s: grace,
        passed,
    })
}

/// Abusers step through the nine kinds with a stride coprime to nine, so each meets every kind.
const STRIDE: usize = 4;
