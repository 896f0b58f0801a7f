//! stillmap perception, free of network I/O (the model file is the one file it reads).
//!
//! - [`segment`]: the [`Segmenter`] trait and [`YoloSegmenter`] (YOLOv8-seg on ONNX Runtime),
//!   with the tensor contract in [`yolo`].
//! - [`flow`]: Farneback dense flow on a subsampled grey image (OpenCV).
//! - [`ego`]: ego-motion compensation: predicted flow from depth and camera motion, residuals
//!   scaled by the depth uncertainty.
//! - [`fusion`]: the paper's four cases with the 3×3 neighbourhood test, per pixel and per instance.
//! - [`warp`]: carrying a late segmentation forward through the flow.
//! - [`masker`]: the per-session state machine tying them together.
//! - [`origins`]: recent keyframes' pixels followed through the flow, to take moving things back out of the map.
//! - `composite` (feature `testing`): pastes a moving textured plane into real RGB-D frames with exact masks (tests, benches).
//! - `testing` (feature `testing`): the real model and photos, and the composite runs the tests and benches of perception and mapping share.

#[cfg(any(test, feature = "testing"))]
pub mod composite;
pub mod config;
pub mod ego;
pub mod flow;
pub mod fusion;
pub mod masker;
pub mod origins;
pub mod segment;
#[cfg(feature = "testing")]
pub mod testing;
pub mod warp;
pub mod yolo;

pub use config::PerceptionConfig;
pub use fusion::{Fused, InstanceState, PixelLabel};
pub use masker::{DynamicMasker, MaskOutput, MaskSource, MaskerInput};
pub use origins::Retraction;
pub use segment::{Instance, Segmentation, Segmenter, YoloSegmenter};

/// Errors of the perception crate.
#[derive(Debug, thiserror::Error)]
pub enum PerceptionError {
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
    /// The segmentation model file: missing, unreadable, or not the expected kind.
    #[error("{0}")]
    Model(String),
    /// ONNX Runtime itself: library missing or inference failing.
    #[error("ONNX Runtime: {0}")]
    Runtime(String),
    #[error("bad perception input: {0}")]
    Input(String),
    #[error("bad perception configuration: {0}")]
    Config(String),
}
