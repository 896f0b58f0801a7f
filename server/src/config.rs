//! Server configuration: documented defaults, overridden by a TOML file, then by
//! environment variables and command-line flags (see `main.rs`).
//!
//! `deploy/stillmap-server.toml` spells out every key with its default; a test
//! checks that file parses to exactly [`ServerConfig::default`].

use serde::{Deserialize, Serialize};

use crate::ServerError;

/// Everything the server can be told.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    pub grpc: GrpcConfig,
    pub http: HttpConfig,
    pub zenoh: ZenohConfig,
    pub session: SessionConfig,
    /// Camera tracking (defaults documented in `stillmap_tracking::TrackerConfig`).
    pub tracking: stillmap_tracking::TrackerConfig,
    /// Segmentation, flow and the dynamic mask (defaults documented in
    /// `stillmap_perception::PerceptionConfig`).
    pub perception: stillmap_perception::PerceptionConfig,
    /// The static semantic map (defaults documented in `stillmap_mapping::MappingConfig`).
    pub mapping: stillmap_mapping::MappingConfig,
    pub store: StoreConfig,
    pub auth: AuthConfig,
    pub fleet: FleetConfig,
    pub limits: LimitsConfig,
    pub tls: TlsConfig,
}

/// TLS on the gRPC and HTTP ports (rustls). Off by default: plain TCP, for a
/// trusted network or behind a TLS-terminating proxy.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TlsConfig {
    /// The server's certificate chain (PEM). Empty (default): no TLS.
    pub cert_path: String,
    /// Its private key (PEM).
    pub key_path: String,
    /// A CA (PEM): clients must present a certificate it signed, on gRPC and HTTP
    /// (mutual TLS). Empty (default): no client certificate is asked for.
    pub client_ca_path: String,
}

/// What the sessions in memory may take together. A hello beyond a limit first
/// makes room by evicting idle sessions (disconnected, answered, committed: their
/// state stays in the store); when none can go it is refused with
/// RESOURCE_EXHAUSTED naming the limit, and counted
/// (`stillmap_sessions_refused_total{limit=…}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LimitsConfig {
    /// Sessions in memory at once: live ones (streaming or recently disconnected)
    /// and stored ones a query brought back. About 70 MB each at 640×480 once
    /// streaming (tracker, perception buffers, the map's window), and up to 58 MB
    /// more as its tracker's keyframes reach `tracking.max_keyframes` (500 of about
    /// 115 KB). Default 128.
    pub max_sessions: usize,
    /// Live sessions in memory per robot id (a robot that reconnects without
    /// resuming opens a new one each time). Default 4.
    pub max_sessions_per_robot: usize,
    /// Camera pixels (width × height) of the live sessions in memory, summed: the
    /// per-pixel buffers grow with it. Default 40,000,000 (128 cameras of 640×480).
    pub max_camera_pixels_total: u64,
    /// Hellos per minute a client may send, after a burst of `hello_burst`: per peer
    /// address on gRPC, per robot id on Zenoh. Beyond: RESOURCE_EXHAUSTED naming the
    /// limit, counted as `rate_limited`. A whole fleet behind one address reconnecting
    /// at once fits the burst. Defaults 600 (10 a second) and 200; 0: no limit.
    pub hellos_per_minute: u32,
    pub hello_burst: u32,
    /// HTTP requests per minute a client may send (per bearer token, else per peer
    /// address), after a burst of `http_burst`; beyond: 429 naming the limit, with
    /// Retry-After. `/healthz` is not limited. Defaults 6,000 (100 a second: a
    /// dashboard's screenful of tiles fits the burst) and 400; 0: no limit.
    pub http_requests_per_minute: u32,
    pub http_burst: u32,
    /// CPU one frame may take on a pipeline thread (decoding, tracking, flow,
    /// mask fusion; milliseconds of that thread's CPU time). A frame cannot be
    /// stopped halfway, so a frame over it is finished, counted
    /// (`stillmap_frame_cpu_over_budget_total`) and logged; `frame_cpu_strikes`
    /// such frames in a row end the session's stream with RESOURCE_EXHAUSTED
    /// naming the limit (the session takes no more frames; a new hello opens a
    /// new one). A 640×480 frame takes 20–80 ms on one core. Defaults 2,000 ms
    /// and 3; 0: no budget.
    pub frame_cpu_ms: f64,
    pub frame_cpu_strikes: u32,
}

impl Default for LimitsConfig {
    fn default() -> Self {
        Self {
            max_sessions: 128,
            max_sessions_per_robot: 4,
            max_camera_pixels_total: 40_000_000,
            hellos_per_minute: 600,
            hello_burst: 200,
            http_requests_per_minute: 6000,
            http_burst: 400,
            frame_cpu_ms: 2000.0,
            frame_cpu_strikes: 3,
        }
    }
}

/// Fleets: one world frame per fleet; sessions join it by place recognition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FleetConfig {
    /// Place recognition and merging (off: every session keeps only its own world).
    pub enabled: bool,
    /// The fleet of a robot whose hello names none.
    pub default_fleet: String,
    /// A vocabulary file (`make vocabulary` writes one); empty: the one built in.
    pub vocabulary_path: String,
    /// Stored keyframes verified per looked-up keyframe (the best place-recognition scores).
    pub candidates: usize,
    /// Keyframes waiting for place recognition; a keyframe finding it full is left out
    /// (logged, counted in `stillmap_fleet_keyframes_left_out_total{queue="places"}`).
    pub queue: usize,
    /// Keyframes indexed per fleet (about 60 KB each); the oldest are forgotten first.
    pub max_places: usize,
    /// Fleets held at once (each with its own place index of up to `max_places`
    /// keyframes: about 300 MB at the defaults); a hello naming one more is refused
    /// (RESOURCE_EXHAUSTED naming `fleet.max_fleets`). Fleets restored from the store count.
    pub max_fleets: usize,
    /// An unmerged session's latest keyframes kept in the index (looked up again as
    /// merged sessions' keyframes arrive).
    pub pending_keyframes: usize,
    /// Verified keyframes of a session that must agree on its `fleet_from_session` to merge it …
    pub consistent_matches: usize,
    /// … within this distance (metres) and angle (degrees) of each other.
    pub agreement_m: f64,
    pub agreement_deg: f64,
    /// A merge is refined by later keyframes of either side (their proposals join
    /// the mean) until this many proposals have been heard.
    pub refine_support: usize,
    /// Inliers a candidate needs after PnP-RANSAC and pose optimisation.
    pub min_inliers: usize,
    /// The fleet's pose graph (merged sessions' keyframes; odometry, loop and
    /// inter-session edges) is solved on its own thread at most this often
    /// (seconds), after a new loop or inter-session edge; 0 turns it off.
    pub graph_interval_s: f64,
    /// A keyframe matching one of its own session's keyframes at least this much
    /// older (capture time, seconds) is a loop edge; younger ones are odometry's.
    pub loop_min_age_s: f64,
    /// σ of an odometry edge (consecutive keyframes of a session, from tracking):
    /// translation (metres) and rotation (degrees).
    pub odometry_sigma_m: f64,
    pub odometry_sigma_deg: f64,
    /// σ of a loop or inter-session edge (one verified match), behind a Huber kernel.
    pub place_sigma_m: f64,
    pub place_sigma_deg: f64,
    /// Rounds of re-weighting per solve: the odometry and the place edges each
    /// have their σ scaled by how well they fit the last solution (up to 10×
    /// either way), and the graph is solved again: drift beyond the odometry's σ
    /// loosens it. 0: the σ as configured.
    pub reweight_rounds: usize,
    /// Map-lane jobs waiting for the fleet maps' thread (each holds a keyframe's
    /// fusion input, about 2 MB at VGA); a job finding it full is left out (logged,
    /// its keyframe counted in `stillmap_fleet_keyframes_left_out_total{queue="fleet_map"}`)
    /// and the fleet's products fall back to merging its sessions' maps.
    pub map_queue: usize,
    /// Keyframe fusion inputs a fleet map keeps to fuse them again where the pose
    /// graph moves them (compact, about 200 KB each at VGA: 200 MB per fleet at the default); beyond, the oldest's stays
    /// where it was fused.
    pub map_keyframes: usize,
    /// Keyframes a fleet map fuses (again) per pass of its thread: the bound on one pass's time.
    pub refuse_per_pass: usize,
    /// With a store, a fused fleet map that changed is saved at most this often
    /// (seconds; its changed blocks, on the fleet map's thread) and when the server
    /// stops, so that it comes back at restart.
    pub map_save_interval_s: f64,
    /// Niceness of the fleets' background threads (the pose graph's and the fleet
    /// map's; not place recognition, whose merges are awaited): they yield the
    /// cores to tracking. 0: the server's own.
    pub nice: i32,
}

