//! Zenoh shell: robots publish `ClientMessage`s on `stillmap/<robot>/frames`;
//! the server answers with `ServerMessage`s on `stillmap/<robot>/results`.
//!
//! Zenoh has no call status, so stream-level problems (a frame before the hello,
//! an oversized or undecodable message, an overloaded session) are published as
//! `ServerMessage.error` with the gRPC code the same problem gets on gRPC.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use prost::Message;
use stillmap_proto::{keys, pb, pb::server_message::Msg};
use tokio::sync::mpsc;
use tonic::Status;
use zenoh::qos::CongestionControl;

use super::{ZenohMessage, ZenohRejection, accepted_message, frame_before_hello, parse_zenoh_message, refusal};
use crate::ServerError;
use crate::config::ZenohConfig;
use crate::session::{Registry, ResultSink, Session, Transport};

/// Builds the Zenoh configuration of the server from its config section: the
/// file it names as it is, else the section's endpoints and mode.
pub fn zenoh_config(cfg: &ZenohConfig) -> Result<zenoh::Config, ServerError> {
    if let Some(path) = &cfg.config_file {
        return zenoh::Config::from_file(path).map_err(|e| ServerError::Zenoh(format!("config file {}: {e}", path.display())));
    }
    let mut c = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, key: &str, value: String| {
        c.insert_json5(key, &value).map_err(|e| ServerError::Zenoh(format!("config {key}: {e}")))
    };
    let list = |v: &[String]| serde_json::to_string(v).unwrap_or_else(|_| "[]".into());
    set(&mut c, "mode", format!("{:?}", cfg.mode))?;
    set(&mut c, "scouting/multicast/enabled", cfg.multicast_scouting.to_string())?;
    set(&mut c, "listen/endpoints", list(&cfg.listen))?;
    set(&mut c, "connect/endpoints", list(&cfg.connect))?;
    Ok(c)
}

/// One robot's link over Zenoh: its session and the sink feeding its publisher.
struct Link {
    session: Arc<Session>,
    sink: ResultSink,
    /// The hello that opened the session (the client repeats it until it hears the accept).
    hello: pb::Hello,
    /// When the robot last sent anything.
    last_seen: Instant,
    /// Whether the idle check has found the robot quiet since it last spoke.
    quiet: bool,
    /// The session came back from the shared storage on this hello, and no frame
    /// came since: the accept of a repeat of it says so too.
    restored: bool,
}

impl Link {
    fn new(session: Arc<Session>, sink: ResultSink, hello: pb::Hello) -> Self {
        Self { session, sink, hello, last_seen: Instant::now(), quiet: false, restored: false }
    }

    /// Whether `hello` repeats the one that opened this session before any frame
    /// arrived: the client did not hear the accept yet (it repeats its hello every
    /// 500 ms), and a second session must not be opened for it.
    fn is_repeat(&self, hello: &pb::Hello) -> bool {
        hello.resume_session_id.is_empty() && *hello == self.hello && self.session.last_received_sequence().is_none()
    }

    /// The robot sent a frame: its results go to it again, unless another
    /// connection (a gRPC resume) holds the session now.
    fn seen(&mut self) {
        self.last_seen = Instant::now();
        if self.session.attach_if_vacant(&self.sink) && self.quiet {
            tracing::info!(session = %self.session.id, "zenoh robot is back");
        }
        self.quiet = false;
    }
}

/// What the Zenoh shell is told besides the registry.
pub struct Settings {
    pub result_buffer: usize,
    pub max_message_bytes: usize,
    /// A robot silent this long (zero: never) counts as disconnected.
    pub idle_disconnect: Duration,
    pub auth: Arc<crate::auth::AuthHandle>,
    pub rate_limits: Arc<crate::ratelimit::RateLimits>,
}

/// Longest wait between two checks for quiet robots.
const MAX_IDLE_CHECK: Duration = Duration::from_secs(1);

