//! ROS recordings: `--source mcap:FILE` (ROS 2, read with Foxglove's `mcap` crate,
//! messages decoded from CDR with `cdr-encoding`) and `--source rosbag:FILE` (ROS 1
//! bags such as TUM's and Bonn's own downloads, read with `rosbag`, messages
//! decoded with rosrust's `serde_rosmsg`) stream `sensor_msgs` `Image` (or
//! `CompressedImage`) colour, `Image` depth (`16UC1` millimetres or `32FC1` metres),
//! `CameraInfo` for the calibration and `Imu` for the accelerometer.
//!
//! Two passes over the file, each streaming (memory is one chunk and the frames
//! waiting for their other half, not the file): the first lists the topics and
//! every image's timestamp, pairs colour with depth exactly as the TUM source does
//! (`stillmap_dataset::tum::associate`, 20 ms) and keeps the camera info and accelerometer samples;
//! the second, on a reader thread, decodes the paired images in order and hands
//! frames over a bounded channel.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use serde::Deserialize;
use stillmap_proto::codec::{self, ColorImage, DepthImage};
use stillmap_proto::pb::{self, DistortionModel};

use crate::ClientError;
use crate::calibration::{CameraOptions, KnownCamera, SourceCamera};
use crate::source::{FrameSource, RawFrame};

/// Which topics hold what; `None`: the one topic of the right kind (an error listing
/// the file's topics when there are several or none).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BagTopics {
    pub color: Option<String>,
    pub depth: Option<String>,
    pub camera_info: Option<String>,
    pub imu: Option<String>,
}

const IMAGE: &str = "sensor_msgs/msg/Image";
const COMPRESSED: &str = "sensor_msgs/msg/CompressedImage";
const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";
const IMU: &str = "sensor_msgs/msg/Imu";

/// Depth in `32FC1` metres becomes 16-bit depth at this scale (0.2 mm; up to 13 m),
/// TUM's own: a TUM recording converted to metres comes back to the same integers.
const FLOAT_DEPTH_UNITS_PER_METRE: f64 = 5000.0;
/// Images read ahead of their pair, at most (colour and depth of one frame lie close
/// together in a recording; a file where they do not is refused, not buffered).
const MAX_PENDING_IMAGES: usize = 64;
/// Accelerometer samples kept (about 3 h at 100 Hz).
const MAX_IMU_SAMPLES: usize = 1 << 20;

#[derive(Deserialize)]
struct Time {
    sec: i32,
    nanosec: u32,
}

#[derive(Deserialize)]
struct Header {
    stamp: Time,
    frame_id: String,
}

impl Header {
    fn stamp_ns(&self) -> Option<u64> {
        u64::try_from(self.stamp.sec).ok().map(|s| s * 1_000_000_000 + u64::from(self.stamp.nanosec))
    }
}

// The messages after their `std_msgs/Header` (decoded on its own: ROS 1's differs).

/// The leading fields of an `Image` (what the first pass needs).
#[derive(Deserialize)]
struct ImageHead {
    height: u32,
    width: u32,
    encoding: String,
}

#[derive(Deserialize)]
struct Image {
    height: u32,
    width: u32,
    encoding: String,
    is_bigendian: u8,
    step: u32,
    data: Vec<u8>,
}

#[derive(Deserialize)]
struct CompressedImage {
    format: String,
    data: Vec<u8>,
}

#[derive(Deserialize)]
struct CameraInfo {
    height: u32,
    width: u32,
    distortion_model: String,
    d: Vec<f64>,
    k: [f64; 9],
}

#[derive(Deserialize)]
struct Vector3 {
    x: f64,
    y: f64,
    z: f64,
}

#[derive(Deserialize)]
struct Imu {
    _orientation: [f64; 4],
    _orientation_covariance: [f64; 9],
    _angular_velocity: Vector3,
    _angular_velocity_covariance: [f64; 9],
    linear_acceleration: Vector3,
}

/// A ROS 2 message from its CDR bytes (the 4-byte encapsulation header, then the body).
fn decode<'de, T: Deserialize<'de>>(bytes: &'de [u8], what: &str) -> Result<T, ClientError> {
    let bad = |m: String| ClientError::Source(format!("{what}: {m}"));
    let (head, body) = bytes.split_at_checked(4).ok_or_else(|| bad("shorter than its CDR header".into()))?;
    let result = match head[..2] {
        [0, 1] => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body),
        [0, 0] => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body),
        _ => return Err(bad(format!("not plain CDR (encapsulation {:02x}{:02x})", head[0], head[1]))),
    };
    result.map(|(v, _)| v).map_err(|e| bad(format!("bad CDR: {e}")))
}

