"""Tests of omnitof.eval.ate and `omnitof eval ate`: the absolute trajectory error after an
alignment, against transforms applied by hand and against a numerical least squares."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize

from omnitof.cli import main
from omnitof.errors import InputError, OmnitofWarning
from omnitof.eval.ate import evaluate_ate, fit_alignment
from omnitof.io.tum import write_tum
from omnitof.types import Trajectory

T0 = 1_700_000_000.0


def _walk(n: int, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = np.column_stack([np.cumsum(rng.normal(0, 1, n)), np.cumsum(rng.normal(0, 1, n)),
                             rng.uniform(-np.pi, np.pi, n)])
    return Trajectory(T0 + 0.1 * np.arange(n), poses)


def _moved(poses: np.ndarray, angle: float, t: tuple[float, float], scale: float = 1.0) -> np.ndarray:
    """`poses` under x ↦ scale·R(angle)·x + t, by homogeneous matrices (not omnitof's code)."""
    m = np.array([[scale * math.cos(angle), -scale * math.sin(angle), t[0]],
                  [scale * math.sin(angle), scale * math.cos(angle), t[1]], [0.0, 0.0, 1.0]])
    xy = (m @ np.column_stack([poses[:, :2], np.ones(len(poses))]).T).T[:, :2]
    heading = np.arctan2(np.sin(poses[:, 2] + angle), np.cos(poses[:, 2] + angle))
    return np.column_stack([xy, heading])


@settings(max_examples=60, deadline=None)
@given(n=st.integers(3, 40), seed=st.integers(0, 10_000), angle=st.floats(-math.pi, math.pi),
       tx=st.floats(-1e3, 1e3), ty=st.floats(-1e3, 1e3), scale=st.floats(0.5, 2.0))
def test_a_moved_trajectory_is_aligned_back_exactly(n, seed, angle, tx, ty, scale):
    estimate = _walk(n, seed)
    truth = Trajectory(estimate.timestamps, _moved(estimate.poses, angle, (tx, ty), scale))
    similar, _, _ = evaluate_ate(estimate, truth, align="similarity")
    assert similar.error.max < 1e-6 and similar.error.heading_mean_deg < 1e-6
    assert abs(similar.alignment.scale - scale) < 1e-9
    assert abs(math.remainder(similar.alignment.rotation - angle, 2 * math.pi)) < 1e-9
    rigid_truth = Trajectory(estimate.timestamps, _moved(estimate.poses, angle, (tx, ty)))
    rigid, _, _ = evaluate_ate(estimate, rigid_truth)  # rigid is the default
    assert rigid.error.max < 1e-6 and rigid.alignment.scale == 1.0
    np.testing.assert_allclose(rigid.alignment.translation, (tx, ty), atol=1e-6)


def test_the_alignment_is_the_least_squares_one():
    # Noisy positions: the closed form's cost against a numerical minimum over (θ, tx, ty[, s]).
    rng = np.random.default_rng(3)
    estimate = _walk(30, 5).poses
    truth = _moved(estimate, 0.7, (4.0, -2.0), 1.03)
    truth[:, :2] += rng.normal(0, 0.3, (30, 2))

    def cost(params, with_scale):
        angle, tx, ty = params[:3]
        scale = params[3] if with_scale else 1.0
        return float(np.sum((_moved(estimate, angle, (tx, ty), scale)[:, :2] - truth[:, :2]) ** 2))

    for with_scale in (False, True):
        a = fit_alignment(estimate, truth, scale=with_scale)
        closed = cost([a.rotation, *a.translation, a.scale], with_scale)
        numeric = minimize(cost, x0=[0.0, 0.0, 0.0, 1.0][:4 if with_scale else 3], args=(with_scale,),
                           method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 20000})
        assert closed <= numeric.fun + 1e-6
        assert closed == pytest.approx(numeric.fun, rel=1e-6)


def test_without_alignment_the_error_is_the_offset():
    estimate = _walk(20, 1)
    truth = Trajectory(estimate.timestamps, estimate.poses + [0.3, -0.4, 0.0])
    result, _, _ = evaluate_ate(estimate, truth, align="none")
    assert result.error.mean == pytest.approx(0.5) and result.error.max == pytest.approx(0.5)
    assert evaluate_ate(estimate, truth)[0].error.max < 1e-9  # a rigid alignment takes the offset out


