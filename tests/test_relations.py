"""Tests of omnitof.eval.relations (the Kümmerle et al. 2009 relation metric)."""

from __future__ import annotations

import json
import math
import os
import statistics
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from omnitof.errors import InputError, OmnitofWarning
from omnitof.eval.relations import Relations, evaluate_relations, read_relations
from omnitof.geometry import compose, relative
from omnitof.types import Trajectory

T0 = 976052896.784509  # a Unix time like the Intel log's


def _ground_truth(n: int = 12, seed: int = 1) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = np.column_stack(
        [
            np.cumsum(rng.normal(0, 1, n)),
            np.cumsum(rng.normal(0, 1, n)),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )
    return Trajectory(T0 + np.arange(n) * 0.4 + rng.uniform(0, 0.01, n), poses)


def _relations_of(traj: Trajectory, pairs: list[tuple[int, int]]) -> Relations:
    i, j = np.array(pairs).T
    return Relations(traj.timestamps[i], traj.timestamps[j], relative(traj.poses[i], traj.poses[j]))


def _matrix(pose: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]])


def _independent_errors(p1: np.ndarray, p2: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """Errors from homogeneous matrices: E = ref⁻¹ (p1⁻¹ p2); not using omnitof.geometry."""
    e = np.linalg.inv(_matrix(ref)) @ np.linalg.inv(_matrix(p1)) @ _matrix(p2)
    return float(np.hypot(e[0, 2], e[1, 2])), abs(math.degrees(math.atan2(e[1, 0], e[0, 0])))


PAIRS = [(0, 1), (1, 2), (2, 5), (3, 9), (7, 4), (0, 11), (10, 11)]  # (7, 4): t1 > t2 happens


def test_ground_truth_scores_zero() -> None:
    gt = _ground_truth()
    result = evaluate_relations(gt, _relations_of(gt, PAIRS))
    assert result.n_relations == result.n_matched == len(PAIRS)
    np.testing.assert_allclose(result.trans_errors, 0.0, atol=1e-12)
    np.testing.assert_allclose(result.rot_errors, 0.0, atol=1e-10)
    assert result.trans_mean < 1e-12 and result.rot2_mean < 1e-18


def test_heading_error_on_second_pose() -> None:
    # Rotating the robot at t2 in place changes the relative heading only: rot 2 deg, trans 0.
    p1, p2 = np.array([1.0, 2.0, 0.3]), np.array([4.0, 6.0, 1.0])
    ref = relative(p1, p2)
    est = Trajectory([10.0, 11.0], [p1, p2 + [0.0, 0.0, math.radians(2.0)]])
    result = evaluate_relations(est, Relations([10.0], [11.0], [ref]))
    assert result.rot_errors[0] == pytest.approx(2.0, abs=1e-9)
    assert result.trans_errors[0] == pytest.approx(0.0, abs=1e-12)


def test_heading_error_on_first_pose() -> None:
    # Rotating the robot at t1 by 2 deg swings the seen position of pose 2 (distance 5 m) through
    # 2 deg: translational error = chord = 2 * 5 * sin(1 deg); rotational error 2 deg.
    p1, p2 = np.array([1.0, 2.0, 0.3]), np.array([4.0, 6.0, 1.0])
    ref = relative(p1, p2)
    est = Trajectory([10.0, 11.0], [p1 + [0.0, 0.0, math.radians(2.0)], p2])
    result = evaluate_relations(est, Relations([10.0], [11.0], [ref]))
    assert result.trans_errors[0] == pytest.approx(2 * 5.0 * math.sin(math.radians(1.0)), rel=1e-12)
    assert result.rot_errors[0] == pytest.approx(2.0, abs=1e-9)


def test_position_error_on_second_pose() -> None:
    # Shifting pose 2 by (0.3, -0.4) in the world gives a 0.5 m translational error, whatever the
    # headings, and no rotational error.
    p1, p2 = np.array([1.0, 2.0, 2.5]), np.array([-4.0, 6.0, -1.0])
    est = Trajectory([10.0, 11.0], [p1, p2 + [0.3, -0.4, 0.0]])
    result = evaluate_relations(est, Relations([10.0], [11.0], [relative(p1, p2)]))
    assert result.trans_errors[0] == pytest.approx(0.5, rel=1e-12)
    assert result.rot_errors[0] == pytest.approx(0.0, abs=1e-10)


def test_rotation_error_wraps() -> None:
    # Reference turns by +179 deg, estimate by -179 deg: 2 deg apart, not 358.
    rel = Relations([0.0], [1.0], [[1.0, 0.0, math.radians(179.0)]])
    est = Trajectory([0.0, 1.0], [[0.0, 0.0, 0.0], [1.0, 0.0, math.radians(-179.0)]])
    assert evaluate_relations(est, rel).rot_errors[0] == pytest.approx(2.0, abs=1e-9)


def test_statistics_match_an_independent_computation() -> None:
    gt = _ground_truth()
    rng = np.random.default_rng(7)
    est_poses = gt.poses + rng.normal(0, [0.05, 0.05, 0.02], gt.poses.shape)
    est = Trajectory(gt.timestamps, est_poses)
    rel = _relations_of(gt, PAIRS)
    result = evaluate_relations(est, rel)

    expected = [
        _independent_errors(est_poses[i], est_poses[j], rel.delta[k])
        for k, (i, j) in enumerate(PAIRS)
    ]
    trans = [t for t, _ in expected]
    rot = [r for _, r in expected]
    np.testing.assert_allclose(result.trans_errors, trans, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.rot_errors, rot, rtol=1e-9, atol=1e-9)
    # statistics.stdev is the sample (n - 1) standard deviation, as in the benchmark's evaluator.
    checks = {
        "trans": trans,
        "trans2": [t * t for t in trans],
        "rot": rot,
        "rot2": [r * r for r in rot],
    }
    for key, values in checks.items():
        assert getattr(result, f"{key}_mean") == pytest.approx(statistics.mean(values), rel=1e-9)
        assert getattr(result, f"{key}_std") == pytest.approx(statistics.stdev(values), rel=1e-9)


def test_nearby_relations_and_revisits_are_reported_apart() -> None:
    # Twelve poses 30 s apart: pairs one step apart are nearby, the others revisits (>= 60 s).
    # The second half of the trajectory is shifted 1 m, as if a loop had come back beside itself,
    # and every pose is perturbed a little.
    gt = _ground_truth()
    gt = Trajectory(T0 + np.arange(len(gt)) * 30.0, gt.poses)
    rng = np.random.default_rng(3)
    est_poses = gt.poses + rng.normal(0, [0.02, 0.02, 0.01], gt.poses.shape)
    est_poses[6:, 0] += 1.0
    pairs = [(0, 1), (1, 2), (4, 5), (6, 7), (9, 10), (0, 11), (2, 9), (5, 4), (3, 8)]
    rel = _relations_of(gt, pairs)
    result = evaluate_relations(Trajectory(gt.timestamps, est_poses), rel)

    groups = result.split()
    expected = [_independent_errors(est_poses[i], est_poses[j], rel.delta[k]) for k, (i, j) in enumerate(pairs)]
    nearby = [e for e, (i, j) in zip(expected, pairs) if abs(i - j) == 1]
    revisits = [e for e, (i, j) in zip(expected, pairs) if abs(i - j) > 1]
    assert groups["nearby"]["n"] == 6 and groups["revisits"]["n"] == 3
    assert groups["nearby"]["trans_mean"] == pytest.approx(statistics.mean(t for t, _ in nearby), rel=1e-9)
    assert groups["nearby"]["rot_mean"] == pytest.approx(statistics.mean(r for _, r in nearby), rel=1e-9)
    assert groups["revisits"]["trans_mean"] == pytest.approx(statistics.mean(t for t, _ in revisits), rel=1e-9)
    # Every revisit straddles the shift and no nearby pair does: the revisits err by about a
    # metre, the nearby relations by centimetres.
    assert groups["revisits"]["trans_mean"] > 0.5 > 0.1 > groups["nearby"]["trans_mean"]
    d = result.to_dict()
    assert d["nearby"] == groups["nearby"] and d["revisits"]["n"] == 3
    assert "revisits: 3" in result.format().splitlines()[-1]


def test_no_revisits_leaves_the_table_as_it_was() -> None:
    gt = _ground_truth()
    result = evaluate_relations(gt, _relations_of(gt, PAIRS))
    assert result.split()["revisits"] == {"n": 0, "trans_mean": None, "rot_mean": None}
    assert len(result.format().splitlines()) == 6


def test_unmatched_relations_are_counted() -> None:
    gt = _ground_truth()
    t = gt.timestamps
    rel = Relations(
        t1=[t[0], t[1], t[2] + 5e-4, t[3] + 2e-3, t[0] - 100.0],
        t2=[t[1], t[2], t[3], t[4], t[1]],
        delta=relative(gt.poses[[0, 1, 2, 3, 0]], gt.poses[[1, 2, 3, 4, 1]]),
    )
    result = evaluate_relations(gt, rel)  # tolerance 1 ms: the 0.5 ms offset matches, 2 ms not
    assert result.n_relations == 5 and result.n_matched == 3 and result.n_unmatched == 2
    np.testing.assert_array_equal(result.matched, [True, True, True, False, False])
    assert len(result.trans_errors) == 3
    assert evaluate_relations(gt, rel, time_tolerance=3e-3).n_matched == 4


def test_a_loose_tolerance_that_matches_other_moments_is_warned_of() -> None:
    gt = _ground_truth()  # poses 0.4 s apart
    t = gt.timestamps
    rel = Relations(
        t1=[t[0], t[1], t[0] - 100.0],  # the last end lies 100 s before the trajectory
        t2=[t[1], t[2], t[1]],
        delta=relative(gt.poses[[0, 1, 0]], gt.poses[[1, 2, 1]]),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert evaluate_relations(gt, rel, time_tolerance=0.1).n_matched == 2  # none far: no warning
    with pytest.warns(OmnitofWarning, match=r"run.tum: 1 of 3 matched relations have an end up to 100 s"):
        result = evaluate_relations(gt, rel, time_tolerance=1e6, source="run.tum")
    assert result.n_matched == 3


def test_non_finite_poses_and_tolerances_are_refused_not_scored_as_nan() -> None:
    from omnitof.eval.trajectory import absolute_trajectory_error

    gt = _ground_truth()
    rel = _relations_of(gt, PAIRS)
    poses = gt.poses.copy()
    poses[5, 1] = np.nan
    with pytest.raises(InputError, match="run.tum: the trajectory's pose 5 is not finite"):
        evaluate_relations(Trajectory(gt.timestamps, poses), rel, source="run.tum")
    with pytest.raises(ValueError, match="time_tolerance must be >= 0 seconds, got nan"):
        evaluate_relations(gt, rel, time_tolerance=float("nan"))
    with pytest.raises(ValueError, match="the estimate's pose 5 is not finite"):
        absolute_trajectory_error(poses, gt.poses)
    with pytest.raises(ValueError, match=r"must be \(N >= 1, 3\) poses"):
        absolute_trajectory_error(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"poses must have shape \(N, 3\) \(x, y, theta\), got \(12, 2\)"):
        Trajectory(gt.timestamps, gt.poses[:, :2])
    assert absolute_trajectory_error(gt.poses, gt.poses).rmse == 0.0


def test_of_poses_sharing_a_stamp_the_last_is_scored_as_the_tum_file_keeps_it(tmp_path: Path) -> None:
    from omnitof.io.tum import read_tum, write_tum

    gt = _ground_truth()
    t = gt.timestamps
    # Two estimates at t[3]: the first wrong, the second (the latest) right.
    traj = Trajectory(np.insert(t, 3, t[3]), np.insert(gt.poses, 3, gt.poses[3] + [5.0, 5.0, 1.0], axis=0))
    rel = _relations_of(gt, [(2, 3), (3, 4)])
    in_memory = evaluate_relations(traj, rel)
    write_tum(tmp_path / "t.tum", traj)
    from_file = evaluate_relations(read_tum(tmp_path / "t.tum"), rel)
    np.testing.assert_allclose(in_memory.trans_errors, 0.0, atol=1e-9)
    np.testing.assert_allclose(from_file.trans_errors, in_memory.trans_errors, atol=1e-5)


def test_unsorted_trajectory_is_matched() -> None:
    gt = _ground_truth()
    order = np.random.default_rng(3).permutation(len(gt))
    shuffled = Trajectory(gt.timestamps[order], gt.poses[order])
    result = evaluate_relations(shuffled, _relations_of(gt, PAIRS))
    assert result.n_matched == len(PAIRS)
    np.testing.assert_allclose(result.trans_errors, 0.0, atol=1e-12)


def test_nothing_matched_is_an_error() -> None:
    gt = _ground_truth()
    rel = _relations_of(gt, PAIRS)
    shifted = Trajectory(gt.timestamps - T0, gt.poses)  # e.g. times since the start of the log
    with pytest.raises(InputError, match="ipc timestamps") as info:
        evaluate_relations(shifted, rel, source="run/trajectory.tum")
    assert "no relation timestamp" in str(info.value)
    assert info.value.path == Path("run/trajectory.tum")
    with pytest.raises(InputError, match="no relation timestamp"):
        evaluate_relations(Trajectory(np.zeros(0), np.zeros((0, 3))), rel)


def test_single_relation_std_is_nan_and_dict_is_serialisable() -> None:
    gt = _ground_truth()
    result = evaluate_relations(gt, _relations_of(gt, [(0, 1)]))
    assert math.isnan(result.trans_std)
    d = result.to_dict()
    assert d["trans_std"] is None and d["n_matched"] == 1
    json.dumps(d, allow_nan=False)
    assert yaml.safe_load(yaml.safe_dump(d)) == d
    assert len(result.to_dict(include_errors=True)["trans_errors"]) == 1
    # The printed table shows no "nan" either: a dash where summary.yaml has null.
    rows = result.format().splitlines()[2:]
    assert [row.split()[-1] for row in rows] == ["–"] * 4 and "nan" not in result.format()
    assert float(rows[0].split()[-2]) == pytest.approx(result.trans_mean, abs=1e-6)


def test_format_is_a_short_table() -> None:
    gt = _ground_truth()
    est = Trajectory(gt.timestamps, gt.poses + [0.1, 0.0, 0.0])
    text = evaluate_relations(est, _relations_of(gt, PAIRS)).format()
    lines = text.splitlines()
    assert len(lines) == 6
    assert "matched 7" in lines[0]
    assert lines[2].startswith("translational [m]") and lines[4].startswith("rotational [deg]")


def test_read_relations(tmp_path: Path) -> None:
    path = tmp_path / "r.relations"
    path.write_text(
        "# comment\n"
        "976052905.167303 976052911.885496 -0.056990 -0.128430 0 0 0 -1.682210\n"
        "\n"
        "976052896.784509 976052905.167303 -0.153130 -0.051420 0.0 0.0 0.0 -2.405850\n"
    )
    rel = read_relations(path)
    assert len(rel) == 2 and rel.source == str(path)
    assert rel.t1[0] == 976052905.167303 and rel.t2[1] == 976052905.167303
    np.testing.assert_array_equal(rel.delta[1], [-0.153130, -0.051420, -2.405850])


def test_a_byte_order_mark_before_the_first_row_is_dropped(tmp_path: Path) -> None:
    # Windows editors write one; it read as part of the first number (or the '#').
    path = tmp_path / "r.relations"
    path.write_bytes("\ufeff# made in Notepad\r\n1 2 0.1 0.2 0 0 0 0.3\r\n".encode())
    rel = read_relations(path)
    assert len(rel) == 1 and rel.t1[0] == 1.0


def test_a_bad_row_after_a_form_feed_is_named_by_its_own_line(tmp_path: Path) -> None:
    path = tmp_path / "r.relations"
    path.write_text("# made by a tool\x0cthat pages its output\n1 2 0.1 0.2 0 0 0 0.3\n1 2 0.1 x 0 0 0 0.3\n")
    with pytest.raises(InputError) as info:
        read_relations(path)
    assert info.value.line == 3


@pytest.mark.parametrize(
    ("row", "match"),
    [
        ("1 2 0.1 0.2 0 0 0", "8 numbers"),
        ("1 2 0.1 0.2 0 0 0 0.3 7", "8 numbers"),
        ("1 2 0.1 x 0 0 0 0.3", "y is 'x', not a finite decimal number"),
        ("1 2 0.1 0.2 0 0 nan 0.3", "pitch is 'nan', not a finite"),
        ("1 2 0.1 0.2 0 0.5 0 0.3", "planar"),
        # Python's float() reads "1_0" as 10 and "infinity" as inf; neither is what a writer meant.
        ("1 2 1_0 0.2 0 0 0 0.3", "x is '1_0', not a finite decimal number"),
        ("1 2 0.1 0.2 0 0 0 infinity", "yaw is 'infinity'"),
        ("1 1e400 0.1 0.2 0 0 0 0.3", "t2 is '1e400', not a finite"),
        # Values a broken writer leaves: their statistics printed as 300-digit numbers.
        ("1 2 1e308 0.2 0 0 0 0.3", r"x is 1e\+308, beyond ±1e\+09"),
        ("1 1.7e18 0.1 0.2 0 0 0 0.3", r"t2 1.7e\+18 is beyond ±1e\+12 s: relation timestamps are seconds"),
        ("1 2 0.1 0.2 0 0 0 1e200", r"yaw is 1e\+200, beyond ±1000"),
        ("5 5 0.1 0.2 0 0 0 0.3", "t1 and t2 are both 5.000000: a relation joins two different times"),
        # A field of 5000 digits is quoted, not echoed whole.
        ("1 2 0.1 " + "9" * 5000 + "x 0 0 0 0.3", r"y is '9{40}\.\.\.', not a finite"),
    ],
)
def test_bad_relation_rows(tmp_path: Path, row: str, match: str) -> None:
    path = tmp_path / "bad.relations"
    path.write_text(f"0 1 0 0 0 0 0 0\n{row}\n")
    with pytest.raises(InputError, match=match) as info:
        read_relations(path)
    assert info.value.line == 2 and info.value.path == path


def test_empty_relations_file(tmp_path: Path) -> None:
    (tmp_path / "e.relations").write_text("# nothing\n")
    with pytest.raises(InputError, match="empty"):
        read_relations(tmp_path / "e.relations")


DATA = os.environ.get("OMNITOF_DATA")


@pytest.mark.skipif(
    not DATA, reason="real-data test: set OMNITOF_DATA to the folder holding intel.relations"
)
def test_intel_relations_real_data() -> None:
    path = Path(DATA or "") / "intel.relations"
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    rel = read_relations(path)
    assert len(rel) == len(lines) == 2984

    # Synthesise a trajectory that fits a few relations exactly: for each chosen relation, a pose
    # A at t1 and A ⊕ δ_ref at t2. Choose relations whose two timestamps are fresh, and keep only
    # choices that cover no other relation (its error would not be zero by construction).
    rng = np.random.default_rng(5)
    times: dict[float, np.ndarray] = {}
    chosen: list[int] = []
    for k in rng.permutation(len(rel)):
        t1, t2 = rel.t1[k], rel.t2[k]
        if t1 in times or t2 in times or t1 == t2:
            continue
        trial = set(times) | {t1, t2}
        covered = np.isin(rel.t1, list(trial)) & np.isin(rel.t2, list(trial))
        if covered.sum() != len(chosen) + 1:
            continue
        a = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-np.pi, np.pi)])
        times[t1], times[t2] = a, compose(a, rel.delta[k])
        chosen.append(int(k))
        if len(chosen) == 5:
            break
    stamps = np.array(sorted(times))
    traj = Trajectory(stamps, np.array([times[t] for t in stamps]))

    result = evaluate_relations(traj, rel)
    assert result.n_relations == 2984 and result.n_matched == 5
    np.testing.assert_array_equal(np.flatnonzero(result.matched), sorted(chosen))
    assert result.trans_mean < 1e-9 and result.rot_mean < 1e-7

    # Moving one t2 pose by 10 cm gives exactly that error on its relation and zero elsewhere.
    k = chosen[0]
    moved = traj.poses.copy()
    moved[np.searchsorted(stamps, rel.t2[k])] += [0.06, 0.08, 0.0]
    result = evaluate_relations(Trajectory(stamps, moved), rel)
    errors = dict(zip(np.flatnonzero(result.matched), result.trans_errors, strict=True))
    assert errors[k] == pytest.approx(0.1, rel=1e-9)
    assert sum(errors.values()) == pytest.approx(0.1, rel=1e-9)


