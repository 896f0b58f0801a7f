//! Transports between the streamer and the server. Each link is a task that
//! takes frames from a channel and reports events on another; the streamer never
//! sees which transport it talks to.
//!
//! - gRPC: one bidirectional `Ingest.Stream` with HTTP/2 keepalive; on a
//!   transport failure it reconnects with exponential backoff, resumes the session
//!   (`Hello.resume_session_id`) and resends the frames the server had not received.
//! - Zenoh: publishes on `stillmap/<robot>/frames`, listens on `stillmap/<robot>/results`.

use std::collections::VecDeque;
use std::time::Duration;

#[cfg(feature = "zenoh")]
use prost::Message;
use stillmap_proto::pb::{self, client_message::Msg as ClientMsg, ingest_client::IngestClient, server_message::Msg};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use crate::ClientError;

/// What a link reports to the streamer.
#[derive(Debug)]
pub enum LinkEvent {
    /// The gRPC server the next accept comes from (where the robot was placed).
    Streaming(String),
    Accepted(pb::SessionAccepted),
    Result(pb::FrameResult),
    /// The connection broke and was re-established (attempt number).
    Reconnected(u32),
    /// Frames the server had received before a reconnect but whose results were lost.
    Unanswered(Vec<u64>),
}

/// Reconnection and keepalive settings of the gRPC link.
#[derive(Debug, Clone)]
pub struct GrpcOptions {
    /// The servers to ask where to stream (`Ingest.Place`), in turn from the last
    /// that answered; at least one.
    pub servers: Vec<String>,
    /// TLS to the server (an https:// endpoint), `None`: plain.
    pub tls: Option<ClientTls>,
    pub keepalive: Duration,
    pub connect_timeout: Duration,
    pub initial_backoff: Duration,
    pub max_backoff: Duration,
    /// Consecutive failed attempts before giving up.
    pub max_attempts: u32,
    /// No result for this long while frames wait for theirs: the stream is taken
    /// as dead (a server that stopped answering, or the session's results going
    /// elsewhere) and the link reconnects, resuming the session.
    pub result_timeout: Duration,
}

/// The PEM files of a TLS link: the CA that signed the server's certificate, and
/// this robot's certificate and key when the server asks for one.
#[derive(Debug, Clone)]
pub struct ClientTls {
    pub ca: Vec<u8>,
    pub identity: Option<(Vec<u8>, Vec<u8>)>,
}

impl ClientTls {
    fn config(&self) -> tonic::transport::ClientTlsConfig {
        let mut c = tonic::transport::ClientTlsConfig::new().ca_certificate(tonic::transport::Certificate::from_pem(&self.ca));
        if let Some((cert, key)) = &self.identity {
            c = c.identity(tonic::transport::Identity::from_pem(cert, key));
        }
        c
    }
}

/// Zenoh link settings.
#[derive(Debug, Clone)]
pub struct ZenohOptions {
    /// Endpoints to connect to (the server's listen endpoints, or a router).
    pub connect: Vec<String>,
    /// "peer" or "client".
    pub mode: String,
    /// How long to wait for the server to accept the hello, and for late results.
    pub timeout: Duration,
    /// A Zenoh configuration file (JSON5: TLS, mTLS, authentication); when given
    /// it is the whole Zenoh configuration, and `connect` and `mode` are ignored.
    pub config_file: Option<std::path::PathBuf>,
}

/// A started link.
pub struct Link {
    pub frames: mpsc::Sender<pb::Frame>,
    pub events: mpsc::Receiver<LinkEvent>,
    pub task: tokio::task::JoinHandle<Result<(), ClientError>>,
}

/// Frames the link may buffer between the streamer and the wire.
const LINK_BUFFER: usize = 4;

fn is_transient(code: Code) -> bool {
    matches!(code, Code::Unavailable | Code::Unknown | Code::Cancelled | Code::Internal | Code::DeadlineExceeded)
}

/// A frame over gRPC (the robot is placed by asking, `Ingest.Place`, not by its messages).
fn frame_message(frame: pb::Frame) -> pb::ClientMessage {
    pb::ClientMessage { msg: Some(ClientMsg::Frame(frame)), fleet: String::new() }
}

/// A message over Zenoh, with the fleet the servers place the robot by (its
/// hello's: every robot of a fleet on one server; none: placed by the robot id).
#[cfg(feature = "zenoh")]
fn zenoh_message(msg: ClientMsg, hello: &pb::Hello) -> Vec<u8> {
    pb::ClientMessage { msg: Some(msg), fleet: hello.fleet.clone() }.encode_to_vec()
}

