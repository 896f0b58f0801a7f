//! Two robots in one room (issue 20): robot A tracks `rgbd_dataset_freiburg1_rpy`,
//! robot B `rgbd_dataset_freiburg1_rpy_b` (the same recording, 5 s later), each in
//! its own world. B's keyframes are looked up in A's place index, verified, and B
//! merges into A's frame once three of its keyframes agree. B's poses in A's frame
//! are scored with A's alignment to the ground truth only.
//!
//! Look-alikes must not merge: B's clip mirrored (the same room, left and right
//! swapped: the same colours, textures and layout statistics) and the synthetic
//! room. The vocabulary is trained on A's clip alone; the synthetic room, which it
//! never saw, still closes its own loop.
//!
//! `cargo test --release -p stillmap-places --test fleet -- --nocapture` prints the numbers.

use stillmap_tracking::testing as tum;

use std::time::Instant;

use nalgebra::Isometry3;
use stillmap_dataset::eval::align::align_orientations;
use stillmap_dataset::eval::associate::associate;
use stillmap_dataset::eval::metrics::{Relation, Stats, ape};
use stillmap_places::{MergeConfig, MergeDetector, Merged, Place, PlaceIndex, VerifyConfig, Vocabulary, propose, verify};
use stillmap_tracking::synthetic::{Scene, kinect_camera, render, sway_path};
use stillmap_tracking::{Camera, FrameInput, Tracker, TrackerConfig};

/// A tracked session: its keyframes (time, world_from_camera, place) and every tracked pose.
struct Session {
    keyframes: Vec<(u64, Isometry3<f64>, Place)>,
    trajectory: Vec<(u64, Isometry3<f64>)>,
}

fn track(camera: &Camera, frames: impl Iterator<Item = (u64, Vec<u8>, Vec<u16>)>) -> Session {
    let mut tracker = Tracker::new(camera.clone(), TrackerConfig::default()).expect("tracker");
    let mut trajectory = Vec::new();
    for (timestamp_ns, rgb, depth) in frames {
        let out = tracker.track(&FrameInput { timestamp_ns, rgb: &rgb, depth: &depth, dynamic_mask: None }).expect("track");
        if let Some(p) = out.world_from_camera {
            trajectory.push((timestamp_ns, p));
        }
    }
    let keyframes = tracker
        .map()
        .keyframes
        .values()
        .map(|kf| (kf.timestamp_ns, kf.world_from_camera, Place::from_features(camera, &kf.features)))
        .collect();
    Session { keyframes, trajectory }
}

fn tum_session(frames: &[tum::TumFrame], mirrored: bool) -> Session {
    let camera = tum::fr1_camera();
    track(
        &camera,
        frames.iter().map(|f| {
            if !mirrored {
                return (f.timestamp_ns, f.rgb.clone(), f.depth.clone());
            }
            let (mut rgb, mut depth) = (f.rgb.clone(), f.depth.clone());
            for row in rgb.chunks_exact_mut(640 * 3) {
                let pixels: Vec<[u8; 3]> = row.chunks_exact(3).rev().map(|p| [p[0], p[1], p[2]]).collect();
                row.copy_from_slice(pixels.as_flattened());
            }
            depth.chunks_exact_mut(640).for_each(<[u16]>::reverse);
            (f.timestamp_ns, rgb, depth)
        }),
    )
}

/// What one session's keyframes found in the fleet's index, in time order.
struct Lookup {
    merged: Option<(u64, Merged)>,
    /// Verifications tried, and those that passed.
    pairings: usize,
    verified: usize,
    /// Mean query and verification time per keyframe (ms).
    query_ms: f64,
    verify_ms: f64,
}

fn look_up(camera: &Camera, vocabulary: &Vocabulary, index: &PlaceIndex<usize>, fleet: &Session, session: &Session) -> Lookup {
    let config = VerifyConfig::default();
    let mut detector = MergeDetector::new(MergeConfig::default()).expect("merge config");
    let mut lookup = Lookup { merged: None, pairings: 0, verified: 0, query_ms: 0.0, verify_ms: 0.0 };
    for (t, session_from_query, place) in &session.keyframes {
        let started = Instant::now();
        let candidates = index.query(&vocabulary.transform(&place.descriptors), 3, 0.0, |_| true);
        lookup.query_ms += started.elapsed().as_secs_f64() * 1e3;
        let started = Instant::now();
        let mut best: Option<(Isometry3<f64>, usize)> = None;
        for (k, _) in candidates {
            lookup.pairings += 1;
            let (_, fleet_from_candidate, candidate) = &fleet.keyframes[k];
            if let Some(v) = verify(camera, place, candidate, &config) {
                lookup.verified += 1;
                if best.is_none_or(|b| v.inliers > b.1) {
                    best = Some((propose(fleet_from_candidate, &v.query_from_candidate, session_from_query), v.inliers));
                }
            }
        }
        lookup.verify_ms += started.elapsed().as_secs_f64() * 1e3;
        if let Some((proposal, inliers)) = best
            && lookup.merged.is_none()
            && let Some(m) = detector.observe(proposal, inliers)
        {
            lookup.merged = Some((*t, m));
        }
    }
    let n = session.keyframes.len().max(1) as f64;
    lookup.query_ms /= n;
    lookup.verify_ms /= n;
    lookup
}