def test_errors_beyond_float_range_are_inf_without_numpy_warnings():
    # A relation 1e308 m long: its square overflows. The statistics that overflow say inf (the
    # squares' spread nan), quietly, where numpy printed eight lines of RuntimeWarning before.
    import warnings

    est = Trajectory(np.array([10.0, 11.0, 12.0]), np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]))
    rel = Relations(np.array([10.0, 11.0]), np.array([11.0, 12.0]), np.array([[1e308, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = evaluate_relations(est, rel)
        both = evaluate_relations(est, Relations(rel.t1, rel.t2, np.array([[1e308, 0.0, 0.0], [-1e308, 0.0, 0.0]])))
        assert both.split()["nearby"]["trans_mean"] == math.inf and both.to_dict()["nearby"]["n"] == 2
    assert result.trans_mean == 5e307 and result.trans_std == math.inf and result.trans2_mean == math.inf
    assert math.isnan(result.trans2_std) and result.rot_mean == 0.0
    assert list(result.trans_errors) == [1e308, 0.0]


def test_the_printed_table_keeps_its_columns_apart_for_any_error():
    # A diverged run's squared error (4.6e5 m²) ran into its std: "462044.206789944552.690425".
    from omnitof.eval.relations import _cell

    for value in (0.0123, 552.690425, 462044.206789944, 4.62e11, math.inf):
        cell = _cell(value)
        assert len(cell) == 12 and cell[0] == " " and float(cell) == pytest.approx(value, rel=1e-5)
    assert _cell(0.0123).strip() == "0.012300" and _cell(math.nan).strip() == "–"
