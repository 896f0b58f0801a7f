//! How the shipped vocabulary is trained: every 5th frame of the public clip
//! `rgbd_dataset_freiburg1_rpy` (30 frames), the tracker's ORB extractor with its
//! default configuration, the default [`TrainConfig`] (10 × 4, fixed seed).
//! Feature `training` (it reads the clip); `make vocabulary` runs it.

use crate::{PlacesError, TrainConfig, Vocabulary};
use stillmap_tracking::TrackerConfig;
use stillmap_tracking::features::Extractor;
use stillmap_tracking::tracker::to_gray;

use stillmap_tracking::testing as tum;

/// Trains the vocabulary `places/vocabulary/fr1_rpy.smvoc` holds.
pub fn train_shipped() -> Result<Vocabulary, PlacesError> {
    let camera = tum::fr1_camera();
    let frames = tum::load(&tum::fr1_rpy_dir(), 150);
    let mut extractor = Extractor::new(&TrackerConfig::default()).map_err(|e| PlacesError::Training(e.to_string()))?;
    let mut images = Vec::new();
    for f in frames.iter().step_by(5) {
        let features = extractor.extract(&camera, &to_gray(&f.rgb), &f.depth, None).map_err(|e| PlacesError::Training(e.to_string()))?;
        images.push(features.descriptors);
    }
    Vocabulary::train(&images, &TrainConfig::default())
}
