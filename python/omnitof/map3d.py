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

Where the points come from: `backproject_frame` turns one frame's distance image into rays in
the robot frame (from the mirror point of each pixel to its measured surface point).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from omnitof import _core
from omnitof.camera import Camera
from omnitof.errors import ConfigError, InputError
from omnitof.io.atomic import atomic_write
from omnitof.mirrors import Mirror, MirrorPlane, mount_rotation
from omnitof.sim.worlds import World
from omnitof.tof import DEFAULT_F_MOD, unambiguous_range

DEFAULT_RESOLUTION = 0.1  # metres: the paper's Fig. 11(b) grid
# The same increments and limits as the 2D grid (omnitof.config, MapConfig defaults).
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

    @property
    def resolution(self) -> float:
        return self._grid.resolution

    def integrate_world(self, origins: np.ndarray, endpoints: np.ndarray) -> IntegrateStats:
        """Integrate one frame of rays given in the world frame: origins and end points (N, 3)."""
        o = _points(origins, "origins")
        e = _points(endpoints, "endpoints")
        if o.shape != e.shape:
            raise Map3DError(f"origins {o.shape} and endpoints {e.shape} differ in shape")
        try:
            stats = IntegrateStats(*self._grid.integrate(o, e, self.max_range))
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
        return self._grid.occupied(float(threshold))

    def observed(self) -> tuple[np.ndarray, np.ndarray]:
        """(indices (K, 3) int64, log-odds (K,) float32) of every observed voxel, sorted."""
        return self._grid.observed()

    def log_odds_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) log-odds of the voxels holding world points (N, 3); NaN where unknown."""
        return self._grid.log_odds_at(_points(points, "points"))

    def voxel_count(self) -> int:
        """Observed (free, occupied or in between) voxels."""
        return self._grid.voxel_count()

    def memory_bytes(self) -> int:
        """Heap bytes of the grid: 8³-voxel blocks of float32 and the hash table over them."""
        return self._grid.memory_bytes()

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(min corner (3,), max corner (3,)) metres of the observed voxels; None if empty."""
        b = self._grid.bounds()
        return None if b is None else (np.array(b[0]), np.array(b[1]))


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


