//! Map speed and size on the real fr1_rpy clip: fusion per keyframe, tile
//! rendering, the exports, memory per m³ and the size the store writes. Prints a
//! table, then runs criterion.
//!
//! `cargo bench -p stillmap-mapping`. Keyframes are every 5th frame (the
//! tracker's longest keyframe interval) at the ground-truth poses, all pixels
//! static (perception is benchmarked on its own).

use stillmap_tracking::testing as tum;

use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group};
use nalgebra::Vector3;
use stillmap_mapping::export::{cloud, objects, to_ply};
use stillmap_mapping::tiles::{MAX_ZOOM, OccupancyGrid, TopDown, encode_png_rgba};
use stillmap_mapping::voxel::BLOCK_EDGE;
use stillmap_mapping::{DepthView, MapBuilder, MappingConfig};
use stillmap_perception::composite::interpolate_pose;

const KEYFRAME_INTERVAL: usize = 5;

fn stats(mut v: Vec<Duration>) -> (f64, f64, f64) {
    v.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let mean = v.iter().map(|d| ms(*d)).sum::<f64>() / v.len() as f64;
    (mean, ms(v[v.len() / 2]), ms(v[(v.len() * 95 / 100).min(v.len() - 1)]))
}

fn build(frames: &[tum::TumFrame], gt: &[(u64, nalgebra::Isometry3<f64>)], config: MappingConfig) -> (MapBuilder, Vec<Duration>) {
    let camera = tum::fr1_camera();
    let mut b = MapBuilder::new(&camera, config).expect("builder");
    let mut times = Vec::new();
    for (k, f) in frames.iter().enumerate().step_by(KEYFRAME_INTERVAL) {
        let pose = interpolate_pose(gt, f.timestamp_ns).expect("ground truth");
        b.observe_accel(&pose, &(pose.rotation.inverse() * Vector3::z() * 9.81));
        let view = DepthView { depth: &f.depth, rgb: &f.rgb, exclude: None, classes: None };
        let t = Instant::now();
        b.add_keyframe(k as u64, &pose, &view).expect("fuse");
        times.push(t.elapsed());
    }
    (b, times)
}

