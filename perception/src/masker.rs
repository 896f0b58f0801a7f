//! The per-session perception state machine: flow to the previous frame,
//! ego-motion compensation, the latest segmentation carried to the current frame,
//! and the fused dynamic/static mask.
//!
//! Segmentation runs elsewhere (its own worker, see the server) and arrives when
//! it is ready, tagged with the frame it was computed on. A result for the current
//! frame is used as is (`Fresh`); an older one, or the last one when nothing new
//! came, is carried forward through the stored flows (`Warped`, with its age).

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Point3, Vector3};
use stillmap_tracking::Camera;
use stillmap_tracking::geometry::{frame_intervals, scale_motion};

use crate::PerceptionError;
use crate::config::{PerceptionConfig, PriorDynamicTracking};
use crate::ego::{CONSISTENT, EgoMotion, EgoResult, FrameSamples, RESIDUAL};
use crate::flow::{FlowField, SmallGray, farneback};
use crate::fusion::{Fused, PixelLabel, cell_centres, dynamic_fraction, fuse, grow_over_depth};
use crate::origins::{KeyframeOrigins, Retraction};
use crate::segment::Segmentation;
use crate::warp::{warp_grid, warp_segmentation};

/// Where the frame's segmentation came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MaskSource {
    /// No segmentation available: flow alone decided.
    None,
    /// Segmented on this very frame.
    Fresh,
    /// An earlier frame's segmentation, warped by the flow; `age_frames` frames old.
    Warped { age_frames: u32 },
}

/// One frame for the masker.
pub struct MaskerInput<'a> {
    pub sequence: u64,
    /// When the frame was captured (nanoseconds; 0: unknown, and a flow step then
    /// spans as many frame intervals as sequence numbers).
    pub capture_time_ns: u64,
    /// RGB8, `width × height × 3`.
    pub rgb: &'a [u8],
    /// Raw depth, `width × height`, 0 = no reading.
    pub depth: &'a [u16],
    /// A segmentation finished since the last frame: the sequence of the frame it
    /// was computed on, and the result.
    pub segmentation: Option<(u64, Segmentation)>,
    /// The camera motion `previous_from_current` ([`process`](DynamicMasker::process)
    /// only; the two-phase API takes the tracked motion in `finish`).
    pub motion_prior: Option<Isometry3<f64>>,
    /// The accelerometer at this frame, in the camera frame (m/s²; at rest it points
    /// up): the up direction of a person's body (`segmentation.person_height_m`).
    pub accel_in_camera: Option<Vector3<f64>>,
}

/// Time per perception stage on one frame.
#[derive(Debug, Clone, Copy, Default)]
pub struct MaskTimes {
    pub flow: Duration,
    pub ego_motion: Duration,
    pub warp: Duration,
    pub fusion: Duration,
    /// Wall time of `prepare` and `finish` together (tracking between them not
    /// included): the stages plus the little between them.
    pub total: Duration,
}

/// What the masker made of one frame.
#[derive(Debug, Clone)]
pub struct MaskOutput {
    pub fused: Fused,
    pub source: MaskSource,
    /// The frame the segmentation in use was computed on.
    pub segmentation_sequence: Option<u64>,
    /// Ego-motion compensation of this frame (none on the first frame).
    pub ego: Option<EgoSummary>,
    /// Fraction of valid-depth pixels that are dynamic or prior-dynamic.
    pub dynamic_fraction: f32,
    /// Cells of recent keyframes that show moving things in this frame (see [`crate::origins`]).
    pub retractions: Vec<Retraction>,
    pub times: MaskTimes,
}

#[derive(Debug, Clone, Copy)]
pub struct EgoSummary {
    pub previous_from_current: Isometry3<f64>,
    pub refined: bool,
    pub samples: usize,
    pub inliers: usize,
}

struct FlowStep {
    from: u64,
    to: u64,
    /// Frame intervals (`ego_motion.frame_interval_s`) the step spans, from the
    /// capture times (else the sequence numbers): more than one after drops.
    intervals: f64,
    flow: FlowField,
}

struct Carried {
    segmentation: Segmentation,
    source_sequence: u64,
    at_sequence: u64,
    /// The prior-dynamic instances (see `track_coast_frames`).
    tracks: Vec<Track>,
}

/// A prior-dynamic instance over time.
#[derive(Debug, Clone)]
struct Track {
    /// Its id in the carried segmentation.
    id: u16,
    /// The frame it was last detected on (a coasting instance keeps its detection's).
    detected_at: u64,
    /// Median depth of its pixels, metres.
    depth_m: Option<f32>,
    class_id: u16,
    score: f32,
    /// Where it was last seen, in the pose chain's frame.
    points: Option<TrackPoints>,
    /// Seen moving at some frame (a detection that takes it over inherits this).
    moved: bool,
    /// A person who moved, once coasting: the upright volume his body stands in.
    body: Option<Body>,
}

/// An upright cylinder in the pose chain's frame: where a person's body is, from
/// the part of him that was seen (`segmentation.person_height_m`).
#[derive(Debug, Clone, Copy)]
struct Body {
    epoch: u32,
    /// Unit vectors: up, and two horizontal axes.
    up: Vector3<f64>,
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    /// The axis' horizontal position along `e1`, `e2`.
    centre: (f64, f64),
    radius_m: f64,
    /// Lowest and highest height along `up` the body may take.
    heights: (f64, f64),
}

impl Body {
    /// The volume a body at most `height_m` tall takes when `points` are part of it:
    /// their horizontal spread (90th percentile from their median) plus
    /// [`BODY_MARGIN_M`], at least [`MIN_BODY_RADIUS_M`] and at most
    /// [`MAX_BODY_RADIUS_M`]; vertically every placement
    /// of the body that contains the points. `None` with fewer than
    /// [`MIN_BODY_POINTS`] points.
    fn around(epoch: u32, points: &[[f32; 3]], up: Vector3<f64>, height_m: f64) -> Option<Self> {
        if points.len() < MIN_BODY_POINTS {
            return None;
        }
        let up = up.try_normalize(1e-9)?;
        let helper = if up.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let e1 = up.cross(&helper).normalize();
        let e2 = up.cross(&e1);
        let centre = horizontal_median(points, &e1, &e2)?;
        let p = |q: &[f32; 3]| stored_point(q).coords;
        let mut spread: Vec<f64> =
            points.iter().map(|q| ((p(q).dot(&e1) - centre.0).powi(2) + (p(q).dot(&e2) - centre.1).powi(2)).sqrt()).collect();
        spread.sort_by(f64::total_cmp);
        let p90 = spread[(spread.len() * 9 / 10).min(spread.len() - 1)];
        let radius_m = (p90 + BODY_MARGIN_M).clamp(MIN_BODY_RADIUS_M, MAX_BODY_RADIUS_M);
        let (lo, hi) = points.iter().map(|q| p(q).dot(&up)).fold((f64::MAX, f64::MIN), |(lo, hi), h| (lo.min(h), hi.max(h)));
        let extra = (height_m - (hi - lo)).max(0.0);
        Some(Self { epoch, up, e1, e2, centre, radius_m, heights: (lo - extra, hi + extra) })
    }

    /// Moves the axis towards the median of `points` (horizontally), by at most
    /// `max_step_m`; too few points leave it.
    fn follow(&mut self, points: &[[f32; 3]], max_step_m: f64) {
        if points.len() < MIN_BODY_POINTS {
            return;
        }
        let Some((x, y)) = horizontal_median(points, &self.e1, &self.e2) else { return };
        let (dx, dy) = (x - self.centre.0, y - self.centre.1);
        let d = (dx * dx + dy * dy).sqrt();
        let k = if d > max_step_m { max_step_m / d } else { 1.0 };
        self.centre = (self.centre.0 + k * dx, self.centre.1 + k * dy);
    }

    fn contains(&self, p: &Point3<f64>) -> bool {
        let v = p.coords;
        let h = v.dot(&self.up);
        let (dx, dy) = (v.dot(&self.e1) - self.centre.0, v.dot(&self.e2) - self.centre.1);
        h >= self.heights.0 && h <= self.heights.1 && dx * dx + dy * dy <= self.radius_m * self.radius_m
    }
}

/// A track point as stored (`f32`, the pose chain's frame).
fn stored_point(p: &[f32; 3]) -> Point3<f64> {
    Point3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
}

/// The median of `points` along the horizontal axes `e1` and `e2`.
fn horizontal_median(points: &[[f32; 3]], e1: &Vector3<f64>, e2: &Vector3<f64>) -> Option<(f64, f64)> {
    let mut xs: Vec<f32> = points.iter().map(|q| stored_point(q).coords.dot(e1) as f32).collect();
    let mut ys: Vec<f32> = points.iter().map(|q| stored_point(q).coords.dot(e2) as f32).collect();
    Some((f64::from(median(&mut xs)?), f64::from(median(&mut ys)?)))
}

#[derive(Debug, Clone)]
struct TrackPoints {
    /// The pose chain's epoch the points are expressed in.
    epoch: u32,
    /// Pixel spacing of the grid they were sampled on.
    spacing_px: u32,
    points: Vec<[f32; 3]>,
    /// The first `fresh` points were sampled on the latest frame (the rest are
    /// remembered from earlier ones, where the person may have stood elsewhere).
    fresh: usize,
}

/// The camera's pose chained from the tracked motions: `anchor_from_camera` at
/// frame `sequence`, the last per-frame motion, and an epoch that changes
/// whenever the chain breaks (tracking lost).
#[derive(Debug, Clone, Copy)]
struct PoseChain {
    sequence: u64,
    anchor_from_camera: Isometry3<f64>,
    motion: Isometry3<f64>,
    epoch: u32,
}

/// Per-camera perception state.
pub struct DynamicMasker {
    camera: Camera,
    config: PerceptionConfig,
    ego: EgoMotion,
    prior_dynamic: Vec<bool>,
    /// The last finished frame: sequence, capture time (ns, 0: unknown) and image.
    previous: Option<(u64, u64, SmallGray)>,
    flows: VecDeque<FlowStep>,
    carried: Option<Carried>,
    last_ego: Option<EgoResult>,
    /// Frame intervals the last result's motion spans: more than one after drops.
    last_ego_frames: f64,
    /// The last finished frame's dynamic flow-grid cells (1 = dynamic); `None` when
    /// that frame had no camera motion the flow confirmed (nothing on it was judged
    /// for sure), or, with `ego_motion.refine_tracked_motion` off, no prior taken as
    /// it was.
    dynamic_grid: Option<(u64, Vec<u8>)>,
    /// A prepared frame waiting for `finish`.
    pending: Option<Pending>,
    /// Recent keyframes' pixels, followed through the flow.
    origins: KeyframeOrigins,
    class_names: Vec<String>,
    /// Prior-dynamic tracks out of view (see `track_coast_frames`).
    offscreen: Vec<Track>,
    chain: Option<PoseChain>,
    epochs: u32,
    /// The accelerometer's direction in the pose chain's frame, decaying sum over
    /// recent frames (motion accelerations average out), with its epoch.
    up: Option<(u32, Vector3<f64>)>,
    /// What the flow saw moving (`ego_motion.remember_moved_frames`): points in the
    /// pose chain's frame, with its epoch and the frame they were seen on, oldest first.
    moved: VecDeque<(u32, u64, [f32; 3])>,
    /// Recent flow images and the chosen camera motion of the step ending at each
    /// (`previous_from_current`), for the baseline (`ego_motion.baseline_frames`).
    recent_images: VecDeque<(u64, SmallGray, Vec<f32>)>,
    recent_motions: VecDeque<(u64, Isometry3<f64>)>,
}

struct Pending {
    sequence: u64,
    capture_time_ns: u64,
    small: SmallGray,
    previous: Option<SmallGray>,
    /// Flow-grid cells the ego-motion estimate ignores.
    exclude: Vec<u8>,
    /// Compensation, labels and their dynamic flow-grid cells computed before
    /// tracking (`ego_motion.before_tracking`).
    early: Option<(EgoResult, Fused, Vec<u8>)>,
    /// Flow-grid cells that moved over the baseline (`ego_motion.baseline_frames`).
    baseline: Option<Baseline>,
    /// The previous frame's dynamic flow-grid cells carried into this frame.
    carried_cells: Option<Vec<u8>>,
    times: MaskTimes,
}

impl DynamicMasker {
    /// `class_names` are the segmenter's (indexed by class id); the configured
    /// prior-dynamic names are looked up in them.
    pub fn new(camera: Camera, config: PerceptionConfig, class_names: &[String]) -> Result<Self, PerceptionError> {
        config.validate().map_err(PerceptionError::Config)?;
        let s = config.flow.subsample as usize;
        if (camera.width as usize) < 8 * s || (camera.height as usize) < 8 * s {
            return Err(PerceptionError::Config(format!("image {}x{} is too small for flow at 1/{s}", camera.width, camera.height)));
        }
        let prior_dynamic = class_names.iter().map(|n| config.segmentation.prior_dynamic_classes.iter().any(|p| p == n)).collect();
        let ego = EgoMotion::new(camera.clone(), config.ego_motion.clone(), config.flow.subsample);
        let origins = KeyframeOrigins::new(config.fusion.retract_keyframes, u64::from(config.fusion.retract_horizon_frames));
        Ok(Self {
            camera,
            config,
            ego,
            prior_dynamic,
            previous: None,
            flows: VecDeque::new(),
            carried: None,
            last_ego: None,
            last_ego_frames: 1.0,
            dynamic_grid: None,
            pending: None,
            origins,
            class_names: class_names.to_vec(),
            offscreen: Vec::new(),
            chain: None,
            epochs: 0,
            up: None,
            moved: VecDeque::new(),
            recent_images: VecDeque::new(),
            recent_motions: VecDeque::new(),
        })
    }

