"""Mirror masks: which pixels look through which mirror (paper Fig. 3(a)).

Two ways to draw them, both ending with the same edge margin (pixels within edge_margin_px of
another region are left out: they mix light from two directions):

- from the calibrated geometry (`labels_from_planes`): the mirrors form a convex pyramid, apex
  down, and a pixel's ray enters the pyramid's solid through the face whose plane it crosses
  last, so it sees that mirror; rays that do not approach every plane never reach the pyramid.
  The planes do not say where the mirrors end, so the outer edge is taken from the rig's design
  (`outside`: pixels that see past the mirrors there);
- by hand, as the paper does (`labels_from_polygons`): one image polygon (u, v pixels, pixel
  centres at integers) per mirror, in a YAML file {name: [[u, v], ...]}
  (`read_polygon_file`); a pixel belongs to the first polygon that holds its centre.

`polygons_from_labels` turns labels back into polygons, to start editing from.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np
import yaml
from matplotlib.path import Path as MplPath
from scipy.ndimage import distance_transform_edt

from omnitof.calibration import CalibrationError
from omnitof.errors import dump_yaml, load_yaml, yaml_problem
from omnitof.sensor.camera import Camera
from omnitof.io.atomic import atomic_write
from omnitof.sensor.mirrors import MirrorPlane


def erode_labels(labels: np.ndarray, edge_margin_px: float) -> np.ndarray:
    """Set to −1 every labelled pixel with a differently labelled pixel (or −1) within
    edge_margin_px, centre to centre; the image border is no boundary."""
    margin = float(edge_margin_px)
    if not (math.isfinite(margin) and margin >= 0.0):
        raise CalibrationError(f"edge_margin_px must be >= 0, got {edge_margin_px!r}")
    out = np.array(labels, dtype=np.int32, copy=True)
    if margin == 0.0:
        return out
    for value in np.unique(labels[labels >= 0]):
        region = labels == value
        if region.all():
            continue
        out[region & (distance_transform_edt(region) <= margin)] = -1
    return out


def labels_from_planes(
    camera: Camera,
    planes: Sequence[MirrorPlane],
    outside: np.ndarray | None = None,
    edge_margin_px: float = 2.0,
) -> np.ndarray:
    """(H, W) int32 mirror index per pixel from the planes of a convex pyramid (see above).

    Args:
        outside: (H, W) bool, pixels that see past the mirrors' outer edges (−1), e.g.
            `omnitof.sensor.mirrors.assign_pixels(camera, design_mirrors) < 0`.
    """
    rays = camera.pixel_grid_rays().reshape(-1, 3)
    normals = np.array([p.normal for p in planes]).reshape(-1, 3)
    ds = np.array([p.d for p in planes])
    with np.errstate(invalid="ignore", divide="ignore"):
        approach = rays @ normals.T  # (N, M)
        t = np.where(approach > 0.0, ds / approach, np.inf)
    reaches = np.all(approach > 0.0, axis=1) & np.all(np.isfinite(rays), axis=1)
    labels = np.where(reaches, np.argmax(np.where(np.isfinite(t), t, -np.inf), axis=1), -1)
    labels = labels.reshape(camera.shape).astype(np.int32)
    if outside is not None:
        outside = np.asarray(outside, dtype=bool)
        if outside.shape != camera.shape:
            raise CalibrationError(f"outside must have shape {camera.shape}, got {outside.shape}")
        labels[outside] = -1
    return erode_labels(labels, edge_margin_px)


def labels_from_polygons(
    camera: Camera,
    names: Sequence[str],
    polygons: Mapping[str, np.ndarray],
    edge_margin_px: float = 2.0,
    path: str | Path | None = None,
) -> np.ndarray:
    """(H, W) int32 labels from hand-drawn image polygons, one per mirror name (see above).

    Mirrors without a polygon get no pixels; a polygon named after no mirror, a vertex more than
    an image's width or height outside the image, and a polygon that keeps no pixel are errors.
    """
    h, w = camera.shape
    labels = np.full((h, w), -1, dtype=np.int32)
    v, u = np.mgrid[0:h, 0:w]
    centres = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    for key in polygons:
        if key not in names:
            raise CalibrationError(f"polygon {key!r}: no mirror of that name ({list(names)})", path)
    for index, name in enumerate(names):
        if name not in polygons:
            continue
        poly = np.asarray(polygons[name], dtype=np.float64)
        if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3 or not np.all(np.isfinite(poly)):
            raise CalibrationError(f"polygon {name!r}: expected >= 3 points [u, v]", path)
        # A vertex may lie outside the image (a region reaching its edge), but not far: 1e30
        # is a typo, and the point-in-polygon test loses every pixel to rounding there.
        far = np.flatnonzero((poly[:, 0] < -w) | (poly[:, 0] > 2 * w) | (poly[:, 1] < -h) | (poly[:, 1] > 2 * h))
        if far.size:
            u_far, v_far = poly[far[0]]
            raise CalibrationError(
                f"polygon {name!r}: point {far[0]} ({u_far:g}, {v_far:g}) lies more than the image's size "
                f"outside the {w}×{h} image (u in [{-w}, {2 * w}], v in [{-h}, {2 * h}])", path)
        # radius: pixel centres on the outline count as inside.
        inside = MplPath(poly).contains_points(centres, radius=1e-9).reshape(h, w)
        inside |= MplPath(poly[::-1]).contains_points(centres, radius=1e-9).reshape(h, w)
        labels[inside & (labels < 0)] = index
    labels = erode_labels(labels, edge_margin_px)
    for index, name in enumerate(names):
        if name in polygons and not (labels == index).any():  # a mask that silently drops the mirror
            raise CalibrationError(
                f"polygon {name!r} keeps no pixel: it holds no pixel centre, or only ones of an earlier "
                f"polygon or within the {edge_margin_px:g} px edge margin", path)
    return labels


def grow_labels(labels: np.ndarray, margin_px: float) -> np.ndarray:
    """The edge margin given back: every unlabelled pixel within margin_px (centre to centre)
    of a labelled one joins the nearest labelled pixel's region. Undoes `erode_labels` up to
    the regions' corners, so that outlines drawn from eroded labels and eroded again on
    redrawing keep the pixels they had."""
    labels = np.asarray(labels, dtype=np.int32)
    margin = float(margin_px)
    if margin <= 0.0 or not (labels >= 0).any():
        return labels.copy()
    distance, (rows, cols) = distance_transform_edt(labels < 0, return_indices=True)
    return np.where((labels < 0) & (distance <= margin), labels[rows, cols], labels).astype(np.int32)


def polygons_from_labels(
    labels: np.ndarray, names: Sequence[str], tolerance_px: float = 0.1, margin_px: float = 0.0
) -> dict[str, np.ndarray]:
    """Per mirror, the outline (K, 2) of its largest region (u, v through the boundary pixels'
    centres), simplified to within tolerance_px (cv2.approxPolyDP). `margin_px`: the edge
    margin the labels were eroded by, grown back first (`grow_labels`), so that
    `labels_from_polygons` with the same margin draws the same masks again."""
    labels = grow_labels(labels, margin_px)
    out: dict[str, np.ndarray] = {}
    for index, name in enumerate(names):
        region = (labels == index).astype(np.uint8)
        if not region.any():
            continue
        contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        largest = max(contours, key=cv2.contourArea)
        simple = cv2.approxPolyDP(largest, tolerance_px, True).reshape(-1, 2)
        out[name] = simple.astype(np.float64)
    return out


def read_polygon_file(path: str | Path) -> dict[str, np.ndarray]:
    """Polygons from a YAML file {name: [[u, v], ...], ...}; errors name the file and mirror."""
    path = Path(path)
    try:
        data = load_yaml(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise CalibrationError(f"cannot read the polygon file: {err.strerror or err}", path) from None
    except UnicodeDecodeError:
        raise CalibrationError("not a text file (polygons are a UTF-8 YAML file)", path) from None
    except yaml.YAMLError as err:
        problem, line = yaml_problem(err)
        raise CalibrationError(problem, path, line) from None
    if isinstance(data, Mapping) and "polygons" in data:
        data = data["polygons"]
    if not isinstance(data, Mapping) or not data:
        raise CalibrationError("expected a mapping {mirror name: [[u, v], ...]}", path)
    out = {}
    for name, poly in data.items():
        try:
            arr = np.asarray(poly, dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.zeros((0,))
        if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 3 or not np.all(np.isfinite(arr)):
            raise CalibrationError(f"{name}: expected a list of >= 3 points [u, v]", path)
        out[str(name)] = arr
    return out


def write_polygon_file(path: str | Path, polygons: Mapping[str, np.ndarray]) -> Path:
    """Write polygons as read_polygon_file reads them (atomically)."""
    path = Path(path)
    data = {k: np.asarray(v, dtype=np.float64).tolist() for k, v in polygons.items()}
    text = "# mirror regions: image polygons, u v in pixels (pixel centres at integers)\n"
    text += dump_yaml(data, sort_keys=False, default_flow_style=None, width=100)
    with atomic_write(path, "w") as handle:
        handle.write(text)
    return path
