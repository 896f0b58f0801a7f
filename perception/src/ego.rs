//! Ego-motion compensation (beyond the paper).
//!
//! Thresholding raw flow marks everything as moving once the camera moves. Here
//! each pixel's flow is *predicted* from its depth and the camera motion
//! `previous_from_current`, and only the residual `measured − predicted` counts,
//! against a threshold scaled by the uncertainty of the prediction (flow noise and
//! the depth noise σ_z = a + b·z² carried through the projection).
//!
//! Residual flow is confirmed photometrically (Farneback's flow on textureless
//! surfaces is unconstrained): the pixel's patch must be explained badly by the
//! camera motion and clearly better by the measured flow.
//!
//! The motion is the tracker's (from static features) and refinements of it on
//! the flow itself: one textured flow sample with depth per grid cell gives a
//! dense 3D–2D correspondence set (a point in the current camera, its pixel in the
//! previous image) for the tracker's robust pose optimisation, started from the
//! tracked motion (without one: from identity and an EPnP-RANSAC hypothesis).
//! Flow alone cannot tell the camera's motion from that of a large textured
//! moving object, so of these candidates the one under which the fewest pixels
//! move wins (a refinement beats its prior only by more than
//! `ego_motion.refinement_margin`), with known dynamic pixels left out of the
//! samples and the vote.

use nalgebra::{Isometry3, Point2, Point3};
use stillmap_tracking::Camera;
use stillmap_tracking::geometry::{Measurement, PnpRansac, pnp_ransac};
use stillmap_tracking::optimize::optimize_pose;

use crate::config::EgoMotionConfig;
use crate::flow::{FlowField, SmallGray};

/// Per flow pixel: no prediction possible (no valid depth).
pub const NO_PREDICTION: u8 = 0;
/// Per flow pixel: flow agrees with the camera's own motion.
pub const CONSISTENT: u8 = 1;
/// Per flow pixel: residual flow beyond its uncertainty.
pub const RESIDUAL: u8 = 2;

/// The outcome of ego-motion compensation for one frame, on the flow grid.
#[derive(Debug, Clone)]
pub struct EgoResult {
    /// The camera motion used for the prediction.
    pub previous_from_current: Isometry3<f64>,
    /// Whether the motion was refined on the flow (else the prior alone was used).
    pub refined: bool,
    /// Whether the flow tested the motion: it is a refinement on the flow, or a
    /// prior that a refinement did not beat in the vote (by more than
    /// `ego_motion.refinement_margin`; false: a prior nothing could check).
    pub confirmed: bool,
    /// Whether the motion is a prior given to the estimate, as it was (not a
    /// refinement, not identity left where no prior was given and no refinement held).
    pub from_prior: bool,
    /// Flow samples used by the refinement, and how many it kept as inliers.
    pub samples: usize,
    pub inliers: usize,
    /// [`NO_PREDICTION`], [`CONSISTENT`] or [`RESIDUAL`] per flow pixel.
    pub class: Vec<u8>,
    /// Residual flow magnitude in full-size pixels (0 without a prediction).
    pub residual_px: Vec<f32>,
    /// Depth (metres) per flow pixel, 0 when invalid.
    pub depth_m: Vec<f32>,
}

/// One frame's flow-grid samples: depth in metres (0 when invalid) and texture
/// (the smaller eigenvalue of the structure tensor) per flow pixel.
#[derive(Debug, Clone)]
pub struct FrameSamples {
    pub depth_m: Vec<f32>,
    pub texture: Vec<f32>,
}

/// Per flow cell: the class and the residual (full-size pixels) under one motion.
type Classified = (Vec<u8>, Vec<f32>);

/// What [`EgoMotion::movers_over_baseline`] found.
#[derive(Debug, Clone)]
pub struct BaselineMovers {
    /// The winning camera motion over the baseline.
    pub reference_from_current: Isometry3<f64>,
    /// Per flow cell: 1 where the composed flow is not explained by it (each judged
    /// cell's value fills its block).
    pub moving: Vec<u8>,
    /// Distinct candidate motions compared.
    pub candidates: usize,
}

/// Ego-motion compensation for one camera; caches per-pixel rays of the flow grid.
pub struct EgoMotion {
    camera: Camera,
    config: EgoMotionConfig,
    subsample: usize,
    width: usize,
    height: usize,
    /// Per flow pixel: raw (distorted) full-size position of its centre and its ideal ray.
    raw: Vec<Point2<f64>>,
    ray: Vec<Point2<f64>>,
}

/// Fewer refinement inliers than this fraction of the samples: the refinement is not trusted.
const MIN_INLIER_FRACTION: f64 = 0.3;
/// `ego_motion.refinement_margin` holds where the prediction leaves at least this
/// share of the vote cells moving: below it, the two motions do not conflict and the
/// refinement, the better estimate, wins.
const CONFLICT_SHARE: f64 = 0.01;
/// Candidate motions are compared on every `VOTE_STRIDE`-th flow cell in each direction.
const VOTE_STRIDE: usize = 2;
/// Two candidate motions closer than this (metres and radians) are the same.
const SAME_MOTION: f64 = 1e-6;
/// [`EgoMotion::reconsider`]: a candidate motion this close to the chosen one
/// (metres, radians; about half a pixel at 1 m for a 525 px lens) classifies
/// the same pixels.
pub const RECONSIDER_TOLERANCE_M: f64 = 0.001;
pub const RECONSIDER_TOLERANCE_RAD: f64 = 0.001;
/// [`EgoMotion::movers_over_baseline`]: a cell whose composed flow lands on a
/// surface farther from its own depth than this fraction was uncovered during the
/// baseline (an occlusion, not a mover). A person walking at 1.5 m/s moves 0.2 m in
/// depth over 4 frames, an eighth of his distance at 1.5 m; a thing held in front of
/// a wall is usually twice as near as the wall or more.
const OCCLUSION_DEPTH_RATIO: f64 = 0.25;
/// PnP-RANSAC hypothesis: iterations, inlier threshold in flow σ, and confidence.
const RANSAC_ITERATIONS: i32 = 100;
const RANSAC_THRESHOLD_SIGMAS: f64 = 3.0;
const RANSAC_CONFIDENCE: f64 = 0.99;

