//! Servers on one Zenoh network announce themselves (issue 22): two real servers
//! connected to a Zenoh router each hold the liveliness token
//! `stillmap-cluster/servers/<id>` and answer `.../<id>/status` with who they are
//! (their process id: the servers this test started) and their load; a server
//! killed with `kill -9` disappears from the liveliness view, and comes back when
//! it restarts.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use stillmap_e2e::{Server, free_port, run_client, tum_dir};
use stillmap_proto::keys;

async fn open(mode: &str, endpoints: (&str, &str)) -> zenoh::Session {
    let mut config = zenoh::Config::default();
    config.insert_json5("mode", &format!("{mode:?}")).expect("mode");
    config.insert_json5("scouting/multicast/enabled", "false").expect("scouting");
    config.insert_json5(endpoints.0, &format!("[{:?}]", endpoints.1)).expect("endpoints");
    zenoh::open(config).await.expect("zenoh open")
}

/// The server ids holding a liveliness token now.
async fn live(z: &zenoh::Session) -> Vec<String> {
    let replies = z.liveliness().get(keys::ALL_SERVERS).await.expect("liveliness get");
    let mut ids = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            ids.extend(keys::server_of_key(sample.key_expr().as_str()).map(str::to_owned));
        }
    }
    ids.sort();
    ids
}

/// Every server's status, by id.
async fn statuses(z: &zenoh::Session) -> BTreeMap<String, serde_json::Value> {
    let replies = z.get(keys::ALL_SERVER_STATUS).await.expect("get");
    let mut out = BTreeMap::new();
    while let Ok(reply) = replies.recv_async().await {
        let sample = reply.result().expect("a status reply");
        let status: serde_json::Value = serde_json::from_slice(&sample.payload().to_bytes()).expect("status JSON");
        out.insert(status["server_id"].as_str().expect("server_id").to_string(), status);
    }
    out
}

/// Polls `live` until it equals `want`; returns how long that took.
async fn wait_live(z: &zenoh::Session, want: &[&str], within: Duration) -> Duration {
    let start = Instant::now();
    loop {
        let ids = live(z).await;
        if ids == want {
            return start.elapsed();
        }
        assert!(start.elapsed() < within, "live servers {ids:?}, expected {want:?} within {within:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn servers_announce_themselves_and_their_load_and_vanish_when_killed() {
    let router_endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let _router = open("router", ("listen/endpoints", &router_endpoint)).await;
    let tag = std::process::id();
    let (id_a, id_b) = (format!("a-{tag}"), format!("b-{tag}"));
    let start = |id: &str| Server::start(&["--no-perception", "--zenoh-connect", &router_endpoint, "--server-id", id]);
    let a = start(&id_a);
    let mut b = start(&id_b);
    let tool = open("client", ("connect/endpoints", &router_endpoint)).await;
    wait_live(&tool, &[&id_a, &id_b], Duration::from_secs(10)).await;

    // Each status comes from the process this test started, with its addresses.
    let s = statuses(&tool).await;
    assert_eq!(s.len(), 2, "{s:?}");
    for (id, server) in [(&id_a, &a), (&id_b, &b)] {
        assert_eq!(s[id]["pid"], server.pid(), "{id}");
        assert_eq!(s[id]["grpc"], server.grpc, "{id}");
        assert_eq!(s[id]["http"], server.http, "{id}");
        assert_eq!((s[id]["sessions_in_memory"].as_u64(), s[id]["robots_connected"].as_u64()), (Some(0), Some(0)), "{id}");
    }

    // A robot streams to A: A's load shows its session, B's does not.
    let tum = format!("tum:{}", tum_dir().display());
    let (out, _) = run_client(&["--source", &tum, "--server", &a.grpc_url(), "--robot-id", "r1", "--rate", "max", "--max-frames", "5"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s = statuses(&tool).await;
    assert_eq!(s[&id_a]["sessions_in_memory"], 1);
    assert_eq!(s[&id_a]["robots_connected"], 0, "the robot finished");
    assert_eq!(s[&id_b]["sessions_in_memory"], 0);

    // kill -9: B's token goes with its process.
    let watch = tool.liveliness().declare_subscriber(keys::ALL_SERVERS).await.expect("liveliness subscriber");
    b.kill9();
    let gone = wait_live(&tool, &[&id_a], Duration::from_secs(5)).await;
    eprintln!("server B's liveliness token withdrawn {:.0} ms after kill -9", gone.as_secs_f64() * 1e3);
    let deleted = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            let sample = watch.recv_async().await.expect("liveliness sample");
            if sample.kind() == zenoh::sample::SampleKind::Delete && sample.key_expr().as_str() == keys::server(&id_b) {
                return;
            }
        }
    })
    .await;
    assert!(deleted.is_ok(), "no liveliness delete for B");
    assert_eq!(statuses(&tool).await.keys().collect::<Vec<_>>(), [&id_a]);

    // B restarts under the same id and is back.
    let b2 = start(&id_b);
    wait_live(&tool, &[&id_a, &id_b], Duration::from_secs(10)).await;
    assert_eq!(statuses(&tool).await[&id_b]["pid"], b2.pid());
}
