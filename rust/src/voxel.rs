//! Sparse 3D log-odds occupancy voxels (the paper's Fig. 11(b): a 3D occupancy grid of 0.1 m
//! along the SLAM trajectory) and the 3D grid traversal that writes rays into it.
//!
//! Indexing: voxel (ix, iy, iz) covers [ix·res, (ix+1)·res) × [iy·res, (iy+1)·res) ×
//! [iz·res, (iz+1)·res) in the world frame (metres, z up); its centre is ((i + ½)·res). Indices
//! are limited to [−2²⁰, 2²⁰) on every axis (±104.8 km at 0.1 m), so that a voxel packs into
//! one u64 key (see `pack`).
//!
//! Storage: a hash map of blocks of BLOCK³ = 8³ voxels keyed by block index; a block is a flat
//! f32 array of log-odds, allocated on the first update of any of its voxels. Unknown (never
//! observed) voxels hold NaN, as in the 2D grid (grid.rs); the prior log-odds is 0.
//!
//! Updates follow the inverse sensor model of the 2D grid (paper eq. 8, per-cell independence,
//! in log-odds; Thrun, Burgard & Fox, Probabilistic Robotics, sec. 9.2): a ray adds l_free to
//! every voxel it passes through before its end point and l_occ to the voxel holding its end
//! point, and the sum is clamped to [l_min, l_max]. Within one `integrate` call (one frame) a
//! voxel gets each kind of update at most once, and a voxel that holds some ray's end point is
//! not also freed by the call (as OctoMap does it): a frame's thousands of rays all start near
//! the sensor and would otherwise drive the voxels there to l_min, and grazing rays would erase
//! the surfaces that other rays of the same frame end on. This makes a call's result
//! independent of the order of its rays, hence of the thread count.

use std::collections::hash_map::DefaultHasher;
use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use rayon::prelude::*;

use crate::grid::LogOddsModel;

pub const BLOCK_SHIFT: u32 = 3;
pub const BLOCK: i32 = 1 << BLOCK_SHIFT;
pub(crate) const BLOCK_VOXELS: usize = (BLOCK * BLOCK * BLOCK) as usize;
/// Voxel indices on each axis lie in [−INDEX_LIMIT, INDEX_LIMIT).
pub const INDEX_LIMIT: i64 = 1 << 20;
const AXIS_BITS: u32 = 21;
const AXIS_MASK: u64 = (1 << AXIS_BITS) - 1;
const BLOCK_AXIS_BITS: u32 = AXIS_BITS - BLOCK_SHIFT;
const BLOCK_AXIS_MASK: u64 = (1 << BLOCK_AXIS_BITS) - 1;
const LOCAL_MASK: u64 = (BLOCK - 1) as u64;
/// Rays per parallel task of `integrate`.
const RAYS_PER_TASK: usize = 256;

pub(crate) type Block = [f32; BLOCK_VOXELS];
// A fixed-key hasher: the map's layout (and so its iteration order) depends on the inputs only.
type Blocks = HashMap<u64, Box<Block>, BuildHasherDefault<DefaultHasher>>;

/// The u64 key of voxel (ix, iy, iz): block index bits high, in-block bits low, so that sorted
/// keys come grouped by block. Layout: bx (18 bits) | by (18) | bz (18) | lx (3) | ly (3) | lz (3),
/// where (b, l) are the high and low bits of i + INDEX_LIMIT. Indices must be in range.
#[inline]
pub fn pack(i: [i64; 3]) -> u64 {
    let u = i.map(|v| (v + INDEX_LIMIT) as u64 & AXIS_MASK);
    let b = u.map(|v| v >> BLOCK_SHIFT);
    let l = u.map(|v| v & LOCAL_MASK);
    (b[0] << (2 * BLOCK_AXIS_BITS + 9))
        | (b[1] << (BLOCK_AXIS_BITS + 9))
        | (b[2] << 9)
        | (l[0] << 6)
        | (l[1] << 3)
        | l[2]
}

