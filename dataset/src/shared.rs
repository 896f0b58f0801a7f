//! Where the data and models beside the repository are: `../shared` next to the
//! checkout (`shared/data/tum/…`, `shared/models/…`), or the folder `SHARED` names
//! (the Makefile's and the scripts' variable); the public clip itself may be moved
//! with `TUM`. Relative paths in either are taken from the repository's root. For
//! tests, benches, examples and the demo; the server and client take paths.

use std::path::{Path, PathBuf};

/// The repository's root.
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn from_env(name: &str) -> Option<PathBuf> {
    std::env::var_os(name).filter(|v| !v.is_empty()).map(|v| repo().join(v))
}

/// The shared folder: `SHARED`, else `../shared` beside the repository.
pub fn dir() -> PathBuf {
    from_env("SHARED").unwrap_or_else(|| repo().join("../shared"))
}

/// A TUM RGB-D sequence folder in the shared data (`rgbd_dataset_freiburg1_rpy`).
pub fn tum_sequence(name: &str) -> PathBuf {
    dir().join("data/tum").join(name)
}

/// The public clip most tests use, frames 0–149 of freiburg1_rpy: `TUM`, else in
/// the shared data.
pub fn fr1_rpy() -> PathBuf {
    from_env("TUM").unwrap_or_else(|| tum_sequence("rgbd_dataset_freiburg1_rpy"))
}

/// The clip's continuation, frames 150–299 of the same recording: beside [`fr1_rpy`].
pub fn fr1_rpy_b() -> PathBuf {
    fr1_rpy().with_file_name("rgbd_dataset_freiburg1_rpy_b")
}

/// A file in the shared models folder (`yolov8n-seg_fp32_640.onnx`, `images/…`).
pub fn model(name: &str) -> PathBuf {
    dir().join("models").join(name)
}
