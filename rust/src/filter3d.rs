//! The paper's 3D variant (sec. V, Fig. 11(b)): the Rao-Blackwellized particle filter of
//! filter.rs with a 3D occupancy map per particle, weighed by the frame's 3D rays.
//!
//! - Pose: planar (x, y, θ), the robot drives on the floor; sampled from the odometry motion
//!   model (motion.rs), or from a Gaussian around a scan-match mode (the proposal of Grisetti,
//!   Stachniss & Burgard 2007, as scan_match::propose does it in 2D: hill climbing, then
//!   Gauss-Newton on the field, `Field3d::linearise`).
//! - Map: a sparse log-odds voxel grid (voxel.rs indexing, 8³ blocks) whose blocks are held
//!   through `Arc`: particles copied from one another by resampling share every block neither
//!   has changed since, and a write copies a block first where another particle holds it
//!   (`Arc::make_mut`), as the 2D tiles do (grid.rs).
//! - Inverse sensor model: voxel.rs's (paper eq. 8 in 3D): each frame's rays free the voxels they
//!   pass through and mark the voxel of their end point occupied, each voxel updated at most once
//!   per frame, a voxel some ray ends in not freed by the frame.
//! - Observation model: a 3D likelihood field (Probabilistic Robotics, sec. 6.4) on a subsample
//!   of the frame's end points: p(z) = z_hit·exp(−d²/2σ²) + z_rand, d the distance from the end
//!   point to the centre of the nearest occupied voxel within a 3×3×3 window. Why not the beam
//!   model: its expected range needs a 3D ray cast per ray and particle (tens of voxel look-ups
//!   each, and the scan-matching proposal evaluates a hundred poses), where the field needs one
//!   look-up where the end point lies in an occupied voxel and 27 at most; and the field is what
//!   the scan matcher climbs, so both proposals weigh with one model.
//!
//! Determinism: every random draw comes from a generator seeded by (seed, step, particle)
//! (filter::rng_for); each particle's work is serial and writes its own slot; the map update of a
//! frame does not depend on the order of its rays. The result does not depend on the number of
//! threads.

use std::collections::{HashMap, HashSet};
use std::hash::{BuildHasherDefault, Hasher};
use std::sync::Arc;

use rayon::prelude::*;

use crate::filter::{fallback_pose, rng_for, ProposalKind, TrajectoryNode, Weighing};
use crate::correlative::correlative_search;
use crate::grid::{GridError, LogOddsModel, TiledGrid};
use crate::motion::{compose, relative, OdometryMotion};
use crate::scan_match::{climb, draw_around_mode, gauss_newton_with, motion_prior, MatcherParams, PosePrior};
use crate::sensor_model::ScanGeometry;
use crate::voxel::{pack, ray_voxels, sorted_difference, traverse, unpack, Block, IntegrateStats, SeenFilter, VoxelGrid, BLOCK_SHIFT, BLOCK_VOXELS, INDEX_LIMIT};

/// One 8³ block of a particle's map: log-odds (NaN = unknown) and, per voxel, the running mean
/// of the end points that fell into it, as an offset in 1/256 of a voxel per axis (as grid.rs
/// keeps it per cell), with the number averaged so far (saturating at 255). The likelihood
/// field measures distances to that point, not to the voxel's centre: walls on voxel
/// boundaries (common in buildings laid out in round metres) would otherwise pull every pose
/// by half a voxel, 5 cm at 0.1 m.
#[derive(Clone)]
pub struct Block3 {
    pub log_odds: Block,
    offset: [[u8; 3]; BLOCK_VOXELS],
    hits: [u8; BLOCK_VOXELS],
}

impl Block3 {
    fn unknown() -> Self {
        Block3 { log_odds: [f32::NAN; BLOCK_VOXELS], offset: [[128; 3]; BLOCK_VOXELS], hits: [0; BLOCK_VOXELS] }
    }
}

/// A multiplicative hash of a block key (Fibonacci hashing): keys are already well spread, and
/// the default SipHash cost half the likelihood field's time. Fixed, so that a map's layout
/// depends on its inputs only.
#[derive(Default)]
pub struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.0 = (self.0.rotate_left(8) ^ *b as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }
    fn write_u64(&mut self, k: u64) {
        self.0 = (k ^ (k >> 29)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }
}

type Blocks = HashMap<u64, Arc<Block3>, BuildHasherDefault<KeyHasher>>;

/// Room for `n` more blocks in a block table, or GridError::NoMemory (never an abort).
fn reserve_blocks(blocks: &mut Blocks, n: usize) -> Result<(), GridError> {
    blocks.try_reserve(n).map_err(|_| GridError::NoMemory {
        what: "the 3D map's voxel blocks",
        bytes: (n as u128).saturating_mul((std::mem::size_of::<Block3>() + 24) as u128),
    })
}

/// A sparse log-odds voxel grid with copy-on-write blocks (see the module docs).
#[derive(Clone)]
pub struct SharedVoxels {
    pub resolution: f64,
    pub model: LogOddsModel,
    blocks: Blocks,
}

impl SharedVoxels {
    pub fn new(resolution: f64, model: LogOddsModel) -> Result<Self, String> {
        // The checks of VoxelGrid::new, in one place.
        VoxelGrid::new(resolution, model)?;
        Ok(SharedVoxels { resolution, model, blocks: Blocks::default() })
    }

    #[inline]
    fn voxel(&self, i: [i64; 3]) -> Option<(&Block3, usize)> {
        if i.iter().any(|v| !(-INDEX_LIMIT..INDEX_LIMIT).contains(v)) {
            return None;
        }
        let key = pack(i);
        self.blocks.get(&(key >> 9)).map(|b| (&**b, (key & 511) as usize))
    }

    /// Log-odds of voxel `i`; NaN where unknown.
    #[inline]
    pub fn get(&self, i: [i64; 3]) -> f32 {
        self.voxel(i).map_or(f32::NAN, |(b, k)| b.log_odds[k])
    }

    /// Write one frame of rays (world frame) into the grid, serially (the filter runs the
    /// particles in parallel): voxel.rs's inverse sensor model, with copy-on-write blocks, and
    /// each end point averaged into its voxel's mean end point. Only every `free_stride`-th ray
    /// frees the voxels it passes through; every ray marks its end point (the likelihood field
    /// reads occupied voxels only, and neighbouring rays free nearly the same voxels).
    /// Fails (GridError::NoMemory), with the map as it was, where the blocks the frame adds
    /// cannot be had: growing the block table is the one large allocation of a 3D run.
    pub fn integrate(
        &mut self,
        origins: &[[f64; 3]],
        endpoints: &[[f64; 3]],
        max_range: f64,
        free_stride: usize,
    ) -> Result<IntegrateStats, GridError> {
        let mut stats = IntegrateStats::default();
        let (mut free, mut ignored) = (Vec::new(), Vec::new());
        let mut ends: Vec<(u64, [u8; 3])> = Vec::new();
        let mut seen = SeenFilter::new();
        let res = self.resolution;
        let limit = (INDEX_LIMIT - 2) as f64 * res;
        let free_stride = free_stride.max(1);
        for (n, (o, e)) in origins.iter().zip(endpoints).enumerate() {
            // Rays beyond the index range are skipped (the binding rejects them up front).
            if o.iter().chain(e).any(|v| !v.is_finite() || v.abs() > limit) {
                stats.skipped += 1;
                continue;
            }
            let hits_before = stats.hits;
            if n % free_stride == 0 {
                ray_voxels(*o, *e, max_range, res, &mut seen, &mut free, &mut ignored, &mut stats);
            } else if (0..3).map(|a| (e[a] - o[a]).powi(2)).sum::<f64>().sqrt() <= max_range {
                stats.hits += 1;
            } else {
                stats.max_range += 1;
            }
            if stats.hits > hits_before {
                let u = e.map(|v| v / res);
                let i = u.map(|v| v.floor() as i64);
                let off = [0, 1, 2].map(|a| ((u[a] - i[a] as f64) * 256.0).clamp(0.0, 255.0) as u8);
                ends.push((pack(i), off));
            }
        }
        free.sort_unstable();
        free.dedup();
        // Sorted by key and offset: the means do not depend on the order of the rays.
        ends.sort_unstable();
        let mut hit: Vec<u64> = ends.iter().map(|e| e.0).collect();
        hit.dedup();
        let free = sorted_difference(&free, &hit);
        stats.free_voxels = free.len();
        stats.occupied_voxels = hit.len();
        // The blocks the frame touches (the keys are sorted, so a block's keys lie together).
        let mut touched: Vec<u64> = Vec::new();
        for keys in [&free, &hit] {
            for &k in keys.iter() {
                if touched.last() != Some(&(k >> 9)) {
                    touched.push(k >> 9);
                }
            }
        }
        touched.sort_unstable();
        touched.dedup();
        let new_blocks = touched.iter().filter(|b| !self.blocks.contains_key(*b)).count();
        reserve_blocks(&mut self.blocks, new_blocks)?;
        self.apply(&free, self.model.l_free);
        self.apply(&hit, self.model.l_occ);
        self.average_ends(&ends);
        Ok(stats)
    }

