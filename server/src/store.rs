//! The embedded store (redb): sessions, their trajectories, keyframes and map
//! blocks, so that a restart keeps everything.
//!
//! **Why redb:** pure Rust (no C library to build), ACID transactions on
//! copy-on-write B-trees, and a commit that survives `kill -9` or power loss
//! once it returns (fsync'd, `Durability::Immediate`). SQLite would serve equally
//! but brings a C build and an SQL layer this key-value data does not need.
//!
//! **What is committed when.** A session's description and camera when it opens;
//! then, in one transaction per keyframe: the poses since the previous keyframe,
//! the keyframe (pose, keypoints, descriptors), every map block changed since the
//! previous commit and every block evicted from memory. A crash therefore loses
//! at most the frames after the last keyframe. Commits run on the session's
//! worker: they happen once per keyframe and a block read back later (the
//! camera returning) always sees its latest version.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use prost::Message;
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use serde::{Deserialize, Serialize};
use stillmap_mapping::voxel::{Block, BlockKey};
use stillmap_proto::pb;

const SESSIONS: TableDefinition<&str, &[u8]> = TableDefinition::new("sessions");
const CAMERAS: TableDefinition<&str, &[u8]> = TableDefinition::new("cameras");
const POSES: TableDefinition<(&str, u64), &[u8]> = TableDefinition::new("poses");
const KEYFRAMES: TableDefinition<(&str, u64), &[u8]> = TableDefinition::new("keyframes");
const BLOCKS: TableDefinition<(&str, i32, i32, i32), &[u8]> = TableDefinition::new("map_blocks");
/// Session id → its frame in its fleet (JSON [`FleetFrame`]), once anchored or merged.
const FLEET_FRAMES: TableDefinition<&str, &[u8]> = TableDefinition::new("fleet_frames");
const FLEET_GRAPHS: TableDefinition<&str, &[u8]> = TableDefinition::new("fleet_graphs");
/// Fleet name → what its fused map holds (JSON [`FleetMapHead`]).
const FLEET_MAPS: TableDefinition<&str, &[u8]> = TableDefinition::new("fleet_maps");
/// The fused fleet maps' blocks, by fleet name and block key.
const FLEET_MAP_BLOCKS: TableDefinition<(&str, i32, i32, i32), &[u8]> = TableDefinition::new("fleet_map_blocks");

/// redb's page cache unless `store.cache_bytes` says otherwise.
pub const DEFAULT_CACHE_BYTES: usize = 64 << 20;

/// zstd level for map blocks: most voxels are empty, level 1 already gives ~10×.
const BLOCK_ZSTD_LEVEL: i32 = 1;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("store {path}: {message}")]
    Db { path: String, message: String },
    #[error("store holds corrupt data: {0}")]
    Corrupt(String),
    /// A map file given to import.
    #[error("bad map file: {0}")]
    File(String),
}

/// What the store knows about a session beyond its camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionMeta {
    pub robot_id: String,
    pub transport: String,
    pub started_unix_ns: u64,
    pub class_names: Vec<String>,
    /// The map's frozen up direction (world frame) and where it came from.
    pub up_in_world: Option<[f64; 3]>,
    pub up_source: Option<String>,
    pub keyframes: u64,
    /// The map's keyframe stamp at the last commit.
    pub map_stamp: u64,
    /// The fleet the robot's hello named (empty in stores older than fleets: the default fleet).
    #[serde(default)]
    pub fleet: String,
}

/// A session's frame in its fleet: the anchor's is the identity; a merged
/// session's comes from place recognition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FleetFrame {
    pub fleet: String,
    /// tx, ty, tz, qx, qy, qz, qw of `fleet_from_session`.
    pub fleet_from_session: [f64; 7],
    /// The session whose frame is the fleet's.
    pub anchor: bool,
    /// Agreeing verified keyframes behind the merge, and the chosen one's inliers (0 for the anchor).
    pub support: usize,
    pub inliers: usize,
    /// When the frame was last set (a merge or a refinement of it).
    pub merged_unix_ns: u64,
    /// When the session was first merged, and how far into its keyframes (capture
    /// time since its first keyframe) that was (0 for the anchor).
    #[serde(default)]
    pub first_merged_unix_ns: u64,
    #[serde(default)]
    pub merged_after_ns: u64,
    /// The session whose world the fleet frame is (its anchor, on whichever server
    /// anchored it): two frames with the same lineage are in one frame, so a session
    /// resumed on another server brings its merge along (empty: written before it
    /// was recorded; an anchor's own id then).
    #[serde(default)]
    pub lineage: String,
}

impl FleetFrame {
    /// The anchor whose world this frame is in (see [`lineage`](Self::lineage)):
    /// `session_id`'s own when it is the anchor and nothing else is recorded.
    pub fn lineage_of(&self, session_id: &str) -> String {
        if self.lineage.is_empty() && self.anchor { session_id.to_string() } else { self.lineage.clone() }
    }
}

/// A fleet's pose graph as its last solve left it: the place edges (so a solve
/// after a restart keeps them), every merged session's keyframe corrections and
/// the solve's summary.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct FleetGraph {
    pub edges: Vec<GraphEdge>,
    /// Per session id: (keyframe capture time, tx, ty, tz, qx, qy, qz, qw of
    /// `fleet_corrected_from_fleet`), in time order.
    pub corrections: std::collections::BTreeMap<String, Vec<(u64, [f64; 7])>>,
    pub last_solve: Option<GraphSolve>,
}

/// What a fleet's fused map (`crate::fleet_map`) holds, saved with its blocks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FleetMapHead {
    /// The map's voxel size: blocks of another size are not this server's map.
    pub voxel_size_m: f64,
    /// The map's change stamp when it was saved.
    pub change_stamp: u64,
    /// Keyframes fused in it, per session id.
    pub fused: std::collections::BTreeMap<String, u64>,
}

/// What a fleet's pose-graph solve did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraphSolve {
    pub solved_unix_ns: u64,
    pub keyframes: usize,
    pub odometry_edges: usize,
    pub loop_edges: usize,
    pub inter_session_edges: usize,
    /// Keyframes the solve put more than 1 cm or 0.5° from where their merge put them.
    pub moved_keyframes: usize,
    pub max_translation_m: f64,
    pub max_rotation_deg: f64,
    pub solve_ms: f64,
}

/// A verified match between two keyframes (session id, keyframe id): `a_from_b`
/// (tx, ty, tz, qx, qy, qz, qw) is b's camera in a's camera frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraphEdge {
    pub a: (String, u64),
    pub b: (String, u64),
    pub a_from_b: [f64; 7],
    /// Within one session.
    pub is_loop: bool,
}

/// A session's share of its fleet's pose graph, carried with it to a server that
/// resumes it (through the shared storage).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SessionGraph {
    /// (keyframe capture time, tx, ty, tz, qx, qy, qz, qw of
    /// `fleet_corrected_from_fleet`), in time order.
    pub corrections: Vec<(u64, [f64; 7])>,
    /// The place edges with one of its keyframes at either end.
    pub edges: Vec<GraphEdge>,
    /// When the solve that wrote it finished (Unix ns).
    #[serde(default)]
    pub solved_unix_ns: u64,
}

/// A keyframe as stored: pose, keypoints and descriptors (for relocalization
/// against an archived map).
#[derive(Debug, Clone, PartialEq)]
pub struct KeyframeRecord {
    pub id: u64,
    /// The keyframe's frame timestamp (`capture_time_ns`; its pose refers to that
    /// plus the session's `exposure_time_offset_s`).
    pub timestamp_ns: u64,
    /// tx, ty, tz, qx, qy, qz, qw of `world_from_camera`.
    pub world_from_camera: [f64; 7],
    /// Raw pixel x, y, octave, depth in metres (NaN: none), descriptor.
    pub features: Vec<([f32; 2], u8, f32, [u64; 4])>,
}

