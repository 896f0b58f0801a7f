//! ROS 2 recordings: `--source mcap:FILE` streams `sensor_msgs/msg/Image` (or
//! `CompressedImage`) colour, `Image` depth (`16UC1` millimetres or `32FC1` metres),
//! `CameraInfo` for the calibration and `Imu` for the accelerometer, read with
//! Foxglove's `mcap` crate and decoded from CDR with `cdr-encoding`.
//!
//! Two passes over the file, each streaming (memory is one chunk and the frames
//! waiting for their other half, not the file): the first lists the topics and
//! every image's timestamp, pairs colour with depth exactly as the TUM source does
//! (`tum::associate`, 20 ms) and keeps the camera info and accelerometer samples;
//! the second decodes the paired images in order.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use stillmap_proto::codec::{self, ColorImage, DepthImage};
use stillmap_proto::pb::{self, DistortionModel};

use crate::ClientError;
use crate::calibration::{CameraOptions, SourceCamera};
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

/// Colour and depth further apart than this are not one frame (as `tum.rs`).
const MAX_ASSOCIATION_NS: u64 = 20_000_000;
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

/// The leading fields of an `Image` (what the first pass needs).
#[derive(Deserialize)]
struct ImageHead {
    header: Header,
    height: u32,
    width: u32,
    encoding: String,
}

#[derive(Deserialize)]
struct Image {
    _header: Header,
    height: u32,
    width: u32,
    encoding: String,
    is_bigendian: u8,
    step: u32,
    data: Vec<u8>,
}

#[derive(Deserialize)]
struct CompressedImage {
    _header: Header,
    format: String,
    data: Vec<u8>,
}

