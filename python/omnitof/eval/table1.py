"""Distances between opposite walls measured in an occupancy map (the paper's Table I, Fig. 12).

At each landmark (a place where the true wall-to-wall distance is known, `World.landmarks`) a
patch is cut across the corridor from the map: the occupancy probability of the cells that hold
evidence of an obstacle (log-odds above 0) is sampled along `n_lines` parallel lines through the
patch, in the landmark's direction, spread over `patch_width` across it, and averaged into one
profile; free and unknown cells read 0. (Free cells as their probability made shoulders of
0.3–0.45 beside the walls, where grazing beams end now and then, and the fit took them for wall:
in the simulated corridors #2 read 10 cm short in every seed and #4 25–45 cm short;
BENCHMARKS.md, "Table I on the cells that hold an obstacle".) Two Gaussian bumps on a constant,

    p(s) = c + a1·exp(−(s − m1)²/(2σ1²)) + a2·exp(−(s − m2)²/(2σ2²)),

are fitted to the profile (scipy.optimize.curve_fit), started from the most prominent peak on
each side of the landmark, and the measured distance is the peak-to-peak |m2 − m1|. A patch
without a peak on each side, or a fit that fails, gives NaN and a reason, never an exception.

Frames: landmarks live in the world frame; a SLAM map lives in its own frame (it starts at the
odometry's first pose). `world_T_map` is the map frame's pose (x, y, θ) in the world frame;
`world_T_map_from_start` gives it from the first true and the first map pose. Distances are in
metres inside and in cm only in `format_table1`, which mirrors the paper's table.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.optimize import curve_fit
from scipy.signal import find_peaks

from omnitof.geometry import compose, inverse
from omnitof.sim.worlds import Landmark
from omnitof.types import OccupancyMap

# The paper's Table I ("Measured distances of two test sequences compared to groundtruth data of
# known object distances within the environment. Measurements are given in cm."): per location,
# the ground truth and, per sequence, (measured, offset), in cm, as printed (the printed offsets
# are |measured − ground truth| up to the paper's own rounding: CORRIDOR 2 #1 prints 6.31 for
# 217 − 210.62 = 6.38).
PAPER_TABLE1: dict[str, dict[str, tuple[float, ...]]] = {
    "ground_truth": {"1": (217.0,), "2": (134.0,), "3": (306.0,), "4": (1213.0,), "5": (133.0,)},
    "corridor1": {
        "1": (209.69, 7.31), "2": (134.86, 0.86), "3": (388.00, 82.00),
        "4": (1493.25, 280.25), "5": (133.28, 0.28),
    },
    "corridor2": {
        "1": (210.62, 6.31), "2": (137.88, 3.88), "3": (409.58, 103.57),
        "4": (1522.83, 309.83), "5": (132.25, 0.75),
    },
}


@dataclass(frozen=True)
class WallFit:
    """A two-Gaussian fit to an occupancy profile.

    distance: |m2 − m1| in metres, NaN if the fit failed. centres: (2,) peak positions m1 < m2
    along the line (m from the landmark); widths: (2,) σ1, σ2; amplitudes: (2,) a1, a2;
    baseline: c. reason: "" on success, else why the distance is NaN.
    """

    distance: float
    centres: np.ndarray
    widths: np.ndarray
    amplitudes: np.ndarray
    baseline: float
    reason: str = ""

    @property
    def ok(self) -> bool:
        return not self.reason


@dataclass(frozen=True)
class LandmarkMeasurement:
    """One row of Table I: a landmark's true and measured wall-to-wall distance (metres).

    offset: measured − true (signed; the paper prints its absolute value). s, profile: the
    averaged occupancy profile (positions along the line in m from the landmark, values).
    """

    name: str
    true_distance: float
    measured: float
    offset: float
    fit: WallFit
    s: np.ndarray = field(repr=False)
    profile: np.ndarray = field(repr=False)

    @property
    def reason(self) -> str:
        return self.fit.reason


def _gaussians(s: np.ndarray, c: float, a1: float, m1: float, w1: float, a2: float, m2: float, w2: float) -> np.ndarray:
    return c + a1 * np.exp(-0.5 * ((s - m1) / w1) ** 2) + a2 * np.exp(-0.5 * ((s - m2) / w2) ** 2)


def _failed(reason: str) -> WallFit:
    nan2 = np.full(2, np.nan)
    return WallFit(math.nan, nan2, nan2.copy(), nan2.copy(), math.nan, reason)


def fit_two_gaussians(
    s: np.ndarray,
    profile: np.ndarray,
    *,
    split: float = 0.0,
    min_prominence: float = 0.1,
    max_width: float = 1.0,
) -> WallFit:
    """Fit two Gaussian bumps plus a constant to a profile and return their peak-to-peak distance.

    Args:
        s: (K,) increasing positions, metres. profile: (K,) values (occupancy probability); NaN
            samples are left out.
        split: the start values are the most prominent peak with s < split and the most
            prominent with s >= split (the landmark lies between the walls, at s = 0).
        min_prominence: peaks less prominent than this (in profile units) do not count.
        max_width: upper bound of σ, metres.

    Returns:
        A WallFit; distance NaN with a reason when there is no peak on one side or the fit
        fails (never raises for a bad profile).
    """
    s = np.asarray(s, dtype=np.float64)
    p = np.asarray(profile, dtype=np.float64)
    if s.shape != p.shape or s.ndim != 1:
        raise ValueError(f"s {s.shape} and profile {p.shape} must be one-dimensional and match")
    ok = np.isfinite(p) & np.isfinite(s)
    s, p = s[ok], p[ok]
    if len(s) < 7:
        return _failed(f"only {len(s)} valid samples in the profile")
    step = float(np.median(np.diff(s)))
    peaks, props = find_peaks(np.pad(p, 1, constant_values=p.min()), prominence=min_prominence)
    peaks = peaks - 1
    prominence = props["prominences"]
    left, right = peaks[s[peaks] < split], peaks[s[peaks] >= split]
    if len(left) == 0 or len(right) == 0:
        side = "either side" if len(left) == len(right) == 0 else ("the left" if len(left) == 0 else "the right")
        return _failed(f"no occupancy peak (prominence >= {min_prominence:g}) on {side} of the landmark")
    i1 = left[np.argmax(prominence[s[peaks] < split])]
    i2 = right[np.argmax(prominence[s[peaks] >= split])]
    base = float(np.median(p))
    w0 = max(2.0 * step, 0.05)
    start = [base, max(p[i1] - base, 1e-3), s[i1], w0, max(p[i2] - base, 1e-3), s[i2], w0]
    lower = [-1.0, 0.0, s[0], step / 4.0, 0.0, split, step / 4.0]
    upper = [2.0, 2.0, split, max_width, 2.0, s[-1], max_width]
    start = list(np.clip(start, np.array(lower) + 1e-9, np.array(upper) - 1e-9))
    try:
        params, _ = curve_fit(_gaussians, s, p, p0=start, bounds=(lower, upper), maxfev=5000)
    except (RuntimeError, ValueError) as err:
        return _failed(f"two-Gaussian fit did not converge: {err}")
    c, a1, m1, w1, a2, m2, w2 = (float(v) for v in params)
    if not np.all(np.isfinite(params)):
        return _failed("two-Gaussian fit gave non-finite parameters")
    return WallFit(abs(m2 - m1), np.array([m1, m2]), np.array([w1, w2]), np.array([a1, a2]), c)


# The most points one profile samples: far more than any patch of a map holds cells.
MAX_PROFILE_SAMPLES = 1e7


def sample_profile(
    occ: OccupancyMap,
    centre: np.ndarray,
    direction: float,
    *,
    half_length: float,
    patch_width: float = 0.5,
    n_lines: int = 5,
    step: float | None = None,
    unknown: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The occupancy profile across a patch: (s (K,), mean probability (K,)).

    Samples the probability of the cells with evidence of an obstacle (log-odds > 0; bilinear
    between cell centres) along n_lines lines parallel to `direction` (radians, map frame)
    through `centre` (2,), from −half_length to +half_length, spread evenly over `patch_width`
    across, and averages them. Free and unknown cells (and outside the grid) count as `unknown`
    (default 0: no evidence of a wall), not as their probability or 0.5, so that neither free
    cells beside a wall nor unexplored space beyond it raise the profile. step defaults to half
    a cell.
    """
    res = float(occ.resolution)
    step = res / 2.0 if step is None else float(step)
    if not (0 < step < math.inf and 0 < half_length < math.inf and n_lines >= 1 and patch_width >= 0):
        raise ValueError("step, half_length must be finite and > 0, n_lines >= 1 and patch_width >= 0")
    samples = (2.0 * half_length / step + 1.0) * n_lines
    if not samples <= MAX_PROFILE_SAMPLES:  # rather than numpy's MemoryError, or a hang
        raise ValueError(
            f"a profile of {2 * half_length:g} m every {step:g} m on {n_lines} lines is "
            f"{samples:.3g} samples, more than {MAX_PROFILE_SAMPLES:.0e}: give a larger step"
        )
    if not (np.isfinite(np.asarray(centre, dtype=np.float64)).all() and math.isfinite(direction)
            and math.isfinite(patch_width)):
        raise ValueError("the profile's centre, direction and patch_width must be finite")
    obstacle = np.asarray(occ.known, dtype=bool) & (np.asarray(occ.log_odds) > 0)
    values = np.where(obstacle, occ.probability, unknown)
    s = np.arange(-half_length, half_length + step / 2, step)
    along = np.array([math.cos(direction), math.sin(direction)])
    across = np.array([-along[1], along[0]])
    offsets = np.linspace(-patch_width / 2, patch_width / 2, n_lines) if n_lines > 1 else np.zeros(1)
    pts = np.asarray(centre, dtype=np.float64)[None, None, :] + s[None, :, None] * along + offsets[:, None, None] * across
    # Cell (row, col) has its centre at origin + (col + 0.5, row + 0.5)·res; row 0 = lowest y.
    cols = (pts[..., 0] - occ.origin[0]) / res - 0.5
    rows = (pts[..., 1] - occ.origin[1]) / res - 0.5
    sampled = map_coordinates(values, [rows.ravel(), cols.ravel()], order=1, mode="constant", cval=unknown)
    return s, sampled.reshape(rows.shape).mean(axis=0)