/// How a file's messages are serialized.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BagFormat {
    /// ROS 2 in MCAP (CDR).
    Mcap,
    /// ROS 1 bag (ROS 1 serialization).
    Ros1,
}

#[derive(Deserialize)]
struct Time1 {
    sec: u32,
    nsec: u32,
}

#[derive(Deserialize)]
struct Header1 {
    _seq: u32,
    stamp: Time1,
    frame_id: String,
}

impl From<Header1> for Header {
    fn from(h: Header1) -> Self {
        // ROS 1 stamps are unsigned; seconds beyond i32 are out of any recording's range.
        Self { stamp: Time { sec: i32::try_from(h.stamp.sec).unwrap_or(-1), nanosec: h.stamp.nsec }, frame_id: h.frame_id }
    }
}

/// A ROS 1 message from its bytes (no length prefix in a bag's message records).
fn decode1<'de, T: Deserialize<'de>>(bytes: &[u8], what: &str) -> Result<T, ClientError> {
    let length = u32::try_from(bytes.len()).map_err(|_| ClientError::Source(format!("{what}: larger than 4 GiB")))?;
    let mut de = serde_rosmsg::de::Deserializer::new(std::io::Cursor::new(bytes), length);
    T::deserialize(&mut de).map_err(|e| ClientError::Source(format!("{what}: bad ROS 1 message: {e}")))
}

/// A message of the file's format: its header (as ROS 2's) and what follows it. Both
/// serializations lay a message's fields out in order (CDR aligns them from the
/// start), so the pair reads the same bytes as the whole message would.
fn message<B: serde::de::DeserializeOwned>(format: BagFormat, bytes: &[u8], what: &str) -> Result<(Header, B), ClientError> {
    match format {
        BagFormat::Mcap => decode(bytes, what),
        BagFormat::Ros1 => decode1::<(Header1, B)>(bytes, what).map(|(h, b)| (h.into(), b)),
    }
}

/// ROS 1 type names (`sensor_msgs/Image`) as ROS 2's (`sensor_msgs/msg/Image`).
fn ros2_name(ros1: &str) -> String {
    match ros1.split_once('/') {
        Some((package, name)) if !name.contains('/') => format!("{package}/msg/{name}"),
        _ => ros1.to_string(),
    }
}

/// Sees one message (topic, schema, bytes); `false` stops the reading.
type Visitor<'a> = dyn FnMut(&str, &str, &[u8]) -> Result<bool, ClientError> + 'a;

/// Calls `f(topic, schema, bytes)` for every message of the file in file order, until
/// it returns `false`; messages in encodings other than the format's are skipped.
fn visit(path: &Path, format: BagFormat, f: &mut Visitor<'_>) -> Result<(), ClientError> {
    let bad = |e: String| ClientError::Source(format!("{}: {e}", path.display()));
    match format {
        BagFormat::Mcap => {
            for message in open_reader(path)? {
                let message = message.map_err(|e| bad(format!("not a readable MCAP file: {e}")))?;
                if message.channel.message_encoding != "cdr" {
                    continue;
                }
                let schema = message.channel.schema.as_ref().map(|s| s.name.as_str()).unwrap_or_default();
                if !f(&message.channel.topic, schema, &message.data)? {
                    break;
                }
            }
        }
        BagFormat::Ros1 => {
            check_ros1_records(path).map_err(|e| bad(format!("not a readable ROS 1 bag: {e}")))?;
            let bag = rosbag::RosBag::new(path).map_err(|e| bad(format!("not a readable ROS 1 bag: {e}")))?;
            let mut connections: HashMap<u32, (String, String)> = HashMap::new();
            for record in bag.chunk_records() {
                let rosbag::ChunkRecord::Chunk(chunk) = record.map_err(|e| bad(format!("not a readable ROS 1 bag: {e}")))? else {
                    continue;
                };
                for message in chunk.messages() {
                    match message.map_err(|e| bad(format!("bad chunk: {e}")))? {
                        rosbag::MessageRecord::Connection(c) => {
                            connections.insert(c.id, (c.topic.to_string(), ros2_name(c.tp)));
                        }
                        rosbag::MessageRecord::MessageData(m) => {
                            let Some((topic, schema)) = connections.get(&m.conn_id) else {
                                return Err(bad(format!("a message on connection {} before its connection record", m.conn_id)));
                            };
                            if !f(topic, schema, m.data)? {
                                return Ok(());
                            }
                        }
                    }
                }
            }
        }
    }
    Ok(())
}

