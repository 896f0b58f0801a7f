//! What anyone can publish on a Zenoh frames key: the key (up to the first NUL)
//! and the payload after it, through the server's key parsing and message
//! checks, and the placement's read of the fleet (done on every message a server
//! hears). An accepted hello always names the robot of its key, and the fleet its
//! message was placed by when it names one.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stillmap_proto::keys;
use stillmap_server::ingest::{ZenohMessage, parse_zenoh_message};

fuzz_target!(|data: &[u8]| {
    let split = data.iter().position(|b| *b == 0).unwrap_or(data.len());
    let Ok(key) = std::str::from_utf8(&data[..split]) else { return };
    let payload = data.get(split + 1..).unwrap_or_default();
    let Some(robot) = keys::robot_of_frames_key(key) else { return };
    let placed_by = stillmap_proto::client_message_fleet(payload).unwrap_or_default();
    match parse_zenoh_message(robot, payload, 1 << 16) {
        Ok(ZenohMessage::Hello(hello)) => {
            assert_eq!(hello.robot_id, robot);
            assert!(placed_by.is_empty() || hello.fleet == placed_by);
        }
        Ok(ZenohMessage::Frame(_)) => assert!(payload.len() <= 1 << 16),
        Err(rejection) => assert!(!rejection.status.message().is_empty()),
    }
});