    /// Add `delta` to the voxels of sorted keys, copying a shared block before its first write.
    fn apply(&mut self, keys: &[u64], delta: f32) {
        let (lo, hi) = (self.model.l_min, self.model.l_max);
        let mut i = 0;
        while i < keys.len() {
            let block_key = keys[i] >> 9;
            let block = Arc::make_mut(self.blocks.entry(block_key).or_insert_with(|| Arc::new(Block3::unknown())));
            while i < keys.len() && keys[i] >> 9 == block_key {
                let cell = &mut block.log_odds[(keys[i] & 511) as usize];
                let prior = if cell.is_nan() { 0.0 } else { *cell };
                *cell = (prior + delta).clamp(lo, hi);
                i += 1;
            }
        }
    }

    /// Fold end points (sorted (key, offset)) into their voxels' running means.
    fn average_ends(&mut self, ends: &[(u64, [u8; 3])]) {
        let mut i = 0;
        while i < ends.len() {
            let block_key = ends[i].0 >> 9;
            let block = Arc::make_mut(self.blocks.entry(block_key).or_insert_with(|| Arc::new(Block3::unknown())));
            while i < ends.len() && ends[i].0 >> 9 == block_key {
                let k = (ends[i].0 & 511) as usize;
                let n = block.hits[k].saturating_add(1);
                block.hits[k] = n;
                for a in 0..3 {
                    let m = block.offset[k][a] as f32;
                    block.offset[k][a] = (m + (ends[i].1[a] as f32 - m) / n as f32).round().clamp(0.0, 255.0) as u8;
                }
                i += 1;
            }
        }
    }

    /// Squared distance from world point `p` to the mean end point of the nearest voxel with
    /// log-odds above `threshold` among the 27 around the voxel holding `p`; None if there is
    /// none. Where the voxel holding p is occupied, its own mean is taken (one look-up; a
    /// neighbour's mean can lie nearer, by less than a voxel).
    #[inline]
    pub fn nearest_occupied(&self, p: [f64; 3], threshold: f32) -> Option<f64> {
        self.nearest_occupied_offset(p, threshold).map(|(d2, _)| d2)
    }

    /// As `nearest_occupied`, with the offset (m) from `p` to that mean end point.
    #[inline]
    pub fn nearest_occupied_offset(&self, p: [f64; 3], threshold: f32) -> Option<(f64, [f64; 3])> {
        let res = self.resolution;
        let u = p.map(|v| v / res);
        let c = u.map(|v| v.floor() as i64);
        // Offset (m) from p to the mean end point `off` (1/256 voxel) of voxel i, and its square.
        let offset = |i: [i64; 3], off: [u8; 3]| -> (f64, [f64; 3]) {
            let m = [0, 1, 2].map(|a| i[a] as f64 + (off[a] as f64 + 0.5) / 256.0);
            let d2 = (0..3).map(|a| (u[a] - m[a]).powi(2)).sum::<f64>() * res * res;
            (d2, [0, 1, 2].map(|a| (m[a] - u[a]) * res))
        };
        let own = |i: [i64; 3]| -> Option<(f64, [f64; 3])> {
            let (b, k) = self.voxel(i)?;
            // NaN (unknown) compares false.
            if !(b.log_odds[k] > threshold) {
                return None;
            }
            Some(offset(i, b.offset[k]))
        };
        if let Some(found) = own(c) {
            return Some(found);
        }
        // The 26 neighbours lie in at most 8 blocks: look each block up once.
        let mut cache: [(u64, Option<&Block3>); 8] = [(u64::MAX, None); 8];
        let mut cached = 0;
        let mut best: Option<(f64, [f64; 3])> = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if dx == 0 && dy == 0 && dz == 0 {
                        continue;
                    }
                    let i = [c[0] + dx, c[1] + dy, c[2] + dz];
                    if i.iter().any(|v| !(-INDEX_LIMIT..INDEX_LIMIT).contains(v)) {
                        continue;
                    }
                    let key = pack(i);
                    let bk = key >> 9;
                    let block = match cache[..cached].iter().find(|e| e.0 == bk) {
                        Some(e) => e.1,
                        None => {
                            let b = self.blocks.get(&bk).map(|b| &**b);
                            if cached < cache.len() {
                                cache[cached] = (bk, b);
                                cached += 1;
                            }
                            b
                        }
                    };
                    let Some(b) = block else { continue };
                    let k = (key & 511) as usize;
                    if !(b.log_odds[k] > threshold) {
                        continue;
                    }
                    let found = offset(i, b.offset[k]);
                    if best.is_none_or(|bb| found.0 < bb.0) {
                        best = Some(found);
                    }
                }
            }
        }
        best
    }

    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// The occupied voxels (log-odds above `threshold`) whose mean end points lie at heights
    /// [z_min, z_max] within the world rectangle `bounds` ([x0, y0, x1, y1]), seen from above: a
    /// 2D grid at the voxels' resolution whose cells are occupied (log-odds l_max) where any voxel
    /// of their column is, each with the mean of those voxels' mean end points. For the odometry
    /// check's wide search (correlative.rs searches 2D grids): every height of the frame's rays
    /// up to the projection's top, not the 2D filter's slice, so that where the slice holds a few
    /// readings (the office: 27 of 360 bins) the search still finds the desks, screens and upper
    /// walls. Fails where the rectangle is beyond the grid's reach.
    pub fn column_grid(&self, bounds: [f64; 4], z_min: f64, z_max: f64, threshold: f32) -> Result<TiledGrid, GridError> {
        let res = self.resolution;
        let mut grid = TiledGrid::new(res);
        grid.ensure_covers(bounds[0], bounds[1], bounds[2], bounds[3])?;
        let index = |v: f64| ((v / res).floor() as i64).clamp(-INDEX_LIMIT, INDEX_LIMIT - 1);
        let (ix0, iy0, iz0) = (index(bounds[0]), index(bounds[1]), index(z_min));
        let (ix1, iy1, iz1) = (index(bounds[2]), index(bounds[3]), index(z_max));
        // Block by block over the rectangle's blocks (a few hundred), not over the whole map.
        for bx in (ix0 >> BLOCK_SHIFT)..=(ix1 >> BLOCK_SHIFT) {
            for by in (iy0 >> BLOCK_SHIFT)..=(iy1 >> BLOCK_SHIFT) {
                for bz in (iz0 >> BLOCK_SHIFT)..=(iz1 >> BLOCK_SHIFT) {
                    let base = [bx << BLOCK_SHIFT, by << BLOCK_SHIFT, bz << BLOCK_SHIFT];
                    let key = pack(base);
                    let Some(block) = self.blocks.get(&(key >> 9)) else { continue };
                    for k in 0..BLOCK_VOXELS {
                        // NaN (unknown) compares false.
                        if !(block.log_odds[k] > threshold) {
                            continue;
                        }
                        let i = unpack((key & !511) | k as u64);
                        if i[0] < ix0 || i[0] > ix1 || i[1] < iy0 || i[1] > iy1 {
                            continue;
                        }
                        // The height of the voxel's mean end point, as the frame's points are
                        // chosen by theirs: the floor's voxel reaches 0.1 m, its points lie at 0.
                        let mean = [0, 1, 2].map(|a| (i[a] as f64 + (block.offset[k][a] as f64 + 0.5) / 256.0) * res);
                        if !(mean[2] >= z_min && mean[2] <= z_max) {
                            continue;
                        }
                        let (cx, cy) = (i[0] as i32, i[1] as i32);
                        if grid.get(cx, cy).is_nan() {
                            grid.add(cx, cy, self.model.l_max, &self.model);
                        }
                        grid.add_hit(mean[0], mean[1]);
                    }
                }
            }
        }
        Ok(grid)
    }

    pub fn blocks(&self) -> impl Iterator<Item = &Arc<Block3>> {
        self.blocks.values()
    }

    /// Bytes of one block (log-odds, mean end points, counts).
    pub const fn block_bytes() -> usize {
        std::mem::size_of::<Block3>()
    }

    /// A plain VoxelGrid with this grid's log-odds (for output: PLY, figures, the 2D projection).
    pub fn to_voxel_grid(&self) -> VoxelGrid {
        VoxelGrid::from_blocks(self.resolution, self.model, self.blocks.iter().map(|(k, b)| (*k, b.log_odds)))
    }
}

