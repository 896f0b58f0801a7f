//! HTTP shell (axum): health, sessions, maps, metrics. Errors are JSON `{"error": "..."}`.

use std::sync::Arc;

use axum::Extension;
use axum::extract::DefaultBodyLimit;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde_json::{Value, json};
use stillmap_proto::pb;

use crate::api::map_queries::{self as mapping, BadQuery, FleetParts};
use crate::api::openapi::{ApiError, Health, Imported, PoseReply, PoseView, SessionList, SessionView, StoreHealth, Trajectory};
use crate::map::SharedMap;
use crate::session::{Registry, Session};

/// `Query<T>` whose rejection (bad query-string syntax, a wrong type) is the API's
/// JSON error with 400, like every other error, instead of axum's plain text.
pub(crate) struct JsonQuery<T>(T);

impl<T, S> axum::extract::FromRequestParts<S> for JsonQuery<T>
where
    T: serde::de::DeserializeOwned,
    S: Send + Sync,
{
    type Rejection = Response;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, state: &S) -> Result<Self, Self::Rejection> {
        match Query::<T>::from_request_parts(parts, state).await {
            Ok(Query(v)) => Ok(Self(v)),
            Err(e) => Err(error(StatusCode::BAD_REQUEST, e.body_text())),
        }
    }
}

/// What the HTTP shell needs besides the registry: who may query, import and
/// export (the tokens in force), how large an import may be, the dashboard's
/// viewer limit.
pub struct HttpSettings {
    pub auth: Arc<crate::auth::AuthHandle>,
    /// Requests per client (`limits.http_requests_per_minute`).
    pub rate_limits: Arc<crate::ratelimit::RateLimits>,
    /// `store.import_max_bytes`.
    pub import_max_bytes: usize,
    /// `http.max_event_viewers`.
    pub max_event_viewers: usize,
    /// `http.pose_event_interval_ms`.
    pub pose_event_interval: std::time::Duration,
    /// The other servers' live data for the dashboard's event stream (a cluster on Zenoh).
    pub remote_live: Option<Arc<dyn crate::api::RemoteLive>>,
}

pub fn router(registry: Arc<Registry>, dashboard_dir: Option<std::path::PathBuf>, settings: Arc<HttpSettings>) -> Router {
    let feed = crate::api::dashboard::EventFeed::new(
        registry.clone(),
        settings.max_event_viewers,
        settings.pose_event_interval,
        settings.remote_live.clone(),
    );
    let dashboard = crate::api::dashboard::DashboardState { registry: registry.clone(), dir: dashboard_dir, feed };
    let read = axum::middleware::from_fn_with_state(settings.clone(), require_read);
    let rate_limited = axum::middleware::from_fn_with_state(settings.clone(), rate_limit);
    // The dashboard's files hold no data: open. Its event stream needs `read`.
    let ui = Router::new()
        .route("/api/v1/events", get(crate::api::dashboard::events))
        .route_layer(read.clone())
        .route("/", get(crate::api::dashboard::index))
        .route("/assets/{*path}", get(crate::api::dashboard::asset))
        .with_state(dashboard);
    // Whole maps in and out check `admin` themselves (before reading a body). The
    // compressed body is never much larger than what it decompresses to.
    let body_limit = settings.import_max_bytes.saturating_add(IMPORT_BODY_MARGIN);
    let admin = Router::new()
        .route("/api/v1/maps/{id}/export", get(map_export).layer(Extension(settings.clone())))
        .route("/api/v1/maps/import", post(map_import).layer((DefaultBodyLimit::max(body_limit), Extension(settings))))
        .with_state(registry.clone());
    Router::new()
        .route("/api/v1/sessions", get(list_sessions))
        .route("/api/v1/sessions/{id}", get(get_session))
        .route("/api/v1/sessions/{id}/pose", get(get_pose))
        .route("/api/v1/sessions/{id}/trajectory", get(get_trajectory))
        .route("/api/v1/sessions/{id}/export.mcap", get(session_mcap))
        .route("/api/v1/fleets", get(list_fleets))
        .route("/api/v1/fleets/{fleet}", get(get_fleet))
        .route("/api/v1/fleets/{fleet}/cloud.ply", get(fleet_cloud))
        .route("/api/v1/fleets/{fleet}/occupancy.pgm", get(fleet_occupancy_pgm))
        .route("/api/v1/fleets/{fleet}/occupancy.yaml", get(fleet_occupancy_yaml))
        .route("/api/v1/fleets/{fleet}/objects", get(fleet_objects))
        .route("/api/v1/fleets/{fleet}/tiles/{z}/{x}/{y}", get(fleet_tile))
        .route("/api/v1/fleets/{fleet}/legend", get(fleet_legend))
        .route("/api/v1/maps/{id}", get(map_info))
        .route("/api/v1/maps/{id}/tiles/{z}/{x}/{y}", get(map_tile))
        .route("/api/v1/maps/{id}/legend", get(map_legend))
        .route("/api/v1/maps/{id}/occupancy.pgm", get(map_occupancy_pgm))
        .route("/api/v1/maps/{id}/occupancy.yaml", get(map_occupancy_yaml))
        .route("/api/v1/maps/{id}/cloud.ply", get(map_cloud))
        .route("/api/v1/maps/{id}/objects", get(map_objects))
        .route("/metrics", get(metrics))
        .route_layer(read)
        .route("/healthz", get(healthz))
        .route("/api/v1/openapi.json", get(openapi))
        .with_state(registry)
        .merge(admin)
        .merge(ui)
        .layer(rate_limited)
        .layer(axum::middleware::map_response(json_errors))
        .fallback(|| async {
            let mut response = error(StatusCode::NOT_FOUND, "no such endpoint".into());
            response.extensions_mut().insert(NoSuchEndpoint);
            response
        })
}

/// Marks the 404 of a path no route matches (no token was checked for it), which
/// is never forwarded to another server.
#[derive(Debug, Clone, Copy)]
pub struct NoSuchEndpoint;

fn error(code: StatusCode, message: String) -> Response {
    (code, Json(ApiError { error: message })).into_response()
}

/// The most of a plain-text rejection's body kept as its JSON message.
const MAX_REJECTION_TEXT: usize = 4096;

/// Every error answer is JSON ([`ApiError`]): axum's own rejections (a path segment
/// that is not UTF-8, a body over its limit, a wrong method) come as plain text and
/// are turned into the same shape; their status and other headers stay.
async fn json_errors(response: Response) -> Response {
    let status = response.status();
    let json = response.headers().get(header::CONTENT_TYPE).is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if json || !(status.is_client_error() || status.is_server_error()) {
        return response;
    }
    let (parts, body) = response.into_parts();
    let text =
        axum::body::to_bytes(body, MAX_REJECTION_TEXT).await.map(|b| String::from_utf8_lossy(&b).trim().to_string()).unwrap_or_default();
    let message = if text.is_empty() { status.canonical_reason().unwrap_or("error").to_lowercase() } else { text };
    let mut out = error(status, message);
    for (name, value) in &parts.headers {
        if name != header::CONTENT_TYPE && name != header::CONTENT_LENGTH {
            out.headers_mut().append(name.clone(), value.clone());
        }
    }
    out.extensions_mut().extend(parts.extensions);
    out
}

