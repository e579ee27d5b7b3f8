//! The server on loopback, driven by the client: results equal the in-process pipeline's, bad
//! requests are refused naming the field while the server keeps serving, a full queue answers
//! RESOURCE_EXHAUSTED, deadlines stop work, the token is checked, and every request of a
//! concurrent burst is answered.

use std::sync::Arc;
use std::time::{Duration, Instant};

use deocc_completion::rules::RulesCompleter;
use deocc_completion::{
    Completer, CompleterChain, CompletionError, CompletionOptions, CropCompletion, CropRequest,
    Provenance,
};
use deocc_pipeline::segment::ConvexitySegmenter;
use deocc_pipeline::{PipelineOptions, SceneInput, Unobserved};
use deocc_service::client::Client;
use deocc_service::proto::{GraspRequest, PlaceRequest};
use deocc_service::request::request_from_scene;
use deocc_service::server::{serve, DeoccService, ServerConfig};
use tonic::Code;

/// The rules completer, slowed down: a request that takes long enough to queue behind.
struct Slow(RulesCompleter, Duration);

impl Completer for Slow {
    fn name(&self) -> &str {
        "rules"
    }
    fn provenance(&self) -> Provenance {
        self.0.provenance()
    }
    fn resolution(&self) -> usize {
        self.0.resolution()
    }
    fn complete(
        &self,
        batch: &[CropRequest<'_>],
        opts: &CompletionOptions,
    ) -> Result<Vec<CropCompletion>, CompletionError> {
        std::thread::sleep(self.1);
        self.0.complete(batch, opts)
    }
}

fn scene(seed: u64) -> SceneInput {
    let config = deocc_synth::scene::SceneConfig {
        views: 2,
        width: 160,
        height: 120,
        gt_points_per_m2: 100.0,
        ..Default::default()
    };
    deocc_synth::dataset::render_full_scene(&config, seed)
        .unwrap()
        .scene_input()
}

struct Running {
    addr: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    handle: tokio::task::JoinHandle<()>,
}

impl Running {
    async fn stop(mut self) {
        let _ = self.stop.take().unwrap().send(());
        tokio::time::timeout(Duration::from_secs(30), self.handle)
            .await
            .expect("graceful shutdown took over 30 s")
            .unwrap();
    }
}

async fn start(chain: CompleterChain, config: ServerConfig) -> Running {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = format!("http://{}", listener.local_addr().unwrap());
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let service = DeoccService::new(chain, "test".into(), config);
    let handle = tokio::spawn(async move {
        serve(service, listener, async {
            let _ = rx.await;
        })
        .await
        .unwrap();
    });
    Running {
        addr,
        stop: Some(tx),
        handle,
    }
}

fn rules() -> CompleterChain {
    CompleterChain::new(vec![Box::new(RulesCompleter::default())])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_completion_over_grpc_equals_the_pipeline_in_process() {
    let s = scene(9_000_000);
    // The scene as the server sees it (poses cross as 4x4 rows, which may move a pose's last
    // bit; a scene folder's rows cross unchanged, as the Python test shows).
    let (as_sent, _) = deocc_service::request::scene_from_request(
        &request_from_scene(&s, ""),
        &deocc_service::request::Limits::default(),
    )
    .unwrap();
    let direct = deocc_pipeline::run_in_memory(
        as_sent,
        &rules(),
        &PipelineOptions::default(),
        &ConvexitySegmenter::default(),
        false,
        &Unobserved,
    )
    .unwrap();
    let server = start(rules(), ServerConfig::default()).await;
    let mut client = Client::connect(&server.addr, None).await.unwrap();
    let health = client.health().await.unwrap();
    assert!(health.serving);
    assert_eq!(health.model, "test");
    let got = client.complete_scene(&s, "", None).await.unwrap();
    let cloud = got.cloud().unwrap();
    assert!(
        cloud.positions == direct.completed.positions,
        "points differ"
    );
    assert!(
        cloud.instance == direct.completed.instance,
        "instances differ"
    );
    assert!(
        cloud.generated == direct.completed.generated,
        "provenance differs"
    );
    assert_eq!(
        got.result.points_observed as usize,
        direct.report.points_observed
    );
    for stage in ["queued", "reconstruct", "complete", "planes", "encode"] {
        assert!(
            got.stages.iter().any(|s| s == stage),
            "no {stage} in {:?}",
            got.stages
        );
    }
    // Grasp and place on the answer.
    let ids = cloud.instance.clone().unwrap();
    let target = *ids.iter().filter(|&&i| i > 2).max().unwrap();
    let g = client
        .grasp(GraspRequest {
            cloud: got.result.cloud.clone(),
            target,
            options_json: String::new(),
            target_pick: None,
        })
        .await;
    match g {
        Ok(g) => assert!(g.target_points > 0),
        // A target the planner cannot grasp is answered, naming it.
        Err(s) => assert!(s.message().contains(&format!("target {target}")), "{s:?}"),
    }
    let e = client
        .grasp(GraspRequest {
            cloud: got.result.cloud.clone(),
            target: 60_000,
            options_json: String::new(),
            target_pick: None,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("target"), "{e:?}");
    // The target by a pixel of the first view: the object whose mask holds the pixel with the
    // most of the same id around it.
    let f0 = &s.frames[0];
    let inst = f0.instances.as_ref().unwrap();
    let (w, h) = (inst.width, inst.height);
    let at = |u: u32, v: u32| inst.ids[(v * w + u) as usize];
    let (mut best, mut best_r) = ((0, 0, 0u16), 0);
    for v in 8..h - 8 {
        for u in 8..w - 8 {
            let id = at(u, v);
            if id == 0 || s.structure_ids.contains(&id) {
                continue;
            }
            let r = (1..8)
                .take_while(|&r| {
                    at(u - r, v) == id
                        && at(u + r, v) == id
                        && at(u, v - r) == id
                        && at(u, v + r) == id
                })
                .count();
            if r > best_r {
                (best, best_r) = ((u, v, id), r);
            }
        }
    }
    let frame0 = &request_from_scene(&s, "").frames[0];
    let pick = deocc_service::proto::TargetPick {
        pixel: vec![best.0 as f32 + 0.5, best.1 as f32 + 0.5],
        camera_info: frame0.camera_info.clone(),
        world_from_camera: frame0.world_from_camera.clone(),
    };
    let g = client
        .grasp(GraspRequest {
            cloud: got.result.cloud.clone(),
            target: 0,
            options_json: String::new(),
            target_pick: Some(pick),
        })
        .await;
    match g {
        Ok(g) => assert_eq!(g.target, best.2 as u32, "picked the wrong instance"),
        Err(s) => assert!(s.message().contains(&format!("target {}", best.2)), "{s:?}"),
    }
    let p = client
        .place(PlaceRequest {
            cloud: got.result.cloud.clone(),
            footprint_w: 0.08,
            footprint_d: 0.08,
            height: 0.12,
            ..Default::default()
        })
        .await;
    match p {
        Ok(p) => assert!(!p.maps.is_empty()),
        Err(s) => assert_eq!(s.code(), Code::InvalidArgument, "{s:?}"),
    }
    let e = client
        .place(PlaceRequest {
            cloud: got.result.cloud.clone(),
            footprint_w: -1.0,
            footprint_d: 0.08,
            height: 0.12,
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_name_the_field_and_the_server_keeps_serving() {
    let server = start(
        rules(),
        ServerConfig {
            max_message_bytes: 8 << 20,
            limits: deocc_service::request::Limits {
                max_frames: 3,
                ..Default::default()
            },
            ..Default::default()
        },
    )
    .await;
    let mut client = Client::connect(&server.addr, None).await.unwrap();
    let good = request_from_scene(&scene(9_000_001), "");
    let check = |e: tonic::Status, code: Code, field: &str| {
        assert_eq!(e.code(), code, "{e:?}");
        assert!(
            e.message().contains(field),
            "{field} not in {:?}",
            e.message()
        );
    };
    let mut r = good.clone();
    r.frames[1].depth = None;
    check(
        client.complete(r, None).await.err().unwrap(),
        Code::InvalidArgument,
        "frames[1].depth: missing",
    );
    let mut r = good.clone();
    r.frames[0].depth.as_mut().unwrap().data.truncate(100);
    check(
        client.complete(r, None).await.err().unwrap(),
        Code::InvalidArgument,
        "frames[0].depth.data",
    );
    let mut r = good.clone();
    r.frames[0].camera_info.as_mut().unwrap().k[0] = f64::NAN;
    check(
        client.complete(r, None).await.err().unwrap(),
        Code::InvalidArgument,
        "frames[0].camera_info.k",
    );
    let mut r = good.clone();
    r.frames[1].rgb.as_mut().unwrap().width = 80;
    check(
        client.complete(r, None).await.err().unwrap(),
        Code::InvalidArgument,
        "frames[1].rgb",
    );
    let mut r = good.clone();
    r.frames[0].world_from_camera[0] = 2.0;
    check(
        client.complete(r, None).await.err().unwrap(),
        Code::InvalidArgument,
        "frames[0].world_from_camera",
    );
    let mut r = good.clone();
    r.options_json = r#"{"stpes": 4}"#.into();
    check(
        client.complete(r, None).await.err().unwrap(),
        Code::InvalidArgument,
        "options_json",
    );
    let mut r = good.clone();
    r.frames = vec![r.frames[0].clone(); 4];
    check(
        client.complete(r, None).await.err().unwrap(),
        Code::InvalidArgument,
        "frames",
    );
    // Over the 8 MiB message limit: refused before decoding.
    let mut r = good.clone();
    r.frames[0].rgb.as_mut().unwrap().data = vec![0; 9 << 20];
    let e = client.complete(r, None).await.err().unwrap();
    assert!(
        matches!(e.code(), Code::OutOfRange | Code::ResourceExhausted),
        "{e:?}"
    );
    // Still serving.
    let ok = client.complete(good, None).await.unwrap();
    assert!(ok.result.points_observed > 0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_refuses_and_a_deadline_stops_the_work() {
    let slow = || {
        CompleterChain::new(vec![Box::new(Slow(
            RulesCompleter::default(),
            Duration::from_millis(1500),
        ))])
    };
    let server = start(
        slow(),
        ServerConfig {
            workers: 1,
            queue: 0,
            ..Default::default()
        },
    )
    .await;
    let s = Arc::new(scene(9_000_002));
    let mut a = Client::connect(&server.addr, None).await.unwrap();
    let mut b = a.clone();
    let first = {
        let s = s.clone();
        tokio::spawn(async move { a.complete_scene(&s, "", None).await })
    };
    // Wait until the first request holds the only worker.
    let t = Instant::now();
    while b.health().await.unwrap().running == 0 {
        assert!(t.elapsed() < Duration::from_secs(20));
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let e = b.complete_scene(&s, "", None).await.err().unwrap();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(first.await.unwrap().is_ok());
    // A deadline shorter than the run: the client hears of it and the server stops the work.
    let e = b
        .complete_scene(&s, "", Some(Duration::from_millis(300)))
        .await
        .err()
        .unwrap();
    assert!(
        matches!(e.code(), Code::DeadlineExceeded | Code::Cancelled),
        "{e:?}"
    );
    let t = Instant::now();
    loop {
        let h = b.health().await.unwrap();
        if h.running == 0 && h.queued == 0 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(10), "work kept running");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_token_is_checked_and_a_burst_is_answered_in_full() {
    let server = start(
        rules(),
        ServerConfig {
            workers: 1,
            queue: 1,
            token: Some("s3cret".into()),
            ..Default::default()
        },
    )
    .await;
    let mut anon = Client::connect(&server.addr, None).await.unwrap();
    assert_eq!(
        anon.health().await.unwrap_err().code(),
        Code::Unauthenticated
    );
    let mut wrong = Client::connect(&server.addr, Some("nope".into()))
        .await
        .unwrap();
    assert_eq!(
        wrong.health().await.unwrap_err().code(),
        Code::Unauthenticated
    );
    let client = Client::connect(&server.addr, Some("s3cret".into()))
        .await
        .unwrap();
    let s = Arc::new(scene(9_000_003));
    let mut tasks = Vec::new();
    for _ in 0..4 {
        let (mut c, s) = (client.clone(), s.clone());
        tasks.push(tokio::spawn(async move {
            let mut codes = Vec::new();
            for _ in 0..2 {
                codes.push(match c.complete_scene(&s, "", None).await {
                    Ok(_) => Code::Ok,
                    Err(e) => e.code(),
                });
            }
            codes
        }));
    }
    let mut codes = Vec::new();
    for t in tasks {
        codes.extend(t.await.unwrap());
    }
    assert_eq!(codes.len(), 8);
    assert!(codes.contains(&Code::Ok));
    assert!(
        codes
            .iter()
            .all(|c| matches!(c, Code::Ok | Code::ResourceExhausted)),
        "{codes:?}"
    );
    server.stop().await;
}
