//! Multipath compensation of a ToF frame from the frame's own point cloud (model-based, after
//! Fuchs, ICPR 2010, and Jiménez et al., Image and Vision Computing 2014). Pure Rust, no I/O;
//! the Python face is `omnitof.scan.multipath`.
//!
//! A diffuse point P seen by the camera gets, besides the light of the camera's LEDs, the light
//! that the other lit surfaces send it. The camera sees that light at the longer path
//! LED → Q → P → camera and reads P too far (BENCHMARKS.md, "ToF error budget"). The LEDs light
//! about what the mirrors show (the LEDs sit beside the lens), so the frame's own points are
//! the secondary sources: each pixel Q (on a grid of `stride` pixels) is a Lambertian patch whose
//! radiance the camera measured, L_Q = g_Q·A_Q / (A₁·ρ_m·π) (A₁ the amplitude of an albedo-1
//! target at 1 m, ρ_m the mirror's reflectivity on the way back, g_Q ≥ 1 the light the LEDs send
//! onto Q's surface beside the view per unit of what Q shows, `source_gain`), of area
//! Ω_Q·stride²·D_Q²/cos θ_Q,v
//! (Ω the pixel's solid angle, D the one-way path, θ_v the angle between the view ray and Q's
//! normal). P's irradiance from them, relative to the LEDs' own, is
//!
//! ```text
//! S_P = Σ_Q L_Q·cos θ_P·cos θ_Q·area_Q / |PQ|² · e^{i·k/2·(|PQ| + D_Q − D_P)} / G_P,
//! G_P = ρ_m·η_P·cos θ_P,v / D_P²
//! ```
//!
//! (η_P the LEDs' emission towards P, relative to a coaxial isotropic source; k the phase per
//! metre of measured distance). The camera measured z_P = a_P·e^{i·k·D_P}·(1 + S_P), so the
//! direct light's distance is D_P − arg(1 + S_P)/k. The visibility between P and Q is not
//! tested (the frame does not show what lies between them): in cluttered rooms the sum is too
//! large by what furniture hides (BENCHMARKS.md gives the figures).
//! Optional sources beyond the image (`BeyondView`, `with_beyond_view`) stand for the surfaces
//! the LEDs light outside the view, continued from the image's edge.
//!
//! Normals come from the points of a distance image smoothed over `smooth_radius` pixels of the
//! same mirror (neighbours within `depth_tolerance`), by differences `normal_radius` pixels
//! apart along the row and the column, each towards the side nearer in distance (`normal`).
//! The sum is taken at every `target_stride`-th pixel and shared with the pixels between on the
//! same surface. The result does not depend on the thread count: every pixel's sum runs over
//! the same sources in the same order.

use rayon::prelude::*;

use crate::render::{cross, dot, norm, scale, sub};

/// How the sum is taken (module docs; `omnitof.scan.multipath.MultipathSettings` documents each).
#[derive(Clone, Debug)]
pub struct CompensationParams {
    /// Phase per metre of measured one-way distance, 4π·f_mod/c.
    pub k: f64,
    pub amplitude_at_1m: f64,
    pub mirror_reflectivity: f64,
    pub stride: usize,
    pub target_stride: usize,
    pub normal_radius: usize,
    pub smooth_radius: usize,
    pub depth_tolerance: f64,
    pub min_reflectance: f64,
    pub min_cos: f64,
    pub min_separation: f64,
    pub max_ratio: f64,
    /// Test each source's visibility from the point against the frame's own points (`Heights`).
    pub visibility: bool,
}

/// What is fixed per rig: per pixel (row-major, H·W) where its light leaves the mirror, the
/// reflected unit direction, the path camera → mirror, its mirror (−1: none), its solid angle,
/// the LEDs' relative emission towards it, and how much of its surface's light it stands for as
/// a source (`source_gain`); and the pixels to correct with their windows of distances (the
/// others are only sources).
pub struct Compensator {
    pub width: usize,
    pub height: usize,
    pub origin: Vec<[f64; 3]>,
    pub dir: Vec<[f64; 3]>,
    pub path: Vec<f64>,
    pub label: Vec<i32>,
    pub omega: Vec<f64>,
    pub emission: Vec<f64>,
    /// Per pixel, the factor on its radiance as a source: the LEDs' light that lands on its
    /// surface beside the view, per unit of what the pixel shows (1: none; see the module docs).
    pub source_gain: Vec<f64>,
    pub targets: Vec<u32>,
    pub windows: Vec<[f64; 2]>,
    pub params: CompensationParams,
    /// Sources beyond the image (`BeyondView`; `with_beyond_view`), none by default.
    pub beyond: Vec<BeyondView>,
    /// Per pixel, its index in `targets` (u32::MAX: not a target); filled by `new`.
    window_of: Vec<u32>,
}

/// A secondary source beyond the image: the LEDs light the mirrors, and the scene through them,
/// beyond the camera's view (their cone is wider than the image), so the walls just above and
/// below what the mirrors show, and the floor near the robot, light the seen points too. Such a
/// source is a ray beyond the image, reflected by the pyramid's face it meets (robot frame, as
/// `origin`, `dir`, `path`), that continues the surface of an anchor pixel at the image's edge
/// on the same mirror: it meets the anchor's plane (or the floor, z = 0, below it). Its weight is
/// the anchor's, L·area without the source gain, times `factor` = (the centre's emission along
/// the ray · the ray's cell's solid angle) / (the anchor's emission · its cell's solid angle):
/// the anchor's albedo, lit as the ray's point is.
#[derive(Clone, Copy, Debug)]
pub struct BeyondView {
    pub origin: [f64; 3],
    pub dir: [f64; 3],
    pub path: f64,
    pub anchor: u32,
    pub factor: f64,
}

