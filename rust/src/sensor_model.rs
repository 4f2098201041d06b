//! The range sensor's two models: the beam model p(z | m, x) that weighs particles (paper eq. 9;
//! Thrun, Burgard & Fox, Probabilistic Robotics, section 6.3) and the inverse sensor model that
//! writes a scan into a log-odds grid (paper eq. 8).

use crate::grid::{GridError, LogOddsModel, TiledGrid, TILE};
use crate::raycast::traverse;

/// Beam model mixture: weights of the hit / short / max / random parts and their parameters.
#[derive(Clone, Copy, Debug)]
pub struct BeamModel {
    pub z_hit: f64,
    pub z_short: f64,
    pub z_max: f64,
    pub z_rand: f64,
    /// Standard deviation of the hit part (metres).
    pub sigma_hit: f64,
    /// Rate of the exponential short-reading part (1/metres).
    pub lambda_short: f64,
    /// Largest range the model describes (metres); readings at or beyond it are max readings.
    pub max_range: f64,
    /// Log-odds above which a cell counts as an obstacle when casting the expected range.
    pub occupied_threshold: f32,
}

/// Scan geometry shared by both models: beam bearings in the sensor frame and the sensor's
/// pose in the robot frame.
pub struct ScanGeometry<'a> {
    pub angles: &'a [f64],
    pub sensor: [f64; 3],
}

impl<'a> ScanGeometry<'a> {
    /// The sensor's world pose for a robot pose.
    #[inline]
    pub fn sensor_pose(&self, robot: [f64; 3]) -> [f64; 3] {
        crate::motion::compose(robot, self.sensor)
    }
}

fn std_normal_cdf(x: f64) -> f64 {
    0.5 * (1.0 + libm::erf(x / std::f64::consts::SQRT_2))
}

impl BeamModel {
    /// Density of reading `z` when the map predicts `z_star` (both in [0, max_range]); a reading
    /// `z >= max_range` is a max reading and gets the point mass z_max instead of a density.
    /// The mixture integrates to one over [0, max_range] plus the point mass: the hit part is a
    /// Gaussian truncated to [0, max_range], the short part an exponential truncated to
    /// [0, z_star], the random part uniform.
    pub fn likelihood(&self, z: f64, z_star: f64) -> f64 {
        if z >= self.max_range {
            return self.z_max;
        }
        if z < 0.0 {
            return 0.0;
        }
        let s = self.sigma_hit;
        let mass = std_normal_cdf((self.max_range - z_star) / s) - std_normal_cdf(-z_star / s);
        let u = (z - z_star) / s;
        let hit = if mass > 0.0 {
            (-0.5 * u * u).exp() / (s * (2.0 * std::f64::consts::PI).sqrt()) / mass
        } else {
            0.0
        };
        let short = if z <= z_star && z_star > 0.0 {
            let l = self.lambda_short;
            l * (-l * z).exp() / (1.0 - (-l * z_star).exp())
        } else {
            0.0
        };
        self.z_hit * hit + self.z_short * short + self.z_rand / self.max_range
    }

    /// The range the map predicts along a ray: the distance to the middle of the ray's chord
    /// through the first occupied cell, or `max_range` if none is within it. `None` when the
    /// ray reaches a never-observed cell first (the map says nothing beyond it) — the returned
    /// value then is the distance at which it did.
    #[inline]
    pub fn expected_range(&self, grid: &TiledGrid, origin: [f64; 2], angle: f64) -> (f64, bool) {
        let mut result = (self.max_range, true);
        traverse(origin, [angle.cos(), angle.sin()], self.max_range, grid.resolution, |ix, iy, t0, t1| {
            let l = grid.get(ix, iy);
            if l.is_nan() {
                result = (t0, false);
                false
            } else if l > self.occupied_threshold {
                result = (0.5 * (t0 + t1.min(self.max_range)), true);
                false
            } else {
                true
            }
        });
        result
    }

