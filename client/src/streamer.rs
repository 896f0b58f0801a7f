//! The streaming core: read and encode frames on a source thread, pace them,
//! keep at most `max_in_flight` unanswered, and account for every result.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use prost::Message;
use serde::Serialize;
use stillmap_proto::codec;
use stillmap_proto::pb::{self, ColorEncoding, DepthEncoding, FrameStatus};
use tokio::sync::{mpsc, oneshot};

use crate::ClientError;
use crate::calibration::CameraOptions;
use crate::link::{Link, LinkEvent};
use crate::source::{self, RawFrame, SourceSpec};

/// Frames read and encoded ahead of the sender.
const ENCODE_AHEAD: usize = 4;
/// Rejection messages kept for the summary.
const MAX_REPORTED_ERRORS: usize = 5;

/// How fast frames go out.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rate {
    /// At the pace they were captured (recordings replay in real time).
    Realtime,
    /// As fast as the window of unanswered frames allows.
    Max,
    /// A fixed rate in Hz.
    Fixed(f64),
}

/// Slowest and fastest fixed rate (Hz): a frame every 1000 s at most (slower, the
/// wait between frames stops being a rate), a microsecond apart at least.
pub const MIN_RATE_HZ: f64 = 0.001;
pub const MAX_RATE_HZ: f64 = 1_000_000.0;

impl std::str::FromStr for Rate {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "realtime" => Ok(Self::Realtime),
            "max" => Ok(Self::Max),
            hz => match hz.parse::<f64>() {
                Ok(v) if (MIN_RATE_HZ..=MAX_RATE_HZ).contains(&v) => Ok(Self::Fixed(v)),
                _ => Err(format!("rate {s:?} is not realtime, max or a number of Hz from {MIN_RATE_HZ} to {MAX_RATE_HZ}")),
            },
        }
    }
}

#[derive(Debug, Clone)]
pub struct StreamOptions {
    pub robot_id: String,
    /// The hello's fleet (empty: the server's default).
    pub fleet: String,
    pub auth_token: String,
    pub source: SourceSpec,
    pub max_frames: Option<usize>,
    pub rate: Rate,
    pub jpeg_quality: u8,
    pub color_encoding: ColorEncoding,
    pub depth_encoding: DepthEncoding,
    pub max_in_flight: usize,
    pub progress: bool,
    /// Overrides the source's rolling-shutter readout (seconds) in the hello.
    pub rolling_shutter_readout_s: Option<f64>,
    /// Overrides the source's exposure-time offset (seconds) in the hello.
    pub exposure_time_offset_s: Option<f64>,
    /// Where the intrinsics come from (`--calibration`, `--camera`, `--allow-default-intrinsics`).
    pub camera: CameraOptions,
}

/// A frame ready to send, with what the client needs to check its result.
#[derive(Debug, Clone)]
pub struct Encoded {
    pub frame: pb::Frame,
    /// CRC-32 of the raw depth, to prove the server decoded it bit-exact.
    pub depth_crc32: u32,
}

/// Where a stream's frames come from: the camera they were taken with, how many
/// there are (when known), and the encoded frames in order.
pub struct Feed {
    pub camera: pb::CameraInfo,
    pub len_hint: Option<usize>,
    pub frames: mpsc::Receiver<Result<Encoded, ClientError>>,
}

/// A pose the server returned, for `--trajectory`.
#[derive(Debug, Clone, Serialize)]
pub struct ReturnedPose {
    pub capture_time_ns: u64,
    /// The time the pose refers to (`FrameResult.pose_time_ns`).
    pub pose_time_ns: u64,
    pub translation: [f64; 3],
    pub rotation_xyzw: [f64; 4],
}

/// The longest gap between two frames' capture times that `--rate realtime` waits
/// out: beyond it (a driver clock that started at 0, a clock set) the pacing starts
/// again from that frame.
const MAX_REALTIME_GAP_NS: u64 = 10_000_000_000;

/// What `--rate realtime` paces from: a frame's capture time and the wall time it
/// was sent at, and the last frame's capture time.
#[derive(Debug, Clone, Copy)]
struct RealtimeAnchor {
    capture_ns: u64,
    wall: tokio::time::Instant,
    last_ns: u64,
}

