//! `stillmap-router`: a Zenoh router for a fleet of robots and servers, for a
//! machine without Eclipse's `zenohd` (its container image `eclipse/zenoh` is what
//! deploy/compose.yaml and deploy/k8s run). It is the zenoh crate's router mode,
//! the routing core `zenohd` runs, without `zenohd`'s plugins (REST, storages).
//!
//!   stillmap-router --listen tcp/0.0.0.0:7447
//!   stillmap-router --config deploy/zenoh/router.json5   (TLS, mTLS and the ACL)
//!
//! It prints `stillmap-router ready on <endpoints>` once listening and routes until
//! SIGINT or SIGTERM.

use clap::Parser;
use stillmap_server::config::ZenohConfig;
use stillmap_server::ingest::zenoh::zenoh_config;

#[derive(Parser)]
#[command(version, about = "A Zenoh router for stillmap robots and servers (the zenoh crate's router mode).")]
struct Args {
    /// Endpoints to listen on, repeatable or comma-separated.
    #[arg(long, env = "STILLMAP_ROUTER_LISTEN", value_delimiter = ',', default_value = "tcp/0.0.0.0:7447")]
    listen: Vec<String>,
    /// A Zenoh configuration file (JSON5) used as it is (mode router; TLS, ACL); it
    /// replaces --listen.
    #[arg(long, env = "STILLMAP_ROUTER_CONFIG")]
    config: Option<std::path::PathBuf>,
}

fn main() {
    if let Err(e) = real_main() {
        eprintln!("stillmap-router: {e:#}");
        std::process::exit(1);
    }
}

fn real_main() -> anyhow::Result<()> {
    let args = Args::parse();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_env("STILLMAP_LOG").unwrap_or_else(|_| "info,zenoh=warn".into()))
        .with_writer(std::io::stderr)
        .init();
    let shown = match &args.config {
        Some(path) => format!("the endpoints of {}", path.display()),
        None => args.listen.join(", "),
    };
    // The server's own Zenoh configuration builder, in router mode.
    let zenoh = ZenohConfig {
        mode: "router".into(),
        listen: args.listen.clone(),
        connect: vec![],
        config_file: args.config.clone(),
        ..ZenohConfig::default()
    };
    let config = zenoh_config(&zenoh)?;
    tokio::runtime::Builder::new_multi_thread().enable_all().build()?.block_on(async {
        let session = zenoh::open(config).await.map_err(|e| anyhow::anyhow!("open: {e}"))?;
        println!("stillmap-router ready on {shown}");
        stillmap_server::shutdown_signal().await?;
        session.close().await.map_err(|e| anyhow::anyhow!("close: {e}"))?;
        anyhow::Ok(())
    })
}
