//! A robot's long session, as a fleet server sees it: the public clip's 300 frames
//! (freiburg1_rpy, then its continuation rpy_b) played again and again at 30 Hz, for
//! `FRAMES` frames (default 6,000: 3 min 20 s of camera time).
//! Prints, per pass of 300 frames: the tracker's keyframes and map points, its mean
//! time per frame, the frames without a pose, the largest error against the ground
//! truth (translation and rotation, the first frame aligned) and the process's
//! resident memory. `cargo run --release -p stillmap-tracking --example long_run`
//! (`TRACKING` takes `[tracking]` keys as TOML, `;` between lines).

use std::time::Instant;

use nalgebra::Isometry3;
use stillmap_tracking::testing as tum;
use stillmap_tracking::{FrameInput, Tracker, TrackerConfig};

fn resident_mib() -> f64 {
    std::fs::read_to_string("/proc/self/statm")
        .ok()
        .and_then(|s| s.split_whitespace().nth(1).and_then(|p| p.parse::<f64>().ok()))
        .map_or(f64::NAN, |pages| pages * 4096.0 / 1048576.0)
}

fn main() {
    let total: usize = std::env::var("FRAMES").ok().and_then(|v| v.parse().ok()).unwrap_or(6_000);
    let dirs = [tum::fr1_rpy_dir(), stillmap_dataset::shared::fr1_rpy_b()];
    let mut frames = Vec::new();
    let mut gt = Vec::new();
    for dir in &dirs {
        frames.extend(tum::load(dir, 150));
        gt.extend(tum::groundtruth(dir));
    }
    gt.sort_by_key(|g| g.0);
    let truth = |t: u64| gt.iter().min_by_key(|(g, _)| g.abs_diff(t)).map(|g| g.1).expect("ground truth");
    let config: TrackerConfig = tum::config_from_env("TRACKING");
    let mut tracker = Tracker::new(tum::fr1_camera_with_readout_from_env(), config).expect("tracker");
    let n = frames.len();
    let first = truth(tum::fr1_pose_time_ns(frames[0].timestamp_ns));
    let start_ns = frames[0].timestamp_ns;
    println!(
        "| frames | keyframes | map points | ms per frame (features / dense / matching / pose / keyframe) | without a pose | worst error mm / deg | resident MiB |"
    );
    println!("|---|---|---|---|---|---|---|");
    let (mut window_s, mut lost, mut worst) = (0.0f64, 0, (0.0f64, 0.0f64));
    let mut stages = [0.0f64; 5];
    for k in 0..total {
        // The 300 frames again and again: from the last back to the first is a jump
        // the tracker relocalizes after. (Played backwards, a rolling shutter's
        // images would show motion the other way than the tracker rectifies for.)
        let i = k % n;
        let f = &frames[i];
        let timestamp_ns = start_ns + (k as u64) * 33_333_333;
        let t = Instant::now();
        let out = tracker.track(&FrameInput { timestamp_ns, rgb: &f.rgb, depth: &f.depth, dynamic_mask: None }).expect("track");
        window_s += t.elapsed().as_secs_f64();
        let st = &out.times;
        for (sum, d) in stages.iter_mut().zip([st.extraction, st.dense, st.matching, st.optimization, st.local_ba]) {
            *sum += d.as_secs_f64();
        }
        match out.world_from_camera {
            Some(p) => {
                let g: Isometry3<f64> = first.inverse() * truth(tum::fr1_pose_time_ns(f.timestamp_ns));
                let e = g.inverse() * p;
                worst.0 = worst.0.max(e.translation.vector.norm() * 1e3);
                worst.1 = worst.1.max(e.rotation.angle().to_degrees());
            }
            None => lost += 1,
        }
        if (k + 1) % n == 0 || k + 1 == total {
            let map = tracker.map();
            let per_frame = |s: f64| s * 1e3 / ((k % n) + 1) as f64;
            let split: Vec<String> = stages.iter().map(|&s| format!("{:.1}", per_frame(s))).collect();
            println!(
                "| {} | {} | {} | {:.1} ({}) | {lost} | {:.0} / {:.1} | {:.0} |",
                k + 1,
                map.keyframes.len(),
                map.points.len(),
                per_frame(window_s),
                split.join(" / "),
                worst.0,
                worst.1,
                resident_mib()
            );
            (window_s, lost, worst, stages) = (0.0, 0, (0.0, 0.0), [0.0; 5]);
        }
    }
}
