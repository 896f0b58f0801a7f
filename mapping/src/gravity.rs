//! Which way is up: the gravity-aligned map frame.
//!
//! From the client's accelerometer when it sends one (specific force in the camera
//! frame: at rest it points up), averaged over the samples received until the
//! first keyframe is fused; else from the dominant floor plane of that first
//! keyframe (the largest plane below the camera whose normal is within
//! [`FLOOR_MAX_TILT_DEG`] of the configured up: a floor, or a desk top, both
//! horizontal); else from the configured direction
//! in the first camera's frame. Then it is frozen, so tiles never shift under a client.

use nalgebra::{Isometry3, Unit, UnitQuaternion, Vector3};

/// Where the up direction came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpSource {
    Accelerometer,
    FloorPlane,
    Config,
}

impl UpSource {
    pub fn label(self) -> &'static str {
        match self {
            Self::Accelerometer => "accelerometer",
            Self::FloorPlane => "floor_plane",
            Self::Config => "config",
        }
    }

    pub fn from_label(label: &str) -> Option<Self> {
        [Self::Accelerometer, Self::FloorPlane, Self::Config].into_iter().find(|s| s.label() == label)
    }
}

/// Floor candidates: planes whose normal is within this of the configured up. Wide
/// enough for a hand-held camera looking down at a desk (≈ 50° on TUM fr1); a level
/// camera sees walls at 90° from its up, so they never qualify, while a camera
/// pitched more than ≈ 45° sees walls as close as the floor and the larger plane wins.
pub const FLOOR_MAX_TILT_DEG: f64 = 60.0;
/// Points within this of a plane are its inliers (metres).
const FLOOR_INLIER_M: f64 = 0.02;
/// A floor must hold this share of the keyframe's points (and 500 at least).
const FLOOR_MIN_SHARE: f64 = 0.15;
const FLOOR_MIN_POINTS: usize = 500;
/// The floor lies at least this far below the camera (metres): a table top at
/// camera height is not a floor.
const FLOOR_MIN_DEPTH_BELOW_M: f64 = 0.2;
const FLOOR_RANSAC_ITERATIONS: usize = 300;

/// The dominant floor plane among `points_in_camera`: the up direction (the
/// plane's normal towards the camera) in the camera frame, or `None` when no
/// plane qualifies. Deterministic (fixed RANSAC seed).
pub fn floor_up(points_in_camera: &[[f32; 3]], prior_up_in_camera: &Vector3<f64>) -> Option<Unit<Vector3<f64>>> {
    let n = points_in_camera.len();
    let prior = Unit::try_new(*prior_up_in_camera, 1e-9)?;
    if n < FLOOR_MIN_POINTS {
        return None;
    }
    let p =
        |i: usize| Vector3::new(f64::from(points_in_camera[i][0]), f64::from(points_in_camera[i][1]), f64::from(points_in_camera[i][2]));
    let min_cos = FLOOR_MAX_TILT_DEG.to_radians().cos();
    // SplitMix64: reproducible samples.
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = || {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) % n as u64) as usize
    };
    let mut best: Option<(usize, Unit<Vector3<f64>>, f64)> = None;
    for _ in 0..FLOOR_RANSAC_ITERATIONS {
        let (a, b, c) = (p(next()), p(next()), p(next()));
        let Some(mut normal) = Unit::try_new((b - a).cross(&(c - a)), 1e-9) else { continue };
        if normal.dot(&prior) < 0.0 {
            normal = -normal;
        }
        if normal.dot(&prior) < min_cos {
            continue;
        }
        // Plane n·x + d = 0; the camera (origin) is at height d above it.
        let d = -normal.dot(&a);
        if d < FLOOR_MIN_DEPTH_BELOW_M {
            continue;
        }
        let inliers = (0..n).step_by(4).filter(|&i| (normal.dot(&p(i)) + d).abs() < FLOOR_INLIER_M).count() * 4;
        // Among qualifying planes the one with most support; ties go to the lower one.
        if best.is_none_or(|(k, _, bd)| inliers > k || (inliers == k && d > bd)) {
            best = Some((inliers, normal, d));
        }
    }
    let (inliers, normal, d) = best?;
    if inliers < FLOOR_MIN_POINTS || (inliers as f64) < FLOOR_MIN_SHARE * n as f64 {
        return None;
    }
    // Refine: least-squares normal of the inliers (smallest eigenvector of their covariance).
    let members: Vec<Vector3<f64>> = (0..n).map(p).filter(|q| (normal.dot(q) + d).abs() < FLOOR_INLIER_M).collect();
    let mean = members.iter().sum::<Vector3<f64>>() / members.len() as f64;
    let cov = members.iter().fold(nalgebra::Matrix3::zeros(), |acc, q| acc + (q - mean) * (q - mean).transpose());
    let eig = cov.symmetric_eigen();
    let k = eig.eigenvalues.imin();
    let mut refined = Unit::new_normalize(eig.eigenvectors.column(k).into_owned());
    if refined.dot(&prior) < 0.0 {
        refined = -refined;
    }
    Some(refined)
}

