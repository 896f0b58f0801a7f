//! A session's static semantic map: the [`MapBuilder`] with its class names, the
//! cached top-down index, and its persistence to the store (commits, evicted
//! blocks read back).
//!
//! The map sits behind a mutex shared by the session's map lane (which fuses,
//! [`crate::pipeline::fuse`]) and the query shells ([`crate::api::map_queries`]);
//! queries copy what they need (the top-down index is built once per map version
//! and shared) and render outside the lock.

use std::borrow::Cow;
use std::sync::{Arc, Mutex};

use rustc_hash::FxHashSet;
use stillmap_mapping::VoxelMap;
use stillmap_mapping::export::Aabb;
use stillmap_mapping::voxel::{BLOCK_EDGE, Block, BlockKey};

use nalgebra::{UnitQuaternion, Vector3};
use stillmap_mapping::tiles::TopDown;
use stillmap_mapping::{MapBuilder, MappingConfig, MappingError, UpSource};
use stillmap_proto::pb;

use crate::convert::camera_of;
use crate::lock;
use crate::store::{Commit, KeyframeRecord, SessionMeta, Store, StoreError};

/// Part of a map cannot be read back from the store (HTTP 503, gRPC UNAVAILABLE).
#[derive(Debug, Clone, thiserror::Error)]
#[error("{0}")]
pub struct MapUnreadable(pub String);

pub struct SessionMap {
    pub(crate) builder: MapBuilder,
    pub(crate) class_names: Vec<String>,
    top: Option<Arc<TopDown>>,
    persistence: Option<Persistence>,
    /// Occupied voxels in memory at a map version (the dashboard's summary).
    occupied_cache: Option<(u64, usize)>,
    /// The newest keyframe images (`session.keyframe_images`), for the Foxglove export.
    images: std::collections::VecDeque<KeyframeImage>,
}

/// A keyframe's colour with the pixels perception kept out of the map tinted, JPEG.
#[derive(Debug, Clone)]
pub struct KeyframeImage {
    pub id: u64,
    pub time_ns: u64,
    pub jpeg: Vec<u8>,
}

/// Where the map is committed, and what the last commit covered.
struct Persistence {
    store: Arc<Store>,
    session_id: String,
    meta: SessionMeta,
    /// Poses of the trajectory already committed.
    committed_poses: usize,
    /// Where the next pose is stored (`Commit::first_pose`).
    next_pose_place: u64,
    /// The map's change stamp at the last commit.
    committed_stamp: u64,
    /// Blocks evicted to the store (not in memory).
    cold: FxHashSet<BlockKey>,
    /// Keyframes whose commit failed, for the next one (the newest
    /// `MAX_PENDING_KEYFRAMES`; older ones lose only their place-recognition record).
    pending: Vec<KeyframeRecord>,
    /// The session's camera while the store has not recorded the session yet.
    unrecorded_camera: Option<pb::CameraInfo>,
}

/// Keyframe records kept for the next commit while the store fails (about 45 KB each).
const MAX_PENDING_KEYFRAMES: usize = 256;

/// A session's map, shared by its worker and the queries.
pub type SharedMap = Arc<Mutex<SessionMap>>;

/// One map's description (the info endpoint and the dashboard).
#[derive(Debug, Clone)]
pub struct MapInfo {
    pub voxel_size_m: f64,
    pub keyframes: u64,
    pub refused_keyframes: u64,
    /// Keyframe samples taken back out because perception later found them moving.
    pub retracted_samples: u64,
    pub blocks: usize,
    pub occupied_voxels: usize,
    pub bytes: usize,
    pub version: u64,
    /// Keyframes in the store (`None`: no store).
    pub committed_keyframes: Option<u64>,
    /// Blocks evicted to the store (not in memory).
    pub evicted_blocks: usize,
    pub up: Option<(UnitQuaternion<f64>, UpSource)>,
    /// Map-frame bounds (min x, min y, max x, max y) of what the tiles draw.
    pub bounds: Option<[f64; 4]>,
}

impl SessionMap {
    pub fn new(camera: &pb::CameraInfo, config: MappingConfig, class_names: Vec<String>) -> Result<SharedMap, MappingError> {
        let builder = MapBuilder::new(&camera_of(camera), config)?;
        Ok(Arc::new(Mutex::new(Self {
            builder,
            class_names,
            top: None,
            persistence: None,
            occupied_cache: None,
            images: std::collections::VecDeque::new(),
        })))
    }

