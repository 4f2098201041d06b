"""Scan delay: odometry re-timed to when a scan was taken, and the delay estimated from the data."""

from __future__ import annotations

import numpy as np
import pytest

from omnitof.geometry import interpolate_poses, wrap_angle
from omnitof.sim.laser2d import World2D, beam_angles, simulate_scans
from omnitof.slam.timing import estimate_scan_delay, retime_odometry
from omnitof.types import ScanSequence, Trajectory

RATE_HZ = 5.0


def slalom(duration: float, rate_hz: float) -> Trajectory:
    """A robot weaving through a room: 0.3 m/s, turn rate 0.8·sin(2πt/4 s) rad/s, integrated
    finely so that the poses are exact to well below a millimetre."""
    dt = 1e-3
    t = np.arange(0.0, duration + dt / 2, dt)
    theta = 0.8 * 4.0 / (2 * np.pi) * (1.0 - np.cos(2 * np.pi * t / 4.0))
    x = 2.0 + np.concatenate([[0.0], np.cumsum(0.3 * np.cos(theta[:-1]) * dt)])
    y = 3.0 + np.concatenate([[0.0], np.cumsum(0.3 * np.sin(theta[:-1]) * dt)])
    fine = Trajectory(t, np.stack([x, y, wrap_angle(theta)], axis=1))
    stamps = np.arange(0.0, duration, 1.0 / rate_hz)
    return Trajectory(stamps, interpolate_poses(fine, stamps)), fine


def room() -> World2D:
    outline = np.array([[0, 0], [12, 0], [12, 7], [7, 7], [7, 9], [0, 9], [0, 0]], dtype=float)
    pillar = np.array([[8.5, 4.0], [9.1, 4.0], [9.1, 4.8], [8.5, 4.8], [8.5, 4.0]])
    shelf = np.array([[9.5, 1.0], [11.0, 1.0], [11.0, 1.4]])
    return World2D.from_polylines([outline, pillar, shelf])


def delayed_log(delay: float) -> tuple[ScanSequence, np.ndarray]:
    """Scans taken at the true poses, stamped `delay` seconds late, each logged with the
    odometry (noise-free) at its stamp; and the true poses."""
    scan_times, fine = slalom(24.0, RATE_HZ)
    truth = scan_times.poses
    angles = beam_angles(181, 180.0)
    ranges = simulate_scans(room(), truth, angles, max_range=15.0, range_noise=0.005, seed=3)
    odometry = interpolate_poses(fine, scan_times.timestamps + delay)
    scans = ScanSequence(scan_times.timestamps, ranges, angles, odometry, max_range=15.0, source="slalom")
    return scans, truth


def test_the_delay_is_found_from_the_scans_alone():
    scans, _ = delayed_log(0.13)
    estimate = estimate_scan_delay(scans, min_turn_deg=1.0)
    assert estimate.pairs >= 40
    assert abs(estimate.delay - 0.13) < 0.02, estimate.delay
    # The curve it was read from has its minimum there, and rises to both sides.
    best = int(np.argmin(estimate.heading_error))
    assert abs(estimate.delays[best] - 0.13) <= 0.02
    assert estimate.heading_error[0] > 2 * estimate.heading_error[best]
    assert estimate.heading_error[-1] > 2 * estimate.heading_error[best]


def irregular_log(delay: float) -> ScanSequence:
    """As `delayed_log`, along turns that never repeat (two turn rates of unrelated periods)."""
    dt = 1e-3
    t = np.arange(0.0, 40.0 + dt / 2, dt)
    rate = 0.5 * np.sin(2 * np.pi * t / 4.0) + 0.4 * np.sin(2 * np.pi * t / 6.7 + 1.0)
    theta = np.concatenate([[0.0], np.cumsum(rate[:-1] * dt)])
    x = 2.0 + np.concatenate([[0.0], np.cumsum(0.2 * np.cos(theta[:-1]) * dt)])
    y = 4.0 + np.concatenate([[0.0], np.cumsum(0.2 * np.sin(theta[:-1]) * dt)])
    fine = Trajectory(t, np.stack([x, y, wrap_angle(theta)], axis=1))
    stamps = np.arange(2.0, 36.0, 1.0 / RATE_HZ)  # odometry on both sides of every re-timed stamp
    angles = beam_angles(181, 180.0)
    ranges = simulate_scans(room(), interpolate_poses(fine, stamps), angles, max_range=15.0, range_noise=0.005, seed=3)
    return ScanSequence(stamps, ranges, angles, interpolate_poses(fine, stamps + delay), max_range=15.0,
                        source="irregular")


