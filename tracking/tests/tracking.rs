//! End-to-end tracking tests: accuracy on the synthetic room and on the real TUM
//! fr1_rpy clip (offline, from `shared/data`), determinism, and the issue's edge
//! cases — frames without depth, black frames (coasted on dense odometry, or lost
//! with coasting off), a sudden jump, bad input sizes and
//! a dynamic mask. Run with `--nocapture` to see the measured numbers.
//!
//! Bounds are what the tracker achieves, with a margin; the measured values are
//! noted beside each bound. Poses are compared with ground truth relative to the
//! frame that started the map (the tracker's world frame):
//! `GT(first)⁻¹ · GT(t)`.

use stillmap_tracking::testing as tum;

use std::sync::OnceLock;

use nalgebra::Isometry3;
use stillmap_tracking::synthetic::{RenderOptions, Scene, kinect_camera, render, render_rolling_shutter, sway_path, sway_pose};
use stillmap_tracking::{FrameInput, TrackOutput, Tracker, TrackerConfig, TrackingError, TrackingState};

/// Frame period of the synthetic sequence (30 Hz), in nanoseconds.
const SYNTHETIC_FRAME_NS: u64 = 33_333_333;
/// Synthetic frames tracked (the issue's sequence length).
const SYNTHETIC_FRAMES: usize = 150;
/// Scene seed of the synthetic room (as the `synthetic` example).
const SYNTHETIC_SEED: u64 = 7;
/// Issue targets on the synthetic sequence: ATE ≤ 5 mm and ≤ 0.2° (measured 0.45 mm, 0.114°).
const SYNTHETIC_MAX_ATE_M: f64 = 0.005;
const SYNTHETIC_MAX_ATE_DEG: f64 = 0.2;

/// Frames of fr1_rpy.
const FR1_RPY_FRAMES: usize = 150;
/// fr1_rpy bounds, with the camera's 25 ms rolling-shutter readout modelled
/// (`tum::fr1_camera`) and the poses scored at the time they refer to, the middle
/// row's, 12.5 ms before the frame's arrival stamp (`tum::fr1_pose_time_ns`):
/// measured ATE 0.77 cm (origin-aligned rotation 1.41°), RPE 5.31 mm, 0.460° (with
/// the feature count nudged by ±1–2 %, `--example tum_spread`: ATE 0.77–0.82 cm,
/// 1.36–1.43°, RPE 5.25–5.42 mm, 0.456–0.460°; before new map points were spread
/// over the image, 2026-12-06: 0.95 cm, 1.24°, 5.49 mm, 0.454°). The rotation after SE(3) alignment
/// is not bounded: the clip moves only a few centimetres, so the alignment's
/// rotation is ill-determined.
const FR1_MAX_ATE_M: f64 = 0.015;
const FR1_MAX_ATE_ORIGIN_DEG: f64 = 1.7;
const FR1_MAX_RPE_M: f64 = 0.0065;
const FR1_MAX_RPE_DEG: f64 = 0.5;
/// ATE bound with frames dropped (`dropped_frames_are_tracked`; measured 1.32 and 1.05 cm).
const DROPPED_FRAMES_MAX_ATE_M: f64 = 0.02;

/// Good frames tracked before a disturbance.
const FRAMES_BEFORE_DROPOUT: usize = 20;
/// Consecutive black frames (real depth) coasted on dense odometry.
const COASTED_FRAMES: usize = 5;
/// Consecutive frames with no valid depth in the dropout test.
const DEPTH_DROPOUT_FRAMES: usize = 3;
/// Frames compared with ground truth after a recovery (dropout and black frame).
const FRAMES_AFTER_RECOVERY: usize = 15;
/// Pose error bound after a depth dropout or black frame, relative to the first frame:
/// measured at most 21.2 mm / 2.66° (the uninterrupted run: 29.8 mm / 2.72° on frames 0–39).
const RECOVERY_MAX_ERROR_M: f64 = 0.04;
const RECOVERY_MAX_ERROR_DEG: f64 = 3.5;

/// Last frame before the jump, and first frame after it: 30 frames skipped. Ground
/// truth rotates 67.7° (6.3 cm) from frame 59 to 90, close to the clip's largest
/// 31-frame rotation (79.8°, frames 51→82), so the motion model cannot bridge it.
const JUMP_FROM: usize = 59;
const JUMP_TO: usize = 90;
/// The ground-truth rotation across the jump is at least this (degrees).
const JUMP_MIN_GT_ROTATION_DEG: f64 = 45.0;
/// Frames after the jump within which the tracker must report `Relocalized`.
const JUMP_RELOCALIZE_WITHIN: usize = 3;
/// Pose error bound after the jump, relative to frame 0: measured at most 97.0 mm /
/// 5.21° (84.1 mm / 4.45° with the feature-only tracker, whose uninterrupted run
/// reaches 90 mm / 4.14° on its own, from drift).
const JUMP_MAX_ERROR_M: f64 = 0.12;
const JUMP_MAX_ERROR_DEG: f64 = 6.0;