    /// The last finished frame is keyframe `id` (the caller's id, as the map knows
    /// it): its pixels are followed from now on (see [`crate::origins`]).
    pub fn note_keyframe(&mut self, id: u64) {
        if let Some((sequence, _, _)) = &self.previous {
            let (gw, gh) = self.ego.grid_size();
            self.origins.note(id, *sequence, gw * gh);
        }
    }

    /// The pixels of `fused` (a frame of depth `depth`) the map must not take:
    /// dynamic and prior-dynamic labels, grown over the surfaces they stand on
    /// (4-neighbour steps that continue the depth, `mapping_mask_growth_px`) and
    /// dilated (`mapping_mask_dilation_px`), so an object's rim, its feet on the
    /// floor and the pixels the labels miss at its outline are not fused either.
    pub fn mapping_mask(&self, fused: &Fused, depth: &[u16]) -> Result<Vec<u8>, PerceptionError> {
        let mask = fused.mapping_mask();
        let (w, h) = (fused.width, fused.height);
        if depth.len() != w * h {
            return Err(PerceptionError::Input(format!("depth has {} pixels, the labels {}", depth.len(), w * h)));
        }
        if !mask.contains(&1) {
            return Ok(mask);
        }
        let f = &self.config.fusion;
        let mask = if f.mapping_mask_growth_px > 0 {
            let scale = (1.0 / self.camera.depth_units_per_metre) as f32;
            let depth_m: Vec<f32> = depth.iter().map(|&d| f32::from(d) * scale).collect();
            let mut inside: Vec<bool> = mask.iter().map(|&m| m != 0).collect();
            grow_over_depth(&mut inside, &depth_m, w, h, f.region_depth_ratio, f.mapping_mask_growth_px as usize, |_| true);
            inside.into_iter().map(u8::from).collect()
        } else {
            mask
        };
        dilate(mask, w, h, f.mapping_mask_dilation_px)
    }

    /// The segmentation in the current frame's coordinates, if any.
    pub fn segmentation(&self) -> Option<&Segmentation> {
        self.carried.as_ref().map(|c| &c.segmentation)
    }

    /// The last frame's ego-motion classification on the flow grid.
    pub fn last_ego(&self) -> Option<&EgoResult> {
        self.last_ego.as_ref()
    }

    /// Processes one frame in one go: [`prepare`](Self::prepare), then
    /// [`finish`](Self::finish) with `input.motion_prior` as the camera motion.
    pub fn process(&mut self, input: MaskerInput<'_>) -> Result<MaskOutput, PerceptionError> {
        let motion = input.motion_prior;
        let depth = input.depth;
        self.prepare(input)?;
        self.finish(depth, motion)
    }

    /// The camera motion (`previous_from_current`) the prepared frame's own labels
    /// were made under, when the flow confirmed it (`ego_motion.before_tracking`):
    /// a refinement on the flow, or the constant-velocity prediction (from the
    /// masker's last motion, which the tracked one may have replaced) when no
    /// refinement beat it. For diagnostics.
    pub fn prepared_motion(&self) -> Option<Isometry3<f64>> {
        let (ego, _, _) = self.pending.as_ref()?.early.as_ref()?;
        ego.confirmed.then_some(ego.previous_from_current)
    }

    /// First phase of a frame (frames in increasing sequence order): flow to the
    /// previous frame, the segmentation carried to this frame, with
    /// `ego_motion.before_tracking` this frame's own labels under the predicted
    /// motion refined on the flow, and the mask tracking should use now: this
    /// frame's dynamic pixels (when the flow confirmed the motion) and the previous
    /// frame's carried by the flow, plus prior-dynamic instances where the policy
    /// (or not knowing yet) says so. Track the frame with it, then call
    /// [`finish`](Self::finish) with the tracked camera motion.
    pub fn prepare(&mut self, input: MaskerInput<'_>) -> Result<Vec<u8>, PerceptionError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if input.rgb.len() != w * h * 3 {
            return Err(PerceptionError::Input(format!("colour has {} bytes, expected {} ({w}x{h}x3)", input.rgb.len(), w * h * 3)));
        }
        if input.depth.len() != w * h {
            return Err(PerceptionError::Input(format!("depth has {} pixels, expected {} ({w}x{h})", input.depth.len(), w * h)));
        }
        if let Some((k, seg)) = &input.segmentation {
            if *k > input.sequence {
                return Err(PerceptionError::Input(format!("segmentation of frame {k} arrived before frame {} itself", input.sequence)));
            }
            if (seg.width, seg.height) != (self.camera.width, self.camera.height) || seg.instance_map.len() != w * h {
                return Err(PerceptionError::Input(format!("segmentation is {}x{}, expected {w}x{h}", seg.width, seg.height)));
            }
        }
        let started = Instant::now();
        let mut times = MaskTimes::default();
        let s = self.config.flow.subsample;

        let t = Instant::now();
        let small = SmallGray::from_rgb(input.rgb, w, h, s)?;
        let previous = self.previous.take().filter(|(prev_seq, _, _)| *prev_seq < input.sequence);
        let flow = match &previous {
            Some((prev_seq, prev_time_ns, prev)) => {
                let intervals = Some(*prev_time_ns)
                    .filter(|&t| t > 0)
                    .and_then(|t| frame_intervals(t, input.capture_time_ns, self.config.ego_motion.frame_interval_s))
                    .unwrap_or((input.sequence - *prev_seq) as f64);
                Some(FlowStep { from: *prev_seq, to: input.sequence, intervals, flow: farneback(&small, prev, &self.config.flow, s)? })
            }
            None => None,
        };
        times.flow = t.elapsed();

        let t = Instant::now();
        let max_age = u64::from(self.config.segmentation.max_mask_age_frames);
        // The previous frame's dynamic cells, carried into this frame by the flow
        // and dilated (the tracking mask is a frame old, and an object's strongest
        // corners sit on its outline, where the carried mask is least exact).
        let (gw, gh) = self.ego.grid_size();
        let radius_cells = self.config.fusion.tracking_mask_dilation_px.div_ceil(s);
        let carried_cells = match (&flow, self.dynamic_grid.take()) {
            (Some(step), Some((at, grid))) if at == step.from => Some(warp_grid(&grid, &step.flow)),
            _ => None,
        };
        let carried_dynamic = carried_cells.clone().map(|g| dilate(g, gw, gh, radius_cells)).transpose()?;
        match &flow {
            Some(step) => {
                // Carry the last segmentation forward one frame.
                if let Some(c) = self.carried.take_if(|c| c.at_sequence == step.from) {
                    self.carried =
                        Some(Carried { segmentation: warp_segmentation(&c.segmentation, &step.flow), at_sequence: step.to, ..c });
                }
            }
            None => {
                self.flows.clear();
                self.carried = None;
            }
        }
        match &flow {
            Some(step) => self.origins.advance(step.from, step.to, &step.flow),
            None => self.origins.clear(),
        }
        if let Some(step) = flow {
            self.flows.push_back(step);
            while self.flows.len() > (max_age as usize).max(self.config.ego_motion.baseline_frames as usize) {
                self.flows.pop_front();
            }
        }
        // Up, in the pose chain's frame, for the bodies of coasting people.
        if let (Some(a), Some((epoch, anchor_from_camera))) = (input.accel_in_camera, self.predicted_pose(input.sequence))
            && let Some(u) = a.try_normalize(1e-6)
        {
            let u = anchor_from_camera.rotation * u;
            self.up = Some(match self.up {
                Some((e, sum)) if e == epoch => (e, sum * UP_DECAY + u),
                _ => (epoch, u),
            });
        }
        if let Some((k, seg)) = input.segmentation {
            let newer = self.carried.as_ref().is_none_or(|c| c.source_sequence < k);
            if newer && let Some(seg) = self.carry_to(k, seg, input.sequence) {
                let (segmentation, tracks) = self.keep_coasting(seg, k, input.sequence, input.depth);
                self.carried = Some(Carried { segmentation, source_sequence: k, at_sequence: input.sequence, tracks });
            }
        }
        self.carried.take_if(|c| input.sequence - c.source_sequence > max_age || c.at_sequence != input.sequence);

        // What the camera-motion estimate must not listen to (and, below, what moved
        // over the baseline).
        let mut exclude = self.vote_exclusion(carried_dynamic.as_deref(), input.sequence, input.depth);
        // Constant velocity over the frames this step spans (more than one after drops).
        let step_frames = self.latest_step(input.sequence).map_or(1.0, |step| step.intervals);
        let factor = step_frames / self.last_ego_frames.max(1.0);
        let predicted = self.last_ego.as_ref().map(|e| scale_motion(&e.previous_from_current, factor));
        times.warp = t.elapsed();
        let t = Instant::now();
        // This frame's flow-grid depth and texture, shared by the baseline and the compensation.
        let frame = self.latest_step(input.sequence).map(|_| self.ego.frame_samples(&small, input.depth));
        let baseline = frame.as_ref().and_then(|f| self.baseline_movers(input.sequence, &small, f, predicted, &exclude));
        if let Some(b) = &baseline {
            exclude.iter_mut().zip(&b.moving).for_each(|(e, &m)| *e |= m);
        }
        times.ego_motion += t.elapsed();

        // This frame's own labels, before tracking: compensation with the previous
        // frame's motion as the prediction (constant velocity), refined on the flow.
        let early = if self.config.ego_motion.before_tracking {
            let t = Instant::now();
            let ego = frame
                .and_then(|f| self.compensate(input.sequence, &small, previous.as_ref().map(|(_, _, p)| p), f, predicted, &exclude))
                .map(|e| self.with_movers(e, baseline.as_ref()));
            times.ego_motion += t.elapsed();
            ego.map(|ego| {
                let t = Instant::now();
                let fused = fuse(
                    w,
                    h,
                    s as usize,
                    Some(&ego),
                    self.carried.as_ref().map(|c| &c.segmentation),
                    &self.prior_dynamic,
                    &self.config.fusion,
                );
                let cells = self.dynamic_cells(&fused.labels);
                times.fusion += t.elapsed();
                (ego, fused, cells)
            })
        } else {
            None
        };
        // The tracking mask counts as fusion.
        let t = Instant::now();
        // Only a motion the flow confirmed (a refinement with enough inliers, or
        // the prediction when no refinement beat it in the vote) labels pixels for tracking:
        // an unchecked prediction (no refinement held: a sudden acceleration,
        // motion blur) can call most of the scene moving and starve the tracker.
        let persistent = carried_cells.clone();
        let seeds = match (&early, carried_cells) {
            (Some((ego, _, cells)), carried) if ego.confirmed => Some(match carried {
                Some(c) => cells.iter().zip(&c).map(|(&a, &b)| a | b).collect(),
                None => cells.clone(),
            }),
            (_, carried) => carried,
        };
        // Grown over the objects' surfaces (the flow flags an object's textured,
        // fast-moving parts; its features sit inside and beside them), then dilated.
        let growth_cells = self.config.fusion.tracking_mask_growth_px.div_ceil(s) as usize;
        let tracking_dynamic = match seeds {
            Some(seeds) if growth_cells > 0 && seeds.contains(&1) => {
                let grown = match &early {
                    Some((ego, _, _)) => {
                        grow_over_surfaces(seeds, &ego.depth_m, gw, gh, growth_cells, self.config.fusion.region_depth_ratio)
                    }
                    None => grow_over_surfaces(
                        seeds,
                        &self.ego.sample_depth(input.depth),
                        gw,
                        gh,
                        growth_cells,
                        self.config.fusion.region_depth_ratio,
                    ),
                };
                Some(dilate(grown, gw, gh, radius_cells)?)
            }
            Some(seeds) => Some(dilate(seeds, gw, gh, radius_cells)?),
            None => None,
        };

