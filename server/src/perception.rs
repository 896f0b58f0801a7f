//! The perception stage of a session's pipeline, and the segmentation service
//! that all sessions share.
//!
//! Segmentation must not stall tracking: it runs on its own worker threads
//! ([`SegmentationService`], each with its own model). A session hands it a frame
//! only when it has none in flight (so at most one job per session waits: the
//! queue is bounded by the number of sessions) and picks the result up on a later
//! frame; the masker carries it to the current frame through the optical flow and
//! the result says `MASK_SOURCE_WARPED` with the age in frames.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use nalgebra::Isometry3;
use stillmap_perception::{DynamicMasker, Fused, MaskSource, MaskerInput, PerceptionConfig, PerceptionError, Segmentation, Segmenter, YoloSegmenter};
use stillmap_proto::codec::{ColorImage, DepthImage};
use stillmap_proto::pb;

use crate::pipeline::append_stages;
use crate::tracking::camera_of;

/// Stage names of perception, as they appear in results and `/metrics`.
pub mod perception_stage {
    pub const FLOW: &str = "perception_flow";
    pub const WARP: &str = "perception_warp";
    pub const EGO_MOTION: &str = "perception_ego_motion";
    pub const FUSION: &str = "perception_fusion";
    /// Inference time of the segmentation the frame used (on the worker), when it arrived with this frame.
    pub const SEGMENTATION: &str = "segmentation";
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// A finished segmentation: the frame it was computed on, the result, the inference time.
type Finished = (u64, Segmentation, Duration);

struct Job {
    sequence: u64,
    rgb: Vec<u8>,
    width: u32,
    height: u32,
    client: Arc<ClientSlot>,
}

#[derive(Default)]
struct ClientSlot {
    busy: AtomicBool,
    done: Mutex<Option<Finished>>,
}

#[derive(Default)]
struct Queue {
    jobs: VecDeque<Job>,
    closed: bool,
}

/// Segmentation worker threads shared by every session.
pub struct SegmentationService {
    queue: Arc<(Mutex<Queue>, Condvar)>,
    class_names: Vec<String>,
    device: String,
    /// The worker threads, joined by [`close`](Self::close): a worker must not be
    /// inferring while the process tears ONNX Runtime down.
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
}

impl SegmentationService {
    /// Loads one model per worker (start-up fails on any model problem) and starts the workers.
    pub fn start(config: &PerceptionConfig) -> Result<Arc<Self>, PerceptionError> {
        let queue: Arc<(Mutex<Queue>, Condvar)> = Arc::default();
        let mut class_names = Vec::new();
        let mut device = String::new();
        let mut threads = Vec::new();
        for n in 0..config.segmentation.workers {
            let mut segmenter = YoloSegmenter::new(&config.segmentation)?;
            class_names = segmenter.class_names().to_vec();
            device = segmenter.device().to_string();
            let queue = queue.clone();
            let thread = std::thread::Builder::new()
                .name(format!("segmentation-{n}"))
                .spawn(move || worker(&mut segmenter, &queue))
                .map_err(|e| PerceptionError::Runtime(format!("cannot start a segmentation worker: {e}")))?;
            threads.push(thread);
        }
        Ok(Arc::new(Self { queue, class_names, device, threads: Mutex::new(threads) }))
    }

    pub fn class_names(&self) -> &[String] {
        &self.class_names
    }

    pub fn device(&self) -> &str {
        &self.device
    }

    fn client(self: &Arc<Self>) -> SegmentationClient {
        SegmentationClient { service: self.clone(), slot: Arc::default() }
    }

    /// Stops the workers once the jobs already queued are done, and waits for them.
    /// Call it after the sessions' workers have stopped (a deterministic session
    /// waits for its jobs).
    pub fn close(&self) {
        lock(&self.queue.0).closed = true;
        self.queue.1.notify_all();
        for thread in std::mem::take(&mut *lock(&self.threads)) {
            if thread.join().is_err() {
                tracing::warn!("a segmentation worker panicked");
            }
        }
    }
}

fn worker(segmenter: &mut YoloSegmenter, queue: &(Mutex<Queue>, Condvar)) {
    loop {
        let job = {
            let mut q = lock(&queue.0);
            loop {
                if let Some(job) = q.jobs.pop_front() {
                    break job;
                }
                if q.closed {
                    return;
                }
                q = queue.1.wait(q).unwrap_or_else(|p| p.into_inner());
            }
        };
        let t = Instant::now();
        match segmenter.segment(&job.rgb, job.width, job.height) {
            Ok(seg) => *lock(&job.client.done) = Some((job.sequence, seg, t.elapsed())),
            Err(e) => tracing::warn!(sequence = job.sequence, "segmentation failed: {e}"),
        }
        job.client.busy.store(false, Ordering::Release);
    }
}

/// One session's link to the segmentation service.
struct SegmentationClient {
    service: Arc<SegmentationService>,
    slot: Arc<ClientSlot>,
}

impl SegmentationClient {
    /// Hands a frame to the service unless this session already has one in flight.
    fn submit(&self, sequence: u64, color: &ColorImage) {
        if self.slot.busy.swap(true, Ordering::AcqRel) {
            return;
        }
        let job = Job { sequence, rgb: color.data.clone(), width: color.width, height: color.height, client: self.slot.clone() };
        lock(&self.service.queue.0).jobs.push_back(job);
        self.service.queue.1.notify_one();
    }

    fn take(&self) -> Option<Finished> {
        lock(&self.slot.done).take()
    }

