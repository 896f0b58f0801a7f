//! Prometheus metrics served at `/metrics`.

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

type Labels = Vec<(&'static str, String)>;

/// Latency buckets: 50 µs doubling to about 1.6 s.
const LATENCY_BUCKET_START_S: f64 = 50e-6;
const LATENCY_BUCKET_FACTOR: f64 = 2.0;
const LATENCY_BUCKET_COUNT: u16 = 16;

fn latency_histogram() -> Histogram {
    Histogram::new(exponential_buckets(LATENCY_BUCKET_START_S, LATENCY_BUCKET_FACTOR, LATENCY_BUCKET_COUNT))
}

/// Every counter the server keeps, labelled by transport, reason or stage.
pub struct Metrics {
    registry: Registry,
    frames_received: Family<Labels, Counter>,
    frames_processed: Family<Labels, Counter>,
    frames_dropped: Family<Labels, Counter>,
    frames_rejected: Family<Labels, Counter>,
    bytes_received: Family<Labels, Counter>,
    stage_latency: Family<Labels, Histogram, fn() -> Histogram>,
    features_eliminated: Counter,
    masks: Family<Labels, Counter>,
    keyframes_fused: Counter,
    keyframes_forgotten: Counter,
    sessions_connected: Gauge,
    sessions_total: Counter,
    segmentation_batch_size: Histogram,
    segmentation_batch_seconds: Histogram,
    segmentation_replaced: Counter,
    map_backlog: Gauge,
    map_jobs_skipped: Family<Labels, Counter>,
    fleet_keyframes_left_out: Family<Labels, Counter>,
    store_errors: Counter,
    replica: crate::replica::ReplicaCounters,
    sessions_resident: Gauge,
    sessions_evicted: Counter,
    sessions_handed_over: Counter,
    sessions_loaded: Counter,
    sessions_refused: Family<Labels, Counter>,
    frame_cpu_over_budget: Counter,
    sessions_ended: Family<Labels, Counter>,
    panics: Family<Labels, Counter>,
}

impl Default for Metrics {
    fn default() -> Self {
        let mut registry = Registry::with_prefix("stillmap");
        let frames_received = Family::<Labels, Counter>::default();
        let frames_processed = Family::<Labels, Counter>::default();
        let frames_dropped = Family::<Labels, Counter>::default();
        let frames_rejected = Family::<Labels, Counter>::default();
        let bytes_received = Family::<Labels, Counter>::default();
        let stage_latency = Family::<Labels, Histogram, fn() -> Histogram>::new_with_constructor(latency_histogram);
        let sessions_connected = Gauge::default();
        let sessions_total = Counter::default();
        registry.register("frames_received", "Frames received, by transport", frames_received.clone());
        registry.register("frames_processed", "Frames decoded and processed, by transport", frames_processed.clone());
        registry.register("frames_dropped", "Frames dropped by the overload policy, by transport", frames_dropped.clone());
        registry.register(
            "frames_rejected",
            "Frames, messages or hellos rejected, by reason (order, color, depth, oversized, no_hello, malformed, unauthenticated, server_full, too_large)",
            frames_rejected.clone(),
        );
        registry.register("bytes_received", "Frame payload bytes received, by transport", bytes_received.clone());
        registry.register("stage_latency_seconds", "Server-side time per pipeline stage", stage_latency.clone());
        let features_eliminated = Counter::default();
        registry.register("features_eliminated", "Keypoints dropped before tracking by the dynamic mask", features_eliminated.clone());
        let masks = Family::<Labels, Counter>::default();
        registry.register("masks", "Dynamic masks computed, by segmentation source (fresh, warped, none)", masks.clone());
        let keyframes_fused = Counter::default();
        registry.register("keyframes_fused", "Keyframes fused into the static semantic maps", keyframes_fused.clone());
        let keyframes_forgotten = Counter::default();
        registry.register(
            "tracker_keyframes_forgotten",
            "Keyframes the sessions' trackers forgot beyond tracking.max_keyframes (the store keeps their records)",
            keyframes_forgotten.clone(),
        );
        registry.register("sessions_connected", "Sessions with a connected robot", sessions_connected.clone());
        registry.register("sessions", "Sessions opened", sessions_total.clone());
        let segmentation_batch_size = Histogram::new(exponential_buckets(1.0, 2.0, 7));
        registry.register("segmentation_batch_size", "Frames per segmentation inference", segmentation_batch_size.clone());
        let segmentation_batch_seconds = latency_histogram();
        registry.register(
            "segmentation_batch_seconds",
            "Time of one segmentation inference (a whole batch)",
            segmentation_batch_seconds.clone(),
        );
        let segmentation_replaced = Counter::default();
        registry.register(
            "segmentation_replaced",
            "Frames waiting for segmentation replaced by their session's newer frame (segmentation fell behind)",
            segmentation_replaced.clone(),
        );
        let map_backlog = Gauge::default();
        registry.register("map_backlog", "Map jobs (keyframes, re-fusions) waiting for the map pool, all sessions", map_backlog.clone());
        let map_jobs_skipped = Family::<Labels, Counter>::default();
        registry.register(
            "map_jobs_skipped",
            "Map jobs left out because their session's map queue was full (kind: keyframe, refuse)",
            map_jobs_skipped.clone(),
        );
        let fleet_keyframes_left_out = Family::<Labels, Counter>::default();
        registry.register(
            "fleet_keyframes_left_out",
            "Keyframes left out of their fleet because its queue was full: place recognition (queue=places, fleet.queue) or the fused fleet map (queue=fleet_map, fleet.map_queue); a keyframe left out of both counts in each",
            fleet_keyframes_left_out.clone(),
        );
        let replica = crate::replica::ReplicaCounters::default();
        registry.register("replica_commits", "Store commits copied to shared storage (store.replica_url)", replica.commits.clone());
        registry.register("replica_bytes", "Bytes of store commits copied to shared storage", replica.bytes.clone());
        registry.register("replica_dropped", "Store commits not copied: the replica queue was full", replica.dropped.clone());
        registry.register(
            "replica_fenced",
            "Store commits not copied: another server had taken the session over (a late commit of this one)",
            replica.fenced.clone(),
        );
        registry.register("replica_write_microseconds", "Time spent writing commits to shared storage", replica.write_micros.clone());
        let store_errors = Counter::default();
        registry.register(
            "store_errors",
            "Store operations that failed (a full disk, an I/O error); /healthz says 503 while writes fail",
            store_errors.clone(),
        );
        let sessions_resident = Gauge::default();
        registry.register(
            "sessions_resident",
            "Sessions in memory (live, and stored ones a query brought back)",
            sessions_resident.clone(),
        );
        let sessions_evicted = Counter::default();
        registry.register(
            "sessions_evicted",
            "Sessions that left memory (idle, or to make room); the store keeps them",
            sessions_evicted.clone(),
        );
        let sessions_handed_over = Counter::default();
        registry.register(
            "sessions_handed_over",
            "Sessions handed over to the server a joining server's placement gave their robot (it resumes them)",
            sessions_handed_over.clone(),
        );
        let sessions_loaded = Counter::default();
        registry.register("sessions_loaded", "Stored sessions brought back into memory by a query", sessions_loaded.clone());
        let frame_cpu_over_budget = Counter::default();
        registry.register(
            "frame_cpu_over_budget",
            "Frames that took more pipeline CPU than limits.frame_cpu_ms",
            frame_cpu_over_budget.clone(),
        );
        let sessions_ended = Family::<Labels, Counter>::default();
        registry.register(
            "sessions_ended",
            "Session streams the server ended: by a limit (frame_cpu_ms), a resumed session not found again (resume_find_s), or a panic on one of its frames (panic)",
            sessions_ended.clone(),
        );
        let panics = Family::<Labels, Counter>::default();
        registry.register(
            "panics",
            "Panics caught (server bugs), by where: a session's frame (its stream ended), its map job, the fleet's place recognition or pose graph (the job dropped)",
            panics.clone(),
        );
        let sessions_refused = Family::<Labels, Counter>::default();
        registry.register(
            "sessions_refused",
            "Hellos refused by a limit (max_connected, max_sessions, max_sessions_per_robot, max_camera_pixels_total)",
            sessions_refused.clone(),
        );
        Self {
            registry,
            frames_received,
            frames_processed,
            frames_dropped,
            frames_rejected,
            bytes_received,
            stage_latency,
            features_eliminated,
            masks,
            keyframes_fused,
            keyframes_forgotten,
            sessions_connected,
            sessions_total,
            segmentation_batch_size,
            segmentation_batch_seconds,
            segmentation_replaced,
            map_backlog,
            map_jobs_skipped,
            fleet_keyframes_left_out,
            store_errors,
            replica,
            sessions_resident,
            sessions_evicted,
            sessions_handed_over,
            sessions_loaded,
            sessions_refused,
            frame_cpu_over_budget,
            sessions_ended,
            panics,
        }
    }
}

impl Metrics {
    /// The counter the store counts its errors in.
    pub fn store_errors(&self) -> Counter {
        self.store_errors.clone()
    }

    /// The counters of the copy to shared storage (`store.replica_url`).
    pub fn replica(&self) -> crate::replica::ReplicaCounters {
        self.replica.clone()
    }
}

fn one(key: &'static str, value: &str) -> Labels {
    vec![(key, value.to_string())]
}

impl Metrics {
    pub fn frame_received(&self, transport: &str, bytes: usize) {
        self.frames_received.get_or_create(&one("transport", transport)).inc();
        self.bytes_received.get_or_create(&one("transport", transport)).inc_by(bytes as u64);
    }
    pub fn frame_processed(&self, transport: &str) {
        self.frames_processed.get_or_create(&one("transport", transport)).inc();
    }
    pub fn frame_dropped(&self, transport: &str) {
        self.frames_dropped.get_or_create(&one("transport", transport)).inc();
    }
    pub fn rejected(&self, reason: &str) {
        self.frames_rejected.get_or_create(&one("reason", reason)).inc();
    }
    pub fn stage(&self, stage: &str, micros: u32) {
        self.stage_latency.get_or_create(&one("stage", stage)).observe(f64::from(micros) * 1e-6);
    }
    pub fn perception(&self, mask_source: &str, features_eliminated: u32) {
        self.masks.get_or_create(&one("source", mask_source)).inc();
        self.features_eliminated.inc_by(u64::from(features_eliminated));
    }

    pub fn keyframe_fused(&self) {
        self.keyframes_fused.inc();
    }

    pub fn keyframes_forgotten(&self, n: u64) {
        self.keyframes_forgotten.inc_by(n);
    }

    pub fn segmentation_batch(&self, frames: usize, elapsed: std::time::Duration) {
        self.segmentation_batch_size.observe(frames as f64);
        self.segmentation_batch_seconds.observe(elapsed.as_secs_f64());
    }
    pub fn segmentation_replaced(&self) {
        self.segmentation_replaced.inc();
    }

    pub fn map_backlog(&self, delta: i64) {
        self.map_backlog.inc_by(delta);
    }
    pub fn map_job_skipped(&self, keyframe: bool) {
        self.map_jobs_skipped.get_or_create(&one("kind", if keyframe { "keyframe" } else { "refuse" })).inc();
    }

    /// `n` keyframes left out of a fleet's `queue` ("places" or "fleet_map").
    pub fn fleet_keyframes_left_out(&self, queue: &str, n: usize) {
        self.fleet_keyframes_left_out.get_or_create(&one("queue", queue)).inc_by(n as u64);
    }

    /// A counter's value as rendered (`series`: its name and labels), 0 before it
    /// counted anything (tests).
    #[cfg(test)]
    pub fn counter(&self, series: &str) -> u64 {
        self.render().lines().find_map(|l| l.strip_prefix(series)?.strip_prefix(' ')?.parse().ok()).unwrap_or(0)
    }

    pub fn session_opened(&self) {
        self.sessions_total.inc();
    }
    pub fn connected_delta(&self, delta: i64) {
        self.sessions_connected.inc_by(delta);
    }
    pub fn resident_delta(&self, delta: i64) {
        self.sessions_resident.inc_by(delta);
    }
    pub fn session_handed_over(&self) {
        self.sessions_handed_over.inc();
    }

    pub fn session_evicted(&self) {
        self.sessions_evicted.inc();
    }
    pub fn session_loaded(&self) {
        self.sessions_loaded.inc();
    }
    pub fn frame_cpu_over_budget(&self) {
        self.frame_cpu_over_budget.inc();
    }
    pub fn session_ended(&self, limit: &str) {
        self.sessions_ended.get_or_create(&one("limit", limit)).inc();
    }
    /// A panic caught in `stage` (`pipeline`, `map`, `places`, `pose_graph`).
    pub fn panicked(&self, stage: &str) {
        self.panics.get_or_create(&one("stage", stage)).inc();
    }
    pub fn session_refused(&self, limit: &str) {
        self.sessions_refused.get_or_create(&one("limit", limit)).inc();
    }

    /// The Prometheus text exposition of every metric.
    pub fn render(&self) -> String {
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = encode(&mut out, &self.registry);
        out
    }
}