#[utoipa::path(
    get,
    path = "/api/v1/sessions",
    tag = "sessions",
    params(
        ("limit" = Option<usize>, Query, description = "Sessions per answer: 1000 by default, at most 5000; where more follow, `next_page_token` says where to ask from"),
        ("page_token" = Option<String>, Query, description = "Where the page starts: a `next_page_token` an earlier answer gave"),
    ),
    responses(
        (status = 200, description = "The sessions, live and stored, oldest first (by start time, then id)", body = SessionList),
        (status = 400, description = "Bad limit or page token", body = ApiError),
    )
)]
pub(crate) async fn list_sessions(State(registry): State<Arc<Registry>>, JsonQuery(q): JsonQuery<ListQuery>) -> Response {
    let (after, limit) = match q.checked() {
        Ok(page) => page,
        Err(message) => return error(StatusCode::BAD_REQUEST, message),
    };
    let listed = tokio::task::spawn_blocking(move || registry.list_page(after.as_ref(), limit)).await;
    let Ok((sessions, next)) = listed else { return error(StatusCode::INTERNAL_SERVER_ERROR, "the sessions list failed".into()) };
    Json(SessionList { sessions: sessions.iter().map(|s| SessionView::from(s, false)).collect(), next_page_token: next.map(|c| c.token()) })
        .into_response()
}

/// `GET /api/v1/sessions`'s query.
#[derive(Debug, Default, serde::Deserialize)]
pub(crate) struct ListQuery {
    pub(crate) limit: Option<usize>,
    pub(crate) page_token: Option<String>,
}

impl ListQuery {
    /// Where the page starts and how long it is, or what is wrong with them.
    pub(crate) fn checked(&self) -> Result<(Option<crate::session::ListCursor>, usize), String> {
        let limit = self.limit.unwrap_or(crate::session::DEFAULT_SESSIONS_PAGE);
        if !(1..=crate::session::MAX_SESSIONS_PAGE).contains(&limit) {
            return Err(format!(
                "limit must be within 1..={} sessions (page with page_token), got {limit}",
                crate::session::MAX_SESSIONS_PAGE
            ));
        }
        let after = self.page_token.as_deref().filter(|t| !t.is_empty()).map(crate::session::ListCursor::parse).transpose()?;
        Ok((after, limit))
    }
}

#[utoipa::path(
    get,
    path = "/api/v1/sessions/{id}",
    tag = "sessions",
    params(
        ("id" = String, Path, description = "Session id"),
    ),
    responses(
        (status = 200, description = "The session with its camera", body = SessionView),
        (status = 404, description = "Unknown session or no map", body = ApiError),
    )
)]
pub(crate) async fn get_session(State(registry): State<Arc<Registry>>, Path(id): Path<String>) -> Response {
    match registry.info(&id) {
        Some(s) => Json(SessionView::from(&s, true)).into_response(),
        None => error(StatusCode::NOT_FOUND, format!("unknown session {id:?}")),
    }
}

/// What the pose endpoints say about the frame of reference.
const WORLD_FRAME: &str =
    "world = the camera frame of the session's first tracked frame (x right, y down, z forward); poses are world_from_camera";

/// What the pose endpoints say about the fleet frame.
const FLEET_FRAME: &str = "fleet = the world of the session that anchors the fleet; poses are fleet_from_camera";

#[derive(serde::Deserialize)]
pub(crate) struct FrameQuery {
    /// `world` (the session's own, the default) or `fleet`.
    frame: Option<String>,
}

/// The transform taking this session's poses into the asked frame, and that frame's description.
/// The transform into the fleet frame with the pose graph's corrections (none for
/// the session's own world) and the frame's description.
type Frame = (Option<crate::fleet::FleetTransform>, &'static str);

fn frame_of(registry: &Registry, s: &Session, frame: Option<&str>) -> Result<Frame, (StatusCode, String)> {
    match frame {
        None | Some("world") => Ok((None, WORLD_FRAME)),
        Some("fleet") => {
            let Some(fleets) = registry.fleets() else {
                return Err((StatusCode::CONFLICT, "fleets are off on this server (fleet.enabled)".into()));
            };
            match fleets.fleet_transform(&s.fleet_name, &s.id) {
                Some(t) => Ok((Some(t), FLEET_FRAME)),
                None => Err((StatusCode::CONFLICT, format!("session {} is not merged into fleet {:?} yet", s.id, s.fleet_name))),
            }
        }
        Some(other) => Err((StatusCode::BAD_REQUEST, format!("unknown frame {other:?}; use world or fleet"))),
    }
}

/// `p` in the fleet frame when a transform is given (corrected as of its capture time).
fn in_frame(p: &pb::PoseStamped, fleet: Option<&crate::fleet::FleetTransform>) -> pb::PoseStamped {
    fleet.map_or(*p, |t| crate::convert::pose_in(p, &t.at(p.capture_time_ns)))
}

#[utoipa::path(
    get,
    path = "/api/v1/sessions/{id}/pose",
    tag = "sessions",
    params(
        ("id" = String, Path, description = "Session id"),
        ("frame" = Option<String>, Query, description = "world (the session's own, default) or fleet"),
    ),
    responses(
        (status = 200, description = "The latest pose", body = PoseReply),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 409, description = "Not merged into its fleet yet (frame=fleet)", body = ApiError),
    )
)]
pub(crate) async fn get_pose(
    State(registry): State<Arc<Registry>>,
    Path(id): Path<String>,
    JsonQuery(q): JsonQuery<FrameQuery>,
) -> Response {
    let s = match session_of(&registry, &id).await {
        Ok(s) => s,
        Err(response) => return response,
    };
    let (transform, frame) = match frame_of(&registry, &s, q.frame.as_deref()) {
        Ok(f) => f,
        Err((code, message)) => return error(code, message),
    };
    let track = s.tracking();
    Json(PoseReply {
        session_id: s.id.clone(),
        tracking_state: track.state.as_str_name().to_string(),
        frame: frame.to_string(),
        pose: track.latest.as_ref().map(|p| PoseView::from(&in_frame(p, transform.as_ref()))),
    })
    .into_response()
}