/// Accelerometer samples further than this from 1 g (m/s²) are the client
/// accelerating, not gravity, and are ignored.
const MAX_GRAVITY_DEVIATION: f64 = 1.5;
const STANDARD_GRAVITY: f64 = 9.80665;

#[derive(Debug, Clone)]
pub struct Gravity {
    sum_in_world: Vector3<f64>,
    samples: usize,
    frozen: Option<(Unit<Vector3<f64>>, UpSource)>,
    fallback_in_world: Vector3<f64>,
}

impl Gravity {
    /// `fallback_up_in_camera` is in the first camera's frame, which is the world frame.
    pub fn new(fallback_up_in_camera: [f64; 3]) -> Self {
        Self { sum_in_world: Vector3::zeros(), samples: 0, frozen: None, fallback_in_world: Vector3::from(fallback_up_in_camera) }
    }

    /// One accelerometer sample of a tracked frame. Returns whether it was used.
    pub fn observe(&mut self, world_from_camera: &Isometry3<f64>, accel_in_camera: &Vector3<f64>) -> bool {
        let g = accel_in_camera.norm();
        if self.frozen.is_some() || !g.is_finite() || (g - STANDARD_GRAVITY).abs() > MAX_GRAVITY_DEVIATION {
            return false;
        }
        self.sum_in_world += world_from_camera.rotation * (accel_in_camera / g);
        self.samples += 1;
        true
    }

    /// Freezes (on first use) and returns the up direction in the world frame.
    /// `floor`: the first keyframe's floor normal in the world frame, if it has one.
    pub fn up(&mut self) -> (Unit<Vector3<f64>>, UpSource) {
        self.up_with(|| None)
    }

    /// As [`up`](Self::up), asking `floor` for the floor normal (world frame) when
    /// there are no accelerometer samples.
    pub fn up_with(&mut self, floor: impl FnOnce() -> Option<Unit<Vector3<f64>>>) -> (Unit<Vector3<f64>>, UpSource) {
        if let Some(f) = self.frozen {
            return f;
        }
        let up = match Unit::try_new(self.sum_in_world, 1e-6) {
            Some(up) if self.samples > 0 => (up, UpSource::Accelerometer),
            _ => match floor() {
                Some(up) => (up, UpSource::FloorPlane),
                None => (Unit::try_new(self.fallback_in_world, 1e-9).unwrap_or(-Vector3::y_axis()), UpSource::Config),
            },
        };
        self.frozen = Some(up);
        up
    }

    /// The configured up (world frame).
    pub fn fallback(&self) -> Vector3<f64> {
        self.fallback_in_world
    }

