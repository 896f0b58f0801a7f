//! The static semantic map through the real client and server on the real TUM
//! clip: tiles, legend, occupancy grid, PLY, objects over HTTP and gRPC, and the
//! errors for bad coordinates and unknown sessions.

use stillmap_e2e::{Server, decode_png, http_get as get, run_client, tum_dir};
use stillmap_proto::pb;
use stillmap_proto::pb::query_client::QueryClient;

#[tokio::test(flavor = "multi_thread")]
async fn the_streamed_clip_is_mapped_and_served() {
    let server = Server::start(&["--no-zenoh"]);
    let (out, summary) =
        run_client(&["--source", &format!("tum:{}", tum_dir().display()), "--server", &server.grpc_url(), "--rate", "max"]);
    assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
    let id = summary.expect("summary")["session_id"].as_str().expect("session id").to_string();

    let (status, info) = server.get_json(&format!("/api/v1/maps/{id}")).await;
    assert_eq!(status, 200, "{info}");
    let keyframes = info["keyframes"].as_u64().expect("keyframes");
    assert!(keyframes >= 20, "{info}");
    assert!(info["occupied_voxels"].as_u64().expect("voxels") > 20_000, "{info}");
    assert!(info["retracted_samples"].is_u64(), "{info}");
    // TUM's accelerometer gives the up direction.
    assert_eq!(info["up_source"], "accelerometer", "{info}");
    let bounds: Vec<f64> = info["bounds_xy"].as_array().expect("bounds").iter().map(|v| v.as_f64().expect("number")).collect();
    let max_zoom = info["tiles"]["max_zoom"].as_u64().expect("max zoom") as u32;
    let metres_per_px = info["tiles"]["zooms"][max_zoom as usize]["metres_per_pixel"].as_f64().expect("scale");
    let span = 256.0 * metres_per_px;
    let (tx, ty) = (((bounds[0] + bounds[2]) / 2.0 / span).floor() as i64, (-(bounds[1] + bounds[3]) / 2.0 / span).floor() as i64);

    // A tile over the middle of the map: a valid 256x256 PNG with something drawn.
    let tile_path = format!("/api/v1/maps/{id}/tiles/{max_zoom}/{tx}/{ty}.png");
    let r = get(&server, &tile_path, None).await;
    assert_eq!(r.status(), 200);
    assert_eq!(r.headers()["content-type"], "image/png");
    assert_eq!(r.headers()["cache-control"], "no-cache");
    let etag = r.headers()["etag"].to_str().expect("etag").to_string();
    let (w, h, rgba) = decode_png(&r.bytes().await.expect("body"));
    assert_eq!((w, h), (256, 256));
    let drawn = rgba.chunks_exact(4).filter(|p| p[3] == 255).count();
    assert!(drawn > 1000, "{drawn} pixels drawn");
    // Unchanged map: the ETag revalidates.
    let r = get(&server, &tile_path, Some(&etag)).await;
    assert_eq!(r.status(), 304);
    // Zoomed out, the same place is still drawn; 1.6 km away nothing is.
    let span0 = span * f64::from(1u32 << max_zoom);
    let (x0, y0) = (((bounds[0] + bounds[2]) / 2.0 / span0).floor() as i64, (-(bounds[1] + bounds[3]) / 2.0 / span0).floor() as i64);
    let r = get(&server, &format!("/api/v1/maps/{id}/tiles/0/{x0}/{y0}.png"), None).await;
    assert_eq!(r.status(), 200);
    let (_, _, coarse) = decode_png(&r.bytes().await.expect("body"));
    assert!(coarse.chunks_exact(4).any(|p| p[3] == 255), "zoom 0 draws the map");
    let r = get(&server, &format!("/api/v1/maps/{id}/tiles/0/{}/{}.png", x0 + 10, y0 - 10), None).await;
    let (_, _, far) = decode_png(&r.bytes().await.expect("body"));
    assert!(far.chunks_exact(4).all(|p| p[3] == 0), "a tile 1.6 km away is empty");

    // Legend: class names and colours, the segmenter's classes among them.
    let (status, legend) = server.get_json(&format!("/api/v1/maps/{id}/legend")).await;
    assert_eq!(status, 200);
    let names: Vec<&str> = legend["classes"].as_array().expect("classes").iter().map(|c| c["name"].as_str().expect("name")).collect();
    assert!(names.contains(&"unlabelled"), "{legend}");
    assert!(names.len() >= 3, "{legend}");
    assert!(legend["classes"][0]["color"].as_str().expect("colour").starts_with('#'));

    // Objects clustered from the voxels.
    let (status, objects) = server.get_json(&format!("/api/v1/maps/{id}/objects")).await;
    assert_eq!(status, 200);
    let objects = objects["objects"].as_array().expect("objects").clone();
    assert!(!objects.is_empty());
    for o in &objects {
        let (lo, hi, c) = (&o["bbox_min"], &o["bbox_max"], &o["centroid"]);
        for i in 0..3 {
            let (lo, hi, c) = (lo[i].as_f64().unwrap(), hi[i].as_f64().unwrap(), c[i].as_f64().unwrap());
            assert!(lo <= c && c <= hi, "{o}");
        }
        assert!(o["voxels"].as_u64().unwrap() >= 30);
    }

    // PLY: header and binary body agree; a bounding box query returns a subset.
    let r = get(&server, &format!("/api/v1/maps/{id}/cloud.ply"), None).await;
    assert_eq!(r.status(), 200);
    let ply = r.bytes().await.expect("body").to_vec();
    let vertices = |ply: &[u8]| -> usize {
        let end = ply.windows(11).position(|w| w == b"end_header\n").expect("end_header") + 11;
        let header = std::str::from_utf8(&ply[..end]).expect("ascii header");
        assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"), "{header}");
        for p in ["float x", "float y", "float z", "uchar red", "uchar green", "uchar blue", "ushort class", "float confidence"] {
            assert!(header.contains(&format!("property {p}\n")), "{header}");
        }
        let n: usize = header.lines().find_map(|l| l.strip_prefix("element vertex ")).expect("vertex count").parse().expect("number");
        assert_eq!(ply.len() - end, n * 21, "binary body is n × 21 bytes");
        n
    };
    let all = vertices(&ply);
    assert!(all > 20_000);
    let r = get(&server, &format!("/api/v1/maps/{id}/cloud.ply?bbox=-0.5,-0.5,-0.5,0.5,0.5,0.5"), None).await;
    assert_eq!(r.status(), 200);
    let some = vertices(&r.bytes().await.expect("body"));
    assert!(some < all);

    // Occupancy grid in the ROS map_server format.
    let pgm = get(&server, &format!("/api/v1/maps/{id}/occupancy.pgm"), None).await.bytes().await.expect("pgm").to_vec();
    assert!(pgm.starts_with(b"P5\n"));
    let text = String::from_utf8_lossy(&pgm[..64.min(pgm.len())]).to_string();
    let dims: Vec<usize> = text.lines().nth(2).expect("size line").split(' ').map(|v| v.parse().expect("size")).collect();
    let header_len = pgm.windows(4).position(|w| w == b"255\n").expect("maxval") + 4;
    assert_eq!(pgm.len() - header_len, dims[0] * dims[1]);
    assert!(pgm[header_len..].contains(&0), "some occupied cells");
    let yaml = server.get_text(&format!("/api/v1/maps/{id}/occupancy.yaml")).await;
    assert!(yaml.contains("image: occupancy.pgm\nresolution: 0.05\norigin: ["), "{yaml}");

    // gRPC equivalents.
    let mut q = QueryClient::connect(server.grpc_url()).await.expect("connect");
    let tile =
        q.get_map_tile(pb::MapTileRequest { session_id: id.clone(), zoom: max_zoom, x: tx, y: ty }).await.expect("tile").into_inner();
    assert_eq!(tile.etag, etag);
    assert_eq!(decode_png(&tile.png).2, rgba);
    let mut stream = q.get_map_cloud(pb::MapCloudRequest { session_id: id.clone(), bbox: None }).await.expect("cloud").into_inner();
    let (mut points, mut first) = (0, true);
    while let Some(chunk) = stream.message().await.expect("chunk") {
        assert_eq!(chunk.xyz.len(), 3 * chunk.class_id.len());
        assert_eq!(chunk.rgb.len(), 3 * chunk.class_id.len());
        if first {
            assert_eq!(chunk.class_names.len(), 80);
            first = false;
        }
        points += chunk.class_id.len();
    }
    assert_eq!(points, all);

    // Errors: JSON 400 for bad coordinates, 404 for unknown sessions; gRPC codes alike.
    for (path, code, message) in [
        (format!("/api/v1/maps/{id}/tiles/9/0/0.png"), 400, "zoom 9 is out of range 0..=5"),
        (format!("/api/v1/maps/{id}/tiles/x/0/0.png"), 400, "zoom \"x\" is not an integer 0..=5"),
        (format!("/api/v1/maps/{id}/tiles/3/0/0.jpg"), 400, "tile \"0.jpg\" must end in .png"),
        (format!("/api/v1/maps/{id}/tiles/3/99999999/0.png"), 400, "tile index (99999999, 0) is out of range ±1048576"),
        (format!("/api/v1/maps/{id}/cloud.ply?bbox=1,2,3"), 400, "bbox needs 6 finite numbers min_x,min_y,min_z,max_x,max_y,max_z; got 3"),
        (
            format!("/api/v1/maps/{id}/cloud.ply?bbox=0,0,0,inf,1,1"),
            400,
            "bbox needs 6 finite numbers min_x,min_y,min_z,max_x,max_y,max_z; got inf",
        ),
        (format!("/api/v1/maps/{id}/occupancy.pgm?min_height=1&max_height=0"), 400, "height band [1, 0] is empty"),
        (
            format!("/api/v1/maps/{id}/occupancy.pgm?resolution=fine"),
            400,
            "Failed to deserialize query string: resolution: invalid float literal",
        ),
        ("/api/v1/maps/nobody/tiles/0/0/0.png".to_string(), 404, "unknown session \"nobody\""),
        ("/api/v1/maps/nobody/cloud.ply".to_string(), 404, "unknown session \"nobody\""),
        ("/api/v1/maps/nobody".to_string(), 404, "unknown session \"nobody\""),
    ] {
        let (status, body) = server.get_json(&path).await;
        assert_eq!((status, body["error"].as_str()), (code, Some(message)), "{path}");
    }
    let err = q.get_map_tile(pb::MapTileRequest { session_id: id.clone(), zoom: 6, x: 0, y: 0 }).await.unwrap_err();
    assert_eq!((err.code(), err.message()), (tonic::Code::InvalidArgument, "zoom 6 is out of range 0..=5"));
    let err = q.get_map_cloud(pb::MapCloudRequest { session_id: "nobody".into(), bbox: None }).await.unwrap_err();
    assert_eq!((err.code(), err.message()), (tonic::Code::NotFound, "unknown session \"nobody\""));
}

