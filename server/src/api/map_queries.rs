//! The map queries both API shells answer: tiles, legend, occupancy grid, PLY,
//! points and objects, computed from a session's [`SharedMap`] (render outside the
//! lock: the top-down index is shared per map version).

use std::collections::HashMap;
use std::hash::{Hash, Hasher};
use std::sync::{Arc, Mutex};
use stillmap_mapping::MappingError;
use stillmap_mapping::export::{Aabb, MapObject, cloud, objects, to_ply};

use nalgebra::Isometry3;
use stillmap_mapping::NO_CLASS;
use stillmap_mapping::tiles::{OccupancyGrid, TILE_PX, TopDown, class_color, encode_png_rgba};

use crate::lock;
use crate::map::{MapUnreadable, SharedMap};

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

/// Why a map query has no answer: the query (HTTP 400 / INVALID_ARGUMENT), or a
/// part of the map the store cannot give back (HTTP 503 / UNAVAILABLE: answering
/// without it would serve a map with a hole).
#[derive(Debug, thiserror::Error)]
pub enum QueryError {
    #[error(transparent)]
    Bad(#[from] BadQuery),
    #[error(transparent)]
    Unreadable(#[from] MapUnreadable),
}

impl From<MappingError> for QueryError {
    fn from(e: MappingError) -> Self {
        Self::Bad(e.into())
    }
}

impl From<QueryError> for tonic::Status {
    fn from(e: QueryError) -> Self {
        match e {
            QueryError::Bad(b) => tonic::Status::invalid_argument(b.0),
            QueryError::Unreadable(u) => tonic::Status::unavailable(u.0),
        }
    }
}

/// A rendered tile and its entity tag (changes whenever the map does).
#[derive(Debug)]
pub struct Tile {
    pub png: Vec<u8>,
    pub etag: String,
}

/// The ETag a tile of the current map version has (cheap: no rendering).
pub fn tile_etag(map: &SharedMap, z: u8, x: i64, y: i64) -> String {
    format!("\"m{}-{z}-{x}-{y}\"", lock(map).builder.map().version())
}

pub fn tile(map: &SharedMap, z: u8, x: i64, y: i64) -> Result<Tile, QueryError> {
    let (top, version) = {
        let mut m = lock(map);
        (m.top_down()?, m.builder.map().version())
    };
    let rgba = top.render(z, x, y)?;
    let png = encode_png_rgba(&rgba, TILE_PX as u32, TILE_PX as u32).map_err(|e| BadQuery(e.to_string()))?;
    Ok(Tile { png, etag: format!("\"m{version}-{z}-{x}-{y}\"") })
}

/// One legend entry: a class drawn on the tiles.
#[derive(Debug)]
pub struct LegendEntry {
    pub class: u16,
    pub name: String,
    pub color: [u8; 3],
    pub cells: usize,
}

/// The classes the tiles draw now (most cells first), plus "unlabelled".
pub fn legend(map: &SharedMap) -> Result<Vec<LegendEntry>, MapUnreadable> {
    let mut m = lock(map);
    let top = m.top_down()?;
    Ok(legend_of(&top, &m.class_names))
}

/// The legend of a top-down view whose classes are named by `class_names`.
pub fn legend_of(top: &TopDown, class_names: &[String]) -> Vec<LegendEntry> {
    top.class_counts
        .iter()
        .map(|&(class, cells)| LegendEntry {
            class,
            name: if class == NO_CLASS {
                "unlabelled".into()
            } else {
                class_names.get(usize::from(class)).cloned().unwrap_or_else(|| format!("class {class}"))
            },
            // Unlabelled surfaces are grey, shaded by height; the legend shows the middle grey.
            color: if class == NO_CLASS { [145, 145, 145] } else { class_color(class) },
            cells,
        })
        .collect()
}

pub fn occupancy(
    map: &SharedMap,
    min_height: Option<f64>,
    max_height: Option<f64>,
    resolution: Option<f64>,
) -> Result<OccupancyGrid, QueryError> {
    let m = lock(map);
    let cfg = m.builder.config();
    let grid = OccupancyGrid::build(
        &*m.full_map()?,
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
    if v.len() != 6 {
        return Err(BadQuery(format!("bbox needs 6 finite numbers min_x,min_y,min_z,max_x,max_y,max_z; got {}", v.len())));
    }
    if let Some(x) = v.iter().find(|x| !x.is_finite()) {
        return Err(BadQuery(format!("bbox needs 6 finite numbers min_x,min_y,min_z,max_x,max_y,max_z; got {x}")));
    }
    if v[0] > v[3] || v[1] > v[4] || v[2] > v[5] {
        return Err(BadQuery("bbox minimum exceeds its maximum".into()));
    }
    Ok(Aabb { min: [v[0], v[1], v[2]], max: [v[3], v[4], v[5]] })
}

pub fn ply(map: &SharedMap, session_id: &str, bbox: Option<&Aabb>) -> Result<Vec<u8>, MapUnreadable> {
    let m = lock(map);
    let up = m.map_from_world();
    let points = cloud(&*m.map_within(bbox)?, &up, bbox);
    let q = up.coords;
    let comment = format!(
        "stillmap static semantic map, session {session_id}\nmap frame: z up (gravity), origin at the first camera; map_from_world rotation xyzw {:.9} {:.9} {:.9} {:.9}\nclass 65535 = unlabelled surface",
        q.x, q.y, q.z, q.w
    );
    Ok(to_ply(&points, &m.class_names, &comment))
}

/// A fleet's map in the anchor's map frame: the fleet map fused from every merged
/// session's keyframes (`crate::fleet_map`) when it holds them all, else the
/// anchor session's map with every other merged session's surfaces moved into
/// it by its `fleet_from_session` (`VoxelMap::merge_map`).
pub struct FleetMap {
    pub map: stillmap_mapping::VoxelMap,
    pub map_from_fleet: nalgebra::UnitQuaternion<f64>,
    pub class_names: Vec<String>,
    /// The anchor's occupancy defaults: lowest and highest height, resolution.
    pub occupancy: (f64, f64, f64),
    /// Whether it is the fused fleet map (not the merge of the sessions' maps).
    pub fused: bool,
}

/// What a fleet map is built from: the merged sessions' maps (session id, map,
/// `fleet_from_session`), the anchor's first, and the fleet's fused map (settle
/// it with [`FleetParts::drop_incomplete_fused`] before building or tagging).
pub struct FleetParts {
    pub maps: Vec<(String, SharedMap, Isometry3<f64>)>,
    pub fused: Option<Arc<crate::fleet_map::FleetMapHandle>>,
}

impl FleetParts {
    /// Keeps the fused map only when every keyframe of every merged session's map
    /// is fused in it, once for the tag and the map built from these parts (it
    /// locks each map: call it off the runtime).
    pub fn drop_incomplete_fused(&mut self) {
        let complete = |state: &crate::fleet_map::FleetMapHandle| {
            self.maps.iter().all(|(id, map, _)| {
                let keyframes = lock(map).builder.keyframes();
                keyframes > 0 && lock(&state.state).fused(id) == keyframes
            })
        };
        if self.fused.as_deref().is_some_and(|state| !complete(state)) {
            self.fused = None;
        }
    }
}

/// Builds the fleet map from its parts (`None` without an anchor).
pub fn fleet_map(parts: &FleetParts) -> Result<Option<FleetMap>, MapUnreadable> {
    let Some((_, anchor, _)) = parts.maps.first() else { return Ok(None) };
    let fused = parts.fused.as_ref();
    let mut fleet = {
        let m = lock(anchor);
        let cfg = m.builder.config();
        let map = match fused {
            Some(fused) => lock(&fused.state).map().clone(),
            None => m.full_map()?.into_owned(),
        };
        FleetMap {
            map,
            map_from_fleet: m.map_from_world(),
            class_names: m.class_names.clone(),
            occupancy: (cfg.occupancy_min_height_m, cfg.occupancy_max_height_m, cfg.occupancy_resolution_m),
            fused: fused.is_some(),
        }
    };
    if fused.is_none() {
        for (_, map, fleet_from_session) in &parts.maps[1..] {
            let other = lock(map).full_map()?.into_owned();
            fleet.map.merge_map(&other, fleet_from_session);
        }
    }
    Ok(Some(fleet))
}

/// The fleet map as one PLY in the anchor's map frame.
pub fn fleet_ply(fleet: &FleetMap, name: &str, sessions: usize) -> Vec<u8> {
    let points = cloud(&fleet.map, &fleet.map_from_fleet, None);
    let q = fleet.map_from_fleet.coords;
    let comment = format!(
        "stillmap fleet map {name}: {sessions} sessions merged, {}\nmap frame: the anchor session's (z up, origin at its first camera); map_from_fleet rotation xyzw {:.9} {:.9} {:.9} {:.9}\nclass 65535 = unlabelled surface",
        if fleet.fused { "fused from their keyframes in the fleet frame" } else { "their maps' surfaces merged" },
        q.x,
        q.y,
        q.z,
        q.w
    );
    to_ply(&points, &fleet.class_names, &comment)
}

/// The fleet map's occupancy grid (the anchor's defaults where a parameter is absent).
pub fn fleet_occupancy(
    fleet: &FleetMap,
    min_height: Option<f64>,
    max_height: Option<f64>,
    resolution: Option<f64>,
) -> Result<OccupancyGrid, BadQuery> {
    let (lo, hi, res) = fleet.occupancy;
    Ok(OccupancyGrid::build(
        &fleet.map,
        &fleet.map_from_fleet,
        min_height.unwrap_or(lo),
        max_height.unwrap_or(hi),
        resolution.unwrap_or(res),
    )?)
}

/// A fleet map's top-down view (tiles and legend), in the anchor's map frame.
pub struct FleetTop {
    pub top: TopDown,
    pub class_names: Vec<String>,
    /// What it was built from ([`fleet_tag`]): the tiles' ETag.
    pub tag: u64,
}

/// The latest top-down view of each fleet, rebuilt when one of its parts changed
/// (a map fused a keyframe, a merge moved, the anchor's up changed); one build at
/// a time, so a browser asking for a screenful of tiles builds the fleet map once.
#[derive(Default)]
pub struct FleetTops {
    built: Mutex<HashMap<String, Arc<FleetTop>>>,
    building: Mutex<()>,
}

/// Identifies the state a fleet map is built from: each part's map (which one, its
/// version and up direction), its `fleet_from_session`, and the fused map's version.
pub fn fleet_tag(parts: &FleetParts) -> u64 {
    let mut h = std::hash::DefaultHasher::new();
    for (_, map, fleet_from_session) in &parts.maps {
        (Arc::as_ptr(map) as usize).hash(&mut h);
        let (version, up) = {
            let m = lock(map);
            (m.builder.map().version(), m.map_from_world())
        };
        version.hash(&mut h);
        up.coords.iter().chain(fleet_from_session.to_homogeneous().iter()).for_each(|v| v.to_bits().hash(&mut h));
    }
    if let Some(fused) = &parts.fused {
        (Arc::as_ptr(fused) as usize).hash(&mut h);
        lock(&fused.state).map().version().hash(&mut h);
    }
    h.finish()
}

impl FleetTops {
    /// Fleet `name`'s top-down view of `parts` in the state `tag` ([`fleet_tag`]; see
    /// [`fleet_map`]), from the cache when nothing changed since it was built;
    /// `None` when there is no anchor map.
    pub fn get(&self, name: &str, parts: &FleetParts, tag: u64) -> Result<Option<Arc<FleetTop>>, MapUnreadable> {
        let cached = || lock(&self.built).get(name).filter(|t| t.tag == tag).cloned();
        if let Some(top) = cached() {
            return Ok(Some(top));
        }
        let _one_build = lock(&self.building);
        if let Some(top) = cached() {
            return Ok(Some(top));
        }
        let Some(fleet) = fleet_map(parts)? else { return Ok(None) };
        let top = Arc::new(FleetTop { top: TopDown::build(&fleet.map, &fleet.map_from_fleet), class_names: fleet.class_names, tag });
        lock(&self.built).insert(name.to_string(), top.clone());
        Ok(Some(top))
    }
}

/// The ETag of a fleet tile.
pub fn fleet_tile_etag(tag: u64, z: u8, x: i64, y: i64) -> String {
    format!("\"f{tag:016x}-{z}-{x}-{y}\"")
}

/// Renders a fleet tile (same scheme as a session's, in the anchor's map frame).
pub fn fleet_tile(top: &FleetTop, z: u8, x: i64, y: i64) -> Result<Tile, QueryError> {
    let rgba = top.top.render(z, x, y)?;
    let png = encode_png_rgba(&rgba, TILE_PX as u32, TILE_PX as u32).map_err(|e| BadQuery(e.to_string()))?;
    Ok(Tile { png, etag: fleet_tile_etag(top.tag, z, x, y) })
}

pub type Points = (Vec<stillmap_mapping::export::CloudPoint>, Vec<String>);

pub fn points(map: &SharedMap, bbox: Option<&Aabb>) -> Result<Points, MapUnreadable> {
    let m = lock(map);
    Ok((cloud(&*m.map_within(bbox)?, &m.map_from_world(), bbox), m.class_names.clone()))
}

pub fn map_objects(map: &SharedMap) -> Result<(Vec<MapObject>, Vec<String>), MapUnreadable> {
    let m = lock(map);
    Ok((objects(&*m.full_map()?, &m.map_from_world()), m.class_names.clone()))
}
