"""The Rust core's building blocks against analytic values and independent computations."""

from __future__ import annotations

import numpy as np
import pytest

from omnitof import _core

ALPHAS = [0.04, 0.02, 0.03, 0.05]


def moments(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return samples.mean(axis=0), np.cov(samples.T)


def test_motion_model_straight_line_matches_analytic_moments():
    # Odometry drove d metres straight ahead: rot1 = rot2 = 0, trans = d. Then
    # r1 ~ N(0, a2 d²), t ~ N(d, a3 d²), r2 ~ N(0, a2 d²) independent, and the new pose is
    # (t cos r1, t sin r1, r1 + r2). With s² = a2 d² and E[cos r1] = exp(-s²/2):
    a1, a2, a3, a4 = ALPHAS
    d = 0.8
    n = 400_000
    z = np.zeros(3)
    samples = _core.sample_motion_odometry(z, z, np.array([d, 0.0, 0.0]), ALPHAS, n, 7)
    s2 = a2 * d * d
    t2 = d * d + a3 * d * d  # E[t²]
    mean_want = np.array([d * np.exp(-s2 / 2), 0.0, 0.0])
    var_x = t2 * (1 + np.exp(-2 * s2)) / 2 - (d * np.exp(-s2 / 2)) ** 2
    var_y = t2 * (1 - np.exp(-2 * s2)) / 2
    var_th = 2 * s2
    cov_y_th = d * s2 * np.exp(-s2 / 2)  # E[t sin(r1) r1]
    cov_want = np.array([[var_x, 0, 0], [0, var_y, cov_y_th], [0, cov_y_th, var_th]])
    mean, cov = moments(samples)
    se = np.sqrt(np.diag(cov_want) / n)
    assert np.all(np.abs(mean - mean_want) < 5 * se)
    # Standard error of a sample covariance: sqrt((var_i var_j + cov_ij²) / n).
    var = np.diag(cov_want)
    cov_se = np.sqrt((np.outer(var, var) + cov_want**2) / n)
    assert np.all(np.abs(cov - cov_want) < 5 * cov_se)


def test_motion_model_turn_in_place_matches_analytic_moments():
    # Pure rotation by phi: trans = 0, rot1 = 0, rot2 = phi, so x ~ N(0, a4 phi²), y = 0,
    # theta ~ N(phi, a1 phi²), independent.
    a1, a2, a3, a4 = ALPHAS
    phi = 0.9
    n = 200_000
    z = np.zeros(3)
    samples = _core.sample_motion_odometry(z, z, np.array([0.0, 0.0, phi]), ALPHAS, n, 3)
    mean, cov = moments(samples)
    assert abs(mean[0]) < 5 * np.sqrt(a4 * phi**2 / n)
    assert abs(mean[2] - phi) < 5 * np.sqrt(a1 * phi**2 / n)
    assert np.all(samples[:, 1] == 0.0)
    assert cov[0, 0] == pytest.approx(a4 * phi**2, rel=0.02)
    assert cov[2, 2] == pytest.approx(a1 * phi**2, rel=0.02)
    assert abs(cov[0, 2]) < 5 * np.sqrt(a4 * a1) * phi**2 / np.sqrt(n)


def test_motion_model_is_applied_in_the_particle_frame():
    # Noise-free: the particle moves by the odometry increment expressed in its own frame.
    prev, cur = np.array([1.0, 2.0, 0.3]), np.array([1.5, 2.7, -0.4])
    start = np.array([-3.0, 0.5, 2.0])
    got = _core.sample_motion_odometry(start, prev, cur, [0, 0, 0, 0], 1, 0)[0]
    from omnitof.geometry import compose, relative

    assert np.allclose(got, compose(start, relative(prev, cur)), atol=1e-12)


BEAM = dict(z_hit=0.7, z_short=0.1, z_max=0.05, z_rand=0.15, sigma_hit=0.08, lambda_short=0.6, max_range=12.0)


@pytest.mark.parametrize("z_star", [0.02, 0.5, 3.7, 11.9, 12.0])
def test_beam_model_is_normalised(z_star):
    # Continuous part over [0, max_range) by the midpoint rule, plus the max-reading mass.
    n = 400_000
    h = BEAM["max_range"] / n
    z = (np.arange(n) + 0.5) * h
    density = _core.beam_likelihood(z, z_star, **BEAM)
    assert density.sum() * h + BEAM["z_max"] == pytest.approx(1.0, abs=1e-4)
    assert _core.beam_likelihood(np.array([12.0, 30.0]), z_star, **BEAM) == pytest.approx([0.05, 0.05])


def test_beam_model_hit_part_peaks_at_expected_range():
    z = np.linspace(0.0, 11.99, 10_000)
    density = _core.beam_likelihood(z, 4.0, **BEAM)
    assert abs(z[np.argmax(density)] - 4.0) < 0.01
    # Far from z*, only the uniform part remains beyond it, the short part below it.
    assert _core.beam_likelihood(np.array([9.0]), 4.0, **BEAM)[0] == pytest.approx(0.15 / 12.0, rel=1e-6)


def cells_crossed(p0: np.ndarray, p1: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Brute force: every cell of the segment's bounding box whose open square the segment
    crosses (Liang–Barsky clipping against each cell), and which of them holds the end point."""
    lo = np.floor(np.minimum(p0, p1) / res).astype(int) - 1
    hi = np.floor(np.maximum(p0, p1) / res).astype(int) + 1
    ix, iy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    ix, iy = ix.ravel(), iy.ravel()
    d = p1 - p0
    t0 = np.zeros(ix.shape)
    t1 = np.ones(ix.shape)
    for axis, idx in ((0, ix), (1, iy)):
        a, b = idx * res, (idx + 1) * res
        if d[axis] == 0:
            inside = (p0[axis] > a) & (p0[axis] < b)
            t1 = np.where(inside, t1, -1.0)
            continue
        ta, tb = (a - p0[axis]) / d[axis], (b - p0[axis]) / d[axis]
        t0 = np.maximum(t0, np.minimum(ta, tb))
        t1 = np.minimum(t1, np.maximum(ta, tb))
    crossed = t1 > t0 + 1e-12
    end = (ix == np.floor(p1[0] / res)) & (iy == np.floor(p1[1] / res))
    return np.column_stack([ix[crossed], iy[crossed]]), end[crossed]


def test_grid_update_matches_brute_force_traversal():
    rng = np.random.default_rng(5)
    res, l_occ, l_free = 0.1, 0.85, -0.4
    grid = _core.OccupancyGrid(res, l_occ, l_free, -1e6, 1e6)  # clamps out of reach
    pose = np.array([0.37, -0.21, 0.4])
    angles = np.sort(rng.uniform(-np.pi, np.pi, 60))
    ranges = rng.uniform(0.3, 4.0, 60).astype(np.float32)
    ranges[[5, 17]] = np.inf  # no echo: no update
    ranges[23] = 9.0  # beyond max_range: free space to max_range only
    max_range = 5.0
    grid.integrate(pose, angles, ranges, max_range)
    want: dict[tuple[int, int], float] = {}
    for a, r in zip(angles, ranges.astype(np.float64)):
        if not np.isfinite(r):
            continue
        length = min(r, max_range)
        end = pose[:2] + length * np.array([np.cos(pose[2] + a), np.sin(pose[2] + a)])
        cells, is_end = cells_crossed(pose[:2], end, res)
        for (cx, cy), e in zip(cells, is_end):
            delta = l_occ if (e and r <= max_range) else l_free
            want[(cx, cy)] = want.get((cx, cy), 0.0) + delta
    log_odds, ix0, iy0 = grid.to_dense()
    known = ~np.isnan(log_odds)
    rows, cols = np.nonzero(known)
    got = {(int(c + ix0), int(r + iy0)): float(log_odds[r, c]) for r, c in zip(rows, cols)}
    assert got.keys() == want.keys()
    for key, value in want.items():
        assert got[key] == pytest.approx(value, abs=1e-4)


def test_grid_update_clamps_log_odds():
    grid = _core.OccupancyGrid(0.05, 0.9, -0.4, -2.0, 3.5)
    pose, angles = np.zeros(3), np.array([0.0])
    for _ in range(20):
        grid.integrate(pose, angles, np.array([1.02], dtype=np.float32), 10.0)
    log_odds, ix0, iy0 = grid.to_dense()
    assert log_odds[0 - iy0, 20 - ix0] == pytest.approx(3.5)  # end point cell (20, 0)
    assert log_odds[0 - iy0, 10 - ix0] == pytest.approx(-2.0)


def test_expected_range_sees_the_wall_it_was_built_from():
    grid = _core.OccupancyGrid(0.05, 2.0, -0.5, -5.0, 5.0)
    angles = np.linspace(-0.5, 0.5, 41)
    wall_x = 3.0
    ranges = (wall_x / np.cos(angles)).astype(np.float32)
    grid.integrate(np.zeros(3), angles, ranges, 10.0)
    expected = grid.expected_ranges(np.zeros(3), angles, 10.0, 0.0)
    assert np.all(np.abs(expected - ranges) < 0.05 / np.cos(angles) + 1e-9)
    # Looking backwards the map is unknown: no prediction.
    assert np.isnan(grid.expected_ranges(np.array([0.0, 0.0, np.pi]), np.array([0.0]), 10.0, 0.0)[0])


def test_neff_of_uniform_degenerate_and_scaled_weights():
    assert _core.neff(np.full(8, 1 / 8)) == pytest.approx(8.0)
    assert _core.neff(np.array([0.0, 1.0, 0.0])) == pytest.approx(1.0)
    w = np.array([0.5, 0.25, 0.25])
    assert _core.neff(w) == pytest.approx(1 / (0.25 + 0.0625 + 0.0625))


def test_low_variance_resampling_properties():
    rng = np.random.default_rng(0)
    w = rng.random(37)
    w /= w.sum()
    counts_sum = np.zeros(37)
    for seed in range(300):
        idx = _core.low_variance_resample(w, seed)
        assert len(idx) == 37 and np.all(np.diff(idx.astype(np.int64)) >= 0)
        counts = np.bincount(idx.astype(np.int64), minlength=37)
        assert np.all(counts >= np.floor(37 * w) - 1e-9) and np.all(counts <= np.ceil(37 * w) + 1e-9)
        counts_sum += counts
    # Unbiased: the mean count of each particle approaches N·w.
    assert np.allclose(counts_sum / 300, 37 * w, atol=0.1)
    assert np.array_equal(_core.low_variance_resample(w, 11), _core.low_variance_resample(w, 11))


def test_particle_filter_takes_configuration_sections_and_refuses_unknown_or_missing_fields():
    from omnitof.slam.config import SlamConfig
    from omnitof.slam.driver import core_sections

    # As omnitof.slam.driver passes them: every section whole, less what the driver uses itself.
    sections = core_sections(SlamConfig())
    sensor = dict(angles=np.linspace(-1.5, 1.5, 181), sensor_pose=np.zeros(3), scan_max_range=80.0)
    assert _core.ParticleFilter(**sections, **sensor).steps == 0
    extra = {**sections, "scan_matcher": {**sections["scan_matcher"], "step_size": 0.1}}
    with pytest.raises(ValueError, match=r"scan_matcher\.step_size: unknown field"):
        _core.ParticleFilter(**extra, **sensor)
    missing = {**sections, "map": {k: v for k, v in sections["map"].items() if k != "l_occ"}}
    with pytest.raises(ValueError, match=r"map\.l_occ: missing field"):
        _core.ParticleFilter(**missing, **sensor)
    wrong = {**sections, "filter": {**sections["filter"], "seed": "zero"}}
    with pytest.raises(TypeError, match=r"filter\.seed: "):
        _core.ParticleFilter(**wrong, **sensor)


def test_grids_beyond_reach_or_memory_raise_instead_of_aborting():
    # Before, a 1e-5 m grid panicked ("capacity overflow") and a 1e-4 m one aborted the process
    # allocating its window; now the core says which, before it allocates, and the caller decides.
    pose = np.zeros(3)
    short = dict(angles=np.zeros(1), ranges=np.array([1.0], np.float32), max_range=1e6)
    fine = _core.OccupancyGrid(1e-5, 0.9, -0.4, -2.0, 3.5)
    with pytest.raises(ValueError, match="beyond"):  # 20 km is 2e9 cells out
        fine.integrate(np.array([2.0e4, 0.0, 0.0]), **short)
    grid = _core.OccupancyGrid(1e-4, 0.9, -0.4, -2.0, 3.5)
    grid.integrate(pose, **short)
    before = grid.to_dense()[0]
    with pytest.raises(MemoryError, match="window of tiles"):  # 50 km away: 1e15 tiles of window
        grid.integrate(np.array([5.0e4, 5.0e4, 0.0]), **short)
    with pytest.raises(MemoryError, match="one scan would write"):  # a 50 km beam: 77 GB of tiles
        grid.integrate(pose, np.zeros(1), np.array([5.0e4], np.float32), 1e6)
    assert np.array_equal(grid.to_dense()[0], before, equal_nan=True)  # the failed scans wrote nothing
    with pytest.raises(ValueError, match="finite"):
        _core.OccupancyGrid(float("inf"), 0.9, -0.4, -2.0, 3.5)


def test_particle_filter_reports_a_map_it_cannot_allocate_as_memory_error():
    # The configuration refuses such a resolution (omnitof.slam.config); the core alone must
    # still fail as an exception, for the first scan and for a later one.
    from omnitof.slam.config import SlamConfig
    from omnitof.slam.driver import core_sections

    sections = core_sections(SlamConfig())
    sections["map"] = {**sections["map"], "resolution": 1e-4, "max_range": 1e6}
    sections["sensor_model"] = {**sections["sensor_model"], "max_range": 1e6}
    pf = _core.ParticleFilter(**sections, angles=np.zeros(1), sensor_pose=np.zeros(3), scan_max_range=1e6)
    far, near = np.array([5.0e4], np.float32), np.array([1.0], np.float32)
    with pytest.raises(MemoryError, match="one scan would write"):
        pf.step(np.zeros(3), np.zeros(3), far, 0)
    pf.step(np.zeros(3), np.zeros(3), near, 0)
    with pytest.raises(MemoryError, match="window of tiles"):
        pf.step(np.zeros(3), np.array([5.0e4, 5.0e4, 0.0]), near, 1)


def test_the_cores_functions_refuse_what_no_sensor_robot_or_filter_gives():
    # Each of these returned junk, hung (10**9 refinements) or aborted the process (10**12
    # motion samples) before; each is now one exception naming what is wrong.
    z = np.zeros(3)
    with pytest.raises(MemoryError, match="motion samples"):
        _core.sample_motion_odometry(z, z, np.array([1.0, 0.0, 0.0]), ALPHAS, 10**12, 0)
    with pytest.raises(ValueError, match="finite"):
        _core.sample_motion_odometry(np.array([np.nan, 0.0, 0.0]), z, z, ALPHAS, 3, 0)
    with pytest.raises(ValueError, match="non-negative"):
        _core.sample_motion_odometry(z, z, z, [-0.1, 0.0, 0.0, 0.0], 3, 0)
    for w, what in ((np.array([np.nan, 1.0]), "finite"), (np.array([-0.5, 1.5]), "non-negative"),
                    (np.zeros(3), "normalised"), (np.array([2.0, 2.0]), "normalised"), (np.zeros(0), "no weights")):
        with pytest.raises(ValueError, match=what):
            _core.low_variance_resample(w, 0)
        with pytest.raises(ValueError, match=what):
            _core.neff(w)

    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    ranges = np.full(90, 2.0, np.float32)
    grid = _core.OccupancyGrid(0.05, 0.9, -0.4, -2.0, 3.5)
    grid.integrate(z, angles, ranges, 10.0)
    for bad, what in (({"window": 0}, "window"), ({"window": 10**6}, "window"), ({"sigma": np.inf}, "sigma"),
                      ({"max_range": np.nan}, "max_range"), ({"refinements": 10**9}, "refinements"),
                      ({"step_xy": 0.0}, "step_xy"), ({"sensor_pose": np.array([np.nan, 0, 0])}, "sensor_pose")):
        with pytest.raises(ValueError, match=what):
            grid.match_scan(z, angles, ranges, **{"max_range": 10.0, **bad})
    with pytest.raises(ValueError, match="window"):
        grid.match_each(z[None, :], ranges[None, :], angles, window=10**6, max_range=10.0)

    from omnitof.slam.config import SlamConfig
    from omnitof.slam.driver import core_sections

    sensor = dict(angles=angles, sensor_pose=z, scan_max_range=20.0)
    for bad, what in (({"angles": np.full(90, np.nan)}, "angles"), ({"scan_max_range": -1.0}, "scan_max_range"),
                      ({"sensor_pose": np.array([0.0, np.inf, 0.0])}, "sensor_pose")):
        with pytest.raises(ValueError, match=what):
            _core.ParticleFilter(**core_sections(SlamConfig()), **{**sensor, **bad})
    # The configuration's sections as the Python API may hand them over: a clamp the wrong way
    # round panicked at the first scan, 10**9 refinements or threads hung, NaN sigmas, steps and
    # alphas ran on without a word (a review's hostile inputs, thirty-seventh session).
    for section, field, value, what in (
        ("map", "l_min", 5.0, "l_min must not exceed l_max"), ("map", "l_max", np.nan, "must be finite"),
        ("map", "resolution", 0.0, "map.resolution"), ("scan_matcher", "refinements", 10**9, "refinements"),
        ("scan_matcher", "step_xy", np.nan, "step_xy"), ("filter", "threads", 10**9, "filter.threads"),
        ("likelihood_field", "sigma", np.nan, "likelihood_field: sigma"),
        ("likelihood_field", "window_cells", -5, "likelihood_field: window"), ("motion", "alpha1", np.nan, "motion.alpha"),
        ("sensor_model", "beam_stride", 0, "beam_stride"), ("sensor_model", "effective_beams", np.nan, "effective_beams"),
    ):
        sections = core_sections(SlamConfig())
        sections[section] = {**sections[section], field: value}
        with pytest.raises(ValueError, match=what):
            _core.ParticleFilter(**sections, **sensor)
    pf = _core.ParticleFilter(**core_sections(SlamConfig()), **sensor)
    with pytest.raises(ValueError, match="odom_prev and odom_cur must be finite"):
        pf.step(z, np.array([np.nan, 0.0, 0.0]), ranges, 0)
    with pytest.raises(ValueError, match="threads must lie in 1..=1024"):
        _core.VoxelGrid(0.1, 0.9, -0.4, -2.0, 3.5, threads=10**9)
    # These returned plausible numbers (or wrote nothing) from NaN poses, angles and ranges.
    with pytest.raises(ValueError, match="finite"):
        grid.expected_ranges(np.array([np.nan, 0.0, 0.0]), angles, 10.0, 0.5)
    with pytest.raises(ValueError, match="max_range positive"):
        grid.expected_ranges(z, angles, -5.0, 0.5)
    with pytest.raises(ValueError, match="max_range positive"):
        grid.integrate(z, angles, ranges, np.nan)
    with pytest.raises(ValueError, match="scan angles must be finite"):
        grid.integrate(z, np.full(90, np.nan), ranges, 10.0)
    with pytest.raises(ValueError, match="sigma_hit"):
        _core.beam_likelihood(np.ones(2), 1.0, **{**BEAM, "sigma_hit": 0.0})
    sections = core_sections(SlamConfig())
    sections["sensor_model"] = {**sections["sensor_model"], "sigma_hit": np.nan}
    with pytest.raises(ValueError, match="sensor_model: .*sigma_hit"):
        _core.ParticleFilter(**sections, **sensor)


def test_the_3d_filter_refuses_nan_weights_zero_strides_and_frames_beyond_its_grid():
    # effective_rays NaN gave NaN weights; a frame at 1e15 m was dropped and the reset's map was
    # empty, without a word.
    from omnitof.slam.config import SlamConfig
    from omnitof.slam.filter3d import core_sections_3d

    def sections(**f3):
        s = core_sections_3d(SlamConfig.model_validate({"filter": {"particles": 3, "threads": 1, "seed": 1}}))
        s["filter3d"] = {**s["filter3d"], **f3}
        return s

    for bad in ({"effective_rays": np.nan}, {"free_stride": 0}, {"climb_stride": 0}):
        with pytest.raises(ValueError, match="filter3d"):
            _core.ParticleFilter3D(**sections(**bad))
    pf = _core.ParticleFilter3D(**sections())
    cloud = np.ones((3, 6), np.float32)
    with pytest.raises(ValueError, match="poses: .* is not a finite point within"):
        pf.reset(np.zeros(3), 0, np.array([[1e15, 0.0, 0.0]]), [cloud])
    pf.reset(np.zeros(3), 0, np.zeros((1, 3)), [cloud])
    assert pf.map().bounds() is not None


def test_arrays_in_fortran_order_are_refused_not_read_transposed():
    # rust-numpy's as_slice takes a Fortran-ordered array and hands over its columns as rows:
    # `starts.T` of a (3, N) array matched other poses, `xyz.T` integrated other points.
    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    ranges = np.full(90, 2.0, np.float32)
    grid = _core.OccupancyGrid(0.05, 0.9, -0.4, -2.0, 3.5)
    grid.integrate(np.zeros(3), angles, ranges, 10.0)
    starts = np.array([[0.0, 0.1, 0.0], [0.1, 0.0, 0.05]])
    both = np.tile(ranges, (2, 1))
    poses, _ = grid.match_each(starts, both, angles, max_range=10.0, gauss_newton=0)
    with pytest.raises(TypeError, match="starts: an array of shape .* not C-ordered"):
        grid.match_each(np.asfortranarray(starts), both, angles, max_range=10.0, gauss_newton=0)
    poses_again, _ = grid.match_each(np.ascontiguousarray(np.asfortranarray(starts)), both, angles, max_range=10.0,
                                     gauss_newton=0)
    np.testing.assert_array_equal(poses, poses_again)
    voxels = _core.VoxelGrid(0.1, 0.9, -0.4, -2.0, 3.5)
    xyz = np.array([[1.0, 2.0, 3.0], [1.5, 0.5, 1.0]])
    with pytest.raises(TypeError, match="not C-ordered"):
        voxels.integrate(np.zeros((2, 3)), np.asfortranarray(xyz), 10.0)


def _renderer(**changes):
    """The core's renderer of an 8×8 pinhole camera in a 6 m × 6 m room, with `changes`."""
    v, u = np.mgrid[0:8, 0:8] - 3.5
    d = np.stack([u / 6, v / 6, np.ones((8, 8))], -1).reshape(-1, 3)
    args = dict(
        walls=np.array([[-3, -3, 3, -3, 0, 2.5], [3, -3, 3, 3, 0, 2.5], [3, 3, -3, 3, 0, 2.5], [-3, 3, -3, -3, 0, 2.5]],
                       dtype=float),
        wall_materials=np.zeros(4, np.uint32), boxes=np.zeros((0, 7)), box_materials=np.zeros(0, np.uint32),
        materials=np.array([[0, 0.6, 0, 0, 0, 0]], dtype=float), floor_material=0, ceiling_material=0,
        ceiling_height=2.5, cell=0.5, directions=d / np.linalg.norm(d, axis=1)[:, None], height=8, width=8,
        sub_rays=1, mirror_planes=np.array([[0.0, 0, 1, 0.1]]),
        mirror_vertices=np.array([[-1.0, -1, 0.1], [1, -1, 0.1], [1, 1, 0.1], [-1, 1, 0.1]]),
        mirror_counts=np.array([4], np.uint64), mirror_reflectivity=np.array([0.9]),
        robot_T_camera=np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0.3], [0, 0, 0, 1]], dtype=float),
        f_mod=20e6, amplitude_at_1m=1000.0, max_bounces=2, min_gain=1e-4,
    )
    args.update(changes)
    return _core._Renderer(**args)


