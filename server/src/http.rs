//! HTTP shell (axum): health, sessions, metrics. Errors are JSON `{"error": "..."}`.

use std::sync::Arc;

use axum::extract::{Path, Query, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde_json::{Value, json};
use stillmap_proto::pb;

use crate::session::{Registry, Session, summary};

pub fn router(registry: Arc<Registry>) -> Router {
    Router::new()
        .route("/healthz", get(|| async { Json(json!({ "status": "ok" })) }))
        .route("/api/v1/sessions", get(list_sessions))
        .route("/api/v1/sessions/{id}", get(get_session))
        .route("/api/v1/sessions/{id}/pose", get(get_pose))
        .route("/api/v1/sessions/{id}/trajectory", get(get_trajectory))
        .route("/metrics", get(metrics))
        .fallback(|| async { error(StatusCode::NOT_FOUND, "no such endpoint".into()) })
        .with_state(registry)
}

fn error(code: StatusCode, message: String) -> Response {
    (code, Json(json!({ "error": message }))).into_response()
}

fn enum_name<E: TryFrom<i32>>(v: i32, name: impl Fn(E) -> &'static str) -> &'static str {
    E::try_from(v).map(name).unwrap_or("UNKNOWN")
}

fn camera_json(c: &pb::CameraInfo) -> Value {
    json!({
        "width": c.width, "height": c.height,
        "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
        "distortion_model": enum_name(c.distortion_model, |m: pb::DistortionModel| m.as_str_name()),
        "distortion_coeffs": c.distortion_coeffs,
        "depth_units_per_metre": c.depth_units_per_metre,
        "color_encoding": enum_name(c.color_encoding, |e: pb::ColorEncoding| e.as_str_name()),
        "depth_encoding": enum_name(c.depth_encoding, |e: pb::DepthEncoding| e.as_str_name()),
        "nominal_rate_hz": c.nominal_rate_hz,
    })
}

fn session_json(s: &Session, detail: bool) -> Value {
    let sum = summary(s);
    let mut v = json!({
        "session_id": sum.session_id,
        "robot_id": sum.robot_id,
        "transport": sum.transport,
        "connected": sum.connected,
        "tracking_state": enum_name(sum.tracking_state, |t: pb::TrackingState| t.as_str_name()),
        "started_unix_ns": sum.started_unix_ns,
        "counters": {
            "frames_received": sum.frames_received,
            "frames_processed": sum.frames_processed,
            "frames_dropped": sum.frames_dropped,
            "frames_rejected": sum.frames_rejected,
            "bytes_received": s.counters.bytes.load(std::sync::atomic::Ordering::Relaxed),
            "last_received_sequence": s.last_received_sequence(),
        },
    });
    if detail && let Some(c) = &sum.camera {
        v["camera"] = camera_json(c);
    }
    v
}

async fn list_sessions(State(registry): State<Arc<Registry>>) -> Json<Value> {
    let sessions: Vec<Value> = registry.list().iter().map(|s| session_json(s, false)).collect();
    Json(json!({ "sessions": sessions }))
}

async fn get_session(State(registry): State<Arc<Registry>>, Path(id): Path<String>) -> Response {
    match registry.get(&id) {
        Some(s) => Json(session_json(&s, true)).into_response(),
        None => error(StatusCode::NOT_FOUND, format!("unknown session {id:?}")),
    }
}

fn pose_json(p: &pb::PoseStamped) -> Value {
    let pose = p.world_from_camera.unwrap_or_default();
    let t = pose.translation.unwrap_or_default();
    let q = pose.rotation.unwrap_or_default();
    json!({
        "sequence": p.sequence,
        "capture_time_ns": p.capture_time_ns,
        "tracking_state": enum_name(p.tracking_state, |t: pb::TrackingState| t.as_str_name()),
        "translation": [t.x, t.y, t.z],
        "rotation_xyzw": [q.x, q.y, q.z, q.w],
    })
}

/// What the pose endpoints say about the frame of reference.
const WORLD_FRAME: &str = "world = the camera frame of the session's first tracked frame (x right, y down, z forward); poses are world_from_camera";

async fn get_pose(State(registry): State<Arc<Registry>>, Path(id): Path<String>) -> Response {
    let Some(s) = registry.get(&id) else {
        return error(StatusCode::NOT_FOUND, format!("unknown session {id:?}"));
    };
    let track = s.tracking();
    Json(json!({
        "session_id": s.id,
        "tracking_state": track.state.as_str_name(),
        "frame": WORLD_FRAME,
        "pose": track.latest.as_ref().map(pose_json),
    }))
    .into_response()
}

#[derive(serde::Deserialize)]
struct TrajectoryQuery {
    format: Option<String>,
}

async fn get_trajectory(
    State(registry): State<Arc<Registry>>,
    Path(id): Path<String>,
    Query(q): Query<TrajectoryQuery>,
) -> Response {
    let Some(s) = registry.get(&id) else {
        return error(StatusCode::NOT_FOUND, format!("unknown session {id:?}"));
    };
    let poses = s.tracking().trajectory.clone();
    match q.format.as_deref() {
        None | Some("json") => Json(json!({
            "session_id": s.id,
            "frame": WORLD_FRAME,
            "poses": poses.iter().map(pose_json).collect::<Vec<_>>(),
        }))
        .into_response(),
        Some("tum") => {
            let mut text = String::from("# timestamp tx ty tz qx qy qz qw (stillmap world_from_camera)\n");
            for p in &poses {
                let pose = p.world_from_camera.unwrap_or_default();
                let (t, r) = (pose.translation.unwrap_or_default(), pose.rotation.unwrap_or_default());
                let ns = p.capture_time_ns;
                text.push_str(&format!(
                    "{}.{:09} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n",
                    ns / 1_000_000_000,
                    ns % 1_000_000_000,
                    t.x,
                    t.y,
                    t.z,
                    r.x,
                    r.y,
                    r.z,
                    r.w
                ));
            }
            ([(header::CONTENT_TYPE, "text/plain; charset=utf-8")], text).into_response()
        }
        Some(other) => error(StatusCode::BAD_REQUEST, format!("unknown trajectory format {other:?}; use json or tum")),
    }
}

async fn metrics(State(registry): State<Arc<Registry>>) -> Response {
    (
        [(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")],
        registry.metrics().render(),
    )
        .into_response()
}
