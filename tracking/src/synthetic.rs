//! A synthetic RGB-D renderer with exact ground truth, for tracking tests and benches.
//!
//! A [`Scene`] is a set of flat, double-sided, textured quads (a box is six of them).
//! [`render`] ray-casts every pixel through a [`Camera`] at a pose `world_from_camera`
//! (camera frame x right, y down, z forward) and returns an RGB8 image (supersampled
//! and mildly blurred, so texture details do not flicker from frame to frame) and a
//! depth image whose values are the camera-frame z of the centre ray's nearest hit.
//! Pixel `(u, v)` is centred on the ideal coordinates `(u, v)` that [`Camera::project`]
//! returns (OpenCV convention); with distortion, the raw pixel is undistorted first.
//!
//! Textures are procedural "cluttered posters" defined in metric texture coordinates,
//! so a surface looks the same from every viewpoint and offers corners at several scales.
//! Everything is deterministic: the same scene, camera, pose and options give
//! bit-identical images.

use std::f64::consts::TAU;

use nalgebra::{Isometry3, Point2, Point3, Translation3, UnitQuaternion, Vector3};

use crate::Camera;

/// SplitMix64: a tiny, fast, deterministic 64-bit generator (Steele, Lea & Flood 2014).
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

/// The SplitMix64 increment (the golden ratio in 64-bit fixed point).
const GOLDEN_GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;
/// Bits of a `u64` that make an `f64` mantissa.
const MANTISSA_BITS: u32 = 53;
/// Largest grey level.
const WHITE: f64 = 255.0;

/// The SplitMix64 output function: a strong 64-bit mixer.
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl SplitMix64 {
    /// A generator started from `seed`.
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(GOLDEN_GAMMA);
        mix64(self.state)
    }

    /// A uniform value in `[0, 1)`.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> (u64::BITS - MANTISSA_BITS)) as f64 / (1u64 << MANTISSA_BITS) as f64
    }

    /// A uniform value in `[low, high)`.
    pub fn range(&mut self, low: f64, high: f64) -> f64 {
        low + (high - low) * self.next_f64()
    }
}

/// The poster's layers, coarse to fine: (log2 of cells per metre, probability that a cell
/// holds a shape). Each cell holds at most one rectangle or disc, inside the cell; finer
/// layers paint over coarser ones, so corners appear at every scale from 50 cm cells
/// down to 3 cm cells (shapes of 1–3 cm are 2–7 px at 4 m with f = 525 px).
const POSTER_LAYERS: [(u32, f64); 5] = [(1, 0.8), (2, 0.6), (3, 0.5), (4, 0.4), (5, 0.3)];
/// A shape's extent as a fraction of its cell: `[min, max)`.
const SHAPE_EXTENT: (f64, f64) = (0.3, 0.95);
/// Probability that a shape is a disc rather than an axis-aligned rectangle.
const DISC_PROBABILITY: f64 = 0.25;
/// Grey level of the poster background, before the per-surface tint.
const BACKGROUND_GREY: f64 = 128.0;
/// Largest per-channel shift of a surface's background from grey.
const BACKGROUND_TINT: f64 = 20.0;
/// Grey-level range of dark shapes.
const DARK_LEVELS: (f64, f64) = (10.0, 80.0);
/// Grey-level range of bright shapes.
const BRIGHT_LEVELS: (f64, f64) = (175.0, 245.0);
/// Largest per-channel colour shift of a shape around its grey level.
const SHAPE_TINT: f64 = 45.0;

/// Texture coordinates are evaluated in fixed point with this many fractional bits per
/// metre (about 1 µm), so cells are found with shifts and masks.
const FIXED_BITS: u32 = 20;
/// Bits of a position within a cell, and of the random fields that place shapes.
const FRACTION_BITS: u32 = 12;
/// One cell in [`FRACTION_BITS`] fixed point.
const CELL_ONE: i64 = 1 << FRACTION_BITS;
/// Bits of a cell hash that decide whether the cell is filled, and whether with a disc.
const FILL_BITS: u32 = 10;
const KIND_BITS: u32 = 6;
/// Odd 64-bit constants that spread a cell's coordinates over the hash key.
const CELL_KEY_S: u64 = 0xD1B5_4A32_D192_ED03;
const CELL_KEY_T: u64 = 0xAEF1_7502_108E_F2D9;

/// `width` bits of `bits` starting at bit `low`.
#[inline]
fn bit_field(bits: u64, low: u32, width: u32) -> i64 {
    ((bits >> low) & ((1 << width) - 1)) as i64
}

/// `probability` as a threshold on a `width`-bit uniform field.
fn threshold(probability: f64, width: u32) -> i64 {
    (probability * f64::from(1u32 << width)) as i64
}

/// One layer of a poster: its cell size, fill threshold, grid offset and seed.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PosterLayer {
    /// log2 of the cell size in fixed-point units.
    shift: u32,
    /// A cell is filled when its fill field is below this.
    fill_threshold: i64,
    /// Grid offset in fixed-point units.
    offset: [i64; 2],
    seed: u64,
}

/// The shape of one cell, in [`FRACTION_BITS`] cell coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Shape {
    Empty,
    Rectangle { min: [i64; 2], max: [i64; 2], hash: u64 },
    Disc { centre: [i64; 2], radius_squared: i64, hash: u64 },
}

