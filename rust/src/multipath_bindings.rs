//! PyO3 binding of the multipath compensation (multipath.rs); registered from lib.rs.
//!
//! One private class, `_core._MultipathCompensator`, built once per rig from plain arrays and
//! then handed frames. Its Python face is `omnitof.scan.multipath.MultipathCompensation`.

use numpy::ndarray::Array3;
use numpy::{IntoPyArray, PyArray3, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::COrder;

use crate::multipath::{BeyondView, CompensationParams, Compensator};
use crate::points3;

#[pyclass(name = "_MultipathCompensator", module = "omnitof._core")]
struct PyMultipathCompensator {
    inner: Compensator,
    pool: Option<rayon::ThreadPool>,
}

#[pymethods]
impl PyMultipathCompensator {
    #[new]
    #[pyo3(signature = (*, width, height, origins, directions, paths, labels, solid_angles, emission, source_gain,
        targets, windows, k, amplitude_at_1m, mirror_reflectivity, stride, target_stride, normal_radius, smooth_radius,
        depth_tolerance, min_reflectance, min_cos, min_separation, max_ratio, visibility=false, beyond_origins=None, beyond_directions=None,
        beyond_paths=None, beyond_anchors=None, beyond_factors=None, threads=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        width: usize,
        height: usize,
        origins: PyReadonlyArray2<f64>,
        directions: PyReadonlyArray2<f64>,
        paths: PyReadonlyArray1<f64>,
        labels: PyReadonlyArray1<i32>,
        solid_angles: PyReadonlyArray1<f64>,
        emission: PyReadonlyArray1<f64>,
        source_gain: PyReadonlyArray1<f64>,
        targets: PyReadonlyArray1<u32>,
        windows: PyReadonlyArray2<f64>,
        k: f64,
        amplitude_at_1m: f64,
        mirror_reflectivity: f64,
        stride: usize,
        target_stride: usize,
        normal_radius: usize,
        smooth_radius: usize,
        depth_tolerance: f64,
        min_reflectance: f64,
        min_cos: f64,
        min_separation: f64,
        max_ratio: f64,
        visibility: bool,
        beyond_origins: Option<PyReadonlyArray2<f64>>,
        beyond_directions: Option<PyReadonlyArray2<f64>>,
        beyond_paths: Option<PyReadonlyArray1<f64>>,
        beyond_anchors: Option<PyReadonlyArray1<u32>>,
        beyond_factors: Option<PyReadonlyArray1<f64>>,
        threads: Option<usize>,
    ) -> PyResult<Self> {
        let shape = windows.shape();
        if shape[1] != 2 {
            return Err(PyValueError::new_err(format!("windows must have shape (T, 2), got {shape:?}")));
        }
        let inner = Compensator::new(
            width,
            height,
            points3(&origins, "origins")?,
            points3(&directions, "directions")?,
            paths.c_slice("paths")?.to_vec(),
            labels.c_slice("labels")?.to_vec(),
            solid_angles.c_slice("solid_angles")?.to_vec(),
            emission.c_slice("emission")?.to_vec(),
            source_gain.c_slice("source_gain")?.to_vec(),
            targets.c_slice("targets")?.to_vec(),
            windows.c_slice("windows")?.chunks_exact(2).map(|r| [r[0], r[1]]).collect(),
            CompensationParams {
                k,
                amplitude_at_1m,
                mirror_reflectivity,
                stride,
                target_stride,
                normal_radius,
                smooth_radius,
                depth_tolerance,
                min_reflectance,
                min_cos,
                min_separation,
                max_ratio,
                visibility,
            },
        )
        .map_err(PyValueError::new_err)?;
        let beyond = match (beyond_origins, beyond_directions, beyond_paths, beyond_anchors, beyond_factors) {
            (None, None, None, None, None) => vec![],
            (Some(o), Some(d), Some(p), Some(a), Some(f)) => {
                let (o, d) = (points3(&o, "beyond_origins")?, points3(&d, "beyond_directions")?);
                let (p, a, f) = (p.c_slice("beyond_paths")?, a.c_slice("beyond_anchors")?, f.c_slice("beyond_factors")?);
                if [d.len(), p.len(), a.len(), f.len()].iter().any(|&len| len != o.len()) {
                    return Err(PyValueError::new_err("the beyond_* arrays must all have one row per source"));
                }
                (0..o.len()).map(|i| BeyondView { origin: o[i], dir: d[i], path: p[i], anchor: a[i], factor: f[i] }).collect()
            }
            _ => return Err(PyValueError::new_err("give all five beyond_* arrays or none")),
        };
        let inner = inner.with_beyond_view(beyond).map_err(PyValueError::new_err)?;
        Ok(PyMultipathCompensator { inner, pool: crate::optional_pool(threads)? })
    }

    /// (F, H, W) float32 distances with the targets' interreflection taken out, from distances
    /// and amplitudes (F, H, W) float32.
    fn correct<'py>(
        &self,
        py: Python<'py>,
        distances: PyReadonlyArray3<f32>,
        amplitudes: PyReadonlyArray3<f32>,
    ) -> PyResult<Bound<'py, PyArray3<f32>>> {
        let shape = distances.shape().to_vec();
        if shape[1..] != [self.inner.height, self.inner.width] || amplitudes.shape() != shape.as_slice() {
            return Err(PyValueError::new_err(format!(
                "distances and amplitudes must both have shape (F, {}, {}), got {:?} and {:?}",
                self.inner.height,
                self.inner.width,
                shape,
                amplitudes.shape()
            )));
        }
        let (d, a) = (distances.c_slice("distances")?, amplitudes.c_slice("amplitudes")?);
        let n = self.inner.width * self.inner.height;
        let mut out = vec![0f32; d.len()];
        py.detach(|| {
            let run = |out: &mut [f32]| {
                for ((frame, amp), dst) in d.chunks_exact(n).zip(a.chunks_exact(n)).zip(out.chunks_exact_mut(n)) {
                    self.inner.correct(frame, amp, dst);
                }
            };
            match &self.pool {
                Some(pool) => pool.install(|| run(&mut out)),
                None => run(&mut out),
            }
        });
        Ok(Array3::from_shape_vec((shape[0], shape[1], shape[2]), out).unwrap().into_pyarray(py))
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.setattr("_MultipathCompensator", m.py().get_type::<PyMultipathCompensator>())
}
