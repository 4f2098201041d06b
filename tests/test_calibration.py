"""Tests of omnitof.calibration: the calibration file, intrinsics from a checkerboard, the
mirror planes from the four-dot target (paper sec. II-C, eq. 5 and 6), masks and the checks."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from omnitof.calibration import (
    Calibration,
    CalibrationError,
    decode_rows,
    encode_rows,
    load_calibration,
    save_calibration,
)
from omnitof.sensor.design import default_rig


@pytest.fixture(scope="module")
def rig():
    return default_rig()


# --- the calibration file ------------------------------------------------------------------


def test_from_rig_is_the_true_geometry(rig):
    from omnitof.sensor.mirrors import masks

    camera, mirrors = rig.camera, rig.mirrors
    cal = Calibration.from_rig(rig)
    assert cal.names == [m.name for m in mirrors]
    assert np.array_equal(cal.labels, masks(camera, mirrors, 2.0))
    for plane, mirror in zip(cal.planes, mirrors):
        assert np.allclose(plane.normal, mirror.plane.normal) and plane.d == mirror.plane.d
    # eq. 6: the virtual camera maps a point to where the real camera sees it in the mirror.
    point = np.array([0.3, -1.2, -0.1])
    pv = cal.virtual_cameras()[0] @ np.append(point, 1.0)
    image = mirrors[0].plane.reflect_points(point[None])[0]
    assert np.allclose(pv[:2] / pv[2], (camera.K @ image)[:2] / image[2])


def test_save_load_round_trip_is_exact(rig, tmp_path):
    camera = rig.camera
    cal = Calibration.from_rig(rig)
    cal.polygons = {"front": np.array([[0.0, 0.0], [175.0, 0.0], [88.0, 70.0]])}
    cal.quality = {"intrinsics_rms_px": 0.1, "mirrors": {"front": {"inliers": 12}}}
    path = save_calibration(cal, tmp_path / "cal.yaml")
    back = load_calibration(path)
    assert back.camera == camera
    assert np.array_equal(back.labels, cal.labels) and back.labels.dtype == np.int32
    assert back.names == cal.names
    for a, b in zip(back.planes, cal.planes):
        assert np.array_equal(a.normal, b.normal) and a.d == b.d
    assert np.array_equal(back.robot_T_camera, cal.robot_T_camera)
    assert np.array_equal(back.polygons["front"], cal.polygons["front"])
    assert back.quality["mirrors"]["front"]["inliers"] == 12
    assert back.edge_margin_px == 2.0


def test_rows_encoding_round_trip():
    labels = np.random.default_rng(1).integers(-1, 3, size=(5, 9)).astype(np.int32)
    assert np.array_equal(decode_rows(encode_rows(labels), labels.shape), labels)
    assert encode_rows(np.array([[-1, -1, 0, 0, 0, 2]])) == ["-1*2 0*3 2*1"]


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("fx: ", "fx: -"), "camera"),
        (lambda t: t.replace("  d: 0.0829", "  d: -0.0829", 1), "mirrors[0]"),
        (lambda t: t.replace("omnitof_calibration: 1", "omnitof_calibration: 7"), "version"),
        (lambda t: t.replace("  - 3*5 ", "  - 3*6 ", 1), "masks.rows[0]"),
        (lambda t: t.replace("normal: [0.0, ", "normal: [", 1), "mirrors[0].normal"),
    ],
)
def test_bad_file_names_file_and_field(rig, tmp_path, edit, message):
    path = save_calibration(Calibration.from_rig(rig), tmp_path / "cal.yaml")
    path.write_text(edit(path.read_text()))
    with pytest.raises(CalibrationError) as err:
        load_calibration(path)
    assert str(path) in str(err.value) and message in str(err.value)


def _set(*keys, value):
    """An edit of the calibration's YAML data: the field at `keys` set to `value`."""
    def edit(data):
        for key in keys[:-1]:
            data = data[key]
        data[keys[-1]] = value
    return edit


def _turn_mirror0(normal):
    return _set("mirrors", 0, "normal", value=normal)