impl Default for FleetConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            default_fleet: "default".into(),
            vocabulary_path: String::new(),
            candidates: 3,
            queue: 256,
            max_places: 5000,
            max_fleets: 16,
            pending_keyframes: 64,
            consistent_matches: 3,
            agreement_m: 0.05,
            agreement_deg: 2.0,
            refine_support: 32,
            min_inliers: 60,
            graph_interval_s: 2.0,
            loop_min_age_s: 3.0,
            odometry_sigma_m: 0.002,
            odometry_sigma_deg: 0.1,
            place_sigma_m: 0.03,
            place_sigma_deg: 1.0,
            reweight_rounds: 2,
            map_queue: 64,
            map_keyframes: 1000,
            refuse_per_pass: 8,
            map_save_interval_s: 5.0,
            nice: 10,
        }
    }
}

/// Largest `session.pipeline_threads`, `session.map_threads` and `http.worker_threads`.
const MAX_POOL_THREADS: usize = 1024;
/// Largest `http.max_connections` (a semaphore's permits; tokio panics beyond 2^61).
const MAX_HTTP_CONNECTIONS: usize = 1 << 20;
/// Largest `session.result_buffer` (a channel's capacity per stream).
const MAX_RESULT_BUFFER: usize = 65_536;
/// Largest `store.import_max_bytes` (4 GiB: an import may hold 16 times as much).
const MAX_IMPORT_BYTES: usize = 4 << 30;
/// Largest `limits.frame_cpu_ms`: an hour (a `Duration` holds no more than 2^64 s).
const MAX_FRAME_CPU_MS: f64 = 3_600_000.0;
/// Largest `fleet.max_places` (about 60 KB each).
const MAX_FLEET_PLACES: usize = 1_000_000;
/// Fewest poses `session.trajectory_in_memory` keeps (a few seconds: the poses
/// since the last keyframe stay in memory until they are committed anyway).
pub const MIN_TRAJECTORY_IN_MEMORY: usize = 100;

/// Largest `session.keyframe_images` (about 50 MB per session).
const MAX_KEYFRAME_IMAGES: usize = 1024;

/// Largest `session.map_queue` (each job holds a keyframe's images, about 1.5 MB).
const MAX_MAP_QUEUE: usize = 256;

/// Largest `fleet.candidates` (each costs a verification, about 3 ms).
const MAX_FLEET_CANDIDATES: usize = 32;
/// Largest `fleet.queue` and `fleet.pending_keyframes` (a keyframe holds about 50 KB).
const MAX_FLEET_QUEUE: usize = 4096;

/// Largest `zenoh.idle_disconnect_s`: a day.
const MAX_IDLE_DISCONNECT_S: f64 = 86_400.0;
/// Longest `session.handover_wait_s`: a robot keeps saying hello for about 10 s.
const MAX_HANDOVER_WAIT_S: f64 = 60.0;

/// Who may do what (see [`crate::auth`]): tokens with scopes. None configured
/// anywhere (the default): everything is open, for a server on a trusted network.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AuthConfig {
    /// Robot tokens (`robot:*`): a hello must carry a token that may stream as its
    /// robot (`Hello.auth_token`, `stillmap-client --token`) on gRPC and Zenoh, else
    /// UNAUTHENTICATED (no or an unknown token) or PERMISSION_DENIED (another
    /// robot's). Not covered: Zenoh frames after an accepted hello (anyone who can
    /// publish on a robot's key speaks for it: use Zenoh's access control and TLS).
    pub tokens: Vec<String>,
    /// Admin tokens (`admin`, implies `read`): whole maps in and out of the store
    /// (`POST /api/v1/maps/import`, `GET /api/v1/maps/{id}/export`, `Authorization:
    /// Bearer <token>`); another token gets 403, none 401.
    pub admin_tokens: Vec<String>,
    /// Read tokens (`read`): the query APIs, HTTP `/api/v1/...`, `/metrics`, the
    /// dashboard's event stream (`?access_token=` where a browser cannot send a
    /// header) and gRPC `Query` (`authorization` metadata). When any token is
    /// configured anywhere, queries need one with `read` (these, admin tokens, or a
    /// token file's); `/healthz` and the dashboard's files stay open.
    pub read_tokens: Vec<String>,
    /// A file of scoped tokens, one per line: the token, then its scopes separated by
    /// spaces: `robot:<glob>` (stream as matching robot ids), `read`, `admin`
    /// (implies `read`); `#` starts a comment (so a token cannot hold `#`). SIGHUP
    /// reads it again (a mistake keeps the tokens in force and is logged). Empty:
    /// none.
    pub token_file: String,
}

/// The embedded store (redb): sessions, trajectories, keyframes and map blocks
/// survive a restart, and a crash loses at most the frames after the last keyframe.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StoreConfig {
    pub enabled: bool,
    /// The store file (its folder is created).
    pub path: String,
    /// Largest map file body `POST /api/v1/maps/import` decompresses, in bytes
    /// (default 256 MiB; 60 frames of the public clip export as 4.1 MB uncompressed).
    /// A body that declares more is refused before decoding, and decoding stops
    /// here whatever it declared.
    pub import_max_bytes: usize,
    /// Longest wait between write attempts while the store fails (a full disk):
    /// the wait starts at 1 s and doubles up to this (seconds; default 60). While
    /// failing, `/healthz` answers 503 and the maps stay in memory.
    pub retry_max_s: f64,
    /// Every this many seconds, what a live session has not committed (the poses
    /// after its last keyframe, a commit that failed while the store could not
    /// write) is committed: a crash loses at most this much, and a store that
    /// failed is retried without waiting for the robot's next keyframe (default 5).
    pub flush_interval_s: f64,
    /// The store's page cache in memory, in bytes (default 64 MiB; redb's own
    /// default, 1 GiB, is taken as the store grows and kept).
    pub cache_bytes: usize,
    /// Storage shared by several servers: every commit (a session's description,
    /// new poses, keyframe records and changed map blocks) is copied to this
    /// PostgreSQL database too (a libpq URL, `postgresql://user@host:port/db`, or
    /// key=value string; empty, the default: no copy), except those left out and
    /// counted (`replica.rs`: a full queue, a refusal, a failure at shutdown).
    /// A robot resuming a session this server does not hold (its server left) gets
    /// it back from there. Needs `store.enabled`.
    pub replica_url: String,
    /// Commits waiting to be copied at most (default 256); a commit finding the
    /// queue full is not copied (`stillmap_replica_dropped_total`).
    pub replica_queue: usize,
}

