//! The bridge node (feature `ros2`, on `ros2-client`: pure Rust DDS, no ROS installation):
//! subscribes to one camera's colour, depth and CameraInfo topics (and a camera pose topic),
//! keeps the newest synchronised views, and on each call of its `~/complete` service
//! (std_srvs/Trigger) completes them, in this process or through `deocc serve`, and publishes
//! the completed cloud on `~/completed_points` (sensor_msgs/PointCloud2, transient local so a
//! late RViz still gets the last one).
//!
//! Input QoS follows REP-2003: best-effort subscriptions (they match reliable and best-effort
//! publishers alike); `reliable_input` asks for reliable delivery instead.

use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, Instant};

use deocc_completion::CompleterChain;
use deocc_pipeline::Unobserved;
use deocc_service::client::Client as ServiceClient;
use deocc_service::proto::{CompleteRequest, CompleteResult};
use deocc_service::request::{scene_from_request, Limits};
use futures::StreamExt;
use ros2_client::{
    qos::{Durability, History, WhenFull},
    Context, MessageTypeName, Name, Node, NodeName, NodeOptions, QosProfile, ServiceMapping,
    ServiceTypeName,
};
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::convert;
use crate::msgs::{
    CameraInfo, Header, Image, PointCloud2, PoseStamped, TriggerRequest, TriggerResponse,
};
use crate::sync::{SyncConfig, Synchronizer};

pub use ros2_client;

/// Where completions run.
#[derive(Clone)]
pub enum Backend {
    /// In this process, with this chain (the model loaded once).
    InProcess {
        chain: Arc<CompleterChain>,
        limits: Limits,
    },
    /// Through a `deocc serve` server.
    Service {
        client: ServiceClient,
        timeout: Option<Duration>,
    },
}

impl Backend {
    /// Completes `req`; an error is a sentence for the trigger's answer.
    pub async fn complete(&self, req: CompleteRequest) -> Result<CompleteResult, String> {
        match self {
            Backend::InProcess { chain, limits } => {
                let (chain, limits) = (chain.clone(), *limits);
                tokio::task::spawn_blocking(move || {
                    let (scene, opts) =
                        scene_from_request(&req, &limits).map_err(|e| e.to_string())?;
                    deocc_service::local::complete(scene, &opts, req.segment, &chain, &Unobserved)
                        .map_err(|e| e.to_string())
                })
                .await
                .map_err(|e| format!("the pipeline panicked: {e}"))?
            }
            Backend::Service { client, timeout } => client
                .clone()
                .complete(req, *timeout)
                .await
                .map(|c| c.result)
                .map_err(|s| format!("deocc serve answered {:?}: {}", s.code(), s.message())),
        }
    }
}

/// The node's names, topics and behaviour.
#[derive(Debug, Clone)]
pub struct BridgeConfig {
    /// ROS_DOMAIN_ID.
    pub domain_id: u16,
    /// Node namespace, e.g. `/` or `/robot1`.
    pub namespace: String,
    pub node_name: String,
    /// Colour image topic (rgb8 or bgr8).
    pub rgb_topic: String,
    /// Depth image topic (16UC1 mm or 32FC1 m), registered to the colour camera.
    pub depth_topic: String,
    /// CameraInfo of the (rectified) colour camera.
    pub info_topic: String,
    /// geometry_msgs/PoseStamped of the camera's optical frame in the world frame. Without it
    /// the views are registered by ICP and the cloud is in the first view's camera frame.
    pub pose_topic: Option<String>,
    pub sync: SyncConfig,
    /// Pipeline options as JSON (the fields of `deocc run --options`); empty = defaults.
    pub options_json: String,
    /// Reliable input subscriptions instead of best effort.
    pub reliable_input: bool,
}

impl Default for BridgeConfig {
    fn default() -> Self {
        Self {
            domain_id: 0,
            namespace: "/".into(),
            node_name: "deocc".into(),
            rgb_topic: "/camera/color/image_raw".into(),
            depth_topic: "/camera/aligned_depth_to_color/image_raw".into(),
            info_topic: "/camera/color/camera_info".into(),
            pose_topic: None,
            sync: SyncConfig::default(),
            options_json: String::new(),
            reliable_input: false,
        }
    }
}

/// A failure to set the node up (names, DDS), as a sentence.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BridgeError(pub String);

