//! APE and RPE error vectors and their statistics, as evo's `core.metrics`.

use nalgebra::{Isometry3, UnitQuaternion};
use serde::Serialize;

use crate::DatasetError;

/// What part of the error pose is measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Relation {
    /// Norm of the translation part, metres (evo `trans_part`).
    Translation,
    /// Rotation angle of the rotation part, degrees (evo `angle_deg`).
    RotationDeg,
}

impl Relation {
    /// Unit of the errors.
    pub fn unit(self) -> &'static str {
        match self {
            Relation::Translation => "m",
            Relation::RotationDeg => "deg",
        }
    }

    fn of(self, error: &Isometry3<f64>) -> f64 {
        match self {
            Relation::Translation => error.translation.vector.norm(),
            Relation::RotationDeg => rotation_angle_deg(&error.rotation),
        }
    }
}

/// The rotation angle in degrees, in `[0, 180]`: the norm of scipy's
/// `as_rotvec()`, which evo's `so3_log_angle` uses (`2·atan2(|v|, |w|)`, accurate
/// for small angles where `arccos((trace(R) - 1) / 2)` is not).
pub fn rotation_angle_deg(rotation: &UnitQuaternion<f64>) -> f64 {
    let q = rotation.quaternion();
    (2.0 * q.imag().norm().atan2(q.w.abs())).to_degrees()
}

/// Absolute pose errors: `|p_est - p_ref|` for translation, the angle of
/// `est⁻¹ · ref` for rotation (evo's `APE`).
pub fn ape(reference: &[Isometry3<f64>], estimate: &[Isometry3<f64>], relation: Relation) -> Vec<f64> {
    reference
        .iter()
        .zip(estimate)
        .map(|(r, e)| match relation {
            Relation::Translation => (e.translation.vector - r.translation.vector).norm(),
            Relation::RotationDeg => relation.of(&(e.inverse() * r)),
        })
        .collect()
}

/// evo's consecutive index pairs for a delta in frames (`all_pairs` off):
/// `(0, d), (d, 2d), …` while the second index exists.
pub fn id_pairs(poses: usize, delta: usize) -> Vec<(usize, usize)> {
    let ids: Vec<usize> = (0..poses).step_by(delta.max(1)).collect();
    ids.windows(2).map(|w| (w[0], w[1])).collect()
}

/// Relative pose errors over [`id_pairs`]: `E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)` with `Q`
/// the reference and `P` the estimate (evo's `RPE.rpe_base`).
pub fn rpe(reference: &[Isometry3<f64>], estimate: &[Isometry3<f64>], relation: Relation, delta: usize) -> Result<Vec<f64>, DatasetError> {
    if delta == 0 {
        return Err(DatasetError::NoPairs { delta, poses: reference.len() });
    }
    let pairs = id_pairs(reference.len().min(estimate.len()), delta);
    if pairs.is_empty() {
        return Err(DatasetError::NoPairs { delta, poses: reference.len() });
    }
    Ok(pairs
        .into_iter()
        .map(|(i, j)| {
            let q_rel = reference[i].inverse() * reference[j];
            let p_rel = estimate[i].inverse() * estimate[j];
            relation.of(&(q_rel.inverse() * p_rel))
        })
        .collect())
}

/// Summary statistics of an error vector, defined as evo (numpy) defines them.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    /// `sqrt(mean(e²))`.
    pub rmse: f64,
    /// Arithmetic mean.
    pub mean: f64,
    /// numpy median: the middle value, or the mean of the two middle values.
    pub median: f64,
    /// Population standard deviation (numpy's default, `ddof = 0`).
    pub std: f64,
    /// Smallest error.
    pub min: f64,
    /// Largest error.
    pub max: f64,
    /// Sum of squared errors.
    pub sse: f64,
    /// Number of errors.
    pub count: usize,
}

impl Stats {
    /// Statistics of `errors`, or `None` when it is empty.
    pub fn of(errors: &[f64]) -> Option<Stats> {
        if errors.is_empty() {
            return None;
        }
        let n = errors.len() as f64;
        let sse: f64 = errors.iter().map(|e| e * e).sum();
        let mean = errors.iter().sum::<f64>() / n;
        let var = errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / n;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mid = sorted.len() / 2;
        let median = if sorted.len() % 2 == 1 { sorted[mid] } else { (sorted[mid - 1] + sorted[mid]) / 2.0 };
        Some(Stats {
            rmse: (sse / n).sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: sorted[0],
            max: sorted[sorted.len() - 1],
            sse,
            count: errors.len(),
        })
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;

    #[test]
    fn stats_of_a_known_vector() {
        let s = Stats::of(&[2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0]).unwrap();
        assert_eq!((s.mean, s.std, s.median, s.min, s.max, s.count), (5.0, 2.0, 4.5, 2.0, 9.0, 8));
        assert_eq!(s.sse, 232.0);
        assert!((s.rmse - 29.0f64.sqrt()).abs() < 1e-15);
        assert_eq!(Stats::of(&[3.0, 1.0, 2.0]).unwrap().median, 2.0);
        assert!(Stats::of(&[]).is_none());
    }

    #[test]
    fn rotation_angle_is_accurate_for_small_and_large_angles() {
        for deg in [1e-7f64, 0.5, 90.0, 179.9] {
            let q = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), deg.to_radians());
            assert!((rotation_angle_deg(&q) - deg).abs() < 1e-12 * deg.max(1.0), "{deg}");
            assert!((rotation_angle_deg(&q.inverse()) - deg).abs() < 1e-12 * deg.max(1.0), "{deg}");
        }
    }

    #[test]
    fn pairs_are_consecutive_with_step_delta() {
        assert_eq!(id_pairs(5, 1), vec![(0, 1), (1, 2), (2, 3), (3, 4)]);
        assert_eq!(id_pairs(25, 10), vec![(0, 10), (10, 20)]);
        assert!(id_pairs(5, 5).is_empty());
    }

    #[test]
    fn ape_and_rpe_of_known_errors() {
        let reference: Vec<_> = (0..4).map(|i| Isometry3::translation(i as f64, 0.0, 0.0)).collect();
        let offset = Isometry3::new(Vector3::new(0.0, 0.5, 0.0), Vector3::new(0.0, 0.0, 0.1));
        let estimate: Vec<_> = reference.iter().map(|p| offset * p).collect();
        let trans = ape(&reference, &estimate, Relation::Translation);
        assert!((trans[0] - 0.5).abs() < 1e-15);
        let rot = ape(&reference, &estimate, Relation::RotationDeg);
        assert!(rot.iter().all(|a| (a - 0.1f64.to_degrees()).abs() < 1e-12));
        // A rigid change of the whole trajectory leaves the relative rotations unchanged.
        let rpe_rot = rpe(&reference, &estimate, Relation::RotationDeg, 1).unwrap();
        assert!(rpe_rot.iter().all(|a| a.abs() < 1e-12) && rpe_rot.len() == 3);
        assert!(matches!(rpe(&reference, &estimate, Relation::Translation, 4), Err(DatasetError::NoPairs { .. })));
    }
}