    /// Whether accelerometer samples arrived (the floor is then not needed).
    pub fn has_samples(&self) -> bool {
        self.samples > 0
    }

    pub fn frozen(&self) -> Option<(Unit<Vector3<f64>>, UpSource)> {
        self.frozen
    }

    /// Sets the frozen direction (a map loaded from the store).
    pub fn freeze(&mut self, up: Unit<Vector3<f64>>, source: UpSource) {
        self.frozen = Some((up, source));
    }
}

/// The rotation taking the world's up to the map's +z (no yaw or translation added:
/// the map origin is the first camera's centre).
pub fn map_from_world(up_in_world: &Unit<Vector3<f64>>) -> UnitQuaternion<f64> {
    UnitQuaternion::rotation_between(up_in_world, &Vector3::z())
        .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accelerometer_wins_and_is_frozen() {
        let mut g = Gravity::new([0.0, -1.0, 0.0]);
        let tilt = Isometry3::rotation(Vector3::x() * 0.3);
        assert!(g.observe(&tilt, &Vector3::new(0.0, -9.8, 0.0)));
        assert!(!g.observe(&tilt, &Vector3::new(0.0, -25.0, 0.0)), "a shake is not gravity");
        let (up, source) = g.up();
        assert_eq!(source, UpSource::Accelerometer);
        assert!((up.into_inner() - tilt.rotation * -Vector3::y()).norm() < 1e-9);
        assert!(!g.observe(&Isometry3::identity(), &Vector3::new(9.8, 0.0, 0.0)));
        assert_eq!(g.up().0, up);
        let r = map_from_world(&up);
        assert!((r * up.into_inner() - Vector3::z()).norm() < 1e-9);
    }

    /// A camera pitched 30° down, 1.2 m above a floor: the floor gives up exactly
    /// where the configured "−y of the camera" would be 30° off.
    #[test]
    fn the_floor_plane_gives_up_when_there_is_no_accelerometer() {
        let pitch = 30f64.to_radians();
        // Up in the camera frame for a camera pitched down by `pitch`.
        let up = Vector3::new(0.0, -pitch.cos(), -pitch.sin());
        let mut points = Vec::new();
        for v in 0..60 {
            for u in 0..80 {
                let ray = Vector3::new((f64::from(u) - 40.0) / 60.0, (f64::from(v) - 30.0) / 60.0, 1.0);
                let t = -1.2 / ray.dot(&up);
                if t > 0.0 && t < 6.0 {
                    let q = ray * t;
                    // A little sensor noise.
                    let noise = 0.003 * ((u * 7 + v * 13) % 5) as f64 / 5.0;
                    points.push([q.x as f32, (q.y + noise) as f32, q.z as f32]);
                }
            }
        }
        let found = floor_up(&points, &-Vector3::y()).expect("a floor");
        assert!(found.angle(&up).to_degrees() < 1.0, "{found:?} vs {up:?}");
        // A wall in front is no floor.
        let wall: Vec<[f32; 3]> = (0..2000).map(|i| [(i % 50) as f32 * 0.02 - 0.5, (i / 50) as f32 * 0.02 - 0.4, 2.0]).collect();
        assert_eq!(floor_up(&wall, &-Vector3::y()), None);
        let mut g = Gravity::new([0.0, -1.0, 0.0]);
        assert_eq!(g.up_with(|| Some(Unit::new_normalize(up))).1, UpSource::FloorPlane);
        assert_eq!(UpSource::from_label("floor_plane"), Some(UpSource::FloorPlane));
    }

    #[test]
    fn config_fallback_without_samples() {
        let mut g = Gravity::new([0.0, -1.0, 0.0]);
        let (up, source) = g.up();
        assert_eq!(source, UpSource::Config);
        assert_eq!(up.into_inner(), -Vector3::y());
        assert!((map_from_world(&-Vector3::z_axis()) * -Vector3::z() - Vector3::z()).norm() < 1e-9);
    }
}
