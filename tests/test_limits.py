"""What a configuration implies for a log, checked before a run (omnitof.slam.limits): the
memory estimate against a measured run, refusals that name the number and the setting."""

from __future__ import annotations

import numpy as np
import pytest

from omnitof import _core
from omnitof.errors import ConfigError, InputError, ResourceError
from omnitof.slam.config import load_config
from omnitof.slam.limits import (
    MAP_CELL_BYTES,
    available_memory,
    check_limits,
    check_memory,
    estimate_memory,
    map_extent,
)


@pytest.fixture(scope="module")
def loop(corridor_loop):
    return corridor_loop.slice(0, 300)


def test_extent_holds_every_end_point_and_no_more(loop):
    cfg = load_config(preset="sim2d")
    x0, y0, x1, y1 = map_extent(loop, cfg)
    # Independently: every finite reading within the map's reach, at its pose.
    reach = min(cfg.map.max_range, loop.max_range)
    pts = []
    for i in range(len(loop)):
        r, a = loop.scan_ranges(i).astype(float), loop.scan_angles(i)
        ok = np.isfinite(r)
        th = loop.odometry[i, 2] + loop.sensor_pose[2] + a[ok]
        sx = loop.odometry[i, 0] + np.cos(loop.odometry[i, 2]) * loop.sensor_pose[0]
        sy = loop.odometry[i, 1] + np.sin(loop.odometry[i, 2]) * loop.sensor_pose[0]
        rr = np.minimum(r[ok], reach)
        pts.append(np.column_stack([sx + rr * np.cos(th), sy + rr * np.sin(th)]))
    pts = np.concatenate(pts + [loop.odometry[:, :2]])
    assert np.allclose([x0, y0], pts.min(axis=0), atol=0.15) and np.allclose([x1, y1], pts.max(axis=0), atol=0.15)


def test_estimate_counts_the_map_cells_and_the_particles(loop):
    cfg = load_config(preset="sim2d", overrides={"filter": {"particles": 10}})
    est = estimate_memory(loop, cfg)
    cols, rows = est.cells
    x0, y0, x1, y1 = map_extent(loop, cfg)
    assert cols == pytest.approx((x1 - x0) / 0.05, abs=1.5) and rows == pytest.approx((y1 - y0) / 0.05, abs=1.5)
    assert est.map_bytes == cols * rows * MAP_CELL_BYTES
    more = estimate_memory(loop, load_config(preset="sim2d", overrides={"filter": {"particles": 20}}))
    assert more.particles_bytes == pytest.approx(2 * est.particles_bytes)
    # Each particle holds at least its window of pointers and its copies of the tiles one scan
    # writes (a scan of this loop has its end points in a few dozen tiles).
    window = np.ceil(cols / 16) * np.ceil(rows / 16) * 8
    per_particle = est.particles_bytes / 10
    assert window + 10 * _core.ParticleFilter.tile_bytes() < per_particle < window + 200 * _core.ParticleFilter.tile_bytes()


def test_a_map_that_cannot_fit_is_refused_naming_the_resolution(loop):
    cfg = load_config(preset="sim2d", overrides={"map": {"resolution": 0.001}})
    need = estimate_memory(loop, cfg).total
    assert need > 1e9  # 1 mm cells over the loop: billions of bytes
    with pytest.raises(ResourceError, match=r"map\.resolution 0\.001 m: .* cells, and the run would need about .* GB; "
                       r"the machine has 500 MB available \(choose a coarser map\.resolution\)"):
        check_memory(loop, cfg, available=500e6)
    assert check_memory(loop, cfg, available=2 * need).total == need


def test_particles_that_cannot_fit_are_refused_naming_the_particles(loop):
    cfg = load_config(preset="sim2d", overrides={"filter": {"particles": 100_000}})
    est = estimate_memory(loop, cfg)
    assert est.particles_bytes > est.map_bytes
    with pytest.raises(ResourceError, match=r"filter\.particles 100000: the particles' maps would need about .* GB"):
        check_memory(loop, cfg, available=1e9)


def test_available_memory_is_what_the_machine_reports():
    found = available_memory()
    assert found is None or 0 < found


def test_submaps_wider_than_the_back_end_allows_are_refused(loop):
    cfg = load_config(preset="laser180-scanmatch", overrides={"map": {"resolution": 0.001}})
    with pytest.raises(ConfigError, match=r"backend\.submap_length 6 m plus twice the reach 8 m .* cells wide at "
                       r"map\.resolution 0\.001 m; the back end allows 8192"):
        check_limits(loop, cfg, available=float("inf"))
    # Cells coarser than an eighth of the reach: refused by the core's submap at the first
    # submap (a traceback after the front end had run); now before the run.
    coarse = load_config(preset="laser180-scanmatch", overrides={"map": {"resolution": 0.5, "max_range": 3.0}})
    with pytest.raises(ConfigError, match=r"map\.resolution 0\.5 m is too coarse for the back end's submaps at a "
                       r"reach of 3 m \(map\.max_range 3 m"):
        check_limits(loop, coarse, available=float("inf"))


