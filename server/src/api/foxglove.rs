//! A session as an MCAP file for Foxglove (`GET /api/v1/sessions/{id}/export.mcap`):
//! Foxglove's well-known schemas, JSON-encoded (`jsonschema` schemas, `json`
//! messages; byte fields base64, as Foxglove reads them), written with the `mcap`
//! crate (zstd chunks).
//!
//! | topic | schema | messages |
//! |---|---|---|
//! | `/pose` | `foxglove.PoseInFrame` (`world_from_camera`, frame `world`) | one per tracked frame, at its pose time |
//! | `/trajectory` | `foxglove.PosesInFrame` | one, every pose, at the last pose time |
//! | `/tracking_state` | `stillmap.TrackingState` | one per frame |
//! | `/tf` | `foxglove.FrameTransform` (`map` ← `world`: the map frame's rotation) | one, at the first pose time |
//! | `/map` | `foxglove.PointCloud` (frame `map`: x y z, class colour, class id) | one, at the last pose time |
//! | `/keyframes` | `foxglove.CompressedImage` (JPEG: colour, the pixels kept out of the map tinted red) | the newest `session.keyframe_images` keyframes |

use std::collections::BTreeMap;
use std::io::Cursor;

use base64::Engine;
use nalgebra::UnitQuaternion;
use serde_json::json;
use stillmap_mapping::export::CloudPoint;
use stillmap_proto::pb;

/// The schemas (JSON Schema), as Foxglove publishes them: the fields this file uses.
fn schema(name: &str) -> serde_json::Value {
    let number = json!({ "type": "number" });
    let integer = json!({ "type": "integer" });
    let string = json!({ "type": "string" });
    let object = |properties: serde_json::Value| json!({ "type": "object", "properties": properties });
    let time = object(json!({ "sec": integer, "nsec": integer }));
    let vector = object(json!({ "x": number, "y": number, "z": number }));
    let quaternion = object(json!({ "x": number, "y": number, "z": number, "w": number }));
    let pose = object(json!({ "position": vector, "orientation": quaternion }));
    let properties = match name {
        "foxglove.PoseInFrame" => json!({ "timestamp": time, "frame_id": string, "pose": pose }),
        "foxglove.PosesInFrame" => json!({ "timestamp": time, "frame_id": string, "poses": { "type": "array", "items": pose } }),
        "foxglove.FrameTransform" => json!({
            "timestamp": time, "parent_frame_id": string, "child_frame_id": string, "translation": vector, "rotation": quaternion,
        }),
        "foxglove.CompressedImage" => json!({
            "timestamp": time, "frame_id": string, "data": { "type": "string", "contentEncoding": "base64" }, "format": string,
        }),
        "foxglove.PointCloud" => json!({
            "timestamp": time, "frame_id": string, "pose": pose, "point_stride": integer,
            "fields": { "type": "array", "items": object(json!({ "name": string, "offset": integer, "type": integer })) },
            "data": { "type": "string", "contentEncoding": "base64" },
        }),
        _ => json!({ "sequence": integer, "capture_time_ns": integer, "state": string }),
    };
    json!({ "title": name, "type": "object", "properties": properties })
}

/// `foxglove.PackedElementField` numeric types.
const UINT8: u8 = 1;
const UINT16: u8 = 3;
const FLOAT32: u8 = 7;
/// Bytes per map point: x y z (f32), red green blue alpha (u8), class (u16).
const POINT_STRIDE: usize = 18;