/// Masked test: a calm stretch of the clip, tracked with the left half masked.
const MASK_FIRST_FRAME: usize = 60;
const MASK_FRAMES: usize = 10;
/// Pose error bound with the left half masked: measured 8.2 mm / 0.57°
/// (unmasked: 8.1 mm / 0.69°).
const MASK_MAX_ERROR_M: f64 = 0.02;
const MASK_MAX_ERROR_DEG: f64 = 1.5;

/// The real clip and its ground truth, loaded once for all tests.
struct Clip {
    frames: Vec<tum::TumFrame>,
    gt: Vec<(u64, Isometry3<f64>)>,
}

impl Clip {
    fn get() -> &'static Clip {
        static CLIP: OnceLock<Clip> = OnceLock::new();
        CLIP.get_or_init(|| {
            let dir = tum::fr1_rpy_dir();
            let frames = tum::load(&dir, FR1_RPY_FRAMES);
            assert_eq!(frames.len(), FR1_RPY_FRAMES, "fr1_rpy frames in {}", dir.display());
            Clip { frames, gt: tum::groundtruth(&dir) }
        })
    }

    /// Ground truth nearest to frame `i`'s timestamp.
    fn gt(&self, i: usize) -> Isometry3<f64> {
        let t = self.frames[i].timestamp_ns;
        self.gt.iter().min_by_key(|(g, _)| g.abs_diff(t)).expect("ground truth").1
    }

    /// Translation (m) and rotation (°) error of `est` at frame `i`, in the world
    /// frame of the map started at frame `first`.
    fn error(&self, first: usize, i: usize, est: &Isometry3<f64>) -> (f64, f64) {
        let e = (self.gt(first).inverse() * self.gt(i)).inverse() * est;
        (e.translation.vector.norm(), e.rotation.angle().to_degrees())
    }
}

/// How a real frame is fed to the tracker.
#[derive(Clone, Copy)]
enum Feed<'a> {
    Real,
    /// Same colour, depth all zero (no reading anywhere).
    NoDepth,
    /// Colour all zero, real depth.
    Black,
    Masked(&'a [u8]),
}

fn fr1_tracker() -> Tracker {
    Tracker::new(tum::fr1_camera(), TrackerConfig::default()).expect("tracker")
}

fn track(tracker: &mut Tracker, frame: &tum::TumFrame, feed: Feed<'_>) -> TrackOutput {
    let no_depth = vec![0u16; frame.depth.len()];
    let black = vec![0u8; frame.rgb.len()];
    let (rgb, depth, dynamic_mask) = match feed {
        Feed::Real => (&frame.rgb[..], &frame.depth[..], None),
        Feed::NoDepth => (&frame.rgb[..], &no_depth[..], None),
        Feed::Black => (&black[..], &frame.depth[..], None),
        Feed::Masked(m) => (&frame.rgb[..], &frame.depth[..], Some(m)),
    };
    tracker.track(&FrameInput { timestamp_ns: frame.timestamp_ns, rgb, depth, dynamic_mask }).expect("track")
}

/// A lost frame: no pose, no inliers, no keyframe.
fn assert_lost(out: &TrackOutput, what: &str) {
    assert_eq!(out.state, TrackingState::Lost, "{what}");
    assert!(out.world_from_camera.is_none() && out.tracked_points == 0 && !out.keyframe, "{what}: {out:?}");
}

/// Tracks real frames `range` and checks every one is `Tracking` within the bounds
/// of ground truth (map started at `first`); returns the largest errors.
fn track_and_check(tracker: &mut Tracker, first: usize, range: std::ops::Range<usize>, bound: (f64, f64)) -> (f64, f64) {
    let clip = Clip::get();
    let mut worst = (0f64, 0f64);
    for i in range {
        let out = track(tracker, &clip.frames[i], Feed::Real);
        assert_eq!(out.state, TrackingState::Tracking, "frame {i}");
        let (m, deg) = clip.error(first, i, &out.world_from_camera.expect("pose"));
        assert!(m <= bound.0 && deg <= bound.1, "frame {i}: {:.1} mm {deg:.2}°", m * 1e3);
        worst = (worst.0.max(m), worst.1.max(deg));
    }
    worst
}

