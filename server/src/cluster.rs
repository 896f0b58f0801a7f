//! The server among servers on one Zenoh network: while it runs it holds the
//! liveliness token `stillmap-cluster/servers/<server_id>` (Zenoh withdraws it when
//! the process or its link dies, `kill -9` included), and it answers queries on
//! `stillmap-cluster/servers/<server_id>/status` with its [`ServerStatus`] as JSON:
//! who it is, where it listens and its load. A fleet's tools find every live
//! server and its load with one liveliness query and one get.
//!
//! **Placement.** The same tokens tell each server which servers are live
//! ([`Membership`]); a robot on Zenoh belongs to one of them by rendezvous hashing
//! on its fleet when its messages name one (every robot of a fleet on one server,
//! with one fleet map), else on its id (`stillmap_proto::placement_key`,
//! `placement_owner`), and only that server answers it
//! (`ingest/zenoh.rs`). No coordination: every server computes the same owner from
//! the same live set. When a server leaves (its token withdrawn) its robots'
//! frames reach their new owner, which tells them to say hello again; when one
//! joins, the robots it now owns move to it the same way. With storage shared by
//! the servers (`store.replica_url`, `replica.rs`), a moved robot's session comes
//! back on its new owner (`Registry::read_from_replica`); without, it starts a
//! new session.
//!
//! **Any server answers.** An HTTP GET for a session or map this server does not
//! hold (404 here) is asked of the other live servers over Zenoh
//! (`stillmap-cluster/servers/<id>/http`, [`Forwarder`]); the one holding it runs
//! the request through its own HTTP API (token checks included) and its answer is
//! returned as is. A forwarded request is never forwarded again. The unary gRPC
//! queries about a session (`GetLatestPose`, `GetTrajectory`, `GetMapTile`) are
//! asked the same way (`stillmap-cluster/servers/<id>/grpc`: the request message,
//! the method and the caller's token), `GetMapCloud`'s chunks come back together,
//! and `ListSessions` lists every server's sessions. Live data (the dashboard's
//! event stream, `SubscribePoses`) comes from the other servers' publications
//! (`relay.rs`). The fleet endpoints are each server's own.

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use serde::Serialize;
use stillmap_proto::keys;

use axum::body::Body;
use axum::http::{HeaderValue, Request, StatusCode, header};
use axum::response::{IntoResponse, Response};
use tower::ServiceExt as _;

use crate::ServerError;
use crate::api::openapi::ApiError;

/// The content type of an error's body, as every HTTP error has it.
const JSON: &str = "application/json";

/// An HTTP error's JSON body (`{"error": …}`), for an answer built by hand.
fn json_error(message: &str) -> Vec<u8> {
    serde_json::to_vec(&ApiError { error: message.into() }).unwrap_or_default()
}
use crate::lock;
use crate::session::Registry;

/// The servers this server sees live on Zenoh (itself always among them).
pub struct Membership {
    own: String,
    live: Mutex<BTreeSet<String>>,
    /// Counts the changes of `live`.
    changes: tokio::sync::watch::Sender<u64>,
}

impl Membership {
    pub fn new(own: &str) -> Arc<Self> {
        Arc::new(Self {
            own: own.to_string(),
            live: Mutex::new(BTreeSet::from([own.to_string()])),
            changes: tokio::sync::watch::Sender::new(0),
        })
    }

    /// Hears of every change of the live servers.
    pub fn changes(&self) -> tokio::sync::watch::Receiver<u64> {
        self.changes.subscribe()
    }

    /// This server's id.
    pub fn own(&self) -> &str {
        &self.own
    }

    /// Whether the robots placed by `key` (`stillmap_proto::placement_key`: a
    /// robot's fleet, else its id) belong to this server among the live ones.
    pub fn owns(&self, key: &str) -> bool {
        let live = lock(&self.live);
        stillmap_proto::placement_owner(key, live.iter().map(String::as_str)) == Some(self.own.as_str())
    }

    /// The server robots placed by `key` belong to among the live ones.
    pub fn owner(&self, key: &str) -> String {
        let live = lock(&self.live);
        stillmap_proto::placement_owner(key, live.iter().map(String::as_str)).unwrap_or(&self.own).to_string()
    }

    /// The live servers, by id.
    pub fn servers(&self) -> Vec<String> {
        lock(&self.live).iter().cloned().collect()
    }

    pub(crate) fn seen(&self, id: &str, alive: bool) {
        if id == self.own {
            return;
        }
        let mut live = lock(&self.live);
        let changed = if alive { live.insert(id.to_string()) } else { live.remove(id) };
        if changed {
            tracing::info!(server = id, live = live.len(), "{}", if alive { "server joined" } else { "server left" });
            self.changes.send_modify(|n| *n += 1);
        }
    }
}