    /// Keeps `image`, and the `keep - 1` newest before it.
    pub fn keep_image(&mut self, image: KeyframeImage, keep: usize) {
        self.images.push_back(image);
        while self.images.len() > keep {
            self.images.pop_front();
        }
    }

    /// The keyframe images kept, oldest first.
    pub fn images(&self) -> Vec<KeyframeImage> {
        self.images.iter().cloned().collect()
    }

    /// Commits this map to `store` from now on (blocks beyond the memory budget
    /// go there too). `meta` describes the session.
    pub fn attach_store(&mut self, store: Arc<Store>, session_id: &str, meta: SessionMeta) {
        self.builder.enable_eviction();
        self.persistence = Some(Persistence {
            store,
            session_id: session_id.to_string(),
            meta,
            committed_poses: 0,
            next_pose_place: 0,
            committed_stamp: 0,
            cold: FxHashSet::default(),
            pending: Vec::new(),
            unrecorded_camera: None,
        });
    }

    /// As [`attach_store`](Self::attach_store) for a session the store failed to
    /// record: the first commit that goes through records it (its camera with it).
    pub fn attach_store_unrecorded(&mut self, store: Arc<Store>, session_id: &str, meta: SessionMeta, camera: pb::CameraInfo) {
        self.attach_store(store, session_id, meta);
        if let Some(p) = &mut self.persistence {
            p.unrecorded_camera = Some(camera);
        }
    }

    /// A map restored from the store: its blocks, keyframe count and map frame.
    pub fn restore(
        &mut self,
        blocks: Vec<(BlockKey, Block)>,
        meta: &SessionMeta,
        poses: usize,
        next_pose_place: u64,
        last_camera: Option<nalgebra::Point3<f64>>,
    ) {
        for (k, b) in blocks {
            self.builder.restore_block(k, b);
        }
        self.builder.note_restored(meta.keyframes, meta.map_stamp);
        if let (Some(up), Some(source)) = (meta.up_in_world, meta.up_source.as_deref())
            && let Some(up) = nalgebra::Unit::try_new(Vector3::from(up), 1e-9)
        {
            let source = UpSource::from_label(source).unwrap_or(UpSource::Config);
            self.builder.freeze_up(up, source);
        }
        let evicted = self.builder.evict_now(&last_camera.unwrap_or_else(nalgebra::Point3::origin));
        if let Some(p) = &mut self.persistence {
            // Already in the store: just forget them here.
            p.cold.extend(evicted.into_iter().map(|(k, _)| k));
            p.committed_poses = poses;
            p.next_pose_place = next_pose_place;
            p.committed_stamp = meta.map_stamp;
            p.meta = meta.clone();
        }
    }

    /// Whether anything is not committed yet: poses beyond `trajectory_len` already
    /// committed, map changes, keyframe records, or the session itself.
    pub fn uncommitted(&self, trajectory_len: usize) -> bool {
        self.persistence.as_ref().is_some_and(|p| {
            p.committed_poses < trajectory_len
                || p.committed_stamp != self.builder.map().change_stamp()
                || !p.pending.is_empty()
                || p.unrecorded_camera.is_some()
        })
    }

    /// Whether the map commits to a store.
    pub fn has_store(&self) -> bool {
        self.persistence.is_some()
    }

    /// Poses of the trajectory the store holds (0 without a store).
    pub fn committed_poses(&self) -> usize {
        self.persistence.as_ref().map_or(0, |p| p.committed_poses)
    }

    /// The store this map commits to, and the session's id there.
    pub(crate) fn stored_as(&self) -> Option<(Arc<Store>, String)> {
        self.persistence.as_ref().map(|p| (p.store.clone(), p.session_id.clone()))
    }

    /// Keyframes covered by the last commit (what a crash keeps).
    pub fn committed_keyframes(&self) -> Option<u64> {
        self.persistence.as_ref().map(|p| p.meta.keyframes)
    }

