//! The fuse stage: what a tracked frame asks of the session's map, as a
//! [`MapJob`] for the map lane (which runs it on the map pool, off the tracking
//! path), and the fusion itself ([`apply`]).
//!
//! The [`Handoff`] remembers the keyframes the map holds for re-fusion (its
//! `refuse_window` newest) and the poses it last sent for them: a frame makes a
//! job only when it is a new keyframe or bundle adjustment moved one of them;
//! other frames only collect their accelerometer sample for the next job.

use std::collections::VecDeque;
use std::time::Duration;

use nalgebra::{Isometry3, Vector3};
use stillmap_mapping::DepthView;
use stillmap_perception::Retraction;
use stillmap_proto::codec::{ColorImage, DepthImage};

use crate::lock;
use crate::map::SharedMap;
use crate::store::KeyframeRecord;

/// Accelerometer samples carried to the next map job, at most.
const MAX_ACCEL_PER_MAP_JOB: usize = 64;

/// A new keyframe: what fusion and the store need of it.
pub struct KeyframeJob {
    pub id: u64,
    /// The frame's capture time, nanoseconds.
    pub capture_time_ns: u64,
    pub color: ColorImage,
    pub depth: DepthImage,
    /// Nonzero where perception keeps the pixel out of the map.
    pub exclude: Option<Vec<u8>>,
    /// The segmentation class per pixel.
    pub classes: Option<Vec<u16>>,
    /// The keyframe as the store keeps it.
    pub record: Option<KeyframeRecord>,
}

/// Map work of one tracked frame.
pub struct MapJob {
    pub world_from_camera: Isometry3<f64>,
    pub keyframe: Option<KeyframeJob>,
    /// Current poses of the keyframes in the map's re-fusion window.
    pub keyframe_poses: Vec<(u64, Isometry3<f64>)>,
    /// Accelerometer samples (camera pose, specific force in the camera frame).
    pub accel: Vec<(Isometry3<f64>, Vector3<f64>)>,
    /// Cells of keyframes in the window that perception found moving since: their
    /// samples leave the map.
    pub retractions: Vec<Retraction>,
}

/// The tracking path's side of the map lane.
pub struct Handoff {
    window: usize,
    /// Keyframes the map holds for re-fusion, newest last, with the poses last sent.
    keyframes: VecDeque<(u64, Isometry3<f64>)>,
    accel: Vec<(Isometry3<f64>, Vector3<f64>)>,
}

impl Handoff {
    /// `window`: the map's `refuse_window`.
    pub fn new(window: usize) -> Self {
        Self { window, keyframes: VecDeque::new(), accel: Vec::new() }
    }

    /// The map job of a frame tracked at `world_from_camera`, if it needs one.
    pub fn job(
        &mut self,
        world_from_camera: Isometry3<f64>,
        accel: Option<Vector3<f64>>,
        keyframe: Option<KeyframeJob>,
        mut retractions: Vec<Retraction>,
        keyframe_pose: impl Fn(u64) -> Option<Isometry3<f64>>,
    ) -> Option<MapJob> {
        if let Some(a) = accel
            && self.accel.len() < MAX_ACCEL_PER_MAP_JOB
        {
            self.accel.push((world_from_camera, a));
        }
        let mut moved = false;
        let mut keyframe_poses = Vec::with_capacity(self.keyframes.len());
        for (id, sent) in &mut self.keyframes {
            if let Some(now) = keyframe_pose(*id) {
                moved |= now != *sent;
                *sent = now;
                keyframe_poses.push((*id, now));
            }
        }
        retractions.retain(|r| self.keyframes.iter().any(|(id, _)| *id == r.keyframe));
        if keyframe.is_none() && !moved && retractions.is_empty() {
            return None;
        }
        if let Some(k) = &keyframe {
            self.keyframes.push_back((k.id, world_from_camera));
            while self.keyframes.len() > self.window {
                self.keyframes.pop_front();
            }
        }
        Some(MapJob { world_from_camera, keyframe, keyframe_poses, accel: std::mem::take(&mut self.accel), retractions })
    }

    /// The map lane could not take `job`: its keyframe is not in the map.
    pub fn refused(&mut self, job: &MapJob) {
        if let Some(k) = &job.keyframe {
            self.keyframes.retain(|(id, _)| *id != k.id);
        }
    }
}

/// Runs a map job: accelerometer samples, re-fusion of the keyframes whose pose
/// moved, the new keyframe's fusion, then the samples perception found moving
/// taken back out (each at the pose its keyframe is fused at now). Returns the
/// fusion time of the new keyframe.
pub fn apply(map: &SharedMap, job: &MapJob) -> Option<Duration> {
    let mut m = lock(map);
    for (pose, a) in &job.accel {
        m.builder.observe_accel(pose, a);
    }
    let moved = m.builder.moved_keyframes(|id| job.keyframe_poses.iter().find(|(k, _)| *k == id).map(|(_, p)| *p));
    if !moved.is_empty() || job.keyframe.is_some() {
        // Evicted blocks near the camera come back before anything is fused there.
        m.restore_near(&nalgebra::Point3::from(job.world_from_camera.translation.vector));
    }
    m.builder.refuse(&moved);
    let fused = job.keyframe.as_ref().and_then(|k| {
        let view = DepthView { depth: &k.depth.data, rgb: &k.color.data, exclude: k.exclude.as_deref(), classes: k.classes.as_deref() };
        match m.builder.add_keyframe(k.id, &job.world_from_camera, &view) {
            Ok(report) => {
                if report.stats.samples_over_block_budget > 0 {
                    tracing::warn!(
                        keyframe = k.id,
                        left_out = report.stats.samples_over_block_budget,
                        "the keyframe would start more than mapping.max_new_blocks_per_keyframe map blocks: samples left out"
                    );
                }
                Some(report.fuse_time)
            }
            Err(e) => {
                tracing::warn!(keyframe = k.id, "map fusion failed: {e}");
                None
            }
        }
    });
    let width = m.builder.camera_width();
    for r in &job.retractions {
        m.builder.retract(r.keyframe, r.pixel_test(width));
    }
    fused
}

