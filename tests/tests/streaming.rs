//! The real client streams real frames to the real server, over gRPC and Zenoh.
#![allow(clippy::disallowed_methods)] // a test's client threads need no names

use std::time::Duration;

use stillmap_e2e::{Server, run_client, tum_dir};

fn tum_source() -> String {
    format!("tum:{}", tum_dir().display())
}

const TUM_FRAMES: u64 = 150;

fn assert_complete(summary: &serde_json::Value, frames: u64) {
    for (key, want) in [
        ("frames_sent", frames),
        ("frames_acknowledged", frames),
        ("depth_bit_exact", frames),
        ("depth_mismatch", 0),
        ("frames_dropped", 0),
        ("frames_rejected", 0),
        ("frames_unanswered", 0),
        ("results_out_of_order", 0),
    ] {
        assert_eq!(summary[key].as_u64(), Some(want), "{key} in {summary:#}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn grpc_delivers_every_tum_frame_bit_exact_and_in_order() {
    let server = Server::start(&[]);
    let (out, summary) = run_client(&["--source", &tum_source(), "--server", &server.grpc_url(), "--rate", "max"]);
    assert!(out.status.success(), "client failed ({}): {}", out.status, String::from_utf8_lossy(&out.stderr));
    let summary = summary.expect("summary JSON");
    assert_complete(&summary, TUM_FRAMES);
    let id = summary["session_id"].as_str().expect("session id");

    let (status, session) = server.get_json(&format!("/api/v1/sessions/{id}")).await;
    assert_eq!(status, 200);
    assert_eq!(session["counters"]["frames_received"], TUM_FRAMES);
    assert_eq!(session["counters"]["frames_processed"], TUM_FRAMES);
    assert_eq!(session["camera"]["fx"], 517.3);
    assert_eq!(session["camera"]["rolling_shutter_readout_s"], 0.025, "the freiburg1 readout the TUM source declares");
    assert_eq!(session["camera"]["exposure_time_offset_s"], -0.0125, "stamped on arrival, half the readout after the middle row");
    assert_eq!(session["camera"]["distortion_model"], "DISTORTION_MODEL_PLUMB_BOB");
    assert_eq!(session["camera"]["depth_encoding"], "DEPTH_ENCODING_ZSTD");
    assert_eq!(session["camera"]["calibration_source"], "tum-folder:rgbd_dataset_freiburg1_rpy (tum-fr1)");
    assert_eq!(session["tracking_state"], "TRACKING_STATE_TRACKING");
    // Every frame's result carried a pose back on the gRPC stream.
    assert_eq!(summary["poses_returned"], TUM_FRAMES);

    let metrics = server.get_text("/metrics").await;
    assert!(metrics.contains("stillmap_frames_processed_total{transport=\"grpc\"} 150"), "{metrics}");
    assert!(metrics.contains("stillmap_stage_latency_seconds_count{stage=\"decode_depth\"} 150"), "{metrics}");
}

#[tokio::test(flavor = "multi_thread")]
async fn zenoh_delivers_every_tum_frame_bit_exact_and_in_order() {
    let server = Server::start(&[]);
    let (out, summary) = run_client(&[
        "--source",
        &tum_source(),
        "--transport",
        "zenoh",
        "--zenoh-connect",
        &server.zenoh,
        "--rate",
        "max",
        "--robot-id",
        "zenoh-bot",
    ]);
    assert!(out.status.success(), "client failed ({}): {}", out.status, String::from_utf8_lossy(&out.stderr));
    let summary = summary.expect("summary JSON");
    assert_complete(&summary, TUM_FRAMES);
    let (_, sessions) = server.get_json("/api/v1/sessions").await;
    let s = &sessions["sessions"][0];
    assert_eq!(s["transport"], "zenoh");
    assert_eq!(s["robot_id"], "zenoh-bot");
    assert_eq!(s["counters"]["frames_processed"], TUM_FRAMES);
    // Poses come back on the Zenoh results topic too.
    assert_eq!(s["tracking_state"], "TRACKING_STATE_TRACKING");
    assert_eq!(summary["poses_returned"], TUM_FRAMES);
}

#[tokio::test(flavor = "multi_thread")]
async fn every_depth_codec_arrives_bit_exact() {
    let server = Server::start(&[]);
    for codec in ["rvl", "png16"] {
        let (out, summary) = run_client(&[
            "--source",
            &tum_source(),
            "--server",
            &server.grpc_url(),
            "--rate",
            "max",
            "--max-frames",
            "20",
            "--depth-codec",
            codec,
        ]);
        assert!(out.status.success(), "{codec}: {}", String::from_utf8_lossy(&out.stderr));
        assert_complete(&summary.expect("summary"), 20);
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn openni2_dummy_device_streams_through_the_real_client() {
    let server = Server::start(&[]);
    // The Dummy device reports no field of view: without a calibration it refuses.
    let (out, _) = run_client(&["--source", "openni2:Dummy", "--server", &server.grpc_url(), "--max-frames", "2"]);
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("OpenNI2 device Dummy: the camera's calibration is not known; give --calibration FILE"), "{stderr}");
    let (out, summary) = run_client(&[
        "--source",
        "openni2:Dummy",
        "--server",
        &server.grpc_url(),
        "--max-frames",
        "12",
        "--robot-id",
        "kinect",
        "--allow-default-intrinsics",
    ]);
    assert!(out.status.success(), "client failed ({}): {}", out.status, String::from_utf8_lossy(&out.stderr));
    assert_complete(&summary.expect("summary"), 12);
    let (_, sessions) = server.get_json("/api/v1/sessions").await;
    let camera_id = sessions["sessions"][0]["session_id"].as_str().expect("id").to_string();
    let (_, detail) = server.get_json(&format!("/api/v1/sessions/{camera_id}")).await;
    assert_eq!(detail["camera"]["width"], 320);
    assert_eq!(detail["camera"]["height"], 240);
    assert_eq!(detail["camera"]["depth_units_per_metre"], 1000.0);
    assert_eq!(detail["camera"]["calibration_source"], "default:nominal intrinsics (--allow-default-intrinsics)");
}

/// A TUM folder reached through a renamed symlink is not guessed: it refuses, and
/// streams with the calibration given as a ROS camera_info file or a known camera.
#[tokio::test(flavor = "multi_thread")]
async fn calibration_comes_from_a_file_or_a_named_camera_never_a_guess() {
    let server = Server::start(&[]);
    let dir = std::env::temp_dir().join(format!("stillmap-e2e-calib-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let link = dir.join("kitchen_run");
    let _ = std::fs::remove_file(&link);
    std::os::unix::fs::symlink(tum_dir(), &link).expect("symlink");
    let src = format!("tum:{}", link.display());

    let (out, _) = run_client(&["--source", &src, "--server", &server.grpc_url(), "--max-frames", "3"]);
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("TUM folder kitchen_run (no freiburg1/2/3 in its name): the camera's calibration is not known"), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "one line: {stderr}");

    let yaml = dir.join("kinect_rgb.yaml");
    std::fs::write(
        &yaml,
        "image_width: 640\nimage_height: 480\ncamera_name: kinect\ncamera_matrix:\n  rows: 3\n  cols: 3\n  \
         data: [517.3, 0, 318.6, 0, 516.5, 255.3, 0, 0, 1]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  \
         rows: 1\n  cols: 5\n  data: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]\n",
    )
    .expect("write yaml");
    let (out, summary) = run_client(&[
        "--source",
        &src,
        "--server",
        &server.grpc_url(),
        "--max-frames",
        "5",
        "--rate",
        "max",
        "--robot-id",
        "from-file",
        "--calibration",
        &yaml.display().to_string(),
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let id = summary.expect("summary")["session_id"].as_str().expect("id").to_string();
    let (_, session) = server.get_json(&format!("/api/v1/sessions/{id}")).await;
    assert_eq!(session["camera"]["calibration_source"], format!("file:{} (ROS camera_info)", yaml.display()));
    assert_eq!(session["camera"]["fy"], 516.5);
    assert_eq!(session["camera"]["distortion_coeffs"][4], 1.1633);
    assert_eq!(session["camera"]["rolling_shutter_readout_s"], 0.0, "a file gives no timing");

    let (out, summary) = run_client(&[
        "--source",
        &src,
        "--server",
        &server.grpc_url(),
        "--max-frames",
        "5",
        "--rate",
        "max",
        "--robot-id",
        "named",
        "--camera",
        "tum-fr1",
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let id = summary.expect("summary")["session_id"].as_str().expect("id").to_string();
    let (_, session) = server.get_json(&format!("/api/v1/sessions/{id}")).await;
    assert_eq!(session["camera"]["calibration_source"], "preset:tum-fr1 (--camera)");
    assert_eq!(session["camera"]["rolling_shutter_readout_s"], 0.025);

    let (out, _) = run_client(&["--source", &src, "--server", &server.grpc_url(), "--camera", "kinect2"]);
    assert_eq!(out.status.code(), Some(2), "clap's usage error");
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown camera \"kinect2\": use tum-fr1|tum-fr2|tum-fr3"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn no_openni2_device_is_a_clear_error() {
    let (out, _) = run_client(&["--source", "openni2", "--server", "http://127.0.0.1:9"]);
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("no OpenNI2 device found"), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "one line: {stderr}");
}

#[tokio::test(flavor = "multi_thread")]
async fn two_robots_at_once_stay_separate() {
    let server = Server::start(&[]);
    let src = tum_source();
    let (grpc, zenoh) = (server.grpc_url(), server.zenoh.clone());
    let a = {
        let src = src.clone();
        std::thread::spawn(move || {
            run_client(&["--source", &src, "--server", &grpc, "--rate", "max", "--max-frames", "60", "--robot-id", "alpha"])
        })
    };
    let b = std::thread::spawn(move || {
        run_client(&[
            "--source",
            &src,
            "--transport",
            "zenoh",
            "--zenoh-connect",
            &zenoh,
            "--rate",
            "max",
            "--max-frames",
            "40",
            "--robot-id",
            "beta",
        ])
    });
    let (a, b) = (a.join().expect("alpha"), b.join().expect("beta"));
    assert!(a.0.status.success() && b.0.status.success());
    let (sa, sb) = (a.1.expect("alpha summary"), b.1.expect("beta summary"));
    assert_complete(&sa, 60);
    assert_complete(&sb, 40);
    assert_ne!(sa["session_id"], sb["session_id"]);
    let (_, sessions) = server.get_json("/api/v1/sessions").await;
    let mut seen: Vec<(String, u64)> = sessions["sessions"]
        .as_array()
        .expect("sessions")
        .iter()
        .map(|s| (s["robot_id"].as_str().unwrap_or("").to_string(), s["counters"]["frames_processed"].as_u64().unwrap_or(0)))
        .collect();
    seen.sort();
    assert_eq!(seen, [("alpha".to_string(), 60), ("beta".to_string(), 40)]);
}

#[test]
fn trajectory_file_holds_only_returned_poses() {
    // Every returned pose, one line each, after the header.
    let server = Server::start(&[]);
    let path = stillmap_e2e::tempfile_path("traj.txt");
    let (out, _) = run_client(&[
        "--source",
        &tum_source(),
        "--server",
        &server.grpc_url(),
        "--rate",
        "max",
        "--max-frames",
        "5",
        "--trajectory",
        path.to_str().expect("utf-8 path"),
    ]);
    assert!(out.status.success());
    let text = std::fs::read_to_string(&path).expect("trajectory file");
    assert_eq!(text.lines().filter(|l| !l.starts_with('#')).count(), 5, "{text}");
    assert!(
        text.lines()
            .nth(1)
            .is_some_and(|l| l.ends_with(" 0.000000000 0.000000000 0.000000000 0.000000000 0.000000000 0.000000000 1.000000000")),
        "{text}"
    );
    let _ = std::fs::remove_file(path);
}

/// Zenoh shows the server no connection closing (gRPC has its stream): a robot that
/// goes quiet counts as disconnected after `zenoh.idle_disconnect_s`, and its next
/// frame attaches the same session again, answered on its results key.
#[tokio::test(flavor = "multi_thread")]
async fn a_quiet_zenoh_robot_is_disconnected_until_its_next_frame() {
    use prost::Message;
    use std::time::Duration;
    use stillmap_e2e::{eventually, tempfile_path, tum_frame};
    use stillmap_proto::{keys, pb};

    let config = tempfile_path("idle.toml");
    // Long enough that answering the next frame (debug build, with the model) cannot
    // be mistaken for going quiet again.
    std::fs::write(&config, "[zenoh]\nidle_disconnect_s = 3.0\n").expect("write config");
    let server = Server::start(&["--config", config.to_str().expect("utf-8 path")]);
    let (out, summary) = run_client(&[
        "--source",
        &tum_source(),
        "--transport",
        "zenoh",
        "--zenoh-connect",
        &server.zenoh,
        "--rate",
        "max",
        "--max-frames",
        "10",
        "--robot-id",
        "quiet-bot",
    ]);
    assert!(out.status.success(), "client failed ({}): {}", out.status, String::from_utf8_lossy(&out.stderr));
    let summary = summary.expect("summary JSON");
    assert_complete(&summary, 10);
    let id = summary["session_id"].as_str().expect("session id").to_string();
    let connected = async |want: bool| {
        let (_, session) = server.get_json(&format!("/api/v1/sessions/{id}")).await;
        let gauge = server.get_text("/metrics").await;
        session["connected"] == want && gauge.contains(&format!("stillmap_sessions_connected {}", u8::from(want)))
    };
    eventually(Duration::from_secs(10), "the quiet robot to count as disconnected", async || connected(false).await).await;

    // The robot speaks again on its key: the same session takes the frame and answers.
    let mut zconfig = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
        ("listen/endpoints", "[]".to_string()),
        ("connect/endpoints", format!("[\"{}\"]", server.zenoh)),
    ] {
        zconfig.insert_json5(key, &value).expect(key);
    }
    let robot = zenoh::open(zconfig).await.expect("zenoh open");
    let results = robot.declare_subscriber(keys::results("quiet-bot")).await.expect("subscribe");
    eventually(Duration::from_secs(10), "the server as a Zenoh peer", async || robot.info().peers_zid().await.count() > 0).await;
    // A put before the server's subscription has reached this peer would be lost.
    // Blocking, as the client's publisher: the frame (140 KB) spans three of the
    // transport's 64 KB batches and its queue holds two, so under load a dropping
    // put (Zenoh's default) can lose it while waiting for the first to drain.
    let publisher = robot
        .declare_publisher(keys::frames("quiet-bot"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .expect("publisher");
    eventually(Duration::from_secs(10), "the server's subscription", async || {
        publisher.matching_status().await.is_ok_and(|m| m.matching())
    })
    .await;
    let frame = pb::ClientMessage { msg: Some(pb::client_message::Msg::Frame(tum_frame(10, 1_000_000_000))), fleet: String::new() };
    publisher.put(frame.encode_to_vec()).await.expect("put frame");
    let answer = tokio::time::timeout(Duration::from_secs(10), results.recv_async()).await.expect("an answer").expect("sample");
    let answer = pb::ServerMessage::decode(answer.payload().to_bytes().as_ref()).expect("server message");
    match answer.msg {
        Some(pb::server_message::Msg::Result(r)) => assert_eq!(r.sequence, 10),
        other => panic!("expected the frame's result, got {other:?}"),
    }
    assert!(connected(true).await, "the robot's frame attached its session again");
    let (_, session) = server.get_json(&format!("/api/v1/sessions/{id}")).await;
    assert_eq!(session["counters"]["frames_received"], 11);
    let _ = std::fs::remove_file(&config);
}

/// A Zenoh server that accepts the robot and then never answers (a stalled
/// pipeline, its liveliness up): each `--timeout` with frames waiting the client
/// says hello again, and after three in a row it gives up, instead of waiting for
/// ever once `--max-in-flight` frames wait.
#[tokio::test(flavor = "multi_thread")]
async fn a_zenoh_server_that_stops_answering_is_given_up_after_the_timeout() {
    use prost::Message;
    use stillmap_proto::{keys, pb};
    let endpoint = format!("tcp/127.0.0.1:{}", stillmap_e2e::free_port());
    let mut zconfig = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
        ("listen/endpoints", format!("[\"{endpoint}\"]")),
    ] {
        zconfig.insert_json5(key, &value).expect(key);
    }
    let stalled = zenoh::open(zconfig).await.expect("zenoh open");
    let frames = stalled.declare_subscriber(keys::frames("stalled-bot")).await.expect("subscribe");
    let results = stalled.declare_publisher(keys::results("stalled-bot")).await.expect("publisher");
    // Accepts every hello, answers no frame.
    let accepting = tokio::spawn(async move {
        while let Ok(sample) = frames.recv_async().await {
            let Ok(pb::ClientMessage { msg: Some(pb::client_message::Msg::Hello(_)), .. }) =
                pb::ClientMessage::decode(sample.payload().to_bytes().as_ref())
            else {
                continue;
            };
            let accepted = pb::SessionAccepted { session_id: "stalled-bot-1".into(), max_message_bytes: 64 << 20, ..Default::default() };
            let reply = pb::ServerMessage { msg: Some(pb::server_message::Msg::Accepted(accepted)) };
            results.put(reply.encode_to_vec()).await.expect("put accept");
        }
    });
    let src = format!("tum:{}", tum_dir().display());
    let started = std::time::Instant::now();
    let client = tokio::task::spawn_blocking(move || {
        run_client(&[
            "--source",
            &src,
            "--transport",
            "zenoh",
            "--zenoh-connect",
            &endpoint,
            "--robot-id",
            "stalled-bot",
            "--rate",
            "max",
            "--timeout",
            "3",
        ])
    });
    // A client that waits for ever fails the test here, not the run.
    let (out, _) =
        tokio::time::timeout(Duration::from_secs(60), client).await.expect("the client gave up within 60 s").expect("client thread");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("results did not arrive within 3s (--timeout), 3 times in a row"), "{stderr}");
    assert!(started.elapsed() < Duration::from_secs(30), "took {:?}", started.elapsed());
    accepting.abort();
}

/// gRPC health checking answers for the server and each service (SERVING), names an
/// unknown service NOT_FOUND and turns NOT_SERVING when the server shuts down;
/// reflection lists the services.
#[tokio::test(flavor = "multi_thread")]
async fn grpc_health_and_reflection_describe_the_server() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

    let mut server = Server::start(&["--no-zenoh", "--no-perception"]);
    let channel = tonic::transport::Channel::from_shared(server.grpc_url()).expect("url").connect().await.expect("connect");
    let mut health = HealthClient::new(channel.clone());
    for service in ["", "stillmap.v1.Ingest", "stillmap.v1.Query"] {
        let status = health.check(HealthCheckRequest { service: service.into() }).await.expect("check").into_inner().status;
        assert_eq!(status, ServingStatus::Serving as i32, "{service:?}");
    }
    let unknown = health.check(HealthCheckRequest { service: "stillmap.v1.Nope".into() }).await.expect_err("unknown service");
    assert_eq!(unknown.code(), tonic::Code::NotFound);

    let mut reflection = ServerReflectionClient::new(channel);
    let request = ServerReflectionRequest { host: String::new(), message_request: Some(MessageRequest::ListServices(String::new())) };
    let mut answers = reflection.server_reflection_info(tokio_stream::iter([request])).await.expect("reflection").into_inner();
    let answer = answers.message().await.expect("answer").expect("one answer");
    let Some(MessageResponse::ListServicesResponse(list)) = answer.message_response else { panic!("{answer:?}") };
    let mut names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    names.sort();
    assert_eq!(names, ["grpc.health.v1.Health", "grpc.reflection.v1.ServerReflection", "stillmap.v1.Ingest", "stillmap.v1.Query"]);

    // A load balancer watching the server sees it leave before it closes.
    let mut watch = health.watch(HealthCheckRequest { service: String::new() }).await.expect("watch").into_inner();
    assert_eq!(watch.message().await.expect("status").expect("first status").status, ServingStatus::Serving as i32);
    let stopping = tokio::task::spawn_blocking(move || server.terminate());
    let next = tokio::time::timeout(Duration::from_secs(10), watch.message()).await.expect("a status in time").expect("status");
    assert_eq!(next.map(|s| s.status), Some(ServingStatus::NotServing as i32));
    stopping.await.expect("terminate");
}