    /// Commits the poses since the last commit (`poses` are the trajectory's from
    /// index `first` on: those before left memory, committed), the keyframe,
    /// changed and evicted blocks. On failure the evicted blocks come back into
    /// memory (nothing is lost). Returns whether there is a store (and so a
    /// commit happened).
    pub fn persist(&mut self, poses: &[pb::PoseStamped], first: usize, keyframe: Option<KeyframeRecord>) -> Result<bool, StoreError> {
        let Some(p) = &mut self.persistence else { return Ok(false) };
        // Kept for the next commit whatever happens below.
        p.pending.extend(keyframe);
        if p.pending.len() > MAX_PENDING_KEYFRAMES {
            let dropped = p.pending.len() - MAX_PENDING_KEYFRAMES;
            p.pending.drain(..dropped);
            tracing::warn!(session = %p.session_id, dropped, "the store keeps failing: the oldest uncommitted keyframe records are dropped (their map data stays)");
        }
        // A block started where an evicted one was (fusion out of the camera's
        // reach): merge the stored one in before this commit overwrites it.
        let reborn: Vec<BlockKey> =
            self.builder.map().changed_since(p.committed_stamp).map(|(k, _)| *k).filter(|k| p.cold.contains(k)).collect();
        for key in reborn {
            if let Some(block) = p.store.block(&p.session_id, key)? {
                self.builder.restore_block(key, block);
            }
            p.cold.remove(&key);
        }
        let mut evicted = self.builder.take_evicted();
        let (min, max) = (self.builder.config().log_odds_min, self.builder.config().log_odds_max);
        // Started where an evicted block was and evicted again at once: merge the
        // stored one in before this commit overwrites it. All read first, so that
        // a failed read puts every evicted block back in memory untouched.
        let mut stored = Vec::new();
        for (i, (key, _)) in evicted.iter().enumerate() {
            if !p.cold.contains(key) {
                continue;
            }
            match p.store.block(&p.session_id, *key) {
                Ok(Some(block)) => stored.push((i, block)),
                Ok(None) => {}
                Err(e) => {
                    for (k, b) in evicted {
                        self.builder.restore_block(k, b);
                    }
                    return Err(e);
                }
            }
        }
        // Keys whose stored block is merged into memory now: no longer only in the
        // store, whether this commit lands or not.
        let mut merged = Vec::with_capacity(stored.len());
        for (i, block) in stored {
            evicted[i].1.merge_older(&block, min, max);
            merged.push(evicted[i].0);
        }
        // What this commit would make true; `p.meta` keeps what the store holds
        // until it has (committed_keyframes must not count a failed commit's).
        let mut meta = p.meta.clone();
        meta.keyframes = self.builder.keyframes();
        meta.map_stamp = self.builder.map().change_stamp();
        if let Some((up, source)) = self.builder.up_in_world() {
            meta.up_in_world = Some([up.x, up.y, up.z]);
            meta.up_source = Some(source.label().to_string());
        }
        let since = p.committed_stamp;
        let commit = Commit {
            session_id: &p.session_id,
            meta: &meta,
            poses: poses.get(p.committed_poses.saturating_sub(first)..).unwrap_or_default(),
            first_pose: p.next_pose_place,
            keyframes: &p.pending,
            camera: p.unrecorded_camera.as_ref(),
            blocks: self.builder.map().changed_since(since).map(|(k, b)| (*k, b)).collect(),
            evicted: &evicted,
        };
        let new_poses = commit.poses.len() as u64;
        match p.store.commit(&commit) {
            Ok(()) => {
                p.next_pose_place += new_poses;
                p.committed_poses = first + poses.len();
                p.committed_stamp = meta.map_stamp;
                p.meta = meta;
                p.pending.clear();
                p.unrecorded_camera = None;
                p.cold.extend(evicted.into_iter().map(|(k, _)| k));
                Ok(true)
            }
            Err(e) => {
                for (k, b) in evicted {
                    self.builder.restore_block(k, b);
                }
                // Back in memory with the stored data merged in: the next commit must
                // not merge it a second time.
                for key in merged {
                    p.cold.remove(&key);
                }
                Err(e)
            }
        }
    }

    /// Brings evicted blocks within sensor range of the camera back into memory.
    pub(crate) fn restore_near(&mut self, camera_in_world: &nalgebra::Point3<f64>) {
        let Some(p) = &mut self.persistence else { return };
        if p.cold.is_empty() {
            return;
        }
        let block_m = self.builder.config().voxel_size_m * f64::from(BLOCK_EDGE);
        let reach = self.builder.reach_m() + block_m * 3f64.sqrt();
        let near: Vec<BlockKey> = p
            .cold
            .iter()
            .filter(|k| {
                let c = Vector3::new(f64::from(k[0]) + 0.5, f64::from(k[1]) + 0.5, f64::from(k[2]) + 0.5) * block_m;
                (c - camera_in_world.coords).norm() <= reach
            })
            .copied()
            .collect();
        for key in near {
            match p.store.block(&p.session_id, key) {
                Ok(Some(block)) => {
                    p.cold.remove(&key);
                    self.builder.restore_block(key, block);
                }
                Ok(None) => {
                    tracing::error!(session = %p.session_id, ?key, "evicted map block missing from the store");
                    p.cold.remove(&key);
                }
                Err(e) => tracing::error!(session = %p.session_id, "cannot read an evicted map block back: {e}"),
            }
        }
    }

