"""End to end on a simulated world: frames → calibration → scans → SLAM → 3D map → evaluation.

The corridor2 run is the paper's CORRIDOR 2 sequence (58 m loop) in full: about a minute.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from omnitof.demo import DemoSettings, run_world
from omnitof.io.tum import read_tum


@pytest.fixture(scope="module")
def corridor2_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("corridor2")
    run = run_world(DemoSettings(world="corridor2", seed=0, map3d_every=20), out, progress=False,
                    echo=lambda _: None)
    return run, out


def test_corridor2_loop_closes(corridor2_run):
    run, _ = corridor2_run
    t = run.summary["evaluation"]["trajectory"]
    # Raw odometry ends about 2 m off; SLAM must bring the robot back to where it started.
    assert t["odometry"]["final"] > 1.5
    assert t["slam"]["final"] < 0.5
    assert t["slam"]["mean"] < 0.3 * t["odometry"]["mean"]


def test_corridor2_map_matches_the_floor_plan(corridor2_run):
    run, _ = corridor2_run
    fp = run.summary["evaluation"]["floorplan"]
    # Recorded (BENCHMARKS.md, "ToF worlds"), seed 0 with the estimated calibration: 38 % of the
    # occupied cells within 5 cm of a true wall (84 % within 20 cm), 28 % of the wall length in
    # view mapped, 12 cm mean distance. With the true rig: 60 %, 46 %, 8 cm; a map built from
    # the true poses: 89 %, 76 %.
    assert fp["occupied_within_5cm"] > 0.30
    assert fp["seen_wall_mapped"] > 0.20
    assert fp["mean_distance_m"] < 0.15


def test_corridor2_table1_corridor_widths(corridor2_run):
    # The corridors (#1, #2, #5) are seen from the middle on both sides: within 10 cm, in the
    # summary's Table I (the filter's map, its cells that hold an obstacle) and in the map the
    # run writes (map.yaml / map.pgm, what a user gets). Before Table I left out the free cells,
    # #1 read 17.5 cm wide in the summary of this run: free-leaning cells beyond the wall took
    # the two-Gaussian fit (BENCHMARKS.md, "Table I on the cells that hold an obstacle").
    from omnitof.eval.table1 import table1
    from omnitof.io.rosmap import read_ros_map

    run, out = corridor2_run
    measured = {r.name: r for r in table1(read_ros_map(out / "map.yaml"), run.world.landmarks)}
    summary = run.summary["evaluation"]["table1"]
    for name in ("1", "2", "5"):
        assert abs(measured[name].offset) < 0.10, (name, measured[name].offset)
        assert abs(summary[name]["offset_cm"]) < 10.0, (name, summary[name])


def test_corridor2_outputs_are_consistent(corridor2_run):
    run, out = corridor2_run
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    assert summary["demo"]["sequence"]["frames"] == len(run.scans)
    trajectory = read_tum(out / "trajectory.tum")
    truth = read_tum(out / "ground_truth.tum")
    assert len(trajectory) == len(truth) == len(run.scans)
    # The 3D map's occupied voxels lie in the building (x 0..44, y 0..22.25, z 0..2.8).
    from omnitof.io.ply import read_ply

    points, _ = read_ply(out / "map3d.ply")
    assert len(points) > 1000
    inside = (points[:, 2] > -0.2) & (points[:, 2] < 3.0)
    assert np.mean(inside) > 0.95
    assert (out / "report.md").read_text().count("![") >= 5


def test_cli_slam_on_a_simulated_tof_bag(tmp_path, capsys):
    from omnitof.cli import main

    bag = tmp_path / "room"
    assert main(["simulate", "--world", "room", "--out", str(bag), "--max-frames", "80", "--quiet"]) == 0
    out = tmp_path / "slam"
    with pytest.warns(UserWarning, match="true rig"):
        code = main(["slam", str(bag), "--out", str(out), "--map3d", "--map3d-every", "20", "--quiet"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "trajectory error" in printed
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    assert summary["input"]["kind"] == "tof-rosbag"
    # Without --preset a ToF bag runs tof-scanmatch (the paper's filter is --preset tof).
    assert summary["run"]["particles"] == 30 and summary["run"]["proposal"] == "scanmatch"
    assert summary["trajectory_error"]["slam"]["final"] < 0.3
    for name in ("map.yaml", "trajectory.tum", "map3d.ply", "map3d.png"):
        assert (out / name).exists(), name


def test_a_tof_bag_without_odometry_maps_from_its_scans(tmp_path, capsys):
    # A camera carried by hand records no odometry: `omnitof slam` estimates it from the scans,
    # in a frame of its own, and compares it with the truth moved into that frame.
    import dataclasses

    from omnitof.cli import main
    from omnitof.geometry import relative
    from omnitof.io.rosbag import read_tof_bag, write_tof_bag
    from omnitof.scan.tof_input import ToFInputWarning, read_tof_scans

    bag = tmp_path / "room"
    assert main(["simulate", "--world", "room", "--out", str(bag), "--max-frames", "80", "--quiet"]) == 0
    original = read_tof_bag(bag)
    frames = [dataclasses.replace(f, samples=None) for f in original.frames(samples=False)]
    bare = tmp_path / "bare"
    write_tof_bag(bare, frames, camera=original.camera, odometry=None, ground_truth=original.ground_truth,
                  sidecar=original.sidecar)
    out = tmp_path / "slam"
    with pytest.warns(UserWarning, match="true rig"):
        assert main(["slam", str(bare), "--out", str(out), "--quiet"]) == 0
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    assert summary["input"]["odometry"].startswith("estimated from the scans")
    assert summary["input"]["scan_odometry"]["matched"] >= 70 and "ground_truth_frame" in summary["input"]
    assert summary["trajectory_error"]["slam"]["mean"] < 0.05  # 0.02 m with the wheels' odometry
    # The truth written beside the trajectory is in the estimate's frame: its first pose is the
    # trajectory's, and its motion is the true one.
    truth, slam = read_tum(out / "ground_truth.tum").poses, read_tum(out / "trajectory.tum").poses
    np.testing.assert_allclose(truth[0], slam[0], atol=1e-9)
    true = original.frame_ground_truth().poses
    np.testing.assert_allclose(relative(truth[0], truth[-1]), relative(true[0], true[-1]), atol=1e-6)
    # The 3D filter picks its frames by the odometry: refused, with the reason.
    capsys.readouterr()
    assert main(["slam", str(bare), "--out", str(tmp_path / "x"), "--filter", "3d", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "has no odometry" in err and "--filter 3d" in err and "Traceback" not in err
    # `omnitof scans` writes such a bag's scans as a LaserScan bag without odometry; a CARMEN log
    # needs a pose per scan and is refused before anything is written.
    with pytest.warns(UserWarning, match="true rig"):
        assert main(["scans", str(bare), "--out", str(tmp_path / "bare.clf"), "--quiet"]) == 2
        assert main(["scans", str(bare), "--out", str(tmp_path / "bare.bag"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "has no odometry, and a CARMEN log" in err and not (tmp_path / "bare.clf").exists()
    from omnitof.io.rosbag import read_laserscan_bag

    assert not read_laserscan_bag(tmp_path / "bare.bag").odometry_known
    # Wheels that start late: the frames before them are dropped, with a warning.
    late = tmp_path / "late"
    odometry = original.odometry
    start = frames[10].timestamp - 1e-3
    keep = odometry.timestamps >= start
    write_tof_bag(late, frames, camera=original.camera, odometry=type(odometry)(odometry.timestamps[keep],
                  odometry.poses[keep]), sidecar=original.sidecar)
    with pytest.warns(ToFInputWarning, match=r"dropped 10 frames outside the odometry's time span .*70 kept"):
        scans = read_tof_scans(late).scans
    assert len(scans) == 70 and scans.odometry_known and "/odom" in scans.odometry_rule
    # Reading only the first frames with odometry still says what was dropped before them.
    with pytest.warns(ToFInputWarning, match=r"dropped 10 frames .*5 kept"):
        assert len(read_tof_scans(late, max_frames=5).scans) == 5


def test_the_configurations_scan_section_reaches_the_extraction(tmp_path, capsys):
    from omnitof.cli import main

    bag = tmp_path / "room"
    assert main(["simulate", "--world", "room", "--out", str(bag), "--max-frames", "12", "--seed", "3",
                 "--tof-errors", "all", "--quiet"]) == 0
    out = tmp_path / "slam"
    argv = ["slam", str(bag), "--out", str(out), "--quiet", "--height", "0.55", "--set", "scan.max_range=3",
            "--set", "scan.height=0.7", "--set", "scan.multipath.stride=4", "--set", "scan.multipath.amplitude_at_1m=1"]
    with pytest.warns(UserWarning, match="true rig"):
        assert main(argv) == 0
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    scan = summary["input"]["scan"]
    # --height wins over the configuration; the filter's sensor takes the section's max_range.
    assert scan["height"] == 0.55 and scan["max_range"] == 3.0
    assert summary["input"]["max_range"]["metres"] == 3.0
    assert yaml.safe_load((out / "config.yaml").read_text())["scan"]["height"] == 0.55
    # The simulated camera has multipath: auto turns the compensation on with the camera's own
    # figures from the sidecar, and keeps how the configuration takes the sum.
    assert scan["multipath"]["enabled"] and scan["multipath"]["stride"] == 4
    assert scan["multipath"]["amplitude_at_1m"] > 1000
    capsys.readouterr()
    assert main(["slam", str(bag), "--out", str(tmp_path / "bad"), "--quiet", "--set", "scan.max_range=-1"]) == 2
    err = capsys.readouterr().err
    assert "scan.max_range" in err and "Traceback" not in err and not (tmp_path / "bad").exists()


def test_a_drivers_bag_with_depth_images_gives_the_same_scans(tmp_path, capsys):
    # The simulated bag rewritten as a camera driver would record it: other topic names and the
    # depth z instead of the radial distance. Read with --tof-topics and --tof-distance depth, it
    # must give the scans of the original.
    import dataclasses

    from omnitof.cli import main
    from omnitof.io.carmen import read_carmen
    from omnitof.io.rosbag import ToFTopics, read_tof_bag, write_tof_bag

    bag = tmp_path / "room"
    assert main(["simulate", "--world", "room", "--out", str(bag), "--max-frames", "8", "--quiet"]) == 0
    original = read_tof_bag(bag)
    ray_z = original.camera.pixel_grid_rays()[..., 2].astype(np.float32)
    topics = ToFTopics(distance="/sr/depth", amplitude="/sr/amplitude", camera_info="/sr/camera_info",
                       odometry="/wheel_odom")
    frames = [dataclasses.replace(f, distance=f.distance * ray_z, samples=None) for f in original.frames()]
    driver = tmp_path / "driver"
    write_tof_bag(driver, frames, camera=original.camera, odometry=original.odometry, sidecar=original.sidecar,
                  topics=topics)
    with pytest.warns(UserWarning, match="true rig"):
        assert main(["scans", str(bag), "--out", str(tmp_path / "a.clf"), "--quiet"]) == 0
        assert main(["scans", str(driver), "--out", str(tmp_path / "b.clf"), "--quiet", "--tof-distance", "depth",
                     "--tof-topics", "distance=/sr/depth,amplitude=/sr/amplitude,camera_info=/sr/camera_info,"
                     "odometry=/wheel_odom"]) == 0
    a, b = read_carmen(tmp_path / "a.clf").scans, read_carmen(tmp_path / "b.clf").scans
    assert np.isfinite(a.ranges).sum() > 1000
    np.testing.assert_array_equal(np.isfinite(a.ranges), np.isfinite(b.ranges))
    seen = np.isfinite(a.ranges)
    np.testing.assert_allclose(b.ranges[seen], a.ranges[seen], atol=2e-3)
    # Without --tof-distance depth the same bag reads short: z is less than the radial distance.
    capsys.readouterr()
    with pytest.warns(UserWarning, match="true rig"):
        assert main(["scans", str(driver), "--out", str(tmp_path / "c.clf"), "--quiet", "--tof-topics",
                     "distance=/sr/depth,amplitude=/sr/amplitude,camera_info=/sr/camera_info,odometry=/wheel_odom"]) == 0
    c = read_carmen(tmp_path / "c.clf").scans
    both = seen & np.isfinite(c.ranges)
    assert np.median(a.ranges[both] - c.ranges[both]) > 0.05


def test_cli_slam_refuses_calibration_for_a_laser_log(tmp_path, capsys):
    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen
    from omnitof.sim.laser2d import make_loop_dataset

    log = tmp_path / "loop.clf"
    write_carmen(log, make_loop_dataset(seed=0).slice(0, 20))
    assert main(["slam", str(log), "--out", str(tmp_path / "o"), "--map3d", "--quiet"]) == 2
    assert "ToF images" in capsys.readouterr().err
    assert main(["slam", str(log), "--out", str(tmp_path / "o"), "--tof-distance", "depth", "--quiet"]) == 2
    assert "--tof-distance needs a bag of ToF images" in capsys.readouterr().err
    # A slice height or band on a laser log was ignored without a word.
    assert main(["slam", str(log), "--out", str(tmp_path / "o"), "--height", "5", "--band", "0.2", "--quiet"]) == 2
    assert "--height, --band need a bag of ToF images" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_cli_scans_exports_carmen_and_laserscan_bag(tmp_path, capsys):
    from omnitof.cli import main
    from omnitof.io.carmen import read_carmen
    from omnitof.io.rosbag import read_laserscan_bag
    from omnitof.scan.tof_input import read_tof_scans

    bag = tmp_path / "room"
    assert main(["simulate", "--world", "room", "--out", str(bag), "--max-frames", "12", "--quiet"]) == 0
    with pytest.warns(UserWarning, match="true rig"):
        want = read_tof_scans(bag).scans
        assert main(["scans", str(bag), "--out", str(tmp_path / "scans.clf"), "--quiet"]) == 0
        assert main(["scans", str(bag), "--out", str(tmp_path / "scans"), "--quiet"]) == 0
    carmen = read_carmen(tmp_path / "scans.clf").scans
    laser = read_laserscan_bag(tmp_path / "scans")
    for got in (carmen, laser):
        assert got.ranges.shape == want.ranges.shape == (12, 360)
        assert np.array_equal(np.isfinite(got.ranges), np.isfinite(want.ranges))
        finite = np.isfinite(want.ranges)
        assert np.allclose(got.ranges[finite], want.ranges[finite], atol=1e-3)
        assert np.allclose(got.angles, want.angles, atol=1e-6)
        assert np.allclose(got.odometry, want.odometry, atol=1e-6)
