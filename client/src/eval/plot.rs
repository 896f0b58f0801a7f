//! `--plot`: the associated reference and the (aligned) estimate, as a top view
//! and as x / y / z over time, in PNG or SVG.
//!
//! The top view projects onto the two axes of the reference frame along which the
//! associated reference moves most (x–y unless another pair spans more), at equal
//! scale. Text uses a TrueType font read at run time (`STILLMAP_PLOT_FONT`, else
//! DejaVu Sans / Liberation Sans / Noto Sans from Debian's font packages); without
//! one the plot is drawn without text and a warning is logged.

use std::ops::Range;
use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::{EvalError, Evaluation, Trajectory};

/// Image size, pixels: the top view on the left, the three time series on the right.
const SIZE: (u32, u32) = (1600, 800);
/// Environment variable naming a TTF/OTF font file for the plot's text.
pub const FONT_ENV: &str = "STILLMAP_PLOT_FONT";
/// Fonts tried when [`FONT_ENV`] is unset (fonts-dejavu-core, fonts-liberation2, fonts-noto-core).
const FONT_CANDIDATES: [&str; 4] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation2/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/noto/NotoSans-Regular.ttf",
];
/// Family name the font is registered under (plotters' `FontFamily::SansSerif`).
const FAMILY: &str = "sans-serif";
const CAPTION_PX: u32 = 22;
const LABEL_PX: u32 = 15;
const REFERENCE_COLOR: RGBColor = RGBColor(90, 90, 90);
const ESTIMATE_COLOR: RGBColor = RGBColor(0, 114, 189);
/// Margin around the data, as a fraction of its span.
const PAD: f64 = 0.05;
/// Line width, pixels. Wider lines hit plotters' bitmap bug #549 (strokes leaving
/// the chart on jagged data).
const LINE_PX: u32 = 1;
/// Smallest axis span, metres or seconds (a constant coordinate still gets an axis).
const MIN_SPAN: f64 = 1e-3;
const AXES: [&str; 3] = ["x", "y", "z"];

/// Output format, from the file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// PNG image.
    Png,
    /// SVG document.
    Svg,
}

impl Format {
    /// The format of `path` by its extension (`.png` or `.svg`, any case).
    pub fn of(path: &Path) -> Result<Format, EvalError> {
        match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
            Some("png") => Ok(Format::Png),
            Some("svg") => Ok(Format::Svg),
            _ => Err(EvalError::Usage(format!("--plot {}: the file name must end in .png or .svg", path.display()))),
        }
    }
}

