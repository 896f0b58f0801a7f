//! Test, bench and example support (the `testing` feature): the real model, the
//! ONNX Runtime library and the real photos from `../shared/models` (see MODELS.md
//! there), the composite runs of [`composite_run`] and the board scene of [`boards`].

pub mod boards;
pub mod composite_run;

use std::path::{Path, PathBuf};

use crate::config::SegmentationConfig;
use opencv::imgcodecs;
use opencv::imgproc;
use opencv::prelude::*;

/// A file in the shared models folder.
pub fn model(name: &str) -> PathBuf {
    stillmap_dataset::shared::model(name)
}

/// `ORT_DYLIB_PATH`, else the library `deploy/install-deps.sh` puts in `.deps/ort`.
pub fn onnxruntime_library() -> String {
    std::env::var("ORT_DYLIB_PATH")
        .unwrap_or_else(|_| Path::new(env!("CARGO_MANIFEST_DIR")).join("../.deps/ort/libonnxruntime.so.1.31.1").display().to_string())
}

pub fn segmentation_config(model_file: &str) -> SegmentationConfig {
    SegmentationConfig {
        model_path: model(model_file).display().to_string(),
        onnxruntime_library: onnxruntime_library(),
        ..SegmentationConfig::default()
    }
}

/// Decodes a photo as RGB8 (OpenCV reads BGR).
pub fn photo(name: &str) -> (Vec<u8>, u32, u32) {
    let path = model("images").join(name);
    let bgr = imgcodecs::imread(path.to_str().expect("utf-8 path"), imgcodecs::IMREAD_COLOR).expect("imread");
    assert!(!bgr.empty(), "cannot read {}", path.display());
    let mut rgb = Mat::default();
    imgproc::cvt_color(&bgr, &mut rgb, imgproc::COLOR_BGR2RGB, 0).expect("cvtColor");
    let (w, h) = (rgb.cols() as u32, rgb.rows() as u32);
    (rgb.data_bytes().expect("continuous").to_vec(), w, h)
}
