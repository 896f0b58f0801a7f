//! Helpers for the end-to-end tests: run the real `stillmap-server` and
//! `stillmap-client` binaries as processes on loopback, with the real TUM frames.

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use stillmap_proto::codec::{self, ColorImage, DepthImage};
use stillmap_proto::pb;

/// How long a server may take to print its ready line.
const SERVER_START_TIMEOUT: Duration = Duration::from_secs(30);

/// The folder holding the workspace's binaries (`target/<profile>`).
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> -> target/<profile>
    exe.parent().and_then(Path::parent).expect("target/<profile>").to_path_buf()
}

pub fn bin(name: &str) -> PathBuf {
    let path = bin_dir().join(name);
    assert!(path.exists(), "{} is missing: run `cargo build --workspace --bins` first (make test does)", path.display());
    path
}

/// The repository's root.
pub fn repo_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A Python interpreter `make deps` installed in `.deps/<venv>` (`pyclient`, `bagtools`).
pub fn venv_python(venv: &str) -> PathBuf {
    let python = repo_dir().join(".deps").join(venv).join("bin/python");
    assert!(python.exists(), "{} is missing: run `make deps`", python.display());
    python
}

/// The real TUM clip beside the checkout (or where `TUM` says).
pub fn tum_dir() -> PathBuf {
    let dir = stillmap_dataset::shared::fr1_rpy();
    assert!(dir.join("rgb.txt").exists(), "TUM clip not found at {}", dir.display());
    dir
}

/// A port nobody listens on right now.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).map(|a| a.port()).expect("free port")
}

/// A running server, killed on drop.
pub struct Server {
    child: Child,
    /// The store this server made for itself (removed on drop).
    own_store: Option<PathBuf>,
    pub grpc: String,
    pub http: String,
    pub zenoh: String,
    /// The token [`get_json`](Self::get_json) and [`get_text`](Self::get_text) send:
    /// the server's `--read-token` (else its `--admin-token`), when it has one.
    pub token: Option<String>,
}

/// Attempts at starting a server: [`free_port`] only finds ports free at that
/// moment, and another process (a client's outgoing connection, say) can take one
/// before the server binds it; the server then exits naming the port.
const SERVER_START_ATTEMPTS: usize = 3;

impl Server {
    pub fn start(extra: &[&str]) -> Self {
        Self::start_with(extra, false)
    }

    /// [`start`](Self::start), the server advertising its gRPC address to robots
    /// (`--grpc-advertise http://<its gRPC address>`) when `advertise`.
    pub fn start_with(extra: &[&str], advertise: bool) -> Self {
        for _ in 1..SERVER_START_ATTEMPTS {
            if let Some(server) = Self::try_start(extra, advertise) {
                return server;
            }
        }
        Self::try_start(extra, advertise).expect("server exited before its ready line (its stderr is above)")
    }

    /// `None` when the server exited before printing its ready line.
    fn try_start(extra: &[&str], advertise: bool) -> Option<Self> {
        let (grpc, http, zenoh) =
            (format!("127.0.0.1:{}", free_port()), format!("127.0.0.1:{}", free_port()), format!("tcp/127.0.0.1:{}", free_port()));
        // The real segmentation model from ../shared/models, unless a test says otherwise.
        let model = model_path();
        let mut command = Command::new(bin("stillmap-server"));
        command.args(["--grpc-listen", &grpc, "--http-listen", &http, "--zenoh-listen", &zenoh]);
        if advertise {
            command.args(["--grpc-advertise", &format!("http://{grpc}")]);
        }
        if !extra.contains(&"--model") && !extra.contains(&"--no-perception") {
            command.args(["--model", model.to_str().expect("utf-8 path")]);
        }
        // A store of its own, unless the test brings one.
        let store = tempfile_path("store.redb");
        let own_store = (!extra.contains(&"--store") && !extra.contains(&"--no-store")).then_some(store);
        if let Some(store) = &own_store {
            command.args(["--store", store.to_str().expect("utf-8 path")]);
        }
        let mut child = command
            .args(extra)
            // Warnings only, unless STILLMAP_E2E_LOG asks for more (a filter such as
            // `info,stillmap_server=debug`) to see what the servers did.
            .env("STILLMAP_LOG", std::env::var("STILLMAP_E2E_LOG").unwrap_or_else(|_| "warn".into()))
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("spawn stillmap-server");
        let stdout = child.stdout.take().expect("server stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::Builder::new()
            .name("server-stdout".into())
            .spawn(move || {
                for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                    if line.contains("ready") {
                        let _ = tx.send(line);
                    }
                }
            })
            .expect("a thread reading the server's stdout");
        // Dropped on a failed start: killed, waited for, its own store removed.
        let token_after = |flag: &str| extra.iter().position(|a| *a == flag).and_then(|i| extra.get(i + 1)).map(|t| t.to_string());
        let token = token_after("--read-token").or_else(|| token_after("--admin-token"));
        let server = Self { child, own_store, grpc, http, zenoh, token };
        match rx.recv_timeout(SERVER_START_TIMEOUT) {
            Ok(line) => {
                assert!(line.contains(&server.grpc), "{line}");
                Some(server)
            }
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => None,
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => panic!("server printed no ready line in {SERVER_START_TIMEOUT:?}"),
        }
    }

