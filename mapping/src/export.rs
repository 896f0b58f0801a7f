//! The map as a point cloud (binary PLY) and as static objects.

use nalgebra::{Point3, UnitQuaternion};
use rustc_hash::{FxHashMap, FxHashSet};

use crate::map::VoxelMap;
use crate::voxel::{NO_CLASS, VoxelKey};

/// One occupied voxel in the map frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudPoint {
    pub point_in_map: [f32; 3],
    pub rgb: [u8; 3],
    /// `NO_CLASS` (65535) for an unlabelled surface.
    pub class: u16,
    pub confidence: f32,
}

/// An axis-aligned box in the map frame, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl Aabb {
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }
}

/// Occupied voxels (their centres) in the map frame, optionally inside `bbox`.
pub fn cloud(map: &VoxelMap, map_from_world: &UnitQuaternion<f64>, bbox: Option<&Aabb>) -> Vec<CloudPoint> {
    let mut out: Vec<(VoxelKey, CloudPoint)> = map
        .occupied()
        .filter_map(|(key, centre, v)| {
            let p = map_from_world * centre;
            if bbox.is_some_and(|b| !b.contains(&p)) {
                return None;
            }
            let (class, confidence) = v.class();
            Some((key, CloudPoint { point_in_map: [p.x as f32, p.y as f32, p.z as f32], rgb: v.color, class, confidence }))
        })
        .collect();
    // Deterministic order (hash iteration is not): by voxel key.
    out.sort_unstable_by_key(|(k, _)| *k);
    out.into_iter().map(|(_, p)| p).collect()
}

/// Binary little-endian PLY: x, y, z (float), red, green, blue (uchar), class
/// (ushort, 65535 = unlabelled), confidence (float). Class names go in comments.
pub fn to_ply(points: &[CloudPoint], class_names: &[String], comment: &str) -> Vec<u8> {
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    for line in comment.lines() {
        header.push_str(&format!("comment {line}\n"));
    }
    let present: FxHashSet<u16> = points.iter().map(|p| p.class).collect();
    let mut present: Vec<u16> = present.into_iter().filter(|&c| c != NO_CLASS).collect();
    present.sort_unstable();
    for c in present {
        let name = class_names.get(usize::from(c)).map_or("?", String::as_str);
        header.push_str(&format!("comment class {c} {name}\n"));
    }
    header.push_str(&format!(
        "element vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nproperty ushort class\nproperty float confidence\nend_header\n",
        points.len()
    ));
    let mut out = header.into_bytes();
    out.reserve(points.len() * PLY_VERTEX_BYTES);
    for p in points {
        for v in p.point_in_map {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&p.rgb);
        out.extend_from_slice(&p.class.to_le_bytes());
        out.extend_from_slice(&p.confidence.to_le_bytes());
    }
    out
}

pub const PLY_VERTEX_BYTES: usize = 12 + 3 + 2 + 4;

/// A static object: a 26-connected cluster of voxels sharing a confident class.
#[derive(Debug, Clone, PartialEq)]
pub struct MapObject {
    pub class: u16,
    pub centroid: [f64; 3],
    pub bbox: Aabb,
    pub voxels: usize,
    /// Mean class confidence over its voxels.
    pub confidence: f32,
}

pub fn objects(map: &VoxelMap, map_from_world: &UnitQuaternion<f64>) -> Vec<MapObject> {
    let cfg = map.config();
    let labelled: FxHashMap<VoxelKey, (u16, f32, Point3<f64>)> = map
        .occupied()
        .filter_map(|(key, centre, v)| {
            let (class, confidence) = v.class();
            (class != NO_CLASS && confidence >= cfg.objects_min_confidence).then(|| (key, (class, confidence, map_from_world * centre)))
        })
        .collect();
    let mut seen: FxHashSet<VoxelKey> = FxHashSet::default();
    let mut keys: Vec<VoxelKey> = labelled.keys().copied().collect();
    keys.sort_unstable();
    let mut out = Vec::new();
    for start in keys {
        if !seen.insert(start) {
            continue;
        }
        let class = labelled[&start].0;
        let mut stack = vec![start];
        let mut members = Vec::new();
        while let Some(k) = stack.pop() {
            members.push(k);
            for dz in -1..=1 {
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let n = [k[0] + dx, k[1] + dy, k[2] + dz];
                        if labelled.get(&n).is_some_and(|e| e.0 == class) && seen.insert(n) {
                            stack.push(n);
                        }
                    }
                }
            }
        }
        if members.len() < cfg.objects_min_voxels {
            continue;
        }
        let (mut min, mut max, mut sum, mut conf) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3], [0.0; 3], 0.0f32);
        for k in &members {
            let (_, c, p) = labelled[k];
            conf += c;
            for i in 0..3 {
                min[i] = min[i].min(p[i]);
                max[i] = max[i].max(p[i]);
                sum[i] += p[i];
            }
        }
        let n = members.len() as f64;
        out.push(MapObject {
            class,
            centroid: [sum[0] / n, sum[1] / n, sum[2] / n],
            bbox: Aabb { min, max },
            voxels: members.len(),
            confidence: conf / members.len() as f32,
        });
    }
    out.sort_by_key(|o| std::cmp::Reverse(o.voxels));
    out
}