impl EgoMotion {
    pub fn new(camera: Camera, config: EgoMotionConfig, subsample: u32) -> Self {
        let s = subsample.max(1) as usize;
        let (width, height) = (camera.width as usize / s, camera.height as usize / s);
        let mut raw = Vec::with_capacity(width * height);
        let mut ray = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                // Centre of the s×s block in full-size pixel coordinates.
                let r = Point2::new((x as f64 + 0.5) * s as f64 - 0.5, (y as f64 + 0.5) * s as f64 - 0.5);
                let ideal = camera.undistort(&r);
                raw.push(r);
                ray.push(Point2::new((ideal.x - camera.cx) / camera.fx, (ideal.y - camera.cy) / camera.fy));
            }
        }
        Self { camera, config, subsample: s, width, height, raw, ray }
    }

    /// Depth in metres per flow pixel: the block's centre reading, else any valid one in the block.
    pub fn sample_depth(&self, depth: &[u16]) -> Vec<f32> {
        let s = self.subsample;
        let w = self.camera.width as usize;
        let scale = 1.0 / self.camera.depth_units_per_metre;
        let (lo, hi) = (self.config.min_depth_m, self.config.max_depth_m);
        let mut out = vec![0f32; self.width * self.height];
        for y in 0..self.height {
            for x in 0..self.width {
                let (cx, cy) = (x * s + s / 2, y * s + s / 2);
                let mut d = depth[cy * w + cx];
                if d == 0 {
                    'block: for by in 0..s {
                        for bx in 0..s {
                            d = depth[(y * s + by) * w + x * s + bx];
                            if d != 0 {
                                break 'block;
                            }
                        }
                    }
                }
                let z = f64::from(d) * scale;
                if d != 0 && (lo..=hi).contains(&z) {
                    out[y * self.width + x] = z as f32;
                }
            }
        }
        out
    }

    /// Where the scene point at flow pixel `i` and depth `z` was in the previous raw
    /// image (what `classify` computes inline; the tests build exact flow with it).
    #[cfg(test)]
    fn predict(&self, i: usize, z: f64, previous_from_current: &Isometry3<f64>) -> Option<Point2<f64>> {
        let r = self.ray[i];
        let point_in_current = Point3::new(r.x * z, r.y * z, z);
        let point_in_previous = previous_from_current * point_in_current;
        let ideal = self.camera.project(&point_in_previous)?;
        Some(self.camera.distort(&ideal))
    }

    /// Flow samples for a refinement: current-camera points (from `depth_m`) against
    /// their flow targets in the earlier image, with `information` (1/σ²); only
    /// every `stride`-th cell in each direction is looked at (where the flow is).
    fn flow_samples(
        &self,
        flow: &FlowField,
        texture: &[f32],
        depth_m: &[f32],
        exclude: Option<&[u8]>,
        information: f64,
        stride: usize,
    ) -> Vec<(Point3<f64>, Measurement)> {
        let s = self.subsample as f64;
        let step = self.config.sample_step.max(1) as usize;
        let mut correspondences = Vec::new();
        // One sample per step×step cell, at its most textured pixel, so that no
        // compact textured object can outvote the rest of the scene.
        for cy in (0..self.height).step_by(step) {
            for cx in (0..self.width).step_by(step) {
                let mut best: Option<(f32, usize)> = None;
                // Only every `stride`-th cell has flow (whatever `sample_step` is).
                for y in (cy.next_multiple_of(stride)..(cy + step).min(self.height)).step_by(stride) {
                    for x in (cx.next_multiple_of(stride)..(cx + step).min(self.width)).step_by(stride) {
                        let i = y * self.width + x;
                        if depth_m[i] == 0.0 || exclude.is_some_and(|m| m[i] != 0) {
                            continue;
                        }
                        if best.is_none_or(|(t, _)| texture[i] > t) {
                            best = Some((texture[i], i));
                        }
                    }
                }
                let Some((t, i)) = best else { continue };
                if f64::from(t) < self.config.min_texture {
                    continue;
                }
                let z = f64::from(depth_m[i]);
                let r = self.ray[i];
                let f = flow.data[i];
                let target_raw = Point2::new(self.raw[i].x + f64::from(f[0]) * s, self.raw[i].y + f64::from(f[1]) * s);
                let ideal = self.camera.undistort(&target_raw);
                correspondences.push((Point3::new(r.x * z, r.y * z, z), Measurement { ideal, disparity: None, information }));
            }
        }
        correspondences
    }

    /// Chooses the camera motion (`prior`, the tracked one, or a refinement on the
    /// flow) and classifies every flow pixel under it. `current` and `previous`
    /// are the flow's grey images; `exclude` (flow-grid sized, nonzero = skip) keeps
    /// known dynamic pixels out of the refinement.
    pub fn compensate(
        &self,
        flow: &FlowField,
        current: &SmallGray,
        previous: &SmallGray,
        depth: &[u16],
        prior: Option<Isometry3<f64>>,
        exclude: Option<&[u8]>,
    ) -> EgoResult {
        self.compensate_sampled(flow, current, previous, self.frame_samples(current, depth), prior, exclude, 1.0)
    }

    /// The frame's flow-grid depth and texture, which [`compensate_sampled`](Self::compensate_sampled)
    /// and [`movers_over_baseline`](Self::movers_over_baseline) share.
    pub fn frame_samples(&self, current: &SmallGray, depth: &[u16]) -> FrameSamples {
        FrameSamples { depth_m: self.sample_depth(depth), texture: min_eigen_texture(current) }
    }

    /// [`compensate`](Self::compensate) with the frame's samples taken already, for a
    /// flow step spanning `intervals` frame intervals (`ego_motion.frame_interval_s`;
    /// 1 at the camera's full rate): the flow's noise scales with them.
    #[allow(clippy::too_many_arguments)]
    pub fn compensate_sampled(
        &self,
        flow: &FlowField,
        current: &SmallGray,
        previous: &SmallGray,
        frame: FrameSamples,
        prior: Option<Isometry3<f64>>,
        exclude: Option<&[u8]>,
        intervals: f64,
    ) -> EgoResult {
        debug_assert_eq!((flow.width, flow.height), (self.width, self.height));
        let FrameSamples { depth_m, texture } = frame;
        let intervals = intervals.max(1.0);
        let sigma = self.config.flow_sigma_px * intervals;
        // `classify` composes noise as variances: n intervals' σ, n-fold, is n² steps.
        let noise_steps = intervals * intervals;

        // Refinement: current-camera points against their flow targets in the previous image.
        let information = 1.0 / (sigma * sigma);
        let correspondences = self.flow_samples(flow, &texture, &depth_m, exclude, information, 1);
        let samples = correspondences.len();

        // Candidate camera motions: the tracked one (from static features) and its
        // refinement on the flow; with no tracked motion, refinements of identity
        // and of an EPnP-RANSAC hypothesis. `optimize_pose`
        // estimates camera_from_world: here previous_from_current, with the current
        // camera frame playing the world.
        let mut candidates: Vec<(Isometry3<f64>, bool, usize)> = prior.map(|p| (p, false, 0)).into_iter().collect();
        if samples >= self.config.min_samples && (prior.is_none() || self.config.refine_tracked_motion) {
            // Without a tracked motion, an EPnP-RANSAC hypothesis competes with
            // identity (with one, it never won on the composite and costs ~1.5 ms).
            let hypothesis = if prior.is_some() {
                None
            } else {
                let pairs: Vec<_> = correspondences.iter().map(|(p, m)| (*p, m.ideal)).collect();
                let params = PnpRansac {
                    iterations: RANSAC_ITERATIONS,
                    threshold_px: (sigma * RANSAC_THRESHOLD_SIGMAS) as f32,
                    confidence: RANSAC_CONFIDENCE,
                };
                pnp_ransac(&self.camera, &pairs, params).map(|(pose, _)| pose)
            };
            for start in [Some(prior.unwrap_or_else(Isometry3::identity)), hypothesis].into_iter().flatten() {
                let estimate = optimize_pose(&self.camera, 1.0, start, &correspondences);
                let n = estimate.inlier_count;
                if n >= self.config.min_samples && n as f64 >= MIN_INLIER_FRACTION * samples as f64 {
                    candidates.push((estimate.camera_from_world, true, n));
                }
            }
        }
        // The camera's motion is the one under which the scene is static: the
        // flow alone cannot tell it from the motion of a large, well-textured moving
        // object (that refinement leaves the whole background moving), so the
        // candidate leaving the fewest pixels moving wins; a refinement beats the
        // prior (first among the candidates) only by more than
        // `refinement_margin`, where the prior leaves a part of the view moving
        // (`clear_of_prediction`). Known dynamic pixels
        // (`exclude`) do not vote: a person must not make its own motion the camera's.
        // Candidates are compared on every other cell in each direction; the winner
        // is then classified in full.
        let (mut previous_from_current, mut refined, mut inliers) =
            candidates.first().copied().unwrap_or((Isometry3::identity(), false, 0));
        let mut classified = None;
        if candidates.len() > 1 {
            let mut best = usize::MAX;
            let mut seen: Vec<Isometry3<f64>> = Vec::new();
            // The unrefined prior's moving cells, when it is a candidate (it comes first).
            let mut predicted_moving: Option<usize> = None;
            let vote_cells = self.width.div_ceil(VOTE_STRIDE) * self.height.div_ceil(VOTE_STRIDE);
            for &(motion, is_refined, n) in &candidates {
                // Refinements from different starts often converge to the same motion.
                if seen.iter().any(|m| {
                    (m.inverse() * motion).translation.vector.norm() < SAME_MOTION && (m.inverse() * motion).rotation.angle() < SAME_MOTION
                }) {
                    continue;
                }
                seen.push(motion);
                let vote = self.classify(flow, current, previous, &depth_m, &motion, noise_steps, Cells::VoteGrid, None);
                let moving = moving_count(&vote.0, exclude);
                if !is_refined {
                    predicted_moving.get_or_insert(moving);
                }
                let clear = !is_refined || clear_of_prediction(moving, predicted_moving, self.config.refinement_margin, vote_cells);
                if moving < best && clear {
                    (best, previous_from_current, refined, inliers, classified) = (moving, motion, is_refined, n, Some(vote));
                }
            }
        }
        // The winner's vote cells are classified already.
        let (class, residual_px) = match classified {
            Some(vote) => {
                self.classify(flow, current, previous, &depth_m, &previous_from_current, noise_steps, Cells::OffVoteGrid, Some(vote))
            }
            None => self.classify(flow, current, previous, &depth_m, &previous_from_current, noise_steps, Cells::All, None),
        };
        let confirmed = candidates.iter().any(|&(_, is_refined, _)| is_refined);
        let from_prior = prior.is_some() && !refined;
        EgoResult { previous_from_current, refined, confirmed, from_prior, samples, inliers, class, residual_px, depth_m }
    }

    /// Classifies flow pixels under `previous_from_current`: their class and
    /// residual in full-size pixels. Only the `cells` asked for are classified, into
    /// `into` when given (the others keep their values; [`NO_PREDICTION`] and 0 in
    /// a new result).
    #[allow(clippy::too_many_arguments)]
    fn classify(
        &self,
        flow: &FlowField,
        current: &SmallGray,
        previous: &SmallGray,
        depth_m: &[f32],
        previous_from_current: &Isometry3<f64>,
        steps: f64,
        cells: Cells,
        into: Option<Classified>,
    ) -> Classified {
        let s = self.subsample as f64;
        let n = self.width * self.height;
        let (mut class, mut residual_px) = into.unwrap_or_else(|| (vec![NO_PREDICTION; n], vec![0f32; n]));
        let (a, b) = (self.config.depth_sigma_a_m, self.config.depth_sigma_b_per_m);
        // The flow's noise adds up over the `steps` flows composed into `flow`.
        let flow_var = self.config.flow_sigma_px * self.config.flow_sigma_px * steps;
        let min_residual_px = self.config.min_residual_px * steps.sqrt();
        let rotation = previous_from_current.rotation.to_rotation_matrix();
        let translation = previous_from_current.translation.vector;
        let w = self.width;
        // Vote-grid cells are those with both coordinates multiples of VOTE_STRIDE.
        let (row_step, col_step) = match cells {
            Cells::VoteGrid => (VOTE_STRIDE, VOTE_STRIDE),
            Cells::All | Cells::OffVoteGrid => (1, 1),
        };
        for y in (0..self.height).step_by(row_step) {
            let vote_row = y.is_multiple_of(VOTE_STRIDE);
            for x in (0..w).step_by(col_step) {
                if cells == Cells::OffVoteGrid && vote_row && x.is_multiple_of(VOTE_STRIDE) {
                    continue;
                }
                let i = y * w + x;
                let z = f64::from(depth_m[i]);
                if z == 0.0 {
                    continue;
                }
                // point_in_previous = z · (R · ray) + t, at the depth and one σ_z farther.
                let r = self.ray[i];
                let q = rotation * nalgebra::Vector3::new(r.x, r.y, 1.0);
                let far = Point3::from(q * (z + a + b * z * z) + translation);
                let Some(ideal) = self.camera.project(&Point3::from(q * z + translation)) else { continue };
                if far.z <= 0.0 {
                    continue; // no prediction one σ_z farther (what `project` refuses)
                }
                let p = self.camera.distort(&ideal);
                let f = flow.data[i];
                let measured = Point2::new(self.raw[i].x + f64::from(f[0]) * s, self.raw[i].y + f64::from(f[1]) * s);
                let residual = (measured - p).norm();
                residual_px[i] = residual as f32;
                // The threshold is never below min_residual_px: most pixels are decided
                // without the depth term.
                let moving = residual > min_residual_px
                    && {
                        // The depth's effect on the prediction, through the pinhole (the lens
                        // scales it by a few per cent at most).
                        let ideal_far = self.camera.project(&far).unwrap_or(ideal);
                        let depth_var = (ideal_far - ideal).norm_squared();
                        residual > (self.config.residual_sigmas * (flow_var + depth_var).sqrt()).max(min_residual_px)
                    }
                    && {
                        // Where the camera motion alone puts this pixel in the previous flow image.
                        let (qx, qy) = ((p.x + 0.5) / s - 0.5, (p.y + 0.5) / s - 0.5);
                        // The pixel's own patch, compared where the camera motion and where the flow put it.
                        let here = patch(current, x, y);
                        let d = here.as_ref().and_then(|p| difference_to(p, previous, qx, qy));
                        let measured =
                            here.as_ref().and_then(|p| difference_to(p, previous, x as f64 + f64::from(f[0]), y as f64 + f64::from(f[1])));
                        // Moving when the camera motion explains the patch badly, and clearly
                        // worse than the measured flow does. A pixel whose predicted patch
                        // leaves the image cannot be confirmed and is not called moving
                        // (Farneback is least reliable at the border).
                        match (d, measured) {
                            (Some(d), Some(m)) => d > self.config.photometric_threshold && d > self.config.photometric_ratio * m,
                            (Some(d), None) => d > self.config.photometric_threshold,
                            (None, _) => false,
                        }
                    };
                class[i] = if moving { RESIDUAL } else { CONSISTENT };
            }
        }
        (class, residual_px)
    }

    /// Re-decides `earlier` (a result of [`compensate`](Self::compensate) on the
    /// same flow) against another candidate motion, the tracker's: the two are
    /// compared on every other cell like the candidates in `compensate`, and the
    /// full classification under `candidate` is returned only when it leaves
    /// fewer pixels moving. Motions within [`RECONSIDER_TOLERANCE_M`] /
    /// [`RECONSIDER_TOLERANCE_RAD`] of the earlier one are not worth a vote.
    /// `intervals`: the frame intervals the flow step spans, as in `compensate_sampled`.
    #[allow(clippy::too_many_arguments)]
    pub fn reconsider(
        &self,
        flow: &FlowField,
        current: &SmallGray,
        previous: &SmallGray,
        earlier: &EgoResult,
        candidate: &Isometry3<f64>,
        exclude: Option<&[u8]>,
        intervals: f64,
    ) -> Option<EgoResult> {
        let noise_steps = intervals.max(1.0).powi(2);
        let delta = earlier.previous_from_current.inverse() * candidate;
        if delta.translation.vector.norm() < RECONSIDER_TOLERANCE_M && delta.rotation.angle() < RECONSIDER_TOLERANCE_RAD {
            return None;
        }
        let earlier_moving = self.vote_cells().filter(|&i| earlier.class[i] == RESIDUAL && exclude.is_none_or(|m| m[i] == 0)).count();
        if earlier_moving == 0 {
            return None; // nothing moves: no motion can leave fewer pixels moving
        }
        let vote = self.classify(flow, current, previous, &earlier.depth_m, candidate, noise_steps, Cells::VoteGrid, None);
        let moving = moving_count(&vote.0, exclude);
        if moving >= earlier_moving {
            return None;
        }
        let (class, residual_px) =
            self.classify(flow, current, previous, &earlier.depth_m, candidate, noise_steps, Cells::OffVoteGrid, Some(vote));
        Some(EgoResult {
            previous_from_current: *candidate,
            refined: false,
            // It left fewer pixels moving than the earlier result.
            confirmed: true,
            // The tracker's motion, as it was given.
            from_prior: true,
            samples: earlier.samples,
            inliers: 0,
            class,
            residual_px,
            depth_m: earlier.depth_m.clone(),
        })
    }

    /// What moved over a longer baseline: `composed` is the flow of several frames
    /// (this frame's pixels to where they were in `reference`, the image that many
    /// frames back; `noise_steps`: its noise in one frame's flow variances, Σ n² over
    /// the composed steps, n the frame intervals each spans), read at every [`baseline_stride`](Self::baseline_stride)-th
    /// cell in each direction; each judged cell stands for its block. One frame's
    /// flow cannot tell the camera's motion from that of a large textured thing that
    /// starts moving (a lateral translation with a compensating rotation explains
    /// the far background within the flow's noise);
    /// over several frames the wrong motion's parallax on the background outgrows
    /// the noise. Candidate motions `reference_from_current` are refined on the
    /// composed flow from `starts` (the chained per-frame motions), on the nearer
    /// and on the farther half of the samples (depth layers), and from an
    /// EPnP-RANSAC hypothesis on the samples the
    /// best-supported refinement leaves out (the other rigid motion in view). Each
    /// vote cell then goes to the candidate that explains it best, and the one most
    /// of the scene follows wins; its moving cells are returned, less those the
    /// mover uncovered (whose composed flow lands on another surface in
    /// `reference_depth_m`, the reference frame's flow-grid depth). `None` when
    /// the flow has too few samples.
    #[allow(clippy::too_many_arguments)]
    pub fn movers_over_baseline(
        &self,
        composed: &FlowField,
        noise_steps: f64,
        current: &SmallGray,
        reference: &SmallGray,
        frame: &FrameSamples,
        reference_depth_m: &[f32],
        starts: &[Isometry3<f64>],
        exclude: Option<&[u8]>,
    ) -> Option<BaselineMovers> {
        debug_assert_eq!((composed.width, composed.height), (self.width, self.height));
        let steps_f = noise_steps.max(1.0);
        let (depth_m, texture) = (&frame.depth_m, &frame.texture);
        let sigma = self.config.flow_sigma_px * steps_f.sqrt();
        let correspondences = self.flow_samples(composed, texture, depth_m, exclude, 1.0 / (sigma * sigma), VOTE_STRIDE);
        let samples = correspondences.len();
        if samples < self.config.min_samples {
            return None;
        }
        let params = PnpRansac {
            iterations: RANSAC_ITERATIONS,
            threshold_px: (sigma * RANSAC_THRESHOLD_SIGMAS) as f32,
            confidence: RANSAC_CONFIDENCE,
        };
        let mut candidates: Vec<(Isometry3<f64>, usize)> = Vec::new();
        let refine = |start: Isometry3<f64>, on: &[(Point3<f64>, Measurement)], candidates: &mut Vec<(Isometry3<f64>, usize)>| {
            let estimate = optimize_pose(&self.camera, 1.0, start, on);
            if estimate.inlier_count >= self.config.min_samples {
                candidates.push((estimate.camera_from_world, estimate.inlier_count));
            }
        };
        for &start in starts {
            refine(start, &correspondences, &mut candidates);
        }
        // Depth layers: a thing held in front of the background moves with its own
        // rigid motion; refined on the nearer and on the farther half of the samples
        // (started where the whole scene's refinement ended), each layer's motion is
        // a candidate.
        if let Some(&(best, _)) = candidates.iter().max_by_key(|(_, n)| *n) {
            let mut depths: Vec<f64> = correspondences.iter().map(|(p, _)| p.z).collect();
            depths.sort_by(f64::total_cmp);
            let median = depths[depths.len() / 2];
            for near in [true, false] {
                let layer: Vec<_> = correspondences.iter().filter(|(p, _)| (p.z < median) == near).cloned().collect();
                if layer.len() >= self.config.min_samples {
                    refine(best, &layer, &mut candidates);
                }
            }
        }
        // The other rigid motion: a hypothesis on what the best-supported candidate
        // leaves unexplained, refined there (on all samples, the more textured
        // motion would pull it back).
        if let Some(&(best, _)) = candidates.iter().max_by_key(|(_, n)| *n) {
            let threshold = sigma * RANSAC_THRESHOLD_SIGMAS;
            let rest: Vec<_> = correspondences
                .iter()
                .filter(|(p, m)| self.camera.project(&(best * p)).is_none_or(|q| (q - m.ideal).norm() > threshold))
                .cloned()
                .collect();
            let rest_pairs: Vec<_> = rest.iter().map(|(p, m)| (*p, m.ideal)).collect();
            if rest.len() >= self.config.min_samples
                && let Some((pose, _)) = pnp_ransac(&self.camera, &rest_pairs, params)
            {
                refine(pose, &rest, &mut candidates);
            }
        }
        // Candidates whose predictions differ by less than the flow's noise on
        // average (over the samples' points) are one: the flow cannot tell them apart,
        // and they would split the cells they explain between them. The better
        // supported (more inliers) is kept.
        candidates.sort_by_key(|c| std::cmp::Reverse(c.1));
        let mut distinct: Vec<Isometry3<f64>> = Vec::new();
        for &(motion, _) in &candidates {
            if !distinct.iter().any(|other| self.prediction_gap(&motion, other, depth_m).is_some_and(|gap| gap < 2.0 * sigma)) {
                distinct.push(motion);
            }
        }
        let mut votes: Vec<(Isometry3<f64>, Classified)> = distinct
            .iter()
            .map(|motion| (*motion, self.classify(composed, current, reference, depth_m, motion, steps_f, Cells::VoteGrid, None)))
            .collect();
        // Each vote cell goes to the candidate that explains it best (when it is
        // static under it): the scene splits into the rigid motions in view, and the
        // camera's is the one most of the scene follows. Not the one leaving the
        // fewest cells beyond the noise: a large thing's motion explains the far
        // background within the threshold even over several frames, only less well
        // than the camera's motion, while the camera's motion leaves all of the thing.
        let mut support = vec![0usize; votes.len()];
        for i in self.vote_cells() {
            if exclude.is_some_and(|m| m[i] != 0) || votes.iter().any(|(_, (class, _))| class[i] == NO_PREDICTION) {
                continue;
            }
            let best = votes.iter().enumerate().min_by(|(_, a), (_, b)| a.1.1[i].total_cmp(&b.1.1[i])).map(|(k, _)| k);
            if let Some(k) = best.filter(|&k| votes[k].1.0[i] == CONSISTENT) {
                support[k] += 1;
            }
        }
        // The first (best refined) of equally supported candidates.
        let winner = (0..votes.len()).max_by_key(|&k| (support[k], std::cmp::Reverse(k)))?;
        let (reference_from_current, (class, _)) = votes.swap_remove(winner);
        // A cell the thing uncovered during the baseline (background hidden behind
        // it in the reference image) follows the thing back in the composed flow: it
        // lands on a surface at another depth there. Only cells that land on their own
        // surface are movers.
        let mut moving = vec![0u8; class.len()];
        for y in (0..self.height).step_by(VOTE_STRIDE) {
            for x in (0..self.width).step_by(VOTE_STRIDE) {
                let i = y * self.width + x;
                if class[i] != RESIDUAL {
                    continue;
                }
                let f = composed.data[i];
                // The nearest reference cell (+0.5 and truncation: no libm call).
                let (tx, ty) = (x as f32 + f[0] + 0.5, y as f32 + f[1] + 0.5);
                if tx < 0.0 || ty < 0.0 || tx as usize >= self.width || ty as usize >= self.height {
                    continue;
                }
                let (there, here) = (reference_depth_m[ty as usize * self.width + tx as usize], depth_m[i]);
                let own_surface = there > 0.0 && here > 0.0 && f64::from((there - here).abs()) <= OCCLUSION_DEPTH_RATIO * f64::from(here);
                if own_surface {
                    // The vote cell stands for its VOTE_STRIDE × VOTE_STRIDE block.
                    for by in y..(y + VOTE_STRIDE).min(self.height) {
                        moving[by * self.width + x..by * self.width + (x + VOTE_STRIDE).min(self.width)].fill(1);
                    }
                }
            }
        }
        Some(BaselineMovers { reference_from_current, moving, candidates: distinct.len() })
    }

    /// The baseline judges every `baseline_stride()`-th flow cell in each direction
    /// (its composed flow is needed only there).
    pub fn baseline_stride(&self) -> usize {
        VOTE_STRIDE
    }

    /// Mean distance (full-size pixels) between where two motions put the scene's
    /// points (the cells with depth, every `VOTE_STRIDE`-th in each direction):
    /// `None` without such points.
    pub fn prediction_gap(&self, a: &Isometry3<f64>, b: &Isometry3<f64>, depth_m: &[f32]) -> Option<f64> {
        let (mut sum, mut n) = (0.0, 0usize);
        for i in self.vote_cells() {
            let z = f64::from(depth_m[i]);
            if z == 0.0 {
                continue;
            }
            let p = Point3::new(self.ray[i].x * z, self.ray[i].y * z, z);
            if let (Some(pa), Some(pb)) = (self.camera.project(&(a * p)), self.camera.project(&(b * p))) {
                sum += (pa - pb).norm();
                n += 1;
            }
        }
        (n > 0).then(|| sum / n as f64)
    }

    /// The flow cells candidate motions are compared on, row by row.
    fn vote_cells(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.height).step_by(VOTE_STRIDE).flat_map(move |y| (0..self.width).step_by(VOTE_STRIDE).map(move |x| y * self.width + x))
    }

    pub fn grid_size(&self) -> (usize, usize) {
        (self.width, self.height)
    }
}

