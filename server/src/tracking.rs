//! The tracking stage of a session's pipeline: adapts decoded frames to
//! [`stillmap_tracking::Tracker`] and its output to the frame result.


use nalgebra::Isometry3;
use stillmap_proto::codec::{ColorImage, DepthImage};
use stillmap_proto::pb::{self, TrackingState};
use stillmap_tracking::{Camera, FrameInput, Tracker, TrackerConfig, TrackingError};

use crate::pipeline::append_stages;

/// Stage names of tracking, as they appear in results and `/metrics`.
pub mod tracking_stage {
    pub const EXTRACT: &str = "track_extract";
    pub const MATCH: &str = "track_match";
    pub const OPTIMIZE: &str = "track_optimize";
    pub const LOCAL_BA: &str = "track_local_ba";
    /// Dense odometry, on its own thread beside extraction.
    pub const DENSE: &str = "track_dense";
    pub const TRACK: &str = "track";
}

/// The session's camera model from its hello (validated by `validate_camera`).
pub fn camera_of(info: &pb::CameraInfo) -> Camera {
    let distortion = match pb::DistortionModel::try_from(info.distortion_model) {
        Ok(pb::DistortionModel::PlumbBob) => <[f64; 5]>::try_from(info.distortion_coeffs.as_slice()).ok(),
        _ => None,
    };
    Camera {
        width: info.width,
        height: info.height,
        fx: info.fx,
        fy: info.fy,
        cx: info.cx,
        cy: info.cy,
        distortion,
        depth_units_per_metre: info.depth_units_per_metre,
        readout_s: info.rolling_shutter_readout_s,
    }
}

/// `world_from_camera` as a protobuf pose.
pub fn pose_of(world_from_camera: &Isometry3<f64>) -> pb::Pose {
    let t = world_from_camera.translation.vector;
    let q = world_from_camera.rotation.coords; // (i, j, k, w)
    pb::Pose::from_parts([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])
}

fn state_of(s: stillmap_tracking::TrackingState) -> TrackingState {
    match s {
        stillmap_tracking::TrackingState::Initializing => TrackingState::Initializing,
        stillmap_tracking::TrackingState::Tracking => TrackingState::Tracking,
        stillmap_tracking::TrackingState::Lost => TrackingState::Lost,
        stillmap_tracking::TrackingState::Relocalized => TrackingState::Relocalized,
    }
}


/// One session's tracker.
pub struct SessionTracker {
    tracker: Tracker,
    /// The last frame's pose and the one before (for the camera motion perception needs).
    last_pose: Option<Isometry3<f64>>,
    previous_pose: Option<Isometry3<f64>>,
    masked_features: usize,
    /// The keyframe the last frame became, if it did.
    new_keyframe: Option<u64>,
    /// `CameraInfo.exposure_time_offset_s`: from a frame's timestamp to its pose's time.
    exposure_time_offset_s: f64,
}

impl SessionTracker {
    pub fn new(camera: &pb::CameraInfo, config: &TrackerConfig) -> Result<Self, TrackingError> {
        Ok(Self {
            tracker: Tracker::new(camera_of(camera), config.clone())?,
            last_pose: None,
            previous_pose: None,
            masked_features: 0,
            new_keyframe: None,
            exposure_time_offset_s: camera.exposure_time_offset_s,
        })
    }

    /// Tracks a decoded frame and writes state, pose (with the time it refers to),
    /// counts and stage times into `result`. Returns the pose when there is one. A tracking error (which only
    /// malformed input can cause) leaves the frame `LOST` without a pose.
    pub fn track(
        &mut self,
        result: &mut pb::FrameResult,
        color: &ColorImage,
        depth: &DepthImage,
        dynamic_mask: Option<&[u8]>,
    ) -> Option<pb::Pose> {
        let input = FrameInput { timestamp_ns: result.capture_time_ns, rgb: &color.data, depth: &depth.data, dynamic_mask };
        self.previous_pose = self.last_pose.take();
        self.masked_features = 0;
        self.new_keyframe = None;
        let out = match self.tracker.track(&input) {
            Ok(out) => out,
            Err(e) => {
                tracing::warn!(sequence = result.sequence, "tracking failed: {e}");
                result.tracking_state = TrackingState::Lost as i32;
                return None;
            }
        };
        self.last_pose = out.world_from_camera;
        self.masked_features = out.masked_features;
        if out.keyframe {
            // Keyframe ids only grow: the newest is the one just made.
            self.new_keyframe = self.tracker.map().keyframes.keys().next_back().copied();
        }
        result.tracking_state = state_of(out.state) as i32;
        let pose = out.world_from_camera.as_ref().map(pose_of);
        result.world_from_camera = pose;
        if pose.is_some() {
            result.pose_time_ns = Some(stillmap_proto::pose_time_ns(result.capture_time_ns, self.exposure_time_offset_s));
        }
        let counts = result.counts.get_or_insert_with(pb::FrameCounts::default);
        counts.features = out.tracked_points as u32;
        let t = out.times;
        let stages = [
            (tracking_stage::EXTRACT, t.extraction),
            (tracking_stage::DENSE, t.dense),
            (tracking_stage::MATCH, t.matching),
            (tracking_stage::OPTIMIZE, t.optimization),
            (tracking_stage::LOCAL_BA, t.local_ba),
            (tracking_stage::TRACK, t.total),
        ];
        append_stages(result, &stages, t.total);
        pose
    }
}

impl SessionTracker {
    /// `previous_from_current` between the last two frames, when both were tracked.
    pub fn last_motion(&self) -> Option<Isometry3<f64>> {
        Some(self.previous_pose?.inverse() * self.last_pose?)
    }

    /// The last frame's pose, when it was tracked.
    pub fn last_pose(&self) -> Option<Isometry3<f64>> {
        self.last_pose
    }

    /// The keyframe the last frame became, if it did.
    pub fn new_keyframe(&self) -> Option<u64> {
        self.new_keyframe
    }

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
        Some(crate::store::KeyframeRecord { id, timestamp_ns: k.timestamp_ns, world_from_camera: [t.x, t.y, t.z, q.x, q.y, q.z, q.w], features })
    }

    /// Keypoints the dynamic mask removed on the last frame.
    pub fn masked_features(&self) -> usize {
        self.masked_features
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn camera_and_pose_conversions() {
        let info = pb::CameraInfo {
            width: 640,
            height: 480,
            fx: 517.3,
            fy: 516.5,
            cx: 318.6,
            cy: 255.3,
            distortion_model: pb::DistortionModel::PlumbBob as i32,
            distortion_coeffs: vec![0.2624, -0.9531, -0.0054, 0.0026, 1.1633],
            depth_units_per_metre: 5000.0,
            ..Default::default()
        };
        let cam = camera_of(&info);
        assert_eq!(cam.distortion, Some([0.2624, -0.9531, -0.0054, 0.0026, 1.1633]));
        assert_eq!((cam.fx, cam.cy, cam.depth_units_per_metre), (517.3, 255.3, 5000.0));
        let q = UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3);
        let p = pose_of(&Isometry3::from_parts(Translation3::new(1.0, 2.0, 3.0), q));
        let r = p.rotation.unwrap();
        assert_eq!(p.translation.unwrap(), pb::Vector3 { x: 1.0, y: 2.0, z: 3.0 });
        assert_eq!([r.x, r.y, r.z, r.w], [q.i, q.j, q.k, q.w]);
    }
}