impl Default for StoreConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            path: "stillmap-data/stillmap.redb".into(),
            import_max_bytes: 256 << 20,
            retry_max_s: 60.0,
            flush_interval_s: 5.0,
            cache_bytes: crate::store::DEFAULT_CACHE_BYTES,
            replica_url: String::new(),
            replica_queue: 256,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GrpcConfig {
    /// Address the gRPC ingest and query services listen on.
    pub listen: String,
    /// Largest single message accepted, in bytes (larger: RESOURCE_EXHAUSTED).
    pub max_message_bytes: usize,
    /// Seconds between HTTP/2 keepalive pings to each client.
    pub keepalive_interval_s: u64,
    /// Seconds to wait for a keepalive answer before dropping the connection.
    pub keepalive_timeout_s: u64,
    /// The address robots reach this server's gRPC port at (`http://host:port`, or
    /// `https://` with TLS), for servers on one Zenoh network: `Ingest.Place` sends a
    /// robot that belongs here (placement by fleet, else robot id) to it, whichever
    /// server the robot asked. Empty (default): robots are not sent here; a robot
    /// that asks streams to the server it asked, as without a cluster.
    pub advertise: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HttpConfig {
    /// Address of the HTTP API (`/healthz`, `/api/v1/...`, `/metrics`) and the dashboard (`/`).
    pub listen: String,
    /// Folder of the web dashboard (`dashboard/` of the repository, with its
    /// `node_modules` from `make dashboard`). Empty: `dashboard/` beside the
    /// working directory, else two levels above the server binary (`target/<profile>/`).
    pub dashboard_dir: String,
    /// Dashboard event streams (`/api/v1/events`) at once; one more is answered 503.
    /// Every viewer shares one snapshot per 500 ms and one serialisation of the new
    /// poses per `pose_event_interval_ms`, so a viewer costs a connection and a copy
    /// of the text (default 1024).
    pub max_event_viewers: usize,
    /// How often viewers get the new poses of every session, as one `poses` event
    /// (milliseconds, 20..=5000). Each event is a write per viewer whatever the fleet's
    /// frame rate: 4 a second per viewer at the default, where one event per pose
    /// would be 480 for 16 robots at 30 Hz (default 250).
    pub pose_event_interval_ms: u64,
    /// Threads for the server's blocking work: map queries (tiles, clouds,
    /// occupancy grids), the dashboard's snapshot, store flushes and session
    /// eviction. Queued beyond it; a thread once started stays, so the thread
    /// count stays flat (default 32).
    pub blocking_threads: usize,
    /// A connection must send each request's head within this many seconds, or it
    /// is closed (slowloris: a client dribbling its headers, or sending nothing).
    /// Default 10.
    pub header_timeout_s: f64,
    /// HTTP connections served at once; more are closed on accept and counted
    /// (`rejected_total{reason="http_connections"}`). Default 4096.
    pub max_connections: usize,
    /// Threads of the runtime that serves HTTP (the API, map queries' hand-off,
    /// the dashboard and its event streams), apart from the one that takes
    /// robots' frames. Default 2.
    pub worker_threads: usize,
    /// Scheduling niceness of the HTTP runtime's threads (Linux, per thread;
    /// 0–19): above 0, robots' frames and their tracking win the CPU over
    /// dashboards and queries when both want it. Default 10; 0: same priority.
    pub nice: i32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ZenohConfig {
    /// Subscribe to `stillmap/*/frames` on Zenoh.
    pub enabled: bool,
    /// Zenoh mode: "peer" or "client" (connect to a router).
    pub mode: String,
    /// Endpoints to listen on, e.g. "tcp/0.0.0.0:7447".
    pub listen: Vec<String>,
    /// Endpoints (routers or peers) to connect to.
    pub connect: Vec<String>,
    /// Multicast scouting (off by default: explicit endpoints only).
    pub multicast_scouting: bool,
    /// A Zenoh configuration file (JSON5, Zenoh's own format): TLS and mTLS under
    /// `transport/link/tls`, user/password authentication, access control. When
    /// set it is the whole Zenoh configuration, and `mode`, `listen`, `connect`
    /// and `multicast_scouting` above are ignored. `deploy/zenoh/` has the
    /// server's, the router's (TLS, mTLS, per-robot ACL) and a robot's.
    /// Default: none.
    pub config_file: Option<std::path::PathBuf>,
    /// Seconds without a message, with every frame answered, after which a Zenoh
    /// robot's session counts as disconnected. Zenoh has no per-robot connection whose close the server could
    /// see (gRPC has its stream), so without this a robot that vanished would show
    /// as connected forever. Its next frame attaches the session again; nothing is
    /// closed or lost. 0: never.
    pub idle_disconnect_s: f64,
    /// The server's name among servers on one Zenoh network: its liveliness token
    /// `stillmap-cluster/servers/<id>` and status queryable `.../<id>/status`
    /// (A-Z a-z 0-9 _ -, at most 64). Empty (default): the host name and the gRPC
    /// port, `<hostname>-<port>`, unique on a machine and stable across restarts.
    pub server_id: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SessionConfig {
    /// Frames waiting for the pipeline, per session; beyond it the overload policy applies.
    pub queue_capacity: usize,
    /// What to do with a frame that finds the queue full.
    pub overload_policy: OverloadPolicy,
    /// Results buffered per connection while the client reads slowly.
    pub result_buffer: usize,
    /// Dropped-frame notices a session may hold for a client that does not read its
    /// results; past it the stream ends with RESOURCE_EXHAUSTED.
    pub max_pending_drop_notices: usize,
    /// Robots streaming at once (sessions with a connection attached); a hello beyond
    /// it is refused with RESOURCE_EXHAUSTED, so an overloaded server turns robots
    /// away instead of dropping every robot's frames. Size it from the fleet
    /// benchmark (`make bench-fleet`). 0 = no limit.
    pub max_connected: usize,
    /// Threads that run the sessions' tracking paths (decode, perception,
    /// tracking), shared by all sessions; 0 (default) = one per core.
    pub pipeline_threads: usize,
    /// Threads that fuse keyframes into the maps and commit them to the store,
    /// shared by all sessions, off the tracking path.
    pub map_threads: usize,
    /// Threads each OpenCV call (ORB, flow, dense odometry) may use, process-wide;
    /// 0 = OpenCV's default (one per core). 1 by default: the pipeline pool already
    /// runs one session per core, and OpenCV's own parallel loops on top of it
    /// only oversubscribe the cores (README, "Fleet capacity", measures both).
    pub opencv_threads: usize,
    /// Map jobs (keyframes, re-fusions) waiting per session; a keyframe finding the
    /// queue full is left out of the map and counted (`stillmap_map_jobs_skipped_total`),
    /// so tracking never waits for the map.
    pub map_queue: usize,
    /// Keyframe images a session keeps in memory for its Foxglove export
    /// (`/api/v1/sessions/{id}/export.mcap`): the newest ones, colour with the pixels
    /// perception kept out of the map tinted, JPEG (about 50 KB each). 0 = none.
    pub keyframe_images: usize,
    /// Poses of a session's trajectory kept in memory: the newest. With a store,
    /// older poses, once committed, leave memory (when a quarter more than this
    /// are held, down to this many) and the trajectory queries and the export read
    /// them back from the store; a session streaming for hours holds 112 bytes
    /// per pose otherwise (97 MB in 8 hours at 30 Hz). Default 36,000 (20 minutes
    /// at 30 Hz: 4 MB of poses, up to 8 MB with the list's spare room); 0 = every
    /// pose. Without a store every pose stays in memory (nothing else holds it).
    pub trajectory_in_memory: usize,
    /// Largest camera a hello may declare, in pixels (width × height; default
    /// 2,097,152 = 2 MP, a 1920×1080 camera fits). A session's buffers grow with
    /// it (about 8 bytes of camera rays per pixel before any frame), so a larger
    /// hello is refused with RESOURCE_EXHAUSTED naming this key.
    pub max_camera_pixels: u64,
    /// A frame whose sequence number is more than this past the session's previous
    /// frame is rejected (counted as `order`) and does not move the session on:
    /// one forged or corrupt frame (sequence 2⁶⁴−1) cannot make every later frame
    /// of the robot look old. Default 1,000,000 (nine hours at 30 Hz).
    pub max_sequence_jump: u64,
    /// The same for capture time: a frame more than this many seconds after the
    /// previous one is rejected (default 86,400 s, a day).
    pub max_capture_gap_s: f64,
    /// A session disconnected (or, restored from the store, not queried) for this
    /// long leaves memory once everything it holds is answered and committed: its
    /// pipeline, tracker and map are freed, the store keeps its trajectory and map,
    /// and a query brings it back (read-only; a robot resuming it gets a new
    /// session, as after a restart). Default 300 s; 0 = only under the `limits`.
    /// Without a store nothing is evicted (it would be lost).
    pub idle_evict_s: f64,
    /// A session resumed from the shared storage (`store.replica_url`: its server
    /// left) whose new tracker is not found among its stored keyframes within this
    /// many seconds of frames (capture time) is given up: its stream ends with
    /// ABORTED, and the robot opens a new session in a world of its own. Until then
    /// its frames are LOST without a pose. Default 10 s; 0 = wait for as long as
    /// the robot streams.
    pub resume_find_s: f64,
    /// With shared storage (`store.replica_url`), for Zenoh robots and gRPC robots
    /// that ask where they belong (`Ingest.Place`): when a server joins and takes a
    /// robot, the server the robot was on hands its session over (once the
    /// robot's last frames there are answered and committed) and the new owner
    /// resumes it, the same session in the same world; the new owner answers the
    /// robot's resume UNAVAILABLE (it says hello again) for at most this many
    /// seconds, then opens a new session instead. The server handing over tries
    /// for as long. Default 5 s; 0 = no handover (a robot taken by a joining server
    /// gets a new session). At most 60 s.
    pub handover_wait_s: f64,
}

/// Overload policy of a session's frame queue. Every dropped frame is counted in
/// `/metrics` and answered with a `FRAME_STATUS_DROPPED` result.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OverloadPolicy {
    /// Drop the oldest waiting frame: the freshest view wins (good for tracking).
    DropOldest,
    /// Drop the arriving frame: the oldest waiting frames are kept.
    DropNewest,
}

impl Default for GrpcConfig {
    fn default() -> Self {
        Self {
            listen: "127.0.0.1:50051".into(),
            max_message_bytes: 8 * 1024 * 1024,
            keepalive_interval_s: 10,
            keepalive_timeout_s: 20,
            advertise: String::new(),
        }
    }
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            listen: "127.0.0.1:8080".into(),
            dashboard_dir: String::new(),
            max_event_viewers: 1024,
            pose_event_interval_ms: 250,
            blocking_threads: 32,
            header_timeout_s: 10.0,
            max_connections: 4096,
            worker_threads: 2,
            nice: 10,
        }
    }
}

