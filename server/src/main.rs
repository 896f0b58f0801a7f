//! `stillmap-server`: configuration from defaults < TOML file < environment < flags.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use stillmap_perception::config::ExecutionProvider;
use stillmap_server::config::OverloadPolicy;
use stillmap_server::{ServerConfig, run};

#[derive(Parser, Debug)]
#[command(name = "stillmap-server", version, about = "stillmap mapping server: gRPC + Zenoh ingest, HTTP API")]
struct Args {
    /// TOML configuration file (every key documented in deploy/stillmap-server.toml).
    #[arg(long, env = "STILLMAP_CONFIG")]
    config: Option<PathBuf>,
    /// gRPC listen address [default: 127.0.0.1:50051].
    #[arg(long, env = "STILLMAP_GRPC_LISTEN")]
    grpc_listen: Option<String>,
    /// HTTP listen address [default: 127.0.0.1:8080].
    #[arg(long, env = "STILLMAP_HTTP_LISTEN")]
    http_listen: Option<String>,
    /// Where robots reach this server's gRPC port (http://host:port), for servers
    /// on one Zenoh network: robots that belong here are sent to it [default: none].
    #[arg(long, env = "STILLMAP_GRPC_ADVERTISE")]
    grpc_advertise: Option<String>,
    /// Zenoh listen endpoint, repeatable [default: tcp/127.0.0.1:7447].
    #[arg(long, env = "STILLMAP_ZENOH_LISTEN", value_delimiter = ',')]
    zenoh_listen: Vec<String>,
    /// Zenoh endpoint (router or peer) to connect to, repeatable.
    #[arg(long, env = "STILLMAP_ZENOH_CONNECT", value_delimiter = ',')]
    zenoh_connect: Vec<String>,
    /// This server's name on Zenoh (liveliness token and status queryable under
    /// stillmap-cluster/servers/<id>) [default: <hostname>-<gRPC port>].
    #[arg(long, env = "STILLMAP_SERVER_ID")]
    server_id: Option<String>,
    /// Serve gRPC only.
    #[arg(long, env = "STILLMAP_NO_ZENOH")]
    no_zenoh: bool,
    /// Frames queued per session [default: 8].
    #[arg(long, env = "STILLMAP_QUEUE_CAPACITY")]
    queue_capacity: Option<usize>,
    /// Overload policy of the per-session queue [default: drop-oldest].
    #[arg(long, env = "STILLMAP_OVERLOAD_POLICY", value_parser = parse_policy)]
    overload_policy: Option<OverloadPolicy>,
    /// Largest message accepted, in bytes [default: 8388608].
    #[arg(long, env = "STILLMAP_MAX_MESSAGE_BYTES")]
    max_message_bytes: Option<usize>,
    /// Segmentation model (ONNX, YOLOv8-seg export) [default: none: masks from flow alone].
    #[arg(long, env = "STILLMAP_MODEL")]
    model: Option<String>,
    /// Turn perception (segmentation, flow, dynamic mask) off: tracking sees every pixel as static.
    #[arg(long, env = "STILLMAP_NO_PERCEPTION")]
    no_perception: bool,
    /// The embedded store file (sessions, trajectories, keyframes, maps) [default: stillmap-data/stillmap.redb].
    #[arg(long, env = "STILLMAP_STORE")]
    store: Option<String>,
    /// Keep nothing on disk: a restart forgets every session.
    #[arg(long, env = "STILLMAP_NO_STORE")]
    no_store: bool,
    /// Copy every store commit to this PostgreSQL database too, storage shared by
    /// several servers (store.replica_url; `postgresql://user@host:port/db`).
    #[arg(long, env = "STILLMAP_REPLICA_URL", hide_env_values = true)]
    replica_url: Option<String>,
    /// Bearer token a robot's hello must carry, repeatable (adds to auth.tokens).
    #[arg(long = "auth-token", env = "STILLMAP_AUTH_TOKENS", value_delimiter = ',', hide_env_values = true)]
    auth_tokens: Vec<String>,
    /// Bearer token for the HTTP map import and export, repeatable (adds to auth.admin_tokens).
    #[arg(long = "admin-token", env = "STILLMAP_ADMIN_TOKENS", value_delimiter = ',', hide_env_values = true)]
    admin_tokens: Vec<String>,
    /// Bearer token for the query APIs and the dashboard, repeatable (adds to auth.read_tokens).
    #[arg(long = "read-token", env = "STILLMAP_READ_TOKENS", value_delimiter = ',', hide_env_values = true)]
    read_tokens: Vec<String>,
    /// A file of scoped tokens (auth.token_file; SIGHUP reloads it).
    #[arg(long, env = "STILLMAP_TOKEN_FILE")]
    token_file: Option<String>,
    /// Where segmentation runs: cpu, cuda or tensorrt (perception.segmentation.execution_provider).
    #[arg(long, env = "STILLMAP_EXECUTION_PROVIDER", value_parser = parse_provider)]
    execution_provider: Option<ExecutionProvider>,
    /// Print the effective configuration as TOML and exit (auth tokens redacted).
    #[arg(long)]
    print_config: bool,
}

