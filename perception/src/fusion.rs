//! Mask fusion: segmentation priors and residual flow become one label per pixel.
//!
//! The paper's four cases, per pixel, after its 3×3 neighbourhood test on the
//! residual flow:
//! - prior-dynamic class with flow → dynamic;
//! - prior-dynamic class without flow → prior-dynamic region (never mapped; for
//!   tracking, see [`PriorDynamicTracking`]);
//! - prior-static (or no instance) with flow → dynamic;
//! - otherwise static.
//!
//! Decided per instance as well: an instance moves when enough of its pixels carry
//! residual flow, and then all of it is dynamic. Flow outside any instance forms
//! regions that are cleaned (too small: noise; too large: an ego-motion failure)
//! and pruned to the depth of their core, which removes the flow halo that
//! Farneback's window smears onto the background behind a moving object.

use crate::config::{FusionConfig, PriorDynamicTracking};
use crate::ego::{EgoResult, NO_PREDICTION, RESIDUAL};
use crate::segment::{NO_INSTANCE, Segmentation};

/// Per-pixel label of the fused mask.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum PixelLabel {
    Static = 0,
    /// Moving now: excluded from tracking and mapping.
    Dynamic = 1,
    /// A prior-dynamic class that is not moving now: never mapped.
    PriorDynamic = 2,
}

/// What fusion decided about one instance.
#[derive(Debug, Clone, PartialEq)]
pub struct InstanceState {
    pub id: u16,
    pub class_id: u16,
    pub class_name: String,
    pub score: f32,
    pub prior_dynamic: bool,
    /// `None` when its motion could not be judged (no flow yet, or too few pixels with depth).
    pub moving: Option<bool>,
    /// Fraction of its judged pixels that carry residual flow.
    pub moving_fraction: f32,
    pub pixels: u32,
    /// x0, y0, x1, y1 in frame pixels.
    pub bbox: [f32; 4],
}

/// Fusion output at full resolution.
#[derive(Debug, Clone)]
pub struct Fused {
    pub width: usize,
    pub height: usize,
    /// [`PixelLabel`] as u8 per pixel.
    pub labels: Vec<u8>,
    pub instances: Vec<InstanceState>,
    /// Flow-only regions accepted as moving, and rejected as too large (ego-motion failure).
    pub flow_regions: usize,
    pub rejected_regions: usize,
}

impl Fused {
    /// Nonzero where tracking must not take features.
    pub fn tracking_mask(&self, policy: PriorDynamicTracking) -> Vec<u8> {
        self.labels
            .iter()
            .map(|&l| match l {
                x if x == PixelLabel::Dynamic as u8 => 1,
                x if x == PixelLabel::PriorDynamic as u8 && policy == PriorDynamicTracking::AlwaysExclude => 1,
                _ => 0,
            })
            .collect()
    }

    /// Nonzero where mapping must not fuse depth (dynamic and prior-dynamic).
    pub fn mapping_mask(&self) -> Vec<u8> {
        self.labels.iter().map(|&l| u8::from(l != PixelLabel::Static as u8)).collect()
    }

    pub fn count(&self, label: PixelLabel) -> usize {
        self.labels.iter().filter(|&&l| l == label as u8).count()
    }
}

/// Pixels with a prediction an instance needs before its motion is judged.
const MIN_JUDGED_PIXELS: usize = 30;

