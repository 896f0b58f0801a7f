//! Instance segmentation with the real YOLOv8n-seg model on the real test photos
//! (numbers in MODELS.md were measured with Python onnxruntime on the same files).

use stillmap_perception::testing as support;

use stillmap_perception::config::SegmentationConfig;
use stillmap_perception::segment::{NO_CLASS, NO_INSTANCE, RgbFrame};
use stillmap_perception::{PerceptionError, Segmentation, Segmenter, YoloSegmenter};
use support::{photo, segmentation_config};

fn count(seg: &Segmentation, class: &str) -> usize {
    seg.instances.iter().filter(|i| i.class_name == class).count()
}

#[test]
fn bus_has_four_persons_and_the_bus_at_640() {
    let mut seg = YoloSegmenter::new(&segmentation_config("yolov8n-seg_fp32_640.onnx")).expect("model loads");
    assert_eq!(seg.input_size(), 640);
    assert_eq!(seg.class_names().len(), 80);
    assert_eq!((seg.class_names()[0].as_str(), seg.class_names()[79].as_str()), ("person", "toothbrush"));
    let (rgb, w, h) = photo("bus.jpg");
    let out = seg.segment(&rgb, w, h).expect("segment");
    for i in &out.instances {
        eprintln!("{} {:.2} {:?} {} px", i.class_name, i.score, i.bbox.map(|v| v.round()), i.pixels);
    }
    assert_eq!(count(&out, "person"), 4, "{:?}", out.instances);
    assert_eq!(count(&out, "bus"), 1);
    let bus = out.instances.iter().find(|i| i.class_name == "bus").expect("bus");
    // MODELS.md: bus 0.87, box [20,225,797,739], 259.6k px (29.7 % of the image).
    assert!((bus.score - 0.87).abs() < 0.02, "{}", bus.score);
    for (got, want) in bus.bbox.iter().zip([20.0, 225.0, 797.0, 739.0]) {
        assert!((got - want).abs() < 6.0, "{:?}", bus.bbox);
    }
    let fraction = bus.pixels as f64 / f64::from(w * h);
    assert!((fraction - 0.297).abs() < 0.015, "bus covers {fraction}");
    // Per-pixel maps agree with the instance list.
    let classes = out.class_map();
    let scores = out.score_map();
    assert_eq!(out.instance_map.iter().filter(|&&id| id == bus.id).count() as u32, bus.pixels);
    for (k, &id) in out.instance_map.iter().enumerate() {
        if id == NO_INSTANCE {
            assert_eq!((classes[k], scores[k]), (NO_CLASS, 0.0));
        } else {
            let inst = out.instance(id).expect("listed");
            assert_eq!((classes[k], scores[k]), (inst.class_id, inst.score));
        }
    }
}

#[test]
fn astronaut_is_one_person_covering_about_forty_percent() {
    let mut seg = YoloSegmenter::new(&segmentation_config("yolov8n-seg_fp32_640.onnx")).expect("model loads");
    let (rgb, w, h) = photo("astronaut.png");
    let out = seg.segment(&rgb, w, h).expect("segment");
    assert_eq!(count(&out, "person"), 1, "{:?}", out.instances);
    let person = out.instances.iter().find(|i| i.class_name == "person").expect("person");
    let fraction = person.pixels as f64 / f64::from(w * h);
    // MODELS.md: 110.4k px, 42.1 %.
    assert!((0.38..=0.46).contains(&fraction), "person covers {fraction}");
}

#[test]
fn the_320_model_works_too() {
    let mut seg = YoloSegmenter::new(&segmentation_config("yolov8n-seg_fp32_320.onnx")).expect("model loads");
    assert_eq!(seg.input_size(), 320);
    let (rgb, w, h) = photo("bus.jpg");
    let out = seg.segment(&rgb, w, h).expect("segment");
    assert_eq!(count(&out, "bus"), 1, "{:?}", out.instances);
    assert!(count(&out, "person") >= 3, "{:?}", out.instances);
}

#[test]
fn model_problems_are_named_at_start_up() {
    let err = |config: SegmentationConfig| match YoloSegmenter::new(&config) {
        Ok(_) => panic!("model {} loaded", config.model_path),
        Err(e) => e,
    };
    let missing = SegmentationConfig { model_path: "/nonexistent/yolo.onnx".into(), ..segmentation_config("x") };
    let e = err(missing);
    assert!(matches!(e, PerceptionError::Model(_)));
    assert_eq!(e.to_string(), "segmentation model /nonexistent/yolo.onnx does not exist");

    let not_onnx = segmentation_config("images/bus.jpg");
    let e = err(not_onnx.clone()).to_string();
    assert!(e.starts_with(&format!("cannot load segmentation model {}: ", not_onnx.model_path)), "{e}");

    let size = SegmentationConfig { input_size: 320, ..segmentation_config("yolov8n-seg_fp32_640.onnx") };
    let e = err(size.clone()).to_string();
    assert_eq!(e, format!("perception.segmentation.input_size is 320 but model {} takes 640×640", size.model_path));

    let bad_input = YoloSegmenter::new(&segmentation_config("yolov8n-seg_fp32_320.onnx")).expect("model").segment(&[0; 10], 4, 4);
    assert_eq!(bad_input.unwrap_err().to_string(), "bad perception input: colour has 10 bytes, expected 48 (4x4x3)");
}