        // The mask for tracking this frame.
        let policy = self.config.fusion.prior_dynamic_tracking;
        let flow_regions = self.config.fusion.flow_regions_in_tracking_mask;
        let instance_map = self.carried.as_ref().map(|c| &c.segmentation.instance_map);
        let mut mask = vec![0u8; w * h];
        if let Some(grid) = tracking_dynamic.as_ref().filter(|g| g.iter().any(|&v| v != 0)) {
            let su = s as usize;
            let cell_of_column: Vec<usize> = (0..w).map(|x| (x / su).min(gw - 1)).collect();
            for (y, row) in mask.chunks_exact_mut(w).enumerate() {
                let grid_row = &grid[(y / su).min(gh - 1) * gw..][..gw];
                match (flow_regions, instance_map) {
                    (true, _) => row.iter_mut().zip(&cell_of_column).for_each(|(m, &cx)| *m = u8::from(grid_row[cx] != 0)),
                    // Without flow regions, only dynamic pixels of segmented instances.
                    (false, Some(map)) => {
                        for ((m, &cx), &id) in row.iter_mut().zip(&cell_of_column).zip(&map[y * w..(y + 1) * w]) {
                            *m = u8::from(id != 0 && grid_row[cx] != 0);
                        }
                    }
                    (false, None) => {}
                }
            }
        }
        if let Some(c) = &self.carried {
            // Still prior-dynamic instances are excluded by policy, or while their motion is unknown.
            let exclude_still = policy == PriorDynamicTracking::AlwaysExclude || tracking_dynamic.is_none();
            for (m, &id) in mask.iter_mut().zip(&c.segmentation.instance_map) {
                if id != 0 && exclude_still && self.is_prior_dynamic(&c.segmentation, id) {
                    *m = 1;
                }
            }
        }
        times.fusion += t.elapsed();
        times.total = started.elapsed();
        self.pending = Some(Pending {
            sequence: input.sequence,
            capture_time_ns: input.capture_time_ns,
            small,
            previous: previous.map(|(_, _, p)| p),
            exclude,
            early,
            baseline,
            carried_cells: persistent,
            times,
        });
        Ok(mask)
    }

    /// Second phase (labels already made in `prepare`: re-decided only when the
    /// tracked motion disagrees and leaves fewer pixels moving; otherwise):
    /// ego-motion compensation with the camera motion
    /// `previous_from_current` (the tracker's, from the static features; `None`
    /// when tracking failed: the flow refines identity then), and fusion into this
    /// frame's labels. `depth` is the frame's, as given to `prepare`.
    pub fn finish(&mut self, depth: &[u16], previous_from_current: Option<Isometry3<f64>>) -> Result<MaskOutput, PerceptionError> {
        let Some(Pending { sequence, capture_time_ns, small, previous, exclude, early, baseline, carried_cells, mut times }) =
            self.pending.take()
        else {
            return Err(PerceptionError::Input("finish called without prepare".into()));
        };
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if depth.len() != w * h {
            return Err(PerceptionError::Input(format!("depth has {} pixels, expected {} ({w}x{h})", depth.len(), w * h)));
        }
        let s = self.config.flow.subsample;
        let started = Instant::now();
        let t = Instant::now();
        let (ego, fused) = match early {
            // Labelled before tracking: the tracked motion re-decides only when it
            // disagrees and leaves fewer pixels moving.
            Some((early_ego, early_fused, early_cells)) => {
                let better = match (self.latest_step(sequence), &previous, previous_from_current) {
                    (Some(step), Some(prev), Some(tracked)) => {
                        self.ego.reconsider(&step.flow, &small, prev, &early_ego, &tracked, Some(&exclude), step.intervals)
                    }
                    _ => None,
                };
                times.ego_motion += t.elapsed();
                match better {
                    Some(ego) => (Some(self.with_movers(ego, baseline.as_ref())), None),
                    None => (Some(early_ego), Some((early_fused, early_cells))),
                }
            }
            None => {
                let frame = self.ego.frame_samples(&small, depth);
                let ego = self
                    .compensate(sequence, &small, previous.as_ref(), frame, previous_from_current, &exclude)
                    .map(|e| self.with_movers(e, baseline.as_ref()));
                times.ego_motion += t.elapsed();
                (ego, None)
            }
        };
        // What the baseline needs: the images and the chosen motions of the last frames.
        let keep = self.config.ego_motion.baseline_frames as usize;
        if keep > 1 {
            // The flow-grid depth compensation sampled from this frame's depth already.
            let depth_m = ego.as_ref().map_or_else(|| self.ego.sample_depth(depth), |e| e.depth_m.clone());
            self.recent_images.push_back((sequence, small.clone(), depth_m));
            if let Some(e) = &ego {
                self.recent_motions.push_back((sequence, e.previous_from_current));
            }
            while self.recent_images.len() > keep + 1 {
                self.recent_images.pop_front();
            }
            while self.recent_motions.front().is_some_and(|(q, _)| *q + keep as u64 + 1 < sequence) {
                self.recent_motions.pop_front();
            }
        }
        self.previous = Some((sequence, capture_time_ns, small));
        // The pose chain: broken (a new epoch) when tracking gave no motion.
        self.chain = match (self.chain.take(), previous_from_current) {
            (Some(c), Some(m)) if c.sequence < sequence => {
                let motion = scale_motion(&m, 1.0 / (sequence - c.sequence) as f64);
                Some(PoseChain { sequence, anchor_from_camera: c.anchor_from_camera * m, motion, ..c })
            }
            _ => {
                self.offscreen.clear();
                self.epochs = self.epochs.wrapping_add(1);
                Some(PoseChain { sequence, anchor_from_camera: Isometry3::identity(), motion: Isometry3::identity(), epoch: self.epochs })
            }
        };

        let t = Instant::now();
        let (mut fused, cells) = match fused {
            Some(labelled) => labelled,
            None => {
                let segmentation = self.carried.as_ref().map(|c| &c.segmentation);
                let fused = fuse(w, h, s as usize, ego.as_ref(), segmentation, &self.prior_dynamic, &self.config.fusion);
                let cells = self.dynamic_cells(&fused.labels);
                (fused, cells)
            }
        };
        // People's bodies (`segmentation.person_height_m`) leave the map, not tracking:
        // labelled after the tracking mask and the dynamic cells were made.
        self.label_bodies(&mut fused.labels, sequence, depth);
        let dynamic_fraction = dynamic_fraction(&fused.labels, depth);
        if let Some(c) = self.carried.as_mut() {
            for t in &mut c.tracks {
                t.moved |= fused.instances.iter().any(|i| i.id == t.id && i.moving == Some(true));
            }
        }
        self.remember_moved(&fused.labels, carried_cells.as_deref(), sequence, depth);
        // Without a camera motion the flow confirmed (the first frame, the first after
        // a break in the flow, or one where no refinement held and the tracked motion
        // did not win the vote in `reconsider`) nothing was judged moving or still for
        // sure: its grid carried into the next frame would read as a verdict there
        // ("nothing moves", "he stands"), and a next frame whose own motion the flow
        // does not confirm would then track on the people it cannot judge. Nor is
        // anything then remembered as moving twice, nor retracted as dynamic twice, on
        // the next frame. A prior the configuration takes as it is
        // (`ego_motion.refine_tracked_motion` off) is unchecked by choice: its verdict
        // is carried (identity left where no prior was given and no refinement held
        // is not).
        let refine = self.config.ego_motion.refine_tracked_motion;
        let judged = ego.as_ref().is_some_and(|e| e.confirmed || (e.from_prior && !refine));
        self.dynamic_grid = judged.then_some((sequence, cells));
        let retractions = if self.origins.is_empty() {
            Vec::new()
        } else {
            // Prior-dynamic cells, and dynamic cells that were dynamic in the previous
            // frame too (under a motion it had confirmed, or a prior taken as it was by
            // configuration; one frame's false motion must not take a keyframe's
            // samples out for good), dilated by one cell.
            let (gw, gh) = self.ego.grid_size();
            let kept_out: Vec<bool> = self
                .cell_centres()
                .enumerate()
                .map(|(g, i)| match fused.labels[i] {
                    l if l == PixelLabel::PriorDynamic as u8 => true,
                    l if l == PixelLabel::Dynamic as u8 => carried_cells.as_ref().is_some_and(|c| c[g] != 0),
                    _ => false,
                })
                .collect();
            let mut moving = kept_out.clone();
            for (g, _) in kept_out.iter().enumerate().filter(|(_, k)| **k) {
                let (x, y) = (g % gw, g / gw);
                for ny in y.saturating_sub(1)..=(y + 1).min(gh - 1) {
                    for nx in x.saturating_sub(1)..=(x + 1).min(gw - 1) {
                        moving[ny * gw + nx] = true;
                    }
                }
            }
            self.origins.retractions(sequence, &moving, gw, s)
        };
        times.fusion += t.elapsed();

        let source = match &self.carried {
            None => MaskSource::None,
            Some(c) if c.source_sequence == sequence => MaskSource::Fresh,
            Some(c) => MaskSource::Warped { age_frames: u32::try_from(sequence - c.source_sequence).unwrap_or(u32::MAX) },
        };
        let summary = ego.as_ref().map(|e| EgoSummary {
            previous_from_current: e.previous_from_current,
            refined: e.refined,
            samples: e.samples,
            inliers: e.inliers,
        });
        if ego.is_some() {
            self.last_ego_frames = self.latest_step(sequence).map_or(1.0, |step| step.intervals);
        }
        self.last_ego = ego;
        times.total += started.elapsed();
        Ok(MaskOutput {
            fused,
            source,
            segmentation_sequence: self.carried.as_ref().map(|c| c.source_sequence),
            ego: summary,
            dynamic_fraction,
            retractions,
            times,
        })
    }

    /// Ego-motion compensation of frame `sequence` against the previous grey image,
    /// when the latest flow step ends at this frame.
    fn compensate(
        &self,
        sequence: u64,
        small: &SmallGray,
        previous: Option<&SmallGray>,
        frame: FrameSamples,
        prior: Option<Isometry3<f64>>,
        exclude: &[u8],
    ) -> Option<EgoResult> {
        match (self.latest_step(sequence), previous) {
            (Some(step), Some(prev)) => {
                Some(self.ego.compensate_sampled(&step.flow, small, prev, frame, prior, Some(exclude), step.intervals))
            }
            _ => None,
        }
    }

    /// Flow-grid cells that moved over the last `ego_motion.baseline_frames` flow
    /// steps (see [`EgoMotion::movers_over_baseline`]); `None` without that many
    /// consecutive steps ending at frame `sequence` or without their first image.
    fn baseline_movers(
        &self,
        sequence: u64,
        small: &SmallGray,
        frame: &FrameSamples,
        predicted: Option<Isometry3<f64>>,
        exclude: &[u8],
    ) -> Option<Baseline> {
        let n = self.config.ego_motion.baseline_frames as usize;
        if n < 2 || self.flows.len() < n {
            return None;
        }
        let steps: Vec<&FlowStep> = self.flows.iter().skip(self.flows.len() - n).collect();
        if steps.last()?.to != sequence || steps.windows(2).any(|w| w[0].to != w[1].from) {
            return None;
        }
        let reference_sequence = steps[0].from;
        let (reference, reference_depth) =
            self.recent_images.iter().find(|(q, _, _)| *q == reference_sequence).map(|(_, g, d)| (g, d.as_slice()))?;
        // Composed back to the reference from the cells the baseline judges (every
        // other one each way); cells whose path leaves the image on the way are not
        // judged (nor sampled).
        let mut later = steps.iter().rev().map(|step| &step.flow);
        let latest = later.next()?;
        let earlier: Vec<&FlowField> = later.collect();
        let (composed, inside) = latest.chain_sparse(&earlier, self.ego.baseline_stride());
        let ignored: Vec<u8> = exclude.iter().zip(&inside).map(|(&e, &ok)| u8::from(e != 0 || !ok)).collect();
        // The chained motions: reference_from_current = m₁ · m₂ · … · mₙ (each step's
        // previous_from_current), the last one predicted.
        let chained = steps[..n - 1]
            .iter()
            .try_fold(Isometry3::identity(), |chain, step| self.recent_motions.iter().find(|(q, _)| *q == step.to).map(|(_, m)| chain * m));
        let starts: Vec<Isometry3<f64>> = chained.map(|c| c * predicted.unwrap_or_else(Isometry3::identity)).into_iter().collect();
        let chained = chained?;
        // The composed flow's noise: each step's, n-fold over its n frame intervals.
        let noise_steps: f64 = steps.iter().map(|step| step.intervals * step.intervals).sum();
        let movers =
            self.ego.movers_over_baseline(&composed, noise_steps, small, reference, frame, reference_depth, &starts, Some(&ignored))?;
        // Judged cells whose path left the image are not movers (each stands for its block).
        let (gw, gh) = self.ego.grid_size();
        let stride = self.ego.baseline_stride();
        let mut moving = movers.moving;
        for y in (0..gh).step_by(stride) {
            for x in (0..gw).step_by(stride).filter(|&x| !inside[y * gw + x]) {
                for row in y..(y + stride).min(gh) {
                    moving[row * gw + x..row * gw + (x + stride).min(gw)].fill(0);
                }
            }
        }
        // The composed flow is least exact along depth and contrast edges (motion
        // blur, disocclusion): thin lines of "movers" there go; a moving thing is a region.
        let moving = open_regions(moving, gw, gh, BASELINE_OPENING_CELLS).ok()?;
        Some(Baseline { moving, reference_from_current: movers.reference_from_current, chained, noise_steps })
    }

    /// `ego` with the cells that moved over the baseline marked as residual flow too
    /// (where a prediction was made), when the baseline's camera motion disagrees
    /// with the per-frame motions chained up to this frame (by more than twice the
    /// composed flow's noise, on average over the scene): one frame's flow was
    /// fooled by a large moving thing, and its labels missed it. When they agree, the
    /// per-frame labels stand (the baseline's are coarser: its flow is composed).
    fn with_movers(&self, mut ego: EgoResult, baseline: Option<&Baseline>) -> EgoResult {
        let Some(b) = baseline else { return ego };
        let implied = b.chained * ego.previous_from_current;
        let noise = self.config.ego_motion.flow_sigma_px * b.noise_steps.sqrt();
        let disagree = self.ego.prediction_gap(&implied, &b.reference_from_current, &ego.depth_m).is_some_and(|gap| gap > 2.0 * noise);
        if disagree {
            for (c, &m) in ego.class.iter_mut().zip(&b.moving) {
                if m != 0 && *c == CONSISTENT {
                    *c = RESIDUAL;
                }
            }
        }
        ego
    }

    /// The latest flow step, when it ends at frame `sequence`.
    fn latest_step(&self, sequence: u64) -> Option<&FlowStep> {
        self.flows.back().filter(|step| step.to == sequence)
    }

    fn is_prior_dynamic(&self, seg: &Segmentation, id: u16) -> bool {
        seg.instance(id).is_some_and(|i| self.prior_dynamic.get(usize::from(i.class_id)).copied().unwrap_or(false))
    }

    /// A new segmentation (of frame `k`, carried to frame `now`, whose depth is
    /// `depth`) with the prior-dynamic instances it missed. A track detected within
    /// `track_coast_frames` of `now` that no new prior-dynamic instance covers for at
    /// least [`COAST_MATCH_FRACTION`] of its pixels keeps its pixels (those no new
    /// prior-dynamic instance claims) under a fresh id: the previous segmentation's
    /// pixels carried by the flow, or, for a track that left the view, its last 3D
    /// points projected at the predicted camera pose (a person the camera turned away
    /// from is still there when it turns back). Only pixels near the track's depth
    /// stay (within [`COAST_DEPTH_GATE`] of the median of its last ones; pixels
    /// without depth stay too): where the flow leaves part of a mask on the
    /// background as the instance walks off, that part does not follow it. Returns
    /// the merged segmentation and its prior-dynamic tracks; tracks with no pixel
    /// now stay in `self.offscreen`.
    fn keep_coasting(&mut self, mut seg: Segmentation, k: u64, now: u64, depth: &[u16]) -> (Segmentation, Vec<Track>) {
        let (w, h) = (seg.width as usize, seg.height as usize);
        let limit = u64::from(self.config.segmentation.track_coast_frames);
        let pose = self.predicted_pose(now);
        let mut tracks: Vec<Track> = Vec::new();
        for i in &seg.instances {
            if self.is_prior_dynamic(&seg, i.id) {
                let pixels: Vec<usize> = bbox_pixels(&i.bbox, w, h).filter(|&p| seg.instance_map[p] == i.id).collect();
                tracks.push(self.track_from(i.id, (i.class_id, i.score), k, (&pixels, &pixels), depth, pose.as_ref(), None));
            }
        }
        let detected = tracks.len();
        let offscreen = std::mem::take(&mut self.offscreen);
        if limit == 0 {
            return (seg, tracks);
        }
        // Candidates: the previous segmentation's tracks with their carried pixels
        // (none when they left the view), and tracks already out of view, projected.
        // (track, pixels carried by the flow or projected from out of view, pixels
        // where its remembered points still lie on the measured surface).
        let mut candidates: Vec<(Track, Vec<usize>, Vec<usize>)> = Vec::new();
        if let Some(prev) = self.carried.as_ref().filter(|c| c.at_sequence == now) {
            for t in &prev.tracks {
                let pixels = prev
                    .segmentation
                    .instance(t.id)
                    .map(|i| bbox_pixels(&i.bbox, w, h).filter(|&p| prev.segmentation.instance_map[p] == t.id).collect())
                    .unwrap_or_default();
                let agreeing = pose.as_ref().map(|p| self.agreeing_pixels(t, p, depth, w, h)).unwrap_or_default();
                candidates.push((t.clone(), pixels, agreeing));
            }
        }
        for t in offscreen {
            let pixels = pose.as_ref().map(|p| self.project_track(&t, p, w, h)).unwrap_or_default();
            candidates.push((t, pixels, Vec::new()));
        }
        let claimed: Vec<bool> = {
            let max = seg.instances.iter().map(|i| usize::from(i.id)).max().unwrap_or(0);
            let mut v = vec![false; max + 1];
            for t in &tracks {
                v[usize::from(t.id)] = true;
            }
            v
        };
        let claimed = |id: u16| claimed.get(usize::from(id)).copied().unwrap_or(false);
        let metres = (1.0 / self.camera.depth_units_per_metre) as f32;
        let depth_of = |i: usize| depth.get(i).filter(|&&d| d != 0).map(|&d| f32::from(d) * metres);
        let mut next_id = seg.instances.iter().map(|i| i.id).max().unwrap_or(0);
        let mut coasted = false;
        for (mut track, sampled, agreeing) in candidates {
            if now.saturating_sub(track.detected_at) > limit {
                continue;
            }
            // A person seen moving, coasting: his body's volume, from the part of him
            // seen so far (kept while he coasts).
            if track.body.is_none() {
                track.body = self.body_of(&track);
            }
            // A standing person the flow's carried mask erodes from is still where his
            // points are: their pixels join the mask (each point marks only its own
            // grid cell, so the mask does not grow from one refresh to the next).
            let pixels: Vec<usize> = if agreeing.is_empty() {
                sampled.clone()
            } else {
                let mut all = sampled.clone();
                all.extend_from_slice(&agreeing);
                all.sort_unstable();
                all.dedup();
                all
            };
            let covered = pixels.iter().filter(|&&i| claimed(seg.instance_map[i])).count();
            if !pixels.is_empty() && covered as f64 >= COAST_MATCH_FRACTION * pixels.len() as f64 {
                // Found again: the new detection takes over, and knows he moved.
                if track.moved {
                    let mut counts = std::collections::HashMap::<u16, usize>::new();
                    for &i in &pixels {
                        if claimed(seg.instance_map[i]) {
                            *counts.entry(seg.instance_map[i]).or_default() += 1;
                        }
                    }
                    if let Some((id, _)) = counts.into_iter().max_by_key(|&(id, n)| (n, id))
                        && let Some(t) = tracks.iter_mut().find(|t| t.id == id)
                    {
                        t.moved = true;
                    }
                }
                continue;
            }
            let near = |i: usize| match (track.depth_m, depth_of(i)) {
                (Some(reference), Some(d)) => (d - reference).abs() <= COAST_DEPTH_GATE * reference,
                _ => true,
            };
            let kept: Vec<usize> = pixels.into_iter().filter(|&i| !claimed(seg.instance_map[i]) && near(i)).collect();
            let sampled: Vec<usize> = sampled.into_iter().filter(|&i| !claimed(seg.instance_map[i]) && near(i)).collect();
            let with_depth = kept.iter().filter(|&&i| depth_of(i).is_some()).count();
            if kept.len() < MIN_COAST_PX || (track.depth_m.is_some() && with_depth == 0) {
                // Out of view (or nothing of it left): remembered by its points.
                if track.points.is_some() && self.offscreen.len() < MAX_OFFSCREEN_TRACKS {
                    self.offscreen.push(track);
                }
                continue;
            }
            let Some(id) = next_id.checked_add(1) else { break };
            next_id = id;
            let mut bbox = [f32::MAX, f32::MAX, f32::MIN, f32::MIN];
            for &i in &kept {
                seg.instance_map[i] = id;
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                bbox = [bbox[0].min(x), bbox[1].min(y), bbox[2].max(x + 1.0), bbox[3].max(y + 1.0)];
            }
            let class_name = self.class_names.get(usize::from(track.class_id)).cloned().unwrap_or_default();
            seg.instances.push(crate::segment::Instance {
                id,
                class_id: track.class_id,
                class_name,
                score: track.score,
                bbox,
                pixels: kept.len() as u32,
            });
            let mut coasting = self.track_from(
                id,
                (track.class_id, track.score),
                track.detected_at,
                (&kept, &sampled),
                depth,
                pose.as_ref(),
                track.points.as_ref(),
            );
            (coasting.moved, coasting.body) = (track.moved, track.body);
            // The body follows him (a walking pace at most per refresh): its axis moves
            // to where his latest points are.
            if let (Some(body), Some(tp)) = (coasting.body.as_mut(), coasting.points.as_ref())
                && tp.epoch == body.epoch
            {
                let frames = now.saturating_sub(self.carried.as_ref().map_or(now, |c| c.source_sequence)).max(1);
                body.follow(&tp.points[..tp.fresh.min(tp.points.len())], BODY_STEP_M_PER_FRAME * frames as f64);
            }
            tracks.push(coasting);
            coasted = true;
        }
        // A detected person who moved (known once a detection took over a track that
        // had): his body too, from the detection's points; the segmenter's mask misses
        // his feet and rim, the body does not.
        for t in tracks.iter_mut().take(detected) {
            if t.moved && t.body.is_none() {
                t.body = self.body_of(t);
            }
        }
        if !coasted {
            return (seg, tracks);
        }
        // Coasting pixels may have been taken from static instances: count again.
        let mut counts = std::collections::HashMap::<u16, u32>::new();
        for &id in &seg.instance_map {
            if id != 0 {
                *counts.entry(id).or_default() += 1;
            }
        }
        seg.instances.retain_mut(|i| match counts.get(&i.id) {
            Some(&n) => {
                i.pixels = n;
                true
            }
            None => false,
        });
        (seg, tracks)
    }

    /// The body of a person who moved (`segmentation.person_height_m`; `None` for
    /// other classes, people who never moved, without an up direction or with too
    /// few points): around his latest frame's points, or all his points when too few
    /// of those were left.
    fn body_of(&self, track: &Track) -> Option<Body> {
        let height_m = f64::from(self.config.segmentation.person_height_m);
        if !track.moved || height_m <= 0.0 || self.class_names.get(usize::from(track.class_id)).is_none_or(|n| n != "person") {
            return None;
        }
        let (tp, (epoch, up)) = (track.points.as_ref()?, self.up?);
        if tp.epoch != epoch {
            return None;
        }
        let latest = &tp.points[..tp.fresh.min(tp.points.len())];
        let points = if latest.len() >= MIN_BODY_POINTS { latest } else { &tp.points[..] };
        Body::around(epoch, points, up, height_m)
    }

    /// A track of instance `id` (class and score) with these pixels of the current
    /// frame: its median depth over `pixels`, and 3D points (a grid sample of
    /// `sample`, at most [`MAX_TRACK_POINTS`]) in the pose chain's frame when the
    /// camera pose is known, plus the `previous` points that lie out of the current
    /// view (the part of a person the camera does not see now is remembered, not
    /// forgotten) or still on the measured surface (see [`Self::agreeing_pixels`]).
    #[allow(clippy::too_many_arguments)]
    fn track_from(
        &self,
        id: u16,
        (class_id, score): (u16, f32),
        detected_at: u64,
        (pixels, sample): (&[usize], &[usize]),
        depth: &[u16],
        pose: Option<&(u32, Isometry3<f64>)>,
        previous: Option<&TrackPoints>,
    ) -> Track {
        let w = self.camera.width as usize;
        let metres = 1.0 / self.camera.depth_units_per_metre;
        let has_depth = |i: &usize| depth.get(*i).is_some_and(|&d| d != 0);
        let mut d: Vec<f32> = pixels.iter().filter(|i| has_depth(i)).map(|&i| (f64::from(depth[i]) * metres) as f32).collect();
        let depth_m = median(&mut d);
        let valid: Vec<usize> = sample.iter().copied().filter(has_depth).collect();
        let spacing = ((valid.len() as f64 / MAX_TRACK_POINTS as f64).sqrt().ceil() as usize).max(1);
        let points = pose.map(|(epoch, anchor_from_camera)| {
            let points: Vec<[f32; 3]> = valid
                .iter()
                .filter(|&&i| (i % w).is_multiple_of(spacing) && (i / w).is_multiple_of(spacing))
                .map(|&i| {
                    let ideal = self.camera.undistort(&nalgebra::Point2::new((i % w) as f64, (i / w) as f64));
                    let p = anchor_from_camera * self.camera.unproject(&ideal, f64::from(depth[i]) * metres);
                    [p.x as f32, p.y as f32, p.z as f32]
                })
                .collect();
            let fresh = points.len();
            let mut tp = TrackPoints { epoch: *epoch, spacing_px: spacing as u32, points, fresh };
            if let Some(prev) = previous.filter(|p| p.epoch == *epoch) {
                let camera_from_anchor = anchor_from_camera.inverse();
                let (wf, hf) = (f64::from(self.camera.width), f64::from(self.camera.height));
                let kept = |p: &&[f32; 3]| {
                    let q = camera_from_anchor * stored_point(p);
                    match self.camera.project(&q).map(|ideal| self.camera.distort(&ideal)) {
                        Some(r) if r.x >= 0.0 && r.y >= 0.0 && r.x < wf && r.y < hf => {
                            let (x, y) = ((r.x.round() as usize).min(w - 1), (r.y.round() as usize).min(hf as usize - 1));
                            self.on_surface(q.z, depth.get(y * w + x).copied().unwrap_or(0))
                        }
                        _ => true, // out of view
                    }
                };
                tp.points.extend(prev.points.iter().filter(kept));
                tp.spacing_px = tp.spacing_px.max(prev.spacing_px);
                if tp.points.len() > 2 * MAX_TRACK_POINTS {
                    let keep = tp.points.len().div_ceil(2 * MAX_TRACK_POINTS);
                    tp.points = tp.points.into_iter().step_by(keep).collect();
                    tp.fresh = tp.fresh.div_ceil(keep);
                }
            }
            tp
        });
        Track { id, detected_at, depth_m, class_id, score, points, moved: false, body: None }
    }

    /// The pixels where a track's 3D points land at the camera pose
    /// `anchor_from_camera` (each point covers the pixels around it).
    fn project_track(&self, track: &Track, pose: &(u32, Isometry3<f64>), w: usize, h: usize) -> Vec<usize> {
        let Some(tp) = &track.points else { return Vec::new() };
        if tp.epoch != pose.0 {
            return Vec::new();
        }
        let camera_from_anchor = pose.1.inverse();
        let mut hit = vec![false; w * h];
        let r = i64::from(tp.spacing_px);
        for p in &tp.points {
            let q = camera_from_anchor * stored_point(p);
            let Some(ideal) = self.camera.project(&q) else { continue };
            let raw = self.camera.distort(&ideal);
            let margin = f64::from(tp.spacing_px);
            if !(raw.x >= -margin && raw.y >= -margin && raw.x < w as f64 + margin && raw.y < h as f64 + margin) {
                continue;
            }
            let (x, y) = (raw.x.round() as i64, raw.y.round() as i64);
            for yy in (y - r).max(0)..=(y + r).min(h as i64 - 1) {
                for xx in (x - r).max(0)..=(x + r).min(w as i64 - 1) {
                    hit[yy as usize * w + xx as usize] = true;
                }
            }
        }
        hit.iter().enumerate().filter(|(_, h)| **h).map(|(i, _)| i).collect()
    }

    /// Whether a remembered point at depth `z_m` (camera frame) lies on the surface
    /// the camera measures at its pixel (`raw` depth units; 0: no depth, no).
    /// The pixel a point in the camera frame projects to, when it is in the image
    /// and the measured depth there agrees with the point's ([`Self::on_surface`]).
    fn surface_pixel(&self, q: &Point3<f64>, depth: &[u16]) -> Option<(usize, usize)> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let r = self.camera.project(q).map(|ideal| self.camera.distort(&ideal))?;
        let (x, y) = (r.x.round(), r.y.round());
        if !(x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64) {
            return None;
        }
        let (x, y) = (x as usize, y as usize);
        self.on_surface(q.z, depth.get(y * w + x).copied().unwrap_or(0)).then_some((x, y))
    }

    fn on_surface(&self, z_m: f64, raw: u16) -> bool {
        let d = f64::from(raw) / self.camera.depth_units_per_metre;
        raw != 0 && (d - z_m).abs() <= f64::from(COAST_DEPTH_GATE) * z_m
    }

    /// The pixels of a track's 3D points, projected at the camera pose, where the
    /// measured depth agrees with the point (within [`COAST_DEPTH_GATE`] of its
    /// depth): the person is still there. Each point marks the grid cell it was
    /// sampled for (`spacing_px` square from its pixel), no more, so the mask does
    /// not grow from frame to frame. Points that now lie in front of the background
    /// (he walked off) mark nothing.
    fn agreeing_pixels(&self, track: &Track, pose: &(u32, Isometry3<f64>), depth: &[u16], w: usize, h: usize) -> Vec<usize> {
        let Some(tp) = track.points.as_ref().filter(|tp| tp.epoch == pose.0) else { return Vec::new() };
        let camera_from_anchor = pose.1.inverse();
        let mut hit = vec![false; w * h];
        let s = tp.spacing_px as usize;
        for p in &tp.points {
            let q = camera_from_anchor * stored_point(p);
            let Some((x, y)) = self.surface_pixel(&q, depth) else { continue };
            for yy in y..(y + s).min(h) {
                for xx in x..(x + s).min(w) {
                    let i = yy * w + xx;
                    if self.on_surface(q.z, depth.get(i).copied().unwrap_or(0)) {
                        hit[i] = true;
                    }
                }
            }
        }
        hit.iter().enumerate().filter(|(_, h)| **h).map(|(i, _)| i).collect()
    }

    /// Labels prior-dynamic (kept out of the map, and taken back out of recent
    /// keyframes) the static pixels in the bodies of the coasting people, carried or
    /// out of view, at the pose chain's pose of frame `sequence`. The cylinder is the
    /// gate: no depth gate around his median depth, which a person looked down on
    /// from close by leaves (his feet lie deeper along the view than his chest).
    fn label_bodies(&self, labels: &mut [u8], sequence: u64, depth: &[u16]) {
        let Some(chain) = self.chain.filter(|c| c.sequence == sequence) else { return };
        let limit = u64::from(self.config.segmentation.track_coast_frames);
        let carried = self.carried.as_ref().map(|c| c.tracks.as_slice()).unwrap_or_default();
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let offscreen = carried.len();
        for (k, t) in carried.iter().chain(&self.offscreen).enumerate() {
            let Some(body) = t.body.as_ref().filter(|_| sequence.saturating_sub(t.detected_at) <= limit) else { continue };
            // Out of view he may have walked on: his body widens at a walking pace.
            let mut body = *body;
            if k >= offscreen {
                let unseen = sequence.saturating_sub(t.detected_at) as f64;
                body.radius_m += (UNSEEN_WALK_M_PER_FRAME * unseen).min(MAX_UNSEEN_GROWTH_M);
            }
            for i in self.body_pixels(&body, &(chain.epoch, chain.anchor_from_camera), depth, w, h) {
                if labels[i] == PixelLabel::Static as u8 {
                    labels[i] = PixelLabel::PriorDynamic as u8;
                }
            }
        }
    }

    /// The pixels whose measured 3D points lie in `body` at the camera pose
    /// `anchor_from_camera` (through the pinhole, lens distortion left out: the
    /// volume has a margin of its own). Only the pixels inside the projection of
    /// the cylinder's outline are looked at (the whole image when part of it is
    /// behind the camera).
    fn body_pixels(&self, body: &Body, pose: &(u32, Isometry3<f64>), depth: &[u16], w: usize, h: usize) -> Vec<usize> {
        if body.epoch != pose.0 {
            return Vec::new();
        }
        let c = &self.camera;
        let camera_from_anchor = pose.1.inverse();
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        let mut behind = false;
        for k in 0..16 {
            let a = f64::from(k) * std::f64::consts::TAU / 16.0;
            let (dx, dy) = (body.radius_m * a.cos(), body.radius_m * a.sin());
            for height in [body.heights.0, body.heights.1] {
                let p = body.up * height + body.e1 * (body.centre.0 + dx) + body.e2 * (body.centre.1 + dy);
                let q = camera_from_anchor * Point3::from(p);
                match c.project(&q).filter(|_| q.z > 0.05) {
                    Some(r) => (x0, y0, x1, y1) = (x0.min(r.x), y0.min(r.y), x1.max(r.x), y1.max(r.y)),
                    None => behind = true,
                }
            }
        }
        // The outline's projection misses the cylinder's bulge between its 16 points: a pixel of margin per side is plenty.
        let (x0, y0, x1, y1) = if behind {
            (0, 0, w, h)
        } else if x1 < 0.0 || y1 < 0.0 || x0 >= w as f64 || y0 >= h as f64 {
            return Vec::new();
        } else {
            let margin = 0.05 * (x1 - x0).max(y1 - y0) + 2.0;
            let clip = |v: f64, n: usize| (v.max(0.0) as usize).min(n);
            (clip(x0 - margin, w), clip(y0 - margin, h), clip(x1 + margin + 1.0, w), clip(y1 + margin + 1.0, h))
        };
        let metres = 1.0 / c.depth_units_per_metre;
        let mut out = Vec::new();
        for y in y0..y1 {
            for x in x0..x1 {
                let i = y * w + x;
                let d = depth.get(i).copied().unwrap_or(0);
                if d == 0 {
                    continue;
                }
                let q = c.unproject(&nalgebra::Point2::new(x as f64, y as f64), f64::from(d) * metres);
                if body.contains(&(pose.1 * q)) {
                    out.push(i);
                }
            }
        }
        out
    }

    /// The camera pose at frame `now` predicted from the chain (constant velocity), with its epoch.
    fn predicted_pose(&self, now: u64) -> Option<(u32, Isometry3<f64>)> {
        let c = self.chain.as_ref()?;
        let frames = now.checked_sub(c.sequence)?;
        Some((c.epoch, c.anchor_from_camera * scale_motion(&c.motion, frames as f64)))
    }

    /// Warps a segmentation of frame `k` through the stored flows up to frame `to`;
    /// `None` when the chain of flows from `k` is not (or no longer) complete.
    fn carry_to(&self, k: u64, seg: Segmentation, to: u64) -> Option<Segmentation> {
        if k == to {
            return Some(seg);
        }
        // Compose the flows from `to` back to `k` on the flow grid, then warp the
        // full-size map once (not once per frame of delay).
        let first = self.flows.iter().position(|f| f.from == k)?;
        let mut chain: Vec<&FlowField> = Vec::new();
        let mut at = k;
        for step in self.flows.iter().skip(first) {
            if step.from != at {
                return None;
            }
            chain.push(&step.flow);
            at = step.to;
            if at == to {
                let mut steps = chain.into_iter().rev();
                let latest = steps.next()?.clone();
                let composed = steps.fold(latest, |later, earlier| later.then(earlier));
                return Some(warp_segmentation(&seg, &composed));
            }
        }
        None
    }

    /// Full-size labels → 1 where the flow-grid cell's centre pixel is dynamic.
    fn dynamic_cells(&self, labels: &[u8]) -> Vec<u8> {
        self.cell_centres().map(|i| u8::from(labels[i] == PixelLabel::Dynamic as u8)).collect()
    }

    /// The full-size pixel index at the centre of each flow-grid cell, row by row.
    fn cell_centres(&self) -> impl Iterator<Item = usize> {
        cell_centres(self.camera.width as usize, self.camera.height as usize, self.config.flow.subsample as usize)
    }

    /// Remembers the cells labelled dynamic on this frame and the previous one (when
    /// that frame's motion was confirmed, or taken as it was by configuration: the
    /// flow saw them move twice, not one frame's noise) as points in the pose
    /// chain's frame, and forgets those older than `ego_motion.remember_moved_frames`.
    fn remember_moved(&mut self, labels: &[u8], carried: Option<&[u8]>, sequence: u64, depth: &[u16]) {
        let limit = u64::from(self.config.ego_motion.remember_moved_frames);
        let Some(chain) = self.chain.filter(|c| c.sequence == sequence && limit > 0) else {
            self.moved.clear();
            return;
        };
        while self.moved.front().is_some_and(|(epoch, seen, _)| *epoch != chain.epoch || seen + limit < sequence) {
            self.moved.pop_front();
        }
        let Some(carried) = carried else { return };
        let w = self.camera.width as usize;
        let metres = 1.0 / self.camera.depth_units_per_metre;
        let fresh: Vec<[f32; 3]> = self
            .cell_centres()
            .enumerate()
            .filter(|(g, i)| labels[*i] == PixelLabel::Dynamic as u8 && carried.get(*g).is_some_and(|&c| c != 0))
            .filter_map(|(_, i)| {
                let d = *depth.get(i).filter(|&&d| d != 0)?;
                let ideal = self.camera.undistort(&nalgebra::Point2::new((i % w) as f64, (i / w) as f64));
                let p = chain.anchor_from_camera * self.camera.unproject(&ideal, f64::from(d) * metres);
                Some([p.x as f32, p.y as f32, p.z as f32])
            })
            .collect();
        self.moved.extend(fresh.into_iter().map(|p| (chain.epoch, sequence, p)));
        while self.moved.len() > MAX_MOVED_POINTS {
            self.moved.pop_front();
        }
    }

    /// Marks in `exclude` the flow-grid cells where a remembered moving point lands
    /// at the predicted pose of frame `sequence` and the measured depth agrees with
    /// it (the thing is still there, resting).
    fn exclude_remembered(&self, exclude: &mut [u8], sequence: u64, depth: &[u16]) {
        let Some((epoch, anchor_from_camera)) = self.predicted_pose(sequence).filter(|_| !self.moved.is_empty()) else { return };
        let camera_from_anchor = anchor_from_camera.inverse();
        let s = self.config.flow.subsample as usize;
        let (gw, _) = self.ego.grid_size();
        for (_, _, p) in self.moved.iter().filter(|(e, _, _)| *e == epoch) {
            let q = camera_from_anchor * stored_point(p);
            if let Some((x, y)) = self.surface_pixel(&q, depth)
                && x / s < gw
                && let Some(cell) = exclude.get_mut((y / s) * gw + x / s)
            {
                *cell = 1;
            }
        }
    }

    /// The flow cells the camera-motion estimate of frame `sequence` must not listen
    /// to: the previous frame's dynamic cells carried here (`carried_dynamic`),
    /// prior-dynamic instances and remembered movers at rest. When the carried cells
    /// are more than `ego_motion.moving_majority_share` of the view, that verdict may
    /// be the camera's own motion misjudged (the estimate assumes most of the view is
    /// static), and only the prior-dynamic instances stay out.
    fn vote_exclusion(&self, carried_dynamic: Option<&[u8]>, sequence: u64, depth: &[u16]) -> Vec<u8> {
        let seg = self.carried.as_ref().map(|c| &c.segmentation);
        let moving_share = carried_dynamic.map_or(0.0, |d| d.iter().filter(|&&v| v != 0).count() as f64 / d.len().max(1) as f64);
        if moving_share > self.config.ego_motion.moving_majority_share {
            return self.exclusion_grid(seg, None);
        }
        let mut exclude = self.exclusion_grid(seg, carried_dynamic);
        self.exclude_remembered(&mut exclude, sequence, depth);
        exclude
    }

    /// Flow-grid cells kept out of the ego-motion estimate: prior-dynamic
    /// instances and the carried dynamic cells.
    fn exclusion_grid(&self, seg: Option<&Segmentation>, dynamic: Option<&[u8]>) -> Vec<u8> {
        let dynamic_ids: Vec<bool> = seg.map_or_else(Vec::new, |seg| {
            let max = seg.instances.iter().map(|i| usize::from(i.id)).max().unwrap_or(0);
            let mut v = vec![false; max + 1];
            for i in &seg.instances {
                v[usize::from(i.id)] = self.prior_dynamic.get(usize::from(i.class_id)).copied().unwrap_or(false);
            }
            v
        });
        self.cell_centres()
            .enumerate()
            .map(|(g, i)| {
                let prior = seg.is_some_and(|seg| dynamic_ids.get(usize::from(seg.instance_map[i])).copied().unwrap_or(false));
                u8::from(prior || dynamic.is_some_and(|d| d[g] != 0))
            })
            .collect()
    }
}