#[utoipa::path(
    get,
    path = "/api/v1/sessions/{id}/trajectory",
    tag = "sessions",
    params(
        ("id" = String, Path, description = "Session id"),
        ("frame" = Option<String>, Query, description = "world (the session's own, default) or fleet"),
        ("format" = Option<String>, Query, description = "json (default) or tum (text: timestamp tx ty tz qx qy qz qw)"),
        ("start_ns" = Option<u64>, Query, description = "Capture times from (inclusive, ns; default 0)"),
        ("end_ns" = Option<u64>, Query, description = "Capture times up to (inclusive, ns; default: all)"),
        ("limit" = Option<usize>, Query, description = "Poses per answer, at most and by default 200000; where more follow, `next_start_ns` (JSON), a last comment line (TUM) and the `x-stillmap-next-start-ns` header say where to ask from"),
    ),
    responses(
        (status = 200, description = "The poses, oldest first", body = Trajectory, content_type = "application/json"),
        (status = 200, description = "TUM trajectory text", body = String, content_type = "text/plain"),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 409, description = "Not merged into its fleet yet (frame=fleet)", body = ApiError),
        (status = 503, description = "Poses out of memory (session.trajectory_in_memory) cannot be read back from the store (no trajectory with a gap is answered)", body = ApiError),
    )
)]
pub(crate) async fn get_trajectory(
    State(registry): State<Arc<Registry>>,
    Path(id): Path<String>,
    JsonQuery(q): JsonQuery<TrajectoryQuery>,
) -> Response {
    let (start_ns, end_ns) = (q.start_ns.unwrap_or(0), q.end_ns.unwrap_or(u64::MAX));
    if start_ns > end_ns {
        return error(StatusCode::BAD_REQUEST, format!("start_ns {start_ns} is after end_ns {end_ns}"));
    }
    let limit = q.limit.unwrap_or(crate::session::MAX_TRAJECTORY_PAGE);
    if !(1..=crate::session::MAX_TRAJECTORY_PAGE).contains(&limit) {
        return error(
            StatusCode::BAD_REQUEST,
            format!("limit must be within 1..={} poses (page with start_ns), got {limit}", crate::session::MAX_TRAJECTORY_PAGE),
        );
    }
    let s = match session_of(&registry, &id).await {
        Ok(s) => s,
        Err(response) => return response,
    };
    let (transform, frame) = match frame_of(&registry, &s, q.frame.as_deref()) {
        Ok(f) => f,
        Err((code, message)) => return error(code, message),
    };
    let session = s.clone();
    let (poses, next) = match blocking(move || session.trajectory_page(start_ns, end_ns, limit)).await {
        Ok(Ok(page)) => page,
        Ok(Err(e)) => return trajectory_unreadable(&e),
        Err(r) => return r,
    };
    let poses: Vec<pb::PoseStamped> = poses.iter().map(|p| in_frame(p, transform.as_ref())).collect();
    let next_header = next.map(|n| [(HeaderName::from_static(NEXT_START_HEADER), HeaderValue::from(n))]);
    let body = match q.format.as_deref() {
        None | Some("json") => Json(Trajectory {
            session_id: s.id.clone(),
            frame: frame.to_string(),
            poses: poses.iter().map(PoseView::from).collect(),
            next_start_ns: next,
        })
        .into_response(),
        Some("tum") => {
            let mut text = format!("# timestamp tx ty tz qx qy qz qw ({frame}; timestamp = pose_time_ns)\n");
            for p in &poses {
                let pose = p.world_from_camera.unwrap_or_default();
                let (t, r) = (pose.translation.unwrap_or_default(), pose.rotation.unwrap_or_default());
                stillmap_dataset::trajectory::push_line_ns(&mut text, p.time_ns(), [t.x, t.y, t.z], [r.x, r.y, r.z, r.w]);
            }
            if let Some(n) = next {
                text.push_str(&format!("# more poses follow: ask again with start_ns={n}\n"));
            }
            ([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], text).into_response()
        }
        Some(other) => return error(StatusCode::BAD_REQUEST, format!("unknown trajectory format {other:?}; use json or tum")),
    };
    (next_header, body).into_response()
}

/// A trajectory whose older poses (out of memory) the store cannot give back:
/// 503, not a trajectory with a gap.
fn trajectory_unreadable(e: &crate::store::StoreError) -> Response {
    error(StatusCode::SERVICE_UNAVAILABLE, Session::poses_unreadable(e))
}

/// The header naming where a trajectory's next page starts (when more poses follow).
const NEXT_START_HEADER: &str = "x-stillmap-next-start-ns";

/// `GET /api/v1/sessions/{id}/trajectory`'s query.
#[derive(Debug, serde::Deserialize)]
pub(crate) struct TrajectoryQuery {
    /// `world` (the session's own, the default) or `fleet`.
    frame: Option<String>,
    format: Option<String>,
    start_ns: Option<u64>,
    end_ns: Option<u64>,
    limit: Option<usize>,
}

fn fleet_json(f: &crate::fleet::FleetView, detail: bool) -> Value {
    let anchor = f.members.iter().find(|m| m.frame.as_ref().is_some_and(|fr| fr.anchor)).map(|m| m.session_id.clone());
    let merged = f.members.iter().filter(|m| m.frame.is_some()).count();
    let mut v = json!({
        "fleet": f.name,
        "anchor_session_id": anchor,
        "sessions": f.members.len(),
        "merged": merged,
        "indexed_keyframes": f.indexed_keyframes,
        // A pose-graph solve is due or running: the corrections are about to change.
        "pose_graph_pending": f.pose_graph_pending,
        // Place edges sessions resumed from another server brought, waiting for
        // their keyframes to be indexed here.
        "carried_edges_waiting": f.carried_edges_waiting,
    });
    if detail {
        // The fused fleet map: keyframes held (fused, or waiting for their
        // session's merge), fused, with their input kept, and fused again after moving.
        v["map"] = f.map.map_or(Value::Null, |c| json!(c));
        v["sessions"] = f
            .members
            .iter()
            .map(|m| {
                let frame = m.frame.as_ref().map(|fr| {
                    let p = &fr.fleet_from_session;
                    json!({
                        "translation": [p[0], p[1], p[2]],
                        "rotation_xyzw": [p[3], p[4], p[5], p[6]],
                        "anchor": fr.anchor,
                        "support": fr.support,
                        "inliers": fr.inliers,
                        "merged_unix_ns": fr.merged_unix_ns,
                        "first_merged_unix_ns": fr.first_merged_unix_ns,
                        "merged_after_s": fr.merged_after_ns as f64 * 1e-9,
                        // The anchor whose world the frame is (on whichever server it anchored).
                        "lineage": fr.lineage_of(&m.session_id),
                    })
                });
                // The pose graph's correction of its latest keyframe (poses are
                // corrected per keyframe: `?frame=fleet` applies them).
                let correction = m.latest_correction.map(|c| {
                    let (t, q) = (c.translation.vector, c.rotation.coords);
                    json!({ "translation": [t.x, t.y, t.z], "rotation_xyzw": [q.x, q.y, q.z, q.w] })
                });
                json!({
                    "session_id": m.session_id,
                    "robot_id": m.robot_id,
                    "merged": m.frame.is_some(),
                    "fleet_from_session": frame,
                    "latest_correction": correction,
                    // Its keyframes place recognition can find it by here (a
                    // resumed session's include those stored on the server before).
                    "indexed_keyframes": m.indexed_keyframes,
                    "oldest_indexed_keyframe": m.oldest_indexed_keyframe,
                })
            })
            .collect::<Vec<_>>()
            .into();
        // The pose graph's last solve (null until a loop or inter-session edge came).
        v["last_correction"] = f.last_correction.as_ref().map_or(Value::Null, |c| json!(c));
        v["tiles"] = json!({
            "url": format!("/api/v1/fleets/{}/tiles/{{z}}/{{x}}/{{y}}.png", f.name),
            "legend": format!("/api/v1/fleets/{}/legend", f.name),
            "tile_px": stillmap_mapping::tiles::TILE_PX,
            "min_zoom": 0,
            "max_zoom": stillmap_mapping::tiles::MAX_ZOOM,
            "scheme": "as a session map's tiles (see /api/v1/maps/{id}), in the fleet's map frame",
        });
    }
    v
}

#[utoipa::path(
    get,
    path = "/api/v1/fleets",
    tag = "fleets",
    responses(
        (status = 200, description = "Every fleet: anchor, members, merged or not", body = Object),
    )
)]
pub(crate) async fn list_fleets(State(registry): State<Arc<Registry>>) -> Response {
    let Some(fleets) = registry.fleets() else {
        return Json(json!({ "fleets": [] })).into_response();
    };
    Json(json!({
        "fleets": fleets.list().iter().map(|f| fleet_json(f, false)).collect::<Vec<_>>(),
        "place_recognition_backlog": fleets.backlog(),
    }))
    .into_response()
}