/// The 3D likelihood field (see the module docs).
#[derive(Clone, Copy, Debug)]
pub struct Field3d {
    pub sigma: f64,
    pub z_hit: f64,
    pub z_rand: f64,
    pub occupied_threshold: f32,
}

impl Field3d {
    /// (mean over `pts` (robot frame) of log p at planar pose `pose`, points with an occupied
    /// voxel within the window). Mean, not sum: see FilterParams3d::effective_rays.
    pub fn score(&self, map: &SharedVoxels, pose: [f64; 3], pts: &[[f64; 3]]) -> (f64, usize) {
        if pts.is_empty() {
            return (0.0, 0);
        }
        let (s, c) = pose[2].sin_cos();
        let inv = 1.0 / (2.0 * self.sigma * self.sigma);
        let floor = self.z_rand.max(1e-300).ln();
        let mut sum = 0.0;
        let mut matched = 0;
        for p in pts {
            let w = [pose[0] + c * p[0] - s * p[1], pose[1] + s * p[0] + c * p[1], p[2]];
            sum += match map.nearest_occupied(w, self.occupied_threshold) {
                Some(d2) => {
                    matched += 1;
                    (self.z_hit * (-d2 * inv).exp() + self.z_rand).ln()
                }
                None => floor,
            };
        }
        (sum / pts.len() as f64, matched)
    }
}

impl Field3d {
    /// For Gauss-Newton (`scan_match::gauss_newton_with`): at planar pose `pose`, (the sum over
    /// `pts` (robot frame) of what `score` averages, its gradient and Gauss-Newton Hessian in
    /// (x, y, θ), points with an occupied voxel in reach). Each point pulls towards its nearest
    /// occupied voxel's mean end point, weighted as iteratively reweighted least squares of its
    /// log-likelihood; points with none drop out of the step (they score the floor).
    pub fn linearise(&self, map: &SharedVoxels, pose: [f64; 3], pts: &[[f64; 3]]) -> (f64, [f64; 3], [[f64; 3]; 3], usize) {
        let (s, c) = pose[2].sin_cos();
        let inv = 1.0 / (2.0 * self.sigma * self.sigma);
        let floor = self.z_rand.max(1e-300).ln();
        let (mut total, mut matched) = (0.0, 0);
        let mut g = [0.0; 3];
        let mut h = [[0.0; 3]; 3];
        for p in pts {
            let (rx, ry) = (c * p[0] - s * p[1], s * p[0] + c * p[1]);
            let w = [pose[0] + rx, pose[1] + ry, p[2]];
            let Some((d2, off)) = map.nearest_occupied_offset(w, self.occupied_threshold) else {
                total += floor;
                continue;
            };
            matched += 1;
            let e = self.z_hit * (-d2 * inv).exp();
            total += (e + self.z_rand).ln();
            let weight = e / (e + self.z_rand) / (self.sigma * self.sigma);
            // Residual r = w − mean end point = −off; dw/d(x, y, θ) = [[1, 0, −ry], [0, 1, rx], [0, 0, 0]].
            let rows = [[1.0, 0.0, -ry], [0.0, 1.0, rx]];
            for (k, row) in rows.iter().enumerate() {
                for a in 0..3 {
                    g[a] += weight * row[a] * -off[k];
                    for b in 0..3 {
                        h[a][b] += weight * row[a] * row[b];
                    }
                }
            }
        }
        (total, g, h, matched)
    }
}

#[derive(Clone, Debug)]
pub struct FilterParams3d {
    pub n_particles: usize,
    pub seed: u64,
    pub threads: usize,
    pub motion: OdometryMotion,
    pub proposal: ProposalKind,
    pub field: Field3d,
    pub matcher: MatcherParams,
    /// A frame's log-likelihood is the mean over its scored end points times this number (as
    /// filter.rs's effective_beams): neighbouring rays are far from independent.
    pub effective_rays: f64,
    /// Score at most this many of the frame's rays, evenly spread over them (the map gets them
    /// all): the scan matcher evaluates about a hundred poses per particle, each over every scored ray.
    pub score_rays: usize,
    /// End points scored: those at heights within [score_z_min, score_z_max] (m) and within
    /// max_range of their origin. The floor tells nothing of (x, y, θ).
    pub score_z_min: f64,
    pub score_z_max: f64,
    /// The odometry check (check_odometry3d) matches the end points at heights within
    /// [check_z_min, check_z_max] (m): the obstacles of the map's 2D projection. Not the ceiling,
    /// which fits as well a metre to either side.
    pub check_z_min: f64,
    pub check_z_max: f64,
    pub log_odds: LogOddsModel,
    pub resolution: f64,
    /// Rays longer than this (m) free space up to it and mark nothing.
    pub max_range: f64,
    /// Every n-th ray frees the voxels it passes through (see SharedVoxels::integrate).
    pub free_stride: usize,
    /// The scan-matching proposal climbs on every n-th scored ray (then fits its Gaussian and
    /// weighs on all of them): the climb evaluates most of the poses.
    pub climb_stride: usize,
    pub resample_threshold: f64,
}

#[derive(Clone)]
pub struct Particle3d {
    pub pose: [f64; 3],
    pub log_weight: f64,
    pub map: SharedVoxels,
    pub trajectory: Arc<TrajectoryNode>,
}

#[derive(Clone, Copy, Debug, Default)]
pub struct StepInfo3d {
    pub neff: f64,
    pub resampled: bool,
    pub fallbacks: usize,
    /// Rays scored for the weights.
    pub scored: usize,
    /// Whether the odometry check replaced the step's odometry (check_odometry3d).
    pub odometry_corrected: bool,
}

pub struct ParticleFilter3d {
    pub params: FilterParams3d,
    pub particles: Vec<Particle3d>,
    pub steps: u64,
    pub resamplings: u64,
    pub fallbacks: u64,
    best: usize,
    pool: rayon::ThreadPool,
}

/// (x, y, z) of a planar pose applied to a robot-frame point.
#[inline]
fn to_world(pose: [f64; 3], p: [f64; 3]) -> [f64; 3] {
    let (s, c) = pose[2].sin_cos();
    [pose[0] + c * p[0] - s * p[1], pose[1] + s * p[0] + c * p[1], p[2]]
}

