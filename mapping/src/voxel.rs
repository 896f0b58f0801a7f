//! Voxels, blocks and their keys.
//!
//! The map is a hash of blocks of 8×8×8 voxels (voxblox's layout): only blocks a
//! surface was seen in exist, and a block is the unit of eviction and storage.

use nalgebra::Point3;

/// Voxels per block edge.
pub const BLOCK_EDGE: i32 = 8;
pub const VOXELS_PER_BLOCK: usize = (BLOCK_EDGE * BLOCK_EDGE * BLOCK_EDGE) as usize;
/// Class id of "no instance" (a surface the segmenter put in no instance: walls, floors).
pub const NO_CLASS: u16 = u16::MAX;
/// Class slots kept per voxel (a Misra–Gries summary: the winner is exact whenever
/// it holds more than a quarter of the votes).
pub const CLASS_SLOTS: usize = 3;

/// Integer voxel coordinates in the world frame (`floor(point / voxel_size)`).
pub type VoxelKey = [i32; 3];
/// Largest block coordinate a map holds (either sign): ±2²⁰ blocks of 8 voxels is
/// ±168 km at 2 cm voxels, far beyond any building, and keeps every voxel
/// coordinate (block × 8 + 7) well inside `i32`. Stored and imported blocks
/// beyond it are refused.
pub const MAX_BLOCK_INDEX: i32 = 1 << 20;

/// Whether a block key is within ±[`MAX_BLOCK_INDEX`].
pub fn block_in_range(key: BlockKey) -> bool {
    key.iter().all(|v| v.unsigned_abs() <= MAX_BLOCK_INDEX as u32)
}

/// Integer block coordinates (`voxel.div_euclid(BLOCK_EDGE)`).
pub type BlockKey = [i32; 3];

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ClassVote {
    pub class: u16,
    pub votes: u16,
}

/// One voxel: occupancy, colour and class evidence. 24 bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Voxel {
    /// Occupancy log-odds; 0 with `hits == 0` is unknown.
    pub log_odds: f32,
    /// Running mean colour.
    pub color: [u8; 3],
    /// Keyframes that saw a surface here (saturating; the colour's weight).
    pub hits: u8,
    pub classes: [ClassVote; CLASS_SLOTS],
    pub votes_total: u16,
}

impl Voxel {
    pub fn is_occupied(&self, threshold: f32) -> bool {
        self.hits > 0 && self.log_odds > threshold
    }

    /// The class with the most votes and its share of all votes (`NO_CLASS`, 0 when
    /// none). The share is a lower bound: votes for a fourth class decrement every slot.
    pub fn class(&self) -> (u16, f32) {
        let best = self.classes.iter().max_by_key(|c| c.votes).copied().unwrap_or_default();
        if best.votes == 0 || self.votes_total == 0 {
            return (NO_CLASS, 0.0);
        }
        (best.class, f32::from(best.votes) / f32::from(self.votes_total))
    }

    pub(crate) fn vote(&mut self, class: u16) {
        self.vote_n(class, 1);
    }

    /// `n` votes for `class` at once (weighted Misra–Gries: when every slot is
    /// taken by other classes, all lose as many votes as the weakest can give, and
    /// what is left of `n` takes the slot that emptied).
    fn vote_n(&mut self, class: u16, n: u16) {
        if n == 0 {
            return;
        }
        while u32::from(self.votes_total) + u32::from(n) > u32::from(u16::MAX) {
            for c in &mut self.classes {
                c.votes /= 2;
            }
            self.votes_total /= 2;
        }
        self.votes_total += n;
        if let Some(slot) = self.classes.iter_mut().find(|c| c.votes > 0 && c.class == class) {
            slot.votes = slot.votes.saturating_add(n);
        } else if let Some(slot) = self.classes.iter_mut().find(|c| c.votes == 0) {
            *slot = ClassVote { class, votes: n };
        } else {
            let d = self.classes.iter().map(|c| c.votes).min().unwrap_or(0).min(n);
            for c in &mut self.classes {
                c.votes -= d;
            }
            if n > d
                && let Some(slot) = self.classes.iter_mut().find(|c| c.votes == 0)
            {
                *slot = ClassVote { class, votes: n - d };
            }
        }
    }

    pub(crate) fn unvote(&mut self, class: u16) {
        if let Some(slot) = self.classes.iter_mut().find(|c| c.votes > 0 && c.class == class) {
            slot.votes -= 1;
        }
        self.votes_total = self.votes_total.saturating_sub(1);
    }

