//! The masker and the tracker together (the server's per-frame order, every frame
//! segmented by the real model) on the public clips' object-free frames, fed every
//! frame (30 Hz) and every 2nd, 3rd and 4th (15, 10, 7.5 Hz): what a robot streaming
//! to a saturated server, or a slower camera, gets with perception in front of
//! tracking. Sequence numbers stay consecutive, as from a camera whose driver
//! dropped the frames; the flow's noise follows the capture times. Prints a table
//! (about two minutes):
//! `cargo run --release -p stillmap-perception --example frame_rate`
//! (`TRACKING="key = value;…"` overrides the tracker's config, as for the tracker
//! alone: `cargo run --release -p stillmap-tracking --example frame_rate`).

use stillmap_perception::testing as support;
use stillmap_perception::testing::composite_run::{self, Schedule};
use stillmap_perception::{PerceptionConfig, YoloSegmenter};
use stillmap_tracking::testing as tum;

fn main() {
    let tracking: stillmap_tracking::TrackerConfig = tum::config_from_env("TRACKING");
    let mut segmenter = YoloSegmenter::new(&support::segmentation_config("yolov8n-seg_fp32_640.onnx")).expect("model");
    println!("| clip | frames fed | ATE | frames without a pose |");
    println!("|---|---|---|---|");
    for dir in [tum::fr1_rpy_dir(), stillmap_dataset::shared::fr1_rpy_b()] {
        let frames = tum::load(&dir, 150);
        let gt = tum::groundtruth(&dir);
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        for (label, every) in [("30 Hz (every frame)", 1), ("15 Hz (every 2nd)", 2), ("10 Hz (every 3rd)", 3), ("7.5 Hz (every 4th)", 4)] {
            let fed: Vec<tum::TumFrame> = frames.iter().step_by(every).cloned().collect();
            let scores = composite_run::run_with(
                &composite_run::without_object(&fed),
                Some(&mut segmenter),
                Schedule::EveryFrame,
                false,
                PerceptionConfig::default(),
                tracking.clone(),
            );
            let ate = tum::score(&gt, &scores.trajectory).ate_m;
            println!("| {name} | {label}: {} | {:.2} cm | {} |", fed.len(), 100.0 * ate, fed.len() - scores.trajectory.len());
        }
    }
}
