//! Perception speed on the real fr1_rpy frames: segmentation at 640 and 320,
//! flow + mask per stage, and dynamic feature elimination. Prints a table beside
//! the paper's Table 9, then runs criterion.
//!
//! `cargo bench -p stillmap-perception` (needs ORT_DYLIB_PATH or .deps/ort;
//! `STILLMAP_BENCH_NO_SEGMENTATION=1` skips the segmentation rows). With the
//! batching models in .deps/models (deploy/make-batched-model.py) it also prints
//! segmentation per batch size: `STILLMAP_BENCH_BATCHES` (default "1 4 8 16"),
//! `STILLMAP_BENCH_PROVIDER` (cpu, cuda or tensorrt; the GPU ones need the GPU
//! build of ONNX Runtime: `make gpu-deps`, then ORT_DYLIB_PATH and LD_LIBRARY_PATH as
//! `make ... GPU=1` sets them); `STILLMAP_BENCH_ONLY_BATCHES=1` prints that table alone
//! (needs only the 640 batching model and the frames: what a GPU run carries). The
//! table's flow + mask rows run the two-phase masker around the real tracker, as
//! the server does (tracking time not included); the criterion bench runs the
//! one-phase `process` without a tracked motion (the path after a tracking loss).

use stillmap_perception::testing as support;
use stillmap_tracking::testing as tum;

use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group};
use stillmap_perception::segment::RgbFrame;
use stillmap_perception::{DynamicMasker, MaskerInput, PerceptionConfig, Segmenter, YoloSegmenter};
use stillmap_tracking::features::Extractor;
use stillmap_tracking::tracker::to_gray;
use stillmap_tracking::{FrameInput, Tracker, TrackerConfig};

const FRAMES: usize = 60;

fn stats(mut v: Vec<Duration>) -> (f64, f64, f64) {
    v.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let mean = v.iter().map(|d| ms(*d)).sum::<f64>() / v.len() as f64;
    (mean, ms(v[v.len() / 2]), ms(v[(v.len() * 95 / 100).min(v.len() - 1)]))
}

/// Segmentation time per batch size with the symbolic-batch models.
fn batch_table(frames: &[tum::TumFrame]) {
    let batches: Vec<usize> = std::env::var("STILLMAP_BENCH_BATCHES")
        .unwrap_or_else(|_| "1 4 8 16".into())
        .split_whitespace()
        .filter_map(|b| b.parse().ok())
        .filter(|&b| b > 0)
        .collect();
    let provider = match std::env::var("STILLMAP_BENCH_PROVIDER").as_deref() {
        Ok("cuda") => stillmap_perception::config::ExecutionProvider::Cuda,
        Ok("tensorrt") => stillmap_perception::config::ExecutionProvider::Tensorrt,
        _ => stillmap_perception::config::ExecutionProvider::Cpu,
    };
    for size in [640, 320] {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../.deps/models/yolov8n-seg_fp32_{size}_batch.onnx"));
        if !path.is_file() {
            println!("(no {}: run deploy/install-deps.sh for the batch rows)", path.display());
            return;
        }
        let mut config = support::segmentation_config("x");
        config.model_path = path.display().to_string();
        config.execution_provider = provider;
        config.intra_threads = std::env::var("STILLMAP_BENCH_ORT_THREADS").ok().and_then(|v| v.parse().ok()).unwrap_or(0);
        let mut seg = YoloSegmenter::new(&config).expect("batching model");
        println!("\nsegmentation {size} by batch size ({}); ms", seg.device());
        println!("| batch | per batch (median) | per frame | frames/s |");
        println!("|---|---|---|---|");
        for &b in &batches {
            let inputs: Vec<RgbFrame<'_>> =
                (0..b).map(|i| RgbFrame { rgb: &frames[i % frames.len()].rgb, width: 640, height: 480 }).collect();
            let _ = seg.segment_batch(&inputs).expect("warm-up");
            let runs = (32 / b).clamp(3, 10);
            let times: Vec<Duration> = (0..runs)
                .map(|_| {
                    let t = Instant::now();
                    seg.segment_batch(&inputs).expect("batch");
                    t.elapsed()
                })
                .collect();
            let (_, median, _) = stats(times);
            println!("| {b} | {median:.1} | {:.1} | {:.0} |", median / b as f64, 1e3 * b as f64 / median);
        }
    }
}

