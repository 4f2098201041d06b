//! The scan-matching proposal of Grisetti, Stachniss & Burgard, "Improved techniques for grid
//! mapping with Rao-Blackwellized particle filters" (IEEE T-RO 2007), and the likelihood-field
//! observation model it matches against (Probabilistic Robotics, section 6.4).
//!
//! Per particle: start at the pose the odometry predicts (or, with `climb_from_sample`, at a
//! pose drawn from the motion model), climb the likelihood field of the particle's own map to the
//! mode, evaluate the target p(z|m,x)·p(x|x',u) at K poses around the mode, fit a Gaussian to
//! them, draw the new pose from it and multiply the weight by the normaliser
//! η = Σ_k p(z|m,x_k)·p(x_k|x',u). Before that, `check_odometry` may replace the step's odometry
//! where a wide search (correlative.rs) finds the scan far from where the odometry puts it.

use std::sync::Arc;

use rand::RngExt;
use rand_distr::StandardNormal;

use crate::correlative::{correlative_search, SearchWindow};
use crate::grid::{GridError, TiledGrid, MAX_CELL_INDEX, TILE};
use crate::motion::{compose, decompose, relative, wrap, OdometryMotion};
use crate::raycast::floor_i32;
use crate::sensor_model::ScanGeometry;

/// Likelihood field: each beam end point is scored by its distance d to the nearest occupied
/// cell's mean end point (see grid.rs), p = z_hit·N(d; 0, σ) + z_rand/max_range.
///
/// The distance is searched in the grid around the end point, ring by ring up to `window`
/// cells, instead of being read from a precomputed distance field: end points of a matched
/// scan lie within a cell or two of an obstacle, so the search mostly stops after 9–25 cells,
/// and the map needs no second structure to keep up to date when cells turn free again.
///
/// With `fit_walls`, d is instead the distance to the wall fitted through the mean end points
/// around the nearest one (see `wall_distance`), searched exactly within window·resolution, and the
/// Gaussian runs continuously into the floor there. Why: the nearest mean end point alone is a
/// noisy and biased stand-in for a wall. Along a wall the points sit a cell apart, and the
/// cells on the sensor's side of a surface are crossed by most beams and turn free while
/// those behind it keep even single stray hits, so the occupied means lie behind the surface.
/// On the simulated corridor loop, scans matched against a map built from the true poses came
/// out 3.7 mm too far forward each (1.1 mm with fitted walls); the global optimum of the score
/// lay 0.11° (rms) off the true heading against the map behind the robot, 0.04° against the
/// true walls. Chained scan after scan, with a 5 cm field, the estimate stretched the corridors
/// by about 1 % and its heading wandered by a degree over the loop; with fitted walls and a
/// 2 cm field, 0.14–0.23° rms (at most 0.4–0.7°) with 10 particles.
#[derive(Clone, Debug)]
pub struct LikelihoodField {
    pub sigma: f64,
    pub z_hit: f64,
    pub z_rand: f64,
    pub max_range: f64,
    pub window: i32,
    pub occupied_threshold: f32,
    pub fit_walls: bool,
    table: Arc<LogLikelihoodTable>,
}

/// ln(z_hit·N(d; 0, σ) + z_rand/max_range) tabulated against q = d²/(2σ²), read with linear
/// interpolation. Why: the hill climbing and the proposal's 27 poses evaluate it for every end
/// point of every candidate pose, and `exp` and `ln` took a seventh of the filter's time on
/// Intel. Written here because it is four lines that no library offers for this function.
/// The function is smooth (second derivative at most 1/4 in q), so with TABLE_SIZE knots the
/// interpolation error stays below h²/32 ≈ 6e-6 per point; beyond `q_max` the Gaussian is below
/// 1e-9 of the floor and the value is the floor's.
#[derive(Debug)]
struct LogLikelihoodTable {
    q_max: f64,
    knots_per_q: f64,
    values: Vec<f64>,
    floor_ln: f64,
}

const TABLE_SIZE: usize = 4096;

impl LogLikelihoodTable {
    fn new(sigma: f64, z_hit: f64, z_rand: f64, max_range: f64) -> Self {
        let peak = z_hit / (sigma * (2.0 * std::f64::consts::PI).sqrt());
        // Never 0: ln(0) = −inf would make every particle's weight NaN (z_rand = 5e-324 does it).
        let floor = (z_rand / max_range).max(f64::MIN_POSITIVE);
        // Where peak·e^(−q) = 1e-9·floor; at least one knot apart from 0 for degenerate settings.
        // In logarithms: peak / (1e-9·floor) overflows to inf for a floor below ~1e-296.
        let q_max = (peak.ln() - floor.ln() + 9.0 * std::f64::consts::LN_10).max(1.0);
        let knots_per_q = (TABLE_SIZE - 1) as f64 / q_max;
        let values = (0..TABLE_SIZE).map(|k| (peak * (-(k as f64) / knots_per_q).exp() + floor).ln()).collect();
        LogLikelihoodTable { q_max, knots_per_q, values, floor_ln: floor.ln() }
    }

    #[inline]
    fn at(&self, q: f64) -> f64 {
        if !(q < self.q_max) {
            return self.floor_ln; // also for an infinite distance (no obstacle in the window)
        }
        let x = q * self.knots_per_q;
        let k = x as usize;
        let t = x - k as f64;
        let (a, b) = (self.values[k], self.values[(k + 1).min(TABLE_SIZE - 1)]);
        a + t * (b - a)
    }
}

/// Beam end points in the sensor frame, every `stride`-th beam with a reading below max_range.
pub fn endpoints(geom: &ScanGeometry, ranges: &[f32], stride: usize, max_range: f64) -> Vec<[f64; 2]> {
    (0..ranges.len())
        .step_by(stride.max(1))
        .filter_map(|i| {
            let r = ranges[i] as f64;
            (r.is_finite() && r < max_range && r > 0.0).then(|| {
                let (s, c) = geom.angles[i].sin_cos();
                [r * c, r * s]
            })
        })
        .collect()
}

/// Calls `visit` on every cell of the square ring `r` cells out from (ix, iy) (the cell itself
/// for r = 0), in a fixed order, so that ties between equally near cells resolve the same way
/// in every search.
#[inline]
fn for_ring(ix: i32, iy: i32, r: i32, mut visit: impl FnMut(i32, i32)) {
    if r == 0 {
        visit(ix, iy);
        return;
    }
    for k in -r..=r {
        visit(ix + k, iy - r);
        visit(ix + k, iy + r);
    }
    for k in (-r + 1)..r {
        visit(ix - r, iy + k);
        visit(ix + r, iy + k);
    }
}

impl LikelihoodField {
    pub fn new(sigma: f64, z_hit: f64, z_rand: f64, max_range: f64, window: i32, occupied_threshold: f32, fit_walls: bool) -> Self {
        let table = Arc::new(LogLikelihoodTable::new(sigma, z_hit, z_rand, max_range));
        LikelihoodField { sigma, z_hit, z_rand, max_range, window, occupied_threshold, fit_walls, table }
    }

    /// (squared distance, offset (dx, dy) from the point to) the nearest occupied cell's mean end
    /// point among `candidates` of the point's cell; infinite distance if there is none.
    #[inline]
    fn nearest_cell(&self, grid: &TiledGrid, x: f64, y: f64) -> (f64, [f64; 2]) {
        let res = grid.resolution;
        let (ix, iy) = (floor_i32(x / res), floor_i32(y / res));
        let mut best = f64::INFINITY;
        let mut offset = [0.0; 2];
        self.candidates(grid, ix, iy, |h| {
            let (dx, dy) = (h[0] - x, h[1] - y);
            if dx * dx + dy * dy < best {
                best = dx * dx + dy * dy;
                offset = [dx, dy];
            }
        });
        (best, offset)
    }

    /// The mean end points of the occupied cells that the search for a point in cell (ix, iy)
    /// considers, in a fixed order: ring by ring out to `window` cells, stopping one ring after
    /// the first ring that holds any (a diagonal neighbour there can still be nearer). They
    /// depend on the cell alone, which is what lets `FieldView` remember them.
    #[inline]
    fn candidates(&self, grid: &TiledGrid, ix: i32, iy: i32, visit: impl FnMut([f64; 2])) {
        // A cell beyond the grid's reach (a pose very far out: its index saturated) has no
        // obstacle near it, and its neighbourhood's tile arithmetic would overflow.
        if !(ix.unsigned_abs() < MAX_CELL_INDEX as u32 && iy.unsigned_abs() < MAX_CELL_INDEX as u32) {
            return;
        }
        if self.window >= TILE / 2 {
            return self.candidates_in(|cx, cy| grid.occupied_hit(cx, cy, self.occupied_threshold), ix, iy, visit);
        }
        let near = grid.neighbourhood(ix, iy, self.window);
        self.candidates_in(|cx, cy| near.occupied_hit(cx, cy, self.occupied_threshold), ix, iy, visit)
    }

