//! The segmentation service all sessions share.
//!
//! Segmentation must not stall tracking: it runs on its own worker threads
//! ([`SegmentationService`], each with its own model) and a session picks a result
//! up on a later frame; the masker ([`super::mask`]) carries it to the current frame
//! through the optical flow and the result says `MASK_SOURCE_WARPED` with the age
//! in frames.
//!
//! The service is a dynamic batcher, as Triton's: each session has one slot that
//! holds its newest frame waiting for segmentation (a newer frame replaces it, so
//! nothing queues up behind a slow model), and a worker takes the waiting frames of
//! up to `max_batch` sessions, waiting at most `max_queue_delay_ms` for more when
//! it has fewer, and runs them as one batch. Results go back to each session's slot.
//! Only a model with a symbolic batch dimension batches; with a batch-1 model each
//! worker runs one frame at a time.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use stillmap_perception::segment::RgbFrame;
use stillmap_perception::{PerceptionConfig, PerceptionError, Segmentation, Segmenter, YoloSegmenter};
use stillmap_proto::codec::ColorImage;

use crate::lock;
use crate::metrics::Metrics;

/// A finished segmentation: the frame it was computed on, the result, the inference time.
pub(crate) type Finished = (u64, Segmentation, Duration);

struct Job {
    sequence: u64,
    rgb: Vec<u8>,
    width: u32,
    height: u32,
}

/// One session's place in the service.
#[derive(Default)]
struct Slot {
    /// The newest frame waiting for segmentation.
    pending: Option<Job>,
    /// Frames of this session a worker is segmenting now.
    in_flight: usize,
    /// The newest finished segmentation not taken yet.
    done: Option<Finished>,
}

#[derive(Default)]
struct State {
    slots: HashMap<u64, Slot>,
    /// Sessions with a pending frame, oldest first; each at most once.
    ready: VecDeque<u64>,
    closed: bool,
}

struct Shared {
    state: Mutex<State>,
    /// Signalled when a frame becomes pending and at close.
    wake: Condvar,
    max_batch: usize,
    max_queue_delay: Duration,
    metrics: Arc<Metrics>,
    nice: i32,
}

/// Segmentation worker threads shared by every session, batching their frames.
pub struct SegmentationService {
    shared: Arc<Shared>,
    class_names: Vec<String>,
    device: String,
    next_client: AtomicU64,
    /// The worker threads, joined by [`close`](Self::close): a worker must not be
    /// inferring while the process tears ONNX Runtime down.
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
}

impl SegmentationService {
    /// Loads one model per worker (start-up fails on any model problem) and starts the workers.
    pub fn start(config: &PerceptionConfig, metrics: Arc<Metrics>) -> Result<Arc<Self>, PerceptionError> {
        let mut segmenters: Vec<Box<dyn Segmenter>> = Vec::new();
        for _ in 0..config.segmentation.workers {
            segmenters.push(Box::new(YoloSegmenter::new(&config.segmentation)?));
        }
        Self::with_segmenters(segmenters, config, metrics)
    }

