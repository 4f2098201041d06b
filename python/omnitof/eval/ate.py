"""Absolute trajectory error (ATE) of an estimated trajectory against a ground truth on the same
clock, after aligning the estimate's frame to the truth's.

A SLAM run's map frame is its own: a real robot's ground truth (motion capture, a total station,
a survey) lives in another frame, and the error of every pose is only meaningful once the
estimate is moved into it. This module does what the TUM RGB-D benchmark's ATE and evo's
`evo_ape -a` / `-as` do for planar poses (written here from the papers, not from their code):

1. **Pairing** (`pair_poses`): at most one estimate pose per truth pose, the nearest in time
   within `max_diff` seconds (`relations.match_times`, the relations metric's nearest-stamp rule),
   whichever of the two is recorded faster. Both trajectories are planar: a TUM file's z, roll
   and pitch are not read (`io.tum.read_tum`).
2. **Alignment** (`align`), fitted to the paired positions:
   - "none": the frames are the same (the simulator's runs, which start at the true pose);
   - "rigid": the rotation and translation minimising the sum of squared position errors;
   - "similarity": the same with a scale, the factor that brings the estimate's lengths to the
     truth's (0.909 for an estimate 1.1 times too long: a wheel-radius error that a loop
     closure cannot see, or a monocular scale).
   An estimate in a mirrored (left-handed) frame is not aligned by either: no rotation undoes a
   reflection.
   Closed form of Umeyama (IEEE PAMI 13(4), 1991), eqs. 38–42, in 2D. Written by hand: scipy's
   `Rotation.align_vectors` finds a 3D rotation only (no translation, no scale), and the
   libraries that do it all (evo) are GPL.
3. **Errors** of the aligned poses, `trajectory.absolute_trajectory_error`: position error
   (RMSE, mean, max, at the last pair) and heading error, the estimate's headings turned by the
   alignment's rotation.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import InputError, OmnitofWarning
from omnitof.eval.relations import match_times
from omnitof.eval.trajectory import TrajectoryError, absolute_trajectory_error
from omnitof.geometry import wrap_angle
from omnitof.types import Trajectory, first_non_finite

ALIGNMENTS = ("none", "rigid", "similarity")
# Where the truth moves more than this (metres) between the stamps of a pair, the pairing itself
# puts that much error in: warned of.
PAIRING_MOTION = 0.01
# Paired positions must spread more than this (metres, RMS about their centroid) to fix a
# rotation: a robot that stood still determines no frame.
MIN_SPREAD = 1e-6


@dataclass(frozen=True)
class Alignment:
    """truth ≈ scale · R(rotation) · estimate + translation (positions); headings + rotation."""

    rotation: float = 0.0  # rad
    translation: tuple[float, float] = (0.0, 0.0)  # m
    scale: float = 1.0

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """(N, 3) poses moved into the truth's frame."""
        poses = np.asarray(poses, dtype=np.float64)
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        x, y = poses[:, 0], poses[:, 1]
        return np.column_stack([
            self.scale * (c * x - s * y) + self.translation[0],
            self.scale * (s * x + c * y) + self.translation[1],
            wrap_angle(poses[:, 2] + self.rotation),
        ])