/// Fuses the residual-flow classification (`ego`, on the flow grid; `None` when
/// there is no flow for this frame) with a segmentation in the current frame's
/// coordinates. `prior_dynamic[class_id]` says which classes are dynamic a priori.
#[allow(clippy::too_many_arguments)]
pub fn fuse(
    width: usize,
    height: usize,
    subsample: usize,
    ego: Option<&EgoResult>,
    segmentation: Option<&Segmentation>,
    prior_dynamic: &[bool],
    config: &FusionConfig,
) -> Fused {
    let s = subsample.max(1);
    let (gw, gh) = (width / s, height / s);
    // The instance at each flow cell's centre pixel.
    let grid_ids: Option<Vec<u16>> = segmentation.map(|seg| cell_centres(width, height, s).map(|i| seg.instance_map[i]).collect());
    let grid_instance = |i: usize| -> u16 { grid_ids.as_ref().map_or(NO_INSTANCE, |ids| ids[i]) };

    // 3×3 neighbourhood test on the flow grid: residual cells counted over each
    // cell's 3×3 neighbourhood (clipped at the border), as column sums then row sums.
    let mut flow = vec![false; gw * gh];
    if let Some(e) = ego {
        let residual: Vec<u32> = e.class.iter().map(|&c| u32::from(c == RESIDUAL)).collect();
        let mut columns = vec![0u32; gw * gh];
        for y in 0..gh {
            let (y0, y1) = (y.saturating_sub(1), (y + 1).min(gh - 1));
            for x in 0..gw {
                columns[y * gw + x] = (y0..=y1).map(|dy| residual[dy * gw + x]).sum();
            }
        }
        for y in 0..gh {
            let row = &columns[y * gw..][..gw];
            for x in 0..gw {
                let votes: u32 = row[x.saturating_sub(1)..=(x + 1).min(gw - 1)].iter().sum();
                flow[y * gw + x] = votes >= config.neighbourhood_votes;
            }
        }
    }

    // Per-instance decision.
    let mut instances: Vec<InstanceState> = Vec::new();
    if let Some(seg) = segmentation {
        let max_id = seg.instances.iter().map(|i| usize::from(i.id)).max().unwrap_or(0);
        let (mut judged, mut moving_px) = (vec![0usize; max_id + 1], vec![0usize; max_id + 1]);
        if let Some(e) = ego {
            // Each instance is judged on its own surface: the cells near its median
            // depth (`instance_depth_gate`). Its mask spills onto what lies in front
            // of it or behind it at its outline, and a mover there must not make it move.
            let mut depths: Vec<Vec<f32>> = vec![Vec::new(); max_id + 1];
            for (i, (&class, &z)) in e.class.iter().zip(&e.depth_m).enumerate() {
                let id = usize::from(grid_instance(i));
                if id != 0 && id <= max_id && class != NO_PREDICTION && z > 0.0 {
                    depths[id].push(z);
                }
            }
            let medians: Vec<f32> = depths
                .iter_mut()
                .map(|d| {
                    if d.is_empty() {
                        return 0.0;
                    }
                    let m = d.len() / 2;
                    *d.select_nth_unstable_by(m, f32::total_cmp).1
                })
                .collect();
            let gate = config.instance_depth_gate as f32;
            for (i, ((&class, &has_flow), &z)) in e.class.iter().zip(&flow).zip(&e.depth_m).enumerate() {
                let id = usize::from(grid_instance(i));
                if id != 0 && id <= max_id && class != NO_PREDICTION && (gate <= 0.0 || (z - medians[id]).abs() <= gate * medians[id]) {
                    judged[id] += 1;
                    moving_px[id] += usize::from(has_flow);
                }
            }
        }
        for inst in &seg.instances {
            let id = usize::from(inst.id);
            let fraction = if judged[id] > 0 { moving_px[id] as f64 / judged[id] as f64 } else { 0.0 };
            let moving = (ego.is_some() && judged[id] >= MIN_JUDGED_PIXELS).then_some(fraction >= config.instance_moving_fraction);
            instances.push(InstanceState {
                id: inst.id,
                class_id: inst.class_id,
                class_name: inst.class_name.clone(),
                score: inst.score,
                prior_dynamic: prior_dynamic.get(usize::from(inst.class_id)).copied().unwrap_or(false),
                moving,
                moving_fraction: fraction as f32,
                pixels: inst.pixels,
                bbox: inst.bbox,
            });
        }
    }
    let max_id = instances.iter().map(|i| usize::from(i.id)).max().unwrap_or(0);
    // Whole-instance label per id, or None when the pixel decides.
    let mut whole: Vec<Option<PixelLabel>> = vec![None; max_id + 1];
    for i in &instances {
        whole[usize::from(i.id)] = match (i.prior_dynamic, i.moving) {
            (_, Some(true)) => Some(PixelLabel::Dynamic),
            // Prior-dynamic and still, or not judged yet: a prior-dynamic region.
            (true, _) => Some(PixelLabel::PriorDynamic),
            (false, _) => None,
        };
    }

    // Flow-only regions (pixels outside whole-instance decisions).
    let mut grid_dynamic = vec![false; gw * gh];
    let (mut flow_regions, mut rejected_regions) = (0, 0);
    if let Some(e) = ego {
        let free = |i: usize| {
            flow[i] && {
                let id = usize::from(grid_instance(i));
                id == 0 || id > max_id || whole[id].is_none()
            }
        };
        let min_cells = (config.min_region_px as usize).div_ceil(s * s).max(1);
        let max_cells = (config.max_region_fraction * (gw * gh) as f64) as usize;
        let mut seen = vec![false; gw * gh];
        let mut stack = Vec::new();
        let mut region = Vec::new();
        for start in 0..gw * gh {
            if seen[start] || !free(start) {
                continue;
            }
            region.clear();
            seen[start] = true;
            stack.push(start);
            while let Some(i) = stack.pop() {
                region.push(i);
                let (x, y) = (i % gw, i / gw);
                for ny in y.saturating_sub(1)..=(y + 1).min(gh - 1) {
                    for nx in x.saturating_sub(1)..=(x + 1).min(gw - 1) {
                        let j = ny * gw + nx;
                        if !seen[j] && free(j) {
                            seen[j] = true;
                            stack.push(j);
                        }
                    }
                }
            }
            if region.len() < min_cells {
                continue;
            }
            if region.len() > max_cells {
                rejected_regions += 1;
                continue;
            }
            let kept = prune_to_core_depth(&region, e, config.region_depth_ratio);
            if kept.len() < min_cells {
                continue;
            }
            let kept = grow_along_depth(kept, e, gw, gh, config.region_depth_ratio, |i| {
                let id = usize::from(grid_instance(i));
                id != 0 && id <= max_id && whole[id].is_some()
            });
            flow_regions += 1;
            for i in kept {
                grid_dynamic[i] = true;
            }
        }
    }

    // Full-resolution labels: instance decisions at their exact outline, flow
    // decisions at flow-grid resolution.
    let mut labels = vec![PixelLabel::Static as u8; width * height];
    let cell_of_column: Vec<usize> = (0..width).map(|x| (x / s).min(gw - 1)).collect();
    for (y, row) in labels.chunks_exact_mut(width).enumerate() {
        let grid_row = (y / s).min(gh - 1) * gw;
        match segmentation {
            None => {
                for (label, &cx) in row.iter_mut().zip(&cell_of_column) {
                    if grid_dynamic[grid_row + cx] {
                        *label = PixelLabel::Dynamic as u8;
                    }
                }
            }
            Some(seg) => {
                let ids = &seg.instance_map[y * width..(y + 1) * width];
                for ((label, &cx), &id) in row.iter_mut().zip(&cell_of_column).zip(ids) {
                    let id = usize::from(id);
                    if id != 0
                        && let Some(Some(whole_label)) = whole.get(id)
                    {
                        *label = *whole_label as u8;
                        continue;
                    }
                    let g = grid_row + cx;
                    if grid_dynamic[g] || (id != 0 && flow[g]) {
                        *label = PixelLabel::Dynamic as u8;
                    }
                }
            }
        }
    }
    Fused { width, height, labels, instances, flow_regions, rejected_regions }
}