/// The voxel index of a key made by `pack`.
#[inline]
pub fn unpack(key: u64) -> [i64; 3] {
    let b = [
        (key >> (2 * BLOCK_AXIS_BITS + 9)) & BLOCK_AXIS_MASK,
        (key >> (BLOCK_AXIS_BITS + 9)) & BLOCK_AXIS_MASK,
        (key >> 9) & BLOCK_AXIS_MASK,
    ];
    let l = [(key >> 6) & LOCAL_MASK, (key >> 3) & LOCAL_MASK, key & LOCAL_MASK];
    [0, 1, 2].map(|a| ((b[a] << BLOCK_SHIFT) | l[a]) as i64 - INDEX_LIMIT)
}

/// Visit the voxels along the segment from `start` in unit direction `dir` for `length` metres
/// (Amanatides & Woo, "A fast voxel traversal algorithm", 1987; the 3D form of
/// raycast::traverse). `visit(index, t_enter, t_exit)` gets every voxel whose interior the
/// segment passes through, in order, with the ray lengths at which it enters and leaves it, and
/// returns false to stop early; the last voxel visited has `t_exit >= length`.
#[inline]
pub fn traverse<F>(start: [f64; 3], dir: [f64; 3], length: f64, resolution: f64, mut visit: F)
where
    F: FnMut([i64; 3], f64, f64) -> bool,
{
    let inv = 1.0 / resolution;
    let u = start.map(|s| s * inv);
    let mut idx = u.map(|v| v.floor() as i64);
    let mut step = [0i64; 3];
    let mut t_max = [f64::INFINITY; 3];
    let mut t_delta = [f64::INFINITY; 3];
    for a in 0..3 {
        let d = dir[a];
        if d > 0.0 {
            step[a] = 1;
            t_max[a] = (u[a].floor() + 1.0 - u[a]) * resolution / d;
            t_delta[a] = resolution / d;
        } else if d < 0.0 {
            step[a] = -1;
            t_max[a] = (u[a] - u[a].floor()) * resolution / -d;
            t_delta[a] = resolution / -d;
        }
    }
    let mut t_enter = 0.0;
    loop {
        // The axis whose boundary comes first; ties go to the later axis (as in 2D).
        let a = if t_max[0] < t_max[1] {
            if t_max[0] < t_max[2] { 0 } else { 2 }
        } else if t_max[1] < t_max[2] {
            1
        } else {
            2
        };
        let t_exit = t_max[a];
        if !visit(idx, t_enter, t_exit) || t_exit >= length {
            return;
        }
        t_enter = t_exit;
        idx[a] += step[a];
        t_max[a] += t_delta[a];
    }
}

/// What one `integrate` call did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct IntegrateStats {
    /// Rays that ended on a surface within max_range.
    pub hits: usize,
    /// Rays longer than max_range: freed up to max_range, no end point.
    pub max_range: usize,
    /// Rays with a non-finite origin or end point: not used.
    pub skipped: usize,
    /// Distinct voxels freed / marked occupied by the call.
    pub free_voxels: usize,
    pub occupied_voxels: usize,
}

/// A sparse, unbounded log-odds voxel grid (see the module docs for indexing and updates).
#[derive(Clone)]
pub struct VoxelGrid {
    pub resolution: f64,
    pub model: LogOddsModel,
    blocks: Blocks,
}

impl VoxelGrid {
    pub fn new(resolution: f64, model: LogOddsModel) -> Result<Self, String> {
        if !(resolution.is_finite() && resolution > 0.0) {
            return Err(format!("resolution must be a positive number of metres, got {resolution}"));
        }
        let LogOddsModel { l_occ, l_free, l_min, l_max } = model;
        if !(l_occ > 0.0 && l_free < 0.0 && l_min < 0.0 && l_max > 0.0 && l_min.is_finite() && l_max.is_finite()) {
            return Err(format!(
                "log-odds model needs l_occ > 0, l_free < 0, finite l_min < 0 < l_max; got \
                 l_occ={l_occ}, l_free={l_free}, l_min={l_min}, l_max={l_max}"
            ));
        }
        Ok(VoxelGrid { resolution, model, blocks: Blocks::default() })
    }