/// When to send the frame captured at `capture_ns` at the recording's own pace;
/// `now`, the wall clock. A gap over [`MAX_REALTIME_GAP_NS`] from the last frame, or
/// a frame before it, moves the anchor to this frame (sent now).
fn realtime_send_at(anchor: &mut Option<RealtimeAnchor>, capture_ns: u64, now: tokio::time::Instant) -> tokio::time::Instant {
    match anchor {
        Some(a) if capture_ns >= a.last_ns && capture_ns - a.last_ns <= MAX_REALTIME_GAP_NS => {
            a.last_ns = capture_ns;
            a.wall + Duration::from_nanos(capture_ns - a.capture_ns)
        }
        _ => {
            if let Some(a) = anchor {
                tracing::warn!("capture times jump from {} ns to {capture_ns} ns: realtime pacing starts again from this frame", a.last_ns);
            }
            *anchor = Some(RealtimeAnchor { capture_ns, wall: now, last_ns: capture_ns });
            now
        }
    }
}

/// What happened to a streaming run.
#[derive(Debug, Default, Clone, Serialize)]
pub struct Summary {
    pub transport: String,
    pub session_id: String,
    /// The gRPC server the robot streamed to last (where it was placed); empty on Zenoh.
    pub server: String,
    pub frames_sent: u64,
    /// Results with status OK.
    pub frames_acknowledged: u64,
    pub frames_dropped: u64,
    pub frames_rejected: u64,
    /// Frames too large for the server's message limit, never sent.
    pub frames_too_large: u64,
    /// Frames whose results were lost in a reconnect.
    pub frames_unanswered: u64,
    /// OK results whose depth CRC matched the frame sent.
    pub depth_bit_exact: u64,
    pub depth_mismatch: u64,
    /// Results that arrived with a lower sequence than an earlier result.
    pub results_out_of_order: u64,
    pub reconnects: u64,
    pub bytes_sent: u64,
    pub bytes_per_frame: f64,
    pub seconds: f64,
    pub frames_per_second: f64,
    pub mbit_per_second: f64,
    /// Mbit/s this stream would need at the camera's nominal rate.
    pub mbit_per_second_at_nominal_rate: f64,
    pub nominal_rate_hz: f64,
    pub latency_ms_p50: f64,
    pub latency_ms_p95: f64,
    pub latency_ms_p99: f64,
    /// Age in frames of the segmentation each OK result used (0 = segmented on that
    /// very frame), over the results that had one.
    pub mask_age_p50: f64,
    pub mask_age_p95: f64,
    /// OK results whose frame had no segmentation at all (none yet, or perception off).
    pub frames_without_mask: u64,
    pub first_errors: Vec<String>,
    /// Every result's latency (ms) and OK result's mask age, for fleet totals.
    #[serde(skip)]
    pub latencies_ms: Vec<f64>,
    #[serde(skip)]
    pub mask_ages: Vec<f64>,
    /// Poses the server returned (the JSON summary holds their count as `poses_returned`).
    #[serde(rename = "poses_returned", serialize_with = "serialize_count")]
    pub poses: Vec<ReturnedPose>,
}

fn serialize_count<S: serde::Serializer>(poses: &[ReturnedPose], s: S) -> Result<S::Ok, S::Error> {
    s.serialize_u64(poses.len() as u64)
}

/// Nearest-rank percentile of sorted values (0 for none).
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let rank = (p / 100.0 * (sorted.len() - 1) as f64).round() as usize;
    sorted[rank.min(sorted.len() - 1)]
}

/// The source's camera and frame count (when known), sent once when it opens.
type SourceOpened = oneshot::Receiver<Result<(pb::CameraInfo, Option<usize>), ClientError>>;

/// Encodes one captured frame as frame `sequence`.
pub fn encode(
    raw: &RawFrame,
    sequence: u64,
    color_encoding: ColorEncoding,
    depth_encoding: DepthEncoding,
    jpeg_quality: u8,
) -> Result<Encoded, ClientError> {
    (|| {
        let frame = pb::Frame {
            sequence,
            capture_time_ns: raw.capture_time_ns,
            color: codec::encode_color(color_encoding, &raw.color, jpeg_quality)?.into(),
            depth: codec::encode_depth(depth_encoding, &raw.depth)?.into(),
            accel_in_camera: raw.accel_in_camera.map(|[x, y, z]| pb::Vector3 { x, y, z }),
        };
        Ok(Encoded { frame, depth_crc32: raw.depth.crc32() })
    })()
    .map_err(|e: codec::CodecError| ClientError::Source(format!("encoding frame {sequence}: {e}")))
}

