//! Camera calibration: where a session's intrinsics come from.
//!
//! A source knows its image size, depth units and frame rate, and sometimes its
//! intrinsics (a TUM folder whose name says which freiburg camera recorded it, an
//! OpenNI2 device that reports its field of view). The user can name a known camera
//! (`--camera tum-fr1`) or give a calibration file (`--calibration FILE`: ROS
//! `camera_info` YAML, or OpenCV's `FileStorage` YAML, including ORB-SLAM's
//! `Camera.fx` settings). Nothing is guessed silently: a source whose intrinsics are
//! not known refuses to start unless `--allow-default-intrinsics` is given.
//!
//! Precedence: `--calibration` (intrinsics, size and distortion) over `--camera`
//! (intrinsics and the camera's timing) over what the source knows. The hello's
//! `CameraInfo.calibration_source` says which one was used.

use std::path::{Path, PathBuf};

use serde_yaml::Value;
use stillmap_proto::pb::{self, DistortionModel};

use crate::ClientError;

/// Largest calibration file read (a camera_info YAML is about 1 KB).
const MAX_CALIBRATION_FILE_BYTES: u64 = 1 << 20;

pub use stillmap_dataset::calibration::{
    KnownCamera, TUM_DEPTH_UNITS_PER_METRE, TUM_FREIBURG1_EXPOSURE_OFFSET_S, TUM_FREIBURG1_READOUT_S, TUM_RATE_HZ,
};

/// What a source knows about its camera before the user's options are applied.
#[derive(Debug, Clone)]
pub struct SourceCamera {
    /// Size, depth units and rate (always right), and intrinsics (right only when
    /// `known` is set; otherwise a nominal guess).
    pub info: pb::CameraInfo,
    /// Where `info`'s intrinsics came from, when they are known
    /// (`tum-folder:rgbd_dataset_freiburg1_rpy (tum-fr1)`, `device:...`).
    pub known: Option<String>,
    /// What the source is, for messages (`TUM folder rgbd_x`, `OpenNI2 device Dummy`).
    pub what: String,
}

/// The user's calibration options (`--calibration`, `--camera`, `--allow-default-intrinsics`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CameraOptions {
    pub calibration: Option<PathBuf>,
    pub camera: Option<KnownCamera>,
    pub allow_default_intrinsics: bool,
}

/// Intrinsics read from a calibration file.
#[derive(Debug, Clone, PartialEq)]
pub struct FileCalibration {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Plumb-bob coefficients k1 k2 p1 p2 k3; `None` when the file has none or all are 0.
    pub plumb_bob: Option<[f64; 5]>,
    /// `ROS camera_info`, `OpenCV`, or `ORB-SLAM settings`.
    pub format: &'static str,
}

impl FileCalibration {
    /// The file's intrinsics and distortion as the contract carries them.
    fn camera_info(&self) -> pb::CameraInfo {
        pb::CameraInfo {
            width: self.width,
            height: self.height,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            distortion_model: if self.plumb_bob.is_some() { DistortionModel::PlumbBob } else { DistortionModel::None } as i32,
            distortion_coeffs: self.plumb_bob.map(|c| c.to_vec()).unwrap_or_default(),
            ..Default::default()
        }
    }
}

/// Applies the user's options to what the source knows; the result carries its
/// `calibration_source`. Fails, naming the way out, when nothing is known.
pub fn resolve(source: SourceCamera, options: &CameraOptions) -> Result<pb::CameraInfo, ClientError> {
    let SourceCamera { mut info, known, what } = source;
    let mut origin = known;
    if let Some(camera) = options.camera {
        let preset = camera.camera_info();
        if (preset.width, preset.height) != (info.width, info.height) {
            return Err(ClientError::Usage(format!(
                "--camera {} is a {}x{} calibration but {what} delivers {}x{} images",
                camera.name(),
                preset.width,
                preset.height,
                info.width,
                info.height
            )));
        }
        set_intrinsics(&mut info, &preset);
        info.rolling_shutter_readout_s = preset.rolling_shutter_readout_s;
        info.exposure_time_offset_s = preset.exposure_time_offset_s;
        origin = Some(format!("preset:{} (--camera)", camera.name()));
    }
    if let Some(path) = &options.calibration {
        let file = load_file(path)?;
        if (file.width, file.height) != (info.width, info.height) {
            return Err(ClientError::Usage(format!(
                "calibration {} is for {}x{} images but {what} delivers {}x{}",
                path.display(),
                file.width,
                file.height,
                info.width,
                info.height
            )));
        }
        set_intrinsics(&mut info, &file.camera_info());
        origin = Some(format!("file:{} ({})", path.display(), file.format));
    }
    info.calibration_source = match origin {
        Some(origin) => origin,
        None if options.allow_default_intrinsics => {
            tracing::warn!("{what}: calibration unknown; using nominal intrinsics (--allow-default-intrinsics)");
            "default:nominal intrinsics (--allow-default-intrinsics)".to_string()
        }
        None => {
            return Err(ClientError::Usage(format!(
                "{what}: the camera's calibration is not known; give --calibration FILE (ROS camera_info or \
                 OpenCV YAML), --camera {}, or --allow-default-intrinsics to track with nominal intrinsics",
                KnownCamera::NAMES
            )));
        }
    };
    Ok(info)
}

