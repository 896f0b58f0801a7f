//! Every tunable of perception, with its documented default.
//!
//! Defaults hold for any indoor RGB-D camera at VGA resolution and 15–30 Hz; none
//! is fitted to a particular clip. Flow thresholds are in pixels of the full-size
//! image so they do not change meaning with `flow.subsample`.

use serde::{Deserialize, Serialize};

/// Perception configuration (`[perception]` in the server's TOML).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PerceptionConfig {
    /// Run perception at all; off means tracking gets an all-static mask.
    pub enabled: bool,
    pub segmentation: SegmentationConfig,
    pub flow: FlowConfig,
    pub ego_motion: EgoMotionConfig,
    pub fusion: FusionConfig,
}

/// Where segmentation runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ExecutionProvider {
    /// ONNX Runtime's CPU provider.
    Cpu,
    /// NVIDIA CUDA (needs the GPU build of ONNX Runtime, CUDA 13 and cuDNN 9, driver 580+:
    /// `make gpu-deps`). Start-up fails when it cannot run, unless `fallback_to_cpu`.
    Cuda,
    /// NVIDIA TensorRT, CUDA for the nodes it does not take; engines are cached in
    /// `tensorrt_cache_dir` (the first start builds them: minutes).
    Tensorrt,
}

impl ExecutionProvider {
    pub fn name(self) -> &'static str {
        match self {
            Self::Cpu => "cpu",
            Self::Cuda => "cuda",
            Self::Tensorrt => "tensorrt",
        }
    }
}

/// Keyframes followed for retraction, at most (each costs 5 bytes per flow cell).
pub const MAX_RETRACT_KEYFRAMES: usize = 64;
/// Largest `perception.segmentation.max_batch`.
pub const MAX_SEGMENTATION_BATCH: usize = 64;
/// Largest `perception.segmentation.max_queue_delay_ms`: a batch waits at most a frame interval.
pub const MAX_QUEUE_DELAY_MS: u64 = 33;
/// The longest baseline (`ego_motion.baseline_frames`): its flows and images are kept.
pub const MAX_BASELINE_FRAMES: u32 = 30;

