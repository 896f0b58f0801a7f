//! The HTTP API's OpenAPI 3.1 description, served at `GET /api/v1/openapi.json`:
//! generated (utoipa) from the handlers' `#[utoipa::path]` attributes and from the
//! response types below, which the handlers serialize. The fleet and map
//! documents are described as objects (their fields are in the README).

use serde::Serialize;
use stillmap_proto::pb;
use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
use utoipa::{Modify, OpenApi, ToSchema};

use crate::api::{dashboard, http};
use crate::session::SessionInfo;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "stillmap",
        description = "Networked mapping server for robots: sessions, poses, trajectories, fleets and static semantic maps. \
                       Every route but /healthz, /api/v1/openapi.json and the dashboard's files needs a token with the \
                       `read` scope when tokens are configured (export and import: `admin`), as `Authorization: Bearer` \
                       or an `access_token` query parameter. Errors are JSON `{\"error\": \"...\"}`."
    ),
    paths(
        http::list_sessions,
        http::get_session,
        http::get_pose,
        http::get_trajectory,
        http::session_mcap,
        http::list_fleets,
        http::get_fleet,
        http::fleet_cloud,
        http::fleet_occupancy_pgm,
        http::fleet_occupancy_yaml,
        http::fleet_objects,
        http::fleet_tile,
        http::fleet_legend,
        http::map_info,
        http::map_tile,
        http::map_legend,
        http::map_occupancy_pgm,
        http::map_occupancy_yaml,
        http::map_cloud,
        http::map_objects,
        http::map_export,
        http::map_import,
        http::metrics,
        http::healthz,
        http::openapi,
        dashboard::events,
        dashboard::index,
        dashboard::asset,
    ),
    components(schemas(ApiError, SessionList, SessionView, Counters, CameraView, PoseReply, PoseView, Trajectory, Health, StoreHealth, Imported)),
    modifiers(&BearerAuth),
    security(("bearer" = [])),
    tags(
        (name = "sessions", description = "Robots' sessions, poses and trajectories"),
        (name = "fleets", description = "Robots merged into one frame, and the fleet map"),
        (name = "maps", description = "A session's static semantic map"),
        (name = "server", description = "Health, metrics, this document, the dashboard"),
    )
)]
pub struct ApiDoc;

/// The bearer-token scheme every protected route names.
struct BearerAuth;

impl Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme("bearer", SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()));
    }
}

/// The document, as served.
pub fn document() -> utoipa::openapi::OpenApi {
    ApiDoc::openapi()
}

/// Every error: 4xx and 5xx.
#[derive(Debug, Serialize, ToSchema)]
pub struct ApiError {
    /// What was wrong, naming the input.
    pub error: String,
}

/// `GET /api/v1/sessions`.
#[derive(Debug, Serialize, ToSchema)]
pub struct SessionList {
    pub sessions: Vec<SessionView>,
    /// Where more sessions follow: the `page_token` of the next page.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next_page_token: Option<String>,
}

/// A session: live, archived (restored from the store) or imported.
#[derive(Debug, Serialize, ToSchema)]
pub struct SessionView {
    pub session_id: String,
    pub robot_id: String,
    /// `grpc` or `zenoh`.
    pub transport: String,
    pub connected: bool,
    /// Read-only: restored from the store or evicted from memory.
    pub archived: bool,
    /// In memory now.
    pub resident: bool,
    pub fleet: String,
    /// `TRACKING_STATE_*` of the proto.
    pub tracking_state: String,
    pub started_unix_ns: u64,
    pub counters: Counters,
    /// Only in `GET /api/v1/sessions/{id}`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraView>,
    /// On servers sharing a Zenoh network, in the sessions list: the server holding
    /// the session (its `--server-id`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub server_id: Option<String>,
}

#[derive(Debug, Serialize, ToSchema)]
pub struct Counters {
    pub frames_received: u64,
    pub frames_processed: u64,
    pub frames_dropped: u64,
    pub frames_rejected: u64,
    pub bytes_received: u64,
    pub last_received_sequence: Option<u64>,
}

