//! The dynamic mask on real data with the camera moving: a textured board moving in
//! world coordinates is pasted into the real TUM fr1_rpy frames (rotation-heavy
//! hand-held motion) consistently with the ground truth, and the fused mask is
//! scored against the board's exact mask. Run with `--nocapture` for the numbers.

use stillmap_perception::testing as support;
use stillmap_perception::testing::composite_run;
use stillmap_tracking::testing as tum;

use std::sync::OnceLock;

use composite_run::{CompositeFrame, Schedule};
use stillmap_perception::YoloSegmenter;

/// The clip's frames, their composite with the board, and the ground truth.
type Clip = (Vec<tum::TumFrame>, Vec<CompositeFrame>, Vec<(u64, nalgebra::Isometry3<f64>)>);

fn clip() -> &'static Clip {
    static CLIP: OnceLock<Clip> = OnceLock::new();
    CLIP.get_or_init(|| {
        let dir = tum::fr1_rpy_dir();
        let frames = tum::load(&dir, 150);
        let gt = tum::groundtruth(&dir);
        let composite = composite_run::composite(&frames, &gt);
        (frames, composite, gt)
    })
}

#[test]
fn moving_board_is_found_while_the_camera_rotates() {
    let (frames, composite, gt) = clip();
    let mut seg = YoloSegmenter::new(&support::segmentation_config("yolov8n-seg_fp32_640.onnx")).expect("model");
    let s = composite_run::run(composite, Some(&mut seg), Schedule::EveryFrame, std::env::var_os("STILLMAP_VERBOSE").is_some());
    let plain = composite_run::track_plain(frames);
    if std::env::var_os("STILLMAP_VERBOSE").is_some() {
        for ((t, a), (_, b)) in s.trajectory.iter().zip(&plain) {
            let g0 = gt.iter().min_by_key(|(g, _)| g.abs_diff(s.trajectory[0].0)).expect("gt").1;
            let g = gt.iter().min_by_key(|(g, _)| g.abs_diff(*t)).expect("gt").1;
            let truth = g0.inverse() * g;
            eprintln!(
                "pose {t}: with {:.4} plain {:.4} (to truth from the first frame)",
                (a.translation.vector - truth.translation.vector).norm(),
                (b.translation.vector - truth.translation.vector).norm()
            );
        }
    }
    let with_object = tum::score(gt, &s.trajectory);
    let without = tum::score(gt, &plain);
    eprintln!(
        "scored {} frames: IoU mean {:.3} min {:.3}; false-dynamic {:.4}; features on object {} eliminated {:.4}; ATE with object {:.4} m / without {:.4} m; RPE {:.4} / {:.4} m",
        s.scored_frames,
        s.mean_iou,
        s.min_iou,
        s.false_dynamic,
        s.object_features,
        s.eliminated_fraction,
        with_object.ate_m,
        without.ate_m,
        with_object.rpe_m,
        without.rpe_m
    );
    if std::env::var_os("STILLMAP_VERBOSE").is_some() {
        // The same masker and tracker on the frames without the board: what
        // perception itself costs tracking on this clip, apart from the object
        // (another 40 s, so only on request).
        let unpasted = composite_run::without_object(frames);
        let masked_without = tum::score(gt, &composite_run::run(&unpasted, Some(&mut seg), Schedule::EveryFrame, false).trajectory);
        eprintln!("masked, without the object: ATE {:.4} m, RPE {:.4} m", masked_without.ate_m, masked_without.rpe_m);
    }
    // Measured (this machine, 2026-12-06; the board drawn at the exposure time): 109
    // frames scored, IoU mean 0.75, false-dynamic 1.67 % (2.01 % with
    // `fusion.instance_depth_gate` 0), 97.6 % of the board's features eliminated. Earlier
    // (drawn at the image's timestamp): 107 frames, IoU 0.79, false-dynamic 1.3 %,
    // 96.5 % of the board's features eliminated (94.3 % before the tracking mask grew
    // over the flagged surfaces, 87 % with the mask computed after tracking only),
    // ATE 2.21 cm with the board vs 2.06 cm for the tracker alone without it (+7 %;
    // `--example composite_spread` over five runs with the tracker's feature count
    // nudged by ±1–2 %: medians 2.32 vs 2.19 cm, +6 %). Before the tracker had its
    // dense-odometry prior: 6.0 vs 3.2 cm. The IoU, false-dynamic, elimination and
    // tracking bounds are the targets.
    assert!(s.scored_frames >= 100, "object visible in {} frames", s.scored_frames);
    assert!(s.mean_iou >= 0.7, "IoU {:.3}", s.mean_iou);
    assert!(s.false_dynamic <= 0.02, "false-dynamic {:.4}", s.false_dynamic);
    assert!(s.eliminated_fraction >= 0.95, "eliminated {:.4}", s.eliminated_fraction);
    // Labelled before tracking, the board is masked on the first frame with flow
    // (measured: 137 of its 195 features; with the previous frame's labels alone, none).
    let (on_board, removed) = s.first_flow_frame_features;
    assert!(on_board > 100 && removed * 2 >= on_board, "frame 1: {removed} of {on_board} board features removed");
    assert_eq!(s.trajectory.len(), frames.len(), "every composite frame tracked");
    assert!(with_object.ate_m <= 0.035, "ATE {:.4} vs {:.4}", with_object.ate_m, without.ate_m);
    assert!(
        with_object.ate_m <= 1.2 * without.ate_m,
        "ATE with the board {:.4} m is over 120 % of {:.4} m without it",
        with_object.ate_m,
        without.ate_m
    );
}

