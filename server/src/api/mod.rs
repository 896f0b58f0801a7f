//! The query shells: HTTP (axum) with the dashboard, gRPC `Query`, and the map
//! queries both answer.

pub mod dashboard;
pub mod foxglove;
pub mod http;
pub mod map_queries;
pub mod openapi;
pub mod query;
pub mod serve;

/// Other servers' live data, for this server's streams (a cluster on Zenoh:
/// `relay.rs`): the dashboard's event stream shows every server's sessions and
/// poses, and `SubscribePoses` follows a session another server holds.
pub trait RemoteLive: Send + Sync {
    /// This server's id (its own sessions are tagged with it).
    fn own_id(&self) -> &str;
    /// Counts a local consumer while the guard lives: the other servers publish
    /// their live data only while some server counts one.
    fn watch(&self) -> Box<dyn Send + Sync>;
    /// The other live servers' sessions, as their dashboards list them (each
    /// tagged `server_id`), from their latest lists (none older than a few seconds).
    fn sessions(&self) -> Vec<serde_json::Value>;
    /// Every new pose of the other servers' sessions while watched.
    fn subscribe_poses(&self) -> tokio::sync::broadcast::Receiver<crate::session::FleetPose>;
    /// Every new pose, in its fleet's frame, of the other servers' sessions merged
    /// into a fleet, while watched.
    fn subscribe_fleet_poses(&self) -> tokio::sync::broadcast::Receiver<RemoteFleetPose>;
}

/// A pose of another server's session in its fleet's frame: (fleet, pose).
pub type RemoteFleetPose = (std::sync::Arc<str>, stillmap_proto::pb::FleetPose);
