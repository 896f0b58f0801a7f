//! The tracker: one per camera session. Feed it frames in capture order; it
//! returns a tracking state for every frame and a pose whenever it has one.

use std::collections::{HashMap, HashSet};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Matrix6, Point3, Vector6};

use crate::TrackingError;
use crate::ba;
use crate::camera::Camera;
use crate::config::TrackerConfig;
use crate::dense::{DenseOdometry, DenseStart};
use crate::features::{Descriptor, Extractor, Feature, FrameFeatures, GridIndex, hamming, level_scales, rectify_rolling_shutter};
use crate::geometry::{Measurement, PnpRansac, frame_intervals, huber_weight, linearise_pose, pnp_ransac, scale_motion};
use crate::map::{Keyframe, KeyframeId, Map, MapPoint, PointId};
use crate::optimize::{PosePrior, optimize_pose, optimize_pose_with_prior};

/// The state of tracking for one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrackingState {
    /// No map yet: the frame could not start one (too few features with depth).
    Initializing,
    /// Tracked continuously from the previous frame.
    Tracking,
    /// No pose for this frame.
    Lost,
    /// Continuity was broken and the pose was recovered against the map's keyframes.
    Relocalized,
    /// The features lost the map; dense odometry alone carries the pose from the
    /// last tracked frame (for up to `coast_s`). Posed, but not to be mapped.
    Coasting,
}

/// One RGB-D frame, borrowed.
pub struct FrameInput<'a> {
    pub timestamp_ns: u64,
    /// RGB8, row-major, `width × height × 3` bytes.
    pub rgb: &'a [u8],
    /// Raw depth, row-major, `width × height`, in `Camera::depth_units_per_metre`; 0 = no reading.
    pub depth: &'a [u16],
    /// Dynamic-pixel mask, `width × height`, nonzero = dynamic; `None` = all static.
    pub dynamic_mask: Option<&'a [u8]>,
}

/// Time spent per tracking stage on one frame.
#[derive(Debug, Clone, Copy, Default)]
pub struct StageTimes {
    pub extraction: Duration,
    /// Dense odometry from the previous frame (the motion prior).
    pub dense: Duration,
    pub matching: Duration,
    pub optimization: Duration,
    pub local_ba: Duration,
    pub total: Duration,
}

/// What the tracker made of one frame.
#[derive(Debug, Clone)]
pub struct TrackOutput {
    pub state: TrackingState,
    /// Never set without a real estimate.
    pub world_from_camera: Option<Isometry3<f64>>,
    /// Features extracted (after the dynamic mask).
    pub features: usize,
    /// Keypoints removed by the dynamic mask.
    pub masked_features: usize,
    /// Map points matched as inliers.
    pub tracked_points: usize,
    /// Whether the frame became a keyframe.
    pub keyframe: bool,
    pub times: StageTimes,
}

/// The previous frame, kept for the motion model.
struct LastFrame {
    camera_from_world: Isometry3<f64>,
    points: Vec<PointId>,
}

/// Relocalization: Hamming ratio test for brute-force matches.
const RELOC_MATCH_RATIO: f32 = 0.75;
/// The dense alignment starts from the motion model's step only over up to this many
/// frame intervals: over longer gaps a constant velocity predicts no better than
/// standing still (the identity start).
const MAX_GUESS_INTERVALS: f64 = 5.0;
/// Relocalization: correspondences needed before PnP is tried.
const RELOC_MIN_MATCHES: usize = 15;
/// PnP-RANSAC iterations, inlier reprojection threshold (pixels) and confidence.
const PNP_ITERATIONS: i32 = 200;
const PNP_REPROJECTION_PX: f32 = 4.0;
const PNP_CONFIDENCE: f64 = 0.99;
/// Thumbnail size for relocalization candidate ranking.
const THUMB_W: usize = 40;
const THUMB_H: usize = 30;
/// Factor applied to the motion-model radius for the wider second search.
const WIDE_SEARCH_FACTOR: f64 = 3.0;
/// Relocalization replaces a weak motion-model placement (`weak_placement_ratio`)
/// only when it explains more than this many times as many points.
const WEAK_REPLACEMENT_FACTOR: usize = 2;
/// Keyframes created since a point's birth after which it must have ≥ 2 observations.
const CULL_AFTER_KEYFRAMES: u64 = 3;
/// Keyframes (the newest not kept) searched for a redundant one to forget
/// (`tracking.max_keyframes`).
const FORGET_SCAN: usize = 50;
/// Points matched in fewer than this fraction of the frames predicting them are culled.
const CULL_FOUND_RATIO: f64 = 0.25;
/// Visibility count before the found ratio is trusted.
const CULL_MIN_VISIBLE: u32 = 10;
/// Fixed keyframes (outside the window) anchoring a local BA, at most.
const BA_MAX_FIXED: usize = 10;

/// `camera_from_world` and the (feature, point) pairs PnP-RANSAC kept as inliers.
type PnpSolution = (Isometry3<f64>, Vec<(usize, PointId)>);

/// RGB-D camera tracker.
pub struct Tracker {
    camera: Camera,
    config: TrackerConfig,
    extractor: Extractor,
    map: Map,
    scales: Vec<f64>,
    bf: f64,
    initialized: bool,
    lost: bool,
    last: Option<LastFrame>,
    /// `camera_from_world(k) · world_from_camera(k−1)`, when the last two frames were tracked.
    velocity: Option<Isometry3<f64>>,
    reference: Option<KeyframeId>,
    reference_inliers: usize,
    frames_since_keyframe: u32,
    dense: Option<DenseOdometry>,
    /// This frame's pose as dense odometry predicts it from the last frame's.
    prior: Option<PosePrior>,
    /// Timestamp of the frame before this one (dense odometry's step starts there).
    previous_timestamp_ns: Option<u64>,
    /// Frame intervals the last tracked step (`velocity`) spanned.
    velocity_intervals: f64,
    /// Capture time of the last frame the features tracked (or relocalized):
    /// coasting ends `coast_s` after it.
    last_tracked_ns: Option<u64>,
    /// The last frame was `Coasting`.
    coasting: bool,
    /// A keyframe made while no motion was known (the first one; one after a failed
    /// dense step with no tracked velocity), whose keypoints a rolling shutter still
    /// distorts: rectified with the next frame's step.
    unrectified_keyframe: Option<KeyframeId>,
    /// Keyframes forgotten beyond `max_keyframes`.
    forgotten_keyframes: u64,
}

/// The grey image of an RGB8 image: BT.601 luma, rounded to 8 bits.
pub fn to_gray(rgb: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3).map(|p| ((luma_x256(p) + 128) >> 8) as u8).collect()
}

/// ITU-R BT.601 luma of one RGB8 pixel in 8-bit fixed point (×256), as OpenCV's RGB2GRAY.
#[inline]
pub fn luma_x256(rgb: &[u8]) -> u32 {
    u32::from(rgb[0]) * 77 + u32::from(rgb[1]) * 150 + u32::from(rgb[2]) * 29
}

