"""The grazing-incidence estimate of the scan extraction's bins (omnitof.scan.grazing), against
the exact incidence of straight walls."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from omnitof.scan.grazing import drop_grazing, incidence_angles

STEP = math.radians(1.0)
BEARINGS = np.arange(360) * STEP


def wall(distance: float, normal: float) -> np.ndarray:
    """Ranges of 360 one-degree bins to an infinite straight wall `distance` m away whose
    normal (from the sensor towards it) points at bearing `normal`; +inf where it is behind."""
    c = np.cos(BEARINGS - normal)
    with np.errstate(divide="ignore"):
        return np.where(c > 1e-9, distance / np.where(c > 1e-9, c, 1.0), np.inf)


@settings(max_examples=50, deadline=None)
@given(distance=st.floats(0.5, 5.0), normal=st.floats(0.0, 2 * math.pi))
def test_a_straight_walls_incidence_is_found(distance, normal):
    r = wall(distance, normal)
    exact = np.abs((BEARINGS - normal + math.pi) % (2 * math.pi) - math.pi)
    found = incidence_angles(r, STEP)
    # Up to 80°, where the difference over one bin is still close to the derivative: the smaller
    # one-sided slope is the derivative half a bin towards the normal, so it errs by < 1°.
    judged = exact < math.radians(80)
    assert np.all(np.isfinite(found[judged]))
    assert np.abs(found[judged] - exact[judged]).max() < math.radians(1.0)


def test_a_depth_edge_is_not_taken_for_a_grazing_wall():
    # Two walls facing the sensor, 2 m and 4 m away, meeting at bearing 10°: the bins on either
    # side of the jump see their own wall nearly head-on.
    r = wall(2.0, 0.0)
    r[10:40] = wall(4.0, math.radians(25.0))[10:40]
    r[40:320] = np.inf
    found = np.degrees(incidence_angles(r, STEP))
    assert found[9] < 10.5 and abs(found[10] - 15.0) < 1.0
    assert np.isnan(found[45])  # no reading
    lone = np.full(360, np.inf)
    lone[100] = 3.0
    assert np.isnan(incidence_angles(lone, STEP)[100])  # no neighbour: nothing to judge


def test_grazing_bins_are_dropped_and_the_rest_kept():
    r = wall(1.0, math.radians(90.0)).astype(np.float32)  # a corridor wall on the left
    out = drop_grazing(r, STEP, math.radians(70.0))
    off_normal = np.abs(np.degrees(BEARINGS) - 90.0)
    kept = np.isfinite(out)
    assert kept[np.abs(off_normal) <= 68].all()
    assert not kept[(np.abs(off_normal) >= 72) & np.isfinite(r)].any()
    assert np.array_equal(out[kept], r[kept]) and out.dtype == np.float32
    assert np.array_equal(drop_grazing(r, STEP, math.pi / 2), r)  # off
    many = np.stack([r, np.roll(r, 90)])
    assert np.array_equal(drop_grazing(many, STEP, math.radians(70.0))[1], np.roll(out, 90))


def test_a_pole_in_front_of_a_wall_is_kept():
    # A pole one bin wide at 1.5 m before a wall 3 m away, and a one-bin gap in the wall that
    # sees 6 m through it: each bin stands alone, too narrow to judge, and keeps its reading;
    # its neighbours see the wall head-on and keep theirs.
    r = wall(3.0, 0.0).astype(np.float32)
    r[5], r[355] = 1.5, 6.0
    out = drop_grazing(r, STEP, math.radians(60.0))
    assert out[5] == np.float32(1.5) and out[355] == np.float32(6.0)
    assert np.array_equal(out[[4, 6, 354, 356]], r[[4, 6, 354, 356]])
    # Along a grazing wall each bin jumps far from its neighbours too, but nearer on one side and
    # further on the other: it is dropped.
    steep = wall(1.0, math.radians(90.0)).astype(np.float32)
    assert not np.isfinite(drop_grazing(steep, STEP, math.radians(60.0))[5])
