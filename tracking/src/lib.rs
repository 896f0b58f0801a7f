//! stillmap camera tracking, free of network and file I/O (the `testing` feature
//! adds test support that reads the public clips).
//!
//! [`Tracker`] estimates `world_from_camera` for every RGB-D frame from ORB
//! features outside the dynamic mask, against a local map of keyframes and points
//! refined by sliding-window bundle adjustment (see ARCHITECTURE.md).

pub mod ba;
pub mod camera;
pub mod config;
pub mod dense;
pub mod features;
pub mod geometry;
pub mod map;
pub mod optimize;
#[cfg(any(test, feature = "testing"))]
pub mod synthetic;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod tracker;

pub use camera::Camera;
pub use config::TrackerConfig;
pub use tracker::{FrameInput, StageTimes, TrackOutput, Tracker, TrackingState};

/// Threads OpenCV's parallel loops may use, process-wide (`cv::setNumThreads`;
/// 0 keeps OpenCV's default, one per core). A server that already runs one
/// session per core sets 1, so N sessions do not oversubscribe the cores.
pub fn set_opencv_threads(threads: usize) -> Result<(), TrackingError> {
    if threads == 0 {
        return Ok(());
    }
    let n = i32::try_from(threads).map_err(|_| TrackingError::Config(format!("{threads} OpenCV threads")))?;
    opencv::core::set_num_threads(n)?;
    Ok(())
}

/// Errors of the tracking crate.
#[derive(Debug, thiserror::Error)]
pub enum TrackingError {
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
    #[error("bad tracking input: {0}")]
    Input(String),
    #[error("bad tracking configuration: {0}")]
    Config(String),
    #[error("cannot start a tracking thread: {0}")]
    Thread(std::io::Error),
}
