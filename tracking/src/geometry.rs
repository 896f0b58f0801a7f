//! The measurement model shared by pose optimisation and bundle adjustment.
//!
//! An observation of a map point is its ideal pixel (u, v) and, when the keypoint
//! has depth, a virtual disparity `d = fx·b/z` (pixels). Predictions come from the
//! point in the camera frame; the pose is perturbed on the left,
//! `camera_from_world ← exp(δ) · camera_from_world` with `δ = (ω, v)`.

use nalgebra::{Isometry3, Matrix3, Matrix3x6, Point2, Point3, Translation3, UnitQuaternion, Vector3, Vector6};

use crate::camera::Camera;

/// χ² 95 % quantile for 2 degrees of freedom (pixel residual).
pub const CHI2_2DOF: f64 = 5.991;
/// χ² 95 % quantile for 3 degrees of freedom (pixel + disparity residual).
pub const CHI2_3DOF: f64 = 7.815;

/// One measurement of a point in an image.
#[derive(Debug, Clone, Copy)]
pub struct Measurement {
    pub ideal: Point2<f64>,
    /// `fx·b/z` when the keypoint had depth.
    pub disparity: Option<f64>,
    /// 1/σ² of the pixel (and disparity) noise; σ grows with the pyramid level.
    pub information: f64,
}

impl Measurement {
    pub fn chi2_threshold(&self) -> f64 {
        if self.disparity.is_some() { CHI2_3DOF } else { CHI2_2DOF }
    }
}

/// A residual `e = measured − predicted` of one measurement.
#[derive(Debug, Clone, Copy)]
pub struct Residual {
    pub error: Vector3<f64>,
    /// Rows used: 2 without disparity, 3 with.
    pub rows: usize,
}

impl Residual {
    /// Mahalanobis squared error.
    pub fn chi2(&self, information: f64) -> f64 {
        self.error.rows(0, self.rows).norm_squared() * information
    }
}

/// A linearised residual: `e = measured − predicted`, and the Jacobians of the
/// prediction with respect to the pose perturbation and the point in the world.
pub struct Linearised {
    pub error: Vector3<f64>,
    /// Rows used: 2 without disparity, 3 with.
    pub rows: usize,
    pub d_pose: Matrix3x6<f64>,
    pub d_point: Matrix3<f64>,
}

impl Linearised {
    /// Mahalanobis squared error.
    pub fn chi2(&self, information: f64) -> f64 {
        self.error.rows(0, self.rows).norm_squared() * information
    }
}

/// Points nearer than this (metres, in the camera) give no residual.
const MIN_Z: f64 = 1e-3;

/// The residual of a point in the camera, and the projection's Jacobian with
/// respect to that point (rows: u, v, disparity).
fn project_linearised(camera: &Camera, bf: f64, point_in_camera: &Point3<f64>, m: &Measurement) -> Option<(Residual, Matrix3<f64>)> {
    let pc = point_in_camera;
    if pc.z < MIN_Z {
        return None;
    }
    let inv_z = 1.0 / pc.z;
    let inv_z2 = inv_z * inv_z;
    let u = camera.fx * pc.x * inv_z + camera.cx;
    let v = camera.fy * pc.y * inv_z + camera.cy;
    let mut d_proj = Matrix3::zeros();
    d_proj[(0, 0)] = camera.fx * inv_z;
    d_proj[(0, 2)] = -camera.fx * pc.x * inv_z2;
    d_proj[(1, 1)] = camera.fy * inv_z;
    d_proj[(1, 2)] = -camera.fy * pc.y * inv_z2;
    let mut error = Vector3::new(m.ideal.x - u, m.ideal.y - v, 0.0);
    let rows = if let Some(d) = m.disparity {
        d_proj[(2, 2)] = -bf * inv_z2;
        error.z = d - bf * inv_z;
        3
    } else {
        2
    };
    Some((Residual { error, rows }, d_proj))
}

/// The residual of a measurement of `point_in_world` seen from
/// `camera_from_world` (the same numbers as [`linearise`]'s, without the pose and
/// point Jacobians).
pub fn residual(
    camera: &Camera,
    bf: f64,
    camera_from_world: &Isometry3<f64>,
    point_in_world: &Point3<f64>,
    m: &Measurement,
) -> Option<Residual> {
    project_linearised(camera, bf, &(camera_from_world * point_in_world), m).map(|(r, _)| r)
}

