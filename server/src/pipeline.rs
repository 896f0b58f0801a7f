//! Per-frame processing, free of network and file I/O.
//!
//! [`FramePipeline::process`] checks a frame against the session's order and
//! camera, decodes both images and returns the frame's result (state
//! `TRACKING_STATE_INITIALIZING`, no pose). The session worker then hands the
//! decoded images to the tracking stage (`tracking.rs`), which sets the state,
//! the pose and the tracking stage times.

use std::time::{Duration, Instant};

use stillmap_proto::{MAX_EXPOSURE_TIME_OFFSET_S, MAX_ROLLING_SHUTTER_READOUT_S};
use stillmap_proto::codec::{self, ColorImage, DepthImage};
use stillmap_proto::pb::{self, ColorEncoding, DepthEncoding, FrameStatus, TrackingState};
use tonic::Code;

/// Names of the pipeline stages, as they appear in results and `/metrics`.
pub mod stage {
    pub const QUEUE: &str = "queue";
    pub const DECODE_COLOR: &str = "decode_color";
    pub const DECODE_DEPTH: &str = "decode_depth";
    pub const TOTAL: &str = "total";
}

/// Why a frame was rejected, as a metrics label.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RejectReason {
    Order,
    Color,
    Depth,
}

impl RejectReason {
    pub fn label(self) -> &'static str {
        match self {
            Self::Order => "order",
            Self::Color => "color",
            Self::Depth => "depth",
        }
    }
}

/// A processed frame: its result plus the decoded images for later stages.
pub struct Processed {
    pub result: pb::FrameResult,
    pub images: Option<(ColorImage, DepthImage)>,
    pub rejected: Option<RejectReason>,
}

/// The state a session's pipeline carries from frame to frame.
pub struct FramePipeline {
    camera: pb::CameraInfo,
    color_encoding: ColorEncoding,
    depth_encoding: DepthEncoding,
    last_sequence: Option<u64>,
    last_capture_time_ns: Option<u64>,
}

pub(crate) fn micros(d: Duration) -> u32 {
    u32::try_from(d.as_micros()).unwrap_or(u32::MAX)
}

/// Appends a later stage's times to a result, keeping `total` last and adding
/// `spent` (that stage's own time) to it.
pub(crate) fn append_stages(result: &mut pb::FrameResult, stages: &[(&str, Duration)], spent: Duration) {
    let total = result.latency.iter().position(|l| l.stage == stage::TOTAL).map(|i| result.latency.remove(i));
    for (name, d) in stages {
        result.latency.push(pb::StageLatency { stage: (*name).into(), micros: micros(*d) });
    }
    if let Some(mut e) = total {
        e.micros = e.micros.saturating_add(micros(spent));
        result.latency.push(e);
    }
}

impl FramePipeline {
    /// `camera` must have passed [`validate_camera`].
    pub fn new(camera: pb::CameraInfo) -> Self {
        Self {
            color_encoding: camera.color_encoding(),
            depth_encoding: camera.depth_encoding(),
            camera,
            last_sequence: None,
            last_capture_time_ns: None,
        }
    }

    /// Processes one frame that waited `queued_for` in the session queue.
    pub fn process(&mut self, frame: &pb::Frame, queued_for: Duration) -> Processed {
        let start = Instant::now();
        let mut result = pb::FrameResult {
            sequence: frame.sequence,
            capture_time_ns: frame.capture_time_ns,
            tracking_state: TrackingState::Initializing as i32,
            latency: vec![pb::StageLatency { stage: stage::QUEUE.into(), micros: micros(queued_for) }],
            ..Default::default()
        };
        let reject = |mut result: pb::FrameResult, reason, code: Code, message: String| {
            result.status = FrameStatus::Rejected as i32;
            result.error = Some(pb::RpcStatus { code: code as i32, message });
            Processed { result, images: None, rejected: Some(reason) }
        };

        if let Some(last) = self.last_sequence
            && frame.sequence <= last
        {
            let msg = format!("frame sequence {} is not after the previous frame's {last}", frame.sequence);
            return reject(result, RejectReason::Order, Code::InvalidArgument, msg);
        }
        if let Some(last) = self.last_capture_time_ns
            && frame.capture_time_ns <= last
        {
            let msg = format!(
                "capture timestamp went backwards: frame {} at {} ns is not after the previous frame's {last} ns",
                frame.sequence, frame.capture_time_ns
            );
            return reject(result, RejectReason::Order, Code::InvalidArgument, msg);
        }
        self.last_sequence = Some(frame.sequence);
        self.last_capture_time_ns = Some(frame.capture_time_ns);

        let (w, h) = (self.camera.width, self.camera.height);
        let t = Instant::now();
        let color = match codec::decode_color(self.color_encoding, &frame.color, w, h) {
            Ok(c) => c,
            Err(e) => return reject(result, RejectReason::Color, Code::InvalidArgument, format!("frame {}: {e}", frame.sequence)),
        };
        result.latency.push(pb::StageLatency { stage: stage::DECODE_COLOR.into(), micros: micros(t.elapsed()) });
        let t = Instant::now();
        let depth = match codec::decode_depth(self.depth_encoding, &frame.depth, w, h) {
            Ok(d) => d,
            Err(e) => return reject(result, RejectReason::Depth, Code::InvalidArgument, format!("frame {}: {e}", frame.sequence)),
        };
        result.depth_crc32 = depth.crc32();
        result.latency.push(pb::StageLatency { stage: stage::DECODE_DEPTH.into(), micros: micros(t.elapsed()) });

        result.counts = Some(pb::FrameCounts { mask_source: pb::MaskSource::None as i32, ..Default::default() });
        result.status = FrameStatus::Ok as i32;
        result.latency.push(pb::StageLatency { stage: stage::TOTAL.into(), micros: micros(start.elapsed()) });
        Processed { result, images: Some((color, depth)), rejected: None }
    }
}