/// Subscribes to every robot's frames until `shutdown` fires. A robot silent for
/// `idle_disconnect` (zero: never) counts as disconnected until it sends again.
/// Only the robots `membership` says are this server's are answered (placement
/// among servers on one Zenoh network, `cluster.rs`); a robot that moved to another
/// server is let go here without a word.
pub async fn serve(
    zenoh: zenoh::Session,
    registry: Arc<Registry>,
    settings: Settings,
    membership: Arc<crate::cluster::Membership>,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) -> Result<(), ServerError> {
    let Settings { result_buffer, max_message_bytes, idle_disconnect, auth, rate_limits } = settings;
    let subscriber =
        zenoh.declare_subscriber(keys::ALL_FRAMES).await.map_err(|e| ServerError::Zenoh(format!("subscribe {}: {e}", keys::ALL_FRAMES)))?;
    let mut links: HashMap<String, Link> = HashMap::new();
    // Hellos whose open reads the shared storage (PostgreSQL) run on a blocking
    // thread; their outcome comes back here. Meanwhile the robot's repeated hellos
    // wait for it, and every other robot is served.
    let (opened_tx, mut opened_rx) = mpsc::channel::<OpenedHello>(OPENS_IN_FLIGHT);
    // (with when each began: one that never reports back is forgotten after OPEN_GIVE_UP)
    let mut opening: HashMap<String, Instant> = HashMap::new();
    let mut idle_check = tokio::time::interval((idle_disconnect / 2).clamp(Duration::from_millis(10), MAX_IDLE_CHECK));
    idle_check.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        let sample = tokio::select! {
            s = subscriber.recv_async() => match s { Ok(s) => s, Err(_) => break },
            Some((robot, placement, hello, sink, result)) = opened_rx.recv() => {
                opening.remove(&robot);
                // Placement may have moved the robot meanwhile: its new owner answers it.
                if membership.owns(&placement) {
                    answer_open(&mut links, robot, hello, sink, result, max_message_bytes, registry.metrics()).await;
                } else if let Ok(opened) = result {
                    opened.session.detach(&sink);
                }
                continue;
            }
            _ = idle_check.tick(), if !idle_disconnect.is_zero() => {
                // Quiet and answered: a robot whose frames are still in the pipeline
                // (its window full behind a slow server) is waiting, not gone.
                let quiet = |l: &Link| !l.quiet && l.last_seen.elapsed() >= idle_disconnect && l.session.unanswered() == 0;
                for link in links.values_mut().filter(|l| quiet(l)) {
                    // Only our own sink is detached: a gRPC resume keeps the session.
                    link.session.detach(&link.sink);
                    link.quiet = true;
                    tracing::info!(session = %link.session.id, "zenoh robot silent for {idle_disconnect:?}: disconnected");
                }
                // A session that left memory (session.idle_evict_s) is not held here:
                // the robot's next frame is told to send a hello.
                links.retain(|_, l| !l.quiet || registry.resident(&l.session.id).is_some());
                continue;
            }
            _ = shutdown.changed() => break,
        };
        let Some(robot) = keys::robot_of_frames_key(sample.key_expr().as_str()).map(str::to_owned) else {
            continue;
        };
        let payload = sample.payload().to_bytes();
        let placement = placement_of(&robot, &payload, max_message_bytes);
        if !membership.owns(&placement) {
            // Another server's robot: its owner answers. One that was ours moved
            // (a server joined): its session is let go, and handed over to the new
            // owner once what it holds is answered and committed (with shared
            // storage), so that the robot resumes it there.
            if let Some(link) = links.remove(&robot) {
                link.session.detach(&link.sink);
                tracing::info!(session = %link.session.id, robot, "robot placed on another server: let go");
                super::hand_over(registry.clone(), link.session.id.clone());
            }
            continue;
        }
        let metrics = registry.metrics();
        let reply = |links: &HashMap<String, Link>, status: Status| {
            let z = zenoh.clone();
            let key = keys::results(&robot);
            let sink = links.get(&robot).map(|l| l.sink.clone());
            async move {
                match sink {
                    Some(sink) => {
                        let _ = sink.send(Err(status)).await;
                    }
                    None => publish(&z, &key, &error_message(status, "")).await,
                }
            }
        };
        let message = match parse_zenoh_message(&robot, &payload, max_message_bytes) {
            Ok(m) => m,
            Err(ZenohRejection { label, status }) => {
                if let Some(label) = label {
                    metrics.rejected(label);
                }
                reply(&links, status).await;
                continue;
            }
        };
        match message {
            ZenohMessage::Hello(hello) => {
                // Zenoh carries no peer address: hellos are counted per robot key.
                if let Err(message) = rate_limits.hello(&format!("robot {robot}")) {
                    metrics.rejected("rate_limited");
                    reply(&links, Status::resource_exhausted(message)).await;
                    continue;
                }
                if let Err(status) = auth.get().check_hello(&hello) {
                    metrics.rejected("unauthenticated");
                    reply(&links, status).await;
                    continue;
                }
                // A repeated hello for the session already attached is a retry: answer it again.
                // A hello for the session already attached is answered again: a resume
                // of it (secret checked), or the opening hello repeated before the
                // client heard the accept.
                if let Some(link) = links.get_mut(&robot) {
                    let resumed = hello.resume_session_id == link.session.id;
                    if resumed || link.is_repeat(&hello) {
                        if resumed {
                            if let Err(e) = link.session.check_resume_secret(&hello.resume_secret) {
                                metrics.rejected("unauthenticated");
                                reply(&links, e.status()).await;
                                continue;
                            }
                            // A hello asks for the session outright, as a new one would.
                            link.session.attach(link.sink.clone());
                        }
                        link.seen();
                        let restored = link.restored && hello == link.hello;
                        let opened = crate::session::Opened { session: link.session.clone(), resumed, restored };
                        let _ = link.sink.send(Ok(accepted_message(&opened, max_message_bytes))).await;
                        continue;
                    }
                }
                opening.retain(|_, began| began.elapsed() < OPEN_GIVE_UP);
                if opening.contains_key(&robot) {
                    continue; // answered when its open (a read of the shared storage) is done
                }
                let sink = spawn_publisher(zenoh.clone(), keys::results(&robot), result_buffer);
                if registry.reads_replica(&hello) && opening.len() < OPENS_IN_FLIGHT {
                    opening.insert(robot.clone(), Instant::now());
                    let (registry, opened_tx) = (registry.clone(), opened_tx.clone());
                    tokio::task::spawn_blocking(move || {
                        let result = registry.open(&hello, Transport::Zenoh, sink.clone());
                        let _ = opened_tx.blocking_send((robot, placement, hello, sink, result));
                    });
                    continue;
                }
                let result = registry.open(&hello, Transport::Zenoh, sink.clone());
                answer_open(&mut links, robot, hello, sink, result, max_message_bytes, metrics).await;
            }
            ZenohMessage::Frame(frame) => {
                let Some(link) = links.get_mut(&robot) else {
                    metrics.rejected("no_hello");
                    reply(&links, frame_before_hello(frame.sequence)).await;
                    continue;
                };
                link.seen();
                link.restored = false;
                if let Err(e) = link.session.push(frame, payload.len()) {
                    let _ = link.sink.send(Err(link.session.refusal_of(e))).await;
                }
            }
        }
    }
    for link in links.values() {
        link.session.detach(&link.sink);
    }
    Ok(())
}

