"""The relation-based SLAM metric of Kümmerle et al. 2009.

R. Kümmerle, B. Steder, C. Dornhege, M. Ruhnke, G. Grisetti, C. Stachniss, A. Kleiner, "On
measuring the accuracy of SLAM algorithms", Autonomous Robots 27(4):387-407, 2009.

A relations file lists reference relative motions: `t1 t2 x y z roll pitch yaw` means the robot
pose at time t2 seen from the frame of the robot pose at time t1 (metres, radians) is
δ_ref = (x, y, yaw). For each relation whose two timestamps are in the evaluated trajectory,

    δ_est = ⊖pose(t1) ⊕ pose(t2)              (geometry.relative)
    e     = ⊖δ_ref ⊕ δ_est                    (geometry.relative(δ_ref, δ_est))
    translational error = hypot(e.x, e.y)  [m]
    rotational error    = |wrap(e.θ)|       [deg]

and the result reports mean and standard deviation of these errors and of their squares, and
the mean errors of the relations between scans less than REVISIT_SECONDS apart and of the
revisits apart (`RelationsResult.split`).

How this matches the benchmark's own tools (read from their public sources, not copied):

* The authors' `metricEvaluator` (Freiburg, 2009) subtracts the two relative transforms
  component-wise, (x, y, z, roll, pitch, yaw)_est - (...)_ref with the angle differences
  normalised, then takes sqrt(dᵀ W d) with weights W = diag(1,1,1,0,0,0) for the translational
  error and diag(0,0,0,1,1,1) for the rotational one (radians there; the paper tables use
  degrees). In the plane this equals the definition above exactly: e's translation is
  R(-θ_ref)(t_est - t_ref), a rotation of t_est - t_ref, so it has the same length, and e.θ =
  θ_est - θ_ref. Its `-q` option averages the squared errors instead, which is our trans2/rot2.
* Cartographer's `compute_relations_metrics` uses δ_est ⊕ ⊖δ_ref instead, whose translation
  t_est - R(θ_est - θ_ref) t_ref differs from ours by a term of the order of the rotational error
  times |t_ref| (its own source notes the asymmetry). We follow the original evaluator.
* Both compute the standard deviation with the sample (n - 1) denominator; so does this module
  (with one matched relation the std is NaN: null in summary.yaml, "–" in the printed table).
* metricEvaluator takes the SLAM pose nearest in time to each relation timestamp (within 0.1 s,
  otherwise it shifts it along raw odometry). Here a trajectory pose is used only if its timestamp
  equals the relation's to within `time_tolerance` (1 ms by default; the benchmark files use the
  logs' scan ipc timestamps to 1e-5 s); other relations are counted as unmatched.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import InputError, OmnitofWarning, read_problem
from omnitof.io.text import parse_float_row
from omnitof.geometry import relative, wrap_angle
from omnitof.types import MAX_TIMESTAMP, Trajectory, first_non_finite

ROW_MESSAGE = "relation rows need 8 numbers: t1 t2 x y z roll pitch yaw"
_FIELDS = ("t1", "t2", "x", "y", "z", "roll", "pitch", "yaw")
# A relative motion beyond a million kilometres or a thousand radians comes from a broken writer.
_LIMITS = {"x": 1e9, "y": 1e9, "z": 1e9, "roll": 1e3, "pitch": 1e3, "yaw": 1e3}

# Most benchmark relations join scans seconds apart; some join two passes of the same place
# (the Freiburg hospital's local set: 178 of 2820, minutes apart). Reported apart, the first say
# how accurate the trajectory is locally and the second whether its loops agree: a run can be
# locally better than its odometry and still have mapped a wing twice (BENCHMARKS.md, issue 13).
REVISIT_SECONDS = 60.0

# z, roll and pitch of a planar benchmark are 0 (written as 0.000000); anything larger means a 3D
# relation that a planar evaluation would silently get wrong.
_PLANAR_TOLERANCE = 1e-6


@dataclass
class Relations:
    """Reference relative motions.

    Attributes:
        t1, t2: (N,) float64 timestamps, seconds (the logs' ipc timestamps for the benchmark).
        delta: (N, 3) float64 relative poses (x, y, yaw): the pose at t2 in the frame of the pose
            at t1, metres and radians.
        source: the file they came from, for messages.
    """

    t1: np.ndarray
    t2: np.ndarray
    delta: np.ndarray
    source: str = ""

    def __post_init__(self) -> None:
        self.t1 = np.ascontiguousarray(self.t1, dtype=np.float64).reshape(-1)
        self.t2 = np.ascontiguousarray(self.t2, dtype=np.float64).reshape(-1)
        self.delta = np.ascontiguousarray(self.delta, dtype=np.float64).reshape(-1, 3)
        if not len(self.t1) == len(self.t2) == len(self.delta):
            raise ValueError("relations need one t1, one t2 and one delta per relation")

    def __len__(self) -> int:
        return len(self.t1)


def read_relations(path: str | Path) -> Relations:
    """Read a benchmark relations file (`t1 t2 x y z roll pitch yaw` per line, '#' comments).

    Raises:
        InputError: naming the file and line for a row that is not 8 finite numbers or is not
            planar (z, roll, pitch not 0); naming the file if it cannot be read or is empty.
    """
    try:
        # "\n" only (read_text folds "\r\n" and "\r" into it): splitlines() also breaks at form
        # feeds, \x1c-\x1e, \x85 and \u2028, and every line number after them would be wrong. utf-8-sig drops the byte order mark that Windows editors write first.
        lines = Path(path).read_text(encoding="utf-8-sig").split("\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the relations file: {read_problem(exc)}", path) from None
    rows = [
        _parse_relation(text, path, number)
        for number, text in enumerate((line.strip() for line in lines), start=1)
        if text and not text.startswith("#")
    ]
    if not rows:
        raise InputError("no relations: the file is empty", path)
    data = np.asarray(rows)
    return Relations(t1=data[:, 0], t2=data[:, 1], delta=data[:, [2, 3, 7]], source=str(path))


RELATION_UNITS = {"m": "m of the truth's path", "s": "s", "f": "poses"}


def path_along(poses: np.ndarray) -> np.ndarray:
    """(N,) metres driven from the first of (N, 3) poses to each, along the straight steps between them."""
    return np.r_[0.0, np.cumsum(np.hypot(*np.diff(np.asarray(poses)[:, :2], axis=0).T))]


def relations_along(truth: Trajectory, delta: float, unit: str = "m") -> Relations:
    """Relations made from a ground truth: from each of its poses to the first one at least
    `delta` further along it, in metres of path ("m"), seconds ("s") or poses ("f"). Scored with
    `evaluate_relations`, they give the relative pose error (RPE) of a trajectory, as evo_rpe
    and the TUM RGB-D benchmark define it, over the same distance everywhere.

    Raises:
        ValueError: for a unit other than m, s, f or a `delta` that is not positive (a whole
            number of poses for "f").
    """
    if unit not in RELATION_UNITS:
        raise ValueError(f"unit must be one of {', '.join(RELATION_UNITS)}, got {unit!r}")
    if not (math.isfinite(delta) and delta > 0) or (unit == "f" and delta != int(delta)):
        raise ValueError(f"delta must be a positive {'whole number' if unit == 'f' else 'number'}, got {delta!r}")
    poses, stamps = truth.poses, truth.timestamps
    n = len(truth)
    if unit == "f":
        first = np.arange(n) + int(min(delta, n))  # min: a delta beyond any integer type's range
    else:
        along = stamps - stamps[0] if unit == "s" else path_along(poses)
        # A small tolerance: a pose that a rounding error puts a hair short of delta still counts;
        # never the pose itself, however small delta is.
        first = np.searchsorted(along, along + delta - 1e-9 * max(1.0, delta), side="left")
        first = np.maximum(first, np.arange(n) + 1)
    i = np.flatnonzero(first < n)
    j = first[i]
    return Relations(stamps[i], stamps[j], relative(poses[i], poses[j]),
                     source=f"pairs of truth poses {delta:g} {RELATION_UNITS[unit]} apart")


def _parse_relation(text: str, path: str | Path, number: int) -> list[float]:
    row = parse_float_row(text, 8, ROW_MESSAGE, path, number, names=_FIELDS, limits=_LIMITS)
    for name, t in zip(("t1", "t2"), row[:2]):
        if abs(t) > MAX_TIMESTAMP:
            raise InputError(f"{name} {t:g} is beyond ±{MAX_TIMESTAMP:g} s: relation timestamps are seconds", path,
                             number)
    if row[0] == row[1]:
        raise InputError(f"t1 and t2 are both {row[0]:.6f}: a relation joins two different times", path, number)
    if max(abs(v) for v in row[4:7]) > _PLANAR_TOLERANCE:
        raise InputError(
            "z, roll and pitch must be 0: only planar relations are supported", path, number
        )
    return row


@dataclass(frozen=True)
class RelationsResult:
    """Statistics of the relation errors over the matched relations.

    Units: trans_* in metres, trans2_* in m², rot_* in degrees, rot2_* in deg². Standard deviations
    use the sample (n - 1) denominator, like the benchmark's evaluator; NaN with one relation.
    `matched` is a (n_relations,) bool mask over the relations as read; `trans_errors`,
    `rot_errors` and `gaps` (|t2 - t1|, seconds) hold one value per matched relation, in that
    order. `split()` gives the mean errors of the relations between scans less than
    REVISIT_SECONDS apart and of the revisits.
    """

    n_relations: int
    n_matched: int
    trans_mean: float
    trans_std: float
    trans2_mean: float
    trans2_std: float
    rot_mean: float
    rot_std: float
    rot2_mean: float
    rot2_std: float
    trans_errors: np.ndarray = field(repr=False)
    rot_errors: np.ndarray = field(repr=False)
    matched: np.ndarray = field(repr=False)
    gaps: np.ndarray = field(repr=False)
    time_tolerance: float = 1e-3

    @property
    def n_unmatched(self) -> int:
        return self.n_relations - self.n_matched

    def split(self) -> dict[str, dict[str, Any]]:
        """Count and mean errors of the relations between scans less than REVISIT_SECONDS apart
        ("nearby") and of the rest ("revisits"); a group without relations has None for its means."""
        out = {}
        for name, mask in (("nearby", self.gaps < REVISIT_SECONDS), ("revisits", self.gaps >= REVISIT_SECONDS)):
            n = int(mask.sum())
            with np.errstate(over="ignore"):  # errors beyond float64's range average to inf
                out[name] = {
                    "n": n,
                    "trans_mean": _plain(_mean(self.trans_errors[mask])) if n else None,
                    "rot_mean": _plain(_mean(self.rot_errors[mask])) if n else None,
                }
        return out

    def format(self) -> str:
        """A short table: counts, then mean and std of each error."""
        rows = [
            ("translational [m]", self.trans_mean, self.trans_std),
            ("translational² [m²]", self.trans2_mean, self.trans2_std),
            ("rotational [deg]", self.rot_mean, self.rot_std),
            ("rotational² [deg²]", self.rot2_mean, self.rot2_std),
        ]
        lines = [
            f"relations: {self.n_relations}, matched {self.n_matched}, "
            f"unmatched {self.n_unmatched}",
            f"{'error':<22}{'mean':>12}{'std':>12}",
        ]
        # One matched relation has no std (NaN; summary.yaml writes null): a dash, not "nan".
        lines += [f"{name:<22}{_cell(mean)}{_cell(std)}" for name, mean, std in rows]
        groups = self.split()
        if groups["revisits"]["n"]:
            lines.append(
                "mean errors, " + "; ".join(
                    f"{label}: {g['n']}, {g['trans_mean']:.4f} m, {g['rot_mean']:.3f} deg"
                    for label, g in (
                        (f"scans < {REVISIT_SECONDS:g} s apart", groups["nearby"]),
                        ("revisits", groups["revisits"]),
                    )
                    if g["n"]
                )
            )
        return "\n".join(lines)

    def to_dict(self, *, include_errors: bool = False) -> dict[str, Any]:
        """Plain Python values for YAML/JSON (NaN becomes None); per-relation errors on request."""
        out: dict[str, Any] = {
            "n_relations": self.n_relations,
            "n_matched": self.n_matched,
            "n_unmatched": self.n_unmatched,
            "time_tolerance": self.time_tolerance,
        }
        for key in ("trans", "trans2", "rot", "rot2"):
            out[f"{key}_mean"] = _plain(getattr(self, f"{key}_mean"))
            out[f"{key}_std"] = _plain(getattr(self, f"{key}_std"))
        for group, values in self.split().items():
            out[group] = values
        if include_errors:
            out["trans_errors"] = [float(v) for v in self.trans_errors]
            out["rot_errors"] = [float(v) for v in self.rot_errors]
        return out


def _plain(value: float) -> float | None:
    return None if math.isnan(value) else float(value)


def evaluate_relations(
    traj: Trajectory,
    relations: Relations,
    *,
    time_tolerance: float = 1e-3,
    source: str | Path | None = None,
) -> RelationsResult:
    """Score `traj` against the reference `relations` (see the module docstring for the metric).

    Args:
        traj: the estimated trajectory; its timestamps must be on the relations' clock.
        relations: the reference relative motions.
        time_tolerance: seconds; a relation end matches the nearest trajectory pose only if their
            timestamps differ by at most this.
        source: the trajectory's file, named in error messages.

    Raises:
        InputError: if no relation has both ends in the trajectory.
    """
    if not time_tolerance >= 0:  # NaN too
        raise ValueError(f"time_tolerance must be >= 0 seconds, got {time_tolerance}")
    i = first_non_finite(traj.timestamps, traj.poses)
    if i is not None:
        raise InputError(f"the trajectory's pose {i} is not finite: stamp {traj.timestamps[i]}, pose {traj.poses[i]}",
                         source)
    i1, ok1 = match_times(traj.timestamps, relations.t1, time_tolerance)
    i2, ok2 = match_times(traj.timestamps, relations.t2, time_tolerance)
    matched = ok1 & ok2
    if not matched.any():
        raise InputError(_no_match_message(traj, relations, time_tolerance), source)
    _warn_of_other_moments(traj, relations, i1, i2, matched, source)
    gaps = np.abs(relations.t2[matched] - relations.t1[matched])
    # Errors beyond float64's range (a trajectory or a relation 1e300 m off) are inf, and so are
    # their statistics: the answer, not a page of numpy's overflow warnings.
    with np.errstate(over="ignore", invalid="ignore"):
        trans, rot = relation_errors(
            traj.poses[i1[matched]], traj.poses[i2[matched]], relations.delta[matched]
        )
        stats = dict(
            trans_mean=_mean(trans),
            trans_std=_sample_std(trans),
            trans2_mean=_mean(trans**2),
            trans2_std=_sample_std(trans**2),
            rot_mean=_mean(rot),
            rot_std=_sample_std(rot),
            rot2_mean=_mean(rot**2),
            rot2_std=_sample_std(rot**2),
        )
    return RelationsResult(
        n_relations=len(relations),
        n_matched=int(matched.sum()),
        **stats,
        trans_errors=trans,
        rot_errors=rot,
        matched=matched,
        gaps=gaps,
        time_tolerance=time_tolerance,
    )


def check_relations_match(
    relations: Relations, timestamps: np.ndarray, *, time_tolerance: float = 1e-3
) -> None:
    """Check, before a run, that some relation has both ends among the scans' `timestamps`
    (as `evaluate_relations` will need of the trajectory, which has a pose at every scan).

    Raises:
        InputError: naming the relations file, if none has.
    """
    _, ok1 = match_times(timestamps, relations.t1, time_tolerance)
    _, ok2 = match_times(timestamps, relations.t2, time_tolerance)
    if not (ok1 & ok2).any():
        times = np.concatenate([relations.t1, relations.t2])
        scans = f"{timestamps.min():.6f}..{timestamps.max():.6f} s" if len(timestamps) else "none"
        raise InputError(
            f"no relation has both its timestamps among the scans to be processed (within "
            f"{time_tolerance:g} s; the relations span {times.min():.6f}..{times.max():.6f} s, the "
            f"scans {scans}): are they the relations of this log?",
            relations.source or None,
        )


def relation_errors(
    pose1: np.ndarray, pose2: np.ndarray, delta_ref: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-relation (translational error [m], rotational error [deg]) of poses (N, 3) at t1, t2."""
    delta_est = relative(pose1, pose2)
    e = relative(delta_ref, delta_est)
    trans = np.hypot(e[:, 0], e[:, 1])
    rot = np.degrees(np.abs(wrap_angle(e[:, 2])))
    return trans, rot


def match_times(
    timestamps: np.ndarray, query: np.ndarray, tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per query time: (index of the nearest trajectory timestamp, whether within tolerance)."""
    n = len(timestamps)
    if n == 0:
        return np.zeros(len(query), dtype=np.intp), np.zeros(len(query), dtype=bool)
    # Sorting makes searchsorted valid even for a trajectory that is not in time order.
    order = np.argsort(timestamps, kind="stable")
    ts = timestamps[order]
    right = np.clip(np.searchsorted(ts, query), 0, n - 1)
    left = np.clip(right - 1, 0, n - 1)
    take_left = np.abs(query - ts[left]) < np.abs(query - ts[right])
    nearest = np.where(take_left, left, right)
    # Of poses that share a stamp, the last (the latest estimate): the one write_tum keeps, so
    # that a run scores the same in memory and from its TUM file.
    nearest = (np.searchsorted(ts, ts, side="right") - 1)[nearest]
    ok = np.abs(query - ts[nearest]) <= tolerance
    return order[nearest], ok


def _warn_of_other_moments(
    traj: Trajectory, relations: Relations, i1: np.ndarray, i2: np.ndarray, matched: np.ndarray,
    source: str | Path | None,
) -> None:
    """Warn where a loose `time_tolerance` matched relation ends to poses of other moments.

    A relation end further from its pose than half the trajectory's median step is nearer to
    another moment of the run than to that pose: its error then holds the motion in between, not
    the estimate's. The default 1 ms never allows this at a scanner's rate."""
    steps = np.diff(np.sort(traj.timestamps))
    steps = steps[steps > 0]
    if not len(steps):
        return
    half_step = 0.5 * float(np.median(steps))
    offsets = np.maximum(
        np.abs(relations.t1[matched] - traj.timestamps[i1[matched]]),
        np.abs(relations.t2[matched] - traj.timestamps[i2[matched]]),
    )
    far = offsets > half_step
    if far.any():
        where = f"{source}: " if source else ""
        warnings.warn(OmnitofWarning(
            f"{where}{int(far.sum())} of {int(matched.sum())} matched relations have an end up to "
            f"{offsets.max():.3g} s from the trajectory's pose it was matched to (the trajectory's "
            f"median step is {2 * half_step:.3g} s): their errors include the motion in between. "
            "Is the time tolerance too loose, or the trajectory not one pose per scan?"
        ), stacklevel=3)


def _no_match_message(traj: Trajectory, relations: Relations, tolerance: float) -> str:
    times = np.concatenate([relations.t1, relations.t2])
    span = f"relations span {times.min():.6f}..{times.max():.6f} s"
    if len(traj):
        span += f", trajectory {traj.timestamps.min():.6f}..{traj.timestamps.max():.6f} s"
    else:
        span += ", the trajectory is empty"
    where = f" of {relations.source}" if relations.source else ""
    return (
        f"no relation timestamp{where} was found in the trajectory "
        f"(within {tolerance:g} s; {span}); "
        "the benchmark relations use the log's ipc timestamps: write the trajectory with those "
        "(one pose per scan)"
    )


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values))


def _cell(value: float) -> str:
    """A number of the printed table, or a dash where there is none (NaN)."""
    if math.isnan(value):
        return f"{'–':>12}"
    # Six decimals while they fit; a diverged run's error (10⁶ m and more) in fewer digits, so
    # that the columns never run together.
    text = f"{value:.6f}"
    return f"{text if len(text) < 12 else f'{value:.6g}':>12}"


def _sample_std(values: np.ndarray) -> float:
    return float(np.std(values, ddof=1)) if len(values) > 1 else math.nan
