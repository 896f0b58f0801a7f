//! One frame for a fleet (issue 20): two real clients stream the two public clips
//! of the same room into one server, robot A `rgbd_dataset_freiburg1_rpy` and
//! robot B `rgbd_dataset_freiburg1_rpy_b`, in fleet `lab`. A anchors the fleet's
//! frame; B is merged into it by place recognition, its poses are served in the
//! fleet frame, they score against the ground truth with A's alignment alone,
//! and the merge survives a restart.
#![allow(clippy::disallowed_methods)] // a test's client threads need no names

use std::time::{Duration, Instant};

use stillmap_dataset::eval::align::align_orientations;
use stillmap_dataset::eval::associate::associate;
use stillmap_dataset::eval::metrics::{Relation, Stats, ape};
use stillmap_dataset::trajectory::{parse_tum, read_tum};
use stillmap_e2e::{Server, decode_png, http_get, run_client, tempfile_path, tum_dir};
use stillmap_proto::pb::{self, query_client::QueryClient};

/// Polls `/api/v1/fleets/{fleet}` until `done` holds (or the deadline passes).
async fn wait_for_fleet(server: &Server, fleet: &str, timeout: Duration, done: impl Fn(&serde_json::Value) -> bool) -> serde_json::Value {
    let deadline = Instant::now() + timeout;
    loop {
        let (status, v) = server.get_json(&format!("/api/v1/fleets/{fleet}")).await;
        if status == 200 && done(&v) {
            return v;
        }
        assert!(Instant::now() < deadline, "fleet {fleet} never got there: {v}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// The fleet `lab` once place recognition has no backlog and the fleet has not
/// changed for three seconds (the clients are done; the map lanes hand over their
/// last keyframes within milliseconds; the pose graph is solved at most every 2 s
/// after new edges, `fleet.graph_interval_s`) and its last solve covered every
/// indexed keyframe.
async fn settled(server: &Server) -> serde_json::Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    let (mut last, mut unchanged) = (serde_json::Value::Null, 0);
    loop {
        let (_, all) = server.get_json("/api/v1/fleets").await;
        let (_, fleet) = server.get_json("/api/v1/fleets/lab").await;
        // The pose graph is solved on a timer (`fleet.graph_interval_s`), and a solve
        // takes seconds in a debug build on a loaded machine: settled also means no
        // solve is due or running, and the last one covered every indexed keyframe.
        let solved_all = fleet["pose_graph_pending"] == false && fleet["last_correction"]["keyframes"] == fleet["indexed_keyframes"];
        unchanged = if all["place_recognition_backlog"] == 0 && fleet == last && solved_all { unchanged + 1 } else { 0 };
        if unchanged == 3 {
            return fleet;
        }
        assert!(Instant::now() < deadline, "fleet lab never settled: {all}");
        last = fleet;
        tokio::time::sleep(Duration::from_millis(1000)).await;
    }
}

/// The vertices of one of the server's binary PLY files (x, y, z float; rgb; class; confidence).
fn ply_points(ply: &[u8]) -> Vec<[f64; 3]> {
    let end = ply.windows(11).position(|w| w == b"end_header\n").expect("PLY header") + 11;
    ply[end..]
        .chunks_exact(21)
        .map(|v| {
            let f = |o: usize| f64::from(f32::from_le_bytes([v[o], v[o + 1], v[o + 2], v[o + 3]]));
            [f(0), f(4), f(8)]
        })
        .collect()
}

/// (A's desk thickness, the fleet map's on the same cells), metres; see the test.
fn desk_thickness(a: &[[f64; 3]], fleet: &[[f64; 3]]) -> (f64, f64) {
    let mut layers = std::collections::HashMap::<i64, usize>::new();
    for p in a {
        *layers.entry((p[2] / 0.02).round() as i64).or_default() += 1;
    }
    let z0 = layers.iter().max_by_key(|(_, n)| **n).map(|(z, _)| *z as f64 * 0.02).expect("points");
    let fit = |points: &[[f64; 3]]| {
        let (mut m, mut b) = (nalgebra::Matrix3::<f64>::zeros(), nalgebra::Vector3::<f64>::zeros());
        for p in points {
            let v = nalgebra::Vector3::new(p[0], p[1], 1.0);
            m += v * v.transpose();
            b += v * p[2];
        }
        m.lu().solve(&b).expect("a plane")
    };
    let above = |plane: &nalgebra::Vector3<f64>, p: &[f64; 3]| p[2] - (plane.x * p[0] + plane.y * p[1] + plane.z);
    let mut desk: Vec<[f64; 3]> = a.iter().filter(|p| (p[2] - z0).abs() < 0.08).copied().collect();
    let mut plane = fit(&desk);
    for _ in 0..3 {
        desk.retain(|p| above(&plane, p).abs() < 0.05);
        plane = fit(&desk);
    }
    let cell = |p: &[f64; 3]| ((p[0] / 0.1).floor() as i64, (p[1] / 0.1).floor() as i64);
    let cells: std::collections::HashSet<_> = desk.iter().map(cell).collect();
    let rms = |points: &[[f64; 3]]| {
        let r: Vec<f64> = points.iter().filter(|p| cells.contains(&cell(p))).map(|p| above(&plane, p)).filter(|r| r.abs() < 0.05).collect();
        (r.iter().map(|x| x * x).sum::<f64>() / r.len().max(1) as f64).sqrt()
    };
    (rms(a), rms(fleet))
}

fn member<'a>(fleet: &'a serde_json::Value, session: &str) -> &'a serde_json::Value {
    fleet["sessions"]
        .as_array()
        .and_then(|s| s.iter().find(|m| m["session_id"] == session))
        .unwrap_or_else(|| panic!("{session} not in {fleet}"))
}

