//! `--source mcap:` against the TUM folder it was written from: a ROS 2 recording
//! (rosbag2, MCAP storage) made by `tests/scripts/write-mcap.py` from the shared clip
//! streams the same frames bit for bit (colour, depth, timestamps, accelerometer)
//! with the calibration of its `CameraInfo`; a file without depth is refused naming
//! what it holds. The writer's Python is `.deps/bagtools` (`make deps`).

use std::path::{Path, PathBuf};
use std::process::Command;

use stillmap_client::bag::{BagTopics, McapSource};
use stillmap_client::calibration::CameraOptions;
use stillmap_client::source::FrameSource;
use stillmap_client::tum::TumSource;

const FRAMES: usize = 30;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn tum() -> PathBuf {
    repo().join("../shared/data/tum/rgbd_dataset_freiburg1_rpy")
}

/// Writes the first `FRAMES` frames of the clip as a recording; the .mcap file inside it.
fn write_recording(name: &str, extra: &[&str]) -> PathBuf {
    let python = repo().join(".deps/bagtools/bin/python");
    assert!(python.exists(), "{} is missing: run `make deps`", python.display());
    let dir = std::env::temp_dir().join(format!("stillmap-mcap-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = Command::new(python)
        .arg(repo().join("tests/scripts/write-mcap.py"))
        .arg(tum())
        .arg(&dir)
        .args(["--frames", &FRAMES.to_string()])
        .args(extra)
        .output()
        .expect("run write-mcap.py");
    assert!(out.status.success(), "write-mcap.py: {}", String::from_utf8_lossy(&out.stderr));
    let file = dir.join(format!("{}.mcap", dir.file_name().and_then(|n| n.to_str()).expect("name")));
    assert!(file.exists(), "{} was not written", file.display());
    file
}

#[test]
fn a_recording_streams_the_tum_frames_bit_for_bit() {
    let file = write_recording("metres", &[]);
    let mut bag = McapSource::open(&file, &BagTopics::default(), None, &CameraOptions::default()).expect("open the recording");
    let mut folder = TumSource::open(&tum(), None, &CameraOptions::default()).expect("open the folder");
    // Calibration from CameraInfo: freiburg1's intrinsics and distortion, depth in 1/5000 m.
    let (b, f) = (bag.camera(), folder.camera());
    assert_eq!((b.width, b.height, b.fx, b.fy, b.cx, b.cy), (f.width, f.height, f.fx, f.fy, f.cx, f.cy));
    assert_eq!((b.distortion_model, &b.distortion_coeffs), (f.distortion_model, &f.distortion_coeffs));
    assert_eq!(b.depth_units_per_metre, 5000.0);
    assert!(b.calibration_source.contains("/camera/color/camera_info"), "{}", b.calibration_source);
    // 30 colour and 30 depth images pair into 29 or 30 frames, the folder's first ones.
    let n = bag.len_hint().expect("known length");
    assert!((FRAMES - 1..=FRAMES).contains(&n), "{n} frames");
    for k in 0..n {
        let (m, t) = (bag.next_frame().expect("bag frame").expect("a frame"), folder.next_frame().expect("tum frame").expect("a frame"));
        assert_eq!(m.capture_time_ns, t.capture_time_ns, "frame {k}");
        assert!(m.color.data == t.color.data, "frame {k}: colour differs");
        assert!(m.depth.data == t.depth.data, "frame {k}: depth differs");
        assert_eq!(m.accel_in_camera, t.accel_in_camera, "frame {k}");
        assert!(m.accel_in_camera.is_some(), "frame {k} has its accelerometer sample");
    }
    assert!(bag.next_frame().expect("end").is_none());
    let _ = std::fs::remove_dir_all(file.parent().expect("folder"));
}

#[test]
fn millimetre_depth_is_read_at_its_scale_and_bad_topics_are_named() {
    let file = write_recording("mm", &["--depth-mm"]);
    let mut bag = McapSource::open(&file, &BagTopics::default(), Some(3), &CameraOptions::default()).expect("open");
    let mut folder = TumSource::open(&tum(), Some(3), &CameraOptions::default()).expect("open the folder");
    assert_eq!(bag.camera().depth_units_per_metre, 1000.0);
    let (m, t) = (bag.next_frame().expect("frame").expect("a frame"), folder.next_frame().expect("frame").expect("a frame"));
    // The same depth in millimetres: TUM's 1/5000 m values divided by 5 and rounded.
    let expected: Vec<u16> = t.depth.data.iter().map(|&v| ((f64::from(v) / 5.0).round()) as u16).collect();
    assert!(m.depth.data == expected, "millimetre depth differs");

    // A topic that is not there, or not depth: refused, listing the file's topics.
    let named = |depth: &str| BagTopics { depth: Some(depth.into()), ..Default::default() };
    for (topic, says) in [("/nope", "no topic /nope"), ("/camera/color/image_raw", "holds sensor_msgs/msg/Image (encoding rgb8)")] {
        let Err(e) = McapSource::open(&file, &named(topic), None, &CameraOptions::default()) else { panic!("{topic} accepted") };
        let e = e.to_string();
        assert!(e.contains(says) && e.contains("/camera/imu (sensor_msgs/msg/Imu, "), "{e}");
    }
    // Not an MCAP file at all.
    let not = std::env::temp_dir().join(format!("stillmap-not-{}.mcap", std::process::id()));
    std::fs::write(&not, b"hello").expect("write");
    let Err(e) = McapSource::open(&not, &BagTopics::default(), None, &CameraOptions::default()) else { panic!("accepted") };
    assert!(e.to_string().contains("not a readable MCAP file"), "{e}");
    let _ = std::fs::remove_file(&not);
    let _ = std::fs::remove_dir_all(file.parent().expect("folder"));
}

/// Reading speed, the whole clip as a recording beside the folder (frames/s, release):
/// `cargo test --release -p stillmap-client --test mcap_source -- --ignored --nocapture`.
#[test]
#[ignore = "a measurement: writes a 320 MB recording"]
fn reading_speed() {
    let python = repo().join(".deps/bagtools/bin/python");
    let dir = std::env::temp_dir().join(format!("stillmap-mcap-{}-speed", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = Command::new(python).arg(repo().join("tests/scripts/write-mcap.py")).arg(tum()).arg(&dir).output().expect("write");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let file = dir.join(format!("{}.mcap", dir.file_name().and_then(|n| n.to_str()).expect("name")));
    let read = |source: &mut dyn FrameSource| {
        let started = std::time::Instant::now();
        let mut n = 0;
        while source.next_frame().expect("frame").is_some() {
            n += 1;
        }
        (n, n as f64 / started.elapsed().as_secs_f64())
    };
    let started = std::time::Instant::now();
    let mut bag = McapSource::open(&file, &BagTopics::default(), None, &CameraOptions::default()).expect("open");
    let index_s = started.elapsed().as_secs_f64();
    let (n, bag_fps) = read(&mut bag);
    let (m, tum_fps) = read(&mut TumSource::open(&tum(), None, &CameraOptions::default()).expect("open"));
    let size = std::fs::metadata(&file).map(|m| m.len()).unwrap_or(0);
    eprintln!("| source | frames | frames/s |\n|---|---|---|");
    eprintln!("| TUM folder (PNG) | {m} | {tum_fps:.0} |");
    eprintln!("| MCAP, rgb8 + 32FC1, uncompressed ({} MB; first pass {index_s:.2} s) | {n} | {bag_fps:.0} |", size / 1_000_000);
    let _ = std::fs::remove_dir_all(&dir);
}