/// Reads the source on its own thread (OpenNI2 handles stay on one thread) and encodes.
fn spawn_source(options: &StreamOptions) -> (SourceOpened, mpsc::Receiver<Result<Encoded, ClientError>>) {
    let (camera_tx, camera_rx) = oneshot::channel();
    let (frames_tx, frames_rx) = mpsc::channel(ENCODE_AHEAD);
    let (spec, max_frames, quality) = (options.source.clone(), options.max_frames, options.jpeg_quality);
    let (color_encoding, depth_encoding) = (options.color_encoding, options.depth_encoding);
    let camera_options = options.camera.clone();
    // A thread that cannot start drops `camera_tx` with its closure: `run` then
    // reports that the source thread stopped.
    let _source = std::thread::Builder::new().name("camera-source".into()).spawn(move || {
        let mut src = match source::open(&spec, max_frames, &camera_options) {
            Ok(s) => s,
            Err(e) => {
                let _ = camera_tx.send(Err(e));
                return;
            }
        };
        let _ = camera_tx.send(Ok((src.camera(), src.len_hint())));
        let mut sequence = 0u64;
        loop {
            let item = match src.next_frame() {
                Ok(None) => break,
                Ok(Some(raw)) => encode(&raw, sequence, color_encoding, depth_encoding, quality),
                Err(e) => Err(e),
            };
            sequence += 1;
            let failed = item.is_err();
            if frames_tx.blocking_send(item).is_err() || failed {
                break;
            }
        }
    });
    (camera_rx, frames_rx)
}

/// Streams the source through a link built by `connect` from the hello.
pub async fn run(options: &StreamOptions, transport: &str, connect: impl FnOnce(pb::Hello) -> Link) -> Result<Summary, ClientError> {
    let (camera_rx, frames) = spawn_source(options);
    let (camera, len_hint) = camera_rx.await.map_err(|_| ClientError::Source("the source thread stopped".into()))??;
    stream(options, transport, Feed { camera, len_hint, frames }, connect).await
}

