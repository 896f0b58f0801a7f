//! One session's map: fuses keyframes, keeps it following the trajectory, and
//! knows which way is up.
//!
//! **Following the trajectory.** Local bundle adjustment keeps moving the last few
//! keyframes after they are fused, and relocalization can place a new keyframe
//! far from the old ones. The builder keeps the fusion input of the last
//! `refuse_window` keyframes and the pose each was fused at; after every frame
//! the server hands it the tracker's current keyframe poses, and a keyframe that
//! moved more than `refuse_translation_m` / `refuse_rotation_deg` has its hits
//! taken out at the old pose and is fused again at the new one. Older keyframes
//! are outside the BA window and no longer move (the tracker has no loop closure
//! yet); their contribution stays where it was fused.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Point3, Unit, UnitQuaternion, Vector3};
use stillmap_tracking::Camera;

use crate::MappingError;
use crate::config::MappingConfig;
use crate::gravity::{Gravity, UpSource, floor_up, map_from_world};
use crate::map::{CameraRays, DepthView, FuseStats, FusionInput, VoxelMap};
use crate::voxel::{Block, BlockKey};

struct Fused {
    id: u64,
    world_from_camera: Isometry3<f64>,
    input: FusionInput,
}

/// What one keyframe cost and did.
#[derive(Debug, Clone, Copy, Default)]
pub struct KeyframeReport {
    pub stats: FuseStats,
    pub fuse_time: Duration,
    /// Blocks moved out of memory to stay within the budget.
    pub evicted: usize,
}

pub struct MapBuilder {
    rays: CameraRays,
    map: VoxelMap,
    gravity: Gravity,
    window: VecDeque<Fused>,
    keyframes: u64,
    refused: u64,
    retracted: u64,
    /// Evict beyond the block budget (only when something stores what is evicted).
    eviction: bool,
    evicted: Vec<(BlockKey, Block)>,
}

impl MapBuilder {
    pub fn new(camera: &Camera, config: MappingConfig) -> Result<Self, MappingError> {
        if camera.width < 2 || camera.height < 2 {
            return Err(MappingError::Input(format!("camera of {}x{} pixels", camera.width, camera.height)));
        }
        let gravity = Gravity::new(config.fallback_up_in_camera);
        Ok(Self {
            rays: CameraRays::new(camera),
            map: VoxelMap::new(config)?,
            gravity,
            window: VecDeque::new(),
            keyframes: 0,
            refused: 0,
            retracted: 0,
            eviction: false,
            evicted: Vec::new(),
        })
    }

    pub fn map(&self) -> &VoxelMap {
        &self.map
    }

    pub fn config(&self) -> &MappingConfig {
        self.map.config()
    }

    /// The camera's image width (pixels).
    pub fn camera_width(&self) -> u32 {
        self.rays.camera.width
    }

    /// An accelerometer sample of a tracked frame (used until the first keyframe).
    pub fn observe_accel(&mut self, world_from_camera: &Isometry3<f64>, accel_in_camera: &Vector3<f64>) -> bool {
        self.gravity.observe(world_from_camera, accel_in_camera)
    }

    /// The gravity-aligned map frame (fixed at the first keyframe), and where up came from.
    pub fn map_from_world(&self) -> Option<(UnitQuaternion<f64>, UpSource)> {
        self.gravity.frozen().map(|(up, source)| (map_from_world(&up), source))
    }

    pub fn up_in_world(&self) -> Option<(Unit<Vector3<f64>>, UpSource)> {
        self.gravity.frozen()
    }

    /// Restores a stored map frame.
    pub fn freeze_up(&mut self, up: Unit<Vector3<f64>>, source: UpSource) {
        self.gravity.freeze(up, source);
    }

    /// How far from the camera centre a keyframe can fuse or carve (metres).
    pub fn reach_m(&self) -> f64 {
        self.map.config().max_depth_m * self.rays.max_ray_norm()
    }

    pub fn keyframes(&self) -> u64 {
        self.keyframes
    }

    /// Keyframes fused again after their pose was corrected.
    pub fn refused(&self) -> u64 {
        self.refused
    }

