"""Relative pose error (RPE) of an estimated trajectory against a ground truth on the same clock:
how far the estimate's motion over a fixed stretch (metres of path, seconds or poses) differs
from the truth's, as evo_rpe and the TUM RGB-D benchmark define it. No alignment is needed.

1. **Pairing**, as for the ATE (`ate.pair_poses`): at most one estimate pose per truth pose,
   the nearest in time within `max_diff` seconds. Only the paired poses are used, so a truth
   recorded faster than the estimate (motion capture at 120 Hz, SLAM at 10 Hz) costs nothing.
2. **Relations** (`relations.relations_along`): from each paired truth pose to the first paired
   one at least `delta` further along the truth.
3. **Errors**: the relations metric (`relations.evaluate_relations`) of the estimate's paired
   poses, put at their truth poses' stamps.

A relation that spans more than GAP_FACTOR times `delta` (of path or time; with "f", of the
relations' median time) bridges a gap in the truth or in the pairing: warned of, as its error
holds that stretch.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import InputError, OmnitofWarning
from omnitof.eval.ate import pair_poses
from omnitof.eval.relations import (
    RELATION_UNITS,
    Relations,
    RelationsResult,
    evaluate_relations,
    path_along,
    relations_along,
)
from omnitof.types import Trajectory

GAP_FACTOR = 3.0


@dataclass(frozen=True)
class RpeResult:
    """The relations metric's result over relations `delta` `unit` apart, and how many poses
    were paired."""

    delta: float
    unit: str
    max_diff: float
    n_paired: int
    relations: RelationsResult

    @property
    def trans_rmse(self) -> float:
        return math.sqrt(self.relations.trans2_mean)

    @property
    def rot_rmse(self) -> float:
        return math.sqrt(self.relations.rot2_mean)

    def format(self) -> str:
        r = self.relations
        lines = [
            f"relative pose error over {self.delta:g} {RELATION_UNITS[self.unit]}: {r.n_matched} pairs of the "
            f"{self.n_paired} poses paired with the truth (within {self.max_diff:g} s)",
            f"{'error':<18}{'mean':>10}{'std':>10}{'rmse':>10}",
        ]
        for name, mean, std, rmse in (("translation [m]", r.trans_mean, r.trans_std, self.trans_rmse),
                                      ("rotation [deg]", r.rot_mean, r.rot_std, self.rot_rmse)):
            lines.append(f"{name:<18}" + "".join(_cell(v) for v in (mean, std, rmse)))
        if self.unit == "m":
            lines.append(f"per metre of path: {100 * r.trans_mean / self.delta:.2f} % of the distance, "
                         f"{r.rot_mean / self.delta:.3f} deg/m")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        r = self.relations
        values = {"delta": self.delta, "unit": self.unit, "max_diff_s": self.max_diff, "paired_poses": self.n_paired,
                  "pairs": r.n_matched, "trans_mean": r.trans_mean, "trans_std": r.trans_std,
                  "trans_rmse": self.trans_rmse, "rot_mean_deg": r.rot_mean, "rot_std_deg": r.rot_std,
                  "rot_rmse_deg": self.rot_rmse}
        return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in values.items()}


def evaluate_rpe(
    estimate: Trajectory,
    truth: Trajectory,
    *,
    delta: float = 1.0,
    unit: str = "m",
    max_diff: float = 0.01,
    sources: tuple[str | Path | None, str | Path | None] = (None, None),
) -> RpeResult:
    """The RPE of `estimate` against `truth` (module docstring).

    Raises:
        ValueError: for a unit other than m, s, f, or a `delta` that is not positive (a whole
            number for "f").
        InputError: naming the file (`sources`: the estimate's and the truth's) where a pose is
            not finite, no pose pairs within `max_diff`, or no two paired poses lie `delta` apart.
    """
    est_index, truth_index = pair_poses(estimate, truth, max_diff, sources)
    stamps = truth.timestamps[truth_index]
    paired_truth = Trajectory(stamps, truth.poses[truth_index])
    relations = relations_along(paired_truth, delta, unit)
    if not len(relations):
        raise InputError(f"no two poses paired with the estimate lie {delta:g} {RELATION_UNITS[unit]} apart "
                         f"({len(stamps)} paired over {stamps[-1] - stamps[0]:.3f} s): give a shorter --delta",
                         sources[1])
    _warn_of_gaps(paired_truth, relations, delta, unit, sources[1])
    result = evaluate_relations(Trajectory(stamps, estimate.poses[est_index]), relations, time_tolerance=0.0,
                                source=sources[0])
    return RpeResult(delta=delta, unit=unit, max_diff=max_diff, n_paired=len(stamps), relations=result)


def _warn_of_gaps(truth: Trajectory, relations: Relations, delta: float, unit: str, source: str | Path | None) -> None:
    """Warn of the relations that span more than GAP_FACTOR times what they should: `delta` of
    path ("m") or of time ("s"), or the relations' median time ("f")."""
    i = np.searchsorted(truth.timestamps, relations.t1)
    j = np.searchsorted(truth.timestamps, relations.t2)
    if unit == "m":
        path = path_along(truth.poses)
        spans, limit, what = path[j] - path[i], GAP_FACTOR * delta, "m of path"
    else:
        spans = relations.t2 - relations.t1
        limit = GAP_FACTOR * (delta if unit == "s" else float(np.median(spans)))
        what = "s"
    long = spans > limit
    if long.any():
        where = f"{source}: " if source else ""
        warnings.warn(OmnitofWarning(
            f"{where}{int(long.sum())} of {len(spans)} pairs {delta:g} {RELATION_UNITS[unit]} apart span up to "
            f"{spans.max():.3g} {what}, more than {GAP_FACTOR:g} times what they should (a gap in the truth or in "
            "its pairing with the estimate, or poses further apart than --delta): their errors hold that longer "
            "stretch"), stacklevel=3)


def _cell(value: float) -> str:
    return f"{'–':>10}" if math.isnan(value) else f"{value:>10.4f}"