fn thumbnail(gray: &[u8], w: usize, h: usize) -> Vec<f32> {
    let mut t = vec![0f32; THUMB_W * THUMB_H];
    for ty in 0..THUMB_H {
        for tx in 0..THUMB_W {
            let (x0, x1) = (tx * w / THUMB_W, ((tx + 1) * w / THUMB_W).max(tx * w / THUMB_W + 1));
            let (y0, y1) = (ty * h / THUMB_H, ((ty + 1) * h / THUMB_H).max(ty * h / THUMB_H + 1));
            let mut s = 0u32;
            for y in y0..y1.min(h) {
                for x in x0..x1.min(w) {
                    s += u32::from(gray[y * w + x]);
                }
            }
            t[ty * THUMB_W + tx] = s as f32 / ((y1 - y0) * (x1 - x0)) as f32;
        }
    }
    let n = t.len() as f32;
    let mean = t.iter().sum::<f32>() / n;
    let var = t.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
    let inv = if var > f32::EPSILON { 1.0 / var.sqrt() } else { 0.0 };
    t.iter_mut().for_each(|v| *v = (*v - mean) * inv);
    t
}

impl Tracker {
    pub fn new(camera: Camera, config: TrackerConfig) -> Result<Self, TrackingError> {
        if camera.width < 3 || camera.height < 3 {
            return Err(TrackingError::Config(format!("image {}x{} is too small to track", camera.width, camera.height)));
        }
        config.validate().map_err(TrackingError::Config)?;
        let extractor = Extractor::new(&config)?;
        let bf = camera.fx * config.depth_baseline_m;
        let dense = if config.dense_odometry { Some(DenseOdometry::new(&camera, config.min_depth_m, config.max_depth_m)?) } else { None };
        Ok(Self {
            dense,
            prior: None,
            previous_timestamp_ns: None,
            velocity_intervals: 1.0,
            last_tracked_ns: None,
            coasting: false,
            unrectified_keyframe: None,
            forgotten_keyframes: 0,
            scales: level_scales(&config),
            camera,
            extractor,
            map: Map::default(),
            bf,
            config,
            initialized: false,
            lost: false,
            last: None,
            velocity: None,
            reference: None,
            reference_inliers: 0,
            frames_since_keyframe: 0,
        })
    }

    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Keyframes forgotten so far beyond `tracking.max_keyframes`.
    pub fn forgotten_keyframes(&self) -> u64 {
        self.forgotten_keyframes
    }

    pub fn map(&self) -> &Map {
        &self.map
    }

    /// Dense odometry's step into the last tracked frame (`previous_from_current`),
    /// when it ran and gave one: for diagnostics.
    pub fn dense_step(&self) -> Option<Isometry3<f64>> {
        self.dense.as_ref().and_then(DenseOdometry::last_step)
    }

    /// The map points the last tracked frame placed itself on (its inliers; a
    /// keyframe's every point, new ones included; kept while coasting, empty after
    /// LOST): for diagnostics.
    pub fn last_points(&self) -> &[PointId] {
        self.last.as_ref().map_or(&[], |l| l.points.as_slice())
    }

    /// [`DenseOdometry::agreement`] of the last step: for diagnostics.
    pub fn dense_agreement(&self) -> Option<f64> {
        self.dense.as_ref().and_then(DenseOdometry::agreement)
    }

    /// The last inter-frame motion `camera_k_from_camera_k−1`, when the last two
    /// frames were tracked (the constant-velocity prediction of the next step).
    pub fn velocity(&self) -> Option<Isometry3<f64>> {
        self.velocity
    }

    fn measurement(&self, f: &Feature) -> Measurement {
        let s = self.scales[usize::from(f.octave).min(self.scales.len() - 1)];
        Measurement { ideal: f.ideal, disparity: f.depth.map(|z| self.bf / z), information: 1.0 / (s * s) }
    }