/// The camera as the robot's hello stated it.
#[derive(Debug, Serialize, ToSchema)]
pub struct CameraView {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// `DISTORTION_MODEL_*` of the proto.
    pub distortion_model: String,
    pub distortion_coeffs: Vec<f64>,
    pub depth_units_per_metre: f64,
    pub color_encoding: String,
    pub depth_encoding: String,
    pub nominal_rate_hz: f64,
    pub rolling_shutter_readout_s: f64,
    pub exposure_time_offset_s: f64,
    /// Where the calibration came from (`unstated` when the hello did not say).
    pub calibration_source: String,
}

/// `GET /api/v1/sessions/{id}/pose`.
#[derive(Debug, Serialize, ToSchema)]
pub struct PoseReply {
    pub session_id: String,
    pub tracking_state: String,
    /// The frame of reference the pose is in.
    pub frame: String,
    /// `null` until the session has a pose.
    pub pose: Option<PoseView>,
}

/// A camera pose: `world_from_camera` (or `fleet_from_camera` with `?frame=fleet`).
#[derive(Debug, Serialize, ToSchema)]
pub struct PoseView {
    pub sequence: u64,
    pub capture_time_ns: u64,
    /// The time the pose refers to.
    pub pose_time_ns: u64,
    pub tracking_state: String,
    /// Metres.
    pub translation: [f64; 3],
    pub rotation_xyzw: [f64; 4],
}

/// `GET /api/v1/sessions/{id}/trajectory` (JSON).
#[derive(Debug, Serialize, ToSchema)]
pub struct Trajectory {
    pub session_id: String,
    pub frame: String,
    pub poses: Vec<PoseView>,
    /// Where more poses of the range follow (at most `limit` per answer): ask
    /// again with `start_ns` = this.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next_start_ns: Option<u64>,
}

/// `GET /healthz`.
#[derive(Debug, Serialize, ToSchema)]
pub struct Health {
    /// `ok`, or `unhealthy` (503) while the store fails to write.
    pub status: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub store: Option<StoreHealth>,
}

#[derive(Debug, Serialize, ToSchema)]
pub struct StoreHealth {
    pub error: String,
    pub failing_since_unix_ns: u64,
    pub errors_total: u64,
}

/// `POST /api/v1/maps/import`: 201.
#[derive(Debug, Serialize, ToSchema)]
pub struct Imported {
    pub session_id: String,
}

fn enum_name<E: TryFrom<i32>>(v: i32, name: impl Fn(E) -> &'static str) -> String {
    E::try_from(v).map(name).unwrap_or("UNKNOWN").to_string()
}

impl CameraView {
    fn from(c: &pb::CameraInfo) -> Self {
        Self {
            width: c.width,
            height: c.height,
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            distortion_model: enum_name(c.distortion_model, |m: pb::DistortionModel| m.as_str_name()),
            distortion_coeffs: c.distortion_coeffs.clone(),
            depth_units_per_metre: c.depth_units_per_metre,
            color_encoding: enum_name(c.color_encoding, |e: pb::ColorEncoding| e.as_str_name()),
            depth_encoding: enum_name(c.depth_encoding, |e: pb::DepthEncoding| e.as_str_name()),
            nominal_rate_hz: c.nominal_rate_hz,
            rolling_shutter_readout_s: c.rolling_shutter_readout_s,
            exposure_time_offset_s: c.exposure_time_offset_s,
            calibration_source: if c.calibration_source.is_empty() { "unstated".into() } else { c.calibration_source.clone() },
        }
    }
}

impl SessionView {
    /// `detail`: with the camera.
    pub fn from(s: &SessionInfo, detail: bool) -> Self {
        let sum = &s.summary;
        Self {
            session_id: sum.session_id.clone(),
            robot_id: sum.robot_id.clone(),
            transport: sum.transport.clone(),
            connected: sum.connected,
            archived: s.archived,
            resident: s.resident,
            fleet: s.fleet.clone(),
            tracking_state: enum_name(sum.tracking_state, |t: pb::TrackingState| t.as_str_name()),
            started_unix_ns: sum.started_unix_ns,
            counters: Counters {
                frames_received: sum.frames_received,
                frames_processed: sum.frames_processed,
                frames_dropped: sum.frames_dropped,
                frames_rejected: sum.frames_rejected,
                bytes_received: s.bytes_received,
                last_received_sequence: s.last_received_sequence,
            },
            camera: if detail { sum.camera.as_ref().map(CameraView::from) } else { None },
            server_id: None,
        }
    }
}