    /// `candidates` through `occupied_hit`, the grid's or a neighbourhood's.
    #[inline(always)]
    fn candidates_in(&self, occupied_hit: impl Fn(i32, i32) -> Option<[f64; 2]>, ix: i32, iy: i32, mut visit: impl FnMut([f64; 2])) {
        let mut found_at = None;
        for r in 0..=self.window {
            if let Some(f) = found_at {
                if r > f + 1 {
                    break;
                }
            }
            let mut any = false;
            for_ring(ix, iy, r, |cx, cy| {
                if let Some(h) = occupied_hit(cx, cy) {
                    any = true;
                    visit(h);
                }
            });
            if any && found_at.is_none() {
                found_at = Some(r);
            }
        }
    }

    /// The search radius (m) with `fit_walls`: end points farther than this from every
    /// obstacle score z_rand/max_range.
    #[inline]
    fn radius(&self, res: f64) -> f64 {
        self.window as f64 * res
    }

    /// (squared distance, offset (dx, dy) from the point to the nearest obstacle, unit normal of
    /// the fitted wall if the distance runs across one); infinite distance if there is none.
    #[inline]
    fn nearest(&self, grid: &TiledGrid, x: f64, y: f64) -> (f64, [f64; 2], Option<[f64; 2]>) {
        if self.fit_walls {
            self.nearest_wall(grid, x, y)
        } else {
            let (d2, offset) = self.nearest_cell(grid, x, y);
            (d2, offset, None)
        }
    }

    /// The nearest occupied cell's mean end point within `radius`, then the wall through it
    /// (`wall_distance`). Exact: the rings stop only once no cell of the next ring can hold a nearer
    /// point (a cell r rings away lies at least (r − 1) cells from any point of the centre cell).
    #[inline]
    fn nearest_wall(&self, grid: &TiledGrid, x: f64, y: f64) -> (f64, [f64; 2], Option<[f64; 2]>) {
        let res = grid.resolution;
        let radius = self.radius(res);
        let (ix, iy) = (floor_i32(x / res), floor_i32(y / res));
        let mut best = radius * radius;
        let mut offset = [0.0; 2];
        let mut found = None;
        for r in 0..=self.window + 1 {
            if r >= 1 {
                let gap = (r - 1) as f64 * res;
                if gap * gap >= best {
                    break;
                }
            }
            for_ring(ix, iy, r, |cx, cy| {
                if let Some(h) = grid.occupied_hit(cx, cy, self.occupied_threshold) {
                    let (dx, dy) = (h[0] - x, h[1] - y);
                    if dx * dx + dy * dy < best {
                        best = dx * dx + dy * dy;
                        offset = [dx, dy];
                        found = Some((cx, cy));
                    }
                }
            });
        }
        match found {
            Some(cell) => self.wall_distance(grid, x, y, cell).unwrap_or((best, offset, None)),
            None => (f64::INFINITY, offset, None),
        }
    }

    /// (squared distance, offset, unit normal) from (x, y) to the wall through the mean end points
    /// of the cells around `cell` (3×3), a line fitted to them weighted by their end point counts:
    /// the distance across it, plus the part of the distance along it that reaches past the
    /// points' extent (then no normal). Cells count whether occupied or not, so that the end
    /// points on the sensor's side of a surface, whose cells the beams cleared, still pull the
    /// wall towards where the end points fell. None where the points do not lie along a line
    /// (fewer than three cells, or a corner).
    #[inline]
    fn wall_distance(&self, grid: &TiledGrid, x: f64, y: f64, cell: (i32, i32)) -> Option<(f64, [f64; 2], Option<[f64; 2]>)> {
        let mut n = 0.0;
        let mut cells = 0;
        let (mut sx, mut sy, mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for cy in cell.1 - 1..=cell.1 + 1 {
            for cx in cell.0 - 1..=cell.0 + 1 {
                if let Some((h, count)) = grid.hit_mean(cx, cy) {
                    // Relative to the query point: small numbers, no cancellation.
                    let (u, v) = (h[0] - x, h[1] - y);
                    let w = count as f64;
                    cells += 1;
                    n += w;
                    sx += w * u;
                    sy += w * v;
                    sxx += w * u * u;
                    sxy += w * u * v;
                    syy += w * v * v;
                }
            }
        }
        if cells < 3 {
            return None;
        }
        let (mx, my) = (sx / n, sy / n);
        let (a, b, c) = (sxx / n - mx * mx, sxy / n - mx * my, syy / n - my * my);
        let half_diff = 0.5 * (a - c);
        let root = (half_diff * half_diff + b * b).sqrt();
        let (major, minor) = (0.5 * (a + c) + root, 0.5 * (a + c) - root);
        if minor >= 0.1 * major {
            return None;
        }
        // Direction of the major axis, and the line's normal.
        let phi = 0.5 * (2.0 * b).atan2(a - c);
        let (su, cu) = phi.sin_cos();
        // Centroid relative to the point: across and along the line.
        let across = -su * mx + cu * my;
        let along = cu * mx + su * my;
        let half_length = (3.0 * major).sqrt();
        let past = if along.abs() > half_length { along - half_length * along.signum() } else { 0.0 };
        let offset = [-su * across + cu * past, cu * across + su * past];
        let normal = (past == 0.0).then_some([-su, cu]);
        Some((across * across + past * past, offset, normal))
    }

    /// The Gaussian part of a point at squared distance d2; with `fit_walls`, less its value at
    /// the search radius, so that the score runs continuously into z_rand/max_range there (a
    /// step makes the scan match jump between poses).
    #[inline]
    fn hit_density(&self, d2: f64, radius2: f64) -> f64 {
        if !d2.is_finite() || (self.fit_walls && d2 >= radius2) {
            return 0.0;
        }
        let norm = 1.0 / (self.sigma * (2.0 * std::f64::consts::PI).sqrt());
        let gauss = |q: f64| (-0.5 * q / (self.sigma * self.sigma)).exp();
        if self.fit_walls {
            norm * (gauss(d2) - gauss(radius2))
        } else {
            norm * gauss(d2)
        }
    }

    #[inline]
    fn point_log_likelihood(&self, d2: f64, radius2: f64) -> f64 {
        if self.fit_walls {
            // The shifted Gaussian depends on the grid's resolution: computed exactly.
            return (self.z_hit * self.hit_density(d2, radius2) + self.z_rand / self.max_range).ln();
        }
        self.table.at(0.5 * d2 / (self.sigma * self.sigma))
    }

    /// (mean log-likelihood over the points, points with an obstacle inside the window) for
    /// end points `pts` (sensor frame) seen from sensor pose `sp`. One-off scores; a match that
    /// scores many poses in one map reads it through a `FieldView`.
    pub fn score(&self, grid: &TiledGrid, sp: [f64; 3], pts: &[[f64; 2]]) -> (f64, usize) {
        self.score_with(|x, y| self.nearest(grid, x, y).0, grid.resolution, sp, pts)
    }

    /// `score` with the squared distance to the nearest obstacle given by `nearest_d2`.
    #[inline]
    fn score_with(&self, nearest_d2: impl Fn(f64, f64) -> f64, resolution: f64, sp: [f64; 3], pts: &[[f64; 2]]) -> (f64, usize) {
        if pts.is_empty() {
            return (0.0, 0);
        }
        let (s, c) = sp[2].sin_cos();
        let radius = self.radius(resolution);
        let mut total = 0.0;
        let mut matched = 0;
        for p in pts {
            let x = sp[0] + c * p[0] - s * p[1];
            let y = sp[1] + s * p[0] + c * p[1];
            let d2 = nearest_d2(x, y);
            if d2.is_finite() {
                matched += 1;
            }
            total += self.point_log_likelihood(d2, radius * radius);
        }
        (total / pts.len() as f64, matched)
    }
}

/// The likelihood field read in one map while that map stays unchanged: one scan match, or a
/// chain of them in the same map. The borrow of the grid guarantees that nothing changes it
/// while the view lives, so the view may remember what it has looked up.
///
/// What it remembers: per grid cell, the occupied cells that `nearest_cell`'s ring search visits
/// from any point of that cell (which cells, and in which order, depend on the cell alone; only
/// the distances depend on the point). A match evaluates the same end points at dozens of poses
/// a fraction of a cell apart (the hill climb's last steps, the proposal's 27 poses, Gauss-Newton),
/// so most searches start in a cell already searched; the view then measures the distances to
/// that cell's few remembered candidates instead of walking the cells of its search window (49
/// with the default window of 3) again. Same candidates, same order, same strict comparison:
/// every result is bit-identical to
/// `LikelihoodField::nearest`. With `fit_walls` (whose search depends on the point, not the cell)
/// the view reads the field directly.
pub struct FieldView<'a> {
    pub field: &'a LikelihoodField,
    pub grid: &'a TiledGrid,
    cache: std::cell::RefCell<CandidateCache>,
}

