//! Where the light comes from: the camera's LEDs (beside the lens, not at its centre), their
//! images in the mirrors, and light that reaches a surface from another surface (multipath).
//! Pure Rust, used by the renderer (render.rs). Frames and units as there.
//!
//! Light model. An LED at L (camera frame, a few cm from the optical centre) lights a world
//! point x directly if the segment L→x crosses no mirror, and through mirror m if the segment
//! from x to L's image in m's plane, L'_m, crosses the plane inside m's outline (the unfolded
//! path; its length |x − L'_m| is the light's path LED → mirror → x). Each such path gives the
//! irradiance factor
//!
//! ```text
//! gain = w · cosᵖ(ε) · ρ_m · cos(θ_x) / ℓ²
//! ```
//!
//! with w = 1/(number of LEDs), ε the emission angle from the optical axis (the LED's profile,
//! exponent p), ρ_m the mirror's reflectivity (1 directly), θ_x the incidence at x and ℓ the
//! path's length. An LED at the camera centre with p = 0 gives back the coaxial model of
//! render.rs (ρ_m·cos θ/r²). With no path, x is dark.
//!
//! Multipath: from a diffuse point P seen by the camera, secondary rays are drawn cosine-weighted
//! about P's normal; where one meets a diffuse Q, Q's light paths (checked for occlusion by the
//! scene) give P the extra radiance ρ_P·ρ_Q·gain/M per ray (M rays: the Monte-Carlo estimate of
//! ρ_P/π·∫L_Q cos dω with the pdf cos/π), with the path camera → P → Q → LED. Random numbers
//! come from a SplitMix64 hash of (seed, pose, pixel, ray), so frames do not depend on threads.

use rayon::prelude::*;

use crate::render::{add, cross, dot, norm, reflect_point, rotate, scale, sub, Kind, Mailbox, Mirror, Scene, SubRay, T_MIN};

/// The LEDs (camera frame, metres), the exponent p of their emission profile cosᵖ(ε), and
/// the cosine of the largest emission angle (the LEDs' optics and the housing let nothing out
/// beyond it; −1: no limit).
#[derive(Clone, Debug, PartialEq)]
pub struct Illumination {
    pub leds: Vec<[f64; 3]>,
    pub profile_exponent: f64,
    pub min_cos: f64,
}

impl Illumination {
    /// The coaxial point source of the simple model: one isotropic LED at the camera centre.
    pub fn coaxial() -> Illumination {
        Illumination { leds: vec![[0.0; 3]], profile_exponent: 0.0, min_cos: -1.0 }
    }

    pub fn check(&self) -> Result<(), String> {
        if self.leds.is_empty() || self.leds.iter().flatten().any(|v| !v.is_finite()) {
            return Err("illumination needs at least one LED with finite coordinates".into());
        }
        if !(self.profile_exponent >= 0.0 && self.profile_exponent.is_finite()) {
            return Err("the LEDs' profile exponent must be >= 0".into());
        }
        if !(-1.0..=1.0).contains(&self.min_cos) {
            return Err("the cosine of the LEDs' largest emission angle must lie in [-1, 1]".into());
        }
        Ok(())
    }
}

#[derive(Clone, Debug)]
struct WorldMirror {
    normal: [f64; 3],
    d: f64,
    polygon: Vec<[f64; 3]>,
    reflectivity: f64,
    /// The optical axis mirrored in this mirror's plane: the LED's emission angle of the light
    /// that reaches x through the mirror is the angle between x − (LED's image) and this axis,
    /// so no mirror point has to be computed for it.
    axis: [f64; 3],
}

impl WorldMirror {
    /// Whether the segment a→b crosses the plane inside the outline.
    fn crosses(&self, a: [f64; 3], b: [f64; 3]) -> bool {
        let (da, db) = (dot(self.normal, a) - self.d, dot(self.normal, b) - self.d);
        if da * db >= 0.0 {
            return false;
        }
        let p = add(a, scale(sub(b, a), da / (da - db)));
        let k = self.polygon.len();
        let (mut pos, mut neg) = (false, false);
        for i in 0..k {
            let (u, v) = (self.polygon[i], self.polygon[(i + 1) % k]);
            let side = dot(self.normal, cross(sub(v, u), sub(p, u)));
            pos |= side > 0.0;
            neg |= side < 0.0;
        }
        !(pos && neg)
    }
}