fn err(what: &str, e: impl std::fmt::Debug) -> BridgeError {
    BridgeError(format!("{what}: {e:?}"))
}

/// The node's fully qualified name, `/ns/name`.
pub fn node_path(namespace: &str, name: &str) -> String {
    let ns = namespace.trim_end_matches('/');
    format!("{ns}/{name}")
}

/// QoS of the completed cloud: reliable, the last one kept for late subscribers.
pub fn cloud_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::Wait(Duration::from_secs(5)))
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// QoS of the trigger service's request and reply topics (the rclcpp service default).
pub fn service_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 })
}

fn input_qos(reliable: bool) -> QosProfile {
    let q = QosProfile::subscription_default().history(History::KeepLast { depth: 5 });
    if reliable {
        q.reliability_reliable(WhenFull::DEFAULT)
    } else {
        q
    }
}

/// The UDP receive buffer a participant asks for. A completed cloud is tens of MB in one
/// sample; whatever the buffer cannot hold while the reader catches up is dropped and repaired
/// slowly (RustDDS re-sends at most 256 fragments a round). The kernel caps the request at
/// `net.core.rmem_max` (often 4 MB: raise it, `sysctl -w net.core.rmem_max=67108864`).
pub const RECEIVE_BUFFER_BYTES: usize = 64 << 20;

/// A ROS 2 context on `domain_id`.
pub fn context(domain_id: u16) -> Result<Context, BridgeError> {
    let participant = ros2_client::dds::rustdds::DomainParticipantBuilder::new(domain_id)
        .socket_receive_buffer_size(RECEIVE_BUFFER_BYTES)
        .build()
        .map_err(|e| err("creating the DDS participant", e))?;
    Context::from_domain_participant(participant).map_err(|e| err("creating the ROS 2 context", e))
}

/// A node named `name` in `namespace`.
pub fn node(ctx: &Context, namespace: &str, name: &str) -> Result<Node, BridgeError> {
    let n = NodeName::new(namespace, name).map_err(|e| err("node name", e))?;
    ctx.new_node(n, NodeOptions::new().enable_rosout(false))
        .map_err(|e| err("creating the node", e))
}

fn topic_name(topic: &str, what: &str) -> Result<Name, BridgeError> {
    Name::parse(topic).map_err(|e| err(&format!("{what} topic {topic:?}"), e))
}

/// A ROS message type: package and name.
pub type MsgType = (&'static str, &'static str);
pub const IMAGE: MsgType = ("sensor_msgs", "Image");
pub const CAMERA_INFO: MsgType = ("sensor_msgs", "CameraInfo");
pub const POINT_CLOUD2: MsgType = ("sensor_msgs", "PointCloud2");
pub const POSE_STAMPED: MsgType = ("geometry_msgs", "PoseStamped");

/// A subscription to `topic` of type `pkg/ty`.
pub fn subscribe<M: 'static + DeserializeOwned>(
    node: &mut Node,
    topic: &str,
    (pkg, ty): MsgType,
    qos: QosProfile,
) -> Result<ros2_client::Subscription<M>, BridgeError> {
    let t = node
        .create_topic(&topic_name(topic, ty)?, MessageTypeName::new(pkg, ty), &qos)
        .map_err(|e| err(&format!("topic {topic}"), e))?;
    node.create_subscription(&t, Some(qos))
        .map_err(|e| err(&format!("subscribing to {topic}"), e))
}

/// A publisher on `topic` of type `pkg/ty`.
pub fn advertise<M: Serialize>(
    node: &mut Node,
    topic: &str,
    (pkg, ty): MsgType,
    qos: QosProfile,
) -> Result<ros2_client::Publisher<M>, BridgeError> {
    let t = node
        .create_topic(&topic_name(topic, ty)?, MessageTypeName::new(pkg, ty), &qos)
        .map_err(|e| err(&format!("topic {topic}"), e))?;
    node.create_publisher(&t, Some(qos))
        .map_err(|e| err(&format!("publishing {topic}"), e))
}

/// The topic of completed clouds and the trigger service of a node at `path`.
pub fn cloud_topic(path: &str) -> String {
    format!("{path}/completed_points")
}

pub fn trigger_service(path: &str) -> String {
    format!("{path}/complete")
}