/// The map's re-fusion window (keyframes whose poses it follows).
pub fn refuse_window(map: &SharedMap) -> usize {
    lock(map).builder.config().refuse_window
}

/// Quality of the keyframe images kept for the Foxglove export.
const KEYFRAME_IMAGE_QUALITY: u8 = 80;

/// The keyframe's colour with the pixels perception kept out of the map tinted red
/// (half way), as JPEG; `None` when encoding fails (the export then lacks it).
pub fn keyframe_image(k: &KeyframeJob) -> Option<crate::map::KeyframeImage> {
    let mut color = k.color.clone();
    if let Some(exclude) = &k.exclude {
        for (px, &out) in color.data.chunks_exact_mut(3).zip(exclude) {
            if out != 0 {
                px[0] = px[0] / 2 + 128;
                px[1] /= 2;
                px[2] /= 2;
            }
        }
    }
    let jpeg = stillmap_proto::codec::encode_color(stillmap_proto::pb::ColorEncoding::Jpeg, &color, KEYFRAME_IMAGE_QUALITY)
        .map_err(|e| tracing::warn!(keyframe = k.id, "keyframe image not kept: {e}"))
        .ok()?;
    Some(crate::map::KeyframeImage { id: k.id, time_ns: k.capture_time_ns, jpeg })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Translation3;

    fn keyframe(id: u64) -> KeyframeJob {
        KeyframeJob {
            id,
            capture_time_ns: id,
            color: ColorImage { width: 1, height: 1, data: vec![0; 3] },
            depth: DepthImage { width: 1, height: 1, data: vec![0] },
            exclude: None,
            classes: None,
            record: None,
        }
    }

    /// Only keyframes and moved keyframes make jobs; the window keeps the newest;
    /// accelerometer samples ride along with the next job.
    #[test]
    fn jobs_for_keyframes_and_moves_only() {
        let at = |x: f64| Isometry3::from_parts(Translation3::new(x, 0.0, 0.0), nalgebra::UnitQuaternion::identity());
        let mut h = Handoff::new(2);
        let poses = std::cell::RefCell::new(std::collections::HashMap::<u64, Isometry3<f64>>::new());
        let pose = |id: u64| poses.borrow().get(&id).copied();
        let up = Some(Vector3::new(0.0, -9.8, 0.0));
        assert!(h.job(at(0.0), up, None, Vec::new(), pose).is_none(), "no keyframe, nothing moved");
        poses.borrow_mut().insert(1, at(0.0));
        let j = h.job(at(0.0), up, Some(keyframe(1)), Vec::new(), pose).expect("keyframe job");
        assert_eq!(j.accel.len(), 2, "the earlier frame's sample rides along");
        assert!(h.job(at(0.1), None, None, Vec::new(), pose).is_none());
        poses.borrow_mut().insert(1, at(0.05)); // bundle adjustment moved keyframe 1
        let j = h.job(at(0.1), None, None, Vec::new(), pose).expect("re-fusion job");
        assert_eq!(j.keyframe_poses, vec![(1, at(0.05))]);
        assert!(h.job(at(0.1), None, None, Vec::new(), pose).is_none(), "sent once");
        for id in 2..=3 {
            poses.borrow_mut().insert(id, at(id as f64));
            h.job(at(id as f64), None, Some(keyframe(id)), Vec::new(), pose).expect("keyframe job");
        }
        let ids: Vec<u64> = h.keyframes.iter().map(|k| k.0).collect();
        assert_eq!(ids, [2, 3], "the window holds the newest two");
        poses.borrow_mut().insert(4, at(4.0));
        let j = h.job(at(4.0), None, Some(keyframe(4)), Vec::new(), pose).expect("keyframe job");
        h.refused(&j);
        let ids: Vec<u64> = h.keyframes.iter().map(|k| k.0).collect();
        assert_eq!(ids, [3], "a refused keyframe is not in the map's window");
        // Found-moving cells make a job for keyframes in the window only.
        let cells = |keyframe: u64| Retraction { keyframe, cells: vec![0], grid_width: 1, grid_height: 1, subsample: 1 };
        assert!(h.job(at(4.0), None, None, vec![cells(2), cells(4)], pose).is_none(), "2 left the window, 4 was refused");
        let j = h.job(at(4.0), None, None, vec![cells(2), cells(3)], pose).expect("retraction job");
        assert_eq!(j.retractions, vec![cells(3)]);
    }
}