    /// A grid holding `blocks` (block key, voxels) as they are: how the 3D particle filter
    /// (filter3d.rs) hands out a particle's map. The model must be valid (see `new`).
    pub(crate) fn from_blocks(resolution: f64, model: LogOddsModel, blocks: impl Iterator<Item = (u64, Block)>) -> Self {
        VoxelGrid { resolution, model, blocks: blocks.map(|(k, b)| (k, Box::new(b))).collect() }
    }

    /// The index of the voxel holding world point `p`, or None if `p` is not finite or beyond
    /// the index range.
    #[inline]
    pub fn index_of(&self, p: [f64; 3]) -> Option<[i64; 3]> {
        let mut out = [0i64; 3];
        for a in 0..3 {
            let u = (p[a] / self.resolution).floor();
            if !(u >= -(INDEX_LIMIT as f64) && u < INDEX_LIMIT as f64) {
                return None;
            }
            out[a] = u as i64;
        }
        Some(out)
    }

    /// Log-odds of a voxel; NaN where unknown.
    #[inline]
    pub fn get(&self, i: [i64; 3]) -> f32 {
        if i.iter().any(|v| !(-INDEX_LIMIT..INDEX_LIMIT).contains(v)) {
            return f32::NAN;
        }
        let key = pack(i);
        match self.blocks.get(&(key >> 9)) {
            Some(block) => block[(key & 511) as usize],
            None => f32::NAN,
        }
    }

    /// Write rays from `origins` to `endpoints` (world frame, metres) into the grid as one
    /// frame (see the module docs). Rays longer than `max_range` free the voxels up to
    /// max_range and mark none occupied; rays with a non-finite origin or end point are
    /// skipped. Runs on the current rayon pool; the result does not depend on its size.
    ///
    /// How: tasks of RAYS_PER_TASK rays traverse their rays in parallel into lists of voxel
    /// keys (skipping keys a small cache has just seen), sorted and deduplicated per task; the
    /// lists are joined, sorted and deduplicated again, the occupied keys are taken out of the
    /// free ones, and both are applied serially, one map look-up per block.
    pub fn integrate(
        &mut self,
        origins: &[[f64; 3]],
        endpoints: &[[f64; 3]],
        max_range: f64,
    ) -> Result<IntegrateStats, String> {
        if origins.len() != endpoints.len() {
            return Err(format!("{} origins for {} end points", origins.len(), endpoints.len()));
        }
        if max_range.is_nan() || max_range <= 0.0 {
            return Err(format!("max_range must be > 0, got {max_range}"));
        }
        // A ray stays within the box of its two ends, so checking the ends suffices.
        let limit = (INDEX_LIMIT - 2) as f64 * self.resolution;
        for (o, e) in origins.iter().zip(endpoints) {
            let finite = o.iter().chain(e).all(|v| v.is_finite());
            if finite && o.iter().chain(e).any(|v| v.abs() > limit) {
                return Err(format!(
                    "ray from {o:?} to {e:?} leaves the grid's index range (±{limit} m on each axis)"
                ));
            }
        }
        let res = self.resolution;
        let parts: Vec<(Vec<u64>, Vec<u64>, IntegrateStats)> = origins
            .par_chunks(RAYS_PER_TASK)
            .zip(endpoints.par_chunks(RAYS_PER_TASK))
            .map(|(os, es)| {
                let (mut free, mut hit) = (Vec::new(), Vec::new());
                let mut stats = IntegrateStats::default();
                let mut seen = SeenFilter::new();
                for (o, e) in os.iter().zip(es) {
                    ray_voxels(*o, *e, max_range, res, &mut seen, &mut free, &mut hit, &mut stats);
                }
                free.sort_unstable();
                free.dedup();
                hit.sort_unstable();
                hit.dedup();
                (free, hit, stats)
            })
            .collect();
        let mut stats = IntegrateStats::default();
        let (mut free, mut hit) = (Vec::new(), Vec::new());
        for (f, h, s) in parts {
            free.extend_from_slice(&f);
            hit.extend_from_slice(&h);
            stats.hits += s.hits;
            stats.max_range += s.max_range;
            stats.skipped += s.skipped;
        }
        free.par_sort_unstable();
        free.dedup();
        hit.par_sort_unstable();
        hit.dedup();
        let free = sorted_difference(&free, &hit);
        stats.free_voxels = free.len();
        stats.occupied_voxels = hit.len();
        let model = self.model;
        self.apply(&free, model.l_free);
        self.apply(&hit, model.l_occ);
        Ok(stats)
    }