    /// Segments a frame and waits for the result (deterministic mode).
    fn segment_now(&self, sequence: u64, color: &ColorImage) -> Option<Finished> {
        // Nothing is in flight in this mode: every job is waited for.
        self.submit(sequence, color);
        while self.slot.busy.load(Ordering::Acquire) {
            std::thread::sleep(DETERMINISTIC_POLL);
        }
        self.take()
    }
}

/// How often a deterministic session checks for its segmentation.
const DETERMINISTIC_POLL: Duration = Duration::from_millis(1);

/// One session's perception state.
pub struct SessionPerception {
    masker: DynamicMasker,
    segmentation: Option<SegmentationClient>,
    policy_mask: Option<Vec<u8>>,
    segmentation_time: Option<Duration>,
    /// The last finished frame's fused mask.
    fused: Option<Fused>,
    /// Deterministic mode: (every, delay), the frames seen, and results held back
    /// until their release frame.
    deterministic: Option<(u32, u32)>,
    frames: u64,
    held: VecDeque<(u64, Finished)>,
}

impl SessionPerception {
    pub fn new(camera: &pb::CameraInfo, config: &PerceptionConfig, service: Option<&Arc<SegmentationService>>) -> Result<Self, PerceptionError> {
        let names = service.map(|s| s.class_names().to_vec()).unwrap_or_default();
        let masker = DynamicMasker::new(camera_of(camera), config.clone(), &names)?;
        let seg = &config.segmentation;
        let deterministic = (seg.deterministic_every_frames > 0).then_some((seg.deterministic_every_frames, seg.deterministic_delay_frames));
        Ok(Self {
            masker,
            segmentation: service.map(|s| s.client()),
            policy_mask: None,
            segmentation_time: None,
            fused: None,
            deterministic,
            frames: 0,
            held: VecDeque::new(),
        })
    }

    /// First phase: returns the mask tracking must use for this frame.
    pub fn prepare(&mut self, sequence: u64, color: &ColorImage, depth: &DepthImage) -> Option<&[u8]> {
        self.fused = None;
        let index = self.frames;
        self.frames += 1;
        let finished = match (&self.segmentation, self.deterministic) {
            (Some(client), Some((every, delay))) => {
                if index.is_multiple_of(u64::from(every))
                    && let Some(f) = client.segment_now(sequence, color)
                {
                    self.held.push_back((index + u64::from(delay), f));
                }
                match self.held.front() {
                    Some((release, _)) if *release <= index => self.held.pop_front().map(|(_, f)| f),
                    _ => None,
                }
            }
            (Some(client), None) => {
                let finished = client.take();
                client.submit(sequence, color);
                finished
            }
            (None, _) => None,
        };
        self.segmentation_time = finished.as_ref().map(|f| f.2);
        let input = MaskerInput {
            sequence,
            rgb: &color.data,
            depth: &depth.data,
            segmentation: finished.map(|(k, seg, _)| (k, seg)),
            motion_prior: None,
        };
        match self.masker.prepare(input) {
            Ok(mask) => {
                self.policy_mask = Some(mask);
                self.policy_mask.as_deref()
            }
            Err(e) => {
                tracing::warn!(sequence, "perception failed: {e}");
                self.policy_mask = None;
                None
            }
        }
    }

    /// Second phase, after tracking: fuses with the tracked motion and writes the
    /// counts, instances and stage times into `result`.
    pub fn finish(
        &mut self,
        result: &mut pb::FrameResult,
        depth: &DepthImage,
        previous_from_current: Option<Isometry3<f64>>,
        dynamic_features: u32,
    ) -> Option<&'static str> {
        self.policy_mask.take()?;
        let out = match self.masker.finish(&depth.data, previous_from_current) {
            Ok(out) => out,
            Err(e) => {
                tracing::warn!(sequence = result.sequence, "perception failed: {e}");
                return None;
            }
        };
        let (source, label, age) = match out.source {
            MaskSource::None => (pb::MaskSource::None, "none", 0),
            MaskSource::Fresh => (pb::MaskSource::Fresh, "fresh", 0),
            MaskSource::Warped { age_frames } => (pb::MaskSource::Warped, "warped", age_frames),
        };
        let counts = result.counts.get_or_insert_with(pb::FrameCounts::default);
        counts.dynamic_fraction = out.dynamic_fraction;
        counts.dynamic_features = dynamic_features;
        counts.mask_source = source as i32;
        counts.mask_age_frames = age;
        result.instances = out
            .fused
            .instances
            .iter()
            .map(|i| pb::DetectedInstance {
                class_id: u32::from(i.class_id),
                class_name: i.class_name.clone(),
                score: i.score,
                prior_dynamic: i.prior_dynamic,
                moving: i.moving == Some(true),
                pixels: i.pixels,
                bbox: i.bbox.to_vec(),
            })
            .collect();
        let t = out.times;
        let mut stages = vec![
            (perception_stage::FLOW, t.flow),
            (perception_stage::WARP, t.warp),
            (perception_stage::EGO_MOTION, t.ego_motion),
            (perception_stage::FUSION, t.fusion),
        ];
        if let Some(d) = self.segmentation_time.take() {
            stages.push((perception_stage::SEGMENTATION, d));
        }
        append_stages(result, &stages, t.total);
        self.fused = Some(out.fused);
        Some(label)
    }

    /// Pixels of the last finished frame that must stay out of the map (nonzero):
    /// dynamic and prior-dynamic. `None` when perception failed on it.
    pub fn map_exclusion(&self) -> Option<Vec<u8>> {
        self.fused.as_ref().map(Fused::mapping_mask)
    }

    /// The segmentation class per pixel in the current frame (fresh or warped), if any.
    pub fn class_map(&self) -> Option<Vec<u16>> {
        self.fused.as_ref()?;
        self.masker.segmentation().map(|s| s.class_map())
    }
}
