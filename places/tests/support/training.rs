//! How the shipped vocabulary is trained: every 5th frame of the public clip
//! `rgbd_dataset_freiburg1_rpy` (30 frames), the tracker's ORB extractor with its
//! default configuration, the default [`TrainConfig`] (10 × 4, fixed seed).

use stillmap_places::{PlacesError, TrainConfig, Vocabulary};
use stillmap_tracking::TrackerConfig;
use stillmap_tracking::features::Extractor;
use stillmap_tracking::tracker::to_gray;

use crate::tum;

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