    /// Add `delta` to the voxels of sorted keys (grouped by block: one map look-up per block).
    fn apply(&mut self, keys: &[u64], delta: f32) {
        let (lo, hi) = (self.model.l_min, self.model.l_max);
        let mut i = 0;
        while i < keys.len() {
            let block_key = keys[i] >> 9;
            let block = self.blocks.entry(block_key).or_insert_with(|| Box::new([f32::NAN; BLOCK_VOXELS]));
            while i < keys.len() && keys[i] >> 9 == block_key {
                let cell = &mut block[(keys[i] & 511) as usize];
                let prior = if cell.is_nan() { 0.0 } else { *cell };
                *cell = (prior + delta).clamp(lo, hi);
                i += 1;
            }
        }
    }

    /// Indices of the voxels whose log-odds exceed `threshold`, sorted by (ix, iy, iz).
    pub fn occupied(&self, threshold: f32) -> Vec<[i64; 3]> {
        let mut out = self.collect(move |v| v > threshold);
        out.sort_unstable();
        out
    }

    /// (index, log-odds) of every observed voxel, sorted by index.
    pub fn observed(&self) -> Vec<([i64; 3], f32)> {
        let mut out: Vec<([i64; 3], f32)> = self
            .keys_where(|v| !v.is_nan())
            .map(|k| (unpack(k), self.blocks[&(k >> 9)][(k & 511) as usize]))
            .collect();
        out.sort_unstable_by_key(|a| a.0);
        out
    }

    fn collect(&self, keep: impl Fn(f32) -> bool + Copy + 'static) -> Vec<[i64; 3]> {
        self.keys_where(keep).map(unpack).collect()
    }

    fn keys_where<'a>(&'a self, keep: impl Fn(f32) -> bool + Copy + 'a) -> impl Iterator<Item = u64> + 'a {
        self.blocks.iter().flat_map(move |(&bk, block)| {
            block.iter().enumerate().filter(move |(_, &v)| keep(v)).map(move |(l, _)| (bk << 9) | l as u64)
        })
    }

    /// Number of observed (not NaN) voxels.
    pub fn voxel_count(&self) -> usize {
        self.blocks.values().map(|b| b.iter().filter(|v| !v.is_nan()).count()).sum()
    }

    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    pub const fn block_bytes() -> usize {
        std::mem::size_of::<Block>()
    }

    /// Heap bytes held: the blocks plus the hash table's slots (key, pointer, control byte).
    pub fn memory_bytes(&self) -> usize {
        let slot = std::mem::size_of::<u64>() + std::mem::size_of::<Box<Block>>() + 1;
        std::mem::size_of::<Self>() + self.blocks.len() * Self::block_bytes() + self.blocks.capacity() * slot
    }

    /// (min corner, max corner) in metres of the observed voxels; None if there are none.
    pub fn bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        let mut any = false;
        for k in self.keys_where(|v| !v.is_nan()) {
            let i = unpack(k);
            for a in 0..3 {
                lo[a] = lo[a].min(i[a]);
                hi[a] = hi[a].max(i[a]);
            }
            any = true;
        }
        let r = self.resolution;
        any.then(|| (lo.map(|v| v as f64 * r), hi.map(|v| (v + 1) as f64 * r)))
    }
}

