//! ORB extraction (OpenCV), even spreading over the image, undistortion and depth
//! lookup, plus the grid index used by projection search.

use nalgebra::{Isometry3, Point2, Point3, UnitQuaternion};
use opencv::core::{KeyPoint, Mat, Vector};
use opencv::features2d::{ORB, ORB_ScoreType};
use opencv::prelude::*;

use crate::TrackingError;
use crate::camera::Camera;
use crate::config::TrackerConfig;

/// A 256-bit ORB descriptor.
pub type Descriptor = [u64; 4];

/// Hamming distance between two descriptors.
#[inline]
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    (a[0] ^ b[0]).count_ones() + (a[1] ^ b[1]).count_ones() + (a[2] ^ b[2]).count_ones() + (a[3] ^ b[3]).count_ones()
}

/// One keypoint of a frame.
#[derive(Debug, Clone)]
pub struct Feature {
    /// Where the detector found it in the raw (distorted) image.
    pub raw: Point2<f32>,
    /// Its ideal pinhole position (undistorted).
    pub ideal: Point2<f64>,
    /// Pyramid level it was detected at.
    pub octave: u8,
    /// Depth in metres, when valid and not on a depth edge.
    pub depth: Option<f64>,
}

impl Feature {
    /// The back-projected point in the camera frame, when the depth is valid.
    pub fn point_in_camera(&self, camera: &Camera) -> Option<Point3<f64>> {
        self.depth.map(|z| camera.unproject(&self.ideal, z))
    }
}

/// Features of one frame with their descriptors (same index).
#[derive(Debug, Clone, Default)]
pub struct FrameFeatures {
    pub features: Vec<Feature>,
    pub descriptors: Vec<Descriptor>,
    /// Keypoints dropped because they fell on dynamic pixels.
    pub masked_out: usize,
}

/// Image level scale factors: `scale[level]` multiplies level-0 pixel sizes.
pub fn level_scales(config: &TrackerConfig) -> Vec<f64> {
    (0..config.pyramid_levels.max(1)).map(|l| f64::from(config.scale_factor).powi(l as i32)).collect()
}

/// ORB extractor with even spreading; keeps its OpenCV detector between frames.
pub struct Extractor {
    orb: opencv::core::Ptr<ORB>,
    config: TrackerConfig,
}

/// Border (pixels) ORB needs around a keypoint for its 31×31 patch.
const ORB_EDGE_THRESHOLD: i32 = 19;
/// ORB's descriptor patch size.
const ORB_PATCH_SIZE: i32 = 31;
/// When at least 1/n of the detected candidates fall in the dynamic mask, the
/// static pixels are searched again on their own.
const REDETECT_MASKED_SHARE: usize = 4;

impl Extractor {
    pub fn new(config: &TrackerConfig) -> Result<Self, TrackingError> {
        let orb = ORB::create(
            i32::try_from(config.candidate_features).unwrap_or(i32::MAX),
            config.scale_factor,
            i32::try_from(config.pyramid_levels.max(1)).unwrap_or(8),
            ORB_EDGE_THRESHOLD,
            0,
            2,
            ORB_ScoreType::FAST_SCORE,
            ORB_PATCH_SIZE,
            i32::try_from(config.fast_threshold).unwrap_or(20),
        )?;
        Ok(Self { orb, config: config.clone() })
    }

    /// Extracts features from a grey image; `dynamic` (same size, nonzero = dynamic)
    /// removes keypoints before descriptors are computed.
    pub fn extract(&mut self, camera: &Camera, gray: &[u8], depth: &[u16], dynamic: Option<&[u8]>) -> Result<FrameFeatures, TrackingError> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let image = Mat::new_rows_cols_with_data(h as i32, w as i32, gray)?;
        let mut detected = Vector::<KeyPoint>::new();
        self.orb.detect(&image, &mut detected, &opencv::core::no_array())?;

        // Drop masked keypoints, then spread the rest evenly: round-robin over grid
        // cells, strongest first within each cell.
        let mut masked_out = 0;
        let cell = self.config.grid_cell_px.max(1) as usize;
        let (gw, gh) = (w.div_ceil(cell), h.div_ceil(cell));
        let mut cells: Vec<Vec<KeyPoint>> = vec![Vec::new(); gw * gh];
        for kp in detected.iter() {
            let (x, y) = (kp.pt().x.round() as usize, kp.pt().y.round() as usize);
            if x >= w || y >= h {
                continue;
            }
            if dynamic.is_some_and(|m| m[y * w + x] != 0) {
                masked_out += 1;
                continue;
            }
            cells[(y / cell) * gw + x / cell].push(kp);
        }
        // A large textured moving thing (a poster, a board) takes most of the
        // detector's candidates, and masking them leaves the static scene starved:
        // detect again within the static pixels only, so the candidates are spent
        // there. `masked_out` still counts the first detection's masked keypoints.
        if let Some(m) = dynamic
            && masked_out * REDETECT_MASKED_SHARE >= detected.len().max(1)
        {
            let static_pixels: Vec<u8> = m.iter().map(|&v| if v == 0 { 255 } else { 0 }).collect();
            let static_mask = Mat::new_rows_cols_with_data(h as i32, w as i32, &static_pixels)?;
            let mut again = Vector::<KeyPoint>::new();
            self.orb.detect(&image, &mut again, &static_mask)?;
            cells.iter_mut().for_each(Vec::clear);
            for kp in again.iter() {
                let (x, y) = (kp.pt().x.round() as usize, kp.pt().y.round() as usize);
                if x < w && y < h && m[y * w + x] == 0 {
                    cells[(y / cell) * gw + x / cell].push(kp);
                }
            }
        }
        for c in &mut cells {
            c.sort_by(|a, b| b.response().total_cmp(&a.response()));
        }
        let mut kept = Vector::<KeyPoint>::new();
        let mut round = 0;
        while kept.len() < self.config.features {
            let mut any = false;
            for c in &cells {
                if let Some(kp) = c.get(round) {
                    kept.push(kp.clone());
                    any = true;
                    if kept.len() == self.config.features {
                        break;
                    }
                }
            }
            if !any {
                break;
            }
            round += 1;
        }