/// What the first pass saw of one topic.
#[derive(Debug, Default)]
struct TopicStats {
    schema: String,
    messages: u64,
    /// `Image`: the first message's encoding.
    encoding: Option<String>,
}

pub struct BagSource {
    camera: pb::CameraInfo,
    frames: usize,
    /// Frames from the reader thread (started by the first `next_frame`).
    reader: Option<std::sync::mpsc::Receiver<Result<RawFrame, ClientError>>>,
    /// What the reader thread needs: the file, its format, the colour and depth
    /// topics and the pairs (colour ordinal, depth ordinal, time, accelerometer).
    plan: Option<ReadPlan>,
}

struct ReadPlan {
    path: PathBuf,
    format: BagFormat,
    topics: (String, String),
    pairs: Vec<(usize, usize, u64, Option<[f64; 3]>)>,
    camera: pb::CameraInfo,
}

/// Frames decoded ahead of the streamer, at most.
const READ_AHEAD_FRAMES: usize = 4;

/// The longest record (an MCAP record, a ROS 1 chunk uncompressed) the reader takes:
/// above any camera frame the server accepts (an 8192 × 8192 RGB image is 192 MiB),
/// far below what a corrupt length field asks for (the reader allocates it).
const MAX_RECORD_BYTES: u64 = 256 << 20;
/// The longest ROS 1 record header: field lists and message definitions.
const MAX_ROS1_HEADER_BYTES: u64 = 16 << 20;
/// A ROS 1 bag's first line.
const ROS1_MAGIC: &[u8] = b"#ROSBAG V2.0\n";

fn open_reader(path: &Path) -> Result<mcap::io::MessageReader<BufReader<File>>, ClientError> {
    let file = File::open(path).map_err(|e| ClientError::Source(format!("{}: {e}", path.display())))?;
    let options = mcap::sans_io::LinearReaderOptions::default().with_record_length_limit(MAX_RECORD_BYTES as usize);
    Ok(mcap::io::MessageReader::new_with_options(BufReader::new(file), options))
}

/// Checks a ROS 1 bag's top-level records before `rosbag` reads them: `rosbag`
/// allocates a chunk's declared uncompressed size before decompressing it, so a
/// chunk declaring more than [`MAX_RECORD_BYTES`] (or a record running past the
/// file's end) is an error here. Only the headers are read; data is skipped.
fn check_ros1_records(path: &Path) -> Result<(), String> {
    let file = File::open(path).map_err(|e| e.to_string())?;
    let len = file.metadata().map_err(|e| e.to_string())?.len();
    let mut file = BufReader::new(file);
    let mut magic = [0u8; ROS1_MAGIC.len()];
    if file.read_exact(&mut magic).is_err() || magic != ROS1_MAGIC {
        return Ok(()); // not a ROS 1 bag: rosbag says so
    }
    let read_u32 = |file: &mut BufReader<File>| -> Result<u64, String> {
        let mut b = [0u8; 4];
        file.read_exact(&mut b).map_err(|e| e.to_string())?;
        Ok(u64::from(u32::from_le_bytes(b)))
    };
    let mut pos = ROS1_MAGIC.len() as u64;
    while pos < len {
        let header_len = read_u32(&mut file)?;
        if header_len > MAX_ROS1_HEADER_BYTES || pos + 8 + header_len > len {
            return Err(format!(
                "record at byte {pos} declares a header of {header_len} bytes, past the file's end or over {MAX_ROS1_HEADER_BYTES}"
            ));
        }
        let mut header = vec![0u8; header_len as usize];
        file.read_exact(&mut header).map_err(|e| e.to_string())?;
        let data_len = read_u32(&mut file)?;
        let end = pos + 8 + header_len + data_len;
        if end > len {
            return Err(format!("record at byte {pos} declares {data_len} bytes of data, past the file's end"));
        }
        let (mut op, mut size) = (None, None);
        let mut fields = header.as_slice();
        while let Some((field_len, rest)) = fields.split_first_chunk::<4>() {
            let field_len = u32::from_le_bytes(*field_len) as usize;
            let Some((field, rest)) = rest.split_at_checked(field_len) else { break };
            fields = rest;
            match field.iter().position(|&c| c == b'=').map(|at| field.split_at(at)) {
                Some((b"op", [_, value])) => op = Some(*value),
                Some((b"size", [_, value @ ..])) if value.len() == 4 => size = value.try_into().ok().map(u32::from_le_bytes),
                _ => {}
            }
        }
        if op == Some(0x05)
            && let Some(size) = size
            && u64::from(size) > MAX_RECORD_BYTES
        {
            return Err(format!(
                "chunk at byte {pos} declares {size} bytes uncompressed, more than the {MAX_RECORD_BYTES} this reader takes"
            ));
        }
        file.seek(SeekFrom::Start(end)).map_err(|e| e.to_string())?;
        pos = end;
    }
    Ok(())
}