/// A client of a bridge's trigger service (for tests and for robot code in Rust).
pub fn trigger_client(
    node: &mut Node,
    bridge_path: &str,
) -> Result<ros2_client::Client<TriggerRequest, TriggerResponse>, BridgeError> {
    let name = trigger_service(bridge_path);
    node.create_client(
        ServiceMapping::Enhanced,
        &topic_name(&name, "service")?,
        &ServiceTypeName::new("std_srvs", "Trigger"),
        service_qos(),
        service_qos(),
    )
    .map_err(|e| err(&format!("client of {name}"), e))
}

/// Runs the bridge until `shutdown` resolves. Call from inside a tokio runtime.
pub async fn run(
    cfg: BridgeConfig,
    backend: Backend,
    shutdown: impl Future<Output = ()>,
) -> Result<(), BridgeError> {
    let ctx = context(cfg.domain_id)?;
    let mut node = node(&ctx, &cfg.namespace, &cfg.node_name)?;
    let path = node_path(&cfg.namespace, &cfg.node_name);
    let qos = input_qos(cfg.reliable_input);
    let rgb = subscribe::<Image>(&mut node, &cfg.rgb_topic, IMAGE, qos.clone())?;
    let depth = subscribe::<Image>(&mut node, &cfg.depth_topic, IMAGE, qos.clone())?;
    let info = subscribe::<CameraInfo>(&mut node, &cfg.info_topic, CAMERA_INFO, qos.clone())?;
    let pose = cfg
        .pose_topic
        .as_deref()
        .map(|t| subscribe::<PoseStamped>(&mut node, t, POSE_STAMPED, qos.clone()))
        .transpose()?;
    let cloud_pub =
        advertise::<PointCloud2>(&mut node, &cloud_topic(&path), POINT_CLOUD2, cloud_qos())?;
    let trigger_name = trigger_service(&path);
    let server = node
        .create_server::<TriggerRequest, TriggerResponse>(
            ServiceMapping::Enhanced,
            &topic_name(&trigger_name, "service")?,
            &ServiceTypeName::new("std_srvs", "Trigger"),
            service_qos(),
            service_qos(),
        )
        .map_err(|e| err(&format!("service {trigger_name}"), e))?;
    let spinner = node.spinner().map_err(|e| err("node spinner", e))?;
    let spin = tokio::spawn(spinner.spin());
    tracing::info!(
        node = %path,
        rgb = %cfg.rgb_topic, depth = %cfg.depth_topic, info = %cfg.info_topic,
        pose = ?cfg.pose_topic,
        "deocc bridge up: call {trigger_name} (std_srvs/Trigger); clouds on {}",
        cloud_topic(&path)
    );

    let mut sync = Synchronizer::new(SyncConfig {
        use_pose: cfg.pose_topic.is_some(),
        ..cfg.sync.clone()
    });
    let mut rgb_s = Box::pin(rgb.async_stream());
    let mut depth_s = Box::pin(depth.async_stream());
    let mut info_s = Box::pin(info.async_stream());
    let mut pose_s = pose.as_ref().map(|p| Box::pin(p.async_stream()));
    let mut requests = Box::pin(server.receive_request_stream());
    let mut shutdown = std::pin::pin!(shutdown);
    type Running = (
        ros2_client::service::RmwRequestId,
        Header,
        usize,
        Instant,
        tokio::task::JoinHandle<Result<CompleteResult, String>>,
    );
    let mut running: Option<Running> = None;

    loop {
        tokio::select! {
            () = &mut shutdown => break,
            Some(m) = rgb_s.next() => match m {
                Ok((m, _)) => sync.push_rgb(m),
                Err(e) => tracing::warn!("{}: {e:?}", cfg.rgb_topic),
            },
            Some(m) = depth_s.next() => match m {
                Ok((m, _)) => sync.push_depth(m),
                Err(e) => tracing::warn!("{}: {e:?}", cfg.depth_topic),
            },
            Some(m) = info_s.next() => match m {
                Ok((m, _)) => sync.push_info(m),
                Err(e) => tracing::warn!("{}: {e:?}", cfg.info_topic),
            },
            Some(m) = async { pose_s.as_mut()?.next().await }, if pose_s.is_some() => match m {
                Ok((m, _)) => sync.push_pose(m),
                Err(e) => tracing::warn!("pose: {e:?}"),
            },
            Some(r) = requests.next() => {
                let (id, _) = match r {
                    Ok(r) => r,
                    Err(e) => {
                        tracing::warn!("{trigger_name}: {e:?}");
                        continue;
                    }
                };
                let refuse = |message: String| TriggerResponse { success: false, message };
                let answer = if running.is_some() {
                    Some(refuse("busy: a completion is running; call again when it is published".into()))
                } else if sync.views().is_empty() {
                    let w = sync.waiting_for();
                    Some(refuse(if w.is_empty() {
                        format!("no synchronised view yet: colour and depth stamps must lie within {} ms{}",
                            cfg.sync.slop_ns / 1_000_000,
                            if sync.config().use_pose { " of each other and of a pose" } else { "" })
                    } else {
                        format!("no view yet: waiting for {}", w.join(", "))
                    }))
                } else {
                    let views: Vec<_> = sync.views().iter().cloned().collect();
                    match convert::request(&views, &cfg.options_json) {
                        Err(e) => Some(refuse(e)),
                        Ok(req) => {
                            // Posed views are in the poses' world frame; unposed ones in the
                            // first camera's.
                            let frame_id = match &views[0].pose {
                                Some(p) => p.header.frame_id.clone(),
                                None => views[0].depth.header.frame_id.clone(),
                            };
                            let header = Header { stamp: views[views.len() - 1].depth.header.stamp, frame_id };
                            let b = backend.clone();
                            let handle = tokio::spawn(async move { b.complete(req).await });
                            running = Some((id, header, views.len(), Instant::now(), handle));
                            None
                        }
                    }
                };
                if let Some(a) = answer {
                    if let Err(e) = server.async_send_response(id, a).await {
                        tracing::warn!("{trigger_name}: answer not sent: {e:?}");
                    }
                }
            },
            done = async { (&mut running.as_mut().expect("guarded").4).await }, if running.is_some() => {
                let (id, header, n, t0, _) = running.take().expect("guarded");
                let answer = match done.map_err(|e| e.to_string()).and_then(|r| r) {
                    Ok(result) => match result.cloud {
                        Some(c) => {
                            let msg = convert::cloud_msg(c, header);
                            let points = msg.width as u64 * msg.height as u64;
                            match cloud_pub.async_publish(msg).await {
                                Ok(()) => TriggerResponse {
                                    success: true,
                                    message: format!(
                                        "{points} points ({} generated) from {n} views in {:.2} s",
                                        result.points_generated,
                                        t0.elapsed().as_secs_f64()
                                    ),
                                },
                                Err(e) => TriggerResponse { success: false, message: format!("publishing the cloud: {e:?}") },
                            }
                        }
                        None => TriggerResponse { success: false, message: "the result had no cloud".into() },
                    },
                    Err(e) => TriggerResponse { success: false, message: e },
                };
                tracing::info!(success = answer.success, "{}", answer.message);
                if let Err(e) = server.async_send_response(id, answer).await {
                    tracing::warn!("{trigger_name}: answer not sent: {e:?}");
                }
            },
        }
    }
    drop(requests);
    drop((rgb_s, depth_s, info_s, pose_s));
    drop(node); // stops its spinner (calling stop_spinner too would log an error at drop)
    let _ = tokio::time::timeout(Duration::from_secs(2), spin).await;
    Ok(())
}

