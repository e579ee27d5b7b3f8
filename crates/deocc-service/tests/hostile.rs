//! Hostile input to the server, each case one that was mishandled before (issue "Hostile input,
//! round two"): K matrices that are not pinhole, float millimetres, malformed and oversized
//! messages' status codes, Health's counters after cancels and for Grasp/Place, stalled uploads
//! holding memory, a unary call past its deadline, and the token header's forms.

use std::time::{Duration, Instant};

use deocc_completion::rules::RulesCompleter;
use deocc_completion::CompleterChain;
use deocc_service::client::Client;
use deocc_service::guard::UploadLimits;
use deocc_service::proto::{GraspRequest, PlaceRequest};
use deocc_service::raw::{frame, frame_header, RawCall};
use deocc_service::request::request_from_scene;
use deocc_service::server::{serve, DeoccService, ServerConfig};
use prost::Message;
use tonic::Code;

fn scene(seed: u64) -> deocc_pipeline::SceneInput {
    let config = deocc_synth::scene::SceneConfig {
        views: 1,
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
    stop: tokio::sync::oneshot::Sender<()>,
    handle: tokio::task::JoinHandle<()>,
}

/// The rules completer, slowed down: a call that holds the worker long enough to queue behind.
struct Slow(RulesCompleter, Duration);

impl deocc_completion::Completer for Slow {
    fn name(&self) -> &str {
        "rules"
    }
    fn provenance(&self) -> deocc_completion::Provenance {
        self.0.provenance()
    }
    fn resolution(&self) -> usize {
        self.0.resolution()
    }
    fn complete(
        &self,
        batch: &[deocc_completion::CropRequest<'_>],
        opts: &deocc_completion::CompletionOptions,
    ) -> Result<Vec<deocc_completion::CropCompletion>, deocc_completion::CompletionError> {
        std::thread::sleep(self.1);
        self.0.complete(batch, opts)
    }
}

async fn start(config: ServerConfig) -> Running {
    start_with(
        CompleterChain::new(vec![Box::new(RulesCompleter::default())]),
        config,
    )
    .await
}

async fn start_with(chain: CompleterChain, config: ServerConfig) -> Running {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let (stop, rx) = tokio::sync::oneshot::channel::<()>();
    let service = DeoccService::new(chain, "test".into(), config);
    let handle = tokio::spawn(async move {
        serve(service, listener, async {
            let _ = rx.await;
        })
        .await
        .unwrap();
    });
    Running { addr, stop, handle }
}

impl Running {
    async fn client(&self) -> Client {
        Client::connect(&format!("http://{}", self.addr), None)
            .await
            .unwrap()
    }
    async fn stop(self) {
        let _ = self.stop.send(());
        tokio::time::timeout(Duration::from_secs(40), self.handle)
            .await
            .expect("shutdown")
            .unwrap();
    }
}

/// Health's counters back at zero within `within`.
async fn settles(client: &mut Client, within: Duration) {
    let t = Instant::now();
    loop {
        let h = client.health().await.unwrap();
        if h.queued == 0 && h.running == 0 {
            return;
        }
        assert!(t.elapsed() < within, "Health stuck at {h:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn camera_matrices_that_are_not_pinhole_and_float_millimetres_are_refused() {
    let server = start(ServerConfig::default()).await;
    let mut client = server.client().await;
    let good = request_from_scene(&scene(9_100_000), "");
    let k = good.frames[0].camera_info.as_ref().unwrap().k.clone();
    let transposed = vec![k[0], 0.0, 0.0, 0.0, k[4], 0.0, k[2], k[5], 1.0];
    let mut skewed = k.clone();
    skewed[1] = 3.0;
    let mut k8 = k.clone();
    k8[8] = 0.0;
    for (name, bad, says) in [
        ("transposed", transposed, "transposed"),
        ("skewed", skewed, "skew"),
        ("K[8] = 0", k8, "K[8]"),
    ] {
        let mut r = good.clone();
        r.frames[0].camera_info.as_mut().unwrap().k = bad;
        let e = client.complete(r, None).await.err().unwrap();
        assert_eq!(e.code(), Code::InvalidArgument, "{name}: {e:?}");
        assert!(
            e.message().contains("frames[0].camera_info.k") && e.message().contains(says),
            "{name}: {}",
            e.message()
        );
    }
    // Distortion as ROS states it: unknown models and wrong counts refused by field; a stated
    // lens is taken (and removed on arrival).
    for (model, d, says) in [
        ("kannala_brandt8", vec![0.1; 8], "unknown distortion model"),
        ("plumb_bob", vec![0.1, 0.2], "takes 5"),
        ("", vec![0.1, 0.0, 0.0, 0.0, 0.0], "without a model"),
    ] {
        let mut r = good.clone();
        let info = r.frames[0].camera_info.as_mut().unwrap();
        info.distortion_model = model.into();
        info.d = d;
        let e = client.complete(r, None).await.err().unwrap();
        assert_eq!(e.code(), Code::InvalidArgument, "{model}: {e:?}");
        assert!(
            e.message().contains("frames[0].camera_info.d") && e.message().contains(says),
            "{model}: {}",
            e.message()
        );
    }
    let mut r = good.clone();
    let info = r.frames[0].camera_info.as_mut().unwrap();
    info.distortion_model = "plumb_bob".into();
    info.d = vec![-0.05, 0.01, 0.0, 0.0, 0.0];
    assert!(client.complete(r, None).await.is_ok());
    // The same depth as float32 millimetres: refused, saying what to do.
    let mut r = good.clone();
    let d = r.frames[0].depth.as_mut().unwrap();
    let mm: Vec<u8> = d
        .data
        .chunks_exact(2)
        .flat_map(|b| f32::from(u16::from_le_bytes([b[0], b[1]])).to_le_bytes())
        .collect();
    d.encoding = "32FC1".into();
    d.step *= 2;
    d.data = mm;
    let e = client.complete(r.clone(), None).await.err().unwrap();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(
        e.message().contains("frames[0].depth") && e.message().contains("millimetres"),
        "{}",
        e.message()
    );
    // In metres it is taken.
    let d = r.frames[0].depth.as_mut().unwrap();
    let m: Vec<u8> = d
        .data
        .chunks_exact(4)
        .flat_map(|b| (f32::from_le_bytes([b[0], b[1], b[2], b[3]]) / 1000.0).to_le_bytes())
        .collect();
    d.data = m;
    assert!(client.complete(r, None).await.is_ok());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_and_oversized_messages_get_the_conventional_codes() {
    let server = start(ServerConfig {
        max_message_bytes: 1 << 20,
        ..Default::default()
    })
    .await;
    // Not protobuf: INVALID_ARGUMENT (tonic said INTERNAL).
    let mut call = RawCall::open(&server.addr, "Complete", &[]).await.unwrap();
    call.send(&frame(&[0xff; 64]), true).unwrap();
    let a = call.answer().await.unwrap();
    assert_eq!(a.status.code(), Code::InvalidArgument, "{:?}", a.status);
    // A body that ends inside a message: INVALID_ARGUMENT too.
    let mut call = RawCall::open(&server.addr, "Grasp", &[]).await.unwrap();
    call.send(&frame_header(100), false).unwrap();
    call.send(&[1, 2, 3], true).unwrap();
    let a = call.answer().await.unwrap();
    assert_eq!(a.status.code(), Code::InvalidArgument, "{:?}", a.status);
    // Over the size limit: RESOURCE_EXHAUSTED (tonic said OUT_OF_RANGE).
    let mut call = RawCall::open(&server.addr, "Complete", &[]).await.unwrap();
    call.send(&frame_header(2 << 20), false).unwrap();
    let a = call.answer().await.unwrap();
    assert_eq!(a.status.code(), Code::ResourceExhausted, "{:?}", a.status);
    // A well-formed Health through the raw client answers OK.
    let mut call = RawCall::open(&server.addr, "Health", &[]).await.unwrap();
    call.send(&frame(&[]), true).unwrap();
    let a = call.answer().await.unwrap();
    assert_eq!(a.status.code(), Code::Ok, "{:?}", a.status);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_uploads_are_timed_out_and_bounded_before_they_are_buffered() {
    let server = start(ServerConfig {
        uploads: UploadLimits {
            max_uploads: 4,
            max_upload_bytes: 3 << 20,
            stall: Duration::from_millis(1500),
        },
        ..Default::default()
    })
    .await;
    let mut client = server.client().await;
    // Two uploads announce 60 MB and stop after 1 MiB each.
    let mut stalled = Vec::new();
    for _ in 0..2 {
        let mut call = RawCall::open(&server.addr, "Complete", &[]).await.unwrap();
        call.send(&frame_header(60 << 20), false).unwrap();
        call.send(&vec![0u8; 1 << 20], false).unwrap();
        stalled.push(call);
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    // A third that would pass the 3 MiB of bytes in flight is refused at once.
    let mut third = RawCall::open(&server.addr, "Complete", &[]).await.unwrap();
    third.send(&frame_header(60 << 20), false).unwrap();
    third.send(&vec![0u8; 2 << 20], false).unwrap();
    let a = tokio::time::timeout(Duration::from_secs(5), third.answer())
        .await
        .expect("refused at once")
        .unwrap();
    assert_eq!(a.status.code(), Code::ResourceExhausted, "{:?}", a.status);
    // The stalled ones end with DEADLINE_EXCEEDED after the stall time, not never.
    let t = Instant::now();
    for call in stalled {
        let a = tokio::time::timeout(Duration::from_secs(10), call.answer())
            .await
            .expect("a stalled upload must be timed out")
            .unwrap();
        assert_eq!(a.status.code(), Code::DeadlineExceeded, "{:?}", a.status);
    }
    assert!(t.elapsed() < Duration::from_secs(5));
    // Five bodies arriving at once with a limit of four: one is refused before a byte is read.
    let mut open = Vec::new();
    for _ in 0..4 {
        let mut call = RawCall::open(&server.addr, "Complete", &[]).await.unwrap();
        call.send(&frame_header(100), false).unwrap();
        open.push(call);
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut fifth = RawCall::open(&server.addr, "Complete", &[]).await.unwrap();
    fifth.send(&frame_header(100), false).unwrap();
    let a = fifth.answer().await.unwrap();
    assert_eq!(a.status.code(), Code::ResourceExhausted, "{:?}", a.status);
    for c in open {
        c.cancel();
    }
    // Normal traffic still answered, and nothing is left counted.
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(client
        .complete(request_from_scene(&scene(9_100_001), ""), None)
        .await
        .is_ok());
    settles(&mut client, Duration::from_secs(5)).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_counts_every_call_and_returns_to_zero_after_cancels() {
    let slow = CompleterChain::new(vec![Box::new(Slow(
        RulesCompleter::default(),
        Duration::from_millis(4000),
    ))]);
    let server = start_with(
        slow,
        ServerConfig {
            workers: 1,
            queue: 4,
            ..Default::default()
        },
    )
    .await;
    let mut client = server.client().await;
    let req = request_from_scene(&scene(9_100_002), "");
    // Hold the worker with one call, queue another and hang up on it (RST_STREAM) while it
    // waits: its place is given back at once, while the first still runs.
    let mut a = client.clone();
    let r1 = req.clone();
    let first = tokio::spawn(async move { a.complete(r1, None).await });
    let t = Instant::now();
    while client.health().await.unwrap().running == 0 {
        assert!(t.elapsed() < Duration::from_secs(20));
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let mut second = RawCall::open(&server.addr, "Complete", &[]).await.unwrap();
    second.send(&frame(&req.encode_to_vec()), true).unwrap();
    while client.health().await.unwrap().queued == 0 {
        assert!(
            !first.is_finished(),
            "the first call ended before the second queued"
        );
        assert!(t.elapsed() < Duration::from_secs(20));
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    second.cancel();
    let t = Instant::now();
    loop {
        let h = client.health().await.unwrap();
        if h.queued == 0 {
            assert_eq!(h.running, 1, "the first call should still run: {h:?}");
            break;
        }
        assert!(
            t.elapsed() < Duration::from_millis(1500),
            "a hung-up call stayed queued: {h:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // One that times out while queued.
    let mut c = client.clone();
    let _ = c
        .complete(req.clone(), Some(Duration::from_millis(1)))
        .await;
    let _ = first.await;
    settles(&mut client, Duration::from_secs(10)).await;

    // A Grasp counts as running while it plans.
    let done = client.complete(req, None).await.unwrap();
    let target = done
        .cloud()
        .unwrap()
        .instance
        .unwrap()
        .into_iter()
        .find(|&i| i != 0)
        .unwrap();
    let cloud = done.result.cloud.clone();
    let mut g = client.clone();
    let grasp = tokio::spawn(async move {
        g.grasp(GraspRequest {
            cloud,
            target,
            options_json: r#"{"seeds": 1500, "approaches": 20}"#.into(),
            target_pick: None,
        })
        .await
    });
    let t = Instant::now();
    let mut saw = false;
    while !grasp.is_finished() && t.elapsed() < Duration::from_secs(60) {
        if client.health().await.unwrap().running > 0 {
            saw = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let _ = grasp.await;
    assert!(saw, "Health never counted the Grasp as running");
    settles(&mut client, Duration::from_secs(10)).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_unary_call_answers_at_its_deadline_and_bad_options_are_refused_by_name() {
    let server = start(ServerConfig::default()).await;
    let mut client = server.client().await;
    let done = client
        .complete(request_from_scene(&scene(9_100_003), ""), None)
        .await
        .unwrap();
    let cloud = done.result.cloud.clone();
    let target = done
        .cloud()
        .unwrap()
        .instance
        .unwrap()
        .into_iter()
        .find(|&i| i != 0)
        .unwrap();
    for (options, field) in [
        (r#"{"approaches": 1000000000000}"#, "approaches"),
        (
            r#"{"normal_neighbours": 18446744073709551615}"#,
            "normal_neighbours",
        ),
        (r#"{"normal_neighbours": 0}"#, "normal_neighbours"),
        (r#"{"voxel_m": 1e-30}"#, "voxel_m"),
        (r#"{"depths": [-1]}"#, "depths[0]"),
        ("[]", "JSON object"),
        ("[4]", "JSON object"),
    ] {
        let e = client
            .grasp(GraspRequest {
                cloud: cloud.clone(),
                target,
                options_json: options.into(),
                target_pick: None,
            })
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{options}: {e:?}");
        assert!(e.message().contains(field), "{options}: {}", e.message());
    }
    // A NaN robot position.
    let e = client
        .place(PlaceRequest {
            cloud: cloud.clone(),
            footprint_w: 0.08,
            footprint_d: 0.08,
            height: 0.1,
            robot: vec![f32::NAN; 3],
            up: vec![],
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    // The longest grasp the ranges allow, with a 300 ms deadline: DEADLINE_EXCEEDED by about
    // then, not when the planning ends.
    let msg = GraspRequest {
        cloud,
        target,
        options_json: r#"{"seeds": 1600, "approaches": 20}"#.into(),
        target_pick: None,
    };
    let mut call = RawCall::open(&server.addr, "Grasp", &[("grpc-timeout", b"300m")])
        .await
        .unwrap();
    call.send(&frame(&msg.encode_to_vec()), true).unwrap();
    let t = Instant::now();
    let a = call.answer().await.unwrap();
    let took = t.elapsed();
    if a.status.code() != Code::Ok {
        assert_eq!(a.status.code(), Code::DeadlineExceeded, "{:?}", a.status);
        assert!(took < Duration::from_secs(2), "answered after {took:?}");
    }
    settles(&mut client, Duration::from_secs(60)).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_bearer_scheme_is_case_insensitive_and_a_non_ascii_token_is_wrong_not_missing() {
    let server = start(ServerConfig {
        token: Some("s3cret".into()),
        ..Default::default()
    })
    .await;
    let health = |auth: &'static [u8]| {
        let addr = server.addr.clone();
        async move {
            let headers: Vec<(&str, &[u8])> = if auth.is_empty() {
                vec![]
            } else {
                vec![("authorization", auth)]
            };
            let mut call = RawCall::open(&addr, "Health", &headers).await.unwrap();
            // A refused caller may be answered, and its stream closed, before its body goes out
            // (h2's InactiveStreamId): the answer is what this test reads.
            let _ = call.send(&frame(&[]), true);
            call.answer().await.unwrap().status
        }
    };
    assert_eq!(health(b"Bearer s3cret").await.code(), Code::Ok);
    assert_eq!(health(b"bearer s3cret").await.code(), Code::Ok);
    assert_eq!(health(b"BEARER s3cret").await.code(), Code::Ok);
    let s = health(b"Bearer s\xc3\xa9cret").await;
    assert_eq!(s.code(), Code::Unauthenticated);
    assert!(s.message().contains("wrong token"), "{}", s.message());
    let s = health(b"").await;
    assert_eq!(s.code(), Code::Unauthenticated);
    assert!(s.message().contains("needs"), "{}", s.message());
    server.stop().await;
}