    /// Starts a worker per segmenter (all the same model).
    pub fn with_segmenters(
        segmenters: Vec<Box<dyn Segmenter>>,
        config: &PerceptionConfig,
        metrics: Arc<Metrics>,
    ) -> Result<Arc<Self>, PerceptionError> {
        let first = segmenters.first().ok_or_else(|| PerceptionError::Config("no segmentation worker".into()))?;
        let class_names = first.class_names().to_vec();
        let device = first.device().to_string();
        let max_batch = config.segmentation.max_batch.min(first.max_batch()).max(1);
        if max_batch < config.segmentation.max_batch {
            tracing::info!(
                configured = config.segmentation.max_batch,
                "the segmentation model has a fixed batch of 1: frames run one at a time (deploy/make-batched-model.py makes a batching one)"
            );
        }
        // Every batch shape runs once before the first frame (all workers at once):
        // on a GPU a new shape costs a convolution search that would stall frames.
        let mut segmenters = segmenters;
        let started = Instant::now();
        let warmed = std::thread::scope(|scope| {
            let runs: Vec<_> = segmenters
                .iter_mut()
                .enumerate()
                .map(|(n, s)| {
                    std::thread::Builder::new().name(format!("seg-warm-up-{n}")).spawn_scoped(scope, move || s.warm_up(max_batch))
                })
                .collect();
            runs.into_iter()
                .map(|r| match r {
                    Ok(handle) => handle.join().unwrap_or_else(|_| Err(PerceptionError::Runtime("a segmentation warm-up panicked".into()))),
                    Err(e) => Err(PerceptionError::Runtime(format!("cannot start a segmentation warm-up thread: {e}"))),
                })
                .collect::<Result<Vec<_>, _>>()
        })?;
        if let Some(shapes) = warmed.first().filter(|s| !s.is_empty()) {
            tracing::info!(?shapes, workers = warmed.len(), ms = started.elapsed().as_millis() as u64, "segmentation warmed up");
        }
        let shared = Arc::new(Shared {
            state: Mutex::default(),
            wake: Condvar::new(),
            max_batch,
            max_queue_delay: Duration::from_millis(config.segmentation.max_queue_delay_ms),
            metrics,
            nice: config.segmentation.worker_nice,
        });
        let mut threads = Vec::new();
        for (n, mut segmenter) in segmenters.into_iter().enumerate() {
            let shared = shared.clone();
            let thread = std::thread::Builder::new()
                .name(format!("segmentation-{n}"))
                .spawn(move || worker(segmenter.as_mut(), &shared))
                .map_err(|e| PerceptionError::Runtime(format!("cannot start a segmentation worker: {e}")))?;
            threads.push(thread);
        }
        Ok(Arc::new(Self { shared, class_names, device, next_client: AtomicU64::new(0), threads: Mutex::new(threads) }))
    }

    pub fn class_names(&self) -> &[String] {
        &self.class_names
    }

    pub fn device(&self) -> &str {
        &self.device
    }

    /// Frames one inference runs together at most.
    pub fn max_batch(&self) -> usize {
        self.shared.max_batch
    }

    pub(crate) fn client(self: &Arc<Self>) -> SegmentationClient {
        let id = self.next_client.fetch_add(1, Ordering::Relaxed);
        lock(&self.shared.state).slots.insert(id, Slot::default());
        SegmentationClient { service: self.clone(), id }
    }

    /// Stops the workers once the frames already waiting are done, and waits for them.
    /// Call it after the sessions' workers have stopped (a deterministic session
    /// waits for its jobs).
    pub fn close(&self) {
        lock(&self.shared.state).closed = true;
        self.shared.wake.notify_all();
        for thread in std::mem::take(&mut *lock(&self.threads)) {
            if thread.join().is_err() {
                tracing::warn!("a segmentation worker panicked");
            }
        }
    }
}

/// Takes the next batch: waits for a first pending frame, then for up to
/// `max_batch` frames of different sessions or until `max_queue_delay` has passed.
/// `None` once the service is closed and nothing waits.
fn next_batch(shared: &Shared) -> Option<Vec<(u64, Job)>> {
    let mut state = lock(&shared.state);
    while state.ready.is_empty() {
        if state.closed {
            return None;
        }
        state = crate::wait(&shared.wake, state, None);
    }
    if shared.max_batch > 1 && state.ready.len() < shared.max_batch && !state.closed {
        let deadline = Instant::now() + shared.max_queue_delay;
        while state.ready.len() < shared.max_batch && !state.closed {
            let Some(left) = deadline.checked_duration_since(Instant::now()).filter(|d| !d.is_zero()) else { break };
            state = crate::wait(&shared.wake, state, Some(left));
        }
    }
    let mut batch = Vec::new();
    while batch.len() < shared.max_batch {
        let Some(id) = state.ready.pop_front() else { break };
        if let Some(slot) = state.slots.get_mut(&id)
            && let Some(job) = slot.pending.take()
        {
            slot.in_flight += 1;
            batch.push((id, job));
        }
    }
    Some(batch)
}

