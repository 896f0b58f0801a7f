//! Runs perception and tracking over the real fr1_rpy clip with a moving textured
//! plane pasted in (`stillmap_perception::composite`), and scores the dynamic mask
//! against the plane's exact mask. Shared by the tests, benches and examples of
//! perception and mapping.

use crate::composite::{CircularMotion, TexturedPlane, interpolate_pose, paste};
use crate::{DynamicMasker, MaskOutput, MaskSource, MaskerInput, PerceptionConfig, PixelLabel, Segmentation, Segmenter};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use stillmap_tracking::features::Extractor;
use stillmap_tracking::tracker::to_gray;
use stillmap_tracking::{FrameInput, TrackOutput, Tracker, TrackerConfig, TrackingState};

use stillmap_tracking::testing as tum;

/// A frame with the object pasted in, and the object's exact mask.
pub struct CompositeFrame {
    pub timestamp_ns: u64,
    pub rgb: Vec<u8>,
    pub depth: Vec<u16>,
    pub object_mask: Vec<u8>,
}

/// The moving object: a 24 × 20 cm textured board 0.8 m in front of the clip's
/// mean camera position (nearer than the desk and monitors behind it), along its
/// mean viewing direction (so it stays in view while the camera rolls, pitches
/// and yaws), circling in world coordinates (radius 12 cm, one turn per 1.5 s:
/// 0.5 m/s, a walking pace or a pushed chair).
pub fn object_motion(world_from_cameras: &[Isometry3<f64>]) -> CircularMotion {
    let n = world_from_cameras.len() as f64;
    let mean_position = world_from_cameras.iter().map(|p| p.translation.vector).sum::<Vector3<f64>>() / n;
    let axis = world_from_cameras.iter().map(|p| p.rotation * Vector3::z()).sum::<Vector3<f64>>().normalize();
    let up = world_from_cameras[0].rotation * -Vector3::y();
    // The board's +z faces the camera.
    let rotation = UnitQuaternion::face_towards(&-axis, &up);
    let centre = mean_position + axis * 0.8;
    CircularMotion { world_from_centre: Isometry3::from_parts(Translation3::from(centre), rotation), radius_m: 0.12, period_s: 1.5 }
}

/// The textured board (multi-scale noise: no COCO class, only flow can find it).
pub fn board() -> TexturedPlane {
    TexturedPlane::noise(3, 256, 256, 0.24, 0.20)
}

/// The ground-truth camera pose at each frame's exposure time, the time its pose is
/// scored at (at the image's timestamp, 12.5 ms later, a drawn object would shake
/// against the room).
pub fn exposure_poses(frames: &[tum::TumFrame], gt: &[(u64, Isometry3<f64>)]) -> Vec<Isometry3<f64>> {
    frames.iter().map(|f| interpolate_pose(gt, tum::fr1_pose_time_ns(f.timestamp_ns)).expect("ground truth")).collect()
}

/// The real clip with the board pasted consistently with the ground-truth poses.
pub fn composite(frames: &[tum::TumFrame], gt: &[(u64, Isometry3<f64>)]) -> Vec<CompositeFrame> {
    composite_with(frames, gt, &board())
}

/// The real clip with `plane` moving as [`object_motion`] says.
pub fn composite_with(frames: &[tum::TumFrame], gt: &[(u64, Isometry3<f64>)], plane: &TexturedPlane) -> Vec<CompositeFrame> {
    let camera = tum::fr1_camera();
    let t0 = frames[0].timestamp_ns;
    let poses = exposure_poses(frames, gt);
    let motion = object_motion(&poses);
    frames
        .iter()
        .zip(&poses)
        .map(|(f, world_from_camera)| {
            let t = (f.timestamp_ns - t0) as f64 * 1e-9;
            let camera_from_plane = world_from_camera.inverse() * motion.world_from_plane(t);
            let (mut rgb, mut depth) = (f.rgb.clone(), f.depth.clone());
            let object_mask = paste(&camera, plane, &camera_from_plane, &mut rgb, &mut depth);
            CompositeFrame { timestamp_ns: f.timestamp_ns, rgb, depth, object_mask }
        })
        .collect()
}

/// The real clip as composite frames with nothing pasted in (an empty object mask).
pub fn without_object(frames: &[tum::TumFrame]) -> Vec<CompositeFrame> {
    frames
        .iter()
        .map(|f| CompositeFrame {
            timestamp_ns: f.timestamp_ns,
            rgb: f.rgb.clone(),
            depth: f.depth.clone(),
            object_mask: vec![0; f.depth.len()],
        })
        .collect()
}

