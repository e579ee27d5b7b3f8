//! `deocc-ros2`: the ROS 2 bridge node, and a player of recorded scenes to try it with.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use deocc_ros2::node::{self, Backend, BridgeConfig, PlayConfig};
use deocc_ros2::sync::SyncConfig;

#[derive(Parser)]
#[command(
    name = "deocc-ros2",
    version,
    about = "deocc on ROS 2: completes occluded objects from RGB-D topics and publishes the completed cloud"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the bridge node: subscribe to a camera, complete on each `~/complete` call
    /// (std_srvs/Trigger), publish `~/completed_points` (sensor_msgs/PointCloud2).
    Bridge(BridgeArgs),
    /// Publish a scene folder's frames as a camera would (and optionally trigger a bridge and
    /// save its cloud), to try the bridge without a robot.
    Play(PlayArgs),
}

/// The highest DDS domain id whose RTPS ports stay below 65536.
const MAX_DOMAIN_ID: u16 = 232;

/// Longest --period / --timeout, seconds (a day).
const MAX_SECONDS: f64 = 86_400.0;

#[derive(Args)]
struct Topics {
    /// ROS domain (default: $ROS_DOMAIN_ID, else 0).
    #[arg(long)]
    domain_id: Option<u16>,
    /// Colour image topic (rgb8 / bgr8).
    #[arg(long, default_value = "/camera/color/image_raw")]
    rgb: String,
    /// Depth image topic registered to the colour camera (16UC1 mm / 32FC1 m).
    #[arg(long, default_value = "/camera/aligned_depth_to_color/image_raw")]
    depth: String,
    /// CameraInfo of the rectified colour camera.
    #[arg(long, default_value = "/camera/color/camera_info")]
    info: String,
    /// geometry_msgs/PoseStamped of the camera's optical frame in the world. Without it, views
    /// are registered by ICP and the cloud is in the first view's camera frame.
    #[arg(long)]
    pose: Option<String>,
}

impl Topics {
    fn domain(&self) -> Result<u16> {
        let (d, from) = match self.domain_id {
            Some(d) => (d, "--domain-id"),
            None => match std::env::var("ROS_DOMAIN_ID") {
                Ok(v) if !v.trim().is_empty() => (
                    v.trim()
                        .parse()
                        .with_context(|| format!("ROS_DOMAIN_ID={v:?} is not a domain number"))?,
                    "ROS_DOMAIN_ID",
                ),
                _ => (0, "the default"),
            },
        };
        // DDS maps a domain to UDP ports 7400 + 250 x domain + ...: past 232 they wrap past
        // 65535 and bind another domain's ports.
        anyhow::ensure!(
            d <= MAX_DOMAIN_ID,
            "{from} {d} is outside 0..={MAX_DOMAIN_ID} (the DDS domains whose ports fit)"
        );
        Ok(d)
    }
}

#[derive(Args)]
struct BridgeArgs {
    #[command(flatten)]
    topics: Topics,
    /// Node namespace.
    #[arg(long, default_value = "/")]
    namespace: String,
    /// Node name.
    #[arg(long, default_value = "deocc")]
    name: String,
    /// Views kept (the newest) and completed together.
    #[arg(long, default_value_t = 10)]
    max_views: usize,
    /// Largest stamp difference between the colour, depth (and pose) of one view, ms.
    #[arg(long, default_value_t = 20.0)]
    slop_ms: f64,
    /// Do not keep a view closer than this to the newest kept one, ms (0 keeps all).
    #[arg(long, default_value_t = 0.0)]
    min_interval_ms: f64,
    /// Subscribe reliably (default best effort, which matches every publisher).
    #[arg(long)]
    reliable_input: bool,
    /// Pipeline options as JSON (the fields of `deocc run --options`).
    #[arg(long)]
    options: Option<PathBuf>,
    /// Complete through this `deocc serve` server (http://host:port) instead of in process.
    #[arg(long)]
    service: Option<String>,
    /// A file holding the server's shared token (as `deocc serve --token-file`).
    #[arg(long, requires = "service")]
    token_file: Option<PathBuf>,
    /// Completers, in order (in process): gldot, rules (default: the shipped chain).
    #[arg(long, default_value = "gldot,rules", value_delimiter = ',')]
    completer: Vec<String>,
    /// GL-DoT weights folder (in process; default the built-in model).
    #[arg(long)]
    weights: Option<PathBuf>,
}

#[derive(Args)]
struct PlayArgs {
    /// A scene folder (as `deocc run` reads).
    scene: PathBuf,
    #[command(flatten)]
    topics: Topics,
    /// Seconds between views.
    #[arg(long, default_value_t = 0.2)]
    period: f64,
    /// After the last view, call this bridge's `~/complete` (its node path, e.g. /deocc).
    #[arg(long)]
    trigger: Option<String>,
    /// Write the bridge's cloud here (PLY; needs --trigger).
    #[arg(long, requires = "trigger")]
    out: Option<PathBuf>,
    /// Longest wait for subscribers, the service and the answer, seconds.
    #[arg(long, default_value_t = 120.0)]
    timeout: f64,
    /// Instead of publishing, write what would be published as a ROS 2 bag (MCAP, CDR, as
    /// `ros2 bag record -s mcap` writes it); `deocc run FILE --rgb TOPIC --depth-topic TOPIC
    /// --info TOPIC [--poses POSE_TOPIC]` reads it back.
    #[arg(long, value_name = "FILE.mcap", conflicts_with = "trigger")]
    record: Option<PathBuf>,
}

fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,rustdds=off,ros2_client=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let rt = tokio::runtime::Runtime::new()?;
    match cli.cmd {
        Cmd::Bridge(a) => rt.block_on(bridge(a)),
        Cmd::Play(a) => rt.block_on(play(a)),
    }
}

async fn bridge(a: BridgeArgs) -> Result<()> {
    for (v, name) in [
        (a.slop_ms, "--slop-ms"),
        (a.min_interval_ms, "--min-interval-ms"),
    ] {
        anyhow::ensure!(
            v.is_finite() && v >= 0.0,
            "{name} must be a number >= 0, got {v}"
        );
    }
    anyhow::ensure!(a.max_views >= 1, "--max-views must be at least 1");
    let domain_id = a.topics.domain()?;
    let options_json = match &a.options {
        Some(p) => {
            let o = deocc_pipeline::PipelineOptions::from_json_file(p)?;
            serde_json::to_string(&o)?
        }
        None => String::new(),
    };
    let backend = match &a.service {
        Some(url) => {
            let token = match &a.token_file {
                Some(p) => {
                    let t = std::fs::read_to_string(p)
                        .with_context(|| format!("--token-file {}", p.display()))?
                        .trim()
                        .to_string();
                    if t.is_empty() {
                        anyhow::bail!("--token-file {}: the token is empty", p.display());
                    }
                    Some(t)
                }
                None => None,
            };
            let mut client = deocc_service::client::Client::connect(url, token)
                .await
                .with_context(|| format!("--service {url}: cannot connect"))?;
            let h = client
                .health()
                .await
                .with_context(|| format!("--service {url}: no health answer"))?;
            tracing::info!("completing through {url} ({})", h.model);
            Backend::Service {
                client,
                timeout: None,
            }
        }
        None => {
            let chain = deocc_model::chain::build(&a.completer, a.weights.as_deref())
                .map_err(|e| anyhow::anyhow!("--completer: {e}"))?;
            tracing::info!(
                "completing in process: {}",
                deocc_model::chain::describe(&a.completer, a.weights.as_deref())
            );
            Backend::InProcess {
                chain: Arc::new(chain),
                limits: Default::default(),
            }
        }
    };
    let cfg = BridgeConfig {
        domain_id,
        namespace: a.namespace,
        node_name: a.name,
        rgb_topic: a.topics.rgb,
        depth_topic: a.topics.depth,
        info_topic: a.topics.info,
        pose_topic: a.topics.pose,
        sync: SyncConfig {
            slop_ns: (a.slop_ms * 1e6) as i64,
            max_views: a.max_views,
            min_interval_ns: (a.min_interval_ms * 1e6) as i64,
            ..Default::default()
        },
        options_json,
        reliable_input: a.reliable_input,
    };
    node::run(cfg, backend, async {
        let _ = tokio::signal::ctrl_c().await;
        tracing::info!("shutting down");
    })
    .await?;
    Ok(())
}

async fn play(a: PlayArgs) -> Result<()> {
    anyhow::ensure!(
        a.period.is_finite() && (0.0..=MAX_SECONDS).contains(&a.period),
        "--period {} must be in [0, {MAX_SECONDS}] seconds",
        a.period
    );
    anyhow::ensure!(
        a.timeout.is_finite() && a.timeout > 0.0 && a.timeout <= MAX_SECONDS,
        "--timeout {} must be in (0, {MAX_SECONDS}] seconds",
        a.timeout
    );
    let domain_id = a.topics.domain()?;
    let scene = deocc_io::scene::read_scene(&a.scene)
        .with_context(|| format!("reading the scene {}", a.scene.display()))?;
    let req = deocc_service::request::request_from_scene(&scene, "");
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)?
        .as_nanos() as i64;
    let step = (a.period * 1e9) as i64;
    let views = deocc_ros2::convert::views_from_request(
        &req,
        now,
        step.max(1),
        "camera_color_optical_frame",
        "world",
    );
    let n = views.len();
    if let Some(path) = &a.record {
        let topics = deocc_ros2::bag::BagTopics {
            rgb: a.topics.rgb.clone(),
            depth: a.topics.depth.clone(),
            info: a.topics.info.clone(),
            pose: if scene.posed {
                a.topics.pose.clone()
            } else {
                None
            },
        };
        deocc_ros2::bag::write_bag(path, &views, &topics)
            .map_err(|e| anyhow::anyhow!("writing {}: {e}", path.display()))?;
        eprintln!("recorded {n} views to {}", path.display());
        return Ok(());
    }
    let cfg = PlayConfig {
        domain_id,
        rgb_topic: a.topics.rgb,
        depth_topic: a.topics.depth,
        info_topic: a.topics.info,
        pose_topic: if scene.posed { a.topics.pose } else { None },
        period: Duration::from_secs_f64(a.period),
        trigger: a.trigger,
        timeout: Duration::from_secs_f64(a.timeout),
    };
    let played = node::play(cfg, views).await?;
    eprintln!("published {n} views");
    if let Some(p) = played {
        anyhow::ensure!(
            p.answer.success,
            "the bridge answered: {}",
            p.answer.message
        );
        eprintln!("bridge: {}", p.answer.message);
        if let (Some(out), Some(cloud)) = (a.out, p.cloud) {
            let c =
                deocc_service::cloud2::decode(&deocc_ros2::convert::cloud_proto(&cloud), "cloud")
                    .map_err(|e| anyhow::anyhow!("the published cloud: {e}"))?;
            deocc_io::ply::write_point_cloud(
                &out,
                &c,
                deocc_io::ply::PlyEncoding::BinaryLittleEndian,
            )
            .with_context(|| format!("writing {}", out.display()))?;
            eprintln!("wrote {} ({} points)", out.display(), c.len());
        }
    }
    Ok(())
}
