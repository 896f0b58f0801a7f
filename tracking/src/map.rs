//! The tracking map: keyframes and the 3D points they observe.

use std::collections::{BTreeMap, HashMap};

use nalgebra::{Isometry3, Point3};

use crate::features::{Descriptor, FrameFeatures, hamming};

pub type PointId = u64;
pub type KeyframeId = u64;

/// A 3D point in the world with the descriptor used to match it.
#[derive(Debug, Clone)]
pub struct MapPoint {
    pub point_in_world: Point3<f64>,
    /// The observation descriptor closest to all others (the "median" descriptor).
    pub descriptor: Descriptor,
    /// Pyramid level of the creating observation; sets the search radius.
    pub octave: u8,
    /// (keyframe, feature index) pairs.
    pub observations: Vec<(KeyframeId, usize)>,
    pub created_by: KeyframeId,
    /// Frames in which the point was predicted visible, and in which it was matched.
    pub visible: u32,
    pub found: u32,
}

/// A frame kept in the map.
#[derive(Debug, Clone)]
pub struct Keyframe {
    pub id: KeyframeId,
    pub timestamp_ns: u64,
    pub world_from_camera: Isometry3<f64>,
    pub features: FrameFeatures,
    /// Map point observed by each feature.
    pub points: Vec<Option<PointId>>,
    /// A small zero-mean, unit-variance thumbnail for relocalization candidates.
    pub thumbnail: Vec<f32>,
}

impl Keyframe {
    pub fn tracked_points(&self) -> usize {
        self.points.iter().filter(|p| p.is_some()).count()
    }
}

/// Keyframes and points. Ids are never reused.
#[derive(Debug, Default)]
pub struct Map {
    pub keyframes: BTreeMap<KeyframeId, Keyframe>,
    pub points: HashMap<PointId, MapPoint>,
    next_point: PointId,
    next_keyframe: KeyframeId,
}

impl Map {
    pub fn next_keyframe_id(&mut self) -> KeyframeId {
        let id = self.next_keyframe;
        self.next_keyframe += 1;
        id
    }

    pub fn add_point(&mut self, point: MapPoint) -> PointId {
        let id = self.next_point;
        self.next_point += 1;
        self.points.insert(id, point);
        id
    }

    /// Records that feature `feature` of keyframe `kf` observes `point`.
    pub fn add_observation(&mut self, point: PointId, kf: KeyframeId, feature: usize) {
        let Some(keyframe) = self.keyframes.get_mut(&kf) else { return };
        let Some(mp) = self.points.get_mut(&point) else { return };
        if keyframe.points[feature].is_some() || mp.observations.iter().any(|&(k, _)| k == kf) {
            return;
        }
        keyframe.points[feature] = Some(point);
        mp.observations.push((kf, feature));
        self.update_descriptor(point);
    }

    /// Removes one observation; a point left with none is erased.
    pub fn remove_observation(&mut self, point: PointId, kf: KeyframeId) {
        let mut empty = false;
        if let Some(mp) = self.points.get_mut(&point) {
            if let Some(pos) = mp.observations.iter().position(|&(k, _)| k == kf) {
                let (_, feature) = mp.observations.swap_remove(pos);
                if let Some(keyframe) = self.keyframes.get_mut(&kf) {
                    keyframe.points[feature] = None;
                }
            }
            empty = mp.observations.is_empty();
        }
        if empty {
            self.points.remove(&point);
        } else {
            self.update_descriptor(point);
        }
    }

    /// Erases a point and all its observations.
    pub fn erase_point(&mut self, point: PointId) {
        if let Some(mp) = self.points.remove(&point) {
            for (kf, feature) in mp.observations {
                if let Some(keyframe) = self.keyframes.get_mut(&kf) {
                    keyframe.points[feature] = None;
                }
            }
        }
    }

    /// Picks the observation descriptor with the least median distance to the others.
    fn update_descriptor(&mut self, point: PointId) {
        let Some(mp) = self.points.get(&point) else { return };
        let descriptors: Vec<Descriptor> =
            mp.observations.iter().filter_map(|&(kf, f)| self.keyframes.get(&kf).map(|k| k.features.descriptors[f])).collect();
        if descriptors.len() < 3 {
            return;
        }
        let mut best = (u32::MAX, descriptors[0]);
        for a in &descriptors {
            let mut d: Vec<u32> = descriptors.iter().map(|b| hamming(a, b)).collect();
            d.sort_unstable();
            let median = d[d.len() / 2];
            if median < best.0 {
                best = (median, *a);
            }
        }
        if let Some(mp) = self.points.get_mut(&point) {
            mp.descriptor = best.1;
        }
    }
}
