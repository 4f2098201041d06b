//! The camera's four samples A0..A3 from the renderer's phasors, with the sensor's noise and
//! systematic errors, and their 4-tap decoding (paper eq. 1–4): one pass per pixel, in parallel.
//! Pure Rust; the model is that of omnitof.sensor.tof.synthesise and omnitof.sensor.tof_errors
//! (the Python functions stay the reference; their docstrings derive every formula), and the
//! decoding that of omnitof.sensor.tof.decode, operation for operation, so that decoding the
//! returned f32 samples in numpy gives the returned distances bit for bit.
//!
//! Per pixel, with p = A·e^{iΦ} its phasor (sample units) and B = ambient + active offset:
//!
//! ```text
//! p'   = p · e^{i·k·(δ_amp(|p|) + δ_fpn)},  k = 4π·f_mod/c          (offsets, tof_errors)
//! μ_j  = B + Re(t_j) + |t_j|·(h3·Re(u_j³) + h5·Re(u_j⁵)),  t_j = p'·i^j, u_j = t_j/|t_j|
//! A_j  = clip(μ_j + √(max(μ_j, 0)/g + σ_r²)·z_j, 0, full_well)
//! ```
//!
//! Randomness: z_j are standard normals from a generator seeded with (frame seed, image row),
//! drawn along the row (one task handles a whole row), so a frame is the same for any thread
//! count and whatever batch it is made in. They are not
//! numpy's draws: the same model with another random stream.

use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64Mcg;
use rayon::prelude::*;

use crate::light::mix;
use crate::render::SPEED_OF_LIGHT;

/// The sensor's noise and systematic errors (omnitof.sensor.tof.SensorNoise, ToFErrors).
#[derive(Clone, Debug, PartialEq)]
pub struct SensorModel {
    pub f_mod: f64,
    /// Electrons per sample unit; infinity turns shot noise off.
    pub gain: f64,
    pub read_noise: f64,
    pub full_well: f64,
    /// Odd harmonics (h3, h5) of the correlation function (wiggling), if on.
    pub harmonics: Option<[f64; 2]>,
    /// Amplitude-dependent offset: (metres per e-fold, reference amplitude), if on.
    pub amplitude_offset: Option<[f64; 2]>,
    /// Per-pixel fixed-pattern offset, metres (H·W, row-major), if on.
    pub fixed_pattern: Option<Vec<f64>>,
}

impl SensorModel {
    pub fn check(&self, pixels: usize) -> Result<(), String> {
        if !(self.f_mod > 0.0 && self.f_mod.is_finite()) {
            return Err("f_mod must be a positive number".into());
        }
        if !(self.gain > 0.0 && self.read_noise >= 0.0 && self.read_noise.is_finite() && self.full_well > 0.0) {
            return Err("the gain and the full well must be > 0, the read noise >= 0".into());
        }
        if let Some(fp) = &self.fixed_pattern {
            if fp.len() != pixels {
                return Err(format!("fixed_pattern has {} values for {pixels} pixels", fp.len()));
            }
            if !fp.iter().all(|v| v.is_finite()) {
                return Err("fixed_pattern must be finite".into());
            }
        }
        if let Some(h) = self.harmonics {
            if !h.iter().all(|v| v.is_finite()) {
                return Err("harmonics must be finite".into());
            }
        }
        if let Some([scale, reference]) = self.amplitude_offset {
            if !(scale.is_finite() && reference > 0.0 && reference.is_finite()) {
                return Err("the amplitude offset must be finite, its reference amplitude > 0".into());
            }
        }
        Ok(())
    }
}

/// The renderer's images of a batch: M images of P pixels each.
pub struct Images<'a> {
    /// re, im of each pixel's phasor, interleaved (numpy's complex64 layout).
    pub phasor: &'a [f32],
    /// The offset the returning modulated light adds (>= |phasor|).
    pub active: &'a [f32],
    /// The offset from background light.
    pub ambient: &'a [f32],
}

/// Which images make frame n: image `first[n]` for all four samples, or images first[n] ..
/// first[n] + 3 (one per sample: motion during the frame) where `per_sample[n]`.
pub struct Layout<'a> {
    pub first: &'a [usize],
    pub per_sample: &'a [bool],
    pub seeds: &'a [u64],
}

/// Frames out: samples (N, 4, P), distance, amplitude, offset and saturated (N, P).
pub struct Decoded<'a> {
    pub samples: &'a mut [f32],
    pub distance: &'a mut [f32],
    pub amplitude: &'a mut [f32],
    pub offset: &'a mut [f32],
    pub saturated: &'a mut [bool],
}

