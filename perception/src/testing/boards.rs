//! Issue 19's board scene, built from the public clips: photo-printed boards
//! (0.7 × 0.5 m, the shipped photos) carried through the view, set down and carried
//! on, one of them standing in the first frame, together covering a quarter of the
//! image on average and up to 60 %; and the crowd ([`crowd`]), boards, a box and
//! people covering a third of it. Shared by the board benchmarks and their
//! per-frame trace (`perception/tests/boards.rs`).

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};

use crate::Segmenter;
use crate::composite::{StopAndGo, TexturedPlane, paste};
use crate::testing::composite_run::{CompositeFrame, Stage};
use stillmap_tracking::testing as tum;

/// The floor of the TUM freiburg1 room (the motion-capture frame's z = 0; the
/// clips' lowest depth points lie at −3 to 0 cm) and its desk top (the clips'
/// points cluster at 0.75–0.80 m).
pub const FLOOR_Z_M: f64 = 0.0;
pub const DESK_Z_M: f64 = 0.76;

struct Board {
    plane: TexturedPlane,
    motion: StopAndGo,
}

/// A shipped photo printed on a `w × h` m board.
fn photo(name: &str, w: f64, h: f64) -> TexturedPlane {
    let (rgb, pw, ph) = super::photo(name);
    TexturedPlane::from_image(rgb, pw as usize, ph as usize, w, h)
}

fn boards(poses: &[Isometry3<f64>]) -> Vec<Board> {
    let s = Stage::new(poses);
    // Held a little below the camera (it looks down at the desk).
    let z = s.origin.z - 0.45;
    vec![
        // Standing 0.7 m ahead in the first frame; carried off to the right after 1.5 s.
        Board {
            plane: photo("bus.jpg", 0.7, 0.5),
            motion: StopAndGo {
                waypoints: vec![(0.0, s.at(0.7, 0.1, z)), (1.5, s.at(0.7, 0.1, z)), (3.0, s.at(0.7, 1.3, z))],
                rotation: s.facing,
            },
        },
        // Carried in from the left, set down for 1.5 s, carried on to the right.
        Board {
            plane: photo("astronaut.png", 0.7, 0.5),
            motion: StopAndGo {
                waypoints: vec![
                    (0.0, s.at(0.8, -1.2, z)),
                    (1.5, s.at(0.8, -0.25, z)),
                    (3.0, s.at(0.8, -0.25, z)),
                    (4.5, s.at(0.8, 0.5, z)),
                ],
                rotation: s.facing,
            },
        },
        // A smaller board carried across at a walking pace, nearer.
        Board {
            plane: photo("bus.jpg", 0.5, 0.35),
            motion: StopAndGo { waypoints: vec![(0.0, s.at(0.6, 0.9, z - 0.1)), (5.0, s.at(0.6, -0.9, z - 0.1))], rotation: s.facing },
        },
    ]
}

/// Where the boards are: as built, further along their paths, mirrored, or both.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Arrangement {
    AsBuilt,
    Later(f64),
    Mirrored,
    MirroredLater(f64),
}

impl Arrangement {
    /// The three the benchmark runs (tracking on one arrangement swings with small
    /// changes). Every default kept for issue 19 was chosen by its score on these.
    pub const ALL: [Arrangement; 3] = [Arrangement::AsBuilt, Arrangement::Later(0.7), Arrangement::Mirrored];
    /// Three arrangements no default was chosen on (added 2026-12-06), to check
    /// that a change which helps on [`ALL`](Self::ALL) is not fitted to them.
    pub const FRESH: [Arrangement; 3] = [Arrangement::Later(0.35), Arrangement::Later(1.4), Arrangement::MirroredLater(0.7)];

    pub fn label(self) -> String {
        match self {
            Self::AsBuilt => "as built".into(),
            Self::Later(dt) => format!("{dt} s later"),
            Self::Mirrored => "mirrored".into(),
            Self::MirroredLater(dt) => format!("mirrored, {dt} s later"),
        }
    }
}

