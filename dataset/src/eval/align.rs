//! Trajectory alignment: Umeyama's least-squares SE(3) fit (evo `-a`) and origin
//! alignment (evo `--align_origin`).

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::DatasetError;

/// The rigid transform `T` minimising `Σ |y_i - T x_i|²` (Umeyama 1991, no scale),
/// computed like evo's `geometry.umeyama_alignment`, including its rank test.
pub fn umeyama(x: &[Vector3<f64>], y: &[Vector3<f64>]) -> Result<Isometry3<f64>, DatasetError> {
    if x.len() != y.len() || x.is_empty() {
        return Err(DatasetError::Degenerate { points: x.len().min(y.len()) });
    }
    let n = x.len() as f64;
    let mean_x = x.iter().sum::<Vector3<f64>>() / n;
    let mean_y = y.iter().sum::<Vector3<f64>>() / n;
    let outer_sum: Matrix3<f64> = x.iter().zip(y).map(|(xi, yi)| (yi - mean_y) * (xi - mean_x).transpose()).sum();
    let cov = outer_sum * (1.0 / n);
    let svd = cov.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(DatasetError::Degenerate { points: x.len() });
    };
    // evo: fewer than m - 1 singular values above machine epsilon cannot be aligned.
    if svd.singular_values.iter().filter(|&&d| d > f64::EPSILON).count() < 2 {
        return Err(DatasetError::Degenerate { points: x.len() });
    }
    let mut s = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let r = u * s * v_t;
    let t = mean_y - r * mean_x;
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Ok(Isometry3::from_parts(Translation3::from(t), rotation))
}

/// Aligns `estimate` to `reference` by their positions with [`umeyama`].
pub fn align_se3(reference: &[Isometry3<f64>], estimate: &[Isometry3<f64>]) -> Result<Isometry3<f64>, DatasetError> {
    let positions = |poses: &[Isometry3<f64>]| poses.iter().map(|p| p.translation.vector).collect::<Vec<_>>();
    umeyama(&positions(estimate), &positions(reference))
}

/// The transform that moves the first estimated pose onto the first reference pose
/// (`ref_0 · est_0⁻¹`), or `None` when either is empty.
pub fn align_origin(reference: &[Isometry3<f64>], estimate: &[Isometry3<f64>]) -> Option<Isometry3<f64>> {
    Some(reference.first()? * estimate.first()?.inverse())
}

/// The rigid transform taking `estimate` onto `reference` with its rotation from
/// the orientations (the chordal mean of `R_ref · R_estᵀ`) and its translation from
/// the mean positions: for trajectories that barely translate (a camera turning on
/// the spot), where a position-only fit leaves the rotation ill-conditioned.
/// `None` when the lists are empty or differ in length.
pub fn align_orientations(reference: &[Isometry3<f64>], estimate: &[Isometry3<f64>]) -> Option<Isometry3<f64>> {
    if reference.len() != estimate.len() || reference.is_empty() {
        return None;
    }
    let m: Matrix3<f64> = reference
        .iter()
        .zip(estimate)
        .map(|(r, e)| r.rotation.to_rotation_matrix().into_inner() * e.rotation.to_rotation_matrix().into_inner().transpose())
        .sum();
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut s = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(u * s * v_t));
    let n = reference.len() as f64;
    let t = reference.iter().zip(estimate).map(|(r, e)| r.translation.vector - rotation * e.translation.vector).sum::<Vector3<f64>>() / n;
    Some(Isometry3::from_parts(Translation3::from(t), rotation))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Poses turning on the spot (2 mm of translation): the orientations give the
    /// alignment back exactly.
    #[test]
    fn orientation_alignment_recovers_a_known_transform() {
        let truth = known();
        let estimate: Vec<Isometry3<f64>> = (0..30)
            .map(|i| {
                Isometry3::new(Vector3::new(0.002 * (i as f64).sin(), 0.0, 0.001), Vector3::new(0.1 * i as f64, 0.05, -0.02 * i as f64))
            })
            .collect();
        let reference: Vec<Isometry3<f64>> = estimate.iter().map(|e| truth * e).collect();
        let found = align_orientations(&reference, &estimate).expect("aligned");
        let error = truth.inverse() * found;
        assert!(error.translation.vector.norm() < 1e-9 && error.rotation.angle() < 1e-9, "{error:?}");
        assert!(align_orientations(&reference[..2], &estimate).is_none());
    }

    fn known() -> Isometry3<f64> {
        Isometry3::new(Vector3::new(0.5, -1.25, 2.0), Vector3::new(0.3, -0.7, 1.1))
    }

    fn points() -> Vec<Vector3<f64>> {
        (0..40)
            .map(|i| {
                let s = i as f64;
                Vector3::new((0.37 * s).sin() * 2.0, (0.11 * s).cos() - 0.05 * s, 0.02 * s * s - 1.0)
            })
            .collect()
    }

    #[test]
    fn recovers_a_known_transform() {
        let x = points();
        let y: Vec<_> = x.iter().map(|p| known() * nalgebra::Point3::from(*p)).map(|p| p.coords).collect();
        let t = umeyama(&x, &y).unwrap();
        assert!((t.translation.vector - known().translation.vector).norm() < 1e-12);
        assert!(t.rotation.angle_to(&known().rotation) < 1e-12);
    }

    #[test]
    fn recovers_a_reflection_free_rotation_of_planar_points() {
        // Points in a plane: one singular value is zero, still a proper rotation.
        let x: Vec<_> = points().iter().map(|p| Vector3::new(p.x, p.y, 0.0)).collect();
        let y: Vec<_> = x.iter().map(|p| (known() * nalgebra::Point3::from(*p)).coords).collect();
        let t = umeyama(&x, &y).unwrap();
        assert!(t.rotation.angle_to(&known().rotation) < 1e-10);
    }

    #[test]
    fn rejects_degenerate_input() {
        let x = vec![Vector3::new(1.0, 2.0, 3.0); 5];
        assert!(matches!(umeyama(&x, &x), Err(DatasetError::Degenerate { .. })));
        let line: Vec<_> = (0..5).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(matches!(umeyama(&line, &line), Err(DatasetError::Degenerate { .. })));
        assert!(umeyama(&[], &[]).is_err());
    }

    #[test]
    fn origin_alignment_maps_first_pose() {
        let reference = [known(), Isometry3::identity()];
        let estimate = [Isometry3::new(Vector3::new(1.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.4)), known()];
        let t = align_origin(&reference, &estimate).unwrap();
        let moved = t * estimate[0];
        assert!((moved.translation.vector - reference[0].translation.vector).norm() < 1e-12);
        assert!(moved.rotation.angle_to(&reference[0].rotation) < 1e-12);
        assert!(align_origin(&[], &estimate).is_none());
    }
}
