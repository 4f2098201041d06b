"""Odometry that no robot makes (omnitof.slam.odometry_faults): frozen wheels and jumps, found,
repaired, and the runs they would have ruined mapped."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import yaml

from omnitof.cli import main
from omnitof.geometry import compose, relative, wrap_angle
from omnitof.io.carmen import read_carmen, write_carmen
from omnitof.io.tum import read_tum
from omnitof.slam.odometry_faults import (
    OdometryWarning,
    frozen_odometry,
    odometry_jumps,
    repair_odometry,
    without_jumps,
)

N = 300  # scans of the simulated loop: 30 s, two corners


@pytest.fixture(scope="module")
def loop(corridor_loop):
    return corridor_loop.slice(0, N)


def _reset_at(scans, k: int):
    """The odometry as a base driver restarted before scan k gives it: from scan k on it starts
    again at (0, 0, 0)."""
    odometry = scans.odometry.copy()
    odometry[k:] = relative(odometry[k], odometry[k:])
    return dataclasses.replace(scans, odometry=odometry)


def _run(tmp_path, scans, name: str, *extra: str):
    log = tmp_path / f"{name}.log"
    write_carmen(log, scans)
    out = tmp_path / name
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["slam", str(log), "--out", str(out), "--preset", "laser180-scanmatch", "--particles", "5",
                     "--quiet", *extra]) == 0
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    return summary, [w for w in caught if issubclass(w.category, OdometryWarning)], read_tum(out / "trajectory.tum")


def _error(trajectory, truth) -> float:
    """Mean distance (m) to the truth, both seen from their first pose (a run whose odometry is
    estimated starts at its own origin)."""
    mine, true = relative(trajectory.poses[0], trajectory.poses), relative(truth[0], truth)
    return float(np.mean(np.hypot(*(mine[:, :2] - true[:, :2]).T)))


def test_the_simulated_wheels_neither_freeze_nor_jump_even_across_a_gap(loop):
    assert not frozen_odometry(loop) and odometry_jumps(loop) == []
    # 3 s of scans lost: the robot moved 1 m meanwhile, which is no jump.
    keep = np.r_[0:100, 130:N]
    gapped = dataclasses.replace(loop, timestamps=loop.timestamps[keep], ranges=loop.ranges[keep],
                                 odometry=loop.odometry[keep], ground_truth=loop.ground_truth[keep])
    step = np.hypot(*(gapped.odometry[100, :2] - gapped.odometry[99, :2]))
    assert step > 0.5 and odometry_jumps(gapped) == []


def test_a_reset_is_found_and_taken_as_no_motion(loop):
    reset = _reset_at(loop, 150)
    jumps = odometry_jumps(reset)
    assert [j.scan for j in jumps] == [150]
    assert jumps[0].metres == pytest.approx(np.hypot(*reset.odometry[149, :2]), rel=1e-12)
    assert jumps[0].seconds == pytest.approx(loop.timestamps[150] - loop.timestamps[149])
    repaired = without_jumps(reset.odometry, jumps)
    # Every step but the jump is the wheels' own; the jump's is no motion.
    before, after = (relative(o[:-1], o[1:]) for o in (loop.odometry, repaired))
    np.testing.assert_allclose(np.delete(after, 149, axis=0)[:, :2], np.delete(before, 149, axis=0)[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(np.delete(after - before, 149, axis=0)[:, 2]), 0.0, atol=1e-9)
    np.testing.assert_allclose(after[149], 0.0, atol=1e-12)
    # A spike (one pose 100 m off and back) is two jumps, and the poses around it are kept.
    spike = loop.odometry.copy()
    spike[200] = compose(spike[200], np.array([100.0, 0.0, 0.0]))
    spiked = dataclasses.replace(loop, odometry=spike)
    assert [j.scan for j in odometry_jumps(spiked)] == [200, 201]
    np.testing.assert_allclose(without_jumps(spike, odometry_jumps(spiked))[:200], loop.odometry[:200])


def test_frozen_odometry_is_set_aside_with_a_warning(loop):
    frozen = dataclasses.replace(loop, odometry=np.zeros_like(loop.odometry))
    with pytest.warns(OdometryWarning, match=r"never moves over its 300 scans \(every pose is \(0, 0, 0\)\)"):
        repaired, record = repair_odometry(frozen, "x.log")
    assert record == {"frozen": True} and not repaired.odometry_known
    assert repaired.odometry_rule.startswith("none: the input's never moved")
    # Wheels that moved by a millimetre over the log are not frozen; one scan is no motion at all.
    nudged = frozen.odometry.copy()
    nudged[-1, 0] = 1e-3
    assert not frozen_odometry(dataclasses.replace(frozen, odometry=nudged))
    assert not frozen_odometry(frozen.slice(0, 1))


def test_a_run_on_frozen_or_reset_wheels_maps_as_on_good_ones(tmp_path, loop):
    _, _, good = _run(tmp_path, loop, "good")
    summary, warned, frozen = _run(tmp_path, dataclasses.replace(loop, odometry=np.zeros_like(loop.odometry)),
                                   "frozen")
    assert len(warned) == 1 and summary["input"]["odometry_repair"] == {"frozen": True}
    assert summary["input"]["odometry"].startswith("estimated from the scans")
    summary, warned, reset = _run(tmp_path, _reset_at(loop, 150), "reset")
    assert len(warned) == 1 and "before scan 150" in str(warned[0].message)
    assert [j["scan"] for j in summary["input"]["odometry_repair"]["jumps"]] == [150]
    # Unrepaired, the reset puts the second half of the run metres away (the filter followed
    # it); repaired, both runs stay as near the truth as the run on good wheels.
    truth = loop.ground_truth
    assert np.hypot(*(_reset_at(loop, 150).odometry[-1, :2] - truth[-1, :2])) > 5.0
    assert _error(good, truth) < 0.15
    for run in (frozen, reset):
        assert _error(run, truth) < max(0.1, 2 * _error(good, truth))


def test_ignore_odometry_skips_the_repair(tmp_path, loop):
    summary, warned, _ = _run(tmp_path, _reset_at(loop, 150), "ignored", "--ignore-odometry")
    assert warned == [] and "odometry_repair" not in summary["input"]


def test_the_benchmark_logs_have_no_faults(data_dir):
    for name in ("intel.clf.bz2", "fr079.clf.bz2", "fr-clinic_robotlaser.clf.bz2"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scans = read_carmen(data_dir / name).scans
        assert not frozen_odometry(scans) and odometry_jumps(scans) == [], name
