//! Camera tracking through the real client and server on the real TUM clip:
//! poses on every channel, and accuracy measured by the evo-exact eval tool.

use std::path::Path;
use std::process::Command;

use stillmap_e2e::{Server, bin, run_client, tempfile_path, tum_dir};

/// Frames in the clip.
const TUM_FRAMES: usize = 150;

/// Runs `stillmap-client eval` and returns its JSON result.
fn eval(args: &[&str], estimate: &std::path::Path) -> serde_json::Value {
    let json = tempfile_path("eval.json");
    let out = Command::new(bin("stillmap-client"))
        .arg("eval")
        .args(args)
        .arg(tum_dir().join("groundtruth.txt"))
        .arg(estimate)
        .arg("--json")
        .arg(&json)
        .output()
        .expect("run stillmap-client eval");
    assert!(out.status.success(), "eval {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
    let v = serde_json::from_str(&std::fs::read_to_string(&json).expect("eval json")).expect("valid json");
    let _ = std::fs::remove_file(&json);
    v
}

/// `relation` is "translation" (metres) or "rotation" (degrees).
fn rmse(result: &serde_json::Value, relation: &str) -> f64 {
    result[relation]["rmse"].as_f64().unwrap_or_else(|| panic!("no {relation}.rmse in {result}"))
}

#[tokio::test(flavor = "multi_thread")]
async fn streamed_tum_clip_is_tracked_and_served_on_every_channel() {
    // Reproducible: every frame segmented before it is masked (the paper's
    // synchronous pipeline). The asynchronous default makes masks, and so poses,
    // depend on thread timing: over 14 runs ATE moved between 4.8 and 7.0 cm, the
    // spread coming from false-dynamic flow regions on the motion-blurred frames
    // 105-116 (see the closing note of the map issue).
    let config = tempfile_path("deterministic.toml");
    std::fs::write(&config, "[perception.segmentation]\ndeterministic_every_frames = 1\ndeterministic_delay_frames = 0\n").expect("config");
    let server = Server::start(&["--no-zenoh", "--config", config.to_str().expect("utf-8 path")]);
    let client_trajectory = tempfile_path("client.tum");
    let (out, summary) = run_client(&[
        "--source",
        &format!("tum:{}", tum_dir().display()),
        "--server",
        &server.grpc_url(),
        "--rate",
        "max",
        "--trajectory",
        client_trajectory.to_str().expect("utf-8 path"),
    ]);
    assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
    let summary = summary.expect("summary");
    let id = summary["session_id"].as_str().expect("session id").to_string();
    assert_eq!(summary["frames_dropped"], 0);
    assert_eq!(summary["poses_returned"], TUM_FRAMES as u64, "every frame tracked, pose on the result stream");

    // Latest pose.
    let (status, pose) = server.get_json(&format!("/api/v1/sessions/{id}/pose")).await;
    assert_eq!(status, 200);
    assert_eq!(pose["tracking_state"], "TRACKING_STATE_TRACKING");
    assert_eq!(pose["pose"]["sequence"], TUM_FRAMES as u64 - 1);
    assert_eq!(pose["pose"]["rotation_xyzw"].as_array().map(Vec::len), Some(4));
    // The TUM source stamps freiburg1 frames on arrival, after the last row: the pose
    // refers to the middle row, half the 25 ms readout earlier.
    let capture_ns = pose["pose"]["capture_time_ns"].as_u64().expect("capture time");
    assert_eq!(pose["pose"]["pose_time_ns"].as_u64(), Some(capture_ns - 12_500_000), "{pose}");

    // Trajectory as JSON and as TUM text; both hold every frame, and the text is
    // exactly what the client got back on its result stream.
    let (status, traj) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    assert_eq!(status, 200);
    assert_eq!(traj["poses"].as_array().map(Vec::len), Some(TUM_FRAMES));
    assert_eq!(traj["poses"][0]["translation"], serde_json::json!([0.0, 0.0, 0.0]), "world = first camera");
    let tum = server.get_text(&format!("/api/v1/sessions/{id}/trajectory?format=tum")).await;
    let lines: Vec<&str> = tum.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(lines.len(), TUM_FRAMES);
    let first_stamp = lines[0].split_whitespace().next().expect("timestamp");
    assert_eq!(first_stamp, "1305031229.516248000", "the first frame (stamped 1305031229.528748) at its pose's time");
    let server_trajectory = tempfile_path("server.tum");
    std::fs::write(&server_trajectory, &tum).expect("write trajectory");
    let client_text = std::fs::read_to_string(&client_trajectory).expect("client trajectory");
    let parse = |text: &str| stillmap_dataset::trajectory::parse_tum_ns(text, Path::new("trajectory")).expect("TUM trajectory");
    let (client_poses, server_poses) = (parse(&client_text), parse(&tum));
    assert_eq!(client_poses.len(), server_poses.len());
    for ((ta, a), (tb, b)) in client_poses.iter().zip(&server_poses) {
        let d = a.inverse() * b;
        assert!(
            ta == tb && d.translation.vector.norm() < 1e-5 && d.rotation.angle() < 1e-5,
            "client and server trajectories differ: {a:?} vs {b:?}"
        );
    }
    let (status, bad) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory?format=xml")).await;
    assert_eq!(status, 400);
    assert_eq!(bad["error"], "unknown trajectory format \"xml\"; use json or tum");
    let (status, missing) = server.get_json("/api/v1/sessions/nobody-1/pose").await;
    assert_eq!(status, 404);
    assert_eq!(missing["error"], "unknown session \"nobody-1\"");

    // Accuracy against the ground truth, evo semantics (20 ms association).
    // Measured on this machine (every frame segmented, the client declaring the
    // freiburg1 camera's 25 ms rolling-shutter readout and its -12.5 ms exposure
    // offset): ATE 0.89 cm, origin-aligned rotation 1.38 deg, RPE 5.9 mm / 0.454 deg
    // (2026-12-06, new map points spread over the image; before: 0.96 cm, 1.41 deg,
    // 5.89 mm, 0.453 deg)
    // per frame (docs/tracking.md, "Tracking accuracy"); the targets are 2.0 cm, 2.0 deg,
    // 6 mm and 0.5 deg. The bounds leave a margin for the clip's sensitivity to tiny
    // changes.
    let ate = eval(&["ape", "--align", "--relation", "trans"], &server_trajectory);
    let ate_rot = eval(&["ape", "--align-origin", "--relation", "rot"], &server_trajectory);
    let rpe = eval(&["rpe"], &server_trajectory);
    let (t, r, rt, rr) = (rmse(&ate, "translation"), rmse(&ate_rot, "rotation"), rmse(&rpe, "translation"), rmse(&rpe, "rotation"));
    println!("streamed fr1_rpy: ATE {:.2} cm, {r:.2} deg (origin) | RPE {:.1} mm, {rr:.3} deg", t * 100.0, rt * 1000.0);
    assert!(t <= 0.013, "ATE translation {t} m");
    assert!(r <= 1.7, "ATE rotation {r} deg");
    assert!(rt <= 0.0065, "RPE translation {rt} m");
    assert!(rr <= 0.5, "RPE rotation {rr} deg");
    for p in [client_trajectory, server_trajectory, config] {
        let _ = std::fs::remove_file(p);
    }
}
