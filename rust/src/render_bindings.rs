//! PyO3 bindings of the ToF renderer (render.rs); registered from lib.rs.
//!
//! One private class, `_core._Renderer`, built once per world and rig from plain arrays and then
//! asked for frames. Its Python face is `omnitof.sim.render.Renderer`; nobody else should use it.

use numpy::ndarray::{Array1, Array3, Array4};
use numpy::{IntoPyArray, PyArray1, PyArray3, PyArray4, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::COrder;

use crate::light::Illumination;
use crate::tof_frames::{self, check_layout, Decoded, Images, Layout, SensorModel};
use crate::render::{light_masks, render_with, Block, Kind, Material, Mirror, Rig, RenderParams, Scene, Wall, MAX_SECONDARY};

fn rows<'a>(a: &'a PyReadonlyArray2<'_, f64>, cols: usize, what: &str) -> PyResult<Vec<&'a [f64]>> {
    let shape = a.shape();
    if shape[1] != cols {
        return Err(PyValueError::new_err(format!("{what} must have shape (N, {cols}), got {shape:?}")));
    }
    Ok(a.c_slice(what)?.chunks_exact(cols).collect())
}

fn same_len(n: usize, m: usize, what: &str) -> PyResult<()> {
    if n != m {
        return Err(PyValueError::new_err(format!("{what}: {m} entries for {n} rows")));
    }
    Ok(())
}

fn materials(table: &PyReadonlyArray2<'_, f64>) -> PyResult<Vec<Material>> {
    rows(table, 6, "materials")?
        .into_iter()
        .map(|r| {
            if r[0] != r[0].round() {
                return Err(PyValueError::new_err(format!("material kind must be a whole number, got {}", r[0])));
            }
            let kind = match r[0] as i64 {
                0 => Kind::Matte,
                1 => Kind::Metal,
                2 => Kind::Glass,
                3 => Kind::Grid,
                k => return Err(PyValueError::new_err(format!("unknown material kind {k}"))),
            };
            Ok(Material { kind, albedo: r[1], specular: r[2], transmission: r[3], coverage: r[4], pitch: r[5] })
        })
        .collect()
}

fn mirrors(
    planes: &PyReadonlyArray2<'_, f64>,
    vertices: &PyReadonlyArray2<'_, f64>,
    counts: &PyReadonlyArray1<'_, u64>,
    reflectivity: &PyReadonlyArray1<'_, f64>,
) -> PyResult<Vec<Mirror>> {
    let planes = rows(planes, 4, "mirror_planes")?;
    let vertices = rows(vertices, 3, "mirror_vertices")?;
    let (counts, reflectivity) = (counts.c_slice("mirror_counts")?, reflectivity.c_slice("mirror_reflectivity")?);
    same_len(planes.len(), counts.len(), "mirror_counts")?;
    same_len(planes.len(), reflectivity.len(), "mirror_reflectivity")?;
    let total = counts.iter().try_fold(0u64, |sum, &k| sum.checked_add(k));
    if total != Some(vertices.len() as u64) {
        return Err(PyValueError::new_err("mirror_counts must add up to the number of mirror_vertices"));
    }
    let mut next = 0;
    let mut out = Vec::with_capacity(planes.len());
    for ((p, &k), &r) in planes.iter().zip(counts).zip(reflectivity) {
        let polygon = vertices[next..next + k as usize].iter().map(|v| [v[0], v[1], v[2]]).collect();
        next += k as usize;
        out.push(Mirror { normal: [p[0], p[1], p[2]], d: p[3], polygon, reflectivity: r });
    }
    Ok(out)
}

/// Most specular bounces a ray follows: a ray between two perfect mirrors never fades, so
/// `min_gain` alone does not end it (10⁹ bounces hung).
const MAX_BOUNCES: u32 = 64;

/// (samples, distance, amplitude, offset, saturated) of `_Renderer.frames`.
type Frames<'py> = (
    Bound<'py, PyArray4<f32>>,
    Bound<'py, PyArray3<f32>>,
    Bound<'py, PyArray3<f32>>,
    Bound<'py, PyArray3<f32>>,
    Bound<'py, PyArray3<bool>>,
);

/// (distances, material indices) of `_Renderer.cast`.
type Casts<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<i64>>);

/// A world and a rig, ready to render (see omnitof.sim.render for the meaning of every array).
#[pyclass(name = "_Renderer", module = "omnitof._core")]
struct PyRenderer {
    scene: Scene,
    rig: Rig,
    params: RenderParams,
    /// The LEDs' candidate sources per sub-ray (render::light_masks), once for the renderer.
    masks: Option<Vec<crate::light::SubRayLight>>,
    pool: Option<rayon::ThreadPool>,
}

