//! Test support: fuses a clip's keyframes into a map the way the server does (the
//! real masker and tracker choose keyframes and masks; keyframes are fused at their
//! ground-truth poses), and measures voxels against pasted planar objects.
#![allow(dead_code)] // each test file uses part of it

use nalgebra::{Isometry3, Point3, Vector3};
use stillmap_mapping::{DepthView, MapBuilder, MappingConfig};
use stillmap_perception::composite::TexturedPlane;
use stillmap_perception::{Segmenter, YoloSegmenter};

use crate::{composite_run, tum};

/// A frame as the pipeline sees it, and the board's world pose when one is pasted in.
pub struct Frame {
    pub timestamp_ns: u64,
    pub rgb: Vec<u8>,
    pub depth: Vec<u16>,
}

#[derive(Clone, Copy, PartialEq)]
pub enum Masking {
    /// The fused dynamic/static mask keeps pixels out of the map (the pipeline).
    Perception,
    /// Every pixel is fused (the control: shows what the mask prevents).
    None,
}

pub struct Fused {
    pub builder: MapBuilder,
    pub keyframes: Vec<usize>,
    /// The tracker's poses (stamped at the ground truth's time base).
    pub trajectory: Vec<(u64, Isometry3<f64>)>,
    /// Time spent fusing keyframes, and taking samples back out.
    pub fuse_time: std::time::Duration,
    pub retract_time: std::time::Duration,
    /// Occupied-voxel snapshots after the given frames.
    pub snapshots: Vec<(usize, Vec<Point3<f64>>)>,
}

/// Runs perception and tracking over `frames`, fusing the tracker's keyframes at
/// the ground-truth poses. `segment_every`: frames k with k % n == 0 are segmented
/// (their result arrives for that frame; the masker warps it forward until the next).
pub fn fuse(
    frames: &[Frame],
    poses: &[Isometry3<f64>],
    masking: Masking,
    segmenter: Option<(&mut YoloSegmenter, usize)>,
    snapshot_at: &[usize],
) -> Fused {
    fuse_debug(frames, poses, masking, segmenter, snapshot_at, None)
}

/// [`fuse`], printing per keyframe how much of `debug_truth` (each frame's exact
/// object pixels) the mapping mask kept out.
pub fn fuse_debug(
    frames: &[Frame],
    poses: &[Isometry3<f64>],
    masking: Masking,
    mut segmenter: Option<(&mut YoloSegmenter, usize)>,
    snapshot_at: &[usize],
    debug_truth: Option<&[Vec<u8>]>,
) -> Fused {
    let camera = tum::fr1_camera();
    let names: Vec<String> = segmenter.as_ref().map(|(s, _)| s.class_names().to_vec()).unwrap_or_default();
    let mut pipeline = composite_run::MaskedTracking::new(&names);
    let mut builder = MapBuilder::new(&camera, MappingConfig::default()).expect("builder");
    let (mut keyframes, mut snapshots, mut trajectory) = (Vec::new(), Vec::new(), Vec::new());
    let (mut fuse_time, mut retract_time) = (std::time::Duration::ZERO, std::time::Duration::ZERO);
    for (k, (f, gt_pose)) in frames.iter().zip(poses).enumerate() {
        // Gravity from the ground truth's up (+z), as an accelerometer at rest reports it.
        let accel = gt_pose.rotation.inverse() * Vector3::z() * 9.81;
        builder.observe_accel(gt_pose, &accel);
        let segmentation = match segmenter.as_mut() {
            Some((s, every)) if k % *every == 0 => Some((k as u64, s.segment(&f.rgb, 640, 480).expect("segment"))),
            _ => None,
        };
        let (_, track, mask) = pipeline.step(k as u64, f.timestamp_ns, &f.rgb, &f.depth, segmentation, Some(accel));
        if let Some(p) = track.world_from_camera {
            trajectory.push((tum::fr1_pose_time_ns(f.timestamp_ns), p));
        }
        if masking == Masking::Perception {
            let t = std::time::Instant::now();
            for r in &mask.retractions {
                builder.retract(r.keyframe, r.pixel_test(camera.width));
            }
            retract_time += t.elapsed();
        }
        if track.keyframe {
            let exclude = pipeline.masker.mapping_mask(&mask.fused, &f.depth).expect("mapping mask");
            if let Some(truth) = debug_truth.and_then(|t| t.get(k)) {
                let n = truth.iter().filter(|&&t| t != 0).count();
                let kept = truth.iter().zip(&exclude).filter(|&(&t, &e)| t != 0 && e == 0).count();
                // Per object (bit i of the truth: object i), pixels not excluded.
                let per_object: Vec<usize> =
                    (0..3).map(|i| truth.iter().zip(&exclude).filter(|&(&t, &e)| t & (1 << i) != 0 && e == 0).count()).collect();
                let persons: Vec<_> = mask.fused.instances.iter().map(|i| (i.class_name.clone(), i.pixels, i.moving)).collect();
                // STILLMAP_PEOPLE_MISSED=<dir>: each keyframe as a PPM image, the objects' pixels
                // the mapping mask missed red, those it kept out green, other kept-out pixels blue.
                if let Some(dir) = std::env::var_os("STILLMAP_PEOPLE_MISSED") {
                    let mut ppm = b"P6\n640 480\n255\n".to_vec();
                    for (i, (&t, &e)) in truth.iter().zip(&exclude).enumerate() {
                        let g = f.rgb[3 * i] / 3;
                        ppm.extend_from_slice(&match (t != 0, e != 0) {
                            (true, false) => [255, 0, 0],
                            (true, true) => [0, 255, 0],
                            (false, true) => [0, 0, 160],
                            (false, false) => [g, g, g],
                        });
                    }
                    std::fs::write(std::path::Path::new(&dir).join(format!("kf{k}.ppm")), ppm).expect("dump");
                }
                eprintln!("kf {k:3}: truth {n} px, not excluded {kept} {per_object:?}; source {:?}; instances {persons:?}", mask.source);
            }
            let classes = pipeline.masker.segmentation().map(|s| s.class_map());
            let view = DepthView {
                depth: &f.depth,
                rgb: &f.rgb,
                exclude: (masking == Masking::Perception).then_some(exclude.as_slice()),
                classes: classes.as_deref(),
            };
            fuse_time += builder.add_keyframe(k as u64, gt_pose, &view).expect("fuse").fuse_time;
            pipeline.masker.note_keyframe(k as u64);
            keyframes.push(k);
        }
        if snapshot_at.contains(&k) {
            snapshots.push((k, builder.map().occupied().map(|(_, c, _)| c).collect()));
        }
    }
    Fused { builder, keyframes, trajectory, fuse_time, retract_time, snapshots }
}

/// Distance from `p` to the board rectangle at `world_from_plane`.
pub fn distance_to_board(p: &Point3<f64>, world_from_plane: &Isometry3<f64>, plane: &TexturedPlane) -> f64 {
    let q = world_from_plane.inverse() * p;
    let dx = (q.x.abs() - plane.width_m / 2.0).max(0.0);
    let dy = (q.y.abs() - plane.height_m / 2.0).max(0.0);
    (dx * dx + dy * dy + q.z * q.z).sqrt()
}

/// A voxel "is the board" when its centre lies within 1.5 voxels of the board at some frame.
pub const ON_BOARD_M: f64 = 0.03;
