"""omnitof.sensor.camera: the pinhole + distortion model against OpenCV, back-projection accuracy over
every pixel, the field of view, straight lines after undistortion, and parameter checks."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from omnitof.sensor.camera import Camera
from omnitof.errors import ConfigError

LENSES = {"standard": Camera.sr4000, "wide": Camera.sr4000_wide}


def pixel_centres(cam: Camera) -> np.ndarray:
    v, u = np.mgrid[0 : cam.height, 0 : cam.width]
    return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)


def points_in_view(cam: Camera, n: int, seed: int) -> np.ndarray:
    """Random points (n, 3) whose rays pass through the image, at 0.3–8 m."""
    rng = np.random.default_rng(seed)
    px = rng.uniform([-0.5, -0.5], [cam.width - 0.5, cam.height - 0.5], (n, 2))
    return cam.rays(px) * rng.uniform(0.3, 8.0, (n, 1))


@pytest.mark.parametrize(
    "cam",
    [
        Camera.sr4000(),
        Camera.sr4000_wide(),
        # every coefficient non-zero, so each term of the model is compared
        Camera(176, 144, 250.0, 245.0, 90.0, 70.0, (-0.3, 0.1, 0.004, -0.006, -0.02)),
    ],
    ids=["standard", "wide", "all-terms"],
)
def test_project_matches_cv2_project_points(cam):
    points = points_in_view(cam, 5000, seed=1)
    points = np.vstack([points, [[0.0, 0.0, 1.0], [0.3, -0.2, 2.5]]])
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    np.testing.assert_allclose(cam.project(points), expected.reshape(-1, 2), rtol=0, atol=1e-9)


def test_camera_matrix_and_coefficients_in_opencv_order():
    cam = Camera.sr4000()
    np.testing.assert_array_equal(
        cam.K, [[249.58, 0, 83.60], [0, 248.65, 76.10], [0, 0, 1]]
    )
    assert cam.dist == (-0.8, 0.3, 0.01, 0.0, 0.0)  # (k1, k2, p1, p2, k3)
    assert cam.shape == (144, 176)


@pytest.mark.parametrize("lens", sorted(LENSES))
def test_every_pixel_centre_back_projects_and_reprojects(lens):
    cam = LENSES[lens]()
    pixels = pixel_centres(cam)
    rays = cam.rays(pixels)
    assert np.isfinite(rays).all()
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    assert (rays[:, 2] > 0).all()
    error = np.linalg.norm(cam.project(rays * 3.0) - pixels, axis=1)
    assert error.max() < 1e-3
    # cv2's undistortion with its default 5 iterations would be far off at the corners; ours
    # is iterated to convergence (the slowest pixel, top right, needs hundreds of steps).
    assert error.max() < 1e-8


def test_rays_agree_with_an_independent_inversion():
    # Newton's method on the distortion written out here, from the projection of cv2.
    cam = Camera.sr4000()
    pixels = np.array([[0.0, 0.0], [175.0, 0.0], [0.0, 143.0], [175.0, 143.0], [88.0, 72.0]])
    rays = cam.rays(pixels)
    for (u, v), ray in zip(pixels, rays):
        xy = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy])
        for _ in range(50):
            def pix(q):
                out, _ = cv2.projectPoints(
                    np.array([[q[0], q[1], 1.0]]), np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs
                )
                return out.reshape(2)
            h = 1e-7
            jac = np.column_stack([(pix(xy + d) - pix(xy - d)) / (2 * h) for d in np.eye(2) * h])
            xy = xy - np.linalg.solve(jac, pix(xy) - [u, v])
        expected = np.array([xy[0], xy[1], 1.0]) / np.linalg.norm([xy[0], xy[1], 1.0])
        np.testing.assert_allclose(ray, expected, atol=1e-9)


def test_principal_point_looks_along_the_axis():
    cam = Camera.sr4000()
    np.testing.assert_allclose(cam.rays(np.array([[cam.cx, cam.cy]]))[0], [0, 0, 1], atol=1e-15)


def test_pixel_grid_rays_are_cached_row_major_and_read_only():
    cam = Camera.sr4000()
    grid = cam.pixel_grid_rays()
    assert grid.shape == (144, 176, 3)
    assert grid is cam.pixel_grid_rays()
    np.testing.assert_array_equal(grid[10, 150], cam.rays(np.array([[150.0, 10.0]]))[0])
    assert grid[0, 0, 0] < 0 and grid[0, 0, 1] < 0  # top-left pixel: left (x < 0) and up (y < 0)
    with pytest.raises(ValueError):
        grid[0, 0, 0] = 1.0


def test_field_of_view_of_the_sr4000_models():
    horizontal, vertical = Camera.sr4000().field_of_view()
    # Datasheet: 43.6° × 34.6°; this model gives 43.8° × 34.9°.
    assert horizontal == pytest.approx(43.6, abs=1.0)
    assert vertical == pytest.approx(34.6, abs=1.0)
    # A distortion-free pinhole with the same focal lengths sees much less: the datasheet
    # figure includes the barrel distortion.
    assert Camera(176, 144, 249.58, 248.65, 83.6, 76.1).field_of_view()[0] < 39.0

    wide = Camera.sr4000_wide()
    horizontal, vertical = wide.field_of_view()
    assert horizontal == pytest.approx(69.0, abs=1e-6)  # solved for
    assert vertical == pytest.approx(56.0, abs=1.0)
    assert wide.fx / wide.fy == pytest.approx(249.58 / 248.65)


def test_wide_lens_has_the_same_distortion_in_pixels():
    standard, wide = Camera.sr4000(), Camera.sr4000_wide()
    # Same pixel → same undistorted pixel offset from the principal point, for both lenses.
    pixels = pixel_centres(standard)[::37]

    def undistorted_offset(cam):
        r = cam.rays(pixels)
        return np.stack([cam.fx * r[:, 0] / r[:, 2], cam.fy * r[:, 1] / r[:, 2]], axis=1)

    np.testing.assert_allclose(undistorted_offset(wide), undistorted_offset(standard), atol=1e-6)


def test_points_behind_the_camera_or_beyond_the_fold_do_not_project():
    cam = Camera.sr4000()
    assert np.isnan(cam.project(np.array([[0.1, 0.1, -1.0], [0.0, 0.0, 0.0]]))).all()
    # k2 = 0: the radial map r(1 − 0.8 r²) folds back at r = 1/√2.4 = 0.645 (33° off axis);
    # a point at r = 1 (45°) would land inside the image, a ghost of some other direction.
    folding = Camera(176, 144, 249.58, 248.65, 83.6, 76.1, (-0.8, 0.0, 0.0, 0.0, 0.0))
    ghost = np.array([[1.0, 0.0, 1.0]])
    uv, _ = cv2.projectPoints(ghost, np.zeros(3), np.zeros(3), folding.K, folding.dist_coeffs)
    assert 0 <= uv.reshape(2)[0] < 176  # cv2 puts it in the image...
    assert np.isnan(folding.project(ghost)).all()  # ...we refuse
    assert np.isfinite(folding.project(np.array([[0.6, 0.0, 1.0]]))).all()
    # The SR4000 model has no fold anywhere in its image (row -40 straight up at the nearest).
    assert np.isfinite(cam.pixel_grid_rays()).all()


# --- undistortion of a checkerboard ---------------------------------------------------------

SQUARE = 0.09  # checker size in normalised coordinates (≈ 22 px)
PHASE = (0.013, -0.021)  # so that no edge runs through the principal point


def checkerboard(xy: np.ndarray) -> np.ndarray:
    """1 on white squares, 0 on black, of normalised coordinates (..., 2)."""
    i = np.floor((xy[..., 0] - PHASE[0]) / SQUARE) + np.floor((xy[..., 1] - PHASE[1]) / SQUARE)
    return (i % 2).astype(np.float32)


def render_distorted(cam: Camera, oversample: int = 6) -> np.ndarray:
    """The checkerboard on the plane z = 1 as the distorting camera sees it, box-filtered."""
    offsets = (np.arange(oversample) + 0.5) / oversample - 0.5
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    du, dv = np.meshgrid(offsets, offsets)
    su = (u[..., None] + du.ravel()).ravel()
    sv = (v[..., None] + dv.ravel()).ravel()
    rays = cam.rays(np.stack([su, sv], axis=1))
    values = checkerboard(rays[:, :2] / rays[:, 2:])
    return values.reshape(cam.height, cam.width, -1).mean(axis=2)


def edge_points(image: np.ndarray, xy: np.ndarray, axis: int) -> dict[int, np.ndarray]:
    """Sub-pixel points where the image crosses 0.5 across the checker lines of `axis`.

    axis 0: vertical lines x = const, searched along rows; axis 1: horizontal lines, along
    columns. `xy` (H, W, 2) gives each pixel's normalised coordinates, used only to know which
    line an edge belongs to and to skip pixels near the crossing lines (the checker corners).
    Returns {line index: (n, 2) points (u, v)}.
    """
    img, coords = (image, xy) if axis == 0 else (image.T, xy.transpose(1, 0, 2))
    along = (coords[..., axis] - PHASE[axis]) / SQUARE
    across = (coords[..., 1 - axis] - PHASE[1 - axis]) / SQUARE
    lines: dict[int, list[tuple[float, float]]] = {}
    for r in range(img.shape[0]):
        for c in range(img.shape[1] - 1):
            a, b = img[r, c] - 0.5, img[r, c + 1] - 0.5
            k = math.floor(along[r, c + 1])
            if a * b > 0 or a == b or math.floor(along[r, c]) == k:
                continue
            # two pixels from any crossing line, the edge is a clean step
            if abs(across[r, c] - round(across[r, c])) * SQUARE * 250.0 < 2.5:  # 250 ≈ fx, px
                continue
            t = c + a / (a - b)
            lines.setdefault(k, []).append((t, r) if axis == 0 else (r, t))
    return {k: np.array(v) for k, v in lines.items() if len(v) >= 20}


def straight_line_residual(points: np.ndarray, axis: int) -> float:
    """Largest distance (px) of the points from their least-squares line u = a·v + b (or v(u))."""
    dep, ind = (points[:, 0], points[:, 1]) if axis == 0 else (points[:, 1], points[:, 0])
    coeffs = np.polyfit(ind, dep, 1)
    return float(np.abs(np.polyval(coeffs, ind) - dep).max() / math.hypot(1.0, coeffs[0]))


@pytest.mark.parametrize("interpolation", ["linear", "nearest"])
def test_undistorted_checkerboard_has_straight_edges(interpolation):
    cam = Camera.sr4000()
    distorted = render_distorted(cam)
    undistorted = cam.undistort_image(distorted, interpolation=interpolation)
    assert undistorted.shape == distorted.shape and undistorted.dtype == np.float32
    assert np.isfinite(undistorted).all()  # barrel: the output needs nothing from outside

    # Normalised coordinates of every pixel: through the distortion for the raw image, plain
    # pinhole for the undistorted one.
    raw_xy = cam.pixel_grid_rays()[..., :2] / cam.pixel_grid_rays()[..., 2:]
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    pinhole_xy = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy], axis=-1)

    tolerance = 0.5 if interpolation == "linear" else 1.0  # nearest moves edges by ≤ 0.5 px
    for axis in (0, 1):
        straight = edge_points(undistorted, pinhole_xy, axis)
        curved = edge_points(distorted, raw_xy, axis)
        assert len(straight) >= 4
        for k, points in straight.items():
            assert straight_line_residual(points, axis) < tolerance, (axis, k)
            # and where the pinhole puts the line: x = PHASE + k·SQUARE
            focal, centre = (cam.fx, cam.cx) if axis == 0 else (cam.fy, cam.cy)
            line = focal * (PHASE[axis] + k * SQUARE) + centre
            assert np.abs(points[:, axis] - line).max() < tolerance + 0.1, (axis, k)
        # the same lines in the raw image are visibly bent: the test is not vacuous
        assert max(straight_line_residual(p, axis) for p in curved.values()) > 3.0


def test_undistort_image_keeps_dtype_and_nearest_keeps_values():
    cam = Camera.sr4000()
    labels = np.arange(144 * 176, dtype=np.float32).reshape(144, 176)
    out = cam.undistort_image(labels, interpolation="nearest")
    assert out.dtype == np.float32
    assert np.isin(out, labels).all()  # no blended values: safe for distance images
    counts = cam.undistort_image(np.ones((144, 176), np.uint16), interpolation="linear")
    assert counts.dtype == np.uint16 and counts.shape == (144, 176)
    with pytest.raises(ValueError, match="image"):
        cam.undistort_image(np.zeros((176, 144), np.float32))
    with pytest.raises(ValueError, match="interpolation"):
        cam.undistort_image(labels, interpolation="cubic")


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"fx": -249.58}, "fx"),
        ({"fy": 0.0}, "fy"),
        ({"fx": math.nan}, "fx"),
        ({"cx": math.inf}, "cx"),
        ({"width": 0}, "width"),
        ({"height": 144.5}, "height"),
        ({"width": 10**9}, "width"),  # a typo: its ray table alone would need 10 PB
        ({"dist": (-0.8, 0.3, 0.01, 0.0)}, "dist"),
        ({"dist": (-0.8, 0.3, 0.01, 0.0, 0.0, 0.0)}, "dist"),
        ({"dist": (-0.8, math.nan, 0.01, 0.0, 0.0)}, "dist"),
    ],
)
def test_bad_parameters_raise_value_error_naming_the_field(changes, field):
    params = dict(width=176, height=144, fx=249.58, fy=248.65, cx=83.6, cy=76.1,
                  dist=(-0.8, 0.3, 0.01, 0.0, 0.0))
    params.update(changes)
    with pytest.raises(ValueError, match=rf"Camera\.{field}\b") as info:
        Camera(**params)
    assert isinstance(info.value, ConfigError)  # the CLI prints it as one line


def test_bad_array_shapes_are_refused():
    cam = Camera.sr4000()
    with pytest.raises(ValueError, match="points"):
        cam.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="pixels"):
        cam.rays(np.zeros(2))
    assert cam.rays(np.zeros((0, 2))).shape == (0, 3)
