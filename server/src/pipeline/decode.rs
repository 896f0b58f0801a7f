//! The decode stage: checks a frame against the session's order and camera and
//! decodes both images. Also the hello's camera check.

use std::time::{Duration, Instant};

use stillmap_proto::codec::{self, ColorImage, DepthImage};
use stillmap_proto::pb::{self, ColorEncoding, DepthEncoding};
use stillmap_proto::{MAX_EXPOSURE_TIME_OFFSET_S, MAX_ROLLING_SHUTTER_READOUT_S};
use tonic::Code;

/// Why a frame was rejected, as a metrics label.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RejectReason {
    Order,
    Color,
    Depth,
    Accelerometer,
}

impl RejectReason {
    pub fn label(self) -> &'static str {
        match self {
            Self::Order => "order",
            Self::Color => "color",
            Self::Depth => "depth",
            Self::Accelerometer => "accelerometer",
        }
    }
}

/// A frame that cannot be used: the reason, and the gRPC code and message its
/// result carries.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejection {
    pub reason: RejectReason,
    pub code: Code,
    pub message: String,
}

/// A decoded frame.
pub struct Decoded {
    pub color: ColorImage,
    pub depth: DepthImage,
    pub depth_crc32: u32,
    pub color_time: Duration,
    pub depth_time: Duration,
}

/// What the decode stage carries from frame to frame: the camera and the order.
pub struct Decoder {
    camera: pb::CameraInfo,
    color_encoding: ColorEncoding,
    depth_encoding: DepthEncoding,
    window: OrderWindow,
    /// Frames in a row that jumped past the window.
    jumps: JumpCount,
    last_sequence: Option<u64>,
    last_capture_time_ns: Option<u64>,
    /// The (sequence, capture time) of the frame taken before the last one.
    before_last: Option<(u64, u64)>,
}

/// Frames in a row that jump past the order window before the decoder takes the
/// next one as the robot's new sequence and clock.
pub const RESYNC_AFTER_JUMPS: u32 = 3;

/// Frames in a row that jumped past the order window: after
/// [`RESYNC_AFTER_JUMPS`] of them the next jumping frame starts the robot's new
/// timeline (one forged frame between the robot's own changes nothing).
#[derive(Debug, Clone, Copy, Default)]
pub struct JumpCount(u32);

impl JumpCount {
    /// Counts a frame that `jumped` or not; true when the frame starts a new
    /// timeline (the previous frame is to be forgotten).
    pub fn restart(&mut self, jumped: bool) -> bool {
        if !jumped {
            self.0 = 0;
            false
        } else if self.0 >= RESYNC_AFTER_JUMPS {
            self.0 = 0;
            true
        } else {
            self.0 += 1;
            false
        }
    }
}

/// How far a frame may jump past the previous one and still be taken as the
/// session's next (`session.max_sequence_jump`, `session.max_capture_gap_s`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OrderWindow {
    pub max_sequence_jump: u64,
    pub max_capture_gap_ns: u64,
}

impl Default for OrderWindow {
    fn default() -> Self {
        Self { max_sequence_jump: 1_000_000, max_capture_gap_ns: 86_400_000_000_000 }
    }
}

impl OrderWindow {
    /// Whether sequence `next` is plausible after `last` (no previous frame: any).
    pub fn sequence_fits(&self, last: Option<u64>, next: u64) -> bool {
        last.is_none_or(|l| next.saturating_sub(l) <= self.max_sequence_jump)
    }
}

impl Decoder {
    /// `camera` must have passed [`validate_camera`].
    pub fn new(camera: pb::CameraInfo, window: OrderWindow) -> Self {
        Self {
            color_encoding: camera.color_encoding(),
            depth_encoding: camera.depth_encoding(),
            camera,
            window,
            jumps: JumpCount::default(),
            last_sequence: None,
            last_capture_time_ns: None,
            before_last: None,
        }
    }

