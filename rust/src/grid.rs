//! Tiled log-odds occupancy grid with copy-on-write tiles (paper eq. 8).
//!
//! The grid is unbounded: cells are addressed by signed integer indices (ix, iy) with cell
//! (ix, iy) covering [ix·res, (ix+1)·res) × [iy·res, (iy+1)·res) in the world frame. Cells are
//! grouped in square tiles of TILE×TILE; a tile is held through an `Arc`, so particles that were
//! copied from one another by resampling share every tile that neither has changed since. A
//! write goes through `Arc::make_mut`, which copies the tile first if another particle holds it.
//! Unknown (never observed) cells hold NaN.
//!
//! Beside its log-odds, a cell keeps the running mean of the beam end points that fell into it
//! (as a sub-cell offset, 1/256 of a cell per step). The scan matcher measures distances to that
//! point rather than to the cell centre: walls that run along cell boundaries would otherwise
//! pull every match by up to half a cell.

use std::fmt;
use std::sync::Arc;

pub const TILE_SHIFT: i32 = 4;
pub const TILE: i32 = 1 << TILE_SHIFT;
const TILE_CELLS: usize = (TILE * TILE) as usize;
/// Cells are addressed by i32 indices; a grid reaches |index| < 2^30 (53 000 km at 5 cm), so
/// that tile indices, window margins and window sizes never overflow.
pub const MAX_CELL_INDEX: f64 = (1u64 << 30) as f64;

/// Why a grid could not be grown or copied. The filter's bindings turn these into Python
/// exceptions (ValueError, MemoryError): nothing a run's data or settings do may panic or abort.
#[derive(Clone, Debug, PartialEq)]
pub enum GridError {
    /// A point beyond the cells a grid addresses (`MAX_CELL_INDEX`): a pose or a reading very
    /// far out, a resolution very fine, or a coordinate that is not a number.
    OutOfReach { x: f64, y: f64, resolution: f64 },
    /// An allocation that failed: what it was for and how many bytes it asked for.
    NoMemory { what: &'static str, bytes: u128 },
}

impl fmt::Display for GridError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            GridError::OutOfReach { x, y, resolution } => write!(
                f,
                "the point ({x}, {y}) m lies beyond the {MAX_CELL_INDEX} cells a grid of resolution {resolution} m reaches"
            ),
            GridError::NoMemory { what, bytes } => {
                write!(f, "cannot allocate {:.3} GB for {what}", *bytes as f64 / 1e9)
            }
        }
    }
}

impl std::error::Error for GridError {}

/// An empty Vec with room for `n` items of type T, or GridError::NoMemory (never an abort).
pub(crate) fn try_vec<T>(n: usize, what: &'static str) -> Result<Vec<T>, GridError> {
    let mut v = Vec::new();
    v.try_reserve_exact(n)
        .map_err(|_| GridError::NoMemory { what, bytes: n as u128 * std::mem::size_of::<T>() as u128 })?;
    Ok(v)
}

#[derive(Clone)]
pub struct Tile {
    cells: [f32; TILE_CELLS],
    /// Mean end-point offset inside the cell, (x, y) in 1/256 of a cell, and the number of end
    /// points averaged so far (saturating: the mean then follows the latest 255 with equal weight).
    hit_offset: [[u8; 2]; TILE_CELLS],
    hits: [u8; TILE_CELLS],
}

impl Tile {
    fn unknown() -> Self {
        Tile { cells: [f32::NAN; TILE_CELLS], hit_offset: [[128, 128]; TILE_CELLS], hits: [0; TILE_CELLS] }
    }

