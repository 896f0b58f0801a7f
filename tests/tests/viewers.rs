//! Dashboard viewers against ingest (issue 21): the event stream is built once for
//! every viewer, viewers beyond `http.max_event_viewers` are refused, and (the
//! ignored benchmark) 500 viewers leave a streaming robot's frame rate alone.

use std::time::{Duration, Instant};

use stillmap_e2e::{Server, run_client, tempfile_path, tum_dir};

/// Opens `/api/v1/events` and reads until its first `sessions` event; the stream is
/// kept reading in the background until the returned handle is aborted.
async fn viewer(http: &str) -> Result<tokio::task::JoinHandle<()>, (u16, String)> {
    let mut r = reqwest::get(format!("http://{http}/api/v1/events")).await.expect("GET events");
    if r.status() != 200 {
        let status = r.status().as_u16();
        return Err((status, r.text().await.unwrap_or_default()));
    }
    let mut seen = String::new();
    while !seen.contains("event: sessions") {
        let chunk = tokio::time::timeout(Duration::from_secs(10), r.chunk()).await.expect("a sessions event in time").expect("stream open").expect("chunk");
        seen.push_str(&String::from_utf8_lossy(&chunk));
    }
    Ok(tokio::spawn(async move { while let Ok(Some(_)) = r.chunk().await {} }))
}

#[tokio::test(flavor = "multi_thread")]
async fn viewers_beyond_the_limit_are_refused_and_a_freed_place_is_taken() {
    let config = tempfile_path("viewers.toml");
    std::fs::write(&config, "[http]\nmax_event_viewers = 2\n").expect("config");
    let server = Server::start(&["--no-zenoh", "--no-perception", "--config", config.to_str().expect("utf-8")]);
    let first = viewer(&server.http).await.expect("first viewer");
    let _second = viewer(&server.http).await.expect("second viewer");
    let refused = viewer(&server.http).await.expect_err("a third viewer is refused");
    assert_eq!(refused.0, 503);
    let body: serde_json::Value = serde_json::from_str(&refused.1).expect("JSON error");
    assert_eq!(body["error"], "too many dashboard viewers: http.max_event_viewers = 2");
    // A viewer leaving frees its place.
    first.abort();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        match viewer(&server.http).await {
            Ok(_) => break,
            Err(e) => assert!(Instant::now() < deadline, "the freed place was never taken: {e:?}"),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let _ = std::fs::remove_file(&config);
}

/// Benchmark (release): a robot streaming the clip at full rate with 0 and 500
/// dashboard viewers connected, three times each, on a fresh server per run; prints
/// frames/s. `cargo build --release --workspace --bins && cargo test --release -p
/// stillmap-e2e --test viewers -- --ignored --nocapture`.
#[tokio::test(flavor = "multi_thread")]
#[ignore = "benchmark: prints the frame rate with and without dashboard viewers (run in release)"]
async fn viewers_do_not_slow_a_streaming_robot() {
    // 500 dashboards on one address: the per-address request limit is lifted.
    let config = tempfile_path("viewers-bench.toml");
    std::fs::write(&config, "[limits]\nhttp_requests_per_minute = 0\n").expect("config");
    let mut rows = Vec::new();
    for run in 0..3 {
        for viewers in [0usize, 500] {
            let server = Server::start(&["--no-zenoh", "--config", config.to_str().expect("utf-8")]);
            let mut handles = Vec::new();
            for _ in 0..viewers {
                handles.push(viewer(&server.http).await.expect("viewer"));
            }
            let src = format!("tum:{}", tum_dir().display());
            let grpc = server.grpc_url();
            let (out, summary) = tokio::task::spawn_blocking(move || run_client(&["--source", &src, "--server", &grpc, "--rate", "max"])).await.expect("client");
            assert!(out.status.success(), "client failed: {}", String::from_utf8_lossy(&out.stderr));
            let s = summary.expect("summary");
            let fps = s["frames_per_second"].as_f64().expect("fps");
            let (status, _) = server.get_json("/healthz").await;
            rows.push((run, viewers, fps, status, handles.iter().filter(|h| !h.is_finished()).count()));
            for h in handles {
                h.abort();
            }
        }
    }
    println!("| run | viewers | robot frames/s | /healthz | viewers still reading |\n|---|---|---|---|---|");
    for (run, viewers, fps, status, reading) in &rows {
        println!("| {} | {viewers} | {fps:.1} | {status} | {reading} |", run + 1);
    }
}