    /// Fuses a new keyframe.
    pub fn add_keyframe(
        &mut self,
        id: u64,
        world_from_camera: &Isometry3<f64>,
        view: &DepthView<'_>,
    ) -> Result<KeyframeReport, MappingError> {
        let start = Instant::now();
        let input = self.map.prepare(&self.rays, view)?;
        if self.gravity.frozen().is_none() {
            let prior_in_camera = world_from_camera.rotation.inverse() * self.gravity.fallback();
            let points: Vec<[f32; 3]> = input.samples.iter().map(|s| s.point_in_camera).collect();
            let has_samples = self.gravity.has_samples();
            self.gravity.up_with(|| {
                if has_samples {
                    return None;
                }
                floor_up(&points, &prior_in_camera).map(|up| Unit::new_unchecked(world_from_camera.rotation * up.into_inner()))
            });
        }
        let stats = self.map.integrate(&self.rays, &input, world_from_camera);
        self.keyframes += 1;
        // A keyframe some of whose samples were left out (over
        // `max_new_blocks_per_keyframe`) is never re-fused nor retracted: taking its
        // samples back out would take hits it never added from blocks made since.
        if stats.samples_over_block_budget == 0 {
            self.window.push_back(Fused { id, world_from_camera: *world_from_camera, input });
        }
        while self.window.len() > self.map.config().refuse_window {
            self.window.pop_front();
        }
        let camera_in_world = Point3::from(world_from_camera.translation.vector);
        let evicted = if self.eviction { self.map.evict(&camera_in_world) } else { Vec::new() };
        let n = evicted.len();
        self.evicted.extend(evicted);
        Ok(KeyframeReport { stats, fuse_time: start.elapsed(), evicted: n })
    }

    /// Turns eviction beyond `max_resident_blocks` on: the caller then stores what
    /// [`take_evicted`](Self::take_evicted) returns. Off by default (nothing is dropped).
    pub fn enable_eviction(&mut self) {
        self.eviction = true;
    }

    /// Blocks evicted since the last call (the caller stores them).
    pub fn take_evicted(&mut self) -> Vec<(BlockKey, Block)> {
        std::mem::take(&mut self.evicted)
    }

    /// A restored map: its keyframe count and block stamps continue from the store.
    pub fn note_restored(&mut self, keyframes: u64, stamp: u64) {
        self.keyframes = self.keyframes.max(keyframes);
        self.map.set_change_stamp(stamp);
    }

    /// Puts a stored block back into memory.
    pub fn restore_block(&mut self, key: BlockKey, block: Block) {
        self.map.restore(key, block);
    }

    /// The fusion input of keyframe `id` while it is in the re-fusion window.
    pub fn input_of(&self, id: u64) -> Option<&FusionInput> {
        self.window.iter().find(|f| f.id == id).map(|f| &f.input)
    }

    /// Evicts beyond the budget now (a restored map), nearest to `camera_in_world` kept.
    pub fn evict_now(&mut self, camera_in_world: &Point3<f64>) -> Vec<(BlockKey, Block)> {
        self.map.evict(camera_in_world)
    }

    /// The recent keyframes whose pose `current_pose` reports moved beyond the
    /// re-fusion thresholds, with their new poses. Keyframes it does not know are kept.
    pub fn moved_keyframes(&self, mut current_pose: impl FnMut(u64) -> Option<Isometry3<f64>>) -> Vec<(u64, Isometry3<f64>)> {
        let cfg = self.map.config();
        self.window
            .iter()
            .filter_map(|f| {
                let now = current_pose(f.id)?;
                let delta = f.world_from_camera.inverse() * now;
                (delta.translation.vector.norm() > cfg.refuse_translation_m
                    || delta.rotation.angle().to_degrees() > cfg.refuse_rotation_deg)
                    .then_some((f.id, now))
            })
            .collect()
    }

    /// Re-fuses keyframes at corrected poses (from [`moved_keyframes`](Self::moved_keyframes)):
    /// hits out at the old pose, fused again at the new one.
    pub fn refuse(&mut self, moved: &[(u64, Isometry3<f64>)]) -> usize {
        let mut n = 0;
        for (id, now) in moved {
            let Some(k) = self.window.iter().position(|f| f.id == *id) else { continue };
            let f = &self.window[k];
            self.map.deintegrate(&f.input, &f.world_from_camera);
            let stats = self.map.integrate(&self.rays, &f.input, now);
            self.window[k].world_from_camera = *now;
            if stats.samples_over_block_budget > 0 {
                // As for a new keyframe: what was left out must never be taken out.
                self.window.remove(k);
            }
            n += 1;
        }
        self.refused += n as u64;
        n
    }