/// A direct-mapped table from grid cells to their candidate lists, stored one after the other in
/// `points`. Written here rather than taken from a hash map crate: a general hash map costs
/// about as much per lookup as the search it would save. A slot is valid only while it carries
/// the table's current `generation`, which advances with each new view and each restart, so a
/// table is handed from one view to the next on the same thread without clearing it (a filter
/// step makes one view per particle).
struct CandidateCache {
    slots: Vec<CacheSlot>,
    points: Vec<[f64; 2]>,
    generation: u32,
    /// CACHE_POINTS, lowered by a test to reach the restart.
    max_points: usize,
}

#[derive(Clone, Copy, Default)]
struct CacheSlot {
    cell: (i32, i32),
    start: u32,
    len: u32,
    generation: u32,
}

/// 8192 slots (160 KiB), 128 × 64 cells by position: a match in a real log touches one to two
/// thousand cells (Freiburg 079: with 2048 slots half again as many searches). Slots by position
/// rather than by a hash keep the neighbouring end points of a scan in neighbouring slots.
const CACHE_X_BITS: u32 = 7;
const CACHE_Y_BITS: u32 = 6;
const CACHE_BITS: u32 = CACHE_X_BITS + CACHE_Y_BITS;
/// When the stored candidates reach this many, the table starts afresh (evicted lists stay in
/// `points` until then).
const CACHE_POINTS: usize = 1 << 16;

thread_local! {
    /// The table of the last view dropped on this thread, for the next one.
    static SPARE_CACHE: std::cell::Cell<Option<CandidateCache>> = const { std::cell::Cell::new(None) };
}

impl CandidateCache {
    /// A table with no valid slot: the spare one of this thread, or a new one.
    fn fresh() -> Self {
        let mut cache = SPARE_CACHE.with(|spare| spare.take()).unwrap_or_else(|| CandidateCache {
            slots: vec![CacheSlot::default(); 1 << CACHE_BITS],
            points: Vec::new(),
            generation: 0,
            max_points: CACHE_POINTS,
        });
        cache.max_points = CACHE_POINTS;
        cache.restart();
        cache
    }

    fn restart(&mut self) {
        self.points.clear();
        self.generation = self.generation.wrapping_add(1);
        if self.generation == 0 {
            // After 2³² views the marks could repeat: clear them.
            self.slots.fill(CacheSlot::default());
            self.generation = 1;
        }
    }
}

impl Drop for FieldView<'_> {
    fn drop(&mut self) {
        let cache = std::mem::replace(
            self.cache.get_mut(),
            CandidateCache { slots: Vec::new(), points: Vec::new(), generation: 0, max_points: CACHE_POINTS },
        );
        // During thread teardown the slot may be gone already; the table is then just dropped.
        let _ = SPARE_CACHE.try_with(|spare| spare.set(Some(cache)));
    }
}

impl<'a> FieldView<'a> {
    pub fn new(field: &'a LikelihoodField, grid: &'a TiledGrid) -> Self {
        FieldView { field, grid, cache: std::cell::RefCell::new(CandidateCache::fresh()) }
    }

    /// As `LikelihoodField::nearest`, through the remembered candidates.
    #[inline]
    pub fn nearest(&self, x: f64, y: f64) -> (f64, [f64; 2], Option<[f64; 2]>) {
        let lf = self.field;
        if lf.fit_walls {
            return lf.nearest_wall(self.grid, x, y);
        }
        let res = self.grid.resolution;
        let (ix, iy) = (floor_i32(x / res), floor_i32(y / res));
        let k = (((iy as u32 & ((1 << CACHE_Y_BITS) - 1)) << CACHE_X_BITS)
            | (ix as u32 & ((1 << CACHE_X_BITS) - 1))) as usize;
        let mut cache = self.cache.borrow_mut();
        let mut slot = cache.slots[k];
        if slot.generation != cache.generation || slot.cell != (ix, iy) {
            if cache.points.len() >= cache.max_points {
                cache.restart();
            }
            let start = cache.points.len();
            let points = &mut cache.points;
            lf.candidates(self.grid, ix, iy, |h| points.push(h));
            let len = (cache.points.len() - start) as u32;
            slot = CacheSlot { cell: (ix, iy), start: start as u32, len, generation: cache.generation };
            cache.slots[k] = slot;
        }
        let mut best = f64::INFINITY;
        let mut offset = [0.0; 2];
        for h in &cache.points[slot.start as usize..(slot.start + slot.len) as usize] {
            let (dx, dy) = (h[0] - x, h[1] - y);
            if dx * dx + dy * dy < best {
                best = dx * dx + dy * dy;
                offset = [dx, dy];
            }
        }
        (best, offset, None)
    }

    /// As `LikelihoodField::score`.
    pub fn score(&self, sp: [f64; 3], pts: &[[f64; 2]]) -> (f64, usize) {
        self.field.score_with(|x, y| self.nearest(x, y).0, self.grid.resolution, sp, pts)
    }
}

#[derive(Clone, Copy, Debug)]
pub struct MatcherParams {
    /// Initial step of the hill climbing in x and y (m) and in θ (rad); halved `refinements` times.
    pub step_xy: f64,
    pub step_theta: f64,
    pub refinements: u32,
    /// Gauss-Newton iterations on the likelihood field after the hill climbing (0: none).
    pub gauss_newton: u32,
    /// Spacing of the K = 27 poses (3×3×3 grid) around the mode used to fit the Gaussian.
    pub sample_xy: f64,
    pub sample_theta: f64,
    /// Fall back to the odometry proposal when fewer than this share of end points lie near an
    /// obstacle of the map at the mode.
    pub min_matched: f64,
    /// Where the match falls back: draw the pose from the odometry motion model (true, as GMapping
    /// does) or take the odometry's prediction (false; see `ScanMatcherConfig.fallback`).
    pub fallback_draw: bool,
    /// The scan's log-likelihood is the mean over its points times this (see FilterParams).
    pub effective_beams: f64,
    /// Climb to the mode of likelihood × odometry prior (true) or of the likelihood alone.
    pub odometry_prior: bool,
    /// The odometry prior's Student-t degrees of freedom (0: Gaussian; see `PosePrior::dof`).
    pub prior_dof: f64,
    /// Start each particle's climb at a pose drawn from the odometry motion model (GMapping's
    /// way) instead of at the odometry prediction; see `propose`.
    pub climb_from_sample: bool,
    /// The odometry check before each step (see `check_odometry`).
    pub check: OdometryCheck,
}

/// The odometry check's settings (`check_odometry`; in 3D, `filter3d::check_odometry3d`).
#[derive(Clone, Copy, Debug)]
pub struct OdometryCheck {
    /// The wide search's window; None: no check.
    pub window: Option<SearchWindow>,
    /// Search when fewer than this share of end points lie near an obstacle after the local match.
    pub below: f64,
    /// Take the search's pose only where at least this share of end points lie near an obstacle
    /// (the configuration's `search_accept`, `search_below` where unset).
    pub accept: f64,
    /// Take the search's pose only where it is at least this distinct (`correlative::Found`); 0:
    /// any pose that passes `accept`.
    pub distinct: f64,
    /// Search only scans of at least this many end points.
    pub min_points: usize,
}

impl OdometryCheck {
    /// No check: the matcher's other users (the final match, the loop closures' refinement).
    pub const OFF: OdometryCheck = OdometryCheck { window: None, below: 0.0, accept: 0.0, distinct: 0.0, min_points: 0 };
}

