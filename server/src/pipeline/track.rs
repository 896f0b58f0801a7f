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

/// One session's tracker.
pub struct SessionTracker {
    tracker: Tracker,
    /// The last frame's pose (for the camera motion perception needs).
    last_pose: Option<Isometry3<f64>>,
    /// `CameraInfo.exposure_time_offset_s`: from a frame's timestamp to its pose's time.
    exposure_time_offset_s: f64,
}

impl SessionTracker {
    pub fn new(camera: &pb::CameraInfo, config: &TrackerConfig) -> Result<Self, TrackingError> {
        Ok(Self {
            tracker: Tracker::new(camera_of(camera), config.clone())?,
            last_pose: None,
            exposure_time_offset_s: camera.exposure_time_offset_s,
        })
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
                    previous_from_current: None,
                    times: StageTimes::default(),
                };
            }
        };
        self.last_pose = out.world_from_camera;
        // Keyframe ids only grow: the newest is the one just made.
        let new_keyframe = if out.keyframe { self.tracker.map().keyframes.keys().next_back().copied() } else { None };
        TrackOutcome {
            state: state_of(out.state),
            world_from_camera: out.world_from_camera,
            pose_time_ns: out.world_from_camera.map(|_| stillmap_proto::pose_time_ns(capture_time_ns, self.exposure_time_offset_s)),
            features: out.tracked_points as u32,
            masked_features: out.masked_features as u32,
            new_keyframe,
            previous_from_current: previous_pose.zip(out.world_from_camera).map(|(previous, now)| previous.inverse() * now),
            times: out.times,
        }
    }
}

impl SessionTracker {
    /// A keyframe's current (bundle-adjusted) pose.
    pub fn keyframe_pose(&self, id: u64) -> Option<Isometry3<f64>> {
        self.tracker.map().keyframes.get(&id).map(|k| k.world_from_camera)
    }

    /// A keyframe as the store keeps it: pose, keypoints, descriptors.
    pub fn keyframe_record(&self, id: u64) -> Option<crate::store::KeyframeRecord> {
        let k = self.tracker.map().keyframes.get(&id)?;
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
