//! PyO3 bindings of omnitof's core: numpy arrays in, numpy arrays out, nothing else here.
//! The algorithms live in the other modules and know nothing of Python.

pub mod correlative;
pub mod filter;
pub mod filter3d;
mod filter3d_bindings;
pub mod grid;
pub mod light;
pub mod loop_closure;
mod loop_closure_bindings;
pub mod motion;
pub mod multipath;
mod multipath_bindings;
pub mod raycast;
pub mod render;
mod render_bindings;
pub mod rvl;
pub mod scan_match;
pub mod sensor_model;
#[cfg(test)]
mod test_support;
pub mod tof_frames;
pub mod voxel;

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyMemoryError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use filter::{FilterParams, ObservationKind, ParticleFilter, ProposalKind};
use correlative::SearchWindow;
use scan_match::{LikelihoodField, MatcherParams, OdometryCheck};
use grid::{GridError, LogOddsModel, TiledGrid};
use motion::OdometryMotion;
use sensor_model::{integrate_scan, BeamModel, ScanGeometry};
use voxel::VoxelGrid;

/// The data of a numpy array in C (row-major) order. rust-numpy's `as_slice` takes a
/// Fortran-ordered array too, and hands over its columns as rows (`xyz.T` of a (3, N) array
/// was read as other points): such an array is refused.
pub(crate) trait COrder<T> {
    fn c_slice(&self, what: &str) -> PyResult<&[T]>;
}

impl<T: numpy::Element, D: numpy::ndarray::Dimension> COrder<T> for numpy::PyReadonlyArray<'_, T, D> {
    fn c_slice(&self, what: &str) -> PyResult<&[T]> {
        if !self.is_c_contiguous() {
            return Err(PyTypeError::new_err(format!(
                "{what}: an array of shape {:?} is not C-ordered (row-major) and contiguous: pass numpy.ascontiguousarray(it)",
                self.shape()
            )));
        }
        Ok(self.as_slice()?)
    }
}

/// Most worker threads a pool is made with: more only exhausts the machine (a pool of 10⁹
/// threads hung), never speeds a run.
pub(crate) const MAX_THREADS: usize = 1024;

/// `threads` checked: at least 1 and at most MAX_THREADS.
pub(crate) fn checked_threads(threads: usize, what: &str) -> PyResult<usize> {
    if !(1..=MAX_THREADS).contains(&threads) {
        return Err(PyValueError::new_err(format!("{what} must lie in 1..={MAX_THREADS}, got {threads}")));
    }
    Ok(threads)
}

/// A grid's log-odds increments and clamps, checked: finite, and l_min <= l_max (a clamp the
/// other way round panicked at the first scan).
pub(crate) fn log_odds_model(l_occ: f32, l_free: f32, l_min: f32, l_max: f32) -> PyResult<LogOddsModel> {
    if ![l_occ, l_free, l_min, l_max].iter().all(|v| v.is_finite()) {
        return Err(PyValueError::new_err("l_occ, l_free, l_min and l_max must be finite"));
    }
    if !(l_min <= l_max) {
        return Err(PyValueError::new_err("l_min must not exceed l_max"));
    }
    Ok(LogOddsModel { l_occ, l_free, l_min, l_max })
}

/// The local climb of `OccupancyGrid.match_scan`: hill climbing in steps of `step_xy` and
/// `step_theta`, halved `refinements` times, then `gauss_newton` Gauss-Newton steps.
fn climb_params(step_xy: f64, step_theta: f64, refinements: u32, gauss_newton: u32) -> PyResult<MatcherParams> {
    if !(step_xy.is_finite() && step_xy > 0.0 && step_theta.is_finite() && step_theta > 0.0) {
        return Err(PyValueError::new_err("step_xy and step_theta must be positive and finite"));
    }
    if refinements > MAX_MATCH_ITERATIONS || gauss_newton > MAX_MATCH_ITERATIONS {
        return Err(PyValueError::new_err(format!("refinements and gauss_newton must not exceed {MAX_MATCH_ITERATIONS}")));
    }
    Ok(MatcherParams {
        step_xy, step_theta, refinements, gauss_newton, sample_xy: 0.01, sample_theta: 0.005,
        min_matched: 0.0, effective_beams: 1.0, odometry_prior: false, prior_dof: 0.0, climb_from_sample: false, fallback_draw: true, check: OdometryCheck::OFF,
    })
}

/// A rayon pool of `threads` workers, or None (rayon's global pool) when not given.
pub(crate) fn optional_pool(threads: Option<usize>) -> PyResult<Option<rayon::ThreadPool>> {
    match threads {
        Some(n) => rayon::ThreadPoolBuilder::new()
            .num_threads(checked_threads(n, "threads")?)
            .build()
            .map(Some)
            .map_err(|e| PyValueError::new_err(e.to_string())),
        None => Ok(None),
    }
}

/// A grid's error as the Python exception a caller can act on: memory that cannot be had is a
/// MemoryError, a point beyond a grid's reach a ValueError (never a panic or an abort).
pub(crate) fn grid_error(err: GridError) -> PyErr {
    match err {
        GridError::NoMemory { .. } => PyMemoryError::new_err(err.to_string()),
        GridError::OutOfReach { .. } => PyValueError::new_err(err.to_string()),
    }
}

fn pose3(v: &[f64], what: &str) -> PyResult<[f64; 3]> {
    if v.len() != 3 {
        return Err(PyValueError::new_err(format!("{what} must be a pose (x, y, theta)")));
    }
    Ok([v[0], v[1], v[2]])
}

fn rows3<'py>(py: Python<'py>, poses: &[[f64; 3]]) -> Bound<'py, PyArray2<f64>> {
    let flat: Vec<f64> = poses.iter().flat_map(|p| p.iter().copied()).collect();
    Array2::from_shape_vec((poses.len(), 3), flat).unwrap().into_pyarray(py)
}

/// Scan geometry from beam angles (checked against the ranges) and an optional sensor pose.
fn scan_geometry<'a>(
    angles: &'a [f64],
    ranges: &[f32],
    sensor_pose: Option<PyReadonlyArray1<f64>>,
) -> PyResult<ScanGeometry<'a>> {
    let angles = scan_angles(angles, ranges.len())?;
    let sensor = match sensor_pose {
        Some(s) => pose3(s.c_slice("sensor_pose")?, "sensor_pose")?,
        None => [0.0; 3],
    };
    if !sensor.iter().all(|v| v.is_finite()) {
        return Err(PyValueError::new_err("sensor_pose must be finite"));
    }
    Ok(ScanGeometry { angles, sensor })
}

