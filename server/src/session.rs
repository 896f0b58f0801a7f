//! Robot sessions: the registry both ingest transports feed, and one pipeline
//! worker thread per session.
//!
//! A session outlives its connection: a robot that reconnects with
//! `Hello.resume_session_id` gets the same session back, and queries keep
//! answering for disconnected sessions. Results go to whichever connection is
//! attached when the worker finishes a frame.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use stillmap_proto::pb::{self, FrameStatus, TrackingState, server_message::Msg};
use tokio::sync::{broadcast, mpsc, watch};
use tonic::Status;

use crate::config::SessionConfig;
use crate::mapping::{MapFrame, SessionMap, SharedMap};
use crate::perception::{SegmentationService, SessionPerception};
use crate::tracking::SessionTracker;
use stillmap_mapping::MappingConfig;
use stillmap_perception::PerceptionConfig;
use stillmap_tracking::TrackerConfig;
use crate::metrics::Metrics;
use crate::pipeline::{FramePipeline, validate_camera};
use crate::queue::{FrameQueue, PushOutcome, QueueError, QueuedFrame, Work};
use crate::store::{SessionMeta, Store, StoredSession};

/// Where a connection's results go: the gRPC response stream, or the Zenoh
/// publisher task (which turns an `Err` into a `ServerMessage.error`).
pub type ResultSink = mpsc::Sender<Result<pb::ServerMessage, Status>>;

/// Poses a slow `SubscribePoses` client may lag behind before it skips some.
const POSE_SUBSCRIBER_BUFFER: usize = 256;
/// Poses of all sessions a slow dashboard may lag behind before it skips some.
const FLEET_POSE_BUFFER: usize = 1024;

/// A pose of some session, for the fleet-wide event stream (the dashboard).
pub type FleetPose = (Arc<str>, pb::PoseStamped);

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transport {
    Grpc,
    Zenoh,
}

impl Transport {
    pub fn label(self) -> &'static str {
        match self {
            Self::Grpc => "grpc",
            Self::Zenoh => "zenoh",
        }
    }
}

/// Per-session counters, readable while the worker runs.
#[derive(Default)]
pub struct Counters {
    pub received: AtomicU64,
    pub processed: AtomicU64,
    pub dropped: AtomicU64,
    pub rejected: AtomicU64,
    pub bytes: AtomicU64,
    /// Frames answered (processed, dropped or rejected) — the worker's progress.
    pub answered: AtomicU64,
}

/// What tracking knows; filled in by the tracking stage once it exists.
#[derive(Default)]
pub struct TrackState {
    pub state: TrackingState,
    pub latest: Option<pb::PoseStamped>,
    pub trajectory: Vec<pb::PoseStamped>,
}

pub struct Session {
    pub id: String,
    pub robot_id: String,
    pub transport: Transport,
    pub camera: pb::CameraInfo,
    pub started_unix_ns: u64,
    pub counters: Counters,
    connected: AtomicBool,
    queue: FrameQueue,
    sink: Mutex<Option<ResultSink>>,
    last_received_sequence: Mutex<Option<u64>>,
    track: Mutex<TrackState>,
    poses: broadcast::Sender<pb::PoseStamped>,
    fleet: broadcast::Sender<FleetPose>,
    /// The last processed frame's stage latencies (the dashboard's sparklines).
    last_latency: Mutex<Vec<pb::StageLatency>>,
    answered_tx: watch::Sender<u64>,
    metrics: Arc<Metrics>,
    tracker_config: TrackerConfig,
    perception: Option<(PerceptionConfig, Option<Arc<SegmentationService>>)>,
    /// The static semantic map (`None`: mapping off, or it could not start).
    map: Option<SharedMap>,
    /// Restored from the store after a restart: queries only, no worker.
    archived: bool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Session {
    /// Queues a received frame. Dropped frames are counted here and answered by the worker.
    pub fn push(&self, frame: pb::Frame, encoded_len: usize) -> Result<(), QueueError> {
        let transport = self.transport.label();
        let sequence = frame.sequence;
        self.metrics.frame_received(transport, encoded_len);
        let outcome = self.queue.push(QueuedFrame { frame, received_at: Instant::now() })?;
        self.counters.received.fetch_add(1, Ordering::Relaxed);
        self.counters.bytes.fetch_add(encoded_len as u64, Ordering::Relaxed);
        {
            let mut last = lock(&self.last_received_sequence);
            *last = Some(last.map_or(sequence, |l| l.max(sequence)));
        }
        if outcome != PushOutcome::Queued {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
            self.metrics.frame_dropped(transport);
        }
        Ok(())
    }

    pub fn last_received_sequence(&self) -> Option<u64> {
        *lock(&self.last_received_sequence)
    }

    pub fn is_connected(&self) -> bool {
        self.connected.load(Ordering::Relaxed)
    }

    pub fn tracking(&self) -> MutexGuard<'_, TrackState> {
        lock(&self.track)
    }