impl KeyframeRecord {
    fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(8 * 9 + 4 + self.features.len() * 45);
        out.extend_from_slice(&self.id.to_le_bytes());
        out.extend_from_slice(&self.timestamp_ns.to_le_bytes());
        for v in self.world_from_camera {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&(self.features.len() as u32).to_le_bytes());
        for (xy, octave, depth, d) in &self.features {
            out.extend_from_slice(&xy[0].to_le_bytes());
            out.extend_from_slice(&xy[1].to_le_bytes());
            out.push(*octave);
            out.extend_from_slice(&depth.to_le_bytes());
            for w in d {
                out.extend_from_slice(&w.to_le_bytes());
            }
        }
        out
    }

    pub(crate) fn from_bytes(b: &[u8]) -> Result<Self, StoreError> {
        let bad = || StoreError::Corrupt(format!("keyframe record of {} bytes", b.len()));
        let u64_at = |o: usize| b.get(o..o + 8).map(|s| u64::from_le_bytes(s.try_into().expect("8 bytes")));
        let f32_at = |o: usize| b.get(o..o + 4).map(|s| f32::from_le_bytes(s.try_into().expect("4 bytes")));
        let id = u64_at(0).ok_or_else(bad)?;
        let timestamp_ns = u64_at(8).ok_or_else(bad)?;
        let mut pose = [0.0; 7];
        for (i, p) in pose.iter_mut().enumerate() {
            *p = f64::from_bits(u64_at(16 + 8 * i).ok_or_else(bad)?);
        }
        let n = b.get(72..76).map(|s| u32::from_le_bytes(s.try_into().expect("4 bytes"))).ok_or_else(bad)? as usize;
        if b.len() != 76 + n * 45 {
            return Err(bad());
        }
        let features = (0..n)
            .map(|k| {
                let o = 76 + k * 45;
                let d =
                    [u64_at(o + 13).unwrap_or(0), u64_at(o + 21).unwrap_or(0), u64_at(o + 29).unwrap_or(0), u64_at(o + 37).unwrap_or(0)];
                ([f32_at(o).unwrap_or(0.0), f32_at(o + 4).unwrap_or(0.0)], b[o + 8], f32_at(o + 9).unwrap_or(f32::NAN), d)
            })
            .collect();
        Ok(Self { id, timestamp_ns, world_from_camera: pose, features })
    }
}

/// One keyframe's transaction.
pub struct Commit<'a> {
    pub session_id: &'a str,
    pub meta: &'a SessionMeta,
    pub poses: &'a [pb::PoseStamped],
    /// The place of `poses[0]` in the session's trajectory: poses are stored by
    /// their place (the order they came), not by the robot's sequence number,
    /// which starts again when a robot's timeline is taken again.
    pub first_pose: u64,
    /// Keyframes not committed yet (a failed commit's come again with the next).
    pub keyframes: &'a [KeyframeRecord],
    /// The session's camera, when the session was not recorded yet.
    pub camera: Option<&'a pb::CameraInfo>,
    pub blocks: Vec<(BlockKey, &'a Block)>,
    pub evicted: &'a [(BlockKey, Block)],
}

/// The next pose's place once a pose is stored at `key`: places are counted from 0,
/// and a key beyond 2⁶² is a robot's sequence number (stores before 2026-12-07 kept
/// poses by it), after which no place is taken (the count would run out).
pub(crate) fn next_place_after(next: u64, key: u64) -> u64 {
    if key < 1 << 62 { next.max(key + 1) } else { next }
}

/// Map blocks as stored: key and zstd-compressed bytes.
type CompressedBlocks = Vec<(BlockKey, Vec<u8>)>;

/// Everything stored about one session.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredSession {
    pub id: String,
    pub meta: SessionMeta,
    pub camera: pb::CameraInfo,
    pub poses: Vec<pb::PoseStamped>,
    /// The place the session's next pose is stored at: after the last stored one
    /// (more than the count where places are missing: a copy dropped, or a store
    /// that kept poses by the robot's sequence numbers).
    pub next_pose_place: u64,
    pub keyframes: Vec<KeyframeRecord>,
    pub blocks: Vec<(BlockKey, Block)>,
}

/// What [`Store::heads`] reads of a stored session.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionHead {
    pub id: String,
    pub meta: SessionMeta,
    pub camera: pb::CameraInfo,
    /// Poses stored, and the latest of them.
    pub pose_count: usize,
    pub latest: Option<pb::PoseStamped>,
    /// Empty from [`Store::heads`]; an imported session's, for its fleet.
    pub keyframes: Vec<KeyframeRecord>,
}

/// The store: a redb file. A failed write (a full disk, an I/O error) marks it
/// failing until a write succeeds again: [`Store::failing`] says since when and
/// why (`/healthz` answers 503), every failure is counted
/// (`stillmap_store_errors_total`), and writes are retried with backoff, the
/// file reopened first (redb refuses every operation after an I/O error until it
/// is). What a failed commit held stays in memory and goes with the next one.
pub struct Store {
    db: RwLock<Option<Arc<Database>>>,
    path: PathBuf,
    health: Mutex<Health>,
    errors: prometheus_client::metrics::counter::Counter,
    /// Longest backoff between write attempts while failing.
    retry_max: Duration,
    /// Opens the database (the file; a test's failing backend).
    opener: Box<dyn Fn() -> Result<Database, String> + Send + Sync>,
    /// Every commit is copied there too (`store.replica_url`, PostgreSQL).
    replica: Option<Arc<crate::replica::Replica>>,
}

/// Backoff between reopening attempts after a failed write: doubling from
/// `STORE_RETRY_MIN` up to `store.retry_max_s`.
const STORE_RETRY_MIN: Duration = Duration::from_secs(1);

#[derive(Debug, Default)]
struct Health {
    /// Since when writes fail, and the latest error.
    failing: Option<(u64, String)>,
    /// When the next write may try again (reopening the file first).
    retry_at: Option<Instant>,
    backoff: Duration,
}

/// Why the store is failing, for `/healthz`.
#[derive(Debug, Clone, PartialEq)]
pub struct Failing {
    pub since_unix_ns: u64,
    pub error: String,
}