def measure_landmark(
    occ: OccupancyMap,
    landmark: Landmark,
    *,
    world_T_map: np.ndarray | None = None,
    margin: float = 1.0,
    patch_width: float = 0.5,
    n_lines: int = 5,
    min_prominence: float = 0.1,
) -> LandmarkMeasurement:
    """Measure one landmark's wall-to-wall distance in the map (see the module docstring).

    The profile runs `margin` metres past each true wall (half the true distance from the
    landmark plus the margin), so a map up to about `margin` off still shows both walls.
    """
    mark = world_to_map([landmark], world_T_map)[0] if world_T_map is not None else landmark
    s, profile = sample_profile(
        occ, mark.position, mark.direction, half_length=mark.distance / 2.0 + margin,
        patch_width=patch_width, n_lines=n_lines,
    )
    fit = fit_two_gaussians(s, profile, min_prominence=min_prominence)
    return LandmarkMeasurement(
        mark.name, float(mark.distance), fit.distance, fit.distance - float(mark.distance), fit, s, profile
    )


def table1(
    occ: OccupancyMap,
    landmarks: Sequence[Landmark],
    *,
    world_T_map: np.ndarray | None = None,
    **options: float,
) -> list[LandmarkMeasurement]:
    """`measure_landmark` for each landmark (options: margin, patch_width, n_lines,
    min_prominence)."""
    return [measure_landmark(occ, m, world_T_map=world_T_map, **options) for m in landmarks]  # type: ignore[arg-type]