/// A scan-match proposal's outcome (as scan_match::Proposal).
struct Drawn {
    pose: [f64; 3],
    log_normaliser: f64,
}

impl ParticleFilter3d {
    pub fn new(params: FilterParams3d) -> Result<Self, String> {
        if params.n_particles == 0 {
            return Err("n_particles must be at least 1".into());
        }
        if params.score_rays == 0 {
            return Err("score_rays must be at least 1".into());
        }
        if !(params.field.sigma > 0.0 && params.field.z_rand > 0.0 && params.field.z_hit >= 0.0) {
            return Err("the likelihood field needs sigma > 0, z_rand > 0, z_hit >= 0".into());
        }
        if !(params.max_range > 0.0) {
            return Err(format!("max_range must be > 0, got {}", params.max_range));
        }
        SharedVoxels::new(params.resolution, params.log_odds)?;
        let pool = rayon::ThreadPoolBuilder::new().num_threads(params.threads.max(1)).build().map_err(|e| e.to_string())?;
        Ok(ParticleFilter3d { params, particles: Vec::new(), steps: 0, resamplings: 0, fallbacks: 0, best: 0, pool })
    }

    /// The robot-frame end points a frame is weighed by (see FilterParams3d): of the rays whose
    /// end points lie in the height band and within max_range, at most score_rays, evenly spread.
    pub fn scored_points(&self, origins: &[[f64; 3]], endpoints: &[[f64; 3]]) -> Vec<[f64; 3]> {
        self.rays_between(origins, endpoints, self.params.score_z_min, self.params.score_z_max).into_iter().map(|r| r.1).collect()
    }

    /// Of the rays (origin, end point) whose end points lie at heights [z_min, z_max] and within
    /// max_range, at most score_rays, evenly spread.
    fn rays_between(&self, origins: &[[f64; 3]], endpoints: &[[f64; 3]], z_min: f64, z_max: f64) -> Vec<([f64; 3], [f64; 3])> {
        let p = &self.params;
        let candidates: Vec<([f64; 3], [f64; 3])> = origins
            .iter()
            .zip(endpoints)
            .filter(|(o, e)| {
                let d2: f64 = (0..3).map(|a| (e[a] - o[a]).powi(2)).sum();
                e.iter().all(|v| v.is_finite()) && d2.sqrt() <= p.max_range && e[2] >= z_min && e[2] <= z_max
            })
            .map(|(o, e)| (*o, *e))
            .collect();
        let n = candidates.len();
        if n <= p.score_rays {
            return candidates;
        }
        (0..p.score_rays).map(|k| candidates[k * n / p.score_rays]).collect()
    }

    /// Integrate one frame of rays (robot frame: origins on the mirrors, end points) taken at
    /// odometry pose `odom_cur`, the robot having come from `odom_prev` since the last one. The
    /// first call starts every particle's map at `odom_cur`. Origins and end points must be
    /// finite and within the grid's reach (the binding checks).
    /// Fails (GridError::NoMemory) where a particle's map cannot grow; the filter is then spent,
    /// as a run that ran out of memory is.
    pub fn step(
        &mut self,
        odom_prev: [f64; 3],
        odom_cur: [f64; 3],
        origins: &[[f64; 3]],
        endpoints: &[[f64; 3]],
        scan: u64,
    ) -> Result<StepInfo3d, GridError> {
        let step_index = self.steps;
        self.steps += 1;
        let n = self.params.n_particles;
        if self.particles.is_empty() {
            let mut map = self.empty_map();
            self.integrate_frame(&mut map, odom_cur, origins, endpoints)?;
            self.reset(odom_cur, scan, map);
            return Ok(StepInfo3d { neff: n as f64, resampled: false, fallbacks: 0, scored: 0, odometry_corrected: false });
        }
        let pts = self.scored_points(origins, endpoints);
        let p = &self.params;
        let corrected = match (p.proposal, self.particles.get(self.best), p.matcher.check.window.is_some()) {
            (ProposalKind::ScanMatch, Some(best), true) => {
                let walls = self.rays_between(origins, endpoints, p.check_z_min, p.check_z_max);
                check_odometry3d(p, &best.map, &walls, best.pose, odom_prev, odom_cur)?
            }
            _ => None,
        };
        let odom_cur = corrected.unwrap_or(odom_cur);
        let seed = p.seed;
        let fell: Vec<Result<bool, GridError>> = self.pool.install(|| {
            self.particles
                .par_iter_mut()
                .enumerate()
                .map(|(i, part)| {
                    let mut rng = rng_for(seed, step_index, i as u64);
                    let drawn = match p.proposal {
                        ProposalKind::ScanMatch => propose3d(p, &part.map, &pts, part.pose, odom_prev, odom_cur, &mut rng),
                        ProposalKind::Odometry => None,
                    };
                    let fell_back = p.proposal == ProposalKind::ScanMatch && drawn.is_none();
                    let pose = match drawn {
                        Some(d) => {
                            part.log_weight += d.log_normaliser;
                            d.pose
                        }
                        None => {
                            let pose = fallback_pose(p.proposal, &p.matcher, &p.motion, part.pose, odom_prev, odom_cur, &mut rng);
                            part.log_weight += p.effective_rays * p.field.score(&part.map, pose, &pts).0;
                            pose
                        }
                    };
                    part.pose = pose;
                    part.trajectory = Arc::new(TrajectoryNode { pose, scan, parent: Some(part.trajectory.clone()) });
                    let (wo, we) = Self::world_rays(pose, origins, endpoints);
                    part.map.integrate(&wo, &we, p.max_range, p.free_stride)?;
                    Ok(fell_back)
                })
                .collect()
        });
        // In particle order, so that the error reported does not depend on the thread count.
        let mut fallbacks = 0;
        for f in fell {
            fallbacks += f? as usize;
        }
        self.fallbacks += fallbacks as u64;
        let log_w: Vec<f64> = self.particles.iter().map(|q| q.log_weight).collect();
        let weighing = Weighing::new(&log_w, self.params.resample_threshold, seed, step_index);
        if let Some(idx) = &weighing.ancestors {
            self.particles = idx
                .iter()
                .map(|&j| {
                    let mut q = self.particles[j].clone();
                    q.log_weight = 0.0;
                    q
                })
                .collect();
            self.resamplings += 1;
        } else {
            for q in &mut self.particles {
                q.log_weight -= weighing.max_log_weight;
            }
        }
        self.best = weighing.best_after();
        Ok(StepInfo3d {
            neff: weighing.n_eff,
            resampled: weighing.ancestors.is_some(),
            fallbacks,
            scored: pts.len(),
            odometry_corrected: corrected.is_some(),
        })
    }

    /// An empty map of the filter's resolution and log-odds model.
    pub fn empty_map(&self) -> SharedVoxels {
        // Resolution and model were checked by `new`.
        SharedVoxels { resolution: self.params.resolution, model: self.params.log_odds, blocks: Blocks::default() }
    }

    /// Write one frame of rays (robot frame) taken at `pose` into `map`, as `step` writes a
    /// frame into each particle's map.
    pub fn integrate_frame(&self, map: &mut SharedVoxels, pose: [f64; 3], origins: &[[f64; 3]], endpoints: &[[f64; 3]]) -> Result<(), GridError> {
        let (wo, we) = Self::world_rays(pose, origins, endpoints);
        map.integrate(&wo, &we, self.params.max_range, self.params.free_stride).map(|_| ())
    }

    /// Restart every particle at `pose`, its trajectory beginning at `scan`, all sharing `map`.
    /// The first frame starts the run this way; the pose-graph back end
    /// (python/omnitof/slam/backend.py) restarts the filter this way at a correction, on a map
    /// of every integrated frame written at its optimised pose (`integrate_frame`).
    pub fn reset(&mut self, pose: [f64; 3], scan: u64, map: SharedVoxels) {
        let root = Arc::new(TrajectoryNode { pose, scan, parent: None });
        let first = Particle3d { pose, log_weight: 0.0, map, trajectory: root };
        self.particles = vec![first; self.params.n_particles];
        self.best = 0;
    }

