//! `stillmap-client fleet`: a load generator that runs N robots from one process.
//!
//! The recording is read and encoded once (the generator must not be what limits
//! the server); every robot then replays it with its own session, link and robot
//! id. A robot plays the recording forward and then backward, over and over (a
//! ping-pong loop: the camera never jumps, so tracking stays valid however long the
//! run), starting at its own place in that loop, spread evenly, so robots send
//! different frames (two going opposite ways cross on one frame twice per loop). Timestamps advance at the camera's nominal rate. After the run
//! it reports every robot's counts, latency and segmentation freshness, the totals,
//! and the server's time per stage from `/metrics` (the difference between a
//! snapshot before and one after).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;
use stillmap_proto::pb::{self, ColorEncoding, DepthEncoding};
use tokio::sync::mpsc;

use crate::ClientError;
use crate::calibration::CameraOptions;
use crate::link::{self, GrpcOptions, ZenohOptions};
use crate::source::{FrameSource, SourceSpec};
use crate::streamer::{self, Encoded, Feed, Rate, StreamOptions, Summary, percentile};
use crate::tum::TumSource;

/// Frames a robot's feed encodes ahead of its sender (they are clones of the
/// pre-encoded recording, so this bounds only bookkeeping).
const FEED_AHEAD: usize = 4;
/// JPEG quality of the replayed colour (the stream command's default).
const JPEG_QUALITY: u8 = 90;

/// How the robots reach the server.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FleetTransport {
    Grpc,
    Zenoh,
    /// Robots alternate: even ones over gRPC, odd ones over Zenoh.
    Mixed,
}

impl FleetTransport {
    fn for_robot(self, index: usize) -> &'static str {
        match self {
            Self::Grpc => "grpc",
            Self::Zenoh => "zenoh",
            Self::Mixed if index.is_multiple_of(2) => "grpc",
            Self::Mixed => "zenoh",
        }
    }
}

#[derive(Debug, Clone)]
pub struct FleetOptions {
    pub robots: usize,
    /// A TUM RGB-D folder, replayed by every robot.
    pub tum: PathBuf,
    pub camera: CameraOptions,
    /// Frames of the recording to load (all when `None`).
    pub max_frames: Option<usize>,
    pub rate: Rate,
    /// How long robots send frames; results still in flight are awaited after it.
    pub duration: Duration,
    pub transport: FleetTransport,
    pub grpc: GrpcOptions,
    pub zenoh: ZenohOptions,
    /// The server's HTTP address (`http://host:port`), for `/metrics`; none skips the stage table.
    pub http: Option<String>,
    /// Robot ids are `<prefix>-01`, `<prefix>-02`, …
    pub robot_prefix: String,
    pub token: String,
    pub max_in_flight: usize,
}

/// One robot's outcome: its summary, or the error that ended it.
#[derive(Debug, Clone, Serialize)]
pub struct RobotReport {
    pub robot_id: String,
    pub transport: String,
    /// The error that stopped this robot (the others go on).
    pub error: Option<String>,
    pub summary: Option<Summary>,
}

/// The server's mean time per stage over the run.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct StageTime {
    pub stage: String,
    pub frames: u64,
    pub mean_ms: f64,
}

