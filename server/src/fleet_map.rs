//! One map per fleet, fused from every merged session's keyframes in the fleet
//! frame, and fused again where the pose graph moves them.
//!
//! The map lane of each session hands its keyframes over after fusing them into
//! the session's own map: the keyframe's fusion input (kept compactly: depth to
//! the millimetre, zstd, about 200 KB at VGA), the current poses of the session's recent keyframes (local
//! bundle adjustment still moves them) and the samples perception took back out
//! (people found moving later). One thread of its own (`fleet-map`) behind a
//! bounded queue (`fleet.map_queue`) keeps each fleet's map: a keyframe is fused
//! once its session is merged, at `fleet_from_session` with the pose graph's
//! correction for its capture time; after a merge is refined, a pose-graph solve
//! or a bundle adjustment, each keyframe whose fleet pose moved more than
//! `mapping.refuse_translation_m` / `refuse_rotation_deg` has its hits taken out
//! where they were fused and is fused again where it is now — at most
//! `fleet.refuse_per_pass` keyframes per pass, so one pass is bounded in time,
//! and neither tracking nor a session's map waits for any of it.
//!
//! Bounded: `fleet.map_keyframes` inputs per fleet; beyond, the oldest input is
//! dropped (what it fused stays, and is no longer moved). Nothing is fused while a
//! fleet has a single merged session (its map would be that session's own): the
//! inputs wait for a second one. A fleet whose merged sessions all have every
//! keyframe fused here is served from this map; otherwise (one session, a full
//! queue, a catch-up after a merge, keyframes made after the last save of a server
//! that was killed) the fleet products fall back to the merge of the sessions' own maps. The thread runs at
//! niceness `fleet.nice`: it yields the cores to tracking.
//!
//! Kept across restarts: with a store, each fleet's map (its blocks changed since
//! the last save, and how many keyframes of each session it fused) is saved at
//! most every `fleet.map_save_interval_s` and when the server stops, after the
//! keyframes still waiting are fused (for at most [`CLOSE_BUDGET`]). At start the
//! saved maps come back, so a fleet whose sessions are all fused there is served
//! from it again. The inputs kept to fuse keyframes again are not saved (200 KB
//! each): a keyframe fused before the restart stays where it was fused, as one
//! whose input was dropped beyond `fleet.map_keyframes`.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use nalgebra::Isometry3;
use stillmap_mapping::map::FusionInput;
use stillmap_mapping::{CameraRays, MappingConfig, VoxelMap};
use stillmap_perception::origins::Retraction;
use stillmap_tracking::Camera;

use crate::fleet::FleetTransform;
use crate::lock;
use crate::store::{FleetMapHead, Store};

/// One map-lane job of a session, for its fleet's map.
pub struct FleetMapJob {
    pub fleet: String,
    pub session_id: String,
    pub camera: Camera,
    /// A new keyframe: id, capture time, `session_from_camera`, its fusion input.
    pub keyframe: Option<(u64, u64, Isometry3<f64>, FusionInput)>,
    /// Current `session_from_camera` of the session's recent keyframes.
    pub keyframe_poses: Vec<(u64, Isometry3<f64>)>,
    /// Samples of recent keyframes perception found moving since.
    pub retractions: Vec<Retraction>,
}

/// A keyframe the fleet map holds.
struct Kept {
    timestamp_ns: u64,
    session_from_camera: Isometry3<f64>,
    /// Where in the fleet frame its hits are (none yet: its session is unmerged).
    fused_at: Option<Isometry3<f64>>,
    /// Its fusion input, compact.
    input: Vec<u8>,
    width: u32,
}

/// One fleet's map and what it was fused from.
pub struct FleetMapState {
    map: VoxelMap,
    rays: HashMap<String, Arc<CameraRays>>,
    kept: HashMap<(String, u64), Kept>,
    /// Keys with an input, oldest first.
    order: VecDeque<(String, u64)>,
    /// Keyframes per session fused here or waiting for the merge.
    held: HashMap<String, u64>,
    /// Keyframes per session fused here.
    fused: HashMap<String, u64>,
    /// Keyframes fused again after their fleet pose moved.
    refused: u64,
    /// The map's change stamp at its last save (or load).
    saved_stamp: u64,
    /// Whether the store holds this map (saved or loaded): a first save replaces
    /// whatever blocks the store held for the fleet.
    in_store: bool,
}

impl FleetMapState {
    pub fn map(&self) -> &VoxelMap {
        &self.map
    }

