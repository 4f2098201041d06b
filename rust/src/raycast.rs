//! 2D grid traversal (Amanatides & Woo, "A fast voxel traversal algorithm", 1987).
//!
//! Cells are unit squares of side `resolution` in the world frame: cell (ix, iy) covers
//! [ix·res, (ix+1)·res) × [iy·res, (iy+1)·res). The traversal visits, in order along the ray,
//! every cell whose interior the segment passes through, and reports for each the ray length
//! (metres from the start) at which the ray enters and leaves it.

/// Visit the cells along the segment from `start` in unit direction `(dx, dy)` for `length`
/// metres. `visit(ix, iy, t_enter, t_exit)` returns false to stop early; the last cell visited
/// (the one holding the end point) has `t_exit >= length`.
#[inline]
pub fn traverse<F>(start: [f64; 2], dir: [f64; 2], length: f64, resolution: f64, mut visit: F)
where
    F: FnMut(i32, i32, f64, f64) -> bool,
{
    let inv_res = 1.0 / resolution;
    let ux = start[0] * inv_res;
    let uy = start[1] * inv_res;
    let mut ix = floor_i32(ux);
    let mut iy = floor_i32(uy);
    // Per-axis: step direction, ray length to the next cell boundary, and length per cell.
    let (step_x, mut t_max_x, t_delta_x) = axis_setup(ux, ix, dir[0], resolution);
    let (step_y, mut t_max_y, t_delta_y) = axis_setup(uy, iy, dir[1], resolution);
    let mut t_enter = 0.0;
    loop {
        let t_exit = t_max_x.min(t_max_y);
        if !visit(ix, iy, t_enter, t_exit) || t_exit >= length {
            return;
        }
        t_enter = t_exit;
        if t_max_x < t_max_y {
            ix += step_x;
            t_max_x += t_delta_x;
        } else {
            iy += step_y;
            t_max_y += t_delta_y;
        }
    }
}

/// `x.floor() as i32`, exactly, for every x (saturating; NaN gives 0, as the cast does).
/// Without SSE4.1 (not in the baseline x86-64 the wheels are built for) `floor` is a call into
/// libm, about 2 % of the scan matcher's and the renderer's time; a truncation and a compare
/// cost next to nothing.
#[inline(always)]
pub fn floor_i32(x: f64) -> i32 {
    let i = x as i32;
    if (i as f64) > x { i.saturating_sub(1) } else { i }
}

/// Step, length to the first boundary and length per cell along one axis (lengths in metres),
/// for the coordinate u (in cells) of cell `cell` = floor(u).
#[inline]
fn axis_setup(u: f64, cell: i32, d: f64, resolution: f64) -> (i32, f64, f64) {
    if d > 0.0 {
        let next = cell as f64 + 1.0;
        (1, (next - u) * resolution / d, resolution / d)
    } else if d < 0.0 {
        let prev = cell as f64;
        (-1, (u - prev) * resolution / -d, resolution / -d)
    } else {
        (0, f64::INFINITY, f64::INFINITY)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cells(start: [f64; 2], end: [f64; 2], res: f64) -> Vec<(i32, i32)> {
        let d = [end[0] - start[0], end[1] - start[1]];
        let len = (d[0] * d[0] + d[1] * d[1]).sqrt();
        let mut out = vec![];
        traverse(start, [d[0] / len, d[1] / len], len, res, |x, y, _, _| {
            out.push((x, y));
            true
        });
        out
    }

    #[test]
    fn floor_i32_is_floor_cast_to_i32() {
        let specials = [0.0, -0.0, 0.5, -0.5, 1.0, -1.0, 2.999999999, -2.000000001, 1e-300, -1e-300, 2147483646.5,
            -2147483647.5, 2147483648.0, -2147483649.0, 3e9, -3e9, f64::INFINITY, f64::NEG_INFINITY, f64::NAN];
        for x in specials {
            assert_eq!(floor_i32(x), x.floor() as i32, "{x}");
        }
        let mut z = 1u64;
        for _ in 0..100_000 {
            z = crate::light::mix(z);
            let x = (z as f64 / u64::MAX as f64 - 0.5) * 2e3;
            assert_eq!(floor_i32(x), x.floor() as i32, "{x}");
        }
    }

    #[test]
    fn horizontal_ray_visits_each_cell_once() {
        let c = cells([0.05, 0.05], [0.95, 0.05], 0.1);
        assert_eq!(c, (0..10).map(|i| (i, 0)).collect::<Vec<_>>());
    }

    #[test]
    fn diagonal_ray_count_matches_manhattan_distance() {
        // A general segment crosses |Δix| + |Δiy| boundaries, so it visits that many cells + 1.
        let c = cells([0.013, 0.021], [0.777, -0.532], 0.05);
        let (x0, y0) = ((0.013f64 / 0.05).floor() as i32, (0.021f64 / 0.05).floor() as i32);
        let (x1, y1) = ((0.777f64 / 0.05).floor() as i32, (-0.532f64 / 0.05).floor() as i32);
        assert_eq!(c.len() as i32, (x1 - x0).abs() + (y1 - y0).abs() + 1);
        assert_eq!(*c.first().unwrap(), (x0, y0));
        assert_eq!(*c.last().unwrap(), (x1, y1));
    }

    #[test]
    fn enter_exit_lengths_are_contiguous() {
        let mut last_exit = 0.0;
        traverse([0.3, 0.7], [0.6f64.cos(), 0.6f64.sin()], 3.0, 0.25, |_, _, t0, t1| {
            assert!((t0 - last_exit).abs() < 1e-12 && t1 >= t0);
            last_exit = t1;
            true
        });
        assert!(last_exit >= 3.0);
    }
}
