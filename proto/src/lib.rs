//! The stillmap wire contract.
//!
//! - [`pb`]: the protobuf / gRPC types generated from `proto/stillmap.proto`
//!   (package `stillmap.v1`).
//! - [`codec`]: encoders and decoders for the colour and depth payloads a
//!   [`pb::Frame`] carries, shared by the robot client and the server so both
//!   ends agree byte for byte.
//! - [`keys`]: Zenoh key expressions of the contract.

pub mod codec;

/// Generated protobuf and gRPC code for package `stillmap.v1`.
pub mod pb {
    tonic::include_proto!("stillmap.v1");

    /// The encoded `FileDescriptorSet` of `stillmap.proto` (gRPC server reflection).
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("stillmap_descriptor");
}

/// Zenoh key expressions used by the contract.
pub mod keys {
    /// Key on which robot `robot_id` publishes `ClientMessage`s (hello, then frames).
    pub fn frames(robot_id: &str) -> String {
        format!("stillmap/{robot_id}/frames")
    }
    /// Key on which the server publishes `ServerMessage`s for robot `robot_id`.
    pub fn results(robot_id: &str) -> String {
        format!("stillmap/{robot_id}/results")
    }
    /// Wildcard the server subscribes to for every robot's frames.
    pub const ALL_FRAMES: &str = "stillmap/*/frames";

    /// Liveliness token of the server `server_id` while it runs. Outside `stillmap/`,
    /// where robots publish: no robot id can reach these keys (and a router's ACL
    /// keeps robots on `stillmap/<robot>/**`).
    pub fn server(server_id: &str) -> String {
        format!("stillmap-cluster/servers/{server_id}")
    }
    /// Every server's liveliness token.
    pub const ALL_SERVERS: &str = "stillmap-cluster/servers/*";
    /// Queryable on which the server `server_id` answers with its status (JSON: who
    /// it is, where it listens, its load).
    pub fn server_status(server_id: &str) -> String {
        format!("stillmap-cluster/servers/{server_id}/status")
    }
    /// Every server's status queryable.
    pub const ALL_SERVER_STATUS: &str = "stillmap-cluster/servers/*/status";
    /// Queryable on which the server `server_id` answers HTTP GETs another server
    /// forwards (a session it holds, asked of a server that does not).
    pub fn server_http(server_id: &str) -> String {
        format!("stillmap-cluster/servers/{server_id}/http")
    }
    /// Queryable on which the server `server_id` answers unary gRPC queries another
    /// server forwards (the request message as the payload, the method and the
    /// caller's authorization as a JSON attachment).
    pub fn server_grpc(server_id: &str) -> String {
        format!("stillmap-cluster/servers/{server_id}/grpc")
    }

    /// Where the server `server_id` publishes every pose of the sessions it holds
    /// (a `FleetPose` each), while another server subscribes.
    pub fn server_poses(server_id: &str) -> String {
        format!("stillmap-cluster/servers/{server_id}/poses")
    }
    /// Where the server `server_id` publishes its dashboard sessions list (JSON, every
    /// 500 ms) while another server subscribes.
    pub fn server_sessions(server_id: &str) -> String {
        format!("stillmap-cluster/servers/{server_id}/sessions")
    }
    /// Every server's published live data (poses and sessions lists).
    pub const ALL_SERVER_LIVE: &str = "stillmap-cluster/servers/*/*";

    /// The server id inside a server's liveliness key.
    pub fn server_of_key(key: &str) -> Option<&str> {
        let id = key.strip_prefix("stillmap-cluster/servers/")?;
        (!id.is_empty() && !id.contains('/')).then_some(id)
    }

    /// The robot id inside a frames key, if the key has the contract's shape.
    pub fn robot_of_frames_key(key: &str) -> Option<&str> {
        let rest = key.strip_prefix("stillmap/")?;
        let robot = rest.strip_suffix("/frames")?;
        (!robot.is_empty() && !robot.contains('/')).then_some(robot)
    }
}

/// Longest rolling-shutter readout the contract accepts (`CameraInfo.rolling_shutter_readout_s`),
/// seconds: a 10 Hz camera reading its whole frame.
pub const MAX_ROLLING_SHUTTER_READOUT_S: f64 = 0.1;

/// Largest exposure-time offset the contract accepts either way
/// (`CameraInfo.exposure_time_offset_s`), seconds.
pub const MAX_EXPOSURE_TIME_OFFSET_S: f64 = 0.1;

/// The time a frame's pose refers to: its timestamp plus the camera's exposure-time
/// offset (`FrameResult.pose_time_ns`), rounded to the nanosecond and saturating at
/// the clock's ends.
pub fn pose_time_ns(capture_time_ns: u64, exposure_time_offset_s: f64) -> u64 {
    let offset_ns = (exposure_time_offset_s * 1e9).round() as i64;
    capture_time_ns.saturating_add_signed(offset_ns)
}

