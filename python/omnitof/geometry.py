"""SE(2) pose algebra on numpy arrays.

A pose is (x, y, theta): metres and radians, theta counter-clockwise from +x. Arrays of poses have
shape (N, 3). `compose(a_T_b, b_T_c)` gives a_T_c; every function broadcasts over leading axes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from omnitof.types import Trajectory


def wrap_angle(theta: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(theta) + np.pi) % (2.0 * np.pi) - np.pi


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a ⊕ b: the pose b, given in the frame of a, expressed in a's parent frame."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    th = wrap_angle(a[..., 2] + b[..., 2])
    return np.stack([x, y, th], axis=-1)


def inverse(a: np.ndarray) -> np.ndarray:
    """⊖a: the inverse transform, so that compose(inverse(a), a) is the identity."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """⊖a ⊕ b: the pose b seen from the frame of a."""
    return compose(inverse(a), b)


def anchor_offset(xy: np.ndarray, cell: float, reach_cells: float, unit_cells: int) -> np.ndarray:
    """(x, y) metres by which to move points (N, 2) that lie far from their origin before they
    go into a grid of `cell` metres: zero where every point lies within `reach_cells` cells of
    the origin, else the first point rounded to whole units of `unit_cells` cells, so that the
    moved grid's cells keep their place in the world (omnitof.slam.anchor tells why)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0 or not np.max(np.abs(xy)) / cell > reach_cells:
        return np.zeros(2)
    unit = unit_cells * cell
    return np.round(xy[0] / unit) * unit


# The largest heading (rad, unwrapped) a writer turns into a quaternion: at 1e6 rad a float64
# still holds it to 1e-10 rad; at 1e300 its quaternion is rounding error.
MAX_HEADING = 1e6


def check_headings(poses: np.ndarray, what: str) -> None:
    """ValueError naming the first of `poses` (N, 3) whose heading lies beyond MAX_HEADING, for
    writers that turn headings into quaternions (TUM files, bags)."""
    turned = np.flatnonzero(np.abs(poses[:, 2]) > MAX_HEADING)
    if turned.size:
        i = int(turned[0])
        raise ValueError(f"{what} pose {i}: heading {poses[i, 2]:g} rad is beyond ±{MAX_HEADING:g} rad")


def yaw_to_quaternion(theta: np.ndarray) -> np.ndarray:
    """Unit quaternions (qx, qy, qz, qw) of rotations by theta about +z."""
    theta = np.asarray(theta, dtype=np.float64)
    zeros = np.zeros_like(theta)
    return np.stack([zeros, zeros, np.sin(theta / 2.0), np.cos(theta / 2.0)], axis=-1)


def quaternion_to_yaw(q: np.ndarray) -> np.ndarray:
    """Yaw (rotation about +z) of quaternions (qx, qy, qz, qw); roll and pitch are ignored.

    The quaternions need not be unit: the formula is invariant to their length (for a unit
    quaternion qw² + qx² − qy² − qz² = 1 − 2(qy² + qz²)), and each is first divided by its
    largest component, so that files rounded to a few decimals read right and huge
    components do not overflow."""
    q = np.asarray(q, dtype=np.float64)
    scale = np.max(np.abs(q), axis=-1, keepdims=True)
    q = q / np.where(scale > 0, scale, 1.0)
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (qw * qz + qx * qy), qw * qw + qx * qx - qy * qy - qz * qz)


def interpolate_poses(trajectory: Trajectory, timestamps: np.ndarray | float) -> np.ndarray:
    """Poses (N, 3) of a trajectory at `timestamps`: linear in x, y, along the shorter arc in θ.

    The trajectory's timestamps must not decrease (equal ones are allowed). Rows at times
    outside [first, last] timestamp are NaN; a time equal to a trajectory timestamp gets that
    pose exactly (θ wrapped to [-π, π)).
    """
    t_query = np.atleast_1d(np.asarray(timestamps, dtype=np.float64))
    t, poses = trajectory.timestamps, trajectory.poses
    out = np.full((len(t_query), 3), np.nan)
    if len(t) == 0:
        return out
    if np.any(np.diff(t) < 0):
        raise ValueError("cannot interpolate a trajectory whose timestamps go backwards")
    inside = (t_query >= t[0]) & (t_query <= t[-1])
    if len(t) == 1:
        out[inside] = poses[0]
        out[inside, 2] = wrap_angle(poses[0, 2])
        return out
    tq = t_query[inside]
    i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
    t0, t1 = t[i], t[i + 1]
    span = t1 - t0
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(span > 0.0, (tq - t0) / np.where(span > 0.0, span, 1.0), 1.0)
    p0, p1 = poses[i], poses[i + 1]
    w_col = w[:, None]
    # (1 - w)·a + w·b gives a exactly at w = 0 and b exactly at w = 1.
    xy = (1.0 - w_col) * p0[:, :2] + w_col * p1[:, :2]
    theta = p0[:, 2] + w * wrap_angle(p1[:, 2] - p0[:, 2])
    theta = np.where(w == 1.0, p1[:, 2], theta)
    out[inside, :2] = xy
    out[inside, 2] = wrap_angle(theta)
    return out