fn set_intrinsics(info: &mut pb::CameraInfo, from: &pb::CameraInfo) {
    info.fx = from.fx;
    info.fy = from.fy;
    info.cx = from.cx;
    info.cy = from.cy;
    info.distortion_model = from.distortion_model;
    info.distortion_coeffs = from.distortion_coeffs.clone();
}

/// Reads and parses a calibration file; errors name the file and the problem.
pub fn load_file(path: &Path) -> Result<FileCalibration, ClientError> {
    let fail = |e: String| ClientError::Usage(format!("calibration {}: {e}", path.display()));
    let meta = std::fs::metadata(path).map_err(|e| fail(e.to_string()))?;
    if meta.len() > MAX_CALIBRATION_FILE_BYTES {
        return Err(fail(format!("{} bytes is too large for a calibration file", meta.len())));
    }
    let text = std::fs::read_to_string(path).map_err(|e| fail(e.to_string()))?;
    parse(&text).map_err(fail)
}

/// Parses a ROS `camera_info` YAML, an OpenCV `FileStorage` YAML (`camera_matrix` /
/// `distortion_coefficients` as `!!opencv-matrix`, `image_width` / `image_height`),
/// or ORB-SLAM's settings (`Camera.fx` … `Camera.k3`, `Camera.width`).
pub fn parse(text: &str) -> Result<FileCalibration, String> {
    // OpenCV writes a `%YAML:1.0` directive, which YAML parsers reject; it carries nothing.
    let body: String = text.lines().filter(|l| !l.trim_start().starts_with("%YAML")).collect::<Vec<_>>().join("\n");
    let body = body.trim_start().strip_prefix("---").unwrap_or(&body);
    let doc: Value = serde_yaml::from_str(body).map_err(|e| format!("not YAML: {e}"))?;
    let map = doc.as_mapping().ok_or("expected a YAML mapping of calibration keys")?;
    let get = |key: &str| map.get(key).map(untag);

    if let Some(k) = get("camera_matrix") {
        let k = matrix(k, "camera_matrix", 9)?;
        if k[1] != 0.0 || k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || k[8] != 1.0 {
            return Err(format!("camera_matrix {k:?} is not a pinhole matrix [fx 0 cx; 0 fy cy; 0 0 1]"));
        }
        let width = get("image_width").ok_or("no image_width")?;
        let height = get("image_height").ok_or("no image_height")?;
        let (ros, format) = match get("distortion_model") {
            Some(_) => (true, "ROS camera_info"),
            None => (false, "OpenCV"),
        };
        if ros {
            let model = get("distortion_model").and_then(Value::as_str).ok_or("distortion_model is not a string")?;
            if model != "plumb_bob" {
                return Err(format!("distortion_model {model:?} is not supported (plumb_bob only)"));
            }
        }
        let coeffs = match get("distortion_coefficients").or_else(|| get("dist_coeffs")) {
            Some(d) => matrix_any(d, "distortion_coefficients")?,
            None => vec![],
        };
        return finish(FileCalibration {
            width: size(width, "image_width")?,
            height: size(height, "image_height")?,
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
            plumb_bob: plumb_bob(&coeffs)?,
            format,
        });
    }
    if get("Camera.fx").is_some() || get("Camera1.fx").is_some() {
        let prefix = if get("Camera1.fx").is_some() { "Camera1" } else { "Camera" };
        let num = |name: &str| -> Result<f64, String> {
            let key = format!("{prefix}.{name}");
            get(&key).and_then(Value::as_f64).ok_or(format!("no number {key}"))
        };
        let opt = |name: &str| get(&format!("{prefix}.{name}")).and_then(Value::as_f64);
        let coeffs: Vec<f64> = ["k1", "k2", "p1", "p2", "k3"].iter().map(|n| opt(n).unwrap_or(0.0)).collect();
        let w = get("Camera.width").ok_or("no Camera.width")?;
        let h = get("Camera.height").ok_or("no Camera.height")?;
        return finish(FileCalibration {
            width: size(w, "Camera.width")?,
            height: size(h, "Camera.height")?,
            fx: num("fx")?,
            fy: num("fy")?,
            cx: num("cx")?,
            cy: num("cy")?,
            plumb_bob: plumb_bob(&coeffs)?,
            format: "ORB-SLAM settings",
        });
    }
    Err("no camera_matrix (ROS camera_info, OpenCV) or Camera.fx (ORB-SLAM) key".into())
}

