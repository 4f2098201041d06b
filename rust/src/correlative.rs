//! A wide correlative scan match (Olson, "Real-time correlative scan matching", ICRA 2009) that
//! finds a scan in a map when the odometry has put it far from where the robot really is.
//!
//! Why: the hill climbing of the scan-matching proposal only sees the likelihood field within a
//! few cells of the map's obstacles, so it cannot undo an odometry error larger than that. Real
//! wheel odometry has such errors: in the Freiburg 079 log the wheels report up to a metre of
//! travel in two seconds that the robot never made (the laser sees the room stand still), and
//! one such scan, matched in the wrong place, turns the rest of the map by tens of degrees.
//!
//! The search scores every pose of a regular grid around the prediction (± `half_xy` in x and y,
//! ± `half_theta` in heading) against a raster of a smoothed likelihood field of the map around
//! the scan, built once per search: a brute-force search with per-heading precomputed point
//! offsets, so that one pose costs one raster read per end point. Written here because the map
//! is the particle's own tiled grid, which no library's matcher reads.
//!
//! The search also says how clearly its best pose stands out from the other places of the
//! window (`Found::distinct`): along a corridor that the scan sees too little of, every place
//! scores alike and the best one is only the tie-break (Olson 2009 reads the same from the
//! score surface's covariance; a second peak is what a wrong jump needs, so this compares peaks).

use crate::grid::{try_vec, GridError, TiledGrid, MAX_CELL_INDEX};
use crate::motion::wrap;
use crate::sensor_model::ScanGeometry;

/// The grid of poses searched.
#[derive(Clone, Copy, Debug)]
pub struct SearchWindow {
    /// Half-widths of the window in x and y (m) and in heading (rad).
    pub half_xy: f64,
    pub half_theta: f64,
    /// Spacing of the poses in x and y (m) and in heading (rad).
    pub step_xy: f64,
    pub step_theta: f64,
}

/// Log-likelihood of an end point per raster cell: ln(N(d; 0, σ) + floor) for the distance d
/// from the cell centre to the nearest occupied cell's mean end point within 3σ, and ln(floor)
/// beyond. σ is the search's translation step, so that a pose between two grid poses still
/// scores nearly as well as the nearer one.
struct FieldRaster {
    ix0: i32,
    iy0: i32,
    nx: i32,
    ny: i32,
    resolution: f64,
    ll: Vec<f32>,
    floor_ll: f32,
}

impl FieldRaster {
    /// The raster over world rectangle [x0, x1] × [y0, y1]; an error instead of a panic or an
    /// abort for a rectangle beyond the grid's reach or too large to allocate.
    fn build(grid: &TiledGrid, occupied_threshold: f32, sigma: f64, floor: f64, bounds: [f64; 4]) -> Result<Self, GridError> {
        let res = grid.resolution;
        let reach = (3.0 * sigma / res).ceil() as i32;
        let cell = |v: f64| (v / res).floor();
        let outside = |i: usize| GridError::OutOfReach { x: bounds[i & 2], y: bounds[(i & 2) + 1], resolution: res };
        for (i, v) in bounds.iter().enumerate() {
            if !(cell(*v).abs() < MAX_CELL_INDEX) {
                return Err(outside(i));
            }
        }
        let (ix0, iy0) = (cell(bounds[0]) as i32, cell(bounds[1]) as i32);
        let (ix1, iy1) = (cell(bounds[2]) as i32, cell(bounds[3]) as i32);
        let (nx, ny) = (ix1 - ix0 + 1, iy1 - iy0 + 1);
        let n = nx as usize * ny as usize; // below 2^62: no overflow
        let mut d2 = try_vec(n, "the wide search's raster")?;
        d2.resize(n, f64::INFINITY);
        // Stamp the neighbourhood of every occupied cell (obstacles are few: this is cheaper
        // than a nearest-obstacle search per raster cell).
        for cy in iy0 - reach..=iy1 + reach {
            for cx in ix0 - reach..=ix1 + reach {
                let Some(h) = grid.occupied_hit(cx, cy, occupied_threshold) else { continue };
                for ny_ in (cy - reach).max(iy0)..=(cy + reach).min(iy1) {
                    for nx_ in (cx - reach).max(ix0)..=(cx + reach).min(ix1) {
                        let (dx, dy) = ((nx_ as f64 + 0.5) * res - h[0], (ny_ as f64 + 0.5) * res - h[1]);
                        let k = ((ny_ - iy0) * nx + (nx_ - ix0)) as usize;
                        d2[k] = d2[k].min(dx * dx + dy * dy);
                    }
                }
            }
        }
        let norm = 1.0 / (sigma * (2.0 * std::f64::consts::PI).sqrt());
        let limit = (3.0 * sigma).powi(2);
        let ll = d2
            .iter()
            .map(|&q| {
                let hit = if q <= limit { norm * (-0.5 * q / (sigma * sigma)).exp() } else { 0.0 };
                (hit + floor).ln() as f32
            })
            .collect();
        Ok(FieldRaster { ix0, iy0, nx, ny, resolution: res, ll, floor_ll: floor.ln() as f32 })
    }