/// Instance segmentation (YOLOv8-seg style ONNX model).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentationConfig {
    /// Run the segmenter (off: flow alone decides, every pixel is prior-static).
    pub enabled: bool,
    /// Path of the ONNX model. Empty: the server looks for
    /// `../shared/models/yolov8n-seg_fp32_640.onnx` beside its working directory
    /// and `STILLMAP_MODEL`. The weights are not part of stillmap (AGPL-3.0).
    pub model_path: String,
    /// Path of `libonnxruntime.so`; empty: `ORT_DYLIB_PATH`.
    pub onnxruntime_library: String,
    /// Square input side in pixels; 0 takes it from the model (640 and 320 files both work).
    pub input_size: u32,
    /// Detections scoring below this are dropped (class score, 0–1).
    pub score_threshold: f32,
    /// Class-aware non-maximum suppression: boxes of one class overlapping more than this IoU merge.
    pub nms_iou_threshold: f32,
    /// Mask probability above which a pixel belongs to its instance.
    pub mask_threshold: f32,
    /// Most instances kept per frame (highest scores first).
    pub max_instances: usize,
    /// ONNX Runtime intra-op threads per worker (0: ONNX Runtime's default, one per
    /// core). 1 by default so that on a small CPU segmentation leaves the other
    /// cores to the session pipelines (tracking must never wait for it).
    pub intra_threads: usize,
    /// Where inference runs: "cpu" (default), "cuda" or "tensorrt".
    pub execution_provider: ExecutionProvider,
    /// With a GPU provider that cannot run: false (default) fails at start-up naming
    /// the problem; true runs on the CPU with a warning.
    pub fallback_to_cpu: bool,
    /// The GPU the provider runs on (CUDA device ordinal).
    pub device_id: i32,
    /// TensorRT's engine and timing cache folder.
    pub tensorrt_cache_dir: String,
    /// Server: most frames (of different sessions) one inference runs together. Only
    /// a model with a symbolic batch dimension batches (deploy/make-batched-model.py);
    /// with the shipped batch-1 files every frame runs alone. On a GPU provider each
    /// worker keeps one session per padded batch shape (1, 2, 4, … up to `max_batch`,
    /// made and run once at start-up): on a small GPU, a lower `max_batch` needs less
    /// of its memory (a start that runs out names the batch size).
    pub max_batch: usize,
    /// Server: how long a worker holding fewer than `max_batch` frames waits for
    /// more before it runs them (Triton's `max_queue_delay`), in milliseconds.
    pub max_queue_delay_ms: u64,
    /// Class names that are dynamic a priori (they may move by themselves).
    /// Default: person, the COCO animals and vehicles.
    pub prior_dynamic_classes: Vec<String>,
    /// Server: segmentation worker threads shared by all sessions (each owns a model).
    pub workers: usize,
    /// Server: niceness of the segmentation worker threads (Linux, 0..=19). On a
    /// CPU that segments, tracking and segmentation compete for the cores; a nice
    /// worker takes what the tracking paths leave (masks then get older and are
    /// carried by the flow meanwhile). 0 = the same priority as tracking.
    pub worker_nice: i32,
    /// A segmentation is carried forward through the flow for at most this many
    /// frames; older, it is dropped and flow alone decides until a new one arrives.
    pub max_mask_age_frames: u32,
    /// A prior-dynamic instance (a person) the segmenter stops finding is kept,
    /// carried by the flow, for up to this many frames after its last detection:
    /// detectors miss a partly hidden or unusual person for many frames in a row,
    /// and a missed person must neither be mapped nor feed the camera's motion.
    /// A new detection overlapping it takes over. 0 disables it.
    pub track_coast_frames: u32,
    /// A *person* (the class named "person") seen moving is a vertical body at
    /// most this tall (metres) standing where his latest points are: the pixels
    /// whose 3D points fall in that upright cylinder (his points' horizontal
    /// spread plus 0.05 m, at least 0.4 m and at most 0.45 m in radius) are kept
    /// out of the map, so legs the detector never saw stay out while he stands. Needs the accelerometer
    /// (`accel_in_camera` on the frames) for the up direction. 0 disables it.
    pub person_height_m: f32,
    /// Server: 0 (default) runs segmentation beside the pipeline, its results used
    /// whenever they are ready — the real-time mode, whose masks (and so poses)
    /// depend on thread timing. n > 0 makes a session reproducible: every n-th
    /// frame is segmented while the pipeline waits, and the result is handed to
    /// the masker `deterministic_delay_frames` frames later, as if it had taken
    /// that long. For evaluations and tests, not for robots.
    pub deterministic_every_frames: u32,
    pub deterministic_delay_frames: u32,
}

/// Dense optical flow (OpenCV Farneback) on a subsampled grey image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FlowConfig {
    /// Integer subsampling of the image before flow (2: 640×480 → 320×240; the paper subsamples too).
    pub subsample: u32,
    /// Farneback pyramid scale between levels (< 1).
    pub pyr_scale: f64,
    /// Farneback pyramid levels.
    pub levels: i32,
    /// Farneback averaging window (pixels of the subsampled image).
    pub winsize: i32,
    /// Farneback iterations per level.
    pub iterations: i32,
    /// Farneback polynomial neighbourhood (5 or 7).
    pub poly_n: i32,
    /// Farneback Gaussian σ for the polynomial fit (1.1 for poly_n 5, 1.5 for 7).
    pub poly_sigma: f64,
}