    /// Mean log p(z_i | m, x) over the scored beams of a scan (every `stride`-th beam) and how
    /// many were scored. Readings that are no echo (+inf) or beyond max_range are left out, as
    /// are beams whose ray leaves the known map before the reading could have ended.
    pub fn scan_log_likelihood(
        &self,
        grid: &TiledGrid,
        geom: &ScanGeometry,
        robot: [f64; 3],
        ranges: &[f32],
        stride: usize,
    ) -> (f64, usize) {
        let sp = geom.sensor_pose(robot);
        let mut total = 0.0;
        let mut scored = 0;
        for i in (0..ranges.len()).step_by(stride.max(1)) {
            let z = ranges[i] as f64;
            if !z.is_finite() || z >= self.max_range {
                continue;
            }
            let (z_star, known) = self.expected_range(grid, [sp[0], sp[1]], sp[2] + geom.angles[i]);
            // Unknown space ahead: a reading well short of it contradicts the free cells it
            // passed; a reading past it is uninformative and is left out.
            if !known && z > z_star - 2.0 * self.sigma_hit {
                continue;
            }
            total += self.likelihood(z, z_star).max(1e-300).ln();
            scored += 1;
        }
        if scored == 0 {
            (0.0, 0)
        } else {
            (total / scored as f64, scored)
        }
    }
}

/// The most tiles one scan may write: 2^22 tiles are 7.5 GB. At the finest resolution the
/// configuration allows (1 mm), a scan of 1081 beams of 30 m writes at most 2.9 million.
pub const MAX_SCAN_TILES: f64 = (1u64 << 22) as f64;

/// Write a scan into a grid with the inverse sensor model: every cell a beam passes through
/// gets l_free, the cell holding its end point l_occ; log-odds are clamped to [l_min, l_max].
/// Beams longer than `max_range` (including no echo, +inf, when `clear_no_echo`) mark free
/// space up to `max_range` and no obstacle. Fails, writing nothing, when the scan reaches beyond
/// the grid or its window cannot grow (see `TiledGrid::ensure_covers`).
pub fn integrate_scan(
    grid: &mut TiledGrid,
    model: &LogOddsModel,
    geom: &ScanGeometry,
    robot: [f64; 3],
    ranges: &[f32],
    max_range: f64,
    clear_no_echo: bool,
    once_per_scan: bool,
) -> Result<(), GridError> {
    let sp = geom.sensor_pose(robot);
    let (mut x0, mut y0, mut x1, mut y1) = (sp[0], sp[1], sp[0], sp[1]);
    let mut beams: Vec<(usize, f64, bool)> = Vec::with_capacity(ranges.len());
    for (i, &r) in ranges.iter().enumerate() {
        let r = r as f64;
        let (len, hit) = if r.is_finite() && r <= max_range {
            (r, true)
        } else if r.is_finite() || clear_no_echo {
            (max_range, false)
        } else {
            continue;
        };
        if !(len > 0.0) {
            continue;
        }
        let a = sp[2] + geom.angles[i];
        let (ex, ey) = (sp[0] + len * a.cos(), sp[1] + len * a.sin());
        if !(ex.is_finite() && ey.is_finite()) {
            continue; // a bearing or pose that is not a number marks nothing
        }
        x0 = x0.min(ex);
        y0 = y0.min(ey);
        x1 = x1.max(ex);
        y1 = y1.max(ey);
        beams.push((i, len, hit));
    }
    let res = grid.resolution;
    // A beam of length l crosses at most √2·l/T + 2 tiles of side T, and every tile the scan
    // writes lies in the box around the sensor and the end points: bound what the scan may
    // allocate before it allocates anything (tiles are allocated one by one, where a failure
    // could not be caught). The box matters for dense scans: two million beams of 4 m overlap
    // in a few hundred tiles, where their sum counted twelve million.
    let tile = TILE as f64 * res;
    let along: f64 = beams.iter().map(|&(_, len, _)| std::f64::consts::SQRT_2 * len / tile + 2.0).sum();
    let boxed = ((x1 - x0 + 2.0 * res) / tile + 2.0) * ((y1 - y0 + 2.0 * res) / tile + 2.0);
    let tiles = along.min(boxed);
    if !(tiles <= MAX_SCAN_TILES) {
        return Err(GridError::NoMemory {
            what: "the tiles one scan would write",
            bytes: (tiles.min(1e30) as u128).saturating_mul(TiledGrid::tile_bytes() as u128),
        });
    }
    grid.ensure_covers(x0 - res, y0 - res, x1 + res, y1 + res)?;
    if once_per_scan {
        write_each_cell_once(grid, model, sp, geom, &beams, [x0, y0, x1, y1]);
        return Ok(());
    }
    // A beam's cells are gathered and written in runs per tile; a very long beam is flushed in
    // chunks so the buffer stays small. Cells are written in the order walked either way.
    const FLUSH_CELLS: usize = 4096;
    let mut cells = Vec::with_capacity(FLUSH_CELLS);
    for (i, len, hit) in beams {
        let (s, c) = (sp[2] + geom.angles[i]).sin_cos();
        traverse([sp[0], sp[1]], [c, s], len, res, |ix, iy, _, t1| {
            let end = t1 >= len;
            cells.push((ix, iy, if end && hit { model.l_occ } else { model.l_free }));
            if cells.len() == FLUSH_CELLS {
                grid.add_cells(&cells, model);
                cells.clear();
            }
            true
        });
        grid.add_cells(&cells, model);
        cells.clear();
        if hit {
            grid.add_hit(sp[0] + len * c, sp[1] + len * s);
        }
    }
    Ok(())
}

