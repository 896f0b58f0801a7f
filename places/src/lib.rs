//! stillmap place recognition, free of network and file I/O (the `training`
//! feature adds the vocabulary's build step, which reads the public clip).
//!
//! The pipeline, one typed step each:
//! 1. [`Vocabulary`]: a tree of binary words trained by hierarchical k-majority
//!    over ORB descriptors (deterministic for a seed), turning a keyframe's
//!    descriptors into a TF-IDF [`BowVector`].
//! 2. [`PlaceIndex`]: an inverted index (word → keyframes holding it) that answers
//!    "which stored keyframes look like this one" touching only keyframes that
//!    share words with the query.
//! 3. [`verify()`]: descriptor matching, PnP-RANSAC on the candidate's points with
//!    depth, robust pose optimisation and minimum inliers: a candidate becomes a
//!    [`Verified`] relative pose or nothing.
//! 4. [`MergeDetector`]: a session joins a fleet frame only when several of its
//!    keyframes, verified against the fleet's, agree on one `fleet_from_session`.
//! 5. [`PoseGraph`]: odometry, loop and inter-session edges between keyframes,
//!    solved with a robust kernel (factrs) after a loop closes.

pub mod graph;
pub mod index;
pub mod merge;
#[cfg(feature = "training")]
pub mod training;
pub mod verify;
pub mod vocabulary;

pub use graph::{Edge, EdgeKind, PoseGraph, SolveConfig};
pub use index::PlaceIndex;
pub use merge::{MergeConfig, MergeDetector, Merged, propose};
pub use verify::{Place, Verified, VerifyConfig, verify};
pub use vocabulary::{BowVector, TrainConfig, Vocabulary};

/// Errors of the places crate.
#[derive(Debug, thiserror::Error)]
pub enum PlacesError {
    #[error("bad vocabulary: {0}")]
    Vocabulary(String),
    #[error("bad vocabulary training input: {0}")]
    Training(String),
    #[error("bad place-recognition configuration: {0}")]
    Config(String),
    #[error("pose-graph solver: {0}")]
    Solver(String),
}