/// Longest `CameraInfo.calibration_source` the server accepts.
pub const MAX_CALIBRATION_SOURCE_BYTES: usize = 512;

/// Largest image side the server accepts in a hello.
pub const MAX_IMAGE_SIDE: u32 = 8192;

/// Checks a hello's camera; the message names the first problem.
pub fn validate_camera(camera: Option<&pb::CameraInfo>) -> Result<&pb::CameraInfo, String> {
    let c = camera.ok_or("hello has no camera info")?;
    if c.width == 0 || c.height == 0 || c.width > MAX_IMAGE_SIDE || c.height > MAX_IMAGE_SIDE {
        return Err(format!("camera size {}x{} is outside 1..={MAX_IMAGE_SIDE}", c.width, c.height));
    }
    let finite_positive = |v: f64| v.is_finite() && v > 0.0;
    if !finite_positive(c.fx) || !finite_positive(c.fy) {
        return Err(format!("camera focal lengths must be positive, got fx={} fy={}", c.fx, c.fy));
    }
    if !c.cx.is_finite() || !c.cy.is_finite() {
        return Err("camera principal point is not finite".into());
    }
    let readout = c.rolling_shutter_readout_s;
    if !(0.0..=MAX_ROLLING_SHUTTER_READOUT_S).contains(&readout) {
        return Err(format!("rolling_shutter_readout_s must be within 0..={MAX_ROLLING_SHUTTER_READOUT_S} s, got {readout}"));
    }
    if c.nominal_rate_hz > 0.0 && readout > 1.0 / c.nominal_rate_hz {
        return Err(format!(
            "rolling_shutter_readout_s {readout} s is longer than one frame at the nominal {} Hz",
            c.nominal_rate_hz
        ));
    }
    let offset = c.exposure_time_offset_s;
    if !(-MAX_EXPOSURE_TIME_OFFSET_S..=MAX_EXPOSURE_TIME_OFFSET_S).contains(&offset) {
        return Err(format!(
            "exposure_time_offset_s must be within -{MAX_EXPOSURE_TIME_OFFSET_S}..={MAX_EXPOSURE_TIME_OFFSET_S} s, got {offset}"
        ));
    }
    if c.calibration_source.len() > MAX_CALIBRATION_SOURCE_BYTES {
        return Err(format!(
            "calibration_source is {} bytes, more than {MAX_CALIBRATION_SOURCE_BYTES}",
            c.calibration_source.len()
        ));
    }
    if !finite_positive(c.depth_units_per_metre) {
        return Err(format!("depth_units_per_metre must be positive, got {}", c.depth_units_per_metre));
    }
    if ColorEncoding::try_from(c.color_encoding).unwrap_or_default() == ColorEncoding::Unspecified {
        return Err(format!("unknown or unspecified colour encoding {}", c.color_encoding));
    }
    if DepthEncoding::try_from(c.depth_encoding).unwrap_or_default() == DepthEncoding::Unspecified {
        return Err(format!("unknown or unspecified depth encoding {}", c.depth_encoding));
    }
    match pb::DistortionModel::try_from(c.distortion_model) {
        Ok(pb::DistortionModel::PlumbBob) if c.distortion_coeffs.len() != 5 => {
            return Err(format!("plumb_bob distortion needs 5 coefficients, got {}", c.distortion_coeffs.len()));
        }
        Err(_) => return Err(format!("unknown distortion model {}", c.distortion_model)),
        _ => {}
    }
    Ok(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> pb::CameraInfo {
        pb::CameraInfo {
            width: 8,
            height: 4,
            fx: 5.0,
            fy: 5.0,
            cx: 4.0,
            cy: 2.0,
            depth_units_per_metre: 1000.0,
            color_encoding: ColorEncoding::Rgb8 as i32,
            depth_encoding: DepthEncoding::Rvl as i32,
            ..Default::default()
        }
    }

    fn frame(sequence: u64, t: u64) -> pb::Frame {
        let depth = DepthImage { width: 8, height: 4, data: (0..32).collect() };
        pb::Frame {
            sequence,
            capture_time_ns: t,
            color: vec![7; 8 * 4 * 3].into(),
            depth: codec::encode_depth(DepthEncoding::Rvl, &depth).unwrap().into(),
            accel_in_camera: None,
        }
    }

    fn error_of(p: &Processed) -> (i32, String) {
        let e = p.result.error.clone().unwrap();
        (e.code, e.message)
    }

    #[test]
    fn good_frame_is_decoded_without_a_pose() {
        let mut p = FramePipeline::new(camera());
        let out = p.process(&frame(1, 100), Duration::ZERO);
        assert_eq!(out.result.status(), FrameStatus::Ok);
        assert_eq!(out.result.tracking_state(), TrackingState::Initializing);
        assert!(out.result.world_from_camera.is_none());
        let depth = DepthImage { width: 8, height: 4, data: (0..32).collect() };
        assert_eq!(out.result.depth_crc32, depth.crc32());
        let stages: Vec<_> = out.result.latency.iter().map(|l| l.stage.as_str()).collect();
        assert_eq!(stages, [stage::QUEUE, stage::DECODE_COLOR, stage::DECODE_DEPTH, stage::TOTAL]);
    }

    #[test]
    fn order_problems_are_rejected_and_the_session_goes_on() {
        let mut p = FramePipeline::new(camera());
        p.process(&frame(5, 500), Duration::ZERO);
        let back = p.process(&frame(6, 400), Duration::ZERO);
        assert_eq!(
            error_of(&back),
            (
                Code::InvalidArgument as i32,
                "capture timestamp went backwards: frame 6 at 400 ns is not after the previous frame's 500 ns".into()
            )
        );
        let dup = p.process(&frame(5, 600), Duration::ZERO);
        assert_eq!(error_of(&dup).1, "frame sequence 5 is not after the previous frame's 5");
        assert_eq!(p.process(&frame(6, 600), Duration::ZERO).result.status(), FrameStatus::Ok);
    }

    #[test]
    fn bad_images_name_the_problem() {
        let mut p = FramePipeline::new(camera());
        let mut f = frame(1, 1);
        f.color.truncate(5);
        assert_eq!(error_of(&p.process(&f, Duration::ZERO)).1, "frame 1: raw RGB8 colour holds 5 bytes, expected 96 (8x4x3)");
        let mut f = frame(2, 2);
        f.depth = vec![0, 0, 0].into();
        let out = p.process(&f, Duration::ZERO);
        assert_eq!(out.rejected, Some(RejectReason::Depth));
        assert_eq!(error_of(&out).1, "frame 2: RVL depth is malformed: length is not a whole number of 32-bit words");
    }

    #[test]
    fn camera_validation() {
        assert!(validate_camera(Some(&camera())).is_ok());
        assert_eq!(validate_camera(None).unwrap_err(), "hello has no camera info");
        let mut c = camera();
        c.width = 0;
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "camera size 0x4 is outside 1..=8192");
        let mut c = camera();
        c.depth_encoding = 0;
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "unknown or unspecified depth encoding 0");
        let mut c = camera();
        c.distortion_model = pb::DistortionModel::PlumbBob as i32;
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "plumb_bob distortion needs 5 coefficients, got 0");
        let mut c = camera();
        c.rolling_shutter_readout_s = 0.03;
        assert!(validate_camera(Some(&c)).is_ok(), "a 30 ms readout");
        for bad in [-0.001, 0.2, f64::NAN] {
            c.rolling_shutter_readout_s = bad;
            assert_eq!(validate_camera(Some(&c)).unwrap_err(), format!("rolling_shutter_readout_s must be within 0..=0.1 s, got {bad}"));
        }
        c.rolling_shutter_readout_s = 0.05;
        c.nominal_rate_hz = 30.0;
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "rolling_shutter_readout_s 0.05 s is longer than one frame at the nominal 30 Hz");
        let mut c = camera();
        for good in [-0.0125, 0.0, 0.1, -0.1] {
            c.exposure_time_offset_s = good;
            assert!(validate_camera(Some(&c)).is_ok(), "offset {good}");
        }
        for bad in [-0.2, 0.11, f64::NAN, f64::INFINITY] {
            c.exposure_time_offset_s = bad;
            assert_eq!(validate_camera(Some(&c)).unwrap_err(), format!("exposure_time_offset_s must be within -0.1..=0.1 s, got {bad}"));
        }
        let mut c = camera();
        c.calibration_source = "x".repeat(512);
        assert!(validate_camera(Some(&c)).is_ok());
        c.calibration_source.push('x');
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "calibration_source is 513 bytes, more than 512");
    }
}
