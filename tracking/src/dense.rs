//! Dense RGB-D odometry between consecutive frames, the tracker's motion prior.
//!
//! OpenCV's `rgbd::RgbdICPOdometry` (the contrib `rgbd` module that Debian's
//! libopencv-dev ships): coarse-to-fine Gauss–Newton on the photometric error of
//! every textured pixel plus point-to-plane ICP on a sample of the depth pixels, between the
//! previous frame and this one. Features constrain the pose only through a few
//! hundred corners, and on rotation-heavy hand-held motion the solution slides
//! along the direction where a sideways translation and a rotation look alike
//! (docs/tracking.md, "Tracking accuracy"); every surface the depth camera sees pins that
//! direction down. Frame to frame it drifts, so it does not replace the map: its
//! motion predicts the pose for the projection search and enters the pose
//! optimisation as a robust prior (see `optimize::optimize_pose_with_prior`).
//!
//! The images are reduced by [`SCALE`] and undistorted with the camera's lens
//! model (the dense model is a pinhole) before alignment; dynamic pixels are masked.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use opencv::core::{self, Mat, Ptr, Scalar, Size};
use opencv::prelude::*;
use opencv::{calib3d, imgproc, rgbd};

use crate::TrackingError;
use crate::camera::Camera;

/// Integer reduction of the image before alignment (640×480 → 320×240): the
/// coarse-to-fine alignment needs the fine level only to polish, and a quarter
/// of the pixels keeps the step near the feature tracker's own cost.
pub const SCALE: usize = 2;
/// Gauss–Newton iterations per pyramid level, finest first.
const ITERATIONS: [i32; 4] = [3, 3, 3, 3];
/// Pixels whose grey gradient is weaker than this (grey levels) carry no
/// photometric residual (OpenCV's default).
const MIN_GRADIENT: f32 = 10.0;
/// Depth pairs farther apart than this (metres) are not ICP correspondences (OpenCV's default).
const MAX_DEPTH_DIFFERENCE_M: f64 = 0.07;
/// Share of the depth pixels that enter ICP (OpenCV's default).
const MAX_POINTS_PART: f64 = 0.07;
/// OpenCV's `Odometry::RIGID_BODY_MOTION`.
const RIGID_BODY_MOTION: i32 = 4;
/// OpenCV's `OdometryFrame::CACHE_ALL`: a frame is prepared once, as the
/// destination of one step and the source of the next.
const CACHE_ALL: i32 = 3;

/// A second alignment (see [`DenseStart::IdentityOrGuess`]) is run only where the
/// first one ended further than this from the motion model's step (metres of
/// translation or degrees of rotation). A cost trade-off: the wrong minima it is for
/// end centimetres away; at 1 cm / 0.5° it ran on a third of the public clip's
/// frames (the tracker's median 9.7 → 13.6 ms on a 2-core machine) for little more
/// gain, at 2 cm / 1° on 8 % (docs/tracking.md, "Two starts").
const SECOND_START_BEYOND_M: f64 = 0.02;
const SECOND_START_BEYOND_DEG: f64 = 1.0;

/// The cells (pixels of the reduced image, square) over which two starts' grey
/// residuals are compared: 20 reduced pixels, a 16 × 12 grid at 320 × 240.
const RESIDUAL_CELL_PX: usize = 20;
/// Overlapping pixels a cell needs (of 400) to take part in the comparison.
const MIN_CELL_OVERLAP: usize = 50;
/// Grey levels two cell residuals must differ by to decide a cell (below that,
/// a bare wall's noise).
const MIN_CELL_DIFFERENCE: f64 = 1.0;