/// Ego-motion compensation: the camera's own motion explains most flow; only
/// what is left over (the residual) can mean motion in the world.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EgoMotionConfig {
    /// Spacing (pixels of the subsampled image) of the flow samples the camera
    /// motion is refined from.
    pub sample_step: u32,
    /// Flow noise σ in full-size pixels (Farneback on real images: about one pixel).
    pub flow_sigma_px: f64,
    /// Depth noise model σ_z = a + b·z² (metres): the constant part a …
    pub depth_sigma_a_m: f64,
    /// … and the quadratic part b (1/m); Kinect-type structured light ≈ 0.0015–0.003.
    pub depth_sigma_b_per_m: f64,
    /// A pixel has residual flow when its residual exceeds this many σ (flow
    /// noise and the depth uncertainty propagated into the predicted flow) …
    pub residual_sigmas: f64,
    /// … and at least this many full-size pixels.
    pub min_residual_px: f64,
    /// Nearest and farthest depth (metres) used; others have no predicted flow.
    pub min_depth_m: f64,
    pub max_depth_m: f64,
    /// Samples with valid depth needed to refine the motion; fewer: the prior is used alone.
    pub min_samples: usize,
    /// Flow is trusted for the refinement only where the image has texture: the
    /// smaller eigenvalue of the 3×3 structure tensor, as a mean squared gradient in
    /// (grey levels per flow pixel)², must reach this.
    pub min_texture: f64,
    /// Photometric confirmation: a pixel with residual flow counts as moving only
    /// if its 3×3 patch, looked up where the camera motion alone would have put it
    /// in the previous image, differs from it by more than this mean absolute
    /// zero-mean difference (grey levels). Textureless surfaces, where Farneback's
    /// flow is unconstrained, pass this test and stay static.
    pub photometric_threshold: f64,
    /// … and by more than this factor times the difference under the measured flow
    /// (the flow must explain the pixel better than the camera motion does).
    pub photometric_ratio: f64,
    /// Refine the prior camera motion on the flow (off: use it as it is).
    pub refine_tracked_motion: bool,
    /// Compensate before tracking, with the previous frame's camera motion as the
    /// prediction (refined on the flow), so that the tracking mask holds this
    /// frame's own dynamic pixels (objects entering the view, the first frames,
    /// sudden starts) besides the previous frame's; the tracked motion then only
    /// re-decides the labels when it disagrees and leaves fewer pixels moving.
    /// Off: compensation waits for the tracked motion, and tracking uses the
    /// previous frame's mask alone.
    pub before_tracking: bool,
    /// What the flow saw moving (cells dynamic in two frames in a row, any class)
    /// is remembered in 3D for this many frames, and kept out of the camera-motion
    /// estimate wherever the measured surface still lies on it: a thing of no known
    /// class that moved, then rests, does not vote for the camera's motion when it
    /// is picked up again. Tracking and the map are not affected. 0: off.
    pub remember_moved_frames: u32,
    /// When more than this share of the flow cells was labelled moving in the
    /// previous frame (carried into this one and dilated, as they are kept out),
    /// that verdict does not keep them (nor the remembered movers) out of this
    /// frame's camera-motion estimate; only prior-dynamic instances stay
    /// out. The estimate assumes most of the view is static: a camera motion
    /// misjudged at the onset of a mover covering half the view labels the room
    /// moving, and a room kept out of the estimate cannot win it back. 1: off.
    pub moving_majority_share: f64,
    /// A refinement of the prior (the constant-velocity prediction; the tracked
    /// motion when `before_tracking` is off) must leave more than this share fewer
    /// flow cells moving than the prior itself to win, where the prior leaves 1 %
    /// of the vote cells or more moving: a camera moves smoothly, and a refinement
    /// that a large mover pulled to its own motion explains about as much of the
    /// view as the prediction does (the crowd scene's onsets: 7 % fewer). 0: the
    /// fewest moving cells win (the default). At 0.1 (measured) the crowd scene's
    /// rpy_b as built goes from 7.11 to 2.75 cm, but over its twelve arrangements
    /// the mean only from 5.56 to 5.30 cm, worse on the rpy clip (1.85 → 2.01 cm),
    /// and the board scene's from 2.72 to 2.76 cm; object-free runs are unchanged
    /// (docs/people.md, "The crowd"). Off by default: it helps one arrangement.
    pub refinement_margin: f64,
    /// Movers are also looked for over this many frames (the flows composed):
    /// one frame's flow cannot tell the camera's motion from that of a large
    /// textured thing that starts moving (a sideways step with a compensating turn
    /// explains the far background within the flow's noise), several frames'
    /// parallax can. What moved over the baseline is kept out of this frame's
    /// camera-motion estimate, and labelled moving when the per-frame motion
    /// disagrees with the baseline's. 0 or 1: off; at most 30.
    pub baseline_frames: u32,
    /// The frame interval (seconds) the flow's noise (`flow_sigma_px`,
    /// `min_residual_px`) holds for. A step spanning n such intervals (frames
    /// dropped on the way, a slower camera; from the frames' capture times) scales
    /// both n-fold: Farneback's error grows with the displacement it measures.
    pub frame_interval_s: f64,
}

