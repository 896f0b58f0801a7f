//! Dense optical flow: OpenCV's Farneback on a subsampled grey image.

use opencv::core::Mat;
use opencv::prelude::*;
use opencv::video;

use stillmap_tracking::tracker::luma_x256;

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
    /// Grey (ITU-R BT.601 luma, as [`to_gray`](stillmap_tracking::tracker::to_gray))
    /// averaged over exact `factor`×`factor` blocks of an RGB8 image, in one pass:
    /// flow pixel `(x, y)` covers full-size pixels `factor·x .. factor·x + factor`,
    /// the geometry ego-motion compensation assumes (a remainder of fewer than
    /// `factor` columns or rows at the right and bottom is dropped).
    pub fn from_rgb(rgb: &[u8], width: usize, height: usize, factor: u32) -> Result<Self, PerceptionError> {
        if rgb.len() != width * height * 3 {
            return Err(PerceptionError::Input(format!("colour has {} bytes, expected {}", rgb.len(), width * height * 3)));
        }
        let f = factor.max(1) as usize;
        let (sw, sh) = (width / f, height / f);
        if sw < 8 || sh < 8 {
            return Err(PerceptionError::Input(format!("image {width}x{height} is too small for flow at 1/{f}")));
        }
        // Sums of 8-bit fixed-point luma (×256) over each block; rounded once at the end.
        let mut sums = vec![0u32; sw];
        let mut data = Vec::with_capacity(sw * sh);
        let divisor = (f * f * 256) as u32;
        for y in 0..sh {
            sums.iter_mut().for_each(|v| *v = 0);
            for row in rgb[y * f * width * 3..(y * f + f) * width * 3].chunks_exact(width * 3) {
                for (sum, block) in sums.iter_mut().zip(row.chunks_exact(f * 3)) {
                    for p in block.chunks_exact(3) {
                        *sum += luma_x256(p);
                    }
                }
            }
            data.extend(sums.iter().map(|&v| ((v + divisor / 2) / divisor) as u8));
        }
        Ok(Self { width: sw, height: sh, data })
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
        let mut data = Vec::with_capacity(self.data.len());
        for y in 0..self.height {
            for x in 0..w {
                let f = self.data[y * w + x];
                let g = earlier.sample(x as f32 + f[0], y as f32 + f[1]);
                data.push([f[0] + g[0], f[1] + g[1]]);
            }
        }
        FlowField { data, ..self.clone_shape() }
    }

    /// This flow chained with `earlier` ones (each a step further back), followed
    /// only from every `stride`-th pixel in each direction: the composed flow there
    /// (0 elsewhere), and whether the path stayed in the image at every step
    /// (false elsewhere; where it left, the earlier flows were only clamped).
    pub fn chain_sparse(&self, earlier: &[&FlowField], stride: usize) -> (FlowField, Vec<bool>) {
        let (w, h) = (self.width, self.height);
        let (wf, hf) = ((w - 1) as f32, (h - 1) as f32);
        let within = |x: f32, y: f32| (0.0..=wf).contains(&x) && (0.0..=hf).contains(&y);
        let mut data = vec![[0f32; 2]; self.data.len()];
        let mut inside = vec![false; self.data.len()];
        for y in (0..h).step_by(stride.max(1)) {
            for x in (0..w).step_by(stride.max(1)) {
                let i = y * w + x;
                let f = self.data[i];
                let (mut px, mut py) = (x as f32 + f[0], y as f32 + f[1]);
                let mut ok = within(px, py);
                for e in earlier {
                    let g = e.sample(px, py);
                    (px, py) = (px + g[0], py + g[1]);
                    ok &= within(px, py);
                }
                data[i] = [px - x as f32, py - y as f32];
                inside[i] = ok;
            }
        }
        (FlowField { data, ..self.clone_shape() }, inside)
    }

    fn clone_shape(&self) -> FlowField {
        FlowField { width: self.width, height: self.height, subsample: self.subsample, data: Vec::new() }
    }

    /// Bilinear flow at a (sub)pixel position, clamped to the image.
    pub fn sample(&self, x: f32, y: f32) -> [f32; 2] {
        let x = x.clamp(0.0, (self.width - 1) as f32);
        let y = y.clamp(0.0, (self.height - 1) as f32);
        // Clamped to 0 or more: truncation is the floor (and no libm call).
        let (x0, y0) = (x as usize, y as usize);
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
    fn grey_blocks_from_rgb_match_the_luma_average() {
        // 7×5 image at 1/2: a 3×2 grid, the last column and row dropped.
        let (w, h) = (7, 5);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 37 % 251) as u8).collect();
        let small = SmallGray::from_rgb(&rgb, w, h, 2);
        assert!(small.is_err(), "7x5 at 1/2 is under 8x8");
        let (w, h) = (50, 37);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 37 % 251) as u8).collect();
        let small = SmallGray::from_rgb(&rgb, w, h, 3).unwrap();
        assert_eq!((small.width, small.height), (16, 12));
        let luma = |x: usize, y: usize| {
            let p = &rgb[(y * w + x) * 3..(y * w + x) * 3 + 3];
            f64::from(p[0]) * 77.0 / 256.0 + f64::from(p[1]) * 150.0 / 256.0 + f64::from(p[2]) * 29.0 / 256.0
        };
        for (y, x) in [(0, 0), (5, 7), (11, 15)] {
            let mean = (0..3).flat_map(|dy| (0..3).map(move |dx| (dx, dy))).map(|(dx, dy)| luma(3 * x + dx, 3 * y + dy)).sum::<f64>() / 9.0;
            assert!((f64::from(small.data[y * 16 + x]) - mean).abs() <= 0.5 + 1e-9, "({x},{y}): {} vs {mean}", small.data[y * 16 + x]);
        }
        assert!(SmallGray::from_rgb(&rgb[1..], w, h, 3).is_err());
    }

    #[test]
    fn chained_flows_add_up_along_the_path() {
        // Current → previous moves 2 right; previous → before moves right by 1 + x/10
        // (so the second flow is read where the first one points).
        let (w, h) = (20, 10);
        let later = FlowField { width: w, height: h, subsample: 2, data: vec![[2.0, 0.0]; w * h] };
        let earlier =
            FlowField { width: w, height: h, subsample: 2, data: (0..w * h).map(|i| [1.0 + (i % w) as f32 / 10.0, 0.5]).collect() };
        let both = later.then(&earlier);
        assert_eq!(both.subsample, 2);
        // Cell (5, 3): 2 → x = 7, where the earlier flow is 1.7 → total 3.7.
        let f = both.data[3 * w + 5];
        assert!((f[0] - 3.7).abs() < 1e-5 && (f[1] - 0.5).abs() < 1e-6, "{f:?}");
        // The same chain from every other cell: the same flow there, and the cells
        // whose path leaves the image marked (x + 2 beyond 19 after the first step;
        // x + 2 + 1 + (x + 2) / 10 beyond 19 after the second).
        let (sparse, inside) = later.chain_sparse(&[&earlier], 2);
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if x % 2 == 0 && y % 2 == 0 {
                    let (a, b) = (sparse.data[i], both.data[i]);
                    assert!((a[0] - b[0]).abs() < 1e-5 && (a[1] - b[1]).abs() < 1e-5, "cell {x},{y}: {a:?} vs {b:?}");
                    let end = (x + 2) as f32 + 1.0 + (x + 2).min(w - 1) as f32 / 10.0;
                    assert_eq!(inside[i], x + 2 < w && end <= (w - 1) as f32, "cell {x},{y}");
                } else {
                    assert!(!inside[i] && sparse.data[i] == [0.0, 0.0], "cell {x},{y} is not followed");
                }
            }
        }
    }
}
