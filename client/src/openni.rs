//! OpenNI2 devices through Debian's libopenni2: colour + depth, depth registered
//! to colour, mirroring off. `openni2:Dummy` is OpenNI2's built-in hardware-free
//! device (a moving blob at 2 m), used by the tests.
//!
//! `openni2::shutdown()` is never called: after the Dummy device it segfaults
//! inside the C++ library (see shared/notes/build-recipe.md, pitfall 6).

use std::mem::ManuallyDrop;

use openni2::{Device, OniDepthPixel, OniRGB888Pixel, PixelFormat, SensorType, Stream};
use stillmap_proto::codec::{ColorImage, DepthImage};
use stillmap_proto::pb::{self, DistortionModel};

use crate::ClientError;
use crate::calibration::{CameraOptions, SourceCamera};
use crate::source::{FrameSource, RawFrame};

/// Depth units per metre of OpenNI2's two metric depth formats.
const DEPTH_1_MM_UNITS: f64 = 1000.0;
const DEPTH_100_UM_UNITS: f64 = 10_000.0;
/// Nominal field of view of PrimeSense-class sensors (Kinect v1, Xtion), radians,
/// used with `--allow-default-intrinsics` when a driver reports none (the Dummy
/// device does not).
const NOMINAL_HFOV_RAD: f64 = 1.0144; // 58.1 degrees
const NOMINAL_VFOV_RAD: f64 = 0.7898; // 45.3 degrees

pub struct OpenNiSource {
    // Never destroyed: destroying the Dummy device's streams crashes libDummyDevice
    // intermittently (measured: 2 segfaults in 8 runs), like OpenNI2's shutdown.
    // They live until the process exits, as the device does.
    depth: ManuallyDrop<Stream<'static>>,
    color: ManuallyDrop<Stream<'static>>,
    camera: pb::CameraInfo,
    max_frames: Option<usize>,
    read: usize,
    last_ns: u64,
}

fn err(what: &str) -> impl Fn(openni2::Status) -> ClientError + '_ {
    move |e| ClientError::Source(format!("OpenNI2 {what}: {e}"))
}