@pytest.mark.parametrize(
    "edit, message",
    [
        (_set("quality", value="good"), "quality: expected a mapping, got 'good'"),
        (_set("quality", value=5), "quality: expected a mapping, got 5"),
        (_set("quality", value=[1, 2]), "quality: expected a mapping"),
        (_set("provenance", value="me"), "provenance: expected a mapping, got 'me'"),
        (_set("mirrors", 0, "quality", value="good"), r"mirrors\[0\].quality: expected a mapping"),
        (_set("masks", "rows", 0, value="0*99999999999999999999"), r"masks.rows\[0\]: runs cover more than"),
        (_set("masks", "rows", 0, value="0*1000000000"), r"masks.rows\[0\]: runs cover more than"),
        (_set("masks", "polygons", value={"front": [[0, 0], [1], [2, 2]]}), "masks.polygons.front: expected"),
        (_set("mirrors", 0, "name", value=None), r"mirrors\[0\].name: expected a text, got None"),
        (_set("mirrors", 0, "name", value=5), r"mirrors\[0\].name: expected a text"),
        (_set("mirrors", 0, "name", value=["a"]), r"mirrors\[0\].name: expected a text"),
        (_set("mirrors", 0, "d", value="0.08"), r"mirrors\[0\].d: expected a number"),
        (_set("camera", "dist", value=[True, 0, 0, 0, 0]), "camera.dist: True is not a number"),
        (_set("mirrors", 0, "normal", value=["0.5", 0.5, 0.7]), r"mirrors\[0\].normal: '0.5' is not a number"),
        (_set("omnitof_calibration", value=True), "omnitof_calibration: expected format version 1, got True"),
        (_turn_mirror0([0.0, 0.0, 1.0]), r"mirrors\[0\] \(.*\): the normal is 0.0° from the optical axis, within 5°"),
        (_turn_mirror0([0.0, 1.0, 0.0]), "within 5° of perpendicular"),
        (_turn_mirror0([0.0, 0.56, -0.83]), "behind the camera"),
    ],
)
def test_wrong_typed_or_impossible_fields_name_the_field(rig, tmp_path, edit, message):
    from omnitof.errors import dump_yaml, load_yaml

    cal = Calibration.from_rig(rig)
    cal.polygons = {"front": np.array([[0.0, 0.0], [175.0, 0.0], [88.0, 70.0]])}
    path = save_calibration(cal, tmp_path / "cal.yaml")
    data = load_yaml(path.read_text())
    edit(data)
    path.write_text(dump_yaml(data))
    with pytest.raises(CalibrationError, match=message) as err:
        load_calibration(path)
    assert str(path) in str(err.value)


def test_mirrors_facing_the_same_way_are_no_pyramid(rig, tmp_path):
    from omnitof.errors import dump_yaml, load_yaml

    path = save_calibration(Calibration.from_rig(rig), tmp_path / "cal.yaml")
    data = load_yaml(path.read_text())
    data["mirrors"][2]["normal"] = data["mirrors"][0]["normal"]
    path.write_text(dump_yaml(data))
    with pytest.raises(CalibrationError, match=r"mirrors\[2\] \(.*\) faces the same way as mirrors\[0\]"):
        load_calibration(path)


# --- shared simulated data -----------------------------------------------------------------

PLACEMENTS = 8  # dot-target placements per mirror in the accuracy tests


@pytest.fixture(scope="module")
def dot_images(rig):
    from omnitof.calibration.targets import render_dot_images

    camera, mirrors = rig.camera, rig.mirrors
    images, truth = render_dot_images(camera, mirrors, PLACEMENTS, seed=3)
    return images, truth


def _calibrate(rig, images, **kwargs):
    from omnitof.calibration.mirror_planes import calibrate_mirrors
    from omnitof.sensor.mirrors import assign_pixels

    camera, mirrors = rig.camera, rig.mirrors
    return calibrate_mirrors(
        camera, images, [m.name for m in mirrors], [m.plane for m in mirrors],
        assign_pixels(camera, mirrors), **kwargs
    )


def _errors(result, mirrors):
    out = {}
    for estimate, mirror in zip(result.estimates, mirrors):
        cos = float(np.clip(estimate.plane.normal @ mirror.plane.normal, -1.0, 1.0))
        out[mirror.name] = (np.degrees(np.arccos(cos)), 1000.0 * (estimate.plane.d - mirror.plane.d))
    return out


# --- intrinsics ----------------------------------------------------------------------------


