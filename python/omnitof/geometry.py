"""SE(2) pose algebra on numpy arrays.

A pose is (x, y, theta): metres and radians, theta counter-clockwise from +x. Arrays of poses have
shape (N, 3). `compose(a_T_b, b_T_c)` gives a_T_c; every function broadcasts over leading axes.
"""

from __future__ import annotations

import numpy as np


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


def yaw_to_quaternion(theta: np.ndarray) -> np.ndarray:
    """Unit quaternions (qx, qy, qz, qw) of rotations by theta about +z."""
    theta = np.asarray(theta, dtype=np.float64)
    zeros = np.zeros_like(theta)
    return np.stack([zeros, zeros, np.sin(theta / 2.0), np.cos(theta / 2.0)], axis=-1)


def quaternion_to_yaw(q: np.ndarray) -> np.ndarray:
    """Yaw (rotation about +z) of quaternions (qx, qy, qz, qw); roll and pitch are ignored."""
    q = np.asarray(q, dtype=np.float64)
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