fn table() {
    let frames = tum::load(&tum::fr1_rpy_dir(), FRAMES);
    let camera = tum::fr1_camera();
    println!("\nperception on {FRAMES} real fr1_rpy frames (640x480, this CPU); ms per frame");
    println!("| stage | mean | median | p95 | paper (Table 9, GPU) |");
    println!("|---|---|---|---|---|");
    // STILLMAP_BENCH_NO_SEGMENTATION=1: the flow + mask rows only.
    let models: &[(&str, &str)] = if std::env::var_os("STILLMAP_BENCH_NO_SEGMENTATION").is_some() {
        &[]
    } else {
        &[("yolov8n-seg_fp32_640.onnx", "336.1 (Mask R-CNN)"), ("yolov8n-seg_fp32_320.onnx", "")]
    };
    for &(model, paper) in models {
        let mut config = support::segmentation_config(model);
        // STILLMAP_BENCH_ORT_THREADS: ONNX Runtime intra-op threads (default: its own choice).
        config.intra_threads = std::env::var("STILLMAP_BENCH_ORT_THREADS").ok().and_then(|v| v.parse().ok()).unwrap_or(0);
        let mut seg = YoloSegmenter::new(&config).expect("model");
        let _ = seg.segment(&frames[0].rgb, 640, 480);
        let times: Vec<Duration> = frames
            .iter()
            .map(|f| {
                let t = Instant::now();
                seg.segment(&f.rgb, 640, 480).expect("segment");
                t.elapsed()
            })
            .collect();
        let (mean, median, p95) = stats(times);
        println!("| segmentation {} ({}) | {mean:.1} | {median:.1} | {p95:.1} | {paper} |", seg.input_size(), seg.device());
    }
    let mut config = PerceptionConfig::default();
    // STILLMAP_BENCH_NO_RETRACT=1: without following keyframes' pixels (its cost).
    if std::env::var_os("STILLMAP_BENCH_NO_RETRACT").is_some() {
        config.fusion.retract_keyframes = 0;
    }
    let flow_label = format!("flow (Farneback {}x{})", 640 / config.flow.subsample, 480 / config.flow.subsample);
    let mut masker = DynamicMasker::new(camera.clone(), config, &[]).expect("masker");
    let (mut flow, mut ego, mut warp, mut fusion, mut total) = (vec![], vec![], vec![], vec![], vec![]);
    let mut masks = Vec::new();
    // As in the server: the tracker runs between the two phases and its motion feeds `finish`.
    let mut tracker = Tracker::new(camera.clone(), TrackerConfig::default()).expect("tracker");
    let mut last_pose: Option<nalgebra::Isometry3<f64>> = None;
    for (k, f) in frames.iter().enumerate() {
        let mask = masker
            .prepare(MaskerInput {
                sequence: k as u64,
                capture_time_ns: f.timestamp_ns,
                rgb: &f.rgb,
                depth: &f.depth,
                segmentation: None,
                motion_prior: None,
                accel_in_camera: None,
            })
            .expect("prepare");
        let track = tracker
            .track(&FrameInput { timestamp_ns: f.timestamp_ns, rgb: &f.rgb, depth: &f.depth, dynamic_mask: Some(&mask) })
            .expect("track");
        let motion = last_pose.zip(track.world_from_camera).map(|(a, b)| a.inverse() * b);
        last_pose = track.world_from_camera;
        let out = masker.finish(&f.depth, motion).expect("finish");
        if track.keyframe {
            masker.note_keyframe(k as u64);
        }
        if k > 0 {
            let t = out.times;
            flow.push(t.flow);
            ego.push(t.ego_motion);
            warp.push(t.warp);
            fusion.push(t.fusion);
            total.push(t.total);
        }
        masks.push(mask);
    }
    for (name, v, paper) in [
        (flow_label.as_str(), flow, ""),
        ("ego-motion compensation", ego, ""),
        ("warp", warp, ""),
        ("fusion", fusion, ""),
        ("flow + mask", total, "19.5 (flow)"),
    ] {
        let (mean, median, p95) = stats(v);
        println!("| {name} | {mean:.2} | {median:.2} | {p95:.2} | {paper} |");
    }
    // Elimination: the mask lookup of every extracted keypoint.
    let mut extractor = Extractor::new(&TrackerConfig::default()).expect("extractor");
    let times: Vec<Duration> = frames
        .iter()
        .zip(&masks)
        .map(|(f, mask)| {
            let feats = extractor.extract(&camera, &to_gray(&f.rgb), &f.depth, None).expect("extract");
            let t = Instant::now();
            let kept = feats.features.iter().filter(|ft| mask[ft.raw.y.round() as usize * 640 + ft.raw.x.round() as usize] == 0).count();
            std::hint::black_box(kept);
            t.elapsed()
        })
        .collect();
    let (mean, median, p95) = stats(times);
    println!("| elimination (mask lookup per keypoint) | {mean:.4} | {median:.4} | {p95:.4} | 2.45 |\n");
    if std::env::var_os("STILLMAP_BENCH_NO_SEGMENTATION").is_none() {
        batch_table(&frames);
    }
}

fn benches(c: &mut Criterion) {
    let frames = tum::load(&tum::fr1_rpy_dir(), 2);
    let mut seg = YoloSegmenter::new(&support::segmentation_config("yolov8n-seg_fp32_320.onnx")).expect("model");
    c.bench_function("segment/320", |b| b.iter(|| seg.segment(&frames[0].rgb, 640, 480).expect("segment")));
    let mut masker = DynamicMasker::new(tum::fr1_camera(), PerceptionConfig::default(), &[]).expect("masker");
    let mut k = 0u64;
    c.bench_function("flow_and_mask/fr1_rpy", |b| {
        b.iter(|| {
            let f = &frames[(k % 2) as usize];
            k += 1;
            masker
                .process(MaskerInput {
                    sequence: k,
                    capture_time_ns: 0,
                    rgb: &f.rgb,
                    depth: &f.depth,
                    segmentation: None,
                    motion_prior: None,
                    accel_in_camera: None,
                })
                .expect("mask")
        })
    });
}

criterion_group! {
    name = group;
    config = Criterion::default().sample_size(20);
    targets = benches
}

fn main() {
    if std::env::var_os("STILLMAP_BENCH_ONLY_BATCHES").is_some() {
        batch_table(&tum::load(&tum::fr1_rpy_dir(), 16));
        return;
    }
    table();
    group();
    Criterion::default().configure_from_args().final_summary();
}
