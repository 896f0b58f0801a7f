//! Ego-motion compensation (beyond the paper).
//!
//! Thresholding raw flow marks everything as moving once the camera moves. Here
//! each pixel's flow is *predicted* from its depth and the camera motion
//! `previous_from_current`, and only the residual `measured − predicted` counts,
//! against a threshold scaled by the uncertainty of the prediction (flow noise and
//! the depth noise σ_z = a + b·z² carried through the projection).
//!
//! The motion comes from the tracker's motion model and is refined on the flow
//! itself: a grid of flow samples with depth is a dense 3D–2D correspondence set
//! (a point in the current camera, its pixel in the previous image), solved by the
//! tracker's robust pose optimisation, so pixels that move in the world fall out
//! as outliers.

use nalgebra::{Isometry3, Point2, Point3};
use stillmap_tracking::Camera;
use stillmap_tracking::geometry::Measurement;
use stillmap_tracking::optimize::optimize_pose;

use crate::config::EgoMotionConfig;
use crate::flow::FlowField;

/// Per flow pixel: no prediction possible (no valid depth).
pub const NO_PREDICTION: u8 = 0;
/// Per flow pixel: flow agrees with the camera's own motion.
pub const CONSISTENT: u8 = 1;
/// Per flow pixel: residual flow beyond its uncertainty.
pub const RESIDUAL: u8 = 2;

/// The outcome of ego-motion compensation for one frame, on the flow grid.
#[derive(Debug, Clone)]
pub struct EgoResult {
    /// The camera motion used for the prediction.
    pub previous_from_current: Isometry3<f64>,
    /// Whether the motion was refined on the flow (else the prior alone was used).
    pub refined: bool,
    /// Flow samples used by the refinement, and how many it kept as inliers.
    pub samples: usize,
    pub inliers: usize,
    /// [`NO_PREDICTION`], [`CONSISTENT`] or [`RESIDUAL`] per flow pixel.
    pub class: Vec<u8>,
    /// Residual flow magnitude in full-size pixels (0 without a prediction).
    pub residual_px: Vec<f32>,
    /// Depth (metres) per flow pixel, 0 when invalid.
    pub depth_m: Vec<f32>,
}

/// Ego-motion compensation for one camera; caches per-pixel rays of the flow grid.
pub struct EgoMotion {
    camera: Camera,
    config: EgoMotionConfig,
    subsample: usize,
    width: usize,
    height: usize,
    /// Per flow pixel: raw (distorted) full-size position of its centre and its ideal ray.
    raw: Vec<Point2<f64>>,
    ray: Vec<Point2<f64>>,
}

/// Fewer refinement inliers than this fraction of the samples: the refinement is not trusted.
const MIN_INLIER_FRACTION: f64 = 0.3;