pub fn start_grpc(hello: pb::Hello, options: GrpcOptions) -> Link {
    let (frames_tx, frames_rx) = mpsc::channel(LINK_BUFFER);
    let (events_tx, events_rx) = mpsc::channel(LINK_BUFFER * 16);
    let task = tokio::spawn(run_grpc(hello, options, frames_rx, events_tx));
    Link { frames: frames_tx, events: events_rx, task }
}

/// Why a connection attempt or a stream ended without finishing.
enum Broke {
    /// Reconnect and resume.
    Transient(String),
    /// Give up: the server refused (bad hello, frame before hello, …).
    Fatal(ClientError),
}

fn classify(status: tonic::Status) -> Broke {
    if is_transient(status.code()) {
        Broke::Transient(format!("{}: {}", status.code(), status.message()))
    } else {
        Broke::Fatal(ClientError::Server { code: status.code(), message: status.message().into() })
    }
}

/// An open, accepted stream.
struct Connected {
    out: mpsc::Sender<pb::ClientMessage>,
    inbound: tonic::Streaming<pb::ServerMessage>,
    accepted: pb::SessionAccepted,
}

/// Connects to `to` (or streams on the connection it already is), sends the hello
/// (resuming `session_id` when set) and waits for the accept.
async fn connect_once(to: Target, hello: &pb::Hello, session_id: &str, resume_secret: &str) -> Result<Connected, Broke> {
    let channel = match to {
        Target::Open(channel) => channel,
        Target::Dial(endpoint) => endpoint.connect().await.map_err(|e| Broke::Transient(e.to_string()))?,
    };
    let mut client = IngestClient::new(channel);
    let (out, out_rx) = mpsc::channel(LINK_BUFFER);
    let hello = pb::Hello { resume_session_id: session_id.to_string(), resume_secret: resume_secret.to_string(), ..hello.clone() };
    out.send(pb::ClientMessage { msg: Some(ClientMsg::Hello(hello)), fleet: String::new() })
        .await
        .map_err(|_| Broke::Transient("outbound stream closed".into()))?;
    let mut inbound = client.stream(ReceiverStream::new(out_rx)).await.map_err(classify)?.into_inner();
    match inbound.message().await.map_err(classify)? {
        Some(pb::ServerMessage { msg: Some(Msg::Accepted(accepted)) }) => Ok(Connected { out, inbound, accepted }),
        Some(other) => Err(Broke::Fatal(ClientError::Protocol(format!("expected SessionAccepted first, got {other:?}")))),
        None => Err(Broke::Transient("server closed the stream before accepting".into())),
    }
}

/// A server address as an endpoint with the link's TLS, timeouts and keepalive.
fn grpc_endpoint(address: &str, options: &GrpcOptions) -> Result<tonic::transport::Endpoint, ClientError> {
    let mut endpoint = tonic::transport::Endpoint::from_shared(address.to_string())
        .map_err(|e| ClientError::Usage(format!("bad server address {address:?}: {e}")))?;
    if let Some(tls) = &options.tls {
        endpoint = endpoint.tls_config(tls.config()).map_err(|e| ClientError::Usage(format!("TLS to {address}: {e}")))?;
    }
    Ok(endpoint
        .connect_timeout(options.connect_timeout)
        .http2_keep_alive_interval(options.keepalive)
        .keep_alive_timeout(options.keepalive * 2)
        .keep_alive_while_idle(true))
}

/// Where a stream goes: a server to dial, or the connection to the server asked.
enum Target {
    Dial(Box<tonic::transport::Endpoint>),
    Open(tonic::transport::Channel),
}

