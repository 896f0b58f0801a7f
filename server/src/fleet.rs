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
//! keyframe finding the queue full is left out of place recognition (logged).
//! Memory is bounded by `fleet.max_places` keyframes per fleet (about 60 KB each:
//! the features with depth, point and descriptor, and the index postings; 300 MB
//! per fleet at the default 5,000) and `fleet.pending_keyframes` per unmerged session.

use std::collections::{HashMap, VecDeque};
use std::sync::mpsc::{SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use nalgebra::{Isometry3, Point2, Quaternion, Translation3, UnitQuaternion};
use stillmap_places::{BowVector, MergeConfig, MergeDetector, Place, PlaceIndex, VerifyConfig, Vocabulary, propose, verify};
use stillmap_tracking::Camera;

use crate::config::FleetConfig;
use crate::lock;
use crate::store::{FleetFrame, KeyframeRecord, SessionHead, Store};

/// A committed keyframe of some session, for place recognition.
pub struct FleetJob {
    pub fleet: String,
    pub session_id: String,
    pub robot_id: String,
    pub camera: Camera,
    pub keyframe: KeyframeRecord,
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
}

/// One fleet: its members and the index of its merged keyframes.
#[derive(Default)]
struct Fleet {
    members: Vec<Member>,
    index: PlaceIndex<(u32, u64)>,
    /// Per indexed keyframe: `session_from_camera` and its place (the fleet frame
    /// is its member's `fleet_from_session` away, which a refined merge may move).
    places: HashMap<(u32, u64), (Isometry3<f64>, Arc<Place>)>,
    /// Indexed keyframes, oldest first (the first forgotten beyond `max_places`).
    order: VecDeque<(u32, u64)>,
}

/// A session's place in its fleet, for the APIs.
#[derive(Debug, Clone)]
pub struct MemberView {
    pub session_id: String,
    pub robot_id: String,
    pub frame: Option<FleetFrame>,
}

/// A fleet, for the APIs.
#[derive(Debug, Clone)]
pub struct FleetView {
    pub name: String,
    pub members: Vec<MemberView>,
    pub indexed_keyframes: usize,
}

struct Shared {
    config: FleetConfig,
    vocabulary: Vocabulary,
    verify: VerifyConfig,
    /// An empty detector with the server's merge settings (each member starts from a copy).
    detector: MergeDetector,
    store: Option<Arc<Store>>,
    fleets: Mutex<HashMap<String, Fleet>>,
}

/// The fleets and the place-recognition thread.
pub struct FleetService {
    shared: Arc<Shared>,
    /// Keyframes handed to place recognition and not yet done with.
    backlog: Arc<std::sync::atomic::AtomicUsize>,
    jobs: Mutex<Option<SyncSender<FleetJob>>>,
    worker: Mutex<Option<std::thread::JoinHandle<()>>>,
}

#[derive(Debug, thiserror::Error)]
pub enum FleetError {
    #[error("fleet.vocabulary_path {path}: {message}")]
    Vocabulary { path: String, message: String },
    #[error("cannot start the place-recognition thread: {0}")]
    Thread(std::io::Error),
    #[error("fleet: {0}")]
    Config(String),
}

impl FleetService {
    /// Loads the vocabulary and starts the place-recognition thread.
    pub fn start(config: &FleetConfig, store: Option<Arc<Store>>) -> Result<Arc<Self>, FleetError> {
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
        let shared = Arc::new(Shared { config: config.clone(), vocabulary, verify, detector, store, fleets: Mutex::default() });
        let (tx, rx) = std::sync::mpsc::sync_channel::<FleetJob>(config.queue);
        let worker_shared = shared.clone();
        let backlog = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let worker_backlog = backlog.clone();
        let worker = std::thread::Builder::new()
            .name("places".into())
            .spawn(move || {
                for job in rx {
                    worker_shared.process(job);
                    worker_backlog.fetch_sub(1, std::sync::atomic::Ordering::SeqCst);
                }
            })
            .map_err(FleetError::Thread)?;
        Ok(Arc::new(Self { shared, backlog, jobs: Mutex::new(Some(tx)), worker: Mutex::new(Some(worker)) }))
    }

    /// The fleet of a hello that named `requested` (empty: the default fleet).
    pub fn fleet_for(&self, requested: &str) -> String {
        if requested.is_empty() { self.shared.config.default_fleet.clone() } else { requested.to_string() }
    }

    /// Hands a committed keyframe to place recognition; a full queue leaves it out.
    pub fn submit(&self, job: FleetJob) {
        let Some(tx) = lock(&self.jobs).clone() else { return };
        self.backlog.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        match tx.try_send(job) {
            Ok(()) => {}
            Err(TrySendError::Full(job)) => {
                self.backlog.fetch_sub(1, std::sync::atomic::Ordering::SeqCst);
                tracing::warn!(session = %job.session_id, keyframe = job.keyframe.id, "place-recognition queue full (fleet.queue): keyframe left out");
            }
            Err(TrySendError::Disconnected(_)) => {
                self.backlog.fetch_sub(1, std::sync::atomic::Ordering::SeqCst);
            }
        }
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

    /// Rebuilds the fleets from the store: sessions in the order they started,
    /// their merges, and the keyframes of merged sessions in the index.
    pub fn restore(&self, stored: &[SessionHead]) {
        let frames = match &self.shared.store {
            Some(store) => store.fleet_frames().unwrap_or_else(|e| {
                tracing::error!("fleet merges cannot be read from the store: {e}");
                HashMap::new()
            }),
            None => HashMap::new(),
        };
        let mut order: Vec<&SessionHead> = stored.iter().collect();
        order.sort_by_key(|s| (s.meta.started_unix_ns, s.id.clone()));
        let mut fleets = lock(&self.shared.fleets);
        for s in order {
            let name = self.fleet_for(&s.meta.fleet);
            let camera = crate::convert::camera_of(&s.camera);
            let f = fleets.entry(name.clone()).or_default();
            let m = match frames.get(&s.id).filter(|frame| frame.fleet == name) {
                Some(frame) => {
                    f.members.push(self.shared.new_member(&s.id, &s.meta.robot_id, Some(frame.clone())));
                    f.members.len() - 1
                }
                None => self.shared.member(f, &name, &s.id, &s.meta.robot_id),
            };
            for k in &s.keyframes {
                self.shared.add_keyframe(f, m, &camera, k);
            }
        }
    }

    /// Every fleet, by name.
    pub fn list(&self) -> Vec<FleetView> {
        let fleets = lock(&self.shared.fleets);
        let mut all: Vec<FleetView> = fleets.iter().map(|(name, f)| view(name, f)).collect();
        all.sort_by(|a, b| a.name.cmp(&b.name));
        all
    }

    pub fn get(&self, name: &str) -> Option<FleetView> {
        lock(&self.shared.fleets).get(name).map(|f| view(name, f))
    }

    /// `fleet_from_session` of a merged session.
    pub fn fleet_from_session(&self, fleet: &str, session_id: &str) -> Option<Isometry3<f64>> {
        let fleets = lock(&self.shared.fleets);
        let member = fleets.get(fleet)?.members.iter().find(|m| m.session_id == session_id)?;
        member.frame.as_ref().map(|f| isometry(&f.fleet_from_session))
    }

    /// Waits until every submitted keyframe has been processed, and stops the thread.
    pub fn close(&self) {
        lock(&self.jobs).take();
        if let Some(worker) = lock(&self.worker).take() {
            let _ = worker.join();
        }
    }
}

fn view(name: &str, f: &Fleet) -> FleetView {
    FleetView {
        name: name.to_string(),
        members: f
            .members
            .iter()
            .map(|m| MemberView { session_id: m.session_id.clone(), robot_id: m.robot_id.clone(), frame: m.frame.clone() })
            .collect(),
        indexed_keyframes: f.index.len(),
    }
}

impl Shared {
    fn new_member(&self, session_id: &str, robot_id: &str, frame: Option<FleetFrame>) -> Member {
        Member {
            session_id: session_id.to_string(),
            robot_id: robot_id.to_string(),
            frame,
            detector: self.detector.clone(),
            indexed: VecDeque::new(),
            heard: 0,
            keyframe_span_ns: None,
        }
    }

    /// The member for `session_id`, added when new: the fleet's first session
    /// anchors its frame (committed to the store).
    fn member(&self, f: &mut Fleet, fleet: &str, session_id: &str, robot_id: &str) -> usize {
        if let Some(m) = f.members.iter().position(|m| m.session_id == session_id) {
            return m;
        }
        let anchor = !f.members.iter().any(|m| m.frame.as_ref().is_some_and(|fr| fr.anchor));
        let frame = anchor.then(|| FleetFrame {
            fleet: fleet.to_string(),
            fleet_from_session: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            anchor: true,
            support: 0,
            inliers: 0,
            merged_unix_ns: now_ns(),
            first_merged_unix_ns: now_ns(),
            merged_after_ns: 0,
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
        // (the candidate's member, fleet_from_query or None, fleet_from_candidate or None, session_from_candidate, place)
        type Candidate = (usize, Option<Isometry3<f64>>, Option<Isometry3<f64>>, Isometry3<f64>, Arc<Place>);
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
            let candidates: Vec<Candidate> = found
                .iter()
                .filter_map(|(k, _)| {
                    let r = k.0 as usize;
                    let (session_from_candidate, candidate) = f.places.get(k)?;
                    let fleet_from_candidate =
                        f.members[r].frame.as_ref().map(|fr| isometry(&fr.fleet_from_session) * session_from_candidate);
                    let fleet_from_query = m_frame.filter(|_| self.refining(f, r)).map(|t| t * session_from_query);
                    let fleet_from_candidate = fleet_from_candidate.filter(|_| m_refining);
                    Some((r, fleet_from_query, fleet_from_candidate, *session_from_candidate, candidate.clone()))
                })
                .collect();
            let t = job.keyframe.timestamp_ns;
            let span = &mut f.members[m].keyframe_span_ns;
            *span = Some(span.map_or((t, t), |(first, last)| (first.min(t), last.max(t))));
            self.add_place(f, m, job.keyframe.id, session_from_query, place.clone(), bow);
            (m, candidates)
        };
        // Verification (the expensive part) holds no lock. Per target member, the
        // proposal of the verification with the most inliers.
        let mut best: HashMap<usize, (Isometry3<f64>, usize)> = HashMap::new();
        for (r, fleet_from_query, fleet_from_candidate, session_from_candidate, candidate) in &candidates {
            let Some(v) = verify(&job.camera, &place, candidate, &self.verify) else { continue };
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
                offer(*r, fleet_from_query * v.query_from_candidate * session_from_candidate.inverse());
            }
        }
        let mut fleets = lock(&self.fleets);
        let Some(f) = fleets.get_mut(&job.fleet) else { return };
        for (target, (proposal, inliers)) in best {
            self.observe(f, &job.fleet, target, proposal, inliers, started);
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
        let q = merged.fleet_from_session.rotation.coords;
        let v = merged.fleet_from_session.translation.vector;
        let member = &mut f.members[t];
        let now = now_ns();
        let (first_merged_unix_ns, merged_after_ns) = match &member.frame {
            Some(fr) => (fr.first_merged_unix_ns, fr.merged_after_ns),
            None => (now, member.keyframe_span_ns.map_or(0, |(first, last)| last.saturating_sub(first))),
        };
        let frame = FleetFrame {
            fleet: fleet.to_string(),
            fleet_from_session: [v.x, v.y, v.z, q.x, q.y, q.z, q.w],
            anchor: false,
            support: merged.support,
            inliers: merged.inliers,
            merged_unix_ns: now,
            first_merged_unix_ns,
            merged_after_ns,
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
    }

    /// Adds a stored keyframe of member `m`.
    fn add_keyframe(&self, f: &mut Fleet, m: usize, camera: &Camera, record: &KeyframeRecord) {
        let (place, bow, session_from_camera) = self.place_of(camera, record);
        self.add_place(f, m, record.id, session_from_camera, place, bow);
    }

    /// Indexes a keyframe of member `m`; an unmerged member keeps only its latest
    /// `fleet.pending_keyframes` there.
    fn add_place(&self, f: &mut Fleet, m: usize, id: u64, session_from_camera: Isometry3<f64>, place: Arc<Place>, bow: BowVector) {
        self.index(f, m, id, session_from_camera, place, bow);
        if f.members[m].frame.is_none() {
            while f.members[m].indexed.len() > self.config.pending_keyframes {
                if let Some(old) = f.members[m].indexed.pop_front() {
                    f.index.remove(&(m as u32, old));
                    f.places.remove(&(m as u32, old));
                }
            }
        }
    }

    fn index(&self, f: &mut Fleet, m: usize, id: u64, session_from_camera: Isometry3<f64>, place: Arc<Place>, bow: BowVector) {
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
        if f.places.insert(key, (session_from_camera, place)).is_none() {
            f.order.push_back(key);
            f.members[m].indexed.push_back(id);
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

fn now_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}
