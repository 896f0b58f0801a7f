//! The gRPC link against servers of the test's own: a session the server gives up
//! (ABORTED: a resumed session not found again) is followed by a new one, and the
//! frames not yet answered go to it; a robot given several servers asks them in
//! turn where it belongs (`Ingest.Place`) and streams there.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use stillmap_client::link::{GrpcOptions, LinkEvent, start_grpc};
use stillmap_proto::pb::client_message::Msg as ClientMsg;
use stillmap_proto::pb::ingest_server::{Ingest, IngestServer};
use stillmap_proto::pb::server_message::Msg;
use stillmap_proto::pb::{self};
use tokio_stream::StreamExt;
use tokio_stream::wrappers::{ReceiverStream, TcpListenerStream};
use tonic::{Request, Response, Status, Streaming};

/// Opens session `s<n>` for the n-th hello and answers every frame, except that
/// session `s1` is given up at frame 2 when `gives_up`. `Place` answers `placement`,
/// or UNIMPLEMENTED (a server of a version before it) when there is none.
#[derive(Default)]
struct Fake {
    gives_up: bool,
    placement: Option<pb::Placement>,
    places: Arc<Mutex<Vec<pb::Hello>>>,
    hellos: Arc<Mutex<Vec<pb::Hello>>>,
    /// (session, frame) for every frame answered.
    answered: Arc<Mutex<Vec<(String, u64)>>>,
}

#[tonic::async_trait]
impl Ingest for Fake {
    type StreamStream = ReceiverStream<Result<pb::ServerMessage, Status>>;

    async fn place(&self, request: Request<pb::Hello>) -> Result<Response<pb::Placement>, Status> {
        self.places.lock().expect("places").push(request.into_inner());
        self.placement.clone().map(Response::new).ok_or_else(|| Status::unimplemented("Place"))
    }