/// A secondary source: point, unit normal, measured distance and its weight L_Q·area_Q.
#[derive(Clone, Copy)]
struct Source {
    point: [f64; 3],
    normal: [f64; 3],
    distance: f64,
    weight: f64,
}

impl Compensator {
    /// A compensator from the rig's per-pixel arrays (`Compensator`'s fields), checked: the
    /// error names what is wrong.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        width: usize,
        height: usize,
        origin: Vec<[f64; 3]>,
        dir: Vec<[f64; 3]>,
        path: Vec<f64>,
        label: Vec<i32>,
        omega: Vec<f64>,
        emission: Vec<f64>,
        source_gain: Vec<f64>,
        targets: Vec<u32>,
        windows: Vec<[f64; 2]>,
        params: CompensationParams,
    ) -> Result<Compensator, String> {
        let mut c = Compensator {
            width,
            height,
            origin,
            dir,
            path,
            label,
            omega,
            emission,
            source_gain,
            targets,
            windows,
            params,
            beyond: vec![],
            window_of: vec![],
        };
        c.check()?;
        let mut window_of = vec![u32::MAX; width * height];
        for (k, &t) in c.targets.iter().enumerate() {
            window_of[t as usize] = k as u32;
        }
        c.window_of = window_of;
        Ok(c)
    }

    /// The same compensator with sources beyond the image (`BeyondView`), checked.
    pub fn with_beyond_view(mut self, beyond: Vec<BeyondView>) -> Result<Compensator, String> {
        let n = self.width * self.height;
        for b in &beyond {
            if b.anchor as usize >= n {
                return Err("a source beyond the view has its anchor outside the image".into());
            }
            if !(b.factor.is_finite() && b.factor >= 0.0 && b.path.is_finite())
                || b.origin.iter().chain(&b.dir).any(|v| !v.is_finite())
                || (norm(b.dir) - 1.0).abs() >= 1e-6
            {
                return Err("sources beyond the view need finite origins, unit directions, finite paths and factors >= 0".into());
            }
        }
        self.beyond = beyond;
        Ok(self)
    }

    fn check(&self) -> Result<(), String> {
        let n = match self.width.checked_mul(self.height) {
            Some(n) if self.width > 0 && self.height > 0 => n,
            _ => return Err(format!("the image must be at least 1×1 pixels, got {}×{}", self.width, self.height)),
        };
        for (name, len) in [
            ("origins", self.origin.len()),
            ("directions", self.dir.len()),
            ("paths", self.path.len()),
            ("labels", self.label.len()),
            ("solid angles", self.omega.len()),
            ("emission", self.emission.len()),
            ("source gains", self.source_gain.len()),
        ] {
            if len != n {
                return Err(format!("{name}: {len} values for {n} pixels"));
            }
        }
        for (name, values) in [("source gains", &self.source_gain), ("solid angles", &self.omega), ("emission", &self.emission)] {
            if values.iter().any(|g| !(g.is_finite() && *g >= 0.0)) {
                return Err(format!("{name} must be finite and >= 0"));
            }
        }
        // Pixels without a ray (label < 0) carry zeros and an infinite path; every other one a
        // finite origin, a unit direction and a finite path.
        for i in 0..n {
            if !self.origin[i].iter().chain(&self.dir[i]).all(|v| v.is_finite()) {
                return Err(format!("pixel {i}: origins and directions must be finite"));
            }
            if self.label[i] >= 0 && !((norm(self.dir[i]) - 1.0).abs() < 1e-6 && self.path[i].is_finite() && self.path[i] >= 0.0) {
                return Err(format!("pixel {i}: a mirror pixel needs a unit direction and a finite path >= 0"));
            }
        }
        if self.windows.iter().any(|w| !(w[0].is_finite() && w[1].is_finite() && w[0] <= w[1])) {
            return Err("windows must be finite (lo, hi) pairs with lo <= hi".into());
        }
        if self.targets.len() != self.windows.len() {
            return Err(format!("{} targets but {} windows", self.targets.len(), self.windows.len()));
        }
        if self.targets.iter().any(|&t| t as usize >= n) {
            return Err("a target pixel lies outside the image".into());
        }
        let p = &self.params;
        if p.stride == 0 || p.target_stride == 0 || p.normal_radius == 0 {
            return Err("stride, target_stride and normal_radius must be >= 1".into());
        }
        let side = self.width.max(self.height);
        if p.normal_radius > side || p.smooth_radius > side {
            return Err(format!("normal_radius and smooth_radius must be at most the image's side, {side} pixels"));
        }
        // k = 4π·f_mod/c: 1e6 rad/m is a modulation of 24 THz, far beyond any ToF camera's (tens of MHz).
        if !(p.k <= 1e6 && p.amplitude_at_1m <= 1e30 && p.mirror_reflectivity <= 1.0 && p.min_cos <= 1.0) {
            return Err(format!(
                "k must be at most 1e6 rad/m, amplitude_at_1m at most 1e30, mirror_reflectivity and min_cos at most 1 \
                 (got {}, {}, {}, {})",
                p.k, p.amplitude_at_1m, p.mirror_reflectivity, p.min_cos
            ));
        }
        for (name, v) in [
            ("k", p.k),
            ("amplitude_at_1m", p.amplitude_at_1m),
            ("mirror_reflectivity", p.mirror_reflectivity),
            ("min_cos", p.min_cos),
            ("max_ratio", p.max_ratio),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                return Err(format!("{name} must be > 0 and finite, got {v}"));
            }
        }
        for (name, v) in [("depth_tolerance", p.depth_tolerance), ("min_reflectance", p.min_reflectance), ("min_separation", p.min_separation)] {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(format!("{name} must be >= 0 and finite, got {v}"));
            }
        }
        Ok(())
    }

    /// One frame (H·W distances and amplitudes): `out` gets the distances with each target's
    /// interreflection taken out (NaN where it exceeds max_ratio; others as given). Returns how
    /// many targets were corrected or dropped.
    pub fn correct(&self, distance: &[f32], amplitude: &[f32], out: &mut [f32]) -> usize {
        out.copy_from_slice(distance);
        let valid: Vec<bool> = (0..distance.len())
            .map(|i| self.label[i] >= 0 && distance[i].is_finite() && amplitude[i] > 0.0 && self.path[i].is_finite())
            .collect();
        let smooth = self.smoothed(distance, &valid);
        let points: Vec<[f64; 3]> = (0..distance.len())
            .map(|i| {
                let s = smooth[i] - self.path[i];
                let (o, d) = (self.origin[i], self.dir[i]);
                [o[0] + s * d[0], o[1] + s * d[1], o[2] + s * d[2]]
            })
            .collect();
        let p = &self.params;
        let (w, h, st) = (self.width, self.height, p.stride);
        // The sources: every stride-th pixel of every stride-th row, started half a stride in.
        let grid: Vec<usize> = (st / 2..h).step_by(st).flat_map(|r| (st / 2..w).step_by(st).map(move |c| r * w + c)).collect();
        let sources: Vec<Source> = grid
            .into_iter()
            .filter_map(|i| {
                let d = distance[i] as f64;
                let a = amplitude[i] as f64;
                if !valid[i] || a * d * d < p.min_reflectance {
                    return None;
                }
                let n = self.normal(i, &points, &smooth, &valid)?;
                let cos_v = self.incidence(i, n);
                let radiance = self.source_gain[i] * a / (p.amplitude_at_1m * p.mirror_reflectivity * std::f64::consts::PI);
                let area = self.omega[i] * (st * st) as f64 * d * d / cos_v;
                Some(Source { point: points[i], normal: n, distance: d, weight: radiance * area })
            })
            .collect();
        let mut sources = sources;
        sources.extend(self.beyond.iter().filter_map(|b| {
            let i = b.anchor as usize;
            let (d, a) = (distance[i] as f64, amplitude[i] as f64);
            if !valid[i] || a * d * d < p.min_reflectance {
                return None;
            }
            let n = self.normal(i, &points, &smooth, &valid)?;
            let cos_v = self.incidence(i, n);
            // The anchor's L·area per unit of its cell, without the source gain (module docs).
            let weight = a / (p.amplitude_at_1m * p.mirror_reflectivity * std::f64::consts::PI) * self.omega[i] * (st * st) as f64 * d * d / cos_v;
            let (point, normal, s) = continued(b, points[i], n, smooth[i] - self.path[i])?;
            Some(Source { point, normal, distance: b.path + s, weight: weight * b.factor })
        }));
        // Which targets need a correction in this frame: measured within their window.
        let wanted = |i: usize| valid[i] && {
            let t = self.window_of[i];
            t != u32::MAX && {
                let [lo, hi] = self.windows[t as usize];
                let d = distance[i] as f64;
                d >= lo && d <= hi
            }
        };
        // The blockers: the points the sources are drawn from (wrapped readings left out).
        let heights = p.visibility.then(|| {
            let solid: Vec<bool> =
                (0..distance.len()).map(|i| valid[i] && amplitude[i] as f64 * (distance[i] as f64).powi(2) >= p.min_reflectance).collect();
            Heights::new(&points, &solid)
        });
        let ratio_at = |i: usize| -> Option<[f64; 2]> {
            let n = self.normal(i, &points, &smooth, &valid)?;
            let d = distance[i] as f64;
            let cos_v = self.incidence(i, n);
            self.relative_interreflection(points[i], n, d, cos_v, self.emission[i], &sources, heights.as_ref())
        };
        // The sum relative to the direct light changes slowly along a surface: it is taken at
        // the anchors (every target_stride-th pixel of every target_stride-th row) and shared
        // with the targets between them on the same surface (same mirror, distance within
        // depth_tolerance); a target with no such anchor gets its own sum.
        let ts = p.target_stride.max(1);
        let anchors: Vec<usize> =
            self.targets.iter().map(|&t| t as usize).filter(|&i| (i / w) % ts == 0 && (i % w) % ts == 0 && wanted(i)).collect();
        let mut at_anchor: Vec<Option<[f64; 2]>> = vec![None; w * h];
        let sums: Vec<Option<[f64; 2]>> = anchors.par_iter().map(|&i| ratio_at(i)).collect();
        for (&i, s) in anchors.iter().zip(sums) {
            at_anchor[i] = s;
        }
        let corrections: Vec<Option<f64>> = self
            .targets
            .par_iter()
            .map(|&t| {
                let i = t as usize;
                if !wanted(i) {
                    return None;
                }
                let ratio = if at_anchor[i].is_some() || ts == 1 {
                    at_anchor[i]
                } else {
                    self.shared(i, distance, &at_anchor).or_else(|| ratio_at(i))
                }?;
                Some(self.correction(ratio))
            })
            .collect();
        let mut count = 0;
        for (&t, c) in self.targets.iter().zip(corrections) {
            if let Some(c) = c {
                out[t as usize] = (distance[t as usize] as f64 - c) as f32;
                count += 1;
            }
        }
        count
    }

    /// The mean of the anchors' sums around target i (the corners of its target_stride cell)
    /// that lie on i's surface; None if none does.
    fn shared(&self, i: usize, distance: &[f32], at_anchor: &[Option<[f64; 2]>]) -> Option<[f64; 2]> {
        let (w, h, ts) = (self.width, self.height, self.params.target_stride);
        let (row, col) = (i / w, i % w);
        let (r0, c0) = (row / ts * ts, col / ts * ts);
        let (mut re, mut im, mut count) = (0.0, 0.0, 0usize);
        for r in [r0, r0 + ts] {
            for c in [c0, c0 + ts] {
                if r >= h || c >= w {
                    continue;
                }
                let j = r * w + c;
                if let Some([a, b]) = at_anchor[j] {
                    if self.label[j] == self.label[i] && (distance[j] as f64 - distance[i] as f64).abs() <= self.params.depth_tolerance {
                        re += a;
                        im += b;
                        count += 1;
                    }
                }
            }
        }
        (count > 0).then(|| [re / count as f64, im / count as f64])
    }

    /// The distance (m) that the relative interreflection S adds, arg(1 + S)/k; NaN beyond
    /// max_ratio, where the reading is mostly interreflection and the model's error would
    /// exceed what it takes out: the pixel is dropped.
    fn correction(&self, [re, im]: [f64; 2]) -> f64 {
        if re.hypot(im) > self.params.max_ratio || 1.0 + re <= 0.0 {
            return f64::NAN;
        }
        im.atan2(1.0 + re) / self.params.k
    }

    /// S at point x (normal n, measured distance d, cosine of the view's incidence, LED emission η), the
    /// interreflection relative to the direct light (module docs), as (re, im); None where the
    /// LEDs do not light x.
    #[allow(clippy::too_many_arguments)]
    fn relative_interreflection(
        &self,
        x: [f64; 3],
        n: [f64; 3],
        d: f64,
        cos_v: f64,
        emission: f64,
        sources: &[Source],
        heights: Option<&Heights>,
    ) -> Option<[f64; 2]> {
        let p = &self.params;
        let direct = p.mirror_reflectivity * emission * cos_v / (d * d);
        if !(direct > 0.0) {
            return None;
        }
        let (mut re, mut im) = (0.0, 0.0);
        let min_sep2 = p.min_separation * p.min_separation;
        for q in sources {
            let v = sub(q.point, x);
            let along_p = dot(v, n);
            let along_q = -dot(v, q.normal);
            // Each must face the other: cos θ_P > 0 and cos θ_Q > 0 (decided before the root).
            if along_p <= 0.0 || along_q <= 0.0 {
                continue;
            }
            let d2 = dot(v, v);
            if d2 < min_sep2 {
                continue;
            }
            let dist = d2.sqrt();
            if heights.is_some_and(|g| g.blocked(x, n, q.point, q.normal, dist)) {
                continue;
            }
            // cos θ_P·cos θ_Q/|PQ|² = along_p·along_q/|PQ|⁴.
            let gain = q.weight * along_p * along_q / (d2 * d2);
            let (s, c) = sin_cos(0.5 * p.k * (dist + q.distance - d));
            re += gain * c;
            im += gain * s;
        }
        Some([re / direct, im / direct])
    }

    /// The cosine of the view's incidence at pixel i with normal n, at least min_cos.
    fn incidence(&self, i: usize, n: [f64; 3]) -> f64 {
        (-dot(n, self.dir[i])).max(self.params.min_cos)
    }

    /// Distances averaged over the pixels within smooth_radius of the same mirror whose
    /// distance differs by at most depth_tolerance (noise off the normals; depth edges kept).
    fn smoothed(&self, distance: &[f32], valid: &[bool]) -> Vec<f64> {
        let (w, h, r) = (self.width, self.height, self.params.smooth_radius);
        let tol = self.params.depth_tolerance;
        (0..w * h)
            .into_par_iter()
            .map(|i| {
                let d = distance[i] as f64;
                if !valid[i] || r == 0 {
                    return d;
                }
                let (row, col) = (i / w, i % w);
                let (mut sum, mut count) = (0.0, 0usize);
                for rr in row.saturating_sub(r)..(row + r + 1).min(h) {
                    for cc in col.saturating_sub(r)..(col + r + 1).min(w) {
                        let j = rr * w + cc;
                        let dj = distance[j] as f64;
                        if valid[j] && self.label[j] == self.label[i] && (dj - d).abs() <= tol {
                            sum += dj;
                            count += 1;
                        }
                    }
                }
                sum / count as f64
            })
            .collect()
    }

    /// The unit normal at pixel i facing the camera, from the points normal_radius pixels away
    /// along its row and its column (nearer where those are not on i's mirror). Along each, the
    /// side whose distance differs less from i's is taken: at a crease or a depth edge that is
    /// the side on i's own surface (a central difference would mix the two). None if even the
    /// nearest neighbours are missing.
    fn normal(&self, i: usize, points: &[[f64; 3]], smooth: &[f64], valid: &[bool]) -> Option<[f64; 3]> {
        let (w, h) = (self.width as isize, self.height as isize);
        let (row, col) = ((i as isize) / w, (i as isize) % w);
        let same = |r: isize, c: isize| -> Option<usize> {
            if r < 0 || c < 0 || r >= h || c >= w {
                return None;
            }
            let j = (r * w + c) as usize;
            (valid[j] && self.label[j] == self.label[i]).then_some(j)
        };
        // The step along one axis: towards the neighbour (at +k or −k) nearer in distance.
        let step = |before: Option<usize>, after: Option<usize>| -> Option<[f64; 3]> {
            let gap = |j: usize| (smooth[j] - smooth[i]).abs();
            match (before, after) {
                (Some(b), Some(a)) if gap(b) < gap(a) => Some(sub(points[i], points[b])),
                (_, Some(a)) => Some(sub(points[a], points[i])),
                (Some(b), None) => Some(sub(points[i], points[b])),
                (None, None) => None,
            }
        };
        for k in (1..=self.params.normal_radius as isize).rev() {
            let (Some(along_row), Some(along_col)) =
                (step(same(row, col - k), same(row, col + k)), step(same(row - k, col), same(row + k, col)))
            else {
                continue;
            };
            let n = cross(along_row, along_col);
            let len = norm(n);
            if !(len > 0.0) {
                continue;
            }
            let n = scale(n, 1.0 / len);
            return Some(if dot(n, self.dir[i]) > 0.0 { scale(n, -1.0) } else { n });
        }
        None
    }
}