    /// See `TiledGrid::occupied_hit`; (ix, iy) must lie in this tile.
    #[inline]
    fn occupied_hit(&self, ix: i32, iy: i32, threshold: f32, res: f64) -> Option<[f64; 2]> {
        let k = TiledGrid::cell_offset(ix, iy);
        // NaN (unknown) compares false, so unknown cells are never occupied.
        if !(self.cells[k] > threshold) {
            return None;
        }
        let off = self.hit_offset[k];
        Some([(ix as f64 + (off[0] as f64 + 0.5) / 256.0) * res, (iy as f64 + (off[1] as f64 + 0.5) / 256.0) * res])
    }
}

/// Log-odds increments and limits of the inverse sensor model.
#[derive(Clone, Copy, Debug)]
pub struct LogOddsModel {
    pub l_occ: f32,
    pub l_free: f32,
    pub l_min: f32,
    pub l_max: f32,
}

/// The cells around one cell of a grid; see `TiledGrid::neighbourhood`.
pub struct Neighbourhood<'a> {
    tiles: [Option<&'a Tile>; 4],
    tx0: i32,
    ty0: i32,
    resolution: f64,
}

impl Neighbourhood<'_> {
    /// As `TiledGrid::occupied_hit`, for a cell within the neighbourhood's reach.
    #[inline]
    pub fn occupied_hit(&self, ix: i32, iy: i32, threshold: f32) -> Option<[f64; 2]> {
        let t = (((iy >> TILE_SHIFT) - self.ty0) * 2 + ((ix >> TILE_SHIFT) - self.tx0)) as usize;
        self.tiles[t]?.occupied_hit(ix, iy, threshold, self.resolution)
    }
}

#[derive(Clone)]
pub struct TiledGrid {
    pub resolution: f64,
    // Tile-index window covered by `tiles`: tiles (tx0..tx0+ntx, ty0..ty0+nty), row-major in y.
    tx0: i32,
    ty0: i32,
    ntx: i32,
    nty: i32,
    tiles: Vec<Option<Arc<Tile>>>,
}

impl TiledGrid {
    pub fn new(resolution: f64) -> Self {
        TiledGrid { resolution, tx0: 0, ty0: 0, ntx: 0, nty: 0, tiles: Vec::new() }
    }

    #[inline]
    fn tile_slot(&self, ix: i32, iy: i32) -> Option<usize> {
        let tx = (ix >> TILE_SHIFT) - self.tx0;
        let ty = (iy >> TILE_SHIFT) - self.ty0;
        if tx < 0 || ty < 0 || tx >= self.ntx || ty >= self.nty {
            None
        } else {
            Some((ty * self.ntx + tx) as usize)
        }
    }

    #[inline]
    fn cell_offset(ix: i32, iy: i32) -> usize {
        (((iy & (TILE - 1)) << TILE_SHIFT) | (ix & (TILE - 1))) as usize
    }

    /// Log-odds of a cell; NaN where unknown (never observed, or outside the grid).
    #[inline]
    pub fn get(&self, ix: i32, iy: i32) -> f32 {
        match self.tile_slot(ix, iy).and_then(|s| self.tiles[s].as_ref()) {
            Some(tile) => tile.cells[Self::cell_offset(ix, iy)],
            None => f32::NAN,
        }
    }

    /// Add `delta` to a cell's log-odds and clamp. The cell must lie inside the window made by
    /// `ensure_covers`.
    #[inline]
    pub fn add(&mut self, ix: i32, iy: i32, delta: f32, model: &LogOddsModel) {
        let slot = self.tile_slot(ix, iy).expect("cell outside the grid window");
        let tile = self.tiles[slot].get_or_insert_with(|| Arc::new(Tile::unknown()));
        let cell = &mut Arc::make_mut(tile).cells[Self::cell_offset(ix, iy)];
        let prior = if cell.is_nan() { 0.0 } else { *cell };
        *cell = (prior + delta).clamp(model.l_min, model.l_max);
    }

