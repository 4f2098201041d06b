"""Joint refinement of the whole calibration: intrinsics, distortion, every mirror plane and
every target pose, over all images at once (issue 16).

The closed-form chain (`intrinsics`, then `mirror_planes` with the intrinsics held fixed, paper
sec. II-C) leaves each step's error in the next: the principal point's error turns the mirror
normals. The paper notes that a final bundle adjustment cannot help *its* data, because the
mirrors share no constraint. Two kinds of measurement do tie them, and this module uses both:

1. the ToF camera measures each pixel's path length (camera → mirror → surface, one way). A
   card of known pose predicts it exactly: the distance along the pixel's ray to the card's plane,
   or, through a mirror {n·x = d}, to the card's plane reflected in the mirror (the path through
   the mirror equals the distance to the mirror image). This pins the plane distances d metrically
   and ties the intrinsics (the ray of every card pixel) to the boards' poses;
2. a flat board seen through two neighbouring mirrors at once (`targets.pair_board_poses`): one
   plane, measured along the rays of both mirrors, so the mirrors' relative pose is fixed.

Residuals (each divided by its kind's noise level, re-estimated from the fit):
- checkerboard corners, seen directly: reprojection error (pixels);
- the four dots, seen directly and through their mirror: reprojection error of the dot target's
  model at its pose, the mirrored dots through the mirror's reflection (eq. 5–6);
- ToF path lengths of card pixels (boards, dot cards, both views, two-mirror boards):
  predicted − measured (metres), weighted by the pixel's amplitude (shot noise: σ ∝ 1/amplitude).

Solver: Levenberg–Marquardt on the normal equations with a Huber loss at 3σ (iteratively
reweighted), the Jacobian by finite differences grouped over its sparsity pattern (a residual
depends on the camera, its view's pose and at most one mirror, so all views' j-th pose columns
are perturbed together; Curtis, Powell and Reid). `scipy.optimize.least_squares` was the first
choice; see `_solve` for why it is not used. Parameter standard deviations: (JᵀWJ)⁻¹ scaled by
the residual variance at the solution.

Parameters: fx, fy, cx, cy, k1, k2, p1, p2 (k3 is kept as given, as `calibrate_intrinsics` does);
per mirror a normal (two angles in the tangent plane of the start) and d; per board or dot card a
pose (rotation vector applied to the start, translation); per two-mirror board its plane (two
angles and its distance from the camera centre).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from threadpoolctl import threadpool_limits

from omnitof.calibration import CalibrationError
from omnitof.calibration.intrinsics import MIN_OUTLIER_PX
from omnitof.sensor.camera import Camera
from omnitof.sensor.mirrors import MirrorPlane

CAMERA_FIELDS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
# Newton steps of the undistortion (vectorised; a fixed count keeps the residuals smooth for
# finite differences): 8 steps bring every pixel of the wide SR4000 lens to Camera.rays
# within 1e-12 rad.
UNDISTORT_STEPS = 8
# Boards must be tilted from facing the camera by at least this much (some of them): with every
# board fronto-parallel the focal length trades off against the boards' distances.
MIN_BOARD_TILT_DEG = 10.0
MIN_BOARDS = 3
# The Huber loss's knee, in units of each kind's noise level.
HUBER_SIGMAS = 3.0
# Rounds of (fit, re-estimate each kind's noise level).
ROUNDS = 2
# At most this many times views are left out as outliers and the fit repeated (`refine`).
REJECTION_ROUNDS = 2
# A view is an outlier above this many times its kind's median RMS reprojection error. Not the
# intrinsics step's 3: the fit from a closed-form start can stop short in a view (3× the median
# in 1 of 12 synthetic draws, tests/test_refine.py), while a slipped detection is 100× or more.
OUTLIER_FACTOR = 10.0
# Vertices of the polygon that stands for a disc's outline (`polygon_centroids`).
DISC_VERTICES = 24


@dataclass
class ToFSamples:
    """Path lengths measured at pixels of one card: pixels (N, 2) (u, v), ranges (N,) metres,
    weights (N,) (relative 1/σ, e.g. amplitude / median amplitude), mirror: the mirror the
    pixels look through (−1: directly)."""

    pixels: np.ndarray
    ranges: np.ndarray
    weights: np.ndarray
    mirror: int = -1


@dataclass
class PosedView:
    """A target of known shape at an unknown pose: a checkerboard (points: its corners, all
    direct) or the dot target (its four dots seen directly and through `mirror`).

    points (K, 3): model points in the target frame; pixels (K, 2): where they were seen;
    via (K,) int: −1 seen directly, else the mirror index; pose (4×4): camera_T_target start;
    tof: ToF samples on the card. radius (metres): the points are the centres of printed discs
    of this radius, seen as their image's centroid (`polygon_centroids`); 0: points (corners).
    """

    name: str
    kind: str  # "board" or "dots"
    points: np.ndarray
    pixels: np.ndarray
    via: np.ndarray
    pose: np.ndarray
    tof: list[ToFSamples] = field(default_factory=list)
    radius: float = 0.0


@dataclass
class PlaneView:
    """A flat board seen through two (or more) mirrors: only its path lengths.
    plane: start (normal (3,), c) with normal·x = c in the camera frame."""

    name: str
    normal: np.ndarray
    c: float
    tof: list[ToFSamples] = field(default_factory=list)


@dataclass
class Problem:
    """Everything the refinement fits: the start values and the observations."""

    camera: Camera
    planes: list[MirrorPlane]
    names: list[str]
    views: list[PosedView]
    plane_views: list[PlaneView] = field(default_factory=list)


@dataclass
class Refinement:
    """The result of `refine`.

    camera, planes: the refined intrinsics and mirrors. std: standard deviations (camera fields;
    per mirror: the normal's two tangent angles in degrees, `normal_deg` their root sum of
    squares, `d_mm`). covariance: of the parameter vector (layout in `layout`). sigma: the noise
    level of each residual kind (pixels; path lengths in mm). per_view / per_mirror: RMS
    residuals (pixels, mm). iterations, cost: of the last round.
    """

    camera: Camera
    planes: list[MirrorPlane]
    names: list[str]
    std: dict[str, Any]
    covariance: np.ndarray
    layout: dict[str, Any]
    sigma: dict[str, float]
    per_view: dict[str, dict[str, float]]
    per_mirror: dict[str, dict[str, float]]
    iterations: int
    cost: float
    tangents: list[np.ndarray]
    # Views left out as outliers (`refine`): name → its RMS reprojection error (px).
    rejected: dict[str, float] = field(default_factory=dict)

    def quality(self) -> dict[str, Any]:
        """What a calibration file keeps of it (`quality.refinement`)."""
        return {
            "std": self.std,
            "noise": {k: round(v, 5) for k, v in self.sigma.items()},
            "per_view": self.per_view,
            "per_mirror": self.per_mirror,
            "iterations": self.iterations,
            "rejected": {name: round(rms, 4) for name, rms in self.rejected.items()},
        }


# --- the camera model, vectorised over parameters as a vector ------------------------------


def _camera_vector(camera: Camera) -> np.ndarray:
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist[:4]], dtype=np.float64)


def _camera_from(vector: np.ndarray, base: Camera) -> Camera:
    fx, fy, cx, cy, k1, k2, p1, p2 = (float(v) for v in vector)
    return Camera(base.width, base.height, fx, fy, cx, cy, (k1, k2, p1, p2, base.dist[4]))


def _distort(cam: np.ndarray, k3: float, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k1, k2, p1, p2 = cam[4:8]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


def project(cam: np.ndarray, k3: float, points: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of camera-frame points (N, 3) for the camera vector (fx..p2)."""
    x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    xd, yd = _distort(cam, k3, x, y)
    return np.stack([cam[0] * xd + cam[2], cam[1] * yd + cam[3]], axis=1)


