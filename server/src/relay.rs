//! Live data across servers on one Zenoh network: what a dashboard's event stream
//! and a gRPC pose subscriber need from sessions another server holds.
//!
//! Every server publishes, on its own keys, every pose of the sessions it holds
//! (`stillmap-cluster/servers/<id>/poses`, a `RelayedPose` each: the pose in the
//! session's world and, once the session is merged into its fleet, in the
//! fleet's frame) and its dashboard
//! sessions list every 500 ms (`…/<id>/sessions`, JSON), but only while some
//! other server subscribes (Zenoh's matching status): a server subscribes to the
//! others' keys only while it has a local consumer (a dashboard viewer, a
//! `SubscribePoses` of a session or a `SubscribeFleetPoses` of a fleet held
//! elsewhere). Puts drop under congestion,
//! and received poses go to a bounded broadcast whose laggards skip: a slow
//! viewer or server never holds a robot's frames. A server's own keys are never
//! read back; a list older than [`SESSIONS_STALE`], or of a server no longer
//! live, is left out.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use prost::Message;
use stillmap_proto::{keys, pb};
use tokio::sync::{broadcast, watch};

use crate::ServerError;
use crate::cluster::Membership;
use crate::lock;
use crate::session::{FleetPose, Registry};

/// How often the sessions list is published (the dashboard's snapshot interval).
const SESSIONS_EVERY: Duration = Duration::from_millis(500);
/// A server's list not renewed for this long is left out (it died, or stopped publishing).
pub const SESSIONS_STALE: Duration = Duration::from_secs(3);
/// Other servers' poses buffered for local consumers; a laggard skips poses.
const REMOTE_POSES_BUFFER: usize = 1024;
/// Sessions lists received and not yet parsed, at most.
const LISTS_QUEUE: usize = 64;
/// Largest message accepted from another server (a sessions list of thousands of sessions).
const MAX_RELAYED_BYTES: usize = 8 << 20;

/// This server's view of the other servers' live data.
pub struct Relay {
    own: String,
    membership: Arc<Membership>,
    /// Local consumers of the other servers' live data.
    interest: Arc<AtomicUsize>,
    poses: broadcast::Sender<FleetPose>,
    fleet_poses: broadcast::Sender<RemoteFleetPose>,
    sessions: std::sync::Mutex<HashMap<String, (Instant, Vec<serde_json::Value>)>>,
}

/// Counts one local consumer while it lives.
struct Interest(Arc<AtomicUsize>);

impl Drop for Interest {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

impl Relay {
    pub fn new(membership: Arc<Membership>) -> Arc<Self> {
        Arc::new(Self {
            own: membership.own().to_string(),
            membership,
            interest: Arc::default(),
            poses: broadcast::channel(REMOTE_POSES_BUFFER).0,
            fleet_poses: broadcast::channel(REMOTE_POSES_BUFFER).0,
            sessions: std::sync::Mutex::default(),
        })
    }

    /// A sessions list received from server `server`.
    fn received_sessions(&self, server: &str, payload: &[u8]) {
        let Ok(serde_json::Value::Array(mut sessions)) = serde_json::from_slice::<serde_json::Value>(payload) else {
            tracing::warn!(server, "a sessions list that is not a JSON array: ignored");
            return;
        };
        for s in &mut sessions {
            if let Some(o) = s.as_object_mut() {
                o.insert("server_id".into(), server.into());
            }
        }
        lock(&self.sessions).insert(server.to_string(), (Instant::now(), sessions));
    }

    /// A pose received from another server: to the session's followers, and to
    /// its fleet's when it was given in the fleet's frame.
    fn received_pose(&self, server: &str, payload: &[u8]) {
        let p = match pb::RelayedPose::decode(payload) {
            Ok(p) => p,
            Err(e) => {
                tracing::warn!(server, "a relayed pose that does not decode: {e}");
                return;
            }
        };
        if let Some(pose) = p.pose {
            let _ = self.poses.send((Arc::from(p.session_id.as_str()), pose));
        }
        if let Some(pose) = p.pose_in_fleet.filter(|_| !p.fleet.is_empty()) {
            let _ = self
                .fleet_poses
                .send((Arc::from(p.fleet.as_str()), pb::FleetPose { session_id: p.session_id, robot_id: p.robot_id, pose: Some(pose) }));
        }
    }
}

impl crate::api::RemoteLive for Relay {
    fn own_id(&self) -> &str {
        &self.own
    }

    fn watch(&self) -> Box<dyn Send + Sync> {
        self.interest.fetch_add(1, Ordering::SeqCst);
        Box::new(Interest(self.interest.clone()))
    }

    fn sessions(&self) -> Vec<serde_json::Value> {
        let live = self.membership.servers();
        let mut lists = lock(&self.sessions);
        lists.retain(|server, (at, _)| at.elapsed() < SESSIONS_STALE && live.contains(server));
        let mut servers: Vec<&String> = lists.keys().collect();
        servers.sort();
        servers.into_iter().flat_map(|s| lists[s].1.iter().cloned()).collect()
    }