impl Shape {
    /// The shape of cell `cell` of `layer`.
    fn of_cell(layer: &PosterLayer, cell: [i64; 2]) -> Self {
        let key =
            layer.seed.wrapping_add((cell[0] as u64).wrapping_mul(CELL_KEY_S)).wrapping_add((cell[1] as u64).wrapping_mul(CELL_KEY_T));
        let hash = mix64(key);
        if bit_field(hash, 0, FILL_BITS) >= layer.fill_threshold {
            return Self::Empty;
        }
        let disc = bit_field(hash, FILL_BITS, KIND_BITS) < threshold(DISC_PROBABILITY, KIND_BITS);
        let [extent_low, extent_high] = [SHAPE_EXTENT.0, SHAPE_EXTENT.1].map(|e| (e * CELL_ONE as f64) as i64);
        // Four uniform fields: two extents and two placements within the slack.
        let field = |i: u32| bit_field(hash, FILL_BITS + KIND_BITS + i * FRACTION_BITS, FRACTION_BITS);
        let size = [0, 1].map(|i| extent_low + (((extent_high - extent_low) * field(i)) >> FRACTION_BITS));
        if disc {
            let radius = size[0] / 2;
            let centre = [2, 3].map(|i| radius + (((CELL_ONE - 2 * radius) * field(i)) >> FRACTION_BITS));
            Self::Disc { centre, radius_squared: radius * radius, hash }
        } else {
            let min = [0, 1].map(|i: usize| ((CELL_ONE - size[i]) * field(i as u32 + 2)) >> FRACTION_BITS);
            Self::Rectangle { min, max: [min[0] + size[0], min[1] + size[1]], hash }
        }
    }

    /// The shape's hash if it covers `point` (cell coordinates).
    #[inline]
    fn covering(&self, point: [i64; 2]) -> Option<u64> {
        match *self {
            Self::Empty => None,
            Self::Rectangle { min, max, hash } => {
                ((min[0]..max[0]).contains(&point[0]) && (min[1]..max[1]).contains(&point[1])).then_some(hash)
            }
            Self::Disc { centre, radius_squared, hash } => {
                let (dx, dy) = (point[0] - centre[0], point[1] - centre[1]);
                (dx * dx + dy * dy < radius_squared).then_some(hash)
            }
        }
    }

    /// The colour of a shape with hash `hash`: dark or bright, with a random tint.
    fn colour(hash: u64) -> [f64; 3] {
        let bits = mix64(hash);
        let (low, high) = if bits & 1 == 0 { DARK_LEVELS } else { BRIGHT_LEVELS };
        let uniform = |i: u32| bit_field(bits, 1 + i * FRACTION_BITS, FRACTION_BITS) as f64 / CELL_ONE as f64;
        let grey = low + (high - low) * uniform(0);
        let channel = |i| (grey + SHAPE_TINT * (2.0 * uniform(i) - 1.0)).clamp(0.0, WHITE);
        [channel(1), channel(2), channel(3)]
    }
}

/// The last decoded cell of each poster layer: neighbouring samples mostly fall in the
/// same cells, so [`Texture::sample_cached`] rarely hashes.
#[derive(Debug, Clone)]
pub struct TextureCache {
    /// Per layer: (texture address, cell, shape).
    entries: [(usize, [i64; 2], Shape); POSTER_LAYERS.len()],
}

impl Default for TextureCache {
    fn default() -> Self {
        // Address 0 is no texture's, so every entry starts stale.
        Self { entries: [(0, [0; 2], Shape::Empty); POSTER_LAYERS.len()] }
    }
}

/// A procedural "cluttered poster" texture: random rectangles and discs of strong dark or
/// bright colours, at several sizes, over a mid-grey background. It is a function of
/// metric texture coordinates, so it is consistent from every viewpoint.
#[derive(Debug, Clone, PartialEq)]
pub struct Texture {
    background: [f64; 3],
    layers: [PosterLayer; POSTER_LAYERS.len()],
}

impl Texture {
    /// A poster whose layout and colours are determined by `seed`.
    pub fn poster(seed: u64) -> Self {
        let mut rng = SplitMix64::new(seed);
        let background = [(); 3].map(|_| BACKGROUND_GREY + rng.range(-BACKGROUND_TINT, BACKGROUND_TINT));
        let layers = POSTER_LAYERS.map(|(log2_cells_per_m, fill_probability)| {
            let shift = FIXED_BITS - log2_cells_per_m;
            PosterLayer {
                shift,
                fill_threshold: threshold(fill_probability, FILL_BITS),
                offset: [(); 2].map(|_| (rng.next_u64() >> (u64::BITS - shift)) as i64),
                seed: rng.next_u64(),
            }
        });
        Self { background, layers }
    }

    /// The colour (RGB, 0–255) at texture coordinates `(s, t)` in metres.
    pub fn sample(&self, s: f64, t: f64) -> [f64; 3] {
        self.sample_cached(s, t, &mut TextureCache::default())
    }

    /// [`Texture::sample`], reusing the cells decoded by the previous calls with `cache`
    /// (which may be shared between textures).
    #[inline]
    pub fn sample_cached(&self, s: f64, t: f64, cache: &mut TextureCache) -> [f64; 3] {
        let scale = f64::from(1u32 << FIXED_BITS);
        let point = [(s * scale) as i64, (t * scale) as i64];
        let address = std::ptr::from_ref(self) as usize;
        // Finest layer first: the first shape that covers the point is the one on top.
        for (layer, entry) in self.layers.iter().zip(&mut cache.entries).rev() {
            let shifted = [point[0] + layer.offset[0], point[1] + layer.offset[1]];
            let cell = [shifted[0] >> layer.shift, shifted[1] >> layer.shift];
            if entry.0 != address || entry.1 != cell {
                *entry = (address, cell, Shape::of_cell(layer, cell));
            }
            let within_shift = layer.shift - FRACTION_BITS;
            let within = [(shifted[0] >> within_shift) & (CELL_ONE - 1), (shifted[1] >> within_shift) & (CELL_ONE - 1)];
            if let Some(hash) = entry.2.covering(within) {
                return Shape::colour(hash);
            }
        }
        self.background
    }
}

/// A flat, double-sided parallelogram `origin + a·edge_u + b·edge_v`, `a, b ∈ [0, 1]`,
/// textured with texture coordinates `(a·|edge_u|, b·|edge_v|)` metres (metric when the
/// edges are perpendicular).
#[derive(Debug, Clone, PartialEq)]
pub struct Quad {
    /// The corner at `a = b = 0`, in the world frame.
    pub origin: Point3<f64>,
    /// The edges from `origin`, in the world frame.
    pub edge_u: Vector3<f64>,
    pub edge_v: Vector3<f64>,
    pub texture: Texture,
}