/// Where to stream: asks the servers in turn, from `*next`, where this robot
/// belongs (`Ingest.Place`), and returns the address to stream to and how: the
/// owner's advertised address, or the server asked (on the connection the question
/// went over) when the answer names none or the server predates `Place`, and
/// whether a server answered (the robot follows placement: it asks again on every
/// reconnect, so a server may send it elsewhere). `*next` becomes the server that
/// answered. Transient when none answered.
async fn placed(
    seeds: &[(String, tonic::transport::Endpoint)],
    next: &mut usize,
    hello: &pb::Hello,
    options: &GrpcOptions,
) -> Result<(String, Target, bool), Broke> {
    let mut why = Vec::new();
    for i in 0..seeds.len() {
        let at = (*next + i) % seeds.len();
        let (address, endpoint) = &seeds[at];
        let channel = match endpoint.connect().await {
            Ok(channel) => channel,
            Err(e) => {
                why.push(format!("{address}: {e}"));
                continue;
            }
        };
        let asked = IngestClient::new(channel.clone()).place(hello.clone()).await;
        let (placement, follows) = match asked {
            Ok(p) => (p.into_inner(), true),
            Err(status) if status.code() == Code::Unimplemented => (pb::Placement::default(), false),
            Err(status) if is_transient(status.code()) => {
                why.push(format!("{address}: {}: {}", status.code(), status.message()));
                continue;
            }
            Err(status) => return Err(classify(status)),
        };
        *next = at;
        if placement.grpc_address.is_empty() || placement.grpc_address == *address {
            return Ok((address.clone(), Target::Open(channel), follows));
        }
        tracing::info!("{address} places this robot on {} ({})", placement.server_id, placement.grpc_address);
        return match grpc_endpoint(&placement.grpc_address, options) {
            Ok(e) => Ok((placement.grpc_address, Target::Dial(Box::new(e)), follows)),
            Err(e) => Err(Broke::Fatal(ClientError::Protocol(format!("{address} placed this robot at an unusable address: {e}")))),
        };
    }
    Err(Broke::Transient(format!("no server said where to stream ({})", why.join("; "))))
}

async fn run_grpc(
    hello: pb::Hello,
    options: GrpcOptions,
    mut frames_rx: mpsc::Receiver<pb::Frame>,
    events: mpsc::Sender<LinkEvent>,
) -> Result<(), ClientError> {
    if options.servers.is_empty() {
        return Err(ClientError::Usage("no gRPC server given (--server)".into()));
    }
    let seeds = options.servers.iter().map(|a| Ok((a.clone(), grpc_endpoint(a, &options)?))).collect::<Result<Vec<_>, ClientError>>()?;
    let mut next_seed = 0;
    let mut at = seeds[0].0.clone();
    // Frames sent whose result has not come back: resent after a reconnect.
    let mut unacked: VecDeque<pb::Frame> = VecDeque::new();
    let mut session_id = String::new();
    let mut resume_secret = String::new();
    let mut input_done = false;
    let mut failures = 0u32;
    let mut backoff = options.initial_backoff;
    loop {
        if failures > 0 {
            if failures > options.max_attempts {
                return Err(ClientError::Connect(format!(
                    "gave up on {} after {} attempts",
                    options.servers.join(", "),
                    options.max_attempts
                )));
            }
            tokio::time::sleep(backoff).await;
            backoff = (backoff * 2).min(options.max_backoff);
        }
        let attempt = match placed(&seeds, &mut next_seed, &hello, &options).await {
            Ok((address, target, follows)) => {
                at = address;
                let hello = pb::Hello { follows_placement: follows, ..hello.clone() };
                connect_once(target, &hello, &session_id, &resume_secret).await
            }
            Err(broke) => Err(broke),
        };
        let Connected { out, mut inbound, accepted } = match attempt {
            Ok(c) => c,
            Err(Broke::Fatal(e)) => return Err(e),
            Err(Broke::Transient(why)) => {
                failures += 1;
                tracing::warn!("connecting to {at} failed ({why}); attempt {failures}");
                continue;
            }
        };
        if !session_id.is_empty() {
            let _ = events.send(LinkEvent::Reconnected(failures)).await;
        }
        failures = 0;
        backoff = options.initial_backoff;
        // Frames the server already has are never sent twice; their results are lost.
        if accepted.resumed
            && let Some(last) = accepted.last_received_sequence
        {
            let lost: Vec<u64> = unacked.iter().map(|f| f.sequence).filter(|&s| s <= last).collect();
            unacked.retain(|f| f.sequence > last);
            if !lost.is_empty() {
                let _ = events.send(LinkEvent::Unanswered(lost)).await;
            }
        }
        session_id = accepted.session_id.clone();
        resume_secret = accepted.resume_secret.clone();
        let _ = events.send(LinkEvent::Streaming(at.clone())).await;
        let _ = events.send(LinkEvent::Accepted(accepted)).await;
        for f in &unacked {
            if out.send(frame_message(f.clone())).await.is_err() {
                break;
            }
        }
        // Dropping the sender half-closes the stream: the server answers what it has, then ends it.
        let mut sender = (!input_done).then_some(out);
        // Since when frames have waited for a result with none arriving.
        let mut waiting_since = (!unacked.is_empty()).then(tokio::time::Instant::now);
        let broke = loop {
            let deadline = waiting_since.map(|t| t + options.result_timeout);
            tokio::select! {
                _ = tokio::time::sleep_until(deadline.unwrap_or_else(tokio::time::Instant::now)), if deadline.is_some() => {
                    break Broke::Transient(format!("no result for {:.1} s while {} frames wait (--result-timeout)", options.result_timeout.as_secs_f64(), unacked.len()));
                }
                frame = frames_rx.recv(), if sender.is_some() => match (frame, &sender) {
                    (Some(frame), Some(out)) => {
                        if unacked.is_empty() {
                            waiting_since = Some(tokio::time::Instant::now());
                        }
                        unacked.push_back(frame.clone());
                        // A stream that stopped taking frames (flow control) is as dead as one
                        // that stopped answering.
                        match tokio::time::timeout(options.result_timeout, out.send(frame_message(frame))).await {
                            Ok(Ok(())) => {}
                            Ok(Err(_)) => break Broke::Transient("outbound stream closed".into()),
                            Err(_) => break Broke::Transient(format!("a frame could not be sent for {:.1} s (--result-timeout)", options.result_timeout.as_secs_f64())),
                        }
                    }
                    _ => {
                        input_done = true;
                        sender = None;
                    }
                },
                message = inbound.message() => match message {
                    Ok(Some(pb::ServerMessage { msg: Some(Msg::Result(r)) })) => {
                        while unacked.front().is_some_and(|f| f.sequence <= r.sequence) {
                            unacked.pop_front();
                        }
                        waiting_since = (!unacked.is_empty()).then(tokio::time::Instant::now);
                        let _ = events.send(LinkEvent::Result(r)).await;
                    }
                    Ok(Some(_)) => {}
                    Ok(None) if input_done && unacked.is_empty() => return Ok(()),
                    Ok(None) => break Broke::Transient("server ended the stream early".into()),
                    // The server gave the session up (a resumed session not found again
                    // in its stored world): stream on in a new session, resending what
                    // was not answered.
                    Err(status) if status.code() == Code::Aborted => {
                        tracing::warn!("{}: streaming on in a new session", status.message());
                        session_id.clear();
                        resume_secret.clear();
                        let _ = events.send(LinkEvent::Reconnected(0)).await;
                        break Broke::Transient(format!("{}: {}", status.code(), status.message()));
                    }
                    Err(status) => break classify(status),
                },
            }
        };
        match broke {
            Broke::Fatal(e) => return Err(e),
            Broke::Transient(why) => {
                failures += 1;
                tracing::warn!("stream to {at} broke ({why}); reconnecting");
            }
        }
    }
}