def fit_alignment(estimate: np.ndarray, truth: np.ndarray, *, scale: bool = False) -> Alignment:
    """The rigid (or, with `scale`, similarity) transform that moves the (N, 2+) positions of
    `estimate` closest to those of `truth` in the least-squares sense (Umeyama 1991, eqs. 38–42).

    Raises:
        ValueError: where the positions do not determine it (fewer than two distinct ones).
    """
    p = np.asarray(estimate, dtype=np.float64)[:, :2]
    q = np.asarray(truth, dtype=np.float64)[:, :2]
    mp, mq = p.mean(axis=0), q.mean(axis=0)
    a, b = p - mp, q - mq
    spread = float(np.mean(np.sum(a**2, axis=1)))  # σ²_p of eq. 36
    if not (math.sqrt(spread) > MIN_SPREAD and math.sqrt(float(np.mean(np.sum(b**2, axis=1)))) > MIN_SPREAD):
        raise ValueError("the paired positions are all at one place: they determine no rotation")
    cov = b.T @ a / len(p)  # Σ_qp of eq. 38
    u, d, vt = np.linalg.svd(cov)
    sign = np.diag([1.0, 1.0 if np.linalg.det(u) * np.linalg.det(vt) > 0 else -1.0])  # eq. 39: no reflection
    r = u @ sign @ vt  # eq. 40
    c = float(np.trace(np.diag(d) @ sign) / spread) if scale else 1.0  # eq. 42
    t = mq - c * r @ mp  # eq. 41
    return Alignment(rotation=math.atan2(r[1, 0], r[0, 0]), translation=(float(t[0]), float(t[1])), scale=c)


@dataclass(frozen=True)
class AteResult:
    """The ATE of one estimate: how many poses were paired, the alignment and the errors
    (metres, degrees) of the aligned poses."""

    align: str
    n_estimate: int
    n_truth: int
    n_paired: int
    max_diff: float
    alignment: Alignment
    error: TrajectoryError
    median: float  # of the position errors, m

    def format(self) -> str:
        a, e = self.alignment, self.error
        lines = [
            f"paired {self.n_paired} of {self.n_estimate} estimate poses with the truth's {self.n_truth} "
            f"(within {self.max_diff:g} s)",
        ]
        if self.align == "none":
            lines.append("alignment: none (the estimate's frame taken as the truth's)")
        else:
            lines.append(
                f"alignment ({self.align}): rotation {math.degrees(a.rotation):+.3f} deg, translation "
                f"({a.translation[0]:+.4f}, {a.translation[1]:+.4f}) m"
                + (f", scale {a.scale:.5f}" if self.align == "similarity" else "")
            )
        lines += [
            f"{'error':<18}{'rmse':>10}{'mean':>10}{'median':>10}{'max':>10}{'final':>10}",
            f"{'position [m]':<18}{e.rmse:>10.4f}{e.mean:>10.4f}{self.median:>10.4f}{e.max:>10.4f}{e.final:>10.4f}",
            f"{'heading [deg]':<18}{'':>10}{e.heading_mean_deg:>10.3f}{'':>10}{'':>10}{e.heading_final_deg:>10.3f}",
        ]
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        a = self.alignment
        return {
            "align": self.align, "n_estimate": self.n_estimate, "n_truth": self.n_truth, "n_paired": self.n_paired,
            "max_diff_s": self.max_diff,
            "alignment": {"rotation_deg": math.degrees(a.rotation), "translation_m": list(a.translation),
                          "scale": a.scale},
            **self.error.to_dict(), "median": self.median,
        }


def evaluate_ate(
    estimate: Trajectory,
    truth: Trajectory,
    *,
    align: str = "rigid",
    max_diff: float = 0.01,
    sources: tuple[str | Path | None, str | Path | None] = (None, None),
) -> tuple[AteResult, np.ndarray, np.ndarray]:
    """The ATE of `estimate` against `truth` (module docstring), and the paired poses: the
    aligned estimate's and the truth's, (n_paired, 3) each, in time order.

    Raises:
        InputError: naming the file (`sources`: the estimate's and the truth's) where a pose is
            not finite, no pose pairs within `max_diff`, or the pairs determine no alignment.
    """
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {', '.join(ALIGNMENTS)}, got {align!r}")
    est_index, truth_index = pair_poses(estimate, truth, max_diff, sources)
    est, ref = estimate.poses[est_index], truth.poses[truth_index]
    if align == "none":
        alignment = Alignment()
    else:
        try:
            alignment = fit_alignment(est, ref, scale=align == "similarity")
        except ValueError as err:
            raise InputError(f"{err} ({len(est)} paired poses), so no {align} alignment: use --align none",
                             sources[0]) from None
    moved = alignment.apply(est)
    error = absolute_trajectory_error(moved, ref)
    median = float(np.median(np.hypot(moved[:, 0] - ref[:, 0], moved[:, 1] - ref[:, 1])))
    result = AteResult(align=align, n_estimate=len(estimate), n_truth=len(truth), n_paired=len(est),
                       max_diff=max_diff, alignment=alignment, error=error, median=median)
    return result, moved, ref