/// A direct-mapped cache of recently freed voxel keys: neighbouring pixels' rays share most of
/// their voxels, and skipping a key already pushed keeps the lists to sort short. Lossy (a
/// slot holds the last key that mapped to it), so the lists are still sorted and deduplicated.
pub(crate) struct SeenFilter {
    slots: Vec<u64>,
}

impl SeenFilter {
    const BITS: u32 = 13;

    pub(crate) fn new() -> Self {
        // u64::MAX is no key: keys use the low 63 bits.
        SeenFilter { slots: vec![u64::MAX; 1 << Self::BITS] }
    }

    /// True if `key` was the last key seen in its slot; records it otherwise.
    #[inline]
    fn check(&mut self, key: u64) -> bool {
        let slot = (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> (64 - Self::BITS)) as usize;
        if self.slots[slot] == key {
            true
        } else {
            self.slots[slot] = key;
            false
        }
    }
}

/// Append the keys of the voxels one ray frees and the one it marks occupied.
#[inline]
#[allow(clippy::too_many_arguments)]
pub(crate) fn ray_voxels(
    o: [f64; 3],
    e: [f64; 3],
    max_range: f64,
    res: f64,
    seen: &mut SeenFilter,
    free: &mut Vec<u64>,
    hit: &mut Vec<u64>,
    stats: &mut IntegrateStats,
) {
    if !o.iter().chain(&e).all(|v| v.is_finite()) {
        stats.skipped += 1;
        return;
    }
    let d = [e[0] - o[0], e[1] - o[1], e[2] - o[2]];
    let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let end_voxel = e.map(|v| (v / res).floor() as i64);
    if length == 0.0 {
        stats.hits += 1;
        hit.push(pack(end_voxel));
        return;
    }
    let dir = d.map(|v| v / length);
    if length > max_range {
        stats.max_range += 1;
        traverse(o, dir, max_range, res, |i, _, _| {
            let key = pack(i);
            if !seen.check(key) {
                free.push(key);
            }
            true
        });
        return;
    }
    stats.hits += 1;
    traverse(o, dir, length, res, |i, _, _| {
        if i == end_voxel {
            return false;
        }
        let key = pack(i);
        if !seen.check(key) {
            free.push(key);
        }
        true
    });
    hit.push(pack(end_voxel));
}

