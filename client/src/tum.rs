//! TUM RGB-D sequences: `rgb.txt`, `depth.txt` (and optionally `accelerometer.txt`)
//! in a folder, colour PNG 8-bit RGB and depth PNG 16-bit at 5000 units per metre.
//!
//! Colour and depth are paired like TUM's `associate.py`: every candidate pair
//! closer than 20 ms, closest first, each image used once, then sorted by time.

use std::path::{Path, PathBuf};

use stillmap_proto::codec;
use stillmap_proto::pb::{self, DistortionModel};

use crate::ClientError;
use crate::calibration::{CameraOptions, KnownCamera, SourceCamera};
use crate::source::{FrameSource, RawFrame};

/// `associate.py`'s default maximum time difference.
pub const MAX_ASSOCIATION_NS: u64 = 20_000_000;
/// TUM sequences' depth scale, rate and known cameras live in `calibration`.
pub use crate::calibration::{TUM_DEPTH_UNITS_PER_METRE, TUM_RATE_HZ};

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
        let ts = fields
            .next()
            .and_then(parse_timestamp_ns)
            .ok_or_else(|| ClientError::Source(format!("{}:{}: bad timestamp in {line:?}", path.display(), i + 1)))?;
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

/// The index of the time in `sorted` nearest to `t`, when it is less than `max_ns` away.
pub fn nearest(sorted: &[u64], t: u64, max_ns: u64) -> Option<usize> {
    let after = sorted.partition_point(|&s| s < t);
    [after.checked_sub(1), Some(after)]
        .into_iter()
        .flatten()
        .filter(|&k| k < sorted.len() && sorted[k].abs_diff(t) < max_ns)
        .min_by_key(|&k| sorted[k].abs_diff(t))
}

/// What a TUM folder says about its camera: the freiburg calibration its name
/// (as given, not a symlink's target) names, or 640×480 with the ROS default
/// intrinsics the TUM page recommends for unknown Kinects, marked unknown.
pub fn tum_camera(dir: &Path) -> SourceCamera {
    let name = folder_name(dir);
    match KnownCamera::from_tum_folder_name(&name) {
        Some(camera) => SourceCamera {
            info: camera.camera_info(),
            known: Some(format!("tum-folder:{name} ({})", camera.name())),
            what: format!("TUM folder {name}"),
        },
        None => SourceCamera {
            info: pb::CameraInfo {
                width: 640,
                height: 480,
                fx: 525.0,
                fy: 525.0,
                cx: 319.5,
                cy: 239.5,
                distortion_model: DistortionModel::None as i32,
                depth_units_per_metre: TUM_DEPTH_UNITS_PER_METRE,
                nominal_rate_hz: TUM_RATE_HZ,
                ..Default::default()
            },
            known: None,
            what: format!("TUM folder {name} (no freiburg1/2/3 in its name)"),
        },
    }
}

/// The folder's own name as the user gave it: `a/b/` → `b`; `.` or `..` → the
/// last component of the absolute path (`std::path::absolute` resolves no symlink).
fn folder_name(dir: &Path) -> String {
    dir.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .or_else(|| {
            let abs = std::path::absolute(dir).ok()?;
            let mut parts: Vec<String> = Vec::new();
            for c in abs.components() {
                match c {
                    std::path::Component::Normal(n) => parts.push(n.to_string_lossy().into_owned()),
                    std::path::Component::ParentDir => {
                        parts.pop();
                    }
                    _ => {}
                }
            }
            parts.pop()
        })
        .unwrap_or_default()
}

pub struct TumSource {
    frames: Vec<(u64, PathBuf, PathBuf, Option<[f64; 3]>)>,
    next: usize,
    camera: pb::CameraInfo,
}

impl TumSource {
    pub fn open(dir: &Path, max_frames: Option<usize>, options: &CameraOptions) -> Result<Self, ClientError> {
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
                list[k]
                    .1
                    .first()
                    .map(|f| dir.join(f))
                    .ok_or_else(|| ClientError::Source(format!("{name}.txt: line for {} names no file", list[k].0)))
            };
            let ts = rgb_ts[i];
            let accel_sample = nearest(&accel_ts, ts, MAX_ASSOCIATION_NS).and_then(|k| {
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
        let camera = crate::calibration::resolve(tum_camera(dir), options)?;
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
pub(crate) fn kinect_accel_to_camera([x, y, z]: [f64; 3]) -> [f64; 3] {
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
    fn tum_folder_names_as_given() {
        let c = tum_camera(Path::new("/data/rgbd_dataset_freiburg1_rpy"));
        assert_eq!(c.known.as_deref(), Some("tum-folder:rgbd_dataset_freiburg1_rpy (tum-fr1)"));
        assert_eq!((c.info.fx, c.info.rolling_shutter_readout_s), (517.3, 0.025));
        let c = tum_camera(Path::new("/data/freiburg3_walking_xyz/"));
        assert_eq!(c.known.as_deref(), Some("tum-folder:freiburg3_walking_xyz (tum-fr3)"));
        // Only the folder's own name counts, not its parents'.
        let c = tum_camera(Path::new("/data/rgbd_dataset_freiburg1_rpy/renamed"));
        assert_eq!(c.known, None);
        assert_eq!(c.what, "TUM folder renamed (no freiburg1/2/3 in its name)");
        assert_eq!(folder_name(Path::new("/x/rgbd_dataset_freiburg2_desk/sub/..")), "rgbd_dataset_freiburg2_desk");
    }

    /// A symlink named like a TUM folder is taken by its own name; a renamed link to
    /// a freiburg1 folder is not taken for freiburg1 and the source refuses to start.
    #[test]
    fn symlinked_folders_use_their_own_name() {
        let real = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/tum/rgbd_dataset_freiburg1_rpy");
        let dir = std::env::temp_dir().join(format!("stillmap-tum-link-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let renamed = dir.join("my_kinect_run");
        std::os::unix::fs::symlink(&real, &renamed).expect("symlink");
        let e = TumSource::open(&renamed, Some(2), &CameraOptions::default()).err().expect("refused").to_string();
        assert!(e.contains("TUM folder my_kinect_run (no freiburg1/2/3 in its name): the camera's calibration is not known"), "{e}");
        let preset = CameraOptions { camera: Some(KnownCamera::TumFr1), ..Default::default() };
        let s = TumSource::open(&renamed, Some(2), &preset).expect("with --camera");
        assert_eq!(s.camera().calibration_source, "preset:tum-fr1 (--camera)");
        assert_eq!(s.camera().fx, 517.3);
        std::fs::remove_dir_all(&dir).ok();
    }
}
