//! Every tunable of the map, with its documented default.
//!
//! Defaults hold for any indoor RGB-D camera (structured light or time of flight,
//! VGA, 0.3–4 m); none is fitted to a particular clip.

use serde::{Deserialize, Serialize};

/// Map configuration (`[mapping]` in the server's TOML).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MappingConfig {
    /// Build a map at all.
    pub enabled: bool,
    /// Voxel edge, metres.
    pub voxel_size_m: f64,
    /// The paper's range filter: depth readings outside [min, max] metres are not fused
    /// (structured-light noise grows with z², so far readings smear surfaces).
    pub min_depth_m: f64,
    pub max_depth_m: f64,
    /// Every n-th pixel in x and y is fused (2: a quarter of a VGA frame; at 2 cm
    /// voxels and ≤ 4 m a voxel still gets several pixels).
    pub pixel_stride: usize,
    /// Occupancy log-odds added by a hit and by a miss (free-space carving), the
    /// clamping bounds and the occupied threshold. Clamping keeps the map able to
    /// change: a voxel at the upper bound needs `(clamp_max − occupied) / −miss`
    /// misses (5 by default) to become free, so an object that leaves is carved
    /// within a few keyframes of seeing what is behind it.
    pub log_odds_hit: f32,
    pub log_odds_miss: f32,
    pub log_odds_min: f32,
    pub log_odds_max: f32,
    pub occupied_log_odds: f32,
    /// Depth noise σ_z = a + b·z² (metres) of the sensor; a voxel is carved when the
    /// reading at its pixel lies more than `carve_sigmas`·σ_z (and at least two
    /// voxels) behind it.
    pub depth_noise_a: f64,
    pub depth_noise_b: f64,
    pub carve_sigmas: f64,
    /// A keyframe whose pose moved more than this since it was fused (local BA,
    /// relocalization) is fused again at its new pose.
    pub refuse_translation_m: f64,
    pub refuse_rotation_deg: f64,
    /// Keyframes kept (subsampled) for re-fusion: the local BA window and some margin.
    pub refuse_window: usize,
    /// Where "up" comes from when the client sends no accelerometer samples: this
    /// direction in the first camera's frame (x right, y down, z forward; the
    /// default assumes a camera mounted level).
    pub fallback_up_in_camera: [f64; 3],
    /// Highest surface drawn on the top-down tiles, metres above the first camera
    /// (cuts ceilings; lower it for a robot with a low camera).
    pub tiles_max_height_m: f64,
    /// Static objects: voxels whose winning class has at least this confidence, in
    /// 26-connected clusters of at least `objects_min_voxels`.
    pub objects_min_confidence: f32,
    pub objects_min_voxels: usize,
    /// Occupancy grid (ROS map_server): cell size and the default height band,
    /// metres relative to the first camera.
    pub occupancy_resolution_m: f64,
    pub occupancy_min_height_m: f64,
    pub occupancy_max_height_m: f64,
    /// Voxel blocks kept in memory per session; beyond it the blocks farthest from
    /// the camera go to the store (they come back when a query or the camera needs them).
    pub max_resident_blocks: usize,
    /// New voxel blocks one keyframe may start (each ~12 KiB): a real camera's
    /// keyframe starts a few hundred; the samples that would start more are left
    /// out and counted, so that a camera declaring a huge view (a 170° pinhole over
    /// 2 megapixels: one block per sample) cannot allocate gigabytes at once.
    pub max_new_blocks_per_keyframe: usize,
}

impl Default for MappingConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            voxel_size_m: 0.02,
            min_depth_m: 0.3,
            max_depth_m: 4.0,
            pixel_stride: 2,
            log_odds_hit: 0.85,
            log_odds_miss: -0.4,
            log_odds_min: -2.0,
            log_odds_max: 2.5,
            occupied_log_odds: 0.5,
            // Nguyen et al. 2012 (Kinect v1): σ_z ≈ 0.0012 + 0.0019·(z − 0.4)²; a + b·z²
            // bounds it from above over 0.3–4 m (the same model perception uses).
            depth_noise_a: 0.002,
            depth_noise_b: 0.003,
            carve_sigmas: 3.0,
            refuse_translation_m: 0.01,
            refuse_rotation_deg: 0.5,
            refuse_window: 12,
            fallback_up_in_camera: [0.0, -1.0, 0.0],
            tiles_max_height_m: 1.0,
            objects_min_confidence: 0.5,
            objects_min_voxels: 30,
            occupancy_resolution_m: 0.05,
            occupancy_min_height_m: -0.5,
            occupancy_max_height_m: 0.5,
            max_resident_blocks: 16384,
            max_new_blocks_per_keyframe: 8192,
        }
    }
}