    /// Tracks one frame.
    pub fn track(&mut self, frame: &FrameInput<'_>) -> Result<TrackOutput, TrackingError> {
        let start = Instant::now();
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if frame.rgb.len() != w * h * 3 {
            return Err(TrackingError::Input(format!("colour has {} bytes, expected {} ({w}x{h}x3)", frame.rgb.len(), w * h * 3)));
        }
        if frame.depth.len() != w * h {
            return Err(TrackingError::Input(format!("depth has {} pixels, expected {} ({w}x{h})", frame.depth.len(), w * h)));
        }
        if let Some(m) = frame.dynamic_mask
            && m.len() != w * h
        {
            return Err(TrackingError::Input(format!("dynamic mask has {} pixels, expected {} ({w}x{h})", m.len(), w * h)));
        }
        let mut times = StageTimes::default();
        let t = Instant::now();
        let gray = to_gray(frame.rgb);
        // Frame intervals (`dense_prior_interval_s`) since the previous frame.
        let intervals = self
            .previous_timestamp_ns
            .and_then(|previous_ns| frame_intervals(previous_ns, frame.timestamp_ns, self.config.dense_prior_interval_s))
            .unwrap_or(1.0);
        let velocity = self.velocity.filter(|_| !self.lost).map(|v| (v, self.velocity_intervals));
        let dense_start = dense_start(velocity, intervals, &self.config);
        // Dense odometry needs only the images: it runs on its own thread while the
        // features are extracted.
        let (feats, step) = std::thread::scope(|scope| {
            let dense = self.dense.as_mut().map(|dense| {
                let gray = &gray;
                std::thread::Builder::new().name("dense-odometry".into()).spawn_scoped(scope, move || {
                    let t = Instant::now();
                    (dense.push_started(gray, frame.depth, frame.dynamic_mask, dense_start), t.elapsed())
                })
            });
            let feats = self.extractor.extract(&self.camera, &gray, frame.depth, frame.dynamic_mask);
            times.extraction = t.elapsed();
            let step = match dense.map(|spawned| spawned.map(|handle| handle.join())) {
                Some(Ok(Ok((step, elapsed)))) => {
                    times.dense = elapsed;
                    step
                }
                // A panic there is a bug, as it would be inline: pass it on.
                Some(Ok(Err(panic))) => std::panic::resume_unwind(panic),
                Some(Err(e)) => Err(TrackingError::Thread(e)),
                None => Ok(None),
            };
            (feats, step)
        });
        let (mut feats, step) = (feats?, step?);
        let previous_timestamp_ns = self.previous_timestamp_ns.replace(frame.timestamp_ns);
        // A rolling shutter saw each row at its own time: turn the keypoints to the
        // middle row's, with this frame's motion (the dense step, else the last
        // tracked step repeated).
        let mut rectified = false;
        if self.camera.readout_s > 0.0
            && let Some(previous_ns) = previous_timestamp_ns
            && frame.timestamp_ns > previous_ns
            && let Some(previous_from_current) = step.or_else(|| self.velocity.filter(|_| !self.lost).map(|v| v.inverse()))
        {
            let interval_s = (frame.timestamp_ns - previous_ns) as f64 * 1e-9;
            rectify_rolling_shutter(&self.camera, &mut feats.features, &previous_from_current, interval_s);
            if let Some(id) = self.unrectified_keyframe.take() {
                self.rectify_keyframe(id, &previous_from_current, interval_s);
            }
            rectified = true;
        }
        // current_from_world = current_from_previous · previous_from_world. The σ
        // widen with the frame intervals the step spans.
        self.prior = match (step, &self.last) {
            (Some(previous_from_current), Some(last)) if !self.lost => Some(PosePrior {
                camera_from_world: previous_from_current.inverse() * last.camera_from_world,
                rotation_information: (intervals * self.config.dense_prior_sigma_deg).to_radians().powi(2).recip(),
                translation_information: (intervals * self.config.dense_prior_sigma_m).powi(2).recip(),
            }),
            _ => None,
        };

        let mut out = TrackOutput {
            state: TrackingState::Lost,
            world_from_camera: None,
            features: feats.features.len(),
            masked_features: feats.masked_out,
            tracked_points: 0,
            keyframe: false,
            times,
        };

        if !self.initialized {
            out.state = TrackingState::Initializing;
            if feats.features.iter().filter(|f| f.depth.is_some()).count() >= self.config.min_init_features {
                let t = Instant::now();
                let points = self.insert_keyframe(frame.timestamp_ns, Isometry3::identity(), feats, &gray, Vec::new());
                out.times.local_ba = t.elapsed();
                self.remember_if_unrectified(rectified);
                self.initialized = true;
                self.reference_inliers = points.len();
                self.last = Some(LastFrame { camera_from_world: Isometry3::identity(), points });
                self.last_tracked_ns = Some(frame.timestamp_ns);
                out.state = TrackingState::Tracking;
                out.world_from_camera = Some(Isometry3::identity());
                out.tracked_points = self.reference_inliers;
                out.keyframe = true;
            }
            out.times.total = start.elapsed();
            return Ok(out);
        }

        let index = GridIndex::new(&self.camera, &feats.features);
        let mut tracked = None;
        let mut relocalized = false;
        if !self.lost {
            tracked = self.track_with_motion_model(&feats, &index, &mut out.times);
        }
        let inliers = |t: &Option<(Isometry3<f64>, Vec<Option<PointId>>)>| t.as_ref().map_or(0, |(_, m)| m.iter().flatten().count());
        // A weak placement (`weak_placement_ratio` of the reference keyframe's points)
        // is checked against relocalization, which must explain more than
        // WEAK_REPLACEMENT_FACTOR times as many points to replace it: where the two
        // are close, the motion model (with the dense prior) is the better placement.
        let weak = tracked.is_some() && (inliers(&tracked) as f64) < self.config.weak_placement_ratio * self.reference_inliers as f64;
        // While coasting, the local map around the coasted pose may be a copy that
        // keyframes made at wrong poses left: relocalization is tried too, and the
        // placement with more inliers wins.
        if tracked.is_none() || self.coasting || weak {
            // Relocalization stands on the map alone.
            let prior = self.prior.take();
            let found = self.relocalize(&feats, &index, &gray, &mut out.times);
            let factor = if weak && !self.coasting { WEAK_REPLACEMENT_FACTOR } else { 1 };
            if inliers(&found) > factor * inliers(&tracked) {
                (tracked, relocalized) = (found, true);
            } else {
                self.prior = prior;
            }
        }
        let Some((camera_from_world, matches)) = tracked else {
            // Neither the motion model nor relocalization placed the features: dense
            // odometry alone carries the pose for up to `coast_s` since the last
            // tracked frame (current_from_world = current_from_previous ·
            // previous_from_world). A coasted frame makes no keyframe; the next
            // one searches the local map around its pose and tries relocalization.
            if let (Some(previous_from_current), Some(last), Some(tracked_ns)) = (step, self.last.as_mut(), self.last_tracked_ns)
                && !self.lost
                && self.config.coast_s > 0.0
                && (frame.timestamp_ns.saturating_sub(tracked_ns) as f64) * 1e-9 <= self.config.coast_s
                && self.dense.as_ref().and_then(DenseOdometry::agreement).is_some_and(|a| a >= self.config.coast_min_agreement)
            {
                let camera_from_world = previous_from_current.inverse() * last.camera_from_world;
                self.velocity = Some(camera_from_world * last.camera_from_world.inverse());
                self.velocity_intervals = intervals;
                // The last tracked frame's points stay the motion model's candidates.
                last.camera_from_world = camera_from_world;
                out.state = TrackingState::Coasting;
                self.coasting = true;
                out.world_from_camera = Some(camera_from_world.inverse());
                out.times.total = start.elapsed();
                return Ok(out);
            }
            self.lost = true;
            self.coasting = false;
            self.last = None;
            self.velocity = None;
            out.times.total = start.elapsed();
            return Ok(out);
        };

        let inliers = matches.iter().filter(|m| m.is_some()).count();
        out.tracked_points = inliers;
        out.state = if relocalized { TrackingState::Relocalized } else { TrackingState::Tracking };
        out.world_from_camera = Some(camera_from_world.inverse());
        self.velocity = match (&self.last, relocalized) {
            (Some(last), false) => Some(camera_from_world * last.camera_from_world.inverse()),
            _ => None,
        };
        self.velocity_intervals = intervals;
        self.lost = false;
        self.last_tracked_ns = Some(frame.timestamp_ns);
        self.coasting = false;
        self.frames_since_keyframe += 1;

        let need_keyframe = relocalized
            || self.frames_since_keyframe >= self.config.keyframe_max_interval
            || (inliers as f64) < self.config.keyframe_tracked_ratio * self.reference_inliers as f64;
        let points = if need_keyframe {
            let t = Instant::now();
            let points = self.insert_keyframe(frame.timestamp_ns, camera_from_world.inverse(), feats, &gray, matches);
            self.remember_if_unrectified(rectified);
            self.reference_inliers = inliers;
            out.times.local_ba = t.elapsed();
            out.keyframe = true;
            // Local BA may have moved this keyframe: without a dense prior, report
            // the refined pose. With one, the tracked pose stands: BA weighs the
            // features alone, and moving the keyframe to them would undo the
            // prior's smoothing for this frame and the next (README, "Tracking
            // accuracy"); the map takes BA's result either way.
            if self.prior.is_none()
                && let Some(kf) = self.reference.and_then(|r| self.map.keyframes.get(&r))
            {
                out.world_from_camera = Some(kf.world_from_camera);
            }
            points
        } else {
            matches.into_iter().flatten().collect()
        };
        let camera_from_world = out.world_from_camera.map_or(camera_from_world, |p| p.inverse());
        self.last = Some(LastFrame { camera_from_world, points });
        out.times.total = start.elapsed();
        Ok(out)
    }