    /// Takes keyframe `id`'s samples at the pixels `covered` says (row-major index)
    /// back out of the map, for good (a re-fusion does not bring them back): they
    /// showed something later seen moving. Returns the samples taken out; 0 when
    /// the keyframe is no longer in the window.
    pub fn retract(&mut self, id: u64, covered: impl Fn(u32) -> bool) -> usize {
        let Some(f) = self.window.iter_mut().find(|f| f.id == id) else { return 0 };
        let mut taken = Vec::new();
        f.input.samples.retain(|s| {
            let out = covered(s.pixel);
            if out {
                taken.push(*s);
            }
            !out
        });
        if taken.is_empty() {
            return 0;
        }
        let pose = f.world_from_camera;
        self.map.deintegrate_samples(&taken, &pose);
        self.retracted += taken.len() as u64;
        taken.len()
    }

    /// Samples taken back out by [`retract`](Self::retract) so far.
    pub fn retracted(&self) -> u64 {
        self.retracted
    }

    /// [`moved_keyframes`](Self::moved_keyframes) then [`refuse`](Self::refuse).
    pub fn follow(&mut self, current_pose: impl FnMut(u64) -> Option<Isometry3<f64>>) -> usize {
        let moved = self.moved_keyframes(current_pose);
        self.refuse(&moved)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Translation3;

    #[test]
    fn a_corrected_keyframe_moves_its_surface() {
        let cam = Camera::pinhole(160, 120, 130.0, 130.0, 79.5, 59.5, 1000.0);
        let mut b = MapBuilder::new(&cam, MappingConfig::default()).unwrap();
        let depth = vec![2000u16; 160 * 120];
        let rgb = vec![100u8; 160 * 120 * 3];
        let view = DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: None };
        b.add_keyframe(7, &Isometry3::identity(), &view).unwrap();
        // A wall and no accelerometer: up from the configuration.
        assert_eq!(b.map_from_world().unwrap().1, UpSource::Config);
        let z_of = |b: &MapBuilder| b.map().occupied().map(|(_, c, _)| c.z).sum::<f64>() / b.map().stats().occupied_voxels as f64;
        assert!((z_of(&b) - 2.0).abs() < 0.02);
        // A 5 mm correction is ignored; 30 cm along z re-fuses the wall there.
        assert_eq!(b.follow(|id| (id == 7).then(|| Isometry3::translation(0.0, 0.0, 0.005))), 0);
        let moved = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.3), UnitQuaternion::identity());
        assert_eq!(b.follow(|id| (id == 7).then_some(moved)), 1);
        assert!((z_of(&b) - 2.3).abs() < 0.02, "{}", z_of(&b));
        assert_eq!(b.refused(), 1);
        assert_eq!(b.follow(|_| Some(moved)), 0, "already at its pose");
    }

    /// Samples a keyframe took from something later found moving leave the map,
    /// and a re-fusion of that keyframe does not bring them back.
    #[test]
    fn retracted_samples_leave_the_map_for_good() {
        let cam = Camera::pinhole(160, 120, 130.0, 130.0, 79.5, 59.5, 1000.0);
        let mut b = MapBuilder::new(&cam, MappingConfig::default()).unwrap();
        // A wall at 2 m; the left half of the image also shows a box at 1 m.
        let depth: Vec<u16> = (0..160 * 120).map(|i| if i % 160 < 80 { 1000 } else { 2000 }).collect();
        let rgb = vec![100u8; 160 * 120 * 3];
        let view = DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: None };
        b.add_keyframe(3, &Isometry3::identity(), &view).unwrap();
        let near = |b: &MapBuilder| b.map().occupied().filter(|(_, c, _)| c.z < 1.5).count();
        let before = (near(&b), b.map().stats().occupied_voxels);
        assert!(before.0 > 100);
        // The box moved off: its pixels (left half) are taken back.
        let taken = b.retract(3, |pixel| pixel % 160 < 80);
        assert_eq!(taken, 40 * 60, "every second pixel and row of the left half (stride 2)");
        assert_eq!(near(&b), 0, "the box is gone");
        assert_eq!(b.map().stats().occupied_voxels, before.1 - before.0, "the wall stays");
        assert_eq!(b.retract(3, |pixel| pixel % 160 < 80), 0, "taken once");
        assert_eq!(b.retract(9, |_| true), 0, "unknown keyframe");
        assert_eq!(b.retracted(), 40 * 60);
        let moved = Isometry3::from_parts(Translation3::new(0.0, 0.0, 0.3), UnitQuaternion::identity());
        assert_eq!(b.follow(|_| Some(moved)), 1);
        assert_eq!(near(&b), 0, "re-fused without the box");
    }
}