#[test]
fn synthetic_sway_meets_the_issue_targets() {
    let camera = kinect_camera();
    let scene = Scene::room(SYNTHETIC_SEED);
    let mut tracker = Tracker::new(camera.clone(), TrackerConfig::default()).expect("tracker");
    let (mut gt, mut est) = (Vec::new(), Vec::new());
    for (i, pose) in sway_path(SYNTHETIC_FRAMES).iter().enumerate() {
        let r = render(&scene, &camera, pose);
        let ts = i as u64 * SYNTHETIC_FRAME_NS;
        let out = tracker.track(&FrameInput { timestamp_ns: ts, rgb: &r.rgb, depth: &r.depth, dynamic_mask: None }).expect("track");
        assert_eq!(out.state, TrackingState::Tracking, "frame {i}");
        gt.push((ts, *pose));
        est.push((ts, out.world_from_camera.expect("pose")));
    }
    let s = tum::score(&gt, &est);
    println!("synthetic: ATE {:.2} mm {:.3}° | RPE {:.2} mm {:.3}°", s.ate_m * 1e3, s.ate_deg, s.rpe_m * 1e3, s.rpe_deg);
    assert_eq!(s.pairs, SYNTHETIC_FRAMES);
    assert!(s.ate_m <= SYNTHETIC_MAX_ATE_M && s.ate_deg <= SYNTHETIC_MAX_ATE_DEG, "{s:?}");
}

/// Frames of the rolling-shutter sequence, its readout (a typical 30 Hz CMOS colour
/// camera reads its frame in about 30 ms) and its speed along the sway path (three
/// times the plain sequence's: up to about 60°/s).
const ROLLING_SHUTTER_FRAMES: usize = 60;
const ROLLING_SHUTTER_READOUT_S: f64 = 0.03;
const ROLLING_SHUTTER_SPEED: f64 = 3.0;

#[test]
fn a_rolling_shutter_camera_is_tracked_with_its_readout_modelled() {
    let camera = stillmap_tracking::Camera { readout_s: ROLLING_SHUTTER_READOUT_S, ..kinect_camera() };
    let scene = Scene::room(SYNTHETIC_SEED);
    let frame_s = SYNTHETIC_FRAME_NS as f64 * 1e-9;
    // Frame k's rows are read around its middle row's time k·frame_s; its ground truth
    // is the middle row's pose.
    let frames: Vec<_> = (0..ROLLING_SHUTTER_FRAMES)
        .map(|k| {
            let at = |t: f64| sway_pose(ROLLING_SHUTTER_SPEED * (k as f64 + t / frame_s));
            (at(0.0), render_rolling_shutter(&scene, &camera, at, &RenderOptions::default()))
        })
        .collect();
    let score = |camera: &stillmap_tracking::Camera| {
        let mut tracker = Tracker::new(camera.clone(), TrackerConfig::default()).expect("tracker");
        let (mut gt, mut est) = (Vec::new(), Vec::new());
        for (i, (pose, r)) in frames.iter().enumerate() {
            let ts = i as u64 * SYNTHETIC_FRAME_NS;
            let out = tracker.track(&FrameInput { timestamp_ns: ts, rgb: &r.rgb, depth: &r.depth, dynamic_mask: None }).expect("track");
            assert_eq!(out.state, TrackingState::Tracking, "frame {i}");
            gt.push((ts, *pose));
            est.push((ts, out.world_from_camera.expect("pose")));
        }
        tum::score(&gt, &est)
    };
    let modelled = score(&camera);
    let ignored = score(&stillmap_tracking::Camera { readout_s: 0.0, ..camera.clone() });
    // Rotation origin-aligned: on a path this short, the Umeyama fit's rotation hangs
    // on millimetres of position error.
    println!(
        "rolling shutter: modelled ATE {:.2} mm {:.3}° (origin-aligned), ignored ATE {:.2} mm {:.3}°",
        modelled.ate_m * 1e3,
        modelled.ate_origin_deg,
        ignored.ate_m * 1e3,
        ignored.ate_origin_deg
    );
    assert!(modelled.ate_m <= SYNTHETIC_MAX_ATE_M && modelled.ate_origin_deg <= SYNTHETIC_MAX_ATE_DEG, "{modelled:?}");
    assert!(
        ignored.ate_m > 3.0 * modelled.ate_m && ignored.ate_origin_deg > 3.0 * modelled.ate_origin_deg,
        "ignoring the readout: {ignored:?}, modelling it: {modelled:?}"
    );
}

#[test]
fn fr1_rpy_is_tracked_accurately_and_deterministically() {
    let clip = Clip::get();
    let run = || {
        let mut tracker = fr1_tracker();
        clip.frames.iter().map(|f| track(&mut tracker, f, Feed::Real)).collect::<Vec<_>>()
    };
    let (first, second) = (run(), run());
    for (i, (a, b)) in first.iter().zip(&second).enumerate() {
        assert_eq!(a.state, TrackingState::Tracking, "frame {i}");
        assert!(a.world_from_camera.is_some(), "frame {i}");
        assert_eq!((a.state, a.world_from_camera, a.tracked_points), (b.state, b.world_from_camera, b.tracked_points), "frame {i}");
    }
    let est: Vec<_> =
        clip.frames.iter().zip(&first).filter_map(|(f, o)| Some((tum::fr1_pose_time_ns(f.timestamp_ns), o.world_from_camera?))).collect();
    let s = tum::score(&clip.gt, &est);
    println!(
        "fr1_rpy: {} frames | ATE {:.2} cm {:.2}° (origin-aligned {:.2}°) | RPE {:.2} mm {:.3}°",
        s.pairs,
        s.ate_m * 100.0,
        s.ate_deg,
        s.ate_origin_deg,
        s.rpe_m * 1e3,
        s.rpe_deg
    );
    assert_eq!(s.pairs, FR1_RPY_FRAMES);
    assert!(s.ate_m <= FR1_MAX_ATE_M && s.ate_origin_deg <= FR1_MAX_ATE_ORIGIN_DEG, "{s:?}");
    assert!(s.rpe_m <= FR1_MAX_RPE_M && s.rpe_deg <= FR1_MAX_RPE_DEG, "{s:?}");
}