    fn subscribe_poses(&self) -> broadcast::Receiver<FleetPose> {
        self.poses.subscribe()
    }

    fn subscribe_fleet_poses(&self) -> broadcast::Receiver<RemoteFleetPose> {
        self.fleet_poses.subscribe()
    }
}

pub use crate::api::RemoteFleetPose;

/// What this server relays of one of its sessions' poses: the session's robot and
/// fleet, and the pose in the fleet's frame when the session is merged into it.
fn relayed_pose(registry: &Registry, session_id: &Arc<str>, pose: pb::PoseStamped) -> pb::RelayedPose {
    let (robot_id, fleet) = registry.get(session_id).map(|s| (s.robot_id.clone(), s.fleet_name.clone())).unwrap_or_default();
    let pose_in_fleet = registry
        .fleets()
        .filter(|_| !fleet.is_empty())
        .and_then(|fleets| fleets.fleet_transform(&fleet, session_id))
        .map(|to_fleet| crate::convert::pose_in(&pose, &to_fleet.at(pose.capture_time_ns)));
    pb::RelayedPose { session_id: session_id.to_string(), robot_id, pose: Some(pose), fleet, pose_in_fleet }
}

/// What a received sample is, from its key: the publishing server and the kind.
fn relayed(key: &str, own: &str) -> Option<(String, bool)> {
    let rest = key.strip_prefix("stillmap-cluster/servers/")?;
    let (server, kind) = rest.split_once('/')?;
    if server == own || server.is_empty() {
        return None;
    }
    match kind {
        "poses" => Some((server.to_string(), true)),
        "sessions" => Some((server.to_string(), false)),
        _ => None,
    }
}

/// Publishes this server's live data while another server watches, and receives
/// the others' while this one has a local consumer; until shutdown.
pub async fn run(
    zenoh: zenoh::Session,
    relay: Arc<Relay>,
    registry: Arc<Registry>,
    mut shutdown: watch::Receiver<bool>,
) -> Result<(), ServerError> {
    let declare = |key: String| {
        let zenoh = zenoh.clone();
        async move {
            zenoh
                .declare_publisher(key.clone())
                .congestion_control(zenoh::qos::CongestionControl::Drop)
                // Matching counts the other servers' subscribers only (not this one's own).
                .allowed_destination(zenoh::sample::Locality::Remote)
                .await
                .map_err(|e| ServerError::Zenoh(format!("publisher {key}: {e}")))
        }
    };
    let poses_out = declare(keys::server_poses(&relay.own)).await?;
    let sessions_out = declare(keys::server_sessions(&relay.own)).await?;
    let mut local = registry.subscribe_fleet();
    let mut tick = tokio::time::interval(SESSIONS_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut poses_watched = false;
    let mut subscriber = None;
    // Sessions lists are parsed here, not on Zenoh's receive path (a full queue drops one).
    let (lists_tx, mut lists_rx) = tokio::sync::mpsc::channel::<(String, Vec<u8>)>(LISTS_QUEUE);
    let mut previous = HashMap::new();
    loop {
        tokio::select! {
            _ = shutdown.changed() => break,
            _ = tick.tick() => {
                poses_watched = poses_out.matching_status().await.is_ok_and(|m| m.matching());
                if sessions_out.matching_status().await.is_ok_and(|m| m.matching()) {
                    let r = registry.clone();
                    let Ok((list, seen, _)) = tokio::task::spawn_blocking(move || crate::api::dashboard::session_list(&r, previous)).await else { break };
                    previous = seen;
                    if let Ok(bytes) = serde_json::to_vec(&list)
                        && let Err(e) = sessions_out.put(bytes).await
                    {
                        tracing::warn!("sessions list not published to the other servers: {e}");
                    }
                }
                let wanted = relay.interest.load(Ordering::SeqCst) > 0;
                if wanted && subscriber.is_none() {
                    let (r, lists) = (relay.clone(), lists_tx.clone());
                    let declared = zenoh
                        .declare_subscriber(keys::ALL_SERVER_LIVE)
                        .callback(move |sample: zenoh::sample::Sample| {
                            let Some((server, is_pose)) = relayed(sample.key_expr().as_str(), &r.own) else { return };
                            let payload = sample.payload().to_bytes();
                            if payload.len() > MAX_RELAYED_BYTES {
                                tracing::warn!(server, bytes = payload.len(), "a relayed message too large: ignored");
                            } else if is_pose {
                                r.received_pose(&server, &payload);
                            } else {
                                let _ = lists.try_send((server, payload.into_owned()));
                            }
                        })
                        .await;
                    match declared {
                        Ok(s) => subscriber = Some(s),
                        Err(e) => tracing::warn!("cannot follow the other servers' live data: {e}"),
                    }
                } else if !wanted && subscriber.is_some() {
                    subscriber = None;
                    lock(&relay.sessions).clear();
                }
            }
            Some((server, payload)) = lists_rx.recv() => {
                // Only a live server's list is kept (a stale or unknown one is not).
                if relay.membership.servers().contains(&server) {
                    relay.received_sessions(&server, &payload);
                }
            }
            received = local.recv() => match received {
                Ok((id, pose)) => {
                    if poses_watched {
                        let message = relayed_pose(&registry, &id, pose);
                        if let Err(e) = poses_out.put(message.encode_to_vec()).await {
                            tracing::debug!("pose not published to the other servers: {e}");
                        }
                    }
                }
                Err(broadcast::error::RecvError::Lagged(_)) => {}
                Err(broadcast::error::RecvError::Closed) => break,
            },
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Only the other servers' poses and sessions lists are read, never this server's own.
    #[test]
    fn a_relayed_key_names_another_server_and_the_kind() {
        assert_eq!(relayed("stillmap-cluster/servers/b/poses", "a"), Some(("b".into(), true)));
        assert_eq!(relayed("stillmap-cluster/servers/b/sessions", "a"), Some(("b".into(), false)));
        assert_eq!(relayed("stillmap-cluster/servers/a/poses", "a"), None, "its own");
        assert_eq!(relayed("stillmap-cluster/servers/b/status", "a"), None);
        assert_eq!(relayed("stillmap/robot/poses", "a"), None);
        assert_eq!(keys::server_poses("b"), "stillmap-cluster/servers/b/poses");
        assert_eq!(keys::server_sessions("b"), "stillmap-cluster/servers/b/sessions");
    }

    /// A relayed pose reaches its session's followers, and its fleet's once it was
    /// given in the fleet's frame; an older server's `FleetPose` still reaches the
    /// session's.
    #[test]
    fn a_relayed_pose_reaches_its_session_and_its_fleet() {
        let relay = Relay::new(Membership::new("a"));
        let (mut poses, mut fleet) = (relay.poses.subscribe(), relay.fleet_poses.subscribe());
        let in_world = pb::PoseStamped { sequence: 3, capture_time_ns: 7, ..Default::default() };
        let at = |x: f64| pb::Pose { translation: Some(pb::Vector3 { x, y: 0.0, z: 0.0 }), rotation: None };
        let in_fleet = pb::PoseStamped { world_from_camera: Some(at(2.0)), ..in_world };
        let relayed = |fleet: &str, pose_in_fleet: Option<pb::PoseStamped>| {
            pb::RelayedPose { session_id: "s1".into(), robot_id: "r1".into(), pose: Some(in_world), fleet: fleet.into(), pose_in_fleet }
                .encode_to_vec()
        };
        relay.received_pose("b", &relayed("warehouse", Some(in_fleet)));
        assert_eq!(poses.try_recv().ok(), Some((Arc::from("s1"), in_world)));
        let expected = pb::FleetPose { session_id: "s1".into(), robot_id: "r1".into(), pose: Some(in_fleet) };
        assert_eq!(fleet.try_recv().ok(), Some((Arc::from("warehouse"), expected)));
        // Not merged into its fleet yet, or no fleet named: the session's followers only.
        relay.received_pose("b", &relayed("warehouse", None));
        relay.received_pose("b", &relayed("", Some(in_fleet)));
        let older = pb::FleetPose { session_id: "s1".into(), robot_id: String::new(), pose: Some(in_world) };
        relay.received_pose("b", &older.encode_to_vec());
        relay.received_pose("b", b"\xff\xff not a pose");
        for _ in 0..3 {
            assert_eq!(poses.try_recv().ok(), Some((Arc::from("s1"), in_world)));
        }
        assert!(poses.try_recv().is_err() && fleet.try_recv().is_err(), "nothing more, and nothing for the fleet");
    }

    /// A list is tagged with its server, and left out once stale or its server gone.
    #[test]
    fn other_servers_sessions_are_tagged_and_age_out() {
        use crate::api::RemoteLive;
        let membership = Membership::new("a");
        membership.seen("b", true);
        let relay = Relay::new(membership.clone());
        relay.received_sessions("b", br#"[{"session_id":"s1"},{"session_id":"s2"}]"#);
        relay.received_sessions("c", br#"[{"session_id":"s3"}]"#);
        relay.received_sessions("b", b"not json");
        let listed = relay.sessions();
        assert_eq!(listed.len(), 2, "c is not live: {listed:?}");
        assert!(listed.iter().all(|s| s["server_id"] == "b"));
        lock(&relay.sessions).insert("b".into(), (Instant::now() - SESSIONS_STALE, vec![serde_json::json!({})]));
        assert!(relay.sessions().is_empty(), "stale");
    }
}
