//! The gRPC link against a server of the test's own: a session the server gives up
//! (ABORTED: a resumed session not found again) is followed by a new one, and the
//! frames not yet answered go to it.

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
/// session `s1` is given up at frame 2.
#[derive(Default)]
struct GivesUpOnce {
    hellos: Arc<Mutex<Vec<pb::Hello>>>,
    /// (session, frame) for every frame answered.
    answered: Arc<Mutex<Vec<(String, u64)>>>,
}

#[tonic::async_trait]
impl Ingest for GivesUpOnce {
    type StreamStream = ReceiverStream<Result<pb::ServerMessage, Status>>;

    async fn stream(&self, request: Request<Streaming<pb::ClientMessage>>) -> Result<Response<Self::StreamStream>, Status> {
        let mut inbound = request.into_inner();
        let (tx, rx) = tokio::sync::mpsc::channel(16);
        let (hellos, answered) = (self.hellos.clone(), self.answered.clone());
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
                    Some(ClientMsg::Frame(frame)) if session == "s1" && frame.sequence == 2 => {
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

#[tokio::test]
async fn a_session_the_server_gives_up_is_followed_by_a_new_one() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let address = listener.local_addr().expect("address");
    let server = GivesUpOnce::default();
    let (hellos, by_session) = (server.hellos.clone(), server.answered.clone());
    tokio::spawn(
        tonic::transport::Server::builder().add_service(IngestServer::new(server)).serve_with_incoming(TcpListenerStream::new(listener)),
    );

    let options = GrpcOptions {
        endpoint: format!("http://{address}"),
        tls: None,
        keepalive: Duration::from_secs(10),
        connect_timeout: Duration::from_secs(5),
        initial_backoff: Duration::from_millis(10),
        max_backoff: Duration::from_millis(100),
        max_attempts: 3,
        result_timeout: Duration::from_secs(10),
    };
    let mut link = start_grpc(pb::Hello { robot_id: "r1".into(), ..Default::default() }, options);
    for sequence in 1..=4 {
        link.frames.send(pb::Frame { sequence, capture_time_ns: sequence * 1000, ..Default::default() }).await.expect("frame");
    }
    drop(link.frames);
    let mut seen = Vec::new();
    let mut answered = Vec::new();
    while let Some(event) = tokio::time::timeout(Duration::from_secs(20), link.events.recv()).await.expect("events in time") {
        match event {
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