        let mut descriptors = Mat::default();
        self.orb.compute(&image, &mut kept, &mut descriptors)?;
        let mut out = FrameFeatures { masked_out, ..Default::default() };
        for (i, kp) in kept.iter().enumerate() {
            let row = descriptors.at_row::<u8>(i as i32)?;
            let mut d = [0u64; 4];
            for (k, chunk) in row.chunks_exact(8).enumerate().take(4) {
                d[k] = u64::from_le_bytes(chunk.try_into().unwrap_or([0; 8]));
            }
            let raw = Point2::new(kp.pt().x, kp.pt().y);
            let ideal = camera.undistort(&Point2::new(f64::from(raw.x), f64::from(raw.y)));
            let depth = depth_at(camera, depth, w, h, raw, &self.config);
            out.features.push(Feature { raw, ideal, octave: kp.octave().clamp(0, 255) as u8, depth });
            out.descriptors.push(d);
        }
        Ok(out)
    }
}

/// Moves each feature to where it would have been seen at the middle row's time by a
/// rolling-shutter camera (`Camera::readout_s`) moving at constant velocity:
/// `previous_from_current` over `interval_s` (the frame's step, `world_from_camera`
/// advancing by it). A row read `Δt` after the middle one saw the scene from the
/// camera moved by that step scaled to `Δt`, so the keypoint's point is moved back
/// into the middle row's frame; its depth, registered to that colour row, moves with
/// it. A keypoint without depth turns with the rotation alone.
pub fn rectify_rolling_shutter(camera: &Camera, features: &mut [Feature], previous_from_current: &Isometry3<f64>, interval_s: f64) {
    if camera.readout_s == 0.0 || interval_s.is_nan() || interval_s <= 0.0 {
        return;
    }
    let angular_velocity = previous_from_current.rotation.scaled_axis() / interval_s;
    let linear_velocity = previous_from_current.translation.vector / interval_s;
    for f in features {
        let dt = camera.row_time_s(f64::from(f.raw.y));
        let rotation = UnitQuaternion::from_scaled_axis(angular_velocity * dt);
        let moved = match f.depth {
            Some(z) => rotation * camera.unproject(&f.ideal, z) + linear_velocity * dt,
            None => rotation * camera.unproject(&f.ideal, 1.0),
        };
        if let Some(ideal) = camera.project(&moved) {
            f.ideal = ideal;
            f.depth = f.depth.map(|_| moved.z);
        }
    }
}

/// Depth in metres at a raw pixel, if valid, in range and not on a depth edge.
fn depth_at(camera: &Camera, depth: &[u16], w: usize, h: usize, raw: Point2<f32>, config: &TrackerConfig) -> Option<f64> {
    let (x, y) = (raw.x.round() as isize, raw.y.round() as isize);
    if x < 1 || y < 1 || x as usize >= w - 1 || y as usize >= h - 1 {
        return None;
    }
    let (x, y) = (x as usize, y as usize);
    let centre = depth[y * w + x];
    if centre == 0 {
        return None;
    }
    let (mut lo, mut hi) = (u16::MAX, 0u16);
    for dy in 0..3 {
        for dx in 0..3 {
            let d = depth[(y + dy - 1) * w + x + dx - 1];
            if d == 0 {
                return None;
            }
            lo = lo.min(d);
            hi = hi.max(d);
        }
    }
    let z = f64::from(centre) / camera.depth_units_per_metre;
    if !(config.min_depth_m..=config.max_depth_m).contains(&z) {
        return None;
    }
    if f64::from(hi - lo) / camera.depth_units_per_metre > config.depth_edge_ratio * z {
        return None;
    }
    Some(z)
}

/// Buckets a frame's features by ideal position for radius queries.
pub struct GridIndex {
    cell: f64,
    cols: usize,
    rows: usize,
    buckets: Vec<Vec<u32>>,
}

/// Side of a grid-index cell in pixels.
const INDEX_CELL_PX: f64 = 16.0;