/// d(point in camera)/dδ for the left perturbation: `[ -[pc]× | I ]`.
fn d_point_in_camera_d_pose(point_in_camera: &Point3<f64>) -> Matrix3x6<f64> {
    let mut d_pc_pose = Matrix3x6::zeros();
    d_pc_pose.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-point_in_camera.coords.cross_matrix()));
    d_pc_pose.fixed_view_mut::<3, 3>(0, 3).copy_from(&Matrix3::identity());
    d_pc_pose
}

/// [`linearise`] without the point Jacobian: the residual and its Jacobian with
/// respect to the pose perturbation (what motion-only optimisation needs).
pub fn linearise_pose(
    camera: &Camera,
    bf: f64,
    camera_from_world: &Isometry3<f64>,
    point_in_world: &Point3<f64>,
    m: &Measurement,
) -> Option<(Residual, Matrix3x6<f64>)> {
    let pc = camera_from_world * point_in_world;
    let (r, d_proj) = project_linearised(camera, bf, &pc, m)?;
    Some((r, d_proj * d_point_in_camera_d_pose(&pc)))
}

/// Linearises a measurement of `point_in_world` seen from `camera_from_world`.
/// `None` when the point is behind or too close to the camera.
pub fn linearise(
    camera: &Camera,
    bf: f64,
    camera_from_world: &Isometry3<f64>,
    point_in_world: &Point3<f64>,
    m: &Measurement,
) -> Option<Linearised> {
    let pc = camera_from_world * point_in_world;
    let (r, d_proj) = project_linearised(camera, bf, &pc, m)?;
    let d_pose = d_proj * d_point_in_camera_d_pose(&pc);
    let d_point = d_proj * camera_from_world.rotation.to_rotation_matrix().matrix();
    Some(Linearised { error: r.error, rows: r.rows, d_pose, d_point })
}

/// PnP-RANSAC parameters for [`pnp_ransac`].
#[derive(Debug, Clone, Copy)]
pub struct PnpRansac {
    pub iterations: i32,
    /// Inlier reprojection threshold in pixels.
    pub threshold_px: f32,
    pub confidence: f64,
}

/// OpenCV EPnP inside RANSAC on (point, ideal pixel) pairs: `camera_from_world`
/// and the indices of the inlier pairs, or `None` when OpenCV finds no solution.
pub fn pnp_ransac(camera: &Camera, pairs: &[(Point3<f64>, Point2<f64>)], params: PnpRansac) -> Option<(Isometry3<f64>, Vec<usize>)> {
    use opencv::core::{Mat, Point2f, Point3f, Vector};
    use opencv::prelude::*;
    let object: Vector<Point3f> = pairs.iter().map(|(p, _)| Point3f::new(p.x as f32, p.y as f32, p.z as f32)).collect();
    let image: Vector<Point2f> = pairs.iter().map(|(_, q)| Point2f::new(q.x as f32, q.y as f32)).collect();
    let c = camera;
    let k = Mat::from_slice_2d(&[[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]]).ok()?;
    let (mut rvec, mut tvec, mut inliers) = (Mat::default(), Mat::default(), Mat::default());
    let ok = opencv::calib3d::solve_pnp_ransac(
        &object,
        &image,
        &k,
        &opencv::core::no_array(),
        &mut rvec,
        &mut tvec,
        false,
        params.iterations,
        params.threshold_px,
        params.confidence,
        &mut inliers,
        opencv::calib3d::SOLVEPNP_EPNP,
    )
    .ok()?;
    if !ok {
        return None;
    }
    let r = Vector3::new(*rvec.at::<f64>(0).ok()?, *rvec.at::<f64>(1).ok()?, *rvec.at::<f64>(2).ok()?);
    let t = Vector3::new(*tvec.at::<f64>(0).ok()?, *tvec.at::<f64>(1).ok()?, *tvec.at::<f64>(2).ok()?);
    let pose = Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::new(r)));
    let mut kept = Vec::with_capacity(inliers.rows().max(0) as usize);
    for i in 0..inliers.rows() {
        kept.push(usize::try_from(*inliers.at::<i32>(i).ok()?).ok()?);
    }
    Some((pose, kept))
}

/// Applies a left perturbation `δ = (ω, v)` to a pose.
pub fn perturb(delta: &Vector6<f64>, camera_from_world: &Isometry3<f64>) -> Isometry3<f64> {
    let omega = Vector3::new(delta[0], delta[1], delta[2]);
    let v = Vector3::new(delta[3], delta[4], delta[5]);
    Isometry3::from_parts(Translation3::from(v), UnitQuaternion::from_scaled_axis(omega)) * camera_from_world
}

/// A motion scaled along its screw, approximately: the rotation's angle and the
/// translation both times `factor` (constant velocity over `factor` frame intervals).
pub fn scale_motion(motion: &Isometry3<f64>, factor: f64) -> Isometry3<f64> {
    if factor == 1.0 {
        return *motion;
    }
    Isometry3::from_parts((motion.translation.vector * factor).into(), motion.rotation.powf(factor))
}

