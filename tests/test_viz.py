"""Tests of omnitof.viz.maps: the PNG really shows the map and the trajectories."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from omnitof.types import OccupancyMap
from omnitof.viz.maps import plot_map


def _map() -> OccupancyMap:
    """10 m x 8 m at 0.1 m from (0, 0): free; occupied at x 2..3, y 5..6; unknown for x >= 8."""
    h, w = 80, 100
    log_odds = np.full((h, w), -4.0, dtype=np.float32)
    log_odds[50:60, 20:30] = 4.0  # rows are y, columns x
    known = np.ones((h, w), dtype=bool)
    known[:, 80:] = False
    return OccupancyMap(log_odds=log_odds, known=known, resolution=0.1, origin=(0.0, 0.0))


def _pixel(fig: Figure, image: np.ndarray, x: float, y: float) -> np.ndarray:
    """RGB of the PNG at map point (x, y): display coords have y up, image rows go down."""
    px, py = fig.axes[0].transData.transform((x, y))
    return image[int(round(image.shape[0] - py)), int(round(px)), :3]


def _assert_line_colour(fig: Figure, image: np.ndarray, x: float, y: float, colour: str) -> None:
    """A pixel within 1 px of (x, y) shows `colour` drawn over the white (free) background.

    A line thinner than two pixels covers no pixel fully, so the PNG holds alpha * colour +
    (1 - alpha) * white; fit alpha per pixel and require a good fit with a large coverage.
    """
    px, py = fig.axes[0].transData.transform((x, y))
    row, col = int(round(image.shape[0] - py)), int(round(px))
    window = image[row - 1 : row + 2, col - 1 : col + 2, :3].reshape(-1, 3).astype(float)
    direction = np.array(to_rgb(colour)) - 1.0
    alpha = (window - 1.0) @ direction / (direction @ direction)
    residual = np.abs(window - (1.0 + alpha[:, None] * direction)).max(axis=1)
    best = np.argmax(np.where(residual < 0.03, alpha, -1.0))
    assert alpha[best] > 0.75 and residual[best] < 0.03, f"no {colour} near ({x}, {y}): {window}"


@pytest.mark.parametrize("dpi", [80, 150])
def test_png_shows_map_and_trajectories(tmp_path: Path, dpi: int) -> None:
    path = tmp_path / "map.png"
    # A horizontal path along y = 2 from x = 1 to x = 7, and a second one along y = 7.
    first = np.column_stack([np.linspace(1, 7, 50), np.full(50, 2.0), np.zeros(50)])
    second = np.column_stack([np.linspace(7, 1, 50), np.full(50, 7.0), np.full(50, np.pi)])
    fig = plot_map(path, _map(), {"slam": first, "odometry": second}, title="intel", dpi=dpi)

    image = matplotlib.image.imread(path)
    assert image.shape[:2] == (8 * dpi, 8 * dpi)  # default figsize 8 x 8 inches
    assert fig.axes[0].get_title() == "intel"

    # Occupied block (x 2..3, y 5..6): its centre is black.
    assert _pixel(fig, image, 2.5, 5.5).max() < 0.15
    # A free cell away from everything is white; an unknown one mid-grey.
    assert _pixel(fig, image, 5.0, 4.5).min() > 0.9
    np.testing.assert_allclose(_pixel(fig, image, 9.0, 4.5), 0.5, atol=0.05)
    # The trajectories' lines, halfway along, have their colours (C0 and C1 of the cycle).
    _assert_line_colour(fig, image, 4.0, 2.0, "C0")
    _assert_line_colour(fig, image, 4.0, 7.0, "C1")
    assert _pixel(fig, image, 4.0, 3.0).min() > 0.9  # and only there: 1 m off the line is free
    # The start marker (radius ~3 pt) covers a point 1.5 px beyond the line's start.
    start = fig.axes[0].transData.transform((1.0, 2.0))
    px, py = int(round(start[0] - 1.5 * dpi / 72)), int(round(image.shape[0] - start[1]))
    np.testing.assert_allclose(image[py, px, :3], to_rgb("C0"), atol=0.1)

    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["slam", "odometry"]
    assert [p.name for p in tmp_path.iterdir()] == ["map.png"]



def test_odometry_that_drifts_far_leaves_the_view_to_the_map(tmp_path: Path) -> None:
    """Wheels that drift hundreds of metres (MIT Killian Court's end 600 m away) would shrink a
    10 m map to a corner of the figure: the view stays the map's, and the legend says which
    trajectory leaves it."""
    inside = np.column_stack([np.linspace(1, 7, 50), np.full(50, 2.0), np.zeros(50)])
    drifting = np.column_stack([np.linspace(1, -600, 50), np.linspace(2, -450, 50), np.zeros(50)])
    fig = plot_map(tmp_path / "map.png", _map(), {"SLAM": inside, "odometry": drifting}, dpi=50)
    ax = fig.axes[0]
    np.testing.assert_allclose([*ax.get_xlim(), *ax.get_ylim()], _map().extent)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["SLAM", "odometry (leaves the map's extent)"]
    # The map fills the figure's width: 10 m across more than half of its 400 pixels.
    left, right = ax.transData.transform([(0.0, 0.0), (10.0, 0.0)])[:, 0]
    assert right - left > 200
    # Odometry a metre beyond the map is drawn whole, as before: the figure grows to hold it.
    near = np.column_stack([np.linspace(1, 11, 50), np.full(50, 2.0), np.zeros(50)])
    fig = plot_map(tmp_path / "near.png", _map(), {"SLAM": inside, "odometry": near}, dpi=50)
    assert fig.axes[0].get_xlim()[1] >= 11.0
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["SLAM", "odometry"]

def test_trajectories_without_map(tmp_path: Path) -> None:
    path = tmp_path / "t.png"
    square = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0], [0, 0, 0]], dtype=float)
    fig = plot_map(path, None, {"square": square}, dpi=50, figsize=(6.0, 4.0))
    image = matplotlib.image.imread(path)
    assert image.shape[:2] == (200, 300)
    _assert_line_colour(fig, image, 2.0, 0.0, "C0")
    ax = fig.axes[0]
    assert ax.get_xlabel() == "x [m]" and ax.get_ylabel() == "y [m]"


def test_bad_trajectory_shape_writes_nothing(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="trajectory 'xy'"):
        plot_map(tmp_path / "x.png", None, {"xy": np.zeros((4, 2))})
    assert list(tmp_path.iterdir()) == []


def test_huge_maps_are_drawn_by_blocks_that_keep_thin_walls():
    from omnitof.viz.maps import UNKNOWN_SHADE, _at_most

    rng = np.random.default_rng(0)
    shades = rng.uniform(0.6, 1.0, size=(7, 10))
    shades[3, :] = 0.0  # a one-cell wall
    reduced = _at_most(shades, 4)  # k = 3: 3×4 blocks, the last ones padded as unknown
    assert reduced.shape == (3, 4)
    for r in range(3):
        for c in range(4):
            block = shades[3 * r:3 * r + 3, 3 * c:3 * c + 3]
            padded = block.size < 9
            expected = min(block.min(), UNKNOWN_SHADE) if padded else block.min()
            assert reduced[r, c] == expected
    assert np.all(reduced[1, :] == 0.0)  # the wall survives
    assert _at_most(shades, 10) is shades  # small maps are drawn as they are


def test_degenerate_figures_draw_without_warnings(tmp_path: Path) -> None:
    # An empty map made matplotlib warn of singular limits, which reached the user as
    # "omnitof: warning: ..."; a single pose and a map of one tile are fine too.
    import warnings

    from omnitof.viz.maps import plot_pose_graph

    empty = OccupancyMap(np.zeros((0, 0), np.float32), np.zeros((0, 0), bool), 0.05, (0.0, 0.0))
    tile = OccupancyMap(np.zeros((16, 16), np.float32), np.ones((16, 16), bool), 0.05, (0.0, 0.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plot_map(tmp_path / "empty.png", empty, {"SLAM": np.zeros((3, 3))})
        plot_map(tmp_path / "one.png", tile, {"SLAM": np.zeros((1, 3))})
        plot_pose_graph(tmp_path / "graph.png", tile, np.zeros((1, 3)), np.zeros((0, 2), np.int64))
    assert all((tmp_path / n).stat().st_size > 1000 for n in ("empty.png", "one.png", "graph.png"))


def test_the_pose_graph_names_its_closures_and_relocalisations(tmp_path: Path) -> None:
    from omnitof.viz.maps import plot_pose_graph

    tile = OccupancyMap(np.zeros((16, 16), np.float32), np.ones((16, 16), bool), 0.05, (0.0, 0.0))
    nodes = np.array([[0.1, 0.1, 0.0], [0.5, 0.1, 0.0], [0.5, 0.5, 0.0], [0.12, 0.1, 0.0]])
    fig = plot_pose_graph(tmp_path / "graph.png", tile, nodes, np.array([[0, 3]]), np.array([[1, 3]]),
                          relocalised=np.array([3]))
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["nodes (4)", "loop closures (1)", "rejected closures (1)", "relocalisations (1)"]
    [marker] = [line for line in fig.axes[0].get_lines() if line.get_label().startswith("relocalisations")]
    assert np.allclose(marker.get_xydata(), [[0.12, 0.1]])
