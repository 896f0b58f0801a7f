//! Geometric verification of a place candidate: is the query keyframe really
//! looking at the candidate's scene, and from where?
//!
//! Descriptors are matched (nearest neighbour, ratio test, one query feature per
//! candidate point), the candidate's points with depth are registered to the
//! query's pixels by PnP-RANSAC (OpenCV's EPnP), and the pose is refined by the
//! tracker's robust optimisation with the query's depth as a third row. A
//! candidate passes only with enough inliers, and enough of the matches among
//! them: a look-alike place gives a few matches that no single pose explains.

use nalgebra::{Isometry3, Point2, Point3};
use stillmap_tracking::Camera;
use stillmap_tracking::features::{Descriptor, FrameFeatures, hamming};
use stillmap_tracking::geometry::{Measurement, PnpRansac, pnp_ransac};
use stillmap_tracking::optimize::optimize_pose;

use crate::PlacesError;

/// A keyframe as place recognition sees it, in its own camera frame.
#[derive(Debug, Clone, Default)]
pub struct Place {
    /// Ideal (undistorted) pixel of each feature.
    pub pixels: Vec<Point2<f64>>,
    /// Pyramid level of each feature (sets its pixel noise).
    pub octaves: Vec<u8>,
    /// The feature's 3D point in the camera frame, when it had depth.
    pub points: Vec<Option<Point3<f64>>>,
    pub descriptors: Vec<Descriptor>,
}

impl Place {
    /// A place from a keyframe's features.
    pub fn from_features(camera: &Camera, features: &FrameFeatures) -> Self {
        Self {
            pixels: features.features.iter().map(|f| f.ideal).collect(),
            octaves: features.features.iter().map(|f| f.octave).collect(),
            points: features.features.iter().map(|f| f.point_in_camera(camera)).collect(),
            descriptors: features.descriptors.clone(),
        }
    }

    pub fn len(&self) -> usize {
        self.descriptors.len()
    }

    pub fn is_empty(&self) -> bool {
        self.descriptors.is_empty()
    }
}

/// Verification thresholds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerifyConfig {
    /// Largest Hamming distance of a descriptor match (of 256 bits; ORB-SLAM's TH_HIGH is 100, its loop search 50).
    pub max_descriptor_distance: u32,
    /// A match's distance must be below this share of the second best's (Lowe's ratio).
    pub ratio: f32,
    /// Matches needed before PnP is tried.
    pub min_matches: usize,
    /// PnP-RANSAC reprojection threshold (pixels), iterations and confidence.
    pub pnp_threshold_px: f32,
    pub pnp_iterations: i32,
    pub pnp_confidence: f64,
    /// Inliers after the pose optimisation needed to accept.
    pub min_inliers: usize,
    /// … and the share of the matches they must be.
    pub min_inlier_ratio: f64,
    /// Depth baseline (metres) of the disparity row, as the tracker's `depth_baseline_m`.
    pub depth_baseline_m: f64,
    /// Pixel noise grows by this factor per pyramid level (the ORB scale factor).
    pub scale_factor: f64,
}

impl Default for VerifyConfig {
    fn default() -> Self {
        Self {
            max_descriptor_distance: 60,
            ratio: 0.8,
            min_matches: 40,
            pnp_threshold_px: 4.0,
            pnp_iterations: 200,
            pnp_confidence: 0.999,
            min_inliers: 60,
            min_inlier_ratio: 0.4,
            depth_baseline_m: 0.08,
            scale_factor: 1.2,
        }
    }
}

impl VerifyConfig {
    pub fn validate(&self) -> Result<(), PlacesError> {
        if !(self.ratio > 0.0 && self.ratio <= 1.0 && (0.0..=1.0).contains(&self.min_inlier_ratio)) {
            return Err(PlacesError::Config("verify: ratio must be in (0, 1] and min_inlier_ratio in [0, 1]".into()));
        }
        if self.min_matches < 6
            || self.min_inliers < 6
            || self.pnp_threshold_px.is_nan()
            || self.pnp_threshold_px <= 0.0
            || self.pnp_iterations < 1
        {
            return Err(PlacesError::Config(
                "verify: min_matches and min_inliers must be at least 6, the PnP threshold and iterations positive".into(),
            ));
        }
        if !(self.depth_baseline_m > 0.0 && self.scale_factor >= 1.0) {
            return Err(PlacesError::Config("verify: depth_baseline_m must be positive and scale_factor at least 1".into()));
        }
        Ok(())
    }
}

/// A verified candidate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Verified {
    /// The candidate keyframe's camera in the query keyframe's camera frame.
    pub query_from_candidate: Isometry3<f64>,
    pub matches: usize,
    pub inliers: usize,
}

