//! A generator of dynamic scenes from real static ones: pastes a textured planar
//! object that moves in *world* coordinates into real RGB-D frames, consistently
//! with the ground-truth camera poses (projection through the real lens model,
//! exact depth, occlusion by nearer scene surfaces), and returns its exact mask.
//! An object is a rectangle ([`TexturedPlane::noise`], a board) or a cut-out
//! ([`TexturedPlane::cutout`]: a person cut from a photo by the segmenter's own
//! mask, a billboard); it moves in a circle ([`CircularMotion`]) or walks and stops
//! along waypoints ([`StopAndGo`]).
//!
//! Used by the tests and benches to score the dynamic mask with the camera moving.

use nalgebra::{Isometry3, Point2, Point3, Translation3, UnitQuaternion, Vector3};
use stillmap_tracking::Camera;

use crate::segment::Segmentation;

/// A textured rectangle, centred on its own origin in the x–y plane, facing +z.
#[derive(Debug, Clone)]
pub struct TexturedPlane {
    /// RGB8, row-major.
    pub texture: Vec<u8>,
    pub tex_width: usize,
    pub tex_height: usize,
    pub width_m: f64,
    pub height_m: f64,
    /// Per texel, 0 = transparent (a cut-out's background); `None`: opaque.
    pub alpha: Option<Vec<u8>>,
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
        Self { texture, tex_width, tex_height, width_m, height_m, alpha: None }
    }

    /// A plane showing an RGB8 photo (a poster of a person, say).
    pub fn from_image(texture: Vec<u8>, tex_width: usize, tex_height: usize, width_m: f64, height_m: f64) -> Self {
        Self { texture, tex_width, tex_height, width_m, height_m, alpha: None }
    }

    /// A billboard cut out of an RGB8 photo (`width × height`) along instance `id`
    /// of its segmentation (the segmenter's own mask), `height_m` tall, as wide as
    /// the instance's box keeps the photo's aspect. `None` when the instance has no
    /// pixels in the photo.
    pub fn cutout(rgb: &[u8], width: u32, height: u32, segmentation: &Segmentation, id: u16, height_m: f64) -> Option<Self> {
        let (w, h) = (width as usize, height as usize);
        if rgb.len() != w * h * 3 || segmentation.instance_map.len() != w * h {
            return None;
        }
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
        for (i, _) in segmentation.instance_map.iter().enumerate().filter(|(_, m)| **m == id) {
            let (x, y) = (i % w, i / w);
            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
        }
        if x0 > x1 || y0 > y1 {
            return None;
        }
        let (tw, th) = (x1 - x0 + 1, y1 - y0 + 1);
        let mut texture = Vec::with_capacity(tw * th * 3);
        let mut alpha = Vec::with_capacity(tw * th);
        for y in y0..=y1 {
            texture.extend_from_slice(&rgb[(y * w + x0) * 3..(y * w + x1 + 1) * 3]);
            alpha.extend(segmentation.instance_map[y * w + x0..=y * w + x1].iter().map(|&m| u8::from(m == id)));
        }
        let width_m = height_m * tw as f64 / th as f64;
        Some(Self { texture, tex_width: tw, tex_height: th, width_m, height_m, alpha: Some(alpha) })
    }

    /// Whether the texel at plane coordinates (metres) is part of the object.
    fn opaque(&self, a: f64, b: f64) -> bool {
        let Some(alpha) = &self.alpha else { return true };
        let u = ((a / self.width_m + 0.5) * self.tex_width as f64).floor().clamp(0.0, (self.tex_width - 1) as f64) as usize;
        let v = ((0.5 - b / self.height_m) * self.tex_height as f64).floor().clamp(0.0, (self.tex_height - 1) as f64) as usize;
        alpha[v * self.tex_width + u] != 0
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
            if p.x.abs() > plane.width_m / 2.0 || p.y.abs() > plane.height_m / 2.0 || !plane.opaque(p.x, p.y) {
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
        self.world_from_centre
            * Isometry3::from_parts(Translation3::new(self.radius_m * a.cos(), self.radius_m * a.sin(), 0.0), UnitQuaternion::identity())
    }
}

/// An object that walks and stops: its centre moves in straight lines between
/// waypoints `(t_s, position in the world)`, at constant speed between two of
/// them; two waypoints at one position make it stand still between their times.
/// Before the first waypoint and after the last it stays at their positions. It
/// keeps `rotation` (world_from_plane's) throughout: a billboard facing one way.
#[derive(Debug, Clone)]
pub struct StopAndGo {
    pub waypoints: Vec<(f64, Point3<f64>)>,
    pub rotation: UnitQuaternion<f64>,
}

