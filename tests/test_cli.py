"""The `omnitof` command: each subcommand on data the test makes, outputs checked, and user
mistakes reported as one line with exit status 2 (no traceback)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import omnitof
from omnitof.cli import main
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.eval.relations import read_relations
from omnitof.geometry import relative
from omnitof.io.carmen import write_carmen
from omnitof.io.rosmap import read_ros_map
from omnitof.io.tum import read_tum
from omnitof.slam.timing import retime_odometry


@pytest.fixture(scope="module")
def loop_log(tmp_path_factory, corridor_loop):
    path = tmp_path_factory.mktemp("log") / "loop.log.gz"
    write_carmen(path, corridor_loop)
    return path


@pytest.fixture(scope="module")
def loop_relations(tmp_path_factory, corridor_loop):
    # Reference relations from the ground truth, between scans 50 apart.
    t, gt = corridor_loop.timestamps, corridor_loop.ground_truth
    i = np.arange(0, len(t) - 50, 25)
    d = relative(gt[i], gt[i + 50])
    path = tmp_path_factory.mktemp("rel") / "loop.relations"
    rows = [f"{t[a]:.6f} {t[a + 50]:.6f} {x:.6f} {y:.6f} 0 0 0 {th:.6f}" for a, (x, y, th) in zip(i, d)]
    path.write_text("\n".join(rows) + "\n")
    return path


def test_slam_writes_the_results_folder(tmp_path, loop_log, loop_relations, corridor_loop, capsys):
    out = tmp_path / "run"
    code = main(["slam", str(loop_log), "--out", str(out), "--preset", "sim2d", "--particles", "10",
                 "--relations", str(loop_relations), "--quiet"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "scans 1597" in printed and "particles 10" in printed and "resamplings" in printed
    traj = read_tum(out / "trajectory.tum")
    assert np.allclose(traj.timestamps, corridor_loop.timestamps, atol=1e-6)
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    delay = summary["input"]["scan_delay"]["seconds"]  # estimated by default: the loop has none
    assert abs(delay) < 0.02
    odom = read_tum(out / "odometry.tum")  # the odometry re-timed by it
    assert np.allclose(odom.poses[:, :2], retime_odometry(corridor_loop, delay).odometry[:, :2], atol=1e-5)
    occ = read_ros_map(out / "map.yaml")
    assert occ.known.mean() > 0.2 and occ.resolution == 0.05
    meta = yaml.safe_load((out / "map.yaml").read_text())
    assert meta["image"] == "map.pgm" and meta["mode"] == "trinary"
    used = yaml.safe_load((out / "config.yaml").read_text())
    assert used["filter"]["particles"] == 10
    assert summary["run"]["scans"] == 1597
    assert summary["relations"]["n_matched"] == len(read_relations(loop_relations))
    assert (out / "map.png").stat().st_size > 10_000


def test_slam_of_a_file_whose_name_is_not_utf8_writes_every_output(tmp_path, corridor_loop, capsys):
    # A Latin-1 "café" reaches Python with a surrogate escape (PEP 383), which fonts and UTF-8
    # files do not take: the titles and summary.yaml show the byte as \xe9, and nothing is lost.
    # The folder is deep enough that its path is longer than the 80 characters at which PyYAML
    # folds a line (the path was split over two lines of summary.yaml).
    folder = tmp_path / ("a folder with a long name " * 3).strip() / "données ñ"
    folder.mkdir(parents=True)
    log = folder / os.fsdecode(b"caf\xe9.log")
    write_carmen(log, corridor_loop.slice(0, 300))
    out = tmp_path / "r\u00e9sultats 結果"
    assert main(["slam", str(log), "--out", str(out), "--preset", "sim2d", "--particles", "5", "--quiet"]) == 0
    capsys.readouterr()
    for name in ("map.png", "map.pgm", "trajectory.tum", "config.yaml"):
        assert (out / name).stat().st_size > 0
    text = (out / "summary.yaml").read_text(encoding="utf-8")
    assert "données ñ/caf\\xe9.log" in text  # other alphabets as they are, the stray byte escaped
    assert str(folder) + "/caf\\xe9.log" in text  # the whole path, on one line
    assert yaml.safe_load(text)["run"]["scans"] == 300


def test_a_reader_that_goes_away_stops_the_output_quietly(tmp_path, loop_relations, corridor_loop):
    # `omnitof eval relations … | head -3` ended with "omnitof: error: [Errno 32] Broken pipe".
    from omnitof.io.tum import write_tum
    from omnitof.types import Trajectory

    path = tmp_path / "gt.tum"
    write_tum(path, Trajectory(corridor_loop.timestamps, corridor_loop.ground_truth))
    proc = subprocess.Popen([sys.executable, "-m", "omnitof", "eval", "relations", str(path), str(loop_relations)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # long before the command has imported enough to print
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141, err  # 128 + SIGPIPE, as Unix tools end
    assert err == "", err


def test_a_config_of_a_few_fields_lies_over_the_inputs_default_preset(tmp_path, loop_log, capsys):
    # It replaced the preset: the fields it left out fell to the bare defaults (the paper's beam
    # model on a laser log), without a word.
    from omnitof.slam.config import SlamConfig, load_preset

    partial = tmp_path / "mine.yaml"
    partial.write_text("filter:\n  particles: 7\n")
    out = tmp_path / "run"
    assert main(["slam", str(loop_log), "--out", str(out), "--config", str(partial), "--max-scans", "150",
                 "--quiet"]) == 0
    capsys.readouterr()
    used = yaml.safe_load((out / "config.yaml").read_text())
    preset = yaml.safe_load(SlamConfig.model_validate(load_preset("laser180-scanmatch")).to_yaml())
    assert used["filter"]["particles"] == 7
    assert used["sensor_model"] == preset["sensor_model"] and used["backend"] == preset["backend"]
    assert used["sensor_model"]["model"] == "likelihood_field" and used["backend"]["enabled"] is True


def test_eval_relations_prints_the_metric(tmp_path, loop_relations, corridor_loop, capsys):
    from omnitof.io.tum import write_tum
    from omnitof.types import Trajectory

    path = tmp_path / "gt.tum"
    write_tum(path, Trajectory(corridor_loop.timestamps, corridor_loop.ground_truth))
    assert main(["eval", "relations", str(path), str(loop_relations)]) == 0
    printed = capsys.readouterr().out
    n = len(read_relations(loop_relations))
    assert f"matched {n}" in printed
    # Ground truth against its own relations: zero error (to the printed precision).
    trans_row = next(line for line in printed.splitlines() if line.startswith("translational [m]"))
    assert float(trans_row.split()[2]) < 1e-5


def test_config_prints_a_loadable_configuration(tmp_path, capsys):
    assert main(["config", "--preset", "paper", "--seed", "9"]) == 0
    text = capsys.readouterr().out
    data = yaml.safe_load(text)
    assert data["filter"]["particles"] == 200 and data["filter"]["seed"] == 9
    assert main(["config", "--list"]) == 0
    assert "laser180" in capsys.readouterr().out


def test_python_dash_m_runs_the_command(tmp_path):
    # The package's folder on the child's path, as the installed package would be.
    env = {**os.environ, "PYTHONPATH": str(Path(omnitof.__file__).parents[1])}
    ok = subprocess.run([sys.executable, "-m", "omnitof", "config", "--list"], capture_output=True, text=True,
                        env=env, cwd=tmp_path)
    assert ok.returncode == 0 and "laser180" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "omnitof", "config", "--preset", "nope"], capture_output=True,
                         text=True, env=env, cwd=tmp_path)
    assert bad.returncode == 2 and "unknown preset" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize(
    "argv, message",
    [
        (["slam", "MISSING.clf", "--out", "OUT"], "MISSING.clf"),
        (["config", "--preset", "nope"], "unknown preset"),
        (["config", "--particles", "0"], "filter.particles"),
        (["config", "--set", "filter.partcles=3"], "filter.partcles"),
        (["config", "--set", "particles=3"], "SECTION.FIELD"),
        (["eval", "relations", "none.tum", "none.relations"], "none.tum"),
        # The demo ran the 2D filter with the 3D preset's settings without a word.
        (["demo", "--preset", "tof3d", "--out", "OUT"], "--preset tof3d: the demo runs the 2D filter"),
    ],
)
def test_user_mistakes_are_one_line(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_malformed_log_names_the_line(tmp_path, capsys):
    log = tmp_path / "bad.clf"
    log.write_text("ODOM 0 0 0 0 0 0 1.0 host 0\nFLASER 3 1.0 2.0 0 0 0 0 0 0 2.0 host 0\n")
    assert main(["slam", str(log), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "bad.clf:2" in err
    assert not (tmp_path / "out" / "map.yaml").exists()


def test_demo_runs_and_writes_figures(tmp_path, capsys):
    # The whole pipeline on the room world (two laps, 17 m): simulate, calibrate, scans, SLAM,
    # 3D map, evaluation, report.
    out = tmp_path / "demo"
    assert main(["demo", "--world", "room", "--out", str(out), "--quiet"]) == 0
    assert "trajectory error" in capsys.readouterr().out
    for name in ("map.png", "map.yaml", "map.pgm", "trajectory.tum", "ground_truth.tum", "summary.yaml",
                 "report.md", "overlay.png", "map3d.ply", "map3d.png", "calibration.yaml", "fig3_depth.png",
                 "scan.png", "slice.png"):
        assert (out / name).exists(), name
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    ev = summary["demo"]["evaluation"]
    # Raw odometry drifts 0.14 m on average and ends 0.19 m off; SLAM stays within a few cm.
    assert ev["trajectory"]["odometry"]["final"] > 0.15
    assert ev["trajectory"]["slam"]["mean"] < 0.5 * ev["trajectory"]["odometry"]["mean"]
    assert ev["trajectory"]["slam"]["final"] < 0.05
    assert ev["floorplan"]["occupied_within_5cm"] > 0.5
    report = (out / "report.md").read_text()
    assert "Trajectory error" in report and "![map](map.png)" in report


def test_design_reports_the_default_rig_and_draws_it(tmp_path, capsys):
    from omnitof.sensor.camera import Camera
    from omnitof.sensor.design import default_rig, design_report

    figure = tmp_path / "regions.png"
    assert main(["design", "--figure", str(figure)]) == 0
    printed = capsys.readouterr().out
    rig = default_rig()
    camera, mirrors = rig.camera, rig.mirrors
    want = design_report(camera, mirrors).coverage
    assert f"{100 * want:.1f} %" in printed
    assert figure.stat().st_size > 5_000
    assert isinstance(camera, Camera)


@pytest.mark.parametrize("argv, message", [
    # Each printed the table, then a ValueError traceback or a table of nan.
    (["design", "--figure", "."], ".: is a folder; the figure is a file"),
    (["design", "--mirrors", "100"], "--mirrors 100 --tilt 56: mirror 'back-176.4deg' keeps no pixel"),
    (["design", "--tilt", "0.001"], "--mirrors 4 --tilt 0.001: mirror 'front' keeps no pixel"),
])
def test_design_refuses_what_it_cannot_measure_or_draw_before_printing(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert message in captured.err and "Traceback" not in captured.err
    assert captured.out == "" and list(tmp_path.iterdir()) == []


def test_slam_reads_a_laserscan_ros2_bag(tmp_path, corridor_loop, capsys):
    from omnitof.io.rosbag import write_laserscan_bag

    bag = tmp_path / "loop_bag"
    write_laserscan_bag(bag, corridor_loop.slice(0, 300))
    out = tmp_path / "run"
    assert main(["slam", str(bag), "--out", str(out), "--preset", "sim2d", "--particles", "5", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "scans 300" in printed
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    assert summary["input"]["kind"] == "rosbag"
    # With the bag's ground truth: the error after a rigid alignment too, no larger (least squares).
    te = summary["trajectory_error"]
    assert te["slam_rigid"]["rmse"] <= te["slam"]["rmse"] + 1e-12
    assert f"after a rigid alignment to the truth (the map's shape, not its placement): SLAM mean {te['slam_rigid']['mean']:.3f} m" in printed
    traj = read_tum(out / "trajectory.tum")
    assert len(traj) == 300


def test_slam_reads_odometry_from_tf_and_a_named_scan_topic(tmp_path, corridor_loop, capsys):
    # A robot that publishes its odometry only to tf, with its laser on a topic of its own name
    # beside a second one: --laser-topics names it; the odometry is found on /tf by itself.
    from omnitof.io.rosbag import write_laserscan_bag

    scans = corridor_loop.slice(0, 200)
    bag = tmp_path / "tf_bag"
    write_laserscan_bag(bag, scans, scan_topic="/front_scan", odometry_on_tf=True)
    assert quick_slam(bag, tmp_path / "run", "--laser-topics", "scan=/front_scan") == 0
    summary = yaml.safe_load((tmp_path / "run" / "summary.yaml").read_text())
    assert summary["input"]["odometry"] == ("interpolated from the transform odom → base_link on /tf at each "
                                            "scan's timestamp")
    odometry = read_tum(tmp_path / "run" / "odometry.tum")
    np.testing.assert_allclose(odometry.poses[:, :2], scans.odometry[:, :2], atol=1e-6)
    # The SLAM trajectory against the bag's ground truth: the run is a real one.
    assert summary["trajectory_error"]["slam"]["mean"] < 0.1
    capsys.readouterr()
    # The option reaches the reader: a topic the bag lacks is named as missing.
    assert quick_slam(bag, tmp_path / "y", "--laser-topics", "scan=/rear_scan") != 0
    assert "topic /rear_scan (sensor_msgs/msg/LaserScan or sensor_msgs/msg/MultiEchoLaserScan) is missing" in (
        capsys.readouterr().err)
    with pytest.raises(SystemExit) as exit_:
        main(["slam", str(bag), "--out", str(tmp_path / "x"), "--laser-topics", "scan=/front_scan,laser=/x"])
    assert exit_.value.code == 2 and "unknown role 'laser'" in capsys.readouterr().err


def test_ignore_odometry_estimates_it_from_the_scans_and_says_so(tmp_path, corridor_loop, capsys):
    from omnitof.io.rosbag import write_laserscan_bag

    bag = tmp_path / "bag"
    write_laserscan_bag(bag, corridor_loop.slice(0, 300))
    assert main(["slam", str(bag), "--out", str(tmp_path / "run"), "--preset", "laser180-scanmatch", "--particles",
                 "3", "--quiet", "--ignore-odometry"]) == 0
    assert "odometry estimated from the scans: 299 matched, 0 by the step before" in capsys.readouterr().out
    summary = yaml.safe_load((tmp_path / "run" / "summary.yaml").read_text())
    assert summary["input"]["odometry"].startswith("estimated from the scans (299 matched")
    assert summary["input"]["odometry"].endswith("none: set aside by --ignore-odometry")
    so = summary["input"]["scan_odometry"]
    assert (so["matched"], so["unmatched"]) == (299, 0) and 0 < so["keyframes"] < 299
    assert summary["input"]["scan_delay"]["how"] == "none: the odometry is the scans' own"
    # The estimate against the bag's ground truth: better than the simulated wheels it set aside.
    wheels = absolute_trajectory_error(corridor_loop.odometry[:300], corridor_loop.ground_truth[:300])
    assert summary["trajectory_error"]["odometry"]["mean"] < wheels.mean


def test_ignore_odometry_refuses_what_cannot_apply_to_an_estimate(tmp_path, short_log, capsys):
    assert quick_slam(short_log, tmp_path / "a", "--ignore-odometry") != 0  # quick_slam gives --scan-delay 0
    assert "--scan-delay: the odometry is estimated from the scans at their own stamps" in capsys.readouterr().err
    assert main(["slam", str(short_log), "--out", str(tmp_path / "b"), "--ignore-odometry", "--filter", "3d",
                 "--quiet"]) != 0
    assert "--ignore-odometry does not work with the 3D filter" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_laser_topics_on_a_carmen_log_is_refused(tmp_path, short_log, capsys):
    assert quick_slam(short_log, tmp_path / "run", "--laser-topics", "scan=/scan") != 0
    err = capsys.readouterr().err
    assert "--laser-topics needs a bag of LaserScan messages" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("option, value, message", [
    ("--scan-delay", "nan", "within"), ("--scan-delay", "inf", "within"), ("--scan-delay", "1e6", "within"),
    ("--scan-delay", "soon", "seconds or 'auto'"), ("--max-scans", "0", "at least 1"),
    ("--max-scans", "-5", "at least 1"), ("--max-scans", "1.5", "whole number"),
])
def test_slam_refuses_numbers_outside_their_domain(tmp_path, capsys, option, value, message):
    log = tmp_path / "x.clf"
    log.write_text("")
    with pytest.raises(SystemExit) as exit_:
        main(["slam", str(log), "--out", str(tmp_path / "out"), option, value])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert option in err and message in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def short_log(tmp_path_factory, corridor_loop):
    path = tmp_path_factory.mktemp("short") / "short.log"
    write_carmen(path, corridor_loop.slice(0, 150))
    return path


def quick_slam(log, out, *extra):
    return main(["slam", str(log), "--out", str(out), "--preset", "sim2d", "--particles", "3", "--quiet",
                 "--scan-delay", "0", *extra])


@pytest.mark.filterwarnings("ignore::omnitof.io.carmen.CarmenWarning")
def test_a_log_with_a_repeated_line_and_a_stamp_that_steps_back_runs_and_counts_them(tmp_path, short_log, capsys):
    # Before, the run died after SLAM in the TUM writer with a traceback, leaving half a folder.
    lines = short_log.read_text().splitlines(keepends=True)
    scans = [i for i, line in enumerate(lines) if line.startswith("ROBOTLASER1")]
    fields = lines[scans[100]].split()
    fields[-3] = f"{float(fields[-3]) - 0.5:.6f}"  # 0.5 s back: onto the stamp of scan 95
    lines[scans[100]] = " ".join(fields) + "\n"
    lines.insert(scans[40] + 1, lines[scans[40]])  # scan 40 logged twice
    log = tmp_path / "jitter.log"
    log.write_text("".join(lines))
    out = tmp_path / "run"
    from omnitof.errors import OmnitofWarning

    with pytest.warns(OmnitofWarning, match=r"trajectory\.tum: 1 of 150 poses share their timestamp"):  # said, not only counted
        assert quick_slam(log, out) == 0
    captured = capsys.readouterr()
    assert "scans 150" in captured.out and "Traceback" not in captured.err
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    assert summary["input"]["time_order"] == {"repeated_scans_dropped": 1, "equal_stamps": 0, "backward_steps": 1}
    assert summary["tum_poses_merged"] == 1  # scans 95 and 100 share a stamp: one row, scan 100's
    traj = read_tum(out / "trajectory.tum")
    assert len(traj) == 149 and np.all(np.diff(traj.timestamps) > 0)


def test_a_second_run_replaces_the_whole_folder(tmp_path, short_log, corridor_loop, capsys):
    # A bag with ground truth, then a CARMEN log without, into one folder: nothing of the
    # first run survives beside the second.
    from omnitof.io.rosbag import write_laserscan_bag

    bag = tmp_path / "bag"
    write_laserscan_bag(bag, corridor_loop.slice(0, 150))
    out = tmp_path / "run"
    assert quick_slam(bag, out) == 0
    assert (out / "ground_truth.tum").exists()
    assert quick_slam(short_log, out) == 0
    assert not (out / "ground_truth.tum").exists()
    assert yaml.safe_load((out / "summary.yaml").read_text())["input"]["kind"] == "carmen"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "run"]  # no hidden leftovers
    from omnitof.results import RESULT_FILES

    assert {p.name for p in out.iterdir()} <= RESULT_FILES


@pytest.mark.parametrize("case, message", [
    ("file", "is a file, not a folder"),
    ("under a file", "is a file, not a folder"),
    ("foreign folder", "holds files that are not results of omnitof (notes.txt)"),
    ("unwritable", "cannot create the results folder"),
    ("name too long", "cannot be the results folder: File name too long"),  # was a raw OSError
    # These three failed only after the whole run, when the finished folder was to replace them.
    ("mount point", "results: is a mount point: results are written by replacing the folder; give a folder "
                    "inside it, e.g. "),
    ("bind mount", "results: is a mount point"),  # os.path.ismount misses one within a file system
    ("immutable", "results: the folder cannot be replaced (Operation not permitted), and results are written "
                  "by replacing the folder: give another folder for the results"),
])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys, unreplaceable, case, message):
    # The log is malformed too: the output is checked first, so its error is the one reported.
    log = tmp_path / "bad.clf"
    log.write_text("ODOM 0 0 0 0 0 0 1.0 host 0\nFLASER 3 1.0 2.0 0 0 0 0 0 0 2.0 host 0\n")
    (tmp_path / "taken").write_text("a file")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    (tmp_path / "results").mkdir()  # a Docker volume, say
    if case in ("mount point", "bind mount", "immutable"):
        unreplaceable(tmp_path / "results", case)
    out = {"file": tmp_path / "taken", "under a file": tmp_path / "taken" / "run",
           "foreign folder": tmp_path / "mine", "unwritable": Path("/proc/omnitof-run"),
           "name too long": tmp_path / ("a" * 300)}.get(case, tmp_path / "results")
    assert quick_slam(log, out) == 2
    err = capsys.readouterr().err
    assert message in err and "bad.clf" not in err and err.count("\n") == 1
    assert (tmp_path / "taken").read_text() == "a file" and (tmp_path / "mine" / "notes.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.clf", "mine", "results", "taken"]


def test_a_path_the_file_system_refuses_is_named_once_before_its_problem(tmp_path, short_log, capsys):
    # OSError's own text put "[Errno 36] File name too long:" before the path, and repeated it.
    long = tmp_path / ("b" * 300)
    for argv in (["slam", str(long), "--out", str(tmp_path / "o")],
                 ["slam", str(short_log), "--relations", str(long), "--out", str(tmp_path / "o")],
                 ["eval", "relations", str(long), str(long)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"omnitof: error: {long}: ") and err.count(str(long)) == 1, err
        assert "File name too long" in err and "Errno" not in err and err.count("\n") == 1


def test_relations_that_do_not_parse_or_match_are_refused_before_slam(tmp_path, short_log, capsys):
    bad = tmp_path / "bad.relations"
    bad.write_text("1.0 2.0 0 0 0 0 0\n")
    other = tmp_path / "other.relations"
    other.write_text("5000.0 5001.0 1.0 0 0 0 0 0\n")  # times the log does not have
    out = tmp_path / "run"
    assert quick_slam(short_log, out, "--relations", str(bad)) == 2
    assert "bad.relations:1: relation rows need 8 numbers" in capsys.readouterr().err
    assert quick_slam(short_log, out, "--relations", str(other)) == 2
    captured = capsys.readouterr()
    assert "other.relations: no relation has both its timestamps among the scans" in captured.err
    assert "scans 150" not in captured.out and not out.exists()  # SLAM never ran


def test_a_log_where_no_beam_echoes_is_one_clear_error(tmp_path, short_log, capsys):
    lines = []
    for line in short_log.read_text().splitlines():
        if line.startswith("ROBOTLASER1"):
            f = line.split()
            n = int(f[8])
            f[9:9 + n] = [f[5]] * n  # every reading at the maximum range: no echo
            line = " ".join(f)
        lines.append(line + "\n")
    log = tmp_path / "blind.log"
    log.write_text("".join(lines))
    out = tmp_path / "run"
    assert quick_slam(log, out) == 2
    err = capsys.readouterr().err
    assert "blind.log: no beam of the 150 scans has an echo" in err and err.count("\n") == 1
    assert not out.exists()


def test_the_summary_line_names_the_scans_whose_odometry_the_check_replaced():
    from omnitof.cli import _summary_line

    stats = {"scans": 900, "integrated": 80, "seconds": 12.34, "particles": 30, "resamplings": 7}
    plain = _summary_line({**stats, "odometry_corrected_scans": []})
    assert plain == "scans 900 (integrated 80), time 12.3 s, particles 30, resamplings 7"
    assert _summary_line(stats) == plain  # a run without the check has no such entry
    one = _summary_line({**stats, "odometry_corrected_scans": [562]})
    assert one == plain + "; odometry replaced by the odometry check at 1 scan(s): 562"
    many = _summary_line({**stats, "odometry_corrected_scans": list(range(100, 107))})
    assert many.endswith("at 7 scan(s): 100, 101, 102, 103, 104, ...")
    # The back end's verdicts: a relocalisation onto an older map is named apart from slips.
    judged = [{"scan": 562, "verdict": "slip"}, {"scan": 2920, "verdict": "relocalised, spread"}]
    both = _summary_line({**stats, "odometry_corrected_scans": [562, 2920], "check_corrections": judged})
    assert both.endswith("at 2 scan(s): 562, 2920 (1 of them relocalised onto an older map: 2920)")


def test_only_omnitofs_own_warnings_read_as_omnitof_warnings():
    from omnitof.cli import _format_warning
    from omnitof.io.carmen import CarmenWarning

    assert _format_warning("3 scans dropped", CarmenWarning, "carmen.py", 1) == "omnitof: warning: 3 scans dropped\n"
    other = _format_warning("singular limits", UserWarning, "matplotlib/axes.py", 7)
    assert not other.startswith("omnitof:") and "matplotlib/axes.py" in other


@pytest.mark.parametrize("argv, message", [
    (["simulate", "--out", "OUT", "--seed", "-1"], "--seed: expected a seed in 0 … 2^63 - 1"),  # a traceback before
    (["demo", "--out", "OUT", "--seed", "-3"], "--seed: expected a seed"),
    (["slam", "LOG", "--out", "OUT", "--seed", "2e3"], "--seed: expected a whole number"),
    (["slam", "LOG", "--out", "OUT", "--height", "nan"], "--height: expected a finite number"),
    (["slam", "LOG", "--out", "OUT", "--map3d-every", "0"], "--map3d-every: expected at least 1"),
    (["scans", "BAG", "--out", "x.clf", "--band", "-0.1"], "--band: expected a number above 0"),
    (["eval", "relations", "a", "b", "--tolerance", "-1"], "--tolerance: expected a number of at least 0"),
    (["design", "--yaw", "1e308"], "--yaw: expected a number of at most 360"),
    # These three named the library's fields (n_mirrors, tilt_deg, elev_band_deg), not the options.
    (["design", "--mirrors", "2"], "--mirrors: expected at least 3"),
    (["design", "--mirrors", "1000"], "--mirrors: expected at most 360"),  # a table of nan before
    (["design", "--tilt", "90"], "--tilt: expected a number below 90"),
    (["design", "--band", "-5"], "--band: expected a number of at least 0"),
    (["simulate", "--out", "OUT", "--speed", "inf"], "--speed: expected a finite number"),
    (["calibrate", "render-targets", "--out", "OUT", "--boards", "0"], "--boards: expected at least 1"),
    # 100 000 boards rendered on for hours.
    (["simulate", "calibration", "--out", "OUT", "--boards", "100000"], "--boards: expected at most 1000"),
    (["calibrate", "plan-boards", "--boards", "1000000"], "--boards: expected at most 1000"),
    (["calibrate", "intrinsics", "x.png", "--out", "c.yaml", "--square", "0"], "--square: expected a number above 0"),
])
def test_every_command_refuses_numbers_outside_their_domain(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_the_demo_refuses_a_bad_configuration_before_any_work(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--particles", "0", "--quiet"]) == 2
    captured = capsys.readouterr()
    assert "filter.particles" in captured.err and "[1]" not in captured.out and not out.exists()


def test_running_out_of_memory_is_one_line_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    # Whatever asks for more memory than the machine has, past every field's bound: numpy's
    # MemoryError (as a path of 1e12 laps raised, before path.laps was bounded) is one line.
    def too_big(*args, **kwargs):
        raise MemoryError("Unable to allocate 58.2 TiB for an array with shape (1000000000000, 8)")

    monkeypatch.setattr("omnitof.sim.sequence.robot_path", too_big)
    out = tmp_path / "bag"
    assert main(["simulate", "--world", "room", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("omnitof: error: out of memory (Unable to allocate 58.2 TiB") and not out.exists()


@pytest.fixture(scope="module")
def tiny_tof_bag(tmp_path_factory):
    """A simulated ToF bag of three frames (omnitof simulate)."""
    bag = tmp_path_factory.mktemp("tof") / "bag"
    assert main(["simulate", "--world", "room", "--out", str(bag), "--max-frames", "3", "--quiet"]) == 0
    return bag


@pytest.mark.filterwarnings("ignore:.*no --calibration given")  # the simulated bag's true rig is meant
def test_scans_and_simulate_replace_a_bag_or_log_and_nothing_else(tmp_path, monkeypatch, capsys, tiny_tof_bag):
    # --overwrite replaced whatever --out named: a folder of the user's own, the folder holding
    # the input bag, a CARMEN log without being asked. Each is now refused before any work.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    (tmp_path / "log.clf").write_text("a log of my own")
    inner = tmp_path / "holder" / "in"
    inner.parent.mkdir()
    import shutil

    shutil.copytree(tiny_tof_bag, inner)
    (tmp_path / "holder" / "notes.txt").write_text("keep me")
    cases = [
        (["simulate", "--world", "room", "--out", "mine", "--max-frames", "2", "--overwrite"],
         "mine: is a folder but not a ROS 2 bag (it holds notes.txt)"),
        (["simulate", "--world", "room", "--out", ".", "--max-frames", "2", "--overwrite"], "holds the current folder"),
        (["simulate", "--world", "room", "--out", "mine/..", "--max-frames", "2", "--overwrite"], "holds the current folder"),
        (["simulate", "--world", "room", "--out", "log.clf", "--max-frames", "2", "--overwrite"], "not a ROS 1 bag"),
        (["scans", "holder/in", "--out", "holder", "--overwrite"], "holder: is (or holds) the input"),
        (["scans", "holder/in", "--out", "holder/in", "--overwrite"], "is (or holds) the input"),
        (["scans", "holder/in", "--out", "log.clf"], "log.clf exists already; replace it with --overwrite"),
        (["scans", "holder/in", "--out", "new.clf", "--figure", "mine"], "mine: is a folder"),
        (["scans", "holder/in", "--out", "new.clf", "--figure", "/proc/omnitof.png"], "/proc/omnitof.png: cannot write"),
        (["scans", "holder/in", "--out", "nowhere/new.clf"], "its folder does not exist"),
    ]
    for argv, message in cases:
        assert main([*argv, "--quiet"]) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and err.count("error:") == 1, (argv, err)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"
    assert (tmp_path / "log.clf").read_text() == "a log of my own"
    assert (tmp_path / "holder" / "notes.txt").exists() and (inner / "metadata.yaml").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["holder", "log.clf", "mine"]  # nothing half-written
    # What it may replace, it replaces: a log with --overwrite, a bag with --overwrite.
    assert main(["scans", "holder/in", "--out", "log.clf", "--overwrite", "--quiet"]) == 0
    assert (tmp_path / "log.clf").read_text().startswith("# CARMEN Logfile written by omnitof")
    assert main(["scans", "holder/in", "--out", "scans", "--quiet"]) == 0
    assert main(["scans", "holder/in", "--out", "scans", "--overwrite", "--quiet"]) == 0
    assert main(["simulate", "--world", "room", "--out", "scans", "--max-frames", "2", "--overwrite", "--quiet"]) == 0
