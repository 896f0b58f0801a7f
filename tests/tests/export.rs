//! A session as an MCAP file for Foxglove (`GET /api/v1/sessions/{id}/export.mcap`):
//! the real client streams the clip, and Foxglove's reference reader (the Python
//! `mcap` library, `tests/scripts/check-mcap.py` from `.deps/bagtools`) reads every
//! channel back; the file agrees with what the server serves over its own API.

use std::process::Command;
use std::time::Instant;

use stillmap_e2e::{Server, http_get, repo_dir, run_client, tempfile_path, tum_dir, venv_python};

#[tokio::test(flavor = "multi_thread")]
async fn a_session_exports_as_mcap_for_foxglove() {
    let python = venv_python("bagtools");
    let server = Server::start(&["--no-zenoh", "--no-perception"]);
    let (out, summary) =
        run_client(&["--source", &format!("tum:{}", tum_dir().display()), "--server", &server.grpc_url(), "--rate", "max"]);
    assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
    let id = summary.expect("summary")["session_id"].as_str().expect("session id").to_string();

    let started = Instant::now();
    let r = http_get(&server, &format!("/api/v1/sessions/{id}/export.mcap"), None).await;
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "application/octet-stream");
    let bytes = r.bytes().await.expect("body");
    eprintln!("export.mcap: {} bytes in {:.0} ms", bytes.len(), started.elapsed().as_secs_f64() * 1e3);
    assert!(bytes.starts_with(b"\x89MCAP0\r\n"), "an MCAP file");
    let file = tempfile_path("session.mcap");
    std::fs::write(&file, &bytes).expect("write");
    let out = Command::new(python).arg(repo_dir().join("tests/scripts/check-mcap.py")).arg(&file).output().expect("run check-mcap.py");
    assert!(out.status.success(), "the mcap library could not read it: {}", String::from_utf8_lossy(&out.stderr));
    let read: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    let _ = std::fs::remove_file(&file);

    // Every channel, with Foxglove's schema names and JSON encodings.
    let topics = &read["topics"];
    for (topic, schema) in [
        ("/pose", "foxglove.PoseInFrame"),
        ("/trajectory", "foxglove.PosesInFrame"),
        ("/tracking_state", "stillmap.TrackingState"),
        ("/tf", "foxglove.FrameTransform"),
        ("/map", "foxglove.PointCloud"),
        ("/keyframes", "foxglove.CompressedImage"),
    ] {
        assert_eq!(topics[topic]["schema"], schema, "{topic}: {read}");
        assert_eq!((&topics[topic]["schema_encoding"], &topics[topic]["message_encoding"]), (&"jsonschema".into(), &"json".into()));
    }
    assert_eq!(read["channels_in_summary"], 6);
    assert_eq!(read["metadata"][0]["session_id"], id.as_str());
    // The poses are the served trajectory's, in order, one state per frame.
    let (_, trajectory) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    let served: Vec<&serde_json::Value> = trajectory["poses"].as_array().expect("poses").iter().collect();
    assert_eq!(served.len(), 150);
    assert_eq!(read["states"], 150);
    let poses = read["poses"].as_array().expect("poses");
    assert_eq!(poses.len(), 150, "every frame was tracked");
    assert_eq!(read["trajectory"], 150);
    for (p, s) in poses.iter().zip(&served) {
        assert_eq!((&p["translation"], &p["rotation_xyzw"]), (&s["translation"], &s["rotation_xyzw"]));
        assert_eq!(p["log_time"], s["pose_time_ns"]);
        assert_eq!(p["frame_id"], "world");
    }
    // The map: every occupied voxel, in the map frame, rotated from world as the map says.
    let (_, info) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    let cloud = &read["cloud"];
    assert_eq!(cloud["points"], info["occupied_voxels"], "{cloud} vs {info}");
    assert_eq!((&cloud["stride"], &cloud["remainder"], &cloud["frame_id"]), (&18.into(), &0.into(), &"map".into()));
    assert!(cloud["points"].as_u64().expect("count") > 20_000);
    let q: Vec<f64> = info["map_from_world_xyzw"].as_array().expect("rotation").iter().map(|v| v.as_f64().expect("number")).collect();
    let tf = &read["tf"];
    let got = [&tf["rotation"]["x"], &tf["rotation"]["y"], &tf["rotation"]["z"], &tf["rotation"]["w"]].map(|v| v.as_f64().expect("number"));
    assert!(q.iter().zip(got).all(|(a, b)| (a - b).abs() < 1e-12), "{q:?} vs {got:?}");
    assert_eq!((&tf["parent_frame_id"], &tf["child_frame_id"]), (&"map".into(), &"world".into()));

    // The newest keyframes' images (session.keyframe_images, 32), JPEG, at frame times.
    let images = read["images"].as_array().expect("images");
    let keyframes = info["keyframes"].as_u64().expect("keyframes") as usize;
    assert_eq!(images.len(), keyframes.min(32), "{keyframes} keyframes");
    let times: Vec<&serde_json::Value> = served.iter().map(|s| &s["capture_time_ns"]).collect();
    for i in images {
        assert!(i["jpeg"].as_bool() == Some(true) && i["format"] == "jpeg" && i["bytes"].as_u64() > Some(10_000), "{i}");
        assert!(times.contains(&&i["log_time"]), "{i} is not at a frame's time");
    }

    // An unknown session: 404 naming it.
    let (status, body) = server.get_json("/api/v1/sessions/nobody/export.mcap").await;
    assert_eq!((status, body["error"].as_str()), (404, Some("unknown session \"nobody\"")));
}