/// Hill climbing of `eval` from `start` (robot pose); returns the mode and its value.
pub fn climb<F: Fn([f64; 3]) -> f64>(eval: F, start: [f64; 3], m: &MatcherParams) -> ([f64; 3], f64) {
    let mut pose = start;
    let mut best = eval(pose);
    let (mut dxy, mut dth) = (m.step_xy, m.step_theta);
    for _ in 0..=m.refinements {
        // Moves in opposite pairs: after a move, its opposite leads back to the pose just left,
        // which scored lower; it is not evaluated again (a sixth of the climb's evaluations).
        let mut came_by: Option<usize> = None;
        // Bounded: a level moves the pose by at most 50 steps.
        for _ in 0..50 {
            let moves = [
                [dxy, 0.0, 0.0],
                [-dxy, 0.0, 0.0],
                [0.0, dxy, 0.0],
                [0.0, -dxy, 0.0],
                [0.0, 0.0, dth],
                [0.0, 0.0, -dth],
            ];
            let mut improved = None;
            for (k, mv) in moves.iter().enumerate() {
                if came_by == Some(k ^ 1) {
                    continue;
                }
                let cand = [pose[0] + mv[0], pose[1] + mv[1], wrap(pose[2] + mv[2])];
                let s = eval(cand);
                if s > best + 1e-12 {
                    best = s;
                    improved = Some((k, cand));
                }
            }
            match improved {
                Some((k, c)) => {
                    pose = c;
                    came_by = Some(k);
                }
                None => break,
            }
        }
        dxy *= 0.5;
        dth *= 0.5;
    }
    (pose, best)
}

/// A prior on the pose: mean, variance of x and y (isotropic) and of θ; Gaussian, or Student-t
/// with `dof` degrees of freedom.
#[derive(Clone, Copy, Debug)]
pub struct PosePrior {
    pub mean: [f64; 3],
    pub var_xy: f64,
    pub var_theta: f64,
    /// Degrees of freedom ν of a Student-t prior on the pose (0: a Gaussian). Heavy-tailed: where
    /// the scan places the pose many standard deviations from the wheels' prediction (a wheel
    /// that slips in a turn), the prior gives way instead of pulling the match towards the
    /// wheels; near the prediction (along a corridor the scan cannot fix) it holds as firmly as
    /// a Gaussian, or more: its curvature at the mean is (ν + 3)/ν times the Gaussian's.
    pub dof: f64,
}

impl PosePrior {
    /// Its information matrix (diagonal).
    pub fn information(&self) -> [[f64; 3]; 3] {
        [[1.0 / self.var_xy, 0.0, 0.0], [0.0, 1.0 / self.var_xy, 0.0], [0.0, 0.0, 1.0 / self.var_theta]]
    }

    /// ln p(pose) up to a constant: the Gaussian's −m²/2, or for ν > 0 the 3-dimensional
    /// Student-t's −(ν + 3)/2 · ln(1 + m²/ν), m the Mahalanobis distance (the normalising
    /// terms in the variances included, which differ from particle to particle).
    pub fn log_prob(&self, pose: [f64; 3]) -> f64 {
        let m2 = self.mahalanobis2(pose);
        let kernel = if self.dof > 0.0 { (self.dof + 3.0) * (m2 / self.dof).ln_1p() } else { m2 };
        -0.5 * (kernel + 2.0 * self.var_xy.ln() + self.var_theta.ln())
    }

    /// The weight of the prior's quadratic in Gauss-Newton at `pose`, as iteratively reweighted
    /// least squares gives it: (ν + 3) / (ν + m²) for a Student-t, 1 for a Gaussian.
    pub fn weight(&self, pose: [f64; 3]) -> f64 {
        if self.dof > 0.0 {
            (self.dof + 3.0) / (self.dof + self.mahalanobis2(pose))
        } else {
            1.0
        }
    }

    /// The same prior with `dof` degrees of freedom (0: Gaussian).
    pub fn with_dof(self, dof: f64) -> PosePrior {
        PosePrior { dof, ..self }
    }

    /// The squared Mahalanobis distance of `pose` from the mean.
    pub fn mahalanobis2(&self, pose: [f64; 3]) -> f64 {
        let (dx, dy) = (pose[0] - self.mean[0], pose[1] - self.mean[1]);
        let dt = wrap(pose[2] - self.mean[2]);
        (dx * dx + dy * dy) / self.var_xy + dt * dt / self.var_theta
    }
}

/// The objective of the scan match: gain · (mean log-likelihood of the end points) plus the log
/// prior (none: the likelihood alone).
pub fn objective(
    view: &FieldView,
    geom: &ScanGeometry,
    pts: &[[f64; 2]],
    gain: f64,
    prior: Option<&PosePrior>,
    pose: [f64; 3],
) -> f64 {
    gain * view.score(geom.sensor_pose(pose), pts).0 + prior.map_or(0.0, |p| p.log_prob(pose))
}

/// One sweep over the end points at `pose`: (sum over the points of
/// log(z_hit·N(d; 0, σ) + z_rand/max_range), its gradient g and Gauss-Newton Hessian H in
/// (x, y, θ), unscaled, and the number of points with an obstacle in the window, as
/// `LikelihoodField::score` counts them). Each end point pulls towards the mean end point of its nearest
/// occupied cell, weighted as iteratively reweighted least squares of the log-likelihood
/// (points with no obstacle in the window drop out).
fn linearise(view: &FieldView, geom: &ScanGeometry, pts: &[[f64; 2]], pose: [f64; 3]) -> (f64, [f64; 3], [[f64; 3]; 3], usize) {
    let lf = view.field;
    let norm = lf.z_hit / (lf.sigma * (2.0 * std::f64::consts::PI).sqrt());
    let floor = lf.z_rand / lf.max_range;
    let radius2 = lf.radius(view.grid.resolution).powi(2);
    let sp = geom.sensor_pose(pose);
    let (s, c) = sp[2].sin_cos();
    let mut h = [[0.0; 3]; 3];
    let mut g = [0.0; 3];
    let mut total = 0.0;
    let mut matched = 0;
    for p in pts {
        let qx = sp[0] + c * p[0] - s * p[1];
        let qy = sp[1] + s * p[0] + c * p[1];
        let (d2, off, normal) = view.nearest(qx, qy);
        if !d2.is_finite() {
            total += floor.ln();
            continue;
        }
        matched += 1;
        let g_d = norm * (-0.5 * d2 / (lf.sigma * lf.sigma)).exp();
        let e = if lf.fit_walls { lf.z_hit * lf.hit_density(d2, radius2) } else { g_d };
        total += (e + floor).ln();
        // d log(e + floor) / d(d²) = −g_d / (2σ²(e + floor)), g_d the Gaussian without the shift.
        let w = if e > 0.0 { g_d / (e + floor) / (lf.sigma * lf.sigma) } else { 0.0 };
        // Residual r = q − hit point = −off; dq/d(x, y, θ) = [[1, 0, −(qy − y)], [0, 1, qx − x]].
        let jt = [-(qy - pose[1]), qx - pose[0]];
        // Across a fitted wall one residual, the distance along its normal n; otherwise the
        // two of the offset.
        let (rows, r, n_rows) = match normal {
            Some(n) => ([[n[0], n[1], n[0] * jt[0] + n[1] * jt[1]], [0.0; 3]], [-(n[0] * off[0] + n[1] * off[1]), 0.0], 1),
            None => ([[1.0, 0.0, jt[0]], [0.0, 1.0, jt[1]]], [-off[0], -off[1]], 2),
        };
        for (k, row) in rows.iter().enumerate().take(n_rows) {
            for a in 0..3 {
                g[a] += w * row[a] * r[k];
                for b in 0..3 {
                    h[a][b] += w * row[a] * row[b];
                }
            }
        }
    }
    (total, g, h, matched)
}

/// Refine a pose by Gauss-Newton on the likelihood field (see `linearise`); the points' mean
/// is scaled by `gain`, and the Gaussian `prior` (if any) adds its own pull.
/// A step that lowers the objective is undone and ends the refinement. Returns (pose, its
/// objective, its end points with an obstacle in the window), the count saving callers a sweep.
#[allow(clippy::too_many_arguments)]
pub fn gauss_newton(
    view: &FieldView,
    geom: &ScanGeometry,
    pts: &[[f64; 2]],
    gain: f64,
    prior: Option<&PosePrior>,
    start: [f64; 3],
    iterations: u32,
) -> ([f64; 3], f64, usize) {
    gauss_newton_with(|pose| linearise(view, geom, pts, pose), pts.len(), gain, prior, start, iterations)
}