/// Which flow cells [`EgoMotion::classify`] works on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Cells {
    All,
    /// Every [`VOTE_STRIDE`]-th cell in each direction (candidate motions are compared there).
    VoteGrid,
    /// The rest.
    OffVoteGrid,
}

/// Whether a refinement leaving `moving` vote cells moving is clear of the
/// unrefined prior's `predicted_moving` (`ego_motion.refinement_margin`): where the
/// prior leaves at least [`CONFLICT_SHARE`] of the `vote_cells` moving, the
/// refinement must leave more than that margin fewer; below it the two do not
/// conflict.
fn clear_of_prediction(moving: usize, predicted_moving: Option<usize>, margin: f64, vote_cells: usize) -> bool {
    match predicted_moving {
        Some(p) if p as f64 >= CONFLICT_SHARE * vote_cells as f64 => (moving as f64) < (1.0 - margin) * p as f64,
        _ => true,
    }
}

fn moving_count(class: &[u8], exclude: Option<&[u8]>) -> usize {
    match exclude {
        Some(m) => class.iter().zip(m).filter(|&(&c, &x)| c == RESIDUAL && x == 0).count(),
        None => class.iter().filter(|&&c| c == RESIDUAL).count(),
    }
}

/// Smaller eigenvalue of the 3×3-summed structure tensor per pixel, divided by 9:
/// the mean squared intensity gradient along the weakest direction (0 at the border).
pub fn min_eigen_texture(image: &SmallGray) -> Vec<f32> {
    let (w, h) = (image.width, image.height);
    let px = |x: usize, y: usize| f32::from(image.data[y * w + x]);
    // Gradient products (gx², gx·gy, gy²) per pixel, then their 3-wide sums along x.
    let mut products = vec![[0f32; 3]; w * h];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let gx = (px(x + 1, y) - px(x - 1, y)) * 0.5;
            let gy = (px(x, y + 1) - px(x, y - 1)) * 0.5;
            products[y * w + x] = [gx * gx, gx * gy, gy * gy];
        }
    }
    let mut row_sums = vec![[0f32; 3]; w * h];
    for y in 1..h - 1 {
        for x in 2..w.saturating_sub(2) {
            let (l, c, r) = (products[y * w + x - 1], products[y * w + x], products[y * w + x + 1]);
            row_sums[y * w + x] = [l[0] + c[0] + r[0], l[1] + c[1] + r[1], l[2] + c[2] + r[2]];
        }
    }
    let mut out = vec![0f32; w * h];
    for y in 2..h.saturating_sub(2) {
        for x in 2..w.saturating_sub(2) {
            let (u, m, d) = (row_sums[(y - 1) * w + x], row_sums[y * w + x], row_sums[(y + 1) * w + x]);
            let (a, b, c) = (u[0] + m[0] + d[0], u[1] + m[1] + d[1], u[2] + m[2] + d[2]);
            let half = (a - c) * 0.5;
            let (mean, diff) = ((a + c) * 0.5, (half * half + b * b).sqrt());
            out[y * w + x] = (mean - diff).max(0.0) / 9.0;
        }
    }
    out
}