/// What a status query answers.
#[derive(Debug, Clone, Serialize)]
pub struct ServerStatus {
    pub server_id: String,
    pub version: &'static str,
    pub host: String,
    pub pid: u32,
    /// The addresses the server's gRPC and HTTP ports are bound to.
    pub grpc: String,
    pub http: String,
    /// Where robots reach its gRPC port (`grpc.advertise`; empty: robots are not sent here).
    pub grpc_advertised: String,
    pub started_unix_ns: u64,
    /// Sessions in memory (live, and stored ones a query brought back), and the limit.
    pub sessions_in_memory: usize,
    pub max_sessions: usize,
    /// Robots streaming now.
    pub robots_connected: usize,
    /// The live servers this one sees (placement is computed over them).
    pub servers: Vec<String>,
}

/// Who this server is, fixed at start-up.
pub struct Identity {
    pub server_id: String,
    pub host: String,
    pub grpc: SocketAddr,
    pub http: SocketAddr,
    pub grpc_advertised: String,
    pub started_unix_ns: u64,
    pub max_sessions: usize,
}

impl Identity {
    fn status(&self, registry: &Registry, membership: &Membership) -> ServerStatus {
        let sessions = registry.list();
        ServerStatus {
            server_id: self.server_id.clone(),
            version: env!("CARGO_PKG_VERSION"),
            host: self.host.clone(),
            pid: std::process::id(),
            grpc: self.grpc.to_string(),
            http: self.http.to_string(),
            grpc_advertised: self.grpc_advertised.clone(),
            started_unix_ns: self.started_unix_ns,
            sessions_in_memory: sessions.len(),
            max_sessions: self.max_sessions,
            robots_connected: sessions.iter().filter(|s| s.is_connected()).count(),
            servers: membership.servers(),
        }
    }
}

/// The configured `zenoh.server_id`, else `<hostname>-<gRPC port>` (the host name
/// reduced to the characters a key segment allows).
pub fn server_id(configured: &str, host: &str, grpc: &SocketAddr) -> String {
    if !configured.is_empty() {
        return configured.to_string();
    }
    let suffix = format!("-{}", grpc.port());
    let host: String = host.chars().map(|c| if c.is_ascii_alphanumeric() || c == '_' || c == '-' { c } else { '-' }).collect();
    let host = if host.is_empty() { "stillmap".to_string() } else { host };
    let keep = stillmap_proto::MAX_ROBOT_ID_LEN.saturating_sub(suffix.len()).min(host.len());
    format!("{}{suffix}", &host[..keep])
}

/// The machine's host name (empty when it cannot be read).
pub fn host_name() -> String {
    let mut buf = [0u8; 256];
    // SAFETY: gethostname writes at most `buf.len()` bytes into the buffer it is given.
    let rc = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) };
    if rc != 0 {
        return String::new();
    }
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    String::from_utf8_lossy(&buf[..end]).into_owned()
}

/// Declares this server's liveliness token, then fills `membership` with the servers
/// live now (before any robot is answered: a server that saw only itself would take
/// every robot). The token lasts as long as the value returned.
pub async fn join(zenoh: &zenoh::Session, membership: &Membership) -> Result<zenoh::liveliness::LivelinessToken, ServerError> {
    let token_key = keys::server(&membership.own);
    let token =
        zenoh.liveliness().declare_token(&token_key).await.map_err(|e| ServerError::Zenoh(format!("liveliness token {token_key}: {e}")))?;
    let replies = zenoh
        .liveliness()
        .get(keys::ALL_SERVERS)
        .timeout(JOIN_TIMEOUT)
        .await
        .map_err(|e| ServerError::Zenoh(format!("liveliness query {}: {e}", keys::ALL_SERVERS)))?;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result()
            && let Some(id) = keys::server_of_key(sample.key_expr().as_str())
        {
            membership.seen(id, true);
        }
    }
    tracing::info!(server_id = %membership.own, servers = ?membership.servers(), "announced on Zenoh ({token_key})");
    Ok(token)
}

/// How long [`join`] waits for the live servers' tokens.
const JOIN_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(1);

/// The status queryable and the subscriber to the servers' tokens, declared
/// before [`join`] declares this server's token: a server that sees the token
/// finds the status answering (queries wait in the queryable's channel until
/// [`announce`] runs), and tokens already there reach the membership.
pub struct Announcement {
    status_key: String,
    queryable: zenoh::query::Queryable<zenoh::handlers::FifoChannelHandler<zenoh::query::Query>>,
    servers: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
}

