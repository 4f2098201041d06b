//! Odometry motion model (Thrun, Burgard & Fox, Probabilistic Robotics, table 5.6,
//! sample_motion_model_odometry), with α1..α4 as variances:
//! δ̂rot1 = δrot1 − ε(α1 δrot1² + α2 δtrans²), δ̂trans = δtrans − ε(α3 δtrans² + α4 (δrot1² + δrot2²)),
//! δ̂rot2 = δrot2 − ε(α1 δrot2² + α2 δtrans²), where ε(b²) is a zero-mean normal of variance b².

use rand::RngExt;
use rand_distr::StandardNormal;

pub fn wrap(a: f64) -> f64 {
    let two_pi = 2.0 * std::f64::consts::PI;
    (a + std::f64::consts::PI).rem_euclid(two_pi) - std::f64::consts::PI
}

/// a ⊕ b for planar poses (x, y, θ).
#[inline]
pub fn compose(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    let (s, c) = a[2].sin_cos();
    [a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2])]
}

/// a⁻¹ ⊕ b: pose b in the frame of pose a.
#[inline]
pub fn relative(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    let (s, c) = a[2].sin_cos();
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    [c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2])]
}

#[derive(Clone, Copy, Debug)]
pub struct OdometryMotion {
    pub alpha: [f64; 4],
}

/// The odometry increment (δrot1, δtrans, δrot2) between two odometry poses.
pub fn decompose(prev: [f64; 3], cur: [f64; 3]) -> (f64, f64, f64) {
    let (dx, dy) = (cur[0] - prev[0], cur[1] - prev[1]);
    let trans = (dx * dx + dy * dy).sqrt();
    // Below a micrometre the direction of travel is noise: count it as a turn in place.
    let rot1 = if trans < 1e-6 { 0.0 } else { wrap(dy.atan2(dx) - prev[2]) };
    let rot2 = wrap(cur[2] - prev[2] - rot1);
    (rot1, trans, rot2)
}

impl OdometryMotion {
    /// Draw a new pose for a particle at `pose`, given the odometry moved from `prev` to `cur`.
    pub fn sample<R: rand::Rng>(&self, pose: [f64; 3], prev: [f64; 3], cur: [f64; 3], rng: &mut R) -> [f64; 3] {
        let (rot1, trans, rot2) = decompose(prev, cur);
        // Driving backwards gives δrot1 ≈ ±π; its noise is that of the small turn it really is.
        let r1 = rot1.abs().min(std::f64::consts::PI - rot1.abs());
        let r2 = rot2.abs().min(std::f64::consts::PI - rot2.abs());
        let [a1, a2, a3, a4] = self.alpha;
        let mut eps = |var: f64| -> f64 {
            let n: f64 = rng.sample(StandardNormal);
            n * var.max(0.0).sqrt()
        };
        let h_rot1 = rot1 - eps(a1 * r1 * r1 + a2 * trans * trans);
        let h_trans = trans - eps(a3 * trans * trans + a4 * (r1 * r1 + r2 * r2));
        let h_rot2 = rot2 - eps(a1 * r2 * r2 + a2 * trans * trans);
        let heading = pose[2] + h_rot1;
        [
            pose[0] + h_trans * heading.cos(),
            pose[1] + h_trans * heading.sin(),
            wrap(heading + h_rot2),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn noise_free_model_follows_odometry_from_another_start() {
        let m = OdometryMotion { alpha: [0.0; 4] };
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let prev = [1.0, 2.0, 0.3];
        let cur = [1.5, 2.7, -0.4];
        let start = [-3.0, 0.5, 2.0];
        let got = m.sample(start, prev, cur, &mut rng);
        // Same motion in the start's frame: start ⊕ (prev⁻¹ ⊕ cur).
        let want = compose(start, relative(prev, cur));
        for k in 0..3 {
            assert!((got[k] - want[k]).abs() < 1e-12);
        }
    }
}