def test_the_renderer_refuses_what_would_panic_hang_or_render_garbage():
    base = _renderer()
    t, material = base.cast(np.array([[0.0, 0, 1], [0, 0, 1], [0, 0, 1]]),
                            np.array([[1e-200, 0, 0], [1e160, 0, 0], [np.nan, 0, 0]]))
    np.testing.assert_allclose(t[:2], 3.0)  # the +x wall, whatever the direction's length
    assert t[2] == np.inf and material[2] == -1  # NaN: the rig's marker of a ray that is not there
    refused = {
        # sums and products that wrapped past 2⁶⁴ and panicked later
        "mirror_counts must add up": dict(mirror_planes=np.array([[0.0, 0, 1, 0.1]] * 2),
                                          mirror_reflectivity=np.array([0.9, 0.9]),
                                          mirror_counts=np.array([2**64 - 1, 5], np.uint64)),
        "directions do not fill": dict(height=2**63, width=2, directions=np.zeros((0, 3))),
        # a ray between two perfect mirrors never fades: 10⁹ bounces hung
        "max_bounces must be at most 64": dict(max_bounces=10**9),
        "min_gain must be finite": dict(min_gain=np.inf),
        "f_mod must lie in": dict(f_mod=np.inf),
        "amplitude_at_1m in": dict(amplitude_at_1m=1e300),
        "led_half_angle_deg must lie in": dict(leds=np.array([[0.02, 0, 0]]), led_half_angle_deg=360.0),
        "orthonormal": dict(robot_T_camera=np.zeros((4, 4))),
        "a reflection": dict(robot_T_camera=np.diag([1.0, 1.0, -1.0, 1.0])),
        "encloses no area": dict(mirror_vertices=np.tile([0.0, 0, 0.1], (4, 1))),
        "material kind must be a whole number": dict(materials=np.array([[1.9, 0.6, 0, 0, 0, 0]])),
        "robot_T_camera: an array": dict(robot_T_camera=np.asfortranarray(np.eye(4))),
    }
    for message, changes in refused.items():
        with pytest.raises((ValueError, TypeError), match=message):
            _renderer(**changes)
    with pytest.raises(ValueError, match="ray 0: the origin must be finite and the direction finite and not zero"):
        base.cast(np.zeros((1, 3)), np.zeros((1, 3)))
    image = np.zeros((64, 2), np.float32), np.ones(64, np.float32), np.ones(64, np.float32)
    layout = np.zeros(1, np.uint64), np.zeros(1, bool), np.zeros(1, np.uint64)
    for message, extra in {"harmonics must be finite": dict(harmonics=(np.nan, 0.0)),
                           "amplitude offset must be finite": dict(amplitude_offset=(np.inf, 100.0)),
                           "fixed_pattern must be finite": dict(fixed_pattern=np.full(64, np.nan)),
                           "fixed_pattern: an array": dict(fixed_pattern=np.zeros(128)[::2])}.items():
        with pytest.raises((ValueError, TypeError), match=message):
            base.frames(*image, *layout, electrons_per_unit=20.0, read_noise=0.0, full_well=1e5, **extra)


