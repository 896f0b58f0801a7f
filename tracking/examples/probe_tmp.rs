#[path = "../benches/support/tum.rs"]
mod tum;
use nalgebra::Isometry3;
use stillmap_tracking::{FrameInput, Tracker, TrackerConfig};

fn gt_at(gt: &[(u64, Isometry3<f64>)], t: u64) -> Isometry3<f64> {
    gt.iter().min_by_key(|(g, _)| g.abs_diff(t)).unwrap().1
}
#[derive(Clone, Copy)]
enum Mod { None, ZeroDepth, Black, LeftMask }

fn run(frames: &[tum::TumFrame], seq: &[(usize, Mod)], gt: &[(u64, Isometry3<f64>)], label: &str, verbose: bool) -> Vec<Option<Isometry3<f64>>> {
    let mut tr = Tracker::new(tum::fr1_camera(), TrackerConfig::default()).unwrap();
    let g0 = gt_at(gt, frames[seq[0].0].timestamp_ns);
    println!("== {label}");
    let zero = vec![0u16; 640 * 480];
    let black = vec![0u8; 640 * 480 * 3];
    let mask: Vec<u8> = (0..640 * 480).map(|i| u8::from(i % 640 < 320)).collect();
    let mut maxe = (0.0f64, 0.0f64);
    let mut poses = Vec::new();
    for (k, &(i, m)) in seq.iter().enumerate() {
        let f = &frames[i];
        let (rgb, depth, dm) = match m {
            Mod::None => (&f.rgb[..], &f.depth[..], None),
            Mod::ZeroDepth => (&f.rgb[..], &zero[..], None),
            Mod::Black => (&black[..], &f.depth[..], None),
            Mod::LeftMask => (&f.rgb[..], &f.depth[..], Some(&mask[..])),
        };
        let out = tr.track(&FrameInput { timestamp_ns: f.timestamp_ns, rgb, depth, dynamic_mask: dm }).unwrap();
        poses.push(out.world_from_camera);
        let err = out.world_from_camera.map(|p| {
            let g = g0.inverse() * gt_at(gt, f.timestamp_ns);
            let e = g.inverse() * p;
            let (a, b) = (e.translation.vector.norm() * 1e3, e.rotation.angle().to_degrees());
            maxe = (maxe.0.max(a), maxe.1.max(b));
            format!("{a:.1}mm {b:.2}deg")
        });
        if verbose { println!("{k} f{i} {:?} feats {} masked {} tracked {} kf {} {:?}", out.state, out.features, out.masked_features, out.tracked_points, out.keyframe, err); }
    }
    println!("max err {:.1} mm {:.2} deg", maxe.0, maxe.1);
    poses
}

fn main() {
    let dir = tum::fr1_rpy_dir();
    let frames = tum::load(&dir, usize::MAX);
    let gt = tum::groundtruth(&dir);
    let n = frames.len();
    for i in 0..n-1 {
        let d = gt_at(&gt, frames[i].timestamp_ns).inverse() * gt_at(&gt, frames[i+1].timestamp_ns);
        print!("{i}:{:.1} ", d.rotation.angle().to_degrees());
    }
    println!();
    let s: Vec<(usize, Mod)> = (0..60).chain(90..n).map(|i| (i, Mod::None)).collect();
    run(&frames, &s, &gt, "jump 59-90", false);
    let s: Vec<(usize, Mod)> = (60..150).map(|i| (i, Mod::None)).collect();
    run(&frames, &s, &gt, "post 60.. plain", false);
    for start in [0usize, 20, 60, 90, 120] {
        let s: Vec<(usize, Mod)> = (start..start + 10).map(|i| (i, Mod::LeftMask)).collect();
        run(&frames, &s, &gt, &format!("mask from {start}"), true);
        let s: Vec<(usize, Mod)> = (start..start + 10).map(|i| (i, Mod::None)).collect();
        run(&frames, &s, &gt, &format!("nomask from {start}"), false);
    }
}
