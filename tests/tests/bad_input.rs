//! Bad input against a real server process: every case gets a gRPC status (or a
//! rejected result carrying one) whose message names the problem, the session
//! survives a bad frame, and the server survives everything.

use std::time::Duration;

use stillmap_e2e::{Server, first_tum_frame, tum_frame, tum_hello};
use stillmap_proto::codec;
use stillmap_proto::pb::{
    self, FrameStatus, client_message::Msg as ClientMsg, ingest_client::IngestClient, query_client::QueryClient, server_message::Msg,
};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

/// One raw ingest stream.
struct Stream {
    tx: mpsc::Sender<pb::ClientMessage>,
    rx: tonic::Streaming<pb::ServerMessage>,
}

impl Stream {
    async fn open(server: &Server) -> Self {
        let mut client = IngestClient::connect(server.grpc_url()).await.expect("connect");
        let (tx, rx) = mpsc::channel(16);
        let rx = client.stream(ReceiverStream::new(rx)).await.expect("stream").into_inner();
        Self { tx, rx }
    }

    async fn send(&self, msg: ClientMsg) {
        self.tx.send(pb::ClientMessage { msg: Some(msg), fleet: String::new() }).await.expect("send");
    }

    async fn next(&mut self) -> Result<pb::ServerMessage, tonic::Status> {
        tokio::time::timeout(Duration::from_secs(20), self.rx.message()).await.expect("answer in time").map(|m| m.expect("stream open"))
    }

    async fn hello(server: &Server, hello: pb::Hello) -> (Self, pb::SessionAccepted) {
        let mut s = Self::open(server).await;
        s.send(ClientMsg::Hello(hello)).await;
        match s.next().await.expect("accepted").msg {
            Some(Msg::Accepted(a)) => (s, a),
            other => panic!("expected accepted, got {other:?}"),
        }
    }

    async fn result(&mut self) -> pb::FrameResult {
        match self.next().await.expect("result").msg {
            Some(Msg::Result(r)) => r,
            other => panic!("expected a result, got {other:?}"),
        }
    }
}

fn rejected(r: &pb::FrameResult) -> (Code, String) {
    assert_eq!(r.status(), FrameStatus::Rejected, "{r:?}");
    let e = r.error.clone().expect("error");
    (Code::from_i32(e.code), e.message)
}

