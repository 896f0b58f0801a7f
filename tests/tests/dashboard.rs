//! The web dashboard end to end in a real browser: the server and the real client
//! as processes, Debian's chromium driven by playwright-core
//! (`tests/browser/dashboard.mjs`; `make test` installs both): live and finished
//! rows, the table fitting a 1400 px window, the map, the trajectory at every zoom, the
//! fleet view. The screenshot is left in `target/test-artifacts/dashboard.png`.

use std::path::Path;
use std::process::Command;

use stillmap_e2e::{Server, bin, tum_dir};

#[test]
fn the_dashboard_draws_live_sessions_map_and_trajectory() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let dashboard = repo.join("dashboard");
    assert!(
        dashboard.join("node_modules/playwright-core").is_dir() && Path::new("/usr/bin/chromium").exists(),
        "the browser test needs dashboard/node_modules (npm ci) and /usr/bin/chromium: run `make deps`"
    );
    let artifacts = repo.join("target/test-artifacts");
    std::fs::create_dir_all(&artifacts).expect("artifact folder");
    let screenshot = artifacts.join("dashboard.png");
    let _ = std::fs::remove_file(&screenshot);
    let server = Server::start(&["--no-zenoh"]);
    let out = Command::new("node")
        .arg(repo.join("tests/browser/dashboard.mjs"))
        .arg(format!("http://{}/", server.http))
        .arg(server.grpc_url())
        .arg(bin("stillmap-client"))
        .arg(tum_dir())
        .arg(&dashboard)
        .arg(&screenshot)
        .output()
        .expect("run node");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprintln!("{stdout}{stderr}");
    assert!(out.status.success(), "browser test failed: {stderr}");
    assert!(stdout.contains("\"ok\":true"), "{stdout}");
    let png = std::fs::read(&screenshot).expect("screenshot saved");
    assert!(png.starts_with(b"\x89PNG"), "the screenshot is a PNG");
}