impl OpenNiSource {
    pub fn open(uri: Option<&str>, max_frames: Option<usize>, options: &CameraOptions) -> Result<Self, ClientError> {
        openni2::init().map_err(err("init"))?;
        let device = match uri {
            Some(uri) => Device::open_uri(uri).map_err(|e| match uri {
                "Dummy" => ClientError::Source(format!("OpenNI2 Dummy device: {e}")),
                _ => ClientError::Source(format!("no OpenNI2 device found at {uri:?}: {e}")),
            })?,
            None => {
                if openni2::get_device_list().is_empty() {
                    return Err(ClientError::Source("no OpenNI2 device found".into()));
                }
                Device::open_default().map_err(|e| ClientError::Source(format!("no OpenNI2 device found: {e}")))?
            }
        };
        // The device lives as long as the process (its streams borrow it, and
        // OpenNI2 must not be shut down), so it is leaked on purpose.
        let device: &'static Device = Box::leak(Box::new(device));
        let depth = device.create_stream(SensorType::DEPTH).map_err(err("depth stream"))?;
        let color = device.create_stream(SensorType::COLOR).map_err(err("colour stream"))?;
        for s in [&depth, &color] {
            // Not every driver supports mirroring control; the Dummy does not mirror.
            let _ = s.set_mirroring(false);
        }
        if device.is_image_registration_mode_supported(openni2::ImageRegistrationMode::DEPTH_TO_COLOR) {
            device.set_image_registration(true).map_err(err("depth-to-colour registration"))?;
        } else {
            tracing::warn!("device cannot register depth to colour; depth stays in the depth camera's frame");
        }
        let dmode = depth.get_video_mode().map_err(err("depth video mode"))?;
        let cmode = color.get_video_mode().map_err(err("colour video mode"))?;
        let depth_units_per_metre = match dmode.pixel_format {
            PixelFormat::DEPTH_1_MM => DEPTH_1_MM_UNITS,
            PixelFormat::DEPTH_100_UM => DEPTH_100_UM_UNITS,
            other => return Err(ClientError::Source(format!("unsupported depth format {other:?}"))),
        };
        if !matches!(cmode.pixel_format, PixelFormat::RGB888) {
            return Err(ClientError::Source(format!("unsupported colour format {:?}", cmode.pixel_format)));
        }
        if (dmode.resolution_x, dmode.resolution_y) != (cmode.resolution_x, cmode.resolution_y) {
            return Err(ClientError::Source(format!(
                "depth {}x{} and colour {}x{} differ",
                dmode.resolution_x, dmode.resolution_y, cmode.resolution_x, cmode.resolution_y
            )));
        }
        let (w, h) = (cmode.resolution_x as u32, cmode.resolution_y as u32);
        // Pinhole intrinsics from the colour stream's field of view.
        // The driver's field of view is the device's own report (PS1080 reads it from
        // the sensor); without one, the PrimeSense nominal field of view is a guess.
        let what = format!("OpenNI2 device {}", uri.unwrap_or("(first)"));
        let reported = match (color.get_horizontal_fov(), color.get_vertical_fov()) {
            (Ok(h), Ok(v)) if h.is_finite() && v.is_finite() && h > 0.0 && v > 0.0 => Some((f64::from(h), f64::from(v))),
            _ => None,
        };
        let (hfov, vfov) = reported.unwrap_or((NOMINAL_HFOV_RAD, NOMINAL_VFOV_RAD));
        let known = reported.map(|(h, v)| format!("device:{what} field of view {:.1} x {:.1} deg", h.to_degrees(), v.to_degrees()));
        let fx = f64::from(w) / (2.0 * (hfov / 2.0).tan());
        let fy = f64::from(h) / (2.0 * (vfov / 2.0).tan());
        let info = pb::CameraInfo {
            width: w,
            height: h,
            fx,
            fy,
            cx: (f64::from(w) - 1.0) / 2.0,
            cy: (f64::from(h) - 1.0) / 2.0,
            distortion_model: DistortionModel::None as i32,
            depth_units_per_metre,
            nominal_rate_hz: f64::from(cmode.fps),
            ..Default::default()
        };
        let camera = crate::calibration::resolve(SourceCamera { info, known, what }, options)?;
        depth.start().map_err(err("start depth"))?;
        color.start().map_err(err("start colour"))?;
        Ok(Self { depth: ManuallyDrop::new(depth), color: ManuallyDrop::new(color), camera, max_frames, read: 0, last_ns: 0 })
    }
}

impl FrameSource for OpenNiSource {
    fn camera(&self) -> pb::CameraInfo {
        self.camera.clone()
    }

    fn len_hint(&self) -> Option<usize> {
        self.max_frames
    }

    fn next_frame(&mut self) -> Result<Option<RawFrame>, ClientError> {
        if self.max_frames.is_some_and(|m| self.read >= m) {
            return Ok(None);
        }
        let (w, h) = (self.camera.width, self.camera.height);
        let depth_frame = self.depth.read_frame::<OniDepthPixel>().map_err(err("read depth"))?;
        let color_frame = self.color.read_frame::<OniRGB888Pixel>().map_err(err("read colour"))?;
        for (what, (fw, fh)) in [("depth", depth_frame.dimensions()), ("colour", color_frame.dimensions())] {
            if (u32::from(fw), u32::from(fh)) != (w, h) {
                return Err(ClientError::Source(format!("OpenNI2 {what} frame is {fw}x{fh}, expected {w}x{h}")));
            }
        }
        let depth = DepthImage { width: w, height: h, data: depth_frame.pixels().to_vec() };
        let color = ColorImage { width: w, height: h, data: color_frame.pixels().iter().flat_map(|p| [p.r, p.g, p.b]).collect() };
        // OpenNI2 timestamps are microseconds; keep them strictly increasing.
        let ns = (depth_frame.timestamp() * 1000).max(self.last_ns + 1);
        self.last_ns = ns;
        self.read += 1;
        Ok(Some(RawFrame { capture_time_ns: ns, color, depth, accel_in_camera: None }))
    }
}