impl Default for ZenohConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            mode: "peer".into(),
            listen: vec!["tcp/127.0.0.1:7447".into()],
            connect: vec![],
            multicast_scouting: false,
            config_file: None,
            idle_disconnect_s: 10.0,
            server_id: String::new(),
        }
    }
}

impl Default for SessionConfig {
    fn default() -> Self {
        Self {
            queue_capacity: 8,
            overload_policy: OverloadPolicy::DropOldest,
            result_buffer: 64,
            max_pending_drop_notices: 1024,
            max_connected: 64,
            pipeline_threads: 0,
            map_threads: 1,
            opencv_threads: 1,
            map_queue: 16,
            keyframe_images: 32,
            trajectory_in_memory: 36_000,
            max_camera_pixels: 1 << 21,
            max_sequence_jump: 1_000_000,
            max_capture_gap_s: 86_400.0,
            idle_evict_s: 300.0,
            resume_find_s: 10.0,
            handover_wait_s: 5.0,
        }
    }
}

impl ServerConfig {
    /// Parses a TOML document; keys left out keep their defaults.
    pub fn from_toml(text: &str) -> Result<Self, ServerError> {
        let config: Self = toml::from_str(text).map_err(|e| ServerError::Config(e.to_string()))?;
        config.validate()?;
        Ok(config)
    }