fn table() {
    let dir = tum::fr1_rpy_dir();
    let frames = tum::load(&dir, 150);
    let gt = tum::groundtruth(&dir);
    println!("\nstatic semantic map on the real fr1_rpy clip (150 frames, a keyframe every {KEYFRAME_INTERVAL}); this CPU");
    println!(
        "| voxel | keyframes | fusion mean / median / p95 ms | occupied voxels | blocks | memory | memory per m³ of bounding box | store (zstd blocks) |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for voxel in [0.02, 0.04] {
        let (b, times) = build(&frames, &gt, MappingConfig { voxel_size_m: voxel, ..MappingConfig::default() });
        let n = times.len();
        let (mean, median, p95) = stats(times);
        let stats = b.map().stats();
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for (_, c, _) in b.map().occupied() {
            for i in 0..3 {
                lo[i] = lo[i].min(c[i]);
                hi[i] = hi[i].max(c[i]);
            }
        }
        let volume: f64 = (0..3).map(|i| hi[i] - lo[i] + voxel).product();
        let disk: usize = b.map().blocks().map(|(_, blk)| zstd::bulk::compress(&blk.to_bytes(), 1).expect("zstd").len() + 16).sum();
        let block_m3 = (voxel * f64::from(BLOCK_EDGE)).powi(3);
        println!(
            "| {:.0} cm | {n} | {mean:.1} / {median:.1} / {p95:.1} | {} | {} | {:.1} MiB ({:.2} MiB/m³ of blocks) | {:.2} MiB/m³ ({:.1} m³) | {:.2} MiB |",
            voxel * 100.0,
            stats.occupied_voxels,
            stats.blocks,
            stats.bytes as f64 / 1048576.0,
            stats.bytes as f64 / 1048576.0 / (stats.blocks as f64 * block_m3),
            stats.bytes as f64 / 1048576.0 / volume,
            volume,
            disk as f64 / 1048576.0
        );
    }
    let (b, _) = build(&frames, &gt, MappingConfig::default());
    let (up, _) = b.map_from_world().expect("map frame");
    let t = Instant::now();
    let top = TopDown::build(b.map(), &up);
    let top_build = t.elapsed();
    let [x0, y0, x1, y1] = top.bounds().expect("bounds");
    println!("\n| product (2 cm map) | mean ms | median | p95 | count |");
    println!("|---|---|---|---|---|");
    println!("| top-down index build (once per map version) | {:.1} | | | 1 |", top_build.as_secs_f64() * 1e3);
    for zoom in [MAX_ZOOM, MAX_ZOOM - 2, 0] {
        let span = top.tile_span_m(zoom);
        let mut times = Vec::new();
        for tx in (x0 / span).floor() as i64..=(x1 / span).floor() as i64 {
            for ty in (-y1 / span).floor() as i64..=(-y0 / span).floor() as i64 {
                let t = Instant::now();
                let rgba = top.render(zoom, tx, ty).expect("tile");
                encode_png_rgba(&rgba, 256, 256).expect("png");
                times.push(t.elapsed());
            }
        }
        let n = times.len();
        let (mean, median, p95) = stats(times);
        println!("| tile render + PNG, zoom {zoom} ({:.2} m/tile) | {mean:.2} | {median:.2} | {p95:.2} | {n} |", span);
    }
    let t = Instant::now();
    let points = cloud(b.map(), &up, None);
    let ply = to_ply(&points, &[], "bench");
    println!(
        "| PLY export ({} points, {:.1} MiB) | {:.1} | | | 1 |",
        points.len(),
        ply.len() as f64 / 1048576.0,
        t.elapsed().as_secs_f64() * 1e3
    );
    let t = Instant::now();
    let objs = objects(b.map(), &up);
    println!("| objects ({} clusters) | {:.1} | | | 1 |", objs.len(), t.elapsed().as_secs_f64() * 1e3);
    let t = Instant::now();
    let grid = OccupancyGrid::build(b.map(), &up, -0.5, 0.5, 0.05).expect("grid");
    println!("| occupancy grid ({}x{} at 5 cm) | {:.1} | | | 1 |", grid.width, grid.height, t.elapsed().as_secs_f64() * 1e3);
}

fn criterion_benches(c: &mut Criterion) {
    let dir = tum::fr1_rpy_dir();
    let frames = tum::load(&dir, 40);
    let gt = tum::groundtruth(&dir);
    let (mut b, _) = build(&frames, &gt, MappingConfig::default());
    let f = &frames[37];
    let pose = interpolate_pose(&gt, f.timestamp_ns).expect("ground truth");
    let mut id = 1000;
    c.bench_function("fuse keyframe (2 cm, 640x480, warm map)", |bench| {
        bench.iter(|| {
            id += 1;
            b.add_keyframe(id, &pose, &DepthView { depth: &f.depth, rgb: &f.rgb, exclude: None, classes: None }).expect("fuse")
        })
    });
    let (up, _) = b.map_from_world().expect("map frame");
    let top = TopDown::build(b.map(), &up);
    let [x0, _, _, y1] = top.bounds().expect("bounds");
    let span = top.tile_span_m(MAX_ZOOM);
    let (tx, ty) = ((x0 / span).floor() as i64, (-y1 / span).floor() as i64);
    c.bench_function("render tile (zoom 5) + PNG", |bench| {
        bench.iter(|| encode_png_rgba(&top.render(MAX_ZOOM, tx, ty).expect("tile"), 256, 256).expect("png"))
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(Duration::from_secs(5));
    targets = criterion_benches
}

fn main() {
    table();
    benches();
    Criterion::default().configure_from_args().final_summary();
}
