//! Loop closure with exact ground truth (issue 20): the synthetic room, rendered
//! along its swaying path (which comes back to the same views), is tracked; a
//! drift is injected into the tracked keyframe poses (each keyframe step turned
//! 0.05° and pushed 1 mm further, or 0.3° and 4 mm); place recognition and
//! verification find the loops, and the pose graph (odometry edges from the
//! drifted poses, loop edges from verification, the server's default σ and
//! re-weighting) takes the drift out: the keyframes' error after closure is
//! within 1.5× of the drift-free run's.
//!
//! `cargo test --release -p stillmap-places --test loop_closure -- --nocapture --include-ignored`
//! also prints the pose-graph solve times at 100 / 1,000 / 10,000 keyframes.

use std::time::Instant;

use nalgebra::{Isometry3, Vector3};
use stillmap_places::{Edge, EdgeKind, Place, PlaceIndex, PoseGraph, SolveConfig, VerifyConfig, Vocabulary, verify};
use stillmap_tracking::synthetic::{Scene, kinect_camera, render, sway_path};
use stillmap_tracking::{FrameInput, Tracker, TrackerConfig};

const FRAME_NS: u64 = 33_333_333;

/// RMS position error of keyframe poses against the exact ones.
fn rms(poses: &[Isometry3<f64>], truth: &[Isometry3<f64>]) -> f64 {
    (poses.iter().zip(truth).map(|(p, t)| (p.translation.vector - t.translation.vector).norm_squared()).sum::<f64>() / poses.len() as f64)
        .sqrt()
}