fn finish(c: FileCalibration) -> Result<FileCalibration, String> {
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if !positive(c.fx) || !positive(c.fy) {
        return Err(format!("focal lengths must be positive, got fx={} fy={}", c.fx, c.fy));
    }
    if !c.cx.is_finite() || !c.cy.is_finite() {
        return Err("principal point is not finite".into());
    }
    // As the server's hello checks it: a principal point off the image is a
    // calibration of another camera (or of pixels in another unit).
    if !((0.0..=f64::from(c.width)).contains(&c.cx) && (0.0..=f64::from(c.height)).contains(&c.cy)) {
        return Err(format!("principal point ({}, {}) lies outside the {}x{} image", c.cx, c.cy, c.width, c.height));
    }
    Ok(c)
}

/// A tagged value (`!!opencv-matrix {...}`) as its inner value.
fn untag(v: &Value) -> &Value {
    match v {
        Value::Tagged(t) => &t.value,
        v => v,
    }
}

fn size(v: &Value, name: &str) -> Result<u32, String> {
    v.as_u64().and_then(|n| u32::try_from(n).ok()).filter(|&n| n > 0).ok_or(format!("{name} must be a positive integer, got {v:?}"))
}

/// A matrix as `{rows, cols, data: [...]}` (ROS and OpenCV) or a plain list.
fn matrix_any(v: &Value, name: &str) -> Result<Vec<f64>, String> {
    let v = untag(v);
    let data = match v {
        Value::Mapping(m) => {
            let data = m.get("data").ok_or(format!("{name} has no data"))?;
            let rows = m.get("rows").and_then(Value::as_u64);
            let cols = m.get("cols").and_then(Value::as_u64);
            let list = data.as_sequence().ok_or(format!("{name}.data is not a list"))?;
            if let (Some(r), Some(c)) = (rows, cols)
                && r.checked_mul(c) != Some(list.len() as u64)
            {
                return Err(format!("{name} declares {r}x{c} but holds {} numbers", list.len()));
            }
            list
        }
        Value::Sequence(list) => list,
        _ => return Err(format!("{name} is not a matrix")),
    };
    data.iter().map(|x| x.as_f64().ok_or(format!("{name} holds a non-number {x:?}"))).collect()
}

fn matrix(v: &Value, name: &str, len: usize) -> Result<Vec<f64>, String> {
    let m = matrix_any(v, name)?;
    if m.len() != len {
        return Err(format!("{name} must hold {len} numbers, got {}", m.len()));
    }
    Ok(m)
}

/// Coefficients in OpenCV order; 4 (k3 = 0) or 5 are plumb bob, all zero is none.
fn plumb_bob(coeffs: &[f64]) -> Result<Option<[f64; 5]>, String> {
    if coeffs.iter().any(|c| !c.is_finite()) {
        return Err("distortion coefficients must be finite".into());
    }
    let c = match coeffs.len() {
        0 => return Ok(None),
        4 => [coeffs[0], coeffs[1], coeffs[2], coeffs[3], 0.0],
        5 => [coeffs[0], coeffs[1], coeffs[2], coeffs[3], coeffs[4]],
        // OpenCV's rational and thin-prism models: usable only when the extra terms are 0.
        n if n > 5 && coeffs[5..].iter().all(|&c| c == 0.0) => [coeffs[0], coeffs[1], coeffs[2], coeffs[3], coeffs[4]],
        n => return Err(format!("{n} distortion coefficients: only plumb_bob (k1 k2 p1 p2 [k3]) is supported")),
    };
    Ok(c.iter().any(|&x| x != 0.0).then_some(c))
}

#[cfg(test)]
mod tests {
    use super::*;