    /// The whole map, stored blocks included (a copy when some are evicted), or
    /// [`MapUnreadable`] when the store cannot give one of them back: a map with
    /// a hole is never answered as the map.
    pub(crate) fn full_map(&self) -> Result<Cow<'_, VoxelMap>, MapUnreadable> {
        self.map_within(None)
    }

    /// The map with the stored blocks that may hold surfaces inside `bbox` (map
    /// frame; all of them without one): a query about a box reads only the blocks
    /// around it back from the store.
    pub(crate) fn map_within(&self, bbox: Option<&Aabb>) -> Result<Cow<'_, VoxelMap>, MapUnreadable> {
        let Some(p) = self.persistence.as_ref().filter(|p| !p.cold.is_empty()) else {
            return Ok(Cow::Borrowed(self.builder.map()));
        };
        let block_m = self.builder.config().voxel_size_m * f64::from(BLOCK_EDGE);
        let map_from_world = self.map_from_world();
        let near_box = |k: &BlockKey| {
            bbox.is_none_or(|b| {
                // The block's bounding sphere against the box, in the map frame.
                let centre = map_from_world * (Vector3::new(f64::from(k[0]) + 0.5, f64::from(k[1]) + 0.5, f64::from(k[2]) + 0.5) * block_m);
                let radius = block_m * 3f64.sqrt() / 2.0;
                (0..3).all(|i| centre[i] + radius >= b.min[i] && centre[i] - radius <= b.max[i])
            })
        };
        let mut loaded: Vec<(BlockKey, Block)> = Vec::new();
        for k in p.cold.iter().filter(|k| near_box(k)) {
            let why = match p.store.block(&p.session_id, *k) {
                Ok(Some(b)) => {
                    loaded.push((*k, b));
                    continue;
                }
                Ok(None) => "missing from the store".to_string(),
                Err(e) => e.to_string(),
            };
            tracing::error!(session = %p.session_id, ?k, "cannot read a map block back: {why}");
            return Err(MapUnreadable(format!("session {}: a map block evicted to the store cannot be read back ({why})", p.session_id)));
        }
        if loaded.is_empty() {
            return Ok(Cow::Borrowed(self.builder.map()));
        }
        Ok(Cow::Owned(self.builder.map().with_blocks(loaded)))
    }

    pub fn class_names(&self) -> &[String] {
        &self.class_names
    }

    pub fn builder(&self) -> &MapBuilder {
        &self.builder
    }

    pub fn builder_mut(&mut self) -> &mut MapBuilder {
        &mut self.builder
    }

    pub(crate) fn map_from_world(&self) -> UnitQuaternion<f64> {
        self.builder.map_from_world().map_or_else(UnitQuaternion::identity, |(r, _)| r)
    }

    pub(crate) fn top_down(&mut self) -> Result<Arc<TopDown>, MapUnreadable> {
        let version = self.builder.map().version();
        match &self.top {
            Some(t) if t.map_version == version => Ok(t.clone()),
            _ => {
                let t = Arc::new(TopDown::build(&*self.full_map()?, &self.map_from_world()));
                self.top = Some(t.clone());
                Ok(t)
            }
        }
    }

    pub fn info(&mut self) -> MapInfo {
        let stats = self.builder.map().stats();
        // Unknown while a stored block cannot be read back (logged).
        let bounds = self.top_down().ok().and_then(|t| t.bounds());
        MapInfo {
            voxel_size_m: self.builder.map().voxel_size(),
            keyframes: self.builder.keyframes(),
            refused_keyframes: self.builder.refused(),
            retracted_samples: self.builder.retracted(),
            blocks: stats.blocks,
            occupied_voxels: stats.occupied_voxels,
            bytes: stats.bytes,
            version: self.builder.map().version(),
            committed_keyframes: self.committed_keyframes(),
            evicted_blocks: self.persistence.as_ref().map_or(0, |p| p.cold.len()),
            up: self.builder.map_from_world(),
            bounds,
        }
    }
}