impl Store {
    /// Opens (or creates) the store file, creating its folder.
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        Self::open_with_cache(path, DEFAULT_CACHE_BYTES)
    }

    /// [`open`](Self::open) with redb's page cache bounded to `cache_bytes`
    /// (`store.cache_bytes`; redb's own default is 1 GiB, which a long-running
    /// server fills as the store grows).
    pub fn open_with_cache(path: &Path, cache_bytes: usize) -> Result<Self, StoreError> {
        let err = |e: &dyn std::fmt::Display| StoreError::Db { path: path.display().to_string(), message: e.to_string() };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| err(&e))?;
        }
        let file = path.to_path_buf();
        Self::with_opener(path, Box::new(move || redb::Builder::new().set_cache_size(cache_bytes).create(&file).map_err(|e| e.to_string())))
    }

    /// A store whose database `opener` opens (again after a failure).
    fn with_opener(path: &Path, opener: Box<dyn Fn() -> Result<Database, String> + Send + Sync>) -> Result<Self, StoreError> {
        let err = |e: &dyn std::fmt::Display| StoreError::Db { path: path.display().to_string(), message: e.to_string() };
        let db = opener().map_err(|e| err(&e))?;
        // Create the tables so that reads of an empty store find them.
        let tx = db.begin_write().map_err(|e| err(&e))?;
        {
            tx.open_table(SESSIONS).map_err(|e| err(&e))?;
            tx.open_table(CAMERAS).map_err(|e| err(&e))?;
            tx.open_table(POSES).map_err(|e| err(&e))?;
            tx.open_table(KEYFRAMES).map_err(|e| err(&e))?;
            tx.open_table(BLOCKS).map_err(|e| err(&e))?;
            tx.open_table(FLEET_FRAMES).map_err(|e| err(&e))?;
            tx.open_table(FLEET_GRAPHS).map_err(|e| err(&e))?;
        }
        tx.commit().map_err(|e| err(&e))?;
        Ok(Self {
            db: RwLock::new(Some(Arc::new(db))),
            path: path.to_path_buf(),
            health: Mutex::default(),
            errors: Default::default(),
            retry_max: Duration::from_secs(60),
            replica: None,
            opener,
        })
    }

    /// Counts store errors in `counter` (the server's `stillmap_store_errors_total`).
    pub fn count_errors_in(self, counter: prometheus_client::metrics::counter::Counter) -> Self {
        Self { errors: counter, ..self }
    }

    /// Copies every commit to `replica` too (storage shared by several servers).
    pub fn replicate_to(self, replica: Arc<crate::replica::Replica>) -> Self {
        Self { replica: Some(replica), ..self }
    }

    /// The replica commits are copied to, if any.
    pub fn replica(&self) -> Option<&Arc<crate::replica::Replica>> {
        self.replica.as_ref()
    }

    /// Sets the longest backoff between write attempts while failing (`store.retry_max_s`).
    pub fn retry_at_most_every(self, retry_max: Duration) -> Self {
        Self { retry_max, ..self }
    }

    /// Since when and why writes fail; `None` while the store is healthy.
    pub fn failing(&self) -> Option<Failing> {
        crate::lock(&self.health).failing.as_ref().map(|(since, error)| Failing { since_unix_ns: *since, error: error.clone() })
    }

    /// Store errors so far.
    pub fn errors(&self) -> u64 {
        self.errors.get()
    }

    /// The database for a read.
    fn db(&self) -> Result<Arc<Database>, StoreError> {
        crate::read(&self.db).clone().ok_or_else(|| self.err("closed after an error; reopening"))
    }

    /// The database for a write: while failing, refused until the backoff has
    /// passed; then this writer (one: it claims the retry) reopens the database,
    /// since one that saw an I/O error refuses everything, and tries.
    fn db_for_write(&self) -> Result<Arc<Database>, StoreError> {
        let retry = {
            let mut h = crate::lock(&self.health);
            match (&h.failing, h.retry_at) {
                (Some((_, error)), Some(at)) if Instant::now() < at => {
                    return Err(StoreError::Db {
                        path: self.path.display().to_string(),
                        message: format!(
                            "failing, next try in {:.1} s: {error}",
                            at.saturating_duration_since(Instant::now()).as_secs_f64()
                        ),
                    });
                }
                (Some(_), _) => {
                    // Claimed: other writers wait for this one's outcome.
                    let backoff = h.backoff;
                    h.retry_at = Some(Instant::now() + backoff);
                    true
                }
                (None, _) => false,
            }
        };
        if retry {
            let mut slot = crate::write(&self.db);
            // Ours must be dropped before the file can be opened again (readers
            // still holding it make the reopening fail, and the backoff retries).
            slot.take();
            match (self.opener)() {
                Ok(db) => *slot = Some(Arc::new(db)),
                Err(e) => {
                    drop(slot);
                    let e = self.err(format!("reopening: {e}"));
                    self.failed(&e);
                    return Err(e);
                }
            }
        }
        self.db()
    }

    /// A write's outcome: a success makes the store healthy again, a failure marks
    /// it failing (reads that fail are counted, never marked).
    fn written<T>(&self, outcome: Result<T, StoreError>) -> Result<T, StoreError> {
        match &outcome {
            Ok(_) => {
                let mut h = crate::lock(&self.health);
                if h.failing.take().is_some() {
                    tracing::info!(path = %self.path.display(), "the store takes writes again");
                }
                *h = Health::default();
            }
            Err(e) => self.failed(e),
        }
        outcome
    }

    /// Marks the store failing with `e`, and pushes the next write attempt back
    /// (1 s doubling to `store.retry_max_s`).
    fn failed(&self, e: &StoreError) {
        let message = match e {
            StoreError::Db { message, .. } => message.clone(),
            other => other.to_string(),
        };
        let mut h = crate::lock(&self.health);
        let now = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64);
        if h.failing.is_none() {
            tracing::error!(path = %self.path.display(), "the store fails: {message}");
        }
        let since = h.failing.as_ref().map_or(now, |(since, _)| *since);
        h.failing = Some((since, message));
        h.backoff = if h.backoff.is_zero() { STORE_RETRY_MIN.min(self.retry_max) } else { (h.backoff * 2).min(self.retry_max) };
        h.retry_at = Some(Instant::now() + h.backoff);
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// A database error, counted (`stillmap_store_errors_total`).
    fn err(&self, e: impl std::fmt::Display) -> StoreError {
        self.errors.inc();
        StoreError::Db { path: self.path.display().to_string(), message: e.to_string() }
    }

    /// Records a new session (before any frame); the shared storage, if any, also
    /// keeps a hash of its resume secret (empty: none), so that another server can
    /// resume it.
    pub fn put_session(&self, id: &str, meta: &SessionMeta, camera: &pb::CameraInfo, resume_secret: &str) -> Result<(), StoreError> {
        // Later commits carry the hash even when this write fails here.
        if let Some(replica) = &self.replica
            && !resume_secret.is_empty()
        {
            replica.remember(id, crate::replica::secret_hash(resume_secret));
        }
        let db = self.db_for_write()?;
        let json = serde_json::to_vec(meta).map_err(|e| self.err(e))?;
        self.written((|| {
            let tx = db.begin_write().map_err(|e| self.err(e))?;
            {
                tx.open_table(SESSIONS).map_err(|e| self.err(e))?.insert(id, json.as_slice()).map_err(|e| self.err(e))?;
                tx.open_table(CAMERAS).map_err(|e| self.err(e))?.insert(id, camera.encode_to_vec().as_slice()).map_err(|e| self.err(e))?;
            }
            tx.commit().map_err(|e| self.err(e))
        })())?;
        if let Some(replica) = &self.replica {
            let camera = Some(camera.encode_to_vec());
            let resume_secret_sha256 = (!resume_secret.is_empty()).then(|| crate::replica::secret_hash(resume_secret));
            replica.submit(crate::replica::ReplicaCommit {
                session_id: id.to_string(),
                meta_json: json,
                camera,
                resume_secret_sha256,
                ..Default::default()
            });
        }
        Ok(())
    }

    /// Records a session's frame in its fleet (its anchoring or its merge).
    pub fn put_fleet_frame(&self, id: &str, frame: &FleetFrame) -> Result<(), StoreError> {
        // The shared storage carries it to a server that resumes the session.
        if let Some(replica) = &self.replica
            && let Ok(json) = serde_json::to_vec(frame)
        {
            replica.fleet_frame(id, json);
        }
        self.put_json(FLEET_FRAMES, id, frame)
    }

    /// Records a fleet's pose graph after a solve.
    pub fn put_fleet_graph(&self, fleet: &str, graph: &FleetGraph) -> Result<(), StoreError> {
        self.put_json(FLEET_GRAPHS, fleet, graph)
    }

    /// Every fleet's pose graph, by fleet name.
    pub fn fleet_graphs(&self) -> Result<std::collections::HashMap<String, FleetGraph>, StoreError> {
        self.all_json(FLEET_GRAPHS, "pose graph of fleet")
    }

    /// Saves what changed in a fleet's fused map: its head and the blocks changed
    /// since the last save, in one transaction; `replace` first removes every
    /// block stored for the fleet (a map started afresh: another voxel size, or one
    /// the store could not read back).
    pub fn put_fleet_map(&self, fleet: &str, head: &FleetMapHead, blocks: &[(BlockKey, Block)], replace: bool) -> Result<(), StoreError> {
        let json = serde_json::to_vec(head).map_err(|e| self.err(e))?;
        let compressed = blocks
            .iter()
            .map(|(key, block)| Ok((*key, zstd::bulk::compress(&block.to_bytes(), BLOCK_ZSTD_LEVEL).map_err(|e| self.err(e))?)))
            .collect::<Result<Vec<_>, StoreError>>()?;
        let db = self.db_for_write()?;
        self.written((|| {
            let tx = db.begin_write().map_err(|e| self.err(e))?;
            {
                tx.open_table(FLEET_MAPS).map_err(|e| self.err(e))?.insert(fleet, json.as_slice()).map_err(|e| self.err(e))?;
                let mut table = tx.open_table(FLEET_MAP_BLOCKS).map_err(|e| self.err(e))?;
                if replace {
                    table
                        .retain_in((fleet, i32::MIN, i32::MIN, i32::MIN)..=(fleet, i32::MAX, i32::MAX, i32::MAX), |_, _| false)
                        .map_err(|e| self.err(e))?;
                }
                for (key, bytes) in &compressed {
                    table.insert((fleet, key[0], key[1], key[2]), bytes.as_slice()).map_err(|e| self.err(e))?;
                }
            }
            tx.commit().map_err(|e| self.err(e))
        })())
    }

    /// Every saved fleet map: its head and its blocks, by fleet name. A fleet with
    /// a block that does not decode is left out (logged); the others come back.
    #[allow(clippy::type_complexity)]
    pub fn fleet_maps(&self) -> Result<std::collections::HashMap<String, (FleetMapHead, Vec<(BlockKey, Block)>)>, StoreError> {
        let heads: std::collections::HashMap<String, FleetMapHead> = self.all_json(FLEET_MAPS, "fused map of fleet")?;
        let mut out: std::collections::HashMap<String, (FleetMapHead, Vec<(BlockKey, Block)>)> =
            heads.into_iter().map(|(fleet, head)| (fleet, (head, Vec::new()))).collect();
        let tx = self.db()?.begin_read().map_err(|e| self.err(e))?;
        let table = match tx.open_table(FLEET_MAP_BLOCKS) {
            Ok(table) => table,
            Err(redb::TableError::TableDoesNotExist(_)) => return Ok(out),
            Err(e) => return Err(self.err(e)),
        };
        for entry in table.iter().map_err(|e| self.err(e))? {
            let (k, v) = entry.map_err(|e| self.err(e))?;
            let (fleet, x, y, z) = k.value();
            let Some((_, blocks)) = out.get_mut(fleet) else { continue };
            match checked_block_key([x, y, z]).and_then(|key| Ok((key, decode_block(v.value())?))) {
                Ok((key, block)) => blocks.push((key, block)),
                Err(e) => {
                    tracing::error!(fleet, "the stored fused fleet map is left out: {e}");
                    out.remove(fleet);
                }
            }
        }
        Ok(out)
    }

    /// Every session's fleet frame.
    pub fn fleet_frames(&self) -> Result<std::collections::HashMap<String, FleetFrame>, StoreError> {
        self.all_json(FLEET_FRAMES, "fleet frame of")
    }

    /// Writes `value` as JSON under `key` in one transaction.
    fn put_json<T: Serialize>(&self, table: TableDefinition<&str, &[u8]>, key: &str, value: &T) -> Result<(), StoreError> {
        let db = self.db_for_write()?;
        self.written((|| {
            let tx = db.begin_write().map_err(|e| self.err(e))?;
            {
                let json = serde_json::to_vec(value).map_err(|e| self.err(e))?;
                tx.open_table(table).map_err(|e| self.err(e))?.insert(key, json.as_slice()).map_err(|e| self.err(e))?;
            }
            tx.commit().map_err(|e| self.err(e))
        })())
    }

    /// Every JSON value of `table` by key (none when a store older than the table
    /// was opened read-only). A value that does not parse is left out, logged with
    /// `what` and its key: one damaged row costs its own fleet or session, not every
    /// other's (whose state the server would otherwise start afresh and overwrite).
    fn all_json<T: serde::de::DeserializeOwned>(
        &self,
        table: TableDefinition<&str, &[u8]>,
        what: &str,
    ) -> Result<std::collections::HashMap<String, T>, StoreError> {
        let tx = self.db()?.begin_read().map_err(|e| self.err(e))?;
        let table = match tx.open_table(table) {
            Ok(table) => table,
            Err(redb::TableError::TableDoesNotExist(_)) => return Ok(std::collections::HashMap::new()),
            Err(e) => return Err(self.err(e)),
        };
        let mut out = std::collections::HashMap::new();
        for entry in table.iter().map_err(|e| self.err(e))? {
            let (k, v) = entry.map_err(|e| self.err(e))?;
            match serde_json::from_slice::<T>(v.value()) {
                Ok(value) => {
                    out.insert(k.value().to_string(), value);
                }
                Err(e) => tracing::error!(path = %self.path.display(), "the stored {what} {} is left out: {e}", k.value()),
            }
        }
        Ok(out)
    }

    /// One keyframe's worth of state, atomically.
    pub fn commit(&self, c: &Commit<'_>) -> Result<(), StoreError> {
        let db = self.db_for_write()?;
        let (json, blocks) = self.encoded(c)?;
        self.written((|| {
            let tx = db.begin_write().map_err(|e| self.err(e))?;
            self.write(&tx, c, &json, &blocks)?;
            tx.commit().map_err(|e| self.err(e))
        })())?;
        if let Some(replica) = &self.replica {
            replica.submit(crate::replica::ReplicaCommit {
                session_id: c.session_id.to_string(),
                meta_json: json,
                camera: c.camera.map(prost::Message::encode_to_vec),
                poses: c.poses.iter().zip(c.first_pose..).map(|(p, place)| (place, p.encode_to_vec())).collect(),
                keyframes: c.keyframes.iter().map(|k| (k.id, k.to_bytes())).collect(),
                blocks,
                resume_secret_sha256: None,
                fleet_frame: None,
            });
        }
        Ok(())
    }

    /// A commit's description as JSON and its blocks compressed, as stored.
    fn encoded(&self, c: &Commit<'_>) -> Result<(Vec<u8>, CompressedBlocks), StoreError> {
        let mut blocks = Vec::with_capacity(c.blocks.len() + c.evicted.len());
        for (key, block) in c.blocks.iter().map(|(k, b)| (k, *b)).chain(c.evicted.iter().map(|(k, b)| (k, b))) {
            blocks.push((*key, zstd::bulk::compress(&block.to_bytes(), BLOCK_ZSTD_LEVEL).map_err(|e| self.err(e))?));
        }
        Ok((serde_json::to_vec(c.meta).map_err(|e| self.err(e))?, blocks))
    }

    fn write(&self, tx: &redb::WriteTransaction, c: &Commit<'_>, json: &[u8], blocks: &[(BlockKey, Vec<u8>)]) -> Result<(), StoreError> {
        tx.open_table(SESSIONS).map_err(|e| self.err(e))?.insert(c.session_id, json).map_err(|e| self.err(e))?;
        if let Some(camera) = c.camera {
            tx.open_table(CAMERAS)
                .map_err(|e| self.err(e))?
                .insert(c.session_id, camera.encode_to_vec().as_slice())
                .map_err(|e| self.err(e))?;
        }
        let mut poses = tx.open_table(POSES).map_err(|e| self.err(e))?;
        for (p, place) in c.poses.iter().zip(c.first_pose..) {
            poses.insert((c.session_id, place), p.encode_to_vec().as_slice()).map_err(|e| self.err(e))?;
        }
        if !c.keyframes.is_empty() {
            let mut table = tx.open_table(KEYFRAMES).map_err(|e| self.err(e))?;
            for k in c.keyframes {
                table.insert((c.session_id, k.id), k.to_bytes().as_slice()).map_err(|e| self.err(e))?;
            }
        }
        let mut table = tx.open_table(BLOCKS).map_err(|e| self.err(e))?;
        for (key, bytes) in blocks {
            table.insert((c.session_id, key[0], key[1], key[2]), bytes.as_slice()).map_err(|e| self.err(e))?;
        }
        Ok(())
    }

    /// One stored block (an evicted block coming back).
    pub fn block(&self, session_id: &str, key: BlockKey) -> Result<Option<Block>, StoreError> {
        let tx = self.db()?.begin_read().map_err(|e| self.err(e))?;
        let table = tx.open_table(BLOCKS).map_err(|e| self.err(e))?;
        let Some(v) = table.get((session_id, key[0], key[1], key[2])).map_err(|e| self.err(e))? else {
            return Ok(None);
        };
        decode_block(v.value()).map(Some)
    }

    /// Overwrites a stored map block with `bytes` (a damaged block, for tests).
    #[cfg(test)]
    pub(crate) fn put_raw_block(&self, session_id: &str, key: BlockKey, bytes: &[u8]) -> Result<(), StoreError> {
        let tx = self.db()?.begin_write().map_err(|e| self.err(e))?;
        tx.open_table(BLOCKS).map_err(|e| self.err(e))?.insert((session_id, key[0], key[1], key[2]), bytes).map_err(|e| self.err(e))?;
        tx.commit().map_err(|e| self.err(e))
    }

    /// Calls `f` with the first `n` stored poses of session `id`, in the order
    /// they came (one read transaction; nothing is collected here); returns how
    /// many there were.
    pub fn first_poses(&self, id: &str, n: usize, mut f: impl FnMut(pb::PoseStamped)) -> Result<usize, StoreError> {
        let tx = self.db()?.begin_read().map_err(|e| self.err(e))?;
        let poses = tx.open_table(POSES).map_err(|e| self.err(e))?;
        let mut read = 0;
        for p in poses.range((id, 0)..=(id, u64::MAX)).map_err(|e| self.err(e))?.take(n) {
            let (_, v) = p.map_err(|e| self.err(e))?;
            f(pb::PoseStamped::decode(v.value()).map_err(|e| StoreError::Corrupt(format!("session {id} pose: {e}")))?);
            read += 1;
        }
        Ok(read)
    }

    /// What the server keeps of every stored session while it is not in memory:
    /// description, camera, pose count and latest pose. No map block and no keyframe
    /// record is read (place recognition reads what it can hold with
    /// [`Store::newest_keyframes`]), and of the poses only the latest is decoded
    /// (the others are counted, key by key): start-up memory stays small however
    /// much the store holds (a robot's hour is about 20,000 keyframe records of
    /// 45 KB and 100,000 poses).
    pub fn heads(&self) -> Result<Vec<SessionHead>, StoreError> {
        let tx = self.db()?.begin_read().map_err(|e| self.err(e))?;
        let sessions = tx.open_table(SESSIONS).map_err(|e| self.err(e))?;
        let cameras = tx.open_table(CAMERAS).map_err(|e| self.err(e))?;
        let poses = tx.open_table(POSES).map_err(|e| self.err(e))?;
        let mut out = Vec::new();
        for entry in sessions.iter().map_err(|e| self.err(e))? {
            let (id, meta) = entry.map_err(|e| self.err(e))?;
            let id = id.value().to_string();
            let meta: SessionMeta = serde_json::from_slice(meta.value()).map_err(|e| StoreError::Corrupt(format!("session {id}: {e}")))?;
            let camera = cameras
                .get(id.as_str())
                .map_err(|e| self.err(e))?
                .ok_or_else(|| StoreError::Corrupt(format!("session {id} has no camera")))?;
            let camera = pb::CameraInfo::decode(camera.value()).map_err(|e| StoreError::Corrupt(format!("session {id} camera: {e}")))?;
            let range = (id.as_str(), 0)..=(id.as_str(), u64::MAX);
            let (mut pose_count, mut last) = (0, None);
            for p in poses.range(range).map_err(|e| self.err(e))? {
                pose_count += 1;
                last = Some(p.map_err(|e| self.err(e))?.1);
            }
            let latest = match last {
                Some(v) => Some(pb::PoseStamped::decode(v.value()).map_err(|e| StoreError::Corrupt(format!("session {id} pose: {e}")))?),
                None => None,
            };
            out.push(SessionHead { id, meta, camera, pose_count, latest, keyframes: Vec::new() });
        }
        Ok(out)
    }

    /// The newest `n` keyframe records of session `id`, oldest first.
    pub fn newest_keyframes(&self, id: &str, n: usize) -> Result<Vec<KeyframeRecord>, StoreError> {
        let tx = self.db()?.begin_read().map_err(|e| self.err(e))?;
        self.newest_records(&tx.open_table(KEYFRAMES).map_err(|e| self.err(e))?, id, n)
    }

    /// [`Store::newest_keyframes`] from an open keyframe table.
    fn newest_records(
        &self,
        table: &redb::ReadOnlyTable<(&str, u64), &[u8]>,
        id: &str,
        n: usize,
    ) -> Result<Vec<KeyframeRecord>, StoreError> {
        let mut out = Vec::new();
        for k in table.range((id, 0)..=(id, u64::MAX)).map_err(|e| self.err(e))?.rev().take(n) {
            out.push(KeyframeRecord::from_bytes(k.map_err(|e| self.err(e))?.1.value())?);
        }
        out.reverse();
        Ok(out)
    }

    /// One stored session, everything committed about it (an export).
    pub fn load(&self, id: &str) -> Result<Option<StoredSession>, StoreError> {
        self.load_with(id, usize::MAX)
    }

    /// One stored session with only its newest `keyframes` keyframe records (its
    /// poses and map blocks all): what a query or a resume needs of a session that
    /// ran for hours, whose keyframes (about 45 KB each, 20,000 an hour) would not
    /// fit in memory.
    pub fn load_with(&self, id: &str, keyframes: usize) -> Result<Option<StoredSession>, StoreError> {
        let tx = self.db()?.begin_read().map_err(|e| self.err(e))?;
        let sessions = tx.open_table(SESSIONS).map_err(|e| self.err(e))?;
        let Some(meta) = sessions.get(id).map_err(|e| self.err(e))? else { return Ok(None) };
        let meta: SessionMeta = serde_json::from_slice(meta.value()).map_err(|e| StoreError::Corrupt(format!("session {id}: {e}")))?;
        let cameras = tx.open_table(CAMERAS).map_err(|e| self.err(e))?;
        let poses = tx.open_table(POSES).map_err(|e| self.err(e))?;
        let keyframes_table = tx.open_table(KEYFRAMES).map_err(|e| self.err(e))?;
        let blocks = tx.open_table(BLOCKS).map_err(|e| self.err(e))?;
        let camera = cameras.get(id).map_err(|e| self.err(e))?.ok_or_else(|| StoreError::Corrupt(format!("session {id} has no camera")))?;
        let camera = pb::CameraInfo::decode(camera.value()).map_err(|e| StoreError::Corrupt(format!("session {id} camera: {e}")))?;
        let (mut trajectory, mut next_pose_place) = (Vec::new(), 0);
        for p in poses.range((id, 0)..=(id, u64::MAX)).map_err(|e| self.err(e))? {
            let (k, v) = p.map_err(|e| self.err(e))?;
            next_pose_place = next_place_after(next_pose_place, k.value().1);
            trajectory.push(pb::PoseStamped::decode(v.value()).map_err(|e| StoreError::Corrupt(format!("session {id} pose: {e}")))?);
        }
        let kfs = self.newest_records(&keyframes_table, id, keyframes)?;
        let mut bl = Vec::new();
        for b in blocks.range((id, i32::MIN, i32::MIN, i32::MIN)..=(id, i32::MAX, i32::MAX, i32::MAX)).map_err(|e| self.err(e))? {
            let (k, v) = b.map_err(|e| self.err(e))?;
            let (_, x, y, z) = k.value();
            bl.push((checked_block_key([x, y, z])?, decode_block(v.value())?));
        }
        Ok(Some(StoredSession { id: id.to_string(), meta, camera, poses: trajectory, next_pose_place, keyframes: kfs, blocks: bl }))
    }

    pub fn contains(&self, id: &str) -> Result<bool, StoreError> {
        let tx = self.db()?.begin_read().map_err(|e| self.err(e))?;
        Ok(tx.open_table(SESSIONS).map_err(|e| self.err(e))?.get(id).map_err(|e| self.err(e))?.is_some())
    }

    /// Adds keyframe records of session `id` (a resumed session's older ones, read
    /// back from the shared storage, which holds them already: not copied there).
    pub fn put_keyframes(&self, id: &str, keyframes: &[KeyframeRecord]) -> Result<(), StoreError> {
        let db = self.db_for_write()?;
        self.written((|| {
            let tx = db.begin_write().map_err(|e| self.err(e))?;
            {
                let mut table = tx.open_table(KEYFRAMES).map_err(|e| self.err(e))?;
                for k in keyframes {
                    table.insert((id, k.id), k.to_bytes().as_slice()).map_err(|e| self.err(e))?;
                }
            }
            tx.commit().map_err(|e| self.err(e))
        })())
    }

    /// Writes a whole session (an imported map file) in one transaction.
    pub fn import(&self, s: &StoredSession) -> Result<(), StoreError> {
        let db = self.db_for_write()?;
        self.written((|| {
            let tx = db.begin_write().map_err(|e| self.err(e))?;
            tx.open_table(CAMERAS)
                .map_err(|e| self.err(e))?
                .insert(s.id.as_str(), s.camera.encode_to_vec().as_slice())
                .map_err(|e| self.err(e))?;
            {
                // The copy's poses replace those of an earlier copy (numbered from 0
                // here, or by sequence numbers in an older store).
                let mut poses = tx.open_table(POSES).map_err(|e| self.err(e))?;
                let old: Vec<u64> = poses
                    .range((s.id.as_str(), 0)..=(s.id.as_str(), u64::MAX))
                    .map_err(|e| self.err(e))?
                    .map(|p| p.map(|(k, _)| k.value().1))
                    .collect::<Result<_, _>>()
                    .map_err(|e| self.err(e))?;
                for place in old {
                    poses.remove((s.id.as_str(), place)).map_err(|e| self.err(e))?;
                }
            }
            {
                let mut table = tx.open_table(KEYFRAMES).map_err(|e| self.err(e))?;
                for k in &s.keyframes {
                    table.insert((s.id.as_str(), k.id), k.to_bytes().as_slice()).map_err(|e| self.err(e))?;
                }
            }
            let commit = Commit {
                session_id: &s.id,
                meta: &s.meta,
                poses: &s.poses,
                first_pose: 0,
                keyframes: &[],
                camera: None,
                blocks: s.blocks.iter().map(|(k, b)| (*k, b)).collect(),
                evicted: &[],
            };
            let (json, blocks) = self.encoded(&commit)?;
            self.write(&tx, &commit, &json, &blocks)?;
            tx.commit().map_err(|e| self.err(e))
        })())
    }
}

