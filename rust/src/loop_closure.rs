//! Loop closure against submaps: a scan is searched in a finished submap by branch and bound
//! over a window of poses (Hess, Kohler, Rapp & Andor, "Real-Time Loop Closure in 2D LIDAR
//! SLAM", ICRA 2016, sec. V), on top of the exhaustive correlative formulation of Olson
//! ("Real-time correlative scan matching", ICRA 2009), then refined below the grid resolution.
//!
//! A submap is a local log-odds grid (grid.rs) built with the filter's own inverse sensor model
//! (sensor_model::integrate_scan). Once finished, it gets its precomputed grids: for every height
//! h = 0..=H the grid whose cell (x, y) holds the maximum probability of the 2^h × 2^h cells
//! starting at (x, y) (Hess et al. sec. V-C). They are built once per submap and shared by
//! every search against it.
//!
//! The search scores a pose by the mean occupancy probability of the cells the scan's end points
//! fall in. A node of the search tree at height h stands for 2^h × 2^h translations at one
//! heading; reading the height-h grid instead of the probabilities gives an upper bound of all
//! its leaves' scores (Hess et al. eq. 14), so a depth-first search that visits the child with
//! the highest bound first and skips nodes whose bound cannot beat the best leaf so far finds the
//! same pose as scoring every leaf.
//!
//! Frames: every pose here is a robot pose (x, y, θ) in the frame the submap's scans were
//! inserted in. A pose-graph constraint relative to the submap is `relative(origin, pose)`.
//!
//! Determinism: scores are sums of integers (probabilities quantised to 1/255, as in Hess et
//! al.), and the best leaf is the maximum of a total order (score, then lowest (heading, x, y)
//! index), kept in one atomic. The pruning threads race, but the order's maximum is unique, so
//! the answer is the same bit for bit whatever the number of threads.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

use rayon::prelude::*;

use crate::grid::{GridError, LogOddsModel, TiledGrid};
use crate::motion::{compose, relative, wrap};
use crate::sensor_model::{integrate_scan, ScanGeometry};

/// Height of the top of the search tree: 2^7 = 128 cells, 6.4 m at 5 cm (Hess et al. use 7).
pub const DEFAULT_DEPTH: u32 = 7;
/// Probability of never-observed cells: below free space (l_min) of the usual models, so that
/// an end point in unknown space counts against a pose.
pub const DEFAULT_UNKNOWN_PROBABILITY: f32 = 0.1;
const MAX_DEPTH: u32 = 12;
/// A submap is local: what its scans can reach must fit in a square this many cells wide (410 m
/// at 5 cm). A guard against misuse only: the precomputed grids cost about 12 bytes per observed
/// cell (2 MB for a 20 m × 20 m submap at 5 cm), and this caps them below 1 GB.
pub const MAX_SIDE_CELLS: f64 = 8192.0;
/// Bound of |coordinates| (in cells) of everything the search touches, so that i32 cell
/// indices plus window offsets never overflow.
const MAX_CELL_COORD: f64 = (1u64 << 29) as f64;
/// Bound of the cell reads of a search's top level (rotations × top nodes × points): about a
/// second's work.
const MAX_TOP_LEVEL_WORK: f64 = (1u64 << 30) as f64;
/// Bound of (rotations × points), the memory of the discretised scans (8 bytes each).
const MAX_ROTATED_POINTS: usize = 1 << 26;
/// Neighbourhood of the best pose whose scores give the covariance: ± this many cells in x and
/// y and ± this many angular steps.
const COV_HALF_XY: i32 = 8;
const COV_HALF_THETA: i32 = 4;

fn probability(log_odds: f32) -> f32 {
    1.0 - 1.0 / (1.0 + log_odds.exp())
}