/// Memory stays within `mapping.max_resident_blocks`: the farthest blocks go to the
/// store, come back when the camera needs them, and every query still sees them.
/// Perception off, so both runs see exactly the same frames and poses.
#[tokio::test(flavor = "multi_thread")]
async fn a_map_over_its_memory_budget_evicts_to_the_store_and_loses_nothing() {
    let config = stillmap_e2e::tempfile_path("budget.toml");
    std::fs::write(&config, "[mapping]\nmax_resident_blocks = 300\n").expect("write config");
    let mut vertices = Vec::new();
    for extra in [vec![], vec!["--config", config.to_str().expect("utf-8 path")]] {
        let mut args = vec!["--no-zenoh", "--no-perception"];
        args.extend(extra.iter().copied());
        let server = Server::start(&args);
        let (out, summary) =
            run_client(&["--source", &format!("tum:{}", tum_dir().display()), "--server", &server.grpc_url(), "--rate", "max"]);
        assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
        let summary = summary.expect("summary");
        assert_eq!(summary["frames_dropped"], 0);
        let id = summary["session_id"].as_str().expect("session id").to_string();
        // The robot hears its last result before the map lane has fused and
        // committed its last keyframes: wait until the map is at rest.
        let mut info = serde_json::Value::Null;
        stillmap_e2e::eventually(std::time::Duration::from_secs(60), "the map to be fused and committed", async || {
            let (_, before) = server.get_json(&format!("/api/v1/maps/{id}")).await;
            tokio::time::sleep(std::time::Duration::from_millis(500)).await;
            let (_, after) = server.get_json(&format!("/api/v1/maps/{id}")).await;
            let settled = before["version"] == after["version"] && after["committed_keyframes"] == after["keyframes"];
            info = after;
            settled
        })
        .await;
        let ply = get(&server, &format!("/api/v1/maps/{id}/cloud.ply"), None).await.bytes().await.expect("body");
        let header = String::from_utf8_lossy(&ply[..ply.windows(11).position(|w| w == b"end_header\n").expect("header")]).to_string();
        let n: usize = header.lines().find_map(|l| l.strip_prefix("element vertex ")).expect("count").parse().expect("number");
        eprintln!("{extra:?}: {} resident blocks, {} evicted, {n} points", info["blocks"], info["evicted_blocks"]);
        vertices.push((n, info));
    }
    let _ = std::fs::remove_file(&config);
    let (unbounded, bounded) = (&vertices[0], &vertices[1]);
    assert_eq!(unbounded.1["evicted_blocks"], 0);
    let resident = bounded.1["blocks"].as_u64().expect("blocks");
    let evicted = bounded.1["evicted_blocks"].as_u64().expect("evicted");
    assert!(resident <= 300, "{resident} blocks resident over a budget of 300");
    assert!(evicted > 0);
    assert_eq!(resident + evicted, unbounded.1["blocks"].as_u64().expect("blocks"), "every block is resident or stored");
    assert_eq!(bounded.0, unbounded.0, "the PLY holds every occupied voxel either way");
}