/// Positions in the scene as (metres ahead of the clip's mean camera position along
/// its mean horizontal viewing direction, metres to the side, height of the centre).
pub struct Stage {
    pub origin: Point3<f64>,
    pub ahead: Vector3<f64>,
    pub side: Vector3<f64>,
    /// world_from_plane's rotation of an object facing the camera, upright.
    pub facing: UnitQuaternion<f64>,
}

impl Stage {
    pub fn new(poses: &[Isometry3<f64>]) -> Self {
        let n = poses.len() as f64;
        let origin = Point3::from(poses.iter().map(|p| p.translation.vector).sum::<Vector3<f64>>() / n);
        let view = poses.iter().map(|p| p.rotation * Vector3::z()).sum::<Vector3<f64>>();
        let ahead = Vector3::new(view.x, view.y, 0.0).normalize();
        let side = Vector3::z().cross(&ahead);
        Self { origin, ahead, side, facing: UnitQuaternion::face_towards(&-ahead, &Vector3::z()) }
    }

    pub fn at(&self, ahead_m: f64, side_m: f64, z_m: f64) -> Point3<f64> {
        let p = self.origin + self.ahead * ahead_m + self.side * side_m;
        Point3::new(p.x, p.y, z_m)
    }
}

/// When segmentation results become available to the masker.
#[derive(Debug, Clone, Copy)]
pub enum Schedule {
    /// Every frame is segmented before it is masked.
    EveryFrame,
    /// Frame k is segmented when k % every == 0 and its result arrives `delay` frames later.
    Late { every: usize, delay: usize },
}

/// Minimum visible object pixels for a frame to be scored.
pub const MIN_OBJECT_PX: usize = 1500;

#[derive(Debug, Default, Clone)]
pub struct Scores {
    pub scored_frames: usize,
    pub mean_iou: f64,
    pub min_iou: f64,
    /// Dynamic pixels on the static background, over all background pixels of the scored frames.
    pub false_dynamic: f64,
    /// ORB features (tracker's extractor, no mask) on the object, and the share the mask removes.
    pub object_features: usize,
    pub eliminated_fraction: f64,
    pub warped_frames: usize,
    /// Frame 1, the first with flow (no earlier labels to carry): the object's
    /// features, and those the tracking mask removed.
    pub first_flow_frame_features: (usize, usize),
    /// Scored frames with a person instance overlapping the object, and those where it was judged moving.
    pub person_frames: usize,
    pub moving_person_frames: usize,
    pub trajectory: Vec<(u64, Isometry3<f64>)>,
    /// Frames posed by dense odometry alone (`TrackingState::Coasting`).
    pub coasting: usize,
}

/// The server's per-frame order: the mask for tracking, tracking with it, then the
/// fused mask with the tracked motion. Shared by these runs and the map's tests.
pub struct MaskedTracking {
    pub masker: DynamicMasker,
    pub tracker: Tracker,
    last_pose: Option<Isometry3<f64>>,
    /// The masker's own camera motion for the last frame, before tracking ([`DynamicMasker::prepared_motion`]).
    pub prepared_motion: Option<Isometry3<f64>>,
}

impl MaskedTracking {
    pub fn new(class_names: &[String]) -> Self {
        Self::with_configs(class_names, PerceptionConfig::default(), TrackerConfig::default())
    }

    pub fn with_configs(class_names: &[String], perception: PerceptionConfig, tracking: TrackerConfig) -> Self {
        let camera = tum::fr1_camera();
        Self {
            masker: DynamicMasker::new(camera.clone(), perception, class_names).expect("masker"),
            tracker: Tracker::new(camera, tracking).expect("tracker"),
            last_pose: None,
            prepared_motion: None,
        }
    }

    /// One frame: (the tracking mask, tracking's output, the fused mask).
    pub fn step(
        &mut self,
        sequence: u64,
        timestamp_ns: u64,
        rgb: &[u8],
        depth: &[u16],
        segmentation: Option<(u64, Segmentation)>,
        accel_in_camera: Option<nalgebra::Vector3<f64>>,
    ) -> (Vec<u8>, TrackOutput, MaskOutput) {
        let tracking_mask = self
            .masker
            .prepare(MaskerInput { sequence, capture_time_ns: timestamp_ns, rgb, depth, segmentation, motion_prior: None, accel_in_camera })
            .expect("prepare");
        self.prepared_motion = self.masker.prepared_motion();
        let track = self.tracker.track(&FrameInput { timestamp_ns, rgb, depth, dynamic_mask: Some(&tracking_mask) }).expect("track");
        let motion = match (self.last_pose, track.world_from_camera) {
            (Some(prev), Some(cur)) => Some(prev.inverse() * cur),
            _ => None,
        };
        self.last_pose = track.world_from_camera;
        let out = self.masker.finish(depth, motion).expect("finish");
        (tracking_mask, track, out)
    }
}

