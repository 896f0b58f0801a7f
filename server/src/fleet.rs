//! Fleets: one world frame per fleet, shared by every robot merged into it.
//!
//! A robot's hello names its fleet (`Hello.fleet`, else `fleet.default_fleet`).
//! The fleet's first session anchors its frame (`fleet_from_session` = identity).
//! Every other session lives in its own frame, unmerged, until place recognition
//! (`stillmap-places`) merges it: each of its keyframes, as the map lane commits
//! it, is looked up in the fleet's index of merged keyframes, the best candidates
//! are verified geometrically, and once `fleet.consistent_matches` keyframes agree
//! on one `fleet_from_session` the session is merged (their inlier-weighted mean);
//! later keyframes of either side refine it, until `fleet.refine_support`
//! proposals have been heard. Keyframes are looked up both ways (a merged
//! session's new keyframe against unmerged sessions' keyframes too), so the order
//! in which two robots see a place does not matter.
//! Merges are committed to the store and come back at restart.
//!
//! All of it runs on one thread of its own behind a bounded queue
//! (`fleet.queue`): neither tracking nor the map lane ever waits for it, and a
//! keyframe finding the queue full is left out of place recognition (logged and
//! counted in `stillmap_fleet_keyframes_left_out_total`).
//! Memory is bounded by `fleet.max_places` keyframes per fleet (about 60 KB each:
//! the features with depth, point and descriptor, and the index postings; 300 MB
//! per fleet at the default 5,000) and `fleet.pending_keyframes` per unmerged session.