/// How a prior-dynamic instance (a person, say) that does not move is treated by tracking.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PriorDynamicTracking {
    /// Never track on prior-dynamic classes.
    AlwaysExclude,
    /// Exclude them only while their instance moves (a parked car, a seated person may
    /// help), and while their motion is unknown (no flow yet, or a camera motion the
    /// flow did not confirm, with no confirmed judgement on the frame before).
    ExcludeWhileMoving,
}

/// Fusion of segmentation and residual flow into the dynamic/static mask.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FusionConfig {
    /// 3×3 neighbourhood test: a pixel carries flow when at least this many of the
    /// 9 pixels around it (itself included) have residual flow.
    pub neighbourhood_votes: u32,
    /// An instance moves when at least this fraction of its pixels with a
    /// predicted flow carry residual flow.
    pub instance_moving_fraction: f64,
    /// Only an instance's pixels within this fraction of its median depth take part
    /// in that judgement: its mask spills over its outline onto what stands in front
    /// of it or behind it, and a thing moving there (a board carried in front of a
    /// monitor) must not make the whole instance move. 0 lets every pixel take part.
    pub instance_depth_gate: f64,
    /// Flow-only dynamic regions smaller than this (full-size pixels) are noise.
    pub min_region_px: u32,
    /// A flow-only region grows over neighbouring pixels whose depth is within this
    /// fraction of the region's own (an object moves as a whole; its still-looking
    /// inner texture belongs to it). 0 disables growing.
    pub region_depth_ratio: f64,
    /// Flow-only regions wider than this fraction of the image are rejected as an
    /// ego-motion failure rather than reported as motion.
    pub max_region_fraction: f64,
    pub prior_dynamic_tracking: PriorDynamicTracking,
    /// Keep flow-only dynamic regions (moving pixels outside any segmented
    /// instance, e.g. an object no class covers) out of tracking too; they are
    /// always kept out of mapping. Off: only segmented instances are masked for
    /// tracking (for cameras whose flow is too poor to trust).
    pub flow_regions_in_tracking_mask: bool,
    /// The dynamic cells tracking avoids are dilated by this radius (full-size
    /// pixels): the previous frame's are carried by the flow, this frame's come from
    /// a flow grid at 1/subsample, and the strongest corners of a moving object sit
    /// on its outline, where either is least exact.
    pub tracking_mask_dilation_px: u32,
    /// Before that dilation, the dynamic cells tracking avoids grow over neighbouring
    /// cells that continue their surface in depth (within `region_depth_ratio` of the
    /// cell grown from), up to this distance (full-size pixels) from the cells the
    /// flow flagged: an object moves as a whole, while the flow flags its textured
    /// and fast-moving parts, so its features sit up to a few tens of pixels inside
    /// or beside the flagged cells. Only the tracking mask grows (mapping labels and
    /// instance decisions do not); a depth edge stops it. 0 disables growing.
    pub tracking_mask_growth_px: u32,
    /// The pixels kept out of the map (dynamic and prior-dynamic labels) grow over
    /// the surfaces they lie on, in depth-continuous 4-neighbour steps, up to this
    /// many full-size pixels: the labels miss an object's rim and its feet where
    /// they meet the floor, and those must not be fused. 0 disables growing.
    pub mapping_mask_growth_px: u32,
    /// After growing, the kept-out pixels are dilated by this radius (full-size
    /// pixels), across depth edges too: the outline of a mask is where it is least
    /// exact. 0 disables it.
    pub mapping_mask_dilation_px: u32,
    /// Recent keyframes whose pixels are followed through the flow: when a pixel
    /// that a keyframe fused is later seen moving (a person the segmenter missed or
    /// found late, a box that rested and moves on), that keyframe's samples there
    /// leave the map. At most this many keyframes (the map's `refuse_window` keeps
    /// the samples; a keyframe it no longer holds is skipped). 0 disables it.
    pub retract_keyframes: usize,
    /// A keyframe is followed for at most this many frames after it was made.
    pub retract_horizon_frames: u32,
}

