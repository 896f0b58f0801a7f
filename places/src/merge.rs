//! When a session joins the fleet's frame.
//!
//! Each verified match between a keyframe of the session and one of the fleet's
//! proposes a `fleet_from_session`. One match can be a look-alike that passed
//! verification; several keyframes of the session agreeing on the same transform
//! cannot all be (ORB-SLAM asks three consecutive consistent loop candidates,
//! COVINS a consistent group). The detector keeps the last proposals and merges
//! when enough of them agree.

use std::collections::VecDeque;

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use crate::PlacesError;

/// When proposals agree, and how many are needed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MergeConfig {
    /// Proposals (from distinct query keyframes) that must agree.
    pub consistent: usize,
    /// Two proposals agree when they differ by at most this much.
    pub max_translation_m: f64,
    pub max_rotation_deg: f64,
    /// Only the last this many proposals are compared.
    pub window: usize,
}

impl Default for MergeConfig {
    fn default() -> Self {
        Self { consistent: 3, max_translation_m: 0.05, max_rotation_deg: 2.0, window: 8 }
    }
}

impl MergeConfig {
    pub fn validate(&self) -> Result<(), PlacesError> {
        if self.consistent < 1 || self.window < self.consistent || !(self.max_translation_m > 0.0 && self.max_rotation_deg > 0.0) {
            return Err(PlacesError::Config("merge: consistent must be at least 1 and at most window, the tolerances positive".into()));
        }
        Ok(())
    }
}

/// A merge: the session's frame in the fleet's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Merged {
    pub fleet_from_session: Isometry3<f64>,
    /// Proposals that agreed, and their verification inliers together.
    pub support: usize,
    pub inliers: usize,
}

/// A proposed `fleet_from_session` from one verified match: the fleet keyframe's
/// pose, the verified relative pose, and the session keyframe's pose (composed
/// right to left: session → query camera → candidate camera → fleet).
pub fn propose(
    fleet_from_candidate: &Isometry3<f64>,
    query_from_candidate: &Isometry3<f64>,
    session_from_query: &Isometry3<f64>,
) -> Isometry3<f64> {
    fleet_from_candidate * query_from_candidate.inverse() * session_from_query.inverse()
}

/// Proposals and their verification inliers.
type Group = Vec<(Isometry3<f64>, usize)>;

/// Collects proposals for one session until enough agree.
#[derive(Debug, Clone)]
pub struct MergeDetector {
    config: MergeConfig,
    proposals: VecDeque<(Isometry3<f64>, usize)>,
}

impl MergeDetector {
    pub fn new(config: MergeConfig) -> Result<Self, PlacesError> {
        config.validate()?;
        Ok(Self { config, proposals: VecDeque::new() })
    }

    /// Adds the best proposal of one query keyframe (and its verification
    /// inliers); returns the merge once `consistent` recent proposals agree: their
    /// mean weighted by inliers (the chordal mean of the rotations), which halves
    /// the error of a single proposal for four of them.
    pub fn observe(&mut self, fleet_from_session: Isometry3<f64>, inliers: usize) -> Option<Merged> {
        self.proposals.push_back((fleet_from_session, inliers));
        while self.proposals.len() > self.config.window {
            self.proposals.pop_front();
        }
        let agree = |a: &Isometry3<f64>, b: &Isometry3<f64>| {
            let d = a.inverse() * b;
            d.translation.vector.norm() <= self.config.max_translation_m && d.rotation.angle() <= self.config.max_rotation_deg.to_radians()
        };
        // (agreeing proposals, their inliers, the proposals)
        let mut best: Option<(usize, usize, Group)> = None;
        for (centre, _) in &self.proposals {
            let group: Vec<(Isometry3<f64>, usize)> = self.proposals.iter().filter(|(p, _)| agree(centre, p)).copied().collect();
            let total: usize = group.iter().map(|g| g.1).sum();
            if group.len() >= self.config.consistent && best.as_ref().is_none_or(|b| (group.len(), total) > (b.0, b.1)) {
                best = Some((group.len(), total, group));
            }
        }
        let (support, inliers, group) = best?;
        Some(Merged { fleet_from_session: weighted_mean(&group), support, inliers })
    }
}

/// The inlier-weighted mean of nearby transforms: mean translation, and the
/// rotation nearest to the weighted sum of the rotation matrices.
fn weighted_mean(group: &[(Isometry3<f64>, usize)]) -> Isometry3<f64> {
    let total: f64 = group.iter().map(|g| g.1.max(1) as f64).sum();
    let t = group.iter().map(|(p, n)| p.translation.vector * (*n.max(&1)) as f64).sum::<Vector3<f64>>() / total;
    let m: Matrix3<f64> = group.iter().map(|(p, n)| p.rotation.to_rotation_matrix().into_inner() * (*n.max(&1)) as f64).sum();
    let svd = m.svd(true, true);
    let rotation = match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => {
            let mut s = Matrix3::identity();
            if (u * v_t).determinant() < 0.0 {
                s[(2, 2)] = -1.0;
            }
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(u * s * v_t))
        }
        _ => group[0].0.rotation,
    };
    Isometry3::from_parts(Translation3::from(t), rotation)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn pose(x: f64, yaw_deg: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, 0.0, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw_deg.to_radians()))
    }

    #[test]
    fn merges_only_when_enough_proposals_agree() {
        let mut d = MergeDetector::new(MergeConfig::default()).expect("config");
        assert!(d.observe(pose(1.0, 10.0), 80).is_none());
        assert!(d.observe(pose(-3.0, 90.0), 300).is_none(), "a look-alike's proposal");
        assert!(d.observe(pose(1.02, 10.5), 120).is_none(), "two agree, three are needed");
        let m = d.observe(pose(0.99, 9.5), 90).expect("three agree");
        assert_eq!((m.support, m.inliers), (3, 290));
        // The inlier-weighted mean: x = (80·1.0 + 120·1.02 + 90·0.99) / 290, yaw likewise.
        let x = (80.0 * 1.0 + 120.0 * 1.02 + 90.0 * 0.99) / 290.0;
        let yaw = (80.0 * 10.0 + 120.0 * 10.5 + 90.0 * 9.5) / 290.0;
        let error = pose(x, yaw).inverse() * m.fleet_from_session;
        assert!(error.translation.vector.norm() < 1e-9 && error.rotation.angle() < 1e-4, "{error:?}");
    }

    #[test]
    fn proposals_compose_right_to_left() {
        let (fleet_from_candidate, query_from_candidate, session_from_query) = (pose(1.0, 30.0), pose(0.2, -5.0), pose(-0.5, 12.0));
        let fleet_from_session = propose(&fleet_from_candidate, &query_from_candidate, &session_from_query);
        // The query camera, reached through the session and through the candidate, is one place.
        let via_session = fleet_from_session * session_from_query;
        let via_candidate = fleet_from_candidate * query_from_candidate.inverse();
        assert!((via_session.inverse() * via_candidate).translation.vector.norm() < 1e-12);
        assert!(MergeDetector::new(MergeConfig { consistent: 9, ..MergeConfig::default() }).is_err());
    }
}
