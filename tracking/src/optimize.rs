//! Motion-only optimisation: one camera pose against fixed map points, robust
//! (Huber) Gauss–Newton on reprojection plus disparity residuals, with rounds of
//! outlier classification as in ORB-SLAM.

use nalgebra::{Isometry3, Matrix6, Point3, Vector6};

use crate::camera::Camera;
use crate::geometry::{Measurement, huber_weight, linearise_pose, perturb, residual, robust_cost};

/// Classification rounds; the last one runs without the robust kernel.
const ROUNDS: usize = 4;
/// Levenberg–Marquardt iterations per round, at most.
const ITERATIONS: usize = 15;
/// Stop iterating once the update is this small (radians / metres) …
const CONVERGED_STEP: f64 = 1e-7;
/// … and the relative cost decrease this small.
const CONVERGED_COST: f64 = 1e-9;
/// Levenberg–Marquardt damping: start, bounds of its decrease, and change factor.
const INITIAL_LAMBDA: f64 = 1e-4;
const MIN_LAMBDA: f64 = 1e-9;
const LAMBDA_FACTOR: f64 = 10.0;

/// The result of a pose optimisation.
pub struct PoseEstimate {
    pub camera_from_world: Isometry3<f64>,
    /// Per correspondence: whether it was an inlier in the final round.
    pub inliers: Vec<bool>,
    pub inlier_count: usize,
}

/// χ² 95 % quantile for 6 degrees of freedom: a pose prior further off than this
/// is down-weighted (Huber) like an outlying measurement.
const CHI2_6DOF: f64 = 12.592;

/// A Gaussian prior on `camera_from_world`: the pose it expects and the
/// information (1/σ²) of the rotation (rad⁻²) and translation (m⁻²) of the
/// difference, per axis, in the camera frame.
#[derive(Debug, Clone, Copy)]
pub struct PosePrior {
    pub camera_from_world: Isometry3<f64>,
    pub rotation_information: f64,
    pub translation_information: f64,
}

impl PosePrior {
    /// The prior's residual `e = (ω, v)` with `prior = exp(e) · pose` (to first
    /// order), and its Mahalanobis norm².
    fn residual(&self, pose: &Isometry3<f64>) -> (Vector6<f64>, f64) {
        let d = self.camera_from_world * pose.inverse();
        let (w, v) = (d.rotation.scaled_axis(), d.translation.vector);
        let e = Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z);
        let chi2 = w.norm_squared() * self.rotation_information + v.norm_squared() * self.translation_information;
        (e, chi2)
    }

    fn information(&self) -> Vector6<f64> {
        let (r, t) = (self.rotation_information, self.translation_information);
        Vector6::new(r, r, r, t, t, t)
    }
}

/// Optimises `camera_from_world` from 3D–2D(+depth) correspondences.
pub fn optimize_pose(camera: &Camera, bf: f64, initial: Isometry3<f64>, correspondences: &[(Point3<f64>, Measurement)]) -> PoseEstimate {
    optimize_pose_with_prior(camera, bf, initial, correspondences, None)
}