    /// Motion-model projection of the last frame's points, widened once, then the
    /// local map; returns the pose and per-feature inlier matches.
    fn track_with_motion_model(
        &mut self,
        feats: &FrameFeatures,
        index: &GridIndex,
        times: &mut StageTimes,
    ) -> Option<(Isometry3<f64>, Vec<Option<PointId>>)> {
        let last = self.last.as_ref()?;
        let predicted = match (&self.prior, self.velocity) {
            (Some(prior), _) => prior.camera_from_world,
            (None, Some(v)) if self.config.constant_velocity => v * last.camera_from_world,
            _ => last.camera_from_world,
        };
        let mut candidates = last.points.clone();
        if self.coasting {
            // The last tracked frame's points leave the view while coasting: the
            // local map around the coasted pose is searched too.
            let known: HashSet<PointId> = candidates.iter().copied().collect();
            candidates.extend(self.local_points(predicted).into_iter().filter(|id| !known.contains(id)));
        }
        let mut pose = None;
        for factor in [1.0, WIDE_SEARCH_FACTOR] {
            let t = Instant::now();
            let mut matches = vec![None; feats.features.len()];
            let radius = self.config.motion_search_radius_px * factor;
            let n = self.search_by_projection(feats, index, &predicted, &candidates, radius, false, &mut matches);
            times.matching += t.elapsed();
            if n < self.config.min_motion_matches {
                continue;
            }
            let t = Instant::now();
            let result = self.optimize(feats, predicted, &mut matches);
            times.optimization += t.elapsed();
            if let Some(p) = result
                && matches.iter().filter(|m| m.is_some()).count() >= self.config.min_motion_matches
            {
                pose = Some(p);
                break;
            }
        }
        let pose = pose?;
        self.track_local_map(feats, index, pose, times)
    }

    /// Projects the local map into the frame around `pose`, re-optimises, and checks
    /// the frame has enough inliers (with depth) to count as tracked.
    fn track_local_map(
        &mut self,
        feats: &FrameFeatures,
        index: &GridIndex,
        pose: Isometry3<f64>,
        times: &mut StageTimes,
    ) -> Option<(Isometry3<f64>, Vec<Option<PointId>>)> {
        let t = Instant::now();
        let local = self.local_points(pose);
        let mut matches = vec![None; feats.features.len()];
        self.search_by_projection(feats, index, &pose, &local, self.config.local_map_search_radius_px, true, &mut matches);
        times.matching += t.elapsed();
        let t = Instant::now();
        let pose = self.optimize(feats, pose, &mut matches);
        times.optimization += t.elapsed();
        let pose = pose?;
        let inliers = matches.iter().filter(|m| m.is_some()).count();
        let with_depth = matches.iter().zip(&feats.features).filter(|(m, f)| m.is_some() && f.depth.is_some()).count();
        for id in matches.iter().flatten() {
            if let Some(mp) = self.map.points.get_mut(id) {
                mp.found += 1;
            }
        }
        (inliers >= self.config.min_tracked_inliers && with_depth >= self.config.min_tracked_inliers / 2).then_some((pose, matches))
    }

    /// Points of the keyframes nearest in covisibility to `pose`: the most recent
    /// keyframes plus the reference, up to `local_keyframes`.
    fn local_points(&self, camera_from_world: Isometry3<f64>) -> Vec<PointId> {
        let mut seen = HashSet::new();
        let mut points = Vec::new();
        for id in self.nearest_keyframes(&camera_from_world.inverse()) {
            if let Some(kf) = self.map.keyframes.get(&id) {
                for p in kf.points.iter().flatten() {
                    if seen.insert(*p) {
                        points.push(*p);
                    }
                }
            }
        }
        points
    }

    /// The `local_keyframes` keyframes nearest in viewpoint to `world_from_camera`:
    /// translation plus rotation (1 rad ≈ 1 m), the older first among equals.
    fn nearest_keyframes(&self, world_from_camera: &Isometry3<f64>) -> Vec<KeyframeId> {
        let mut kfs: Vec<(f64, KeyframeId)> = self
            .map
            .keyframes
            .values()
            .map(|kf| {
                let rel = kf.world_from_camera.inverse() * world_from_camera;
                (rel.translation.vector.norm() + rel.rotation.angle(), kf.id)
            })
            .collect();
        kfs.sort_by(|a, b| a.0.total_cmp(&b.0));
        kfs.into_iter().take(self.config.local_keyframes).map(|(_, id)| id).collect()
    }

    /// Keeps at most `tracking.max_keyframes` keyframes after keyframe `newest` was
    /// made at `world_from_camera` (see the option for which are forgotten).
    fn forget_keyframes(&mut self, newest: KeyframeId, world_from_camera: Isometry3<f64>) {
        let cap = self.config.max_keyframes;
        if cap == 0 || self.map.keyframes.len() <= cap {
            return;
        }
        let mut kept: HashSet<KeyframeId> = self.map.keyframes.keys().rev().take(self.config.ba_window).copied().collect();
        kept.extend(self.nearest_keyframes(&world_from_camera));
        kept.extend([Some(newest), self.reference, self.unrectified_keyframe].into_iter().flatten());
        while self.map.keyframes.len() > cap {
            let Some(id) = self.map.keyframe_to_forget(&kept, FORGET_SCAN) else { break };
            self.map.forget_keyframe(id);
            self.forgotten_keyframes += 1;
        }
    }

    /// Matches map points projected with `camera_from_world` to features within
    /// `radius` pixels (scaled by the point's pyramid level). Returns the number of matches.
    #[allow(clippy::too_many_arguments)]
    fn search_by_projection(
        &mut self,
        feats: &FrameFeatures,
        index: &GridIndex,
        camera_from_world: &Isometry3<f64>,
        candidates: &[PointId],
        radius: f64,
        count_visible: bool,
        matches: &mut [Option<PointId>],
    ) -> usize {
        let ratio = self.config.match_ratio;
        let mut best_distance = vec![u32::MAX; feats.features.len()];
        let max_level = self.scales.len() - 1;
        for &id in candidates {
            let Some(mp) = self.map.points.get_mut(&id) else { continue };
            let pc = camera_from_world * mp.point_in_world;
            if pc.z < self.config.min_depth_m {
                continue;
            }
            let Some(px) = self.camera.project(&pc) else { continue };
            if !self.camera.contains(&px) {
                continue;
            }
            if count_visible {
                mp.visible += 1;
            }
            let r = radius * self.scales[usize::from(mp.octave).min(max_level)];
            let predicted_disparity = self.bf / pc.z;
            let (mut best, mut second, mut best_i, mut second_i) = (u32::MAX, u32::MAX, usize::MAX, usize::MAX);
            let descriptor = mp.descriptor;
            index.for_each_near(&feats.features, &px, r, |i| {
                let f = &feats.features[i];
                if let Some(z) = f.depth
                    && (self.bf / z - predicted_disparity).abs() > r
                {
                    return;
                }
                let d = hamming(&descriptor, &feats.descriptors[i]);
                if d < best {
                    (second, second_i) = (best, best_i);
                    (best, best_i) = (d, i);
                } else if d < second {
                    (second, second_i) = (d, i);
                }
            });
            if best > self.config.max_descriptor_distance {
                continue;
            }
            // The same corner is often detected at two pyramid levels with nearly the
            // same descriptor: the ratio test only compares candidates of one level.
            if second_i != usize::MAX
                && feats.features[second_i].octave == feats.features[best_i].octave
                && best as f32 > ratio * second as f32
            {
                continue;
            }
            if best < best_distance[best_i] {
                best_distance[best_i] = best;
                matches[best_i] = Some(id);
            }
        }
        matches.iter().filter(|m| m.is_some()).count()
    }