impl GridIndex {
    pub fn new(camera: &Camera, features: &[Feature]) -> Self {
        let cols = (f64::from(camera.width) / INDEX_CELL_PX).ceil() as usize + 1;
        let rows = (f64::from(camera.height) / INDEX_CELL_PX).ceil() as usize + 1;
        let mut buckets = vec![Vec::new(); cols * rows];
        for (i, f) in features.iter().enumerate() {
            if let Some(b) = Self::bucket(cols, rows, INDEX_CELL_PX, &f.ideal) {
                buckets[b].push(i as u32);
            }
        }
        Self { cell: INDEX_CELL_PX, cols, rows, buckets }
    }

    fn bucket(cols: usize, rows: usize, cell: f64, p: &Point2<f64>) -> Option<usize> {
        let (c, r) = ((p.x / cell).floor(), (p.y / cell).floor());
        (c >= 0.0 && r >= 0.0 && (c as usize) < cols && (r as usize) < rows).then(|| r as usize * cols + c as usize)
    }

    /// Calls `f` with the index of every feature within `radius` of `p`.
    pub fn for_each_near(&self, features: &[Feature], p: &Point2<f64>, radius: f64, mut f: impl FnMut(usize)) {
        let c0 = ((p.x - radius) / self.cell).floor().max(0.0) as usize;
        let r0 = ((p.y - radius) / self.cell).floor().max(0.0) as usize;
        let c1 = (((p.x + radius) / self.cell).floor().max(0.0) as usize).min(self.cols - 1);
        let r1 = (((p.y + radius) / self.cell).floor().max(0.0) as usize).min(self.rows - 1);
        let r2 = radius * radius;
        for r in r0..=r1 {
            for c in c0..=c1 {
                for &i in &self.buckets[r * self.cols + c] {
                    if (features[i as usize].ideal - p).norm_squared() <= r2 {
                        f(i as usize);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Translation3, Vector3};

    use super::*;
    use crate::synthetic::{ROLLING_SHUTTER_BAND_ROWS, RenderOptions, Scene, kinect_camera, render_rolling_shutter, sway_pose};
    use crate::tracker::to_gray;

    /// A rolling-shutter render of the room while the camera turns at 100°/s and
    /// moves at 0.5 m/s: every keypoint, moved to the middle row's time, lands where
    /// the middle row's camera sees its scene point, where it was off by pixels before.
    #[test]
    fn rolling_shutter_keypoints_are_moved_to_the_middle_row_time() {
        let camera = Camera { readout_s: 0.03, ..kinect_camera() };
        let config = TrackerConfig::default();
        let scene = Scene::room(7);
        let world_from_middle = sway_pose(10.0);
        // 100°/s and 0.5 m/s, as one 33 ms frame step.
        let interval_s = 0.033;
        let (angular_velocity, linear_velocity) = (Vector3::new(0.6, -1.6, 0.3), Vector3::new(0.4, -0.1, 0.3));
        let step =
            |t: f64| Isometry3::from_parts(Translation3::from(linear_velocity * t), UnitQuaternion::from_scaled_axis(angular_velocity * t));
        let world_from_camera_at = |t: f64| world_from_middle * step(t);
        let image = render_rolling_shutter(&scene, &camera, world_from_camera_at, &RenderOptions::default());
        let mut features = Extractor::new(&config)
            .expect("extractor")
            .extract(&camera, &to_gray(&image.rgb), &image.depth, None)
            .expect("extract")
            .features;
        // Where the middle row's camera sees each keypoint's scene point (the render
        // gave every band of rows the pose of its middle row).
        let truth: Vec<Option<Point2<f64>>> = features
            .iter()
            .map(|f| {
                let band_row = (f.raw.y.round() as usize / ROLLING_SHUTTER_BAND_ROWS * ROLLING_SHUTTER_BAND_ROWS) as f64
                    + (ROLLING_SHUTTER_BAND_ROWS as f64 - 1.0) / 2.0;
                let point_in_world = world_from_camera_at(camera.row_time_s(band_row)) * camera.unproject(&f.ideal, f.depth?);
                camera.project(&(world_from_middle.inverse() * point_in_world))
            })
            .collect();
        let median_error = |features: &[Feature]| {
            let mut e: Vec<f64> = features.iter().zip(&truth).filter_map(|(f, t)| t.map(|t| (f.ideal - t).norm())).collect();
            e.sort_by(f64::total_cmp);
            e[e.len() / 2]
        };
        let before = median_error(&features);
        rectify_rolling_shutter(&camera, &mut features, &step(interval_s), interval_s);
        let after = median_error(&features);
        assert!(before > 2.0, "as read, keypoints are {before} px from the middle row's view (median)");
        assert!(after < 0.3, "moved to the middle row's time they are {after} px off (was {before})");

        // A global shutter is left alone.
        let global = Camera { readout_s: 0.0, ..camera.clone() };
        let mut untouched = features.clone();
        rectify_rolling_shutter(&global, &mut untouched, &step(interval_s), interval_s);
        assert!(untouched.iter().zip(&features).all(|(a, b)| a.ideal == b.ideal));
    }
}
