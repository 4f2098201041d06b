"""Time-of-flight measurement: four phase samples ↔ distance, amplitude and offset (paper eq. 1–4).

A continuous-wave ToF pixel correlates the returning light with the modulation signal at four
phase steps and stores four samples A0..A3. This module decodes them (eq. 1–4) and, for the
simulator, synthesises them from a phasor with shot noise, read noise and saturation.

Sample model (the one eq. 1 and eq. 3 imply, used exactly by the synthesis):

    A_k = B + A·cos(Φ + k·π/2),   k = 0, 1, 2, 3

so A0 = B + A·cosΦ, A1 = B − A·sinΦ, A2 = B − A·cosΦ, A3 = B + A·sinΦ. Then
A3 − A1 = 2A·sinΦ and A0 − A2 = 2A·cosΦ, hence atan2(A3 − A1, A0 − A2) = Φ (eq. 1, with atan2
for the quadrant) and √((A3 − A1)² + (A2 − A0)²)/2 = A (eq. 3). The other sign choice,
cos(Φ − k·π/2), would decode to −Φ. With a phasor p = A·e^{iΦ}: A_k = B + Re(p·i^k).

Offset convention: B = (1/4)·ΣA_k, the mean of the samples (the "4-bucket" convention of
Lange & Seitz 2001). It is the DC level of the correlation function, so the synthesis can add
ambient light to it directly and decode returns the B it was given. The paper prints
B = (1/2)·ΣA_k, which is twice that; only the scale differs.

Units: distances in metres (one way, camera to surface), phases in radians in [0, 2π), f_mod in
Hz; A, B and the samples in "sample units" (the camera's raw digital numbers); shot noise is
expressed through `electrons_per_unit` (the conversion gain, electrons per sample unit).
Arrays may have any shape; images are (rows, cols) = (144, 176).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import scipy.constants

from omnitof.errors import ConfigError
from omnitof.sensor.tof_errors import ToFErrors, apply_offsets, correlation_samples

SPEED_OF_LIGHT: float = scipy.constants.c  # m/s, exact by definition of the metre

# 20 MHz: c/(2 f) = 7.49 m unambiguous range. DESIGN.md asks for "about 20 MHz" (the SR-3000's
# default); the SR4000 ships at 30 MHz (5 m) but libMesaSR also selects 20 MHz (7.5 m), as the
# MITK SR4000 driver's frequency table shows.
DEFAULT_F_MOD: float = 20e6


class ToFParameterError(ConfigError, ValueError):
    """A bad ToF parameter or input array; the message names it (a ConfigError and a ValueError)."""


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (value > 0.0):  # also rejects NaN
        raise ToFParameterError(f"{name} must be > 0, got {value!r}")
    return value


def _non_negative(name: str, value: float) -> float:
    value = float(value)
    if not (value >= 0.0):
        raise ToFParameterError(f"{name} must be >= 0, got {value!r}")
    return value


def unambiguous_range(f_mod: float) -> float:
    """The largest distance (m) the phase can tell apart: c / (2·f_mod); 7.49 m at 20 MHz."""
    return SPEED_OF_LIGHT / (2.0 * _positive("f_mod", f_mod))


def phase_to_distance(phase: np.ndarray | float, f_mod: float) -> np.ndarray:
    """Eq. 2: d = Φ·c / (4π·f_mod). Φ in radians, d in metres (one way)."""
    return np.asarray(phase) * (SPEED_OF_LIGHT / (4.0 * math.pi * _positive("f_mod", f_mod)))


def path_to_phase(path_length: np.ndarray | float, f_mod: float) -> np.ndarray:
    """Phase delay (rad, wrapped to [0, 2π)) of light that travelled `path_length` metres.

    `path_length` is the whole optical path, light source → surface → pixel (through mirrors if
    any); for a source at the camera centre it is twice the distance, so that eq. 2 gives the
    distance back, modulo the unambiguous range.
    """
    phase = np.asarray(path_length, dtype=np.float64) * (
        2.0 * math.pi * _positive("f_mod", f_mod) / SPEED_OF_LIGHT
    )
    return _wrap_phase(phase)


def phasor(
    path_length: np.ndarray | float, amplitude: np.ndarray | float, f_mod: float
) -> np.ndarray:
    """The complex return amplitude·e^{iΦ} of one light path (Φ from `path_to_phase`).

    Phasors of several paths seen by one pixel add (mixed pixels at depth edges, multipath).
    """
    return np.asarray(amplitude, dtype=np.float64) * np.exp(1j * path_to_phase(path_length, f_mod))


def _wrap_phase(phase: np.ndarray) -> np.ndarray:
    wrapped = np.mod(phase, 2.0 * math.pi)
    # np.mod of a tiny negative number rounds to exactly 2π; the interval is half-open.
    return np.where(wrapped >= 2.0 * math.pi, 0.0, wrapped)


@dataclass
class ToFFrame:
    """One decoded ToF frame; every array has the shape of the samples, e.g. (144, 176).

    Attributes:
        distance: metres, one way, in [0, c/(2·f_mod)): wraps at the unambiguous range.
        amplitude: A of eq. 3, sample units.
        offset: B = mean of the four samples, sample units (see the module docstring).
        saturated: bool mask of pixels where a sample reached full well (their distance,
            amplitude and offset are biased), or None when unknown.
    """

    distance: np.ndarray
    amplitude: np.ndarray
    offset: np.ndarray
    saturated: np.ndarray | None = None

    def __post_init__(self) -> None:
        shape = np.shape(self.distance)
        for name in ("amplitude", "offset", "saturated"):
            value = getattr(self, name)
            if value is not None and np.shape(value) != shape:
                raise ToFParameterError(
                    f"ToFFrame.{name} must have the shape of distance {shape}, "
                    f"got {np.shape(value)}"
                )


def _samples(
    a0: npt.ArrayLike, a1: npt.ArrayLike, a2: npt.ArrayLike, a3: npt.ArrayLike
) -> tuple[list[np.ndarray], np.dtype]:
    arrays = [np.asarray(a) for a in (a0, a1, a2, a3)]
    for k, a in enumerate(arrays[1:], start=1):
        if a.shape != arrays[0].shape:
            raise ToFParameterError(
                f"a{k} must have the shape of a0 {arrays[0].shape}, got {a.shape}"
            )
    # Output in the samples' float type (float32 images stay float32), never integer.
    dtype = np.result_type(*arrays, np.float32)
    return [a.astype(np.float64) for a in arrays], dtype


def decode(
    a0: np.ndarray,
    a1: np.ndarray,
    a2: np.ndarray,
    a3: np.ndarray,
    f_mod: float,
    *,
    full_well: float | None = None,
    saturated: np.ndarray | None = None,
) -> ToFFrame:
    """Decode four phase samples into distance, amplitude and offset (eq. 1–4), per pixel.

    Φ = atan2(A3 − A1, A0 − A2) wrapped to [0, 2π) (eq. 1), d = Φ·c/(4π·f_mod) (eq. 2),
    A = √((A3 − A1)² + (A2 − A0)²)/2 (eq. 3), B = (A0 + A1 + A2 + A3)/4 (eq. 4 as the mean).

    Args:
        a0..a3: samples of the same shape, any float or integer type, sample units.
        f_mod: modulation frequency, Hz.
        full_well: when given, a pixel is flagged saturated if any sample is >= full_well.
        saturated: a mask of pixels already known to be saturated (e.g. from `synthesise`);
            OR-ed with the full-well test.

    Returns:
        A ToFFrame in the samples' float type (float32 stays float32); `saturated` is None when
        neither `full_well` nor `saturated` is given. Computed in float64 internally.
    """
    (s0, s1, s2, s3), dtype = _samples(a0, a1, a2, a3)
    f_mod = _positive("f_mod", f_mod)
    sin_part = s3 - s1  # 2A·sinΦ
    cos_part = s0 - s2  # 2A·cosΦ
    phase = _wrap_phase(np.arctan2(sin_part, cos_part))
    distance = _cast_distance(phase_to_distance(phase, f_mod), dtype, unambiguous_range(f_mod))
    amplitude = (np.hypot(sin_part, cos_part) / 2.0).astype(dtype)
    offset = ((s0 + s1 + s2 + s3) / 4.0).astype(dtype)
    mask = _saturation_mask((s0, s1, s2, s3), full_well, saturated)
    return ToFFrame(distance, amplitude, offset, mask)


def _cast_distance(distance: np.ndarray, dtype: np.dtype, wrap: float) -> np.ndarray:
    out = distance.astype(dtype)
    # A distance a hair below the range can round up to it in float32; keep [0, range).
    return np.where(out >= dtype.type(wrap), dtype.type(0.0), out)


def _saturation_mask(
    samples: tuple[np.ndarray, ...], full_well: float | None, saturated: np.ndarray | None
) -> np.ndarray | None:
    if full_well is None and saturated is None:
        return None
    mask = np.zeros(samples[0].shape, dtype=bool)
    if full_well is not None:
        for s in samples:
            mask |= s >= full_well
    if saturated is not None:
        saturated = np.asarray(saturated, dtype=bool)
        if saturated.shape != mask.shape:
            raise ToFParameterError(
                f"saturated must have the shape of the samples {mask.shape}, got {saturated.shape}"
            )
        mask |= saturated
    return mask


def ideal_samples(
    phasor: np.ndarray, offset: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Noise-free samples A_k = B + Re(p·i^k) = B + A·cos(Φ + k·π/2) of the module's model.

    Args:
        phasor: complex, A·e^{iΦ}, sample units.
        offset: B, sample units, broadcast against `phasor`.

    Returns:
        (a0, a1, a2, a3) in float64, the broadcast shape; `decode` returns Φ, A, B exactly
        (to rounding).
    """
    p = np.asarray(phasor, dtype=np.complex128)
    re, im, b = np.broadcast_arrays(p.real, p.imag, np.asarray(offset, dtype=np.float64))
    # i^k turns p by k·90°: Re(p), Re(i·p) = −Im(p), Re(−p) = −Re(p), Re(−i·p) = Im(p).
    return b + re, b - im, b - re, b + im