#[derive(Deserialize)]
struct CameraInfo {
    header: Header,
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
    header: Header,
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

/// What the first pass saw of one topic.
#[derive(Debug, Default)]
struct TopicStats {
    schema: String,
    messages: u64,
    /// `Image`: the first message's encoding.
    encoding: Option<String>,
}

pub struct McapSource {
    path: PathBuf,
    camera: pb::CameraInfo,
    topics: (String, String),
    /// (colour message ordinal, depth message ordinal, capture time, accelerometer).
    pairs: Vec<(usize, usize, u64, Option<[f64; 3]>)>,
    next: usize,
    reader: Option<mcap::io::MessageReader<BufReader<File>>>,
    /// Ordinals of the colour and depth messages seen so far in the second pass.
    seen: (usize, usize),
    /// The colour and depth ordinals some frame uses.
    needed: (std::collections::HashSet<usize>, std::collections::HashSet<usize>),
    pending_color: HashMap<usize, ColorImage>,
    pending_depth: HashMap<usize, DepthImage>,
}

fn open_reader(path: &Path) -> Result<mcap::io::MessageReader<BufReader<File>>, ClientError> {
    let file = File::open(path).map_err(|e| ClientError::Source(format!("{}: {e}", path.display())))?;
    Ok(mcap::io::MessageReader::new(BufReader::new(file)))
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

impl McapSource {
    pub fn open(path: &Path, topics: &BagTopics, max_frames: Option<usize>, options: &CameraOptions) -> Result<Self, ClientError> {
        let source_error = |m: String| ClientError::Source(format!("{}: {m}", path.display()));
        // First pass: the topics, every image's stamp, the calibration, the accelerometer.
        let mut stats: BTreeMap<String, TopicStats> = BTreeMap::new();
        let mut stamps: HashMap<String, Vec<u64>> = HashMap::new();
        let mut infos: HashMap<String, CameraInfo> = HashMap::new();
        let mut imu: HashMap<String, Vec<(u64, [f64; 3], String)>> = HashMap::new();
        let mut image_frames: HashMap<String, String> = HashMap::new();
        for message in open_reader(path)? {
            let message = message.map_err(|e| source_error(format!("not a readable MCAP file: {e}")))?;
            let topic = &message.channel.topic;
            let schema = message.channel.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default();
            let entry = stats.entry(topic.clone()).or_insert_with(|| TopicStats { schema: schema.clone(), ..Default::default() });
            entry.messages += 1;
            let cdr = message.channel.message_encoding == "cdr";
            let what = || format!("{topic} message {}", entry.messages);
            match schema.as_str() {
                IMAGE if cdr => {
                    let head: ImageHead = decode(&message.data, &what())?;
                    entry.encoding.get_or_insert(head.encoding);
                    image_frames.entry(topic.clone()).or_insert(head.header.frame_id.clone());
                    let stamp = head.header.stamp_ns().ok_or_else(|| source_error(format!("{}: negative time stamp", what())))?;
                    stamps.entry(topic.clone()).or_default().push(stamp);
                }
                COMPRESSED if cdr => {
                    let head: Header = decode(&message.data, &what())?;
                    image_frames.entry(topic.clone()).or_insert(head.frame_id.clone());
                    let stamp = head.stamp_ns().ok_or_else(|| source_error(format!("{}: negative time stamp", what())))?;
                    stamps.entry(topic.clone()).or_default().push(stamp);
                }
                CAMERA_INFO if cdr && !infos.contains_key(topic) => {
                    infos.insert(topic.clone(), decode(&message.data, &what())?);
                }
                IMU if cdr => {
                    let m: Imu = decode(&message.data, &what())?;
                    let samples = imu.entry(topic.clone()).or_default();
                    if samples.len() >= MAX_IMU_SAMPLES {
                        return Err(source_error(format!("{topic}: more than {MAX_IMU_SAMPLES} IMU samples")));
                    }
                    if let Some(t) = m.header.stamp_ns() {
                        let a = &m.linear_acceleration;
                        samples.push((t, [a.x, a.y, a.z], m.header.frame_id));
                    }
                }
                _ => {}
            }
        }
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

        // The accelerometer only when it is in the colour camera's frame (no TF here).
        let color_frame = image_frames.get(&color).cloned().unwrap_or_default();
        let accel: Vec<(u64, [f64; 3])> = match imu_topic.and_then(|t| imu.remove(&t).map(|s| (t, s))) {
            Some((t, samples)) => {
                if samples.iter().all(|s| s.2 == color_frame) {
                    let mut v: Vec<(u64, [f64; 3])> = samples.into_iter().map(|s| (s.0, s.1)).collect();
                    v.sort_by_key(|s| s.0);
                    v
                } else {
                    tracing::warn!("{t} is not in the colour camera's frame {color_frame:?}; its accelerometer is left out");
                    Vec::new()
                }
            }
            None => Vec::new(),
        };
        let accel_ts: Vec<u64> = accel.iter().map(|a| a.0).collect();
        let mut pairs = Vec::new();
        for (i, j) in crate::tum::associate(&color_stamps, &depth_stamps, MAX_ASSOCIATION_NS) {
            let ts = color_stamps[i];
            let nearest = accel_ts.partition_point(|&t| t < ts);
            let sample = [nearest.checked_sub(1), Some(nearest)]
                .into_iter()
                .flatten()
                .filter(|&k| k < accel.len() && accel_ts[k].abs_diff(ts) < MAX_ASSOCIATION_NS)
                .min_by_key(|&k| accel_ts[k].abs_diff(ts))
                .map(|k| accel[k].1);
            pairs.push((i, j, ts, sample));
        }
        if pairs.is_empty() {
            return Err(source_error(format!("no {color} / {depth} pair within 20 ms")));
        }
        if let Some(max) = max_frames {
            pairs.truncate(max);
        }

        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let first = infos.remove(info_topic.as_deref().unwrap_or_default());
        let source_camera = match first {
            Some(ci) => SourceCamera {
                info: camera_from_info(&ci, &depth_encoding).map_err(source_error)?,
                known: Some(format!("mcap:{name} {} ({})", info_topic.unwrap_or_default(), ci.header.frame_id)),
                what: format!("MCAP file {name}"),
            },
            None => {
                // Size from the first colour image; nominal intrinsics, marked unknown.
                let (w, h) = first_size(path, &color)?;
                SourceCamera {
                    info: pb::CameraInfo {
                        width: w,
                        height: h,
                        fx: 525.0,
                        fy: 525.0,
                        cx: (f64::from(w) - 1.0) / 2.0,
                        cy: (f64::from(h) - 1.0) / 2.0,
                        distortion_model: DistortionModel::None as i32,
                        depth_units_per_metre: depth_units(&depth_encoding),
                        ..Default::default()
                    },
                    known: None,
                    what: format!("MCAP file {name} (no CameraInfo topic)"),
                }
            }
        };
        let camera = crate::calibration::resolve(source_camera, options)?;
        Ok(Self {
            path: path.to_path_buf(),
            camera,
            topics: (color, depth),
            next: 0,
            reader: None,
            seen: (0, 0),
            needed: (pairs.iter().map(|p| p.0).collect(), pairs.iter().map(|p| p.1).collect()),
            pairs,
            pending_color: HashMap::new(),
            pending_depth: HashMap::new(),
        })
    }

    fn decode_color(&self, data: &[u8], compressed: bool, what: &str) -> Result<ColorImage, ClientError> {
        let (w, h) = (self.camera.width, self.camera.height);
        let bad = |m: String| ClientError::Source(format!("{what}: {m}"));
        if compressed {
            let m: CompressedImage = decode(data, what)?;
            let encoding = if m.format.contains("png") { pb::ColorEncoding::Png } else { pb::ColorEncoding::Jpeg };
            return codec::decode_color(encoding, &m.data, w, h).map_err(|e| bad(e.to_string()));
        }
        let m: Image = decode(data, what)?;
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
        let m: Image = decode(data, what)?;
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

/// The camera from a ROS `CameraInfo` (`plumb_bob`, or no distortion).
fn camera_from_info(ci: &CameraInfo, depth_encoding: &str) -> Result<pb::CameraInfo, String> {
    let [fx, _, cx, _, fy, cy, _, _, _] = ci.k;
    if !(fx > 0.0 && fy > 0.0 && ci.width > 0 && ci.height > 0) {
        return Err(format!("camera info has no usable intrinsics (K = {:?}, {}x{})", ci.k, ci.width, ci.height));
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
fn first_size(path: &Path, topic: &str) -> Result<(u32, u32), ClientError> {
    for message in open_reader(path)? {
        let message = message.map_err(|e| ClientError::Source(format!("{}: {e}", path.display())))?;
        if message.channel.topic == topic {
            let what = format!("{topic} message 1");
            return match message.channel.schema.as_ref().map(|s| s.name.as_str()) {
                Some(IMAGE) => decode::<ImageHead>(&message.data, &what).map(|h| (h.width, h.height)),
                _ => Err(ClientError::Source(format!(
                    "{topic}: a compressed colour topic and no CameraInfo: give --calibration (it states the image size)"
                ))),
            };
        }
    }
    Err(ClientError::Source(format!("{}: no message on {topic}", path.display())))
}

impl FrameSource for McapSource {
    fn camera(&self) -> pb::CameraInfo {
        self.camera.clone()
    }

    fn len_hint(&self) -> Option<usize> {
        Some(self.pairs.len())
    }

    fn next_frame(&mut self) -> Result<Option<RawFrame>, ClientError> {
        let Some(&(ci, di, ts, accel)) = self.pairs.get(self.next) else {
            return Ok(None);
        };
        if self.reader.is_none() {
            self.reader = Some(open_reader(&self.path)?);
        }
        while !(self.pending_color.contains_key(&ci) && self.pending_depth.contains_key(&di)) {
            let Some(message) = self.reader.as_mut().and_then(Iterator::next) else {
                return Err(ClientError::Source(format!(
                    "{}: ended before frame {} (changed while read?)",
                    self.path.display(),
                    self.next
                )));
            };
            let message = message.map_err(|e| ClientError::Source(format!("{}: {e}", self.path.display())))?;
            let topic = message.channel.topic.as_str();
            let compressed = message.channel.schema.as_ref().is_some_and(|s| s.name == COMPRESSED);
            // Only images some frame needs are decoded and kept.
            let wanted = |k: usize, colour: bool| if colour { self.needed.0.contains(&k) } else { self.needed.1.contains(&k) };
            if topic == self.topics.0 {
                let k = self.seen.0;
                self.seen.0 += 1;
                if wanted(k, true) {
                    let image = self.decode_color(&message.data, compressed, &format!("{topic} message {}", k + 1))?;
                    self.pending_color.insert(k, image);
                }
            } else if topic == self.topics.1 {
                let k = self.seen.1;
                self.seen.1 += 1;
                if wanted(k, false) {
                    let image = self.decode_depth(&message.data, &format!("{topic} message {}", k + 1))?;
                    self.pending_depth.insert(k, image);
                }
            }
            if self.pending_color.len() + self.pending_depth.len() > MAX_PENDING_IMAGES {
                return Err(ClientError::Source(format!(
                    "{}: colour and depth of one frame lie more than {MAX_PENDING_IMAGES} images apart in the file",
                    self.path.display()
                )));
            }
        }
        self.next += 1;
        let (Some(color), Some(depth)) = (self.pending_color.remove(&ci), self.pending_depth.remove(&di)) else {
            return Err(ClientError::Source("frame pairing lost its images".into()));
        };
        Ok(Some(RawFrame { capture_time_ns: ts, color, depth, accel_in_camera: accel }))
    }
}