def rays(cam: np.ndarray, k3: float, pixels: np.ndarray) -> np.ndarray:
    """Unit rays (N, 3) of pixels (N, 2): the distortion inverted by Newton steps (vectorised,
    the 2×2 Jacobian of the distortion in closed form)."""
    xd = (pixels[:, 0] - cam[2]) / cam[0]
    yd = (pixels[:, 1] - cam[3]) / cam[1]
    k1, k2, p1, p2 = cam[4:8]
    x, y = xd.copy(), yd.copy()
    for _ in range(UNDISTORT_STEPS):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))  # ∂radial/∂x = dradial·x
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        a = radial + dradial * x * x + 2.0 * p1 * y + 6.0 * p2 * x
        b = dradial * x * y + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + dradial * y * y + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * b
        x = x - (d * fx - b * fy) / det
        y = y - (a * fy - b * fx) / det
    out = np.stack([x, y, np.ones_like(x)], axis=1)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _reflect(points: np.ndarray, normal: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Points (..., 3) reflected in the planes normal·x = d (eq. 6's D), broadcast over the
    leading axes."""
    return points - 2.0 * (np.sum(points * normal, axis=-1) - d)[..., None] * normal


def polygon_centroids(vertices: np.ndarray) -> np.ndarray:
    """Area centroids (N, 2) of N polygons (N, V, 2) (shoelace formula).

    A printed dot's image is not centred on its centre's image: perspective and the lens
    distortion stretch the far side. The detector measures the image's darkness-weighted
    centroid, so the model predicts that (the outline's polygon at DISC_VERTICES vertices), not
    the projected centre: on simulated dot targets this takes the model error of the dots from
    0.046–0.057 px RMS to 0.032–0.035 px (the rest is the detector's own).
    """
    x, y = vertices[..., 0], vertices[..., 1]
    x1, y1 = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    cross = x * y1 - x1 * y
    area = cross.sum(axis=-1) / 2.0
    cx = ((x + x1) * cross).sum(axis=-1) / (6.0 * area)
    cy = ((y + y1) * cross).sum(axis=-1) / (6.0 * area)
    return np.stack([cx, cy], axis=-1)


def rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (V, 3, 3) of rotation vectors (V, 3)."""
    theta = np.linalg.norm(w, axis=1)
    k = w / np.where(theta > 0, theta, 1.0)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def tangent_basis(n: np.ndarray) -> np.ndarray:
    """(2, 3): two unit vectors orthogonal to the unit vector n and to each other."""
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1)
    return np.stack([t1, np.cross(n, t1)])


# --- the problem as residuals -------------------------------------------------------------


class _Model:
    """The parameter layout, the stacked observations and the residual function."""

    def __init__(self, problem: Problem) -> None:
        self.problem = problem
        self.k3 = float(problem.camera.dist[4])
        m, v, p = len(problem.planes), len(problem.views), len(problem.plane_views)
        self.n_mirrors, self.n_views, self.n_planes = m, v, p
        self.i_mirror = 8
        self.i_view = 8 + 3 * m
        self.i_plane = self.i_view + 6 * v
        self.size = self.i_plane + 3 * p
        self.normals0 = np.array([pl.normal for pl in problem.planes])
        self.tangents = [tangent_basis(n) for n in self.normals0]
        self.d0 = np.array([pl.d for pl in problem.planes])
        self.R0 = np.array([view.pose[:3, :3] for view in problem.views]).reshape(v, 3, 3)
        self.t0 = np.array([view.pose[:3, 3] for view in problem.views]).reshape(v, 3)
        self.pn0 = np.array([pv.normal for pv in problem.plane_views]).reshape(p, 3)
        self.pt = [tangent_basis(n) for n in self.pn0]
        self.pc0 = np.array([pv.c for pv in problem.plane_views], dtype=np.float64)
        # Point observations: view, model point, pixel, mirror.
        owners, pts, pix, via = [], [], [], []
        for i, view in enumerate(problem.views):
            owners.append(np.full(len(view.points), i))
            pts.append(view.points)
            pix.append(view.pixels)
            via.append(view.via)
        self.pt_owner = np.concatenate(owners).astype(int) if owners else np.zeros(0, int)
        self.pt_model = np.vstack(pts) if pts else np.zeros((0, 3))
        self.pt_pixel = np.vstack(pix) if pix else np.zeros((0, 2))
        self.pt_via = np.concatenate(via).astype(int) if via else np.zeros(0, int)
        self.pt_kind = np.concatenate(
            [np.full(len(view.points), 0 if view.kind == "board" else 1) for view in problem.views]
        ) if problem.views else np.zeros(0, int)
        self.pt_radius = np.concatenate(
            [np.full(len(view.points), float(view.radius)) for view in problem.views]
        ) if problem.views else np.zeros(0)
        # Discs: their outlines in the target frame (the card is the frame's z = 0 plane).
        self.discs = np.flatnonzero(self.pt_radius > 0.0)
        angle = np.linspace(0.0, 2.0 * math.pi, DISC_VERTICES, endpoint=False)
        ring = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
        self.disc_outline = (self.pt_model[self.discs, None, :]
                             + self.pt_radius[self.discs, None, None] * ring[None, :, :])
        # ToF samples: source (view index, or n_views + plane index), pixel, range, weight, mirror.
        src, tpix, rng, wts, mir = [], [], [], [], []
        for i, view in enumerate(problem.views):
            for s in view.tof:
                src.append(np.full(len(s.ranges), i))
                tpix.append(s.pixels), rng.append(s.ranges), wts.append(s.weights)
                mir.append(np.full(len(s.ranges), s.mirror))
        for j, pv in enumerate(problem.plane_views):
            for s in pv.tof:
                src.append(np.full(len(s.ranges), v + j))
                tpix.append(s.pixels), rng.append(s.ranges), wts.append(s.weights)
                mir.append(np.full(len(s.ranges), s.mirror))
        self.tof_src = np.concatenate(src).astype(int) if src else np.zeros(0, int)
        self.tof_pixel = np.vstack(tpix) if tpix else np.zeros((0, 2))
        self.tof_range = np.concatenate(rng) if rng else np.zeros(0)
        self.tof_weight = np.concatenate(wts) if wts else np.zeros(0)
        self.tof_mirror = np.concatenate(mir).astype(int) if mir else np.zeros(0, int)
        self.n_points = len(self.pt_owner)
        self.n_tof = len(self.tof_src)
        # Noise levels per kind: corners (px), dots (px), path lengths (m); refined in rounds.
        self.sigma = np.array([0.1, 0.1, 0.005])
        self._ray_cache: tuple[np.ndarray, np.ndarray] | None = None

    def start(self) -> np.ndarray:
        x = np.zeros(self.size)
        x[:8] = _camera_vector(self.problem.camera)
        x[self.i_mirror + 2 : self.i_view : 3] = self.d0
        x[self.i_plane + 2 :: 3] = self.pc0
        return x

    def unpack(self, x: np.ndarray):
        cam = x[:8]
        mp = x[self.i_mirror : self.i_view].reshape(-1, 3)
        normals = np.array([
            n0 + a * t[0] + b * t[1] for n0, t, (a, b, _) in zip(self.normals0, self.tangents, mp)
        ]).reshape(-1, 3)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        d = mp[:, 2] if len(mp) else np.zeros(0)
        vp = x[self.i_view : self.i_plane].reshape(-1, 6)
        R = rodrigues(vp[:, :3]) @ self.R0 if len(vp) else np.zeros((0, 3, 3))
        t = self.t0 + vp[:, 3:] if len(vp) else np.zeros((0, 3))
        pp = x[self.i_plane :].reshape(-1, 3)
        pn = np.array([
            n0 + a * tt[0] + b * tt[1] for n0, tt, (a, b, _) in zip(self.pn0, self.pt, pp)
        ]).reshape(-1, 3)
        if len(pn):
            pn /= np.linalg.norm(pn, axis=1, keepdims=True)
        pc = pp[:, 2] if len(pp) else np.zeros(0)
        return cam, normals, d, R, t, pn, pc

    def raw(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(point residuals (P, 2) in pixels, path-length residuals (T,) in metres)."""
        cam, normals, d, R, t, pn, pc = self.unpack(x)
        # Points: X = R·p + t, reflected in the mirror for mirrored views (eq. 6's D).
        X = np.einsum("nij,nj->ni", R[self.pt_owner], self.pt_model) + t[self.pt_owner]
        mirrored = self.pt_via >= 0
        if mirrored.any():
            n = normals[self.pt_via[mirrored]]
            dd = d[self.pt_via[mirrored]]
            X[mirrored] = _reflect(X[mirrored], n, dd)
        predicted_px = project(cam, self.k3, X)
        if len(self.discs):
            predicted_px[self.discs] = self._disc_centroids(cam, normals, d, R, t)
        point_res = predicted_px - self.pt_pixel
        # Path lengths: the distance along the pixel's ray to the card's plane (reflected).
        posed = self.tof_src < self.n_views
        plane_n = np.empty((self.n_tof, 3))
        plane_c = np.empty(self.n_tof)
        if posed.any():
            src = self.tof_src[posed]
            plane_n[posed] = R[src][:, :, 2]
            plane_c[posed] = np.sum(plane_n[posed] * t[src], axis=1)
        if (~posed).any():
            src = self.tof_src[~posed] - self.n_views
            plane_n[~posed] = pn[src]
            plane_c[~posed] = pc[src]
        via = self.tof_mirror >= 0
        if via.any():
            m_n, m_d = normals[self.tof_mirror[via]], d[self.tof_mirror[via]]
            nc = plane_n[via]
            dot = np.sum(nc * m_n, axis=1)
            plane_n[via] = nc - 2.0 * dot[:, None] * m_n
            plane_c[via] = plane_c[via] - 2.0 * m_d * dot
        r = self._rays(cam)
        predicted = plane_c / np.sum(plane_n * r, axis=1)
        return point_res, predicted - self.tof_range

    def _disc_centroids(self, cam, normals, d, R, t) -> np.ndarray:
        """Where the discs' images have their centroids (D, 2): the outlines moved to their
        views' poses, reflected for mirrored views, projected, and `polygon_centroids`."""
        owner = self.pt_owner[self.discs]
        X = np.einsum("nij,nkj->nki", R[owner], self.disc_outline) + t[owner][:, None, :]
        via = self.pt_via[self.discs]
        mirrored = via >= 0
        if mirrored.any():
            n, dd = normals[via[mirrored]], d[via[mirrored]]
            X[mirrored] = _reflect(X[mirrored], n[:, None, :], dd[:, None])
        outline_px = project(cam, self.k3, X.reshape(-1, 3)).reshape(len(owner), DISC_VERTICES, 2)
        return polygon_centroids(outline_px)

    def _rays(self, cam: np.ndarray) -> np.ndarray:
        # Only the camera's columns change the rays: the pose and mirror columns of the
        # Jacobian reuse them.
        if self._ray_cache is None or not np.array_equal(self._ray_cache[0], cam):
            self._ray_cache = (cam.copy(), rays(cam, self.k3, self.tof_pixel))
        return self._ray_cache[1]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        point_res, tof_res = self.raw(x)
        scale = self.sigma[self.pt_kind][:, None]
        return np.concatenate([(point_res / scale).ravel(), tof_res * self.tof_weight / self.sigma[2]])

    def sparsity(self) -> coo_matrix:
        """Which parameters each residual depends on: the camera, its view (pose or plane) and
        at most one mirror."""
        rows, cols = [], []

        def block(row_ids: np.ndarray, starts: np.ndarray, width: int) -> None:
            keep = starts >= 0
            r = np.repeat(row_ids[keep], width)
            c = (starts[keep][:, None] + np.arange(width)).ravel()
            rows.append(r), cols.append(c)

        n_rows = 2 * self.n_points + self.n_tof
        block(np.arange(n_rows), np.zeros(n_rows, dtype=int), 8)
        for offset in (0, 1):
            r = 2 * np.arange(self.n_points) + offset
            block(r, self.i_view + 6 * self.pt_owner, 6)
            block(r, np.where(self.pt_via >= 0, self.i_mirror + 3 * self.pt_via, -1), 3)
        r = 2 * self.n_points + np.arange(self.n_tof)
        posed = self.tof_src < self.n_views
        block(r, np.where(posed, self.i_view + 6 * self.tof_src, -1), 6)
        block(r, np.where(posed, -1, self.i_plane + 3 * (self.tof_src - self.n_views)), 3)
        block(r, np.where(self.tof_mirror >= 0, self.i_mirror + 3 * self.tof_mirror, -1), 3)
        rows_all, cols_all = np.concatenate(rows), np.concatenate(cols)
        return coo_matrix((np.ones(len(rows_all), dtype=np.int8), (rows_all, cols_all)),
                          shape=(n_rows, self.size)).tocsr()


# --- checks of what the data can determine ---------------------------------------------------


def check_problem(problem: Problem) -> None:
    """CalibrationError naming what is missing if the data cannot determine every parameter:
    too few boards, boards that all face the camera, a mirror that no dot target and no
    two-mirror board was seen in."""
    boards = [v for v in problem.views if v.kind == "board"]
    if len(boards) < MIN_BOARDS:
        raise CalibrationError(
            f"refinement: {len(boards)} checkerboard view(s), need at least {MIN_BOARDS} for the intrinsics"
        )
    tilts = []
    for view in boards:
        centre = view.pose[:3, :3] @ view.points.mean(axis=0) + view.pose[:3, 3]
        cos = abs(float(view.pose[:3, 2] @ centre)) / float(np.linalg.norm(centre))
        tilts.append(math.degrees(math.acos(min(1.0, cos))))
    if max(tilts) < MIN_BOARD_TILT_DEG:
        raise CalibrationError(
            f"refinement: all {len(boards)} checkerboards face the camera (largest tilt "
            f"{max(tilts):.1f}°, need some beyond {MIN_BOARD_TILT_DEG:g}°): the focal length is not "
            "determined; tilt the boards by 20–50°"
        )
    seen = np.zeros(len(problem.planes), dtype=bool)
    for view in problem.views:
        seen[view.via[view.via >= 0]] = True
    for pv in problem.plane_views:
        for s in pv.tof:
            if s.mirror >= 0:
                seen[s.mirror] = True
    missing = [problem.names[k] for k in np.flatnonzero(~seen)]
    if missing:
        raise CalibrationError(
            "refinement: mirror(s) " + ", ".join(repr(m) for m in missing) + " seen in no image "
            "(no dot target placed at them, no board seen through them): their planes are not "
            "determined; place the dot target at every mirror"
        )


# --- the solver -----------------------------------------------------------------------------


def refine(problem: Problem, *, max_nfev: int = 50) -> Refinement:
    """Fit every parameter to every observation at once (see the module docstring).

    Robust step, like `intrinsics.calibrate_intrinsics`'s: a view whose RMS reprojection error
    is far beyond its kind's (boards, dot cards: above OUTLIER_FACTOR × their median and above
    `intrinsics.MIN_OUTLIER_PX`) is a detection gone wrong (a checkerboard's corners
    misassigned, a dot taken for another); it is left out and the fit repeated, unless that
    would leave a parameter undetermined (then it stays). The Huber loss bounds such a view's
    pull but not its count of residuals, and its cost inflated the reported σ twofold.

    BLAS runs on one thread meanwhile: a multithreaded BLAS sums the products of the fit
    (JᵀWJ, Jᵀr and more) in an order that depends on the thread count, and the last-digit
    differences grew through the iterations into a calibration, and a demo map, that differed
    between one core and two.

    Raises:
        CalibrationError naming what is missing (`check_problem`, also after views are left
        out) or the parameter that the data leave undetermined.
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return _refine(problem, max_nfev)


def _refine(problem: Problem, max_nfev: int) -> Refinement:
    check_problem(problem)
    result = _fit(problem, max_nfev)
    rejected: dict[str, float] = {}
    for _ in range(REJECTION_ROUNDS):
        outliers = _outlying_views(problem, result.per_view)
        if not outliers:
            break
        reduced = replace(problem, views=[v for v in problem.views if v.name not in outliers])
        try:
            check_problem(reduced)
        except CalibrationError:
            break
        rejected.update(outliers)
        problem = reduced
        result = _fit(problem, max_nfev)
    result.rejected = rejected
    return result


def _outlying_views(problem: Problem, per_view: dict[str, dict[str, float]]) -> dict[str, float]:
    """{name: RMS px} of the views whose reprojection error is far beyond their kind's."""
    out: dict[str, float] = {}
    for kind in ("board", "dots"):
        names = [v.name for v in problem.views if v.kind == kind]
        if len(names) < 3:  # too few to say what is usual
            continue
        rms = np.array([max(per_view[n].get("direct_px", 0.0), per_view[n].get("mirrored_px", 0.0)) for n in names])
        limit = max(OUTLIER_FACTOR * float(np.median(rms)), MIN_OUTLIER_PX)
        out.update({n: float(r) for n, r in zip(names, rms) if r > limit})
    return out


def _fit(problem: Problem, max_nfev: int) -> Refinement:
    model = _Model(problem)
    x = model.start()
    sparsity = model.sparsity()
    result = None
    model.sigma = _noise_levels(model, x, model.sigma)
    for _ in range(ROUNDS):
        result = _solve(model, x, sparsity, max_nfev)
        x = result.x
        new = _noise_levels(model, x, model.sigma)
        if np.allclose(new, model.sigma, rtol=0.05):
            model.sigma = new
            break
        model.sigma = new
    assert result is not None
    # The last fit with the final noise levels, for the covariance: (JᵀWJ)⁻¹ times the
    # residual variance (≈ 1, as every residual is divided by its kind's noise level).
    result = _solve(model, x, sparsity, max_nfev)
    x = result.x
    variance = 2.0 * result.cost / result.dof
    covariance = _inverse(result.JtWJ, model, problem) * variance
    std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    cam, normals, d, R, t, pn, pc = model.unpack(x)
    camera = _camera_from(cam, problem.camera)
    planes = [MirrorPlane(n, float(dd)) for n, dd in zip(normals, d)]
    out_std: dict[str, Any] = {"camera": {f: float(s) for f, s in zip(CAMERA_FIELDS, std[:8])}, "mirrors": {}}
    for k, name in enumerate(problem.names):
        a, b, sd = std[model.i_mirror + 3 * k : model.i_mirror + 3 * k + 3]
        out_std["mirrors"][name] = {
            "normal_deg": float(math.degrees(math.hypot(a, b))),
            "tangent_deg": [float(math.degrees(a)), float(math.degrees(b))],
            "d_mm": float(1000.0 * sd),
        }
    per_view, per_mirror = _residual_tables(model, x, problem)
    return Refinement(
        camera, planes, list(problem.names), out_std, covariance,
        {"camera": 0, "mirrors": model.i_mirror, "views": model.i_view, "planes": model.i_plane},
        {"corner_px": float(model.sigma[0]), "dot_px": float(model.sigma[1]),
         "path_mm": float(1000.0 * model.sigma[2])},
        per_view, per_mirror, result.iterations, float(result.cost), model.tangents,
    )


@dataclass
class _Solution:
    x: np.ndarray
    JtWJ: np.ndarray
    cost: float
    dof: int
    iterations: int


def _huber_weights(r: np.ndarray) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= HUBER_SIGMAS, 1.0, HUBER_SIGMAS / np.maximum(a, 1e-300))


def _huber_cost(r: np.ndarray) -> float:
    a = np.abs(r)
    return float(np.sum(np.where(a <= HUBER_SIGMAS, 0.5 * a * a, HUBER_SIGMAS * (a - 0.5 * HUBER_SIGMAS))))


def _solve(model: _Model, x: np.ndarray, sparsity, max_iterations: int) -> _Solution:
    """Levenberg–Marquardt on the normal equations with Huber weights (iteratively reweighted
    least squares), the Jacobian by grouped finite differences over its sparsity pattern.

    Why not scipy's least_squares itself: with jac_sparsity it is forced onto LSMR steps,
    which on this problem (a few hundred parameters, ~20 000 residuals) stalled after 100
    evaluations far from the optimum; its exact steps take an SVD of the whole Jacobian (7 s
    here per iteration). JᵀWJ is a few hundred square, so each step costs ~0.3 s."""
    groups = _column_groups(model)
    csc = sparsity.tocsc()
    rows_of = [csc.indices[csc.indptr[c] : csc.indptr[c + 1]] for c in range(model.size)]
    r = model.residuals(x)
    cost = _huber_cost(r)
    lam = 1e-3
    iterations = 0
    JtWJ = np.eye(model.size)
    for iterations in range(1, max_iterations + 1):
        J = _jacobian(model, x, groups, rows_of, r)
        w = _huber_weights(r)
        JtWJ = J.T @ (J * w[:, None])
        g = J.T @ (w * r)
        diag = np.maximum(np.diag(JtWJ), 1e-12)
        improved = False
        while lam < 1e12:
            try:
                step = np.linalg.solve(JtWJ + lam * np.diag(diag), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            candidate = x + step
            r_new = model.residuals(candidate)
            cost_new = _huber_cost(r_new) if np.all(np.isfinite(r_new)) else math.inf
            if cost_new < cost:
                improved = True
                converged = (cost - cost_new) < 1e-10 * cost or np.all(np.abs(step) <= 1e-10 * (1.0 + np.abs(x)))
                x, r, cost = candidate, r_new, cost_new
                lam = max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
        if not improved or converged:
            break
    J = _jacobian(model, x, groups, rows_of, r)
    w = _huber_weights(r)
    JtWJ = J.T @ (J * w[:, None])
    return _Solution(x, JtWJ, cost, max(1, len(r) - model.size), iterations)


def _column_groups(model: _Model) -> list[np.ndarray]:
    """Columns that share no residual, perturbed together (Curtis, Powell and Reid): each camera
    and mirror column alone; the j-th pose column of every view (and the j-th plane column of
    every two-mirror board) together."""
    groups = [np.array([c]) for c in range(model.i_view)]
    for j in range(6):
        cols = list(model.i_view + 6 * np.arange(model.n_views) + j)
        if j < 3:
            cols += list(model.i_plane + 3 * np.arange(model.n_planes) + j)
        if cols:
            groups.append(np.array(cols, dtype=int))
    return groups


def _jacobian(model: _Model, x: np.ndarray, groups: list[np.ndarray], rows_of: list[np.ndarray],
              f0: np.ndarray) -> np.ndarray:
    J = np.zeros((len(f0), model.size))
    for cols in groups:
        step = 1e-7 * np.maximum(1.0, np.abs(x[cols]))
        y = x.copy()
        y[cols] += step
        df = model.residuals(y) - f0
        for c, h in zip(cols, step):
            rows = rows_of[c]
            J[rows, c] = df[rows] / h
    return J


def _noise_levels(model: _Model, x: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """Robust noise level (1.4826 × median absolute residual) of each residual kind."""
    point_res, tof_res = model.raw(x)
    norms = np.abs(point_res).ravel()
    kinds = np.repeat(model.pt_kind, 2)
    new = previous.copy()
    for k in (0, 1):
        if np.any(kinds == k):
            new[k] = max(1.4826 * float(np.median(norms[kinds == k])), 1e-4)
    if model.n_tof:
        new[2] = max(1.4826 * float(np.median(np.abs(tof_res * model.tof_weight))), 1e-5)
    return new


def _inverse(JtJ: np.ndarray, model: _Model, problem: Problem) -> np.ndarray:
    """(JᵀJ)⁻¹, or CalibrationError naming a parameter the data do not determine."""
    scale = np.sqrt(np.clip(np.diag(JtJ), 1e-300, None))
    normalised = JtJ / scale[:, None] / scale[None, :]
    w, vecs = np.linalg.eigh(normalised)
    if w[0] < 1e-12 * w[-1]:
        weakest = int(np.argmax(np.abs(vecs[:, 0])))
        raise CalibrationError(f"refinement: the data do not determine {_parameter_name(weakest, model, problem)}")
    inv = (vecs / w) @ vecs.T
    return inv / scale[:, None] / scale[None, :]


def _parameter_name(i: int, model: _Model, problem: Problem) -> str:
    if i < 8:
        return f"the camera's {CAMERA_FIELDS[i]}"
    if i < model.i_view:
        k, part = divmod(i - model.i_mirror, 3)
        return f"mirror {problem.names[k]!r}'s " + ("plane distance" if part == 2 else "normal")
    if i < model.i_plane:
        return f"the pose of {problem.views[(i - model.i_view) // 6].name}"
    return f"the plane of {problem.plane_views[(i - model.i_plane) // 3].name}"


def _residual_tables(model: _Model, x: np.ndarray, problem: Problem):
    """RMS residuals per view and per mirror (pixels; path lengths in mm)."""
    point_res, tof_res = model.raw(x)
    per_view: dict[str, dict[str, float]] = {}
    point_norm = np.linalg.norm(point_res, axis=1)
    for i, view in enumerate(problem.views):
        entry = {}
        for label, sel in (("direct_px", (model.pt_owner == i) & (model.pt_via < 0)),
                           ("mirrored_px", (model.pt_owner == i) & (model.pt_via >= 0))):
            if sel.any():
                entry[label] = round(float(np.sqrt(np.mean(point_norm[sel] ** 2))), 4)
        sel = model.tof_src == i
        if sel.any():
            entry["path_mm"] = round(1000.0 * float(np.median(np.abs(tof_res[sel]))), 3)
        per_view[view.name] = entry
    for j, pv in enumerate(problem.plane_views):
        sel = model.tof_src == model.n_views + j
        per_view[pv.name] = {"path_mm": round(1000.0 * float(np.median(np.abs(tof_res[sel]))), 3)} if sel.any() else {}
    per_mirror: dict[str, dict[str, float]] = {}
    for k, name in enumerate(problem.names):
        entry = {}
        sel = model.pt_via == k
        if sel.any():
            entry["dot_px"] = round(float(np.sqrt(np.mean(point_norm[sel] ** 2))), 4)
        sel = model.tof_mirror == k
        if sel.any():
            entry["path_mm"] = round(1000.0 * float(np.median(np.abs(tof_res[sel]))), 3)
            entry["path_bias_mm"] = round(1000.0 * float(np.median(tof_res[sel])), 3)
        per_mirror[name] = entry
    return per_view, per_mirror


def mirror_errors(refinement: Refinement, truth: Sequence[MirrorPlane]) -> list[dict[str, float]]:
    """Per mirror, the true error in the refinement's own coordinates, for coverage checks:
    the two tangent-angle components (radians) and d (metres)."""
    out = []
    for plane, true, t in zip(refinement.planes, truth, refinement.tangents):
        diff = true.normal - plane.normal
        out.append({"a": float(diff @ t[0]), "b": float(diff @ t[1]), "d": float(true.d - plane.d)})
    return out