/// What moved over the last `ego_motion.baseline_frames` frames.
struct Baseline {
    /// Flow-grid cells (1 = moved).
    moving: Vec<u8>,
    /// The camera motion over the baseline that most of the scene follows.
    reference_from_current: Isometry3<f64>,
    /// The per-frame motions chosen over the baseline but the last, chained.
    chained: Isometry3<f64>,
    /// The composed flow's noise in one frame's flow variances (Σ n² over its steps).
    noise_steps: f64,
}

/// What moved over the baseline is opened by a disc of this radius (flow cells)
/// before use: narrower lines are the composed flow's errors along edges.
const BASELINE_OPENING_CELLS: u32 = 2;

/// A new prior-dynamic detection covering at least this fraction of a carried
/// prior-dynamic instance is that instance found again (it then replaces it).
const COAST_MATCH_FRACTION: f64 = 0.3;
/// A coasting instance keeps the pixels within this fraction of its median depth.
const COAST_DEPTH_GATE: f32 = 0.15;
/// A body's horizontal margin around its seen points, and its largest radius (metres).
const BODY_MARGIN_M: f64 = 0.05;
const MAX_BODY_RADIUS_M: f64 = 0.45;
/// A body's smallest radius: an adult's shoulders are about 0.45 m wide and his hands
/// swing and hang beside them, up to about 0.4 m from his axis, so however little of
/// him was seen (his legs at the image's edge), his body reaches that far.
const MIN_BODY_RADIUS_M: f64 = 0.4;
/// How far a body's axis may follow its points per frame (a brisk walk, 1.5 m/s at 30 Hz).
const BODY_STEP_M_PER_FRAME: f64 = 0.05;
/// Points a track needs before its body's volume is estimated.
const MIN_BODY_POINTS: usize = 20;
/// How fast the body of a person out of view widens (metres per frame: 0.6 m/s at 30 Hz).
const UNSEEN_WALK_M_PER_FRAME: f64 = 0.02;
/// The most it widens.
const MAX_UNSEEN_GROWTH_M: f64 = 0.5;
/// Per frame, the weight left to earlier accelerometer samples in the up estimate.
const UP_DECAY: f64 = 0.9;
/// A coasting track with fewer pixels than this is out of view.
const MIN_COAST_PX: usize = 100;
/// Tracks remembered out of view, at most (per session).
const MAX_OFFSCREEN_TRACKS: usize = 16;
/// 3D points kept per track, at most.
const MAX_TRACK_POINTS: usize = 1500;
/// Points remembered of what the flow saw moving, at most (per session).
const MAX_MOVED_POINTS: usize = 20_000;