    /// Folds an older copy of this voxel into it (a stored block coming back to
    /// memory after a new block was started at its place): log-odds, hits and class
    /// votes add, colours average by hits.
    pub(crate) fn merge_older(&mut self, older: &Voxel, min: f32, max: f32) {
        if older.hits == 0 && older.log_odds == 0.0 {
            return;
        }
        let (a, b) = (u32::from(older.hits), u32::from(self.hits));
        for c in 0..3 {
            // No hits on either side: the colour stays.
            if let Some(mixed) = (u32::from(older.color[c]) * a + u32::from(self.color[c]) * b).checked_div(a + b) {
                self.color[c] = mixed as u8;
            }
        }
        self.log_odds = (self.log_odds + older.log_odds).clamp(min, max);
        self.hits = self.hits.saturating_add(older.hits);
        for c in older.classes.iter().filter(|c| c.votes > 0) {
            self.vote_n(c.class, c.votes);
        }
    }

    pub(crate) fn blend_color(&mut self, rgb: [u8; 3]) {
        let w = u32::from(self.hits.min(u8::MAX - 1));
        for (c, &n) in self.color.iter_mut().zip(&rgb) {
            *c = ((u32::from(*c) * w + u32::from(n)) / (w + 1)) as u8;
        }
    }
}

/// 8×8×8 voxels.
#[derive(Debug, Clone, PartialEq)]
pub struct Block {
    pub voxels: Box<[Voxel; VOXELS_PER_BLOCK]>,
    /// The keyframe counter when the block last changed (eviction picks old, far blocks).
    pub touched: u64,
}

impl Block {
    /// Folds an older copy of this block (from the store) into it, voxel by voxel.
    pub fn merge_older(&mut self, older: &Block, log_odds_min: f32, log_odds_max: f32) {
        for (n, o) in self.voxels.iter_mut().zip(older.voxels.iter()) {
            n.merge_older(o, log_odds_min, log_odds_max);
        }
        self.touched = self.touched.max(older.touched);
    }
}

impl Default for Block {
    fn default() -> Self {
        Self { voxels: Box::new([Voxel::default(); VOXELS_PER_BLOCK]), touched: 0 }
    }
}

pub fn block_of(voxel: VoxelKey) -> (BlockKey, usize) {
    let b = [voxel[0].div_euclid(BLOCK_EDGE), voxel[1].div_euclid(BLOCK_EDGE), voxel[2].div_euclid(BLOCK_EDGE)];
    let l = [voxel[0].rem_euclid(BLOCK_EDGE), voxel[1].rem_euclid(BLOCK_EDGE), voxel[2].rem_euclid(BLOCK_EDGE)];
    (b, ((l[2] * BLOCK_EDGE + l[1]) * BLOCK_EDGE + l[0]) as usize)
}

pub fn voxel_of(block: BlockKey, index: usize) -> VoxelKey {
    let i = index as i32;
    let l = [i % BLOCK_EDGE, (i / BLOCK_EDGE) % BLOCK_EDGE, i / (BLOCK_EDGE * BLOCK_EDGE)];
    [block[0] * BLOCK_EDGE + l[0], block[1] * BLOCK_EDGE + l[1], block[2] * BLOCK_EDGE + l[2]]
}

pub fn voxel_key(point_in_world: &Point3<f64>, voxel_size: f64) -> VoxelKey {
    [
        (point_in_world.x / voxel_size).floor() as i32,
        (point_in_world.y / voxel_size).floor() as i32,
        (point_in_world.z / voxel_size).floor() as i32,
    ]
}

pub fn voxel_centre(key: VoxelKey, voxel_size: f64) -> Point3<f64> {
    Point3::new((f64::from(key[0]) + 0.5) * voxel_size, (f64::from(key[1]) + 0.5) * voxel_size, (f64::from(key[2]) + 0.5) * voxel_size)
}

/// Largest serialised block (every voxel observed); the key is stored beside it.
pub const BLOCK_BYTES: usize = 8 + VOXELS_PER_BLOCK / 8 + VOXELS_PER_BLOCK * 24;

/// Bytes of one voxel record in the block encoding.
const VOXEL_RECORD: usize = 24;
/// The presence bitmap: one bit per voxel.
const BITMAP_BYTES: usize = VOXELS_PER_BLOCK / 8;

