//! Carrying a segmentation forward through the flow, for frames whose own
//! segmentation is not ready yet.

use crate::flow::FlowField;
use crate::segment::{NO_INSTANCE, Segmentation};

/// Warps a segmentation of the previous frame into the current one: each current
/// pixel takes the instance at the position the flow (current → previous) points
/// to. Instances that leave the image are dropped; counts and boxes are recomputed.
pub fn warp_segmentation(previous: &Segmentation, flow: &FlowField) -> Segmentation {
    let (w, h) = (previous.width as usize, previous.height as usize);
    // A current pixel can only land in an instance if it lies within that
    // instance's box widened by the largest displacement: warp only there.
    let s = flow.subsample.max(1) as f32;
    let reach = flow.data.iter().fold(0f32, |m, f| m.max(f[0].abs()).max(f[1].abs())) * s + 2.0;
    let regions: Vec<[usize; 4]> = previous
        .instances
        .iter()
        .map(|i| {
            let clamp = |v: f32, hi: usize| (v.max(0.0) as usize).min(hi);
            [
                clamp((i.bbox[0] - reach).floor(), w),
                clamp((i.bbox[1] - reach).floor(), h),
                clamp((i.bbox[2] + reach).ceil(), w),
                clamp((i.bbox[3] + reach).ceil(), h),
            ]
        })
        .collect();
    let map = warp_map_in(&previous.instance_map, w, h, flow, NO_INSTANCE, &regions);
    let max_id = previous.instances.iter().map(|i| usize::from(i.id)).max().unwrap_or(0);
    let mut pixels = vec![0u32; max_id + 1];
    let mut boxes = vec![[f32::MAX, f32::MAX, f32::MIN, f32::MIN]; max_id + 1];
    for y in 0..h {
        for x in 0..w {
            let id = usize::from(map[y * w + x]);
            if id != 0 && id <= max_id {
                pixels[id] += 1;
                let b = &mut boxes[id];
                b[0] = b[0].min(x as f32);
                b[1] = b[1].min(y as f32);
                b[2] = b[2].max(x as f32 + 1.0);
                b[3] = b[3].max(y as f32 + 1.0);
            }
        }
    }
    let instances = previous
        .instances
        .iter()
        .filter(|i| pixels[usize::from(i.id)] > 0)
        .map(|i| {
            let mut i = i.clone();
            i.pixels = pixels[usize::from(i.id)];
            i.bbox = boxes[usize::from(i.id)];
            i
        })
        .collect();
    Segmentation { width: previous.width, height: previous.height, instance_map: map, instances }
}

/// Warps a map that lives on the flow grid itself (one value per flow pixel) into
/// the current frame: each cell takes the value where its own flow points.
pub fn warp_grid(previous: &[u8], flow: &FlowField) -> Vec<u8> {
    let (w, h) = (flow.width, flow.height);
    let mut out = vec![0u8; w * h];
    for (i, f) in flow.data.iter().enumerate() {
        let (sx, sy) = (((i % w) as f32 + f[0]).round(), ((i / w) as f32 + f[1]).round());
        if sx >= 0.0 && sy >= 0.0 && (sx as usize) < w && (sy as usize) < h {
            out[i] = previous[sy as usize * w + sx as usize];
        }
    }
    out
}

/// Backward warping of a per-pixel map by the flow (nearest), inside `regions`
/// (x0, y0, x1, y1, exclusive ends); `outside` elsewhere and where the flow leaves
/// the image.
fn warp_map_in<T: Copy>(previous: &[T], width: usize, height: usize, flow: &FlowField, outside: T, regions: &[[usize; 4]]) -> Vec<T> {
    // Each pixel moves with its flow cell (nearest): a cell is a few pixels wide
    // and the flow is smooth across it.
    let s = flow.subsample.max(1) as usize;
    let (gw, gh) = (flow.width, flow.height);
    let mut out = vec![outside; width * height];
    for &[x0, y0, x1, y1] in regions {
        for y in y0..y1.min(height) {
            let row = (y / s).min(gh - 1) * gw;
            for x in x0..x1.min(width) {
                let f = flow.data[row + (x / s).min(gw - 1)];
                let (sx, sy) = ((x as f32 + f[0] * s as f32).round(), (y as f32 + f[1] * s as f32).round());
                if sx >= 0.0 && sy >= 0.0 && (sx as usize) < width && (sy as usize) < height {
                    out[y * width + x] = previous[sy as usize * width + sx as usize];
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::segment::Instance;

    #[test]
    fn a_translated_instance_follows_the_flow() {
        let (w, h) = (64, 48);
        let mut seg = Segmentation::empty(w, h);
        for y in 10..20 {
            for x in 10..30 {
                seg.instance_map[y * w as usize + x] = 1;
            }
        }
        seg.instances.push(Instance {
            id: 1,
            class_id: 0,
            class_name: "person".into(),
            score: 0.8,
            bbox: [10.0, 10.0, 30.0, 20.0],
            pixels: 200,
        });
        // The scene moved 6 px right: current (x, y) shows previous (x − 6, y).
        let flow = FlowField { width: 32, height: 24, subsample: 2, data: vec![[-3.0, 0.0]; 32 * 24] };
        let out = warp_segmentation(&seg, &flow);
        assert_eq!(out.instances[0].pixels, 200);
        assert_eq!(out.instances[0].bbox, [16.0, 10.0, 36.0, 20.0]);
        assert_eq!(out.instance_map[15 * w as usize + 16], 1);
        assert_eq!(out.instance_map[15 * w as usize + 15], 0);
    }
}