impl PerceptionConfig {
    /// Rejects values perception cannot run with; the message names the key.
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn validate(&self) -> Result<(), String> {
        let s = &self.segmentation;
        if s.input_size != 0 && (!s.input_size.is_multiple_of(32) || s.input_size > 2048) {
            return Err(format!("perception.segmentation.input_size must be 0 or a multiple of 32 up to 2048, got {}", s.input_size));
        }
        for (k, v) in
            [("score_threshold", s.score_threshold), ("nms_iou_threshold", s.nms_iou_threshold), ("mask_threshold", s.mask_threshold)]
        {
            if !(v > 0.0 && v < 1.0) {
                return Err(format!("perception.segmentation.{k} must be in (0, 1), got {v}"));
            }
        }
        if s.max_instances == 0 || s.max_instances > usize::from(u16::MAX) {
            return Err("perception.segmentation.max_instances must be in 1..=65535".into());
        }
        if !(0.0..=3.0).contains(&s.person_height_m) {
            return Err(format!("perception.segmentation.person_height_m must be in 0..=3 m, got {}", s.person_height_m));
        }
        if s.max_mask_age_frames == 0 {
            return Err("perception.segmentation.max_mask_age_frames must be at least 1".into());
        }
        if s.deterministic_every_frames > 0 && s.deterministic_delay_frames >= s.max_mask_age_frames {
            return Err("perception.segmentation.deterministic_delay_frames must be below max_mask_age_frames".into());
        }
        if !(1..=64).contains(&s.workers) {
            return Err(format!("perception.segmentation.workers must be within 1..=64 (each loads the model), got {}", s.workers));
        }
        if s.intra_threads > 1024 {
            return Err(format!("perception.segmentation.intra_threads must be within 0..=1024, got {}", s.intra_threads));
        }
        if !(0..=19).contains(&s.worker_nice) {
            return Err(format!("perception.segmentation.worker_nice must be in 0..=19, got {}", s.worker_nice));
        }
        if !(1..=MAX_SEGMENTATION_BATCH).contains(&s.max_batch) {
            return Err(format!("perception.segmentation.max_batch must be in 1..={MAX_SEGMENTATION_BATCH}, got {}", s.max_batch));
        }
        if s.max_queue_delay_ms > MAX_QUEUE_DELAY_MS {
            return Err(format!(
                "perception.segmentation.max_queue_delay_ms must be at most {MAX_QUEUE_DELAY_MS}, got {}",
                s.max_queue_delay_ms
            ));
        }
        if s.device_id < 0 {
            return Err(format!("perception.segmentation.device_id must be 0 or more, got {}", s.device_id));
        }
        if s.execution_provider == ExecutionProvider::Tensorrt && s.tensorrt_cache_dir.is_empty() {
            return Err("perception.segmentation.tensorrt_cache_dir must name a folder with execution_provider = \"tensorrt\"".into());
        }
        let f = &self.flow;
        if !(1..=8).contains(&f.subsample) {
            return Err(format!("perception.flow.subsample must be in 1..=8, got {}", f.subsample));
        }
        let flow_ok = f.pyr_scale > 0.0
            && f.pyr_scale < 1.0
            && (1..=10).contains(&f.levels)
            && (3..=101).contains(&f.winsize)
            && (1..=20).contains(&f.iterations);
        if !flow_ok {
            return Err(format!(
                "perception.flow: pyr_scale must be within (0, 1), levels within 1..=10, winsize within 3..=101 and iterations within 1..=20, got {}, {}, {} and {}",
                f.pyr_scale, f.levels, f.winsize, f.iterations
            ));
        }
        if !(f.poly_sigma > 0.0 && f.poly_sigma <= 5.0) {
            return Err(format!("perception.flow.poly_sigma must be within (0, 5], got {}", f.poly_sigma));
        }
        if f.poly_n != 5 && f.poly_n != 7 {
            return Err(format!("perception.flow.poly_n must be 5 or 7, got {}", f.poly_n));
        }
        let e = &self.ego_motion;
        if e.sample_step == 0 {
            return Err("perception.ego_motion.sample_step must be at least 1".into());
        }
        if !(e.frame_interval_s > 0.0 && e.frame_interval_s <= 1.0) {
            return Err(format!("perception.ego_motion.frame_interval_s must be in (0, 1], got {}", e.frame_interval_s));
        }
        if !(0.0..1.0).contains(&e.refinement_margin) {
            return Err(format!("perception.ego_motion.refinement_margin must be in [0, 1), got {}", e.refinement_margin));
        }
        if !(e.moving_majority_share > 0.0 && e.moving_majority_share <= 1.0) {
            return Err(format!("perception.ego_motion.moving_majority_share must be in (0, 1], got {}", e.moving_majority_share));
        }
        if e.baseline_frames > MAX_BASELINE_FRAMES {
            return Err(format!("perception.ego_motion.baseline_frames must be at most {MAX_BASELINE_FRAMES}, got {}", e.baseline_frames));
        }
        if !(e.flow_sigma_px > 0.0 && e.residual_sigmas > 0.0 && e.min_residual_px >= 0.0) {
            return Err("perception.ego_motion: flow_sigma_px and residual_sigmas must be positive, min_residual_px ≥ 0".into());
        }
        if !(e.depth_sigma_a_m >= 0.0 && e.depth_sigma_b_per_m >= 0.0) {
            return Err("perception.ego_motion: depth noise terms must be ≥ 0".into());
        }
        if !(e.min_depth_m > 0.0 && e.max_depth_m > e.min_depth_m) {
            return Err("perception.ego_motion.min_depth_m must be positive and below max_depth_m".into());
        }
        if !(e.min_texture >= 0.0 && e.photometric_threshold >= 0.0 && e.photometric_ratio >= 1.0) {
            return Err("perception.ego_motion: min_texture and photometric_threshold must be ≥ 0, photometric_ratio ≥ 1".into());
        }
        if e.min_samples < 6 {
            return Err("perception.ego_motion.min_samples must be at least 6".into());
        }
        let u = &self.fusion;
        if !(1..=9).contains(&u.neighbourhood_votes) {
            return Err(format!("perception.fusion.neighbourhood_votes must be in 1..=9, got {}", u.neighbourhood_votes));
        }
        if !(u.instance_moving_fraction > 0.0 && u.instance_moving_fraction <= 1.0) {
            return Err("perception.fusion.instance_moving_fraction must be in (0, 1]".into());
        }
        if !(u.instance_depth_gate >= 0.0 && u.instance_depth_gate < 1.0) {
            return Err(format!("perception.fusion.instance_depth_gate must be in [0, 1), got {}", u.instance_depth_gate));
        }
        if !(u.region_depth_ratio >= 0.0 && u.region_depth_ratio < 1.0) {
            return Err("perception.fusion.region_depth_ratio must be in [0, 1)".into());
        }
        if u.tracking_mask_growth_px > 256 {
            return Err(format!("perception.fusion.tracking_mask_growth_px must be at most 256, got {}", u.tracking_mask_growth_px));
        }
        if u.mapping_mask_growth_px > 256 {
            return Err(format!("perception.fusion.mapping_mask_growth_px must be at most 256, got {}", u.mapping_mask_growth_px));
        }
        if u.mapping_mask_dilation_px > 64 {
            return Err(format!("perception.fusion.mapping_mask_dilation_px must be at most 64, got {}", u.mapping_mask_dilation_px));
        }
        if u.retract_keyframes > MAX_RETRACT_KEYFRAMES {
            return Err(format!(
                "perception.fusion.retract_keyframes must be at most {MAX_RETRACT_KEYFRAMES}, got {}",
                u.retract_keyframes
            ));
        }
        if u.tracking_mask_dilation_px > 64 {
            return Err(format!("perception.fusion.tracking_mask_dilation_px must be at most 64, got {}", u.tracking_mask_dilation_px));
        }
        if !(u.max_region_fraction > 0.0 && u.max_region_fraction <= 1.0) {
            return Err("perception.fusion.max_region_fraction must be in (0, 1]".into());
        }
        Ok(())
    }
}