/// The topic the user named, or the only one of the kind `fits` accepts.
fn pick(
    named: &Option<String>,
    what: &str,
    stats: &BTreeMap<String, TopicStats>,
    fits: impl Fn(&TopicStats) -> bool,
) -> Result<Option<String>, String> {
    if let Some(t) = named {
        return match stats.get(t) {
            Some(s) if fits(s) => Ok(Some(t.clone())),
            Some(s) => Err(format!("topic {t} holds {} (encoding {}), not {what}", s.schema, s.encoding.as_deref().unwrap_or("-"))),
            None => Err(format!("no topic {t}")),
        };
    }
    let found: Vec<&String> = stats.iter().filter(|(_, s)| fits(s)).map(|(t, _)| t).collect();
    match found.as_slice() {
        [] => Ok(None),
        [one] => Ok(Some((*one).clone())),
        many => Err(format!("several topics hold {what} ({}): name one", many.iter().map(|t| t.as_str()).collect::<Vec<_>>().join(", "))),
    }
}

fn listing(stats: &BTreeMap<String, TopicStats>) -> String {
    let rows: Vec<String> = stats
        .iter()
        .map(|(t, s)| {
            format!("{t} ({}, {} messages{})", s.schema, s.messages, s.encoding.as_ref().map(|e| format!(", {e}")).unwrap_or_default())
        })
        .collect();
    if rows.is_empty() { "no messages".into() } else { rows.join("; ") }
}

fn is_depth_encoding(e: &str) -> bool {
    matches!(e, "16UC1" | "mono16" | "32FC1")
}