#[test]
fn loops_take_an_injected_drift_out() {
    let camera = kinect_camera();
    let scene = Scene::room(7);
    let path = sway_path(360);
    let mut tracker = Tracker::new(camera.clone(), TrackerConfig::default()).expect("tracker");
    for (k, p) in path.iter().enumerate() {
        let f = render(&scene, &camera, p);
        tracker.track(&FrameInput { timestamp_ns: k as u64 * FRAME_NS, rgb: &f.rgb, depth: &f.depth, dynamic_mask: None }).expect("track");
    }
    let keyframes: Vec<(usize, Isometry3<f64>, Place)> = tracker
        .map()
        .keyframes
        .values()
        .map(|kf| ((kf.timestamp_ns / FRAME_NS) as usize, kf.world_from_camera, Place::from_features(&camera, &kf.features)))
        .collect();
    let truth: Vec<Isometry3<f64>> = keyframes.iter().map(|k| path[k.0]).collect();
    let tracked: Vec<Isometry3<f64>> = keyframes.iter().map(|k| k.1).collect();

    // Loops: each keyframe against the keyframes at least 2 s older; the edge
    // j_from_k is the query (k) in the candidate's (j) frame.
    let vocabulary = Vocabulary::shipped();
    let mut index = PlaceIndex::new();
    let (mut loop_edges, mut query_ms, mut verify_ms) = (Vec::new(), 0.0, 0.0);
    for (k, (frame, _, place)) in keyframes.iter().enumerate() {
        let bow = vocabulary.transform(&place.descriptors);
        let started = Instant::now();
        let found = index.query(&bow, 3, 0.0, |&j: &usize| keyframes[j].0 + 60 <= *frame);
        query_ms += started.elapsed().as_secs_f64() * 1e3;
        let started = Instant::now();
        for (j, _) in found {
            if let Some(v) = verify(&camera, place, &keyframes[j].2, &VerifyConfig::default()) {
                loop_edges.push((j, k, v.query_from_candidate.inverse()));
            }
        }
        verify_ms += started.elapsed().as_secs_f64() * 1e3;
        index.insert(k, bow);
    }
    let loops = loop_edges.len();
    assert!(loops >= 10, "{loops} loops");
    let n = keyframes.len() as f64;
    let free = rms(&tracked, &truth);
    println!(
        "| drift per keyframe step | keyframes | loops | ATE drift-free | with the drift | after closure | query / verification per keyframe | solve |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    // Two drifts: every keyframe step turned about the vertical and made longer,
    // slowly (0.05°, 1 mm: within the odometry's σ per step) and fast (0.3°, 4 mm).
    for (drift_m, drift_deg) in [(0.001, 0.05f64), (0.004, 0.3)] {
        let drift = Isometry3::new(Vector3::new(drift_m, 0.0, 0.0), Vector3::new(0.0, drift_deg.to_radians(), 0.0));
        let mut drifted = vec![tracked[0]];
        for w in tracked.windows(2) {
            let step = w[0].inverse() * w[1];
            let last = *drifted.last().expect("a pose");
            drifted.push(last * step * drift);
        }
        // The server's defaults: fleet.odometry_sigma_m / _deg 0.002 / 0.1,
        // fleet.place_sigma_m / _deg 0.03 / 1.0, fleet.reweight_rounds 2.
        let mut graph = PoseGraph::default();
        for p in &drifted {
            graph.add_pose(*p);
        }
        for i in 1..drifted.len() {
            let step = drifted[i - 1].inverse() * drifted[i];
            let edge = Edge {
                from: i - 1,
                to: i,
                from_from_to: step,
                kind: EdgeKind::Odometry,
                sigma_rotation_rad: 0.1f64.to_radians(),
                sigma_translation_m: 0.002,
            };
            graph.add_edge(edge).expect("odometry");
        }
        for &(from, to, from_from_to) in &loop_edges {
            let edge =
                Edge { from, to, from_from_to, kind: EdgeKind::Loop, sigma_rotation_rad: 1f64.to_radians(), sigma_translation_m: 0.03 };
            graph.add_edge(edge).expect("loop");
        }
        let started = Instant::now();
        let closed = graph.optimize(&SolveConfig { reweight_rounds: 2, ..SolveConfig::default() }).expect("solved");
        let solve_ms = started.elapsed().as_secs_f64() * 1e3;
        let (with_drift, after) = (rms(&drifted, &truth), rms(&closed, &truth));
        println!(
            "| {drift_deg}°, {} mm | {} | {loops} | {:.2} cm | {:.2} cm | {:.2} cm | {:.2} / {:.1} ms | {solve_ms:.0} ms |",
            1e3 * drift_m,
            keyframes.len(),
            100.0 * free,
            100.0 * with_drift,
            100.0 * after,
            query_ms / n,
            verify_ms / n
        );
        assert!(with_drift > 5.0 * free, "the injected drift must matter: {with_drift} vs {free}");
        assert!(after <= 1.5 * free, "after closure {:.2} cm, drift-free {:.2} cm", 100.0 * after, 100.0 * free);
        // Without re-weighting, the σ as configured: the tight odometry holds the slow drift in.
        if drift_deg < 0.1 {
            let plain = rms(&graph.optimize(&SolveConfig::default()).expect("solved"), &truth);
            println!("(the slow drift without re-weighting: {:.2} cm)", 100.0 * plain);
            assert!(plain > 2.0 * after);
        }
    }
}

/// Pose-graph solve time on chains of n keyframes (1 cm, 1° steps with noise)
/// with a loop edge every 10 keyframes to one 50 keyframes back.
#[test]
#[ignore = "benchmark: prints pose-graph solve times (run in release)"]
fn pose_graph_cost() {
    println!("| keyframes | edges | solve | re-weighted twice (the server's default) |");
    println!("|---|---|---|---|");
    for n in [100usize, 1_000, 10_000] {
        let step = Isometry3::new(Vector3::new(0.01, 0.0, 0.0), Vector3::new(0.0, 1f64.to_radians(), 0.0));
        let truth: Vec<Isometry3<f64>> = (0..n)
            .scan(Isometry3::identity(), |p, _| {
                let out = *p;
                *p *= step;
                Some(out)
            })
            .collect();
        let mut graph = PoseGraph::default();
        let wobble = |i: usize| {
            Isometry3::new(Vector3::new(0.001 * ((i * 7) % 5) as f64, 0.0, 0.0), Vector3::new(0.0, 0.001 * ((i * 3) % 4) as f64, 0.0))
        };
        let mut p = truth[0];
        graph.add_pose(p);
        for i in 1..n {
            let measured = step * wobble(i);
            p *= measured;
            graph.add_pose(p);
            graph
                .add_edge(Edge {
                    from: i - 1,
                    to: i,
                    from_from_to: measured,
                    kind: EdgeKind::Odometry,
                    sigma_rotation_rad: 0.01,
                    sigma_translation_m: 0.01,
                })
                .expect("edge");
        }
        for i in (50..n).step_by(10) {
            graph
                .add_edge(Edge {
                    from: i - 50,
                    to: i,
                    from_from_to: truth[i - 50].inverse() * truth[i],
                    kind: EdgeKind::Loop,
                    sigma_rotation_rad: 0.002,
                    sigma_translation_m: 0.005,
                })
                .expect("loop");
        }
        let started = Instant::now();
        graph.optimize(&SolveConfig::default()).expect("solved");
        let once = started.elapsed().as_secs_f64() * 1e3;
        // The server's default: two rounds of re-weighting (three solves).
        let started = Instant::now();
        graph.optimize(&SolveConfig { reweight_rounds: 2, ..SolveConfig::default() }).expect("solved");
        println!("| {n} | {} | {once:.0} ms | {:.0} ms |", graph.edges.len(), started.elapsed().as_secs_f64() * 1e3);
    }
}
