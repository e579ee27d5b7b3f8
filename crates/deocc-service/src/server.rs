//! The gRPC server: one model shared by every request, a bounded queue in front of a fixed
//! number of pipeline workers, per-request deadlines and cancellation, message-size limits, an
//! optional shared token, graceful shutdown.
//!
//! A request is admitted if fewer than `workers + queue` requests are queued or running (else
//! RESOURCE_EXHAUSTED), decoded and checked (INVALID_ARGUMENT naming the field), then waits for a
//! worker. Its deadline (the client's `grpc-timeout`, capped by the server's) and the client
//! hanging up are checked while it waits and between pipeline stages: a cancelled or timed-out
//! request stops there and frees what it held.

use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use deocc_completion::CompleterChain;
use deocc_pipeline::{Observer, PipelineError};
use deocc_robot::place::{PlaceOptions, UnseenSpace};
use deocc_robot::{AntipodalPlanner, GraspOptions, GraspPlanner, GridPlacer, PlacePlanner};
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

use crate::guard::{UploadGuardLayer, UploadLimits, UploadState};
use crate::proto::deocc_server::{Deocc, DeoccServer};
use crate::proto::{
    complete_event, CompleteEvent, CompleteRequest, GraspPose, GraspRequest, GraspResponse,
    HealthRequest, HealthResponse, PlaceRequest, PlaceResponse, Progress,
};
use crate::request::{scene_from_request, Limits};
use crate::{cloud2, FieldError};

/// How the server runs.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Pipeline runs at once (each uses every core through rayon; 1 is right for most machines).
    pub workers: usize,
    /// Requests that may wait for a worker; more are refused with RESOURCE_EXHAUSTED.
    pub queue: usize,
    /// Largest request or response message, bytes.
    pub max_message_bytes: usize,
    pub limits: Limits,
    /// Longest a request may take (a client's shorter `grpc-timeout` wins).
    pub max_deadline: Duration,
    /// If set, every call needs `authorization: Bearer <token>`.
    pub token: Option<String>,
    /// What requests may hold while they arrive ([`crate::guard`]).
    pub uploads: UploadLimits,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            workers: 1,
            queue: 8,
            // Ten 640x480 RGB-D frames are ~15 MB; a 2M-point answer is 56 MB.
            max_message_bytes: 64 << 20,
            limits: Limits::default(),
            max_deadline: Duration::from_secs(600),
            token: None,
            uploads: UploadLimits::default(),
        }
    }
}

/// The service: the shared model and the queue.
pub struct DeoccService {
    chain: Arc<CompleterChain>,
    model: String,
    config: ServerConfig,
    admission: Arc<Semaphore>,
    workers: Arc<Semaphore>,
    queued: Arc<AtomicU32>,
    running: Arc<AtomicU32>,
    uploads: Arc<UploadState>,
}

fn status_of(e: &FieldError) -> Status {
    Status::invalid_argument(e.to_string())
}

fn pipeline_status(e: PipelineError) -> Status {
    match e {
        PipelineError::Cancelled { stage } => {
            Status::cancelled(format!("stopped before stage {stage}"))
        }
        PipelineError::Input { .. } | PipelineError::Option { .. } | PipelineError::Io(_) => {
            Status::invalid_argument(e.to_string())
        }
        other => Status::internal(other.to_string()),
    }
}

/// How much earlier than a client's `grpc-timeout` the service gives up, at most (a quarter of
/// the timeout below 400 ms). tonic's own timeout layer starts its clock when the request's
/// headers arrive, before the body has streamed in and been decoded (tens of milliseconds for a
/// large cloud on a busy machine), and answers CANCELLED ("Timeout expired"); the service
/// answers DEADLINE_EXCEEDED, as the gRPC spec says, only if its clock runs out first.
pub const DEADLINE_LEAD: Duration = Duration::from_millis(100);