fn quantise(p: f32) -> u8 {
    (p.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// How a submap is built and precomputed.
#[derive(Clone, Copy, Debug)]
pub struct SubmapParams {
    pub resolution: f64,
    pub log_odds: LogOddsModel,
    /// Readings at or beyond this (and no echo, +inf) are no obstacle; see `integrate_scan`.
    pub max_range: f64,
    /// Whether a no-echo reading clears the cells up to `max_range`.
    pub clear_no_echo: bool,
    /// Each cell updated at most once per scan (`integrate_scan`), else once per beam.
    pub once_per_scan: bool,
    /// Probability the search gives to never-observed cells.
    pub unknown_probability: f32,
    /// Height H of the branch-and-bound tree (number of precomputed grids less one).
    pub depth: u32,
    /// Standard deviation (m) of an end point about its obstacle: the search's cell values are
    /// the probabilities spread by it (`spread`; 0: the raw probabilities).
    pub spread_sigma: f64,
}

impl SubmapParams {
    fn check(&self) -> Result<(), String> {
        let m = &self.log_odds;
        if !(self.resolution.is_finite() && self.resolution > 0.0) {
            return Err("resolution must be positive and finite".into());
        }
        if ![m.l_occ, m.l_free, m.l_min, m.l_max].iter().all(|v| v.is_finite()) || m.l_min > m.l_max {
            return Err("log-odds parameters must be finite with l_min <= l_max".into());
        }
        if !(self.max_range.is_finite() && self.max_range > 0.0) {
            return Err("max_range must be positive and finite".into());
        }
        // A scan must span cells: coarser, the heading step (a cell at max_range) nears π and a
        // match lands anywhere in the cells around the window.
        if self.resolution * 8.0 > self.max_range {
            return Err(format!(
                "resolution {} m is too coarse for max_range {} m: at most an eighth of it",
                self.resolution, self.max_range
            ));
        }
        if !(0.0..=1.0).contains(&self.unknown_probability) {
            return Err("unknown_probability must lie in [0, 1]".into());
        }
        if self.depth > MAX_DEPTH {
            return Err(format!("depth must be at most {MAX_DEPTH}"));
        }
        if !(self.spread_sigma.is_finite() && self.spread_sigma >= 0.0) {
            return Err("spread_sigma must be finite and not negative".into());
        }
        Ok(())
    }
}

/// A local occupancy grid built from a run of scans, then finished and searched in.
pub struct Submap {
    params: SubmapParams,
    grid: TiledGrid,
    origin: Option<[f64; 3]>,
    num_scans: usize,
    /// World rectangle [x0, y0, x1, y1] that every inserted scan can have touched.
    reach: Option<[f64; 4]>,
    finished: bool,
    /// The search grids; a finished submap may release them (`release_grids`) and make them
    /// again when next searched: they cost about three times the grid itself.
    grids: Option<PrecomputedGrids>,
}

impl Submap {
    pub fn new(params: SubmapParams) -> Result<Self, String> {
        params.check()?;
        Ok(Submap {
            params,
            grid: TiledGrid::new(params.resolution),
            origin: None,
            num_scans: 0,
            reach: None,
            finished: false,
            grids: None,
        })
    }

    pub fn params(&self) -> &SubmapParams {
        &self.params
    }

    /// Write a scan taken at `robot` (world frame) into the submap. Fails (and changes nothing)
    /// on a finished submap, mismatched lengths, non-finite poses or angles, or a scan that
    /// would stretch the submap beyond a local map's size.
    pub fn insert(&mut self, robot: [f64; 3], geom: &ScanGeometry, ranges: &[f32]) -> Result<(), String> {
        if self.finished {
            return Err("the submap is finished: no more scans can be inserted".into());
        }
        if geom.angles.len() != ranges.len() {
            return Err(format!("{} angles for {} ranges", geom.angles.len(), ranges.len()));
        }
        if !robot.iter().chain(&geom.sensor).chain(geom.angles).all(|v| v.is_finite()) {
            return Err("poses and angles must be finite".into());
        }
        let sp = geom.sensor_pose(robot);
        let r = self.params.max_range;
        let scan = [sp[0] - r, sp[1] - r, sp[0] + r, sp[1] + r];
        let reach = match self.reach {
            None => scan,
            Some(b) => [b[0].min(scan[0]), b[1].min(scan[1]), b[2].max(scan[2]), b[3].max(scan[3])],
        };
        let side = (reach[2] - reach[0]).max(reach[3] - reach[1]) / self.params.resolution;
        let far = reach.iter().map(|v| v.abs()).fold(0.0, f64::max) / self.params.resolution;
        if side > MAX_SIDE_CELLS {
            return Err(format!(
                "a submap must fit in {MAX_SIDE_CELLS} cells: this scan would make it {side:.0} cells wide"
            ));
        }
        if far > MAX_CELL_COORD {
            return Err(format!(
                "the scan at ({:.3e}, {:.3e}) m lies beyond the {MAX_CELL_COORD:.0} cells of {} m a submap \
                 reaches from the map's origin",
                sp[0], sp[1], self.params.resolution
            ));
        }
        let p = &self.params;
        integrate_scan(&mut self.grid, &p.log_odds, geom, robot, ranges, p.max_range, p.clear_no_echo, p.once_per_scan)
            .map_err(|e| e.to_string())?;
        self.reach = Some(reach);
        self.origin.get_or_insert(robot);
        self.num_scans += 1;
        Ok(())
    }

    /// Finish the submap: precompute its search grids (once; later calls return them again,
    /// or make them anew after `release_grids`, the same to the bit). Fails only when their
    /// memory cannot be had.
    pub fn finish(&mut self) -> Result<&PrecomputedGrids, GridError> {
        if self.grids.is_none() {
            let p = self.params;
            self.grids = Some(PrecomputedGrids::new(&self.grid, p.depth, p.unknown_probability, p.spread_sigma)?);
        }
        self.finished = true;
        Ok(self.grids.as_ref().expect("just made"))
    }

    pub fn is_finished(&self) -> bool {
        self.finished
    }

    /// Drop the search grids of a finished submap (`finish` makes them again); a submap not
    /// yet finished keeps nothing to drop.
    pub fn release_grids(&mut self) {
        if self.finished {
            self.grids = None;
        }
    }

    /// The precomputed grids of a finished submap.
    pub fn grids(&self) -> Option<&PrecomputedGrids> {
        self.grids.as_ref()
    }

    pub fn grid(&self) -> &TiledGrid {
        &self.grid
    }

    /// The robot pose of the first inserted scan.
    pub fn origin(&self) -> Option<[f64; 3]> {
        self.origin
    }

    pub fn num_scans(&self) -> usize {
        self.num_scans
    }

    /// The end points (robot frame) of a scan's readings in (0, max_range).
    pub fn scan_points(&self, geom: &ScanGeometry, ranges: &[f32]) -> Vec<[f64; 2]> {
        scan_points(geom, ranges, self.params.max_range)
    }

    /// Search a scan in the finished submap (`search`), then refine the match (`refine`) if
    /// `opts.refine`. Errors on an unfinished submap or bad arguments.
    pub fn match_scan(
        &self,
        geom: &ScanGeometry,
        ranges: &[f32],
        initial: [f64; 3],
        opts: &MatchOptions,
    ) -> Result<Option<LoopMatch>, String> {
        let grids = self.grids.as_ref().ok_or("the submap is not finished, or its grids were released")?;
        if geom.angles.len() != ranges.len() {
            return Err(format!("{} angles for {} ranges", geom.angles.len(), ranges.len()));
        }
        if !geom.sensor.iter().chain(geom.angles).all(|v| v.is_finite()) {
            return Err("sensor pose and angles must be finite".into());
        }
        let pts = self.scan_points(geom, ranges);
        let found = search(grids, &pts, initial, opts.linear_window, opts.angular_window, opts.min_score)?;
        Ok(found.map(|m| if opts.refine { refine(grids, &pts, &m) } else { m }))
    }

    /// Heap bytes of the grid's tiles and the precomputed grids.
    pub fn memory_bytes(&self) -> usize {
        self.grid.tiles().count() * TiledGrid::tile_bytes() + self.grids.as_ref().map_or(0, PrecomputedGrids::memory_bytes)
    }
}

/// The window and acceptance of `Submap::match_scan`.
#[derive(Clone, Copy, Debug)]
pub struct MatchOptions {
    /// Half-width of the searched window in x and y (m) and in heading (rad); π or more
    /// searches every heading.
    pub linear_window: f64,
    pub angular_window: f64,
    /// Smallest score (mean probability of the end points) a match needs.
    pub min_score: f64,
    pub refine: bool,
}

/// End points (robot frame) of the readings in (0, max_range) of a scan.
pub fn scan_points(geom: &ScanGeometry, ranges: &[f32], max_range: f64) -> Vec<[f64; 2]> {
    ranges
        .iter()
        .zip(geom.angles)
        .filter_map(|(&r, &a)| {
            let r = r as f64;
            (r.is_finite() && r > 0.0 && r < max_range).then(|| {
                let p = compose(geom.sensor, [r * a.cos(), r * a.sin(), 0.0]);
                [p[0], p[1]]
            })
        })
        .collect()
}

/// One precomputed grid: cell (ix, iy) holds the maximum (quantised) probability of the base
/// cells [ix, ix + w) × [iy, iy + w), w = 2^h; cells outside the base count as unknown. It
/// covers every cell whose window meets the base: w − 1 more cells than the base on the low side.
struct MaxGrid {
    ix0: i32,
    iy0: i32,
    nx: usize,
    ny: usize,
    cells: Vec<u8>,
    /// The value of windows wholly outside the base: unknown.
    outside: u8,
}

impl MaxGrid {
    #[inline(always)]
    fn get(&self, ix: i32, iy: i32) -> u8 {
        let (u, v) = (ix.wrapping_sub(self.ix0) as u32 as usize, iy.wrapping_sub(self.iy0) as u32 as usize);
        if u < self.nx && v < self.ny {
            self.cells[v * self.nx + u]
        } else {
            self.outside
        }
    }
}

/// out[u] = max(input(u), …, input(u + w − 1)) for every u < out.len(); `input` is read on
/// 0..out.len() + w − 1. A monotone deque of (index, value) with decreasing values: every index
/// enters and leaves it once, so a row costs O(its length) whatever w. Written by hand: the
/// crates that offer a sliding maximum work on f64 streams one push at a time, not on
/// rows of u8 with padding, and the loop is a dozen lines.
fn sliding_max(input: impl Fn(usize) -> u8, w: usize, out: &mut [u8], deque: &mut VecDeque<(usize, u8)>) {
    deque.clear();
    for q in 0..out.len() + w - 1 {
        let v = input(q);
        while deque.back().is_some_and(|&(_, b)| b <= v) {
            deque.pop_back();
        }
        deque.push_back((q, v));
        if q + 1 >= w {
            let u = q + 1 - w;
            while deque.front().is_some_and(|&(i, _)| i < u) {
                deque.pop_front();
            }
            out[u] = deque.front().map_or(0, |&(_, m)| m);
        }
    }
}

/// The search grids of a finished submap: its probabilities (f32, for the refinement) and the
/// max grids of heights 0..=H (u8, for branch and bound).
pub struct PrecomputedGrids {
    resolution: f64,
    unknown: f32,
    /// Base extent: cells (ix0.., iy0..), nx × ny, row-major in y.
    ix0: i32,
    iy0: i32,
    nx: usize,
    ny: usize,
    probability: Vec<f32>,
    levels: Vec<MaxGrid>,
}

/// The search's cell values: each cell's probability raised to the most probable cell within
/// `sigma` (m) of it, discounted by a Gaussian of standard deviation `sigma` over the distance
/// between the cell centres: max_n p(n)·exp(−d(c, n)²/2σ²), the rasterised lookup table of Olson
/// (ICRA 2009, sec. III) with the max in place of the sum. Why: an end point a few millimetres in
/// front of a wall that runs along a cell border falls into the free cell before it, and scored
/// by the raw cells such points count as misses; where every wall lies on the lattice (the
/// simulated worlds) a true match then scores below a false one a few metres along a corridor
/// (corridor1: 0.585 against 0.646 at a pose 2.6 m away). `sigma` 0 leaves the values as they are.
fn spread(p: &[f32], nx: usize, ny: usize, resolution: f64, sigma: f64) -> Vec<f32> {
    let radius = if sigma > 0.0 { (sigma / resolution).ceil().min(8.0) as i32 } else { 0 };
    if radius == 0 {
        return p.to_vec();
    }
    let weight = |dx: i32, dy: i32| (-((dx * dx + dy * dy) as f64) * resolution * resolution / (2.0 * sigma * sigma)).exp() as f32;
    let kernel: Vec<(i32, i32, f32)> = (-radius..=radius)
        .flat_map(|dy| (-radius..=radius).map(move |dx| (dx, dy)))
        .filter(|&(dx, dy)| (dx, dy) != (0, 0))
        .map(|(dx, dy)| (dx, dy, weight(dx, dy)))
        .collect();
    let mut out = p.to_vec();
    out.par_chunks_mut(nx).enumerate().for_each(|(y, row)| {
        for (x, value) in row.iter_mut().enumerate() {
            for &(dx, dy, k) in &kernel {
                let (u, v) = (x as i32 + dx, y as i32 + dy);
                if u >= 0 && v >= 0 && (u as usize) < nx && (v as usize) < ny {
                    *value = value.max(k * p[v as usize * nx + u as usize]);
                }
            }
        }
    });
    out
}

impl PrecomputedGrids {
    /// Precompute the grids of heights 0..=depth from a log-odds grid (NaN = unknown, which
    /// gets `unknown_probability`), its probabilities first spread by `spread_sigma` (m; see
    /// `spread`, 0: none). O(cells) per height; the heights are built in parallel.
    pub fn new(grid: &TiledGrid, depth: u32, unknown_probability: f32, spread_sigma: f64) -> Result<Self, GridError> {
        let depth = depth.min(MAX_DEPTH);
        let (ny, nx, ix0, iy0, log_odds) = grid.to_dense()?;
        let raw: Vec<f32> =
            log_odds.iter().map(|&l| if l.is_nan() { unknown_probability } else { probability(l) }).collect();
        let probability = spread(&raw, nx, ny, grid.resolution, spread_sigma);
        let base: Vec<u8> = probability.iter().map(|&p| quantise(p)).collect();
        let outside = quantise(unknown_probability);
        let levels = (0..=depth)
            .into_par_iter()
            .map(|h| {
                let w = 1usize << h;
                let (wx, wy) = (nx + w - 1, ny + w - 1);
                let pad = w - 1;
                let mut deque = VecDeque::with_capacity(w + 1);
                // Maxima along x of each base row (h = 0: the base itself), then along y.
                let mut rows = vec![0u8; wx * ny];
                for y in 0..ny {
                    let row = &base[y * nx..(y + 1) * nx];
                    let input = |q: usize| if q >= pad && q - pad < nx { row[q - pad] } else { outside };
                    sliding_max(input, w, &mut rows[y * wx..(y + 1) * wx], &mut deque);
                }
                let mut cells = vec![0u8; wx * wy];
                let mut column = vec![0u8; wy];
                for x in 0..wx {
                    let input = |q: usize| if q >= pad && q - pad < ny { rows[(q - pad) * wx + x] } else { outside };
                    sliding_max(input, w, &mut column, &mut deque);
                    for (y, &v) in column.iter().enumerate() {
                        cells[y * wx + x] = v;
                    }
                }
                MaxGrid { ix0: ix0 - pad as i32, iy0: iy0 - pad as i32, nx: wx, ny: wy, cells, outside }
            })
            .collect();
        Ok(PrecomputedGrids { resolution: grid.resolution, unknown: unknown_probability, ix0, iy0, nx, ny, probability, levels })
    }

    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// H: the grids have heights 0..=H.
    pub fn depth(&self) -> u32 {
        self.levels.len() as u32 - 1
    }

    /// Quantised (× 255) maximum probability of the 2^h × 2^h cells from (ix, iy); h <= depth.
    pub fn max_at(&self, h: u32, ix: i32, iy: i32) -> u8 {
        self.levels[h as usize].get(ix, iy)
    }

    /// Occupancy probability of a cell (unknown_probability where never observed).
    #[inline]
    pub fn probability_at(&self, ix: i32, iy: i32) -> f32 {
        let (u, v) = (ix.wrapping_sub(self.ix0) as u32 as usize, iy.wrapping_sub(self.iy0) as u32 as usize);
        if u < self.nx && v < self.ny {
            self.probability[v * self.nx + u]
        } else {
            self.unknown
        }
    }

    pub fn memory_bytes(&self) -> usize {
        self.probability.len() * 4 + self.levels.iter().map(|l| l.cells.len()).sum::<usize>()
    }

    /// Probability at world (x, y), interpolated bicubically (Catmull-Rom) between the cell
    /// centres, and its gradient (per metre).
    fn interpolate(&self, x: f64, y: f64) -> (f64, [f64; 2]) {
        let (u, v) = (x / self.resolution - 0.5, y / self.resolution - 0.5);
        let (iu, iv) = (u.floor(), v.floor());
        let (wx, dx) = catmull_rom(u - iu);
        let (wy, dy) = catmull_rom(v - iv);
        let (iu, iv) = (iu as i32 - 1, iv as i32 - 1);
        let (mut val, mut gx, mut gy) = (0.0, 0.0, 0.0);
        for b in 0..4 {
            for a in 0..4 {
                let p = self.probability_at(iu + a as i32, iv + b as i32) as f64;
                val += wy[b] * wx[a] * p;
                gx += wy[b] * dx[a] * p;
                gy += dy[b] * wx[a] * p;
            }
        }
        (val, [gx / self.resolution, gy / self.resolution])
    }
}

/// Weights of the samples at −1, 0, 1, 2 for a point t ∈ [0, 1) past sample 0, and their
/// derivatives in t (Catmull-Rom: C¹, so Gauss-Newton sees a continuous gradient).
fn catmull_rom(t: f64) -> ([f64; 4], [f64; 4]) {
    let (t2, t3) = (t * t, t * t * t);
    (
        [0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0), 0.5 * (-3.0 * t3 + 4.0 * t2 + t), 0.5 * (t3 - t2)],
        [0.5 * (-3.0 * t2 + 4.0 * t - 1.0), 0.5 * (9.0 * t2 - 10.0 * t), 0.5 * (-9.0 * t2 + 8.0 * t + 1.0), 0.5 * (3.0 * t2 - 2.0 * t)],
    )
}

/// A scan found in a submap.
#[derive(Clone, Debug)]
pub struct LoopMatch {
    /// Robot pose in the submap's frame (refined, if `refine` ran).
    pub pose: [f64; 3],
    /// Mean probability (in [0, 1], quantised to 1/255 per point) of the end points at the
    /// branch-and-bound optimum: the score `min_score` was checked against.
    pub score: f64,
    /// Covariance of (x, y, θ), from the score surface around the optimum (Olson 2009 sec. IV).
    pub covariance: [[f64; 3]; 3],
    /// The branch-and-bound optimum, on the search's lattice.
    pub search_pose: [f64; 3],
    /// Lattice spacing: the grid resolution and the angular step.
    pub linear_step: f64,
    pub angular_step: f64,
}

/// A node of the search tree: heading index k, the lowest x and y indices of its 2^h × 2^h
/// translations, and the sum of its height-h grid values (an upper bound of its leaves' sums).
#[derive(Clone, Copy, Debug)]
struct Candidate {
    k: u32,
    i: u32,
    j: u32,
    h: u32,
    sum: u32,
}

/// The discretised search: headings θ0 + (k − n_theta)·δθ, translations (i − n_x, j − n_y)
/// cells from the initial position, and per heading the cells of the rotated end points at the
/// initial position, less (n_x, n_y) so that index (i, j) adds directly (Hess et al. sec. V-A).
struct SearchSpace {
    initial: [f64; 3],
    resolution: f64,
    angular_step: f64,
    n_theta: i64,
    n_x: i32,
    n_y: i32,
    /// Top of the tree: the smallest height whose window holds every translation, at most H.
    height: u32,
    points: Vec<[f64; 2]>,
    rotations: Vec<Vec<[i32; 2]>>,
}

impl SearchSpace {
    fn new(
        grids: &PrecomputedGrids,
        points: &[[f64; 2]],
        initial: [f64; 3],
        linear_window: f64,
        angular_window: f64,
    ) -> Result<Self, String> {
        let res = grids.resolution;
        let d_max = points.iter().map(|p| p[0].hypot(p[1])).fold(0.0, f64::max);
        // Hess et al. eq. 7: the step that moves the farthest end point by one cell.
        let mut step = (1.0 - res * res / (2.0 * d_max * d_max)).clamp(-1.0, 1.0).acos();
        let mut n_theta = (angular_window / step - 1e-9).ceil().max(0.0) as i64;
        if (2 * n_theta + 1) as f64 * step > 2.0 * std::f64::consts::PI {
            // The window wraps: spread 2n + 1 distinct headings evenly over the circle.
            n_theta = ((2.0 * std::f64::consts::PI / step - 1.0) / 2.0).ceil() as i64;
            step = 2.0 * std::f64::consts::PI / (2 * n_theta + 1) as f64;
        }
        let n_xy = (linear_window / res - 1e-9).ceil().max(0.0);
        let far = (initial[0].abs().max(initial[1].abs()) + d_max) / res + n_xy;
        if far.is_nan() || far >= MAX_CELL_COORD {
            return Err("the search reaches too far from the grid's origin".into());
        }
        let (n_x, n_y) = (n_xy as i32, n_xy as i32);
        let n_rot = (2 * n_theta + 1) as usize;
        let leaves = n_rot as f64 * (2 * n_x + 1) as f64 * (2 * n_y + 1) as f64;
        if leaves >= u32::MAX as f64 {
            return Err(format!("the window holds {leaves:.0} poses, more than a search can index"));
        }
        if n_rot.saturating_mul(points.len()) > MAX_ROTATED_POINTS {
            return Err("too many headings × points: subsample the scan or narrow the window".into());
        }
        let height = (0..=grids.depth()).find(|&h| (1i64 << h) > 2 * n_xy as i64).unwrap_or(grids.depth());
        // The search scores every node of its top level: a tree too shallow for the window
        // makes that an exhaustive search (a 20 m window at depth 0 ran for minutes).
        let top = ((2.0 * n_xy + 1.0) / (1u64 << height) as f64).ceil();
        let top_work = n_rot as f64 * top * top * points.len() as f64;
        if top_work > MAX_TOP_LEVEL_WORK {
            return Err(format!(
                "the window is too wide for a tree of depth {}: {top_work:.0} cell reads at its top level \
                 (at most {MAX_TOP_LEVEL_WORK:.0}); raise the depth or narrow the window",
                grids.depth()
            ));
        }
        let mut space = SearchSpace {
            initial,
            resolution: res,
            angular_step: step,
            n_theta,
            n_x,
            n_y,
            height,
            points: points.to_vec(),
            rotations: Vec::new(),
        };
        space.rotations = (0..n_rot).into_par_iter().map(|k| space.cells_at(k as i64 - n_theta)).collect();
        Ok(space)
    }

    /// Cells of the end points at the initial position turned by `k`·δθ, less (n_x, n_y).
    fn cells_at(&self, k: i64) -> Vec<[i32; 2]> {
        let theta = self.initial[2] + k as f64 * self.angular_step;
        let (s, c) = theta.sin_cos();
        let res = self.resolution;
        self.points
            .iter()
            .map(|p| {
                let x = self.initial[0] + c * p[0] - s * p[1];
                let y = self.initial[1] + s * p[0] + c * p[1];
                [(x / res).floor() as i32 - self.n_x, (y / res).floor() as i32 - self.n_y]
            })
            .collect()
    }

    fn flat_index(&self, k: u32, i: u32, j: u32) -> u32 {
        (k * (2 * self.n_x as u32 + 1) + i) * (2 * self.n_y as u32 + 1) + j
    }

    /// The order of candidates and leaves: higher sum first, then lower (k, i, j). Unique per
    /// leaf; a node's key is at least that of every leaf below it.
    fn key(&self, c: &Candidate) -> u64 {
        ((c.sum as u64) << 32) | (u32::MAX - self.flat_index(c.k, c.i, c.j)) as u64
    }

    fn pose(&self, k: u32, i: u32, j: u32) -> [f64; 3] {
        let res = self.resolution;
        [
            self.initial[0] + (i as i32 - self.n_x) as f64 * res,
            self.initial[1] + (j as i32 - self.n_y) as f64 * res,
            wrap(self.initial[2] + (k as i64 - self.n_theta) as f64 * self.angular_step),
        ]
    }

    fn decode(&self, key: u64) -> Candidate {
        let idx = u32::MAX - (key & 0xffff_ffff) as u32;
        let ny = 2 * self.n_y as u32 + 1;
        let nx = 2 * self.n_x as u32 + 1;
        Candidate { k: idx / (nx * ny), i: (idx / ny) % nx, j: idx % ny, h: 0, sum: (key >> 32) as u32 }
    }

    #[inline]
    fn sum(level: &MaxGrid, cells: &[[i32; 2]], dx: i32, dy: i32) -> u32 {
        cells.iter().map(|c| level.get(c[0] + dx, c[1] + dy) as u32).sum()
    }

    fn candidate(&self, grids: &PrecomputedGrids, k: u32, i: u32, j: u32, h: u32) -> Candidate {
        let sum = Self::sum(&grids.levels[h as usize], &self.rotations[k as usize], i as i32, j as i32);
        Candidate { k, i, j, h, sum }
    }

    /// Depth-first branch and bound below `c` (Hess et al. algorithm 3): children in order of
    /// their bound, a node skipped once its bound cannot beat `best`.
    fn descend(&self, grids: &PrecomputedGrids, best: &AtomicU64, c: Candidate) {
        let key = self.key(&c);
        if key <= best.load(Ordering::Relaxed) {
            return;
        }
        if c.h == 0 {
            best.fetch_max(key, Ordering::Relaxed);
            return;
        }
        let half = 1u32 << (c.h - 1);
        let (last_i, last_j) = (2 * self.n_x as u32, 2 * self.n_y as u32);
        let mut children = [c; 4];
        let mut n = 0;
        for (a, b) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
            let (i, j) = (c.i + a * half, c.j + b * half);
            if i <= last_i && j <= last_j {
                children[n] = self.candidate(grids, c.k, i, j, c.h - 1);
                n += 1;
            }
        }
        let children = &mut children[..n];
        children.sort_unstable_by_key(|ch| std::cmp::Reverse(self.key(ch)));
        for ch in children.iter() {
            self.descend(grids, best, *ch);
        }
    }

    /// The best leaf whose sum reaches `min_sum`, if any.
    fn branch_and_bound(&self, grids: &PrecomputedGrids, min_sum: u32) -> Option<Candidate> {
        let top = self.height;
        let stride = 1usize << top;
        let (nx, ny) = (2 * self.n_x as usize + 1, 2 * self.n_y as usize + 1);
        let floor = (min_sum as u64) << 32;
        let mut roots: Vec<Candidate> = (0..self.rotations.len() as u32)
            .into_par_iter()
            .flat_map_iter(|k| {
                (0..nx).step_by(stride).flat_map(move |i| {
                    (0..ny).step_by(stride).map(move |j| self.candidate(grids, k, i as u32, j as u32, top))
                })
            })
            .filter(|c| self.key(c) > floor)
            .collect();
        // Best bound first (Hess et al.: the top-level candidates sorted by score), so that the
        // first descents set a high bar for all the others.
        roots.par_sort_unstable_by_key(|c| std::cmp::Reverse(self.key(c)));
        let best = AtomicU64::new(floor);
        // The roots are the headings' windows: the workers take them in that order from one
        // counter (a parallel iterator would start its second half before the best roots had
        // raised the bar, and score 40 % more nodes). Once a root's bound cannot beat the best
        // leaf, no later root can either.
        let next = AtomicUsize::new(0);
        let workers = rayon::current_num_threads().clamp(1, roots.len().max(1));
        (0..workers).into_par_iter().for_each(|_| {
            while let Some(c) = roots.get(next.fetch_add(1, Ordering::Relaxed)) {
                if self.key(c) <= best.load(Ordering::Relaxed) {
                    break;
                }
                self.descend(grids, &best, *c);
            }
        });
        let best = best.into_inner();
        (best > floor).then(|| self.decode(best))
    }

    /// Covariance of (x, y, θ) from the leaf scores around `best` (Olson 2009 sec. IV): the
    /// weighted second moment Σ w·d·dᵀ/Σ w − μμᵀ of the offsets d, w = exp((s − s_max)/τ).
    /// τ is the standard error of the mean score at the optimum: score differences below the
    /// noise of a mean over these points are no evidence. A floor of one cell and one angular
    /// step (the lattice cannot resolve finer) keeps it positive definite. Where the scan does
    /// not fix a direction (a bare corridor) the neighbourhood caps it: σ ≈ 0.25 m along the
    /// corridor at 5 cm cells (the spread of ± COV_HALF_XY cells).
    fn covariance(&self, grids: &PrecomputedGrids, best: &Candidate) -> [[f64; 3]; 3] {
        let n = self.points.len() as f64;
        let norm = 1.0 / (255.0 * n);
        let level0 = &grids.levels[0];
        let (bi, bj) = (best.i as i32, best.j as i32);
        let best_cells = &self.rotations[best.k as usize];
        let (mut m1, mut m2) = (0.0, 0.0);
        for c in best_cells {
            let p = level0.get(c[0] + bi, c[1] + bj) as f64 / 255.0;
            m1 += p;
            m2 += p * p;
        }
        let var = (m2 / n - (m1 / n).powi(2)).max(0.0);
        let tau = (var / n).sqrt().max(1e-3);
        let k0 = best.k as i64 - self.n_theta;
        // Scores per heading offset, in parallel; collected in order, summed in order below.
        let side = (2 * COV_HALF_XY + 1) as usize;
        let scores: Vec<Vec<f64>> = (-COV_HALF_THETA..=COV_HALF_THETA)
            .into_par_iter()
            .map(|dk| {
                let cells = self.cells_at(k0 + dk as i64);
                let mut out = Vec::with_capacity(side * side);
                for di in -COV_HALF_XY..=COV_HALF_XY {
                    for dj in -COV_HALF_XY..=COV_HALF_XY {
                        out.push(SearchSpace::sum(level0, &cells, bi + di, bj + dj) as f64 * norm);
                    }
                }
                out
            })
            .collect();
        let s_max = scores.iter().flatten().cloned().fold(f64::NEG_INFINITY, f64::max);
        let (res, step) = (self.resolution, self.angular_step);
        let mut sw = 0.0;
        let mut mean = [0.0; 3];
        let mut second = [[0.0; 3]; 3];
        for (a, row) in scores.iter().enumerate() {
            for (b, &s) in row.iter().enumerate() {
                let d = [
                    ((b / side) as i32 - COV_HALF_XY) as f64 * res,
                    ((b % side) as i32 - COV_HALF_XY) as f64 * res,
                    (a as i32 - COV_HALF_THETA) as f64 * step,
                ];
                let w = ((s - s_max) / tau).exp();
                sw += w;
                for p in 0..3 {
                    mean[p] += w * d[p];
                    for q in 0..3 {
                        second[p][q] += w * d[p] * d[q];
                    }
                }
            }
        }
        let floor = [res * res, res * res, step * step];
        let mut cov = [[0.0; 3]; 3];
        for p in 0..3 {
            // Symmetric by construction (the two products of one pair can differ in the last bit).
            for q in 0..p {
                let v = 0.5 * (second[p][q] + second[q][p]) / sw - mean[p] * mean[q] / (sw * sw);
                cov[p][q] = v;
                cov[q][p] = v;
            }
            // The moment matrix is positive semidefinite up to rounding; the floor makes it
            // definite.
            cov[p][p] = (second[p][p] / sw - mean[p] * mean[p] / (sw * sw)).max(0.0) + floor[p];
        }
        cov
    }
}

