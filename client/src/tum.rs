//! TUM RGB-D sequences: `rgb.txt`, `depth.txt` (and optionally `accelerometer.txt`)
//! in a folder, colour PNG 8-bit RGB and depth PNG 16-bit at 5000 units per metre.
//!
//! Colour and depth are paired like TUM's `associate.py`: every candidate pair
//! closer than 20 ms, closest first, each image used once, then sorted by time.

use std::path::{Path, PathBuf};

use stillmap_proto::codec;
use stillmap_proto::pb::{self, DistortionModel};

use crate::ClientError;
use crate::source::{FrameSource, RawFrame};

/// `associate.py`'s default maximum time difference.
pub const MAX_ASSOCIATION_NS: u64 = 20_000_000;
/// TUM depth PNGs store metres × 5000.
pub const TUM_DEPTH_UNITS_PER_METRE: f64 = 5000.0;
/// TUM sequences are recorded at 30 Hz.
pub const TUM_RATE_HZ: f64 = 30.0;

/// Parses a TUM timestamp ("1305031229.528748") to nanoseconds, exactly.
pub fn parse_timestamp_ns(s: &str) -> Option<u64> {
    let (secs, frac) = s.split_once('.').unwrap_or((s, ""));
    if frac.len() > 9 || !frac.chars().all(|c| c.is_ascii_digit()) {
        return None;
    }
    let secs: u64 = secs.parse().ok()?;
    let frac_ns: u64 = if frac.is_empty() { 0 } else { format!("{frac:0<9}").parse().ok()? };
    secs.checked_mul(1_000_000_000)?.checked_add(frac_ns)
}

/// Reads a TUM list file: `timestamp rest...` lines, `#` comments skipped.
pub fn read_list(path: &Path) -> Result<Vec<(u64, Vec<String>)>, ClientError> {
    let text = std::fs::read_to_string(path).map_err(|e| ClientError::Source(format!("{}: {e}", path.display())))?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut fields = line.split_whitespace();
        let ts = fields.next().and_then(parse_timestamp_ns).ok_or_else(|| {
            ClientError::Source(format!("{}:{}: bad timestamp in {line:?}", path.display(), i + 1))
        })?;
        out.push((ts, fields.map(str::to_owned).collect()));
    }
    Ok(out)
}

/// Pairs two timestamp lists like `associate.py` (offset 0): returns index pairs sorted by time.
pub fn associate(first: &[u64], second: &[u64], max_difference_ns: u64) -> Vec<(usize, usize)> {
    let mut sorted_second: Vec<(u64, usize)> = second.iter().copied().zip(0..).collect();
    sorted_second.sort_unstable();
    let mut candidates: Vec<(u64, usize, usize)> = Vec::new();
    for (i, &a) in first.iter().enumerate() {
        let lo = sorted_second.partition_point(|&(b, _)| b + max_difference_ns <= a);
        for &(b, j) in sorted_second[lo..].iter().take_while(|&&(b, _)| b < a + max_difference_ns) {
            candidates.push((a.abs_diff(b), i, j));
        }
    }
    candidates.sort_unstable();
    let (mut used_first, mut used_second) = (vec![false; first.len()], vec![false; second.len()]);
    let mut pairs = Vec::new();
    for (_, i, j) in candidates {
        if !used_first[i] && !used_second[j] {
            used_first[i] = true;
            used_second[j] = true;
            pairs.push((i, j));
        }
    }
    pairs.sort_unstable_by_key(|&(i, j)| (first[i], second[j]));
    pairs
}

/// Rolling-shutter readout of the freiburg1 Kinect's colour camera (seconds): not
/// published with the dataset; measured without ground truth as the readout at
/// which the tracker's map is most consistent (README, "Rolling shutter";
/// `cargo run --release -p stillmap-tracking --example readout_sweep`).
pub const TUM_FREIBURG1_READOUT_S: f64 = 0.025;

/// When a freiburg1 image was exposed relative to its timestamp (seconds). The TUM
/// recordings are ROS bags from the `openni_camera` driver, which stamps an image
/// with the host's clock when it arrives (`ros::Time::now()` in its image callback),
/// so after the last row was read: the middle row was exposed at least half a
/// readout earlier. The transfer time after the last row is not known and counts
/// as 0. freiburg2/3 stay at 0: their timing is not measured.
pub const TUM_FREIBURG1_EXPOSURE_OFFSET_S: f64 = -TUM_FREIBURG1_READOUT_S / 2.0;