/// Check that the layout fits the images; the error names what does not.
pub fn check_layout(images: &Images, layout: &Layout, pixels: usize) -> Result<(), String> {
    let m = images.active.len();
    if pixels == 0 || m % pixels != 0 || images.phasor.len() != 2 * m || images.ambient.len() != m {
        return Err(format!("phasor, active and ambient must hold whole images of {pixels} pixels each"));
    }
    let (n, count) = (layout.first.len(), m / pixels);
    if layout.per_sample.len() != n || layout.seeds.len() != n {
        return Err("first, per_sample and seeds must have one entry per frame".into());
    }
    for (i, (&f, &ps)) in layout.first.iter().zip(layout.per_sample).enumerate() {
        if f.checked_add(if ps { 4 } else { 1 }).is_none_or(|end| end > count) {
            return Err(format!("frame {i} needs images beyond the {count} given"));
        }
    }
    Ok(())
}

/// Samples and decoding of every frame of `layout` (module docs), rows of `width` pixels in
/// parallel on the current rayon pool. The caller checks the model and the layout first.
pub fn frames(model: &SensorModel, images: &Images, layout: &Layout, pixels: usize, width: usize, out: Decoded) {
    let Decoded { samples, distance, amplitude, offset, saturated } = out;
    let frames = samples
        .chunks_mut(4 * pixels)
        .zip(distance.chunks_mut(pixels))
        .zip(amplitude.chunks_mut(pixels))
        .zip(offset.chunks_mut(pixels))
        .zip(saturated.chunks_mut(pixels));
    for (n, ((((frame_samples, d), a), o), s)) in frames.enumerate() {
        let (s01, s23) = frame_samples.split_at_mut(2 * pixels);
        let (s0, s1) = s01.split_at_mut(pixels);
        let (s2, s3) = s23.split_at_mut(pixels);
        let first = layout.first[n] * pixels;
        let step = if layout.per_sample[n] { pixels } else { 0 };
        let seed = layout.seeds[n];
        s0.par_chunks_mut(width)
            .zip(s1.par_chunks_mut(width))
            .zip(s2.par_chunks_mut(width))
            .zip(s3.par_chunks_mut(width))
            .zip(d.par_chunks_mut(width))
            .zip(a.par_chunks_mut(width))
            .zip(o.par_chunks_mut(width))
            .zip(s.par_chunks_mut(width))
            .enumerate()
            .for_each(|(row, (((((((r0, r1), r2), r3), rd), ra), ro), rs))| {
                // One generator per image row (a row is never split between threads).
                let mut rng = Pcg64Mcg::seed_from_u64(mix(seed ^ mix(row as u64)));
                for col in 0..rd.len() {
                    let pixel = row * width + col;
                    let a = pixel_samples(model, images, first + pixel, step, pixel, &mut rng);
                    (r0[col], r1[col], r2[col], r3[col]) = (a[0], a[1], a[2], a[3]);
                    rs[col] = a[4] != 0.0;
                    let (dist, amp, off) = decode(model.f_mod, [a[0], a[1], a[2], a[3]]);
                    (rd[col], ra[col], ro[col]) = (dist, amp, off);
                }
            });
    }
}

