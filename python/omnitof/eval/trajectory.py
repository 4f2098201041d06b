"""Trajectory error against ground truth.

Both trajectories start from the same, known pose (the simulator gives the filter the true start
pose), so no alignment is estimated: the error at each timestamp is the pose difference itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnitof.geometry import wrap_angle
from omnitof.types import first_non_finite


@dataclass(frozen=True)
class TrajectoryError:
    """Absolute trajectory error (ATE) statistics; metres and degrees."""

    rmse: float
    mean: float
    max: float
    final: float
    heading_mean_deg: float
    heading_final_deg: float

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


def absolute_trajectory_error(estimate: np.ndarray, truth: np.ndarray) -> TrajectoryError:
    """ATE of (N, 3) poses against (N, 3) true poses taken at the same timestamps."""
    estimate = np.asarray(estimate, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if estimate.shape != truth.shape:
        raise ValueError(f"trajectories differ in shape: {estimate.shape} vs {truth.shape}")
    if estimate.ndim != 2 or estimate.shape[1] != 3 or len(estimate) == 0:
        raise ValueError(f"trajectories must be (N >= 1, 3) poses (x, y, theta), got shape {estimate.shape}")
    for name, poses in (("estimate", estimate), ("truth", truth)):
        i = first_non_finite(poses)
        if i is not None:
            raise ValueError(f"the {name}'s pose {i} is not finite: {poses[i]}")
    d = np.hypot(estimate[:, 0] - truth[:, 0], estimate[:, 1] - truth[:, 1])
    h = np.degrees(np.abs(wrap_angle(estimate[:, 2] - truth[:, 2])))
    return TrajectoryError(
        rmse=float(np.sqrt(np.mean(d**2))),
        mean=float(d.mean()),
        max=float(d.max()),
        final=float(d[-1]),
        heading_mean_deg=float(h.mean()),
        heading_final_deg=float(h[-1]),
    )
