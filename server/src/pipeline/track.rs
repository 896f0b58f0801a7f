//! The tracking stage: adapts decoded frames to [`stillmap_tracking::Tracker`]
//! and its output to a [`TrackOutcome`].

use std::time::Duration;

use nalgebra::Isometry3;
use stillmap_proto::codec::{ColorImage, DepthImage};
use stillmap_proto::pb::{self, TrackingState};
use stillmap_tracking::{StageTimes, Tracker, TrackerConfig, TrackingError};

use super::stage;
use crate::convert::{camera_of, state_of};

/// What tracking made of one frame.
#[derive(Debug, Clone)]
pub struct TrackOutcome {
    pub state: TrackingState,
    pub world_from_camera: Option<Isometry3<f64>>,
    /// The time the pose refers to (capture time plus the camera's exposure offset).
    pub pose_time_ns: Option<u64>,
    /// Features used for tracking.
    pub features: u32,
    /// Keypoints the dynamic mask removed before tracking.
    pub masked_features: u32,
    /// The keyframe this frame became, if it did.
    pub new_keyframe: Option<u64>,
    /// Keyframes the tracker forgot on this frame (`tracking.max_keyframes`).
    pub forgotten_keyframes: u64,
    /// A resumed session not found in its stored world within
    /// `ResumeAnchor::find_within_s`: the session is to be given up.
    pub resume_abandoned: bool,
    /// `previous_from_current` between the last two frames, when both were tracked.
    pub previous_from_current: Option<Isometry3<f64>>,
    pub times: StageTimes,
}

impl TrackOutcome {
    /// The stage times in the order results report them.
    pub fn stages(&self) -> [(&'static str, Duration); 6] {
        let t = &self.times;
        [
            (stage::TRACK_EXTRACT, t.extraction),
            (stage::TRACK_DENSE, t.dense),
            (stage::TRACK_MATCH, t.matching),
            (stage::TRACK_OPTIMIZE, t.optimization),
            (stage::TRACK_LOCAL_BA, t.local_ba),
            (stage::TRACK, t.total),
        ]
    }
}

/// A session resumed on this server from the shared storage: its last stored
/// keyframes (`world_from_camera` and the place verification sees, newest first),
/// in whose world its new tracker must be found before it reports anything.
pub struct ResumeAnchor {
    pub keyframes: Vec<(Isometry3<f64>, stillmap_places::Place)>,
    pub verify: stillmap_places::VerifyConfig,
    /// The session's next keyframe id (its stored ones are not reused).
    pub next_keyframe_id: u64,
    /// Seconds of frames (capture time) to be found in; 0 = no limit
    /// (`session.resume_find_s`).
    pub find_within_s: f64,
}

/// One session's tracker.
pub struct SessionTracker {
    tracker: Tracker,
    /// The last frame's pose in the tracker's own world (for the camera motion
    /// perception needs: a motion, the same in any world).
    last_pose: Option<Isometry3<f64>>,
    /// `CameraInfo.exposure_time_offset_s`: from a frame's timestamp to its pose's time.
    exposure_time_offset_s: f64,
    /// The session's world from the tracker's (identity, but for a resumed session).
    world_from_tracker: Isometry3<f64>,
    /// While a resumed session's tracker is not yet found in the session's world.
    resume: Option<ResumeAnchor>,
    /// The session's keyframe ids are the tracker's plus this (a resumed session's
    /// go on from its stored ones).
    keyframe_id_offset: u64,
    /// Capture time of the first frame tracked while not yet found.
    resume_since_ns: Option<u64>,
}

impl SessionTracker {
    pub fn new(camera: &pb::CameraInfo, config: &TrackerConfig) -> Result<Self, TrackingError> {
        Ok(Self {
            tracker: Tracker::new(camera_of(camera), config.clone())?,
            last_pose: None,
            exposure_time_offset_s: camera.exposure_time_offset_s,
            world_from_tracker: Isometry3::identity(),
            resume: None,
            keyframe_id_offset: 0,
            resume_since_ns: None,
        })
    }

    /// Resumes a session in the world of its stored keyframes: until one of this
    /// tracker's keyframes is verified against one of them (PnP on their features
    /// with depth), frames are `LOST` without a pose and nothing is mapped.
    pub fn resume_in(&mut self, anchor: ResumeAnchor) {
        self.keyframe_id_offset = anchor.next_keyframe_id;
        self.resume = Some(anchor);
    }

