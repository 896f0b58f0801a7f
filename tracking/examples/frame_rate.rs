//! Tracking when frames are dropped: the public clips (both, or `DIR`) tracked at
//! every frame (30 Hz), every 2nd, 3rd and 4th (15, 10, 7.5 Hz), and with each
//! frame kept at random with probability 1/2 (a fixed seed): what a robot streaming
//! to a saturated server, or a slower camera, gives the tracker. Prints a table:
//! `cargo run --release -p stillmap-tracking --example frame_rate [DIR]`
//! (`TRACKING="key = value;…"` overrides the tracker's config; `VERBOSE=1` prints
//! each frame's state and its step's error against ground truth).

use std::path::PathBuf;

use stillmap_tracking::testing as tum;
use stillmap_tracking::{FrameInput, Tracker, TrackerConfig, TrackingState};

/// Which frames are fed: every n-th, or each kept at random with probability 1/2.
#[derive(Clone, Copy)]
enum Keep {
    Every(usize),
    RandomHalf,
}

fn main() {
    let dirs: Vec<PathBuf> = match std::env::args().nth(1) {
        Some(dir) => vec![PathBuf::from(dir)],
        None => vec![tum::fr1_rpy_dir(), stillmap_dataset::shared::fr1_rpy_b()],
    };
    let config: TrackerConfig = tum::config_from_env("TRACKING");
    let runs = [
        ("30 Hz (every frame)", Keep::Every(1)),
        ("15 Hz (every 2nd)", Keep::Every(2)),
        ("10 Hz (every 3rd)", Keep::Every(3)),
        ("7.5 Hz (every 4th)", Keep::Every(4)),
        ("half, at random", Keep::RandomHalf),
    ];
    println!("| clip | frames fed | ATE | frames coasting | frames without a pose |");
    println!("|---|---|---|---|---|");
    for dir in &dirs {
        let frames = tum::load(dir, usize::MAX);
        let gt = tum::groundtruth(dir);
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        for (label, keep) in runs {
            let fed: Vec<&tum::TumFrame> = match keep {
                Keep::Every(n) => frames.iter().step_by(n).collect(),
                Keep::RandomHalf => tum::half_at_random(&frames),
            };
            let mut tracker = Tracker::new(tum::fr1_camera(), config.clone()).expect("tracker");
            let mut est: Vec<(u64, nalgebra::Isometry3<f64>)> = Vec::new();
            let mut coasting = 0;
            for f in &fed {
                let input = FrameInput { timestamp_ns: f.timestamp_ns, rgb: &f.rgb, depth: &f.depth, dynamic_mask: None };
                let out = tracker.track(&input).expect("track");
                coasting += usize::from(out.state == TrackingState::Coasting);
                if std::env::var_os("VERBOSE").is_some() {
                    let g = |t: u64| gt.iter().min_by_key(|(g, _)| g.abs_diff(t)).map(|x| x.1).expect("gt");
                    let err = out.world_from_camera.zip(est.last()).map(|(p, (t0, p0))| {
                        let e = (g(*t0).inverse() * g(tum::fr1_pose_time_ns(f.timestamp_ns))).inverse() * (p0.inverse() * p);
                        e.translation.vector.norm() * 1e3
                    });
                    eprintln!("{label} {} {:?} inliers {} step err {err:?}", f.timestamp_ns, out.state, out.tracked_points);
                }
                if let Some(pose) = out.world_from_camera {
                    est.push((tum::fr1_pose_time_ns(f.timestamp_ns), pose));
                }
            }
            let s = tum::score(&gt, &est);
            println!("| {name} | {label}: {} | {:.2} cm | {coasting} | {} |", fed.len(), 100.0 * s.ate_m, fed.len() - est.len());
        }
    }
}
