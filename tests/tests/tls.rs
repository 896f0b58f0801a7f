//! TLS on the gRPC and HTTP ports with client certificates (issue 21): a CA, the
//! server's and a robot's certificates are made at test time (`openssl`), the real
//! client streams over TLS with its certificate, and a client without one, or
//! without TLS, is refused on both ports.

use std::path::{Path, PathBuf};
use std::process::Command;

use stillmap_e2e::{Server, run_client, signed_certificate, tempfile_path, test_ca, tum_dir};

fn certificates() -> PathBuf {
    let dir = tempfile_path("tls");
    std::fs::create_dir_all(&dir).expect("dir");
    test_ca(&dir);
    signed_certificate(&dir, "server", "serverAuth", "IP:127.0.0.1,DNS:localhost");
    signed_certificate(&dir, "robot", "clientAuth", "DNS:robot-1");
    dir
}

/// `curl` on the HTTP port over TLS: its HTTP status, or `None` when no answer came.
fn curl(server: &Server, dir: &Path, with_certificate: bool) -> Option<u16> {
    let mut c = Command::new("curl");
    c.args(["-s", "-o", "/dev/null", "-w", "%{http_code}", "--max-time", "10", "--cacert"]).arg(dir.join("ca.pem"));
    if with_certificate {
        c.arg("--cert").arg(dir.join("robot.pem")).arg("--key").arg(dir.join("robot.key"));
    }
    let out = c.arg(format!("https://{}/healthz", server.http)).output().expect("run curl");
    String::from_utf8_lossy(&out.stdout).trim().parse().ok().filter(|&code| code != 0)
}

#[tokio::test(flavor = "multi_thread")]
async fn grpc_and_http_over_tls_need_the_robots_certificate() {
    let dir = certificates();
    let path = |f: &str| dir.join(f).to_str().expect("utf-8").to_string();
    let config = dir.join("server.toml");
    std::fs::write(
        &config,
        format!(
            "[tls]\ncert_path = {:?}\nkey_path = {:?}\nclient_ca_path = {:?}\n",
            path("server.pem"),
            path("server.key"),
            path("ca.pem")
        ),
    )
    .expect("config");
    let server = Server::start(&["--no-zenoh", "--no-perception", "--config", config.to_str().expect("utf-8")]);
    let https = format!("https://{}", server.grpc);
    let source = format!("tum:{}", tum_dir().display());
    let base = [
        "--source",
        source.as_str(),
        "--max-frames",
        "5",
        "--rate",
        "max",
        "--server",
        https.as_str(),
        "--reconnect-attempts",
        "1",
        "--timeout",
        "5",
    ];

    // The robot with its certificate streams over TLS.
    let mut args = base.to_vec();
    let (ca, cert, key) = (path("ca.pem"), path("robot.pem"), path("robot.key"));
    args.extend(["--tls-ca", ca.as_str(), "--tls-cert", cert.as_str(), "--tls-key", key.as_str()]);
    let (out, summary) = run_client(&args);
    assert!(out.status.success(), "client over TLS failed: {}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(summary.expect("summary")["frames_acknowledged"], 5);

    // Without its certificate, or without TLS: no session.
    let mut args = base.to_vec();
    args.extend(["--tls-ca", ca.as_str()]);
    let (out, _) = run_client(&args);
    eprintln!("no client certificate: {}", String::from_utf8_lossy(&out.stderr).trim());
    assert_eq!(out.status.code(), Some(1), "no client certificate: {}", String::from_utf8_lossy(&out.stderr));
    let plain = format!("http://{}", server.grpc);
    let mut args = base.to_vec();
    args[7] = plain.as_str();
    let (out, _) = run_client(&args);
    eprintln!("plain gRPC to a TLS port: {}", String::from_utf8_lossy(&out.stderr).trim());
    assert_eq!(out.status.code(), Some(1), "plain gRPC to a TLS port: {}", String::from_utf8_lossy(&out.stderr));

    // HTTP: TLS with the certificate answers; without it the handshake fails.
    assert_eq!(curl(&server, &dir, true), Some(200));
    assert_eq!(curl(&server, &dir, false), None);
    let _ = std::fs::remove_dir_all(&dir);
}
