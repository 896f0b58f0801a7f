//! Top-down views of the map in the gravity-aligned map frame: semantic tiles and
//! the ROS occupancy grid.
//!
//! **Tile scheme.** Tiles are 256×256 PNGs addressed `z/x/y`. At the finest zoom
//! `MAX_ZOOM` one pixel is one voxel; each zoom out doubles the pixel size. Tile
//! `(x, y)` at zoom `z` covers map x ∈ [x·T, (x+1)·T) and map y ∈ (−(y+1)·T, −y·T]
//! with `T = 256 · voxel · 2^(MAX_ZOOM − z)`: x grows east (map +x), y grows south
//! (map −y), as in slippy maps, and tile (0, 0)'s top-left corner is the map
//! origin (the first camera's centre); indices may be negative. Each pixel shows
//! the highest surface under it (up to `tiles_max_height_m`): its class colour
//! when the class is confident, grey shaded by height when not (walls, floors:
//! surfaces no COCO class covers), transparent where nothing is known.

use nalgebra::UnitQuaternion;
use rustc_hash::FxHashMap;

use crate::MappingError;
use crate::map::VoxelMap;
use crate::voxel::NO_CLASS;

pub const TILE_PX: usize = 256;
/// Zoom levels 0 (coarsest) ..= MAX_ZOOM (one voxel per pixel).
pub const MAX_ZOOM: u8 = 5;
/// Cells per chunk edge of the top-down index.
const CHUNK: i32 = 64;
/// Largest occupancy grid built, in cells (64 MiB: a 2 km square at 25 cm, 160 m at 2 cm).
pub const MAX_GRID_CELLS: usize = 1 << 26;
/// Tile indices beyond this are refused (±2²⁰ tiles is far beyond any building).
const MAX_TILE_INDEX: i64 = 1 << 20;

/// A distinct, stable colour per class id (golden-angle hues).
pub fn class_color(class: u16) -> [u8; 3] {
    let hue = (f64::from(class) * 137.508).rem_euclid(360.0);
    hsv(hue, 0.7, 0.95)
}

fn hsv(h: f64, s: f64, v: f64) -> [u8; 3] {
    let c = v * s;
    let x = c * (1.0 - ((h / 60.0).rem_euclid(2.0) - 1.0).abs());
    let (r, g, b) = match (h / 60.0) as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [((r + m) * 255.0) as u8, ((g + m) * 255.0) as u8, ((b + m) * 255.0) as u8]
}

/// Grey of an unlabelled surface, brighter higher up (relative to the map origin).
fn height_grey(height_m: f32) -> [u8; 3] {
    let t = ((height_m + 1.5) / 2.5).clamp(0.0, 1.0);
    let g = (70.0 + 150.0 * t) as u8;
    [g, g, g]
}

#[derive(Debug, Clone, Copy)]
struct Cell {
    height: f32,
    /// `NO_CLASS` when the winning class is not confident.
    class: u16,
}

/// The highest surface per map-frame column at voxel resolution, in 64×64 chunks.
pub struct TopDown {
    voxel_size: f64,
    chunks: FxHashMap<[i32; 2], Box<[Option<Cell>]>>,
    /// Voxels per class over the columns (the legend).
    pub class_counts: Vec<(u16, usize)>,
    pub map_version: u64,
}

