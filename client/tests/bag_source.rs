//! `--source mcap:` and `--source rosbag:` against the TUM folder they were written
//! from: a ROS 2 recording (rosbag2, MCAP storage) and a ROS 1 bag made by
//! `tests/scripts/write-bag.py` (rosbags) from the shared clip stream the same frames
//! bit for bit (colour, depth, timestamps, accelerometer) with the calibration of
//! their `CameraInfo`; a topic that does not fit is refused naming what the file
//! holds. The writer's Python is `.deps/bagtools` (`make deps`).

use std::path::{Path, PathBuf};
use std::process::Command;

use stillmap_client::bag::{BagFormat, BagSource, BagTopics};
use stillmap_client::calibration::CameraOptions;
use stillmap_client::source::FrameSource;
use stillmap_client::tum::TumSource;

const FRAMES: usize = 30;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn tum() -> PathBuf {
    stillmap_dataset::shared::fr1_rpy()
}

/// Writes the first `FRAMES` frames of the clip as a recording: the .mcap file
/// (inside its rosbag2 folder) or the ROS 1 .bag file.
/// Returns (the folder to remove, the file).
fn write_recording(name: &str, format: BagFormat, frames: Option<usize>, extra: &[&str]) -> (PathBuf, PathBuf) {
    let python = repo().join(".deps/bagtools/bin/python");
    assert!(python.exists(), "{} is missing: run `make deps`", python.display());
    let dir = std::env::temp_dir().join(format!("stillmap-bag-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temporary folder");
    let (out, file) = match format {
        BagFormat::Mcap => (dir.join("recording"), dir.join("recording/recording.mcap")),
        BagFormat::Ros1 => (dir.join("recording.bag"), dir.join("recording.bag")),
    };
    let run = Command::new(python)
        .arg(repo().join("tests/scripts/write-bag.py"))
        .arg(tum())
        .arg(&out)
        .args(frames.map(|n| ["--frames".to_string(), n.to_string()]).into_iter().flatten())
        .args(if format == BagFormat::Ros1 { &["--ros1"][..] } else { &[][..] })
        .args(extra)
        .output()
        .expect("run write-bag.py");
    assert!(run.status.success(), "write-bag.py: {}", String::from_utf8_lossy(&run.stderr));
    assert!(file.exists(), "{} was not written", file.display());
    (dir, file)
}

/// The recording streams exactly the folder's first frames, with its calibration.
fn same_frames_as_the_folder(format: BagFormat) {
    let (dir, file) = write_recording(&format!("{format:?}"), format, Some(FRAMES), &[]);
    let mut bag = BagSource::open(&file, format, &BagTopics::default(), None, &CameraOptions::default()).expect("open the recording");
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
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_ros1_bag_streams_the_tum_frames_bit_for_bit() {
    same_frames_as_the_folder(BagFormat::Ros1);
}

#[test]
fn an_mcap_recording_streams_the_tum_frames_bit_for_bit() {
    same_frames_as_the_folder(BagFormat::Mcap);
}

#[test]
fn millimetre_depth_is_read_at_its_scale_and_bad_topics_are_named() {
    let (dir, file) = write_recording("mm", BagFormat::Mcap, Some(FRAMES), &["--depth-mm"]);
    let mut bag = BagSource::open(&file, BagFormat::Mcap, &BagTopics::default(), Some(3), &CameraOptions::default()).expect("open");
    let mut folder = TumSource::open(&tum(), Some(3), &CameraOptions::default()).expect("open the folder");
    assert_eq!(bag.camera().depth_units_per_metre, 1000.0);
    let (m, t) = (bag.next_frame().expect("frame").expect("a frame"), folder.next_frame().expect("frame").expect("a frame"));
    // The same depth in millimetres: TUM's 1/5000 m values divided by 5 and rounded.
    let expected: Vec<u16> = t.depth.data.iter().map(|&v| ((f64::from(v) / 5.0).round()) as u16).collect();
    assert!(m.depth.data == expected, "millimetre depth differs");

    // A topic that is not there, or not depth: refused, listing the file's topics.
    let named = |depth: &str| BagTopics { depth: Some(depth.into()), ..Default::default() };
    for (topic, says) in [("/nope", "no topic /nope"), ("/camera/color/image_raw", "holds sensor_msgs/msg/Image (encoding rgb8)")] {
        let Err(e) = BagSource::open(&file, BagFormat::Mcap, &named(topic), None, &CameraOptions::default()) else {
            panic!("{topic} accepted")
        };
        let e = e.to_string();
        assert!(e.contains(says) && e.contains("/camera/imu (sensor_msgs/msg/Imu, "), "{e}");
    }
    // Not an MCAP file at all.
    let not = std::env::temp_dir().join(format!("stillmap-not-{}.mcap", std::process::id()));
    std::fs::write(&not, b"hello").expect("write");
    let Err(e) = BagSource::open(&not, BagFormat::Mcap, &BagTopics::default(), None, &CameraOptions::default()) else { panic!("accepted") };
    assert!(e.to_string().contains("not a readable MCAP file"), "{e}");
    let _ = std::fs::remove_file(&not);
    let Err(e) = BagSource::open(&file, BagFormat::Ros1, &BagTopics::default(), None, &CameraOptions::default()) else {
        panic!("accepted")
    };
    assert!(e.to_string().contains("not a readable ROS 1 bag"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Length fields the reader would allocate: a ROS 1 chunk declaring 4 GiB
/// uncompressed, an MCAP record declaring 1 TiB. Each is refused naming the file and
/// the problem, before anything of that size is allocated.
#[test]
fn a_recording_declaring_a_huge_record_is_refused_before_allocating() {
    let (dir, file) = write_recording("huge", BagFormat::Ros1, Some(2), &[]);
    let mut bytes = std::fs::read(&file).expect("read the bag");
    // A chunk header's `size` field: its length (9), "size=", the u32.
    let field = b"\x09\x00\x00\x00size=";
    let at = bytes.windows(field.len()).position(|w| w == field).expect("a chunk's size field") + field.len();
    bytes[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(&file, &bytes).expect("write the bag");
    let Err(e) = BagSource::open(&file, BagFormat::Ros1, &BagTopics::default(), None, &CameraOptions::default()) else {
        panic!("accepted")
    };
    assert!(e.to_string().contains("declares 4294967295 bytes uncompressed, more than the 268435456 this reader takes"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);

    // MCAP's magic, then a header record (opcode 1) declaring 2⁴⁰ bytes.
    let huge = std::env::temp_dir().join(format!("stillmap-huge-{}.mcap", std::process::id()));
    let mut mcap = b"\x89MCAP0\r\n\x01".to_vec();
    mcap.extend_from_slice(&(1u64 << 40).to_le_bytes());
    mcap.extend_from_slice(&[0; 16]);
    std::fs::write(&huge, &mcap).expect("write");
    let Err(e) = BagSource::open(&huge, BagFormat::Mcap, &BagTopics::default(), None, &CameraOptions::default()) else {
        panic!("accepted")
    };
    assert!(e.to_string().contains("not a readable MCAP file"), "{e}");
    let _ = std::fs::remove_file(&huge);
}

/// A bag like TUM's own: its `CameraInfo` holds ROS's uncalibrated defaults and its
/// IMU is in the Kinect's own frame. It is not taken as calibrated (it refuses to
/// start saying so), and `--camera tum-fr1` gives it freiburg1's calibration and its
/// accelerometer in the camera's axes, as the folder has them.
#[test]
fn a_bag_like_tums_own_needs_the_camera_named() {
    let (dir, file) = write_recording("default-info", BagFormat::Ros1, Some(3), &["--default-camera-info", "--kinect-imu"]);
    let Err(e) = BagSource::open(&file, BagFormat::Ros1, &BagTopics::default(), None, &CameraOptions::default()) else {
        panic!("uncalibrated intrinsics accepted")
    };
    assert!(e.to_string().contains("holds ROS's uncalibrated defaults"), "{e}");
    let fr1 = CameraOptions { camera: Some(stillmap_client::calibration::KnownCamera::TumFr1), ..Default::default() };
    let mut bag = BagSource::open(&file, BagFormat::Ros1, &BagTopics::default(), None, &fr1).expect("open with --camera tum-fr1");
    let mut folder = TumSource::open(&tum(), None, &CameraOptions::default()).expect("open the folder");
    assert_eq!((bag.camera().fx, bag.camera().cy), (folder.camera().fx, folder.camera().cy));
    let (m, t) = (bag.next_frame().expect("frame").expect("a frame"), folder.next_frame().expect("frame").expect("a frame"));
    assert!(m.accel_in_camera.is_some() && m.accel_in_camera == t.accel_in_camera, "{:?} vs {:?}", m.accel_in_camera, t.accel_in_camera);
    // Without a Kinect named, an IMU in another frame is left out.
    let plain = CameraOptions { allow_default_intrinsics: true, ..Default::default() };
    let mut bag = BagSource::open(&file, BagFormat::Ros1, &BagTopics::default(), None, &plain).expect("open");
    assert_eq!(bag.next_frame().expect("frame").expect("a frame").accel_in_camera, None);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Reading speed, the whole clip as a recording and as a ROS 1 bag beside the folder
/// (frames/s, release):
/// `cargo test --release -p stillmap-client --test bag_source -- --ignored --nocapture`.
#[test]
#[ignore = "a measurement: writes two 320 MB recordings"]
fn reading_speed() {
    let read = |source: &mut dyn FrameSource| {
        let started = std::time::Instant::now();
        let mut n = 0;
        while source.next_frame().expect("frame").is_some() {
            n += 1;
        }
        (n, n as f64 / started.elapsed().as_secs_f64())
    };
    let (m, tum_fps) = read(&mut TumSource::open(&tum(), None, &CameraOptions::default()).expect("open"));
    eprintln!("| source | frames | frames/s |\n|---|---|---|");
    eprintln!("| TUM folder (PNG) | {m} | {tum_fps:.0} |");
    for format in [BagFormat::Mcap, BagFormat::Ros1] {
        let (dir, file) = write_recording(&format!("speed-{format:?}"), format, None, &[]);
        let started = std::time::Instant::now();
        let mut bag = BagSource::open(&file, format, &BagTopics::default(), None, &CameraOptions::default()).expect("open");
        let index_s = started.elapsed().as_secs_f64();
        let (n, fps) = read(&mut bag);
        let size = std::fs::metadata(&file).map(|m| m.len()).unwrap_or(0);
        eprintln!("| {format:?}, rgb8 + 32FC1, uncompressed ({} MB; first pass {index_s:.2} s) | {n} | {fps:.0} |", size / 1_000_000);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