/// Largest `max_depth_m`: the reach of a keyframe's rays, which also sizes the
/// blocks brought back from the store around it.
const MAX_DEPTH_M: f64 = 20.0;

impl MappingConfig {
    /// (Comparisons are negated so that NaN fails them too.)
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn validate(&self) -> Result<(), crate::MappingError> {
        let bad = |m: &str| Err(crate::MappingError::Config(m.to_string()));
        if !(self.voxel_size_m > 0.001 && self.voxel_size_m <= 1.0) {
            return bad("voxel_size_m must be in (0.001, 1] metres");
        }
        if !(self.min_depth_m >= 0.0 && self.max_depth_m > self.min_depth_m && self.max_depth_m <= MAX_DEPTH_M) {
            return bad("need 0 <= min_depth_m < max_depth_m <= 20 metres");
        }
        if !(1..=16).contains(&self.pixel_stride) {
            return bad("pixel_stride must be within 1..=16");
        }
        if !(self.log_odds_hit > 0.0 && self.log_odds_miss < 0.0) {
            return bad("log_odds_hit must be positive and log_odds_miss negative");
        }
        if !(self.log_odds_min < 0.0 && self.log_odds_max > self.occupied_log_odds && self.occupied_log_odds >= 0.0) {
            return bad("need log_odds_min < 0 <= occupied_log_odds < log_odds_max");
        }
        if !(self.occupancy_resolution_m >= self.voxel_size_m && self.occupancy_resolution_m <= 1.0) {
            return bad("occupancy_resolution_m must be within voxel_size_m..=1 metre");
        }
        let (low, high) = (self.occupancy_min_height_m, self.occupancy_max_height_m);
        if !(low.is_finite() && high.is_finite() && high > low) {
            return bad("occupancy_min_height_m and occupancy_max_height_m must be finite, the maximum above the minimum");
        }
        if !(self.carve_sigmas > 0.0 && self.carve_sigmas <= 100.0) {
            return bad("carve_sigmas must be within (0, 100]");
        }
        if !(self.depth_noise_a >= 0.0 && self.depth_noise_a.is_finite() && self.depth_noise_b >= 0.0 && self.depth_noise_b.is_finite()) {
            return bad("depth_noise_a and depth_noise_b must be finite and at least 0");
        }
        if !(self.refuse_translation_m >= 0.0
            && self.refuse_translation_m.is_finite()
            && self.refuse_rotation_deg >= 0.0
            && self.refuse_rotation_deg.is_finite())
        {
            return bad("refuse_translation_m and refuse_rotation_deg must be finite and at least 0");
        }
        let up = nalgebra::Vector3::from(self.fallback_up_in_camera);
        if !(up.iter().all(|v| v.is_finite()) && up.norm() >= 1e-3 && up.norm() <= 1e3) {
            return bad("fallback_up_in_camera must be finite, with a length within 0.001..=1000");
        }
        if !self.tiles_max_height_m.is_finite() {
            return bad("tiles_max_height_m must be finite");
        }
        if !(self.objects_min_confidence >= 0.0 && self.objects_min_confidence <= 1.0) {
            return bad("objects_min_confidence must be within [0, 1]");
        }
        if self.max_resident_blocks == 0 {
            return bad("max_resident_blocks must be at least 1");
        }
        if !(1..=1 << 20).contains(&self.max_new_blocks_per_keyframe) {
            return bad("max_new_blocks_per_keyframe must be within 1..=1048576");
        }
        Ok(())
    }
}