/// The batching model `deploy/make-batched-model.py` makes (`make test` runs it via
/// deploy/install-deps.sh into .deps/models).
fn batched_model(size: u32) -> String {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../.deps/models/yolov8n-seg_fp32_{size}_batch.onnx"));
    assert!(path.is_file(), "{} is missing: run deploy/install-deps.sh (make test does)", path.display());
    path.display().to_string()
}

/// A batch of frames of different sizes through the symbolic-batch model gives each
/// frame exactly what it gets alone, and what the shipped batch-1 model gives it.
#[test]
fn a_batched_run_equals_the_single_frame_runs() {
    let config = SegmentationConfig { model_path: batched_model(320), ..segmentation_config("x") };
    let mut batched = YoloSegmenter::new(&config).expect("batched model loads");
    assert!(batched.dynamic_batch());
    assert_eq!(batched.max_batch(), usize::MAX);
    let mut single = YoloSegmenter::new(&segmentation_config("yolov8n-seg_fp32_320.onnx")).expect("model loads");
    assert!(!single.dynamic_batch());
    assert_eq!(single.max_batch(), 1);

    let (bus, bw, bh) = photo("bus.jpg");
    let (astronaut, aw, ah) = photo("astronaut.png");
    let flipped: Vec<u8> = bus.chunks_exact(3).rev().flatten().copied().collect();
    let frames = [
        RgbFrame { rgb: &bus, width: bw, height: bh },
        RgbFrame { rgb: &astronaut, width: aw, height: ah },
        RgbFrame { rgb: &flipped, width: bw, height: bh },
    ];
    let together = batched.segment_batch(&frames).expect("batch");
    assert_eq!(together.len(), 3);
    for (f, seg) in frames.iter().zip(&together) {
        let alone = batched.segment(f.rgb, f.width, f.height).expect("alone");
        assert_eq!(seg, &alone, "a frame's result does not depend on its batch");
        assert_eq!(seg, &single.segment(f.rgb, f.width, f.height).expect("batch-1 model"), "same as the shipped model");
    }
    assert_eq!(count(&together[0], "bus"), 1);
    assert!(count(&together[1], "person") >= 1, "{:?}", together[1].instances);
    assert_ne!(together[0], together[2], "the flipped photo is a different frame");
    // A batch-1 model runs a batch one frame at a time, with the same results.
    assert_eq!(single.segment_batch(&frames).expect("one by one"), together);
}

/// Padding a batch to a power of two (GPU providers: few input shapes, warmed up at
/// start) changes no frame's result; the warm-up runs the shapes batches will use.
#[test]
fn padded_batches_give_the_same_results() {
    use stillmap_perception::segment::{batch_shape, batch_shapes};
    assert_eq!([0, 1, 2, 3, 5, 8, 9, 16].map(batch_shape), [1, 1, 2, 4, 8, 8, 16, 16]);
    assert_eq!(batch_shapes(1), [1]);
    assert_eq!(batch_shapes(12), [1, 2, 4, 8, 16]);
    assert_eq!(batch_shapes(16), [1, 2, 4, 8, 16]);

    let config = SegmentationConfig { model_path: batched_model(320), ..segmentation_config("x") };
    let mut plain = YoloSegmenter::new(&config).expect("batched model loads");
    assert_eq!(plain.warm_up(8).expect("warm-up"), Vec::<usize>::new(), "the CPU pads nothing, so warms nothing");
    let mut padded = YoloSegmenter::new(&config).expect("batched model loads");
    padded.set_batch_padding(true);
    assert_eq!(padded.warm_up(3).expect("warm-up"), [1, 2, 4]);
    let (bus, bw, bh) = photo("bus.jpg");
    let (astronaut, aw, ah) = photo("astronaut.png");
    let frames = [
        RgbFrame { rgb: &bus, width: bw, height: bh },
        RgbFrame { rgb: &astronaut, width: aw, height: ah },
        RgbFrame { rgb: &bus, width: bw, height: bh },
    ];
    let three = padded.segment_batch(&frames).expect("3 frames run as a batch of 4");
    assert_eq!(three, plain.segment_batch(&frames).expect("3 frames as 3"));
    assert_eq!(count(&three[0], "bus"), 1);
}

/// A GPU provider that cannot run is a start-up error naming the way out, unless
/// the configuration allows the CPU.
#[test]
fn a_gpu_provider_that_cannot_run_fails_unless_the_cpu_is_allowed() {
    use stillmap_perception::config::ExecutionProvider;
    // This machine's ONNX Runtime is the CPU build: it has no CUDA provider.
    for provider in [ExecutionProvider::Cuda, ExecutionProvider::Tensorrt] {
        let config = SegmentationConfig { execution_provider: provider, ..segmentation_config("yolov8n-seg_fp32_320.onnx") };
        let e = match YoloSegmenter::new(&config) {
            Ok(s) => panic!("{provider:?} loaded on {}", s.device()),
            Err(e) => e.to_string(),
        };
        assert!(e.starts_with(&format!("perception.segmentation.execution_provider = \"{}\" cannot run: ", provider.name())), "{e}");
        assert!(e.contains("make gpu-deps") && e.contains("fallback_to_cpu = true"), "{e}");
        let fallback = SegmentationConfig { fallback_to_cpu: true, ..config };
        assert_eq!(YoloSegmenter::new(&fallback).expect("falls back").device(), "cpu");
    }
}
