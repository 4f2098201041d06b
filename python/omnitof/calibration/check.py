"""Checking a calibration the way the paper's Fig. 6 does: the rig stands among objects of
equal height, and the upper edges of the objects, seen through different mirrors, must come out
at one height. A tilted or shifted mirror plane lifts or lowers its mirror's edges.

`equal_height_world` builds such a scene for the simulator: eight boxes of one height in a ring
around the robot (2 m away, so that their upper edges fall inside the mirrors' view, which
spans about −21° … +16° of elevation on the default rig). `points_from_frame` turns a distance
image into robot-frame points with a calibration: the pixel's ray meets its mirror's plane at
t = d/(n·r), continues reflected, and the ToF distance is the whole path (camera → mirror →
surface). `edge_heights` keeps the points whose horizontal range lies in the objects' band and
takes, per bearing bin, the highest: an upper edge. The spread of those heights per mirror, and
between mirrors' medians, is the check.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnitof.calibration import Calibration, CalibrationError

CHECK_DISTANCE = 2.0  # metres from the robot to the boxes' near faces
CHECK_HEIGHT = 0.6  # metres: the back mirror of the default rig sees up to ~0.7 m at 2 m
CHECK_BOX = 0.4  # metres, box side


def equal_height_world(
    distance: float = CHECK_DISTANCE, height: float = CHECK_HEIGHT, boxes: int = 8
):
    """A 10 m × 10 m room with `boxes` boxes of one height around its centre (the robot's
    place), their near faces `distance` metres away (robot at (0, 0))."""
    from omnitof.sim.worlds import parse_world

    half = 5.0
    specs = []
    for k in range(boxes):
        bearing = 2.0 * math.pi * (k + 0.5) / boxes
        r = distance + CHECK_BOX / 2.0
        specs.append({
            "centre": [r * math.cos(bearing), r * math.sin(bearing)],
            "size": [CHECK_BOX, 1.2],
            "yaw_deg": math.degrees(bearing),
            "height": height,
        })
    data = {
        "name": "calibration-check",
        "description": "objects of equal height around the robot (paper Fig. 6)",
        "ceiling_height": 2.6,
        "walls": [{"points": [[-half, -half], [half, -half], [half, half], [-half, half]], "closed": True}],
        "boxes": specs,
    }
    return parse_world(data)


def render_check_frame(camera, mirrors, *, seed: int = 0, robot_T_camera=None):
    """The simulated frame of the true rig in `equal_height_world`, robot at (0, 0, 0)."""
    from omnitof.sim.render import Renderer, RenderSettings

    renderer = Renderer(equal_height_world(), camera, mirrors, robot_T_camera=robot_T_camera,
                        settings=RenderSettings(sub_rays=4, seed=seed))
    return renderer.render(np.zeros(3), seed=seed)


def points_from_frame(cal: Calibration, distance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robot-frame points (N, 3) and their mirror index (N,) of every labelled pixel with a
    finite distance (metres, one way: the whole path through the mirror)."""
    distance = np.asarray(distance, dtype=np.float64)
    if distance.shape != cal.camera.shape:
        raise CalibrationError(
            f"distance image is {distance.shape}, the calibration's camera {cal.camera.shape}"
        )
    rays = cal.camera.pixel_grid_rays().reshape(-1, 3)
    labels = cal.labels.reshape(-1)
    rho = distance.reshape(-1)
    points, owners = [], []
    for index, plane in enumerate(cal.planes):
        sel = (labels == index) & np.isfinite(rho) & (rho > 0)
        hits = plane.intersect(np.zeros((int(sel.sum()), 3)), rays[sel])
        ok = hits.hit & (rho[sel] > hits.distances)
        p = hits.points[ok] + (rho[sel][ok] - hits.distances[ok])[:, None] * hits.directions[ok]
        points.append(p)
        owners.append(np.full(len(p), index))
    pts = np.vstack(points) if points else np.zeros((0, 3))
    robot = pts @ cal.robot_T_camera[:3, :3].T + cal.robot_T_camera[:3, 3]
    return robot, np.concatenate(owners) if owners else np.zeros(0, dtype=int)


@dataclass
class HeightCheck:
    """Upper-edge heights per mirror: name → (median m, robust std m, bins); and `spread`, the
    largest difference between two mirrors' medians (metres), NaN where fewer than two mirrors
    saw an edge (nothing to compare: `measured` is False)."""

    per_mirror: dict[str, tuple[float, float, int]]
    spread: float
    points: np.ndarray
    owners: np.ndarray
    band: tuple[float, float]

    @property
    def measured(self) -> bool:
        """Whether at least two mirrors saw an upper edge, so that the check compares something."""
        return len(self.per_mirror) >= 2

    def report(self, names: list[str] | None = None) -> list[str]:
        """One line per mirror (`names`: every mirror, those without an edge said so) and the
        difference between them."""
        lines = []
        for name in names if names is not None else list(self.per_mirror):
            if name not in self.per_mirror:
                lines.append(f"{name:>12}: no upper edge in the band")
                continue
            med, std, n = self.per_mirror[name]
            lines.append(f"{name:>12}: upper edge at {1000 * med:7.1f} mm, spread (robust std) {1000 * std:5.1f} mm, "
                         f"{n} bearing bins")
        if self.measured:
            lines.append(f"difference between mirrors: {1000 * self.spread:.1f} mm")
        else:
            lines.append(f"difference between mirrors: not measured (an upper edge through {len(self.per_mirror)} "
                         "mirror(s); the check needs two)")
        return lines


def edge_heights(
    cal: Calibration,
    distance: np.ndarray,
    band: tuple[float, float] = (CHECK_DISTANCE - 0.05, CHECK_DISTANCE + 0.15),
    bin_deg: float = 2.0,
    min_height: float = 0.5 * CHECK_HEIGHT,
) -> HeightCheck:
    """Per mirror, the highest point per bearing bin among points whose horizontal range lies
    in `band` (the objects' near faces) and whose height exceeds min_height (not the floor
    between the objects), and the statistics of those heights."""
    points, owners = points_from_frame(cal, distance)
    horizontal = np.hypot(points[:, 0], points[:, 1])
    keep = (horizontal >= band[0]) & (horizontal <= band[1]) & (points[:, 2] > min_height)
    bearing = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360.0
    bins = np.floor(bearing / bin_deg).astype(int)
    per_mirror = {}
    for index, name in enumerate(cal.names):
        sel = keep & (owners == index)
        tops = []
        for b in np.unique(bins[sel]):
            z = points[sel & (bins == b), 2]
            if len(z) >= 3:
                tops.append(float(z.max()))
        if tops:
            med = float(np.median(tops))
            # Robust spread (1.4826 × median absolute deviation): mixed pixels at the boxes'
            # sides give a few wild bins.
            mad = 1.4826 * float(np.median(np.abs(np.array(tops) - med)))
            per_mirror[name] = (med, mad, len(tops))
    medians = [v[0] for v in per_mirror.values()]
    spread = float(max(medians) - min(medians)) if len(medians) > 1 else math.nan
    return HeightCheck(per_mirror, spread, points[keep], owners[keep], band)


def plane_errors(estimated: Calibration, truth: Calibration) -> dict[str, tuple[float, float]]:
    """Per mirror name in both: (angle between normals in degrees, d error in mm)."""
    out = {}
    for name, plane in zip(estimated.names, estimated.planes):
        if name not in truth.names:
            continue
        true = truth.planes[truth.names.index(name)]
        angle = math.degrees(math.acos(min(1.0, abs(float(plane.normal @ true.normal)))))
        out[name] = (angle, 1000.0 * (plane.d - true.d))
    return out