/// [`fleet_parts`] off the async runtime: a stored member is read back from the
/// store.
#[allow(clippy::result_large_err)]
async fn fleet_parts_of(registry: &Arc<Registry>, name: &str) -> Result<FleetParts, Response> {
    let (registry, name) = (registry.clone(), name.to_string());
    blocking(move || fleet_parts(&registry, &name)).await?
}

/// The fleet's merged sessions' maps, the anchor's first, and the fused fleet map
/// when it holds every keyframe of them (the error is the finished HTTP response,
/// as for `session_map`).
#[allow(clippy::result_large_err)]
fn fleet_parts(registry: &Registry, name: &str) -> Result<FleetParts, Response> {
    let Some((fleets, fleet)) = registry.fleets().and_then(|f| Some((f, f.get(name)?))) else {
        return Err(error(StatusCode::NOT_FOUND, format!("unknown fleet {name:?}")));
    };
    let mut members: Vec<_> = fleet
        .members
        .iter()
        .filter_map(|m| m.frame.as_ref().map(|fr| (fr.anchor, m.session_id.clone(), crate::fleet::isometry(&fr.fleet_from_session))))
        .collect();
    members.sort_by_key(|(anchor, _, _)| !anchor);
    let anchor_has_map = members.first().is_some_and(|(anchor, id, _)| *anchor && registry.get(id).is_some_and(|s| s.map().is_some()));
    if !anchor_has_map {
        return Err(error(StatusCode::NOT_FOUND, format!("fleet {name:?} has no anchor map yet")));
    }
    let maps = members.iter().filter_map(|(_, id, t)| Some((id.clone(), registry.get(id)?.map()?.clone(), *t))).collect();
    Ok(FleetParts { maps, fused: fleets.map_state(name) })
}

/// Fleet maps built and in use at once, over every fleet: each is a copy of its
/// members' maps (hundreds of MB for a large fleet), so that many requests at
/// once wait for a turn rather than each holding its own copy.
static FLEET_MAP_BUILDS: tokio::sync::Semaphore = tokio::sync::Semaphore::const_new(2);

/// Builds the fleet map off the runtime, once one of [`FLEET_MAP_BUILDS`] is
/// free: move the permit returned into the blocking work that uses the map (held
/// by a blocking thread, it outlives a request whose client hung up).
async fn fleet_map(
    registry: &Arc<Registry>,
    name: &str,
) -> Result<(mapping::FleetMap, usize, tokio::sync::SemaphorePermit<'static>), Response> {
    let mut parts = fleet_parts_of(registry, name).await?;
    let n = parts.maps.len();
    let permit =
        FLEET_MAP_BUILDS.acquire().await.map_err(|_| error(StatusCode::SERVICE_UNAVAILABLE, "the server is stopping".to_string()))?;
    match blocking(move || {
        parts.drop_incomplete_fused();
        (mapping::fleet_map(&parts), permit)
    })
    .await?
    {
        (Ok(Some(m)), permit) => Ok((m, n, permit)),
        (Ok(None), _) => Err(error(StatusCode::NOT_FOUND, format!("fleet {name:?} has no map yet"))),
        (Err(e), _) => Err(query_error(e)),
    }
}