/// Declares [`Announcement`] for server `server_id`.
pub async fn declare_announcement(zenoh: &zenoh::Session, server_id: &str) -> Result<Announcement, ServerError> {
    let status_key = keys::server_status(server_id);
    let queryable = zenoh.declare_queryable(&status_key).await.map_err(|e| ServerError::Zenoh(format!("queryable {status_key}: {e}")))?;
    let servers = zenoh
        .liveliness()
        .declare_subscriber(keys::ALL_SERVERS)
        .history(true)
        .await
        .map_err(|e| ServerError::Zenoh(format!("liveliness subscriber {}: {e}", keys::ALL_SERVERS)))?;
    Ok(Announcement { status_key, queryable, servers })
}

/// Follows the other servers' tokens into `membership` and answers status queries
/// until `shutdown` fires.
pub async fn announce(
    announcement: Announcement,
    registry: Arc<Registry>,
    identity: Identity,
    membership: Arc<Membership>,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) -> Result<(), ServerError> {
    let Announcement { status_key, queryable, servers } = announcement;
    loop {
        let query = tokio::select! {
            q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
            s = servers.recv_async() => {
                let Ok(sample) = s else { break };
                if let Some(id) = keys::server_of_key(sample.key_expr().as_str()) {
                    membership.seen(id, sample.kind() == zenoh::sample::SampleKind::Put);
                }
                continue;
            }
            _ = shutdown.changed() => break,
        };
        let body = match serde_json::to_vec(&identity.status(&registry, &membership)) {
            Ok(body) => body,
            Err(e) => {
                tracing::warn!("server status not serialised: {e}");
                continue;
            }
        };
        if let Err(e) = query.reply(&status_key, body).await {
            tracing::warn!(key = %status_key, "status reply failed: {e}");
        }
    }
    drop(servers);
    drop(queryable);
    Ok(())
}

/// Answers `Ingest.Place`: the robot's owner among the live servers (as Zenoh
/// robots are placed) and the gRPC address it advertises, read from its status.
pub struct Placer {
    pub zenoh: zenoh::Session,
    pub membership: Arc<Membership>,
    /// This server's `grpc.advertise`.
    pub advertised: String,
    pub timeout: std::time::Duration,
}

impl Placer {
    /// The `grpc_advertised` of server `id`'s status; `None` when it did not answer.
    async fn advertised_by(&self, id: &str) -> Option<String> {
        let replies = self.zenoh.get(keys::server_status(id)).timeout(self.timeout).await.ok()?;
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result()
                && let Ok(status) = serde_json::from_slice::<serde_json::Value>(&sample.payload().to_bytes())
            {
                // A server of a version before Place advertises nothing.
                return Some(status["grpc_advertised"].as_str().unwrap_or_default().to_string());
            }
        }
        None
    }
}

#[tonic::async_trait]
impl crate::ingest::grpc::Placement for Placer {
    async fn place(&self, key: &str) -> Result<stillmap_proto::pb::Placement, tonic::Status> {
        let owner = self.membership.owner(key);
        let here = || stillmap_proto::pb::Placement { server_id: self.membership.own.clone(), grpc_address: self.advertised.clone() };
        if owner == self.membership.own {
            return Ok(here());
        }
        match self.advertised_by(&owner).await {
            // The owner cannot be reached by robots: stream here, as without a cluster.
            Some(address) if address.is_empty() => Ok(here()),
            Some(address) => Ok(stillmap_proto::pb::Placement { server_id: owner, grpc_address: address }),
            None => Err(tonic::Status::unavailable(format!(
                "server {owner}, where this robot belongs, did not answer within {:.0} s (it may have just left): ask again",
                self.timeout.as_secs_f64()
            ))),
        }
    }

    fn changes(&self) -> tokio::sync::watch::Receiver<u64> {
        self.membership.changes()
    }

    fn here(&self) -> &str {
        self.membership.own()
    }
}

/// Marks a request one server forwarded to another (never forwarded again).
pub const FORWARDED_HEADER: &str = "x-stillmap-forwarded";
/// Largest forwarded answer (a map export or a point cloud of a big map fits).
const MAX_FORWARDED_BYTES: usize = 256 << 20;

/// What a forwarded request carries.
#[derive(Debug, serde::Serialize, serde::Deserialize)]
struct Forwarded {
    path_and_query: String,
    authorization: Option<String>,
}

