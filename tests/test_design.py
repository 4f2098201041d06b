"""omnitof.sensor.design: bearing coverage against analytic answers (one 45° mirror: the lens's
horizontal field of view; the 45° pyramid: ±10° around each face), the trends of the sweep, the
default rig's optimality, and the report and figure."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from omnitof.sensor.camera import Camera
from omnitof.sensor.design import (
    DEFAULT_RIG_TILT_DEG,
    default_rig,
    design_report,
    format_sweep,
    sweep,
)
from omnitof.viz.sensor import plot_sweep
from omnitof.errors import ConfigError
from omnitof.sensor.mirrors import Mirror, MirrorPlane, camera_mount, pyramid

Z = np.array([0.0, 0.0, 1.0])
LENSES = {"standard": Camera.sr4000(), "wide": Camera.sr4000_wide()}


def ideal_camera() -> Camera:
    return Camera(176, 144, 200.0, 200.0, 87.3, 71.6)


def single_mirror(e: np.ndarray, apex_height: float = 0.1, half: float = 1.0) -> Mirror:
    """One large 45° mirror through (0, 0, apex_height) that sends the optical axis along the
    horizontal camera-frame direction e: a square of side 2·half in its plane."""
    across = np.cross(Z, e)
    rising = (e + Z) / math.sqrt(2.0)
    centre = np.array([0.0, 0.0, apex_height])
    plane = MirrorPlane.through(centre, np.cross(across, rising))
    signs = ((-1, -1), (1, -1), (1, 1), (-1, 1))  # in order around the square
    corners = [centre + half * (sa * across + sr * rising) for sa, sr in signs]
    return Mirror(plane, np.array(corners), "single")


def test_one_45_degree_mirror_covers_the_horizontal_field_of_view():
    camera = ideal_camera()
    # Camera −y is the robot's front (camera_mount), so this mirror looks forward.
    report = design_report(camera, [single_mirror(np.array([0.0, -1.0, 0.0]))], edge_margin_px=0)
    # A 45° mirror turns the camera to look horizontally without turning its image: the
    # column u looks at bearing atan((u − cx)/fx) (camera x = robot left), whatever its row,
    # and the row through cy lies on the horizon, inside the band.
    columns = np.arange(camera.width)
    bearings = np.degrees(np.arctan((columns - camera.cx) / camera.fx))
    expected = np.zeros(360, bool)
    expected[np.floor(bearings).astype(int) % 360] = True
    np.testing.assert_array_equal(report.covered, expected)
    right, left = (camera.width - 0.5 - camera.cx) / camera.fx, (camera.cx + 0.5) / camera.fx
    hfov = math.degrees(math.atan(right) + math.atan(left))
    assert abs(int(report.covered.sum()) - hfov) <= 1.0
    assert report.largest_gap_deg == 360 - int(report.covered.sum())
    # The band keeps the rays (x, y, 1) with |elevation| = |asin(y / |ray|)| <= 10°, that is
    # |y| <= tan(10°)·sqrt(1 + x²): count them column by column.
    x = (columns - camera.cx) / camera.fx
    y = (np.arange(camera.height) - camera.cy) / camera.fy
    in_band = np.abs(y)[:, None] <= math.tan(math.radians(10)) * np.sqrt(1 + x**2)[None, :]
    expected_per_degree = in_band.sum() / report.covered.sum()
    assert report.pixels_per_degree == pytest.approx(expected_per_degree, rel=1e-12)
    stats = report.mirrors[0]
    assert stats.bearing_deg == pytest.approx(0.0)
    assert stats.pixels == camera.width * camera.height


def test_bearings_turn_counter_clockwise_from_the_driving_direction():
    # The camera's +x is the robot's left: a mirror sending the axis that way looks at 90°.
    mirror = single_mirror(np.array([1.0, 0.0, 0.0]))
    report = design_report(ideal_camera(), [mirror], edge_margin_px=0)
    seen = np.flatnonzero(report.covered)
    assert seen.min() > 60 and seen.max() < 120
    assert report.mirrors[0].bearing_deg == pytest.approx(90.0)


@pytest.mark.parametrize("lens", sorted(LENSES))
@pytest.mark.parametrize("yaw", [0.0, 45.0])
def test_the_45_degree_pyramid_looks_from_the_horizon_upwards(lens, yaw):
    camera = LENSES[lens]
    report = design_report(camera, pyramid(4, 45.0, yaw_deg=yaw, camera=camera), edge_margin_px=0)
    # A 45° face maps the camera's (across, along-the-face, axis) components of a ray to
    # (across, up, out): inside a face's quarter of the image `up` >= |across| >= 0, so no
    # ray looks down, and a ray within 10° of the horizon (up <= sin 10°) stays within
    # atan(sin 10° / sqrt(1 − 2 sin² 10°)) = 10.15° of the face's bearing.
    assert min(m.elevation_min_deg for m in report.mirrors) > -1e-9
    assert min(m.elevation_min_deg for m in report.mirrors) < 0.5
    s = math.sin(math.radians(10.0))
    half = math.degrees(math.atan(s / math.sqrt(1.0 - 2.0 * s * s)))
    assert abs(report.covered.sum() - 4 * 2 * half) <= 4
    for m in report.mirrors:
        assert abs(m.band_bearings - 2 * half) <= 1.5


def test_turning_the_camera_with_the_pyramid_turns_the_bearings_only():
    # The paper's diagonal yaw (45°) with the camera turned 45° on its axis puts the pyramid's
    # edges into the image corners, like yaw 0° on the square mount: same pixels, same
    # coverage, bearings turned by 45°.
    camera, mirrors = Camera.sr4000_wide(), default_rig().mirrors
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    turned = camera_mount()
    turned[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ turned[:3, :3]
    diagonal = pyramid(4, DEFAULT_RIG_TILT_DEG, yaw_deg=45.0, camera=camera, robot_T_camera=turned)
    assert [m.name for m in diagonal] == ["front-left", "back-left", "back-right", "front-right"]
    for a, b in zip(mirrors, diagonal):
        np.testing.assert_allclose(a.plane.normal, b.plane.normal, atol=1e-12)
    square = design_report(camera, mirrors)
    report = design_report(camera, diagonal, turned)
    assert report.coverage == pytest.approx(square.coverage, abs=2 / 360)
    assert (np.roll(square.covered, 45) != report.covered).sum() <= 2


@pytest.fixture(scope="module")
def small_sweep():
    return sweep(LENSES, [45.0, 50.0, 52.0, 54.0, 56.0, 58.0], yaws_deg=(0.0, 45.0), n_mirrors=(4,))


def pick(rows, **fields):
    return [r for r in rows if all(getattr(r, k) == v for k, v in fields.items())]


def test_sweep_trends(small_sweep):
    rows = small_sweep
    assert len(rows) == 2 * 6 * 2
    for yaw in (0.0, 45.0):
        for tilt in (45.0, 50.0, 52.0, 54.0, 56.0, 58.0):
            standard = pick(rows, lens="standard", yaw_deg=yaw, tilt_deg=tilt)[0]
            wide = pick(rows, lens="wide", yaw_deg=yaw, tilt_deg=tilt)[0]
            # A wider lens sees more bearings (at any elevation).
            assert wide.coverage_any_elevation > standard.coverage_any_elevation + 0.1
        # The wider lens spreads its pixels thinner: fewer per degree at its best tilt.
        best = {
            lens: max(r.pixels_per_degree for r in pick(rows, lens=lens, yaw_deg=yaw))
            for lens in LENSES
        }
        assert best["wide"] < 0.7 * best["standard"]
        for lens in LENSES:
            family = pick(rows, lens=lens, yaw_deg=yaw)
            # Each degree of tilt lowers the view by about two.
            drop = family[-1].median_elevation_deg - family[0].median_elevation_deg
            slope = drop / (58.0 - 45.0)
            assert -2.15 < slope < -1.8
            # At 45° only the apex sees the horizon: ~20° per face, whatever the lens.
            assert family[0].coverage == pytest.approx(80 / 360, abs=0.03)
            assert family[0].elevation_min_deg > 0.0
            assert max(r.coverage for r in family) > family[0].coverage + 0.07
    # Edges to the image corners (yaw 0° with this mount) beat a quadrant per mirror (45°).
    for lens in LENSES:
        for tilt in (52.0, 54.0, 56.0):
            corner = pick(rows, lens=lens, yaw_deg=0.0, tilt_deg=tilt)[0]
            quadrant = pick(rows, lens=lens, yaw_deg=45.0, tilt_deg=tilt)[0]
            assert corner.coverage > quadrant.coverage
    assert "coverage" not in format_sweep(rows[:1]) and "standard" in format_sweep(rows[:1])


def test_default_rig_centres_the_view_and_is_near_the_best_tilt():
    rig = default_rig()
    camera, mirrors = rig.camera, rig.mirrors
    assert camera == Camera.sr4000_wide()
    assert [m.name for m in mirrors] == ["front", "left", "back", "right"]
    report = design_report(camera, mirrors)
    assert abs(report.median_elevation_deg) < 2.0
    family = sweep({"wide": camera}, np.arange(48.0, 63.0, 1.0), yaws_deg=(0.0,))
    best = max(r.coverage for r in family)
    assert report.coverage >= best - 0.015
    chosen = pick(family, tilt_deg=DEFAULT_RIG_TILT_DEG)[0]
    assert chosen.coverage == pytest.approx(report.coverage)
    # Far better than the paper-like rig: standard lens, 45°, diagonal yaw.
    paper_camera = Camera.sr4000()
    paper = design_report(paper_camera, pyramid(camera=paper_camera))
    assert report.coverage > paper.coverage + 0.3


def test_report_text_and_validation():
    rig = default_rig()
    camera, mirrors = rig.camera, rig.mirrors
    report = design_report(camera, mirrors)
    text = report.format()
    for m in mirrors:
        assert m.name in text
    assert f"{100 * report.coverage:.1f} %" in text
    with pytest.raises(ConfigError):
        design_report(camera, mirrors, elev_band_deg=-1.0)


def test_sweep_figure(tmp_path: Path, small_sweep):
    path = tmp_path / "sweep.png"
    fig = plot_sweep(path, small_sweep, dpi=60)
    assert len(fig.axes) == 4
    assert len(fig.axes[0].lines) == 4  # (lens, mirrors, yaw) families
    image = matplotlib.image.imread(path)
    assert image.shape[:2] == (8 * 60, 11 * 60)
