//! Whole-map import and export under attack (issue 21): admin tokens, decompression
//! bombs, and an imported map taking the id the next live session would get.

use std::io::Write;

use stillmap_e2e::{Server, run_client, tempfile_path, tum_dir};

const ROBOT_TOKEN: &str = "robot-token-1";
const ADMIN_TOKEN: &str = "admin-token-9";
/// The server's `store.import_max_bytes` here.
const IMPORT_MAX_BYTES: usize = 32 << 20;
const MAGIC: &[u8] = b"STILLMAP-MAP\0\x01";

/// The server's peak resident memory (VmHWM), bytes.
fn peak_rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("/proc status");
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmHWM");
    kb * 1024
}

/// A map file's body: its sections, uncompressed.
fn body_of(file: &[u8]) -> Vec<u8> {
    zstd::stream::decode_all(file.strip_prefix(MAGIC).expect("a map file")).expect("zstd body")
}

/// `file` with its header's session id replaced.
fn with_session_id(file: &[u8], id: &str) -> Vec<u8> {
    let body = body_of(file);
    let n = u32::from_le_bytes(body[..4].try_into().expect("4 bytes")) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&body[4..4 + n]).expect("JSON header");
    header["session_id"] = id.into();
    let header = serde_json::to_vec(&header).expect("JSON");
    let mut out = (header.len() as u32).to_le_bytes().to_vec();
    out.extend_from_slice(&header);
    out.extend_from_slice(&body[4 + n..]);
    let mut file = MAGIC.to_vec();
    file.extend(zstd::bulk::compress(&out, 3).expect("zstd"));
    file
}