/// Frames dropped on the way (a saturated server, a slower camera): fr1_rpy fed
/// every third frame (10 Hz) and with each frame kept at random with probability
/// 1/2 (a fixed seed) is tracked on every frame fed, within
/// `DROPPED_FRAMES_MAX_ATE_M`. Measured 1.32 and 1.05 cm (every frame: 0.77 cm);
/// before the dense alignment started from the motion model's step and its prior
/// widened with the frame intervals it spans: 11.0 cm with a frame lost, and 3.6 cm
/// with 9 lost.
#[test]
fn dropped_frames_are_tracked() {
    let clip = Clip::get();
    let every_third: Vec<&tum::TumFrame> = clip.frames.iter().step_by(3).collect();
    let half_at_random = tum::half_at_random(&clip.frames);
    for (what, fed) in [("every third frame", every_third), ("half the frames at random", half_at_random)] {
        let mut tracker = fr1_tracker();
        let mut est = Vec::new();
        for f in &fed {
            let out = track(&mut tracker, f, Feed::Real);
            let pose = out.world_from_camera.unwrap_or_else(|| panic!("{what}: no pose at {}: {out:?}", f.timestamp_ns));
            est.push((tum::fr1_pose_time_ns(f.timestamp_ns), pose));
        }
        let s = tum::score(&clip.gt, &est);
        println!("fr1_rpy, {what} ({} frames): ATE {:.2} cm", fed.len(), s.ate_m * 100.0);
        assert!(s.ate_m <= DROPPED_FRAMES_MAX_ATE_M, "{what}: {s:?}");
    }
}

/// The fewest keyframes `tracking.max_keyframes` takes with the default windows
/// (`local_keyframes` 10 + `ba_window` 6 + 1).
const FEWEST_KEYFRAMES: usize = 17;
/// Pose error bound on the second pass of
/// `keyframes_beyond_max_keyframes_are_forgotten_and_tracking_holds`.
const FORGETTING_SECOND_PASS_MAX_ERROR_M: f64 = 0.06;
const FORGETTING_SECOND_PASS_MAX_ERROR_DEG: f64 = 4.5;

