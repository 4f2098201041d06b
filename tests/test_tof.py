"""omnitof.sensor.tof: the paper's eq. 1–4, their inverse, and the noise model, against independent
computations (hand-worked samples, scalar math, Monte-Carlo)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnitof.sensor import tof
from omnitof.errors import ConfigError

C = 299_792_458.0  # m/s, written out here so the tests do not share the module's constant
F20 = 20e6
RANGE20 = C / (2 * F20)  # 7.4948 m


def circular_error(d: np.ndarray, truth: np.ndarray, period: float) -> np.ndarray:
    """d − truth wrapped to [-period/2, period/2): 0 and period are the same distance."""
    return np.mod(d - truth + period / 2, period) - period / 2


def test_unambiguous_range_at_20_and_30_mhz():
    assert tof.unambiguous_range(20e6) == pytest.approx(7.4948, abs=1e-4)
    assert tof.unambiguous_range(30e6) == pytest.approx(4.9965, abs=1e-4)


def test_hand_worked_samples_follow_the_sample_model():
    # Φ = π/2, A = 10, B = 50 under A_k = B + A·cos(Φ + k·π/2): samples (50, 40, 50, 60).
    frame = tof.decode(
        np.array([50.0]), np.array([40.0]), np.array([50.0]), np.array([60.0]), F20
    )
    assert frame.distance[0] == pytest.approx(RANGE20 / 4, abs=1e-12)  # Φ = π/2 → a quarter
    assert frame.amplitude[0] == pytest.approx(10.0, abs=1e-12)
    assert frame.offset[0] == pytest.approx(50.0, abs=1e-12)
    assert frame.saturated is None


def test_offset_is_the_mean_of_the_samples_not_half_their_sum():
    frame = tof.decode(*(np.array([v]) for v in (1.0, 2.0, 3.0, 4.0)), F20)
    assert frame.offset[0] == pytest.approx(2.5)  # (1/4)ΣA_k; the paper's (1/2)ΣA_k would be 5


def test_eq1_to_eq4_round_trip_on_random_phasors():
    rng = np.random.default_rng(7)
    n = 20_000
    phase = rng.uniform(0.0, 2 * math.pi, n)
    amplitude = rng.uniform(1e-3, 1e4, n)
    offset = amplitude + rng.uniform(0.0, 1e4, n)
    p = amplitude * np.exp(1j * phase)

    frame = tof.decode(*tof.ideal_samples(p, offset), F20)

    assert frame.distance.dtype == np.float64
    distance = phase * C / (4 * math.pi * F20)  # eq. 2
    assert np.abs(circular_error(frame.distance, distance, RANGE20)).max() < 1e-9
    assert np.all((frame.distance >= 0) & (frame.distance < RANGE20))
    assert np.abs(frame.amplitude - amplitude).max() < 1e-9 * 1e4
    assert np.abs(frame.offset - offset).max() < 1e-9 * 1e4


def test_noise_free_synthesis_round_trips_with_ambient_and_active_offset():
    rng = np.random.default_rng(3)
    p = rng.uniform(10, 1000, (50, 60)) * np.exp(1j * rng.uniform(0, 2 * math.pi, (50, 60)))
    ambient = rng.uniform(0, 500, (50, 60))
    a0, a1, a2, a3, saturated = tof.synthesise(
        p, ambient, rng=0, electrons_per_unit=math.inf, read_noise=0.0,
        modulation_contrast=0.5, full_well=1e9, dtype=np.float64,
    )
    frame = tof.decode(a0, a1, a2, a3, F20)
    assert not saturated.any()
    distance = np.angle(p) % (2 * math.pi) * C / (4 * math.pi * F20)
    assert np.abs(circular_error(frame.distance, distance, RANGE20)).max() < 1e-9
    assert np.abs(frame.amplitude - np.abs(p)).max() < 1e-9
    # Offset = ambient + DC of the active light, |p| / modulation contrast.
    assert np.abs(frame.offset - (ambient + np.abs(p) / 0.5)).max() < 1e-9


@pytest.mark.parametrize("f_mod", [20e6, 30e6])
def test_distances_wrap_at_the_unambiguous_range(f_mod):
    wrap = C / (2 * f_mod)
    true_distance = np.array([0.5, 2.0, wrap - 0.01, wrap + 0.5, 2 * wrap + 1.25])
    p = tof.phasor(2 * true_distance, 100.0, f_mod)  # source at the camera: path = 2·d
    frame = tof.decode(*tof.ideal_samples(p, 300.0), f_mod)
    expected = np.array([0.5, 2.0, wrap - 0.01, 0.5, 1.25])  # d − k·c/(2 f)
    np.testing.assert_allclose(frame.distance, expected, atol=1e-9)


def test_decoding_is_vectorised_over_images_and_keeps_float32():
    rng = np.random.default_rng(11)
    samples = [rng.uniform(0, 4000, (144, 176)).astype(np.float32) for _ in range(4)]
    frame = tof.decode(*samples, F20)
    for image in (frame.distance, frame.amplitude, frame.offset):
        assert image.shape == (144, 176)
        assert image.dtype == np.float32
    # A few pixels by scalar math, straight from eq. 1–4.
    for row, col in [(0, 0), (143, 175), (71, 88), (5, 170)]:
        a0, a1, a2, a3 = (float(s[row, col]) for s in samples)
        phase = math.atan2(a3 - a1, a0 - a2) % (2 * math.pi)
        assert frame.distance[row, col] == pytest.approx(phase * C / (4 * math.pi * F20), rel=1e-6)
        amplitude = math.hypot(a3 - a1, a2 - a0) / 2
        assert frame.amplitude[row, col] == pytest.approx(amplitude, rel=1e-6)
        assert frame.offset[row, col] == pytest.approx((a0 + a1 + a2 + a3) / 4, rel=1e-6)


def test_synthesis_is_deterministic_for_a_seed():
    p = np.full((144, 176), 900.0 + 300.0j)
    first = tof.synthesise(p, 400.0, rng=42)
    again = tof.synthesise(p, 400.0, rng=np.random.default_rng(42))
    other = tof.synthesise(p, 400.0, rng=43)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first[0], other[0])
    assert first[0].dtype == np.float32 and first[0].shape == (144, 176)


@pytest.mark.parametrize(
    ("amplitude", "offset", "gain", "read_noise"),
    [
        (912.5, 2225.0, 20.0, 0.0),  # the default wall at 2 m, shot noise only
        (150.0, 400.0, 1.0, 0.0),  # weak return (σ_Φ ≈ 0.09 rad), electrons as units
        (5000.0, 12000.0, 4.0, 0.0),
        (300.0, 1000.0, 20.0, 5.0),  # read noise too (the formula's generalisation)
    ],
)
def test_distance_noise_matches_the_analytic_sigma(amplitude, offset, gain, read_noise):
    n = 200_000
    phase = 1.0  # away from 0 so that the noise does not wrap
    p = np.full(n, amplitude * np.exp(1j * phase))
    a0, a1, a2, a3, saturated = tof.synthesise(
        p, 0.0, rng=5, active_offset=offset, electrons_per_unit=gain,
        read_noise=read_noise, full_well=1e12, dtype=np.float64,
    )
    assert not saturated.any()
    frame = tof.decode(a0, a1, a2, a3, F20)
    measured = np.std(circular_error(frame.distance, phase * C / (4 * math.pi * F20), RANGE20))
    # Lange & Seitz, written out independently: σ_d = c/(4π f)·√(B/g + σ_r²)/(√2·A).
    sigma_phase = math.sqrt(offset / gain + read_noise**2) / (math.sqrt(2) * amplitude)
    expected = C / (4 * math.pi * F20) * sigma_phase
    assert tof.distance_noise_std(
        amplitude, offset, F20, electrons_per_unit=gain, read_noise=read_noise
    ) == pytest.approx(expected, rel=1e-12)
    assert measured == pytest.approx(expected, rel=0.03)


def test_lange_seitz_in_electrons_is_the_default_form():
    # Units = electrons, no read noise: σ_d = c/(4π f)·√B/(√2·A).
    assert tof.distance_noise_std(1e4, 4e4, F20) == pytest.approx(
        C / (4 * math.pi * F20) * 200.0 / (math.sqrt(2) * 1e4)
    )


def test_default_sensor_gives_about_1_cm_on_a_matte_wall_at_2_m():
    noise = tof.SensorNoise()
    amplitude, offset = noise.wall_signal(2.0, albedo=0.5)
    assert float(noise.distance_noise_std(amplitude, offset)) == pytest.approx(0.010, abs=0.0005)
    # Monte-Carlo through the whole chain, a (144, 176) image of the wall.
    p = tof.phasor(np.full((144, 176), 4.0), amplitude, noise.f_mod)
    a0, a1, a2, a3, saturated = noise.synthesise(p, rng=1)
    frame = tof.decode(a0, a1, a2, a3, noise.f_mod, saturated=saturated)
    assert not frame.saturated.any()
    assert float(np.mean(frame.distance)) == pytest.approx(2.0, abs=0.001)
    assert float(np.std(frame.distance)) == pytest.approx(0.010, abs=0.0007)
    # Amplitude falls as 1/r²: a quarter at twice the distance.
    assert noise.wall_signal(4.0)[0] == pytest.approx(amplitude / 4)


def test_saturation_flags_exactly_the_pixels_with_a_sample_over_full_well():
    rng = np.random.default_rng(9)
    p = rng.uniform(0, 3000, (144, 176)) * np.exp(1j * rng.uniform(0, 2 * math.pi, (144, 176)))
    ambient = 500.0
    full_well = 6000.0
    expected_samples = np.stack(tof.ideal_samples(p, ambient + np.abs(p) / 0.5))
    expected = (expected_samples > full_well).any(axis=0)
    assert 0 < expected.sum() < expected.size  # the test image has both kinds of pixels

    a0, a1, a2, a3, saturated = tof.synthesise(
        p, ambient, rng=0, full_well=full_well, electrons_per_unit=math.inf, read_noise=0.0,
        modulation_contrast=0.5, dtype=np.float64,
    )
    np.testing.assert_array_equal(saturated, expected)
    samples = np.stack([a0, a1, a2, a3])
    assert samples.max() == full_well  # clipped at full well
    np.testing.assert_array_equal((samples >= full_well).any(axis=0), expected)

    # decode reports them: from the clipped samples and full_well, or from the mask.
    by_level = tof.decode(a0, a1, a2, a3, F20, full_well=full_well)
    by_mask = tof.decode(a0, a1, a2, a3, F20, saturated=saturated)
    np.testing.assert_array_equal(by_level.saturated, expected)
    np.testing.assert_array_equal(by_mask.saturated, expected)
    # Unsaturated pixels decode exactly; saturated ones are biased (hence the flag).
    true_amplitude = np.abs(p)
    assert np.abs(by_level.amplitude - true_amplitude)[~expected].max() < 1e-9
    assert np.abs(by_level.amplitude - true_amplitude)[expected].max() > 1.0


def test_noisy_saturation_flags_follow_the_drawn_samples():
    p = np.full((144, 176), 2000.0 + 0j)
    # B = 400 + 2000/0.5 = 4400, so μ0 = B + A = 6400: about half the pixels' A0 exceed it.
    full_well = 6400.0
    a0, a1, a2, a3, saturated = tof.synthesise(
        p, 400.0, rng=2, full_well=full_well, dtype=np.float64
    )
    at_limit = np.stack([a0, a1, a2, a3]) >= full_well
    np.testing.assert_array_equal(saturated, at_limit.any(axis=0))
    assert 0 < saturated.sum() < saturated.size


def test_bad_parameters_raise_errors_naming_them():
    p = np.ones((2, 2), dtype=complex)
    with pytest.raises(ValueError, match="f_mod"):
        tof.decode(p.real, p.real, p.real, p.real, -20e6)
    with pytest.raises(ValueError, match="a2"):
        tof.decode(p.real, p.real, np.ones(3), p.real, F20)
    with pytest.raises(ValueError, match="ambient"):
        tof.synthesise(p, -1.0, rng=0)
    with pytest.raises(ValueError, match="rng"):
        tof.synthesise(p, 1.0, rng=None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="active_offset"):
        tof.synthesise(p, 1.0, rng=0, active_offset=0.5)
    with pytest.raises(ConfigError, match="modulation_contrast"):
        tof.SensorNoise(modulation_contrast=1.5)
    with pytest.raises(ValueError, match="full_well"):
        tof.SensorNoise(full_well=0.0)