/// The fleet's merged sessions' maps as one PLY in the fleet's map frame.
#[utoipa::path(
    get,
    path = "/api/v1/fleets/{fleet}/cloud.ply",
    tag = "fleets",
    params(
        ("fleet" = String, Path, description = "Fleet name"),
    ),
    responses(
        (status = 200, description = "The fleet map as a binary PLY, class colours", content_type = "application/octet-stream"),
        (status = 404, description = "Unknown fleet", body = ApiError),
        (status = 409, description = "Fleets off, or nothing merged yet", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn fleet_cloud(State(registry): State<Arc<Registry>>, Path(name): Path<String>) -> Response {
    let (fleet, n, turn) = match fleet_map(&registry, &name).await {
        Ok(f) => f,
        Err(r) => return r,
    };
    let fleet_name = name.clone();
    match blocking(move || {
        let _turn = turn;
        mapping::fleet_ply(&fleet, &fleet_name, n)
    })
    .await
    {
        Ok(ply) => (
            [
                (header::CONTENT_TYPE, "application/octet-stream".to_string()),
                (header::CONTENT_DISPOSITION, format!("attachment; filename=\"fleet-{name}.ply\"")),
            ],
            ply,
        )
            .into_response(),
        Err(r) => r,
    }
}

async fn fleet_occupancy(
    registry: &Arc<Registry>,
    name: &str,
    q: OccupancyQuery,
) -> Result<stillmap_mapping::tiles::OccupancyGrid, Response> {
    let (fleet, _, turn) = fleet_map(registry, name).await?;
    blocking(move || {
        let _turn = turn;
        mapping::fleet_occupancy(&fleet, q.min_height, q.max_height, q.resolution)
    })
    .await?
    .map_err(|e| error(StatusCode::BAD_REQUEST, e.0))
}

#[utoipa::path(
    get,
    path = "/api/v1/fleets/{fleet}/occupancy.pgm",
    tag = "fleets",
    params(
        ("fleet" = String, Path, description = "Fleet name"),
        OccupancyQuery,
    ),
    responses(
        (status = 200, description = "ROS map_server occupancy image", content_type = "image/x-portable-graymap"),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown fleet", body = ApiError),
        (status = 409, description = "Fleets off, or nothing merged yet", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn fleet_occupancy_pgm(
    State(registry): State<Arc<Registry>>,
    Path(name): Path<String>,
    JsonQuery(q): JsonQuery<OccupancyQuery>,
) -> Response {
    match fleet_occupancy(&registry, &name, q).await {
        Ok(grid) => ([(header::CONTENT_TYPE, "image/x-portable-graymap")], grid.to_pgm()).into_response(),
        Err(r) => r,
    }
}

#[utoipa::path(
    get,
    path = "/api/v1/fleets/{fleet}/occupancy.yaml",
    tag = "fleets",
    params(
        ("fleet" = String, Path, description = "Fleet name"),
        OccupancyQuery,
    ),
    responses(
        (status = 200, description = "ROS map_server parameters", body = String, content_type = "application/yaml"),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown fleet", body = ApiError),
        (status = 409, description = "Fleets off, or nothing merged yet", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn fleet_occupancy_yaml(
    State(registry): State<Arc<Registry>>,
    Path(name): Path<String>,
    JsonQuery(q): JsonQuery<OccupancyQuery>,
) -> Response {
    match fleet_occupancy(&registry, &name, q).await {
        Ok(grid) => ([(header::CONTENT_TYPE, "application/yaml")], grid.to_yaml("occupancy.pgm")).into_response(),
        Err(r) => r,
    }
}

#[utoipa::path(
    get,
    path = "/api/v1/fleets/{fleet}/objects",
    tag = "fleets",
    params(
        ("fleet" = String, Path, description = "Fleet name"),
    ),
    responses(
        (status = 200, description = "Objects of the fleet map with class and box", body = Object),
        (status = 404, description = "Unknown fleet", body = ApiError),
        (status = 409, description = "Fleets off, or nothing merged yet", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn fleet_objects(State(registry): State<Arc<Registry>>, Path(name): Path<String>) -> Response {
    let (fleet, _, turn) = match fleet_map(&registry, &name).await {
        Ok(f) => f,
        Err(r) => return r,
    };
    match blocking(move || {
        let _turn = turn;
        (stillmap_mapping::export::objects(&fleet.map, &fleet.map_from_fleet), fleet.class_names)
    })
    .await
    {
        Ok((objects, names)) => {
            Json(json!({ "fleet": name, "frame": FLEET_MAP_FRAME, "objects": objects_json(&objects, &names) })).into_response()
        }
        Err(r) => r,
    }
}

/// Fleet `name`'s merged members and the tag of the state their maps are in (off
/// the runtime: it locks every member's map).
async fn fleet_state(registry: &Arc<Registry>, name: &str) -> Result<(FleetParts, u64), Response> {
    let mut parts = fleet_parts_of(registry, name).await?;
    blocking(move || {
        parts.drop_incomplete_fused();
        let tag = mapping::fleet_tag(&parts);
        (parts, tag)
    })
    .await
}

/// The fleet map's top-down view for `parts` in the state `tag` (cached per fleet until a part changes).
async fn fleet_top(registry: Arc<Registry>, name: &str, parts: FleetParts, tag: u64) -> Result<Arc<mapping::FleetTop>, Response> {
    let fleet = name.to_string();
    blocking_query(move || registry.fleet_tops().get(&fleet, &parts, tag))
        .await?
        .ok_or_else(|| error(StatusCode::NOT_FOUND, format!("fleet {name:?} has no map yet")))
}

/// A tile of the fleet map: the session tiles' scheme, in the fleet's map frame.
#[utoipa::path(
    get,
    path = "/api/v1/fleets/{fleet}/tiles/{z}/{x}/{y}",
    tag = "fleets",
    params(
        ("fleet" = String, Path, description = "Fleet name"),
        TilePath,
    ),
    responses(
        (status = 200, description = "Top-down PNG tile (ETag)", content_type = "image/png"),
        (status = 304, description = "Not modified (If-None-Match)"),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown fleet", body = ApiError),
        (status = 409, description = "Fleets off, or nothing merged yet", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn fleet_tile(
    State(registry): State<Arc<Registry>>,
    Path((name, z, x, y)): Path<(String, String, String, String)>,
    headers: HeaderMap,
) -> Response {
    let (z, x, y) = match tile_coordinates(&z, &x, &y) {
        Ok(c) => c,
        Err(e) => return error(StatusCode::BAD_REQUEST, e.0),
    };
    let (parts, tag) = match fleet_state(&registry, &name).await {
        Ok(s) => s,
        Err(r) => return r,
    };
    if let Some(r) = not_modified(&headers, mapping::fleet_tile_etag(tag, z, x, y)) {
        return r;
    }
    let top = match fleet_top(registry, &name, parts, tag).await {
        Ok(t) => t,
        Err(r) => return r,
    };
    tile_response(blocking(move || mapping::fleet_tile(&top, z, x, y)).await)
}

/// The fleet map's legend, with the extent its tiles cover.
#[utoipa::path(
    get,
    path = "/api/v1/fleets/{fleet}/legend",
    tag = "fleets",
    params(
        ("fleet" = String, Path, description = "Fleet name"),
    ),
    responses(
        (status = 200, description = "Classes and colours of the fleet tiles, and their extent", body = Object),
        (status = 404, description = "Unknown fleet", body = ApiError),
        (status = 409, description = "Fleets off, or nothing merged yet", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn fleet_legend(State(registry): State<Arc<Registry>>, Path(name): Path<String>) -> Response {
    let (parts, tag) = match fleet_state(&registry, &name).await {
        Ok(s) => s,
        Err(r) => return r,
    };
    let top = match fleet_top(registry, &name, parts, tag).await {
        Ok(t) => t,
        Err(r) => return r,
    };
    let entries = mapping::legend_of(&top.top, &top.class_names);
    Json(json!({
        "fleet": name,
        "frame": FLEET_MAP_FRAME,
        "bounds_xy": top.top.bounds(),
        "classes": legend_json(&entries),
    }))
    .into_response()
}

/// Legend entries as the API lists them.
fn legend_json(entries: &[mapping::LegendEntry]) -> Vec<Value> {
    entries
        .iter()
        .map(|e| {
            json!({
                "class_id": if e.class == stillmap_mapping::NO_CLASS { Value::Null } else { json!(e.class) },
                "name": e.name,
                "color": format!("#{:02x}{:02x}{:02x}", e.color[0], e.color[1], e.color[2]),
                "cells": e.cells,
            })
        })
        .collect()
}

/// The fleet map's frame.
const FLEET_MAP_FRAME: &str = "the fleet's map frame = the anchor session's map frame (its world rotated so that +z is up; origin at its first camera's centre); metres";

#[utoipa::path(
    get,
    path = "/api/v1/fleets/{fleet}",
    tag = "fleets",
    params(
        ("fleet" = String, Path, description = "Fleet name"),
    ),
    responses(
        (status = 200, description = "Sessions, merged or not, fleet_from_session transforms and latest corrections, the last pose-graph solve, the fused map's counts, tiles", body = Object),
        (status = 404, description = "Unknown fleet", body = ApiError),
    )
)]
pub(crate) async fn get_fleet(State(registry): State<Arc<Registry>>, Path(name): Path<String>) -> Response {
    match registry.fleets().and_then(|f| f.get(&name)) {
        Some(f) => Json(fleet_json(&f, true)).into_response(),
        None => error(StatusCode::NOT_FOUND, format!("unknown fleet {name:?}")),
    }
}

/// 200 `{"status": "ok"}`; 503 with the reason while the store fails to write
/// (the server goes on serving from memory).
#[utoipa::path(
    get,
    path = "/healthz",
    tag = "server",
    security(()),
    responses(
        (status = 200, description = "Serving", body = Health),
        (status = 503, description = "The store fails to write (still serving from memory)", body = Health),
    )
)]
pub(crate) async fn healthz(State(registry): State<Arc<Registry>>) -> Response {
    match registry.store().and_then(|s| s.failing().map(|f| (f, s.errors()))) {
        None => Json(Health { status: "ok".into(), store: None }).into_response(),
        Some((f, errors)) => (
            StatusCode::SERVICE_UNAVAILABLE,
            Json(Health {
                status: "unhealthy".into(),
                store: Some(StoreHealth { error: f.error, failing_since_unix_ns: f.since_unix_ns, errors_total: errors }),
            }),
        )
            .into_response(),
    }
}

#[utoipa::path(
    get,
    path = "/api/v1/sessions/{id}/export.mcap",
    tag = "sessions",
    params(
        ("id" = String, Path, description = "Session id"),
    ),
    responses(
        (status = 200, description = "The session for Foxglove: poses, trajectory, tracking states, the map as a point cloud, keyframe images with the mask (MCAP, JSON-encoded Foxglove schemas)", content_type = "application/octet-stream"),
        (status = 404, description = "Unknown session", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn session_mcap(State(registry): State<Arc<Registry>>, Path(id): Path<String>) -> Response {
    let s = match session_of(&registry, &id).await {
        Ok(s) => s,
        Err(response) => return response,
    };
    let map = s.map().cloned();
    let key = id.clone();
    let session = s.clone();
    let file = blocking(move || {
        let trajectory = session.whole_trajectory().map_err(|e| crate::map::MapUnreadable(Session::poses_unreadable(&e)))?;
        let map = map
            .map(|m| {
                let points = mapping::points(&m, None)?.0;
                let locked = crate::lock(&m);
                Ok(crate::api::foxglove::MapExport { points, map_from_world: locked.map_from_world(), images: locked.images() })
            })
            .transpose()?;
        Ok::<_, crate::map::MapUnreadable>(crate::api::foxglove::session_mcap(&key, &trajectory, map.as_ref()))
    })
    .await;
    match file {
        Ok(Ok(Ok(bytes))) => (
            [
                (header::CONTENT_TYPE, "application/octet-stream".to_string()),
                (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{id}.mcap\"")),
            ],
            bytes,
        )
            .into_response(),
        Ok(Ok(Err(e))) => error(StatusCode::INTERNAL_SERVER_ERROR, format!("writing the MCAP file failed: {e}")),
        Ok(Err(e)) => query_error(e),
        Err(r) => r,
    }
}

/// The API's OpenAPI 3.1 document (open: it holds no data).
#[utoipa::path(
    get,
    path = "/api/v1/openapi.json",
    tag = "server",
    security(()),
    responses(
        (status = 200, description = "This document", body = Object),
    )
)]
pub(crate) async fn openapi() -> Json<utoipa::openapi::OpenApi> {
    Json(crate::api::openapi::document())
}

#[utoipa::path(
    get,
    path = "/metrics",
    tag = "server",
    responses(
        (status = 200, description = "OpenMetrics text", body = String, content_type = "application/openmetrics-text"),
    )
)]
pub(crate) async fn metrics(State(registry): State<Arc<Registry>>) -> Response {
    ([(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], registry.metrics().render()).into_response()
}

/// The session's map, or the 404 to answer.
// The error is the finished HTTP response, handed straight back by the handlers.
#[allow(clippy::result_large_err)]
async fn session_map(registry: &Arc<Registry>, id: &str) -> Result<SharedMap, Response> {
    let s = session_of(registry, id).await?;
    s.map().cloned().ok_or_else(|| error(StatusCode::NOT_FOUND, format!("session {id:?} has no map (mapping is disabled)")))
}

/// The session ([`Registry::get_off_runtime`]), or the 404 to answer.
#[allow(clippy::result_large_err)]
async fn session_of(registry: &Arc<Registry>, id: &str) -> Result<Arc<Session>, Response> {
    registry.get_off_runtime(id).await.ok_or_else(|| error(StatusCode::NOT_FOUND, format!("unknown session {id:?}")))
}

/// Runs a map query off the async runtime (fusion may hold the map for a few ms).
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Result<T, Response> {
    tokio::task::spawn_blocking(f).await.map_err(|e| error(StatusCode::INTERNAL_SERVER_ERROR, format!("map query failed: {e}")))
}

/// A map query's error as the response: 400 for the query, 503 for a part of the
/// map the store cannot give back.
fn query_error(e: impl Into<mapping::QueryError>) -> Response {
    match e.into() {
        mapping::QueryError::Bad(b) => error(StatusCode::BAD_REQUEST, b.0),
        mapping::QueryError::Unreadable(u) => error(StatusCode::SERVICE_UNAVAILABLE, u.0),
    }
}

/// [`blocking`] for a map query that may fail ([`query_error`]).
async fn blocking_query<T: Send + 'static, E: Into<mapping::QueryError> + Send + 'static>(
    f: impl FnOnce() -> Result<T, E> + Send + 'static,
) -> Result<T, Response> {
    blocking(f).await?.map_err(query_error)
}

const MAP_FRAME: &str = "map = world rotated so that +z is up (gravity); origin at the first camera's centre; metres";

#[utoipa::path(
    get,
    path = "/api/v1/maps/{id}",
    tag = "maps",
    params(
        ("id" = String, Path, description = "Session id"),
    ),
    responses(
        (status = 200, description = "Map frame, extent, voxel counts, zoom levels", body = Object),
        (status = 404, description = "Unknown session or no map", body = ApiError),
    )
)]
pub(crate) async fn map_info(State(registry): State<Arc<Registry>>, Path(id): Path<String>) -> Response {
    let map = match session_map(&registry, &id).await {
        Ok(m) => m,
        Err(r) => return r,
    };
    let info = match blocking(move || crate::map::lock_info(&map)).await {
        Ok(i) => i,
        Err(r) => return r,
    };
    let (rotation, up_source) = match info.up {
        Some((r, source)) => (Some([r.coords.x, r.coords.y, r.coords.z, r.coords.w]), Some(source.label())),
        None => (None, None),
    };
    let zooms: Vec<Value> = (0..=stillmap_mapping::tiles::MAX_ZOOM)
        .map(|z| json!({ "zoom": z, "metres_per_pixel": info.voxel_size_m * f64::from(1u32 << (stillmap_mapping::tiles::MAX_ZOOM - z)) }))
        .collect();
    Json(json!({
        "session_id": id,
        "frame": MAP_FRAME,
        "map_from_world_xyzw": rotation,
        "up_source": up_source,
        "voxel_size_m": info.voxel_size_m,
        "keyframes": info.keyframes,
        "refused_keyframes": info.refused_keyframes,
        "retracted_samples": info.retracted_samples,
        "blocks": info.blocks,
        "evicted_blocks": info.evicted_blocks,
        "occupied_voxels": info.occupied_voxels,
        "memory_bytes": info.bytes,
        "version": info.version,
        "committed_keyframes": info.committed_keyframes,
        "bounds_xy": info.bounds,
        "tiles": {
            "url": format!("/api/v1/maps/{id}/tiles/{{z}}/{{x}}/{{y}}.png"),
            "tile_px": stillmap_mapping::tiles::TILE_PX,
            "min_zoom": 0,
            "max_zoom": stillmap_mapping::tiles::MAX_ZOOM,
            "zooms": zooms,
            "scheme": "tile (x, y) at zoom z covers map x in [x*T, (x+1)*T) and map y in (-(y+1)*T, -y*T], T = 256 * metres_per_pixel(z); x east, y south; indices may be negative",
        },
    }))
    .into_response()
}

/// Parses a tile path: zoom, x and `y.png`.
fn tile_coordinates(z: &str, x: &str, y: &str) -> Result<(u8, i64, i64), BadQuery> {
    let y = y.strip_suffix(".png").ok_or_else(|| BadQuery(format!("tile {y:?} must end in .png")))?;
    let z: u8 = z.parse().map_err(|_| BadQuery(format!("zoom {z:?} is not an integer 0..={}", stillmap_mapping::tiles::MAX_ZOOM)))?;
    let x: i64 = x.parse().map_err(|_| BadQuery(format!("tile x {x:?} is not an integer")))?;
    let y: i64 = y.parse().map_err(|_| BadQuery(format!("tile y {y:?} is not an integer")))?;
    Ok((z, x, y))
}

#[utoipa::path(
    get,
    path = "/api/v1/maps/{id}/tiles/{z}/{x}/{y}",
    tag = "maps",
    params(
        ("id" = String, Path, description = "Session id"),
        TilePath,
    ),
    responses(
        (status = 200, description = "Top-down PNG tile (ETag)", content_type = "image/png"),
        (status = 304, description = "Not modified (If-None-Match)"),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn map_tile(
    State(registry): State<Arc<Registry>>,
    Path((id, z, x, y)): Path<(String, String, String, String)>,
    headers: HeaderMap,
) -> Response {
    let map = match session_map(&registry, &id).await {
        Ok(m) => m,
        Err(r) => return r,
    };
    let (z, x, y) = match tile_coordinates(&z, &x, &y) {
        Ok(c) => c,
        Err(e) => return error(StatusCode::BAD_REQUEST, e.0),
    };
    // The map's lock may be held for long (a fusion, a PLY of a large map): taken
    // off the runtime, for the ETag as for the tile.
    let rendered = blocking(move || match not_modified(&headers, mapping::tile_etag(&map, z, x, y)) {
        Some(unchanged) => Err(Box::new(unchanged)),
        None => Ok(mapping::tile(&map, z, x, y)),
    })
    .await;
    match rendered {
        Ok(Err(unchanged)) => *unchanged,
        Ok(Ok(tile)) => tile_response(Ok(tile)),
        Err(r) => r,
    }
}

/// Tiles change as the map grows: caches may keep them but must revalidate (ETag).
const TILE_CACHE_CONTROL: &str = "no-cache";

/// 304 when the request's `If-None-Match` names `etag`.
fn not_modified(headers: &HeaderMap, etag: String) -> Option<Response> {
    let matches = headers.get(header::IF_NONE_MATCH).and_then(|v| v.to_str().ok()).is_some_and(|v| v.split(',').any(|t| t.trim() == etag));
    matches.then(|| {
        (StatusCode::NOT_MODIFIED, [(header::ETAG, etag), (header::CACHE_CONTROL, TILE_CACHE_CONTROL.to_string())]).into_response()
    })
}

/// A rendered tile as the response (PNG with its ETag), or its error.
fn tile_response(rendered: Result<Result<mapping::Tile, mapping::QueryError>, Response>) -> Response {
    match rendered {
        Ok(Ok(tile)) => (
            [
                (header::CONTENT_TYPE, "image/png".to_string()),
                (header::ETAG, tile.etag),
                (header::CACHE_CONTROL, TILE_CACHE_CONTROL.to_string()),
            ],
            tile.png,
        )
            .into_response(),
        Ok(Err(e)) => query_error(e),
        Err(r) => r,
    }
}

#[utoipa::path(
    get,
    path = "/api/v1/maps/{id}/legend",
    tag = "maps",
    params(
        ("id" = String, Path, description = "Session id"),
    ),
    responses(
        (status = 200, description = "Classes and colours of the tiles", body = Object),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn map_legend(State(registry): State<Arc<Registry>>, Path(id): Path<String>) -> Response {
    let map = match session_map(&registry, &id).await {
        Ok(m) => m,
        Err(r) => return r,
    };
    match blocking_query(move || mapping::legend(&map)).await {
        Ok(entries) => Json(json!({
            "session_id": id,
            "classes": legend_json(&entries),
        }))
        .into_response(),
        Err(r) => r,
    }
}

#[derive(serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub(crate) struct OccupancyQuery {
    /// Lowest height above the floor counted as an obstacle, metres.
    min_height: Option<f64>,
    /// Highest height counted, metres.
    max_height: Option<f64>,
    /// Cell size, metres.
    resolution: Option<f64>,
}

/// A tile's place in the path (the OpenAPI document's description of it).
#[derive(utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
#[allow(dead_code)]
pub(crate) struct TilePath {
    /// Zoom level.
    z: u8,
    /// Tile column.
    x: i64,
    /// Tile row followed by .png, e.g. 3.png.
    y: String,
}

async fn occupancy(registry: Arc<Registry>, id: String, q: OccupancyQuery) -> Result<stillmap_mapping::tiles::OccupancyGrid, Response> {
    let map = session_map(&registry, &id).await?;
    blocking_query(move || mapping::occupancy(&map, q.min_height, q.max_height, q.resolution)).await
}

#[utoipa::path(
    get,
    path = "/api/v1/maps/{id}/occupancy.pgm",
    tag = "maps",
    params(
        ("id" = String, Path, description = "Session id"),
        OccupancyQuery,
    ),
    responses(
        (status = 200, description = "ROS map_server occupancy image", content_type = "image/x-portable-graymap"),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn map_occupancy_pgm(
    State(registry): State<Arc<Registry>>,
    Path(id): Path<String>,
    JsonQuery(q): JsonQuery<OccupancyQuery>,
) -> Response {
    match occupancy(registry, id, q).await {
        Ok(grid) => ([(header::CONTENT_TYPE, "image/x-portable-graymap")], grid.to_pgm()).into_response(),
        Err(r) => r,
    }
}

#[utoipa::path(
    get,
    path = "/api/v1/maps/{id}/occupancy.yaml",
    tag = "maps",
    params(
        ("id" = String, Path, description = "Session id"),
        OccupancyQuery,
    ),
    responses(
        (status = 200, description = "ROS map_server parameters", body = String, content_type = "application/yaml"),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn map_occupancy_yaml(
    State(registry): State<Arc<Registry>>,
    Path(id): Path<String>,
    JsonQuery(q): JsonQuery<OccupancyQuery>,
) -> Response {
    match occupancy(registry, id, q).await {
        Ok(grid) => ([(header::CONTENT_TYPE, "application/yaml")], grid.to_yaml("occupancy.pgm")).into_response(),
        Err(r) => r,
    }
}

#[derive(serde::Deserialize)]
pub(crate) struct CloudQuery {
    bbox: Option<String>,
}

#[utoipa::path(
    get,
    path = "/api/v1/maps/{id}/cloud.ply",
    tag = "maps",
    params(
        ("id" = String, Path, description = "Session id"),
        ("bbox" = Option<String>, Query, description = "min_x,min_y,min_z,max_x,max_y,max_z in the map frame, metres"),
    ),
    responses(
        (status = 200, description = "Binary PLY point cloud with class colours", content_type = "application/octet-stream"),
        (status = 400, description = "Bad query", body = ApiError),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn map_cloud(
    State(registry): State<Arc<Registry>>,
    Path(id): Path<String>,
    JsonQuery(q): JsonQuery<CloudQuery>,
) -> Response {
    let map = match session_map(&registry, &id).await {
        Ok(m) => m,
        Err(r) => return r,
    };
    let bbox = match q.bbox.as_deref().map(mapping::parse_bbox).transpose() {
        Ok(b) => b,
        Err(e) => return error(StatusCode::BAD_REQUEST, e.0),
    };
    let session = id.clone();
    match blocking_query(move || mapping::ply(&map, &session, bbox.as_ref())).await {
        Ok(ply) => (
            [
                (header::CONTENT_TYPE, "application/octet-stream".to_string()),
                (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{id}.ply\"")),
            ],
            ply,
        )
            .into_response(),
        Err(r) => r,
    }
}

fn objects_json(objects: &[stillmap_mapping::export::MapObject], names: &[String]) -> Vec<Value> {
    objects
        .iter()
        .map(|o| {
            json!({
                "class_id": o.class,
                "class_name": names.get(usize::from(o.class)).cloned().unwrap_or_else(|| format!("class {}", o.class)),
                "centroid": o.centroid,
                "bbox_min": o.bbox.min,
                "bbox_max": o.bbox.max,
                "voxels": o.voxels,
                "confidence": o.confidence,
            })
        })
        .collect()
}

#[utoipa::path(
    get,
    path = "/api/v1/maps/{id}/objects",
    tag = "maps",
    params(
        ("id" = String, Path, description = "Session id"),
    ),
    responses(
        (status = 200, description = "Objects of the map with class and box", body = Object),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 503, description = "Part of the map cannot be read back from the store (no map with a hole is answered)", body = ApiError),
    )
)]
pub(crate) async fn map_objects(State(registry): State<Arc<Registry>>, Path(id): Path<String>) -> Response {
    let map = match session_map(&registry, &id).await {
        Ok(m) => m,
        Err(r) => return r,
    };
    match blocking_query(move || mapping::map_objects(&map)).await {
        Ok((objects, names)) => {
            Json(json!({ "session_id": id, "frame": MAP_FRAME, "objects": objects_json(&objects, &names) })).into_response()
        }
        Err(r) => r,
    }
}

/// How much larger than `store.import_max_bytes` an import's (compressed) body may
/// be: zstd's framing of incompressible data.
const IMPORT_BODY_MARGIN: usize = 1 << 20;

/// The request's credentials: its `Authorization` header, else an
/// `access_token` query parameter (a browser's `EventSource` and `<img>` cannot
/// send headers), as `Bearer <token>`.
fn credentials(headers: &HeaderMap, uri: &axum::http::Uri) -> Option<Vec<u8>> {
    if let Some(v) = headers.get(header::AUTHORIZATION) {
        return Some(v.as_bytes().to_vec());
    }
    let pairs: Vec<(String, String)> = serde_urlencoded::from_str(uri.query()?).ok()?;
    pairs.into_iter().find(|(k, _)| k == "access_token").map(|(_, v)| format!("Bearer {v}").into_bytes())
}

/// 401 / 403 unless the request's credentials carry `need` (when any token is configured).
#[allow(clippy::result_large_err)]
fn authorize(settings: &HttpSettings, headers: &HeaderMap, uri: &axum::http::Uri, need: crate::auth::Need) -> Result<(), Response> {
    settings.auth.get().check(credentials(headers, uri).as_deref(), need).map_err(|refusal| {
        let status = StatusCode::from_u16(refusal.http_status()).unwrap_or(StatusCode::UNAUTHORIZED);
        error(status, refusal.to_string())
    })
}

/// Every route but `/healthz`: at most `limits.http_requests_per_minute` per client
/// (its bearer token when it is a configured one, else its peer address: made-up
/// tokens cannot each get a bucket of their own), else 429 naming the limit.
async fn rate_limit(State(settings): State<Arc<HttpSettings>>, request: axum::extract::Request, next: axum::middleware::Next) -> Response {
    if request.uri().path() == "/healthz" {
        return next.run(request).await;
    }
    let (client, shown) = match credentials(request.headers(), request.uri()).filter(|c| settings.auth.get().known(Some(c))) {
        Some(token) => (format!("token {}", String::from_utf8_lossy(&token)), "this token".to_string()),
        None => match crate::api::serve::peer(&request) {
            Some(peer) => (format!("ip {}", peer.ip()), peer.ip().to_string()),
            None => ("unknown".to_string(), "this client".to_string()),
        },
    };
    match settings.rate_limits.http(&client, &shown) {
        Ok(()) => next.run(request).await,
        Err(message) => {
            let mut response = error(StatusCode::TOO_MANY_REQUESTS, message);
            response.headers_mut().insert(header::RETRY_AFTER, axum::http::HeaderValue::from_static("1"));
            response
        }
    }
}

/// The query APIs' layer: a token with the `read` scope.
async fn require_read(
    State(settings): State<Arc<HttpSettings>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    match authorize(&settings, request.headers(), request.uri(), crate::auth::Need::Read) {
        Ok(()) => next.run(request).await,
        Err(refused) => refused,
    }
}

/// The admin check as an extractor: it runs on the request's head, before a body
/// extractor reads (up to 1 GiB of) the body.
pub(crate) struct AdminOnly(Arc<HttpSettings>);

impl<S: Send + Sync> axum::extract::FromRequestParts<S> for AdminOnly {
    type Rejection = Response;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, _state: &S) -> Result<Self, Self::Rejection> {
        let transfer = parts
            .extensions
            .get::<Arc<HttpSettings>>()
            .cloned()
            .ok_or_else(|| error(StatusCode::INTERNAL_SERVER_ERROR, "HTTP settings missing on this route".into()))?;
        authorize(&transfer, &parts.headers, &parts.uri, crate::auth::Need::Admin)?;
        Ok(Self(transfer))
    }
}

/// The session as one file (everything committed to the store: up to its last keyframe).
#[utoipa::path(
    get,
    path = "/api/v1/maps/{id}/export",
    tag = "maps",
    params(
        ("id" = String, Path, description = "Session id"),
    ),
    responses(
        (status = 200, description = "The session as one .stillmap file (admin scope)", content_type = "application/octet-stream"),
        (status = 401, description = "No token", body = ApiError),
        (status = 403, description = "Not admin", body = ApiError),
        (status = 404, description = "Unknown session or no map", body = ApiError),
        (status = 409, description = "No store", body = ApiError),
    )
)]
pub(crate) async fn map_export(State(registry): State<Arc<Registry>>, AdminOnly(_): AdminOnly, Path(id): Path<String>) -> Response {
    if registry.info(&id).is_none() {
        return error(StatusCode::NOT_FOUND, format!("unknown session {id:?}"));
    }
    let Some(store) = registry.store().cloned() else {
        return error(StatusCode::CONFLICT, "exporting maps needs the store (store.enabled)".into());
    };
    let key = id.clone();
    let file = blocking(move || store.load(&key).and_then(|s| s.map(|s| crate::store::export(&s)).transpose())).await;
    match file {
        Ok(Ok(Some(bytes))) => (
            [
                (header::CONTENT_TYPE, "application/octet-stream".to_string()),
                (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{id}.stillmap\"")),
            ],
            bytes,
        )
            .into_response(),
        Ok(Ok(None)) => error(StatusCode::NOT_FOUND, format!("session {id:?} has nothing in the store")),
        Ok(Err(e)) => error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
        Err(r) => r,
    }
}