use std::collections::{HashMap, VecDeque};
use std::sync::mpsc::{SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use nalgebra::{Isometry3, Point2, Quaternion, Translation3, UnitQuaternion};
use stillmap_places::{
    BowVector, Edge, EdgeKind, MergeConfig, MergeDetector, Place, PlaceIndex, PoseGraph, SolveConfig, VerifyConfig, Vocabulary, propose,
    verify,
};
use stillmap_tracking::Camera;

use crate::config::FleetConfig;
use crate::lock;
use crate::store::{FleetFrame, FleetGraph, GraphEdge, GraphSolve, KeyframeRecord, SessionGraph, SessionHead, Store};
use stillmap_mapping::MappingConfig;

/// A committed keyframe of some session, for place recognition.
pub struct FleetJob {
    pub fleet: String,
    pub session_id: String,
    pub robot_id: String,
    pub camera: Camera,
    pub keyframe: KeyframeRecord,
}

/// The stored keyframes of a session resumed from another server, to put into
/// its fleet's place index here (as a restart puts a session's stored keyframes).
pub struct StoredKeyframes {
    pub fleet: String,
    pub session_id: String,
    pub camera: Camera,
    /// In any order.
    pub keyframes: Vec<KeyframeRecord>,
}

/// What the place-recognition thread does.
enum Work {
    /// A committed keyframe: matched against the fleet, then indexed.
    Keyframe(FleetJob),
    /// A resumed session's stored keyframes: indexed.
    Stored(StoredKeyframes),
}

impl Work {
    /// The keyframes it carries (what the backlog counts).
    fn keyframes(&self) -> usize {
        match self {
            Work::Keyframe(_) => 1,
            Work::Stored(s) => s.keyframes.len(),
        }
    }
}

/// A session as its fleet knows it.
struct Member {
    session_id: String,
    robot_id: String,
    frame: Option<FleetFrame>,
    detector: MergeDetector,
    /// Its keyframes in the index, oldest first (an unmerged session keeps only
    /// its latest `fleet.pending_keyframes` there).
    indexed: VecDeque<u64>,
    /// Proposals heard for its merge (it stops refining at `fleet.refine_support`).
    heard: usize,
    /// Capture times of its first and latest keyframes seen here.
    keyframe_span_ns: Option<(u64, u64)>,
    /// The pose graph's corrections of its keyframes (see [`FleetTransform`]).
    corrections: Corrections,
    /// The corrections and the number of edges of the share last copied to the
    /// shared storage (a share that barely changed is not copied again).
    shared: Option<(Corrections, usize)>,
}

/// (capture time, `fleet_corrected_from_fleet`) of a session's keyframes, in time order.
type Corrections = Arc<Vec<(u64, Isometry3<f64>)>>;

/// One fleet: its members and the index of its merged keyframes.
#[derive(Default)]
struct Fleet {
    members: Vec<Member>,
    index: PlaceIndex<(u32, u64)>,
    /// Per indexed keyframe: `session_from_camera`, its place (the fleet frame
    /// is its member's `fleet_from_session` away, which a refined merge may move)
    /// and its capture time.
    places: HashMap<(u32, u64), Indexed>,
    /// Indexed keyframes, oldest first (the first forgotten beyond `max_places`).
    order: VecDeque<(u32, u64)>,
    /// Verified matches between merged keyframes (loop and inter-session edges of
    /// the pose graph); those of forgotten keyframes are dropped.
    edges: Vec<PlaceEdge>,
    /// Edges that sessions resumed from another server brought along, waiting until
    /// both their keyframes are indexed here (the older ones are read back in the
    /// background); at most `fleet.max_places`, the oldest dropped beyond.
    carried_edges: VecDeque<GraphEdge>,
    /// A place edge came since the last solve.
    dirty: bool,
    /// Solves that have taken the graph and not handed their corrections back yet
    /// (the pose-graph thread's, and `solve_now`'s in tests).
    solving: usize,
    last_solve: Option<Instant>,
    last_correction: Option<GraphSolve>,
}

/// An indexed keyframe.
struct Indexed {
    session_from_camera: Isometry3<f64>,
    place: Arc<Place>,
    /// Capture time.
    timestamp_ns: u64,
}

/// A verified match between two indexed keyframes (member, keyframe id):
/// `a_from_b` is b's camera in a's camera frame.
#[derive(Debug, Clone, Copy)]
struct PlaceEdge {
    a: (u32, u64),
    b: (u32, u64),
    a_from_b: Isometry3<f64>,
    kind: EdgeKind,
}

/// A merged session's poses into the fleet frame: its merge (`fleet_from_session`)
/// and the pose graph's correction of its keyframes, each applying from its
/// keyframe's capture time on (the first keyframe's before it).
#[derive(Debug, Clone)]
pub struct FleetTransform {
    pub fleet_from_session: Isometry3<f64>,
    /// (capture time, `fleet_corrected_from_fleet`), in time order.
    pub corrections: Arc<Vec<(u64, Isometry3<f64>)>>,
}

impl FleetTransform {
    /// `fleet_from_session` for a pose captured at `t_ns`, corrected.
    pub fn at(&self, t_ns: u64) -> Isometry3<f64> {
        let c = &self.corrections;
        let i = c.partition_point(|(t, _)| *t <= t_ns);
        match c.get(i.saturating_sub(1)) {
            Some((_, correction)) => correction * self.fleet_from_session,
            None => self.fleet_from_session,
        }
    }
}

/// A session's place in its fleet, for the APIs.
#[derive(Debug, Clone)]
pub struct MemberView {
    pub session_id: String,
    pub robot_id: String,
    pub frame: Option<FleetFrame>,
    /// The pose graph's correction of its latest keyframe (`fleet_corrected_from_fleet`).
    pub latest_correction: Option<Isometry3<f64>>,
    /// Its keyframes in the place index, and the oldest one's id.
    pub indexed_keyframes: usize,
    pub oldest_indexed_keyframe: Option<u64>,
}

/// A fleet, for the APIs.
#[derive(Debug, Clone)]
pub struct FleetView {
    pub name: String,
    pub members: Vec<MemberView>,
    pub indexed_keyframes: usize,
    pub last_correction: Option<GraphSolve>,
    /// A pose-graph solve is due (place edges came since the last one) or running:
    /// `last_correction` and the members' corrections are about to change.
    pub pose_graph_pending: bool,
    /// Place edges that sessions resumed from another server brought along and
    /// that wait for their keyframes to be indexed here.
    pub carried_edges_waiting: usize,
    /// The fused fleet map's counts, when it has one.
    pub map: Option<crate::fleet_map::FleetMapCounts>,
}

struct Shared {
    config: FleetConfig,
    vocabulary: Vocabulary,
    verify: VerifyConfig,
    /// An empty detector with the server's merge settings (each member starts from a copy).
    detector: MergeDetector,
    store: Option<Arc<Store>>,
    fleets: Mutex<HashMap<String, Fleet>>,
    /// Panics caught in the fleet's threads are counted here.
    metrics: Arc<crate::metrics::Metrics>,
}

/// The fleets and the place-recognition thread.
pub struct FleetService {
    shared: Arc<Shared>,
    /// Keyframes handed to place recognition and not yet done with.
    backlog: Arc<std::sync::atomic::AtomicUsize>,
    jobs: Mutex<Option<SyncSender<Work>>>,
    worker: Mutex<Option<std::thread::JoinHandle<()>>>,
    /// The pose-graph thread, and the sender whose drop stops it.
    solver: Mutex<Option<(std::sync::mpsc::Sender<()>, std::thread::JoinHandle<()>)>>,
    /// The fleets' fused maps and their thread.
    maps: crate::fleet_map::FleetMaps,
}

#[derive(Debug, thiserror::Error)]
pub enum FleetError {
    #[error("fleet.vocabulary_path {path}: {message}")]
    Vocabulary { path: String, message: String },
    #[error("cannot start the place-recognition or pose-graph thread: {0}")]
    Thread(std::io::Error),
    #[error("fleet: {0}")]
    Config(String),
}

impl FleetService {
    /// Loads the vocabulary and starts the place-recognition, pose-graph and fleet-map threads.
    pub fn start(
        config: &FleetConfig,
        mapping: &MappingConfig,
        store: Option<Arc<Store>>,
        metrics: Arc<crate::metrics::Metrics>,
    ) -> Result<Arc<Self>, FleetError> {
        let vocabulary = if config.vocabulary_path.is_empty() {
            Vocabulary::shipped()
        } else {
            let err = |message: String| FleetError::Vocabulary { path: config.vocabulary_path.clone(), message };
            let bytes = std::fs::read(&config.vocabulary_path).map_err(|e| err(e.to_string()))?;
            Vocabulary::from_bytes(&bytes).map_err(|e| err(e.to_string()))?
        };
        let verify = VerifyConfig { min_inliers: config.min_inliers, ..VerifyConfig::default() };
        let merge = MergeConfig {
            consistent: config.consistent_matches,
            max_translation_m: config.agreement_m,
            max_rotation_deg: config.agreement_deg,
            window: config.refine_support.max(config.consistent_matches),
        };
        let detector = MergeDetector::new(merge).map_err(|e| FleetError::Config(e.to_string()))?;
        let shared = Arc::new(Shared {
            config: config.clone(),
            vocabulary,
            verify,
            detector,
            store: store.clone(),
            fleets: Mutex::default(),
            metrics: metrics.clone(),
        });
        let (tx, rx) = std::sync::mpsc::sync_channel::<Work>(config.queue);
        let worker_shared = shared.clone();
        let backlog = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let worker_backlog = backlog.clone();
        let worker = std::thread::Builder::new()
            .name("places".into())
            .spawn(move || {
                for work in rx {
                    let carried = work.keyframes();
                    let (session, done) = match work {
                        Work::Keyframe(job) => (job.session_id.clone(), crate::pool::caught(|| worker_shared.process(job))),
                        Work::Stored(stored) => (stored.session_id.clone(), crate::pool::caught(|| worker_shared.index_stored(stored))),
                    };
                    if let Err(panic) = done {
                        worker_shared.metrics.panicked("places");
                        tracing::error!(
                            session,
                            "place recognition panicked (a bug; the keyframe or the stored keyframes are left out): {panic}"
                        );
                    }
                    worker_backlog.fetch_sub(carried, std::sync::atomic::Ordering::SeqCst);
                }
            })
            .map_err(FleetError::Thread)?;
        let solver = if config.graph_interval_s > 0.0 {
            let (stop, stopped) = std::sync::mpsc::channel::<()>();
            let solver_shared = shared.clone();
            let tick = Duration::from_secs_f64(config.graph_interval_s.min(0.25));
            let thread = std::thread::Builder::new()
                .name("pose-graph".into())
                .spawn(move || {
                    crate::lower_this_thread(solver_shared.config.nice, "pose-graph");
                    while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) = stopped.recv_timeout(tick) {
                        solver_shared.solve_due();
                    }
                })
                .map_err(FleetError::Thread)?;
            Some((stop, thread))
        } else {
            None
        };
        let maps_shared = shared.clone();
        let maps = crate::fleet_map::FleetMaps::start(
            crate::fleet_map::FleetMapConfig {
                mapping: mapping.clone(),
                queue: config.map_queue,
                max_keyframes: config.map_keyframes,
                refuse_per_pass: config.refuse_per_pass,
                nice: config.nice,
                save_interval: Duration::from_secs_f64(config.map_save_interval_s),
            },
            Arc::new(move |fleet: &str, session: &str| maps_shared.transform(fleet, session)),
            store,
            metrics,
        )
        .map_err(FleetError::Thread)?;
        Ok(Arc::new(Self {
            shared,
            backlog,
            jobs: Mutex::new(Some(tx)),
            worker: Mutex::new(Some(worker)),
            solver: Mutex::new(solver),
            maps,
        }))
    }

    /// The fleet of a hello that named `requested` (empty: the default fleet).
    /// The fleet a session belongs to: the one it named, the default where it named
    /// none. A name no hello could give (read from a store or the shared storage)
    /// is not made a fleet: the session goes to the default fleet, logged.
    pub fn fleet_for(&self, requested: &str) -> String {
        if requested.is_empty() {
            return self.shared.config.default_fleet.clone();
        }
        if let Err(e) = stillmap_proto::validate_fleet(requested) {
            tracing::error!("a stored session names no fleet a robot could ({e}): it goes to the default fleet");
            return self.shared.config.default_fleet.clone();
        }
        requested.to_string()
    }

    /// Hands a committed keyframe to place recognition; a full queue leaves it out.
    pub fn submit(&self, job: FleetJob) {
        if let Some(Work::Keyframe(job)) = self.enqueue(Work::Keyframe(job), false) {
            self.shared.metrics.fleet_keyframes_left_out("places", 1);
            tracing::warn!(session = %job.session_id, keyframe = job.keyframe.id, "place-recognition queue full (fleet.queue): keyframe left out");
        }
    }

    /// Hands the stored keyframes of a session resumed from another server to
    /// place recognition, which indexes them in its fleet here (a merged
    /// session's up to `fleet.max_places`; of an unmerged one's, those newer than
    /// it has there, its latest `fleet.pending_keyframes`): the session's map can
    /// be found by the fleet's other robots here at once, not only from its next
    /// keyframe. A full queue leaves them out (the session's next keyframes are
    /// indexed as usual), unless `wait` (a background reader) waits for room.
    pub fn index_stored(&self, stored: StoredKeyframes, wait: bool) {
        if stored.keyframes.is_empty() {
            return;
        }
        if let Some(Work::Stored(stored)) = self.enqueue(Work::Stored(stored), wait) {
            self.shared.metrics.fleet_keyframes_left_out("places", stored.keyframes.len());
            tracing::warn!(
                session = %stored.session_id,
                keyframes = stored.keyframes.len(),
                "place-recognition queue full (fleet.queue): the resumed session's stored keyframes left out of its fleet's index"
            );
        }
    }

    /// Queues `work` for the place-recognition thread (`wait`: for room in the
    /// queue); gives it back when the queue is full (nothing when the thread is
    /// stopping).
    fn enqueue(&self, work: Work, wait: bool) -> Option<Work> {
        let tx = lock(&self.jobs).clone()?;
        let n = work.keyframes();
        self.backlog.fetch_add(n, std::sync::atomic::Ordering::SeqCst);
        let (queued, back) = match (wait, tx.try_send(work)) {
            (_, Ok(())) => (true, None),
            (false, Err(TrySendError::Full(work))) => (false, Some(work)),
            (true, Err(TrySendError::Full(work))) => (tx.send(work).is_ok(), None),
            (_, Err(TrySendError::Disconnected(_))) => (false, None),
        };
        if !queued {
            self.backlog.fetch_sub(n, std::sync::atomic::Ordering::SeqCst);
        }
        back
    }

    /// Keyframes waiting for (or in) place recognition.
    pub fn backlog(&self) -> usize {
        self.backlog.load(std::sync::atomic::Ordering::SeqCst)
    }

    /// Whether a new session may join `fleet`: it exists, or there is room for one
    /// more under `fleet.max_fleets`. `Err` carries the fleets held and the limit.
    pub fn admits(&self, fleet: &str) -> Result<(), (usize, usize)> {
        let fleets = lock(&self.shared.fleets);
        let max = self.shared.config.max_fleets;
        if fleets.contains_key(fleet) || fleets.len() < max { Ok(()) } else { Err((fleets.len(), max)) }
    }

    /// Registers a new session in its fleet (the fleet's first anchors it).
    pub fn join(&self, fleet: &str, session_id: &str, robot_id: &str) {
        let mut fleets = lock(&self.shared.fleets);
        let f = fleets.entry(fleet.to_string()).or_default();
        self.shared.member(f, fleet, session_id, robot_id);
    }

    /// Registers a session resumed from another server with the frame it had in
    /// its fleet there (`carried`): kept when it is in this fleet's frame here (the
    /// same lineage), or when the fleet has no frame here yet (it then takes that
    /// lineage, and a new session here is merged into it rather than anchoring
    /// it); otherwise the session joins as a new one and place recognition merges
    /// it. Returns whether the carried frame was kept.
    pub fn join_carried(&self, fleet: &str, session_id: &str, robot_id: &str, carried: Option<FleetFrame>) -> bool {
        let mut fleets = lock(&self.shared.fleets);
        let f = fleets.entry(fleet.to_string()).or_default();
        if f.members.iter().any(|m| m.session_id == session_id) {
            return false;
        }
        // A frame read from the shared storage is used only if a merge could have
        // written it (finite, a unit rotation); else the session merges again here.
        let Some(mut frame) = carried.filter(|fr| fr.fleet == fleet && valid_pose7(&fr.fleet_from_session)) else {
            self.shared.member(f, fleet, session_id, robot_id);
            return false;
        };
        frame.lineage = frame.lineage_of(session_id);
        let here = lineage(f);
        if !here.is_empty() && here != frame.lineage {
            tracing::info!(fleet, session = session_id, "resumed with a merge in another frame of its fleet: merged again here");
            self.shared.member(f, fleet, session_id, robot_id);
            return false;
        }
        self.shared.persist(session_id, &frame);
        tracing::info!(fleet, session = session_id, anchor = frame.anchor, "resumed with its merge in its fleet's frame");
        f.members.push(self.shared.new_member(session_id, robot_id, Some(frame)));
        true
    }

    /// Puts back the share of its fleet's pose graph that a session resumed from
    /// another server brought along (call after [`Self::join_carried`] kept its
    /// frame): its corrections at once, so that its fleet-frame poses are those the
    /// other server served, and its place edges as soon as both their keyframes
    /// are indexed here (then the graph is solved again with them).
    pub fn carry_graph(&self, fleet: &str, session_id: &str, graph: SessionGraph) {
        let mut fleets = lock(&self.shared.fleets);
        let Some(f) = fleets.get_mut(fleet) else { return };
        let Some(m) = f.members.iter().position(|m| m.session_id == session_id && m.frame.is_some()) else { return };
        let max = self.shared.config.max_places;
        // Only what a solve could have written: finite, unit rotations, in time
        // order, at most one per place the fleet may index.
        if f.members[m].corrections.is_empty() {
            f.members[m].corrections = Arc::new(checked_corrections(&graph.corrections, max));
        }
        let mut known: std::collections::HashSet<EdgeKey> = f.carried_edges.iter().map(edge_key).collect();
        for e in graph.edges.into_iter().filter(|e| valid_pose7(&e.a_from_b)).take(max) {
            if known.insert(edge_key(&e)) {
                f.carried_edges.push_back(e);
            }
        }
        while f.carried_edges.len() > max {
            f.carried_edges.pop_front();
        }
        let carried = f.carried_edges.len();
        let promoted = promote_carried(f);
        tracing::info!(fleet, session = session_id, carried, promoted, "resumed with its share of the fleet's pose graph");
    }

    /// [`restore_with`](Self::restore_with) the keyframe records the heads carry
    /// (an imported session's).
    pub fn restore(&self, stored: &[SessionHead]) {
        self.restore_with(stored, |s, n| s.keyframes[s.keyframes.len().saturating_sub(n)..].to_vec());
    }

    /// Rebuilds the fleets from the store: sessions with a frame in their fleet,
    /// then the others, each in the order they started; their merges, and the
    /// keyframes of merged sessions in the index.
    /// A fleet that was already here (an import into a running server) keeps its
    /// live pose graph: only fleets this call brings get their stored one.
    /// `keyframes(s, n)` gives the newest `n` keyframe records of session `s`,
    /// oldest first; only those the index keeps are asked for (it keeps a fleet's
    /// newest `fleet.max_places`, and of an unmerged session its newest
    /// `fleet.pending_keyframes`), the newest sessions first: start-up holds at
    /// most `max_places` records a fleet however many sessions the store has.
    pub fn restore_with(&self, stored: &[SessionHead], keyframes: impl Fn(&SessionHead, usize) -> Vec<KeyframeRecord>) {
        let mut frames = match &self.shared.store {
            Some(store) => store.fleet_frames().unwrap_or_else(|e| {
                tracing::error!("fleet merges cannot be read from the store: {e}");
                HashMap::new()
            }),
            None => HashMap::new(),
        };
        frames.retain(|session, frame| {
            let valid = valid_pose7(&frame.fleet_from_session);
            if !valid {
                tracing::error!(session = session.as_str(), "a stored fleet merge is not a pose: left out, the session merges again");
            }
            valid
        });
        let mut order: Vec<&SessionHead> = stored.iter().collect();
        // Sessions with a frame first: one without, coming back before them, would
        // otherwise anchor a fleet whose frame came with a resumed session's merge.
        order.sort_by_key(|s| (!frames.contains_key(&s.id), s.meta.started_unix_ns, s.id.clone()));
        let mut fleets = lock(&self.shared.fleets);
        let live: std::collections::HashSet<String> = fleets.keys().cloned().collect();
        let mut members = Vec::with_capacity(order.len());
        for s in &order {
            let name = self.fleet_for(&s.meta.fleet);
            let f = fleets.entry(name.clone()).or_default();
            let m = match frames.get(&s.id).filter(|frame| frame.fleet == name) {
                Some(frame) => {
                    f.members.push(self.shared.new_member(&s.id, &s.meta.robot_id, Some(frame.clone())));
                    f.members.len() - 1
                }
                None => self.shared.member(f, &name, &s.id, &s.meta.robot_id),
            };
            members.push((name, m));
        }
        // What the index would keep of them, added in this order: the last
        // max_places of each fleet, an unmerged session's last pending_keyframes.
        // Read from the newest session back until each fleet has them.
        let (max_places, pending) = (self.shared.config.max_places, self.shared.config.pending_keyframes);
        let mut left: HashMap<&str, usize> = HashMap::new();
        let mut records = vec![Vec::new(); order.len()];
        for (i, (name, m)) in members.iter().enumerate().rev() {
            let room = left.entry(name.as_str()).or_insert(max_places);
            let merged = fleets.get(name).is_some_and(|f| f.members[*m].frame.is_some());
            let n = if merged { *room } else { pending.min(*room) };
            if n > 0 {
                records[i] = keyframes(order[i], n);
                *room = room.saturating_sub(records[i].len());
            }
        }
        for ((s, (name, m)), records) in order.iter().zip(&members).zip(records) {
            let camera = crate::convert::camera_of(&s.camera);
            if let Some(f) = fleets.get_mut(name) {
                for k in &records {
                    self.shared.add_keyframe(f, *m, &camera, k);
                }
            }
        }
        let graphs = match &self.shared.store {
            Some(store) => store.fleet_graphs().unwrap_or_else(|e| {
                tracing::error!("fleet pose graphs cannot be read from the store: {e}");
                HashMap::new()
            }),
            None => HashMap::new(),
        };
        let (max_places, max_edges) = (self.shared.config.max_places, self.shared.max_edges());
        for (name, graph) in graphs {
            if !live.contains(&name)
                && let Some(f) = fleets.get_mut(&name)
            {
                restore_graph(f, graph, max_places, max_edges);
            }
        }
    }

    /// Every fleet, by name.
    pub fn list(&self) -> Vec<FleetView> {
        let mut all: Vec<FleetView> = lock(&self.shared.fleets).iter().map(|(name, f)| view(name, f)).collect();
        all.sort_by(|a, b| a.name.cmp(&b.name));
        all.into_iter().map(|v| self.with_map(v)).collect()
    }

    /// Whether this server holds fleet `name` (what a forwarded query about it asks).
    pub fn holds(&self, name: &str) -> bool {
        lock(&self.shared.fleets).contains_key(name)
    }

    pub fn get(&self, name: &str) -> Option<FleetView> {
        let v = lock(&self.shared.fleets).get(name).map(|f| view(name, f))?;
        Some(self.with_map(v))
    }

    fn with_map(&self, mut v: FleetView) -> FleetView {
        v.map = self.maps.state(&v.name).map(|s| s.counts());
        v
    }

    /// A merged session's transform into the fleet frame, with the pose graph's corrections.
    pub fn fleet_transform(&self, fleet: &str, session_id: &str) -> Option<FleetTransform> {
        self.shared.transform(fleet, session_id)
    }

    /// Hands a session's map-lane work to its fleet's fused map.
    pub fn submit_map(&self, job: crate::fleet_map::FleetMapJob) {
        self.maps.submit(job);
    }

    /// Fleet `name`'s fused map, when it has one.
    pub fn map_state(&self, name: &str) -> Option<Arc<crate::fleet_map::FleetMapHandle>> {
        self.maps.state(name)
    }

    /// Solves the pose graph of every fleet with new place edges now (tests; the
    /// pose-graph thread does it every `fleet.graph_interval_s`).
    pub fn solve_now(&self) {
        let names: Vec<String> = lock(&self.shared.fleets).iter().filter(|(_, f)| f.dirty).map(|(n, _)| n.clone()).collect();
        for name in names {
            self.shared.solve(&name);
        }
    }

    /// Waits until every submitted keyframe has been processed, and stops the threads.
    pub fn close(&self) {
        lock(&self.jobs).take();
        if let Some(worker) = lock(&self.worker).take() {
            let _ = worker.join();
        }
        if let Some((stop, thread)) = lock(&self.solver).take() {
            drop(stop);
            let _ = thread.join();
        }
        self.maps.close();
    }
}