def test_non_finite_odometry_is_refused(loop):
    bad = loop.slice(0, 10)
    bad.odometry[4, 1] = np.nan
    with pytest.raises(InputError, match="odometry pose of scan 4 is not finite"):
        check_limits(bad, load_config(preset="sim2d"))


def test_echoes_beyond_map_max_range_are_refused_or_warned_of(loop):
    # Readings beyond map.max_range clear free space only: with every echo beyond it, a hall
    # logged at 20.5-70 m made a map without a wall, exit 0; with most beyond, most walls went
    # without a word.
    import dataclasses
    import warnings

    from omnitof.slam.limits import MapRangeWarning

    beams = loop.ranges.shape[1]
    ranges = np.tile(np.linspace(2.5, 6.5, beams, dtype=np.float32), (40, 1))
    ranges[:, 1::10] = np.inf  # no echo: neither within nor beyond
    far = dataclasses.replace(loop.slice(0, 40), ranges=ranges, source="hall.clf")
    for clear in (False, True):  # no-echo beams clearing free space make no wall either
        cfg = load_config(preset="sim2d", overrides={"map": {"max_range": 2.0, "clear_no_echo": clear}})
        with pytest.raises(ConfigError) as info:
            check_limits(far, cfg)
        assert str(info.value) == (
            "map.max_range 2 m: every echo of the 40 scans of hall.clf lies beyond it (the nearest at 2.5 m), and "
            "readings beyond it clear free space only: the map would have no wall; raise it, e.g. "
            "--set map.max_range=5 (half of the echoes lie within)")
    echoes = ranges[np.isfinite(ranges)]
    with pytest.warns(MapRangeWarning) as record:
        check_limits(far, load_config(preset="sim2d", overrides={"map": {"max_range": 4.0}}))
    share = int(100 * np.mean(echoes > 4.0))
    assert share == 62 and len(record) == 1 and str(record[0].message) == (
        f"hall.clf: {share} % of the echoes lie beyond map.max_range 4 m and leave no wall in the map (they "
        "clear free space only); --set map.max_range=5 keeps half of them")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_limits(far, load_config(preset="sim2d", overrides={"map": {"max_range": 5.0}}))  # 38 % beyond
        check_limits(loop, load_config(preset="sim2d"))  # the simulated corridors, within 8 m


def test_odometry_whose_extent_overflows_is_refused_as_too_big(loop, monkeypatch):
    # Finite poses 3.4e308 m apart: the extent is infinite, and so is the memory the map needs,
    # whether the machine's memory is known or not. (check_limits refuses such odometry sooner,
    # as too far out to resolve its motions: tests/test_anchor.py.)
    bad = loop.slice(0, 10)
    bad.odometry[4, 0], bad.odometry[5, 0] = 1.7e308, -1.7e308
    with pytest.raises(ResourceError, match=r"map\.resolution .* spans inf m.*has 1 TB available"):
        check_memory(bad, load_config(preset="sim2d"), available=1e12)
    monkeypatch.setattr("omnitof.slam.limits.available_memory", lambda: None)
    with pytest.raises(ResourceError, match=r"map\.resolution .* spans inf m.*no machine has that much"):
        check_memory(bad, load_config(preset="sim2d"))
    with pytest.raises(InputError, match="odometry pose of scan 4 lies at"):
        check_limits(bad, load_config(preset="sim2d"))
    huge = loop.slice(0, 10)
    huge.odometry[4, 0], huge.odometry[5, 0] = 1e11, -1e11  # resolved to 1.5e-5 m, and far beyond any machine
    with pytest.raises(ResourceError, match=r"map\.resolution .* spans 2e\+11 m.*no machine has that much"):
        check_limits(huge, load_config(preset="sim2d"))
    assert check_limits(loop, load_config(preset="sim2d")).total < 1e9  # unknown memory, finite need


def test_a_log_whose_odometry_leaps_100_km_is_refused_before_slam(tmp_path, loop, capsys):
    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen

    far = loop.slice(0, 20)
    far.odometry[10:, 0] += 1e5
    path = tmp_path / "leap.log"
    write_carmen(path, far)
    config = tmp_path / "fine.yaml"
    config.write_text("map:\n  resolution: 0.001\n")
    out = tmp_path / "out"
    code = main(["slam", str(path), "--out", str(out), "--config", str(config), "--preset", "sim2d", "--quiet",
                 "--scan-delay", "0"])
    assert code == 2 and not out.exists()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "map.resolution 0.001 m: the map of" in err and "1e+05 m ×" in err and "TB" in err
    assert "alone" not in err  # half the log leapt: no single pose to blame