/// Totals over every robot that ran.
#[derive(Debug, Clone, Default, Serialize)]
pub struct FleetTotals {
    pub robots: usize,
    pub robots_failed: usize,
    pub frames_sent: u64,
    pub frames_answered: u64,
    pub frames_dropped: u64,
    pub frames_rejected: u64,
    pub frames_unanswered: u64,
    /// Answered frames per second over the run, all robots together.
    pub frames_per_second: f64,
    /// The same per robot that ran (mean).
    pub frames_per_second_per_robot: f64,
    pub latency_ms_p50: f64,
    pub latency_ms_p95: f64,
    pub latency_ms_p99: f64,
    pub mask_age_p50: f64,
    pub mask_age_p95: f64,
    pub frames_without_mask: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct FleetReport {
    pub rate_hz: Option<f64>,
    pub duration_s: f64,
    pub seconds: f64,
    pub recording_frames: usize,
    pub robots: Vec<RobotReport>,
    pub total: FleetTotals,
    /// From `/metrics`, when the server's HTTP address was given and answered.
    pub server_stages: Vec<StageTime>,
    pub metrics_error: Option<String>,
}

/// The recording, read and encoded once.
struct Recording {
    camera: pb::CameraInfo,
    frames: Vec<Encoded>,
}

fn load_recording(options: &FleetOptions) -> Result<Recording, ClientError> {
    let mut source = TumSource::open(&options.tum, options.max_frames, &options.camera)?;
    let camera = source.camera();
    let mut frames = Vec::new();
    while let Some(raw) = source.next_frame()? {
        let sequence = frames.len() as u64;
        frames.push(streamer::encode(&raw, sequence, ColorEncoding::Jpeg, DepthEncoding::Zstd, JPEG_QUALITY)?);
    }
    Ok(Recording { camera, frames })
}

/// The recording index of the `n`-th frame of a ping-pong loop over `len` frames
/// (0, 1, …, len−1, len−2, …, 1, 0, 1, …).
pub fn ping_pong(n: usize, len: usize) -> usize {
    if len < 2 {
        return 0;
    }
    let period = 2 * len - 2;
    let m = n % period;
    if m < len { m } else { period - m }
}

/// Where robot `index` of `robots` starts in the ping-pong loop: spread evenly.
pub fn start_offset(index: usize, robots: usize, len: usize) -> usize {
    let period = if len < 2 { 1 } else { 2 * len - 2 };
    index * period / robots.max(1)
}

/// A robot's feed: the recording in a ping-pong loop from `offset`, renumbered
/// from 0 and stamped at the nominal rate, until `until`.
fn replay(recording: Arc<Recording>, offset: usize, until: Instant) -> Feed {
    let (tx, rx) = mpsc::channel(FEED_AHEAD);
    let camera = recording.camera.clone();
    let rate_hz = if camera.nominal_rate_hz > 0.0 { camera.nominal_rate_hz } else { 30.0 };
    let t0 = recording.frames.first().map_or(0, |f| f.frame.capture_time_ns);
    tokio::spawn(async move {
        for k in 0u64.. {
            if Instant::now() >= until {
                break;
            }
            let index = ping_pong(offset + k as usize, recording.frames.len());
            let Some(recorded) = recording.frames.get(index) else { break };
            let mut enc = recorded.clone();
            enc.frame.sequence = k;
            enc.frame.capture_time_ns = t0 + (k as f64 * 1e9 / rate_hz).round() as u64;
            if tx.send(Ok(enc)).await.is_err() {
                break;
            }
        }
    });
    Feed { camera, len_hint: None, frames: rx }
}

/// Runs the fleet and gathers the report. A robot the server refuses is reported
/// with its error; the others go on.
pub async fn run(options: &FleetOptions) -> Result<FleetReport, ClientError> {
    if options.robots == 0 {
        return Err(ClientError::Usage("--robots must be at least 1".into()));
    }
    if options.max_in_flight == 0 {
        return Err(ClientError::Usage("--max-in-flight must be at least 1".into()));
    }
    let loading = options.clone();
    let recording = tokio::task::spawn_blocking(move || load_recording(&loading))
        .await
        .map_err(|e| ClientError::Source(format!("loading the recording: {e}")))??;
    let recording_frames = recording.frames.len();
    let recording = Arc::new(recording);
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(10))
        .build()
        .map_err(|e| ClientError::Connect(format!("HTTP client: {e}")))?;
    let before = match &options.http {
        Some(http) => Some(fetch_stages(&client, http).await),
        None => None,
    };