/// A session longer than `tracking.max_keyframes` allows: fr1_rpy with the
/// smallest cap, twice over (the second time after a jump back to its first frame,
/// 5 s later). The tracker never holds more keyframes than the cap, forgets one
/// for each it makes beyond it, keeps its map consistent (every observation a
/// point lists is a slot of a kept keyframe naming it back, every point a kept
/// keyframe names exists), tracks every frame of the first pass within the clip's
/// bounds (measured ATE 0.75 cm, RPE 5.28 mm; without the cap 0.77 cm, 5.31 mm),
/// relocalizes on the first frame of the second pass against what it kept and
/// poses every frame of it within `FORGETTING_SECOND_PASS_MAX_ERROR_*` (measured
/// at most 39.3 mm, 3.12°). 64 keyframes made, 47 forgotten.
#[test]
fn keyframes_beyond_max_keyframes_are_forgotten_and_tracking_holds() {
    let clip = Clip::get();
    let config = TrackerConfig { max_keyframes: FEWEST_KEYFRAMES, ..TrackerConfig::default() };
    let mut tracker = Tracker::new(tum::fr1_camera(), config).expect("tracker");
    let (mut made, mut est, mut second) = (0, Vec::new(), Vec::new());
    let pass_ns = 5_000_000_000;
    for pass in 0..2u64 {
        for (i, f) in clip.frames.iter().enumerate() {
            let input = FrameInput { timestamp_ns: f.timestamp_ns + pass * pass_ns, rgb: &f.rgb, depth: &f.depth, dynamic_mask: None };
            let out = tracker.track(&input).expect("track");
            made += usize::from(out.keyframe);
            let map = tracker.map();
            assert!(map.keyframes.len() <= FEWEST_KEYFRAMES, "pass {pass} frame {i}: {} keyframes", map.keyframes.len());
            assert_eq!(tracker.forgotten_keyframes() as usize, made.saturating_sub(FEWEST_KEYFRAMES), "pass {pass} frame {i}");
            if pass == 0 {
                assert_eq!(out.state, TrackingState::Tracking, "frame {i}");
                est.push((tum::fr1_pose_time_ns(f.timestamp_ns), out.world_from_camera.expect("pose")));
            } else if let Some(p) = out.world_from_camera {
                second.push((i, out.state, clip.error(0, i, &p)));
            }
        }
    }
    let map = tracker.map();
    for (id, mp) in &map.points {
        for &(kf, f) in &mp.observations {
            assert_eq!(map.keyframes.get(&kf).and_then(|k| k.points.get(f).copied()).flatten(), Some(*id), "point {id} in keyframe {kf}");
        }
    }
    for kf in map.keyframes.values() {
        assert!(kf.points.iter().flatten().all(|p| map.points.contains_key(p)), "keyframe {} names a point that is gone", kf.id);
    }
    let s = tum::score(&clip.gt, &est);
    let worst = second.iter().fold((0f64, 0f64), |w, (_, _, (m, deg))| (w.0.max(*m), w.1.max(*deg)));
    println!(
        "fr1_rpy with at most {FEWEST_KEYFRAMES} keyframes ({made} made): ATE {:.2} cm, RPE {:.2} mm; second pass: {} of {} frames posed, first {:?}, worst {:.1} mm {:.2}°",
        s.ate_m * 100.0,
        s.rpe_m * 1e3,
        second.len(),
        clip.frames.len(),
        second.first().map(|(i, state, _)| (*i, *state)),
        worst.0 * 1e3,
        worst.1
    );
    assert_eq!(made, tracker.map().keyframes.len() + tracker.forgotten_keyframes() as usize);
    assert!(s.ate_m <= FR1_MAX_ATE_M && s.rpe_m <= FR1_MAX_RPE_M, "first pass: {s:?}");
    assert_eq!(second.len(), clip.frames.len(), "every frame of the second pass posed");
    assert_eq!(second.first().map(|(i, state, _)| (*i, *state)), Some((0, TrackingState::Relocalized)));
    assert!(worst.0 <= FORGETTING_SECOND_PASS_MAX_ERROR_M && worst.1 <= FORGETTING_SECOND_PASS_MAX_ERROR_DEG, "second pass: {worst:?}");
}

/// At 7.5 Hz (every 4th frame) the first step after the first keyframe has no
/// velocity to predict from, and on rpy_b the motion model places it about 10 cm
/// off on a few of the keyframe's points. That placement is weak (under
/// `tracking.weak_placement_ratio` of the reference keyframe's points), so the
/// frame is relocalized too, and relocalization's placement, on more than twice
/// as many points, replaces it.
#[test]
fn a_weak_placement_is_replaced_by_relocalization() {
    let dir = stillmap_dataset::shared::fr1_rpy_b();
    let clip = Clip { frames: tum::load(&dir, 5), gt: tum::groundtruth(&dir) };
    let run = |config: TrackerConfig| {
        let mut tracker = Tracker::new(tum::fr1_camera(), config).expect("tracker");
        assert_eq!(track(&mut tracker, &clip.frames[0], Feed::Real).state, TrackingState::Tracking);
        let out = track(&mut tracker, &clip.frames[4], Feed::Real);
        // Frame 4's pose in the map started at frame 0.
        let (error_m, _) = clip.error(0, 4, &out.world_from_camera.expect("a pose"));
        (out.state, out.tracked_points, error_m)
    };
    let (state, points, error_m) = run(TrackerConfig::default());
    let (state_off, points_off, error_off_m) = run(TrackerConfig { weak_placement_ratio: 0.0, ..TrackerConfig::default() });
    println!(
        "rpy_b frame 4 after frame 0: {state:?} on {points} points, {:.1} mm off; without the check {state_off:?} on {points_off}, {:.1} mm off",
        error_m * 1e3,
        error_off_m * 1e3
    );
    assert_eq!(state_off, TrackingState::Tracking);
    assert!(error_off_m >= 0.05, "the motion model's placement is the wrong one here: {:.1} mm", error_off_m * 1e3);
    assert_eq!(state, TrackingState::Relocalized);
    assert!(points > 2 * points_off, "{points} against {points_off}");
    assert!(error_m <= 0.02, "relocalized {:.1} mm off", error_m * 1e3);
}