    /// Rejects values the server cannot run with.
    /// (Comparisons are negated so that NaN fails them too.)
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn validate(&self) -> Result<(), ServerError> {
        let bad = |msg: String| Err(ServerError::Config(msg));
        if self.session.queue_capacity == 0 {
            return bad("session.queue_capacity must be at least 1".into());
        }
        if self.session.pipeline_threads > MAX_POOL_THREADS {
            return bad(format!("session.pipeline_threads must be at most {MAX_POOL_THREADS}, got {}", self.session.pipeline_threads));
        }
        if !(1..=MAX_POOL_THREADS).contains(&self.session.map_threads) {
            return bad(format!("session.map_threads must be in 1..={MAX_POOL_THREADS}, got {}", self.session.map_threads));
        }
        if self.session.opencv_threads > MAX_POOL_THREADS {
            return bad(format!("session.opencv_threads must be at most {MAX_POOL_THREADS}, got {}", self.session.opencv_threads));
        }
        if self.session.trajectory_in_memory != 0 && self.session.trajectory_in_memory < MIN_TRAJECTORY_IN_MEMORY {
            return bad(format!(
                "session.trajectory_in_memory must be 0 (every pose) or at least {MIN_TRAJECTORY_IN_MEMORY} poses, got {}",
                self.session.trajectory_in_memory
            ));
        }
        if self.session.keyframe_images > MAX_KEYFRAME_IMAGES {
            return bad(format!("session.keyframe_images must be at most {MAX_KEYFRAME_IMAGES}, got {}", self.session.keyframe_images));
        }
        if !(1..=MAX_MAP_QUEUE).contains(&self.session.map_queue) {
            return bad(format!("session.map_queue must be in 1..={MAX_MAP_QUEUE}, got {}", self.session.map_queue));
        }
        if !(1..=MAX_POOL_THREADS).contains(&self.http.blocking_threads) {
            return bad(format!("http.blocking_threads must be in 1..={MAX_POOL_THREADS}, got {}", self.http.blocking_threads));
        }
        let header_timeout = self.http.header_timeout_s >= 0.1 && self.http.header_timeout_s <= 3600.0;
        if !(header_timeout && (1..=MAX_HTTP_CONNECTIONS).contains(&self.http.max_connections)) {
            return bad(format!(
                "http.header_timeout_s must be within 0.1..=3600 and http.max_connections within 1..={MAX_HTTP_CONNECTIONS}, got {} and {}",
                self.http.header_timeout_s, self.http.max_connections
            ));
        }
        if !(1..=MAX_RESULT_BUFFER).contains(&self.session.result_buffer) {
            return bad(format!("session.result_buffer must be within 1..={MAX_RESULT_BUFFER}, got {}", self.session.result_buffer));
        }
        if !(1..=86_400).contains(&self.grpc.keepalive_interval_s) || !(1..=3600).contains(&self.grpc.keepalive_timeout_s) {
            return bad(format!(
                "grpc.keepalive_interval_s must be within 1..=86400 and grpc.keepalive_timeout_s within 1..=3600 seconds, got {} and {}",
                self.grpc.keepalive_interval_s, self.grpc.keepalive_timeout_s
            ));
        }
        if self.grpc.max_message_bytes < 1024 {
            return bad(format!("grpc.max_message_bytes {} is below 1024", self.grpc.max_message_bytes));
        }
        self.tracking.validate().map_err(ServerError::Config)?;
        self.perception.validate().map_err(ServerError::Config)?;
        self.mapping.validate().map_err(|e| ServerError::Config(e.to_string()))?;
        if self.store.enabled && self.store.path.is_empty() {
            return bad("store.path must name a file when store.enabled is true".into());
        }
        if !["peer", "client"].contains(&self.zenoh.mode.as_str()) {
            return bad(format!("zenoh.mode must be \"peer\" or \"client\", got {:?}", self.zenoh.mode));
        }
        for (name, tokens) in
            [("tokens", &self.auth.tokens), ("admin_tokens", &self.auth.admin_tokens), ("read_tokens", &self.auth.read_tokens)]
        {
            if let Some(i) = tokens.iter().position(|t| t.trim().is_empty()) {
                return bad(format!("auth.{name}[{i}] is empty"));
            }
            if let Some(i) = tokens.iter().position(|t| t.trim() != t) {
                return bad(format!("auth.{name}[{i}] has leading or trailing whitespace"));
            }
        }
        let a = &self.auth;
        if a.admin_tokens.iter().chain(&a.read_tokens).any(|t| a.tokens.contains(t))
            || a.admin_tokens.iter().any(|t| a.read_tokens.contains(t))
        {
            return bad("a token is in two of auth.tokens, auth.read_tokens and auth.admin_tokens: give each role tokens of its own".into());
        }
        if self.session.max_camera_pixels == 0
            || self.session.max_sequence_jump == 0
            || !(self.session.max_capture_gap_s > 0.0 && self.session.max_capture_gap_s.is_finite())
        {
            return bad("session.max_camera_pixels, max_sequence_jump and max_capture_gap_s must be positive".into());
        }
        if !(0.1..=3600.0).contains(&self.store.flush_interval_s) {
            return bad(format!("store.flush_interval_s must be within 0.1..=3600, got {}", self.store.flush_interval_s));
        }
        if !(0.1..=3600.0).contains(&self.store.retry_max_s) {
            return bad(format!("store.retry_max_s must be within 0.1..=3600, got {}", self.store.retry_max_s));
        }
        if !self.store.replica_url.is_empty() && !self.store.enabled {
            return bad("store.replica_url copies the store's commits: it needs store.enabled".into());
        }
        if !(1..=65536).contains(&self.store.replica_queue) {
            return bad(format!("store.replica_queue must be within 1..=65536, got {}", self.store.replica_queue));
        }
        if self.store.cache_bytes < 1 << 20 {
            return bad(format!("store.cache_bytes {} is below 1 MiB", self.store.cache_bytes));
        }
        if !(1024..=MAX_IMPORT_BYTES).contains(&self.store.import_max_bytes) {
            return bad(format!("store.import_max_bytes must be within 1024..={MAX_IMPORT_BYTES}, got {}", self.store.import_max_bytes));
        }
        let f = &self.fleet;
        stillmap_proto::validate_fleet(&f.default_fleet).map_err(|e| ServerError::Config(format!("fleet.default_fleet: {e}")))?;
        if !(1..=MAX_FLEET_CANDIDATES).contains(&f.candidates)
            || !(1..=MAX_FLEET_QUEUE).contains(&f.queue)
            || !(1..=MAX_FLEET_PLACES).contains(&f.max_places)
            || f.max_fleets == 0
        {
            return bad(format!(
                "fleet.candidates must be in 1..={MAX_FLEET_CANDIDATES}, fleet.queue in 1..={MAX_FLEET_QUEUE}, fleet.max_places in 1..={MAX_FLEET_PLACES} and fleet.max_fleets at least 1"
            ));
        }
        if !(1..=MAX_FLEET_QUEUE).contains(&f.pending_keyframes) || !(1..=16).contains(&f.consistent_matches) || f.min_inliers < 6 {
            return bad(format!(
                "fleet.pending_keyframes must be in 1..={MAX_FLEET_QUEUE}, fleet.consistent_matches in 1..=16 and fleet.min_inliers at least 6"
            ));
        }
        if !(f.consistent_matches..=64).contains(&f.refine_support) {
            return bad(format!("fleet.refine_support must be in fleet.consistent_matches..=64, got {}", f.refine_support));
        }
        if !(f.agreement_m > 0.0 && f.agreement_m <= 1.0 && f.agreement_deg > 0.0 && f.agreement_deg <= 45.0) {
            return bad(format!(
                "fleet.agreement_m must be in (0, 1] and fleet.agreement_deg in (0, 45], got {} and {}",
                f.agreement_m, f.agreement_deg
            ));
        }
        let graph_interval = f.graph_interval_s == 0.0 || (f.graph_interval_s >= 0.05 && f.graph_interval_s <= 3600.0);
        if !(graph_interval && f.loop_min_age_s >= 0.0 && f.loop_min_age_s <= 3600.0) {
            return bad(format!(
                "fleet.graph_interval_s must be 0 (off) or within 0.05..=3600 seconds and fleet.loop_min_age_s within 0..=3600, got {} and {}",
                f.graph_interval_s, f.loop_min_age_s
            ));
        }
        if !(0..=19).contains(&f.nice) {
            return bad(format!("fleet.nice must be in 0..=19, got {}", f.nice));
        }
        if f.reweight_rounds > 8 {
            return bad(format!("fleet.reweight_rounds must be in 0..=8, got {}", f.reweight_rounds));
        }
        if !(1..=MAX_MAP_QUEUE).contains(&f.map_queue) || f.map_keyframes == 0 || !(1..=MAX_MAP_QUEUE).contains(&f.refuse_per_pass) {
            return bad(format!(
                "fleet.map_queue and fleet.refuse_per_pass must be in 1..={MAX_MAP_QUEUE} and fleet.map_keyframes at least 1, got {}, {} and {}",
                f.map_queue, f.refuse_per_pass, f.map_keyframes
            ));
        }
        if !(f.map_save_interval_s > 0.0 && f.map_save_interval_s <= 3600.0) {
            return bad(format!("fleet.map_save_interval_s must be in (0, 3600] seconds, got {}", f.map_save_interval_s));
        }
        let sigma = |v: f64| v > 0.0 && v <= 10.0;
        if ![f.odometry_sigma_m, f.odometry_sigma_deg, f.place_sigma_m, f.place_sigma_deg].into_iter().all(sigma) {
            return bad(format!(
                "fleet.odometry_sigma_m, odometry_sigma_deg, place_sigma_m and place_sigma_deg must be in (0, 10], got {}, {}, {} and {}",
                f.odometry_sigma_m, f.odometry_sigma_deg, f.place_sigma_m, f.place_sigma_deg
            ));
        }
        if !(self.session.idle_evict_s >= 0.0 && self.session.idle_evict_s <= MAX_IDLE_DISCONNECT_S) {
            return bad(format!(
                "session.idle_evict_s must be 0 (only under the limits) or a number of seconds up to {MAX_IDLE_DISCONNECT_S}, got {}",
                self.session.idle_evict_s
            ));
        }
        if !(self.session.resume_find_s >= 0.0 && self.session.resume_find_s <= MAX_IDLE_DISCONNECT_S) {
            return bad(format!(
                "session.resume_find_s must be 0 (wait as long as the robot streams) or a number of seconds up to {MAX_IDLE_DISCONNECT_S}, got {}",
                self.session.resume_find_s
            ));
        }
        if !(self.session.handover_wait_s >= 0.0 && self.session.handover_wait_s <= MAX_HANDOVER_WAIT_S) {
            return bad(format!(
                "session.handover_wait_s must be 0 (no handover) or a number of seconds up to {MAX_HANDOVER_WAIT_S}, got {}",
                self.session.handover_wait_s
            ));
        }
        if self.tls.cert_path.is_empty() != self.tls.key_path.is_empty()
            || (self.tls.cert_path.is_empty() && !self.tls.client_ca_path.is_empty())
        {
            return bad("tls.cert_path and tls.key_path go together, and tls.client_ca_path needs them".into());
        }
        let l = &self.limits;
        if l.max_sessions == 0 || l.max_sessions_per_robot == 0 {
            return bad("limits.max_sessions and limits.max_sessions_per_robot must be at least 1".into());
        }
        if !(20..=5000).contains(&self.http.pose_event_interval_ms) {
            return bad(format!("http.pose_event_interval_ms must be within 20..=5000, got {}", self.http.pose_event_interval_ms));
        }
        if !(1..=MAX_POOL_THREADS).contains(&self.http.worker_threads) || !(0..=19).contains(&self.http.nice) {
            return bad(format!(
                "http.worker_threads must be within 1..={MAX_POOL_THREADS} and http.nice within 0..=19; got {} and {}",
                self.http.worker_threads, self.http.nice
            ));
        }
        if !(l.frame_cpu_ms >= 0.0 && l.frame_cpu_ms <= MAX_FRAME_CPU_MS) || l.frame_cpu_strikes == 0 {
            return bad(format!(
                "limits.frame_cpu_ms must be 0 (no budget) or a number of milliseconds up to {MAX_FRAME_CPU_MS}, and limits.frame_cpu_strikes at least 1; got {} and {}",
                l.frame_cpu_ms, l.frame_cpu_strikes
            ));
        }
        if l.max_camera_pixels_total < self.session.max_camera_pixels {
            return bad(format!(
                "limits.max_camera_pixels_total ({}) must be at least session.max_camera_pixels ({}): the largest camera allowed could never stream",
                l.max_camera_pixels_total, self.session.max_camera_pixels
            ));
        }
        if !(self.zenoh.idle_disconnect_s >= 0.0 && self.zenoh.idle_disconnect_s <= MAX_IDLE_DISCONNECT_S) {
            return bad(format!(
                "zenoh.idle_disconnect_s must be 0 (never) or a positive number of seconds up to {MAX_IDLE_DISCONNECT_S}, got {}",
                self.zenoh.idle_disconnect_s
            ));
        }
        if !self.zenoh.server_id.is_empty() {
            stillmap_proto::validate_server_id(&self.zenoh.server_id).map_err(|e| ServerError::Config(format!("zenoh.{e}")))?;
        }
        if !self.grpc.advertise.is_empty() {
            validate_advertised(&self.grpc.advertise).map_err(|e| ServerError::Config(format!("grpc.advertise: {e}")))?;
        }
        Ok(())
    }
}

