"""Bins of surfaces seen at grazing incidence, estimated from the neighbouring bins, and their
removal: the last step of the scan extraction (`ScanSettings.max_incidence_deg`).

Why: a ToF pixel that sees a wall at a grazing angle gets little direct light back (the
return falls with the cosine of the incidence), while the same wall takes light from the nearer,
brighter walls, floor and ceiling that face the LEDs. That interreflected light travels
further, so the pixel's phase, and its distance, come out long: multipath, which no per-pixel
test sees, as the error is smooth along the wall. In the simulated corridors with multipath on,
the bins of matte walls seen at less than 45° from their normal are 99 % within 5 cm, those at
70–75° 62 %, those at 75–80° 20 % (BENCHMARKS.md, "Multipath at grazing incidence").

How: for a flat surface, the range r along the bearing θ grows as dr/dθ = r·tan(α), with α the
angle between the ray and the surface's normal. Each bin's α is estimated from the one-sided
differences to its two neighbouring bins, taking the smaller slope: at a depth edge the bin
belongs to one surface, whose continuation gives the small slope, while the jump to the other
surface gives a huge one. A bin with no reading beside it keeps its reading (nothing to judge), and so does a bin that
stands alone, both neighbours jumping the same way by more than LONE_BIN_JUMP of its range: a
pole in front of a wall, or a gap in it. Its surface is too narrow to judge, and a grazing wall
cannot look so: along it the range grows on one side and shrinks on the other.
The per-bin noise of a median range (about 1 cm) makes tan(α) uncertain by about 0.2 at 3 m,
small against tan(70°) = 2.7.
"""

from __future__ import annotations

import numpy as np

LONE_BIN_JUMP = 0.2  # share of the bin's range by which both neighbours jump for a lone bin


def incidence_angles(ranges: np.ndarray, step: float) -> np.ndarray:
    """Each bin's estimated incidence angle (radians; see the module notes).

    Args:
        ranges: (..., B) positive ranges of B bins spread evenly over the full circle, +inf
            where no reading (the last axis wraps around: bin B−1 neighbours bin 0).
        step: the bins' angular spacing (radians).

    Returns:
        (..., B) float64 in [0, π/2]; NaN where the bin has no reading, neither neighbour has,
        or the bin stands alone (see the module notes).
    """
    r = np.asarray(ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        rise_before = r - np.roll(r, 1, axis=-1)  # inf or NaN where a side has no reading
        rise_after = np.roll(r, -1, axis=-1) - r
    before, after = np.abs(rise_before), np.abs(rise_after)
    before[~np.isfinite(before)] = np.inf
    after[~np.isfinite(after)] = np.inf
    slope = np.minimum(before, after)
    with np.errstate(divide="ignore", invalid="ignore"):
        angle = np.arctan(slope / (step * r))
        lone = (rise_before * rise_after < 0) & (slope > LONE_BIN_JUMP * r)
    angle[~np.isfinite(r) | ~np.isfinite(slope) | lone] = np.nan
    return angle


def drop_grazing(ranges: np.ndarray, step: float, max_incidence: float) -> np.ndarray:
    """`ranges` (..., B) with +inf in the bins whose estimated incidence exceeds `max_incidence`
    (radians); a copy, float32 like the extraction's output. `max_incidence` ≥ π/2 drops none."""
    out = np.array(ranges, dtype=np.float32, copy=True)
    if max_incidence >= np.pi / 2:
        return out
    with np.errstate(invalid="ignore"):
        out[incidence_angles(out, step) > max_incidence] = np.inf
    return out
