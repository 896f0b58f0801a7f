//! Every tunable of the tracker, with its documented default.
//!
//! Defaults are chosen for any indoor structured-light or time-of-flight RGB-D
//! camera at VGA resolution and 15–30 Hz; none is fitted to a particular clip.

use serde::{Deserialize, Serialize};

/// Tracking configuration (`[tracking]` in the server's TOML).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackerConfig {
    /// ORB features kept per frame after spreading them over the image grid.
    pub features: usize,
    /// Candidate corners detected before the grid spreads them (≥ `features`).
    pub candidate_features: usize,
    /// ORB pyramid scale factor between levels.
    pub scale_factor: f32,
    /// ORB pyramid levels.
    pub pyramid_levels: u32,
    /// FAST threshold for corner detection (intensity steps, 0–255).
    pub fast_threshold: u32,
    /// Side of the square grid cells (pixels) over which features are spread evenly.
    pub grid_cell_px: u32,
    /// Nearest valid depth in metres; closer readings are treated as missing.
    pub min_depth_m: f64,
    /// Farthest trusted depth in metres; farther readings are treated as missing.
    pub max_depth_m: f64,
    /// A keypoint's depth is unreliable when its 3×3 neighbourhood spans more than
    /// this fraction of its depth (it sits on a depth edge).
    pub depth_edge_ratio: f64,
    /// Virtual stereo baseline (metres) that turns a depth reading into a disparity
    /// residual `fx·b/z`, in pixels: inverse depth matches the quadratic noise of
    /// structured-light sensors. 0.08 m is the Kinect/Xtion projector baseline.
    pub depth_baseline_m: f64,
    /// Features with valid depth the first frame needs to start the map.
    pub min_init_features: usize,
    /// Search radius (pixels at pyramid level 0) when matching the last frame's points
    /// projected with the motion model.
    pub motion_search_radius_px: f64,
    /// Search radius (pixels at level 0) when matching the local map after a first pose.
    pub local_map_search_radius_px: f64,
    /// Largest Hamming distance (of 256 bits) of an accepted match.
    pub max_descriptor_distance: u32,
    /// Best/second-best distance ratio a match must beat when two candidates compete.
    pub match_ratio: f32,
    /// Predict each frame's pose with a constant-velocity model (else: the last pose).
    /// Off by default: on real handheld data (TUM fr1_rpy) and on the synthetic
    /// sequence the prediction fed its own error back through the motion-model
    /// search and made tracking worse (docs/tracking.md, "Tracking accuracy").
    pub constant_velocity: bool,
    /// Dense RGB-D odometry (photometric + point-to-plane ICP, OpenCV's
    /// RgbdICPOdometry at half resolution) from the previous frame predicts each
    /// pose and enters its optimisation as a robust prior (`dense.rs`).
    pub dense_odometry: bool,
    /// Per-axis σ of that prior on one frame step: rotation in degrees and
    /// translation in metres. A dense alignment of tens of thousands of pixels
    /// pins the step down far more tightly than a few hundred corners at one
    /// pixel each do along their weakest direction (a sideways translation traded
    /// for a rotation), so the prior is tight; it is robust (Huber at χ² 95 %), so
    /// a failed alignment loses its weight instead of dragging the pose.
    pub dense_prior_sigma_deg: f64,
    pub dense_prior_sigma_m: f64,
    /// The frame interval (seconds) those σ hold for. A step spanning n such
    /// intervals (frames dropped, a slower camera) widens them n-fold (n rounded,
    /// at least 1): the alignment's error grows with the motion it must recover.
    pub dense_prior_interval_s: f64,
    /// How far the features may disagree with the dense prior before it loses
    /// weight: the features alone place the frame first, and where the prior lies
    /// further from that placement than this χ² (over both covariances, the
    /// features' from their information at their placement), its information is
    /// scaled down as a Huber kernel would (√(threshold / χ²)). Dense odometry
    /// aligns every pixel the mask leaves, a near thing the mask missed included,
    /// while the features are matched to the map with a robust kernel. Off (0) by
    /// default: at 50 (four times the χ² 95 % quantile for six degrees of freedom;
    /// the features' covariance assumes independent one-pixel errors) streamed ATE
    /// on the public clip falls from 0.90 to 0.81 cm and the board scene's from
    /// 2.72 to 2.57 cm, but streamed RPE rises to 5.90–6.03 mm, over the 6 mm the
    /// tracker is held to (docs/people.md, "an eighth session"). Where large unknown
    /// things move in front of the camera, 50 is the value measured. Features placing
    /// the frame on fewer than `min_tracked_inliers` inliers are no judge (the prior
    /// keeps its weight). When on, each of a frame's two pose optimisations first
    /// runs one without the prior (the tracker's 10 ms per frame became 11 ms on a
    /// 2-core machine, `tracker_under_a_configuration`).
    pub dense_prior_check_chi2: f64,
    /// Dense odometry's second start. Each frame's alignment starts from standing
    /// still; where it ends more than 2 cm or 1° from the motion model's step
    /// (the last tracked step), it is run again from that step, and the second
    /// step is kept where it explains the grey levels better nearly everywhere:
    /// the image is cut into 40-pixel cells, a cell favours the step whose mean
    /// grey-level difference over the two frames' overlap there is below this
    /// share of the other's (and a grey level lower), and at least
    /// `dense_second_start_share` of the cells that favour either must favour the
    /// second. Coarse-to-fine alignment from standing still lands in a wrong
    /// minimum where a near thing masked out leaves little of the image to align
    /// in a fast turn (rpy_b, the crowd's exact masks: a step 91 mm off, 37 mm of
    /// point-to-plane error on the pixels left), and misregisters the whole image
    /// (75–100 % of the deciding cells, 92 % or more in 14 of 17 such frames,
    /// favour the start from the motion model); where the motion model followed a
    /// moving thing the mask missed, that thing's cells favour it and the room's
    /// do not (17 of 31 at a board's onset). 0 turns the second start off
    /// (docs/tracking.md, "Two starts").
    pub dense_second_start_ratio: f64,
    /// See `dense_second_start_ratio`: the share of the deciding cells that must
    /// favour the second start's step.
    pub dense_second_start_share: f64,
    /// Matches below which the motion-model search is repeated with a wider radius,
    /// then replaced by PnP-RANSAC.
    pub min_motion_matches: usize,
    /// Inlier matches (after optimisation) for a frame to count as tracked.
    pub min_tracked_inliers: usize,
    /// Inlier matches a relocalization must reach to be accepted.
    pub min_relocalization_inliers: usize,
    /// Keyframes whose points form the local map used for tracking.
    pub local_keyframes: usize,
    /// A new keyframe is taken when the tracked points fall below this fraction of
    /// the reference keyframe's tracked points.
    pub keyframe_tracked_ratio: f64,
    /// A new keyframe is taken at least every this many frames.
    pub keyframe_max_interval: u32,
    /// Keyframes the tracker keeps, at most (0: every one). A keyframe every few
    /// frames for hours would hold them all in memory (about 115 KB each with their
    /// features, point links and points: 2.6 GB an hour at 30 Hz) and rank them all
    /// for every frame's local map. Beyond this number one is forgotten for each new
    /// one, never the bundle-adjustment window, the reference, the `local_keyframes`
    /// nearest the new one (the next frames track on them), nor one a rolling
    /// shutter's next step must still rectify: of the 50 newest others, the newest
    /// whose points three other keyframes see as well (90 % of them, ORB-SLAM's
    /// redundancy), else the oldest. Forgotten keyframes are no longer
    /// relocalization candidates (500 keyframes are about 80 s of new ground at 30
    /// Hz: a robot exploring cannot relocalize where it began; the fleet's place
    /// recognition still can); the server's store keeps every keyframe record. At
    /// least `local_keyframes + ba_window + 1` (`ba_window` counted as at least 1).
    pub max_keyframes: usize,
    /// New map points created per keyframe, at most.
    pub max_new_points_per_keyframe: usize,
    /// New map points are made spread over the image, from the unmatched features
    /// with depth: the nearest of every square cell this wide (pixels) first, then
    /// the second nearest of each, and so on. Near points have the best depth, but
    /// the nearest over the whole frame are most often on one near thing, and on a
    /// moving one the mask missed they are most of what no map point explains
    /// (docs/people.md). 0: the nearest over the whole frame first.
    pub new_point_cell_px: u32,
    /// Keyframes optimised together by local bundle adjustment (0 disables it).
    pub ba_window: usize,
    /// Levenberg–Marquardt iterations of one local bundle adjustment.
    pub ba_iterations: u32,
    /// Keyframes tried by one relocalization attempt (most similar first).
    pub relocalization_candidates: usize,
    /// A frame the motion model places with fewer inliers than this share of the
    /// reference keyframe's tracked points is relocalized as well, and
    /// relocalization's placement replaces it when it explains more than twice as
    /// many points. A weak placement is most often a wrong one: the first step
    /// after a keyframe made without a motion (the first, a relocalized one) has
    /// no velocity to predict from, and at 7.5 Hz (every 4th frame) rpy_b's first
    /// step was placed 104 mm off on 73 of 744 points, where relocalization finds
    /// 270 and 7.7 mm. 0 turns it off.
    pub weak_placement_ratio: f64,
    /// How long (seconds of capture time since the last frame the features
    /// tracked) dense odometry alone carries the pose when feature tracking and
    /// relocalization fail, before the tracker reports LOST: the frames meanwhile
    /// are `Coasting`, posed but not mapped. 0 turns it off. (ORB-SLAM3 carries a
    /// lost pose on its IMU the same way, for 5 s.)
    pub coast_s: f64,
    /// A dense step carries a coasted pose only if it explains at least this share
    /// of its overlap: of this frame's pixels with depth that land on the previous
    /// frame's, the share whose depth it predicts within the alignment's own 7 cm
    /// correspondence distance. Steps the features confirmed explain 0.9–1.0 at
    /// 30 Hz; a failed alignment in a fast turn explains 0.04–0.74.
    pub coast_min_agreement: f64,
}