#[tokio::test(flavor = "multi_thread")]
async fn import_and_export_need_an_admin_and_survive_bombs_and_id_theft() {
    let config = tempfile_path("import.toml");
    std::fs::write(&config, format!("[store]\nimport_max_bytes = {IMPORT_MAX_BYTES}\n")).expect("config");
    let server = Server::start(&[
        "--no-zenoh",
        "--no-perception",
        "--config",
        config.to_str().expect("utf-8"),
        "--auth-token",
        ROBOT_TOKEN,
        "--admin-token",
        ADMIN_TOKEN,
    ]);
    // Bombs first, while the server's peak memory is its start-up's.
    let bomb = |body: Vec<u8>| async {
        let r = reqwest::Client::new()
            .post(format!("http://{}/api/v1/maps/import", server.http))
            .bearer_auth(ADMIN_TOKEN)
            .body(body)
            .send()
            .await
            .expect("POST");
        let status = r.status().as_u16();
        (status, r.json::<serde_json::Value>().await.expect("JSON error")["error"].as_str().unwrap_or_default().to_string())
    };
    // 256 MiB of zeros in a few KB, with and without a declared size. Both
    // are refused naming the limit, and the server never holds them.
    let zeros = vec![0u8; 256 << 20];
    let mut declared = MAGIC.to_vec();
    declared.extend(zstd::bulk::compress(&zeros, 1).expect("zstd"));
    let mut encoder = zstd::stream::write::Encoder::new(MAGIC.to_vec(), 1).expect("zstd");
    encoder.write_all(&zeros).expect("zstd");
    let undeclared = encoder.finish().expect("zstd");
    drop(zeros);
    eprintln!("bombs: {} and {} bytes", declared.len(), undeclared.len());
    assert!(declared.len() < 64 << 10 && undeclared.len() < 64 << 10);
    let before = peak_rss(server.pid());
    let limit = format!("imports are limited to {IMPORT_MAX_BYTES} bytes uncompressed (store.import_max_bytes)");
    assert_eq!(bomb(declared).await, (400, format!("bad map file: the body declares {} bytes uncompressed; {limit}", 256 << 20)));
    assert_eq!(bomb(undeclared).await, (400, format!("bad map file: the body decompresses to more; {limit}")));
    let after = peak_rss(server.pid());
    eprintln!("server peak RSS {} MB before the bombs, {} MB after", before >> 20, after >> 20);
    // At most the cap (32 MiB) and its vector's doubling on top of what it had.
    assert!(after < before + 3 * IMPORT_MAX_BYTES as u64, "peak RSS {} -> {} MB", before >> 20, after >> 20);

    let (out, summary) = run_client(&[
        "--source",
        &format!("tum:{}", tum_dir().display()),
        "--server",
        &server.grpc_url(),
        "--rate",
        "max",
        "--max-frames",
        "60",
        "--robot-id",
        "alpha",
        "--token",
        ROBOT_TOKEN,
    ]);
    assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
    let first = summary.expect("summary")["session_id"].as_str().expect("session id").to_string();

    // Export and import need the admin token; a robot's is refused.
    let http = reqwest::Client::new();
    let url = |path: &str| format!("http://{}{path}", server.http);
    let export = |token: Option<&str>| {
        let mut r = http.get(url(&format!("/api/v1/maps/{first}/export")));
        if let Some(t) = token {
            r = r.bearer_auth(t);
        }
        r.send()
    };
    let import = |token: Option<&str>, body: Vec<u8>| {
        let mut r = http.post(url("/api/v1/maps/import")).body(body);
        if let Some(t) = token {
            r = r.bearer_auth(t);
        }
        r.send()
    };
    let refusal = |r: reqwest::Response| async move {
        let status = r.status().as_u16();
        (status, r.json::<serde_json::Value>().await.expect("JSON error")["error"].as_str().unwrap_or_default().to_string())
    };
    let missing = (401, "this needs a token with the admin scope: Authorization: Bearer <token>".to_string());
    assert_eq!(refusal(export(None).await.expect("GET")).await, missing);
    assert_eq!(refusal(export(Some(ROBOT_TOKEN)).await.expect("GET")).await, (403, "this token lacks the admin scope".to_string()));
    assert_eq!(refusal(export(Some("guess")).await.expect("GET")).await, (401, "unknown token".to_string()));
    // axum's own rejections answer in the same JSON: a path segment that is not UTF-8.
    let r = http.get(url("/api/v1/maps/%FF/export")).bearer_auth(ADMIN_TOKEN).send().await.expect("GET");
    let (status, message) = refusal(r).await;
    assert_eq!(status, 400);
    assert!(message.contains("UTF-8") || message.contains("utf-8") || message.contains("parse"), "{message}");
    let r = export(Some(ADMIN_TOKEN)).await.expect("GET");
    assert_eq!(r.status(), 200);
    let file = r.bytes().await.expect("body").to_vec();
    let unpacked = body_of(&file).len();
    eprintln!("export of 60 frames: {} bytes, {unpacked} bytes uncompressed", file.len());
    assert!(unpacked < IMPORT_MAX_BYTES);
    assert_eq!(refusal(import(None, file.clone()).await.expect("POST")).await, missing);

    // The map under the id this run gives next ("alpha-<run>-2"): imported as it
    // is, and the next live session of alpha gets another id, leaving it untouched.
    let (prefix, n) = first.rsplit_once('-').expect("<robot>-<run>-<n>");
    let next = format!("{prefix}-{}", n.parse::<u64>().expect("n") + 1);
    let r = import(Some(ADMIN_TOKEN), with_session_id(&file, &next)).await.expect("POST");
    assert_eq!(r.status(), 201);
    assert_eq!(r.json::<serde_json::Value>().await.expect("JSON")["session_id"], next.as_str());
    let (_, imported) = server.get_json(&format!("/api/v1/sessions/{next}/trajectory")).await;
    let (out, summary) = run_client(&[
        "--source",
        &format!("tum:{}", tum_dir().display()),
        "--server",
        &server.grpc_url(),
        "--rate",
        "max",
        "--max-frames",
        "10",
        "--robot-id",
        "alpha",
        "--token",
        ROBOT_TOKEN,
    ]);
    assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
    let live = summary.expect("summary")["session_id"].as_str().expect("session id").to_string();
    assert_ne!(live, next, "a live session took the imported map's id");
    let (_, after_live) = server.get_json(&format!("/api/v1/sessions/{next}/trajectory")).await;
    assert!(imported["poses"].as_array().is_some_and(|p| !p.is_empty()), "{imported}");
    assert_eq!(after_live["poses"], imported["poses"], "the imported session changed");
    let _ = std::fs::remove_file(&config);
}
