//! Runs the tracker over a TUM folder and prints scores and stage times:
//! `cargo run --release -p stillmap-tracking --example tum [DIR]`.

use stillmap_tracking::testing as tum;

use std::path::PathBuf;

use stillmap_tracking::{FrameInput, Tracker, TrackerConfig, TrackingState};

fn main() {
    let dir = std::env::args().nth(1).map(PathBuf::from).unwrap_or_else(tum::fr1_rpy_dir);
    let frames = tum::load(&dir, usize::MAX);
    let gt = tum::groundtruth(&dir);
    let config: TrackerConfig = tum::config_from_env("TRACKING");
    let mut tracker = Tracker::new(tum::fr1_camera_with_readout_from_env(), config).expect("tracker");
    let mut est = Vec::new();
    let mut totals = Vec::new();
    let mut tracked = 0;
    for f in &frames {
        let out =
            tracker.track(&FrameInput { timestamp_ns: f.timestamp_ns, rgb: &f.rgb, depth: &f.depth, dynamic_mask: None }).expect("track");
        if matches!(out.state, TrackingState::Tracking | TrackingState::Relocalized) {
            tracked += 1;
        }
        if let Some(p) = out.world_from_camera {
            est.push((tum::fr1_pose_time_ns_from_env(f.timestamp_ns), p));
        }
        if std::env::var_os("VERBOSE").is_some() {
            let g = |t: u64| gt.iter().min_by_key(|(g, _)| g.abs_diff(t)).map(|x| x.1).expect("gt");
            let rel = match (est.len() >= 2, out.world_from_camera) {
                (true, Some(_)) => {
                    let (t0, p0) = est[est.len() - 2];
                    let (t1, p1) = est[est.len() - 1];
                    let de = p0.inverse() * p1;
                    let dg = g(t0).inverse() * g(t1);
                    format!(
                        "est {:.2}deg {:.1}mm gt {:.2}deg {:.1}mm err {:.2}deg {:.1}mm",
                        de.rotation.angle().to_degrees(),
                        de.translation.vector.norm() * 1e3,
                        dg.rotation.angle().to_degrees(),
                        dg.translation.vector.norm() * 1e3,
                        (dg.inverse() * de).rotation.angle().to_degrees(),
                        (dg.inverse() * de).translation.vector.norm() * 1e3
                    )
                }
                _ => String::new(),
            };
            println!(
                "{:?} feats {} tracked {} kf {} {rel} {:.1}ms",
                out.state,
                out.features,
                out.tracked_points,
                out.keyframe,
                out.times.total.as_secs_f64() * 1e3
            );
        }
        totals.push(out.times.total.as_secs_f64() * 1e3);
    }
    tum::write_est_if_asked(&est);
    totals.sort_by(f64::total_cmp);
    let s = tum::score(&gt, &est);
    println!(
        "frames {} tracked {} | ATE {:.2} cm {:.2} deg (origin-aligned {:.2} deg) | RPE {:.2} mm {:.3} deg | median {:.1} ms | keyframes {} points {}",
        frames.len(),
        tracked,
        s.ate_m * 100.0,
        s.ate_deg,
        s.ate_origin_deg,
        s.rpe_m * 1000.0,
        s.rpe_deg,
        totals[totals.len() / 2],
        tracker.map().keyframes.len(),
        tracker.map().points.len()
    );
}
