//! `stillmap-client servers`: the stillmap servers live on a Zenoh network (their
//! liveliness tokens `stillmap-cluster/servers/<id>`) and each one's status (who it
//! is, where it listens, its load, the servers it sees), as a table or JSON.

use std::collections::BTreeMap;

use stillmap_proto::keys;

use crate::ClientError;
use crate::link::{ZenohOptions, open_zenoh};

/// A live server: its id and its status, when it answered in time.
#[derive(Debug, Clone)]
pub struct LiveServer {
    pub server_id: String,
    pub status: Option<serde_json::Value>,
}

/// The live servers and their statuses, by id.
pub async fn list(options: &ZenohOptions) -> Result<Vec<LiveServer>, ClientError> {
    let session = open_zenoh(options).await?;
    let zerr = |what: &'static str| move |e: zenoh::Error| ClientError::Connect(format!("zenoh {what}: {e}"));
    let mut live: BTreeMap<String, Option<serde_json::Value>> = BTreeMap::new();
    let replies = session.liveliness().get(keys::ALL_SERVERS).timeout(options.timeout).await.map_err(zerr("liveliness get"))?;
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result()
            && let Some(id) = keys::server_of_key(sample.key_expr().as_str())
        {
            live.insert(id.to_string(), None);
        }
    }
    let replies = session.get(keys::ALL_SERVER_STATUS).timeout(options.timeout).await.map_err(zerr("get"))?;
    while let Ok(reply) = replies.recv_async().await {
        let Ok(sample) = reply.result() else { continue };
        let Ok(status) = serde_json::from_slice::<serde_json::Value>(&sample.payload().to_bytes()) else { continue };
        if let Some(id) = status["server_id"].as_str().map(str::to_owned)
            && let Some(slot) = live.get_mut(&id)
        {
            *slot = Some(status);
        }
    }
    session.close().await.map_err(zerr("close"))?;
    Ok(live.into_iter().map(|(server_id, status)| LiveServer { server_id, status }).collect())
}

/// The servers as a table: one line each.
pub fn table(servers: &[LiveServer]) -> String {
    let mut out = format!("{:<24} {:<22} {:<22} {:>8} {:>9} {:>7}  {}\n", "server", "grpc", "http", "sessions", "streaming", "pid", "sees");
    for s in servers {
        let Some(st) = &s.status else {
            out += &format!("{:<24} (live, no status within the timeout)\n", s.server_id);
            continue;
        };
        let text = |k: &str| st[k].as_str().unwrap_or("?").to_string();
        let num = |k: &str| st[k].as_u64().map_or("?".into(), |n| n.to_string());
        let sees = st["servers"].as_array().map_or(String::new(), |a| a.iter().filter_map(|v| v.as_str()).collect::<Vec<_>>().join(","));
        out += &format!(
            "{:<24} {:<22} {:<22} {:>8} {:>9} {:>7}  {sees}\n",
            s.server_id,
            text("grpc"),
            text("http"),
            format!("{}/{}", num("sessions_in_memory"), num("max_sessions")),
            num("robots_connected"),
            num("pid"),
        );
    }
    out
}
