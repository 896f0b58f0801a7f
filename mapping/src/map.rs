//! The voxel map: fusing a keyframe's depth (hits), carving free space (misses),
//! and taking a keyframe's contribution back out when its pose is corrected.
//!
//! **Surface model: occupancy log-odds, not a TSDF.** A TSDF only updates voxels
//! within its truncation band of the observed surface, so a person who stood
//! still and walked away stays in the map until something is seen *at* their
//! place — voxblox's and RTAB-Map's best-known ghost complaint. Occupancy with
//! carving along the viewing rays removes them as soon as what is behind them is
//! seen. The price is a blockier surface (one voxel, no sub-voxel zero crossing),
//! which 2 cm voxels and top-down tiles do not notice.
//!
//! **Carving is projective:** instead of marching every ray (≈ 150 voxels per
//! pixel at 2 cm), every voxel that ever held a surface and lies in the view is
//! projected into the depth image; when the nearest reading around its pixel
//! (3×3 cells of the 2×2 min-pooled depth, most of them valid) lies clearly
//! behind it, the ray to that reading passed through it, and it gets a miss. Its cost is proportional to the surfaces in view, and
//! unknown space stays unknown (only surfaces can be ghosts). Rays to dynamic
//! pixels carve too: a person walking in front of a wall still proves the space
//! in front of them empty.

use nalgebra::{Isometry3, Point2, Point3, Vector3};
use rustc_hash::FxHashMap;
use stillmap_tracking::Camera;

use crate::MappingError;
use crate::config::MappingConfig;
use crate::voxel::{BLOCK_EDGE, Block, BlockKey, NO_CLASS, VOXELS_PER_BLOCK, Voxel, VoxelKey, block_of, voxel_centre, voxel_key, voxel_of};

/// Each pixel's viewing ray, `point_in_camera = (x·z, y·z, z)`, undistorted once.
#[derive(Debug, Clone)]
pub struct CameraRays {
    pub camera: Camera,
    rays: Vec<[f32; 2]>,
}

impl CameraRays {
    /// The longest viewing ray per metre of depth (an image corner's).
    pub fn max_ray_norm(&self) -> f64 {
        self.rays.iter().map(|[x, y]| f64::from(x * x + y * y + 1.0).sqrt()).fold(1.0, f64::max)
    }

    pub fn new(camera: &Camera) -> Self {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut rays = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let ideal = camera.undistort(&Point2::new(x as f64, y as f64));
                rays.push([((ideal.x - camera.cx) / camera.fx) as f32, ((ideal.y - camera.cy) / camera.fy) as f32]);
            }
        }
        Self { camera: camera.clone(), rays }
    }
}

/// One frame's images, as the map needs them.
#[derive(Debug, Clone, Copy)]
pub struct DepthView<'a> {
    /// Raw depth, `width × height`, 0 = no reading.
    pub depth: &'a [u16],
    /// RGB8, `width × height × 3`.
    pub rgb: &'a [u8],
    /// Nonzero where the pixel must stay out of the map (dynamic, prior-dynamic);
    /// `None`: every pixel is static.
    pub exclude: Option<&'a [u8]>,
    /// Segmentation class per pixel (`NO_CLASS` outside instances); `None`: no
    /// segmentation for this frame, so no class evidence either way.
    pub classes: Option<&'a [u16]>,
}

/// One voxel's share of a keyframe: its mean colour and majority class.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceSample {
    pub point_in_camera: [f32; 3],
    pub rgb: [u8; 3],
    /// `None` when the frame had no segmentation.
    pub class: Option<u16>,
    /// The pixel it was taken from (row-major index).
    pub pixel: u32,
}

/// A keyframe reduced to what fusing it needs: surface samples (static pixels
/// in range, one per pixel at the stride) and a 2×2 min-pooled depth for carving.
#[derive(Debug, Clone, PartialEq)]
pub struct FusionInput {
    pub samples: Vec<SurfaceSample>,
    pub carve_depth: Vec<f32>,
    pub carve_width: usize,
    pub carve_height: usize,
    /// Pixels in range that the mask kept out.
    pub excluded_pixels: usize,
}

/// Largest decoded [`FusionInput::to_compact`] (a 4K depth image's worth).
const MAX_COMPACT_BYTES: usize = 256 << 20;

/// Bytes per sample in [`FusionInput::to_compact`]'s columns (pixel step, depth,
/// colour, class flag, class).
const COMPACT_SAMPLE_BYTES: usize = 4 + 2 + 3 + 1 + 2;

/// Depth in whole millimetres (what a compact input keeps; carving and voxels are
/// centimetres).
fn to_mm(z_m: f32) -> u16 {
    (z_m * 1000.0).round().clamp(0.0, f32::from(u16::MAX)) as u16
}

