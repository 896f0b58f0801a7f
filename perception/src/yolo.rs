//! The YOLOv8-seg tensor contract, without ONNX Runtime: letterbox geometry and
//! preprocessing, box/class/coefficient decoding, class-aware NMS, and instance
//! masks (coefficients × prototypes) mapped back to the frame.
//!
//! Tensors (Ultralytics export, `nms: False`): `output0` is `[1, 4 + C + M, N]`
//! channel-major (box cx, cy, w, h in input pixels; C sigmoid-ed class scores; M
//! mask coefficients), `output1` is `[1, M, S/4, S/4]` mask prototypes.

use opencv::core::{Mat, Size};
use opencv::imgproc;
use opencv::prelude::*;

use crate::PerceptionError;
use crate::segment::{Instance, Segmentation};

/// Letterbox padding value (grey), as Ultralytics.
pub const PAD_VALUE: u8 = 114;
/// Mask prototypes are at 1/4 of the input resolution.
pub const PROTO_STRIDE: f32 = 4.0;

/// How a `width × height` frame sits in the square `size × size` model input.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Letterbox {
    pub size: u32,
    /// Input pixels per frame pixel.
    pub scale: f32,
    pub resized_w: u32,
    pub resized_h: u32,
    pub pad_left: u32,
    pub pad_top: u32,
}

impl Letterbox {
    pub fn new(width: u32, height: u32, size: u32) -> Self {
        let scale = (size as f32 / height as f32).min(size as f32 / width as f32);
        let resized_w = ((width as f32 * scale).round() as u32).clamp(1, size);
        let resized_h = ((height as f32 * scale).round() as u32).clamp(1, size);
        // Ultralytics: left = round(dw/2 − 0.1), top = round(dh/2 − 0.1).
        let pad_left = ((size - resized_w) as f32 / 2.0 - 0.1).round().max(0.0) as u32;
        let pad_top = ((size - resized_h) as f32 / 2.0 - 0.1).round().max(0.0) as u32;
        Self { size, scale, resized_w, resized_h, pad_left, pad_top }
    }

    /// Input pixel coordinates → frame pixel coordinates.
    pub fn to_frame(&self, x: f32, y: f32) -> (f32, f32) {
        ((x - self.pad_left as f32) / self.scale, (y - self.pad_top as f32) / self.scale)
    }
}

/// Letterboxes an RGB8 frame into a float32 NCHW tensor (values 0–1), bilinear.
pub fn preprocess(rgb: &[u8], width: u32, height: u32, lb: &Letterbox) -> Result<Vec<f32>, PerceptionError> {
    let expected = width as usize * height as usize * 3;
    if rgb.len() != expected {
        return Err(PerceptionError::Input(format!("colour has {} bytes, expected {expected} ({width}x{height}x3)", rgb.len())));
    }
    let src = Mat::new_rows_cols_with_data(height as i32, width as i32 * 3, rgb)?;
    let src = src.reshape(3, height as i32)?;
    let mut resized = Mat::default();
    imgproc::resize(&src, &mut resized, Size::new(lb.resized_w as i32, lb.resized_h as i32), 0.0, 0.0, imgproc::INTER_LINEAR)?;
    let s = lb.size as usize;
    let plane = s * s;
    let mut out = vec![f32::from(PAD_VALUE) / 255.0; 3 * plane];
    let bytes = resized.data_bytes()?;
    let rw = lb.resized_w as usize;
    for y in 0..lb.resized_h as usize {
        let row = &bytes[y * rw * 3..(y + 1) * rw * 3];
        let base = (y + lb.pad_top as usize) * s + lb.pad_left as usize;
        for (x, px) in row.chunks_exact(3).enumerate() {
            for c in 0..3 {
                out[c * plane + base + x] = f32::from(px[c]) / 255.0;
            }
        }
    }
    Ok(out)
}

/// Decoding thresholds.
#[derive(Debug, Clone, Copy)]
pub struct DecodeParams {
    pub score_threshold: f32,
    pub nms_iou_threshold: f32,
    pub mask_threshold: f32,
    pub max_instances: usize,
}