/// The one-file map format: magic, then zstd of length-prefixed sections.
pub const EXPORT_MAGIC: &[u8] = b"STILLMAP-MAP\0\x01";
/// zstd level of exports (written once, read rarely).
const EXPORT_ZSTD_LEVEL: i32 = 3;
/// Largest section an import accepts (a corrupt length must not allocate wildly).
const MAX_SECTION_BYTES: usize = 1 << 30;

/// A whole session as one file: description, camera, trajectory, keyframes, blocks.
pub fn export(s: &StoredSession) -> Result<Vec<u8>, StoreError> {
    let mut body = Vec::new();
    let section = |bytes: &[u8], body: &mut Vec<u8>| {
        body.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
        body.extend_from_slice(bytes);
    };
    let header =
        serde_json::to_vec(&serde_json::json!({ "session_id": s.id, "meta": s.meta })).map_err(|e| StoreError::Corrupt(e.to_string()))?;
    section(&header, &mut body);
    section(&s.camera.encode_to_vec(), &mut body);
    body.extend_from_slice(&(s.poses.len() as u32).to_le_bytes());
    for p in &s.poses {
        section(&p.encode_to_vec(), &mut body);
    }
    body.extend_from_slice(&(s.keyframes.len() as u32).to_le_bytes());
    for k in &s.keyframes {
        section(&k.to_bytes(), &mut body);
    }
    body.extend_from_slice(&(s.blocks.len() as u32).to_le_bytes());
    for (key, b) in &s.blocks {
        for v in key {
            body.extend_from_slice(&v.to_le_bytes());
        }
        section(&b.to_bytes(), &mut body);
    }
    let mut out = EXPORT_MAGIC.to_vec();
    out.extend(zstd::bulk::compress(&body, EXPORT_ZSTD_LEVEL).map_err(|e| StoreError::Corrupt(e.to_string()))?);
    Ok(out)
}