def test_poses_pair_by_the_nearest_stamp_within_max_diff():
    truth = _walk(50, 2)
    # The estimate at twice the truth's rate, 4 ms late: every other pose lies 50 ms from any truth pose.
    stamps = T0 + 0.05 * np.arange(99) + 0.004
    estimate = Trajectory(stamps, np.repeat(truth.poses, 2, axis=0)[:99])
    with pytest.warns(OmnitofWarning, match="pairs of poses lie up to 0.004 s apart"):  # a walk at 14 m/s
        result, moved, paired = evaluate_ate(estimate, truth, align="none")
    assert result.n_paired == 50 and result.error.max == 0.0
    np.testing.assert_array_equal(paired, truth.poses)
    late = Trajectory(truth.timestamps + 0.02, truth.poses)
    with pytest.raises(InputError, match=r"est\.tum: no pose lies within 0\.01 s of a pose of the truth \(gt\.tum\)"):
        evaluate_ate(late, truth, sources=("est.tum", "gt.tum"))
    with pytest.warns(OmnitofWarning, match=r"50 of 50 pairs of poses lie up to 0\.02 s apart, in which the truth moves up to"):
        assert evaluate_ate(late, truth, max_diff=0.03)[0].n_paired == 50


def test_a_robot_that_stood_still_cannot_be_aligned():
    still = Trajectory(T0 + 0.1 * np.arange(5), np.tile([1.0, 2.0, 0.3], (5, 1)))
    with pytest.raises(InputError, match="all at one place.*--align none"):
        evaluate_ate(still, still)
    assert evaluate_ate(still, still, align="none")[0].error.max == 0.0