/// One detection in input (letterboxed) pixel coordinates.
#[derive(Debug, Clone)]
pub struct Detection {
    pub class_id: usize,
    pub score: f32,
    /// x0, y0, x1, y1 in input pixels.
    pub bbox: [f32; 4],
    pub coefficients: Vec<f32>,
}

/// Intersection over union of two xyxy boxes.
pub fn iou(a: &[f32; 4], b: &[f32; 4]) -> f32 {
    let iw = (a[2].min(b[2]) - a[0].max(b[0])).max(0.0);
    let ih = (a[3].min(b[3]) - a[1].max(b[1])).max(0.0);
    let inter = iw * ih;
    let union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter;
    if union > 0.0 { inter / union } else { 0.0 }
}

/// Decodes `output0` (`[4 + classes + mask_dim, anchors]`, row-major) into detections
/// above the score threshold, then applies class-aware NMS. Highest scores first.
/// (A negated comparison, so that a NaN score is dropped too.)
#[allow(clippy::neg_cmp_op_on_partial_ord)]
pub fn decode_detections(
    output0: &[f32],
    anchors: usize,
    classes: usize,
    mask_dim: usize,
    params: &DecodeParams,
) -> Result<Vec<Detection>, PerceptionError> {
    let rows = 4 + classes + mask_dim;
    if output0.len() != rows * anchors {
        return Err(PerceptionError::Model(format!("output0 holds {} values, expected {rows}×{anchors}", output0.len())));
    }
    let at = |row: usize, j: usize| output0[row * anchors + j];
    let mut candidates = Vec::new();
    for j in 0..anchors {
        let (mut best, mut best_c) = (f32::MIN, 0);
        for c in 0..classes {
            let s = at(4 + c, j);
            if s > best {
                best = s;
                best_c = c;
            }
        }
        if !(best > params.score_threshold) {
            continue;
        }
        let (cx, cy, w, h) = (at(0, j), at(1, j), at(2, j), at(3, j));
        let bbox = [cx - w / 2.0, cy - h / 2.0, cx + w / 2.0, cy + h / 2.0];
        let coefficients = (0..mask_dim).map(|k| at(4 + classes + k, j)).collect();
        candidates.push(Detection { class_id: best_c, score: best, bbox, coefficients });
    }
    candidates.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut kept: Vec<Detection> = Vec::new();
    for d in candidates {
        if kept.len() == params.max_instances {
            break;
        }
        if kept.iter().any(|k| k.class_id == d.class_id && iou(&k.bbox, &d.bbox) > params.nms_iou_threshold) {
            continue;
        }
        kept.push(d);
    }
    Ok(kept)
}