def test_intrinsics_from_noisy_checkerboards(rig):
    from omnitof.calibration.intrinsics import calibrate_intrinsics
    from omnitof.calibration.targets import render_checkerboard_images

    camera = rig.camera
    images, _ = render_checkerboard_images(camera, 12, seed=2)
    result = calibrate_intrinsics(images)
    assert result.rms_px < 0.15
    assert abs(result.camera.fx / camera.fx - 1.0) < 0.01
    assert abs(result.camera.fy / camera.fy - 1.0) < 0.01
    assert abs(result.camera.cx - camera.cx) < 1.5 and abs(result.camera.cy - camera.cy) < 1.5
    # Over the image, the calibrated model sends the true rays near their pixels (the extreme
    # corners, which no board reaches, extrapolate the distortion and are worse).
    v, u = np.mgrid[4:140:8, 4:172:8]
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
    moved = np.linalg.norm(result.camera.project(camera.rays(pixels)) - pixels, axis=1)
    assert np.percentile(moved, 90) < 1.5


def _corner_image(corner, angles, gradient, size=25, samples=32):
    """A checkerboard corner at `corner` (u, v) whose two edges run at `angles` (radians; not at
    right angles, as perspective makes them), each pixel the exact mean over a samples² grid of
    its area, lit by a light that grows by `gradient` per pixel along u."""
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    v, u = np.mgrid[0:size, 0:size].astype(float)
    su = u[..., None, None] + offsets[None, None, None, :]
    sv = v[..., None, None] + offsets[None, None, :, None]
    du, dv = su - corner[0], sv - corner[1]
    side = [np.sign(np.cos(a) * dv - np.sin(a) * du) for a in angles]
    albedo = np.where(side[0] * side[1] > 0, 0.85, 0.05).mean(axis=(-1, -2))
    return albedo * (1.0 + gradient * (u - corner[0]))


@pytest.mark.parametrize("corner, angles, gradient", [
    ((12.37, 11.81), (0.3, 1.75), 0.02),
    ((11.62, 12.55), (-0.5, 0.9), -0.02),
    ((12.05, 12.93), (0.1, 1.4), 0.0),
])
def test_saddle_points_find_an_analytic_corner(corner, angles, gradient):
    from omnitof.calibration.intrinsics import saddle_points

    image = _corner_image(corner, angles, gradient)
    start = np.array([corner]) + [0.3, -0.25]  # as far off as the detector's first guess
    found = saddle_points(image, start)[0]
    # 0.013–0.018 px measured; cv2.cornerSubPix on the same images 0.02–0.12 px.
    assert np.hypot(*(found - corner)) < 0.03, found
    # A flat patch has no saddle: the point stays where it was.
    assert np.array_equal(saddle_points(np.ones((25, 25)), start), start)


def test_saddle_points_on_a_board_of_large_squares():
    """A camera of more pixels sees larger squares (40 px here, turned, under a light gradient,
    with 1 % noise): the level window (9 px) then holds one colour in places; the corners must
    still come out right (measured 0.021 px RMS)."""
    from omnitof.calibration.intrinsics import saddle_points

    rng = np.random.default_rng(0)
    square, turn, origin = 40.0, 0.3, np.array([37.3, 41.6])
    offsets = (np.arange(8) + 0.5) / 8 - 0.5
    v, u = np.mgrid[0:260, 0:260].astype(float)
    su = u[..., None, None] + offsets[None, None, None, :] - origin[0]
    sv = v[..., None, None] + offsets[None, None, :, None] - origin[1]
    x = (np.cos(turn) * su + np.sin(turn) * sv) / square
    y = (-np.sin(turn) * su + np.cos(turn) * sv) / square
    albedo = np.where((np.floor(x) + np.floor(y)) % 2 == 0, 0.85, 0.05).mean(axis=(-1, -2))
    image = albedo * (1.0 + 0.004 * (u - 130.0)) + rng.normal(0.0, 0.01, albedo.shape)
    i, j = (g.ravel() for g in np.mgrid[1:5, 1:5])
    truth = origin + square * np.stack([np.cos(turn) * i - np.sin(turn) * j,
                                        np.sin(turn) * i + np.cos(turn) * j], axis=1)
    found = saddle_points(image, truth + rng.uniform(-0.2, 0.2, truth.shape))
    assert np.sqrt(np.mean(np.sum((found - truth) ** 2, axis=1))) < 0.04


