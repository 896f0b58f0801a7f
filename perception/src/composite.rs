//! A generator of dynamic scenes from real static ones: pastes a textured planar
//! object that moves in *world* coordinates into real RGB-D frames, consistently
//! with the ground-truth camera poses (projection through the real lens model,
//! exact depth, occlusion by nearer scene surfaces), and returns its exact mask.
//!
//! Used by the tests and benches to score the dynamic mask with the camera moving.

use nalgebra::{Isometry3, Point2, Point3, Translation3, UnitQuaternion, Vector3};
use stillmap_tracking::Camera;

/// A textured rectangle, centred on its own origin in the x–y plane, facing +z.
#[derive(Debug, Clone)]
pub struct TexturedPlane {
    /// RGB8, row-major.
    pub texture: Vec<u8>,
    pub tex_width: usize,
    pub tex_height: usize,
    pub width_m: f64,
    pub height_m: f64,
}

/// Deterministic 64-bit LCG (Knuth's MMIX constants): textures are reproducible.
struct Lcg(u64);
impl Lcg {
    fn next_f32(&mut self) -> f32 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

impl TexturedPlane {
    /// A plane with a multi-scale value-noise texture: rich, non-repeating texture
    /// at every scale (like a poster or a patterned box), coloured from `seed`.
    pub fn noise(seed: u64, tex_width: usize, tex_height: usize, width_m: f64, height_m: f64) -> Self {
        let mut rng = Lcg(seed ^ 0x9e37_79b9_7f4a_7c15);
        let mut value = vec![0f32; tex_width * tex_height];
        let mut amplitude = 1.0f32;
        for cells in [4usize, 8, 16, 32, 64] {
            let lattice: Vec<f32> = (0..(cells + 1) * (cells + 1)).map(|_| rng.next_f32()).collect();
            for y in 0..tex_height {
                let gy = y as f32 / tex_height as f32 * cells as f32;
                let (y0, ty) = (gy.floor() as usize, gy.fract());
                for x in 0..tex_width {
                    let gx = x as f32 / tex_width as f32 * cells as f32;
                    let (x0, tx) = (gx.floor() as usize, gx.fract());
                    let at = |i: usize, j: usize| lattice[j.min(cells) * (cells + 1) + i.min(cells)];
                    let top = at(x0, y0) * (1.0 - tx) + at(x0 + 1, y0) * tx;
                    let bottom = at(x0, y0 + 1) * (1.0 - tx) + at(x0 + 1, y0 + 1) * tx;
                    value[y * tex_width + x] += amplitude * (top * (1.0 - ty) + bottom * ty);
                }
            }
            amplitude *= 0.7;
        }
        let (lo, hi) = value.iter().fold((f32::MAX, f32::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        let tint = [rng.next_f32(), rng.next_f32(), rng.next_f32()];
        let mut texture = Vec::with_capacity(tex_width * tex_height * 3);
        for v in value {
            let n = (v - lo) / (hi - lo).max(f32::EPSILON);
            for t in tint {
                texture.push((255.0 * (0.15 + 0.85 * n) * (0.5 + 0.5 * t)).clamp(0.0, 255.0) as u8);
            }
        }
        Self { texture, tex_width, tex_height, width_m, height_m }
    }

    /// A plane showing an RGB8 photo (a poster of a person, say).
    pub fn from_image(texture: Vec<u8>, tex_width: usize, tex_height: usize, width_m: f64, height_m: f64) -> Self {
        Self { texture, tex_width, tex_height, width_m, height_m }
    }

    fn sample(&self, a: f64, b: f64) -> [u8; 3] {
        // Plane coordinates (metres) → texel, bilinear.
        let u = ((a / self.width_m + 0.5) * self.tex_width as f64 - 0.5).clamp(0.0, (self.tex_width - 1) as f64);
        let v = ((0.5 - b / self.height_m) * self.tex_height as f64 - 0.5).clamp(0.0, (self.tex_height - 1) as f64);
        let (x0, y0) = (u.floor() as usize, v.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.tex_width - 1), (y0 + 1).min(self.tex_height - 1));
        let (tx, ty) = (u - x0 as f64, v - y0 as f64);
        let px = |x: usize, y: usize, c: usize| f64::from(self.texture[(y * self.tex_width + x) * 3 + c]);
        let mut out = [0u8; 3];
        for (c, o) in out.iter_mut().enumerate() {
            let top = px(x0, y0, c) * (1.0 - tx) + px(x1, y0, c) * tx;
            let bottom = px(x0, y1, c) * (1.0 - tx) + px(x1, y1, c) * tx;
            *o = (top * (1.0 - ty) + bottom * ty).round() as u8;
        }
        out
    }
}

/// Margin (pixels) around the projected corners searched for plane pixels (lens distortion bends edges).
const BBOX_MARGIN_PX: f64 = 12.0;

/// Renders `plane` at `camera_from_plane` into a real frame, in place: colour and
/// depth where the plane is in front of the scene (or the scene has no depth).
/// Returns the object's mask (1 = visible object pixel).
pub fn paste(camera: &Camera, plane: &TexturedPlane, camera_from_plane: &Isometry3<f64>, rgb: &mut [u8], depth: &mut [u16]) -> Vec<u8> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut mask = vec![0u8; w * h];
    let normal = camera_from_plane.rotation * Vector3::z();
    let origin = camera_from_plane.translation.vector;
    let plane_from_camera = camera_from_plane.inverse();
    // Image box of the projected corners.
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for (sa, sb) in [(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)] {
        let corner = camera_from_plane * Point3::new(sa * plane.width_m, sb * plane.height_m, 0.0);
        let Some(ideal) = camera.project(&corner) else { return mask };
        let raw = camera.distort(&ideal);
        x0 = x0.min(raw.x);
        y0 = y0.min(raw.y);
        x1 = x1.max(raw.x);
        y1 = y1.max(raw.y);
    }
    let clampx = |v: f64| v.clamp(0.0, w as f64) as usize;
    let clampy = |v: f64| v.clamp(0.0, h as f64) as usize;
    for y in clampy(y0 - BBOX_MARGIN_PX)..clampy(y1 + BBOX_MARGIN_PX) {
        for x in clampx(x0 - BBOX_MARGIN_PX)..clampx(x1 + BBOX_MARGIN_PX) {
            let ideal = camera.undistort(&Point2::new(x as f64, y as f64));
            let ray = Vector3::new((ideal.x - camera.cx) / camera.fx, (ideal.y - camera.cy) / camera.fy, 1.0);
            let denom = normal.dot(&ray);
            if denom.abs() < 1e-9 {
                continue;
            }
            let z = normal.dot(&origin) / denom;
            if z <= 0.0 {
                continue;
            }
            let p = plane_from_camera * Point3::from(ray * z);
            if p.x.abs() > plane.width_m / 2.0 || p.y.abs() > plane.height_m / 2.0 {
                continue;
            }
            let i = y * w + x;
            let raw_z = (z * camera.depth_units_per_metre).round();
            if raw_z < 1.0 || raw_z > f64::from(u16::MAX) {
                continue;
            }
            let scene = depth[i];
            if scene != 0 && f64::from(scene) <= raw_z {
                continue; // occluded by a nearer real surface
            }
            depth[i] = raw_z as u16;
            rgb[i * 3..i * 3 + 3].copy_from_slice(&plane.sample(p.x, p.y));
            mask[i] = 1;
        }
    }
    mask
}

/// Motion of the plane in the world: a circle of `radius_m` at constant speed in
/// the plane's own x–y plane around `world_from_centre`, one turn per `period_s`.
#[derive(Debug, Clone, Copy)]
pub struct CircularMotion {
    pub world_from_centre: Isometry3<f64>,
    pub radius_m: f64,
    pub period_s: f64,
}

impl CircularMotion {
    pub fn world_from_plane(&self, t_s: f64) -> Isometry3<f64> {
        let a = std::f64::consts::TAU * t_s / self.period_s;
        self.world_from_centre * Isometry3::from_parts(Translation3::new(self.radius_m * a.cos(), self.radius_m * a.sin(), 0.0), UnitQuaternion::identity())
    }
}

/// Ground truth interpolated at `t_ns` (linear translation, slerped rotation)
/// between the two stamped poses around it; `None` outside the list.
pub fn interpolate_pose(stamped: &[(u64, Isometry3<f64>)], t_ns: u64) -> Option<Isometry3<f64>> {
    let after = stamped.partition_point(|(t, _)| *t < t_ns);
    if after == 0 || after == stamped.len() {
        return stamped.get(after).filter(|(t, _)| *t == t_ns).map(|(_, p)| *p);
    }
    let ((t0, p0), (t1, p1)) = (stamped[after - 1], stamped[after]);
    let f = (t_ns - t0) as f64 / (t1 - t0).max(1) as f64;
    let t = p0.translation.vector.lerp(&p1.translation.vector, f);
    let r = p0.rotation.slerp(&p1.rotation, f);
    Some(Isometry3::from_parts(Translation3::from(t), r))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_plane_facing_the_camera_covers_its_projection_and_respects_occlusion() {
        let camera = Camera::pinhole(160, 120, 100.0, 100.0, 80.0, 60.0, 1000.0);
        let plane = TexturedPlane::noise(1, 64, 64, 0.395, 0.395);
        let camera_from_plane = Isometry3::translation(0.0, 0.0, 1.0);
        let mut rgb = vec![0u8; 160 * 120 * 3];
        // Background at 2 m, except a nearer post at 0.5 m over columns 70..75.
        let mut depth = vec![2000u16; 160 * 120];
        for y in 0..120 {
            for x in 70..75 {
                depth[y * 160 + x] = 500;
            }
        }
        let mask = paste(&camera, &plane, &camera_from_plane, &mut rgb, &mut depth);
        // 0.395 m at 1 m with f = 100 px → pixel centres 61..=99 in x and 41..=79 in y
        // (39 × 39), minus the post's 5 columns.
        let count = mask.iter().filter(|&&m| m != 0).count();
        assert_eq!(count, 39 * 39 - 5 * 39);
        assert_eq!(depth[60 * 160 + 80], 1000);
        assert_eq!(depth[60 * 160 + 72], 500);
        assert_eq!(mask[60 * 160 + 72], 0);
    }

    #[test]
    fn interpolation_between_ground_truth_samples() {
        let a = Isometry3::translation(0.0, 0.0, 0.0);
        let b = Isometry3::from_parts(Translation3::new(1.0, 0.0, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, 0.2));
        let p = interpolate_pose(&[(100, a), (200, b)], 150).unwrap();
        assert!((p.translation.vector.x - 0.5).abs() < 1e-12);
        assert!((p.rotation.angle() - 0.1).abs() < 1e-12);
        assert!(interpolate_pose(&[(100, a), (200, b)], 250).is_none());
        assert_eq!(interpolate_pose(&[(100, a), (200, b)], 100), Some(a));
    }
}