/// Turns detections into a per-pixel instance map of the `width × height` frame.
/// `proto` is `[mask_dim, p, p]`. A pixel overlapped by several instances belongs
/// to the highest-scoring one (detections arrive sorted by score).
#[allow(clippy::too_many_arguments)]
pub fn assemble(
    detections: &[Detection],
    proto: &[f32],
    mask_dim: usize,
    p: usize,
    lb: &Letterbox,
    width: u32,
    height: u32,
    params: &DecodeParams,
    class_names: &[String],
) -> Result<Segmentation, PerceptionError> {
    if proto.len() != mask_dim * p * p {
        return Err(PerceptionError::Model(format!("output1 holds {} values, expected {mask_dim}×{p}×{p}", proto.len())));
    }
    let (w, h) = (width as usize, height as usize);
    let mut instance_map = vec![0u16; w * h];
    let mut instances = Vec::with_capacity(detections.len());
    let mut probs = Vec::new();
    for d in detections {
        // The box in frame pixels, clipped to the frame.
        let (fx0, fy0) = lb.to_frame(d.bbox[0], d.bbox[1]);
        let (fx1, fy1) = lb.to_frame(d.bbox[2], d.bbox[3]);
        let (fx0, fy0) = (fx0.clamp(0.0, width as f32), fy0.clamp(0.0, height as f32));
        let (fx1, fy1) = (fx1.clamp(0.0, width as f32), fy1.clamp(0.0, height as f32));
        if fx1 - fx0 < 1.0 || fy1 - fy0 < 1.0 {
            continue;
        }
        // Prototype window covering the box (one cell of margin for interpolation).
        let px0 = ((d.bbox[0] / PROTO_STRIDE).floor() as isize - 1).clamp(0, p as isize - 1) as usize;
        let py0 = ((d.bbox[1] / PROTO_STRIDE).floor() as isize - 1).clamp(0, p as isize - 1) as usize;
        let px1 = ((d.bbox[2] / PROTO_STRIDE).ceil() as isize + 1).clamp(0, p as isize - 1) as usize;
        let py1 = ((d.bbox[3] / PROTO_STRIDE).ceil() as isize + 1).clamp(0, p as isize - 1) as usize;
        let (ww, wh) = (px1 - px0 + 1, py1 - py0 + 1);
        probs.clear();
        probs.resize(ww * wh, 0f32);
        for (k, &c) in d.coefficients.iter().enumerate() {
            let plane = &proto[k * p * p..(k + 1) * p * p];
            for y in 0..wh {
                let row = &plane[(py0 + y) * p + px0..(py0 + y) * p + px0 + ww];
                let out = &mut probs[y * ww..(y + 1) * ww];
                for (o, v) in out.iter_mut().zip(row) {
                    *o += c * v;
                }
            }
        }
        probs.iter_mut().for_each(|v| *v = 1.0 / (1.0 + (-*v).exp()));

        let id = (instances.len() + 1) as u16;
        let mut pixels = 0u32;
        let (x0, y0) = (fx0.floor() as usize, fy0.floor() as usize);
        let (x1, y1) = ((fx1.ceil() as usize).min(w), (fy1.ceil() as usize).min(h));
        for y in y0..y1 {
            let fy = y as f32 + 0.5;
            if fy < fy0 || fy > fy1 {
                continue;
            }
            // Frame pixel centre → input pixel → prototype cell coordinates.
            let iy = fy * lb.scale + lb.pad_top as f32;
            let gy = (iy / PROTO_STRIDE - 0.5 - py0 as f32).clamp(0.0, (wh - 1) as f32);
            let (gy0, ty) = (gy.floor() as usize, gy.fract());
            let gy1 = (gy0 + 1).min(wh - 1);
            for x in x0..x1 {
                let fx = x as f32 + 0.5;
                if fx < fx0 || fx > fx1 {
                    continue;
                }
                let i = y * w + x;
                if instance_map[i] != 0 {
                    continue;
                }
                let ix = fx * lb.scale + lb.pad_left as f32;
                let gx = (ix / PROTO_STRIDE - 0.5 - px0 as f32).clamp(0.0, (ww - 1) as f32);
                let (gx0, tx) = (gx.floor() as usize, gx.fract());
                let gx1 = (gx0 + 1).min(ww - 1);
                let top = probs[gy0 * ww + gx0] * (1.0 - tx) + probs[gy0 * ww + gx1] * tx;
                let bottom = probs[gy1 * ww + gx0] * (1.0 - tx) + probs[gy1 * ww + gx1] * tx;
                if top * (1.0 - ty) + bottom * ty > params.mask_threshold {
                    instance_map[i] = id;
                    pixels += 1;
                }
            }
        }
        if pixels == 0 {
            continue;
        }
        let class_name = class_names.get(d.class_id).cloned().unwrap_or_else(|| format!("class{}", d.class_id));
        instances.push(Instance { id, class_id: d.class_id as u16, class_name, score: d.score, bbox: [fx0, fy0, fx1, fy1], pixels });
    }
    Ok(Segmentation { width, height, instance_map, instances })
}

