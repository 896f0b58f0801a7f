//! Tracking speed on the real TUM fr1_rpy clip: `cargo bench -p stillmap-tracking`.
//!
//! First prints a table of the tracker's own per-stage times (mean, median and p95
//! over the clip's 150 frames, after one warm-up pass) with that run's accuracy,
//! then runs the criterion benchmark `track_frame/fr1_rpy`: the time to track one
//! frame. Frames are fed cyclically in capture order, with a fresh tracker at the
//! start of every pass over the clip, so each frame is tracked in its real context
//! (its map and motion) and the mean covers the whole clip. Decoding the PNGs and
//! creating trackers stay outside the timing.

use stillmap_tracking::testing as tum;

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput};
use stillmap_tracking::{FrameInput, StageTimes, TrackOutput, Tracker, TrackerConfig, TrackingState};

/// Criterion samples (its minimum) and time budgets: the whole bench takes about 20 s.
const SAMPLE_SIZE: usize = 10;
const WARM_UP: Duration = Duration::from_secs(2);
const MEASUREMENT: Duration = Duration::from_secs(8);
/// The percentile reported beside mean and median.
const PERCENTILE: f64 = 95.0;

/// Reads one stage's time from a frame's [`StageTimes`].
type Stage = fn(&StageTimes) -> Duration;
/// The table's rows, in pipeline order.
const STAGES: [(&str, Stage); 6] = [
    ("extraction", |t| t.extraction),
    ("dense odometry (beside extraction)", |t| t.dense),
    ("matching", |t| t.matching),
    ("optimization", |t| t.optimization),
    ("local_ba", |t| t.local_ba),
    ("total", |t| t.total),
];

fn fr1_tracker() -> Tracker {
    Tracker::new(tum::fr1_camera(), TrackerConfig::default()).expect("tracker")
}

fn track(tracker: &mut Tracker, f: &tum::TumFrame) -> TrackOutput {
    tracker.track(&FrameInput { timestamp_ns: f.timestamp_ns, rgb: &f.rgb, depth: &f.depth, dynamic_mask: None }).expect("track")
}

/// Mean, median and nearest-rank percentile of `values` (ms), which it sorts.
fn summary(values: &mut [f64]) -> [f64; 3] {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    let median = if n.is_multiple_of(2) { (values[n / 2 - 1] + values[n / 2]) / 2.0 } else { values[n / 2] };
    let rank = ((PERCENTILE / 100.0 * n as f64).ceil() as usize).clamp(1, n);
    [values.iter().sum::<f64>() / n as f64, median, values[rank - 1]]
}

/// Tracks the clip once (after a warm-up pass) and prints per-stage times and accuracy.
fn print_stage_table(frames: &[tum::TumFrame], gt: &[(u64, nalgebra::Isometry3<f64>)]) {
    let mut tracker = fr1_tracker();
    for f in frames {
        track(&mut tracker, f);
    }
    let mut tracker = fr1_tracker();
    let outputs: Vec<TrackOutput> = frames.iter().map(|f| track(&mut tracker, f)).collect();

    println!("fr1_rpy, {} frames: per-frame stage times (ms)", frames.len());
    println!("{:<14}{:>8}{:>8}{:>8}", "stage", "mean", "median", "p95");
    for (name, stage) in STAGES {
        let mut ms: Vec<f64> = outputs.iter().map(|o| stage(&o.times).as_secs_f64() * 1e3).collect();
        let [mean, median, p95] = summary(&mut ms);
        println!("{name:<14}{mean:>8.2}{median:>8.2}{p95:>8.2}");
    }
    let keyframes = outputs.iter().filter(|o| o.keyframe).count();
    let tracked = outputs.iter().filter(|o| matches!(o.state, TrackingState::Tracking | TrackingState::Relocalized)).count();
    let est: Vec<_> =
        frames.iter().zip(&outputs).filter_map(|(f, o)| Some((tum::fr1_pose_time_ns(f.timestamp_ns), o.world_from_camera?))).collect();
    let s = tum::score(gt, &est);
    println!("(local_ba runs on keyframes only: {keyframes} of {})", frames.len());
    println!(
        "tracked {tracked}/{} | ATE {:.2} cm (origin-aligned {:.2}°) | RPE {:.2} mm {:.3}°",
        frames.len(),
        s.ate_m * 100.0,
        s.ate_origin_deg,
        s.rpe_m * 1e3,
        s.rpe_deg
    );
}

/// Feeds the clip's frames in order, forever, starting a fresh tracker on each pass.
struct Cycle<'a> {
    frames: &'a [tum::TumFrame],
    tracker: Tracker,
    next: usize,
}

impl Cycle<'_> {
    /// Tracks the next frame; returns the time `track` took.
    fn step(&mut self) -> Duration {
        if self.next == self.frames.len() {
            self.tracker = fr1_tracker();
            self.next = 0;
        }
        let f = &self.frames[self.next];
        self.next += 1;
        let start = Instant::now();
        black_box(track(&mut self.tracker, f));
        start.elapsed()
    }
}

fn main() {
    let dir = tum::fr1_rpy_dir();
    let frames = tum::load(&dir, usize::MAX);
    print_stage_table(&frames, &tum::groundtruth(&dir));

    let mut c = Criterion::default().sample_size(SAMPLE_SIZE).warm_up_time(WARM_UP).measurement_time(MEASUREMENT).configure_from_args();
    let mut group = c.benchmark_group("track_frame");
    group.throughput(Throughput::Elements(1));
    let mut cycle = Cycle { frames: &frames, tracker: fr1_tracker(), next: 0 };
    group.bench_function("fr1_rpy", |b| b.iter_custom(|iters| (0..iters).map(|_| cycle.step()).sum()));
    group.finish();
    c.final_summary();
}
