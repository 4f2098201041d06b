"""The 3D particle filter (paper sec. V; rust/src/filter3d.rs, omnitof.slam.filter3d) on frames of
the ToF simulator: its observation model against a known map, shared voxel blocks, determinism
over thread counts, and an atrium whose slice at scan height is empty but whose upper parts are
not: the 3D filter localises there, the 2D one cannot."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from omnitof import _core
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.scan.extract import ScanExtractor
from omnitof.scan.tof_input import tof_scans
from omnitof.sim.render import Renderer, RenderSettings
from omnitof.sim.sequence import MotionSettings, OdometryErrors, make_sequence, render_sequence
from omnitof.sim.worlds import load_world, parse_world
from omnitof.slam import run_slam
from omnitof.slam.config import load_config
from omnitof.slam.filter3d import core_sections_3d, project_to_floor, run_slam3d


def _config(**filter_fields):
    cfg = load_config(preset="tof3d")
    for key, value in filter_fields.items():
        setattr(cfg.filter, key, value)
    return cfg


def _frames(world, poses, seed=0):
    renderer = Renderer(world, settings=RenderSettings(seed=seed, sub_rays=1))
    extractor = ScanExtractor.from_rig(renderer.rig)
    return [extractor.rays(f.distance, f.amplitude) for f in renderer.render_many(np.asarray(poses), seed=seed)]


# --- the observation model in a known map --------------------------------------------------


@pytest.fixture(scope="module")
def room_map():
    """A 1-particle filter whose map holds frames of the room rendered at their true poses
    (noise-free motion, odometry = truth), and a further rendered frame with its true pose."""
    world = load_world("room")
    poses = np.array([[1.5, 1.5, 0.0], [2.5, 1.6, 0.3], [4.0, 1.8, 1.2], [3.0, 3.0, 2.8], [1.8, 2.7, -1.8]])
    truth = np.array([2.2, 2.0, 0.4])
    frames = _frames(world, np.vstack([poses, truth]))
    cfg = _config(particles=1, proposal="odometry")
    for k in ("alpha1", "alpha2", "alpha3", "alpha4"):
        setattr(cfg.motion, k, 0.0)
    pf = _core.ParticleFilter3D(**core_sections_3d(cfg))
    for i, (pose, (o, e)) in enumerate(zip(poses, frames)):
        prev = poses[max(i - 1, 0)]
        pf.step(prev, pose, o, e, i)
    return pf, truth, frames[-1]


def test_likelihood_is_highest_at_the_true_pose_and_falls_off(room_map):
    pf, truth, (_, ends) = room_map
    ends = ends[ends[:, 2] > 0.1]  # the floor says nothing of the pose
    steps = {0: [0.05, 0.1, 0.2], 1: [0.05, 0.1, 0.2], 2: [math.radians(d) for d in (2, 4, 8)]}
    for axis, offsets in steps.items():
        for sign in (-1.0, 1.0):
            poses = [truth.copy()]
            for off in offsets:
                p = truth.copy()
                p[axis] += sign * off
                poses.append(p)
            ll, matched = pf.score(0, np.array(poses), ends)
            # Strictly falling with distance from the true pose along every axis, both ways.
            assert np.all(np.diff(ll) < 0), (axis, sign, ll)
    ll, matched = pf.score(0, truth[None, :], ends)
    assert matched[0] > 0.9 * len(ends)


def test_resampling_shares_unchanged_blocks():
    world = load_world("room")
    poses = np.array([[1.5, 1.5, 0.0], [1.8, 1.5, 0.0]])
    frames = _frames(world, poses)
    cfg = _config(particles=20, proposal="odometry", resample_threshold=1.0)  # resample every step
    pf = _core.ParticleFilter3D(**core_sections_3d(cfg))
    pf.step(poses[0], poses[0], *frames[0], 0)
    one = pf.map().block_count()
    assert pf.block_counts() == (one, 20 * one)
    # A frame that looks along +x only (a 40° sector) changes a few blocks of each map; the
    # others stay those of the first frame, shared by all. Measured in bytes of distinct blocks.
    origins, ends = frames[1]
    sector = (ends[:, 0] > 0) & (np.abs(ends[:, 1]) < 0.35 * ends[:, 0])
    pf.step(poses[0], poses[1], origins[sector], ends[sector], 1)
    distinct, refs = pf.block_counts()
    size = _core.ParticleFilter3D.block_bytes()
    assert refs >= 20 * one
    assert distinct * size < 0.5 * refs * size, (distinct, refs)
    # After the resampling, copies of one particle (same pose) share every block of their map.
    assert pf.resamplings == 1
    _, groups = np.unique(pf.poses(), axis=0, return_inverse=True)
    groups = groups.reshape(-1)
    group = np.flatnonzero(groups == np.bincount(groups).argmax())
    assert len(group) >= 2
    blocks = pf.map(int(group[0])).block_count()
    assert pf.block_counts(group.tolist()) == (blocks, len(group) * blocks)


# --- an atrium: nothing at scan height within 7 m, galleries above --------------------------

ATRIUM = {
    "name": "atrium",
    "description": "a 26 m x 22 m hall; galleries from 1.0 m to 2.2 m high around a loop",
    "ceiling_height": 5.0,
    "walls": [{"points": [[-1.0, -1.0], [25.0, -1.0], [25.0, 21.0], [-1.0, 21.0]], "closed": True}],
    "boxes": [
        {"centre": [12.0, 5.0], "size": [7.0, 0.5], "bottom": 1.0, "height": 1.2},
        {"centre": [12.5, 15.0], "size": [5.0, 0.5], "bottom": 1.0, "height": 1.2},
        {"centre": [6.0, 10.0], "size": [0.5, 5.0], "bottom": 1.0, "height": 1.2},
        {"centre": [18.0, 9.0], "size": [0.5, 3.0], "bottom": 1.0, "height": 1.2},
        {"centre": [12.0, 10.0], "size": [1.5, 0.6], "bottom": 1.0, "height": 1.2},
        {"centre": [10.5, 11.0], "size": [0.6, 0.6], "bottom": 1.0, "height": 1.2},
    ],
    "path": {"waypoints": [[9.0, 8.0], [15.0, 8.0], [15.0, 12.0], [9.0, 12.0]]},
}


@pytest.fixture(scope="module")
def atrium_run():
    world = parse_world(ATRIUM)
    seq = make_sequence(world, seed=3, motion=MotionSettings(speed=1.0, rate_hz=5.0),
                        odometry_errors=OdometryErrors(wheel_radius_error=0.02, wheel_base_error=0.02,
                                                       heading_drift=math.radians(0.2)))
    renderer = Renderer(world, settings=RenderSettings(seed=3, sub_rays=1))
    cfg = _config()
    keyframes = (cfg.filter.linear_update, math.radians(cfg.filter.angular_update_deg))
    data = tof_scans(render_sequence(seq, renderer), ScanExtractor.from_rig(renderer.rig),
                     cloud_keyframes=keyframes, cloud_pixel_stride=cfg.filter3d.pixel_stride)
    return data, cfg


def test_the_slice_is_empty_but_the_upper_rays_are_not(atrium_run):
    data, _ = atrium_run
    # A few stray readings (mixed pixels at the galleries' lower edges), no wall.
    assert np.isfinite(data.scans.ranges).mean() < 0.01
    heights = np.concatenate([c[:, 5] for c in data.clouds])
    assert np.sum(heights > 0.9) > 100 * len(data.clouds)


def test_3d_filter_localises_where_the_2d_filter_cannot(atrium_run):
    data, cfg = atrium_run
    truth, odometry = data.scans.ground_truth, data.scans.odometry
    odo = absolute_trajectory_error(odometry, truth)
    assert odo.mean > 0.15  # the drift to beat
    run = run_slam3d(data.scans, data.cloud_frames, data.clouds, cfg)
    err3 = absolute_trajectory_error(run.result.trajectory.poses, truth)
    # Over two drives × four filter seeds of this world the 3D filter errs 0.060–0.097 m mean
    # (0.067–0.103 m with the Gauss-Newton step) and ends 0.03–0.15 m off: the test asks for at
    # most half the odometry's drift (0.28 m here) and an end within 0.2 m.
    assert err3.mean < 0.5 * odo.mean and err3.final < 0.2, (err3, odo)
    # The 2D filter has next to nothing to map, hence to localise against: it follows the odometry.
    flat = run_slam(data.scans, cfg)
    err2 = absolute_trajectory_error(flat.trajectory.poses, truth)
    print(f"mean error: odometry {odo.mean:.3f} m, 2D filter {err2.mean:.3f} m, 3D filter {err3.mean:.3f} m")
    assert err2.mean > 0.5 * odo.mean and err2.mean > 3 * err3.mean, (err2, err3, odo)


def test_the_back_end_leaves_a_3d_run_alone_where_the_slice_finds_no_closure(atrium_run):
    # The atrium's slice is empty: the back end's 2D submaps hold next to nothing, no closure is
    # found, and the run is the filter's own (the graph's chain of its steps).
    data, cfg = atrium_run
    assert cfg.backend.enabled  # tof3d has it
    with_backend = run_slam3d(data.scans, data.cloud_frames, data.clouds, cfg).result
    cfg = cfg.model_copy(deep=True)
    cfg.backend.enabled = False
    alone = run_slam3d(data.scans, data.cloud_frames, data.clouds, cfg).result
    assert "backend" not in alone.stats
    assert with_backend.stats["backend"]["closures_found"] == 0
    np.testing.assert_allclose(with_backend.trajectory.poses, alone.trajectory.poses, atol=1e-9)


def test_same_seed_same_result_for_one_and_two_threads(atrium_run):
    data, cfg = atrium_run
    keep = 8
    stop = int(data.cloud_frames[keep - 1]) + 1
    scans = data.scans.slice(0, stop)
    runs = []
    for threads in (1, 2):
        c = cfg.model_copy(deep=True)
        c.filter.threads = threads
        runs.append(run_slam3d(scans, data.cloud_frames[:keep], data.clouds[:keep], c).result.trajectory.poses)
    assert np.array_equal(runs[0], runs[1])


def test_the_odometry_check_undoes_a_wheel_glitch_and_leaves_a_clean_drive_alone(atrium_run):
    from omnitof.geometry import compose, relative

    data, cfg = atrium_run
    scans = data.scans
    # The wheels slide 0.3 m back, 0.4 m left and turn 12° that the robot never did, 30 % of the
    # way through: beyond the hill climbing's reach.
    at = int(round(0.3 * len(scans)))
    before = scans.odometry[at - 1]
    odometry = scans.odometry.copy()
    odometry[at:] = compose(compose(before, np.array([-0.3, 0.4, math.radians(-12.0)])), relative(before, scans.odometry[at:]))
    glitched = dataclasses.replace(scans, odometry=odometry)

    def run(inputs, search_xy):
        c = cfg.model_copy(deep=True)
        c.scan_matcher.search_xy = search_xy
        result = run_slam3d(inputs, data.cloud_frames, data.clouds, c).result
        return result, absolute_trajectory_error(result.trajectory.poses, scans.ground_truth)

    lost, lost_err = run(glitched, 0.0)
    found, found_err = run(glitched, 1.0)
    first = int(data.cloud_frames[np.searchsorted(data.cloud_frames, at)])
    assert lost.stats["odometry_corrected_scans"] == []
    assert found.stats["odometry_corrected_scans"] == [first]
    # 0.203 m without the check, 0.104 m with it (0.09 m without the glitch).
    assert found_err.mean < 0.7 * lost_err.mean, (found_err, lost_err)
    clean, _ = run(scans, 1.0)
    assert clean.stats["odometry_corrected_scans"] == []
    np.testing.assert_array_equal(clean.trajectory.poses, run(scans, 0.0)[0].trajectory.poses)


def _drive_with_glitch(world_name: str, start: int, stop: int, at: int, jump: tuple[float, float, float]):
    """tof3d without the back end (cfg), frames start..stop of the world's drive 0 rendered with the
    true rig (data), the same scans with the wheels glitching by `jump` (x, y m, heading degrees,
    robot frame) from frame `at` on, and the truth seen from the run's first odometry pose."""
    from omnitof.geometry import compose, relative

    world = load_world(world_name)
    renderer = Renderer(world, settings=RenderSettings(seed=0, sub_rays=1))
    cfg = load_config(preset="tof3d")
    cfg.backend.enabled = False
    keyframes = (cfg.filter.linear_update, math.radians(cfg.filter.angular_update_deg))
    data = tof_scans(render_sequence(make_sequence(world, seed=0), renderer, start=start, stop=stop),
                     ScanExtractor.from_rig(renderer.rig), cloud_keyframes=keyframes,
                     cloud_pixel_stride=cfg.filter3d.pixel_stride)
    scans, k = data.scans, at - start
    odometry = scans.odometry.copy()
    odometry[k:] = compose(compose(scans.odometry[k - 1], np.array([jump[0], jump[1], math.radians(jump[2])])),
                           relative(scans.odometry[k - 1], scans.odometry[k:]))
    truth = compose(scans.odometry[0], relative(scans.ground_truth[0], scans.ground_truth))
    first_after = int(data.cloud_frames[np.searchsorted(data.cloud_frames, k)]) + start
    return cfg, data, dataclasses.replace(scans, odometry=odometry), truth, first_after


