//! Trajectory evaluation, computing what evo's `evo_ape` / `evo_rpe` compute:
//! timestamp association ([`associate`]), Umeyama and origin alignment
//! ([`align`]), APE / RPE errors and statistics ([`metrics`]); TUM files are read by
//! [`crate::trajectory`].
//!
//! [`evaluate`] is pure: it takes `(timestamp, pose)` lists and does no I/O, so the
//! client's `eval` command, the tests and the benches share it. [`summary`] is the
//! one-call score the accuracy tests and benches print.

pub mod align;
pub mod associate;
pub mod metrics;

use std::fmt::Write as _;

use nalgebra::Isometry3;
use serde::Serialize;

pub use metrics::{Relation, Stats};

use crate::DatasetError;

/// Poses with their timestamps in seconds, in file order.
pub type Trajectory = Vec<(f64, Isometry3<f64>)>;

/// Default `--t-max-diff`: 20 ms (evo's default is 10 ms).
pub const DEFAULT_MAX_DIFF_S: f64 = 0.02;
/// Default `--delta` of the RPE, in frames.
pub const DEFAULT_DELTA: usize = 1;

/// Absolute or relative pose error.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Metric {
    /// Absolute pose error (evo_ape).
    Ape,
    /// Relative pose error between poses `delta` frames apart (evo_rpe, consecutive pairs).
    Rpe { delta: usize },
}

/// How the estimate is aligned to the reference before the errors are taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Alignment {
    /// As is.
    None,
    /// SE(3) Umeyama on the associated positions (evo `-a`).
    Se3,
    /// First associated estimated pose onto the first reference pose (evo `--align_origin`).
    Origin,
}

/// What to compute.
#[derive(Debug, Clone, PartialEq)]
pub struct EvalOptions {
    /// APE or RPE.
    pub metric: Metric,
    /// Alignment before the errors.
    pub alignment: Alignment,
    /// The relations to report, in order.
    pub relations: Vec<Relation>,
    /// Largest timestamp difference of an associated pair, seconds.
    pub max_diff: f64,
    /// Added to the estimate's timestamps before association, seconds.
    pub offset: f64,
}

/// The result of [`evaluate`].
#[derive(Debug, Clone)]
pub struct Evaluation {
    /// The options it was computed with.
    pub options: EvalOptions,
    /// Associated reference poses.
    pub reference: Trajectory,
    /// Associated estimated poses, after the alignment.
    pub estimate: Trajectory,
    /// The transform applied to the estimate, if aligned.
    pub transform: Option<Isometry3<f64>>,
    /// Statistics per requested relation.
    pub stats: Vec<(Relation, Stats)>,
}

/// Associates, aligns and measures `estimate` against `reference` like evo.
pub fn evaluate(
    reference: &[(f64, Isometry3<f64>)],
    estimate: &[(f64, Isometry3<f64>)],
    options: &EvalOptions,
) -> Result<Evaluation, DatasetError> {
    let synced = associate::associate(reference, estimate, options.max_diff, options.offset)?;
    let ref_poses: Vec<Isometry3<f64>> = synced.reference.iter().map(|p| p.1).collect();
    let est_poses: Vec<Isometry3<f64>> = synced.estimate.iter().map(|p| p.1).collect();
    let transform = match options.alignment {
        Alignment::None => None,
        Alignment::Se3 => Some(align::align_se3(&ref_poses, &est_poses)?),
        Alignment::Origin => align::align_origin(&ref_poses, &est_poses),
    };
    let est_poses: Vec<Isometry3<f64>> = match transform {
        Some(t) => est_poses.iter().map(|p| t * p).collect(),
        None => est_poses,
    };
    let mut stats = Vec::with_capacity(options.relations.len());
    for &relation in &options.relations {
        let (errors, delta) = match options.metric {
            Metric::Ape => (metrics::ape(&ref_poses, &est_poses, relation), 0),
            Metric::Rpe { delta } => (metrics::rpe(&ref_poses, &est_poses, relation, delta)?, delta),
        };
        let empty = DatasetError::NoPairs { delta, poses: ref_poses.len() };
        stats.push((relation, Stats::of(&errors).ok_or(empty)?));
    }
    let estimate = synced.estimate.iter().zip(est_poses).map(|(s, p)| (s.0, p)).collect();
    Ok(Evaluation { options: options.clone(), reference: synced.reference, estimate, transform, stats })
}

