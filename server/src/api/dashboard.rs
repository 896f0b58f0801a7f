//! The web dashboard's shell: its files (plain ES modules from the repository's
//! `dashboard/`, three.js from its `node_modules`) and the fleet-wide event stream
//! (Server-Sent Events) it draws live from.

use std::collections::HashMap;
use std::convert::Infallible;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use axum::extract::{Path as UrlPath, State};
use axum::http::{StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use serde_json::{Value, json};
use stillmap_proto::pb;
use tokio::sync::{broadcast, watch};
use tokio_stream::StreamExt;
use tokio_stream::wrappers::{BroadcastStream, WatchStream};

use crate::session::Registry;

/// How often the event stream sends the sessions snapshot.
const SNAPSHOT_INTERVAL: Duration = Duration::from_millis(500);
/// Largest dashboard file served (three.js is ~1.3 MB).
const MAX_ASSET_BYTES: u64 = 8 << 20;

/// Finds the dashboard folder: the configured one, else `dashboard/` in the working
/// directory, else two levels above the executable (`target/<profile>/../../dashboard`).
pub fn locate(configured: &str) -> Option<PathBuf> {
    if !configured.is_empty() {
        return Some(PathBuf::from(configured));
    }
    let mut candidates = vec![PathBuf::from("dashboard")];
    if let Ok(exe) = std::env::current_exe()
        && let Some(dir) = exe.parent()
    {
        candidates.push(dir.join("../../dashboard"));
    }
    candidates.into_iter().find(|d| d.join("index.html").is_file())
}

#[derive(Clone)]
pub struct DashboardState {
    pub registry: Arc<Registry>,
    pub dir: Option<PathBuf>,
    pub feed: Arc<EventFeed>,
}

#[utoipa::path(
    get,
    path = "/",
    tag = "server",
    security(()),
    responses(
        (status = 200, description = "The dashboard", content_type = "text/html"),
    )
)]
pub async fn index(State(state): State<DashboardState>) -> Response {
    let Some(dir) = &state.dir else {
        return (StatusCode::NOT_FOUND, Html(NOT_BUILT.to_string())).into_response();
    };
    match tokio::fs::read_to_string(dir.join("index.html")).await {
        Ok(html) => ([(header::CACHE_CONTROL, "no-cache")], Html(html)).into_response(),
        Err(e) => (StatusCode::NOT_FOUND, Html(format!("{NOT_BUILT}<p>{e}</p>"))).into_response(),
    }
}

const NOT_BUILT: &str = "<!doctype html><title>stillmap</title><h1>stillmap</h1><p>The dashboard files were not found: run <code>make dashboard</code> in the repository, or set <code>http.dashboard_dir</code>.</p>";

/// `/assets/<path>`: `src/` of the dashboard, and `vendor/three/...` from its node_modules.
#[utoipa::path(
    get,
    path = "/assets/{path}",
    tag = "server",
    security(()),
    params(
        ("path" = String, Path, description = "A file of the dashboard"),
    ),
    responses(
        (status = 200, description = "The file"),
        (status = 400, description = "Not a plain file name", body = crate::api::openapi::ApiError),
        (status = 404, description = "No such file", body = crate::api::openapi::ApiError),
    )
)]
pub async fn asset(State(state): State<DashboardState>, UrlPath(path): UrlPath<String>) -> Response {
    let Some(dir) = &state.dir else {
        return not_found(&path);
    };
    // Only plain names: no "..", no absolute paths, no hidden files.
    let ok = !path.is_empty()
        && path
            .split('/')
            .all(|c| !c.is_empty() && !c.starts_with('.') && c.chars().all(|ch| ch.is_ascii_alphanumeric() || "._-".contains(ch)));
    if !ok {
        return (StatusCode::BAD_REQUEST, axum::Json(json!({ "error": format!("bad asset path {path:?}") }))).into_response();
    }
    let file = match path.strip_prefix("vendor/three/") {
        Some(rest) => dir.join("node_modules/three").join(rest),
        None => dir.join("src").join(&path),
    };
    serve_file(&file, &path).await
}

async fn serve_file(file: &Path, name: &str) -> Response {
    let Ok(meta) = tokio::fs::metadata(file).await else { return not_found(name) };
    if !meta.is_file() || meta.len() > MAX_ASSET_BYTES {
        return not_found(name);
    }
    let Ok(bytes) = tokio::fs::read(file).await else { return not_found(name) };
    let kind = match file.extension().and_then(|e| e.to_str()) {
        Some("js") => "text/javascript; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("html") => "text/html; charset=utf-8",
        Some("svg") => "image/svg+xml",
        Some("png") => "image/png",
        _ => "application/octet-stream",
    };
    ([(header::CONTENT_TYPE, kind), (header::CACHE_CONTROL, "no-cache")], bytes).into_response()
}