#[pymethods]
impl PyRenderer {
    #[new]
    #[pyo3(signature = (*, walls, wall_materials, boxes, box_materials, materials, floor_material,
        ceiling_material, ceiling_height, cell, directions, height, width, sub_rays, mirror_planes,
        mirror_vertices, mirror_counts, mirror_reflectivity, robot_T_camera, f_mod, amplitude_at_1m,
        max_bounces, min_gain, threads=None, leds=None, led_profile_exponent=0.0, led_half_angle_deg=180.0, multipath_rays=0, multipath_window=0, seed=0))]
    #[allow(clippy::too_many_arguments, non_snake_case)]
    fn new(
        walls: PyReadonlyArray2<f64>,
        wall_materials: PyReadonlyArray1<u32>,
        boxes: PyReadonlyArray2<f64>,
        box_materials: PyReadonlyArray1<u32>,
        materials: PyReadonlyArray2<f64>,
        floor_material: u32,
        ceiling_material: u32,
        ceiling_height: f64,
        cell: f64,
        directions: PyReadonlyArray2<f64>,
        height: usize,
        width: usize,
        sub_rays: usize,
        mirror_planes: PyReadonlyArray2<f64>,
        mirror_vertices: PyReadonlyArray2<f64>,
        mirror_counts: PyReadonlyArray1<u64>,
        mirror_reflectivity: PyReadonlyArray1<f64>,
        robot_T_camera: PyReadonlyArray2<f64>,
        f_mod: f64,
        amplitude_at_1m: f64,
        max_bounces: u32,
        min_gain: f64,
        threads: Option<usize>,
        leds: Option<PyReadonlyArray2<f64>>,
        led_profile_exponent: f64,
        led_half_angle_deg: f64,
        multipath_rays: u32,
        multipath_window: u32,
        seed: u64,
    ) -> PyResult<Self> {
        let wall_rows = rows(&walls, 6, "walls")?;
        let wall_mats = wall_materials.c_slice("wall_materials")?;
        same_len(wall_rows.len(), wall_mats.len(), "wall_materials")?;
        let walls: Vec<Wall> = wall_rows
            .iter()
            .zip(wall_mats)
            .map(|(r, &m)| Wall { a: [r[0], r[1]], b: [r[2], r[3]], bottom: r[4], top: r[5], material: m })
            .collect();
        let box_rows = rows(&boxes, 7, "boxes")?;
        let box_mats = box_materials.c_slice("box_materials")?;
        same_len(box_rows.len(), box_mats.len(), "box_materials")?;
        let blocks: Vec<Block> = box_rows
            .iter()
            .zip(box_mats)
            .map(|(r, &m)| Block {
                centre: [r[0], r[1]],
                half: [0.5 * r[2], 0.5 * r[3]],
                yaw: r[4],
                bottom: r[5],
                top: r[6],
                material: m,
            })
            .collect();
        let table = self::materials(&materials)?;
        // "world: " marks the scene's own refusals, which the Python side blames on the world file.
        let scene = Scene::new(&walls, &blocks, table, floor_material, ceiling_material, ceiling_height, cell)
            .map_err(|e| PyValueError::new_err(format!("world: {e}")))?;

        let dirs: Vec<[f64; 3]> = rows(&directions, 3, "directions")?.iter().map(|r| [r[0], r[1], r[2]]).collect();
        let mirrors = self::mirrors(&mirror_planes, &mirror_vertices, &mirror_counts, &mirror_reflectivity)?;
        let mount = rows(&robot_T_camera, 4, "robot_T_camera")?;
        if mount.len() != 4 {
            return Err(PyValueError::new_err("robot_T_camera must be 4×4"));
        }
        let mut m = [[0.0; 4]; 3];
        for (i, row) in m.iter_mut().enumerate() {
            row.copy_from_slice(mount[i]);
        }
        let rig = Rig::new(&dirs, height, width, sub_rays, &mirrors, m).map_err(PyValueError::new_err)?;

        // f_mod beyond 1 THz makes the unambiguous range 0.15 mm; an amplitude beyond 1e30 overflows
        // the float32 images.
        if !(f_mod > 0.0 && f_mod <= 1e12 && amplitude_at_1m > 0.0 && amplitude_at_1m <= 1e30) {
            return Err(PyValueError::new_err("f_mod must lie in (0, 1e12] Hz and amplitude_at_1m in (0, 1e30]"));
        }
        if !(min_gain >= 0.0 && min_gain.is_finite()) {
            return Err(PyValueError::new_err(format!("min_gain must be finite and >= 0, got {min_gain}")));
        }
        if max_bounces > MAX_BOUNCES {
            return Err(PyValueError::new_err(format!("max_bounces must be at most {MAX_BOUNCES}, got {max_bounces}")));
        }
        if !(led_half_angle_deg > 0.0 && led_half_angle_deg <= 180.0) {
            return Err(PyValueError::new_err(format!("led_half_angle_deg must lie in (0, 180], got {led_half_angle_deg}")));
        }
        // Without `leds` the light is coaxial, and the interreflections are lit by one source at
        // the lens centre with the LEDs' profile; with them, by the LEDs themselves.
        let positions: Vec<[f64; 3]> = match &leds {
            None => vec![[0.0; 3]],
            Some(a) => rows(a, 3, "leds")?.iter().map(|r| [r[0], r[1], r[2]]).collect(),
        };
        let min_cos = led_half_angle_deg.to_radians().cos();
        let light = Illumination { leds: positions, profile_exponent: led_profile_exponent, min_cos };
        light.check().map_err(PyValueError::new_err)?;
        let bounce = light.clone();
        let illumination = leds.is_some().then_some(light);
        if multipath_rays as usize > MAX_SECONDARY.saturating_mul(sub_rays) {
            return Err(PyValueError::new_err(format!(
                "multipath_rays must be at most {} per sub-ray, got {multipath_rays}",
                MAX_SECONDARY
            )));
        }
        let params =
            RenderParams { f_mod, amplitude_at_1m, max_bounces, min_gain, illumination, multipath_rays, multipath_window, bounce, seed };
        let pool = crate::optional_pool(threads)?;
        let masks = match &pool {
            Some(pool) => pool.install(|| light_masks(&rig, &params)),
            None => light_masks(&rig, &params),
        };
        Ok(PyRenderer { scene, rig, params, masks, pool })
    }

    /// (N, H, W, 4) float32: per pose (x, y, θ) and pixel, the mean over its sub-rays of the
    /// phasor (re, im), Σ|p| and the ambient brightness Σ g1·albedo. `keys` (N, 3): the pose
    /// whose hash seeds each image's secondary rays (default: `poses`; `render_with`).
    #[pyo3(signature = (poses, keys=None))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        poses: PyReadonlyArray2<f64>,
        keys: Option<PyReadonlyArray2<f64>>,
    ) -> PyResult<Bound<'py, PyArray4<f32>>> {
        let poses: Vec<[f64; 3]> = rows(&poses, 3, "poses")?.iter().map(|r| [r[0], r[1], r[2]]).collect();
        if poses.iter().flatten().any(|v| !v.is_finite()) {
            return Err(PyValueError::new_err("poses must be finite"));
        }
        let keys: Vec<[f64; 3]> = match keys {
            Some(k) => rows(&k, 3, "keys")?.iter().map(|r| [r[0], r[1], r[2]]).collect(),
            None => poses.clone(),
        };
        same_len(poses.len(), keys.len(), "keys")?;
        let (h, w) = (self.rig.height, self.rig.width);
        let mut out = vec![0f32; poses.len() * h * w * 4];
        py.detach(|| {
            let (scene, rig, params, masks) = (&self.scene, &self.rig, &self.params, self.masks.as_deref());
            match &self.pool {
                Some(pool) => pool.install(|| render_with(scene, rig, params, masks, &poses, &keys, &mut out)),
                None => render_with(scene, rig, params, masks, &poses, &keys, &mut out),
            }
        });
        Ok(Array4::from_shape_vec((poses.len(), h, w, 4), out).unwrap().into_pyarray(py))
    }

    /// First surface along world rays (N, 3) origins and directions of any length: (distance
    /// (N,), material index (N,)); inf and −1 where nothing is hit or the direction holds a NaN.
    fn cast<'py>(
        &self,
        py: Python<'py>,
        origins: PyReadonlyArray2<f64>,
        directions: PyReadonlyArray2<f64>,
    ) -> PyResult<Casts<'py>> {
        let o = rows(&origins, 3, "origins")?;
        let d = rows(&directions, 3, "directions")?;
        same_len(o.len(), d.len(), "directions")?;
        let mut t = Array1::from_elem(o.len(), f64::INFINITY);
        let mut material = Array1::from_elem(o.len(), -1i64);
        for (i, (o, d)) in o.iter().zip(&d).enumerate() {
            // Scaled by the largest component first, so that 1e-200 or 1e160 neither under- nor
            // overflows its square.
            if d.iter().any(|v| v.is_nan()) {
                continue; // the rig's marker of a ray the lens does not have: nothing is hit
            }
            let big = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            if !(big > 0.0 && big.is_finite() && o.iter().all(|v| v.is_finite())) {
                return Err(PyValueError::new_err(format!(
                    "ray {i}: the origin must be finite and the direction finite and not zero, got {o:?}, {d:?}"
                )));
            }
            let d = [d[0] / big, d[1] / big, d[2] / big];
            let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let unit = [d[0] / norm, d[1] / norm, d[2] / norm];
            if let Some(hit) = self.scene.intersect([o[0], o[1], o[2]], unit, 0.0, f64::INFINITY) {
                t[i] = hit.t;
                material[i] = hit.material as i64;
            }
        }
        Ok((t.into_pyarray(py), material.into_pyarray(py)))
    }

    /// Noisy samples and their decoding for frames made of the images (M, H, W) of `render`
    /// (rust/src/tof_frames.rs): phasor as (M·H·W, 2) float32 (re, im), active and ambient
    /// offsets (M·H·W,); frame n uses image first[n] (or first[n]..first[n] + 3 where
    /// per_sample[n]) and the noise seed seeds[n]. Returns samples (N, 4, H, W), distance,
    /// amplitude, offset (N, H, W) float32 and saturated (N, H, W) bool.
    #[pyo3(signature = (phasor, active, ambient, first, per_sample, seeds, *, electrons_per_unit, read_noise,
        full_well, harmonics=None, amplitude_offset=None, fixed_pattern=None))]
    #[allow(clippy::too_many_arguments)]
    fn frames<'py>(
        &self,
        py: Python<'py>,
        phasor: PyReadonlyArray2<f32>,
        active: PyReadonlyArray1<f32>,
        ambient: PyReadonlyArray1<f32>,
        first: PyReadonlyArray1<u64>,
        per_sample: PyReadonlyArray1<bool>,
        seeds: PyReadonlyArray1<u64>,
        electrons_per_unit: f64,
        read_noise: f64,
        full_well: f64,
        harmonics: Option<(f64, f64)>,
        amplitude_offset: Option<(f64, f64)>,
        fixed_pattern: Option<PyReadonlyArray1<f64>>,
    ) -> PyResult<Frames<'py>> {
        let (h, w) = (self.rig.height, self.rig.width);
        let pixels = h * w;
        if phasor.shape()[1] != 2 {
            return Err(PyValueError::new_err("phasor must have shape (M·H·W, 2)"));
        }
        let model = SensorModel {
            f_mod: self.params.f_mod,
            gain: electrons_per_unit,
            read_noise,
            full_well,
            harmonics: harmonics.map(|(a, b)| [a, b]),
            amplitude_offset: amplitude_offset.map(|(a, b)| [a, b]),
            fixed_pattern: fixed_pattern.map(|a| a.c_slice("fixed_pattern").map(|s| s.to_vec())).transpose()?,
        };
        model.check(pixels).map_err(PyValueError::new_err)?;
        let images = Images { phasor: phasor.c_slice("phasor")?, active: active.c_slice("active")?, ambient: ambient.c_slice("ambient")? };
        let first: Vec<usize> = first.c_slice("first")?.iter().map(|&f| f as usize).collect();
        let layout = Layout { first: &first, per_sample: per_sample.c_slice("per_sample")?, seeds: seeds.c_slice("seeds")? };
        check_layout(&images, &layout, pixels).map_err(PyValueError::new_err)?;
        let n = first.len();
        let mut samples = vec![0f32; n * 4 * pixels];
        let (mut distance, mut amplitude, mut offset) = (vec![0f32; n * pixels], vec![0f32; n * pixels], vec![0f32; n * pixels]);
        let mut saturated = vec![false; n * pixels];
        py.detach(|| {
            let out = Decoded {
                samples: &mut samples,
                distance: &mut distance,
                amplitude: &mut amplitude,
                offset: &mut offset,
                saturated: &mut saturated,
            };
            let run = || tof_frames::frames(&model, &images, &layout, pixels, w, out);
            match &self.pool {
                Some(pool) => pool.install(run),
                None => run(),
            }
        });
        let image = |v: Vec<f32>| Array3::from_shape_vec((n, h, w), v).unwrap().into_pyarray(py);
        Ok((
            Array4::from_shape_vec((n, 4, h, w), samples).unwrap().into_pyarray(py),
            image(distance),
            image(amplitude),
            image(offset),
            Array3::from_shape_vec((n, h, w), saturated).unwrap().into_pyarray(py),
        ))
    }

    /// (height, width, sub_rays) of the rig.
    #[getter]
    fn shape(&self) -> (usize, usize, usize) {
        (self.rig.height, self.rig.width, self.rig.sub_rays)
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // A plain attribute rather than `add_class`, which would also list the private class in the
    // module's `__all__` (the public names the stubs in _core.pyi describe).
    m.setattr("_Renderer", m.py().get_type::<PyRenderer>())
}
