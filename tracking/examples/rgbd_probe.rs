//! Probe: OpenCV rgbd odometry frame to frame on fr1_rpy (per-frame RPE vs ground truth).
#[path = "../benches/support/tum.rs"]
mod tum;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Ptr, Scalar, CV_32F, CV_64F, CV_8U};
use opencv::prelude::*;
use opencv::{calib3d, core, imgproc, rgbd};

fn main() {
    let dir = tum::fr1_rpy_dir();
    let frames = tum::load(&dir, usize::MAX);
    let gt = tum::groundtruth(&dir);
    let cam = tum::fr1_camera();
    let k = Mat::from_slice_2d(&[[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]]).unwrap();
    let half: bool = std::env::var_os("HALF").is_some();
    let kh = if half { Mat::from_slice_2d(&[[cam.fx / 2.0, 0.0, (cam.cx + 0.5) / 2.0 - 0.5], [0.0, cam.fy / 2.0, (cam.cy + 0.5) / 2.0 - 0.5], [0.0, 0.0, 1.0]]).unwrap() } else { k.clone() };
    let d = cam.distortion.unwrap();
    let dist = Mat::from_slice(&d).unwrap().try_clone().unwrap();
    let (mut m1, mut m2) = (Mat::default(), Mat::default());
    calib3d::init_undistort_rectify_map(&k, &dist, &Mat::default(), &k, core::Size::new(640, 480), CV_32F, &mut m1, &mut m2).unwrap();
    let iters: core::Vector<i32> = std::env::var("ITER").map(|v| v.split(',').map(|x| x.parse().unwrap()).collect()).unwrap_or_default();
    let grads: core::Vector<f32> = if iters.is_empty() { core::Vector::new() } else { iters.iter().map(|_| 10.0f32).collect() };
    let kind = std::env::var("KIND").unwrap_or("rgbd".into());
    let mut odo: Ptr<rgbd::Odometry> = match kind.as_str() {
        "icp" => Ptr::<rgbd::Odometry>::from(rgbd::ICPOdometry::create(&kh, 0.1, 4.0, 0.07, 0.26, &core::Vector::<i32>::new(), 4).unwrap()),
        "both" => Ptr::<rgbd::Odometry>::from(rgbd::RgbdICPOdometry::create(&kh, 0.1, 4.0, 0.07, 0.26, &iters, &grads, 4).unwrap()),
        _ => Ptr::<rgbd::Odometry>::from(rgbd::RgbdOdometry::create(&kh, 0.1, 4.0, 0.07, &core::Vector::<i32>::new(), &core::Vector::<f32>::new(), 0.26, 4).unwrap()),
    };
    let prep = |f: &tum::TumFrame| -> (Mat, Mat) {
        let gray: Vec<u8> = stillmap_tracking::tracker::to_gray(&f.rgb);
        let g = Mat::new_rows_cols_with_data(480, 640, &gray).unwrap().try_clone().unwrap();
        let dz: Vec<f32> = f.depth.iter().map(|&v| if v == 0 { f32::NAN } else { v as f32 / 5000.0 }).collect();
        let dm = Mat::new_rows_cols_with_data(480, 640, &dz).unwrap().try_clone().unwrap();
        let (mut gu, mut du) = (Mat::default(), Mat::default());
        imgproc::remap(&g, &mut gu, &m1, &m2, imgproc::INTER_LINEAR, core::BORDER_CONSTANT, Scalar::default()).unwrap();
        imgproc::remap(&dm, &mut du, &m1, &m2, imgproc::INTER_NEAREST, core::BORDER_CONSTANT, Scalar::all(f64::NAN)).unwrap();
        if half {
            let (mut gh, mut dh) = (Mat::default(), Mat::default());
            imgproc::resize(&gu, &mut gh, core::Size::new(320, 240), 0.0, 0.0, imgproc::INTER_AREA).unwrap();
            imgproc::resize(&du, &mut dh, core::Size::new(320, 240), 0.0, 0.0, imgproc::INTER_NEAREST).unwrap();
            return (gh, dh);
        }
        (gu, du)
    };
    let mask = Mat::new_rows_cols_with_default(if half { 240 } else { 480 }, if half { 320 } else { 640 }, CV_8U, Scalar::all(255.0)).unwrap();
    let frame_of = |odo: &Ptr<rgbd::Odometry>, im: &(Mat, Mat), id: i32| -> Ptr<rgbd::OdometryFrame> {
        let mut f = rgbd::OdometryFrame::create(&im.0, &im.1, &mask, &Mat::default(), id).unwrap();
        odo.prepare_frame_cache(&mut f, 3).unwrap();
        f
    };
    let mut prev_f = frame_of(&odo, &prep(&frames[0]), 0);
    let mut prev = prep(&frames[0]);
    let mut pose = Isometry3::<f64>::identity();
    let mut est = vec![(frames[0].timestamp_ns, pose)];
    let mut errs = Vec::new();
    let mut times = Vec::new();
    let g = |t: u64| gt.iter().min_by_key(|(g, _)| g.abs_diff(t)).map(|x| x.1).unwrap();
    for i in 1..frames.len() {
        let cur = prep(&frames[i]);
        let mut rt = Mat::default();
        let t0 = std::time::Instant::now();
        let mut cur_f = frame_of(&odo, &cur, i as i32);
        let ok = odo.compute2(&mut prev_f, &mut cur_f, &mut rt, &Mat::default()).unwrap();
        prev_f = cur_f;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        let mut rel = Isometry3::identity();
        if ok {
            let m = |r: i32, c: i32| *rt.at_2d::<f64>(r, c).unwrap();
            let rot = Matrix3::new(m(0, 0), m(0, 1), m(0, 2), m(1, 0), m(1, 1), m(1, 2), m(2, 0), m(2, 1), m(2, 2));
            // Rt maps points of the source (prev) frame into the destination (current) frame: cur_from_prev.
            let cur_from_prev = Isometry3::from_parts(Translation3::new(m(0, 3), m(1, 3), m(2, 3)), UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rot)));
            rel = cur_from_prev.inverse();
        }
        pose = pose * rel;
        est.push((frames[i].timestamp_ns, pose));
        let dg = g(frames[i - 1].timestamp_ns).inverse() * g(frames[i].timestamp_ns);
        let e = dg.inverse() * rel;
        errs.push(e.translation.vector.norm() * 1e3);
        if std::env::var_os("VERBOSE").is_some() {
            println!("{i} ok {ok} est {:.2}deg {:.1}mm err {:.2}deg {:.1}mm", rel.rotation.angle().to_degrees(), rel.translation.vector.norm() * 1e3, e.rotation.angle().to_degrees(), e.translation.vector.norm() * 1e3);
        }
        prev = cur;
    }
    let s = tum::score(&gt, &est);
    let _ = (Vector3::<f64>::zeros(), CV_64F);
    times.sort_by(f64::total_cmp);
    println!("median {:.1} ms", times[times.len() / 2]);
    println!("{kind}: ATE {:.2} cm (origin {:.2} deg) RPE {:.2} mm {:.3} deg", s.ate_m * 100.0, s.ate_origin_deg, s.rpe_m * 1e3, s.rpe_deg);
}