/// Registers the plot font once; false when none could be loaded.
fn font_loaded() -> bool {
    static LOADED: OnceLock<bool> = OnceLock::new();
    *LOADED.get_or_init(|| {
        let candidates: Vec<String> = match std::env::var(FONT_ENV) {
            Ok(path) => vec![path],
            Err(_) => FONT_CANDIDATES.iter().map(|s| s.to_string()).collect(),
        };
        for path in &candidates {
            if let Ok(bytes) = std::fs::read(path) {
                // Registered fonts must live for the whole process.
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font(FAMILY, FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        tracing::warn!("no usable font among {candidates:?} (set {FONT_ENV}); plotting without text");
        false
    })
}

/// Draws `evaluation`'s trajectories to `path` (PNG or SVG by extension).
pub fn plot(path: &Path, evaluation: &Evaluation) -> Result<(), EvalError> {
    let format = Format::of(path)?;
    let text = font_loaded();
    let write_error = |message: String| EvalError::Write { path: path.to_owned(), message };
    let bytes = match format {
        Format::Png => {
            let mut buffer = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
            {
                let root = BitMapBackend::with_buffer(&mut buffer, SIZE).into_drawing_area();
                draw(&root, evaluation, text).map_err(write_error)?;
            }
            let image = stillmap_proto::codec::ColorImage { width: SIZE.0, height: SIZE.1, data: buffer };
            stillmap_proto::codec::encode_png_rgb(&image).map_err(|e| write_error(e.to_string()))?
        }
        Format::Svg => {
            let mut svg = String::new();
            {
                let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
                draw(&root, evaluation, text).map_err(write_error)?;
            }
            svg.into_bytes()
        }
    };
    std::fs::write(path, bytes).map_err(|e| write_error(e.to_string()))
}

/// `lo..hi` of `values`, padded, at least [`MIN_SPAN`] wide.
fn range(values: impl Iterator<Item = f64>) -> Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
    let (lo, hi) = if lo.is_finite() { (lo, hi) } else { (0.0, 0.0) };
    let pad = ((hi - lo) * PAD).max(MIN_SPAN / 2.0);
    lo - pad..hi + pad
}

/// The two axes along which `trajectory` spans most, in axis order.
fn top_view_axes(trajectory: &Trajectory) -> (usize, usize) {
    let span = |axis: usize| {
        let r = range(trajectory.iter().map(|p| p.1.translation.vector[axis]));
        r.end - r.start
    };
    let spans = [span(0), span(1), span(2)];
    let smallest = (0..3).min_by(|&a, &b| spans[a].total_cmp(&spans[b])).unwrap_or(2);
    match smallest {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    }
}

/// The same span for both ranges (equal scale), centred on each.
fn equal_spans(a: Range<f64>, b: Range<f64>) -> (Range<f64>, Range<f64>) {
    let half = (a.end - a.start).max(b.end - b.start) / 2.0;
    let centre = |r: &Range<f64>| (r.start + r.end) / 2.0;
    let (ca, cb) = (centre(&a), centre(&b));
    (ca - half..ca + half, cb - half..cb + half)
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, evaluation: &Evaluation, text: bool) -> Result<(), String> {
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    root.fill(&WHITE).map_err(err)?;
    let (left, right) = root.split_horizontally(SIZE.0 / 2);
    let (reference, estimate) = (&evaluation.reference, &evaluation.estimate);

    let (a, b) = top_view_axes(reference);
    let all = || reference.iter().chain(estimate.iter());
    let (ra, rb) = equal_spans(range(all().map(|p| p.1.translation.vector[a])), range(all().map(|p| p.1.translation.vector[b])));
    let mut builder = ChartBuilder::on(&left);
    builder.margin(15).x_label_area_size(40).y_label_area_size(60);
    if text {
        builder.caption(format!("{} — top view ({}–{})", evaluation.title(), AXES[a], AXES[b]), (FAMILY, CAPTION_PX));
    }
    let mut chart = builder.build_cartesian_2d(ra, rb).map_err(err)?;
    let mut mesh = chart.configure_mesh();
    if text {
        mesh.x_desc(format!("{} (m)", AXES[a])).y_desc(format!("{} (m)", AXES[b])).label_style((FAMILY, LABEL_PX));
    } else {
        mesh.x_labels(0).y_labels(0);
    }
    mesh.draw().map_err(err)?;
    // The reference last, on top of a possibly noisy estimate.
    for (trajectory, color, name) in [(estimate, ESTIMATE_COLOR, "estimate"), (reference, REFERENCE_COLOR, "reference")] {
        let points = trajectory.iter().map(|p| (p.1.translation.vector[a], p.1.translation.vector[b]));
        let series = chart.draw_series(LineSeries::new(points, color.stroke_width(LINE_PX))).map_err(err)?;
        series.label(name).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(LINE_PX + 1)));
    }
    if text {
        chart
            .configure_series_labels()
            .label_font((FAMILY, LABEL_PX))
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(err)?;
    }

    // Seconds since the first associated reference pose; the estimate on its own
    // clock shifted by the association offset.
    let t0 = reference.first().map_or(0.0, |p| p.0);
    let offset = evaluation.options.offset;
    let series = |trajectory: &Trajectory, shift: f64, axis: usize| -> Vec<(f64, f64)> {
        trajectory.iter().map(|p| (p.0 + shift - t0, p.1.translation.vector[axis])).collect()
    };
    let time = range(reference.iter().map(|p| p.0 - t0).chain(estimate.iter().map(|p| p.0 + offset - t0)));
    for (axis, area) in right.split_evenly((3, 1)).iter().enumerate() {
        let (ref_line, est_line) = (series(reference, 0.0, axis), series(estimate, offset, axis));
        let values = range(ref_line.iter().chain(&est_line).map(|p| p.1));
        let mut builder = ChartBuilder::on(area);
        builder.margin(10).x_label_area_size(35).y_label_area_size(60);
        let mut chart = builder.build_cartesian_2d(time.clone(), values).map_err(err)?;
        let mut mesh = chart.configure_mesh();
        if text {
            mesh.y_desc(format!("{} (m)", AXES[axis])).label_style((FAMILY, LABEL_PX));
            if axis == 2 {
                mesh.x_desc("time (s)");
            }
        } else {
            mesh.x_labels(0).y_labels(0);
        }
        mesh.draw().map_err(err)?;
        chart.draw_series(LineSeries::new(est_line, ESTIMATE_COLOR.stroke_width(LINE_PX))).map_err(err)?;
        chart.draw_series(LineSeries::new(ref_line, REFERENCE_COLOR.stroke_width(LINE_PX))).map_err(err)?;
    }
    root.present().map_err(err)
}

#[cfg(test)]
mod tests {
    use nalgebra::Isometry3;

    use super::*;

    #[test]
    fn format_by_extension() {
        assert_eq!(Format::of(Path::new("a/b.PNG")).unwrap(), Format::Png);
        assert_eq!(Format::of(Path::new("b.svg")).unwrap(), Format::Svg);
        assert!(Format::of(Path::new("b.pdf")).is_err());
        assert!(Format::of(Path::new("png")).is_err());
    }

    #[test]
    fn top_view_uses_the_two_widest_axes() {
        let t: Trajectory = (0..10).map(|i| (i as f64, Isometry3::translation(i as f64, 0.01 * i as f64, -2.0 * i as f64))).collect();
        assert_eq!(top_view_axes(&t), (0, 2));
        let (a, b) = equal_spans(0.0..1.0, 5.0..9.0);
        assert_eq!((a, b), (-1.5..2.5, 5.0..9.0));
    }
}