fn pose7(p: &Isometry3<f64>) -> [f64; 7] {
    let (v, q) = (p.translation.vector, p.rotation.coords);
    [v.x, v.y, v.z, q.x, q.y, q.z, q.w]
}

/// A fleet's pose graph as the store keeps it.
fn stored_graph(f: &Fleet) -> FleetGraph {
    let key = |k: &(u32, u64)| f.members.get(k.0 as usize).map(|m| (m.session_id.clone(), k.1));
    let edges = f
        .edges
        .iter()
        .filter_map(|e| Some(GraphEdge { a: key(&e.a)?, b: key(&e.b)?, a_from_b: pose7(&e.a_from_b), is_loop: e.kind == EdgeKind::Loop }))
        .collect();
    let corrections = f
        .members
        .iter()
        .filter(|m| !m.corrections.is_empty())
        .map(|m| (m.session_id.clone(), m.corrections.iter().map(|(t, c)| (*t, pose7(c))).collect()))
        .collect();
    FleetGraph { edges, corrections, last_solve: f.last_correction.clone() }
}

/// Puts a stored pose graph back: its edges and corrections for the sessions the
/// fleet has (merged ones: a correction is relative to the merge). Only what a
/// solve could have written comes back, as for a carried share: edges with a pose,
/// the newest `max_edges` of them (as many as a live fleet keeps), and
/// [`checked_corrections`] (at most `max_places` per session).
fn restore_graph(f: &mut Fleet, g: FleetGraph, max_places: usize, max_edges: usize) {
    let member = |f: &Fleet, session: &str| f.members.iter().position(|m| m.session_id == session && m.frame.is_some());
    let mut edges: Vec<PlaceEdge> = g
        .edges
        .iter()
        .filter(|e| valid_pose7(&e.a_from_b))
        .filter_map(|e| {
            let a = (member(f, &e.a.0)? as u32, e.a.1);
            let b = (member(f, &e.b.0)? as u32, e.b.1);
            let kind = if e.is_loop { EdgeKind::Loop } else { EdgeKind::InterSession };
            Some(PlaceEdge { a, b, a_from_b: isometry(&e.a_from_b), kind })
        })
        .collect();
    // Stored in the order they were found: the oldest go first.
    let skip = edges.len().saturating_sub(max_edges);
    f.edges = edges.split_off(skip);
    for (session, list) in &g.corrections {
        if let Some(m) = member(f, session) {
            f.members[m].corrections = Arc::new(checked_corrections(list, max_places));
        }
    }
    f.last_correction = g.last_solve;
}

/// A session's corrections as a solve could have written them, from stored or
/// carried numbers: poses only ([`valid_pose7`]), in time order (served by a binary
/// search), one per time, the latest `max` (one per place the fleet may index).
fn checked_corrections(list: &[(u64, [f64; 7])], max: usize) -> Vec<(u64, Isometry3<f64>)> {
    let mut corrections: Vec<(u64, Isometry3<f64>)> =
        list.iter().filter(|(_, c)| valid_pose7(c)).map(|(t, c)| (*t, exact_isometry(c))).collect();
    corrections.sort_by_key(|(t, _)| *t);
    corrections.dedup_by_key(|(t, _)| *t);
    let skip = corrections.len().saturating_sub(max);
    corrections.split_off(skip)
}

/// An edge's two ends, in either order.
type EdgeKey = ((String, u64), (String, u64));

fn edge_key(e: &GraphEdge) -> EdgeKey {
    unordered(e.a.clone(), e.b.clone())
}

/// A pair in order, whichever way it came.
fn unordered<T: PartialOrd>(a: T, b: T) -> (T, T) {
    if a <= b { (a, b) } else { (b, a) }
}

/// Whether stored numbers are a pose a solve could have written: finite, with a
/// unit quaternion.
fn valid_pose7(p: &[f64; 7]) -> bool {
    p.iter().all(|v| v.is_finite()) && ((p[3] * p[3] + p[4] * p[4] + p[5] * p[5] + p[6] * p[6]).sqrt() - 1.0).abs() < 1e-6
}

/// A stored pose as it was stored (unit when written): not normalised again, so
/// that a restart or another server serves the same poses.
fn exact_isometry(p: &[f64; 7]) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), UnitQuaternion::new_unchecked(Quaternion::new(p[6], p[3], p[4], p[5])))
}

/// Moves the carried edges whose keyframes are both indexed here (of members
/// with a frame) into the fleet's edges, unless it has the same edge already;
/// the fleet is then due a solve. Returns how many were moved.
fn promote_carried(f: &mut Fleet) -> usize {
    if f.carried_edges.is_empty() {
        return 0;
    }
    let member = |f: &Fleet, session: &str| f.members.iter().position(|m| m.session_id == session && m.frame.is_some());
    let mut present: std::collections::HashSet<((u32, u64), (u32, u64))> = f.edges.iter().map(|e| unordered(e.a, e.b)).collect();
    let mut promoted = 0;
    let mut waiting = VecDeque::with_capacity(f.carried_edges.len());
    for e in std::mem::take(&mut f.carried_edges) {
        let ends = member(f, &e.a.0).zip(member(f, &e.b.0)).map(|(ma, mb)| ((ma as u32, e.a.1), (mb as u32, e.b.1)));
        match ends.filter(|(a, b)| f.places.contains_key(a) && f.places.contains_key(b)) {
            Some((a, b)) => {
                if present.insert(unordered(a, b)) {
                    let kind = if e.is_loop { EdgeKind::Loop } else { EdgeKind::InterSession };
                    f.edges.push(PlaceEdge { a, b, a_from_b: isometry(&e.a_from_b), kind });
                    promoted += 1;
                }
            }
            None => waiting.push_back(e),
        }
    }
    f.carried_edges = waiting;
    if promoted > 0 {
        f.dirty = true;
    }
    promoted
}