/// Where a frame's alignment starts (as `previous_from_current`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DenseStart {
    /// Standing still.
    Identity,
    /// The motion model's step.
    Guess(Isometry3<f64>),
    /// Standing still and, where that alignment ends away from the motion model's
    /// step `guess`, also from `guess`; the second alignment's step is kept where
    /// it explains the grey levels better nearly everywhere: of the image cells
    /// where the two steps' mean grey-level differences differ (the lower below
    /// `ratio` times the higher), at least `share` favour it. Where the first
    /// alignment fails there is no step, as with `Identity`. Coarse-to-fine
    /// alignment from standing still lands in a wrong minimum where little of the
    /// image is left to align (a near thing masked out) and the step is large, and
    /// such a step misregisters the whole image; a moving thing the mask missed
    /// that the motion model followed explains only its own part.
    IdentityOrGuess { guess: Isometry3<f64>, ratio: f64, share: f64 },
}

/// Frame-to-frame dense odometry for one camera.
pub struct DenseOdometry {
    odometry: Ptr<rgbd::Odometry>,
    /// Undistortion maps at the reduced size (None: the camera has no distortion).
    undistort: Option<(Mat, Mat)>,
    /// Full-size image, and the reduced one aligned.
    full: (usize, usize),
    width: usize,
    height: usize,
    depth_scale: f32,
    depth_range: (f32, f32),
    previous: Option<Ptr<rgbd::OdometryFrame>>,
    /// The last pushed frame's reduced depth and the one's before (metres, NaN where
    /// missing or masked), for [`agreement`](Self::agreement) and the comparison of
    /// two starts; reused frame to frame.
    depth: Vec<f32>,
    earlier_depth: Vec<f32>,
    /// The same frames' reduced, undistorted grey images, for the photometric fit
    /// that chooses between two starts.
    gray: Vec<u8>,
    earlier_gray: Vec<u8>,
    /// The last push's step (`previous_from_current`), if it gave one.
    step: Option<Isometry3<f64>>,
    frames: i32,
    /// (fx, fy, cx, cy) at the reduced size.
    reduced_k: (f64, f64, f64, f64),
}

impl DenseOdometry {
    pub fn new(camera: &Camera, min_depth_m: f64, max_depth_m: f64) -> Result<Self, TrackingError> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        if w < 8 * SCALE || h < 8 * SCALE {
            return Err(TrackingError::Config(format!("image {w}x{h} is too small for dense odometry")));
        }
        // Pixel (x, y) of the reduced image covers full-size pixels SCALE·x .. SCALE·x + SCALE − 1.
        let s = SCALE as f64;
        let reduced_k = (camera.fx / s, camera.fy / s, (camera.cx + 0.5) / s - 0.5, (camera.cy + 0.5) / s - 0.5);
        let (fx, fy, cx, cy) = reduced_k;
        let reduced = Mat::from_slice_2d(&[[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])?;
        // The images are reduced first and undistorted at the reduced size (the lens
        // model works on normalised coordinates, so it holds at any scale).
        let undistort = match camera.distortion {
            Some(d) => {
                let coefficients = Mat::from_slice(&d)?.try_clone()?;
                let (mut map_x, mut map_y) = (Mat::default(), Mat::default());
                let size = Size::new((w / SCALE) as i32, (h / SCALE) as i32);
                calib3d::init_undistort_rectify_map(
                    &reduced,
                    &coefficients,
                    &Mat::default(),
                    &reduced,
                    size,
                    core::CV_32FC1,
                    &mut map_x,
                    &mut map_y,
                )?;
                Some((map_x, map_y))
            }
            None => None,
        };
        let iterations: core::Vector<i32> = ITERATIONS.iter().copied().collect();
        let gradients: core::Vector<f32> = ITERATIONS.iter().map(|_| MIN_GRADIENT).collect();
        let odometry = Ptr::<rgbd::Odometry>::from(rgbd::RgbdICPOdometry::create(
            &reduced,
            min_depth_m as f32,
            max_depth_m as f32,
            MAX_DEPTH_DIFFERENCE_M as f32,
            MAX_POINTS_PART as f32,
            &iterations,
            &gradients,
            RIGID_BODY_MOTION,
        )?);
        Ok(Self {
            odometry,
            undistort,
            full: (w, h),
            width: w / SCALE,
            height: h / SCALE,
            depth_scale: (1.0 / camera.depth_units_per_metre) as f32,
            depth_range: (min_depth_m as f32, max_depth_m as f32),
            previous: None,
            depth: Vec::new(),
            earlier_depth: Vec::new(),
            gray: Vec::new(),
            earlier_gray: Vec::new(),
            step: None,
            frames: 0,
            reduced_k,
        })
    }