/// Adds a map file as a new (read-only) session: 201 with its id.
#[utoipa::path(
    post,
    path = "/api/v1/maps/import",
    tag = "maps",
    request_body(content = Vec<u8>, description = "A .stillmap file", content_type = "application/octet-stream"),
    responses(
        (status = 201, description = "Imported as a new read-only session", body = Imported),
        (status = 400, description = "Not a valid map file", body = ApiError),
        (status = 401, description = "No token", body = ApiError),
        (status = 403, description = "Not admin", body = ApiError),
        (status = 409, description = "Exists already, or no store", body = ApiError),
    )
)]
pub(crate) async fn map_import(State(registry): State<Arc<Registry>>, AdminOnly(transfer): AdminOnly, body: axum::body::Bytes) -> Response {
    let max_bytes = transfer.import_max_bytes;
    let parsed = match blocking(move || crate::store::import_file(&body, max_bytes)).await {
        Ok(p) => p,
        Err(r) => return r,
    };
    let stored = match parsed {
        Ok(s) => s,
        Err(e) => return error(StatusCode::BAD_REQUEST, e.to_string()),
    };
    let r = registry.clone();
    match blocking(move || r.import(stored)).await {
        Ok(Ok(id)) => (StatusCode::CREATED, Json(Imported { session_id: id })).into_response(),
        Ok(Err(e @ crate::session::ImportError::Exists(_))) => error(StatusCode::CONFLICT, e.to_string()),
        Ok(Err(e @ crate::session::ImportError::NoStore)) => error(StatusCode::CONFLICT, e.to_string()),
        Ok(Err(e)) => error(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()),
        Err(r) => r,
    }
}
