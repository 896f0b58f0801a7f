//! Robot sessions: the registry both ingest transports feed, and each session's
//! pipeline and map work on the shared worker pools.
//!
//! A session outlives its connection: a robot that reconnects with
//! `Hello.resume_session_id` gets the same session back, and queries keep
//! answering for disconnected sessions. Results go to whichever connection is
//! attached when the pipeline finishes a frame.
//!
//! No session owns a thread. Its frame queue is a [`Lane`] of the pipeline pool
//! (`session.pipeline_threads`); the tracking path (decode, perception, tracking)
//! runs there and answers the frame. A new keyframe (and keyframes bundle
//! adjustment moved) become a job on the session's map lane, run by the map pool
//! (`session.map_threads`): fusion and the store commit never hold up tracking. The
//! map lane is bounded (`session.map_queue`); a keyframe finding it full is left
//! out of the map and counted (`stillmap_map_jobs_skipped_total`).

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock, Weak};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use stillmap_mapping::MappingConfig;
use stillmap_perception::PerceptionConfig;
use stillmap_proto::pb::{self, FrameStatus, TrackingState, server_message::Msg};
use stillmap_tracking::TrackerConfig;
use tokio::sync::{broadcast, mpsc, watch};
use tonic::Status;

use crate::config::{LimitsConfig, SessionConfig};
use crate::map::{SessionMap, SharedMap};
use crate::metrics::Metrics;
use crate::pipeline::decode::validate_camera;
use crate::pipeline::fuse::{self, MapJob};
use crate::pipeline::segmentation::SegmentationService;
use crate::pipeline::{FrameOutcome, SessionPipeline, micros, stage};
use crate::pool::{Lane, Pool};
use crate::queue::{FrameQueue, PushOutcome, QueueError, QueuedFrame, Work};
use crate::store::{SessionHead, SessionMeta, Store, StoreError, StoredSession};
use crate::{lock, read, write};

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
    /// The transport a stored session's description names (`label`'s inverse).
    fn stored(label: &str) -> Self {
        if label == Self::Zenoh.label() { Self::Zenoh } else { Self::Grpc }
    }

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
    /// The newest poses, in the order they came (every pose unless older ones
    /// left memory: `earlier`).
    pub trajectory: Vec<pb::PoseStamped>,
    /// Poses before `trajectory[0]`: committed to the store and out of memory
    /// (`session.trajectory_in_memory`); the store holds them first, in the order
    /// they came.
    pub earlier: usize,
    /// The latest capture time among the poses out of memory: a page starting
    /// after it needs no store read.
    pub earlier_until_ns: u64,
}

/// Sessions a list answers with when the request names no limit: about 0.5 MB of
/// JSON or protobuf.
pub const DEFAULT_SESSIONS_PAGE: usize = 1_000;
/// The most sessions one list answer holds (about 2.5 MB: under a gRPC client's
/// default 4 MiB message limit).
pub const MAX_SESSIONS_PAGE: usize = 5_000;

/// A place in the sessions list, which is ordered by start time, then id: a page
/// starts after it. Its token (`<started_unix_ns>:<session_id>`) is what the lists
/// answer as `next_page_token` and take back as `page_token`; it stays right
/// while sessions come and go, and over several servers' lists merged.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct ListCursor {
    pub started_unix_ns: u64,
    pub session_id: String,
}

impl ListCursor {
    pub fn of(summary: &pb::SessionSummary) -> Self {
        Self { started_unix_ns: summary.started_unix_ns, session_id: summary.session_id.clone() }
    }

    pub fn token(&self) -> String {
        format!("{}:{}", self.started_unix_ns, self.session_id)
    }

    /// Reads a token that [`token`](Self::token) wrote.
    pub fn parse(token: &str) -> Result<Self, String> {
        let bad = || format!("page_token {token:?} is not one a sessions list gave (<started_unix_ns>:<session_id>)");
        let (started, id) = token.split_once(':').ok_or_else(bad)?;
        let started_unix_ns = started.parse().map_err(|_| bad())?;
        if id.is_empty() {
            return Err(bad());
        }
        Ok(Self { started_unix_ns, session_id: id.to_string() })
    }
}

/// Poses a trajectory query answers with when it names no limit on gRPC (about
/// 2 MB, under a client's default 4 MiB message limit).
pub const DEFAULT_TRAJECTORY_PAGE: usize = 20_000;
/// The most poses one trajectory answer holds (HTTP's default): about 1.9 hours
/// at 30 Hz, 18 MB as TUM text.
pub const MAX_TRAJECTORY_PAGE: usize = 200_000;

impl TrackState {
    /// Poses of the whole trajectory, in memory or not.
    pub fn len(&self) -> usize {
        self.earlier + self.trajectory.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Leaves the oldest poses out of memory once more than `keep` · 5/4 are
    /// held, down to `keep`, but only the first `committed` of the trajectory
    /// (those the store holds); `keep` 0 keeps every pose. Returns how many left.
    pub fn trim(&mut self, committed: usize, keep: usize) -> usize {
        if keep == 0 || self.trajectory.len() <= keep + keep / 4 {
            return 0;
        }
        let out = (self.trajectory.len() - keep).min(committed.saturating_sub(self.earlier));
        let until = self.trajectory.drain(..out).map(|p| p.capture_time_ns).max();
        self.earlier_until_ns = self.earlier_until_ns.max(until.unwrap_or(0));
        self.earlier += out;
        // A session read back from the store drops most of its poses at once.
        if self.trajectory.capacity() > 2 * self.trajectory.len().max(keep) {
            self.trajectory.shrink_to_fit();
        }
        out
    }
}

/// One page of a trajectory, built from its poses in any order with bounded
/// memory (about twice the limit): the poses captured within `start_ns..=end_ns`
/// in capture-time order (the order they came, unless a robot's clock went back
/// and its timeline was taken again), `limit` of them and any more of the last
/// one's capture time, and where the next page starts (the next pose's capture
/// time) when more of the range follow: asking again from there skips and
/// repeats nothing.
pub struct Page {
    range: std::ops::RangeInclusive<u64>,
    limit: usize,
    kept: Vec<pb::PoseStamped>,
}

impl Page {
    pub fn new(start_ns: u64, end_ns: u64, limit: usize) -> Self {
        Self { range: start_ns..=end_ns, limit: limit.max(1), kept: Vec::new() }
    }

    pub fn push(&mut self, pose: pb::PoseStamped) {
        if self.range.contains(&pose.capture_time_ns) {
            self.kept.push(pose);
            if self.kept.len() > 2 * self.limit + 1 {
                self.compact();
            }
        }
    }

    /// Sorts what is kept and keeps the page and the first pose after it: no
    /// pose after that one can be on the page or start the next.
    fn compact(&mut self) -> Option<u64> {
        if !self.kept.is_sorted_by_key(|p| p.capture_time_ns) {
            self.kept.sort_by_key(|p| p.capture_time_ns);
        }
        let mut cut = self.limit.min(self.kept.len());
        while cut > 0 && cut < self.kept.len() && self.kept[cut].capture_time_ns == self.kept[cut - 1].capture_time_ns {
            cut += 1;
        }
        let next = self.kept.get(cut).map(|p| p.capture_time_ns);
        self.kept.truncate(cut + usize::from(next.is_some()));
        next
    }

    pub fn finish(mut self) -> (Vec<pb::PoseStamped>, Option<u64>) {
        let next = self.compact();
        if next.is_some() {
            self.kept.pop();
        }
        (self.kept, next)
    }
}

pub struct Session {
    pub id: String,
    pub robot_id: String,
    /// What a hello resuming this session must carry (`Hello.resume_secret`).
    resume_secret: String,
    /// A session resumed from the shared storage: where its new tracker must find
    /// itself (taken by the first pipeline).
    resume_anchor: Mutex<Option<crate::pipeline::track::ResumeAnchor>>,
    /// The fleet the hello named (or the default one).
    pub fleet_name: String,
    pub transport: Transport,
    pub camera: pb::CameraInfo,
    pub started_unix_ns: u64,
    pub counters: Counters,
    connected: AtomicBool,
    queue: FrameQueue,
    sink: Mutex<Option<ResultSink>>,
    /// Why the stream was ended (a limit, a resume given up): frames that still
    /// arrive are refused with the same status.
    ended: Mutex<Option<(tonic::Code, String)>>,
    last_received_sequence: Mutex<Option<u64>>,
    /// Frames received in a row whose sequence jumped past the order window.
    received_jumps: Mutex<crate::pipeline::decode::JumpCount>,
    /// The sequence received before `last_received_sequence` (as the decoder's: a
    /// frame behind both is a resend, never a new timeline).
    received_before_last: Mutex<Option<u64>>,
    /// `limits.frame_cpu_ms`: what one frame may cost on a pipeline thread.
    cpu_budget: CpuBudget,
    track: Mutex<TrackState>,
    /// `session.trajectory_in_memory`.
    trajectory_in_memory: usize,
    poses: broadcast::Sender<pb::PoseStamped>,
    fleet: broadcast::Sender<FleetPose>,
    /// The last processed frame's stage latencies (the dashboard's sparklines).
    last_latency: Mutex<Vec<pb::StageLatency>>,
    answered_tx: watch::Sender<u64>,
    metrics: Arc<Metrics>,
    tracker_config: TrackerConfig,
    /// How far a frame may jump past the previous one (`session.max_sequence_jump`, …).
    order_window: crate::pipeline::decode::OrderWindow,
    perception: Option<(PerceptionConfig, Option<Arc<SegmentationService>>)>,
    /// The static semantic map (`None`: mapping off, or it could not start).
    map: Option<SharedMap>,
    /// Restored from the store after a restart: queries only, no worker.
    archived: bool,
    /// Place recognition, fed each committed keyframe (`None`: fleets off).
    fleets: Option<Arc<crate::fleet::FleetService>>,
    /// The pools this session's work runs on (`None`: archived).
    pools: Option<Pools>,
    /// The pipeline state, built on the first frame (the pool runs one slice of a
    /// session at a time, so this lock is never contended).
    worker: Mutex<Option<SessionPipeline>>,
    /// On the pipeline pool's ready list or running there.
    scheduled: AtomicBool,
    /// Fusion and store commits, in order, off the tracking path.
    map_lane: Option<Arc<MapLane>>,
    /// Waiting for room in the connection's result buffer (see `park_while_full`).
    parked: AtomicBool,
    /// The runtime that wakes a parked session (`None` outside one: unit tests).
    runtime: Option<tokio::runtime::Handle>,
    /// When a robot or a query last used the session (idle eviction counts from it).
    touched: Mutex<Instant>,
    me: Weak<Session>,
}

/// The shared worker pools: the tracking path, and map fusion with store commits.
#[derive(Clone)]
pub struct Pools {
    pub pipeline: Arc<Pool>,
    pub map: Arc<Pool>,
}

impl Pools {
    /// Starts the pools `config` sizes (0 pipeline threads: one per core).
    pub fn start(config: &SessionConfig) -> std::io::Result<Self> {
        let cores = std::thread::available_parallelism().map_or(1, std::num::NonZeroUsize::get);
        let pipeline = if config.pipeline_threads == 0 { cores } else { config.pipeline_threads };
        Ok(Self { pipeline: Pool::new("pipeline", pipeline)?, map: Pool::new("map", config.map_threads)? })
    }

