//! `stillmap-client`: stream RGB-D frames to a stillmap server; measure codecs;
//! evaluate trajectories like evo.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use clap::{Parser, Subcommand, ValueEnum};
use stillmap_client::calibration::{CameraOptions, KnownCamera};
use stillmap_client::eval::{self, Alignment, EvalOptions, Metric, Relation};
use stillmap_client::fleet::{self, FleetOptions, FleetTransport};
use stillmap_client::link::{self, GrpcOptions, ZenohOptions};
use stillmap_client::source::SourceSpec;
use stillmap_client::streamer::{self, Rate, StreamOptions};
use stillmap_client::{ClientError, bench};
use stillmap_proto::pb::{ColorEncoding, DepthEncoding};

#[derive(Parser)]
#[command(name = "stillmap-client", version, about = "stillmap robot client")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum TransportArg {
    Grpc,
    Zenoh,
}

#[derive(Clone, Copy, ValueEnum)]
enum FleetTransportArg {
    Grpc,
    Zenoh,
    /// Even robots over gRPC, odd ones over Zenoh.
    Mixed,
}

#[derive(Clone, Copy, ValueEnum)]
enum DepthArg {
    Rvl,
    Png16,
    Zstd,
}

#[derive(Clone, Copy, ValueEnum)]
enum ColorArg {
    Jpeg,
    Png,
    Rgb8,
}

#[derive(Clone, Copy, ValueEnum)]
enum MetricArg {
    /// Absolute pose error (evo_ape).
    Ape,
    /// Relative pose error (evo_rpe).
    Rpe,
}

#[derive(Clone, Copy, ValueEnum)]
enum RelationArg {
    /// Translation part, metres.
    Trans,
    /// Rotation angle, degrees.
    Rot,
}

/// Where the server is (`stream` and `fleet`).
#[derive(clap::Args)]
struct EndpointArgs {
    /// gRPC server address; several, comma-separated, for servers on one Zenoh
    /// network: the robot asks them in turn where it belongs (Ingest.Place) and
    /// streams there, and asks again when that server goes.
    #[arg(long, env = "STILLMAP_SERVER", value_delimiter = ',', default_value = "http://127.0.0.1:50051")]
    server: Vec<String>,
    /// Zenoh endpoints to connect to (the server's, or a router's).
    #[arg(long, env = "STILLMAP_ZENOH_CONNECT", value_delimiter = ',', default_value = "tcp/127.0.0.1:7447")]
    zenoh_connect: Vec<String>,
    /// Zenoh mode: peer or client.
    #[arg(long, default_value = "peer")]
    zenoh_mode: String,
    /// A Zenoh configuration file (JSON5, Zenoh's own format) for TLS, mTLS or
    /// authentication to a router (deploy/zenoh/robot.json5); it replaces
    /// --zenoh-connect and --zenoh-mode.
    #[arg(long, env = "STILLMAP_ZENOH_CONFIG")]
    zenoh_config: Option<PathBuf>,
    /// The CA (PEM) that signed the server's certificate: gRPC over TLS (give the
    /// server as https://...).
    #[arg(long, env = "STILLMAP_TLS_CA")]
    tls_ca: Option<PathBuf>,
    /// This robot's certificate and key (PEM), for a server that asks for client
    /// certificates (tls.client_ca_path).
    #[arg(long, env = "STILLMAP_TLS_CERT", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    #[arg(long, env = "STILLMAP_TLS_KEY", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
}

impl EndpointArgs {
    /// The TLS files, read (a problem names the file).
    fn tls(&self) -> Result<Option<link::ClientTls>, ClientError> {
        let read = |flag: &str, p: &PathBuf| std::fs::read(p).map_err(|e| ClientError::Usage(format!("{flag} {}: {e}", p.display())));
        let Some(ca) = &self.tls_ca else {
            return match self.tls_cert {
                Some(_) => Err(ClientError::Usage("--tls-cert needs --tls-ca (the CA that signed the server's certificate)".into())),
                None => Ok(None),
            };
        };
        let identity = match (&self.tls_cert, &self.tls_key) {
            (Some(c), Some(k)) => Some((read("--tls-cert", c)?, read("--tls-key", k)?)),
            _ => None,
        };
        Ok(Some(link::ClientTls { ca: read("--tls-ca", ca)?, identity }))
    }
}

