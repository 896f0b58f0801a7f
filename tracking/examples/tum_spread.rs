//! How much the tracker's scores on a TUM folder move under tiny changes: the same
//! frames tracked with the ORB feature count nudged by ±1–2 %, one row per run and
//! the spread. On fr1_rpy single runs swing by centimetres (README, "Tracking
//! accuracy"), so a change to the tracker is worth judging on this table, not on
//! one run:
//! `cargo run --release -p stillmap-tracking --example tum_spread [DIR]`
//! (`TRACKING="key = value;..."` overrides the rest of the configuration).

use stillmap_tracking::testing as tum;

use std::path::PathBuf;

use stillmap_tracking::{FrameInput, Tracker, TrackerConfig, TrackingState};

/// Feature counts relative to the configured one.
const NUDGES: [f64; 5] = [0.98, 0.99, 1.0, 1.01, 1.02];

fn main() {
    let dir = std::env::args().nth(1).map(PathBuf::from).unwrap_or_else(tum::fr1_rpy_dir);
    let frames = tum::load(&dir, usize::MAX);
    let gt = tum::groundtruth(&dir);
    let base: TrackerConfig = tum::config_from_env("TRACKING");
    println!("| features | tracked | ATE (cm) | ATE rot, origin-aligned (deg) | RPE (mm) | RPE (deg) |");
    println!("|---|---|---|---|---|---|");
    let mut ates = Vec::new();
    let mut rpes = Vec::new();
    for nudge in NUDGES {
        let features = (base.features as f64 * nudge).round() as usize;
        let config = TrackerConfig { features, candidate_features: base.candidate_features.max(features), ..base.clone() };
        let mut tracker = Tracker::new(tum::fr1_camera_with_readout_from_env(), config).expect("tracker");
        let (mut est, mut tracked) = (Vec::new(), 0);
        for f in &frames {
            let out = tracker
                .track(&FrameInput { timestamp_ns: f.timestamp_ns, rgb: &f.rgb, depth: &f.depth, dynamic_mask: None })
                .expect("track");
            tracked += usize::from(matches!(out.state, TrackingState::Tracking | TrackingState::Relocalized));
            if let Some(p) = out.world_from_camera {
                est.push((tum::fr1_pose_time_ns_from_env(f.timestamp_ns), p));
            }
        }
        let s = tum::score(&gt, &est);
        println!(
            "| {features} | {tracked}/{} | {:.2} | {:.2} | {:.2} | {:.3} |",
            frames.len(),
            s.ate_m * 100.0,
            s.ate_origin_deg,
            s.rpe_m * 1000.0,
            s.rpe_deg
        );
        ates.push(s.ate_m * 100.0);
        rpes.push(s.rpe_m * 1000.0);
    }
    let spread = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (v[v.len() / 2], v[0], v[v.len() - 1])
    };
    let (ate_median, ate_min, ate_max) = spread(&mut ates);
    let (rpe_median, rpe_min, rpe_max) = spread(&mut rpes);
    println!(
        "\nATE median {ate_median:.2} cm (min {ate_min:.2}, max {ate_max:.2}); RPE median {rpe_median:.2} mm (min {rpe_min:.2}, max {rpe_max:.2}) over {} runs",
        NUDGES.len()
    );
}
