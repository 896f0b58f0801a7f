//! gRPC shell: the `Ingest` stream and the `Query` service over the registry.

use std::pin::Pin;
use std::sync::Arc;

use futures_util::Stream;
use prost::Message;
use stillmap_proto::pb::{self, client_message::Msg as ClientMsg, ingest_server::Ingest, query_server::Query};
use tokio::sync::mpsc;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::{BroadcastStream, ReceiverStream};
use tonic::{Request, Response, Status, Streaming};

use crate::queue::QueueError;
use crate::session::{BadHello, Registry, ResultSink, Session, Transport, accepted_message, summary};

pub struct IngestService {
    pub registry: Arc<Registry>,
    pub tokens: Arc<crate::auth::Tokens>,
    pub result_buffer: usize,
    pub max_message_bytes: usize,
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

/// Status for a frame that arrived before any hello.
pub fn frame_before_hello(sequence: u64) -> Status {
    Status::failed_precondition(format!(
        "frame {sequence} arrived before the hello: the first message of a session must be a hello"
    ))
}

/// Status for a queue that can no longer take frames.
pub fn queue_status(e: QueueError) -> Status {
    match e {
        QueueError::Overloaded(_) => Status::resource_exhausted(e.to_string()),
        QueueError::Closed => Status::unavailable("the server is shutting down"),
    }
}

#[tonic::async_trait]
impl Ingest for IngestService {
    type StreamStream = BoxStream<pb::ServerMessage>;

