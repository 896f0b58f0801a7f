//! The camera model: pinhole intrinsics plus optional plumb-bob (Brown–Conrady)
//! distortion, and depth back-projection.

use nalgebra::{Point2, Point3};

/// Pinhole intrinsics with optional radial–tangential distortion, in pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Plumb-bob coefficients k1, k2, p1, p2, k3 (OpenCV order); `None` for an ideal pinhole.
    pub distortion: Option<[f64; 5]>,
    /// Raw depth units per metre (5000 for TUM, 1000 for OpenNI millimetres).
    pub depth_units_per_metre: f64,
    /// Rolling-shutter readout of the colour camera: seconds from the first row's
    /// exposure to the last row's, rows read top to bottom (0 = global shutter).
    /// Poses then refer to the middle row's time.
    pub readout_s: f64,
}

/// Iterations of the fixed-point undistortion; converges to < 1e-6 px for TUM-like lenses.
const UNDISTORT_ITERATIONS: usize = 10;

impl Camera {
    /// An ideal pinhole camera (no distortion).
    pub fn pinhole(width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64, depth_units_per_metre: f64) -> Self {
        Self { width, height, fx, fy, cx, cy, distortion: None, depth_units_per_metre, readout_s: 0.0 }
    }

    /// Projects a point in the camera frame (z forward) to an ideal (undistorted) pixel.
    /// Returns `None` behind the camera.
    pub fn project(&self, point_in_camera: &Point3<f64>) -> Option<Point2<f64>> {
        if point_in_camera.z <= 0.0 {
            return None;
        }
        let inv_z = 1.0 / point_in_camera.z;
        Some(Point2::new(self.fx * point_in_camera.x * inv_z + self.cx, self.fy * point_in_camera.y * inv_z + self.cy))
    }

    /// Back-projects an ideal (undistorted) pixel at depth `z` metres.
    pub fn unproject(&self, ideal_pixel: &Point2<f64>, z: f64) -> Point3<f64> {
        Point3::new((ideal_pixel.x - self.cx) / self.fx * z, (ideal_pixel.y - self.cy) / self.fy * z, z)
    }

    /// Seconds between the exposure of raw row `row` and the middle row's (negative
    /// above the middle); 0 for a global shutter.
    pub fn row_time_s(&self, row: f64) -> f64 {
        if self.height == 0 {
            return 0.0;
        }
        (row - (f64::from(self.height) - 1.0) / 2.0) / f64::from(self.height) * self.readout_s
    }

    /// Whether an ideal pixel lies inside the image.
    pub fn contains(&self, ideal_pixel: &Point2<f64>) -> bool {
        ideal_pixel.x >= 0.0 && ideal_pixel.y >= 0.0 && ideal_pixel.x < self.width as f64 && ideal_pixel.y < self.height as f64
    }

    /// Maps a raw (distorted) image pixel to its ideal pinhole position.
    pub fn undistort(&self, raw_pixel: &Point2<f64>) -> Point2<f64> {
        let Some([k1, k2, p1, p2, k3]) = self.distortion else {
            return *raw_pixel;
        };
        let xd = (raw_pixel.x - self.cx) / self.fx;
        let yd = (raw_pixel.y - self.cy) / self.fy;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..UNDISTORT_ITERATIONS {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            x = (xd - dx) / radial;
            y = (yd - dy) / radial;
        }
        Point2::new(x * self.fx + self.cx, y * self.fy + self.cy)
    }

    /// Maps an ideal pinhole pixel to where the lens puts it in the raw image.
    pub fn distort(&self, ideal_pixel: &Point2<f64>) -> Point2<f64> {
        let Some([k1, k2, p1, p2, k3]) = self.distortion else {
            return *ideal_pixel;
        };
        let x = (ideal_pixel.x - self.cx) / self.fx;
        let y = (ideal_pixel.y - self.cy) / self.fy;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        Point2::new(xd * self.fx + self.cx, yd * self.fy + self.cy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// freiburg1's intrinsics and distortion, as a global shutter.
    fn fr1() -> Camera {
        Camera { readout_s: 0.0, ..crate::testing::fr1_camera() }
    }

    #[test]
    fn undistort_inverts_distort_over_the_image() {
        let cam = fr1();
        for &(u, v) in &[(0.0, 0.0), (639.0, 479.0), (320.0, 240.0), (10.0, 470.0), (600.0, 30.0)] {
            let raw = Point2::new(u, v);
            let back = cam.distort(&cam.undistort(&raw));
            assert!((back - raw).norm() < 1e-3, "{raw} -> {back}");
        }
    }

    #[test]
    fn project_unproject_round_trip() {
        let cam = fr1();
        let p = Point3::new(0.3, -0.2, 1.7);
        let px = cam.project(&p).unwrap();
        let q = cam.unproject(&px, 1.7);
        assert!((p - q).norm() < 1e-12);
        assert!(cam.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }
}
