//! gRPC queries: the `Query` service (sessions, poses, trajectories, map products)
//! over the registry. In a cluster, the unary queries about a session or a fleet
//! this server does not hold are asked of the other servers ([`Remote`]), the
//! sessions list is every server's, and the subscriptions follow the other
//! servers' live poses (`RemoteLive`).

use std::pin::Pin;
use std::sync::Arc;

use futures_util::Stream;
use prost::Message as _;
use stillmap_proto::pb::{self, query_server::Query};
use tokio_stream::StreamExt;
use tokio_stream::wrappers::BroadcastStream;
use tonic::{Request, Response, Status};

use crate::session::{Registry, Session};

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

/// The queries other servers answer for sessions and fleets this one does not hold
/// (`cluster::Forwarder` on Zenoh). `GetMapCloud`'s chunks come back together
/// (length-delimited), and are streamed from here; `SubscribePoses` and
/// `SubscribeFleetPoses` follow the other servers' live poses instead (`RemoteLive`).
pub const FORWARDED_METHODS: [&str; 6] = ["ListSessions", "GetLatestPose", "GetTrajectory", "GetMapTile", "GetMapCloud", "GetFleetPoses"];

/// The other servers of a cluster, asked what this one does not hold.
#[tonic::async_trait]
pub trait Remote: Send + Sync {
    /// The answer of the other server holding what the query is about (the encoded
    /// response message, or its status); UNAVAILABLE when none holds it and some
    /// server did not answer; `None` when every other server answered and none holds it.
    async fn call(&self, method: &'static str, request: Vec<u8>, authorization: Option<String>) -> Option<Result<Vec<u8>, Status>>;
    /// Every other server's successful answer.
    async fn gather(&self, method: &'static str, request: Vec<u8>, authorization: Option<String>) -> Vec<Vec<u8>>;
}

pub struct QueryService {
    pub registry: Arc<Registry>,
    /// The other servers (none: a single server, or the side answering a forwarded query).
    pub remote: Option<Arc<dyn Remote>>,
    /// The other servers' live poses (`SubscribePoses` of a session another server holds).
    pub remote_live: Option<Arc<dyn crate::api::RemoteLive>>,
}

fn authorization<T>(request: &Request<T>) -> Option<String> {
    request.metadata().get("authorization").and_then(|v| v.to_str().ok()).map(str::to_owned)
}

impl QueryService {
    async fn session(&self, id: &str) -> Result<Arc<Session>, Status> {
        self.registry.get_off_runtime(id).await.ok_or_else(|| Self::unknown(id))
    }

    fn unknown(id: &str) -> Status {
        Status::not_found(format!("unknown session {id:?}"))
    }

    /// `request` about session `id`, which this server does not hold, asked of the other servers.
    async fn forwarded<Q: prost::Message, R: prost::Message + Default>(
        &self,
        method: &'static str,
        id: &str,
        request: &Request<Q>,
    ) -> Result<Response<R>, Status> {
        self.forwarded_else(method, request, || Self::unknown(id)).await
    }

    /// `request`, about something this server does not hold, asked of the other
    /// servers; `missing` when none holds it.
    async fn forwarded_else<Q: prost::Message, R: prost::Message + Default>(
        &self,
        method: &'static str,
        request: &Request<Q>,
        missing: impl FnOnce() -> Status,
    ) -> Result<Response<R>, Status> {
        let bytes = self.forwarded_bytes(method, request, missing).await?;
        R::decode(bytes.as_slice()).map(Response::new).map_err(|e| Status::internal(format!("another server's answer: {e}")))
    }

    /// The encoded answer of the server holding what `request` is about; `missing`
    /// when none holds it.
    async fn forwarded_bytes<Q: prost::Message>(
        &self,
        method: &'static str,
        request: &Request<Q>,
        missing: impl FnOnce() -> Status,
    ) -> Result<Vec<u8>, Status> {
        let Some(remote) = &self.remote else { return Err(missing()) };
        match remote.call(method, request.get_ref().encode_to_vec(), authorization(request)).await {
            Some(answer) => answer,
            None => Err(missing()),
        }
    }

    /// Whether this server holds what a forwarded query (`method`, `request` its
    /// encoded message) is about: the session or fleet it names (the sessions list:
    /// always).
    pub fn holds(&self, method: &str, request: &[u8]) -> bool {
        if method == "GetFleetPoses" {
            return pb::FleetRef::decode(request).is_ok_and(|r| self.registry.fleets().is_some_and(|f| f.holds(&r.fleet)));
        }
        let session_id = match method {
            "GetLatestPose" => pb::SessionRef::decode(request).map(|r| r.session_id),
            "GetTrajectory" => pb::TrajectoryRequest::decode(request).map(|r| r.session_id),
            "GetMapTile" => pb::MapTileRequest::decode(request).map(|r| r.session_id),
            "GetMapCloud" => pb::MapCloudRequest::decode(request).map(|r| r.session_id),
            _ => return method == "ListSessions",
        };
        session_id.is_ok_and(|id| self.registry.info(&id).is_some())
    }

    /// Answers a unary query forwarded by another server (`method` one of
    /// [`FORWARDED_METHODS`], `request` its encoded message), as this server alone.
    pub async fn answer(&self, method: &str, request: &[u8]) -> Result<Vec<u8>, Status> {
        fn decode<M: prost::Message + Default>(bytes: &[u8]) -> Result<Request<M>, Status> {
            M::decode(bytes).map(Request::new).map_err(|e| Status::invalid_argument(format!("forwarded request: {e}")))
        }
        fn encoded_of<M: prost::Message>(response: &Response<M>) -> Vec<u8> {
            response.get_ref().encode_to_vec()
        }
        match method {
            "ListSessions" => self.list_sessions(decode(request)?).await.map(|r| encoded_of(&r)),
            "GetLatestPose" => self.get_latest_pose(decode(request)?).await.map(|r| encoded_of(&r)),
            "GetTrajectory" => self.get_trajectory(decode(request)?).await.map(|r| encoded_of(&r)),
            "GetMapTile" => self.get_map_tile(decode(request)?).await.map(|r| encoded_of(&r)),
            "GetFleetPoses" => self.get_fleet_poses(decode(request)?).await.map(|r| encoded_of(&r)),
            "GetMapCloud" => {
                // Every chunk, length-delimited, in one answer.
                let mut chunks = self.get_map_cloud(decode(request)?).await?.into_inner();
                let mut out = Vec::new();
                while let Some(chunk) = chunks.next().await {
                    chunk?.encode_length_delimited(&mut out).map_err(|e| Status::internal(format!("map cloud: {e}")))?;
                }
                Ok(out)
            }
            other => Err(Status::unimplemented(format!("{other} is not forwarded between servers"))),
        }
    }

    fn fleet(&self, name: &str) -> Result<(Arc<crate::fleet::FleetService>, crate::fleet::FleetView), Status> {
        // A name no hello could give is refused before it is looked up or forwarded.
        stillmap_proto::validate_fleet(name).map_err(|e| Status::invalid_argument(format!("fleet: {e}")))?;
        let fleets = self.registry.fleets().ok_or_else(|| Status::not_found("fleets are off on this server (fleet.enabled)"))?;
        let fleet = fleets.get(name).ok_or_else(|| Status::not_found(format!("unknown fleet {name:?}")))?;
        Ok((fleets.clone(), fleet))
    }

    async fn map(&self, id: &str) -> Result<crate::map::SharedMap, Status> {
        self.session(id).await?.map().cloned().ok_or_else(|| Status::not_found(format!("session {id:?} has no map (mapping is disabled)")))
    }
}

#[tonic::async_trait]
impl Query for QueryService {
    type SubscribePosesStream = BoxStream<pb::PoseStamped>;
    type GetMapCloudStream = BoxStream<pb::MapCloudChunk>;
    type SubscribeFleetPosesStream = BoxStream<pb::FleetPose>;

    async fn get_fleet_poses(&self, request: Request<pb::FleetRef>) -> Result<Response<pb::FleetPoses>, Status> {
        let (fleets, fleet) = match self.fleet(&request.get_ref().fleet) {
            Ok(held) => held,
            // Held by another server (a named fleet's robots are all on one), or by none.
            Err(missing) if missing.code() == tonic::Code::NotFound => {
                return self.forwarded_else("GetFleetPoses", &request, || missing).await;
            }
            Err(refused) => return Err(refused),
        };
        let mut out = pb::FleetPoses::default();
        for m in &fleet.members {
            let Some(to_fleet) = fleets.fleet_transform(&fleet.name, &m.session_id) else {
                out.unmerged_session_ids.push(m.session_id.clone());
                continue;
            };
            // The latest pose alone: a stored member's info holds it, without
            // loading its map and trajectory back into memory.
            if let Some(p) = self.registry.info(&m.session_id).and_then(|i| i.latest) {
                out.poses.push(pb::FleetPose {
                    session_id: m.session_id.clone(),
                    robot_id: m.robot_id.clone(),
                    pose: Some(crate::convert::pose_in(&p, &to_fleet.at(p.capture_time_ns))),
                });
            }
        }
        Ok(Response::new(out))
    }

    async fn subscribe_fleet_poses(&self, request: Request<pb::FleetRef>) -> Result<Response<Self::SubscribeFleetPosesStream>, Status> {
        let (fleets, fleet) = match (self.fleet(&request.get_ref().fleet), &self.remote_live) {
            (Ok(held), _) => held,
            // Held by another server: its poses in the fleet's frame come over Zenoh
            // (relay.rs), from the holder's next tick on, once some server holds it.
            (Err(missing), Some(live)) if missing.code() == tonic::Code::NotFound => {
                let watching = live.watch();
                let poses = live.subscribe_fleet_poses();
                self.forwarded_else::<_, pb::FleetPoses>("GetFleetPoses", &request, || missing).await?;
                let name = request.into_inner().fleet;
                let stream = BroadcastStream::new(poses).filter_map(move |r| {
                    let _counted = &watching;
                    r.ok().filter(|(fleet, _)| **fleet == *name).map(|(_, pose)| Ok(pose))
                });
                return Ok(Response::new(Box::pin(stream)));
            }
            (Err(refused), _) => return Err(refused),
        };
        let registry = self.registry.clone();
        let name = fleet.name;
        // A lagging subscriber skips poses rather than holding the pipeline.
        let stream = BroadcastStream::new(self.registry.subscribe_fleet()).filter_map(move |r| {
            let (session_id, pose) = r.ok()?;
            let session = registry.get(&session_id).filter(|s| s.fleet_name == name)?;
            let to_fleet = fleets.fleet_transform(&name, &session_id)?;
            Some(Ok(pb::FleetPose {
                session_id: session_id.to_string(),
                robot_id: session.robot_id.clone(),
                pose: Some(crate::convert::pose_in(&pose, &to_fleet.at(pose.capture_time_ns))),
            }))
        });
        Ok(Response::new(Box::pin(stream)))
    }

    /// This server's sessions, then every other live server's.
    /// A page of every server's sessions merged: each server answers its first
    /// `page_size` after the token, so the merged list's first `page_size` are
    /// among them.
    async fn list_sessions(&self, request: Request<pb::ListSessionsRequest>) -> Result<Response<pb::ListSessionsResponse>, Status> {
        let page = crate::api::http::ListQuery {
            limit: Some(match request.get_ref().page_size {
                0 => crate::session::DEFAULT_SESSIONS_PAGE,
                n => usize::try_from(n).unwrap_or(usize::MAX),
            }),
            page_token: Some(request.get_ref().page_token.clone()),
        };
        let (after, limit) = page.checked().map_err(Status::invalid_argument)?;
        let registry = self.registry.clone();
        let (listed, next) = tokio::task::spawn_blocking(move || registry.list_page(after.as_ref(), limit))
            .await
            .map_err(|_| Status::internal("the sessions list failed"))?;
        let mut sessions: Vec<pb::SessionSummary> = listed.into_iter().map(|s| s.summary).collect();
        let mut more = next.is_some();
        if let Some(remote) = &self.remote {
            for answer in remote.gather("ListSessions", request.get_ref().encode_to_vec(), authorization(&request)).await {
                match pb::ListSessionsResponse::decode(answer.as_slice()) {
                    Ok(theirs) => {
                        more |= !theirs.next_page_token.is_empty();
                        sessions.extend(theirs.sessions);
                    }
                    Err(e) => tracing::warn!("another server's sessions list is not a ListSessionsResponse: {e}"),
                }
            }
            sessions.sort_by_cached_key(crate::session::ListCursor::of);
            more |= sessions.len() > limit;
            sessions.truncate(limit);
        }
        let next_page_token = match sessions.last() {
            Some(last) if more => crate::session::ListCursor::of(last).token(),
            _ => String::new(),
        };
        Ok(Response::new(pb::ListSessionsResponse { sessions, next_page_token }))
    }

    async fn get_latest_pose(&self, request: Request<pb::SessionRef>) -> Result<Response<pb::LatestPose>, Status> {
        let id = &request.get_ref().session_id;
        let Some(session) = self.registry.get_off_runtime(id).await else { return self.forwarded("GetLatestPose", id, &request).await };
        let track = session.tracking();
        Ok(Response::new(pb::LatestPose { tracking_state: track.state as i32, pose: track.latest }))
    }

    async fn get_trajectory(&self, request: Request<pb::TrajectoryRequest>) -> Result<Response<pb::Trajectory>, Status> {
        let r = request.get_ref();
        let Some(session) = self.registry.get_off_runtime(&r.session_id).await else {
            return self.forwarded("GetTrajectory", &r.session_id, &request).await;
        };
        let end = if r.end_ns == 0 { u64::MAX } else { r.end_ns };
        if r.start_ns > end {
            return Err(Status::invalid_argument(format!("start_ns {} is after end_ns {}", r.start_ns, r.end_ns)));
        }
        let limit = match r.limit as usize {
            0 => crate::session::DEFAULT_TRAJECTORY_PAGE,
            n if n > crate::session::MAX_TRAJECTORY_PAGE => {
                return Err(Status::invalid_argument(format!(
                    "limit {n} is over the {} poses one answer holds: page with start_ns",
                    crate::session::MAX_TRAJECTORY_PAGE
                )));
            }
            n => n,
        };
        let start_ns = r.start_ns;
        let (poses, next) = tokio::task::spawn_blocking(move || session.trajectory_page(start_ns, end, limit))
            .await
            .map_err(|e| Status::internal(format!("trajectory query failed: {e}")))?
            .map_err(|e| Status::unavailable(Session::poses_unreadable(&e)))?;
        Ok(Response::new(pb::Trajectory { poses, next_start_ns: next.unwrap_or(0) }))
    }

    async fn subscribe_poses(&self, request: Request<pb::SessionRef>) -> Result<Response<Self::SubscribePosesStream>, Status> {
        let id = request.get_ref().session_id.clone();
        let here = self.registry.get_off_runtime(&id).await;
        // A lagging subscriber skips poses rather than holding the pipeline.
        let local = |session: &Session| BroadcastStream::new(session.subscribe_poses()).filter_map(|r| r.ok().map(Ok));
        if let Some(session) = here.as_ref().filter(|s| !s.is_archived()) {
            return Ok(Response::new(Box::pin(local(session))));
        }
        // Held by another server (or stored here and live there after a move): its
        // poses come over Zenoh (relay.rs), from the holder's next tick on, and
        // whichever server holds the session later (this one included).
        let Some(live) = &self.remote_live else {
            return here.map(|s| Response::new(Box::pin(local(&s)) as Self::SubscribePosesStream)).ok_or_else(|| Self::unknown(&id));
        };
        let watching = live.watch();
        let (poses, own) = (live.subscribe_poses(), self.registry.subscribe_fleet());
        // Some live server holds it (asked as GetLatestPose): else this server's
        // stored copy, or NOT_FOUND (or the holder's refusal).
        if let Err(status) = self.forwarded::<_, pb::LatestPose>("GetLatestPose", &id, &request).await {
            return match here {
                Some(s) if status.code() == tonic::Code::NotFound => Ok(Response::new(Box::pin(local(&s)))),
                _ => Err(status),
            };
        }
        let stream = BroadcastStream::new(poses).merge(BroadcastStream::new(own)).filter_map(move |r| {
            let _counted = &watching;
            r.ok().filter(|(session, _)| **session == *id).map(|(_, pose)| Ok(pose))
        });
        Ok(Response::new(Box::pin(stream)))
    }

    async fn get_map_tile(&self, request: Request<pb::MapTileRequest>) -> Result<Response<pb::MapTile>, Status> {
        if self.registry.info(&request.get_ref().session_id).is_none() {
            return self.forwarded("GetMapTile", &request.get_ref().session_id, &request).await;
        }
        let r = request.into_inner();
        let map = self.map(&r.session_id).await?;
        let zoom = u8::try_from(r.zoom)
            .map_err(|_| Status::invalid_argument(format!("zoom {} is out of range 0..={}", r.zoom, stillmap_mapping::tiles::MAX_ZOOM)))?;
        let tile = tokio::task::spawn_blocking(move || crate::api::map_queries::tile(&map, zoom, r.x, r.y))
            .await
            .map_err(|e| Status::internal(format!("map query failed: {e}")))??;
        Ok(Response::new(pb::MapTile { png: tile.png, etag: tile.etag }))
    }

    async fn get_map_cloud(&self, request: Request<pb::MapCloudRequest>) -> Result<Response<Self::GetMapCloudStream>, Status> {
        if self.registry.info(&request.get_ref().session_id).is_none() {
            let id = request.get_ref().session_id.clone();
            let answer = self.forwarded_bytes("GetMapCloud", &request, || Self::unknown(&id)).await?;
            let (mut rest, mut chunks) = (answer.as_slice(), Vec::new());
            while !rest.is_empty() {
                let chunk = pb::MapCloudChunk::decode_length_delimited(&mut rest)
                    .map_err(|e| Status::internal(format!("another server's map cloud: {e}")))?;
                chunks.push(Ok(chunk));
            }
            return Ok(Response::new(Box::pin(tokio_stream::iter(chunks))));
        }
        let r = request.into_inner();
        let map = self.map(&r.session_id).await?;
        let bbox = match r.bbox {
            None => None,
            Some(b) => {
                let (lo, hi) = (b.min.unwrap_or_default(), b.max.unwrap_or_default());
                let text = format!("{},{},{},{},{},{}", lo.x, lo.y, lo.z, hi.x, hi.y, hi.z);
                Some(crate::api::map_queries::parse_bbox(&text).map_err(|e| Status::invalid_argument(e.0))?)
            }
        };
        let (points, names) = tokio::task::spawn_blocking(move || crate::api::map_queries::points(&map, bbox.as_ref()))
            .await
            .map_err(|e| Status::internal(format!("map query failed: {e}")))?
            .map_err(|e| Status::from(crate::api::map_queries::QueryError::from(e)))?;
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
