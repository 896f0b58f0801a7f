//! Conversions between the wire types (`stillmap_proto::pb`) and the pipeline's
//! own: the camera model from a hello, poses, tracking states, and the frame
//! result built once from a [`FrameOutcome`].

use nalgebra::Isometry3;
use stillmap_perception::{InstanceState, MaskSource};
use stillmap_proto::pb::{self, FrameStatus, TrackingState};
use stillmap_tracking::Camera;

use crate::pipeline::{FrameOutcome, micros, stage};

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

/// A protobuf pose as an isometry (missing parts: identity).
pub fn isometry_of(pose: &pb::Pose) -> Isometry3<f64> {
    let (t, q) = (pose.translation.unwrap_or_default(), pose.rotation.unwrap_or_default());
    let rotation = nalgebra::UnitQuaternion::try_new(nalgebra::Quaternion::new(q.w, q.x, q.y, q.z), 1e-12)
        .unwrap_or_else(nalgebra::UnitQuaternion::identity);
    Isometry3::from_parts(nalgebra::Translation3::new(t.x, t.y, t.z), rotation)
}

/// `p` with its pose moved by `target_from_world` (a session's pose in its fleet's frame, say).
pub fn pose_in(p: &pb::PoseStamped, target_from_world: &Isometry3<f64>) -> pb::PoseStamped {
    let world_from_camera = p.world_from_camera.map(|w| pose_of(&(target_from_world * isometry_of(&w))));
    pb::PoseStamped { world_from_camera, ..*p }
}

pub fn state_of(s: stillmap_tracking::TrackingState) -> TrackingState {
    match s {
        stillmap_tracking::TrackingState::Initializing => TrackingState::Initializing,
        stillmap_tracking::TrackingState::Tracking => TrackingState::Tracking,
        stillmap_tracking::TrackingState::Lost => TrackingState::Lost,
        stillmap_tracking::TrackingState::Relocalized => TrackingState::Relocalized,
        stillmap_tracking::TrackingState::Coasting => TrackingState::Coasting,
    }
}

/// An instance as the mask stage judged it, as the result reports it.
pub fn instance_of(i: &InstanceState) -> pb::DetectedInstance {
    pb::DetectedInstance {
        class_id: u32::from(i.class_id),
        class_name: i.class_name.clone(),
        score: i.score,
        prior_dynamic: i.prior_dynamic,
        moving: i.moving == Some(true),
        pixels: i.pixels,
        bbox: i.bbox.to_vec(),
    }
}

impl From<&FrameOutcome> for pb::FrameResult {
    /// The frame's result on the wire: status, pose, counts, instances and every
    /// stage's time, `total` last.
    fn from(o: &FrameOutcome) -> Self {
        let mut latency: Vec<pb::StageLatency> =
            o.stages.iter().map(|(name, d)| pb::StageLatency { stage: (*name).into(), micros: micros(*d) }).collect();
        let mut result = pb::FrameResult {
            sequence: o.sequence,
            capture_time_ns: o.capture_time_ns,
            tracking_state: TrackingState::Initializing as i32,
            depth_crc32: o.depth_crc32,
            ..Default::default()
        };
        if let Some(r) = &o.rejection {
            result.status = FrameStatus::Rejected as i32;
            result.error = Some(pb::RpcStatus { code: r.code as i32, message: r.message.clone(), ..Default::default() });
            result.latency = latency;
            return result;
        }
        result.status = FrameStatus::Ok as i32;
        let mut counts = pb::FrameCounts { mask_source: pb::MaskSource::None as i32, ..Default::default() };
        if let Some(t) = &o.track {
            result.tracking_state = t.state as i32;
            result.world_from_camera = t.world_from_camera.as_ref().map(pose_of);
            result.pose_time_ns = t.pose_time_ns;
            counts.features = t.features;
        }
        if let Some(m) = &o.mask {
            let (source, age) = match m.source {
                MaskSource::None => (pb::MaskSource::None, 0),
                MaskSource::Fresh => (pb::MaskSource::Fresh, 0),
                MaskSource::Warped { age_frames } => (pb::MaskSource::Warped, age_frames),
            };
            counts.mask_source = source as i32;
            counts.mask_age_frames = age;
            counts.dynamic_fraction = m.dynamic_fraction;
            counts.dynamic_features = m.dynamic_features;
            result.instances = m.instances.iter().map(instance_of).collect();
        }
        result.counts = Some(counts);
        latency.push(pb::StageLatency { stage: stage::TOTAL.into(), micros: micros(o.total) });
        result.latency = latency;
        result
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn camera_and_pose_conversions() {
        let info = stillmap_dataset::calibration::KnownCamera::TumFr1.camera_info();
        let cam = camera_of(&info);
        assert_eq!(cam.distortion, Some([0.2624, -0.9531, -0.0054, 0.0026, 1.1633]));
        assert_eq!((cam.fx, cam.cy, cam.depth_units_per_metre), (517.3, 255.3, 5000.0));
        let q = UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3);
        let p = pose_of(&Isometry3::from_parts(Translation3::new(1.0, 2.0, 3.0), q));
        let r = p.rotation.expect("rotation");
        assert_eq!(p.translation.expect("translation"), pb::Vector3 { x: 1.0, y: 2.0, z: 3.0 });
        assert_eq!([r.x, r.y, r.z, r.w], [q.i, q.j, q.k, q.w]);
    }
}