/// COCO names (Ultralytics spelling) that are dynamic a priori: person, vehicles, animals.
pub const DEFAULT_PRIOR_DYNAMIC: &[&str] = &[
    "person",
    "bicycle",
    "car",
    "motorcycle",
    "airplane",
    "bus",
    "train",
    "truck",
    "boat",
    "bird",
    "cat",
    "dog",
    "horse",
    "sheep",
    "cow",
    "elephant",
    "bear",
    "zebra",
    "giraffe",
];

impl Default for PerceptionConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            segmentation: SegmentationConfig::default(),
            flow: FlowConfig::default(),
            ego_motion: EgoMotionConfig::default(),
            fusion: FusionConfig::default(),
        }
    }
}

impl Default for SegmentationConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            model_path: String::new(),
            onnxruntime_library: String::new(),
            input_size: 0,
            score_threshold: 0.25,
            nms_iou_threshold: 0.45,
            mask_threshold: 0.5,
            max_instances: 100,
            intra_threads: 1,
            execution_provider: ExecutionProvider::Cpu,
            fallback_to_cpu: false,
            device_id: 0,
            tensorrt_cache_dir: "stillmap-data/tensorrt".into(),
            max_batch: 8,
            max_queue_delay_ms: 2,
            prior_dynamic_classes: DEFAULT_PRIOR_DYNAMIC.iter().map(|s| (*s).to_string()).collect(),
            workers: 1,
            worker_nice: 0,
            max_mask_age_frames: 15,
            track_coast_frames: 60,
            person_height_m: 2.0,
            deterministic_every_frames: 0,
            deterministic_delay_frames: 0,
        }
    }
}