/// An LED, or its image in a mirror, in the world frame. For an image, `cone` holds the
/// inward normals of the planes through the image and each edge of the mirror's outline: a
/// point on the mirror's reflective side is lit through the mirror iff it lies inside all of
/// them (the segment to the image then crosses the outline), a few dot products instead of a
/// plane crossing and a polygon test for every source. `depth` is the image's signed distance
/// to the mirror's plane (> 0: behind it), fixed per pose.
#[derive(Clone, Debug)]
struct Source {
    position: [f64; 3],
    mirror: Option<usize>,
    cone: Vec<[f64; 3]>,
    depth: f64,
}

/// The light sources of one pose, in the world frame.
#[derive(Clone, Debug)]
pub struct PoseLight {
    sources: Vec<Source>,
    direct_bits: u64,
    mirrors: Vec<WorldMirror>,
    axis: [f64; 3],
    weight: f64,
    exponent: f64,
    min_cos: f64,
}

impl PoseLight {
    /// The LEDs and their mirror images for the camera at world_T_camera (3×4). Everything that
    /// does not depend on the lit point is computed here, once per pose.
    pub fn new(light: &Illumination, camera_mirrors: &[Mirror], m: &[[f64; 4]; 3]) -> PoseLight {
        let t = [m[0][3], m[1][3], m[2][3]];
        let axis = rotate(m, [0.0, 0.0, 1.0]);
        let world: Vec<WorldMirror> = camera_mirrors
            .iter()
            .map(|mi| {
                let normal = rotate(m, mi.normal);
                WorldMirror {
                    normal,
                    d: mi.d + dot(normal, t),
                    polygon: mi.polygon.iter().map(|&p| add(rotate(m, p), t)).collect(),
                    reflectivity: mi.reflectivity,
                    axis: sub(axis, scale(normal, 2.0 * dot(axis, normal))),
                }
            })
            .collect();
        let mut sources = Vec::new();
        for &l in &light.leds {
            let led = add(rotate(m, l), t);
            sources.push(Source { position: led, mirror: None, cone: vec![], depth: 0.0 });
            for (k, (mi, camera_mirror)) in world.iter().zip(camera_mirrors).enumerate() {
                // Only an LED in front of a mirror's reflective side has an image in it; decided
                // in the camera frame, so that every pose has the same sources in the same order
                // (`candidate_masks` numbers them once for all poses).
                if dot(camera_mirror.normal, l) < camera_mirror.d {
                    let image = reflect_point(led, mi.normal, mi.d);
                    let n = mi.polygon.len();
                    let centroid = scale(mi.polygon.iter().fold([0.0; 3], |a, &p| add(a, p)), 1.0 / n as f64);
                    let cone = (0..n)
                        .map(|i| {
                            let c = cross(sub(mi.polygon[i], image), sub(mi.polygon[(i + 1) % n], image));
                            if dot(c, sub(centroid, image)) < 0.0 { scale(c, -1.0) } else { c }
                        })
                        .collect();
                    let depth = dot(mi.normal, image) - mi.d;
                    sources.push(Source { position: image, mirror: Some(k), cone, depth });
                }
            }
        }
        let direct_bits = sources.iter().take(MASK_BITS).enumerate().filter(|(_, s)| s.mirror.is_none()).fold(0u64, |m, (i, _)| m | 1 << i);
        PoseLight { sources, direct_bits, mirrors: world, axis, weight: 1.0 / light.leds.len() as f64, exponent: light.profile_exponent, min_cos: light.min_cos }
    }