    fn world_rays(pose: [f64; 3], origins: &[[f64; 3]], endpoints: &[[f64; 3]]) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        (origins.iter().map(|o| to_world(pose, *o)).collect(), endpoints.iter().map(|e| to_world(pose, *e)).collect())
    }

    pub fn best(&self) -> Option<&Particle3d> {
        self.particles.get(self.best)
    }

    /// (distinct blocks over all particles, block references over all particles).
    pub fn block_counts(&self) -> (usize, usize) {
        self.block_counts_of(&self.particles.iter().collect::<Vec<_>>())
    }

    /// (distinct blocks, block references) over the maps of `particles`.
    pub fn block_counts_of(&self, particles: &[&Particle3d]) -> (usize, usize) {
        let mut seen = HashSet::new();
        let mut refs = 0;
        for q in particles {
            for b in q.map.blocks() {
                refs += 1;
                seen.insert(Arc::as_ptr(b) as usize);
            }
        }
        (seen.len(), refs)
    }
}

/// The scan-matching proposal in 3D (Grisetti et al. 2007, as scan_match::propose): hill
/// climbing (scan_match::climb) of gain·(mean log-likelihood of the scored end points) + the
/// odometry prior's log density from the odometry prediction; then the target at the 27 poses
/// around the mode, a Gaussian fitted to them, one pose drawn from it, and the log of the
/// target's sum there as the weight's factor. None where fewer than min_matched of the points
/// find an occupied voxel at the mode (the caller falls back to the odometry proposal).
fn propose3d<R: rand::Rng>(
    p: &FilterParams3d,
    map: &SharedVoxels,
    pts: &[[f64; 3]],
    prev_pose: [f64; 3],
    odom_prev: [f64; 3],
    odom_cur: [f64; 3],
    rng: &mut R,
) -> Option<Drawn> {
    if pts.is_empty() {
        return None;
    }
    let m: &MatcherParams = &p.matcher;
    let predicted = compose(prev_pose, relative(odom_prev, odom_cur));
    let prior: PosePrior = motion_prior(&p.motion, odom_prev, odom_cur, predicted).with_dof(m.prior_dof);
    let target = |pose: [f64; 3]| p.effective_rays * p.field.score(map, pose, pts).0 + prior.log_prob(pose);
    let start = if m.climb_from_sample { p.motion.sample(prev_pose, odom_prev, odom_cur, rng) } else { predicted };
    let (mode, _, matched) = local_match3d(p, map, pts, start, m.odometry_prior.then_some(&prior));
    if (matched as f64) < m.min_matched * pts.len() as f64 {
        return None;
    }
    let (pose, log_normaliser) = draw_around_mode(target, mode, m.sample_xy, m.sample_theta, rng);
    Some(Drawn { pose, log_normaliser })
}

/// Hill climbing on every `climb_stride`-th scored ray, then Gauss-Newton on all of them, from
/// `start` to the mode of the frame's likelihood (times `prior`, if any): (mode, objective there,
/// end points with an occupied voxel within the window). The 3D twin of scan_match::local_match.
fn local_match3d(
    p: &FilterParams3d,
    map: &SharedVoxels,
    pts: &[[f64; 3]],
    start: [f64; 3],
    prior: Option<&PosePrior>,
) -> ([f64; 3], f64, usize) {
    let sparse: Vec<[f64; 3]> = pts.iter().step_by(p.climb_stride.max(1)).copied().collect();
    let climb_goal = |pose: [f64; 3]| {
        let s = p.effective_rays * p.field.score(map, pose, &sparse).0;
        prior.map_or(s, |q| s + q.log_prob(pose))
    };
    let (mode, _) = climb(climb_goal, start, &p.matcher);
    // Below the climb's last step, Gauss-Newton on all the scored rays (as the 2D matcher).
    gauss_newton_with(|pose| p.field.linearise(map, pose, pts), pts.len(), p.effective_rays, prior, mode, p.matcher.gauss_newton)
}

/// The odometry check for the 3D filter (as scan_match::check_odometry does it in 2D), on the
/// frame's `rays` at the heights of the map's 2D projection, in the best particle's map from its
/// `pose`. Returns the odometry pose that would have predicted the pose found, or None where
/// the odometry stands:
/// 1. At the odometry's prediction, the share of the end points near an occupied voxel among
///    those the map can judge (`explained_share`); at least `search_below`: it stands.
/// 2. A climb without the odometry prior from there (`local_match3d`). Where that explains the
///    frame, the particles' own climbs get there too unless their odometry prior holds them back
///    (the climb ended more than three standard deviations of the prior away): then its pose is
///    taken if it explains clearly more than the prediction (a tenth more of the judged points).
/// 3. Otherwise the wide search (correlative.rs) around the prediction, in 2D: the map's occupied
///    columns (`SharedVoxels::column_grid`) and the end points seen from above; where its pose
///    stands out (`search_distinct`), a 3D climb from it, taken where it explains the frame and
///    clearly more of it than the climb of step 2.
///
/// Why a search in 2D: the pose is planar, and the raster search is what finds a frame a metre
/// from its prediction; the 3D climb then judges the jump on every point's height, which the
/// projection has thrown away.
fn check_odometry3d(
    p: &FilterParams3d,
    map: &SharedVoxels,
    rays: &[([f64; 3], [f64; 3])],
    pose: [f64; 3],
    odom_prev: [f64; 3],
    odom_cur: [f64; 3],
) -> Result<Option<[f64; 3]>, GridError> {
    let m = &p.matcher.check;
    let Some(window) = m.window.as_ref() else { return Ok(None) };
    // As in 2D (scan_match::check_odometry): too few points to tell one place from another.
    if rays.is_empty() || rays.len() < m.min_points {
        return Ok(None);
    }
    let pts: Vec<[f64; 3]> = rays.iter().map(|r| r.1).collect();
    let pts = &pts[..];
    let predicted = compose(pose, relative(odom_prev, odom_cur));
    let n = pts.len() as f64;
    let share = |at: [f64; 3]| explained_share(p, map, at, rays);
    let at_prediction = share(predicted);
    if at_prediction.0 >= m.below {
        return Ok(None);
    }
    let (local, local_value, _) = local_match3d(p, map, pts, predicted, None);
    let at_local = share(local);
    let accept = |found: [f64; 3], value: f64, baseline: (f64, usize), baseline_value: f64| {
        let (fs, fc) = share(found);
        fs >= m.accept && fc as f64 >= 0.3 * n && fs >= baseline.0 + 0.1 && value > baseline_value
    };
    if at_local.0 >= m.below {
        // The climb alone explains the frame. Where the particles' climbs can get there too (within
        // three standard deviations of the odometry prior), they will; where the prior holds them
        // at the wheels' pose, the wheels slipped.
        let prior = motion_prior(&p.motion, odom_prev, odom_cur, predicted);
        let within_reach = !p.matcher.odometry_prior || prior.mahalanobis2(local) <= 9.0;
        if within_reach || !accept(local, local_value, at_prediction, p.effective_rays * p.field.score(map, predicted, pts).0) {
            return Ok(None);
        }
        return Ok(Some(compose(odom_prev, relative(pose, local))));
    }
    // The points lie within max_range of the mirrors, which stand within centimetres of the robot.
    let reach = p.max_range + window.half_xy + 1.0;
    let bounds = [predicted[0] - reach, predicted[1] - reach, predicted[0] + reach, predicted[1] + reach];
    let grid = map.column_grid(bounds, p.check_z_min, p.check_z_max, p.field.occupied_threshold)?;
    let flat: Vec<[f64; 2]> = pts.iter().map(|q| [q[0], q[1]]).collect();
    let geom = ScanGeometry { angles: &[], sensor: [0.0; 3] };
    // The 2D field's floor, as the 2D check passes it (z_rand over the range).
    let floor = p.field.z_rand / p.max_range;
    let searched = correlative_search(&grid, p.field.occupied_threshold, floor, &geom, &flat, predicted, window)?;
    if searched.distinct < m.distinct {
        return Ok(None);
    }
    let (found, value, _) = local_match3d(p, map, pts, searched.pose, None);
    Ok(accept(found, value, at_local, local_value).then(|| compose(odom_prev, relative(pose, found))))
}

