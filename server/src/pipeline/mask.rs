//! The mask stage: one session's perception. The first phase (before tracking)
//! takes the segmentation the shared service finished, computes the optical flow
//! and returns the mask tracking must ignore; the second (after tracking) checks
//! the labels against the tracked motion and returns a [`MaskOutcome`].

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use nalgebra::Isometry3;
use stillmap_perception::masker::MaskTimes;
use stillmap_perception::{DynamicMasker, Fused, InstanceState, MaskSource, MaskerInput, PerceptionConfig, PerceptionError, Retraction};
use stillmap_proto::codec::{ColorImage, DepthImage};
use stillmap_proto::pb;

use super::segmentation::{Finished, SegmentationClient, SegmentationService};
use super::stage;
use crate::convert::camera_of;

/// What the mask stage made of one frame.
#[derive(Debug, Clone)]
pub struct MaskOutcome {
    /// Where the frame's segmentation came from (and how old it is).
    pub source: MaskSource,
    /// Fraction of valid-depth pixels marked dynamic or prior-dynamic.
    pub dynamic_fraction: f32,
    /// Keypoints dropped before tracking because they fell in the mask.
    pub dynamic_features: u32,
    pub instances: Vec<InstanceState>,
    pub times: MaskTimes,
    /// Inference time of the segmentation that arrived with this frame.
    pub segmentation_time: Option<Duration>,
}

impl MaskOutcome {
    /// `/metrics` label of the mask source.
    pub fn label(&self) -> &'static str {
        match self.source {
            MaskSource::None => "none",
            MaskSource::Fresh => "fresh",
            MaskSource::Warped { .. } => "warped",
        }
    }

    /// The stage times in the order results report them.
    pub fn stages(&self) -> Vec<(&'static str, Duration)> {
        let t = &self.times;
        let mut stages = vec![
            (stage::PERCEPTION_FLOW, t.flow),
            (stage::PERCEPTION_WARP, t.warp),
            (stage::PERCEPTION_EGO_MOTION, t.ego_motion),
            (stage::PERCEPTION_FUSION, t.fusion),
        ];
        if let Some(d) = self.segmentation_time {
            stages.push((stage::SEGMENTATION, d));
        }
        stages
    }
}

/// One session's perception state.
pub struct SessionPerception {
    masker: DynamicMasker,
    segmentation: Option<SegmentationClient>,
    policy_mask: Option<Vec<u8>>,
    segmentation_time: Option<Duration>,
    /// The last finished frame's fused mask.
    fused: Option<Fused>,
    /// The last finished frame's keyframe cells showing moving things (for the map).
    retractions: Vec<Retraction>,
    /// Deterministic mode: (every, delay), the frames seen, and results held back
    /// until their release frame.
    deterministic: Option<(u32, u32)>,
    frames: u64,
    held: VecDeque<(u64, Finished)>,
}

impl SessionPerception {
    pub fn new(
        camera: &pb::CameraInfo,
        config: &PerceptionConfig,
        service: Option<&Arc<SegmentationService>>,
    ) -> Result<Self, PerceptionError> {
        let names = service.map(|s| s.class_names().to_vec()).unwrap_or_default();
        let masker = DynamicMasker::new(camera_of(camera), config.clone(), &names)?;
        let seg = &config.segmentation;
        let deterministic =
            (seg.deterministic_every_frames > 0).then_some((seg.deterministic_every_frames, seg.deterministic_delay_frames));
        Ok(Self {
            masker,
            segmentation: service.map(|s| s.client()),
            policy_mask: None,
            segmentation_time: None,
            fused: None,
            retractions: Vec::new(),
            deterministic,
            frames: 0,
            held: VecDeque::new(),
        })
    }

    /// First phase: returns the mask tracking must use for this frame (`accel`: the
    /// frame's accelerometer in the camera frame, when the robot sends one).
    pub fn prepare(
        &mut self,
        sequence: u64,
        capture_time_ns: u64,
        color: &ColorImage,
        depth: &DepthImage,
        accel: Option<nalgebra::Vector3<f64>>,
    ) -> Option<&[u8]> {
        self.fused = None;
        let index = self.frames;
        self.frames += 1;
        let finished = match (&self.segmentation, self.deterministic) {
            (Some(client), Some((every, delay))) => {
                if index.is_multiple_of(u64::from(every))
                    && let Some(f) = client.segment_now(sequence, color)
                {
                    self.held.push_back((index + u64::from(delay), f));
                }
                match self.held.front() {
                    Some((release, _)) if *release <= index => self.held.pop_front().map(|(_, f)| f),
                    _ => None,
                }
            }
            (Some(client), None) => {
                let finished = client.take();
                client.submit(sequence, color);
                finished
            }
            (None, _) => None,
        };
        self.segmentation_time = finished.as_ref().map(|f| f.2);
        let input = MaskerInput {
            sequence,
            capture_time_ns,
            rgb: &color.data,
            depth: &depth.data,
            segmentation: finished.map(|(k, seg, _)| (k, seg)),
            motion_prior: None,
            accel_in_camera: accel,
        };
        match self.masker.prepare(input) {
            Ok(mask) => {
                self.policy_mask = Some(mask);
                self.policy_mask.as_deref()
            }
            Err(e) => {
                tracing::warn!(sequence, "perception failed: {e}");
                self.policy_mask = None;
                None
            }
        }
    }

    /// Second phase, after tracking: fuses with the tracked motion.
    pub fn finish(
        &mut self,
        sequence: u64,
        depth: &DepthImage,
        previous_from_current: Option<Isometry3<f64>>,
        dynamic_features: u32,
    ) -> Option<MaskOutcome> {
        self.policy_mask.take()?;
        let out = match self.masker.finish(&depth.data, previous_from_current) {
            Ok(out) => out,
            Err(e) => {
                tracing::warn!(sequence, "perception failed: {e}");
                return None;
            }
        };
        let outcome = MaskOutcome {
            source: out.source,
            dynamic_fraction: out.dynamic_fraction,
            dynamic_features,
            instances: out.fused.instances.clone(),
            times: out.times,
            segmentation_time: self.segmentation_time.take(),
        };
        self.fused = Some(out.fused);
        self.retractions = out.retractions;
        Some(outcome)
    }

    /// What the last finished frame found moving in recent keyframes (taken once).
    pub fn take_retractions(&mut self) -> Vec<Retraction> {
        std::mem::take(&mut self.retractions)
    }

    /// The last finished frame became keyframe `id`: perception follows its pixels.
    pub fn note_keyframe(&mut self, id: u64) {
        self.masker.note_keyframe(id);
    }

    /// Pixels of the last finished frame (of depth `depth`) that must stay out of
    /// the map (nonzero): dynamic and prior-dynamic, grown over their surfaces and
    /// dilated (`DynamicMasker::mapping_mask`). `None` when perception failed on it.
    pub fn map_exclusion(&self, depth: &DepthImage) -> Option<Vec<u8>> {
        let fused = self.fused.as_ref()?;
        self.masker
            .mapping_mask(fused, &depth.data)
            .map_err(|e| tracing::warn!("mapping mask failed, the keyframe's labels are used as they are: {e}"))
            .ok()
            .or_else(|| Some(fused.mapping_mask()))
    }

    /// The segmentation class per pixel in the current frame (fresh or warped), if any.
    pub fn class_map(&self) -> Option<Vec<u16>> {
        self.fused.as_ref()?;
        self.masker.segmentation().map(|s| s.class_map())
    }
}
