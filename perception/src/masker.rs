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

use nalgebra::Isometry3;
use stillmap_tracking::Camera;

use crate::PerceptionError;
use crate::config::{PerceptionConfig, PriorDynamicTracking};
use crate::ego::{EgoMotion, EgoResult};
use crate::flow::{FlowField, SmallGray, farneback};
use crate::fusion::{Fused, PixelLabel, cell_centres, dynamic_fraction, fuse, grow_over_depth};
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
    flow: FlowField,
}

impl FlowStep {
    /// Frame intervals the step spans (more than one after drops).
    fn frames(&self) -> u64 {
        self.to - self.from
    }
}

struct Carried {
    segmentation: Segmentation,
    source_sequence: u64,
    at_sequence: u64,
}

/// Per-camera perception state.
pub struct DynamicMasker {
    camera: Camera,
    config: PerceptionConfig,
    ego: EgoMotion,
    prior_dynamic: Vec<bool>,
    previous: Option<(u64, SmallGray)>,
    flows: VecDeque<FlowStep>,
    carried: Option<Carried>,
    last_ego: Option<EgoResult>,
    /// Frames (sequence numbers) the last result's motion spans: more than one after drops.
    last_ego_frames: u64,
    /// The last finished frame's dynamic flow-grid cells (1 = dynamic).
    dynamic_grid: Option<(u64, Vec<u8>)>,
    /// A prepared frame waiting for `finish`.
    pending: Option<Pending>,
}