/// [`optimize_pose`] with a robust (Huber) Gaussian prior on the pose.
pub fn optimize_pose_with_prior(
    camera: &Camera,
    bf: f64,
    initial: Isometry3<f64>,
    correspondences: &[(Point3<f64>, Measurement)],
    prior: Option<&PosePrior>,
) -> PoseEstimate {
    let mut pose = initial;
    let mut inliers = vec![true; correspondences.len()];
    for round in 0..ROUNDS {
        let robust = round + 1 < ROUNDS;
        let cost = |pose: &Isometry3<f64>, inliers: &[bool]| -> f64 {
            // The prior stays robust in every round: it is one measurement, and
            // a wrong one must not outweigh the features in the last round.
            let prior_cost = prior.map_or(0.0, |p| robust_cost(p.residual(pose).1, CHI2_6DOF));
            prior_cost
                + correspondences
                    .iter()
                    .zip(inliers)
                    .filter(|(_, i)| **i)
                    .map(|((pw, m), _)| match residual(camera, bf, pose, pw, m) {
                        Some(r) => {
                            let chi2 = r.chi2(m.information);
                            if robust { robust_cost(chi2, m.chi2_threshold()) } else { chi2 }
                        }
                        None => 2.0 * m.chi2_threshold(),
                    })
                    .sum::<f64>()
        };
        let mut current = cost(&pose, &inliers);
        let mut lambda = INITIAL_LAMBDA;
        // The normal equations at the current pose; a rejected step leaves the pose,
        // and so them, unchanged.
        let mut normal: Option<(Matrix6<f64>, Vector6<f64>, usize)> = None;
        for _ in 0..ITERATIONS {
            let (h, b, used) = *normal.get_or_insert_with(|| {
                let mut h = Matrix6::zeros();
                let mut b = Vector6::zeros();
                let mut used = 0;
                for ((pw, m), &inlier) in correspondences.iter().zip(&inliers) {
                    if !inlier {
                        continue;
                    }
                    let Some((r, d_pose)) = linearise_pose(camera, bf, &pose, pw, m) else { continue };
                    let chi2 = r.chi2(m.information);
                    let w = m.information * if robust { huber_weight(chi2, m.chi2_threshold()) } else { 1.0 };
                    let j = d_pose.rows(0, r.rows);
                    let e = r.error.rows(0, r.rows);
                    h += j.transpose() * j * w;
                    b += j.transpose() * e * w;
                    used += 1;
                }
                if let Some(p) = prior {
                    let (e, chi2) = p.residual(&pose);
                    let information = p.information() * huber_weight(chi2, CHI2_6DOF);
                    for i in 0..6 {
                        h[(i, i)] += information[i];
                        b[i] += information[i] * e[i];
                    }
                }
                (h, b, used)
            });
            if used < 3 {
                break;
            }
            let mut damped = h;
            for i in 0..6 {
                damped[(i, i)] *= 1.0 + lambda;
            }
            let Some(delta) = damped.cholesky().map(|c| c.solve(&b)) else { break };
            let candidate = perturb(&delta, &pose);
            let next = cost(&candidate, &inliers);
            if next <= current {
                pose = candidate;
                normal = None;
                lambda = (lambda / LAMBDA_FACTOR).max(MIN_LAMBDA);
                let done = current - next < CONVERGED_COST * current.max(1.0) && delta.norm() < CONVERGED_STEP;
                current = next;
                if done {
                    break;
                }
            } else {
                lambda *= LAMBDA_FACTOR;
            }
        }
        for ((pw, m), inlier) in correspondences.iter().zip(inliers.iter_mut()) {
            *inlier = residual(camera, bf, &pose, pw, m).is_some_and(|r| r.chi2(m.information) <= m.chi2_threshold());
        }
    }
    let inlier_count = inliers.iter().filter(|&&i| i).count();
    PoseEstimate { camera_from_world: pose, inliers, inlier_count }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point2, Vector3};

    #[test]
    fn recovers_a_pose_despite_outliers() {
        let camera = Camera::pinhole(640, 480, 520.0, 520.0, 320.0, 240.0, 5000.0);
        let bf = 41.6;
        let truth = Isometry3::new(Vector3::new(0.05, -0.02, 0.1), Vector3::new(0.02, 0.05, -0.01));
        let mut corr = Vec::new();
        for i in 0..200 {
            let pw = Point3::new(((i * 37) % 200) as f64 / 100.0 - 1.0, ((i * 91) % 150) as f64 / 100.0 - 0.75, 1.5 + (i % 7) as f64 * 0.3);
            let pc = truth * pw;
            let mut ideal = camera.project(&pc).unwrap();
            if i % 10 == 0 {
                ideal += nalgebra::Vector2::new(40.0, -25.0); // gross outlier
            }
            corr.push((pw, Measurement { ideal: Point2::from(ideal.coords), disparity: Some(bf / pc.z), information: 1.0 }));
        }
        let est = optimize_pose(&camera, bf, Isometry3::identity(), &corr);
        let err = est.camera_from_world.inverse() * truth;
        assert!(err.translation.vector.norm() < 1e-6, "{}", err.translation.vector.norm());
        assert!(err.rotation.angle() < 1e-6);
        assert_eq!(est.inlier_count, 180);
        assert!(corr.iter().zip(&est.inliers).enumerate().all(|(i, (_, &inl))| inl == (i % 10 != 0)));
    }
}