/// What the frame shows of the space between two of its points: per cell of a horizontal grid
/// (robot frame, `HEIGHT_CELL` m), the lowest and highest point seen in it. A segment is taken
/// as blocked where it passes through a cell within that height range: furniture and walls
/// stand on the floor and are seen down to it or to the view's lower edge. Written here: a
/// 2.5D height-interval map of one frame, simpler than any library's voxel map for this use.
struct Heights {
    x0: f64,
    y0: f64,
    nx: usize,
    ny: usize,
    lo: Vec<f32>,
    hi: Vec<f32>,
}

/// The height map's cell (m), the spacing of the tests along a segment (m), how far from each
/// end the tests start (m: the ends' own surfaces fill the cells beside them), and the margin
/// on each cell's height range (m).
const HEIGHT_CELL: f64 = 0.1;
const VISIBILITY_STEP: f64 = 0.15;
const VISIBILITY_MARGIN: f64 = 0.25;
const HEIGHT_TOLERANCE: f64 = 0.05;
/// Cells beyond this many on a side are not kept (a frame's points lie within ±8 m).
const MAX_CELLS: usize = 400;

impl Heights {
    fn new(points: &[[f64; 3]], valid: &[bool]) -> Heights {
        let seen = || points.iter().zip(valid).filter(|(p, &v)| v && p.iter().all(|c| c.is_finite())).map(|(p, _)| p);
        let (mut x0, mut y0, mut x1, mut y1) = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        for p in seen() {
            (x0, y0, x1, y1) = (x0.min(p[0]), y0.min(p[1]), x1.max(p[0]), y1.max(p[1]));
        }
        if !(x0 <= x1 && y0 <= y1) {
            return Heights { x0: 0.0, y0: 0.0, nx: 0, ny: 0, lo: vec![], hi: vec![] };
        }
        let nx = (((x1 - x0) / HEIGHT_CELL) as usize + 1).min(MAX_CELLS);
        let ny = (((y1 - y0) / HEIGHT_CELL) as usize + 1).min(MAX_CELLS);
        let mut g = Heights { x0, y0, nx, ny, lo: vec![f32::INFINITY; nx * ny], hi: vec![f32::NEG_INFINITY; nx * ny] };
        for p in seen() {
            if let Some(c) = g.cell(p[0], p[1]) {
                g.lo[c] = g.lo[c].min(p[2] as f32);
                g.hi[c] = g.hi[c].max(p[2] as f32);
            }
        }
        g
    }