/// Robot B joins a room robot A has mapped: the merge comes within 2 s of B's
/// keyframes (its capture clock, from its first keyframe, which already overlaps A's map).
#[tokio::test(flavor = "multi_thread")]
async fn a_robot_joining_a_mapped_room_merges_within_two_seconds() {
    let server = Server::start(&["--no-zenoh", "--no-perception", "--no-store"]);
    let a_dir = tum_dir();
    let b_dir = stillmap_dataset::shared::fr1_rpy_b();
    let grpc = server.grpc_url();
    let (a, _) = run_client(&[
        "--source",
        &format!("tum:{}", a_dir.display()),
        "--server",
        &grpc,
        "--rate",
        "max",
        "--robot-id",
        "alpha",
        "--fleet",
        "lab",
    ]);
    assert!(a.status.success(), "{}", String::from_utf8_lossy(&a.stderr));
    // A's keyframes all indexed.
    let deadline = Instant::now() + Duration::from_secs(60);
    while server.get_json("/api/v1/fleets").await.1["place_recognition_backlog"] != 0 {
        assert!(Instant::now() < deadline, "place recognition never caught up");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let (b, summary) = run_client(&[
        "--source",
        &format!("tum:{}", b_dir.display()),
        "--server",
        &grpc,
        "--rate",
        "max",
        "--max-frames",
        "90",
        "--robot-id",
        "beta",
        "--fleet",
        "lab",
    ]);
    assert!(b.status.success(), "{}", String::from_utf8_lossy(&b.stderr));
    let b_id = summary.expect("beta summary")["session_id"].as_str().expect("id").to_string();
    let fleet = wait_for_fleet(&server, "lab", Duration::from_secs(60), |f| {
        f["merged"] == 2 || f["sessions"].as_array().is_some_and(|s| s.iter().all(|m| m["merged"] == true))
    })
    .await;
    let merge = &member(&fleet, &b_id)["fleet_from_session"];
    let merged_after_s = merge["merged_after_s"].as_f64().expect("merged_after_s");
    eprintln!("B merged {merged_after_s:.2} s into its keyframes: {merge}");
    // Measured (2026-12-03): see docs/fleet.md. The goal: 2 s.
    assert!(merged_after_s <= 2.0, "B merged {merged_after_s:.2} s into its keyframes");
}

async fn get_text(server: &Server, path: &str) -> (u16, String) {
    let r = reqwest::get(format!("http://{}{path}", server.http)).await.expect("HTTP GET");
    (r.status().as_u16(), r.text().await.expect("body"))
}

#[tokio::test(flavor = "multi_thread")]
async fn robot_b_joins_robot_as_frame_and_the_merge_survives_a_restart() {
    let store = tempfile_path("fleet.redb");
    let store_arg = store.to_str().expect("utf-8 path").to_string();
    let mut server = Server::start(&["--no-zenoh", "--no-perception", "--store", &store_arg]);
    let a_dir = tum_dir();
    let b_dir = stillmap_dataset::shared::fr1_rpy_b();
    let stream = |dir: &std::path::Path, robot: &str| {
        let (src, grpc, robot) = (format!("tum:{}", dir.display()), server.grpc_url(), robot.to_string());
        std::thread::spawn(move || {
            run_client(&["--source", &src, "--server", &grpc, "--rate", "max", "--robot-id", &robot, "--fleet", "lab"])
        })
    };
    // A first (its session anchors the fleet), then B while A still streams.
    let a = stream(&a_dir, "alpha");
    wait_for_fleet(&server, "lab", Duration::from_secs(60), |f| f["anchor_session_id"].is_string()).await;
    // A fleet subscriber sees both robots' poses once each is merged.
    let mut subscriber = QueryClient::connect(server.grpc_url()).await.expect("connect");
    let mut fleet_poses = subscriber.subscribe_fleet_poses(pb::FleetRef { fleet: "lab".into() }).await.expect("subscribe").into_inner();
    let watcher = tokio::spawn(async move {
        let mut seen = std::collections::BTreeSet::new();
        while seen.len() < 2 {
            match fleet_poses.message().await {
                Ok(Some(p)) => {
                    seen.insert(p.robot_id);
                }
                _ => break,
            }
        }
        seen
    });
    let b = stream(&b_dir, "beta");
    let (a, b) = (a.join().expect("alpha"), b.join().expect("beta"));
    assert!(
        a.0.status.success() && b.0.status.success(),
        "clients failed: {} {}",
        String::from_utf8_lossy(&a.0.stderr),
        String::from_utf8_lossy(&b.0.stderr)
    );
    let a_id = a.1.expect("alpha summary")["session_id"].as_str().expect("id").to_string();
    let b_id = b.1.expect("beta summary")["session_id"].as_str().expect("id").to_string();

    wait_for_fleet(&server, "lab", Duration::from_secs(60), |f| {
        f["sessions"].as_array().is_some_and(|s| s.len() == 2 && s.iter().all(|m| m["merged"] == true))
    })
    .await;
    // Later keyframes refine the merge: wait until they are all looked up.
    let fleet = settled(&server).await;
    let seen = tokio::time::timeout(Duration::from_secs(30), watcher).await.expect("fleet poses in time").expect("watcher");
    assert_eq!(seen.into_iter().collect::<Vec<_>>(), ["alpha", "beta"], "SubscribeFleetPoses");
    assert_eq!(fleet["anchor_session_id"], a_id.as_str());
    let merge = member(&fleet, &b_id)["fleet_from_session"].clone();
    assert_eq!(merge["anchor"], false);
    assert!(merge["support"].as_u64().is_some_and(|n| n >= 3), "{merge}");
    // How far into B's own keyframes (its capture clock) the first merge came: here
    // late, because B's first views are A's last ones, which A had not streamed yet
    // (the next test measures a robot joining a room already mapped).
    eprintln!("B merged {:.2} s into its keyframes", merge["merged_after_s"].as_f64().unwrap_or(f64::NAN));
    // The pose graph: both robots' keyframes, solved with the verified matches
    // between them (and their own loops) as edges.
    let solve = fleet["last_correction"].clone();
    eprintln!("last correction: {solve}; fleet map {}", fleet["map"]);
    assert!(solve["inter_session_edges"].as_u64().is_some_and(|n| n >= 3), "{solve}");
    assert!(solve["keyframes"].as_u64().is_some_and(|n| n >= 40), "{solve}");
    assert!(solve["max_translation_m"].as_f64().is_some_and(|m| m < 0.1), "no keyframe moves by 10 cm in one room: {solve}");
    assert!(member(&fleet, &b_id)["latest_correction"]["rotation_xyzw"].is_array(), "{fleet}");
    let (_, all) = server.get_json("/api/v1/fleets").await;
    assert_eq!(all["fleets"][0]["fleet"], "lab");
    assert_eq!(all["fleets"][0]["merged"], 2);
    let (_, session) = server.get_json(&format!("/api/v1/sessions/{b_id}")).await;
    assert_eq!(session["fleet"], "lab");

    // B in the fleet frame, scored with A's alignment to the ground truth.
    let gt = read_tum(&a_dir.join("groundtruth.txt")).expect("ground truth");
    let trajectory = |text: &str| parse_tum(text, std::path::Path::new("served")).expect("TUM trajectory");
    // A's alignment in the fleet frame: A anchors it, and the pose graph corrects A's poses too.
    let (status, a_text) = get_text(&server, &format!("/api/v1/sessions/{a_id}/trajectory?format=tum&frame=fleet")).await;
    assert_eq!(status, 200);
    let (status, b_text) = get_text(&server, &format!("/api/v1/sessions/{b_id}/trajectory?format=tum&frame=fleet")).await;
    assert_eq!(status, 200);
    assert!(b_text.starts_with("# timestamp tx ty tz qx qy qz qw (fleet = "), "{}", &b_text[..80.min(b_text.len())]);
    // (reference, estimate) paired by time (evo's association, 20 ms), and an RMS error.
    let paired = |text: &str| {
        let pairs = associate(&gt, &trajectory(text), 0.02, 0.0).expect("associated");
        (pairs.reference.iter().map(|p| p.1).collect::<Vec<_>>(), pairs.estimate.iter().map(|p| p.1).collect::<Vec<_>>())
    };
    let rmse = |reference: &[_], estimate: &[_], relation| Stats::of(&ape(reference, estimate, relation)).map_or(f64::NAN, |s| s.rmse);
    let (a_reference, a_estimate) = paired(&a_text);
    let gt_from_a = align_orientations(&a_reference, &a_estimate).expect("A aligned");
    let a_aligned: Vec<_> = a_estimate.iter().map(|p| gt_from_a * p).collect();
    let a_m = rmse(&a_reference, &a_aligned, Relation::Translation);
    let (reference, b_estimate) = paired(&b_text);
    let estimate: Vec<_> = b_estimate.iter().map(|p| gt_from_a * p).collect();
    let (b_m, b_deg) = (rmse(&reference, &estimate, Relation::Translation), rmse(&reference, &estimate, Relation::RotationDeg));
    // The same without the pose graph's corrections (the merge alone), for the record.
    let (_, a_world) = get_text(&server, &format!("/api/v1/sessions/{a_id}/trajectory?format=tum")).await;
    let (_, b_world) = get_text(&server, &format!("/api/v1/sessions/{b_id}/trajectory?format=tum")).await;
    let (a_reference_w, a_estimate_w) = paired(&a_world);
    let gt_from_a_w = align_orientations(&a_reference_w, &a_estimate_w).expect("A aligned");
    let value = |v: &serde_json::Value| v.as_f64().expect("number");
    let (t, q) = (&merge["translation"], &merge["rotation_xyzw"]);
    let fleet_from_b = nalgebra::Isometry3::from_parts(
        nalgebra::Translation3::new(value(&t[0]), value(&t[1]), value(&t[2])),
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(value(&q[3]), value(&q[0]), value(&q[1]), value(&q[2]))),
    );
    let (reference_w, b_estimate_w) = paired(&b_world);
    let merged_only: Vec<_> = b_estimate_w.iter().map(|p| gt_from_a_w * fleet_from_b * p).collect();
    eprintln!(
        "A: {:.2} cm; B in the fleet frame with A's alignment: {:.2} cm, {b_deg:.2}° over {} poses \
         (the merge alone: {:.2} cm, {:.2}°); merge {merge}",
        100.0 * a_m,
        100.0 * b_m,
        reference.len(),
        100.0 * rmse(&reference_w, &merged_only, Relation::Translation),
        rmse(&reference_w, &merged_only, Relation::RotationDeg),
    );
    // Measured (2026-12-05, 13 runs, with the pose graph's corrections): 1.13–1.31 cm
    // and 0.63–0.71° (the merge alone 0.99–1.70 cm, 0.60–0.90°), with A itself at
    // 1.08 cm (B inherits A's error where they overlap). The goal is 2 cm and 2°.
    assert!(b_m < 0.02 && b_deg < 1.0, "B in the fleet frame: {:.2} cm, {b_deg:.2}°", 100.0 * b_m);

    // One cloud for the fleet: both maps in the anchor's map frame, fused where they overlap.
    let vertices = |ply: &[u8]| {
        let header = String::from_utf8_lossy(&ply[..ply.len().min(4096)]).into_owned();
        header
            .lines()
            .find_map(|l| l.strip_prefix("element vertex "))
            .and_then(|n| n.trim().parse::<usize>().ok())
            .expect("PLY vertex count")
    };
    let http = server.http.clone();
    let ply = |path: String| {
        let http = http.clone();
        async move { reqwest::get(format!("http://{http}{path}")).await.expect("GET").bytes().await.expect("body") }
    };
    let (fleet_ply, a_ply, b_ply) = (
        ply("/api/v1/fleets/lab/cloud.ply".into()).await,
        ply(format!("/api/v1/maps/{a_id}/cloud.ply")).await,
        ply(format!("/api/v1/maps/{b_id}/cloud.ply")).await,
    );
    let (n_fleet, n_a, n_b) = (vertices(&fleet_ply), vertices(&a_ply), vertices(&b_ply));
    // One map fused from both robots' keyframes in the fleet frame (each at its
    // corrected pose, fused again as merges, bundle adjustment and the pose graph moved it).
    let header = String::from_utf8_lossy(&fleet_ply[..fleet_ply.len().min(4096)]).into_owned();
    assert!(header.contains("fused from their keyframes in the fleet frame"), "{header}");
    let map = &fleet["map"];
    assert_eq!(map["fused"], map["keyframes"], "{map}");
    assert_eq!(map["keyframes"], solve["keyframes"], "every keyframe of both robots: {map} {solve}");
    eprintln!("fleet cloud {n_fleet} voxels; A {n_a}, B {n_b}");
    // The desk: the plane through A's most populated 2 cm height layer, refit on its
    // inliers. The fleet map's thickness there (RMS distance of voxel centres within
    // 5 cm of the plane, over the 10 cm cells A's desk covers) against A's own.
    let (a_points, fleet_points) = (ply_points(&a_ply), ply_points(&fleet_ply));
    let (a_thick, fleet_thick) = desk_thickness(&a_points, &fleet_points);
    eprintln!("desk thickness: A {:.2} cm, fleet {:.2} cm", 100.0 * a_thick, 100.0 * fleet_thick);
    assert!(fleet_thick <= 1.1 * a_thick, "the fleet map's desk is {:.2} cm thick, A's {:.2} cm", 100.0 * fleet_thick, 100.0 * a_thick);
    assert!(n_fleet > n_a.max(n_b) && n_fleet < n_a + n_b, "fleet {n_fleet}, A {n_a}, B {n_b}: the same room must overlap");
    assert_eq!(server.get_json("/api/v1/fleets/nobody/cloud.ply").await.0, 404);
    // The fleet map's occupancy grid (ROS map_server) and static objects.
    let (status, yaml) = get_text(&server, "/api/v1/fleets/lab/occupancy.yaml").await;
    assert!(status == 200 && yaml.contains("image: occupancy.pgm"), "{status} {yaml}");
    let pgm = ply("/api/v1/fleets/lab/occupancy.pgm".into()).await;
    assert!(pgm.starts_with(b"P5"), "a PGM");
    // (Perception is off here, so no surface has a class and there are no objects:
    // the answer's shape only.)
    let (status, objects) = server.get_json("/api/v1/fleets/lab/objects").await;
    let (_, a_objects) = server.get_json(&format!("/api/v1/maps/{a_id}/objects")).await;
    assert_eq!(status, 200);
    assert!(objects["frame"].as_str().is_some_and(|f| f.starts_with("the fleet's map frame")), "{objects}");
    assert_eq!(objects["objects"].as_array().map(Vec::len), a_objects["objects"].as_array().map(Vec::len));
    let (status, _) = server.get_json("/api/v1/fleets/lab/occupancy.yaml?resolution=0.001").await;
    assert_eq!(status, 400, "a resolution finer than the voxels");

    // The fleet map's tiles and legend, in A's map frame: where A's own tile draws,
    // the fleet's tile at the same address draws too (B adds to A's room).
    let asked = Instant::now();
    let (status, legend) = server.get_json("/api/v1/fleets/lab/legend").await;
    assert_eq!(status, 200, "{legend}");
    let built = asked.elapsed();
    let asked = Instant::now();
    server.get_json("/api/v1/fleets/lab/legend").await;
    eprintln!(
        "fleet legend: {:.0} ms building the fleet map's top-down view, {:.1} ms from the cache",
        built.as_secs_f64() * 1e3,
        asked.elapsed().as_secs_f64() * 1e3
    );
    assert!(legend["classes"].as_array().is_some_and(|c| c.iter().any(|e| e["name"] == "unlabelled")), "{legend}");
    let bounds: Vec<f64> = legend["bounds_xy"].as_array().expect("bounds").iter().filter_map(|v| v.as_f64()).collect();
    let max_zoom = fleet["tiles"]["max_zoom"].as_u64().expect("max zoom");
    // The fleet's tiles have the anchor's scale.
    let (_, a_info) = server.get_json(&format!("/api/v1/maps/{a_id}")).await;
    let span = 256.0 * a_info["tiles"]["zooms"][max_zoom as usize]["metres_per_pixel"].as_f64().expect("scale");
    let (tx, ty) = (((bounds[0] + bounds[2]) / 2.0 / span).floor() as i64, (-(bounds[1] + bounds[3]) / 2.0 / span).floor() as i64);
    let tile_path = format!("/api/v1/fleets/lab/tiles/{max_zoom}/{tx}/{ty}.png");
    assert_eq!(fleet["tiles"]["url"], "/api/v1/fleets/lab/tiles/{z}/{x}/{y}.png");
    let r = http_get(&server, &tile_path, None).await;
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "image/png");
    let etag = r.headers()["etag"].to_str().expect("etag").to_string();
    let (w, h, fleet_tile) = decode_png(&r.bytes().await.expect("body"));
    assert_eq!((w, h), (256, 256));
    let r = http_get(&server, &format!("/api/v1/maps/{a_id}/tiles/{max_zoom}/{tx}/{ty}.png"), None).await;
    let (_, _, a_tile) = decode_png(&r.bytes().await.expect("body"));
    let drawn = |rgba: &[u8]| rgba.chunks_exact(4).map(|p| p[3] == 255).collect::<Vec<_>>();
    let (fleet_drawn, a_drawn) = (drawn(&fleet_tile), drawn(&a_tile));
    let a_count = a_drawn.iter().filter(|&&d| d).count();
    let both = fleet_drawn.iter().zip(&a_drawn).filter(|(f, a)| **f && **a).count();
    // A's keyframes sit in the fleet map at their corrected fleet poses (the pose
    // graph moves them by a fraction of a voxel), so at the finest zoom an edge of
    // A's room may be drawn one pixel over: a pixel of A's counts as covered when the
    // fleet draws it or one of its 8 neighbours. (Exactly the same pixel: 94.8–96.7 %
    // over runs, varying with when the graph was solved; within one pixel 99.87–99.90 %.)
    let near = (0..256 * 256)
        .filter(|&i| a_drawn[i])
        .filter(|&i| {
            let (x, y) = ((i % 256) as i64, (i / 256) as i64);
            (-1..=1).any(|dy| {
                (-1..=1).any(|dx| {
                    (0..256).contains(&(x + dx)) && (0..256).contains(&(y + dy)) && fleet_drawn[((y + dy) * 256 + x + dx) as usize]
                })
            })
        })
        .count();
    eprintln!(
        "tile {tx},{ty}: A draws {a_count} pixels, the fleet {}: {both} of A's exactly, {near} within one pixel",
        fleet_drawn.iter().filter(|&&d| d).count()
    );
    assert!(
        a_count > 1000 && near as f64 >= 0.99 * a_count as f64,
        "A draws {a_count} pixels, the fleet {near} of them (within one pixel)"
    );
    assert_eq!(http_get(&server, &tile_path, Some(&etag)).await.status(), 304, "an unchanged fleet map revalidates");
    assert_eq!(http_get(&server, "/api/v1/fleets/lab/tiles/9/0/0.png", None).await.status(), 400);
    assert_eq!(http_get(&server, "/api/v1/fleets/nobody/tiles/0/0/0.png", None).await.status(), 404);
    assert_eq!(server.get_json("/api/v1/fleets/nobody/legend").await.0, 404);

    // gRPC: every merged robot's newest pose in the fleet frame, the same as HTTP's.
    let mut q = QueryClient::connect(server.grpc_url()).await.expect("connect");
    let poses = q.get_fleet_poses(pb::FleetRef { fleet: "lab".into() }).await.expect("fleet poses").into_inner();
    assert!(poses.unmerged_session_ids.is_empty());
    let mut robots: Vec<&str> = poses.poses.iter().map(|p| p.robot_id.as_str()).collect();
    robots.sort_unstable();
    assert_eq!(robots, ["alpha", "beta"]);
    let b_grpc = poses
        .poses
        .iter()
        .find(|p| p.session_id == b_id)
        .and_then(|p| p.pose.as_ref())
        .and_then(|p| p.world_from_camera)
        .expect("B's pose");
    let (_, b_http) = server.get_json(&format!("/api/v1/sessions/{b_id}/pose?frame=fleet")).await;
    let t = b_grpc.translation.expect("translation");
    let http_t: Vec<f64> = b_http["pose"]["translation"].as_array().expect("translation").iter().filter_map(|v| v.as_f64()).collect();
    // The same pose; JSON parsing (serde_json without float_roundtrip) may be one ulp off.
    assert_eq!(http_t.len(), 3);
    assert!(http_t.iter().zip([t.x, t.y, t.z]).all(|(h, g)| (h - g).abs() <= 1e-12 * g.abs().max(1.0)), "HTTP {http_t:?}, gRPC {t:?}");
    let status = q.get_fleet_poses(pb::FleetRef { fleet: "nobody".into() }).await.expect_err("unknown fleet");
    assert_eq!(status.code(), tonic::Code::NotFound);
    // A name no robot could give is refused as such, before any lookup or forwarding.
    let status = q.get_fleet_poses(pb::FleetRef { fleet: "x".repeat(1 << 20) }).await.expect_err("not a fleet name");
    assert_eq!((status.code(), status.message()), (tonic::Code::InvalidArgument, "fleet: fleet must be 1-64 characters, got 1048576"));

    // Frames are named; bad ones are refused.
    let (status, body) = server.get_json(&format!("/api/v1/sessions/{b_id}/pose?frame=fleet")).await;
    assert_eq!(status, 200);
    assert!(body["frame"].as_str().is_some_and(|f| f.starts_with("fleet")), "{body}");
    let (status, body) = server.get_json(&format!("/api/v1/sessions/{b_id}/pose?frame=map")).await;
    assert_eq!((status, body["error"].as_str()), (400, Some("unknown frame \"map\"; use world or fleet")));
    let (status, _) = server.get_json("/api/v1/fleets/nobody").await;
    assert_eq!(status, 404);

    // A restart brings the merge back from the store, and the fused fleet map.
    server.terminate();
    let server = Server::start(&["--no-zenoh", "--no-perception", "--store", &store_arg]);
    let (_, after) = server.get_json("/api/v1/fleets/lab").await;
    assert_eq!(member(&after, &b_id)["fleet_from_session"], merge, "{after}");
    assert_eq!(after["last_correction"], solve, "the pose graph's corrections come back");
    let (_, again) = get_text(&server, &format!("/api/v1/sessions/{b_id}/trajectory?format=tum&frame=fleet")).await;
    assert_eq!(again, b_text);
    // The fleet was settled before the restart (its map unchanged for three seconds),
    // so the fused map comes back voxel for voxel, and is what the fleet serves.
    assert_eq!((&after["map"]["fused"], &after["map"]["keyframes"]), (&map["fused"], &map["keyframes"]), "{after}");
    let fleet_ply_again =
        reqwest::get(format!("http://{}/api/v1/fleets/lab/cloud.ply", server.http)).await.expect("GET").bytes().await.expect("body");
    let header = String::from_utf8_lossy(&fleet_ply_again[..fleet_ply_again.len().min(4096)]).into_owned();
    assert!(header.contains("fused from their keyframes in the fleet frame"), "after the restart: {header}");
    let sorted = |ply: &[u8]| {
        let mut points = ply_points(ply);
        points.sort_by(|a, b| a.partial_cmp(b).expect("finite"));
        points
    };
    assert!(sorted(&fleet_ply_again) == sorted(&fleet_ply), "the fleet map's {n_fleet} voxels come back as they were");
    drop(server);
    let _ = std::fs::remove_file(&store);
}