    const ROS: &str = "image_width: 640
image_height: 480
camera_name: kinect_rgb
camera_matrix:
  rows: 3
  cols: 3
  data: [517.3, 0, 318.6, 0, 516.5, 255.3, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [517.3, 0, 318.6, 0, 0, 516.5, 255.3, 0, 0, 0, 1, 0]
";

    const OPENCV: &str = "%YAML:1.0
---
calibration_time: \"Thu 03 Dec 2026\"
image_width: 320
image_height: 240
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 2.6e+02, 0., 1.6e+02, 0., 2.61e+02, 1.2e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ 0.1, -0.2, 0., 0., 0. ]
";

    const ORB_SLAM: &str = "%YAML:1.0
Camera.type: \"PinHole\"
Camera.fx: 535.4
Camera.fy: 539.2
Camera.cx: 320.1
Camera.cy: 247.6
Camera.k1: 0.0
Camera.k2: 0.0
Camera.p1: 0.0
Camera.p2: 0.0
Camera.width: 640
Camera.height: 480
";

    #[test]
    fn reads_ros_camera_info() {
        let c = parse(ROS).expect("parses");
        assert_eq!((c.width, c.height, c.fx, c.fy, c.cx, c.cy), (640, 480, 517.3, 516.5, 318.6, 255.3));
        assert_eq!(c.plumb_bob, Some([0.2624, -0.9531, -0.0054, 0.0026, 1.1633]));
        assert_eq!(c.format, "ROS camera_info");
    }

    #[test]
    fn reads_opencv_and_orb_slam_yaml() {
        let c = parse(OPENCV).expect("parses");
        assert_eq!((c.width, c.height, c.fx, c.fy, c.cx, c.cy), (320, 240, 260.0, 261.0, 160.0, 120.0));
        assert_eq!(c.plumb_bob, Some([0.1, -0.2, 0.0, 0.0, 0.0]));
        assert_eq!(c.format, "OpenCV");
        let c = parse(ORB_SLAM).expect("parses");
        assert_eq!((c.width, c.height, c.fx, c.fy, c.cx, c.cy), (640, 480, 535.4, 539.2, 320.1, 247.6));
        assert_eq!(c.plumb_bob, None, "all-zero coefficients are no distortion");
        assert_eq!(c.format, "ORB-SLAM settings");
    }

    #[test]
    fn bad_files_are_named_errors() {
        assert_eq!(parse("just text").unwrap_err(), "expected a YAML mapping of calibration keys");
        assert_eq!(
            parse(&ROS.replace("plumb_bob", "equidistant")).unwrap_err(),
            "distortion_model \"equidistant\" is not supported (plumb_bob only)"
        );
        assert_eq!(
            parse(&ROS.replace("517.3, 0, 318.6", "517.3, 0, 318.6, 1")).unwrap_err(),
            "camera_matrix declares 3x3 but holds 10 numbers"
        );
        assert_eq!(
            parse(&ROS.replace("516.5, 255.3", "-516.5, 255.3")).unwrap_err(),
            "focal lengths must be positive, got fx=517.3 fy=-516.5"
        );
        assert_eq!(parse(&ROS.replace("image_width: 640\n", "")).unwrap_err(), "no image_width");
        assert_eq!(
            parse(&ROS.replace("image_width: 640", "image_width: 300")).unwrap_err(),
            "principal point (318.6, 255.3) lies outside the 300x480 image"
        );
        assert_eq!(
            parse(&ROS.replace("image_height: 480", "image_height: -4")).unwrap_err(),
            "image_height must be a positive integer, got Number(-4)"
        );
        assert!(parse("a: [1, 2").unwrap_err().starts_with("not YAML: "));
        assert_eq!(parse("fx: 1").unwrap_err(), "no camera_matrix (ROS camera_info, OpenCV) or Camera.fx (ORB-SLAM) key");
        let eight = ROS.replace(
            "rows: 1\n  cols: 5\n  data: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]",
            "rows: 1\n  cols: 8\n  data: [0.1, 0, 0, 0, 0, 0.5, 0, 0]",
        );
        assert_eq!(parse(&eight).unwrap_err(), "8 distortion coefficients: only plumb_bob (k1 k2 p1 p2 [k3]) is supported");
    }