def test_clocks_that_disagree_by_seconds_are_found_beyond_a_lasers_delay():
    # A bag whose odometry is stamped by another clock, 1.7 s ahead: beyond the ±0.3 s of a
    # laser's own delay the estimate searches on, and finds it.
    estimate = estimate_scan_delay(irregular_log(1.7), min_turn_deg=1.0)
    assert abs(estimate.delay - 1.7) < 0.02, estimate.delay
    assert estimate.delays[0] < -5 and estimate.delays[-1] > 5
    # A laser's own delay is found as before, without the wider search.
    small = estimate_scan_delay(irregular_log(0.12), min_turn_deg=1.0)
    assert abs(small.delay - 0.12) < 0.02 and small.delays[-1] < 0.31


def test_a_delay_that_turns_to_a_rhythm_is_not_guessed():
    # The slalom turns with a period of 4 s: 1.5 s and 1.5 - 4 s explain its turns alike.
    scan_times, fine = slalom(30.0, RATE_HZ)
    keep = scan_times.timestamps < 24.0
    stamps, angles = scan_times.timestamps[keep], beam_angles(181, 180.0)
    ranges = simulate_scans(room(), scan_times.poses[keep], angles, max_range=15.0, range_noise=0.005, seed=3)
    scans = ScanSequence(stamps, ranges, angles, interpolate_poses(fine, stamps + 1.5), max_range=15.0)
    with pytest.raises(ValueError, match="as well at a delay of .* as at .*the robot turns to a rhythm"):
        estimate_scan_delay(scans, min_turn_deg=1.0)


def test_no_delay_is_estimated_as_none():
    scans, _ = delayed_log(0.0)
    assert abs(estimate_scan_delay(scans, min_turn_deg=1.0).delay) < 0.02


@pytest.mark.parametrize("scans, reason", [
    (1, "slalom: no scan pair taken while turning (by 1° or more) to estimate the scan delay from"),
    (20, "slalom: only 19 of the 19 scan pairs taken while turning match well; too few (20 needed) to estimate a "
         "scan delay"),  # every pair of the slalom turns, and matches
])
def test_a_log_too_short_for_a_delay_says_why(scans, reason):
    # A log of 1-3 scans was told "only 0 scan pairs taken while turning match well".
    log, _ = delayed_log(0.0)
    with pytest.raises(ValueError) as info:
        estimate_scan_delay(log.slice(0, scans), min_turn_deg=1.0)
    assert str(info.value) == reason


def test_retimed_odometry_is_where_the_robot_was():
    scans, truth = delayed_log(0.13)
    retimed = retime_odometry(scans, 0.13)
    inner = slice(2, -2)  # the ends are held, not extrapolated
    before = np.abs(wrap_angle(scans.odometry[inner, 2] - truth[inner, 2])).max()
    after = np.abs(wrap_angle(retimed.odometry[inner, 2] - truth[inner, 2])).max()
    assert before > np.radians(3.0)
    assert after < 0.1 * before
    assert np.abs(retimed.odometry[inner, :2] - truth[inner, :2]).max() < 0.005
    assert retimed.ranges is scans.ranges  # only the odometry changes
    assert retime_odometry(scans, 0.0) is scans


@pytest.mark.parametrize("jitter", ["swapped", "shared"])
def test_jittering_timestamps_are_refused(jitter):
    # A stamp shared by two scans with different poses is as ambiguous as a step back.
    scans, _ = delayed_log(0.1)
    stamps = scans.timestamps.copy()
    if jitter == "swapped":
        stamps[10], stamps[11] = stamps[11], stamps[10]
    else:
        stamps[11] = stamps[10]
    jittery = ScanSequence(stamps, scans.ranges, scans.angles, scans.odometry, max_range=15.0, source="jittery")
    with pytest.raises(ValueError, match="jittery: timestamps do not increase"):
        retime_odometry(jittery, 0.1)
    with pytest.raises(ValueError, match="jittery: timestamps do not increase"):
        estimate_scan_delay(jittery)


