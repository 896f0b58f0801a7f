//! Test, bench and example support for every crate (the `testing` feature): the
//! public TUM clips through `stillmap_dataset`, the freiburg1 camera as a tracking
//! [`Camera`], and a clip tracked by a fresh [`Tracker`]. Failures panic: this is
//! for tests and examples only.

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;
use stillmap_dataset::calibration::KnownCamera;
use stillmap_dataset::eval::Scores;
pub use stillmap_dataset::tum::Frame as TumFrame;

use crate::{Camera, FrameInput, Tracker, TrackerConfig};

/// The public clip beside the repository: frames 0–149 of freiburg1_rpy.
pub fn fr1_rpy_dir() -> PathBuf {
    stillmap_dataset::shared::fr1_rpy()
}

/// The tracking camera of a shipped calibration (intrinsics, distortion, depth
/// units and rolling-shutter readout), as the client sends it and the server's
/// `convert::camera_of` reads it.
pub fn known_camera(known: KnownCamera) -> Camera {
    let info = known.camera_info();
    let plumb_bob = info.distortion_model == stillmap_proto::pb::DistortionModel::PlumbBob as i32;
    let distortion = <[f64; 5]>::try_from(info.distortion_coeffs.as_slice()).ok().filter(|_| plumb_bob);
    Camera {
        distortion,
        readout_s: info.rolling_shutter_readout_s,
        ..Camera::pinhole(info.width, info.height, info.fx, info.fy, info.cx, info.cy, info.depth_units_per_metre)
    }
}

/// The freiburg1 Kinect ([`known_camera`]).
pub fn fr1_camera() -> Camera {
    known_camera(KnownCamera::TumFr1)
}

/// The time the pose of the freiburg1 frame stamped `capture_time_ns` refers to,
/// as the server reports it (`FrameResult.pose_time_ns`).
pub fn fr1_pose_time_ns(capture_time_ns: u64) -> u64 {
    KnownCamera::TumFr1.pose_time_ns(capture_time_ns)
}

/// [`fr1_pose_time_ns`] with the offset `EXPOSURE_OFFSET_MS` (milliseconds) from the
/// environment when set, for the examples.
pub fn fr1_pose_time_ns_from_env(capture_time_ns: u64) -> u64 {
    match std::env::var("EXPOSURE_OFFSET_MS") {
        Ok(ms) => stillmap_proto::pose_time_ns(capture_time_ns, ms.parse::<f64>().expect("EXPOSURE_OFFSET_MS: milliseconds") * 1e-3),
        Err(_) => fr1_pose_time_ns(capture_time_ns),
    }
}

/// [`fr1_camera`] with the rolling-shutter readout `READOUT_MS` (milliseconds; 0 =
/// a global shutter) from the environment when set, for the examples.
pub fn fr1_camera_with_readout_from_env() -> Camera {
    match std::env::var("READOUT_MS") {
        Ok(ms) => Camera { readout_s: ms.parse::<f64>().expect("READOUT_MS: milliseconds") * 1e-3, ..fr1_camera() },
        Err(_) => fr1_camera(),
    }
}

/// Each item kept with probability 1/2 by a fixed 64-bit LCG (Knuth's MMIX
/// constants): frames dropped at random, the same ones every run.
pub fn half_at_random<T>(items: &[T]) -> Vec<&T> {
    let mut state = 12_345u64;
    items
        .iter()
        .filter(|_| {
            state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            (state >> 33).is_multiple_of(2)
        })
        .collect()
}

/// The first `max_frames` frames of a TUM folder, decoded.
pub fn load(dir: &Path, max_frames: usize) -> Vec<TumFrame> {
    stillmap_dataset::tum::load_frames(dir, max_frames).unwrap_or_else(|e| panic!("{e}"))
}

/// A TUM folder's ground truth as (timestamp, world_from_camera).
pub fn groundtruth(dir: &Path) -> Vec<(u64, Isometry3<f64>)> {
    stillmap_dataset::tum::groundtruth(dir).unwrap_or_else(|e| panic!("{e}"))
}

/// `stillmap_dataset::eval::summary` of `est` against `gt`.
pub fn score(gt: &[(u64, Isometry3<f64>)], est: &[(u64, Isometry3<f64>)]) -> Scores {
    stillmap_dataset::eval::summary(gt, est).unwrap_or_else(|e| panic!("score: {e}"))
}

/// Tracks `frames` with a fresh tracker; returns it (with its map) and the poses,
/// each at `pose_time_ns` of its frame's timestamp.
pub fn track_clip(
    camera: Camera,
    config: TrackerConfig,
    frames: &[TumFrame],
    pose_time_ns: impl Fn(u64) -> u64,
) -> (Tracker, Vec<(u64, Isometry3<f64>)>) {
    let mut tracker = Tracker::new(camera, config).expect("tracker");
    let mut est = Vec::new();
    for f in frames {
        let out =
            tracker.track(&FrameInput { timestamp_ns: f.timestamp_ns, rgb: &f.rgb, depth: &f.depth, dynamic_mask: None }).expect("track");
        if let Some(p) = out.world_from_camera {
            est.push((pose_time_ns(f.timestamp_ns), p));
        }
    }
    (tracker, est)
}

/// Writes `est` as a TUM trajectory file when the environment variable `EST`
/// names one (for evo or `stillmap-client eval`).
pub fn write_est_if_asked(est: &[(u64, Isometry3<f64>)]) {
    let Some(path) = std::env::var_os("EST") else { return };
    std::fs::write(path, stillmap_dataset::trajectory::format_tum_ns(est)).expect("write EST");
}

/// The `[tracking]` keys given as TOML in the environment variable `var`, on lines of
/// their own or separated by `;`, over the defaults (all defaults without it): how
/// examples and benchmarks take a configuration to compare. Panics naming `var` on
/// keys it cannot read (a developer's command line, not a robot's input).
pub fn config_from_env(var: &str) -> TrackerConfig {
    toml_from_env(var)
}

/// Any configuration given as TOML in the environment variable `var` (lines, or `;`
/// between them) over its defaults, as [`config_from_env`] reads `[tracking]` keys.
pub fn toml_from_env<T: serde::de::DeserializeOwned>(var: &str) -> T {
    toml::from_str(&std::env::var(var).unwrap_or_default().replace(';', "\n")).unwrap_or_else(|e| panic!("{var}: {e}"))
}
