//! A hello through the checks a new session's hello passes before anything is
//! allocated for it, both as bytes off the wire and built field by field from
//! the input (so every check is reached, not only "no camera"): an accepted
//! camera is within the size limits with usable intrinsics, and every refusal
//! maps to a status with a message.
#![no_main]

use libfuzzer_sys::fuzz_target;
use prost::Message;
use stillmap_proto::pb;
use stillmap_server::pipeline::decode::{MAX_IMAGE_SIDE, MIN_IMAGE_SIDE};
use stillmap_server::session::validate_new_hello;

/// The server's default `session.max_camera_pixels`.
const MAX_PIXELS: u64 = 1920 * 1080;

/// Reads fields off the input, zeros once it runs out.
struct Bytes<'a>(&'a [u8]);

impl Bytes<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0; N];
        let n = N.min(self.0.len());
        out[..n].copy_from_slice(&self.0[..n]);
        self.0 = &self.0[n..];
        out
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.take())
    }
    fn string(&mut self) -> String {
        let [n] = self.take();
        let n = usize::from(n).min(self.0.len());
        let s = String::from_utf8_lossy(&self.0[..n]).into_owned();
        self.0 = &self.0[n..];
        s
    }
}

fn built(data: &[u8]) -> pb::Hello {
    let mut b = Bytes(data);
    let robot_id = b.string();
    let fleet = b.string();
    let camera = pb::CameraInfo {
        width: b.u32() % (2 * MAX_IMAGE_SIDE),
        height: b.u32() % (2 * MAX_IMAGE_SIDE),
        fx: b.f64(),
        fy: b.f64(),
        cx: b.f64(),
        cy: b.f64(),
        distortion_model: (b.u32() % 4) as i32,
        distortion_coeffs: (0..b.u32() % 8).map(|_| b.f64()).collect(),
        depth_units_per_metre: b.f64(),
        color_encoding: (b.u32() % 5) as i32,
        depth_encoding: (b.u32() % 5) as i32,
        nominal_rate_hz: b.f64(),
        rolling_shutter_readout_s: b.f64(),
        exposure_time_offset_s: b.f64(),
        calibration_source: b.string(),
    };
    pb::Hello { robot_id, fleet, camera: Some(camera), ..Default::default() }
}

fuzz_target!(|data: &[u8]| {
    let [mode, rest @ ..] = data else { return };
    let hello = if mode & 1 == 0 {
        let Ok(hello) = pb::Hello::decode(rest) else { return };
        hello
    } else {
        built(rest)
    };
    match validate_new_hello(&hello, MAX_PIXELS) {
        Ok(camera) => {
            assert!((MIN_IMAGE_SIDE..=MAX_IMAGE_SIDE).contains(&camera.width) && (MIN_IMAGE_SIDE..=MAX_IMAGE_SIDE).contains(&camera.height));
            assert!(u64::from(camera.width) * u64::from(camera.height) <= MAX_PIXELS);
            assert!(camera.fx.is_finite() && camera.fx > 0.0 && camera.fy.is_finite() && camera.fy > 0.0);
            assert!(camera.cx.is_finite() && camera.cy.is_finite());
            assert!(camera.depth_units_per_metre.is_finite() && camera.depth_units_per_metre > 0.0);
        }
        Err(e) => assert!(!e.status().message().is_empty()),
    }
});
