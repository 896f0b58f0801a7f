//! Frame sources: where RGB-D frames come from before they are encoded.

use stillmap_proto::codec::{ColorImage, DepthImage};
use stillmap_proto::pb;

use crate::ClientError;
use crate::calibration::CameraOptions;

/// One captured RGB-D frame, depth registered to colour.
#[derive(Debug, Clone)]
pub struct RawFrame {
    /// Capture time on the sensor clock, nanoseconds.
    pub capture_time_ns: u64,
    pub color: ColorImage,
    pub depth: DepthImage,
    /// Nearest accelerometer sample, m/s², camera frame.
    pub accel_in_camera: Option<[f64; 3]>,
}

/// A camera or a recording. Runs on one thread (OpenNI2 handles are not `Send`).
pub trait FrameSource {
    /// The camera's intrinsics and size, resolved with the user's calibration
    /// options (`calibration::resolve`); encodings are filled in by the streamer.
    fn camera(&self) -> pb::CameraInfo;
    /// Frames in this source when known (recordings), for the progress bar.
    fn len_hint(&self) -> Option<usize>;
    /// The next frame; `None` at the end of a recording.
    fn next_frame(&mut self) -> Result<Option<RawFrame>, ClientError>;
}

/// A parsed `--source` value.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SourceSpec {
    /// `tum:<dir>`: a TUM RGB-D sequence folder.
    Tum(std::path::PathBuf),
    /// `openni2` or `openni2:<uri>`: a device (`Dummy` is OpenNI2's hardware-free one).
    OpenNi2(Option<String>),
    /// `mcap:<file>`: a ROS 2 recording, and which of its topics to read.
    Mcap(std::path::PathBuf, crate::bag::BagTopics),
}

impl std::str::FromStr for SourceSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if let Some(dir) = s.strip_prefix("tum:") {
            if dir.is_empty() {
                return Err("tum: needs a folder, e.g. tum:data/rgbd_dataset_freiburg1_rpy".into());
            }
            return Ok(Self::Tum(dir.into()));
        }
        if let Some(file) = s.strip_prefix("mcap:") {
            if file.is_empty() {
                return Err("mcap: needs a file, e.g. mcap:recording.mcap".into());
            }
            return Ok(Self::Mcap(file.into(), crate::bag::BagTopics::default()));
        }
        if s == "openni2" {
            return Ok(Self::OpenNi2(None));
        }
        if let Some(uri) = s.strip_prefix("openni2:") {
            return Ok(Self::OpenNi2((!uri.is_empty()).then(|| uri.to_string())));
        }
        Err(format!("unknown source {s:?}: use tum:<dir>, mcap:<file>, openni2 or openni2:<uri>"))
    }
}

/// Opens a source. Call it on the thread that will read it.
pub fn open(spec: &SourceSpec, max_frames: Option<usize>, camera: &CameraOptions) -> Result<Box<dyn FrameSource>, ClientError> {
    match spec {
        SourceSpec::Tum(dir) => Ok(Box::new(crate::tum::TumSource::open(dir, max_frames, camera)?)),
        SourceSpec::Mcap(file, topics) => Ok(Box::new(crate::bag::McapSource::open(file, topics, max_frames, camera)?)),
        #[cfg(feature = "openni2")]
        SourceSpec::OpenNi2(uri) => Ok(Box::new(crate::openni::OpenNiSource::open(uri.as_deref(), max_frames, camera)?)),
        #[cfg(not(feature = "openni2"))]
        SourceSpec::OpenNi2(_) => Err(ClientError::Source("this client was built without the openni2 feature".into())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_sources() {
        assert_eq!("tum:/a/b".parse(), Ok(SourceSpec::Tum("/a/b".into())));
        assert_eq!("openni2".parse(), Ok(SourceSpec::OpenNi2(None)));
        assert_eq!("openni2:Dummy".parse(), Ok(SourceSpec::OpenNi2(Some("Dummy".into()))));
        assert_eq!("mcap:a.mcap".parse(), Ok(SourceSpec::Mcap("a.mcap".into(), crate::bag::BagTopics::default())));
        assert!("mcap:".parse::<SourceSpec>().is_err());
        assert!("kinect".parse::<SourceSpec>().unwrap_err().contains("unknown source \"kinect\""));
    }
}
