//! A hello as it comes off the wire, through the checks a new session's hello
//! passes before anything is allocated for it: an accepted camera is within the
//! size limits, and every refusal maps to a status.
#![no_main]

use libfuzzer_sys::fuzz_target;
use prost::Message;
use stillmap_proto::pb;
use stillmap_server::pipeline::decode::MAX_IMAGE_SIDE;
use stillmap_server::session::validate_new_hello;

/// The server's default `session.max_camera_pixels`.
const MAX_PIXELS: u64 = 1920 * 1080;

fuzz_target!(|data: &[u8]| {
    let Ok(hello) = pb::Hello::decode(data) else { return };
    match validate_new_hello(&hello, MAX_PIXELS) {
        Ok(camera) => {
            assert!(camera.width >= 1 && camera.width <= MAX_IMAGE_SIDE);
            assert!(camera.height >= 1 && camera.height <= MAX_IMAGE_SIDE);
            assert!(u64::from(camera.width) * u64::from(camera.height) <= MAX_PIXELS);
            assert!(camera.fx.is_finite() && camera.fx > 0.0 && camera.fy.is_finite() && camera.fy > 0.0);
        }
        Err(e) => {
            let status = e.status();
            assert!(!status.message().is_empty());
        }
    }
});
