//! The stillmap server as a library: [`run`] serves gRPC, Zenoh and HTTP over one
//! session registry until the shutdown signal fires.
//!
//! The per-frame [`pipeline`] and the [`queue`] are free of network and file
//! I/O; the shells ([`ingest`] for robots, [`api`] for queries) only translate,
//! through [`convert`]. Sessions ([`session`]) run on the worker [`pool`]s.

pub mod api;
pub mod auth;
#[cfg(feature = "zenoh")]
pub mod cluster;
pub mod config;
pub mod convert;
pub mod fleet;
pub mod fleet_map;
pub mod ingest;
pub mod map;
pub mod metrics;
pub mod pipeline;
pub mod pool;
pub mod queue;
pub mod ratelimit;
#[cfg(feature = "zenoh")]
pub mod relay;
pub mod replica;
pub mod session;
pub mod store;
pub mod tls;

use std::net::SocketAddr;
use std::sync::{Mutex, MutexGuard, RwLock, RwLockReadGuard, RwLockWriteGuard};

/// Locks `m`, recovering a lock poisoned by a panicking thread: every structure the
/// server keeps behind a mutex stays consistent between its single-step updates.
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// [`lock`] for reading an `RwLock`.
pub(crate) fn read<T>(m: &RwLock<T>) -> RwLockReadGuard<'_, T> {
    m.read().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// [`lock`] for writing an `RwLock`.
pub(crate) fn write<T>(m: &RwLock<T>) -> RwLockWriteGuard<'_, T> {
    m.write().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// Waits on `cv` (at most `timeout` when given), recovering a poisoned lock as [`lock`] does.
pub(crate) fn wait<'a, T>(cv: &std::sync::Condvar, guard: MutexGuard<'a, T>, timeout: Option<Duration>) -> MutexGuard<'a, T> {
    match timeout {
        None => cv.wait(guard).unwrap_or_else(|poisoned| poisoned.into_inner()),
        Some(t) => cv.wait_timeout(guard, t).unwrap_or_else(|poisoned| poisoned.into_inner()).0,
    }
}
use std::sync::Arc;
use std::time::Duration;

use stillmap_proto::pb::{ingest_server::IngestServer, query_server::QueryServer};
use tokio::sync::watch;

pub use config::ServerConfig;
use session::Registry;

/// Time given to open streams after a shutdown signal before the server stops anyway.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(5);
/// How long a server waits for the others to answer a forwarded query: longer than
/// they take at most (their answer, a timeout included, comes back).
#[cfg(feature = "zenoh")]
const FORWARD_TIMEOUT: Duration = Duration::from_secs(cluster::FORWARDED_ANSWER_TIMEOUT.as_secs() + 5);

/// Stored sessions that another live server wrote last (they went on there while this
/// server was away) are left out of this server's listing, so that queries about
/// them reach the live copy instead of this older one: checked at start-up and
/// whenever a server joins or leaves, and a few times in the seconds after this
/// server hands a session over (one query of the shared storage each time), until
/// shutdown. A writer that is not live (a server gone, or this one under an
/// earlier id) leaves the copy here.
#[cfg(feature = "zenoh")]
async fn leave_moved_sessions(
    registry: Arc<Registry>,
    replica: Arc<replica::Replica>,
    membership: Arc<cluster::Membership>,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) {
    let mut changes = membership.changes();
    loop {
        let ids = registry.stored_ids();
        if !ids.is_empty() {
            let r = replica.clone();
            match tokio::task::spawn_blocking(move || r.writers(&ids)).await {
                Ok(Ok(writers)) => {
                    let (own, live) = (membership.own().to_string(), membership.servers());
                    let moved = registry.leave_moved(|id| writers.get(id).filter(|w| **w != own && live.contains(w)).cloned());
                    if !moved.is_empty() {
                        tracing::info!(sessions = moved.len(), "stored sessions that went on on other servers are theirs now");
                    }
                }
                Ok(Err(e)) => tracing::warn!("stored sessions not checked against the shared storage (they stay listed here): {e}"),
                Err(e) => tracing::warn!("stored sessions not checked against the shared storage: {e}"),
            }
        }
        tokio::select! {
            changed = changes.changed() => if changed.is_err() { return },
            // A session this server handed over: its copy here leaves the listing
            // once the new owner writes it.
            () = registry.handed_over().notified() => {}
            _ = shutdown.changed() => return,
        }
    }
}