    #[inline]
    fn cell(&self, x: f64, y: f64) -> Option<usize> {
        let (cx, cy) = (((x - self.x0) / HEIGHT_CELL).floor(), ((y - self.y0) / HEIGHT_CELL).floor());
        (cx >= 0.0 && cy >= 0.0 && (cx as usize) < self.nx && (cy as usize) < self.ny).then(|| cy as usize * self.nx + cx as usize)
    }

    /// Whether the segment a → b (length `length`; the ends' surfaces have the unit normals
    /// na, nb) passes through a seen cell at a height it spans. Tests within a cell's diagonal
    /// of either end's plane are skipped: the cells there hold that surface's own points (a
    /// segment leaving a wall at a grazing angle stays beside it for a while).
    fn blocked(&self, a: [f64; 3], na: [f64; 3], b: [f64; 3], nb: [f64; 3], length: f64) -> bool {
        let own = HEIGHT_CELL * std::f64::consts::SQRT_2;
        let steps = (length / VISIBILITY_STEP).ceil() as usize;
        (1..steps).any(|j| {
            let t = j as f64 / steps as f64;
            if t * length < VISIBILITY_MARGIN || (1.0 - t) * length < VISIBILITY_MARGIN {
                return false;
            }
            let p = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2])];
            if dot(sub(p, a), na).abs() < own || dot(sub(p, b), nb).abs() < own {
                return false;
            }
            self.cell(p[0], p[1]).is_some_and(|c| {
                let z = p[2] as f32;
                z >= self.lo[c] - HEIGHT_TOLERANCE as f32 && z <= self.hi[c] + HEIGHT_TOLERANCE as f32
            })
        })
    }
}