/// Parses the class list Ultralytics stores in the model metadata (`names`): a
/// Python dict literal such as `{0: 'person', 1: 'bicycle', 9: "traffic light"}`.
pub fn parse_class_names(text: &str) -> Result<Vec<String>, PerceptionError> {
    let bad = |why: &str| PerceptionError::Model(format!("model metadata `names` is not a class dict ({why}): {:.60}", text));
    let body = text.trim().strip_prefix('{').and_then(|t| t.strip_suffix('}')).ok_or_else(|| bad("no braces"))?;
    let mut names: Vec<(usize, String)> = Vec::new();
    let mut rest = body.trim_start();
    while !rest.is_empty() {
        let colon = rest.find(':').ok_or_else(|| bad("no colon"))?;
        let index: usize = rest[..colon].trim().parse().map_err(|_| bad("non-numeric key"))?;
        let after = rest[colon + 1..].trim_start();
        let quote = after.chars().next().filter(|c| *c == '\'' || *c == '"').ok_or_else(|| bad("unquoted name"))?;
        let end = after[1..].find(quote).ok_or_else(|| bad("unterminated name"))? + 1;
        names.push((index, after[1..end].to_string()));
        rest = after[end + 1..].trim_start();
        rest = rest.strip_prefix(',').unwrap_or(rest).trim_start();
    }
    names.sort_by_key(|(i, _)| *i);
    if names.iter().enumerate().any(|(k, (i, _))| k != *i) {
        return Err(bad("keys are not 0..n"));
    }
    Ok(names.into_iter().map(|(_, n)| n).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn letterbox_of_a_portrait_photo() {
        // bus.jpg: 810×1080 into 640.
        let lb = Letterbox::new(810, 1080, 640);
        assert_eq!((lb.resized_w, lb.resized_h, lb.pad_left, lb.pad_top), (480, 640, 80, 0));
        let (x, y) = lb.to_frame(80.0 + 240.0, 320.0);
        assert!((x - 405.0).abs() < 1e-3 && (y - 540.0).abs() < 1e-3);
        let lb = Letterbox::new(640, 480, 320);
        assert_eq!((lb.resized_w, lb.resized_h, lb.pad_left, lb.pad_top), (320, 240, 0, 40));
    }

    #[test]
    fn class_names_from_metadata() {
        let names = parse_class_names("{0: 'person', 1: 'bicycle', 2: \"traffic light\", 3: 'teddy bear'}").unwrap();
        assert_eq!(names, ["person", "bicycle", "traffic light", "teddy bear"]);
        let err = parse_class_names("{0: 'a', 2: 'b'}").unwrap_err().to_string();
        assert!(err.contains("keys are not 0..n"), "{err}");
        assert!(parse_class_names("[1, 2]").is_err());
    }

    #[test]
    fn class_aware_nms() {
        // Three anchors, 2 classes, no mask coefficients: two overlapping boxes of
        // class 0 (one suppressed) and one overlapping box of class 1 (kept).
        let anchors = 3;
        let mut out = vec![0f32; 6 * anchors];
        let set = |out: &mut Vec<f32>, row: usize, j: usize, v: f32| out[row * anchors + j] = v;
        for (j, (cx, s0, s1)) in [(50.0, 0.9, 0.0), (52.0, 0.8, 0.0), (51.0, 0.0, 0.7)].into_iter().enumerate() {
            set(&mut out, 0, j, cx);
            set(&mut out, 1, j, 50.0);
            set(&mut out, 2, j, 20.0);
            set(&mut out, 3, j, 20.0);
            set(&mut out, 4, j, s0);
            set(&mut out, 5, j, s1);
        }
        let params = DecodeParams { score_threshold: 0.25, nms_iou_threshold: 0.45, mask_threshold: 0.5, max_instances: 10 };
        let d = decode_detections(&out, anchors, 2, 0, &params).unwrap();
        assert_eq!(d.iter().map(|d| (d.class_id, d.score)).collect::<Vec<_>>(), [(0, 0.9), (1, 0.7)]);
        assert_eq!(d[0].bbox, [40.0, 40.0, 60.0, 60.0]);
    }
}