/// The status and type of a forwarded answer (its body is the reply's payload),
/// and whether the answering server holds the session or map the path names
/// (only a holder's answer counts; the sessions list is held by every server).
#[derive(Debug, serde::Serialize, serde::Deserialize)]
struct ForwardedHead {
    held: bool,
    status: u16,
    content_type: Option<String>,
}

/// The session (or map) id a forwardable path names, if any.
fn named_session(path: &str) -> Option<&str> {
    let rest = path.strip_prefix("/api/v1/sessions/").or_else(|| path.strip_prefix("/api/v1/maps/"))?;
    rest.split('/').next().filter(|id| !id.is_empty())
}

/// The fleet a forwarded path is about (`/api/v1/fleets/<fleet>…`).
fn named_fleet(path: &str) -> Option<&str> {
    path.strip_prefix("/api/v1/fleets/")?.split('/').next().filter(|name| !name.is_empty())
}

/// Asks the other live servers for what this one does not hold.
pub struct Forwarder {
    pub zenoh: zenoh::Session,
    pub membership: Arc<Membership>,
    pub timeout: std::time::Duration,
}

impl Forwarder {
    /// Every other live server's replies on its queryable `key_of(server)` to
    /// `payload` with `attachment` (server id, reply attachment, reply payload),
    /// in the order the servers are listed.
    async fn ask_raw(
        &self,
        key_of: fn(&str) -> String,
        what: &str,
        payload: Vec<u8>,
        attachment: Option<Vec<u8>>,
    ) -> Vec<(String, Vec<u8>, Vec<u8>)> {
        let mut out = Vec::new();
        for server in self.membership.servers().into_iter().filter(|s| *s != self.membership.own) {
            let mut get = self.zenoh.get(key_of(&server)).payload(payload.clone()).timeout(self.timeout);
            if let Some(a) = &attachment {
                get = get.attachment(a.clone());
            }
            let replies = match get.await {
                Ok(r) => r,
                Err(e) => {
                    tracing::warn!(server, "forwarding {what} failed: {e}");
                    continue;
                }
            };
            while let Ok(reply) = replies.recv_async().await {
                let Ok(sample) = reply.result() else { continue };
                let attachment = sample.attachment().map(|a| a.to_bytes().into_owned()).unwrap_or_default();
                out.push((server.clone(), attachment, sample.payload().to_bytes().into_owned()));
            }
        }
        out
    }

    /// Every other live server's answer to `request` (server id, status and type,
    /// body), in the order the servers are listed, and whether every one answered.
    async fn ask(&self, request: &Forwarded) -> (Vec<(String, ForwardedHead, Vec<u8>)>, bool) {
        let Ok(payload) = serde_json::to_vec(request) else { return (Vec::new(), false) };
        self.ask_headed(keys::server_http, &request.path_and_query, payload, None).await
    }

    /// [`Self::ask_raw`] with each reply's attachment read as its head `H` (a reply
    /// without one is left out), and whether every other live server answered.
    async fn ask_headed<H: serde::de::DeserializeOwned>(
        &self,
        key_of: fn(&str) -> String,
        what: &str,
        payload: Vec<u8>,
        attachment: Option<Vec<u8>>,
    ) -> (Vec<(String, H, Vec<u8>)>, bool) {
        let asked = self.others();
        let replies = self.ask_raw(key_of, what, payload, attachment).await;
        let answers: Vec<(String, H, Vec<u8>)> =
            replies.into_iter().filter_map(|(server, head, body)| Some((server, serde_json::from_slice::<H>(&head).ok()?, body))).collect();
        let all = asked.iter().all(|s| answers.iter().any(|(server, _, _)| server == s));
        (answers, all)
    }

    /// The other live servers.
    fn others(&self) -> BTreeSet<String> {
        self.membership.servers().into_iter().filter(|s| *s != self.membership.own).collect()
    }

    /// Every other live server's answer to a unary gRPC query (server id, status,
    /// encoded response), and whether every one of them answered.
    async fn ask_grpc(&self, call: &ForwardedCall, request: Vec<u8>) -> (Vec<(String, ForwardedStatus, Vec<u8>)>, bool) {
        let Ok(head) = serde_json::to_vec(call) else { return (Vec::new(), false) };
        self.ask_headed(keys::server_grpc, &call.method, request, Some(head)).await
    }

