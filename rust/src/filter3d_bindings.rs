//! PyO3 bindings of the 3D particle filter (filter3d.rs); registered from lib.rs.
//!
//! `_core.ParticleFilter3D` takes the configuration's sections whole, as `_core.ParticleFilter`
//! does: the 2D filter's sections give the particles, seed, threads, proposal, motion model,
//! scan matcher and log-odds model, the `filter3d` section what is 3D's own. Its Python face is
//! `omnitof.slam.filter3d`.

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::COrder;
use pyo3::types::PyDict;

use crate::filter3d::{Field3d, FilterParams3d, ParticleFilter3d};
use crate::scan_match::MatcherParams;
use crate::voxel::{VoxelGrid, INDEX_LIMIT};
use crate::{
    filter_params, pose3, rows3, section_dict, section_field, FilterSection, LikelihoodFieldSection, MapSection, MotionSection,
    PyVoxelGrid, ScanMatcherSection, SensorModelSection,
};

/// The `filter3d` section (python/omnitof/slam/config.py, Filter3DConfig), less `enabled` and
/// `pixel_stride`, which the driver uses. `project_z_min`/`project_z_max` (the heights of the map's
/// 2D projection) are also the heights the odometry check matches (filter3d.rs, check_odometry3d).
struct Filter3dSection {
    resolution: f64,
    max_range: f64,
    sigma: f64,
    z_hit: f64,
    z_rand: f64,
    effective_rays: f64,
    score_rays: usize,
    score_z_min: f64,
    score_z_max: f64,
    free_stride: usize,
    climb_stride: usize,
    min_matched: f64,
    project_z_min: f64,
    project_z_max: f64,
}

const FILTER3D_FIELDS: [&str; 14] = [
    "resolution", "max_range", "sigma", "z_hit", "z_rand", "effective_rays", "score_rays", "score_z_min", "score_z_max",
    "free_stride", "climb_stride", "min_matched", "project_z_min", "project_z_max",
];

impl<'a, 'py> FromPyObject<'a, 'py> for Filter3dSection {
    type Error = PyErr;

    fn extract(obj: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        let d: Bound<'py, PyDict> = section_dict(&obj, "filter3d", &FILTER3D_FIELDS)?;
        let f = |name: &str| section_field::<f64>(&d, "filter3d", name);
        Ok(Filter3dSection {
            resolution: f("resolution")?,
            max_range: f("max_range")?,
            sigma: f("sigma")?,
            z_hit: f("z_hit")?,
            z_rand: f("z_rand")?,
            effective_rays: f("effective_rays")?,
            score_rays: section_field::<usize>(&d, "filter3d", "score_rays")?,
            score_z_min: f("score_z_min")?,
            score_z_max: f("score_z_max")?,
            free_stride: section_field::<usize>(&d, "filter3d", "free_stride")?,
            climb_stride: section_field::<usize>(&d, "filter3d", "climb_stride")?,
            min_matched: f("min_matched")?,
            project_z_min: f("project_z_min")?,
            project_z_max: f("project_z_max")?,
        })
    }
}

/// Rows of an (N, 3) float64 array, every value finite and within the grid's reach.
fn rays(a: &PyReadonlyArray2<'_, f64>, what: &str, resolution: f64) -> PyResult<Vec<[f64; 3]>> {
    let shape = a.shape();
    if shape[1] != 3 {
        return Err(PyValueError::new_err(format!("{what} must have shape (N, 3), got {shape:?}")));
    }
    let limit = 0.5 * (INDEX_LIMIT as f64) * resolution;
    let out: Vec<[f64; 3]> = a.c_slice(what)?.chunks_exact(3).map(|r| [r[0], r[1], r[2]]).collect();
    if let Some(bad) = out.iter().find(|p| !p.iter().all(|v| v.is_finite() && v.abs() < limit)) {
        return Err(PyValueError::new_err(format!("{what}: {bad:?} is not a finite point within ±{limit} m")));
    }
    Ok(out)
}

/// The paper's filter with 3D voxel maps per particle (rust/src/filter3d.rs).
#[pyclass(name = "ParticleFilter3D", module = "omnitof._core")]
struct PyParticleFilter3D {
    inner: ParticleFilter3d,
}

