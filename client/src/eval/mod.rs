//! `stillmap-client eval`: trajectory evaluation like evo's `evo_ape` / `evo_rpe`.
//! The numbers are `stillmap_dataset::eval`'s (association, alignment, metrics)
//! and the files `stillmap_dataset::trajectory`'s; this module adds the command's
//! options, its JSON report and the plots ([`plot`]).

pub mod plot;

use std::path::{Path, PathBuf};

pub use stillmap_dataset::DatasetError as EvalError;
pub use stillmap_dataset::eval::*;
pub use stillmap_dataset::trajectory;

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
