//! The Python client example (`examples/python/stillmap_example.py`, gRPC stubs
//! generated from `proto/` with grpcio-tools) against a real server while the real
//! client streams the TUM clip: it lists the sessions, receives live poses and saves
//! a map tile, with a read token. Its Python comes from `.deps/pyclient` (`make deps`).

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use stillmap_e2e::{Server, bin, decode_png, repo_dir, tempfile_path, tum_dir, venv_python};

#[tokio::test(flavor = "multi_thread")]
async fn the_python_example_lists_sessions_follows_poses_and_saves_a_tile() {
    let python = venv_python("pyclient");
    let server = Server::start(&["--no-zenoh", "--no-perception", "--auth-token", "robot-secret", "--read-token", "reader"]);
    let summary = tempfile_path("summary.json");
    let mut robot = Command::new(bin("stillmap-client"))
        .args(["stream", "--source", &format!("tum:{}", tum_dir().display()), "--server", &server.grpc_url()])
        .args(["--rate", "30", "--token", "robot-secret", "--robot-id", "py-robot"])
        .args(["--summary-json", summary.to_str().expect("utf-8 path")])
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("spawn stillmap-client");

    let tile = tempfile_path("tile.png");
    let started = Instant::now();
    let out = Command::new(&python)
        .arg(repo_dir().join("examples/python/stillmap_example.py"))
        .args(["--grpc", &server.grpc, "--http", &format!("http://{}", server.http), "--token", "reader"])
        .args(["--poses", "10", "--wait", "30", "--tile", tile.to_str().expect("utf-8 path")])
        .output()
        .expect("run the Python example");
    assert!(out.status.success(), "the example failed: {}", String::from_utf8_lossy(&out.stderr));
    assert!(started.elapsed() < Duration::from_secs(90));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object on stdout");
    assert!(robot.wait().expect("client").success(), "the streaming client failed");
    let streamed: serde_json::Value = serde_json::from_slice(&std::fs::read(&summary).expect("summary")).expect("summary JSON");
    let id = streamed["session_id"].as_str().expect("session id");

    // The session it listed and followed is the robot's.
    assert_eq!(report["session_id"], id, "{report}");
    assert!(report["sessions"].as_array().expect("sessions").iter().any(|s| s["robot_id"] == "py-robot"), "{report}");
    // Ten live poses, in order, each the one the server keeps for that frame.
    let poses = report["poses"].as_array().expect("poses");
    assert_eq!(poses.len(), 10, "{report}");
    let sequences: Vec<u64> = poses.iter().map(|p| p["sequence"].as_u64().expect("sequence")).collect();
    assert!(sequences.windows(2).all(|w| w[0] < w[1]), "{sequences:?}");
    let (status, trajectory) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    assert_eq!(status, 200, "{trajectory}");
    for p in poses {
        let kept = trajectory["poses"]
            .as_array()
            .expect("poses")
            .iter()
            .find(|q| q["sequence"] == p["sequence"])
            .unwrap_or_else(|| panic!("pose {} not in the trajectory", p["sequence"]));
        assert_eq!(kept["translation"], p["translation"], "frame {}", p["sequence"]);
        assert_eq!(kept["rotation_xyzw"], p["rotation_xyzw"], "frame {}", p["sequence"]);
    }
    // The tile: a 256x256 PNG with the map drawn in it.
    let bytes = std::fs::read(&tile).expect("the saved tile");
    assert_eq!(report["tile"]["bytes"].as_u64(), Some(bytes.len() as u64));
    let (w, h, rgba) = decode_png(&bytes);
    assert_eq!((w, h), (256, 256));
    let drawn = rgba.chunks_exact(4).filter(|p| p[3] == 255).count();
    assert!(drawn > 100, "{drawn} pixels drawn in {report}");

    // Refused by name without the token, exit code 1.
    let out = Command::new(&python)
        .arg(repo_dir().join("examples/python/stillmap_example.py"))
        .args(["--grpc", &server.grpc, "--http", &format!("http://{}", server.http), "--wait", "1"])
        .output()
        .expect("run the Python example");
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.starts_with("stillmap_example: ") && stderr.contains("read scope"), "{stderr}");
}