#[test]
fn frames_without_depth_or_colour_cannot_start_the_map() {
    let clip = Clip::get();
    let mut tracker = fr1_tracker();
    for (i, feed) in [Feed::NoDepth, Feed::NoDepth, Feed::Black].into_iter().enumerate() {
        let out = track(&mut tracker, &clip.frames[i], feed);
        assert_eq!(out.state, TrackingState::Initializing, "frame {i}");
        assert!(out.world_from_camera.is_none() && !out.keyframe, "frame {i}: {out:?}");
        assert!(tracker.map().keyframes.is_empty() && tracker.map().points.is_empty());
    }
    // The first good frame starts the map at the identity.
    const FIRST: usize = 3;
    let out = track(&mut tracker, &clip.frames[FIRST], Feed::Real);
    assert_eq!(out.state, TrackingState::Tracking);
    assert_eq!(out.world_from_camera, Some(Isometry3::identity()));
    assert!(out.keyframe && tracker.map().keyframes.len() == 1);
    let (m, deg) =
        track_and_check(&mut tracker, FIRST, FIRST + 1..FIRST + 1 + FRAMES_AFTER_RECOVERY, (RECOVERY_MAX_ERROR_M, RECOVERY_MAX_ERROR_DEG));
    println!("map started on frame {FIRST}: then at most {:.1} mm {deg:.2}° from ground truth", m * 1e3);
}

/// Tracks `FRAMES_BEFORE_DROPOUT` good frames, then `bad` frames fed as `feed`
/// (each must be lost), then checks relocalization and the frames after it.
fn lose_and_recover(config: TrackerConfig, feed: Feed<'_>, bad: usize, what: &str) {
    let clip = Clip::get();
    let mut tracker = Tracker::new(tum::fr1_camera(), config).expect("tracker");
    for f in &clip.frames[..FRAMES_BEFORE_DROPOUT] {
        assert_eq!(track(&mut tracker, f, Feed::Real).state, TrackingState::Tracking);
    }
    let resume = FRAMES_BEFORE_DROPOUT + bad;
    for i in FRAMES_BEFORE_DROPOUT..resume {
        assert_lost(&track(&mut tracker, &clip.frames[i], feed), &format!("{what}, frame {i}"));
    }
    let out = track(&mut tracker, &clip.frames[resume], Feed::Real);
    assert_eq!(out.state, TrackingState::Relocalized, "{what}: frame {resume}");
    assert!(out.keyframe, "a relocalized frame becomes a keyframe");
    let (m, deg) = clip.error(0, resume, &out.world_from_camera.expect("pose"));
    println!("{what}: relocalized at frame {resume} {:.1} mm {deg:.2}° from ground truth", m * 1e3);
    assert!(m <= RECOVERY_MAX_ERROR_M && deg <= RECOVERY_MAX_ERROR_DEG);
    let (m, deg) =
        track_and_check(&mut tracker, 0, resume + 1..resume + 1 + FRAMES_AFTER_RECOVERY, (RECOVERY_MAX_ERROR_M, RECOVERY_MAX_ERROR_DEG));
    println!("{what}: then at most {:.1} mm {deg:.2}°", m * 1e3);
}

#[test]
fn depth_dropout_is_lost_then_relocalized() {
    // Without depth dense odometry has nothing to align either: no coasting.
    lose_and_recover(TrackerConfig::default(), Feed::NoDepth, DEPTH_DROPOUT_FRAMES, "depth dropout");
}

#[test]
fn black_frame_is_lost_then_relocalized_when_coasting_is_off() {
    lose_and_recover(TrackerConfig { coast_s: 0.0, ..TrackerConfig::default() }, Feed::Black, 1, "black frame");
}

/// Black frames with real depth: the features find nothing, dense odometry aligns
/// the depth alone. Each frame is `Coasting` with a pose near the truth, makes no
/// keyframe, and the real frames after them are placed against the map again.
#[test]
fn black_frames_are_coasted_on_depth_then_tracked() {
    let clip = Clip::get();
    let mut tracker = fr1_tracker();
    for f in &clip.frames[..FRAMES_BEFORE_DROPOUT] {
        assert_eq!(track(&mut tracker, f, Feed::Real).state, TrackingState::Tracking);
    }
    let keyframes = tracker.map().keyframes.len();
    let resume = FRAMES_BEFORE_DROPOUT + COASTED_FRAMES;
    let mut worst = (0f64, 0f64);
    for i in FRAMES_BEFORE_DROPOUT..resume {
        let out = track(&mut tracker, &clip.frames[i], Feed::Black);
        assert_eq!((out.state, out.tracked_points, out.keyframe), (TrackingState::Coasting, 0, false), "frame {i}");
        let (m, deg) = clip.error(0, i, &out.world_from_camera.expect("a coasted pose"));
        assert!(m <= RECOVERY_MAX_ERROR_M && deg <= RECOVERY_MAX_ERROR_DEG, "frame {i}: {:.1} mm {deg:.2}°", m * 1e3);
        worst = (worst.0.max(m), worst.1.max(deg));
    }
    assert_eq!(tracker.map().keyframes.len(), keyframes, "coasted frames make no keyframe");
    println!("black frames coasted: at most {:.1} mm {:.2}° from ground truth", worst.0 * 1e3, worst.1);
    // The first real frame is placed by the local map around the coasted pose or by
    // relocalization, whichever matches more points (here relocalization: 10.9 mm,
    // 1.15° from the truth).
    let out = track(&mut tracker, &clip.frames[resume], Feed::Real);
    assert!(matches!(out.state, TrackingState::Tracking | TrackingState::Relocalized), "frame {resume}: {:?}", out.state);
    let (m, deg) = clip.error(0, resume, &out.world_from_camera.expect("pose"));
    assert!(m <= RECOVERY_MAX_ERROR_M && deg <= RECOVERY_MAX_ERROR_DEG, "frame {resume}: {:.1} mm {deg:.2}°", m * 1e3);
    println!("frame {resume} {:?}: {:.1} mm {deg:.2}°", out.state, m * 1e3);
    let (m, deg) =
        track_and_check(&mut tracker, 0, resume + 1..resume + 1 + FRAMES_AFTER_RECOVERY, (RECOVERY_MAX_ERROR_M, RECOVERY_MAX_ERROR_DEG));
    println!("then tracked: at most {:.1} mm {deg:.2}°", m * 1e3);
}