    fn tum_like(known: Option<&str>) -> SourceCamera {
        let mut info = KnownCamera::TumFr1.camera_info();
        if known.is_none() {
            (info.fx, info.fy, info.cx, info.cy) = (525.0, 525.0, 319.5, 239.5);
            info.distortion_model = DistortionModel::None as i32;
            info.distortion_coeffs.clear();
            info.rolling_shutter_readout_s = 0.0;
            info.exposure_time_offset_s = 0.0;
        }
        SourceCamera { info, known: known.map(str::to_owned), what: "TUM folder renamed".into() }
    }

    #[test]
    fn unknown_calibration_refuses_unless_allowed() {
        let e = resolve(tum_like(None), &CameraOptions::default()).unwrap_err().to_string();
        assert!(e.contains("TUM folder renamed: the camera's calibration is not known; give --calibration FILE"), "{e}");
        let allowed = CameraOptions { allow_default_intrinsics: true, ..Default::default() };
        let c = resolve(tum_like(None), &allowed).expect("allowed");
        assert_eq!((c.fx, c.cx), (525.0, 319.5));
        assert_eq!(c.calibration_source, "default:nominal intrinsics (--allow-default-intrinsics)");
        let c = resolve(tum_like(Some("tum-folder:x (tum-fr1)")), &CameraOptions::default()).expect("known");
        assert_eq!(c.calibration_source, "tum-folder:x (tum-fr1)");
    }

    #[test]
    fn preset_and_file_take_precedence() {
        let preset = CameraOptions { camera: Some(KnownCamera::TumFr1), ..Default::default() };
        let c = resolve(tum_like(None), &preset).expect("preset");
        assert_eq!((c.fx, c.fy, c.cx, c.cy), (517.3, 516.5, 318.6, 255.3));
        assert_eq!(c.rolling_shutter_readout_s, TUM_FREIBURG1_READOUT_S, "the preset's timing comes along");
        assert_eq!(c.calibration_source, "preset:tum-fr1 (--camera)");

        let dir = std::env::temp_dir().join(format!("stillmap-calib-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let ros = dir.join("rgb.yaml");
        std::fs::write(&ros, ROS.replace("517.3, 0", "500.0, 0")).expect("write");
        let both = CameraOptions { calibration: Some(ros.clone()), camera: Some(KnownCamera::TumFr1), ..Default::default() };
        let c = resolve(tum_like(None), &both).expect("file");
        assert_eq!(c.fx, 500.0, "the file's intrinsics win over the preset's");
        assert_eq!(c.rolling_shutter_readout_s, TUM_FREIBURG1_READOUT_S, "the preset still gives the timing");
        assert_eq!(c.calibration_source, format!("file:{} (ROS camera_info)", ros.display()));

        let small = dir.join("small.yaml");
        std::fs::write(&small, OPENCV).expect("write");
        let e = resolve(tum_like(None), &CameraOptions { calibration: Some(small.clone()), ..Default::default() }).unwrap_err().to_string();
        assert_eq!(e, format!("calibration {} is for 320x240 images but TUM folder renamed delivers 640x480", small.display()));
        let missing = dir.join("missing.yaml");
        let e =
            resolve(tum_like(None), &CameraOptions { calibration: Some(missing.clone()), ..Default::default() }).unwrap_err().to_string();
        assert!(e.starts_with(&format!("calibration {}: ", missing.display())), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn known_cameras() {
        assert_eq!("tum-fr2".parse(), Ok(KnownCamera::TumFr2));
        assert_eq!("fr2".parse::<KnownCamera>().unwrap_err(), "unknown camera \"fr2\": use tum-fr1|tum-fr2|tum-fr3");
        assert_eq!(KnownCamera::from_tum_folder_name("rgbd_dataset_freiburg1_rpy_b"), Some(KnownCamera::TumFr1));
        assert_eq!(KnownCamera::from_tum_folder_name("my_sequence"), None);
        let c = KnownCamera::TumFr1.camera_info();
        assert_eq!((c.fx, c.fy, c.cx, c.cy), (517.3, 516.5, 318.6, 255.3));
        assert_eq!(c.distortion_coeffs.len(), 5);
        assert_eq!(c.rolling_shutter_readout_s, 0.025);
        assert_eq!(c.exposure_time_offset_s, -0.0125, "stamped on arrival, after the last row");
        let c = KnownCamera::TumFr3.camera_info();
        assert_eq!(c.distortion_model(), DistortionModel::None);
        assert_eq!(c.rolling_shutter_readout_s, 0.0, "not measured: sent as a global shutter");
        assert_eq!(c.exposure_time_offset_s, 0.0, "not measured");
    }
}