/// Runs the masker (with `segmenter` on `schedule`) and the tracker with its mask.
pub fn run(frames: &[CompositeFrame], segmenter: Option<&mut dyn Segmenter>, schedule: Schedule, verbose: bool) -> Scores {
    run_with(frames, segmenter, schedule, verbose, PerceptionConfig::default(), TrackerConfig::default())
}

/// [`run`] with the given perception and tracking configurations.
pub fn run_with(
    frames: &[CompositeFrame],
    segmenter: Option<&mut dyn Segmenter>,
    schedule: Schedule,
    verbose: bool,
    perception: PerceptionConfig,
    tracking: TrackerConfig,
) -> Scores {
    let camera = tum::fr1_camera();
    let (w, h) = (camera.width as usize, camera.height as usize);
    let names: Vec<String> = segmenter.as_ref().map(|s| s.class_names().to_vec()).unwrap_or_default();
    let mut pipeline = MaskedTracking::with_configs(&names, perception, tracking);
    let mut extractor = Extractor::new(&TrackerConfig::default()).expect("extractor");
    let mut segmenter = segmenter;
    let mut pending: Vec<(usize, u64, Segmentation)> = Vec::new();
    let mut s = Scores { min_iou: 1.0, ..Scores::default() };
    let (mut iou_sum, mut bg_dynamic, mut bg_total, mut eliminated) = (0.0, 0usize, 0usize, 0usize);
    for (k, f) in frames.iter().enumerate() {
        let sequence = k as u64;
        let mut arrived = None;
        if let Some(seg) = segmenter.as_deref_mut() {
            match schedule {
                Schedule::EveryFrame => arrived = Some((sequence, seg.segment(&f.rgb, 640, 480).expect("segment"))),
                Schedule::Late { every, delay } => {
                    if k % every == 0 {
                        pending.push((k + delay, sequence, seg.segment(&f.rgb, 640, 480).expect("segment")));
                    }
                    if let Some(i) = pending.iter().position(|(due, _, _)| *due == k) {
                        let (_, seq, seg) = pending.remove(i);
                        arrived = Some((seq, seg));
                    }
                }
            }
        }
        let (tracking_mask, track, out) = pipeline.step(sequence, f.timestamp_ns, &f.rgb, &f.depth, arrived, None);
        if let Some(p) = track.world_from_camera {
            s.trajectory.push((tum::fr1_pose_time_ns(f.timestamp_ns), p));
        }
        s.coasting += usize::from(track.state == TrackingState::Coasting);
        if verbose {
            eprintln!(
                "track {k:3}: {:?} tracked {} masked {} keyframe {}; dynamic px {} (object {}), regions {} rejected {}, ego {:?}",
                track.state,
                track.tracked_points,
                track.masked_features,
                track.keyframe,
                out.fused.count(PixelLabel::Dynamic),
                f.object_mask.iter().filter(|&&m| m != 0).count(),
                out.fused.flow_regions,
                out.fused.rejected_regions,
                out.ego.map(|e| (
                    e.refined,
                    e.inliers,
                    e.samples,
                    e.previous_from_current.translation.vector.norm(),
                    e.previous_from_current.rotation.angle().to_degrees()
                ))
            );
        }
        if matches!(out.source, MaskSource::Warped { .. }) {
            s.warped_frames += 1;
        }
        let object_px = f.object_mask.iter().filter(|&&m| m != 0).count();
        if k == 0 || object_px < MIN_OBJECT_PX {
            continue;
        }
        let (mut inter, mut union, mut fd) = (0usize, 0usize, 0usize);
        for i in 0..w * h {
            let dynamic = out.fused.labels[i] == PixelLabel::Dynamic as u8;
            let object = f.object_mask[i] != 0;
            inter += usize::from(dynamic && object);
            union += usize::from(dynamic || object);
            fd += usize::from(dynamic && !object);
        }
        let iou = inter as f64 / union.max(1) as f64;
        if let Some(seg) = pipeline.masker.segmentation() {
            let on_object = |id: u16| (0..w * h).filter(|&i| seg.instance_map[i] == id && f.object_mask[i] != 0).count();
            if let Some(person) = out.fused.instances.iter().find(|i| i.class_name == "person" && on_object(i.id) * 2 > i.pixels as usize) {
                s.person_frames += 1;
                s.moving_person_frames += usize::from(person.moving == Some(true));
                if verbose {
                    eprintln!(
                        "frame {k}: person {:?} fraction {:.2} pixels {} on board {}",
                        person.moving,
                        person.moving_fraction,
                        person.pixels,
                        on_object(person.id)
                    );
                }
            }
        }
        let feats = extractor.extract(&camera, &to_gray(&f.rgb), &f.depth, None).expect("extract");
        let (mut on_object, eliminated_before) = (0, eliminated);
        for ft in &feats.features {
            let i = (ft.raw.y.round() as usize).min(h - 1) * w + (ft.raw.x.round() as usize).min(w - 1);
            if f.object_mask[i] != 0 {
                on_object += 1;
                eliminated += usize::from(tracking_mask[i] != 0);
            }
        }
        s.object_features += on_object;
        if k == 1 {
            s.first_flow_frame_features = (on_object, eliminated - eliminated_before);
        }
        if verbose {
            eprintln!(
                "frame {k:3}: object {object_px:6} px, IoU {iou:.3}, features {on_object} eliminated {}, false-dynamic {:.4}, regions {} (rejected {}), ego {:?}, source {:?}",
                eliminated - eliminated_before,
                fd as f64 / (w * h - object_px) as f64,
                out.fused.flow_regions,
                out.fused.rejected_regions,
                out.ego.map(|e| (e.refined, e.inliers, e.samples)),
                out.source
            );
        }
        iou_sum += iou;
        s.min_iou = s.min_iou.min(iou);
        bg_dynamic += fd;
        bg_total += w * h - object_px;
        s.scored_frames += 1;
    }
    s.mean_iou = iou_sum / s.scored_frames.max(1) as f64;
    s.false_dynamic = bg_dynamic as f64 / bg_total.max(1) as f64;
    s.eliminated_fraction = eliminated as f64 / s.object_features.max(1) as f64;
    s
}

