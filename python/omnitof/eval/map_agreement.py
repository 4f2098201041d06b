"""How well an estimated occupancy map agrees with a reference map of the same place, both
map_server maps (YAML + PGM), once the estimate is moved into the reference's frame.

The simulated worlds' maps are scored against their true walls (`eval.floorplan`: the demo's
"occupied cells within 5 cm of a wall"). A user's building has no floor plan in omnitof's terms,
but often a reference map: a floor plan drawn as a map_server image, or the map another system
made of the same place. This module scores an estimate against it the same way:

1. **Occupied cells** of each map (map_server's trinary reading, `io.rosmap.read_ros_map`; a map
   in memory by the same thresholds, p > 0.65 occupied, p < 0.196 free), taken as points at the
   cells' centres. Distances are between cell centres: a reference cell says a wall lies
   somewhere in it, and its centre is where that is on average (the nearest point of the cell
   instead would favour the estimate by up to a cell). A reference of resolution r therefore
   blurs each distance by up to r/2: draw a floor plan finely (`eval.floorplan.plan_map`, 1 cm
   in benchmarks/map_agreement.py).
2. **Alignment** (`align`), the pose reference_T_estimate:
   - "none": the maps share a frame (a reference made from the same start, as the simulator's);
   - "initial": trimmed ICP (Besl & McKay 1992; each step the closed-form rigid fit of
     `eval.ate.fit_alignment` to the nearest reference cell of every estimate cell within a
     pairing distance that shrinks from 1 m to a few cells) from a given pose (`initial`;
     default the identity);
   - "search" (default): a global search first, then the same ICP. Every rotation in steps
     small enough that the estimate's farthest cell moves by at most half a coarse cell; per
     rotation the best translation by cross-correlating the estimate's cells, binned at
     `SEARCH_CELL`, with the reference's walls blurred by a Gaussian of one coarse cell, on the
     FFT (Olson's correlative matching, "Real-time correlative scan matching", ICRA 2009,
     exhaustive over translation); the `SEARCH_CANDIDATES` best rotations refined by ICP, and
     the one with the most cells within the tolerance kept. A building that looks the same
     turned (a square hall) has more than one answer: the figure shows which one was taken,
     and "initial" with a pose the user knows settles it.
3. **Scores** at `tolerance` (the demo's 5 cm by default):
   - `near`: the share of the estimate's occupied cells within `tolerance` of a reference
     occupied cell, and the distances' mean, median and 90th percentile: how much of what the
     estimate calls a wall is one (clutter that the reference does not hold counts against it);
   - `covered`: among the reference's occupied cells that the estimate observed (within `reach`
     of a cell the estimate holds free: the faces of walls the robot saw, not those of rooms it
     never entered), the share within `tolerance` of an estimate occupied cell: how much of the
     seen walls the estimate mapped.

Written here from the papers: scipy gives the KD-tree and the FFT, no package in our stack
aligns two occupancy maps (OpenCV's `estimateAffinePartial2D` needs point correspondences, and
its ICP lives in the contrib module's 3D surface matching).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import fft as sfft
from scipy import ndimage
from scipy.spatial import cKDTree

from omnitof.errors import OmnitofError
from omnitof.eval.ate import fit_alignment
from omnitof.geometry import compose, wrap_angle
from omnitof.types import OccupancyMap

ALIGNMENTS = ("search", "initial", "none")
# The global search's raster (m): coarse enough that the rotations of a building's map take
# seconds, fine enough that the ICP after it starts within its first pairing distance. A map
# larger than SEARCH_CELLS_ACROSS of them across its radius is searched on a coarser raster, so
# that the search stays at most about 2·π·SEARCH_CELLS_ACROSS rotations of a bounded raster.
SEARCH_CELL = 0.2
SEARCH_CELLS_ACROSS = 100
# Rotations of the search refined by ICP (the best-scoring ones, at least 5 degrees apart).
SEARCH_CANDIDATES = 5
SEARCH_SEPARATION = math.radians(5.0)
# ICP's pairing distances (m), each run to convergence: wide first to pull in a coarse start,
# then down to a few cells so that clutter and unmapped walls do not pull (none below two of
# the coarser map's cells, whose centres lie that far apart on one wall).
ICP_PAIRING = (1.0, 0.5, 0.25, 0.1)
ICP_MAX_ITERATIONS = 100
ICP_CONVERGED = 1e-7  # m and rad per step
# Occupied and free, as map_server's defaults (io.rosmap.write_ros_map writes them).
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
# Fewest occupied cells a map must have to be aligned and scored.
MIN_CELLS = 3


class MapAgreementError(OmnitofError, ValueError):
    """The maps cannot be compared: too few occupied cells, or no place where they overlap."""


@dataclass(frozen=True)
class MapAgreement:
    """An estimate's occupied cells against a reference's, after the alignment `pose`
    (reference_T_estimate: x, y m, theta rad)."""

    align: str
    pose: tuple[float, float, float]
    tolerance: float
    reach: float
    estimate_cells: int
    reference_cells: int
    near: float  # share of the estimate's occupied cells within tolerance of the reference's
    mean_distance: float
    median_distance: float
    p90_distance: float
    seen_reference_cells: int
    covered: float  # share of the seen reference cells within tolerance of the estimate's (nan: none seen)

    def format(self) -> str:
        x, y, th = self.pose
        how = {"none": "none (the maps' frames taken as one)", "initial": "ICP from the given pose",
               "search": "global search, then ICP"}[self.align]
        covered = "n/a (no reference wall next to the estimate's free space)" if math.isnan(self.covered) \
            else f"{100 * self.covered:.1f} %"
        return "\n".join([
            f"alignment: {how}: estimate -> reference x {x:+.4f} m, y {y:+.4f} m, "
            f"rotation {math.degrees(th):+.3f} deg",
            f"estimate's occupied cells within {100 * self.tolerance:g} cm of the reference's: "
            f"{100 * self.near:.1f} % of {self.estimate_cells}",
            f"their distance to the reference's [m]: mean {self.mean_distance:.4f}, median "
            f"{self.median_distance:.4f}, p90 {self.p90_distance:.4f}",
            f"reference's occupied cells the estimate saw (within {self.reach:g} m of its free space) "
            f"that it mapped within {100 * self.tolerance:g} cm: {covered} of {self.seen_reference_cells}",
        ])

    def to_dict(self) -> dict[str, Any]:
        x, y, th = self.pose
        return {
            "align": self.align,
            "pose": {"x_m": x, "y_m": y, "rotation_deg": math.degrees(th)},
            "tolerance_m": self.tolerance, "reach_m": self.reach,
            "estimate_cells": self.estimate_cells, "reference_cells": self.reference_cells,
            "near": self.near, "mean_distance_m": self.mean_distance, "median_distance_m": self.median_distance,
            "p90_distance_m": self.p90_distance,
            "seen_reference_cells": self.seen_reference_cells,
            "covered": None if math.isnan(self.covered) else self.covered,
        }


def cell_centres(occ: OccupancyMap, which: str) -> np.ndarray:
    """(K, 2) centres (m) of the map's known cells that are occupied or free, by map_server's
    default thresholds (those `io.rosmap.write_ros_map` writes with): a map in memory is
    scored as the same map read back from its YAML would be."""
    p = occ.probability
    known = np.asarray(occ.known, dtype=bool)
    mask = known & ((p > OCCUPIED_THRESH) if which == "occupied" else (p < FREE_THRESH))
    rows, cols = np.nonzero(mask)
    return np.column_stack([occ.origin[0] + (cols + 0.5) * occ.resolution,
                            occ.origin[1] + (rows + 0.5) * occ.resolution])


def transform(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points (N, 2) moved by the pose (x, y, theta): R(theta)·p + (x, y)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.column_stack([c * points[:, 0] - s * points[:, 1] + pose[0],
                            s * points[:, 0] + c * points[:, 1] + pose[1]])


def compare_maps(
    estimate: OccupancyMap,
    reference: OccupancyMap,
    *,
    align: str = "search",
    initial: tuple[float, float, float] = (0.0, 0.0, 0.0),
    tolerance: float = 0.05,
    reach: float | None = None,
) -> tuple[MapAgreement, np.ndarray, np.ndarray]:
    """Score `estimate` against `reference` (module docstring).

    Args:
        align: "search", "initial" or "none".
        initial: reference_T_estimate (x, y m, theta rad) to start ICP from ("initial") or to
            take as it is ("none" ignores it: the identity).
        tolerance: metres.
        reach: metres; default the larger of 2·tolerance and three of the estimate's cells.

    Returns:
        (the agreement, the estimate's occupied cells moved into the reference's frame (K, 2),
        their distances to the reference's nearest occupied cell (K,)).

    Raises:
        MapAgreementError: a map with fewer than MIN_CELLS occupied cells, or an alignment that
            pairs fewer than MIN_CELLS of them.
        ValueError: an unknown `align`, a tolerance or reach that is not a positive number.
    """
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {', '.join(ALIGNMENTS)}, got {align!r}")
    if not (math.isfinite(tolerance) and tolerance > 0.0):
        raise ValueError(f"tolerance must be a positive number of metres, got {tolerance!r}")
    if reach is None:
        reach = round(max(2.0 * tolerance, 3.0 * estimate.resolution), 9)
    if not (math.isfinite(reach) and reach > 0.0):
        raise ValueError(f"reach must be a positive number of metres, got {reach!r}")
    est = cell_centres(estimate, "occupied")
    ref = cell_centres(reference, "occupied")
    for name, pts in (("the estimate", est), ("the reference", ref)):
        if len(pts) < MIN_CELLS:
            raise MapAgreementError(f"{name} has {len(pts)} occupied cells; at least {MIN_CELLS} are needed")
    tree = cKDTree(ref)
    floor = 2.0 * max(estimate.resolution, reference.resolution)
    pairing = tuple(sorted({max(p, floor) for p in ICP_PAIRING}, reverse=True))
    if align == "none":
        pose = np.zeros(3)
    elif align == "initial":
        pose = icp(est, ref, tree, np.asarray(initial, dtype=np.float64), pairing)
    else:
        pose = search(est, ref, tree, tolerance, pairing)
    moved = transform(est, pose)
    distance = tree.query(moved)[0]
    seen_ref, covered = _coverage(estimate, moved, ref, pose, tolerance, reach)
    return MapAgreement(
        align=align, pose=(float(pose[0]), float(pose[1]), float(wrap_angle(pose[2]))),
        tolerance=tolerance, reach=reach, estimate_cells=len(est), reference_cells=len(ref),
        near=float(np.mean(distance <= tolerance)), mean_distance=float(np.mean(distance)),
        median_distance=float(np.median(distance)), p90_distance=float(np.percentile(distance, 90)),
        seen_reference_cells=seen_ref, covered=covered,
    ), moved, distance


def _coverage(estimate: OccupancyMap, moved: np.ndarray, ref: np.ndarray, pose: np.ndarray,
              tolerance: float, reach: float) -> tuple[int, float]:
    free = cell_centres(estimate, "free")
    if len(free) == 0:
        return 0, math.nan
    seen = np.isfinite(cKDTree(transform(free, pose)).query(ref, distance_upper_bound=reach)[0])
    if not seen.any():
        return 0, math.nan
    near = cKDTree(moved).query(ref[seen], distance_upper_bound=tolerance)[0]
    return int(seen.sum()), float(np.mean(np.isfinite(near)))


def icp(points: np.ndarray, ref: np.ndarray, tree: cKDTree, pose: np.ndarray,
        pairings: tuple[float, ...] = ICP_PAIRING) -> np.ndarray:
    """reference_T_estimate refined from `pose` by trimmed point-to-point ICP (module docstring),
    run to convergence at each pairing distance (m) in turn."""
    pose = np.array(pose, dtype=np.float64)
    for pairing in pairings:
        for _ in range(ICP_MAX_ITERATIONS):
            moved = transform(points, pose)
            d, index = tree.query(moved, distance_upper_bound=pairing)
            paired = np.isfinite(d)
            if paired.sum() < MIN_CELLS:
                raise MapAgreementError(
                    f"the alignment pairs {int(paired.sum())} of the estimate's {len(points)} occupied cells with "
                    f"the reference's within {pairing:g} m: the maps do not overlap there (give a closer --initial)")
            try:
                step = fit_alignment(moved[paired], ref[index[paired]])
            except ValueError:  # every paired cell at one place: no rotation to fit
                break
            delta = np.array([step.translation[0], step.translation[1], step.rotation])
            pose = compose(delta, pose)
            if np.all(np.abs(delta) < ICP_CONVERGED):
                break
    return pose


def search(points: np.ndarray, ref: np.ndarray, tree: cKDTree, tolerance: float,
           pairings: tuple[float, ...] = ICP_PAIRING) -> np.ndarray:
    """reference_T_estimate from a global search over rotation and translation, then ICP."""
    centroid = points.mean(axis=0)
    centred = points - centroid
    radius = max(float(np.max(np.hypot(centred[:, 0], centred[:, 1]))), SEARCH_CELL)
    cell = max(SEARCH_CELL, radius / SEARCH_CELLS_ACROSS)
    # ICP's first pairing reaches past the search's own error (a cell and a half).
    pairings = tuple(sorted({max(pairings[0], 2.0 * cell), *pairings}, reverse=True))
    # The reference's walls, blurred: exp(-d²/2σ²) with σ one coarse cell.
    lo = ref.min(axis=0) - 3 * cell
    shape_ref = tuple((np.ceil((ref.max(axis=0) + 3 * cell - lo) / cell)).astype(int)[::-1])  # rows (y), cols (x)
    walls = np.zeros(shape_ref, dtype=bool)
    ij = np.floor((ref - lo) / cell).astype(int)
    walls[ij[:, 1], ij[:, 0]] = True
    blurred = np.exp(-0.5 * ndimage.distance_transform_edt(~walls) ** 2)
    # The estimate, turned about its centroid, always fits a square raster of side 2·radius.
    side = int(math.ceil(2 * radius / cell)) + 2
    shape = (sfft.next_fast_len(shape_ref[0] + side - 1), sfft.next_fast_len(shape_ref[1] + side - 1))
    ref_spectrum = sfft.rfft2(blurred, s=shape)
    step = 0.5 * cell / radius  # the farthest cell moves half a coarse cell per step
    angles = np.arange(0.0, 2 * math.pi, step)
    best = np.empty((len(angles), 3))  # score, x, y of the best translation per rotation
    low = -radius - cell  # the estimate raster's lower-left corner, relative to the centroid
    for k, theta in enumerate(angles):
        turned = transform(centred, np.array([0.0, 0.0, theta]))
        ab = np.floor((turned - low) / cell).astype(int)
        raster = np.bincount(ab[:, 1] * side + ab[:, 0], minlength=side * side).reshape(side, side).astype(np.float64)
        score = sfft.irfft2(ref_spectrum * sfft.rfft2(raster[::-1, ::-1], s=shape), s=shape)
        r, c = np.unravel_index(int(np.argmax(score)), score.shape)
        # Index (r, c) lays raster cell (a, b) on reference cell (a + v, b + u), so the turned
        # points move by t = lo - low + (u, v)·cell onto the reference.
        u, v = c - (side - 1), r - (side - 1)
        best[k] = (score[r, c], lo[0] - low + u * cell, lo[1] - low + v * cell)
    order = np.argsort(-best[:, 0], kind="stable")
    chosen: list[int] = []
    for k in order:
        if all(abs(wrap_angle(angles[k] - angles[j])) >= SEARCH_SEPARATION for j in chosen):
            chosen.append(int(k))
        if len(chosen) == SEARCH_CANDIDATES:
            break
    results = []
    for k in chosen:
        theta = float(angles[k])
        c, s = math.cos(theta), math.sin(theta)
        # p -> R(p - centroid) + t = R p + (t - R centroid)
        start = np.array([best[k, 1] - (c * centroid[0] - s * centroid[1]),
                          best[k, 2] - (s * centroid[0] + c * centroid[1]), theta])
        try:
            pose = icp(points, ref, tree, start, pairings)
        except MapAgreementError:
            continue
        d = tree.query(transform(points, pose))[0]
        results.append((float(np.mean(d <= tolerance)), -float(np.mean(np.minimum(d, 1.0))), pose))
    if not results:
        raise MapAgreementError("the search found no place where the estimate overlaps the reference")
    return max(results, key=lambda r: (r[0], r[1]))[2]
