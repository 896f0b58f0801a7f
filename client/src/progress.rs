//! The progress bar while streaming (drawn on stderr only when it is a terminal).

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

pub fn bar(enabled: bool, len: Option<usize>) -> ProgressBar {
    let bar = match len {
        Some(n) => ProgressBar::new(n as u64),
        None => ProgressBar::no_length(),
    };
    if !enabled {
        bar.set_draw_target(ProgressDrawTarget::hidden());
        return bar;
    }
    let template = if len.is_some() {
        "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} frames answered ({per_sec}, eta {eta})"
    } else {
        "{spinner} [{elapsed_precise}] {pos} frames answered ({per_sec})"
    };
    if let Ok(style) = ProgressStyle::with_template(template) {
        bar.set_style(style);
    }
    bar
}