/// A set of textured quads in the world frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Scene {
    pub quads: Vec<Quad>,
}

/// [`Scene::room`]: the room's extent in x (metres; the camera path is centred on x = 0).
const ROOM_X: (f64, f64) = (-2.0, 2.0);
/// [`Scene::room`]: ceiling and floor heights (world y points down, the camera is at y = 0).
const ROOM_Y: (f64, f64) = (-1.6, 0.9);
/// [`Scene::room`]: extent in z; the back wall is at the far end, 3.5 m ahead of the origin.
const ROOM_Z: (f64, f64) = (-0.5, 3.5);
/// [`Scene::room`]: boxes standing on the floor, as (centre x, centre z, yaw in degrees,
/// width x, height y, depth z), in metres.
const ROOM_BOXES: [[f64; 6]; 4] =
    [[-0.6, 1.5, 20.0, 0.5, 0.9, 0.5], [0.6, 2.0, -15.0, 0.6, 1.1, 0.5], [-0.1, 2.9, 5.0, 1.0, 0.6, 0.4], [1.2, 2.8, 40.0, 0.5, 0.8, 0.5]];

impl Scene {
    /// An empty scene.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a quad with a poster texture drawn from `seed`.
    pub fn add_quad(&mut self, origin: Point3<f64>, edge_u: Vector3<f64>, edge_v: Vector3<f64>, seed: u64) {
        self.quads.push(Quad { origin, edge_u, edge_v, texture: Texture::poster(seed) });
    }

    /// Adds a box of full extents `size` (along its own x, y, z) centred on the origin of
    /// `world_from_box`, as six quads whose textures are drawn from `seed`.
    pub fn add_box(&mut self, world_from_box: &Isometry3<f64>, size: &Vector3<f64>, seed: u64) {
        let mut rng = SplitMix64::new(seed);
        let half = size / 2.0;
        for axis in 0..3 {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let edge_u = world_from_box.rotation * (Vector3::ith(u, 1.0) * size[u]);
            let edge_v = world_from_box.rotation * (Vector3::ith(v, 1.0) * size[v]);
            for side in [-1.0, 1.0] {
                let mut corner = -half;
                corner[axis] = side * half[axis];
                self.add_quad(world_from_box * Point3::from(corner), edge_u, edge_v, rng.next_u64());
            }
        }
    }

    /// A closed room about 4 m × 2.5 m × 4 m (floor, ceiling and four walls) with four
    /// boxes standing on the floor 1.5–3 m ahead: 30 quads. World y points down, the floor is
    /// 0.9 m below the origin, and a camera at the origin looking along +z (the identity
    /// pose, the start of [`sway_path`]) faces the back wall 3.5 m away.
    pub fn room(seed: u64) -> Self {
        let mut scene = Self::new();
        let mut rng = SplitMix64::new(seed);
        let size = Vector3::new(ROOM_X.1 - ROOM_X.0, ROOM_Y.1 - ROOM_Y.0, ROOM_Z.1 - ROOM_Z.0);
        let centre = Vector3::new(ROOM_X.0 + ROOM_X.1, ROOM_Y.0 + ROOM_Y.1, ROOM_Z.0 + ROOM_Z.1) / 2.0;
        scene.add_box(&Isometry3::from_parts(Translation3::from(centre), UnitQuaternion::identity()), &size, rng.next_u64());
        for [x, z, yaw_deg, width, height, depth] in ROOM_BOXES {
            let pose = Isometry3::new(Vector3::new(x, ROOM_Y.1 - height / 2.0, z), Vector3::y() * yaw_deg.to_radians());
            scene.add_box(&pose, &Vector3::new(width, height, depth), rng.next_u64());
        }
        scene
    }
}

/// Rendering parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOptions {
    /// Colour samples per pixel along each axis (1 = no anti-aliasing; 0 is taken as 1).
    pub supersampling: u32,
    /// Hits farther than this (camera-frame z, metres) get depth 0.
    pub max_range_m: f64,
    /// Standard deviation of the colour noise, in grey levels (0 = none).
    pub noise_sigma: f64,
    /// Seed of the colour noise; vary it per frame for temporally independent noise.
    pub noise_seed: u64,
    /// Whether to blur the colour image with a [1 2 1]/4 kernel along rows and columns
    /// (σ ≈ 0.7 px, like real optics): it keeps small texture details from flickering
    /// as the camera moves, which makes features far more repeatable.
    pub blur: bool,
    /// Threads to render with (0 = the machine's available parallelism). The image does
    /// not depend on it.
    pub threads: usize,
}

/// Default [`RenderOptions::supersampling`]: 2×2 samples keep texture edges stable.
pub const DEFAULT_SUPERSAMPLING: u32 = 2;
/// Default [`RenderOptions::max_range_m`], about a structured-light sensor's range.
pub const DEFAULT_MAX_RANGE_M: f64 = 8.0;

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            supersampling: DEFAULT_SUPERSAMPLING,
            max_range_m: DEFAULT_MAX_RANGE_M,
            noise_sigma: 0.0,
            noise_seed: 0,
            blur: true,
            threads: 0,
        }
    }
}

/// A rendered RGB-D frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Rendered {
    /// The camera's image size.
    pub width: u32,
    pub height: u32,
    /// RGB8, row-major, `width * height * 3` bytes.
    pub rgb: Vec<u8>,
    /// Row-major camera-frame z of the pixel centre's nearest hit, in the camera's
    /// `depth_units_per_metre`, rounded; 0 where nothing is hit within
    /// [`RenderOptions::max_range_m`] or the value would not fit.
    pub depth: Vec<u16>,
}