/// Where the camera's intrinsics come from (`stream` and `fleet`).
#[derive(clap::Args)]
struct CalibrationArgs {
    /// Camera calibration file: ROS camera_info YAML, OpenCV FileStorage YAML
    /// (camera_matrix, distortion_coefficients, image_width/height) or ORB-SLAM
    /// settings. Its intrinsics win over --camera's and the source's own.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// A camera whose calibration stillmap knows (tum-fr1, tum-fr2, tum-fr3):
    /// intrinsics and timing. Unset for a TUM folder: the folder's own name says.
    #[arg(long)]
    camera: Option<KnownCamera>,
    /// Track with nominal intrinsics when the source's calibration is not known
    /// (a TUM folder whose name names no freiburg camera, an OpenNI2 device that
    /// reports no field of view) instead of refusing to start.
    #[arg(long)]
    allow_default_intrinsics: bool,
}

/// Which topics of an `mcap:` or `rosbag:` recording to read (unset: the one topic of each kind).
#[derive(clap::Args)]
struct TopicArgs {
    /// Colour images (sensor_msgs/msg/Image rgb8 or bgr8, or CompressedImage).
    #[arg(long)]
    color_topic: Option<String>,
    /// Depth images (sensor_msgs/msg/Image 16UC1 in mm or 32FC1 in m), registered to colour.
    #[arg(long)]
    depth_topic: Option<String>,
    /// sensor_msgs/msg/CameraInfo of the colour camera (its calibration).
    #[arg(long)]
    camera_info_topic: Option<String>,
    /// sensor_msgs/msg/Imu in the colour camera's frame (its accelerometer).
    #[arg(long)]
    imu_topic: Option<String>,
}

impl From<CalibrationArgs> for CameraOptions {
    fn from(a: CalibrationArgs) -> Self {
        Self { calibration: a.calibration, camera: a.camera, allow_default_intrinsics: a.allow_default_intrinsics }
    }
}