impl BagSource {
    pub fn open(
        path: &Path,
        format: BagFormat,
        topics: &BagTopics,
        max_frames: Option<usize>,
        options: &CameraOptions,
    ) -> Result<Self, ClientError> {
        let source_error = |m: String| ClientError::Source(format!("{}: {m}", path.display()));
        // First pass: the topics, every image's stamp, the calibration, the accelerometer.
        let mut stats: BTreeMap<String, TopicStats> = BTreeMap::new();
        let mut stamps: HashMap<String, Vec<u64>> = HashMap::new();
        let mut infos: HashMap<String, (Header, CameraInfo)> = HashMap::new();
        let mut imu_samples: HashMap<String, Vec<(u64, [f64; 3], String)>> = HashMap::new();
        let mut image_frames: HashMap<String, String> = HashMap::new();
        visit(path, format, &mut |topic, schema, data| {
            let entry = stats.entry(topic.to_string()).or_insert_with(|| TopicStats { schema: schema.to_string(), ..Default::default() });
            entry.messages += 1;
            let what = format!("{topic} message {}", entry.messages);
            let negative = || source_error(format!("{what}: negative time stamp"));
            match schema {
                IMAGE => {
                    let (header, head) = message::<ImageHead>(format, data, &what)?;
                    entry.encoding.get_or_insert(head.encoding);
                    stamps.entry(topic.to_string()).or_default().push(header.stamp_ns().ok_or_else(negative)?);
                    image_frames.entry(topic.to_string()).or_insert(header.frame_id);
                }
                COMPRESSED => {
                    let (header, ()) = message::<()>(format, data, &what)?;
                    stamps.entry(topic.to_string()).or_default().push(header.stamp_ns().ok_or_else(negative)?);
                    image_frames.entry(topic.to_string()).or_insert(header.frame_id);
                }
                CAMERA_INFO if !infos.contains_key(topic) => {
                    infos.insert(topic.to_string(), message::<CameraInfo>(format, data, &what)?);
                }
                IMU => {
                    let (header, Imu { linear_acceleration: a, .. }) = message(format, data, &what)?;
                    let samples = imu_samples.entry(topic.to_string()).or_default();
                    if samples.len() >= MAX_IMU_SAMPLES {
                        return Err(source_error(format!("{topic}: more than {MAX_IMU_SAMPLES} IMU samples")));
                    }
                    // A sample without a time or with a non-finite reading is left out
                    // (the frames near it take the next nearest).
                    if let Some(t) = header.stamp_ns()
                        && [a.x, a.y, a.z].iter().all(|v| v.is_finite())
                    {
                        samples.push((t, [a.x, a.y, a.z], header.frame_id));
                    }
                }
                _ => {}
            }
            Ok(true)
        })?;
        let chosen = (|| -> Result<_, String> {
            let color = pick(&topics.color, "colour images", &stats, |s| {
                s.schema == COMPRESSED || (s.schema == IMAGE && !s.encoding.as_deref().is_some_and(is_depth_encoding))
            })?;
            let depth = pick(&topics.depth, "depth images (16UC1 or 32FC1)", &stats, |s| {
                s.schema == IMAGE && s.encoding.as_deref().is_some_and(is_depth_encoding)
            })?;
            let info = pick(&topics.camera_info, "camera info", &stats, |s| s.schema == CAMERA_INFO);
            // Several camera infos (colour and depth): the one beside the colour topic.
            let info = match (info, &color) {
                (Err(_), Some(c)) if topics.camera_info.is_none() => {
                    let parent = c.rsplit_once('/').map_or("", |(p, _)| p);
                    Ok(stats
                        .iter()
                        .find(|(t, s)| s.schema == CAMERA_INFO && t.starts_with(parent) && !parent.is_empty())
                        .map(|(t, _)| t.clone()))
                }
                (other, _) => other,
            }?;
            let imu = pick(&topics.imu, "IMU samples", &stats, |s| s.schema == IMU)?;
            Ok((color, depth, info, imu))
        })();
        let (color, depth, info_topic, imu_topic) =
            chosen.map_err(|m| source_error(format!("{m}; the file holds: {}", listing(&stats))))?;
        let (Some(color), Some(depth)) = (color, depth) else {
            return Err(source_error(format!(
                "needs a colour and a depth image topic (--color-topic, --depth-topic); the file holds: {}",
                listing(&stats)
            )));
        };
        let color_stamps = stamps.remove(&color).unwrap_or_default();
        let depth_stamps = stamps.remove(&depth).unwrap_or_default();
        let depth_encoding = stats.get(&depth).and_then(|s| s.encoding.clone()).unwrap_or_default();

        // The accelerometer when it is in the colour camera's frame (there is no TF
        // tree here), or when the camera is a Kinect the user named (`--camera
        // tum-fr1|tum-fr2`: TUM's own bags publish the Kinect's accelerometer in its
        // own axes, as their accelerometer.txt); otherwise it is left out.
        let color_frame = image_frames.get(&color).cloned().unwrap_or_default();
        let kinect = matches!(options.camera, Some(KnownCamera::TumFr1 | KnownCamera::TumFr2));
        let accel: Vec<(u64, [f64; 3])> = match imu_topic.and_then(|t| imu_samples.remove(&t).map(|s| (t, s))) {
            Some((t, samples)) => {
                let in_camera = samples.iter().all(|s| s.2 == color_frame);
                if !in_camera && !kinect {
                    tracing::warn!(
                        "{t} is not in the colour camera's frame {color_frame:?}; its accelerometer is left out (a Kinect's: --camera tum-fr1 or tum-fr2)"
                    );
                }
                let convert = |a: [f64; 3]| if in_camera { a } else { stillmap_dataset::tum::kinect_accel_to_camera(a) };
                let mut v: Vec<(u64, [f64; 3])> =
                    if in_camera || kinect { samples.into_iter().map(|s| (s.0, convert(s.1))).collect() } else { Vec::new() };
                v.sort_by_key(|s| s.0);
                v
            }
            None => Vec::new(),
        };
        let accel_ts: Vec<u64> = accel.iter().map(|a| a.0).collect();
        let mut pairs = Vec::new();
        for (i, j) in stillmap_dataset::tum::associate(&color_stamps, &depth_stamps, stillmap_dataset::tum::MAX_ASSOCIATION_NS) {
            let ts = color_stamps[i];
            let sample = stillmap_dataset::tum::nearest(&accel_ts, ts, stillmap_dataset::tum::MAX_ASSOCIATION_NS).map(|k| accel[k].1);
            pairs.push((i, j, ts, sample));
        }
        if pairs.is_empty() {
            return Err(source_error(format!("no {color} / {depth} pair within 20 ms")));
        }
        if let Some(max) = max_frames {
            pairs.truncate(max);
        }

        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let (scheme, kind) = match format {
            BagFormat::Mcap => ("mcap", "MCAP file"),
            BagFormat::Ros1 => ("rosbag", "ROS 1 bag"),
        };
        let first = infos.remove(info_topic.as_deref().unwrap_or_default());
        let source_camera = match first {
            // ROS's uncalibrated defaults (TUM's own bags carry them) are no calibration.
            Some((_, ci)) if is_ros_default(&ci) => SourceCamera {
                info: camera_from_info(&ci, &depth_encoding).map_err(source_error)?,
                known: None,
                what: format!("{kind} {name} ({} holds ROS's uncalibrated defaults)", info_topic.unwrap_or_default()),
            },
            Some((header, ci)) => SourceCamera {
                info: camera_from_info(&ci, &depth_encoding).map_err(source_error)?,
                known: Some(format!("{scheme}:{name} {} ({})", info_topic.unwrap_or_default(), header.frame_id)),
                what: format!("{kind} {name}"),
            },
            None => {
                // Size from the first colour image; nominal intrinsics, marked unknown.
                let (w, h) = first_size(path, format, &color)?;
                SourceCamera {
                    info: stillmap_dataset::calibration::nominal_camera_info(w, h, depth_units(&depth_encoding)),
                    known: None,
                    what: format!("{kind} {name} (no CameraInfo topic)"),
                }
            }
        };
        let camera = crate::calibration::resolve(source_camera, options)?;
        let plan = ReadPlan { path: path.to_path_buf(), format, topics: (color, depth), pairs, camera: camera.clone() };
        Ok(Self { camera, frames: plan.pairs.len(), reader: None, plan: Some(plan) })
    }
}