/// The scan's cells written once each (`map.once_per_scan`): l_occ where a beam ends, else
/// l_free where any beam passes, as Cartographer's range-data inserter does; per beam, a cell
/// that many beams of one scan cross takes many updates (BENCHMARKS.md, "Each cell once per
/// scan"). Every cell a beam visits is gathered with whether the beam ends there; the end
/// cells are written first, then the free ones not yet written. "Written" is a bitmap over the
/// box of the sensor and the end points (`bounds`, plus a margin), a few kilobytes for a laser;
/// a box too large for one (a fine grid and long beams) falls back to sorted cell keys.
fn write_each_cell_once(
    grid: &mut TiledGrid,
    model: &LogOddsModel,
    sp: [f64; 3],
    geom: &ScanGeometry,
    beams: &[(usize, f64, bool)],
    bounds: [f64; 4],
) {
    let res = grid.resolution;
    let mut visited: Vec<(i32, i32, bool)> = Vec::new();
    for &(i, len, hit) in beams {
        let (s, c) = (sp[2] + geom.angles[i]).sin_cos();
        traverse([sp[0], sp[1]], [c, s], len, res, |ix, iy, _, t1| {
            visited.push((ix, iy, hit && t1 >= len));
            true
        });
        if hit {
            grid.add_hit(sp[0] + len * c, sp[1] + len * s);
        }
    }
    // Ends first, so that a cell where one beam ends and another passes is occupied.
    let ordered = visited.iter().filter(|v| v.2).chain(visited.iter().filter(|v| !v.2));
    let delta = |end: bool| if end { model.l_occ } else { model.l_free };
    const MARGIN: i64 = 2;
    let (bx0, by0) = ((bounds[0] / res).floor() as i64 - MARGIN, (bounds[1] / res).floor() as i64 - MARGIN);
    let (w, h) = ((bounds[2] / res).floor() as i64 + MARGIN + 1 - bx0, (bounds[3] / res).floor() as i64 + MARGIN + 1 - by0);
    let cells: Vec<(i32, i32, f32)> = if w > 0 && h > 0 && w.saturating_mul(h) <= MAX_BITMAP_CELLS {
        let mut written = vec![0u64; ((w * h + 63) / 64) as usize];
        ordered
            .filter(|&&(ix, iy, _)| {
                let (dx, dy) = (ix as i64 - bx0, iy as i64 - by0);
                if !(0..w).contains(&dx) || !(0..h).contains(&dy) {
                    return true; // outside the box (it cannot be, but a rounding must not panic)
                }
                let k = (dy * w + dx) as usize;
                let fresh = written[k / 64] & (1 << (k % 64)) == 0;
                written[k / 64] |= 1 << (k % 64);
                fresh
            })
            .map(|&(ix, iy, end)| (ix, iy, delta(end)))
            .collect()
    } else {
        let key = |ix: i32, iy: i32| ((ix as i64) << 32) | (iy as u32 as i64);
        let mut seen: Vec<(i64, bool)> = ordered.map(|&(ix, iy, end)| (key(ix, iy), end)).collect();
        seen.sort_by_key(|&(k, end)| (k, !end)); // stable per key: an end before a pass
        seen.dedup_by_key(|&mut (k, _)| k);
        seen.iter().map(|&(k, end)| ((k >> 32) as i32, k as i32, delta(end))).collect()
    };
    grid.add_cells(&cells, model);
}