/// Mean absolute zero-mean difference between the 3×3 patch of `a` at pixel
/// `(x, y)` and the 3×3 patch of `b` around the subpixel `(qx, qy)` (bilinear);
/// `None` when either patch leaves its image.
pub fn patch_difference(a: &SmallGray, x: usize, y: usize, b: &SmallGray, qx: f64, qy: f64) -> Option<f64> {
    difference_to(&patch(a, x, y)?, b, qx, qy)
}

/// The 3×3 patch of `image` around pixel `(x, y)`, zero-mean; `None` at the border.
fn patch(image: &SmallGray, x: usize, y: usize) -> Option<[f32; 9]> {
    if x < 1 || y < 1 || x + 1 >= image.width || y + 1 >= image.height {
        return None;
    }
    let mut p = [0f32; 9];
    for dy in 0..3 {
        let row = &image.data[(y + dy - 1) * image.width + x - 1..][..3];
        for dx in 0..3 {
            p[dy * 3 + dx] = f32::from(row[dx]);
        }
    }
    let mean = p.iter().sum::<f32>() / 9.0;
    p.iter_mut().for_each(|v| *v -= mean);
    Some(p)
}

/// [`patch_difference`] for a patch already taken (zero-mean) by [`patch`].
fn difference_to(pa: &[f32; 9], b: &SmallGray, qx: f64, qy: f64) -> Option<f64> {
    if qx < 1.0 || qy < 1.0 || qx >= (b.width - 2) as f64 || qy >= (b.height - 2) as f64 {
        return None;
    }
    let (x0, y0) = (qx.floor() as usize, qy.floor() as usize);
    let (tx, ty) = ((qx - x0 as f64) as f32, (qy - y0 as f64) as f32);
    let (w00, w10, w01, w11) = ((1.0 - tx) * (1.0 - ty), tx * (1.0 - ty), (1.0 - tx) * ty, tx * ty);
    let mut pb = [0f32; 9];
    for dy in 0..3 {
        // Rows y0+dy−1 and y0+dy, columns x0−1 ..= x0+2.
        let r0 = &b.data[(y0 + dy - 1) * b.width + x0 - 1..][..4];
        let r1 = &b.data[(y0 + dy) * b.width + x0 - 1..][..4];
        for dx in 0..3 {
            let at = |r: &[u8], i: usize| f32::from(r[i]);
            pb[dy * 3 + dx] = w00 * at(r0, dx) + w10 * at(r0, dx + 1) + w01 * at(r1, dx) + w11 * at(r1, dx + 1);
        }
    }
    let mb = pb.iter().sum::<f32>() / 9.0;
    Some(f64::from(pa.iter().zip(&pb).map(|(u, v)| (u - (v - mb)).abs()).sum::<f32>() / 9.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// A textured fronto-parallel wall at 2 m seen by a camera moving by `truth`,
    /// with a patch that moves on its own; the flow is exact.
    fn wall_with_patch(ego: &EgoMotion, truth: &Isometry3<f64>) -> (FlowField, SmallGray, SmallGray, Vec<u16>) {
        let depth = vec![2000u16; 320 * 240];
        let (w, h) = ego.grid_size();
        let texture = |x: f64, y: f64| 128.0 + 60.0 * (0.7 * x).sin() * (0.5 * y).cos() + 40.0 * (0.31 * x + 0.17 * y).sin();
        let previous =
            SmallGray { width: w, height: h, data: (0..w * h).map(|i| texture((i % w) as f64, (i / w) as f64).round() as u8).collect() };
        let (mut data, mut current) = (Vec::with_capacity(w * h), Vec::with_capacity(w * h));
        for i in 0..w * h {
            let (x, y) = (i % w, i / w);
            let p = ego.predict(i, 2.0, truth).unwrap();
            // Previous-image position in flow-grid coordinates; the patch moved 4 more.
            let (mut qx, qy) = ((p.x + 0.5) / 2.0 - 0.5, (p.y + 0.5) / 2.0 - 0.5);
            if inside(x, y) {
                qx += 4.0;
            }
            data.push([(qx - x as f64) as f32, (qy - y as f64) as f32]);
            current.push(texture(qx, qy).round() as u8);
        }
        let current = SmallGray { width: w, height: h, data: current };
        let flow = FlowField { width: w, height: h, subsample: 2, data };
        (flow, current, previous, depth)
    }

    fn inside(x: usize, y: usize) -> bool {
        (60..90).contains(&x) && (40..70).contains(&y)
    }

    /// The numbers of the crowd scene's onset (rpy_b as built, frame 31: the
    /// prediction leaves 1,264 of the 8,560 vote cells of a 640×480 frame at the
    /// default subsample moving, the refinement the board pulled 1,179) and of an
    /// ordinary frame (2,102 against 391).
    #[test]
    fn a_refinement_must_explain_clearly_more_than_the_prediction() {
        let cells = 107 * 80;
        assert!(!clear_of_prediction(1_179, Some(1_264), 0.1, cells), "7 % fewer is not clear");
        assert!(clear_of_prediction(1_179, Some(1_264), 0.0, cells), "no margin: fewer wins");
        assert!(clear_of_prediction(391, Some(2_102), 0.1, cells));
        assert!(!clear_of_prediction(900, Some(1_000), 0.1, cells), "exactly the margin is not clear");
        assert!(clear_of_prediction(899, Some(1_000), 0.1, cells));
        // No conflict where the prediction leaves under 1 % of the cells (85.6) moving.
        assert!(clear_of_prediction(80, Some(85), 0.1, cells));
        assert!(!clear_of_prediction(80, Some(86), 0.1, cells));
        assert!(clear_of_prediction(5, None, 0.1, cells), "no prediction among the candidates");
    }

    /// Through the vote: a prior 0.01 rad off the truth leaves nearly the whole wall
    /// moving, its refinement only the patch. At a margin of one half the
    /// refinement wins; at 0.99 (it would have to leave under 1 % of the prior's
    /// moving cells) the prior stands, checked by the flow, as it is.
    #[test]
    fn the_prior_stands_unless_its_refinement_explains_clearly_more() {
        let truth = Isometry3::new(Vector3::new(0.03, -0.01, 0.02), Vector3::new(0.01, -0.02, 0.005));
        let prior = truth * Isometry3::new(Vector3::zeros(), Vector3::new(0.0, 0.01, 0.0));
        let run = |margin: f64| {
            let config = EgoMotionConfig { min_samples: 20, refinement_margin: margin, ..EgoMotionConfig::default() };
            let ego = EgoMotion::new(wall_camera(), config, 2);
            let (flow, current, previous, depth) = wall_with_patch(&ego, &truth);
            ego.compensate(&flow, &current, &previous, &depth, Some(prior), None)
        };
        let refined = run(0.5);
        assert!(refined.refined && refined.confirmed);
        let err = refined.previous_from_current.inverse() * truth;
        assert!(err.translation.vector.norm() < 1e-3 && err.rotation.angle() < 1e-4, "{err:?}");
        let held = run(0.99);
        assert!(!held.refined && held.confirmed, "the prior stands, and a refinement was tried against it");
        assert_eq!(held.previous_from_current, prior);
    }

    fn wall_camera() -> Camera {
        Camera::pinhole(320, 240, 260.0, 260.0, 160.0, 120.0, 1000.0)
    }

    #[test]
    fn refines_the_motion_and_flags_only_the_independent_patch() {
        let config = EgoMotionConfig { min_samples: 20, ..EgoMotionConfig::default() };
        let ego = EgoMotion::new(wall_camera(), config, 2);
        let truth = Isometry3::new(Vector3::new(0.03, -0.01, 0.02), Vector3::new(0.01, -0.02, 0.005));
        let (flow, current, previous, depth) = wall_with_patch(&ego, &truth);
        let (w, h) = ego.grid_size();
        let out = ego.compensate(&flow, &current, &previous, &depth, None, None);
        assert!(out.refined && out.confirmed);
        // With the true motion as the prior, a refinement competes with it: whichever
        // wins, the flow checked the motion.
        let with_prior = ego.compensate(&flow, &current, &previous, &depth, Some(truth), None);
        assert!(with_prior.confirmed);
        assert_eq!(with_prior.class, ego.compensate(&flow, &current, &previous, &depth, None, None).class);
        let err = out.previous_from_current.inverse() * truth;
        assert!(err.translation.vector.norm() < 1e-3 && err.rotation.angle() < 1e-4, "{err:?}");
        for i in 0..w * h {
            let (x, y) = (i % w, i / w);
            if x < 2 || y < 2 || x + 3 >= w || y + 3 >= h {
                continue; // patches leave the image
            }
            if (59..=60).contains(&x) || (89..=90).contains(&x) || (39..=40).contains(&y) || (69..=70).contains(&y) {
                continue; // 3×3 patches straddling the motion boundary mix both motions
            }
            assert_eq!(out.class[i], if inside(x, y) { RESIDUAL } else { CONSISTENT }, "pixel {x},{y}");
        }
    }

    /// The patch's 8-pixel independent motion is beyond one frame interval's flow
    /// noise (3σ = 3 px) and within three intervals' (9 px): a step spanning three
    /// (frames dropped on the way) does not call it moving.
    #[test]
    fn a_step_over_three_frame_intervals_is_judged_with_three_times_the_noise() {
        let config = EgoMotionConfig { min_samples: 20, ..EgoMotionConfig::default() };
        let ego = EgoMotion::new(wall_camera(), config, 2);
        let truth = Isometry3::new(Vector3::new(0.03, -0.01, 0.02), Vector3::new(0.01, -0.02, 0.005));
        let (flow, current, previous, depth) = wall_with_patch(&ego, &truth);
        let (w, _) = ego.grid_size();
        let judged = |intervals: f64| {
            let out = ego.compensate_sampled(&flow, &current, &previous, ego.frame_samples(&current, &depth), Some(truth), None, intervals);
            let centre = 55 * w + 75;
            assert!(inside(75, 55), "the patch's centre");
            out.class[centre]
        };
        assert_eq!(judged(1.0), RESIDUAL);
        assert_eq!(judged(3.0), CONSISTENT);
    }

    /// Labels made under a wrong (predicted) motion are re-decided by the tracked
    /// one only when it differs and leaves fewer pixels moving.
    #[test]
    fn reconsider_takes_the_tracked_motion_only_when_it_explains_more() {
        // Priors used as they are, so each result is the classification under its prior.
        let config = EgoMotionConfig { min_samples: 20, refine_tracked_motion: false, ..EgoMotionConfig::default() };
        let ego = EgoMotion::new(wall_camera(), config, 2);
        let truth = Isometry3::new(Vector3::new(0.03, -0.01, 0.02), Vector3::new(0.01, -0.02, 0.005));
        let wrong = Isometry3::new(Vector3::new(0.0, 0.0, 0.0), Vector3::new(0.0, -0.01, 0.0));
        let (flow, current, previous, depth) = wall_with_patch(&ego, &truth);
        let moving = |r: &EgoResult| r.class.iter().filter(|&&c| c == RESIDUAL).count();
        let under_wrong = ego.compensate(&flow, &current, &previous, &depth, Some(wrong), None);
        let under_truth = ego.compensate(&flow, &current, &previous, &depth, Some(truth), None);
        assert!(moving(&under_wrong) > 4 * moving(&under_truth), "{} vs {}", moving(&under_wrong), moving(&under_truth));

        // Priors used as they are: nothing on the flow checked them.
        assert!(!under_wrong.confirmed && !under_wrong.refined);
        let better = ego.reconsider(&flow, &current, &previous, &under_wrong, &truth, None, 1.0).expect("the tracked motion explains more");
        assert!(better.confirmed, "it won the vote on the flow");
        assert_eq!(better.previous_from_current, truth);
        assert_eq!(better.class, under_truth.class);
        assert_eq!(better.residual_px, under_truth.residual_px);
        // Worse, or within the tolerance of the chosen motion: the labels stand.
        assert!(ego.reconsider(&flow, &current, &previous, &under_truth, &wrong, None, 1.0).is_none());
        let nudged = truth * Isometry3::new(Vector3::new(RECONSIDER_TOLERANCE_M * 0.5, 0.0, 0.0), Vector3::zeros());
        assert!(ego.reconsider(&flow, &current, &previous, &under_wrong, &nudged, None, 1.0).is_some());
        assert!(ego.reconsider(&flow, &current, &previous, &under_truth, &nudged, None, 1.0).is_none());
    }

    /// Over a baseline, a near textured board that moved sideways (a fifth of the
    /// view) in front of a far background at two depths: the board's own motion
    /// explains the far background within the threshold (the fewest-moving rule
    /// would take it for the camera's), yet the camera's motion is chosen, the board
    /// is what moved, and background the board uncovered (whose flow followed the
    /// board, as Farneback's does) is an occlusion, not a mover.
    #[test]
    fn the_baseline_tells_the_camera_from_a_large_mover() {
        let config = EgoMotionConfig { min_samples: 20, ..EgoMotionConfig::default() };
        let camera = wall_camera();
        let ego = EgoMotion::new(camera.clone(), config, 2);
        let (w, h) = ego.grid_size();
        let truth = Isometry3::new(Vector3::new(0.01, 0.0, 0.005), Vector3::new(0.0, 0.02, 0.0));
        let shift = Vector3::new(0.08, 0.0, 0.0); // the board's motion over the baseline, current camera axes
        let board_motion = truth * nalgebra::Translation3::from(-shift);
        let on_board = |x: usize, y: usize| (40..100).contains(&x) && (30..90).contains(&y);
        let background_z = |x: usize| if x < w / 2 { 3.0 } else { 3.3 };
        let z_of = |x: usize, y: usize| if on_board(x, y) { 0.8 } else { background_z(x) };
        let point = |i: usize| {
            let z = z_of(i % w, i / w);
            Point3::new(ego.ray[i].x * z, ego.ray[i].y * z, z)
        };
        let grid = |p: &Point3<f64>| {
            let raw = camera.distort(&camera.project(p).expect("in front"));
            ((raw.x + 0.5) / 2.0 - 0.5, (raw.y + 0.5) / 2.0 - 0.5)
        };
        // The reference depth: the scene splatted into the reference view (nearest wins).
        let mut reference_depth = vec![0f32; w * h];
        for i in 0..w * h {
            let motion = if on_board(i % w, i / w) { board_motion } else { truth };
            let q = motion * point(i);
            let (x, y) = grid(&q);
            let (x, y) = (x.round(), y.round());
            if x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h {
                let cell = &mut reference_depth[y as usize * w + x as usize];
                if *cell == 0.0 || (q.z as f32) < *cell {
                    *cell = q.z as f32;
                }
            }
        }
        for (i, z) in reference_depth.iter_mut().enumerate().filter(|(_, z)| **z == 0.0) {
            *z = background_z(i % w) as f32;
        }
        // Exact flow (where each cell was `steps` frames back), except on background
        // the board hid then: there the flow follows the board.
        let texture = |x: f64, y: f64| 128.0 + 60.0 * (0.7 * x).sin() * (0.5 * y).cos() + 40.0 * (0.31 * x + 0.17 * y).sin();
        let reference =
            SmallGray { width: w, height: h, data: (0..w * h).map(|i| texture((i % w) as f64, (i / w) as f64).round() as u8).collect() };
        let (mut data, mut current, mut uncovered) = (Vec::with_capacity(w * h), Vec::with_capacity(w * h), Vec::new());
        for i in 0..w * h {
            let (x, y) = (i % w, i / w);
            let static_target = grid(&(truth * point(i)));
            let hidden = !on_board(x, y) && {
                let (tx, ty) = (static_target.0.round(), static_target.1.round());
                tx >= 0.0 && ty >= 0.0 && (tx as usize) < w && (ty as usize) < h && reference_depth[ty as usize * w + tx as usize] < 1.0
            };
            let (qx, qy) = if on_board(x, y) || hidden { grid(&(board_motion * point(i))) } else { static_target };
            if hidden {
                uncovered.push(i);
            }
            data.push([(qx - x as f64) as f32, (qy - y as f64) as f32]);
            current.push(texture(qx, qy).round() as u8);
        }
        assert!(uncovered.len() > 100, "the board uncovered background: {}", uncovered.len());
        let composed = FlowField { width: w, height: h, subsample: 2, data };
        let current = SmallGray { width: w, height: h, data: current };
        let depth: Vec<u16> = (0..320 * 240).map(|i| (1000.0 * z_of((i % 320) / 2, (i / 320) / 2)).round() as u16).collect();
        let steps = 4;

        // The board's motion with a compensating turn: the rigid motion that moves the
        // board and the nearer wall exactly (fitted on their samples) leaves the
        // farther wall within the threshold, so the fewest-moving rule would take it
        // for the camera's motion.
        let depth_m = ego.sample_depth(&depth);
        let samples = ego.flow_samples(&composed, &min_eigen_texture(&current), &depth_m, None, 1.0, 1);
        let board_and_wall: Vec<_> = samples.iter().filter(|(p, _)| p.z < 1.0 || (p.z - 3.0).abs() < 1e-3).cloned().collect();
        let impostor = optimize_pose(&camera, 1.0, board_motion, &board_and_wall).camera_from_world;
        let moving_under = |m: &Isometry3<f64>| {
            let (class, _) = ego.classify(&composed, &current, &reference, &depth_m, m, steps as f64, Cells::All, None);
            class.iter().filter(|&&c| c == RESIDUAL).count()
        };
        assert!(
            moving_under(&impostor) < moving_under(&truth) / 2,
            "under the impostor {} cells move, under the camera's motion {}",
            moving_under(&impostor),
            moving_under(&truth)
        );

        let out = ego
            .movers_over_baseline(
                &composed,
                steps as f64,
                &current,
                &reference,
                &ego.frame_samples(&current, &depth),
                &reference_depth,
                &[impostor],
                None,
            )
            .expect("enough samples");
        let err = out.reference_from_current.inverse() * truth;
        assert!(err.translation.vector.norm() < 1e-3 && err.rotation.angle() < 1e-4, "the camera's motion: {err:?}");
        assert!(out.candidates >= 2, "the board's motion competed");
        let interior = |x: usize, y: usize| (43..97).contains(&x) && (33..87).contains(&y);
        let board_moving = (0..w * h).filter(|&i| interior(i % w, i / w) && out.moving[i] != 0).count();
        let interior_cells = (0..w * h).filter(|&i| interior(i % w, i / w)).count();
        assert!(board_moving as f64 >= 0.95 * interior_cells as f64, "{board_moving} of {interior_cells} board cells moved");
        // Outside the band the board swept (it came from the left, 13 cells), no
        // background moved.
        let swept = |x: usize, y: usize| (24..103).contains(&x) && (27..93).contains(&y);
        let elsewhere = (0..w * h).filter(|&i| !swept(i % w, i / w) && out.moving[i] != 0).count();
        assert_eq!(elsewhere, 0, "background called moving");
        // Uncovered background whose flow lands on the board in the reference: an occlusion.
        let lands_on_board = |i: usize| {
            let f = composed.data[i];
            let (x, y) = (((i % w) as f32 + f[0]).round(), ((i / w) as f32 + f[1]).round());
            x >= 0.0 && y >= 0.0 && reference_depth.get(y as usize * w + x as usize).is_some_and(|&z| z < 1.0)
        };
        let occluded: Vec<usize> = uncovered.iter().copied().filter(|&i| lands_on_board(i)).collect();
        assert!(occluded.len() > 100, "{} uncovered cells land on the board", occluded.len());
        assert_eq!(occluded.iter().filter(|&&i| out.moving[i] != 0).count(), 0, "uncovered background is an occlusion");
    }

    #[test]
    fn texture_and_patch_difference() {
        let flat = SmallGray { width: 16, height: 16, data: vec![90; 256] };
        assert!(min_eigen_texture(&flat).iter().all(|&t| t == 0.0));
        // Vertical stripes: texture in x only, so the smaller eigenvalue is still 0.
        let stripes = SmallGray { width: 16, height: 16, data: (0..256).map(|i| if i % 2 == 0 { 0 } else { 200 }).collect() };
        assert!(min_eigen_texture(&stripes).iter().all(|&t| t == 0.0));
        let checker = SmallGray {
            width: 16,
            height: 16,
            data: (0..256).map(|i| if ((i % 16) / 2 + (i / 16) / 2) % 2 == 0 { 0 } else { 200 }).collect(),
        };
        assert!(min_eigen_texture(&checker)[8 * 16 + 8] > 100.0);
        // A brightness offset is not a difference; a shift is.
        let brighter = SmallGray { width: 16, height: 16, data: checker.data.iter().map(|v| v + 30).collect() };
        assert_eq!(patch_difference(&checker, 8, 8, &brighter, 8.0, 8.0), Some(0.0));
        assert!(patch_difference(&checker, 8, 8, &checker, 9.0, 8.0).unwrap() > 50.0);
        assert_eq!(patch_difference(&checker, 0, 8, &checker, 8.0, 8.0), None);
    }
}
