//! Which way is up: the gravity-aligned map frame.
//!
//! From the client's accelerometer when it sends one (specific force in the camera
//! frame: at rest it points up), averaged over the samples received until the
//! first keyframe is fused; otherwise from the configured direction in the first
//! camera's frame. Then it is frozen, so tiles never shift under a client.

use nalgebra::{Isometry3, Unit, UnitQuaternion, Vector3};

/// Where the up direction came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpSource {
    Accelerometer,
    Config,
}

impl UpSource {
    pub fn label(self) -> &'static str {
        match self {
            Self::Accelerometer => "accelerometer",
            Self::Config => "config",
        }
    }
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
    pub fn up(&mut self) -> (Unit<Vector3<f64>>, UpSource) {
        *self.frozen.get_or_insert_with(|| match Unit::try_new(self.sum_in_world, 1e-6) {
            Some(up) if self.samples > 0 => (up, UpSource::Accelerometer),
            _ => (Unit::try_new(self.fallback_in_world, 1e-9).unwrap_or(-Vector3::y_axis()), UpSource::Config),
        })
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

    #[test]
    fn config_fallback_without_samples() {
        let mut g = Gravity::new([0.0, -1.0, 0.0]);
        let (up, source) = g.up();
        assert_eq!(source, UpSource::Config);
        assert_eq!(up.into_inner(), -Vector3::y());
        assert!((map_from_world(&-Vector3::z_axis()) * -Vector3::z() - Vector3::z()).norm() < 1e-9);
    }
}