def pair_poses(
    estimate: Trajectory,
    truth: Trajectory,
    max_diff: float,
    sources: tuple[str | Path | None, str | Path | None] = (None, None),
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (estimate's, truth's) of the pose pairs, in time order: each truth pose with the
    estimate pose nearest to it among those whose nearest truth pose it is, if within `max_diff`
    seconds (so one pair per truth pose at most, whichever trajectory is recorded faster).

    Raises:
        ValueError: for a negative or NaN `max_diff`.
        InputError: naming the file (`sources`) where a pose is not finite or no pose pairs.
    """
    if not max_diff >= 0:  # NaN too
        raise ValueError(f"max_diff must be >= 0 seconds, got {max_diff}")
    for traj, source, name in ((estimate, sources[0], "estimate"), (truth, sources[1], "truth")):
        i = first_non_finite(traj.timestamps, traj.poses)
        if i is not None:
            raise InputError(f"the {name}'s pose {i} is not finite: stamp {traj.timestamps[i]}, pose {traj.poses[i]}",
                             source)
    nearest, ok = match_times(truth.timestamps, estimate.timestamps, max_diff)
    if not ok.any():
        truth_name = f" ({sources[1]})" if sources[1] is not None else ""
        raise InputError(
            f"no pose lies within {max_diff:g} s of a pose of the truth{truth_name} (estimate {_span(estimate)}, "
            f"truth {_span(truth)}): are both on the same clock? (--max-diff widens the pairing)", sources[0])
    candidates = np.flatnonzero(ok)
    offset = np.abs(estimate.timestamps[candidates] - truth.timestamps[nearest[candidates]])
    order = np.lexsort((offset, nearest[candidates]))  # by truth pose, then nearest first
    truth_index, first = np.unique(nearest[candidates][order], return_index=True)
    est_index = candidates[order][first]
    by_time = np.argsort(truth.timestamps[truth_index], kind="stable")
    est_index, truth_index = est_index[by_time], truth_index[by_time]
    _warn_of_time_offsets(estimate, truth, est_index, truth_index, sources[0])
    return est_index, truth_index


def _warn_of_time_offsets(estimate: Trajectory, truth: Trajectory, est_index: np.ndarray, truth_index: np.ndarray,
                          source: str | Path | None) -> None:
    """Warn where the truth moves more than PAIRING_MOTION between a pair's two stamps (its
    speed there, from its neighbouring poses, times the stamps' difference): that motion is
    counted as error."""
    if len(truth) < 2:
        return
    t, xy = truth.timestamps, truth.poses[:, :2]
    lo, hi = np.maximum(truth_index - 1, 0), np.minimum(truth_index + 1, len(truth) - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        speed = np.hypot(*(xy[hi] - xy[lo]).T) / (t[hi] - t[lo])
    motion = np.nan_to_num(speed) * np.abs(estimate.timestamps[est_index] - t[truth_index])
    far = motion > PAIRING_MOTION
    if far.any():
        where = f"{source}: " if source else ""
        warnings.warn(OmnitofWarning(
            f"{where}{int(far.sum())} of {len(motion)} pairs of poses lie up to "
            f"{np.max(np.abs(estimate.timestamps[est_index] - t[truth_index])):.3g} s apart, in which the truth moves up "
            f"to {motion.max():.3g} m: an offset in time that large becomes error in position (stamps on two clocks, "
            "or a --max-diff too loose)"), stacklevel=3)


def _span(traj: Trajectory) -> str:
    return f"{traj.timestamps.min():.6f}..{traj.timestamps.max():.6f} s" if len(traj) else "empty"