    /// Adds a frame (`gray` and raw `depth` at full size, `dynamic_mask` nonzero =
    /// dynamic) and returns `previous_from_current` when there was a previous frame
    /// and the alignment converged (OpenCV also refuses steps beyond 15 cm or 15°).
    pub fn push(&mut self, gray: &[u8], depth: &[u16], dynamic_mask: Option<&[u8]>) -> Result<Option<Isometry3<f64>>, TrackingError> {
        self.push_started(gray, depth, dynamic_mask, DenseStart::Identity)
    }

    /// [`push`](Self::push) with the alignment started as `start` says.
    pub fn push_started(
        &mut self,
        gray: &[u8],
        depth: &[u16],
        dynamic_mask: Option<&[u8]>,
        start: DenseStart,
    ) -> Result<Option<Isometry3<f64>>, TrackingError> {
        let (w, h) = self.full;
        if gray.len() != w * h || depth.len() != w * h || dynamic_mask.is_some_and(|m| m.len() != w * h) {
            return Err(TrackingError::Input(format!("dense odometry: images must be {w}x{h}")));
        }
        // The reduced depth and mask take pixel (SCALE·x, SCALE·y), as OpenCV's
        // nearest-neighbour resize would, without converting the full-size images.
        let (lo, hi) = self.depth_range;
        let reduced = (0..self.height).flat_map(|y| (0..self.width).map(move |x| y * SCALE * w + x * SCALE));
        let metres: Vec<f32> = reduced
            .clone()
            .map(|i| {
                let z = f32::from(depth[i]) * self.depth_scale;
                if depth[i] != 0 && (lo..=hi).contains(&z) { z } else { f32::NAN }
            })
            .collect();
        let valid: Vec<u8> = reduced.map(|i| if dynamic_mask.is_some_and(|m| m[i] != 0) { 0 } else { 255 }).collect();
        let size = Size::new(self.width as i32, self.height as i32);
        let gray = reduce(&Mat::new_rows_cols_with_data(h as i32, w as i32, gray)?, size, imgproc::INTER_AREA)?;
        let metres = Mat::new_rows_cols_with_data(size.height, size.width, &metres)?.try_clone()?;
        let valid = Mat::new_rows_cols_with_data(size.height, size.width, &valid)?.try_clone()?;
        let (gray, metres, valid) = match &self.undistort {
            Some((map_x, map_y)) => (
                remap(&gray, map_x, map_y, imgproc::INTER_LINEAR, 0.0)?,
                remap(&metres, map_x, map_y, imgproc::INTER_NEAREST, f64::NAN)?,
                remap(&valid, map_x, map_y, imgproc::INTER_NEAREST, 0.0)?,
            ),
            None => (gray, metres, valid),
        };
        // This frame's depth where it may be used, for the step's agreement and the
        // comparison of two starts.
        std::mem::swap(&mut self.depth, &mut self.earlier_depth);
        self.depth.clear();
        self.depth
            .extend(metres.data_typed::<f32>()?.iter().zip(valid.data_typed::<u8>()?).map(|(&z, &ok)| if ok != 0 { z } else { f32::NAN }));
        std::mem::swap(&mut self.gray, &mut self.earlier_gray);
        self.gray.clear();
        self.gray.extend_from_slice(gray.data_typed::<u8>()?);
        self.step = None;
        let mut frame = rgbd::OdometryFrame::create(&gray, &metres, &valid, &Mat::default(), self.frames)?;
        self.frames = self.frames.wrapping_add(1);
        self.odometry.prepare_frame_cache(&mut frame, CACHE_ALL)?;
        let Some(mut previous) = self.previous.replace(frame) else { return Ok(None) };
        let Some(current) = self.previous.as_mut() else { return Ok(None) };
        self.step = match start {
            DenseStart::Identity => align(&mut self.odometry, &mut previous, current, None)?,
            DenseStart::Guess(guess) => align(&mut self.odometry, &mut previous, current, Some(guess))?,
            DenseStart::IdentityOrGuess { guess, ratio, share } => {
                // A first alignment that fails gives no step, as it did alone: the
                // second one would have nothing to be judged against.
                match align(&mut self.odometry, &mut previous, current, None)? {
                    Some(first) if !near(&first, &guess) => {
                        let second = align(&mut self.odometry, &mut previous, current, Some(guess))?;
                        let overlap = self.overlap();
                        let cells = |step: &Isometry3<f64>| overlap.grey_residual_cells(step, &self.gray, &self.earlier_gray);
                        Some(match second {
                            Some(second) if explains_nearly_everywhere_better(&cells(&second), &cells(&first), ratio, share) => second,
                            _ => first,
                        })
                    }
                    first => first,
                }
            }
        };
        Ok(self.step)
    }

