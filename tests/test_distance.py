"""Tests of the distance calibration (omnitof.calibration.distance, issue 16): it removes an
injected wiggling curve, amplitude term and fixed pattern; it survives the calibration file;
the scan extraction applies it; files without one load with none."""

from __future__ import annotations

import numpy as np
import pytest

from omnitof.calibration import Calibration, CalibrationError, load_calibration, save_calibration
from omnitof.calibration.distance import DistanceCorrection
from omnitof.sensor.design import default_rig

SHAPE = (12, 16)
PERIOD = 5.0 / 4.0  # a quarter of the unambiguous range at 30 MHz


def _injected(seed):
    pattern = np.random.default_rng(seed).normal(0.0, 0.004, SHAPE).ravel()

    def error(d, a, p):
        wiggle = 0.015 * np.sin(2 * np.pi * d / PERIOD) + 0.005 * np.sin(4 * np.pi * d / PERIOD + 0.3)
        return wiggle + 0.01 * np.log10(1000.0 / a) + pattern[p]

    return error


def _samples(error, n, seed, noise=0.002):
    rng = np.random.default_rng(seed)
    true = rng.uniform(0.4, 4.5, n)
    amp = np.exp(rng.uniform(np.log(50.0), np.log(20000.0), n))
    pix = rng.integers(0, SHAPE[0] * SHAPE[1], n)
    return true + error(true, amp, pix) + rng.normal(0.0, noise, n), true, amp, pix


def test_the_correction_removes_an_injected_wiggling_curve():
    error = _injected(0)
    m, t, a, p = _samples(error, 40_000, 1)
    correction = DistanceCorrection.fit(m, t, a, p, SHAPE)
    m2, t2, a2, p2 = _samples(error, 5_000, 2, noise=0.0)
    before = np.median(np.abs(m2 - t2))
    after = np.abs(correction.correct(m2, a2, p2) - t2)
    assert before > 0.008
    assert np.median(after) < 0.0015 and np.percentile(after, 95) < 0.004
    # The fitted error is the injected one (the split between the terms aside).
    assert np.allclose(correction.error(m2, a2, p2), m2 - t2, atol=0.004)


def test_the_fit_is_the_same_for_one_blas_thread_and_two(monkeypatch):
    # As for the refinement (test_refine): the fit's dense products and solves run on one BLAS
    # thread, whose sums do not depend on the core count; without that (the limit made a no-op
    # below) the demo's correction differed in its last digits between one core and two.
    from contextlib import nullcontext

    from threadpoolctl import threadpool_limits

    import omnitof.calibration.distance as distance_module

    shape = (144, 176)  # the SR4000's pixels: the Schur complement sums over all of them
    rng = np.random.default_rng(3)
    t = rng.uniform(0.4, 4.5, 60_000)
    a = np.exp(rng.uniform(np.log(50.0), np.log(20000.0), len(t)))
    p = rng.integers(0, shape[0] * shape[1], len(t))
    m = t + 0.015 * np.sin(2 * np.pi * t / PERIOD) + rng.normal(0.0, 0.002, len(t))

    def fitted(threads):
        with threadpool_limits(limits=threads, user_api="blas"):
            c = DistanceCorrection.fit(m, t, a, p, shape)
        return np.concatenate([c.distance_coefficients, c.amplitude_coefficients, c.pixel_offsets.ravel()])

    assert np.array_equal(fitted(1), fitted(2))
    monkeypatch.setattr(distance_module, "threadpool_limits", lambda **_: nullcontext())
    if not np.array_equal(fitted(1), fitted(2)):
        return  # what the limit prevents, seen here
    pytest.skip("this BLAS sums alike on one thread and two for a problem of this size")


def test_without_the_pixel_term_the_wiggling_is_still_removed():
    base = _injected(0)

    def error(d, a, p):  # no fixed pattern
        return base(d, a, np.zeros_like(p)) - base(np.zeros(1), np.full(1, 1000.0), np.zeros(1, int))

    m, t, a, _ = _samples(error, 20_000, 3)
    correction = DistanceCorrection.fit(m, t, a)
    assert correction.pixel_offsets is None
    m2, t2, a2, p2 = _samples(error, 3_000, 4, noise=0.0)
    assert np.median(np.abs(correction.correct(m2, a2) - t2)) < 0.0015


