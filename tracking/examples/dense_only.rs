//! Dense RGB-D odometry alone (`stillmap_tracking::dense`, the tracker's motion
//! prior, same settings), chained frame to frame with no map, scored against the
//! ground truth: what the prior knows by itself.
//! `cargo run --release -p stillmap-tracking --example dense_only [DIR]`

use stillmap_tracking::testing as tum;

use std::path::PathBuf;

use nalgebra::Isometry3;
use stillmap_tracking::dense::DenseOdometry;
use stillmap_tracking::tracker::to_gray;

fn main() {
    let dir = std::env::args().nth(1).map(PathBuf::from).unwrap_or_else(tum::fr1_rpy_dir);
    let frames = tum::load(&dir, usize::MAX);
    let gt = tum::groundtruth(&dir);
    let mut dense = DenseOdometry::new(&tum::fr1_camera(), 0.1, 6.0).expect("dense odometry");
    let mut world_from_camera = Isometry3::identity();
    let (mut est, mut failed) = (Vec::new(), 0);
    for f in &frames {
        match dense.push(&to_gray(&f.rgb), &f.depth, None).expect("push") {
            Some(previous_from_current) => world_from_camera *= previous_from_current,
            None if !est.is_empty() => failed += 1,
            None => {}
        }
        est.push((tum::fr1_pose_time_ns_from_env(f.timestamp_ns), world_from_camera));
    }
    tum::write_est_if_asked(&est);
    let s = tum::score(&gt, &est);
    println!(
        "dense odometry alone, {} frames ({failed} steps failed, kept as no motion) | ATE {:.2} cm (origin-aligned {:.2} deg) | RPE {:.2} mm {:.3} deg",
        frames.len(),
        s.ate_m * 100.0,
        s.ate_origin_deg,
        s.rpe_m * 1000.0,
        s.rpe_deg
    );
}
