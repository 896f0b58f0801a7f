//! A vocabulary tree of binary words (Nistér & Stewénius; DBoW2's layout and
//! TF-IDF weighting) over 256-bit ORB descriptors.
//!
//! Training is hierarchical k-majority: the descriptors are split into
//! `branching` clusters (k-means++ seeding from a seeded generator, Hamming
//! distance, bitwise-majority centres), each cluster again, down to `depth`
//! levels; the leaves are the words. A word's weight is its inverse document
//! frequency over the training images. Everything is deterministic for a seed:
//! the same images and configuration give the same bytes.

use stillmap_tracking::features::{Descriptor, hamming};

use crate::PlacesError;

pub type WordId = u32;

/// Inner nodes carry no word.
const NO_WORD: u32 = u32::MAX;
/// File header: magic and format version.
const MAGIC: &[u8; 8] = b"SMVOC\x01\0\0";
const HEADER_BYTES: usize = 24;
const NODE_BYTES: usize = 44;
/// The largest vocabulary this format takes (2^22 nodes: 180 MB).
const MAX_NODES: usize = 1 << 22;
/// The shipped vocabulary's bytes.
const SHIPPED: &[u8] = include_bytes!("../vocabulary/fr1_rpy.smvoc");

/// How a vocabulary is trained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrainConfig {
    /// Children per node (k of the k-majority).
    pub branching: u32,
    /// Levels below the root; at most `branching^depth` words.
    pub depth: u32,
    /// k-majority rounds per split (it stops earlier when no descriptor changes cluster).
    pub iterations: u32,
    /// Seed of the k-means++ seeding.
    pub seed: u64,
}

impl Default for TrainConfig {
    /// 10 × 4: up to 10,000 words, ORB-SLAM's branching with one level less (its
    /// 10^6 words are trained on far more images than a fleet ships).
    fn default() -> Self {
        Self { branching: 10, depth: 4, iterations: 10, seed: 0x05EE_D0F5_7111 }
    }
}

impl TrainConfig {
    pub fn validate(&self) -> Result<(), PlacesError> {
        if !(2..=64).contains(&self.branching) || !(1..=8).contains(&self.depth) || self.iterations == 0 {
            return Err(PlacesError::Config(format!(
                "vocabulary: branching must be 2..=64, depth 1..=8 and iterations at least 1 (got {}, {}, {})",
                self.branching, self.depth, self.iterations
            )));
        }
        let nodes = (0..=self.depth).try_fold(0usize, |n, l| n.checked_add((self.branching as usize).checked_pow(l)?));
        if nodes.is_none_or(|n| n > MAX_NODES) {
            return Err(PlacesError::Config(format!("vocabulary: {}^{} words is more than this format holds", self.branching, self.depth)));
        }
        Ok(())
    }
}

#[derive(Debug, Clone, PartialEq)]
struct Node {
    descriptor: Descriptor,
    first_child: u32,
    children: u32,
    word: u32,
}

/// A bag-of-words vector: (word, weight) sorted by word, weights summing to 1.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BowVector(pub Vec<(WordId, f32)>);