/// Machine-readable result (`--json`).
#[derive(Debug, Serialize)]
pub struct Report {
    /// `ape` or `rpe`.
    pub metric: &'static str,
    /// RPE delta in frames (absent for APE).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub delta: Option<usize>,
    /// Alignment used.
    pub alignment: Alignment,
    /// Association window, seconds.
    pub t_max_diff: f64,
    /// Estimate time offset, seconds.
    pub t_offset: f64,
    /// Reference file and its pose count.
    pub reference: Source,
    /// Estimate file and its pose count.
    pub estimate: Source,
    /// Associated pose pairs.
    pub associated: usize,
    /// The applied 4x4 transform, row-major, if aligned.
    pub alignment_transform: Option<[[f64; 4]; 4]>,
    /// Translation error statistics, metres.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub translation: Option<Stats>,
    /// Rotation angle error statistics, degrees.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rotation: Option<Stats>,
}

/// A trajectory file in a [`Report`].
#[derive(Debug, Serialize)]
pub struct Source {
    /// The path as given.
    pub path: String,
    /// Poses in the file.
    pub poses: usize,
}

impl Evaluation {
    fn stats_of(&self, relation: Relation) -> Option<Stats> {
        self.stats.iter().find(|(r, _)| *r == relation).map(|(_, s)| *s)
    }

    /// The [`Report`] of this evaluation for the given input files.
    pub fn report(&self, reference: Source, estimate: Source) -> Report {
        let (metric, delta) = match self.options.metric {
            Metric::Ape => ("ape", None),
            Metric::Rpe { delta } => ("rpe", Some(delta)),
        };
        let alignment_transform = self.transform.map(|t| {
            let m = t.to_homogeneous();
            std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
        });
        Report {
            metric,
            delta,
            alignment: self.options.alignment,
            t_max_diff: self.options.max_diff,
            t_offset: self.options.offset,
            reference,
            estimate,
            associated: self.reference.len(),
            alignment_transform,
            translation: self.stats_of(Relation::Translation),
            rotation: self.stats_of(Relation::RotationDeg),
        }
    }

    /// A one-line description of what was compared.
    pub fn title(&self) -> String {
        let metric = match self.options.metric {
            Metric::Ape => "APE".to_string(),
            Metric::Rpe { delta } => format!("RPE, delta {delta} frame{}", if delta == 1 { "" } else { "s" }),
        };
        let alignment = match self.options.alignment {
            Alignment::None => "not aligned",
            Alignment::Se3 => "SE(3) Umeyama alignment",
            Alignment::Origin => "origin alignment",
        };
        format!("{metric}, {alignment}")
    }

    /// The human-readable table: header lines, then one column per relation.
    pub fn table(&self, reference: &Source, estimate: &Source) -> String {
        let mut out = String::new();
        let _ = writeln!(out, "{}", self.title());
        let _ = writeln!(out, "reference {} ({} poses)", reference.path, reference.poses);
        let _ = writeln!(out, "estimate  {} ({} poses)", estimate.path, estimate.poses);
        let _ = write!(
            out,
            "associated {} pose pairs (max diff {} s, offset {} s)",
            self.reference.len(),
            self.options.max_diff,
            self.options.offset
        );
        if let Some((_, s)) = self.stats.first().filter(|_| matches!(self.options.metric, Metric::Rpe { .. })) {
            let _ = write!(out, ", {} relative pairs", s.count);
        }
        out.push('\n');
        let _ = write!(out, "{:<8}", "");
        for (relation, _) in &self.stats {
            let name = match relation {
                Relation::Translation => "translation (m)",
                Relation::RotationDeg => "rotation (deg)",
            };
            let _ = write!(out, "{name:>17}");
        }
        out.push('\n');
        type Field = fn(&Stats) -> f64;
        let rows: [(&str, Field); 6] = [
            ("rmse", |s| s.rmse),
            ("mean", |s| s.mean),
            ("median", |s| s.median),
            ("std", |s| s.std),
            ("min", |s| s.min),
            ("max", |s| s.max),
        ];
        for (name, field) in rows {
            let _ = write!(out, "{name:<8}");
            for (_, s) in &self.stats {
                let _ = write!(out, "{:>17.6}", field(s));
            }
            out.push('\n');
        }
        out
    }
}