    /// The last frame's step (`previous_from_current`), if the alignment gave one.
    pub fn last_step(&self) -> Option<Isometry3<f64>> {
        self.step
    }

    /// Of the last step's overlap (this frame's pixels with depth that land on the
    /// previous frame's pixels with depth), the share whose depth the step predicts
    /// within the alignment's own correspondence distance (7 cm): how much of the
    /// scene it explains. `None` without a step or without overlap. Computed on
    /// demand (the tracker asks only on a frame it would coast).
    pub fn agreement(&self) -> Option<f64> {
        self.overlap().depth_agreement(&self.step?)
    }

    /// The last pushed frame and the one before, at the reduced size.
    fn overlap(&self) -> Overlap<'_> {
        Overlap { current: &self.depth, previous: &self.earlier_depth, width: self.width, height: self.height, k: self.reduced_k }
    }
}

/// Two frames' reduced depth (metres, NaN where missing or masked) and the reduced
/// intrinsics `k` = (fx, fy, cx, cy), for judging a step between them.
struct Overlap<'a> {
    current: &'a [f32],
    previous: &'a [f32],
    width: usize,
    height: usize,
    k: (f64, f64, f64, f64),
}

impl Overlap<'_> {
    /// Calls `each(i, j, z, seen)` for every pixel `i` of the current frame with
    /// depth that `previous_from_current` carries onto a pixel `j` of the previous
    /// frame with depth (`z`: the point's depth carried into the previous frame;
    /// `seen`: the depth measured there). Nothing where the sizes do not match.
    fn each(&self, previous_from_current: &Isometry3<f64>, mut each: impl FnMut(usize, usize, f64, f32)) {
        let (width, height) = (self.width, self.height);
        if self.current.len() != width * height || self.previous.len() != width * height {
            return;
        }
        let (fx, fy, cx, cy) = self.k;
        for (i, &z) in self.current.iter().enumerate() {
            if !z.is_finite() {
                continue;
            }
            let (u, v) = ((i % width) as f64, (i / width) as f64);
            let z = f64::from(z);
            let p = previous_from_current * nalgebra::Point3::new((u - cx) / fx * z, (v - cy) / fy * z, z);
            if p.z <= 0.0 {
                continue;
            }
            let (pu, pv) = ((fx * p.x / p.z + cx).round(), (fy * p.y / p.z + cy).round());
            if pu < 0.0 || pv < 0.0 || pu >= width as f64 || pv >= height as f64 {
                continue;
            }
            let j = pv as usize * width + pu as usize;
            let seen = self.previous[j];
            if seen.is_finite() {
                each(i, j, p.z, seen);
            }
        }
    }

    /// See [`DenseOdometry::agreement`]: the share of the overlap whose depth the step
    /// predicts within the correspondence distance; `None` without overlap.
    fn depth_agreement(&self, previous_from_current: &Isometry3<f64>) -> Option<f64> {
        let (mut overlap, mut agree) = (0usize, 0usize);
        self.each(previous_from_current, |_, _, z, seen| {
            overlap += 1;
            agree += usize::from((f64::from(seen) - z).abs() <= MAX_DEPTH_DIFFERENCE_M);
        });
        (overlap > 0).then(|| agree as f64 / overlap as f64)
    }

    /// Per cell of [`RESIDUAL_CELL_PX`] square (row-major over the current frame),
    /// the mean absolute difference between the current frame's grey levels `gray`
    /// and the previous frame's `earlier_gray` over the step's overlap: what the
    /// photometric half of the alignment minimises. `None` for a cell with fewer
    /// than [`MIN_CELL_OVERLAP`] overlapping pixels; empty where the sizes do not match.
    fn grey_residual_cells(&self, previous_from_current: &Isometry3<f64>, gray: &[u8], earlier_gray: &[u8]) -> Vec<Option<f64>> {
        if gray.len() != self.current.len() || earlier_gray.len() != self.previous.len() {
            return Vec::new();
        }
        let columns = self.width.div_ceil(RESIDUAL_CELL_PX);
        let mut cells = vec![(0u64, 0usize); columns * self.height.div_ceil(RESIDUAL_CELL_PX)];
        self.each(previous_from_current, |i, j, _, _| {
            let cell = &mut cells[(i / self.width / RESIDUAL_CELL_PX) * columns + (i % self.width) / RESIDUAL_CELL_PX];
            cell.0 += u64::from(gray[i].abs_diff(earlier_gray[j]));
            cell.1 += 1;
        });
        cells.into_iter().map(|(sum, n)| (n >= MIN_CELL_OVERLAP).then(|| sum as f64 / n as f64)).collect()
    }
}