# --- Sensor noise defaults -------------------------------------------------------------------
#
# Working point (the project's target, not a published figure): a matte wall (albedo 0.5 in the
# near infrared, an assumption for light-grey paint at 850 nm) facing the camera at 2 m gives
# σ_d ≈ 1.0 cm at 20 MHz. The numbers below were solved together for that point; what each one
# assumes:
#
# - electrons_per_unit = 20: conversion gain of the raw samples (an assumption, not published for
#   the SR4000); with the 16-bit full scale it makes the well 65535·20 ≈ 1.3 million electrons,
#   the order of a 40 µm CCD lock-in pixel.
# - full_well = 65535: assumed 16-bit raw samples that clip there. With the amplitude scale
#   below a white (albedo 1) target facing the camera saturates nearer than 0.58 m, a 0.5-albedo
#   wall nearer than 0.41 m: SR4000-class cameras saturate on bright targets at close range
#   (the SR4000's calibrated range starts at 0.8 m).
# - read_noise = 2 units (40 electrons rms per sample): assumed; at the working point it adds
#   2 % to σ_d, so the shot noise of the offset dominates, as Lange & Seitz describe.
# - modulation_contrast = 0.5: A / (offset due to the active light), assumed; CCD lock-in
#   pixels of that time demodulate with a contrast of the order of 40–50 % at 20 MHz (Lange &
#   Seitz 2001 discuss it; the exact figure varies by device).
# - amplitude_at_1m = 7300 units: the amplitude of an albedo-1 Lambertian target facing the
#   camera at 1 m; amplitude ∝ albedo·cos(incidence)/r² (one-way r, or half the whole path).
#   Solved so that the working point gives 1 cm: A = 912.5, B = 2225 units, σ_d = 9.9 mm at 2 m.
# - ambient = 400 units: offset from background light through the camera's 850 nm band-pass
#   filter in a lit office (assumed; 18 % of B at the working point).
#
# Against the SR4000 datasheet (absolute accuracy ±1 cm; repeatability 1σ about 4 mm at 2 m on a
# 99 % reflective target in the central pixels, quoted from memory of the datasheet, not
# re-checked here): these defaults give 6.7 mm for a 99 % target at 2 m, i.e. about 1.7× the
# datasheet's typical value; they model the brief's "1 cm on a matte wall at 2 m" working point
# (shorter integration, off-centre pixels, an older camera of that class) rather than the best
# case of the datasheet.


