//! TUM RGB-D sequences: `rgb.txt`, `depth.txt` (and optionally `accelerometer.txt`
//! and `groundtruth.txt`) in a folder, colour PNG 8-bit RGB and depth PNG 16-bit at
//! 5000 units per metre.
//!
//! Colour and depth are paired like TUM's `associate.py`: every candidate pair
//! closer than 20 ms, closest first, each image used once, then sorted by time.

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;
use stillmap_proto::codec;
use stillmap_proto::pb;

use crate::DatasetError;

/// `associate.py`'s default maximum time difference.
pub const MAX_ASSOCIATION_NS: u64 = 20_000_000;

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
pub fn read_list(path: &Path) -> Result<Vec<(u64, Vec<String>)>, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Read { path: path.to_owned(), source })?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut fields = line.split_whitespace();
        let ts = fields.next().and_then(parse_timestamp_ns).ok_or_else(|| DatasetError::Parse {
            path: path.to_owned(),
            line: i + 1,
            message: format!("bad timestamp in {line:?}"),
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
        // Saturating: timestamps near u64::MAX parse (18446744073.7 s).
        let lo = sorted_second.partition_point(|&(b, _)| b.saturating_add(max_difference_ns) <= a);
        for &(b, j) in sorted_second[lo..].iter().take_while(|&&(b, _)| b < a.saturating_add(max_difference_ns)) {
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

/// One associated colour/depth pair of a sequence, by file.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameFiles {
    /// The colour image's timestamp (the frame's capture time).
    pub timestamp_ns: u64,
    pub rgb: PathBuf,
    pub depth: PathBuf,
    /// The accelerometer sample within 20 ms, in the camera's axes ([`kinect_accel_to_camera`]).
    pub accel_in_camera: Option<[f64; 3]>,
}

/// The associated frames of the TUM folder `dir`, in time order.
pub fn read_sequence(dir: &Path) -> Result<Vec<FrameFiles>, DatasetError> {
    if !dir.is_dir() {
        let source = std::io::Error::new(std::io::ErrorKind::NotFound, "no such folder");
        return Err(DatasetError::Read { path: dir.to_owned(), source });
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
                .ok_or_else(|| DatasetError::MissingFile { list: dir.join(format!("{name}.txt")), timestamp_ns: list[k].0 })
        };
        let ts = rgb_ts[i];
        let accel_in_camera = nearest(&accel_ts, ts, MAX_ASSOCIATION_NS).and_then(|k| {
            // A line that does not hold three finite numbers gives the frame no reading.
            let v: Vec<f64> = accel[k].1.iter().filter_map(|x| x.parse::<f64>().ok().filter(|v| v.is_finite())).collect();
            (v.len() == 3).then(|| kinect_accel_to_camera([v[0], v[1], v[2]]))
        });
        frames.push(FrameFiles { timestamp_ns: ts, rgb: file(&rgb, i, "rgb")?, depth: file(&depth, j, "depth")?, accel_in_camera });
    }
    if frames.is_empty() {
        return Err(DatasetError::NoFrames { path: dir.to_owned() });
    }
    Ok(frames)
}

/// Reads one image file and decodes it with the wire contract's decoders (the code
/// the server runs).
pub fn read_image<T>(path: &Path, decode: impl FnOnce(&[u8]) -> Result<T, codec::CodecError>) -> Result<T, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Read { path: path.to_owned(), source })?;
    decode(&bytes).map_err(|e| DatasetError::Decode { path: path.to_owned(), message: e.to_string() })
}

/// A decoded frame: RGB8 and depth in TUM units (5000 per metre), `width × height`.
#[derive(Debug, Clone)]
pub struct Frame {
    pub timestamp_ns: u64,
    pub rgb: Vec<u8>,
    pub depth: Vec<u16>,
}

impl FrameFiles {
    /// Reads and decodes the pair (TUM images are 640 × 480).
    pub fn decode(&self, width: u32, height: u32) -> Result<Frame, DatasetError> {
        let rgb = read_image(&self.rgb, |b| codec::decode_color(pb::ColorEncoding::Png, b, width, height))?.data;
        let depth = read_image(&self.depth, |b| codec::decode_depth(pb::DepthEncoding::Png16, b, width, height))?.data;
        Ok(Frame { timestamp_ns: self.timestamp_ns, rgb, depth })
    }
}

/// The first `max_frames` associated frames of the TUM folder `dir`, decoded (640 × 480).
pub fn load_frames(dir: &Path, max_frames: usize) -> Result<Vec<Frame>, DatasetError> {
    read_sequence(dir)?.iter().take(max_frames).map(|f| f.decode(640, 480)).collect()
}

/// The folder's `groundtruth.txt` as (timestamp, world_from_camera), in file order.
pub fn groundtruth(dir: &Path) -> Result<Vec<(u64, Isometry3<f64>)>, DatasetError> {
    crate::trajectory::read_tum_ns(&dir.join("groundtruth.txt"))
}

/// TUM's `accelerometer.txt` is the Kinect's own accelerometer, whose x and y axes
/// point opposite to the optical frame's (x right, y down, z forward). At rest it
/// reads the specific force, which points up. Checked against the ground truth's
/// up direction below.
pub fn kinect_accel_to_camera([x, y, z]: [f64; 3]) -> [f64; 3] {
    [-x, -y, z]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On the real fr1_rpy files, the converted accelerometer agrees with the up
    /// direction of the motion-capture ground truth (world z up) in the camera frame.
    #[test]
    fn kinect_accelerometer_axes_match_the_ground_truth() {
        let dir = crate::shared::fr1_rpy();
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

    /// Timestamps at the top of the range (they parse) pair without overflowing.
    #[test]
    fn association_holds_at_the_largest_timestamps() {
        let top = parse_timestamp_ns("18446744073.709551").expect("parses");
        let ms = 1_000_000;
        assert_eq!(associate(&[top, 5 * ms], &[top - ms, 6 * ms], 20 * ms), vec![(1, 1), (0, 0)]);
    }

    /// The public clip reads as 150 associated frames with the accelerometer, and
    /// decodes at TUM's size.
    #[test]
    fn the_public_clip_reads_and_decodes() {
        let frames = read_sequence(&crate::shared::fr1_rpy()).expect("sequence");
        assert_eq!(frames.len(), 150);
        assert!(frames.windows(2).all(|w| w[0].timestamp_ns < w[1].timestamp_ns));
        assert!(frames.iter().all(|f| f.accel_in_camera.is_some()));
        let decoded = load_frames(&crate::shared::fr1_rpy(), 2).expect("frames");
        assert_eq!((decoded.len(), decoded[0].rgb.len(), decoded[0].depth.len()), (2, 640 * 480 * 3, 640 * 480));
        assert!(matches!(read_sequence(Path::new("/nonexistent/tum")), Err(DatasetError::Read { .. })));
    }
}