/// The camera of the TUM RGB-D benchmark's default ("ROS") calibration: 640×480,
/// f = 525 px, centre (319.5, 239.5), 5000 depth units per metre, no distortion.
pub fn kinect_camera() -> Camera {
    Camera::pinhole(640, 480, 525.0, 525.0, 319.5, 239.5, 5000.0)
}

/// Rays closer than this (metres of camera-frame z) hit nothing.
const NEAR_M: f64 = 1e-3;
/// Rays this close to parallel to a quad's plane (|n·d| per unit z) miss it.
const PARALLEL_EPSILON: f64 = 1e-12;
/// Side of the square pixel tiles whose rays share one list of candidate quads.
const TILE: usize = 8;
/// Colour of rays that hit nothing.
const BACKGROUND_RGB: [f64; 3] = [0.0; 3];
/// Uniform variates summed to approximate a Gaussian (Irwin–Hall); their sum has
/// variance `NOISE_TERMS / 12`.
const NOISE_TERMS: u32 = 4;

/// A quad moved into the camera frame, with what a ray–quad test needs precomputed.
struct CameraQuad<'a> {
    /// Unit normal and the plane offset `normal · origin`.
    normal: Vector3<f64>,
    offset: f64,
    /// Dual basis: `a = dual_u · (p − origin)`, likewise `b`; with `·origin` precomputed.
    dual_u: Vector3<f64>,
    dual_v: Vector3<f64>,
    dual_u_origin: f64,
    dual_v_origin: f64,
    /// Texture metres per unit of `a`, `b`.
    length_u: f64,
    length_v: f64,
    /// Bounds of the quad's normalised image coordinates `(x/z, y/z)`, after clipping
    /// to `z ≥ NEAR_M`: `[min x, min y, max x, max y]`.
    bounds: [f64; 4],
    texture: &'a Texture,
}

impl<'a> CameraQuad<'a> {
    /// The quad in the camera frame, or `None` if it is degenerate or wholly behind the camera.
    fn new(quad: &'a Quad, camera_from_world: &Isometry3<f64>) -> Option<Self> {
        let origin = camera_from_world * quad.origin;
        let edge_u = camera_from_world * quad.edge_u;
        let edge_v = camera_from_world * quad.edge_v;
        let normal = edge_u.cross(&edge_v).try_normalize(0.0)?;
        let dual_u = edge_v.cross(&normal) / edge_u.dot(&edge_v.cross(&normal));
        let dual_v = normal.cross(&edge_u) / edge_v.dot(&normal.cross(&edge_u));
        let corners = [origin, origin + edge_u, origin + edge_u + edge_v, origin + edge_v];
        let mut bounds = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
        let mut extend = |p: &Point3<f64>| {
            let (x, y) = (p.x / p.z, p.y / p.z);
            bounds = [bounds[0].min(x), bounds[1].min(y), bounds[2].max(x), bounds[3].max(y)];
        };
        // Clip the polygon against the near plane (Sutherland–Hodgman, one plane).
        for (i, a) in corners.iter().enumerate() {
            let b = &corners[(i + 1) % corners.len()];
            if a.z >= NEAR_M {
                extend(a);
            }
            if (a.z >= NEAR_M) != (b.z >= NEAR_M) {
                extend(&(a + (b - a) * ((NEAR_M - a.z) / (b.z - a.z))));
            }
        }
        (bounds[0] <= bounds[2]).then(|| Self {
            normal,
            offset: normal.dot(&origin.coords),
            dual_u_origin: dual_u.dot(&origin.coords),
            dual_v_origin: dual_v.dot(&origin.coords),
            dual_u,
            dual_v,
            length_u: edge_u.norm(),
            length_v: edge_v.norm(),
            bounds,
            texture: &quad.texture,
        })
    }

    /// Where the ray `(x, y, 1)·z` hits the quad: `(z, a, b)` if it does at `NEAR_M ≤ z < nearest`.
    #[inline]
    fn hit(&self, ray: &Vector3<f64>, nearest: f64) -> Option<(f64, f64, f64)> {
        let denominator = self.normal.dot(ray);
        if denominator.abs() < PARALLEL_EPSILON {
            return None;
        }
        let z = self.offset / denominator;
        if !(NEAR_M..nearest).contains(&z) {
            return None;
        }
        let a = z * self.dual_u.dot(ray) - self.dual_u_origin;
        let b = z * self.dual_v.dot(ray) - self.dual_v_origin;
        ((0.0..=1.0).contains(&a) && (0.0..=1.0).contains(&b)).then_some((z, a, b))
    }

    /// Whether the quad's image bounds overlap `rect` (`[min x, min y, max x, max y]`).
    fn overlaps(&self, rect: &[f64; 4]) -> bool {
        self.bounds[0] <= rect[2] && rect[0] <= self.bounds[2] && self.bounds[1] <= rect[3] && rect[1] <= self.bounds[3]
    }

    /// Over the rays through the rectangle `rect` of normalised image coordinates: the
    /// nearest positive z of the quad's plane (infinite if the plane is behind all of
    /// them), and the farthest z of the quad if it covers the whole rectangle.
    fn depth_over(&self, rect: &[f64; 4]) -> (f64, Option<f64>) {
        // z = offset / (normal · ray) is monotonic in the ray's (x, y) wherever it is
        // positive, so its extremes lie on the corners; a convex quad that contains the
        // four corners contains the rectangle.
        let (mut nearest, mut farthest, mut covers) = (f64::INFINITY, 0.0_f64, true);
        for (x, y) in [(rect[0], rect[1]), (rect[2], rect[1]), (rect[0], rect[3]), (rect[2], rect[3])] {
            let ray = Vector3::new(x, y, 1.0);
            let z = self.offset / self.normal.dot(&ray);
            if z > 0.0 {
                nearest = nearest.min(z);
                farthest = farthest.max(z);
            }
            covers &= self.hit(&ray, f64::INFINITY).is_some_and(|(_, a, b)| {
                (COVER_MARGIN..=1.0 - COVER_MARGIN).contains(&a) && (COVER_MARGIN..=1.0 - COVER_MARGIN).contains(&b)
            });
        }
        (nearest, covers.then_some(farthest))
    }
}