/// A cursor over an export body; every read is bounds-checked.
struct Reader<'a> {
    body: &'a [u8],
    at: usize,
}

fn file_error(m: impl std::fmt::Display) -> StoreError {
    StoreError::File(m.to_string())
}

impl<'a> Reader<'a> {
    fn u32(&mut self) -> Result<u32, StoreError> {
        let v = self.body.get(self.at..self.at + 4).ok_or_else(|| file_error("truncated"))?;
        self.at += 4;
        Ok(u32::from_le_bytes(v.try_into().expect("4 bytes")))
    }

    fn section(&mut self) -> Result<&'a [u8], StoreError> {
        let n = self.u32()? as usize;
        if n > MAX_SECTION_BYTES {
            return Err(file_error(format!("section of {n} bytes")));
        }
        let v = self.body.get(self.at..self.at + n).ok_or_else(|| file_error("truncated"))?;
        self.at += n;
        Ok(v)
    }
}

/// The body of an export, decompressed without ever holding more than
/// `max_bytes`: a size the frame declares beyond it is refused before decoding,
/// and the streaming decoder stops one byte past it whatever the frame declared.
fn decompress_capped(body: &[u8], max_bytes: usize) -> Result<Vec<u8>, StoreError> {
    use std::io::Read;
    let over = |what: String| file_error(format!("{what}; imports are limited to {max_bytes} bytes uncompressed (store.import_max_bytes)"));
    if let Ok(Some(declared)) = zstd::zstd_safe::get_frame_content_size(body)
        && declared > max_bytes as u64
    {
        return Err(over(format!("the body declares {declared} bytes uncompressed")));
    }
    let decoder = zstd::stream::read::Decoder::new(body).map_err(|e| file_error(format!("compressed body: {e}")))?;
    let mut out = Vec::new();
    decoder.take(max_bytes as u64 + 1).read_to_end(&mut out).map_err(|e| file_error(format!("compressed body: {e}")))?;
    if out.len() > max_bytes {
        return Err(over("the body decompresses to more".into()));
    }
    Ok(out)
}

