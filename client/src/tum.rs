//! A TUM RGB-D folder as a frame source (the folder reading and the colour/depth
//! association are `stillmap_dataset::tum`'s): which camera the folder's name says
//! recorded it, and the frames at the resolved camera's size.

use std::path::Path;

use stillmap_dataset::calibration::{TUM_DEPTH_UNITS_PER_METRE, TUM_RATE_HZ, nominal_camera_info};
use stillmap_dataset::tum::{self, FrameFiles};
use stillmap_proto::codec;
use stillmap_proto::pb;

use crate::ClientError;
use crate::calibration::{CameraOptions, KnownCamera, SourceCamera};
use crate::source::{FrameSource, RawFrame};

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
            info: pb::CameraInfo { nominal_rate_hz: TUM_RATE_HZ, ..nominal_camera_info(640, 480, TUM_DEPTH_UNITS_PER_METRE) },
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
    frames: Vec<FrameFiles>,
    next: usize,
    camera: pb::CameraInfo,
}

impl TumSource {
    pub fn open(dir: &Path, max_frames: Option<usize>, options: &CameraOptions) -> Result<Self, ClientError> {
        if !dir.is_dir() {
            return Err(ClientError::Source(format!("TUM folder {} does not exist", dir.display())));
        }
        let mut frames = tum::read_sequence(dir).map_err(|e| ClientError::Source(e.to_string()))?;
        if let Some(max) = max_frames {
            frames.truncate(max);
        }
        let camera = crate::calibration::resolve(tum_camera(dir), options)?;
        Ok(Self { frames, next: 0, camera })
    }

    /// Capture times of the associated frames, in order.
    pub fn timestamps(&self) -> impl Iterator<Item = u64> + '_ {
        self.frames.iter().map(|f| f.timestamp_ns)
    }
}

impl FrameSource for TumSource {
    fn camera(&self) -> pb::CameraInfo {
        self.camera.clone()
    }

    fn len_hint(&self) -> Option<usize> {
        Some(self.frames.len())
    }

    fn next_frame(&mut self) -> Result<Option<RawFrame>, ClientError> {
        let Some(f) = self.frames.get(self.next) else {
            return Ok(None);
        };
        self.next += 1;
        let (w, h) = (self.camera.width, self.camera.height);
        let source = |e: stillmap_dataset::DatasetError| ClientError::Source(e.to_string());
        let color = tum::read_image(&f.rgb, |b| codec::decode_color(pb::ColorEncoding::Png, b, w, h)).map_err(source)?;
        let depth = tum::read_image(&f.depth, |b| codec::decode_depth(pb::DepthEncoding::Png16, b, w, h)).map_err(source)?;
        Ok(Some(RawFrame { capture_time_ns: f.timestamp_ns, color, depth, accel_in_camera: f.accel_in_camera }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let real = stillmap_dataset::shared::fr1_rpy();
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