impl ReadPlan {
    fn decode_color(&self, data: &[u8], compressed_image: bool, what: &str) -> Result<ColorImage, ClientError> {
        let (w, h) = (self.camera.width, self.camera.height);
        let bad = |m: String| ClientError::Source(format!("{what}: {m}"));
        if compressed_image {
            let (_, m) = message::<CompressedImage>(self.format, data, what)?;
            let encoding = if m.format.contains("png") { pb::ColorEncoding::Png } else { pb::ColorEncoding::Jpeg };
            return codec::decode_color(encoding, &m.data, w, h).map_err(|e| bad(e.to_string()));
        }
        let (_, m) = message::<Image>(self.format, data, what)?;
        check_size(&m, w, h, 3, what)?;
        let row = 3 * w as usize;
        let mut rgb = Vec::with_capacity(row * h as usize);
        for y in 0..h as usize {
            let line = &m.data[y * m.step as usize..][..row];
            match m.encoding.as_str() {
                "rgb8" => rgb.extend_from_slice(line),
                "bgr8" => rgb.extend(line.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]])),
                other => return Err(bad(format!("colour encoding {other:?}: use rgb8, bgr8 or a CompressedImage"))),
            }
        }
        Ok(ColorImage { width: w, height: h, data: rgb })
    }

    fn decode_depth(&self, data: &[u8], what: &str) -> Result<DepthImage, ClientError> {
        let (w, h) = (self.camera.width, self.camera.height);
        let bad = |m: String| ClientError::Source(format!("{what}: {m}"));
        let (_, m) = message::<Image>(self.format, data, what)?;
        let bytes = if m.encoding == "32FC1" { 4 } else { 2 };
        check_size(&m, w, h, bytes, what)?;
        let scale = self.camera.depth_units_per_metre;
        let mut depth = Vec::with_capacity((w * h) as usize);
        for y in 0..h as usize {
            let line = &m.data[y * m.step as usize..][..bytes * w as usize];
            match (m.encoding.as_str(), m.is_bigendian != 0) {
                ("16UC1" | "mono16", big) => depth.extend(line.chunks_exact(2).map(|b| {
                    let b = [b[0], b[1]];
                    if big { u16::from_be_bytes(b) } else { u16::from_le_bytes(b) }
                })),
                ("32FC1", big) => depth.extend(line.chunks_exact(4).map(|b| {
                    let b = [b[0], b[1], b[2], b[3]];
                    let metres = f64::from(if big { f32::from_be_bytes(b) } else { f32::from_le_bytes(b) });
                    // NaN, ±inf, ≤ 0 and beyond 16 bits: no depth.
                    let units = (metres * scale).round();
                    if units.is_finite() && units > 0.0 && units <= f64::from(u16::MAX) { units as u16 } else { 0 }
                })),
                (other, _) => return Err(bad(format!("depth encoding {other:?}: use 16UC1 (mm) or 32FC1 (m)"))),
            }
        }
        Ok(DepthImage { width: w, height: h, data: depth })
    }
}