    /// Robust pose optimisation over the current matches; outliers are unmatched.
    fn optimize(&self, feats: &FrameFeatures, initial: Isometry3<f64>, matches: &mut [Option<PointId>]) -> Option<Isometry3<f64>> {
        let mut which = Vec::new();
        let mut corr = Vec::new();
        for (i, m) in matches.iter().enumerate() {
            if let Some(mp) = m.and_then(|id| self.map.points.get(&id)) {
                which.push(i);
                let mut measurement = self.measurement(&feats.features[i]);
                measurement.information *= point_information_share(mp.observations.len());
                corr.push((mp.point_in_world, measurement));
            }
        }
        if corr.len() < 3 {
            return None;
        }
        // The dense prior, weighed by how well the features alone agree with it.
        let prior = self.prior.map(|prior| {
            let check = (self.config.dense_prior_check_chi2, self.config.min_tracked_inliers);
            let weight = prior_weight(&self.camera, self.bf, initial, &corr, &prior, check);
            PosePrior {
                rotation_information: prior.rotation_information * weight,
                translation_information: prior.translation_information * weight,
                ..prior
            }
        });
        let est = optimize_pose_with_prior(&self.camera, self.bf, initial, &corr, prior.as_ref());
        for (k, &i) in which.iter().enumerate() {
            if !est.inliers[k] {
                matches[i] = None;
            }
        }
        Some(est.camera_from_world)
    }

    /// Global recovery: brute-force matching against the most similar keyframes,
    /// PnP-RANSAC, pose optimisation and the local map.
    fn relocalize(
        &mut self,
        feats: &FrameFeatures,
        index: &GridIndex,
        gray: &[u8],
        times: &mut StageTimes,
    ) -> Option<(Isometry3<f64>, Vec<Option<PointId>>)> {
        if feats.features.len() < RELOC_MIN_MATCHES {
            return None;
        }
        let t = Instant::now();
        let thumb = thumbnail(gray, self.camera.width as usize, self.camera.height as usize);
        let mut ranked: Vec<(f32, KeyframeId)> =
            self.map.keyframes.values().map(|kf| (-kf.thumbnail.iter().zip(&thumb).map(|(a, b)| a * b).sum::<f32>(), kf.id)).collect();
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut candidates: Vec<KeyframeId> = ranked.iter().take(self.config.relocalization_candidates).map(|r| r.1).collect();
        if let Some(r) = self.reference
            && !candidates.contains(&r)
        {
            candidates.push(r);
        }
        times.matching += t.elapsed();
        let mut best: Option<(usize, Isometry3<f64>, Vec<Option<PointId>>)> = None;
        for kf_id in candidates {
            let t = Instant::now();
            let Some(kf) = self.map.keyframes.get(&kf_id) else { continue };
            let kf_points: Vec<(Descriptor, PointId)> =
                kf.points.iter().enumerate().filter_map(|(i, p)| p.map(|id| (kf.features.descriptors[i], id))).collect();
            let pairs = brute_force_match(&feats.descriptors, &kf_points, self.config.max_descriptor_distance);
            if pairs.len() < RELOC_MIN_MATCHES {
                times.matching += t.elapsed();
                continue;
            }
            let pnp = self.pnp_ransac(feats, &pairs);
            times.matching += t.elapsed();
            let Some((pose, inlier_pairs)) = pnp else { continue };
            let mut matches = vec![None; feats.features.len()];
            for (fi, id) in inlier_pairs {
                matches[fi] = Some(id);
            }
            let t = Instant::now();
            let refined = self.optimize(feats, pose, &mut matches);
            times.optimization += t.elapsed();
            let Some(refined) = refined else { continue };
            let Some((pose, matches)) = self.track_local_map(feats, index, refined, times) else { continue };
            let n = matches.iter().filter(|m| m.is_some()).count();
            if n >= self.config.min_relocalization_inliers && best.as_ref().is_none_or(|b| n > b.0) {
                best = Some((n, pose, matches));
            }
        }
        best.map(|(_, pose, matches)| (pose, matches))
    }

    /// PnP-RANSAC (OpenCV) on ideal pixels; returns `camera_from_world` and the inlier pairs.
    fn pnp_ransac(&self, feats: &FrameFeatures, pairs: &[(usize, PointId)]) -> Option<PnpSolution> {
        let mut points = Vec::new();
        let mut used = Vec::new();
        for &(fi, id) in pairs {
            let Some(mp) = self.map.points.get(&id) else { continue };
            points.push((mp.point_in_world, feats.features[fi].ideal));
            used.push((fi, id));
        }
        if used.len() < RELOC_MIN_MATCHES {
            return None;
        }
        let params = PnpRansac { iterations: PNP_ITERATIONS, threshold_px: PNP_REPROJECTION_PX, confidence: PNP_CONFIDENCE };
        let (pose, inliers) = pnp_ransac(&self.camera, &points, params)?;
        if inliers.len() < RELOC_MIN_MATCHES {
            return None;
        }
        Some((pose, inliers.into_iter().filter_map(|i| used.get(i).copied()).collect()))
    }

