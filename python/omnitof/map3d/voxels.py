"""3D occupancy along a trajectory: the paper's Fig. 11(b), a voxel grid of 0.1 m.

Every back-projected point of every frame is written, at the robot's SLAM pose, into a sparse
log-odds voxel grid (the Rust core's `VoxelGrid`, rust/src/voxel.rs): the voxels a ray passes
through from the mirror to its point get l_free, the voxel holding the point gets l_occ, and the
sum is clamped to [l_min, l_max] — the inverse sensor model of the 2D grid (paper eq. 8) in 3D.
Within one frame a voxel gets each kind of update at most once, and a voxel some ray ends in is
not freed by the frame's other rays; the result does not depend on the ray order or the thread
count.

Frames and units: metres and radians. World frame: x, y on the floor, z up. Robot frame: x
forward, z up, origin on the floor below the robot's centre. A 2D SLAM pose (x, y, θ) is
world_T_robot: a rotation by θ about z and a shift by (x, y); z is left as it is (the robot
drives on a flat floor). Voxel (i, j, k) covers [i·r, (i+1)·r) × [j·r, (j+1)·r) ×
[k·r, (k+1)·r) for resolution r; its centre is ((i, j, k) + ½)·r. Log-odds are float32, NaN
where unknown.

Georeferenced odometry (UTM: millions of metres) would put the voxels beyond the core's
indices (±2^20 per axis, rust/src/voxel.rs: 105 km at 0.1 m), so a map whose first frame lies
more than 2^14 voxels from (0, 0) (omnitof.slam.anchor.voxel_offset) keeps its voxels relative
to `offset`, that frame's (x, y) in whole 8-voxel blocks; every point going in or out is moved
by it.

Where the points come from: `backproject_frame` turns one frame's distance image into rays in
the robot frame (from the mirror point of each pixel to its measured surface point).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np

from omnitof import _core
from omnitof.sensor.camera import Camera
from omnitof.errors import ConfigError
from omnitof.sensor.mirrors import Mirror, MirrorPlane, mount_rotation
from omnitof.sim.worlds import World
from omnitof.sensor.tof import DEFAULT_F_MOD, unambiguous_range
from omnitof.slam.anchor import voxel_offset

DEFAULT_RESOLUTION = 0.1  # metres: the paper's Fig. 11(b) grid
# The same increments and limits as the 2D grid (omnitof.slam.config, MapConfig defaults).
DEFAULT_L_OCC = 0.9
DEFAULT_L_FREE = -0.4
DEFAULT_L_MIN = -2.0
DEFAULT_L_MAX = 3.5
# Rays are cut here: the default sensor's unambiguous range (20 MHz: 7.49 m); farther readings
# are wrapped and cannot be trusted.
DEFAULT_MAX_RANGE = unambiguous_range(DEFAULT_F_MOD)
DEFAULT_OCCUPIED_THRESHOLD = 0.0  # log-odds: occupied means p > 0.5


class Map3DError(ConfigError, ValueError):
    """A bad voxel map parameter or input array, named in the message."""


class IntegrateStats(NamedTuple):
    """What integrating one frame did: rays that ended on a surface, rays longer than max_range
    (freed up to it), rays skipped (non-finite), distinct voxels freed and marked occupied."""

    hits: int
    max_range: int
    skipped: int
    free_voxels: int
    occupied_voxels: int


class VoxelMap:
    """A sparse 3D log-odds occupancy grid in the world frame.

    Args:
        resolution: voxel edge, metres.
        l_occ, l_free: log-odds added to a ray's end voxel / to each voxel it passes through.
        l_min, l_max: clamps of a voxel's log-odds.
        max_range: rays longer than this (metres, from their origin) free the voxels up to it
            and mark nothing occupied.
        threads: worker threads of the core (None: rayon's global pool); results are the same
            for any number.
    """

    def __init__(
        self,
        resolution: float = DEFAULT_RESOLUTION,
        *,
        l_occ: float = DEFAULT_L_OCC,
        l_free: float = DEFAULT_L_FREE,
        l_min: float = DEFAULT_L_MIN,
        l_max: float = DEFAULT_L_MAX,
        max_range: float = DEFAULT_MAX_RANGE,
        threads: int | None = None,
    ) -> None:
        if not (math.isfinite(max_range) and max_range > 0.0):
            raise Map3DError(f"max_range must be a positive number of metres, got {max_range!r}")
        try:
            self._grid = _core.VoxelGrid(resolution, l_occ, l_free, l_min, l_max, threads)
        except ValueError as exc:
            raise Map3DError(str(exc)) from None
        self.max_range = float(max_range)
        self.frames = 0
        self.offset = np.zeros(3)  # world point of the grid's own origin (module notes)

    @classmethod
    def of_grid(cls, grid: "_core.VoxelGrid", max_range: float = DEFAULT_MAX_RANGE,
                offset: Sequence[float] = (0.0, 0.0)) -> "VoxelMap":
        """A VoxelMap around a core VoxelGrid made elsewhere (the 3D filter's best map,
        `_core.ParticleFilter3D.map`), whose voxels lie relative to the world point `offset`
        (x, y)."""
        vm = cls.__new__(cls)
        vm._grid, vm.max_range, vm.frames = grid, float(max_range), 0
        vm.offset = np.array([float(offset[0]), float(offset[1]), 0.0])
        return vm

    @property
    def resolution(self) -> float:
        return self._grid.resolution

    def integrate_world(self, origins: np.ndarray, endpoints: np.ndarray) -> IntegrateStats:
        """Integrate one frame of rays given in the world frame: origins and end points (N, 3)."""
        o = _points(origins, "origins")
        e = _points(endpoints, "endpoints")
        if o.shape != e.shape:
            raise Map3DError(f"origins {o.shape} and endpoints {e.shape} differ in shape")
        if self.frames == 0 and self._grid.voxel_count() == 0:
            self.offset[:2] = voxel_offset(o[:, :2], self.resolution)
        try:
            stats = IntegrateStats(*self._grid.integrate(o - self.offset, e - self.offset, self.max_range))
        except ValueError as exc:
            raise Map3DError(str(exc)) from None
        self.frames += 1
        return stats

    def integrate_frame(
        self, pose: np.ndarray, origins_robot: np.ndarray, points_robot: np.ndarray
    ) -> IntegrateStats:
        """Integrate one frame of rays given in the robot frame (N, 3) at the 2D pose
        world_T_robot = (x, y, θ)."""
        world_T = _pose_transform(pose)
        return self.integrate_world(
            transform_points(world_T, _points(origins_robot, "origins_robot")),
            transform_points(world_T, _points(points_robot, "points_robot")),
        )

    def occupied(self, threshold: float = DEFAULT_OCCUPIED_THRESHOLD) -> np.ndarray:
        """(M, 3) centres (metres) of the voxels whose log-odds exceed `threshold`, sorted by
        voxel index (i, j, k)."""
        return self._grid.occupied(float(threshold)) + self.offset

    def observed(self) -> tuple[np.ndarray, np.ndarray]:
        """(indices (K, 3) int64, log-odds (K,) float32) of every observed voxel, sorted; the
        indices count from `offset` (module notes)."""
        return self._grid.observed()

    def log_odds_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) log-odds of the voxels holding world points (N, 3); NaN where unknown."""
        return self._grid.log_odds_at(_points(points, "points") - self.offset)

    def voxel_count(self) -> int:
        """Observed (free, occupied or in between) voxels."""
        return self._grid.voxel_count()

    def memory_bytes(self) -> int:
        """Heap bytes of the grid: 8³-voxel blocks of float32 and the hash table over them."""
        return self._grid.memory_bytes()

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(min corner (3,), max corner (3,)) metres of the observed voxels; None if empty."""
        b = self._grid.bounds()
        return None if b is None else (np.array(b[0]) + self.offset, np.array(b[1]) + self.offset)


def build_voxel_map(
    poses: Iterable[np.ndarray],
    frames: Iterable[tuple[np.ndarray, np.ndarray]],
    voxel_map: VoxelMap | None = None,
) -> VoxelMap:
    """Integrate frames (origins_robot (N, 3), points_robot (N, 3)) at poses (x, y, θ), pair by
    pair, into `voxel_map` (default: a new VoxelMap()) and return it. Both iterables must have
    the same length; they are consumed lazily, one frame at a time."""
    vm = VoxelMap() if voxel_map is None else voxel_map
    poses_it, frames_it = iter(poses), iter(frames)
    count = 0
    for pose in poses_it:
        try:
            origins, points = next(frames_it)
        except StopIteration:
            raise Map3DError(f"{count} frames for more poses") from None
        vm.integrate_frame(pose, origins, points)
        count += 1
    if next(frames_it, None) is not None:
        raise Map3DError(f"more frames than the {count} poses")
    return vm


# --- back-projection -----------------------------------------------------------------------


def backproject_frame(
    distance: np.ndarray,
    camera: Camera,
    mirrors_or_planes: Sequence[Mirror] | Sequence[MirrorPlane],
    labels: np.ndarray,
    robot_T_camera: np.ndarray,
    *,
    valid: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rays of one frame in the robot frame: (origins (N, 3), points (N, 3)), metres.

    Each pixel with a mirror label (>= 0) looks along its central ray to the labelled mirror's
    plane, is reflected there and travels on; its distance (H, W) is the one-way path length
    from the camera centre via the mirror, so its surface point is o + (distance − |o|)·v with o
    the mirror point and v the reflected unit direction (camera frame), then mapped by
    robot_T_camera (4×4). The ray's origin is o, mapped likewise: free space starts at the mirror.

    Pixels are kept where labels >= 0, the distance is finite and longer than |o|, and `valid`
    (H, W) bool, if given, is true (e.g. an amplitude filter).
    """
    h, w = camera.shape
    dist = np.asarray(distance, dtype=np.float64)
    lab = np.asarray(labels)
    for name, arr in (("distance", dist), ("labels", lab)):
        if arr.shape != (h, w):
            raise Map3DError(f"{name} must have the camera's shape {(h, w)}, got {arr.shape}")
    planes = [m.plane if isinstance(m, Mirror) else m for m in mirrors_or_planes]
    rays = camera.pixel_grid_rays().reshape(-1, 3)
    flat_labels = lab.reshape(-1)
    flat_dist = dist.reshape(-1)
    keep = (flat_labels >= 0) & np.isfinite(flat_dist)
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (h, w):
            raise Map3DError(f"valid must have the camera's shape {(h, w)}, got {valid.shape}")
        keep &= valid.reshape(-1)
    origins = np.full((h * w, 3), np.nan)
    directions = np.full((h * w, 3), np.nan)
    for index, plane in enumerate(planes):
        sel = keep & (flat_labels == index)
        if np.any(sel):
            hits = plane.intersect(np.zeros((int(sel.sum()), 3)), rays[sel])
            origins[sel] = hits.points
            directions[sel] = hits.directions
    reach = flat_dist - np.linalg.norm(origins, axis=1)
    with np.errstate(invalid="ignore"):
        keep &= np.isfinite(reach) & (reach > 0.0)
    o = origins[keep]
    p = o + reach[keep, None] * directions[keep]
    mount = np.asarray(robot_T_camera, dtype=np.float64)
    rotation = mount_rotation(mount)
    shift = mount[:3, 3]
    return o @ rotation.T + shift, p @ rotation.T + shift


def voxel_map_from_clouds(poses: np.ndarray, clouds: list[np.ndarray], **options: float) -> VoxelMap:
    """A VoxelMap (options: its constructor's) from kept clouds (`scan.ToFScans.clouds`, (M, 6)
    origin and end point per ray, robot frame) at their frames' poses (K, 3)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(poses) != len(clouds):
        raise Map3DError(f"{len(poses)} poses for {len(clouds)} clouds")
    rays = ((c[:, :3].astype(np.float64), c[:, 3:].astype(np.float64)) for c in clouds)
    return build_voxel_map(poses, rays, VoxelMap(**options))


# --- ground truth of simulated worlds --------------------------------------------------------


def surface_distance(points: np.ndarray, world: World) -> np.ndarray:
    """(N,) distance (metres) from world points (N, 3) to the nearest surface of a simulated
    world: its wall quads, its boxes (their surface, from inside or out), the floor (z = 0)
    and the ceiling — the ground truth that a 3D map of a simulated run is measured against."""
    pts = _points(points, "points")
    d = np.minimum(np.abs(pts[:, 2]), np.abs(pts[:, 2] - world.ceiling_height))
    for quad in world.quads:
        a, b = quad[0:2], quad[2:4]
        ab = b - a
        t = np.clip((pts[:, :2] - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0)
        horizontal = np.linalg.norm(pts[:, :2] - (a + t[:, None] * ab), axis=1)
        vertical = np.maximum(np.maximum(quad[4] - pts[:, 2], pts[:, 2] - quad[5]), 0.0)
        d = np.minimum(d, np.hypot(horizontal, vertical))
    for cx, cy, sx, sy, yaw, bottom, top in world.boxes:
        c, s = math.cos(yaw), math.sin(yaw)
        rel = pts[:, :2] - (cx, cy)
        q = np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                             pts[:, 2] - 0.5 * (bottom + top)])
        half = np.array([0.5 * sx, 0.5 * sy, 0.5 * (top - bottom)])
        outside = np.linalg.norm(np.maximum(np.abs(q) - half, 0.0), axis=1)
        inside = np.min(half - np.abs(q), axis=1)
        d = np.minimum(d, np.where(outside > 0.0, outside, inside))
    return d


# --- helpers --------------------------------------------------------------------------------


def transform_points(a_T_b: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) in frame b mapped by the 4×4 transform a_T_b to frame a."""
    return points @ a_T_b[:3, :3].T + a_T_b[:3, 3]


def _pose_transform(pose: np.ndarray) -> np.ndarray:
    """world_T_robot (4×4) of a 2D pose (x, y, θ): rotation θ about z, shift (x, y, 0)."""
    p = np.asarray(pose, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise Map3DError(f"pose must be 3 finite numbers (x, y, θ), got {pose!r}")
    c, s = math.cos(p[2]), math.sin(p[2])
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = p[:2]
    return out


def _points(array: np.ndarray, name: str) -> np.ndarray:
    pts = np.ascontiguousarray(array, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise Map3DError(f"{name} must have shape (N, 3), got {pts.shape}")
    return pts