impl TopDown {
    pub fn build(map: &VoxelMap, map_from_world: &UnitQuaternion<f64>) -> Self {
        let cfg = map.config();
        let res = cfg.voxel_size_m;
        let max_h = cfg.tiles_max_height_m;
        let mut chunks: FxHashMap<[i32; 2], Box<[Option<Cell>]>> = FxHashMap::default();
        for (_, centre, v) in map.occupied() {
            let p = map_from_world * centre;
            if p.z > max_h {
                continue;
            }
            let (cx, cy) = ((p.x / res).floor() as i32, (p.y / res).floor() as i32);
            let chunk = chunks
                .entry([cx.div_euclid(CHUNK), cy.div_euclid(CHUNK)])
                .or_insert_with(|| vec![None; (CHUNK * CHUNK) as usize].into_boxed_slice());
            let slot = &mut chunk[(cy.rem_euclid(CHUNK) * CHUNK + cx.rem_euclid(CHUNK)) as usize];
            let (class, confidence) = v.class();
            let class = if confidence >= cfg.objects_min_confidence { class } else { NO_CLASS };
            if slot.is_none_or(|c| c.height < p.z as f32) {
                *slot = Some(Cell { height: p.z as f32, class });
            }
        }
        let mut counts: FxHashMap<u16, usize> = FxHashMap::default();
        for chunk in chunks.values() {
            for c in chunk.iter().flatten() {
                *counts.entry(c.class).or_default() += 1;
            }
        }
        let mut class_counts: Vec<(u16, usize)> = counts.into_iter().collect();
        class_counts.sort_unstable_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        Self { voxel_size: res, chunks, class_counts, map_version: map.version() }
    }

    /// Map-frame bounds (min x, min y, max x, max y) of everything drawn, if anything.
    pub fn bounds(&self) -> Option<[f64; 4]> {
        let mut b: Option<[f64; 4]> = None;
        let span = f64::from(CHUNK) * self.voxel_size;
        for k in self.chunks.keys() {
            let (x0, y0) = (f64::from(k[0]) * span, f64::from(k[1]) * span);
            let e = b.get_or_insert([x0, y0, x0 + span, y0 + span]);
            *e = [e[0].min(x0), e[1].min(y0), e[2].max(x0 + span), e[3].max(y0 + span)];
        }
        b
    }

    /// Metres covered by one tile at `zoom`.
    pub fn tile_span_m(&self, zoom: u8) -> f64 {
        TILE_PX as f64 * self.voxel_size * f64::from(1u32 << (MAX_ZOOM - zoom.min(MAX_ZOOM)))
    }

    /// Renders tile `z/x/y` as RGBA8 (256×256×4, rows top = north).
    pub fn render(&self, zoom: u8, x: i64, y: i64) -> Result<Vec<u8>, MappingError> {
        if zoom > MAX_ZOOM {
            return Err(MappingError::Input(format!("zoom {zoom} is out of range 0..={MAX_ZOOM}")));
        }
        // `unsigned_abs`: i64::MIN has no `abs`.
        if x.unsigned_abs() > MAX_TILE_INDEX.unsigned_abs() || y.unsigned_abs() > MAX_TILE_INDEX.unsigned_abs() {
            return Err(MappingError::Input(format!("tile index ({x}, {y}) is out of range ±{MAX_TILE_INDEX}")));
        }
        let k = 1i64 << (MAX_ZOOM - zoom); // cells per pixel edge
        let side = TILE_PX as i64 * k; // cells per tile edge
        // Cell columns [x·side, (x+1)·side); cell rows: map y from −y·side − 1 down to −(y+1)·side.
        let (cx0, cx1) = (x * side, (x + 1) * side);
        let (cy0, cy1) = (-(y + 1) * side, -y * side); // [cy0, cy1)
        let mut best: Vec<Option<Cell>> = vec![None; TILE_PX * TILE_PX];
        let chunk = i64::from(CHUNK);
        for kx in cx0.div_euclid(chunk)..=(cx1 - 1).div_euclid(chunk) {
            for ky in cy0.div_euclid(chunk)..=(cy1 - 1).div_euclid(chunk) {
                let Some(cells) = self.chunks.get(&[kx as i32, ky as i32]) else { continue };
                for (i, cell) in cells.iter().enumerate() {
                    let Some(cell) = cell else { continue };
                    let cx = kx * chunk + (i as i64 % chunk);
                    let cy = ky * chunk + (i as i64 / chunk);
                    if cx < cx0 || cx >= cx1 || cy < cy0 || cy >= cy1 {
                        continue;
                    }
                    let px = ((cx - cx0) / k) as usize;
                    let py = ((cy1 - 1 - cy) / k) as usize;
                    let slot = &mut best[py * TILE_PX + px];
                    if slot.is_none_or(|b| b.height < cell.height) {
                        *slot = Some(*cell);
                    }
                }
            }
        }
        let mut rgba = vec![0u8; TILE_PX * TILE_PX * 4];
        for (px, cell) in rgba.chunks_exact_mut(4).zip(&best) {
            if let Some(c) = cell {
                let rgb = if c.class == NO_CLASS { height_grey(c.height) } else { class_color(c.class) };
                px.copy_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
            }
        }
        Ok(rgba)
    }
}

