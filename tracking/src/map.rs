//! The tracking map: keyframes and the 3D points they observe.

use std::collections::{BTreeMap, HashMap, HashSet};

use nalgebra::{Isometry3, Point3};

use crate::features::{Descriptor, FrameFeatures, hamming};

pub type PointId = u64;
pub type KeyframeId = u64;

/// A keyframe whose points are this share or more seen by other keyframes too is
/// redundant ([`Map::is_redundant`]; ORB-SLAM's 90 %).
pub const REDUNDANT_SHARE: f64 = 0.9;
/// Other keyframes that must see a point for it to count as seen elsewhere (ORB-SLAM's 3).
pub const REDUNDANT_OTHER_OBSERVERS: usize = 3;
/// A point's descriptor is chosen among the observations of at most this many of
/// the oldest keyframes that see it: the choice costs the square of their number,
/// and a place seen on every pass of a long session collects hundreds.
pub const DESCRIPTOR_OBSERVATIONS: usize = 32;

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
        // Not among the oldest that choose the descriptor: nothing to choose again.
        if mp.observations.len() > DESCRIPTOR_OBSERVATIONS && mp.observations.iter().filter(|o| o.0 < kf).count() >= DESCRIPTOR_OBSERVATIONS
        {
            return;
        }
        self.update_descriptor(point);
    }

    /// Removes one observation; a point left with none is erased.
    pub fn remove_observation(&mut self, point: PointId, kf: KeyframeId) {
        if !self.unobserve(point, kf) {
            self.update_descriptor(point);
        }
    }

    /// Removes one observation and erases the point left with none (true then);
    /// the point's descriptor stays as it was.
    fn unobserve(&mut self, point: PointId, kf: KeyframeId) -> bool {
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
        }
        empty
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

    /// Forgets keyframe `id`: its observations are removed, and the points only it
    /// saw are erased with it. The others keep their descriptors (chosen among
    /// observations that included this one: a copy, still a descriptor the point
    /// was seen with); recomputing them costs the square of their observations
    /// each, for a thousand points.
    pub fn forget_keyframe(&mut self, id: KeyframeId) {
        let Some(kf) = self.keyframes.remove(&id) else { return };
        for point in kf.points.into_iter().flatten() {
            self.unobserve(point, id);
        }
    }

    /// Whether the keyframe adds little to the map: at least [`REDUNDANT_SHARE`] of
    /// the points it sees are seen by [`REDUNDANT_OTHER_OBSERVERS`] other keyframes
    /// as well (ORB-SLAM's keyframe culling rule), or it sees none.
    pub fn is_redundant(&self, kf: &Keyframe) -> bool {
        let (mut seen, mut elsewhere) = (0usize, 0usize);
        for p in kf.points.iter().flatten() {
            seen += 1;
            if self.points.get(p).is_some_and(|mp| mp.observations.len() > REDUNDANT_OTHER_OBSERVERS) {
                elsewhere += 1;
            }
        }
        elsewhere as f64 >= REDUNDANT_SHARE * seen as f64
    }

    /// The keyframe to forget when the map holds too many (`tracking.max_keyframes`),
    /// none of those in `kept`: of the `scan` newest others, the newest redundant
    /// one ([`Map::is_redundant`]: a place seen again adds nothing, and the older
    /// keyframes that first mapped it stay), else the oldest. The scan bounds the
    /// cost where nothing is redundant (a robot exploring).
    pub fn keyframe_to_forget(&self, kept: &HashSet<KeyframeId>, scan: usize) -> Option<KeyframeId> {
        let others = || self.keyframes.values().filter(|kf| !kept.contains(&kf.id));
        others().rev().take(scan).find(|kf| self.is_redundant(kf)).or_else(|| others().next()).map(|kf| kf.id)
    }

    /// Picks the observation descriptor with the least median distance to the others,
    /// among the observations of the [`DESCRIPTOR_OBSERVATIONS`] oldest keyframes
    /// (those that first saw the point; where a place is seen again, forgetting
    /// takes the newest redundant keyframes first).
    fn update_descriptor(&mut self, point: PointId) {
        let Some(mp) = self.points.get(&point) else { return };
        // The newest keyframe taken (a point has one observation per keyframe); the
        // observations stay in the order they are listed (ties go to the first).
        let newest = if mp.observations.len() > DESCRIPTOR_OBSERVATIONS {
            let mut ids: Vec<KeyframeId> = mp.observations.iter().map(|o| o.0).collect();
            *ids.select_nth_unstable(DESCRIPTOR_OBSERVATIONS - 1).1
        } else {
            KeyframeId::MAX
        };
        let descriptors: Vec<Descriptor> = mp
            .observations
            .iter()
            .filter(|o| o.0 <= newest)
            .filter_map(|&(kf, f)| self.keyframes.get(&kf).map(|k| k.features.descriptors[f]))
            .collect();
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

#[cfg(test)]
mod tests {
    use super::*;

    fn keyframe(id: KeyframeId, features: usize) -> Keyframe {
        Keyframe {
            id,
            timestamp_ns: id,
            world_from_camera: Isometry3::identity(),
            features: FrameFeatures { descriptors: vec![[id, 0, 0, 0]; features], ..FrameFeatures::default() },
            points: vec![None; features],
            thumbnail: Vec::new(),
        }
    }

    fn point(created_by: KeyframeId) -> MapPoint {
        MapPoint {
            point_in_world: Point3::origin(),
            descriptor: [0; 4],
            octave: 0,
            observations: Vec::new(),
            created_by,
            visible: 1,
            found: 1,
        }
    }

    /// Every observation a point lists is the slot of an existing keyframe that
    /// names the point back, and every point a keyframe names exists.
    fn assert_consistent(map: &Map) {
        for (id, mp) in &map.points {
            assert!(!mp.observations.is_empty(), "point {id} without observations");
            for &(kf, f) in &mp.observations {
                assert_eq!(map.keyframes[&kf].points[f], Some(*id), "point {id} in keyframe {kf}");
            }
        }
        for kf in map.keyframes.values() {
            for p in kf.points.iter().flatten() {
                assert!(map.points.contains_key(p), "keyframe {} names point {p}", kf.id);
            }
        }
    }

    #[test]
    fn a_redundant_keyframe_is_forgotten_before_older_ones_and_its_own_points_with_it() {
        // Keyframe 0 sees ten points no other sees; keyframes 1–4 all see ten others.
        let mut map = Map::default();
        for _ in 0..5 {
            let id = map.next_keyframe_id();
            map.keyframes.insert(id, keyframe(id, 10));
        }
        for f in 0..10 {
            let own = map.add_point(point(0));
            map.add_observation(own, 0, f);
            let shared = map.add_point(point(1));
            for kf in 1..5 {
                map.add_observation(shared, kf, f);
            }
        }
        assert_consistent(&map);
        assert!(!map.is_redundant(&map.keyframes[&0]) && map.is_redundant(&map.keyframes[&1]));
        let kept = HashSet::from([4]);
        assert_eq!(map.keyframe_to_forget(&kept, 50), Some(3), "the newest redundant one, not the oldest");
        assert_eq!(map.keyframe_to_forget(&HashSet::from([3, 4]), 1), Some(2));
        assert_eq!(map.keyframe_to_forget(&HashSet::from([1, 2, 3, 4]), 50), Some(0), "nothing redundant: the oldest");
        assert_eq!(map.keyframe_to_forget(&HashSet::from([0, 1, 2, 3, 4]), 50), None);

        map.forget_keyframe(3);
        assert_consistent(&map);
        assert_eq!(map.points.len(), 20, "the shared points stay: three keyframes still see them");
        // Keyframes 1 and 2's points are now seen by two others only.
        assert_eq!(map.keyframe_to_forget(&kept, 50), Some(0));
        map.forget_keyframe(0);
        assert_consistent(&map);
        assert_eq!(map.points.len(), 10, "the points only keyframe 0 saw are erased with it");
        assert_eq!(map.keyframes.keys().copied().collect::<Vec<_>>(), vec![1, 2, 4]);
        map.forget_keyframe(0);
        assert_eq!(map.keyframes.len(), 3, "forgetting a keyframe no longer held changes nothing");
    }

    #[test]
    fn a_points_descriptor_is_chosen_among_its_oldest_observations() {
        // Seen by 72 keyframes: the 32 oldest with descriptors of their own, the 40
        // newest all alike. Over every observation the newest would win (their
        // median distance is 0); among the oldest 32 one of theirs does.
        let mut map = Map::default();
        let point = map.add_point(point(0));
        let alike = [u64::MAX; 4];
        for k in 0..72u64 {
            let id = map.next_keyframe_id();
            let mut kf = keyframe(id, 1);
            kf.features.descriptors[0] =
                if k < 32 { [k.wrapping_mul(0x9E37_79B9_7F4A_7C15), k.wrapping_mul(0xC2B2_AE3D_27D4_EB4F), k, !k] } else { alike };
            map.keyframes.insert(id, kf);
            map.add_observation(point, id, 0);
        }
        let chosen = map.points[&point].descriptor;
        assert_ne!(chosen, alike);
        assert!((0..32).any(|k| map.keyframes[&k].features.descriptors[0] == chosen), "{chosen:?}");
    }
}