/// The four clipped samples of one pixel and a saturation flag (1.0: a sample exceeded the
/// full well). `index`: the pixel in its frame's first image, `step`: the distance to the next
/// sample's image (0: one image for all four), `pixel`: its index in the image.
fn pixel_samples(model: &SensorModel, images: &Images, index: usize, step: usize, pixel: usize, rng: &mut Pcg64Mcg) -> [f32; 5] {
    let mut out = [0f32; 5];
    // Per image: the phasor p after the offsets, and for the wiggling |p|·u³, |p|·u⁵ (u = p/|p|).
    // Sample j sees t_j = p·i^j, so |t_j| = |p| and u_j^n = i^{nj}·u^n: turning by i^{nj} is
    // exact (a swap and a sign), so each image needs one magnitude and no powers per sample.
    let (mut p, mut w3, mut w5) = ([0.0; 2], [0.0; 2], [0.0; 2]);
    let (inv_gain, read2) = (1.0 / model.gain, model.read_noise * model.read_noise);
    for j in 0..4 {
        let i = index + j * step;
        if j == 0 || step != 0 {
            p = offset_phasor(model, [images.phasor[2 * i], images.phasor[2 * i + 1]], pixel);
            (w3, w5) = ([0.0; 2], [0.0; 2]);
            if let Some([h3, h5]) = model.harmonics {
                let magnitude = (p[0] * p[0] + p[1] * p[1]).sqrt();
                if magnitude > 0.0 {
                    let u = [p[0] / magnitude, p[1] / magnitude];
                    let u2 = cmul(u, u);
                    let u3 = cmul(u2, u);
                    let u5 = cmul(u3, u2);
                    (w3, w5) = ([h3 * magnitude * u3[0], h3 * magnitude * u3[1]], [h5 * magnitude * u5[0], h5 * magnitude * u5[1]]);
                }
            }
        }
        let b = images.ambient[i] as f64 + images.active[i] as f64;
        // μ_j = B + Re(p·i^j) + Re(w3·i^{3j}) + Re(w5·i^{5j}) (i^{5j} = i^j); Re(z·i^k) for k mod 4.
        let re_turned = |z: [f64; 2], k: usize| match k % 4 {
            0 => z[0],
            1 => -z[1],
            2 => -z[0],
            _ => z[1],
        };
        let mu = b + re_turned(p, j) + re_turned(w3, 3 * j) + re_turned(w5, j);
        let sigma = (mu.max(0.0) * inv_gain + read2).sqrt();
        let z: f64 = rng.sample(StandardNormal);
        let drawn = mu + sigma * z;
        if drawn > model.full_well {
            out[4] = 1.0;
        }
        out[j] = drawn.clamp(0.0, model.full_well) as f32;
    }
    out
}

#[inline]
fn cmul(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0]]
}

/// The phasor turned by the amplitude-dependent and fixed-pattern offsets (tof_errors.apply_offsets).
fn offset_phasor(model: &SensorModel, phasor: [f32; 2], pixel: usize) -> [f64; 2] {
    let p = [phasor[0] as f64, phasor[1] as f64];
    if model.amplitude_offset.is_none() && model.fixed_pattern.is_none() {
        return p;
    }
    let mut delta = 0.0;
    if let Some([metres, reference]) = model.amplitude_offset {
        delta += metres * (reference / (p[0] * p[0] + p[1] * p[1]).sqrt().max(1.0)).ln();
    }
    if let Some(fp) = &model.fixed_pattern {
        delta += fp[pixel];
    }
    let (s, c) = (4.0 * std::f64::consts::PI * model.f_mod / SPEED_OF_LIGHT * delta).sin_cos();
    cmul(p, [c, s])
}