/// Largest robot id the contract accepts.
pub const MAX_ROBOT_ID_LEN: usize = 64;

/// Checks a robot id: 1–64 characters of `[A-Za-z0-9_-]` (it becomes a Zenoh key segment).
pub fn validate_robot_id(robot_id: &str) -> Result<(), String> {
    validate_name("robot_id", robot_id)
}

/// What a robot on Zenoh is placed by ([`placement_owner`]): its fleet when its
/// messages name one (`ClientMessage.fleet`), so that every robot of a fleet is
/// served by one server and shares its fleet map; else its robot id. Fleet keys
/// are `fleet:<name>`: `:` is in no robot id, so a fleet never shares a key with a robot.
pub fn placement_key<'a>(robot_id: &'a str, fleet: &str) -> std::borrow::Cow<'a, str> {
    if fleet.is_empty() { robot_id.into() } else { format!("fleet:{fleet}").into() }
}

/// The `fleet` of an encoded `ClientMessage`, read without decoding the rest: the
/// hello or frame it carries is skipped (prost advances past unknown fields
/// without copying them), so a server can place every message it hears, its
/// own robots' or not, at the cost of reading a few bytes.
pub fn client_message_fleet(payload: &[u8]) -> Result<String, prost::DecodeError> {
    /// `ClientMessage` with only its `fleet` field.
    #[derive(Clone, PartialEq, prost::Message)]
    struct FleetOnly {
        #[prost(string, tag = "3")]
        fleet: String,
    }
    <FleetOnly as prost::Message>::decode(payload).map(|m| m.fleet)
}

/// Which of the live servers `servers` a robot belongs to, by its
/// [`placement_key`]: rendezvous (highest random weight) hashing, the weight of a
/// server SipHash-2-4 (fixed zero key: the same on every machine and release) of
/// `server_id`, a separator and the key.
/// Every server computes it alone from the set of live servers it sees: one owner
/// per key without any coordination, and when a server joins or leaves only the
/// robots whose owner it is (or becomes) move. Ties go to the smaller id. `None`
/// when `servers` is empty.
pub fn placement_owner<'a>(key: &str, servers: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    servers.into_iter().max_by(|a, b| {
        let weight = |s: &str| {
            use std::hash::Hasher as _;
            let mut h = siphasher::sip::SipHasher24::new();
            h.write(s.as_bytes());
            h.write(&[0xff]);
            h.write(key.as_bytes());
            h.finish()
        };
        weight(a).cmp(&weight(b)).then_with(|| b.cmp(a))
    })
}

/// A server id follows the robot id's rules (it is a key segment too).
pub fn validate_server_id(server_id: &str) -> Result<(), String> {
    validate_name("server_id", server_id)
}

/// A fleet name follows the robot id's rules (it is a key segment too).
pub fn validate_fleet(fleet: &str) -> Result<(), String> {
    validate_name("fleet", fleet)
}

fn validate_name(what: &str, name: &str) -> Result<(), String> {
    if name.is_empty() || name.len() > MAX_ROBOT_ID_LEN {
        return Err(format!("{what} must be 1-{MAX_ROBOT_ID_LEN} characters, got {}", name.len()));
    }
    if let Some(c) = name.chars().find(|c| !(c.is_ascii_alphanumeric() || *c == '_' || *c == '-')) {
        return Err(format!("{what} {name:?} contains {c:?}; allowed are A-Z a-z 0-9 _ -"));
    }
    Ok(())
}

impl pb::PoseStamped {
    /// The time the pose refers to: `pose_time_ns`, or `capture_time_ns` for a pose
    /// stored before that field existed.
    pub fn time_ns(&self) -> u64 {
        self.pose_time_ns.unwrap_or(self.capture_time_ns)
    }
}

