//! The per-frame pipeline of a session, free of network and file I/O.
//!
//! [`SessionPipeline::process`] runs one queued frame through the stages, each
//! passing a typed result to the next:
//!
//! 1. [`decode`]: order check and image decoding → [`decode::Decoded`] or a rejection;
//! 2. [`mask`] (first phase): segmentation from the shared [`segmentation`]
//!    service, optical flow, the mask tracking must ignore;
//! 3. [`track`]: the camera pose without the masked pixels → [`track::TrackOutcome`];
//! 4. [`mask`] (second phase): the labels checked against the tracked motion →
//!    [`mask::MaskOutcome`];
//! 5. [`fuse`]: what the map must do for this frame (a new keyframe, keyframes
//!    bundle adjustment moved) becomes a [`fuse::MapJob`] for the session's map
//!    lane, which runs off this path.
//!
//! The [`FrameOutcome`] carries all of it; the wire's `FrameResult` is built from it
//! once, in [`crate::convert`].

pub mod decode;
pub mod fuse;
pub mod mask;
pub mod segmentation;
pub mod track;

use std::sync::Arc;
use std::time::{Duration, Instant};

use nalgebra::Vector3;
use stillmap_perception::PerceptionConfig;
use stillmap_proto::pb;
use stillmap_tracking::TrackerConfig;

use crate::queue::QueuedFrame;
use decode::{Decoder, Rejection};
use fuse::{Handoff, MapJob};
use mask::{MaskOutcome, SessionPerception};
use segmentation::SegmentationService;
use track::{SessionTracker, TrackOutcome};

/// Names of the pipeline stages, as they appear in results and `/metrics`.
pub mod stage {
    pub const QUEUE: &str = "queue";
    pub const DECODE_COLOR: &str = "decode_color";
    pub const DECODE_DEPTH: &str = "decode_depth";
    pub const TRACK_EXTRACT: &str = "track_extract";
    pub const TRACK_MATCH: &str = "track_match";
    pub const TRACK_OPTIMIZE: &str = "track_optimize";
    pub const TRACK_LOCAL_BA: &str = "track_local_ba";
    /// Dense odometry, on its own thread beside extraction.
    pub const TRACK_DENSE: &str = "track_dense";
    pub const TRACK: &str = "track";
    pub const PERCEPTION_FLOW: &str = "perception_flow";
    pub const PERCEPTION_WARP: &str = "perception_warp";
    pub const PERCEPTION_EGO_MOTION: &str = "perception_ego_motion";
    pub const PERCEPTION_FUSION: &str = "perception_fusion";
    /// Inference time of the segmentation the frame used (on the worker; its share
    /// of the batch it ran in), when it arrived with this frame.
    pub const SEGMENTATION: &str = "segmentation";
    /// Map fusion of a keyframe (map pool, `/metrics` only).
    pub const MAP_FUSE: &str = "map_fuse";
    /// The keyframe's store commit (map pool, `/metrics` only).
    pub const STORE_COMMIT: &str = "store_commit";
    /// Everything on the tracking path except the queue.
    pub const TOTAL: &str = "total";
}

/// Microseconds, saturating (stage times on the wire).
pub(crate) fn micros(d: Duration) -> u32 {
    u32::try_from(d.as_micros()).unwrap_or(u32::MAX)
}

/// What happened to one frame on the tracking path.
pub struct FrameOutcome {
    pub sequence: u64,
    pub capture_time_ns: u64,
    /// Why the frame was not used (`None`: processed).
    pub rejection: Option<Rejection>,
    /// CRC-32 of the decoded depth (0 when not decoded).
    pub depth_crc32: u32,
    /// The tracking stage's result (`None`: rejected, or tracking unavailable).
    pub track: Option<TrackOutcome>,
    /// The second mask phase's result (`None`: perception off or failed).
    pub mask: Option<MaskOutcome>,
    /// Stage times in the order they are reported, `total` excluded.
    pub stages: Vec<(&'static str, Duration)>,
    /// Time on the tracking path (the `total` stage).
    pub total: Duration,
    /// Work for the session's map lane.
    pub map_job: Option<MapJob>,
}

/// One session's pipeline state, carried from frame to frame.
pub struct SessionPipeline {
    decoder: Decoder,
    tracker: Option<SessionTracker>,
    perception: Option<SessionPerception>,
    handoff: Option<Handoff>,
}

impl SessionPipeline {
    /// `camera` must have passed [`decode::validate_camera`]. A stage that cannot
    /// start for this camera is logged and left out (the frames are still answered).
    pub fn new(
        session_id: &str,
        camera: &pb::CameraInfo,
        tracking: &TrackerConfig,
        perception: Option<&(PerceptionConfig, Option<Arc<SegmentationService>>)>,
        map_refuse_window: Option<usize>,
        order: decode::OrderWindow,
    ) -> Self {
        let tracker = SessionTracker::new(camera, tracking)
            .map_err(|e| tracing::error!(session = %session_id, "tracking unavailable for this session: {e}"))
            .ok();
        let perception = perception.and_then(|(config, service)| {
            SessionPerception::new(camera, config, service.as_ref())
                .map_err(|e| tracing::error!(session = %session_id, "perception unavailable for this session: {e}"))
                .ok()
        });
        Self { decoder: Decoder::new(camera.clone(), order), tracker, perception, handoff: map_refuse_window.map(Handoff::new) }
    }

    /// A session resumed from the shared storage: its tracker reports nothing until
    /// it finds itself among the session's stored keyframes.
    pub fn resume_in(&mut self, anchor: track::ResumeAnchor) {
        if let Some(t) = self.tracker.as_mut() {
            t.resume_in(anchor);
        }
    }