    /// Whether the tracker is in the session's world (always, but while a resumed
    /// session is being found).
    pub fn placed(&self) -> bool {
        self.resume.is_none()
    }

    /// Whether a resumed session still not found at `capture_time_ns` has run past
    /// its time to be found (counted from its first frame here).
    fn resume_overdue(&mut self, capture_time_ns: u64) -> bool {
        let Some(anchor) = &self.resume else { return false };
        let since = *self.resume_since_ns.get_or_insert(capture_time_ns);
        anchor.find_within_s > 0.0 && capture_time_ns.saturating_sub(since) as f64 * 1e-9 > anchor.find_within_s
    }

    /// Tries to find the tracker's keyframe `id` among the anchor's keyframes;
    /// on success the tracker is in the session's world from now on.
    fn relocate(&mut self, id: u64) {
        let (Some(anchor), Some(record)) = (self.resume.as_ref(), self.tracker_record(id)) else { return };
        let camera = self.tracker.camera().clone();
        let (query, tracker_from_query) = crate::fleet::place_of_record(&camera, &record);
        // Every stored keyframe it is verified against proposes where the tracker is.
        // A false match must not put the session in a wrong world: at least
        // RESUME_AGREEING proposals must agree (within 5 cm and 2°, as the fleet
        // merge asks); a single verification is off by a centimetre or two, so the
        // agreeing ones are averaged, weighted by their inliers.
        let proposals: Vec<(Isometry3<f64>, f64)> = anchor
            .keyframes
            .iter()
            .filter_map(|(world_from_candidate, candidate)| {
                let v = stillmap_places::verify(&camera, &query, candidate, &anchor.verify)?;
                let world_from_query = world_from_candidate * v.query_from_candidate.inverse();
                Some((world_from_query * tracker_from_query.inverse(), v.inliers as f64))
            })
            .collect();
        let agreeing = largest_agreeing(&proposals);
        // A session stored with a single keyframe has only its one proposal.
        if agreeing.len() < RESUME_AGREEING.min(anchor.keyframes.len()) {
            return;
        }
        if let Some(world_from_tracker) = weighted_mean(&agreeing) {
            self.world_from_tracker = world_from_tracker;
            tracing::info!(agreeing = agreeing.len(), verified = proposals.len(), "resumed session found in its stored world");
            self.resume = None;
        }
    }

    /// Tracks a decoded frame. A tracking error (which only malformed input can
    /// cause) leaves the frame `LOST` without a pose.
    pub fn track(
        &mut self,
        sequence: u64,
        capture_time_ns: u64,
        color: &ColorImage,
        depth: &DepthImage,
        dynamic_mask: Option<&[u8]>,
    ) -> TrackOutcome {
        let input = stillmap_tracking::FrameInput { timestamp_ns: capture_time_ns, rgb: &color.data, depth: &depth.data, dynamic_mask };
        let previous_pose = self.last_pose.take();
        let forgotten_before = self.tracker.forgotten_keyframes();
        let out = match self.tracker.track(&input) {
            Ok(out) => out,
            Err(e) => {
                tracing::warn!(sequence, "tracking failed: {e}");
                return TrackOutcome {
                    state: TrackingState::Lost,
                    world_from_camera: None,
                    pose_time_ns: None,
                    features: 0,
                    masked_features: 0,
                    new_keyframe: None,
                    forgotten_keyframes: 0,
                    resume_abandoned: self.resume_overdue(capture_time_ns),
                    previous_from_current: None,
                    times: StageTimes::default(),
                };
            }
        };
        let forgotten_keyframes = self.tracker.forgotten_keyframes() - forgotten_before;
        // Keyframe ids only grow: the newest is the one just made.
        let new_keyframe =
            if out.keyframe { self.tracker.map().keyframes.keys().next_back().map(|id| id + self.keyframe_id_offset) } else { None };
        if let (false, Some(id)) = (self.placed(), new_keyframe) {
            self.relocate(id);
        }
        self.last_pose = out.world_from_camera;
        let previous_from_current = previous_pose.zip(out.world_from_camera).map(|(previous, now)| previous.inverse() * now);
        if !self.placed() {
            // Not yet found in the session's world: nothing to report or to map.
            return TrackOutcome {
                state: TrackingState::Lost,
                world_from_camera: None,
                pose_time_ns: None,
                features: out.tracked_points as u32,
                masked_features: out.masked_features as u32,
                new_keyframe: None,
                forgotten_keyframes,
                resume_abandoned: self.resume_overdue(capture_time_ns),
                previous_from_current,
                times: out.times,
            };
        }
        let world_from_camera = out.world_from_camera.map(|p| self.world_from_tracker * p);
        TrackOutcome {
            state: state_of(out.state),
            world_from_camera,
            pose_time_ns: world_from_camera.map(|_| stillmap_proto::pose_time_ns(capture_time_ns, self.exposure_time_offset_s)),
            features: out.tracked_points as u32,
            masked_features: out.masked_features as u32,
            new_keyframe,
            forgotten_keyframes,
            resume_abandoned: false,
            previous_from_current,
            times: out.times,
        }
    }
}

impl SessionTracker {
    /// A keyframe's current (bundle-adjusted) pose, in the session's world.
    pub fn keyframe_pose(&self, id: u64) -> Option<Isometry3<f64>> {
        let own = id.checked_sub(self.keyframe_id_offset)?;
        self.tracker.map().keyframes.get(&own).map(|k| self.world_from_tracker * k.world_from_camera)
    }