impl Block {
    /// A compact little-endian encoding for the store: the change stamp, a bitmap
    /// of the voxels ever observed, then 24 bytes per observed voxel (most of a
    /// block is unknown space, so this is a fraction of the 12 KiB in memory).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut bitmap = [0u8; BITMAP_BYTES];
        let mut records = Vec::with_capacity(VOXELS_PER_BLOCK / 4 * VOXEL_RECORD);
        for (i, v) in self.voxels.iter().enumerate() {
            if *v == Voxel::default() {
                continue;
            }
            bitmap[i / 8] |= 1 << (i % 8);
            records.extend_from_slice(&v.log_odds.to_le_bytes());
            records.extend_from_slice(&v.color);
            records.push(v.hits);
            for c in &v.classes {
                records.extend_from_slice(&c.class.to_le_bytes());
                records.extend_from_slice(&c.votes.to_le_bytes());
            }
            records.extend_from_slice(&v.votes_total.to_le_bytes());
            records.extend_from_slice(&[0, 0]);
        }
        let mut out = Vec::with_capacity(8 + BITMAP_BYTES + records.len());
        out.extend_from_slice(&self.touched.to_le_bytes());
        out.extend_from_slice(&bitmap);
        out.extend_from_slice(&records);
        out
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<Self, crate::MappingError> {
        let corrupt = |m: String| crate::MappingError::Corrupt(m);
        if bytes.len() < 8 + BITMAP_BYTES {
            return Err(corrupt(format!("voxel block of {} bytes, shorter than its header", bytes.len())));
        }
        let bitmap = &bytes[8..8 + BITMAP_BYTES];
        let present = bitmap.iter().map(|b| b.count_ones() as usize).sum::<usize>();
        let expected = 8 + BITMAP_BYTES + present * VOXEL_RECORD;
        if bytes.len() != expected {
            return Err(corrupt(format!("voxel block of {} bytes, expected {expected} for {present} voxels", bytes.len())));
        }
        let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
        let mut block = Block { touched: u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")), ..Block::default() };
        let mut o = 8 + BITMAP_BYTES;
        for (i, v) in block.voxels.iter_mut().enumerate() {
            if bitmap[i / 8] & (1 << (i % 8)) == 0 {
                continue;
            }
            v.log_odds = f32::from_le_bytes(bytes[o..o + 4].try_into().expect("4 bytes"));
            if !v.log_odds.is_finite() {
                return Err(corrupt("voxel block with a non-finite log-odds".into()));
            }
            v.color = [bytes[o + 4], bytes[o + 5], bytes[o + 6]];
            v.hits = bytes[o + 7];
            for (k, c) in v.classes.iter_mut().enumerate() {
                *c = ClassVote { class: u16_at(o + 8 + 4 * k), votes: u16_at(o + 10 + 4 * k) };
            }
            v.votes_total = u16_at(o + 20);
            o += VOXEL_RECORD;
        }
        Ok(block)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_round_trip_for_negative_coordinates() {
        for v in [[0, 0, 0], [-1, -1, -1], [7, 8, -9], [-8, 15, -16], [123, -456, 789]] {
            let (b, i) = block_of(v);
            assert_eq!(voxel_of(b, i), v);
        }
        assert_eq!(block_of([-1, 0, 8]).0, [-1, 0, 1]);
        assert_eq!(voxel_key(&Point3::new(-0.001, 0.019, 0.02), 0.02), [-1, 0, 1]);
    }

    #[test]
    fn class_votes_keep_the_majority() {
        let mut v = Voxel::default();
        assert_eq!(v.class(), (NO_CLASS, 0.0));
        for c in [56, 56, 3, 56, 7, 9, 56, 11, 56] {
            v.vote(c);
        }
        let (class, confidence) = v.class();
        assert_eq!(class, 56);
        // 9 arrived when all three slots were full: every slot lost a vote, so the
        // confidence is a lower bound (4 of 9 counted, 5 of 9 true).
        assert!((confidence - 4.0 / 9.0).abs() < 1e-6, "{confidence}");
        v.unvote(56);
        assert_eq!(v.votes_total, 8);
    }

    #[test]
    fn blocks_serialise_exactly_and_reject_bad_bytes() {
        let mut b = Block { touched: 42, ..Block::default() };
        b.voxels[5] = Voxel {
            log_odds: 1.25,
            color: [1, 2, 3],
            hits: 4,
            classes: [ClassVote { class: 62, votes: 9 }, ClassVote::default(), ClassVote { class: NO_CLASS, votes: 2 }],
            votes_total: 11,
        };
        let bytes = b.to_bytes();
        // Header, bitmap and the one observed voxel.
        assert_eq!(bytes.len(), 8 + 64 + 24);
        assert_eq!(Block::from_bytes(&bytes).unwrap(), b);
        let err = Block::from_bytes(&bytes[..90]).unwrap_err().to_string();
        assert_eq!(err, "corrupt map data: voxel block of 90 bytes, expected 96 for 1 voxels");
        let full = Block { voxels: Box::new([b.voxels[5]; VOXELS_PER_BLOCK]), touched: 1 };
        assert_eq!(full.to_bytes().len(), BLOCK_BYTES);
        assert_eq!(Block::from_bytes(&full.to_bytes()).unwrap(), full);
    }
}