fn worker(segmenter: &mut dyn Segmenter, shared: &Shared) {
    crate::lower_this_thread(shared.nice, "segmentation worker");
    while let Some(batch) = next_batch(shared) {
        if batch.is_empty() {
            continue;
        }
        let frames: Vec<RgbFrame<'_>> = batch.iter().map(|(_, j)| RgbFrame { rgb: &j.rgb, width: j.width, height: j.height }).collect();
        let t = Instant::now();
        let results = segmenter.segment_batch(&frames);
        let elapsed = t.elapsed();
        shared.metrics.segmentation_batch(batch.len(), elapsed);
        let share = elapsed / batch.len() as u32;
        let mut state = lock(&shared.state);
        match results {
            Ok(segs) if segs.len() == batch.len() => {
                for ((id, job), seg) in batch.iter().zip(segs) {
                    let Some(slot) = state.slots.get_mut(id) else { continue };
                    slot.in_flight -= 1;
                    // Two workers may finish one session's frames out of order: keep the newest.
                    if slot.done.as_ref().is_none_or(|d| d.0 < job.sequence) {
                        slot.done = Some((job.sequence, seg, share));
                    }
                }
            }
            other => {
                let why = match other {
                    Err(e) => e.to_string(),
                    Ok(segs) => format!("{} results for {} frames", segs.len(), batch.len()),
                };
                tracing::warn!(frames = batch.len(), "segmentation failed: {why}");
                for (id, _) in &batch {
                    if let Some(slot) = state.slots.get_mut(id) {
                        slot.in_flight -= 1;
                    }
                }
            }
        }
    }
}

/// One session's link to the segmentation service.
pub(crate) struct SegmentationClient {
    service: Arc<SegmentationService>,
    id: u64,
}

impl Drop for SegmentationClient {
    fn drop(&mut self) {
        let mut state = lock(&self.service.shared.state);
        state.slots.remove(&self.id);
        state.ready.retain(|&id| id != self.id);
    }
}

impl SegmentationClient {
    /// Offers a frame; it replaces this session's frame still waiting, if any.
    pub(crate) fn submit(&self, sequence: u64, color: &ColorImage) {
        let shared = &self.service.shared;
        let job = Job { sequence, rgb: color.data.clone(), width: color.width, height: color.height };
        let mut state = lock(&shared.state);
        let Some(slot) = state.slots.get_mut(&self.id) else { return };
        if slot.pending.replace(job).is_some() {
            shared.metrics.segmentation_replaced();
        } else {
            state.ready.push_back(self.id);
            shared.wake.notify_one();
        }
    }

    /// The newest finished segmentation not taken yet.
    pub(crate) fn take(&self) -> Option<Finished> {
        lock(&self.service.shared.state).slots.get_mut(&self.id)?.done.take()
    }

    /// Segments a frame and waits for the result (deterministic mode).
    pub(crate) fn segment_now(&self, sequence: u64, color: &ColorImage) -> Option<Finished> {
        self.submit(sequence, color);
        loop {
            {
                let mut state = lock(&self.service.shared.state);
                let slot = state.slots.get_mut(&self.id)?;
                if slot.pending.is_none() && slot.in_flight == 0 {
                    return slot.done.take().filter(|d| d.0 == sequence);
                }
            }
            std::thread::sleep(DETERMINISTIC_POLL);
        }
    }
}

/// How often a deterministic session checks for its segmentation.
const DETERMINISTIC_POLL: Duration = Duration::from_millis(1);
#[cfg(test)]
mod tests {
    use std::sync::mpsc;

    use stillmap_perception::segment::{Instance, NO_INSTANCE};

    use super::*;

    /// A segmenter that makes one instance whose class is the frame's first byte,
    /// records every batch it ran (the first bytes), and can wait for a permit per batch.
    struct Fake {
        batches: mpsc::Sender<Vec<u8>>,
        permits: Option<mpsc::Receiver<()>>,
        max_batch: usize,
    }