    /// Whether the emission direction v (v·axis = `along`) lies clearly beyond the largest
    /// emission angle: a test without the square root and the division of cos ε = along/|v|,
    /// with a margin far above rounding, so that only directions the exact test would also
    /// refuse are refused here (most of the LEDs' direct paths to points seen in the mirrors).
    #[inline]
    fn beyond_cone(&self, along: f64, v: [f64; 3]) -> bool {
        self.min_cos > 0.0 && (along < 0.0 || along * along < self.min_cos * self.min_cos * dot(v, v) * (1.0 - 1e-9))
    }

    /// cosᵖ(ε) of the emission profile; the common exponents without `powf`.
    #[inline]
    fn profile(&self, cos_e: f64) -> f64 {
        let c = cos_e.max(0.0);
        match self.exponent {
            e if e == 0.0 => 1.0,
            e if e == 1.0 => c,
            e if e == 2.0 => c * c,
            e => c.powf(e),
        }
    }

    /// Calls `f(gain, length)` for every light path from an LED to the point `x` whose unit
    /// normal `n` faces the side the light must come from (module docs). With `occlusion`,
    /// paths the scene blocks are left out (the mirrors are not part of the scene), tested once
    /// per mirror and once for the LEDs' direct light. Sources
    /// whose bit (in the order of `sources`) is clear in `candidates` are skipped untested;
    /// `candidate_masks` clears only those that light no point of the camera ray that x lies on
    /// (and the renderer the direct LEDs' bits beyond their reach), so the result is the same
    /// as with every bit set (`ALL_SOURCES`).
    #[allow(clippy::too_many_arguments)]
    pub fn paths(
        &self,
        scene: &Scene,
        x: [f64; 3],
        n: [f64; 3],
        candidates: u64,
        occlusion: bool,
        mail: &mut Mailbox,
        mut f: impl FnMut(f64, f64),
    ) {
        // The candidate sources in their order: the set bits, then any beyond the mask's 64.
        let masked = self.sources.len().min(MASK_BITS);
        let mut bits = if masked == MASK_BITS { candidates } else { candidates & ((1u64 << masked) - 1) };
        let chosen = std::iter::from_fn(move || {
            (bits != 0).then(|| {
                let i = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                &self.sources[i]
            })
        })
        .chain(&self.sources[masked..]);
        let (mut tested, mut blocked) = (0u64, 0u64);
        for s in chosen {
            // x's signed distance to an image's mirror plane (< 0: on its reflective side): an
            // image lights only points on that side.
            let da = s.mirror.map_or(-1.0, |k| dot(self.mirrors[k].normal, x) - self.mirrors[k].d);
            if da >= 0.0 {
                continue;
            }
            // rel: from the source (an LED or its image) to x, a straight (unfolded) path.
            let rel = sub(x, s.position);
            // x's side must face the light: cos θ_x = −n·rel/|rel| > 0 (decided before the root).
            let facing = -dot(n, rel);
            if !(facing > 0.0) {
                continue;
            }
            let (cos_e, length, inv_length, reach, reflectivity) = match s.mirror {
                None => {
                    // The LED emits towards x itself; nothing beyond the largest emission angle
                    // (an isotropic source, p = 0, in every direction).
                    let along = dot(rel, self.axis);
                    if self.beyond_cone(along, rel) {
                        continue;
                    }
                    let length = norm(rel);
                    let inv_length = 1.0 / length;
                    let cos_e = along * inv_length;
                    if cos_e < self.min_cos || self.mirrors.iter().any(|mi| mi.crosses(x, s.position)) {
                        continue;
                    }
                    (cos_e, length, inv_length, length, 1.0)
                }
                Some(k) => {
                    let mi = &self.mirrors[k];
                    if s.cone.iter().any(|&c| dot(c, rel) < 0.0) {
                        continue;
                    }
                    // The LED emits towards the mirror point, along rel mirrored in the plane.
                    let along = dot(rel, mi.axis);
                    if self.beyond_cone(along, rel) {
                        continue;
                    }
                    let length = norm(rel);
                    let inv_length = 1.0 / length;
                    let cos_e = along * inv_length;
                    if cos_e < self.min_cos {
                        continue;
                    }
                    // The light leaves the mirror at the point where rel crosses its plane.
                    (cos_e, length, inv_length, length * da / (da - s.depth), mi.reflectivity)
                }
            };
            if occlusion {
                // One test per mirror (bit k; the direct light bit 63; a mirror past the 63rd is
                // tested for every path): the LEDs' images in a mirror lie a few centimetres
                // apart, so the scene blocks their paths from x alike but at shadows' edges.
                let bit = match s.mirror {
                    None => 1u64 << 63,
                    Some(k) if k < 63 => 1u64 << k,
                    Some(_) => 0,
                };
                let occluded = if tested & bit != 0 {
                    blocked & bit != 0
                } else {
                    // Unit direction from x towards where the light leaves the last optical surface.
                    let dir = scale(rel, -inv_length);
                    let occluded = scene.occluded(x, dir, T_MIN, reach * (1.0 - 1e-9), mail);
                    tested |= bit;
                    blocked |= if occluded { bit } else { 0 };
                    occluded
                };
                if occluded {
                    continue;
                }
            }
            let cos_x = facing * inv_length;
            f(self.weight * self.profile(cos_e) * reflectivity * cos_x * inv_length * inv_length, length);
        }
    }