/// Eq. 1–4 on the f32 samples, computed in f64 as omnitof.sensor.tof.decode does: distance in
/// [0, c/(2·f_mod)), amplitude, offset (the mean of the samples).
pub fn decode(f_mod: f64, a: [f32; 4]) -> (f32, f32, f32) {
    let [s0, s1, s2, s3] = a.map(|v| v as f64);
    let (sin, cos) = (s3 - s1, s0 - s2);
    let tau = 2.0 * std::f64::consts::PI;
    // numpy's mod(Φ, 2π) for Φ = atan2 in [−π, π]: Φ + 2π where negative (a tiny negative
    // phase rounds to 2π, which the next test folds to 0).
    let mut phase = sin.atan2(cos);
    if phase < 0.0 {
        phase += tau;
    }
    if phase >= tau {
        phase = 0.0;
    }
    let distance = (phase * (SPEED_OF_LIGHT / (4.0 * std::f64::consts::PI * f_mod))) as f32;
    let range = (SPEED_OF_LIGHT / (2.0 * f_mod)) as f32;
    let distance = if distance >= range { 0.0 } else { distance };
    (distance, (sin.hypot(cos) / 2.0) as f32, ((s0 + s1 + s2 + s3) / 4.0) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> SensorModel {
        SensorModel {
            f_mod: 20e6,
            gain: f64::INFINITY,
            read_noise: 0.0,
            full_well: 65535.0,
            harmonics: None,
            amplitude_offset: None,
            fixed_pattern: None,
        }
    }

    fn run(model: &SensorModel, phasor: &[[f32; 2]], seeds: &[u64], threads: usize) -> (Vec<f32>, Vec<f32>) {
        let pixels = phasor.len();
        let active: Vec<f32> = phasor.iter().map(|p| 2.0 * p[0].hypot(p[1])).collect();
        let phasor: Vec<f32> = phasor.iter().flatten().copied().collect();
        let phasor = &phasor[..];
        let ambient = vec![400f32; pixels];
        let images = Images { phasor, active: &active, ambient: &ambient };
        let n = seeds.len();
        let (first, per_sample) = (vec![0; n], vec![false; n]);
        let layout = Layout { first: &first, per_sample: &per_sample, seeds };
        check_layout(&images, &layout, pixels).unwrap();
        let (mut s, mut d, mut a, mut o, mut sat) =
            (vec![0f32; 4 * n * pixels], vec![0f32; n * pixels], vec![0f32; n * pixels], vec![0f32; n * pixels], vec![false; n * pixels]);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let out = Decoded { samples: &mut s, distance: &mut d, amplitude: &mut a, offset: &mut o, saturated: &mut sat };
            frames(model, &images, &layout, pixels, 8, out)
        });
        (s, d)
    }

    #[test]
    fn a_layout_beyond_the_images_is_an_error_not_a_panic() {
        let (phasor, active, ambient) = (vec![0f32; 8], vec![0f32; 4], vec![0f32; 4]);
        let images = Images { phasor: &phasor, active: &active, ambient: &ambient };
        let seeds = [0u64];
        for (first, per_sample) in [(usize::MAX, false), (0, true), (1, false)] {
            let layout = Layout { first: &[first], per_sample: &[per_sample], seeds: &seeds };
            assert!(check_layout(&images, &layout, 4).is_err());
        }
        let layout = Layout { first: &[0], per_sample: &[false], seeds: &seeds };
        assert!(check_layout(&images, &layout, 4).is_ok());
        assert!(check_layout(&images, &layout, 3).is_err());
    }

    #[test]
    fn noise_free_samples_decode_to_the_phasor() {
        // 1.5 m at 20 MHz: Φ = 4π·f·d/c; amplitude 900.
        let d = 1.5;
        let phi = 4.0 * std::f64::consts::PI * 20e6 * d / SPEED_OF_LIGHT;
        let p = [[(900.0 * phi.cos()) as f32, (900.0 * phi.sin()) as f32]; 16];
        let (s, dist) = run(&model(), &p, &[1], 1);
        assert!(dist.iter().all(|&x| (x as f64 - d).abs() < 1e-5));
        // A0 = B + A·cosΦ, B = 400 + 2A.
        assert!((s[0] as f64 - (400.0 + 1800.0 + 900.0 * phi.cos())).abs() < 1e-2);
    }

    #[test]
    fn wiggling_follows_the_harmonic_models_error() {
        // (R/2π)·arg(1 + h3·e^{−4iΦ} + h5·e^{4iΦ}): tof_errors.wiggling_error, computed here
        // independently of the samples.
        let m = SensorModel { harmonics: Some([0.035, 0.014]), ..model() };
        let range = SPEED_OF_LIGHT / 40e6;
        for k in 0..50 {
            let d = 0.1 + 0.14 * k as f64;
            let phi = 2.0 * std::f64::consts::PI * d / range;
            let (re, im) = (1.0 + (0.035 + 0.014) * (4.0 * phi).cos(), (0.014 - 0.035) * (4.0 * phi).sin());
            let want = d + im.atan2(re) * range / (2.0 * std::f64::consts::PI);
            let p = [[(1000.0 * phi.cos()) as f32, (1000.0 * phi.sin()) as f32]; 8];
            let (_, dist) = run(&m, &p, &[0], 1);
            assert!((dist[0] as f64 - want).abs() < 1e-5, "{d}: {} vs {want}", dist[0]);
        }
    }

    #[test]
    fn noise_has_the_shot_noise_spread_and_does_not_depend_on_threads() {
        let m = SensorModel { gain: 20.0, read_noise: 2.0, ..model() };
        let p = vec![[500f32, 0.0]; 4096];
        let seeds: Vec<u64> = (0..3).collect();
        let (one, _) = run(&m, &p, &seeds, 1);
        let (two, _) = run(&m, &p, &seeds, 2);
        assert_eq!(one, two);
        // A1 = B = 400 + 1000 (cos(π/2) = 0): σ² = B/g + σ_r² = 74.
        let a1 = &one[4096..2 * 4096];
        let mean = a1.iter().map(|&v| v as f64).sum::<f64>() / 4096.0;
        let var = a1.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / 4095.0;
        assert!((mean - 1400.0).abs() < 0.5 && (var / 74.0 - 1.0).abs() < 0.07, "{mean} {var}");
        // Frames with other seeds draw other noise.
        assert_ne!(&one[..4096], &one[4 * 4096..5 * 4096]);
    }
}