    /// Makes the frame a keyframe: records its matches, creates points from its
    /// unmatched features with depth, runs local BA and culls points. Returns the
    /// keyframe's points (for the next frame's motion model).
    fn insert_keyframe(
        &mut self,
        timestamp_ns: u64,
        world_from_camera: Isometry3<f64>,
        feats: FrameFeatures,
        gray: &[u8],
        matches: Vec<Option<PointId>>,
    ) -> Vec<PointId> {
        let id = self.map.next_keyframe_id();
        let n = feats.features.len();
        let thumb = thumbnail(gray, self.camera.width as usize, self.camera.height as usize);
        let new = new_point_order(&feats.features, &matches, self.config.new_point_cell_px);
        let limit = if self.map.keyframes.is_empty() { usize::MAX } else { self.config.max_new_points_per_keyframe };
        let kf = Keyframe { id, timestamp_ns, world_from_camera, features: feats, points: vec![None; n], thumbnail: thumb };
        self.map.keyframes.insert(id, kf);
        for (i, m) in matches.iter().enumerate() {
            if let Some(p) = m {
                self.map.add_observation(*p, id, i);
            }
        }
        for &i in new.iter().take(limit) {
            let Some(kf) = self.map.keyframes.get(&id) else { break };
            let f = &kf.features.features[i];
            let Some(pc) = f.point_in_camera(&self.camera) else { continue };
            let point = MapPoint {
                point_in_world: world_from_camera * pc,
                descriptor: kf.features.descriptors[i],
                octave: f.octave,
                observations: Vec::new(),
                created_by: id,
                visible: 1,
                found: 1,
            };
            let pid = self.map.add_point(point);
            self.map.add_observation(pid, id, i);
        }
        self.reference = Some(id);
        self.frames_since_keyframe = 0;
        self.local_bundle_adjustment();
        self.cull_points(id);
        self.forget_keyframes(id, world_from_camera);
        self.map.keyframes.get(&id).map(|kf| kf.points.iter().flatten().copied().collect()).unwrap_or_default()
    }

    /// After inserting a keyframe: remembers it for rectification when a rolling
    /// shutter distorts it and this frame had no motion to rectify it with.
    fn remember_if_unrectified(&mut self, rectified: bool) {
        if self.camera.readout_s > 0.0 && !rectified {
            self.unrectified_keyframe = self.map.keyframes.keys().next_back().copied();
        }
    }

    /// Rectifies a keyframe's keypoints for a rolling shutter with the camera's motion
    /// `previous_from_current` over `interval_s` (a step next to it, as constant
    /// velocity), and moves the points only it has seen to its rectified keypoints.
    fn rectify_keyframe(&mut self, id: KeyframeId, previous_from_current: &Isometry3<f64>, interval_s: f64) {
        let Some(kf) = self.map.keyframes.get_mut(&id) else { return };
        rectify_rolling_shutter(&self.camera, &mut kf.features.features, previous_from_current, interval_s);
        let Some(kf) = self.map.keyframes.get(&id) else { return };
        for (i, point) in kf.points.iter().enumerate() {
            let Some(pid) = point else { continue };
            let Some(mp) = self.map.points.get_mut(pid) else { continue };
            if let ([(only, _)], Some(pc)) = (mp.observations.as_slice(), kf.features.features[i].point_in_camera(&self.camera))
                && *only == id
            {
                mp.point_in_world = kf.world_from_camera * pc;
            }
        }
    }

    /// Sliding-window BA over the newest keyframes and their points.
    fn local_bundle_adjustment(&mut self) {
        if self.config.ba_window < 2 || self.map.keyframes.len() < 2 {
            return;
        }
        let window: Vec<KeyframeId> = self.map.keyframes.keys().rev().take(self.config.ba_window).copied().collect();
        let window_set: HashSet<KeyframeId> = window.iter().copied().collect();
        let mut points = ba::Indexer::<PointId>::default();
        for kf in &window {
            for p in self.map.keyframes[kf].points.iter().flatten() {
                points.get_or_insert(*p);
            }
        }
        // Fixed keyframes: those outside the window sharing the most points with it.
        let mut shared: HashMap<KeyframeId, usize> = HashMap::new();
        for p in &points.keys {
            for (kf, _) in &self.map.points[p].observations {
                if !window_set.contains(kf) {
                    *shared.entry(*kf).or_default() += 1;
                }
            }
        }
        let mut fixed: Vec<(usize, KeyframeId)> = shared.into_iter().map(|(k, n)| (n, k)).collect();
        fixed.sort_by(|a, b| b.cmp(a));
        let fixed: Vec<KeyframeId> = fixed.into_iter().take(BA_MAX_FIXED).map(|(_, k)| k).collect();
        let mut poses = ba::Indexer::<KeyframeId>::default();
        let mut problem = ba::Problem { poses: Vec::new(), fixed: Vec::new(), points: Vec::new(), observations: Vec::new() };
        // The very first keyframe defines the world frame: keep it fixed.
        let first = self.map.keyframes.keys().next().copied();
        for kf in window.iter().chain(&fixed) {
            poses.get_or_insert(*kf);
            problem.poses.push(self.map.keyframes[kf].world_from_camera.inverse());
            problem.fixed.push(!window_set.contains(kf) || Some(*kf) == first);
        }
        for p in &points.keys {
            problem.points.push(self.map.points[p].point_in_world);
        }
        let mut obs_keys = Vec::new();
        for (pi, p) in points.keys.iter().enumerate() {
            for &(kf, fi) in &self.map.points[p].observations {
                if let Some(&ci) = poses.index.get(&kf) {
                    let m = self.measurement(&self.map.keyframes[&kf].features.features[fi]);
                    problem.observations.push((ci, pi, m));
                    obs_keys.push((*p, kf));
                }
            }
        }
        ba::solve(&self.camera, self.bf, &mut problem, self.config.ba_iterations);
        for (ci, kf) in poses.keys.iter().enumerate() {
            if !problem.fixed[ci]
                && let Some(k) = self.map.keyframes.get_mut(kf)
            {
                k.world_from_camera = problem.poses[ci].inverse();
            }
        }
        for (pi, p) in points.keys.iter().enumerate() {
            if let Some(mp) = self.map.points.get_mut(p) {
                mp.point_in_world = problem.points[pi];
            }
        }
        for k in ba::outliers(&self.camera, self.bf, &problem) {
            let (p, kf) = obs_keys[k];
            self.map.remove_observation(p, kf);
        }
    }

    /// Removes points that were rarely re-found or never seen from a second keyframe.
    fn cull_points(&mut self, newest: KeyframeId) {
        let doomed: Vec<PointId> = self
            .map
            .points
            .iter()
            .filter(|(_, mp)| {
                let old = newest.saturating_sub(mp.created_by) >= CULL_AFTER_KEYFRAMES;
                (mp.visible >= CULL_MIN_VISIBLE && f64::from(mp.found) < CULL_FOUND_RATIO * f64::from(mp.visible))
                    || (old && mp.observations.len() < 2)
            })
            .map(|(id, _)| *id)
            .collect();
        for id in doomed {
            self.map.erase_point(id);
        }
    }
}

/// Where dense odometry starts a frame's alignment, `intervals` frame intervals
/// after the last one, given the motion model's `velocity` (`current_from_previous`
/// over the intervals it spanned; `None` while lost or unknown). After dropped
/// frames (or from a slower camera) the step is larger than the alignment's identity
/// start can reach: the motion model's step over those intervals starts it (up to
/// [`MAX_GUESS_INTERVALS`]; beyond, standing still). At the nominal rate the alignment
/// starts from the identity, and from the motion model's step as well where the two
/// may land apart (`dense_second_start_ratio`, 0: off).
fn dense_start(velocity: Option<(Isometry3<f64>, f64)>, intervals: f64, config: &TrackerConfig) -> DenseStart {
    match velocity {
        Some((v, velocity_intervals)) if intervals <= MAX_GUESS_INTERVALS => {
            let guess = scale_motion(&v, intervals / velocity_intervals).inverse();
            let (ratio, share) = (config.dense_second_start_ratio, config.dense_second_start_share);
            if intervals > 1.0 {
                DenseStart::Guess(guess)
            } else if ratio > 0.0 {
                DenseStart::IdentityOrGuess { guess, ratio, share }
            } else {
                DenseStart::Identity
            }
        }
        _ => DenseStart::Identity,
    }
}