    let started = Instant::now();
    let until = started + options.duration;
    let mut tasks = Vec::new();
    for index in 0..options.robots {
        let robot_id = format!("{}-{:02}", options.robot_prefix, index + 1);
        stillmap_proto::validate_robot_id(&robot_id).map_err(ClientError::Usage)?;
        let transport = options.transport.for_robot(index);
        let stream_options = StreamOptions {
            robot_id: robot_id.clone(),
            fleet: String::new(),
            auth_token: options.token.clone(),
            source: SourceSpec::Tum(options.tum.clone()),
            max_frames: None,
            rate: options.rate,
            jpeg_quality: JPEG_QUALITY,
            color_encoding: ColorEncoding::Jpeg,
            depth_encoding: DepthEncoding::Zstd,
            max_in_flight: options.max_in_flight,
            progress: false,
            rolling_shutter_readout_s: None,
            exposure_time_offset_s: None,
            camera: options.camera.clone(),
        };
        let feed = replay(recording.clone(), start_offset(index, options.robots, recording_frames), until);
        let (grpc, zenoh) = (options.grpc.clone(), options.zenoh.clone());
        tasks.push(tokio::spawn(async move {
            let result = match transport {
                "zenoh" => zenoh_stream(&stream_options, feed, zenoh).await,
                _ => streamer::stream(&stream_options, "grpc", feed, |hello| link::start_grpc(hello, grpc)).await,
            };
            let (summary, error) = match result {
                Ok(s) => (Some(s), None),
                Err(e) => (None, Some(e.to_string())),
            };
            RobotReport { robot_id, transport: transport.into(), error, summary }
        }));
    }
    let mut robots = Vec::new();
    for task in tasks {
        robots.push(task.await.map_err(|e| ClientError::Protocol(format!("robot task: {e}")))?);
    }
    let seconds = started.elapsed().as_secs_f64();

    let (server_stages, metrics_error) = match (&options.http, before) {
        (Some(http), Some(Ok(before))) => match fetch_stages(&client, http).await {
            Ok(after) => (stage_difference(&before, &after), None),
            Err(e) => (vec![], Some(e)),
        },
        (_, Some(Err(e))) => (vec![], Some(e)),
        _ => (vec![], None),
    };
    let total = totals(&robots, seconds);
    Ok(FleetReport {
        rate_hz: match options.rate {
            Rate::Fixed(hz) => Some(hz),
            Rate::Realtime => Some(recording.camera.nominal_rate_hz),
            Rate::Max => None,
        },
        duration_s: options.duration.as_secs_f64(),
        seconds,
        recording_frames,
        robots,
        total,
        server_stages,
        metrics_error,
    })
}

#[cfg(feature = "zenoh")]
async fn zenoh_stream(options: &StreamOptions, feed: Feed, zenoh: ZenohOptions) -> Result<Summary, ClientError> {
    streamer::stream(options, "zenoh", feed, |hello| link::start_zenoh(hello, zenoh)).await
}

#[cfg(not(feature = "zenoh"))]
async fn zenoh_stream(_: &StreamOptions, _: Feed, _: ZenohOptions) -> Result<Summary, ClientError> {
    Err(ClientError::Usage("this client was built without the zenoh feature".into()))
}

fn totals(robots: &[RobotReport], seconds: f64) -> FleetTotals {
    let mut t = FleetTotals { robots: robots.len(), ..Default::default() };
    let (mut latencies, mut ages) = (Vec::new(), Vec::new());
    let mut ran = 0usize;
    for r in robots {
        let Some(s) = &r.summary else {
            t.robots_failed += 1;
            continue;
        };
        ran += 1;
        t.frames_sent += s.frames_sent;
        t.frames_answered += s.frames_acknowledged;
        t.frames_dropped += s.frames_dropped;
        t.frames_rejected += s.frames_rejected;
        t.frames_unanswered += s.frames_unanswered;
        t.frames_without_mask += s.frames_without_mask;
        latencies.extend_from_slice(&s.latencies_ms);
        ages.extend_from_slice(&s.mask_ages);
    }
    t.frames_per_second = t.frames_answered as f64 / seconds.max(1e-9);
    t.frames_per_second_per_robot = t.frames_per_second / ran.max(1) as f64;
    latencies.sort_by(f64::total_cmp);
    ages.sort_by(f64::total_cmp);
    t.latency_ms_p50 = percentile(&latencies, 50.0);
    t.latency_ms_p95 = percentile(&latencies, 95.0);
    t.latency_ms_p99 = percentile(&latencies, 99.0);
    t.mask_age_p50 = percentile(&ages, 50.0);
    t.mask_age_p95 = percentile(&ages, 95.0);
    t
}