    /// What the map holds: keyframes fused here or waiting for a merge, of them
    /// fused, of them with their input still kept, and the re-fusions done.
    pub fn counts(&self) -> FleetMapCounts {
        FleetMapCounts {
            keyframes: self.held.values().sum(),
            fused: self.fused.values().sum(),
            kept_inputs: self.order.len() as u64,
            kept_bytes: self.kept.values().map(|k| k.input.len() as u64).sum(),
            refused: self.refused,
        }
    }

    /// Keyframes of `session_id` fused here.
    pub fn fused(&self, session_id: &str) -> u64 {
        self.fused.get(session_id).copied().unwrap_or(0)
    }
}

/// One fleet's map as the APIs reach it: the state (locked while a pass fuses)
/// and its counts after the last job or pass (never waits for a pass).
pub struct FleetMapHandle {
    pub state: Mutex<FleetMapState>,
    counts: Mutex<FleetMapCounts>,
}

impl FleetMapHandle {
    pub fn counts(&self) -> FleetMapCounts {
        *lock(&self.counts)
    }
}

/// See [`FleetMapState::counts`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct FleetMapCounts {
    pub keyframes: u64,
    pub fused: u64,
    pub kept_inputs: u64,
    /// Their compact size in all.
    pub kept_bytes: u64,
    pub refused: u64,
}

/// Settings of the fleet maps.
#[derive(Debug, Clone)]
pub struct FleetMapConfig {
    pub mapping: MappingConfig,
    pub queue: usize,
    pub max_keyframes: usize,
    pub refuse_per_pass: usize,
    /// The thread's niceness (`fleet.nice`).
    pub nice: i32,
    /// How often at most a fleet map that changed is saved (`fleet.map_save_interval_s`).
    pub save_interval: Duration,
}

/// The fleets' maps and their thread.
pub struct FleetMaps {
    states: Arc<Mutex<HashMap<String, Arc<FleetMapHandle>>>>,
    jobs: Mutex<Option<SyncSender<FleetMapJob>>>,
    worker: Mutex<Option<std::thread::JoinHandle<()>>>,
    /// Set when the server stops: the jobs still queued are only recorded, not fused one by one.
    closing: Arc<AtomicBool>,
    metrics: Arc<crate::metrics::Metrics>,
}

/// How the thread finds a session's transform into its fleet's frame.
pub type TransformOf = Arc<dyn Fn(&str, &str) -> Option<FleetTransform> + Send + Sync>;

impl FleetMaps {
    /// Starts the thread, with the maps saved in `store` (if any) back.
    pub fn start(
        config: FleetMapConfig,
        transform_of: TransformOf,
        store: Option<Arc<Store>>,
        metrics: Arc<crate::metrics::Metrics>,
    ) -> std::io::Result<Self> {
        let (tx, rx) = std::sync::mpsc::sync_channel::<FleetMapJob>(config.queue.max(1));
        let states: Arc<Mutex<HashMap<String, Arc<FleetMapHandle>>>> = Arc::new(Mutex::new(load(&config, store.as_deref())));
        let worker_states = states.clone();
        let closing = Arc::new(AtomicBool::new(false));
        let worker_closing = closing.clone();
        let worker_metrics = metrics.clone();
        let worker = std::thread::Builder::new().name("fleet-map".into()).spawn(move || {
            let metrics = worker_metrics;
            crate::lower_this_thread(config.nice, "fleet-map");
            let store = store.as_deref();
            // A panic (a bug) costs the job it was on, not the thread; while the
            // server stops, it ends the thread (the maps are then not saved again:
            // the last periodic save stands).
            while let Err(panic) = crate::pool::caught(|| run(&config, &rx, &worker_states, &transform_of, store, &worker_closing)) {
                metrics.panicked("fleet_map");
                tracing::error!("the fleet map panicked (a bug; the keyframe it was fusing is left out): {panic}");
                if worker_closing.load(Ordering::SeqCst) {
                    return;
                }
                // One that recurs on every pass is logged once a second at most.
                std::thread::sleep(PASS_INTERVAL * 4);
            }
        })?;
        Ok(Self { states, jobs: Mutex::new(Some(tx)), worker: Mutex::new(Some(worker)), closing, metrics })
    }

