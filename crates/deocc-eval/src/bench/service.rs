//! `deocc bench service`: the gRPC service on loopback against the pipeline called in process,
//! on the example scene (bench-v1 scene 0, 10 views at 640x480).
//!
//! - Overhead: one client, one request at a time, alternating rounds with the in-process call.
//! - Serialisation: each step of a request's and an answer's way through the wire format, timed
//!   alone, as a share of the pipeline's time; a 1M-point cloud encoded and decoded.
//! - Load: `clients` concurrent clients x `requests` each; every request's status counted (none
//!   may be lost), latency p50 / p99, throughput against the in-process pipeline's, peak RSS.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use deocc_completion::CompleterChain;
use deocc_pipeline::segment::ConvexitySegmenter;
use deocc_pipeline::{PipelineOptions, SceneInput, Unobserved};
use deocc_service::client::Client;
use deocc_service::request::{request_from_scene, scene_from_request, Limits};
use deocc_service::server::{serve, DeoccService, ServerConfig};
use nalgebra::Point3;
use prost::Message;
use serde::Serialize;

use super::timing::median;
use crate::EvalError;

#[derive(Debug, Clone)]
pub struct ServiceBenchOptions {
    pub clients: usize,
    pub requests: usize,
    /// Alternating rounds of the overhead comparison.
    pub rounds: usize,
    pub workers: usize,
    pub queue: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct Serialisation {
    pub request_bytes: usize,
    pub response_bytes: usize,
    /// Client: scene -> request message -> bytes.
    pub request_encode_s: f64,
    /// Server: bytes -> message -> checked scene.
    pub request_decode_s: f64,
    /// Server: completed cloud -> PointCloud2 -> bytes.
    pub response_encode_s: f64,
    /// Client: bytes -> message -> cloud.
    pub response_decode_s: f64,
    pub total_s: f64,
    /// `total_s` over the in-process pipeline's median time (target <= 0.05).
    pub share_of_pipeline: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct MillionPoints {
    pub points: usize,
    pub bytes: usize,
    pub encode_ms: f64,
    pub decode_ms: f64,
    /// Target <= 50 ms.
    pub total_ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct Load {
    pub clients: usize,
    pub requests_per_client: usize,
    pub sent: usize,
    /// Answers by status code name (`Ok`, `ResourceExhausted`, ...).
    pub statuses: BTreeMap<String, usize>,
    /// Sent minus answered (must be 0).
    pub lost: usize,
    pub latency_p50_s: f64,
    pub latency_p99_s: f64,
    pub latency_max_s: f64,
    pub wall_s: f64,
    pub throughput_per_s: f64,
    /// One over the in-process pipeline's median time.
    pub in_process_throughput_per_s: f64,
    pub peak_rss_mib_before: Option<f64>,
    pub peak_rss_mib_after: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ServiceReport {
    /// The machine and its load when the figures were taken.
    pub machine: super::timing::Machine,
    pub scene: String,
    pub views: usize,
    pub width: u32,
    pub height: u32,
    pub completers: String,
    pub workers: usize,
    pub queue: usize,
    pub rounds: usize,
    pub in_process_s: Vec<f64>,
    pub service_s: Vec<f64>,
    pub in_process_median_s: f64,
    pub service_median_s: f64,
    /// Service over in-process, medians (1.0 = no overhead).
    pub overhead_ratio: f64,
    pub serialisation: Serialisation,
    pub million_points: MillionPoints,
    pub load: Load,
}

fn timed<T>(f: impl FnOnce() -> T) -> (f64, T) {
    let t = Instant::now();
    let out = f();
    (t.elapsed().as_secs_f64(), out)
}

fn err(e: impl std::fmt::Display) -> EvalError {
    EvalError::Data(e.to_string())
}

/// Percentile `q` (0..1) of `v`, nearest rank.
fn percentile(v: &[f64], q: f64) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return f64::NAN;
    }
    let k = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
    v[k]
}

fn million_points() -> Result<MillionPoints, EvalError> {
    let n = 1_000_000;
    let cloud = deocc_geometry::PointCloud {
        positions: (0..n)
            .map(|i| Point3::new((i % 1000) as f32 * 1e-3, (i / 1000) as f32 * 1e-3, 1.0))
            .collect(),
        colors: Some((0..n).map(|i| [i as u8, 0, 255]).collect()),
        instance: Some((0..n).map(|i| (i % 7) as u32).collect()),
        generated: Some((0..n).map(|i| (i % 4) as u8).collect()),
        ..Default::default()
    };
    let (mut enc, mut dec, mut bytes) = (Vec::new(), Vec::new(), 0);
    for _ in 0..5 {
        let (te, wire) = timed(|| deocc_service::cloud2::encode(&cloud).encode_to_vec());
        let (td, back) = timed(|| {
            deocc_service::proto::PointCloud2::decode(wire.as_slice())
                .map_err(err)
                .and_then(|m| deocc_service::cloud2::decode(&m, "cloud").map_err(err))
        });
        if back?.positions != cloud.positions {
            return Err(EvalError::Data("1M-point cloud changed on the way".into()));
        }
        bytes = wire.len();
        enc.push(te);
        dec.push(td);
    }
    let (e, d) = (median(&enc) * 1e3, median(&dec) * 1e3);
    Ok(MillionPoints {
        points: n,
        bytes,
        encode_ms: e,
        decode_ms: d,
        total_ms: e + d,
    })
}

fn serialisation(
    scene: &SceneInput,
    completed: &deocc_geometry::PointCloud,
    pipeline_s: f64,
) -> Result<Serialisation, EvalError> {
    let (req_enc, wire) = timed(|| request_from_scene(scene, "").encode_to_vec());
    let (req_dec, decoded) = timed(|| {
        deocc_service::proto::CompleteRequest::decode(wire.as_slice())
            .map_err(err)
            .and_then(|r| scene_from_request(&r, &Limits::default()).map_err(err))
    });
    decoded?;
    let (resp_enc, answer) = timed(|| deocc_service::cloud2::encode(completed).encode_to_vec());
    let (resp_dec, back) = timed(|| {
        deocc_service::proto::PointCloud2::decode(answer.as_slice())
            .map_err(err)
            .and_then(|m| deocc_service::cloud2::decode(&m, "cloud").map_err(err))
    });
    back?;
    let total = req_enc + req_dec + resp_enc + resp_dec;
    Ok(Serialisation {
        request_bytes: wire.len(),
        response_bytes: answer.len(),
        request_encode_s: req_enc,
        request_decode_s: req_dec,
        response_encode_s: resp_enc,
        response_decode_s: resp_dec,
        total_s: total,
        share_of_pipeline: total / pipeline_s,
    })
}

/// Runs the benchmark with `chain` (the server's and the in-process call's); `tick` after each
/// load-test request.
pub fn service_bench(
    chain: CompleterChain,
    opts: &ServiceBenchOptions,
    tick: Arc<dyn Fn() + Send + Sync>,
) -> Result<ServiceReport, EvalError> {
    let preset = deocc_synth::dataset::bench_v1();
    let rendered = deocc_synth::dataset::render_full_scene(&preset.config, preset.seeds[0])?;
    let scene = rendered.scene_input();
    drop(rendered);
    let completers = chain.describe();
    let chain = Arc::new(chain);
    let direct = |chain: &CompleterChain| {
        deocc_pipeline::run_in_memory(
            scene.clone(),
            chain,
            &PipelineOptions::default(),
            &ConvexitySegmenter::default(),
            false,
            &Unobserved,
        )
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(err)?;
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .map_err(err)?;
    let addr = format!("http://{}", listener.local_addr().map_err(err)?);
    let config = ServerConfig {
        workers: opts.workers,
        queue: opts.queue,
        ..ServerConfig::default()
    };
    // The server and the in-process calls share one model.
    let service = DeoccService::from_shared(chain.clone(), completers.clone(), config);
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server = rt.spawn(async move {
        serve(service, listener, async {
            let _ = stop_rx.await;
        })
        .await
    });
    let client = rt.block_on(Client::connect(&addr, None)).map_err(err)?;
    // Warm-up: one of each.
    let warm = direct(&chain)?;
    rt.block_on(client.clone().complete_scene(&scene, "", None))
        .map_err(err)?;
    let (mut in_process, mut service_s) = (Vec::new(), Vec::new());
    for _ in 0..opts.rounds.max(1) {
        let (t, r) = timed(|| direct(&chain));
        r?;
        in_process.push(t);
        let (t, r) = timed(|| rt.block_on(client.clone().complete_scene(&scene, "", None)));
        r.map_err(err)?;
        service_s.push(t);
    }
    let (ip, sv) = (median(&in_process), median(&service_s));
    let ser = serialisation(&scene, &warm.completed, ip)?;
    drop(warm);
    let million = million_points()?;

    // Load.
    let rss_before = deocc_pipeline::report::peak_rss_mib();
    let scene = Arc::new(scene);
    let t0 = Instant::now();
    let results: Vec<(f64, tonic::Code)> = rt.block_on(async {
        let mut tasks = Vec::new();
        for _ in 0..opts.clients {
            let (mut c, s) = (client.clone(), scene.clone());
            let n = opts.requests;
            let tick = tick.clone();
            tasks.push(tokio::spawn(async move {
                let mut out = Vec::new();
                for _ in 0..n {
                    let t = Instant::now();
                    let code = match c
                        .complete_scene(&s, "", Some(Duration::from_secs(900)))
                        .await
                    {
                        Ok(_) => tonic::Code::Ok,
                        Err(e) => e.code(),
                    };
                    out.push((t.elapsed().as_secs_f64(), code));
                    tick();
                }
                out
            }));
        }
        let mut all = Vec::new();
        for t in tasks {
            if let Ok(v) = t.await {
                all.extend(v);
            }
        }
        all
    });
    let wall = t0.elapsed().as_secs_f64();
    let rss_after = deocc_pipeline::report::peak_rss_mib();
    let _ = stop_tx.send(());
    let _ = rt.block_on(server);
    let sent = opts.clients * opts.requests;
    let mut statuses = BTreeMap::new();
    for (_, c) in &results {
        *statuses.entry(format!("{c:?}")).or_insert(0) += 1;
    }
    let ok: Vec<f64> = results
        .iter()
        .filter(|(_, c)| *c == tonic::Code::Ok)
        .map(|(t, _)| *t)
        .collect();
    Ok(ServiceReport {
        machine: super::timing::Machine::now(),
        scene: format!("{} scene 0", preset.name),
        views: scene.frames.len(),
        width: preset.config.width,
        height: preset.config.height,
        completers,
        workers: opts.workers,
        queue: opts.queue,
        rounds: opts.rounds,
        in_process_s: in_process,
        service_s,
        in_process_median_s: ip,
        service_median_s: sv,
        overhead_ratio: sv / ip,
        serialisation: ser,
        million_points: million,
        load: Load {
            clients: opts.clients,
            requests_per_client: opts.requests,
            sent,
            lost: sent - results.len(),
            statuses,
            latency_p50_s: percentile(&ok, 0.5),
            latency_p99_s: percentile(&ok, 0.99),
            latency_max_s: percentile(&ok, 1.0),
            wall_s: wall,
            throughput_per_s: ok.len() as f64 / wall,
            in_process_throughput_per_s: 1.0 / ip,
            peak_rss_mib_before: rss_before,
            peak_rss_mib_after: rss_after,
        },
    })
}
