//! The moving-board composite (the `dynamic` test's) over five runs with the
//! tracker's ORB feature count nudged by ±1–2 %: tracking on fr1_rpy swings by
//! centimetres under such tiny changes (docs/tracking.md, "Tracking accuracy"), so the
//! issue's "tracking error with the object within 20 % of the same frames
//! without it" is judged on medians, not on one run. Per run: the mask's scores,
//! then ATE of the masker + tracker on the composite, of the same masker + tracker
//! on the same frames without the board, and of the tracker alone without it.
//!
//! `cargo run --release -p stillmap-perception --example composite_spread`
//! (`PERCEPTION="fusion.key = value;..."` and `TRACKING="key = value;..."`
//! override the configurations). The real YOLOv8n-seg model segments each frame
//! once; its results are replayed, in order, to every run.

use stillmap_perception::testing as support;
use stillmap_perception::testing::composite_run;
use stillmap_tracking::testing as tum;

use composite_run::{CompositeFrame, Schedule};
use stillmap_perception::{PerceptionConfig, PerceptionError, Segmentation, Segmenter, YoloSegmenter};
use stillmap_tracking::TrackerConfig;

/// Feature counts relative to the configured one.
const NUDGES: [f64; 5] = [0.98, 0.99, 1.0, 1.01, 1.02];

/// The real segmenter's results on one clip, handed out again frame by frame.
struct Replay {
    names: Vec<String>,
    results: Vec<Segmentation>,
    next: usize,
}

impl Replay {
    fn record(segmenter: &mut YoloSegmenter, frames: &[CompositeFrame]) -> Self {
        let results = frames.iter().map(|f| segmenter.segment(&f.rgb, 640, 480).expect("segment")).collect();
        Self { names: segmenter.class_names().to_vec(), results, next: 0 }
    }
}

impl Segmenter for Replay {
    fn segment(&mut self, _rgb: &[u8], _width: u32, _height: u32) -> Result<Segmentation, PerceptionError> {
        let out = self.results.get(self.next).cloned().ok_or_else(|| PerceptionError::Input("replay ran out of frames".into()));
        self.next += 1;
        out
    }
    fn class_names(&self) -> &[String] {
        &self.names
    }
    fn device(&self) -> &str {
        "replay"
    }
}

fn overrides<T: serde::de::DeserializeOwned>(var: &str) -> T {
    toml::from_str(&std::env::var(var).unwrap_or_default().replace(';', "\n")).unwrap_or_else(|e| panic!("{var}: {e}"))
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let dir = tum::fr1_rpy_dir();
    let frames = tum::load(&dir, 150);
    let gt = tum::groundtruth(&dir);
    let with_board = composite_run::composite(&frames, &gt);
    let without_board = composite_run::without_object(&frames);
    let perception: PerceptionConfig = overrides("PERCEPTION");
    let base: TrackerConfig = overrides("TRACKING");
    let mut model = YoloSegmenter::new(&support::segmentation_config("yolov8n-seg_fp32_640.onnx")).expect("model");
    let mut seg_with = Replay::record(&mut model, &with_board);
    let mut seg_without = Replay::record(&mut model, &without_board);

    println!(
        "| features | IoU | false-dynamic | eliminated | ATE with board (cm) | masked, without board (cm) | tracker alone, without board (cm) |"
    );
    println!("|---|---|---|---|---|---|---|");
    let (mut with, mut masked, mut plain, mut eliminated) = (vec![], vec![], vec![], vec![]);
    for nudge in NUDGES {
        let features = (base.features as f64 * nudge).round() as usize;
        let tracking = TrackerConfig { features, candidate_features: base.candidate_features.max(features), ..base.clone() };
        seg_with.next = 0;
        seg_without.next = 0;
        let s =
            composite_run::run_with(&with_board, Some(&mut seg_with), Schedule::EveryFrame, false, perception.clone(), tracking.clone());
        let m = composite_run::run_with(
            &without_board,
            Some(&mut seg_without),
            Schedule::EveryFrame,
            false,
            perception.clone(),
            tracking.clone(),
        );
        let p = composite_run::track_plain_with(&frames, tracking);
        let (a, b, c) =
            (tum::score(&gt, &s.trajectory).ate_m * 100.0, tum::score(&gt, &m.trajectory).ate_m * 100.0, tum::score(&gt, &p).ate_m * 100.0);
        println!(
            "| {features} | {:.3} | {:.2} % | {:.2} % | {a:.2} | {b:.2} | {c:.2} |",
            s.mean_iou,
            s.false_dynamic * 100.0,
            s.eliminated_fraction * 100.0
        );
        with.push(a);
        masked.push(b);
        plain.push(c);
        eliminated.push(s.eliminated_fraction * 100.0);
    }
    let (a, b, c) = (median(with), median(masked), median(plain));
    println!(
        "\nmedians over {} runs: eliminated {:.2} %; ATE with board {a:.2} cm, masked without board {b:.2} cm ({:+.0} %), tracker alone without board {c:.2} cm ({:+.0} %)",
        NUDGES.len(),
        median(eliminated),
        (a / b - 1.0) * 100.0,
        (a / c - 1.0) * 100.0
    );
}
