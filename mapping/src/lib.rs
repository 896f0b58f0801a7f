//! stillmap's static semantic map, free of network and file I/O.
//!
//! - [`voxel`]: voxels (occupancy log-odds, colour, class votes) in hashed 8³ blocks.
//! - [`map`]: fusing a keyframe (hits), projective free-space carving (misses),
//!   taking a keyframe back out, eviction beyond a memory budget.
//! - [`builder`]: one session's map following the trajectory (re-fusion of corrected
//!   keyframes) with its gravity-aligned frame ([`gravity`]).
//! - [`tiles`]: top-down semantic tiles and the ROS occupancy grid.
//! - [`export`]: binary PLY and static objects.

pub mod builder;
pub mod config;
pub mod export;
pub mod gravity;
pub mod map;
pub mod tiles;
pub mod voxel;

pub use builder::{KeyframeReport, MapBuilder};
pub use config::MappingConfig;
pub use gravity::UpSource;
pub use map::{CameraRays, DepthView, FuseStats, MapStats, VoxelMap};
pub use voxel::NO_CLASS;

/// Errors of the mapping crate.
#[derive(Debug, thiserror::Error)]
pub enum MappingError {
    #[error("bad map input: {0}")]
    Input(String),
    #[error("bad mapping configuration: {0}")]
    Config(String),
    #[error("corrupt map data: {0}")]
    Corrupt(String),
    #[error("encoding failed: {0}")]
    Encode(String),
}