def test_checkerboard_corners_lie_on_the_true_projections(rig):
    from scipy.spatial import cKDTree

    from omnitof.calibration.intrinsics import detect_checkerboard
    from omnitof.calibration.targets import Checkerboard, render_checkerboard_images

    board, camera = Checkerboard(), rig.camera
    images, poses = render_checkerboard_images(camera, 4, seed=5)
    errors = []
    for image, pose in zip(images, poses):
        corners = detect_checkerboard(image.amplitude, board.pattern_size)
        assert corners is not None, image.name
        truth = camera.project(board.object_points() @ pose[:3, :3].T + pose[:3, 3])
        # A board printed alike on both sides may be found in mirrored order: nearest truth.
        _, nearest = cKDTree(truth).query(corners)
        assert len(set(nearest)) == len(truth)
        errors.append(corners - truth[nearest])
    rms = float(np.sqrt(np.mean(np.sum(np.concatenate(errors) ** 2, axis=1))))
    # 0.018–0.024 px measured (seeds 0–2, 30 boards); cv2.cornerSubPix gave 0.10 px.
    assert rms < 0.04, rms


def test_edge_pixels_get_every_sub_ray(rig, monkeypatch):
    """The adaptive sampling of target images (16 sub-rays, all 64 where the 16 disagree) against
    tracing every pixel with 64: the pixels on edges are the same, the rest within the sampling's
    smooth error, and the corners found in both images agree."""
    from omnitof.calibration import targets
    from omnitof.calibration.intrinsics import detect_checkerboard

    board = targets.Checkerboard()
    pose = targets.checkerboard_poses(rig.camera, board, 1, seed=7)[0]

    def image():
        frame, _ = targets.render_target(rig.camera, board, pose, (), rng=0, sensor=rig.sensor, noise=False)
        return frame.amplitude

    adaptive = image()
    monkeypatch.setattr(targets, "COARSE_SUB_RAYS", targets.DEFAULT_SUB_RAYS)
    full = image()
    relative = np.abs(adaptive - full) / np.maximum(np.abs(full), 1e-9)
    # Measured (board seeds 7–9): median 1e-4, 99th percentile 7e-4, corners within 0.0002 px.
    assert np.median(relative) < 1e-3 and np.percentile(relative, 99) < 0.005
    a, b = (detect_checkerboard(x, board.pattern_size) for x in (adaptive, full))
    assert np.max(np.hypot(*(a - b).T)) < 0.002


def test_intrinsics_reads_png_and_rejects_too_few_boards(rig, tmp_path):
    import cv2

    from omnitof.calibration.images import load_images
    from omnitof.calibration.intrinsics import calibrate_intrinsics

    camera = rig.camera
    cv2.imwrite(str(tmp_path / "blank.png"), np.full(camera.shape, 1000, np.uint16))
    images = load_images([tmp_path])
    assert images[0].amplitude.shape == camera.shape and images[0].distance is None
    with pytest.raises(CalibrationError, match="blank.png"):
        calibrate_intrinsics(images)


def test_a_truncated_npz_a_tiny_image_and_a_tiny_board_are_user_mistakes(tmp_path, capfd):
    # Each was a traceback (zipfile.BadZipFile; cv2.error from the detector's thresholding;
    # cv2.error from findChessboardCorners).
    from omnitof.calibration.images import load_images
    from omnitof.calibration.intrinsics import detect_checkerboard
    from omnitof.cli import main

    whole = tmp_path / "whole.npz"
    np.savez(whole, amplitude=np.ones((20, 30), np.float32))
    cut = tmp_path / "cut.npz"
    cut.write_bytes(whole.read_bytes()[:100])
    with pytest.raises(CalibrationError, match="cut.npz: cannot read the npz file"):
        load_images([cut])
    with pytest.raises(CalibrationError, match="gone.png: no such file or folder"):
        load_images([tmp_path / "gone.png"])  # was OpenCV's own warning, then "cannot read the image"
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    capfd.readouterr()
    with pytest.raises(CalibrationError, match="garbage.png: cannot read the image"):
        load_images([garbage])
    assert capfd.readouterr().err == ""  # OpenCV's [ WARN ] and [ERROR] lines held back: one message
    for side in (1, 3, 14):
        assert detect_checkerboard(np.random.default_rng(0).random((side, 40)), (7, 5)) is None
    for board in ("3x3", "1x8", "8x0"):
        assert main(["calibrate", "intrinsics", "--out", str(tmp_path / "c.yaml"), "--board", board, str(whole)]) == 2
        err = capfd.readouterr().err
        assert "--board: needs at least 4x4 squares" in err and err.count("\n") == 1
    assert not (tmp_path / "c.yaml").exists()


