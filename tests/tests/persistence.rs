//! Crash safety of the embedded store with real processes: the server is killed
//! with SIGKILL while the real client streams the real TUM clip, restarted on the
//! same store, and must still serve the session's trajectory and map up to the
//! last committed keyframe.

use std::process::{Command, Stdio};
use std::time::Duration;

use stillmap_e2e::{Server, bin, eventually, tempfile_path, tum_dir};

#[tokio::test(flavor = "multi_thread")]
async fn kill_9_while_streaming_keeps_trajectory_and_map_up_to_the_last_keyframe() {
    let store = tempfile_path("crash.redb");
    let store_arg = store.to_str().expect("utf-8 path").to_string();
    let mut server = Server::start(&["--no-zenoh", "--store", &store_arg]);
    // Real time (30 Hz): the clip takes 5 s, long enough to kill the server mid-stream.
    let mut client = Command::new(bin("stillmap-client"))
        .args(["stream", "--source", &format!("tum:{}", tum_dir().display()), "--server", &server.grpc_url(), "--quiet"])
        .env("STILLMAP_LOG", "error")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn client");

    let mut id = String::new();
    eventually(Duration::from_secs(60), "ten keyframes committed", async || {
        let (_, list) = server.get_json("/api/v1/sessions").await;
        let Some(s) = list["sessions"].as_array().and_then(|a| a.first()) else { return false };
        id = s["session_id"].as_str().unwrap_or_default().to_string();
        let (_, map) = server.get_json(&format!("/api/v1/maps/{id}")).await;
        map["committed_keyframes"].as_u64().unwrap_or(0) >= 10
    })
    .await;
    let (_, before) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    let (_, map_before) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    let committed = map_before["committed_keyframes"].as_u64().expect("committed");
    server.kill9();
    let _ = client.kill();
    let _ = client.wait();
    let seen_before = before["poses"].as_array().expect("poses").clone();
    assert!(seen_before.len() < 150, "the server was killed mid-stream ({} poses)", seen_before.len());

    let server = Server::start(&["--no-zenoh", "--store", &store_arg]);
    let (status, session) = server.get_json(&format!("/api/v1/sessions/{id}")).await;
    assert_eq!(status, 200, "{session}");
    assert_eq!(session["archived"], true);
    assert_eq!(session["connected"], false);
    let (_, after) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    let restored = after["poses"].as_array().expect("poses");
    // Every pose up to the last committed keyframe, exactly as served before the crash.
    assert!(!restored.is_empty());
    assert!(restored.len() <= seen_before.len() + 10, "{} restored, {} seen", restored.len(), seen_before.len());
    let common = restored.len().min(seen_before.len());
    assert_eq!(&restored[..common], &seen_before[..common]);
    let (_, map) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    let keyframes = map["keyframes"].as_u64().expect("keyframes");
    assert!(keyframes >= committed, "{keyframes} keyframes restored, {committed} committed before the kill");
    assert_eq!(map["committed_keyframes"].as_u64(), Some(keyframes));
    assert!(map["occupied_voxels"].as_u64().expect("voxels") > 10_000, "{map}");
    assert_eq!(map["up_source"], "accelerometer");
    // The restored map serves tiles and PLY.
    let ply = reqwest::get(format!("http://{}/api/v1/maps/{id}/cloud.ply", server.http)).await.expect("GET").bytes().await.expect("body");
    assert!(ply.starts_with(b"ply\n"));
    let tile = reqwest::get(format!("http://{}/api/v1/maps/{id}/tiles/0/0/0.png", server.http)).await.expect("GET");
    assert_eq!(tile.status(), 200);

    // Export the whole map as one file, import it into another server.
    let r = reqwest::get(format!("http://{}/api/v1/maps/{id}/export", server.http)).await.expect("GET");
    assert_eq!(r.status(), 200);
    let file = r.bytes().await.expect("body");
    let other = Server::start(&["--no-zenoh"]);
    let http = reqwest::Client::new();
    let import = |body: Vec<u8>| http.post(format!("http://{}/api/v1/maps/import", other.http)).body(body).send();
    let r = import(file.to_vec()).await.expect("POST");
    assert_eq!(r.status(), 201);
    let created: serde_json::Value = r.json().await.expect("json");
    assert_eq!(created["session_id"], id.as_str());
    let (_, imported_map) = other.get_json(&format!("/api/v1/maps/{id}")).await;
    for key in ["keyframes", "occupied_voxels", "blocks", "map_from_world_xyzw", "up_source"] {
        assert_eq!(imported_map[key], map[key], "{key}");
    }
    let (_, imported_trajectory) = other.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    assert_eq!(imported_trajectory["poses"], after["poses"]);
    // Twice is a conflict; a file that is not a map is named.
    let r = import(file.to_vec()).await.expect("POST");
    assert_eq!(r.status(), 409);
    let body: serde_json::Value = r.json().await.expect("json");
    assert_eq!(body["error"], format!("session {id:?} exists already"));
    let r = import(b"GIF89a".to_vec()).await.expect("POST");
    assert_eq!(r.status(), 400);
    let body: serde_json::Value = r.json().await.expect("json");
    assert_eq!(body["error"], "bad map file: not a stillmap map file (bad magic)");
    let (status, body) = other.get_json("/api/v1/maps/nobody/export").await;
    assert_eq!((status, body["error"].as_str()), (404, Some("unknown session \"nobody\"")));
    drop(server);
    let _ = std::fs::remove_file(&store);
}