/// Calibration of the TUM cameras (intrinsics from the benchmark's page), by sequence
/// name. Only freiburg1's rolling-shutter readout has been measured; the others are
/// sent as global shutters.
pub fn tum_camera(dir_name: &str) -> (pb::CameraInfo, bool) {
    let freiburg1 = dir_name.contains("freiburg1");
    let (fx, fy, cx, cy, coeffs, known): (f64, f64, f64, f64, Option<[f64; 5]>, bool) = if freiburg1 {
        (517.3, 516.5, 318.6, 255.3, Some([0.2624, -0.9531, -0.0054, 0.0026, 1.1633]), true)
    } else if dir_name.contains("freiburg2") {
        (520.9, 521.0, 325.1, 249.7, Some([0.2312, -0.7849, -0.0033, -0.0001, 0.9172]), true)
    } else if dir_name.contains("freiburg3") {
        (535.4, 539.2, 320.1, 247.6, None, true)
    } else {
        // The ROS default the TUM page recommends for unknown Kinects.
        (525.0, 525.0, 319.5, 239.5, None, false)
    };
    let camera = pb::CameraInfo {
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
        rolling_shutter_readout_s: if freiburg1 { TUM_FREIBURG1_READOUT_S } else { 0.0 },
        exposure_time_offset_s: if freiburg1 { TUM_FREIBURG1_EXPOSURE_OFFSET_S } else { 0.0 },
        ..Default::default()
    };
    (camera, known)
}

pub struct TumSource {
    frames: Vec<(u64, PathBuf, PathBuf, Option<[f64; 3]>)>,
    next: usize,
    camera: pb::CameraInfo,
}

impl TumSource {
    pub fn open(dir: &Path, max_frames: Option<usize>) -> Result<Self, ClientError> {
        if !dir.is_dir() {
            return Err(ClientError::Source(format!("TUM folder {} does not exist", dir.display())));
        }
        let rgb = read_list(&dir.join("rgb.txt"))?;
        let depth = read_list(&dir.join("depth.txt"))?;
        let accel_path = dir.join("accelerometer.txt");
        let accel = if accel_path.exists() { read_list(&accel_path)? } else { vec![] };
        let accel_ts: Vec<u64> = accel.iter().map(|a| a.0).collect();

        let rgb_ts: Vec<u64> = rgb.iter().map(|r| r.0).collect();
        let depth_ts: Vec<u64> = depth.iter().map(|d| d.0).collect();
        let mut frames = Vec::new();
        for (i, j) in associate(&rgb_ts, &depth_ts, MAX_ASSOCIATION_NS) {
            let file = |list: &[(u64, Vec<String>)], k: usize, name: &str| {
                list[k].1.first().map(|f| dir.join(f)).ok_or_else(|| {
                    ClientError::Source(format!("{name}.txt: line for {} names no file", list[k].0))
                })
            };
            let ts = rgb_ts[i];
            let nearest = accel_ts.partition_point(|&t| t < ts);
            let accel_sample = [nearest.checked_sub(1), Some(nearest)]
                .into_iter()
                .flatten()
                .filter(|&k| k < accel.len() && accel_ts[k].abs_diff(ts) < MAX_ASSOCIATION_NS)
                .min_by_key(|&k| accel_ts[k].abs_diff(ts))
                .and_then(|k| {
                    let v: Vec<f64> = accel[k].1.iter().filter_map(|x| x.parse().ok()).collect();
                    (v.len() == 3).then(|| kinect_accel_to_camera([v[0], v[1], v[2]]))
                });
            frames.push((ts, file(&rgb, i, "rgb")?, file(&depth, j, "depth")?, accel_sample));
        }
        if frames.is_empty() {
            return Err(ClientError::Source(format!("{}: no colour/depth pair within 20 ms", dir.display())));
        }
        if let Some(max) = max_frames {
            frames.truncate(max);
        }
        let name = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
        let (camera, known) = tum_camera(&name.to_string_lossy());
        if !known {
            tracing::warn!("{}: not a freiburg1/2/3 sequence name; using the ROS default intrinsics", dir.display());
        }
        Ok(Self { frames, next: 0, camera })
    }

    /// Capture times of the associated frames, in order.
    pub fn timestamps(&self) -> impl Iterator<Item = u64> + '_ {
        self.frames.iter().map(|f| f.0)
    }
}

/// Reads one image file and decodes it with the contract's decoders (the same code the server runs).
fn read_image<T>(path: &Path, decode: impl FnOnce(&[u8]) -> Result<T, codec::CodecError>) -> Result<T, ClientError> {
    let bytes = std::fs::read(path).map_err(|e| ClientError::Source(format!("{}: {e}", path.display())))?;
    decode(&bytes).map_err(|e| ClientError::Source(format!("{}: {e}", path.display())))
}

impl FrameSource for TumSource {
    fn camera(&self) -> pb::CameraInfo {
        self.camera.clone()
    }

