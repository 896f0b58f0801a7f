//! stillmap camera tracking, free of network and file I/O.

pub mod camera;

pub use camera::Camera;
