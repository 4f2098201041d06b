"""omnitof.sensor.tof_errors: the systematic errors of the ToF camera against independent
computations (the harmonics' effect on the 4-tap decoding worked out by hand, an FFT of the
decoded error, the offsets' closed form) and their YAML form."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from omnitof.sensor import tof
from omnitof.sensor.rig import Rig, RigError
from omnitof.sensor.design import default_rig
from omnitof.sensor.tof_errors import ToFErrors, ToFErrorsError, amplitude_offset, fixed_pattern, wiggling_error

C = 299_792_458.0
F20 = 20e6
RANGE20 = C / (2 * F20)
NOISELESS = dict(electrons_per_unit=math.inf, read_noise=0.0, ambient=0.0)


def circular(d: np.ndarray) -> np.ndarray:
    return np.mod(d + RANGE20 / 2, RANGE20) - RANGE20 / 2


def decoded(sensor: tof.SensorNoise, distance: np.ndarray, amplitude: np.ndarray | float = 500.0) -> np.ndarray:
    p = np.asarray(amplitude) * np.exp(1j * 4 * math.pi * F20 / C * distance)
    a0, a1, a2, a3, _ = sensor.synthesise(p, rng=0, dtype=np.float64)
    return tof.decode(a0, a1, a2, a3, F20).distance


def test_wiggling_decodes_to_the_hand_derived_curve():
    # Samples of c(θ) = cos θ + h3 cos 3θ + h5 cos 5θ at θ = Φ + kπ/2, written out here:
    # A3 − A1 = 2A(sinΦ − h3 sin 3Φ + h5 sin 5Φ), A0 − A2 = 2A(cosΦ + h3 cos 3Φ + h5 cos 5Φ).
    h3, h5 = 0.05, 0.02
    d = np.linspace(0.0, RANGE20, 1001, endpoint=False)
    phi = 2 * math.pi * d / RANGE20
    by_hand = np.arctan2(np.sin(phi) - h3 * np.sin(3 * phi) + h5 * np.sin(5 * phi),
                         np.cos(phi) + h3 * np.cos(3 * phi) + h5 * np.cos(5 * phi))
    expected = circular(np.mod(by_hand, 2 * math.pi) * RANGE20 / (2 * math.pi) - d)
    sensor = tof.SensorNoise(**NOISELESS, errors=ToFErrors(wiggling=True, harmonic3=h3, harmonic5=h5))
    measured = circular(decoded(sensor, d) - d)
    np.testing.assert_allclose(measured, expected, atol=1e-9)
    np.testing.assert_allclose(wiggling_error(d, F20, h3, h5), expected, atol=1e-12)


def test_wiggling_has_a_quarter_range_period_and_the_first_order_amplitude():
    errors = ToFErrors(wiggling=True)
    sensor = tof.SensorNoise(**NOISELESS, errors=errors)
    d = np.linspace(0.0, RANGE20, 4096, endpoint=False)
    err = circular(decoded(sensor, d) - d)
    spectrum = np.abs(np.fft.rfft(err)) / (len(d) / 2)
    assert int(np.argmax(spectrum)) == 4  # 4 cycles over the range: period R/4
    first_order = RANGE20 / (2 * math.pi) * abs(errors.harmonic5 - errors.harmonic3)
    assert spectrum[4] == pytest.approx(first_order, rel=0.01)
    assert 0.02 < first_order < 0.03  # "centimetres": 2.5 cm with the defaults
    # Even harmonics would cancel; without wiggling the decoding is exact.
    exact = decoded(tof.SensorNoise(**NOISELESS), d)
    np.testing.assert_allclose(circular(exact - d), 0.0, atol=1e-9)


def test_offsets_follow_their_closed_form_per_pixel():
    errors = ToFErrors(amplitude_offset=True, fixed_pattern=True, fixed_pattern_seed=7)
    sensor = tof.SensorNoise(**NOISELESS, errors=errors)
    shape = (6, 8)
    d = np.full(shape, 2.0)
    amp = np.geomspace(20.0, 5000.0, d.size).reshape(shape)
    measured = decoded(sensor, d, amp)
    pattern = fixed_pattern(shape, errors)
    expected = 2.0 + pattern + errors.amplitude_offset_m * np.log(errors.amplitude_reference / amp)
    np.testing.assert_allclose(measured, expected, atol=1e-9)
    assert pattern.std() == pytest.approx(errors.fixed_pattern_std, rel=0.5)
    # The pattern is the camera's: the same in every frame, another for another seed.
    np.testing.assert_array_equal(pattern, fixed_pattern(shape, errors))
    assert not np.allclose(pattern, fixed_pattern(shape, ToFErrors(fixed_pattern=True, fixed_pattern_seed=8)))
    # Dim returns read long, bright ones short; zero at the reference.
    assert amplitude_offset(errors.amplitude_reference, errors) == pytest.approx(0.0)
    assert amplitude_offset(60.0, errors) > 0.02 > -amplitude_offset(3000.0, errors) > 0


def test_per_sample_phasors_give_each_sample_its_own_scene():
    # The same phasor for all four samples equals the one-phasor synthesis.
    sensor = tof.SensorNoise(**NOISELESS, errors=ToFErrors(wiggling=True))
    p = 300.0 * np.exp(1j * np.linspace(0, 6, 12)).reshape(3, 4)
    one = sensor.synthesise(p, rng=0, dtype=np.float64)
    four = sensor.synthesise(np.stack([p] * 4), rng=0, dtype=np.float64, per_sample=True)
    for a, b in zip(one[:4], four[:4]):
        np.testing.assert_allclose(a, b, atol=1e-9)
    # Sample k reads its own phasor: A_k = B + Re(p_k·i^k) (no wiggling).
    plain = tof.SensorNoise(**NOISELESS)
    ps = np.array([100.0, 200j, -50.0, 10 - 30j]).reshape(4, 1, 1)
    samples = plain.synthesise(ps, rng=0, dtype=np.float64, per_sample=True)
    b = np.abs(ps) / plain.modulation_contrast
    expected = [b[0] + 100.0, b[1] - 200.0, b[2] + 50.0, b[3] - 30.0]
    for k in range(4):
        assert samples[k].item() == pytest.approx(expected[k].item())


def test_errors_travel_with_the_rig_and_bad_fields_are_named():
    rig = default_rig()
    errors = ToFErrors.realistic(fixed_pattern_seed=3)
    with_errors = Rig(rig.camera, rig.planes, rig.names, rig.robot_T_camera, rig.outlines,
                      tof.SensorNoise(errors=errors))
    back = Rig.from_dict(with_errors.to_dict())
    assert back.sensor == with_errors.sensor and back.sensor.errors.motion
    assert Rig.from_dict(rig.to_dict()).sensor.errors == ToFErrors()  # an old sidecar: none
    data = with_errors.to_dict()
    data["sensor"]["errors"]["wiggle"] = True
    with pytest.raises(RigError, match="wiggle"):
        Rig.from_dict(data)
    # A number that is not one is named by its field and entry (it read "expected finite numbers
    # of shape (4, 4), got shape (4, 4)", and "could not convert string to float" without a field).
    data = rig.to_dict()
    data["robot_T_camera"][2][3] = float("nan")
    with pytest.raises(RigError, match=re.escape("robot_T_camera: entry [2, 3] is nan, not a finite number")):
        Rig.from_dict(data)
    data = rig.to_dict()
    data["camera"]["fx"] = "abc"
    with pytest.raises(RigError, match="camera.fx: expected a number, got 'abc'"):
        Rig.from_dict(data)
    data["camera"]["fx"] = np.float32(rig.camera.fx)  # numbers of numpy's own are numbers
    assert Rig.from_dict(data).camera.fx == pytest.approx(rig.camera.fx)
    with pytest.raises(ToFErrorsError, match="harmonic3"):
        ToFErrors(harmonic3=0.5)
    with pytest.raises(ToFErrorsError, match="integration_time"):
        ToFErrors(integration_time=0.0)
    with pytest.raises(ToFErrorsError, match="errors.led_count must be at most 64, got 4000"):
        ToFErrors(led_count=4000)  # every light path is worked out per LED: it ran for minutes
    with pytest.raises(ToFErrorsError, match=r"errors.led_half_angle_deg must lie in \(0, 180\], got 360"):
        ToFErrors(led_half_angle_deg=360.0)  # rendered a dark image
    assert ToFErrors.realistic().only("wiggling") == ToFErrors(wiggling=True)