    /// The answer of the other live server holding what `request` names; 503 when
    /// none holds it and some server did not answer; `None` when none holds it.
    async fn forward(&self, request: &Forwarded) -> Option<Response> {
        let (answers, all_answered) = self.ask(request).await;
        let Some((_, head, body)) = answers.into_iter().find(|(_, head, _)| head.held) else {
            return (!all_answered).then(|| {
                let error = serde_json::json!({"error": "not held by this server, and a server of the cluster did not answer"});
                (StatusCode::SERVICE_UNAVAILABLE, axum::Json(error)).into_response()
            });
        };
        let status = StatusCode::from_u16(head.status).unwrap_or(StatusCode::BAD_GATEWAY);
        let mut response = (status, body).into_response();
        if let Some(t) = head.content_type.and_then(|t| HeaderValue::from_str(&t).ok()) {
            response.headers_mut().insert(header::CONTENT_TYPE, t);
        }
        Some(response)
    }

    /// Every other live server's 200 answer to `request`, with its server id.
    async fn gather(&self, request: &Forwarded) -> Vec<(String, Vec<u8>)> {
        let ok = StatusCode::OK.as_u16();
        let (answers, _) = self.ask(request).await;
        answers.into_iter().filter(|(_, head, _)| head.status == ok).map(|(server, _, body)| (server, body)).collect()
    }
}

/// A unary gRPC query forwarded to another server (its request message is the payload).
#[derive(Debug, serde::Serialize, serde::Deserialize)]
struct ForwardedCall {
    method: String,
    authorization: Option<String>,
}

/// The gRPC status of a forwarded query's answer (its response message is the
/// reply's payload when the code is OK), and whether the answering server holds
/// what it is about (only a holder's answer counts: another server's NOT_FOUND, or
/// its refusal, says nothing about the session).
#[derive(Debug, serde::Serialize, serde::Deserialize)]
struct ForwardedStatus {
    held: bool,
    code: i32,
    message: String,
}

#[tonic::async_trait]
impl crate::api::query::Remote for Forwarder {
    async fn call(&self, method: &'static str, request: Vec<u8>, authorization: Option<String>) -> Option<Result<Vec<u8>, tonic::Status>> {
        let call = ForwardedCall { method: method.to_string(), authorization };
        let (answers, all_answered) = self.ask_grpc(&call, request).await;
        let Some((_, status, body)) = answers.into_iter().find(|(_, status, _)| status.held) else {
            return (!all_answered)
                .then(|| Err(tonic::Status::unavailable(format!("{method}: not held here, and a server of the cluster did not answer"))));
        };
        Some(match tonic::Code::from_i32(status.code) {
            tonic::Code::Ok => Ok(body),
            code => Err(tonic::Status::new(code, status.message)),
        })
    }

    async fn gather(&self, method: &'static str, request: Vec<u8>, authorization: Option<String>) -> Vec<Vec<u8>> {
        let call = ForwardedCall { method: method.to_string(), authorization };
        let ok = tonic::Code::Ok as i32;
        let (answers, _) = self.ask_grpc(&call, request).await;
        answers.into_iter().filter(|(_, status, _)| status.code == ok).map(|(_, _, body)| body).collect()
    }
}

/// A list of every live server (`list_key` "sessions": `GET /api/v1/sessions`;
/// "fleets": `GET /api/v1/fleets`): this server's, then the others', each entry
/// with the `server_id` holding it; a fleet's name once.
async fn merged_list(forwarder: &Forwarder, request: Forwarded, local: Response, list_key: &str) -> Response {
    let (parts, body) = local.into_parts();
    let Ok(bytes) = axum::body::to_bytes(body, MAX_FORWARDED_BYTES).await else {
        return (StatusCode::INTERNAL_SERVER_ERROR, axum::Json(ApiError { error: format!("{list_key} list too large") })).into_response();
    };
    let Ok(mut list) = serde_json::from_slice::<serde_json::Value>(&bytes) else {
        return Response::from_parts(parts, Body::from(bytes));
    };
    let tag = |sessions: &mut Vec<serde_json::Value>, server: &str| {
        for s in sessions.iter_mut() {
            if let Some(o) = s.as_object_mut() {
                o.insert("server_id".into(), server.into());
            }
        }
    };
    let mut all: Vec<serde_json::Value> = list[list_key].as_array().cloned().unwrap_or_default();
    tag(&mut all, &forwarder.membership.own);
    let mut next_tokens = usize::from(list.get("next_page_token").is_some_and(|t| t.is_string()));
    for (server, body) in forwarder.gather(&request).await {
        let Ok(theirs) = serde_json::from_slice::<serde_json::Value>(&body) else { continue };
        next_tokens += usize::from(theirs.get("next_page_token").is_some_and(|t| t.is_string()));
        let mut items = theirs[list_key].as_array().cloned().unwrap_or_default();
        tag(&mut items, &server);
        if list_key == "fleets" {
            // A fleet's paths are answered by the server that holds it, this one
            // first: a name listed here already (the default fleet, split by robot
            // ids) is not listed again.
            items.retain(|f| !all.iter().any(|a| a["fleet"] == f["fleet"]));
        }
        all.extend(items);
    }
    if list_key == "sessions" {
        // A page of every server's sessions: each answered its first `limit` after
        // the token (the query was passed on), so the merged page's are among them.
        let query = request.path_and_query.split_once('?').map_or("", |(_, q)| q);
        let limit = serde_urlencoded::from_str::<crate::api::http::ListQuery>(query)
            .ok()
            .and_then(|q| q.checked().ok())
            .map_or(crate::session::DEFAULT_SESSIONS_PAGE, |(_, limit)| limit);
        let cursor =
            |s: &serde_json::Value| (s["started_unix_ns"].as_u64().unwrap_or(0), s["session_id"].as_str().unwrap_or("").to_string());
        all.sort_by_cached_key(cursor);
        let more = all.len() > limit || next_tokens > 0;
        all.truncate(limit);
        match all.last().map(cursor) {
            Some((started_unix_ns, session_id)) if more => {
                list["next_page_token"] = crate::session::ListCursor { started_unix_ns, session_id }.token().into();
            }
            _ => {
                if let Some(o) = list.as_object_mut() {
                    o.remove("next_page_token");
                }
            }
        }
    }
    list[list_key] = serde_json::Value::Array(all);
    let mut response = axum::Json(list).into_response();
    *response.status_mut() = parts.status;
    response
}