/// Sum and count of every stage's latency histogram in a Prometheus text page.
type StageSums = BTreeMap<String, (f64, u64)>;

async fn fetch_stages(client: &reqwest::Client, http: &str) -> Result<StageSums, String> {
    let url = format!("{}/metrics", http.trim_end_matches('/'));
    let response = client.get(&url).send().await.map_err(|e| format!("GET {url}: {e}"))?;
    if !response.status().is_success() {
        return Err(format!("GET {url}: HTTP {}", response.status()));
    }
    let text = response.text().await.map_err(|e| format!("GET {url}: {e}"))?;
    Ok(parse_stage_sums(&text))
}

/// Reads `stillmap_stage_latency_seconds_sum{stage="x"} v` and `_count` lines.
pub fn parse_stage_sums(text: &str) -> StageSums {
    let mut out = StageSums::new();
    for line in text.lines() {
        let Some(rest) = line.strip_prefix("stillmap_stage_latency_seconds_") else { continue };
        let (kind, rest) = match rest.split_once('{') {
            Some((kind @ ("sum" | "count"), rest)) => (kind, rest),
            _ => continue,
        };
        let Some((labels, value)) = rest.split_once('}') else { continue };
        let Some(stage) = labels.split(',').find_map(|l| l.trim().strip_prefix("stage=\"")?.strip_suffix('"')) else {
            continue;
        };
        let Ok(value) = value.trim().parse::<f64>() else { continue };
        let entry = out.entry(stage.to_string()).or_insert((0.0, 0));
        match kind {
            "sum" => entry.0 = value,
            _ => entry.1 = value as u64,
        }
    }
    out
}

/// The mean time per stage between two snapshots, stages that saw frames only.
pub fn stage_difference(before: &StageSums, after: &StageSums) -> Vec<StageTime> {
    after
        .iter()
        .filter_map(|(stage, &(sum, count))| {
            let (sum0, count0) = before.get(stage).copied().unwrap_or((0.0, 0));
            let frames = count.checked_sub(count0).filter(|&n| n > 0)?;
            Some(StageTime { stage: stage.clone(), frames, mean_ms: (sum - sum0) * 1e3 / frames as f64 })
        })
        .collect()
}

