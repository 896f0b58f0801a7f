//! Large moving things of no known class (issue 19's board scene, built from the
//! public clips): photo-printed boards (0.7 × 0.5 m, the shipped photos) carried
//! through the view, set down and carried on, one of them standing in the first
//! frame, together covering a third to half of the image. Tracking runs three ways
//! on each clip: on the object-free frames (the pipeline: mask and tracker), with
//! the boards and the mask, and with the boards and no mask (the tracker alone);
//! and, for the headroom, the tracker alone with exact masks: every board pixel,
//! or only the pixels of boards that move at that instant.
//!
//! Tracking on one arrangement swings with small changes, so the scene is also run
//! in two other arrangements (the boards 0.7 s further along their paths, and
//! their paths mirrored left to right), each with the mask, with the mask but no
//! baseline (`ego_motion.baseline_frames` = 0), and without a mask.
//!
//! A benchmark, not a check: it prints the tables docs/people.md quotes.
//! `cargo test --release -p stillmap-perception --test boards -- --ignored --nocapture`

use stillmap_perception::testing as support;
use stillmap_perception::testing::composite_run;
use stillmap_tracking::testing as tum;

use composite_run::{CompositeFrame, Schedule, Stage};
use nalgebra::Isometry3;
use stillmap_perception::composite::{StopAndGo, TexturedPlane, interpolate_pose, paste};
use stillmap_perception::{PerceptionConfig, YoloSegmenter};
use stillmap_tracking::TrackerConfig;

struct Board {
    plane: TexturedPlane,
    motion: StopAndGo,
}

fn boards(poses: &[Isometry3<f64>]) -> Vec<Board> {
    let s = Stage::new(poses);
    // Held a little below the camera (it looks down at the desk).
    let z = s.origin.z - 0.45;
    let photo = |name: &str, w: f64, h: f64| {
        let (rgb, pw, ph) = support::photo(name);
        TexturedPlane::from_image(rgb, pw as usize, ph as usize, w, h)
    };
    vec![
        // Standing 0.7 m ahead in the first frame; carried off to the right after 1.5 s.
        Board {
            plane: photo("bus.jpg", 0.7, 0.5),
            motion: StopAndGo {
                waypoints: vec![(0.0, s.at(0.7, 0.1, z)), (1.5, s.at(0.7, 0.1, z)), (3.0, s.at(0.7, 1.3, z))],
                rotation: s.facing,
            },
        },
        // Carried in from the left, set down for 1.5 s, carried on to the right.
        Board {
            plane: photo("astronaut.png", 0.7, 0.5),
            motion: StopAndGo {
                waypoints: vec![
                    (0.0, s.at(0.8, -1.2, z)),
                    (1.5, s.at(0.8, -0.25, z)),
                    (3.0, s.at(0.8, -0.25, z)),
                    (4.5, s.at(0.8, 0.5, z)),
                ],
                rotation: s.facing,
            },
        },
        // A smaller board carried across at a walking pace, nearer.
        Board {
            plane: photo("bus.jpg", 0.5, 0.35),
            motion: StopAndGo { waypoints: vec![(0.0, s.at(0.6, 0.9, z - 0.1)), (5.0, s.at(0.6, -0.9, z - 0.1))], rotation: s.facing },
        },
    ]
}

/// Where the boards are: as built, further along their paths, or mirrored.
#[derive(Debug, Clone, Copy)]
enum Arrangement {
    AsBuilt,
    Later(f64),
    Mirrored,
}

impl Arrangement {
    fn label(self) -> String {
        match self {
            Self::AsBuilt => "as built".into(),
            Self::Later(dt) => format!("{dt} s later"),
            Self::Mirrored => "mirrored".into(),
        }
    }
}

/// The composite frames of one arrangement and, per frame, the pixels of boards moving then.
fn scene(frames: &[tum::TumFrame], poses: &[Isometry3<f64>], arrangement: Arrangement) -> (Vec<CompositeFrame>, Vec<Vec<u8>>) {
    let camera = tum::fr1_camera();
    let mut boards = boards(poses);
    if let Arrangement::Mirrored = arrangement {
        let s = Stage::new(poses);
        for b in &mut boards {
            for (_, p) in &mut b.motion.waypoints {
                let side = s.side.dot(&(*p - s.origin));
                *p -= 2.0 * side * s.side;
            }
        }
    }
    let later = if let Arrangement::Later(dt) = arrangement { dt } else { 0.0 };
    let t0 = frames[0].timestamp_ns;
    let mut moving_masks = Vec::with_capacity(frames.len());
    let composite = frames
        .iter()
        .zip(poses)
        .map(|(f, world_from_camera)| {
            let t = (f.timestamp_ns - t0) as f64 * 1e-9 + later;
            let (mut rgb, mut depth) = (f.rgb.clone(), f.depth.clone());
            let mut object_mask = vec![0u8; depth.len()];
            let mut moving_mask = vec![0u8; depth.len()];
            // Farthest first.
            let mut order: Vec<&Board> = boards.iter().collect();
            let distance = |b: &Board| (b.motion.world_from_plane(t).translation.vector - world_from_camera.translation.vector).norm();
            order.sort_by(|a, b| distance(b).total_cmp(&distance(a)));
            for b in order {
                let m = paste(&camera, &b.plane, &(world_from_camera.inverse() * b.motion.world_from_plane(t)), &mut rgb, &mut depth);
                let moving = !b.motion.standing(t);
                for ((o, v), m) in object_mask.iter_mut().zip(moving_mask.iter_mut()).zip(m) {
                    *o |= m;
                    *v |= m & u8::from(moving);
                }
            }
            moving_masks.push(moving_mask);
            CompositeFrame { timestamp_ns: f.timestamp_ns, rgb, depth, object_mask }
        })
        .collect();
    (composite, moving_masks)
}