/// Largest likelihood-field window (cells) the grid's matchers take: the configuration allows
/// 20 (`likelihood_field.window_cells`); the search walks (2w + 1)² cells per end point.
const MAX_FIELD_WINDOW: i32 = 64;
/// Largest number of hill-climbing refinements and Gauss-Newton iterations the grid's matchers
/// take (the configuration allows 20 and 100): each refinement halves the steps, so more than
/// this only spends time below any grid's precision.
const MAX_MATCH_ITERATIONS: u32 = 1000;

/// The likelihood field's settings as the grid's matchers take them, or a ValueError naming
/// what is wrong (NaN and infinite values included).
fn field_settings(sigma: f64, max_range: f64, window: i32, prefix: &str) -> PyResult<()> {
    if !(sigma.is_finite() && sigma > 0.0 && max_range.is_finite() && max_range > 0.0) {
        return Err(PyValueError::new_err(format!("{prefix}sigma and max_range must be positive and finite")));
    }
    if !(1..=MAX_FIELD_WINDOW).contains(&window) {
        return Err(PyValueError::new_err(format!("{prefix}window must lie in 1..={MAX_FIELD_WINDOW} cells, got {window}")));
    }
    Ok(())
}

/// The likelihood field's weights: z_rand > 0, since with none a single end point far from every
/// wall has likelihood 0 and makes every particle's weight 0 (NaN once normalised).
fn field_weights(z_hit: f64, z_rand: f64) -> PyResult<()> {
    if !(z_hit.is_finite() && z_hit >= 0.0 && z_rand.is_finite() && z_rand > 0.0) {
        return Err(PyValueError::new_err(format!(
            "likelihood_field: z_hit must be at least 0 and z_rand above 0, got {z_hit} and {z_rand}"
        )));
    }
    Ok(())
}

/// The beam model, checked: weights at least 0, sigma_hit, lambda_short and max_range positive
/// and finite (a NaN sigma gave plausible densities, a zero one NaN weights).
fn beam_model(m: BeamModel, prefix: &str) -> PyResult<BeamModel> {
    let weights = [m.z_hit, m.z_short, m.z_max, m.z_rand].iter().all(|w| w.is_finite() && *w >= 0.0);
    let positive = [m.sigma_hit, m.lambda_short, m.max_range].iter().all(|v| v.is_finite() && *v > 0.0);
    if !(weights && positive) {
        return Err(PyValueError::new_err(format!(
            "{prefix}z_hit, z_short, z_max and z_rand must be at least 0, sigma_hit, lambda_short and max_range positive and finite"
        )));
    }
    Ok(m)
}

/// A scan's own beam bearings: one finite angle per range.
fn scan_angles(angles: &[f64], n_ranges: usize) -> PyResult<&[f64]> {
    if angles.len() != n_ranges {
        return Err(PyValueError::new_err(format!("scan has {n_ranges} ranges but {} angles", angles.len())));
    }
    if !angles.iter().all(|a| a.is_finite()) {
        return Err(PyValueError::new_err("scan angles must be finite"));
    }
    Ok(angles)
}

type DenseGrid<'py> = (Bound<'py, PyArray2<f32>>, i32, i32);

pub(crate) fn dense<'py>(py: Python<'py>, grid: &TiledGrid) -> PyResult<DenseGrid<'py>> {
    let (rows, cols, ix0, iy0, data) = grid.to_dense().map_err(grid_error)?;
    let array = Array2::from_shape_vec((rows, cols), data).map_err(|e| PyValueError::new_err(e.to_string()))?;
    Ok((array.into_pyarray(py), ix0, iy0))
}

