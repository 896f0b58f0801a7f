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
    /// `mcap:<file>` (ROS 2) or `rosbag:<file>` (ROS 1): a recording, and which of its topics to read.
    Bag(crate::bag::BagFormat, std::path::PathBuf, crate::bag::BagTopics),
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
        for (scheme, format, example) in
            [("mcap:", crate::bag::BagFormat::Mcap, "recording.mcap"), ("rosbag:", crate::bag::BagFormat::Ros1, "recording.bag")]
        {
            if let Some(file) = s.strip_prefix(scheme) {
                if file.is_empty() {
                    return Err(format!("{scheme} needs a file, e.g. {scheme}{example}"));
                }
                return Ok(Self::Bag(format, file.into(), crate::bag::BagTopics::default()));
            }
        }
        if s == "openni2" {
            return Ok(Self::OpenNi2(None));
        }
        if let Some(uri) = s.strip_prefix("openni2:") {
            return Ok(Self::OpenNi2((!uri.is_empty()).then(|| uri.to_string())));
        }
        Err(format!("unknown source {s:?}: use tum:<dir>, mcap:<file>, rosbag:<file>, openni2 or openni2:<uri>"))
    }
}

/// Opens a source. Call it on the thread that will read it.
pub fn open(spec: &SourceSpec, max_frames: Option<usize>, camera: &CameraOptions) -> Result<Box<dyn FrameSource>, ClientError> {
    match spec {
        SourceSpec::Tum(dir) => Ok(Box::new(crate::tum::TumSource::open(dir, max_frames, camera)?)),
        SourceSpec::Bag(format, file, topics) => Ok(Box::new(crate::bag::BagSource::open(file, *format, topics, max_frames, camera)?)),
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
        let bag = |f, p: &str| SourceSpec::Bag(f, p.into(), crate::bag::BagTopics::default());
        assert_eq!("mcap:a.mcap".parse(), Ok(bag(crate::bag::BagFormat::Mcap, "a.mcap")));
        assert_eq!("rosbag:a.bag".parse(), Ok(bag(crate::bag::BagFormat::Ros1, "a.bag")));
        assert!("mcap:".parse::<SourceSpec>().is_err());
        assert!("kinect".parse::<SourceSpec>().unwrap_err().contains("unknown source \"kinect\""));
    }
}
