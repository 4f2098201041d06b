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
   - "initial": ICP from a given pose (`initial`; default the identity): each estimate cell
     paired with the nearest reference cell within a pairing distance that shrinks from 1 m to
     a few cells (farther ones, clutter and walls the reference lacks, left out), then one
     Gauss-Newton step of the point-to-line distances where the reference cell lies on a wall
     (its 9 nearest cells along a line, normal by their principal axes) and the point-to-point
     ones elsewhere (Chen & Medioni 1992; point-to-point alone, Besl & McKay 1992, stalls on
     the cells' lattice a few tenths of a degree off), to convergence;
   - "search" (default): a global search first, then the same ICP. Every rotation in steps
     small enough that the estimate's farthest cell moves by at most half a coarse cell; per
     rotation the best translation by cross-correlating the estimate's cells, binned at
     `SEARCH_CELL`, with the reference's walls blurred by a Gaussian of one coarse cell, on the
     FFT (Olson's correlative matching, "Real-time correlative scan matching", ICRA 2009,
     exhaustive over translation); the `SEARCH_CANDIDATES` best rotations refined by ICP on at
     most `SEARCH_CELLS` of the estimate's cells, the one with the most cells within the
     tolerance refined again on all of them.
   Two checks say where the answer cannot be trusted (warnings, and fields of the result): a
   building that looks the same turned or moved (a square hall, a corridor's repeated doors)
   gives the search a second candidate nearly as good (`runner_up_near`); walls that all run
   one way (a straight corridor) leave the pose free to slide along them, which the
   Gauss-Newton system's conditioning shows (`constraint`: its smallest eigenvalue over its
   largest, the rotation scaled by the cells' radius about their centroid).
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
from omnitof.geometry import compose, wrap_angle
from omnitof.io.rosmap import DEFAULT_FREE_THRESH, DEFAULT_OCCUPIED_THRESH
from omnitof.types import OccupancyMap

ALIGNMENTS = ("search", "initial", "none")
# The global search's raster (m): coarse enough that the rotations of a building's map take
# seconds, fine enough that the ICP after it starts within its first pairing distance. A map
# larger than SEARCH_CELLS_ACROSS of them across its radius is searched on a coarser raster, so
# that a turn takes at most 2·π·2·SEARCH_CELLS_ACROSS rotations of a bounded raster.
SEARCH_CELL = 0.2
SEARCH_CELLS_ACROSS = 100
# Rotations of the search refined by ICP (the best-scoring ones, at least 5 degrees apart), on
# at most this many of the estimate's cells (every k-th) before the winner's final ICP.
SEARCH_CANDIDATES = 5
SEARCH_SEPARATION = math.radians(5.0)
SEARCH_CELLS = 4000
# A runner-up of the search that lies elsewhere (moving the cells by more than this many
# tolerances on average) within this share of cells of the best is an ambiguity worth a warning.
RUNNER_UP_APART = 10.0
RUNNER_UP_CLOSE = 0.02
# ICP's pairing distances (m), each run to convergence: wide first to pull in a coarse start,
# then down to a few cells so that clutter and unmapped walls do not pull (none below two of
# the coarser map's cells, whose centres lie that far apart on one wall).
ICP_PAIRING = (1.0, 0.5, 0.25, 0.1)
ICP_MAX_ITERATIONS = 100
ICP_CONVERGED = 1e-6  # m: how far a step moves the estimate's cells at most
# A reference cell lies on a wall where its nearest cells spread along a line: the smaller
# principal variance under this share of the larger (as the Rust core's fitted walls).
WALL_LINEARITY = 0.1
WALL_NEIGHBOURS = 9
# Below this conditioning the shared walls leave the pose free along one direction (a straight
# corridor: 0, tests/test_map_agreement.py; the worlds' maps in benchmarks/map_agreement.py
# 0.30-0.57, two runs of Intel 0.88, of Freiburg 079 0.99, a drawn square hall 0.52).
WELL_CONSTRAINED = 0.01
# Directions whose eigenvalue lies below this share of the largest are left where they are.
DEGENERATE = 1e-6
# Fewest occupied cells a map must have to be aligned and scored.
MIN_CELLS = 3
# Occupied and free as map_server reads them with its usual thresholds (io.rosmap), compared
# as log-odds so that a large map is not turned into probabilities three times over.
OCCUPIED_LOG_ODDS = math.log(DEFAULT_OCCUPIED_THRESH / (1.0 - DEFAULT_OCCUPIED_THRESH))
FREE_LOG_ODDS = math.log(DEFAULT_FREE_THRESH / (1.0 - DEFAULT_FREE_THRESH))


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
    constraint: float = math.nan  # conditioning of the fit (nan: none fitted)
    weakest: tuple[float, float, float] | None = None  # the direction it fixes least (x, y, radius·theta)
    runner_up_near: float | None = None  # the search's best candidate elsewhere
    runner_up_moved: float | None = None  # how far it moves the cells from the answer, m (mean)

    def warnings(self) -> list[str]:
        """What makes the alignment doubtful, one sentence each (none: nothing found)."""
        out = []
        if self.weakest is not None and self.constraint < WELL_CONSTRAINED:
            wx, wy, wt = self.weakest
            along = "its rotation" if abs(wt) > math.hypot(wx, wy) else \
                f"the direction ({wx:+.2f}, {wy:+.2f}) of the reference's frame"
            out.append(f"the walls the two maps share hardly fix the estimate's position along {along} "
                       f"(conditioning {self.constraint:.1e}): the alignment may slide there; look at the figure, "
                       "or score with --align none or --initial where the frames are known")
        if self.runner_up_near is not None and self.runner_up_near >= self.near - RUNNER_UP_CLOSE:
            out.append(f"another alignment, moving the estimate's cells {self.runner_up_moved:.2f} m on average from "
                       f"this one, fits nearly as well ({100 * self.runner_up_near:.1f} % against "
                       f"{100 * self.near:.1f} %): the building looks alike there; look at the figure, or give "
                       "--initial")
        return out

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
            "constraint": None if math.isnan(self.constraint) else self.constraint,
            "runner_up": None if self.runner_up_near is None else
            {"near": self.runner_up_near, "cells_moved_m": self.runner_up_moved},
            "warnings": self.warnings(),
        }


def cell_centres(occ: OccupancyMap, which: str) -> np.ndarray:
    """(K, 2) centres (m) of the map's known cells that are occupied or free by map_server's
    usual thresholds (those `io.rosmap.write_ros_map` writes): a map in memory is scored as the
    same map read back from its YAML would be."""
    lo = np.asarray(occ.log_odds)
    known = np.asarray(occ.known, dtype=bool)
    mask = known & ((lo > OCCUPIED_LOG_ODDS) if which == "occupied" else (lo < FREE_LOG_ODDS))
    rows, cols = np.nonzero(mask)
    return np.column_stack([occ.origin[0] + (cols + 0.5) * occ.resolution,
                            occ.origin[1] + (rows + 0.5) * occ.resolution])


def transform(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Points (N, 2) moved by the pose (x, y, theta): R(theta)·p + (x, y)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.column_stack([c * points[:, 0] - s * points[:, 1] + pose[0],
                            s * points[:, 0] + c * points[:, 1] + pose[1]])


def moved_by(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance (m) between the points moved by pose `a` and by pose `b`: how far apart
    two alignments are where it matters (a pose's translation alone depends on the origin)."""
    return float(np.mean(np.linalg.norm(transform(points, a) - transform(points, b), axis=1)))


@dataclass(frozen=True)
class _Reference:
    """The reference's occupied cells, their KD-tree, and per cell the normal of the wall it
    lies on (`on_wall`) where its WALL_NEIGHBOURS nearest cells spread along a line."""

    points: np.ndarray
    tree: cKDTree
    normals: np.ndarray
    on_wall: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray) -> "_Reference":
        tree = cKDTree(points)
        k = min(WALL_NEIGHBOURS, len(points))
        _, index = tree.query(points, k=k)
        near = points[index.reshape(len(points), k)]
        centred = near - near.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred) / k
        values, vectors = np.linalg.eigh(cov)  # ascending: the normal is the first vector
        on_wall = values[:, 0] < WALL_LINEARITY * values[:, 1]
        return cls(points, tree, vectors[:, :, 0], on_wall)


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
        initial: reference_T_estimate (x, y m, theta rad) to start ICP from ("initial"; "none"
            takes the identity).
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
    ref_points = cell_centres(reference, "occupied")
    for name, pts in (("the estimate", est), ("the reference", ref_points)):
        if len(pts) < MIN_CELLS:
            raise MapAgreementError(f"{name} has {len(pts)} occupied cells; at least {MIN_CELLS} are needed")
    ref = _Reference.of(ref_points)
    floor = 2.0 * max(estimate.resolution, reference.resolution)
    pairing = tuple(sorted({max(p, floor) for p in ICP_PAIRING}, reverse=True))
    fit = _Fit(np.zeros(3))
    runner_up: tuple[float, float] | None = None
    if align == "initial":
        fit = icp(est, ref, np.asarray(initial, dtype=np.float64), pairing)
    elif align == "search":
        fit, runner_up = search(est, ref, tolerance, pairing)
    pose = fit.pose
    moved = transform(est, pose)
    distance = ref.tree.query(moved)[0]
    seen_ref, covered = _coverage(estimate, moved, ref_points, pose, tolerance, reach)
    return MapAgreement(
        align=align, pose=(float(pose[0]), float(pose[1]), float(wrap_angle(pose[2]))),
        tolerance=tolerance, reach=reach, estimate_cells=len(est), reference_cells=len(ref_points),
        near=float(np.mean(distance <= tolerance)), mean_distance=float(np.mean(distance)),
        median_distance=float(np.median(distance)), p90_distance=float(np.percentile(distance, 90)),
        seen_reference_cells=seen_ref, covered=covered, constraint=fit.constraint, weakest=fit.weakest,
        runner_up_near=None if runner_up is None else runner_up[0],
        runner_up_moved=None if runner_up is None else runner_up[1],
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


@dataclass(frozen=True)
class _Fit:
    pose: np.ndarray
    constraint: float = math.nan
    weakest: tuple[float, float, float] | None = None


def icp(points: np.ndarray, ref: _Reference, pose: np.ndarray,
        pairings: tuple[float, ...] = ICP_PAIRING) -> _Fit:
    """reference_T_estimate refined from `pose` (module docstring), run to convergence at each
    pairing distance (m) in turn, with the conditioning of its last step."""
    pose = np.array(pose, dtype=np.float64)
    hessian, radius = None, 1.0
    for pairing in pairings:
        for _ in range(ICP_MAX_ITERATIONS):
            moved = transform(points, pose)
            d, index = ref.tree.query(moved, distance_upper_bound=pairing)
            paired = np.isfinite(d)
            if paired.sum() < MIN_CELLS:
                raise MapAgreementError(
                    f"the alignment pairs {int(paired.sum())} of the estimate's {len(points)} occupied cells with "
                    f"the reference's within {pairing:g} m: the maps do not overlap there (give a closer --initial)")
            step, hessian, radius = _gauss_newton(moved[paired], ref, index[paired])
            if step is None:  # the pairs fix no pose (all at one place)
                break
            # The step turns about the paired cells' centroid c: x -> R(dθ)(x - c) + c + dt.
            c, (dx, dy, dth) = moved[paired].mean(axis=0), step
            turned_c = transform(c[None, :], np.array([0.0, 0.0, dth]))[0]
            pose = compose(np.array([c[0] + dx - turned_c[0], c[1] + dy - turned_c[1], dth]), pose)
            if math.hypot(dx, dy) + abs(dth) * radius < ICP_CONVERGED:
                break
    if hessian is None:
        return _Fit(pose)
    scale = np.diag([1.0, 1.0, 1.0 / radius])  # the rotation as the cells' arc length
    values, vectors = np.linalg.eigh(scale @ hessian @ scale)
    constraint = float(values[0] / values[-1]) if values[-1] > 0 else 0.0
    return _Fit(pose, constraint, tuple(float(v) for v in vectors[:, 0]))


def _gauss_newton(moved: np.ndarray, ref: _Reference, index: np.ndarray):
    """One Gauss-Newton step (dx, dy, dθ about the cells' centroid) for the paired cells: the
    distance along the wall's normal where the reference cell lies on a wall, both coordinates
    elsewhere. Returns (step or None, the 3×3 normal matrix, the cells' RMS radius)."""
    c = moved.mean(axis=0)
    lever = moved - c
    radius = max(float(np.sqrt(np.mean(np.sum(lever**2, axis=1)))), 1e-9)
    delta = moved - ref.points[index]
    wall = ref.on_wall[index]
    n = ref.normals[index[wall]]
    # d(R(θ)u)/dθ at 0 is (-u_y, u_x).
    rows = [np.column_stack([n[:, 0], n[:, 1], n[:, 0] * -lever[wall, 1] + n[:, 1] * lever[wall, 0]])]
    residuals = [np.sum(n * delta[wall], axis=1)]
    other = ~wall
    k = int(other.sum())
    rows += [np.column_stack([np.ones(k), np.zeros(k), -lever[other, 1]]),
             np.column_stack([np.zeros(k), np.ones(k), lever[other, 0]])]
    residuals += [delta[other, 0], delta[other, 1]]
    jac, r = np.vstack(rows), np.concatenate(residuals)
    hessian = jac.T @ jac
    # Solved in the directions the pairs fix only: along a straight corridor the system is
    # singular, and a plain solve slid the estimate off the corridor's end (Zhang, Kaess & Singh,
    # "On degeneracy of optimization-based state estimation problems", ICRA 2016).
    scale = np.diag([1.0, 1.0, 1.0 / radius])
    values, vectors = np.linalg.eigh(scale @ hessian @ scale)
    if values[-1] <= 0.0:
        return None, hessian, radius
    fixed = values > DEGENERATE * values[-1]
    gradient = scale @ (jac.T @ r)
    step = -(vectors[:, fixed] @ ((vectors[:, fixed].T @ gradient) / values[fixed]))
    return scale @ step, hessian, radius


def search(points: np.ndarray, ref: _Reference, tolerance: float,
           pairings: tuple[float, ...] = ICP_PAIRING) -> tuple[_Fit, tuple[float, float] | None]:
    """reference_T_estimate from a global search over rotation and translation, then ICP; and
    the best candidate elsewhere (share of cells within tolerance, mean distance its pose moves
    the cells from the answer's), None where the search has no other."""
    centroid = points.mean(axis=0)
    centred = points - centroid
    radius = max(float(np.max(np.hypot(centred[:, 0], centred[:, 1]))), SEARCH_CELL)
    cell = max(SEARCH_CELL, radius / SEARCH_CELLS_ACROSS)
    # ICP's first pairing reaches past the search's own error (a cell and a half).
    pairings = tuple(sorted({max(pairings[0], 2.0 * cell), *pairings}, reverse=True))
    # The reference's walls, blurred: exp(-d²/2σ²) with σ one coarse cell.
    lo = ref.points.min(axis=0) - 3 * cell
    shape_ref = tuple((np.ceil((ref.points.max(axis=0) + 3 * cell - lo) / cell)).astype(int)[::-1])  # rows (y), cols (x)
    walls = np.zeros(shape_ref, dtype=bool)
    ij = np.floor((ref.points - lo) / cell).astype(int)
    walls[ij[:, 1], ij[:, 0]] = True
    blurred = np.exp(-0.5 * ndimage.distance_transform_edt(~walls) ** 2)
    # The estimate, turned about its centroid, always fits a square raster of side 2·radius.
    side = int(math.ceil(2 * radius / cell)) + 2
    shape = (sfft.next_fast_len(shape_ref[0] + side - 1), sfft.next_fast_len(shape_ref[1] + side - 1))
    # workers=-1: the transforms of rows and columns are independent, so the result does not
    # depend on the thread count.
    ref_spectrum = sfft.rfft2(blurred, s=shape, workers=-1)
    step = 0.5 * cell / radius  # the farthest cell moves half a coarse cell per step
    angles = np.arange(0.0, 2 * math.pi, step)
    best = np.empty((len(angles), 3))  # score, x, y of the best translation per rotation
    low = -radius - cell  # the estimate raster's lower-left corner, relative to the centroid
    for k, theta in enumerate(angles):
        turned = transform(centred, np.array([0.0, 0.0, theta]))
        ab = np.floor((turned - low) / cell).astype(int)
        raster = np.bincount(ab[:, 1] * side + ab[:, 0], minlength=side * side).reshape(side, side).astype(np.float64)
        score = sfft.irfft2(ref_spectrum * sfft.rfft2(raster[::-1, ::-1], s=shape, workers=-1), s=shape, workers=-1)
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
    few = points[np.unique(np.linspace(0, len(points) - 1, min(len(points), SEARCH_CELLS)).astype(int))]
    results = []
    for k in chosen:
        theta = float(angles[k])
        c, s = math.cos(theta), math.sin(theta)
        # p -> R(p - centroid) + t = R p + (t - R centroid)
        start = np.array([best[k, 1] - (c * centroid[0] - s * centroid[1]),
                          best[k, 2] - (s * centroid[0] + c * centroid[1]), theta])
        try:
            pose = icp(few, ref, start, pairings).pose
        except MapAgreementError:
            continue
        d = ref.tree.query(transform(few, pose))[0]
        results.append((float(np.mean(d <= tolerance)), -float(np.mean(np.minimum(d, 1.0))), pose))
    if not results:
        raise MapAgreementError("the search found no place where the estimate overlaps the reference")
    results.sort(key=lambda r: (r[0], r[1]), reverse=True)
    fit = icp(points, ref, results[0][2], pairings[-2:])
    # The best candidate elsewhere, scored on every cell as the answer is.
    for _, _, pose in results[1:]:
        apart = moved_by(points, pose, fit.pose)
        if apart > RUNNER_UP_APART * tolerance:
            d = ref.tree.query(transform(points, pose))[0]
            return fit, (float(np.mean(d <= tolerance)), apart)
    return fit, None