def _run_with(cfg, data, inputs, truth, **scan_matcher):
    """One tof3d run on `inputs` with these scan_matcher settings: (result, its error to `truth`)."""
    c = cfg.model_copy(deep=True)
    for name, value in scan_matcher.items():
        setattr(c.scan_matcher, name, value)
    result = run_slam3d(inputs, data.cloud_frames, data.clouds, c).result
    return result, absolute_trajectory_error(result.trajectory.poses, truth)


def test_the_odometry_check_catches_a_wheel_glitch_where_a_corridor_turns():
    # Corridor1, drive 0, frames 1380-1640, where the robot leaves a corridor at a corner; the
    # wheels report 0.6 m and 8 degrees more than the robot drove at frame 1486. Most of a frame's
    # rays end on the side walls within a metre, which neither slip moves off the wall: at the
    # wheels' pose 0.85 of the judged end points still lie near the map, so with
    # scan_matcher.search_below 0.8 the check let the glitch pass and the rest of the drive was
    # mapped turned (every corridor glitch unrepaired, 2-7 m off at the loop's end); tof3d's
    # 0.9 searches there and takes it back. A clean drive is left alone by either.
    first = 1380
    cfg, data, glitched, truth, after = _drive_with_glitch("corridor1", first, 1640, 1486, (0.6, 0.0, 8.0))
    assert cfg.scan_matcher.search_below == 0.9
    missed, missed_err = _run_with(cfg, data, glitched, truth, search_below=0.8)
    caught, caught_err = _run_with(cfg, data, glitched, truth, search_below=0.9)
    clean, clean_err = _run_with(cfg, data, data.scans, truth, search_below=0.9)
    assert missed.stats["odometry_corrected_scans"] == []
    assert caught.stats["odometry_corrected_scans"] == [after - first]
    assert clean.stats["odometry_corrected_scans"] == []
    np.testing.assert_array_equal(clean.trajectory.poses,
                                  _run_with(cfg, data, data.scans, truth, search_below=0.8)[0].trajectory.poses)
    # Measured: mean (final) 0.427 (0.939) m missed, 0.039 (0.098) caught, 0.039 (0.100) clean.
    assert missed_err.final > 0.5 and missed_err.mean > 0.2, missed_err
    assert caught_err.mean < clean_err.mean + 0.02 and caught_err.final < clean_err.final + 0.05, (caught_err, clean_err)


