//! Recorded data and how it is scored, shared by the client, the server, the tests
//! and the benches:
//!
//! - [`tum`]: TUM RGB-D folders (list files, colour/depth association like
//!   `associate.py`, decoded frames, the accelerometer, the ground truth);
//! - [`calibration`]: the cameras stillmap ships a calibration for (`--camera`);
//! - [`trajectory`]: TUM trajectory files, read and written;
//! - [`eval`]: what evo's `evo_ape` / `evo_rpe` compute, and the summary score the
//!   accuracy tests print;
//! - [`shared`]: where the data and models beside the repository (`../shared`) are.
//!
//! Everything here reads files; nothing here tracks, segments or maps.

pub mod calibration;
pub mod eval;
pub mod shared;
pub mod trajectory;
pub mod tum;

use std::path::PathBuf;

/// Errors of reading recorded data and of evaluating trajectories.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// Invalid options.
    #[error("{0}")]
    Usage(String),
    /// A file or folder cannot be read.
    #[error("cannot read {}: {source}", path.display())]
    Read { path: PathBuf, source: std::io::Error },
    /// A malformed line in a list or trajectory file (1-based line number).
    #[error("{}:{line}: {message}", path.display())]
    Parse { path: PathBuf, line: usize, message: String },
    /// A trajectory file without poses.
    #[error("{}: no poses (expected lines `timestamp tx ty tz qx qy qz qw`)", path.display())]
    Empty { path: PathBuf },
    /// A line of a TUM list file with a timestamp and no file name.
    #[error("{}: the line for timestamp {timestamp_ns} ns names no file", list.display())]
    MissingFile { list: PathBuf, timestamp_ns: u64 },
    /// A TUM folder in which no colour image has a depth image within 20 ms.
    #[error("{}: no colour/depth pair within 20 ms", path.display())]
    NoFrames { path: PathBuf },
    /// An image file that does not decode as the sequence says it should.
    #[error("{}: {message}", path.display())]
    Decode { path: PathBuf, message: String },
    /// No estimated pose is close enough in time to a reference pose.
    #[error("no matching timestamps between reference and estimate (max diff {max_diff} s, offset {offset} s)")]
    NoMatches { max_diff: f64, offset: f64 },
    /// Umeyama alignment needs positions that span at least a plane.
    #[error("cannot align {points} associated positions: degenerate covariance (they do not span a plane)")]
    Degenerate { points: usize },
    /// The RPE delta leaves no pose pairs.
    #[error("delta {delta} frames leaves no pose pairs among {poses} associated poses")]
    NoPairs { delta: usize, poses: usize },
    /// An output file cannot be written.
    #[error("cannot write {}: {message}", path.display())]
    Write { path: PathBuf, message: String },
}