/// Whether the step with per-cell grey residuals `candidate` explains the images
/// better than the one with `incumbent` nearly everywhere: of the cells both
/// overlap where the residuals differ (the lower below `ratio` times the higher and
/// by more than [`MIN_CELL_DIFFERENCE`]), at least `share` favour `candidate`; no
/// such cell keeps the incumbent.
fn explains_nearly_everywhere_better(candidate: &[Option<f64>], incumbent: &[Option<f64>], ratio: f64, share: f64) -> bool {
    let (mut for_candidate, mut deciding) = (0usize, 0usize);
    for (c, i) in candidate.iter().zip(incumbent) {
        let (Some(c), Some(i)) = (*c, *i) else { continue };
        if c < ratio * i && i - c > MIN_CELL_DIFFERENCE {
            for_candidate += 1;
            deciding += 1;
        } else if i < ratio * c && c - i > MIN_CELL_DIFFERENCE {
            deciding += 1;
        }
    }
    deciding > 0 && for_candidate as f64 >= share * deciding as f64
}

/// Whether `step` ends within [`SECOND_START_BEYOND_M`] and [`SECOND_START_BEYOND_DEG`]
/// of `guess` (both `previous_from_current`).
fn near(step: &Isometry3<f64>, guess: &Isometry3<f64>) -> bool {
    let apart = guess.inverse() * step;
    apart.translation.vector.norm() <= SECOND_START_BEYOND_M && apart.rotation.angle() <= SECOND_START_BEYOND_DEG.to_radians()
}