/// Margin (in quad coordinates) by which a quad must contain a tile's corners to hide
/// what is behind it, so rounding cannot open a gap.
const COVER_MARGIN: f64 = 1e-9;

/// The quads that rays through `rect` (normalised image coordinates) can hit first, the
/// one that hides the others (if any) first: `candidates` is cleared and refilled.
fn select_candidates(quads: &[CameraQuad], rect: &[f64; 4], candidates: &mut Vec<usize>, nearest: &mut Vec<f64>) {
    candidates.clear();
    nearest.clear();
    let mut occluder: Option<(usize, f64)> = None;
    for (i, quad) in quads.iter().enumerate() {
        if !quad.overlaps(rect) {
            continue;
        }
        let (near, cover_far) = quad.depth_over(rect);
        if near.is_infinite() {
            continue;
        }
        if let Some(far) = cover_far
            && occluder.is_none_or(|(_, z)| far < z)
        {
            occluder = Some((candidates.len(), far));
        }
        candidates.push(i);
        nearest.push(near);
    }
    if let Some((first, far)) = occluder {
        candidates.swap(0, first);
        nearest.swap(0, first);
        let mut kept = 0;
        for k in 0..candidates.len() {
            if nearest[k] <= far {
                candidates[kept] = candidates[k];
                kept += 1;
            }
        }
        candidates.truncate(kept);
    }
}

/// The nearest hit of `ray` among `candidates`: (z, quad, a, b).
#[inline]
fn nearest_hit<'q, 'a>(
    quads: &'q [CameraQuad<'a>],
    candidates: &[usize],
    ray: &Vector3<f64>,
) -> Option<(f64, &'q CameraQuad<'a>, f64, f64)> {
    let mut best = None;
    let mut nearest = f64::INFINITY;
    for &i in candidates {
        if let Some((z, a, b)) = quads[i].hit(ray, nearest) {
            nearest = z;
            best = Some((z, &quads[i], a, b));
        }
    }
    best
}

/// Renders `scene` seen by `camera` at `world_from_camera` with [`RenderOptions::default`].
pub fn render(scene: &Scene, camera: &Camera, world_from_camera: &Isometry3<f64>) -> Rendered {
    render_with(scene, camera, world_from_camera, &RenderOptions::default())
}

/// Renders `scene` seen by `camera` at `world_from_camera`.
pub fn render_with(scene: &Scene, camera: &Camera, world_from_camera: &Isometry3<f64>, options: &RenderOptions) -> Rendered {
    render_bands(scene, camera, options, |_| *world_from_camera)
}

/// Renders `scene` through a rolling shutter (`camera.readout_s`): each band of
/// [`TILE`] rows is seen from `world_from_camera_at(t)`, `t` being its middle row's
/// time relative to the image's middle row ([`Camera::row_time_s`]). Depth is
/// rendered the same way (a depth camera reading rows with the colour camera).
pub fn render_rolling_shutter(
    scene: &Scene,
    camera: &Camera,
    world_from_camera_at: impl Fn(f64) -> Isometry3<f64>,
    options: &RenderOptions,
) -> Rendered {
    render_bands(scene, camera, options, |first_row| world_from_camera_at(camera.row_time_s(first_row as f64 + (TILE as f64 - 1.0) / 2.0)))
}

/// Rows a band of a rolling-shutter render shares one pose for.
pub const ROLLING_SHUTTER_BAND_ROWS: usize = TILE;

/// Renders with `world_from_camera_of_band(first_row)` for each band of [`TILE`] rows.
fn render_bands(
    scene: &Scene,
    camera: &Camera,
    options: &RenderOptions,
    world_from_camera_of_band: impl Fn(usize) -> Isometry3<f64>,
) -> Rendered {
    let (width, height) = (camera.width as usize, camera.height as usize);
    if width == 0 || height == 0 {
        return Rendered { width: camera.width, height: camera.height, rgb: Vec::new(), depth: Vec::new() };
    }
    let renderer_at = |world_from_camera: &Isometry3<f64>| {
        let camera_from_world = world_from_camera.inverse();
        Renderer {
            quads: scene.quads.iter().filter_map(|q| CameraQuad::new(q, &camera_from_world)).collect(),
            camera,
            options,
            samples: options.supersampling.max(1) as usize,
            inverse_focal: [1.0 / camera.fx, 1.0 / camera.fy],
        }
    };
    // One renderer per distinct pose: a global shutter shares one for every band.
    let poses: Vec<Isometry3<f64>> = (0..height.div_ceil(TILE)).map(|band| world_from_camera_of_band(band * TILE)).collect();
    let renderers: Vec<Renderer> =
        if poses.windows(2).all(|p| p[0] == p[1]) { vec![renderer_at(&poses[0])] } else { poses.iter().map(renderer_at).collect() };
    let renderer_of = |band: usize| &renderers[band.min(renderers.len() - 1)];
    let renderer = &renderers[0];
    // Linear colour (0–255 per channel) before blur, noise and quantisation.
    let mut colour = vec![0f32; width * height * 3];
    let mut depth = vec![0u16; width * height];
    let mut bands: Vec<_> = colour.chunks_mut(width * 3 * TILE).zip(depth.chunks_mut(width * TILE)).enumerate().collect();
    let threads = match options.threads {
        0 => std::thread::available_parallelism().map_or(1, usize::from),
        n => n,
    }
    .min(bands.len());
    if threads <= 1 {
        let mut scratch = Scratch::default();
        for (band, (colour, depth)) in bands {
            renderer_of(band).render_band(band * TILE, colour, depth, &mut scratch);
        }
    } else {
        // Interleave the bands so that every thread gets a similar share of the scene.
        let mut shares: Vec<Vec<_>> = (0..threads).map(|_| Vec::new()).collect();
        for (i, band) in bands.drain(..).enumerate() {
            shares[i % threads].push(band);
        }
        std::thread::scope(|scope| {
            for (n, share) in shares.into_iter().enumerate() {
                let renderer_of = &renderer_of;
                std::thread::Builder::new()
                    .name(format!("synthetic-{n}"))
                    .spawn_scoped(scope, move || {
                        let mut scratch = Scratch::default();
                        for (band, (colour, depth)) in share {
                            renderer_of(band).render_band(band * TILE, colour, depth, &mut scratch);
                        }
                    })
                    .expect("a thread for rendering the synthetic frame (test data)");
            }
        });
    }
    if options.blur {
        blur_rows(&mut colour, width);
        blur_columns(&mut colour, width);
    }
    let rgb = colour
        .iter()
        .enumerate()
        .map(|(i, &c)| {
            let value = f64::from(c) + renderer.noise(i);
            // Adding a half and truncating rounds non-negative values without the libm
            // call that `round` costs on baseline x86-64.
            (value.clamp(0.0, WHITE) + 0.5) as u8
        })
        .collect();
    Rendered { width: camera.width, height: camera.height, rgb, depth }
}