impl FleetReport {
    /// Markdown tables: one row per robot and the total, then the server's stages.
    pub fn table(&self) -> String {
        let mut s = format!(
            "fleet: {} robots, {} for {:.0} s ({:.1} s with the last results), recording of {} frames\n\n",
            self.total.robots,
            self.rate_hz.map_or("max rate".into(), |hz| format!("{hz:.0} Hz")),
            self.duration_s,
            self.seconds,
            self.recording_frames
        );
        s.push_str("| robot | transport | sent | answered | dropped | rejected | unanswered | frames/s | latency p50 / p95 / p99 ms | mask age p50 / p95 | no mask | error |\n");
        s.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|\n");
        for r in &self.robots {
            match &r.summary {
                Some(x) => s.push_str(&format!(
                    "| {} | {} | {} | {} | {} | {} | {} | {:.1} | {:.0} / {:.0} / {:.0} | {:.0} / {:.0} | {} | {} |\n",
                    r.robot_id,
                    r.transport,
                    x.frames_sent,
                    x.frames_acknowledged,
                    x.frames_dropped,
                    x.frames_rejected,
                    x.frames_unanswered,
                    x.frames_acknowledged as f64 / x.seconds.max(1e-9),
                    x.latency_ms_p50,
                    x.latency_ms_p95,
                    x.latency_ms_p99,
                    x.mask_age_p50,
                    x.mask_age_p95,
                    x.frames_without_mask,
                    x.first_errors.first().map_or("", String::as_str),
                )),
                None => s.push_str(&format!(
                    "| {} | {} | – | – | – | – | – | – | – | – | – | {} |\n",
                    r.robot_id,
                    r.transport,
                    r.error.as_deref().unwrap_or("")
                )),
            }
        }
        let t = &self.total;
        s.push_str(&format!(
            "| **total** | | {} | {} | {} | {} | {} | {:.1} ({:.1} per robot) | {:.0} / {:.0} / {:.0} | {:.0} / {:.0} | {} | {} failed |\n",
            t.frames_sent,
            t.frames_answered,
            t.frames_dropped,
            t.frames_rejected,
            t.frames_unanswered,
            t.frames_per_second,
            t.frames_per_second_per_robot,
            t.latency_ms_p50,
            t.latency_ms_p95,
            t.latency_ms_p99,
            t.mask_age_p50,
            t.mask_age_p95,
            t.frames_without_mask,
            t.robots_failed
        ));
        if !self.server_stages.is_empty() {
            s.push_str("\n| server stage | frames | mean ms |\n|---|---|---|\n");
            for st in &self.server_stages {
                s.push_str(&format!("| {} | {} | {:.2} |\n", st.stage, st.frames, st.mean_ms));
            }
        }
        if let Some(e) = &self.metrics_error {
            s.push_str(&format!("\n(no server stage times: {e})\n"));
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ping_pong_never_jumps() {
        let seq: Vec<usize> = (0..10).map(|n| ping_pong(n, 4)).collect();
        assert_eq!(seq, [0, 1, 2, 3, 2, 1, 0, 1, 2, 3]);
        assert_eq!(ping_pong(7, 1), 0);
        for n in 0..500 {
            assert!(ping_pong(n, 150).abs_diff(ping_pong(n + 1, 150)) == 1, "step at {n}");
        }
    }

    #[test]
    fn robots_start_apart() {
        // 150 frames: a loop of 298; four robots a quarter of it apart. Two robots
        // going opposite ways cross on one frame at most twice per loop.
        let starts: Vec<usize> = (0..4).map(|i| start_offset(i, 4, 150)).collect();
        assert_eq!(starts, [0, 74, 149, 223]);
        for a in 0..4 {
            for b in a + 1..4 {
                let same = (0..298).filter(|&k| ping_pong(starts[a] + k, 150) == ping_pong(starts[b] + k, 150)).count();
                assert!(same <= 2, "robots {a} and {b} send the same frame {same} times per loop");
            }
        }
    }

    #[test]
    fn stage_times_come_from_two_metric_snapshots() {
        let before = "# HELP x\nstillmap_stage_latency_seconds_sum{stage=\"track\"} 1.0\n\
                      stillmap_stage_latency_seconds_count{stage=\"track\"} 100\n\
                      stillmap_stage_latency_seconds_bucket{stage=\"track\",le=\"0.01\"} 3\n";
        let after = "stillmap_stage_latency_seconds_sum{stage=\"track\"} 3.0\n\
                     stillmap_stage_latency_seconds_count{stage=\"track\"} 200\n\
                     stillmap_stage_latency_seconds_sum{stage=\"segmentation\"} 0.5\n\
                     stillmap_stage_latency_seconds_count{stage=\"segmentation\"} 10\n\
                     stillmap_stage_latency_seconds_sum{stage=\"idle\"} 0.5\n\
                     stillmap_stage_latency_seconds_count{stage=\"idle\"} 0\n";
        let d = stage_difference(&parse_stage_sums(before), &parse_stage_sums(after));
        assert_eq!(
            d,
            vec![
                StageTime { stage: "segmentation".into(), frames: 10, mean_ms: 50.0 },
                StageTime { stage: "track".into(), frames: 100, mean_ms: 20.0 },
            ]
        );
    }
}