/// Brute-force Hamming matching of frame descriptors against keyframe points with
/// the ratio test; one frame feature per point. Returns (feature index, point).
fn brute_force_match(frame: &[Descriptor], points: &[(Descriptor, PointId)], max_distance: u32) -> Vec<(usize, PointId)> {
    let mut best_for_point: HashMap<PointId, (u32, usize)> = HashMap::new();
    for (fi, d) in frame.iter().enumerate() {
        let (mut best, mut second, mut best_p) = (u32::MAX, u32::MAX, None);
        for (pd, id) in points {
            let dist = hamming(d, pd);
            if dist < best {
                second = best;
                best = dist;
                best_p = Some(*id);
            } else if dist < second {
                second = dist;
            }
        }
        let Some(id) = best_p else { continue };
        if best > max_distance || (best as f32) > RELOC_MATCH_RATIO * second as f32 {
            continue;
        }
        let e = best_for_point.entry(id).or_insert((u32::MAX, fi));
        if best < e.0 {
            *e = (best, fi);
        }
    }
    let mut out: Vec<(usize, PointId)> = best_for_point.into_iter().map(|(id, (_, fi))| (fi, id)).collect();
    out.sort_unstable();
    out
}

/// The unmatched features with depth in the order a keyframe makes new map points
/// from them (`tracking.new_point_cell_px`): spread over square cells of
/// `cell_px`, the nearest of every cell first, then the second nearest of each, and
/// so on (nearest first within a round); `cell_px` 0: nearest first over the frame.
fn new_point_order(features: &[Feature], matches: &[Option<PointId>], cell_px: u32) -> Vec<usize> {
    let mut nearest_first: Vec<(f64, usize)> = features
        .iter()
        .enumerate()
        .filter(|(i, _)| matches.get(*i).is_none_or(|m| m.is_none()))
        .filter_map(|(i, f)| f.depth.map(|z| (z, i)))
        .collect();
    nearest_first.sort_by(|a, b| a.0.total_cmp(&b.0));
    if cell_px == 0 {
        return nearest_first.into_iter().map(|(_, i)| i).collect();
    }
    let cell_px = cell_px as f32;
    let mut taken: HashMap<(u32, u32), usize> = HashMap::new();
    // (round, nearness): the k-th nearest of its cell is in round k.
    let mut ranked: Vec<(usize, usize)> = nearest_first
        .iter()
        .enumerate()
        .map(|(nearness, &(_, i))| {
            let at = &features[i].raw;
            // Keypoints lie in the image (a stray negative coordinate saturates to cell 0).
            let round = taken.entry(((at.x / cell_px) as u32, (at.y / cell_px) as u32)).or_default();
            *round += 1;
            (*round, nearness)
        })
        .collect();
    ranked.sort_unstable();
    ranked.into_iter().map(|(_, nearness)| nearest_first[nearness].1).collect()
}

/// The share of the dense prior's information a frame keeps
/// (`tracking.dense_prior_check_chi2`, `threshold`; 0: all of it): the features
/// alone place the frame from `initial`, and the prior's distance from that
/// placement, χ² over the sum of both covariances (the features' the inverse of
/// their information at their placement), is weighed as a Huber kernel would.
/// Features placing the frame on fewer than `min_inliers` inliers (a frame the
/// mask nearly fills) are no judge: the prior keeps all of its information.
fn prior_weight(
    camera: &Camera,
    bf: f64,
    initial: Isometry3<f64>,
    correspondences: &[(Point3<f64>, Measurement)],
    prior: &PosePrior,
    (threshold, min_inliers): (f64, usize),
) -> f64 {
    if threshold <= 0.0 {
        return 1.0;
    }
    let features = optimize_pose(camera, bf, initial, correspondences);
    if features.inlier_count < min_inliers {
        return 1.0;
    }
    let mut information = Matrix6::<f64>::zeros();
    for ((point_in_world, m), _) in correspondences.iter().zip(&features.inliers).filter(|(_, inlier)| **inlier) {
        if let Some((r, d_pose)) = linearise_pose(camera, bf, &features.camera_from_world, point_in_world, m) {
            let j = d_pose.rows(0, r.rows);
            information += j.transpose() * j * m.information;
        }
    }
    // Too few features to place the frame on their own: nothing to check against.
    let Some(mut covariance) = information.try_inverse() else { return 1.0 };
    for i in 0..3 {
        covariance[(i, i)] += 1.0 / prior.rotation_information;
        covariance[(i + 3, i + 3)] += 1.0 / prior.translation_information;
    }
    let Some(combined) = covariance.try_inverse() else { return 1.0 };
    // prior = exp(e) · placement, e = (ω, v), as the prior's own residual.
    let d = prior.camera_from_world * features.camera_from_world.inverse();
    let (w, v) = (d.rotation.scaled_axis(), d.translation.vector);
    let e = Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z);
    let chi2 = e.dot(&(combined * e));
    // A degenerate placement judges nothing.
    if chi2.is_nan() { 1.0 } else { huber_weight(chi2, threshold) }
}