impl BowVector {
    /// DBoW2's L1 similarity, `1 − ½‖v − w‖₁` for L1-normalised vectors: 1 for
    /// the same words in the same proportions, 0 for no word in common.
    pub fn score(&self, other: &BowVector) -> f32 {
        let (mut a, mut b) = (self.0.iter().peekable(), other.0.iter().peekable());
        let mut common = 0.0;
        while let (Some(&&(wa, va)), Some(&&(wb, vb))) = (a.peek(), b.peek()) {
            match wa.cmp(&wb) {
                std::cmp::Ordering::Less => {
                    a.next();
                }
                std::cmp::Ordering::Greater => {
                    b.next();
                }
                std::cmp::Ordering::Equal => {
                    common += va + vb - (va - vb).abs();
                    a.next();
                    b.next();
                }
            }
        }
        0.5 * common
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

/// The trained tree and each word's inverse document frequency.
#[derive(Debug, Clone, PartialEq)]
pub struct Vocabulary {
    branching: u32,
    depth: u32,
    nodes: Vec<Node>,
    idf: Vec<f32>,
}

impl Vocabulary {
    /// Trains on the descriptors of `images` (one list per training image).
    pub fn train(images: &[Vec<Descriptor>], config: &TrainConfig) -> Result<Self, PlacesError> {
        config.validate()?;
        let all: Vec<(Descriptor, u32)> = images.iter().enumerate().flat_map(|(i, d)| d.iter().map(move |d| (*d, i as u32))).collect();
        if images.len() < 2 || all.len() < config.branching as usize {
            return Err(PlacesError::Training(format!(
                "{} images with {} descriptors: at least 2 images and {} descriptors are needed",
                images.len(),
                all.len(),
                config.branching
            )));
        }
        let mut rng = XorShift64Star::new(config.seed);
        let mut nodes = vec![Node { descriptor: [0; 4], first_child: 0, children: 0, word: NO_WORD }];
        // Breadth first, so that a node's children are contiguous.
        let mut queue = std::collections::VecDeque::from([(0usize, (0..all.len() as u32).collect::<Vec<u32>>(), 0u32)]);
        let mut word_members: Vec<Vec<u32>> = Vec::new();
        while let Some((node, members, level)) = queue.pop_front() {
            if level == config.depth || members.len() <= config.branching as usize {
                nodes[node].word = word_members.len() as u32;
                word_members.push(members);
                continue;
            }
            let clusters = k_majority(&all, &members, config, &mut rng);
            nodes[node].first_child = nodes.len() as u32;
            nodes[node].children = clusters.len() as u32;
            for (centre, cluster) in clusters {
                queue.push_back((nodes.len(), cluster, level + 1));
                nodes.push(Node { descriptor: centre, first_child: 0, children: 0, word: NO_WORD });
            }
        }
        let n = images.len() as f32;
        let idf = word_members
            .iter()
            .map(|members| {
                let mut seen: Vec<u32> = members.iter().map(|&m| all[m as usize].1).collect();
                seen.sort_unstable();
                seen.dedup();
                (n / seen.len().max(1) as f32).ln()
            })
            .collect();
        Ok(Self { branching: config.branching, depth: config.depth, nodes, idf })
    }

    /// The vocabulary shipped with stillmap (`places/vocabulary/fr1_rpy.smvoc`,
    /// made by `make vocabulary` from the public clip; see `tests/vocabulary.rs`).
    pub fn shipped() -> Self {
        // Checked by the golden test and by `shipped_vocabulary_reads`: a bad file cannot pass CI.
        Self::from_bytes(SHIPPED).unwrap_or_else(|e| panic!("the shipped vocabulary is corrupt: {e}"))
    }

    /// Number of words (leaves).
    pub fn words(&self) -> usize {
        self.idf.len()
    }

    /// The word a descriptor falls in: down the tree, nearest child first.
    pub fn word(&self, d: &Descriptor) -> WordId {
        let mut node = &self.nodes[0];
        while node.children > 0 {
            let first = node.first_child as usize;
            let children = &self.nodes[first..first + node.children as usize];
            node = children.iter().min_by_key(|c| hamming(&c.descriptor, d)).unwrap_or(&children[0]);
        }
        node.word
    }

    /// TF-IDF bag of words of one image's descriptors, L1-normalised. Words seen in
    /// every training image weigh nothing and are left out.
    pub fn transform(&self, descriptors: &[Descriptor]) -> BowVector {
        let mut words: Vec<WordId> = descriptors.iter().map(|d| self.word(d)).collect();
        words.sort_unstable();
        let mut v: Vec<(WordId, f32)> = Vec::new();
        for w in words {
            match v.last_mut() {
                Some((last, count)) if *last == w => *count += 1.0,
                _ => v.push((w, 1.0)),
            }
        }
        for (w, x) in &mut v {
            *x *= self.idf[*w as usize];
        }
        v.retain(|&(_, x)| x > 0.0);
        let total: f32 = v.iter().map(|&(_, x)| x).sum();
        if total > 0.0 {
            v.iter_mut().for_each(|(_, x)| *x /= total);
        }
        BowVector(v)
    }

    /// The vocabulary as bytes (little endian): header, nodes, word weights.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_BYTES + self.nodes.len() * NODE_BYTES + self.idf.len() * 4);
        out.extend_from_slice(MAGIC);
        for v in [self.branching, self.depth, self.nodes.len() as u32, self.idf.len() as u32] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for n in &self.nodes {
            for w in n.descriptor {
                out.extend_from_slice(&w.to_le_bytes());
            }
            for v in [n.first_child, n.children, n.word] {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        for x in &self.idf {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out
    }

    /// Reads [`to_bytes`](Self::to_bytes)'s format; every size is checked against
    /// the bytes given before anything is allocated, and the tree against itself.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, PlacesError> {
        let bad = |why: String| PlacesError::Vocabulary(why);
        if bytes.len() < HEADER_BYTES || &bytes[..8] != MAGIC {
            return Err(bad("not a stillmap vocabulary (wrong header)".into()));
        }
        let u32_at = |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        let (branching, depth, node_count, word_count) = (u32_at(8), u32_at(12), u32_at(16) as usize, u32_at(20) as usize);
        let expected = node_count
            .checked_mul(NODE_BYTES)
            .and_then(|n| n.checked_add(word_count.checked_mul(4)?))
            .and_then(|n| n.checked_add(HEADER_BYTES));
        if expected != Some(bytes.len()) || node_count == 0 || node_count > MAX_NODES || word_count > node_count {
            return Err(bad(format!("{} bytes, but the header declares {node_count} nodes and {word_count} words", bytes.len())));
        }
        let mut nodes = Vec::with_capacity(node_count);
        for k in 0..node_count {
            let o = HEADER_BYTES + k * NODE_BYTES;
            let w = |i: usize| u64::from_le_bytes(bytes[o + 8 * i..o + 8 * i + 8].try_into().unwrap_or([0; 8]));
            nodes.push(Node {
                descriptor: [w(0), w(1), w(2), w(3)],
                first_child: u32_at(o + 32),
                children: u32_at(o + 36),
                word: u32_at(o + 40),
            });
        }
        let idf: Vec<f32> = (0..word_count).map(|k| f32::from_bits(u32_at(HEADER_BYTES + node_count * NODE_BYTES + 4 * k))).collect();
        let mut words_seen = vec![false; word_count];
        for (k, n) in nodes.iter().enumerate() {
            if n.children == 0 {
                let seen =
                    words_seen.get_mut(n.word as usize).ok_or_else(|| bad(format!("leaf {k} names word {} of {word_count}", n.word)))?;
                if std::mem::replace(seen, true) {
                    return Err(bad(format!("word {} has two leaves", n.word)));
                }
            } else {
                // Children come after their parent (breadth first): no cycle.
                let (first, end) = (n.first_child as usize, n.first_child as usize + n.children as usize);
                if n.word != NO_WORD || first <= k || end > node_count {
                    return Err(bad(format!("node {k}: children {first}..{end} of {node_count} nodes")));
                }
            }
        }
        if words_seen.iter().any(|s| !s) || idf.iter().any(|x| !(x.is_finite() && *x >= 0.0)) {
            return Err(bad("a word without a leaf, or a weight that is not a finite non-negative number".into()));
        }
        Ok(Self { branching, depth, nodes, idf })
    }
}

/// Splits `members` of `all` into up to `branching` clusters: (centre, members).
fn k_majority(all: &[(Descriptor, u32)], members: &[u32], config: &TrainConfig, rng: &mut XorShift64Star) -> Vec<(Descriptor, Vec<u32>)> {
    let k = config.branching as usize;
    let d = |m: u32| &all[m as usize].0;
    // k-means++ seeding: each next centre drawn with probability ∝ distance².
    let mut centres: Vec<Descriptor> = vec![*d(members[rng.below(members.len())])];
    let mut nearest: Vec<u32> = members.iter().map(|&m| hamming(d(m), &centres[0])).collect();
    while centres.len() < k {
        let total: u64 = nearest.iter().map(|&x| u64::from(x) * u64::from(x)).sum();
        if total == 0 {
            break; // every member equals a centre
        }
        let mut pick = rng.next() % total;
        let chosen = nearest
            .iter()
            .position(|&x| {
                let w = u64::from(x) * u64::from(x);
                if pick < w {
                    true
                } else {
                    pick -= w;
                    false
                }
            })
            .unwrap_or(members.len() - 1);
        let c = *d(members[chosen]);
        for (n, &m) in nearest.iter_mut().zip(members) {
            *n = (*n).min(hamming(d(m), &c));
        }
        centres.push(c);
    }
    let mut assignment = vec![usize::MAX; members.len()];
    for _ in 0..config.iterations {
        let mut changed = false;
        for (a, &m) in assignment.iter_mut().zip(members) {
            let best = (0..centres.len()).min_by_key(|&c| hamming(d(m), &centres[c])).unwrap_or(0);
            changed |= *a != best;
            *a = best;
        }
        if !changed {
            break;
        }
        // Bitwise majority of each cluster.
        let mut counts = vec![[0u32; 256]; centres.len()];
        let mut sizes = vec![0u32; centres.len()];
        for (&a, &m) in assignment.iter().zip(members) {
            sizes[a] += 1;
            for (bit, count) in counts[a].iter_mut().enumerate() {
                *count += ((d(m)[bit / 64] >> (bit % 64)) & 1) as u32;
            }
        }
        for ((c, count), &size) in centres.iter_mut().zip(&counts).zip(&sizes) {
            if size == 0 {
                continue;
            }
            let mut majority = [0u64; 4];
            for (bit, &n) in count.iter().enumerate() {
                if 2 * n > size {
                    majority[bit / 64] |= 1 << (bit % 64);
                }
            }
            *c = majority;
        }
    }
    let mut clusters: Vec<(Descriptor, Vec<u32>)> = centres.into_iter().map(|c| (c, Vec::new())).collect();
    for (&a, &m) in assignment.iter().zip(members) {
        clusters[a].1.push(m);
    }
    clusters.retain(|(_, m)| !m.is_empty());
    clusters
}

/// Marsaglia's xorshift64* (the seeding needs reproducibility, not quality).
struct XorShift64Star(u64);

impl XorShift64Star {
    fn new(seed: u64) -> Self {
        Self(seed | 1)
    }

    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Descriptors scattered around a few random "true" words.
    fn images(seed: u64) -> Vec<Vec<Descriptor>> {
        let mut rng = XorShift64Star::new(seed);
        let words: Vec<Descriptor> = (0..40).map(|_| [rng.next(), rng.next(), rng.next(), rng.next()]).collect();
        (0..12)
            .map(|i| {
                (0..200)
                    .map(|j| {
                        let mut d = words[(i * 7 + j * 3) % words.len()];
                        d[j % 4] ^= 1 << (rng.next() % 64); // one flipped bit
                        d
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn training_is_deterministic_and_bytes_round_trip() {
        let config = TrainConfig { branching: 4, depth: 3, ..TrainConfig::default() };
        let a = Vocabulary::train(&images(3), &config).expect("train");
        let b = Vocabulary::train(&images(3), &config).expect("train");
        assert_eq!(a.to_bytes(), b.to_bytes(), "same images and seed, same vocabulary");
        assert!(a.words() > 16 && a.words() <= 64, "{} words", a.words());
        let read = Vocabulary::from_bytes(&a.to_bytes()).expect("read back");
        assert_eq!(read, a);
        let other_seed = Vocabulary::train(&images(3), &TrainConfig { seed: 99, ..config }).expect("train");
        assert_ne!(other_seed.to_bytes(), a.to_bytes(), "the seed matters");
    }

    #[test]
    fn an_image_scores_one_against_itself_and_less_against_another() {
        let data = images(5);
        let v = Vocabulary::train(&data, &TrainConfig { branching: 4, depth: 3, ..TrainConfig::default() }).expect("train");
        let a = v.transform(&data[0]);
        let total: f32 = a.0.iter().map(|&(_, x)| x).sum();
        assert!((total - 1.0).abs() < 1e-5, "L1-normalised: {total}");
        assert!(a.0.windows(2).all(|w| w[0].0 < w[1].0), "sorted by word");
        assert!((a.score(&a) - 1.0).abs() < 1e-5);
        let b = v.transform(&data[5]);
        assert!(a.score(&b) < 0.9, "{}", a.score(&b));
        assert_eq!(a.score(&BowVector::default()), 0.0);
    }

    #[test]
    fn shipped_vocabulary_reads() {
        assert!(Vocabulary::from_bytes(SHIPPED).expect("shipped").words() > 1000);
    }

    #[test]
    fn bad_bytes_and_bad_configurations_are_named() {
        let v = Vocabulary::train(&images(7), &TrainConfig { branching: 4, depth: 2, ..TrainConfig::default() }).expect("train");
        let bytes = v.to_bytes();
        let err = Vocabulary::from_bytes(&bytes[..bytes.len() - 1]).expect_err("truncated");
        assert!(err.to_string().starts_with("bad vocabulary: "), "{err}");
        assert!(err.to_string().contains("header declares"), "{err}");
        assert_eq!(
            Vocabulary::from_bytes(b"PNG").expect_err("junk").to_string(),
            "bad vocabulary: not a stillmap vocabulary (wrong header)"
        );
        // A header declaring 2^31 nodes in 24 bytes allocates nothing.
        let mut huge = bytes[..HEADER_BYTES].to_vec();
        huge[16..20].copy_from_slice(&(1u32 << 31).to_le_bytes());
        assert!(Vocabulary::from_bytes(&huge).is_err());
        // A child pointing back at the root (a cycle).
        let mut cyclic = bytes.clone();
        cyclic[HEADER_BYTES + 32..HEADER_BYTES + 36].copy_from_slice(&0u32.to_le_bytes());
        assert!(Vocabulary::from_bytes(&cyclic).expect_err("cycle").to_string().contains("node 0: children"));
        let err = TrainConfig { branching: 1, ..TrainConfig::default() }.validate().expect_err("k = 1");
        assert!(err.to_string().contains("branching must be 2..=64"), "{err}");
        assert!(Vocabulary::train(&images(7)[..1], &TrainConfig::default()).is_err(), "one image has no document frequency");
    }
}