fn index_of(vocabulary: &Vocabulary, session: &Session) -> PlaceIndex<usize> {
    let mut index = PlaceIndex::new();
    for (k, (_, _, place)) in session.keyframes.iter().enumerate() {
        index.insert(k, vocabulary.transform(&place.descriptors));
    }
    index
}

/// Stamped poses in seconds, as the evaluation takes them.
fn seconds(t: &[(u64, Isometry3<f64>)]) -> Vec<(f64, Isometry3<f64>)> {
    t.iter().map(|(ns, p)| (*ns as f64 * 1e-9, *p)).collect()
}

/// Ground-truth and estimated poses paired by time (evo's association, 20 ms).
fn paired(gt: &[(u64, Isometry3<f64>)], est: &[(u64, Isometry3<f64>)]) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) {
    let a = associate(&seconds(gt), &seconds(est), 0.02, 0.0).expect("associated");
    (a.reference.iter().map(|p| p.1).collect(), a.estimate.iter().map(|p| p.1).collect())
}

/// RMS position (m) and rotation (°) error of `gt_from_world · est` against the ground truth.
fn errors(gt: &[(u64, Isometry3<f64>)], gt_from_world: &Isometry3<f64>, est: &[(u64, Isometry3<f64>)]) -> (f64, f64) {
    let (reference, estimate) = paired(gt, est);
    let aligned: Vec<Isometry3<f64>> = estimate.iter().map(|e| gt_from_world * e).collect();
    let rmse = |relation| Stats::of(&ape(&reference, &aligned, relation)).map_or(f64::NAN, |s| s.rmse);
    (rmse(Relation::Translation), rmse(Relation::RotationDeg))
}

