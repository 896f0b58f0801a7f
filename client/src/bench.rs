//! `stillmap-client bench-codecs`: measures the depth codecs (and JPEG colour) on
//! real frames and prints a Markdown table.

use std::path::Path;
use std::time::Instant;

use stillmap_proto::codec::{self, ColorImage, DepthImage};
use stillmap_proto::pb::DepthEncoding;

use crate::ClientError;
use crate::source::FrameSource;
use crate::tum::TumSource;

/// One row of the table.
#[derive(Debug, Clone)]
pub struct CodecRow {
    pub name: String,
    pub lossless: bool,
    pub mean_bytes: f64,
    pub ratio: f64,
    pub encode_ms: f64,
    pub decode_ms: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// Times `encode` and `decode` over `items`, `repeats` times each, median per frame.
fn measure<T, E: Fn(&T) -> Vec<u8>, D: Fn(&[u8], &T) -> bool>(
    name: &str,
    items: &[T],
    raw_bytes: usize,
    repeats: usize,
    encode: E,
    decode_ok: D,
) -> CodecRow {
    let (mut enc_ms, mut dec_ms, mut sizes) = (vec![], vec![], vec![]);
    let mut lossless = true;
    for item in items {
        for _ in 0..repeats {
            let t = Instant::now();
            let bytes = encode(item);
            enc_ms.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            lossless &= decode_ok(&bytes, item);
            dec_ms.push(t.elapsed().as_secs_f64() * 1e3);
            sizes.push(bytes.len() as f64);
        }
    }
    let mean_bytes = sizes.iter().sum::<f64>() / sizes.len().max(1) as f64;
    CodecRow {
        name: name.into(),
        lossless,
        mean_bytes,
        ratio: raw_bytes as f64 / mean_bytes.max(1.0),
        encode_ms: median(enc_ms),
        decode_ms: median(dec_ms),
    }
}

/// Runs every codec over up to `max_frames` frames of a TUM sequence.
pub fn bench_codecs(dir: &Path, max_frames: usize, repeats: usize, jpeg_quality: u8) -> Result<Vec<CodecRow>, ClientError> {
    // Codecs do not depend on the intrinsics: any folder name will do.
    let nominal = crate::calibration::CameraOptions { allow_default_intrinsics: true, ..Default::default() };
    let mut src = TumSource::open(dir, Some(max_frames), &nominal)?;
    let (mut depths, mut colors): (Vec<DepthImage>, Vec<ColorImage>) = (vec![], vec![]);
    while let Some(f) = src.next_frame()? {
        depths.push(f.depth);
        colors.push(f.color);
    }
    let Some(first) = depths.first() else {
        return Err(ClientError::Source("no frames".into()));
    };
    let (w, h) = (first.width, first.height);
    let raw_depth = w as usize * h as usize * 2;
    let mut rows = Vec::new();
    for (name, enc) in [("PNG16", DepthEncoding::Png16), ("RVL", DepthEncoding::Rvl), ("zstd-1", DepthEncoding::Zstd)] {
        rows.push(measure(
            name,
            &depths,
            raw_depth,
            repeats,
            |d| codec::encode_depth(enc, d).unwrap_or_default(),
            |b, d| codec::decode_depth(enc, b, w, h).is_ok_and(|back| back == *d),
        ));
    }
    let jpeg_name = format!("JPEG q{jpeg_quality} (colour)");
    rows.push(measure(
        &jpeg_name,
        &colors,
        w as usize * h as usize * 3,
        repeats,
        |c| codec::encode_jpeg(c, jpeg_quality).unwrap_or_default(),
        // JPEG is lossy: decode for the timing, report "no".
        |b, _| {
            let _ = codec::decode_color(stillmap_proto::pb::ColorEncoding::Jpeg, b, w, h);
            false
        },
    ));
    Ok(rows)
}

/// Formats rows as a Markdown table.
pub fn table(rows: &[CodecRow], frames: usize) -> String {
    let mut s = format!(
        "| codec ({frames} real 640x480 frames) | lossless | mean bytes | ratio | encode ms (median) | decode ms (median) |\n|---|---|---|---|---|---|\n"
    );
    for r in rows {
        s.push_str(&format!(
            "| {} | {} | {:.0} | {:.2} | {:.2} | {:.2} |\n",
            r.name,
            if r.lossless { "yes" } else { "no" },
            r.mean_bytes,
            r.ratio,
            r.encode_ms,
            r.decode_ms
        ));
    }
    s
}