impl Default for FlowConfig {
    fn default() -> Self {
        Self { subsample: 3, pyr_scale: 0.5, levels: 3, winsize: 13, iterations: 3, poly_n: 5, poly_sigma: 1.1 }
    }
}

impl Default for EgoMotionConfig {
    fn default() -> Self {
        Self {
            sample_step: 6,
            flow_sigma_px: 1.0,
            depth_sigma_a_m: 0.002,
            depth_sigma_b_per_m: 0.003,
            residual_sigmas: 3.0,
            min_residual_px: 2.0,
            min_depth_m: 0.3,
            max_depth_m: 6.0,
            min_samples: 50,
            min_texture: 9.0,
            photometric_threshold: 4.0,
            photometric_ratio: 2.0,
            refine_tracked_motion: true,
            before_tracking: true,
            remember_moved_frames: 90,
            moving_majority_share: 0.5,
            refinement_margin: 0.0,
            baseline_frames: 4,
            frame_interval_s: 1.0 / 30.0,
        }
    }
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            neighbourhood_votes: 5,
            instance_moving_fraction: 0.2,
            instance_depth_gate: 0.15,
            min_region_px: 400,
            region_depth_ratio: 0.05,
            max_region_fraction: 0.5,
            prior_dynamic_tracking: PriorDynamicTracking::ExcludeWhileMoving,
            flow_regions_in_tracking_mask: true,
            tracking_mask_dilation_px: 8,
            tracking_mask_growth_px: 12,
            mapping_mask_growth_px: 12,
            mapping_mask_dilation_px: 4,
            retract_keyframes: 12,
            retract_horizon_frames: 90,
        }
    }
}