/// One alignment of `previous` onto `current` started from `guess`
/// (`previous_from_current`; standing still when `None`): the step, or `None` where
/// it did not converge.
fn align(
    odometry: &mut Ptr<rgbd::Odometry>,
    previous: &mut Ptr<rgbd::OdometryFrame>,
    current: &mut Ptr<rgbd::OdometryFrame>,
    guess: Option<Isometry3<f64>>,
) -> Result<Option<Isometry3<f64>>, TrackingError> {
    let mut rt = Mat::default();
    // OpenCV's initial Rt takes the source (previous) frame into the destination.
    let init = match guess {
        Some(previous_from_current) => {
            let m = previous_from_current.inverse().to_homogeneous();
            let rows: Vec<f64> = (0..4).flat_map(|r| (0..4).map(move |c| m[(r, c)])).collect();
            Mat::new_rows_cols_with_data(4, 4, &rows)?.try_clone()?
        }
        None => Mat::default(),
    };
    if !odometry.compute2(previous, current, &mut rt, &init)? {
        return Ok(None);
    }
    let m = |r: i32, c: i32| rt.at_2d::<f64>(r, c).copied();
    let rotation = Matrix3::new(m(0, 0)?, m(0, 1)?, m(0, 2)?, m(1, 0)?, m(1, 1)?, m(1, 2)?, m(2, 0)?, m(2, 1)?, m(2, 2)?);
    // OpenCV's Rt takes points of the source (previous) frame into the destination (current) one.
    let current_from_previous = Isometry3::from_parts(
        Translation3::new(m(0, 3)?, m(1, 3)?, m(2, 3)?),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&rotation)),
    );
    Ok(Some(current_from_previous.inverse()))
}

/// `src` resampled through the undistortion maps; outside the image: `border`.
fn remap(src: &impl core::ToInputArray, map_x: &Mat, map_y: &Mat, interpolation: i32, border: f64) -> Result<Mat, TrackingError> {
    let mut out = Mat::default();
    imgproc::remap(src, &mut out, map_x, map_y, interpolation, core::BORDER_CONSTANT, Scalar::all(border))?;
    Ok(out)
}