/// A map built on one server and imported into another anchors its fleet there, and
/// a robot streaming the same room merges into it: robots find themselves in a map
/// loaded from a file. Robot B maps `rgbd_dataset_freiburg1_rpy_b` on the first
/// server; its map file is imported into the second; robot A streams
/// `rgbd_dataset_freiburg1_rpy` there and is merged into B's frame, where its poses
/// score against the ground truth with B's alignment.
#[tokio::test(flavor = "multi_thread")]
async fn a_robot_merges_into_an_imported_map() {
    let a_dir = tum_dir();
    let b_dir = stillmap_dataset::shared::fr1_rpy_b();
    let (first_store, second_store) = (tempfile_path("mapped.redb"), tempfile_path("imported.redb"));
    let first = Server::start(&["--no-zenoh", "--no-perception", "--store", first_store.to_str().expect("utf-8")]);
    let stream = |server: &Server, dir: &std::path::Path, robot: &str| {
        let (out, summary) = run_client(&[
            "--source",
            &format!("tum:{}", dir.display()),
            "--server",
            &server.grpc_url(),
            "--rate",
            "max",
            "--robot-id",
            robot,
            "--fleet",
            "lab",
        ]);
        assert!(out.status.success(), "{robot}: {}", String::from_utf8_lossy(&out.stderr));
        summary.expect("summary")["session_id"].as_str().expect("session id").to_string()
    };
    let b_id = stream(&first, &b_dir, "beta");
    settled(&first).await;
    let file = reqwest::get(format!("http://{}/api/v1/maps/{b_id}/export", first.http)).await.expect("export");
    assert_eq!(file.status(), 200);
    let file = file.bytes().await.expect("map file");
    drop(first);

    let second = Server::start(&["--no-zenoh", "--no-perception", "--store", second_store.to_str().expect("utf-8")]);
    let imported =
        reqwest::Client::new().post(format!("http://{}/api/v1/maps/import", second.http)).body(file).send().await.expect("import");
    assert_eq!(imported.status(), 201);
    let fleet = wait_for_fleet(&second, "lab", Duration::from_secs(10), |f| f["anchor_session_id"] == b_id.as_str()).await;
    assert_eq!(fleet["sessions"].as_array().map(Vec::len), Some(1), "{fleet}");

    let a_id = stream(&second, &a_dir, "alpha");
    wait_for_fleet(&second, "lab", Duration::from_secs(60), |f| member(f, &a_id)["merged"] == true).await;
    let fleet = settled(&second).await;
    assert_eq!(fleet["anchor_session_id"], b_id.as_str(), "the imported map stays the anchor");

    // A in the fleet frame (the imported map's), with B's alignment to the ground truth.
    let gt = read_tum(&a_dir.join("groundtruth.txt")).expect("ground truth");
    let trajectory = |text: &str| parse_tum(text, std::path::Path::new("served")).expect("TUM trajectory");
    let paired = |text: &str| {
        let pairs = associate(&gt, &trajectory(text), 0.02, 0.0).expect("associated");
        (pairs.reference.iter().map(|p| p.1).collect::<Vec<_>>(), pairs.estimate.iter().map(|p| p.1).collect::<Vec<_>>())
    };
    let rmse = |reference: &[_], estimate: &[_], relation| Stats::of(&ape(reference, estimate, relation)).map_or(f64::NAN, |s| s.rmse);
    let (status, b_text) = get_text(&second, &format!("/api/v1/sessions/{b_id}/trajectory?format=tum")).await;
    assert_eq!(status, 200);
    let (status, a_text) = get_text(&second, &format!("/api/v1/sessions/{a_id}/trajectory?format=tum&frame=fleet")).await;
    assert_eq!(status, 200);
    let (b_reference, b_estimate) = paired(&b_text);
    let gt_from_b = align_orientations(&b_reference, &b_estimate).expect("B aligned");
    let (reference, a_estimate) = paired(&a_text);
    let estimate: Vec<_> = a_estimate.iter().map(|p| gt_from_b * p).collect();
    let (a_m, a_deg) = (rmse(&reference, &estimate, Relation::Translation), rmse(&reference, &estimate, Relation::RotationDeg));
    let merge = &member(&fleet, &a_id)["fleet_from_session"];
    eprintln!(
        "A in the imported map's frame with B's alignment: {:.2} cm, {a_deg:.2}° over {} poses; merge {merge}",
        100.0 * a_m,
        reference.len()
    );
    // The bound of the live merge test (B into A's frame: 1.21–1.70 cm, 0.67–0.90°).
    assert!(a_m < 0.025 && a_deg < 1.5, "A in the imported map's frame: {:.2} cm, {a_deg:.2}°", 100.0 * a_m);
}