#[cfg(feature = "zenoh")]
pub fn start_zenoh(hello: pb::Hello, options: ZenohOptions) -> Link {
    let (frames_tx, frames_rx) = mpsc::channel(LINK_BUFFER);
    let (events_tx, events_rx) = mpsc::channel(LINK_BUFFER * 16);
    let task = tokio::spawn(run_zenoh(hello, options, frames_rx, events_tx));
    Link { frames: frames_tx, events: events_rx, task }
}

#[cfg(feature = "zenoh")]
async fn run_zenoh(
    hello: pb::Hello,
    options: ZenohOptions,
    mut frames_rx: mpsc::Receiver<pb::Frame>,
    events: mpsc::Sender<LinkEvent>,
) -> Result<(), ClientError> {
    use stillmap_proto::keys;
    use zenoh::qos::CongestionControl;

    let zerr = |what: &str| {
        let what = what.to_string();
        move |e: zenoh::Error| ClientError::Connect(format!("zenoh {what}: {e}"))
    };
    let session = open_zenoh(&options).await?;
    let robot = hello.robot_id.clone();
    let subscriber = session.declare_subscriber(keys::results(&robot)).await.map_err(zerr("subscribe"))?;
    let publisher =
        session.declare_publisher(keys::frames(&robot)).congestion_control(CongestionControl::Block).await.map_err(zerr("publisher"))?;
    let hello_bytes = zenoh_message(ClientMsg::Hello(hello.clone()), &hello);
    // Servers on one Zenoh network place each robot on one of them; when one leaves,
    // its robots belong to another. Every server leaving is heard here (where the
    // router lets the robot see the servers' tokens), and the robot says hello again
    // asking for its session back: its own server, still there, resumes it; a new one
    // opens a new session. Without the tokens, the new owner's FAILED_PRECONDITION
    // for the next frame does the same.
    let mut servers = match session.liveliness().declare_subscriber(keys::ALL_SERVERS).await {
        Ok(s) => Some(s),
        Err(e) => {
            tracing::warn!("not following the servers' liveliness ({e}): a move is noticed at the next frame");
            None
        }
    };

    let (mut accepted, _) = zenoh_hello(&publisher, &subscriber, &hello_bytes, options.timeout).await?;
    let _ = events.send(LinkEvent::Accepted(accepted.clone())).await;

    let ends = ZenohEnds { publisher: &publisher, subscriber: &subscriber, hello: &hello, events: &events, timeout: options.timeout };
    // Sequences sent whose result has not come back.
    let mut in_flight: VecDeque<u64> = VecDeque::new();
    // New sessions in a row without a result in between.
    let mut moves = 0u32;
    // Timeouts in a row while frames waited for their results.
    let mut stalls = 0u32;
    let mut input_done = false;
    loop {
        if input_done && in_flight.is_empty() {
            break;
        }
        tokio::select! {
            frame = frames_rx.recv(), if !input_done => match frame {
                Some(frame) => {
                    let sequence = frame.sequence;
                    publisher.put(zenoh_message(ClientMsg::Frame(frame), &hello)).await.map_err(zerr("put frame"))?;
                    in_flight.push_back(sequence);
                }
                None => input_done = true,
            },
            left = async { servers.as_ref()?.recv_async().await.ok() }, if servers.is_some() => {
                match left {
                    None => servers = None, // the subscriber closed: moves are noticed at the next frame
                    Some(sample) if sample.kind() == zenoh::sample::SampleKind::Delete => {
                        accepted = rejoin(&ends, &accepted, &mut in_flight, &mut moves).await?.0;
                    }
                    Some(_) => {}
                }
            }
            s = tokio::time::timeout(options.timeout, subscriber.recv_async()) => {
                let Ok(s) = s else {
                    if input_done {
                        return Err(ClientError::Protocol(format!("{} results did not arrive within {:?}", in_flight.len(), options.timeout)));
                    }
                    if in_flight.is_empty() {
                        continue;
                    }
                    // Frames wait and nothing came back for a whole timeout (the streamer
                    // sends no more while `max_in_flight` wait, so waiting on would never
                    // end): the server left before its liveliness token did, or stalled.
                    // The robot says hello again (its own server resumes the session,
                    // another takes it over), and gives up after MAX_ZENOH_STALLS in a row.
                    stalls += 1;
                    if stalls > MAX_ZENOH_STALLS {
                        return Err(ClientError::Protocol(format!(
                            "{} results did not arrive within {:?} (--timeout), {stalls} times in a row",
                            in_flight.len(),
                            options.timeout
                        )));
                    }
                    tracing::warn!("no result within {:?} while {} frames wait: saying hello again", options.timeout, in_flight.len());
                    match rejoin(&ends, &accepted, &mut in_flight, &mut moves).await {
                        Ok((again, answered)) => {
                            accepted = again;
                            // Results came back meanwhile: the server answers.
                            if answered {
                                stalls = 0;
                            }
                        }
                        // No server took the hello yet (a server that left may hold its
                        // liveliness token until Zenoh's lease ends): one more stall.
                        Err(ClientError::Connect(e)) => tracing::warn!("{e}"),
                        Err(e) => return Err(e),
                    }
                    continue;
                };
                let s = s.map_err(|e| ClientError::Connect(format!("zenoh results: {e}")))?;
                match pb::ServerMessage::decode(s.payload().to_bytes().as_ref()) {
                    Ok(pb::ServerMessage { msg: Some(Msg::Result(r)) }) => {
                        in_flight.retain(|&q| q != r.sequence);
                        moves = 0;
                        stalls = 0;
                        let _ = events.send(LinkEvent::Result(r)).await;
                    }
                    // The server that answers this robot now does not know it: the
                    // robot was placed on another server (one left or joined), or its
                    // session left memory. Ask for the session back.
                    Ok(pb::ServerMessage { msg: Some(Msg::Error(e)) }) if Code::from_i32(e.code) == Code::FailedPrecondition => {
                        tracing::warn!("{}: saying hello again", e.message);
                        accepted = rejoin(&ends, &accepted, &mut in_flight, &mut moves).await?.0;
                    }
                    // The server gave the session up (a resumed session not found again
                    // in its stored world): a new session. The same status answers the
                    // frames that were on their way to it: those name a session already
                    // left, and are passed over.
                    Ok(pb::ServerMessage { msg: Some(Msg::Error(e)) }) if Code::from_i32(e.code) == Code::Aborted => {
                        if about_session(&e, &accepted.session_id) {
                            tracing::warn!("{}: streaming on in a new session", e.message);
                            accepted = rejoin(&ends, &pb::SessionAccepted::default(), &mut in_flight, &mut moves).await?.0;
                        }
                    }
                    Ok(pb::ServerMessage { msg: Some(Msg::Error(e)) }) => {
                        return Err(ClientError::Server { code: Code::from_i32(e.code), message: e.message });
                    }
                    Ok(_) => {}
                    Err(e) => return Err(ClientError::Protocol(format!("undecodable result: {e}"))),
                }
            }
        }
    }
    drop(servers);
    drop(publisher);
    drop(subscriber);
    session.close().await.map_err(zerr("close"))?;
    Ok(())
}