/// What an import may hold in memory, in multiples of `store.import_max_bytes`: a map
/// block takes 12 KiB in memory however few of its voxels the file holds (a plane
/// through a block, about 1.6 KB in the file, is 8 times that), so a file of empty
/// blocks would take 140 times its size.
pub const IMPORT_MEMORY_FACTOR: usize = 16;

/// A map block in memory: its voxels (boxed) and the rest.
const BLOCK_IN_MEMORY: usize =
    std::mem::size_of::<Block>() + std::mem::size_of::<[stillmap_mapping::voxel::Voxel; stillmap_mapping::voxel::VOXELS_PER_BLOCK]>();

/// A block key read back from this store or the shared storage (a map file's
/// are checked as it is read, `import_file`): within the map's range, as every key the mapper makes is
/// ([`MAX_BLOCK_INDEX`](stillmap_mapping::voxel::MAX_BLOCK_INDEX)); beyond it a
/// voxel's index would overflow.
pub fn checked_block_key(key: BlockKey) -> Result<BlockKey, StoreError> {
    if stillmap_mapping::voxel::block_in_range(key) {
        Ok(key)
    } else {
        Err(StoreError::Corrupt(format!("map block key {key:?} lies outside the map's range")))
    }
}

/// Reads a file [`export`] wrote, decompressing at most `max_bytes`; every problem
/// is named, block keys outside the map's range
/// ([`MAX_BLOCK_INDEX`](stillmap_mapping::voxel::MAX_BLOCK_INDEX)) or repeated are
/// refused, and so is a file whose poses, keyframes and blocks would take more than
/// [`IMPORT_MEMORY_FACTOR`] × `max_bytes` in memory.
pub fn import_file(bytes: &[u8], max_bytes: usize) -> Result<StoredSession, StoreError> {
    let body = bytes.strip_prefix(EXPORT_MAGIC).ok_or_else(|| file_error("not a stillmap map file (bad magic)"))?;
    let body = decompress_capped(body, max_bytes)?;
    let mut r = Reader { body: &body, at: 0 };
    let header: serde_json::Value = serde_json::from_slice(r.section()?).map_err(|e| file_error(format!("header: {e}")))?;
    let id = header["session_id"].as_str().ok_or_else(|| file_error("header has no session_id"))?.to_string();
    stillmap_proto::validate_robot_id(&id).map_err(|e| file_error(format!("session id: {e}")))?;
    let meta: SessionMeta = serde_json::from_value(header["meta"].clone()).map_err(|e| file_error(format!("header: {e}")))?;
    if !meta.fleet.is_empty() {
        stillmap_proto::validate_fleet(&meta.fleet).map_err(|e| file_error(format!("header: {e}")))?;
    }
    let camera = pb::CameraInfo::decode(r.section()?).map_err(|e| file_error(format!("camera: {e}")))?;
    crate::pipeline::decode::validate_camera(Some(&camera)).map_err(|e| file_error(format!("camera: {e}")))?;
    // What the parsed file takes in memory, checked before each item is made.
    let budget = max_bytes.saturating_mul(IMPORT_MEMORY_FACTOR);
    let mut in_memory = 0usize;
    let mut take = |bytes: usize, what: &str| {
        in_memory = in_memory.saturating_add(bytes);
        if in_memory > budget {
            return Err(file_error(format!(
                "its {what} would take more than {budget} bytes in memory ({IMPORT_MEMORY_FACTOR} × store.import_max_bytes)"
            )));
        }
        Ok(())
    };
    let mut poses = Vec::new();
    for _ in 0..r.u32()? {
        take(std::mem::size_of::<pb::PoseStamped>(), "poses")?;
        poses.push(pb::PoseStamped::decode(r.section()?).map_err(|e| file_error(format!("pose: {e}")))?);
    }
    let mut keyframes = Vec::new();
    for _ in 0..r.u32()? {
        let section = r.section()?;
        take(section.len(), "keyframes")?;
        keyframes.push(
            KeyframeRecord::from_bytes(section).map_err(|e| file_error(e.to_string().trim_start_matches("store holds corrupt data: ")))?,
        );
    }
    let mut blocks = Vec::new();
    let mut keys = std::collections::HashSet::new();
    for _ in 0..r.u32()? {
        let key = [r.u32()? as i32, r.u32()? as i32, r.u32()? as i32];
        if !stillmap_mapping::voxel::block_in_range(key) {
            return Err(file_error(format!(
                "map block {key:?} is outside the map's range of ±{} blocks",
                stillmap_mapping::voxel::MAX_BLOCK_INDEX
            )));
        }
        if !keys.insert(key) {
            return Err(file_error(format!("map block {key:?} appears twice")));
        }
        take(BLOCK_IN_MEMORY, "map blocks")?;
        blocks.push((key, Block::from_bytes(r.section()?).map_err(file_error)?));
    }
    if r.at != body.len() {
        return Err(file_error(format!("{} bytes after the last block", body.len() - r.at)));
    }
    let next_pose_place = poses.len() as u64;
    Ok(StoredSession { id, meta, camera, poses, next_pose_place, keyframes, blocks })
}

pub(crate) fn decode_block(bytes: &[u8]) -> Result<Block, StoreError> {
    let raw =
        zstd::bulk::decompress(bytes, stillmap_mapping::voxel::BLOCK_BYTES).map_err(|e| StoreError::Corrupt(format!("map block: {e}")))?;
    Block::from_bytes(&raw).map_err(|e| StoreError::Corrupt(e.to_string()))
}

#[cfg(test)]
impl SessionMeta {
    /// A session of robot `robot_id` over gRPC, started at 1 ns, with nothing mapped.
    pub(crate) fn for_tests(robot_id: &str) -> Self {
        Self {
            robot_id: robot_id.into(),
            transport: "grpc".into(),
            started_unix_ns: 1,
            class_names: Vec::new(),
            up_in_world: None,
            up_source: None,
            keyframes: 0,
            map_stamp: 0,
            fleet: String::new(),
        }
    }
}

/// A store on a disk in memory that can be full (tests of failing writes).
#[cfg(test)]
pub(crate) mod memory_disk {
    use std::path::Path;
    use std::sync::{Arc, RwLock};

    use super::Store;

    /// A disk in memory that can be full: every write fails with ENOSPC while it is.
    #[derive(Debug, Default, Clone)]
    pub(crate) struct Disk {
        bytes: Arc<RwLock<Vec<u8>>>,
        /// While set, every write fails with ENOSPC.
        pub(crate) full: Arc<std::sync::atomic::AtomicBool>,
    }