/// The share of a measurement's information left when it is matched to a map point
/// known from `observations` keyframe measurements of the same noise: the point's
/// own error (variance σ²/n) adds to the new measurement's (σ²), so the residual has
/// variance σ²·(1 + 1/n). A point seen once counts half; a well-observed one almost
/// fully. The χ² inlier gate scales with it (a match to a point seen once may be
/// √2 further off), and right after a keyframe the dense prior weighs relatively
/// more against the features.
fn point_information_share(observations: usize) -> f64 {
    let n = observations.max(1) as f64;
    n / (n + 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_match_weighs_by_how_well_its_point_is_known() {
        assert_eq!(point_information_share(1), 0.5, "a point measured once: residual variance doubles");
        assert_eq!(point_information_share(0), 0.5, "no observation left counts as one");
        assert_eq!(point_information_share(3), 0.75);
        assert!(point_information_share(99) > 0.98);
    }

    /// The motion model starts the alignment after dropped frames (scaled to the
    /// intervals, up to five), starts a second one at the nominal rate unless
    /// turned off, and nothing while the velocity is unknown (lost).
    #[test]
    fn the_dense_start_follows_the_rate_and_the_configuration() {
        let config = TrackerConfig::default();
        let v = Isometry3::translation(0.01, 0.0, 0.0);
        let step = |n: f64| scale_motion(&v, n).inverse();
        assert_eq!(dense_start(None, 1.0, &config), DenseStart::Identity);
        assert_eq!(dense_start(None, 3.0, &config), DenseStart::Identity);
        assert_eq!(dense_start(Some((v, 1.0)), 1.0, &config), DenseStart::IdentityOrGuess { guess: step(1.0), ratio: 0.8, share: 0.9 });
        assert_eq!(dense_start(Some((v, 1.0)), 3.0, &config), DenseStart::Guess(step(3.0)));
        assert_eq!(dense_start(Some((v, 2.0)), 1.0, &config), DenseStart::IdentityOrGuess { guess: step(0.5), ratio: 0.8, share: 0.9 });
        assert_eq!(dense_start(Some((v, 1.0)), 6.0, &config), DenseStart::Identity, "beyond five intervals");
        let off = TrackerConfig { dense_second_start_ratio: 0.0, ..TrackerConfig::default() };
        assert_eq!(dense_start(Some((v, 1.0)), 1.0, &off), DenseStart::Identity);
        assert_eq!(dense_start(Some((v, 1.0)), 3.0, &off), DenseStart::Guess(step(3.0)), "dropped frames are unchanged");
    }

    #[test]
    fn gray_matches_bt601() {
        assert_eq!(to_gray(&[255, 255, 255, 0, 0, 0, 255, 0, 0]), vec![255, 0, 77]);
    }

    #[test]
    fn new_points_are_spread_over_cells_nearest_first_in_each() {
        use nalgebra::Point2;
        let feature = |x: f32, y: f32, depth: Option<f64>| Feature {
            raw: Point2::new(x, y),
            ideal: Point2::new(f64::from(x), f64::from(y)),
            octave: 0,
            depth,
        };
        let features = [
            feature(10.0, 10.0, Some(1.0)),  // cell (0, 0)
            feature(20.0, 20.0, Some(0.5)),  // cell (0, 0), the nearest of all
            feature(100.0, 10.0, Some(2.0)), // cell (1, 0)
            feature(30.0, 30.0, Some(0.7)),  // cell (0, 0)
            feature(200.0, 200.0, None),     // no depth: no point
            feature(110.0, 20.0, Some(0.1)), // matched already: no new point
        ];
        let matches = [None, None, None, None, None, Some(7)];
        assert_eq!(new_point_order(&features, &matches, 64), [1, 2, 3, 0], "one of each cell per round, nearest first");
        assert_eq!(new_point_order(&features, &matches, 0), [1, 3, 0, 2], "0: nearest first over the frame");
        assert_eq!(new_point_order(&features, &matches[..2], 64), [5, 1, 3, 2, 0], "a feature without a match slot is unmatched");
    }

    #[test]
    fn the_dense_prior_loses_weight_as_far_as_the_features_disagree() {
        use nalgebra::{Point2, Vector3};
        let camera = Camera::pinhole(640, 480, 520.0, 520.0, 320.0, 240.0, 5000.0);
        let bf = 41.6;
        let truth = Isometry3::new(Vector3::new(0.05, -0.02, 0.1), Vector3::new(0.02, 0.05, -0.01));
        let correspondences: Vec<(Point3<f64>, Measurement)> = (0..200)
            .map(|i| {
                let pw =
                    Point3::new(((i * 37) % 200) as f64 / 100.0 - 1.0, ((i * 91) % 150) as f64 / 100.0 - 0.75, 1.5 + (i % 7) as f64 * 0.3);
                let pc = truth * pw;
                let ideal = camera.project(&pc).expect("in front");
                (pw, Measurement { ideal: Point2::from(ideal.coords), disparity: Some(bf / pc.z), information: 1.0 })
            })
            .collect();
        let prior_at = |offset_m: f64| PosePrior {
            camera_from_world: Isometry3::translation(offset_m, 0.0, 0.0) * truth,
            rotation_information: 0.1f64.to_radians().powi(2).recip(),
            translation_information: 0.001f64.powi(2).recip(),
        };
        let weight = |offset_m: f64, check: (f64, usize)| prior_weight(&camera, bf, truth, &correspondences, &prior_at(offset_m), check);
        assert_eq!(weight(0.0, (50.0, 30)), 1.0, "a prior where the features put the frame keeps its weight");
        assert_eq!(weight(0.0005, (50.0, 30)), 1.0, "half its σ off: within the threshold");
        let (near, far) = (weight(0.02, (50.0, 30)), weight(0.05, (50.0, 30)));
        assert!(0.0 < far && far < near && near < 1.0, "2 cm off keeps {near}, 5 cm off {far}");
        // Huber: the weight falls as the distance grows (χ² with its square).
        assert!((near / far - 2.5).abs() < 0.05, "weights {near} / {far}");
        assert_eq!(weight(0.05, (0.0, 30)), 1.0, "threshold 0: the check is off");
        assert_eq!(weight(0.05, (50.0, 201)), 1.0, "fewer inliers than needed: the features are no judge");

        // Far points without depth cannot tell a sideways step from a turn: a prior
        // off by 2 cm sideways with the compensating turn keeps its weight, since the
        // features' covariance along that direction is wide (without the features'
        // term in the sum it would be 20 σ of the prior away). A 10 cm step without
        // the turn, which every point shows as a 1 ° turn would be, loses weight.
        let far: Vec<(Point3<f64>, Measurement)> = (0..40)
            .map(|i| {
                let pw =
                    Point3::new(((i * 37) % 40) as f64 / 10.0 - 2.0, ((i * 13) % 40) as f64 / 40.0 * 3.0 - 1.5, 4.0 + (i % 5) as f64 * 0.5);
                let ideal = camera.project(&pw).expect("in front");
                (pw, Measurement { ideal: Point2::from(ideal.coords), disparity: None, information: 1.0 })
            })
            .collect();
        let prior = |camera_from_world: Isometry3<f64>| PosePrior {
            camera_from_world,
            rotation_information: 0.1f64.to_radians().powi(2).recip(),
            translation_information: 0.001f64.powi(2).recip(),
        };
        let sideways_turned = prior(Isometry3::new(Vector3::new(0.02, 0.0, 0.0), Vector3::new(0.0, -0.004, 0.0)));
        let sideways = prior(Isometry3::translation(0.1, 0.0, 0.0));
        let check = (50.0, 30);
        assert_eq!(prior_weight(&camera, bf, Isometry3::identity(), &far, &sideways_turned, check), 1.0, "the features cannot tell");
        assert!(prior_weight(&camera, bf, Isometry3::identity(), &far, &sideways, check) < 1.0, "every point shows the step");
    }

    #[test]
    fn brute_force_keeps_one_feature_per_point() {
        let a = [0u64, 0, 0, 0];
        let b = [u64::MAX, u64::MAX, 0, 0];
        let m = brute_force_match(&[a, a, b], &[(a, 7), (b, 9)], 50);
        assert_eq!(m, vec![(0, 7), (2, 9)]);
    }
}