    /// Hands a map-lane job over; a full queue leaves it out (logged, and counted
    /// in `stillmap_fleet_keyframes_left_out_total{queue="fleet_map"}` when it
    /// carries a keyframe), and the fleet products then fall back to the
    /// sessions' maps. Returns whether the job was queued.
    pub fn submit(&self, job: FleetMapJob) -> bool {
        let Some(tx) = lock(&self.jobs).clone() else { return false };
        match tx.try_send(job) {
            Ok(()) => true,
            Err(TrySendError::Full(job)) => {
                if job.keyframe.is_some() {
                    self.metrics.fleet_keyframes_left_out("fleet_map", 1);
                }
                let what = if job.keyframe.is_some() { "keyframe" } else { "job" };
                tracing::warn!(session = %job.session_id, "fleet map queue full (fleet.map_queue): {what} left out of the fleet map");
                false
            }
            Err(TrySendError::Disconnected(_)) => false,
        }
    }

    /// Fleet `name`'s map, when it has one.
    pub fn state(&self, name: &str) -> Option<Arc<FleetMapHandle>> {
        lock(&self.states).get(name).cloned()
    }

    /// Records the queued jobs, fuses what waits (for at most [`CLOSE_BUDGET`]),
    /// saves the maps and stops the thread.
    pub fn close(&self) {
        self.closing.store(true, Ordering::SeqCst);
        lock(&self.jobs).take();
        if let Some(worker) = lock(&self.worker).take() {
            let _ = worker.join();
        }
    }
}

/// How often a pass runs without a job (merges and pose-graph solves move keyframes).
const PASS_INTERVAL: Duration = Duration::from_millis(250);
/// When the server stops, keyframes still waiting are fused for at most this
/// long before the maps are saved. (The server gives its workers 5 s in all to
/// stop; the queued jobs before it are only recorded, each a compression.)
pub const CLOSE_BUDGET: Duration = Duration::from_secs(2);

/// A fleet's map handle around `state`.
fn handle(state: FleetMapState) -> Arc<FleetMapHandle> {
    let counts = Mutex::new(state.counts());
    Arc::new(FleetMapHandle { state: Mutex::new(state), counts })
}

/// An empty fleet map state around `map`.
fn state_of(map: VoxelMap) -> FleetMapState {
    let saved_stamp = map.change_stamp();
    FleetMapState {
        map,
        rays: HashMap::new(),
        kept: HashMap::new(),
        order: VecDeque::new(),
        held: HashMap::new(),
        fused: HashMap::new(),
        refused: 0,
        saved_stamp,
        in_store: false,
    }
}

/// The fleet maps saved in `store`, as the thread starts with them. A map of
/// another voxel size, or one the store cannot read, is left out (logged): its
/// fleet falls back to merging its sessions' maps, as after a restart without it.
fn load(config: &FleetMapConfig, store: Option<&Store>) -> HashMap<String, Arc<FleetMapHandle>> {
    let Some(store) = store else { return HashMap::new() };
    let saved = match store.fleet_maps() {
        Ok(saved) => saved,
        Err(e) => {
            tracing::error!("fused fleet maps cannot be read from the store: {e}");
            return HashMap::new();
        }
    };
    let mut out = HashMap::new();
    for (fleet, (head, blocks)) in saved {
        if (head.voxel_size_m - config.mapping.voxel_size_m).abs() > 1e-9 {
            tracing::warn!(
                fleet = %fleet,
                "the stored fused fleet map has {} m voxels, mapping.voxel_size_m is {} m: left out",
                head.voxel_size_m,
                config.mapping.voxel_size_m
            );
            continue;
        }
        let map = match VoxelMap::new(config.mapping.clone()) {
            Ok(map) => map,
            Err(e) => {
                tracing::error!("fleet map not made: {e}");
                return HashMap::new();
            }
        };
        let mut map = map.with_blocks(blocks);
        map.set_change_stamp(head.change_stamp);
        let mut state = state_of(map);
        state.in_store = true;
        let fused: HashMap<String, u64> = head.fused.into_iter().collect();
        // Fused here, so held here: no input is kept for them.
        state.held = fused.clone();
        state.fused = fused;
        tracing::info!(fleet = %fleet, keyframes = state.fused.values().sum::<u64>(), "fused fleet map restored from the store");
        out.insert(fleet, handle(state));
    }
    out
}

/// Every fleet's map handle, copied out of the lock.
fn every_fleet(states: &Mutex<HashMap<String, Arc<FleetMapHandle>>>) -> Vec<(String, Arc<FleetMapHandle>)> {
    lock(states).iter().map(|(k, v)| (k.clone(), v.clone())).collect()
}