def test_one_pose_far_from_the_rest_is_named_where_it_makes_the_map_too_big(loop):
    # One odometry x read as 1e7 made the map 10,000 km wide: the refusal named only the
    # resolution, which is not what the user must fix.
    cfg = load_config(preset="sim2d")
    one = loop.slice(0, 50)
    one.odometry[17, 0] = 1e7
    with pytest.raises(ResourceError, match=r"choose a coarser map\.resolution\); most of that span is the "
                       r"odometry pose of scan 17 alone, at \(1e\+07, [-0-9.e+]+\) m"):
        check_memory(one, cfg, available=500e6)


# --- memory while a run goes on (MemoryWatch) ----------------------------------------------


def _scripted(monkeypatch, available, resident):
    """Make the watch read `available` and `resident` (bytes), one value per call, in turn."""
    from omnitof.slam import limits

    a, r = iter(available), iter(resident)
    monkeypatch.setattr(limits, "available_memory", lambda: next(a))
    monkeypatch.setattr(limits, "_resident_bytes", lambda: next(r))


def test_the_watch_stops_where_less_is_left_than_the_last_steps_took(monkeypatch):
    from omnitof.slam.limits import HEADROOM_STEPS, MIN_HEADROOM, MemoryWatch

    mb = 10**6
    # The process grows 60 MB a step while the machine's free memory shrinks by as much from 2 GB.
    steps = 40
    resident = [100 * mb + 60 * mb * i for i in range(steps + 1)]
    available = [2048 * mb - 60 * mb * i for i in range(1, steps + 1)]
    _scripted(monkeypatch, available, resident)
    watch = MemoryWatch("the test run", "choose less")
    # Independently: the first step whose free memory is below both the floor and the growth of
    # the HEADROOM_STEPS steps before it (8 × 60 MB = 480 MB once 8 steps are seen).
    expected = next(i for i in range(1, steps + 1)
                    if available[i - 1] < max(MIN_HEADROOM, 60 * mb * min(i, HEADROOM_STEPS)))
    for step in range(1, expected):
        watch.check(step, steps)
    with pytest.raises(ResourceError) as err:
        watch.check(expected, steps)
    message = str(err.value)
    assert f"the test run stopped at step {expected} of {steps}" in message
    assert "(choose less)" in message and "holding" in message
    assert expected == 27  # 2048 − 60·27 = 428 MB < 480 MB; step 26 left 488 MB


def test_what_cannot_be_read_is_not_held_against_a_run(monkeypatch):
    from omnitof.slam.limits import MemoryWatch

    gb = 10**9
    # Nothing known of the machine: however fast the process grows, it is not stopped.
    _scripted(monkeypatch, [None] * 5, [10 * gb * i for i in range(6)])
    watch = MemoryWatch("x", "y")
    for step in range(1, 6):
        watch.check(step, 5)
    # The machine known but not the process: the floor still holds, and the message says
    # nothing of what the process holds.
    _scripted(monkeypatch, [10 * gb, 10**8], [None] * 3)
    watch = MemoryWatch("x", "y")
    watch.check(1, 2)
    with pytest.raises(ResourceError) as err:
        watch.check(2, 2)
    assert "only 100 MB of memory is left, and it needs 250 MB" in str(err.value)


def _short_after_two_looks(monkeypatch, left):
    """Plenty of memory until the watch has looked twice (it alone reads the resident memory),
    then `left` bytes."""
    from omnitof.slam import limits

    resident, looked = limits._resident_bytes, {"n": 0}

    def counted():
        looked["n"] += 1
        return resident()

    monkeypatch.setattr(limits, "_resident_bytes", counted)
    monkeypatch.setattr(limits, "available_memory", lambda: 20 * 10**9 if looked["n"] < 3 else left)


def test_slam_that_runs_out_of_memory_stops_with_one_line_and_writes_nothing(tmp_path, loop, monkeypatch, capsys):
    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen

    path = tmp_path / "loop.log"
    write_carmen(path, loop.slice(0, 120))
    _short_after_two_looks(monkeypatch, 100 * 10**6)
    out = tmp_path / "out"
    code = main(["slam", str(path), "--out", str(out), "--preset", "sim2d", "--particles", "5", "--quiet",
                 "--scan-delay", "0"])
    assert code == 2 and not out.exists()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "SLAM stopped at step 2 of" in err and "only 100 MB of memory is left" in err
    assert "filter.particles 5" in err


def test_the_3d_filter_that_runs_out_of_memory_stops_with_one_line(tmp_path, monkeypatch, capsys):
    from omnitof.cli import main

    bag = tmp_path / "room_bag"
    assert main(["simulate", "--world", "room", "--out", str(bag), "--max-frames", "30", "--quiet"]) == 0
    capsys.readouterr()
    _short_after_two_looks(monkeypatch, 50 * 10**6)
    out = tmp_path / "out"
    code = main(["slam", str(bag), "--filter", "3d", "--particles", "3", "--out", str(out), "--quiet"])
    assert code == 2 and not out.exists()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "the 3D filter stopped at step 2 of" in err and "filter3d.resolution" in err
