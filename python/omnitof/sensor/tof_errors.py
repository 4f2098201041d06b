"""The ToF camera's systematic errors: wiggling, amplitude-dependent and fixed-pattern offsets,
and the settings (switches) of every systematic effect the simulator models.

`ToFErrors` is part of the sensor settings (`SensorNoise.errors`), so a rig's YAML form, the bag
sidecar and the calibration file record which effects a frame was made with. Every effect is
off in `ToFErrors()` (the ideal camera of issue 3, which the tests of the decoding rely on);
`ToFErrors.realistic()` turns all of them on; `omnitof simulate` and `omnitof demo` simulate
all but multipath by default (`DEFAULT_SWITCHES`, which says why).

The functional form (what the distance correction of `omnitof.calibration.distance` is fitted
to). With R = c/(2·f_mod) the unambiguous range, d the true one-way distance of a pixel that
sees one surface, A its noise-free amplitude (sample units) and (row, col) the pixel:

    d'     = d + δ_fpn[row, col] + δ_amp(A)
    δ_amp  = amplitude_offset_m · ln(amplitude_reference / max(A, 1))
    δ_fpn  ~ N(0, fixed_pattern_std²), one value per pixel, drawn from fixed_pattern_seed
    d_meas = wrap_R( d' + (R/2π) · arg(1 + h3·e^{−i·4Φ'} + h5·e^{+i·4Φ'}) ),   Φ' = 2π·d'/R
           ≈ d' + (R/2π)·(h5 − h3)·sin(4Φ')     to first order in h3, h5

so the wiggling is periodic in d' with period R/4 (1.87 m at 20 MHz) and amplitude
(R/2π)·|h5 − h3| (2.5 cm with the defaults). Where it comes from: the correlation of the
returning light with the demodulation signal is not a pure cosine but
c(θ) = cos θ + h3·cos 3θ + h5·cos 5θ (odd harmonics of square-ish LED and shutter waveforms;
even harmonics cancel in the 4-tap differences). Sampling it at θ_k = Φ + k·π/2 gives
A3 − A1 = 2A·(sinΦ − h3·sin 3Φ + h5·sin 5Φ) and A0 − A2 = 2A·(cosΦ + h3·cos 3Φ + h5·cos 5Φ),
i.e. the decoded phasor e^{iΦ} + h3·e^{−3iΦ} + h5·e^{5iΦ}: the 3rd harmonic folds onto −3Φ and
the 5th onto +5Φ, both four times the fundamental's rate away from it (Lange 2000, PhD thesis,
Univ. Siegen, sec. 2.2, the figure of phase errors for cos x + cos nx sampled at four phases:
even n give no error, odd n a periodic one). A mixed pixel (a sum of phasors) gets the
harmonics of its summed phasor; that is exact for a pixel that sees one distance.

The figures (from the literature as remembered, not re-checked against the papers here):
- h3 = 0.035, h5 = 0.014 (the 1/n² ratio of a triangular correlation, 1/9 : 1/25, scaled down
  because the LEDs low-pass the square wave): 2.5 cm of wiggling amplitude at 20 MHz, the
  order of the "wiggling" that Lindner & Kolb (ISVC 2006, PMD camera at 20 MHz) and Kahlmann,
  Remondino & Ingensand (2006, SwissRanger SR-3000) report before calibration (centimetres,
  up to about 10 cm for some devices and frequencies); a pure triangle would give 8.5 cm.
- amplitude_offset_m = 1 cm per e-fold of amplitude, amplitude_reference = 1000 units (an
  albedo-0.5 wall at about 1.9 m): dim returns read long; −1.1 cm at 1 m and +2.8 cm at 7 m on
  a matte wall through a mirror, the few-centimetre intensity-related error that Lindner &
  Kolb (2006) calibrate.
- fixed_pattern_std = 1 cm: per-pixel offsets of the order Lindner & Kolb's per-pixel
  calibration removes (an assumption for this camera class).
- multipath_rays = 1 secondary ray per pixel, averaged over the pixels within
  multipath_window = 4 rows and columns that see the same surface (9 × 9 pixels, about 80
  rays). Rays per pixel alone are an unbiased estimate of each pixel's phasor but a very noisy
  one (with two, about its own size), and the scan's bins take the median of their pixels,
  which throws most of the interreflection away with the noise: matte bins read 0.1 cm long
  with 2 rays a pixel, 1.6 cm with 64 (BENCHMARKS.md, "Multipath averaged over the pixels that
  see the same surface"). The interreflection changes smoothly along a surface, so averaging
  it there gives about 64 rays' answer; 1 ray a pixel over 9 × 9 pixels reads the same as 2 over
  7 × 7 (within 0.05 cm and one point of the bins within 5 cm) at a sixth less of a frame's time.
- LEDs: 4 on a ring of 3.5 cm around the lens (the ring sampled at four points: each LED
  costs a set of light paths per surface point): the SR4000's LED array surrounds its lens
  within a few centimetres of the optical centre (from the camera's product photographs, not
  measured); profile cos of the angle from the axis (a Lambertian LED, the textbook emission
  pattern of a bare LED: 82 % at 34.5°, the wide lens's half field of view), and nothing beyond
  40° (the LEDs' optics match the illumination to the lens's field of view, 5° to spare; the
  light that leaves beyond the mirrors lights the ceiling directly and from there the walls:
  corridor1's matte bins within 5 cm with multipath alone, 8 frames: 88.6 % at 35°, 85.8 % at
  40°, 83.7 % at 50°). A narrower profile,
  cos^3.6 (half power at 34.5°), was tried: it dims the mirror view's edges by up to half and
  empties a third of the office's matte-wall bins (amplitude below the scan's threshold), more
  than the camera's designers would accept for their own field of view.
- integration_time = 5 ms per sample (the SR4000 allows 0.3–25.8 ms; 4 × 5 ms fits its 10 Hz
  at a 20 ms acquisition): the four samples are taken one after another, sample k at
  k·integration_time after the frame's time, each at the robot's pose then
  (`omnitof.sim.sequence`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from functools import lru_cache
from typing import Any

import numpy as np
import scipy.constants

from omnitof.errors import ConfigError

SPEED_OF_LIGHT: float = scipy.constants.c
# Most LEDs a ring may have: every light path is worked out per LED (a real ring holds a few dozen; 4000
# took the multipath compensation's set-up past half a minute).
MAX_LEDS = 64


# The effects a user switches on and off (`omnitof simulate --tof-errors`, `omnitof demo`).
SWITCHES = ("wiggling", "amplitude_offset", "fixed_pattern", "motion", "multipath", "illumination")
# What `omnitof simulate` and `omnitof demo` simulate unless told otherwise: every effect but
# multipath. With multipath on (`--tof-errors all`) the walls read long, by up to decimetres where
# they are seen at grazing angles; the scan extraction's multipath compensation
# (omnitof.scan.multipath, on for such a camera) takes most of it out, but the demo with it does
# not yet end corridor1 within 5 cm in every seed of 3 (1.5, 5.7, 4.3 cm; BENCHMARKS.md, "The
# demo with every effect, re-run"), so the default realism leaves it out.
DEFAULT_SWITCHES = ("wiggling", "amplitude_offset", "fixed_pattern", "motion", "illumination")


def led_ring(count: int, radius: float) -> np.ndarray:
    """(count, 3) LEDs evenly on a ring of `radius` metres around the lens, in the lens plane
    (camera frame), the first on the +x axis."""
    angle = 2.0 * math.pi * np.arange(count) / count
    return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(count)])


class ToFErrorsError(ConfigError, ValueError):
    """A bad systematic-error setting; the message names the field."""


@dataclass(frozen=True)
class ToFErrors:
    """Which systematic errors the simulated camera makes, and how large (module docstring).

    Attributes:
        wiggling: odd harmonics h3, h5 of the correlation function (relative to the fundamental).
        amplitude_offset: distance offset amplitude_offset_m·ln(amplitude_reference/A), metres.
        fixed_pattern: a per-pixel offset, normal with fixed_pattern_std metres, drawn from
            fixed_pattern_seed (the same pattern for every frame of a camera).
        motion: the four samples taken one after another, integration_time seconds apart,
            each rendered at the robot's pose at its own time (with multipath, all four with
            the same secondary rays, so that they differ by the motion alone).
        multipath: one diffuse interreflection, multipath_rays secondary rays per pixel
            (rust/src/light.rs), averaged over the pixels within multipath_window rows and
            columns that see the same surface (0: each pixel alone; rust/src/render.rs
            `smooth_row`, `smoothed_column`).
        illumination: the light from led_count LEDs on a ring of led_radius metres around
            the lens (in the lens plane, the first at +x of the camera frame), each emitting
            cos^led_profile_exponent of the angle from the optical axis up to
            led_half_angle_deg and nothing beyond; without it, a
            point source at the lens centre whose light follows the view path exactly.
    """

    wiggling: bool = False
    harmonic3: float = 0.035
    harmonic5: float = 0.014
    amplitude_offset: bool = False
    amplitude_offset_m: float = 0.01
    amplitude_reference: float = 1000.0
    fixed_pattern: bool = False
    fixed_pattern_std: float = 0.01
    fixed_pattern_seed: int = 0
    motion: bool = False
    integration_time: float = 0.005
    multipath: bool = False
    multipath_rays: int = 1
    multipath_window: int = 4
    illumination: bool = False
    led_count: int = 4
    led_radius: float = 0.035
    led_profile_exponent: float = 1.0
    led_half_angle_deg: float = 40.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type == "bool" or isinstance(f.default, bool):
                if not isinstance(value, (bool, np.bool_)):
                    raise ToFErrorsError(f"errors.{f.name} must be true or false, got {value!r}")
                continue
            if f.name in ("fixed_pattern_seed", "multipath_rays", "multipath_window", "led_count"):
                least = 1 if f.name == "led_count" else 0
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                    raise ToFErrorsError(f"errors.{f.name} must be a whole number >= {least}, got {value!r}")
                if f.name == "led_count" and value > MAX_LEDS:
                    raise ToFErrorsError(f"errors.led_count must be at most {MAX_LEDS}, got {value!r}")
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise ToFErrorsError(f"errors.{f.name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ToFErrorsError(f"errors.{f.name} must be finite, got {value!r}")
        for name in ("harmonic3", "harmonic5"):
            if not 0.0 <= abs(getattr(self, name)) < 0.3:
                raise ToFErrorsError(f"errors.{name} must lie in (−0.3, 0.3), got {getattr(self, name)!r}")
        for name in ("amplitude_reference", "integration_time"):
            if not getattr(self, name) > 0.0:
                raise ToFErrorsError(f"errors.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0.0 < self.led_half_angle_deg <= 180.0:
            raise ToFErrorsError(f"errors.led_half_angle_deg must lie in (0, 180], got {self.led_half_angle_deg!r}")
        if not 0.0 <= self.led_radius < 0.5:
            raise ToFErrorsError(f"errors.led_radius must lie in [0, 0.5) metres, got {self.led_radius!r}")
        if not 0.0 < self.led_half_angle_deg <= 180.0:
            raise ToFErrorsError(f"errors.led_half_angle_deg must lie in (0, 180], got {self.led_half_angle_deg!r}")
        if self.led_profile_exponent < 0.0:
            raise ToFErrorsError(f"errors.led_profile_exponent must be >= 0, got {self.led_profile_exponent!r}")
        if self.fixed_pattern_std < 0.0:
            raise ToFErrorsError(f"errors.fixed_pattern_std must be >= 0, got {self.fixed_pattern_std!r}")

    @classmethod
    def realistic(cls, **overrides: Any) -> ToFErrors:
        """Every effect on, with the literature's figures (module docstring)."""
        on = {name: True for name in SWITCHES}
        return cls(**{**on, **overrides})

    @classmethod
    def from_dict(cls, data: Any) -> ToFErrors:
        """From the YAML form (`dataclasses.asdict`); ToFErrorsError naming an unknown field."""
        if isinstance(data, ToFErrors):
            return data
        if not isinstance(data, Mapping):
            raise ToFErrorsError(f"errors: expected a mapping of ToFErrors fields, got {data!r}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ToFErrorsError(f"errors: unknown field(s) {unknown}; known: {sorted(known)}")
        return cls(**data)

    def only(self, *names: str) -> ToFErrors:
        """These settings with only the named switches on (for the error budget)."""
        for n in names:
            if n not in SWITCHES:
                raise ToFErrorsError(f"no ToF error {n!r}; the switches: {', '.join(SWITCHES)}")
        return replace(self, **{s: s in names for s in SWITCHES})

    @classmethod
    def simulation_default(cls) -> ToFErrors:
        """What `omnitof simulate` and `omnitof demo` simulate by default (DEFAULT_SWITCHES)."""
        return cls().only(*DEFAULT_SWITCHES)

    @classmethod
    def parse(cls, text: str) -> ToFErrors:
        """The command line's form: "default" (DEFAULT_SWITCHES), "all", "none", or switches
        joined by commas ("wiggling,motion"), each with the literature's figures."""
        text = text.strip()
        if text == "default":
            return cls.simulation_default()
        if text == "all":
            return cls.realistic()
        if text in ("none", ""):
            return cls()
        return cls().only(*(name.strip() for name in text.split(",")))

    @property
    def switched_on(self) -> tuple[str, ...]:
        """The names of the switches that are on."""
        return tuple(s for s in SWITCHES if getattr(self, s))

    def led_positions(self) -> np.ndarray:
        """(led_count, 3) the LEDs in the camera frame (metres): a ring in the lens plane."""
        return led_ring(self.led_count, self.led_radius)

    @property
    def offsets_on(self) -> bool:
        return self.amplitude_offset or self.fixed_pattern


def wiggling_error(distance: np.ndarray | float, f_mod: float, harmonic3: float, harmonic5: float) -> np.ndarray:
    """Decoded minus true distance (m) of the correlation's odd harmonics, exact (docstring):
    (R/2π)·arg(1 + h3·e^{−i4Φ} + h5·e^{i4Φ}), Φ = 2π·d/R, R = c/(2·f_mod)."""
    period = SPEED_OF_LIGHT / (2.0 * f_mod)
    four_phi = 4.0 * (2.0 * math.pi) * np.asarray(distance, dtype=np.float64) / period
    z = 1.0 + harmonic3 * np.exp(-1j * four_phi) + harmonic5 * np.exp(1j * four_phi)
    return np.angle(z) * (period / (2.0 * math.pi))


def amplitude_offset(amplitude: np.ndarray | float, errors: ToFErrors) -> np.ndarray:
    """δ_amp(A) in metres (0 where the switch is off)."""
    a = np.maximum(np.asarray(amplitude, dtype=np.float64), 1.0)
    if not errors.amplitude_offset:
        return np.zeros_like(a)
    return errors.amplitude_offset_m * np.log(errors.amplitude_reference / a)


def fixed_pattern(shape: tuple[int, ...], errors: ToFErrors) -> np.ndarray:
    """δ_fpn (metres) of every pixel of an image of `shape` (zeros where the switch is off)."""
    if not errors.fixed_pattern or errors.fixed_pattern_std == 0.0:
        return np.zeros(shape)
    return _pattern(tuple(int(s) for s in shape), int(errors.fixed_pattern_seed)) * errors.fixed_pattern_std


@lru_cache(maxsize=4)
def _pattern(shape: tuple[int, ...], seed: int) -> np.ndarray:
    out = np.random.default_rng([seed, 0xF1]).standard_normal(shape)
    out.setflags(write=False)
    return out


def apply_offsets(phasor: np.ndarray, errors: ToFErrors, f_mod: float) -> np.ndarray:
    """The phasor with its phase moved by the offsets δ_fpn + δ_amp(|p|) (per pixel; the last
    two axes are the image)."""
    p = np.asarray(phasor, dtype=np.complex128)
    if not errors.offsets_on:
        return p
    delta = amplitude_offset(np.abs(p), errors) + fixed_pattern(p.shape[-2:], errors)
    return p * np.exp(1j * (4.0 * math.pi * f_mod / SPEED_OF_LIGHT) * delta)


def correlation_samples(phasor: np.ndarray, offset: np.ndarray, errors: ToFErrors,
                        per_sample: bool = False) -> np.ndarray:
    """(4, ...) expected samples μ_k = B + A·c(Φ + k·π/2) with c the correlation function
    (cos θ + h3·cos 3θ + h5·cos 5θ when wiggling is on, cos θ otherwise), A·e^{iΦ} = phasor.

    `per_sample`: phasor and offset carry a leading axis of 4, sample k's own (motion during the
    frame); otherwise one phasor serves all four samples.
    """
    p = np.asarray(phasor, dtype=np.complex128)
    b = np.asarray(offset, dtype=np.float64)
    quarter = np.array([1, 1j, -1, -1j])  # i^k
    shape = (4,) + (1,) * (p.ndim - (1 if per_sample else 0))
    if not per_sample:
        p = p[None]
    turned = p * quarter.reshape(shape)  # A·e^{i(Φ + kπ/2)}
    mu = b + turned.real
    if errors.wiggling:
        magnitude = np.abs(turned)
        unit = np.divide(turned, magnitude, out=np.zeros_like(turned), where=magnitude > 0)
        mu = mu + magnitude * (errors.harmonic3 * (unit**3).real + errors.harmonic5 * (unit**5).real)
    return mu