/// Opens the robot's (or a tool's) Zenoh session from `options` and waits until a
/// server or router is connected, at most `options.timeout`.
#[cfg(feature = "zenoh")]
pub async fn open_zenoh(options: &ZenohOptions) -> Result<zenoh::Session, ClientError> {
    /// How often to check that the peer connection is up.
    const PEER_POLL: Duration = Duration::from_millis(20);

    let zerr = |what: &str| {
        let what = what.to_string();
        move |e: zenoh::Error| ClientError::Connect(format!("zenoh {what}: {e}"))
    };
    let config = match &options.config_file {
        Some(path) => {
            zenoh::Config::from_file(path).map_err(|e| ClientError::Usage(format!("zenoh config file {}: {e}", path.display())))?
        }
        None => {
            let mut config = zenoh::Config::default();
            let list = serde_json::to_string(&options.connect).unwrap_or_else(|_| "[]".into());
            for (key, value) in [
                ("mode", format!("{:?}", options.mode)),
                ("scouting/multicast/enabled", "false".to_string()),
                ("listen/endpoints", "[]".to_string()),
                ("connect/endpoints", list),
            ] {
                config.insert_json5(key, &value).map_err(zerr(key))?;
            }
            config
        }
    };
    let session = zenoh::open(config).await.map_err(zerr("open"))?;
    // Wait until the server (or router) is connected, so the hello is not published into the void.
    let deadline = tokio::time::Instant::now() + options.timeout;
    loop {
        let peers = session.info().peers_zid().await.count() + session.info().routers_zid().await.count();
        if peers > 0 {
            break;
        }
        if tokio::time::Instant::now() > deadline {
            return Err(ClientError::Connect(format!("no Zenoh peer reachable at {:?}", options.connect)));
        }
        tokio::time::sleep(PEER_POLL).await;
    }
    Ok(session)
}