/// Coasting lasts `coast_s` of capture time from the last tracked frame, then the
/// tracker is lost (no pose) until relocalization.
#[test]
fn coasting_ends_after_coast_s() {
    const COAST_S: f64 = 0.1;
    let clip = Clip::get();
    let mut tracker = Tracker::new(tum::fr1_camera(), TrackerConfig { coast_s: COAST_S, ..TrackerConfig::default() }).expect("tracker");
    for f in &clip.frames[..FRAMES_BEFORE_DROPOUT] {
        assert_eq!(track(&mut tracker, f, Feed::Real).state, TrackingState::Tracking);
    }
    let tracked_ns = clip.frames[FRAMES_BEFORE_DROPOUT - 1].timestamp_ns;
    let resume = FRAMES_BEFORE_DROPOUT + 3 * COASTED_FRAMES;
    let mut states = Vec::new();
    for i in FRAMES_BEFORE_DROPOUT..resume {
        let out = track(&mut tracker, &clip.frames[i], Feed::Black);
        let within = (clip.frames[i].timestamp_ns - tracked_ns) as f64 * 1e-9 <= COAST_S;
        if within {
            assert_eq!(out.state, TrackingState::Coasting, "frame {i}");
            assert!(out.world_from_camera.is_some(), "frame {i}");
        } else {
            assert_lost(&out, &format!("frame {i}, {COAST_S} s after the last tracked one"));
        }
        states.push(out.state);
    }
    assert!(states.contains(&TrackingState::Coasting) && states.contains(&TrackingState::Lost), "{states:?}");
    assert_eq!(track(&mut tracker, &clip.frames[resume], Feed::Real).state, TrackingState::Relocalized);
}

#[test]
fn jump_breaks_continuity_then_relocalizes() {
    let clip = Clip::get();
    let jump = clip.gt(JUMP_FROM).inverse() * clip.gt(JUMP_TO);
    let jump_deg = jump.rotation.angle().to_degrees();
    assert!(jump_deg >= JUMP_MIN_GT_ROTATION_DEG, "ground truth turns {jump_deg:.1}° over the jump");
    let mut tracker = fr1_tracker();
    for f in &clip.frames[..=JUMP_FROM] {
        assert_eq!(track(&mut tracker, f, Feed::Real).state, TrackingState::Tracking);
    }
    let mut states = Vec::new();
    let mut worst = (0f64, 0f64);
    for i in JUMP_TO..FR1_RPY_FRAMES {
        let out = track(&mut tracker, &clip.frames[i], Feed::Real);
        assert_eq!(out.world_from_camera.is_some(), out.state != TrackingState::Lost, "frame {i}: {out:?}");
        if let Some(pose) = out.world_from_camera {
            let (m, deg) = clip.error(0, i, &pose);
            assert!(m <= JUMP_MAX_ERROR_M && deg <= JUMP_MAX_ERROR_DEG, "frame {i}: {:.1} mm {deg:.2}°", m * 1e3);
            worst = (worst.0.max(m), worst.1.max(deg));
        }
        states.push(out.state);
    }
    println!(
        "jump {JUMP_FROM}→{JUMP_TO} ({jump_deg:.1}°, {:.1} cm): states after it {:?}…; poses at most {:.1} mm {:.2}° from ground truth",
        jump.translation.vector.norm() * 100.0,
        &states[..JUMP_RELOCALIZE_WITHIN + 2],
        worst.0 * 1e3,
        worst.1
    );
    assert_ne!(states[0], TrackingState::Tracking, "the motion model must not bridge the jump");
    let relocalized = states.iter().position(|s| *s == TrackingState::Relocalized).expect("relocalized");
    assert!(relocalized < JUMP_RELOCALIZE_WITHIN, "relocalized {relocalized} frames after the jump");
    assert!(states[relocalized + 1..].iter().all(|s| *s == TrackingState::Tracking), "{states:?}");
}

