//! Where the data and models beside the repository are: `../shared` next to the
//! checkout (`shared/data/tum/…`, `shared/models/…`), or `STILLMAP_SHARED` when set.
//! For tests, benches, examples and the demo; the server and client take paths.

use std::path::{Path, PathBuf};

/// The shared folder: `STILLMAP_SHARED`, else `../shared` beside the repository.
pub fn dir() -> PathBuf {
    match std::env::var_os("STILLMAP_SHARED") {
        Some(d) => PathBuf::from(d),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared"),
    }
}

/// A TUM RGB-D sequence folder in the shared data (`rgbd_dataset_freiburg1_rpy`).
pub fn tum_sequence(name: &str) -> PathBuf {
    dir().join("data/tum").join(name)
}

/// The public clip most tests use: frames 0–149 of freiburg1_rpy.
pub fn fr1_rpy() -> PathBuf {
    tum_sequence("rgbd_dataset_freiburg1_rpy")
}

/// The clip's continuation: frames 150–299 of the same recording.
pub fn fr1_rpy_b() -> PathBuf {
    tum_sequence("rgbd_dataset_freiburg1_rpy_b")
}

/// A file in the shared models folder (`yolov8n-seg_fp32_640.onnx`, `images/…`).
pub fn model(name: &str) -> PathBuf {
    dir().join("models").join(name)
}