/// Row-major pixel indices inside a box (x0, y0, x1, y1; ends exclusive), clipped to the image.
fn bbox_pixels(bbox: &[f32; 4], width: usize, height: usize) -> impl Iterator<Item = usize> {
    let (x0, y0) = ((bbox[0].max(0.0) as usize).min(width), (bbox[1].max(0.0) as usize).min(height));
    let (x1, y1) = ((bbox[2].max(0.0).ceil() as usize).min(width), (bbox[3].max(0.0).ceil() as usize).min(height));
    (y0..y1).flat_map(move |y| (x0..x1).map(move |x| y * width + x))
}

/// The median of `values` (reordered), `None` when empty.
fn median(values: &mut [f32]) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, f32::total_cmp);
    Some(*m)
}

/// Grows the 0/1 flow-grid mask over the surfaces its cells lie on, at most
/// `max_steps` cells (see [`grow_over_depth`]).
fn grow_over_surfaces(mut grid: Vec<u8>, depth_m: &[f32], width: usize, height: usize, max_steps: usize, ratio: f64) -> Vec<u8> {
    let mut inside: Vec<bool> = grid.iter().map(|&v| v != 0).collect();
    for j in grow_over_depth(&mut inside, depth_m, width, height, ratio, max_steps, |_| true) {
        grid[j] = 1;
    }
    grid
}