/// The composite frames of one arrangement and, per frame, the pixels of boards
/// moving then. `poses` are the ground-truth poses at each frame's exposure time:
/// each board is drawn from where the camera was when the image was exposed (the
/// time its pose is scored at), so that a standing board stands still in the room.
pub fn scene(frames: &[tum::TumFrame], poses: &[Isometry3<f64>], arrangement: Arrangement) -> (Vec<CompositeFrame>, Vec<Vec<u8>>) {
    compose(frames, poses, arrangement, boards(poses), Vec::new())
}

/// The people of `bus.jpg` (its four), largest first, cut out along the segmenter's
/// own masks as `height_m` billboards.
pub fn people(segmenter: &mut dyn Segmenter, height_m: f64) -> Vec<TexturedPlane> {
    let (rgb, w, h) = super::photo("bus.jpg");
    let out = segmenter.segment(&rgb, w, h).expect("segment bus.jpg");
    let mut persons: Vec<_> = out.instances.iter().filter(|i| i.class_name == "person").collect();
    persons.sort_by_key(|i| std::cmp::Reverse(i.pixels));
    persons.iter().map(|i| TexturedPlane::cutout(&rgb, w, h, &out, i.id, height_m).expect("cut-out")).collect()
}

/// The crowd: issue 19's second held-out version built like the board scene. The
/// three boards of [`scene`], a fourth board (`astronaut.png`, 0.7 × 0.5 m)
/// standing 0.75 m ahead of the first frame's camera and carried off after 1 s
/// (to its left; mirrored, to its right), a photo-covered box (0.4 × 0.3 m,
/// `bus.jpg`) pushed along the desk, resting 1 s, and the four people of
/// `people` (at least four) standing on the floor, walking, standing 1 s and
/// walking on: behind the desk, beside it coming within 1.2 m, and, starting
/// 0.8 and 1 s later, across the room and from the side to within 1 m. Together
/// they cover about a third of the image on average.
pub fn crowd(
    frames: &[tum::TumFrame],
    poses: &[Isometry3<f64>],
    arrangement: Arrangement,
    people: &[TexturedPlane],
) -> (Vec<CompositeFrame>, Vec<Vec<u8>>) {
    assert!(people.len() >= 4, "the crowd has four people, got {} cut-outs", people.len());
    let s = Stage::new(poses);
    let mut objects = boards(poses);
    // The board in front of the first frame's camera, upright and facing it: placed
    // for the arrangement (the stage's mirror would move it out of that view).
    let mut placed = Vec::new();
    if let Some(first) = poses.first() {
        let view = first.rotation * Vector3::z();
        let ahead = Vector3::new(view.x, view.y, 0.0).normalize();
        let side = Vector3::z().cross(&ahead);
        let at = first.translation.vector + view * 0.75;
        let facing = UnitQuaternion::face_towards(&-ahead, &Vector3::z());
        let away = if let Arrangement::Mirrored | Arrangement::MirroredLater(_) = arrangement { 1.2 } else { -1.2 };
        let p = |d: f64| Point3::from(at + side * d);
        placed.push(Board {
            plane: photo("astronaut.png", 0.7, 0.5),
            motion: StopAndGo { waypoints: vec![(0.0, p(0.0)), (1.0, p(0.0)), (2.5, p(away))], rotation: facing },
        });
    }
    // Waypoints (seconds; metres ahead and to the side, on the stage) at one height, facing the camera.
    let along = |z: f64, path: &[(f64, f64, f64)]| StopAndGo {
        waypoints: path.iter().map(|&(t, ahead, side)| (t, s.at(ahead, side, z))).collect(),
        rotation: s.facing,
    };
    // The box, pushed along the desk, resting 1 s, pushed on.
    objects.push(Board {
        plane: photo("bus.jpg", 0.4, 0.3),
        motion: along(DESK_Z_M + 0.15, &[(0.0, 0.75, -0.4), (1.2, 0.75, 0.05), (2.2, 0.75, 0.05), (4.0, 0.75, 0.9)]),
    });
    let walks: [&[(f64, f64, f64)]; 4] = [
        // Behind the desk, 2.1 m ahead, across.
        &[(0.0, 2.1, 0.8), (1.5, 2.1, 0.0), (2.5, 2.1, 0.0), (4.0, 2.1, -0.8)],
        // Beside the desk, coming from 2.0 m to 1.2 m and back.
        &[(0.0, 2.0, -0.55), (1.3, 1.2, -0.55), (2.3, 1.2, -0.55), (3.8, 2.0, -0.55)],
        // Across the room at 1.6 m, the other way, later.
        &[(0.8, 1.6, -1.2), (2.3, 1.6, -0.3), (3.3, 1.6, -0.3), (5.0, 1.6, 1.0)],
        // From the side to within 1 m, standing, and away.
        &[(1.0, 1.0, 1.4), (2.5, 1.0, 0.5), (3.5, 1.0, 0.5), (5.0, 1.4, -0.6)],
    ];
    for (plane, walk) in people.iter().zip(walks) {
        // Standing on the floor.
        objects.push(Board { plane: plane.clone(), motion: along(FLOOR_Z_M + plane.height_m / 2.0, walk) });
    }
    compose(frames, poses, arrangement, objects, placed)
}

