//! The map queries both API shells answer: tiles, legend, occupancy grid, PLY,
//! points and objects, computed from a session's [`SharedMap`] (render outside the
//! lock: the top-down index is shared per map version).


use stillmap_mapping::MappingError;
use stillmap_mapping::export::{Aabb, MapObject, cloud, objects, to_ply};
use stillmap_mapping::tiles::{OccupancyGrid, TILE_PX, class_color, encode_png_rgba};
use stillmap_mapping::NO_CLASS;

use crate::lock;
use crate::map::SharedMap;

/// Bad query parameters (HTTP 400 / INVALID_ARGUMENT).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BadQuery(pub String);

impl From<MappingError> for BadQuery {
    fn from(e: MappingError) -> Self {
        Self(match e {
            MappingError::Input(m) => m,
            other => other.to_string(),
        })
    }
}

/// A rendered tile and its entity tag (changes whenever the map does).
pub struct Tile {
    pub png: Vec<u8>,
    pub etag: String,
}

/// The ETag a tile of the current map version has (cheap: no rendering).
pub fn tile_etag(map: &SharedMap, z: u8, x: i64, y: i64) -> String {
    format!("\"m{}-{z}-{x}-{y}\"", lock(map).builder.map().version())
}

pub fn tile(map: &SharedMap, z: u8, x: i64, y: i64) -> Result<Tile, BadQuery> {
    let (top, version) = {
        let mut m = lock(map);
        (m.top_down(), m.builder.map().version())
    };
    let rgba = top.render(z, x, y)?;
    let png = encode_png_rgba(&rgba, TILE_PX as u32, TILE_PX as u32).map_err(|e| BadQuery(e.to_string()))?;
    Ok(Tile { png, etag: format!("\"m{version}-{z}-{x}-{y}\"") })
}

/// One legend entry: a class drawn on the tiles.
pub struct LegendEntry {
    pub class: u16,
    pub name: String,
    pub color: [u8; 3],
    pub cells: usize,
}

/// The classes the tiles draw now (most cells first), plus "unlabelled".
pub fn legend(map: &SharedMap) -> Vec<LegendEntry> {
    let mut m = lock(map);
    let top = m.top_down();
    top.class_counts
        .iter()
        .map(|&(class, cells)| LegendEntry {
            class,
            name: if class == NO_CLASS {
                "unlabelled".into()
            } else {
                m.class_names.get(usize::from(class)).cloned().unwrap_or_else(|| format!("class {class}"))
            },
            // Unlabelled surfaces are grey, shaded by height; the legend shows the middle grey.
            color: if class == NO_CLASS { [145, 145, 145] } else { class_color(class) },
            cells,
        })
        .collect()
}

pub fn occupancy(map: &SharedMap, min_height: Option<f64>, max_height: Option<f64>, resolution: Option<f64>) -> Result<OccupancyGrid, BadQuery> {
    let m = lock(map);
    let cfg = m.builder.config();
    let grid = OccupancyGrid::build(
        &m.full_map(),
        &m.map_from_world(),
        min_height.unwrap_or(cfg.occupancy_min_height_m),
        max_height.unwrap_or(cfg.occupancy_max_height_m),
        resolution.unwrap_or(cfg.occupancy_resolution_m),
    )?;
    Ok(grid)
}

/// Parses `min_x,min_y,min_z,max_x,max_y,max_z` (metres, map frame).
pub fn parse_bbox(text: &str) -> Result<Aabb, BadQuery> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>().map_err(|_| BadQuery(format!("bbox value {s:?} is not a number"))))
        .collect::<Result<_, _>>()?;
    if v.len() != 6 || v.iter().any(|x| !x.is_finite()) {
        return Err(BadQuery(format!("bbox needs 6 finite numbers min_x,min_y,min_z,max_x,max_y,max_z; got {}", v.len())));
    }
    if v[0] > v[3] || v[1] > v[4] || v[2] > v[5] {
        return Err(BadQuery("bbox minimum exceeds its maximum".into()));
    }
    Ok(Aabb { min: [v[0], v[1], v[2]], max: [v[3], v[4], v[5]] })
}

pub fn ply(map: &SharedMap, session_id: &str, bbox: Option<&Aabb>) -> Vec<u8> {
    let m = lock(map);
    let up = m.map_from_world();
    let points = cloud(&m.full_map(), &up, bbox);
    let q = up.coords;
    let comment = format!(
        "stillmap static semantic map, session {session_id}\nmap frame: z up (gravity), origin at the first camera; map_from_world rotation xyzw {:.9} {:.9} {:.9} {:.9}\nclass 65535 = unlabelled surface",
        q.x, q.y, q.z, q.w
    );
    to_ply(&points, &m.class_names, &comment)
}

pub fn points(map: &SharedMap, bbox: Option<&Aabb>) -> (Vec<stillmap_mapping::export::CloudPoint>, Vec<String>) {
    let m = lock(map);
    (cloud(&m.full_map(), &m.map_from_world(), bbox), m.class_names.clone())
}

pub fn map_objects(map: &SharedMap) -> (Vec<MapObject>, Vec<String>) {
    let m = lock(map);
    (objects(&m.full_map(), &m.map_from_world()), m.class_names.clone())
}
