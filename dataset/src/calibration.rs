//! The cameras stillmap ships a calibration for (`--camera NAME`): the TUM RGB-D
//! benchmark's published intrinsics and distortion, its depth units and rate, and
//! the freiburg1 Kinect's measured rolling-shutter timing.

use stillmap_proto::pb::{self, DistortionModel};

/// TUM depth PNGs store metres × 5000.
pub const TUM_DEPTH_UNITS_PER_METRE: f64 = 5000.0;
/// TUM sequences are recorded at 30 Hz.
pub const TUM_RATE_HZ: f64 = 30.0;

/// Rolling-shutter readout of the freiburg1 Kinect's colour camera (seconds): not
/// published with the dataset; measured without ground truth as the readout at
/// which the tracker's map is most consistent (docs/tracking.md, "Rolling shutter";
/// `cargo run --release -p stillmap-tracking --example readout_sweep`).
pub const TUM_FREIBURG1_READOUT_S: f64 = 0.025;

/// When a freiburg1 image was exposed relative to its timestamp (seconds). The TUM
/// recordings are ROS bags from the `openni_camera` driver, which stamps an image
/// with the host's clock when it arrives (`ros::Time::now()` in its image callback),
/// so after the last row was read: the middle row was exposed at least half a
/// readout earlier. The transfer time after the last row is not known and counts
/// as 0. freiburg2/3 stay at 0: their timing is not measured.
pub const TUM_FREIBURG1_EXPOSURE_OFFSET_S: f64 = -TUM_FREIBURG1_READOUT_S / 2.0;

/// A camera whose calibration stillmap ships (`--camera NAME`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KnownCamera {
    /// The Kinect of TUM RGB-D's freiburg1 sequences.
    TumFr1,
    /// The Kinect of TUM RGB-D's freiburg2 sequences.
    TumFr2,
    /// The Asus Xtion of TUM RGB-D's freiburg3 sequences (images already undistorted).
    TumFr3,
}

impl KnownCamera {
    pub const NAMES: &'static str = "tum-fr1|tum-fr2|tum-fr3";

    pub fn name(self) -> &'static str {
        match self {
            Self::TumFr1 => "tum-fr1",
            Self::TumFr2 => "tum-fr2",
            Self::TumFr3 => "tum-fr3",
        }
    }

    /// The camera a TUM sequence folder's name says recorded it
    /// (`rgbd_dataset_freiburg1_rpy` → `tum-fr1`), if any.
    pub fn from_tum_folder_name(name: &str) -> Option<Self> {
        if name.contains("freiburg1") {
            Some(Self::TumFr1)
        } else if name.contains("freiburg2") {
            Some(Self::TumFr2)
        } else if name.contains("freiburg3") {
            Some(Self::TumFr3)
        } else {
            None
        }
    }

    /// Intrinsics (the benchmark's published calibration), 640×480, and timing.
    /// Depth units and rate are TUM's; a live camera of the same model overrides them.
    pub fn camera_info(self) -> pb::CameraInfo {
        let (fx, fy, cx, cy, coeffs): (f64, f64, f64, f64, Option<[f64; 5]>) = match self {
            Self::TumFr1 => (517.3, 516.5, 318.6, 255.3, Some([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])),
            Self::TumFr2 => (520.9, 521.0, 325.1, 249.7, Some([0.2312, -0.7849, -0.0033, -0.0001, 0.9172])),
            Self::TumFr3 => (535.4, 539.2, 320.1, 247.6, None),
        };
        let freiburg1 = self == Self::TumFr1;
        pb::CameraInfo {
            width: 640,
            height: 480,
            fx,
            fy,
            cx,
            cy,
            distortion_model: if coeffs.is_some() { DistortionModel::PlumbBob } else { DistortionModel::None } as i32,
            distortion_coeffs: coeffs.map(|c| c.to_vec()).unwrap_or_default(),
            depth_units_per_metre: TUM_DEPTH_UNITS_PER_METRE,
            nominal_rate_hz: TUM_RATE_HZ,
            // Only freiburg1's readout has been measured; the others are sent as global shutters.
            rolling_shutter_readout_s: if freiburg1 { TUM_FREIBURG1_READOUT_S } else { 0.0 },
            exposure_time_offset_s: if freiburg1 { TUM_FREIBURG1_EXPOSURE_OFFSET_S } else { 0.0 },
            ..Default::default()
        }
    }
}

impl std::str::FromStr for KnownCamera {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "tum-fr1" => Ok(Self::TumFr1),
            "tum-fr2" => Ok(Self::TumFr2),
            "tum-fr3" => Ok(Self::TumFr3),
            _ => Err(format!("unknown camera {s:?}: use {}", Self::NAMES)),
        }
    }
}

impl KnownCamera {
    /// The time the pose of a frame stamped `capture_time_ns` refers to, as the
    /// server reports it for this camera (`FrameResult.pose_time_ns`).
    pub fn pose_time_ns(self, capture_time_ns: u64) -> u64 {
        stillmap_proto::pose_time_ns(capture_time_ns, self.camera_info().exposure_time_offset_s)
    }
}

/// The nominal intrinsics of an uncalibrated camera of `width × height` pixels
/// (ROS's and TUM's default for a Kinect: 525 px focal length, the image's centre,
/// no distortion), with `depth_units_per_metre`. A guess: sources mark it unknown.
pub fn nominal_camera_info(width: u32, height: u32, depth_units_per_metre: f64) -> pb::CameraInfo {
    pb::CameraInfo {
        width,
        height,
        fx: 525.0,
        fy: 525.0,
        cx: (f64::from(width) - 1.0) / 2.0,
        cy: (f64::from(height) - 1.0) / 2.0,
        distortion_model: DistortionModel::None as i32,
        depth_units_per_metre,
        ..Default::default()
    }
}
