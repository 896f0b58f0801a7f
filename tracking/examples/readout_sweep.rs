//! Measures a camera's rolling-shutter readout from a recording, without ground
//! truth: tracks the TUM folder (default fr1_rpy) with each readout from 0 to 40 ms,
//! five times with the feature count nudged, and prints how consistent the map came
//! out: observations of points seen from more than one keyframe (more: keypoints
//! re-found), and their reprojection error (median and 90 % trimmed mean, px² at
//! level 0). A readout the images support keeps more of the map and fits it better;
//! the ground truth's ATE is printed beside it for reference only.
//! `cargo run --release -p stillmap-tracking --example readout_sweep [DIR]`

use stillmap_tracking::testing as tum;

use std::path::PathBuf;

use stillmap_tracking::{Camera, Tracker, TrackerConfig};

/// Readouts tried, milliseconds.
const READOUTS_MS: [f64; 9] = [0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0];
/// Feature counts of the five runs per readout (the clip's sensitivity to tiny input
/// changes makes a single run a poor sample).
const FEATURE_COUNTS: [usize; 5] = [980, 990, 1000, 1010, 1020];
/// Share of the smallest errors the trimmed mean keeps.
const TRIMMED_SHARE: f64 = 0.9;

/// (multi-view observations, median squared error, trimmed mean squared error) of a tracker's map.
fn consistency(tracker: &Tracker) -> (usize, f64, f64) {
    let (map, camera) = (tracker.map(), tracker.camera());
    let scale_factor = f64::from(TrackerConfig::default().scale_factor);
    let mut errors = Vec::new();
    for point in map.points.values().filter(|p| p.observations.len() >= 2) {
        for &(id, feature) in &point.observations {
            let Some(kf) = map.keyframes.get(&id) else { continue };
            let f = &kf.features.features[feature];
            if let Some(pixel) = camera.project(&(kf.world_from_camera.inverse() * point.point_in_world)) {
                let level_scale = scale_factor.powi(i32::from(f.octave));
                errors.push((pixel - f.ideal).norm_squared() / (level_scale * level_scale));
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    let kept = ((errors.len() as f64 * TRIMMED_SHARE) as usize).max(1);
    let median = errors.get(errors.len() / 2).copied().unwrap_or(f64::NAN);
    (errors.len(), median, errors.iter().take(kept).sum::<f64>() / kept as f64)
}

fn main() {
    let dir = std::env::args().nth(1).map(PathBuf::from).unwrap_or_else(tum::fr1_rpy_dir);
    let frames = tum::load(&dir, usize::MAX);
    let gt = tum::groundtruth(&dir);
    println!("| readout | multi-view observations | median error (px²) | trimmed mean (px²) | ATE (reference) |");
    println!("|---|---|---|---|---|");
    for readout_ms in READOUTS_MS {
        let camera = Camera { readout_s: readout_ms * 1e-3, ..tum::fr1_camera() };
        let (mut observations, mut median, mut trimmed, mut ate) = (0.0, 0.0, 0.0, 0.0);
        for features in FEATURE_COUNTS {
            let config = TrackerConfig { features, ..TrackerConfig::default() };
            let offset_s = -camera.readout_s / 2.0;
            let (tracker, est) = tum::track_clip(camera.clone(), config, &frames, |t| stillmap_proto::pose_time_ns(t, offset_s));
            let (o, m, t) = consistency(&tracker);
            observations += o as f64;
            median += m;
            trimmed += t;
            ate += tum::score(&gt, &est).ate_m;
        }
        let n = FEATURE_COUNTS.len() as f64;
        println!("| {readout_ms:.0} ms | {:.0} | {:.4} | {:.4} | {:.2} cm |", observations / n, median / n, trimmed / n, ate / n * 100.0);
    }
}
