//! The inverted index over stored keyframes' bags of words.
//!
//! Each word lists the entries (keyframes) that hold it and with what weight. A
//! query walks only the lists of its own words, so its cost grows with the
//! number of entries sharing words with it, not with the whole index (DBoW2's
//! database, without its direct index).

use std::collections::HashMap;
use std::hash::Hash;

use crate::vocabulary::{BowVector, WordId};

/// Removed entries that trigger a compaction (once they are half of all slots).
const COMPACT_AFTER: usize = 64;

/// Keyframes by key `K` (a session and keyframe id, say), searchable by bag of words.
#[derive(Debug)]
pub struct PlaceIndex<K> {
    /// Per word: (entry, weight).
    inverted: HashMap<WordId, Vec<(u32, f32)>>,
    /// Per entry: its key, and its vector (None once removed).
    entries: Vec<(K, Option<BowVector>)>,
    by_key: HashMap<K, u32>,
    /// Entries removed and not yet compacted away.
    removed: usize,
}

impl<K: Copy + Eq + Hash> Default for PlaceIndex<K> {
    fn default() -> Self {
        Self { inverted: HashMap::new(), entries: Vec::new(), by_key: HashMap::new(), removed: 0 }
    }
}

impl<K: Copy + Eq + Hash> PlaceIndex<K> {
    pub fn new() -> Self {
        Self::default()
    }

    /// Entries held.
    pub fn len(&self) -> usize {
        self.by_key.len()
    }

    pub fn is_empty(&self) -> bool {
        self.by_key.is_empty()
    }

    /// Adds (or replaces) the entry `key`.
    pub fn insert(&mut self, key: K, bow: BowVector) {
        self.remove(&key);
        let entry = self.entries.len() as u32;
        for &(w, x) in &bow.0 {
            self.inverted.entry(w).or_default().push((entry, x));
        }
        self.entries.push((key, Some(bow)));
        self.by_key.insert(key, entry);
    }

    /// Removes the entry `key` (its postings go with it). Once removed entries are
    /// half of those ever kept, the rest are renumbered, so that memory follows the
    /// entries held, not those ever inserted.
    pub fn remove(&mut self, key: &K) -> bool {
        let Some(entry) = self.by_key.remove(key) else { return false };
        if let Some(bow) = self.entries[entry as usize].1.take() {
            for (w, _) in bow.0 {
                if let Some(list) = self.inverted.get_mut(&w) {
                    list.retain(|&(e, _)| e != entry);
                    if list.is_empty() {
                        self.inverted.remove(&w);
                    }
                }
            }
        }
        self.removed += 1;
        if self.removed >= COMPACT_AFTER && 2 * self.removed >= self.entries.len() {
            self.compact();
        }
        true
    }

    /// Renumbers the entries held (their order kept) and rebuilds the postings.
    fn compact(&mut self) {
        let entries: Vec<(K, Option<BowVector>)> = std::mem::take(&mut self.entries).into_iter().filter(|(_, bow)| bow.is_some()).collect();
        self.inverted.clear();
        self.by_key.clear();
        for (i, (key, bow)) in entries.iter().enumerate() {
            self.by_key.insert(*key, i as u32);
            for &(w, x) in bow.iter().flat_map(|b| &b.0) {
                self.inverted.entry(w).or_default().push((i as u32, x));
            }
        }
        self.entries = entries;
        self.removed = 0;
    }

    /// Entry slots in use, removed ones included until the next compaction.
    pub fn slots(&self) -> usize {
        self.entries.len()
    }

    /// Postings held (memory: 8 bytes each, plus the entries' vectors, 8 bytes a word).
    pub fn postings(&self) -> usize {
        self.inverted.values().map(Vec::len).sum()
    }

    /// The `max_results` entries most similar to `query` (DBoW2's L1 score, best
    /// first, ties by insertion order) among those `accept` lets through, scoring
    /// at least `min_score`.
    pub fn query(&self, query: &BowVector, max_results: usize, min_score: f32, accept: impl Fn(&K) -> bool) -> Vec<(K, f32)> {
        // ½ Σ over common words of |v| + |w| − |v − w|: accumulated per entry from the postings.
        let mut scores: HashMap<u32, f32> = HashMap::new();
        for &(w, v) in &query.0 {
            let Some(list) = self.inverted.get(&w) else { continue };
            for &(entry, x) in list {
                *scores.entry(entry).or_insert(0.0) += v + x - (v - x).abs();
            }
        }
        let mut ranked: Vec<(u32, f32)> =
            scores.into_iter().map(|(e, s)| (e, 0.5 * s)).filter(|&(e, s)| s >= min_score && accept(&self.entries[e as usize].0)).collect();
        ranked.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        ranked.truncate(max_results);
        ranked.into_iter().map(|(e, s)| (self.entries[e as usize].0, s)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bow(words: &[(WordId, f32)]) -> BowVector {
        let total: f32 = words.iter().map(|w| w.1).sum();
        BowVector(words.iter().map(|&(w, x)| (w, x / total)).collect())
    }

    #[test]
    fn query_scores_match_the_vectors_own_score_and_rank_best_first() {
        let mut index = PlaceIndex::new();
        let a = bow(&[(1, 1.0), (2, 1.0), (3, 2.0)]);
        let b = bow(&[(3, 1.0), (4, 1.0)]);
        let c = bow(&[(7, 1.0)]);
        index.insert(("a", 0), a.clone());
        index.insert(("b", 0), b.clone());
        index.insert(("c", 0), c.clone());
        let q = bow(&[(1, 1.0), (3, 1.0)]);
        let found = index.query(&q, 10, 0.0, |_| true);
        assert_eq!(found.len(), 2, "c shares no word and is never touched: {found:?}");
        assert_eq!(found[0].0, ("a", 0));
        assert!((found[0].1 - q.score(&a)).abs() < 1e-6 && (found[1].1 - q.score(&b)).abs() < 1e-6);
        assert_eq!(index.query(&q, 10, 0.0, |k| k.0 != "a"), vec![(("b", 0), q.score(&b))]);
        assert!(index.query(&q, 10, 0.9, |_| true).is_empty(), "below the minimum score");
        assert!(index.remove(&("a", 0)));
        assert!(!index.remove(&("a", 0)));
        assert_eq!(index.query(&q, 10, 0.0, |_| true).len(), 1);
        assert_eq!((index.len(), index.postings()), (2, 3));
    }

    /// Inserting and removing for ever keeps memory to what is held, and the
    /// survivors are still found with their scores.
    #[test]
    fn removals_are_compacted_away() {
        let mut index = PlaceIndex::new();
        for k in 0..1000u32 {
            index.insert(k, bow(&[(k % 5, 1.0), (100 + k, 1.0)]));
            if k >= 10 {
                index.remove(&(k - 10));
            }
        }
        assert_eq!(index.len(), 10);
        assert!(index.slots() < 200, "{} slots for 10 entries", index.slots());
        // Of the ten held, 990 and 995 share word 0; 995 also its own word.
        let found = index.query(&bow(&[(0, 1.0), (1095, 1.0)]), 3, 0.0, |_| true);
        assert_eq!(found.iter().map(|f| f.0).collect::<Vec<_>>(), [995, 990]);
        assert!((found[0].1 - 1.0).abs() < 1e-6 && (found[1].1 - 0.5).abs() < 1e-6, "{found:?}");
    }
}