struct Pending {
    sequence: u64,
    small: SmallGray,
    previous: Option<SmallGray>,
    /// Flow-grid cells the ego-motion estimate ignores.
    exclude: Vec<u8>,
    /// Compensation, labels and their dynamic flow-grid cells computed before
    /// tracking (`ego_motion.before_tracking`).
    early: Option<(EgoResult, Fused, Vec<u8>)>,
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
        Ok(Self { camera, config, ego, prior_dynamic, previous: None, flows: VecDeque::new(), carried: None, last_ego: None, last_ego_frames: 1, dynamic_grid: None, pending: None })
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
        let previous = self.previous.take().filter(|(prev_seq, _)| *prev_seq < input.sequence);
        let flow = match &previous {
            Some((prev_seq, prev)) => {
                Some(FlowStep { from: *prev_seq, to: input.sequence, flow: farneback(&small, prev, &self.config.flow, s)? })
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
                    self.carried = Some(Carried { segmentation: warp_segmentation(&c.segmentation, &step.flow), at_sequence: step.to, ..c });
                }
            }
            None => {
                self.flows.clear();
                self.carried = None;
            }
        }
        if let Some(step) = flow {
            self.flows.push_back(step);
            while self.flows.len() > max_age as usize {
                self.flows.pop_front();
            }
        }
        if let Some((k, seg)) = input.segmentation {
            let newer = self.carried.as_ref().is_none_or(|c| c.source_sequence < k);
            if newer && let Some(seg) = self.carry_to(k, seg, input.sequence) {
                self.carried = Some(Carried { segmentation: seg, source_sequence: k, at_sequence: input.sequence });
            }
        }
        self.carried.take_if(|c| input.sequence - c.source_sequence > max_age || c.at_sequence != input.sequence);

        // What the camera-motion estimate must not listen to: the carried dynamic
        // cells and prior-dynamic instances.
        let exclude = self.exclusion_grid(self.carried.as_ref().map(|c| &c.segmentation), carried_dynamic.as_deref());
        times.warp = t.elapsed();

        // This frame's own labels, before tracking: compensation with the previous
        // frame's motion as the prediction (constant velocity), refined on the flow.
        let early = if self.config.ego_motion.before_tracking {
            let t = Instant::now();
            // Constant velocity over the frames this step spans (more than one after drops).
            let step_frames = self.latest_step(input.sequence).map_or(1, FlowStep::frames);
            let factor = step_frames as f64 / self.last_ego_frames.max(1) as f64;
            let predicted = self.last_ego.as_ref().map(|e| scaled(&e.previous_from_current, factor));
            let ego = self.compensate(input.sequence, &small, previous.as_ref().map(|(_, p)| p), input.depth, predicted, &exclude);
            times.ego_motion += t.elapsed();
            ego.map(|ego| {
                let t = Instant::now();
                let fused = fuse(w, h, s as usize, Some(&ego), self.carried.as_ref().map(|c| &c.segmentation), &self.prior_dynamic, &self.config.fusion);
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
        // the prediction when it beat one in the vote) labels pixels for tracking:
        // an unchecked prediction (no refinement held: a sudden acceleration,
        // motion blur) can call most of the scene moving and starve the tracker.
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
                    Some((ego, _, _)) => grow_over_surfaces(seeds, &ego.depth_m, gw, gh, growth_cells, self.config.fusion.region_depth_ratio),
                    None => grow_over_surfaces(seeds, &self.ego.sample_depth(input.depth), gw, gh, growth_cells, self.config.fusion.region_depth_ratio),
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
        self.pending = Some(Pending { sequence: input.sequence, small, previous: previous.map(|(_, p)| p), exclude, early, times });
        Ok(mask)
    }

    /// Second phase (labels already made in `prepare`: re-decided only when the
    /// tracked motion disagrees and leaves fewer pixels moving; otherwise):
    /// ego-motion compensation with the camera motion
    /// `previous_from_current` (the tracker's, from the static features; `None`
    /// when tracking failed: the flow refines identity then), and fusion into this
    /// frame's labels. `depth` is the frame's, as given to `prepare`.
    pub fn finish(&mut self, depth: &[u16], previous_from_current: Option<Isometry3<f64>>) -> Result<MaskOutput, PerceptionError> {
        let Some(Pending { sequence, small, previous, exclude, early, mut times }) = self.pending.take() else {
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
                    (Some(step), Some(prev), Some(tracked)) => self.ego.reconsider(&step.flow, &small, prev, &early_ego, &tracked, Some(&exclude)),
                    _ => None,
                };
                times.ego_motion += t.elapsed();
                match better {
                    Some(ego) => (Some(ego), None),
                    None => (Some(early_ego), Some((early_fused, early_cells))),
                }
            }
            None => {
                let ego = self.compensate(sequence, &small, previous.as_ref(), depth, previous_from_current, &exclude);
                times.ego_motion += t.elapsed();
                (ego, None)
            }
        };
        self.previous = Some((sequence, small));

        let t = Instant::now();
        let (fused, cells) = match fused {
            Some(labelled) => labelled,
            None => {
                let segmentation = self.carried.as_ref().map(|c| &c.segmentation);
                let fused = fuse(w, h, s as usize, ego.as_ref(), segmentation, &self.prior_dynamic, &self.config.fusion);
                let cells = self.dynamic_cells(&fused.labels);
                (fused, cells)
            }
        };
        let dynamic_fraction = dynamic_fraction(&fused.labels, depth);
        self.dynamic_grid = Some((sequence, cells));
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
            self.last_ego_frames = self.latest_step(sequence).map_or(1, FlowStep::frames);
        }
        self.last_ego = ego;
        times.total += started.elapsed();
        Ok(MaskOutput {
            fused,
            source,
            segmentation_sequence: self.carried.as_ref().map(|c| c.source_sequence),
            ego: summary,
            dynamic_fraction,
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
        depth: &[u16],
        prior: Option<Isometry3<f64>>,
        exclude: &[u8],
    ) -> Option<EgoResult> {
        match (self.latest_step(sequence), previous) {
            (Some(step), Some(prev)) => Some(self.ego.compensate(&step.flow, small, prev, depth, prior, Some(exclude))),
            _ => None,
        }
    }

    /// The latest flow step, when it ends at frame `sequence`.
    fn latest_step(&self, sequence: u64) -> Option<&FlowStep> {
        self.flows.back().filter(|step| step.to == sequence)
    }

    fn is_prior_dynamic(&self, seg: &Segmentation, id: u16) -> bool {
        seg.instance(id).is_some_and(|i| self.prior_dynamic.get(usize::from(i.class_id)).copied().unwrap_or(false))
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

/// A motion scaled along its screw, approximately: the rotation's angle and the
/// translation both times `factor` (constant velocity over `factor` frame intervals).
fn scaled(motion: &Isometry3<f64>, factor: f64) -> Isometry3<f64> {
    if factor == 1.0 {
        return *motion;
    }
    Isometry3::from_parts((motion.translation.vector * factor).into(), motion.rotation.powf(factor))
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
    imgproc::dilate(&src, &mut out, &kernel, Point::new(-1, -1), 1, opencv::core::BORDER_CONSTANT, imgproc::morphology_default_border_value()?)?;
    Ok(out.data_bytes()?.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// A board at 0.8 m in front of a wall at 2 m, on a 12×5 grid; one cell of the
    /// board is flagged. Growth covers the board within reach, never the wall, and
    /// stops at cells without depth.
    #[test]
    fn growth_follows_the_surface_and_stops_at_depth_edges_holes_and_its_reach() {
        let (w, h) = (12, 5);
        // Columns 0–7 board (with a hole at (4, 2)), 8–11 wall.
        let depth: Vec<f32> = (0..w * h).map(|i| match (i % w, i / w) {
            (4, 2) => 0.0,
            (x, _) if x < 8 => 0.8 + 0.01 * x as f32,
            _ => 2.0,
        }).collect();
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
        let twice = scaled(&m, 2.0);
        assert!((twice.rotation.angle() - 0.06).abs() < 1e-12);
        assert!((twice.translation.vector - Vector3::new(0.02, -0.04, 0.01)).norm() < 1e-12);
        assert_eq!(scaled(&m, 1.0), m);
        let half = scaled(&m, 0.5);
        assert!((half.rotation.angle() - 0.015).abs() < 1e-12);
    }

    /// The map's kept-out pixels grow over the surface they stand on (a person's
    /// feet onto the floor), never across a depth edge, then dilate by a few pixels.
    #[test]
    fn the_mapping_mask_grows_over_its_surface_and_dilates() {
        let (w, h) = (80usize, 40usize);
        let camera = Camera {
            width: w as u32,
            height: h as u32,
            fx: 60.0,
            fy: 60.0,
            cx: 40.0,
            cy: 20.0,
            distortion: None,
            depth_units_per_metre: 1000.0,
            readout_s: 0.0,
        };
        let mut config = PerceptionConfig::default();
        config.fusion.mapping_mask_growth_px = 10;
        config.fusion.mapping_mask_dilation_px = 2;
        let masker = DynamicMasker::new(camera, config, &[]).expect("masker");
        // Left half: one surface at 2 m (a floor, say); right half: a wall at 4 m.
        let depth: Vec<u16> = (0..w * h).map(|i| if i % w < 40 { 2000 } else { 4000 }).collect();
        // A dynamic block at columns 20..30, rows 10..20.
        let labels: Vec<u8> = (0..w * h)
            .map(|i| if (20..30).contains(&(i % w)) && (10..20).contains(&(i / w)) { PixelLabel::Dynamic as u8 } else { PixelLabel::Static as u8 })
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