/// A share is copied again only when its edges changed or a correction moved
/// more than this (metres, degrees) since the last copy.
const SHARE_MIN_MOVE_M: f64 = 0.001;
const SHARE_MIN_MOVE_DEG: f64 = 0.05;

/// Each merged member's share of the stored graph (its corrections, the edges
/// with one of its keyframes at either end, and the carried ones still waiting,
/// at most `max_edges`), by session id: what goes with it to another server.
/// Only shares that changed since they were last copied (the member remembers
/// what it copied).
fn session_graphs(f: &mut Fleet, stored: &FleetGraph, solved_unix_ns: u64, max_edges: usize) -> Vec<(String, SessionGraph)> {
    let mut edges_of: HashMap<&str, Vec<&GraphEdge>> = HashMap::new();
    for e in stored.edges.iter().chain(&f.carried_edges) {
        edges_of.entry(e.a.0.as_str()).or_default().push(e);
        if e.b.0 != e.a.0 {
            edges_of.entry(e.b.0.as_str()).or_default().push(e);
        }
    }
    let mut out = Vec::new();
    for m in f.members.iter_mut().filter(|m| m.frame.is_some()) {
        let edges: Vec<GraphEdge> =
            edges_of.get(m.session_id.as_str()).map_or(Vec::new(), |v| v.iter().take(max_edges).map(|e| (*e).clone()).collect());
        let unchanged = m.shared.as_ref().is_some_and(|(corrections, n)| {
            *n == edges.len()
                && corrections.len() == m.corrections.len()
                && corrections.iter().zip(m.corrections.iter()).all(|((ta, a), (tb, b))| {
                    let d = a.inverse() * b;
                    ta == tb && d.translation.vector.norm() <= SHARE_MIN_MOVE_M && d.rotation.angle().to_degrees() <= SHARE_MIN_MOVE_DEG
                })
        });
        if unchanged {
            continue;
        }
        m.shared = Some((m.corrections.clone(), edges.len()));
        let corrections = m.corrections.iter().map(|(t, c)| (*t, pose7(c))).collect();
        out.push((m.session_id.clone(), SessionGraph { corrections, edges, solved_unix_ns }));
    }
    out
}

fn view(name: &str, f: &Fleet) -> FleetView {
    FleetView {
        name: name.to_string(),
        members: f
            .members
            .iter()
            .map(|m| MemberView {
                session_id: m.session_id.clone(),
                robot_id: m.robot_id.clone(),
                frame: m.frame.clone(),
                latest_correction: m.corrections.last().map(|(_, c)| *c),
                indexed_keyframes: m.indexed.len(),
                oldest_indexed_keyframe: m.indexed.iter().min().copied(),
            })
            .collect(),
        indexed_keyframes: f.index.len(),
        last_correction: f.last_correction.clone(),
        pose_graph_pending: f.dirty || f.solving > 0,
        carried_edges_waiting: f.carried_edges.len(),
        map: None,
    }
}

impl Shared {
    /// The place edges a fleet keeps at most before it drops those of forgotten
    /// keyframes (each keyframe brings at most 2 × `fleet.candidates`).
    fn max_edges(&self) -> usize {
        4 * self.config.max_places * self.config.candidates
    }

    fn transform(&self, fleet: &str, session_id: &str) -> Option<FleetTransform> {
        let fleets = lock(&self.fleets);
        let member = fleets.get(fleet)?.members.iter().find(|m| m.session_id == session_id)?;
        member
            .frame
            .as_ref()
            .map(|f| FleetTransform { fleet_from_session: isometry(&f.fleet_from_session), corrections: member.corrections.clone() })
    }

    fn new_member(&self, session_id: &str, robot_id: &str, frame: Option<FleetFrame>) -> Member {
        Member {
            session_id: session_id.to_string(),
            robot_id: robot_id.to_string(),
            frame,
            detector: self.detector.clone(),
            indexed: VecDeque::new(),
            heard: 0,
            keyframe_span_ns: None,
            corrections: Arc::default(),
            shared: None,
        }
    }

    /// The member for `session_id`, added when new: the fleet's first session
    /// anchors its frame (committed to the store).
    fn member(&self, f: &mut Fleet, fleet: &str, session_id: &str, robot_id: &str) -> usize {
        if let Some(m) = f.members.iter().position(|m| m.session_id == session_id) {
            return m;
        }
        // A fleet with a frame has its anchor, here or where a resumed session's
        // merge came from (`join_carried`).
        let anchor = !f.members.iter().any(|m| m.frame.is_some());
        let frame = anchor.then(|| FleetFrame {
            fleet: fleet.to_string(),
            fleet_from_session: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            anchor: true,
            support: 0,
            inliers: 0,
            merged_unix_ns: now_ns(),
            first_merged_unix_ns: now_ns(),
            merged_after_ns: 0,
            lineage: session_id.to_string(),
        });
        if let Some(frame) = &frame {
            self.persist(session_id, frame);
            tracing::info!(fleet, session = session_id, "session anchors its fleet's frame");
        }
        f.members.push(self.new_member(session_id, robot_id, frame));
        f.members.len() - 1
    }

    fn persist(&self, session_id: &str, frame: &FleetFrame) {
        if let Some(store) = &self.store
            && let Err(e) = store.put_fleet_frame(session_id, frame)
        {
            tracing::error!(session = session_id, "fleet frame not persisted (the store failed): {e}");
        }
    }

    /// Whether member `m`'s merge still takes proposals: unmerged, or merged and
    /// fewer than `fleet.refine_support` proposals heard (never the anchor; a merge
    /// restored from the store is final).
    fn refining(&self, f: &Fleet, m: usize) -> bool {
        let member = &f.members[m];
        member.frame.as_ref().is_none_or(|fr| !fr.anchor && member.heard > 0 && member.heard < self.config.refine_support)
    }

    /// One committed keyframe: indexed, then looked up both ways, so that the
    /// order in which two sessions' keyframes arrive does not matter. A keyframe of
    /// a session still refining its merge is verified against merged sessions'
    /// keyframes (proposals for its own session); a keyframe of a merged session
    /// against refining sessions' keyframes (proposals for theirs).
    fn process(&self, job: FleetJob) {
        let started = Instant::now();
        let (place, bow, session_from_query) = self.place_of(&job.camera, &job.keyframe);
        let query_key = |m: usize| (m as u32, job.keyframe.id);
        // (the candidate's key, fleet_from_query or None, fleet_from_candidate or
        // None, session_from_candidate, place, whether the match is a pose-graph edge)
        type Candidate = ((u32, u64), Option<Isometry3<f64>>, Option<Isometry3<f64>>, Isometry3<f64>, Arc<Place>, bool);
        let (m, candidates) = {
            let mut fleets = lock(&self.fleets);
            let f = fleets.entry(job.fleet.clone()).or_default();
            let m = self.member(f, &job.fleet, &job.session_id, &job.robot_id);
            let m_refining = self.refining(f, m);
            let m_frame = f.members[m].frame.as_ref().map(|fr| isometry(&fr.fleet_from_session));
            let found = f.index.query(&bow, self.config.candidates, 0.0, |k| {
                let r = k.0 as usize;
                r != m && ((m_refining && f.members[r].frame.is_some()) || (m_frame.is_some() && self.refining(f, r)))
            });
            // The pose graph's edges: a merged keyframe against other merged
            // sessions' keyframes and its own session's older ones (loops).
            let graph = self.config.graph_interval_s > 0.0 && m_frame.is_some();
            let min_age_ns = (self.config.loop_min_age_s * 1e9) as u64;
            let t = job.keyframe.timestamp_ns;
            let for_graph = if graph {
                f.index.query(&bow, self.config.candidates, 0.0, |k| {
                    let r = k.0 as usize;
                    f.members[r].frame.is_some()
                        && !found.iter().any(|(seen, _)| seen == k)
                        && (r != m || f.places.get(k).is_some_and(|p| p.timestamp_ns.saturating_add(min_age_ns) <= t))
                })
            } else {
                Vec::new()
            };
            let candidates: Vec<Candidate> = found
                .iter()
                .map(|(k, _)| (*k, false))
                .chain(for_graph.iter().map(|(k, _)| (*k, true)))
                .filter_map(|(k, graph_only)| {
                    let r = k.0 as usize;
                    let Indexed { session_from_camera: session_from_candidate, place: candidate, .. } = f.places.get(&k)?;
                    let fleet_from_candidate =
                        f.members[r].frame.as_ref().map(|fr| isometry(&fr.fleet_from_session) * session_from_candidate);
                    let fleet_from_query = m_frame.filter(|_| !graph_only && self.refining(f, r)).map(|t| t * session_from_query);
                    let fleet_from_candidate = fleet_from_candidate.filter(|_| !graph_only && m_refining);
                    // Every verified match is an edge; the graph takes those between merged sessions.
                    let edge = self.config.graph_interval_s > 0.0;
                    Some((k, fleet_from_query, fleet_from_candidate, *session_from_candidate, candidate.clone(), edge))
                })
                .collect();
            let span = &mut f.members[m].keyframe_span_ns;
            *span = Some(span.map_or((t, t), |(first, last)| (first.min(t), last.max(t))));
            let indexed = Indexed { session_from_camera: session_from_query, place: place.clone(), timestamp_ns: t };
            self.add_place(f, m, job.keyframe.id, indexed, bow);
            (m, candidates)
        };
        // Verification (the expensive part) holds no lock. Per target member, the
        // proposal of the verification with the most inliers.
        let mut best: HashMap<usize, (Isometry3<f64>, usize)> = HashMap::new();
        let mut edges = Vec::new();
        for (k, fleet_from_query, fleet_from_candidate, session_from_candidate, candidate, edge) in &candidates {
            let Some(v) = verify(&job.camera, &place, candidate, &self.verify) else { continue };
            let r = k.0 as usize;
            let mut offer = |target: usize, proposal: Isometry3<f64>| {
                if best.get(&target).is_none_or(|b| v.inliers > b.1) {
                    best.insert(target, (proposal, v.inliers));
                }
            };
            if let Some(fleet_from_candidate) = fleet_from_candidate {
                offer(m, propose(fleet_from_candidate, &v.query_from_candidate, &session_from_query));
            }
            if let Some(fleet_from_query) = fleet_from_query {
                // The candidate's session from the query side: fleet ← query ← candidate ← its session.
                offer(r, fleet_from_query * v.query_from_candidate * session_from_candidate.inverse());
            }
            if *edge {
                let kind = if r == m { EdgeKind::Loop } else { EdgeKind::InterSession };
                edges.push(PlaceEdge { a: query_key(m), b: *k, a_from_b: v.query_from_candidate, kind });
            }
        }
        let mut fleets = lock(&self.fleets);
        let Some(f) = fleets.get_mut(&job.fleet) else { return };
        for (target, (proposal, inliers)) in best {
            self.observe(f, &job.fleet, target, proposal, inliers, started);
        }
        if !edges.is_empty() {
            f.edges.extend(edges);
            f.dirty = true;
            // Bounded: edges of forgotten keyframes go (each keyframe brings at most
            // 2 × `fleet.candidates`).
            if f.edges.len() > self.max_edges() {
                let places = &f.places;
                f.edges.retain(|e| places.contains_key(&e.a) && places.contains_key(&e.b));
            }
        }
    }