    fn len_hint(&self) -> Option<usize> {
        Some(self.frames.len())
    }

    fn next_frame(&mut self) -> Result<Option<RawFrame>, ClientError> {
        let Some((ts, rgb, depth, accel)) = self.frames.get(self.next) else {
            return Ok(None);
        };
        self.next += 1;
        let (w, h) = (self.camera.width, self.camera.height);
        let color = read_image(rgb, |b| codec::decode_color(pb::ColorEncoding::Png, b, w, h))?;
        let depth = read_image(depth, |b| codec::decode_depth(pb::DepthEncoding::Png16, b, w, h))?;
        Ok(Some(RawFrame { capture_time_ns: *ts, color, depth, accel_in_camera: *accel }))
    }
}

/// TUM's `accelerometer.txt` is the Kinect's own accelerometer, whose x and y axes
/// point opposite to the optical frame's (x right, y down, z forward). At rest it
/// reads the specific force, which points up. Checked against the ground truth's
/// up direction below.
fn kinect_accel_to_camera([x, y, z]: [f64; 3]) -> [f64; 3] {
    [-x, -y, z]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On the real fr1_rpy files, the converted accelerometer agrees with the up
    /// direction of the motion-capture ground truth (world z up) in the camera frame.
    #[test]
    fn kinect_accelerometer_axes_match_the_ground_truth() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/tum/rgbd_dataset_freiburg1_rpy");
        let read = |name: &str| -> Vec<Vec<f64>> {
            std::fs::read_to_string(dir.join(name))
                .expect("TUM file")
                .lines()
                .filter(|l| !l.starts_with('#'))
                .map(|l| l.split_whitespace().filter_map(|v| v.parse().ok()).collect())
                .collect()
        };
        let (gt, accel) = (read("groundtruth.txt"), read("accelerometer.txt"));
        let mut checked = 0;
        for g in gt.iter().step_by(50) {
            let a = accel.iter().min_by(|a, b| (a[0] - g[0]).abs().total_cmp(&(b[0] - g[0]).abs())).expect("samples");
            if (a[0] - g[0]).abs() > 0.01 {
                continue;
            }
            let [x, y, z, w] = [g[4], g[5], g[6], g[7]];
            // Third row of the rotation world_from_camera: world z in camera coordinates.
            let up = [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)];
            let c = kinect_accel_to_camera([a[1], a[2], a[3]]);
            let n = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
            let cos = (c[0] * up[0] + c[1] * up[1] + c[2] * up[2]) / n;
            // Hand-held motion adds its own acceleration: within 25°, not exact.
            assert!(cos > 25f64.to_radians().cos(), "at {}: accel {c:?} vs up {up:?}", g[0]);
            checked += 1;
        }
        assert!(checked >= 10, "{checked} samples checked");
    }

    #[test]
    fn timestamps_parse_exactly() {
        assert_eq!(parse_timestamp_ns("1305031229.528748"), Some(1_305_031_229_528_748_000));
        assert_eq!(parse_timestamp_ns("12"), Some(12_000_000_000));
        assert_eq!(parse_timestamp_ns("1.5"), Some(1_500_000_000));
        assert_eq!(parse_timestamp_ns("1.x"), None);
    }

    #[test]
    fn association_is_greedy_closest_first_like_associate_py() {
        let ms = 1_000_000;
        let first = [10 * ms, 11 * ms, 50 * ms, 100 * ms];
        let second = [20 * ms, 12 * ms, 95 * ms];
        // candidates: (10,20)=10 (10,12)=2 (11,20)=9 (11,12)=1 (100,95)=5 ; 50 has none.
        // greedy: (11,12) first, then (100,95), then (10,20).
        assert_eq!(associate(&first, &second, 20 * ms), vec![(0, 0), (1, 1), (3, 2)]);
    }

    #[test]
    fn freiburg_calibrations() {
        let (c, known) = tum_camera("/data/rgbd_dataset_freiburg1_rpy");
        assert!(known);
        assert_eq!((c.fx, c.fy, c.cx, c.cy), (517.3, 516.5, 318.6, 255.3));
        assert_eq!(c.distortion_coeffs.len(), 5);
        assert_eq!(c.rolling_shutter_readout_s, 0.025);
        assert_eq!(c.exposure_time_offset_s, -0.0125, "stamped on arrival, after the last row");
        let (c, _) = tum_camera("freiburg3_walking_xyz");
        assert_eq!(c.distortion_model(), DistortionModel::None);
        assert_eq!(c.rolling_shutter_readout_s, 0.0, "not measured: sent as a global shutter");
        assert_eq!(c.exposure_time_offset_s, 0.0, "not measured");
        assert!(!tum_camera("my_sequence").1);
    }
}