/// The deadline of a request: its `grpc-timeout` header less its lead ([`DEADLINE_LEAD`]),
/// capped by `max`.
pub fn deadline<T>(req: &Request<T>, max: Duration) -> Instant {
    let timeout = req
        .metadata()
        .get("grpc-timeout")
        .and_then(|v| v.to_str().ok())
        .and_then(parse_grpc_timeout)
        .map_or(max, |t| t.saturating_sub(DEADLINE_LEAD.min(t / 4)).min(max));
    Instant::now() + timeout
}

/// A `grpc-timeout` value: up to 8 digits and a unit (H, M, S, m, u, n).
pub fn parse_grpc_timeout(v: &str) -> Option<Duration> {
    let (digits, unit) = v.split_at(v.len().checked_sub(1)?);
    if digits.is_empty() || digits.len() > 8 {
        return None;
    }
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n * 3600),
        "M" => Duration::from_secs(n * 60),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

/// Progress events to the client; stops the run when the client is gone or the deadline passed.
struct StreamObserver {
    tx: mpsc::Sender<Result<CompleteEvent, Status>>,
    deadline: Instant,
}

impl StreamObserver {
    fn send(&self, stage: &str, fraction: f32) -> bool {
        if self.tx.is_closed() || Instant::now() > self.deadline {
            return false;
        }
        // Progress is advisory: a client that does not read it only misses events.
        let _ = self.tx.try_send(Ok(progress(stage, fraction)));
        true
    }
}

impl Observer for StreamObserver {
    fn stage(&self, stage: &'static str, fraction: f32) -> bool {
        self.send(stage, fraction)
    }
}

fn progress(stage: &str, fraction: f32) -> CompleteEvent {
    CompleteEvent {
        event: Some(complete_event::Event::Progress(Progress {
            stage: stage.into(),
            fraction,
        })),
    }
}

impl DeoccService {
    /// A service completing with `chain`; `model` says which model it is (for Health).
    pub fn new(chain: CompleterChain, model: String, config: ServerConfig) -> Self {
        Self::from_shared(Arc::new(chain), model, config)
    }

    /// [`DeoccService::new`] with a chain shared with other users of the model.
    pub fn from_shared(chain: Arc<CompleterChain>, model: String, config: ServerConfig) -> Self {
        let workers = config.workers.max(1);
        Self {
            chain,
            model,
            admission: Arc::new(Semaphore::new(workers + config.queue)),
            workers: Arc::new(Semaphore::new(workers)),
            queued: Arc::new(AtomicU32::new(0)),
            running: Arc::new(AtomicU32::new(0)),
            uploads: Arc::new(UploadState::default()),
            config,
        }
    }

    fn admit(&self) -> Result<OwnedSemaphorePermit, Status> {
        self.admission.clone().try_acquire_owned().map_err(|_| {
            Status::resource_exhausted(format!(
                "the server is busy: {} requests running or queued (workers {} + queue {}); retry later",
                self.config.workers.max(1) + self.config.queue,
                self.config.workers.max(1),
                self.config.queue
            ))
        })
    }

    /// Waits for a worker until `deadline`; counts the request as queued meanwhile.
    fn worker(
        &self,
        deadline: Instant,
    ) -> impl std::future::Future<Output = Result<OwnedSemaphorePermit, Status>> + Send + 'static
    {
        let (queued, workers) = (self.queued.clone(), self.workers.clone());
        async move {
            // Counted down when the wait ends or when the future is dropped (the client hung up
            // while queued): Health's `queued` comes back to zero either way.
            let _counted = Counted::new(queued);
            let got = tokio::time::timeout_at(deadline.into(), workers.acquire_owned()).await;
            match got {
                Ok(Ok(p)) => Ok(p),
                Ok(Err(_)) => Err(Status::unavailable("the server is shutting down")),
                Err(_) => Err(Status::deadline_exceeded(
                    "the deadline passed while the request waited in the queue",
                )),
            }
        }
    }