#[derive(Subcommand)]
enum Command {
    /// Stream a source to the server and print a summary.
    Stream {
        /// tum:<dir> (a TUM RGB-D folder), mcap:<file> (a ROS 2 recording), rosbag:<file> (a
        /// ROS 1 bag), openni2 (first device) or openni2:<uri> (e.g. openni2:Dummy).
        #[arg(long)]
        source: SourceSpec,
        #[command(flatten)]
        topics: TopicArgs,
        #[arg(long, value_enum, default_value = "grpc")]
        transport: TransportArg,
        #[command(flatten)]
        endpoints: EndpointArgs,
        #[arg(long, env = "STILLMAP_ROBOT_ID", default_value = "robot1")]
        robot_id: String,
        /// The fleet to map with (one shared world frame); default: the server's default fleet.
        #[arg(long, env = "STILLMAP_FLEET")]
        fleet: Option<String>,
        #[arg(long, env = "STILLMAP_TOKEN", default_value = "")]
        token: String,
        /// realtime, max, or a rate in Hz.
        #[arg(long, default_value = "realtime")]
        rate: Rate,
        /// Stop after this many frames.
        #[arg(long)]
        max_frames: Option<usize>,
        #[arg(long, default_value_t = 90, value_parser = clap::value_parser!(u8).range(1..=100))]
        jpeg_quality: u8,
        #[arg(long, value_enum, default_value = "jpeg")]
        color_codec: ColorArg,
        /// Lossless depth codec; zstd is the default by measurement (README, bench-codecs).
        #[arg(long, value_enum, default_value = "zstd")]
        depth_codec: DepthArg,
        /// Frames sent but not yet answered, at most.
        #[arg(long, default_value_t = 8)]
        max_in_flight: usize,
        /// The colour camera's rolling-shutter readout in milliseconds (first row to
        /// last; 0 = global shutter), sent in the hello so the tracker models it.
        /// Unset: what the source says (25 ms for TUM freiburg1, 0 for other TUM
        /// recordings and OpenNI2 devices).
        #[arg(long)]
        rolling_shutter_ms: Option<f64>,
        /// When the image was exposed relative to the frame's timestamp, in
        /// milliseconds (for a rolling shutter, the middle row's; negative when the
        /// timestamp is taken after the exposure), so poses carry the time they refer
        /// to. Unset: what the source says (-12.5 for TUM freiburg1, whose driver
        /// stamps a frame when it arrives; 0 otherwise), also when
        /// --rolling-shutter-ms overrides the readout.
        #[arg(long, allow_negative_numbers = true)]
        exposure_offset_ms: Option<f64>,
        #[command(flatten)]
        calibration: CalibrationArgs,
        /// Reconnection attempts (gRPC) before giving up.
        #[arg(long, default_value_t = 10)]
        reconnect_attempts: u32,
        /// Seconds without any result while frames wait for theirs before the gRPC
        /// link gives up on the stream and reconnects (resuming the session).
        #[arg(long, default_value_t = 15.0)]
        result_timeout: f64,
        /// Seconds to wait for the server (Zenoh hello, late results; gRPC connect).
        #[arg(long, default_value_t = 10.0)]
        timeout: f64,
        /// Write the returned poses here in TUM format.
        #[arg(long)]
        trajectory: Option<PathBuf>,
        /// Write the summary here as JSON.
        #[arg(long)]
        summary_json: Option<PathBuf>,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Load generator: N robots from one process, each its own session and link,
    /// replaying a TUM recording in a ping-pong loop from its own offset; prints a
    /// table per robot, the totals and the server's time per stage.
    Fleet {
        /// Robots to run, each its own session, link and robot id.
        #[arg(long, default_value_t = 3)]
        robots: usize,
        /// tum:<dir>, read and encoded once.
        #[arg(long)]
        source: SourceSpec,
        /// A rate in Hz, realtime (the camera's nominal rate) or max.
        #[arg(long, default_value = "30")]
        rate: Rate,
        /// Seconds every robot sends frames (then the last results are awaited).
        #[arg(long, default_value_t = 20.0)]
        duration: f64,
        /// How the robots reach the server.
        #[arg(long, value_enum, default_value = "grpc")]
        transport: FleetTransportArg,
        #[command(flatten)]
        endpoints: EndpointArgs,
        /// The server's HTTP address, for its per-stage times from /metrics ("" skips them).
        #[arg(long, env = "STILLMAP_HTTP", default_value = "http://127.0.0.1:8080")]
        http: String,
        /// Robot ids are <prefix>-01, <prefix>-02, ...
        #[arg(long, default_value = "fleet")]
        robot_prefix: String,
        /// The bearer token every robot's hello carries.
        #[arg(long, env = "STILLMAP_TOKEN", default_value = "")]
        token: String,
        /// Frames sent but not yet answered, per robot, at most.
        #[arg(long, default_value_t = 8)]
        max_in_flight: usize,
        /// Frames of the recording to load (default: all).
        #[arg(long)]
        max_frames: Option<usize>,
        #[command(flatten)]
        calibration: CalibrationArgs,
        /// Seconds to wait for the server (connect, Zenoh hello, late results).
        #[arg(long, default_value_t = 10.0)]
        timeout: f64,
        /// Write the whole report here as JSON.
        #[arg(long)]
        summary_json: Option<PathBuf>,
    },
    /// Measure the depth codecs and JPEG on real TUM frames; print a Markdown table.
    BenchCodecs {
        /// A TUM RGB-D folder.
        #[arg(long)]
        tum: PathBuf,
        #[arg(long, default_value_t = 150)]
        frames: usize,
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        #[arg(long, default_value_t = 90)]
        jpeg_quality: u8,
    },
    /// List the stillmap servers live on a Zenoh network and their load (their
    /// liveliness tokens and status queryables, stillmap-cluster/servers/*).
    #[cfg(feature = "zenoh")]
    Servers {
        /// Zenoh endpoints to connect to (a router's, or a server's).
        #[arg(long, env = "STILLMAP_ZENOH_CONNECT", value_delimiter = ',', default_value = "tcp/127.0.0.1:7447")]
        zenoh_connect: Vec<String>,
        /// Zenoh mode: peer or client.
        #[arg(long, default_value = "client")]
        zenoh_mode: String,
        /// A Zenoh configuration file (JSON5: TLS, mTLS); replaces --zenoh-connect and --zenoh-mode.
        #[arg(long, env = "STILLMAP_ZENOH_CONFIG")]
        zenoh_config: Option<PathBuf>,
        /// Seconds to wait for the network and for the servers' replies.
        #[arg(long, default_value_t = 2.0)]
        timeout_s: f64,
        /// Print JSON (an array of the servers' statuses) instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Evaluate an estimated trajectory against a reference (TUM files), as evo_ape / evo_rpe do.
    Eval {
        #[arg(value_enum)]
        metric: MetricArg,
        /// Reference (ground truth) trajectory, TUM format.
        reference: PathBuf,
        /// Estimated trajectory, TUM format.
        estimate: PathBuf,
        /// Align the estimate with SE(3) Umeyama first (evo -a).
        #[arg(long, conflicts_with = "align_origin")]
        align: bool,
        /// Move the first estimated pose onto the first reference pose (evo --align_origin).
        #[arg(long)]
        align_origin: bool,
        /// Only this relation (default: both).
        #[arg(long, value_enum)]
        relation: Option<RelationArg>,
        /// RPE: frames between the poses of a pair (consecutive pairs, like evo).
        #[arg(long)]
        delta: Option<usize>,
        /// Largest timestamp difference of associated poses, seconds.
        #[arg(long, default_value_t = eval::DEFAULT_MAX_DIFF_S)]
        t_max_diff: f64,
        /// Added to the estimate's timestamps before association, seconds.
        #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
        t_offset: f64,
        /// Write the result here as JSON.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Plot the trajectories here (.png or .svg).
        #[arg(long)]
        plot: Option<PathBuf>,
    },
}

#[tokio::main]
async fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_env("STILLMAP_LOG").unwrap_or_else(|_| "warn,zenoh=error".into()))
        .with_writer(std::io::stderr)
        .init();
    match run(Cli::parse()).await {
        Ok(code) => code,
        Err(e) => {
            eprintln!("stillmap-client: {e:#}");
            ExitCode::from(1)
        }
    }
}

async fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        #[cfg(feature = "zenoh")]
        Command::Servers { zenoh_connect, zenoh_mode, zenoh_config, timeout_s, json } => {
            if !(timeout_s.is_finite() && timeout_s > 0.0 && timeout_s <= 3600.0) {
                anyhow::bail!("--timeout-s must be a positive number of seconds up to 3600, got {timeout_s}");
            }
            let options = ZenohOptions {
                connect: zenoh_connect,
                mode: zenoh_mode,
                timeout: std::time::Duration::from_secs_f64(timeout_s),
                config_file: zenoh_config,
            };
            let servers = stillmap_client::servers::list(&options).await?;
            if json {
                let all: Vec<serde_json::Value> = servers
                    .iter()
                    .map(|s| s.status.clone().unwrap_or_else(|| serde_json::json!({ "server_id": s.server_id, "status": null })))
                    .collect();
                println!("{}", serde_json::to_string_pretty(&all)?);
            } else {
                print!("{}", stillmap_client::servers::table(&servers));
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::BenchCodecs { tum, frames, repeats, jpeg_quality } => {
            let rows = tokio::task::spawn_blocking(move || bench::bench_codecs(&tum, frames, repeats, jpeg_quality)).await??;
            print!("{}", bench::table(&rows, frames));
            Ok(ExitCode::SUCCESS)
        }
        Command::Stream {
            mut source,
            topics,
            transport,
            endpoints,
            robot_id,
            fleet,
            token,
            rate,
            max_frames,
            jpeg_quality,
            color_codec,
            depth_codec,
            max_in_flight,
            reconnect_attempts,
            result_timeout,
            timeout,
            trajectory,
            summary_json,
            quiet,
            rolling_shutter_ms,
            exposure_offset_ms,
            calibration,
        } => {
            stillmap_proto::validate_robot_id(&robot_id).map_err(ClientError::Usage)?;
            let named = [&topics.color_topic, &topics.depth_topic, &topics.camera_info_topic, &topics.imu_topic];
            match &mut source {
                SourceSpec::Bag(_, _, t) => {
                    *t = stillmap_client::bag::BagTopics {
                        color: topics.color_topic,
                        depth: topics.depth_topic,
                        camera_info: topics.camera_info_topic,
                        imu: topics.imu_topic,
                    }
                }
                _ if named.iter().any(|t| t.is_some()) => {
                    return Err(ClientError::Usage(
                        "--color-topic, --depth-topic, --camera-info-topic and --imu-topic are for mcap: and rosbag: sources".into(),
                    )
                    .into());
                }
                _ => {}
            }
            if let Some(f) = &fleet {
                stillmap_proto::validate_fleet(f).map_err(ClientError::Usage)?;
            }
            if let Some(ms) = rolling_shutter_ms
                && !(0.0..=stillmap_proto::MAX_ROLLING_SHUTTER_READOUT_S * 1e3).contains(&ms)
            {
                return Err(ClientError::Usage(format!(
                    "--rolling-shutter-ms {ms} is outside 0..={}",
                    stillmap_proto::MAX_ROLLING_SHUTTER_READOUT_S * 1e3
                ))
                .into());
            }
            let max_offset_ms = stillmap_proto::MAX_EXPOSURE_TIME_OFFSET_S * 1e3;
            if let Some(ms) = exposure_offset_ms
                && !(-max_offset_ms..=max_offset_ms).contains(&ms)
            {
                return Err(ClientError::Usage(format!("--exposure-offset-ms {ms} is outside -{max_offset_ms}..={max_offset_ms}")).into());
            }
            if max_in_flight == 0 {
                return Err(ClientError::Usage("--max-in-flight must be at least 1".into()).into());
            }
            let timeout = positive_seconds("--timeout", timeout)?;
            let options = StreamOptions {
                robot_id,
                fleet: fleet.unwrap_or_default(),
                auth_token: token,
                source,
                max_frames,
                rate,
                jpeg_quality,
                color_encoding: match color_codec {
                    ColorArg::Jpeg => ColorEncoding::Jpeg,
                    ColorArg::Png => ColorEncoding::Png,
                    ColorArg::Rgb8 => ColorEncoding::Rgb8,
                },
                depth_encoding: match depth_codec {
                    DepthArg::Rvl => DepthEncoding::Rvl,
                    DepthArg::Png16 => DepthEncoding::Png16,
                    DepthArg::Zstd => DepthEncoding::Zstd,
                },
                max_in_flight,
                progress: !quiet && std::io::IsTerminal::is_terminal(&std::io::stderr()),
                rolling_shutter_readout_s: rolling_shutter_ms.map(|ms| ms * 1e-3),
                exposure_time_offset_s: exposure_offset_ms.map(|ms| ms * 1e-3),
                camera: calibration.into(),
            };
            let summary = match transport {
                TransportArg::Grpc => {
                    let grpc = GrpcOptions {
                        tls: endpoints.tls()?,
                        servers: endpoints.server,
                        keepalive: Duration::from_secs(10),
                        connect_timeout: timeout,
                        initial_backoff: Duration::from_millis(100),
                        max_backoff: Duration::from_secs(5),
                        max_attempts: reconnect_attempts,
                        result_timeout: positive_seconds("--result-timeout", result_timeout)?,
                    };
                    streamer::run(&options, "grpc", |hello| link::start_grpc(hello, grpc)).await?
                }
                #[cfg(feature = "zenoh")]
                TransportArg::Zenoh => {
                    let z = ZenohOptions {
                        connect: endpoints.zenoh_connect,
                        mode: endpoints.zenoh_mode,
                        timeout,
                        config_file: endpoints.zenoh_config,
                    };
                    streamer::run(&options, "zenoh", |hello| link::start_zenoh(hello, z)).await?
                }
                #[cfg(not(feature = "zenoh"))]
                TransportArg::Zenoh => {
                    let _ = (endpoints, ZenohOptions::clone);
                    return Err(ClientError::Usage("this client was built without the zenoh feature".into()).into());
                }
            };
            println!("{}", summary.report());
            if let Some(path) = trajectory {
                std::fs::write(&path, summary.tum_trajectory()).map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))?;
            }
            if let Some(path) = summary_json {
                std::fs::write(&path, serde_json::to_string_pretty(&summary)?)
                    .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))?;
            }
            // Not clean: a frame the server refused, a depth that came back changed, a
            // frame too large to send, or nothing sent. (A result a reconnect lost is
            // not: the resumed session received that frame once.)
            let clean =
                summary.frames_rejected == 0 && summary.depth_mismatch == 0 && summary.frames_too_large == 0 && summary.frames_sent > 0;
            Ok(if clean { ExitCode::SUCCESS } else { ExitCode::from(2) })
        }
        Command::Fleet {
            robots,
            source,
            rate,
            duration,
            transport,
            endpoints,
            http,
            robot_prefix,
            token,
            max_in_flight,
            max_frames,
            calibration,
            timeout,
            summary_json,
        } => {
            let SourceSpec::Tum(tum) = source else {
                return Err(ClientError::Usage("fleet replays a recording: --source tum:<dir>".into()).into());
            };
            let duration = positive_seconds("--duration", duration)?;
            let timeout = positive_seconds("--timeout", timeout)?;
            let options = FleetOptions {
                robots,
                tum,
                camera: calibration.into(),
                max_frames,
                rate,
                duration,
                transport: match transport {
                    FleetTransportArg::Grpc => FleetTransport::Grpc,
                    FleetTransportArg::Zenoh => FleetTransport::Zenoh,
                    FleetTransportArg::Mixed => FleetTransport::Mixed,
                },
                grpc: GrpcOptions {
                    tls: endpoints.tls()?,
                    servers: endpoints.server.clone(),
                    keepalive: Duration::from_secs(10),
                    connect_timeout: timeout,
                    initial_backoff: Duration::from_millis(100),
                    max_backoff: Duration::from_secs(5),
                    max_attempts: 10,
                    result_timeout: Duration::from_secs(15),
                },
                zenoh: ZenohOptions {
                    connect: endpoints.zenoh_connect,
                    mode: endpoints.zenoh_mode,
                    timeout,
                    config_file: endpoints.zenoh_config,
                },
                http: (!http.is_empty()).then_some(http),
                robot_prefix,
                token,
                max_in_flight,
            };
            let report = fleet::run(&options).await?;
            print!("{}", report.table());
            if let Some(path) = summary_json {
                std::fs::write(&path, serde_json::to_string_pretty(&report)?)
                    .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))?;
            }
            let t = &report.total;
            let clean = t.robots_failed == 0 && t.frames_rejected == 0 && t.frames_unanswered == 0;
            Ok(if clean { ExitCode::SUCCESS } else { ExitCode::from(2) })
        }
        Command::Eval { metric, reference, estimate, align, align_origin, relation, delta, t_max_diff, t_offset, json, plot } => {
            let metric = match (metric, delta) {
                (MetricArg::Ape, Some(_)) => Err(ClientError::Usage("--delta applies to rpe only".into()))?,
                (MetricArg::Ape, None) => Metric::Ape,
                (MetricArg::Rpe, delta) => Metric::Rpe { delta: delta.unwrap_or(eval::DEFAULT_DELTA) },
            };
            let relations = match relation {
                None => vec![Relation::Translation, Relation::RotationDeg],
                Some(RelationArg::Trans) => vec![Relation::Translation],
                Some(RelationArg::Rot) => vec![Relation::RotationDeg],
            };
            let alignment = match (align, align_origin) {
                (true, _) => Alignment::Se3,
                (false, true) => Alignment::Origin,
                (false, false) => Alignment::None,
            };
            let options = EvalOptions { metric, alignment, relations, max_diff: t_max_diff, offset: t_offset };
            let args = eval::RunArgs { reference, estimate, options, json, plot };
            print!("{}", eval::run(&args)?);
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// The longest time a flag may name: 30 days (longer, the clock's arithmetic would
/// overflow; no run waits that long).
const MAX_FLAG_SECONDS: f64 = 30.0 * 86_400.0;

/// `seconds` as a positive duration up to [`MAX_FLAG_SECONDS`], or the usage error
/// naming `flag`.
fn positive_seconds(flag: &str, seconds: f64) -> Result<Duration, ClientError> {
    Some(seconds)
        .filter(|s| *s > 0.0 && *s <= MAX_FLAG_SECONDS)
        .and_then(|s| Duration::try_from_secs_f64(s).ok())
        .filter(|d| !d.is_zero())
        .ok_or_else(|| ClientError::Usage(format!("{flag} {seconds} is not a positive number of seconds up to {MAX_FLAG_SECONDS}")))
}