def _compensator(n_side=8, **changes):
    n = n_side * n_side
    args = dict(width=n_side, height=n_side, origins=np.zeros((n, 3)), directions=np.tile([0.0, 0, 1], (n, 1)),
                paths=np.zeros(n), labels=np.zeros(n, np.int32), solid_angles=np.full(n, 0.03), emission=np.ones(n),
                source_gain=np.ones(n), targets=np.arange(n, dtype=np.uint32), windows=np.tile([0.0, 10], (n, 1)),
                k=0.84, amplitude_at_1m=1000.0, mirror_reflectivity=0.9, stride=1, target_stride=1, normal_radius=1,
                smooth_radius=1, depth_tolerance=0.1, min_reflectance=0.0, min_cos=0.1, min_separation=0.05,
                max_ratio=1.0)
    args.update(changes)
    return _core._MultipathCompensator(**args)


def test_the_multipath_compensator_refuses_what_would_panic_hang_or_switch_it_off():
    _compensator()
    empty = dict(origins=np.zeros((0, 3)), directions=np.zeros((0, 3)), paths=np.zeros(0),
                 labels=np.zeros(0, np.int32), solid_angles=np.zeros(0), emission=np.zeros(0),
                 source_gain=np.zeros(0), targets=np.zeros(0, np.uint32), windows=np.zeros((0, 2)))
    refused = {
        "at least 1×1 pixels, got 0×0": dict(n_side=0),  # a chunk size of 0 panicked at the first frame
        "at least 1×1 pixels, got 4294967296×4294967296": dict(width=2**32, height=2**32, **empty),
        "normal_radius and smooth_radius must be at most the image's side": dict(normal_radius=10**9),  # hung
        "k must be at most 1e6": dict(k=1e300),
        "min_cos at most 1": dict(min_cos=2.0),
        "solid angles must be finite": dict(solid_angles=np.full(64, np.nan)),
        "pixel 0: a mirror pixel needs a unit direction": dict(directions=np.tile([0.0, 0, 2], (64, 1))),
        "windows must be finite": dict(windows=np.tile([5.0, 1], (64, 1))),
    }
    for message, changes in refused.items():
        with pytest.raises(ValueError, match=message):
            _compensator(**changes)