    /// Light that reaches the diffuse point `p` (facing normal `n`) from the scene along a
    /// direction drawn from `u` (two uniforms in [0, 1)): `f(gain, length)` per light path of
    /// the secondary point Q, gain already multiplied by Q's albedo, length = |P − Q| + the
    /// path from an LED to Q. The caller scales by ρ_P and the number of rays.
    pub fn bounce(&self, scene: &Scene, p: [f64; 3], n: [f64; 3], u: [f64; 2], mail: &mut Mailbox, mut f: impl FnMut(f64, f64)) {
        let dir = cosine_direction(n, u);
        let Some(hit) = scene.intersect_with(p, dir, T_MIN, f64::INFINITY, mail) else { return };
        let q = add(p, scale(dir, hit.t));
        let m = scene.material(hit.material);
        if m.albedo <= 0.0 || (m.kind == Kind::Grid && !m.on_bar(q, hit.normal)) {
            return;
        }
        self.paths(scene, q, hit.normal, ALL_SOURCES, true, mail, |gain, length| f(m.albedo * gain, hit.t + length));
    }
}

/// A candidate mask with every source set: nothing is skipped.
pub const ALL_SOURCES: u64 = u64::MAX;
/// Sources beyond the first this many have no bit and are always tested.
const MASK_BITS: usize = 64;

/// What a camera sub-ray needs of the light sources (`candidate_masks`): the sources that can
/// light some point of it (bit i for source i in `PoseLight`'s order, which does not depend on
/// the pose), and how far along it (metres from where it leaves the optics) the LEDs' direct
/// light can reach at most.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SubRayLight {
    pub candidates: u64,
    pub direct_reach: f64,
}

impl SubRayLight {
    /// Every source, everywhere: nothing is skipped.
    pub const ALL: SubRayLight = SubRayLight { candidates: ALL_SOURCES, direct_reach: f64::INFINITY };
}

/// Per camera sub-ray (camera frame, as `Rig::rays`), which light sources of `PoseLight::new(light,
/// mirrors, ·)` can light its points, and up to where (`SubRayLight`). The sources are rigid
/// with the camera, so this holds at every pose; `paths` then skips the others at the sub-ray's
/// first surface: the images in the mirrors the ray does not look through, and the LEDs' direct
/// light beyond the few centimetres where the ray, leaving its mirror, is still inside their
/// 40° cone. A superset by construction: a source is left out only where its tests in `paths`
/// that do not depend on the surface fail, with a margin far above rounding.
pub fn candidate_masks(light: &Illumination, mirrors: &[Mirror], rays: &[SubRay]) -> Vec<SubRayLight> {
    const IDENTITY: [[f64; 4]; 3] = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]];
    let camera = PoseLight::new(light, mirrors, &IDENTITY);
    rays.par_iter()
        .map(|ray| {
            let mut out = SubRayLight { candidates: ALL_SOURCES, direct_reach: 0.0 };
            if ray.g2 <= 0.0 {
                out.candidates = 0;
                return out;
            }
            for (i, s) in camera.sources.iter().enumerate() {
                match camera.reach(s, ray.origin, ray.dir) {
                    None if i < MASK_BITS => out.candidates &= !(1 << i),
                    Some(t) if s.mirror.is_none() => out.direct_reach = out.direct_reach.max(t),
                    _ => {}
                }
            }
            out
        })
        .collect()
}