/// Saves each fleet map that changed since its last save: its changed blocks and
/// head, copied under its lock and written after. A failed write is logged and
/// tried again at the next save (the blocks stay changed since the saved stamp).
fn save(states: &Mutex<HashMap<String, Arc<FleetMapHandle>>>, store: &Store) {
    let all = every_fleet(states);
    for (fleet, handle) in all {
        let (head, blocks, replace) = {
            let s = lock(&handle.state);
            let stamp = s.map.change_stamp();
            if stamp <= s.saved_stamp && s.in_store {
                continue;
            }
            let blocks: Vec<_> = s.map.changed_since(s.saved_stamp).map(|(k, b)| (*k, b.clone())).collect();
            let head = FleetMapHead {
                voxel_size_m: s.map.voxel_size(),
                change_stamp: stamp,
                fused: s.fused.iter().map(|(k, v)| (k.clone(), *v)).collect(),
            };
            (head, blocks, !s.in_store)
        };
        let started = Instant::now();
        match store.put_fleet_map(&fleet, &head, &blocks, replace) {
            Ok(()) => {
                tracing::debug!(fleet = %fleet, blocks = blocks.len(), ms = started.elapsed().as_secs_f64() * 1e3, "fused fleet map saved");
                let mut s = lock(&handle.state);
                s.saved_stamp = s.saved_stamp.max(head.change_stamp);
                s.in_store = true;
            }
            Err(e) => tracing::warn!(fleet = %fleet, "fused fleet map not saved (tried again at the next save): {e}"),
        }
    }
}

fn run(
    config: &FleetMapConfig,
    jobs: &Receiver<FleetMapJob>,
    states: &Mutex<HashMap<String, Arc<FleetMapHandle>>>,
    transform_of: &TransformOf,
    store: Option<&Store>,
    closing: &AtomicBool,
) {
    let mut saved_at = Instant::now();
    loop {
        match jobs.recv_timeout(PASS_INTERVAL) {
            Ok(job) => {
                let state = {
                    let mut all = lock(states);
                    match all.get(&job.fleet) {
                        Some(s) => s.clone(),
                        None => match VoxelMap::new(config.mapping.clone()) {
                            Ok(map) => {
                                let s = handle(state_of(map));
                                all.insert(job.fleet.clone(), s.clone());
                                s
                            }
                            Err(e) => {
                                tracing::error!("fleet map not made: {e}");
                                continue;
                            }
                        },
                    }
                };
                let fleet = job.fleet.clone();
                take_job(&mut lock(&state.state), job, config.max_keyframes);
                // While the server stops, the passes below fuse what waits, bounded.
                if !closing.load(Ordering::SeqCst) {
                    pass(&fleet, &state, config, transform_of);
                }
            }
            Err(RecvTimeoutError::Timeout) => {
                let all = every_fleet(states);
                for (fleet, state) in all {
                    pass(&fleet, &state, config, transform_of);
                }
            }
            Err(RecvTimeoutError::Disconnected) => {
                // The server stops: fuse what waits (bounded), then save.
                let deadline = Instant::now() + CLOSE_BUDGET;
                let all = every_fleet(states);
                for (fleet, state) in all {
                    while Instant::now() < deadline && pass(&fleet, &state, config, transform_of) > 0 {}
                }
                if let Some(store) = store {
                    save(states, store);
                }
                return;
            }
        }
        if let Some(store) = store
            && saved_at.elapsed() >= config.save_interval
        {
            save(states, store);
            saved_at = Instant::now();
        }
    }
}