    /// A unary call through the same queue as `Complete`: admitted, given a worker before its
    /// deadline, run on the blocking pool (counted as running meanwhile); the client gets
    /// DEADLINE_EXCEEDED at its deadline even if the work is still going (the work is bounded by
    /// the options' ranges and keeps its worker until it ends).
    async fn unary<T: Send + 'static, R: Send + 'static>(
        &self,
        req: Request<T>,
        work: impl FnOnce(T) -> Result<R, Status> + Send + 'static,
    ) -> Result<Response<R>, Status> {
        let admitted = self.admit()?;
        let deadline = deadline(&req, self.config.max_deadline);
        let req = req.into_inner();
        let permit = self.worker(deadline).await?;
        let running = Counted::new(self.running.clone());
        let job = tokio::task::spawn_blocking(move || {
            let _held = (permit, running, admitted);
            work(req)
        });
        match tokio::time::timeout_at(deadline.into(), job).await {
            Ok(done) => done
                .map_err(|e| Status::internal(format!("the call panicked: {e}")))?
                .map(Response::new),
            Err(_) => Err(Status::deadline_exceeded(
                "the deadline passed while the call was running",
            )),
        }
    }

    /// The guard for this service's request bodies (add it with `Server::builder().layer`).
    pub fn upload_guard(&self) -> UploadGuardLayer {
        UploadGuardLayer::new(self.config.uploads, self.uploads.clone())
    }

    /// Request bodies arriving now and the bytes they hold.
    pub fn uploads(&self) -> (usize, usize) {
        (
            self.uploads.uploads.load(Ordering::Relaxed),
            self.uploads.bytes.load(Ordering::Relaxed),
        )
    }

    /// The tonic service with the configured limits and token check.
    pub fn into_server(
        self,
    ) -> tonic::service::interceptor::InterceptedService<DeoccServer<Self>, TokenCheck> {
        let max = self.config.max_message_bytes;
        let check = TokenCheck(self.config.token.clone().map(Arc::from));
        let server = DeoccServer::new(self)
            .max_decoding_message_size(max)
            .max_encoding_message_size(max);
        tonic::service::interceptor::InterceptedService::new(server, check)
    }
}

/// One count of a Health counter, given back when dropped (whatever ends the wait or the work:
/// an answer, an error, a deadline, a client hanging up, a panic).
struct Counted(Arc<AtomicU32>);

impl Counted {
    fn new(counter: Arc<AtomicU32>) -> Self {
        counter.fetch_add(1, Ordering::Relaxed);
        Self(counter)
    }
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Refuses calls without the shared token (when one is set).
#[derive(Clone)]
pub struct TokenCheck(Option<Arc<str>>);

impl tonic::service::Interceptor for TokenCheck {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        let Some(token) = &self.0 else {
            return Ok(req);
        };
        let Some(header) = req.metadata().get("authorization") else {
            return Err(Status::unauthenticated(
                "this server needs `authorization: Bearer <token>`",
            ));
        };
        // The scheme is case-insensitive (RFC 7235); the token is compared as bytes, so one
        // that is not ASCII is a wrong token, not a missing one.
        let bytes = header.as_bytes();
        let token_bytes = (bytes.len() > 7 && bytes[..7].eq_ignore_ascii_case(b"bearer "))
            .then(|| bytes[7..].trim_ascii());
        match token_bytes {
            Some(t) if constant_time_eq(t, token.as_bytes()) => Ok(req),
            Some(_) => Err(Status::unauthenticated("wrong token")),
            None => Err(Status::unauthenticated(
                "the authorization header is not `Bearer <token>`",
            )),
        }
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

type EventStream = Pin<Box<dyn Stream<Item = Result<CompleteEvent, Status>> + Send>>;

#[tonic::async_trait]
impl Deocc for DeoccService {
    type CompleteStream = EventStream;