/// An image's size against the camera's, and its rows against its data (never an
/// index past the data, whatever the message declares).
fn check_size(m: &Image, w: u32, h: u32, bytes_per_pixel: usize, what: &str) -> Result<(), ClientError> {
    let bad = |s: String| Err(ClientError::Source(format!("{what}: {s}")));
    if (m.width, m.height) != (w, h) {
        return bad(format!("{}x{} image, the camera is {w}x{h}", m.width, m.height));
    }
    let row = bytes_per_pixel * w as usize;
    if (m.step as usize) < row || m.data.len() < (m.step as usize) * (h as usize - 1) + row {
        return bad(format!("step {} and {} bytes do not hold {w}x{h} pixels of {bytes_per_pixel} bytes", m.step, m.data.len()));
    }
    Ok(())
}

fn depth_units(encoding: &str) -> f64 {
    if encoding == "32FC1" { FLOAT_DEPTH_UNITS_PER_METRE } else { 1000.0 }
}

/// Whether a `CameraInfo` holds the ROS drivers' uncalibrated defaults (fx = fy =
/// 525, the image centre, no distortion) rather than a calibration.
fn is_ros_default(ci: &CameraInfo) -> bool {
    let [fx, _, cx, _, fy, cy, _, _, _] = ci.k;
    let centre = ((f64::from(ci.width) - 1.0) / 2.0, (f64::from(ci.height) - 1.0) / 2.0);
    fx == 525.0 && fy == 525.0 && (cx, cy) == centre && ci.d.iter().all(|&d| d == 0.0)
}

/// The camera from a ROS `CameraInfo` (`plumb_bob`, or no distortion).
fn camera_from_info(ci: &CameraInfo, depth_encoding: &str) -> Result<pb::CameraInfo, String> {
    let [fx, _, cx, _, fy, cy, _, _, _] = ci.k;
    if !(fx > 0.0 && fy > 0.0 && ci.width > 0 && ci.height > 0 && [fx, fy, cx, cy].iter().all(|v| v.is_finite())) {
        return Err(format!("camera info has no usable intrinsics (K = {:?}, {}x{})", ci.k, ci.width, ci.height));
    }
    if ci.d.iter().any(|d| !d.is_finite()) {
        return Err(format!("camera info distortion coefficients {:?} are not all finite", ci.d));
    }
    let (model, coeffs) = match ci.distortion_model.as_str() {
        "plumb_bob" | "rational_polynomial" if ci.d.iter().any(|&d| d != 0.0) => {
            if ci.distortion_model != "plumb_bob" || ci.d.len() < 5 {
                return Err(format!(
                    "camera info distortion {:?} with {} coefficients: only plumb_bob (5) is modelled",
                    ci.distortion_model,
                    ci.d.len()
                ));
            }
            (DistortionModel::PlumbBob, ci.d[..5].to_vec())
        }
        _ => (DistortionModel::None, Vec::new()),
    };
    Ok(pb::CameraInfo {
        width: ci.width,
        height: ci.height,
        fx,
        fy,
        cx,
        cy,
        distortion_model: model as i32,
        distortion_coeffs: coeffs,
        depth_units_per_metre: depth_units(depth_encoding),
        ..Default::default()
    })
}