def test_eval_ate_command(tmp_path: Path, capsys):
    estimate = _walk(40, 7)
    truth = Trajectory(estimate.timestamps, _moved(estimate.poses, -1.2, (10.0, 5.0)))
    write_tum(tmp_path / "est.tum", estimate)
    write_tum(tmp_path / "gt.tum", truth)
    assert main(["eval", "ate", str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--figure",
                 str(tmp_path / "ate.png"), "--out", str(tmp_path / "ate.yaml")]) == 0
    out = capsys.readouterr().out
    assert "paired 40 of 40" in out and "rotation -68.755 deg" in out
    assert (tmp_path / "ate.png").stat().st_size > 0
    saved = yaml.safe_load((tmp_path / "ate.yaml").read_text())
    assert saved["n_paired"] == 40 and saved["rmse"] < 1e-6 and saved["alignment"]["rotation_deg"] == pytest.approx(-68.755, abs=1e-3)
    # Not aligned, the same files are metres apart.
    assert main(["eval", "ate", str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--align", "none"]) == 0
    assert "alignment: none" in capsys.readouterr().out
    # A truth on another clock: one line naming the file, exit 2.
    write_tum(tmp_path / "other.tum", Trajectory(truth.timestamps + 100.0, truth.poses))
    assert main(["eval", "ate", str(tmp_path / "est.tum"), str(tmp_path / "other.tum")]) == 2
    err = capsys.readouterr().err
    assert "est.tum: no pose lies within 0.01 s" in err and "other.tum" in err and "Traceback" not in err


# --- relative pose error (`eval rpe`: relations made from the truth) ---------------------------


def test_relations_along_the_truth_pair_poses_delta_apart():
    from omnitof.eval.relations import relations_along

    # A straight drive at 0.5 m per pose, 0.2 s apart: 1 m of path is two poses, 1 s five.
    truth = Trajectory(T0 + 0.2 * np.arange(11), np.column_stack([0.5 * np.arange(11), np.zeros(11), np.zeros(11)]))
    by_metre = relations_along(truth, 1.0, "m")
    assert len(by_metre) == 9
    np.testing.assert_allclose(by_metre.t2 - by_metre.t1, 0.4, atol=1e-6)
    np.testing.assert_allclose(by_metre.delta, [[1.0, 0.0, 0.0]] * 9)
    by_second = relations_along(truth, 1.0, "s")
    assert len(by_second) == 6 and np.allclose(by_second.delta[:, 0], 2.5)
    assert len(relations_along(truth, 3, "f")) == 8
    assert len(relations_along(truth, 100.0, "m")) == 0
    with pytest.raises(ValueError, match="unit"):
        relations_along(truth, 1.0, "km")


def test_rpe_of_a_trajectory_that_reads_every_step_long(tmp_path: Path, capsys):
    # The estimate drives the truth's straight line 2 % long: every 1 m of truth is 1.02 m of
    # estimate, a translational error of exactly 0.02 m and none in rotation.
    truth = Trajectory(T0 + 0.1 * np.arange(101), np.column_stack([0.1 * np.arange(101), np.zeros(101), np.zeros(101)]))
    long = Trajectory(truth.timestamps, truth.poses * [1.02, 1.0, 1.0])
    write_tum(tmp_path / "est.tum", long)
    write_tum(tmp_path / "gt.tum", truth)
    assert main(["eval", "rpe", str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--out", str(tmp_path / "rpe.yaml")]) == 0
    out = capsys.readouterr().out
    assert "per metre of path: 2.00 % of the distance, 0.000 deg/m" in out
    saved = yaml.safe_load((tmp_path / "rpe.yaml").read_text())
    assert saved["pairs"] == 91 and saved["trans_mean"] == pytest.approx(0.02) and saved["rot_mean_deg"] == pytest.approx(0.0)
    # Too long a delta, or a fraction of a pose: one line, exit 2.
    assert main(["eval", "rpe", str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--delta", "50"]) == 2
    assert "gt.tum: no two poses paired with the estimate lie 50 m of the truth's path apart" in capsys.readouterr().err
    assert main(["eval", "rpe", str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--delta", "1.5", "--unit", "f"]) == 2
    assert "whole number" in capsys.readouterr().err


def test_rpe_of_an_exact_estimate_is_zero_whichever_is_recorded_faster():
    # Motion capture at 120 Hz, SLAM at 10 Hz 3 ms late, exactly on the truth's path: relations
    # between truth poses that no estimate pose stands at put time offsets into the error
    # (0.52 % per metre before pairing first).
    from omnitof.eval.rpe import evaluate_rpe

    def line(stamps):
        return Trajectory(stamps, np.column_stack([stamps - T0, np.zeros(len(stamps)), np.zeros(len(stamps))]))

    mocap = line(T0 + np.arange(0, 30, 1 / 120))
    slam = line(T0 + 0.003 + np.arange(0, 30, 0.1))
    slam.poses[:, 0] -= 0.003  # on the truth's path at its own time: 1 m/s
    for estimate, truth in ((slam, mocap), (mocap, slam)):
        result = evaluate_rpe(estimate, truth, delta=1.0)
        assert result.n_paired == 300 and result.relations.trans_mean < 1e-9


def test_rpe_never_pairs_a_pose_with_itself_and_warns_of_gaps():
    from omnitof.errors import OmnitofWarning
    from omnitof.eval.relations import relations_along
    from omnitof.eval.rpe import evaluate_rpe

    truth = _walk(40, 4)
    for unit in ("m", "s"):
        tiny = relations_along(truth, 1e-12, unit)
        assert len(tiny) == 39 and np.all(tiny.t2 > tiny.t1)
    assert len(relations_along(truth, 1e30, "f")) == 0  # no integer overflow
    still = Trajectory(truth.timestamps, np.tile(truth.poses[:1], (40, 1)))
    with pytest.warns(OmnitofWarning, match="poses further apart than --delta"):
        assert evaluate_rpe(still, truth, delta=1e-9).relations.trans_mean > 0.1  # a robot that stood still is wrong
    # A truth with a 7 s gap: the pairs across it are named.
    gap = Trajectory(np.r_[truth.timestamps[:20], truth.timestamps[20:] + 7.0], truth.poses)
    with pytest.warns(OmnitofWarning, match=r"1 of 39 pairs 0\.1 s apart span up to 7\.1 s"):
        evaluate_rpe(gap, gap, delta=0.1, unit="s")
    with pytest.warns(OmnitofWarning, match=r"1 of 39 pairs 1 poses apart span up to 7\.1 s"):
        evaluate_rpe(gap, gap, delta=1, unit="f")
    with warnings.catch_warnings():  # a robot that stands still for a minute bridges no gap in metres
        warnings.simplefilter("error", OmnitofWarning)
        line = np.column_stack([0.1 * np.arange(40), np.zeros(40), np.zeros(40)])
        stop = Trajectory(np.r_[truth.timestamps[:20], truth.timestamps[20:] + 60.0], line)
        assert evaluate_rpe(stop, stop, delta=1.0).relations.trans_mean < 1e-9


def test_eval_outputs_are_checked_before_any_work(tmp_path: Path, capsys):
    estimate = _walk(20, 8)
    write_tum(tmp_path / "est.tum", estimate)
    write_tum(tmp_path / "gt.tum", estimate)
    before = (tmp_path / "est.tum").read_bytes()
    # --out into a missing folder: the figure is not drawn first.
    assert main(["eval", "ate", str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--figure",
                 str(tmp_path / "ate.png"), "--out", str(tmp_path / "no" / "ate.yaml")]) == 2
    assert "its folder does not exist" in capsys.readouterr().err and not (tmp_path / "ate.png").exists()
    # An output that is an input is refused, the input kept.
    for command in ("ate", "rpe"):
        assert main(["eval", command, str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--out",
                     str(tmp_path / "est.tum")]) == 2
        assert "is one of the inputs" in capsys.readouterr().err
    assert (tmp_path / "est.tum").read_bytes() == before
    assert main(["eval", "rpe", str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--unit", "f", "--delta", "1e19"]) == 2
    assert "gt.tum: no two poses paired with the estimate lie 1e+19 poses apart" in capsys.readouterr().err