/// A section of the SLAM configuration as a Rust struct, read from the section's dict
/// (`SlamConfig.<section>.model_dump()`, python/omnitof/slam/config.py). Fields have the names,
/// units and types of the configuration; defaults and validation live there alone. A key
/// that is unknown or missing is an error: an option added on one side only must not be
/// silently ignored.
macro_rules! config_section {
    ($(#[$meta:meta])* $name:ident = $section:literal { $($(#[$fmeta:meta])* $field:ident: $ty:ty,)* }) => {
        $(#[$meta])*
        struct $name {
            $($(#[$fmeta])* $field: $ty,)*
        }

        impl<'a, 'py> FromPyObject<'a, 'py> for $name {
            type Error = PyErr;

            fn extract(obj: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
                let dict = section_dict(&obj, $section, &[$(stringify!($field)),*])?;
                Ok($name { $($field: section_field(&dict, $section, stringify!($field))?,)* })
            }
        }
    };
}

/// The dict of configuration section `section`, checked to hold no key but `fields`.
fn section_dict<'py>(obj: &Borrowed<'_, 'py, PyAny>, section: &str, fields: &[&str]) -> PyResult<Bound<'py, PyDict>> {
    let dict = obj.cast::<PyDict>().map_err(|_| {
        PyTypeError::new_err(format!("{section}: the section must be a dict of its fields"))
    })?;
    for key in dict.keys() {
        let key: String = key.str()?.extract()?;
        if !fields.contains(&key.as_str()) {
            return Err(PyValueError::new_err(format!("{section}.{key}: unknown field")));
        }
    }
    Ok(dict.to_owned())
}

fn section_field<'py, T>(dict: &Bound<'py, PyDict>, section: &str, field: &str) -> PyResult<T>
where
    T: for<'a> FromPyObject<'a, 'py, Error = PyErr>,
{
    let value = dict
        .get_item(field)?
        .ok_or_else(|| PyValueError::new_err(format!("{section}.{field}: missing field")))?;
    value
        .extract()
        .map_err(|err| PyTypeError::new_err(format!("{section}.{field}: {err}")))
}

config_section! {
    /// `filter`, less the scan selection (linear_update, angular_update_deg) that the driver does.
    FilterSection = "filter" {
        particles: usize,
        proposal: String,
        resample_threshold: f64,
        seed: u64,
        /// 0: one per core.
        threads: usize,
    }
}

config_section! {
    MotionSection = "motion" {
        alpha1: f64,
        alpha2: f64,
        alpha3: f64,
        alpha4: f64,
    }
}

config_section! {
    SensorModelSection = "sensor_model" {
        model: String,
        z_hit: f64,
        z_short: f64,
        z_max: f64,
        z_rand: f64,
        sigma_hit: f64,
        lambda_short: f64,
        max_range: f64,
        beam_stride: usize,
        effective_beams: f64,
    }
}

config_section! {
    LikelihoodFieldSection = "likelihood_field" {
        sigma: f64,
        z_hit: f64,
        z_rand: f64,
        window_cells: i32,
        fit_walls: bool,
    }
}

config_section! {
    ScanMatcherSection = "scan_matcher" {
        step_xy: f64,
        step_deg: f64,
        refinements: u32,
        gauss_newton: u32,
        sample_xy: f64,
        sample_deg: f64,
        odometry_prior: bool,
        prior_dof: f64,
        min_matched: f64,
        climb_from_sample: bool,
        fallback: String,
        search_xy: f64,
        search_deg: f64,
        search_step_xy: f64,
        search_step_deg: f64,
        search_below: f64,
        search_accept: Option<f64>,
        search_distinct: f64,
        search_min_points: usize,
    }
}

config_section! {
    MapSection = "map" {
        resolution: f64,
        l_occ: f32,
        l_free: f32,
        l_min: f32,
        l_max: f32,
        occupied_threshold: f32,
        max_range: f64,
        clear_no_echo: bool,
        once_per_scan: bool,
    }
}

/// The core's parameters from the configuration's sections and the sensor's largest range: the
/// one place where degrees become radians and the configured ranges are capped by the sensor's.
fn filter_params(
    f: FilterSection,
    m: MotionSection,
    s: SensorModelSection,
    lf: LikelihoodFieldSection,
    sm: ScanMatcherSection,
    g: MapSection,
    scan_max_range: f64,
) -> PyResult<FilterParams> {
    let proposal = match f.proposal.as_str() {
        "odometry" => ProposalKind::Odometry,
        "scanmatch" => ProposalKind::ScanMatch,
        other => return Err(PyValueError::new_err(format!("filter.proposal: unknown proposal {other:?}"))),
    };
    let fallback_draw = match sm.fallback.as_str() {
        "prediction" => false,
        "draw" => true,
        other => return Err(PyValueError::new_err(format!("scan_matcher.fallback: unknown fallback {other:?} (prediction or draw)"))),
    };
    let observation = match s.model.as_str() {
        "beam" => ObservationKind::Beam,
        "likelihood_field" => ObservationKind::LikelihoodField,
        other => return Err(PyValueError::new_err(format!("sensor_model.model: unknown observation model {other:?}"))),
    };
    field_weights(lf.z_hit, lf.z_rand)?;
    if sm.search_xy > 0.0 && !(sm.search_step_xy > 0.0 && sm.search_step_deg > 0.0) {
        return Err(PyValueError::new_err("scan_matcher: the wide search needs positive steps"));
    }
    let search = (sm.search_xy > 0.0).then_some(SearchWindow {
        half_xy: sm.search_xy,
        half_theta: sm.search_deg.to_radians(),
        step_xy: sm.search_step_xy,
        step_theta: sm.search_step_deg.to_radians(),
    });
    let threads = match f.threads {
        0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
        n => checked_threads(n, "filter.threads")?,
    };
    // What the config layer checks, checked again here for the Python API: a clamp the wrong
    // way round panicked, an unbounded iteration count hung, NaN sigmas and steps ran on
    // without a word.
    let log_odds = log_odds_model(g.l_occ, g.l_free, g.l_min, g.l_max)?;
    if !(g.resolution.is_finite() && g.resolution > 0.0) {
        return Err(PyValueError::new_err(format!("map.resolution must be positive and finite, got {}", g.resolution)));
    }
    if sm.refinements > MAX_MATCH_ITERATIONS || sm.gauss_newton > MAX_MATCH_ITERATIONS {
        return Err(PyValueError::new_err(format!(
            "scan_matcher.refinements and gauss_newton must not exceed {MAX_MATCH_ITERATIONS}"
        )));
    }
    if !(sm.step_xy.is_finite() && sm.step_xy > 0.0 && sm.step_deg.is_finite() && sm.step_deg > 0.0) {
        return Err(PyValueError::new_err("scan_matcher.step_xy and step_deg must be positive and finite"));
    }
    // Readings beyond the sensor's range are no echo, whatever the configuration allows.
    let max_range = s.max_range.min(scan_max_range);
    field_settings(lf.sigma, max_range, lf.window_cells, "likelihood_field: ")?;
    if ![m.alpha1, m.alpha2, m.alpha3, m.alpha4].iter().all(|a| a.is_finite() && *a >= 0.0) {
        return Err(PyValueError::new_err("motion.alpha1..alpha4 must be finite and at least 0"));
    }
    let beam = beam_model(
        BeamModel {
            z_hit: s.z_hit,
            z_short: s.z_short,
            z_max: s.z_max,
            z_rand: s.z_rand,
            sigma_hit: s.sigma_hit,
            lambda_short: s.lambda_short,
            max_range,
            occupied_threshold: g.occupied_threshold,
        },
        "sensor_model: ",
    )?;
    if s.beam_stride < 1 || !(s.effective_beams.is_finite() && s.effective_beams > 0.0) {
        return Err(PyValueError::new_err("sensor_model.beam_stride must be at least 1 and effective_beams positive and finite"));
    }
    Ok(FilterParams {
        n_particles: f.particles,
        seed: f.seed,
        threads,
        motion: OdometryMotion { alpha: [m.alpha1, m.alpha2, m.alpha3, m.alpha4] },
        proposal,
        observation,
        beam,
        field: LikelihoodField::new(lf.sigma, lf.z_hit, lf.z_rand, max_range, lf.window_cells, g.occupied_threshold, lf.fit_walls),
        matcher: MatcherParams {
            step_xy: sm.step_xy,
            step_theta: sm.step_deg.to_radians(),
            refinements: sm.refinements,
            gauss_newton: sm.gauss_newton,
            sample_xy: sm.sample_xy,
            sample_theta: sm.sample_deg.to_radians(),
            min_matched: sm.min_matched,
            effective_beams: s.effective_beams,
            odometry_prior: sm.odometry_prior,
            prior_dof: sm.prior_dof,
            climb_from_sample: sm.climb_from_sample,
            fallback_draw,
            check: OdometryCheck {
                window: search,
                below: sm.search_below,
                accept: sm.search_accept.unwrap_or(sm.search_below),
                distinct: sm.search_distinct,
                min_points: sm.search_min_points,
            },
        },
        beam_stride: s.beam_stride,
        effective_beams: s.effective_beams,
        log_odds,
        resolution: g.resolution,
        map_max_range: g.max_range.min(scan_max_range),
        clear_no_echo: g.clear_no_echo,
        once_per_scan: g.once_per_scan,
        resample_threshold: f.resample_threshold,
    })
}

#[pyclass(name = "ParticleFilter", module = "omnitof._core")]
struct PyParticleFilter {
    inner: ParticleFilter,
}

#[pymethods]
impl PyParticleFilter {
    /// A filter for the configuration's sections (each the dict `SlamConfig.<section>.model_dump()`)
    /// and a sensor: its beam angles, its pose on the robot and its largest range.
    #[new]
    #[pyo3(signature = (*, filter, motion, sensor_model, likelihood_field, scan_matcher, map,
        angles, sensor_pose, scan_max_range))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        filter: FilterSection,
        motion: MotionSection,
        sensor_model: SensorModelSection,
        likelihood_field: LikelihoodFieldSection,
        scan_matcher: ScanMatcherSection,
        map: MapSection,
        angles: PyReadonlyArray1<f64>,
        sensor_pose: PyReadonlyArray1<f64>,
        scan_max_range: f64,
    ) -> PyResult<Self> {
        if !(scan_max_range.is_finite() && scan_max_range > 0.0) {
            return Err(PyValueError::new_err("scan_max_range must be positive and finite"));
        }
        let params = filter_params(filter, motion, sensor_model, likelihood_field, scan_matcher, map, scan_max_range)?;
        let sensor = pose3(sensor_pose.c_slice("sensor_pose")?, "sensor_pose")?;
        if !sensor.iter().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("sensor_pose must be finite"));
        }
        let angles = angles.c_slice("angles")?;
        if !angles.iter().all(|a| a.is_finite()) {
            return Err(PyValueError::new_err("angles must be finite"));
        }
        let inner = ParticleFilter::new(params, angles.to_vec(), sensor).map_err(PyValueError::new_err)?;
        Ok(PyParticleFilter { inner })
    }

    /// Integrate one scan; returns (Neff before any resampling, whether it resampled, whether the
    /// wide search replaced the step's odometry increment). `angles`: this scan's own beam
    /// bearings, one per range, where the geometry changes from scan to scan; None: the filter's.
    #[pyo3(signature = (odom_prev, odom_cur, ranges, scan, angles=None))]
    fn step(
        &mut self,
        py: Python<'_>,
        odom_prev: PyReadonlyArray1<f64>,
        odom_cur: PyReadonlyArray1<f64>,
        ranges: PyReadonlyArray1<f32>,
        scan: u64,
        angles: Option<PyReadonlyArray1<f64>>,
    ) -> PyResult<(f64, bool, bool)> {
        let prev = pose3(odom_prev.c_slice("odom_prev")?, "odom_prev")?;
        let cur = pose3(odom_cur.c_slice("odom_cur")?, "odom_cur")?;
        if !prev.iter().chain(cur.iter()).all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("odom_prev and odom_cur must be finite poses"));
        }
        let ranges = ranges.c_slice("ranges")?;
        let angles = match &angles {
            Some(a) => Some(scan_angles(a.c_slice("angles")?, ranges.len())?),
            None if ranges.len() != self.inner.n_beams() => {
                return Err(PyValueError::new_err(format!(
                    "scan has {} ranges, the filter was made for {} (give the scan's own angles)",
                    ranges.len(),
                    self.inner.n_beams()
                )))
            }
            None => None,
        };
        let inner = &mut self.inner;
        let info = py.detach(|| inner.step(prev, cur, ranges, angles, scan)).map_err(grid_error)?;
        Ok((info.neff, info.resampled, info.odometry_corrected))
    }

    /// (pose, matched share) of one local match of a scan in the best particle's map from
    /// `start` (see ParticleFilter::match_in_best); None before the first scan.
    #[pyo3(signature = (start, ranges, angles=None))]
    fn match_scan(
        &self,
        py: Python<'_>,
        start: PyReadonlyArray1<f64>,
        ranges: PyReadonlyArray1<f32>,
        angles: Option<PyReadonlyArray1<f64>>,
    ) -> PyResult<Option<([f64; 3], f64)>> {
        let start = pose3(start.c_slice("start")?, "start")?;
        if !start.iter().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("start must be a finite pose"));
        }
        let ranges = ranges.c_slice("ranges")?;
        let angles = match &angles {
            Some(a) => Some(a.c_slice("angles")?),
            None => None,
        };
        let n = angles.map_or(self.inner.n_beams(), |a| a.len());
        if ranges.len() != n {
            return Err(PyValueError::new_err(format!("scan has {} ranges for {} beam angles", ranges.len(), n)));
        }
        let inner = &self.inner;
        Ok(py.detach(|| inner.match_in_best(start, ranges, angles)))
    }

    /// Poses of the scans between integrated ones (ParticleFilter::match_chain): `odometry`
    /// (M + 1, 3), the first row the scan before them; `ranges` (M, B), padding +inf; `angles`
    /// (M, B) or None (the filter's). Returns (poses relative to the best particle's, (M, 3);
    /// whether each match stood, (M,)), or None before the first scan.
    #[pyo3(signature = (odometry, ranges, min_matched, angles=None))]
    fn match_scans<'py>(
        &self,
        py: Python<'py>,
        odometry: PyReadonlyArray2<f64>,
        ranges: PyReadonlyArray2<f32>,
        min_matched: f64,
        angles: Option<PyReadonlyArray2<f64>>,
    ) -> PyResult<Option<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<bool>>)>> {
        let odometry = points3(&odometry, "odometry")?;
        if !odometry.iter().flatten().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("odometry must be finite"));
        }
        let (m, beams) = (ranges.shape()[0], ranges.shape()[1]);
        if odometry.len() != m + 1 {
            return Err(PyValueError::new_err(format!("{} scans need {} odometry rows, got {}", m, m + 1, odometry.len())));
        }
        let angles_slice = match &angles {
            Some(a) if a.shape() != ranges.shape() => {
                return Err(PyValueError::new_err(format!("angles {:?} and ranges {:?} differ in shape", a.shape(), ranges.shape())));
            }
            Some(a) => Some(a.c_slice("angles")?),
            None if beams != self.inner.n_beams() => {
                return Err(PyValueError::new_err(format!("scans have {} ranges for {} beam angles", beams, self.inner.n_beams())));
            }
            None => None,
        };
        let ranges = ranges.c_slice("ranges")?;
        let inner = &self.inner;
        let found = py.detach(|| inner.match_chain(&odometry, ranges, angles_slice, beams, min_matched));
        Ok(found.map(|(poses, matched)| (rows3(py, &poses), PyArray1::from_vec(py, matched))))
    }

    /// The best particle's pose (x, y, theta), or None before the first scan.
    fn best_pose<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray1<f64>>> {
        self.inner.best().map(|p| PyArray1::from_vec(py, p.pose.to_vec()))
    }

    /// Restart every particle at `pose` with a copy of `grid`'s map, trajectories beginning at
    /// scan `scan` (a correction fed back from the pose graph).
    fn reset(&mut self, pose: PyReadonlyArray1<f64>, scan: u64, grid: PyRef<'_, PyOccupancyGrid>) -> PyResult<()> {
        let pose = pose3(pose.c_slice("pose")?, "pose")?;
        if !pose.iter().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("pose must be finite"));
        }
        if grid.grid.resolution != self.inner.params.resolution {
            return Err(PyValueError::new_err(format!(
                "the grid's resolution {} differs from the filter's {}",
                grid.grid.resolution,
                self.inner.params.resolution
            )));
        }
        let map = grid.grid.try_clone().map_err(grid_error)?;
        self.inner.reset(pose, scan, map).map_err(grid_error)
    }

    /// (scan indices (K,), poses (K, 3)) of the best particle's integrated scans.
    fn best_trajectory<'py>(&self, py: Python<'py>) -> (Bound<'py, PyArray1<u64>>, Bound<'py, PyArray2<f64>>) {
        let traj = self.inner.best().map(ParticleFilter::trajectory_of).unwrap_or_default();
        let scans: Vec<u64> = traj.iter().map(|t| t.0).collect();
        let poses: Vec<[f64; 3]> = traj.iter().map(|t| t.1).collect();
        (PyArray1::from_vec(py, scans), rows3(py, &poses))
    }

    /// (log-odds (rows, cols) with NaN = unknown, ix0, iy0) of the best particle's map.
    fn best_map<'py>(&self, py: Python<'py>) -> PyResult<DenseGrid<'py>> {
        match self.inner.best() {
            Some(p) => dense(py, &p.map),
            None => dense(py, &TiledGrid::new(self.inner.params.resolution)),
        }
    }

    fn map_of<'py>(&self, py: Python<'py>, index: usize) -> PyResult<DenseGrid<'py>> {
        let p = self.inner.particles.get(index).ok_or_else(|| PyValueError::new_err("no such particle"))?;
        dense(py, &p.map)
    }

    fn poses<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let poses: Vec<[f64; 3]> = self.inner.particles.iter().map(|p| p.pose).collect();
        rows3(py, &poses)
    }

    fn log_weights<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.inner.particles.iter().map(|p| p.log_weight).collect())
    }

    /// (distinct map tiles over all particles, tile references over all particles).
    fn tile_counts(&self) -> (usize, usize) {
        self.inner.tile_counts()
    }

    #[staticmethod]
    fn tile_bytes() -> usize {
        TiledGrid::tile_bytes()
    }

    #[getter]
    fn steps(&self) -> u64 {
        self.inner.steps
    }

    #[getter]
    fn resamplings(&self) -> u64 {
        self.inner.resamplings
    }

    /// Particle draws that fell back to the odometry proposal because scan matching failed.
    #[getter]
    fn fallbacks(&self) -> u64 {
        self.inner.fallbacks
    }
}