def test_a_board_that_is_not_the_printed_one_warns(rig):
    # 4x4 squares asked of 8x6 boards: a part of each board is found, and the fit (4 px RMS,
    # fy a tenth of fx) was written without a word.
    import warnings

    from omnitof.calibration.intrinsics import calibrate_intrinsics
    from omnitof.calibration.targets import Checkerboard, render_checkerboard_images
    from omnitof.errors import OmnitofWarning

    images, _ = render_checkerboard_images(rig.camera, 6, seed=4)
    with pytest.warns(OmnitofWarning, match=r"the intrinsics fit badly: .* is the board 4x4 squares as printed"):
        calibrate_intrinsics(images, Checkerboard(cols=4, rows=4))
    with warnings.catch_warnings():
        warnings.simplefilter("error", OmnitofWarning)
        assert calibrate_intrinsics(images).rms_px < 0.2  # the printed board: no warning


def test_intrinsics_from_a_ros_bag(rig, tmp_path):
    from omnitof.calibration.images import load_images
    from omnitof.calibration.intrinsics import calibrate_intrinsics
    from omnitof.calibration.targets import render_checkerboard_images
    from omnitof.io.rosbag import ToFFrameStamped, write_tof_bag
    from omnitof.types import Trajectory

    camera = rig.camera
    images, _ = render_checkerboard_images(camera, 8, seed=4)
    frames = [ToFFrameStamped(0.1 * (k + 1), im.distance, im.amplitude) for k, im in enumerate(images)]
    odometry = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)))
    write_tof_bag(tmp_path / "boards", frames, camera=camera, odometry=odometry)
    loaded = load_images([tmp_path / "boards"])
    assert len(loaded) == 8 and loaded[0].name.endswith("frame0")
    assert np.array_equal(loaded[3].amplitude, images[3].amplitude)
    result = calibrate_intrinsics(loaded)
    assert abs(result.camera.fx / camera.fx - 1.0) < 0.01


# --- mirrors (paper sec. II-C, eq. 5) --------------------------------------------------------


def test_mirror_planes_meet_the_targets(rig, dot_images):
    camera, mirrors = rig.camera, rig.mirrors
    images, _ = dot_images
    result = _calibrate(rig, images)
    for name, (angle, dd) in _errors(result, mirrors).items():
        assert angle < 0.2, f"{name}: normal off by {angle:.3f}°"
        assert abs(dd) < 2.0, f"{name}: plane distance off by {dd:.2f} mm"
    for estimate in result.estimates:
        assert len(estimate.images) == PLACEMENTS and estimate.rms_px < 0.2
    # eq. 6: the calibrated virtual camera sees a dot where the image shows it in the mirror.
    truth = Calibration.from_rig(rig)
    cal = truth.with_rig(replace(truth.rig, planes=tuple(result.planes)))
    point = np.array([0.02, -0.06, 0.11])
    pv = cal.virtual_cameras()[0] @ np.append(point, 1.0)
    true_image = mirrors[0].plane.reflect_points(point[None])[0]
    assert np.allclose(pv[:2] / pv[2], (camera.K @ true_image)[:2] / true_image[2], atol=0.5)


def test_scale_from_tof_distances(rig, dot_images):
    mirrors = rig.mirrors
    result = _calibrate(rig, dot_images[0], scale="tof")
    for name, (angle, dd) in _errors(result, mirrors).items():
        assert abs(dd) < 3.0, f"{name}: ToF-scaled plane distance off by {dd:.2f} mm"


def _paint_disc(image, centre, radius, value):
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    image[(u - centre[0]) ** 2 + (v - centre[1]) ** 2 <= radius**2] = value


def test_bad_image_is_rejected_and_reported(rig, dot_images):
    from omnitof.calibration.images import AmplitudeImage
    from omnitof.calibration.mirror_planes import detect_views

    mirrors = rig.mirrors
    images, _ = dot_images
    bad = images[0]
    views = detect_views(bad)
    direct = min(views[:2], key=lambda view: view.distance)
    amplitude = bad.amplitude.copy()
    white = float(np.percentile(amplitude[np.abs(bad.distance - direct.distance) < 0.01], 90))
    # A dot hidden (a thumb over it) and a false blob (a smudge on the card between the dots).
    _paint_disc(amplitude, direct.dots[0], 3.5, white)
    smudge = direct.dots.mean(axis=0) * 0.6 + direct.dots[0] * 0.4
    _paint_disc(amplitude, smudge, 1.6, 0.05 * white)
    corrupted = [AmplitudeImage(bad.name, amplitude, bad.distance)] + images[1:]
    result = _calibrate(rig, corrupted)
    front = result.estimates[0]
    assert any(bad.name in message for message in front.rejected)
    assert any(bad.name in line for line in result.report())
    for name, (angle, dd) in _errors(result, mirrors).items():
        assert angle < 0.2 and abs(dd) < 2.0, name