/// Applies the [1 2 1]/4 kernel along the rows of an RGB image `width` pixels wide,
/// repeating the edge pixels.
fn blur_rows(image: &mut [f32], width: usize) {
    let mut previous = [0f32; 3];
    for row in image.chunks_exact_mut(width * 3) {
        for x in 0..width {
            for c in 0..3 {
                let centre = row[x * 3 + c];
                let left = if x == 0 { centre } else { previous[c] };
                let right = if x + 1 == width { centre } else { row[(x + 1) * 3 + c] };
                previous[c] = centre;
                row[x * 3 + c] = 0.25 * left + 0.5 * centre + 0.25 * right;
            }
        }
    }
}

/// Applies the [1 2 1]/4 kernel along the columns of an RGB image `width` pixels wide,
/// repeating the edge rows.
fn blur_columns(image: &mut [f32], width: usize) {
    let stride = width * 3;
    let mut previous = image.get(..stride).map(<[f32]>::to_vec).unwrap_or_default();
    let rows = image.len() / stride.max(1);
    for y in 0..rows {
        for i in 0..stride {
            let centre = image[y * stride + i];
            let below = if y + 1 == rows { centre } else { image[(y + 1) * stride + i] };
            image[y * stride + i] = 0.25 * previous[i] + 0.5 * centre + 0.25 * below;
            previous[i] = centre;
        }
    }
}

/// One frame's rendering state, shared by the threads that render its bands.
struct Renderer<'a> {
    quads: Vec<CameraQuad<'a>>,
    camera: &'a Camera,
    options: &'a RenderOptions,
    /// Colour samples per pixel along each axis.
    samples: usize,
    /// `1 / fx`, `1 / fy`.
    inverse_focal: [f64; 2],
}

/// Per-thread buffers, reused from tile to tile.
#[derive(Default)]
struct Scratch {
    /// The tile's rays: per pixel, the centre ray then the colour sample rays.
    rays: Vec<Vector3<f64>>,
    candidates: Vec<usize>,
    candidate_nearest: Vec<f64>,
    texture_cache: TextureCache,
}

impl Renderer<'_> {
    /// The ray through raw pixel coordinates `(u, v)`, as `(x/z, y/z, 1)`.
    #[inline]
    fn ray(&self, u: f64, v: f64) -> Vector3<f64> {
        let camera = self.camera;
        let ideal = if camera.distortion.is_some() { camera.undistort(&Point2::new(u, v)) } else { Point2::new(u, v) };
        Vector3::new((ideal.x - camera.cx) * self.inverse_focal[0], (ideal.y - camera.cy) * self.inverse_focal[1], 1.0)
    }

    /// Renders the rows from `first_row` that `colour` and `depth` hold (at most [`TILE`]).
    fn render_band(&self, first_row: usize, colour: &mut [f32], depth: &mut [u16], scratch: &mut Scratch) {
        let width = self.camera.width as usize;
        let rows = depth.len() / width;
        let samples = self.samples;
        let rays_per_pixel = 1 + samples * samples;
        let sample_offset = |s: usize| (s as f64 + 0.5) / samples as f64 - 0.5;
        for tile_u in (0..width).step_by(TILE) {
            let columns = tile_u..(tile_u + TILE).min(width);
            scratch.rays.clear();
            for v in first_row..first_row + rows {
                for u in columns.clone() {
                    scratch.rays.push(self.ray(u as f64, v as f64));
                    for sv in 0..samples {
                        for su in 0..samples {
                            scratch.rays.push(self.ray(u as f64 + sample_offset(su), v as f64 + sample_offset(sv)));
                        }
                    }
                }
            }
            let mut bounds = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
            for r in &scratch.rays {
                bounds = [bounds[0].min(r.x), bounds[1].min(r.y), bounds[2].max(r.x), bounds[3].max(r.y)];
            }
            select_candidates(&self.quads, &bounds, &mut scratch.candidates, &mut scratch.candidate_nearest);

            let mut pixel_rays = scratch.rays.chunks_exact(rays_per_pixel);
            for row in 0..rows {
                for u in columns.clone() {
                    let Some((centre, colour_rays)) = pixel_rays.next().and_then(|rays| rays.split_first()) else {
                        unreachable!("one chunk of rays per pixel of the tile");
                    };
                    let pixel = row * width + u;
                    depth[pixel] = self.depth(centre, &scratch.candidates);
                    let mut sum = [0.0; 3];
                    for r in colour_rays {
                        let sample = nearest_hit(&self.quads, &scratch.candidates, r).map_or(BACKGROUND_RGB, |(_, quad, a, b)| {
                            quad.texture.sample_cached(a * quad.length_u, b * quad.length_v, &mut scratch.texture_cache)
                        });
                        for (c, s) in sum.iter_mut().zip(sample) {
                            *c += s;
                        }
                    }
                    for (channel, c) in sum.iter().enumerate() {
                        colour[pixel * 3 + channel] = (c / (samples * samples) as f64) as f32;
                    }
                }
            }
        }
    }

    /// The raw depth of the nearest hit along `ray`, or 0.
    #[inline]
    fn depth(&self, ray: &Vector3<f64>, candidates: &[usize]) -> u16 {
        match nearest_hit(&self.quads, candidates, ray) {
            Some((z, ..)) if z <= self.options.max_range_m => {
                let units = z * self.camera.depth_units_per_metre + 0.5;
                if units < f64::from(u16::MAX) + 1.0 { units as u16 } else { 0 }
            }
            _ => 0,
        }
    }

    /// The colour noise of channel value `index` (row-major RGB index).
    #[inline]
    fn noise(&self, index: usize) -> f64 {
        if self.options.noise_sigma <= 0.0 {
            return 0.0;
        }
        let scale = self.options.noise_sigma * (12.0 / f64::from(NOISE_TERMS)).sqrt();
        let mut rng = SplitMix64::new(self.options.noise_seed ^ mix64(index as u64));
        scale * (0..NOISE_TERMS).map(|_| rng.next_f64() - 0.5).sum::<f64>()
    }
}