    /// Solves every fleet whose graph has new place edges and whose last solve is
    /// `fleet.graph_interval_s` old (the pose-graph thread).
    fn solve_due(&self) {
        let interval = Duration::from_secs_f64(self.config.graph_interval_s);
        let due: Vec<String> = lock(&self.fleets)
            .iter()
            .filter(|(_, f)| f.dirty && f.last_solve.is_none_or(|t| t.elapsed() >= interval))
            .map(|(n, _)| n.clone())
            .collect();
        for name in due {
            self.solve(&name);
        }
    }

    /// One solve of fleet `name`'s pose graph (see [`Self::solve_graph`]); the fleet
    /// says a solve is pending (`FleetView::pose_graph_pending`) until this returns.
    fn solve(&self, name: &str) {
        match lock(&self.fleets).get_mut(name) {
            Some(f) => f.solving += 1,
            None => return,
        }
        if let Err(panic) = crate::pool::caught(|| self.solve_graph(name)) {
            self.metrics.panicked("pose_graph");
            tracing::error!(fleet = name, "the pose graph solve panicked (a bug; the fleet keeps its last corrections): {panic}");
        }
        if let Some(f) = lock(&self.fleets).get_mut(name) {
            f.solving = f.solving.saturating_sub(1);
        }
    }

    /// Merged sessions' indexed keyframes in the fleet frame, odometry edges between
    /// a session's consecutive keyframes, the place edges; the anchor's first
    /// keyframe held. The lock is held only to take the graph and to hand the
    /// corrections back.
    fn solve_graph(&self, name: &str) {
        let c = &self.config;
        let (graph, keys, raws, fixed, counts) = {
            let mut fleets = lock(&self.fleets);
            let Some(f) = fleets.get_mut(name) else { return };
            f.dirty = false;
            f.last_solve = Some(Instant::now());
            let places = &f.places;
            f.edges.retain(|e| places.contains_key(&e.a) && places.contains_key(&e.b));
            let mut graph = PoseGraph::default();
            let mut keys: Vec<(u32, u64)> = Vec::new();
            // Each keyframe's fleet pose without correction; the graph starts from
            // the corrected ones (the last solve's, or those a resumed session
            // brought), so the keyframe held fixed stays where it was served.
            let mut raws: Vec<Isometry3<f64>> = Vec::new();
            let mut node: HashMap<(u32, u64), usize> = HashMap::new();
            let mut fixed = None;
            let (mut odometry, mut loops, mut inter) = (0, 0, 0);
            for (mi, member) in f.members.iter().enumerate() {
                let Some(frame) = &member.frame else { continue };
                let fleet_from_session = isometry(&frame.fleet_from_session);
                let transform = FleetTransform { fleet_from_session, corrections: member.corrections.clone() };
                let mut mine: Vec<(u64, u64, Isometry3<f64>)> = member
                    .indexed
                    .iter()
                    .filter_map(|id| f.places.get(&(mi as u32, *id)).map(|p| (p.timestamp_ns, *id, p.session_from_camera)))
                    .collect();
                mine.sort_by_key(|(t, id, _)| (*t, *id));
                let mut previous: Option<(usize, Isometry3<f64>)> = None;
                for (t, id, session_from_camera) in mine {
                    let i = graph.add_pose(transform.at(t) * session_from_camera);
                    raws.push(fleet_from_session * session_from_camera);
                    keys.push((mi as u32, id));
                    node.insert((mi as u32, id), i);
                    if frame.anchor && fixed.is_none() {
                        fixed = Some(i);
                    }
                    if let Some((p, session_from_previous)) = previous {
                        let edge = Edge {
                            from: p,
                            to: i,
                            from_from_to: session_from_previous.inverse() * session_from_camera,
                            kind: EdgeKind::Odometry,
                            sigma_rotation_rad: c.odometry_sigma_deg.to_radians(),
                            sigma_translation_m: c.odometry_sigma_m,
                        };
                        if graph.add_edge(edge).is_ok() {
                            odometry += 1;
                        }
                    }
                    previous = Some((i, session_from_camera));
                }
            }
            for e in &f.edges {
                let (Some(&a), Some(&b)) = (node.get(&e.a), node.get(&e.b)) else { continue };
                let edge = Edge {
                    from: a,
                    to: b,
                    from_from_to: e.a_from_b,
                    kind: e.kind,
                    sigma_rotation_rad: c.place_sigma_deg.to_radians(),
                    sigma_translation_m: c.place_sigma_m,
                };
                if graph.add_edge(edge).is_ok() {
                    match e.kind {
                        EdgeKind::Loop => loops += 1,
                        _ => inter += 1,
                    }
                }
            }
            if loops + inter == 0 {
                return;
            }
            (graph, keys, raws, fixed.unwrap_or(0), (odometry, loops, inter))
        };
        let started = Instant::now();
        let solved = match graph.optimize(&SolveConfig { fixed, reweight_rounds: c.reweight_rounds, ..SolveConfig::default() }) {
            Ok(solved) => solved,
            Err(e) => {
                tracing::warn!(fleet = name, "pose graph not solved (the fleet keeps its last corrections): {e}");
                return;
            }
        };
        let solve_ms = started.elapsed().as_secs_f64() * 1e3;
        let (mut moved, mut max_t, mut max_r) = (0, 0.0f64, 0.0f64);
        let mut corrections: HashMap<u32, Vec<(u64, Isometry3<f64>)>> = HashMap::new();
        let mut fleets = lock(&self.fleets);
        let Some(f) = fleets.get_mut(name) else { return };
        for (i, key) in keys.iter().enumerate() {
            let (before, after) = (&graph.poses[i], &solved[i]);
            let dt = (after.translation.vector - before.translation.vector).norm();
            let dr = (after.rotation * before.rotation.inverse()).angle().to_degrees();
            moved += usize::from(dt > 0.01 || dr > 0.5);
            max_t = max_t.max(dt);
            max_r = max_r.max(dr);
            let stamp = f.places.get(key).map_or(0, |p| p.timestamp_ns);
            corrections.entry(key.0).or_default().push((stamp, after * raws[i].inverse()));
        }
        for (mi, list) in corrections {
            if let Some(member) = f.members.get_mut(mi as usize).filter(|m| m.frame.is_some()) {
                member.corrections = Arc::new(list);
            }
        }
        let (odometry_edges, loop_edges, inter_session_edges) = counts;
        let correction = GraphSolve {
            solved_unix_ns: now_ns(),
            keyframes: keys.len(),
            odometry_edges,
            loop_edges,
            inter_session_edges,
            moved_keyframes: moved,
            max_translation_m: max_t,
            max_rotation_deg: max_r,
            solve_ms,
        };
        tracing::info!(
            fleet = name,
            keyframes = keys.len(),
            loop_edges,
            inter_session_edges,
            moved,
            max_translation_m = max_t,
            solve_ms,
            "fleet pose graph solved"
        );
        f.last_correction = Some(correction);
        let Some(store) = &self.store else { return };
        let stored = stored_graph(f);
        // Each session's share goes with it to a server that resumes it.
        let solved_unix_ns = f.last_correction.as_ref().map_or(0, |c| c.solved_unix_ns);
        let replica = store.replica();
        let shares = replica.map(|_| session_graphs(f, &stored, solved_unix_ns, self.config.max_places)).unwrap_or_default();
        drop(fleets);
        if let Err(e) = store.put_fleet_graph(name, &stored) {
            tracing::error!(fleet = name, "pose graph not persisted (the store failed): {e}");
        }
        if let Some(replica) = replica {
            for (session, share) in shares {
                match serde_json::to_string(&share) {
                    Ok(json) => replica.fleet_graph(&session, json),
                    Err(e) => tracing::error!(fleet = name, session, "pose-graph share not copied: {e}"),
                }
            }
        }
    }

    /// A proposal for member `t`'s `fleet_from_session`: a merge, or a refinement of it.
    fn observe(&self, f: &mut Fleet, fleet: &str, t: usize, proposal: Isometry3<f64>, inliers: usize, started: Instant) {
        if !self.refining(f, t) {
            return;
        }
        f.members[t].heard += 1;
        let Some(merged) = f.members[t].detector.observe(proposal, inliers) else { return };
        if f.members[t].frame.as_ref().is_some_and(|fr| fr.support >= merged.support) {
            return; // no more support than the merge already has
        }
        let fleet_lineage = lineage(f);
        let member = &mut f.members[t];
        let now = now_ns();
        let (first_merged_unix_ns, merged_after_ns) = match &member.frame {
            Some(fr) => (fr.first_merged_unix_ns, fr.merged_after_ns),
            None => (now, member.keyframe_span_ns.map_or(0, |(first, last)| last.saturating_sub(first))),
        };
        let frame = FleetFrame {
            fleet: fleet.to_string(),
            fleet_from_session: pose7(&merged.fleet_from_session),
            anchor: false,
            support: merged.support,
            inliers: merged.inliers,
            merged_unix_ns: now,
            first_merged_unix_ns,
            merged_after_ns,
            lineage: fleet_lineage,
        };
        self.persist(&member.session_id, &frame);
        tracing::info!(
            fleet,
            session = %member.session_id,
            support = merged.support,
            inliers = merged.inliers,
            ms = started.elapsed().as_secs_f64() * 1e3,
            "{}",
            if member.frame.is_some() { "merge refined" } else { "session merged into its fleet's frame" }
        );
        member.frame = Some(frame);
        // The matches heard before the merge join the pose graph now.
        f.dirty = true;
    }