def _constant(offset, shape=None):
    knots = np.array([0.0] * 4 + [10.0] * 4)
    return DistanceCorrection(knots, np.full(4, offset), np.array([0.0] * 4 + [12.0] * 4), np.zeros(4),
                              None if shape is None else np.zeros(shape))


def test_the_calibration_file_keeps_the_correction_and_old_files_load_without(tmp_path):
    rig = default_rig()
    cal = Calibration.from_rig(rig)
    path = save_calibration(cal, tmp_path / "old.yaml")
    assert load_calibration(path).distance_correction is None
    error = _injected(5)
    m, t, a, p = _samples(error, 20_000, 6)
    small = DistanceCorrection.fit(m, t, a, p, SHAPE)
    full = DistanceCorrection(small.distance_knots, small.distance_coefficients, small.amplitude_knots,
                              small.amplitude_coefficients, np.resize(small.pixel_offsets, rig.camera.shape))
    cal.distance_correction = full
    back = load_calibration(save_calibration(cal, tmp_path / "new.yaml")).distance_correction
    d = np.full(rig.camera.shape, 2.0)
    amp = np.full(rig.camera.shape, 500.0)
    assert np.allclose(back.correct(d, amp), full.correct(d, amp), atol=1e-6)
    text = (tmp_path / "new.yaml").read_text().replace("log_amplitude_knots: [", "log_amplitude_knots: [0.5, ")
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(CalibrationError, match="distance_correction: amplitude knots"):
        load_calibration(tmp_path / "bad.yaml")


def test_the_scan_extraction_applies_the_correction():
    from omnitof.scan.extract import ScanExtractor
    from omnitof.sensor.mirrors import viewing_rays

    rig = default_rig()
    cal = Calibration.from_rig(rig)
    # A frame of a round room 3 m around the camera: each pixel's path to the wall.
    rays = viewing_rays(rig.camera, rig.mirrors)
    o, v = rays.origins, rays.directions
    b = np.sum(o[..., :2] * v[..., :2], -1)
    vv = np.sum(v[..., :2] ** 2, -1)
    s = (-b + np.sqrt(b * b + vv * (9.0 - np.sum(o[..., :2] ** 2, -1)))) / vv
    distance = (np.linalg.norm(o, axis=-1) + s).astype(np.float32)
    amplitude = np.full(rig.camera.shape, 1000.0, dtype=np.float32)
    # The flying-pixel filter is off: this made-up frame's flat amplitude is no real return.
    off = {"pixel_filter": {"enabled": False}}
    plain = ScanExtractor.from_calibration(cal, **off).extract(distance, amplitude)
    cal.distance_correction = _constant(0.1)
    corrected = ScanExtractor.from_calibration(cal, **off).extract(distance + np.float32(0.1), amplitude)
    ok = np.isfinite(plain)
    assert ok.sum() > 150
    assert np.allclose(corrected[ok], plain[ok], atol=0.002)
    uncorrected = ScanExtractor.from_calibration(Calibration.from_rig(rig), **off).extract(
        distance + np.float32(0.1), amplitude)
    assert np.median(uncorrected[ok] - plain[ok]) > 0.05


def test_the_correction_evaluates_its_splines_as_their_basis_does():
    # error() evaluates the two splines directly; the fit builds their basis. Both must give one
    # curve, inside the knots and held at the end values outside them.
    from omnitof.calibration.distance import DEGREE, _clamped_knots, _design, _spline

    rng = np.random.default_rng(7)
    knots = _clamped_knots(0.4, 6.9, 23)
    coefficients = rng.normal(0.0, 0.02, len(knots) - DEGREE - 1)
    x = np.concatenate([rng.uniform(-1.0, 9.0, 5000), [0.4, 6.9, -50.0, 1e6]])
    basis = _design(knots, x) @ coefficients
    np.testing.assert_allclose(_spline(knots, coefficients, x), basis, rtol=0, atol=1e-15)
    assert _spline(knots, coefficients, np.array([-50.0]))[0] == pytest.approx(coefficients[0], abs=1e-15)
    assert _spline(knots, coefficients, np.array([1e6]))[0] == pytest.approx(coefficients[-1], abs=1e-12)