def test_clear_errors_name_image_and_mirror(rig, dot_images):
    from omnitof.calibration.images import AmplitudeImage
    from omnitof.calibration.mirror_planes import detect_views

    camera = rig.camera
    images, _ = dot_images
    blank = AmplitudeImage("empty.npz", np.full(camera.shape, 50.0, np.float32),
                           np.full(camera.shape, 2.0, np.float32))
    with pytest.raises(CalibrationError, match=r"empty\.npz.*no dots"):
        _calibrate(rig, [blank])
    # One dot left in each view: one correspondence, not enough.
    one = images[0]
    amplitude = one.amplitude.copy()
    for view in detect_views(one)[:2]:
        white = float(np.max(amplitude[np.abs(one.distance - view.distance) < 0.01]))
        for dot in view.dots[1:]:
            _paint_disc(amplitude, dot, 3.5, white)
    with pytest.raises(CalibrationError, match=rf"{one.name}.*'front'.*at least two"):
        _calibrate(rig, [AmplitudeImage(one.name, amplitude, one.distance)])
    # A mirror never seen.
    without_back = [im for im in images if not im.name.startswith("back")]
    with pytest.raises(CalibrationError, match="'back'.*no image"):
        _calibrate(rig, without_back)


# --- masks -----------------------------------------------------------------------------------


def test_masks_from_planes_and_polygons(rig, tmp_path):
    from omnitof.calibration.masks import (
        labels_from_planes,
        labels_from_polygons,
        polygons_from_labels,
        read_polygon_file,
        write_polygon_file,
    )
    from omnitof.sensor.mirrors import assign_pixels, masks

    camera, mirrors = rig.camera, rig.mirrors
    names = [m.name for m in mirrors]
    outside = assign_pixels(camera, mirrors) < 0
    labels = labels_from_planes(camera, [m.plane for m in mirrors], outside, 2.0)
    assert np.array_equal(labels, masks(camera, mirrors, 2.0))
    # By hand (the paper's way): polygons drawn around the regions, edited, redrawn.
    polygons = polygons_from_labels(assign_pixels(camera, mirrors), names)
    path = write_polygon_file(tmp_path / "regions.yaml", polygons)
    redrawn = labels_from_polygons(camera, names, read_polygon_file(path), 2.0)
    assert np.mean(redrawn != labels) < 0.02
    square = {"front": np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]])}
    hand = labels_from_polygons(camera, names, square, 0.0)
    assert (hand == 0).sum() == 121 and (hand == 0)[10:21, 10:21].all()
    with pytest.raises(CalibrationError, match="nowhere"):
        labels_from_polygons(camera, names, {"nowhere": square["front"]})


def test_masks_exported_and_redrawn_unedited_keep_every_pixel(rig, tmp_path, capsys):
    # The outlines were drawn around the eroded regions and eroded again on redrawing: 6 % of
    # a demo calibration's mirror pixels were lost, for no edit at all.
    from omnitof.calibration.masks import erode_labels, grow_labels
    from omnitof.cli import main

    cal = Calibration.from_rig(rig)
    assert cal.edge_margin_px > 0 and (cal.labels >= 0).sum() > 1000
    # Growing back undoes the erosion exactly on these regions (independently: eroding again).
    assert np.array_equal(erode_labels(grow_labels(cal.labels, cal.edge_margin_px), cal.edge_margin_px), cal.labels)
    path = save_calibration(cal, tmp_path / "cal.yaml")
    regions = tmp_path / "regions.yaml"
    assert main(["calibrate", "masks", str(path), "--export", str(regions)]) == 0
    assert main(["calibrate", "masks", str(path), "--polygons", str(regions), "--out", str(tmp_path / "redrawn.yaml")]) == 0
    capsys.readouterr()
    redrawn = load_calibration(tmp_path / "redrawn.yaml")
    assert np.array_equal(redrawn.labels, cal.labels)


