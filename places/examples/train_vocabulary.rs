//! Trains the shipped vocabulary from the public clip and writes it (a build step:
//! the same clip and seed give the same bytes, which `tests/vocabulary.rs` checks).
//!
//! `cargo run --release -p stillmap-places --example train_vocabulary [-- OUT]`
//! (`make vocabulary`; OUT defaults to places/vocabulary/fr1_rpy.smvoc).

use stillmap_places::training;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args().nth(1).unwrap_or_else(|| concat!(env!("CARGO_MANIFEST_DIR"), "/vocabulary/fr1_rpy.smvoc").to_string());
    let vocabulary = training::train_shipped()?;
    std::fs::write(&out, vocabulary.to_bytes())?;
    println!("{} words written to {out}", vocabulary.words());
    Ok(())
}