/// The summary score of a trajectory with nanosecond timestamps, as the accuracy
/// tests and benches print it.
#[derive(Debug, Clone, Copy)]
pub struct Scores {
    /// Estimated poses with a ground-truth pose within 20 ms.
    pub pairs: usize,
    /// ATE after SE(3) Umeyama alignment: RMS translation error (m) ...
    pub ate_m: f64,
    /// ... and RMS rotation error (degrees).
    pub ate_deg: f64,
    /// RMS rotation error (degrees) with the first pose aligned instead.
    pub ate_origin_deg: f64,
    /// RPE over consecutive poses: RMS translation (m) and rotation (degrees).
    pub rpe_m: f64,
    pub rpe_deg: f64,
}

/// Scores `estimate` against `reference` (evo semantics): each estimated pose is
/// paired with the nearest reference pose within 20 ms (several may share one),
/// aligned by SE(3) Umeyama for the ATE ([`align::align_se3`], [`metrics::ape`]),
/// by its first pose for `ate_origin_deg`, and the RPE taken over consecutive pairs
/// ([`metrics::rpe`], delta 1).
pub fn summary(reference: &[(u64, Isometry3<f64>)], estimate: &[(u64, Isometry3<f64>)]) -> Result<Scores, DatasetError> {
    let reference_ns: Vec<u64> = reference.iter().map(|p| p.0).collect();
    let mut sorted: Vec<(u64, usize)> = reference_ns.iter().copied().zip(0..).collect();
    sorted.sort_unstable();
    let sorted_ns: Vec<u64> = sorted.iter().map(|p| p.0).collect();
    let (mut ref_poses, mut est_poses) = (Vec::new(), Vec::new());
    for (t, pose) in estimate {
        if let Some(k) = crate::tum::nearest(&sorted_ns, *t, MAX_DIFF_NS + 1) {
            ref_poses.push(reference[sorted[k].1].1);
            est_poses.push(*pose);
        }
    }
    if ref_poses.is_empty() {
        return Err(DatasetError::NoMatches { max_diff: DEFAULT_MAX_DIFF_S, offset: 0.0 });
    }
    let transform = align::align_se3(&ref_poses, &est_poses)?;
    let aligned: Vec<Isometry3<f64>> = est_poses.iter().map(|p| transform * p).collect();
    let rmse = |errors: &[f64]| Stats::of(errors).map_or(0.0, |s| s.rmse);
    // Both lists hold at least the three positions the SE(3) alignment needed.
    let origin = align::align_origin(&ref_poses, &est_poses).expect("paired poses");
    let at_origin: Vec<Isometry3<f64>> = est_poses.iter().map(|p| origin * p).collect();
    let rpe_m = rmse(&metrics::rpe(&ref_poses, &est_poses, Relation::Translation, 1)?);
    let rpe_deg = rmse(&metrics::rpe(&ref_poses, &est_poses, Relation::RotationDeg, 1)?);
    Ok(Scores {
        pairs: ref_poses.len(),
        ate_m: rmse(&metrics::ape(&ref_poses, &aligned, Relation::Translation)),
        ate_deg: rmse(&metrics::ape(&ref_poses, &aligned, Relation::RotationDeg)),
        ate_origin_deg: rmse(&metrics::ape(&ref_poses, &at_origin, Relation::RotationDeg)),
        rpe_m,
        rpe_deg,
    })
}