    /// Indexes a resumed session's stored keyframes (see
    /// [`FleetService::index_stored`]); those already indexed are skipped. The
    /// bags of words are computed without the lock.
    fn index_stored(&self, stored: StoredKeyframes) {
        let StoredKeyframes { fleet, session_id, camera, keyframes } = stored;
        let (m, chosen) = {
            let fleets = lock(&self.fleets);
            let Some(f) = fleets.get(&fleet) else { return };
            let Some(m) = f.members.iter().position(|member| member.session_id == session_id) else { return };
            let member = &f.members[m];
            // An unmerged member keeps only its latest: older ones would push them out.
            let (keep, after) = match member.frame {
                Some(_) => (self.config.max_places, None),
                None => (self.config.pending_keyframes, member.indexed.iter().max().copied()),
            };
            let mut new: Vec<&KeyframeRecord> =
                keyframes.iter().filter(|k| !f.places.contains_key(&(m as u32, k.id)) && after.is_none_or(|a| k.id > a)).collect();
            new.sort_by_key(|k| k.id);
            let skip = new.len().saturating_sub(keep);
            (m, new.into_iter().skip(skip).collect::<Vec<_>>())
        };
        let places: Vec<(u64, Indexed, BowVector)> = chosen
            .into_iter()
            .map(|k| {
                let (place, bow, session_from_camera) = self.place_of(&camera, k);
                (k.id, Indexed { session_from_camera, place, timestamp_ns: k.timestamp_ns }, bow)
            })
            .collect();
        let mut fleets = lock(&self.fleets);
        let Some(f) = fleets.get_mut(&fleet) else { return };
        let count = places.len();
        // Those older than every keyframe it has indexed go in as the oldest, newest
        // of them first; the others as new ones, oldest first.
        let oldest_here = f.members[m].indexed.iter().min().copied();
        let (older, newer): (Vec<_>, Vec<_>) = places.into_iter().partition(|(id, _, _)| oldest_here.is_some_and(|o| *id < o));
        for (id, indexed, bow) in older.into_iter().rev() {
            self.index_at(f, m, id, indexed, bow, true);
        }
        for (id, indexed, bow) in newer {
            self.add_place(f, m, id, indexed, bow);
        }
        let promoted = promote_carried(f);
        tracing::debug!(
            fleet,
            session = session_id,
            keyframes = count,
            promoted,
            "a resumed session's stored keyframes indexed in its fleet"
        );
    }

    /// Adds a stored keyframe of member `m`.
    fn add_keyframe(&self, f: &mut Fleet, m: usize, camera: &Camera, record: &KeyframeRecord) {
        let (place, bow, session_from_camera) = self.place_of(camera, record);
        let indexed = Indexed { session_from_camera, place, timestamp_ns: record.timestamp_ns };
        self.add_place(f, m, record.id, indexed, bow);
    }

    /// Indexes a keyframe of member `m`; an unmerged member keeps only its latest
    /// `fleet.pending_keyframes` there.
    fn add_place(&self, f: &mut Fleet, m: usize, id: u64, indexed: Indexed, bow: BowVector) {
        // Room among its own first: the fleet-wide limit then takes no other
        // member's place for one this member lets go of at once.
        if f.members[m].frame.is_none() && !f.places.contains_key(&(m as u32, id)) {
            while f.members[m].indexed.len() >= self.config.pending_keyframes.max(1) {
                if let Some(old) = f.members[m].indexed.pop_front() {
                    f.index.remove(&(m as u32, old));
                    f.places.remove(&(m as u32, old));
                }
            }
        }
        self.index_at(f, m, id, indexed, bow, false);
        if f.members[m].frame.is_none() {
            while f.members[m].indexed.len() > self.config.pending_keyframes {
                if let Some(old) = f.members[m].indexed.pop_front() {
                    f.index.remove(&(m as u32, old));
                    f.places.remove(&(m as u32, old));
                }
            }
        }
    }

    /// Indexes keyframe `id` of member `m`: as the newest in the fleet, or, when
    /// `older` (a resumed session's keyframe older than any of its indexed ones),
    /// as the oldest, the first forgotten beyond `fleet.max_places` (so stored
    /// history never pushes out the fleet's current keyframes).
    fn index_at(&self, f: &mut Fleet, m: usize, id: u64, indexed: Indexed, bow: BowVector, older: bool) {
        let Indexed { session_from_camera, place, timestamp_ns } = indexed;
        let key = (m as u32, id);
        // As a candidate, only the features with depth count, and of them only the
        // point and the descriptor (verification reads the query's pixels).
        let with_depth: Vec<usize> = (0..place.len()).filter(|&i| place.points[i].is_some()).collect();
        let place = Arc::new(Place {
            pixels: Vec::new(),
            octaves: Vec::new(),
            points: with_depth.iter().map(|&i| place.points[i]).collect(),
            descriptors: with_depth.iter().map(|&i| place.descriptors[i]).collect(),
        });
        f.index.insert(key, bow);
        if f.places.insert(key, Indexed { session_from_camera, place, timestamp_ns }).is_none() {
            if older {
                f.order.push_front(key);
                f.members[m].indexed.push_front(id);
            } else {
                f.order.push_back(key);
                f.members[m].indexed.push_back(id);
            }
        }
        // The oldest first (keys an unmerged member dropped already are skipped).
        while f.places.len() > self.config.max_places {
            let Some(old) = f.order.pop_front() else { break };
            if f.places.remove(&old).is_some() {
                f.index.remove(&old);
                if let Some(member) = f.members.get_mut(old.0 as usize) {
                    member.indexed.retain(|&k| k != old.1);
                }
            }
        }
        if f.order.len() > 2 * self.config.max_places {
            f.order.retain(|k| f.places.contains_key(k));
        }
    }

    /// A stored keyframe as place recognition sees it: the features with depth
    /// (only those can be registered), its bag of words (from all its descriptors)
    /// and `world_from_camera`.
    fn place_of(&self, camera: &Camera, k: &KeyframeRecord) -> (Arc<Place>, BowVector, Isometry3<f64>) {
        let (place, world_from_camera) = place_of_record(camera, k);
        let bow = self.vocabulary.transform(&place.descriptors);
        (Arc::new(place), bow, world_from_camera)
    }
}

/// A stored keyframe as place verification sees it (every feature: its ideal pixel,
/// octave, 3D point when it had depth, descriptor), and its `world_from_camera`.
pub fn place_of_record(camera: &Camera, k: &KeyframeRecord) -> (Place, Isometry3<f64>) {
    let mut place = Place::default();
    for ([x, y], octave, depth, descriptor) in &k.features {
        let ideal = camera.undistort(&Point2::new(f64::from(*x), f64::from(*y)));
        let z = f64::from(*depth);
        place.pixels.push(ideal);
        place.octaves.push(*octave);
        place.points.push((z.is_finite() && z > 0.0).then(|| camera.unproject(&ideal, z)));
        place.descriptors.push(*descriptor);
    }
    (place, isometry(&k.world_from_camera))
}

/// tx, ty, tz, qx, qy, qz, qw as an isometry.
pub fn isometry(p: &[f64; 7]) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), UnitQuaternion::from_quaternion(Quaternion::new(p[6], p[3], p[4], p[5])))
}

/// The anchor whose world fleet `f`'s frame is (empty: no frame yet).
fn lineage(f: &Fleet) -> String {
    f.members.iter().filter_map(|m| m.frame.as_ref().map(|fr| fr.lineage_of(&m.session_id))).find(|l| !l.is_empty()).unwrap_or_default()
}