/// The composite frames of `boards` (mirrored about the stage for the mirrored
/// arrangements) and `placed` (already placed for the arrangement).
fn compose(
    frames: &[tum::TumFrame],
    poses: &[Isometry3<f64>],
    arrangement: Arrangement,
    mut boards: Vec<Board>,
    placed: Vec<Board>,
) -> (Vec<CompositeFrame>, Vec<Vec<u8>>) {
    let camera = tum::fr1_camera();
    if let Arrangement::Mirrored | Arrangement::MirroredLater(_) = arrangement {
        let s = Stage::new(poses);
        for b in &mut boards {
            for (_, p) in &mut b.motion.waypoints {
                let side = s.side.dot(&(*p - s.origin));
                *p -= 2.0 * side * s.side;
            }
        }
    }
    boards.extend(placed);
    let later = match arrangement {
        Arrangement::Later(dt) | Arrangement::MirroredLater(dt) => dt,
        Arrangement::AsBuilt | Arrangement::Mirrored => 0.0,
    };
    let t0 = frames.first().map_or(0, |f| f.timestamp_ns);
    let mut moving_masks = Vec::with_capacity(frames.len());
    let composite = frames
        .iter()
        .zip(poses)
        .map(|(f, world_from_camera)| {
            let t = (f.timestamp_ns - t0) as f64 * 1e-9 + later;
            let (mut rgb, mut depth) = (f.rgb.clone(), f.depth.clone());
            let mut object_mask = vec![0u8; depth.len()];
            let mut moving_mask = vec![0u8; depth.len()];
            // Farthest first.
            let mut order: Vec<&Board> = boards.iter().collect();
            let distance = |b: &Board| (b.motion.world_from_plane(t).translation.vector - world_from_camera.translation.vector).norm();
            order.sort_by(|a, b| distance(b).total_cmp(&distance(a)));
            for b in order {
                let m = paste(&camera, &b.plane, &(world_from_camera.inverse() * b.motion.world_from_plane(t)), &mut rgb, &mut depth);
                let moving = !b.motion.standing(t);
                for ((o, v), m) in object_mask.iter_mut().zip(moving_mask.iter_mut()).zip(m) {
                    *o |= m;
                    *v |= m & u8::from(moving);
                }
            }
            moving_masks.push(moving_mask);
            CompositeFrame { timestamp_ns: f.timestamp_ns, rgb, depth, object_mask }
        })
        .collect();
    (composite, moving_masks)
}