/// Grows a (pruned) flow region over neighbouring cells whose depth continues its
/// surface (see [`grow_over_depth`]). An object moves as a whole, and the 3×3 vote
/// and Farneback's smoothing leave its rim and weakly textured inside unflagged.
/// Growth stays inside the region's bounding box (a person's feet must not leak
/// along the floor) and out of `blocked` cells.
fn grow_along_depth(
    mut region: Vec<usize>,
    ego: &EgoResult,
    gw: usize,
    gh: usize,
    ratio: f64,
    blocked: impl Fn(usize) -> bool,
) -> Vec<usize> {
    if region.is_empty() {
        return region;
    }
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for &i in &region {
        let (x, y) = (i % gw, i / gw);
        (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
    }
    let mut inside = vec![false; gw * gh];
    for &i in &region {
        inside[i] = true;
    }
    let in_box = |j: usize| (x0..=x1).contains(&(j % gw)) && (y0..=y1).contains(&(j / gw));
    region.extend(grow_over_depth(&mut inside, &ego.depth_m, gw, gh, ratio, usize::MAX, |j| in_box(j) && !blocked(j)));
    region
}

/// Marks in `inside` (a `width`×`height` grid) every cell reachable from the marked
/// ones in at most `max_steps` 4-neighbour steps, each onto an `allowed` cell whose
/// depth is within `ratio` of the depth of the cell stepped from; cells without depth
/// (0) neither grow nor are grown into. Returns the cells it marked. `ratio` ≤ 0
/// grows nothing.
pub(crate) fn grow_over_depth(
    inside: &mut [bool],
    depth_m: &[f32],
    width: usize,
    height: usize,
    ratio: f64,
    max_steps: usize,
    allowed: impl Fn(usize) -> bool,
) -> Vec<usize> {
    debug_assert_eq!(inside.len(), width * height);
    debug_assert_eq!(depth_m.len(), width * height);
    let mut grown = Vec::new();
    if ratio <= 0.0 {
        return grown;
    }
    let mut frontier: Vec<usize> = (0..inside.len()).filter(|&i| inside[i] && depth_m[i] > 0.0).collect();
    let mut next = Vec::new();
    for _ in 0..max_steps {
        if frontier.is_empty() {
            break;
        }
        for &i in &frontier {
            let z = f64::from(depth_m[i]);
            let (x, y) = (i % width, i / width);
            let neighbours =
                [(x > 0).then(|| i - 1), (x + 1 < width).then(|| i + 1), (y > 0).then(|| i - width), (y + 1 < height).then(|| i + width)];
            for j in neighbours.into_iter().flatten() {
                let zj = f64::from(depth_m[j]);
                if !inside[j] && zj > 0.0 && (zj - z).abs() <= ratio * z && allowed(j) {
                    inside[j] = true;
                    grown.push(j);
                    next.push(j);
                }
            }
        }
        std::mem::swap(&mut frontier, &mut next);
        next.clear();
    }
    grown
}

/// Keeps the pixels of a flow region at the depth of its core: the median depth of
/// its stronger-residual half. Pixels without depth stay.
fn prune_to_core_depth(region: &[usize], ego: &EgoResult, ratio: f64) -> Vec<usize> {
    if ratio <= 0.0 {
        return region.to_vec();
    }
    let mut residuals: Vec<f32> = region.iter().filter(|&&i| ego.class[i] != NO_PREDICTION).map(|&i| ego.residual_px[i]).collect();
    if residuals.is_empty() {
        return region.to_vec();
    }
    let mid = residuals.len() / 2;
    let median_residual = *residuals.select_nth_unstable_by(mid, f32::total_cmp).1;
    let mut core: Vec<f32> = region
        .iter()
        .filter(|&&i| ego.class[i] != NO_PREDICTION && ego.residual_px[i] >= median_residual && ego.depth_m[i] > 0.0)
        .map(|&i| ego.depth_m[i])
        .collect();
    if core.is_empty() {
        return region.to_vec();
    }
    let mid = core.len() / 2;
    let z_core = f64::from(*core.select_nth_unstable_by(mid, f32::total_cmp).1);
    region
        .iter()
        .copied()
        .filter(|&i| {
            let z = f64::from(ego.depth_m[i]);
            z == 0.0 || (z - z_core).abs() <= ratio * z_core
        })
        .collect()
}

/// The full-size pixel index at the centre of each flow-grid cell (`subsample`×
/// `subsample` blocks of a `width`×`height` image), row by row.
pub(crate) fn cell_centres(width: usize, height: usize, subsample: usize) -> impl Iterator<Item = usize> {
    let s = subsample.max(1);
    let (gw, gh) = (width / s, height / s);
    (0..gh).flat_map(move |y| (0..gw).map(move |x| (y * s + s / 2).min(height - 1) * width + (x * s + s / 2).min(width - 1)))
}

/// Fraction of valid-depth pixels that are not static (for `FrameCounts.dynamic_fraction`).
pub fn dynamic_fraction(labels: &[u8], depth: &[u16]) -> f32 {
    let (mut valid, mut dynamic) = (0usize, 0usize);
    for (&l, &d) in labels.iter().zip(depth) {
        if d != 0 {
            valid += 1;
            dynamic += usize::from(l != PixelLabel::Static as u8);
        }
    }
    if valid == 0 { 0.0 } else { dynamic as f32 / valid as f32 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ego::CONSISTENT;
    use crate::segment::Instance;
    use nalgebra::Isometry3;

    fn ego_with(gw: usize, gh: usize, residual: impl Fn(usize, usize) -> bool, depth: impl Fn(usize, usize) -> f32) -> EgoResult {
        let mut class = vec![CONSISTENT; gw * gh];
        let mut residual_px = vec![0.5; gw * gh];
        let mut depth_m = vec![0.0; gw * gh];
        for y in 0..gh {
            for x in 0..gw {
                if residual(x, y) {
                    class[y * gw + x] = RESIDUAL;
                    residual_px[y * gw + x] = 6.0;
                }
                depth_m[y * gw + x] = depth(x, y);
            }
        }
        EgoResult {
            previous_from_current: Isometry3::identity(),
            refined: true,
            confirmed: true,
            from_prior: false,
            samples: 0,
            inliers: 0,
            class,
            residual_px,
            depth_m,
        }
    }

    fn person_box(width: usize, height: usize, x0: usize, x1: usize, y0: usize, y1: usize) -> Segmentation {
        let mut seg = Segmentation::empty(width as u32, height as u32);
        for y in y0..y1 {
            for x in x0..x1 {
                seg.instance_map[y * width + x] = 1;
            }
        }
        let pixels = ((x1 - x0) * (y1 - y0)) as u32;
        seg.instances.push(Instance {
            id: 1,
            class_id: 0,
            class_name: "person".into(),
            score: 0.9,
            bbox: [x0 as f32, y0 as f32, x1 as f32, y1 as f32],
            pixels,
        });
        seg
    }

    #[test]
    fn the_four_cases() {
        let (w, h) = (160, 120);
        let config = FusionConfig { min_region_px: 16, ..FusionConfig::default() };
        let prior = [true];
        // A still person: prior-dynamic region. A moving person: dynamic.
        let seg = person_box(w, h, 20, 60, 20, 100);
        let still = ego_with(80, 60, |_, _| false, |_, _| 2.0);
        let f = fuse(w, h, 2, Some(&still), Some(&seg), &prior, &config);
        assert_eq!(f.instances[0].moving, Some(false));
        assert_eq!(f.count(PixelLabel::PriorDynamic), 40 * 80);
        assert_eq!(f.count(PixelLabel::Dynamic), 0);
        let moving = ego_with(80, 60, |x, y| (10..30).contains(&x) && (10..50).contains(&y), |_, _| 2.0);
        let f = fuse(w, h, 2, Some(&moving), Some(&seg), &prior, &config);
        assert_eq!(f.instances[0].moving, Some(true));
        assert_eq!(f.count(PixelLabel::Dynamic), 40 * 80);
        assert_eq!(f.tracking_mask(PriorDynamicTracking::ExcludeWhileMoving).iter().filter(|&&m| m != 0).count(), 40 * 80);

        // No instance, residual flow on a patch in front of the wall: dynamic; the
        // halo at wall depth is pruned; an isolated speck is noise.
        let ego = ego_with(
            80,
            60,
            |x, y| ((40..60).contains(&x) && (20..40).contains(&y)) || (x == 5 && y == 5),
            |x, y| if (42..60).contains(&x) && (20..40).contains(&y) { 1.0 } else { 3.0 },
        );
        let f = fuse(w, h, 2, Some(&ego), None, &prior, &config);
        assert_eq!(f.flow_regions, 1);
        // The two halo columns at 3 m are pruned: 18×20 cells of 2×2 pixels remain (the
        // two corners the vote drops grow back along the patch's depth; the wall at 3 m
        // does not).
        assert_eq!(f.count(PixelLabel::Dynamic), 18 * 20 * 4);
        assert_eq!(f.labels[10 * w + 10], PixelLabel::Static as u8);

        // Without flow (first frame) a person is prior-dynamic and not judged.
        let f = fuse(w, h, 2, None, Some(&seg), &prior, &config);
        assert_eq!(f.instances[0].moving, None);
        assert_eq!(f.count(PixelLabel::PriorDynamic), 40 * 80);
        assert_eq!(f.tracking_mask(PriorDynamicTracking::ExcludeWhileMoving).iter().filter(|&&m| m != 0).count(), 0);
        assert_eq!(f.tracking_mask(PriorDynamicTracking::AlwaysExclude).iter().filter(|&&m| m != 0).count(), 40 * 80);
        assert_eq!(f.mapping_mask().iter().filter(|&&m| m != 0).count(), 40 * 80);
    }

    #[test]
    fn a_mover_in_front_of_an_instance_does_not_make_it_move() {
        let (w, h) = (160, 120);
        let prior = [true, false];
        // A monitor (not prior-dynamic) at 1.2 m, 40 × 80 pixels; a board carried
        // 0.8 m away covers its left third and the wall beside it, and the
        // segmenter's monitor mask spills onto the board.
        let mut seg = person_box(w, h, 20, 60, 20, 100);
        seg.instances[0].class_id = 1;
        seg.instances[0].class_name = "tv".into();
        let board = |x: usize, y: usize| (4..16).contains(&x) && (8..52).contains(&y);
        let ego = ego_with(80, 60, board, |x, y| if board(x, y) { 0.8 } else { 1.2 });
        let gated = FusionConfig { min_region_px: 16, ..FusionConfig::default() };
        assert_eq!(gated.instance_depth_gate, 0.15);
        let f = fuse(w, h, 2, Some(&ego), Some(&seg), &prior, &gated);
        // Judged on its own surface (its 14 × 40 cells at 1.2 m), the monitor is still.
        assert_eq!(f.instances[0].moving, Some(false));
        assert_eq!(f.instances[0].moving_fraction, 0.0);
        // The board is a flow region of its own; the rest of the monitor stays static.
        assert_eq!(f.flow_regions, 1);
        assert_eq!(f.labels[50 * w + 24], PixelLabel::Dynamic as u8);
        assert!((20..100).all(|y| (34..60).all(|x| f.labels[y * w + x] == PixelLabel::Static as u8)));
        // Every pixel judging, the board's cells carry the monitor: all of it moves.
        let ungated = FusionConfig { instance_depth_gate: 0.0, ..gated };
        let f = fuse(w, h, 2, Some(&ego), Some(&seg), &prior, &ungated);
        assert_eq!(f.instances[0].moving, Some(true));
        assert_eq!(
            (20..100).flat_map(|y| (20..60).map(move |x| y * w + x)).filter(|&i| f.labels[i] == PixelLabel::Dynamic as u8).count(),
            40 * 80
        );
    }

    #[test]
    fn a_region_covering_most_of_the_image_is_an_ego_motion_failure() {
        let config = FusionConfig::default();
        let ego = ego_with(80, 60, |x, _| x > 5, |_, _| 2.0);
        let f = fuse(160, 120, 2, Some(&ego), None, &[], &config);
        assert_eq!((f.flow_regions, f.rejected_regions), (0, 1));
        assert_eq!(f.count(PixelLabel::Dynamic), 0);
    }
}