    impl Segmenter for Fake {
        fn segment(&mut self, rgb: &[u8], width: u32, height: u32) -> Result<Segmentation, PerceptionError> {
            let mut seg = Segmentation::empty(width, height);
            seg.instance_map[0] = 1;
            seg.instances.push(Instance {
                id: 1,
                class_id: u16::from(rgb[0]),
                class_name: format!("c{}", rgb[0]),
                score: 1.0,
                bbox: [0.0; 4],
                pixels: 1,
            });
            assert_eq!(seg.instance_map[1], NO_INSTANCE);
            Ok(seg)
        }
        fn segment_batch(&mut self, frames: &[RgbFrame<'_>]) -> Result<Vec<Segmentation>, PerceptionError> {
            if let Some(permits) = &self.permits {
                permits.recv().map_err(|_| PerceptionError::Runtime("no permit".into()))?;
            }
            let _ = self.batches.send(frames.iter().map(|f| f.rgb[0]).collect());
            frames.iter().map(|f| self.segment(f.rgb, f.width, f.height)).collect()
        }
        fn max_batch(&self) -> usize {
            self.max_batch
        }
        fn class_names(&self) -> &[String] {
            &[]
        }
        fn device(&self) -> &str {
            "fake"
        }
    }

    fn config(max_batch: usize, delay_ms: u64) -> PerceptionConfig {
        let mut c = PerceptionConfig::default();
        c.segmentation.max_batch = max_batch;
        c.segmentation.max_queue_delay_ms = delay_ms;
        c
    }

    fn frame(first: u8) -> ColorImage {
        let mut data = vec![0; 4 * 2 * 3];
        data[0] = first;
        ColorImage { width: 4, height: 2, data }
    }

