//! Storage shared by several servers (issue 22): a real server with
//! `--replica-url` copies every commit of its store to a real PostgreSQL server
//! this test started (a fresh cluster on a free port): the session's description,
//! every pose, every keyframe record and the map's blocks. And a server whose
//! PostgreSQL cannot be reached serves its robots all the same and stops promptly.

use std::time::{Duration, Instant};

use prost::Message as _;
use stillmap_e2e::{Postgres, Server, eventually, free_port, run_client, tum_dir, tum_hello};
use stillmap_proto::pb::{
    self, client_message::Msg as ClientMsg, ingest_client::IngestClient, query_client::QueryClient, server_message::Msg,
};

/// A metric's value in the Prometheus text.
fn metric(text: &str, name: &str) -> u64 {
    text.lines()
        .find_map(|l| l.strip_prefix(name).and_then(|v| v.strip_prefix(' ')))
        .and_then(|v| v.trim().parse::<f64>().ok())
        .map_or_else(|| panic!("{name} missing from /metrics"), |v| v as u64)
}

#[tokio::test(flavor = "multi_thread")]
async fn every_commit_is_copied_to_postgres() {
    let pg = Postgres::start();
    let mut server = Server::start(&["--no-perception", "--replica-url", &pg.url()]);
    let tum = format!("tum:{}", tum_dir().display());
    let (out, _) = run_client(&["--source", &tum, "--server", &server.grpc_url(), "--robot-id", "replicated", "--rate", "max"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (_, list) = server.get_json("/api/v1/sessions").await;
    let id = list["sessions"][0]["session_id"].as_str().expect("a session").to_string();
    let mut q = QueryClient::connect(server.grpc_url()).await.expect("connect");
    let served = q.get_trajectory(pb::TrajectoryRequest { session_id: id.clone(), ..Default::default() }).await.expect("trajectory");
    let served = served.into_inner().poses;
    let (_, map) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    let keyframes = map["keyframes"].as_u64().expect("keyframes");
    assert!(served.len() == 150 && keyframes > 0, "{} poses, {keyframes} keyframes", served.len());

    // A graceful stop commits what came after the last keyframe, and copies it.
    let stopping = Instant::now();
    let metrics_before_stop = server.get_text("/metrics").await;
    server.terminate();
    eprintln!("server stopped in {:.0} ms", stopping.elapsed().as_secs_f64() * 1e3);

    let sessions = pg.query("SELECT id, server_id, meta::text, camera FROM stillmap_sessions");
    assert_eq!(sessions.len(), 1);
    assert_eq!(sessions[0].get::<_, String>(0), id);
    assert!(!sessions[0].get::<_, String>(1).is_empty(), "the server's id");
    let meta: serde_json::Value = serde_json::from_str(&sessions[0].get::<_, String>(2)).expect("meta JSON");
    assert_eq!(meta["robot_id"], "replicated", "{meta}");
    assert_eq!(meta["keyframes"].as_u64(), Some(keyframes), "{meta}");
    let camera = pb::CameraInfo::decode(sessions[0].get::<_, Option<Vec<u8>>>(3).expect("camera").as_slice()).expect("CameraInfo");
    assert_eq!((camera.width, camera.height), (640, 480));

    // Every pose, bit for bit what the server served.
    let poses: Vec<pb::PoseStamped> = pg
        .query("SELECT pose FROM stillmap_poses ORDER BY sequence")
        .iter()
        .map(|r| pb::PoseStamped::decode(r.get::<_, Vec<u8>>(0).as_slice()).expect("PoseStamped"))
        .collect();
    assert_eq!(poses, served);
    let stored_keyframes = pg.query("SELECT count(*) FROM stillmap_keyframes")[0].get::<_, i64>(0);
    assert_eq!(stored_keyframes as u64, keyframes);
    let blocks = pg.query("SELECT block FROM stillmap_blocks");
    assert!(!blocks.is_empty(), "map blocks");
    for b in &blocks {
        let bytes: Vec<u8> = b.get(0);
        assert!(zstd::decode_all(bytes.as_slice()).is_ok_and(|raw| !raw.is_empty()), "a block decodes");
    }
    let commits = metric(&metrics_before_stop, "stillmap_replica_commits_total");
    let copied = metric(&metrics_before_stop, "stillmap_replica_bytes_total");
    let micros = metric(&metrics_before_stop, "stillmap_replica_write_microseconds_total");
    assert_eq!(metric(&metrics_before_stop, "stillmap_replica_dropped_total"), 0);
    assert!(commits > 0);
    eprintln!(
        "replica: {keyframes} keyframes, {} blocks, {commits} commits before the stop: {:.0} KB and {:.1} ms per commit (loopback PostgreSQL)",
        blocks.len(),
        copied as f64 / commits as f64 / 1e3,
        micros as f64 / commits as f64 / 1e3,
    );
}

/// A commit still queued on a server after another server has taken its session
/// over (`Replica::claim`: here the same UPDATE, naming another writer) is fenced
/// off: the row keeps naming the other server, none of the commit's poses are
/// written, and the server counts it; its robot is served all the same.
#[tokio::test(flavor = "multi_thread")]
async fn commits_after_another_server_took_the_session_over_are_fenced_off() {
    let pg = Postgres::start();
    let mut server = Server::start(&["--no-perception", "--replica-url", &pg.url()]);
    let (tum, grpc) = (format!("tum:{}", tum_dir().display()), server.grpc_url());
    let robot = std::thread::Builder::new()
        .name("robot".into())
        .spawn(move || run_client(&["--source", &tum, "--server", &grpc, "--robot-id", "fenced", "--rate", "15"]))
        .expect("a thread for the robot");
    let poses = || pg.try_query("SELECT count(*) FROM stillmap_poses").map_or(0, |rows| rows[0].get::<_, i64>(0));
    eventually(Duration::from_secs(20), "the session's first commits copied", async || poses() > 0).await;
    pg.execute("UPDATE stillmap_sessions SET server_id = 'server-x'");
    let at_claim = poses();
    let (out, summary) = robot.join().expect("the robot's thread");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(summary.expect("summary")["poses_returned"], 150, "served all the same");
    let metrics = server.get_text("/metrics").await;
    server.terminate();
    let writer = pg.query("SELECT server_id FROM stillmap_sessions");
    assert_eq!(writer.len(), 1);
    assert_eq!(writer[0].get::<_, String>(0), "server-x", "the other server stays the writer");
    assert_eq!(poses(), at_claim, "nothing of the fenced commits was written ({at_claim} poses before them)");
    let fenced = metric(&metrics, "stillmap_replica_fenced_total");
    assert!(fenced > 0, "fenced commits counted");
    eprintln!("{at_claim} of 150 poses copied before the other server's claim; {fenced} commits fenced off after it");
}

/// PostgreSQL down: the robot is served as ever (the server's own store has
/// everything), nothing is counted as copied, and the server stops promptly.
#[tokio::test(flavor = "multi_thread")]
async fn a_server_whose_postgres_is_down_serves_all_the_same() {
    let nowhere = format!("postgresql://stillmap@127.0.0.1:{}/postgres", free_port());
    let mut server = Server::start(&["--no-perception", "--replica-url", &nowhere]);
    let tum = format!("tum:{}", tum_dir().display());
    let (out, summary) = run_client(&[
        "--source",
        &tum,
        "--server",
        &server.grpc_url(),
        "--robot-id",
        "unreplicated",
        "--rate",
        "max",
        "--max-frames",
        "60",
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary = summary.expect("summary");
    assert_eq!(summary["poses_returned"], 60, "{summary}");
    let (status, health) = server.get_json("/healthz").await;
    assert_eq!(status, 200, "the server's own store is healthy: {health}");
    assert_eq!(metric(&server.get_text("/metrics").await, "stillmap_replica_commits_total"), 0);
    let stopping = Instant::now();
    server.terminate();
    assert!(stopping.elapsed() < Duration::from_secs(10), "stopped in {:?}", stopping.elapsed());
}

/// PostgreSQL answers but refuses every write (a role that may read only): the
/// robot is served as ever, nothing is copied, and the server still stops promptly
/// (the copy backs off between attempts and gives up at shutdown).
#[tokio::test(flavor = "multi_thread")]
async fn a_server_whose_postgres_refuses_writes_serves_and_stops() {
    let pg = Postgres::start();
    pg.execute(stillmap_server::replica::SCHEMA);
    pg.execute(
        "CREATE ROLE reader LOGIN; GRANT CREATE, USAGE ON SCHEMA public TO reader; GRANT SELECT ON ALL TABLES IN SCHEMA public TO reader;",
    );
    let reader = pg.url().replace("stillmap@", "reader@");
    let mut server = Server::start(&["--no-perception", "--replica-url", &reader]);
    let tum = format!("tum:{}", tum_dir().display());
    let (out, summary) =
        run_client(&["--source", &tum, "--server", &server.grpc_url(), "--robot-id", "refused", "--rate", "max", "--max-frames", "60"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(summary.expect("summary")["poses_returned"], 60);
    assert_eq!(metric(&server.get_text("/metrics").await, "stillmap_replica_commits_total"), 0);
    let stopping = Instant::now();
    server.terminate();
    assert!(stopping.elapsed() < Duration::from_secs(12), "stopped in {:?}", stopping.elapsed());
    let rows = pg.query("SELECT count(*) FROM stillmap_sessions")[0].get::<_, i64>(0);
    assert_eq!(rows, 0, "nothing was written");
}

/// A hello on a gRPC stream of its own: the server's accept, or its refusal.
async fn hello(server: &Server, hello: pb::Hello) -> Result<pb::SessionAccepted, tonic::Status> {
    let mut client = IngestClient::connect(server.grpc_url()).await.expect("connect");
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(pb::ClientMessage { msg: Some(ClientMsg::Hello(hello)), fleet: String::new() }).await.expect("queue the hello");
    let mut stream = client.stream(tokio_stream::wrappers::ReceiverStream::new(rx)).await?.into_inner();
    match stream.message().await? {
        Some(pb::ServerMessage { msg: Some(Msg::Accepted(a)) }) => Ok(a),
        other => panic!("not an accept: {other:?}"),
    }
}

/// Another server sharing the storage resumes a session only for its own robot
/// with its resume secret (the storage keeps the secret's SHA-256, checked before
/// anything else is read), and says the session was restored.
#[tokio::test(flavor = "multi_thread")]
async fn another_server_resumes_a_session_only_with_its_secret() {
    let pg = Postgres::start();
    let first = Server::start(&["--no-perception", "--replica-url", &pg.url()]);
    let accepted = hello(&first, tum_hello("owner")).await.expect("accepted");
    let id = accepted.session_id.clone();
    // (The server creates its tables on its first write: until then the query fails.)
    eventually(Duration::from_secs(10), "the session copied", async || {
        pg.try_query(&format!("SELECT count(*) FROM stillmap_sessions WHERE id = '{id}' AND resume_secret_sha256 IS NOT NULL"))
            .is_ok_and(|rows| rows[0].get::<_, i64>(0) == 1)
    })
    .await;
    let held =
        pg.query(&format!("SELECT encode(resume_secret_sha256, 'hex') FROM stillmap_sessions WHERE id = '{id}'"))[0].get::<_, String>(0);
    assert_eq!(held.len(), 64, "a SHA-256");
    assert!(!held.contains(&accepted.resume_secret), "the secret itself is not stored");
    let second = Server::start(&["--no-perception", "--replica-url", &pg.url()]);
    let resume = |robot: &str, secret: &str| pb::Hello { resume_session_id: id.clone(), resume_secret: secret.into(), ..tum_hello(robot) };
    let wrong = hello(&second, resume("owner", "0123456789abcdef0123456789abcdef")).await.expect_err("wrong secret");
    assert_eq!(
        (wrong.code(), wrong.message().to_string()),
        (tonic::Code::Unauthenticated, format!("resuming session {id} needs the resume secret its accept returned (Hello.resume_secret)"))
    );
    let thief = hello(&second, resume("thief", &accepted.resume_secret)).await.expect_err("another robot");
    assert_eq!(
        (thief.code(), thief.message().to_string()),
        (tonic::Code::Unauthenticated, format!("session {id} belongs to robot \"owner\", not \"thief\""))
    );
    let again = hello(&second, resume("owner", &accepted.resume_secret)).await.expect("resumed");
    assert!(again.resumed && again.restored, "{again:?}");
    assert_eq!((again.session_id, again.resume_secret), (id.clone(), accepted.resume_secret.clone()));
    let (status, detail) = second.get_json(&format!("/api/v1/sessions/{id}")).await;
    assert_eq!((status, detail["robot_id"].as_str()), (200, Some("owner")), "{detail}");
}

/// Two servers racing to resume one session (both read the same last writer): the
/// take-over is one PostgreSQL statement, so exactly one of them wins; a session
/// PostgreSQL does not hold is taken by nobody.
#[test]
fn only_one_server_takes_a_session_over() {
    use stillmap_server::replica::{Replica, ReplicaCounters};
    let pg = Postgres::start();
    pg.execute(stillmap_server::replica::SCHEMA);
    pg.execute("INSERT INTO stillmap_sessions (id, server_id, meta) VALUES ('robot-1', 'dead', '{}')");
    let start = |id: &str| {
        let r = Replica::start(&pg.url(), 4, ReplicaCounters::default()).expect("replica");
        r.name_server(id);
        r
    };
    let (a, b) = (start("a"), start("b"));
    assert!(a.claim("robot-1", "dead").expect("claim"), "a takes it over from the dead server");
    assert!(!b.claim("robot-1", "dead").expect("claim"), "b read the same writer: a was first");
    let writer: String = pg.query("SELECT server_id FROM stillmap_sessions WHERE id = 'robot-1'")[0].get(0);
    assert_eq!(writer, "a");
    assert!(!a.claim("nobody-1", "dead").expect("claim"), "not in PostgreSQL");
    a.close();
    b.close();
}