/// Cells of the largest box `write_each_cell_once` marks in a bitmap (8 MiB of bits).
const MAX_BITMAP_CELLS: i64 = 1 << 26;

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> BeamModel {
        BeamModel {
            z_hit: 0.7,
            z_short: 0.1,
            z_max: 0.05,
            z_rand: 0.15,
            sigma_hit: 0.1,
            lambda_short: 0.5,
            max_range: 10.0,
            occupied_threshold: 0.0,
        }
    }

    #[test]
    fn mixture_integrates_to_one() {
        let m = model();
        for &z_star in &[0.05, 1.0, 4.3, 9.95, 10.0] {
            let n = 200_000;
            let h = m.max_range / n as f64;
            let integral: f64 = (0..n).map(|k| m.likelihood((k as f64 + 0.5) * h, z_star) * h).sum();
            assert!((integral + m.z_max - 1.0).abs() < 1e-4, "z*={z_star}: {integral}");
        }
    }

    #[test]
    fn a_scan_that_would_write_too_many_tiles_is_refused_before_it_writes_any() {
        // One beam of 50 km at 0.1 mm crosses 44 million tiles (77 GB): an error, not an abort,
        // and the grid stays empty.
        let lm = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };
        let geom = ScanGeometry { angles: &[0.0, 0.1], sensor: [0.0; 3] };
        let mut g = TiledGrid::new(1e-4);
        let err = integrate_scan(&mut g, &lm, &geom, [0.0; 3], &[5.0e4, 1.0], 1e6, false, false).unwrap_err();
        assert!(matches!(err, GridError::NoMemory { .. }) && err.to_string().contains("one scan"), "{err}");
        assert_eq!(g.tiles().count(), 0);
        integrate_scan(&mut g, &lm, &geom, [0.0; 3], &[0.5, 1.0], 1e6, false, false).unwrap();
        assert!(g.tiles().count() > 0);
    }

    #[test]
    fn a_dense_scan_within_a_small_box_is_written() {
        // 150 000 beams of 4 m at 1 cm: 5.6 million tiles summed along the beams, more than
        // MAX_SCAN_TILES, but all of them inside the 8 m box of 52 × 52 tiles.
        let lm = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };
        let n = 150_000;
        let angles: Vec<f64> = (0..n).map(|k| k as f64 * std::f64::consts::TAU / n as f64).collect();
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let along: f64 = n as f64 * (std::f64::consts::SQRT_2 * 4.0 / (TILE as f64 * 0.01) + 2.0);
        assert!(along > MAX_SCAN_TILES);
        let mut g = TiledGrid::new(0.01);
        integrate_scan(&mut g, &lm, &geom, [0.0; 3], &vec![4.0; n], 10.0, false, false).unwrap();
        let tiles = g.tiles().count();
        assert!(tiles > 1500 && tiles <= 52 * 52, "{tiles}");
    }

    #[test]
    fn once_per_scan_writes_each_cell_once_and_an_end_wins() {
        // Beams 0 and 1 (1e-4 rad apart) end in the cell at 1.0 m, beam 2 ends at 0.52 m inside
        // their path. Per beam: the shared end cell takes l_occ twice, the cells before 0.5 m
        // l_free three times, beam 2's end cell l_occ + 2 l_free. Once per scan: l_occ, l_free,
        // l_occ.
        let lm = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -5.0, l_max: 5.0 };
        let geom = ScanGeometry { angles: &[0.0, 1e-4, 2e-4], sensor: [0.0; 3] };
        let ranges = [1.01, 1.01, 0.52];
        let mut per_beam = TiledGrid::new(0.1);
        integrate_scan(&mut per_beam, &lm, &geom, [0.001, 0.05, 0.0], &ranges, 10.0, false, false).unwrap();
        let mut once = TiledGrid::new(0.1);
        integrate_scan(&mut once, &lm, &geom, [0.001, 0.05, 0.0], &ranges, 10.0, false, true).unwrap();
        let close = |a: f32, b: f32| (a - b).abs() < 1e-6;
        assert!(close(per_beam.get(10, 0), 1.8) && close(once.get(10, 0), 0.9));
        assert!(close(per_beam.get(3, 0), -1.2) && close(once.get(3, 0), -0.4));
        assert!(close(per_beam.get(5, 0), 0.1) && close(once.get(5, 0), 0.9));
        // The same cells are known either way, and the end points' sub-cell means are the same.
        for ix in -1..=11 {
            assert_eq!(per_beam.get(ix, 0).is_nan(), once.get(ix, 0).is_nan(), "cell {ix}");
            assert_eq!(per_beam.hit_mean(ix, 0), once.hit_mean(ix, 0), "cell {ix}");
        }
    }

    #[test]
    fn once_per_scan_without_a_bitmap_writes_the_same_cells() {
        // A box too large for the bitmap takes the sorted keys instead: the same grid.
        let lm = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -5.0, l_max: 5.0 };
        let angles: Vec<f64> = (0..720).map(|k| k as f64 * std::f64::consts::TAU / 720.0).collect();
        let ranges: Vec<f32> = (0..720).map(|k| 1.0 + 0.5 * ((k % 7) as f32)).collect();
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let beams: Vec<(usize, f64, bool)> = (0..720).map(|i| (i, ranges[i] as f64, true)).collect();
        let sp = geom.sensor_pose([0.02, -0.03, 0.1]);
        let grids: Vec<TiledGrid> = [5.0, 1e4]
            .iter()
            .map(|&half| {
                let mut g = TiledGrid::new(0.05);
                g.ensure_covers(-5.0, -5.0, 5.0, 5.0).unwrap();
                write_each_cell_once(&mut g, &lm, sp, &geom, &beams, [-half, -half, half, half]);
                g
            })
            .collect();
        assert!((2e4 / 0.05) * (2e4 / 0.05) > MAX_BITMAP_CELLS as f64);
        let mut known = 0;
        for ix in -110..110 {
            for iy in -110..110 {
                let (a, b) = (grids[0].get(ix, iy), grids[1].get(ix, iy));
                assert!(a == b || (a.is_nan() && b.is_nan()), "cell ({ix}, {iy}): {a} vs {b}");
                known += usize::from(!a.is_nan());
            }
        }
        assert!(known > 1000, "{known}");
    }

    #[test]
    fn expected_range_finds_the_wall_and_reports_unknown() {
        let lm = LogOddsModel { l_occ: 2.0, l_free: -1.0, l_min: -5.0, l_max: 5.0 };
        let mut g = TiledGrid::new(0.1);
        g.ensure_covers(-1.0, -1.0, 10.0, 1.0).unwrap();
        for ix in 0..30 {
            g.add(ix, 0, lm.l_free, &lm);
        }
        g.add(30, 0, lm.l_occ, &lm);
        let m = model();
        let (z, known) = m.expected_range(&g, [0.05, 0.05], 0.0);
        assert!(known && (z - 3.0).abs() < 0.051, "{z}");
        let (z, known) = m.expected_range(&g, [0.05, 0.05], std::f64::consts::FRAC_PI_2);
        assert!(!known && (z - 0.05).abs() < 1e-9);
    }
}
