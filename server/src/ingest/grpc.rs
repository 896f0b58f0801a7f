//! gRPC ingest: the `Ingest` stream (hello, then frames; results back in order).

use std::pin::Pin;
use std::sync::Arc;

use futures_util::Stream;
use prost::Message;
use stillmap_proto::pb::{self, client_message::Msg as ClientMsg, ingest_server::Ingest};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

use super::{accepted_message, frame_before_hello, refusal};
use crate::session::{Registry, ResultSink, Session, Transport};

/// Where robots stream among servers (`cluster::Placer` on Zenoh).
#[tonic::async_trait]
pub trait Placement: Send + Sync {
    /// The server robots placed by `key` (`stillmap_proto::placement_key`) belong
    /// to among the live ones, and its advertised gRPC address (empty: stream here).
    async fn place(&self, key: &str) -> Result<pb::Placement, Status>;
    /// Hears of every change of the live servers.
    fn changes(&self) -> tokio::sync::watch::Receiver<u64>;
    /// This server's id (a placement naming it: stream here).
    fn here(&self) -> &str;
}

/// Resolves when a robot that follows placement (`Hello.follows_placement`) and
/// streams here belongs to another server that robots can reach (a server joined),
/// with that server's placement; never without a cluster or for other robots.
async fn moved_away(placement: Option<Arc<dyn Placement>>, hello: &pb::Hello) -> pb::Placement {
    let Some(placement) = placement.filter(|_| hello.follows_placement) else { return std::future::pending().await };
    let key = stillmap_proto::placement_key(&hello.robot_id, &hello.fleet);
    let mut changes = placement.changes();
    let mut ask_again = false;
    loop {
        // A server that has just joined may not answer its status yet: asked again
        // shortly, not only at the next change.
        let changed = if ask_again {
            tokio::select! {
                changed = changes.changed() => changed,
                () = tokio::time::sleep(MOVED_ASK_AGAIN) => Ok(()),
            }
        } else {
            changes.changed().await
        };
        if changed.is_err() {
            return std::future::pending().await;
        }
        // Only an owner with an address robots can reach takes the robot (an empty
        // one: stream here, as Place answers).
        match placement.place(&key).await {
            Ok(p) if !p.grpc_address.is_empty() && placement.here() != p.server_id => return p,
            Ok(_) => ask_again = false,
            Err(_) => ask_again = true,
        }
    }
}

/// How soon a robot's placement is asked again when its owner did not answer.
const MOVED_ASK_AGAIN: std::time::Duration = std::time::Duration::from_secs(1);

pub struct IngestService {
    /// Servers on one Zenoh network (none: a single server, robots stream here).
    pub placement: Option<Arc<dyn Placement>>,
    pub registry: Arc<Registry>,
    pub auth: Arc<crate::auth::AuthHandle>,
    pub rate_limits: Arc<crate::ratelimit::RateLimits>,
    pub result_buffer: usize,
    pub max_message_bytes: usize,
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

impl IngestService {
    /// Counts a hello from the request's peer address; RESOURCE_EXHAUSTED over the limit.
    fn count_hello<T>(&self, request: &Request<T>) -> Result<(), Status> {
        let client = request.remote_addr().map_or_else(|| "an unknown address".to_string(), |a| a.ip().to_string());
        self.rate_limits.hello(&client).map_err(|message| {
            self.registry.metrics().rejected("rate_limited");
            Status::resource_exhausted(message)
        })
    }
}

#[tonic::async_trait]
impl Ingest for IngestService {
    type StreamStream = BoxStream<pb::ServerMessage>;

    async fn place(&self, request: Request<pb::Hello>) -> Result<Response<pb::Placement>, Status> {
        // The first step of a stream: counted with the hellos.
        self.count_hello(&request)?;
        let hello = request.into_inner();
        stillmap_proto::validate_robot_id(&hello.robot_id).map_err(Status::invalid_argument)?;
        if !hello.fleet.is_empty() {
            stillmap_proto::validate_fleet(&hello.fleet).map_err(Status::invalid_argument)?;
        }
        self.auth.get().check_hello(&hello).inspect_err(|_| self.registry.metrics().rejected("unauthenticated"))?;
        match &self.placement {
            None => Ok(Response::new(pb::Placement::default())),
            Some(p) => p.place(&stillmap_proto::placement_key(&hello.robot_id, &hello.fleet)).await.map(Response::new),
        }
    }