/// Records a job: the new keyframe kept (fused by the next pass), recent poses
/// updated, retracted samples taken out of the kept input and of the map.
fn take_job(s: &mut FleetMapState, job: FleetMapJob, max_keyframes: usize) {
    let width = job.camera.width;
    s.rays.entry(job.session_id.clone()).or_insert_with(|| Arc::new(CameraRays::new(&job.camera)));
    for (id, pose) in &job.keyframe_poses {
        if let Some(k) = s.kept.get_mut(&(job.session_id.clone(), *id)) {
            k.session_from_camera = *pose;
        }
    }
    for r in &job.retractions {
        let key = (job.session_id.clone(), r.keyframe);
        let Some(k) = s.kept.get_mut(&key) else { continue };
        let Some(rays) = s.rays.get(&job.session_id) else { continue };
        let Ok(mut input) = FusionInput::from_compact(&k.input, rays) else { continue };
        let covered = r.pixel_test(k.width);
        let (taken, kept): (Vec<_>, Vec<_>) = input.samples.iter().partition(|p| covered(p.pixel));
        if taken.is_empty() {
            continue;
        }
        input.samples = kept;
        if let Some(at) = k.fused_at {
            s.map.deintegrate_samples(&taken, &at);
        }
        match input.to_compact() {
            Ok(compact) => k.input = compact,
            Err(e) => tracing::warn!(session = %job.session_id, keyframe = r.keyframe, "retraction not kept for the fleet map: {e}"),
        }
    }
    if let Some((id, timestamp_ns, session_from_camera, input)) = job.keyframe {
        let compact = match input.to_compact() {
            Ok(c) => c,
            Err(e) => {
                tracing::warn!(session = %job.session_id, keyframe = id, "keyframe left out of the fleet map: {e}");
                return;
            }
        };
        let key = (job.session_id.clone(), id);
        let kept = Kept { timestamp_ns, session_from_camera, fused_at: None, input: compact, width };
        if s.kept.insert(key.clone(), kept).is_none() {
            *s.held.entry(job.session_id).or_default() += 1;
        }
        s.order.push_back(key);
        while s.order.len() > max_keyframes {
            let Some(old) = s.order.pop_front() else { break };
            // What it fused stays where it is; it will not move again.
            if s.kept.remove(&old).is_some_and(|k| k.fused_at.is_none())
                && let Some(n) = s.held.get_mut(&old.0)
            {
                // Never fused and now never will be: its session's keyframes are no longer all here.
                *n = n.saturating_sub(1);
            }
            // A session with nothing kept any more needs no rays.
            if !s.order.iter().any(|(session, _)| *session == old.0) {
                s.rays.remove(&old.0);
            }
        }
    }
}