fn parse_policy(s: &str) -> Result<OverloadPolicy, String> {
    match s.replace('-', "_").as_str() {
        "drop_oldest" => Ok(OverloadPolicy::DropOldest),
        "drop_newest" => Ok(OverloadPolicy::DropNewest),
        _ => Err(format!("unknown overload policy {s:?}; use drop-oldest or drop-newest")),
    }
}

fn parse_provider(s: &str) -> Result<ExecutionProvider, String> {
    match s {
        "cpu" => Ok(ExecutionProvider::Cpu),
        "cuda" => Ok(ExecutionProvider::Cuda),
        "tensorrt" => Ok(ExecutionProvider::Tensorrt),
        _ => Err(format!("unknown execution provider {s:?}; use cpu, cuda or tensorrt")),
    }
}

fn effective_config(args: &Args) -> anyhow::Result<ServerConfig> {
    let mut c = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
            ServerConfig::from_toml(&text).with_context(|| format!("in {}", path.display()))?
        }
        None => ServerConfig::default(),
    };
    if let Some(v) = &args.grpc_listen {
        c.grpc.listen = v.clone();
    }
    if let Some(v) = &args.grpc_advertise {
        c.grpc.advertise = v.clone();
    }
    if let Some(v) = &args.http_listen {
        c.http.listen = v.clone();
    }
    if !args.zenoh_listen.is_empty() {
        c.zenoh.listen = args.zenoh_listen.clone();
    }
    if !args.zenoh_connect.is_empty() {
        c.zenoh.connect = args.zenoh_connect.clone();
    }
    if let Some(v) = &args.server_id {
        c.zenoh.server_id = v.clone();
    }
    if args.no_zenoh {
        c.zenoh.enabled = false;
    }
    if let Some(v) = args.queue_capacity {
        c.session.queue_capacity = v;
    }
    if let Some(v) = args.overload_policy {
        c.session.overload_policy = v;
    }
    if let Some(v) = args.max_message_bytes {
        c.grpc.max_message_bytes = v;
    }
    if let Some(v) = &args.model {
        c.perception.segmentation.model_path = v.clone();
    }
    if let Some(v) = args.execution_provider {
        c.perception.segmentation.execution_provider = v;
    }
    if args.no_perception {
        c.perception.enabled = false;
    }
    if let Some(v) = &args.store {
        c.store.path = v.clone();
    }
    if let Some(v) = &args.replica_url {
        c.store.replica_url = v.clone();
    }
    if args.no_store {
        c.store.enabled = false;
    }
    // "a, b" in STILLMAP_AUTH_TOKENS means the tokens "a" and "b".
    c.auth.tokens.extend(args.auth_tokens.iter().map(|t| t.trim().to_string()));
    c.auth.admin_tokens.extend(args.admin_tokens.iter().map(|t| t.trim().to_string()));
    c.auth.read_tokens.extend(args.read_tokens.iter().map(|t| t.trim().to_string()));
    if let Some(f) = &args.token_file {
        c.auth.token_file = f.clone();
    }
    c.validate()?;
    Ok(c)
}

fn main() {
    if let Err(e) = real_main() {
        eprintln!("stillmap-server: {e:#}");
        std::process::exit(1);
    }
}

fn real_main() -> anyhow::Result<()> {
    let args = Args::parse();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_env("STILLMAP_LOG").unwrap_or_else(|_| "info,zenoh=warn".into()))
        .with_writer(std::io::stderr)
        .init();
    let config = effective_config(&args)?;
    if args.print_config {
        let mut shown = config.clone();
        shown
            .auth
            .tokens
            .iter_mut()
            .chain(shown.auth.admin_tokens.iter_mut())
            .chain(shown.auth.read_tokens.iter_mut())
            .for_each(|t| *t = "<redacted>".into());
        print!("{}", toml::to_string_pretty(&shown)?);
        return Ok(());
    }
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .max_blocking_threads(config.http.blocking_threads)
        .thread_keep_alive(stillmap_server::BLOCKING_THREAD_KEEP_ALIVE)
        .build()?
        .block_on(serve(config))
}

async fn serve(config: ServerConfig) -> anyhow::Result<()> {
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    tokio::spawn(async move {
        if let Err(e) = stillmap_server::shutdown_signal().await {
            tracing::error!("signal handler: {e}");
        }
        let _ = stop_tx.send(true);
    });
    run(config, stop_rx, |bound| {
        // One machine-readable line on stdout once every listener is up.
        println!("stillmap-server ready grpc={} http={} zenoh={}", bound.grpc, bound.http, bound.zenoh.join(","));
    })
    .await?;
    Ok(())
}