    async fn complete(
        &self,
        req: Request<CompleteRequest>,
    ) -> Result<Response<Self::CompleteStream>, Status> {
        let admitted = self.admit()?;
        let deadline = deadline(&req, self.config.max_deadline);
        let req = req.into_inner();
        let limits = self.config.limits;
        let segment = req.segment;
        let (scene, opts) = tokio::task::spawn_blocking(move || scene_from_request(&req, &limits))
            .await
            .map_err(|e| Status::internal(e.to_string()))?
            .map_err(|e| status_of(&e))?;
        let (tx, rx) = mpsc::channel(32);
        let _ = tx.try_send(Ok(progress("queued", 0.0)));
        let worker = self.worker(deadline);
        let chain = self.chain.clone();
        let running = self.running.clone();
        tokio::spawn(async move {
            let _admitted = admitted;
            // A client that hangs up while queued gives its place back at once.
            let permit = tokio::select! {
                p = worker => p,
                _ = tx.closed() => return,
            };
            let permit = match permit {
                Ok(p) => p,
                Err(s) => {
                    let _ = tx.send(Err(s)).await;
                    return;
                }
            };
            let counted = Counted::new(running);
            let out_tx = tx.clone();
            let result = tokio::task::spawn_blocking(move || {
                let _held = (permit, counted);
                let observer = StreamObserver { tx, deadline };
                crate::local::complete(scene, &opts, segment, &chain, &observer)
            })
            .await;
            let event = match result {
                Ok(Ok(r)) => Ok(CompleteEvent {
                    event: Some(complete_event::Event::Result(r)),
                }),
                Ok(Err(PipelineError::Cancelled { stage })) if Instant::now() > deadline => Err(
                    Status::deadline_exceeded(format!("the deadline passed before stage {stage}")),
                ),
                Ok(Err(e)) => Err(pipeline_status(e)),
                Err(e) => Err(Status::internal(format!("the pipeline panicked: {e}"))),
            };
            let _ = out_tx.send(event).await;
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn grasp(&self, req: Request<GraspRequest>) -> Result<Response<GraspResponse>, Status> {
        self.unary(req, |r| grasp(&r)).await
    }

    async fn place(&self, req: Request<PlaceRequest>) -> Result<Response<PlaceResponse>, Status> {
        self.unary(req, |r| place(&r)).await
    }

    async fn health(&self, _: Request<HealthRequest>) -> Result<Response<HealthResponse>, Status> {
        Ok(Response::new(HealthResponse {
            serving: true,
            version: env!("CARGO_PKG_VERSION").into(),
            model: self.model.clone(),
            queued: self.queued.load(Ordering::Relaxed),
            running: self.running.load(Ordering::Relaxed),
            queue_capacity: self.config.queue as u32,
        }))
    }
}

fn grasp(req: &GraspRequest) -> Result<GraspResponse, Status> {
    let msg = req
        .cloud
        .as_ref()
        .ok_or_else(|| Status::invalid_argument("cloud: missing"))?;
    let cloud = cloud2::decode(msg, "cloud").map_err(|e| status_of(&e))?;
    let options: GraspOptions = if req.options_json.trim().is_empty() {
        GraspOptions::default()
    } else {
        deocc_io::cameras::options_from_json(&req.options_json)
            .map_err(|e| Status::invalid_argument(format!("options_json: {e}")))?
    };
    options
        .validate()
        .map_err(|e| Status::invalid_argument(format!("options_json: {e}")))?;
    let ids = cloud
        .instance
        .as_ref()
        .ok_or_else(|| Status::invalid_argument("cloud.fields: no instance field"))?;
    let target_id = match &req.target_pick {
        Some(p) => {
            let (camera, pick) = crate::request::target_pick(p).map_err(|e| status_of(&e))?;
            deocc_robot::target::instance_at(&cloud, &camera, pick)
                .map_err(|e| Status::invalid_argument(format!("target_pick: {e}")))?
        }
        None => req.target,
    };
    let target: Vec<_> = cloud
        .positions
        .iter()
        .zip(ids)
        .filter(|(_, &i)| i == target_id)
        .map(|(p, _)| *p)
        .collect();
    if target.is_empty() {
        return Err(Status::invalid_argument(format!(
            "target: no point of the cloud has instance {target_id}"
        )));
    }
    let planner = AntipodalPlanner { options };
    let grasps = planner
        .plan(&cloud.positions, &target)
        .map_err(|e| Status::invalid_argument(format!("target {target_id}: {e}")))?;
    Ok(GraspResponse {
        grasps: grasps
            .iter()
            .map(|g| GraspPose {
                position: g.position.to_vec(),
                rotation: g.rotation.iter().flatten().copied().collect(),
                width: g.width,
                score: g.score,
            })
            .collect(),
        target_points: target.len() as u64,
        planner: planner.name().into(),
        target: target_id,
    })
}

fn vec3(v: &[f32], field: &str, default: [f32; 3]) -> Result<[f32; 3], Status> {
    match v.len() {
        0 => Ok(default),
        3 if v.iter().all(|x| x.is_finite()) => Ok([v[0], v[1], v[2]]),
        _ => Err(Status::invalid_argument(format!(
            "{field}: expected three finite numbers, got {v:?}"
        ))),
    }
}

fn place(req: &PlaceRequest) -> Result<PlaceResponse, Status> {
    let msg = req
        .cloud
        .as_ref()
        .ok_or_else(|| Status::invalid_argument("cloud: missing"))?;
    let cloud = cloud2::decode(msg, "cloud").map_err(|e| status_of(&e))?;
    let options = PlaceOptions {
        footprint: [req.footprint_w, req.footprint_d],
        height: req.height,
        up: vec3(&req.up, "up", [0.0, 0.0, 1.0])?,
        ..PlaceOptions::default()
    };
    options.validate().map_err(|e| {
        Status::invalid_argument(format!("footprint_w / footprint_d / height / up: {e}"))
    })?;
    let robot = vec3(&req.robot, "robot", [0.0; 3])?;
    let placer = GridPlacer {
        options,
        unseen: UnseenSpace::AsPoints,
        eye: None,
    };
    let (maps, best) = placer
        .plan_with_errors(
            &cloud.positions,
            cloud.expected_error.as_deref(),
            &robot.into(),
        )
        .map_err(|e| Status::invalid_argument(format!("cloud: {e}")))?;
    let maps_out = maps
        .iter()
        .map(|m| crate::proto::PlaceMap {
            plane_height: m.plane.height,
            bounds: m.plane.bounds.to_vec(),
            cell_m: m.cell_m,
            nx: m.nx as u32,
            ny: m.ny as u32,
            placeable: m.placeable.iter().map(|&p| u8::from(p)).collect(),
        })
        .collect();
    Ok(match best {
        Some(b) => PlaceResponse {
            found: true,
            position: b.position.to_vec(),
            clearance_m: b.clearance_m,
            score: b.score,
            plane: b.plane as u32,
            maps: maps_out,
        },
        None => PlaceResponse {
            found: false,
            maps: maps_out,
            ..Default::default()
        },
    })
}

/// How long in-flight calls may take to finish after a shutdown signal before the server stops
/// anyway (clients holding idle connections open would otherwise keep it up).
pub const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(30);

/// Serves on `listener` until `shutdown` resolves, then stops taking calls and lets the
/// in-flight ones finish (for at most [`SHUTDOWN_GRACE`]).
pub async fn serve(
    service: DeoccService,
    listener: tokio::net::TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<(), tonic::transport::Error> {
    let incoming = tokio_stream::wrappers::TcpListenerStream::new(listener);
    let (tx, rx) = tokio::sync::watch::channel(false);
    let mut rx2 = rx.clone();
    let guard = service.upload_guard();
    let server = tonic::transport::Server::builder()
        .layer(guard)
        .serve_with_incoming_shutdown(service.into_server(), incoming, async move {
            let mut rx = rx;
            let _ = rx.wait_for(|&stop| stop).await;
        });
    let signal = async move {
        shutdown.await;
        let _ = tx.send(true);
        std::future::pending::<()>().await
    };
    let grace = async move {
        let _ = rx2.wait_for(|&stop| stop).await;
        tokio::time::sleep(SHUTDOWN_GRACE).await;
    };
    tokio::select! {
        r = server => r,
        _ = signal => Ok(()),
        _ = grace => {
            tracing::warn!("in-flight calls did not finish within {SHUTDOWN_GRACE:?}; stopping");
            Ok(())
        }
    }
}

/// SIGINT or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}

/// The address to listen on, parsed with the option named.
pub fn parse_listen(s: &str) -> Result<SocketAddr, String> {
    s.parse()
        .map_err(|e| format!("--listen {s:?}: {e} (expected HOST:PORT, e.g. 127.0.0.1:50051)"))
}