/// A single log-odds grid, for tests and for maps built along a known trajectory.
#[pyclass(name = "OccupancyGrid", module = "omnitof._core")]
struct PyOccupancyGrid {
    grid: TiledGrid,
    model: LogOddsModel,
}

#[pymethods]
impl PyOccupancyGrid {
    #[new]
    #[pyo3(signature = (resolution, l_occ, l_free, l_min, l_max))]
    fn new(resolution: f64, l_occ: f32, l_free: f32, l_min: f32, l_max: f32) -> PyResult<Self> {
        if !(resolution > 0.0 && resolution.is_finite()) {
            return Err(PyValueError::new_err("resolution must be positive and finite"));
        }
        Ok(PyOccupancyGrid { grid: TiledGrid::new(resolution), model: log_odds_model(l_occ, l_free, l_min, l_max)? })
    }

    #[pyo3(signature = (robot_pose, angles, ranges, max_range, clear_no_echo=false, sensor_pose=None, once_per_scan=false))]
    fn integrate(
        &mut self,
        robot_pose: PyReadonlyArray1<f64>,
        angles: PyReadonlyArray1<f64>,
        ranges: PyReadonlyArray1<f32>,
        max_range: f64,
        clear_no_echo: bool,
        sensor_pose: Option<PyReadonlyArray1<f64>>,
        once_per_scan: bool,
    ) -> PyResult<()> {
        let robot = pose3(robot_pose.c_slice("robot_pose")?, "robot_pose")?;
        if !robot.iter().all(|v| v.is_finite()) || !(max_range > 0.0) {
            return Err(PyValueError::new_err("robot_pose must be finite and max_range positive"));
        }
        let (angles, ranges) = (angles.c_slice("angles")?, ranges.c_slice("ranges")?);
        let geom = scan_geometry(angles, ranges, sensor_pose)?;
        integrate_scan(&mut self.grid, &self.model, &geom, robot, ranges, max_range, clear_no_echo, once_per_scan)
            .map_err(grid_error)
    }