    /// Checks the frame's order and decodes it. A rejected frame leaves the order
    /// as it was only when its own order was wrong (a frame with a bad image still
    /// counts as seen).
    pub fn decode(&mut self, frame: &pb::Frame) -> Result<Decoded, Rejection> {
        let reject = |reason, message: String| Rejection { reason, code: Code::InvalidArgument, message };
        // A robot that really jumped (it paused for more than a day, its clock was
        // set) sends more frames after the jump: after
        // `RESYNC_AFTER_JUMPS` in a row the next is taken, and the session goes on
        // from there. A frame behind the previous one but after the one before it
        // counts as a jump too (the previous one jumped ahead): one forged frame
        // beyond the order window is rejected and changes nothing, one within it
        // (taken) costs the robot `RESYNC_AFTER_JUMPS` frames, not the session. A
        // frame behind both is a resend of one already taken, and never starts a
        // timeline.
        let behind = self.last_sequence.is_some_and(|last| frame.sequence <= last)
            || self.last_capture_time_ns.is_some_and(|last| frame.capture_time_ns <= last);
        let after_the_one_before = self.last_sequence != Some(frame.sequence)
            && self.before_last.is_none_or(|(sequence, time)| frame.sequence > sequence && frame.capture_time_ns > time);
        let jumped = (behind && after_the_one_before)
            || !self.window.sequence_fits(self.last_sequence, frame.sequence)
            || self.last_capture_time_ns.is_some_and(|last| frame.capture_time_ns.saturating_sub(last) > self.window.max_capture_gap_ns);
        if self.jumps.restart(jumped) {
            tracing::warn!(
                sequence = frame.sequence,
                "{RESYNC_AFTER_JUMPS} frames in a row jumped past the order window or went back: taking the new sequence and clock"
            );
            self.last_sequence = None;
            self.last_capture_time_ns = None;
            self.before_last = None;
        }
        if let Some(last) = self.last_sequence
            && frame.sequence <= last
        {
            return Err(reject(RejectReason::Order, format!("frame sequence {} is not after the previous frame's {last}", frame.sequence)));
        }
        if !self.window.sequence_fits(self.last_sequence, frame.sequence) {
            return Err(reject(
                RejectReason::Order,
                format!(
                    "frame sequence {} jumps more than session.max_sequence_jump = {} past the previous frame's {}: not taken as this robot's next frame",
                    frame.sequence,
                    self.window.max_sequence_jump,
                    self.last_sequence.unwrap_or_default()
                ),
            ));
        }
        if let Some(last) = self.last_capture_time_ns
            && frame.capture_time_ns.saturating_sub(last) > self.window.max_capture_gap_ns
        {
            return Err(reject(
                RejectReason::Order,
                format!(
                    "frame {} captured {} s after the previous frame, more than session.max_capture_gap_s = {}: not taken as this robot's next frame",
                    frame.sequence,
                    (frame.capture_time_ns - last) as f64 * 1e-9,
                    self.window.max_capture_gap_ns as f64 * 1e-9
                ),
            ));
        }
        if let Some(last) = self.last_capture_time_ns
            && frame.capture_time_ns <= last
        {
            return Err(reject(
                RejectReason::Order,
                format!(
                    "capture timestamp went backwards: frame {} at {} ns is not after the previous frame's {last} ns",
                    frame.sequence, frame.capture_time_ns
                ),
            ));
        }
        self.before_last = self.last_sequence.zip(self.last_capture_time_ns);
        self.last_sequence = Some(frame.sequence);
        self.last_capture_time_ns = Some(frame.capture_time_ns);
        if let Some(a) = frame.accel_in_camera
            && !(a.x.is_finite() && a.y.is_finite() && a.z.is_finite())
        {
            return Err(reject(
                RejectReason::Accelerometer,
                format!("frame {}: accelerometer reading ({}, {}, {}) is not finite", frame.sequence, a.x, a.y, a.z),
            ));
        }

        let (w, h) = (self.camera.width, self.camera.height);
        let t = Instant::now();
        let color = codec::decode_color(self.color_encoding, &frame.color, w, h)
            .map_err(|e| reject(RejectReason::Color, format!("frame {}: {e}", frame.sequence)))?;
        let color_time = t.elapsed();
        let t = Instant::now();
        let depth = codec::decode_depth(self.depth_encoding, &frame.depth, w, h)
            .map_err(|e| reject(RejectReason::Depth, format!("frame {}: {e}", frame.sequence)))?;
        let depth_crc32 = depth.crc32();
        Ok(Decoded { color, depth, depth_crc32, color_time, depth_time: t.elapsed() })
    }
}

/// Largest distortion coefficient (absolute) a hello may declare: strong wide-angle
/// lenses stay within tens; beyond this it is a mistake, not a lens.
pub const MAX_DISTORTION_COEFFICIENT: f64 = 1000.0;

