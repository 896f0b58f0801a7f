//! Taking back what was mapped before an object was known to move.
//!
//! A keyframe is fused with the mask of its own frame. When the segmenter misses a
//! person for a while, or a box rests and is fused and then moves on, the map
//! holds surface samples of things that move. The masker follows where each recent
//! keyframe's pixels are now: one origin map per keyframe on the flow grid (for
//! every current cell, the keyframe cell it shows, carried frame to frame through
//! the same flow that carries the segmentation). Whenever a current cell is
//! labelled dynamic or prior-dynamic, the keyframe cell it came from is reported
//! once as a [`Retraction`]; the map then takes that keyframe's samples there back
//! out.
//!
//! Bounded: at most `retract_keyframes` keyframes are followed, each for at most
//! `retract_horizon_frames` frames after it was made (an origin map is one `u32`
//! and one flag per flow cell: 34 k cells at 640×480 with subsample 3, 170 KB).

use crate::flow::FlowField;

/// No keyframe cell (the pixel came into view after the keyframe).
const NONE: u32 = u32::MAX;

/// Cells of one keyframe found to show moving things now: its samples in those
/// cells should leave the map.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Retraction {
    /// The id the keyframe was noted with.
    pub keyframe: u64,
    /// Flow-grid cell indices (row-major, `grid_width` wide) of the keyframe's frame.
    pub cells: Vec<u32>,
    pub grid_width: u32,
    pub grid_height: u32,
    /// Full-size pixels per cell edge.
    pub subsample: u32,
}

impl Retraction {
    /// A per-pixel test for an image of `width` pixels: whether the pixel (row-major
    /// index) lies in one of the cells.
    pub fn pixel_test(&self, width: u32) -> impl Fn(u32) -> bool + '_ {
        let mut grid = vec![false; self.grid_width as usize * self.grid_height as usize];
        for &c in &self.cells {
            if let Some(g) = grid.get_mut(c as usize) {
                *g = true;
            }
        }
        let (s, gw, gh) = (self.subsample.max(1), self.grid_width, self.grid_height);
        move |pixel: u32| {
            if width == 0 || grid.is_empty() {
                return false;
            }
            let (x, y) = (((pixel % width) / s).min(gw.saturating_sub(1)), ((pixel / width) / s).min(gh.saturating_sub(1)));
            grid.get((y * gw + x) as usize).copied().unwrap_or(false)
        }
    }
}

struct Followed {
    keyframe: u64,
    /// The frame the keyframe was made on.
    made_at: u64,
    /// The frame `origin` is expressed in.
    at: u64,
    /// Per current cell, the keyframe cell it shows (`NONE`: none).
    origin: Vec<u32>,
    /// Keyframe cells already reported.
    reported: Vec<bool>,
}

/// The recent keyframes' pixels, followed through the flow.
pub struct KeyframeOrigins {
    max_keyframes: usize,
    horizon_frames: u64,
    followed: Vec<Followed>,
    /// Per current cell, the previous frame's cell it shows (reused buffers).
    source: Vec<u32>,
    scratch: Vec<u32>,
}

impl KeyframeOrigins {
    /// Off when `max_keyframes` or `horizon_frames` is 0.
    pub fn new(max_keyframes: usize, horizon_frames: u64) -> Self {
        Self { max_keyframes, horizon_frames, followed: Vec::new(), source: Vec::new(), scratch: Vec::new() }
    }

    /// Starts following keyframe `keyframe`, made on frame `sequence`, on a grid of `cells` cells.
    pub fn note(&mut self, keyframe: u64, sequence: u64, cells: usize) {
        if self.max_keyframes == 0 || self.horizon_frames == 0 {
            return;
        }
        let Ok(n) = u32::try_from(cells) else { return };
        self.followed.push(Followed { keyframe, made_at: sequence, at: sequence, origin: (0..n).collect(), reported: vec![false; cells] });
        while self.followed.len() > self.max_keyframes {
            self.followed.remove(0);
        }
    }