/// Where the ray of a source beyond the view meets the surface of its anchor (point x, unit
/// normal n facing the camera, `reach` metres from its mirror): (point, normal, distance along
/// the ray). The anchor's plane, or the floor (z = 0, robot frame) where the plane lies below
/// it. None where the ray does not face the plane or meets it further from the anchor than
/// the anchor's own `reach` (a plane continued that far is a guess).
fn continued(b: &BeyondView, x: [f64; 3], n: [f64; 3], reach: f64) -> Option<([f64; 3], [f64; 3], f64)> {
    let facing = dot(n, b.dir);
    if facing > -1e-3 {
        return None;
    }
    let mut s = dot(n, sub(x, b.origin)) / facing;
    let mut normal = n;
    let mut point = [b.origin[0] + s * b.dir[0], b.origin[1] + s * b.dir[1], b.origin[2] + s * b.dir[2]];
    if point[2] < 0.0 && b.dir[2] < 0.0 {
        s = -b.origin[2] / b.dir[2];
        point = [b.origin[0] + s * b.dir[0], b.origin[1] + s * b.dir[1], 0.0];
        normal = [0.0, 0.0, 1.0];
    }
    (s > 0.0 && norm(sub(point, x)) <= reach).then_some((point, normal, s))
}

/// sin and cos of x by Taylor polynomials after reduction to [−π/2, π/2] (absolute error below
/// 1e-7, far below the phase noise): written here because the standard library's `sin_cos`
/// was two thirds of the sum's time, and no crate in use offers a faster one.
#[inline]
fn sin_cos(x: f64) -> (f64, f64) {
    use std::f64::consts::{FRAC_PI_2, PI, TAU};
    let r = x - (x / TAU).round() * TAU;
    let (r, sign) = if r > FRAC_PI_2 {
        (PI - r, -1.0)
    } else if r < -FRAC_PI_2 {
        (-PI - r, -1.0)
    } else {
        (r, 1.0)
    };
    let z = r * r;
    let s = r * (1.0 + z * (-1.0 / 6.0 + z * (1.0 / 120.0 + z * (-1.0 / 5040.0 + z * (1.0 / 362_880.0 + z * (-1.0 / 39_916_800.0))))));
    let c = 1.0
        + z * (-0.5 + z * (1.0 / 24.0 + z * (-1.0 / 720.0 + z * (1.0 / 40_320.0 + z * (-1.0 / 3_628_800.0 + z / 479_001_600.0)))));
    (s, sign * c)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pinhole-like rig without mirrors: pixel (r, c) looks from the origin along a direction
    /// fanned over ±`half` radians in each axis (tan-spaced), with its solid angle.
    fn fan(w: usize, h: usize, half: f64) -> (Vec<[f64; 3]>, Vec<f64>) {
        let mut dirs = Vec::new();
        let mut omega = Vec::new();
        let step = 2.0 * half / w as f64;
        for r in 0..h {
            for c in 0..w {
                let (ax, ay) = ((c as f64 + 0.5) * step - half, (r as f64 + 0.5) * step - half);
                let v = [ax.tan(), ay.tan(), 1.0];
                let l = norm(v);
                dirs.push(scale(v, 1.0 / l));
                // The solid angle of the pixel: d(tan ax)·d(tan ay)·cos³ of the angle off the axis.
                let (tx, ty) = (ax.tan(), ay.tan());
                omega.push(step * step * (1.0 + tx * tx) * (1.0 + ty * ty) / (1.0 + tx * tx + ty * ty).powf(1.5));
            }
        }
        (dirs, omega)
    }

    fn params() -> CompensationParams {
        CompensationParams {
            k: 4.0 * std::f64::consts::PI * 20e6 / 299_792_458.0,
            amplitude_at_1m: 7300.0,
            mirror_reflectivity: 1.0,
            stride: 1,
            target_stride: 2,
            normal_radius: 1,
            smooth_radius: 0,
            depth_tolerance: 0.1,
            min_reflectance: 0.0,
            min_cos: 0.05,
            min_separation: 0.0,
            max_ratio: 10.0,
            visibility: false,
        }
    }

    #[test]
    fn the_polynomial_sine_and_cosine_match_the_library_s() {
        for i in -2000..=2000 {
            let x = i as f64 * 0.0123;
            let (s, c) = sin_cos(x);
            assert!((s - x.sin()).abs() < 1e-7 && (c - x.cos()).abs() < 1e-7, "{x}: {s} {c}");
        }
    }

    /// Wall A (z = 3, facing the camera) meets wall B (x = 0.8) in a corner, seen by a fan of
    /// w × h pixels `half` radians either side of the axis; a coaxial point light at the camera,
    /// albedo 0.6, amplitude scale 7300. The target: the middle row's pixel on A nearest to
    /// x = 0.5 (0.3 m from the corner).
    struct Corner {
        dir: Vec<[f64; 3]>,
        omega: Vec<f64>,
        distance: Vec<f32>,
        amplitude: Vec<f32>,
        target: usize,
        rho: f64,
        c: f64,
    }

    fn corner(w: usize, h: usize, half: f64) -> Corner {
        let (dir, omega) = fan(w, h, half);
        let (rho, c) = (0.6, 7300.0);
        let (mut distance, mut amplitude) = (vec![0.0f32; w * h], vec![0.0f32; w * h]);
        for (i, d) in dir.iter().enumerate() {
            let t_a = 3.0 / d[2];
            let (t, cos) = if t_a * d[0] < 0.8 { (t_a, d[2]) } else { (0.8 / d[0], d[0]) };
            distance[i] = t as f32;
            amplitude[i] = (c * rho * cos / (t * t)) as f32;
        }
        let row = h / 2;
        let col = (0..w).min_by(|&a, &b| {
            let x = |j: usize| (3.0 / dir[row * w + j][2] * dir[row * w + j][0] - 0.5).abs();
            x(a).total_cmp(&x(b))
        }).unwrap();
        Corner { dir, omega, distance, amplitude, target: row * w + col, rho, c }
    }

    #[test]
    fn a_source_gain_scales_the_interreflection_and_max_ratio_drops_the_pixel() {
        let (w, h) = (48, 48);
        let Corner { dir, omega, distance, amplitude, target, c, .. } = corner(w, h, 0.6);
        let run = |gain: f64, max_ratio: f64| -> f32 {
            let params = CompensationParams { target_stride: 1, amplitude_at_1m: c, min_cos: 1e-3, max_ratio, ..params() };
            let comp = Compensator::new(w, h, vec![[0.0; 3]; w * h], dir.clone(), vec![0.0; w * h], vec![0; w * h],
                omega.clone(), vec![1.0; w * h], vec![gain; w * h], vec![target as u32], vec![[0.0, 10.0]], params).unwrap();
            let mut out = vec![0.0f32; w * h];
            assert_eq!(comp.correct(&distance, &amplitude, &mut out), 1);
            distance[target] - out[target]
        };
        let (one, two, three) = (run(1.0, 10.0) as f64, run(2.0, 10.0) as f64, run(3.0, 10.0) as f64);
        assert!(one > 0.005, "the corner matters: {one} m");
        // The gain multiplies S = a + ib: tan(k·c_g) = g·b/(1 + g·a). Gains 1 and 2 give a and b;
        // gain 3 must then give atan2(3b, 1 + 3a)/k.
        let k = params().k;
        let (t1, t2) = ((k * one).tan(), (k * two).tan());
        let a = (2.0 * t1 - t2) / (2.0 * (t2 - t1));
        let b = t1 * (1.0 + a);
        let want = (3.0 * b).atan2(1.0 + 3.0 * a) / k;
        assert!((three - want).abs() < 0.01 * want, "gain 3: {three} m, from gains 1 and 2: {want} m (S = {a} + {b}i)");
        assert!(two > 1.5 * one, "gain 1: {one} m, gain 2: {two} m");
        assert_eq!(run(0.0, 10.0), 0.0, "sources that stand for nothing send nothing");
        assert!(run(1.0, 1e-6).is_nan(), "beyond max_ratio the pixel is dropped");
    }

    #[test]
    fn a_corner_gives_the_quadrature_of_the_neighbouring_wall() {
        // Wall A (z = 3, facing the camera) meets wall B (x = 0.8) in a corner; a coaxial point
        // light at the camera, albedo 0.6. For a pixel on A 0.3 m from the corner, the
        // compensator's sum over B's pixels against a quadrature over the part of B the fan sees:
        // S = ∫ (ρ·G_Q/π)·cos θ_P·cos θ_Q/d² · e^{i·k/2·(d + |Q| − |P|)} dA / G_P.
        let (w, h, half) = (64, 64, 0.6);
        let Corner { dir, omega, distance, amplitude, target, rho, c } = corner(w, h, half);
        let params = CompensationParams { target_stride: 1, mirror_reflectivity: 1.0, amplitude_at_1m: c, min_cos: 1e-3, ..params() };
        let k = params.k;
        let comp = Compensator::new(w, h, vec![[0.0; 3]; w * h], dir.clone(), vec![0.0; w * h], vec![0; w * h], omega,
            vec![1.0; w * h], vec![1.0; w * h], vec![target as u32], vec![[0.0, 10.0]], params).unwrap();
        let mut out = vec![0.0f32; w * h];
        assert_eq!(comp.correct(&distance, &amplitude, &mut out), 1);
        let got = (distance[target] - out[target]) as f64;

        let p = scale(dir[target], distance[target] as f64);
        let want = corner_quadrature(p, half, 0.8 / half.tan(), k, rho);
        // 1.60 against 1.70 cm: the sources are whole pixels, sampled at their centres.
        assert!((got - want).abs() < 0.1 * want.abs(), "compensator {got} m, quadrature {want} m");
        // Nothing stands between the two walls: the visibility test must keep every source
        // (the segments that run along B to their source stay within its cells).
        let seen = CompensationParams { visibility: true, ..comp.params.clone() };
        let comp = Compensator::new(w, h, vec![[0.0; 3]; w * h], dir.clone(), vec![0.0; w * h], vec![0; w * h],
            comp.omega.clone(), vec![1.0; w * h], vec![1.0; w * h], vec![target as u32], vec![[0.0, 10.0]], seen).unwrap();
        comp.correct(&distance, &amplitude, &mut out);
        assert_eq!((distance[target] - out[target]) as f64, got, "with the visibility test");
    }

    /// For `corner`'s point p on wall A, the interreflection's distance arg(1 + S)/k by a
    /// quadrature over wall B (x = 0.8) from z0 to 3, within the fan's spread |y| ≤ z·tan(half):
    /// S = ∫ (ρ·G_Q/π)·cos θ_P·cos θ_Q/d² · e^{i·k/2·(d + |Q| − |P|)} dA / G_P.
    fn corner_quadrature(p: [f64; 3], half: f64, z0: f64, k: f64, rho: f64) -> f64 {
        let g_p = (3.0 / norm(p)) / dot(p, p);
        let tan = half.tan();
        let (n_z, n_y) = (600, 600);
        let z1 = 3.0;
        let (mut re, mut im) = (0.0, 0.0);
        for iz in 0..n_z {
            let z = z0 + (iz as f64 + 0.5) * (z1 - z0) / n_z as f64;
            let y_max = z * tan;
            let dy = 2.0 * y_max / n_y as f64;
            for iy in 0..n_y {
                let q = [0.8, -y_max + (iy as f64 + 0.5) * dy, z];
                let v = sub(q, p);
                let d = norm(v);
                let cos_p = (p[2] - q[2]) / d; // A's normal is −z, and Q lies in front of it (z < 3)
                let cos_q = (0.8 - p[0]) / d;
                let g_q = (0.8 / norm(q)) / dot(q, q);
                let gain = rho * g_q / std::f64::consts::PI * cos_p * cos_q / (d * d) * dy * (z1 - z0) / n_z as f64;
                let (s, co) = (0.5 * k * (d + norm(q) - norm(p))).sin_cos();
                re += gain * co;
                im += gain * s;
            }
        }
        let (re, im) = (re / g_p, im / g_p);
        assert!(re.hypot(im) > 0.02, "the corner matters: |S| = {}", re.hypot(im));
        im.atan2(1.0 + re) / k
    }

    #[test]
    fn sources_beyond_the_view_continue_the_wall_at_the_images_edge() {
        // `corner`'s fan sees wall B from z = 0.8/tan(0.6) on; rays beyond its last column, out
        // to 0.9 rad, continue B (their anchors: the last column's pixels, on B) down to
        // z = 0.8/tan(0.9). What they add must be what the quadrature over that part of B adds
        // (the in-view sum's own error, whole pixels sampled at their centres, cancels).
        let (w, h, half) = (64, 64, 0.6);
        let Corner { dir, omega, distance, amplitude, target, rho, c } = corner(w, h, half);
        let params = CompensationParams { target_stride: 1, mirror_reflectivity: 1.0, amplitude_at_1m: c, min_cos: 1e-3, ..params() };
        let k = params.k;
        let step = 2.0 * half / w as f64;
        let mut beyond = Vec::new();
        let mut ax = half + 0.5 * step;
        while ax < 0.9 {
            for r in 0..h {
                let ay = (r as f64 + 0.5) * step - half;
                let (tx, ty) = (ax.tan(), ay.tan());
                let v = [tx, ty, 1.0];
                let cell = step * step * (1.0 + tx * tx) * (1.0 + ty * ty) / (1.0 + tx * tx + ty * ty).powf(1.5);
                let anchor = r * w + w - 1;
                beyond.push(BeyondView { origin: [0.0; 3], dir: scale(v, 1.0 / norm(v)), path: 0.0, anchor: anchor as u32, factor: cell / omega[anchor] });
            }
            ax += step;
        }
        let run = |beyond: Vec<BeyondView>| -> f64 {
            let comp = Compensator::new(w, h, vec![[0.0; 3]; w * h], dir.clone(), vec![0.0; w * h], vec![0; w * h],
                omega.clone(), vec![1.0; w * h], vec![1.0; w * h], vec![target as u32], vec![[0.0, 10.0]], params.clone())
                .unwrap()
                .with_beyond_view(beyond)
                .unwrap();
            let mut out = vec![0.0f32; w * h];
            assert_eq!(comp.correct(&distance, &amplitude, &mut out), 1);
            (distance[target] - out[target]) as f64
        };
        let p = scale(dir[target], distance[target] as f64);
        let (seen, wider) = (corner_quadrature(p, half, 0.8 / half.tan(), k, rho), corner_quadrature(p, half, 0.8 / 0.9f64.tan(), k, rho));
        assert!(wider > 1.1 * seen, "the part beyond the view matters: {seen} against {wider} m");
        let (without, with) = (run(vec![]), run(beyond));
        let (added, want) = (with - without, wider - seen);
        assert!((added - want).abs() < 0.1 * want, "beyond the view adds {added} m, the quadrature {want} m");
    }

    #[test]
    fn a_slab_between_two_points_blocks_them_and_their_own_surfaces_do_not() {
        // A slab at x = 1 (|y| <= 1, 0 <= z <= 1) seen point by point, walls at x = 0 and x = 2.
        let mut points = Vec::new();
        for iy in -10..=10 {
            for iz in 0..=10 {
                let (y, z) = (iy as f64 * 0.1, iz as f64 * 0.1);
                points.extend([[1.0, y, z], [0.0, y, z], [2.0, y, z]]);
            }
        }
        let g = Heights::new(&points, &vec![true; points.len()]);
        let (west, east) = ([1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]);
        let test = |a: [f64; 3], b: [f64; 3]| g.blocked(a, west, b, east, norm(sub(b, a)));
        assert!(test([0.0, 0.0, 0.5], [2.0, 0.0, 0.5]), "through the slab");
        assert!(test([0.0, 0.0, 0.5], [2.0, 0.0, 1.4]), "through its top edge (z 0.95 at the slab)");
        assert!(!test([0.0, 0.0, 1.2], [2.0, 0.0, 1.4]), "over it");
        assert!(!test([0.0, 0.0, 0.5], [0.0, 0.9, 0.5].map(|v| v + 0.0)), "along the wall it stands on");
        // Along the west wall at a grazing angle, then out to the east wall beyond the slab's end.
        assert!(!test([0.0, -0.9, 0.5], [0.3, 0.95, 0.5]), "beside its own wall");
        assert!(!g.blocked([0.0, 1.6, 0.5], west, [2.0, 1.6, 0.5], east, 2.0), "beside the slab");
    }

    #[test]
    fn a_ray_beyond_the_view_meets_its_anchors_plane_or_the_floor() {
        // The wall x = 2 (normal −x, towards the camera at x = 0.4 m up); anchor at (2, 0, 0.5).
        let (x, n) = ([2.0, 0.0, 0.5], [-1.0, 0.0, 0.0]);
        let ray = |d: [f64; 3]| BeyondView { origin: [0.0, 0.0, 0.4], dir: scale(d, 1.0 / norm(d)), path: 0.1, anchor: 0, factor: 1.0 };
        let (q, normal, s) = continued(&ray([1.0, 0.0, 0.2]), x, n, 2.0).unwrap();
        assert!(norm(sub(q, [2.0, 0.0, 0.8])) < 1e-12 && normal == n && (s - 2.0 * 1.04f64.sqrt()).abs() < 1e-12);
        // Down so steeply that the wall would be met below the floor: the floor, 0.8 m out.
        let (q, normal, _) = continued(&ray([1.0, 0.0, -0.5]), x, n, 2.0).unwrap();
        assert!(norm(sub(q, [0.8, 0.0, 0.0])) < 1e-12 && normal == [0.0, 0.0, 1.0]);
        assert!(continued(&ray([0.0, 1.0, 0.0]), x, n, 2.0).is_none(), "parallel to the wall");
        assert!(continued(&ray([1.0, 0.0, 0.2]), x, n, 0.2).is_none(), "further from the anchor than its reach");
    }

    #[test]
    fn a_single_wall_sends_itself_nothing_and_keeps_its_distances() {
        // One plane z = 3 seen square-on: no point sees another (cos θ = 0), so no correction.
        let (w, h) = (24, 24);
        let (dir, omega) = fan(w, h, 0.3);
        let distance: Vec<f32> = dir.iter().map(|d| (3.0 / d[2]) as f32).collect();
        let amplitude = vec![1000.0f32; w * h];
        let c = Compensator::new(
            w,
            h,
            vec![[0.0; 3]; w * h],
            dir,
            vec![0.0; w * h],
            vec![0; w * h],
            omega,
            vec![1.0; w * h],
            vec![1.0; w * h],
            (0..(w * h) as u32).collect(),
            vec![[0.0, 10.0]; w * h],
            params(),
        )
        .unwrap();
        let mut out = vec![0.0f32; w * h];
        c.correct(&distance, &amplitude, &mut out);
        for (a, b) in out.iter().zip(&distance) {
            assert!((a - b).abs() < 1e-6, "{a} {b}");
        }
    }
}