    /// A keyframe as the store keeps it: pose (in the session's world), keypoints, descriptors.
    pub fn keyframe_record(&self, id: u64) -> Option<crate::store::KeyframeRecord> {
        let mut record = self.tracker_record(id)?;
        let p = self.world_from_tracker * crate::fleet::isometry(&record.world_from_camera);
        let (t, q) = (p.translation.vector, p.rotation.coords);
        record.world_from_camera = [t.x, t.y, t.z, q.x, q.y, q.z, q.w];
        Some(record)
    }

    /// A keyframe (the session's id) as the store keeps it, its pose in the tracker's own world.
    fn tracker_record(&self, id: u64) -> Option<crate::store::KeyframeRecord> {
        let k = self.tracker.map().keyframes.get(&id.checked_sub(self.keyframe_id_offset)?)?;
        let (t, q) = (k.world_from_camera.translation.vector, k.world_from_camera.rotation.coords);
        let features = k
            .features
            .features
            .iter()
            .zip(&k.features.descriptors)
            .map(|(f, d)| ([f.raw.x, f.raw.y], f.octave, f.depth.map_or(f32::NAN, |z| z as f32), *d))
            .collect();
        Some(crate::store::KeyframeRecord {
            id,
            timestamp_ns: k.timestamp_ns,
            world_from_camera: [t.x, t.y, t.z, q.x, q.y, q.z, q.w],
            features,
        })
    }
}

/// Proposals of where a resumed session's tracker is that must agree before it is placed.
const RESUME_AGREEING: usize = 2;
/// Two proposals agree within this translation and rotation.
const AGREE_M: f64 = 0.05;
const AGREE_DEG: f64 = 2.0;

/// The largest group of poses agreeing with one of them (itself included).
fn largest_agreeing(poses: &[(Isometry3<f64>, f64)]) -> Vec<(Isometry3<f64>, f64)> {
    let agree = |a: &Isometry3<f64>, b: &Isometry3<f64>| {
        let d = a.inverse() * b;
        d.translation.vector.norm() <= AGREE_M && d.rotation.angle().to_degrees() <= AGREE_DEG
    };
    poses
        .iter()
        .map(|(p, _)| poses.iter().filter(|(q, _)| agree(p, q)).copied().collect::<Vec<_>>())
        .max_by_key(Vec::len)
        .unwrap_or_default()
}

/// The weighted mean of poses: translations averaged, rotations as the normalised
/// weighted sum of their quaternions (each turned to the first one's hemisphere).
fn weighted_mean(poses: &[(Isometry3<f64>, f64)]) -> Option<Isometry3<f64>> {
    let total: f64 = poses.iter().map(|(_, w)| w).sum();
    let (first, _) = poses.first()?;
    if total <= 0.0 {
        return None;
    }
    let reference = first.rotation.coords;
    let (mut t, mut q) = (nalgebra::Vector3::zeros(), nalgebra::Vector4::zeros());
    for (p, w) in poses {
        t += p.translation.vector * (*w / total);
        let c = p.rotation.coords;
        q += if c.dot(&reference) < 0.0 { -c } else { c } * (*w / total);
    }
    let rotation = nalgebra::UnitQuaternion::try_new(nalgebra::Quaternion::from(q), 1e-9)?;
    Some(Isometry3::from_parts(nalgebra::Translation3::from(t), rotation))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Poses averaged by weight: the translation's weighted mean, a rotation between.
    #[test]
    fn the_weighted_mean_of_poses() {
        let a = Isometry3::new(nalgebra::Vector3::new(1.0, 0.0, 0.0), nalgebra::Vector3::new(0.0, 0.0, 0.1));
        let b = Isometry3::new(nalgebra::Vector3::new(2.0, 0.0, 0.0), nalgebra::Vector3::new(0.0, 0.0, 0.2));
        let m = weighted_mean(&[(a, 1.0), (b, 3.0)]).expect("a mean");
        assert!((m.translation.vector.x - 1.75).abs() < 1e-12);
        let angle = m.rotation.angle();
        assert!(angle > 0.17 && angle < 0.18, "{angle}");
        assert!(weighted_mean(&[]).is_none());
        assert!(weighted_mean(&[(a, 0.0)]).is_none());
    }

    /// A resumed session not found in its stored world is given up once its frames
    /// span more than `find_within_s` of capture time, counted from its first frame
    /// here; with no limit, or never resumed, it never is.
    #[test]
    fn a_resumed_session_not_found_in_time_is_given_up() {
        let camera = pb::CameraInfo {
            width: 160,
            height: 120,
            fx: 150.0,
            fy: 150.0,
            cx: 80.0,
            cy: 60.0,
            depth_units_per_metre: 1000.0,
            ..Default::default()
        };
        let color = ColorImage { width: 160, height: 120, data: vec![7; 160 * 120 * 3] };
        let depth = DepthImage { width: 160, height: 120, data: vec![1000; 160 * 120] };
        let tracker = |find_within_s: Option<f64>| {
            let mut t = SessionTracker::new(&camera, &TrackerConfig::default()).expect("tracker");
            if let Some(find_within_s) = find_within_s {
                t.resume_in(ResumeAnchor { keyframes: vec![], verify: Default::default(), next_keyframe_id: 5, find_within_s });
            }
            t
        };
        let abandoned = |t: &mut SessionTracker, sequence: u64, seconds: f64| {
            let out = t.track(sequence, (seconds * 1e9) as u64, &color, &depth, None);
            assert_eq!((out.state, out.world_from_camera), (TrackingState::Lost, None), "nothing reported while not found");
            out.resume_abandoned
        };
        let mut resumed = tracker(Some(2.0));
        assert!(!abandoned(&mut resumed, 1, 100.0), "its first frame here starts the clock");
        assert!(!abandoned(&mut resumed, 2, 102.0), "2 s: still within");
        assert!(abandoned(&mut resumed, 3, 102.1));
        let mut patient = tracker(Some(0.0));
        assert!(!abandoned(&mut patient, 1, 100.0) && !abandoned(&mut patient, 2, 500.0), "0: no limit");
        let mut fresh = tracker(None);
        let out = fresh.track(1, 0, &color, &depth, None);
        let later = fresh.track(2, 400_000_000_000, &color, &depth, None);
        assert!(!out.resume_abandoned && !later.resume_abandoned, "a session never resumed is never given up");
    }

    /// Only poses within 5 cm and 2° of one another agree; a lone outlier is left out.
    #[test]
    fn the_largest_agreeing_group_leaves_an_outlier_out() {
        let at = |x: f64, yaw: f64| (Isometry3::new(nalgebra::Vector3::new(x, 0.0, 0.0), nalgebra::Vector3::new(0.0, 0.0, yaw)), 1.0);
        let group = largest_agreeing(&[at(0.0, 0.0), at(0.02, 0.01), at(0.5, 0.0), at(0.03, 0.0)]);
        assert_eq!(group.len(), 3);
        assert!(group.iter().all(|(p, _)| p.translation.vector.x < 0.1));
        assert_eq!(largest_agreeing(&[at(0.0, 0.0), at(0.5, 0.0)]).len(), 1, "two that disagree: groups of one");
        assert!(largest_agreeing(&[]).is_empty());
    }
}
