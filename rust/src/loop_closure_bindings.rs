//! PyO3 bindings of loop closure against submaps (loop_closure.rs); registered from lib.rs.
//!
//! One class, `_core.Submap`: insert scans, finish it (precomputes the search grids), then
//! search scans in it. Every argument is checked here or in the core, which answers bad ones
//! with an error, never a panic: they reach Python as ValueError.

use std::borrow::Cow;

use numpy::ndarray::Array2;
use numpy::{Element, IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::grid::LogOddsModel;
use crate::loop_closure::{MatchOptions, Submap, SubmapParams, DEFAULT_DEPTH, DEFAULT_UNKNOWN_PROBABILITY};
use crate::scan_match::{self, LikelihoodField, MatcherParams, OdometryCheck};
use crate::sensor_model::ScanGeometry;

/// The values of a 1-D array, copied only if it is not contiguous (a slice such as a[::2]).
fn values<'a, T: Element + Copy>(a: &'a PyReadonlyArray1<'_, T>) -> Cow<'a, [T]> {
    match a.as_slice() {
        Ok(s) => Cow::Borrowed(s),
        Err(_) => Cow::Owned(a.as_array().to_vec()),
    }
}

fn pose(a: &PyReadonlyArray1<'_, f64>, what: &str) -> PyResult<[f64; 3]> {
    let v = values(a);
    if v.len() != 3 || !v.iter().all(|x| x.is_finite()) {
        return Err(PyValueError::new_err(format!("{what} must be a finite pose (x, y, theta)")));
    }
    Ok([v[0], v[1], v[2]])
}

fn sensor(sensor_pose: Option<&PyReadonlyArray1<'_, f64>>) -> PyResult<[f64; 3]> {
    sensor_pose.map_or(Ok([0.0; 3]), |s| pose(s, "sensor_pose"))
}

/// (pose (3,), score, covariance (3, 3)) of a match.
type Match<'py> = (Bound<'py, PyArray1<f64>>, f64, Bound<'py, PyArray2<f64>>);

/// A local occupancy grid for loop closure: scans go in at robot poses; once finished, scans
/// are searched in it by branch and bound, on its probabilities spread by `spread_sigma` (m: an
/// end point's standard deviation about its obstacle; 0 searches the raw probabilities).
#[pyclass(name = "Submap", module = "omnitof._core")]
struct PySubmap {
    inner: Submap,
    pool: Option<rayon::ThreadPool>,
}

#[pymethods]
impl PySubmap {
    #[new]
    #[pyo3(signature = (resolution, l_occ, l_free, l_min, l_max, max_range, *, clear_no_echo=false,
        once_per_scan=false, unknown_probability=DEFAULT_UNKNOWN_PROBABILITY, depth=DEFAULT_DEPTH, spread_sigma=0.0, threads=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        resolution: f64,
        l_occ: f32,
        l_free: f32,
        l_min: f32,
        l_max: f32,
        max_range: f64,
        clear_no_echo: bool,
        once_per_scan: bool,
        unknown_probability: f32,
        depth: u32,
        spread_sigma: f64,
        threads: Option<usize>,
    ) -> PyResult<Self> {
        let params = SubmapParams {
            resolution,
            log_odds: LogOddsModel { l_occ, l_free, l_min, l_max },
            max_range,
            clear_no_echo,
            once_per_scan,
            unknown_probability,
            depth,
            spread_sigma,
        };
        let inner = Submap::new(params).map_err(PyValueError::new_err)?;
        let pool = crate::optional_pool(threads)?;
        Ok(PySubmap { inner, pool })
    }

    /// Write a scan (ranges, +inf = no echo; beam angles in the sensor frame) taken at robot
    /// pose `pose` (world frame) into the submap.
    #[pyo3(signature = (pose, ranges, angles, sensor_pose=None))]
    fn insert(
        &mut self,
        pose: PyReadonlyArray1<f64>,
        ranges: PyReadonlyArray1<f32>,
        angles: PyReadonlyArray1<f64>,
        sensor_pose: Option<PyReadonlyArray1<f64>>,
    ) -> PyResult<()> {
        let robot = self::pose(&pose, "pose")?;
        let (ranges, angles) = (values(&ranges), values(&angles));
        let geom = ScanGeometry { angles: &angles, sensor: sensor(sensor_pose.as_ref())? };
        self.inner.insert(robot, &geom, &ranges).map_err(PyValueError::new_err)
    }

    /// Finish the submap: no more scans; precompute the search grids (once).
    fn finish(&mut self, py: Python<'_>) -> PyResult<()> {
        let (inner, pool) = (&mut self.inner, &self.pool);
        py.detach(|| match pool {
            Some(pool) => pool.install(|| inner.finish().map(|_| ())),
            None => inner.finish().map(|_| ()),
        })
        .map_err(crate::grid_error)
    }

    /// Drop the precomputed search grids of a finished submap to save memory; the next
    /// `match_scan` (or `finish`) makes them again, the same to the bit.
    fn release_grids(&mut self) {
        self.inner.release_grids()
    }

    /// Whether the search grids are in memory (a finished submap that has not released them).
    #[getter]
    fn has_grids(&self) -> bool {
        self.inner.grids().is_some()
    }

    /// The widest a submap may be, in cells (a submap is local; see loop_closure.rs).
    #[staticmethod]
    fn max_side_cells() -> f64 {
        crate::loop_closure::MAX_SIDE_CELLS
    }

    #[getter]
    fn finished(&self) -> bool {
        self.inner.is_finished()
    }

    #[getter]
    fn num_scans(&self) -> usize {
        self.inner.num_scans()
    }

    /// Robot pose (3,) of the first inserted scan; None while empty.
    #[getter]
    fn origin<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray1<f64>>> {
        self.inner.origin().map(|o| PyArray1::from_slice(py, &o))
    }

    #[getter]
    fn resolution(&self) -> f64 {
        self.inner.params().resolution
    }

    /// Bytes held by the grid's tiles and the precomputed grids.
    fn memory_bytes(&self) -> usize {
        self.inner.memory_bytes()
    }

    /// (log-odds (rows, cols) with NaN = unknown, ix0, iy0): cell (r, c) is (ix0 + c, iy0 + r).
    fn to_dense<'py>(&self, py: Python<'py>) -> PyResult<(Bound<'py, PyArray2<f32>>, i32, i32)> {
        crate::dense(py, self.inner.grid())
    }

    /// Search a scan in the finished submap within ± `linear_window` (m) in x and y and
    /// ± `angular_window` (rad, π or more: every heading) of `initial_pose`; with `refine`,
    /// refine the match below the grid resolution. None if no pose scores `min_score` (mean
    /// occupancy probability of the end points, in [0, 1]); else (pose (3,), score,
    /// covariance (3, 3)). With `field_sigma` (m), the pose is then matched locally on the
    /// submap's likelihood field as the filter matches its scans (scan_match::local_match: the
    /// cells' mean end points, so walls off the cell grid are not pulled onto it), so that a
    /// closure is as precise as the front end's own steps.
    #[pyo3(signature = (ranges, angles, initial_pose, linear_window, angular_window, min_score, sensor_pose=None, refine=true, field_sigma=None))]
    #[allow(clippy::too_many_arguments)]
    fn match_scan<'py>(
        slf: &Bound<'py, Self>,
        ranges: PyReadonlyArray1<f32>,
        angles: PyReadonlyArray1<f64>,
        initial_pose: PyReadonlyArray1<f64>,
        linear_window: f64,
        angular_window: f64,
        min_score: f64,
        sensor_pose: Option<PyReadonlyArray1<f64>>,
        refine: bool,
        field_sigma: Option<f64>,
    ) -> PyResult<Option<Match<'py>>> {
        if let Some(s) = field_sigma {
            if !(s.is_finite() && s > 0.0) {
                return Err(PyValueError::new_err("field_sigma must be positive and finite"));
            }
        }
        let py = slf.py();
        if !slf.borrow().inner.is_finished() {
            return Err(PyValueError::new_err("the submap is not finished: call finish() first"));
        }
        let initial = pose(&initial_pose, "initial_pose")?;
        if !(linear_window.is_finite() && linear_window > 0.0 && angular_window.is_finite() && angular_window > 0.0) {
            return Err(PyValueError::new_err("linear_window and angular_window must be positive and finite"));
        }
        if !(0.0..=1.0).contains(&min_score) {
            return Err(PyValueError::new_err("min_score must lie in [0, 1]"));
        }
        let (ranges, angles) = (values(&ranges), values(&angles));
        if ranges.len() != angles.len() {
            return Err(PyValueError::new_err("angles and ranges differ in length"));
        }
        let geom = ScanGeometry { angles: &angles, sensor: sensor(sensor_pose.as_ref())? };
        let ranges: &[f32] = &ranges;
        let opts = MatchOptions { linear_window, angular_window, min_score, refine };
        if slf.borrow().inner.grids().is_none() {
            // Released: made again, with the GIL held, so that a thread searching meanwhile
            // waits for them instead of finding the submap borrowed.
            let mut this = slf.borrow_mut();
            let PySubmap { inner, pool, .. } = &mut *this;
            match pool {
                Some(pool) => pool.install(|| inner.finish().map(|_| ())),
                None => inner.finish().map(|_| ()),
            }
            .map_err(crate::grid_error)?;
        }
        // A shared borrow for the search itself, so that threads may search one submap at once.
        let this = slf.borrow();
        let (inner, pool) = (&this.inner, &this.pool);
        let found = py
            .detach(|| match pool {
                Some(pool) => pool.install(|| inner.match_scan(&geom, ranges, initial, &opts)),
                None => inner.match_scan(&geom, ranges, initial, &opts),
            })
            .map_err(PyValueError::new_err)?;
        let found = match (found, field_sigma) {
            (Some(mut m), Some(sigma)) => {
                m.pose = field_match(inner, &geom, ranges, m.pose, sigma);
                Some(m)
            }
            (found, _) => found,
        };
        Ok(found.map(|m| {
            let cov: Vec<f64> = m.covariance.iter().flatten().copied().collect();
            (
                PyArray1::from_slice(py, &m.pose),
                m.score,
                Array2::from_shape_vec((3, 3), cov).unwrap().into_pyarray(py),
            )
        }))
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PySubmap>()
}

/// The filter's local matcher (hill climbing from small steps, then Gauss-Newton) on the
/// submap's likelihood field, from `start`.
fn field_match(sub: &Submap, geom: &ScanGeometry, ranges: &[f32], start: [f64; 3], sigma: f64) -> [f64; 3] {
    let max_range = sub.params().max_range;
    let lf = LikelihoodField::new(sigma, 0.9, 0.1, max_range, 3, 0.0, false);
    let m = MatcherParams {
        step_xy: 0.01, step_theta: 0.005, refinements: 2, gauss_newton: 10, sample_xy: 0.005, sample_theta: 0.002,
        min_matched: 0.0, effective_beams: 1.0, odometry_prior: false, prior_dof: 0.0, climb_from_sample: false, fallback_draw: true, check: OdometryCheck::OFF,
    };
    let pts = scan_match::endpoints(geom, ranges, 1, max_range);
    if pts.is_empty() {
        return start;
    }
    let view = scan_match::FieldView::new(&lf, sub.grid());
    scan_match::local_match(&view, &m, geom, &pts, start, None).0
}