/// How long `Ingest.Place` waits for the owner's status (its advertised address):
/// a robot waits that long before asking again when the owner has just died.
#[cfg(feature = "zenoh")]
const PLACE_TIMEOUT: Duration = Duration::from_secs(2);

#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error("cannot listen on {addr}: {source}")]
    Bind { addr: String, source: std::io::Error },
    #[error("gRPC server failed: {0}")]
    Grpc(#[from] tonic::transport::Error),
    #[error("HTTP server failed: {0}")]
    Http(std::io::Error),
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// Displayed by its source (`anyhow`'s chain prints `perception: <problem>`).
    #[error("perception")]
    Perception(#[from] stillmap_perception::PerceptionError),
    #[error("{0}")]
    Store(#[from] store::StoreError),
    #[error("cannot start the worker pools: {0}")]
    Threads(std::io::Error),
    #[error("{0}")]
    Fleet(#[from] fleet::FleetError),
    #[error("{0}")]
    Replica(#[from] replica::ReplicaError),
    #[error("gRPC reflection: {0}")]
    Reflection(String),
}

/// How long an idle thread of a blocking pool stays: once started, threads stay
/// (bounded by `http.blocking_threads`), so the thread count is flat.
pub const BLOCKING_THREAD_KEEP_ALIVE: Duration = Duration::from_secs(24 * 3600);

/// A runtime beside the one running us, shut down without waiting when dropped
/// (dropping a runtime from inside another blocks, which tokio forbids).
struct SideRuntime(Option<tokio::runtime::Runtime>);

impl SideRuntime {
    fn handle(&self) -> tokio::runtime::Handle {
        self.0.as_ref().map(|r| r.handle().clone()).unwrap_or_else(tokio::runtime::Handle::current)
    }
}

impl Drop for SideRuntime {
    fn drop(&mut self) {
        if let Some(runtime) = self.0.take() {
            runtime.shutdown_background();
        }
    }
}

/// The runtime that serves HTTP: `http.worker_threads` threads named `http`,
/// each at niceness `http.nice` (Linux keeps a niceness per thread).
fn http_runtime(config: &config::HttpConfig) -> Result<SideRuntime, ServerError> {
    let nice = config.nice;
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(config.worker_threads)
        .thread_name("http")
        .max_blocking_threads(config.blocking_threads)
        .thread_keep_alive(BLOCKING_THREAD_KEEP_ALIVE)
        .on_thread_start(move || lower_this_thread(nice, "http"))
        .enable_all()
        .build()
        .map(|r| SideRuntime(Some(r)))
        .map_err(ServerError::Threads)
}

/// Raises the calling thread's niceness to `nice` (Linux keeps one per thread;
/// never needs privileges); a failure leaves it as it was, logged as `what`'s.
pub(crate) fn lower_this_thread(nice: i32, what: &str) {
    if nice == 0 {
        return;
    }
    // SAFETY: gettid has no arguments and cannot fail; setpriority on our own
    // thread id only changes this thread's scheduling weight.
    let done = unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, nice)
    };
    if done != 0 {
        tracing::warn!("cannot set the {what} thread's niceness to {nice}: {}", std::io::Error::last_os_error());
    }
}

/// Where the server ended up listening (ports resolved when 0 was asked for).
#[derive(Debug, Clone)]
pub struct Bound {
    pub grpc: SocketAddr,
    pub http: SocketAddr,
    pub zenoh: Vec<String>,
}

async fn bind(addr: &str) -> Result<tokio::net::TcpListener, ServerError> {
    tokio::net::TcpListener::bind(addr).await.map_err(|source| ServerError::Bind { addr: addr.into(), source })
}

/// Perception's configuration and, when a model is loaded, the shared segmentation service.
type PerceptionSetup = (stillmap_perception::PerceptionConfig, Option<Arc<pipeline::segmentation::SegmentationService>>);

/// Loads the segmentation model(s) when perception wants them: any problem with
/// the configured model is a start-up error. No model configured: masks come from
/// the flow alone (every pixel prior-static), with a warning.
fn perception_service(config: &ServerConfig, metrics: &Arc<metrics::Metrics>) -> Result<Option<PerceptionSetup>, ServerError> {
    let p = &config.perception;
    if !p.enabled {
        return Ok(None);
    }
    if !p.segmentation.enabled {
        return Ok(Some((p.clone(), None)));
    }
    if p.segmentation.model_path.is_empty() {
        tracing::warn!(
            "no segmentation model configured (perception.segmentation.model_path / --model): dynamic masks come from optical flow alone"
        );
        return Ok(Some((p.clone(), None)));
    }
    let service = pipeline::segmentation::SegmentationService::start(p, metrics.clone())?;
    tracing::info!(
        model = %p.segmentation.model_path,
        device = service.device(),
        workers = p.segmentation.workers,
        max_batch = service.max_batch(),
        "segmentation ready"
    );
    Ok(Some((p.clone(), Some(service))))
}

/// Serves until `shutdown` becomes true. `on_ready` is called once every listener is up.
pub async fn run(config: ServerConfig, mut shutdown: watch::Receiver<bool>, on_ready: impl FnOnce(&Bound)) -> Result<(), ServerError> {
    config.validate()?;
    let metrics: Arc<metrics::Metrics> = Arc::default();
    stillmap_tracking::set_opencv_threads(config.session.opencv_threads)
        .map_err(|e| ServerError::Config(format!("session.opencv_threads: {e}")))?;
    let pools = session::Pools::start(&config.session).map_err(ServerError::Threads)?;
    let perception = perception_service(&config, &metrics)?;
    let store = if config.store.enabled {
        let store = store::Store::open_with_cache(std::path::Path::new(&config.store.path), config.store.cache_bytes)?
            .count_errors_in(metrics.store_errors())
            .retry_at_most_every(Duration::from_secs_f64(config.store.retry_max_s));
        // Storage shared by several servers: every commit copied to PostgreSQL too (replica.rs).
        let store = if config.store.replica_url.is_empty() {
            store
        } else {
            store.replicate_to(replica::Replica::start(&config.store.replica_url, config.store.replica_queue, metrics.replica())?)
        };
        Some(Arc::new(store))
    } else {
        None
    };
    let replica = store.as_ref().and_then(|s| s.replica().cloned());
    // What is stored is listed, not loaded: a query brings a session's map and
    // trajectory into memory when it needs them. Place recognition reads the
    // keyframe records its index holds (a fleet's newest fleet.max_places).
    let stored = match &store {
        Some(s) => s.heads()?,
        None => Vec::new(),
    };
    if config.fleet.enabled && !config.mapping.enabled {
        tracing::warn!(
            "fleet.enabled needs mapping.enabled: place recognition looks at the keyframes the map lane commits, so no session will merge"
        );
    }
    let fleets = if config.fleet.enabled {
        Some(fleet::FleetService::start(&config.fleet, &config.mapping, store.clone(), metrics.clone())?)
    } else {
        None
    };
    if let Some(f) = &fleets {
        // Place recognition looks at the keyframes the map lane commits.
        let records = store.as_ref().filter(|_| config.mapping.enabled);
        f.restore_with(&stored, |s, n| match records {
            Some(store) => store.newest_keyframes(&s.id, n).unwrap_or_else(|e| {
                tracing::error!(session = %s.id, "stored keyframe records cannot be read: left out of its fleet's place index: {e}");
                Vec::new()
            }),
            None => Vec::new(),
        });
    }
    let registry = Arc::new(
        Registry::new(config.session.clone(), config.tracking.clone(), perception, config.mapping.clone(), store, metrics, pools)
            .with_fleets(fleets)
            .with_limits(config.limits.clone()),
    );
    let auth = Arc::new(auth::AuthHandle::new(&config.auth).map_err(ServerError::Config)?);
    let rate_limits = Arc::new(ratelimit::RateLimits::new(&config.limits));
    let tls = tls::TlsFiles::load(&config.tls).map_err(ServerError::Config)?;
    let http_tls = tls.as_ref().map(tls::TlsFiles::http).transpose().map_err(ServerError::Config)?;
    if tls.is_some() {
        tracing::info!(
            client_certificates = if config.tls.client_ca_path.is_empty() { "not asked" } else { "required" },
            "TLS on the gRPC and HTTP ports"
        );
    }
    if !auth.get().required() {
        tracing::info!("no auth token configured: every robot's hello and every query is accepted");
    }
    if !stored.is_empty() {
        tracing::info!(sessions = stored.len(), "stored sessions listed (loaded when a query needs them)");
        registry.restore(&stored);
    }
    drop(stored);

    let grpc_listener = bind(&config.grpc.listen).await?;
    let http_listener = bind(&config.http.listen).await?;
    let bound_grpc = grpc_listener.local_addr().map_err(ServerError::Http)?;
    let bound_http = http_listener.local_addr().map_err(ServerError::Http)?;

    // The other servers' live data, for the dashboard's events and SubscribePoses.
    #[cfg_attr(not(feature = "zenoh"), allow(unused_mut))]
    let mut remote_live: Option<Arc<dyn api::RemoteLive>> = None;
    #[cfg(feature = "zenoh")]
    let zenoh_task = if config.zenoh.enabled {
        let z = zenoh::open(ingest::zenoh::zenoh_config(&config.zenoh)?).await.map_err(|e| ServerError::Zenoh(format!("open: {e}")))?;
        let settings = ingest::zenoh::Settings {
            result_buffer: config.session.result_buffer,
            max_message_bytes: config.grpc.max_message_bytes,
            idle_disconnect: Duration::from_secs_f64(config.zenoh.idle_disconnect_s),
            auth: auth.clone(),
            rate_limits: rate_limits.clone(),
        };
        let host = cluster::host_name();
        let server_id = cluster::server_id(&config.zenoh.server_id, &host, &bound_grpc);
        if let Some(r) = &replica {
            r.name_server(&server_id);
        }
        let membership = cluster::Membership::new(&server_id);
        // A session another live server last wrote is its own: not resumed here.
        let (live, own) = (membership.clone(), server_id.clone());
        registry.set_live_elsewhere(Arc::new(move |id: &str| id != own && live.servers().iter().any(|s| s == id)));
        let identity = cluster::Identity {
            server_id: server_id.clone(),
            host,
            grpc: bound_grpc,
            http: bound_http,
            grpc_advertised: config.grpc.advertise.clone(),
            started_unix_ns: std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64),
            max_sessions: config.limits.max_sessions,
        };
        // The status answers, and the other servers' tokens are followed, from
        // before this server's token appears (a server that sees it may ask at
        // once); announced, and the other servers known, before any robot is answered.
        let announcement = cluster::declare_announcement(&z, &server_id).await?;
        let announcement = tokio::spawn(cluster::announce(announcement, registry.clone(), identity, membership.clone(), shutdown.clone()));
        let token = cluster::join(&z, &membership).await?;
        if let Some(r) = &replica {
            tokio::spawn(leave_moved_sessions(registry.clone(), r.clone(), membership.clone(), shutdown.clone()));
        }
        let task = tokio::spawn(ingest::zenoh::serve(z.clone(), registry.clone(), settings, membership.clone(), shutdown.clone()));
        let forwarder = Arc::new(cluster::Forwarder { zenoh: z.clone(), membership: membership.clone(), timeout: FORWARD_TIMEOUT });
        let live = relay::Relay::new(membership.clone());
        remote_live = Some(live.clone());
        let relaying = relay::run(z.clone(), live, registry.clone(), shutdown.clone());
        let announce = tokio::spawn(async move {
            let (announced, relayed) = tokio::join!(announcement, relaying);
            match announced {
                Ok(Ok(())) => {}
                Ok(Err(e)) => tracing::error!("not announced to other servers and fleet tools on Zenoh: {e}"),
                Err(e) => tracing::error!("the announcement to other servers stopped: {e}"),
            }
            if let Err(e) = relayed {
                tracing::error!("not sharing live data with the other servers: {e}");
            }
        });
        Some((z, task, announce, forwarder, server_id, token))
    } else {
        None
    };
    #[cfg(not(feature = "zenoh"))]
    if config.zenoh.enabled {
        tracing::warn!("zenoh.enabled is set but this build has no zenoh feature; serving gRPC only");
    }
    let clustered = cfg!(feature = "zenoh") && config.zenoh.enabled;
    if !config.grpc.advertise.is_empty() && !clustered {
        tracing::warn!("grpc.advertise is set, but without Zenoh there are no other servers: robots that ask stream here");
    }

    let max = config.grpc.max_message_bytes;
    // In a cluster, robots that ask are sent to the server they belong to (cluster.rs).
    #[cfg(feature = "zenoh")]
    let placement = zenoh_task.as_ref().map(|(z, _, _, forwarder, _, _)| {
        Arc::new(cluster::Placer {
            zenoh: z.clone(),
            membership: forwarder.membership.clone(),
            advertised: config.grpc.advertise.clone(),
            timeout: PLACE_TIMEOUT,
        }) as Arc<dyn ingest::grpc::Placement>
    });
    #[cfg(not(feature = "zenoh"))]
    let placement = None;
    let ingest = IngestServer::new(ingest::grpc::IngestService {
        placement,
        registry: registry.clone(),
        auth: auth.clone(),
        rate_limits: rate_limits.clone(),
        result_buffer: config.session.result_buffer,
        max_message_bytes: max,
    })
    .max_decoding_message_size(max);
    // Queries need a token with the read scope (when any token is configured).
    let query_auth = auth.clone();
    // In a cluster, what this server does not hold is asked of the others (cluster.rs).
    #[cfg(feature = "zenoh")]
    let remote = zenoh_task.as_ref().map(|(_, _, _, forwarder, _, _)| forwarder.clone() as Arc<dyn api::query::Remote>);
    #[cfg(not(feature = "zenoh"))]
    let remote = None;
    let query = QueryServer::with_interceptor(
        api::query::QueryService { registry: registry.clone(), remote, remote_live: remote_live.clone() },
        move |request: tonic::Request<()>| {
            let authorization = request.metadata().get("authorization").map(|v| v.as_bytes());
            query_auth.get().check(authorization, auth::Need::Read).map_err(|r| r.grpc_status())?;
            Ok(request)
        },
    );
    // gRPC health checking (grpc.health.v1): the server ("") and both services are
    // SERVING while it runs and NOT_SERVING from the moment it starts shutting down,
    // so a load balancer drains it. Open like /healthz; reflection is open too (it
    // describes the API and holds no data).
    let (health, health_service) = tonic_health::server::health_reporter();
    let grpc_services = [
        <IngestServer<ingest::grpc::IngestService> as tonic::server::NamedService>::NAME,
        <QueryServer<api::query::QueryService> as tonic::server::NamedService>::NAME,
    ];
    for service in grpc_services {
        health.set_service_status(service, tonic_health::ServingStatus::Serving).await;
    }
    let health_shutdown = wait_for(shutdown.clone());
    tokio::spawn(async move {
        health_shutdown.await;
        for service in std::iter::once("").chain(grpc_services) {
            health.set_service_status(service, tonic_health::ServingStatus::NotServing).await;
        }
    });
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(stillmap_proto::pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()
        .map_err(|e| ServerError::Reflection(e.to_string()))?;
    let grpc_shutdown = wait_for(shutdown.clone());
    let mut grpc_builder = tonic::transport::Server::builder();
    if let Some(t) = &tls {
        grpc_builder = grpc_builder.tls_config(t.grpc())?;
    }
    let grpc = grpc_builder
        .http2_keepalive_interval(Some(Duration::from_secs(config.grpc.keepalive_interval_s)))
        .http2_keepalive_timeout(Some(Duration::from_secs(config.grpc.keepalive_timeout_s)))
        .add_service(ingest)
        .add_service(query)
        .add_service(health_service)
        .add_service(reflection)
        .serve_with_incoming_shutdown(tokio_stream::wrappers::TcpListenerStream::new(grpc_listener), grpc_shutdown);
    let dashboard_dir = api::dashboard::locate(&config.http.dashboard_dir);
    let settings = Arc::new(api::http::HttpSettings {
        auth: auth.clone(),
        rate_limits: rate_limits.clone(),
        import_max_bytes: config.store.import_max_bytes,
        max_event_viewers: config.http.max_event_viewers,
        pose_event_interval: std::time::Duration::from_millis(config.http.pose_event_interval_ms),
        remote_live: remote_live.clone(),
    });
    match &dashboard_dir {
        Some(d) => tracing::info!(dir = %d.display(), "dashboard at /"),
        None => tracing::warn!("dashboard files not found (make dashboard, or http.dashboard_dir): / explains how to build them"),
    }
    // HTTP on a runtime of its own at a lower priority: dashboards and queries
    // take what CPU robots' frames leave. Its listener moves there (its readiness
    // then comes from that runtime's driver); shut down below without blocking.
    let http_runtime = http_runtime(&config.http)?;
    let http_listener = http_listener.into_std().map_err(ServerError::Http)?;
    let http_app = api::http::router(registry.clone(), dashboard_dir, settings);
    // Sessions and maps another server holds: asked of it over Zenoh (cluster.rs).
    #[cfg(feature = "zenoh")]
    let (http_app, forward_task) = match &zenoh_task {
        Some((z, _, _, forwarder, server_id, _)) => {
            let answering = cluster::answer_forwarded(z.clone(), server_id.clone(), http_app.clone(), registry.clone(), shutdown.clone());
            // Forwarded gRPC queries are answered by this server alone (never forwarded again).
            let alone = Arc::new(api::query::QueryService { registry: registry.clone(), remote: None, remote_live: None });
            let answering_grpc = cluster::answer_forwarded_grpc(z.clone(), server_id.clone(), alone, auth.clone(), shutdown.clone());
            let answer = tokio::spawn(async move {
                let (http, grpc) = tokio::join!(answering, answering_grpc);
                if let Err(e) = http.and(grpc) {
                    tracing::error!("not answering other servers' forwarded queries: {e}");
                }
            });
            (http_app.layer(axum::middleware::from_fn_with_state(forwarder.clone(), cluster::forward_unknown)), Some(answer))
        }
        None => (http_app, None),
    };
    let http_options = api::serve::Options {
        header_timeout: Duration::from_secs_f64(config.http.header_timeout_s),
        max_connections: config.http.max_connections,
        tls: http_tls,
    };
    let (http_metrics, http_shutdown) = (registry.metrics().clone(), shutdown.clone());
    let http = async move {
        let listener = tokio::net::TcpListener::from_std(http_listener).map_err(ServerError::Http)?;
        api::serve::serve(listener, http_app, http_options, http_metrics, http_shutdown, SHUTDOWN_GRACE).await;
        Ok::<(), ServerError>(())
    };

    let bound = Bound {
        grpc: bound_grpc,
        http: bound_http,
        #[cfg(feature = "zenoh")]
        zenoh: if config.zenoh.enabled { config.zenoh.listen.clone() } else { vec![] },
        #[cfg(not(feature = "zenoh"))]
        zenoh: vec![],
    };
    on_ready(&bound);

    // What a session has not committed (the poses after its last keyframe, a commit
    // that failed while the store could not write) is committed every
    // store.flush_interval_s, off the runtime.
    let flush_registry = registry.clone();
    let flush_limits = rate_limits.clone();
    let flush_every = Duration::from_secs_f64(config.store.flush_interval_s);
    let flush_task = tokio::spawn(async move {
        let mut interval = tokio::time::interval(flush_every);
        interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        interval.tick().await;
        loop {
            interval.tick().await;
            let r = flush_registry.clone();
            // Clients quiet long enough leave the rate limiters too.
            flush_limits.forget_idle();
            if tokio::task::spawn_blocking(move || r.list().iter().filter(|s| s.flush()).count()).await.is_err() {
                break;
            }
        }
    });
    // SIGHUP reads auth.token_file again (a mistake keeps the tokens in force).
    let reload_task = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()) {
        Ok(mut hangup) => {
            let auth = auth.clone();
            Some(tokio::spawn(async move {
                while hangup.recv().await.is_some() {
                    match auth.reload() {
                        Ok(n) => tracing::info!(tokens = n, "SIGHUP: auth tokens reloaded"),
                        Err(e) => tracing::error!("SIGHUP: auth tokens not reloaded, the ones in force stay: {e}"),
                    }
                }
            }))
        }
        Err(e) => {
            tracing::warn!("no SIGHUP handler (auth.token_file is read at start-up only): {e}");
            None
        }
    };
    // Sessions idle for session.idle_evict_s leave memory (the store keeps them).
    let evict_task = (config.session.idle_evict_s > 0.0).then(|| {
        let registry = registry.clone();
        let every = Duration::from_secs_f64((config.session.idle_evict_s / 4.0).clamp(0.05, 5.0));
        tokio::spawn(async move {
            let mut interval = tokio::time::interval(every);
            interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                interval.tick().await;
                let r = registry.clone();
                if tokio::task::spawn_blocking(move || r.evict_idle()).await.is_err() {
                    break;
                }
            }
        })
    });
    let grpc_task = tokio::spawn(grpc);
    let http_task = http_runtime.handle().spawn(http);
    let _ = shutdown.wait_for(|stop| *stop).await;
    tracing::info!("shutting down");
    flush_task.abort();
    for task in [evict_task, reload_task].into_iter().flatten() {
        task.abort();
    }
    registry.close_all();
    let finish = async {
        match grpc_task.await {
            Ok(r) => r?,
            Err(e) => tracing::error!("gRPC task: {e}"),
        }
        match http_task.await {
            Ok(r) => r?,
            Err(e) => tracing::error!("HTTP task: {e}"),
        }
        Ok::<(), ServerError>(())
    };
    match tokio::time::timeout(SHUTDOWN_GRACE, finish).await {
        Ok(r) => r?,
        Err(_) => tracing::warn!("open streams outlived the {SHUTDOWN_GRACE:?} grace period; stopping anyway"),
    }
    drop(http_runtime);
    // The workers finish their queues and commit what came after their last keyframe.
    let workers = registry.clone();
    if tokio::time::timeout(SHUTDOWN_GRACE, tokio::task::spawn_blocking(move || workers.join_workers())).await.is_err() {
        tracing::warn!("pipeline workers outlived the {SHUTDOWN_GRACE:?} grace period; stopping anyway");
    }
    // What the workers committed last is copied before the server stops.
    if let Some(r) = replica
        && tokio::time::timeout(SHUTDOWN_GRACE, tokio::task::spawn_blocking(move || r.close())).await.is_err()
    {
        tracing::warn!("the copy to store.replica_url outlived the {SHUTDOWN_GRACE:?} grace period; stopping anyway");
    }
    #[cfg(feature = "zenoh")]
    if let Some(answer) = forward_task {
        let _ = answer.await;
    }
    #[cfg(feature = "zenoh")]
    if let Some((z, task, announce, _, _, token)) = zenoh_task {
        let _ = task.await;
        let _ = announce.await;
        let _ = token.undeclare().await;
        if let Err(e) = z.close().await {
            tracing::warn!("zenoh close: {e}");
        }
    }
    Ok(())
}

/// Waits for SIGINT or SIGTERM (the server's and the router's graceful stop).
pub async fn shutdown_signal() -> std::io::Result<()> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = signal(SignalKind::terminate())?;
    tokio::select! {
        r = tokio::signal::ctrl_c() => r?,
        _ = term.recv() => {}
    }
    Ok(())
}

async fn wait_for(mut shutdown: watch::Receiver<bool>) {
    let _ = shutdown.wait_for(|stop| *stop).await;
}