#[test]
fn bad_input_sizes_are_rejected() {
    let clip = Clip::get();
    let f = &clip.frames[0];
    let mut tracker = fr1_tracker();
    let short_rgb = &f.rgb[..100];
    let short_depth = &f.depth[..100];
    let long_mask = vec![0u8; f.depth.len() + 1];
    let cases: [(FrameInput<'_>, &str); 3] = [
        (
            FrameInput { timestamp_ns: 0, rgb: short_rgb, depth: &f.depth, dynamic_mask: None },
            "colour has 100 bytes, expected 921600 (640x480x3)",
        ),
        (
            FrameInput { timestamp_ns: 0, rgb: &f.rgb, depth: short_depth, dynamic_mask: None },
            "depth has 100 pixels, expected 307200 (640x480)",
        ),
        (
            FrameInput { timestamp_ns: 0, rgb: &f.rgb, depth: &f.depth, dynamic_mask: Some(&long_mask) },
            "dynamic mask has 307201 pixels, expected 307200 (640x480)",
        ),
    ];
    for (input, expected) in cases {
        match tracker.track(&input) {
            Err(e @ TrackingError::Input(_)) => assert_eq!(e.to_string(), format!("bad tracking input: {expected}")),
            other => panic!("expected an input error, got {other:?}"),
        }
    }
    // Rejected frames leave the tracker untouched: the next good frame starts the map.
    assert!(tracker.map().keyframes.is_empty());
    assert_eq!(track(&mut tracker, f, Feed::Real).world_from_camera, Some(Isometry3::identity()));

    let tiny = stillmap_tracking::Camera::pinhole(2, 2, 1.0, 1.0, 1.0, 1.0, 1000.0);
    match Tracker::new(tiny, TrackerConfig::default()) {
        Err(e @ TrackingError::Config(_)) => assert_eq!(e.to_string(), "bad tracking configuration: image 2x2 is too small to track"),
        other => panic!("expected a configuration error, got {:?}", other.err()),
    }
}

#[test]
fn dynamic_mask_removes_features_and_tracking_uses_the_rest() {
    let clip = Clip::get();
    let (w, h) = (tum::fr1_camera().width as usize, tum::fr1_camera().height as usize);
    let mask_where = |dynamic: &dyn Fn(usize) -> bool| (0..w * h).map(|p| u8::from(dynamic(p % w))).collect::<Vec<u8>>();
    let left = mask_where(&|x| x < w / 2);
    let right = mask_where(&|x| x >= w / 2);
    let all = mask_where(&|_| true);
    let first = &clip.frames[MASK_FIRST_FRAME];
    let masked = |mask: &[u8]| track(&mut fr1_tracker(), first, Feed::Masked(mask));

    // `masked_features` counts the detected keypoints the mask removed: the left and
    // right halves partition the full mask's count, and no mask removes none.
    let (l, r, a, none) = (masked(&left), masked(&right), masked(&all), track(&mut fr1_tracker(), first, Feed::Real));
    println!(
        "masked keypoints: left {} right {} all {} (features kept: {} / {} / {})",
        l.masked_features, r.masked_features, a.masked_features, l.features, r.features, a.features
    );
    assert!(l.masked_features > 0 && r.masked_features > 0);
    assert_eq!(l.masked_features + r.masked_features, a.masked_features);
    assert_eq!(none.masked_features, 0);
    assert!(a.masked_features >= none.features);
    // A fully masked frame has nothing to track.
    assert_eq!((a.features, a.state, a.world_from_camera), (0, TrackingState::Initializing, None));

    // Tracking on the right half alone.
    let mut tracker = fr1_tracker();
    let mut worst = (0f64, 0f64);
    for i in MASK_FIRST_FRAME..MASK_FIRST_FRAME + MASK_FRAMES {
        let out = track(&mut tracker, &clip.frames[i], Feed::Masked(&left));
        assert_eq!(out.state, TrackingState::Tracking, "frame {i}");
        assert!(out.masked_features > 0 && out.features > 0, "frame {i}: {out:?}");
        let (m, deg) = clip.error(MASK_FIRST_FRAME, i, &out.world_from_camera.expect("pose"));
        assert!(m <= MASK_MAX_ERROR_M && deg <= MASK_MAX_ERROR_DEG, "frame {i}: {:.1} mm {deg:.2}°", m * 1e3);
        worst = (worst.0.max(m), worst.1.max(deg));
    }
    println!(
        "left half masked, frames {MASK_FIRST_FRAME}..{}: at most {:.1} mm {:.2}° from ground truth",
        MASK_FIRST_FRAME + MASK_FRAMES,
        worst.0 * 1e3,
        worst.1
    );
    // No keyframe holds a feature from the masked half (x rounds below w/2 there).
    for kf in tracker.map().keyframes.values() {
        assert!(kf.features.features.iter().all(|f| f.raw.x.round() as usize >= w / 2), "keyframe {}", kf.id);
    }
}