#[test]
#[ignore = "benchmark: prints the board scene's tables (about 5 minutes in release)"]
fn boards_carried_through_the_view() {
    let mut seg = YoloSegmenter::new(&support::segmentation_config("yolov8n-seg_fp32_640.onnx")).expect("model");
    let dirs = [tum::fr1_rpy_dir(), stillmap_dataset::shared::fr1_rpy_b()];
    let schedule = Schedule::Late { every: 2, delay: 0 };
    let verbose = std::env::var_os("STILLMAP_VERBOSE").is_some();
    let no_baseline = || {
        let mut p = PerceptionConfig::default();
        p.ego_motion.baseline_frames = 0;
        p
    };
    let mut table = vec![
        "| clip | boards cover (mean / max / first frame) | ATE object-free | ATE boards, mask | ATE boards, no mask | frames without a pose (free / mask / no mask) | ATE, exact mask of every board / of the moving boards |".to_string(),
        "|---|---|---|---|---|---|---|".to_string(),
    ];
    let mut arrangements = vec![
        "| clip | arrangement | boards cover (mean / max) | ATE boards, mask | mask, no baseline | no mask | frames without a pose (mask / no baseline / no mask) |".to_string(),
        "|---|---|---|---|---|---|---|".to_string(),
    ];
    for dir in &dirs {
        let frames = tum::load(dir, 150);
        let gt = tum::groundtruth(dir);
        // Each board is drawn from where the camera was when the image was exposed (the
        // time its pose is scored at), so that a standing board stands still in the room.
        let poses: Vec<Isometry3<f64>> =
            frames.iter().map(|f| interpolate_pose(&gt, tum::fr1_pose_time_ns(f.timestamp_ns)).expect("ground truth")).collect();
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let ate =
            |t: &[(u64, Isometry3<f64>)]| if t.len() > 2 { format!("{:.2} cm", 100.0 * tum::score(&gt, t).ate_m) } else { "–".into() };
        let cover = |composite: &[CompositeFrame]| -> Vec<f64> {
            composite.iter().map(|f| f.object_mask.iter().filter(|&&m| m != 0).count() as f64 / f.object_mask.len() as f64).collect()
        };
        let free = composite_run::run(&composite_run::without_object(&frames), Some(&mut seg), schedule, false);
        for arrangement in [Arrangement::AsBuilt, Arrangement::Later(0.7), Arrangement::Mirrored] {
            let (composite, moving_masks) = scene(&frames, &poses, arrangement);
            let cover = cover(&composite);
            let masked = composite_run::run(&composite, Some(&mut seg), schedule, verbose);
            let without_baseline =
                composite_run::run_with(&composite, Some(&mut seg), schedule, false, no_baseline(), TrackerConfig::default());
            let unmasked = composite_run::track_unmasked(&composite);
            let mean_cover = 100.0 * cover.iter().sum::<f64>() / cover.len() as f64;
            let max_cover = 100.0 * cover.iter().copied().fold(0.0, f64::max);
            arrangements.push(format!(
                "| {name} | {} | {mean_cover:.0} % / {max_cover:.0} % | {} | {} | {} | {} / {} / {} |",
                arrangement.label(),
                ate(&masked.trajectory),
                ate(&without_baseline.trajectory),
                ate(&unmasked),
                frames.len() - masked.trajectory.len(),
                frames.len() - without_baseline.trajectory.len(),
                frames.len() - unmasked.len(),
            ));
            if let Arrangement::AsBuilt = arrangement {
                let every_board: Vec<Vec<u8>> = composite.iter().map(|f| f.object_mask.clone()).collect();
                let exact = composite_run::track_masked(&composite, &every_board);
                let exact_moving = composite_run::track_masked(&composite, &moving_masks);
                table.push(format!(
                    "| {name} | {mean_cover:.0} % / {max_cover:.0} % / {:.0} % | {} | {} | {} | {} / {} / {} | {} / {} |",
                    100.0 * cover[0],
                    ate(&free.trajectory),
                    ate(&masked.trajectory),
                    ate(&unmasked),
                    frames.len() - free.trajectory.len(),
                    frames.len() - masked.trajectory.len(),
                    frames.len() - unmasked.len(),
                    ate(&exact),
                    ate(&exact_moving),
                ));
            }
        }
    }
    println!("{}\n\n{}", table.join("\n"), arrangements.join("\n"));
}
