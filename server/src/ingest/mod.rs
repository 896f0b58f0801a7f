//! The ingest shells, one per transport: they decode messages, open or resume a
//! session on a hello and push frames into its queue; results come back through
//! the sink the session holds. What both transports share is here.

pub mod grpc;
#[cfg(feature = "zenoh")]
pub mod zenoh;

use prost::Message;
use std::sync::Arc;
use std::time::Duration;

use stillmap_proto::pb::{self, client_message::Msg as ClientMsg, server_message::Msg};
use tonic::Status;

use crate::metrics::Metrics;
use crate::queue::QueueError;
use crate::session::{BadHello, Opened, Registry};

/// Status for a frame that arrived before any hello.
pub fn frame_before_hello(sequence: u64) -> Status {
    Status::failed_precondition(format!("frame {sequence} arrived before the hello: the first message of a session must be a hello"))
}

/// Status for a queue that can no longer take frames.
pub fn queue_status(e: QueueError) -> Status {
    match e {
        QueueError::Overloaded(_) => Status::resource_exhausted(e.to_string()),
        QueueError::Closed => Status::unavailable(
            "session closed (the server is shutting down, or the session left memory after session.idle_evict_s): send a hello for a new one",
        ),
    }
}

/// The status a refused hello is answered with; a full server is counted.
pub fn refusal(e: &BadHello, metrics: &Metrics) -> Status {
    match e {
        BadHello::Full { .. } => metrics.rejected("server_full"),
        BadHello::TooLarge(_) => metrics.rejected("too_large"),
        BadHello::Limit { .. } => metrics.rejected("server_full"),
        BadHello::Unauthenticated(_) => metrics.rejected("unauthenticated"),
        _ => {}
    }
    e.status()
}

/// The first message on a connection: accepted (or resumed) session.
pub fn accepted_message(opened: &Opened, max_message_bytes: usize) -> pb::ServerMessage {
    pb::ServerMessage {
        msg: Some(Msg::Accepted(pb::SessionAccepted {
            session_id: opened.session.id.clone(),
            resumed: opened.resumed,
            last_received_sequence: if opened.resumed { opened.session.last_received_sequence() } else { None },
            max_message_bytes: max_message_bytes as u64,
            server_version: concat!("stillmap-server ", env!("CARGO_PKG_VERSION")).into(),
            resume_secret: opened.session.resume_secret().to_string(),
            restored: opened.restored,
        })),
    }
}

/// A message a robot published on its Zenoh frames key, once checked.
#[derive(Debug)]
pub enum ZenohMessage {
    Hello(pb::Hello),
    Frame(pb::Frame),
}

/// A Zenoh message the shell answers with an error: the metrics label it is
/// counted under (none: not counted) and the status it gets.
#[derive(Debug)]
pub struct ZenohRejection {
    pub label: Option<&'static str>,
    pub status: Status,
}

/// Checks and decodes what `robot` published on its frames key: the size
/// before decoding, then the message, then that a hello names the robot of its
/// key. Free of Zenoh itself, so the fuzz target `zenoh_message` drives it.
pub fn parse_zenoh_message(robot: &str, payload: &[u8], max_message_bytes: usize) -> Result<ZenohMessage, ZenohRejection> {
    let reject = |label, status| Err(ZenohRejection { label, status });
    if payload.len() > max_message_bytes {
        let message = format!("message of {} bytes exceeds the limit of {max_message_bytes} bytes", payload.len());
        return reject(Some("oversized"), Status::resource_exhausted(message));
    }
    let message = match pb::ClientMessage::decode(payload) {
        Ok(m) => m,
        Err(e) => return reject(Some("malformed"), Status::invalid_argument(format!("undecodable message: {e}"))),
    };
    if !message.fleet.is_empty()
        && let Err(problem) = stillmap_proto::validate_fleet(&message.fleet)
    {
        return reject(Some("malformed"), Status::invalid_argument(format!("message placed by a bad fleet: {problem}")));
    }
    match message.msg {
        Some(ClientMsg::Hello(hello)) if hello.robot_id != robot => {
            let message = format!("hello for robot {:?} published on the key of robot {robot:?}", hello.robot_id);
            reject(None, Status::invalid_argument(message))
        }
        // The message's fleet placed it (an older client sends none: placed by its id).
        Some(ClientMsg::Hello(hello)) if !message.fleet.is_empty() && hello.fleet != message.fleet => {
            let message = format!("hello for fleet {:?} in a message placed by fleet {:?}", hello.fleet, message.fleet);
            reject(None, Status::invalid_argument(message))
        }
        Some(ClientMsg::Hello(hello)) => Ok(ZenohMessage::Hello(hello)),
        Some(ClientMsg::Frame(frame)) => Ok(ZenohMessage::Frame(frame)),
        None => reject(Some("malformed"), Status::invalid_argument("empty client message")),
    }
}