/// Opens that read the shared storage at once, at most (beyond: opened inline).
const OPENS_IN_FLIGHT: usize = 16;
/// An open off the loop that has not reported back after this long (PostgreSQL's
/// connect and statement timeouts are 5 s and 30 s) no longer holds its robot's hellos.
const OPEN_GIVE_UP: Duration = Duration::from_secs(60);

/// A hello's open done off the loop: the robot, what it was placed by, its hello,
/// its results sink, the outcome.
type OpenedHello = (String, String, pb::Hello, ResultSink, Result<crate::session::Opened, crate::session::BadHello>);

/// What a message of `robot` is placed by among the servers
/// (`stillmap_proto::placement_key`): the fleet it names, else the robot id. A
/// message too large or undecodable, or naming a fleet that is no valid name, is
/// placed by the robot id; its owner refuses it.
fn placement_of(robot: &str, payload: &[u8], max_message_bytes: usize) -> String {
    let fleet = (payload.len() <= max_message_bytes)
        .then(|| stillmap_proto::client_message_fleet(payload).ok())
        .flatten()
        .filter(|fleet| stillmap_proto::validate_fleet(fleet).is_ok())
        .unwrap_or_default();
    stillmap_proto::placement_key(robot, &fleet).into_owned()
}

/// Answers a hello with its open's outcome: the accept and the robot's link, or the refusal.
async fn answer_open(
    links: &mut HashMap<String, Link>,
    robot: String,
    hello: pb::Hello,
    sink: ResultSink,
    result: Result<crate::session::Opened, crate::session::BadHello>,
    max_message_bytes: usize,
    metrics: &crate::metrics::Metrics,
) {
    match result {
        Ok(opened) => {
            let _ = sink.send(Ok(accepted_message(&opened, max_message_bytes))).await;
            let mut link = Link::new(opened.session, sink, hello);
            link.restored = opened.restored;
            if let Some(old) = links.insert(robot, link) {
                old.session.detach(&old.sink);
            }
        }
        Err(e) => {
            let _ = sink.send(Err(refusal(&e, metrics))).await;
        }
    }
}