/// The Gauss-Newton loop of `gauss_newton` on any linearisation: `linearise(pose)` gives (sum of
/// the points' log-likelihoods, their gradient and Gauss-Newton Hessian in (x, y, θ), points
/// with an obstacle in reach) over `n_points` points; the sum's mean is scaled by `gain`.
/// Shared by the 2D matcher and the 3D filter's (filter3d.rs).
pub(crate) fn gauss_newton_with(
    linearise: impl Fn([f64; 3]) -> (f64, [f64; 3], [[f64; 3]; 3], usize),
    n_points: usize,
    gain: f64,
    prior: Option<&PosePrior>,
    start: [f64; 3],
    iterations: u32,
) -> ([f64; 3], f64, usize) {
    let scale = if n_points == 0 { 0.0 } else { gain / n_points as f64 };
    let mut pose = start;
    let mut best = (start, f64::NEG_INFINITY, 0);
    // Each pass scores the pose and linearises there in one sweep over the points; a pass
    // that scores lower than the one before undoes the last step and ends the refinement.
    for _ in 0..=iterations {
        let (total, mut g, mut h, matched) = linearise(pose);
        let mut score = scale * total;
        for a in 0..3 {
            g[a] *= scale;
            for b in 0..3 {
                h[a][b] *= scale;
            }
        }
        if let Some(p) = prior {
            score += p.log_prob(pose);
            let info = p.information();
            let w = p.weight(pose);
            let d = [pose[0] - p.mean[0], pose[1] - p.mean[1], wrap(pose[2] - p.mean[2])];
            for a in 0..3 {
                g[a] += w * info[a][a] * d[a];
                h[a][a] += w * info[a][a];
            }
        }
        if score < best.1 {
            break;
        }
        best = (pose, score, matched);
        if h[0][0] <= 0.0 || h[2][2] <= 0.0 {
            break;
        }
        for (a, row) in h.iter_mut().enumerate() {
            row[a] *= 1.0 + 1e-3; // a touch of Levenberg damping keeps H invertible
        }
        let l = cholesky3(&h);
        let delta = solve_cholesky(&l, &[-g[0], -g[1], -g[2]]);
        if delta[0].abs() + delta[1].abs() < 1e-4 && delta[2].abs() < 1e-4 {
            break;
        }
        pose = [pose[0] + delta[0], pose[1] + delta[1], wrap(pose[2] + delta[2])];
    }
    best
}

/// Re-pose many scans in one finished map, each by Gauss-Newton alone from its own `start`
/// (a pose already within the likelihood field's reach, as the final pass over a run's
/// trajectory has): (pose, share of its end points with an obstacle in the window) per scan.
/// `ranges` holds `beams` values per scan; `angles` either one scan's worth (shared) or one row
/// per scan. The scans are independent, so they run in parallel and the result does not depend
/// on the number of threads. A scan without end points keeps its start, with share 0.
#[allow(clippy::too_many_arguments)]
pub fn match_each(
    lf: &LikelihoodField,
    grid: &TiledGrid,
    sensor: [f64; 3],
    starts: &[[f64; 3]],
    ranges: &[f32],
    angles: &[f64],
    beams: usize,
    stride: usize,
    iterations: u32,
) -> Vec<([f64; 3], f64)> {
    use rayon::prelude::*;
    let shared = angles.len() == beams;
    starts
        .par_iter()
        .enumerate()
        .map(|(i, &start)| {
            let scan_angles = if shared { angles } else { &angles[i * beams..(i + 1) * beams] };
            let geom = ScanGeometry { angles: scan_angles, sensor };
            let pts = endpoints(&geom, &ranges[i * beams..(i + 1) * beams], stride, lf.max_range);
            if pts.is_empty() {
                return (start, 0.0);
            }
            let (pose, _, matched) = gauss_newton(&FieldView::new(lf, grid), &geom, &pts, 1.0, None, start, iterations);
            (pose, matched as f64 / pts.len() as f64)
        })
        .collect()
}

/// Solve L·Lᵀ·x = b for lower-triangular L.
fn solve_cholesky(l: &[[f64; 3]; 3], b: &[f64; 3]) -> [f64; 3] {
    let mut y = [0.0; 3];
    for i in 0..3 {
        let s: f64 = (0..i).map(|k| l[i][k] * y[k]).sum();
        y[i] = (b[i] - s) / l[i][i];
    }
    let mut x = [0.0; 3];
    for i in (0..3).rev() {
        let s: f64 = (i + 1..3).map(|k| l[k][i] * x[k]).sum();
        x[i] = (y[i] - s) / l[i][i];
    }
    x
}

/// The odometry motion model's Gaussian approximation p(x | x', u) around the pose `predicted`
/// by composing the odometry increment: isotropic position error and heading error with the
/// variances of sample_motion_model_odometry.
pub fn motion_prior(motion: &OdometryMotion, prev: [f64; 3], cur: [f64; 3], predicted: [f64; 3]) -> PosePrior {
    let (rot1, trans, rot2) = decompose(prev, cur);
    let [a1, a2, a3, a4] = motion.alpha;
    let rot = rot1.abs() + rot2.abs();
    // Floors keep a standing robot's Gaussian proper (1 cm, 0.5°).
    PosePrior {
        mean: predicted,
        var_xy: a3 * trans * trans + a4 * rot * rot + 1e-4,
        var_theta: a1 * rot * rot + a2 * trans * trans + 7.6e-5,
        dof: 0.0,
    }
}

/// Hill climbing, then Gauss-Newton, from `start` to the mode of the scan's likelihood (times
/// `prior`, if any): (mode, objective there, end points with an obstacle within the window).
#[allow(clippy::too_many_arguments)]
pub fn local_match(
    view: &FieldView,
    m: &MatcherParams,
    geom: &ScanGeometry,
    pts: &[[f64; 2]],
    start: [f64; 3],
    prior: Option<&PosePrior>,
) -> ([f64; 3], f64, usize) {
    let goal = |pose: [f64; 3]| objective(view, geom, pts, m.effective_beams, prior, pose);
    let (mode, _) = climb(goal, start, m);
    let (mode, value, matched) = gauss_newton(view, geom, pts, m.effective_beams, prior, mode, m.gauss_newton);
    (mode, value, matched)
}

/// Check the odometry increment from `odom_prev` to `odom_cur` against the map of a particle at
/// `pose` (the best one): if the scan, where the odometry puts it and matched locally from there,
/// finds too few of its end points near the map's obstacles (fewer than `search_below`), search the wide
/// window around that prediction (see correlative.rs) and match locally from the best pose
/// found. If that explains clearly more of the scan (a tenth of its end points more, and a
/// higher likelihood), return the odometry pose that would have predicted it: the increment
/// the wheels should have reported. Why: an odometry glitch is common to every particle, so one
/// search on the best map corrects the prediction of them all. Fails when the search's raster
/// cannot be made (correlative.rs).
#[allow(clippy::too_many_arguments)]
pub fn check_odometry(
    lf: &LikelihoodField,
    m: &MatcherParams,
    grid: &TiledGrid,
    geom: &ScanGeometry,
    pts: &[[f64; 2]],
    pose: [f64; 3],
    odom_prev: [f64; 3],
    odom_cur: [f64; 3],
) -> Result<Option<[f64; 3]>, GridError> {
    let c = &m.check;
    let Some(window) = c.window.as_ref() else { return Ok(None) };
    // On a handful of end points every share the check reads is coarse (one point is 1/n of it),
    // and somewhere in a metre's window a few points fit walls by chance: a simulated office
    // scan of one reading in a bare corridor passed `search_distinct` and jumped the run a metre.
    if pts.is_empty() || pts.len() < c.min_points {
        return Ok(None);
    }
    let predicted = compose(pose, relative(odom_prev, odom_cur));
    let n = pts.len() as f64;
    let enough = |matched: usize| matched as f64 >= c.below * n;
    // Cheap first (this runs before the particles, on one core): a prediction that already puts
    // the scan on the map needs no search.
    let view = FieldView::new(lf, grid);
    if enough(view.score(geom.sensor_pose(predicted), pts).1) {
        return Ok(None);
    }
    let (_, local_value, local_matched) = local_match(&view, m, geom, pts, predicted, None);
    if enough(local_matched) {
        return Ok(None);
    }
    let floor = lf.z_rand / lf.max_range;
    let searched = correlative_search(grid, lf.occupied_threshold, floor, geom, pts, predicted, window)?;
    // Where another place a few decimetres off explains the scan as well (along a corridor, the
    // direction the scan cannot see), the best pose is the search's tie-break, not a correction.
    if searched.distinct < c.distinct {
        return Ok(None);
    }
    let (found, value, matched) = local_match(&view, m, geom, pts, searched.pose, None);
    // The jump must put the scan on the map (`search_accept` of it, as a good prediction does), not
    // merely better than the local match: where people walk beside the robot or doors stand open
    // (the Freiburg hospital log), no pose explains the scan, and a pose that explains a little
    // more of it is as likely wrong, a metre and 20 degrees away.
    let better = matched as f64 >= c.accept * n && matched as f64 >= local_matched as f64 + 0.1 * n && value > local_value;
    Ok(better.then(|| compose(odom_prev, relative(pose, found))))
}

