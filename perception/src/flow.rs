//! Dense optical flow: OpenCV's Farneback on a subsampled grey image.

use opencv::core::{Mat, Size};
use opencv::imgproc;
use opencv::prelude::*;
use opencv::video;

use crate::PerceptionError;
use crate::config::FlowConfig;

/// A grey image subsampled by an integer factor (area averaging).
#[derive(Debug, Clone)]
pub struct SmallGray {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

impl SmallGray {
    /// Subsamples a full-size grey image by `factor` (INTER_AREA).
    pub fn from_gray(gray: &[u8], width: usize, height: usize, factor: u32) -> Result<Self, PerceptionError> {
        if gray.len() != width * height {
            return Err(PerceptionError::Input(format!("grey image has {} pixels, expected {}", gray.len(), width * height)));
        }
        let f = factor.max(1) as usize;
        let (sw, sh) = (width / f, height / f);
        if sw < 8 || sh < 8 {
            return Err(PerceptionError::Input(format!("image {width}x{height} is too small for flow at 1/{f}")));
        }
        let src = Mat::new_rows_cols_with_data(height as i32, width as i32, gray)?;
        if f == 1 {
            return Ok(Self { width, height, data: gray.to_vec() });
        }
        let mut dst = Mat::default();
        imgproc::resize(&src, &mut dst, Size::new(sw as i32, sh as i32), 0.0, 0.0, imgproc::INTER_AREA)?;
        Ok(Self { width: sw, height: sh, data: dst.data_bytes()?.to_vec() })
    }
}

/// Flow at every pixel of a subsampled image, in subsampled pixels.
#[derive(Debug, Clone)]
pub struct FlowField {
    pub width: usize,
    pub height: usize,
    /// Full-size pixels per flow pixel.
    pub subsample: u32,
    /// `(dx, dy)` per pixel: the pixel at `(x, y)` of the *current* image shows what
    /// was at `(x + dx, y + dy)` in the *previous* one.
    pub data: Vec<[f32; 2]>,
}

impl FlowField {
    /// Chains this flow (current → previous) with `earlier` (previous → the frame
    /// before): the flow from the current frame two steps back.
    pub fn then(&self, earlier: &FlowField) -> FlowField {
        let w = self.width;
        let data = self
            .data
            .iter()
            .enumerate()
            .map(|(i, f)| {
                let (x, y) = ((i % w) as f32 + f[0], (i / w) as f32 + f[1]);
                let g = earlier.sample(x, y);
                [f[0] + g[0], f[1] + g[1]]
            })
            .collect();
        FlowField { data, ..self.clone_shape() }
    }

    fn clone_shape(&self) -> FlowField {
        FlowField { width: self.width, height: self.height, subsample: self.subsample, data: Vec::new() }
    }

    /// Bilinear flow at a (sub)pixel position, clamped to the image.
    pub fn sample(&self, x: f32, y: f32) -> [f32; 2] {
        let x = x.clamp(0.0, (self.width - 1) as f32);
        let y = y.clamp(0.0, (self.height - 1) as f32);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (tx, ty) = (x - x0 as f32, y - y0 as f32);
        let at = |x: usize, y: usize| self.data[y * self.width + x];
        let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
        let lerp = |k: usize| (a[k] * (1.0 - tx) + b[k] * tx) * (1.0 - ty) + (c[k] * (1.0 - tx) + d[k] * tx) * ty;
        [lerp(0), lerp(1)]
    }
}

/// Farneback flow from `current` back to `previous` (both subsampled alike).
pub fn farneback(current: &SmallGray, previous: &SmallGray, config: &FlowConfig, subsample: u32) -> Result<FlowField, PerceptionError> {
    if (current.width, current.height) != (previous.width, previous.height) {
        return Err(PerceptionError::Input("flow images differ in size".into()));
    }
    let (w, h) = (current.width, current.height);
    let cur = Mat::new_rows_cols_with_data(h as i32, w as i32, &current.data)?;
    let prev = Mat::new_rows_cols_with_data(h as i32, w as i32, &previous.data)?;
    let mut flow = Mat::default();
    video::calc_optical_flow_farneback(
        &cur,
        &prev,
        &mut flow,
        config.pyr_scale,
        config.levels,
        config.winsize,
        config.iterations,
        config.poly_n,
        config.poly_sigma,
        0,
    )?;
    let data = flow.data_typed::<opencv::core::Vec2f>()?.iter().map(|v| v.0).collect();
    Ok(FlowField { width: w, height: h, subsample, data })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chained_flows_add_up_along_the_path() {
        // Current → previous moves 2 right; previous → before moves right by 1 + x/10
        // (so the second flow is read where the first one points).
        let (w, h) = (20, 10);
        let later = FlowField { width: w, height: h, subsample: 2, data: vec![[2.0, 0.0]; w * h] };
        let earlier = FlowField { width: w, height: h, subsample: 2, data: (0..w * h).map(|i| [1.0 + (i % w) as f32 / 10.0, 0.5]).collect() };
        let both = later.then(&earlier);
        assert_eq!(both.subsample, 2);
        // Cell (5, 3): 2 → x = 7, where the earlier flow is 1.7 → total 3.7.
        let f = both.data[3 * w + 5];
        assert!((f[0] - 3.7).abs() < 1e-5 && (f[1] - 0.5).abs() < 1e-6, "{f:?}");
    }
}