fn time(ns: u64) -> serde_json::Value {
    json!({ "sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000 })
}

fn pose_json(p: &pb::PoseStamped) -> serde_json::Value {
    let pose = p.world_from_camera.unwrap_or_default();
    let (t, q) = (pose.translation.unwrap_or_default(), pose.rotation.unwrap_or_default());
    json!({ "position": { "x": t.x, "y": t.y, "z": t.z }, "orientation": { "x": q.x, "y": q.y, "z": q.z, "w": q.w } })
}

/// What the export takes from the session's map: its points, `map_from_world` and
/// the keyframe images it kept.
pub struct MapExport {
    pub points: Vec<CloudPoint>,
    pub map_from_world: UnitQuaternion<f64>,
    /// The keyframe images the session kept (`session.keyframe_images`), oldest first.
    pub images: Vec<crate::map::KeyframeImage>,
}

/// The session's MCAP file: its poses (`trajectory`, oldest first) and, when it has
/// one, its map.
pub fn session_mcap(session_id: &str, trajectory: &[pb::PoseStamped], map: Option<&MapExport>) -> Result<Vec<u8>, mcap::McapError> {
    let options = mcap::WriteOptions::new().profile("").library(concat!("stillmap ", env!("CARGO_PKG_VERSION")));
    let mut out = options.create(Cursor::new(Vec::new()))?;
    out.write_metadata(&mcap::records::Metadata {
        name: "stillmap".into(),
        metadata: BTreeMap::from([("session_id".to_string(), session_id.to_string())]),
    })?;
    let none = BTreeMap::new();
    let mut channel = |topic: &str, name: &str| -> Result<u16, mcap::McapError> {
        let schema = out.add_schema(name, "jsonschema", schema(name).to_string().as_bytes())?;
        out.add_channel(schema, topic, "json", &none)
    };
    let pose = channel("/pose", "foxglove.PoseInFrame")?;
    let state = channel("/tracking_state", "stillmap.TrackingState")?;
    let poses = channel("/trajectory", "foxglove.PosesInFrame")?;
    let tf = channel("/tf", "foxglove.FrameTransform")?;
    let cloud = channel("/map", "foxglove.PointCloud")?;
    let images = channel("/keyframes", "foxglove.CompressedImage")?;
    let mut sequence = 0u32;
    let mut write = |out: &mut mcap::Writer<Cursor<Vec<u8>>>, channel_id: u16, log_time: u64, message: serde_json::Value| {
        sequence = sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader { channel_id, sequence, log_time, publish_time: log_time };
        out.write_to_known_channel(&header, message.to_string().as_bytes())
    };
    let (first, last) = (trajectory.first().map_or(0, pb::PoseStamped::time_ns), trajectory.last().map_or(0, pb::PoseStamped::time_ns));
    if let Some(map) = map {
        let q = map.map_from_world;
        let transform = json!({
            "timestamp": time(first), "parent_frame_id": "map", "child_frame_id": "world",
            "translation": { "x": 0.0, "y": 0.0, "z": 0.0 },
            "rotation": { "x": q.i, "y": q.j, "z": q.k, "w": q.w },
        });
        write(&mut out, tf, first, transform)?;
    }
    for p in trajectory {
        let t = p.time_ns();
        let tracking = pb::TrackingState::try_from(p.tracking_state).map_or("UNKNOWN", |s| s.as_str_name());
        write(&mut out, state, t, json!({ "sequence": p.sequence, "capture_time_ns": p.capture_time_ns, "state": tracking }))?;
        if p.world_from_camera.is_some() {
            write(&mut out, pose, t, json!({ "timestamp": time(t), "frame_id": "world", "pose": pose_json(p) }))?;
        }
    }
    let tracked: Vec<serde_json::Value> = trajectory.iter().filter(|p| p.world_from_camera.is_some()).map(pose_json).collect();
    write(&mut out, poses, last, json!({ "timestamp": time(last), "frame_id": "world", "poses": tracked }))?;
    for image in map.map(|m| m.images.as_slice()).unwrap_or_default() {
        let message = json!({
            "timestamp": time(image.time_ns), "frame_id": "camera", "format": "jpeg",
            "data": base64::engine::general_purpose::STANDARD.encode(&image.jpeg),
        });
        write(&mut out, images, image.time_ns, message)?;
    }
    if let Some(map) = map {
        let mut data = Vec::with_capacity(map.points.len() * POINT_STRIDE);
        for p in &map.points {
            for v in p.point_in_map {
                data.extend_from_slice(&v.to_le_bytes());
            }
            let rgb = if p.class == stillmap_mapping::NO_CLASS { p.rgb } else { stillmap_mapping::tiles::class_color(p.class) };
            data.extend_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
            data.extend_from_slice(&p.class.to_le_bytes());
        }
        let field = |name: &str, offset: usize, kind: u8| json!({ "name": name, "offset": offset, "type": kind });
        let message = json!({
            "timestamp": time(last), "frame_id": "map",
            "pose": { "position": { "x": 0.0, "y": 0.0, "z": 0.0 }, "orientation": { "x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0 } },
            "point_stride": POINT_STRIDE,
            "fields": [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32), field("red", 12, UINT8),
                       field("green", 13, UINT8), field("blue", 14, UINT8), field("alpha", 15, UINT8), field("class", 16, UINT16)],
            "data": base64::engine::general_purpose::STANDARD.encode(&data),
        });
        write(&mut out, cloud, last, message)?;
    }
    out.finish()?;
    Ok(out.into_inner().into_inner())
}