    #[inline]
    fn at(&self, x: f64, y: f64) -> f32 {
        let ix = (x / self.resolution).floor() as i32 - self.ix0;
        let iy = (y / self.resolution).floor() as i32 - self.iy0;
        if ix < 0 || iy < 0 || ix >= self.nx || iy >= self.ny {
            self.floor_ll
        } else {
            self.ll[(iy * self.nx + ix) as usize]
        }
    }
}

/// What the wide search found.
#[derive(Clone, Copy, Debug)]
pub struct Found {
    /// The best robot pose of the window.
    pub pose: [f64; 3],
    /// How clearly it stands out: its score minus the best score at any heading of the positions
    /// more than `DISTINCT_STEPS` steps away from it, as a share of the scan's end points (one end
    /// point moved from the raster's peak to its floor counts 1/n). Near 0 where another place
    /// explains the scan as well (along a bare corridor); 1 where nothing else explains any of it.
    pub distinct: f64,
}

/// Positions within this many search steps of the best one are its own peak's shoulder (the
/// raster is smoothed by one step), not another place.
pub const DISTINCT_STEPS: i32 = 3;

/// The robot pose in the window around `center` whose end points `pts` (sensor frame) score best
/// against the raster of `grid`'s likelihood field, and how distinct it is (`Found`). Ties go to
/// the pose nearest the centre. Fails when the raster cannot be made (see `FieldRaster::build`).
pub fn correlative_search(
    grid: &TiledGrid,
    occupied_threshold: f32,
    floor: f64,
    geom: &ScanGeometry,
    pts: &[[f64; 2]],
    center: [f64; 3],
    w: &SearchWindow,
) -> Result<Found, GridError> {
    if pts.is_empty() {
        return Ok(Found { pose: center, distinct: 0.0 });
    }
    let n_xy = (w.half_xy / w.step_xy).round() as i32;
    let n_th = (w.half_theta / w.step_theta).round() as i32;
    // Offsets of the end points from the robot position, per heading of the window.
    let offsets: Vec<Vec<[f64; 2]>> = (-n_th..=n_th)
        .map(|k| {
            let theta = center[2] + k as f64 * w.step_theta;
            let sp = geom.sensor_pose([0.0, 0.0, theta]);
            let (s, c) = sp[2].sin_cos();
            pts.iter().map(|p| [sp[0] + c * p[0] - s * p[1], sp[1] + s * p[0] + c * p[1]]).collect()
        })
        .collect();
    let mut bounds = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
    for q in offsets.iter().flatten() {
        bounds = [bounds[0].min(q[0]), bounds[1].min(q[1]), bounds[2].max(q[0]), bounds[3].max(q[1])];
    }
    let margin = n_xy as f64 * w.step_xy;
    let bounds = [
        center[0] + bounds[0] - margin,
        center[1] + bounds[1] - margin,
        center[0] + bounds[2] + margin,
        center[1] + bounds[3] + margin,
    ];
    let raster = FieldRaster::build(grid, occupied_threshold, w.step_xy, floor, bounds)?;
    let side = (2 * n_xy + 1) as usize;
    // The best score of each position over the headings, for `Found::distinct`.
    let mut at_position = try_vec(side * side, "the wide search's scores")?;
    at_position.resize(side * side, f64::NEG_INFINITY);
    let mut best = (f64::NEG_INFINITY, 0, 0, 0);
    for (k, offs) in offsets.iter().enumerate() {
        let kt = k as i32 - n_th;
        for i in -n_xy..=n_xy {
            for j in -n_xy..=n_xy {
                let (x, y) = (center[0] + i as f64 * w.step_xy, center[1] + j as f64 * w.step_xy);
                let total: f32 = offs.iter().map(|o| raster.at(x + o[0], y + o[1])).sum();
                // A hair of preference for the centre decides ties (a bare corridor).
                let score = total as f64 - 1e-6 * (i * i + j * j + kt * kt) as f64;
                let cell = &mut at_position[(i + n_xy) as usize * side + (j + n_xy) as usize];
                *cell = cell.max(score);
                if score > best.0 {
                    best = (score, i, j, kt);
                }
            }
        }
    }
    let mut elsewhere = f64::NEG_INFINITY;
    for i in -n_xy..=n_xy {
        for j in -n_xy..=n_xy {
            if (i - best.1).abs().max((j - best.2).abs()) > DISTINCT_STEPS {
                elsewhere = elsewhere.max(at_position[(i + n_xy) as usize * side + (j + n_xy) as usize]);
            }
        }
    }
    // One end point's whole range in the raster: from the peak, ln(N(0; 0, σ) + floor), to ln(floor).
    let span = (1.0 / (w.step_xy * (2.0 * std::f64::consts::PI).sqrt()) + floor).ln() - floor.ln();
    // A window no wider than the peak's shoulder holds no other place to compare with.
    let distinct = if elsewhere.is_finite() { ((best.0 - elsewhere) / (pts.len() as f64 * span)).max(0.0) } else { 1.0 };
    Ok(Found {
        pose: [
            center[0] + best.1 as f64 * w.step_xy,
            center[1] + best.2 as f64 * w.step_xy,
            wrap(center[2] + best.3 as f64 * w.step_theta),
        ],
        distinct,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::LogOddsModel;
    use crate::sensor_model::integrate_scan;

    /// An L-shaped room with a pillar, so that no shift or turn looks like another.
    fn room_scan(at: [f64; 3], angles: &[f64]) -> Vec<f32> {
        let walls: [[f64; 4]; 7] = [
            [0.0, 0.0, 8.0, 0.0],
            [8.0, 0.0, 8.0, 3.0],
            [8.0, 3.0, 4.0, 3.0],
            [4.0, 3.0, 4.0, 6.0],
            [4.0, 6.0, 0.0, 6.0],
            [0.0, 6.0, 0.0, 0.0],
            [2.0, 2.0, 2.5, 2.0],
        ];
        crate::test_support::cast_walls(&walls, at, angles)
    }

    #[test]
    fn finds_a_scan_displaced_far_beyond_the_hill_climbing_reach() {
        let angles: Vec<f64> = (0..360).map(|k| (k as f64 - 180.0).to_radians()).collect();
        let geom = ScanGeometry { angles: &angles, sensor: [0.1, 0.0, 0.0] };
        let lm = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };
        let mut g = TiledGrid::new(0.05);
        let truth = [1.5, 4.0, 0.3];
        for pose in [[3.0, 1.2, -0.2], truth] {
            integrate_scan(&mut g, &lm, &geom, pose, &room_scan(geom.sensor_pose(pose), &angles), 20.0, false, false).unwrap();
        }
        // The scan the robot takes a little later, from a pose its odometry puts 0.7 m and 9° off.
        let real = [1.8, 3.7, 0.45];
        let ranges = room_scan(geom.sensor_pose(real), &angles);
        let pts = crate::scan_match::endpoints(&geom, &ranges, 2, 20.0);
        let predicted = [2.4, 3.4, 0.3];
        let w = SearchWindow { half_xy: 1.0, half_theta: 15f64.to_radians(), step_xy: 0.1, step_theta: 1f64.to_radians() };
        let searched = correlative_search(&g, 0.0, 0.1 / 20.0, &geom, &pts, predicted, &w).unwrap();
        let found = searched.pose;
        assert!((found[0] - real[0]).abs() <= 0.06 && (found[1] - real[1]).abs() <= 0.06, "{found:?}");
        assert!(wrap(found[2] - real[2]).abs() <= 1.1f64.to_radians(), "{found:?}");
        // No other place in the room explains the scan: most of its end points leave the walls
        // 0.3 m or more away from the right pose.
        assert!(searched.distinct > 0.3, "{searched:?}");
    }

    #[test]
    fn a_place_along_a_bare_corridor_is_not_distinct() {
        // Two parallel walls 2 m apart and 40 m long, mapped from the middle; the scan, taken
        // 0.5 m further on, looks the same from anywhere along them (the window is 1 m each way).
        let walls: [[f64; 4]; 2] = [[-20.0, 0.0, 20.0, 0.0], [-20.0, 2.0, 20.0, 2.0]];
        let angles: Vec<f64> = (0..360).map(|k| (k as f64 - 180.0).to_radians()).collect();
        let geom = ScanGeometry { angles: &angles, sensor: [0.0; 3] };
        let lm = LogOddsModel { l_occ: 0.9, l_free: -0.4, l_min: -2.0, l_max: 3.5 };
        let mut g = TiledGrid::new(0.05);
        let mapped = [0.0, 1.0, 0.0];
        let ranges: Vec<f32> = crate::test_support::cast_walls(&walls, mapped, &angles).iter().map(|r| r.min(8.0)).collect();
        integrate_scan(&mut g, &lm, &geom, mapped, &ranges, 8.0, false, false).unwrap();
        let real = [0.5, 1.0, 0.0];
        let ranges: Vec<f32> = crate::test_support::cast_walls(&walls, real, &angles).iter().map(|r| r.min(8.0)).collect();
        let pts = crate::scan_match::endpoints(&geom, &ranges, 1, 7.99);
        let w = SearchWindow { half_xy: 1.0, half_theta: 15f64.to_radians(), step_xy: 0.1, step_theta: 1f64.to_radians() };
        let searched = correlative_search(&g, 0.0, 0.1 / 8.0, &geom, &pts, [1.1, 1.0, 0.0], &w).unwrap();
        assert!((searched.pose[1] - 1.0).abs() <= 0.06, "{searched:?}");
        assert!(searched.distinct < 0.05, "{searched:?}");
    }
}