/// An advertised gRPC address: `http://` or `https://`, a host, a port, nothing else.
fn validate_advertised(address: &str) -> Result<(), String> {
    let uri: axum::http::Uri = address.parse().map_err(|e| format!("{address:?} is not an address: {e}"))?;
    if !matches!(uri.scheme_str(), Some("http" | "https")) {
        return Err(format!("{address:?} must start with http:// or https://"));
    }
    if uri.host().is_none_or(str::is_empty) || uri.port_u16().is_none() {
        return Err(format!("{address:?} must name a host and a port (http://host:50051)"));
    }
    if uri.path_and_query().is_some_and(|p| p.as_str() != "/") {
        return Err(format!("{address:?} must be only a scheme, a host and a port"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_config_file_documents_exactly_the_defaults() {
        let text = include_str!("../../deploy/stillmap-server.toml");
        assert_eq!(ServerConfig::from_toml(text).unwrap(), ServerConfig::default());
    }

    /// The Kubernetes deployment's ConfigMap (deploy/k8s/base/server.toml) is a valid
    /// configuration, pointing the dashboard where the image puts it.
    #[test]
    fn the_kubernetes_config_is_valid() {
        let c = ServerConfig::from_toml(include_str!("../../deploy/k8s/base/server.toml")).unwrap();
        assert_eq!(c.http.dashboard_dir, "/opt/stillmap/dashboard");
        assert!(include_str!("../../deploy/docker/Dockerfile").contains("/src/dashboard/ /opt/stillmap/dashboard/"));
    }

    #[test]
    fn partial_file_keeps_other_defaults_and_unknown_keys_are_named() {
        let c = ServerConfig::from_toml("[session]\nqueue_capacity = 3\noverload_policy = \"drop_newest\"\n").unwrap();
        assert_eq!(c.session.queue_capacity, 3);
        assert_eq!(c.session.overload_policy, OverloadPolicy::DropNewest);
        assert_eq!(c.grpc, GrpcConfig::default());
        let err = ServerConfig::from_toml("[grpc]\nlisten_addr = \"x\"\n").unwrap_err().to_string();
        assert!(err.contains("unknown field `listen_addr`"), "{err}");
        let err = ServerConfig::from_toml("[session]\nqueue_capacity = 0\n").unwrap_err().to_string();
        assert_eq!(err, "invalid configuration: session.queue_capacity must be at least 1");
        let err = ServerConfig::from_toml("[zenoh]\nidle_disconnect_s = -1.0\n").unwrap_err().to_string();
        assert_eq!(
            err,
            "invalid configuration: zenoh.idle_disconnect_s must be 0 (never) or a positive number of seconds up to 86400, got -1"
        );
        assert!(ServerConfig::from_toml("[zenoh]\nidle_disconnect_s = 1e300\n").is_err(), "would overflow a Duration");
        let err = ServerConfig::from_toml("[session]\nresume_find_s = -1.0\n").unwrap_err().to_string();
        assert_eq!(
            err,
            "invalid configuration: session.resume_find_s must be 0 (wait as long as the robot streams) or a number of seconds up to 86400, got -1"
        );
        assert!(ServerConfig::from_toml("[session]\nresume_find_s = nan\n").is_err());
        let err = ServerConfig::from_toml("[auth]\ntokens = [\"a\", \" b\"]\n").unwrap_err().to_string();
        assert_eq!(err, "invalid configuration: auth.tokens[1] has leading or trailing whitespace");
        assert_eq!(ServerConfig::from_toml("[zenoh]\nidle_disconnect_s = 0.0\n").unwrap().zenoh.idle_disconnect_s, 0.0);
        let err = ServerConfig::from_toml("[http]\npose_event_interval_ms = 0\n").unwrap_err().to_string();
        assert_eq!(err, "invalid configuration: http.pose_event_interval_ms must be within 20..=5000, got 0");
        assert_eq!(ServerConfig::from_toml("[http]\npose_event_interval_ms = 20\n").unwrap().http.pose_event_interval_ms, 20);
    }

    /// `grpc.advertise` is what robots are told to dial: a scheme, a host and a port.
    #[test]
    fn the_advertised_grpc_address_is_checked() {
        let ok = |a: &str| ServerConfig::from_toml(&format!("[grpc]\nadvertise = \"{a}\"\n")).map(|c| c.grpc.advertise);
        assert_eq!(ok("http://stillmap-0.stillmap:50051").unwrap(), "http://stillmap-0.stillmap:50051");
        assert_eq!(ok("https://10.0.0.7:443").unwrap(), "https://10.0.0.7:443");
        let err = |a: &str| ok(a).unwrap_err().to_string();
        assert_eq!(
            err("stillmap-0:50051"),
            "invalid configuration: grpc.advertise: \"stillmap-0:50051\" must start with http:// or https://"
        );
        assert_eq!(
            err("http://stillmap-0"),
            "invalid configuration: grpc.advertise: \"http://stillmap-0\" must name a host and a port (http://host:50051)"
        );
        assert_eq!(err("http://h:1/x"), "invalid configuration: grpc.advertise: \"http://h:1/x\" must be only a scheme, a host and a port");
        assert!(err("http://a b:1").starts_with("invalid configuration: grpc.advertise: \"http://a b:1\" is not an address"));
    }

    /// Pool sizes, queues and the segmentation batcher's limits are checked at start-up.
    #[test]
    fn fleet_limits_are_named_when_out_of_range() {
        let err = |toml: &str| ServerConfig::from_toml(toml).unwrap_err().to_string();
        assert_eq!(err("[session]\nmap_threads = 0\n"), "invalid configuration: session.map_threads must be in 1..=1024, got 0");
        assert_eq!(
            err("[session]\npipeline_threads = 5000\n"),
            "invalid configuration: session.pipeline_threads must be at most 1024, got 5000"
        );
        assert_eq!(
            err("[session]\nopencv_threads = 2000\n"),
            "invalid configuration: session.opencv_threads must be at most 1024, got 2000"
        );
        assert_eq!(err("[session]\nmap_queue = 0\n"), "invalid configuration: session.map_queue must be in 1..=256, got 0");
        assert!(
            err("[perception.ego_motion]\nbaseline_frames = 31\n")
                .contains("perception.ego_motion.baseline_frames must be at most 30, got 31"),
            "{}",
            err("[perception.ego_motion]\nbaseline_frames = 31\n")
        );
        assert_eq!(
            ServerConfig::from_toml("[perception.ego_motion]\nbaseline_frames = 0\n").unwrap().perception.ego_motion.baseline_frames,
            0
        );
        // The frame intervals the flow's and the dense prior's noise hold for.
        assert!(
            err("[perception.ego_motion]\nframe_interval_s = 0.0\n")
                .contains("perception.ego_motion.frame_interval_s must be in (0, 1], got 0")
        );
        assert!(err("[tracking]\ndense_prior_interval_s = 2.0\n").contains("tracking.dense_prior_interval_s must be in (0, 1], got 2"));
        assert!(err("[tracking]\ncoast_s = -1.0\n").contains("tracking.coast_s must be in [0, 60], got -1"));
        assert!(err("[tracking]\ncoast_min_agreement = 2.0\n").contains("tracking.coast_min_agreement must be in [0, 1], got 2"));
        assert!(err("[tracking]\nweak_placement_ratio = 1.5\n").contains("tracking.weak_placement_ratio must be in [0, 1], got 1.5"));
        assert!(
            err("[tracking]\ndense_second_start_ratio = -0.5\n").contains("tracking.dense_second_start_ratio must be in [0, 1], got -0.5")
        );
        assert!(err("[tracking]\ndense_second_start_share = 0.0\n").contains("tracking.dense_second_start_share must be in (0, 1], got 0"));
        assert!(
            err("[tracking]\ndense_prior_check_chi2 = -1.0\n")
                .contains("tracking.dense_prior_check_chi2 must be 0 (off) or positive, got -1")
        );
        assert_eq!(
            err("[fleet]\ndefault_fleet = \"a b\"\n"),
            "invalid configuration: fleet.default_fleet: fleet \"a b\" contains ' '; allowed are A-Z a-z 0-9 _ -"
        );
        assert!(err("[fleet]\ncandidates = 0\n").contains("fleet.candidates must be in 1..=32"));
        assert!(err("[fleet]\nagreement_m = -1.0\n").contains("fleet.agreement_m must be in (0, 1]"));
        assert!(err("[fleet]\ngraph_interval_s = -1.0\n").contains("fleet.graph_interval_s must be 0 (off) or within 0.05..=3600 seconds"));
        assert!(err("[fleet]\nmap_save_interval_s = 0.0\n").contains("fleet.map_save_interval_s must be in (0, 3600] seconds, got 0"));
        assert!(err("[fleet]\nplace_sigma_m = 0.0\n").contains("place_sigma_m and place_sigma_deg must be in (0, 10]"));
        assert!(
            err("[perception.ego_motion]\nmoving_majority_share = 0.0\n")
                .contains("perception.ego_motion.moving_majority_share must be in (0, 1], got 0")
        );
        assert!(
            err("[perception.fusion]\ninstance_depth_gate = 1.0\n")
                .contains("perception.fusion.instance_depth_gate must be in [0, 1), got 1")
        );
        assert_eq!(
            err("[perception.fusion]\nretract_keyframes = 1000\n"),
            "invalid configuration: perception.fusion.retract_keyframes must be at most 64, got 1000"
        );
        assert_eq!(
            err("[perception.segmentation]\nmax_batch = 0\n"),
            "invalid configuration: perception.segmentation.max_batch must be in 1..=64, got 0"
        );
        assert_eq!(
            err("[perception.segmentation]\nmax_queue_delay_ms = 100\n"),
            "invalid configuration: perception.segmentation.max_queue_delay_ms must be at most 33, got 100"
        );
        assert_eq!(
            err("[perception.segmentation]\nexecution_provider = \"tensorrt\"\ntensorrt_cache_dir = \"\"\n"),
            "invalid configuration: perception.segmentation.tensorrt_cache_dir must name a folder with execution_provider = \"tensorrt\""
        );
        assert!(err("[perception.segmentation]\nexecution_provider = \"rocm\"\n").contains("unknown variant `rocm`"));
        assert_eq!(
            err("[perception.segmentation]\nperson_height_m = 5.0\n"),
            "invalid configuration: perception.segmentation.person_height_m must be in 0..=3 m, got 5"
        );
        assert_eq!(
            err("[fleet]\nmax_fleets = 0\n"),
            "invalid configuration: fleet.candidates must be in 1..=32, fleet.queue in 1..=4096, fleet.max_places in 1..=1000000 and fleet.max_fleets at least 1"
        );
        let c = ServerConfig::from_toml("[session]\npipeline_threads = 3\nmax_connected = 0\n").unwrap();
        assert_eq!((c.session.pipeline_threads, c.session.max_connected), (3, 0));
    }

    /// Values the server would take and then panic on, spin on or allocate without
    /// bound at run time (a `Duration` beyond 2^64 s, a semaphore beyond tokio's
    /// permits, a keepalive deadline of now, a pose-graph thread woken every
    /// nanosecond, a 34 GB pyramid, a dense Hessian of every keyframe, NaN flow):
    /// each is refused at start-up by its key.
    #[test]
    fn values_that_would_break_at_run_time_are_refused_at_start() {
        let err = |toml: &str| ServerConfig::from_toml(toml).expect_err(toml).to_string();
        assert_eq!(
            err("[limits]\nframe_cpu_ms = 1e30\n"),
            "invalid configuration: limits.frame_cpu_ms must be 0 (no budget) or a number of milliseconds up to 3600000, and limits.frame_cpu_strikes at least 1; got 1000000000000000000000000000000 and 3"
        );
        assert_eq!(
            err("[session]\nresult_buffer = 4611686018427387904\n"),
            "invalid configuration: session.result_buffer must be within 1..=65536, got 4611686018427387904"
        );
        assert!(err("[http]\nmax_connections = 4611686018427387904\n").contains("http.max_connections within 1..=1048576"));
        assert!(err("[http]\nworker_threads = 100000\n").contains("http.worker_threads must be within 1..=1024"));
        assert!(
            err("[session]\ntrajectory_in_memory = 10\n")
                .contains("session.trajectory_in_memory must be 0 (every pose) or at least 100 poses, got 10")
        );
        assert_eq!(ServerConfig::from_toml("[session]\ntrajectory_in_memory = 0\n").expect("every pose").session.trajectory_in_memory, 0);
        for toml in [
            "[grpc]\nkeepalive_timeout_s = 0\n",
            "[grpc]\nkeepalive_interval_s = 0\n",
            "[grpc]\nkeepalive_interval_s = 9223372036854775807\n",
        ] {
            assert!(
                err(toml).contains("grpc.keepalive_interval_s must be within 1..=86400 and grpc.keepalive_timeout_s within 1..=3600"),
                "{toml}"
            );
        }
        assert!(err("[fleet]\ngraph_interval_s = 1e-9\n").contains("fleet.graph_interval_s must be 0 (off) or within 0.05..=3600"));
        assert_eq!(ServerConfig::from_toml("[fleet]\ngraph_interval_s = 0.0\n").expect("off").fleet.graph_interval_s, 0.0);
        assert!(err("[fleet]\nmax_places = 4611686018427387904\n").contains("fleet.max_places in 1..=1000000"));
        assert!(err("[store]\nimport_max_bytes = 1099511627776\n").contains("store.import_max_bytes must be within 1024..=4294967296"));
        // The algorithms' own keys, checked by their crates.
        for (toml, message) in [
            ("[tracking]\npyramid_levels = 4000000000\n", "tracking.pyramid_levels within 1..=16"),
            ("[tracking]\nscale_factor = inf\n", "tracking.scale_factor must be within (1, 2]"),
            (
                "[tracking]\npyramid_levels = 16\nscale_factor = 2.0\n",
                "tracking.scale_factor^(tracking.pyramid_levels - 1) must be at most 32",
            ),
            ("[tracking]\nba_window = 1000000000\n", "tracking.ba_window must be within 0..=64"),
            ("[tracking]\nba_iterations = 4294967295\n", "tracking.ba_iterations within 1..=100"),
            ("[tracking]\ndepth_edge_ratio = -1.0\n", "tracking.depth_edge_ratio must be within [0, 1]"),
            (
                "[tracking]\nlocal_map_search_radius_px = nan\n",
                "tracking.motion_search_radius_px and tracking.local_map_search_radius_px must be within (0, 200] pixels",
            ),
            ("[tracking]\nkeyframe_tracked_ratio = nan\n", "tracking.keyframe_tracked_ratio must be within [0, 1]"),
            ("[tracking]\nmax_descriptor_distance = 300\n", "tracking.max_descriptor_distance within 0..=256"),
            ("[tracking]\nfast_threshold = 300\n", "tracking.fast_threshold must be within 1..=254"),
            ("[perception.flow]\niterations = 2147483647\n", "iterations within 1..=20"),
            ("[perception.flow]\npoly_sigma = nan\n", "perception.flow.poly_sigma must be within (0, 5]"),
            ("[perception.segmentation]\nworkers = 100000\n", "perception.segmentation.workers must be within 1..=64"),
            ("[perception.segmentation]\nintra_threads = 4294967298\n", "perception.segmentation.intra_threads must be within 0..=1024"),
            ("[mapping]\npixel_stride = 4294967296\n", "pixel_stride must be within 1..=16"),
            ("[mapping]\nmax_depth_m = inf\n", "need 0 <= min_depth_m < max_depth_m <= 20"),
            ("[mapping]\noccupancy_min_height_m = nan\n", "occupancy_min_height_m and occupancy_max_height_m must be finite"),
            ("[mapping]\noccupancy_resolution_m = 5.0\n", "occupancy_resolution_m must be within voxel_size_m..=1"),
            ("[mapping]\nfallback_up_in_camera = [inf, 0.0, 0.0]\n", "fallback_up_in_camera must be finite"),
            ("[mapping]\nfallback_up_in_camera = [0.0, 0.0, 0.0]\n", "fallback_up_in_camera must be finite"),
            ("[mapping]\ncarve_sigmas = inf\n", "carve_sigmas must be within (0, 100]"),
            ("[mapping]\nrefuse_translation_m = nan\n", "refuse_translation_m and refuse_rotation_deg must be finite and at least 0"),
            ("[mapping]\nobjects_min_confidence = nan\n", "objects_min_confidence must be within [0, 1]"),
            ("[mapping]\ntiles_max_height_m = nan\n", "tiles_max_height_m must be finite"),
        ] {
            assert!(err(toml).contains(message), "{toml}: {}", err(toml));
        }
    }
}