/// Branch-and-bound search (Hess et al. 2016 sec. V) of the robot pose within ± `linear_window`
/// (m) in x and y and ± `angular_window` (rad) in heading of `initial`, for end points `points`
/// (robot frame), on the lattice of the grid resolution and the angular step of Hess et al.
/// eq. 7 for the scan's farthest point. The best pose scoring at least `min_score` (mean
/// probability of the end points), ties going to the lowest (heading, x, y) index; None if no
/// pose reaches it (or the scan has no points). Errors on bad arguments or a window too large to
/// index; never panics.
pub fn search(
    grids: &PrecomputedGrids,
    points: &[[f64; 2]],
    initial: [f64; 3],
    linear_window: f64,
    angular_window: f64,
    min_score: f64,
) -> Result<Option<LoopMatch>, String> {
    if !initial.iter().all(|v| v.is_finite()) {
        return Err("initial pose must be finite".into());
    }
    if !(linear_window.is_finite() && linear_window >= 0.0 && angular_window.is_finite() && angular_window >= 0.0) {
        return Err("windows must be finite and non-negative".into());
    }
    if !(0.0..=1.0).contains(&min_score) {
        return Err("min_score must lie in [0, 1]".into());
    }
    if !points.iter().flatten().all(|v| v.is_finite()) {
        return Err("points must be finite".into());
    }
    if points.is_empty() {
        return Ok(None);
    }
    if points.len() > (u32::MAX / 255) as usize {
        return Err("too many points".into());
    }
    let space = SearchSpace::new(grids, points, initial, linear_window, angular_window)?;
    let n = points.len() as f64;
    let min_sum = (min_score * 255.0 * n - 1e-6).ceil().max(0.0) as u32;
    let Some(best) = space.branch_and_bound(grids, min_sum) else { return Ok(None) };
    let pose = space.pose(best.k, best.i, best.j);
    Ok(Some(LoopMatch {
        pose,
        score: best.sum as f64 / (255.0 * n),
        covariance: space.covariance(grids, &best),
        search_pose: pose,
        linear_step: space.resolution,
        angular_step: space.angular_step,
    }))
}