impl StopAndGo {
    pub fn world_from_plane(&self, t_s: f64) -> Isometry3<f64> {
        let position = match self.waypoints.iter().position(|(t, _)| *t > t_s) {
            None => self.waypoints.last().map_or_else(Point3::origin, |w| w.1),
            Some(0) => self.waypoints[0].1,
            Some(k) => {
                let ((t0, p0), (t1, p1)) = (self.waypoints[k - 1], self.waypoints[k]);
                let f = if t1 > t0 { (t_s - t0) / (t1 - t0) } else { 1.0 };
                Point3::from(p0.coords.lerp(&p1.coords, f))
            }
        };
        Isometry3::from_parts(Translation3::from(position.coords), self.rotation)
    }

    /// Whether the object stands still at `t_s` (between two waypoints at one place).
    pub fn standing(&self, t_s: f64) -> bool {
        let a = self.world_from_plane(t_s - 0.01).translation.vector;
        let b = self.world_from_plane(t_s + 0.01).translation.vector;
        (a - b).norm() < 1e-9
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

    /// A cut-out keeps the instance's pixels only: its transparent texels neither
    /// colour the frame nor touch its depth or mask.
    #[test]
    fn a_cutout_pastes_only_its_instance() {
        // A 4×4 photo whose instance 1 is the left two columns of the middle rows.
        let rgb: Vec<u8> = (0..16).flat_map(|i| [i as u8 * 10, 0, 0]).collect();
        let mut seg = Segmentation::empty(4, 4);
        for y in 1..3 {
            for x in 0..2 {
                seg.instance_map[y * 4 + x] = 1;
            }
        }
        let plane = TexturedPlane::cutout(&rgb, 4, 4, &seg, 1, 0.395).expect("cut-out");
        assert_eq!((plane.tex_width, plane.tex_height), (2, 2), "the instance's box");
        assert!((plane.width_m - 0.395).abs() < 1e-12, "square box, square billboard");
        assert_eq!(&plane.texture[..6], &[40, 0, 0, 50, 0, 0], "the photo's pixels (4, 5) start the texture");
        assert!(TexturedPlane::cutout(&rgb, 4, 4, &seg, 2, 0.4).is_none(), "no such instance");
        // Now a 2×2 texture with its top-right texel transparent.
        let mut plane = plane;
        plane.alpha = Some(vec![1, 0, 1, 1]);
        let camera = Camera::pinhole(160, 120, 100.0, 100.0, 80.0, 60.0, 1000.0);
        let mut out_rgb = vec![0u8; 160 * 120 * 3];
        let mut depth = vec![2000u16; 160 * 120];
        let mask = paste(&camera, &plane, &Isometry3::translation(0.0, 0.0, 1.0), &mut out_rgb, &mut depth);
        // 0.395 m at 1 m, f = 100 px: pixel centres 61..=99 × 41..=79 (39 × 39). The
        // plane's +x is the image's +x and its +y the image's +y (down), and texture
        // row 0 is the plane's top (+y): the top-right texel lands on image columns
        // 80..=99 (plane x ≥ 0) and rows 61..=79 (plane y > 0), 20 × 19 pixels.
        let count = mask.iter().filter(|&&m| m != 0).count();
        assert_eq!(count, 39 * 39 - 20 * 19);
        let (transparent, opaque) = (70 * 160 + 90, 50 * 160 + 90);
        assert_eq!((mask[transparent], depth[transparent]), (0, 2000), "transparent: the scene stays");
        assert_eq!((mask[opaque], depth[opaque]), (1, 1000));
    }

    #[test]
    fn stop_and_go_walks_stands_and_walks_on() {
        let motion = StopAndGo {
            waypoints: vec![
                (0.0, Point3::new(0.0, 0.0, 0.0)),
                (1.0, Point3::new(1.0, 0.0, 0.0)),
                (2.0, Point3::new(1.0, 0.0, 0.0)),
                (3.0, Point3::new(1.0, 2.0, 0.0)),
            ],
            rotation: UnitQuaternion::identity(),
        };
        let at = |t: f64| motion.world_from_plane(t).translation.vector;
        assert!((at(0.5) - Vector3::new(0.5, 0.0, 0.0)).norm() < 1e-12);
        assert!((at(1.5) - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12, "standing");
        assert!((at(2.5) - Vector3::new(1.0, 1.0, 0.0)).norm() < 1e-12);
        assert!((at(-1.0) - Vector3::zeros()).norm() < 1e-12 && (at(9.0) - Vector3::new(1.0, 2.0, 0.0)).norm() < 1e-12);
        assert!(motion.standing(1.5) && !motion.standing(0.5) && !motion.standing(2.5));
    }
}