impl pb::Pose {
    /// Builds a pose from a translation and a unit quaternion (x, y, z, w).
    pub fn from_parts(t: [f64; 3], q_xyzw: [f64; 4]) -> Self {
        Self {
            translation: Some(pb::Vector3 { x: t[0], y: t[1], z: t[2] }),
            rotation: Some(pb::Quaternion { x: q_xyzw[0], y: q_xyzw[1], z: q_xyzw[2], w: q_xyzw[3] }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One owner per robot; a server leaving moves only its own robots; the owner
    /// does not depend on the order the servers are listed in.
    #[test]
    fn placement_is_rendezvous_hashing() {
        let robots: Vec<String> = (0..200).map(|i| format!("robot-{i}")).collect();
        let three = ["a", "b", "c"];
        let owners: Vec<&str> = robots.iter().map(|r| placement_owner(r, three).expect("owner")).collect();
        for s in three {
            let n = owners.iter().filter(|o| **o == s).count();
            assert!((40..=95).contains(&n), "{s} owns {n} of 200");
        }
        for (r, owner) in robots.iter().zip(&owners) {
            assert_eq!(placement_owner(r, ["c", "a", "b"]), Some(*owner), "order");
            let without_b = placement_owner(r, ["a", "c"]).expect("owner");
            if *owner == "b" {
                assert_ne!(without_b, "b");
            } else {
                assert_eq!(without_b, *owner, "{r} moved though its server stayed");
            }
        }
        assert_eq!(placement_owner("r", std::iter::empty::<&str>()), None);
    }

    /// Robots of a named fleet share one owner; robots without a fleet are placed
    /// by their ids as before; a fleet's key is no robot's.
    #[test]
    fn a_named_fleet_is_placed_as_one() {
        let servers = ["a", "b", "c"];
        let fleet: Vec<&str> = (0..50)
            .map(|i| format!("robot-{i}"))
            .map(|r| placement_owner(&placement_key(&r, "warehouse"), servers).expect("owner"))
            .collect();
        assert!(fleet.iter().all(|o| *o == fleet[0]), "one fleet on {fleet:?}");
        assert_eq!(placement_key("robot-1", ""), "robot-1");
        assert_eq!(placement_key("robot-1", "warehouse"), "fleet:warehouse");
        assert!(validate_robot_id(&placement_key("robot-1", "warehouse")).is_err());
        // Unnamed robots still spread.
        let spread: std::collections::BTreeSet<&str> =
            (0..50).map(|i| format!("robot-{i}")).map(|r| placement_owner(&placement_key(&r, ""), servers).expect("owner")).collect();
        assert_eq!(spread.len(), 3);
    }

    /// The fleet is read from a message whatever it carries, and a message without
    /// one (an older client) reads as empty.
    #[test]
    fn the_fleet_is_read_without_decoding_the_frame() {
        use prost::Message as _;
        let frame = pb::Frame { sequence: 7, depth: vec![1u8; 100_000].into(), ..Default::default() };
        let with = pb::ClientMessage { msg: Some(pb::client_message::Msg::Frame(frame.clone())), fleet: "warehouse".into() };
        assert_eq!(client_message_fleet(&with.encode_to_vec()), Ok("warehouse".into()));
        let hello = pb::Hello { robot_id: "r".into(), fleet: "warehouse".into(), ..Default::default() };
        let without = pb::ClientMessage { msg: Some(pb::client_message::Msg::Hello(hello)), fleet: String::new() };
        assert_eq!(client_message_fleet(&without.encode_to_vec()), Ok(String::new()));
        assert!(client_message_fleet(&[0x1a, 0x05, b'a']).is_err(), "truncated");
    }

    #[test]
    fn frames_key_round_trip() {
        assert_eq!(keys::robot_of_frames_key(&keys::frames("r2-d2")), Some("r2-d2"));
        assert_eq!(keys::robot_of_frames_key("stillmap/a/b/frames"), None);
        assert_eq!(keys::robot_of_frames_key("stillmap//frames"), None);
        assert_eq!(keys::robot_of_frames_key("other/a/frames"), None);
    }

    #[test]
    fn robot_id_rules() {
        assert!(validate_robot_id("turtle_01-a").is_ok());
        assert_eq!(validate_robot_id("a/b").unwrap_err(), "robot_id \"a/b\" contains '/'; allowed are A-Z a-z 0-9 _ -");
        assert!(validate_robot_id("").unwrap_err().contains("1-64"));
        assert!(validate_robot_id(&"x".repeat(65)).is_err());
    }

    #[test]
    fn pose_time_adds_the_exposure_offset() {
        assert_eq!(pose_time_ns(1_305_031_229_528_748_000, -0.0125), 1_305_031_229_516_248_000);
        assert_eq!(pose_time_ns(1_000, 0.0), 1_000);
        assert_eq!(pose_time_ns(1_000, 2e-6), 3_000);
        assert_eq!(pose_time_ns(1_000, -0.05), 0, "saturates at the clock's start");
        assert_eq!(pose_time_ns(u64::MAX - 5, 0.05), u64::MAX, "and at its end");
    }

    #[test]
    fn a_stored_pose_without_its_time_refers_to_its_capture() {
        let p = pb::PoseStamped { capture_time_ns: 7, ..Default::default() };
        assert_eq!(p.time_ns(), 7);
        let p = pb::PoseStamped { capture_time_ns: 7, pose_time_ns: Some(0), ..Default::default() };
        assert_eq!(p.time_ns(), 0, "0 is a time, not a missing one");
    }
}