/// Dilates a 0/1 mask by a disc of `radius` pixels (OpenCV).
fn dilate(mask: Vec<u8>, width: usize, height: usize, radius: u32) -> Result<Vec<u8>, PerceptionError> {
    morphology(mask, width, height, radius, opencv::imgproc::MORPH_DILATE)
}

/// `mask` (1 = set) opened by a disc of `radius` cells: what is narrower than the
/// disc goes, the rest keeps its shape.
fn open_regions(mask: Vec<u8>, width: usize, height: usize, radius: u32) -> Result<Vec<u8>, PerceptionError> {
    morphology(mask, width, height, radius, opencv::imgproc::MORPH_OPEN)
}

/// OpenCV's morphology `operation` on a 0/1 mask with a disc of `radius`.
fn morphology(mask: Vec<u8>, width: usize, height: usize, radius: u32, operation: i32) -> Result<Vec<u8>, PerceptionError> {
    use opencv::core::{Mat, Point, Size};
    use opencv::imgproc;
    use opencv::prelude::*;
    if radius == 0 || !mask.contains(&1) {
        return Ok(mask);
    }
    let src = Mat::new_rows_cols_with_data(height as i32, width as i32, &mask)?;
    let side = 2 * radius as i32 + 1;
    let kernel = imgproc::get_structuring_element(imgproc::MORPH_ELLIPSE, Size::new(side, side), Point::new(-1, -1))?;
    let mut out = Mat::default();
    imgproc::morphology_ex(
        &src,
        &mut out,
        operation,
        &kernel,
        Point::new(-1, -1),
        1,
        opencv::core::BORDER_CONSTANT,
        imgproc::morphology_default_border_value()?,
    )?;
    Ok(out.data_bytes()?.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// A board at 0.8 m in front of a wall at 2 m, on a 12×5 grid; one cell of the
    /// board is flagged. Growth covers the board within reach, never the wall, and
    /// stops at cells without depth.
    /// A `w × h` pinhole camera with focal length `f` pixels, centred, depth in millimetres.
    fn pinhole(w: usize, h: usize, f: f64) -> Camera {
        Camera::pinhole(w as u32, h as u32, f, f, w as f64 / 2.0, h as f64 / 2.0, 1000.0)
    }

    /// Frame `k`'s input, with the segmentation (if any) made on it; no capture
    /// time, motion prior or accelerometer.
    fn frame_input<'a>(k: u64, rgb: &'a [u8], depth: &'a [u16], seg: Option<Segmentation>) -> MaskerInput<'a> {
        MaskerInput {
            sequence: k,
            capture_time_ns: 0,
            rgb,
            depth,
            segmentation: seg.map(|s| (k, s)),
            motion_prior: None,
            accel_in_camera: None,
        }
    }

    /// A segmentation of one person (instance 1, class 0) over `xs` × `ys`.
    fn person(w: usize, h: usize, xs: std::ops::Range<usize>, ys: std::ops::Range<usize>) -> Segmentation {
        let mut seg = Segmentation::empty(w as u32, h as u32);
        for y in ys.clone() {
            for x in xs.clone() {
                seg.instance_map[y * w + x] = 1;
            }
        }
        seg.instances.push(crate::segment::Instance {
            id: 1,
            class_id: 0,
            class_name: "person".into(),
            score: 0.9,
            bbox: [xs.start as f32, ys.start as f32, xs.end as f32, ys.end as f32],
            pixels: (xs.len() * ys.len()) as u32,
        });
        seg
    }

    #[test]
    fn growth_follows_the_surface_and_stops_at_depth_edges_holes_and_its_reach() {
        let (w, h) = (12, 5);
        // Columns 0–7 board (with a hole at (4, 2)), 8–11 wall.
        let depth: Vec<f32> = (0..w * h)
            .map(|i| match (i % w, i / w) {
                (4, 2) => 0.0,
                (x, _) if x < 8 => 0.8 + 0.01 * x as f32,
                _ => 2.0,
            })
            .collect();
        let mut seeds = vec![0u8; w * h];
        seeds[2 * w + 2] = 1;
        let grown = grow_over_surfaces(seeds.clone(), &depth, w, h, 3, 0.05);
        for y in 0..h {
            for x in 0..w {
                // 4-neighbour steps from (2, 2), on depth, not through the hole.
                let reach = x.abs_diff(2) + y.abs_diff(2);
                let through_hole_only = (x, y) == (5, 2);
                let expected = x < 8 && (x, y) != (4, 2) && reach <= 3 && !through_hole_only;
                assert_eq!(grown[y * w + x] == 1, expected, "cell ({x}, {y})");
            }
        }
        // Far enough, the whole board but still not the wall.
        let all = grow_over_surfaces(seeds.clone(), &depth, w, h, 100, 0.05);
        assert_eq!(all.iter().filter(|&&v| v == 1).count(), 8 * h - 1);
        assert!((0..h).all(|y| (8..w).all(|x| all[y * w + x] == 0)));
        // No reach, or a seed without depth: nothing grows.
        assert_eq!(grow_over_surfaces(seeds.clone(), &depth, w, h, 0, 0.05), seeds);
        let mut in_hole = vec![0u8; w * h];
        in_hole[2 * w + 4] = 1;
        assert_eq!(grow_over_surfaces(in_hole.clone(), &depth, w, h, 5, 0.05), in_hole);
    }

    #[test]
    fn a_motion_scales_with_the_frames_it_spans() {
        let m = Isometry3::new(Vector3::new(0.01, -0.02, 0.005), Vector3::new(0.0, 0.03, 0.0));
        let twice = scale_motion(&m, 2.0);
        assert!((twice.rotation.angle() - 0.06).abs() < 1e-12);
        assert!((twice.translation.vector - Vector3::new(0.02, -0.04, 0.01)).norm() < 1e-12);
        assert_eq!(scale_motion(&m, 1.0), m);
        let half = scale_motion(&m, 0.5);
        assert!((half.rotation.angle() - 0.015).abs() < 1e-12);
    }

    /// A person the segmenter stops finding stays a person, carried by the flow,
    /// for `track_coast_frames` after the last detection; only the pixels near
    /// his depth stay; a keyframe fused before he was found gets his cells back.
    #[test]
    fn a_missed_person_coasts_near_his_depth_and_is_taken_out_of_earlier_keyframes() {
        let (w, h) = (96usize, 72usize);
        let camera = pinhole(w, h, 80.0);
        let mut config = PerceptionConfig::default();
        config.segmentation.track_coast_frames = 4;
        let mut masker = DynamicMasker::new(camera, config, &["person".to_string()]).expect("masker");
        // A still, textured scene: a wall at 3 m, a person at 1 m over columns 30..50.
        let rgb: Vec<u8> = (0..w * h)
            .flat_map(|i| {
                let v = ((i % w) * 37 + (i / w) * 91 + (i % 7) * 53) as u8;
                [v, v.wrapping_mul(3), v ^ 0x5a]
            })
            .collect();
        let depth: Vec<u16> = (0..w * h).map(|i| if (30..50).contains(&(i % w)) { 1000 } else { 3000 }).collect();
        // The detection's mask spills 6 columns onto the wall (30..56), rows 10..60.
        let detection = person(w, h, 30..56, 10..60);
        let person_pixels = |m: &DynamicMasker| {
            m.segmentation().map_or(0, |s| s.instances.iter().filter(|i| i.class_name == "person").map(|i| i.pixels).sum::<u32>())
        };
        let step = |m: &mut DynamicMasker, k: u64, seg: Option<Segmentation>| {
            m.prepare(frame_input(k, &rgb, &depth, seg)).expect("prepare");
            m.finish(&depth, Some(Isometry3::identity())).expect("finish")
        };
        // Frame 0 has no person detected and becomes keyframe 100: the person is fused.
        step(&mut masker, 0, Some(Segmentation::empty(w as u32, h as u32)));
        masker.note_keyframe(100);
        assert_eq!(person_pixels(&masker), 0);
        // Frame 1: found. The keyframe's cells on him come back (subsample 3: his
        // 20 × 50 px are about 7 × 17 cells, and the one-cell rim).
        let out = step(&mut masker, 1, Some(detection.clone()));
        assert_eq!(person_pixels(&masker), 26 * 50);
        assert_eq!(out.retractions.len(), 1);
        let r = &out.retractions[0];
        assert_eq!(r.keyframe, 100);
        let test = r.pixel_test(w as u32);
        assert!(test((30 * w + 40) as u32) && !test((30 * w + 5) as u32) && !test((65 * w + 40) as u32));
        assert!(step(&mut masker, 2, None).retractions.is_empty(), "each cell once");
        // Frames 3 and 5: the segmenter misses him; he coasts, his wall pixels dropped.
        step(&mut masker, 3, Some(Segmentation::empty(w as u32, h as u32)));
        assert_eq!(person_pixels(&masker), 20 * 50, "only the pixels at his depth");
        step(&mut masker, 4, None);
        step(&mut masker, 5, Some(Segmentation::empty(w as u32, h as u32)));
        assert_eq!(person_pixels(&masker), 20 * 50, "4 frames after the detection: still coasting");
        step(&mut masker, 6, None);
        step(&mut masker, 7, Some(Segmentation::empty(w as u32, h as u32)));
        assert_eq!(person_pixels(&masker), 0, "6 frames after: gone");
    }

    /// The first frame has no camera motion, so nothing on it was judged moving or
    /// still: on the next frame a person it segmented is tracked on only if that
    /// frame judges him still. Where the flow cannot confirm that frame's motion
    /// (here: an image without texture), his motion is still unknown and he stays in
    /// the tracking mask (`ExcludeWhileMoving`), as on the first frame.
    #[test]
    fn a_person_of_unknown_motion_is_kept_out_of_tracking_on_the_second_frame_too() {
        let (w, h) = (96usize, 72usize);
        let mut masker = DynamicMasker::new(pinhole(w, h, 80.0), PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        assert_eq!(masker.config.fusion.prior_dynamic_tracking, PriorDynamicTracking::ExcludeWhileMoving);
        let rgb = vec![128u8; w * h * 3];
        let depth: Vec<u16> = (0..w * h).map(|i| if (30..50).contains(&(i % w)) { 1000 } else { 3000 }).collect();
        let detection = person(w, h, 30..50, 10..60);
        let on_person: Vec<usize> = (0..w * h).filter(|&i| detection.instance_map[i] != 0).collect();
        let first = masker.prepare(frame_input(0, &rgb, &depth, Some(detection.clone()))).expect("prepare");
        assert!(on_person.iter().all(|&i| first[i] != 0), "first frame: his motion is unknown");
        let out = masker.finish(&depth, None).expect("finish");
        assert!(out.ego.is_none(), "no camera motion on the first frame");
        let second = masker.prepare(frame_input(1, &rgb, &depth, None)).expect("prepare");
        assert!(masker.prepared_motion().is_none(), "the flow cannot confirm a motion on an image without texture");
        assert_eq!(second[5 * w + 5], 0, "the wall is tracked on");
        let kept_out = on_person.iter().filter(|&&i| second[i] != 0).count();
        assert_eq!(kept_out, on_person.len(), "second frame, motion unconfirmed: all of his pixels stay out");
    }

    /// A frame whose camera motion the flow did not confirm judged nothing for
    /// sure: its verdict (here: the person is still) is not carried into the next
    /// frame, which, unconfirmed too, keeps him out of tracking as the first frame
    /// does (`ExcludeWhileMoving`) instead of tracking on him. With refinement off
    /// by configuration a prior taken as it was is unchecked by choice, and its
    /// verdict carried; identity where no prior was given is not.
    #[test]
    fn an_unconfirmed_frame_passes_no_verdict_on_a_person_to_the_next() {
        let (w, h) = (96usize, 72usize);
        let mut masker = DynamicMasker::new(pinhole(w, h, 80.0), PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        let rgb = vec![128u8; w * h * 3];
        let depth: Vec<u16> = (0..w * h).map(|i| if (30..50).contains(&(i % w)) { 1000 } else { 3000 }).collect();
        let detection = person(w, h, 30..50, 10..60);
        let on_person: Vec<usize> = (0..w * h).filter(|&i| detection.instance_map[i] != 0).collect();
        masker.prepare(frame_input(0, &rgb, &depth, Some(detection.clone()))).expect("prepare");
        masker.finish(&depth, None).expect("finish");
        for k in 1..=3 {
            let mask = masker.prepare(frame_input(k, &rgb, &depth, None)).expect("prepare");
            assert!(masker.prepared_motion().is_none(), "frame {k}: the flow cannot confirm a motion on an image without texture");
            let kept_out = on_person.iter().filter(|&&i| mask[i] != 0).count();
            assert_eq!(kept_out, on_person.len(), "frame {k}, motion unconfirmed: all of his pixels stay out");
            assert_eq!(mask[5 * w + 5], 0, "frame {k}: the wall is tracked on");
            let out = masker.finish(&depth, Some(Isometry3::identity())).expect("finish");
            assert!(out.ego.is_some_and(|e| !e.refined), "frame {k}: a motion, not a refinement on the flow");
            // Its labels call him still: carried, they would let him into tracking.
            assert!(on_person.iter().all(|&i| out.fused.labels[i] != PixelLabel::Dynamic as u8), "frame {k}: not judged moving");
        }
        // Refinement off: frame 1 has no prior (frame 0 had no motion) and no
        // refinement holds, so it judged nothing and frame 2 keeps him out; frame 2
        // takes its prior (frame 1's motion) as it is, by configuration, and passes its
        // verdict on: frame 3 tracks on the person it judged still.
        let mut config = PerceptionConfig::default();
        config.ego_motion.refine_tracked_motion = false;
        let mut masker = DynamicMasker::new(pinhole(w, h, 80.0), config, &["person".to_string()]).expect("masker");
        masker.prepare(frame_input(0, &rgb, &depth, Some(detection.clone()))).expect("prepare");
        masker.finish(&depth, None).expect("finish");
        let mut masks = Vec::new();
        for k in 1..=3 {
            masks.push(masker.prepare(frame_input(k, &rgb, &depth, None)).expect("prepare"));
            masker.finish(&depth, Some(Isometry3::identity())).expect("finish");
        }
        assert!(on_person.iter().all(|&i| masks[1][i] != 0), "refinement off, frame 2: nothing judged on frame 1, he stays out");
        assert!(on_person.iter().all(|&i| masks[2][i] == 0), "refinement off, frame 3: judged still under a prior taken as it was");
    }

    /// A track's 3D points: projected back where they were seen; the part out of
    /// view is kept when the visible part is refreshed, so a person the camera
    /// turned away from is found again when it turns back.
    #[test]
    fn a_track_out_of_view_is_remembered_by_its_points() {
        let (w, h) = (96usize, 72usize);
        let camera = pinhole(w, h, 80.0);
        let masker = DynamicMasker::new(camera, PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        let depth = vec![1000u16; w * h];
        // A person over columns 40..56, rows 20..60, seen at the identity pose.
        let pixels: Vec<usize> = (20..60).flat_map(|y| (40..56).map(move |x| y * w + x)).collect();
        let here = (1u32, Isometry3::identity());
        let track = masker.track_from(1, (0, 0.9), 5, (&pixels, &pixels), &depth, Some(&here), None);
        assert_eq!(track.depth_m, Some(1.0));
        let back = masker.project_track(&track, &here, w, h);
        assert!(pixels.iter().all(|p| back.contains(p)), "every pixel of the person is covered again");
        assert!(back.len() < pixels.len() + 2 * (16 + 40) * 2 + 16, "and little around it: {} pixels", back.len());
        // The camera turns 60° away: nothing of him is in view, and refreshing the
        // track with no visible pixels keeps every point.
        let away = (1u32, Isometry3::rotation(nalgebra::Vector3::y() * 60f64.to_radians()));
        assert!(masker.project_track(&track, &away, w, h).is_empty());
        let kept = masker.track_from(1, (0, 0.9), 5, (&[], &[]), &depth, Some(&away), track.points.as_ref());
        assert_eq!(kept.points.as_ref().map(|p| p.points.len()), track.points.as_ref().map(|p| p.points.len()));
        // Turning back finds him where he was; another epoch (tracking was lost) does not.
        assert_eq!(masker.project_track(&kept, &here, w, h), back);
        assert!(masker.project_track(&kept, &(2, Isometry3::identity()), w, h).is_empty());
    }

    /// What the flow saw moving twice in a row is kept out of the camera-motion
    /// vote while the measured surface still lies on it (it rests), not once the
    /// wall behind is measured there (it left), nor after
    /// `ego_motion.remember_moved_frames`, nor in another epoch of the pose chain.
    #[test]
    fn a_thing_seen_moving_is_kept_out_of_the_vote_while_it_rests() {
        let (w, h) = (96usize, 72usize);
        let camera = pinhole(w, h, 80.0);
        let mut masker = DynamicMasker::new(camera, PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        let s = masker.config.flow.subsample as usize;
        let (gw, gh) = masker.ego.grid_size();
        // A box 1 m ahead over columns 40..56 and rows 20..44, in front of a wall at 3 m.
        let on_box = |x: usize, y: usize| (40..56).contains(&x) && (20..44).contains(&y);
        let resting: Vec<u16> = (0..w * h).map(|i| if on_box(i % w, i / w) { 1000 } else { 3000 }).collect();
        let gone = vec![3000u16; w * h];
        let mut labels = vec![PixelLabel::Static as u8; w * h];
        for (i, l) in labels.iter_mut().enumerate() {
            if on_box(i % w, i / w) {
                *l = PixelLabel::Dynamic as u8;
            }
        }
        let box_cells: Vec<usize> = (0..gw * gh).filter(|g| on_box((g % gw) * s + s / 2, (g / gw) * s + s / 2)).collect();
        assert!(box_cells.len() >= 8);
        let at = |sequence: u64, epoch: u32| PoseChain {
            sequence,
            anchor_from_camera: Isometry3::identity(),
            motion: Isometry3::identity(),
            epoch,
        };
        masker.chain = Some(at(10, 1));
        // Seen moving once: nothing remembered; twice (the previous frame's cells carried): remembered.
        masker.remember_moved(&labels, None, 10, &resting);
        assert!(masker.moved.is_empty());
        let carried = vec![1u8; gw * gh];
        masker.remember_moved(&labels, Some(&carried), 10, &resting);
        assert_eq!(masker.moved.len(), box_cells.len());
        let excluded = |masker: &DynamicMasker, sequence: u64, depth: &[u16]| {
            let mut exclude = vec![0u8; gw * gh];
            masker.exclude_remembered(&mut exclude, sequence, depth);
            (0..gw * gh).filter(|g| exclude[*g] != 0).collect::<Vec<_>>()
        };
        assert_eq!(excluded(&masker, 40, &resting), box_cells, "resting: its cells, no others");
        assert!(excluded(&masker, 40, &gone).is_empty(), "gone: the wall is measured there");
        // Forgotten after remember_moved_frames (90 by default) …
        let limit = u64::from(masker.config.ego_motion.remember_moved_frames);
        masker.chain = Some(at(10 + limit + 1, 1));
        masker.remember_moved(&vec![PixelLabel::Static as u8; w * h], Some(&carried), 10 + limit + 1, &resting);
        assert!(masker.moved.is_empty());
        // … and when the pose chain breaks (a new epoch).
        masker.chain = Some(at(200, 1));
        masker.remember_moved(&labels, Some(&carried), 200, &resting);
        assert!(!masker.moved.is_empty());
        masker.chain = Some(at(201, 2));
        assert!(excluded(&masker, 201, &resting).is_empty(), "another epoch");
        masker.remember_moved(&vec![PixelLabel::Static as u8; w * h], Some(&carried), 201, &resting);
        assert!(masker.moved.is_empty());
    }

    /// The camera-motion estimate keeps out what the last frame labelled moving and
    /// the movers remembered at rest, unless that was most of the view
    /// (`ego_motion.moving_majority_share`): then only prior-dynamic instances stay out.
    #[test]
    fn a_verdict_that_most_of_the_view_moves_does_not_keep_it_out_of_the_vote() {
        let (w, h) = (96usize, 72usize);
        let mut masker = DynamicMasker::new(pinhole(w, h, 80.0), PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        assert_eq!(masker.config.ego_motion.moving_majority_share, 0.5);
        let (gw, gh) = masker.ego.grid_size();
        let depth = vec![2000u16; w * h];
        // The last frame's moving cells: the left 40 % or 60 % of the columns.
        let left = |share: f64| -> Vec<u8> { (0..gw * gh).map(|g| u8::from(((g % gw) as f64) < share * gw as f64)).collect() };
        let (some, most) = (left(0.4), left(0.6));
        let count = |v: &[u8]| v.iter().filter(|&&e| e != 0).count();
        assert!(count(&most) * 2 > gw * gh && count(&some) * 2 < gw * gh);
        assert_eq!(masker.vote_exclusion(Some(&some), 5, &depth), some, "a mover: kept out");
        assert_eq!(count(&masker.vote_exclusion(Some(&most), 5, &depth)), 0, "most of the view: listened to again");
        // A prior-dynamic instance stays out either way.
        let seg = person(w, h, 60..80, 10..30);
        masker.carried = Some(Carried { segmentation: seg, source_sequence: 5, at_sequence: 5, tracks: Vec::new() });
        let person = count(&masker.exclusion_grid(masker.carried.as_ref().map(|c| &c.segmentation), None));
        assert!(person > 0);
        assert_eq!(count(&masker.vote_exclusion(Some(&most), 5, &depth)), person);
        // 1 turns it off: the verdict is kept whatever its size.
        masker.config.ego_motion.moving_majority_share = 1.0;
        assert_eq!(count(&masker.vote_exclusion(Some(&most), 5, &depth)), count(&most) + person);
    }

    /// A person the carried mask lost while he stands is still where his points are:
    /// exactly his pixels agree with the measured depth, and a refresh keeps every
    /// point. Once he has walked off (the wall behind him is measured there), no
    /// pixel agrees and a refresh drops the points.
    #[test]
    fn a_standing_track_is_kept_where_its_points_lie_on_the_measured_surface() {
        let (w, h) = (96usize, 72usize);
        let camera = pinhole(w, h, 80.0);
        let masker = DynamicMasker::new(camera, PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        let pixels: Vec<usize> = (20..60).flat_map(|y| (40..56).map(move |x| y * w + x)).collect();
        let mut standing = vec![3000u16; w * h];
        for &i in &pixels {
            standing[i] = 1000;
        }
        let here = (1u32, Isometry3::identity());
        let track = masker.track_from(1, (0, 0.9), 5, (&pixels, &pixels), &standing, Some(&here), None);
        let agreeing = masker.agreeing_pixels(&track, &here, &standing, w, h);
        assert_eq!(agreeing, pixels);
        let kept = masker.track_from(1, (0, 0.9), 5, (&agreeing, &[]), &standing, Some(&here), track.points.as_ref());
        assert_eq!(kept.depth_m, Some(1.0));
        assert_eq!(kept.points.as_ref().map(|p| p.points.len()), Some(pixels.len()));
        let wall = vec![3000u16; w * h];
        assert!(masker.agreeing_pixels(&track, &here, &wall, w, h).is_empty());
        let gone = masker.track_from(1, (0, 0.9), 5, (&[], &[]), &wall, Some(&here), track.points.as_ref());
        assert_eq!(gone.points.as_ref().map(|p| p.points.len()), Some(0));
    }

    /// A person seen from the hips up: his body's volume reaches down to his legs
    /// (at his depth) and leaves the wall behind him out; too few points give no body.
    #[test]
    fn a_body_reaches_the_legs_that_were_never_seen() {
        let (w, h) = (96usize, 72usize);
        let camera = pinhole(w, h, 40.0);
        let masker = DynamicMasker::new(camera, PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        // At 2 m a pixel is 5 cm. The person: columns 44..52 (0.4 m wide), rows 20..55
        // (1.75 m tall); the wall 4 m away. Up is the camera's -y.
        let person = |x: usize, y: usize| (44..52).contains(&x) && (20..55).contains(&y);
        let depth: Vec<u16> = (0..w * h).map(|i| if person(i % w, i / w) { 2000 } else { 4000 }).collect();
        let point = |x: usize, y: usize| [((x as f64 - 48.0) / 20.0) as f32, ((y as f64 - 36.0) / 20.0) as f32, 2.0f32];
        // Seen: the upper body only (rows 20..36).
        let seen: Vec<[f32; 3]> = (20..36).flat_map(|y| (44..52).map(move |x| point(x, y))).collect();
        let up = -Vector3::y();
        let body = Body::around(1, &seen, up, 2.0).expect("a body");
        // 0.4 m of him seen across: 0.2 m from the axis and the margin is less than the
        // least a body takes. Seen 0.76 m across, his own spread and the margin count.
        assert_eq!(body.radius_m, MIN_BODY_RADIUS_M);
        let wide: Vec<[f32; 3]> = seen.iter().map(|p| [p[0] * 1.9, p[1], p[2]]).collect();
        let radius = Body::around(1, &wide, up, 2.0).expect("a body").radius_m;
        assert!(radius > MIN_BODY_RADIUS_M && radius < MAX_BODY_RADIUS_M, "radius {radius}");
        let pixels = masker.body_pixels(&body, &(1, Isometry3::identity()), &depth, w, h);
        let legs: Vec<usize> = (36..55).flat_map(|y| (45..51).map(move |x| y * w + x)).collect();
        assert!(legs.iter().all(|i| pixels.contains(i)), "every leg pixel is his");
        assert!(pixels.iter().all(|&i| person(i % w, i / w)), "no wall pixel is");
        // Another epoch (tracking was lost) marks nothing; nor do 19 points make a body.
        assert!(masker.body_pixels(&body, &(2, Isometry3::identity()), &depth, w, h).is_empty());
        assert!(Body::around(1, &seen[..19], up, 2.0).is_none());
        // He walks 0.3 m away from the camera: the axis follows by at most the step.
        let farther: Vec<[f32; 3]> = seen.iter().map(|p| [p[0], p[1], p[2] + 0.3]).collect();
        let mut moved = body;
        moved.follow(&farther, 0.1);
        let shift = (moved.centre.0 - body.centre.0).hypot(moved.centre.1 - body.centre.1);
        assert!((shift - 0.1).abs() < 1e-9, "moved {shift} m");
        moved.follow(&farther, 1.0);
        let shift = (moved.centre.0 - body.centre.0).hypot(moved.centre.1 - body.centre.1);
        assert!((shift - 0.3).abs() < 1e-6, "moved {shift} m in all");
        assert_eq!((moved.radius_m, moved.heights), (body.radius_m, body.heights), "its size stays");
    }

    /// A person looked down on from close by: his feet lie far deeper along the view
    /// than the chest that was seen (more than the coasting depth gate), and are his
    /// all the same; the wall behind him and the floor away from him are not.
    #[test]
    fn a_body_looked_down_on_takes_his_feet() {
        let (w, h) = (160usize, 120usize);
        let mut masker = DynamicMasker::new(pinhole(w, h, 80.0), PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        // The camera 1.5 m above the floor, pitched 40° down: up and the horizontal
        // forward direction in its frame.
        let pitch = 40f64.to_radians();
        let up = Vector3::new(0.0, -pitch.cos(), -pitch.sin());
        let forward = Vector3::new(0.0, -pitch.sin(), pitch.cos());
        // Him: 0.4 m wide, 1.7 m tall, 1.3 m ahead; a wall 3 m ahead; the floor.
        let hit = |x: usize, y: usize| {
            let ray = Vector3::new((x as f64 + 0.5 - 80.0) / 80.0, (y as f64 + 0.5 - 60.0) / 80.0, 1.0);
            let along = ray.dot(&forward);
            let on = |t: f64| Some(ray * t).filter(|_| t > 0.0);
            let person = on(1.3 / along).filter(|p| p.x.abs() <= 0.2 && (-1.5..=0.2).contains(&p.dot(&up)));
            let floor = if ray.dot(&up) < 0.0 { on(-1.5 / ray.dot(&up)) } else { None };
            let wall = on(3.0 / along).filter(|p| p.dot(&up) >= -1.5);
            person.map(|p| (p, true)).or(floor.filter(|f| f.dot(&forward) < 3.0).map(|p| (p, false))).or(wall.map(|p| (p, false)))
        };
        let scene: Vec<Option<(Vector3<f64>, bool)>> = (0..w * h).map(|i| hit(i % w, i / w)).collect();
        let depth: Vec<u16> = scene.iter().map(|s| s.map_or(0, |(p, _)| (p.z * 1000.0).round() as u16)).collect();
        // Seen: his chest and head (0.4 m and more above the camera's height less 0.4 m).
        let seen: Vec<[f32; 3]> = scene
            .iter()
            .filter_map(|s| *s)
            .filter(|(p, his)| *his && p.dot(&up) >= -0.4)
            .map(|(p, _)| [p.x as f32, p.y as f32, p.z as f32])
            .collect();
        let mut depths: Vec<f32> = seen.iter().map(|p| p[2]).collect();
        depths.sort_by(f32::total_cmp);
        let median = depths[depths.len() / 2];
        let body = Body::around(1, &seen, up, 2.0).expect("a body");
        masker.offscreen = vec![Track {
            id: 1,
            detected_at: 0,
            depth_m: Some(median),
            class_id: 0,
            score: 0.9,
            points: None,
            moved: true,
            body: Some(body),
        }];
        masker.chain = Some(PoseChain { sequence: 0, anchor_from_camera: Isometry3::identity(), motion: Isometry3::identity(), epoch: 1 });
        let mut labels = vec![PixelLabel::Static as u8; w * h];
        masker.label_bodies(&mut labels, 0, &depth);
        let his = |i: usize| labels[i] == PixelLabel::PriorDynamic as u8;
        let feet: Vec<usize> = (0..w * h).filter(|&i| scene[i].is_some_and(|(p, his)| his && p.dot(&up) < -1.2)).collect();
        assert!(!feet.is_empty());
        assert!(feet.iter().all(|&i| f32::from(depth[i]) / 1000.0 > (1.0 + COAST_DEPTH_GATE) * median), "beyond the depth gate");
        assert!(feet.iter().all(|&i| his(i)), "his feet are his");
        for (i, s) in scene.iter().enumerate() {
            if let Some((p, false)) = s {
                let from_axis = (p - forward * 1.3).cross(&up).norm();
                assert!(!his(i) || from_axis <= MIN_BODY_RADIUS_M + 0.02, "pixel {i}, {from_axis:.3} m from his axis");
            }
        }
    }

    /// A person out of view may walk on: his body widens by a walking pace per
    /// frame since he was last detected (at most `MAX_UNSEEN_GROWTH_M`), so where he
    /// stopped unseen is his too (a body in view follows his points instead).
    #[test]
    fn an_unseen_persons_body_widens_at_a_walking_pace() {
        let (w, h) = (160usize, 40usize);
        let mut masker = DynamicMasker::new(pinhole(w, h, 40.0), PerceptionConfig::default(), &["person".to_string()]).expect("masker");
        // A wall 2 m ahead: at 2 m a pixel is 5 cm, column 80 is straight ahead.
        let depth = vec![2000u16; w * h];
        let up = -Vector3::y();
        let seen: Vec<[f32; 3]> = (0..40).map(|k| [0.0, (k as f32 - 20.0) * 0.05, 2.0]).collect();
        let body = Body::around(1, &seen, up, 2.0).expect("a body");
        let person =
            Track { id: 1, detected_at: 0, depth_m: Some(2.0), class_id: 0, score: 0.9, points: None, moved: true, body: Some(body) };
        let labelled_columns = |m: &mut DynamicMasker, sequence: u64| {
            m.chain = Some(PoseChain { sequence, anchor_from_camera: Isometry3::identity(), motion: Isometry3::identity(), epoch: 1 });
            let mut labels = vec![PixelLabel::Static as u8; w * h];
            m.label_bodies(&mut labels, sequence, &depth);
            (0..w).filter(|&x| labels[20 * w + x] == PixelLabel::PriorDynamic as u8).count()
        };
        masker.offscreen = vec![person];
        let narrow = labelled_columns(&mut masker, 0);
        assert_eq!(narrow, 17, "radius 0.4 m, the least a body takes: columns 72..=88");
        // 10 frames unseen: 0.2 m wider on each side (4 columns).
        assert_eq!(labelled_columns(&mut masker, 10), narrow + 2 * 4);
        // 50 frames: at most 0.5 m (10 columns).
        assert_eq!(labelled_columns(&mut masker, 50), narrow + 2 * 10);
    }

    /// A person gets a body once he was seen moving, detected or coasting; a person
    /// who never moved (the seated man) and other classes never do, nor does anyone
    /// without an up direction.
    #[test]
    fn only_people_who_moved_get_a_body() {
        let (w, h) = (96usize, 72usize);
        let mut masker = DynamicMasker::new(pinhole(w, h, 40.0), PerceptionConfig::default(), &["person".to_string(), "chair".to_string()])
            .expect("masker");
        let depth = vec![2000u16; w * h];
        let pixels: Vec<usize> = (20..36).flat_map(|y| (44..52).map(move |x| y * w + x)).collect();
        let here = (1u32, Isometry3::identity());
        let mut person = masker.track_from(1, (0, 0.9), 5, (&pixels, &pixels), &depth, Some(&here), None);
        assert!(masker.body_of(&person).is_none(), "no up direction yet");
        masker.up = Some((1, -Vector3::y()));
        assert!(masker.body_of(&person).is_none(), "never moved");
        person.moved = true;
        let body = masker.body_of(&person).expect("a body");
        // 0.75 m of him seen (rows 20..=35 at 5 cm): a 2 m body may reach 1.25 m above or below.
        assert!((body.heights.1 - body.heights.0 - 3.25).abs() < 1e-6, "heights {:?}", body.heights);
        let mut chair = masker.track_from(2, (1, 0.9), 5, (&pixels, &pixels), &depth, Some(&here), None);
        chair.moved = true;
        assert!(masker.body_of(&chair).is_none(), "a chair has no body");
        masker.up = Some((2, -Vector3::y()));
        assert!(masker.body_of(&person).is_none(), "points of another epoch");
    }

    /// The map's kept-out pixels grow over the surface they stand on (a person's
    /// feet onto the floor), never across a depth edge, then dilate by a few pixels.
    #[test]
    fn the_mapping_mask_grows_over_its_surface_and_dilates() {
        let (w, h) = (80usize, 40usize);
        let camera = pinhole(w, h, 60.0);
        let mut config = PerceptionConfig::default();
        config.fusion.mapping_mask_growth_px = 10;
        config.fusion.mapping_mask_dilation_px = 2;
        let masker = DynamicMasker::new(camera, config, &[]).expect("masker");
        // Left half: one surface at 2 m (a floor, say); right half: a wall at 4 m.
        let depth: Vec<u16> = (0..w * h).map(|i| if i % w < 40 { 2000 } else { 4000 }).collect();
        // A dynamic block at columns 20..30, rows 10..20.
        let labels: Vec<u8> = (0..w * h)
            .map(|i| {
                if (20..30).contains(&(i % w)) && (10..20).contains(&(i / w)) {
                    PixelLabel::Dynamic as u8
                } else {
                    PixelLabel::Static as u8
                }
            })
            .collect();
        let fused = Fused { width: w, height: h, labels, instances: vec![], flow_regions: 0, rejected_regions: 0 };
        let mask = masker.mapping_mask(&fused, &depth).expect("mask");
        let at = |x: usize, y: usize| mask[y * w + x] != 0;
        assert!(at(25, 15) && at(19, 15), "the block and its neighbour");
        assert!(at(10, 15) && !at(7, 15), "grown 10 px over the surface, dilated by 2");
        assert!(at(39, 15) && at(41, 15), "reached the depth edge; the dilation crosses it by 2 px");
        assert!(!at(43, 15), "the wall behind is never grown into");
        let nothing = Fused { labels: vec![PixelLabel::Static as u8; w * h], ..fused };
        assert!(masker.mapping_mask(&nothing, &depth).expect("mask").iter().all(|&m| m == 0));
        assert!(matches!(masker.mapping_mask(&nothing, &depth[1..]), Err(PerceptionError::Input(_))));
    }
}