fn not_found(name: &str) -> Response {
    (StatusCode::NOT_FOUND, axum::Json(json!({ "error": format!("no dashboard asset {name:?} (run make dashboard)") }))).into_response()
}

/// What one session in memory looks like on the dashboard.
fn session_json(s: &crate::session::Session, fps: f64) -> Value {
    let latency: HashMap<_, _> = s.last_latency().iter().map(|l| (l.stage.clone(), f64::from(l.micros) / 1000.0)).collect();
    let map = s
        .map()
        .map(crate::map::summary)
        .map(|(version, keyframes, occupied)| json!({ "version": version, "keyframes": keyframes, "occupied_voxels": occupied }));
    listed_json(&s.info(), fps, json!(latency), map.unwrap_or(Value::Null))
}

/// A session's row: in memory, or out of it (no latencies, no map summary: its map
/// loads when selected).
fn listed_json(info: &crate::session::SessionInfo, fps: f64, latency_ms: Value, map: Value) -> Value {
    let summary = &info.summary;
    json!({
        "session_id": summary.session_id,
        "robot_id": summary.robot_id,
        "transport": summary.transport,
        "connected": summary.connected,
        "archived": info.archived,
        "tracking_state": pb::TrackingState::try_from(summary.tracking_state).map(|t| t.as_str_name()).unwrap_or("UNKNOWN"),
        "frames_received": summary.frames_received,
        "frames_processed": summary.frames_processed,
        "frames_dropped": summary.frames_dropped,
        "frames_rejected": summary.frames_rejected,
        "fps": fps,
        "latency_ms": latency_ms,
        "pose": info.latest.and_then(|p| p.world_from_camera).map(|p| {
            let (t, q) = (p.translation.unwrap_or_default(), p.rotation.unwrap_or_default());
            json!({ "translation": [t.x, t.y, t.z], "rotation_xyzw": [q.x, q.y, q.z, q.w] })
        }),
        "map": map,
    })
}

/// Pose events buffered for viewers; one that falls further behind skips poses
/// (it redraws from the next ones).
const POSE_EVENTS_BUFFER: usize = 64;
/// Poses one `poses` event carries at most; more in one interval are dropped (the
/// viewer's trajectories then skip them; the snapshot and the query APIs have them).
const MAX_POSES_PER_EVENT: usize = 4096;

/// The dashboard's event stream, built once for every viewer: the sessions
/// snapshot every 500 ms (on a blocking thread, not the runtime that serves the
/// robots) and the new poses every `pose_interval`, serialised once; a viewer only copies text out. Started
/// by the first viewer; the snapshot is skipped while nobody watches.
pub struct EventFeed {
    registry: Arc<Registry>,
    snapshot: watch::Sender<Arc<str>>,
    poses: broadcast::Sender<Arc<str>>,
    started: std::sync::Once,
    viewers: Arc<AtomicUsize>,
    max_viewers: usize,
    /// New poses go out together, one `poses` event per interval
    /// (`http.pose_event_interval_ms`): a viewer's writes do not grow with the fleet's
    /// frame rate (16 robots at 30 Hz would be 480 events a second per viewer).
    pose_interval: Duration,
    /// The other servers' sessions and poses (a cluster on Zenoh).
    remote: Option<Arc<dyn crate::api::RemoteLive>>,
}

impl EventFeed {
    pub fn new(
        registry: Arc<Registry>,
        max_viewers: usize,
        pose_interval: Duration,
        remote: Option<Arc<dyn crate::api::RemoteLive>>,
    ) -> Arc<Self> {
        Arc::new(Self {
            remote,
            registry,
            snapshot: watch::channel(Arc::from("{\"sessions\":[]}")).0,
            poses: broadcast::channel(POSE_EVENTS_BUFFER).0,
            started: std::sync::Once::new(),
            viewers: Arc::default(),
            max_viewers,
            pose_interval,
        })
    }

    /// Viewers connected now.
    pub fn viewers(&self) -> usize {
        self.viewers.load(Ordering::SeqCst)
    }

