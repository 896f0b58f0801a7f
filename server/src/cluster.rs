//! The server among servers on one Zenoh network: while it runs it holds the
//! liveliness token `stillmap-cluster/servers/<server_id>` (Zenoh withdraws it when
//! the process or its link dies, `kill -9` included), and it answers queries on
//! `stillmap-cluster/servers/<server_id>/status` with its [`ServerStatus`] as JSON:
//! who it is, where it listens and its load. A fleet's tools (and placement, once
//! built) find every live server and its load with one liveliness query and one get.

use std::net::SocketAddr;
use std::sync::Arc;

use serde::Serialize;
use stillmap_proto::keys;

use crate::ServerError;
use crate::session::Registry;

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
    fn status(&self, registry: &Registry) -> ServerStatus {
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

/// Holds the liveliness token and answers status queries until `shutdown` fires.
pub async fn announce(
    zenoh: zenoh::Session,
    registry: Arc<Registry>,
    identity: Identity,
    mut shutdown: tokio::sync::watch::Receiver<bool>,
) -> Result<(), ServerError> {
    let token_key = keys::server(&identity.server_id);
    let status_key = keys::server_status(&identity.server_id);
    let token =
        zenoh.liveliness().declare_token(&token_key).await.map_err(|e| ServerError::Zenoh(format!("liveliness token {token_key}: {e}")))?;
    let queryable = zenoh.declare_queryable(&status_key).await.map_err(|e| ServerError::Zenoh(format!("queryable {status_key}: {e}")))?;
    tracing::info!(server_id = %identity.server_id, "announced on Zenoh ({token_key})");
    loop {
        let query = tokio::select! {
            q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
            _ = shutdown.changed() => break,
        };
        let body = match serde_json::to_vec(&identity.status(&registry)) {
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
    drop(queryable);
    let _ = token.undeclare().await;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
