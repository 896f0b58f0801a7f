//! The server among servers on one Zenoh network: while it runs it holds the
//! liveliness token `stillmap-cluster/servers/<server_id>` (Zenoh withdraws it when
//! the process or its link dies, `kill -9` included), and it answers queries on
//! `stillmap-cluster/servers/<server_id>/status` with its [`ServerStatus`] as JSON:
//! who it is, where it listens and its load. A fleet's tools find every live
//! server and its load with one liveliness query and one get.
//!
//! **Placement.** The same tokens tell each server which servers are live
//! ([`Membership`]); a robot on Zenoh belongs to one of them by rendezvous hashing
//! on its id (`stillmap_proto::placement_owner`), and only that server answers it
//! (`ingest/zenoh.rs`). No coordination: every server computes the same owner from
//! the same live set. When a server leaves (its token withdrawn) its robots'
//! frames reach their new owner, which tells them to say hello again; when one
//! joins, the robots it now owns move to it the same way. Sessions do not move
//! with them yet (no shared storage): a moved robot starts a new session.

use std::collections::BTreeSet;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use serde::Serialize;
use stillmap_proto::keys;

use crate::ServerError;
use crate::lock;
use crate::session::Registry;

/// The servers this server sees live on Zenoh (itself always among them).
pub struct Membership {
    own: String,
    live: Mutex<BTreeSet<String>>,
}

impl Membership {
    pub fn new(own: &str) -> Arc<Self> {
        Arc::new(Self { own: own.to_string(), live: Mutex::new(BTreeSet::from([own.to_string()])) })
    }

    /// Whether robot `robot_id` belongs to this server among the live ones.
    pub fn owns(&self, robot_id: &str) -> bool {
        let live = lock(&self.live);
        stillmap_proto::placement_owner(robot_id, live.iter().map(String::as_str)) == Some(self.own.as_str())
    }

    /// The live servers, by id.
    pub fn servers(&self) -> Vec<String> {
        lock(&self.live).iter().cloned().collect()
    }

    fn seen(&self, id: &str, alive: bool) {
        if id == self.own {
            return;
        }
        let mut live = lock(&self.live);
        let changed = if alive { live.insert(id.to_string()) } else { live.remove(id) };
        if changed {
            tracing::info!(server = id, live = live.len(), "{}", if alive { "server joined" } else { "server left" });
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

/// Holds the liveliness token, follows the other servers' tokens into `membership`
/// and answers status queries until `shutdown` fires.
pub async fn announce(
    zenoh: zenoh::Session,
    registry: Arc<Registry>,
    identity: Identity,
    membership: Arc<Membership>,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) -> Result<(), ServerError> {
    let token_key = keys::server(&identity.server_id);
    let status_key = keys::server_status(&identity.server_id);
    let token =
        zenoh.liveliness().declare_token(&token_key).await.map_err(|e| ServerError::Zenoh(format!("liveliness token {token_key}: {e}")))?;
    let queryable = zenoh.declare_queryable(&status_key).await.map_err(|e| ServerError::Zenoh(format!("queryable {status_key}: {e}")))?;
    let servers = zenoh
        .liveliness()
        .declare_subscriber(keys::ALL_SERVERS)
        .history(true)
        .await
        .map_err(|e| ServerError::Zenoh(format!("liveliness subscriber {}: {e}", keys::ALL_SERVERS)))?;
    tracing::info!(server_id = %identity.server_id, "announced on Zenoh ({token_key})");
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
    let _ = token.undeclare().await;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