/// [`sway_path`]: frames per period of the slowest sinusoid (8 s at 30 Hz).
pub const SWAY_PERIOD_FRAMES: f64 = 240.0;
/// [`sway_path`]: translation amplitudes in x, y, z (metres).
pub const SWAY_TRANSLATION_M: [f64; 3] = [0.3, 0.1, 0.1];
/// [`sway_path`]: frequencies of the x, y, z translations, in multiples of the base frequency.
const SWAY_TRANSLATION_HARMONICS: [f64; 3] = [1.0, 2.0, 1.5];
/// [`sway_path`]: yaw (about camera y), pitch (about x) and roll (about z) amplitudes in degrees.
pub const SWAY_ROTATION_DEG: [f64; 3] = [15.0, 8.0, 5.0];
/// [`sway_path`]: frequencies of yaw, pitch and roll, in multiples of the base frequency.
const SWAY_ROTATION_HARMONICS: [f64; 3] = [1.0, 2.0, 3.0];
/// The [`sway_path`] pose at (fractional) frame `frame`: `world_from_camera`.
pub fn sway_pose(frame: f64) -> Isometry3<f64> {
    let phase = TAU * frame / SWAY_PERIOD_FRAMES;
    let wave = |amplitude: f64, harmonic: f64| amplitude * (harmonic * phase).sin();
    let translation = Vector3::from_fn(|i, _| wave(SWAY_TRANSLATION_M[i], SWAY_TRANSLATION_HARMONICS[i]));
    let [yaw, pitch, roll] = [0, 1, 2].map(|i| wave(SWAY_ROTATION_DEG[i].to_radians(), SWAY_ROTATION_HARMONICS[i]));
    // Yaw turns left (negative about y) while x moves right, so the camera keeps facing
    // the middle of the back wall.
    let rotation = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), -yaw)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), pitch)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll);
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