    async fn stream(&self, request: Request<Streaming<pb::ClientMessage>>) -> Result<Response<Self::StreamStream>, Status> {
        let mut inbound = request.into_inner();
        let (tx, rx) = tokio::sync::mpsc::channel(16);
        let (hellos, answered, gives_up) = (self.hellos.clone(), self.answered.clone(), self.gives_up);
        tokio::spawn(async move {
            let mut session = String::new();
            while let Some(Ok(message)) = inbound.next().await {
                let reply = match message.msg {
                    Some(ClientMsg::Hello(hello)) => {
                        let n = {
                            let mut hellos = hellos.lock().expect("hellos");
                            hellos.push(hello);
                            hellos.len()
                        };
                        session = format!("s{n}");
                        let accepted =
                            pb::SessionAccepted { session_id: session.clone(), max_message_bytes: 1 << 20, ..Default::default() };
                        Ok(pb::ServerMessage { msg: Some(Msg::Accepted(accepted)) })
                    }
                    Some(ClientMsg::Frame(frame)) if gives_up && session == "s1" && frame.sequence == 2 => {
                        let _ = tx.send(Err(Status::aborted(format!("session {session} was not found again: open a new session")))).await;
                        return;
                    }
                    Some(ClientMsg::Frame(frame)) => {
                        answered.lock().expect("answered").push((session.clone(), frame.sequence));
                        let result = pb::FrameResult { sequence: frame.sequence, ..Default::default() };
                        Ok(pb::ServerMessage { msg: Some(Msg::Result(result)) })
                    }
                    None => continue,
                };
                if tx.send(reply).await.is_err() {
                    return;
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

/// Serves `fake` on a port of its own; its address.
async fn serve(fake: Fake) -> std::net::SocketAddr {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let address = listener.local_addr().expect("address");
    tokio::spawn(
        tonic::transport::Server::builder().add_service(IngestServer::new(fake)).serve_with_incoming(TcpListenerStream::new(listener)),
    );
    address
}

fn options(servers: Vec<String>) -> GrpcOptions {
    GrpcOptions {
        servers,
        tls: None,
        keepalive: Duration::from_secs(10),
        connect_timeout: Duration::from_secs(5),
        initial_backoff: Duration::from_millis(10),
        max_backoff: Duration::from_millis(100),
        max_attempts: 3,
        result_timeout: Duration::from_secs(10),
    }
}

#[tokio::test]
async fn a_session_the_server_gives_up_is_followed_by_a_new_one() {
    let server = Fake { gives_up: true, ..Fake::default() };
    let (hellos, by_session) = (server.hellos.clone(), server.answered.clone());
    let address = serve(server).await;
    let options = options(vec![format!("http://{address}")]);
    let mut link = start_grpc(pb::Hello { robot_id: "r1".into(), ..Default::default() }, options);
    for sequence in 1..=4 {
        link.frames.send(pb::Frame { sequence, capture_time_ns: sequence * 1000, ..Default::default() }).await.expect("frame");
    }
    drop(link.frames);
    let mut seen = Vec::new();
    let mut answered = Vec::new();
    while let Some(event) = tokio::time::timeout(Duration::from_secs(20), link.events.recv()).await.expect("events in time") {
        match event {
            LinkEvent::Streaming(_) => {}
            LinkEvent::Accepted(a) => seen.push(format!("accepted {}", a.session_id)),
            LinkEvent::Reconnected(n) => seen.push(format!("reconnected {n}")),
            LinkEvent::Unanswered(lost) => seen.push(format!("unanswered {lost:?}")),
            LinkEvent::Result(r) => answered.push(r.sequence),
        }
    }
    link.task.await.expect("link task").expect("the link finishes");
    assert_eq!(seen, ["accepted s1", "reconnected 0", "accepted s2"]);
    answered.sort_unstable();
    assert_eq!(answered, [1, 2, 3, 4], "every frame answered once");
    let mut by_session = by_session.lock().expect("answered").clone();
    by_session.sort();
    let expected: Vec<(String, u64)> = [("s1", 1), ("s2", 2), ("s2", 3), ("s2", 4)].into_iter().map(|(s, q)| (s.to_string(), q)).collect();
    assert_eq!(by_session, expected, "frame 1 answered in the given-up session, the rest resent to the new one");
    let resumes: Vec<String> = hellos.lock().expect("hellos").iter().map(|h| h.resume_session_id.clone()).collect();
    assert_eq!(resumes, ["", ""], "the second hello opens a new session, it does not resume the given-up one");
}

/// Of two servers given, the first is down; the second places the robot on a third,
/// which the robot then streams to (the server asked never sees a hello).
#[tokio::test]
async fn a_robot_streams_where_the_server_it_asks_places_it() {
    let owner = Fake::default();
    let (owner_hellos, owner_answered) = (owner.hellos.clone(), owner.answered.clone());
    let owner_address = format!("http://{}", serve(owner).await);
    let owner_address_told = owner_address.clone();
    let asked = Fake { placement: Some(pb::Placement { server_id: "owner".into(), grpc_address: owner_address }), ..Fake::default() };
    let (asked_places, asked_hellos) = (asked.places.clone(), asked.hellos.clone());
    let asked_address = serve(asked).await;
    let down = {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
        listener.local_addr().expect("address")
    };
    let hello = pb::Hello { robot_id: "r1".into(), fleet: "warehouse".into(), ..Default::default() };
    let mut link = start_grpc(hello, options(vec![format!("http://{down}"), format!("http://{asked_address}")]));
    for sequence in 1..=3 {
        link.frames.send(pb::Frame { sequence, capture_time_ns: sequence * 1000, ..Default::default() }).await.expect("frame");
    }
    drop(link.frames);
    let (mut answered, mut streaming) = (Vec::new(), Vec::new());
    while let Some(event) = tokio::time::timeout(Duration::from_secs(20), link.events.recv()).await.expect("events in time") {
        match event {
            LinkEvent::Result(r) => answered.push(r.sequence),
            LinkEvent::Streaming(server) => streaming.push(server),
            _ => {}
        }
    }
    link.task.await.expect("link task").expect("the link finishes");
    assert_eq!(answered, [1, 2, 3]);
    assert_eq!(streaming, [owner_address_told], "the link says where it streams");
    let places: Vec<(String, String)> =
        asked_places.lock().expect("places").iter().map(|h| (h.robot_id.clone(), h.fleet.clone())).collect();
    assert_eq!(places, [("r1".to_string(), "warehouse".to_string())], "asked once, with the robot and its fleet");
    assert!(asked_hellos.lock().expect("hellos").is_empty(), "nothing streamed to the server asked");
    assert_eq!(owner_hellos.lock().expect("hellos").len(), 1);
    let on_owner: Vec<u64> = owner_answered.lock().expect("answered").iter().map(|(_, q)| *q).collect();
    assert_eq!(on_owner, [1, 2, 3], "every frame streamed to the owner");
}