# --- PLY ------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def write_ply(
    path: str | Path,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    *,
    binary: bool = True,
    comment: str = "omnitof occupied voxel centres, metres, world frame (z up)",
) -> None:
    """Write points (N, 3) (and colours (N, 3) uint8 RGB) as a PLY vertex cloud, atomically.

    Format: PLY 1.0, `binary_little_endian` (default) or `ascii`; one `vertex` element with
    float (float32) x, y, z and, with colours, uchar red, green, blue — what MeshLab,
    CloudCompare, Open3D and Blender read.
    """
    pts = _points(points, "points")
    cols = None
    if colors is not None:
        cols = np.asarray(colors)
        if cols.shape != pts.shape:
            raise Map3DError(f"colors must have shape {pts.shape}, got {cols.shape}")
        if cols.dtype != np.uint8:
            raise Map3DError(f"colors must be uint8 RGB, got {cols.dtype}")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if cols is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rows = np.empty(len(pts), dtype=fields)
    for a, name in enumerate("xyz"):
        rows[name] = pts[:, a]
    if cols is not None:
        for a, name in enumerate(("red", "green", "blue")):
            rows[name] = cols[:, a]
    header = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        *(f"comment {line}" for line in comment.splitlines()),
        f"element vertex {len(pts)}",
        "property float x",
        "property float y",
        "property float z",
    ]
    if cols is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    with atomic_write(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            handle.write(rows.tobytes())
        else:
            # %.9g: enough digits to give back every float32 exactly.
            table = np.column_stack([rows[n].astype(np.float64) for n in rows.dtype.names or ()])
            fmt = " ".join(["%.9g"] * 3 + (["%d"] * 3 if cols is not None else []))
            if len(table):
                np.savetxt(handle, table, fmt=fmt, newline="\n")


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY vertex cloud (ascii or binary_little_endian, scalar vertex properties, no
    other elements): (points (N, 3) float64, colours (N, 3) uint8 or None)."""
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise InputError("not a PLY file (no 'ply' magic or 'end_header')", path)
    fmt, count, fields = None, None, []
    for number, line in enumerate(data[:end].decode("ascii").splitlines(), start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
            if fmt not in ("ascii", "binary_little_endian"):
                raise InputError(f"unsupported PLY format {fmt!r}", path, number)
        elif words[0] == "element":
            if words[1] != "vertex" or count is not None:
                raise InputError(
                    f"only one 'vertex' element is supported, got {line!r}", path, number
                )
            count = int(words[2])
        elif words[0] == "property":
            if words[1] not in _PLY_TYPES or len(words) != 3:
                raise InputError(f"unsupported PLY property {line!r}", path, number)
            fields.append((words[2], "<" + _PLY_TYPES[words[1]]))
        else:
            raise InputError(f"unexpected PLY header line {line!r}", path, number)
    names = [f[0] for f in fields]
    if fmt is None or count is None or not {"x", "y", "z"} <= set(names):
        raise InputError("PLY header lacks format, vertex count or x/y/z", path)
    body = data[end + len(b"end_header\n"):]
    dtype = np.dtype(fields)
    if fmt == "binary_little_endian":
        if len(body) < count * dtype.itemsize:
            raise InputError(f"PLY body holds fewer than {count} vertices", path)
        rows = np.frombuffer(body, dtype=dtype, count=count)
        table = {n: rows[n] for n in names}
    else:
        values = np.array(body.split(), dtype=np.float64)
        if values.size != count * len(names):
            raise InputError(
                f"PLY body has {values.size} values, expected {count}×{len(names)}", path
            )
        grid = values.reshape(count, len(names))
        # Through each property's own type, as a binary file would store it.
        table = {n: grid[:, i].astype(dtype[n]) for i, n in enumerate(names)}
    points = np.stack([table[a].astype(np.float64) for a in "xyz"], axis=1).reshape(-1, 3)
    colors = None
    if {"red", "green", "blue"} <= set(names):
        colors = np.stack([table[c] for c in ("red", "green", "blue")], axis=1).astype(np.uint8)
    return points, colors


def height_colors(
    points: np.ndarray, cmap: str = "viridis", z_range: tuple[float, float] | None = None
) -> np.ndarray:
    """(N, 3) uint8 RGB colours of points (N, 3) by height z (low dark, high bright), over
    z_range (default: the points' own range)."""
    import matplotlib

    pts = _points(points, "points")
    lo, hi = z_range if z_range is not None else (_z_range(pts))
    t = np.clip((pts[:, 2] - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    rgba = matplotlib.colormaps[cmap](t)
    return np.round(rgba[:, :3] * 255.0).astype(np.uint8)


# --- figure ---------------------------------------------------------------------------------


def plot_voxels(
    path: str | Path,
    points: np.ndarray,
    *,
    resolution: float = DEFAULT_RESOLUTION,
    trajectory: np.ndarray | None = None,
    title: str = "",
    z_limits: tuple[float, float] | None = None,
    max_points_3d: int = 40_000,
    dpi: int = 120,
) -> Figure:
    """Draw occupied voxel centres (N, 3) as a PNG at `path` (atomically): left, the top view,
    each column of voxels coloured by its highest occupied voxel; right, a perspective view of
    the voxels coloured by height (at most max_points_3d, an even subsample), its height
    exaggerated (and the factor shown) where the map is much wider than high. `trajectory`
    (K, 3) poses (x, y, θ) is drawn on the top view. `z_limits` (zmin, zmax) metres draws only
    the voxels between (e.g. without the floor and ceiling layers)."""
    pts = _points(points, "points")
    if z_limits is not None:
        pts = pts[(pts[:, 2] >= z_limits[0]) & (pts[:, 2] <= z_limits[1])]
    fig = Figure(figsize=(14.0, 6.5), dpi=dpi)
    FigureCanvasAgg(fig)
    top = fig.add_subplot(1, 2, 1)
    side = fig.add_subplot(1, 2, 2, projection="3d")
    zlo, zhi = _z_range(pts)
    if len(pts):
        ij = np.floor(pts[:, :2] / resolution).astype(np.int64)
        i0, j0 = ij.min(axis=0)
        ni, nj = ij.max(axis=0) - (i0, j0) + 1
        image = np.full((nj, ni), np.nan)
        order = np.argsort(pts[:, 2], kind="stable")  # the highest voxel of a column wins
        image[ij[order, 1] - j0, ij[order, 0] - i0] = pts[order, 2]
        extent = (i0 * resolution, (i0 + ni) * resolution, j0 * resolution, (j0 + nj) * resolution)
        shown = top.imshow(image, origin="lower", extent=extent, cmap="viridis", vmin=zlo, vmax=zhi,
                           interpolation="nearest")
        fig.colorbar(shown, ax=top, label="highest occupied voxel z [m]", shrink=0.8)
        step = max(1, math.ceil(len(pts) / max_points_3d))
        sub = pts[::step]
        side.scatter(
            sub[:, 0], sub[:, 1], sub[:, 2], c=sub[:, 2], cmap="viridis", vmin=zlo, vmax=zhi,
            s=2.0, marker="s", linewidths=0, depthshade=False,
        )
        span = np.maximum(pts.max(axis=0) - pts.min(axis=0), resolution)
        exaggeration = max(1.0, 0.2 * float(span[:2].max()) / float(span[2]))
        side.set_box_aspect((span[0], span[1], span[2] * exaggeration))
        side.zaxis.set_major_locator(MaxNLocator(3))
        if exaggeration > 1.05:
            side.set_title(f"perspective view (height ×{exaggeration:.1f})")
    if trajectory is not None:
        traj = np.asarray(trajectory, dtype=np.float64).reshape(-1, 3)
        top.plot(traj[:, 0], traj[:, 1], color="red", linewidth=1.2, label="trajectory")
        top.legend(loc="best")
    top.set_aspect("equal")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title("top view")
    side.set_xlabel("x [m]")
    side.set_ylabel("y [m]")
    side.set_zlabel("z [m]")
    side.view_init(elev=35.0, azim=-60.0)
    if not side.get_title():
        side.set_title("perspective view")
    fig.suptitle(title or f"{len(pts)} occupied voxels of {resolution:g} m")
    with atomic_write(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=dpi)
    return fig


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


def _z_range(pts: np.ndarray) -> tuple[float, float]:
    if len(pts) == 0:
        return 0.0, 1.0
    lo, hi = float(pts[:, 2].min()), float(pts[:, 2].max())
    return (lo, hi) if hi > lo else (lo, lo + 1.0)