/// Fuses the keyframes of merged sessions not fused yet, and fuses again those
/// whose fleet pose moved, at most `refuse_per_pass` of them. Nothing is fused
/// while the fleet has one merged session (its map is that session's own): the
/// inputs wait until a second one merges. Returns the keyframes it fused.
fn pass(fleet: &str, handle: &FleetMapHandle, config: &FleetMapConfig, transform_of: &TransformOf) -> usize {
    let mut s = lock(&handle.state);
    let transforms: HashMap<String, Option<FleetTransform>> = s.held.keys().map(|id| (id.clone(), transform_of(fleet, id))).collect();
    if transforms.values().filter(|t| t.is_some()).count() < 2 {
        *lock(&handle.counts) = s.counts();
        return 0;
    }
    let (max_t, max_deg) = (config.mapping.refuse_translation_m, config.mapping.refuse_rotation_deg);
    let mut todo: Vec<((String, u64), Isometry3<f64>)> = Vec::new();
    for key in &s.order {
        let Some(k) = s.kept.get(key) else { continue };
        let Some(Some(t)) = transforms.get(&key.0) else { continue };
        let target = t.at(k.timestamp_ns) * k.session_from_camera;
        let due = match k.fused_at {
            None => true,
            Some(at) => {
                let delta = at.inverse() * target;
                delta.translation.vector.norm() > max_t || delta.rotation.angle().to_degrees() > max_deg
            }
        };
        if due {
            todo.push((key.clone(), target));
            if todo.len() >= config.refuse_per_pass {
                break;
            }
        }
    }
    let mut done = 0;
    for (key, target) in todo {
        let FleetMapState { map, rays, kept, refused, fused, .. } = &mut *s;
        let (Some(k), Some(r)) = (kept.get_mut(&key), rays.get(&key.0)) else { continue };
        let Ok(input) = FusionInput::from_compact(&k.input, r) else { continue };
        let first = k.fused_at.is_none();
        if let Some(at) = k.fused_at {
            map.deintegrate(&input, &at);
            *refused += 1;
        }
        map.integrate(r, &input, &target);
        k.fused_at = Some(target);
        if first {
            *fused.entry(key.0.clone()).or_default() += 1;
        }
        done += 1;
    }
    *lock(&handle.counts) = s.counts();
    done
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use stillmap_mapping::DepthView;

    /// One keyframe (id 7, captured at 1 µs) of `session`: a wall 2 m ahead, and
    /// for session "s" a box 1 m ahead in the left half (session t sees no left half).
    fn job(camera: &Camera, session: &str, keyframe: Option<u64>, retractions: Vec<Retraction>) -> FleetMapJob {
        let (w, h) = (camera.width as usize, camera.height as usize);
        // Session t sees only the wall's right half (nothing of the box, so it carves none of it).
        let depth: Vec<u16> = (0..w * h)
            .map(|i| match (session, i % w < w / 2) {
                ("s", true) => 1000,
                (_, true) => 0,
                _ => 2000,
            })
            .collect();
        let rgb = vec![100u8; w * h * 3];
        let map = VoxelMap::new(MappingConfig::default()).expect("map");
        let input =
            map.prepare(&CameraRays::new(camera), &DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: None }).expect("input");
        FleetMapJob {
            fleet: "lab".into(),
            session_id: session.into(),
            camera: camera.clone(),
            keyframe: keyframe.map(|id| (id, 1_000, Isometry3::identity(), input)),
            keyframe_poses: Vec::new(),
            retractions,
        }
    }

    fn config(mapping: MappingConfig, save_interval: Duration) -> FleetMapConfig {
        FleetMapConfig { mapping, queue: 4, max_keyframes: 10, refuse_per_pass: 8, nice: 0, save_interval }
    }

    /// Waits until fleet "lab"'s counts satisfy `done`.
    fn wait_for(maps: &FleetMaps, done: &dyn Fn(FleetMapCounts) -> bool) -> FleetMapCounts {
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        loop {
            if let Some(c) = maps.state("lab").map(|s| s.counts()).filter(|c| done(*c)) {
                return c;
            }
            assert!(std::time::Instant::now() < deadline, "never got there: {:?}", maps.state("lab").map(|s| s.counts()));
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Fleet "lab"'s occupied voxels and keyframes fused per session ("s", "t").
    fn contents(maps: &FleetMaps) -> (std::collections::BTreeSet<[i32; 3]>, (u64, u64)) {
        let s = maps.state("lab").expect("state");
        let s = lock(&s.state);
        let voxels = s.map().occupied().map(|(k, _, _)| [k[0], k[1], k[2]]).collect();
        (voxels, (s.fused("s"), s.fused("t")))
    }

    /// Session `session`'s keyframe `id` (see [`job`]) taken `back` metres further from the wall.
    fn job_back(camera: &Camera, session: &str, id: u64, back: f64) -> FleetMapJob {
        let mut j = job(camera, session, Some(id), Vec::new());
        if let Some((_, _, pose, _)) = j.keyframe.as_mut() {
            *pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, -back), UnitQuaternion::identity());
        }
        j
    }

    /// Whether fleet "lab"'s map has occupied voxels within 3 cm of depth `z` (fleet frame).
    fn wall_at(maps: &FleetMaps, z: f64) -> bool {
        let s = maps.state("lab").expect("state");
        let s = lock(&s.state);
        s.map().occupied().any(|(_, c, _)| (c.z - z).abs() < 0.03)
    }

    /// A keyframe finding the fleet map's queue full is left out and counted
    /// (`stillmap_fleet_keyframes_left_out_total{queue="fleet_map"}`), so an
    /// operator sees the fleet map fall behind; a job without a keyframe left out
    /// is not counted as one.
    #[test]
    fn a_keyframe_left_out_of_a_full_queue_is_counted() {
        let camera = Camera::pinhole(160, 120, 130.0, 130.0, 79.5, 59.5, 1000.0);
        let metrics = Arc::new(crate::metrics::Metrics::default());
        let unmerged: TransformOf = Arc::new(|_: &str, _: &str| None);
        let one_job = FleetMapConfig { queue: 1, ..config(MappingConfig::default(), Duration::from_secs(3600)) };
        let maps = FleetMaps::start(one_job, unmerged, None, metrics.clone()).expect("started");
        assert!(maps.submit(job(&camera, "s", Some(1), Vec::new())));
        wait_for(&maps, &|c| c.keyframes == 1);
        let left_out = |metrics: &crate::metrics::Metrics| metrics.counter(r#"stillmap_fleet_keyframes_left_out_total{queue="fleet_map"}"#);
        assert_eq!(left_out(&metrics), 0);
        // Holding the fleet's state stops the thread at its next pass (one runs
        // every PASS_INTERVAL without a job) or job: it holds one job at most, the
        // queue one more.
        let state = maps.state("lab").expect("state");
        let held = lock(&state.state);
        std::thread::sleep(PASS_INTERVAL * 2);
        let queued = (2..8).filter(|&id| maps.submit(job(&camera, "s", Some(id), Vec::new()))).count();
        assert!((1..=2).contains(&queued), "{queued} of 6 queued");
        assert_eq!(left_out(&metrics), 6 - queued as u64);
        // Queued or left out, a job without a keyframe is no keyframe left out.
        let _ = maps.submit(job(&camera, "s", None, Vec::new()));
        assert_eq!(left_out(&metrics), 6 - queued as u64, "a job without a keyframe is no keyframe left out");
        drop(held);
        let c = wait_for(&maps, &|c| c.keyframes == 1 + queued as u64);
        assert_eq!(c.fused, 0, "unmerged: held, not fused");
        maps.close();
    }

    /// A fused fleet map is saved (every `save_interval`, and when it stops) and
    /// comes back at start with what it fused, so the fleet is served from it
    /// again; it goes on fusing after; a map of another voxel size is left out,
    /// and the map started afresh then replaces its blocks in the store.
    #[test]
    fn a_fused_fleet_map_comes_back_after_a_restart() {
        let path = std::env::temp_dir().join(format!("stillmap-fleet-map-restart-{}.redb", std::process::id()));
        let _ = std::fs::remove_file(&path);
        let store = Arc::new(Store::open(&path).expect("store"));
        let camera = Camera::pinhole(160, 120, 130.0, 130.0, 79.5, 59.5, 1000.0);
        let merge = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.1), UnitQuaternion::identity());
        let both: TransformOf =
            Arc::new(move |_: &str, _: &str| Some(FleetTransform { fleet_from_session: merge, corrections: Arc::default() }));
        let start = |mapping: MappingConfig, save_interval: Duration| {
            FleetMaps::start(config(mapping, save_interval), both.clone(), Some(store.clone()), Arc::default()).expect("started")
        };

        // Saved while it runs, every save_interval. (The wall 2 m ahead lands at
        // 2.1 m in the fleet frame; a keyframe taken b metres back puts it at 2.1 − b.)
        let maps = start(MappingConfig::default(), Duration::from_millis(50));
        maps.submit(job(&camera, "s", Some(7), Vec::new()));
        maps.submit(job(&camera, "t", Some(7), Vec::new()));
        maps.submit(job_back(&camera, "t", 8, 0.3));
        wait_for(&maps, &|c| c.fused == 3);
        let (saved, fused) = contents(&maps);
        assert_eq!(fused, (1, 2));
        assert!(saved.len() > 200 && wall_at(&maps, 1.8), "{}", saved.len());
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        loop {
            let stored = store.fleet_maps().expect("read");
            if let Some((head, blocks)) = stored.get("lab").filter(|(head, _)| head.fused.values().sum::<u64>() == 3) {
                assert_eq!(head.fused.get("t"), Some(&2));
                assert!(!blocks.is_empty());
                break;
            }
            assert!(std::time::Instant::now() < deadline, "never saved: {:?}", stored.keys().collect::<Vec<_>>());
            std::thread::sleep(Duration::from_millis(20));
        }
        // A keyframe submitted as the server stops is fused and saved as it stops.
        maps.submit(job_back(&camera, "t", 9, 0.6));
        maps.close();

        // Back at start, before any job: every voxel and the keyframes fused.
        let maps = start(MappingConfig::default(), Duration::from_secs(3600));
        let c = maps.state("lab").expect("restored").counts();
        assert_eq!((c.keyframes, c.fused, c.kept_inputs), (4, 4, 0), "{c:?}");
        let (after, fused) = contents(&maps);
        assert_eq!(fused, (1, 3));
        assert!(after.is_superset(&saved) && wall_at(&maps, 1.8), "what was saved while it ran");
        assert!(wall_at(&maps, 1.5), "what was fused and saved as it stopped");
        // It goes on fusing.
        maps.submit(job_back(&camera, "t", 10, 0.9));
        wait_for(&maps, &|c| c.fused == 5);
        assert_eq!(contents(&maps).1, (1, 4));
        assert!(wall_at(&maps, 1.2));
        maps.close();

        // Another voxel size: the stored map is not this server's, the fleet starts
        // empty, and its first save replaces the stored blocks.
        let coarse = MappingConfig { voxel_size_m: 0.04, ..MappingConfig::default() };
        let maps = start(coarse.clone(), Duration::from_secs(3600));
        assert!(maps.state("lab").is_none());
        maps.submit(job(&camera, "s", Some(7), Vec::new()));
        maps.submit(job(&camera, "t", Some(7), Vec::new()));
        wait_for(&maps, &|c| c.fused == 2);
        let (coarse_voxels, _) = contents(&maps);
        maps.close();
        let maps = start(coarse, Duration::from_secs(3600));
        let (back, fused) = contents(&maps);
        assert_eq!(fused, (1, 1));
        assert!(back == coarse_voxels, "the 2 cm blocks are gone: {} voxels back, {} saved", back.len(), coarse_voxels.len());
        assert!(!wall_at(&maps, 1.2), "nothing of the 2 cm map is left");
        maps.close();
        drop(maps);
        drop(store);
        let _ = std::fs::remove_file(&path);
    }

    /// Keyframes wait until a second session merges, are fused where their merges
    /// put them, move when the pose graph corrects them, and leave the map where
    /// perception takes their samples back.
    #[test]
    fn keyframes_are_fused_at_their_merge_moved_by_corrections_and_retracted() {
        let camera = Camera::pinhole(160, 120, 130.0, 130.0, 79.5, 59.5, 1000.0);
        let transforms: Arc<Mutex<HashMap<String, FleetTransform>>> = Arc::default();
        let shared = transforms.clone();
        let maps = FleetMaps::start(
            config(MappingConfig::default(), Duration::from_secs(3600)),
            Arc::new(move |_: &str, session: &str| lock(&shared).get(session).cloned()),
            None,
            Arc::default(),
        )
        .expect("started");
        let wait = |done: &dyn Fn(FleetMapCounts) -> bool| wait_for(&maps, done);
        // (mean height of the wall's voxels, their count, the box's voxels)
        let measure = || {
            let s = maps.state("lab").expect("state");
            let s = lock(&s.state);
            let far: Vec<f64> = s.map().occupied().map(|(_, c, _)| c.z).filter(|z| *z > 1.5).collect();
            let near = s.map().occupied().filter(|(_, c, _)| c.z < 1.5 && c.z > 0.5).count();
            (far.iter().sum::<f64>() / far.len().max(1) as f64, far.len(), near)
        };
        let merge = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.1), UnitQuaternion::identity());
        let merged =
            |corrections: Vec<(u64, Isometry3<f64>)>| FleetTransform { fleet_from_session: merge, corrections: Arc::new(corrections) };
        lock(&transforms).insert("s".into(), merged(Vec::new()));
        maps.submit(job(&camera, "s", Some(7), Vec::new()));
        maps.submit(job(&camera, "t", Some(7), Vec::new()));
        let c = wait(&|c| c.keyframes == 2);
        assert_eq!((c.fused, c.kept_inputs), (0, 2), "one merged session: kept, not fused");
        // Both merged, 10 cm along z.
        lock(&transforms).insert("t".into(), merged(Vec::new()));
        wait(&|c| c.fused == 2);
        let (z, far, near) = measure();
        assert!((z - 2.1).abs() < 0.02 && far > 100 && near > 100, "{z} {far} {near}");
        assert_eq!(lock(&maps.state("lab").expect("state").state).fused("s"), 1);
        // The pose graph moves both keyframes 20 cm further.
        let correction = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.2), UnitQuaternion::identity());
        for session in ["s", "t"] {
            lock(&transforms).insert(session.into(), merged(vec![(1_000, correction)]));
        }
        let c = wait(&|c| c.refused == 2);
        assert_eq!((c.keyframes, c.fused), (2, 2));
        let (z, far_after, _) = measure();
        assert!((z - 2.3).abs() < 0.02, "{z}");
        assert!(far_after <= far + far / 10, "their hits left the old place: {far} then {far_after}");
        // The box (left half of session s's keyframe) is found moving: its samples leave the fleet map.
        let box_cells = Retraction {
            keyframe: 7,
            cells: (0..12).flat_map(|y| (0..8).map(move |x| y * 16 + x)).collect(),
            grid_width: 16,
            grid_height: 12,
            subsample: 10,
        };
        maps.submit(job(&camera, "s", None, vec![box_cells]));
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while measure().2 > 0 {
            assert!(std::time::Instant::now() < deadline, "the box stays: {:?}", measure());
            std::thread::sleep(Duration::from_millis(20));
        }
        assert_eq!(measure().1, far_after, "the wall stays");
        // Bounded: at most max_keyframes (10) inputs are kept; the rest stay where they were fused.
        for id in 100..120 {
            maps.submit(job(&camera, "t", Some(id), Vec::new()));
            // Each fused before the next comes, so none is dropped unfused.
            wait(&|c| c.keyframes == 2 + id - 99 && c.fused == c.keyframes);
        }
        let c = wait(&|c| c.keyframes == 22);
        assert_eq!((c.keyframes, c.kept_inputs), (22, 10), "{c:?}");
        assert_eq!(lock(&maps.state("lab").expect("state").state).fused("t"), 21);
        maps.close();
    }
}