/// The size of the first image on `topic`.
fn first_size(path: &Path, format: BagFormat, topic: &str) -> Result<(u32, u32), ClientError> {
    let mut size: Option<Result<(u32, u32), ClientError>> = None;
    visit(path, format, &mut |t, schema, data| {
        if t != topic {
            return Ok(true);
        }
        size = Some(match schema {
            IMAGE => message::<ImageHead>(format, data, &format!("{topic} message 1")).map(|(_, h)| (h.width, h.height)),
            _ => Err(ClientError::Source(format!(
                "{topic}: a compressed colour topic and no CameraInfo: give --calibration (it states the image size)"
            ))),
        });
        Ok(false)
    })?;
    size.unwrap_or_else(|| Err(ClientError::Source(format!("{}: no message on {topic}", path.display()))))
}

impl ReadPlan {
    /// The second pass: decodes the paired images in file order and sends the frames
    /// in pair order (each image kept only until its frame is sent; at most
    /// [`MAX_PENDING_IMAGES`] waiting). Stops when the receiver is gone.
    fn run(self, out: &std::sync::mpsc::SyncSender<Result<RawFrame, ClientError>>) {
        let needed: (std::collections::HashSet<usize>, std::collections::HashSet<usize>) =
            (self.pairs.iter().map(|p| p.0).collect(), self.pairs.iter().map(|p| p.1).collect());
        let (mut seen, mut next) = ((0usize, 0usize), 0usize);
        let mut pending_color: HashMap<usize, ColorImage> = HashMap::new();
        let mut pending_depth: HashMap<usize, DepthImage> = HashMap::new();
        let mut receiver_gone = false;
        let result = visit(&self.path, self.format, &mut |topic, schema, data| {
            if topic == self.topics.0 {
                let k = seen.0;
                seen.0 += 1;
                if needed.0.contains(&k) {
                    let what = format!("{topic} message {}", k + 1);
                    pending_color.insert(k, self.decode_color(data, schema == COMPRESSED, &what)?);
                }
            } else if topic == self.topics.1 {
                let k = seen.1;
                seen.1 += 1;
                if needed.1.contains(&k) {
                    pending_depth.insert(k, self.decode_depth(data, &format!("{topic} message {}", k + 1))?);
                }
            } else {
                return Ok(true);
            }
            while let Some(&(ci, di, ts, accel)) = self.pairs.get(next) {
                if !(pending_color.contains_key(&ci) && pending_depth.contains_key(&di)) {
                    break;
                }
                next += 1;
                let (Some(color), Some(depth)) = (pending_color.remove(&ci), pending_depth.remove(&di)) else { break };
                if out.send(Ok(RawFrame { capture_time_ns: ts, color, depth, accel_in_camera: accel })).is_err() {
                    receiver_gone = true;
                    return Ok(false);
                }
            }
            if pending_color.len() + pending_depth.len() > MAX_PENDING_IMAGES {
                return Err(ClientError::Source(format!(
                    "{}: colour and depth of one frame lie more than {MAX_PENDING_IMAGES} images apart in the file",
                    self.path.display()
                )));
            }
            Ok(next < self.pairs.len())
        });
        let ended = match result {
            Err(e) => Some(e),
            Ok(()) if !receiver_gone && next < self.pairs.len() => {
                Some(ClientError::Source(format!("{}: ended before frame {next} (changed while read?)", self.path.display())))
            }
            Ok(()) => None,
        };
        if let Some(e) = ended {
            let _ = out.send(Err(e));
        }
    }
}

impl FrameSource for BagSource {
    fn camera(&self) -> pb::CameraInfo {
        self.camera.clone()
    }

    fn len_hint(&self) -> Option<usize> {
        Some(self.frames)
    }

    fn next_frame(&mut self) -> Result<Option<RawFrame>, ClientError> {
        if let Some(plan) = self.plan.take() {
            let (tx, rx) = std::sync::mpsc::sync_channel(READ_AHEAD_FRAMES);
            std::thread::Builder::new()
                .name("bag-reader".into())
                .spawn(move || plan.run(&tx))
                .map_err(|e| ClientError::Source(format!("cannot start the recording's reader thread: {e}")))?;
            self.reader = Some(rx);
        }
        match self.reader.as_ref().map(std::sync::mpsc::Receiver::recv) {
            Some(Ok(frame)) => frame.map(Some),
            // The reader sent every frame and ended.
            Some(Err(_)) | None => Ok(None),
        }
    }
}