/// Highest nominal frame rate (Hz) a hello may declare.
pub const MAX_NOMINAL_RATE_HZ: f64 = 1000.0;

/// Longest `CameraInfo.calibration_source` the server accepts.
pub const MAX_CALIBRATION_SOURCE_BYTES: usize = 512;

/// Narrowest and widest field of view (degrees, per axis) a hello's intrinsics
/// may give: beyond them they are a mistake (fx = 1e-300), not a camera.
pub const MIN_FIELD_OF_VIEW_DEG: f64 = 0.5;
pub const MAX_FIELD_OF_VIEW_DEG: f64 = 170.0;

/// Largest image side the server accepts in a hello.
pub const MAX_IMAGE_SIDE: u32 = 8192;

/// Smallest image side: ORB's 31-pixel patch and the flow's pyramid need at least
/// this much; a smaller camera (1×1) would track nothing.
pub const MIN_IMAGE_SIDE: u32 = 32;

/// Checks a hello's camera; the message names the first problem.
pub fn validate_camera(camera: Option<&pb::CameraInfo>) -> Result<&pb::CameraInfo, String> {
    let c = camera.ok_or("hello has no camera info")?;
    let side = MIN_IMAGE_SIDE..=MAX_IMAGE_SIDE;
    if !side.contains(&c.width) || !side.contains(&c.height) {
        return Err(format!("camera size {}x{} is outside {MIN_IMAGE_SIDE}..={MAX_IMAGE_SIDE} per side", c.width, c.height));
    }
    let finite_positive = |v: f64| v.is_finite() && v > 0.0;
    if !finite_positive(c.fx) || !finite_positive(c.fy) {
        return Err(format!("camera focal lengths must be positive, got fx={} fy={}", c.fx, c.fy));
    }
    // fx = 1e-300 is positive, and makes every ray of the map's camera infinite.
    for (axis, focal, side) in [("fx", c.fx, c.width), ("fy", c.fy, c.height)] {
        let fov_deg = 2.0 * (f64::from(side) / (2.0 * focal)).atan().to_degrees();
        if !(MIN_FIELD_OF_VIEW_DEG..=MAX_FIELD_OF_VIEW_DEG).contains(&fov_deg) {
            return Err(format!(
                "camera {axis} = {focal:?} over {side} pixels is a field of view of {fov_deg:.3}°, outside {MIN_FIELD_OF_VIEW_DEG}-{MAX_FIELD_OF_VIEW_DEG}°"
            ));
        }
    }
    // Within the image, as every calibration has it: cx = 1e6 with fx = 500 passes
    // the field of view, yet shears each depth sample kilometres sideways.
    if !((0.0..=f64::from(c.width)).contains(&c.cx) && (0.0..=f64::from(c.height)).contains(&c.cy)) {
        return Err(format!("camera principal point ({}, {}) lies outside the {}x{} image", c.cx, c.cy, c.width, c.height));
    }
    if !(c.nominal_rate_hz.is_finite() && (0.0..=MAX_NOMINAL_RATE_HZ).contains(&c.nominal_rate_hz)) {
        return Err(format!("nominal_rate_hz must be within 0..={MAX_NOMINAL_RATE_HZ} (0: unknown), got {}", c.nominal_rate_hz));
    }
    let readout = c.rolling_shutter_readout_s;
    if !(0.0..=MAX_ROLLING_SHUTTER_READOUT_S).contains(&readout) {
        return Err(format!("rolling_shutter_readout_s must be within 0..={MAX_ROLLING_SHUTTER_READOUT_S} s, got {readout}"));
    }
    if c.nominal_rate_hz > 0.0 && readout > 1.0 / c.nominal_rate_hz {
        return Err(format!("rolling_shutter_readout_s {readout} s is longer than one frame at the nominal {} Hz", c.nominal_rate_hz));
    }
    let offset = c.exposure_time_offset_s;
    if !(-MAX_EXPOSURE_TIME_OFFSET_S..=MAX_EXPOSURE_TIME_OFFSET_S).contains(&offset) {
        return Err(format!(
            "exposure_time_offset_s must be within -{MAX_EXPOSURE_TIME_OFFSET_S}..={MAX_EXPOSURE_TIME_OFFSET_S} s, got {offset}"
        ));
    }
    if c.calibration_source.len() > MAX_CALIBRATION_SOURCE_BYTES {
        return Err(format!("calibration_source is {} bytes, more than {MAX_CALIBRATION_SOURCE_BYTES}", c.calibration_source.len()));
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
        // No model: nothing to read, and nothing to keep (a session stores its hello).
        Ok(pb::DistortionModel::None | pb::DistortionModel::Unspecified) if !c.distortion_coeffs.is_empty() => {
            return Err(format!("distortion model none takes no coefficients, got {}", c.distortion_coeffs.len()));
        }
        Err(_) => return Err(format!("unknown distortion model {}", c.distortion_model)),
        _ => {}
    }
    if let Some(bad) = c.distortion_coeffs.iter().find(|k| !(k.is_finite() && k.abs() <= MAX_DISTORTION_COEFFICIENT)) {
        return Err(format!("distortion coefficients must be finite and within ±{MAX_DISTORTION_COEFFICIENT}, got {bad}"));
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

    fn error_of(r: Result<Decoded, Rejection>) -> (i32, String) {
        let e = r.err().expect("rejected");
        (e.code as i32, e.message)
    }

    #[test]
    fn good_frame_is_decoded() {
        let mut p = Decoder::new(camera(), OrderWindow::default());
        let out = p.decode(&frame(1, 100)).expect("decoded");
        let depth = DepthImage { width: 8, height: 4, data: (0..32).collect() };
        assert_eq!(out.depth, depth);
        assert_eq!(out.depth_crc32, depth.crc32());
        assert_eq!(out.color.data, vec![7; 96]);
    }

    #[test]
    fn a_frame_jumping_absurdly_far_is_rejected_and_the_robots_next_frames_go_on() {
        let mut p = Decoder::new(camera(), OrderWindow { max_sequence_jump: 1000, max_capture_gap_ns: 1_000_000_000 });
        assert!(p.decode(&frame(5, 500)).is_ok());
        assert_eq!(
            error_of(p.decode(&frame(u64::MAX, 600))).1,
            "frame sequence 18446744073709551615 jumps more than session.max_sequence_jump = 1000 past the previous frame's 5: not taken as this robot's next frame"
        );
        assert_eq!(
            error_of(p.decode(&frame(6, u64::MAX))).1,
            "frame 6 captured 18446744073.709553 s after the previous frame, more than session.max_capture_gap_s = 1: not taken as this robot's next frame"
        );
        // Neither moved the session on: the robot's real next frames are taken.
        assert!(p.decode(&frame(6, 700)).is_ok());
        assert!(p.decode(&frame(1006, 1_000_000_700)).is_ok(), "a jump of exactly the window fits");
        // A robot that really jumped (back after two days): three frames rejected,
        // then the new timeline is taken and followed.
        let later = 2 * 86_400_000_000_000u64;
        for k in 0..RESYNC_AFTER_JUMPS as u64 {
            assert_eq!(error_of(p.decode(&frame(1007 + k, later + k))).0, Code::InvalidArgument as i32);
        }
        assert!(p.decode(&frame(1010, later + 3)).is_ok());
        assert!(p.decode(&frame(1011, later + 4)).is_ok());
        let w = OrderWindow::default();
        assert!(w.sequence_fits(None, u64::MAX) && w.sequence_fits(Some(7), 3) && !w.sequence_fits(Some(7), 1_000_008));
    }

    #[test]
    fn order_problems_are_rejected_and_the_session_goes_on() {
        let mut p = Decoder::new(camera(), OrderWindow::default());
        assert!(p.decode(&frame(5, 500)).is_ok());
        assert_eq!(
            error_of(p.decode(&frame(6, 400))),
            (
                Code::InvalidArgument as i32,
                "capture timestamp went backwards: frame 6 at 400 ns is not after the previous frame's 500 ns".into()
            )
        );
        assert_eq!(error_of(p.decode(&frame(5, 600))).1, "frame sequence 5 is not after the previous frame's 5");
        assert!(p.decode(&frame(6, 600)).is_ok());
    }

    /// One forged frame within the order window (taken: it could be the robot's)
    /// must not shut the robot's own frames out: they are behind it, and after
    /// `RESYNC_AFTER_JUMPS` of them in a row their timeline is taken again. The
    /// same for a capture time far ahead, and for a robot that restarted its count.
    #[test]
    fn a_forged_frame_within_the_window_costs_the_robot_a_few_frames_not_the_session() {
        let window = OrderWindow { max_sequence_jump: 1_000_000, max_capture_gap_ns: 86_400_000_000_000 };
        for forged in [frame(5 + 999_999, 501), frame(6, 500 + 86_000_000_000_000)] {
            let mut p = Decoder::new(camera(), window);
            assert!(p.decode(&frame(5, 500)).is_ok());
            assert!(p.decode(&forged).is_ok(), "within the window: taken");
            let behind = RESYNC_AFTER_JUMPS as u64;
            for k in 0..behind {
                assert_eq!(error_of(p.decode(&frame(7 + k, 700 + k))).0, Code::InvalidArgument as i32, "frame {}", 7 + k);
            }
            assert!(p.decode(&frame(7 + behind, 700 + behind)).is_ok(), "the robot's timeline again");
            assert!(p.decode(&frame(8 + behind, 701 + behind)).is_ok());
        }
        // Resends of frames taken before (behind the one before the last too) are
        // rejected however many come: no old frame is taken twice.
        let mut p = Decoder::new(camera(), window);
        for k in 1..=6 {
            assert!(p.decode(&frame(k, 100 * k)).is_ok());
        }
        for k in 1..=5 {
            assert!(p.decode(&frame(k, 100 * k)).is_err(), "resend of frame {k}");
        }
        assert!(p.decode(&frame(6, 600)).is_err(), "resend of the last");
        assert!(p.decode(&frame(7, 700)).is_ok());
        // A single frame behind (a duplicate) is rejected and the next goes on.
        let mut p = Decoder::new(camera(), window);
        assert!(p.decode(&frame(5, 500)).is_ok());
        assert!(p.decode(&frame(5, 500)).is_err());
        assert!(p.decode(&frame(6, 600)).is_ok());
        assert!(p.decode(&frame(6, 600)).is_err());
        assert!(p.decode(&frame(7, 700)).is_ok(), "duplicates between good frames never add up");
    }

    #[test]
    fn a_non_finite_accelerometer_reading_is_rejected_and_the_session_goes_on() {
        let mut p = Decoder::new(camera(), OrderWindow::default());
        let mut f = frame(1, 100);
        f.accel_in_camera = Some(pb::Vector3 { x: 0.0, y: f64::NAN, z: 9.8 });
        let e = p.decode(&f).err().expect("rejected");
        assert_eq!((e.reason, e.code), (RejectReason::Accelerometer, Code::InvalidArgument));
        assert_eq!(e.message, "frame 1: accelerometer reading (0, NaN, 9.8) is not finite");
        let mut next = frame(2, 200);
        next.accel_in_camera = Some(pb::Vector3 { x: 0.0, y: 0.0, z: 9.8 });
        assert!(p.decode(&next).is_ok(), "the session goes on");
    }

    #[test]
    fn bad_images_name_the_problem() {
        let mut p = Decoder::new(camera(), OrderWindow::default());
        let mut f = frame(1, 1);
        f.color.truncate(5);
        assert_eq!(error_of(p.decode(&f)).1, "frame 1: raw RGB8 colour holds 5 bytes, expected 96 (8x4x3)");
        let mut f = frame(2, 2);
        f.depth = vec![0, 0, 0].into();
        let e = p.decode(&f).err().expect("rejected");
        assert_eq!(e.reason, RejectReason::Depth);
        assert_eq!(e.message, "frame 2: RVL depth is malformed: length is not a whole number of 32-bit words");
    }

    #[test]
    fn camera_validation() {
        // The decoding tests' 8x4 camera, at the smallest size a hello may declare.
        let hello_camera = || pb::CameraInfo { width: 32, height: 32, fx: 20.0, fy: 20.0, cx: 16.0, cy: 16.0, ..camera() };
        assert!(validate_camera(Some(&hello_camera())).is_ok());
        assert_eq!(validate_camera(None).unwrap_err(), "hello has no camera info");
        let mut c = hello_camera();
        c.width = 0;
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "camera size 0x32 is outside 32..=8192 per side");
        let mut c = hello_camera();
        (c.width, c.height) = (1, 1);
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "camera size 1x1 is outside 32..=8192 per side");
        (c.width, c.height) = (640, 8193);
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "camera size 640x8193 is outside 32..=8192 per side");
        let mut c = hello_camera();
        c.depth_encoding = 0;
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "unknown or unspecified depth encoding 0");
        let mut c = hello_camera();
        c.distortion_model = pb::DistortionModel::PlumbBob as i32;
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "plumb_bob distortion needs 5 coefficients, got 0");
        c.distortion_coeffs = vec![0.2, -0.5, 0.001, 0.0, 0.5];
        assert!(validate_camera(Some(&c)).is_ok(), "fr1's kind of lens");
        for bad in [f64::NAN, f64::INFINITY, 1e300] {
            c.distortion_coeffs[1] = bad;
            assert_eq!(
                validate_camera(Some(&c)).unwrap_err(),
                format!("distortion coefficients must be finite and within ±1000, got {bad}")
            );
        }
        // The principal point lies in the image (at its edges too).
        let mut c = hello_camera();
        (c.cx, c.cy) = (0.0, 32.0);
        assert!(validate_camera(Some(&c)).is_ok());
        for (cx, cy) in [(1e6, 16.0), (16.0, -0.5), (f64::NAN, 16.0), (16.0, f64::INFINITY)] {
            (c.cx, c.cy) = (cx, cy);
            assert_eq!(validate_camera(Some(&c)).unwrap_err(), format!("camera principal point ({cx}, {cy}) lies outside the 32x32 image"));
        }
        // Without a model, a million coefficients would be stored with the session.
        let mut c = hello_camera();
        c.distortion_coeffs = vec![0.0; 1_000_000];
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "distortion model none takes no coefficients, got 1000000");
        let mut c = hello_camera();
        for bad in [-1.0, f64::NAN, f64::INFINITY, 1001.0] {
            c.nominal_rate_hz = bad;
            assert_eq!(validate_camera(Some(&c)).unwrap_err(), format!("nominal_rate_hz must be within 0..=1000 (0: unknown), got {bad}"));
        }
        let mut c = hello_camera();
        c.rolling_shutter_readout_s = 0.03;
        assert!(validate_camera(Some(&c)).is_ok(), "a 30 ms readout");
        for bad in [-0.001, 0.2, f64::NAN] {
            c.rolling_shutter_readout_s = bad;
            assert_eq!(validate_camera(Some(&c)).unwrap_err(), format!("rolling_shutter_readout_s must be within 0..=0.1 s, got {bad}"));
        }
        c.rolling_shutter_readout_s = 0.05;
        c.nominal_rate_hz = 30.0;
        assert_eq!(
            validate_camera(Some(&c)).unwrap_err(),
            "rolling_shutter_readout_s 0.05 s is longer than one frame at the nominal 30 Hz"
        );
        let mut c = hello_camera();
        for good in [-0.0125, 0.0, 0.1, -0.1] {
            c.exposure_time_offset_s = good;
            assert!(validate_camera(Some(&c)).is_ok(), "offset {good}");
        }
        for bad in [-0.2, 0.11, f64::NAN, f64::INFINITY] {
            c.exposure_time_offset_s = bad;
            assert_eq!(validate_camera(Some(&c)).unwrap_err(), format!("exposure_time_offset_s must be within -0.1..=0.1 s, got {bad}"));
        }
        let mut c = hello_camera();
        c.calibration_source = "x".repeat(512);
        assert!(validate_camera(Some(&c)).is_ok());
        c.calibration_source.push('x');
        assert_eq!(validate_camera(Some(&c)).unwrap_err(), "calibration_source is 513 bytes, more than 512");
        // Positive but absurd focal lengths: a field of view of 180° or of nothing.
        let mut c = hello_camera();
        (c.width, c.fx) = (640, 1e-300);
        assert_eq!(
            validate_camera(Some(&c)).unwrap_err(),
            "camera fx = 1e-300 over 640 pixels is a field of view of 180.000°, outside 0.5-170°"
        );
        let mut c = hello_camera();
        (c.height, c.fy) = (480, 1e9);
        assert_eq!(
            validate_camera(Some(&c)).unwrap_err(),
            "camera fy = 1000000000.0 over 480 pixels is a field of view of 0.000°, outside 0.5-170°"
        );
        let mut c = hello_camera();
        let fr1 = stillmap_dataset::calibration::KnownCamera::TumFr1.camera_info();
        (c.width, c.height, c.fx, c.fy) = (fr1.width, fr1.height, fr1.fx, fr1.fy);
        assert!(validate_camera(Some(&c)).is_ok(), "TUM freiburg1");
    }
}