    /// Carries every origin map through one flow step (`from` → `to`, current → previous
    /// flow); maps not at `from`, or past the horizon, are dropped.
    pub fn advance(&mut self, from: u64, to: u64, flow: &FlowField) {
        let horizon = self.horizon_frames;
        self.followed.retain(|f| f.at == from && to.saturating_sub(f.made_at) <= horizon && f.origin.len() == flow.data.len());
        if self.followed.is_empty() {
            return;
        }
        // Where each current cell comes from, once for all keyframes.
        let (w, h) = (flow.width, flow.height);
        self.source.clear();
        self.source.extend(flow.data.iter().enumerate().map(|(i, d)| {
            let (sx, sy) = (((i % w) as f32 + d[0]).round(), ((i / w) as f32 + d[1]).round());
            if sx >= 0.0 && sy >= 0.0 && (sx as usize) < w && (sy as usize) < h { sy as u32 * w as u32 + sx as u32 } else { NONE }
        }));
        for f in &mut self.followed {
            self.scratch.clear();
            self.scratch.extend(self.source.iter().map(|&src| if src == NONE { NONE } else { f.origin[src as usize] }));
            std::mem::swap(&mut f.origin, &mut self.scratch);
            f.at = to;
        }
    }

    /// Forgets everything (the flow chain broke).
    pub fn clear(&mut self) {
        self.followed.clear();
    }

    /// The keyframe cells that show a moving thing in frame `sequence` (`moving`:
    /// one flag per flow cell), each reported once per keyframe.
    pub fn retractions(&mut self, sequence: u64, moving: &[bool], grid_width: usize, subsample: u32) -> Vec<Retraction> {
        let mut out = Vec::new();
        let grid_height = moving.len() / grid_width.max(1);
        let moving_cells: Vec<usize> = moving.iter().enumerate().filter(|(_, m)| **m).map(|(i, _)| i).collect();
        if moving_cells.is_empty() {
            return out;
        }
        for f in self.followed.iter_mut().filter(|f| f.at == sequence && f.origin.len() == moving.len()) {
            let mut cells = Vec::new();
            for &i in &moving_cells {
                let o = f.origin[i];
                if o != NONE && !std::mem::replace(&mut f.reported[o as usize], true) {
                    cells.push(o);
                }
            }
            if !cells.is_empty() {
                cells.sort_unstable();
                out.push(Retraction {
                    keyframe: f.keyframe,
                    cells,
                    grid_width: grid_width as u32,
                    grid_height: grid_height as u32,
                    subsample,
                });
            }
        }
        out
    }

    /// Keyframes followed now.
    pub fn len(&self) -> usize {
        self.followed.len()
    }

    pub fn is_empty(&self) -> bool {
        self.followed.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shift(w: usize, h: usize, dx: f32) -> FlowField {
        // Every current cell shows what was `dx` cells to its right in the previous frame
        // (the scene moved left by dx).
        FlowField { width: w, height: h, subsample: 2, data: vec![[dx, 0.0]; w * h] }
    }

    /// A keyframe's cell is followed as the scene moves, reported once when it
    /// becomes moving, and never after the horizon or the keyframe limit.
    #[test]
    fn keyframe_cells_are_followed_reported_once_and_bounded() {
        let (w, h) = (6, 2);
        let mut o = KeyframeOrigins::new(2, 3);
        o.note(100, 10, w * h);
        o.advance(10, 11, &shift(w, h, 1.0));
        // Cell (2, 0) now shows keyframe cell (3, 0).
        let mut moving = vec![false; w * h];
        moving[2] = true;
        let r = o.retractions(11, &moving, w, 2);
        assert_eq!(r, vec![Retraction { keyframe: 100, cells: vec![3], grid_width: 6, grid_height: 2, subsample: 2 }]);
        assert!(o.retractions(11, &moving, w, 2).is_empty(), "reported once");
        // The last column came into view: it shows no keyframe cell.
        let mut edge = vec![false; w * h];
        edge[5] = true;
        assert!(o.retractions(11, &edge, w, 2).is_empty());
        // Pixel test: cell 3 of a 6-wide grid at subsample 2 is pixels x 6..8, y 0..2 of a 12-wide image.
        let test = r[0].pixel_test(12);
        assert!(test(6) && test(7) && test(12 + 7) && !test(5) && !test(8) && !test(2 * 12 + 6));
        // A step from another frame breaks the chain; past the horizon it is dropped.
        o.note(101, 11, w * h);
        o.note(102, 11, w * h);
        assert_eq!(o.len(), 2, "at most two keyframes");
        o.advance(11, 15, &shift(w, h, 0.0));
        assert!(o.is_empty(), "15 − 11 frames is past a 3-frame horizon");
        // A degenerate report covers nothing (and does not panic).
        let empty = Retraction { keyframe: 1, cells: vec![0], grid_width: 0, grid_height: 0, subsample: 0 };
        assert!(!empty.pixel_test(12)(5) && !r[0].pixel_test(0)(5));
        let mut off = KeyframeOrigins::new(0, 3);
        off.note(1, 1, w * h);
        assert!(off.is_empty());
    }
}