    /// `add` for a sequence of (ix, iy, delta), in order: one copy-on-write check per run of
    /// cells in the same tile. Why: `Arc::make_mut`'s uniqueness check is an atomic
    /// compare-and-swap, and done for every cell it was a third of the map update's time
    /// (Intel), while a beam crosses a tile in runs of up to 31 cells.
    pub fn add_cells(&mut self, cells: &[(i32, i32, f32)], model: &LogOddsModel) {
        let (tx0, ty0, ntx, nty) = (self.tx0, self.ty0, self.ntx, self.nty);
        let slot_of = |ix: i32, iy: i32| {
            let (tx, ty) = ((ix >> TILE_SHIFT) - tx0, (iy >> TILE_SHIFT) - ty0);
            assert!(tx >= 0 && ty >= 0 && tx < ntx && ty < nty, "cell outside the grid window");
            (ty * ntx + tx) as usize
        };
        let mut k = 0;
        while k < cells.len() {
            let slot = slot_of(cells[k].0, cells[k].1);
            let tile = Arc::make_mut(self.tiles[slot].get_or_insert_with(|| Arc::new(Tile::unknown())));
            while k < cells.len() && slot_of(cells[k].0, cells[k].1) == slot {
                let (ix, iy, delta) = cells[k];
                let cell = &mut tile.cells[Self::cell_offset(ix, iy)];
                let prior = if cell.is_nan() { 0.0 } else { *cell };
                *cell = (prior + delta).clamp(model.l_min, model.l_max);
                k += 1;
            }
        }
    }

    /// Record a beam end point at world (x, y) in its cell's running mean. The cell must lie
    /// inside the window made by `ensure_covers`.
    #[inline]
    pub fn add_hit(&mut self, x: f64, y: f64) {
        let (ux, uy) = (x / self.resolution, y / self.resolution);
        let (ix, iy) = (ux.floor() as i32, uy.floor() as i32);
        let slot = self.tile_slot(ix, iy).expect("cell outside the grid window");
        let tile = Arc::make_mut(self.tiles[slot].get_or_insert_with(|| Arc::new(Tile::unknown())));
        let k = Self::cell_offset(ix, iy);
        let n = tile.hits[k] as f64;
        for (a, u) in [ux, uy].into_iter().enumerate() {
            let new = (u - u.floor()) * 256.0;
            let old = tile.hit_offset[k][a] as f64 + 0.5;
            tile.hit_offset[k][a] = ((old * n + new) / (n + 1.0)).clamp(0.0, 255.0) as u8;
        }
        tile.hits[k] = tile.hits[k].saturating_add(1);
    }

    /// The world position of the mean end point of a cell whose log-odds exceed `threshold`;
    /// None for cells below it or unknown. One tile lookup for both.
    #[inline]
    pub fn occupied_hit(&self, ix: i32, iy: i32, threshold: f32) -> Option<[f64; 2]> {
        let tile = self.tile_slot(ix, iy).and_then(|s| self.tiles[s].as_ref())?;
        tile.occupied_hit(ix, iy, threshold, self.resolution)
    }