def test_a_submap_refuses_a_resolution_too_coarse_and_a_window_too_wide_for_its_tree():
    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    ranges = (2 / np.maximum(np.abs(np.cos(angles)), np.abs(np.sin(angles)))).astype(np.float32)  # a 4 m square room
    # Matches came back metres outside a ±0.3 m window at 10 m cells.
    with pytest.raises(ValueError, match="resolution 10 m is too coarse for max_range 5 m"):
        _core.Submap(10.0, 0.9, -0.4, -2.0, 3.5, 5.0)
    shallow = _core.Submap(0.05, 0.9, -0.4, -2.0, 3.5, 5.0, depth=0)
    shallow.insert(np.zeros(3), ranges, angles)
    shallow.finish()
    assert shallow.match_scan(ranges, angles, np.zeros(3), 0.3, 0.1, 0.0) is not None
    # Without a tree every pose of a 20 m window would be scored: minutes.
    with pytest.raises(ValueError, match="the window is too wide for a tree of depth 0"):
        shallow.match_scan(ranges, angles, np.zeros(3), 20.0, 4.0, 0.0)


def _room_ranges(pose, angles, half_x=3.0, half_y=1.6):
    """Exact ranges from `pose` (x, y, heading) to the walls of a 6 x 3.2 m room centred on the origin."""
    x, y, th = pose
    c, s = np.cos(angles + th), np.sin(angles + th)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (half_x - x) / c, (-half_x - x) / c)
        ty = np.where(s > 0, (half_y - y) / s, (-half_y - y) / s)
    return np.minimum(np.abs(tx), np.abs(ty)).astype(np.float32)


