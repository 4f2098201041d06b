"""3D occupancy voxels (omnitof.map3d, rust/src/voxel.rs): traversal, updates, determinism,
PLY output and the map of a rendered room checked against the room's true surfaces."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnitof import _core
from omnitof.map3d import (
    DEFAULT_L_FREE,
    DEFAULT_L_MAX,
    DEFAULT_L_MIN,
    DEFAULT_L_OCC,
    IntegrateStats,
    Map3DError,
    VoxelMap,
    backproject_frame,
    build_voxel_map,
    surface_distance,
)
from omnitof.errors import InputError
from omnitof.io.ply import PlyError, read_ply, write_ply
from omnitof.viz.map3d import height_colors, plot_voxels

RES = 0.1


def one_ray(o, e, max_range=100.0, res=RES):
    vm = VoxelMap(res, max_range=max_range)
    stats = vm.integrate_world(np.array([o], float), np.array([e], float))
    idx, val = vm.observed()
    return stats, {tuple(i): v for i, v in zip(idx.tolist(), val.tolist())}


# --- traversal ------------------------------------------------------------------------------


def test_axis_ray_frees_its_path_and_marks_its_end_voxel():
    stats, vox = one_ray([0.05, 0.05, 0.05], [0.05, 0.05, 0.95])
    assert stats == IntegrateStats(hits=1, max_range=0, skipped=0, free_voxels=9, occupied_voxels=1)
    assert set(vox) == {(0, 0, k) for k in range(10)}
    for k in range(9):
        assert vox[(0, 0, k)] == pytest.approx(DEFAULT_L_FREE)
    assert vox[(0, 0, 9)] == pytest.approx(DEFAULT_L_OCC)


def test_negative_direction_and_diagonal_rays():
    # Along −x across zero: voxels 0, −1, ..., −10.
    _, vox = one_ray([0.05, 0.05, 0.05], [-0.95, 0.05, 0.05])
    assert set(vox) == {(-k, 0, 0) for k in range(11)}
    # A diagonal in the xy plane, off the voxel corners: it steps x and y in turn, so it visits
    # |Δi| + |Δj| + 1 voxels, each a face neighbour of the last.
    _, vox = one_ray([0.03, 0.07, 0.05], [0.53, 0.57, 0.05])
    assert len(vox) == 5 + 5 + 1
    assert (5, 5, 0) in vox and vox[(5, 5, 0)] > 0


def _slab_interval(seg0, seg1, voxel, res, tol):
    t0, t1 = 0.0, 1.0
    for a in range(3):
        lo, hi = voxel[a] * res - tol, (voxel[a] + 1) * res + tol
        d = seg1[a] - seg0[a]
        if abs(d) < 1e-15:
            if not lo <= seg0[a] <= hi:
                return 1.0, 0.0
            continue
        ta, tb = (lo - seg0[a]) / d, (hi - seg0[a]) / d
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
    return t0, t1


def test_traversal_against_brute_force_sampling():
    # The voxels one ray touches (all observed voxels of a fresh grid) are exactly those the
    # segment passes through: every voxel a dense sampling of the segment lands in (samples
    # within 1e-7 voxel of a face left out) is there, every voxel there meets the segment
    # (slab test, 1e-9 m tolerance), and there are |Δi| + |Δj| + |Δk| + 1 of them.
    rng = np.random.default_rng(5)
    for _ in range(40):
        s, e = rng.uniform(-1.5, 1.5, 3), rng.uniform(-1.5, 1.5, 3)
        _, vox = one_ray(s, e)
        t = np.linspace(0.0, 1.0, 40_001)[:, None]
        samples = s + t * (e - s)
        u = samples / RES
        frac = u - np.floor(u)
        clear = np.all((frac > 1e-7) & (frac < 1 - 1e-7), axis=1)
        sampled = {tuple(v) for v in np.floor(u[clear]).astype(int).tolist()}
        assert sampled <= set(vox)
        for v in vox:
            t0, t1 = _slab_interval(s, e, v, RES, 1e-9)
            assert t0 <= t1 + 1e-9, f"voxel {v} does not meet the segment {s} → {e}"
        i0, i1 = np.floor(s / RES).astype(int), np.floor(e / RES).astype(int)
        assert len(vox) == int(np.abs(i1 - i0).sum()) + 1
        assert vox[tuple(i1.tolist())] == pytest.approx(DEFAULT_L_OCC)


def test_long_and_invalid_rays():
    vm = VoxelMap(RES, max_range=0.5)
    o = np.full((3, 3), 0.05)
    e = np.array([[5.05, 0.05, 0.05], [np.nan, 0.0, 0.0], [0.05, 0.05, np.inf]])
    stats = vm.integrate_world(o, e)
    assert stats == IntegrateStats(hits=0, max_range=1, skipped=2, free_voxels=6, occupied_voxels=0)
    assert len(vm.occupied()) == 0
    lo = vm.log_odds_at(np.array([[0.55, 0.05, 0.05], [0.65, 0.05, 0.05], [np.nan, 0, 0]]))
    assert lo[0] == pytest.approx(DEFAULT_L_FREE) and np.isnan(lo[1]) and np.isnan(lo[2])


def test_repeated_frames_clamp_and_hits_win_within_a_frame():
    vm = VoxelMap(RES)
    o = np.full((2, 3), 0.05)
    e = np.array([[0.95, 0.05, 0.05], [0.45, 0.05, 0.05]])  # the 2nd ends where the 1st passes
    vm.integrate_world(o, e)
    probe = np.array([[0.05, 0.05, 0.05], [0.45, 0.05, 0.05], [0.95, 0.05, 0.05]])
    expected = [DEFAULT_L_FREE, DEFAULT_L_OCC, DEFAULT_L_OCC]
    np.testing.assert_allclose(vm.log_odds_at(probe), expected, rtol=1e-6)
    for _ in range(20):
        vm.integrate_world(o, e)
    np.testing.assert_allclose(vm.log_odds_at(probe), [DEFAULT_L_MIN, DEFAULT_L_MAX, DEFAULT_L_MAX])
    assert vm.frames == 21


def test_a_plane_of_points_gives_a_plane_of_occupied_voxels():
    # A sensor at 1.5 m looking down at the plane z = 0.23 over [-2, 2]²: the occupied voxels
    # are the layer k = 2 ([0.2, 0.3)) under the whole square, and the space above is free.
    g = np.arange(-1.995, 2.0, 0.03)
    x, y = np.meshgrid(g, g)
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, 0.23)], axis=1)
    vm = VoxelMap(RES)
    vm.integrate_world(np.tile([0.0, 0.0, 1.5], (len(pts), 1)), pts)
    occ = vm.occupied()
    np.testing.assert_allclose(occ[:, 2], 0.25)
    assert len(occ) == 40 * 40
    assert occ[:, 0].min() == pytest.approx(-1.95) and occ[:, 0].max() == pytest.approx(1.95)
    above = vm.log_odds_at(np.array([[0.0, 0.0, 1.0], [1.0, -1.0, 0.5], [0.3, 0.3, 0.35]]))
    assert np.all(above < 0)
    assert np.isnan(vm.log_odds_at(np.array([[0.0, 0.0, 0.1]])))[0]  # below the plane: unseen
    lo, hi = vm.bounds()
    np.testing.assert_allclose(lo, [-2.0, -2.0, 0.2])
    np.testing.assert_allclose(hi, [2.0, 2.0, 1.6])


def test_integrate_frame_maps_robot_rays_with_the_2d_pose():
    vm = VoxelMap(RES)
    # Robot at (2, 3) facing +y: the robot's +x is the world's +y; z is kept.
    pose = np.array([2.0, 3.0, math.pi / 2])
    vm.integrate_frame(pose, np.array([[0.0, 0.0, 0.5]]), np.array([[1.0, 0.0, 0.55]]))
    np.testing.assert_allclose(vm.occupied(), [[2.05, 4.05, 0.55]])


def test_result_is_independent_of_threads_and_ray_order():
    rng = np.random.default_rng(1)
    n = 20_000
    o = np.column_stack([rng.uniform(-0.2, 0.2, (n, 2)), np.full(n, 0.4)])
    e = rng.uniform(-4.0, 4.0, (n, 3))
    perm = rng.permutation(n)
    results = []
    for threads, order in ((1, slice(None)), (2, slice(None)), (None, perm), (3, perm[::-1])):
        vm = VoxelMap(RES, max_range=3.0, threads=threads)
        vm.integrate_world(o[order], e[order])
        vm.integrate_world(e[order], o[order])
        results.append(vm.observed())
    for idx, val in results[1:]:
        np.testing.assert_array_equal(idx, results[0][0])
        np.testing.assert_array_equal(val.view(np.uint32), results[0][1].view(np.uint32))
    assert len(results[0][0]) > 5000


def test_memory_and_counts():
    vm = VoxelMap(RES)
    assert vm.voxel_count() == 0 and vm.bounds() is None and len(vm.occupied()) == 0
    vm.integrate_world(np.array([[0.05, 0.05, 0.05]]), np.array([[0.95, 0.05, 0.05]]))
    # Ten voxels in two 8³ blocks of float32.
    assert vm.voxel_count() == 10
    assert vm.memory_bytes() >= 2 * 512 * 4


def test_bad_input_is_refused():
    with pytest.raises(Map3DError, match="resolution"):
        VoxelMap(0.0)
    with pytest.raises(Map3DError, match="max_range"):
        VoxelMap(max_range=-1.0)
    with pytest.raises(Map3DError, match="l_occ"):
        VoxelMap(l_occ=-0.5)
    with pytest.raises(ValueError, match="threads"):
        _core.VoxelGrid(0.1, 0.9, -0.4, -2.0, 3.5, 0)
    vm = VoxelMap()
    with pytest.raises(Map3DError, match=r"\(N, 3\)"):
        vm.integrate_world(np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(Map3DError, match="differ"):
        vm.integrate_world(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(Map3DError, match="index range"):
        vm.integrate_world(np.zeros((1, 3)), np.array([[1e7, 0.0, 0.0]]))
    with pytest.raises(Map3DError, match="pose"):
        vm.integrate_frame(np.array([0.0, np.nan, 0.0]), np.zeros((1, 3)), np.ones((1, 3)))
    with pytest.raises(Map3DError, match="more frames"):
        build_voxel_map([np.zeros(3)], [(np.zeros((1, 3)), np.ones((1, 3)))] * 2)
    with pytest.raises(Map3DError, match="frames for more poses"):
        build_voxel_map([np.zeros(3)] * 2, [(np.zeros((1, 3)), np.ones((1, 3)))])


# --- PLY ------------------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("with_colors", [True, False])
def test_ply_round_trip(tmp_path, binary, with_colors):
    rng = np.random.default_rng(2)
    pts = np.round(rng.uniform(-5, 5, (57, 3)), 2)
    cols = height_colors(pts) if with_colors else None
    path = tmp_path / "cloud.ply"
    write_ply(path, pts, cols, binary=binary)
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = header.decode("ascii").splitlines()
    assert lines[0] == "ply"
    assert lines[1] == f"format {'binary_little_endian' if binary else 'ascii'} 1.0"
    assert "element vertex 57" in lines
    props = [ln for ln in lines if ln.startswith("property")]
    expected = ["property float x", "property float y", "property float z"]
    if with_colors:
        expected += ["property uchar red", "property uchar green", "property uchar blue"]
    assert props == expected
    if binary:
        # Independent of read_ply: the body is exactly N little-endian records.
        stride = 12 + (3 if with_colors else 0)
        assert len(body) == 57 * stride
        first = np.frombuffer(body[:12], dtype="<f4")
        np.testing.assert_allclose(first, pts[0], atol=1e-6)
    else:
        assert len(body.decode("ascii").splitlines()) == 57
    back, back_cols = read_ply(path)
    np.testing.assert_array_equal(back, pts.astype(np.float32).astype(np.float64))
    if with_colors:
        np.testing.assert_array_equal(back_cols, cols)
    else:
        assert back_cols is None


def test_ply_of_nothing_and_bad_colours(tmp_path):
    write_ply(tmp_path / "empty.ply", np.zeros((0, 3)))
    pts, cols = read_ply(tmp_path / "empty.ply")
    assert pts.shape == (0, 3) and cols is None
    with pytest.raises(PlyError, match="uint8"):
        write_ply(tmp_path / "x.ply", np.zeros((2, 3)), np.zeros((2, 3)))
    assert not (tmp_path / "x.ply").exists()


# --- the rendered room ----------------------------------------------------------------------


def _quad_distance(points, quad):
    """Distance (N,) from points to one vertical quad [ax, ay, bx, by, bottom, top]."""
    a, b = quad[0:2], quad[2:4]
    t = np.clip((points[:, :2] - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    horizontal = np.linalg.norm(points[:, :2] - (a + t[:, None] * (b - a)), axis=1)
    vertical = np.maximum(np.maximum(quad[4] - points[:, 2], points[:, 2] - quad[5]), 0.0)
    return np.hypot(horizontal, vertical)


def test_surface_distance_of_known_points():
    from omnitof.sim.worlds import load_world

    world = load_world("room")
    pts = np.array([
        [1.0, 0.3, 1.5],   # 0.3 m in front of the south wall
        [2.0, 2.0, 2.4],   # 0.2 m below the ceiling
        [2.0, 2.0, 0.04],  # 4 cm above the floor
        [3.0, 2.25, 0.7],  # inside the sideboard (top at 0.75 m)
        [3.0, 2.25, 0.9],  # 0.15 m above it
    ])
    expected = [0.3, 0.2, 0.04, 0.05, 0.15]
    np.testing.assert_allclose(surface_distance(pts, world), expected, atol=1e-9)


@pytest.fixture(scope="module")
def room_scene():
    from omnitof.sensor import mirrors as mirror_module
    from omnitof.sensor.design import default_rig
    from omnitof.sim.render import Renderer
    from omnitof.sim.worlds import load_world

    world = load_world("room")
    rig = default_rig()
    camera, mirrors = rig.camera, rig.mirrors
    mount = mirror_module.camera_mount()
    labels = mirror_module.masks(camera, mirrors)
    renderer = Renderer(world, camera, mirrors, robot_T_camera=mount)
    corners = world.waypoints
    poses = []
    for i in range(len(corners)):
        a, b = corners[i], corners[(i + 1) % len(corners)]
        heading = math.atan2(b[1] - a[1], b[0] - a[0])
        poses += [[*(a + t * (b - a)), heading] for t in (0.0, 0.5)]
    frames = []
    for k, pose in enumerate(np.array(poses)):
        frame = renderer.render(pose, seed=k)
        # Drop the weakest tenth of the pixels (flying pixels, specular ghosts).
        valid = frame.amplitude > np.percentile(frame.amplitude[labels >= 0], 10)
        rays = backproject_frame(frame.distance, camera, mirrors, labels, mount, valid=valid)
        frames.append((pose, rays))
    return world, frames


def test_backprojected_points_lie_on_the_room_surfaces(room_scene):
    world, frames = room_scene
    pose, (origins, points) = frames[0]
    assert len(points) > 15_000
    c, s = math.cos(pose[2]), math.sin(pose[2])
    world_points = points.copy()
    world_points[:, :2] = points[:, :2] @ np.array([[c, -s], [s, c]]).T + pose[:2]
    d = surface_distance(world_points, world)
    # The ranges carry the sensor's noise (a few cm); a path length not reduced by the camera–
    # mirror leg |o| would put every point about 0.15 m too far.
    assert np.median(d) < 0.02
    assert np.mean(d < 0.1) > 0.95
    # Origins are on the mirrors: above the lens (0.40 m) and within 0.3 m of the axis.
    assert np.all(origins[:, 2] > 0.40) and np.all(np.hypot(origins[:, 0], origins[:, 1]) < 0.3)


def test_room_map_has_occupied_voxels_on_the_true_surfaces(room_scene, tmp_path):
    world, frames = room_scene
    vm = build_voxel_map((p for p, _ in frames), (f for _, f in frames))
    assert vm.frames == len(frames)
    occ = vm.occupied()
    assert len(occ) > 3000
    d = surface_distance(occ, world)
    # A voxel holding a surface point has its centre within √3/2·0.1 = 0.087 m of the surface.
    assert np.median(d) <= 0.05 + 1e-9
    assert np.mean(d < 0.15) >= 0.9
    # Every wall of the room is mapped.
    for quad in world.quads[[0, 1, 8, 9]]:
        near = _quad_distance(occ, quad) < 0.1
        assert near.sum() >= 30, quad
    # The robot's own path is free at the camera's height.
    poses = np.array([p for p, _ in frames])
    path = np.column_stack([poses[:, :2], np.full(len(poses), 0.8)])
    assert np.all(vm.log_odds_at(path) < 0)
    png = tmp_path / "room.png"
    plot_voxels(png, occ, trajectory=poses, title="room")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    write_ply(tmp_path / "room.ply", occ, height_colors(occ))
    back, _ = read_ply(tmp_path / "room.ply")
    np.testing.assert_allclose(back, occ, atol=1e-5)


@pytest.mark.parametrize(
    ("points", "message"),
    [
        ([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]], r"point 1 is not finite: \[nan, 0.0, 0.0\]"),
        ([[0.0, -np.inf, 0.0]], r"point 0 is not finite: \[0.0, -inf, 0.0\]"),
        ([[0.0, 0.0, 0.0], [0.0, 0.0, 1e300]], r"point 1 lies beyond float32's range \(±3.4e\+38\) of PLY float coordinates: \[0.0, 0.0, 1e\+300\]"),
    ],
)
def test_ply_writer_refuses_points_the_reader_would_refuse(tmp_path, points, message):
    with pytest.raises(PlyError, match=message):
        write_ply(tmp_path / "p.ply", np.array(points))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("comment", ["x\nend_header", "x\x0bend_header", "a\rb", "a\x0cb", "a\x1cb", "a\x1eb", "café", "a\u2028b", "a\x85b"])
def test_ply_comment_must_be_one_ascii_line(tmp_path, comment):
    with pytest.raises(PlyError, match=r"the comment must be one line of ASCII text, got "):
        write_ply(tmp_path / "p.ply", np.zeros((1, 3)), comment=comment)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("binary", [True, False])
def test_ply_comment_holding_end_header_round_trips(tmp_path, binary):
    pts = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    write_ply(tmp_path / "p.ply", pts, binary=binary, comment="ends at end_header")
    back, _ = read_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(back, pts)


def _ply_text(properties, rows, newline="\n"):
    header = ["ply", "format ascii 1.0", f"element vertex {len(rows)}", *properties, "end_header"]
    return newline.join(header + [" ".join(map(str, r)) for r in rows]) + newline


def test_ply_float_colours_are_fractions_scaled_to_255(tmp_path):
    props = ["property float x", "property float y", "property float z",
             "property float red", "property float green", "property double blue"]
    path = tmp_path / "c.ply"
    path.write_text(_ply_text(props, [[0, 0, 0, 0.8, 0.0, 1.0], [1, 1, 1, 0.5, 0.25, 0.1]]))
    _, cols = read_ply(path)
    np.testing.assert_array_equal(cols, [[204, 0, 255], [128, 64, 26]])
    path.write_text(_ply_text(props, [[0, 0, 0, 1.5, 0.0, 0.0]]))
    with pytest.raises(InputError, match=r"c.ply: PLY colours must lie in 0..255 \(0..1 for float properties\)"):
        read_ply(path)


def test_ply_integer_colours_stay_0_to_255(tmp_path):
    props = ["property float x", "property float y", "property float z",
             "property uchar red", "property ushort green", "property int blue"]
    path = tmp_path / "c.ply"
    path.write_text(_ply_text(props, [[0, 0, 0, 255, 1, 0]]))
    _, cols = read_ply(path)
    np.testing.assert_array_equal(cols, [[255, 1, 0]])
    path.write_text(_ply_text(props, [[0, 0, 0, 0, 256, 0]]))
    with pytest.raises(InputError, match=r"PLY colours must lie in 0..255"):
        read_ply(path)


def test_ply_with_crlf_line_ends_says_so(tmp_path):
    path = tmp_path / "w.ply"
    path.write_bytes(_ply_text(["property float x", "property float y", "property float z"], [[0, 0, 0]], "\r\n").encode())
    with pytest.raises(InputError, match=r"w.ply: the PLY header's lines end in CRLF \(\\r\\n\)"):
        read_ply(path)