/// Frame intervals of `interval_s` seconds from capture time `from_ns` to `to_ns`,
/// rounded and at least one (a camera's jitter stays one interval; dropped frames
/// make more); `None` unless `to_ns` is later.
pub fn frame_intervals(from_ns: u64, to_ns: u64, interval_s: f64) -> Option<f64> {
    (to_ns > from_ns).then(|| ((to_ns - from_ns) as f64 * 1e-9 / interval_s).round().max(1.0))
}

/// Huber cost of a residual of Mahalanobis norm² `chi2` with threshold `delta2`.
#[inline]
pub fn robust_cost(chi2: f64, delta2: f64) -> f64 {
    if chi2 <= delta2 { chi2 } else { 2.0 * (delta2 * chi2).sqrt() - delta2 }
}

/// Huber weight for a residual of Mahalanobis norm² `chi2` with threshold `delta2`.
#[inline]
pub fn huber_weight(chi2: f64, delta2: f64) -> f64 {
    if chi2 <= delta2 { 1.0 } else { (delta2 / chi2).sqrt() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_intervals_round_jitter_to_one_and_count_dropped_frames() {
        let interval = 1.0 / 30.0;
        assert_eq!(frame_intervals(0, 40_000_000, interval), Some(1.0), "40 ms is one interval");
        assert_eq!(frame_intervals(0, 10_000_000, interval), Some(1.0), "at least one");
        assert_eq!(frame_intervals(1_000, 1_000 + 100_000_000, interval), Some(3.0), "two frames dropped");
        assert_eq!(frame_intervals(5, 5, interval), None);
        assert_eq!(frame_intervals(6, 5, interval), None);
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let camera = Camera::pinhole(640, 480, 520.0, 515.0, 320.0, 240.0, 5000.0);
        let bf = 41.0;
        let pose = Isometry3::new(Vector3::new(0.1, -0.2, 0.3), Vector3::new(0.05, -0.1, 0.2));
        let pw = Point3::new(0.4, 0.3, 2.5);
        let m = Measurement { ideal: Point2::new(300.0, 250.0), disparity: Some(15.0), information: 1.0 };
        let lin = linearise(&camera, bf, &pose, &pw, &m).unwrap();
        let h = 1e-6;
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let e2 = linearise(&camera, bf, &perturb(&d, &pose), &pw, &m).unwrap().error;
            // e = measured − predicted, so de/dδ = −d_pose
            let numeric = (e2 - lin.error) / h;
            assert!((numeric + lin.d_pose.column(k)).norm() < 1e-3, "pose column {k}");
        }
        for k in 0..3 {
            let mut p = pw;
            p[k] += h;
            let e2 = linearise(&camera, bf, &pose, &p, &m).unwrap().error;
            let numeric = (e2 - lin.error) / h;
            assert!((numeric + lin.d_point.column(k)).norm() < 1e-3, "point column {k}");
        }
    }

    #[test]
    fn residual_and_pose_linearisation_match_the_full_one() {
        let camera = Camera::pinhole(640, 480, 520.0, 521.0, 320.0, 240.0, 5000.0);
        let pose = Isometry3::new(Vector3::new(0.1, -0.05, 0.2), Vector3::new(0.03, -0.02, 0.01));
        for (pw, disparity) in [(Point3::new(0.3, -0.2, 2.0), Some(20.0)), (Point3::new(-0.4, 0.1, 1.2), None)] {
            let m = Measurement { ideal: Point2::new(400.0, 200.0), disparity, information: 0.7 };
            let full = linearise(&camera, 41.6, &pose, &pw, &m).unwrap();
            let r = residual(&camera, 41.6, &pose, &pw, &m).unwrap();
            let (p, d_pose) = linearise_pose(&camera, 41.6, &pose, &pw, &m).unwrap();
            assert_eq!((r.error, r.rows), (full.error, full.rows));
            assert_eq!((p.error, p.rows, d_pose), (full.error, full.rows, full.d_pose));
            assert_eq!(r.chi2(m.information), full.chi2(m.information));
        }
        let behind = Point3::new(0.0, 0.0, -0.5);
        let m = Measurement { ideal: Point2::new(0.0, 0.0), disparity: None, information: 1.0 };
        assert!(residual(&camera, 41.6, &Isometry3::identity(), &behind, &m).is_none());
        assert!(linearise_pose(&camera, 41.6, &Isometry3::identity(), &behind, &m).is_none());
    }
}