    /// (log-odds (rows, cols) with NaN = unknown, ix0, iy0): cell (r, c) is (ix0 + c, iy0 + r).
    fn to_dense<'py>(&self, py: Python<'py>) -> PyResult<DenseGrid<'py>> {
        dense(py, &self.grid)
    }

    /// Scan-match a scan against this map from `start` (robot pose): hill climbing, then
    /// Gauss-Newton, on the likelihood field. Returns (pose, mean log-likelihood).
    #[pyo3(signature = (start, angles, ranges, *, sensor_pose=None, sigma=0.05, window=3, max_range=20.0,
        occupied_threshold=0.0, step_xy=0.05, step_theta=0.035, refinements=3, gauss_newton=10))]
    #[allow(clippy::too_many_arguments)]
    fn match_scan(
        &self,
        start: PyReadonlyArray1<f64>,
        angles: PyReadonlyArray1<f64>,
        ranges: PyReadonlyArray1<f32>,
        sensor_pose: Option<PyReadonlyArray1<f64>>,
        sigma: f64,
        window: i32,
        max_range: f64,
        occupied_threshold: f32,
        step_xy: f64,
        step_theta: f64,
        refinements: u32,
        gauss_newton: u32,
    ) -> PyResult<([f64; 3], f64)> {
        let start = pose3(start.c_slice("start")?, "start")?;
        if !start.iter().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("start must be a finite pose"));
        }
        field_settings(sigma, max_range, window, "")?;
        let (angles, ranges) = (angles.c_slice("angles")?, ranges.c_slice("ranges")?);
        let geom = scan_geometry(angles, ranges, sensor_pose)?;
        let lf = LikelihoodField::new(sigma, 0.9, 0.1, max_range, window, occupied_threshold, false);
        let m = climb_params(step_xy, step_theta, refinements, gauss_newton)?;
        let pts = scan_match::endpoints(&geom, ranges, 1, max_range);
        let (pose, _, _) = scan_match::local_match(&scan_match::FieldView::new(&lf, &self.grid), &m, &geom, &pts, start, None);
        Ok((pose, lf.score(&self.grid, geom.sensor_pose(pose), &pts).0))
    }

    /// `match_scan` started from each row of `starts` (N, 3), the matches in parallel on
    /// `threads` workers (rayon's pool when None). Returns the pose and score of the best, the
    /// first of equal scores, so the same for any thread count.
    #[pyo3(signature = (starts, angles, ranges, *, sensor_pose=None, sigma=0.05, window=3, max_range=20.0,
        occupied_threshold=0.0, step_xy=0.05, step_theta=0.035, refinements=3, gauss_newton=10, threads=None))]
    #[allow(clippy::too_many_arguments)]
    fn match_best(
        &self,
        py: Python<'_>,
        starts: PyReadonlyArray2<f64>,
        angles: PyReadonlyArray1<f64>,
        ranges: PyReadonlyArray1<f32>,
        sensor_pose: Option<PyReadonlyArray1<f64>>,
        sigma: f64,
        window: i32,
        max_range: f64,
        occupied_threshold: f32,
        step_xy: f64,
        step_theta: f64,
        refinements: u32,
        gauss_newton: u32,
        threads: Option<usize>,
    ) -> PyResult<([f64; 3], f64)> {
        use rayon::prelude::*;
        let starts = points3(&starts, "starts")?;
        if starts.is_empty() || !starts.iter().flatten().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("starts must be one or more finite poses"));
        }
        field_settings(sigma, max_range, window, "")?;
        let m = climb_params(step_xy, step_theta, refinements, gauss_newton)?;
        let (angles, ranges) = (angles.c_slice("angles")?, ranges.c_slice("ranges")?);
        let geom = scan_geometry(angles, ranges, sensor_pose)?;
        let pool = optional_pool(threads)?;
        let lf = LikelihoodField::new(sigma, 0.9, 0.1, max_range, window, occupied_threshold, false);
        let pts = scan_match::endpoints(&geom, ranges, 1, max_range);
        let grid = &self.grid;
        let climb = |start: &[f64; 3]| {
            let (pose, _, _) = scan_match::local_match(&scan_match::FieldView::new(&lf, grid), &m, &geom, &pts, *start, None);
            (pose, lf.score(grid, geom.sensor_pose(pose), &pts).0)
        };
        let run = || -> Vec<([f64; 3], f64)> { starts.par_iter().map(climb).collect() };
        let found = py.detach(|| match &pool {
            Some(p) => p.install(run),
            None => run(),
        });
        // Sequential and strict: a later start must score more to win, as in a loop over them.
        let mut best = found[0];
        for &(pose, score) in &found[1..] {
            if score > best.1 {
                best = (pose, score);
            }
        }
        Ok(best)
    }

    /// Re-pose many scans in this (finished) map, each by Gauss-Newton alone from its own row of
    /// `starts` (N, 3) (scan_match::match_each). `ranges` (N, B), padding +inf; `angles` (B,)
    /// shared by all scans or (N, B) one row per scan. Returns (poses (N, 3), share of each
    /// scan's end points with an obstacle within the window (N,)).
    #[pyo3(signature = (starts, ranges, angles, *, sensor_pose=None, sigma=0.05, z_hit=0.9, z_rand=0.1,
        window=3, fit_walls=false, max_range=20.0, occupied_threshold=0.0, beam_stride=1, gauss_newton=10, threads=None))]
    #[allow(clippy::too_many_arguments)]
    fn match_each<'py>(
        &self,
        py: Python<'py>,
        starts: PyReadonlyArray2<f64>,
        ranges: PyReadonlyArray2<f32>,
        angles: PyReadonlyArrayDyn<f64>,
        sensor_pose: Option<PyReadonlyArray1<f64>>,
        sigma: f64,
        z_hit: f64,
        z_rand: f64,
        window: i32,
        fit_walls: bool,
        max_range: f64,
        occupied_threshold: f32,
        beam_stride: usize,
        gauss_newton: u32,
        threads: Option<usize>,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<f64>>)> {
        let starts = points3(&starts, "starts")?;
        if !starts.iter().flatten().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("starts must be finite"));
        }
        let (n, beams) = (ranges.shape()[0], ranges.shape()[1]);
        if n != starts.len() {
            return Err(PyValueError::new_err(format!("{} starts for {} scans", starts.len(), n)));
        }
        let shared = angles.shape() == [beams];
        if !shared && angles.shape() != [n, beams] {
            return Err(PyValueError::new_err(format!(
                "angles {:?} fit neither one scan ({beams},) nor every scan ({n}, {beams})", angles.shape()
            )));
        }
        let angles = angles.c_slice("angles")?;
        let ranges = ranges.c_slice("ranges")?;
        // Padding (per-scan geometry) is a NaN angle with an infinite range; any beam with a
        // range needs a bearing.
        let bearing = |i: usize| if shared { angles[i % beams] } else { angles[i] };
        if (0..ranges.len()).any(|i| ranges[i].is_finite() && !bearing(i).is_finite()) {
            return Err(PyValueError::new_err("angles must be finite for every beam with a range"));
        }
        field_settings(sigma, max_range, window, "")?;
        field_weights(z_hit, z_rand)?;
        if beam_stride < 1 || gauss_newton > MAX_MATCH_ITERATIONS {
            return Err(PyValueError::new_err(format!(
                "beam_stride must be at least 1 and gauss_newton at most {MAX_MATCH_ITERATIONS}"
            )));
        }
        let sensor = match sensor_pose {
            Some(s) => pose3(s.c_slice("sensor_pose")?, "sensor_pose")?,
            None => [0.0; 3],
        };
        if !sensor.iter().all(|v| v.is_finite()) {
            return Err(PyValueError::new_err("sensor_pose must be finite"));
        }
        let pool = optional_pool(threads)?;
        let lf = LikelihoodField::new(sigma, z_hit, z_rand, max_range, window, occupied_threshold, fit_walls);
        let grid = &self.grid;
        let run = || scan_match::match_each(&lf, grid, sensor, &starts, ranges, angles, beams, beam_stride, gauss_newton);
        let found = py.detach(|| match &pool {
            Some(p) => p.install(run),
            None => run(),
        });
        let poses: Vec<[f64; 3]> = found.iter().map(|f| f.0).collect();
        let shares: Vec<f64> = found.iter().map(|f| f.1).collect();
        Ok((rows3(py, &poses), PyArray1::from_vec(py, shares)))
    }

    /// Ranges the map predicts from a sensor pose (see BeamModel::expected_range); NaN where
    /// the ray reaches unknown space first.
    fn expected_ranges<'py>(
        &self,
        py: Python<'py>,
        sensor_pose: PyReadonlyArray1<f64>,
        angles: PyReadonlyArray1<f64>,
        max_range: f64,
        occupied_threshold: f32,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let sp = pose3(sensor_pose.c_slice("sensor_pose")?, "sensor_pose")?;
        if !sp.iter().all(|v| v.is_finite()) || !(max_range > 0.0) || !angles.c_slice("angles")?.iter().all(|a| a.is_finite()) {
            return Err(PyValueError::new_err("sensor_pose and angles must be finite and max_range positive"));
        }
        let model = BeamModel {
            z_hit: 1.0, z_short: 0.0, z_max: 0.0, z_rand: 0.0, sigma_hit: 1.0, lambda_short: 1.0,
            max_range, occupied_threshold,
        };
        let out = angles
            .c_slice("angles")?
            .iter()
            .map(|a| match model.expected_range(&self.grid, [sp[0], sp[1]], sp[2] + a) {
                (z, true) => z,
                _ => f64::NAN,
            })
            .collect();
        Ok(PyArray1::from_vec(py, out))
    }
}