impl FusionInput {
    /// The input in a few hundred kilobytes, depth to the millimetre (columns of
    /// samples: pixel steps, depth, colour, class; the carving depth; zstd): what
    /// a map keeps of a keyframe to fuse it again at a corrected pose long after
    /// it was fused. [`from_compact`](Self::from_compact) needs the same camera.
    pub fn to_compact(&self) -> Result<Vec<u8>, MappingError> {
        let n = self.samples.len();
        if self.carve_depth.len() != self.carve_width * self.carve_height {
            return Err(MappingError::Encode("carving depth does not match its size".into()));
        }
        let mut raw = Vec::with_capacity(16 + n * COMPACT_SAMPLE_BYTES + self.carve_depth.len() * 2);
        for v in [n, self.carve_width, self.carve_height, self.excluded_pixels] {
            let v = u32::try_from(v).map_err(|_| MappingError::Encode(format!("fusion input count {v} beyond u32")))?;
            raw.extend_from_slice(&v.to_le_bytes());
        }
        let mut previous = 0u32;
        for p in self.samples.iter().map(|s| s.pixel) {
            raw.extend_from_slice(&p.wrapping_sub(previous).to_le_bytes());
            previous = p;
        }
        self.samples.iter().for_each(|s| raw.extend_from_slice(&to_mm(s.point_in_camera[2]).to_le_bytes()));
        for channel in 0..3 {
            raw.extend(self.samples.iter().map(|s| s.rgb[channel]));
        }
        raw.extend(self.samples.iter().map(|s| u8::from(s.class.is_some())));
        self.samples.iter().for_each(|s| raw.extend_from_slice(&s.class.unwrap_or(0).to_le_bytes()));
        self.carve_depth.iter().for_each(|&d| raw.extend_from_slice(&to_mm(d).to_le_bytes()));
        let raw_len = u32::try_from(raw.len()).map_err(|_| MappingError::Encode("fusion input beyond 4 GiB".into()))?;
        let mut out = raw_len.to_le_bytes().to_vec();
        out.extend(zstd::bulk::compress(&raw, 3).map_err(|e| MappingError::Encode(e.to_string()))?);
        Ok(out)
    }

    /// Reads [`to_compact`](Self::to_compact)'s bytes back for the camera of `rays`.
    pub fn from_compact(bytes: &[u8], rays: &CameraRays) -> Result<Self, MappingError> {
        let corrupt = |what: &str| MappingError::Corrupt(format!("compact fusion input: {what}"));
        let (len, frame) = bytes.split_first_chunk::<4>().ok_or_else(|| corrupt("no header"))?;
        let raw_len = u32::from_le_bytes(*len) as usize;
        if raw_len > MAX_COMPACT_BYTES {
            return Err(corrupt("larger than a keyframe can be"));
        }
        let raw = zstd::bulk::decompress(frame, raw_len).map_err(|e| corrupt(&e.to_string()))?;
        if raw.len() != raw_len {
            return Err(corrupt("shorter than its header says"));
        }
        let mut at = 0usize;
        let mut take = |k: usize| -> Result<&[u8], MappingError> {
            let end = at.checked_add(k).filter(|&e| e <= raw.len()).ok_or_else(|| corrupt("truncated"))?;
            let out = &raw[at..end];
            at = end;
            Ok(out)
        };
        let mut header = [0usize; 4];
        for h in &mut header {
            *h = u32::from_le_bytes(take(4)?.try_into().map_err(|_| corrupt("header"))?) as usize;
        }
        let [n, carve_width, carve_height, excluded_pixels] = header;
        let cells = carve_width.checked_mul(carve_height).ok_or_else(|| corrupt("carving size"))?;
        let expected = n.checked_mul(COMPACT_SAMPLE_BYTES).and_then(|b| b.checked_add(cells.checked_mul(2)?)?.checked_add(16));
        if expected != Some(raw_len) {
            return Err(corrupt("counts do not match its length"));
        }
        let u16s = |b: &[u8]| b.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect::<Vec<_>>();
        let mut pixel = 0u32;
        let pixels: Vec<u32> = take(4 * n)?
            .chunks_exact(4)
            .map(|c| {
                pixel = pixel.wrapping_add(u32::from_le_bytes([c[0], c[1], c[2], c[3]]));
                pixel
            })
            .collect();
        let depth_mm = u16s(take(2 * n)?);
        let (r, g, b) = (take(n)?.to_vec(), take(n)?.to_vec(), take(n)?.to_vec());
        let has_class = take(n)?.to_vec();
        let classes = u16s(take(2 * n)?);
        let carve_depth = u16s(take(2 * cells)?).into_iter().map(|d| f32::from(d) / 1000.0).collect();
        let samples = (0..n)
            .map(|i| {
                let [rx, ry] = *rays.rays.get(pixels[i] as usize).ok_or_else(|| corrupt("a pixel outside the camera"))?;
                let z = f32::from(depth_mm[i]) / 1000.0;
                Ok(SurfaceSample {
                    point_in_camera: [rx * z, ry * z, z],
                    rgb: [r[i], g[i], b[i]],
                    class: (has_class[i] != 0).then_some(classes[i]),
                    pixel: pixels[i],
                })
            })
            .collect::<Result<Vec<_>, MappingError>>()?;
        Ok(Self { samples, carve_depth, carve_width, carve_height, excluded_pixels })
    }
}

/// What fusing one keyframe did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FuseStats {
    pub samples: usize,
    pub excluded_pixels: usize,
    pub voxels_hit: usize,
    pub voxels_carved: usize,
    pub blocks_allocated: usize,
    /// Samples left out because they would have started more than
    /// `max_new_blocks_per_keyframe` blocks.
    pub samples_over_block_budget: usize,
}

/// Totals over the map.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MapStats {
    pub blocks: usize,
    pub occupied_voxels: usize,
    /// Heap bytes of the resident blocks and the hash table.
    pub bytes: usize,
}

/// Carving margin never below this many voxels (a surface is one voxel thick and
/// seen at grazing angles).
const MIN_CARVE_MARGIN_VOXELS: f64 = 2.0;
/// Cells of the 3×3 carving neighbourhood (each the nearest of 2×2 pixels) that
/// must hold a reading: a neighbourhood mostly without depth (a black screen, a
/// reading too near to measure) is no evidence of free space.
const MIN_CARVE_READINGS: usize = 5;