/// HTTP middleware: a GET on a session, a map or a fleet that this server answers 404 is
/// asked of the other live servers; their answer, if one holds it, is returned.
/// `GET /api/v1/sessions` lists every live server's sessions, `GET /api/v1/fleets`
/// every live server's fleets (a name once, this server's first), each tagged
/// with the `server_id` holding it.
pub async fn forward_unknown(
    axum::extract::State(forwarder): axum::extract::State<Arc<Forwarder>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    let path = request.uri().path();
    let first_hand = request.method() == axum::http::Method::GET && !request.headers().contains_key(FORWARDED_HEADER);
    let list = LISTS.iter().find(|(p, _)| first_hand && *p == path).map(|&(_, key)| key);
    let forwardable = first_hand && forwardable_path(path);
    let forwarded = (list.is_some() || forwardable).then(|| Forwarded {
        path_and_query: request.uri().path_and_query().map_or_else(|| path.to_string(), ToString::to_string),
        authorization: request.headers().get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).map(str::to_owned),
    });
    let response = next.run(request).await;
    // A 404 of a matched route passed its token check here; the fallback's did not.
    let unknown_here =
        response.status() == StatusCode::NOT_FOUND && response.extensions().get::<crate::api::http::NoSuchEndpoint>().is_none();
    match (forwarded, list) {
        (Some(f), Some(key)) if response.status() == StatusCode::OK => merged_list(&forwarder, f, response, key).await,
        (Some(f), None) if unknown_here => forwarder.forward(&f).await.unwrap_or(response),
        _ => response,
    }
}

/// The lists merged over the servers: the path, and the key of its JSON array.
const LISTS: [(&str, &str); 2] = [("/api/v1/sessions", "sessions"), ("/api/v1/fleets", "fleets")];

/// The paths forwarded between servers: a session's, a map's or a fleet's (a
/// named fleet's robots are placed on one server: any server answers for it).
fn forwardable_path(path: &str) -> bool {
    path.starts_with("/api/v1/sessions/")
        || (path.starts_with("/api/v1/maps/") && path != "/api/v1/maps/import")
        || path.starts_with("/api/v1/fleets/")
}

/// Forwarded queries answered at once; more wait.
const MAX_FORWARDED_AT_ONCE: usize = 16;
/// Longest a forwarded query may take here (a map export included).
pub const FORWARDED_ANSWER_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);