#[tokio::test(flavor = "multi_thread")]
async fn frame_before_hello_is_failed_precondition() {
    let server = Server::start(&[]);
    let mut s = Stream::open(&server).await;
    s.send(ClientMsg::Frame(tum_frame(0, 1))).await;
    let status = s.next().await.expect_err("status");
    assert_eq!(status.code(), Code::FailedPrecondition);
    assert_eq!(status.message(), "frame 0 arrived before the hello: the first message of a session must be a hello");
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_hello_is_invalid_argument() {
    let server = Server::start(&[]);
    let mut s = Stream::open(&server).await;
    s.send(ClientMsg::Hello(pb::Hello { robot_id: "r".into(), camera: None, ..Default::default() })).await;
    let status = s.next().await.expect_err("status");
    assert_eq!((status.code(), status.message()), (Code::InvalidArgument, "bad hello: hello has no camera info"));
}

/// `Ingest.Place` on a server alone: every robot belongs to it, at the address it
/// advertises; a bad robot id or fleet name is INVALID_ARGUMENT by name, and the
/// token is checked as a hello's.
#[tokio::test(flavor = "multi_thread")]
async fn place_answers_the_servers_own_address_and_names_bad_input() {
    let server = Server::start_with(&["--no-perception", "--auth-token", "fleet-secret-1"], true);
    let mut client = IngestClient::connect(server.grpc_url()).await.expect("connect");
    let hello = |robot_id: &str, fleet: &str, token: &str| pb::Hello {
        robot_id: robot_id.into(),
        fleet: fleet.into(),
        auth_token: token.into(),
        ..Default::default()
    };
    let placed = client.place(hello("r1", "warehouse", "fleet-secret-1")).await.expect("placed").into_inner();
    assert_eq!(placed.grpc_address, format!("http://{}", server.grpc));
    let port = server.grpc.rsplit(':').next().expect("port");
    assert!(placed.server_id.ends_with(&format!("-{port}")), "the default server id <host>-<port>: {}", placed.server_id);
    for (robot, fleet, token, code, message) in [
        ("a b", "", "fleet-secret-1", Code::InvalidArgument, "robot_id \"a b\" contains ' '; allowed are A-Z a-z 0-9 _ -"),
        ("r1", "x/y", "fleet-secret-1", Code::InvalidArgument, "fleet \"x/y\" contains '/'; allowed are A-Z a-z 0-9 _ -"),
        ("r1", "", "wrong", Code::Unauthenticated, "unknown auth token"),
    ] {
        let status = client.place(hello(robot, fleet, token)).await.expect_err("refused");
        assert_eq!((status.code(), status.message()), (code, message), "{robot} {fleet} {token}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_frames_are_rejected_by_name_and_the_session_goes_on() {
    let server = Server::start(&[]);
    let (mut s, accepted) = Stream::hello(&server, tum_hello("bad-frames")).await;
    let (color, depth) = first_tum_frame();

    // 1. Size differs from the hello: a 320x240 colour image.
    let small = codec::ColorImage {
        width: 320,
        height: 240,
        data: color.data.chunks_exact(640 * 3).step_by(2).flat_map(|row| row.chunks_exact(6).flat_map(|p| [p[0], p[1], p[2]])).collect(),
    };
    let mut f = tum_frame(1, 1_000);
    f.color = codec::encode_jpeg(&small, 90).expect("jpeg").into();
    s.send(ClientMsg::Frame(f)).await;
    assert_eq!(
        rejected(&s.result().await),
        (Code::InvalidArgument, "frame 1: colour image is 320x240, but the session's camera is 640x480".into())
    );

    // 2. Undecodable colour.
    let mut f = tum_frame(2, 2_000);
    f.color = b"\xFF\xD8\xFF this is no JPEG".to_vec().into();
    s.send(ClientMsg::Frame(f)).await;
    let (code, msg) = rejected(&s.result().await);
    assert_eq!(code, Code::InvalidArgument);
    assert!(msg.starts_with("frame 2: colour JPEG payload is not decodable"), "{msg}");

    // 3. Depth with the wrong bit depth: 8-bit samples in the zstd payload.
    let mut f = tum_frame(3, 3_000);
    let eight_bit: Vec<u8> = depth.data.iter().map(|&d| (d >> 8) as u8).collect();
    f.depth = zstd_compress(&eight_bit).into();
    s.send(ClientMsg::Frame(f)).await;
    assert_eq!(
        rejected(&s.result().await),
        (
            Code::InvalidArgument,
            "frame 3: depth payload holds 307200 bytes after decompression, expected 614400 (16-bit, 640x480) — looks like 8-bit depth"
                .into()
        )
    );

    // 4. Timestamps going backwards.
    s.send(ClientMsg::Frame(tum_frame(4, 500))).await;
    assert_eq!(
        rejected(&s.result().await),
        (Code::InvalidArgument, "capture timestamp went backwards: frame 4 at 500 ns is not after the previous frame's 3000 ns".into())
    );

    // The session survives: a good frame is processed, bit-exact.
    s.send(ClientMsg::Frame(tum_frame(5, 5_000))).await;
    let ok = s.result().await;
    assert_eq!(ok.status(), FrameStatus::Ok, "{ok:?}");
    assert_eq!(ok.depth_crc32, depth.crc32());

    let (_, detail) = server.get_json(&format!("/api/v1/sessions/{}", accepted.session_id)).await;
    assert_eq!(detail["counters"]["frames_rejected"], 4);
    assert_eq!(detail["counters"]["frames_processed"], 1);
    let metrics = server.get_text("/metrics").await;
    for line in [
        "stillmap_frames_rejected_total{reason=\"color\"} 2",
        "stillmap_frames_rejected_total{reason=\"depth\"} 1",
        "stillmap_frames_rejected_total{reason=\"order\"} 1",
    ] {
        assert!(metrics.contains(line), "{line} missing in\n{metrics}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_forged_frame_far_ahead_is_rejected_and_the_robots_frames_go_on() {
    let server = Server::start(&["--no-perception"]);
    let (mut s, accepted) = Stream::hello(&server, tum_hello("forged")).await;
    s.send(ClientMsg::Frame(tum_frame(1, 1_000))).await;
    assert_eq!(s.result().await.status(), FrameStatus::Ok);
    // Someone else's frame on the robot's stream: sequence 2^64 - 1.
    s.send(ClientMsg::Frame(tum_frame(u64::MAX, 2_000))).await;
    assert_eq!(
        rejected(&s.result().await),
        (
            Code::InvalidArgument,
            "frame sequence 18446744073709551615 jumps more than session.max_sequence_jump = 1000000 past the previous frame's 1: not taken as this robot's next frame".into()
        )
    );
    // The robot's next frames are taken, and a resuming robot is not told the forged one arrived.
    s.send(ClientMsg::Frame(tum_frame(2, 3_000))).await;
    assert_eq!(s.result().await.status(), FrameStatus::Ok);
    let (_, detail) = server.get_json(&format!("/api/v1/sessions/{}", accepted.session_id)).await;
    assert_eq!(detail["counters"]["last_received_sequence"], 2, "{detail}");
    assert_eq!(detail["counters"]["frames_processed"], 2);

    // One within the window (it could be the robot's, so it is taken): the robot's
    // own frames, now behind it, are rejected three times and then followed again,
    // and a resuming robot is told the last of its own.
    s.send(ClientMsg::Frame(tum_frame(2 + 999_999, 4_000))).await;
    assert_eq!(s.result().await.status(), FrameStatus::Ok);
    for k in 0..3 {
        s.send(ClientMsg::Frame(tum_frame(3 + k, 5_000 + k))).await;
        assert_eq!(rejected(&s.result().await).0, Code::InvalidArgument, "frame {}", 3 + k);
    }
    for k in 3..5 {
        s.send(ClientMsg::Frame(tum_frame(3 + k, 5_000 + k))).await;
        assert_eq!(s.result().await.status(), FrameStatus::Ok, "frame {}", 3 + k);
    }
    let (_, detail) = server.get_json(&format!("/api/v1/sessions/{}", accepted.session_id)).await;
    assert_eq!(detail["counters"]["last_received_sequence"], 7, "{detail}");
}

#[tokio::test(flavor = "multi_thread")]
async fn a_resume_needs_the_sessions_resume_secret() {
    let server = Server::start(&["--no-perception"]);
    let (s, accepted) = Stream::hello(&server, tum_hello("owner")).await;
    let (_, other) = Stream::hello(&server, tum_hello("owner")).await;
    assert_eq!(accepted.resume_secret.len(), 32, "128 random bits in hex");
    assert_ne!(accepted.resume_secret, other.resume_secret);
    drop(s);
    // The session id is public (GET /api/v1/sessions); it alone resumes nothing.
    let (_, sessions) = server.get_json("/api/v1/sessions").await;
    assert!(sessions.to_string().contains(&accepted.session_id) && !sessions.to_string().contains(&accepted.resume_secret));
    for secret in ["", "0123456789abcdef0123456789abcdef", other.resume_secret.as_str()] {
        let mut s = Stream::open(&server).await;
        s.send(ClientMsg::Hello(pb::Hello {
            resume_session_id: accepted.session_id.clone(),
            resume_secret: secret.into(),
            ..tum_hello("owner")
        }))
        .await;
        let status = s.next().await.expect_err("refused");
        assert_eq!(
            (status.code(), status.message().to_string()),
            (
                Code::Unauthenticated,
                format!("resuming session {} needs the resume secret its accept returned (Hello.resume_secret)", accepted.session_id)
            ),
            "secret {secret:?}"
        );
    }
    assert!(server.get_text("/metrics").await.contains("stillmap_frames_rejected_total{reason=\"unauthenticated\"} 3"));
    // With it, the session comes back.
    let hello =
        pb::Hello { resume_session_id: accepted.session_id.clone(), resume_secret: accepted.resume_secret.clone(), ..tum_hello("owner") };
    let (_, again) = Stream::hello(&server, hello).await;
    assert!(again.resumed);
    assert_eq!((again.session_id, again.resume_secret), (accepted.session_id, accepted.resume_secret));
}

#[tokio::test(flavor = "multi_thread")]
async fn a_hello_declaring_a_huge_camera_is_resource_exhausted() {
    let server = Server::start(&["--no-perception"]);
    let mut hello = tum_hello("huge");
    if let Some(c) = hello.camera.as_mut() {
        (c.width, c.height) = (8192, 8192);
    }
    let mut s = Stream::open(&server).await;
    s.send(ClientMsg::Hello(hello)).await;
    let status = s.next().await.expect_err("refused");
    assert_eq!(
        (status.code(), status.message()),
        (Code::ResourceExhausted, "camera of 8192x8192 = 67108864 pixels is over session.max_camera_pixels = 2097152")
    );
    assert!(server.get_text("/metrics").await.contains("stillmap_frames_rejected_total{reason=\"too_large\"} 1"));
    let (_, sessions) = server.get_json("/api/v1/sessions").await;
    assert_eq!(sessions["sessions"].as_array().map(Vec::len), Some(0), "no session was opened");
}

fn zstd_compress(bytes: &[u8]) -> Vec<u8> {
    zstd::bulk::compress(bytes, codec::DEPTH_ZSTD_LEVEL).expect("zstd")
}

#[tokio::test(flavor = "multi_thread")]
async fn oversized_message_is_resource_exhausted_and_the_session_can_resume() {
    let server = Server::start(&["--max-message-bytes", "200000"]);
    // An oversized hello gets the same answer as an oversized frame.
    let mut s = Stream::open(&server).await;
    s.send(ClientMsg::Hello(pb::Hello { client_version: "x".repeat(300_000), ..tum_hello("big") })).await;
    let status = s.next().await.expect_err("status");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().starts_with("message too large: ") && status.message().contains("200000"), "{}", status.message());
    let (mut s, accepted) = Stream::hello(&server, tum_hello("big")).await;
    s.send(ClientMsg::Frame(tum_frame(0, 10))).await;
    assert_eq!(s.result().await.status(), FrameStatus::Ok);
    let mut big = tum_frame(1, 20);
    big.color = vec![0u8; 300_000].into();
    s.send(ClientMsg::Frame(big)).await;
    let status = s.next().await.expect_err("status");
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert!(status.message().contains("200000"), "{}", status.message());

    // The session survives: resume it and go on after the last frame it received.
    let hello =
        pb::Hello { resume_session_id: accepted.session_id.clone(), resume_secret: accepted.resume_secret.clone(), ..tum_hello("big") };
    let (mut s2, again) = Stream::hello(&server, hello).await;
    assert!(again.resumed);
    assert_eq!(again.session_id, accepted.session_id);
    assert_eq!(again.last_received_sequence, Some(0));
    s2.send(ClientMsg::Frame(tum_frame(2, 30))).await;
    assert_eq!(s2.result().await.status(), FrameStatus::Ok);
    let metrics = server.get_text("/metrics").await;
    assert!(metrics.contains("stillmap_frames_rejected_total{reason=\"oversized\"} 2"), "the hello and the frame: {metrics}");
    // And the server survived everything.
    assert_eq!(server.get_json("/healthz").await.0, 200);
}

#[tokio::test(flavor = "multi_thread")]
async fn unknown_session_in_queries_is_not_found() {
    let server = Server::start(&[]);
    let mut q = QueryClient::connect(server.grpc_url()).await.expect("connect");
    let r = pb::SessionRef { session_id: "nope".into() };
    let status = q.get_latest_pose(r.clone()).await.expect_err("not found");
    assert_eq!((status.code(), status.message()), (Code::NotFound, "unknown session \"nope\""));
    let status = q.subscribe_poses(r).await.expect_err("not found");
    assert_eq!(status.code(), Code::NotFound);
    let status = q.get_trajectory(pb::TrajectoryRequest { session_id: "nope".into(), ..Default::default() }).await.expect_err("not found");
    assert_eq!(status.code(), Code::NotFound);
    let (code, body) = server.get_json("/api/v1/sessions/nope").await;
    assert_eq!((code, body), (404, serde_json::json!({ "error": "unknown session \"nope\"" })));
}

#[tokio::test(flavor = "multi_thread")]
async fn queries_answer_for_a_live_session() {
    let server = Server::start(&[]);
    let (mut s, accepted) = Stream::hello(&server, tum_hello("q")).await;
    s.send(ClientMsg::Frame(tum_frame(0, 10))).await;
    assert_eq!(s.result().await.status(), FrameStatus::Ok);
    let mut q = QueryClient::connect(server.grpc_url()).await.expect("connect");
    let list = q.list_sessions(pb::ListSessionsRequest::default()).await.expect("list").into_inner();
    assert_eq!(list.sessions.len(), 1);
    assert_eq!(list.sessions[0].frames_processed, 1);
    assert!(list.sessions[0].connected);
    assert_eq!(list.next_page_token, "", "one page");

    // The lists come in pages; a bad size or token is named.
    let (_s2, second) = Stream::hello(&server, tum_hello("q2")).await;
    let page = q.list_sessions(pb::ListSessionsRequest { page_size: 1, ..Default::default() }).await.expect("page").into_inner();
    let token = format!("{}:{}", list.sessions[0].started_unix_ns, accepted.session_id);
    assert_eq!((page.sessions.len(), page.next_page_token.as_str()), (1, token.as_str()));
    let rest = q.list_sessions(pb::ListSessionsRequest { page_size: 1, page_token: token.clone() }).await.expect("page").into_inner();
    assert_eq!(rest.sessions.iter().map(|s| s.session_id.as_str()).collect::<Vec<_>>(), [second.session_id.as_str()]);
    assert_eq!(rest.next_page_token, "");
    for (request, message) in [
        (
            pb::ListSessionsRequest { page_size: 5001, ..Default::default() },
            "limit must be within 1..=5000 sessions (page with page_token), got 5001",
        ),
        (
            pb::ListSessionsRequest { page_token: "nope".into(), ..Default::default() },
            "page_token \"nope\" is not one a sessions list gave (<started_unix_ns>:<session_id>)",
        ),
    ] {
        let status = q.list_sessions(request).await.expect_err("refused");
        assert_eq!((status.code(), status.message()), (Code::InvalidArgument, message));
    }
    let (status, page) = server.get_json("/api/v1/sessions?limit=1").await;
    assert_eq!((status, page["next_page_token"].as_str()), (200, Some(token.as_str())), "{page}");
    let (_, rest) = server.get_json(&format!("/api/v1/sessions?limit=1&page_token={token}")).await;
    assert_eq!(rest["sessions"][0]["session_id"].as_str(), Some(second.session_id.as_str()), "{rest}");
    assert!(rest.get("next_page_token").is_none(), "{rest}");
    for (query, message) in [
        ("limit=0", "limit must be within 1..=5000 sessions (page with page_token), got 0"),
        ("page_token=12", "page_token \"12\" is not one a sessions list gave (<started_unix_ns>:<session_id>)"),
    ] {
        let (status, body) = server.get_json(&format!("/api/v1/sessions?{query}")).await;
        assert_eq!((status, body["error"].as_str()), (400, Some(message)), "{query}");
    }
    let latest = q.get_latest_pose(pb::SessionRef { session_id: accepted.session_id.clone() }).await.expect("pose").into_inner();
    // The first real frame starts the map: it defines the world frame.
    assert_eq!(latest.tracking_state(), pb::TrackingState::Tracking);
    let pose = latest.pose.expect("pose").world_from_camera.expect("world_from_camera");
    assert_eq!(pose, pb::Pose::from_parts([0.0; 3], [0.0, 0.0, 0.0, 1.0]));
    let trajectory = q
        .get_trajectory(pb::TrajectoryRequest { session_id: accepted.session_id.clone(), ..Default::default() })
        .await
        .expect("trajectory")
        .into_inner();
    assert_eq!(trajectory.poses.iter().map(|p| p.sequence).collect::<Vec<_>>(), [0]);
}

/// With `auth.tokens` set, a hello must carry one of them, on gRPC and on Zenoh:
/// raw streams get UNAUTHENTICATED naming what is wrong, the real client exits 1
/// with that one line, and the holder of a token streams as usual.
#[tokio::test(flavor = "multi_thread")]
async fn a_hello_without_a_configured_token_is_unauthenticated() {
    let server = Server::start(&["--auth-token", "fleet-secret-1", "--auth-token", "fleet-secret-2", "--read-token", "viewer-1"]);
    for (token, message) in
        [("", "this server requires an auth token in the hello (stillmap-client --token)"), ("fleet-secret-3", "unknown auth token")]
    {
        let mut s = Stream::open(&server).await;
        s.send(ClientMsg::Hello(pb::Hello { auth_token: token.into(), ..tum_hello("r") })).await;
        let status = s.next().await.expect_err("status");
        assert_eq!((status.code(), status.message()), (Code::Unauthenticated, message), "token {token:?}");
    }
    // A resumed session needs the token too.
    let (_, accepted) = Stream::hello(&server, pb::Hello { auth_token: "fleet-secret-2".into(), ..tum_hello("r") }).await;
    let mut s = Stream::open(&server).await;
    s.send(ClientMsg::Hello(pb::Hello { resume_session_id: accepted.session_id.clone(), ..tum_hello("r") })).await;
    assert_eq!(s.next().await.expect_err("status").code(), Code::Unauthenticated);

    let src = format!("tum:{}", stillmap_e2e::tum_dir().display());
    for transport in [&["--server", &server.grpc_url()][..], &["--transport", "zenoh", "--zenoh-connect", &server.zenoh][..]] {
        let mut args = vec!["--source", src.as_str(), "--max-frames", "5", "--rate", "max", "--token", "wrong"];
        args.extend_from_slice(transport);
        let (out, _) = stillmap_e2e::run_client(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{transport:?}: {stderr}");
        assert!(stderr.contains("unknown auth token"), "{transport:?}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "one line: {stderr}");

        let mut args = vec!["--source", src.as_str(), "--max-frames", "5", "--rate", "max", "--token", "fleet-secret-1"];
        args.extend_from_slice(transport);
        let (out, summary) = stillmap_e2e::run_client(&args);
        assert!(out.status.success(), "{transport:?}: {}", String::from_utf8_lossy(&out.stderr));
        assert_eq!(summary.expect("summary")["frames_acknowledged"], 5);
    }
    let metrics = server.get_text("/metrics").await;
    assert!(metrics.contains("reason=\"unauthenticated\"} 5"), "{metrics}");
}

/// The scope matrix (issue 21): a robot token streams only as its robots, a read
/// token cannot stream, a robot token cannot query, queries need `read` on HTTP
/// (header or `?access_token=`) and gRPC, `/healthz` stays open, and SIGHUP reloads
/// the token file (a broken one keeps the tokens in force).
#[tokio::test(flavor = "multi_thread")]
async fn tokens_carry_scopes_and_sighup_reloads_the_token_file() {
    let file = stillmap_e2e::tempfile_path("tokens.txt");
    std::fs::write(&file, "# robots of the warehouse\nwh-token robot:warehouse-*\nviewer-token read\n").expect("token file");
    let server =
        Server::start(&["--no-zenoh", "--no-perception", "--token-file", file.to_str().expect("utf-8"), "--admin-token", "root-token"]);
    let http = reqwest::Client::new();
    let status = |path: &'static str, header: Option<&'static str>| {
        let mut r = http.get(format!("http://{}{path}", server.http));
        if let Some(t) = header {
            r = r.bearer_auth(t);
        }
        async move {
            let r = r.send().await.expect("GET");
            let code = r.status().as_u16();
            (
                code,
                if code >= 400 {
                    r.json::<serde_json::Value>().await.expect("JSON error")["error"].as_str().unwrap_or_default().to_string()
                } else {
                    String::new()
                },
            )
        }
    };
    assert_eq!(
        status("/api/v1/sessions", None).await,
        (401, "this needs a token with the read scope: Authorization: Bearer <token>".into())
    );
    assert_eq!(status("/api/v1/sessions", Some("wh-token")).await, (403, "this token lacks the read scope".into()));
    assert_eq!(status("/api/v1/sessions", Some("guess")).await, (401, "unknown token".into()));
    assert_eq!(status("/api/v1/sessions", Some("viewer-token")).await.0, 200);
    assert_eq!(status("/api/v1/sessions?access_token=viewer-token", None).await.0, 200);
    assert_eq!(status("/api/v1/events?access_token=wh-token", None).await.0, 403);
    assert_eq!(status("/metrics", None).await.0, 401);
    assert_eq!(status("/healthz", None).await.0, 200);
    // The API's OpenAPI document is open too: it holds no data.
    let doc: serde_json::Value =
        http.get(format!("http://{}/api/v1/openapi.json", server.http)).send().await.expect("GET").json().await.expect("JSON");
    assert_eq!(doc["openapi"], "3.1.0");
    assert!(doc["paths"]["/api/v1/sessions/{id}/pose"]["get"]["responses"]["200"].is_object(), "{doc}");

    // Ingest: a robot token streams only as its robots; a read token not at all.
    let hello = |robot: &str, token: &str| pb::Hello { auth_token: token.into(), ..tum_hello(robot) };
    let (_, accepted) = Stream::hello(&server, hello("warehouse-3", "wh-token")).await;
    for (robot, token) in [("lab-1", "wh-token"), ("warehouse-3", "viewer-token")] {
        let mut s = Stream::open(&server).await;
        s.send(ClientMsg::Hello(hello(robot, token))).await;
        let e = s.next().await.expect_err("refused");
        assert_eq!(e.code(), Code::PermissionDenied, "{robot} with {token}: {e:?}");
    }
    // gRPC queries: the authorization metadata.
    let mut q = QueryClient::connect(server.grpc_url()).await.expect("connect");
    let list = |token: Option<&str>| {
        let mut request = tonic::Request::new(pb::ListSessionsRequest::default());
        if let Some(t) = token {
            request.metadata_mut().insert("authorization", format!("Bearer {t}").parse().expect("metadata"));
        }
        request
    };
    assert_eq!(q.list_sessions(list(None)).await.expect_err("no token").code(), Code::Unauthenticated);
    assert_eq!(q.list_sessions(list(Some("wh-token"))).await.expect_err("robot token").code(), Code::PermissionDenied);
    let sessions = q.list_sessions(list(Some("viewer-token"))).await.expect("read token").into_inner().sessions;
    assert_eq!(sessions.iter().map(|s| s.session_id.as_str()).collect::<Vec<_>>(), [accepted.session_id.as_str()]);

    // SIGHUP: the file's new tokens replace the old ones.
    std::fs::write(&file, "viewer-2 read\n").expect("token file");
    let hup = || assert!(std::process::Command::new("kill").args(["-HUP", &server.pid().to_string()]).status().expect("kill").success());
    hup();
    stillmap_e2e::eventually(Duration::from_secs(10), "the token file is reloaded", async || {
        status("/api/v1/sessions", Some("viewer-token")).await.0 == 401
    })
    .await;
    assert_eq!(status("/api/v1/sessions", Some("viewer-2")).await.0, 200);
    assert_eq!(status("/api/v1/sessions", Some("root-token")).await.0, 200, "the config's admin token stays (admin implies read)");
    // A broken file keeps the tokens in force.
    std::fs::write(&file, "viewer-3 reed\n").expect("token file");
    hup();
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(status("/api/v1/sessions", Some("viewer-2")).await.0, 200);
    assert_eq!(status("/api/v1/sessions", Some("viewer-3")).await.0, 401);
    let _ = std::fs::remove_file(&file);
}

/// Slow and greedy clients (issue 21): a connection that sends no request head, or
/// dribbles one, is closed after `http.header_timeout_s`; connections beyond
/// `http.max_connections` are closed on accept; HTTP requests and hellos beyond
/// their per-client rate get 429 / RESOURCE_EXHAUSTED naming the limit.
#[tokio::test(flavor = "multi_thread")]
async fn slow_and_greedy_clients_are_cut_off_by_name() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let config = stillmap_e2e::tempfile_path("greedy.toml");
    std::fs::write(&config, "[http]\nheader_timeout_s = 1.0\nmax_connections = 4\n[limits]\nhttp_requests_per_minute = 60\nhttp_burst = 5\nhellos_per_minute = 60\nhello_burst = 3\n").expect("config");
    let server = Server::start(&["--no-zenoh", "--no-perception", "--config", config.to_str().expect("utf-8")]);
    // Closed by the server: a read returns end of stream (or a reset) within `within`.
    async fn closed_within(stream: &mut tokio::net::TcpStream, within: Duration) -> bool {
        let mut buf = [0u8; 256];
        let deadline = tokio::time::Instant::now() + within;
        loop {
            match tokio::time::timeout_at(deadline, stream.read(&mut buf)).await {
                Err(_) => return false,
                Ok(Ok(0) | Err(_)) => return true,
                Ok(Ok(_)) => {} // a 408 or 400 answer before the close
            }
        }
    }
    let started = std::time::Instant::now();
    let mut silent = tokio::net::TcpStream::connect(&server.http).await.expect("connect");
    let mut dribbling = tokio::net::TcpStream::connect(&server.http).await.expect("connect");
    dribbling.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n").await.expect("write");
    let mut others = Vec::new();
    for _ in 0..2 {
        others.push(tokio::net::TcpStream::connect(&server.http).await.expect("connect"));
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut fifth = tokio::net::TcpStream::connect(&server.http).await.expect("connect");
    assert!(closed_within(&mut fifth, Duration::from_millis(500)).await, "beyond http.max_connections: closed on accept");
    assert!(closed_within(&mut silent, Duration::from_secs(5)).await, "no request head in 1 s");
    assert!(closed_within(&mut dribbling, Duration::from_secs(5)).await, "half a request head in 1 s");
    let waited = started.elapsed();
    assert!(waited >= Duration::from_millis(900), "closed after the timeout, not before: {waited:?}");
    drop(others);
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert!(server.get_text("/metrics").await.contains("reason=\"http_connections\"} 1"));

    // HTTP: a burst of 5 (the /metrics read above was one), then 429 naming the limit.
    let http = reqwest::Client::new();
    let mut answers = Vec::new();
    for _ in 0..5 {
        answers.push(http.get(format!("http://{}/api/v1/sessions", server.http)).send().await.expect("GET"));
    }
    let codes: Vec<u16> = answers.iter().map(|r| r.status().as_u16()).collect();
    assert_eq!(codes, [200, 200, 200, 200, 429]);
    let limited = answers.pop().expect("the 429");
    assert_eq!(limited.headers().get("retry-after").map(|v| v.as_bytes()), Some(&b"1"[..]));
    let body: serde_json::Value = limited.json().await.expect("JSON");
    assert_eq!(body["error"], "too many requests from 127.0.0.1: limits.http_requests_per_minute = 60, limits.http_burst = 5");
    let healthz = http.get(format!("http://{}/healthz", server.http)).send().await.expect("GET");
    assert_eq!(healthz.status(), 200, "/healthz is not limited");

    // Hellos: a burst of 3 streams from this address, then RESOURCE_EXHAUSTED.
    for _ in 0..3 {
        let _ = Stream::hello(&server, tum_hello("greedy")).await;
    }
    let mut client = IngestClient::connect(server.grpc_url()).await.expect("connect");
    let (_tx, rx) = mpsc::channel::<pb::ClientMessage>(1);
    let refused = client.stream(ReceiverStream::new(rx)).await.expect_err("rate limited");
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert_eq!(refused.message(), "too many hellos from 127.0.0.1: limits.hellos_per_minute = 60, limits.hello_burst = 3");
    let _ = std::fs::remove_file(&config);
}

/// A rolling-shutter readout or an exposure-time offset the server cannot use is
/// refused by name: in a raw hello (INVALID_ARGUMENT) and on the client's command
/// line (exit 1, one line); ones it can use reach the session and its poses' times.
#[tokio::test(flavor = "multi_thread")]
async fn camera_timing_is_checked_and_reaches_the_session() {
    let server = Server::start(&[]);
    for (readout_s, offset_s, message) in [
        (0.2, 0.0, "bad hello: rolling_shutter_readout_s must be within 0..=0.1 s, got 0.2"),
        (0.05, 0.0, "bad hello: rolling_shutter_readout_s 0.05 s is longer than one frame at the nominal 30 Hz"),
        (0.025, -0.5, "bad hello: exposure_time_offset_s must be within -0.1..=0.1 s, got -0.5"),
    ] {
        let mut hello = tum_hello("r");
        if let Some(camera) = hello.camera.as_mut() {
            camera.rolling_shutter_readout_s = readout_s;
            camera.exposure_time_offset_s = offset_s;
        }
        let mut s = Stream::open(&server).await;
        s.send(ClientMsg::Hello(hello)).await;
        let status = s.next().await.expect_err("status");
        assert_eq!((status.code(), status.message()), (Code::InvalidArgument, message));
    }

    let src = format!("tum:{}", stillmap_e2e::tum_dir().display());
    let (out, _) = stillmap_e2e::run_client(&["--source", &src, "--server", &server.grpc_url(), "--rolling-shutter-ms", "500"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert_eq!(stderr.trim(), "stillmap-client: --rolling-shutter-ms 500 is outside 0..=100");
    let (out, _) = stillmap_e2e::run_client(&["--source", &src, "--server", &server.grpc_url(), "--exposure-offset-ms", "-150"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert_eq!(stderr.trim(), "stillmap-client: --exposure-offset-ms -150 is outside -100..=100");

    let args = [
        "--source",
        &src,
        "--server",
        &server.grpc_url(),
        "--max-frames",
        "3",
        "--rate",
        "max",
        "--rolling-shutter-ms",
        "0",
        "--exposure-offset-ms",
        "-4",
    ];
    let (out, summary) = stillmap_e2e::run_client(&args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let id = summary.expect("summary")["session_id"].as_str().expect("session id").to_string();
    let (_, session) = server.get_json(&format!("/api/v1/sessions/{id}")).await;
    assert_eq!(session["camera"]["rolling_shutter_readout_s"], 0.0, "the flag overrides the source's 25 ms");
    assert_eq!(session["camera"]["exposure_time_offset_s"], -0.004, "and this one its -12.5 ms");
    let (_, trajectory) = server.get_json(&format!("/api/v1/sessions/{id}/trajectory")).await;
    let poses = trajectory["poses"].as_array().expect("poses");
    assert!(!poses.is_empty(), "{trajectory}");
    for p in poses {
        let capture_ns = p["capture_time_ns"].as_u64().expect("capture time");
        assert_eq!(p["pose_time_ns"].as_u64(), Some(capture_ns - 4_000_000), "{p}");
    }
    assert!(trajectory.get("next_start_ns").is_none(), "everything in one answer: {trajectory}");

    // Paged: at most `limit` poses an answer, and where the next starts.
    let captured: Vec<u64> = poses.iter().filter_map(|p| p["capture_time_ns"].as_u64()).collect();
    assert!(captured.len() >= 2, "{trajectory}");
    let path = format!("/api/v1/sessions/{id}/trajectory");
    let (status, first) = server.get_json(&format!("{path}?limit=1")).await;
    assert_eq!(status, 200);
    assert_eq!(first["poses"].as_array().map(|p| p.len()), Some(1));
    assert_eq!(first["next_start_ns"].as_u64(), Some(captured[1]));
    let (_, rest) = server.get_json(&format!("{path}?start_ns={}", captured[1])).await;
    let rest: Vec<u64> = rest["poses"].as_array().expect("poses").iter().filter_map(|p| p["capture_time_ns"].as_u64()).collect();
    assert_eq!(rest, captured[1..]);
    let text = server.get_text(&format!("{path}?format=tum&limit=1")).await;
    assert!(text.ends_with(&format!("# more poses follow: ask again with start_ns={}\n", captured[1])), "{text}");
    for (query, message) in [
        ("limit=0", "limit must be within 1..=200000 poses (page with start_ns), got 0"),
        ("limit=200001", "limit must be within 1..=200000 poses (page with start_ns), got 200001"),
        ("start_ns=5&end_ns=4", "start_ns 5 is after end_ns 4"),
    ] {
        let (status, body) = server.get_json(&format!("{path}?{query}")).await;
        assert_eq!((status, body["error"].as_str()), (400, Some(message)), "{query}");
    }
    let mut q = QueryClient::connect(server.grpc_url()).await.expect("connect");
    let page = q
        .get_trajectory(pb::TrajectoryRequest { session_id: id.clone(), limit: 1, ..Default::default() })
        .await
        .expect("a page")
        .into_inner();
    assert_eq!((page.poses.len(), page.next_start_ns), (1, captured[1]));
    let status = q
        .get_trajectory(pb::TrajectoryRequest { session_id: id.clone(), limit: 200_001, ..Default::default() })
        .await
        .expect_err("too many");
    assert_eq!(status.code(), Code::InvalidArgument);
}

/// Rates and durations out of range are one-line errors before anything starts
/// (beyond them the client's clock arithmetic would overflow and panic).
#[test]
fn out_of_range_rates_and_durations_are_named() {
    let src = format!("tum:{}", stillmap_e2e::tum_dir().display());
    let run = |flag: &str, value: &str| {
        let (out, _) = stillmap_e2e::run_client(&["--source", &src, "--server", "http://127.0.0.1:9", flag, value]);
        (out.status.code(), String::from_utf8_lossy(&out.stderr).trim().to_string())
    };
    let (code, stderr) = run("--result-timeout", "1e19");
    assert_eq!(code, Some(1), "{stderr}");
    assert_eq!(stderr, "stillmap-client: --result-timeout 10000000000000000000 is not a positive number of seconds up to 2592000");
    let (code, stderr) = run("--timeout", "1e19");
    assert_eq!(code, Some(1), "{stderr}");
    assert_eq!(stderr, "stillmap-client: --timeout 10000000000000000000 is not a positive number of seconds up to 2592000");
    let (code, stderr) = run("--timeout", "0");
    assert_eq!(code, Some(1), "{stderr}");
    assert_eq!(stderr, "stillmap-client: --timeout 0 is not a positive number of seconds up to 2592000");
    let (code, stderr) = run("--rate", "1e-20");
    assert_eq!(code, Some(2), "clap's usage error: {stderr}");
    assert!(stderr.contains("rate \"1e-20\" is not realtime, max or a number of Hz from 0.001 to 1000000"), "{stderr}");
}

/// Tokens never show in `--print-config`; an empty one is a named start-up error.
#[test]
fn auth_tokens_are_redacted_and_an_empty_one_is_refused() {
    let server = || std::process::Command::new(stillmap_e2e::bin("stillmap-server"));
    let out = server().args(["--print-config", "--auth-token", "s3cret-token"]).output().expect("run server");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("tokens = [\"<redacted>\"]") && !stdout.contains("s3cret"), "{stdout}");
    let out = server().args(["--print-config", "--auth-token", ""]).output().expect("run server");
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(String::from_utf8_lossy(&out.stderr).trim(), "stillmap-server: invalid configuration: auth.tokens[0] is empty");
}

#[tokio::test(flavor = "multi_thread")]
async fn frames_over_the_cpu_budget_end_the_stream_naming_the_limit() {
    // A budget no real frame fits: every frame is over it.
    let config = stillmap_e2e::tempfile_path("cpu-budget.toml");
    std::fs::write(&config, "[limits]\nframe_cpu_ms = 0.001\nframe_cpu_strikes = 2\n").expect("write config");
    let server = Server::start(&["--no-perception", "--config", config.to_str().expect("utf-8")]);
    let (mut s, _) = Stream::hello(&server, tum_hello("heavy")).await;
    // The first strike is answered as usual.
    s.send(ClientMsg::Frame(tum_frame(0, 10))).await;
    assert_eq!(s.result().await.status(), FrameStatus::Ok);
    // The second is answered, then the stream ends naming the limit.
    s.send(ClientMsg::Frame(tum_frame(1, 20))).await;
    assert_eq!(s.result().await.sequence, 1);
    let status = s.next().await.expect_err("the stream ends");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(
        status.message().starts_with("2 frames in a row took more than limits.frame_cpu_ms = 0.001 ms of CPU each (frame 1: "),
        "{}",
        status.message()
    );
    let metrics = server.get_text("/metrics").await;
    assert!(metrics.contains("stillmap_frame_cpu_over_budget_total 2"), "{metrics}");
    assert!(metrics.contains("stillmap_sessions_ended_total{limit=\"frame_cpu_ms\"} 1"), "{metrics}");
    // Another robot still opens a session (the server is fine; only that stream ended).
    let (mut other, _) = Stream::hello(&server, tum_hello("next")).await;
    other.send(ClientMsg::Frame(tum_frame(0, 10))).await;
    assert_eq!(other.result().await.status(), FrameStatus::Ok);
    let _ = std::fs::remove_file(&config);
}