/// Encodes RGBA8 as PNG.
pub fn encode_png_rgba(rgba: &[u8], width: u32, height: u32) -> Result<Vec<u8>, MappingError> {
    encode_png(rgba, width, height, png::ColorType::Rgba)
}

fn encode_png(data: &[u8], width: u32, height: u32, color: png::ColorType) -> Result<Vec<u8>, MappingError> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, width, height);
    enc.set_color(color);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_compression(png::Compression::Fast);
    let mut w = enc.write_header().map_err(|e| MappingError::Encode(e.to_string()))?;
    w.write_image_data(data).map_err(|e| MappingError::Encode(e.to_string()))?;
    w.finish().map_err(|e| MappingError::Encode(e.to_string()))?;
    Ok(out)
}

/// ROS map_server cell values (trinary, `negate: 0`).
pub const PGM_OCCUPIED: u8 = 0;
pub const PGM_FREE: u8 = 254;
pub const PGM_UNKNOWN: u8 = 205;

/// A 2D occupancy grid for a height band, in the map frame.
#[derive(Debug, Clone, PartialEq)]
pub struct OccupancyGrid {
    pub resolution_m: f64,
    /// Map-frame position of the lower-left corner of cell (0, height−1) (ROS `origin`).
    pub origin_m: [f64; 2],
    pub width: usize,
    pub height: usize,
    /// Row-major, first row = north (as the PGM stores it).
    pub cells: Vec<u8>,
}

impl OccupancyGrid {
    /// Occupied: a surface within [min_height, max_height]. Free: no surface in the
    /// band, and either a voxel in the band was seen and carved free, or a surface
    /// below the band (the floor) was seen. Unknown otherwise.
    /// (Comparisons are negated so that NaN fails them too.)
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    pub fn build(
        map: &VoxelMap,
        map_from_world: &UnitQuaternion<f64>,
        min_height_m: f64,
        max_height_m: f64,
        resolution_m: f64,
    ) -> Result<Self, MappingError> {
        if !(max_height_m > min_height_m) {
            return Err(MappingError::Input(format!("height band [{min_height_m}, {max_height_m}] is empty")));
        }
        if !(resolution_m >= map.voxel_size() && resolution_m <= 1.0) {
            return Err(MappingError::Input(format!("resolution {resolution_m} m is outside [{}, 1] m", map.voxel_size())));
        }
        let threshold = map.config().occupied_log_odds;
        // 0 = unknown, 1 = free evidence, 2 = occupied.
        let mut cells: FxHashMap<[i64; 2], u8> = FxHashMap::default();
        for (_, centre, v) in map.observed() {
            let p = map_from_world * centre;
            let key = [(p.x / resolution_m).floor() as i64, (p.y / resolution_m).floor() as i64];
            let occupied = v.is_occupied(threshold);
            let state = if p.z >= min_height_m && p.z <= max_height_m {
                if occupied { 2 } else { 1 }
            } else if p.z < min_height_m && occupied {
                1
            } else {
                continue;
            };
            let e = cells.entry(key).or_insert(0);
            *e = (*e).max(state);
        }
        if cells.is_empty() {
            return Ok(Self { resolution_m, origin_m: [0.0, 0.0], width: 0, height: 0, cells: Vec::new() });
        }
        let (mut x0, mut y0, mut x1, mut y1) = (i64::MAX, i64::MAX, i64::MIN, i64::MIN);
        for k in cells.keys() {
            (x0, y0, x1, y1) = (x0.min(k[0]), y0.min(k[1]), x1.max(k[0]), y1.max(k[1]));
        }
        let (width, height) = (x1 - x0 + 1, y1 - y0 + 1);
        // Sized from the map's extent, so checked before allocating (a map spread
        // over kilometres must not take the process down).
        if width.saturating_mul(height) > MAX_GRID_CELLS as i64 {
            return Err(MappingError::Input(format!(
                "an occupancy grid of {width}x{height} cells at {resolution_m} m is over the limit of {MAX_GRID_CELLS} cells: ask for a coarser resolution"
            )));
        }
        let (width, height) = (width as usize, height as usize);
        let mut out = vec![PGM_UNKNOWN; width * height];
        for (k, s) in cells {
            let (col, row) = ((k[0] - x0) as usize, (y1 - k[1]) as usize);
            out[row * width + col] = if s == 2 { PGM_OCCUPIED } else { PGM_FREE };
        }
        Ok(Self { resolution_m, origin_m: [x0 as f64 * resolution_m, y0 as f64 * resolution_m], width, height, cells: out })
    }