pub struct Proposal {
    pub pose: [f64; 3],
    /// log η, the log of the proposal's normaliser: the particle's log weight increment.
    pub log_normaliser: f64,
    /// False when the match failed and the caller should use the odometry proposal.
    pub matched: bool,
}

/// Draw a particle's new pose from the Gaussian fitted around the scan-match mode.
#[allow(clippy::too_many_arguments)]
pub fn propose<R: rand::Rng>(
    lf: &LikelihoodField,
    m: &MatcherParams,
    motion: &OdometryMotion,
    grid: &TiledGrid,
    geom: &ScanGeometry,
    pts: &[[f64; 2]],
    prev_pose: [f64; 3],
    odom_prev: [f64; 3],
    odom_cur: [f64; 3],
    rng: &mut R,
) -> Proposal {
    let predicted = compose(prev_pose, relative(odom_prev, odom_cur));
    // With `odometry_prior`, climb to the mode of the whole target p(z | m, x)·p(x | x', u), so
    // that where the scan cannot tell (along a bare corridor) the odometry decides; without it,
    // to the mode of the likelihood alone, as GMapping does (better where odometry is poor).
    let prior = motion_prior(motion, odom_prev, odom_cur, predicted).with_dof(m.prior_dof);
    let view = FieldView::new(lf, grid);
    let target = |pose: [f64; 3]| objective(&view, geom, pts, m.effective_beams, Some(&prior), pose);
    let climb_prior = m.odometry_prior.then_some(&prior);
    let enough = |matched: usize| matched as f64 >= m.min_matched * pts.len() as f64;
    // A start that the climb cannot bring back onto the map is no hypothesis: climb again from
    // the prediction.
    let from_sample = m
        .climb_from_sample
        .then(|| local_match(&view, m, geom, pts, motion.sample(prev_pose, odom_prev, odom_cur, rng), climb_prior))
        .filter(|found| enough(found.2));
    let (mode, _, matched) = from_sample.unwrap_or_else(|| local_match(&view, m, geom, pts, predicted, climb_prior));
    if pts.is_empty() || !enough(matched) {
        return Proposal { pose: predicted, log_normaliser: 0.0, matched: false };
    }
    // Target at the 27 poses around the mode; offsets kept relative to the mode. Each pose
    // searches its end points' nearest obstacles anew: holding the mode's (fixed
    // correspondences) saves an eighth of the filter's time on Intel but narrows the
    // Gaussian where two obstacles are about equally near, and on the simulated office the
    // share of map cells within 5 cm of a wall fell from about 50 % to under 30 %.
    let (pose, log_normaliser) = draw_around_mode(target, mode, m.sample_xy, m.sample_theta, rng);
    Proposal { pose, log_normaliser, matched: true }
}

/// The proposal's Gaussian (Grisetti, Stachniss & Burgard 2007): the target evaluated at the
/// 27 poses around `mode` (steps `sample_xy`, `sample_theta`; offsets kept relative to the
/// mode), their weighted mean and covariance, one draw from it. Returns (the drawn pose, the log
/// of the target's sum over the 27 poses: the particle's weight). Shared by the 2D and the 3D
/// filter's scan-matching proposals.
pub(crate) fn draw_around_mode<R: rand::Rng>(
    target: impl Fn([f64; 3]) -> f64,
    mode: [f64; 3],
    sample_xy: f64,
    sample_theta: f64,
    rng: &mut R,
) -> ([f64; 3], f64) {
    let mut offsets = Vec::with_capacity(27);
    let mut logs = Vec::with_capacity(27);
    for i in -1..=1 {
        for j in -1..=1 {
            for k in -1..=1 {
                let off = [i as f64 * sample_xy, j as f64 * sample_xy, k as f64 * sample_theta];
                logs.push(target([mode[0] + off[0], mode[1] + off[1], wrap(mode[2] + off[2])]));
                offsets.push(off);
            }
        }
    }
    let max = logs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let w: Vec<f64> = logs.iter().map(|l| (l - max).exp()).collect();
    let sum: f64 = w.iter().sum();
    let mut mean = [0.0; 3];
    for (wk, o) in w.iter().zip(&offsets) {
        for a in 0..3 {
            mean[a] += wk / sum * o[a];
        }
    }
    let mut cov = [[0.0; 3]; 3];
    for (wk, o) in w.iter().zip(&offsets) {
        let d = [o[0] - mean[0], o[1] - mean[1], o[2] - mean[2]];
        for a in 0..3 {
            for b in 0..3 {
                cov[a][b] += wk / sum * d[a] * d[b];
            }
        }
    }
    // Keep the Gaussian proper even when one pose takes all the weight.
    let floor = [1e-2 * sample_xy * sample_xy, 1e-2 * sample_xy * sample_xy, 1e-2 * sample_theta * sample_theta];
    for a in 0..3 {
        cov[a][a] += floor[a];
    }
    let l = cholesky3(&cov);
    let n: [f64; 3] = [rng.sample(StandardNormal), rng.sample(StandardNormal), rng.sample(StandardNormal)];
    let mut draw = mean;
    for a in 0..3 {
        for b in 0..=a {
            draw[a] += l[a][b] * n[b];
        }
    }
    ([mode[0] + draw[0], mode[1] + draw[1], wrap(mode[2] + draw[2])], max + sum.ln())
}

