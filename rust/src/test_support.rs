//! Helpers for the unit tests of several modules (compiled only for `cargo test`).

/// Ranges from sensor pose `at` to the nearest of the segments `walls` (x0, y0, x1, y1),
/// +inf where a beam meets none: an exact ray cast, independent of any grid.
pub fn cast_walls(walls: &[[f64; 4]], at: [f64; 3], angles: &[f64]) -> Vec<f32> {
    angles
        .iter()
        .map(|a| {
            let (dy, dx) = (at[2] + a).sin_cos();
            let mut best = f64::INFINITY;
            for w in walls {
                let (ex, ey) = (w[2] - w[0], w[3] - w[1]);
                let den = dx * ey - dy * ex;
                if den.abs() < 1e-12 {
                    continue;
                }
                let (fx, fy) = (w[0] - at[0], w[1] - at[1]);
                let t = (fx * ey - fy * ex) / den;
                let u = (fx * dy - fy * dx) / den;
                if t > 0.0 && (0.0..=1.0).contains(&u) {
                    best = best.min(t);
                }
            }
            best as f32
        })
        .collect()
}