    /// Binary PGM (P5), as map_server reads it.
    pub fn to_pgm(&self) -> Vec<u8> {
        let mut out =
            format!("P5\n# stillmap occupancy grid, {} m/cell\n{} {}\n255\n", self.resolution_m, self.width, self.height).into_bytes();
        out.extend_from_slice(&self.cells);
        out
    }

    /// map_server YAML; `image` names the PGM file beside it.
    pub fn to_yaml(&self, image: &str) -> String {
        format!(
            "image: {image}\nresolution: {}\norigin: [{}, {}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\nmode: trinary\n",
            self.resolution_m, self.origin_m[0], self.origin_m[1]
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn class_colours_are_distinct_for_coco() {
        let mut seen = std::collections::HashSet::new();
        for c in 0..80u16 {
            assert!(seen.insert(class_color(c)), "class {c} repeats a colour");
        }
    }

    #[test]
    fn a_tile_index_out_of_range_is_refused_even_at_the_integer_limits() {
        let map = VoxelMap::new(crate::MappingConfig::default()).unwrap();
        let top = TopDown::build(&map, &UnitQuaternion::identity());
        for (x, y) in [(i64::MIN, 0), (0, i64::MIN), (i64::MAX, 0), (MAX_TILE_INDEX + 1, 0), (0, -MAX_TILE_INDEX - 1)] {
            let e = top.render(0, x, y).expect_err("out of range").to_string();
            assert!(e.contains(&format!("tile index ({x}, {y}) is out of range ±1048576")), "{e}");
        }
        assert_eq!(top.render(0, -MAX_TILE_INDEX, MAX_TILE_INDEX).expect("in range").len(), TILE_PX * TILE_PX * 4);
    }

    #[test]
    fn an_occupancy_grid_over_the_cell_limit_is_refused_before_allocating() {
        let mut map = VoxelMap::new(crate::MappingConfig::default()).unwrap();
        let mut block = crate::voxel::Block::default();
        block.voxels[0].log_odds = 3.0;
        block.voxels[0].hits = 5;
        // Two surfaces 2 × 2¹⁹ blocks (2 × 84 km) apart, both at floor height.
        let far = crate::voxel::MAX_BLOCK_INDEX / 2;
        map.restore([-far, -far, 0], block.clone());
        map.restore([far, far, 0], block);
        let up = UnitQuaternion::identity();
        let e = OccupancyGrid::build(&map, &up, -1.0, 1.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("cells at 1 m is over the limit of 67108864 cells: ask for a coarser resolution"), "{e}");
    }
}