def test_the_best_of_many_starts_is_the_best_of_their_matches_for_any_thread_count():
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    grid = _core.OccupancyGrid(0.05, 0.9, -0.4, -2.0, 3.5)
    for pose in ((0.0, 0.0, 0.0), (1.5, 0.5, 0.3), (-1.5, -0.5, -0.3)):
        grid.integrate(np.array(pose), angles, _room_ranges(pose, angles), 10.0)
    truth = np.array([0.42, -0.23, 0.35])
    ranges = _room_ranges(truth, angles)
    starts = np.array([[0.3, -0.1, 0.2], [-2.0, 1.0, 2.5], [0.5, -0.3, 0.45], [1.0, 0.8, -1.0]])
    options = dict(max_range=10.0)
    one_by_one = [grid.match_scan(s, angles, ranges, **options) for s in starts]
    scores = [score for _, score in one_by_one]
    expected = one_by_one[int(np.argmax(scores))]  # argmax: the first of equal scores
    for threads in (1, 2):
        pose, score = grid.match_best(starts, angles, ranges, threads=threads, **options)
        assert score == expected[1]
        np.testing.assert_array_equal(pose, expected[0])
    assert np.hypot(*(np.asarray(expected[0])[:2] - truth[:2])) < 0.02
    assert abs(expected[0][2] - truth[2]) < np.radians(0.5)
    with pytest.raises(ValueError, match="starts"):
        grid.match_best(np.zeros((0, 3)), angles, ranges, **options)
    with pytest.raises(ValueError, match="starts"):
        grid.match_best(np.array([[0.0, np.nan, 0.0]]), angles, ranges, **options)