    /// Starts the two producer tasks (on the caller's runtime), once.
    fn start(self: &Arc<Self>) {
        self.started.call_once(|| {
            let feed = self.clone();
            tokio::spawn(async move {
                let mut previous: HashMap<String, (u64, Instant)> = HashMap::new();
                let mut interval = tokio::time::interval(SNAPSHOT_INTERVAL);
                interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
                loop {
                    interval.tick().await;
                    if feed.snapshot.receiver_count() == 0 {
                        continue;
                    }
                    let registry = feed.registry.clone();
                    let Ok((mut sessions, seen, not_shown)) = tokio::task::spawn_blocking(move || session_list(&registry, previous)).await
                    else {
                        break;
                    };
                    previous = seen;
                    if let Some(remote) = &feed.remote {
                        sessions = with_remote(sessions, remote.own_id(), remote.sessions());
                    }
                    let snapshot = if not_shown > 0 {
                        json!({ "sessions": sessions, "stored_not_shown": not_shown })
                    } else {
                        json!({ "sessions": sessions })
                    };
                    feed.snapshot.send_replace(Arc::from(snapshot.to_string()));
                }
            });
            let feed = self.clone();
            let mut local = feed.registry.subscribe_fleet();
            // The other servers' poses, when there are other servers.
            let mut remote = feed.remote.as_ref().map(|r| r.subscribe_poses());
            tokio::spawn(async move {
                let mut pending: Vec<String> = Vec::new();
                let mut interval = tokio::time::interval(feed.pose_interval);
                interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
                loop {
                    let mut remote_closed = false;
                    let from_remote = async {
                        match remote.as_mut() {
                            Some(r) => r.recv().await,
                            None => std::future::pending().await,
                        }
                    };
                    tokio::select! {
                        received = local.recv() => match received {
                            Ok((id, p)) => feed.pending_pose(&mut pending, &id, &p),
                            Err(broadcast::error::RecvError::Lagged(_)) => {}
                            Err(broadcast::error::RecvError::Closed) => break,
                        },
                        received = from_remote => match received {
                            Ok((id, p)) => feed.pending_pose(&mut pending, &id, &p),
                            Err(broadcast::error::RecvError::Lagged(_)) => {}
                            Err(broadcast::error::RecvError::Closed) => remote_closed = true,
                        },
                        _ = interval.tick() => {
                            if !pending.is_empty() {
                                let text = format!("[{}]", pending.join(","));
                                pending.clear();
                                let _ = feed.poses.send(Arc::from(text));
                            }
                        }
                    }
                    if remote_closed {
                        remote = None;
                    }
                }
            });
        });
    }
}

impl EventFeed {
    /// Adds a pose to the next `poses` event (while anyone watches, up to the cap).
    fn pending_pose(&self, pending: &mut Vec<String>, id: &str, p: &pb::PoseStamped) {
        if pending.len() < MAX_POSES_PER_EVENT && self.poses.receiver_count() > 0 {
            let pose = p.world_from_camera.unwrap_or_default();
            let (t, q) = (pose.translation.unwrap_or_default(), pose.rotation.unwrap_or_default());
            pending.push(
                json!({ "session_id": id, "sequence": p.sequence, "translation": [t.x, t.y, t.z], "rotation_xyzw": [q.x, q.y, q.z, q.w] })
                    .to_string(),
            );
        }
    }
}

/// This server's sessions (tagged `server_id` = `own`) and the other servers'.
/// A session listed twice (stored here, live there after a move) is shown once:
/// the connected one, else this server's.
fn with_remote(mut sessions: Vec<Value>, own: &str, remote: Vec<Value>) -> Vec<Value> {
    for s in &mut sessions {
        if let Some(o) = s.as_object_mut() {
            o.insert("server_id".into(), own.into());
        }
    }
    let mut at: HashMap<String, usize> =
        sessions.iter().enumerate().filter_map(|(i, s)| Some((s["session_id"].as_str()?.to_string(), i))).collect();
    for theirs in remote {
        let id = theirs["session_id"].as_str().unwrap_or_default().to_string();
        match at.get(&id) {
            Some(&i) => {
                if theirs["connected"] == true && sessions[i]["connected"] != true {
                    sessions[i] = theirs;
                }
            }
            None => {
                at.insert(id, sessions.len());
                sessions.push(theirs);
            }
        }
    }
    sessions
}

/// The stored sessions (not in memory) the dashboard's snapshot lists: the newest.
/// The snapshot goes to every viewer and every other server twice a second; a
/// store that has kept thousands of sessions is listed page by page by
/// `GET /api/v1/sessions`.
pub const SNAPSHOT_STORED_SESSIONS: usize = 100;