def test_slam_command_estimates_and_records_the_delay(tmp_path, capsys):
    import yaml

    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen

    scans, _ = delayed_log(0.13)
    log = tmp_path / "slalom.clf"
    write_carmen(log, scans)
    out = tmp_path / "run"
    assert main(["slam", str(log), "--out", str(out), "--preset", "sim2d", "--particles", "5",
                 "--scan-delay", "auto", "--quiet"]) == 0
    assert "scan delay estimated from" in capsys.readouterr().out
    recorded = yaml.safe_load((out / "summary.yaml").read_text())["input"]["scan_delay"]
    assert abs(recorded["seconds"] - 0.13) < 0.02 and recorded["estimated_from_pairs"] >= 20


def test_slam_command_refuses_a_delay_as_long_as_the_log(tmp_path, capsys):
    """A delay of the log's whole length (seconds typed for milliseconds) read every scan's
    odometry beyond the log's end: one scan integrated, and no word of why."""
    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen

    scans, _ = delayed_log(0.0)
    first = scans.timestamps < scans.timestamps[0] + 4.0  # a short log: ±10 s is refused anyway
    log = tmp_path / "log.clf"
    write_carmen(log, ScanSequence(scans.timestamps[first], scans.ranges[first], scans.angles, scans.odometry[first],
                                   max_range=15.0))
    span = float(np.ptp(scans.timestamps[first]))
    for delay in (span + 1.0, -(span + 1.0)):
        assert main(["slam", str(log), "--out", str(tmp_path / "run"), "--scan-delay", f"{delay:g}", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert f"is as long as the log itself ({span:.3g} s of scans)" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "run").exists()

@pytest.mark.filterwarnings("ignore:.*timestamps are earlier than the one before")
def test_slam_command_refuses_a_delay_for_a_jittering_clock(tmp_path, capsys):
    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen

    scans, _ = delayed_log(0.0)
    stamps = scans.timestamps.copy()
    stamps[10], stamps[11] = stamps[11], stamps[10]
    log = tmp_path / "jitter.clf"
    write_carmen(log, ScanSequence(stamps, scans.ranges, scans.angles, scans.odometry, max_range=15.0))
    assert main(["slam", str(log), "--out", str(tmp_path / "run"), "--scan-delay", "0.1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--scan-delay" in err and "timestamps do not increase" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit):
        main(["slam", str(log), "--out", str(tmp_path / "run"), "--scan-delay", "soon"])
    assert "expected seconds or 'auto'" in capsys.readouterr().err


def run_slam_command(tmp_path, scans, *flags):
    """`omnitof slam` on `scans` written as a CARMEN log; (summary's scan_delay, stdout lines)."""
    import yaml

    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen

    log = tmp_path / "log.clf"
    write_carmen(log, scans)
    out = tmp_path / "run"
    assert main(["slam", str(log), "--out", str(out), "--preset", "sim2d", "--particles", "3", "--quiet",
                 *flags]) == 0
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    return summary["input"]["scan_delay"], summary


def test_the_delay_is_estimated_by_default(tmp_path, capsys):
    scans, _ = delayed_log(0.13)
    recorded, summary = run_slam_command(tmp_path, scans)
    assert "scan delay estimated from" in capsys.readouterr().out
    assert abs(recorded["seconds"] - 0.13) < 0.02 and recorded["estimated_from_pairs"] >= 20
    assert recorded["how"] == "default --scan-delay auto: estimated from the log"
    assert summary["input"]["max_range"] == {"metres": 15.0, "rule": "ROBOTLASER1 maximum_range field"}
    assert summary["input"]["odometry"] == "the ROBOTLASER1 messages' robot poses"


def test_a_given_delay_overrides_the_default(tmp_path, capsys):
    scans, _ = delayed_log(0.13)
    recorded, _ = run_slam_command(tmp_path, scans, "--scan-delay", "0")
    assert recorded == {"seconds": 0.0, "how": "--scan-delay: given"}
    assert "scan delay" not in capsys.readouterr().out


@pytest.mark.filterwarnings("ignore:.*timestamps are earlier than the one before")
def test_no_delay_where_the_clock_jitters(tmp_path, capsys):
    # The run goes on with delay 0 and says why, on the terminal and in the summary.
    scans, _ = delayed_log(0.0)
    stamps = scans.timestamps.copy()
    stamps[10], stamps[11] = stamps[11], stamps[10]
    jittery = ScanSequence(stamps, scans.ranges, scans.angles, scans.odometry, max_range=15.0)
    recorded, _ = run_slam_command(tmp_path, jittery)
    assert "scan delay 0 s: not estimated" in capsys.readouterr().out
    assert recorded["seconds"] == 0.0 and "timestamps do not increase" in recorded["reason"]
    assert recorded["how"] == "default --scan-delay auto: not estimated, so none applied"


def test_no_delay_without_turns(tmp_path, capsys):
    scans, _ = delayed_log(0.0)
    straight = scans.odometry.copy()
    straight[:, 2] = 0.0  # the odometry never turns: no scan pair to estimate from
    recorded, _ = run_slam_command(tmp_path, ScanSequence(scans.timestamps, scans.ranges, scans.angles,
                                                          straight, max_range=15.0), "--scan-delay", "auto")
    assert "scan delay 0 s: not estimated" in capsys.readouterr().out
    # Not "only 0 scan pairs taken while turning match well", as before.
    assert recorded["seconds"] == 0.0 and recorded["reason"].endswith(
        "log.clf: no scan pair taken while turning (by 3° or more) to estimate the scan delay from")
    assert recorded["how"] == "--scan-delay: not estimated, so none applied"


def test_the_delay_is_found_in_a_log_of_held_odometry(tmp_path):
    # A CARMEN log whose FLASER messages carry the last ODOM pose (10 Hz, so up to 0.14 s old:
    # the ACES log's habit) over a true scan delay of 0.13 s. The reader interpolates the ODOM
    # messages to each scan's stamp, and the estimate then finds the delay; on the held poses
    # themselves it cannot, as their age changes from scan to scan.
    import dataclasses
    import warnings

    import yaml

    from omnitof.cli import main
    from omnitof.io.carmen import CarmenWarning, read_carmen

    delay = 0.13
    scan_times, fine = slalom(24.0, RATE_HZ)
    angles = beam_angles(181, 180.0)
    ranges = simulate_scans(room(), interpolate_poses(fine, scan_times.timestamps), angles, max_range=15.0,
                            range_noise=0.005, seed=3)
    stamps = scan_times.timestamps + delay
    # ODOM at 10 Hz on its own clock: each pose's age at the scan after it varies.
    odom_times = np.cumsum(np.random.default_rng(4).uniform(0.06, 0.14, 240))
    odom_times = odom_times[odom_times < fine.timestamps[-1]]
    odom_poses = interpolate_poses(fine, odom_times)
    events = sorted([(t, 0, j) for j, t in enumerate(odom_times)] + [(t, 1, k) for k, t in enumerate(stamps)])
    lines, held, last = [], [], None
    for t, kind, i in events:
        if kind == 0:
            last = odom_poses[i]
            lines.append("ODOM {:.6f} {:.6f} {:.6f} 0.3 0 0 {:.6f} h 0".format(*last, t))
        elif last is not None and t <= odom_times[-1]:
            pose = " ".join(f"{v:.6f}" for v in last)
            r = " ".join(f"{v:.3f}" for v in np.where(np.isfinite(ranges[i]), ranges[i], 80.0))
            lines.append(f"FLASER 181 {r} {pose} {pose} {t:.6f} h 0")
            held.append(last)
    path = tmp_path / "held.clf"
    path.write_text("\n".join(lines) + "\n")
    with pytest.warns(CarmenWarning, match="carries the last ODOM pose"):
        scans = read_carmen(path).scans
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        found = estimate_scan_delay(scans, min_turn_deg=1.0)
        as_logged = estimate_scan_delay(dataclasses.replace(scans, odometry=np.array(held)), min_turn_deg=1.0)
    assert abs(found.delay - delay) < 0.02, found.delay
    assert as_logged.heading_error.min() > 2 * found.heading_error.min()
    assert abs(as_logged.delay - delay) > 0.02, as_logged.delay  # the held poses hide the delay
    # The run's summary says how the odometry was found.
    out = tmp_path / "run"
    with pytest.warns(CarmenWarning, match="carries the last ODOM pose"):
        assert main(["slam", str(path), "--out", str(out), "--preset", "sim2d", "--particles", "2", "--quiet"]) == 0
    rule = yaml.safe_load((out / "summary.yaml").read_text())["input"]["odometry"]
    assert rule.startswith("interpolated from ODOM at each scan's timestamp: the FLASER messages carry the last ODOM pose")