/// Rows of an (N, 3) float64 array.
pub(crate) fn points3(a: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Vec<[f64; 3]>> {
    let shape = a.shape();
    if shape[1] != 3 {
        return Err(PyValueError::new_err(format!("{what} must have shape (N, 3), got {shape:?}")));
    }
    Ok(a.c_slice(what)?.chunks_exact(3).map(|r| [r[0], r[1], r[2]]).collect())
}

/// A sparse 3D log-odds voxel grid (rust/src/voxel.rs); NaN = unknown.
#[pyclass(name = "VoxelGrid", module = "omnitof._core")]
struct PyVoxelGrid {
    grid: VoxelGrid,
    pool: Option<rayon::ThreadPool>,
}

#[pymethods]
impl PyVoxelGrid {
    #[new]
    #[pyo3(signature = (resolution, l_occ, l_free, l_min, l_max, threads=None))]
    fn new(resolution: f64, l_occ: f32, l_free: f32, l_min: f32, l_max: f32, threads: Option<usize>) -> PyResult<Self> {
        let grid = VoxelGrid::new(resolution, log_odds_model(l_occ, l_free, l_min, l_max)?).map_err(PyValueError::new_err)?;
        let pool = optional_pool(threads)?;
        Ok(PyVoxelGrid { grid, pool })
    }

    #[getter]
    fn resolution(&self) -> f64 {
        self.grid.resolution
    }

    /// Integrate rays (world frame) as one frame; returns (hits, max-range rays, skipped rays,
    /// voxels freed, voxels marked occupied).
    fn integrate(
        &mut self,
        py: Python<'_>,
        origins: PyReadonlyArray2<f64>,
        endpoints: PyReadonlyArray2<f64>,
        max_range: f64,
    ) -> PyResult<(usize, usize, usize, usize, usize)> {
        let o = points3(&origins, "origins")?;
        let e = points3(&endpoints, "endpoints")?;
        let (grid, pool) = (&mut self.grid, &self.pool);
        let s = py
            .detach(|| match pool {
                Some(pool) => pool.install(|| grid.integrate(&o, &e, max_range)),
                None => grid.integrate(&o, &e, max_range),
            })
            .map_err(PyValueError::new_err)?;
        Ok((s.hits, s.max_range, s.skipped, s.free_voxels, s.occupied_voxels))
    }

    /// (M, 3) centres (metres) of the voxels with log-odds > threshold, sorted by index.
    #[pyo3(signature = (threshold=0.0))]
    fn occupied<'py>(&self, py: Python<'py>, threshold: f32) -> Bound<'py, PyArray2<f64>> {
        let r = self.grid.resolution;
        let c: Vec<[f64; 3]> = self.grid.occupied(threshold).iter().map(|i| i.map(|v| (v as f64 + 0.5) * r)).collect();
        rows3(py, &c)
    }

    /// (indices (K, 3) int64, log-odds (K,) float32) of every observed voxel, sorted by index.
    fn observed<'py>(&self, py: Python<'py>) -> (Bound<'py, PyArray2<i64>>, Bound<'py, PyArray1<f32>>) {
        let obs = self.grid.observed();
        let flat: Vec<i64> = obs.iter().flat_map(|(i, _)| i.iter().copied()).collect();
        let idx = Array2::from_shape_vec((obs.len(), 3), flat).unwrap().into_pyarray(py);
        (idx, PyArray1::from_vec(py, obs.iter().map(|(_, v)| *v).collect()))
    }

    /// Log-odds (N,) of the voxels holding points (N, 3); NaN where unknown or not finite.
    fn log_odds_at<'py>(&self, py: Python<'py>, points: PyReadonlyArray2<f64>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let p = points3(&points, "points")?;
        let out = p.iter().map(|&q| self.grid.index_of(q).map_or(f64::NAN, |i| self.grid.get(i) as f64)).collect();
        Ok(PyArray1::from_vec(py, out))
    }

    /// Number of observed voxels.
    fn voxel_count(&self) -> usize {
        self.grid.voxel_count()
    }

    fn block_count(&self) -> usize {
        self.grid.block_count()
    }

    /// Heap bytes held by the grid (blocks and hash table).
    fn memory_bytes(&self) -> usize {
        self.grid.memory_bytes()
    }

    /// ((xmin, ymin, zmin), (xmax, ymax, zmax)) metres of the observed voxels; None if empty.
    fn bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        self.grid.bounds()
    }
}