/// A Zenoh robot's ends of its link: what [`rejoin`] needs besides the link's state.
#[cfg(feature = "zenoh")]
struct ZenohEnds<'a> {
    publisher: &'a zenoh::pubsub::Publisher<'a>,
    subscriber: &'a zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    hello: &'a pb::Hello,
    events: &'a mpsc::Sender<LinkEvent>,
    timeout: Duration,
}

/// Says hello again asking for `accepted`'s session back (a server left, or one that
/// does not know this robot answered it; an `accepted` without a session id: a new
/// session, the server gave the last one up). Its own server, still there, resumes it and
/// nothing is lost; a new owner opens a new session, and what was in flight is
/// reported lost, and so are frames a resumed session never received. Results that
/// arrive meanwhile are passed on (the bool: some did).
#[cfg(feature = "zenoh")]
async fn rejoin(
    link: &ZenohEnds<'_>,
    accepted: &pb::SessionAccepted,
    in_flight: &mut VecDeque<u64>,
    moves: &mut u32,
) -> Result<(pb::SessionAccepted, bool), ClientError> {
    let ZenohEnds { publisher, subscriber, hello, events, timeout } = link;
    // Judged before the hello: a result arriving meanwhile means a frame reached a
    // server since the last accept (so its repeated accept would not say restored).
    let nothing_sent = in_flight.is_empty();
    let resume =
        pb::Hello { resume_session_id: accepted.session_id.clone(), resume_secret: accepted.resume_secret.clone(), ..(*hello).clone() };
    let resume_bytes = zenoh_message(ClientMsg::Hello(resume), hello);
    let (again, meanwhile) = zenoh_hello(publisher, subscriber, &resume_bytes, *timeout).await?;
    let answered = !meanwhile.is_empty();
    for r in meanwhile {
        in_flight.retain(|&q| q != r.sequence);
        let _ = events.send(LinkEvent::Result(r)).await;
    }
    if again.restored && !same_restore(accepted, &again, *moves, nothing_sent) {
        // Resumed from the shared storage by a server that did not hold it: what was
        // in flight to the server that left is not answered.
        *moves += 1;
        if *moves > MAX_ZENOH_MOVES {
            return Err(ClientError::Protocol(format!("{} moves in a row without a result: giving up", *moves)));
        }
        tracing::warn!("this robot's server left: its session goes on on another server from its last committed keyframe");
        let lost: Vec<u64> = in_flight.drain(..).collect();
        if !lost.is_empty() {
            let _ = events.send(LinkEvent::Unanswered(lost)).await;
        }
        let _ = events.send(LinkEvent::Reconnected(*moves)).await;
    } else if !again.resumed {
        *moves += 1;
        if *moves > MAX_ZENOH_MOVES {
            return Err(ClientError::Protocol(format!("{} new sessions in a row without a result: giving up", *moves)));
        }
        tracing::warn!("this robot's session is on no live server: streaming on in a new session");
        let lost: Vec<u64> = in_flight.drain(..).collect();
        if !lost.is_empty() {
            let _ = events.send(LinkEvent::Unanswered(lost)).await;
        }
        let _ = events.send(LinkEvent::Reconnected(*moves)).await;
        let _ = events.send(LinkEvent::Accepted(again.clone())).await;
    } else {
        // Resumed where it was: frames sent after the last one the server received
        // never reached it, and the Zenoh link keeps no frame to send again.
        let received = again.last_received_sequence;
        let (kept, lost): (VecDeque<u64>, VecDeque<u64>) = in_flight.drain(..).partition(|&q| received.is_some_and(|r| q <= r));
        *in_flight = kept;
        if !lost.is_empty() {
            let _ = events.send(LinkEvent::Unanswered(lost.into())).await;
        }
    }
    Ok((again, answered))
}