    /// Read access to the cells within `reach` (< TILE / 2) cells of (ix, iy), with the (at most
    /// 2×2) tiles they lie in looked up once: a nearest-obstacle search reads up to 49 cells
    /// around each end point, and the lookups dominated the scan matcher's time.
    #[inline]
    pub fn neighbourhood(&self, ix: i32, iy: i32, reach: i32) -> Neighbourhood<'_> {
        debug_assert!(reach < TILE / 2);
        let (tx0, ty0) = ((ix - reach) >> TILE_SHIFT, (iy - reach) >> TILE_SHIFT);
        let tile = |tx: i32, ty: i32| {
            self.tile_slot(tx << TILE_SHIFT, ty << TILE_SHIFT).and_then(|s| self.tiles[s].as_deref())
        };
        Neighbourhood {
            tiles: [tile(tx0, ty0), tile(tx0 + 1, ty0), tile(tx0, ty0 + 1), tile(tx0 + 1, ty0 + 1)],
            tx0,
            ty0,
            resolution: self.resolution,
        }
    }

    /// The world position of a cell's mean end point and the number of end points averaged
    /// (saturating at 255), whatever the cell's log-odds; None if no end point fell into it.
    #[inline]
    pub fn hit_mean(&self, ix: i32, iy: i32) -> Option<([f64; 2], u8)> {
        let tile = self.tile_slot(ix, iy).and_then(|s| self.tiles[s].as_ref())?;
        let k = Self::cell_offset(ix, iy);
        if tile.hits[k] == 0 {
            return None;
        }
        let off = tile.hit_offset[k];
        let res = self.resolution;
        Some((
            [(ix as f64 + (off[0] as f64 + 0.5) / 256.0) * res, (iy as f64 + (off[1] as f64 + 0.5) / 256.0) * res],
            tile.hits[k],
        ))
    }

    /// Grow the tile window so that it holds the world rectangle [x0, x1] × [y0, y1]. Fails,
    /// changing nothing, for a rectangle beyond the grid's reach or a window that cannot be
    /// allocated.
    pub fn ensure_covers(&mut self, x0: f64, y0: f64, x1: f64, y1: f64) -> Result<(), GridError> {
        let res = self.resolution;
        let to_tile = |x: f64, y: f64| -> Result<(i32, i32), GridError> {
            let (cx, cy) = ((x / res).floor(), (y / res).floor());
            // NaN fails the comparison too.
            if !(cx.abs() < MAX_CELL_INDEX && cy.abs() < MAX_CELL_INDEX) {
                return Err(GridError::OutOfReach { x, y, resolution: res });
            }
            Ok(((cx as i32) >> TILE_SHIFT, (cy as i32) >> TILE_SHIFT))
        };
        let (ax, ay) = to_tile(x0, y0)?;
        let (bx, by) = to_tile(x1, y1)?;
        if self.ntx > 0
            && ax >= self.tx0
            && ay >= self.ty0
            && bx < self.tx0 + self.ntx
            && by < self.ty0 + self.nty
        {
            return Ok(());
        }
        // Grow with margin so that a robot moving on does not regrow at every scan.
        let margin = 4;
        let (nx0, ny0, nx1, ny1) = if self.ntx == 0 {
            (ax - margin, ay - margin, bx + margin, by + margin)
        } else {
            (
                ax.min(self.tx0) - if ax < self.tx0 { margin } else { 0 },
                ay.min(self.ty0) - if ay < self.ty0 { margin } else { 0 },
                bx.max(self.tx0 + self.ntx - 1) + if bx >= self.tx0 + self.ntx { margin } else { 0 },
                by.max(self.ty0 + self.nty - 1) + if by >= self.ty0 + self.nty { margin } else { 0 },
            )
        };
        // Tile indices are below 2^26 in size, so these fit in i32 and their product in u64.
        let (ntx, nty) = (nx1 - nx0 + 1, ny1 - ny0 + 1);
        let slots = ntx as u64 * nty as u64;
        let slots = usize::try_from(slots).map_err(|_| GridError::NoMemory {
            what: "the map's window of tiles",
            bytes: slots as u128 * std::mem::size_of::<Option<Arc<Tile>>>() as u128,
        })?;
        let mut tiles = try_vec(slots, "the map's window of tiles")?;
        tiles.resize(slots, None);
        for ty in 0..self.nty {
            for tx in 0..self.ntx {
                let old = &mut self.tiles[(ty * self.ntx + tx) as usize];
                let (gx, gy) = (tx + self.tx0 - nx0, ty + self.ty0 - ny0);
                tiles[(gy * ntx + gx) as usize] = old.take();
            }
        }
        self.tx0 = nx0;
        self.ty0 = ny0;
        self.ntx = ntx;
        self.nty = nty;
        self.tiles = tiles;
        Ok(())
    }

    /// A copy that shares every tile (as `clone`), or NoMemory instead of an abort when even
    /// the window of pointers cannot be had: particles copy their maps at every resampling.
    pub fn try_clone(&self) -> Result<TiledGrid, GridError> {
        let mut tiles = try_vec(self.tiles.len(), "a particle's copy of its map window")?;
        tiles.extend_from_slice(&self.tiles);
        Ok(TiledGrid { resolution: self.resolution, tx0: self.tx0, ty0: self.ty0, ntx: self.ntx, nty: self.nty, tiles })
    }

    /// Tiles this grid holds (allocated, whether shared or not).
    pub fn tiles(&self) -> impl Iterator<Item = &Arc<Tile>> {
        self.tiles.iter().flatten()
    }

    pub const fn tile_bytes() -> usize {
        std::mem::size_of::<Tile>()
    }

    /// Dense copy of the observed part: (rows, cols, first cell ix, first cell iy, data) with
    /// data row-major, row 0 = lowest y; NaN where unknown. Empty grids give 0×0. Fails with
    /// NoMemory when the copy cannot be allocated.
    pub fn to_dense(&self) -> Result<(usize, usize, i32, i32, Vec<f32>), GridError> {
        let mut bounds: Option<(i32, i32, i32, i32)> = None;
        for ty in 0..self.nty {
            for tx in 0..self.ntx {
                if self.tiles[(ty * self.ntx + tx) as usize].is_some() {
                    let (x, y) = (tx + self.tx0, ty + self.ty0);
                    bounds = Some(match bounds {
                        None => (x, y, x, y),
                        Some((a, b, c, d)) => (a.min(x), b.min(y), c.max(x), d.max(y)),
                    });
                }
            }
        }
        let Some((tx_lo, ty_lo, tx_hi, ty_hi)) = bounds else {
            return Ok((0, 0, 0, 0, Vec::new()));
        };
        let (ix0, iy0) = (tx_lo << TILE_SHIFT, ty_lo << TILE_SHIFT);
        let cols = (tx_hi - tx_lo + 1) as usize * TILE as usize;
        let rows = (ty_hi - ty_lo + 1) as usize * TILE as usize;
        let cells = rows.checked_mul(cols).ok_or(GridError::NoMemory {
            what: "a dense copy of the map",
            bytes: rows as u128 * cols as u128 * 4,
        })?;
        let mut data = try_vec(cells, "a dense copy of the map")?;
        data.resize(cells, f32::NAN);
        for r in 0..rows {
            for c in 0..cols {
                data[r * cols + c] = self.get(ix0 + c as i32, iy0 + r as i32);
            }
        }
        Ok((rows, cols, ix0, iy0, data))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MODEL: LogOddsModel = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };

    #[test]
    fn cells_written_in_runs_equal_cells_written_one_by_one_and_leave_a_shared_copy_alone() {
        // A path that wanders over four tiles (negative indices too), revisits cells and
        // clamps, written into a grid that shares its tiles with an earlier copy.
        let mut base = TiledGrid::new(0.05);
        base.ensure_covers(-3.0, -3.0, 3.0, 3.0).unwrap();
        base.add(3, 3, MODEL.l_occ, &MODEL);
        let before: Vec<u32> = (-25..25).flat_map(|iy| (-25..25).map(move |ix| (ix, iy))).map(|(ix, iy)| base.get(ix, iy).to_bits()).collect();
        let cells: Vec<(i32, i32, f32)> = (0..400)
            .map(|k: i32| (((k * 7) % 40) - 20, ((k * 3) % 36) - 18, if k % 5 == 0 { MODEL.l_occ } else { MODEL.l_free }))
            .collect();
        let mut runs = base.clone();
        runs.add_cells(&cells, &MODEL);
        let mut one_by_one = base.clone();
        for &(ix, iy, d) in &cells {
            one_by_one.add(ix, iy, d, &MODEL);
        }
        let mut k = 0;
        for iy in -25..25 {
            for ix in -25..25 {
                assert_eq!(runs.get(ix, iy).to_bits(), one_by_one.get(ix, iy).to_bits(), "({ix}, {iy})");
                // The grid whose tiles `runs` shared is as it was.
                assert_eq!(base.get(ix, iy).to_bits(), before[k], "({ix}, {iy})");
                k += 1;
            }
        }
        assert!(runs.get(-20, -18) < 0.0 || runs.get(-20, -18) > 0.0);
    }

    #[test]
    fn writes_read_back_and_clamp_including_negative_indices() {
        let mut g = TiledGrid::new(0.05);
        g.ensure_covers(-3.0, -3.0, 3.0, 3.0).unwrap();
        assert!(g.get(-37, 12).is_nan());
        for _ in 0..10 {
            g.add(-37, 12, MODEL.l_occ, &MODEL);
        }
        assert_eq!(g.get(-37, 12), MODEL.l_max);
        g.add(5, -5, MODEL.l_free, &MODEL);
        assert_eq!(g.get(5, -5), -0.4);
    }

    #[test]
    fn growing_keeps_contents() {
        let mut g = TiledGrid::new(0.1);
        g.ensure_covers(0.0, 0.0, 1.0, 1.0).unwrap();
        g.add(3, 4, 1.0, &MODEL);
        g.ensure_covers(-50.0, -20.0, 80.0, 1.0).unwrap();
        assert_eq!(g.get(3, 4), 1.0);
        g.add(-499, -199, 1.0, &MODEL);
        assert_eq!(g.get(-499, -199), 1.0);
    }

    #[test]
    fn copies_share_tiles_until_written() {
        let mut a = TiledGrid::new(0.1);
        a.ensure_covers(0.0, 0.0, 10.0, 10.0).unwrap();
        a.add(1, 1, 1.0, &MODEL);
        a.add(60, 60, 1.0, &MODEL);
        let mut b = a.clone();
        let shared = |a: &TiledGrid, b: &TiledGrid| {
            a.tiles().zip(b.tiles()).filter(|(x, y)| Arc::ptr_eq(x, y)).count()
        };
        assert_eq!(shared(&a, &b), 2);
        b.add(1, 2, 1.0, &MODEL);
        assert_eq!(shared(&a, &b), 1);
        assert!(a.get(1, 2).is_nan());
        assert_eq!(b.get(1, 2), 1.0);
        let c = b.try_clone().unwrap();
        assert_eq!(shared(&b, &c), 2);
    }

    #[test]
    fn points_beyond_reach_are_errors_not_panics() {
        // A resolution of 1e-5 m puts a point 20 km out beyond 2^30 cells; NaN and infinity
        // are beyond reach too. The grid is left as it was.
        let mut g = TiledGrid::new(1e-5);
        g.ensure_covers(0.0, 0.0, 1.0, 1.0).unwrap();
        let before = g.tiles.len();
        for (x, y) in [(2.0e4, 0.0), (0.0, -2.0e4), (f64::NAN, 0.0), (f64::INFINITY, 1.0)] {
            assert!(matches!(g.ensure_covers(0.0, 0.0, x, y), Err(GridError::OutOfReach { .. })), "{x} {y}");
        }
        assert_eq!(g.tiles.len(), before);
    }

    #[test]
    fn windows_that_cannot_be_allocated_are_errors_not_aborts() {
        // 0.1 mm cells over 100 km: 2^50 tiles of window, far beyond any memory. Before, this
        // overflowed ("capacity overflow" panic) or aborted on the allocation.
        let mut g = TiledGrid::new(1e-4);
        let err = g.ensure_covers(-5.0e4, -5.0e4, 5.0e4, 5.0e4).unwrap_err();
        assert!(matches!(err, GridError::NoMemory { .. }), "{err}");
        assert!(err.to_string().contains("window of tiles"));
        assert!(try_vec::<u64>(usize::MAX / 4, "a test").is_err());
    }
}
