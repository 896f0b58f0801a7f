//! Trajectory evaluation, computing what evo's `evo_ape` / `evo_rpe` compute:
//! TUM files ([`trajectory`]), timestamp association ([`associate`]), Umeyama and
//! origin alignment ([`align`]), APE / RPE errors and statistics ([`metrics`]),
//! and plots ([`plot`]).
//!
//! The numeric core ([`evaluate`]) is pure: it takes `(timestamp, pose)` lists and
//! does no I/O, so the server and tests can reuse it. [`run`] adds the files.

pub mod align;
pub mod associate;
pub mod metrics;
pub mod plot;
pub mod trajectory;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Isometry3;
use serde::Serialize;

pub use metrics::{Relation, Stats};

/// Poses with their timestamps in seconds, in file order.
pub type Trajectory = Vec<(f64, Isometry3<f64>)>;

/// Default `--t-max-diff`: 20 ms (evo's default is 10 ms).
pub const DEFAULT_MAX_DIFF_S: f64 = 0.02;
/// Default `--delta` of the RPE, in frames.
pub const DEFAULT_DELTA: usize = 1;

/// Errors of trajectory evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// Invalid options.
    #[error("{0}")]
    Usage(String),
    /// A trajectory file cannot be read.
    #[error("cannot read {}: {source}", path.display())]
    Read { path: PathBuf, source: std::io::Error },
    /// A malformed line in a trajectory file (1-based line number).
    #[error("{}:{line}: {message}", path.display())]
    Parse { path: PathBuf, line: usize, message: String },
    /// A trajectory file without poses.
    #[error("{}: no poses (expected lines `timestamp tx ty tz qx qy qz qw`)", path.display())]
    Empty { path: PathBuf },
    /// No estimated pose is close enough in time to a reference pose.
    #[error("no matching timestamps between reference and estimate (max diff {max_diff} s, offset {offset} s)")]
    NoMatches { max_diff: f64, offset: f64 },
    /// Umeyama alignment needs positions that span at least a plane.
    #[error("cannot align {points} associated positions: degenerate covariance (they do not span a plane)")]
    Degenerate { points: usize },
    /// The RPE delta leaves no pose pairs.
    #[error("delta {delta} frames leaves no pose pairs among {poses} associated poses")]
    NoPairs { delta: usize, poses: usize },
    /// An output file cannot be written.
    #[error("cannot write {}: {message}", path.display())]
    Write { path: PathBuf, message: String },
}

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
) -> Result<Evaluation, EvalError> {
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
        let empty = EvalError::NoPairs { delta, poses: ref_poses.len() };
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

/// Inputs and outputs of `stillmap-client eval`.
#[derive(Debug, Clone)]
pub struct RunArgs {
    /// Reference trajectory (TUM file).
    pub reference: PathBuf,
    /// Estimated trajectory (TUM file).
    pub estimate: PathBuf,
    /// What to compute.
    pub options: EvalOptions,
    /// Write the [`Report`] here as JSON.
    pub json: Option<PathBuf>,
    /// Write a plot here (`.png` or `.svg`).
    pub plot: Option<PathBuf>,
}

/// Reads the files, evaluates, writes the JSON and the plot; returns the table.
pub fn run(args: &RunArgs) -> Result<String, EvalError> {
    let o = &args.options;
    if !(o.max_diff.is_finite() && o.max_diff >= 0.0) {
        return Err(EvalError::Usage(format!("--t-max-diff {} must be a non-negative number of seconds", o.max_diff)));
    }
    if !o.offset.is_finite() {
        return Err(EvalError::Usage(format!("--t-offset {} must be a number of seconds", o.offset)));
    }
    if let Metric::Rpe { delta: 0 } = o.metric {
        return Err(EvalError::Usage("--delta must be at least 1".into()));
    }
    if let Some(plot) = &args.plot {
        plot::Format::of(plot)?;
    }
    let reference = trajectory::read_tum(&args.reference)?;
    let estimate = trajectory::read_tum(&args.estimate)?;
    let evaluation = evaluate(&reference, &estimate, o)?;
    let source = |path: &Path, poses: usize| Source { path: path.display().to_string(), poses };
    let (ref_source, est_source) = (source(&args.reference, reference.len()), source(&args.estimate, estimate.len()));
    let table = evaluation.table(&ref_source, &est_source);
    if let Some(path) = &args.json {
        let report = evaluation.report(ref_source, est_source);
        let write_error = |message: String| EvalError::Write { path: path.clone(), message };
        let text = serde_json::to_string_pretty(&report).map_err(|e| write_error(e.to_string()))?;
        std::fs::write(path, text + "\n").map_err(|e| write_error(e.to_string()))?;
    }
    if let Some(path) = &args.plot {
        plot::plot(path, &evaluation)?;
    }
    Ok(table)
}

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
}