/// Lower-triangular L with L·Lᵀ = a for a symmetric positive definite 3×3 matrix.
pub(crate) fn cholesky3(a: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut l = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..=i {
            let s: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
            if i == j {
                l[i][j] = (a[i][i] - s).max(1e-18).sqrt();
            } else {
                l[i][j] = (a[i][j] - s) / l[j][j];
            }
        }
    }
    l
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::LogOddsModel;
    use crate::sensor_model::integrate_scan;

    #[test]
    fn the_table_stays_finite_for_a_vanishing_floor() {
        // z_rand = 1e-300 made peak / (1e-9·floor) overflow to inf: every value became NaN.
        for z_rand in [0.1, 1e-12, 1e-300, f64::MIN_POSITIVE, 5e-324] {
            let t = LogLikelihoodTable::new(0.05, 0.9, z_rand, 15.0);
            let exact = |q: f64| (0.9 / (0.05 * (2.0 * std::f64::consts::PI).sqrt()) * (-q).exp() + z_rand / 15.0).ln();
            for q in [0.0, 0.5, 3.0, 40.0] {
                let v = t.at(q);
                assert!(v.is_finite(), "z_rand {z_rand:e}, q {q}: {v}");
                if q < t.q_max && exact(q).is_finite() {
                    assert!((v - exact(q)).abs() < 1e-4, "z_rand {z_rand:e}, q {q}: {v} vs {}", exact(q));
                }
            }
            assert!(t.at(f64::INFINITY).is_finite());
        }
    }

    fn room() -> (TiledGrid, Vec<f64>, Vec<f32>) {
        // A 6 m × 4 m box seen from (2, 1.5): ranges computed exactly.
        let angles: Vec<f64> = (0..360).map(|k| (k as f64).to_radians()).collect();
        let (x0, y0) = (2.0, 1.5);
        let ranges: Vec<f32> = angles
            .iter()
            .map(|a| {
                let (s, c) = a.sin_cos();
                let tx = if c > 1e-12 { (6.0 - x0) / c } else if c < -1e-12 { -x0 / c } else { f64::INFINITY };
                let ty = if s > 1e-12 { (4.0 - y0) / s } else if s < -1e-12 { -y0 / s } else { f64::INFINITY };
                tx.min(ty) as f32
            })
            .collect();
        let lm = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };
        let mut g = TiledGrid::new(0.05);
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        integrate_scan(&mut g, &lm, &geom, [x0, y0, 0.0], &ranges, 20.0, false, false).unwrap();
        (g, angles, ranges)
    }

    fn searching_matcher() -> MatcherParams {
        MatcherParams {
            step_xy: 0.05, step_theta: 0.035, refinements: 3, gauss_newton: 10, sample_xy: 0.005, sample_theta: 0.002,
            min_matched: 0.5, effective_beams: 9.0, odometry_prior: false, prior_dof: 0.0, climb_from_sample: false, fallback_draw: true,
            check: OdometryCheck {
                window: Some(SearchWindow { half_xy: 1.0, half_theta: 15f64.to_radians(), step_xy: 0.1, step_theta: 1f64.to_radians() }),
                below: 0.8,
                accept: 0.8,
                distinct: 0.0,
                min_points: 0,
            },
        }
    }

    /// `searching_matcher` with the check's `distinct` and `min_points` gates.
    fn gated_matcher(distinct: f64, min_points: usize) -> MatcherParams {
        let mut m = searching_matcher();
        m.check.distinct = distinct;
        m.check.min_points = min_points;
        m
    }

    /// `check_odometry` in the room, the robot at (2, 1.5, 0) seeing `ranges`, after wheels
    /// that report (0.7 m, 0.3 m, 0.2 rad) it never drove.
    fn check_after_glitch(ranges: &[f32]) -> Option<[f64; 3]> {
        check_after_glitch_with(ranges, &searching_matcher())
    }

    fn check_after_glitch_with(ranges: &[f32], m: &MatcherParams) -> Option<[f64; 3]> {
        let (g, angles, _) = room();
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let lf = LikelihoodField::new(0.05, 0.9, 0.1, 20.0, 3, 0.0, false);
        let pts = endpoints(&geom, ranges, 1, 20.0);
        check_odometry(&lf, m, &g, &geom, &pts, [2.0, 1.5, 0.0], [0.0; 3], [0.7, 0.3, 0.2]).unwrap()
    }

    #[test]
    fn the_wide_search_takes_a_distinct_pose_and_only_that() {
        // The room's glitch stands out (no other place within the window explains the scan:
        // `correlative::Found::distinct` 0.37 here), so `search_distinct` 0.2, as
        // tof-scanmatch sets it, still undoes it; asked for more than the room offers, the
        // odometry stands.
        let (_, _, ranges) = room();
        let m = gated_matcher(0.2, 0);
        let odom = check_after_glitch_with(&ranges, &m).expect("the glitch is found");
        assert!(odom[0].abs() < 0.03 && odom[1].abs() < 0.03 && odom[2].abs() < 0.01, "{odom:?}");
        let m = gated_matcher(0.6, 0);
        assert!(check_after_glitch_with(&ranges, &m).is_none());
    }

    #[test]
    fn a_student_t_prior_is_the_gaussian_for_many_degrees_of_freedom_and_its_own_formula_otherwise() {
        let g = PosePrior { mean: [1.0, -2.0, 0.3], var_xy: 0.04, var_theta: 0.01, dof: 0.0 };
        let pose = [1.3, -2.1, 0.2]; // m² = (0.09 + 0.01) / 0.04 + 0.01 / 0.01 = 3.5
        let norm = -0.5 * (2.0 * 0.04f64.ln() + 0.01f64.ln());
        assert!((g.mahalanobis2(pose) - 3.5).abs() < 1e-9);
        assert!((g.log_prob(pose) - (norm - 0.5 * 3.5)).abs() < 1e-9);
        let t = g.with_dof(3.0);
        assert!((t.log_prob(pose) - (norm - 0.5 * 6.0 * (1.0 + 3.5 / 3.0f64).ln())).abs() < 1e-9);
        assert!((t.weight(pose) - 6.0 / 6.5).abs() < 1e-12);
        let wide = g.with_dof(1e9);
        assert!((wide.log_prob(pose) - g.log_prob(pose)).abs() < 1e-6);
        assert!((wide.weight(pose) - 1.0).abs() < 1e-6 && g.weight(pose) == 1.0);
    }

    #[test]
    fn a_student_t_prior_gives_way_where_the_scan_puts_the_pose_far_from_the_wheels() {
        // A scan that fixes x at 0 with information k, and wheels that say x = 1 with σ 0.1 m
        // (10 σ away) and the same information: a Gaussian prior pulls the match halfway, to
        // (k·0 + p·1) / (k + p) = 0.5; the Student-t's pull is its weight (ν + 3) / (ν + m²)
        // times that, so its optimum solves x = w(x)·p / (k + w(x)·p), near 0.06.
        let k = 100.0;
        let linearise = |pose: [f64; 3]| {
            let d = [pose[0], pose[1], pose[2]];
            let cost = 0.5 * k * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            (-cost, [k * d[0], k * d[1], k * d[2]], [[k, 0.0, 0.0], [0.0, k, 0.0], [0.0, 0.0, k]], 1)
        };
        let gaussian = PosePrior { mean: [1.0, 0.0, 0.0], var_xy: 0.01, var_theta: 0.01, dof: 0.0 };
        let (x, _, _) = gauss_newton_with(linearise, 1, 1.0, Some(&gaussian), [0.0; 3], 50);
        assert!((x[0] - 0.5).abs() < 2e-3, "{x:?}");
        let t = gaussian.with_dof(3.0);
        let (x, _, _) = gauss_newton_with(linearise, 1, 1.0, Some(&t), [0.0; 3], 50);
        let p = 1.0 / t.var_xy;
        let w = t.weight(x);
        assert!((x[0] - w * p / (k + w * p)).abs() < 2e-3, "{x:?}, fixed point {}", w * p / (k + w * p));
        assert!(x[0] > 0.03 && x[0] < 0.1, "{x:?}");
        // Near the wheels' prediction it holds as firmly as a Gaussian, and more: at the mean its
        // curvature is (ν + 3) / ν times the Gaussian's.
        let near = PosePrior { mean: [0.05, 0.0, 0.0], ..t };
        let (xt, _, _) = gauss_newton_with(linearise, 1, 1.0, Some(&near), [0.0; 3], 50);
        let (xg, _, _) = gauss_newton_with(linearise, 1, 1.0, Some(&PosePrior { dof: 0.0, ..near }), [0.0; 3], 50);
        assert!(xt[0] > xg[0] && xg[0] > 0.02, "{xt:?} {xg:?}");
    }

    #[test]
    fn the_wide_search_leaves_a_scan_of_a_few_end_points_alone() {
        // The map holds one post, 1.2 m ahead. The robot stands where the odometry says, and its
        // scan holds one reading, 0.5 m ahead, of something the map does not hold yet (the
        // office's sparse scans in a bare corridor: the next stretch of wall). Moved 0.7 m
        // forward, the end point falls on the post, and every other pose of the window that puts
        // it there lies on an arc of 0.5 m radius over ±15°, within the peak's shoulder: the
        // search's pose "stands out" (above 0.2) and, ungated, the check jumps the robot 0.7 m.
        // It is one point's coincidence, which `search_min_points` refuses to judge.
        let post: [[f64; 4]; 1] = [[1.2, -0.05, 1.2, 0.05]];
        let angles: Vec<f64> = (0..360).map(|k| (k as f64).to_radians()).collect();
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let lm = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };
        let mut g = TiledGrid::new(0.05);
        let seen: Vec<f32> = crate::test_support::cast_walls(&post, [0.0; 3], &angles).iter().map(|r| r.min(8.0)).collect();
        integrate_scan(&mut g, &lm, &geom, [0.0; 3], &seen, 7.99, false, false).unwrap();
        let mut ranges = vec![8.0f32; 360];
        ranges[0] = 0.5;
        let pts = endpoints(&geom, &ranges, 1, 7.99);
        let lf = LikelihoodField::new(0.05, 0.9, 0.1, 7.99, 3, 0.0, false);
        let check = |min_points: usize| {
            let m = gated_matcher(0.2, min_points);
            check_odometry(&lf, &m, &g, &geom, &pts, [0.0; 3], [0.0; 3], [0.0; 3]).unwrap()
        };
        let jumped = check(0).expect("ungated, the one point's coincidence is taken");
        assert!((jumped[0] - 0.7).abs() < 0.1 && jumped[1].abs() < 0.1, "{jumped:?}");
        assert!(check(2).is_none());
        // The room's glitch, seen with every beam, is still found with the gate as shipped.
        let (_, _, room_ranges) = room();
        let m = gated_matcher(0.2, 20);
        assert!(check_after_glitch_with(&room_ranges, &m).is_some());
    }

    #[test]
    fn the_wide_search_undoes_an_odometry_glitch() {
        // The wheels report 0.76 m and 11 degrees that the robot never drove, more than the hill
        // climbing undoes (it stops at 2.27 m, a third of the scan off the map); the scan, taken
        // where the robot stands, puts the increment back near zero.
        let (_, _, ranges) = room();
        let odom = check_after_glitch(&ranges).expect("the glitch is found");
        assert!(odom[0].abs() < 0.03 && odom[1].abs() < 0.03 && odom[2].abs() < 0.01, "{odom:?}");
    }

    #[test]
    fn the_wide_search_keeps_the_odometry_where_no_pose_explains_the_scan() {
        // The same glitch, but 30 % of the beams end on something the map does not hold (people
        // beside the robot, 0.5 m away). The true pose explains only 70 % of the scan, less than
        // `search_below`: a jump is then as likely wrong as right, and the odometry stands.
        let (_, _, mut ranges) = room();
        for (k, r) in ranges.iter_mut().enumerate() {
            if k % 10 < 3 {
                *r = 0.5;
            }
        }
        let odom = check_after_glitch(&ranges);
        assert!(odom.is_none(), "{odom:?}");
    }

    #[test]
    fn climbing_recovers_a_displaced_pose() {
        let (g, angles, ranges) = room();
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let lf = LikelihoodField::new(0.05, 0.9, 0.1, 20.0, 3, 0.0, false);
        let m = MatcherParams { step_xy: 0.05, step_theta: 0.02, refinements: 5, gauss_newton: 0, sample_xy: 0.02, sample_theta: 0.005, min_matched: 0.5, effective_beams: 10.0, odometry_prior: false, prior_dof: 0.0, climb_from_sample: false, fallback_draw: true, check: OdometryCheck::OFF };
        let pts = endpoints(&geom, &ranges, 1, 20.0);
        let view = FieldView::new(&lf, &g);
        let (pose, _) = climb(|p| objective(&view, &geom, &pts, 1.0, None, p), [2.08, 1.43, 0.03], &m);
        assert!((pose[0] - 2.0).abs() < 0.02 && (pose[1] - 1.5).abs() < 0.02, "{pose:?}");
        assert!(pose[2].abs() < 0.01, "{pose:?}");
    }

    #[test]
    fn gauss_newton_recovers_a_displaced_pose() {
        let (g, angles, ranges) = room();
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let lf = LikelihoodField::new(0.05, 0.9, 0.1, 20.0, 3, 0.0, false);
        let pts = endpoints(&geom, &ranges, 1, 20.0);
        let (pose, _, _) = gauss_newton(&FieldView::new(&lf, &g), &geom, &pts, 1.0, None, [2.06, 1.46, 0.02], 20);
        assert!((pose[0] - 2.0).abs() < 0.02 && (pose[1] - 1.5).abs() < 0.02, "{pose:?}");
        assert!(pose[2].abs() < 0.01, "{pose:?}");
    }

    #[test]
    fn fitted_walls_recover_a_displaced_pose() {
        let (g, angles, ranges) = room();
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let lf = LikelihoodField::new(0.02, 0.9, 0.1, 20.0, 3, 0.0, true);
        let m = MatcherParams { step_xy: 0.05, step_theta: 0.02, refinements: 5, gauss_newton: 10, sample_xy: 0.02, sample_theta: 0.005, min_matched: 0.5, effective_beams: 10.0, odometry_prior: false, prior_dof: 0.0, climb_from_sample: false, fallback_draw: true, check: OdometryCheck::OFF };
        let pts = endpoints(&geom, &ranges, 1, 20.0);
        let view = FieldView::new(&lf, &g);
        let (mode, _) = climb(|p| objective(&view, &geom, &pts, 1.0, None, p), [2.04, 1.46, 0.02], &m);
        let (pose, _, _) = gauss_newton(&view, &geom, &pts, 1.0, None, mode, m.gauss_newton);
        assert!((pose[0] - 2.0).abs() < 0.01 && (pose[1] - 1.5).abs() < 0.01, "{pose:?}");
        assert!(pose[2].abs() < 0.003, "{pose:?}");
        // Every end point of the true pose lies on a fitted wall: continuous score, no step.
        let (_, matched) = lf.score(&g, geom.sensor_pose([2.0, 1.5, 0.0]), &pts);
        assert_eq!(matched, pts.len());
    }

    #[test]
    fn the_view_finds_what_the_field_finds() {
        // Every answer of the remembering view equals the field's own search, bit for bit: points
        // scattered over and around the room, each looked up twice (the second time from the
        // view's table), points 128 cells apart (the same slot of the table), and a table so
        // small that it starts afresh many times; windows below and above half a tile.
        use rand::SeedableRng;
        let (g, _, _) = room();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut pts: Vec<[f64; 2]> = (0..4000).map(|_| [rng.random_range(-0.5..6.5), rng.random_range(-0.5..4.5)]).collect();
        let shifted: Vec<[f64; 2]> = pts.iter().take(500).map(|p| [p[0] + 128.0 * 0.05, p[1]]).collect();
        pts.extend(shifted);
        for &(window, max_points) in &[(3, CACHE_POINTS), (3, 200), (9, CACHE_POINTS), (9, 500)] {
            let lf = LikelihoodField::new(0.05, 0.9, 0.1, 20.0, window, 0.0, false);
            let view = FieldView::new(&lf, &g);
            view.cache.borrow_mut().max_points = max_points;
            let mut found = 0;
            for round in 0..2 {
                for p in &pts {
                    let want = lf.nearest(&g, p[0], p[1]);
                    let got = view.nearest(p[0], p[1]);
                    assert_eq!(got.0.to_bits(), want.0.to_bits(), "window {window}, round {round}, {p:?}");
                    assert_eq!([got.1[0].to_bits(), got.1[1].to_bits()], [want.1[0].to_bits(), want.1[1].to_bits()]);
                    found += want.0.is_finite() as usize;
                }
            }
            // The test means something: most points near the walls find one, some find none.
            assert!(found > pts.len() / 4 && found < 2 * pts.len(), "window {window}: {found}");
        }
    }

    #[test]
    fn points_beyond_the_grids_reach_find_no_obstacle() {
        // Indices of points this far out saturate; the neighbourhood's tile arithmetic must not
        // see them (it would index out of bounds). No obstacle is near them.
        let (g, _, _) = room();
        let lf = LikelihoodField::new(0.05, 0.9, 0.1, 20.0, 3, 0.0, false);
        let view = FieldView::new(&lf, &g);
        for &(x, y) in &[(1e12, 1.0), (-1e12, 1.0), (1.0, 1e15), (1.0, -1e300), (6e7, 0.0)] {
            assert!(lf.nearest(&g, x, y).0.is_infinite(), "({x}, {y})");
            assert!(view.nearest(x, y).0.is_infinite(), "({x}, {y})");
        }
    }

    #[test]
    fn tabulated_log_likelihood_matches_the_exact_one() {
        for &(sigma, max_range) in &[(0.05, 15.0), (0.02, 7.0), (0.3, 80.0)] {
            let lf = LikelihoodField::new(sigma, 0.9, 0.1, max_range, 3, 0.0, false);
            let norm = 0.9 / (sigma * (2.0 * std::f64::consts::PI).sqrt());
            let exact = |d2: f64| (norm * (-0.5 * d2 / (sigma * sigma)).exp() + 0.1 / max_range).ln();
            for k in 0..20_000 {
                let d2 = (k as f64 * 1e-4 * sigma).powi(2) * 50.0;
                let err = (lf.point_log_likelihood(d2, 0.0) - exact(d2)).abs();
                assert!(err < 1e-5, "sigma {sigma}: d2 {d2}: error {err}");
            }
            assert_eq!(lf.point_log_likelihood(f64::INFINITY, 0.0), (0.1 / max_range as f64).ln());
        }
    }

    #[test]
    fn cholesky_reproduces_the_matrix() {
        let a = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        let l = cholesky3(&a);
        for i in 0..3 {
            for j in 0..3 {
                let v: f64 = (0..3).map(|k| l[i][k] * l[j][k]).sum();
                assert!((v - a[i][j]).abs() < 1e-12);
            }
        }
    }
}