@pytest.mark.parametrize("polygon, message", [
    # 1e30 wrote a calibration whose mirrors all had 0 pixels, with exit status 0.
    ([[0.0, 0.0], [10.0, 0.0], [1e30, 10.0]], r"polygon 'front': point 2 \(1e\+30, 10\) lies more than the image's size"),
    ([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]], "polygon 'front' keeps no pixel"),  # a line holds no pixel
])
def test_a_polygon_far_outside_the_image_or_without_pixels_is_refused(rig, tmp_path, capsys, polygon, message):
    from omnitof.calibration.masks import labels_from_polygons
    from omnitof.cli import main

    with pytest.raises(CalibrationError, match=message):
        labels_from_polygons(rig.camera, rig.names, {"front": np.array(polygon)}, 2.0)
    cal = save_calibration(Calibration.from_rig(rig), tmp_path / "cal.yaml")
    before = cal.read_bytes()
    regions = tmp_path / "regions.yaml"
    regions.write_text(f"front: {polygon}\n")
    assert main(["calibrate", "masks", str(cal), "--polygons", str(regions)]) == 2
    assert "regions.yaml: polygon 'front'" in capsys.readouterr().err and cal.read_bytes() == before


def test_check_refuses_a_band_whose_near_end_is_beyond_its_far_end(rig, tmp_path, capsys):
    # It measured nothing and exited 0.
    from omnitof.cli import main

    cal = save_calibration(Calibration.from_rig(rig), tmp_path / "cal.yaml")
    assert main(["calibrate", "check", str(cal), "--band", "3", "1"]) == 2
    captured = capsys.readouterr()
    assert "--band NEAR FAR: NEAR must be less than FAR, got 3 1" in captured.err and captured.out == ""


# --- the check of paper Fig. 6 ---------------------------------------------------------------


def test_equal_height_check_sees_a_tilted_mirror(rig):
    from omnitof.calibration.check import edge_heights, render_check_frame
    from omnitof.sensor.mirrors import MirrorPlane

    camera, mirrors = rig.camera, rig.mirrors
    frame = render_check_frame(camera, mirrors, seed=1)
    cal = Calibration.from_rig(rig)
    good = edge_heights(cal, frame.distance)
    assert set(good.per_mirror) == set(cal.names)
    assert good.spread < 0.012
    for median, _, bins in good.per_mirror.values():
        assert abs(median - 0.6) < 0.015 and bins >= 10
    tilt = np.radians(0.5)  # the front mirror turned by 0.5° about the camera's x axis
    turn = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    tilted = (MirrorPlane(turn @ cal.planes[0].normal, cal.planes[0].d), *cal.planes[1:])
    cal = cal.with_rig(replace(cal.rig, planes=tilted))
    assert edge_heights(cal, frame.distance).spread > 0.02



def test_equal_height_check_with_edges_through_one_mirror_measures_nothing(rig, tmp_path, capsys):
    """Fewer than two mirrors with an upper edge leave nothing to compare: the check said
    "difference between mirrors: 0.0 mm" and passed. Now it says so and `calibrate check` fails."""
    import math

    from omnitof.calibration.check import edge_heights, render_check_frame
    from omnitof.cli import main

    camera, mirrors = rig.camera, rig.mirrors
    frame = render_check_frame(camera, mirrors, seed=1)
    cal = Calibration.from_rig(rig)
    only_front = np.where(cal.labels == 0, frame.distance, np.nan)
    check = edge_heights(cal, only_front)
    assert list(check.per_mirror) == [cal.names[0]] and not check.measured and math.isnan(check.spread)
    lines = check.report(list(cal.names))
    assert lines[1].strip() == f"{cal.names[1]}: no upper edge in the band"
    assert lines[-1].startswith("difference between mirrors: not measured")
    # A frame with no object in the band at all, through the command line.
    empty = tmp_path / "empty.npz"
    np.savez(empty, distance=np.full(camera.shape, 20.0, np.float32), amplitude=np.full(camera.shape, 50.0, np.float32))
    path = save_calibration(cal, tmp_path / "cal.yaml")
    capsys.readouterr()
    assert main(["calibrate", "check", str(path), "--frame", str(empty)]) == 2
    captured = capsys.readouterr()
    assert "not measured" in captured.out and "upper edge through 0 of 4 mirrors" in captured.err

# --- command line ----------------------------------------------------------------------------


