//! Test and bench support (not part of the library): loads a TUM RGB-D folder and
//! scores a trajectory. Shared by the tests, benches and examples via `#[path]`.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Matrix3, Quaternion, Translation3, UnitQuaternion, Vector3};
use stillmap_proto::codec;
use stillmap_proto::pb::{ColorEncoding, DepthEncoding};
use stillmap_tracking::{Camera, FrameInput, Tracker, TrackerConfig};

pub struct TumFrame {
    pub timestamp_ns: u64,
    pub rgb: Vec<u8>,
    pub depth: Vec<u16>,
}

/// The real fr1_rpy clip beside the repository.
pub fn fr1_rpy_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/tum/rgbd_dataset_freiburg1_rpy")
}

/// Rolling-shutter readout of the freiburg1 Kinect's colour camera, as the client's
/// TUM source declares it (`client/src/tum.rs`; docs/tracking.md, "Rolling shutter").
pub const FR1_READOUT_S: f64 = 0.025;

/// TUM freiburg1 calibration (intrinsics from the dataset's documentation, readout
/// from `--example readout_sweep`), as the client sends it.
pub fn fr1_camera() -> Camera {
    Camera {
        distortion: Some([0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
        readout_s: FR1_READOUT_S,
        ..Camera::pinhole(640, 480, 517.3, 516.5, 318.6, 255.3, 5000.0)
    }
}

/// When a freiburg1 image was exposed relative to its timestamp, as the client's TUM
/// source declares it (`client/src/tum.rs`): the driver stamps a frame on arrival,
/// half a readout after its middle row.
pub const FR1_EXPOSURE_OFFSET_S: f64 = -FR1_READOUT_S / 2.0;

/// The time the pose of the frame stamped `capture_time_ns` refers to, as the server
/// reports it for freiburg1 (`FrameResult.pose_time_ns`).
pub fn fr1_pose_time_ns(capture_time_ns: u64) -> u64 {
    stillmap_proto::pose_time_ns(capture_time_ns, FR1_EXPOSURE_OFFSET_S)
}

/// [`fr1_pose_time_ns`] with the offset `EXPOSURE_OFFSET_MS` (milliseconds) from the
/// environment when set, for the examples.
#[allow(dead_code)]
pub fn fr1_pose_time_ns_from_env(capture_time_ns: u64) -> u64 {
    match std::env::var("EXPOSURE_OFFSET_MS") {
        Ok(ms) => stillmap_proto::pose_time_ns(capture_time_ns, ms.parse::<f64>().expect("EXPOSURE_OFFSET_MS: milliseconds") * 1e-3),
        Err(_) => fr1_pose_time_ns(capture_time_ns),
    }
}

/// [`fr1_camera`] with the rolling-shutter readout `READOUT_MS` (milliseconds; 0 =
/// a global shutter) from the environment when set, for the examples.
#[allow(dead_code)]
pub fn fr1_camera_with_readout_from_env() -> Camera {
    match std::env::var("READOUT_MS") {
        Ok(ms) => Camera { readout_s: ms.parse::<f64>().expect("READOUT_MS: milliseconds") * 1e-3, ..fr1_camera() },
        Err(_) => fr1_camera(),
    }
}

fn parse_ts(s: &str) -> u64 {
    let (sec, frac) = s.split_once('.').unwrap_or((s, "0"));
    let frac = format!("{frac:0<9}");
    sec.parse::<u64>().expect("seconds") * 1_000_000_000 + frac[..9].parse::<u64>().expect("fraction")
}

fn list(dir: &Path, name: &str) -> Vec<(u64, String)> {
    std::fs::read_to_string(dir.join(name))
        .unwrap_or_else(|e| panic!("{}: {e}", dir.join(name).display()))
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let mut it = l.split_whitespace();
            (parse_ts(it.next().expect("ts")), it.next().expect("file").to_string())
        })
        .collect()
}

/// Associates colour and depth like TUM's associate.py (greedy closest first, 20 ms).
pub fn load(dir: &Path, max_frames: usize) -> Vec<TumFrame> {
    let rgb = list(dir, "rgb.txt");
    let depth = list(dir, "depth.txt");
    let mut cands = Vec::new();
    for (i, (a, _)) in rgb.iter().enumerate() {
        for (j, (b, _)) in depth.iter().enumerate() {
            let d = a.abs_diff(*b);
            if d < 20_000_000 {
                cands.push((d, i, j));
            }
        }
    }
    cands.sort();
    let (mut ui, mut uj) = (vec![false; rgb.len()], vec![false; depth.len()]);
    let mut pairs = Vec::new();
    for (_, i, j) in cands {
        if !ui[i] && !uj[j] {
            ui[i] = true;
            uj[j] = true;
            pairs.push((i, j));
        }
    }
    pairs.sort();
    pairs
        .into_iter()
        .take(max_frames)
        .map(|(i, j)| {
            let c = std::fs::read(dir.join(&rgb[i].1)).expect("rgb");
            let d = std::fs::read(dir.join(&depth[j].1)).expect("depth");
            TumFrame {
                timestamp_ns: rgb[i].0,
                rgb: codec::decode_color(ColorEncoding::Png, &c, 640, 480).expect("decode rgb").data,
                depth: codec::decode_depth(DepthEncoding::Png16, &d, 640, 480).expect("decode depth").data,
            }
        })
        .collect()
}