/// [`DEFAULT_MAX_DIFF_S`] in nanoseconds.
const MAX_DIFF_NS: u64 = 20_000_000;

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;

    fn options(metric: Metric, alignment: Alignment) -> EvalOptions {
        EvalOptions {
            metric,
            alignment,
            relations: vec![Relation::Translation, Relation::RotationDeg],
            max_diff: DEFAULT_MAX_DIFF_S,
            offset: 0.0,
        }
    }

    #[test]
    fn aligned_ape_of_a_rigidly_moved_trajectory_is_zero() {
        let reference: Trajectory = (0..50)
            .map(|i| {
                let s = i as f64 * 0.1;
                (s, Isometry3::new(Vector3::new(s.sin(), s.cos(), 0.1 * s), Vector3::new(0.0, 0.2 * s, 0.1)))
            })
            .collect();
        let moved = Isometry3::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.1, 0.2, -0.3));
        let estimate: Trajectory = reference.iter().map(|(t, p)| (t + 0.005, moved * p)).collect();
        for alignment in [Alignment::Se3, Alignment::Origin] {
            let e = evaluate(&reference, &estimate, &options(Metric::Ape, alignment)).unwrap();
            assert_eq!(e.reference.len(), 50);
            assert!(e.stats.iter().all(|(_, s)| s.max < 1e-9), "{alignment:?} {:?}", e.stats);
        }
        let e = evaluate(&reference, &estimate, &options(Metric::Ape, Alignment::None)).unwrap();
        assert!(e.stats[0].1.min > 0.1);
        let e = evaluate(&reference, &estimate, &options(Metric::Rpe { delta: 10 }, Alignment::None)).unwrap();
        assert_eq!(e.stats[0].1.count, 4);
        assert!(e.stats.iter().all(|(_, s)| s.max < 1e-9));
        let table = e.table(&Source { path: "gt".into(), poses: 50 }, &Source { path: "est".into(), poses: 50 });
        assert!(table.contains("RPE, delta 10 frames") && table.contains("rmse"), "{table}");
    }

    /// The summary pairs each estimate with the nearest reference pose within
    /// 20 ms, aligns by SE(3) (a rigid move scores 0) and measures the RPE on the
    /// unaligned poses; an estimate with no reference pose nearby is an error.
    #[test]
    fn summary_of_a_rigidly_moved_and_of_a_shifted_trajectory() {
        let ms = 1_000_000u64;
        let reference: Vec<(u64, Isometry3<f64>)> = (0..60)
            .map(|i| {
                let s = i as f64 * 0.1;
                (i * 33 * ms, Isometry3::new(Vector3::new(s.sin(), s.cos(), 0.1 * s), Vector3::new(0.0, 0.2 * s, 0.1)))
            })
            .collect();
        let moved = Isometry3::new(Vector3::new(1.0, -2.0, 0.5), Vector3::new(0.1, 0.2, -0.3));
        // 5 ms late, and one pose 100 ms away from any reference pose.
        let mut estimate: Vec<(u64, Isometry3<f64>)> = reference.iter().map(|(t, p)| (t + 5 * ms, moved * p)).collect();
        estimate.push((60 * 33 * ms + 100 * ms, Isometry3::identity()));
        let s = summary(&reference, &estimate).unwrap();
        assert_eq!(s.pairs, 60);
        assert!(s.ate_m < 1e-9 && s.ate_deg < 1e-6 && s.ate_origin_deg < 1e-6 && s.rpe_m < 1e-9 && s.rpe_deg < 1e-6, "{s:?}");
        // Every position 1 cm off along x: aligned away; the origin rotation is unaffected.
        let shifted: Vec<(u64, Isometry3<f64>)> =
            reference.iter().enumerate().map(|(i, (t, p))| (*t, Isometry3::translation(0.01 * (i % 2) as f64, 0.0, 0.0) * p)).collect();
        let s = summary(&reference, &shifted).unwrap();
        assert!((s.ate_m - 0.005).abs() < 5e-4, "{s:?}");
        assert!(s.rpe_m > 0.009 && s.ate_origin_deg < 1e-9, "{s:?}");
        assert!(matches!(summary(&reference, &[(10_000 * ms, Isometry3::identity())]), Err(DatasetError::NoMatches { .. })));
    }
}
