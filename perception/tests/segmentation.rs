//! Instance segmentation with the real YOLOv8n-seg model on the real test photos
//! (numbers in MODELS.md were measured with Python onnxruntime on the same files).

mod support;

use stillmap_perception::config::SegmentationConfig;
use stillmap_perception::segment::{NO_CLASS, NO_INSTANCE};
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