/// Timeouts in a row without a result while frames wait, each followed by a hello
/// again, before a Zenoh link gives up.
#[cfg(feature = "zenoh")]
const MAX_ZENOH_STALLS: u32 = 2;

/// Whether a `restored` answer to a rejoin is the restore `accepted` already was,
/// answered again. A server answers a hello identical to the one that opened its link
/// with that open's accept until a frame reaches it (the robot may not have heard it),
/// so when the robot hears of one move twice (the new owner's FAILED_PRECONDITION,
/// then the old server's liveliness token leaving) the second rejoin is told
/// `restored` again. It is the same move when the session is the one just restored,
/// no result came since (`moves` > 0) and nothing was sent since (a frame would have
/// reached that server before the hello, and it would answer `restored: false`).
/// A move to a third server before any frame reached the second looks the same
/// and is counted once too (nothing was in flight to lose).
#[cfg(feature = "zenoh")]
fn same_restore(accepted: &pb::SessionAccepted, again: &pb::SessionAccepted, moves: u32, nothing_in_flight: bool) -> bool {
    moves > 0 && nothing_in_flight && accepted.restored && again.restored && again.session_id == accepted.session_id
}

/// Whether a status is about session `id`: its `session_id`, or for a server that
/// sends none (before it was in the contract), the id as a word of its message.
#[cfg(feature = "zenoh")]
fn about_session(status: &pb::RpcStatus, id: &str) -> bool {
    if status.session_id.is_empty() { names_session(&status.message, id) } else { !id.is_empty() && status.session_id == id }
}

/// Whether a server's message names session `id` (as a word: `robot-1` is not
/// named by a message about `robot-10`).
#[cfg(feature = "zenoh")]
fn names_session(message: &str, id: &str) -> bool {
    !id.is_empty() && message.split(|c: char| !(c.is_ascii_alphanumeric() || c == '-' || c == '_')).any(|word| word == id)
}

/// How often the hello is repeated until a server accepts it.
#[cfg(feature = "zenoh")]
const HELLO_RETRY: Duration = Duration::from_millis(500);

/// New sessions in a row, with no result in between, before a Zenoh robot gives up.
#[cfg(feature = "zenoh")]
const MAX_ZENOH_MOVES: u32 = 16;