/// The keys of sorted `a` that are not in sorted `b`.
pub(crate) fn sorted_difference(a: &[u64], b: &[u64]) -> Vec<u64> {
    let mut out = Vec::with_capacity(a.len());
    let mut j = 0;
    for &k in a {
        while j < b.len() && b[j] < k {
            j += 1;
        }
        if j >= b.len() || b[j] != k {
            out.push(k);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    const MODEL: LogOddsModel = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };

    fn voxels(start: [f64; 3], end: [f64; 3], res: f64) -> Vec<[i64; 3]> {
        let d = [end[0] - start[0], end[1] - start[1], end[2] - start[2]];
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let mut out = vec![];
        traverse(start, d.map(|v| v / len), len, res, |i, _, _| {
            out.push(i);
            true
        });
        out
    }

    /// A small deterministic generator (SplitMix64) for test inputs.
    struct Mix(u64);
    impl Mix {
        fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            lo + (hi - lo) * ((z >> 11) as f64 / (1u64 << 53) as f64)
        }
    }

    #[test]
    fn pack_round_trips_and_groups_blocks() {
        for i in [[0, 0, 0], [-1, 7, 8], [-INDEX_LIMIT, INDEX_LIMIT - 1, 12345], [-9, -8, -7]] {
            assert_eq!(unpack(pack(i)), i);
        }
        assert_eq!(pack([0, 0, 0]) >> 9, pack([7, 7, 7]) >> 9);
        assert_ne!(pack([7, 7, 7]) >> 9, pack([8, 7, 7]) >> 9);
        assert_ne!(pack([-1, 0, 0]) >> 9, pack([0, 0, 0]) >> 9);
    }

    #[test]
    fn axis_ray_visits_each_voxel_once() {
        let v = voxels([0.05, 0.05, 0.05], [0.05, 0.05, 0.95], 0.1);
        assert_eq!(v, (0..10).map(|k| [0, 0, k]).collect::<Vec<_>>());
        let v = voxels([0.05, -0.05, 0.05], [-0.95, -0.05, 0.05], 0.1);
        assert_eq!(v, (0..11).map(|k| [-k, -1, 0]).collect::<Vec<_>>());
    }

    #[test]
    fn general_ray_count_is_manhattan_distance_plus_one() {
        let mut rng = Mix(7);
        for _ in 0..200 {
            let s = [0; 3].map(|_| rng.uniform(-3.0, 3.0));
            let e = [0; 3].map(|_| rng.uniform(-3.0, 3.0));
            let v = voxels(s, e, 0.1);
            let (a, b) = (s.map(|x| (x / 0.1).floor() as i64), e.map(|x| (x / 0.1).floor() as i64));
            let manhattan: i64 = (0..3).map(|k| (a[k] - b[k]).abs()).sum();
            assert_eq!(v.len() as i64, manhattan + 1);
            assert_eq!(v[0], a);
            assert_eq!(*v.last().unwrap(), b);
            // Consecutive voxels are face neighbours.
            for w in v.windows(2) {
                let step: i64 = (0..3).map(|k| (w[0][k] - w[1][k]).abs()).sum();
                assert_eq!(step, 1);
            }
        }
    }

    #[test]
    fn traversal_matches_dense_sampling() {
        // Every voxel a dense sampling of the segment lands in is visited, and every visited
        // voxel is within reach of the segment (its slab intervals overlap, with a tolerance).
        let mut rng = Mix(11);
        let res = 0.1;
        for _ in 0..100 {
            let s = [0; 3].map(|_| rng.uniform(-2.0, 2.0));
            let e = [0; 3].map(|_| rng.uniform(-2.0, 2.0));
            let visited: BTreeSet<[i64; 3]> = voxels(s, e, res).into_iter().collect();
            let n = 20_000;
            let mut sampled = BTreeSet::new();
            for k in 0..=n {
                let t = k as f64 / n as f64;
                let p = [0, 1, 2].map(|a| s[a] + t * (e[a] - s[a]));
                // Skip samples within 1e-9 of a voxel face: rounding decides those.
                if p.iter().all(|x| {
                    let f = x / res - (x / res).floor();
                    f > 1e-7 && f < 1.0 - 1e-7
                }) {
                    sampled.insert(p.map(|x| (x / res).floor() as i64));
                }
            }
            assert!(sampled.is_subset(&visited), "sampling found voxels the traversal missed");
            for v in &visited {
                let (mut t0, mut t1) = (0.0f64, 1.0f64);
                for a in 0..3 {
                    let (lo, hi) = (v[a] as f64 * res - 1e-9, (v[a] + 1) as f64 * res + 1e-9);
                    let d = e[a] - s[a];
                    if d.abs() < 1e-15 {
                        assert!(s[a] >= lo && s[a] <= hi);
                    } else {
                        let (ta, tb) = ((lo - s[a]) / d, (hi - s[a]) / d);
                        t0 = t0.max(ta.min(tb));
                        t1 = t1.min(ta.max(tb));
                    }
                }
                assert!(t0 <= t1 + 1e-9, "visited voxel {v:?} does not meet the segment");
            }
        }
    }

    #[test]
    fn one_ray_frees_its_path_and_marks_its_end() {
        let mut g = VoxelGrid::new(0.1, MODEL).unwrap();
        let s = g.integrate(&[[0.05, 0.05, 0.05]], &[[0.95, 0.05, 0.05]], 10.0).unwrap();
        assert_eq!((s.hits, s.max_range, s.skipped, s.free_voxels, s.occupied_voxels), (1, 0, 0, 9, 1));
        for k in 0..9 {
            assert_eq!(g.get([k, 0, 0]), -0.4);
        }
        assert_eq!(g.get([9, 0, 0]), 0.9);
        assert!(g.get([10, 0, 0]).is_nan() && g.get([0, 1, 0]).is_nan());
        assert_eq!(g.occupied(0.0), vec![[9, 0, 0]]);
        assert_eq!(g.voxel_count(), 10);
        let (lo, hi) = g.bounds().unwrap();
        assert!((lo[0] - 0.0).abs() < 1e-12 && (hi[0] - 1.0).abs() < 1e-12 && (hi[2] - 0.1).abs() < 1e-12);
    }

    #[test]
    fn long_and_invalid_rays() {
        let mut g = VoxelGrid::new(0.1, MODEL).unwrap();
        let o = [[0.05, 0.05, 0.05]; 3];
        let e = [[5.05, 0.05, 0.05], [f64::NAN, 0.0, 0.0], [0.05, 0.05, f64::INFINITY]];
        let s = g.integrate(&o, &e, 0.5).unwrap();
        assert_eq!((s.hits, s.max_range, s.skipped, s.occupied_voxels), (0, 1, 2, 0));
        // Freed up to 0.5 m: voxels 0..=5 (the 0.55 m point lies in voxel 5).
        assert_eq!(s.free_voxels, 6);
        assert!(g.occupied(-10.0).len() == 6 && g.get([6, 0, 0]).is_nan());
    }

    #[test]
    fn a_frame_updates_each_voxel_once_and_hits_win() {
        let mut g = VoxelGrid::new(0.1, MODEL).unwrap();
        // Two rays along the same line; one ends where the other passes.
        let o = [[0.05, 0.05, 0.05]; 3];
        let e = [[0.95, 0.05, 0.05], [0.45, 0.05, 0.05], [0.95, 0.05, 0.05]];
        g.integrate(&o, &e, 10.0).unwrap();
        assert_eq!(g.get([0, 0, 0]), -0.4);
        assert_eq!(g.get([4, 0, 0]), 0.9);
        assert_eq!(g.get([9, 0, 0]), 0.9);
        for _ in 0..10 {
            g.integrate(&o, &e, 10.0).unwrap();
        }
        assert_eq!(g.get([0, 0, 0]), -2.0);
        assert_eq!(g.get([9, 0, 0]), 3.5);
    }

    #[test]
    fn result_does_not_depend_on_thread_count_or_ray_order() {
        let mut rng = Mix(3);
        let n = 5000;
        let o: Vec<[f64; 3]> = (0..n).map(|_| [rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), 0.4]).collect();
        let e: Vec<[f64; 3]> = (0..n).map(|_| [0; 3].map(|_| rng.uniform(-4.0, 4.0))).collect();
        let run = |threads: usize, reverse: bool| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut g = VoxelGrid::new(0.1, MODEL).unwrap();
            let (mut o, mut e) = (o.clone(), e.clone());
            if reverse {
                o.reverse();
                e.reverse();
            }
            pool.install(|| {
                g.integrate(&o, &e, 3.0).unwrap();
                g.integrate(&e, &o, 3.0).unwrap();
            });
            g.observed().into_iter().map(|(i, v)| (i, v.to_bits())).collect::<Vec<_>>()
        };
        let one = run(1, false);
        assert!(one.len() > 1000);
        assert_eq!(one, run(2, false));
        assert_eq!(one, run(4, true));
    }

    #[test]
    fn rejects_bad_input() {
        assert!(VoxelGrid::new(0.0, MODEL).is_err());
        assert!(VoxelGrid::new(0.1, LogOddsModel { l_occ: -1.0, ..MODEL }).is_err());
        let mut g = VoxelGrid::new(0.1, MODEL).unwrap();
        assert!(g.integrate(&[[0.0; 3]], &[], 1.0).is_err());
        assert!(g.integrate(&[[0.0; 3]], &[[1.0; 3]], 0.0).is_err());
        assert!(g.integrate(&[[0.0; 3]], &[[1e7, 0.0, 0.0]], 1.0).is_err());
    }
}