    async fn stream(&self, request: Request<Streaming<pb::ClientMessage>>) -> Result<Response<Self::StreamStream>, Status> {
        // Every stream opens with a hello.
        self.count_hello(&request)?;
        let inbound = request.into_inner();
        let (tx, rx) = mpsc::channel(self.result_buffer);
        let registry = self.registry.clone();
        let auth = self.auth.clone();
        let max = self.max_message_bytes;
        let placement = self.placement.clone();
        tokio::spawn(async move {
            if let Err(status) = serve_stream(inbound, registry, &auth, placement, tx.clone(), max).await {
                let _ = tx.send(Err(status)).await;
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// Runs one ingest connection; an `Err` ends the stream with that status.
async fn serve_stream(
    mut inbound: Streaming<pb::ClientMessage>,
    registry: Arc<Registry>,
    auth: &crate::auth::AuthHandle,
    placement: Option<Arc<dyn Placement>>,
    sink: ResultSink,
    max_message_bytes: usize,
) -> Result<(), Status> {
    let metrics = registry.metrics().clone();
    let hello = match inbound.message().await.map_err(|s| oversized_as_resource_exhausted(s, &metrics))? {
        None => return Ok(()),
        Some(pb::ClientMessage { msg: Some(ClientMsg::Hello(hello)), .. }) => hello,
        Some(pb::ClientMessage { msg: Some(ClientMsg::Frame(frame)), .. }) => {
            metrics.rejected("no_hello");
            return Err(frame_before_hello(frame.sequence));
        }
        Some(pb::ClientMessage { msg: None, .. }) => {
            metrics.rejected("malformed");
            return Err(Status::invalid_argument("empty client message: expected a hello"));
        }
    };
    auth.get().check_hello(&hello).inspect_err(|_| metrics.rejected("unauthenticated"))?;
    // A resume that reads the shared storage blocks on PostgreSQL: off the runtime.
    let opened = if registry.reads_replica(&hello) {
        let (registry, hello, sink) = (registry.clone(), hello.clone(), sink.clone());
        tokio::task::spawn_blocking(move || registry.open(&hello, Transport::Grpc, sink))
            .await
            .map_err(|e| Status::internal(format!("opening the session failed: {e}")))?
    } else {
        registry.open(&hello, Transport::Grpc, sink.clone())
    }
    .map_err(|e| refusal(&e, &metrics))?;
    let session = opened.session.clone();
    sink.send(Ok(accepted_message(&opened, max_message_bytes))).await.map_err(|_| Status::cancelled("client went away"))?;
    // A robot that follows placement and now belongs to another server (one joined)
    // is sent there: its stream ends, and its session is handed over.
    let (outcome, moved) = tokio::select! {
        outcome = read_frames(&mut inbound, &session, &metrics) => (outcome, false),
        to = moved_away(placement, &hello) => {
            tracing::info!(session = %session.id, robot = hello.robot_id, server = to.server_id, "robot placed on another server: sent there");
            let message = format!(
                "robot {} belongs to server {} now (a server joined): ask where to stream (Ingest.Place) and resume session {} there",
                hello.robot_id, to.server_id, session.id
            );
            (Err(Status::unavailable(message)), true)
        }
    };
    if outcome.is_ok() {
        // The client finished sending: answer everything it sent before closing.
        session.drained().await;
    }
    session.detach(&sink);
    if moved {
        super::hand_over(registry, session.id.clone());
    }
    outcome
}

async fn read_frames(
    inbound: &mut Streaming<pb::ClientMessage>,
    session: &Session,
    metrics: &crate::metrics::Metrics,
) -> Result<(), Status> {
    loop {
        let message = match inbound.message().await {
            Ok(Some(m)) => m,
            Ok(None) => return Ok(()),
            Err(status) => return Err(oversized_as_resource_exhausted(status, metrics)),
        };
        // Counted as the whole message, as on Zenoh.
        let len = message.encoded_len();
        match message.msg {
            Some(ClientMsg::Frame(frame)) => {
                session.push(frame, len).map_err(|e| session.refusal_of(e))?;
            }
            Some(ClientMsg::Hello(_)) => {
                metrics.rejected("malformed");
                return Err(Status::failed_precondition("a second hello on an open session"));
            }
            None => {
                metrics.rejected("malformed");
                return Err(Status::invalid_argument("empty client message: expected a frame"));
            }
        }
    }
}

/// tonic reports a message above `max_decoding_message_size` as OUT_OF_RANGE; the
/// contract promises RESOURCE_EXHAUSTED, with the sizes in the message.
fn oversized_as_resource_exhausted(status: Status, metrics: &crate::metrics::Metrics) -> Status {
    const TONIC_TOO_LARGE: &str = "decoded message length too large";
    if status.code() == tonic::Code::OutOfRange && status.message().contains(TONIC_TOO_LARGE) {
        metrics.rejected("oversized");
        let detail = status.message().trim_start_matches("Error, ");
        return Status::resource_exhausted(format!("message too large: {detail}"));
    }
    status
}