/// Refine a match below the lattice: Levenberg-Marquardt (Gauss-Newton with damping) on
/// Σ (1 − M(T(ξ)·p))², M the submap's probabilities interpolated bicubically (the cost of
/// Hess et al. sec. IV, there solved with Ceres). Why this: the search already put the pose
/// within about a cell and an angular step of the optimum, where the cost is smooth and nearly
/// quadratic, so a few steps of a three-parameter least squares converge; Catmull-Rom
/// interpolation keeps the gradient continuous across cell borders (bilinear would jump there
/// and make the steps chatter). A step is only taken if it lowers the cost, and the pose may not
/// move more than one lattice step (each way) from the search's optimum: past that, the search
/// would have found a better leaf, so such a step follows a neighbouring optimum.
/// Limit: the probabilities sit at cell centres, so a wall that runs off-centre pulls the pose
/// by up to half a cell. In the tests (5 cm cells, walls off the lattice) the error falls from
/// 24 mm rms on the lattice to 5 mm rms, 13 mm at worst. The filter's likelihood field on the
/// cells' mean end points (scan_match.rs, `fit_walls`) avoids that bias; it is not used here
/// to keep the submap's search self-contained on its precomputed grids.
pub fn refine(grids: &PrecomputedGrids, points: &[[f64; 2]], m: &LoopMatch) -> LoopMatch {
    let start = m.search_pose;
    let cost_at = |pose: [f64; 3]| -> f64 {
        let (s, c) = pose[2].sin_cos();
        points
            .iter()
            .map(|p| {
                let (v, _) = grids.interpolate(pose[0] + c * p[0] - s * p[1], pose[1] + s * p[0] + c * p[1]);
                (1.0 - v).powi(2)
            })
            .sum()
    };
    let mut pose = start;
    let mut cost = cost_at(pose);
    let mut lambda = 1e-3;
    for _ in 0..30 {
        let (s, c) = pose[2].sin_cos();
        let mut h = [[0.0; 3]; 3];
        let mut g = [0.0; 3];
        for p in points {
            let (rx, ry) = (c * p[0] - s * p[1], s * p[0] + c * p[1]);
            let (v, grad) = grids.interpolate(pose[0] + rx, pose[1] + ry);
            let r = 1.0 - v;
            // dr/dξ = −∇M · ∂(T p)/∂ξ, with ∂(T p)/∂θ = (−ry, rx).
            let jac = [-grad[0], -grad[1], -(grad[0] * -ry + grad[1] * rx)];
            for a in 0..3 {
                g[a] += jac[a] * r;
                for b in 0..3 {
                    h[a][b] += jac[a] * jac[b];
                }
            }
        }
        let mut improved = false;
        while lambda < 1e6 {
            let mut damped = h;
            for (a, row) in damped.iter_mut().enumerate() {
                row[a] += lambda * h[a][a].max(1e-12);
            }
            let Some(delta) = solve3(&damped, &[-g[0], -g[1], -g[2]]) else { break };
            let cand = [pose[0] + delta[0], pose[1] + delta[1], wrap(pose[2] + delta[2])];
            let inside = (cand[0] - start[0]).abs() <= m.linear_step
                && (cand[1] - start[1]).abs() <= m.linear_step
                && wrap(cand[2] - start[2]).abs() <= m.angular_step;
            let new_cost = if inside { cost_at(cand) } else { f64::INFINITY };
            if new_cost < cost {
                let small = delta[0].abs().max(delta[1].abs()) < 1e-5 && delta[2].abs() < 1e-6;
                pose = cand;
                cost = new_cost;
                lambda = (lambda * 0.1).max(1e-9);
                improved = !small;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    LoopMatch { pose, ..m.clone() }
}

/// Solve a·x = b (3×3) by Cramer's rule; None if a is (nearly) singular.
fn solve3(a: &[[f64; 3]; 3], b: &[f64; 3]) -> Option<[f64; 3]> {
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(a);
    let scale = a[0][0].abs() * a[1][1].abs() * a[2][2].abs();
    if !d.is_finite() || d.abs() <= 1e-12 * scale {
        return None;
    }
    let mut x = [0.0; 3];
    for (col, xc) in x.iter_mut().enumerate() {
        let mut m = *a;
        for row in 0..3 {
            m[row][col] = b[row];
        }
        *xc = det(&m) / d;
    }
    Some(x)
}

/// The relative pose of a match in its submap's origin frame: the constraint a pose graph takes.
pub fn constraint(origin: [f64; 3], m: &LoopMatch) -> [f64; 3] {
    relative(origin, m.pose)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use std::time::Instant;

    const MODEL: LogOddsModel = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };

    fn params(resolution: f64, max_range: f64) -> SubmapParams {
        SubmapParams {
            resolution,
            log_odds: MODEL,
            max_range,
            clear_no_echo: false,
            once_per_scan: false,
            unknown_probability: DEFAULT_UNKNOWN_PROBABILITY,
            depth: DEFAULT_DEPTH,
            spread_sigma: 0.0,
        }
    }

    use crate::test_support::cast_walls as cast;

    fn square(cx: f64, cy: f64, half: f64) -> [[f64; 4]; 4] {
        let (a, b, c, d) = ([cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]);
        [[a[0], a[1], b[0], b[1]], [b[0], b[1], c[0], c[1]], [c[0], c[1], d[0], d[1]], [d[0], d[1], a[0], a[1]]]
    }

    /// An L-shaped room with a pillar, a slanted wall and a niche: no shift or turn of it looks
    /// like another. Coordinates off the 5 cm lattice on purpose.
    fn room() -> Vec<[f64; 4]> {
        let mut w = vec![
            [0.013, 0.021, 9.987, 0.021],
            [9.987, 0.021, 9.987, 4.033],
            [9.987, 4.033, 6.012, 4.033],
            [6.012, 4.033, 6.012, 7.977],
            [6.012, 7.977, 0.013, 7.977],
            [0.013, 7.977, 0.013, 0.021],
            [7.004, 1.011, 8.516, 2.207],
            [3.517, 6.009, 4.521, 6.009],
            [4.521, 6.009, 4.521, 7.977],
        ];
        w.extend(square(2.281, 2.269, 0.25));
        w
    }

    /// Another layout: a 5 m × 12 m hall with an octagonal column and a slanted wall.
    fn other_room() -> Vec<[f64; 4]> {
        let mut w = vec![
            [0.0, 0.0, 5.0, 0.0],
            [5.0, 0.0, 5.0, 12.0],
            [5.0, 12.0, 0.0, 12.0],
            [0.0, 12.0, 0.0, 0.0],
            [0.5, 9.0, 2.0, 10.5],
        ];
        for k in 0..8 {
            let (a, b) = (k as f64 * std::f64::consts::FRAC_PI_4, (k + 1) as f64 * std::f64::consts::FRAC_PI_4);
            w.push([2.5 + 0.6 * a.cos(), 6.0 + 0.6 * a.sin(), 2.5 + 0.6 * b.cos(), 6.0 + 0.6 * b.sin()]);
        }
        w
    }

    fn beams(n: usize) -> Vec<f64> {
        (0..n).map(|k| -std::f64::consts::PI + 2.0 * std::f64::consts::PI * k as f64 / n as f64).collect()
    }

    const SENSOR: [f64; 3] = [0.1, 0.02, 0.0];

    fn build(walls: &[[f64; 4]], poses: &[[f64; 3]], p: SubmapParams) -> Submap {
        let angles = beams(720);
        let geom = ScanGeometry { angles: &angles, sensor: SENSOR };
        let mut s = Submap::new(p).unwrap();
        for &pose in poses {
            s.insert(pose, &geom, &cast(walls, geom.sensor_pose(pose), &angles)).unwrap();
        }
        s.finish().unwrap();
        s
    }

    fn room_submap(resolution: f64, depth: u32) -> Submap {
        let poses = [[1.5, 1.5, 0.0], [4.0, 1.0, 0.5], [8.6, 0.9, 1.0], [3.0, 5.0, -1.0], [4.5, 3.0, 2.0], [1.2, 6.5, 0.3]];
        build(&room(), &poses, SubmapParams { depth, ..params(resolution, 20.0) })
    }

    /// End points (robot frame) of a 180-beam scan of `walls` from robot pose `at`.
    fn query(walls: &[[f64; 4]], at: [f64; 3], max_range: f64) -> Vec<[f64; 2]> {
        let angles = beams(180);
        let geom = ScanGeometry { angles: &angles, sensor: SENSOR };
        scan_points(&geom, &cast(walls, geom.sensor_pose(at), &angles), max_range)
    }

    fn pose_error(a: [f64; 3], b: [f64; 3]) -> (f64, f64) {
        ((a[0] - b[0]).hypot(a[1] - b[1]), wrap(a[2] - b[2]).abs())
    }

    fn cholesky_ok(c: &[[f64; 3]; 3]) -> bool {
        let mut l = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..=i {
                let s: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
                if i == j {
                    if c[i][i] - s <= 0.0 || (c[i][i] - s).is_nan() {
                        return false;
                    }
                    l[i][i] = (c[i][i] - s).sqrt();
                } else {
                    l[i][j] = (c[i][j] - s) / l[j][j];
                }
            }
        }
        true
    }

    #[test]
    fn loop_closure_precomputed_grids_equal_brute_force_window_maxima() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut g = TiledGrid::new(0.1);
        g.ensure_covers(-1.0, -1.0, 2.5, 1.5).unwrap();
        for _ in 0..900 {
            let (ix, iy) = (rng.random_range(-10..25), rng.random_range(-10..15));
            let delta = rng.random_range(-2.5f32..3.0);
            g.add(ix, iy, delta, &MODEL);
        }
        let unknown = 0.1;
        let depth = 5;
        let grids = PrecomputedGrids::new(&g, depth, unknown, 0.0).unwrap();
        assert_eq!(grids.depth(), depth);
        let base = |ix: i32, iy: i32| {
            let l = g.get(ix, iy);
            quantise(if l.is_nan() { unknown } else { probability(l) })
        };
        let mut checked = 0;
        for h in 0..=depth {
            let w = 1 << h;
            for iy in grids.iy0 - 40..grids.iy0 + grids.ny as i32 + 5 {
                for ix in grids.ix0 - 40..grids.ix0 + grids.nx as i32 + 5 {
                    let mut want = 0;
                    for y in iy..iy + w {
                        for x in ix..ix + w {
                            want = want.max(base(x, y));
                        }
                    }
                    assert_eq!(grids.max_at(h, ix, iy), want, "h={h} at ({ix}, {iy})");
                    checked += 1;
                }
            }
        }
        assert!(checked > 10_000);
    }

    /// Every leaf of the search space, scored: the best key.
    fn exhaustive(space: &SearchSpace, grids: &PrecomputedGrids, min_sum: u32) -> Option<Candidate> {
        let mut best = (min_sum as u64) << 32;
        for k in 0..space.rotations.len() as u32 {
            for i in 0..=2 * space.n_x as u32 {
                for j in 0..=2 * space.n_y as u32 {
                    best = best.max(space.key(&space.candidate(grids, k, i, j, 0)));
                }
            }
        }
        (best > (min_sum as u64) << 32).then(|| space.decode(best))
    }

    #[test]
    fn loop_closure_released_grids_are_made_again_the_same() {
        let mut submap = room_submap(0.05, DEFAULT_DEPTH);
        let angles = beams(180);
        let geom = ScanGeometry { angles: &angles, sensor: SENSOR };
        let truth = [3.2, 3.6, 0.4];
        let ranges = cast(&room(), geom.sensor_pose(truth), &angles);
        let opts = MatchOptions { linear_window: 1.0, angular_window: 0.3, min_score: 0.5, refine: true };
        let initial = [3.6, 3.3, 0.3];
        let before = submap.match_scan(&geom, &ranges, initial, &opts).unwrap().expect("a match");
        let levels: Vec<Vec<u8>> = submap.grids().unwrap().levels.iter().map(|l| l.cells.clone()).collect();
        let (full, grid_only) = (submap.memory_bytes(), submap.grid().tiles().count() * TiledGrid::tile_bytes());
        submap.release_grids();
        assert!(submap.is_finished() && submap.grids().is_none());
        assert_eq!(submap.memory_bytes(), grid_only);
        assert!(full > 2 * grid_only, "the grids cost more than the submap: {full} against {grid_only} bytes");
        assert!(submap.match_scan(&geom, &ranges, initial, &opts).is_err(), "no grids, no search");
        assert!(submap.insert(truth, &geom, &ranges).is_err(), "still finished");
        submap.finish().unwrap();
        let again: Vec<Vec<u8>> = submap.grids().unwrap().levels.iter().map(|l| l.cells.clone()).collect();
        assert_eq!(levels, again);
        let after = submap.match_scan(&geom, &ranges, initial, &opts).unwrap().expect("a match");
        assert_eq!((before.pose, before.score), (after.pose, after.score));
    }

    #[test]
    fn loop_closure_branch_and_bound_equals_exhaustive_search() {
        let truth = [3.2, 3.6, 0.4];
        let pts = query(&room(), truth, 20.0);
        for depth in [2, 7] {
            let submap = room_submap(0.1, depth);
            let grids = submap.grids().unwrap();
            for (initial, lin, ang) in [
                ([3.5, 3.3, 0.3], 0.5, 0.2),
                ([2.9, 3.9, 0.6], 0.8, 0.3),
                ([6.0, 2.0, -1.0], 0.6, 0.15),
                ([3.2, 3.6, 0.4], 0.0, 0.0),
            ] {
                let space = SearchSpace::new(grids, &pts, initial, lin, ang).unwrap();
                for min_sum in [0, (0.5 * 255.0 * pts.len() as f64) as u32, (0.9 * 255.0 * pts.len() as f64) as u32] {
                    let want = exhaustive(&space, grids, min_sum);
                    let got = space.branch_and_bound(grids, min_sum);
                    let strip = |c: Option<Candidate>| c.map(|c| (c.k, c.i, c.j, c.sum));
                    assert_eq!(strip(got), strip(want), "depth {depth}, initial {initial:?}, min_sum {min_sum}");
                }
            }
        }
    }

    #[test]
    fn loop_closure_finds_a_far_displaced_scan_and_refines_it() {
        let submap = room_submap(0.05, DEFAULT_DEPTH);
        let grids = submap.grids().unwrap();
        let truth = [3.2, 3.6, 0.4];
        let pts = query(&room(), truth, 20.0);
        // 1.5 m and 20° off: far beyond the local matcher's few cells of reach.
        // Off the lattice on purpose (1.503 m, 20.3°), so that no leaf of the search lies on the truth.
        let initial = [truth[0] + 1.213, truth[1] - 0.887, truth[2] - 20.3f64.to_radians()];
        let t = Instant::now();
        let found = search(grids, &pts, initial, 2.0, 30f64.to_radians(), 0.6).unwrap().expect("a match");
        let searched = t.elapsed();
        let refined = refine(grids, &pts, &found);
        let (e_search, a_search) = pose_error(found.search_pose, truth);
        let (e, a) = pose_error(refined.pose, truth);
        println!(
            "search {searched:?}: score {:.3}, lattice pose off by {:.1} mm / {:.3}°, refined {:.1} mm / {:.3}°",
            found.score,
            e_search * 1e3,
            a_search.to_degrees(),
            e * 1e3,
            a.to_degrees()
        );
        // The best leaf lies next to the truth, if not always on the nearest lattice point.
        assert!(e_search <= 0.05 * std::f64::consts::SQRT_2 + 1e-9 && a_search <= found.angular_step + 1e-9);
        assert!(e < 0.02 && a < 0.5f64.to_radians(), "refined pose {:?}", refined.pose);
        assert!(found.score > 0.6 && found.score <= 1.0);
        // Through the submap's own entry point too.
        let angles = beams(180);
        let geom = ScanGeometry { angles: &angles, sensor: SENSOR };
        let ranges = cast(&room(), geom.sensor_pose(truth), &angles);
        let opts = MatchOptions { linear_window: 2.0, angular_window: 30f64.to_radians(), min_score: 0.6, refine: true };
        let m = submap.match_scan(&geom, &ranges, initial, &opts).unwrap().unwrap();
        assert_eq!(m.pose, refined.pose);
        let c = constraint(submap.origin().unwrap(), &m);
        assert!(pose_error(compose(submap.origin().unwrap(), c), m.pose).0 < 1e-12);
    }

    #[test]
    fn loop_closure_rejects_a_scan_from_another_room() {
        let submap = room_submap(0.05, DEFAULT_DEPTH);
        let grids = submap.grids().unwrap();
        let pts = query(&other_room(), [2.2, 3.0, 0.2], 20.0);
        let initial = [3.2, 3.6, 0.4];
        let local = search(grids, &pts, initial, 2.0, 30f64.to_radians(), 0.0).unwrap().unwrap();
        let global = search(grids, &pts, [5.0, 4.0, 0.0], 5.0, std::f64::consts::PI, 0.0).unwrap().unwrap();
        println!("another room: best score {:.3} in the window, {:.3} over the whole submap", local.score, global.score);
        assert!(search(grids, &pts, initial, 2.0, 30f64.to_radians(), 0.6).unwrap().is_none());
        assert!(search(grids, &pts, [5.0, 4.0, 0.0], 5.0, std::f64::consts::PI, 0.6).unwrap().is_none());
        // ... while the right room's scan from there scores well above that.
        let right = query(&room(), [3.2, 3.6, 0.4], 20.0);
        let good = search(grids, &right, initial, 0.2, 0.1, 0.0).unwrap().unwrap();
        assert!(good.score > 0.6 && good.score > global.score + 0.15, "{} vs {}", good.score, global.score);
    }

    #[test]
    fn loop_closure_same_bits_with_one_and_two_threads() {
        let submap = room_submap(0.05, DEFAULT_DEPTH);
        let grids = submap.grids().unwrap();
        let truth = [3.2, 3.6, 0.4];
        let pts = query(&room(), truth, 20.0);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let m = search(grids, &pts, [5.0, 4.0, 0.0], 5.0, std::f64::consts::PI, 0.3).unwrap().unwrap();
                let w = search(grids, &pts, [4.4, 2.7, 0.05], 2.0, 0.5, 0.3).unwrap().unwrap();
                let regrids = PrecomputedGrids::new(submap.grid(), DEFAULT_DEPTH, DEFAULT_UNKNOWN_PROBABILITY, 0.0).unwrap();
                let levels: Vec<Vec<u8>> = regrids.levels.iter().map(|l| l.cells.clone()).collect();
                (refine(grids, &pts, &m), refine(grids, &pts, &w), levels)
            })
        };
        let bits = |m: &LoopMatch| {
            let mut v: Vec<u64> = m.pose.iter().chain(&m.search_pose).map(|x| x.to_bits()).collect();
            v.push(m.score.to_bits());
            v.extend(m.covariance.iter().flatten().map(|x| x.to_bits()));
            v
        };
        let (a1, b1, l1) = run(1);
        let (a2, b2, l2) = run(2);
        assert_eq!(bits(&a1), bits(&a2));
        assert_eq!(bits(&b1), bits(&b2));
        assert!(l1 == l2);
        assert!(pose_error(a1.pose, truth).0 < 0.02);
    }

    #[test]
    fn loop_closure_covariance_is_positive_definite_and_long_along_a_corridor() {
        // Two parallel walls 2 m apart, far longer than the 8 m range: nothing fixes x.
        let walls = [[-40.0, 0.013, 40.0, 0.013], [-40.0, 2.037, 40.0, 2.037]];
        let submap = build(&walls, &[[-3.0, 1.0, 0.0], [0.0, 1.1, 0.1], [3.0, 0.9, -0.1]], params(0.05, 8.0));
        let grids = submap.grids().unwrap();
        let pts = query(&walls, [0.4, 1.02, 0.05], 8.0);
        let m = search(grids, &pts, [0.5, 1.1, 0.0], 0.5, 0.2, 0.5).unwrap().unwrap();
        let c = m.covariance;
        println!("corridor: σx {:.3} m, σy {:.3} m, σθ {:.3}°", c[0][0].sqrt(), c[1][1].sqrt(), c[2][2].sqrt().to_degrees());
        for (p, row) in c.iter().enumerate() {
            for (q, v) in row.iter().enumerate() {
                assert_eq!(*v, c[q][p]);
            }
        }
        assert!(cholesky_ok(&c));
        assert!(c[0][0] > 4.0 * c[1][1], "{c:?}");
        assert!((m.pose[1] - 1.02).abs() <= 0.05 && wrap(m.pose[2] - 0.05).abs() <= 2.0 * m.angular_step);
        // In the room every direction is fixed: near the floor of one cell and one step.
        let rs = room_submap(0.05, DEFAULT_DEPTH);
        let pts = query(&room(), [3.2, 3.6, 0.4], 20.0);
        let r = search(rs.grids().unwrap(), &pts, [3.3, 3.5, 0.4], 0.5, 0.2, 0.5).unwrap().unwrap();
        let c = r.covariance;
        println!("room: σx {:.3} m, σy {:.3} m, σθ {:.3}°", c[0][0].sqrt(), c[1][1].sqrt(), c[2][2].sqrt().to_degrees());
        assert!(cholesky_ok(&c));
        assert!(c[0][0] < 2.0 * 0.05f64.powi(2) && c[1][1] < 2.0 * 0.05f64.powi(2));
        assert!(c[2][2] < 2.0 * r.angular_step.powi(2));
    }

    #[test]
    fn loop_closure_spread_is_the_gaussian_discounted_neighbour_maximum() {
        // One cell of 0.9 among cells of 0.1: with σ one cell, its four neighbours get 0.9·e^(-1/2),
        // its diagonal ones 0.9·e^(-1), and the cells two away keep their 0.1 (beyond σ).
        let (nx, ny) = (5, 5);
        let mut p = vec![0.1f32; nx * ny];
        p[2 * nx + 2] = 0.9;
        let s = spread(&p, nx, ny, 0.05, 0.05);
        let near = |a: f32, b: f32| (a - b).abs() < 1e-6;
        assert!(near(s[2 * nx + 2], 0.9));
        for (x, y) in [(1, 2), (3, 2), (2, 1), (2, 3)] {
            assert!(near(s[y * nx + x], 0.9 * (-0.5f32).exp()), "{x} {y}: {}", s[y * nx + x]);
        }
        for (x, y) in [(1, 1), (3, 3), (1, 3), (3, 1)] {
            assert!(near(s[y * nx + x], 0.9 * (-1.0f32).exp()));
        }
        assert!(near(s[0], 0.1) && near(s[2 * nx], 0.1));
        // σ two cells reaches two cells: 0.9·e^(-4/8) there; σ 0 changes nothing.
        let s2 = spread(&p, nx, ny, 0.05, 0.1);
        assert!(near(s2[2 * nx], 0.9 * (-0.5f32).exp()));
        assert_eq!(spread(&p, nx, ny, 0.05, 0.0), p);
    }

    #[test]
    fn loop_closure_spread_finds_a_corridor_junction_whose_walls_lie_on_cell_borders() {
        // A corridor along x whose walls run along cell borders, a junction at x 3..5 and its end
        // wall at x = 0, seen as the omnidirectional ToF rig sees it (nothing within 20° of the
        // diagonals, where the pyramid's edges are) with range noise of about 1 cm: end points
        // fall on either side of the borders. A scan at the junction, searched from 2 m along
        // the corridor in the spread submap, must be found at the junction, and score higher
        // there than in the raw one.
        let walls = [
            [0.0, 0.0, 30.0, 0.0],
            [0.0, 2.2, 3.0, 2.2],
            [5.0, 2.2, 30.0, 2.2],
            [3.0, 2.2, 3.0, 6.0],
            [5.0, 2.2, 5.0, 6.0],
            [0.0, 0.0, 0.0, 2.2],
        ];
        let angles: Vec<f64> = beams(360)
            .into_iter()
            .filter(|a| (a.rem_euclid(std::f64::consts::FRAC_PI_2) - std::f64::consts::FRAC_PI_4).abs() > 20f64.to_radians())
            .collect();
        let noisy = |r: Vec<f32>, seed: u64| -> Vec<f32> {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            r.iter().map(|&v| v + rng.random_range(-0.017f32..0.017)).collect()
        };
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let truth = [4.1, 1.1, 0.0];
        let pts = scan_points(&geom, &noisy(cast(&walls, truth, &angles), 99), 7.0);
        let submap = |sigma: f64| {
            let mut s = Submap::new(SubmapParams { spread_sigma: sigma, ..params(0.05, 7.0) }).unwrap();
            for k in 0..12 {
                let pose = [1.0 + 0.5 * k as f64, 1.1, 0.0];
                s.insert(pose, &geom, &noisy(cast(&walls, pose, &angles), k)).unwrap();
            }
            s.finish().unwrap();
            s
        };
        let (raw, spread) = (submap(0.0), submap(0.05));
        let m = search(spread.grids().unwrap(), &pts, [6.1, 1.1, 0.0], 2.5, 0.2, 0.3).unwrap().unwrap();
        let (dxy, dth) = pose_error(m.pose, truth);
        assert!(dxy <= 0.05 && dth <= m.angular_step, "{dxy} m, {dth} rad");
        let at_raw = search(raw.grids().unwrap(), &pts, m.pose, 0.0, 0.0, 0.0).unwrap().unwrap();
        println!("junction: score {:.3} spread, {:.3} raw", m.score, at_raw.score);
        assert!(m.score > at_raw.score + 0.05);
    }

    #[test]
    fn loop_closure_errors_instead_of_panics() {
        let mut s = Submap::new(params(0.05, 10.0)).unwrap();
        let angles = beams(8);
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        assert!(s.insert([0.0, 0.0, 0.0], &geom, &[1.0; 7]).is_err());
        assert!(s.insert([f64::NAN, 0.0, 0.0], &geom, &[1.0; 8]).is_err());
        assert!(s.insert([1e6, 0.0, 0.0], &geom, &[1.0; 8]).is_ok());
        assert!(s.insert([0.0, 0.0, 0.0], &geom, &[1.0; 8]).is_err(), "1000 km wide submap");
        let opts = MatchOptions { linear_window: 1.0, angular_window: 0.1, min_score: 0.5, refine: true };
        assert!(s.match_scan(&geom, &[1.0; 8], [1e6, 0.0, 0.0], &opts).is_err(), "not finished");
        s.finish().unwrap();
        assert_eq!(s.num_scans(), 1);
        assert_eq!(s.origin(), Some([1e6, 0.0, 0.0]));
        assert!(s.insert([1e6, 0.0, 0.0], &geom, &[1.0; 8]).is_err(), "finished");
        let g = s.grids().unwrap();
        let pts = [[1.0, 0.0]];
        assert!(search(g, &pts, [0.0, 0.0, f64::INFINITY], 1.0, 0.1, 0.5).is_err());
        assert!(search(g, &pts, [0.0, 0.0, 0.0], -1.0, 0.1, 0.5).is_err());
        assert!(search(g, &pts, [0.0, 0.0, 0.0], 1.0, 0.1, 1.5).is_err());
        assert!(search(g, &[[f64::NAN, 0.0]], [0.0, 0.0, 0.0], 1.0, 0.1, 0.5).is_err());
        assert!(search(g, &pts, [1e12, 0.0, 0.0], 1.0, 0.1, 0.5).is_err());
        assert!(search(g, &pts, [0.0, 0.0, 0.0], 1e5, 3.0, 0.5).is_err(), "too many poses");
        assert!(search(g, &[], [0.0, 0.0, 0.0], 1.0, 0.1, 0.5).unwrap().is_none());
        // An empty submap finishes and matches nothing.
        let mut e = Submap::new(params(0.05, 10.0)).unwrap();
        let eg = e.finish().unwrap();
        assert!(search(eg, &pts, [0.0, 0.0, 0.0], 1.0, 3.2, 0.5).unwrap().is_none());
        assert!(Submap::new(SubmapParams { resolution: 0.0, ..params(0.05, 10.0) }).is_err());
        assert!(Submap::new(SubmapParams { depth: 40, ..params(0.05, 10.0) }).is_err());
    }

    #[test]
    fn loop_closure_timing_of_a_global_and_a_windowed_search() {
        // A 15 m × 15 m floor with inner walls, pillars and a slanted wall.
        let mut walls = vec![
            [0.0, 0.0, 15.0, 0.0],
            [15.0, 0.0, 15.0, 15.0],
            [15.0, 15.0, 0.0, 15.0],
            [0.0, 15.0, 0.0, 0.0],
            [5.01, 0.0, 5.01, 6.0],
            [10.02, 15.0, 10.02, 8.03],
            [0.0, 10.04, 4.0, 10.04],
            [9.03, 4.01, 15.0, 4.01],
            [2.0, 3.0, 4.0, 5.0],
        ];
        walls.extend(square(7.5, 7.5, 0.3));
        walls.extend(square(12.0, 11.0, 0.4));
        let mut poses = vec![];
        for (x, y) in [(2.5, 2.0), (7.5, 2.0), (12.5, 2.0), (2.5, 7.5), (7.0, 9.5), (12.5, 6.5), (2.5, 12.5), (7.5, 12.5), (12.5, 12.5)] {
            poses.push([x, y, 0.3 * x - 0.2 * y]);
        }
        let t = Instant::now();
        let submap = build(&walls, &poses, params(0.05, 20.0));
        let built = t.elapsed();
        let t = Instant::now();
        let grids = PrecomputedGrids::new(submap.grid(), DEFAULT_DEPTH, DEFAULT_UNKNOWN_PROBABILITY, 0.0).unwrap();
        let precomputed = t.elapsed();
        let truth = [11.3, 9.2, 2.1];
        let pts = query(&walls, truth, 20.0);
        let t = Instant::now();
        let global = search(&grids, &pts, [7.5, 7.5, 0.0], 7.5, std::f64::consts::PI, 0.6).unwrap().unwrap();
        let t_global = t.elapsed();
        let t = Instant::now();
        let windowed = search(&grids, &pts, [12.6, 8.1, 1.8], 2.0, 30f64.to_radians(), 0.6).unwrap().unwrap();
        let t_windowed = t.elapsed();
        let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let (t_global_1, t_windowed_1) = one.install(|| {
            let t = Instant::now();
            search(&grids, &pts, [7.5, 7.5, 0.0], 7.5, std::f64::consts::PI, 0.6).unwrap().unwrap();
            let g = t.elapsed();
            let t = Instant::now();
            search(&grids, &pts, [12.6, 8.1, 1.8], 2.0, 30f64.to_radians(), 0.6).unwrap().unwrap();
            (g, t.elapsed())
        });
        let t = Instant::now();
        let refined = refine(&grids, &pts, &global);
        let t_refine = t.elapsed();
        println!(
            "15 m × 15 m submap at 0.05 m ({} scans, built in {built:?}): precomputed grids {:.1} MB in {precomputed:?}",
            submap.num_scans(),
            grids.memory_bytes() as f64 / 1e6
        );
        println!(
            "{} points, angular step {:.3}°: global search {t_global:?} (score {:.3}), ±2 m ±30° search {t_windowed:?}, refinement {t_refine:?}",
            pts.len(),
            global.angular_step.to_degrees(),
            global.score
        );
        println!(
            "one thread: global {t_global_1:?}, windowed {t_windowed_1:?} ({} threads above)",
            rayon::current_num_threads()
        );
        let (e, a) = pose_error(refined.pose, truth);
        println!("global match off by {:.1} mm / {:.3}° after refinement", e * 1e3, a.to_degrees());
        assert!(e < 0.02 && a < 0.5f64.to_radians());
        let (e, a) = pose_error(windowed.search_pose, truth);
        assert!(e < 0.05 && a < windowed.angular_step);
    }

    #[test]
    fn loop_closure_refinement_gets_below_the_lattice() {
        let submap = room_submap(0.05, DEFAULT_DEPTH);
        let grids = submap.grids().unwrap();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let (mut lattice, mut refined, mut worst) = ([0.0; 2], [0.0; 2], [0.0f64; 2]);
        let n = 40;
        for _ in 0..n {
            let truth = [rng.random_range(1.0..5.5), rng.random_range(0.6..3.8), rng.random_range(-3.1..3.1)];
            let pts = query(&room(), truth, 20.0);
            let initial = [
                truth[0] + rng.random_range(-1.0..1.0),
                truth[1] + rng.random_range(-1.0..1.0),
                truth[2] + rng.random_range(-0.3..0.3),
            ];
            let m = search(grids, &pts, initial, 1.5, 0.4, 0.5).unwrap().unwrap();
            let r = refine(grids, &pts, &m);
            let (el, al) = pose_error(m.search_pose, truth);
            let (er, ar) = pose_error(r.pose, truth);
            lattice = [lattice[0] + el * el, lattice[1] + al * al];
            refined = [refined[0] + er * er, refined[1] + ar * ar];
            worst = [worst[0].max(er), worst[1].max(ar)];
        }
        let rms = |s: [f64; 2]| [(s[0] / n as f64).sqrt(), (s[1] / n as f64).sqrt()];
        let (l, r) = (rms(lattice), rms(refined));
        println!(
            "rms error on the lattice {:.1} mm / {:.3}°, refined {:.1} mm / {:.3}°; worst refined {:.1} mm / {:.3}°",
            l[0] * 1e3,
            l[1].to_degrees(),
            r[0] * 1e3,
            r[1].to_degrees(),
            worst[0] * 1e3,
            worst[1].to_degrees()
        );
        assert!(r[0] < 0.5 * l[0] && r[1] < 0.7 * l[1]);
        assert!(worst[0] < 0.02 && worst[1] < 0.5f64.to_radians());
    }
}