    pub fn map(&self) -> Option<&SharedMap> {
        self.map.as_ref()
    }

    pub fn subscribe_poses(&self) -> broadcast::Receiver<pb::PoseStamped> {
        self.poses.subscribe()
    }

    /// Attaches a connection's result sink, replacing any older one.
    pub fn attach(&self, sink: ResultSink) {
        *lock(&self.sink) = Some(sink);
        self.set_connected(true);
    }

    /// Attaches `sink` when no connection holds the session (never takes it from
    /// another one); true when `sink` is attached afterwards.
    pub fn attach_if_vacant(&self, sink: &ResultSink) -> bool {
        let mut current = lock(&self.sink);
        match current.as_ref() {
            Some(held) => held.same_channel(sink),
            None => {
                *current = Some(sink.clone());
                self.set_connected(true);
                true
            }
        }
    }

    /// Detaches `sink` if it is still the attached one (a newer connection may have replaced it).
    pub fn detach(&self, sink: &ResultSink) {
        let mut current = lock(&self.sink);
        if current.as_ref().is_some_and(|s| s.same_channel(sink)) {
            *current = None;
            self.set_connected(false);
        }
    }

    /// Records the connection state; the gauge moves only when it changes.
    fn set_connected(&self, connected: bool) {
        if self.connected.swap(connected, Ordering::Relaxed) != connected {
            self.metrics.connected_delta(if connected { 1 } else { -1 });
        }
    }

    /// Frames received and not yet answered.
    pub fn unanswered(&self) -> u64 {
        let received = self.counters.received.load(Ordering::Relaxed);
        received.saturating_sub(self.counters.answered.load(Ordering::Relaxed))
    }

    /// Waits until every frame received so far has been answered.
    pub async fn drained(&self) {
        let mut rx = self.answered_tx.subscribe();
        let received = self.counters.received.load(Ordering::Relaxed);
        // The worker keeps the sender alive as long as the session exists.
        let _ = rx.wait_for(|answered| *answered >= received).await;
    }

    fn deliver(&self, result: pb::FrameResult) {
        let sink = lock(&self.sink).clone();
        if let Some(sink) = sink {
            // Blocking here is the back-pressure of a slow reader: the queue in front
            // of the worker then applies the overload policy.
            let _ = sink.blocking_send(Ok(pb::ServerMessage { msg: Some(Msg::Result(result)) }));
        }
        let answered = self.counters.answered.fetch_add(1, Ordering::Relaxed) + 1;
        self.answered_tx.send_replace(answered);
    }

    /// Publishes a tracked frame's state and pose to the query APIs and subscribers.
    fn record_pose(&self, result: &pb::FrameResult, pose: Option<pb::Pose>) {
        let state = result.tracking_state();
        let stamped = pose.map(|p| pb::PoseStamped {
            sequence: result.sequence,
            capture_time_ns: result.capture_time_ns,
            world_from_camera: Some(p),
            tracking_state: state as i32,
            pose_time_ns: result.pose_time_ns,
        });
        let mut track = self.tracking();
        track.state = state;
        if let Some(s) = stamped {
            track.latest = Some(s);
            track.trajectory.push(s);
            drop(track);
            // No subscriber is fine.
            let _ = self.poses.send(s);
            let _ = self.fleet.send((Arc::from(self.id.as_str()), s));
        }
    }