impl PoseLight {
    /// The bits of the LEDs' direct sources (not their images) among the first 64 sources.
    pub fn direct_bits(&self) -> u64 {
        self.direct_bits
    }

    /// The largest t >= 0 (infinity included) up to which source `s` may light the points
    /// o + t·d (camera frame, d unit); None if it lights none. An image: the interval of t where
    /// every linear test holds (x on the mirror's reflective side, inside the cone through its
    /// outline). The direct LED: where the ray lies within the emission cone. Each widened by a
    /// margin, so that every t where `paths` could find the source lighting is covered.
    fn reach(&self, s: &Source, o: [f64; 3], d: [f64; 3]) -> Option<f64> {
        let widen = |t: f64| t + 1e-6 * (1.0 + t.abs());
        match s.mirror {
            Some(k) => {
                let mi = &self.mirrors[k];
                let (mut lo, mut hi) = (0.0f64, f64::INFINITY);
                // Each test reads g0 + g1·t >= 0.
                let mut keep = |g0: f64, g1: f64| {
                    if g1.abs() < 1e-300 {
                        if g0 < 0.0 {
                            hi = -1.0;
                        }
                        return;
                    }
                    let root = -g0 / g1;
                    let margin = 1e-6 * (1.0 + root.abs());
                    if g1 > 0.0 { lo = lo.max(root - margin) } else { hi = hi.min(root + margin) }
                };
                // On the reflective side: n·x − d < 0.
                keep(-(dot(mi.normal, o) - mi.d), -dot(mi.normal, d));
                for &c in &s.cone {
                    keep(dot(c, sub(o, s.position)), dot(c, d));
                }
                (lo <= hi).then_some(hi)
            }
            None => {
                if self.min_cos <= 0.0 {
                    return Some(f64::INFINITY);
                }
                // along(t) = p + q·t >= 0 and f(t) = along² − c²·|x − L|² >= 0, with c² a
                // millionth smaller than min_cos² (the margin): the largest such t >= 0.
                let r0 = sub(o, s.position);
                let (p, q) = (dot(r0, self.axis), dot(d, self.axis));
                let c2 = self.min_cos * self.min_cos * (1.0 - 1e-6);
                let (a, b, c) = (q * q - c2, 2.0 * (p * q - c2 * dot(r0, d)), p * p - c2 * dot(r0, r0));
                let f = |t: f64| (a * t + b) * t + c;
                // The t >= 0 where along >= 0: [lo, hi].
                let (lo, hi) = if q > 0.0 {
                    ((-p / q).max(0.0), f64::INFINITY)
                } else if q < 0.0 {
                    (0.0, -p / q)
                } else {
                    (0.0, if p >= 0.0 { f64::INFINITY } else { -1.0 })
                };
                if !(lo <= hi) {
                    return None;
                }
                if hi.is_infinite() {
                    if a > 0.0 || (a == 0.0 && (b > 0.0 || (b == 0.0 && c >= 0.0))) {
                        return Some(f64::INFINITY);
                    }
                } else if f(hi) >= 0.0 {
                    return Some(widen(hi));
                }
                // f < 0 at the far end: the last t where f >= 0 is a root of f, if any in [lo, hi).
                let last = if a == 0.0 {
                    (b < 0.0).then(|| -c / b)
                } else {
                    let disc = b * b - 4.0 * a * c;
                    if disc < 0.0 {
                        None // f has the sign of a everywhere; negative here
                    } else {
                        // Roots without cancellation (Numerical Recipes' form).
                        let h = -0.5 * (b + b.signum() * disc.sqrt());
                        let (r1, r2) = if h == 0.0 { (0.0, 0.0) } else { (h / a, c / h) };
                        let (r1, r2) = (r1.min(r2), r1.max(r2));
                        // Concave: f >= 0 on [r1, r2]; convex: on t <= r1 (and t >= r2, beyond hi).
                        Some(if a < 0.0 { r2 } else { r1 })
                    }
                };
                last.filter(|&t| widen(t) >= lo).map(|t| widen(t.min(hi)))
            }
        }
    }
}