/// Largest `tracking.candidate_features` (ORB's corners before the grid keeps `features`).
const MAX_CANDIDATE_FEATURES: usize = 100_000;
/// Largest `tracking.ba_window`: local BA's Hessian is dense in the window's poses.
const MAX_BA_WINDOW: usize = 64;
/// Largest `tracking.ba_iterations` (each a linearisation of the whole window).
const MAX_BA_ITERATIONS: u32 = 100;
/// Largest `tracking.local_keyframes` and `tracking.relocalization_candidates`.
const MAX_LOCAL_KEYFRAMES: usize = 200;

impl TrackerConfig {
    /// Rejects values the tracker cannot run with; the message names the key.
    /// (Comparisons are negated so that NaN fails them too.)
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn validate(&self) -> Result<(), String> {
        if self.features == 0 || self.candidate_features < self.features || self.candidate_features > MAX_CANDIDATE_FEATURES {
            return Err(format!(
                "tracking.features must be at least 1 and at most tracking.candidate_features, itself at most {MAX_CANDIDATE_FEATURES}"
            ));
        }
        if !(self.scale_factor > 1.0 && self.scale_factor <= 2.0 && (1..=16).contains(&self.pyramid_levels)) {
            return Err(format!(
                "tracking.scale_factor must be within (1, 2] and tracking.pyramid_levels within 1..=16, got {} and {}",
                self.scale_factor, self.pyramid_levels
            ));
        }
        // The coarsest level must keep some pixels (VGA's at 20×15 at the bound).
        let coarsest = f64::from(self.scale_factor).powi(self.pyramid_levels as i32 - 1);
        if !(coarsest <= 32.0) {
            return Err(format!(
                "tracking.scale_factor^(tracking.pyramid_levels - 1) must be at most 32 (the coarsest level's shrink), got {coarsest}"
            ));
        }
        if !(1..=254).contains(&self.fast_threshold) || self.max_descriptor_distance > 256 {
            return Err(format!(
                "tracking.fast_threshold must be within 1..=254 and tracking.max_descriptor_distance within 0..=256, got {} and {}",
                self.fast_threshold, self.max_descriptor_distance
            ));
        }
        if !(self.depth_edge_ratio >= 0.0 && self.depth_edge_ratio <= 1.0) {
            return Err(format!("tracking.depth_edge_ratio must be within [0, 1], got {}", self.depth_edge_ratio));
        }
        let radius = |r: f64| r > 0.0 && r <= 200.0;
        if !(radius(self.motion_search_radius_px) && radius(self.local_map_search_radius_px)) {
            return Err(format!(
                "tracking.motion_search_radius_px and tracking.local_map_search_radius_px must be within (0, 200] pixels, got {} and {}",
                self.motion_search_radius_px, self.local_map_search_radius_px
            ));
        }
        if !(self.keyframe_tracked_ratio >= 0.0 && self.keyframe_tracked_ratio <= 1.0) || self.keyframe_max_interval == 0 {
            return Err(format!(
                "tracking.keyframe_tracked_ratio must be within [0, 1] and tracking.keyframe_max_interval at least 1, got {} and {}",
                self.keyframe_tracked_ratio, self.keyframe_max_interval
            ));
        }
        if self.ba_window > MAX_BA_WINDOW || !(1..=MAX_BA_ITERATIONS).contains(&self.ba_iterations) {
            return Err(format!(
                "tracking.ba_window must be within 0..={MAX_BA_WINDOW} and tracking.ba_iterations within 1..={MAX_BA_ITERATIONS}, got {} and {}",
                self.ba_window, self.ba_iterations
            ));
        }
        if self.local_keyframes == 0 || self.local_keyframes > MAX_LOCAL_KEYFRAMES || self.relocalization_candidates > MAX_LOCAL_KEYFRAMES {
            return Err(format!(
                "tracking.local_keyframes must be within 1..={MAX_LOCAL_KEYFRAMES} and tracking.relocalization_candidates within 0..={MAX_LOCAL_KEYFRAMES}, got {} and {}",
                self.local_keyframes, self.relocalization_candidates
            ));
        }
        // Never forgotten: the BA window (the new keyframe at least), the local
        // map around the new one and a keyframe still to rectify.
        let fewest = self.local_keyframes + self.ba_window.max(1) + 1;
        if self.max_keyframes != 0 && self.max_keyframes < fewest {
            return Err(format!(
                "tracking.max_keyframes must be 0 (every keyframe kept) or at least local_keyframes + ba_window (at least 1) + 1 = {fewest}, got {}",
                self.max_keyframes
            ));
        }
        if !(self.min_depth_m > 0.0 && self.max_depth_m > self.min_depth_m) {
            return Err("tracking.min_depth_m must be positive and below tracking.max_depth_m".into());
        }
        if !(self.depth_baseline_m > 0.0) {
            return Err("tracking.depth_baseline_m must be positive".into());
        }
        if !(self.dense_prior_sigma_deg > 0.0 && self.dense_prior_sigma_m > 0.0) {
            return Err("tracking.dense_prior_sigma_deg and tracking.dense_prior_sigma_m must be positive".into());
        }
        if !(self.dense_prior_interval_s > 0.0 && self.dense_prior_interval_s <= 1.0) {
            return Err(format!("tracking.dense_prior_interval_s must be in (0, 1], got {}", self.dense_prior_interval_s));
        }
        if !(self.dense_prior_check_chi2 >= 0.0 && self.dense_prior_check_chi2.is_finite()) {
            return Err(format!("tracking.dense_prior_check_chi2 must be 0 (off) or positive, got {}", self.dense_prior_check_chi2));
        }
        if !(self.coast_s >= 0.0 && self.coast_s <= 60.0) {
            return Err(format!("tracking.coast_s must be in [0, 60], got {}", self.coast_s));
        }
        if !(self.dense_second_start_ratio >= 0.0 && self.dense_second_start_ratio <= 1.0) {
            return Err(format!("tracking.dense_second_start_ratio must be in [0, 1], got {}", self.dense_second_start_ratio));
        }
        if !(self.dense_second_start_share > 0.0 && self.dense_second_start_share <= 1.0) {
            return Err(format!("tracking.dense_second_start_share must be in (0, 1], got {}", self.dense_second_start_share));
        }
        if !(self.coast_min_agreement >= 0.0 && self.coast_min_agreement <= 1.0) {
            return Err(format!("tracking.coast_min_agreement must be in [0, 1], got {}", self.coast_min_agreement));
        }
        if !(self.weak_placement_ratio >= 0.0 && self.weak_placement_ratio <= 1.0) {
            return Err(format!("tracking.weak_placement_ratio must be in [0, 1], got {}", self.weak_placement_ratio));
        }
        if !(self.match_ratio > 0.0 && self.match_ratio <= 1.0) {
            return Err("tracking.match_ratio must be in (0, 1]".into());
        }
        if self.min_tracked_inliers < 3 || self.min_relocalization_inliers < 3 {
            return Err("tracking.min_tracked_inliers and tracking.min_relocalization_inliers must be at least 3".into());
        }
        Ok(())
    }
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            features: 1000,
            candidate_features: 3000,
            scale_factor: 1.2,
            pyramid_levels: 8,
            fast_threshold: 12,
            grid_cell_px: 32,
            min_depth_m: 0.1,
            max_depth_m: 6.0,
            depth_edge_ratio: 0.05,
            depth_baseline_m: 0.08,
            min_init_features: 100,
            motion_search_radius_px: 15.0,
            local_map_search_radius_px: 4.0,
            max_descriptor_distance: 80,
            match_ratio: 0.9,
            constant_velocity: false,
            dense_odometry: true,
            dense_prior_sigma_deg: 0.1,
            dense_prior_sigma_m: 0.001,
            dense_prior_interval_s: 1.0 / 30.0,
            dense_prior_check_chi2: 0.0,
            dense_second_start_ratio: 0.8,
            dense_second_start_share: 0.9,
            min_motion_matches: 20,
            min_tracked_inliers: 30,
            min_relocalization_inliers: 50,
            local_keyframes: 10,
            keyframe_tracked_ratio: 0.75,
            keyframe_max_interval: 5,
            max_keyframes: 500,
            max_new_points_per_keyframe: 400,
            new_point_cell_px: 64,
            ba_window: 6,
            ba_iterations: 8,
            relocalization_candidates: 5,
            weak_placement_ratio: 0.25,
            coast_s: 2.0,
            coast_min_agreement: 0.8,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_validates_and_bad_intervals_are_named() {
        assert_eq!(TrackerConfig::default().validate(), Ok(()));
        for bad in [0.0, -0.1, 1.5, f64::NAN] {
            let config = TrackerConfig { dense_prior_interval_s: bad, ..TrackerConfig::default() };
            let err = config.validate().expect_err("rejected");
            assert!(err.starts_with("tracking.dense_prior_interval_s must be in (0, 1]"), "{bad}: {err}");
        }
        for bad in [-0.5, 61.0, f64::NAN] {
            let err = TrackerConfig { coast_s: bad, ..TrackerConfig::default() }.validate().expect_err("rejected");
            assert!(err.starts_with("tracking.coast_s must be in [0, 60]"), "{bad}: {err}");
        }
        assert_eq!(TrackerConfig { coast_s: 0.0, ..TrackerConfig::default() }.validate(), Ok(()), "0 turns coasting off");
        let err = TrackerConfig { max_keyframes: 16, ..TrackerConfig::default() }.validate().expect_err("rejected");
        assert_eq!(
            err,
            "tracking.max_keyframes must be 0 (every keyframe kept) or at least local_keyframes + ba_window (at least 1) + 1 = 17, got 16"
        );
        for fine in [0, 17] {
            assert_eq!(TrackerConfig { max_keyframes: fine, ..TrackerConfig::default() }.validate(), Ok(()), "{fine}");
        }
        // Without BA the new keyframe is kept besides the local map and one to rectify.
        let no_ba = |max_keyframes| TrackerConfig { max_keyframes, ba_window: 0, ..TrackerConfig::default() }.validate();
        assert!(no_ba(11).expect_err("rejected").ends_with("= 12, got 11"));
        assert_eq!(no_ba(12), Ok(()));
        let err = TrackerConfig { coast_min_agreement: 1.5, ..TrackerConfig::default() }.validate().expect_err("rejected");
        assert_eq!(err, "tracking.coast_min_agreement must be in [0, 1], got 1.5");
        for bad in [-0.1, 1.01, f64::NAN] {
            let err = TrackerConfig { dense_second_start_ratio: bad, ..TrackerConfig::default() }.validate().expect_err("rejected");
            assert_eq!(err, format!("tracking.dense_second_start_ratio must be in [0, 1], got {bad}"));
        }
        assert_eq!(TrackerConfig { dense_second_start_ratio: 0.0, ..TrackerConfig::default() }.validate(), Ok(()), "0 turns it off");
        for bad in [0.0, 1.5, f64::NAN] {
            let err = TrackerConfig { dense_second_start_share: bad, ..TrackerConfig::default() }.validate().expect_err("rejected");
            assert_eq!(err, format!("tracking.dense_second_start_share must be in (0, 1], got {bad}"));
        }
        for bad in [-0.1, 1.01, f64::NAN] {
            let err = TrackerConfig { weak_placement_ratio: bad, ..TrackerConfig::default() }.validate().expect_err("rejected");
            assert!(err.starts_with("tracking.weak_placement_ratio must be in [0, 1]"), "{bad}: {err}");
        }
        assert_eq!(TrackerConfig { weak_placement_ratio: 0.0, ..TrackerConfig::default() }.validate(), Ok(()), "0 turns it off");
    }
}