@dataclass(frozen=True)
class SensorNoise:
    """Noise, saturation and signal scale of a 176×144 SR4000-class ToF camera (see above).

    Attributes:
        f_mod: modulation frequency (Hz) the noise figures refer to.
        electrons_per_unit: conversion gain, electrons per sample unit; inf turns shot noise off.
        read_noise: standard deviation of the additive Gaussian noise of each sample, units.
        full_well: the value at which a sample clips (well or ADC, whichever first), units.
        modulation_contrast: A / B_active, amplitude over the offset the active light adds.
        amplitude_at_1m: A of an albedo-1 Lambertian target facing the camera at 1 m, units.
        ambient: offset from background light, units.
        errors: the camera's systematic errors (`omnitof.sensor.tof_errors.ToFErrors`: wiggling,
            amplitude-dependent and fixed-pattern offsets, motion during a frame); all off by
            default, a mapping of its fields is accepted (the YAML form).
    """

    f_mod: float = DEFAULT_F_MOD
    electrons_per_unit: float = 20.0
    read_noise: float = 2.0
    full_well: float = 65535.0
    modulation_contrast: float = 0.5
    amplitude_at_1m: float = 7300.0
    ambient: float = 400.0
    errors: ToFErrors = field(default_factory=ToFErrors)

    def __post_init__(self) -> None:
        if isinstance(self.errors, Mapping):
            object.__setattr__(self, "errors", ToFErrors.from_dict(self.errors))
        elif not isinstance(self.errors, ToFErrors):
            raise ToFParameterError(f"SensorNoise.errors must be ToFErrors or a mapping, got {self.errors!r}")
        _positive("SensorNoise.f_mod", self.f_mod)
        _positive("SensorNoise.electrons_per_unit", self.electrons_per_unit)
        _non_negative("SensorNoise.read_noise", self.read_noise)
        _positive("SensorNoise.full_well", self.full_well)
        contrast = float(self.modulation_contrast)
        if not (0.0 < contrast <= 1.0):
            raise ToFParameterError(
                "SensorNoise.modulation_contrast must be in (0, 1], "
                f"got {self.modulation_contrast!r}"
            )
        _positive("SensorNoise.amplitude_at_1m", self.amplitude_at_1m)
        _non_negative("SensorNoise.ambient", self.ambient)

    def wall_signal(
        self, distance: np.ndarray | float, albedo: float = 0.5, incidence: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """(A, B) in sample units of a Lambertian surface at `distance` m, `incidence` rad.

        A = amplitude_at_1m·albedo·cos(incidence)/distance²; B = ambient + A/modulation_contrast.
        """
        r = np.asarray(distance, dtype=np.float64)
        amplitude = self.amplitude_at_1m * albedo * math.cos(incidence) / (r * r)
        return amplitude, self.ambient + amplitude / self.modulation_contrast

    def distance_noise_std(
        self, amplitude: np.ndarray | float, offset: np.ndarray | float
    ) -> np.ndarray:
        """σ_d (m) of `distance_noise_std` with this sensor's gain, read noise and f_mod."""
        return distance_noise_std(
            amplitude,
            offset,
            self.f_mod,
            electrons_per_unit=self.electrons_per_unit,
            read_noise=self.read_noise,
        )

    def synthesise(
        self,
        phasor: np.ndarray,
        ambient: np.ndarray | float | None = None,
        *,
        rng: np.random.Generator | int,
        active_offset: np.ndarray | float | None = None,
        dtype: npt.DTypeLike = np.float32,
        per_sample: bool = False,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """`synthesise` with this sensor's parameters and systematic errors; `ambient`
        defaults to `self.ambient`."""
        return synthesise(
            phasor,
            self.ambient if ambient is None else ambient,
            rng=rng,
            full_well=self.full_well,
            read_noise=self.read_noise,
            electrons_per_unit=self.electrons_per_unit,
            modulation_contrast=self.modulation_contrast,
            active_offset=active_offset,
            dtype=dtype,
            errors=self.errors,
            f_mod=self.f_mod,
            per_sample=per_sample,
        )


_DEFAULT_NOISE = SensorNoise()


def _generator(rng: np.random.Generator | int) -> np.random.Generator:
    # Every stochastic step takes an explicit seed (DESIGN.md); None would be irreproducible.
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise ToFParameterError(f"rng must be a numpy Generator or an integer seed, got {rng!r}")


def _offsets(
    phasor: np.ndarray,
    ambient: np.ndarray | float,
    active_offset: np.ndarray | float | None,
    modulation_contrast: float,
) -> np.ndarray:
    amb = np.asarray(ambient, dtype=np.float64)
    if not np.all(np.isfinite(amb)) or np.any(amb < 0.0):
        raise ToFParameterError("ambient must be finite and >= 0")
    magnitude = np.abs(phasor)
    if active_offset is None:
        active = magnitude / modulation_contrast
    else:
        active = np.asarray(active_offset, dtype=np.float64)
        # B >= A keeps every expected sample >= 0; the sum of |p_i| of a mixed pixel satisfies it.
        if np.any(active < magnitude * (1.0 - 1e-12)):
            raise ToFParameterError("active_offset must be >= |phasor| everywhere")
    return amb + active


def synthesise(
    phasor: np.ndarray,
    ambient: np.ndarray | float,
    *,
    rng: np.random.Generator | int,
    full_well: float = _DEFAULT_NOISE.full_well,
    read_noise: float = _DEFAULT_NOISE.read_noise,
    electrons_per_unit: float = _DEFAULT_NOISE.electrons_per_unit,
    modulation_contrast: float = _DEFAULT_NOISE.modulation_contrast,
    active_offset: np.ndarray | float | None = None,
    dtype: npt.DTypeLike = np.float32,
    errors: ToFErrors | None = None,
    f_mod: float = DEFAULT_F_MOD,
    per_sample: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Draw the four noisy, clipped samples of the module's model from a per-pixel phasor.

    The expected samples are μ_k = B + A·cos(Φ + k·π/2) with A·e^{iΦ} = phasor and offset
    B = ambient + active_offset, where active_offset defaults to |phasor|/modulation_contrast
    (the DC part of the returning modulated light). For a mixed pixel, whose phasor is a sum,
    pass active_offset = Σ|p_i|/modulation_contrast: the DC parts add, the phasors partly cancel.
    Each sample is then μ_k + √(μ_k/electrons_per_unit + read_noise²)·z_k with z_k standard
    normal (shot noise as a Gaussian whose variance in electrons equals the expected electron
    count, plus read noise), clipped to [0, full_well]; a pixel is saturated where any sample
    exceeded full_well.

    Args:
        phasor: complex array, A·e^{iΦ} in sample units (see `phasor`).
        ambient: offset from background light, >= 0, array broadcastable to phasor or scalar.
        rng: a numpy Generator or an integer seed; the same seed gives the same samples.
        full_well, read_noise, electrons_per_unit, modulation_contrast: see `SensorNoise`;
            electrons_per_unit = inf and read_noise = 0 give noise-free samples.
        active_offset: the active light's offset, see above.
        dtype: dtype of the returned samples (float32 for images).
        errors: systematic errors (`ToFErrors`; None: none): the offsets turn the phasor's
            phase, the wiggling adds the correlation's odd harmonics to μ_k; `f_mod` (Hz)
            converts the offsets to phase.
        per_sample: phasor, ambient and active_offset carry a leading axis of 4, sample k's
            own (the scene at sample k's time: motion during the frame).

    Returns:
        (a0, a1, a2, a3, saturated): four sample arrays and a bool mask, all of the broadcast
        shape of phasor and ambient.

    The renderer (`omnitof.sim.render`) makes its frames with the same model in the Rust core
    (rust/src/tof_frames.rs, with its own random stream); this function is the reference.
    """
    gen = _generator(rng)
    full_well = _positive("full_well", full_well)
    read_noise = _non_negative("read_noise", read_noise)
    gain = _positive("electrons_per_unit", electrons_per_unit)
    contrast = _positive("modulation_contrast", modulation_contrast)
    errors = errors if errors is not None else ToFErrors()
    p = apply_offsets(np.asarray(phasor, dtype=np.complex128), errors, _positive("f_mod", f_mod))
    if per_sample and (p.ndim < 1 or p.shape[0] != 4):
        raise ToFParameterError(f"per_sample: phasor must have a leading axis of 4, got shape {p.shape}")
    offset = _offsets(p, ambient, active_offset, contrast)
    expected = correlation_samples(p, offset, errors, per_sample)  # (4, ...)
    sigma = np.sqrt(np.maximum(expected, 0.0) / gain + read_noise**2)
    drawn = expected + sigma * gen.standard_normal(expected.shape)
    saturated = np.any(drawn > full_well, axis=0)
    clipped = np.clip(drawn, 0.0, full_well).astype(dtype)  # charge is never negative
    return clipped[0], clipped[1], clipped[2], clipped[3], saturated


def distance_noise_std(
    amplitude: np.ndarray | float,
    offset: np.ndarray | float,
    f_mod: float,
    *,
    electrons_per_unit: float = 1.0,
    read_noise: float = 0.0,
) -> np.ndarray:
    """Analytic standard deviation (m) of the decoded distance under the module's noise model.

    σ_d = c/(4π·f_mod) · √(B/g + σ_r²) / (√2·A), with g = electrons_per_unit, σ_r = read_noise.
    For σ_r = 0 and A, B counted in electrons (g = 1) this is Lange & Seitz's (IEEE J. Quantum
    Electron. 37(3), 2001) σ_d = c/(4π·f_mod)·√B/(√2·A).

    Derivation: S = A3 − A1 and C = A0 − A2 have expectations 2A·sinΦ and 2A·cosΦ; their noises
    are independent with variance (μ1 + μ3)/g + 2σ_r² = 2B/g + 2σ_r² (the sample model makes
    μ1 + μ3 = μ0 + μ2 = 2B). To first order δΦ = (cosΦ·δS − sinΦ·δC)/(2A), so
    Var Φ = (2B/g + 2σ_r²)/(4A²) whatever Φ; eq. 2 scales it by c/(4π·f_mod). Valid while
    σ_Φ ≪ 1 rad and no sample clips.
    """
    a = np.asarray(amplitude, dtype=np.float64)
    b = np.asarray(offset, dtype=np.float64)
    gain = _positive("electrons_per_unit", electrons_per_unit)
    read_noise = _non_negative("read_noise", read_noise)
    with np.errstate(divide="ignore"):
        sigma_phase = np.sqrt(b / gain + read_noise**2) / (math.sqrt(2.0) * a)
    return phase_to_distance(sigma_phase, f_mod)