def test_cli_render_calibrate_check(tmp_path, capsys):
    from omnitof.cli import main

    out = tmp_path / "targets"
    cal = tmp_path / "cal.yaml"
    assert main(["calibrate", "render-targets", "--out", str(out), "--placements", "4",
                 "--boards", "8", "--seed", "5"]) == 0
    assert main(["calibrate", "intrinsics", str(out / "intrinsics"), "--out", str(cal)]) == 0
    assert "RMS reprojection error" in capsys.readouterr().out
    assert main(["calibrate", "mirrors", str(out / "mirrors"), "--calibration", str(cal)]) == 0
    printed = capsys.readouterr().out
    for name in ("front", "left", "back", "right"):
        assert f"mirror {name}:" in printed
    result = load_calibration(cal)
    truth = load_calibration(out / "truth.yaml")
    for plane, true in zip(result.planes, truth.planes):
        # Calibrated intrinsics and 4 placements: looser than the test above.
        assert np.degrees(np.arccos(min(1.0, plane.normal @ true.normal))) < 1.5
        assert abs(plane.d - true.d) < 0.005
    assert result.quality["mirrors"]["front"]["placements"] == 4
    assert main(["calibrate", "check", str(cal), "--truth", str(out / "truth.yaml"),
                 "--figure", str(tmp_path / "side.png")]) == 0
    assert "difference between mirrors" in capsys.readouterr().out
    assert (tmp_path / "side.png").stat().st_size > 0
    regions = tmp_path / "regions.yaml"
    assert main(["calibrate", "masks", str(cal), "--export", str(regions)]) == 0
    assert main(["calibrate", "masks", str(cal), "--polygons", str(regions)]) == 0
    assert set(load_calibration(cal).polygons) == {"front", "left", "back", "right"}
    # Bad input: one line on stderr, exit status 2, naming the file.
    (tmp_path / "junk.png").write_bytes(b"not a png")
    assert main(["calibrate", "mirrors", str(tmp_path / "junk.png"), "--calibration", str(cal)]) == 2
    assert "junk.png" in capsys.readouterr().err


def test_card_hits_against_the_ray_plane_intersection_worked_by_hand():
    # A plain board and a checkerboard about 2 m ahead, turned 30° about the vertical: rays from
    # the optical centre and from points beside it (as the mirrors' reflected rays start),
    # checked against the intersection written out per ray (t = (c − o)·n / d·n, the hit inside
    # the extent) and the target's albedo at the hit's own coordinates (the checker squares).
    from omnitof.calibration.targets import Checkerboard, PlainBoard, _card_hits, look_at_pose

    turn = np.radians(30.0)
    pose = look_at_pose(np.array([0.1, -0.05, 2.0]), np.array([np.sin(turn), 0.0, -np.cos(turn)]), 0.2)
    rng = np.random.default_rng(5)
    dirs = rng.normal([0.0, 0.0, 1.0], 0.35, size=(4000, 3))
    dirs[:50] = -dirs[:50]  # away from the board: behind their start
    dirs[50] = np.cross(pose[:3, 2], [1.0, 0.0, 0.0])  # along the board's plane
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = rng.uniform(-0.3, 0.3, size=(4000, 3))
    rotation, centre, normal = pose[:3, :3], pose[:3, 3], pose[:3, 2]
    for target in (PlainBoard(), Checkerboard()):
        x0, x1, y0, y1 = target.extent()
        for start in (None, origins):
            o = np.zeros_like(dirs) if start is None else start
            t, albedo, cosine = _card_hits(target, pose, start, dirs)
            hits, albedos = 0, set()
            for k in range(len(dirs)):
                approach = dirs[k] @ normal
                assert cosine[k] == pytest.approx(abs(approach), abs=1e-15)
                tk = (centre - o[k]) @ normal / approach if approach != 0 else np.inf
                x, y = (o[k] + tk * dirs[k] - centre) @ rotation[:, :2] if np.isfinite(tk) else (np.inf, np.inf)
                if 1e-9 < tk < np.inf and x0 <= x <= x1 and y0 <= y <= y1:
                    hits += 1
                    want = float(target.albedo(np.array([x]), np.array([y]))[0])
                    assert t[k] == pytest.approx(tk, abs=1e-12) and albedo[k] == want
                    albedos.add(want)
                else:
                    assert t[k] == np.inf and albedo[k] == 0.0
            assert 50 < hits < len(dirs) - 50  # both cases met many times
            assert len(albedos) == (1 if isinstance(target, PlainBoard) else 2)  # black and white squares hit