/// After a handover, when the stored copy here is checked against the shared
/// storage again (the new owner resumes the session within a second or two when
/// its robot streams on; a later check finds one that took longer).
const HANDED_OVER_CHECKS: [Duration; 3] = [Duration::from_secs(2), Duration::from_secs(5), Duration::from_secs(15)];

/// Hands session `id` over off the runtime ([`Registry::hand_over`]); then has the
/// stored copy here checked again, so that it leaves this server's listing once the
/// new owner holds it.
pub(crate) fn hand_over(registry: Arc<Registry>, id: String) {
    tokio::spawn(async move {
        let r = registry.clone();
        if !matches!(tokio::task::spawn_blocking(move || r.hand_over(&id)).await, Ok(true)) {
            return;
        }
        let mut waited = Duration::ZERO;
        for at in HANDED_OVER_CHECKS {
            tokio::time::sleep(at - waited).await;
            waited = at;
            registry.handed_over().notify_one();
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Code;

    fn encoded(msg: Option<ClientMsg>) -> Vec<u8> {
        pb::ClientMessage { msg, fleet: String::new() }.encode_to_vec()
    }

    fn rejection(r: Result<ZenohMessage, ZenohRejection>) -> (Option<&'static str>, Code, String) {
        let e = r.expect_err("rejected");
        (e.label, e.status.code(), e.status.message().to_string())
    }

    #[test]
    fn zenoh_messages_are_checked_before_and_after_decoding() {
        let hello = |robot: &str| Some(ClientMsg::Hello(pb::Hello { robot_id: robot.into(), ..Default::default() }));
        assert!(matches!(parse_zenoh_message("r1", &encoded(hello("r1")), 1000), Ok(ZenohMessage::Hello(h)) if h.robot_id == "r1"));
        let frame = Some(ClientMsg::Frame(pb::Frame { sequence: 7, ..Default::default() }));
        assert!(matches!(parse_zenoh_message("r1", &encoded(frame), 1000), Ok(ZenohMessage::Frame(f)) if f.sequence == 7));
        assert_eq!(
            rejection(parse_zenoh_message("r1", &encoded(hello("r2")), 1000)),
            (None, Code::InvalidArgument, "hello for robot \"r2\" published on the key of robot \"r1\"".into())
        );
        assert_eq!(
            rejection(parse_zenoh_message("r1", &[0; 11], 10)),
            (Some("oversized"), Code::ResourceExhausted, "message of 11 bytes exceeds the limit of 10 bytes".into())
        );
        let (label, code, message) = rejection(parse_zenoh_message("r1", &[0xff, 0xff], 1000));
        assert_eq!((label, code), (Some("malformed"), Code::InvalidArgument));
        assert!(message.starts_with("undecodable message: "), "{message}");
        assert_eq!(
            rejection(parse_zenoh_message("r1", &encoded(None), 1000)),
            (Some("malformed"), Code::InvalidArgument, "empty client message".into())
        );
    }

    /// A hello must name the fleet its message was placed by; one from a client
    /// that places nothing (no fleet on the message) is taken as it is.
    #[test]
    fn a_hello_names_the_fleet_it_was_placed_by() {
        let message = |hello_fleet: &str, placed_by: &str| {
            let hello = pb::Hello { robot_id: "r1".into(), fleet: hello_fleet.into(), ..Default::default() };
            pb::ClientMessage { msg: Some(ClientMsg::Hello(hello)), fleet: placed_by.into() }.encode_to_vec()
        };
        assert!(matches!(parse_zenoh_message("r1", &message("a", "a"), 1000), Ok(ZenohMessage::Hello(h)) if h.fleet == "a"));
        assert!(matches!(parse_zenoh_message("r1", &message("a", ""), 1000), Ok(ZenohMessage::Hello(h)) if h.fleet == "a"));
        assert_eq!(
            rejection(parse_zenoh_message("r1", &message("a", "b"), 1000)),
            (None, Code::InvalidArgument, "hello for fleet \"a\" in a message placed by fleet \"b\"".into())
        );
        assert_eq!(
            rejection(parse_zenoh_message("r1", &message("", "b"), 1000)),
            (None, Code::InvalidArgument, "hello for fleet \"\" in a message placed by fleet \"b\"".into())
        );
        assert_eq!(
            rejection(parse_zenoh_message("r1", &message("a b", "a b"), 1000)),
            (
                Some("malformed"),
                Code::InvalidArgument,
                "message placed by a bad fleet: fleet \"a b\" contains ' '; allowed are A-Z a-z 0-9 _ -".into()
            )
        );
    }
}