/// `src` resized to `size`.
fn reduce(src: &impl core::ToInputArray, size: Size, interpolation: i32) -> Result<Mat, TrackingError> {
    let mut out = Mat::default();
    imgproc::resize(src, &mut out, size, 0.0, 0.0, interpolation)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::{Rendered, Scene, kinect_camera, render, sway_pose};
    use crate::tracker::to_gray;

    /// The synthetic room rendered twelve frames of its sway apart (a 10 cm, 5.7°
    /// step): the camera, the true step (`previous_from_current`) and both renders.
    fn large_step() -> (Camera, Isometry3<f64>, Rendered, Rendered) {
        let camera = kinect_camera();
        let scene = Scene::room(7);
        let (a, b) = (sway_pose(10.0), sway_pose(22.0));
        let (first, second) = (render(&scene, &camera, &a), render(&scene, &camera, &b));
        (camera, a.inverse() * b, first, second)
    }

    /// A guess starts the alignment, read as `previous_from_current`: over a 10 cm,
    /// 5.7° step, started at the true step it lands on it (measured 0.4 mm); started
    /// at its inverse (twice the step away) it ends 8 cm off (measured), so the start
    /// is used and read the right way round.
    #[test]
    fn a_guess_starts_the_alignment() {
        let (camera, truth, first, second) = large_step();
        assert!(truth.translation.vector.norm() > 0.1, "a large step: {truth:?}");
        let from = |guess: Isometry3<f64>| {
            let mut dense = DenseOdometry::new(&camera, 0.1, 6.0).expect("dense");
            assert!(dense.push(&to_gray(&first.rgb), &first.depth, None).expect("push").is_none());
            dense.push_started(&to_gray(&second.rgb), &second.depth, None, DenseStart::Guess(guess)).expect("push")
        };
        let error = truth.inverse() * from(truth).expect("converged");
        assert!(error.translation.vector.norm() < 1e-3 && error.rotation.angle() < 0.05f64.to_radians(), "{error:?}");
        let wrong_way = from(truth.inverse()).map(|s| (truth.inverse() * s).translation.vector.norm());
        assert!(wrong_way.is_none_or(|e| e > 0.01), "started at the inverse step: {wrong_way:?} m off");
    }

    /// The second start: over a 10 cm, 5.7° step with the left 70 % of the image
    /// masked (a near thing), the alignment from standing still lands in a wrong
    /// minimum (measured 11.7 mm and 2.1° off); started again from the motion
    /// model's step it lands on the truth (0.6 mm), and its cells' lower grey-level
    /// residuals keep that step. Where standing still lands right (nothing masked), a wrong
    /// motion model (the step's inverse, whose own alignment ends centimetres off)
    /// does not replace it.
    #[test]
    fn a_second_start_from_the_motion_model_replaces_a_wrong_minimum_and_not_a_right_one() {
        let (camera, truth, first, second) = large_step();
        let w = camera.width as usize;
        let run = |masked_share: f64, start: DenseStart| {
            let mask: Vec<u8> = (0..first.depth.len()).map(|i| u8::from(((i % w) as f64) < masked_share * w as f64)).collect();
            let mut dense = DenseOdometry::new(&camera, 0.1, 6.0).expect("dense");
            assert!(dense.push(&to_gray(&first.rgb), &first.depth, Some(&mask)).expect("push").is_none());
            dense.push_started(&to_gray(&second.rgb), &second.depth, Some(&mask), start).expect("push").expect("converged")
        };
        let off = |step: Isometry3<f64>| {
            let e = truth.inverse() * step;
            (e.translation.vector.norm(), e.rotation.angle().to_degrees())
        };
        let either = |guess| DenseStart::IdentityOrGuess { guess, ratio: 0.8, share: 0.9 };

        let (m, deg) = off(run(0.7, DenseStart::Identity));
        assert!(m > 0.005, "standing still lands in a wrong minimum here: {m} m, {deg}°");
        let (m, deg) = off(run(0.7, either(truth)));
        assert!(m < 0.001 && deg < 0.05, "the second start keeps the right step: {m} m, {deg}°");

        let from_identity = run(0.0, DenseStart::Identity);
        let (m, _) = off(from_identity);
        assert!(m < 0.001, "nothing masked: standing still lands right ({m} m)");
        let (m, _) = off(run(0.0, DenseStart::Guess(truth.inverse())));
        assert!(m > 0.01, "the wrong motion model's own alignment ends off ({m} m)");
        assert_eq!(run(0.0, either(truth.inverse())), from_identity, "the right step stays");
    }

    /// Nine cells of ten favouring the candidate is 90 %; ties (within the ratio,
    /// or within a grey level) and cells without overlap do not decide, and no
    /// deciding cell keeps the incumbent.
    #[test]
    fn the_second_start_wins_only_where_nearly_every_deciding_cell_favours_it() {
        let mut candidate = vec![Some(4.0); 9];
        let mut incumbent = vec![Some(10.0); 9];
        candidate.push(Some(10.0));
        incumbent.push(Some(4.0));
        assert!(explains_nearly_everywhere_better(&candidate, &incumbent, 0.8, 0.9));
        assert!(!explains_nearly_everywhere_better(&candidate, &incumbent, 0.8, 0.95));
        assert!(!explains_nearly_everywhere_better(&incumbent, &candidate, 0.8, 0.9), "the other way round");
        let (candidate, incumbent) = ([Some(4.0), Some(10.0), None, Some(1.5)], [Some(10.0), Some(10.5), Some(3.0), Some(1.0)]);
        assert!(explains_nearly_everywhere_better(&candidate, &incumbent, 0.8, 1.0), "one cell decides, for the candidate");
        assert!(!explains_nearly_everywhere_better(&[Some(5.0)], &[Some(5.0)], 0.8, 0.9), "no deciding cell");
        assert!(!explains_nearly_everywhere_better(&[], &[], 0.8, 0.9), "no cell");
    }

    #[test]
    fn agreement_is_the_share_of_the_overlap_whose_depth_the_step_predicts() {
        // A wall 2 m ahead filling both frames; the left quarter of the previous one
        // has no depth.
        let (w, h) = (80, 60);
        let k = (60.0, 60.0, 39.5, 29.5);
        let current = vec![2.0f32; w * h];
        let previous: Vec<f32> = (0..w * h).map(|i| if i % w < w / 4 { f32::NAN } else { 2.0 }).collect();
        let along_z = |m: f64| Isometry3::translation(0.0, 0.0, m);
        let overlap = Overlap { current: &current, previous: &previous, width: w, height: h, k };
        assert_eq!(overlap.depth_agreement(&Isometry3::identity()), Some(1.0));
        // 5 cm off is within the 7 cm correspondence distance, 10 cm is not.
        assert_eq!(overlap.depth_agreement(&along_z(0.05)), Some(1.0));
        assert_eq!(overlap.depth_agreement(&along_z(0.10)), Some(0.0));
        // Nothing overlaps: no agreement to judge by.
        assert_eq!(
            Overlap { current: &current, previous: &vec![f32::NAN; w * h], width: w, height: h, k }.depth_agreement(&Isometry3::identity()),
            None
        );
        assert_eq!(
            Overlap { current: &current, previous: &previous, width: w + 1, height: h, k }.depth_agreement(&Isometry3::identity()),
            None,
            "sizes must match"
        );
    }

    /// Two renders of the synthetic room a few frames of its sway apart: the step
    /// comes back as `previous_from_current`, to a millimetre and a twentieth of a degree.
    #[test]
    fn recovers_the_step_between_two_rendered_frames() {
        let camera = kinect_camera();
        let scene = Scene::room(7);
        let (a, b) = (sway_pose(10.0), sway_pose(13.0));
        let truth = a.inverse() * b;
        assert!(truth.translation.vector.norm() > 0.01, "a step worth measuring: {truth:?}");
        let mut dense = DenseOdometry::new(&camera, 0.1, 6.0).expect("dense");
        let first = render(&scene, &camera, &a);
        assert!(dense.push(&to_gray(&first.rgb), &first.depth, None).expect("push").is_none(), "nothing to align the first frame to");
        let second = render(&scene, &camera, &b);
        let step = dense.push(&to_gray(&second.rgb), &second.depth, None).expect("push").expect("converged");
        let error = truth.inverse() * step;
        assert!(error.translation.vector.norm() < 1e-3 && error.rotation.angle() < 0.05f64.to_radians(), "{error:?}");
        let agreement = dense.agreement().expect("an overlap");
        assert!(agreement >= 0.95, "a right step explains its overlap: {agreement}");
    }

    #[test]
    fn wrong_sizes_are_errors_and_a_fully_masked_frame_gives_no_step() {
        let camera = kinect_camera();
        let scene = Scene::room(7);
        let frame = render(&scene, &camera, &sway_pose(0.0));
        let gray = to_gray(&frame.rgb);
        let mut dense = DenseOdometry::new(&camera, 0.1, 6.0).expect("dense");
        let err = dense.push(&gray[1..], &frame.depth, None).expect_err("short image");
        assert_eq!(err.to_string(), "bad tracking input: dense odometry: images must be 640x480");
        assert!(dense.push(&gray, &frame.depth, Some(&[0u8; 3][..])).is_err(), "short mask");
        assert!(dense.push(&gray, &frame.depth, None).expect("push").is_none());
        let all_dynamic = vec![1u8; gray.len()];
        assert!(dense.push(&gray, &frame.depth, Some(&all_dynamic)).expect("push").is_none(), "no static pixel to align");
    }
}