    /// Finishes what is queued and stops the threads (the pipeline first: its last
    /// frames may still give the map work).
    pub fn close(&self) {
        self.pipeline.close();
        self.map.close();
    }
}

/// Frames a pipeline slice processes before the pool turns to another session.
const PIPELINE_SLICE_FRAMES: usize = 4;

/// A session's bounded queue of map jobs (a lane of the map pool).
struct MapLane {
    jobs: Mutex<VecDeque<MapJob>>,
    capacity: usize,
    /// `session.keyframe_images`.
    keyframe_images: usize,
    scheduled: AtomicBool,
    session: Weak<Session>,
}

impl Lane for MapLane {
    fn run_slice(&self) {
        let Some(session) = self.session.upgrade() else { return };
        let Some(job) = lock(&self.jobs).pop_front() else { return };
        session.metrics.map_backlog(-1);
        session.run_map_job(job);
    }
    fn has_work(&self) -> bool {
        !lock(&self.jobs).is_empty()
    }
    fn scheduled(&self) -> &AtomicBool {
        &self.scheduled
    }
    /// The job is dropped (its keyframe may be partly fused); the session's frames
    /// and later keyframes go on.
    fn failed(&self, panic: &str) {
        let Some(session) = self.session.upgrade() else { return };
        session.metrics.panicked("map");
        tracing::error!(session = %session.id, "a map job panicked (a bug; its keyframe may be partly in the map): {panic}");
    }
}

impl Lane for Session {
    fn run_slice(&self) {
        let mut worker = lock(&self.worker);
        for _ in 0..PIPELINE_SLICE_FRAMES {
            // A client that does not read its results must not hold a pool thread:
            // the session parks until its connection has room again, and meanwhile
            // its queue applies the overload policy (the back-pressure of a slow reader).
            if self.park_while_full() {
                return;
            }
            let Some(work) = self.queue.try_pop() else { break };
            // Frames still queued when the stream was ended (a limit, a resume given
            // up) are not run.
            let work = match work {
                Work::Frame(q) if lock(&self.ended).is_some() => {
                    Work::Dropped { sequence: q.frame.sequence, capture_time_ns: q.frame.capture_time_ns }
                }
                work => work,
            };
            let result = match work {
                Work::Dropped { sequence, capture_time_ns } => pb::FrameResult {
                    sequence,
                    capture_time_ns,
                    status: FrameStatus::Dropped as i32,
                    tracking_state: self.tracking().state as i32,
                    ..Default::default()
                },
                Work::Frame(queued) => {
                    let pipeline = worker.get_or_insert_with(|| self.new_pipeline());
                    let cpu_before = thread_cpu_time();
                    let mut outcome = pipeline.process(&queued);
                    let over_budget = self.cpu_budget.spent(outcome.sequence, thread_cpu_time().saturating_sub(cpu_before));
                    if let Some(job) = outcome.map_job.take()
                        && let Some(job) = self.hand_to_map(job)
                    {
                        pipeline.map_job_refused(&job);
                    }
                    let result = self.account(&outcome);
                    let abandoned = outcome.track.as_ref().is_some_and(|t| t.resume_abandoned).then(|| {
                        self.metrics.session_ended("resume_find_s");
                        tonic::Status::aborted(format!(
                            "session {} was not found again in its stored world within session.resume_find_s: open a new session",
                            self.id
                        ))
                    });
                    if let Some(status) = over_budget.or(abandoned) {
                        self.deliver(result);
                        self.end_stream(status);
                        return;
                    }
                    result
                }
            };
            self.deliver(result);
        }
    }
    fn has_work(&self) -> bool {
        !self.parked.load(Ordering::SeqCst) && !self.queue.is_empty_of_work()
    }
    fn scheduled(&self) -> &AtomicBool {
        &self.scheduled
    }
    /// A frame panicked the pipeline: its state may be half-way through that frame,
    /// so it is dropped and the stream ended (ABORTED, which the client answers with
    /// a new session); the frames still queued are answered DROPPED. What the session
    /// committed stays.
    fn failed(&self, panic: &str) {
        *lock(&self.worker) = None;
        self.metrics.panicked("pipeline");
        self.metrics.session_ended("panic");
        self.end_stream(tonic::Status::aborted(format!(
            "session {} failed on a frame (a server bug: {panic}): open a new session",
            self.id
        )));
    }
}

/// CPU time this thread has used (zero where the clock cannot be read).
fn thread_cpu_time() -> Duration {
    let mut t = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `t` is a valid timespec to write into; CLOCK_THREAD_CPUTIME_ID is
    // the calling thread's CPU clock, which every Linux has.
    let ok = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) } == 0;
    if !ok {
        return Duration::ZERO;
    }
    Duration::new(u64::try_from(t.tv_sec).unwrap_or(0), u32::try_from(t.tv_nsec).unwrap_or(0))
}

/// `limits.frame_cpu_ms` for one session: frames over it are counted, and
/// `limits.frame_cpu_strikes` of them in a row end the session's stream.
struct CpuBudget {
    /// `None`: no budget.
    per_frame: Option<Duration>,
    strikes: u32,
    over_in_row: AtomicU32,
    metrics: Arc<Metrics>,
}

impl CpuBudget {
    fn new(limits: &LimitsConfig, metrics: Arc<Metrics>) -> Self {
        let per_frame = (limits.frame_cpu_ms > 0.0).then(|| Duration::from_secs_f64(limits.frame_cpu_ms / 1e3));
        Self { per_frame, strikes: limits.frame_cpu_strikes.max(1), over_in_row: AtomicU32::new(0), metrics }
    }

    /// Counts a frame that took `cpu`: the status ending the stream when it was
    /// the last strike.
    fn spent(&self, sequence: u64, cpu: Duration) -> Option<tonic::Status> {
        let budget = self.per_frame?;
        if cpu <= budget {
            self.over_in_row.store(0, Ordering::Relaxed);
            return None;
        }
        self.metrics.frame_cpu_over_budget();
        let in_row = self.over_in_row.fetch_add(1, Ordering::Relaxed) + 1;
        tracing::warn!(
            sequence,
            cpu_ms = cpu.as_secs_f64() * 1e3,
            in_row,
            "frame over limits.frame_cpu_ms = {}",
            budget.as_secs_f64() * 1e3
        );
        // The stream ends at the last strike; the frames after it are not run
        // (`Session::ended`), so this fires once.
        (in_row >= self.strikes).then(|| {
            self.metrics.session_ended("frame_cpu_ms");
            tonic::Status::resource_exhausted(format!(
                "{in_row} frames in a row took more than limits.frame_cpu_ms = {} ms of CPU each (frame {sequence}: {:.0} ms): the session takes no more frames",
                budget.as_secs_f64() * 1e3,
                cpu.as_secs_f64() * 1e3
            ))
        })
    }
}

impl Session {
    /// Ends the session's stream with `status` (a limit it went over): its queue
    /// takes no more frames, the connection hears why.
    fn end_stream(&self, status: tonic::Status) {
        tracing::warn!(session = %self.id, "stream ended: {}", status.message());
        *lock(&self.ended) = Some((status.code(), status.message().to_string()));
        self.queue.close();
        if let Some(sink) = lock(&self.sink).clone()
            && sink.try_send(Err(status)).is_err()
        {
            tracing::warn!(session = %self.id, "the connection's buffer is full: it hears of the end from its next frame (session closed)");
        }
    }

    /// The status refusing a frame that `push` could not queue: why the stream was
    /// ended, when it was, else the queue's own.
    pub fn refusal_of(&self, e: QueueError) -> tonic::Status {
        match lock(&self.ended).as_ref() {
            Some((code, message)) => tonic::Status::new(*code, message.clone()),
            None => crate::ingest::queue_status(e),
        }
    }

    /// Queues a received frame. Dropped frames are counted here and answered by the worker.
    pub fn push(&self, frame: pb::Frame, encoded_len: usize) -> Result<(), QueueError> {
        let transport = self.transport.label();
        let sequence = frame.sequence;
        self.metrics.frame_received(transport, encoded_len);
        let outcome = self.queue.push(QueuedFrame { frame, received_at: Instant::now() })?;
        self.touch();
        self.counters.received.fetch_add(1, Ordering::Relaxed);
        self.counters.bytes.fetch_add(encoded_len as u64, Ordering::Relaxed);
        {
            // A frame jumping absurdly far (forged, corrupt) is rejected when decoded,
            // and must not tell a resuming robot it was received.
            // (A new timeline is followed here when the decoder follows it.)
            let mut last = lock(&self.last_received_sequence);
            let mut before = lock(&self.received_before_last);
            // As the decoder: a frame behind the last but after the one before it
            // counts as a jump too; one behind both is a resend.
            let behind = last.is_some_and(|l| sequence < l) && before.is_none_or(|b| sequence > b);
            let jumped = !self.order_window.sequence_fits(*last, sequence) || behind;
            if lock(&self.received_jumps).restart(jumped) {
                (*before, *last) = (None, Some(sequence));
            } else if !jumped && last.is_none_or(|l| sequence > l) {
                (*before, *last) = (*last, Some(sequence));
            }
        }
        if outcome != PushOutcome::Queued {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
            self.metrics.frame_dropped(transport);
        }
        // Counted first, so the frame is never answered before it was received.
        self.schedule();
        Ok(())
    }

    /// The secret a resume must present, for the accept.
    pub fn resume_secret(&self) -> &str {
        &self.resume_secret
    }