/// What `play` publishes and whom it asks.
#[derive(Debug, Clone)]
pub struct PlayConfig {
    pub domain_id: u16,
    pub rgb_topic: String,
    pub depth_topic: String,
    pub info_topic: String,
    /// Poses are published here when the views have them.
    pub pose_topic: Option<String>,
    /// Time between views.
    pub period: Duration,
    /// Path of a bridge node (`/deocc`) to trigger after the last view, and read the cloud of.
    pub trigger: Option<String>,
    /// Longest wait for subscribers, the service, and the answer.
    pub timeout: Duration,
}

/// What a triggered bridge answered, and the cloud it published.
#[derive(Debug, Clone)]
pub struct Played {
    pub answer: TriggerResponse,
    pub cloud: Option<PointCloud2>,
}

async fn within<T>(t: Duration, what: &str, f: impl Future<Output = T>) -> Result<T, BridgeError> {
    tokio::time::timeout(t, f)
        .await
        .map_err(|_| BridgeError(format!("{what}: nothing after {:.0} s", t.as_secs_f64())))
}

/// Publishes `views` as a camera would (colour, depth, CameraInfo, pose), `period` apart; then,
/// if `trigger` names a bridge, calls its `~/complete` and returns its answer and cloud. This is
/// the robot side of the loopback test, and a way to try the bridge on a recorded scene.
pub async fn play(
    cfg: PlayConfig,
    views: Vec<crate::convert::View>,
) -> Result<Option<Played>, BridgeError> {
    let ctx = context(cfg.domain_id)?;
    let mut node = node(&ctx, "/", &format!("deocc_play_{}", std::process::id()))?;
    let qos = QosProfile::publisher_default()
        .reliability_reliable(WhenFull::Wait(Duration::from_secs(5)))
        .history(History::KeepLast { depth: 5 });
    let rgb = advertise::<Image>(&mut node, &cfg.rgb_topic, IMAGE, qos.clone())?;
    let depth = advertise::<Image>(&mut node, &cfg.depth_topic, IMAGE, qos.clone())?;
    let info = advertise::<CameraInfo>(&mut node, &cfg.info_topic, CAMERA_INFO, qos.clone())?;
    let pose = cfg
        .pose_topic
        .as_deref()
        .map(|t| advertise::<PoseStamped>(&mut node, t, POSE_STAMPED, qos.clone()))
        .transpose()?;
    let bridge = match &cfg.trigger {
        Some(path) => {
            let cloud =
                subscribe::<PointCloud2>(&mut node, &cloud_topic(path), POINT_CLOUD2, cloud_qos())?;
            Some((path.clone(), cloud, trigger_client(&mut node, path)?))
        }
        None => None,
    };
    let spinner = node.spinner().map_err(|e| err("node spinner", e))?;
    let spin = tokio::spawn(spinner.spin());
    let t = cfg.timeout;
    within(
        t,
        "waiting for a subscriber of the depth topic",
        depth.wait_for_subscription(&node),
    )
    .await?;
    within(
        t,
        "waiting for a subscriber of the colour topic",
        rgb.wait_for_subscription(&node),
    )
    .await?;
    within(
        t,
        "waiting for a subscriber of the camera info",
        info.wait_for_subscription(&node),
    )
    .await?;
    if let Some(p) = &pose {
        within(
            t,
            "waiting for a subscriber of the pose topic",
            p.wait_for_subscription(&node),
        )
        .await?;
    }
    let mut last_stamp = None;
    for v in views {
        last_stamp = Some(v.depth.header.stamp);
        if let (Some(p), Some(m)) = (&pose, v.pose) {
            p.async_publish(m)
                .await
                .map_err(|e| err("publishing a pose", e))?;
        }
        info.async_publish(v.info)
            .await
            .map_err(|e| err("publishing camera info", e))?;
        rgb.async_publish(v.rgb)
            .await
            .map_err(|e| err("publishing a colour image", e))?;
        depth
            .async_publish(v.depth)
            .await
            .map_err(|e| err("publishing a depth image", e))?;
        tokio::time::sleep(cfg.period).await;
    }
    let out = match bridge {
        None => None,
        Some((path, cloud, client)) => {
            within(
                t,
                &format!("waiting for the service {}", trigger_service(&path)),
                client.wait_for_service(&node),
            )
            .await?;
            let answer = within(
                t,
                "waiting for the bridge's answer",
                client.async_call_service(TriggerRequest::default()),
            )
            .await?
            .map_err(|e| err("calling the trigger", e))?;
            let cloud = if answer.success {
                // The cloud of this completion carries the last view's stamp.
                let mut s = Box::pin(cloud.async_stream());
                let got = within(t, "waiting for the completed cloud", async {
                    while let Some(m) = s.next().await {
                        if let Ok((m, _)) = m {
                            if Some(m.header.stamp) == last_stamp {
                                return Some(m);
                            }
                        }
                    }
                    None
                })
                .await?;
                got
            } else {
                None
            };
            Some(Played { answer, cloud })
        }
    };
    drop(node); // stops its spinner (calling stop_spinner too would log an error at drop)
    let _ = tokio::time::timeout(Duration::from_secs(2), spin).await;
    Ok(out)
}
