//! The real client loses its connection mid-stream (a loopback TCP proxy cuts
//! the first connection) and must reconnect, resume the same session and finish.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use stillmap_e2e::{Server, run_client, tum_dir};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// Bytes the first connection may carry towards the server before it is cut (about 10 frames).
const CUT_AFTER_BYTES: usize = 1_500_000;

/// Forwards every connection to `upstream` as it is, except the first, which `first` carries.
async fn proxy<F, Fut>(listener: TcpListener, upstream: String, first: F)
where
    F: Fn(TcpStream, TcpStream) -> Fut + Send + Sync + 'static,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
    let first = Arc::new(first);
    let connections = Arc::new(AtomicUsize::new(0));
    while let Ok((mut client, _)) = listener.accept().await {
        let n = connections.fetch_add(1, Ordering::Relaxed);
        let (upstream, first) = (upstream.clone(), first.clone());
        tokio::spawn(async move {
            let Ok(mut server) = TcpStream::connect(&upstream).await else { return };
            if n > 0 {
                let _ = tokio::io::copy_bidirectional(&mut client, &mut server).await;
            } else {
                first(client, server).await;
            }
        });
    }
}

/// Forwards until the client has sent `CUT_AFTER_BYTES`, then drops both sides.
async fn cut_after_budget(mut client: TcpStream, mut server: TcpStream) {
    let (mut cr, mut cw) = client.split();
    let (mut sr, mut sw) = server.split();
    let up = async {
        let mut buf = vec![0u8; 64 * 1024];
        let mut sent = 0;
        while sent < CUT_AFTER_BYTES {
            let Ok(k) = cr.read(&mut buf).await else { break };
            if k == 0 || sw.write_all(&buf[..k]).await.is_err() {
                break;
            }
            sent += k;
        }
    };
    let down = tokio::io::copy(&mut sr, &mut cw);
    tokio::select! {
        _ = up => {}
        _ = down => {}
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn client_reconnects_and_resumes_the_session() {
    // After the cut, the frames of the dead connection and the resent ones meet in the
    // session queue; with perception in the pipeline the default 8 slots can overflow
    // (drop_oldest), which is the overload policy working, not a resume bug. A deeper
    // queue keeps this test about resume: every frame received once and processed.
    let server = Server::start(&["--queue-capacity", "64"]);
    // The proxy binds port 0: the kernel picks a free port and no one can take it first.
    let listener = TcpListener::bind(("127.0.0.1", 0)).await.expect("proxy bind");
    let port = listener.local_addr().expect("proxy address").port();
    tokio::spawn(proxy(listener, server.grpc.clone(), cut_after_budget));

    let src = format!("tum:{}", tum_dir().display());
    let url = format!("http://127.0.0.1:{port}");
    let (out, summary) = tokio::task::spawn_blocking(move || run_client(&["--source", &src, "--server", &url, "--rate", "max"]))
        .await
        .expect("client thread");
    assert!(out.status.success(), "client failed ({}): {}", out.status, String::from_utf8_lossy(&out.stderr));
    let s = summary.expect("summary");
    assert!(s["reconnects"].as_u64() >= Some(1), "{s:#}");
    assert_eq!(s["frames_sent"], 150);
    // Every frame is answered, except those whose result died with the connection.
    let acked = s["frames_acknowledged"].as_u64().expect("acked");
    let unanswered = s["frames_unanswered"].as_u64().expect("unanswered");
    assert_eq!(acked + unanswered, 150, "{s:#}");
    assert!(unanswered <= 8, "at most one window of results may be lost: {s:#}");
    assert_eq!(s["depth_mismatch"], 0);
    assert_eq!(s["frames_rejected"], 0, "no frame may be sent twice: {s:#}");

    // One session, resumed: the server received each frame exactly once. Frames whose
    // results died with the connection may still be in the pipeline: wait for them.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    let sessions = loop {
        let (_, sessions) = server.get_json("/api/v1/sessions").await;
        let done = sessions["sessions"][0]["counters"]["frames_processed"] == 150;
        if done || std::time::Instant::now() > deadline {
            break sessions;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    };
    let list = sessions["sessions"].as_array().expect("sessions");
    assert_eq!(list.len(), 1, "{sessions:#}");
    assert_eq!(list[0]["counters"]["frames_received"], 150);
    assert_eq!(list[0]["counters"]["frames_processed"], 150);
}

/// Bytes the first connection carries back to the client before its answers stop
/// (the accept and a few results); the connection stays open.
const ANSWER_BYTES: usize = 2_000;

/// The first connection stops answering: the client's frames still reach the
/// server, its results no longer come back (as when another party took the
/// session's results, or the server stalled).
async fn stop_answering(mut client: TcpStream, mut server: TcpStream) {
    let (mut cr, mut cw) = client.split();
    let (mut sr, mut sw) = server.split();
    let up = tokio::io::copy(&mut cr, &mut sw);
    let down = async {
        let mut buf = vec![0u8; 64 * 1024];
        let mut passed = 0;
        while let Ok(k) = sr.read(&mut buf).await {
            if k == 0 {
                break;
            }
            let pass = k.min(ANSWER_BYTES.saturating_sub(passed));
            if pass > 0 && cw.write_all(&buf[..pass]).await.is_err() {
                break;
            }
            passed += pass;
        }
    };
    tokio::select! {
        _ = up => {}
        _ = down => {}
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_client_whose_results_stop_times_out_and_resumes() {
    let server = Server::start(&["--no-perception", "--queue-capacity", "64"]);
    let listener = TcpListener::bind(("127.0.0.1", 0)).await.expect("proxy bind");
    let port = listener.local_addr().expect("proxy address").port();
    tokio::spawn(proxy(listener, server.grpc.clone(), stop_answering));
    let src = format!("tum:{}", tum_dir().display());
    let url = format!("http://127.0.0.1:{port}");
    let started = std::time::Instant::now();
    let (out, summary) = tokio::task::spawn_blocking(move || {
        run_client(&["--source", &src, "--server", &url, "--rate", "max", "--max-frames", "60", "--result-timeout", "2"])
    })
    .await
    .expect("client thread");
    let took = started.elapsed();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "client failed ({}): {stderr}", out.status);
    assert!(stderr.contains("while 8 frames wait (--result-timeout)); reconnecting"), "{stderr}");
    let s = summary.expect("summary");
    assert!(s["reconnects"].as_u64() >= Some(1), "{s:#}");
    let acked = s["frames_acknowledged"].as_u64().expect("acked");
    let unanswered = s["frames_unanswered"].as_u64().expect("unanswered");
    assert_eq!(acked + unanswered, 60, "{s:#}");
    // The link's keepalive alone would notice the silent stream only after 30 s (10 s
    // pings, 20 s to answer); the result timeout gets there in 2 s.
    eprintln!("finished in {:.1} s with {} reconnects, {unanswered} results lost", took.as_secs_f64(), s["reconnects"]);
    assert!(took < std::time::Duration::from_secs(25), "took {took:?}");
}