/// Answers the GETs other servers forward here with this server's HTTP API `app`,
/// until `shutdown` fires: only a session's, a map's or a fleet's paths and the lists,
/// at most `MAX_FORWARDED_AT_ONCE` at once, each within [`FORWARDED_ANSWER_TIMEOUT`].
pub async fn answer_forwarded(
    zenoh: zenoh::Session,
    server_id: String,
    app: axum::Router,
    registry: Arc<Registry>,
    shutdown: tokio::sync::watch::Receiver<bool>,
) -> Result<(), ServerError> {
    serve_queries(&zenoh, keys::server_http(&server_id), shutdown, move |query, key| {
        let (app, registry) = (app.clone(), registry.clone());
        async move {
            let Some(forwarded) = query.payload().and_then(|p| serde_json::from_slice::<Forwarded>(&p.to_bytes()).ok()) else {
                let _ = query.reply_err("a forwarded request must be JSON {path_and_query, authorization}").await;
                return;
            };
            let path = forwarded.path_and_query.split('?').next().unwrap_or_default();
            if !(forwardable_path(path) || LISTS.iter().any(|(p, _)| *p == path)) {
                let _ = query.reply_err(format!("{path} is not forwarded between servers")).await;
                return;
            }
            let held = match (named_session(path), named_fleet(path)) {
                (Some(id), _) => registry.info(id).is_some(),
                (None, Some(fleet)) => registry.fleets().is_some_and(|f| f.holds(fleet)),
                (None, None) => true,
            };
            let mut request = Request::get(&forwarded.path_and_query).header(FORWARDED_HEADER, "1");
            if let Some(auth) = &forwarded.authorization {
                request = request.header(header::AUTHORIZATION, auth);
            }
            let Ok(request) = request.body(Body::empty()) else {
                let _ = query.reply_err("a forwarded request's path is not a URI").await;
                return;
            };
            let answer = async {
                let Ok(response) = app.oneshot(request).await;
                let status = response.status().as_u16();
                let content_type = response.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).map(str::to_owned);
                match axum::body::to_bytes(response.into_body(), MAX_FORWARDED_BYTES).await {
                    Ok(body) => (ForwardedHead { held, status, content_type }, body.to_vec()),
                    Err(_) => (
                        ForwardedHead { held, status: StatusCode::BAD_GATEWAY.as_u16(), content_type: Some(JSON.into()) },
                        json_error("answer too large to forward"),
                    ),
                }
            };
            let (head, body) = match tokio::time::timeout(FORWARDED_ANSWER_TIMEOUT, answer).await {
                Ok(answered) => answered,
                Err(_) => (
                    ForwardedHead { held, status: StatusCode::GATEWAY_TIMEOUT.as_u16(), content_type: Some(JSON.into()) },
                    json_error("answer took too long"),
                ),
            };
            let attachment = serde_json::to_vec(&head).unwrap_or_default();
            if let Err(e) = query.reply(&key, body).attachment(attachment).await {
                tracing::warn!(key, "forwarded answer not sent: {e}");
            }
        }
    })
    .await
}

/// Answers the queries on `key` with `answer` (the query and the key), until
/// `shutdown` fires: at most `MAX_FORWARDED_AT_ONCE` at once, more wait.
async fn serve_queries<F, A>(
    zenoh: &zenoh::Session,
    key: String,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
    answer: F,
) -> Result<(), ServerError>
where
    F: Fn(zenoh::query::Query, String) -> A,
    A: std::future::Future<Output = ()> + Send + 'static,
{
    let queryable = zenoh.declare_queryable(&key).await.map_err(|e| ServerError::Zenoh(format!("queryable {key}: {e}")))?;
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_FORWARDED_AT_ONCE));
    loop {
        let query = tokio::select! {
            q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
            _ = shutdown.changed() => break,
        };
        let Ok(slot) = slots.clone().acquire_owned().await else { break };
        let answered = answer(query, key.clone());
        tokio::spawn(async move {
            let _slot = slot;
            answered.await;
        });
    }
    Ok(())
}