#[pymethods]
impl PyParticleFilter3D {
    #[new]
    #[pyo3(signature = (*, filter, motion, sensor_model, likelihood_field, scan_matcher, map, filter3d))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        filter: FilterSection,
        motion: MotionSection,
        sensor_model: SensorModelSection,
        likelihood_field: LikelihoodFieldSection,
        scan_matcher: ScanMatcherSection,
        map: MapSection,
        filter3d: Filter3dSection,
    ) -> PyResult<Self> {
        let threshold = map.occupied_threshold;
        let f3 = filter3d;
        if !(f3.effective_rays.is_finite() && f3.effective_rays > 0.0) || f3.free_stride < 1 || f3.climb_stride < 1 {
            return Err(PyValueError::new_err(
                "filter3d.effective_rays must be positive and finite, free_stride and climb_stride at least 1",
            ));
        }
        let base = filter_params(filter, motion, sensor_model, likelihood_field, scan_matcher, map, f3.max_range)?;
        let params = FilterParams3d {
            n_particles: base.n_particles,
            seed: base.seed,
            threads: base.threads,
            motion: base.motion,
            proposal: base.proposal,
            field: Field3d { sigma: f3.sigma, z_hit: f3.z_hit, z_rand: f3.z_rand, occupied_threshold: threshold },
            // The 3D rays' own threshold: see Filter3DConfig.min_matched.
            matcher: MatcherParams { min_matched: f3.min_matched, ..base.matcher },
            effective_rays: f3.effective_rays,
            score_rays: f3.score_rays,
            score_z_min: f3.score_z_min,
            score_z_max: f3.score_z_max,
            check_z_min: f3.project_z_min,
            check_z_max: f3.project_z_max,
            log_odds: base.log_odds,
            resolution: f3.resolution,
            max_range: f3.max_range,
            free_stride: f3.free_stride,
            climb_stride: f3.climb_stride,
            resample_threshold: base.resample_threshold,
        };
        Ok(PyParticleFilter3D { inner: ParticleFilter3d::new(params).map_err(PyValueError::new_err)? })
    }

    /// Integrate one frame: its rays in the robot frame (origins on the mirrors (N, 3), end
    /// points (N, 3)) at odometry `odom_cur`, the odometry having moved from `odom_prev`.
    /// Returns (Neff before any resampling, whether it resampled, scan-match fallbacks, rays scored,
    /// whether the odometry check replaced the step's odometry).
    fn step(
        &mut self,
        py: Python<'_>,
        odom_prev: PyReadonlyArray1<f64>,
        odom_cur: PyReadonlyArray1<f64>,
        origins: PyReadonlyArray2<f64>,
        endpoints: PyReadonlyArray2<f64>,
        scan: u64,
    ) -> PyResult<(f64, bool, usize, usize, bool)> {
        let prev = pose3(odom_prev.c_slice("odom_prev")?, "odom_prev")?;
        let cur = pose3(odom_cur.c_slice("odom_cur")?, "odom_cur")?;
        if !prev.iter().chain(&cur).all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("odometry poses must be finite"));
        }
        let res = self.inner.params.resolution;
        let o = rays(&origins, "origins", res)?;
        let e = rays(&endpoints, "endpoints", res)?;
        if o.len() != e.len() {
            return Err(PyValueError::new_err(format!("{} origins for {} end points", o.len(), e.len())));
        }
        let inner = &mut self.inner;
        let info = py.detach(|| inner.step(prev, cur, &o, &e, scan)).map_err(crate::grid_error)?;
        Ok((info.neff, info.resampled, info.fallbacks, info.scored, info.odometry_corrected))
    }

    /// Mean log-likelihood (the 3D likelihood field) of end points (N, 3, robot frame) at each
    /// of `poses` (K, 3) in particle `index`'s map, and how many points found an occupied voxel.
    fn score<'py>(
        &self,
        py: Python<'py>,
        index: usize,
        poses: PyReadonlyArray2<f64>,
        endpoints: PyReadonlyArray2<f64>,
    ) -> PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<u64>>)> {
        let part = self.inner.particles.get(index).ok_or_else(|| PyValueError::new_err(format!("no particle {index}")))?;
        let res = self.inner.params.resolution;
        let pts = rays(&endpoints, "endpoints", res)?;
        let poses = rays(&poses, "poses", f64::INFINITY)?;
        let (ll, n): (Vec<f64>, Vec<u64>) =
            poses.iter().map(|&p| self.inner.params.field.score(&part.map, p, &pts)).map(|(l, n)| (l, n as u64)).unzip();
        Ok((PyArray1::from_vec(py, ll), PyArray1::from_vec(py, n)))
    }

    /// Restart every particle at `pose`, its trajectory beginning at frame `scan`, on one map
    /// of the frames `clouds[k]` ((M, 6) float32: origin, end point, robot frame, as
    /// `scan.ToFScans.clouds`) written at `poses[k]` ((K, 3)) in order: the pose-graph back
    /// end's correction fed back (python/omnitof/slam/backend.py). One frame is converted at a
    /// time, so that a long run's rays are not copied whole.
    fn reset(
        &mut self,
        py: Python<'_>,
        pose: PyReadonlyArray1<f64>,
        scan: u64,
        poses: PyReadonlyArray2<f64>,
        clouds: Vec<PyReadonlyArray2<f32>>,
    ) -> PyResult<()> {
        let pose = pose3(pose.c_slice("pose")?, "pose")?;
        // Within the grid's reach, as the rays are: a frame placed beyond it was dropped, and
        // the reset returned an empty map without a word.
        let at = rays(&poses, "poses", self.inner.params.resolution)?;
        if !pose.iter().chain(at.iter().flatten()).all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("poses must be finite"));
        }
        if clouds.len() != at.len() {
            return Err(PyValueError::new_err(format!("{} poses for {} clouds: one pose per frame", at.len(), clouds.len())));
        }
        let limit = 0.5 * (INDEX_LIMIT as f64) * self.inner.params.resolution;
        let mut map = self.inner.empty_map();
        for (k, cloud) in clouds.iter().enumerate() {
            if cloud.shape()[1] != 6 {
                return Err(PyValueError::new_err(format!("cloud {k} must have shape (M, 6), got {:?}", cloud.shape())));
            }
            let (mut o, mut e) = (Vec::new(), Vec::new());
            for r in cloud.c_slice("cloud")?.chunks_exact(6) {
                let r: [f64; 6] = std::array::from_fn(|i| r[i] as f64);
                if !r.iter().all(|v| v.is_finite() && v.abs() < limit) {
                    return Err(PyValueError::new_err(format!("cloud {k}: {r:?} is not a finite ray within ±{limit} m")));
                }
                o.push([r[0], r[1], r[2]]);
                e.push([r[3], r[4], r[5]]);
            }
            let inner = &self.inner;
            let frame_pose = at[k];
            py.detach(|| inner.integrate_frame(&mut map, frame_pose, &o, &e)).map_err(crate::grid_error)?;
        }
        self.inner.reset(pose, scan, map);
        Ok(())
    }

    /// The best particle's pose; None before the first frame.
    fn best_pose<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray1<f64>>> {
        self.inner.best().map(|b| PyArray1::from_vec(py, b.pose.to_vec()))
    }

    /// (frame indices, poses (K, 3)) of the best particle's trajectory, oldest first.
    fn best_trajectory<'py>(&self, py: Python<'py>) -> (Bound<'py, PyArray1<u64>>, Bound<'py, PyArray2<f64>>) {
        let traj = self.inner.best().map(|b| b.trajectory.lineage()).unwrap_or_default();
        let idx: Vec<u64> = traj.iter().map(|t| t.0).collect();
        let poses: Vec<[f64; 3]> = traj.iter().map(|t| t.1).collect();
        (PyArray1::from_vec(py, idx), rows3(py, &poses))
    }

    /// A copy of particle `index`'s map (default: the best particle's) as a VoxelGrid.
    #[pyo3(signature = (index=None))]
    fn map<'py>(&self, index: Option<usize>) -> PyResult<PyVoxelGrid> {
        let part = match index {
            Some(i) => self.inner.particles.get(i),
            None => self.inner.best(),
        }
        .ok_or_else(|| PyValueError::new_err("no such particle (or no frame integrated yet)"))?;
        let grid: VoxelGrid = part.map.to_voxel_grid();
        Ok(PyVoxelGrid { grid, pool: None })
    }

    fn poses<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let p: Vec<[f64; 3]> = self.inner.particles.iter().map(|q| q.pose).collect();
        rows3(py, &p)
    }

    fn log_weights<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.inner.particles.iter().map(|q| q.log_weight).collect())
    }

    /// (distinct voxel blocks, block references) over the maps of the particles `indices`
    /// (default: all).
    #[pyo3(signature = (indices=None))]
    fn block_counts(&self, indices: Option<Vec<usize>>) -> PyResult<(usize, usize)> {
        match indices {
            None => Ok(self.inner.block_counts()),
            Some(idx) => {
                let parts = idx
                    .iter()
                    .map(|&i| self.inner.particles.get(i).ok_or_else(|| PyValueError::new_err(format!("no particle {i}"))))
                    .collect::<PyResult<Vec<_>>>()?;
                Ok(self.inner.block_counts_of(&parts))
            }
        }
    }

    /// Bytes of one 8³ block (float32 log-odds, mean end points, counts).
    #[staticmethod]
    fn block_bytes() -> usize {
        crate::filter3d::SharedVoxels::block_bytes()
    }

    #[getter]
    fn steps(&self) -> u64 {
        self.inner.steps
    }

    #[getter]
    fn resamplings(&self) -> u64 {
        self.inner.resamplings
    }

    #[getter]
    fn fallbacks(&self) -> u64 {
        self.inner.fallbacks
    }

    #[getter]
    fn resolution(&self) -> f64 {
        self.inner.params.resolution
    }
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyParticleFilter3D>()
}