#[derive(Clone)]
pub struct VoxelMap {
    config: MappingConfig,
    blocks: FxHashMap<BlockKey, Block>,
    /// Bumped on every change (tile caches and ETags key on it).
    version: u64,
    /// Change stamp: one per fusion or de-fusion (blocks carry the stamp of their last change).
    keyframes_fused: u64,
}

/// Packs a voxel key into 63 bits for sorting (±2²⁰ voxels: ±20 km at 2 cm).
fn pack(key: VoxelKey) -> Option<u64> {
    const HALF: i64 = 1 << 20;
    let mut out = 0u64;
    for &k in &key {
        let v = i64::from(k) + HALF;
        if !(0..2 * HALF).contains(&v) {
            return None;
        }
        out = (out << 21) | v as u64;
    }
    Some(out)
}

impl VoxelMap {
    pub fn new(config: MappingConfig) -> Result<Self, MappingError> {
        config.validate()?;
        Ok(Self { config, blocks: FxHashMap::default(), version: 0, keyframes_fused: 0 })
    }

    pub fn config(&self) -> &MappingConfig {
        &self.config
    }

    pub fn version(&self) -> u64 {
        self.version
    }

    pub fn voxel_size(&self) -> f64 {
        self.config.voxel_size_m
    }

    /// Reduces a frame to its fusion input. Checks the image sizes.
    /// (Comparisons are negated so that NaN fails them too.)
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn prepare(&self, rays: &CameraRays, view: &DepthView<'_>) -> Result<FusionInput, MappingError> {
        let (w, h) = (rays.camera.width as usize, rays.camera.height as usize);
        let n = w * h;
        let check = |name: &str, len: usize, want: usize| {
            if len == want { Ok(()) } else { Err(MappingError::Input(format!("{name} has {len} values, expected {want} for {w}x{h}"))) }
        };
        check("depth", view.depth.len(), n)?;
        check("rgb", view.rgb.len(), 3 * n)?;
        if let Some(m) = view.exclude {
            check("exclusion mask", m.len(), n)?;
        }
        if let Some(c) = view.classes {
            check("class map", c.len(), n)?;
        }
        let units = rays.camera.depth_units_per_metre;
        if !(units > 0.0) {
            return Err(MappingError::Input("depth_units_per_metre must be positive".into()));
        }
        let (min_z, max_z) = (self.config.min_depth_m, self.config.max_depth_m);
        let s = self.config.pixel_stride;
        let mut samples = Vec::with_capacity(n / (s * s));
        let mut excluded_pixels = 0;
        for y in (0..h).step_by(s) {
            for x in (0..w).step_by(s) {
                let i = y * w + x;
                let d = view.depth[i];
                if d == 0 {
                    continue;
                }
                let z = f64::from(d) / units;
                if z < min_z || z > max_z {
                    continue;
                }
                if view.exclude.is_some_and(|m| m[i] != 0) {
                    excluded_pixels += 1;
                    continue;
                }
                let [rx, ry] = rays.rays[i];
                let z = z as f32;
                samples.push(SurfaceSample {
                    point_in_camera: [rx * z, ry * z, z],
                    rgb: [view.rgb[3 * i], view.rgb[3 * i + 1], view.rgb[3 * i + 2]],
                    class: view.classes.map(|c| c[i]),
                    pixel: i as u32,
                });
            }
        }
        let (cw, ch) = (w / 2, h / 2);
        let mut carve_depth = vec![0.0f32; cw * ch];
        for y in 0..ch {
            for x in 0..cw {
                // The nearest valid reading of the four (0: none valid, no evidence).
                let mut m = u16::MAX;
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let d = view.depth[(2 * y + dy) * w + 2 * x + dx];
                    if d != 0 {
                        m = m.min(d);
                    }
                }
                carve_depth[y * cw + x] = if m == u16::MAX { 0.0 } else { (f64::from(m) / units) as f32 };
            }
        }
        Ok(FusionInput { samples, carve_depth, carve_width: cw, carve_height: ch, excluded_pixels })
    }

    /// Fuses a keyframe at `world_from_camera`: carving first, then one hit per voxel.
    pub fn integrate(&mut self, rays: &CameraRays, input: &FusionInput, world_from_camera: &Isometry3<f64>) -> FuseStats {
        self.keyframes_fused += 1;
        let voxels_carved = self.carve(rays, input, &world_from_camera.inverse());
        let mut stats = self.apply_hits(&input.samples, world_from_camera, 1);
        stats.voxels_carved = voxels_carved;
        stats.excluded_pixels = input.excluded_pixels;
        self.version += 1;
        stats
    }

    /// Takes a keyframe's hits back out (its pose is about to be corrected). Misses
    /// it carved stay: carving is only ever evidence of free space.
    pub fn deintegrate(&mut self, input: &FusionInput, world_from_camera: &Isometry3<f64>) {
        self.deintegrate_samples(&input.samples, world_from_camera);
    }

    /// Takes some of a keyframe's hits back out (samples of a thing found to move).
    pub fn deintegrate_samples(&mut self, samples: &[SurfaceSample], world_from_camera: &Isometry3<f64>) {
        // A change stamp of its own, so that the blocks it touches count as changed.
        self.keyframes_fused += 1;
        self.apply_hits(samples, world_from_camera, -1);
        self.version += 1;
    }

    /// Groups the samples per voxel and applies one hit (sign +1) or removes one (−1).
    fn apply_hits(&mut self, samples: &[SurfaceSample], world_from_camera: &Isometry3<f64>, sign: i32) -> FuseStats {
        let res = self.config.voxel_size_m;
        let pose = world_from_camera.cast::<f64>();
        let mut keyed: Vec<(u64, u32)> = Vec::with_capacity(samples.len());
        for (i, s) in samples.iter().enumerate() {
            let [x, y, z] = s.point_in_camera;
            let p = pose * Point3::new(f64::from(x), f64::from(y), f64::from(z));
            if let Some(k) = pack(voxel_key(&p, res)) {
                keyed.push((k, i as u32));
            }
        }
        keyed.sort_unstable();
        let mut stats = FuseStats { samples: samples.len(), ..FuseStats::default() };
        let cfg = &self.config;
        let stamp = self.keyframes_fused;
        let mut start = 0;
        let mut classes: Vec<(u16, u32)> = Vec::new();
        while start < keyed.len() {
            let key = keyed[start].0;
            let end = start + keyed[start..].iter().take_while(|e| e.0 == key).count();
            let group = &keyed[start..end];
            start = end;
            let first = &samples[group[0].1 as usize];
            let [x, y, z] = first.point_in_camera;
            let vkey = voxel_key(&(pose * Point3::new(f64::from(x), f64::from(y), f64::from(z))), res);
            let mut sum = [0u32; 3];
            classes.clear();
            let mut labelled = false;
            for &(_, i) in group {
                let s = &samples[i as usize];
                for (total, channel) in sum.iter_mut().zip(s.rgb) {
                    *total += u32::from(channel);
                }
                if let Some(class) = s.class {
                    labelled = true;
                    match classes.iter_mut().find(|(c, _)| *c == class) {
                        Some(e) => e.1 += 1,
                        None => classes.push((class, 1)),
                    }
                }
            }
            let n = group.len() as u32;
            let rgb = [(sum[0] / n) as u8, (sum[1] / n) as u8, (sum[2] / n) as u8];
            let majority = classes.iter().max_by_key(|(c, k)| (*k, *c == NO_CLASS)).map(|&(c, _)| c);
            let (bkey, index) = block_of(vkey);
            let block = match self.blocks.get_mut(&bkey) {
                Some(b) => b,
                None if sign > 0 && stats.blocks_allocated >= cfg.max_new_blocks_per_keyframe => {
                    stats.samples_over_block_budget += group.len();
                    continue;
                }
                None if sign > 0 => {
                    stats.blocks_allocated += 1;
                    self.blocks.entry(bkey).or_default()
                }
                None => continue,
            };
            block.touched = stamp;
            let v = &mut block.voxels[index];
            if sign > 0 {
                v.blend_color(rgb);
                v.hits = v.hits.saturating_add(1);
                v.log_odds = (v.log_odds + cfg.log_odds_hit).min(cfg.log_odds_max);
                if let (true, Some(c)) = (labelled, majority) {
                    v.vote(c);
                }
            } else {
                v.log_odds = (v.log_odds - cfg.log_odds_hit).max(cfg.log_odds_min);
                if let (true, Some(c)) = (labelled, majority) {
                    v.unvote(c);
                }
            }
            stats.voxels_hit += 1;
        }
        stats
    }

    /// Misses for every surface voxel in view with a reading clearly behind it.
    fn carve(&mut self, rays: &CameraRays, input: &FusionInput, camera_from_world: &Isometry3<f64>) -> usize {
        let cam = &rays.camera;
        let cfg = &self.config;
        let res = cfg.voxel_size_m;
        let block_m = res * f64::from(BLOCK_EDGE);
        let block_radius = block_m * 3f64.sqrt() / 2.0;
        let (w, h) = (f64::from(cam.width), f64::from(cam.height));
        let (cw, ch) = (input.carve_width as i64, input.carve_height as i64);
        let stamp = self.keyframes_fused;
        let mut carved = 0;
        for (bkey, block) in self.blocks.iter_mut() {
            let centre = Point3::new(
                (f64::from(bkey[0]) + 0.5) * block_m,
                (f64::from(bkey[1]) + 0.5) * block_m,
                (f64::from(bkey[2]) + 0.5) * block_m,
            );
            let c = camera_from_world * centre;
            if c.z + block_radius < cfg.min_depth_m || c.z - block_radius > cfg.max_depth_m {
                continue;
            }
            if c.z > block_radius {
                // Cull blocks whose bounding sphere projects wholly outside the image.
                let margin = block_radius / (c.z - block_radius);
                let (u, v) = (c.x / c.z, c.y / c.z);
                let (u0, u1) = (-cam.cx / cam.fx - margin, (w - cam.cx) / cam.fx + margin);
                let (v0, v1) = (-cam.cy / cam.fy - margin, (h - cam.cy) / cam.fy + margin);
                // Generous: distortion moves the image border by a few percent.
                let slack = 0.15 * (u1 - u0);
                if u < u0 - slack || u > u1 + slack || v < v0 - slack || v > v1 + slack {
                    continue;
                }
            }
            let mut changed = false;
            for index in 0..VOXELS_PER_BLOCK {
                let v = &mut block.voxels[index];
                if v.hits == 0 || v.log_odds <= cfg.log_odds_min {
                    continue;
                }
                let p = camera_from_world * voxel_centre(voxel_of(*bkey, index), res);
                // The range filter holds for carving too: a voxel this view could not
                // fuse is not carved by it either.
                if p.z < cfg.min_depth_m || p.z > cfg.max_depth_m {
                    continue;
                }
                let Some(ideal) = cam.project(&p) else { continue };
                let raw = cam.distort(&ideal);
                let (x, y) = ((raw.x / 2.0).floor() as i64, (raw.y / 2.0).floor() as i64);
                if x < 1 || y < 1 || x >= cw - 1 || y >= ch - 1 {
                    continue;
                }
                let (mut nearest, mut valid) = (f32::INFINITY, 0);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let d = input.carve_depth[((y + dy) * cw + x + dx) as usize];
                        if d > 0.0 {
                            nearest = nearest.min(d);
                            valid += 1;
                        }
                    }
                }
                if valid < MIN_CARVE_READINGS {
                    continue;
                }
                let sigma = cfg.depth_noise_a + cfg.depth_noise_b * p.z * p.z;
                let margin = (cfg.carve_sigmas * sigma).max(MIN_CARVE_MARGIN_VOXELS * res);
                if f64::from(nearest) > p.z + margin {
                    v.log_odds = (v.log_odds + cfg.log_odds_miss).max(cfg.log_odds_min);
                    carved += 1;
                    changed = true;
                }
            }
            if changed {
                block.touched = stamp;
            }
        }
        carved
    }

    pub fn voxel(&self, key: VoxelKey) -> Option<&Voxel> {
        let (b, i) = block_of(key);
        self.blocks.get(&b).map(|block| &block.voxels[i])
    }

    pub fn is_occupied(&self, key: VoxelKey) -> bool {
        self.voxel(key).is_some_and(|v| v.is_occupied(self.config.occupied_log_odds))
    }

    /// Every voxel that holds a surface now, with its world centre.
    pub fn occupied(&self) -> impl Iterator<Item = (VoxelKey, Point3<f64>, &Voxel)> + '_ {
        let (res, threshold) = (self.config.voxel_size_m, self.config.occupied_log_odds);
        self.blocks.iter().flat_map(move |(bkey, block)| {
            block.voxels.iter().enumerate().filter(move |(_, v)| v.is_occupied(threshold)).map(move |(i, v)| {
                let key = voxel_of(*bkey, i);
                (key, voxel_centre(key, res), v)
            })
        })
    }

    /// Every voxel ever observed (surface or carved), with its world centre.
    pub fn observed(&self) -> impl Iterator<Item = (VoxelKey, Point3<f64>, &Voxel)> + '_ {
        let res = self.config.voxel_size_m;
        self.blocks.iter().flat_map(move |(bkey, block)| {
            block.voxels.iter().enumerate().filter(|(_, v)| v.hits > 0).map(move |(i, v)| {
                let key = voxel_of(*bkey, i);
                (key, voxel_centre(key, res), v)
            })
        })
    }

    pub fn stats(&self) -> MapStats {
        let threshold = self.config.occupied_log_odds;
        let occupied_voxels = self.blocks.values().map(|b| b.voxels.iter().filter(|v| v.is_occupied(threshold)).count()).sum();
        let block_bytes = std::mem::size_of::<[Voxel; VOXELS_PER_BLOCK]>();
        let entry = std::mem::size_of::<(BlockKey, Block)>() + 1;
        MapStats { blocks: self.blocks.len(), occupied_voxels, bytes: self.blocks.len() * block_bytes + self.blocks.capacity() * entry }
    }

    pub fn blocks(&self) -> impl Iterator<Item = (&BlockKey, &Block)> {
        self.blocks.iter()
    }

    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// Removes and returns the blocks beyond the resident budget, farthest from
    /// `camera_in_world` first (they go to the store).
    pub fn evict(&mut self, camera_in_world: &Point3<f64>) -> Vec<(BlockKey, Block)> {
        let budget = self.config.max_resident_blocks;
        if self.blocks.len() <= budget {
            return Vec::new();
        }
        // Evict down to 90 % of the budget, so eviction does not run on every keyframe.
        let keep = budget - budget / 10;
        let block_m = self.config.voxel_size_m * f64::from(BLOCK_EDGE);
        let mut by_distance: Vec<(f64, BlockKey)> = self
            .blocks
            .keys()
            .map(|k| {
                let c = Vector3::new(f64::from(k[0]) + 0.5, f64::from(k[1]) + 0.5, f64::from(k[2]) + 0.5) * block_m;
                ((c - camera_in_world.coords).norm_squared(), *k)
            })
            .collect();
        by_distance.sort_unstable_by(|a, b| b.0.total_cmp(&a.0));
        let out: Vec<(BlockKey, Block)> =
            by_distance[..self.blocks.len() - keep].iter().filter_map(|(_, k)| self.blocks.remove(k).map(|b| (*k, b))).collect();
        if !out.is_empty() {
            self.version += 1;
        }
        out
    }

    /// Blocks changed since change stamp `stamp` (see [`change_stamp`](Self::change_stamp)).
    pub fn changed_since(&self, stamp: u64) -> impl Iterator<Item = (&BlockKey, &Block)> {
        self.blocks.iter().filter(move |(_, b)| b.touched > stamp)
    }

    /// Grows with every fusion and de-fusion; a block carries the stamp of its last change.
    pub fn change_stamp(&self) -> u64 {
        self.keyframes_fused
    }

    /// A map of the same configuration holding copies of these blocks (a query
    /// over resident and stored blocks together).
    pub fn with_blocks(&self, blocks: impl IntoIterator<Item = (BlockKey, Block)>) -> Self {
        let mut all = self.blocks.clone();
        for (k, b) in blocks {
            all.entry(k).or_insert(b);
        }
        Self { config: self.config.clone(), blocks: all, version: self.version, keyframes_fused: self.keyframes_fused }
    }

    /// Adds `other`'s surfaces, moved by `self_from_other` (another robot's map
    /// in this map's world): each occupied voxel of `other` lands in the cell its
    /// centre falls in here, and takes it when the cell holds no surface yet or a
    /// less observed one (fewer hits). Carving is not carried over: a fleet map of
    /// merged maps, not one fused from every keyframe.
    pub fn merge_map(&mut self, other: &VoxelMap, self_from_other: &Isometry3<f64>) {
        let res = self.config.voxel_size_m;
        let threshold = self.config.occupied_log_odds;
        for (_, centre, v) in other.occupied() {
            let key = voxel_key(&(self_from_other * centre), res);
            let (b, i) = block_of(key);
            let here = &mut self.blocks.entry(b).or_default().voxels[i];
            if !here.is_occupied(threshold) || here.hits < v.hits {
                *here = *v;
            }
        }
        self.version += 1;
    }

    /// Continues the change stamps of a restored map.
    pub fn set_change_stamp(&mut self, stamp: u64) {
        self.keyframes_fused = self.keyframes_fused.max(stamp);
    }

    /// Puts a block back (from the store). When a block was started at its place
    /// since it left, the stored one is merged into it (nothing is lost).
    pub fn restore(&mut self, key: BlockKey, block: Block) {
        match self.blocks.get_mut(&key) {
            None => {
                self.blocks.insert(key, block);
            }
            Some(newer) => newer.merge_older(&block, self.config.log_odds_min, self.config.log_odds_max),
        }
        self.version += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A map with one surface voxel at each key, seen `hits` times.
    fn surfaces(keys: &[(VoxelKey, u8)]) -> VoxelMap {
        let mut map = VoxelMap::new(MappingConfig::default()).unwrap();
        for &(key, hits) in keys {
            let (b, i) = block_of(key);
            map.blocks.entry(b).or_default().voxels[i] = Voxel { log_odds: 2.0, hits, color: [hits, 0, 0], ..Voxel::default() };
        }
        map
    }

    /// Another robot's map, one voxel over in its own world: moved back, its
    /// surfaces land on ours, the better observed voxel keeps a shared cell, and
    /// the others are added.
    #[test]
    fn a_merged_map_lands_on_ours_and_keeps_the_better_observed_voxel() {
        let mut ours = surfaces(&[([0, 0, 0], 5), ([1, 0, 0], 1)]);
        let theirs = surfaces(&[([1, 0, 0], 1), ([2, 0, 0], 9), ([3, 0, 0], 2)]);
        let res = ours.voxel_size();
        let ours_from_theirs = Isometry3::translation(-res, 0.0, 0.0);
        let version = ours.version();
        ours.merge_map(&theirs, &ours_from_theirs);
        let merged: Vec<(VoxelKey, u8)> = {
            let mut v: Vec<_> = ours.occupied().map(|(k, _, v)| (k, v.hits)).collect();
            v.sort_unstable();
            v
        };
        // Theirs [1] → [0] (5 hits here stay), [2] → [1] (9 beats 1), [3] → [2] (new).
        assert_eq!(merged, [([0, 0, 0], 5), ([1, 0, 0], 9), ([2, 0, 0], 2)]);
        assert!(ours.version() > version);
    }
    use nalgebra::{Translation3, UnitQuaternion};

    /// A keyframe kept compactly comes back to the millimetre (exactly, from a
    /// camera in millimetre units); damaged bytes are named errors.
    #[test]
    fn a_compact_fusion_input_comes_back_to_the_millimetre() {
        let cam = camera();
        let rays = CameraRays::new(&cam);
        let n = 160 * 120;
        let depth: Vec<u16> = (0..n).map(|i| if i % 7 == 0 { 0 } else { 900 + (i % 160) as u16 * 3 }).collect();
        let rgb: Vec<u8> = (0..3 * n).map(|i| (i * 31 % 251) as u8).collect();
        let exclude: Vec<u8> = (0..n).map(|i| u8::from(i % 160 < 20)).collect();
        let classes: Vec<u16> = (0..n).map(|i| (i / 160 % 5) as u16).collect();
        let map = VoxelMap::new(MappingConfig::default()).unwrap();
        let view = DepthView { depth: &depth, rgb: &rgb, exclude: Some(&exclude), classes: Some(&classes) };
        let input = map.prepare(&rays, &view).unwrap();
        assert!(input.samples.len() > 3000 && input.excluded_pixels > 0);
        let compact = input.to_compact().unwrap();
        assert_eq!(FusionInput::from_compact(&compact, &rays).unwrap(), input, "millimetre depth units: exact");
        let plain = map.prepare(&rays, &DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: None }).unwrap();
        assert_eq!(FusionInput::from_compact(&plain.to_compact().unwrap(), &rays).unwrap(), plain, "no classes");
        // A finer depth unit (TUM's 5000 per metre) comes back within half a millimetre.
        let tum = Camera::pinhole(160, 120, 130.0, 130.0, 79.5, 59.5, 5000.0);
        let tum_rays = CameraRays::new(&tum);
        let fine = map.prepare(&tum_rays, &view).unwrap();
        let back = FusionInput::from_compact(&fine.to_compact().unwrap(), &tum_rays).unwrap();
        assert_eq!(back.samples.len(), fine.samples.len());
        let worst =
            back.samples.iter().zip(&fine.samples).map(|(a, b)| (a.point_in_camera[2] - b.point_in_camera[2]).abs()).fold(0.0, f32::max);
        assert!(worst <= 0.0005 + 1e-6, "{worst}");
        let err = |bytes: &[u8]| FusionInput::from_compact(bytes, &rays).unwrap_err().to_string();
        assert_eq!(err(&compact[..3]), "corrupt map data: compact fusion input: no header");
        assert!(err(&compact[..compact.len() / 2]).starts_with("corrupt map data: compact fusion input: "));
        let mut lying = compact.clone();
        lying[..4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(err(&lying), "corrupt map data: compact fusion input: larger than a keyframe can be");
        let other = CameraRays::new(&Camera::pinhole(80, 60, 65.0, 65.0, 39.5, 29.5, 1000.0));
        assert_eq!(
            FusionInput::from_compact(&compact, &other).unwrap_err().to_string(),
            "corrupt map data: compact fusion input: a pixel outside the camera"
        );
    }

    fn camera() -> Camera {
        Camera::pinhole(160, 120, 130.0, 130.0, 79.5, 59.5, 1000.0)
    }

    /// A fronto-parallel wall at `z` metres, and optionally a box face nearer.
    fn frame(cam: &Camera, wall_z: f64, near: Option<(f64, std::ops::Range<usize>)>) -> (Vec<u16>, Vec<u8>) {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut depth = vec![(wall_z * 1000.0) as u16; w * h];
        if let Some((z, cols)) = near {
            for y in 40..80 {
                for x in cols.clone() {
                    depth[y * w + x] = (z * 1000.0) as u16;
                }
            }
        }
        (depth, vec![128; w * h * 3])
    }

    #[test]
    fn a_wall_is_fused_once_per_voxel_per_keyframe() {
        let cam = camera();
        let rays = CameraRays::new(&cam);
        let mut map = VoxelMap::new(MappingConfig::default()).unwrap();
        // At 0.6 m a pixel is 4.6 mm: several samples per 2 cm voxel.
        let (depth, rgb) = frame(&cam, 0.6, None);
        let input = map.prepare(&rays, &DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: None }).unwrap();
        let stats = map.integrate(&rays, &input, &Isometry3::identity());
        assert_eq!(stats.samples, 80 * 60);
        assert!(stats.voxels_hit > 0 && stats.voxels_hit < stats.samples);
        // Every occupied voxel sits on the wall plane and got exactly one hit.
        let mut n = 0;
        for (_, centre, v) in map.occupied() {
            assert!((centre.z - 0.6).abs() <= 0.02, "voxel at z {}", centre.z);
            assert_eq!(v.hits, 1);
            assert!((v.log_odds - 0.85).abs() < 1e-6);
            n += 1;
        }
        assert_eq!(n, stats.voxels_hit);
        assert_eq!(map.stats().occupied_voxels, n);
    }

    #[test]
    fn a_box_that_leaves_is_carved_and_the_wall_stays() {
        let cam = camera();
        let rays = CameraRays::new(&cam);
        let mut map = VoxelMap::new(MappingConfig::default()).unwrap();
        let pose = Isometry3::identity();
        let (with_box, rgb) = frame(&cam, 2.5, Some((1.2, 60..100)));
        for _ in 0..5 {
            let input = map.prepare(&rays, &DepthView { depth: &with_box, rgb: &rgb, exclude: None, classes: None }).unwrap();
            map.integrate(&rays, &input, &pose);
        }
        let near = |m: &VoxelMap| m.occupied().filter(|(_, c, _)| c.z < 1.5).count();
        let wall = |m: &VoxelMap| m.occupied().filter(|(_, c, _)| c.z > 2.3).count();
        let box_voxels = near(&map);
        let wall_voxels = wall(&map);
        assert!(box_voxels > 50, "{box_voxels}");
        let (empty, _) = frame(&cam, 2.5, None);
        let mut carved_after = None;
        for k in 1..=8 {
            let input = map.prepare(&rays, &DepthView { depth: &empty, rgb: &rgb, exclude: None, classes: None }).unwrap();
            map.integrate(&rays, &input, &pose);
            if carved_after.is_none() && near(&map) == 0 {
                carved_after = Some(k);
            }
        }
        // Saturated at 2.5, five misses of 0.4 bring it to 0.5: not occupied.
        assert_eq!(carved_after, Some(5));
        assert!(wall(&map) >= wall_voxels, "the wall behind the box stays and grows");
    }

    #[test]
    fn excluded_pixels_never_enter_the_map_but_still_carve() {
        let cam = camera();
        let rays = CameraRays::new(&cam);
        let mut map = VoxelMap::new(MappingConfig::default()).unwrap();
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut exclude = vec![0u8; w * h];
        for y in 40..80 {
            for x in 60..100 {
                exclude[y * w + x] = 1;
            }
        }
        let pose = Isometry3::identity();
        // A person at 1.2 m, excluded: nothing of them is fused.
        let (person, rgb) = frame(&cam, 2.5, Some((1.2, 60..100)));
        let input = map.prepare(&rays, &DepthView { depth: &person, rgb: &rgb, exclude: Some(&exclude), classes: None }).unwrap();
        assert_eq!(input.excluded_pixels, 20 * 20);
        map.integrate(&rays, &input, &pose);
        assert_eq!(map.occupied().filter(|(_, c, _)| c.z < 2.0).count(), 0);
        // A static box at 0.8 m fused five times, then the (excluded) person seen
        // behind where it stood: the rays to the person prove the box gone.
        let (boxed, _) = frame(&cam, 2.5, Some((0.8, 60..100)));
        for _ in 0..5 {
            let input = map.prepare(&rays, &DepthView { depth: &boxed, rgb: &rgb, exclude: None, classes: None }).unwrap();
            map.integrate(&rays, &input, &pose);
        }
        assert!(map.occupied().filter(|(_, c, _)| c.z < 1.0).count() > 20);
        for _ in 0..5 {
            let input = map.prepare(&rays, &DepthView { depth: &person, rgb: &rgb, exclude: Some(&exclude), classes: None }).unwrap();
            map.integrate(&rays, &input, &pose);
        }
        assert_eq!(map.occupied().filter(|(_, c, _)| c.z < 2.0).count(), 0);
    }

    #[test]
    fn classes_are_voted_per_voxel_and_deintegration_undoes_hits() {
        let cam = camera();
        let rays = CameraRays::new(&cam);
        let mut map = VoxelMap::new(MappingConfig::default()).unwrap();
        let (depth, rgb) = frame(&cam, 2.0, None);
        let classes = vec![62u16; depth.len()];
        let input = map.prepare(&rays, &DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: Some(&classes) }).unwrap();
        let pose = Isometry3::from_parts(Translation3::new(0.1, 0.0, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.05, 0.0));
        map.integrate(&rays, &input, &pose);
        for (_, _, v) in map.occupied() {
            assert_eq!(v.class(), (62, 1.0));
        }
        map.deintegrate(&input, &pose);
        assert_eq!(map.stats().occupied_voxels, 0);
        assert!(map.observed().all(|(_, _, v)| v.votes_total == 0));
    }

    #[test]
    fn wrong_sizes_are_errors() {
        let cam = camera();
        let rays = CameraRays::new(&cam);
        let map = VoxelMap::new(MappingConfig::default()).unwrap();
        let err = map.prepare(&rays, &DepthView { depth: &[0; 10], rgb: &[0; 30], exclude: None, classes: None }).unwrap_err();
        assert_eq!(err.to_string(), "bad map input: depth has 10 values, expected 19200 for 160x120");
    }

    /// A keyframe starts at most `max_new_blocks_per_keyframe` blocks; the samples
    /// beyond are counted, and the blocks it may start take them as before.
    #[test]
    fn a_keyframe_starts_no_more_blocks_than_its_budget() {
        let config = MappingConfig { max_new_blocks_per_keyframe: 50, ..MappingConfig::default() };
        let block_m = config.voxel_size_m * f64::from(BLOCK_EDGE);
        let mut map = VoxelMap::new(config).unwrap();
        // 80 samples 1.5 blocks apart: one block each; two more in the first block.
        let mut samples: Vec<SurfaceSample> = (0..80)
            .map(|i| SurfaceSample {
                point_in_camera: [(f64::from(i) * 1.5 * block_m) as f32, 0.01, 1.01],
                rgb: [9, 9, 9],
                class: None,
                pixel: i,
            })
            .collect();
        samples.extend([0.05, 0.09].map(|x| SurfaceSample { point_in_camera: [x, 0.01, 1.01], rgb: [9, 9, 9], class: None, pixel: 0 }));
        let stats = map.apply_hits(&samples, &Isometry3::identity(), 1);
        assert_eq!((stats.blocks_allocated, map.block_count()), (50, 50));
        assert_eq!(stats.samples_over_block_budget, 30);
        assert_eq!(stats.voxels_hit, 52, "50 blocks' first samples and the two beside the first");
        // The next keyframe has a budget of its own, and existing blocks take any number.
        let stats = map.apply_hits(&samples, &Isometry3::identity(), 1);
        assert_eq!((stats.blocks_allocated, map.block_count(), stats.samples_over_block_budget), (30, 80, 0));
    }

    #[test]
    fn eviction_keeps_the_nearest_blocks_within_budget() {
        let cam = camera();
        let rays = CameraRays::new(&cam);
        let mut map = VoxelMap::new(MappingConfig { max_resident_blocks: 20, ..MappingConfig::default() }).unwrap();
        let (depth, rgb) = frame(&cam, 2.0, None);
        let input = map.prepare(&rays, &DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: None }).unwrap();
        map.integrate(&rays, &input, &Isometry3::identity());
        let total = map.block_count();
        assert!(total > 20);
        let out = map.evict(&Point3::new(0.0, 0.0, 2.0));
        assert_eq!(map.block_count(), 18);
        assert_eq!(out.len(), total - 18);
        let kept_max = map.blocks().map(|(k, _)| (k[0] as f64 + 0.5).hypot(k[1] as f64 + 0.5)).fold(0.0, f64::max);
        let evicted_min = out.iter().map(|(k, _)| (k[0] as f64 + 0.5).hypot(k[1] as f64 + 0.5)).fold(f64::INFINITY, f64::min);
        assert!(kept_max <= evicted_min + 1e-9);
        let occupied = map.stats().occupied_voxels;
        let (first_key, first) = (out[0].0, out[0].1.clone());
        for (k, b) in out {
            map.restore(k, b);
        }
        assert_eq!(map.block_count(), total);
        // A block restored over a newer one at its place merges into it.
        map.restore(first_key, first.clone());
        let merged = map.blocks().find(|(k, _)| **k == first_key).map(|(_, b)| b.clone()).unwrap();
        for (m, o) in merged.voxels.iter().zip(first.voxels.iter()) {
            assert_eq!(m.hits, o.hits.saturating_mul(2));
        }
        assert!(map.stats().occupied_voxels >= occupied);
    }
}