    /// The last processed frame's stage latencies.
    pub fn last_latency(&self) -> Vec<pb::StageLatency> {
        lock(&self.last_latency).clone()
    }

    /// The worker loop: one thread per session, until the queue closes.
    fn run_worker(self: Arc<Self>) {
        let mut pipeline = FramePipeline::new(self.camera.clone());
        let mut tracker = match SessionTracker::new(&self.camera, &self.tracker_config) {
            Ok(t) => Some(t),
            Err(e) => {
                tracing::error!(session = %self.id, "tracking unavailable for this session: {e}");
                None
            }
        };
        let mut perception = self.perception.as_ref().and_then(|(config, service)| {
            SessionPerception::new(&self.camera, config, service.as_ref())
                .map_err(|e| tracing::error!(session = %self.id, "perception unavailable for this session: {e}"))
                .ok()
        });
        let transport = self.transport.label();
        while let Some(work) = self.queue.pop() {
            let result = match work {
                Work::Dropped { sequence, capture_time_ns } => pb::FrameResult {
                    sequence,
                    capture_time_ns,
                    status: FrameStatus::Dropped as i32,
                    tracking_state: self.tracking().state as i32,
                    ..Default::default()
                },
                Work::Frame(queued) => {
                    let mut out = pipeline.process(&queued.frame, queued.received_at.elapsed());
                    if let (Some(tracker), Some((color, depth))) = (tracker.as_mut(), out.images.as_ref()) {
                        let mask = perception.as_mut().and_then(|p| p.prepare(out.result.sequence, color, depth));
                        let pose = tracker.track(&mut out.result, color, depth, mask);
                        if let Some(p) = perception.as_mut() {
                            let eliminated = tracker.masked_features() as u32;
                            if let Some(source) = p.finish(&mut out.result, depth, tracker.last_motion(), eliminated) {
                                self.metrics.perception(source, eliminated);
                            }
                        }
                        if let Some(map) = &self.map {
                            // Only a new keyframe is fused: the full-size masks are built for it alone.
                            let keyframe = tracker.new_keyframe().is_some();
                            let exclude = perception.as_ref().filter(|_| keyframe).and_then(SessionPerception::map_exclusion);
                            let classes = perception.as_ref().filter(|_| keyframe).and_then(SessionPerception::class_map);
                            let frame = MapFrame {
                                color,
                                depth,
                                exclude: exclude.as_deref(),
                                classes: classes.as_deref(),
                                accel_in_camera: queued.frame.accel_in_camera.map(|a| nalgebra::Vector3::new(a.x, a.y, a.z)),
                            };
                            let fused = crate::mapping::update(map, &mut out.result, &frame, tracker.last_pose().as_ref(), tracker.new_keyframe(), |id| tracker.keyframe_pose(id));
                            self.record_pose(&out.result, pose);
                            if fused.is_some() {
                                self.metrics.keyframe_fused();
                                let record = tracker.new_keyframe().and_then(|id| tracker.keyframe_record(id));
                                self.persist(map, record, Some(&mut out.result));
                            }
                        } else {
                            self.record_pose(&out.result, pose);
                        }
                    }
                    if let Some(reason) = out.rejected {
                        self.counters.rejected.fetch_add(1, Ordering::Relaxed);
                        self.metrics.rejected(reason.label());
                    } else {
                        self.counters.processed.fetch_add(1, Ordering::Relaxed);
                        self.metrics.frame_processed(transport);
                        for l in &out.result.latency {
                            self.metrics.stage(&l.stage, l.micros);
                        }
                        *lock(&self.last_latency) = out.result.latency.clone();
                    }
                    out.result
                }
            };
            self.deliver(result);
        }
        // Shutdown: commit the poses after the last keyframe too.
        if let Some(map) = &self.map {
            self.persist(map, None, None);
        }
        tracing::debug!(session = %self.id, "worker stopped");
    }