/// The sessions event's list (every session in memory, then the newest
/// [`SNAPSHOT_STORED_SESSIONS`] stored ones, oldest first), each session's
/// processed count and time (for the next list's frames/s), and how many stored
/// sessions are not listed.
pub(crate) fn session_list(
    registry: &Registry,
    mut previous: HashMap<String, (u64, Instant)>,
) -> (Vec<Value>, HashMap<String, (u64, Instant)>, usize) {
    let now = Instant::now();
    let dormant = registry.dormant();
    let not_shown = dormant.len().saturating_sub(SNAPSHOT_STORED_SESSIONS);
    let list = registry.list();
    let mut seen = HashMap::with_capacity(list.len());
    let sessions: Vec<Value> = list
        .iter()
        .map(|s| {
            let processed = s.counters.processed.load(Ordering::Relaxed);
            let fps = match previous.remove(&s.id) {
                Some((p, t)) if now > t => (processed.saturating_sub(p)) as f64 / (now - t).as_secs_f64(),
                _ => 0.0,
            };
            seen.insert(s.id.clone(), (processed, now));
            session_json(s, fps)
        })
        .chain(dormant[not_shown..].iter().map(|d| listed_json(d, 0.0, json!({}), Value::Null)))
        .collect();
    (sessions, seen, not_shown)
}

/// Counts a viewer for as long as its stream lives.
struct Viewer(Arc<AtomicUsize>);

impl Drop for Viewer {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

/// `GET /api/v1/events`: `sessions` every 500 ms (the table, frames/s, latencies,
/// map versions) and `poses` every `http.pose_event_interval_ms` (250) while there are new ones (a JSON array of
/// every session's new poses, oldest first). Beyond
/// `http.max_event_viewers` at once: 503.
#[utoipa::path(
    get,
    path = "/api/v1/events",
    tag = "sessions",
    responses(
        (status = 200, description = "Server-sent events: sessions every 500 ms, poses as they come", content_type = "text/event-stream"),
        (status = 503, description = "Too many viewers (http.max_event_viewers)", body = crate::api::openapi::ApiError),
    )
)]
pub async fn events(State(state): State<DashboardState>) -> Response {
    let feed = state.feed.clone();
    if feed.viewers.fetch_add(1, Ordering::SeqCst) >= feed.max_viewers {
        feed.viewers.fetch_sub(1, Ordering::SeqCst);
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            axum::Json(json!({ "error": format!("too many dashboard viewers: http.max_event_viewers = {}", feed.max_viewers) })),
        )
            .into_response();
    }
    let viewer = Viewer(feed.viewers.clone());
    // The other servers publish their live data while a viewer watches here.
    let watching = feed.remote.as_ref().map(|r| r.watch());
    feed.start();
    let sessions = WatchStream::new(feed.snapshot.subscribe()).map(|text| Event::default().event("sessions").data(&*text));
    let poses =
        BroadcastStream::new(feed.poses.subscribe()).filter_map(|p| p.ok().map(|text| Event::default().event("poses").data(&*text)));
    let stream = sessions.merge(poses).map(move |event| {
        let _counted = (&viewer, &watching);
        Ok::<_, Infallible>(event)
    });
    Sse::new(stream).keep_alive(KeepAlive::default()).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every row is tagged with its server; a session both list is shown once, the
    /// connected one (or this server's when neither is).
    #[test]
    fn other_servers_rows_join_this_servers_once_each() {
        let row = |id: &str, connected: bool| json!({ "session_id": id, "connected": connected });
        let theirs = |id: &str, connected: bool| {
            let mut r = row(id, connected);
            r["server_id"] = "b".into();
            r
        };
        let merged = with_remote(
            vec![row("moved", false), row("here", true), row("both-stored", false)],
            "a",
            vec![theirs("moved", true), theirs("there", true), theirs("both-stored", false), theirs("here", false)],
        );
        let by_id = |id: &str| merged.iter().find(|s| s["session_id"] == id).map(|s| s["server_id"].clone());
        assert_eq!(merged.len(), 4, "{merged:?}");
        assert_eq!(by_id("moved"), Some("b".into()), "live there");
        assert_eq!(by_id("here"), Some("a".into()), "live here");
        assert_eq!(by_id("both-stored"), Some("a".into()), "neither live: ours");
        assert_eq!(by_id("there"), Some("b".into()));
    }
}