    impl Disk {
        fn check(&self) -> std::io::Result<()> {
            if self.full.load(std::sync::atomic::Ordering::SeqCst) { Err(std::io::Error::from_raw_os_error(28)) } else { Ok(()) }
        }
    }

    impl redb::StorageBackend for Disk {
        fn len(&self) -> std::io::Result<u64> {
            Ok(self.bytes.read().unwrap().len() as u64)
        }
        fn read(&self, offset: u64, out: &mut [u8]) -> std::io::Result<()> {
            let bytes = self.bytes.read().unwrap();
            let at = offset as usize;
            out.copy_from_slice(bytes.get(at..at + out.len()).ok_or_else(|| std::io::Error::other("read beyond the end"))?);
            Ok(())
        }
        fn set_len(&self, len: u64) -> std::io::Result<()> {
            self.check()?;
            self.bytes.write().unwrap().resize(len as usize, 0);
            Ok(())
        }
        fn sync_data(&self) -> std::io::Result<()> {
            self.check()
        }
        fn write(&self, offset: u64, data: &[u8]) -> std::io::Result<()> {
            self.check()?;
            let mut bytes = self.bytes.write().unwrap();
            let at = offset as usize;
            if bytes.len() < at + data.len() {
                bytes.resize(at + data.len(), 0);
            }
            bytes[at..at + data.len()].copy_from_slice(data);
            Ok(())
        }
    }

    /// A store on `disk`.
    pub(crate) fn store_on(disk: &Disk) -> Store {
        let backend = disk.clone();
        Store::with_opener(
            Path::new("memory"),
            Box::new(move || redb::Builder::new().create_with_backend(backend.clone()).map_err(|e| e.to_string())),
        )
        .expect("a store in memory")
    }
}

#[cfg(test)]
mod tests {
    use super::memory_disk::Disk;
    use super::*;

    #[test]
    fn everything_committed_comes_back() {
        let path = std::env::temp_dir().join(format!("stillmap-store-test-{}.redb", std::process::id()));
        let _ = std::fs::remove_file(&path);
        let meta = SessionMeta {
            robot_id: "r1".into(),
            transport: "grpc".into(),
            started_unix_ns: 5,
            class_names: vec!["person".into()],
            up_in_world: Some([0.0, -1.0, 0.0]),
            up_source: Some("config".into()),
            keyframes: 1,
            map_stamp: 1,
            fleet: "lab".into(),
        };
        let camera = pb::CameraInfo {
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 500.0,
            cx: 319.5,
            cy: 239.5,
            depth_units_per_metre: 1000.0,
            color_encoding: pb::ColorEncoding::Jpeg as i32,
            depth_encoding: pb::DepthEncoding::Zstd as i32,
            ..Default::default()
        };
        let pose = pb::PoseStamped { sequence: 3, capture_time_ns: 9, ..Default::default() };
        let mut block = Block::default();
        block.voxels[7].log_odds = 1.5;
        block.voxels[7].hits = 2;
        let kf = KeyframeRecord {
            id: 0,
            timestamp_ns: 9,
            world_from_camera: [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0],
            features: vec![([1.5, 2.5], 1, f32::NAN, [1, 2, 3, 4]), ([3.0, 4.0], 0, 1.25, [5, 6, 7, 8])],
        };
        {
            let store = Store::open(&path).unwrap();
            store.put_session("s1", &meta, &camera, "").unwrap();
            store
                .commit(&Commit {
                    session_id: "s1",
                    meta: &meta,
                    poses: &[pose],
                    first_pose: 0,
                    keyframes: std::slice::from_ref(&kf),
                    camera: None,
                    blocks: vec![([1, -2, 3], &block)],
                    evicted: &[([9, 9, 9], block.clone())],
                })
                .unwrap();
        }
        let store = Store::open(&path).unwrap();
        let all: Vec<StoredSession> = store.heads().unwrap().iter().map(|h| store.load(&h.id).unwrap().expect("listed")).collect();
        assert_eq!(all.len(), 1);
        let s = &all[0];
        assert_eq!((s.id.as_str(), &s.meta, &s.camera, s.poses.as_slice()), ("s1", &meta, &camera, &[pose][..]));
        assert_eq!(s.next_pose_place, 1);
        assert_eq!(s.keyframes[0].features[1], kf.features[1]);
        assert!(s.keyframes[0].features[0].2.is_nan());
        assert_eq!(s.blocks.len(), 2);
        assert_eq!(s.blocks[0], ([1, -2, 3], block.clone()));
        assert_eq!(store.block("s1", [9, 9, 9]).unwrap(), Some(block));
        assert_eq!(store.block("s1", [0, 0, 0]).unwrap(), None);
        // Heads: no blocks, no trajectory; the count and the latest pose.
        let heads = store.heads().unwrap();
        assert_eq!(
            heads,
            vec![SessionHead {
                id: "s1".into(),
                meta: meta.clone(),
                camera: camera.clone(),
                pose_count: 1,
                latest: Some(pose),
                keyframes: vec![]
            }]
        );
        assert_eq!(store.newest_keyframes("s1", 9).unwrap().len(), 1);
        let frame = FleetFrame {
            fleet: "lab".into(),
            fleet_from_session: [1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0],
            anchor: false,
            support: 3,
            inliers: 120,
            merged_unix_ns: 7,
            first_merged_unix_ns: 5,
            merged_after_ns: 200_000_000,
            lineage: "s0".into(),
        };
        store.put_fleet_frame("s1", &frame).unwrap();
        assert_eq!(store.fleet_frames().unwrap().get("s1"), Some(&frame));
        // One damaged row is left out; the others come back (before, the whole
        // table failed and every fleet started afresh, overwriting its state).
        store.put_json(FLEET_FRAMES, "s0", &"not a frame").unwrap();
        store.put_json(FLEET_GRAPHS, "broken", &[1, 2, 3]).unwrap();
        let frames = store.fleet_frames().unwrap();
        assert_eq!((frames.len(), frames.get("s1")), (1, Some(&frame)));
        assert!(store.fleet_graphs().unwrap().is_empty());
        // The one-file export round-trips exactly, and bad files are named.
        let file = export(s).unwrap();
        let back = import_file(&file, 1 << 20).unwrap();
        // (A NaN depth makes `==` on keyframes false: compare the re-export's bytes.)
        assert!(back.blocks == s.blocks && back.poses == s.poses && back.meta == s.meta && back.camera == s.camera, "import differs");
        assert!(export(&back).unwrap() == file, "re-export differs");
        assert_eq!(import_file(b"PK\x03\x04", 1 << 20).unwrap_err().to_string(), "bad map file: not a stillmap map file (bad magic)");
        // A fleet no robot could name (it would be made a fleet nobody can join,
        // and its name written into headers and URLs).
        let mut named = s.clone();
        named.meta.fleet = "lab\"/x".into();
        assert_eq!(
            import_file(&export(&named).unwrap(), 1 << 20).unwrap_err().to_string(),
            "bad map file: header: fleet \"lab\\\"/x\" contains '\"'; allowed are A-Z a-z 0-9 _ -"
        );
        let mut cut = file.clone();
        cut.truncate(cut.len() - 5);
        assert!(import_file(&cut, 1 << 20).unwrap_err().to_string().starts_with("bad map file: "));
        drop(store);
        let _ = std::fs::remove_file(&path);
    }

    #[test]
    fn a_full_disk_marks_the_store_failing_until_a_retried_write_goes_through() {
        let disk = Disk::default();
        let store = super::memory_disk::store_on(&disk);
        let meta = SessionMeta { keyframes: 1, map_stamp: 1, ..SessionMeta::for_tests("r") };
        let camera = pb::CameraInfo { width: 64, height: 48, fx: 50.0, fy: 50.0, cx: 31.5, cy: 23.5, ..Default::default() };
        store.put_session("s", &meta, &camera, "").unwrap();
        assert_eq!((store.failing(), store.errors()), (None, 0));
        let kf = KeyframeRecord { id: 4, timestamp_ns: 9, world_from_camera: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], features: Vec::new() };
        let pose = pb::PoseStamped { sequence: 7, ..Default::default() };
        let commit = Commit {
            session_id: "s",
            meta: &meta,
            poses: std::slice::from_ref(&pose),
            first_pose: 0,
            keyframes: std::slice::from_ref(&kf),
            camera: None,
            blocks: Vec::new(),
            evicted: &[],
        };

