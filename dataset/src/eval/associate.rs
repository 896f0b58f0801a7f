//! Timestamp association, step for step as evo's `sync.associate_trajectories`
//! (nearest-time method).

use crate::DatasetError;
use crate::eval::Trajectory;

/// Indices of the best matches of `stamps_1` in `stamps_2 + offset_2`, like evo's
/// `matching_time_indices`: binary search when `stamps_2` is sorted, otherwise a
/// linear search; a match is kept when it is at most `max_diff` seconds away.
/// Several stamps of `stamps_1` may match the same stamp of `stamps_2`.
pub fn matching_time_indices(stamps_1: &[f64], stamps_2: &[f64], max_diff: f64, offset_2: f64) -> (Vec<usize>, Vec<usize>) {
    let stamps_2: Vec<f64> = stamps_2.iter().map(|t| t + offset_2).collect();
    let (mut matches_1, mut matches_2) = (Vec::new(), Vec::new());
    let (Some(&first), Some(&last)) = (stamps_2.first(), stamps_2.last()) else {
        return (matches_1, matches_2);
    };
    if !stamps_2.windows(2).all(|w| w[1] - w[0] >= 0.0) {
        for (index_1, &stamp_1) in stamps_1.iter().enumerate() {
            // The first smallest difference, like numpy's argmin.
            let mut best = (0, f64::INFINITY);
            for (index_2, &stamp_2) in stamps_2.iter().enumerate() {
                let diff = (stamp_2 - stamp_1).abs();
                if diff < best.1 {
                    best = (index_2, diff);
                }
            }
            if best.1 <= max_diff {
                matches_1.push(index_1);
                matches_2.push(best.0);
            }
        }
        return (matches_1, matches_2);
    }
    for (index_1, &stamp_1) in stamps_1.iter().enumerate() {
        if stamp_1 < first - max_diff || stamp_1 > last + max_diff {
            continue;
        }
        // numpy's searchsorted(side="right"), clamped to the last index.
        let upper = stamps_2.partition_point(|&t| t <= stamp_1).min(stamps_2.len() - 1);
        let diff_upper = stamps_2[upper] - stamp_1;
        let diff_lower = if upper > 0 { stamp_1 - stamps_2[upper - 1] } else { f64::INFINITY };
        let best = if diff_upper <= max_diff && diff_upper < diff_lower {
            upper
        } else if diff_lower <= max_diff && diff_lower <= diff_upper {
            upper - 1
        } else {
            continue;
        };
        matches_1.push(index_1);
        matches_2.push(best);
    }
    (matches_1, matches_2)
}

/// Reference and estimate poses paired by timestamp, in matching order.
#[derive(Debug, Clone)]
pub struct Associated {
    /// Reference poses, one per pair.
    pub reference: Trajectory,
    /// Estimated poses, one per pair (same length as `reference`).
    pub estimate: Trajectory,
}

/// Pairs `reference` and `estimate` poses like evo's `associate_trajectories`:
/// the trajectory with fewer poses (the estimate on a tie) is walked in order and
/// each of its poses is matched to the nearest pose of the other one, where the
/// estimate's timestamps are shifted by `offset` seconds.
pub fn associate(
    reference: &[(f64, nalgebra::Isometry3<f64>)],
    estimate: &[(f64, nalgebra::Isometry3<f64>)],
    max_diff: f64,
    offset: f64,
) -> Result<Associated, DatasetError> {
    let stamps = |t: &[(f64, _)]| t.iter().map(|p| p.0).collect::<Vec<f64>>();
    let second_longer = estimate.len() > reference.len();
    let (short, long, long_offset) = if second_longer { (reference, estimate, offset) } else { (estimate, reference, -offset) };
    let (ids_short, ids_long) = matching_time_indices(&stamps(short), &stamps(long), max_diff, long_offset);
    if ids_short.is_empty() {
        return Err(DatasetError::NoMatches { max_diff, offset });
    }
    let short: Trajectory = ids_short.iter().map(|&i| short[i]).collect();
    let long: Trajectory = ids_long.iter().map(|&i| long[i]).collect();
    Ok(if second_longer { Associated { reference: short, estimate: long } } else { Associated { reference: long, estimate: short } })
}

#[cfg(test)]
mod tests {
    use nalgebra::Isometry3;

    use super::*;

    fn traj(stamps: &[f64]) -> Trajectory {
        stamps.iter().map(|&t| (t, Isometry3::translation(t, 0.0, 0.0))).collect()
    }

    #[test]
    fn nearest_within_max_diff() {
        let (a, b) = matching_time_indices(&[0.0, 1.04, 2.0, 5.0], &[0.01, 1.0, 1.05, 2.5], 0.02, 0.0);
        assert_eq!(a, vec![0, 1]);
        assert_eq!(b, vec![0, 2]);
    }

    #[test]
    fn boundaries_and_ties_follow_evo() {
        // Exactly max_diff away is accepted; a tie picks the lower stamp.
        let (a, b) = matching_time_indices(&[0.5, 1.5], &[0.25, 0.75, 1.0, 2.0], 0.25, 0.0);
        assert_eq!(a, vec![0]);
        assert_eq!(b, vec![0]);
        // Before the first and after the last stamp, within max_diff.
        let (a, b) = matching_time_indices(&[-0.5, 9.5, 11.0], &[0.0, 10.0], 0.5, 0.0);
        assert_eq!((a, b), (vec![0, 1], vec![0, 1]));
        // Several stamps may match the same one.
        let (a, b) = matching_time_indices(&[0.99, 1.0, 1.01], &[1.0], 0.02, 0.0);
        assert_eq!((a, b), (vec![0, 1, 2], vec![0, 0, 0]));
    }

    #[test]
    fn offset_and_unsorted_stamps() {
        let (a, b) = matching_time_indices(&[10.0, 11.0], &[0.0, 1.0], 0.01, 10.0);
        assert_eq!((a, b), (vec![0, 1], vec![0, 1]));
        let (a, b) = matching_time_indices(&[1.0, 3.0, 2.0], &[3.0, 1.005, 2.0, 1.0], 0.01, 0.0);
        assert_eq!((a, b), (vec![0, 1, 2], vec![3, 0, 2]));
        assert_eq!(matching_time_indices(&[1.0], &[], 0.01, 0.0), (vec![], vec![]));
    }

    #[test]
    fn walks_the_shorter_trajectory_and_keeps_roles() {
        let reference = traj(&[0.0, 0.01, 0.02, 0.03, 0.04, 0.05]);
        let estimate = traj(&[0.011, 0.049, 1.0]);
        let a = associate(&reference, &estimate, 0.005, 0.0).unwrap();
        assert_eq!(a.reference.iter().map(|p| p.0).collect::<Vec<_>>(), vec![0.01, 0.05]);
        assert_eq!(a.estimate.iter().map(|p| p.0).collect::<Vec<_>>(), vec![0.011, 0.049]);
        // Estimate longer: the reference is walked and the offset moves the estimate.
        let a = associate(&estimate, &reference, 0.005, 1.0).unwrap();
        assert_eq!(a.reference.iter().map(|p| p.0).collect::<Vec<_>>(), vec![1.0]);
        assert_eq!(a.estimate.iter().map(|p| p.0).collect::<Vec<_>>(), vec![0.0]);
        assert!(matches!(associate(&reference, &traj(&[7.0]), 0.02, 0.0), Err(DatasetError::NoMatches { .. })));
    }
}