/// Streams a feed of encoded frames through a link built by `connect` from the
/// hello (the source in `options` is not read: the feed is).
pub async fn stream(
    options: &StreamOptions,
    transport: &str,
    feed: Feed,
    connect: impl FnOnce(pb::Hello) -> Link,
) -> Result<Summary, ClientError> {
    let Feed { mut camera, len_hint, frames: mut encoded_rx } = feed;
    camera.color_encoding = options.color_encoding as i32;
    camera.depth_encoding = options.depth_encoding as i32;
    if let Some(readout_s) = options.rolling_shutter_readout_s {
        camera.rolling_shutter_readout_s = readout_s;
    }
    if let Some(offset_s) = options.exposure_time_offset_s {
        camera.exposure_time_offset_s = offset_s;
    }
    let nominal_rate_hz = camera.nominal_rate_hz;
    let hello = pb::Hello {
        robot_id: options.robot_id.clone(),
        auth_token: options.auth_token.clone(),
        camera: Some(camera),
        resume_session_id: String::new(),
        client_version: concat!("stillmap-client ", env!("CARGO_PKG_VERSION")).into(),
        fleet: options.fleet.clone(),
        resume_secret: String::new(),
        // Set by the gRPC link when a server answers where it belongs.
        follows_placement: false,
    };
    let Link { frames, mut events, task } = connect(hello);
    let mut frames = Some(frames);

    let progress = crate::progress::bar(options.progress, len_hint);
    let mut summary = Summary { transport: transport.into(), nominal_rate_hz, ..Default::default() };
    let mut sent_at: HashMap<u64, (Instant, u32)> = HashMap::new();
    let mut latencies_ms: Vec<f64> = Vec::new();
    let mut mask_ages: Vec<f64> = Vec::new();
    let mut last_result_seq: Option<u64> = None;
    let mut max_message_bytes: Option<u64> = None;
    let mut pending: Option<Encoded> = None;
    let mut source_done = false;
    let mut realtime: Option<RealtimeAnchor> = None;
    let mut next_send = tokio::time::Instant::now();
    let started = Instant::now();

    loop {
        let in_flight = sent_at.len();
        let can_send = pending.is_some() && max_message_bytes.is_some() && in_flight < options.max_in_flight;
        if source_done && pending.is_none() && frames.is_some() {
            frames = None; // every frame is handed over: let the link finish
        }
        tokio::select! {
            event = events.recv() => match event {
                None => break,
                Some(LinkEvent::Streaming(server)) => summary.server = server,
                Some(LinkEvent::Accepted(a)) => {
                    summary.session_id = a.session_id;
                    max_message_bytes = Some(a.max_message_bytes);
                }
                Some(LinkEvent::Reconnected(_)) => summary.reconnects += 1,
                Some(LinkEvent::Unanswered(seqs)) => {
                    summary.frames_unanswered += seqs.len() as u64;
                    for s in seqs {
                        sent_at.remove(&s);
                    }
                }
                Some(LinkEvent::Result(r)) => {
                    if last_result_seq.is_some_and(|l| r.sequence < l) {
                        summary.results_out_of_order += 1;
                    }
                    last_result_seq = Some(r.sequence);
                    let Some((at, crc)) = sent_at.remove(&r.sequence) else { continue };
                    latencies_ms.push(at.elapsed().as_secs_f64() * 1e3);
                    match r.status() {
                        FrameStatus::Ok => {
                            summary.frames_acknowledged += 1;
                            if r.depth_crc32 == crc { summary.depth_bit_exact += 1 } else { summary.depth_mismatch += 1 }
                            match r.counts.as_ref().map(|c| (c.mask_source(), c.mask_age_frames)) {
                                Some((pb::MaskSource::Fresh, _)) => mask_ages.push(0.0),
                                Some((pb::MaskSource::Warped, age)) => mask_ages.push(f64::from(age)),
                                _ => summary.frames_without_mask += 1,
                            }
                        }
                        FrameStatus::Dropped => summary.frames_dropped += 1,
                        _ => {
                            summary.frames_rejected += 1;
                            if summary.first_errors.len() < MAX_REPORTED_ERRORS {
                                let msg = r.error.as_ref().map_or("no reason given".into(), |e| e.message.clone());
                                summary.first_errors.push(msg);
                            }
                        }
                    }
                    // A pose without its rotation or translation, or not finite, is no
                    // pose (the trajectory file would hold a zero quaternion).
                    if let Some(p) = r.world_from_camera.as_ref()
                        && let (Some(t), Some(q)) = (p.translation, p.rotation)
                        && [t.x, t.y, t.z, q.x, q.y, q.z, q.w].iter().all(|v| v.is_finite())
                        && q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w > 0.0
                    {
                        summary.poses.push(ReturnedPose {
                            capture_time_ns: r.capture_time_ns,
                            // A server that predates the field sends none: its poses refer to the timestamp.
                            pose_time_ns: r.pose_time_ns.unwrap_or(r.capture_time_ns),
                            translation: [t.x, t.y, t.z],
                            rotation_xyzw: [q.x, q.y, q.z, q.w],
                        });
                    }
                    progress.inc(1);
                }
            },
            item = encoded_rx.recv(), if pending.is_none() && !source_done => match item {
                None => source_done = true,
                Some(Err(e)) => return Err(e),
                Some(Ok(enc)) => {
                    next_send = match options.rate {
                        Rate::Max => tokio::time::Instant::now(),
                        Rate::Fixed(_) => next_send.max(tokio::time::Instant::now() - Duration::from_secs(1)),
                        Rate::Realtime => realtime_send_at(&mut realtime, enc.frame.capture_time_ns, tokio::time::Instant::now()),
                    };
                    pending = Some(enc);
                }
            },
            _ = tokio::time::sleep_until(next_send), if can_send => {
                let Some(enc) = pending.take() else { continue };
                let Some(tx) = frames.as_ref() else { continue };
                // As the Zenoh link sends it, with the fleet (over gRPC a few bytes less).
                let message = pb::ClientMessage { msg: Some(pb::client_message::Msg::Frame(enc.frame.clone())), fleet: options.fleet.clone() };
                let size = message.encoded_len() as u64;
                if max_message_bytes.is_some_and(|m| size > m) {
                    summary.frames_too_large += 1;
                    progress.inc(1);
                    continue;
                }
                let sequence = enc.frame.sequence;
                if tx.send(enc.frame).await.is_err() {
                    break;
                }
                sent_at.insert(sequence, (Instant::now(), enc.depth_crc32));
                summary.frames_sent += 1;
                summary.bytes_sent += size;
                if let Rate::Fixed(hz) = options.rate {
                    next_send += Duration::from_secs_f64(1.0 / hz);
                }
            },
        }
    }
    progress.finish_and_clear();
    task.await.map_err(|e| ClientError::Protocol(format!("link task: {e}")))??;

    summary.seconds = started.elapsed().as_secs_f64();
    let frames_done = summary.frames_sent.max(1) as f64;
    summary.bytes_per_frame = summary.bytes_sent as f64 / frames_done;
    summary.frames_per_second = summary.frames_sent as f64 / summary.seconds.max(1e-9);
    summary.mbit_per_second = summary.bytes_sent as f64 * 8.0 / 1e6 / summary.seconds.max(1e-9);
    summary.mbit_per_second_at_nominal_rate = summary.bytes_per_frame * 8.0 * nominal_rate_hz / 1e6;
    latencies_ms.sort_by(f64::total_cmp);
    summary.latency_ms_p50 = percentile(&latencies_ms, 50.0);
    summary.latency_ms_p95 = percentile(&latencies_ms, 95.0);
    summary.latency_ms_p99 = percentile(&latencies_ms, 99.0);
    mask_ages.sort_by(f64::total_cmp);
    summary.mask_age_p50 = percentile(&mask_ages, 50.0);
    summary.mask_age_p95 = percentile(&mask_ages, 95.0);
    summary.latencies_ms = latencies_ms;
    summary.mask_ages = mask_ages;
    summary.frames_unanswered += sent_at.len() as u64;
    Ok(summary)
}