    /// Commits to the store; the time goes into `result` as the `store_commit` stage.
    fn persist(&self, map: &SharedMap, keyframe: Option<crate::store::KeyframeRecord>, result: Option<&mut pb::FrameResult>) {
        let start = Instant::now();
        // Lock order: tracking, then map (nothing takes them the other way round).
        let track = self.tracking();
        let outcome = lock(map).persist(&track.trajectory, keyframe);
        drop(track);
        match outcome {
            Ok(true) => {
                if let Some(r) = result {
                    let spent = start.elapsed();
                    crate::pipeline::append_stages(r, &[(crate::mapping::STORE_COMMIT_STAGE, spent)], spent);
                }
            }
            Ok(false) => {}
            Err(e) => tracing::error!(session = %self.id, "cannot commit to the store (the map stays in memory): {e}"),
        }
    }

    /// Whether the session was restored from the store (no worker; read-only).
    pub fn is_archived(&self) -> bool {
        self.archived
    }
}

/// A summary of one session, for the query APIs.
pub fn summary(s: &Session) -> pb::SessionSummary {
    let c = &s.counters;
    pb::SessionSummary {
        session_id: s.id.clone(),
        robot_id: s.robot_id.clone(),
        transport: s.transport.label().into(),
        connected: s.is_connected(),
        camera: Some(s.camera.clone()),
        frames_received: c.received.load(Ordering::Relaxed),
        frames_processed: c.processed.load(Ordering::Relaxed),
        frames_dropped: c.dropped.load(Ordering::Relaxed),
        frames_rejected: c.rejected.load(Ordering::Relaxed),
        tracking_state: s.tracking().state as i32,
        started_unix_ns: s.started_unix_ns,
    }
}

/// Why a map file could not be imported.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("importing maps needs the store (store.enabled)")]
    NoStore,
    #[error("session {0:?} exists already")]
    Exists(String),
    #[error("{0}")]
    Store(crate::store::StoreError),
}

/// A hello the server cannot open a session for.
#[derive(Debug, thiserror::Error)]
pub enum BadHello {
    /// The hello itself is wrong (INVALID_ARGUMENT).
    #[error("bad hello: {0}")]
    Invalid(String),
    /// `session.max_connected` robots stream already (RESOURCE_EXHAUSTED).
    #[error("server full: {connected} robots connected, session.max_connected = {limit}")]
    Full { connected: usize, limit: usize },
    /// The server could not start the session (INTERNAL).
    #[error("{0}")]
    Internal(String),
}

impl BadHello {
    /// The gRPC status this refusal is answered with (gRPC, and Zenoh's `ServerMessage.error`).
    pub fn status(&self) -> tonic::Status {
        let code = match self {
            Self::Invalid(_) => tonic::Code::InvalidArgument,
            Self::Full { .. } => tonic::Code::ResourceExhausted,
            Self::Internal(_) => tonic::Code::Internal,
        };
        tonic::Status::new(code, self.to_string())
    }
}

/// Every session of this server process.
pub struct Registry {
    config: SessionConfig,
    tracking: TrackerConfig,
    /// Perception settings and the shared segmentation service (`None`: perception off).
    perception: Option<(PerceptionConfig, Option<Arc<SegmentationService>>)>,
    mapping: MappingConfig,
    store: Option<Arc<Store>>,
    metrics: Arc<Metrics>,
    fleet: broadcast::Sender<FleetPose>,
    sessions: RwLock<HashMap<String, Arc<Session>>>,
    /// Worker threads, joined at shutdown (their last commit must land).
    workers: Mutex<Vec<std::thread::JoinHandle<()>>>,
    next_id: AtomicU64,
    /// Held through `open`, so concurrent hellos see each other when the
    /// `session.max_connected` limit is checked.
    admission: Mutex<()>,
    /// Distinguishes session ids of different server runs.
    epoch: u64,
}

