//! Measures how much a camera's depth should weigh against its keypoints, from a
//! recording and without ground truth. The tracker's measurement has a reprojection
//! residual (u, v, px) and, where the keypoint has depth, a disparity residual
//! `fx·b/z` whose scale is the virtual baseline `b` (`tracking.depth_baseline_m`);
//! both are weighted alike. They are balanced when the two kinds of residual
//! scatter alike over the map. For each baseline this prints the spread of both
//! kinds over the inlier observations of points seen from at least two keyframes,
//! after local bundle adjustment, corrected for what the fitted points absorbed
//! (variance-component estimation with redundancy numbers), averaged over five runs
//! with the feature count nudged, and the baseline that would make the spreads
//! equal, `b · σ_uv / σ_d`. The balanced baseline is where that agrees with `b`
//! (the fixed point of the iteration). The ground truth's ATE and RPE are printed
//! for reference only.
//! `cargo run --release -p stillmap-tracking --example depth_weight [DIR]`

use stillmap_tracking::testing as tum;

use std::path::PathBuf;

use nalgebra::Matrix3;
use stillmap_tracking::geometry::{Measurement, linearise};
use stillmap_tracking::{Tracker, TrackerConfig};

/// Baselines tried, metres.
const BASELINES_M: [f64; 7] = [0.04, 0.08, 0.16, 0.24, 0.32, 0.4, 0.48];
/// Feature counts of the five runs per baseline.
const FEATURE_COUNTS: [usize; 5] = [980, 990, 1000, 1010, 1020];
/// Points need this many keyframe observations to leave any redundancy.
const MIN_OBSERVATIONS: usize = 2;

/// (σ of the reprojection rows, σ of the disparity rows, disparity rows), in the
/// solver's units (each row weighted by 1/level scale²), by variance-component
/// estimation: each group's weighted squared residuals over its redundancy (rows
/// minus the share of them the point positions absorbed: 1 − leverage, with the
/// keyframe poses held), over the inlier observations of points seen at least twice.
fn residual_spreads(tracker: &Tracker, baseline_m: f64) -> (f64, f64, usize) {
    let (map, camera) = (tracker.map(), tracker.camera());
    let scale_factor = f64::from(TrackerConfig::default().scale_factor);
    let bf = camera.fx * baseline_m;
    let (mut sum_uv, mut redundancy_uv, mut sum_d, mut redundancy_d, mut rows_d) = (0.0, 0.0, 0.0, 0.0, 0);
    for point in map.points.values().filter(|p| p.observations.len() >= MIN_OBSERVATIONS) {
        let mut inliers = Vec::new();
        for &(id, feature) in &point.observations {
            let Some(kf) = map.keyframes.get(&id) else { continue };
            let f = &kf.features.features[feature];
            let level_scale = scale_factor.powi(i32::from(f.octave));
            let m = Measurement { ideal: f.ideal, disparity: f.depth.map(|z| bf / z), information: 1.0 / (level_scale * level_scale) };
            if let Some(lin) = linearise(camera, bf, &kf.world_from_camera.inverse(), &point.point_in_world, &m)
                && lin.error.rows(0, lin.rows).norm_squared() * m.information <= m.chi2_threshold()
            {
                inliers.push((lin, m.information));
            }
        }
        // Two rows from one keyframe cannot fix a point's three coordinates.
        if inliers.len() < MIN_OBSERVATIONS {
            continue;
        }
        let mut normal = Matrix3::zeros();
        for (lin, w) in &inliers {
            let j = lin.d_point.rows(0, lin.rows);
            normal += j.transpose() * j * *w;
        }
        let Some(covariance) = normal.try_inverse() else { continue };
        for (lin, w) in &inliers {
            let leverage = lin.d_point * covariance * lin.d_point.transpose() * *w;
            for row in 0..lin.rows {
                // Leverage lies in 0..=1; rounding on a nearly degenerate point must not push it out.
                let (square, redundancy) = (lin.error[row] * lin.error[row] * w, 1.0 - leverage[(row, row)].clamp(0.0, 1.0));
                if row < 2 {
                    sum_uv += square;
                    redundancy_uv += redundancy;
                } else {
                    sum_d += square;
                    redundancy_d += redundancy;
                    rows_d += 1;
                }
            }
        }
    }
    ((sum_uv / redundancy_uv).sqrt(), (sum_d / redundancy_d).sqrt(), rows_d)
}

fn main() {
    let dir = std::env::args().nth(1).map(PathBuf::from).unwrap_or_else(tum::fr1_rpy_dir);
    let frames = tum::load(&dir, usize::MAX);
    let gt = tum::groundtruth(&dir);
    println!("| baseline | observations with depth | σ_uv (px) | σ_d (px) | balanced baseline b·σ_uv/σ_d | ATE, RPE (reference only) |");
    println!("|---|---|---|---|---|---|");
    for baseline_m in BASELINES_M {
        let (mut s_uv, mut s_d, mut count, mut ate, mut rpe) = (0.0, 0.0, 0, 0.0, 0.0);
        for features in FEATURE_COUNTS {
            let config = TrackerConfig { features, depth_baseline_m: baseline_m, ..TrackerConfig::default() };
            let (tracker, est) = tum::track_clip(tum::fr1_camera(), config, &frames, tum::fr1_pose_time_ns);
            let (a, b, n) = residual_spreads(&tracker, baseline_m);
            s_uv += a;
            s_d += b;
            count += n;
            let s = tum::score(&gt, &est);
            ate += s.ate_m;
            rpe += s.rpe_m;
        }
        let n = FEATURE_COUNTS.len() as f64;
        let (s_uv, s_d) = (s_uv / n, s_d / n);
        println!(
            "| {baseline_m:.2} m | {:.0} | {s_uv:.3} | {s_d:.3} | {:.3} m | {:.2} cm, {:.2} mm |",
            count as f64 / n,
            baseline_m * s_uv / s_d,
            ate / n * 100.0,
            rpe / n * 1000.0
        );
    }
}