@pytest.mark.parametrize("fallback", ["prediction", "draw"])
def test_a_scan_that_cannot_be_matched_leaves_the_particles_at_the_prediction_unless_told_to_draw(fallback):
    from omnitof.geometry import compose, relative
    from omnitof.slam.config import SlamConfig
    from omnitof.slam.driver import core_sections

    cfg = SlamConfig.model_validate({"filter": {"proposal": "scanmatch", "particles": 12, "seed": 3},
                                     "scan_matcher": {"fallback": fallback}})
    angles = np.linspace(-np.pi, np.pi, 180, endpoint=False)
    pf = _core.ParticleFilter(**core_sections(cfg), angles=angles, sensor_pose=np.zeros(3), scan_max_range=20.0)
    room = np.full(180, 2.0, np.float32)  # a round room 2 m in radius
    odom0, odom1 = np.array([1.0, -2.0, 0.3]), np.array([1.4, -1.8, 0.45])
    pf.step(odom0, odom0, room, 0)
    start = pf.poses().copy()
    # Every end point 12 m out, in space the map has never seen: nothing to match.
    pf.step(odom0, odom1, np.full(180, 12.0, np.float32), 1)
    assert pf.fallbacks == 12
    predicted = compose(start, relative(odom0, odom1))
    if fallback == "prediction":
        np.testing.assert_allclose(pf.poses(), predicted, atol=1e-12)
    else:  # drawn from the motion model around the prediction: spread, but near it
        spread = np.abs(pf.poses() - predicted)
        assert spread.max() > 1e-4 and spread[:, :2].max() < 0.5