    async fn stream(&self, request: Request<Streaming<pb::ClientMessage>>) -> Result<Response<Self::StreamStream>, Status> {
        let inbound = request.into_inner();
        let (tx, rx) = mpsc::channel(self.result_buffer);
        let registry = self.registry.clone();
        let tokens = self.tokens.clone();
        let max = self.max_message_bytes;
        tokio::spawn(async move {
            if let Err(status) = serve_stream(inbound, &registry, &tokens, tx.clone(), max).await {
                let _ = tx.send(Err(status)).await;
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// Runs one ingest connection; an `Err` ends the stream with that status.
async fn serve_stream(
    mut inbound: Streaming<pb::ClientMessage>,
    registry: &Registry,
    tokens: &crate::auth::Tokens,
    sink: ResultSink,
    max_message_bytes: usize,
) -> Result<(), Status> {
    let metrics = registry.metrics().clone();
    let hello = match inbound.message().await? {
        None => return Ok(()),
        Some(pb::ClientMessage { msg: Some(ClientMsg::Hello(hello)) }) => hello,
        Some(pb::ClientMessage { msg: Some(ClientMsg::Frame(frame)) }) => {
            metrics.rejected("no_hello");
            return Err(frame_before_hello(frame.sequence));
        }
        Some(pb::ClientMessage { msg: None }) => {
            metrics.rejected("malformed");
            return Err(Status::invalid_argument("empty client message: expected a hello"));
        }
    };
    tokens.check(&hello).inspect_err(|_| metrics.rejected("unauthenticated"))?;
    let opened = registry
        .open(&hello, Transport::Grpc, sink.clone())
        .map_err(|e| {
            if matches!(e, BadHello::Full { .. }) {
                metrics.rejected("server_full");
            }
            e.status()
        })?;
    let session = opened.session.clone();
    sink.send(Ok(accepted_message(&opened, max_message_bytes)))
        .await
        .map_err(|_| Status::cancelled("client went away"))?;
    let outcome = read_frames(&mut inbound, &session, &metrics).await;
    if outcome.is_ok() {
        // The client finished sending: answer everything it sent before closing.
        session.drained().await;
    }
    session.detach(&sink);
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
                session.push(frame, len).map_err(queue_status)?;
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

pub struct QueryService {
    pub registry: Arc<Registry>,
}

impl QueryService {
    fn session(&self, id: &str) -> Result<Arc<Session>, Status> {
        self.registry.get(id).ok_or_else(|| Status::not_found(format!("unknown session {id:?}")))
    }

    fn map(&self, id: &str) -> Result<crate::mapping::SharedMap, Status> {
        self.session(id)?.map().cloned().ok_or_else(|| Status::not_found(format!("session {id:?} has no map (mapping is disabled)")))
    }
}

#[tonic::async_trait]
impl Query for QueryService {
    type SubscribePosesStream = BoxStream<pb::PoseStamped>;
    type GetMapCloudStream = BoxStream<pb::MapCloudChunk>;

    async fn list_sessions(&self, _: Request<pb::ListSessionsRequest>) -> Result<Response<pb::ListSessionsResponse>, Status> {
        let sessions = self.registry.list().iter().map(|s| summary(s)).collect();
        Ok(Response::new(pb::ListSessionsResponse { sessions }))
    }

    async fn get_latest_pose(&self, request: Request<pb::SessionRef>) -> Result<Response<pb::LatestPose>, Status> {
        let session = self.session(&request.get_ref().session_id)?;
        let track = session.tracking();
        Ok(Response::new(pb::LatestPose { tracking_state: track.state as i32, pose: track.latest }))
    }

    async fn get_trajectory(&self, request: Request<pb::TrajectoryRequest>) -> Result<Response<pb::Trajectory>, Status> {
        let r = request.get_ref();
        let session = self.session(&r.session_id)?;
        let end = if r.end_ns == 0 { u64::MAX } else { r.end_ns };
        if r.start_ns > end {
            return Err(Status::invalid_argument(format!("start_ns {} is after end_ns {}", r.start_ns, r.end_ns)));
        }
        let poses = session
            .tracking()
            .trajectory
            .iter()
            .filter(|p| (r.start_ns..=end).contains(&p.capture_time_ns))
            .cloned()
            .collect();
        Ok(Response::new(pb::Trajectory { poses }))
    }

    async fn subscribe_poses(&self, request: Request<pb::SessionRef>) -> Result<Response<Self::SubscribePosesStream>, Status> {
        let session = self.session(&request.get_ref().session_id)?;
        // A lagging subscriber skips poses rather than holding the pipeline.
        let stream = BroadcastStream::new(session.subscribe_poses()).filter_map(|r| r.ok().map(Ok));
        Ok(Response::new(Box::pin(stream)))
    }

    async fn get_map_tile(&self, request: Request<pb::MapTileRequest>) -> Result<Response<pb::MapTile>, Status> {
        let r = request.into_inner();
        let map = self.map(&r.session_id)?;
        let zoom = u8::try_from(r.zoom).map_err(|_| Status::invalid_argument(format!("zoom {} is out of range 0..={}", r.zoom, stillmap_mapping::tiles::MAX_ZOOM)))?;
        let tile = tokio::task::spawn_blocking(move || crate::mapping::tile(&map, zoom, r.x, r.y))
            .await
            .map_err(|e| Status::internal(format!("map query failed: {e}")))?
            .map_err(|e| Status::invalid_argument(e.0))?;
        Ok(Response::new(pb::MapTile { png: tile.png, etag: tile.etag }))
    }

    async fn get_map_cloud(&self, request: Request<pb::MapCloudRequest>) -> Result<Response<Self::GetMapCloudStream>, Status> {
        let r = request.into_inner();
        let map = self.map(&r.session_id)?;
        let bbox = match r.bbox {
            None => None,
            Some(b) => {
                let (lo, hi) = (b.min.unwrap_or_default(), b.max.unwrap_or_default());
                let text = format!("{},{},{},{},{},{}", lo.x, lo.y, lo.z, hi.x, hi.y, hi.z);
                Some(crate::mapping::parse_bbox(&text).map_err(|e| Status::invalid_argument(e.0))?)
            }
        };
        let (points, names) = tokio::task::spawn_blocking(move || crate::mapping::points(&map, bbox.as_ref()))
            .await
            .map_err(|e| Status::internal(format!("map query failed: {e}")))?;
        let mut chunks: Vec<Result<pb::MapCloudChunk, Status>> = points
            .chunks(CLOUD_CHUNK_POINTS)
            .map(|c| {
                Ok(pb::MapCloudChunk {
                    xyz: c.iter().flat_map(|p| p.point_in_map).collect(),
                    rgb: c.iter().flat_map(|p| p.rgb).collect(),
                    class_id: c.iter().map(|p| u32::from(p.class)).collect(),
                    confidence: c.iter().map(|p| p.confidence).collect(),
                    class_names: vec![],
                })
            })
            .collect();
        match chunks.first_mut() {
            Some(Ok(first)) => first.class_names = names,
            _ => chunks.push(Ok(pb::MapCloudChunk { class_names: names, ..Default::default() })),
        }
        Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
    }
}

/// Points per `MapCloudChunk` (≈ 1.4 MB: well under the default message limit).
const CLOUD_CHUNK_POINTS: usize = 65536;