pub fn lock_info(map: &SharedMap) -> MapInfo {
    lock(map).info()
}

/// What the dashboard's snapshot needs, without building the top-down index:
/// (version, keyframes, occupied voxels in memory).
pub fn summary(map: &SharedMap) -> (u64, u64, usize) {
    let mut m = lock(map);
    let version = m.builder.map().version();
    // Counting occupied voxels scans the map: once per map version.
    let occupied = match m.occupied_cache {
        Some((v, n)) if v == version => n,
        _ => {
            let n = m.builder.map().stats().occupied_voxels;
            m.occupied_cache = Some((version, n));
            n
        }
    };
    (version, m.builder.keyframes(), occupied)
}

#[cfg(test)]
pub(crate) mod tests {
    use std::sync::atomic::Ordering;

    use nalgebra::{Isometry3, Translation3};
    use stillmap_mapping::DepthView;

    use super::*;
    use crate::store::memory_disk::{Disk, store_on};

    /// A 64×48 pinhole camera for the tests (no encodings).
    pub(crate) fn small_camera() -> pb::CameraInfo {
        pb::CameraInfo {
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 60.0,
            cx: 32.0,
            cy: 24.0,
            depth_units_per_metre: 1000.0,
            ..Default::default()
        }
    }

    /// A stored block the store cannot give back makes every map query on the
    /// whole map an error naming it, not a map with a hole; a query about a box
    /// reads only the stored blocks around it, and is answered.
    #[test]
    fn a_stored_block_that_cannot_be_read_fails_the_query_not_the_map() {
        use crate::api::map_queries::{self as q, QueryError};
        let camera = small_camera();
        let config = MappingConfig { max_resident_blocks: 4, ..MappingConfig::default() };
        let map = SessionMap::new(&camera, config, Vec::new()).expect("map");
        let store = Arc::new(store_on(&Disk::default()));
        let meta = SessionMeta::for_tests("r");
        store.put_session("s", &meta, &camera, "").expect("session");
        let wall = {
            let mut m = lock(&map);
            m.attach_store(store.clone(), "s", meta);
            let (depth, rgb) = (vec![1000u16; 64 * 48], vec![100u8; 64 * 48 * 3]);
            let view = DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: None };
            m.builder.add_keyframe(1, &Isometry3::identity(), &view).expect("fused");
            let wall: Vec<BlockKey> = m.builder.map().blocks().map(|(k, _)| *k).collect();
            m.persist(&[], 0, None).expect("committed");
            let far = Isometry3::from_parts(Translation3::new(100.0, 0.0, 0.0), nalgebra::UnitQuaternion::identity());
            m.builder.add_keyframe(2, &far, &view).expect("fused");
            m.persist(&[], 0, None).expect("committed");
            assert!(wall.iter().all(|k| m.builder.map().blocks().all(|(b, _)| b != k)), "the wall went to the store");
            wall
        };
        let whole = q::points(&map, None).expect("every block reads back").0.len();
        store.put_raw_block("s", wall[0], b"not a block").expect("damaged");
        lock(&map).top = None;
        let unreadable = |e: QueryError| match e {
            QueryError::Unreadable(u) => u.0,
            QueryError::Bad(b) => panic!("not a bad query: {}", b.0),
        };
        let message = unreadable(q::points(&map, None).expect_err("a hole").into());
        assert!(message.starts_with("session s: a map block evicted to the store cannot be read back ("), "{message}");
        unreadable(q::ply(&map, "s", None).expect_err("a hole").into());
        unreadable(q::map_objects(&map).expect_err("a hole").into());
        unreadable(q::legend(&map).expect_err("a hole").into());
        unreadable(q::tile(&map, 0, 0, 0).expect_err("a hole"));
        unreadable(q::occupancy(&map, None, None, None).expect_err("a hole"));
        assert_eq!(lock(&map).info().bounds, None, "unknown, not the bounds of part of the map");
        // The far wall's box (map frame: x forward of the far camera, z up) reads
        // no stored block, and holds the far wall's points.
        let far_box = q::parse_bbox("90,-50,-50,110,50,50").expect("bbox");
        let (near_far, _) = q::points(&map, Some(&far_box)).expect("only blocks around the box are read");
        assert!(!near_far.is_empty() && near_far.len() < whole, "{} of {whole}", near_far.len());
    }

    /// A map restored with its next pose's place (after the last stored one, past
    /// places missing) writes its new poses there, not at the count of poses.
    #[test]
    fn new_poses_are_stored_after_the_last_stored_place() {
        let camera = small_camera();
        let map = SessionMap::new(&camera, MappingConfig::default(), Vec::new()).expect("map");
        let store = Arc::new(store_on(&Disk::default()));
        let meta = SessionMeta::for_tests("r");
        store.put_session("s", &meta, &camera, "").expect("session");
        let pose = |t: u64| pb::PoseStamped { sequence: t, capture_time_ns: t, ..Default::default() };
        let mut m = lock(&map);
        m.attach_store(store.clone(), "s", meta.clone());
        // Three poses restored (stored elsewhere at places up to 9), a fourth new.
        m.restore(Vec::new(), &meta, 3, 10, None);
        let poses: Vec<pb::PoseStamped> = (1..=4).map(pose).collect();
        assert!(m.persist(&poses, 0, None).expect("committed"));
        let mut stored = Vec::new();
        assert_eq!(store.first_poses("s", 5, |p| stored.push(p.capture_time_ns)).expect("read"), 1);
        assert_eq!((stored, store.load("s").expect("read").expect("stored").next_pose_place), (vec![4], 11));
        assert_eq!(crate::store::next_place_after(11, u64::MAX - 3), 11, "a sequence number of an older store takes no place");
    }

    /// A commit that fails after blocks that were evicted, started again and evicted
    /// again had their stored copies merged in: the next commit stores each
    /// voxel's hits once (it merged the stored copies a second time before).
    #[test]
    fn a_failed_commit_merges_no_stored_block_twice() {
        let camera = small_camera();
        let config = MappingConfig { max_resident_blocks: 4, ..MappingConfig::default() };
        let map = SessionMap::new(&camera, config, Vec::new()).expect("map");
        let disk = Disk::default();
        let store = Arc::new(store_on(&disk));
        let meta = SessionMeta::for_tests("r");
        store.put_session("s", &meta, &camera, "").expect("session");
        let mut m = lock(&map);
        m.attach_store(store.clone(), "s", meta);
        let (depth, rgb) = (vec![1000u16; 64 * 48], vec![100u8; 64 * 48 * 3]);
        let view = DepthView { depth: &depth, rgb: &rgb, exclude: None, classes: None };
        let here = Isometry3::identity();
        let far = Isometry3::from_parts(Translation3::new(100.0, 0.0, 0.0), nalgebra::UnitQuaternion::identity());
        let fuse = |m: &mut SessionMap, id: u64, pose: &Isometry3<f64>| {
            m.builder.add_keyframe(id, pose, &view).expect("fused");
        };
        // The wall here, committed; then far away, which evicts it to the store.
        fuse(&mut m, 1, &here);
        let wall: Vec<BlockKey> = m.builder.map().blocks().map(|(k, _)| *k).collect();
        assert!(!wall.is_empty());
        m.persist(&[], 0, None).expect("committed");
        fuse(&mut m, 2, &far);
        m.persist(&[], 0, None).expect("committed");
        assert!(wall.iter().all(|k| m.builder.map().blocks().all(|(b, _)| b != k)), "the wall went to the store");
        // The wall again (its blocks start anew, without the store's restore), and
        // far away again before the commit: evicted again at once.
        fuse(&mut m, 3, &here);
        fuse(&mut m, 4, &far);
        disk.full.store(true, Ordering::SeqCst);
        assert!(m.persist(&[], 0, None).is_err(), "a full disk");
        disk.full.store(false, Ordering::SeqCst);
        std::thread::sleep(std::time::Duration::from_millis(2_100));
        m.persist(&[], 0, None).expect("committed after the disk has room");
        // Every wall voxel was hit by keyframes 1 and 3: twice, not three times.
        let mut seen = 0;
        for key in &wall {
            let block = match m.builder.map().blocks().find(|(b, _)| *b == key) {
                Some((_, b)) => b.clone(),
                None => store.block("s", *key).expect("read").expect("stored"),
            };
            for v in block.voxels.iter().filter(|v| v.hits > 0) {
                assert_eq!(v.hits, 2, "block {key:?}");
                seen += 1;
            }
        }
        assert!(seen > 0);
    }
}