impl PoseView {
    pub fn from(p: &pb::PoseStamped) -> Self {
        let pose = p.world_from_camera.unwrap_or_default();
        let t = pose.translation.unwrap_or_default();
        let q = pose.rotation.unwrap_or_default();
        Self {
            sequence: p.sequence,
            capture_time_ns: p.capture_time_ns,
            pose_time_ns: p.time_ns(),
            tracking_state: enum_name(p.tracking_state, |t: pb::TrackingState| t.as_str_name()),
            translation: [t.x, t.y, t.z],
            rotation_xyzw: [q.x, q.y, q.z, q.w],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The routes as the router declares them (`.route("PATH", METHOD(...))` in the
    /// HTTP shell's source), with axum's `{*rest}` written as OpenAPI's `{rest}`.
    fn declared_routes() -> Vec<(String, String)> {
        let source = include_str!("http.rs");
        let mut routes = Vec::new();
        for piece in source.split(".route(\"").skip(1) {
            let Some((path, rest)) = piece.split_once("\", ") else { continue };
            let method = rest.chars().take_while(|c| c.is_ascii_alphabetic()).collect::<String>();
            routes.push((path.replace("{*", "{"), method));
        }
        routes
    }

    /// Every route the server answers is in the document with its method, and the
    /// document names no route the server does not answer.
    #[test]
    fn every_route_is_in_the_document_and_nothing_else() {
        let routes = declared_routes();
        assert!(routes.len() >= 27, "found only {} routes in http.rs: {routes:?}", routes.len());
        let doc = serde_json::to_value(document()).expect("serializes");
        let paths = doc["paths"].as_object().expect("paths");
        for (path, method) in &routes {
            assert!(paths.get(path).and_then(|p| p.get(method)).is_some(), "{method} {path} is not in the OpenAPI document");
        }
        let documented: usize = paths.values().map(|p| p.as_object().map_or(0, |m| m.len())).sum();
        assert_eq!(documented, routes.len(), "the document has operations the router does not: {:?}", paths.keys().collect::<Vec<_>>());
        assert_eq!(doc["openapi"], "3.1.0");
    }

    /// Protected routes name the bearer scheme; the open ones say no token is needed.
    #[test]
    fn open_routes_need_no_token_and_the_others_name_the_scheme() {
        let doc = serde_json::to_value(document()).expect("serializes");
        assert_eq!(doc["components"]["securitySchemes"]["bearer"]["scheme"], "bearer");
        assert_eq!(doc["security"][0]["bearer"], serde_json::json!([]));
        for open in ["/healthz", "/api/v1/openapi.json", "/", "/assets/{path}"] {
            assert_eq!(doc["paths"][open]["get"]["security"], serde_json::json!([{}]), "{open} is open");
        }
        assert!(doc["paths"]["/api/v1/sessions"]["get"].get("security").is_none(), "sessions take the document's bearer default");
        // Parameters come from the query and path types the handlers read.
        let names = |path: &str| -> Vec<String> {
            doc["paths"][path]["get"]["parameters"].as_array().map_or(Vec::new(), |p| {
                p.iter().map(|q| format!("{}:{}", q["in"].as_str().unwrap_or(""), q["name"].as_str().unwrap_or(""))).collect()
            })
        };
        assert_eq!(
            names("/api/v1/maps/{id}/occupancy.pgm"),
            ["path:id", "query:min_height", "query:max_height", "query:resolution"],
            "{}",
            doc["paths"]["/api/v1/maps/{id}/occupancy.pgm"]
        );
        assert_eq!(names("/api/v1/fleets/{fleet}/tiles/{z}/{x}/{y}"), ["path:fleet", "path:z", "path:x", "path:y"]);
        let session = &doc["components"]["schemas"]["SessionView"]["properties"];
        assert!(session.get("counters").is_some() && session.get("camera").is_some(), "{session}");
    }
}