/// A status as a message; `session_id`: the session it is about (empty: none yet).
fn error_message(status: Status, session_id: &str) -> pb::ServerMessage {
    pb::ServerMessage {
        msg: Some(Msg::Error(pb::RpcStatus {
            code: status.code() as i32,
            message: status.message().to_string(),
            session_id: session_id.to_string(),
        })),
    }
}

/// What a hello's publisher sends for `item`: a status names the session accepted on
/// that hello (`session`, set when the accept goes out).
fn outgoing(item: Result<pb::ServerMessage, Status>, session: &mut String) -> pb::ServerMessage {
    match item {
        Ok(message) => {
            if let Some(Msg::Accepted(accepted)) = &message.msg {
                session.clone_from(&accepted.session_id);
            }
            message
        }
        Err(status) => error_message(status, session),
    }
}

async fn publish(zenoh: &zenoh::Session, key: &str, message: &pb::ServerMessage) {
    if let Err(e) = zenoh.put(key, message.encode_to_vec()).congestion_control(CongestionControl::Block).await {
        tracing::warn!(key, "zenoh put failed: {e}");
    }
}

/// A task that publishes everything sent to the returned sink on `key`, in order.
fn spawn_publisher(zenoh: zenoh::Session, key: String, buffer: usize) -> ResultSink {
    let (tx, mut rx) = mpsc::channel::<Result<pb::ServerMessage, Status>>(buffer);
    tokio::spawn(async move {
        let mut session = String::new();
        while let Some(item) = rx.recv().await {
            publish(&zenoh, &key, &outgoing(item, &mut session)).await;
        }
    });
    tx
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A status the publisher sends names the session its hello was accepted as;
    /// before the accept, none.
    #[test]
    fn a_published_status_names_the_session_of_its_hello() {
        let mut session = String::new();
        let status = |m: &pb::ServerMessage| match &m.msg {
            Some(Msg::Error(e)) => (tonic::Code::from_i32(e.code), e.session_id.clone()),
            other => panic!("not a status: {other:?}"),
        };
        let early = outgoing(Err(Status::failed_precondition("no hello yet")), &mut session);
        assert_eq!(status(&early), (tonic::Code::FailedPrecondition, String::new()));
        let accepted =
            pb::ServerMessage { msg: Some(Msg::Accepted(pb::SessionAccepted { session_id: "r-1a-1".into(), ..Default::default() })) };
        assert_eq!(outgoing(Ok(accepted.clone()), &mut session), accepted);
        let ended = outgoing(Err(Status::aborted("given up")), &mut session);
        assert_eq!(status(&ended), (tonic::Code::Aborted, "r-1a-1".to_string()));
    }

    fn message(fleet: &str) -> Vec<u8> {
        let frame = pb::Frame { sequence: 3, depth: vec![7u8; 1000].into(), ..Default::default() };
        pb::ClientMessage { msg: Some(pb::client_message::Msg::Frame(frame)), fleet: fleet.into() }.encode_to_vec()
    }

    /// A message is placed by the fleet it names, else by its robot; one the owner
    /// will refuse (too large, undecodable, a fleet that is no name) by its robot.
    #[test]
    fn a_message_is_placed_by_its_fleet_else_by_its_robot() {
        assert_eq!(placement_of("r1", &message("warehouse"), 10_000), "fleet:warehouse");
        assert_eq!(placement_of("r1", &message(""), 10_000), "r1");
        assert_eq!(placement_of("r1", &message("warehouse"), 100), "r1", "oversized");
        assert_eq!(placement_of("r1", &message("ware house"), 10_000), "r1", "not a name");
        assert_eq!(placement_of("r1", &[0xff, 0xff], 10_000), "r1", "undecodable");
    }
}