def world_T_map_from_start(true_start: np.ndarray, map_start: np.ndarray) -> np.ndarray:
    """The map frame's pose in the world (3,) when the robot's first pose is `true_start` in the
    world and `map_start` in the map (SLAM starts at the odometry's first pose):
    world_T_map = true_start ⊕ ⊖map_start."""
    return compose(np.asarray(true_start, float), inverse(np.asarray(map_start, float)))


def world_to_map(landmarks: Sequence[Landmark], world_T_map: np.ndarray | None) -> list[Landmark]:
    """Landmarks moved from the world frame into the map frame: position map_T_world·p,
    direction minus the map's rotation. world_T_map: (3,) pose (x, y, θ) or a 3×3 homogeneous
    2D transform; None leaves the landmarks as they are."""
    if world_T_map is None:
        return list(landmarks)
    t = np.asarray(world_T_map, dtype=np.float64)
    if t.shape == (3, 3):
        t = np.array([t[0, 2], t[1, 2], math.atan2(t[1, 0], t[0, 0])])
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"world_T_map must be a pose (3,) or a 3×3 transform, got shape {np.shape(world_T_map)}")
    map_T_world = inverse(t)
    out = []
    for mark in landmarks:
        p = compose(map_T_world, np.array([mark.position[0], mark.position[1], mark.direction]))
        out.append(replace(mark, position=p[:2].copy(), direction=float(p[2])))
    return out


def format_table1(
    results: Mapping[str, Sequence[LandmarkMeasurement]],
    *,
    paper: bool = True,
) -> str:
    """Table I as text, in cm: one row per location, the ground truth, then for each sequence
    our measured distance and |offset| and, with `paper`, the paper's measured and offset beside
    them (PAPER_TABLE1; for sequences it has, at locations it has). Failed fits show "n/a" and
    their reasons are listed below the table."""
    names: list[str] = []
    truth: dict[str, float] = {}
    for rows in results.values():
        for measured in rows:
            if measured.name not in truth:
                names.append(measured.name)
                truth[measured.name] = measured.true_distance
    header = ["location", "ground truth"]
    for seq in results:
        label = re.sub(r"(\D)(\d+)$", r"\1 \2", seq).upper()  # corridor1 → CORRIDOR 1
        header += [f"{label} meas", f"{label} offset"]
        if paper and seq in PAPER_TABLE1:
            header += ["paper meas", "paper offset"]
    lines = [header]
    notes = []

    def cm(v: float) -> str:
        return "n/a" if not math.isfinite(v) else f"{100.0 * v:.2f}"

    for name in names:
        line = [f"#{name}", f"{100.0 * truth[name]:.0f}"]
        for seq, rows in results.items():
            row = next((r for r in rows if r.name == name), None)
            if row is None:
                line += ["", ""]
            else:
                line += [cm(row.measured), cm(abs(row.offset))]
                if row.reason:
                    notes.append(f"{seq} #{name}: {row.reason}")
            if paper and seq in PAPER_TABLE1:
                ref = PAPER_TABLE1[seq].get(name)
                line += [f"{ref[0]:.2f}", f"{ref[1]:.2f}"] if ref else ["", ""]
        lines.append(line)
    widths = [max(len(r[i]) for r in lines) for i in range(len(header))]
    text = "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in lines)
    text += "\nDistances in cm; offset = |measured − ground truth|; paper: Table I of the ICARCV 2010 paper."
    if notes:
        text += "\n" + "\n".join(notes)
    return text
