//! Zenoh behind a router with client certificates and the per-robot access
//! control `deploy/zenoh/make-router-config.py` writes (issue 21). The router is
//! Zenoh's own (opened in this process from the generated file, as `zenohd -c`
//! would); the server and the robot use the shipped `server.json5` and
//! `robot.json5` with this test's certificates. A robot with its own
//! certificate streams; another robot cannot publish a hello or a frame on its
//! key, nor read its results; a link without a certificate gets nowhere.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use prost::Message;
use stillmap_e2e::{Server, eventually, free_port, run_client, signed_certificate, tempfile_path, test_ca, tum_dir, tum_frame, tum_hello};
use stillmap_proto::{keys, pb};

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(path)
}

/// A shipped client-side template (`server.json5`, `robot.json5`) with this
/// test's certificate directory, router endpoint and certificate name.
fn from_template(dir: &Path, template: &str, endpoint: &str, certificate: &str, template_certificate: &str) -> PathBuf {
    let text = std::fs::read_to_string(repo(&format!("deploy/zenoh/{template}"))).expect("read template");
    let text = text
        .replace("/etc/stillmap/zenoh/", &format!("{}/", dir.display()))
        .replace("tls/zenoh-router:7447", endpoint)
        .replace(&format!("{template_certificate}."), &format!("{certificate}."));
    let path = dir.join(format!("{certificate}.json5"));
    std::fs::write(&path, text).expect("write config");
    path
}

async fn open(config: &Path) -> zenoh::Session {
    zenoh::open(zenoh::Config::from_file(config).expect("zenoh config")).await.expect("zenoh open")
}

fn client_message(msg: pb::client_message::Msg) -> Vec<u8> {
    pb::ClientMessage { msg: Some(msg), fleet: String::new() }.encode_to_vec()
}

#[tokio::test(flavor = "multi_thread")]
async fn the_router_keeps_each_robot_on_its_own_keys() {
    let dir = tempfile_path("zenoh-acl");
    std::fs::create_dir_all(&dir).expect("dir");
    test_ca(&dir);
    signed_certificate(&dir, "router", "serverAuth", "IP:127.0.0.1,DNS:localhost");
    for name in ["stillmap-server", "robot-a", "robot-b"] {
        signed_certificate(&dir, name, "clientAuth", &format!("DNS:{name}"));
    }
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let file = |f: &str| dir.join(f).to_str().expect("utf-8").to_string();
    let out = Command::new("python3")
        .arg(repo("deploy/zenoh/make-router-config.py"))
        .args([
            "--robots",
            "robot-a,robot-b",
            "--listen",
            &endpoint,
            "--ca",
            &file("ca.pem"),
            "--cert",
            &file("router.pem"),
            "--key",
            &file("router.key"),
        ])
        .output()
        .expect("run make-router-config.py");
    assert!(out.status.success(), "make-router-config.py: {}", String::from_utf8_lossy(&out.stderr));
    std::fs::write(dir.join("router.json5"), &out.stdout).expect("write router config");
    let router = open(&dir.join("router.json5")).await;

    let server_zenoh = from_template(&dir, "server.json5", &endpoint, "stillmap-server", "stillmap-server");
    let toml = dir.join("server.toml");
    std::fs::write(&toml, format!("[zenoh]\nconfig_file = {:?}\n", server_zenoh.to_str().expect("utf-8"))).expect("server config");
    let server = Server::start(&["--no-perception", "--config", toml.to_str().expect("utf-8")]);

    // Robot B, on its own key: the server hears it (the link and the ACL let the
    // robot's own traffic through).
    let robot_b = open(&from_template(&dir, "robot.json5", &endpoint, "robot-b", "robot-a")).await;
    let own_results = robot_b.declare_subscriber(keys::results("robot-b")).await.expect("subscribe");
    let own_frames = robot_b
        .declare_publisher(keys::frames("robot-b"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .expect("publisher");
    eventually(Duration::from_secs(20), "the server's subscription to reach robot B", async || {
        own_frames.matching_status().await.is_ok_and(|m| m.matching())
    })
    .await;
    own_frames.put(client_message(pb::client_message::Msg::Hello(tum_hello("robot-b")))).await.expect("put hello");
    let answer = tokio::time::timeout(Duration::from_secs(10), own_results.recv_async()).await.expect("robot B's accept").expect("sample");
    match pb::ServerMessage::decode(answer.payload().to_bytes().as_ref()).expect("server message").msg {
        Some(pb::server_message::Msg::Accepted(a)) => assert!(a.session_id.starts_with("robot-b-"), "{a:?}"),
        other => panic!("expected robot B's accept, got {other:?}"),
    }

    // Robot B forges robot A's hello and a frame far ahead of A's sequence, and
    // listens to A's results: the router drops all of it. The puts block rather
    // than drop (the frame spans more batches than the queue holds), so that what
    // is dropped is dropped by the router, not on the way out of robot B.
    let spy = robot_b.declare_subscriber(keys::results("robot-a")).await.expect("subscribe");
    let block = zenoh::qos::CongestionControl::Block;
    for _ in 0..3 {
        let hello = client_message(pb::client_message::Msg::Hello(tum_hello("robot-a")));
        let _ = robot_b.put(keys::frames("robot-a"), hello).congestion_control(block).await;
        let frame = client_message(pb::client_message::Msg::Frame(tum_frame(u64::MAX, u64::MAX)));
        let _ = robot_b.put(keys::frames("robot-a"), frame).congestion_control(block).await;
    }

    // Robot A with its own certificate streams through the router.
    let robot_a = from_template(&dir, "robot.json5", &endpoint, "robot-a", "robot-a");
    let source = format!("tum:{}", tum_dir().display());
    let (out, summary) = run_client(&[
        "--source",
        &source,
        "--max-frames",
        "10",
        "--rate",
        "max",
        "--transport",
        "zenoh",
        "--zenoh-config",
        robot_a.to_str().expect("utf-8"),
        "--robot-id",
        "robot-a",
        "--timeout",
        "20",
    ]);
    assert!(out.status.success(), "robot A failed ({}): {}", out.status, String::from_utf8_lossy(&out.stderr));
    let summary = summary.expect("summary JSON");
    assert_eq!(summary["frames_sent"], 10, "{summary}");
    assert_eq!(summary["poses_returned"], 10, "{summary}");

    let (_, sessions) = server.get_json("/api/v1/sessions").await;
    let sessions = sessions["sessions"].as_array().expect("sessions").clone();
    let of = |robot: &str| sessions.iter().filter(|s| s["robot_id"] == robot).count();
    assert_eq!((of("robot-a"), of("robot-b")), (1, 1), "one session each, none forged: {sessions:?}");
    let a = sessions.iter().find(|s| s["robot_id"] == "robot-a").expect("robot A's session");
    assert_eq!(a["counters"]["frames_received"], 10, "only robot A's own frames: {a}");
    assert!(spy.try_recv().expect("spy").is_none(), "robot B read robot A's results");

    // Without a certificate the router does not let a link up at all.
    let bare = dir.join("bare.json5");
    let text = std::fs::read_to_string(from_template(&dir, "robot.json5", &endpoint, "robot-b", "robot-a")).expect("read");
    let text =
        text.lines().filter(|l| !l.contains("connect_certificate") && !l.contains("connect_private_key")).collect::<Vec<_>>().join("\n");
    std::fs::write(&bare, text).expect("write");
    let refused = zenoh::open(zenoh::Config::from_file(&bare).expect("config")).await;
    assert!(refused.is_err(), "a client without a certificate opened a session through the router");
    drop(router);
    let _ = std::fs::remove_dir_all(&dir);
}