/// Draw n poses from the odometry motion model for a robot at `pose` whose odometry moved from
/// `odom_prev` to `odom_cur`.
#[pyfunction]
fn sample_motion_odometry<'py>(
    py: Python<'py>,
    pose: PyReadonlyArray1<f64>,
    odom_prev: PyReadonlyArray1<f64>,
    odom_cur: PyReadonlyArray1<f64>,
    alphas: [f64; 4],
    n: usize,
    seed: u64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (pose, prev, cur) = (pose3(pose.c_slice("pose")?, "pose")?, pose3(odom_prev.c_slice("odom_prev")?, "odom_prev")?, pose3(odom_cur.c_slice("odom_cur")?, "odom_cur")?);
    if !pose.iter().chain(&prev).chain(&cur).all(|v| v.is_finite()) {
        return Err(PyValueError::new_err("pose, odom_prev and odom_cur must be finite"));
    }
    if !alphas.iter().all(|a| a.is_finite() && *a >= 0.0) {
        return Err(PyValueError::new_err("alphas must be finite and non-negative"));
    }
    // Written straight into the array's buffer: a count no memory holds is a MemoryError, not
    // an abort.
    let mut flat: Vec<f64> = grid::try_vec(n.saturating_mul(3), "the motion samples").map_err(grid_error)?;
    let model = OdometryMotion { alpha: alphas };
    let mut rng = filter::rng_for(seed, 0, 0);
    for _ in 0..n {
        flat.extend(model.sample(pose, prev, cur, &mut rng));
    }
    Ok(Array2::from_shape_vec((n, 3), flat).expect("n rows of 3").into_pyarray(py))
}

