//! `deocc serve`: the gRPC service (deocc-service) on one port.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use deocc_service::request::Limits;
use deocc_service::server::{
    parse_listen, serve as serve_on, shutdown_signal, DeoccService, ServerConfig,
};

use crate::completers::CompleterArgs;

#[derive(Args)]
pub struct ServeArgs {
    /// Address to listen on; 127.0.0.1 serves this machine only, 0.0.0.0:PORT exposes it.
    #[arg(long, default_value = "127.0.0.1:50051")]
    listen: String,
    /// Pipeline runs at once (each uses every core).
    #[arg(long, default_value_t = 1)]
    workers: usize,
    /// Requests that may wait for a worker; more are refused with RESOURCE_EXHAUSTED.
    #[arg(long, default_value_t = 8)]
    queue: usize,
    /// Largest request or answer, MiB.
    #[arg(long, default_value_t = 64)]
    max_message_mib: usize,
    /// Most frames in one request.
    #[arg(long, default_value_t = 32)]
    max_frames: usize,
    /// Longest a request may take, seconds (a client's shorter deadline wins).
    #[arg(long, default_value_t = 600.0)]
    max_deadline_s: f64,
    /// File holding a shared token: every call then needs `authorization: Bearer <token>`.
    /// ($DEOCC_TOKEN works too.)
    #[arg(long)]
    token_file: Option<PathBuf>,
    #[command(flatten)]
    completers: CompleterArgs,
}

pub fn serve(a: ServeArgs) -> Result<()> {
    let addr = parse_listen(&a.listen).map_err(anyhow::Error::msg)?;
    if !(1..=64).contains(&a.workers) {
        bail!("--workers {} is outside 1..=64", a.workers);
    }
    if a.queue > 10_000 {
        bail!("--queue {} is over 10000", a.queue);
    }
    if !(1..=2048).contains(&a.max_message_mib) {
        bail!(
            "--max-message-mib {} is outside 1..=2048",
            a.max_message_mib
        );
    }
    if !(1..=1024).contains(&a.max_frames) {
        bail!("--max-frames {} is outside 1..=1024", a.max_frames);
    }
    if !(a.max_deadline_s.is_finite() && a.max_deadline_s > 0.0 && a.max_deadline_s <= 86_400.0) {
        bail!(
            "--max-deadline-s {} must be in (0, 86400]",
            a.max_deadline_s
        );
    }
    let token = match &a.token_file {
        Some(p) => Some(
            std::fs::read_to_string(p)
                .with_context(|| format!("{}: cannot read the token", p.display()))?
                .trim()
                .to_string(),
        ),
        None => std::env::var("DEOCC_TOKEN").ok(),
    };
    if token.as_deref() == Some("") {
        bail!("the token is empty (--token-file / $DEOCC_TOKEN)");
    }
    let chain = crate::completers::chain(&a.completers)?;
    let model = crate::completers::describe_model(&a.completers);
    let config = ServerConfig {
        workers: a.workers,
        queue: a.queue,
        max_message_bytes: a.max_message_mib << 20,
        limits: Limits {
            max_frames: a.max_frames,
            ..Limits::default()
        },
        max_deadline: Duration::from_secs_f64(a.max_deadline_s),
        token,
        // Bodies arriving at once may hold two of the largest messages, or the default.
        uploads: deocc_service::guard::UploadLimits {
            max_upload_bytes: (a.max_message_mib << 21)
                .max(deocc_service::guard::UploadLimits::default().max_upload_bytes),
            ..Default::default()
        },
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let served = rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .with_context(|| format!("--listen {addr}: cannot listen"))?;
        eprintln!(
            "deocc {} serving {model} on {} (workers {}, queue {}); Ctrl-C stops it",
            env!("CARGO_PKG_VERSION"),
            listener.local_addr()?,
            config.workers,
            config.queue
        );
        let service = DeoccService::new(chain, model, config);
        serve_on(service, listener, shutdown_signal()).await?;
        anyhow::Ok(())
    });
    // A pipeline run still going on the blocking pool would keep the runtime's drop waiting
    // (the process lived on after SIGTERM): the grace period has passed, so stop now.
    rt.shutdown_timeout(Duration::from_millis(500));
    served?;
    eprintln!("stopped");
    Ok(())
}