/// Answers the unary gRPC queries other servers forward here with `service`
/// (which forwards nothing further), the caller's token checked for the read scope
/// as this server's own gRPC queries are, until `shutdown` fires: at most
/// `MAX_FORWARDED_AT_ONCE` at once, each within [`FORWARDED_ANSWER_TIMEOUT`].
pub async fn answer_forwarded_grpc(
    zenoh: zenoh::Session,
    server_id: String,
    service: Arc<crate::api::query::QueryService>,
    auth: Arc<crate::auth::AuthHandle>,
    shutdown: tokio::sync::watch::Receiver<bool>,
) -> Result<(), ServerError> {
    serve_queries(&zenoh, keys::server_grpc(&server_id), shutdown, move |query, key| {
        let (service, auth) = (service.clone(), auth.clone());
        async move {
            let call = query.attachment().and_then(|a| serde_json::from_slice::<ForwardedCall>(&a.to_bytes()).ok());
            let request = query.payload().map(|p| p.to_bytes().into_owned()).unwrap_or_default();
            let held = call.as_ref().is_some_and(|c| service.holds(&c.method, &request));
            let status = |code: tonic::Code, message: &str| ForwardedStatus { held, code: code as i32, message: message.to_string() };
            let (head, body) = match call {
                None => {
                    (status(tonic::Code::InvalidArgument, "a forwarded gRPC query needs a JSON attachment {method, authorization}"), vec![])
                }
                Some(call) => match auth.get().check(call.authorization.as_deref().map(str::as_bytes), crate::auth::Need::Read) {
                    Err(refusal) => {
                        let refused = refusal.grpc_status();
                        (status(refused.code(), refused.message()), vec![])
                    }
                    Ok(()) => match tokio::time::timeout(FORWARDED_ANSWER_TIMEOUT, service.answer(&call.method, &request)).await {
                        Ok(Ok(body)) if body.len() > MAX_FORWARDED_BYTES => (
                            status(
                                tonic::Code::ResourceExhausted,
                                &format!("the answer is {} bytes: more than forwarded answers carry ({MAX_FORWARDED_BYTES}); ask the server holding the session", body.len()),
                            ),
                            vec![],
                        ),
                        Ok(Ok(body)) => (status(tonic::Code::Ok, ""), body),
                        Ok(Err(failed)) => (status(failed.code(), failed.message()), vec![]),
                        Err(_) => (status(tonic::Code::DeadlineExceeded, "answer took too long"), vec![]),
                    },
                },
            };
            let attachment = serde_json::to_vec(&head).unwrap_or_default();
            if let Err(e) = query.reply(&key, body).attachment(attachment).await {
                tracing::warn!(key, "forwarded gRPC answer not sent: {e}");
            }
        }
    })
    .await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_forwarded_path_names_its_session() {
        assert_eq!(named_session("/api/v1/sessions/r-6b1-1/pose"), Some("r-6b1-1"));
        assert_eq!(named_session("/api/v1/sessions/r-6b1-1"), Some("r-6b1-1"));
        assert_eq!(named_session("/api/v1/maps/r-6b1-1/tiles/0/0/0.png"), Some("r-6b1-1"));
        assert_eq!(named_session("/api/v1/sessions/"), None);
        assert_eq!(named_session("/api/v1/sessions"), None, "the list: every server holds it");
        assert_eq!(named_fleet("/api/v1/fleets/warehouse/tiles/0/0/0.png"), Some("warehouse"));
        assert_eq!(named_fleet("/api/v1/fleets/warehouse"), Some("warehouse"));
        assert_eq!(named_fleet("/api/v1/fleets/"), None);
        assert_eq!(named_fleet("/api/v1/fleets"), None, "the list: merged, not forwarded");
        assert_eq!(named_fleet("/api/v1/sessions/warehouse"), None);
        assert!(forwardable_path("/api/v1/fleets/warehouse/cloud.ply") && !forwardable_path("/api/v1/fleets"));
    }

    #[test]
    fn membership_decides_ownership_over_the_live_servers() {
        let (a, b) = (Membership::new("a"), Membership::new("b"));
        let robots: Vec<String> = (0..50).map(|i| format!("r{i}")).collect();
        // Alone, each server owns every robot.
        assert!(robots.iter().all(|r| a.owns(r) && b.owns(r)));
        a.seen("b", true);
        b.seen("a", true);
        assert_eq!(a.servers(), ["a", "b"]);
        // Together, exactly one owns each robot, and both own some.
        assert!(robots.iter().all(|r| a.owns(r) != b.owns(r)));
        assert!(robots.iter().any(|r| a.owns(r)) && robots.iter().any(|r| b.owns(r)));
        // B leaves: A owns everything again; a server never removes itself.
        a.seen("b", false);
        a.seen("a", false);
        assert!(robots.iter().all(|r| a.owns(r)));
        assert_eq!(a.servers(), ["a"]);
    }

    #[test]
    fn the_default_id_is_the_host_and_the_grpc_port_as_a_key_segment() {
        let grpc: SocketAddr = "0.0.0.0:50051".parse().expect("address");
        assert_eq!(server_id("", "gpu-node.example.org", &grpc), "gpu-node-example-org-50051");
        assert_eq!(server_id("edge_1", "host", &grpc), "edge_1");
        assert_eq!(server_id("", "", &grpc), "stillmap-50051");
        let long = server_id("", &"h".repeat(200), &grpc);
        assert_eq!(long.len(), stillmap_proto::MAX_ROBOT_ID_LEN);
        assert!(stillmap_proto::validate_server_id(&long).is_ok() && long.ends_with("-50051"));
        assert!(!host_name().is_empty());
    }
}