def test_the_check_takes_a_pose_that_explains_less_than_its_trigger():
    # The room, drive 0, frames 0-300; at frame 129 the wheels report 0.3 m back, 0.4 m left and
    # -12 degrees that the robot never drove. tof3d searches below 0.9 of the judged end points
    # (scan_matcher.search_below, for the corridors above), but the pose the search finds at the
    # first frame after the glitch explains between 0.8 and 0.9 of them: with that one bar for
    # both (search_accept unset) the glitch was taken back only at a later frame, and the map
    # kept the frames between; search_accept 0.8 takes it at once. A clean drive is left alone.
    cfg, data, glitched, truth, after = _drive_with_glitch("room", 0, 300, 129, (-0.3, 0.4, -12.0))
    assert (cfg.scan_matcher.search_below, cfg.scan_matcher.search_accept) == (0.9, 0.8)
    at_once, at_once_err = _run_with(cfg, data, glitched, truth, search_accept=0.8)
    late, late_err = _run_with(cfg, data, glitched, truth, search_accept=None)
    assert at_once.stats["odometry_corrected_scans"] == [after]
    assert late.stats["odometry_corrected_scans"] and late.stats["odometry_corrected_scans"][0] > after
    # Measured: mean error 0.032 m taken at once, 0.045 m a frame later, 0.016 m clean.
    assert at_once_err.mean < late_err.mean - 0.005, (at_once_err, late_err)
    clean, _ = _run_with(cfg, data, data.scans, truth, search_accept=0.8)
    assert clean.stats["odometry_corrected_scans"] == []
    np.testing.assert_array_equal(clean.trajectory.poses,
                                  _run_with(cfg, data, data.scans, truth, search_accept=None)[0].trajectory.poses)