/// A smooth hand-held-like camera path of `frames` poses (`world_from_camera`) for
/// [`Scene::room`], starting at the identity: sinusoidal sway of
/// [`SWAY_TRANSLATION_M`] and [`SWAY_ROTATION_DEG`] with period [`SWAY_PERIOD_FRAMES`]
/// (and harmonics), at most about 1 cm and 0.7° per frame, always facing the back wall.
pub fn sway_path(frames: usize) -> Vec<Isometry3<f64>> {
    (0..frames).map(|i| sway_pose(i as f64)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fronto-parallel 1.2 m × 0.8 m quad centred on the optical axis at `z` metres.
    fn wall_at(z: f64) -> Scene {
        let mut scene = Scene::new();
        scene.add_quad(Point3::new(-0.6, -0.4, z), Vector3::new(1.2, 0.0, 0.0), Vector3::new(0.0, 0.8, 0.0), 7);
        scene
    }

    #[test]
    fn fronto_parallel_quad_has_exact_depth_and_nothing_outside() {
        let camera = kinect_camera();
        let z = 2.0;
        let frame = render(&wall_at(z), &camera, &Isometry3::identity());
        let expected = (z * camera.depth_units_per_metre) as u16;
        let (mut covered, mut empty) = (0, 0);
        for v in 0..camera.height {
            for u in 0..camera.width {
                let d = frame.depth[(v * camera.width + u) as usize];
                let p = camera.unproject(&Point2::new(u as f64, v as f64), z);
                let inside = (-0.6..=0.6).contains(&p.x) && (-0.4..=0.4).contains(&p.y);
                assert_eq!(d, if inside { expected } else { 0 }, "pixel ({u}, {v})");
                if inside { covered += 1 } else { empty += 1 }
            }
        }
        assert!(covered > 50_000 && empty > 50_000, "{covered} covered, {empty} empty");
        // Outside the quad the colour is the background; inside it is textured.
        assert_eq!(&frame.rgb[..3], &[0, 0, 0]);
    }

    #[test]
    fn depth_is_consistent_with_camera_projection() {
        let fr1 = Camera { readout_s: 0.0, ..crate::testing::fr1_camera() };
        // A tilted quad, seen from a rotated and translated camera.
        let mut scene = Scene::new();
        let origin = Point3::new(-1.0, -0.8, 2.0);
        let (edge_u, edge_v) = (Vector3::new(2.0, 0.0, 1.0), Vector3::new(0.0, 1.6, -0.3));
        scene.add_quad(origin, edge_u, edge_v, 3);
        let world_from_camera = Isometry3::new(Vector3::new(0.1, -0.05, 0.2), Vector3::new(0.05, -0.1, 0.03));
        let camera_from_world = world_from_camera.inverse();
        for camera in [kinect_camera(), fr1] {
            let frame = render(&scene, &camera, &world_from_camera);
            let mut rng = SplitMix64::new(11);
            let mut checked = 0;
            while checked < 200 {
                // Away from the edges, so the nearest pixel centre's ray still hits the quad.
                let point_in_world = origin + edge_u * rng.range(0.02, 0.98) + edge_v * rng.range(0.02, 0.98);
                let point_in_camera = camera_from_world * point_in_world;
                let Some(ideal) = camera.project(&point_in_camera) else { continue };
                let raw = camera.distort(&ideal);
                let (u, v) = (raw.x.round(), raw.y.round());
                if u < 0.0 || v < 0.0 || u >= camera.width as f64 || v >= camera.height as f64 {
                    continue;
                }
                // The pixel centre's ray meets the plane within half a pixel of the point,
                // so its depth is the point's z up to the plane's slope over half a pixel.
                let d = frame.depth[v as usize * camera.width as usize + u as usize];
                let z = f64::from(d) / camera.depth_units_per_metre;
                assert!((z - point_in_camera.z).abs() < 0.01, "({u}, {v}): depth {z} vs point z {}", point_in_camera.z);
                // Exactly: intersect the centre ray with the plane here, in the world frame.
                let ideal_centre = camera.undistort(&Point2::new(u, v));
                let direction = world_from_camera.rotation * camera.unproject(&ideal_centre, 1.0).coords;
                let normal = edge_u.cross(&edge_v);
                let scale = normal.dot(&(origin - world_from_camera.translation.vector).coords) / normal.dot(&direction);
                let expected = (scale * camera.depth_units_per_metre).round();
                assert!((f64::from(d) - expected).abs() <= 1.0, "({u}, {v}): {d} vs {expected}");
                checked += 1;
            }
        }
    }

    #[test]
    fn rendering_is_deterministic() {
        let scene = Scene::room(5);
        let options = RenderOptions { noise_sigma: 2.0, noise_seed: 9, ..RenderOptions::default() };
        let pose = sway_pose(37.0);
        let first = render_with(&scene, &kinect_camera(), &pose, &options);
        assert_eq!(first, render_with(&scene, &kinect_camera(), &pose, &options));
        assert_ne!(first.rgb, render(&scene, &kinect_camera(), &pose).rgb, "noise changes the image");
    }

    /// Mean absolute difference of horizontally adjacent grey levels.
    fn mean_horizontal_gradient(frame: &Rendered) -> f64 {
        let grey: Vec<f64> = frame.rgb.chunks_exact(3).map(|p| p.iter().map(|&c| f64::from(c)).sum::<f64>() / 3.0).collect();
        let rows = grey.chunks_exact(frame.width as usize);
        let total: f64 = rows.map(|row| row.windows(2).map(|w| (w[1] - w[0]).abs()).sum::<f64>()).sum();
        total / (frame.height as f64 * (frame.width - 1) as f64)
    }

    /// Least acceptable [`mean_horizontal_gradient`] of a room frame (the posters give
    /// about 11).
    const MIN_MEAN_GRADIENT: f64 = 4.0;

    #[test]
    fn room_along_the_path_is_densely_textured_with_valid_depth() {
        let camera = kinect_camera();
        let scene = Scene::room(1);
        let path = sway_path(SWAY_PERIOD_FRAMES as usize);
        for (i, pose) in path.iter().enumerate().step_by(30) {
            let frame = render(&scene, &camera, pose);
            let in_band = frame.depth.iter().filter(|&&d| (0.5..5.0).contains(&(f64::from(d) / camera.depth_units_per_metre))).count();
            let valid = frame.depth.iter().filter(|&&d| d > 0).count();
            assert!(valid as f64 >= 0.95 * frame.depth.len() as f64, "frame {i}: {valid} valid");
            assert!(in_band as f64 >= 0.95 * frame.depth.len() as f64, "frame {i}: {in_band} within 0.5-5 m");
            let gradient = mean_horizontal_gradient(&frame);
            assert!(gradient > MIN_MEAN_GRADIENT, "frame {i}: mean gradient {gradient}");
        }
    }

    #[test]
    fn sway_path_steps_are_small_and_smooth() {
        let path = sway_path(2 * SWAY_PERIOD_FRAMES as usize);
        assert_eq!(path[0], Isometry3::identity());
        for pair in path.windows(2) {
            let step = pair[0].inverse() * pair[1];
            assert!(step.translation.vector.norm() <= 0.015, "{step}");
            assert!(step.rotation.angle().to_degrees() <= 1.0, "{step}");
        }
        let max = |f: &dyn Fn(&Isometry3<f64>) -> f64| path.iter().map(f).fold(0.0, f64::max);
        assert!((max(&|p| p.translation.x) - SWAY_TRANSLATION_M[0]).abs() < 1e-3);
        let largest_turn = max(&|p| p.rotation.angle().to_degrees());
        let bound = SWAY_ROTATION_DEG.iter().map(|a| a * a).sum::<f64>().sqrt();
        assert!((SWAY_ROTATION_DEG[0]..=bound).contains(&largest_turn), "{largest_turn}°");
    }

    #[test]
    fn box_faces_enclose_the_box() {
        let mut scene = Scene::new();
        let pose = Isometry3::new(Vector3::new(1.0, 2.0, 3.0), Vector3::new(0.3, 0.2, 0.1));
        let size = Vector3::new(0.4, 0.6, 0.8);
        scene.add_box(&pose, &size, 1);
        assert_eq!(scene.quads.len(), 6);
        for quad in &scene.quads {
            let centre_in_box = pose.inverse() * (quad.origin + (quad.edge_u + quad.edge_v) / 2.0);
            let on_faces = (0..3).filter(|&i| (centre_in_box[i].abs() - size[i] / 2.0).abs() < 1e-12).count();
            assert_eq!(on_faces, 1, "face centre {centre_in_box}");
        }
    }
}
