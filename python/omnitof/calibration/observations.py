"""What the joint refinement (`calibration.refine`) fits, found in the calibration images.

From the closed-form calibration (intrinsics, mirror planes) as the start:

- a checkerboard image gives its corners (`intrinsics.detect_checkerboard`), its pose
  (cv2.solvePnP) and the path lengths of the board's pixels (inside its outline, 2 px in);
- a dot-target image gives the four dot pairs (`mirror_planes.pairs_of_image`), matched to the
  printed square by triangulating them through the start plane and aligning the square to them
  (every order of the four tried, Kabsch), and the path lengths of the card's pixels
  seen directly and through the mirror (white pixels only, 2 px inside the card's outline);
- a two-mirror board image gives the path lengths of the pixels on the largest plane among the
  bright pixels seen through the mirrors (RANSAC on the points of the start calibration), for
  each mirror that sees at least MIN_PLANE_PIXELS of it.

Path-length samples are weighted by amplitude (relative to the card's median), as the phase
noise falls with it, and thinned to at most MAX_SAMPLES per card view (a seeded choice).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
from scipy.ndimage import binary_erosion, grey_dilation

from omnitof.calibration import CalibrationError
from omnitof.calibration.images import AmplitudeImage
from omnitof.calibration.intrinsics import detect_checkerboard
from omnitof.calibration.masks import erode_labels
from omnitof.calibration.mirror_planes import _triangulate, normalised, pairs_of_image
from omnitof.calibration.refine import PlaneView, PosedView, Problem, Refinement, ToFSamples, refine
from omnitof.calibration.targets import Checkerboard, DotTarget
from omnitof.sensor.camera import Camera
from omnitof.sensor.mirrors import MirrorPlane

MAX_SAMPLES = 120
EDGE_PX = 2
MIN_PLANE_PIXELS = 50
# RANSAC of the two-mirror board's plane: inlier band (metres) and hypotheses. A dim board may
# hold a fifth of the bright pixels (the room behind passes the brightness test too), so that 3
# random ones all lie on it in 0.8 % of the trials: 1000 trials miss it with probability 3e-4.
PLANE_BAND = 0.03
PLANE_TRIALS = 1000
# Share of the brightest amplitude above which a pixel may belong to a near board (or a wall:
# any flat surface seen through two mirrors will do, so no test against the background).
BRIGHT = 0.08


def _samples(image: AmplitudeImage, mask: np.ndarray, mirror: int, rng: np.random.Generator) -> ToFSamples | None:
    if image.distance is None:
        return None
    mask = mask & np.isfinite(image.distance) & (image.amplitude > 0)
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return None
    if len(rows) > MAX_SAMPLES:
        keep = np.sort(rng.choice(len(rows), MAX_SAMPLES, replace=False))
        rows, cols = rows[keep], cols[keep]
    amp = image.amplitude[rows, cols].astype(np.float64)
    weights = np.clip(amp / np.median(amp), 0.05, 3.0)
    pixels = np.stack([cols, rows], axis=1).astype(np.float64)
    return ToFSamples(pixels, image.distance[rows, cols].astype(np.float64), weights, mirror)


def _polygon_mask(shape: tuple[int, int], pixels: np.ndarray) -> np.ndarray:
    mask = np.zeros(shape, dtype=np.uint8)
    if np.all(np.isfinite(pixels)):
        cv2.fillPoly(mask, [np.round(pixels).astype(np.int32).reshape(-1, 1, 2)], 1)
    return binary_erosion(mask > 0, iterations=EDGE_PX)


def _outline(extent: tuple[float, float, float, float], steps: int = 8) -> np.ndarray:
    x0, x1, y0, y1 = extent
    t = np.linspace(0.0, 1.0, steps, endpoint=False)
    edges = [np.stack([x0 + (x1 - x0) * t, np.full_like(t, y0)], 1),
             np.stack([np.full_like(t, x1), y0 + (y1 - y0) * t], 1),
             np.stack([x1 - (x1 - x0) * t, np.full_like(t, y1)], 1),
             np.stack([np.full_like(t, x0), y1 - (y1 - y0) * t], 1)]
    xy = np.vstack(edges)
    return np.column_stack([xy, np.zeros(len(xy))])


def board_view(camera: Camera, image: AmplitudeImage, board: Checkerboard, rng: np.random.Generator) -> PosedView | None:
    """The checkerboard's corners, start pose and path lengths; None if it is not found."""
    corners = detect_checkerboard(image.amplitude, board.pattern_size)
    if corners is None:
        return None
    points = board.object_points().astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(points, corners.astype(np.float64), camera.K, camera.dist_coeffs,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(rvec)[0]
    pose[:3, 3] = tvec.ravel()
    outline = camera.project(_outline(board.extent()) @ pose[:3, :3].T + pose[:3, 3])
    tof = _samples(image, _polygon_mask(camera.shape, outline), -1, rng)
    return PosedView(image.name, "board", points, corners.astype(np.float64),
                     np.full(len(points), -1), pose, [tof] if tof else [])


def _kabsch(model: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    mc, pc = model.mean(axis=0), points.mean(axis=0)
    u, _, vt = np.linalg.svd((model - mc).T @ (points - pc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    t = pc - R @ mc
    return R, t, float(np.sum((model @ R.T + t - points) ** 2))


def dot_view(
    camera: Camera, image: AmplitudeImage, names: Sequence[str], planes: Sequence[MirrorPlane],
    labels: np.ndarray, target: DotTarget, rng: np.random.Generator,
) -> tuple[PosedView | None, str]:
    """The dot target's four dots in both views, start pose and path lengths; (None, why)
    if the image cannot be used."""
    normals = np.array([p.normal for p in planes])
    try:
        index, pairs = pairs_of_image(camera, image, names, normals, labels)
    except CalibrationError as err:
        return None, str(err)
    if len(pairs.direct) != 4:
        return None, f"{image.name}: {len(pairs.direct)} dot pairs, the refinement needs all four"
    plane = planes[index]
    found, _, _ = _triangulate(plane.normal, plane.d, normalised(camera, pairs.direct),
                               normalised(camera, pairs.mirrored))
    model = target.dot_centres()
    best = None
    for order in itertools.permutations(range(4)):  # the pairs come in no particular order
        R, t, cost = _kabsch(model[list(order)], found)
        if best is None or cost < best[0]:
            best = (cost, order, R, t)
    _, order, R, t = best
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, t
    points = model[list(order)]
    pixels = np.vstack([pairs.direct, pairs.mirrored])
    via = np.concatenate([np.full(4, -1), np.full(4, index)])
    card = _outline(target.extent()) @ R.T + t
    white = image.amplitude >= 0.5 * grey_dilation(image.amplitude, size=(7, 7))
    direct_mask = _polygon_mask(camera.shape, camera.project(card)) & white
    mirrored_px = camera.project(plane.reflect_points(card))
    region = erode_labels(labels, 2.0) == index
    mirrored_mask = _polygon_mask(camera.shape, mirrored_px) & white & region & ~direct_mask
    tof = [s for s in (_samples(image, direct_mask, -1, rng), _samples(image, mirrored_mask, index, rng)) if s]
    return PosedView(image.name, "dots", np.vstack([points, points]), pixels, via, pose, tof,
                     radius=target.radius), ""


def plane_view(
    camera: Camera, image: AmplitudeImage, planes: Sequence[MirrorPlane], labels: np.ndarray,
    rng: np.random.Generator,
) -> tuple[PlaneView | None, str]:
    """The path lengths of a flat board seen through two or more mirrors; (None, why)."""
    if image.distance is None:
        return None, f"{image.name}: no distance image"
    inner = erode_labels(labels, 3.0)
    a = np.nan_to_num(image.amplitude.astype(np.float64))
    bright = (a > BRIGHT * np.percentile(a, 99.5)) & (inner >= 0) & np.isfinite(image.distance)
    rows, cols = np.nonzero(bright)
    if len(rows) < 2 * MIN_PLANE_PIXELS:
        return None, f"{image.name}: too few bright pixels in the mirrors"
    rays = camera.pixel_grid_rays()[rows, cols]
    which = inner[rows, cols]
    points = np.empty((len(rows), 3))
    for k, plane in enumerate(planes):  # per mirror: the reflected points (eq. 6)
        sel = which == k
        virtual = rays[sel] * image.distance[rows[sel], cols[sel], None]
        points[sel] = plane.reflect_points(virtual)
    # A hypothesis counts by what it is wanted for: the plane seen through two mirrors. Scored
    # by its inliers in its second-best mirror (then by all), so that a larger flat patch of the
    # background behind one mirror cannot win over the board (simulate calibration, seed 0: a
    # dim back-right board lost to the room behind the front mirror, and the image was unused).
    best, best_score = None, (-1, -1)
    for _ in range(PLANE_TRIALS):
        i = rng.choice(len(points), 3, replace=False)
        n = np.cross(points[i[1]] - points[i[0]], points[i[2]] - points[i[0]])
        if np.linalg.norm(n) < 1e-9:
            continue
        n /= np.linalg.norm(n)
        inside = np.abs(points @ n - n @ points[i[0]]) < PLANE_BAND
        per_mirror = np.sort(np.bincount(which[inside], minlength=len(planes)))
        score = (int(per_mirror[-2]) if len(planes) > 1 else 0, int(inside.sum()))
        if score > best_score:
            best, best_score = inside, score
    if best is None:
        return None, f"{image.name}: no plane found"
    centre = points[best].mean(axis=0)
    normal = np.linalg.svd(points[best] - centre)[2][-1]
    mask = np.zeros(camera.shape, dtype=bool)
    mask[rows[best], cols[best]] = True
    mask = binary_erosion(mask, iterations=1)
    tof = []
    for k in range(len(planes)):
        sel = mask & (inner == k)
        if sel.sum() >= MIN_PLANE_PIXELS:
            s = _samples(image, sel, k, rng)
            if s:
                tof.append(s)
    if len(tof) < 2:
        return None, f"{image.name}: the plane is seen through {len(tof)} mirror(s), need two"
    return PlaneView(image.name, normal, float(normal @ centre), tof), ""


def build_problem(
    camera: Camera,
    planes: Sequence[MirrorPlane],
    names: Sequence[str],
    labels: np.ndarray,
    board_images: Sequence[AmplitudeImage],
    dot_images: Sequence[AmplitudeImage],
    pair_images: Sequence[AmplitudeImage] = (),
    *,
    board: Checkerboard = Checkerboard(),
    target: DotTarget = DotTarget(),
    seed: int = 0,
    path_lengths: bool = True,
) -> tuple[Problem, list[str]]:
    """(the refinement problem, notes on the images it could not use). path_lengths False:
    no ToF residuals and no two-mirror boards (for distances with an uncorrected systematic
    error, which would pull the focal length and the planes: see `refine_calibration`)."""
    rng = np.random.default_rng(seed)
    views: list[PosedView] = []
    notes: list[str] = []
    for image in board_images:
        view = board_view(camera, image, board, rng)
        if view is None:
            notes.append(f"{image.name}: no checkerboard found")
        else:
            views.append(view)
    for image in dot_images:
        view, why = dot_view(camera, image, names, planes, labels, target, rng)
        if view is None:
            notes.append(why)
        else:
            views.append(view)
    if not path_lengths:
        for view in views:
            view.tof = []
        return Problem(camera, list(planes), list(names), views, []), notes
    plane_views = []
    for image in pair_images:
        pv, why = plane_view(camera, image, planes, labels, rng)
        if pv is None:
            notes.append(why)
        else:
            plane_views.append(pv)
    return Problem(camera, list(planes), list(names), views, plane_views), notes


def refine_calibration(
    calibration: Any,
    board_images: Sequence[AmplitudeImage],
    dot_images: Sequence[AmplitudeImage],
    pair_images: Sequence[AmplitudeImage] = (),
    *,
    outside: np.ndarray | None = None,
    board: Checkerboard = Checkerboard(),
    target: DotTarget = DotTarget(),
    seed: int = 0,
    path_lengths: bool = True,
) -> tuple[Any, Refinement]:
    """(the refined Calibration, the Refinement) from a closed-form calibration and its images.

    path_lengths: use the ToF path lengths (and the two-mirror boards). Only for distances
    without a systematic error, or corrected for it (`calibration.distance`): with issue 15's
    simulated errors (wiggling, amplitude offset, fixed pattern) left in, they pulled the focal
    length 10 % and the planes 10 mm off (seed 0). Without them the refinement fits corners and
    dots jointly (the dot spacing fixes the scale).

    The masks are redrawn from the refined planes (`masks.labels_from_planes`; `outside`: the
    pixels past the mirrors' outer edges, default the calibration's unlabelled pixels); the
    refinement's standard deviations and residuals go into `quality.refinement`.
    """
    from omnitof.calibration.masks import labels_from_planes

    problem, notes = build_problem(
        calibration.camera, calibration.planes, calibration.names, calibration.labels,
        board_images, dot_images, pair_images, board=board, target=target, seed=seed,
        path_lengths=path_lengths,
    )
    result = refine(problem)
    if outside is None:
        outside = calibration.labels < 0
    labels = labels_from_planes(result.camera, result.planes, outside, calibration.edge_margin_px)
    rig = replace(calibration.rig, camera=result.camera, planes=tuple(result.planes))
    refined = calibration.with_rig(rig)
    refined.labels = labels
    used = [v for v in problem.views if v.name not in result.rejected]
    counts = {"boards": sum(v.kind == "board" for v in used), "dot_targets": sum(v.kind == "dots" for v in used),
              "two_mirror_boards": len(problem.plane_views)}
    refined.quality["refinement"] = {**result.quality(), "skipped": notes, "views_used": counts}
    refined.provenance["refinement"] = (
        f"joint refinement (calibration.refine): {counts['boards']} boards, "
        f"{counts['dot_targets']} dot targets, {counts['two_mirror_boards']} two-mirror boards"
        + ("" if path_lengths else "; no ToF path lengths (distances with a systematic error)")
        + (f"; left out as outliers: {', '.join(result.rejected)}" if result.rejected else "")
    )
    return refined, result