/// Tracks frames without any mask (the reference for the tracking-error comparison).
pub fn track_plain(frames: &[tum::TumFrame]) -> Vec<(u64, Isometry3<f64>)> {
    track_plain_with(frames, TrackerConfig::default())
}

/// [`track_plain`] with the given tracking configuration.
pub fn track_plain_with(frames: &[tum::TumFrame], config: TrackerConfig) -> Vec<(u64, Isometry3<f64>)> {
    track_images(frames.iter().map(|f| (f.timestamp_ns, f.rgb.as_slice(), f.depth.as_slice(), None)), config)
}

/// The tracker alone (no mask) over composite frames: stamped poses.
pub fn track_unmasked(frames: &[CompositeFrame]) -> Vec<(u64, Isometry3<f64>)> {
    track_images(frames.iter().map(|f| (f.timestamp_ns, f.rgb.as_slice(), f.depth.as_slice(), None)), TrackerConfig::default())
}

/// The tracker alone with the given per-frame masks (exact ones, for the headroom): stamped poses.
pub fn track_masked(frames: &[CompositeFrame], masks: &[Vec<u8>]) -> Vec<(u64, Isometry3<f64>)> {
    track_masked_with(frames, masks, TrackerConfig::default())
}

/// [`track_masked`] under the given tracking configuration.
pub fn track_masked_with(frames: &[CompositeFrame], masks: &[Vec<u8>], config: TrackerConfig) -> Vec<(u64, Isometry3<f64>)> {
    track_images(frames.iter().zip(masks).map(|(f, m)| (f.timestamp_ns, f.rgb.as_slice(), f.depth.as_slice(), Some(m.as_slice()))), config)
}

/// Tracks (timestamp, colour, depth, mask) frames; poses stamped at the ground truth's time base.
fn track_images<'a>(
    frames: impl Iterator<Item = (u64, &'a [u8], &'a [u16], Option<&'a [u8]>)>,
    config: TrackerConfig,
) -> Vec<(u64, Isometry3<f64>)> {
    let mut tracker = Tracker::new(tum::fr1_camera(), config).expect("tracker");
    frames
        .filter_map(|(timestamp_ns, rgb, depth, dynamic_mask)| {
            let out = tracker.track(&FrameInput { timestamp_ns, rgb, depth, dynamic_mask }).ok()?;
            out.world_from_camera.map(|p| (tum::fr1_pose_time_ns(timestamp_ns), p))
        })
        .collect()
}