/// Tracks `frames` with a fresh tracker; returns it (with its map) and the poses,
/// each at `pose_time_ns` of its frame's timestamp.
#[allow(dead_code)]
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

/// `groundtruth.txt` as (timestamp, world_from_camera).
pub fn groundtruth(dir: &Path) -> Vec<(u64, Isometry3<f64>)> {
    std::fs::read_to_string(dir.join("groundtruth.txt"))
        .expect("groundtruth")
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let v: Vec<&str> = l.split_whitespace().collect();
            let f = |i: usize| v[i].parse::<f64>().expect("number");
            let q = UnitQuaternion::from_quaternion(Quaternion::new(f(7), f(4), f(5), f(6)));
            (parse_ts(v[0]), Isometry3::from_parts(Translation3::new(f(1), f(2), f(3)), q))
        })
        .collect()
}

/// Scores of a trajectory against ground truth (evo semantics: nearest timestamp
/// within 20 ms, SE(3) Umeyama alignment for ATE; RPE over consecutive poses).
#[derive(Debug, Clone, Copy)]
pub struct Scores {
    pub pairs: usize,
    pub ate_m: f64,
    pub ate_deg: f64,
    pub ate_origin_deg: f64,
    pub rpe_m: f64,
    pub rpe_deg: f64,
}

pub fn score(gt: &[(u64, Isometry3<f64>)], est: &[(u64, Isometry3<f64>)]) -> Scores {
    let mut pairs = Vec::new();
    for (t, p) in est {
        let best = gt.iter().min_by_key(|(g, _)| g.abs_diff(*t)).expect("gt");
        if best.0.abs_diff(*t) <= 20_000_000 {
            pairs.push((best.1, *p));
        }
    }
    let n = pairs.len() as f64;
    let mu_g = pairs.iter().map(|(g, _)| g.translation.vector).sum::<Vector3<f64>>() / n;
    let mu_e = pairs.iter().map(|(_, e)| e.translation.vector).sum::<Vector3<f64>>() / n;
    let mut cov = Matrix3::zeros();
    for (g, e) in &pairs {
        cov += (g.translation.vector - mu_g) * (e.translation.vector - mu_e).transpose();
    }
    cov /= n;
    let svd = cov.svd(true, true);
    let (u, vt) = (svd.u.expect("u"), svd.v_t.expect("v"));
    let mut s = Matrix3::identity();
    if (u.determinant() * vt.determinant()) < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let r = u * s * vt;
    let t = mu_g - r * mu_e;
    let align = Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_matrix(&r));
    let origin = pairs[0].0 * pairs[0].1.inverse();
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
    let te: Vec<f64> = pairs.iter().map(|(g, e)| ((align * e).translation.vector - g.translation.vector).norm()).collect();
    let re: Vec<f64> = pairs.iter().map(|(g, e)| (g.inverse() * (align * e)).rotation.angle().to_degrees()).collect();
    let ro: Vec<f64> = pairs.iter().map(|(g, e)| (g.inverse() * (origin * e)).rotation.angle().to_degrees()).collect();
    let mut rt = Vec::new();
    let mut rr = Vec::new();
    for w in pairs.windows(2) {
        let dg = w[0].0.inverse() * w[1].0;
        let de = w[0].1.inverse() * w[1].1;
        let err = dg.inverse() * de;
        rt.push(err.translation.vector.norm());
        rr.push(err.rotation.angle().to_degrees());
    }
    Scores { pairs: pairs.len(), ate_m: rms(&te), ate_deg: rms(&re), ate_origin_deg: rms(&ro), rpe_m: rms(&rt), rpe_deg: rms(&rr) }
}

/// Writes `est` as a TUM trajectory file when the environment variable `EST`
/// names one (for evo or `stillmap-client eval`).
#[allow(dead_code)]
pub fn write_est_if_asked(est: &[(u64, Isometry3<f64>)]) {
    let Some(path) = std::env::var_os("EST") else { return };
    let text: String = est
        .iter()
        .map(|(t, p)| {
            let (q, v) = (p.rotation.coords, p.translation.vector);
            format!("{}.{:06} {} {} {} {} {} {} {}\n", t / 1_000_000_000, t % 1_000_000_000 / 1000, v.x, v.y, v.z, q.x, q.y, q.z, q.w)
        })
        .collect();
    std::fs::write(path, text).expect("write EST");
}