fn now_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(anchor: bool, fleet_from_session: &Isometry3<f64>) -> FleetFrame {
        FleetFrame {
            fleet: "lab".into(),
            fleet_from_session: pose7(fleet_from_session),
            anchor,
            support: 3,
            inliers: 100,
            merged_unix_ns: 1,
            first_merged_unix_ns: 1,
            merged_after_ns: 0,
            lineage: "a".into(),
        }
    }

    /// A known answer: robot B's merge is 5 cm and 2° off, and five verified
    /// matches say B's keyframes are where A's are. The solve moves B's keyframes
    /// (and the poses between them) onto the truth; A, anchored, stays.
    #[test]
    fn the_graph_moves_a_misplaced_session_onto_its_matches() {
        let config = FleetConfig { graph_interval_s: 60.0, ..FleetConfig::default() };
        let service = FleetService::start(&config, &MappingConfig::default(), None, Arc::default()).expect("started");
        let wrong =
            Isometry3::from_parts(Translation3::new(0.05, 0.0, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, 2f64.to_radians()));
        let truth = |i: u64| {
            Isometry3::from_parts(
                Translation3::new(0.1 * i as f64, 0.02 * i as f64, 1.0),
                UnitQuaternion::from_euler_angles(0.0, 0.05 * i as f64, 0.0),
            )
        };
        {
            let mut fleets = lock(&service.shared.fleets);
            let f = fleets.entry("lab".into()).or_default();
            f.members.push(service.shared.new_member("a", "alpha", Some(frame(true, &Isometry3::identity()))));
            f.members.push(service.shared.new_member("b", "beta", Some(frame(false, &wrong))));
            for m in 0..2u32 {
                for i in 0..5u64 {
                    let indexed = Indexed { session_from_camera: truth(i), place: Arc::default(), timestamp_ns: 1_000 + i };
                    f.places.insert((m, i), indexed);
                    f.members[m as usize].indexed.push_back(i);
                }
            }
            for i in 0..5u64 {
                f.edges.push(PlaceEdge { a: (1, i), b: (0, i), a_from_b: Isometry3::identity(), kind: EdgeKind::InterSession });
            }
            f.dirty = true;
        }
        assert!(service.get("lab").expect("fleet").pose_graph_pending, "new edges: a solve is due");
        service.solve_now();
        let view = service.get("lab").expect("fleet");
        assert!(!view.pose_graph_pending, "solved");
        let solve = view.last_correction.expect("solved");
        assert_eq!((solve.keyframes, solve.odometry_edges, solve.loop_edges, solve.inter_session_edges), (10, 8, 0, 5));
        assert_eq!(solve.moved_keyframes, 5, "B's five keyframes");
        let a = service.fleet_transform("lab", "a").expect("anchor");
        let b = service.fleet_transform("lab", "b").expect("merged");
        assert_eq!(b.fleet_from_session, wrong, "the merge itself stays as it was found");
        for i in 0..5u64 {
            let t = 1_000 + i;
            let b_in_fleet = b.at(t) * truth(i);
            let error = truth(i).inverse() * b_in_fleet;
            assert!(error.translation.vector.norm() < 1e-3 && error.rotation.angle() < 1e-3, "keyframe {i}: {error}");
            let a_error = truth(i).inverse() * (a.at(t) * truth(i));
            assert!(a_error.translation.vector.norm() < 1e-3, "A moved: {a_error}");
        }
        // Before its first keyframe a pose takes the first correction; between
        // keyframes, the one before it.
        assert_eq!(b.at(0), b.at(1_000));
        assert_eq!(b.at(1_002), b.corrections[2].1 * wrong);
        assert_eq!(b.at(1_003), b.corrections[3].1 * wrong);
        assert_eq!(b.corrections.len(), 5);
        // What the store keeps gives the same graph back.
        let stored = {
            let fleets = lock(&service.shared.fleets);
            stored_graph(&fleets["lab"])
        };
        assert_eq!(stored.edges.len(), 5);
        assert_eq!(stored.edges[0].a, ("b".to_string(), 0));
        let mut fresh = Fleet::default();
        fresh.members.push(service.shared.new_member("a", "alpha", Some(frame(true, &Isometry3::identity()))));
        fresh.members.push(service.shared.new_member("b", "beta", Some(frame(false, &wrong))));
        restore_graph(&mut fresh, stored.clone(), 100, 100);
        assert_eq!(fresh.edges.len(), 5);
        assert_eq!(stored_graph(&fresh).corrections, stored.corrections);
        assert_eq!(fresh.last_correction, stored.last_solve);
        // Stored numbers no solve could write stay out (an edge without a pose, a
        // correction whose rotation is not a unit one), as they do from a carried
        // share; the rest comes back in time order, one per time, at most `max`.
        let mut damaged = stored.clone();
        damaged.edges[0].a_from_b[0] = f64::NAN;
        let list = damaged.corrections.get_mut("b").expect("b's corrections");
        list.reverse();
        list.push(list[0]);
        list.push((1_005, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0]));
        let mut again = Fleet::default();
        again.members.push(service.shared.new_member("a", "alpha", Some(frame(true, &Isometry3::identity()))));
        again.members.push(service.shared.new_member("b", "beta", Some(frame(false, &wrong))));
        restore_graph(&mut again, damaged, 3, 3);
        assert_eq!(again.edges.len(), 3, "four edges with a pose, the newest three kept");
        let ends = |edges: &[PlaceEdge]| edges.iter().map(|e| (e.a, e.b)).collect::<Vec<_>>();
        assert_eq!(ends(&again.edges), ends(&fresh.edges[2..]), "the oldest (and the one without a pose) left out");
        assert!(again.edges.iter().all(|e| e.a_from_b.translation.vector.iter().all(|v| v.is_finite())));
        let times: Vec<u64> = again.members[1].corrections.iter().map(|(t, _)| *t).collect();
        assert_eq!(times, vec![1_002, 1_003, 1_004]);
        assert_eq!(again.members[1].corrections[2], b.corrections[4]);
        // Nothing new: no solve, none pending.
        service.solve_now();
        let view = service.get("lab").expect("fleet");
        assert_eq!(view.last_correction.map(|c| c.solved_unix_ns), Some(solve.solved_unix_ns));
        assert!(!view.pose_graph_pending);
        service.close();
    }

    /// A session resumed from another server keeps its merge when its fleet has no
    /// frame here or the same one (lineage); a new session then merges into that
    /// frame instead of anchoring another; a merge in another frame is dropped (the
    /// session merges again), as is a frame of another fleet.
    #[test]
    fn a_resumed_session_keeps_its_merge_only_in_the_same_frame() {
        let service = FleetService::start(&FleetConfig::default(), &MappingConfig::default(), None, Arc::default()).expect("started");
        let moved = Isometry3::from_parts(Translation3::new(1.0, 2.0, 0.0), UnitQuaternion::identity());
        let carried = |anchor: bool, lineage: &str| FleetFrame { lineage: lineage.into(), ..frame(anchor, &moved) };
        let frame_of = |fleet: &str, session: &str| {
            service.get(fleet).and_then(|v| v.members.into_iter().find(|m| m.session_id == session)).and_then(|m| m.frame)
        };
        // A merged session of A's fleet "lab" (anchored by "a0" on A) comes first here.
        assert!(service.join_carried("lab", "b1", "robot-b", Some(carried(false, "a0"))));
        assert_eq!(frame_of("lab", "b1").map(|f| (f.fleet_from_session, f.anchor)), Some((pose7(&moved), false)));
        // Its anchor follows, in the same frame; an anchor written before lineages
        // were recorded counts as its own.
        assert!(service.join_carried("lab", "a0", "robot-a", Some(carried(true, ""))));
        assert_eq!(frame_of("lab", "a0").map(|f| f.lineage), Some("a0".to_string()));
        // A new session here does not anchor another frame: it waits to be merged.
        service.join("lab", "c1", "robot-c");
        assert_eq!(frame_of("lab", "c1"), None);
        // A merge in another frame of the fleet is dropped, and so is another fleet's.
        assert!(!service.join_carried("lab", "d1", "robot-d", Some(carried(false, "elsewhere"))));
        assert_eq!(frame_of("lab", "d1"), None);
        assert!(!service.join_carried("lab", "e1", "robot-e", Some(FleetFrame { fleet: "other".into(), ..carried(false, "a0") })));
        assert_eq!(frame_of("lab", "e1"), None);
        // A frame from the shared storage that no merge could have written (not a
        // pose) is dropped too: the session merges again here.
        let mut not_a_pose = carried(false, "a0");
        not_a_pose.fleet_from_session[0] = f64::NAN;
        assert!(!service.join_carried("lab", "n1", "robot-n", Some(not_a_pose)));
        assert_eq!(frame_of("lab", "n1"), None);
        // Without a carried frame, a fleet's first session anchors it, as a new one does.
        assert!(!service.join_carried("yard", "y1", "robot-y", None));
        assert_eq!(frame_of("yard", "y1").map(|f| (f.anchor, f.lineage)), Some((true, "y1".to_string())));
        service.close();
    }

    /// Session `session`'s stored keyframes `ids` in fleet "lab": each 10 cm along
    /// x from the last, with 20 features of its own.
    fn stored_keyframes(camera: &Camera, session: &str, ids: std::ops::Range<u64>) -> StoredKeyframes {
        StoredKeyframes {
            fleet: "lab".into(),
            session_id: session.into(),
            camera: camera.clone(),
            keyframes: ids
                .map(|id| KeyframeRecord {
                    id,
                    timestamp_ns: 1_000 + id,
                    world_from_camera: [0.1 * id as f64, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                    features: (0..20u64)
                        .map(|i| ([10.0 + i as f32 * 7.0, 20.0 + id as f32], 0, 1.5, [id.wrapping_mul(0x9e37_79b9) ^ i, i, id, !i]))
                        .collect(),
                })
                .collect(),
        }
    }

    /// A resumed session's stored keyframes are indexed in its fleet here, in order:
    /// a merged one's all (up to `fleet.max_places`), an unmerged one's latest
    /// `fleet.pending_keyframes`; keyframes already indexed are not added again, and
    /// a session not in the fleet (or a fleet not held) gets nothing. Older ones
    /// are the first forgotten beyond `fleet.max_places`, before current ones.
    #[test]
    fn a_resumed_sessions_stored_keyframes_are_indexed_here() {
        let config = FleetConfig { pending_keyframes: 2, max_places: 9, ..FleetConfig::default() };
        let service = FleetService::start(&config, &MappingConfig::default(), None, Arc::default()).expect("started");
        let camera = Camera::pinhole(640, 480, 525.0, 525.0, 319.5, 239.5, 5000.0);
        let stored = |session: &str, ids| stored_keyframes(&camera, session, ids);
        let moved = Isometry3::from_parts(Translation3::new(1.0, 2.0, 0.0), UnitQuaternion::identity());
        assert!(service.join_carried("lab", "b1", "robot-b", Some(FleetFrame { lineage: "a0".into(), ..frame(false, &moved) })));
        assert!(!service.join_carried("lab", "d1", "robot-d", Some(FleetFrame { lineage: "elsewhere".into(), ..frame(false, &moved) })));
        service.index_stored(stored("b1", 3..5), false);
        service.index_stored(stored("d1", 0..5), false);
        // Older ones read back later (a page at a time, newest first), and some again.
        service.index_stored(stored("b1", 0..3), true);
        service.index_stored(stored("b1", 3..7), false);
        service.index_stored(stored("d1", 0..3), true);
        service.index_stored(stored("nobody", 0..5), false);
        service.index_stored(StoredKeyframes { fleet: "yard".into(), ..stored("b1", 0..5) }, false);
        let drained = || {
            let deadline = Instant::now() + Duration::from_secs(10);
            while service.backlog() > 0 && Instant::now() < deadline {
                std::thread::sleep(Duration::from_millis(5));
            }
            service.get("lab").expect("the fleet")
        };
        let view = drained();
        let indexed_in = |view: &FleetView, id: &str| {
            let m = view.members.iter().find(|m| m.session_id == id).expect("a member");
            (m.indexed_keyframes, m.oldest_indexed_keyframe)
        };
        let indexed = |id: &str| indexed_in(&view, id);
        assert_eq!(indexed("b1"), (7, Some(0)), "merged: every stored keyframe, 3 and 4 once");
        assert_eq!(indexed("d1"), (2, Some(3)), "unmerged: the latest fleet.pending_keyframes");
        assert_eq!(view.indexed_keyframes, 9);
        assert_eq!(view.members.len(), 2, "no member made for an unknown session");
        assert!(service.get("yard").is_none(), "nor a fleet");
        // Full (fleet.max_places 9): a new merged session's two keyframes push out
        // b1's two oldest, read back last, not its current ones.
        assert!(service.join_carried("lab", "c1", "robot-c", Some(FleetFrame { lineage: "a0".into(), ..frame(false, &moved) })));
        service.index_stored(stored("c1", 0..2), false);
        let view = drained();
        assert_eq!(view.indexed_keyframes, 9);
        assert_eq!(indexed_in(&view, "c1"), (2, Some(0)));
        assert_eq!(indexed_in(&view, "b1"), (5, Some(2)), "b1's 0 and 1 forgotten first");
        assert_eq!(indexed_in(&view, "d1"), (2, Some(3)));
        service.close();
    }

    /// Stored keyframes finding the place-recognition queue full are left out and
    /// counted, every one of them
    /// (`stillmap_fleet_keyframes_left_out_total{queue="places"}`).
    #[test]
    fn stored_keyframes_left_out_of_a_full_queue_are_counted() {
        let config = FleetConfig { queue: 1, graph_interval_s: 0.0, ..FleetConfig::default() };
        let metrics = Arc::new(crate::metrics::Metrics::default());
        let service = FleetService::start(&config, &MappingConfig::default(), None, metrics.clone()).expect("started");
        let camera = Camera::pinhole(640, 480, 525.0, 525.0, 319.5, 239.5, 5000.0);
        service.join("lab", "a1", "robot-a");
        let left_out = || metrics.counter(r#"stillmap_fleet_keyframes_left_out_total{queue="places"}"#) as usize;
        {
            // Holding the fleets stops the thread at its first job: it holds one
            // job at most, the queue one more; the backlog counts their keyframes.
            let _held = lock(&service.shared.fleets);
            for first in [0, 2, 4, 6] {
                service.index_stored(stored_keyframes(&camera, "a1", first..first + 2), false);
            }
            let backlog = service.backlog();
            assert!(backlog == 2 || backlog == 4, "backlog {backlog}");
            assert_eq!(left_out(), 8 - backlog);
        }
        service.close();
    }

    /// A session resumed from another server brings its share of the fleet's pose
    /// graph: its corrections apply at once, its place edges join the graph once
    /// both their keyframes are indexed here (then a solve is due), an edge to a
    /// session not here waits, and a session whose frame was not kept gets nothing.
    #[test]
    fn a_resumed_sessions_share_of_the_pose_graph_is_carried() {
        // Solved only when the test says (no pose-graph thread).
        let config = FleetConfig { graph_interval_s: 0.0, ..FleetConfig::default() };
        let service = FleetService::start(&config, &MappingConfig::default(), None, Arc::default()).expect("started");
        let camera = Camera::pinhole(640, 480, 525.0, 525.0, 319.5, 239.5, 5000.0);
        let stored = |session: &str, ids| stored_keyframes(&camera, session, ids);
        let moved = Isometry3::from_parts(Translation3::new(1.0, 2.0, 0.0), UnitQuaternion::identity());
        let carried = |_: &str| Some(FleetFrame { lineage: "a0".into(), ..frame(false, &moved) });
        assert!(service.join_carried("lab", "b1", "robot-b", carried("b1")));
        assert!(service.join_carried("lab", "c1", "robot-c", carried("c1")));
        assert!(!service.join_carried("lab", "d1", "robot-d", Some(FleetFrame { lineage: "elsewhere".into(), ..frame(false, &moved) })));
        let correction = Isometry3::from_parts(Translation3::new(0.05, 0.0, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, 0.01));
        let edge = |a: (&str, u64), b: (&str, u64)| GraphEdge {
            a: (a.0.into(), a.1),
            b: (b.0.into(), b.1),
            a_from_b: pose7(&Isometry3::identity()),
            is_loop: a.0 == b.0,
        };
        let share = |corrections: Vec<(u64, [f64; 7])>| SessionGraph {
            corrections,
            edges: vec![edge(("b1", 4), ("c1", 2)), edge(("b1", 1), ("gone", 0)), edge(("b1", 0), ("b1", 4))],
            solved_unix_ns: 1,
        };
        // Out of time order, and one no solve could have written (NaN): sorted, left out.
        let not_a_pose = [f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        let later = Isometry3::from_parts(Translation3::new(0.07, 0.0, 0.0), UnitQuaternion::identity());
        service.carry_graph("lab", "b1", share(vec![(1_004, pose7(&later)), (1_002, not_a_pose), (1_003, pose7(&correction))]));
        // c1 brings the same edges (b1–c1 seen from its side): kept once.
        service.carry_graph("lab", "c1", SessionGraph { corrections: vec![], edges: vec![edge(("c1", 2), ("b1", 4))], solved_unix_ns: 1 });
        service.carry_graph("lab", "d1", share(vec![(1_000, pose7(&correction))]));
        service.carry_graph("yard", "b1", share(vec![]));
        let b1 = service.fleet_transform("lab", "b1").expect("merged");
        assert_eq!(b1.corrections.as_slice(), &[(1_003, correction), (1_004, later)], "as the other server served it");
        assert_eq!(b1.at(1_003), correction * moved);
        assert!(service.fleet_transform("lab", "d1").is_none(), "d1 is merged again here, its share left out");
        // Nothing to solve while the edges' keyframes are not indexed here.
        service.solve_now();
        let view = service.get("lab").expect("fleet");
        assert!(view.last_correction.is_none());
        assert_eq!(view.carried_edges_waiting, 3);
        service.index_stored(stored("b1", 0..5), false);
        service.index_stored(stored("c1", 0..3), false);
        let deadline = Instant::now() + Duration::from_secs(10);
        while service.backlog() > 0 {
            assert!(Instant::now() < deadline, "the stored keyframes never indexed");
            std::thread::sleep(Duration::from_millis(5));
        }
        let view = service.get("lab").expect("fleet");
        assert!(view.pose_graph_pending, "a solve is due once the carried edges' keyframes are indexed");
        assert_eq!(view.carried_edges_waiting, 1, "the edge to a session not here waits");
        service.solve_now();
        let solve = service.get("lab").expect("fleet").last_correction.expect("solved");
        assert_eq!(
            (solve.inter_session_edges, solve.loop_edges),
            (1, 1),
            "{solve:?}: the b1–c1 edge once, b1's loop; not the edge to a session not here"
        );
        service.close();
    }

    /// After a restart, a fleet whose frame came with a resumed session's merge
    /// (its anchor on another server) is not anchored anew by a session without a
    /// frame that started before it.
    #[test]
    fn a_restart_keeps_a_carried_frame_unanchored_here() {
        let path = std::env::temp_dir().join(format!("stillmap-fleet-restore-{}.redb", std::process::id()));
        let _ = std::fs::remove_file(&path);
        let store = Arc::new(Store::open(&path).expect("store"));
        let moved = Isometry3::from_parts(Translation3::new(1.0, 2.0, 0.0), UnitQuaternion::identity());
        store.put_fleet_frame("b1", &FleetFrame { lineage: "a0".into(), ..frame(false, &moved) }).expect("frame");
        let head = |id: &str, started_unix_ns: u64| SessionHead {
            id: id.into(),
            meta: crate::store::SessionMeta {
                transport: "zenoh".into(),
                started_unix_ns,
                fleet: "lab".into(),
                ..crate::store::SessionMeta::for_tests(&format!("robot-{id}"))
            },
            camera: stillmap_proto::pb::CameraInfo::default(),
            pose_count: 0,
            latest: None,
            keyframes: vec![],
        };
        let service =
            FleetService::start(&FleetConfig::default(), &MappingConfig::default(), Some(store), Arc::default()).expect("started");
        service.restore(&[head("c0", 1), head("b1", 2)]);
        let view = service.get("lab").expect("the fleet");
        let frame_of = |id: &str| view.members.iter().find(|m| m.session_id == id).and_then(|m| m.frame.clone());
        assert_eq!(frame_of("b1").map(|f| (f.anchor, f.lineage)), Some((false, "a0".to_string())));
        assert_eq!(frame_of("c0"), None, "not an anchor of another frame");
        service.close();
        let _ = std::fs::remove_file(&path);
    }

    /// A restart reads only the keyframe records the place index keeps, the newest
    /// sessions first, and the index is the one every record would have given.
    #[test]
    fn a_restart_reads_only_the_keyframes_the_index_keeps() {
        let config = FleetConfig { max_places: 7, pending_keyframes: 3, ..FleetConfig::default() };
        let head = |id: &str, started_unix_ns: u64, keyframes: u64| SessionHead {
            id: id.into(),
            meta: crate::store::SessionMeta { started_unix_ns, fleet: "lab".into(), ..crate::store::SessionMeta::for_tests(id) },
            camera: stillmap_proto::pb::CameraInfo::default(),
            pose_count: 0,
            latest: None,
            keyframes: (0..keyframes)
                .map(|id| KeyframeRecord { id, timestamp_ns: id, world_from_camera: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], features: vec![] })
                .collect(),
        };
        // The first anchors the fleet (merged: no cap of its own); the others wait
        // unmerged, each with its latest three.
        let heads = [head("s0", 1, 6), head("s1", 2, 5), head("s2", 3, 5)];
        let index = |service: &FleetService| {
            let fleets = lock(&service.shared.fleets);
            let f = &fleets["lab"];
            let mut places: Vec<(String, u64)> = f.places.keys().map(|(m, id)| (f.members[*m as usize].session_id.clone(), *id)).collect();
            places.sort();
            let indexed: Vec<(String, Vec<u64>)> =
                f.members.iter().map(|m| (m.session_id.clone(), m.indexed.iter().copied().collect())).collect();
            (places, indexed)
        };
        // As before: every record of each session added, one session after another.
        let every = FleetService::start(&config, &MappingConfig::default(), None, Arc::default()).expect("started");
        for h in &heads {
            every.restore_with(std::slice::from_ref(h), |s, _| s.keyframes.clone());
        }
        let newest = FleetService::start(&config, &MappingConfig::default(), None, Arc::default()).expect("started");
        let asked = Mutex::new(Vec::new());
        newest.restore_with(&heads, |s, n| {
            lock(&asked).push((s.id.clone(), n));
            s.keyframes[s.keyframes.len().saturating_sub(n)..].to_vec()
        });
        let (places, indexed) = index(&every);
        let s = |id: &str, ids: &[u64]| (id.to_string(), ids.to_vec());
        assert_eq!(indexed, [s("s0", &[5]), s("s1", &[2, 3, 4]), s("s2", &[2, 3, 4])]);
        assert_eq!(places.len(), 7);
        assert_eq!(index(&newest), (places, indexed));
        assert_eq!(
            *lock(&asked),
            [("s2".to_string(), 3), ("s1".to_string(), 3), ("s0".to_string(), 1)],
            "the newest first, no more than kept"
        );
        every.close();
        newest.close();
    }

    /// What is read back at a restart, or with an import into a running server,
    /// never replaces a live fleet's state nor comes back when no merge or solve
    /// could have written it.
    #[test]
    fn stored_fleet_state_comes_back_checked_and_leaves_live_fleets_alone() {
        let path = std::env::temp_dir().join(format!("stillmap-fleet-checked-{}.redb", std::process::id()));
        let _ = std::fs::remove_file(&path);
        let store = Arc::new(Store::open(&path).expect("store"));
        let solve = |solved_unix_ns: u64| crate::store::GraphSolve {
            solved_unix_ns,
            keyframes: 0,
            odometry_edges: 0,
            loop_edges: 0,
            inter_session_edges: 0,
            moved_keyframes: 0,
            max_translation_m: 0.0,
            max_rotation_deg: 0.0,
            solve_ms: 0.0,
        };
        store.put_fleet_graph("lab", &FleetGraph { last_solve: Some(solve(1)), ..Default::default() }).expect("graph");
        let mut not_a_pose = frame(false, &Isometry3::identity());
        not_a_pose.fleet_from_session[6] = 0.0;
        store.put_fleet_frame("n1", &not_a_pose).expect("frame");
        let head = |id: &str, fleet: &str| SessionHead {
            id: id.into(),
            meta: crate::store::SessionMeta { fleet: fleet.into(), ..crate::store::SessionMeta::for_tests(&format!("robot-{id}")) },
            camera: stillmap_proto::pb::CameraInfo::default(),
            pose_count: 0,
            latest: None,
            keyframes: vec![],
        };
        let service =
            FleetService::start(&FleetConfig::default(), &MappingConfig::default(), Some(store.clone()), Arc::default()).expect("started");
        // At start: the fleet's graph comes back; a stored merge that is not a pose does not.
        service.restore(&[head("a0", "lab"), head("n1", "lab"), head("q9", "lab/../x")]);
        let view = service.get("lab").expect("the fleet");
        assert_eq!(view.last_correction.map(|c| c.solved_unix_ns), Some(1));
        let member = |id: &str| view.members.iter().find(|m| m.session_id == id).cloned();
        assert!(member("n1").is_some_and(|m| m.frame.is_none()), "merges again");
        // A stored session naming a fleet no robot could name goes to the default fleet.
        assert!(service.get("lab/../x").is_none());
        assert!(service.get("default").is_some_and(|v| v.members.iter().any(|m| m.session_id == "q9")));
        // An import while the server runs: the live fleet keeps its own graph, even
        // where the store holds another (its next solve writes the live one).
        store.put_fleet_graph("lab", &FleetGraph { last_solve: Some(solve(2)), ..Default::default() }).expect("graph");
        service.restore(&[head("i2", "lab")]);
        let view = service.get("lab").expect("the fleet");
        assert_eq!(view.last_correction.map(|c| c.solved_unix_ns), Some(1), "not the stored graph's");
        assert!(view.members.iter().any(|m| m.session_id == "i2"));
        service.close();
        let _ = std::fs::remove_file(&path);
    }
}
