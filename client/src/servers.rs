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

/// The servers as a table: one line each. The gRPC column is the address robots
/// are sent to (`grpc_advertised`), or the bound one when a server advertises none.
pub fn table(servers: &[LiveServer]) -> String {
    let mut out = format!("{:<24} {:<22} {:<22} {:>8} {:>9} {:>7}  {}\n", "server", "grpc", "http", "sessions", "streaming", "pid", "sees");
    for s in servers {
        let Some(st) = &s.status else {
            out += &format!("{:<24} (live, no status within the timeout)\n", s.server_id);
            continue;
        };
        let text = |k: &str| st[k].as_str().unwrap_or("?").to_string();
        let num = |k: &str| st[k].as_u64().map_or("?".into(), |n| n.to_string());
        let grpc = st["grpc_advertised"].as_str().filter(|a| !a.is_empty()).map_or_else(|| text("grpc"), str::to_owned);
        let sees = st["servers"].as_array().map_or(String::new(), |a| a.iter().filter_map(|v| v.as_str()).collect::<Vec<_>>().join(","));
        out += &format!(
            "{:<24} {:<22} {:<22} {:>8} {:>9} {:>7}  {sees}\n",
            s.server_id,
            grpc,
            text("http"),
            format!("{}/{}", num("sessions_in_memory"), num("max_sessions")),
            num("robots_connected"),
            num("pid"),
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The gRPC column shows where robots are sent (the advertised address), the
    /// bound one when none is advertised; a server without a status says so.
    #[test]
    fn the_table_shows_where_robots_stream() {
        let status = |advertised: &str| {
            serde_json::json!({
                "grpc": "0.0.0.0:50051", "grpc_advertised": advertised, "http": "0.0.0.0:8080",
                "sessions_in_memory": 2, "max_sessions": 64, "robots_connected": 1, "pid": 7, "servers": ["a", "b"]
            })
        };
        let servers = [
            LiveServer { server_id: "a".into(), status: Some(status("http://a.example:50051")) },
            LiveServer { server_id: "b".into(), status: Some(status("")) },
            LiveServer { server_id: "c".into(), status: None },
        ];
        let table = table(&servers);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 4, "{table}");
        assert!(lines[1].starts_with("a ") && lines[1].contains("http://a.example:50051") && lines[1].contains("2/64"), "{table}");
        assert!(lines[2].starts_with("b ") && lines[2].contains("0.0.0.0:50051") && lines[2].ends_with("a,b"), "{table}");
        assert!(lines[3].contains("no status"), "{table}");
    }
}