    /// SIGTERM, then waits for the graceful shutdown to finish.
    pub fn terminate(&mut self) {
        let _ = Command::new("kill").arg("-TERM").arg(self.child.id().to_string()).status();
        let _ = self.child.wait();
    }

    /// `kill -9`: no shutdown, no flush.
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    pub fn grpc_url(&self) -> String {
        format!("http://{}", self.grpc)
    }

    /// The server process's id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// GET on the HTTP API: (status, JSON body).
    pub async fn get_json(&self, path: &str) -> (u16, serde_json::Value) {
        let r = self.get(path).await;
        let status = r.status().as_u16();
        (status, r.json().await.expect("JSON body"))
    }

    pub async fn get_text(&self, path: &str) -> String {
        self.get(path).await.text().await.expect("text")
    }

    /// GET on the HTTP API with [`token`](Self::token) when there is one.
    async fn get(&self, path: &str) -> reqwest::Response {
        let mut request = reqwest::Client::new().get(format!("http://{}{path}", self.http));
        if let Some(t) = &self.token {
            request = request.bearer_auth(t);
        }
        request.send().await.expect("HTTP GET")
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(store) = &self.own_store {
            let _ = std::fs::remove_file(store);
        }
    }
}

/// Runs the real client to completion; returns its output and parsed JSON summary.
pub fn run_client(args: &[&str]) -> (Output, Option<serde_json::Value>) {
    let summary = tempfile_path("summary.json");
    let output = Command::new(bin("stillmap-client"))
        .arg("stream")
        .args(args)
        .args(["--quiet", "--summary-json"])
        .arg(&summary)
        .env("STILLMAP_LOG", "warn")
        .output()
        .expect("run stillmap-client");
    let json = std::fs::read_to_string(&summary).ok().and_then(|t| serde_json::from_str(&t).ok());
    let _ = std::fs::remove_file(&summary);
    (output, json)
}

/// A unique path in the temp folder.
pub fn tempfile_path(name: &str) -> PathBuf {
    static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    std::env::temp_dir().join(format!("stillmap-e2e-{}-{n}-{name}", std::process::id()))
}

/// The first real TUM frame (colour and the depth associated with it), decoded.
pub fn first_tum_frame() -> (ColorImage, DepthImage) {
    use stillmap_dataset::tum;
    let first = tum::read_sequence(&tum_dir()).expect("TUM sequence").swap_remove(0);
    let color = tum::read_image(&first.rgb, |b| codec::decode_color(pb::ColorEncoding::Png, b, 640, 480)).expect("colour PNG");
    let depth = tum::read_image(&first.depth, |b| codec::decode_depth(pb::DepthEncoding::Png16, b, 640, 480)).expect("depth PNG");
    (color, depth)
}

/// A hello for a 640×480 TUM camera with JPEG + zstd.
pub fn tum_hello(robot_id: &str) -> pb::Hello {
    pb::Hello {
        robot_id: robot_id.into(),
        // freiburg1's intrinsics, without its distortion and shutter timing.
        camera: Some(pb::CameraInfo {
            distortion_model: pb::DistortionModel::None as i32,
            distortion_coeffs: vec![],
            rolling_shutter_readout_s: 0.0,
            exposure_time_offset_s: 0.0,
            color_encoding: pb::ColorEncoding::Jpeg as i32,
            depth_encoding: pb::DepthEncoding::Zstd as i32,
            ..stillmap_dataset::calibration::KnownCamera::TumFr1.camera_info()
        }),
        ..Default::default()
    }
}

/// A real TUM frame encoded as `tum_hello` declares.
pub fn tum_frame(sequence: u64, capture_time_ns: u64) -> pb::Frame {
    let (color, depth) = first_tum_frame();
    pb::Frame {
        sequence,
        capture_time_ns,
        color: codec::encode_jpeg(&color, 90).expect("jpeg").into(),
        depth: codec::encode_depth(pb::DepthEncoding::Zstd, &depth).expect("zstd").into(),
        accel_in_camera: None,
    }
}