/// Publishes the hello every [`HELLO_RETRY`] until a server accepts it; returns the
/// acceptance and the results that came in meanwhile (frames in flight when a
/// session is resumed). Replies to frames sent before it (`FAILED_PRECONDITION`: a
/// server that does not know this robot yet; `ABORTED`: the session the server gave
/// up) are passed over, an `UNAVAILABLE` (try again) waits for the next retry; any
/// other error ends the wait.
#[cfg(feature = "zenoh")]
async fn zenoh_hello(
    publisher: &zenoh::pubsub::Publisher<'_>,
    subscriber: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    hello_bytes: &[u8],
    timeout: Duration,
) -> Result<(pb::SessionAccepted, Vec<pb::FrameResult>), ClientError> {
    let zerr = |what: &'static str| move |e: zenoh::Error| ClientError::Connect(format!("zenoh {what}: {e}"));
    let deadline = tokio::time::Instant::now() + timeout;
    let mut results = Vec::new();
    loop {
        publisher.put(hello_bytes.to_vec()).await.map_err(zerr("put hello"))?;
        let wait = tokio::time::sleep(HELLO_RETRY);
        tokio::pin!(wait);
        loop {
            tokio::select! {
                s = subscriber.recv_async() => {
                    let s = s.map_err(|e| ClientError::Connect(format!("zenoh results: {e}")))?;
                    match pb::ServerMessage::decode(s.payload().to_bytes().as_ref()) {
                        Ok(pb::ServerMessage { msg: Some(Msg::Accepted(a)) }) => return Ok((a, results)),
                        Ok(pb::ServerMessage { msg: Some(Msg::Result(r)) }) => results.push(r),
                        // Replies to frames sent before it: a server that does not know
                        // this robot yet, or the session the server gave up.
                        Ok(pb::ServerMessage { msg: Some(Msg::Error(e)) })
                            if matches!(Code::from_i32(e.code), Code::FailedPrecondition | Code::Aborted) => {}
                        // Not now: the session is being handed over from the server
                        // the robot was on, or resumed by another server. The hello
                        // is said again at the next retry, until the timeout.
                        Ok(pb::ServerMessage { msg: Some(Msg::Error(e)) }) if Code::from_i32(e.code) == Code::Unavailable => {
                            tracing::info!("{}", e.message);
                        }
                        Ok(pb::ServerMessage { msg: Some(Msg::Error(e)) }) => {
                            return Err(ClientError::Server { code: Code::from_i32(e.code), message: e.message });
                        }
                        _ => {}
                    }
                }
                _ = &mut wait => break,
            }
        }
        if tokio::time::Instant::now() > deadline {
            return Err(ClientError::Connect(format!("the server did not accept the hello within {timeout:?}")));
        }
    }
}

#[cfg(all(test, feature = "zenoh"))]
mod tests {
    use super::*;

    /// An ABORTED starts a new session only when it names the robot's session as a
    /// word: the late replies about a session already left do not.
    #[test]
    fn a_message_names_a_session_as_a_word() {
        let message = "session robot-1-6b2a-3 was not found again in its stored world within session.resume_find_s: open a new session";
        assert!(names_session(message, "robot-1-6b2a-3"));
        assert!(!names_session(message, "robot-1-6b2a"), "a prefix is another session");
        assert!(!names_session(message, "robot-1-6b2a-30"));
        assert!(!names_session(message, ""), "no session yet");
    }

    /// One move heard twice (a FAILED_PRECONDITION, then the liveliness token) is
    /// counted once; a restore after a result, with frames in flight, of another
    /// session or after a resume that was not a restore is a move of its own.
    #[test]
    fn a_restore_answered_again_is_the_same_move() {
        let accept =
            |id: &str, restored: bool| pb::SessionAccepted { session_id: id.into(), resumed: true, restored, ..Default::default() };
        let (restored, again) = (accept("r-1a-1", true), accept("r-1a-1", true));
        assert!(same_restore(&restored, &again, 1, true));
        assert!(!same_restore(&restored, &again, 0, true), "a result came since: a new move");
        assert!(!same_restore(&restored, &again, 1, false), "frames were sent since: a new move");
        assert!(!same_restore(&restored, &accept("r-1a-2", true), 1, true), "another session");
        assert!(!same_restore(&accept("r-1a-1", false), &again, 1, true), "the last accept was no restore");
        assert!(!same_restore(&restored, &accept("r-1a-1", false), 1, true), "not restored now");
    }

    /// A status that names its session (`session_id`) is judged by it alone; one
    /// from a server that sends none, by its message.
    #[test]
    fn a_status_is_about_the_session_it_names() {
        let status = |session_id: &str, message: &str| pb::RpcStatus {
            code: Code::Aborted as i32,
            message: message.into(),
            session_id: session_id.into(),
        };
        assert!(about_session(&status("r-1a-2", "given up"), "r-1a-2"));
        assert!(!about_session(&status("r-1a-1", "session r-1a-2 given up"), "r-1a-2"), "the field, not the text");
        assert!(!about_session(&status("r-1a-2", "given up"), ""), "no session yet");
        assert!(about_session(&status("", "session r-1a-2 given up"), "r-1a-2"), "an older server: the text");
    }
}