/// Verifies that `query` sees `candidate`'s scene; `None` when it does not. The
/// query needs every field per feature; a candidate only its points and
/// descriptors (a stored place may drop its pixels). Places whose lists do not
/// line up verify nothing.
pub fn verify(camera: &Camera, query: &Place, candidate: &Place, config: &VerifyConfig) -> Option<Verified> {
    let n = query.len();
    if query.pixels.len() != n || query.octaves.len() != n || query.points.len() != n || candidate.points.len() != candidate.len() {
        return None;
    }
    let pairs = match_descriptors(query, candidate, config);
    if pairs.len() < config.min_matches {
        return None;
    }
    let registration: Vec<(Point3<f64>, Point2<f64>)> =
        pairs.iter().filter_map(|&(q, c)| Some((candidate.points[c]?, query.pixels[q]))).collect();
    let params = PnpRansac { iterations: config.pnp_iterations, threshold_px: config.pnp_threshold_px, confidence: config.pnp_confidence };
    let (initial, ransac_inliers) = pnp_ransac(camera, &registration, params)?;
    if ransac_inliers.len() < config.min_inliers {
        return None;
    }
    let bf = camera.fx * config.depth_baseline_m;
    let correspondences: Vec<(Point3<f64>, Measurement)> = pairs
        .iter()
        .filter_map(|&(q, c)| {
            let s = config.scale_factor.powi(i32::from(query.octaves[q]));
            let disparity = query.points[q].map(|p| bf / p.z);
            Some((candidate.points[c]?, Measurement { ideal: query.pixels[q], disparity, information: 1.0 / (s * s) }))
        })
        .collect();
    let estimate = optimize_pose(camera, bf, initial, &correspondences);
    let inliers = estimate.inlier_count;
    (inliers >= config.min_inliers && inliers as f64 >= config.min_inlier_ratio * pairs.len() as f64).then_some(Verified {
        query_from_candidate: estimate.camera_from_world,
        matches: pairs.len(),
        inliers,
    })
}

/// (query feature, candidate feature) pairs: the candidate features with a 3D
/// point, each matched to its nearest query descriptor if it passes the distance
/// and ratio tests and no nearer candidate took that query feature.
fn match_descriptors(query: &Place, candidate: &Place, config: &VerifyConfig) -> Vec<(usize, usize)> {
    let mut best_for_query: Vec<Option<(u32, usize)>> = vec![None; query.len()];
    for (c, cd) in candidate.descriptors.iter().enumerate() {
        if candidate.points[c].is_none() {
            continue;
        }
        let (mut best, mut second) = ((u32::MAX, usize::MAX), u32::MAX);
        for (q, qd) in query.descriptors.iter().enumerate() {
            let d = hamming(cd, qd);
            if d < best.0 {
                (second, best) = (best.0, (d, q));
            } else if d < second {
                second = d;
            }
        }
        let (d, q) = best;
        if d > config.max_descriptor_distance || (second != u32::MAX && d as f32 >= config.ratio * second as f32) {
            continue;
        }
        if best_for_query[q].is_none_or(|(bd, _)| d < bd) {
            best_for_query[q] = Some((d, c));
        }
    }
    best_for_query.iter().enumerate().filter_map(|(q, b)| b.map(|(_, c)| (q, c))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use stillmap_tracking::TrackerConfig;
    use stillmap_tracking::features::Extractor;
    use stillmap_tracking::synthetic::{Scene, kinect_camera, render, sway_pose};
    use stillmap_tracking::tracker::to_gray;

    fn place(scene: &Scene, pose: &Isometry3<f64>) -> Place {
        let camera = kinect_camera();
        let frame = render(scene, &camera, pose);
        let mut extractor = Extractor::new(&TrackerConfig::default()).expect("extractor");
        let feats = extractor.extract(&camera, &to_gray(&frame.rgb), &frame.depth, None).expect("extract");
        Place::from_features(&camera, &feats)
    }

    /// Two renders of the synthetic room from different poses: the relative pose
    /// comes back; a different room (other textures) is rejected.
    #[test]
    fn recovers_the_relative_pose_and_rejects_another_room() {
        let camera = kinect_camera();
        let scene = Scene::room(7);
        let (a, b) = (sway_pose(0.0), sway_pose(40.0));
        let (pa, pb) = (place(&scene, &a), place(&scene, &b));
        let config = VerifyConfig::default();
        let v = verify(&camera, &pb, &pa, &config).expect("same room, verified");
        let truth = b.inverse() * a;
        let error = truth.inverse() * v.query_from_candidate;
        assert!(
            error.translation.vector.norm() < 0.01 && error.rotation.angle() < 0.5f64.to_radians(),
            "{error:?} ({} inliers)",
            v.inliers
        );
        assert!(verify(&camera, &pb, &place(&Scene::room(8), &a), &config).is_none(), "another room's textures must not verify");
        assert!(verify(&camera, &pb, &Place::default(), &config).is_none());
        let pixels_dropped = Place { pixels: Vec::new(), octaves: Vec::new(), ..pa.clone() };
        assert!(verify(&camera, &pb, &pixels_dropped, &config).is_some(), "a candidate needs only points and descriptors");
        assert!(verify(&camera, &pixels_dropped, &pb, &config).is_none(), "a query without pixels verifies nothing");
    }
}