impl EgoMotion {
    pub fn new(camera: Camera, config: EgoMotionConfig, subsample: u32) -> Self {
        let s = subsample.max(1) as usize;
        let (width, height) = (camera.width as usize / s, camera.height as usize / s);
        let mut raw = Vec::with_capacity(width * height);
        let mut ray = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                // Centre of the s×s block in full-size pixel coordinates.
                let r = Point2::new((x as f64 + 0.5) * s as f64 - 0.5, (y as f64 + 0.5) * s as f64 - 0.5);
                let ideal = camera.undistort(&r);
                raw.push(r);
                ray.push(Point2::new((ideal.x - camera.cx) / camera.fx, (ideal.y - camera.cy) / camera.fy));
            }
        }
        Self { camera, config, subsample: s, width, height, raw, ray }
    }

    /// Depth in metres per flow pixel: the block's centre reading, else any valid one in the block.
    pub fn sample_depth(&self, depth: &[u16]) -> Vec<f32> {
        let s = self.subsample;
        let w = self.camera.width as usize;
        let scale = 1.0 / self.camera.depth_units_per_metre;
        let (lo, hi) = (self.config.min_depth_m, self.config.max_depth_m);
        let mut out = vec![0f32; self.width * self.height];
        for y in 0..self.height {
            for x in 0..self.width {
                let (cx, cy) = (x * s + s / 2, y * s + s / 2);
                let mut d = depth[cy * w + cx];
                if d == 0 {
                    'block: for by in 0..s {
                        for bx in 0..s {
                            d = depth[(y * s + by) * w + x * s + bx];
                            if d != 0 {
                                break 'block;
                            }
                        }
                    }
                }
                let z = f64::from(d) * scale;
                if d != 0 && (lo..=hi).contains(&z) {
                    out[y * self.width + x] = z as f32;
                }
            }
        }
        out
    }

    /// Where the scene point at flow pixel `i` and depth `z` was in the previous raw image.
    fn predict(&self, i: usize, z: f64, previous_from_current: &Isometry3<f64>) -> Option<Point2<f64>> {
        let r = self.ray[i];
        let point_in_current = Point3::new(r.x * z, r.y * z, z);
        let point_in_previous = previous_from_current * point_in_current;
        let ideal = self.camera.project(&point_in_previous)?;
        Some(self.camera.distort(&ideal))
    }

    /// Refines `prior` on the flow and classifies every flow pixel. `exclude`
    /// (flow-grid sized, nonzero = skip) keeps known dynamic pixels out of the refinement.
    pub fn compensate(
        &self,
        flow: &FlowField,
        depth: &[u16],
        prior: Isometry3<f64>,
        exclude: Option<&[u8]>,
    ) -> EgoResult {
        debug_assert_eq!((flow.width, flow.height), (self.width, self.height));
        let s = self.subsample as f64;
        let depth_m = self.sample_depth(depth);

        // Refinement: current-camera points against their flow targets in the previous image.
        let step = self.config.sample_step.max(1) as usize;
        let information = 1.0 / (self.config.flow_sigma_px * self.config.flow_sigma_px);
        let mut correspondences = Vec::new();
        for y in (step / 2..self.height).step_by(step) {
            for x in (step / 2..self.width).step_by(step) {
                let i = y * self.width + x;
                let z = f64::from(depth_m[i]);
                if z == 0.0 || exclude.is_some_and(|m| m[i] != 0) {
                    continue;
                }
                let r = self.ray[i];
                let f = flow.data[i];
                let target_raw = Point2::new(self.raw[i].x + f64::from(f[0]) * s, self.raw[i].y + f64::from(f[1]) * s);
                let ideal = self.camera.undistort(&target_raw);
                correspondences.push((
                    Point3::new(r.x * z, r.y * z, z),
                    Measurement { ideal, disparity: None, information },
                ));
            }
        }
        let samples = correspondences.len();
        let (mut previous_from_current, mut refined, mut inliers) = (prior, false, 0);
        if samples >= self.config.min_samples {
            // `optimize_pose` estimates camera_from_world: here previous_from_current,
            // with the current camera frame playing the world.
            let estimate = optimize_pose(&self.camera, 1.0, prior, &correspondences);
            inliers = estimate.inlier_count;
            if inliers >= self.config.min_samples && inliers as f64 >= MIN_INLIER_FRACTION * samples as f64 {
                previous_from_current = estimate.camera_from_world;
                refined = true;
            }
        }

        // Classification of every flow pixel.
        let n = self.width * self.height;
        let mut class = vec![NO_PREDICTION; n];
        let mut residual_px = vec![0f32; n];
        let (a, b) = (self.config.depth_sigma_a_m, self.config.depth_sigma_b_per_m);
        let flow_var = self.config.flow_sigma_px * self.config.flow_sigma_px;
        for i in 0..n {
            let z = f64::from(depth_m[i]);
            if z == 0.0 {
                continue;
            }
            let (Some(p), Some(p_far)) = (
                self.predict(i, z, &previous_from_current),
                self.predict(i, z + a + b * z * z, &previous_from_current),
            ) else {
                continue;
            };
            let f = flow.data[i];
            let measured = Point2::new(self.raw[i].x + f64::from(f[0]) * s, self.raw[i].y + f64::from(f[1]) * s);
            let residual = (measured - p).norm();
            let depth_var = (p_far - p).norm_squared();
            let threshold = (self.config.residual_sigmas * (flow_var + depth_var).sqrt()).max(self.config.min_residual_px);
            residual_px[i] = residual as f32;
            class[i] = if residual > threshold { RESIDUAL } else { CONSISTENT };
        }
        EgoResult { previous_from_current, refined, samples, inliers, class, residual_px, depth_m }
    }

    pub fn grid_size(&self) -> (usize, usize) {
        (self.width, self.height)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// A synthetic flow field for a fronto-parallel wall at 2 m seen by a moving
    /// camera, with a patch that moves on its own.
    #[test]
    fn refines_the_motion_and_flags_only_the_independent_patch() {
        let camera = Camera::pinhole(320, 240, 260.0, 260.0, 160.0, 120.0, 1000.0);
        let config = EgoMotionConfig { min_samples: 20, ..EgoMotionConfig::default() };
        let ego = EgoMotion::new(camera.clone(), config, 2);
        let truth = Isometry3::new(Vector3::new(0.03, -0.01, 0.02), Vector3::new(0.01, -0.02, 0.005));
        let depth = vec![2000u16; 320 * 240];
        let (w, h) = ego.grid_size();
        let mut data = Vec::with_capacity(w * h);
        for i in 0..w * h {
            let p = ego.predict(i, 2.0, &truth).unwrap();
            let mut f = [((p.x - ego.raw[i].x) / 2.0) as f32, ((p.y - ego.raw[i].y) / 2.0) as f32];
            let (x, y) = (i % w, i / w);
            if (60..90).contains(&x) && (40..70).contains(&y) {
                f[0] += 4.0; // 8 full-size pixels of independent motion
            }
            data.push(f);
        }
        let flow = FlowField { width: w, height: h, subsample: 2, data };
        let out = ego.compensate(&flow, &depth, Isometry3::identity(), None);
        assert!(out.refined);
        let err = out.previous_from_current.inverse() * truth;
        assert!(err.translation.vector.norm() < 1e-3 && err.rotation.angle() < 1e-4, "{err:?}");
        for i in 0..w * h {
            let (x, y) = (i % w, i / w);
            let inside = (60..90).contains(&x) && (40..70).contains(&y);
            assert_eq!(out.class[i], if inside { RESIDUAL } else { CONSISTENT }, "pixel {x},{y}");
        }
    }
}