    fn wait_for(client: &SegmentationClient) -> Finished {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if let Some(f) = client.take() {
                return f;
            }
            assert!(Instant::now() < deadline, "no segmentation within 10 s");
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// Frames of three sessions run as one batch; each result returns to its own
    /// session and frame.
    #[test]
    fn a_batch_of_several_sessions_returns_each_result_to_its_own() {
        let (tx, batches) = mpsc::channel();
        let fake = Fake { batches: tx, permits: None, max_batch: usize::MAX };
        let service = SegmentationService::with_segmenters(vec![Box::new(fake)], &config(4, 33), Arc::default()).expect("service");
        assert_eq!(service.max_batch(), 4);
        let clients: Vec<_> = (0..3).map(|_| service.client()).collect();
        for (i, c) in clients.iter().enumerate() {
            c.submit(100 + i as u64, &frame(10 + i as u8));
        }
        for (i, c) in clients.iter().enumerate() {
            let (sequence, seg, _) = wait_for(c);
            assert_eq!(sequence, 100 + i as u64, "session {i} gets its own frame's result");
            assert_eq!(seg.instances[0].class_id, 10 + i as u16, "and its own pixels' segmentation");
        }
        let batches: Vec<Vec<u8>> = batches.try_iter().collect();
        // The worker waits up to 33 ms for a full batch: the three frames, submitted
        // together, ran as one batch mixing the sessions.
        assert_eq!(batches.len(), 1, "{batches:?}");
        let mut seen = batches[0].clone();
        seen.sort_unstable();
        assert_eq!(seen, [10, 11, 12], "every frame segmented once");
        drop(clients);
        service.close();
    }

    /// Records its warm-up and fails a frame segmented before it.
    struct Warming {
        warmed: Arc<Mutex<Vec<usize>>>,
        done: bool,
        fail: bool,
    }

    impl Segmenter for Warming {
        fn segment(&mut self, _: &[u8], width: u32, height: u32) -> Result<Segmentation, PerceptionError> {
            assert!(self.done, "a frame ran before the warm-up");
            Ok(Segmentation::empty(width, height))
        }
        fn max_batch(&self) -> usize {
            usize::MAX
        }
        fn warm_up(&mut self, max_batch: usize) -> Result<Vec<usize>, PerceptionError> {
            if self.fail {
                return Err(PerceptionError::Runtime("out of device memory".into()));
            }
            lock(&self.warmed).push(max_batch);
            self.done = true;
            Ok(vec![1, 2, 4, 8])
        }
        fn class_names(&self) -> &[String] {
            &[]
        }
        fn device(&self) -> &str {
            "fake"
        }
    }

    /// Every worker warms up for the service's batch limit before it takes a frame,
    /// and a warm-up that fails fails the start with its error.
    #[test]
    fn every_worker_warms_up_before_the_first_frame() {
        let warmed = Arc::new(Mutex::new(Vec::new()));
        let workers =
            (0..2).map(|_| Box::new(Warming { warmed: warmed.clone(), done: false, fail: false }) as Box<dyn Segmenter>).collect();
        let service = SegmentationService::with_segmenters(workers, &config(6, 1), Arc::default()).expect("service");
        assert_eq!(*lock(&warmed), [6, 6], "both workers warmed up for max_batch = 6 before the service started");
        let client = service.client();
        client.submit(1, &frame(0));
        assert_eq!(wait_for(&client).0, 1);
        drop(client);
        service.close();

        let failing: Vec<Box<dyn Segmenter>> = vec![Box::new(Warming { warmed, done: false, fail: true })];
        let e = SegmentationService::with_segmenters(failing, &config(6, 1), Arc::default()).err().expect("start fails");
        assert_eq!(e.to_string(), PerceptionError::Runtime("out of device memory".into()).to_string());
    }

    /// A model with a fixed batch of 1 runs frames one at a time, whatever max_batch says.
    #[test]
    fn a_batch_one_model_never_batches() {
        let (tx, batches) = mpsc::channel();
        let fake = Fake { batches: tx, permits: None, max_batch: 1 };
        let service = SegmentationService::with_segmenters(vec![Box::new(fake)], &config(8, 5), Arc::default()).expect("service");
        assert_eq!(service.max_batch(), 1);
        let clients: Vec<_> = (0..3).map(|_| service.client()).collect();
        for (i, c) in clients.iter().enumerate() {
            c.submit(i as u64, &frame(i as u8));
        }
        for c in &clients {
            wait_for(c);
        }
        assert!(batches.try_iter().all(|b| b.len() == 1));
        drop(clients);
        service.close();
    }

    /// While the model is busy a session's waiting frame is replaced by its newer
    /// one: never more than one frame waits per session, and the result is the newest.
    #[test]
    fn a_waiting_frame_is_replaced_by_the_sessions_newer_one() {
        let (tx, batches) = mpsc::channel();
        let (permit, permits) = mpsc::channel();
        let fake = Fake { batches: tx, permits: Some(permits), max_batch: 1 };
        let metrics: Arc<Metrics> = Arc::default();
        let service = SegmentationService::with_segmenters(vec![Box::new(fake)], &config(1, 0), metrics.clone()).expect("service");
        let client = service.client();
        client.submit(1, &frame(1));
        // The worker has taken frame 1 and waits for a permit.
        let deadline = Instant::now() + Duration::from_secs(10);
        while lock(&service.shared.state).slots.get(&client.id).is_some_and(|s| s.in_flight == 0) {
            assert!(Instant::now() < deadline, "the worker never took frame 1");
            std::thread::sleep(Duration::from_millis(1));
        }
        client.submit(2, &frame(2));
        client.submit(3, &frame(3));
        assert_eq!(lock(&service.shared.state).ready.len(), 1, "one waiting frame for the session");
        permit.send(()).expect("permit");
        assert_eq!(wait_for(&client).0, 1);
        permit.send(()).expect("permit");
        assert_eq!(wait_for(&client).0, 3, "frame 2 was replaced by frame 3");
        let ran: Vec<u8> = batches.try_iter().flatten().collect();
        assert_eq!(ran, [1, 3]);
        assert!(metrics.render().contains("stillmap_segmentation_replaced_total 1"), "{}", metrics.render());
        drop(client);
        service.close();
    }
}