#[test]
fn robot_b_merges_into_robot_a_and_look_alikes_never_do() {
    let camera = tum::fr1_camera();
    let a_dir = tum::fr1_rpy_dir();
    let b_dir = stillmap_dataset::shared::fr1_rpy_b();
    let (a_frames, b_frames) = (tum::load(&a_dir, 150), tum::load(&b_dir, 150));
    let stamp = |s: Session| Session { trajectory: s.trajectory.iter().map(|(t, p)| (tum::fr1_pose_time_ns(*t), *p)).collect(), ..s };
    let a = stamp(tum_session(&a_frames, false));
    let b = stamp(tum_session(&b_frames, false));

    // The shipped vocabulary: trained on A's clip only (every 5th frame).
    let vocabulary = Vocabulary::shipped();
    let index = index_of(&vocabulary, &a);

    let found = look_up(&camera, &vocabulary, &index, &a, &b);
    let (merged_at, merged) = found.merged.expect("B merges into A's frame");
    let first_keyframe = b.keyframes.first().map(|k| k.0).expect("B has keyframes");
    let merge_delay_s = (merged_at - first_keyframe) as f64 * 1e-9;

    let gt = tum::groundtruth(&a_dir);
    // A's alignment: the rotation from the orientations (the clip barely translates:
    // a position-only fit leaves it ill-conditioned), the translation from the means.
    let (gt_a, est_a) = paired(&gt, &a.trajectory);
    let gt_from_a = align_orientations(&gt_a, &est_a).expect("A aligned");
    let (a_m, a_deg) = errors(&gt, &gt_from_a, &a.trajectory);
    let b_in_fleet: Vec<(u64, Isometry3<f64>)> = b.trajectory.iter().map(|(t, p)| (*t, merged.fleet_from_session * p)).collect();
    let (b_m, b_deg) = errors(&gt, &gt_from_a, &b_in_fleet);

    // Look-alikes: B mirrored, and the synthetic room, against A's index.
    let mirrored = tum_session(&b_frames, true);
    let mirror = look_up(&camera, &vocabulary, &index, &a, &mirrored);
    let room_camera = kinect_camera();
    let scene = Scene::room(7);
    let path = sway_path(240);
    let room = track(
        &room_camera,
        path.iter().enumerate().map(|(k, p)| {
            let f = render(&scene, &room_camera, p);
            (k as u64 * 33_333_333, f.rgb, f.depth)
        }),
    );
    let synthetic = look_up(&room_camera, &vocabulary, &index, &a, &room);

    // The synthetic room (never trained on) against itself: its later keyframes
    // find its earlier ones, at the true relative pose.
    let room_index = index_of(&vocabulary, &room);
    let truth = |t: u64| path[(t / 33_333_333) as usize];
    let (mut loops, mut worst_loop_m) = (0, 0.0f64);
    for (k, (t, _, place)) in room.keyframes.iter().enumerate() {
        // Earlier keyframes at least two seconds older.
        let older = |&j: &usize| room.keyframes[j].0 + 2_000_000_000 <= *t && j < k;
        for (j, _) in room_index.query(&vocabulary.transform(&place.descriptors), 1, 0.0, older) {
            if let Some(v) = verify(&room_camera, place, &room.keyframes[j].2, &VerifyConfig::default()) {
                loops += 1;
                let exact = truth(*t).inverse() * truth(room.keyframes[j].0);
                worst_loop_m = worst_loop_m.max((exact.inverse() * v.query_from_candidate).translation.vector.norm());
            }
        }
    }

    println!("| | value |");
    println!("|---|---|");
    println!("| vocabulary (shipped: A's clip, 30 frames) | {} words, {} KB |", vocabulary.words(), vocabulary.to_bytes().len() / 1024);
    println!("| keyframes A / B | {} / {} |", a.keyframes.len(), b.keyframes.len());
    println!(
        "| index postings per keyframe | {:.0} ({:.1} KB with the entry's vector) |",
        index.postings() as f64 / index.len() as f64,
        index.postings() as f64 * 16.0 / index.len() as f64 / 1024.0
    );
    let with_depth =
        a.keyframes.iter().map(|k| k.2.points.iter().filter(|p| p.is_some()).count()).sum::<usize>() as f64 / a.keyframes.len() as f64;
    // A stored candidate keeps its features with depth: pixel, octave, point, descriptor.
    let per_feature = std::mem::size_of::<nalgebra::Point2<f64>>() + 1 + std::mem::size_of::<Option<nalgebra::Point3<f64>>>() + 32;
    println!("| stored place per keyframe | {with_depth:.0} features with depth, {:.1} KB |", with_depth * per_feature as f64 / 1024.0);
    println!("| B merged after | {merge_delay_s:.2} s of its keyframes ({} agreeing, {} inliers) |", merged.support, merged.inliers);
    println!("| A's ATE (own alignment) | {:.2} cm, {a_deg:.2}° |", 100.0 * a_m);
    println!("| B's ATE in A's frame (A's alignment) | {:.2} cm, {b_deg:.2}° |", 100.0 * b_m);
    println!("| B: pairings verified / tried | {} / {} |", found.verified, found.pairings);
    println!("| query / verification per keyframe | {:.2} / {:.1} ms |", found.query_ms, found.verify_ms);
    println!("| mirrored B: verified / tried, merged | {} / {}, {} |", mirror.verified, mirror.pairings, mirror.merged.is_some());
    println!(
        "| synthetic room: verified / tried, merged | {} / {}, {} |",
        synthetic.verified,
        synthetic.pairings,
        synthetic.merged.is_some()
    );
    println!("| synthetic room's own loops verified, worst error | {loops}, {:.1} mm |", 1000.0 * worst_loop_m);

    // Measured (2026-12-03): merged 0.20 s after B's first keyframe; 0.78 cm and
    // 0.54° in A's frame (A itself: 1.01 cm, 0.81°). The goals: 2 s, 2 cm, 2°.
    assert!(merge_delay_s <= 1.0, "B merged {merge_delay_s:.2} s after its first keyframe");
    assert!(b_m <= 0.012 && b_deg <= 1.0, "B in A's frame: {:.2} cm, {b_deg:.2}°", 100.0 * b_m);
    assert!(mirror.merged.is_none() && synthetic.merged.is_none(), "a look-alike merged");
    assert!(mirror.pairings + synthetic.pairings >= 50, "{} look-alike pairings", mirror.pairings + synthetic.pairings);
    // Measured: 36 loops, worst 3.0 mm from the exact relative pose.
    assert!(loops >= 10 && worst_loop_m < 0.01, "{loops} loops, worst {worst_loop_m} m");
}