impl Summary {
    /// The human-readable report printed at the end of a run.
    pub fn report(&self) -> String {
        let mut s = format!(
            "stillmap-client summary ({} session {}{})\n\
             frames: sent {} | acknowledged {} | dropped {} | rejected {} | too large {} | unanswered {}\n\
             depth: {} bit-exact, {} mismatched | results out of order: {} | reconnects: {}\n\
             bytes: {} ({:.0} per frame) | {:.1} frames/s | {:.2} Mbit/s ({:.2} Mbit/s at {:.0} Hz)\n\
             result latency: p50 {:.1} ms, p95 {:.1} ms, p99 {:.1} ms over {:.2} s\n\
             segmentation age: p50 {:.0}, p95 {:.0} frames | {} frames without one",
            self.transport,
            self.session_id,
            if self.server.is_empty() { String::new() } else { format!(" on {}", self.server) },
            self.frames_sent,
            self.frames_acknowledged,
            self.frames_dropped,
            self.frames_rejected,
            self.frames_too_large,
            self.frames_unanswered,
            self.depth_bit_exact,
            self.depth_mismatch,
            self.results_out_of_order,
            self.reconnects,
            self.bytes_sent,
            self.bytes_per_frame,
            self.frames_per_second,
            self.mbit_per_second,
            self.mbit_per_second_at_nominal_rate,
            self.nominal_rate_hz,
            self.latency_ms_p50,
            self.latency_ms_p95,
            self.latency_ms_p99,
            self.seconds,
            self.mask_age_p50,
            self.mask_age_p95,
            self.frames_without_mask,
        );
        for e in &self.first_errors {
            s.push_str(&format!("\nrejected: {e}"));
        }
        s
    }

    /// The returned poses in TUM format: `timestamp tx ty tz qx qy qz qw`, each at
    /// the time it refers to (`pose_time_ns`).
    pub fn tum_trajectory(&self) -> String {
        let mut out = String::from("# stillmap poses: timestamp tx ty tz qx qy qz qw (world_from_camera at pose_time_ns)\n");
        for p in &self.poses {
            stillmap_dataset::trajectory::push_line_ns(&mut out, p.pose_time_ns, p.translation, p.rotation_xyzw);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn realtime_pacing_waits_out_the_recording_but_not_a_clock_jump() {
        let now = tokio::time::Instant::now();
        let later = |ms: u64| now + Duration::from_millis(ms);
        let mut anchor = None;
        assert_eq!(realtime_send_at(&mut anchor, 0, now), now, "the first frame: now");
        // A driver clock that started at 0, then the real one: sent at once, not in 56 years.
        let epoch = 1_765_000_000_000_000_000;
        assert_eq!(realtime_send_at(&mut anchor, epoch, later(5)), later(5));
        assert_eq!(realtime_send_at(&mut anchor, epoch + 33_000_000, later(6)), later(5 + 33), "paced from the new anchor");
        assert_eq!(realtime_send_at(&mut anchor, epoch + 9_033_000_000, later(7)), later(5 + 9_033), "a 9 s pause is waited out");
        assert_eq!(realtime_send_at(&mut anchor, epoch + 1_000_000, later(8)), later(8), "back in time: now");
    }

    #[test]
    fn rates_parse() {
        assert_eq!("max".parse(), Ok(Rate::Max));
        assert_eq!("15".parse(), Ok(Rate::Fixed(15.0)));
        assert!("0".parse::<Rate>().is_err());
        assert_eq!("0.001".parse(), Ok(Rate::Fixed(0.001)));
        for bad in ["1e-20", "inf", "NaN", "-3", "2e6"] {
            assert_eq!(
                bad.parse::<Rate>(),
                Err(format!("rate {bad:?} is not realtime, max or a number of Hz from 0.001 to 1000000")),
                "{bad}"
            );
        }
    }

    #[test]
    fn percentiles() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 50.0), 51.0);
        assert_eq!(percentile(&v, 95.0), 95.0);
        assert_eq!(percentile(&[], 50.0), 0.0);
    }
}