    /// Runs one frame through the stages.
    pub fn process(&mut self, queued: &QueuedFrame) -> FrameOutcome {
        let frame = &queued.frame;
        let mut outcome = FrameOutcome {
            sequence: frame.sequence,
            capture_time_ns: frame.capture_time_ns,
            rejection: None,
            depth_crc32: 0,
            track: None,
            mask: None,
            stages: vec![(stage::QUEUE, queued.received_at.elapsed())],
            total: Duration::ZERO,
            map_job: None,
        };
        let start = Instant::now();
        let decoded = match self.decoder.decode(frame) {
            Ok(d) => d,
            Err(rejection) => {
                outcome.rejection = Some(rejection);
                return outcome;
            }
        };
        outcome.depth_crc32 = decoded.depth_crc32;
        outcome.stages.extend([(stage::DECODE_COLOR, decoded.color_time), (stage::DECODE_DEPTH, decoded.depth_time)]);
        outcome.total = start.elapsed();
        let Some(tracker) = self.tracker.as_mut() else { return outcome };
        let (color, depth) = (&decoded.color, &decoded.depth);
        let accel = frame.accel_in_camera.map(|a| Vector3::new(a.x, a.y, a.z));
        let mask = self.perception.as_mut().and_then(|p| p.prepare(frame.sequence, frame.capture_time_ns, color, depth, accel));
        let track = tracker.track(frame.sequence, frame.capture_time_ns, color, depth, mask);
        outcome.stages.extend(track.stages());
        outcome.total += track.times.total;
        if let Some(p) = self.perception.as_mut()
            && let Some(mask) = p.finish(frame.sequence, depth, track.previous_from_current, track.masked_features)
        {
            outcome.stages.extend(mask.stages());
            outcome.total += mask.times.total;
            outcome.mask = Some(mask);
        }
        if let (Some(handoff), Some(pose)) = (self.handoff.as_mut(), track.world_from_camera) {
            // The decoded images are not needed after this: a keyframe takes them.
            let retractions = self.perception.as_mut().map(SessionPerception::take_retractions).unwrap_or_default();
            let keyframe = track.new_keyframe.map(|id| {
                let exclude = self.perception.as_mut().and_then(|p| {
                    p.note_keyframe(id);
                    p.map_exclusion(&decoded.depth)
                });
                fuse::KeyframeJob {
                    id,
                    capture_time_ns: frame.capture_time_ns,
                    color: decoded.color,
                    depth: decoded.depth,
                    exclude,
                    classes: self.perception.as_ref().and_then(SessionPerception::class_map),
                    record: tracker.keyframe_record(id),
                }
            });
            outcome.map_job = handoff.job(pose, accel, keyframe, retractions, |id| tracker.keyframe_pose(id));
        }
        outcome.track = Some(track);
        outcome
    }

    /// The map lane could not take `job` (full): its keyframe is not in the map, so
    /// the handoff forgets it (and the poses it would have sent).
    pub fn map_job_refused(&mut self, job: &MapJob) {
        if let Some(h) = self.handoff.as_mut() {
            h.refused(job);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stillmap_proto::codec::{self, DepthImage};
    use stillmap_proto::pb::{ColorEncoding, DepthEncoding};

    fn camera() -> pb::CameraInfo {
        pb::CameraInfo {
            width: W,
            height: H,
            fx: 150.0,
            fy: 150.0,
            cx: 80.0,
            cy: 60.0,
            depth_units_per_metre: 1000.0,
            color_encoding: ColorEncoding::Rgb8 as i32,
            depth_encoding: DepthEncoding::Rvl as i32,
            ..Default::default()
        }
    }

    const W: u32 = 160;
    const H: u32 = 120;

    fn depth() -> DepthImage {
        DepthImage { width: W, height: H, data: (0..W * H).map(|i| 1000 + (i % 7) as u16).collect() }
    }

    fn queued(sequence: u64) -> QueuedFrame {
        let depth = depth();
        let frame = pb::Frame {
            sequence,
            capture_time_ns: sequence * 100,
            color: vec![7; (W * H * 3) as usize].into(),
            depth: codec::encode_depth(DepthEncoding::Rvl, &depth).expect("encode").into(),
            accel_in_camera: None,
        };
        QueuedFrame { frame, received_at: Instant::now() }
    }

    /// The stages run in order and report their times in order; the result is
    /// built once from the outcome.
    #[test]
    fn a_frame_passes_the_stages_in_order() {
        let mut p = SessionPipeline::new("s", &camera(), &TrackerConfig::default(), None, Some(12), decode::OrderWindow::default());
        let out = p.process(&queued(1));
        assert!(out.rejection.is_none());
        let names: Vec<&str> = out.stages.iter().map(|s| s.0).collect();
        assert_eq!(&names[..3], [stage::QUEUE, stage::DECODE_COLOR, stage::DECODE_DEPTH]);
        assert_eq!(names.last(), Some(&stage::TRACK));
        let track = out.track.as_ref().expect("tracked");
        assert!(track.world_from_camera.is_none(), "a uniform image has no features to start from");
        let result = pb::FrameResult::from(&out);
        let wire: Vec<&str> = result.latency.iter().map(|l| l.stage.as_str()).collect();
        assert_eq!(wire.last(), Some(&stage::TOTAL));
        assert_eq!(result.status(), pb::FrameStatus::Ok);
        assert_eq!(result.depth_crc32, depth().crc32());
        // A frame out of order is rejected and the pipeline goes on.
        let back = p.process(&queued(1));
        assert!(back.rejection.is_some());
        assert_eq!(pb::FrameResult::from(&back).status(), pb::FrameStatus::Rejected);
        assert!(p.process(&queued(2)).rejection.is_none());
    }
}
