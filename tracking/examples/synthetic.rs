//! Tracks the synthetic room along the sway path and prints the error against
//! the exact ground truth: `cargo run --release -p stillmap-tracking --example synthetic`.

use stillmap_tracking::testing as tum;

use stillmap_tracking::synthetic::{Scene, kinect_camera, render, sway_path};
use stillmap_tracking::{FrameInput, Tracker, TrackerConfig};

fn main() {
    let frames: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(150);
    let camera = kinect_camera();
    let scene = Scene::room(7);
    let config: TrackerConfig = tum::config_from_env("TRACKING");
    let mut tracker = Tracker::new(camera.clone(), config).expect("tracker");
    let path = sway_path(frames);
    let mut gt = Vec::new();
    let mut est = Vec::new();
    for (i, pose) in path.iter().enumerate() {
        let r = render(&scene, &camera, pose);
        let ts = i as u64 * 33_333_333;
        let out = tracker.track(&FrameInput { timestamp_ns: ts, rgb: &r.rgb, depth: &r.depth, dynamic_mask: None }).expect("track");
        gt.push((ts, *pose));
        if let Some(p) = out.world_from_camera {
            est.push((ts, p));
            if std::env::var_os("VERBOSE").is_some() {
                let e = pose.inverse() * path[0] * p;
                println!(
                    "{i} {:?} tracked {} err {:.4} m {:.3} deg",
                    out.state,
                    out.tracked_points,
                    e.translation.vector.norm(),
                    e.rotation.angle().to_degrees()
                );
            }
        }
    }
    let s = tum::score(&gt, &est);
    println!(
        "synthetic {} frames: ATE {:.2} mm {:.3} deg | RPE {:.2} mm {:.3} deg",
        s.pairs,
        s.ate_m * 1e3,
        s.ate_deg,
        s.rpe_m * 1e3,
        s.rpe_deg
    );
}