/// What differs between a live session and one restored from the store.
struct SessionParts {
    id: String,
    robot_id: String,
    transport: Transport,
    camera: pb::CameraInfo,
    started_unix_ns: u64,
    counters: Counters,
    queue: FrameQueue,
    last_received_sequence: Option<u64>,
    track: TrackState,
    perception: Option<(PerceptionConfig, Option<Arc<SegmentationService>>)>,
    map: Option<SharedMap>,
    archived: bool,
}

/// The result of a hello.
pub struct Opened {
    pub session: Arc<Session>,
    pub resumed: bool,
}

impl Registry {
    pub fn new(
        config: SessionConfig,
        tracking: TrackerConfig,
        perception: Option<(PerceptionConfig, Option<Arc<SegmentationService>>)>,
        mapping: MappingConfig,
        store: Option<Arc<Store>>,
        metrics: Arc<Metrics>,
    ) -> Self {
        let epoch = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs());
        Self { config, tracking, perception, mapping, store, metrics, fleet: broadcast::channel(FLEET_POSE_BUFFER).0, workers: Mutex::new(Vec::new()), sessions: RwLock::default(), next_id: AtomicU64::new(1), admission: Mutex::new(()), epoch }
    }

    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.metrics
    }

    /// Every session's poses as they are estimated.
    pub fn subscribe_fleet(&self) -> broadcast::Receiver<FleetPose> {
        self.fleet.subscribe()
    }

    pub fn get(&self, id: &str) -> Option<Arc<Session>> {
        self.sessions.read().unwrap_or_else(|p| p.into_inner()).get(id).cloned()
    }

    /// All sessions, oldest first.
    pub fn list(&self) -> Vec<Arc<Session>> {
        let mut all: Vec<_> = self.sessions.read().unwrap_or_else(|p| p.into_inner()).values().cloned().collect();
        all.sort_by_key(|s| (s.started_unix_ns, s.id.clone()));
        all
    }

    /// Opens a session for `hello`, or resumes the one it names, and attaches `sink`.
    pub fn open(&self, hello: &pb::Hello, transport: Transport, sink: ResultSink) -> Result<Opened, BadHello> {
        stillmap_proto::validate_robot_id(&hello.robot_id).map_err(BadHello::Invalid)?;
        let _admission = lock(&self.admission);
        if !hello.resume_session_id.is_empty()
            && let Some(session) = self.get(&hello.resume_session_id).filter(|s| !s.archived)
        {
            if session.robot_id != hello.robot_id {
                return Err(BadHello::Invalid(format!(
                    "session {} belongs to robot {:?}, not {:?}",
                    session.id, session.robot_id, hello.robot_id
                )));
            }
            if !session.is_connected() {
                self.check_capacity()?;
            }
            session.attach(sink);
            return Ok(Opened { session, resumed: true });
        }
        let camera = validate_camera(hello.camera.as_ref()).map_err(BadHello::Invalid)?.clone();
        self.check_capacity()?;
        let n = self.next_id.fetch_add(1, Ordering::Relaxed);
        let id = format!("{}-{:x}-{n}", hello.robot_id, self.epoch);
        let started_unix_ns = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64);
        let map = if self.mapping.enabled {
            let names = match &self.perception {
                Some((_, Some(service))) => service.class_names().to_vec(),
                _ => Vec::new(),
            };
            let meta = SessionMeta {
                robot_id: hello.robot_id.clone(),
                transport: transport.label().to_string(),
                started_unix_ns,
                class_names: names.clone(),
                up_in_world: None,
                up_source: None,
                keyframes: 0,
                map_stamp: 0,
            };
            let map = SessionMap::new(&camera, self.mapping.clone(), names)
                .map_err(|e| tracing::error!(session = %id, "mapping unavailable for this session: {e}"))
                .ok();
            if let (Some(map), Some(store)) = (&map, &self.store) {
                match store.put_session(&id, &meta, &camera) {
                    Ok(()) => lock(map).attach_store(store.clone(), &id, meta),
                    Err(e) => tracing::error!(session = %id, "session not persisted (the store failed): {e}"),
                }
            }
            map
        } else {
            None
        };
        let session = Arc::new(self.session(SessionParts {
            id: id.clone(),
            robot_id: hello.robot_id.clone(),
            transport,
            camera,
            started_unix_ns,
            counters: Counters::default(),
            queue: FrameQueue::new(self.config.queue_capacity, self.config.max_pending_drop_notices, self.config.overload_policy),
            last_received_sequence: None,
            track: TrackState { state: TrackingState::Initializing, ..Default::default() },
            perception: self.perception.clone(),
            map,
            archived: false,
        }));
        session.attach(sink);
        let worker = session.clone();
        let handle = std::thread::Builder::new()
            .name(format!("pipeline-{n}"))
            .spawn(move || worker.run_worker())
            .map_err(|e| BadHello::Internal(format!("cannot start a pipeline worker: {e}")))?;
        lock(&self.workers).push(handle);
        self.sessions.write().unwrap_or_else(|p| p.into_inner()).insert(id, session.clone());
        self.metrics.session_opened();
        tracing::info!(session = %session.id, robot = %session.robot_id, transport = transport.label(), "session opened");
        Ok(Opened { session, resumed: false })
    }

    /// Refuses a new connection when `session.max_connected` robots stream already
    /// (under the admission lock, so racing hellos cannot pass together).
    fn check_capacity(&self) -> Result<(), BadHello> {
        let limit = self.config.max_connected;
        if limit == 0 {
            return Ok(());
        }
        let connected = self.sessions.read().unwrap_or_else(|p| p.into_inner()).values().filter(|s| s.is_connected()).count();
        if connected >= limit {
            return Err(BadHello::Full { connected, limit });
        }
        Ok(())
    }

    /// Brings back every session in the store (read-only: queries answer, robots
    /// resuming one get a new session).
    pub fn restore(&self, stored: Vec<StoredSession>) {
        for s in stored {
            let id = s.id.clone();
            let map = if self.mapping.enabled {
                match SessionMap::new(&s.camera, self.mapping.clone(), s.meta.class_names.clone()) {
                    Ok(map) => {
                        {
                            let mut m = lock(&map);
                            if let Some(store) = &self.store {
                                m.attach_store(store.clone(), &id, s.meta.clone());
                            }
                            let last_camera = s.keyframes.last().map(|k| nalgebra::Point3::new(k.world_from_camera[0], k.world_from_camera[1], k.world_from_camera[2]));
                            m.restore(s.blocks, &s.meta, s.poses.len(), last_camera);
                        }
                        Some(map)
                    }
                    Err(e) => {
                        tracing::error!(session = %id, "stored map cannot be restored: {e}");
                        None
                    }
                }
            } else {
                None
            };
            let transport = if s.meta.transport == "zenoh" { Transport::Zenoh } else { Transport::Grpc };
            let counters = Counters::default();
            counters.processed.store(s.poses.len() as u64, Ordering::Relaxed);
            let latest = s.poses.last().copied();
            let state = latest.map_or(TrackingState::Initializing, |p| p.tracking_state());
            let queue = FrameQueue::new(1, 1, self.config.overload_policy);
            queue.close();
            let session = Arc::new(self.session(SessionParts {
                id: id.clone(),
                robot_id: s.meta.robot_id.clone(),
                transport,
                camera: s.camera,
                started_unix_ns: s.meta.started_unix_ns,
                counters,
                queue,
                last_received_sequence: latest.map(|p| p.sequence),
                track: TrackState { state, latest, trajectory: s.poses },
                perception: None,
                map,
                archived: true,
            }));
            tracing::info!(session = %id, keyframes = s.meta.keyframes, "session restored from the store");
            self.sessions.write().unwrap_or_else(|p| p.into_inner()).insert(id, session);
        }
    }

    pub fn store(&self) -> Option<&Arc<Store>> {
        self.store.as_ref()
    }

    /// Adds a session from a map file (see [`crate::store::export`]) to the store
    /// and to the registry, read-only.
    pub fn import(&self, stored: StoredSession) -> Result<String, ImportError> {
        let store = self.store.as_ref().ok_or(ImportError::NoStore)?;
        if self.get(&stored.id).is_some() || store.contains(&stored.id).map_err(ImportError::Store)? {
            return Err(ImportError::Exists(stored.id));
        }
        store.import(&stored).map_err(ImportError::Store)?;
        let id = stored.id.clone();
        self.restore(vec![stored]);
        Ok(id)
    }

    /// A session from what differs between a live and a restored one.
    fn session(&self, p: SessionParts) -> Session {
        Session {
            id: p.id,
            robot_id: p.robot_id,
            transport: p.transport,
            camera: p.camera,
            started_unix_ns: p.started_unix_ns,
            counters: p.counters,
            connected: AtomicBool::new(false),
            queue: p.queue,
            sink: Mutex::new(None),
            last_received_sequence: Mutex::new(p.last_received_sequence),
            track: Mutex::new(p.track),
            poses: broadcast::channel(POSE_SUBSCRIBER_BUFFER).0,
            fleet: self.fleet.clone(),
            last_latency: Mutex::new(Vec::new()),
            answered_tx: watch::channel(0).0,
            metrics: self.metrics.clone(),
            tracker_config: self.tracking.clone(),
            perception: p.perception,
            map: p.map,
            archived: p.archived,
        }
    }

    /// Waits for every worker to finish its queue and its last commit, then stops
    /// the segmentation workers (the sessions' last frames may still need them).
    pub fn join_workers(&self) {
        let workers = std::mem::take(&mut *lock(&self.workers));
        for w in workers {
            let _ = w.join();
        }
        if let Some((_, Some(service))) = &self.perception {
            service.close();
        }
    }

    /// Stops every worker once its queue is drained (server shutdown).
    pub fn close_all(&self) {
        for s in self.list() {
            s.queue.close();
        }
    }
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
        })),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Zenoh robot's frames re-attach its link only when no other connection holds
    /// the session: a gRPC resume keeps the results, and the gauge counts once.
    #[test]
    fn attach_if_vacant_never_takes_a_session_from_another_connection() {
        let mapping = MappingConfig { enabled: false, ..MappingConfig::default() };
        let registry = Registry::new(SessionConfig::default(), TrackerConfig::default(), None, mapping, None, Arc::default());
        let camera = pb::CameraInfo {
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 60.0,
            cx: 32.0,
            cy: 24.0,
            depth_units_per_metre: 1000.0,
            color_encoding: pb::ColorEncoding::Rgb8 as i32,
            depth_encoding: pb::DepthEncoding::Zstd as i32,
            ..Default::default()
        };
        let hello = pb::Hello { robot_id: "r".into(), camera: Some(camera), ..Default::default() };
        let (zenoh, _zenoh_rx) = mpsc::channel(4);
        let (grpc, _grpc_rx) = mpsc::channel(4);
        let session = registry.open(&hello, Transport::Zenoh, zenoh.clone()).expect("open").session;
        let gauge = || registry.metrics().render().lines().find(|l| l.starts_with("stillmap_sessions_connected ")).map(str::to_owned);
        assert!(session.is_connected());
        assert!(session.attach_if_vacant(&zenoh), "already ours");
        session.attach(grpc.clone()); // a gRPC resume takes the session
        assert!(!session.attach_if_vacant(&zenoh), "held by the gRPC stream");
        session.detach(&zenoh); // the idle check detaches only its own sink
        assert!(session.is_connected());
        assert_eq!(gauge().as_deref(), Some("stillmap_sessions_connected 1"));
        session.detach(&grpc); // the gRPC stream ends
        assert!(!session.is_connected());
        assert_eq!(gauge().as_deref(), Some("stillmap_sessions_connected 0"));
        assert!(session.attach_if_vacant(&zenoh), "vacant: the robot's next frame takes it");
        assert!(session.is_connected());
        assert_eq!(gauge().as_deref(), Some("stillmap_sessions_connected 1"));
        registry.close_all();
    }
}