/// Segmentation that arrives late (every third frame, two frames after its own) is
/// carried forward by the flow: results say so, and the mask holds up as well as
/// with segmentation on every frame (the board is found by flow either way).
#[test]
fn late_segmentation_is_warped_forward() {
    let (_, composite, _) = clip();
    let frames = &composite[..60];
    let mut seg = YoloSegmenter::new(&support::segmentation_config("yolov8n-seg_fp32_320.onnx")).expect("model");
    let late = composite_run::run(frames, Some(&mut seg), Schedule::Late { every: 3, delay: 2 }, false);
    let none = composite_run::run(frames, None, Schedule::EveryFrame, false);
    eprintln!("late: IoU {:.3}, warped {} frames; no segmentation: IoU {:.3}", late.mean_iou, late.warped_frames, none.mean_iou);
    // Frames 2.. carry a segmentation 1 or 2 frames old except where one arrives fresh (never: delay 2).
    assert_eq!(late.warped_frames, 58);
    assert!((late.mean_iou - none.mean_iou).abs() < 0.1, "{:.3} vs {:.3}", late.mean_iou, none.mean_iou);
}

/// A moving photo of a person (astronaut.png on a 30 × 30 cm board, same motion):
/// the segmenter finds a person, fusion marks the instance moving, and its pixels
/// are dynamic — the paper's "prior-dynamic with flow" case, with the camera moving.
#[test]
fn a_moving_person_is_a_moving_prior_dynamic_instance() {
    let (frames, _, gt) = clip();
    let (photo, w, h) = support::photo("astronaut.png");
    let plane = stillmap_perception::composite::TexturedPlane::from_image(photo, w as usize, h as usize, 0.30, 0.30);
    let composite = composite_run::composite_with(&frames[..60], gt, &plane);
    let mut seg = YoloSegmenter::new(&support::segmentation_config("yolov8n-seg_fp32_640.onnx")).expect("model");
    let s = composite_run::run(&composite, Some(&mut seg), Schedule::EveryFrame, std::env::var_os("STILLMAP_VERBOSE").is_some());
    eprintln!(
        "person board: {} frames scored, IoU {:.3}, person instance moving on {} of {} frames seen",
        s.scored_frames, s.mean_iou, s.moving_person_frames, s.person_frames
    );
    // Measured: a person on 33 of 39 scored frames, judged moving on 23 of them,
    // IoU 0.62. The misses are motion-blurred frames where the sharp, large photo's
    // motion wins the camera-motion estimate, and frames where the board re-enters.
    assert!(s.person_frames * 4 >= s.scored_frames * 3, "person found on {} of {} frames", s.person_frames, s.scored_frames);
    assert!(s.moving_person_frames * 5 >= s.person_frames * 3, "moving on {} of {}", s.moving_person_frames, s.person_frames);
    assert!(s.mean_iou >= 0.55, "IoU {:.3}", s.mean_iou);
}