/// Waits until `f` returns true, or panics after `timeout`.
pub async fn eventually(timeout: Duration, what: &str, mut f: impl AsyncFnMut() -> bool) {
    let start = Instant::now();
    while !f().await {
        assert!(start.elapsed() < timeout, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The YOLOv8n-seg model beside the repository (`../shared/models`).
pub fn model_path() -> std::path::PathBuf {
    stillmap_dataset::shared::model("yolov8n-seg_fp32_640.onnx")
}

/// GET `path` from `server`'s HTTP port, with an `If-None-Match` when given.
pub async fn http_get(server: &Server, path: &str, if_none_match: Option<&str>) -> reqwest::Response {
    let mut r = reqwest::Client::new().get(format!("http://{}{path}", server.http));
    if let Some(tag) = if_none_match {
        r = r.header("If-None-Match", tag);
    }
    r.send().await.expect("HTTP GET")
}

/// An RGBA PNG (a map tile): width, height and pixels.
pub fn decode_png(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes.to_vec()));
    let mut reader = decoder.read_info().expect("valid PNG");
    let mut buf = vec![0; reader.output_buffer_size().expect("size")];
    let info = reader.next_frame(&mut buf).expect("PNG frame");
    assert_eq!(info.color_type, png::ColorType::Rgba);
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// Runs `openssl` with `args` in `dir` (test certificates).
pub fn openssl(dir: &Path, args: &[&str]) {
    let out = Command::new("openssl").args(args).current_dir(dir).output().expect("run openssl");
    assert!(out.status.success(), "openssl {args:?}: {}", String::from_utf8_lossy(&out.stderr));
}

/// Makes a test CA in `dir` (`ca.pem`, `ca.key`), valid for a day.
pub fn test_ca(dir: &Path) {
    openssl(
        dir,
        &[
            "req",
            "-x509",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:prime256v1",
            "-nodes",
            "-keyout",
            "ca.key",
            "-out",
            "ca.pem",
            "-days",
            "1",
            "-subj",
            "/CN=stillmap test CA",
            "-addext",
            "basicConstraints=critical,CA:TRUE",
            "-addext",
            "keyUsage=critical,keyCertSign",
        ],
    );
}

/// `<name>.pem` and `<name>.key` in `dir`: common name `name`, signed by the CA
/// [`test_ca`] made there, for `usage` (serverAuth, clientAuth) and `san`.
pub fn signed_certificate(dir: &Path, name: &str, usage: &str, san: &str) {
    let ext = format!("{name}.ext");
    std::fs::write(dir.join(&ext), format!("basicConstraints=CA:FALSE\nextendedKeyUsage={usage}\nsubjectAltName={san}\n"))
        .expect("ext file");
    openssl(
        dir,
        &[
            "req",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:prime256v1",
            "-nodes",
            "-keyout",
            &format!("{name}.key"),
            "-out",
            &format!("{name}.csr"),
            "-subj",
            &format!("/CN={name}"),
        ],
    );
    openssl(
        dir,
        &[
            "x509",
            "-req",
            "-in",
            &format!("{name}.csr"),
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-out",
            &format!("{name}.pem"),
            "-days",
            "1",
            "-extfile",
            &ext,
        ],
    );
}

/// A PostgreSQL server of a test's own: a fresh cluster in a temporary folder,
/// on a free loopback port, trusting local connections, killed and removed on
/// drop. Debian's `postgresql` package (`make deps` installs it); run as root,
/// it runs as the `postgres` user, as PostgreSQL requires.
pub struct Postgres {
    pub port: u16,
    dir: PathBuf,
    child: Child,
}

impl Postgres {
    pub fn start() -> Self {
        let bin = postgres_bin_dir();
        let dir = tempfile_path("postgres");
        std::fs::create_dir_all(&dir).expect("postgres folder");
        let data = dir.join("data");
        let as_postgres = |program: &str| {
            let mut command = Command::new(bin.join(program));
            if is_root() {
                use std::os::unix::process::CommandExt as _;
                let (uid, gid) = postgres_user();
                std::os::unix::fs::chown(&dir, Some(uid), Some(gid)).expect("chown the postgres folder");
                command.uid(uid).gid(gid);
            }
            command
        };
        let init = as_postgres("initdb")
            .args(["-D", data.to_str().expect("utf-8 path"), "-U", "stillmap", "--auth=trust", "--no-sync", "-E", "UTF8"])
            .stdout(Stdio::null())
            .output()
            .expect("initdb");
        assert!(init.status.success(), "initdb: {}", String::from_utf8_lossy(&init.stderr));
        let port = free_port();
        let child = as_postgres("postgres")
            .args(["-D", data.to_str().expect("utf-8 path"), "-p", &port.to_string(), "-k", dir.to_str().expect("utf-8 path")])
            .args(["-c", "listen_addresses=127.0.0.1", "-c", "fsync=off"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("postgres");
        let pg = Self { port, dir, child };
        // Ready when it answers, and the one answering is this test's (its data folder).
        let started = Instant::now();
        loop {
            let url = pg.url();
            let answer = std::thread::Builder::new()
                .name("postgres-ready".into())
                .spawn(move || {
                    let mut client = postgres::Client::connect(&url, postgres::NoTls).ok()?;
                    client.query_one("SHOW data_directory", &[]).ok().map(|row| row.get::<_, String>(0))
                })
                .expect("thread")
                .join()
                .ok()
                .flatten();
            match answer {
                Some(directory) => {
                    assert_eq!(Path::new(&directory), data, "another PostgreSQL answers on port {port}");
                    return pg;
                }
                None => {
                    assert!(started.elapsed() < Duration::from_secs(30), "PostgreSQL did not start within 30 s");
                    std::thread::sleep(Duration::from_millis(100));
                }
            }
        }
    }

    /// The libpq URL of its `postgres` database.
    pub fn url(&self) -> String {
        format!("postgresql://stillmap@127.0.0.1:{}/postgres", self.port)
    }

    /// Runs `sql` (several statements) as the superuser, from a thread of its own.
    pub fn execute(&self, sql: &str) {
        let (url, sql) = (self.url(), sql.to_string());
        std::thread::Builder::new()
            .name("postgres-execute".into())
            .spawn(move || {
                let mut client = postgres::Client::connect(&url, postgres::NoTls).expect("connect to the test's PostgreSQL");
                client.batch_execute(&sql).expect("statements")
            })
            .expect("thread")
            .join()
            .expect("execute thread")
    }

    /// A query's rows, from a thread of its own (the synchronous client runs a runtime of its own).
    pub fn query(&self, sql: &str) -> Vec<postgres::Row> {
        self.try_query(sql).unwrap_or_else(|e| panic!("{sql}: {e}"))
    }

    /// A query's rows, or PostgreSQL's error (a table the server has not created yet).
    pub fn try_query(&self, sql: &str) -> Result<Vec<postgres::Row>, postgres::Error> {
        let (url, sql) = (self.url(), sql.to_string());
        std::thread::Builder::new()
            .name("postgres-query".into())
            .spawn(move || {
                let mut client = postgres::Client::connect(&url, postgres::NoTls).expect("connect to the test's PostgreSQL");
                client.query(&sql, &[])
            })
            .expect("thread")
            .join()
            .expect("query thread")
    }
}

impl Drop for Postgres {
    fn drop(&mut self) {
        // SIGINT: PostgreSQL's fast shutdown (its backends end with it).
        let _ = Command::new("kill").arg("-INT").arg(self.child.id().to_string()).status();
        let stopping = Instant::now();
        while matches!(self.child.try_wait(), Ok(None)) && stopping.elapsed() < Duration::from_secs(10) {
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The folder of PostgreSQL's server programs: Debian's `/usr/lib/postgresql/<version>/bin`
/// (the newest), else the folder of an `initdb` on the PATH.
fn postgres_bin_dir() -> PathBuf {
    let mut debian: Vec<PathBuf> = glob::glob("/usr/lib/postgresql/*/bin/initdb").map(|g| g.flatten().collect()).unwrap_or_default();
    debian.sort_by_key(|p| p.parent().and_then(|b| b.parent()).and_then(|v| v.file_name()?.to_str()?.parse::<u32>().ok()));
    if let Some(dir) = debian.last().and_then(|p| p.parent()) {
        return dir.to_path_buf();
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .find(|d| d.join("initdb").is_file())
        .expect("PostgreSQL's server programs (initdb, postgres): Debian's postgresql package; `make deps` installs it")
}

fn is_root() -> bool {
    Command::new("id").arg("-u").output().map(|o| o.stdout.trim_ascii() == b"0").unwrap_or(false)
}

/// The `postgres` user's uid and gid.
fn postgres_user() -> (u32, u32) {
    let id = |flag: &str| -> u32 {
        let out = Command::new("id").args([flag, "postgres"]).output().expect("id");
        String::from_utf8_lossy(&out.stdout).trim().parse().expect("a postgres user (Debian's postgresql package makes it)")
    };
    (id("-u"), id("-g"))
}