    /// `Ok` when `given` is this session's resume secret (compared in constant time).
    pub fn check_resume_secret(&self, given: &str) -> Result<(), BadHello> {
        if crate::auth::same_secret(&self.resume_secret, given) {
            Ok(())
        } else {
            Err(BadHello::Unauthenticated(format!(
                "resuming session {} needs the resume secret its accept returned (Hello.resume_secret)",
                self.id
            )))
        }
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

    /// A page of the trajectory ([`Page`]): the poses in memory, and those that
    /// left memory (`session.trajectory_in_memory`) read back from the store.
    /// It may read the store: call it off the async runtimes.
    pub fn trajectory_page(&self, start_ns: u64, end_ns: u64, limit: usize) -> Result<(Vec<pb::PoseStamped>, Option<u64>), StoreError> {
        let mut page = Page::new(start_ns, end_ns, limit);
        let (earlier, until) = {
            let track = self.tracking();
            track.trajectory.iter().for_each(|p| page.push(*p));
            (track.earlier, track.earlier_until_ns)
        };
        if earlier > 0 && start_ns <= until {
            self.stored_poses(earlier, |p| page.push(p))?;
        }
        Ok(page.finish())
    }

    /// The whole trajectory, in the order it came: the poses that left memory
    /// read back from the store, then those in memory. Off the async runtimes.
    pub fn whole_trajectory(&self) -> Result<Vec<pb::PoseStamped>, StoreError> {
        let (mut tail, earlier) = {
            let track = self.tracking();
            (track.trajectory.clone(), track.earlier)
        };
        let mut all = Vec::with_capacity(earlier + tail.len());
        if earlier > 0 {
            self.stored_poses(earlier, |p| all.push(p))?;
        }
        all.append(&mut tail);
        Ok(all)
    }

    /// Why a trajectory query has no answer (HTTP 503, gRPC UNAVAILABLE): poses
    /// out of memory the store cannot give back.
    pub fn poses_unreadable(e: &StoreError) -> String {
        format!("the trajectory's older poses cannot be read back from the store: {e}")
    }

    /// Calls `f` with the first `n` poses of this session the store holds, those
    /// out of memory (outside the tracking and map locks). Fewer is an error: a
    /// trajectory with a gap is not answered.
    fn stored_poses(&self, n: usize, f: impl FnMut(pb::PoseStamped)) -> Result<(), StoreError> {
        let stored = self.map.as_ref().and_then(|m| lock(m).stored_as());
        let Some((store, id)) = stored else {
            return Err(StoreError::Corrupt(format!("session {}: poses left memory but there is no store", self.id)));
        };
        let read = store.first_poses(&id, n, f)?;
        if read < n {
            return Err(StoreError::Corrupt(format!("session {}: {n} poses left memory but the store holds {read}", self.id)));
        }
        Ok(())
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

    /// Records a use (a frame, a connection coming or going, a query).
    fn touch(&self) {
        *lock(&self.touched) = Instant::now();
    }

    /// How long since the session was last used.
    fn idle_for(&self) -> std::time::Duration {
        lock(&self.touched).elapsed()
    }

    /// What the session list shows of this session.
    pub fn info(&self) -> SessionInfo {
        SessionInfo {
            summary: summary(self),
            archived: self.archived,
            resident: true,
            fleet: self.fleet_name.clone(),
            bytes_received: self.counters.bytes.load(Ordering::Relaxed),
            last_received_sequence: self.last_received_sequence(),
            latest: self.tracking().latest,
        }
    }

    /// No robot attached, every frame answered, no map work queued or running.
    fn idle_parts(&self) -> bool {
        !self.is_connected()
            && self.unanswered() == 0
            && !self.scheduled.load(Ordering::SeqCst)
            && !self.map_lane.as_ref().is_some_and(|l| l.scheduled.load(Ordering::SeqCst) || !lock(&l.jobs).is_empty())
    }

    /// Whether the session holds nothing that would be lost if it left memory now:
    /// no robot attached, every frame answered, no map work queued or running,
    /// everything committed (`false` without a store or a map: nothing keeps it).
    fn at_rest(&self) -> bool {
        if self.archived {
            return true;
        }
        let Some(map) = &self.map else { return false };
        if !self.idle_parts() {
            return false;
        }
        let track = self.tracking();
        let m = lock(map);
        m.has_store() && !m.uncommitted(track.len())
    }

    /// Records the connection state; the gauge moves only when it changes.
    fn set_connected(&self, connected: bool) {
        if self.connected.swap(connected, Ordering::Relaxed) != connected {
            self.metrics.connected_delta(if connected { 1 } else { -1 });
        }
        self.touch();
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
            let message = Ok(pb::ServerMessage { msg: Some(Msg::Result(result)) });
            // The slice checked for room first (see `run_slice`); only a message the
            // ingest shell slipped in meanwhile can fill it, and then this waits.
            if let Err(mpsc::error::TrySendError::Full(message)) = sink.try_send(message) {
                let _ = sink.blocking_send(message);
            }
        }
        let answered = self.counters.answered.fetch_add(1, Ordering::Relaxed) + 1;
        self.answered_tx.send_replace(answered);
    }

    /// Publishes a tracked frame's state and pose to the query APIs and subscribers.
    fn record_pose(&self, result: &pb::FrameResult) {
        let state = result.tracking_state();
        let stamped = result.world_from_camera.map(|p| pb::PoseStamped {
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

    /// Puts this session's pipeline on the pool (it has work), unless it is parked.
    fn schedule(&self) {
        if self.parked.load(Ordering::SeqCst) {
            return;
        }
        if let (Some(pools), Some(me)) = (&self.pools, self.me.upgrade()) {
            pools.pipeline.schedule(me);
        }
    }

    /// When the attached connection's result buffer is full, parks the session: a
    /// task waits for room (or for the connection to go) and schedules it again.
    /// True when parked.
    fn park_while_full(&self) -> bool {
        if self.parked.load(Ordering::SeqCst) {
            return true;
        }
        let Some(sink) = lock(&self.sink).clone().filter(|s| s.capacity() == 0) else { return false };
        let Some(runtime) = &self.runtime else { return false };
        self.parked.store(true, Ordering::SeqCst);
        let me = self.me.clone();
        runtime.spawn(async move {
            // Room for one result, or the connection is gone: either way go on.
            drop(sink.reserve().await);
            if let Some(session) = me.upgrade() {
                session.parked.store(false, Ordering::SeqCst);
                session.schedule();
            }
        });
        true
    }

    fn new_pipeline(&self) -> SessionPipeline {
        let mut pipeline = SessionPipeline::new(
            &self.id,
            &self.camera,
            &self.tracker_config,
            self.perception.as_ref(),
            self.map.as_ref().map(fuse::refuse_window),
            self.order_window,
        );
        if let Some(anchor) = lock(&self.resume_anchor).take() {
            pipeline.resume_in(anchor);
        }
        pipeline
    }

    /// Publishes what a processed frame changed (pose, counters, metrics) and
    /// returns its result.
    fn account(&self, outcome: &FrameOutcome) -> pb::FrameResult {
        let result = pb::FrameResult::from(outcome);
        if let Some(track) = &outcome.track {
            self.record_pose(&result);
            if track.forgotten_keyframes > 0 {
                self.metrics.keyframes_forgotten(track.forgotten_keyframes);
            }
        }
        if let Some(mask) = &outcome.mask {
            self.metrics.perception(mask.label(), mask.dynamic_features);
        }
        if let Some(r) = &outcome.rejection {
            self.counters.rejected.fetch_add(1, Ordering::Relaxed);
            self.metrics.rejected(r.reason.label());
        } else {
            self.counters.processed.fetch_add(1, Ordering::Relaxed);
            self.metrics.frame_processed(self.transport.label());
            for l in &result.latency {
                self.metrics.stage(&l.stage, l.micros);
            }
            *lock(&self.last_latency) = result.latency.clone();
        }
        result
    }

    /// Queues a map job on the session's map lane; a full lane gives it back
    /// (tracking never waits for the map), counted in `/metrics`.
    fn hand_to_map(&self, job: MapJob) -> Option<MapJob> {
        let Some(lane) = &self.map_lane else { return None };
        {
            let mut jobs = lock(&lane.jobs);
            if jobs.len() >= lane.capacity {
                drop(jobs);
                let keyframe = job.keyframe.as_ref().map(|k| k.id);
                self.metrics.map_job_skipped(keyframe.is_some());
                tracing::warn!(session = %self.id, ?keyframe, "map queue full (session.map_queue): work left out of the map");
                return Some(job);
            }
            jobs.push_back(job);
        }
        self.metrics.map_backlog(1);
        if let Some(pools) = &self.pools {
            pools.map.schedule(lane.clone());
        }
        None
    }

    /// Map work of one frame, on the map pool: re-fusion of moved keyframes, the
    /// new keyframe's fusion, then its store commit. Times go to `/metrics`.
    fn run_map_job(&self, job: MapJob) {
        let Some(map) = &self.map else { return };
        let fused = fuse::apply(map, &job);
        // The fleet's fused map gets the same keyframe, moves and retractions.
        if let Some(fleets) = &self.fleets
            && (fused.is_some() || !job.retractions.is_empty())
        {
            let keyframe = job.keyframe.as_ref().filter(|_| fused.is_some()).and_then(|k| {
                let input = lock(map).builder.input_of(k.id).cloned()?;
                Some((k.id, k.capture_time_ns, job.world_from_camera, input))
            });
            fleets.submit_map(crate::fleet_map::FleetMapJob {
                fleet: self.fleet_name.clone(),
                session_id: self.id.clone(),
                camera: crate::convert::camera_of(&self.camera),
                keyframe,
                keyframe_poses: job.keyframe_poses.clone(),
                retractions: job.retractions.clone(),
            });
        }
        if let Some(spent) = fused {
            self.metrics.keyframe_fused();
            self.metrics.stage(stage::MAP_FUSE, micros(spent));
            let keep = self.map_lane.as_ref().map_or(0, |l| l.keyframe_images);
            if keep > 0
                && let Some(image) = job.keyframe.as_ref().and_then(fuse::keyframe_image)
            {
                lock(map).keep_image(image, keep);
            }
            let record = job.keyframe.and_then(|k| k.record);
            if let (Some(fleets), Some(keyframe)) = (&self.fleets, &record) {
                fleets.submit(crate::fleet::FleetJob {
                    fleet: self.fleet_name.clone(),
                    session_id: self.id.clone(),
                    robot_id: self.robot_id.clone(),
                    camera: crate::convert::camera_of(&self.camera),
                    keyframe: keyframe.clone(),
                });
            }
            self.persist(map, record);
        }
    }

    /// Commits to the store; the time goes to `/metrics` as the `store_commit` stage.
    fn persist(&self, map: &SharedMap, keyframe: Option<crate::store::KeyframeRecord>) {
        let start = Instant::now();
        // Lock order: tracking, then map (nothing takes them the other way round).
        let mut track = self.tracking();
        let outcome = self.commit(&mut track, &mut lock(map), keyframe);
        drop(track);
        match outcome {
            Ok(true) => self.metrics.stage(stage::STORE_COMMIT, micros(start.elapsed())),
            Ok(false) => {}
            Err(e) => tracing::error!(session = %self.id, "cannot commit to the store (the map stays in memory): {e}"),
        }
    }

    /// Commits the poses and map changes since the last commit (`SessionMap::persist`),
    /// then leaves the oldest committed poses out of memory
    /// (`session.trajectory_in_memory`). Call it holding both locks.
    fn commit(
        &self,
        track: &mut TrackState,
        m: &mut crate::map::SessionMap,
        keyframe: Option<crate::store::KeyframeRecord>,
    ) -> Result<bool, StoreError> {
        let outcome = m.persist(&track.trajectory, track.earlier, keyframe);
        track.trim(m.committed_poses(), self.trajectory_in_memory);
        outcome
    }

    /// Commits what is not committed yet (the poses after the last keyframe, what
    /// a failed commit held); nothing when all is committed. Returns whether it
    /// committed. The periodic flush calls it (`store.flush_interval_s`).
    pub fn flush(&self) -> bool {
        let Some(map) = self.map.as_ref().filter(|_| !self.archived) else { return false };
        // Lock order: tracking, then map (as the map lane).
        let mut track = self.tracking();
        let mut m = lock(map);
        if !m.uncommitted(track.len()) {
            return false;
        }
        match self.commit(&mut track, &mut m, None) {
            Ok(committed) => committed,
            Err(e) => {
                tracing::debug!(session = %self.id, "flush not committed: {e}");
                false
            }
        }
    }

    /// Shutdown, after the pools have stopped: commits the poses after the last keyframe.
    fn finish(&self) {
        if let Some(map) = &self.map
            && !self.archived
        {
            self.persist(map, None);
        }
        tracing::debug!(session = %self.id, "session finished");
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

/// What the session list and the dashboard show of a session, in memory or not.
#[derive(Debug, Clone)]
pub struct SessionInfo {
    pub summary: pb::SessionSummary,
    /// Read-only: restored from the store, or evicted from memory (a robot resuming
    /// it gets a new session).
    pub archived: bool,
    /// In memory now (a query on its map or trajectory brings it back when not).
    pub resident: bool,
    pub fleet: String,
    pub bytes_received: u64,
    pub last_received_sequence: Option<u64>,
    pub latest: Option<pb::PoseStamped>,
}

impl SessionInfo {
    /// A stored session's, from what the store keeps of it (not in memory).
    fn stored(head: &crate::store::SessionHead, fleet: String) -> Self {
        let state = head.latest.map_or(TrackingState::Initializing, |p| p.tracking_state());
        Self {
            summary: pb::SessionSummary {
                session_id: head.id.clone(),
                robot_id: head.meta.robot_id.clone(),
                transport: Transport::stored(&head.meta.transport).label().into(),
                connected: false,
                camera: Some(head.camera.clone()),
                frames_processed: head.pose_count as u64,
                tracking_state: state as i32,
                started_unix_ns: head.meta.started_unix_ns,
                ..Default::default()
            },
            archived: true,
            resident: false,
            fleet,
            bytes_received: 0,
            last_received_sequence: head.latest.map(|p| p.sequence),
            latest: head.latest,
        }
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
    /// A resume without the session's resume secret (UNAUTHENTICATED).
    #[error("{0}")]
    Unauthenticated(String),
    /// The hello asks for more than a limit allows (RESOURCE_EXHAUSTED, naming it).
    #[error("{0}")]
    TooLarge(String),
    /// The sessions in memory are at a `limits.*` bound and none is idle enough to
    /// leave (RESOURCE_EXHAUSTED, naming the limit).
    #[error("server full: {message}")]
    Limit { limit: &'static str, message: String },
    /// The server could not start the session (INTERNAL).
    #[error("{0}")]
    Internal(String),
    /// Not now: try again (UNAVAILABLE), e.g. another server is resuming the session.
    #[error("{0}")]
    Unavailable(String),
}

/// Checks a hello that opens a new session, before anything is allocated for
/// it: the robot id, the camera (sizes, intrinsics, encodings), its pixels
/// against `max_camera_pixels`, and the fleet name. Returns the camera. Pure,
/// so the fuzz target `hello` drives it.
pub fn validate_new_hello(hello: &pb::Hello, max_camera_pixels: u64) -> Result<&pb::CameraInfo, BadHello> {
    stillmap_proto::validate_robot_id(&hello.robot_id).map_err(BadHello::Invalid)?;
    let camera = validate_camera(hello.camera.as_ref()).map_err(BadHello::Invalid)?;
    let pixels = u64::from(camera.width) * u64::from(camera.height);
    if pixels > max_camera_pixels {
        return Err(BadHello::TooLarge(format!(
            "camera of {}x{} = {pixels} pixels is over session.max_camera_pixels = {max_camera_pixels}",
            camera.width, camera.height
        )));
    }
    if !hello.fleet.is_empty() {
        stillmap_proto::validate_fleet(&hello.fleet).map_err(BadHello::Invalid)?;
    }
    Ok(camera)
}

impl BadHello {
    /// The gRPC status this refusal is answered with (gRPC, and Zenoh's `ServerMessage.error`).
    pub fn status(&self) -> tonic::Status {
        let code = match self {
            Self::Invalid(_) => tonic::Code::InvalidArgument,
            Self::Full { .. } | Self::TooLarge(_) | Self::Limit { .. } => tonic::Code::ResourceExhausted,
            Self::Internal(_) => tonic::Code::Internal,
            Self::Unauthenticated(_) => tonic::Code::Unauthenticated,
            Self::Unavailable(_) => tonic::Code::Unavailable,
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
    /// Fleets and place recognition (`None`: `fleet.enabled` is off).
    fleets: Option<Arc<crate::fleet::FleetService>>,
    /// The fleet maps' top-down views (tiles and legends), kept between requests.
    fleet_tops: crate::api::map_queries::FleetTops,
    /// The sessions in memory.
    sessions: RwLock<HashMap<String, Arc<Session>>>,
    /// The sessions out of memory (stored, or evicted): what the list shows of
    /// them; the store holds the rest, and [`get`](Self::get) brings them back.
    dormant: RwLock<HashMap<String, SessionInfo>>,
    limits: LimitsConfig,
    /// Held while a stored session is brought back into memory (one at a time,
    /// so two queries for it load it once). Taken before `admission`, never after.
    loading: Mutex<()>,
    /// The worker pools every live session's work runs on.
    pools: Pools,
    next_id: AtomicU64,
    /// Held through `open` and every eviction, so concurrent hellos see each other
    /// when the limits are checked and a resume never races an eviction.
    admission: Mutex<()>,
    /// Whether a server id is another live server of the cluster (set on Zenoh):
    /// its sessions are not resumed from the shared storage here.
    live_elsewhere: RwLock<Option<LiveElsewhere>>,
    /// Sessions whose resume waits for their live writer to hand them over, and
    /// since when (at most [`MAX_HANDOVER_WAITS`]).
    handover_waits: Mutex<HashMap<String, Instant>>,
    /// Told a few seconds after this server handed a session over, so that its
    /// stored copy leaves the listing once the new owner has taken it.
    handed_over: tokio::sync::Notify,
    /// Distinguishes session ids of different server runs, and of servers started
    /// in the same second: the start time (seconds, hex) and 32 random bits.
    epoch: String,
}

/// What differs between a live session and one restored from the store.
struct SessionParts {
    id: String,
    robot_id: String,
    fleet_name: String,
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
    /// What a resume must present (empty for a restored session: it cannot be resumed).
    resume_secret: String,
    resume_anchor: Option<crate::pipeline::track::ResumeAnchor>,
}

/// Whether a server id is another live server.
pub type LiveElsewhere = Arc<dyn Fn(&str) -> bool + Send + Sync>;

/// A session resumed from the shared storage is found again among this many of its
/// newest stored keyframes.
const RESUME_KEYFRAMES: usize = 8;
/// A session read from the shared storage: it, whether it must be copied into
/// this server's store, and its frame in its fleet and its share of the fleet's
/// pose graph there.
type FromReplica = (StoredSession, bool, Option<crate::store::FleetFrame>, Option<Box<crate::store::SessionGraph>>);

/// Sessions whose resume may wait for a handover at once (a bound on the map
/// the hellos fill); beyond it a resume does not wait.
const MAX_HANDOVER_WAITS: usize = 4096;

/// The result of a hello.
pub struct Opened {
    pub session: Arc<Session>,
    pub resumed: bool,
    /// Resumed from the shared storage (its server left).
    pub restored: bool,
}

impl Registry {
    pub fn new(
        config: SessionConfig,
        tracking: TrackerConfig,
        perception: Option<(PerceptionConfig, Option<Arc<SegmentationService>>)>,
        mapping: MappingConfig,
        store: Option<Arc<Store>>,
        metrics: Arc<Metrics>,
        pools: Pools,
    ) -> Self {
        let started = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs());
        let mut salt = [0u8; 4];
        if let Err(e) = getrandom::fill(&mut salt) {
            // The start time alone still tells this run from earlier ones.
            tracing::warn!("no random bits for session ids ({e}): servers started in the same second may give the same id");
        }
        let epoch = format!("{started:x}{:08x}", u32::from_le_bytes(salt));
        Self {
            config,
            tracking,
            perception,
            mapping,
            store,
            metrics,
            fleet: broadcast::channel(FLEET_POSE_BUFFER).0,
            fleets: None,
            fleet_tops: Default::default(),
            pools,
            sessions: RwLock::default(),
            dormant: RwLock::default(),
            limits: LimitsConfig::default(),
            loading: Mutex::new(()),
            next_id: AtomicU64::new(1),
            admission: Mutex::new(()),
            live_elsewhere: RwLock::new(None),
            handover_waits: Mutex::default(),
            handed_over: tokio::sync::Notify::new(),
            epoch,
        }
    }

    /// The registry under `limits` (before any session opens).
    pub fn with_limits(self, limits: LimitsConfig) -> Self {
        Self { limits, ..self }
    }

    /// The registry with fleets and place recognition (before any session opens).
    pub fn with_fleets(self, fleets: Option<Arc<crate::fleet::FleetService>>) -> Self {
        Self { fleets, ..self }
    }

    /// Fleets and place recognition (`None`: off).
    pub fn fleets(&self) -> Option<&Arc<crate::fleet::FleetService>> {
        self.fleets.as_ref()
    }

    /// The fleet maps' top-down views.
    pub fn fleet_tops(&self) -> &crate::api::map_queries::FleetTops {
        &self.fleet_tops
    }

    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.metrics
    }

    /// Every session's poses as they are estimated.
    pub fn subscribe_fleet(&self) -> broadcast::Receiver<FleetPose> {
        self.fleet.subscribe()
    }

    /// [`get`](Self::get) for async code: off the runtime, as a stored session is
    /// read back from the store (its map and trajectory), which would hold one of
    /// the runtime's few threads, and every request or stream on it, meanwhile.
    pub async fn get_off_runtime(self: &Arc<Self>, id: &str) -> Option<Arc<Session>> {
        let (registry, id) = (self.clone(), id.to_string());
        match tokio::task::spawn_blocking(move || registry.get(&id)).await {
            Ok(found) => found,
            Err(e) => {
                tracing::error!("looking a session up failed (a server bug): {e}");
                None
            }
        }
    }

    /// The session `id`, brought back from the store when it is not in memory
    /// (read-only; counted in `stillmap_sessions_loaded_total`). A use: it resets
    /// the session's idle time.
    pub fn get(&self, id: &str) -> Option<Arc<Session>> {
        if let Some(s) = self.resident(id) {
            s.touch();
            return Some(s);
        }
        if !read(&self.dormant).contains_key(id) {
            return None;
        }
        let _loading = lock(&self.loading);
        if let Some(s) = self.resident(id) {
            s.touch();
            return Some(s);
        }
        let store = self.store.as_ref()?;
        // Its newest keyframe only: the map's eviction starts around its camera.
        let stored = match store.load_with(id, 1) {
            Ok(Some(stored)) => stored,
            Ok(None) => {
                tracing::error!(session = id, "listed as stored, but the store does not hold it");
                return None;
            }
            Err(e) => {
                tracing::error!(session = id, "cannot bring the stored session back: {e}");
                return None;
            }
        };
        self.admit_loaded(id, stored)
    }

    /// Puts session `id`, just read from the store for a query, into memory
    /// (read-only), unless it left the listing meanwhile.
    fn admit_loaded(&self, id: &str, stored: StoredSession) -> Option<Arc<Session>> {
        let session = self.archived_session(stored);
        {
            // Listed still, or the load is dropped: while it read the store, a
            // resume may have made the session live (that one answers), or the
            // session may have been left out as moved on to another server (a
            // query then goes there, never to this older copy). Locks: dormant,
            // then sessions.
            let mut dormant = write(&self.dormant);
            if dormant.remove(id).is_none() {
                drop(dormant);
                return self.resident(id);
            }
            let mut sessions = write(&self.sessions);
            if let Some(live) = sessions.get(id) {
                return Some(live.clone());
            }
            sessions.insert(id.to_string(), session.clone());
        }
        self.metrics.session_loaded();
        self.metrics.resident_delta(1);
        tracing::info!(session = id, "stored session brought back into memory for a query");
        // Over limits.max_sessions: an idle session makes room (this one stays).
        let _admission = lock(&self.admission);
        if let Err(e) = self.make_room(None, 0, 0, Some(id)) {
            tracing::debug!(session = id, "loaded beyond the limit for now: {e}");
        }
        Some(session)
    }

    /// The session `id` if it is in memory (nothing is loaded).
    pub fn resident(&self, id: &str) -> Option<Arc<Session>> {
        read(&self.sessions).get(id).cloned()
    }

    /// The sessions in memory, oldest first.
    pub fn list(&self) -> Vec<Arc<Session>> {
        let mut all: Vec<_> = read(&self.sessions).values().cloned().collect();
        all.sort_by_key(|s| (s.started_unix_ns, s.id.clone()));
        all
    }

    /// What the list shows of the sessions out of memory, oldest first.
    pub fn dormant(&self) -> Vec<SessionInfo> {
        let mut all: Vec<_> = read(&self.dormant).values().cloned().collect();
        all.sort_by_key(|s| (s.summary.started_unix_ns, s.summary.session_id.clone()));
        all
    }

    /// Every session, in memory or not, oldest first (nothing is loaded).
    pub fn list_info(&self) -> Vec<SessionInfo> {
        // Both read at once (locks: dormant, then sessions, as every writer that
        // moves a session between them): one moving in or out of memory meanwhile
        // is in one of them, never in neither.
        let (resident, dormant): (Vec<Arc<Session>>, Vec<SessionInfo>) = {
            let dormant = read(&self.dormant);
            let sessions = read(&self.sessions);
            (sessions.values().cloned().collect(), dormant.values().cloned().collect())
        };
        let mut all: Vec<SessionInfo> = resident.iter().map(|s| s.info()).collect();
        let resident: std::collections::HashSet<String> = all.iter().map(|s| s.summary.session_id.clone()).collect();
        all.extend(dormant.into_iter().filter(|d| !resident.contains(&d.summary.session_id)));
        all.sort_by_key(|s| (s.summary.started_unix_ns, s.summary.session_id.clone()));
        all
    }

    /// A page of the sessions list (oldest first, as [`list_info`](Self::list_info)):
    /// at most `limit` sessions after `after`, and where the next page starts when
    /// more follow.
    pub fn list_page(&self, after: Option<&ListCursor>, limit: usize) -> (Vec<SessionInfo>, Option<ListCursor>) {
        let mut all = self.list_info();
        if let Some(after) = after {
            all.retain(|s| &ListCursor::of(&s.summary) > after);
        }
        let next = (all.len() > limit).then(|| ListCursor::of(&all[limit - 1].summary));
        all.truncate(limit);
        (all, next)
    }

    /// What the list shows of session `id` (nothing is loaded).
    pub fn info(&self, id: &str) -> Option<SessionInfo> {
        match self.resident(id) {
            Some(s) => Some(s.info()),
            None => read(&self.dormant).get(id).cloned(),
        }
    }

    /// Takes `s` out of memory if nothing would be lost: a live session must be
    /// disconnected, answered, without map work, and committed (what is left is
    /// committed first); its queue is closed, so a robot still sending to it is
    /// told to open a new session. Call it holding `admission`. True when it left.
    fn try_evict(&self, s: &Arc<Session>) -> bool {
        if !s.archived {
            if !s.idle_parts() {
                return false;
            }
            s.flush();
            if !s.at_rest() {
                return false;
            }
            s.queue.close();
            // A frame that slipped in before the close: the next sweep takes it.
            if !s.at_rest() {
                return false;
            }
        }
        let mut info = s.info();
        info.archived = true;
        info.resident = false;
        info.summary.connected = false;
        {
            // Out of memory and listed as stored at once (locks: dormant, then sessions).
            let mut dormant = write(&self.dormant);
            if write(&self.sessions).remove(&s.id).is_none() {
                return false;
            }
            dormant.insert(s.id.clone(), info);
        }
        if let Some(replica) = self.store.as_ref().and_then(|store| store.replica()) {
            replica.forget(&s.id);
        }
        self.metrics.session_evicted();
        self.metrics.resident_delta(-1);
        tracing::info!(session = %s.id, idle_s = s.idle_for().as_secs_f64(), "session left memory (the store keeps it)");
        true
    }

    /// Evicts sessions idle for `session.idle_evict_s` (see `try_evict`);
    /// returns how many left. The server calls it periodically, off the runtime.
    pub fn evict_idle(&self) -> usize {
        if self.config.idle_evict_s <= 0.0 {
            return 0;
        }
        let idle = std::time::Duration::from_secs_f64(self.config.idle_evict_s);
        let mut evicted = 0;
        for s in self.list().iter().filter(|s| s.idle_for() >= idle) {
            let _admission = lock(&self.admission);
            evicted += usize::from(self.try_evict(s));
        }
        evicted
    }

    /// Makes room for `new` more sessions (of `robot`, with `pixels` camera pixels)
    /// under the `limits`, evicting the longest-idle sessions that can leave
    /// (never `keep`). Call it holding `admission`.
    fn make_room(&self, robot: Option<&str>, new: usize, pixels: u64, keep: Option<&str>) -> Result<(), BadHello> {
        let l = &self.limits;
        loop {
            let resident = self.list();
            let live = || resident.iter().filter(|s| !s.archived);
            let (limit, mut candidates, message) = if resident.len() + new > l.max_sessions {
                (
                    "max_sessions",
                    resident.clone(),
                    format!("{} sessions in memory, limits.max_sessions = {}", resident.len(), l.max_sessions),
                )
            } else if let Some(robot) = robot.filter(|r| live().filter(|s| s.robot_id == *r).count() + new > l.max_sessions_per_robot) {
                let mine: Vec<_> = live().filter(|s| s.robot_id == robot).cloned().collect();
                let message = format!(
                    "robot {robot:?} has {} sessions in memory, limits.max_sessions_per_robot = {}",
                    mine.len(),
                    l.max_sessions_per_robot
                );
                ("max_sessions_per_robot", mine, message)
            } else {
                let used: u64 = live().map(|s| u64::from(s.camera.width) * u64::from(s.camera.height)).sum();
                if used + pixels <= l.max_camera_pixels_total {
                    return Ok(());
                }
                let message = format!(
                    "{used} camera pixels in memory + {pixels} asked, limits.max_camera_pixels_total = {}",
                    l.max_camera_pixels_total
                );
                ("max_camera_pixels_total", live().cloned().collect(), message)
            };
            // Stored sessions a query brought back go first, then the longest idle.
            candidates.retain(|s| keep != Some(s.id.as_str()));
            candidates.sort_by_key(|s| (!s.archived, std::cmp::Reverse(s.idle_for())));
            if !candidates.iter().any(|s| self.try_evict(s)) {
                return Err(BadHello::Limit { limit, message: format!("{message}, and none is idle enough to leave") });
            }
        }
    }

    /// Opens a session for `hello`, or resumes the one it names, and attaches `sink`.
    pub fn open(&self, hello: &pb::Hello, transport: Transport, sink: ResultSink) -> Result<Opened, BadHello> {
        stillmap_proto::validate_robot_id(&hello.robot_id).map_err(BadHello::Invalid)?;
        // Another server's session (it left the cluster), read from the shared
        // storage before the admission lock: a slow read holds no other hello.
        let from_replica = self.read_from_replica(hello, transport)?;
        let _admission = lock(&self.admission);
        if !hello.resume_session_id.is_empty()
            && let Some(session) = self.resident(&hello.resume_session_id).filter(|s| !s.archived && !s.queue.is_closed())
        {
            if session.robot_id != hello.robot_id {
                return Err(BadHello::Invalid(format!(
                    "session {} belongs to robot {:?}, not {:?}",
                    session.id, session.robot_id, hello.robot_id
                )));
            }
            session.check_resume_secret(&hello.resume_secret)?;
            if !session.is_connected() {
                self.check_capacity()?;
            }
            session.attach(sink);
            return Ok(Opened { session, resumed: true, restored: false });
        }
        if let Some((stored, copy, fleet_frame, fleet_graph)) = from_replica
            && self.resident(&stored.id).is_none()
        {
            // A refusal keeps the claim in the shared storage: the robot tries this
            // server again (a release, queued behind commits, could undo the claim
            // of that retry and let a second server write the session); resuming
            // elsewhere, it waits `session.handover_wait_s`, then gets a new session.
            if let Some(opened) = self.resume_stored(stored, copy, (fleet_frame, fleet_graph), hello, transport, sink.clone())? {
                return Ok(opened);
            }
        }
        let camera = validate_new_hello(hello, self.config.max_camera_pixels)?.clone();
        let pixels = u64::from(camera.width) * u64::from(camera.height);
        let fleet_name = self.fleet_for(&hello.fleet);
        if let Some(fleets) = &self.fleets
            && let Err((held, max)) = fleets.admits(&fleet_name)
        {
            self.metrics.session_refused("max_fleets");
            return Err(BadHello::Limit {
                limit: "max_fleets",
                message: format!("hello names a new fleet {fleet_name:?}; the server holds {held} fleets, fleet.max_fleets = {max}"),
            });
        }
        self.check_capacity()?;
        if let Err(e) = self.make_room(Some(&hello.robot_id), 1, pixels, None) {
            if let BadHello::Limit { limit, .. } = &e {
                self.metrics.session_refused(limit);
            }
            return Err(e);
        }
        // An imported map may hold the id this run would give next: skip it.
        let id = loop {
            let n = self.next_id.fetch_add(1, Ordering::Relaxed);
            let id = format!("{}-{}-{n}", hello.robot_id, self.epoch);
            if !self.taken(&id) {
                break id;
            }
        };
        let started_unix_ns = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64);
        let resume_secret =
            crate::auth::new_secret().map_err(|e| BadHello::Internal(format!("cannot make the session's resume secret: {e}")))?;
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
                fleet: fleet_name.clone(),
            };
            let map = SessionMap::new(&camera, self.mapping.clone(), names)
                .map_err(|e| tracing::error!(session = %id, "mapping unavailable for this session: {e}"))
                .ok();
            if let (Some(map), Some(store)) = (&map, &self.store) {
                match store.put_session(&id, &meta, &camera, &resume_secret) {
                    Ok(()) => lock(map).attach_store(store.clone(), &id, meta),
                    Err(e) => {
                        tracing::error!(session = %id, "session not recorded yet (the store failed; its first commit that goes through records it): {e}");
                        lock(map).attach_store_unrecorded(store.clone(), &id, meta, camera.clone());
                    }
                }
            }
            map
        } else {
            None
        };
        if let Some(f) = &self.fleets {
            f.join(&fleet_name, &id, &hello.robot_id);
        }
        let session = Arc::new_cyclic(|me| {
            self.session(
                me,
                SessionParts {
                    id: id.clone(),
                    robot_id: hello.robot_id.clone(),
                    fleet_name,
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
                    resume_secret,
                    resume_anchor: None,
                },
            )
        });
        session.attach(sink);
        write(&self.sessions).insert(id, session.clone());
        self.metrics.session_opened();
        self.metrics.resident_delta(1);
        tracing::info!(session = %session.id, robot = %session.robot_id, transport = transport.label(), "session opened");
        Ok(Opened { session, resumed: false, restored: false })
    }

    /// Refuses a new connection when `session.max_connected` robots stream already
    /// (under the admission lock, so racing hellos cannot pass together).
    fn check_capacity(&self) -> Result<(), BadHello> {
        let limit = self.config.max_connected;
        if limit == 0 {
            return Ok(());
        }
        let connected = read(&self.sessions).values().filter(|s| s.is_connected()).count();
        if connected >= limit {
            self.metrics.session_refused("max_connected");
            return Err(BadHello::Full { connected, limit });
        }
        Ok(())
    }

    /// Whether opening `hello` may read the shared storage (it resumes a session
    /// this server does not hold, and there is a replica): the shells run such an
    /// open off their loop, since it waits on PostgreSQL.
    pub fn reads_replica(&self, hello: &pb::Hello) -> bool {
        !hello.resume_session_id.is_empty()
            && self.store.as_ref().is_some_and(|s| s.replica().is_some())
            && self.resident(&hello.resume_session_id).is_none()
    }

    /// Tells the registry which servers are live besides this one (the cluster's
    /// membership): a session last written by one of them is not resumed here.
    pub fn set_live_elsewhere(&self, live: LiveElsewhere) {
        *write(&self.live_elsewhere) = Some(live);
    }

    /// Lists the stored sessions (read-only: queries answer, and bring a session
    /// into memory when they need its map or trajectory; robots resuming one get a
    /// new session). Nothing is loaded here.
    pub fn restore(&self, heads: &[SessionHead]) {
        let mut dormant = write(&self.dormant);
        for head in heads {
            dormant.insert(head.id.clone(), SessionInfo::stored(head, self.fleet_for(&head.meta.fleet)));
        }
    }

    /// The ids of the stored sessions that are not live here: out of memory, or
    /// brought back read-only for a query.
    pub fn stored_ids(&self) -> Vec<String> {
        let mut ids: Vec<String> = read(&self.dormant).keys().cloned().collect();
        ids.extend(read(&self.sessions).values().filter(|s| s.archived).map(|s| s.id.clone()));
        ids
    }

    /// Leaves out of this server's listing the stored sessions that `holder_of` says
    /// another server holds now (a session that moved on while this server was away:
    /// this copy is older), so that queries about them go to that server; a copy a
    /// query brought into memory leaves memory too. Returns the ids left out.
    pub fn leave_moved(&self, holder_of: impl Fn(&str) -> Option<String>) -> Vec<String> {
        let mut dormant = write(&self.dormant);
        let mut sessions = write(&self.sessions);
        let stored = dormant.keys().cloned().chain(sessions.values().filter(|s| s.archived).map(|s| s.id.clone()));
        let moved: Vec<(String, String)> = stored.filter_map(|id| holder_of(&id).map(|h| (id, h))).collect();
        for (id, holder) in &moved {
            dormant.remove(id);
            if sessions.get(id).is_some_and(|s| s.archived) && sessions.remove(id).is_some() {
                self.metrics.resident_delta(-1);
            }
            tracing::info!(session = %id, holder = %holder, "stored here, but it went on on another server: queries about it go there");
        }
        moved.into_iter().map(|(id, _)| id).collect()
    }

    /// The fleet a session of fleet `named` belongs to (the default one for none).
    fn fleet_for(&self, named: &str) -> String {
        match &self.fleets {
            Some(f) => f.fleet_for(named),
            None => named.to_string(),
        }
    }

    /// Whether a resume of session `id`, which a live server still writes, should
    /// wait for that server's handover: for `session.handover_wait_s` from the
    /// first such hello.
    fn awaits_handover(&self, id: &str) -> bool {
        let wait = std::time::Duration::from_secs_f64(self.config.handover_wait_s);
        let mut waits = lock(&self.handover_waits);
        waits.retain(|_, since| since.elapsed() < wait * 2);
        if waits.len() >= MAX_HANDOVER_WAITS && !waits.contains_key(id) {
            return false;
        }
        waits.entry(id.to_string()).or_insert_with(Instant::now).elapsed() < wait
    }

    /// Hands live session `id` over to the server its robot was placed on (a server
    /// joined): once its robot is gone, its frames answered and everything
    /// committed, it leaves memory (as an idle session does) and the shared storage
    /// names no writer for it, so the new owner resumes it. Tries for up to
    /// `session.handover_wait_s`; gives up when the robot comes back. Blocks: call
    /// it off the runtime. True when it was handed over.
    pub fn hand_over(&self, id: &str) -> bool {
        let Some(replica) = self.store.as_ref().and_then(|s| s.replica()).filter(|_| self.config.handover_wait_s > 0.0) else {
            return false;
        };
        let Some(s) = self.resident(id).filter(|s| !s.archived) else { return false };
        let until = Instant::now() + std::time::Duration::from_secs_f64(self.config.handover_wait_s);
        loop {
            if s.is_connected() {
                return false;
            }
            let left = {
                let _admission = lock(&self.admission);
                self.try_evict(&s)
            };
            if left {
                let released = replica.release(id);
                if released {
                    self.metrics.session_handed_over();
                    tracing::info!(session = id, "session handed over to the server its robot was placed on");
                }
                return released;
            }
            if Instant::now() >= until {
                tracing::warn!(session = id, "session not handed over within session.handover_wait_s (frames or commits still pending)");
                return false;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
    }

    /// Told a few seconds after each handover (see [`hand_over`](Self::hand_over)).
    pub fn handed_over(&self) -> &tokio::sync::Notify {
        &self.handed_over
    }

    /// The session a hello resumes, from the shared storage, when this server does
    /// not hold it and no live server does (that one would go on writing it): its
    /// description, trajectory and map as the storage holds them (its last committed
    /// keyframe), or this server's own stored copy when that is at least as long
    /// (true: it must be copied into this server's store). `None`: no such session
    /// there (or the storage cannot be read: logged), so the robot gets a new one.
    /// The session of a Zenoh robot, or of a gRPC robot that follows placement,
    /// that a live server still writes is waited for (`UNAVAILABLE`) while that
    /// server may hand it over.
    fn read_from_replica(&self, hello: &pb::Hello, transport: Transport) -> Result<Option<FromReplica>, BadHello> {
        let id = hello.resume_session_id.as_str();
        let Some(replica) = self.store.as_ref().and_then(|s| s.replica()).filter(|_| self.reads_replica(hello)) else {
            return Ok(None);
        };
        let ((s, fleet_frame, fleet_graph), writer) = match replica.load(id, &hello.robot_id, &hello.resume_secret, RESUME_KEYFRAMES) {
            Ok(crate::replica::ReplicaSession::Found { session, server_id, fleet_frame, fleet_graph }) => {
                ((*session, fleet_frame, fleet_graph), server_id)
            }
            Ok(crate::replica::ReplicaSession::Absent) => return Ok(None),
            Ok(crate::replica::ReplicaSession::Refused(why)) => return Err(BadHello::Unauthenticated(why)),
            Err(e) => {
                tracing::warn!(session = id, "cannot resume from the shared storage (a new session instead): {e}");
                return Ok(None);
            }
        };
        if read(&self.live_elsewhere).as_ref().is_some_and(|live| live(&writer)) {
            // A server joined and took this robot from `writer`, which hands the
            // session over once its last frames are answered and committed: a Zenoh
            // robot, or a gRPC robot that follows placement (`Ingest.Place`). Other
            // gRPC robots move only when their stream breaks: not handed over.
            if (transport == Transport::Zenoh || hello.follows_placement) && self.awaits_handover(id) {
                return Err(BadHello::Unavailable(format!(
                    "session {id} is still on server {writer}, which hands it over to this one: say hello again"
                )));
            }
            tracing::warn!(session = id, server = %writer, "the session's server is still live and did not hand it over: a new session instead");
            return Ok(None);
        }
        lock(&self.handover_waits).remove(id);
        // Taken over in PostgreSQL first: one server wins a race to resume it.
        match replica.claim(id, &writer) {
            Ok(true) => {}
            Ok(false) => return Err(BadHello::Unavailable(format!("session {id} is being resumed by another server: try again"))),
            Err(e) => {
                tracing::error!(session = id, "cannot take the session over in the shared storage: {e}");
                return Err(BadHello::Unavailable(format!("session {id} cannot be taken over now (the shared storage): try again")));
            }
        }
        if let Some(store) = &self.store
            && let Ok(Some(mut local)) = store.load_with(id, RESUME_KEYFRAMES)
            && local.poses.len() >= s.poses.len()
        {
            // After every place the shared storage holds too (another server may
            // have written beyond this copy where a copy of this one's was dropped).
            local.next_pose_place = local.next_pose_place.max(s.next_pose_place);
            return Ok(Some((local, false, fleet_frame, fleet_graph)));
        }
        Ok(Some((s, true, fleet_frame, fleet_graph)))
    }

    /// A session another server held, live on this one: copied into this server's
    /// store (`copy`), its map and trajectory restored, and a new tracker that
    /// reports nothing until it finds itself among the session's newest stored
    /// keyframes. `None`: it cannot be found again (a new session instead).
    fn resume_stored(
        &self,
        mut s: StoredSession,
        copy: bool,
        (fleet_frame, fleet_graph): (Option<crate::store::FleetFrame>, Option<Box<crate::store::SessionGraph>>),
        hello: &pb::Hello,
        transport: Transport,
        sink: ResultSink,
    ) -> Result<Option<Opened>, BadHello> {
        let id = s.id.clone();
        let id = id.as_str();
        // Found again among its keyframes; without any, only a session with no pose
        // yet goes on (its world is the first camera's, as a new tracker's); one with
        // poses cannot be found again: a new session.
        if s.keyframes.is_empty() && !s.poses.is_empty() {
            tracing::warn!(session = id, "stored without keyframes: it cannot be found again; a new session instead");
            return Ok(None);
        }
        // The camera is the session's own (checked as a new hello's would be).
        let resumed_hello = pb::Hello { camera: Some(s.camera.clone()), ..hello.clone() };
        let camera = validate_new_hello(&resumed_hello, self.config.max_camera_pixels)?.clone();
        self.check_capacity()?;
        let pixels = u64::from(camera.width) * u64::from(camera.height);
        if let Err(e) = self.make_room(Some(&hello.robot_id), 1, pixels, None) {
            if let BadHello::Limit { limit, .. } = &e {
                self.metrics.session_refused(limit);
            }
            return Err(e);
        }
        let fleet_name = self.fleet_for(&s.meta.fleet);
        if let Some(fleets) = &self.fleets
            && let Err((held, max)) = fleets.admits(&fleet_name)
        {
            self.metrics.session_refused("max_fleets");
            return Err(BadHello::Limit {
                limit: "max_fleets",
                message: format!(
                    "the resumed session's fleet {fleet_name:?} is new here; the server holds {held} fleets, fleet.max_fleets = {max}"
                ),
            });
        }
        if let Some(store) = &self.store {
            // Its map and trajectory are taken as committed here (blocks evicted,
            // older poses out of memory): without the copy they would be lost.
            if copy && let Err(e) = store.import(&s) {
                tracing::error!(session = id, "the resumed session cannot be copied into this server's store: {e}");
                return Err(BadHello::Unavailable(format!(
                    "session {id} cannot be taken over now (this server's store failed: {e}): try again"
                )));
            }
            if let Some(replica) = store.replica() {
                replica.remember(id, crate::replica::secret_hash(&hello.resume_secret));
            }
        }
        let tracking_camera = crate::convert::camera_of(&camera);
        let next_keyframe_id = s.keyframes.iter().map(|k| k.id + 1).max().unwrap_or(0).max(s.meta.keyframes);
        let map = self.restored_map(&s);
        // The newest keyframes (all a resume read from the shared storage; of a
        // local copy, as many): the tracker finds itself among them, the fleet
        // indexes them at once, and the older ones follow in the background.
        let mut newest = std::mem::take(&mut s.keyframes);
        newest.sort_by_key(|k| k.id);
        let newest = newest.split_off(newest.len().saturating_sub(RESUME_KEYFRAMES));
        let oldest_read = newest.first().map(|k| k.id);
        let anchor = crate::pipeline::track::ResumeAnchor {
            keyframes: newest.iter().rev().map(|k| crate::fleet::place_of_record(&tracking_camera, k)).map(|(p, w)| (w, p)).collect(),
            verify: stillmap_places::VerifyConfig::default(),
            next_keyframe_id,
            find_within_s: self.config.resume_find_s,
        };
        if let Some(f) = &self.fleets {
            // Its share of the fleet's pose graph holds only in the frame it came with.
            if f.join_carried(&fleet_name, id, &hello.robot_id, fleet_frame)
                && let Some(graph) = fleet_graph
            {
                f.carry_graph(&fleet_name, id, *graph);
            }
            // Its map can be found by the fleet's robots here at once.
            let stored = crate::fleet::StoredKeyframes {
                fleet: fleet_name.clone(),
                session_id: id.to_string(),
                camera: tracking_camera.clone(),
                keyframes: newest,
            };
            f.index_stored(stored, false);
        }
        // The older ones after them (the fleet holds the session by now).
        self.backfill_keyframes(id, oldest_read, &fleet_name, &tracking_camera);
        let counters = Counters::default();
        counters.processed.store(s.poses.len() as u64, Ordering::Relaxed);
        let latest = s.poses.last().copied();
        let session = Arc::new_cyclic(|me| {
            self.session(
                me,
                SessionParts {
                    id: id.to_string(),
                    robot_id: hello.robot_id.clone(),
                    fleet_name,
                    transport,
                    camera,
                    started_unix_ns: s.meta.started_unix_ns,
                    counters,
                    queue: FrameQueue::new(self.config.queue_capacity, self.config.max_pending_drop_notices, self.config.overload_policy),
                    last_received_sequence: latest.map(|p| p.sequence),
                    track: TrackState { state: TrackingState::Lost, latest, trajectory: s.poses, ..Default::default() },
                    perception: self.perception.clone(),
                    map,
                    archived: false,
                    resume_secret: hello.resume_secret.clone(),
                    resume_anchor: (!anchor.keyframes.is_empty()).then_some(anchor),
                },
            )
        });
        session.attach(sink);
        {
            // Locks: dormant, then sessions (a listing sees it in one of them).
            let mut dormant = write(&self.dormant);
            write(&self.sessions).insert(id.to_string(), session.clone());
            dormant.remove(id);
        }
        self.metrics.session_opened();
        self.metrics.resident_delta(1);
        tracing::info!(session = id, robot = %session.robot_id, "session resumed from the shared storage");
        Ok(Some(Opened { session, resumed: true, restored: true }))
    }

    /// Has the shared storage read back, in the background, the keyframe records of
    /// resumed session `id` older than those the resume read (`oldest_read` the
    /// oldest of them): each page goes into
    /// this server's store (so a restart or an export here has them all) and into
    /// its fleet's place index here.
    fn backfill_keyframes(&self, id: &str, oldest_read: Option<u64>, fleet: &str, camera: &stillmap_tracking::Camera) {
        let Some(store) = self.store.clone() else { return };
        let Some(replica) = store.replica().cloned() else { return };
        let Some(before_id) = oldest_read.filter(|id| *id > 0) else { return };
        let (id, fleet, camera, fleets) = (id.to_string(), fleet.to_string(), camera.clone(), self.fleets.clone());
        let session_id = id.clone();
        replica.backfill(crate::replica::Backfill {
            session_id,
            before_id,
            page: Box::new(move |keyframes| {
                if let Err(e) = store.put_keyframes(&id, &keyframes) {
                    tracing::warn!(session = %id, "older keyframe records not kept in this server's store (no more are read back): {e}");
                    return false;
                }
                if let Some(f) = &fleets {
                    let stored =
                        crate::fleet::StoredKeyframes { fleet: fleet.clone(), session_id: id.clone(), camera: camera.clone(), keyframes };
                    f.index_stored(stored, true);
                }
                true
            }),
        });
    }

    /// A stored session's map in memory, attached to this server's store.
    fn restored_map(&self, s: &StoredSession) -> Option<SharedMap> {
        if !self.mapping.enabled {
            return None;
        }
        match SessionMap::new(&s.camera, self.mapping.clone(), s.meta.class_names.clone()) {
            Ok(map) => {
                {
                    let mut m = lock(&map);
                    if let Some(store) = &self.store {
                        m.attach_store(store.clone(), &s.id, s.meta.clone());
                    }
                    let last_camera = s
                        .keyframes
                        .last()
                        .map(|k| nalgebra::Point3::new(k.world_from_camera[0], k.world_from_camera[1], k.world_from_camera[2]));
                    m.restore(s.blocks.clone(), &s.meta, s.poses.len(), s.next_pose_place, last_camera);
                }
                Some(map)
            }
            Err(e) => {
                tracing::error!(session = %s.id, "stored map cannot be restored: {e}");
                None
            }
        }
    }

    /// A stored session in memory, read-only.
    fn archived_session(&self, s: StoredSession) -> Arc<Session> {
        let id = s.id.clone();
        let map = self.restored_map(&s);
        let transport = Transport::stored(&s.meta.transport);
        let counters = Counters::default();
        counters.processed.store(s.poses.len() as u64, Ordering::Relaxed);
        let latest = s.poses.last().copied();
        let state = latest.map_or(TrackingState::Initializing, |p| p.tracking_state());
        let queue = FrameQueue::new(1, 1, self.config.overload_policy);
        queue.close();
        let fleet_name = self.fleet_for(&s.meta.fleet);
        Arc::new_cyclic(|me| {
            self.session(
                me,
                SessionParts {
                    id,
                    robot_id: s.meta.robot_id.clone(),
                    fleet_name,
                    transport,
                    camera: s.camera,
                    started_unix_ns: s.meta.started_unix_ns,
                    counters,
                    queue,
                    last_received_sequence: latest.map(|p| p.sequence),
                    track: TrackState { state, latest, trajectory: s.poses, ..Default::default() },
                    perception: None,
                    map,
                    archived: true,
                    resume_secret: String::new(),
                    resume_anchor: None,
                },
            )
        })
    }

    pub fn store(&self) -> Option<&Arc<Store>> {
        self.store.as_ref()
    }

    /// Adds a session from a map file (see [`crate::store::export`]) to the store
    /// and to the registry, read-only.
    pub fn import(&self, stored: StoredSession) -> Result<String, ImportError> {
        let store = self.store.as_ref().ok_or(ImportError::NoStore)?;
        // Under the admission lock, so a hello cannot take the same id meanwhile.
        let _admission = lock(&self.admission);
        if self.info(&stored.id).is_some() || store.contains(&stored.id).map_err(ImportError::Store)? {
            return Err(ImportError::Exists(stored.id));
        }
        store.import(&stored).map_err(ImportError::Store)?;
        let mut head = SessionHead {
            id: stored.id.clone(),
            meta: stored.meta,
            camera: stored.camera,
            pose_count: stored.poses.len(),
            latest: stored.poses.last().copied(),
            keyframes: stored.keyframes,
        };
        // It joins its fleet as a restart would bring it back: the fleet's first
        // session anchors it (a robot then merges into the imported map), else it
        // is merged when a merged session's keyframe matches its own.
        if let Some(fleets) = &self.fleets {
            let fleet = fleets.fleet_for(&head.meta.fleet);
            match fleets.admits(&fleet) {
                Ok(()) => fleets.restore(std::slice::from_ref(&head)),
                Err((held, max)) => tracing::warn!(
                    session = %head.id,
                    "imported into no fleet: its fleet {fleet:?} is new here and the server holds {held} fleets (fleet.max_fleets = {max})"
                ),
            }
        }
        head.keyframes = Vec::new();
        self.restore(std::slice::from_ref(&head));
        Ok(head.id)
    }

    /// Whether a session `id` exists, live, restored or only in the store (a store
    /// that cannot be read counts it as free: committing to it fails anyway).
    fn taken(&self, id: &str) -> bool {
        self.info(id).is_some() || self.store.as_ref().is_some_and(|s| s.contains(id).unwrap_or(false))
    }

    /// A session from what differs between a live and a restored one.
    fn session(&self, me: &Weak<Session>, p: SessionParts) -> Session {
        let live = !p.archived;
        let map_lane = (live && p.map.is_some()).then(|| {
            Arc::new(MapLane {
                jobs: Mutex::default(),
                capacity: self.config.map_queue,
                keyframe_images: self.config.keyframe_images,
                scheduled: AtomicBool::new(false),
                session: me.clone(),
            })
        });
        Session {
            pools: live.then(|| self.pools.clone()),
            worker: Mutex::new(None),
            scheduled: AtomicBool::new(false),
            map_lane,
            parked: AtomicBool::new(false),
            runtime: tokio::runtime::Handle::try_current().ok(),
            touched: Mutex::new(Instant::now()),
            me: me.clone(),
            id: p.id,
            robot_id: p.robot_id,
            resume_secret: p.resume_secret,
            resume_anchor: Mutex::new(p.resume_anchor),
            fleet_name: p.fleet_name,
            fleets: if p.archived { None } else { self.fleets.clone() },
            transport: p.transport,
            camera: p.camera,
            started_unix_ns: p.started_unix_ns,
            counters: p.counters,
            connected: AtomicBool::new(false),
            queue: p.queue,
            sink: Mutex::new(None),
            ended: Mutex::new(None),
            last_received_sequence: Mutex::new(p.last_received_sequence),
            received_jumps: Mutex::default(),
            received_before_last: Mutex::new(None),
            cpu_budget: CpuBudget::new(&self.limits, self.metrics.clone()),
            track: Mutex::new({
                // A session read back from the store: its older poses stay there.
                let mut track = p.track;
                if let Some(map) = p.map.as_ref().filter(|_| p.archived) {
                    track.trim(lock(map).committed_poses(), self.config.trajectory_in_memory);
                }
                track
            }),
            trajectory_in_memory: self.config.trajectory_in_memory,
            poses: broadcast::channel(POSE_SUBSCRIBER_BUFFER).0,
            fleet: self.fleet.clone(),
            last_latency: Mutex::new(Vec::new()),
            answered_tx: watch::channel(0).0,
            metrics: self.metrics.clone(),
            tracker_config: self.tracking.clone(),
            order_window: crate::pipeline::decode::OrderWindow {
                max_sequence_jump: self.config.max_sequence_jump,
                max_capture_gap_ns: (self.config.max_capture_gap_s * 1e9) as u64,
            },
            perception: p.perception,
            map: p.map,
            archived: p.archived,
        }
    }

    /// Lets the pools finish every queued frame and map job, commits each session's
    /// last poses, then stops the segmentation workers (the sessions' last frames
    /// may still need them). Call it after [`close_all`](Self::close_all).
    pub fn join_workers(&self) {
        self.pools.close();
        for s in self.list() {
            s.finish();
        }
        if let Some((_, Some(service))) = &self.perception {
            service.close();
        }
        // After the map pool: its last keyframes reach place recognition first.
        if let Some(fleets) = &self.fleets {
            fleets.close();
        }
    }

    /// Stops every worker once its queue is drained (server shutdown).
    pub fn close_all(&self) {
        for s in self.list() {
            s.queue.close();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A trajectory answered in pages: the range, the limit, and where the next
    /// page starts exactly when more of the range follow.
    #[test]
    fn a_trajectory_is_answered_in_pages() {
        let pose = |sequence: u64, capture_time_ns: u64| pb::PoseStamped { sequence, capture_time_ns, ..Default::default() };
        // A page of the poses in memory.
        let page_of = |track: &TrackState, start_ns: u64, end_ns: u64, limit: usize| {
            let mut page = Page::new(start_ns, end_ns, limit);
            track.trajectory.iter().for_each(|p| page.push(*p));
            page.finish()
        };
        let track = TrackState { trajectory: (0..10).map(|i| pose(i, 100 + 10 * i)).collect(), ..Default::default() };
        let times =
            |(poses, next): (Vec<pb::PoseStamped>, Option<u64>)| (poses.iter().map(|p| p.capture_time_ns).collect::<Vec<_>>(), next);
        assert_eq!(times(page_of(&track, 0, u64::MAX, 4)), (vec![100, 110, 120, 130], Some(140)));
        assert_eq!(times(page_of(&track, 140, u64::MAX, 4)), (vec![140, 150, 160, 170], Some(180)));
        assert_eq!(times(page_of(&track, 180, u64::MAX, 4)), (vec![180, 190], None));
        assert_eq!(times(page_of(&track, 0, u64::MAX, 10)), ((100..=190).step_by(10).collect(), None), "exactly the limit: no next page");
        assert_eq!(times(page_of(&track, 120, 150, 2)), (vec![120, 130], Some(140)));
        assert_eq!(times(page_of(&track, 140, 150, 2)), (vec![140, 150], None), "the rest is out of the range");
        assert_eq!(times(page_of(&track, 191, u64::MAX, 2)), (vec![], None));
        // A clock that went back (the timeline taken again): pages follow capture
        // time, and poses of one capture time stay on one page.
        let track = TrackState {
            trajectory: [100, 110, 120, 40, 50, 110].iter().zip(0..).map(|(&t, i)| pose(i, t)).collect(),
            ..Default::default()
        };
        assert_eq!(times(page_of(&track, 0, u64::MAX, 2)), (vec![40, 50], Some(100)));
        assert_eq!(times(page_of(&track, 100, u64::MAX, 2)), (vec![100, 110, 110], Some(120)));
        assert_eq!(times(page_of(&track, 120, u64::MAX, 2)), (vec![120], None));
    }

    /// A page built from poses in any order, compacted as it goes (bounded
    /// memory), is the page of the whole range sorted: checked against sorting
    /// everything, over shuffled poses with repeated capture times.
    #[test]
    fn a_page_built_in_bounded_memory_is_the_page_of_everything_sorted() {
        let mut state = 12345u64;
        let mut next_random = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            state >> 33
        };
        let poses: Vec<pb::PoseStamped> =
            (0..500).map(|i| pb::PoseStamped { sequence: i, capture_time_ns: next_random() % 300, ..Default::default() }).collect();
        let sorted_page = |start: u64, end: u64, limit: usize| {
            let mut in_range: Vec<pb::PoseStamped> = poses.iter().filter(|p| (start..=end).contains(&p.capture_time_ns)).copied().collect();
            in_range.sort_by_key(|p| p.capture_time_ns);
            let mut cut = limit.min(in_range.len());
            while cut > 0 && cut < in_range.len() && in_range[cut].capture_time_ns == in_range[cut - 1].capture_time_ns {
                cut += 1;
            }
            let next = in_range.get(cut).map(|p| p.capture_time_ns);
            in_range.truncate(cut);
            (in_range, next)
        };
        for (start, end, limit) in
            [(0, u64::MAX, 1), (0, u64::MAX, 7), (50, 120, 10), (0, u64::MAX, 499), (0, u64::MAX, 500), (299, 299, 3)]
        {
            let mut page = Page::new(start, end, limit);
            poses.iter().for_each(|p| page.push(*p));
            assert_eq!(page.finish(), sorted_page(start, end, limit), "{start}..={end}, {limit}");
        }
    }

    /// With a store, the oldest committed poses leave memory (a quarter over
    /// `session.trajectory_in_memory`, down to it), and the pages and the whole
    /// trajectory read them back: nothing is lost, nothing repeated, also where the
    /// robot's sequence numbers started again (the store keeps poses by their
    /// place, which the robot's numbers would have overwritten).
    #[test]
    fn older_poses_leave_memory_and_come_back_from_the_store() {
        let config = SessionConfig { trajectory_in_memory: 100, idle_evict_s: 0.001, ..SessionConfig::default() };
        let registry = registry_with(Some("trajectory"), config, LimitsConfig::default());
        let (sink, _rx) = mpsc::channel(4);
        let session = registry.open(&hello("r"), Transport::Grpc, sink.clone()).expect("open").session;
        let pose = |i: u64| pb::PoseStamped {
            sequence: i % 250,
            capture_time_ns: 1_000 + 10 * i,
            world_from_camera: Some(pb::Pose::from_parts([i as f64, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])),
            ..Default::default()
        };
        for chunk in 0..10 {
            session.tracking().trajectory.extend((chunk * 50..(chunk + 1) * 50).map(pose));
            let held = session.tracking().trajectory.len();
            assert!(held <= 150, "only committed poses leave: {held}");
            assert!(session.flush(), "committed");
        }
        {
            let track = session.tracking();
            assert_eq!((track.trajectory.len(), track.earlier, track.len()), (100, 400, 500));
        }
        let all: Vec<pb::PoseStamped> = (0..500).map(pose).collect();
        assert_eq!(session.whole_trajectory().expect("read back"), all);
        let (first, next) = session.trajectory_page(0, u64::MAX, 200).expect("a page");
        assert_eq!((first, next), (all[..200].to_vec(), Some(all[200].capture_time_ns)));
        let (mut paged, mut start) = (Vec::new(), 0);
        loop {
            let (page, next) = session.trajectory_page(start, u64::MAX, 60).expect("a page");
            paged.extend(page);
            match next {
                Some(n) => start = n,
                None => break,
            }
        }
        assert_eq!(paged, all, "pages across the poses out of memory and in it");
        let inside = session.trajectory_page(all[10].capture_time_ns, all[19].capture_time_ns, 100).expect("a page");
        assert_eq!(inside, (all[10..20].to_vec(), None));
        // Out of memory and read back: only the newest poses come into memory.
        let id = session.id.clone();
        session.detach(&sink);
        drop(session);
        std::thread::sleep(std::time::Duration::from_millis(5));
        assert_eq!(registry.evict_idle(), 1);
        let back = registry.get(&id).expect("read back from the store");
        {
            let track = back.tracking();
            assert_eq!((track.trajectory.len(), track.earlier), (100, 400));
            assert!(track.trajectory.capacity() <= 200, "the poses read back and left out are freed: {}", track.trajectory.capacity());
        }
        assert_eq!(back.whole_trajectory().expect("read back"), all);
        registry.close_all();
    }

    /// What an 8-hour session's trajectory costs with the default
    /// `session.trajectory_in_memory` (a measurement, not a check):
    /// `cargo test --release -p stillmap-server --lib -- --ignored --nocapture trajectory_of_eight_hours`.
    #[test]
    #[ignore]
    fn trajectory_of_eight_hours() {
        let config = SessionConfig::default();
        let keep = config.trajectory_in_memory;
        let registry = registry_with(Some("eight-hours"), config, LimitsConfig::default());
        let (sink, _rx) = mpsc::channel(4);
        let session = registry.open(&hello("r"), Transport::Grpc, sink).expect("open").session;
        let n: u64 = 8 * 3600 * 30;
        let pose = |i: u64| pb::PoseStamped {
            sequence: i,
            capture_time_ns: 1_000_000_000 + 33_333_333 * i,
            world_from_camera: Some(pb::Pose::from_parts([i as f64 * 1e-3, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])),
            tracking_state: pb::TrackingState::Tracking as i32,
            pose_time_ns: None,
        };
        let started = Instant::now();
        for chunk in 0..n / 300 {
            session.tracking().trajectory.extend((chunk * 300..(chunk + 1) * 300).map(pose));
            assert!(session.flush());
        }
        let committing = started.elapsed();
        let (held, earlier, capacity) = {
            let t = session.tracking();
            (t.trajectory.len(), t.earlier, t.trajectory.capacity())
        };
        let time = |f: &dyn Fn() -> usize| {
            let t = Instant::now();
            let got = f();
            (got, t.elapsed().as_secs_f64() * 1e3)
        };
        let first = time(&|| session.trajectory_page(0, u64::MAX, DEFAULT_TRAJECTORY_PAGE).expect("page").0.len());
        let last_start = pose(n - 1000).capture_time_ns;
        let last = time(&|| session.trajectory_page(last_start, u64::MAX, DEFAULT_TRAJECTORY_PAGE).expect("page").0.len());
        let whole = time(&|| session.whole_trajectory().expect("whole").len());
        println!(
            "| {n} poses, committed 300 at a time in {:.1} s | in memory | out of memory | Vec capacity |\n|---|---|---|---|",
            committing.as_secs_f64()
        );
        println!(
            "| | {held} (keep {keep}) | {earlier} | {capacity} ({:.1} MB) |",
            (capacity * std::mem::size_of::<pb::PoseStamped>()) as f64 / 1e6
        );
        println!("| query | poses | ms |\n|---|---|---|");
        println!("| first page (20,000, from the store) | {} | {:.0} |", first.0, first.1);
        println!("| last 1,000 poses (memory only) | {} | {:.1} |", last.0, last.1);
        println!("| whole trajectory (MCAP export's read) | {} | {:.0} |", whole.0, whole.1);
        registry.close_all();
    }

    fn small_camera() -> pb::CameraInfo {
        pb::CameraInfo {
            color_encoding: pb::ColorEncoding::Rgb8 as i32,
            depth_encoding: pb::DepthEncoding::Zstd as i32,
            ..crate::map::tests::small_camera()
        }
    }

    /// A registry with mapping on, a store in a fresh file (`None`: no store).
    fn registry_with(name: Option<&str>, session: SessionConfig, limits: LimitsConfig) -> Registry {
        let store = name.map(|name| {
            let path = std::env::temp_dir().join(format!("stillmap-registry-{name}-{}.redb", std::process::id()));
            let _ = std::fs::remove_file(&path);
            Arc::new(Store::open(&path).expect("store"))
        });
        let pools = Pools::start(&session).expect("pools");
        Registry::new(session, TrackerConfig::default(), None, MappingConfig::default(), store, Arc::default(), pools).with_limits(limits)
    }

    fn hello(robot: &str) -> pb::Hello {
        pb::Hello { robot_id: robot.into(), camera: Some(small_camera()), ..Default::default() }
    }

    fn metric(registry: &Registry, name: &str) -> Option<String> {
        registry.metrics().render().lines().find(|l| l.starts_with(name)).map(str::to_owned)
    }

    /// Two servers started in the same second (a compose file, a StatefulSet) give
    /// the same robot different session ids: each run's ids carry random bits.
    #[test]
    fn servers_started_together_give_a_robot_different_session_ids() {
        let (a, b) = (
            registry_with(None, SessionConfig::default(), LimitsConfig::default()),
            registry_with(None, SessionConfig::default(), LimitsConfig::default()),
        );
        let (sink, _rx) = mpsc::channel(4);
        let on_a = a.open(&hello("r"), Transport::Grpc, sink.clone()).expect("open").session.id.clone();
        let on_b = b.open(&hello("r"), Transport::Grpc, sink).expect("open").session.id.clone();
        assert_ne!(on_a, on_b);
        // <robot>-<start time in seconds, hex><32 random bits, hex>-<n>
        for id in [&on_a, &on_b] {
            let parts: Vec<&str> = id.split('-').collect();
            assert_eq!((parts.len(), parts[0], parts[2]), (3, "r", "1"), "{id}");
            assert!(parts[1].len() > 8 && parts[1].chars().all(|c| c.is_ascii_hexdigit()), "{id}");
        }
    }

    /// The sessions list comes in pages, oldest first: each page starts after the
    /// token the previous one gave, a session opened meanwhile comes on a later
    /// page, and a token no list gave is refused by name.
    #[test]
    fn sessions_are_listed_in_pages() {
        let registry = registry_with(None, SessionConfig::default(), LimitsConfig::default());
        let (sink, _rx) = mpsc::channel(4);
        let mut opened = Vec::new();
        for robot in ["a", "b", "c", "d", "e"] {
            opened.push(registry.open(&hello(robot), Transport::Grpc, sink.clone()).expect("open").session.id.clone());
            std::thread::sleep(Duration::from_millis(2));
        }
        let ids = |page: &[SessionInfo]| page.iter().map(|s| s.summary.session_id.clone()).collect::<Vec<_>>();
        let (first, next) = registry.list_page(None, 2);
        assert_eq!(ids(&first), opened[..2]);
        let next = next.expect("more follow");
        assert_eq!(next, ListCursor::of(&first[1].summary));
        let token = next.token();
        assert_eq!(ListCursor::parse(&token), Ok(next.clone()), "{token}");
        opened.push(registry.open(&hello("f"), Transport::Grpc, sink.clone()).expect("open").session.id.clone());
        let (second, next) = registry.list_page(Some(&next), 2);
        assert_eq!(ids(&second), opened[2..4]);
        let (last, end) = registry.list_page(next.as_ref(), 2);
        assert_eq!((ids(&last), end), (opened[4..].to_vec(), None), "the session opened meanwhile is on the last page");
        let (all, end) = registry.list_page(None, 6);
        assert_eq!((ids(&all), end), (opened.clone(), None), "exactly the limit: no next page");
        for bad in ["", "12", "x:r-1", "12:", "-1:r-1"] {
            let message = ListCursor::parse(bad).expect_err(bad);
            assert!(message.starts_with(&format!("page_token {bad:?} is not one a sessions list gave")), "{message}");
        }
        registry.close_all();
    }

    /// The dashboard's snapshot (to every viewer and every other server, twice a
    /// second) lists every session in memory and only the newest stored ones, and
    /// says how many it leaves out.
    #[test]
    fn the_dashboard_lists_the_sessions_in_memory_and_the_newest_stored_ones() {
        let config = SessionConfig { idle_evict_s: 0.001, ..SessionConfig::default() };
        let registry = registry_with(Some("snapshot"), config, LimitsConfig::default());
        let (sink, _rx) = mpsc::channel(4);
        let stored = crate::api::dashboard::SNAPSHOT_STORED_SESSIONS + 2;
        let mut ids = Vec::new();
        for i in 0..stored {
            let s = registry.open(&hello(&format!("r{i}")), Transport::Grpc, sink.clone()).expect("open").session;
            ids.push(s.id.clone());
            s.detach(&sink);
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
        assert_eq!(registry.evict_idle(), stored);
        let live = registry.open(&hello("live"), Transport::Grpc, sink.clone()).expect("open").session;
        let (listed, _, not_shown) = crate::api::dashboard::session_list(&registry, HashMap::new());
        let listed: Vec<&str> = listed.iter().filter_map(|s| s["session_id"].as_str()).collect();
        let expected: Vec<&str> = std::iter::once(live.id.as_str()).chain(ids[2..].iter().map(String::as_str)).collect();
        assert_eq!((listed, not_shown), (expected, 2));
        assert_eq!(registry.list_info().len(), stored + 1, "the API lists them all");
        registry.close_all();
    }

    /// A frame that panicked the pipeline (the pool reports it to the session's
    /// lane) ends the stream with ABORTED naming the session, which the client
    /// answers with a new session; later frames get the same status; it is counted.
    #[test]
    fn a_panic_on_a_frame_ends_the_stream_for_a_new_session() {
        let registry = registry_with(None, SessionConfig::default(), LimitsConfig::default());
        let (sink, mut rx) = mpsc::channel(4);
        let session = registry.open(&hello("r"), Transport::Grpc, sink).expect("open").session;
        Lane::failed(&*session, "index out of bounds");
        let expected = format!("session {} failed on a frame (a server bug: index out of bounds): open a new session", session.id);
        let ended = rx.try_recv().expect("the connection hears of it").expect_err("the stream ends");
        assert_eq!((ended.code(), ended.message()), (tonic::Code::Aborted, expected.as_str()));
        let refused = session.push(pb::Frame { sequence: 1, ..Default::default() }, 10).expect_err("no more frames");
        let status = session.refusal_of(refused);
        assert_eq!((status.code(), status.message()), (tonic::Code::Aborted, expected.as_str()));
        let rendered = registry.metrics().render();
        assert!(rendered.contains("stillmap_panics_total{stage=\"pipeline\"} 1"), "{rendered}");
        assert!(rendered.contains("stillmap_sessions_ended_total{limit=\"panic\"} 1"), "{rendered}");
    }

    /// A disconnected session leaves memory after session.idle_evict_s; the list
    /// still shows it, a query brings it back read-only, and a resume of it gets a
    /// new session.
    #[test]
    fn idle_sessions_leave_memory_and_a_query_brings_them_back() {
        let config = SessionConfig { idle_evict_s: 0.001, ..SessionConfig::default() };
        let registry = registry_with(Some("evict"), config, LimitsConfig::default());
        let (sink, _rx) = mpsc::channel(4);
        let opened = registry.open(&hello("r"), Transport::Grpc, sink.clone()).expect("open").session;
        let (id, secret) = (opened.id.clone(), opened.resume_secret().to_string());
        std::thread::sleep(std::time::Duration::from_millis(5));
        assert_eq!(registry.evict_idle(), 0, "a connected session stays");
        opened.detach(&sink);
        std::thread::sleep(std::time::Duration::from_millis(5));
        assert_eq!(registry.evict_idle(), 1);
        assert!(registry.resident(&id).is_none());
        assert!(opened.queue.is_closed(), "a robot still sending to it is told to send a hello");
        drop(opened);
        let info = registry.info(&id).expect("listed");
        assert!((info.archived, info.resident, info.summary.connected) == (true, false, false));
        assert_eq!(registry.list_info().len(), 1);
        assert_eq!(metric(&registry, "stillmap_sessions_evicted_total").as_deref(), Some("stillmap_sessions_evicted_total 1"));
        assert_eq!(metric(&registry, "stillmap_sessions_resident ").as_deref(), Some("stillmap_sessions_resident 0"));
        // The resume finds it gone from memory: a new session.
        let resume = pb::Hello { resume_session_id: id.clone(), resume_secret: secret, ..hello("r") };
        let again = registry.open(&resume, Transport::Grpc, sink.clone()).expect("open");
        assert!(!again.resumed);
        assert_ne!(again.session.id, id);
        // A query brings the evicted one back, read-only, with its map.
        let back = registry.get(&id).expect("loaded from the store");
        assert!(back.is_archived() && back.map().is_some());
        assert_eq!(metric(&registry, "stillmap_sessions_loaded_total").as_deref(), Some("stillmap_sessions_loaded_total 1"));
        assert_eq!(metric(&registry, "stillmap_sessions_resident ").as_deref(), Some("stillmap_sessions_resident 2"));
        assert_eq!(registry.list_info().len(), 2, "listed once");
        registry.close_all();
        registry.join_workers();
    }

    /// A query's load of a stored session that is left out of the listing while it
    /// reads the store (the session went on on another server) is dropped, and a
    /// copy loaded just before leaves memory: the older copy does not answer
    /// instead of the live one.
    #[test]
    fn a_load_racing_a_move_elsewhere_is_dropped() {
        // A registry with a store holding one session, out of memory.
        let evicted = |name: &str| {
            let config = SessionConfig { idle_evict_s: 0.001, ..SessionConfig::default() };
            let registry = registry_with(Some(name), config, LimitsConfig::default());
            let (sink, _rx) = mpsc::channel(4);
            let opened = registry.open(&hello("r"), Transport::Grpc, sink.clone()).expect("open").session;
            let id = opened.id.clone();
            opened.detach(&sink);
            drop(opened);
            std::thread::sleep(std::time::Duration::from_millis(5));
            assert_eq!(registry.evict_idle(), 1);
            (registry, id)
        };
        let (registry, id) = evicted("load-race");
        // A query reads the store; meanwhile the session is found written on server-a.
        let stored = registry.store.as_ref().expect("a store").load(&id).expect("readable").expect("stored");
        assert_eq!(registry.leave_moved(|_| Some("server-a".into())), std::slice::from_ref(&id));
        assert!(registry.admit_loaded(&id, stored).is_none(), "the older copy does not answer");
        assert!(registry.resident(&id).is_none() && registry.info(&id).is_none(), "nor is it listed");
        assert!(registry.get(&id).is_none(), "queries about it go to server-a");
        assert_eq!(metric(&registry, "stillmap_sessions_loaded_total").as_deref(), Some("stillmap_sessions_loaded_total 0"));
        registry.close_all();
        registry.join_workers();

        // A load that finished just before the check: the copy in memory leaves too.
        let (registry, id) = evicted("load-before");
        assert!(registry.get(&id).is_some_and(|s| s.is_archived()), "brought back for a query");
        assert_eq!(registry.stored_ids(), std::slice::from_ref(&id));
        assert_eq!(registry.leave_moved(|_| Some("server-a".into())), std::slice::from_ref(&id));
        assert!(registry.resident(&id).is_none() && registry.info(&id).is_none() && registry.get(&id).is_none());
        assert_eq!(metric(&registry, "stillmap_sessions_resident ").as_deref(), Some("stillmap_sessions_resident 0"));
        registry.close_all();
        registry.join_workers();
    }

    /// Every limit makes room by evicting idle sessions first and is refused,
    /// named and counted, only when none can go; without a store nothing is
    /// evicted (it would be lost).
    #[test]
    fn a_new_hello_is_checked_before_anything_is_allocated() {
        let ok = hello("r1");
        assert_eq!(validate_new_hello(&ok, 64 * 48).expect("valid").width, 64);
        let message = |r: Result<&pb::CameraInfo, BadHello>| r.expect_err("refused").status();
        let status = message(validate_new_hello(&ok, 64 * 48 - 1));
        assert_eq!(
            (status.code(), status.message()),
            (tonic::Code::ResourceExhausted, "camera of 64x48 = 3072 pixels is over session.max_camera_pixels = 3071")
        );
        let status = message(validate_new_hello(&pb::Hello { robot_id: "r/1".into(), ..hello("r1") }, u64::MAX));
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(status.message().contains("robot_id \"r/1\" contains '/'"), "{}", status.message());
        let status = message(validate_new_hello(&pb::Hello { fleet: "a b".into(), ..hello("r1") }, u64::MAX));
        assert!(status.message().contains("fleet \"a b\" contains ' '"), "{}", status.message());
        let status = message(validate_new_hello(&pb::Hello { camera: None, ..hello("r1") }, u64::MAX));
        assert!(status.message().contains("hello has no camera info"), "{}", status.message());
    }

    /// A resume that waits for a live server's handover waits for
    /// `session.handover_wait_s` from its first hello, then no more (a new session);
    /// each session is timed on its own, and 0 never waits. Without a replica there
    /// is nothing to hand over.
    #[test]
    fn a_resume_waits_for_a_handover_only_so_long() {
        let wait = SessionConfig { handover_wait_s: 0.2, ..SessionConfig::default() };
        let registry = registry_with(None, wait, LimitsConfig::default());
        assert!(registry.awaits_handover("s-1"), "the first hello waits");
        assert!(registry.awaits_handover("s-1"), "and the next ones, within the wait");
        std::thread::sleep(std::time::Duration::from_millis(250));
        assert!(registry.awaits_handover("s-2"), "another session is timed on its own");
        assert!(!registry.awaits_handover("s-1"), "past the wait: a new session instead");
        let never = registry_with(None, SessionConfig { handover_wait_s: 0.0, ..SessionConfig::default() }, LimitsConfig::default());
        assert!(!never.awaits_handover("s-1"));
        assert!(!registry.hand_over("s-1"), "no store, no replica: nothing handed over");
    }

    /// A hello naming a fleet beyond `fleet.max_fleets` is refused by name and counted;
    /// fleets already held (and the default one) still take sessions.
    #[test]
    fn fleets_beyond_the_limit_are_refused_by_name() {
        let fleets = crate::fleet::FleetService::start(
            &crate::config::FleetConfig { max_fleets: 2, ..Default::default() },
            &stillmap_mapping::MappingConfig::default(),
            None,
            Arc::default(),
        )
        .expect("fleet service");
        let registry = registry_with(None, SessionConfig::default(), LimitsConfig::default()).with_fleets(Some(fleets.clone()));
        let (sink, _rx) = mpsc::channel(4);
        let in_fleet = |robot: &str, fleet: &str| pb::Hello { fleet: fleet.into(), ..hello(robot) };
        registry.open(&in_fleet("a", "north"), Transport::Grpc, sink.clone()).expect("first fleet");
        registry.open(&hello("b"), Transport::Grpc, sink.clone()).expect("the default fleet, second");
        let refused = registry.open(&in_fleet("c", "south"), Transport::Grpc, sink.clone()).err().expect("a third fleet is refused");
        let status = refused.status();
        assert_eq!(
            (status.code(), status.message()),
            (
                tonic::Code::ResourceExhausted,
                "server full: hello names a new fleet \"south\"; the server holds 2 fleets, fleet.max_fleets = 2"
            )
        );
        registry.open(&in_fleet("d", "north"), Transport::Grpc, sink.clone()).expect("a fleet already held");
        assert_eq!(
            metric(&registry, "stillmap_sessions_refused_total{limit=\"max_fleets\"}").as_deref(),
            Some("stillmap_sessions_refused_total{limit=\"max_fleets\"} 1")
        );
        assert_eq!(fleets.list().len(), 2);
        fleets.close();
    }

    #[test]
    fn limits_evict_idle_sessions_first_and_refuse_by_name() {
        let limits =
            LimitsConfig { max_sessions: 3, max_sessions_per_robot: 1, max_camera_pixels_total: 64 * 48 * 2, ..LimitsConfig::default() };
        let registry = registry_with(Some("limits"), SessionConfig { idle_evict_s: 0.0, ..SessionConfig::default() }, limits.clone());
        let (sink, _rx) = mpsc::channel(4);
        let first = registry.open(&hello("a"), Transport::Grpc, sink.clone()).expect("open").session;
        let limit_of = |r: Result<Opened, BadHello>| match r {
            Err(BadHello::Limit { limit, message }) => (limit, message),
            Err(e) => panic!("another refusal: {e}"),
            Ok(_) => panic!("accepted"),
        };
        let (limit, message) = limit_of(registry.open(&hello("a"), Transport::Grpc, sink.clone()));
        assert_eq!(limit, "max_sessions_per_robot");
        assert!(message.contains("limits.max_sessions_per_robot = 1"), "{message}");
        assert_eq!(
            registry.open(&hello("a"), Transport::Grpc, sink.clone()).err().map(|e| e.status().code()),
            Some(tonic::Code::ResourceExhausted)
        );
        // Disconnected: the robot's next session takes its place.
        first.detach(&sink);
        let second = registry.open(&hello("a"), Transport::Grpc, sink.clone()).expect("room made").session;
        assert!(registry.resident(&first.id).is_none() && registry.info(&first.id).is_some());
        let _b = registry.open(&hello("b"), Transport::Grpc, sink.clone()).expect("open");
        let (limit, _) = limit_of(registry.open(&hello("c"), Transport::Grpc, sink.clone()));
        assert_eq!(limit, "max_camera_pixels_total");
        second.detach(&sink);
        let _c = registry.open(&hello("c"), Transport::Grpc, sink.clone()).expect("room made");
        assert_eq!(
            metric(&registry, "stillmap_sessions_refused_total{limit=\"max_sessions_per_robot\"}").as_deref(),
            Some("stillmap_sessions_refused_total{limit=\"max_sessions_per_robot\"} 2")
        );
        assert_eq!(
            metric(&registry, "stillmap_sessions_refused_total{limit=\"max_camera_pixels_total\"}").as_deref(),
            Some("stillmap_sessions_refused_total{limit=\"max_camera_pixels_total\"} 1")
        );
        registry.close_all();
        registry.join_workers();

        // No store: a disconnected session holds its place (its map would be lost).
        let registry = registry_with(None, SessionConfig { idle_evict_s: 0.001, ..SessionConfig::default() }, limits);
        let first = registry.open(&hello("a"), Transport::Grpc, sink.clone()).expect("open").session;
        first.detach(&sink);
        std::thread::sleep(std::time::Duration::from_millis(5));
        assert_eq!(registry.evict_idle(), 0);
        assert_eq!(limit_of(registry.open(&hello("a"), Transport::Grpc, sink.clone())).0, "max_sessions_per_robot");
        registry.close_all();
        registry.join_workers();
    }

    /// A Zenoh robot's frames re-attach its link only when no other connection holds
    /// the session: a gRPC resume keeps the results, and the gauge counts once.
    #[test]
    fn attach_if_vacant_never_takes_a_session_from_another_connection() {
        let mapping = MappingConfig { enabled: false, ..MappingConfig::default() };
        let config = SessionConfig::default();
        let pools = Pools::start(&config).expect("pools");
        let registry = Registry::new(config, TrackerConfig::default(), None, mapping, None, Arc::default(), pools);
        let hello = hello("r");
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
        registry.join_workers();
    }
}