/// Of the frame's rays at `pose`, the share whose end points lie near an occupied voxel among
/// those that the map can judge, and how many it can judge: those near an occupied voxel, those
/// ending in a voxel it has observed (free), and those that pass through an occupied voxel on
/// their way (the map has a wall in front of the end point). Why not the share of all end
/// points: a robot driving on sees things the map has not, and a pose that pulls those points
/// back onto mapped ones (a few decimetres back along its way) explains more of them than the
/// right pose does; what contradicts a pose is an end point in space the map has seen empty, or
/// behind a surface it has seen.
fn explained_share(p: &FilterParams3d, map: &SharedVoxels, pose: [f64; 3], rays: &[([f64; 3], [f64; 3])]) -> (f64, usize) {
    let res = map.resolution;
    let threshold = p.field.occupied_threshold;
    let voxel = |w: [f64; 3]| w.map(|v| (v / res).floor() as i64);
    let (mut near, mut judged) = (0usize, 0usize);
    for (o, e) in rays {
        let (wo, we) = (to_world(pose, *o), to_world(pose, *e));
        if map.nearest_occupied(we, threshold).is_some() {
            near += 1;
            judged += 1;
            continue;
        }
        if !map.get(voxel(we)).is_nan() {
            judged += 1;
            continue;
        }
        // The voxels the ray passes up to two voxels short of its end point (whose neighbours
        // the test above has read).
        let d = [0, 1, 2].map(|a| we[a] - wo[a]);
        let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let reach = length - 2.0 * res;
        let mut blocked = false;
        if reach > 0.0 {
            traverse(wo, d.map(|v| v / length), reach, res, |i, _, _| {
                blocked = map.get(i) > threshold;
                !blocked
            });
        }
        judged += blocked as usize;
    }
    (if judged == 0 { 1.0 } else { near as f64 / judged as f64 }, judged)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::correlative::SearchWindow;
    use crate::scan_match::OdometryCheck;

    const MODEL: LogOddsModel = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };
    /// Robot-frame origin of every ray: the mirrors, half a metre above the floor.
    const SENSOR: [f64; 3] = [0.0, 0.0, 0.5];

    /// Axis-aligned boxes (min, max): the room (seen from inside) and obstacles (from outside).
    const ROOM: ([f64; 3], [f64; 3]) = ([-3.0, -2.0, 0.0], [3.0, 2.0, 2.5]);
    const OBSTACLES: [([f64; 3], [f64; 3]); 2] = [
        ([1.0, 0.5, 0.0], [1.4, 0.9, 2.5]),   // a pillar
        ([-3.0, -1.0, 1.5], [-2.6, 1.0, 2.0]), // a shelf high on a wall
    ];

    /// Slab test: the entry and exit distances of a ray through a box.
    fn slab(o: [f64; 3], d: [f64; 3], b: ([f64; 3], [f64; 3])) -> (f64, f64) {
        let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
        for a in 0..3 {
            let (ta, tb) = ((b.0[a] - o[a]) / d[a], (b.1[a] - o[a]) / d[a]);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
        (t0, t1)
    }

    /// An exact ray cast in the analytic world: the nearest surface along o + t·d.
    fn cast(o: [f64; 3], d: [f64; 3]) -> f64 {
        let mut t = slab(o, d, ROOM).1;
        for b in OBSTACLES {
            let (t0, t1) = slab(o, d, b);
            if t0 > 0.0 && t0 <= t1 {
                t = t.min(t0);
            }
        }
        t
    }

    /// One frame at world pose `pose`: (origins, end points) in the robot frame, rays every
    /// `az_deg` in azimuth and every 5° in elevation from −20° to +30°.
    fn frame(pose: [f64; 3], az_deg: f64, az_range: (f64, f64)) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        let (mut os, mut es) = (vec![], vec![]);
        let ow = to_world(pose, SENSOR);
        let mut az = az_range.0;
        while az < az_range.1 {
            for k in -4..=6 {
                let (el, a) = ((k as f64 * 5.0).to_radians(), az.to_radians());
                let dr = [el.cos() * a.cos(), el.cos() * a.sin(), el.sin()];
                let (s, c) = pose[2].sin_cos();
                let dw = [c * dr[0] - s * dr[1], s * dr[0] + c * dr[1], dr[2]];
                let t = cast(ow, dw);
                os.push(SENSOR);
                es.push([SENSOR[0] + t * dr[0], SENSOR[1] + t * dr[1], SENSOR[2] + t * dr[2]]);
            }
            az += az_deg;
        }
        (os, es)
    }

    fn params(n: usize, threads: usize, proposal: ProposalKind) -> FilterParams3d {
        FilterParams3d {
            n_particles: n,
            seed: 7,
            threads,
            motion: OdometryMotion { alpha: [0.01, 0.001, 0.01, 0.001] },
            proposal,
            field: Field3d { sigma: 0.1, z_hit: 0.9, z_rand: 0.1, occupied_threshold: 0.0 },
            matcher: MatcherParams {
                step_xy: 0.05,
                step_theta: 2f64.to_radians(),
                refinements: 3,
                gauss_newton: 0,
                sample_xy: 0.01,
                sample_theta: 0.25f64.to_radians(),
                min_matched: 0.3,
                effective_beams: 9.0,
                odometry_prior: true,
                prior_dof: 0.0,
                climb_from_sample: false,
                fallback_draw: true,
                check: OdometryCheck::OFF,
            },
            effective_rays: 9.0,
            score_rays: 600,
            score_z_min: 0.05,
            score_z_max: 10.0,
            check_z_min: 0.05,
            check_z_max: 2.2,
            log_odds: MODEL,
            resolution: 0.1,
            max_range: 7.0,
            free_stride: 2,
            climb_stride: 1,
            resample_threshold: 0.5,
        }
    }

    fn known_map() -> SharedVoxels {
        let mut map = SharedVoxels::new(0.1, MODEL).unwrap();
        for pose in [[0.0, 0.0, 0.0], [0.4, 0.2, 0.3], [-0.5, -0.3, -0.4], [0.2, -0.6, 1.2]] {
            let (o, e) = frame(pose, 2.0, (-180.0, 180.0));
            let (wo, we) = ParticleFilter3d::world_rays(pose, &o, &e);
            for _ in 0..3 {
                map.integrate(&wo, &we, 7.0, 1).unwrap();
            }
        }
        map
    }

    #[test]
    fn a_block_table_that_cannot_grow_is_an_error_not_an_abort() {
        let mut blocks = Blocks::default();
        assert!(reserve_blocks(&mut blocks, 1000).is_ok());
        match reserve_blocks(&mut blocks, usize::MAX / 2) {
            Err(GridError::NoMemory { what, bytes }) => {
                assert_eq!(what, "the 3D map's voxel blocks");
                assert!(bytes > 1u128 << 60);
            }
            other => panic!("expected NoMemory, got {other:?}"),
        }
    }

    #[test]
    fn gauss_newton_brings_a_pose_below_the_climbs_step_to_the_truth() {
        // Started up to 4 cm and 0.6° off in the known room (0.1 m voxels, below the climb's
        // 5 cm first step), Gauss-Newton on the field ends within a tenth of a voxel and 0.35°
        // of the true pose (3-5 mm, 0.17-0.25°), and its objective rose.
        let map = known_map();
        let field = params(1, 1, ProposalKind::Odometry).field;
        let truth = [0.13, -0.07, 0.21];
        let (_, e) = frame(truth, 3.0, (-180.0, 180.0));
        let pts: Vec<[f64; 3]> = e.into_iter().filter(|p| p[2] > 0.05).collect();
        for start in [[0.17, -0.07, 0.21], [0.13, -0.11, 0.22], [0.10, -0.04, 0.20]] {
            let first = field.linearise(&map, start, &pts).0;
            let (pose, value, matched) = gauss_newton_with(|p| field.linearise(&map, p, &pts), pts.len(), 1.0, None, start, 20);
            let err = (pose[0] - truth[0]).hypot(pose[1] - truth[1]);
            println!("from {start:?}: {:.4} m, {:.4} rad", err, (pose[2] - truth[2]).abs());
            assert!(err < 0.01 && (pose[2] - truth[2]).abs() < 0.006, "from {start:?}: {pose:?}");
            assert!(value > first / pts.len() as f64 && matched > pts.len() / 2);
        }
    }

    #[test]
    fn likelihood_peaks_at_the_true_pose_and_falls_off_in_x_y_theta() {
        let map = known_map();
        let field = params(1, 1, ProposalKind::Odometry).field;
        let truth = [0.13, -0.07, 0.21];
        let (_, e) = frame(truth, 3.0, (-180.0, 180.0));
        let pts: Vec<[f64; 3]> = e.into_iter().filter(|p| p[2] > 0.05).collect();
        let at = |d: [f64; 3]| field.score(&map, [truth[0] + d[0], truth[1] + d[1], truth[2] + d[2]], &pts).0;
        let best = at([0.0; 3]);
        for axis in 0..3 {
            let unit = if axis == 2 { 0.05 } else { 0.1 };
            for sign in [-1.0, 1.0] {
                let mut d1 = [0.0; 3];
                d1[axis] = sign * unit;
                let mut d2 = [0.0; 3];
                d2[axis] = sign * 2.0 * unit;
                let (l1, l2) = (at(d1), at(d2));
                assert!(best > l1 && l1 > l2, "axis {axis} sign {sign}: {best} {l1} {l2}");
            }
        }
    }

    #[test]
    fn resampled_particles_share_the_blocks_they_did_not_change() {
        let mut p = params(20, 2, ProposalKind::Odometry);
        p.resample_threshold = 2.0; // resample at every step
        let mut pf = ParticleFilter3d::new(p).unwrap();
        let (o, e) = frame([0.0; 3], 2.0, (-180.0, 180.0));
        pf.step([0.0; 3], [0.0; 3], &o, &e, 0).unwrap();
        let b0 = pf.particles[0].map.block_count();
        assert_eq!(pf.block_counts(), (b0, 20 * b0));
        let initial: HashSet<usize> = pf.particles[0].map.blocks().map(|b| Arc::as_ptr(b) as usize).collect();
        let before: HashMap<u64, Block> = pf.particles[0].map.blocks.iter().map(|(k, b)| (*k, b.log_odds)).collect();
        // A frame that looks along +x only touches a few blocks.
        let (o, e) = frame([0.1, 0.0, 0.0], 2.0, (-10.0, 10.0));
        let info = pf.step([0.0; 3], [0.1, 0.0, 0.0], &o, &e, 1).unwrap();
        assert!(info.resampled);
        let (distinct, refs) = pf.block_counts();
        assert!(refs >= 20 * b0);
        for q in &pf.particles {
            let mut changed = 0;
            for (k, b) in &q.map.blocks {
                let same = before.get(k).is_some_and(|v| v.iter().zip(b.log_odds.iter()).all(|(x, y)| x.to_bits() == y.to_bits()));
                if same {
                    // An unchanged block is the one all particles held: no copy was made.
                    assert!(initial.contains(&(Arc::as_ptr(b) as usize)));
                } else {
                    changed += 1;
                }
            }
            assert!(changed > 0 && changed * 4 < b0, "changed {changed} of {b0}");
        }
        // Memory measured: distinct blocks hold far less than one map per particle.
        assert!(distinct * 4 < refs, "distinct {distinct}, references {refs}");
    }

    fn run(threads: usize, proposal: ProposalKind) -> (Vec<[u64; 3]>, Vec<u64>, (usize, usize)) {
        let mut pf = ParticleFilter3d::new(params(12, threads, proposal)).unwrap();
        let truth = [[0.0, 0.0, 0.0], [0.2, 0.05, 0.1], [0.4, 0.1, 0.25], [0.55, 0.2, 0.45], [0.6, 0.35, 0.7]];
        let mut prev = truth[0];
        for (k, t) in truth.iter().enumerate() {
            let (o, e) = frame(*t, 4.0, (-180.0, 180.0));
            // Odometry that drifts: 10 % long in translation.
            let odom = [t[0] * 1.1, t[1] * 1.1, t[2]];
            pf.step(prev, odom, &o, &e, k as u64).unwrap();
            prev = odom;
        }
        let poses = pf.particles.iter().map(|q| q.pose.map(f64::to_bits)).collect();
        let weights = pf.particles.iter().map(|q| q.log_weight.to_bits()).collect();
        (poses, weights, pf.block_counts())
    }

    #[test]
    fn same_seed_same_result_for_one_and_two_threads() {
        for proposal in [ProposalKind::Odometry, ProposalKind::ScanMatch] {
            assert_eq!(run(1, proposal), run(2, proposal));
        }
    }

    #[test]
    fn reset_restarts_every_particle_on_one_map_of_the_frames_at_their_new_poses() {
        // Two frames taken at `taken`, written at the poses a pose graph moved them to: the
        // map is the one the frames' world rays make, shared by all particles (one map's
        // blocks), each particle at the restart pose with a one-node trajectory.
        let mut pf = ParticleFilter3d::new(params(8, 2, ProposalKind::ScanMatch)).unwrap();
        let taken = [[0.0, 0.0, 0.0], [0.5, 0.1, 0.2]];
        let moved = [[0.05, -0.02, 0.01], [0.52, 0.15, 0.23]];
        let frames: Vec<_> = taken.iter().map(|t| frame(*t, 3.0, (-180.0, 180.0))).collect();
        for (k, (t, (o, e))) in taken.iter().zip(&frames).enumerate() {
            pf.step(taken[k.saturating_sub(1)], *t, o, e, k as u64).unwrap();
        }
        let mut map = pf.empty_map();
        for (m, (o, e)) in moved.iter().zip(&frames) {
            pf.integrate_frame(&mut map, *m, o, e).unwrap();
        }
        pf.reset(moved[1], 7, map);
        let mut expected = SharedVoxels::new(0.1, MODEL).unwrap();
        for (m, (o, e)) in moved.iter().zip(&frames) {
            let (wo, we) = ParticleFilter3d::world_rays(*m, o, e);
            expected.integrate(&wo, &we, 7.0, 2).unwrap();
        }
        let cells = |v: &SharedVoxels| -> Vec<([i64; 3], u32)> {
            let mut c: Vec<_> = v.to_voxel_grid().observed().into_iter().map(|(i, l)| (i, l.to_bits())).collect();
            c.sort();
            c
        };
        assert_eq!(cells(&pf.particles[0].map), cells(&expected));
        assert_eq!(pf.block_counts(), (expected.block_count(), 8 * expected.block_count()));
        for q in &pf.particles {
            assert_eq!(q.pose, moved[1]);
            assert_eq!(q.trajectory.lineage(), vec![(7, moved[1])]);
        }
        // The filter goes on from there: the next frame, taken 0.2 m on from the restart pose,
        // is matched on the rebuilt map.
        let next = [moved[1][0] + 0.2, moved[1][1], moved[1][2]];
        let (o, e) = frame(next, 3.0, (-180.0, 180.0));
        pf.step(taken[1], [taken[1][0] + 0.23, taken[1][1], taken[1][2]], &o, &e, 8).unwrap();
        let best = pf.best().unwrap().pose;
        assert!((best[0] - next[0]).hypot(best[1] - next[1]) < 0.03, "best {best:?}, truth {next:?}");
    }

    #[test]
    fn column_grid_sees_every_height_in_its_band_from_above() {
        // The known room's pillar stands 1.0-1.4 x 0.5-0.9 m, floor to ceiling; the shelf at
        // x -3.0..-2.6 only at 1.5-2.0 m. From above through 0.05-2.2 m both show, with each
        // cell's point on a face of the box (the map's mean end points); through 0.05-1.3 m the
        // shelf's face at x = -2.6 does not.
        let map = known_map();
        let bounds = [-3.5, -2.5, 3.5, 2.5];
        let near_face = |grid: &TiledGrid, x: f64, y0: f64, y1: f64| -> usize {
            let res = grid.resolution;
            let mut found = 0;
            for iy in ((y0 / res).floor() as i32)..((y1 / res).floor() as i32) {
                for ix in ((x / res).floor() as i32 - 1)..=((x / res).floor() as i32) {
                    if let Some(h) = grid.occupied_hit(ix, iy, 0.0) {
                        if (h[0] - x).abs() < 0.03 {
                            found += 1;
                        }
                    }
                }
            }
            found
        };
        let all = map.column_grid(bounds, 0.05, 2.2, 0.0).unwrap();
        let low = map.column_grid(bounds, 0.05, 1.3, 0.0).unwrap();
        // The pillar's west face (x = 1.0) over its 0.4 m, four cells, in both.
        assert!(near_face(&all, 1.0, 0.55, 0.85) >= 3, "{}", near_face(&all, 1.0, 0.55, 0.85));
        assert!(near_face(&low, 1.0, 0.55, 0.85) >= 3);
        // The shelf's face over 2 m: twenty cells, most of them seen.
        assert!(near_face(&all, -2.6, -0.9, 0.9) >= 12, "{}", near_face(&all, -2.6, -0.9, 0.9));
        assert_eq!(near_face(&low, -2.6, -0.9, 0.9), 0);
        // Nothing where the room is empty at every height.
        for (x, y) in [(0.0, 0.0), (-1.5, 1.0), (2.0, -1.2)] {
            let (ix, iy) = ((x / 0.1f64).floor() as i32, (y / 0.1f64).floor() as i32);
            assert!(all.occupied_hit(ix, iy, 0.0).is_none());
        }
    }

    /// A filter that has mapped the known room from the origin, then one frame taken at
    /// `truth` whose odometry reports `odom` instead: the particles' poses and the step's info.
    fn after_glitch(search: bool, distinct: f64, truth: [f64; 3], odom: [f64; 3]) -> (Vec<[f64; 3]>, StepInfo3d) {
        let mut p = params(8, 2, ProposalKind::ScanMatch);
        if search {
            p.matcher.check.window = Some(SearchWindow {
                half_xy: 1.0,
                half_theta: 15f64.to_radians(),
                step_xy: 0.1,
                step_theta: 1f64.to_radians(),
            });
            p.matcher.check.below = 0.8;
            p.matcher.check.accept = 0.8;
            p.matcher.check.distinct = distinct;
        }
        let mut pf = ParticleFilter3d::new(p).unwrap();
        let (o, e) = frame([0.0; 3], 2.0, (-180.0, 180.0));
        for k in 0..3 {
            pf.step([0.0; 3], [0.0; 3], &o, &e, k).unwrap();
        }
        let (o, e) = frame(truth, 2.0, (-180.0, 180.0));
        let info = pf.step([0.0; 3], odom, &o, &e, 3).unwrap();
        (pf.particles.iter().map(|q| q.pose).collect(), info)
    }

    #[test]
    fn odometry_check_undoes_a_wheel_glitch_beyond_the_climbs_reach() {
        // The robot moved 0.3 m and turned 0.1 rad; the wheels report 0.9 m more to the left and
        // 14° more (a slip), beyond the reach of the hill climbing, which from there ends 0.3 m
        // off (in this room a climb without the prior undoes smaller slips by itself).
        let truth = [0.3, 0.0, 0.1];
        let odom = compose(truth, [0.2, 0.9, 14f64.to_radians()]);
        let off = |poses: &[[f64; 3]]| {
            poses.iter().map(|q| ((q[0] - truth[0]).hypot(q[1] - truth[1]), (q[2] - truth[2]).abs())).fold((0.0f64, 0.0f64), |a, b| (a.0.max(b.0), a.1.max(b.1)))
        };
        let (plain, info) = after_glitch(false, 0.0, truth, odom);
        assert!(!info.odometry_corrected);
        assert!(off(&plain).0 > 0.2, "without the check the glitch stays: {:?}", off(&plain));
        let (checked, info) = after_glitch(true, 0.0, truth, odom);
        assert!(info.odometry_corrected);
        let (d, dth) = off(&checked);
        assert!(d < 0.05 && dth < 1f64.to_radians(), "{d} m, {dth} rad");
        // A gate above what this room's search stands out by keeps the odometry, as without the check.
        let (gated, info) = after_glitch(true, 0.99, truth, odom);
        assert!(!info.odometry_corrected);
        assert_eq!(gated, plain);
        // Odometry that is right is left alone, and the particles end as without the check.
        let (unchecked, _) = after_glitch(false, 0.0, truth, truth);
        let (checked, info) = after_glitch(true, 0.0, truth, truth);
        assert!(!info.odometry_corrected);
        assert_eq!(checked, unchecked);
    }

    #[test]
    fn odometry_check_takes_a_climb_that_the_odometry_prior_would_hold_back() {
        // A slip of 0.6 m and 8°: from the wheels' pose a climb without the odometry prior finds
        // the room again, but the particles climb with the prior and stay near the wheels' pose.
        // The check takes the climb's pose (whatever the search's gate: no search runs).
        let truth = [0.3, 0.0, 0.1];
        let odom = compose(truth, [0.6, 0.0, 8f64.to_radians()]);
        let worst = |poses: &[[f64; 3]]| poses.iter().map(|q| (q[0] - truth[0]).hypot(q[1] - truth[1])).fold(0.0f64, f64::max);
        let (plain, info) = after_glitch(false, 0.0, truth, odom);
        assert!(!info.odometry_corrected && worst(&plain) > 0.2, "{}", worst(&plain));
        let (checked, info) = after_glitch(true, 0.99, truth, odom);
        assert!(info.odometry_corrected);
        assert!(worst(&checked) < 0.05, "{}", worst(&checked));
    }

    #[test]
    fn scan_matching_proposal_recovers_the_true_pose() {
        let mut p = params(8, 2, ProposalKind::ScanMatch);
        // The likelihood's mode alone (GMapping's way): the odometry below is off by more than
        // the motion model allows.
        p.matcher.odometry_prior = false;
        let mut pf = ParticleFilter3d::new(p).unwrap();
        let (o, e) = frame([0.0; 3], 2.0, (-180.0, 180.0));
        for k in 0..3 {
            pf.step([0.0; 3], [0.0; 3], &o, &e, k).unwrap();
        }
        // The robot moved 0.3 m and turned 0.1 rad; the odometry says 0.38 m and 0.16 rad.
        let truth = [0.3, 0.0, 0.1];
        let (o, e) = frame(truth, 2.0, (-180.0, 180.0));
        let info = pf.step([0.0; 3], [0.38, 0.0, 0.16], &o, &e, 3).unwrap();
        assert_eq!(info.fallbacks, 0);
        for q in &pf.particles {
            assert!((q.pose[0] - truth[0]).abs() < 0.03 && q.pose[1].abs() < 0.03, "{:?}", q.pose);
            assert!((q.pose[2] - truth[2]).abs() < 0.02, "{:?}", q.pose);
        }
    }
}