/// A unit direction drawn with density cos(θ)/π about the unit normal n (Malley's method).
pub fn cosine_direction(n: [f64; 3], u: [f64; 2]) -> [f64; 3] {
    let r = u[0].sqrt();
    let phi = std::f64::consts::TAU * u[1];
    let z = (1.0 - u[0]).max(0.0).sqrt();
    // An orthonormal basis (t, b, n).
    let helper = if n[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
    let t = cross(helper, n);
    let t = scale(t, 1.0 / norm(t));
    let b = cross(n, t);
    add(add(scale(t, r * phi.cos()), scale(b, r * phi.sin())), scale(n, z))
}

/// SplitMix64 finaliser.
pub(crate) fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Two uniforms in [0, 1) for (seed, pose, pixel, ray): the same for any thread count, and
/// for a pose whatever batch it is rendered in.
pub fn uniforms(seed: u64, pose: [f64; 3], pixel: u64, ray: u64) -> [f64; 2] {
    uniforms_of_pose(pose_hash(seed, pose), pixel, ray)
}

/// The part of `uniforms`' hash that depends on the seed and the pose only (once per frame).
pub fn pose_hash(seed: u64, pose: [f64; 3]) -> u64 {
    let mut h = mix(seed);
    for v in pose {
        h = mix(h ^ v.to_bits());
    }
    h
}

/// `uniforms(seed, pose, pixel, ray)` from `pose_hash(seed, pose)`.
pub fn uniforms_of_pose(pose_hash: u64, pixel: u64, ray: u64) -> [f64; 2] {
    let h = mix(mix(pose_hash ^ pixel) ^ ray);
    let g = mix(h);
    let unit = |x: u64| (x >> 11) as f64 * (1.0 / (1u64 << 53) as f64);
    [unit(h), unit(g)]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::{Material, Wall};

    #[test]
    fn cosine_directions_have_the_cosine_mean() {
        // E[cos θ] = 2/3 under the density cos θ/π.
        let n = [0.0, 0.6, 0.8];
        let (mut sum, count) = (0.0, 20000);
        for i in 0..count {
            let d = cosine_direction(n, uniforms(1, [0.0; 3], i, 0));
            assert!((norm(d) - 1.0).abs() < 1e-12 && dot(d, n) >= 0.0);
            sum += dot(d, n);
        }
        assert!((sum / count as f64 - 2.0 / 3.0).abs() < 0.01);
    }

    #[test]
    fn coaxial_source_without_mirrors_gives_the_inverse_square_law() {
        let walls = [Wall { a: [2.0, -5.0], b: [2.0, 5.0], bottom: 0.0, top: 3.0, material: 0 }];
        let scene = Scene::new(&walls, &[], vec![Material::matte(0.5)], 0, 0, 3.0, 0.5).unwrap();
        let m = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0]];
        let light = PoseLight::new(&Illumination::coaxial(), &[], &m);
        let mut got = vec![];
        let x = [2.0, 1.0, 1.0];
        light.paths(&scene, x, [-1.0, 0.0, 0.0], ALL_SOURCES, true, &mut Mailbox::for_scene(&scene), |g, l| got.push((g, l)));
        let r2: f64 = 5.0;
        assert_eq!(got.len(), 1);
        assert!((got[0].1 - r2.sqrt()).abs() < 1e-12);
        assert!((got[0].0 - (2.0 / r2.sqrt()) / r2).abs() < 1e-12);
    }
}