/// The beam model's density (or max-reading mass) of each reading in `z` given `z_star`.
#[pyfunction]
#[pyo3(signature = (z, z_star, *, z_hit, z_short, z_max, z_rand, sigma_hit, lambda_short, max_range))]
#[allow(clippy::too_many_arguments)]
fn beam_likelihood<'py>(
    py: Python<'py>,
    z: PyReadonlyArray1<f64>,
    z_star: f64,
    z_hit: f64,
    z_short: f64,
    z_max: f64,
    z_rand: f64,
    sigma_hit: f64,
    lambda_short: f64,
    max_range: f64,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let m = beam_model(BeamModel { z_hit, z_short, z_max, z_rand, sigma_hit, lambda_short, max_range, occupied_threshold: 0.0 }, "")?;
    Ok(PyArray1::from_vec(py, z.c_slice("z")?.iter().map(|&zi| m.likelihood(zi, z_star)).collect()))
}

/// Effective sample size (paper eq. 10) of normalised weights.
#[pyfunction]
fn neff(weights: PyReadonlyArray1<f64>) -> PyResult<f64> {
    let w = weights.c_slice("weights")?;
    normalised_weights(w)?;
    Ok(filter::neff(w))
}

/// Weights that resampling and Neff can take: some, each finite and non-negative, summing to 1
/// (to rounding).
fn normalised_weights(w: &[f64]) -> PyResult<()> {
    if w.is_empty() {
        return Err(PyValueError::new_err("no weights"));
    }
    if !w.iter().all(|x| x.is_finite() && *x >= 0.0) {
        return Err(PyValueError::new_err("weights must be finite and non-negative"));
    }
    let sum: f64 = w.iter().sum();
    if !((sum - 1.0).abs() <= 1e-6) {
        return Err(PyValueError::new_err(format!("weights must be normalised (they sum to {sum})")));
    }
    Ok(())
}

/// Indices drawn by low-variance resampling from normalised weights.
#[pyfunction]
fn low_variance_resample<'py>(py: Python<'py>, weights: PyReadonlyArray1<f64>, seed: u64) -> PyResult<Bound<'py, PyArray1<u64>>> {
    let w = weights.c_slice("weights")?;
    normalised_weights(w)?;
    let idx = filter::low_variance_resample(w, &mut filter::rng_for(seed, 0, 1));
    Ok(PyArray1::from_vec(py, idx.into_iter().map(|i| i as u64).collect()))
}

/// The pixels of an RVL-coded depth image (rvl::decode); ValueError for a broken stream.
#[pyfunction]
fn rvl_decode<'py>(py: Python<'py>, data: PyReadonlyArray1<u8>, pixels: usize) -> PyResult<Bound<'py, PyArray1<u16>>> {
    let bytes = data.c_slice("data")?;
    let decoded = py.detach(|| rvl::decode(bytes, pixels)).map_err(|e| PyValueError::new_err(format!("RVL: {e}")))?;
    Ok(decoded.into_pyarray(py))
}

/// The RVL stream of uint16 pixels (rvl::encode), for test data and benchmarks.
#[pyfunction]
fn rvl_encode<'py>(py: Python<'py>, pixels: PyReadonlyArray1<u16>) -> PyResult<Bound<'py, PyArray1<u8>>> {
    let values = pixels.c_slice("pixels")?;
    let encoded = py.detach(|| rvl::encode(values));
    Ok(encoded.into_pyarray(py))
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyParticleFilter>()?;
    m.add_class::<PyOccupancyGrid>()?;
    m.add_class::<PyVoxelGrid>()?;
    m.add_function(wrap_pyfunction!(sample_motion_odometry, m)?)?;
    m.add_function(wrap_pyfunction!(beam_likelihood, m)?)?;
    m.add_function(wrap_pyfunction!(neff, m)?)?;
    m.add_function(wrap_pyfunction!(low_variance_resample, m)?)?;
    m.add_function(wrap_pyfunction!(rvl_decode, m)?)?;
    m.add_function(wrap_pyfunction!(rvl_encode, m)?)?;
    render_bindings::register(m)?;
    multipath_bindings::register(m)?;
    loop_closure_bindings::register(m)?;
    filter3d_bindings::register(m)?;
    Ok(())
}