def test_projection_takes_the_largest_log_odds_of_each_column():
    idx = np.array([[0, 0, 1], [0, 0, 5], [0, 0, 30], [2, 1, 3], [2, 1, 4]])
    lo = np.array([-1.0, 2.0, 3.5, -0.5, -0.4], dtype=np.float32)
    m = project_to_floor(idx, lo, 0.1, z_min=0.1, z_max=2.0)
    assert m.log_odds.shape == (2, 3) and m.origin == (0.0, 0.0)
    # Column (0, 0): 3.5 lies at 3.05 m, above the band: 2.0 wins. Column (2, 1): -0.4.
    assert m.log_odds[0, 0] == 2.0 and m.log_odds[1, 2] == np.float32(-0.4)
    assert m.known.sum() == 2


# --- the command ---------------------------------------------------------------------------


def test_slam_filter_3d_writes_the_voxel_map_its_projection_and_the_difference(tmp_path, capsys):
    import yaml

    from omnitof.cli import main
    from omnitof.io.ply import read_ply
    from omnitof.io.rosmap import read_ros_map
    from omnitof.io.tum import read_tum

    bag = tmp_path / "room_bag"
    assert main(["simulate", "--world", "room", "--out", str(bag), "--max-frames", "40", "--quiet"]) == 0
    out = tmp_path / "out"
    assert main(["slam", str(bag), "--filter", "3d", "--compare-2d", "--particles", "5", "--out", str(out),
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "3D filter vs 2D filter" in printed
    summary = yaml.safe_load((out / "summary.yaml").read_text())
    assert summary["run"]["filter"] == "3d" and summary["run"]["particles"] == 5
    assert summary["run"]["voxel_blocks_distinct"] <= summary["run"]["voxel_blocks_referenced"]
    traj3, traj2 = read_tum(out / "trajectory.tum"), read_tum(out / "trajectory_2d.tum")
    # The 2D filter beside it is the one `omnitof slam` runs without --filter 3d (tof-scanmatch).
    assert main(["slam", str(bag), "--particles", "5", "--out", str(tmp_path / "out2d"), "--quiet"]) == 0
    np.testing.assert_array_equal(read_tum(tmp_path / "out2d" / "trajectory.tum").poses, traj2.poses)
    apart = np.hypot(*(traj3.poses[:, :2] - traj2.poses[:, :2]).T)
    assert summary["filter2d"]["difference_3d_to_2d"]["mean"] == pytest.approx(apart.mean(), abs=1e-4)
    points, _ = read_ply(out / "map3d.ply")
    assert len(points) > 1000 and (out / "map3d.png").stat().st_size > 0
    occ = read_ros_map(out / "map.yaml")
    assert occ.known.sum() > 500
    # The pose-graph back end behind the 3D filter (tof3d has it): its graph drawn and summed up.
    assert summary["run"]["backend"]["nodes"] == summary["run"]["integrated"]
    assert (out / "pose_graph.png").stat().st_size > 0
    # Not on a laser log.
    log = tmp_path / "laser.clf"
    log.write_text("ODOM 0 0 0 0 0 0 1.0 host 0\n")
    assert main(["slam", str(log), "--filter", "3d", "--out", str(tmp_path / "x"), "--quiet"]) == 2
    assert "needs a bag of ToF images" in capsys.readouterr().err


def test_compare_2d_runs_the_2d_filter_as_omnitof_slam_would_without_filter_3d(tmp_path, monkeypatch):
    # tof3d's 2D sections are not the 2D filter a user runs (the 3D check has no search_distinct
    # gate, the 3D particles draw where a match fails): beside the 3D filter runs the 2D filter's
    # own default preset, or the --preset / --set given.
    from omnitof import cli, slam_run
    from omnitof.slam_run import slam_config

    seen = {}

    def capture(request, cfg, out, *, cfg_2d=None, **_):
        seen["cfg"], seen["cfg_2d"] = cfg, cfg_2d
        raise SystemExit(0)

    monkeypatch.setattr(slam_run, "slam_to_folder", capture)
    monkeypatch.setattr(slam_run, "default_preset", lambda log, topics=None: "tof-scanmatch")
    for extra, preset_2d in (([], "tof-scanmatch"), (["--preset", "tof"], "tof")):
        with pytest.raises(SystemExit):
            cli.main(["slam", str(tmp_path / "bag"), "--filter", "3d", "--compare-2d", "--particles", "7",
                      "--set", "backend.min_score=0.6", "--out", str(tmp_path / "out"), *extra])
        assert seen["cfg"].filter3d.enabled and not seen["cfg_2d"].filter3d.enabled
        expected = slam_config(preset=preset_2d, settings={"backend.min_score": 0.6}, particles=7)
        assert seen["cfg_2d"] == expected
        assert seen["cfg"] == slam_config(preset="tof3d" if not extra else "tof",
                                          settings={"backend.min_score": 0.6, "filter3d.enabled": True}, particles=7)


def test_odometry_far_out_gives_the_same_run_moved(atrium_run):
    # 1000 km out: 10 million voxels of 0.1 m, beyond the core's ±2^20 (omnitof.map3d.voxels).
    from omnitof.map3d import VoxelMap

    data, cfg = atrium_run
    keep = 8
    scans = data.scans.slice(0, int(data.cloud_frames[keep - 1]) + 1)
    shift = np.array([1e6, -2e5, 0.0])
    far = dataclasses.replace(scans, odometry=scans.odometry + shift)
    a = run_slam3d(scans, data.cloud_frames[:keep], data.clouds[:keep], cfg)
    b = run_slam3d(far, data.cloud_frames[:keep], data.clouds[:keep], cfg)
    moved = b.result.trajectory.poses - a.result.trajectory.poses - shift
    assert np.abs(moved).max() < 1e-6
    assert np.subtract(b.result.map.origin, a.result.map.origin) == pytest.approx(shift[:2], abs=1e-6)
    near_voxels = VoxelMap.of_grid(a.voxels, offset=a.offset).occupied()
    far_voxels = VoxelMap.of_grid(b.voxels, offset=b.offset).occupied()
    assert len(near_voxels) > 1000 and far_voxels.shape == near_voxels.shape
    assert np.abs(far_voxels - shift - near_voxels).max() < 1e-6


@pytest.mark.parametrize("fallback", ["prediction", "draw"])
def test_rays_that_cannot_be_matched_leave_the_particles_at_the_prediction_unless_told_to_draw(fallback):
    from omnitof.geometry import compose, relative

    cfg = _config(particles=10, proposal="scanmatch", seed=4)
    cfg.scan_matcher.fallback = fallback
    pf = _core.ParticleFilter3D(**core_sections_3d(cfg))
    az, el = np.meshgrid(np.radians(np.arange(0, 360, 4)), np.radians([-20.0, -10.0, 0.0, 10.0, 20.0]))
    dirs = np.column_stack([(np.cos(el) * np.cos(az)).ravel(), (np.cos(el) * np.sin(az)).ravel(), np.sin(el).ravel()])
    origins = np.tile([0.0, 0.0, 0.6], (len(dirs), 1))
    odom0, odom1 = np.array([2.0, 1.0, -0.4]), np.array([2.3, 1.1, -0.3])
    pf.step(odom0, odom0, origins, origins + 2.0 * dirs, 0)  # a round room 2 m in radius
    start = pf.poses().copy()
    # Every ray ends 6 m out, in space the map has never seen: nothing to match.
    pf.step(odom0, odom1, origins, origins + 6.0 * dirs, 1)
    assert pf.fallbacks == 10
    predicted = compose(start, relative(odom0, odom1))
    if fallback == "prediction":
        np.testing.assert_allclose(pf.poses(), predicted, atol=1e-12)
    else:
        spread = np.abs(pf.poses() - predicted)
        assert spread.max() > 1e-4 and spread[:, :2].max() < 0.5


def _extruded_clouds(scans, frames, heights=(0.2, 0.5, 0.9, 1.4)):
    """3D rays of 2D laser scans in a world of vertical walls: from a sensor 0.5 m above the
    floor, each beam's wall point at each of `heights` (robot frame, (M, 6) per frame)."""
    clouds = []
    for k in frames:
        r, a = scans.ranges[k].astype(np.float64), scans.scan_angles(k)
        hit = np.isfinite(r) & (r < scans.max_range)
        xy = np.column_stack([r[hit] * np.cos(a[hit]), r[hit] * np.sin(a[hit])])
        ends = np.vstack([np.column_stack([xy, np.full(len(xy), z)]) for z in heights])
        origins = np.tile([0.0, 0.0, 0.5], (len(ends), 1))
        clouds.append(np.hstack([origins, ends]).astype(np.float32))
    return clouds


def test_the_back_end_repairs_a_loop_the_3d_filter_got_wrong(corridor_loop):
    # tests/test_backend.py's wrong turn (0.6 m and 8 degrees of odometry that never happened at
    # scan 150), seen by the 3D filter through walls extruded from the 2D scans: without its
    # odometry check the filter maps the rest of the loop turned; the back end finds the loop's
    # closures in the 2D scans, feeds the correction back to the voxel map, and writes the map
    # along the optimised poses.
    from scipy.spatial import cKDTree
    from test_scan_match import with_odometry_jump

    from omnitof.geometry import compose
    from omnitof.slam.driver import select_scans

    scans = with_odometry_jump(corridor_loop, 150, [0.6, 0.0, np.radians(8.0)])
    cfg = load_config(preset="sim2d", overrides={
        "filter": {"proposal": "scanmatch", "particles": 10},
        "filter3d": {"enabled": True, "score_z_min": 0.1, "sigma": 0.05},
    })
    frames = select_scans(scans.odometry, cfg.filter.linear_update, math.radians(cfg.filter.angular_update_deg))
    clouds = _extruded_clouds(scans, frames)
    alone_run = run_slam3d(scans, frames, clouds, cfg)
    alone = alone_run.result
    cfg.backend.enabled = True
    cfg.filter.threads = 2
    run = run_slam3d(scans, frames, clouds, cfg)
    repaired = run.result
    cfg.filter.threads = 1  # same seed, same result for one and two threads
    np.testing.assert_array_equal(run_slam3d(scans, frames, clouds, cfg).result.trajectory.poses, repaired.trajectory.poses)
    before = absolute_trajectory_error(alone.trajectory.poses, scans.ground_truth)
    after = absolute_trajectory_error(repaired.trajectory.poses, scans.ground_truth)
    # Measured: mean 1.21 -> 0.29 m, end 0.90 -> 0.04 m (the 2D filter: 1.21 -> 0.29, 0.64 -> 0.03).
    assert before.mean > 0.8 and before.final > 0.4, before
    assert after.final < 0.1 and after.mean < 0.5 * before.mean, after
    stats = repaired.stats["backend"]
    assert stats["closures_accepted"] >= 3
    assert repaired.graph is not None and len(repaired.graph["closures"]) == stats["closures_accepted"]
    np.testing.assert_allclose(repaired.trajectory.poses[frames], repaired.graph["nodes"], atol=1e-9)
    # Every optimisation fed back (the filter restarted on voxels rebuilt along the graph): the
    # loop is repaired as well.
    cfg.backend.feedback_xy = cfg.backend.feedback_deg = 0.0
    fed = run_slam3d(scans, frames, clouds, cfg).result
    assert fed.stats["backend"]["feedbacks"] >= 1
    assert absolute_trajectory_error(fed.trajectory.poses, scans.ground_truth).final < 0.1
    # The voxel map is the frames' rays at the optimised poses: nearer the true walls (the
    # extruded scans' end points at the true poses) than the filter's own map. Measured: median
    # distance 0.39 -> 0.14 m, within two voxels 29 -> 66 %.
    truth_pts = np.vstack([np.column_stack([compose(scans.ground_truth[k], np.column_stack([c[:, 3:5], np.zeros(len(c))]))[:, :2], c[:, 5]])
                           for k, c in zip(frames, clouds)])
    tree = cKDTree(truth_pts)

    def wall_distance(r):
        pts = r.voxels.occupied(0.0)
        pts[:, :2] += r.offset
        return tree.query(pts)[0]

    d_alone, d_repaired = wall_distance(alone_run), wall_distance(run)
    assert np.median(d_repaired) < 0.5 * np.median(d_alone)
    assert np.mean(d_repaired < 0.2) > 0.6 > 0.4 > np.mean(d_alone < 0.2)


def test_the_3d_runs_written_map_has_its_path_free(atrium_run):
    # map.footprint_radius (omnitof.slam.footprint) in the 3D filter's projection too: the cells
    # the robot drove over are known and free, every cell it changed lies within the radius of
    # the path and is set free, and no cell that held an obstacle changes. (Here the projection
    # had the path's own cells free already; the footprint sets its neighbours that were unknown
    # or only weakly free.)
    data, cfg = atrium_run
    keep = 8
    scans = data.scans.slice(0, int(data.cloud_frames[keep - 1]) + 1)
    radius = 0.3
    runs = [run_slam3d(scans, data.cloud_frames[:keep], data.clouds[:keep],
                       cfg.model_copy(update={"map": cfg.map.model_copy(update={"footprint_radius": r})})).result
            for r in (0.0, radius)]
    plain, cleared = (r.map for r in runs)
    np.testing.assert_array_equal(runs[0].trajectory.poses, runs[1].trajectory.poses)
    xy = runs[1].trajectory.poses[:, :2]
    res = cleared.resolution
    cells = np.floor((xy - np.asarray(cleared.origin)) / res).astype(int)
    assert cleared.known[cells[:, 1], cells[:, 0]].all()
    assert (cleared.probability[cells[:, 1], cells[:, 0]] < 0.5).all()
    dc = round((plain.origin[0] - cleared.origin[0]) / res)
    dr = round((plain.origin[1] - cleared.origin[1]) / res)
    h, w = plain.log_odds.shape
    before_lo, before_known = np.zeros_like(cleared.log_odds), np.zeros_like(cleared.known)
    before_lo[dr:dr + h, dc:dc + w], before_known[dr:dr + h, dc:dc + w] = plain.log_odds, plain.known
    obstacles = before_known & (before_lo > 0)
    np.testing.assert_array_equal(cleared.log_odds[obstacles], before_lo[obstacles])
    changed = (cleared.log_odds != before_lo) | (cleared.known != before_known)
    assert changed.any()
    assert np.all(cleared.log_odds[changed] == cfg.map.l_min)
    rows, cols = np.nonzero(changed)
    centres = np.asarray(cleared.origin) + (np.stack([cols, rows], axis=1) + 0.5) * res
    nearest = np.min(np.linalg.norm(centres[:, None, :] - xy[None, :, :], axis=2), axis=1)
    spacing = np.max(np.linalg.norm(np.diff(xy, axis=0), axis=1))
    assert nearest.max() <= radius + res / math.sqrt(2) + spacing / 2