        disk.full.store(true, std::sync::atomic::Ordering::SeqCst);
        let e = store.commit(&commit).unwrap_err().to_string();
        assert!(e.contains("No space left on device"), "{e}");
        let failing = store.failing().expect("failing");
        assert!(failing.error.contains("No space left on device") && failing.since_unix_ns > 0, "{failing:?}");
        assert!(store.errors() >= 1);
        // Within the backoff a write is refused at once, naming the cause.
        let e = store.commit(&commit).unwrap_err().to_string();
        assert!(e.contains("failing, next try in") && e.contains("No space left on device"), "{e}");
        assert_eq!(store.failing().map(|f| f.since_unix_ns), Some(failing.since_unix_ns));
        // Space again: after the backoff the store is reopened and the write goes through.
        disk.full.store(false, std::sync::atomic::Ordering::SeqCst);
        std::thread::sleep(STORE_RETRY_MIN * 2);
        store.commit(&commit).unwrap();
        assert_eq!(store.failing(), None);
        let back = store.load("s").unwrap().expect("session");
        assert_eq!((back.poses, back.keyframes.len()), (vec![pose], 1));
    }

    /// A map file whose body is `body`, compressed declaring its size or not.
    fn map_file(body: &[u8], declare_size: bool) -> Vec<u8> {
        let mut out = EXPORT_MAGIC.to_vec();
        if declare_size {
            out.extend(zstd::bulk::compress(body, 3).unwrap());
        } else {
            let mut e = zstd::stream::write::Encoder::new(Vec::new(), 3).unwrap();
            std::io::Write::write_all(&mut e, body).unwrap();
            out.extend(e.finish().unwrap());
        }
        out
    }

    #[test]
    fn a_decompression_bomb_is_refused_without_being_decompressed() {
        // 64 MiB of zeros compress to a few KB.
        let zeros = vec![0u8; 64 << 20];
        let declared = map_file(&zeros, true);
        assert!(declared.len() < 64 << 10, "{} bytes", declared.len());
        assert_eq!(
            import_file(&declared, 1 << 20).unwrap_err().to_string(),
            "bad map file: the body declares 67108864 bytes uncompressed; imports are limited to 1048576 bytes uncompressed (store.import_max_bytes)"
        );
        // Without a declared size the streaming decoder stops at the cap.
        let undeclared = map_file(&zeros, false);
        assert_eq!(zstd::zstd_safe::get_frame_content_size(&undeclared[EXPORT_MAGIC.len()..]).unwrap(), None);
        assert_eq!(
            import_file(&undeclared, 1 << 20).unwrap_err().to_string(),
            "bad map file: the body decompresses to more; imports are limited to 1048576 bytes uncompressed (store.import_max_bytes)"
        );
    }

    /// Poses are kept by their place in the trajectory: a robot's sequence numbers
    /// starting again overwrite nothing, they come back in the order they came, and
    /// where places are missing (a copy dropped) the next place is after the last.
    #[test]
    fn poses_are_kept_by_their_place_not_the_robots_sequence() {
        let store = memory_disk::store_on(&Disk::default());
        let meta = SessionMeta::for_tests("r");
        let camera = pb::CameraInfo { width: 64, height: 48, ..Default::default() };
        store.put_session("s", &meta, &camera, "").expect("session");
        let pose = |sequence: u64, t: u64| pb::PoseStamped { sequence, capture_time_ns: t, ..Default::default() };
        let commit = |poses: &[pb::PoseStamped], first_pose: u64| {
            let c = Commit { session_id: "s", meta: &meta, poses, first_pose, keyframes: &[], camera: None, blocks: vec![], evicted: &[] };
            store.commit(&c).expect("committed");
        };
        commit(&[pose(7, 10), pose(8, 20)], 0);
        commit(&[pose(7, 30), pose(1, 40)], 2);
        commit(&[pose(2, 50)], 9);
        let s = store.load("s").expect("read").expect("stored");
        assert_eq!(s.poses.iter().map(|p| p.capture_time_ns).collect::<Vec<_>>(), [10, 20, 30, 40, 50]);
        assert_eq!(s.next_pose_place, 10);
        let mut first = Vec::new();
        assert_eq!(store.first_poses("s", 3, |p| first.push(p.capture_time_ns)).expect("read"), 3);
        assert_eq!(first, [10, 20, 30]);
        assert_eq!(store.first_poses("s", 9, |_| {}).expect("read"), 5, "fewer than asked: the caller names the gap");
        // A copy taken again (a session resumed from the shared storage) replaces
        // the poses of the earlier one, wherever they were stored.
        let copy = StoredSession { poses: vec![pose(3, 60), pose(4, 70)], next_pose_place: 12, ..s };
        store.import(&copy).expect("copied");
        let back = store.load("s").expect("read").expect("stored");
        assert_eq!(back.poses.iter().map(|p| p.capture_time_ns).collect::<Vec<_>>(), [60, 70]);
    }

    #[test]
    fn only_the_newest_keyframe_records_are_read_where_only_they_are_used() {
        let store = memory_disk::store_on(&Disk::default());
        let meta = SessionMeta::for_tests("r");
        let camera = pb::CameraInfo { width: 64, height: 48, ..Default::default() };
        store.put_session("s", &meta, &camera, "").expect("session");
        let pose = |t: u64| pb::PoseStamped { sequence: t, capture_time_ns: t, ..Default::default() };
        let keyframe =
            |id: u64| KeyframeRecord { id, timestamp_ns: id, world_from_camera: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], features: vec![] };
        for k in 0..5u64 {
            let poses: Vec<_> = (3 * k..3 * k + 3).map(pose).collect();
            let c = Commit {
                session_id: "s",
                meta: &meta,
                poses: &poses,
                first_pose: 3 * k,
                keyframes: &[keyframe(k)],
                camera: None,
                blocks: vec![],
                evicted: &[],
            };
            store.commit(&c).expect("committed");
        }
        let h = store.heads().expect("heads").remove(0);
        assert_eq!((h.pose_count, h.latest.map(|p| p.capture_time_ns), h.keyframes.len()), (15, Some(14), 0));
        let newest = |n: usize| store.newest_keyframes("s", n).expect("read").iter().map(|k| k.id).collect::<Vec<_>>();
        assert_eq!(newest(2), [3, 4], "the newest, oldest first");
        assert_eq!(newest(0), [0u64; 0]);
        assert_eq!(newest(9), [0, 1, 2, 3, 4]);
        assert_eq!(store.newest_keyframes("unknown", 9).expect("read").len(), 0);
        let ids = |s: StoredSession| (s.keyframes.iter().map(|k| k.id).collect::<Vec<_>>(), s.poses.len());
        assert_eq!(ids(store.load_with("s", 1).expect("read").expect("stored")), (vec![4], 15), "the newest keyframe, every pose");
        assert_eq!(ids(store.load("s").expect("read").expect("stored")), (vec![0, 1, 2, 3, 4], 15));
    }

    #[test]
    fn a_map_block_beyond_the_maps_range_is_refused() {
        let s = StoredSession {
            id: "far".into(),
            meta: SessionMeta { started_unix_ns: 5, ..SessionMeta::for_tests("far") },
            camera: pb::CameraInfo {
                width: 640,
                height: 480,
                fx: 525.0,
                fy: 525.0,
                cx: 319.5,
                cy: 239.5,
                depth_units_per_metre: 5000.0,
                color_encoding: pb::ColorEncoding::Jpeg as i32,
                depth_encoding: pb::DepthEncoding::Zstd as i32,
                ..Default::default()
            },
            poses: Vec::new(),
            next_pose_place: 0,
            keyframes: Vec::new(),
            blocks: vec![([1 << 27, 0, -(1 << 27)], Block::default())],
        };
        let file = export(&s).unwrap();
        assert_eq!(
            import_file(&file, 1 << 20).unwrap_err().to_string(),
            format!(
                "bad map file: map block [134217728, 0, -134217728] is outside the map's range of ±{} blocks",
                stillmap_mapping::voxel::MAX_BLOCK_INDEX
            )
        );
        let near = StoredSession { blocks: vec![([3, 0, -2], Block::default())], ..s.clone() };
        assert_eq!(import_file(&export(&near).unwrap(), 1 << 20).unwrap().blocks.len(), 1);

        // Twice the same block.
        let twice = StoredSession { blocks: vec![([3, 0, -2], Block::default()), ([3, 0, -2], Block::default())], ..s.clone() };
        assert_eq!(
            import_file(&export(&twice).unwrap(), 1 << 20).unwrap_err().to_string(),
            "bad map file: map block [3, 0, -2] appears twice"
        );
        // 1,500 empty blocks: about 130 KB in the file, 18 MB in memory, over 16 × 1 MiB.
        let empty = StoredSession { blocks: (0..1500).map(|k| ([k, 0, 0], Block::default())).collect(), ..s };
        let file = export(&empty).unwrap();
        assert!(file.len() < 1 << 20, "{}", file.len());
        assert_eq!(
            import_file(&file, 1 << 20).unwrap_err().to_string(),
            "bad map file: its map blocks would take more than 16777216 bytes in memory (16 × store.import_max_bytes)"
        );
        assert_eq!(import_file(&file, 2 << 20).unwrap().blocks.len(), 1500, "within 16 × 2 MiB");
    }
}