/// A graceful restart keeps everything, the frames after the last keyframe too.
#[tokio::test(flavor = "multi_thread")]
async fn a_graceful_restart_keeps_every_pose_and_the_map() {
    let store = tempfile_path("restart.redb");
    let store_arg = store.to_str().expect("utf-8 path").to_string();
    let mut server = Server::start(&["--no-zenoh", "--store", &store_arg]);
    let (out, summary) =
        stillmap_e2e::run_client(&["--source", &format!("tum:{}", tum_dir().display()), "--server", &server.grpc_url(), "--rate", "max"]);
    assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
    let id = summary.expect("summary")["session_id"].as_str().expect("id").to_string();
    let (_, before) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    let (_, map_before) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    server.terminate();
    let server = Server::start(&["--no-zenoh", "--store", &store_arg]);
    let (_, after) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    assert_eq!(after["poses"].as_array().map(Vec::len), Some(150));
    assert_eq!(after["poses"], before["poses"]);
    let (_, map) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    for key in ["keyframes", "occupied_voxels", "blocks", "map_from_world_xyzw"] {
        assert_eq!(map[key], map_before[key], "{key}");
    }
    let ply_size =
        reqwest::get(format!("http://{}/api/v1/maps/{id}/export", server.http)).await.expect("GET").bytes().await.expect("body").len();
    eprintln!(
        "store file {} bytes; the session exported as one file: {ply_size} bytes",
        std::fs::metadata(&store).map(|m| m.len()).unwrap_or(0)
    );
    drop(server);
    let _ = std::fs::remove_file(&store);
}

/// The value of the metric line starting with `name ` in `/metrics`.
async fn metric(server: &Server, name: &str) -> Option<u64> {
    let text = server.get_text("/metrics").await;
    text.lines().find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
}

/// A disconnected session leaves memory after session.idle_evict_s and a query
/// brings it back whole; after a restart stored sessions are listed, not loaded,
/// until a query needs one.
#[tokio::test(flavor = "multi_thread")]
async fn idle_sessions_leave_memory_and_stored_ones_load_when_queried() {
    let store = tempfile_path("evict.redb");
    let store_arg = store.to_str().expect("utf-8 path").to_string();
    let config = tempfile_path("evict.toml");
    std::fs::write(&config, "[session]\nidle_evict_s = 1.0\n").expect("write config");
    let config_arg = config.to_str().expect("utf-8 path").to_string();
    let mut server = Server::start(&["--no-zenoh", "--store", &store_arg, "--config", &config_arg]);
    let (out, summary) = stillmap_e2e::run_client(&[
        "--source",
        &format!("tum:{}", tum_dir().display()),
        "--server",
        &server.grpc_url(),
        "--rate",
        "max",
        "--max-frames",
        "60",
    ]);
    assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
    let id = summary.expect("summary")["session_id"].as_str().expect("id").to_string();
    let (_, poses_before) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    let (_, map_before) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    assert!(map_before["occupied_voxels"].as_u64().unwrap_or(0) > 1000, "{map_before}");
    eventually(Duration::from_secs(20), "the idle session leaves memory", async || {
        metric(&server, "stillmap_sessions_evicted_total").await == Some(1)
    })
    .await;
    assert_eq!(metric(&server, "stillmap_sessions_resident").await, Some(0));
    let (_, listed) = server.get_json("/api/v1/sessions").await;
    let entry = &listed["sessions"][0];
    assert_eq!(
        (&entry["session_id"], &entry["resident"], &entry["archived"]),
        (&serde_json::json!(id), &serde_json::json!(false), &serde_json::json!(true))
    );
    assert_eq!(entry["counters"]["frames_processed"], 60);
    // A query brings it back whole.
    let (status, map) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    assert_eq!(status, 200);
    for key in ["keyframes", "occupied_voxels", "blocks"] {
        assert_eq!(map[key], map_before[key], "{key}");
    }
    let (_, poses) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    assert_eq!(poses["poses"], poses_before["poses"]);
    assert_eq!(metric(&server, "stillmap_sessions_loaded_total").await, Some(1));
    // Not queried any more: it leaves again.
    eventually(Duration::from_secs(20), "the loaded session leaves again", async || {
        metric(&server, "stillmap_sessions_evicted_total").await == Some(2)
    })
    .await;
    server.terminate();

    // Restarted on the same store (idle eviction at its default): listed, not loaded.
    let server = Server::start(&["--no-zenoh", "--store", &store_arg]);
    assert_eq!(metric(&server, "stillmap_sessions_resident").await, Some(0));
    let (_, listed) = server.get_json("/api/v1/sessions").await;
    assert_eq!(listed["sessions"][0]["session_id"], serde_json::json!(id));
    let (status, one) = server.get_json(&format!("/api/v1/sessions/{id}")).await;
    assert_eq!((status, &one["resident"]), (200, &serde_json::json!(false)));
    assert_eq!(metric(&server, "stillmap_sessions_resident").await, Some(0), "describing a session loads nothing");
    let (_, poses) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    assert_eq!(poses["poses"], poses_before["poses"]);
    assert_eq!(metric(&server, "stillmap_sessions_resident").await, Some(1));
    assert_eq!(metric(&server, "stillmap_sessions_loaded_total").await, Some(1));
    drop(server);
    let _ = std::fs::remove_file(&store);
    let _ = std::fs::remove_file(&config);
}
