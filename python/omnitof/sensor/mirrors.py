"""Planar mirrors in front of the ToF camera: the reflection matrix D and the virtual cameras of
the paper's eq. 6, the mirror pyramid, and which pixel looks through which mirror.

Frames (right-handed; metres; every transform `a_T_b` is a 4×4 float64 that maps points in b to
points in a):

- Robot frame: x forward (the driving direction), y left, z up; origin on the floor below the
  camera's optical centre. A bearing is atan2(y, x) of a direction in this frame,
  counter-clockwise from the driving direction; an elevation is its angle above the horizontal.
- Camera frame: `omnitof.sensor.camera`'s: x right in the image (growing u), y down (growing v),
  z along the optical axis, which in this sensor points straight up into the mirrors.
- robot_T_camera (`camera_mount`): camera x = robot +y (left), camera y = robot −x (back),
  camera z = robot +z (up), i.e. a rotation of +90° about z, and the optical centre at
  (0, 0, camera_height). Seen in the image: the top edge (small v) looks towards the front and
  the right edge (large u) towards the robot's left, as if lying on the floor, head forward,
  looking up. A horizontal direction at azimuth φ = atan2(y, x) in the camera frame has the
  robot bearing φ + 90°.

Mirror planes (`MirrorPlane`): the plane {x : n·x = d} in the camera frame with a unit normal n
that points *away* from the camera and d > 0, so the camera centre (n·0 = 0 < d) lies on the
reflective side, the side where n·x < d. The mirror image of a point X is
X − 2(n·X − d)n = (I − 2nnᵀ)X + 2dn, so

    D = [[I − 2nnᵀ, 2dn], [0, 1]].

The paper writes the plane as nᵀx + d = 0 (its eq. 6 has −2dn); ours is the same plane with the
sign of d flipped. A virtual camera is Pv = P·D (eq. 6): it maps a world point X to the pixel
where the real camera P sees X through the mirror, and its centre is D·(0, 0, 0, 1) = (2dn, 1),
the camera centre's mirror image.

The pyramid (`pyramid`): n planar faces whose common apex lies on the optical axis at
apex_height above the optical centre, pointing down at the camera. A face is tilted tilt_deg
from the optical axis; with 45° the ray along the optical axis leaves horizontally and, in the
face's plane of symmetry, a ray θ off the axis leaves at elevation θ + 90° − 2·tilt: the 45°
pyramid looks from the horizon upwards. Face k looks towards the robot bearing
yaw_deg + k·360°/n and is named after that bearing (`direction_name`): at the default yaw of
45° (the paper's "diagonal" placement) the four faces look front-left, back-left, back-right and
front-right, and each fills one quadrant of the image, split by the image's axes through the
principal point. (The paper's Fig. 3 calls its regions LEFT, FRONT, BACK, RIGHT; those names are
true at yaw 0°.)

The apex-down pyramid is a convex solid and the camera lies outside it, so a ray that leaves a
face never meets another face: one reflection per ray is the whole story.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.ndimage import distance_transform_edt

from omnitof.sensor.camera import Camera
from omnitof.errors import ConfigError

# Assumed mounting of the paper's rig; the paper gives no numbers. The camera sits on top of a
# Pioneer-class robot (body ≈ 0.28 m high, Fig. 1(b)), so its optical centre is about 0.4 m above
# the floor, and the apex a hand's width above the lens: the paper's conclusion warns that the
# illumination stops following the image when the mirrors come too close to the camera.
DEFAULT_CAMERA_HEIGHT = 0.40  # metres, floor to optical centre
DEFAULT_APEX_HEIGHT = 0.10  # metres, optical centre to the pyramid's apex
# With size=None the pyramid grows until every pixel sees a mirror, but rays nearly parallel to a
# face would need an unbounded mirror (the SR4000 model's top-right corner pixel looks 39.6° off
# the axis, and a 45° face catches it only 4.75 apex heights out): the face's outer edge stops
# at this many apex heights from the axis (a 0.4 m square base for the default apex height),
# and pixels beyond it see past the pyramid.
MAX_SIZE_PER_APEX_HEIGHT = 2.0
# Relative slack added to the computed size, so that the outermost pixel lies safely inside.
_SIZE_SLACK = 1e-3
# Points within this distance (metres) of a polygon's edge count as inside; planes are checked
# to this tolerance too.
_GEOMETRY_TOLERANCE = 1e-9

# camera → robot rotation of `camera_mount`: its columns are the camera axes in the robot frame.
ROBOT_R_CAMERA = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
ROBOT_R_CAMERA.setflags(write=False)

_DIRECTION_NAMES = (
    "front", "front-left", "left", "back-left", "back", "back-right", "right", "front-right",
)


class MirrorParameterError(ConfigError, ValueError):
    """A bad mirror or pyramid parameter, named in the message; ConfigError and ValueError."""


def camera_mount(camera_height: float = DEFAULT_CAMERA_HEIGHT) -> np.ndarray:
    """robot_T_camera (4×4): the fixed rotation ROBOT_R_CAMERA and the optical centre at
    (0, 0, camera_height) metres above the floor (see the module docstring)."""
    height = float(camera_height)
    if not (math.isfinite(height) and height > 0.0):
        raise MirrorParameterError(
            f"camera_height must be a positive number of metres, got {height!r}"
        )
    transform = np.eye(4)
    transform[:3, :3] = ROBOT_R_CAMERA
    transform[2, 3] = height
    return transform


# How far RᵀR of a mount may stray from I: a rotation typed to 5 decimals (a 45° yaw as 0.70711)
# is meant as one. `rigid_mount` then snaps it to the nearest rotation for everything downstream.
MOUNT_TOLERANCE = 1e-5


def mount_rotation(robot_T_camera: np.ndarray | None = None) -> np.ndarray:
    """The rotation robot_R_camera (3×3) of a mount robot_T_camera (4×4), checked to be a
    proper rotation to MOUNT_TOLERANCE and snapped to the nearest one; ROBOT_R_CAMERA
    (camera_mount's) if None."""
    if robot_T_camera is None:
        return np.asarray(ROBOT_R_CAMERA)
    return rigid_mount(robot_T_camera)[:3, :3]


def rigid_mount(robot_T_camera: np.ndarray) -> np.ndarray:
    """robot_T_camera (4×4) checked to be a rigid transform (finite, a proper rotation to
    MOUNT_TOLERANCE, bottom row 0 0 0 1), its rotation snapped to the nearest proper rotation
    (the polar factor, by SVD): the renderer and the multipath compensation need one exactly."""
    transform = np.array(robot_T_camera, dtype=np.float64)
    if transform.shape != (4, 4):
        raise MirrorParameterError(f"robot_T_camera must be 4×4, got shape {transform.shape}")
    if not np.isfinite(transform).all():
        raise MirrorParameterError("robot_T_camera must be finite")
    if not np.array_equal(transform[3], [0.0, 0.0, 0.0, 1.0]):
        raise MirrorParameterError(f"robot_T_camera's last row must be 0 0 0 1, got {transform[3].tolist()}")
    rotation = transform[:3, :3]
    stray = np.abs(rotation.T @ rotation - np.eye(3)).max()
    if not stray <= MOUNT_TOLERANCE or np.linalg.det(rotation) < 0:
        raise MirrorParameterError(
            f"robot_T_camera's rotation must be a proper rotation (RᵀR = I to {MOUNT_TOLERANCE:g}, det +1); "
            f"RᵀR is {stray:.3g} off I, det {np.linalg.det(rotation):.6g}"
        )
    u, _, vt = np.linalg.svd(rotation)
    transform[:3, :3] = u @ vt
    return transform


def direction_name(bearing_deg: float) -> str:
    """The nearest of the eight robot directions (front, front-left, left, ..., front-right) to
    a bearing in degrees counter-clockwise from the driving direction."""
    index = int(round((bearing_deg % 360.0) / 45.0)) % 8
    return _DIRECTION_NAMES[index]


class RayHits(NamedTuple):
    """Where rays meet a mirror, row by row; rows that miss are NaN in every float field.

    points: (N, 3) hit points (camera frame, metres). distances: (N,) metres from the ray's
    origin along its unit direction. hit: (N,) bool. directions: (N, 3) unit reflected
    directions.
    """

    points: np.ndarray
    distances: np.ndarray
    hit: np.ndarray
    directions: np.ndarray


@dataclass(frozen=True, eq=False)
class MirrorPlane:
    """The infinite mirror plane {x : n·x = d} in the camera frame, metres.

    `normal` is normalised on construction (d is scaled with it, so the plane stays the same);
    it points away from the camera, and d > 0 is the camera centre's distance to the plane. Only
    the camera's side, n·x < d, reflects.
    """

    normal: np.ndarray
    d: float

    def __post_init__(self) -> None:
        normal = np.asarray(self.normal, dtype=np.float64)
        if normal.shape != (3,) or not np.all(np.isfinite(normal)):
            raise MirrorParameterError(
                f"MirrorPlane.normal must be 3 finite numbers, got {self.normal!r}"
            )
        d = float(self.d)
        scale = float(np.abs(normal).max())
        if scale == 0.0 or not math.isfinite(d):
            raise MirrorParameterError("MirrorPlane needs a non-zero normal and a finite d")
        # The plane n·x = d is n·x/s = d/s for any s > 0: scaling by the largest component first
        # keeps the norm of huge components from overflowing.
        normal, d = normal / scale, d / scale
        length = float(np.linalg.norm(normal))
        if d / length <= 0.0:
            raise MirrorParameterError(
                f"MirrorPlane.d must be > 0 with the normal pointing away from the camera, got "
                f"d = {d!r}; flip the sign of both normal and d"
            )
        normal = normal / length
        normal.setflags(write=False)
        object.__setattr__(self, "normal", normal)
        object.__setattr__(self, "d", d / length)

    @classmethod
    def through(cls, point: np.ndarray, normal: np.ndarray) -> MirrorPlane:
        """The plane through `point` perpendicular to `normal`, the normal's sign chosen so that
        it points away from the camera centre (which must not lie on the plane)."""
        point = np.asarray(point, dtype=np.float64)
        normal = np.asarray(normal, dtype=np.float64)
        d = float(normal @ point)
        if d == 0.0:
            raise MirrorParameterError("a mirror plane must not pass through the camera centre")
        sign = 1.0 if d > 0.0 else -1.0
        return cls(sign * normal, sign * d)

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """n·x − d for points (N, 3): negative on the reflective (camera's) side, metres."""
        return _rows(points, "points") @ self.normal - self.d

    def reflection_matrix(self) -> np.ndarray:
        """D = [[I − 2nnᵀ, 2dn], [0, 1]] (4×4, paper eq. 6 in this module's sign convention):
        maps a point (homogeneous, camera frame) to its mirror image; D·D = I."""
        n = self.normal
        matrix = np.eye(4)
        matrix[:3, :3] -= 2.0 * np.outer(n, n)
        matrix[:3, 3] = 2.0 * self.d * n
        return matrix

    def reflect_points(self, points: np.ndarray) -> np.ndarray:
        """Mirror images (N, 3) of points (N, 3), camera frame."""
        pts = _rows(points, "points")
        return pts - 2.0 * np.outer(pts @ self.normal - self.d, self.normal)

    def reflect_directions(self, directions: np.ndarray) -> np.ndarray:
        """Reflected directions (N, 3) of directions (N, 3): (I − 2nnᵀ)·v, lengths kept."""
        dirs = _rows(directions, "directions")
        return dirs - 2.0 * np.outer(dirs @ self.normal, self.normal)

    def virtual_centre(self) -> np.ndarray:
        """The virtual camera's centre (3,): D·(0, 0, 0, 1) = 2dn, the camera centre's image."""
        return 2.0 * self.d * self.normal

    def virtual_camera(self, P: np.ndarray) -> np.ndarray:
        """Pv = P·D (3×4, eq. 6) for a real camera P (3×4, e.g. K[I|0] in the camera frame).

        Pv·X is the pixel (homogeneous) at which P sees the point X through the mirror. Pv
        is linear: apply a lens's distortion to its result as to any pinhole projection.
        """
        P = np.asarray(P, dtype=np.float64)
        if P.shape != (3, 4):
            raise MirrorParameterError(f"P must be a 3×4 projection matrix, got shape {P.shape}")
        return P @ self.reflection_matrix()

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """Meet rays (N, 3) origins + t·directions, t > 0, with the plane's reflective side.

        A ray hits if its origin is strictly on the camera's side (n·o < d) and it travels
        towards the plane (n·v > 0); rays that start on the plane (a ray just reflected there)
        or come from behind do not. Directions need not be unit; distances are in metres.
        """
        o = _rows(origins, "origins")
        v = _rows(directions, "directions")
        if o.shape != v.shape:
            raise MirrorParameterError(
                f"origins {o.shape} and directions {v.shape} differ in shape"
            )
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = v / np.linalg.norm(v, axis=1, keepdims=True)
            gap = self.d - o @ self.normal  # > 0 on the reflective side
            approach = unit @ self.normal
            hit = (gap > 0.0) & (approach > 0.0)
            t = np.where(hit, gap / approach, np.nan)
        points = o + t[:, None] * unit
        reflected = self.reflect_directions(unit)
        reflected[~hit] = np.nan
        return RayHits(points, t, hit, reflected)

    def reflect_ray(
        self, origin: np.ndarray, direction: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """(hit point, unit reflected direction) of one ray, or None if it misses the plane."""
        hits = self.intersect(np.reshape(origin, (1, 3)), np.reshape(direction, (1, 3)))
        if not hits.hit[0]:
            return None
        return hits.points[0], hits.directions[0]


@dataclass(frozen=True, eq=False)
class Mirror:
    """A planar mirror: its plane, its convex outline and its name.

    polygon: (K, 3) vertices in the camera frame, metres, in order around the outline, all on
    the plane (to 1e-9 m). name: what the mirror looks at, e.g. "front-left".
    """

    plane: MirrorPlane
    polygon: np.ndarray
    name: str
    # +1 if the outline runs counter-clockwise in the plane's (e1, e2) basis; set on creation.
    _orientation: float = field(default=1.0, init=False, repr=False)

    def __post_init__(self) -> None:
        polygon = np.array(self.polygon, dtype=np.float64)
        if polygon.ndim != 2 or polygon.shape[1] != 3 or len(polygon) < 3:
            raise MirrorParameterError(
                f"mirror {self.name!r}: polygon must be (K >= 3, 3) vertices, got {polygon.shape}"
            )
        off_plane = np.abs(polygon @ self.plane.normal - self.plane.d).max()
        if not off_plane <= _GEOMETRY_TOLERANCE * max(1.0, float(np.abs(polygon).max())):
            raise MirrorParameterError(
                f"mirror {self.name!r}: polygon vertices lie up to {off_plane:.3g} m off its plane"
            )
        polygon.setflags(write=False)
        object.__setattr__(self, "polygon", polygon)
        outline = self._in_plane(polygon)
        edges = np.roll(outline, -1, axis=0) - outline
        turns = _cross2(edges, np.roll(edges, -1, axis=0))
        if not (np.all(turns >= 0.0) or np.all(turns <= 0.0)) or not np.any(turns != 0.0):
            raise MirrorParameterError(f"mirror {self.name!r}: polygon must be convex and ordered")
        object.__setattr__(self, "_orientation", 1.0 if turns.sum() > 0.0 else -1.0)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: whether points (N, 3) on the plane lie inside the outline (edges included,
        to 1e-9 m). Points off the plane are judged by their orthogonal projection onto it."""
        p = self._in_plane(_rows(points, "points"))
        outline = self._in_plane(self.polygon)
        edges = np.roll(outline, -1, axis=0) - outline
        lengths = np.linalg.norm(edges, axis=1)
        # Distance of each point to the left of each edge (counter-clockwise outlines: inside).
        side = _cross2(edges[None, :, :], p[:, None, :] - outline[None, :, :]) / lengths
        with np.errstate(invalid="ignore"):
            return np.all(side * self._orientation >= -_GEOMETRY_TOLERANCE, axis=1)

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """Like MirrorPlane.intersect, but a ray hits only inside the outline."""
        hits = self.plane.intersect(origins, directions)
        inside = hits.hit.copy()
        inside[hits.hit] = self.contains(hits.points[hits.hit])
        return _keep(hits, inside)

    def virtual_camera(self, P: np.ndarray) -> np.ndarray:
        """Pv = P·D of this mirror's plane (see MirrorPlane.virtual_camera)."""
        return self.plane.virtual_camera(P)

    def _in_plane(self, points: np.ndarray) -> np.ndarray:
        """2D coordinates (N, 2) of points in an orthonormal basis (e1, e2) of the plane."""
        n = self.plane.normal
        helper = np.eye(3)[int(np.argmin(np.abs(n)))]
        e1 = helper - (helper @ n) * n
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        return np.stack([points @ e1, points @ e2], axis=1)


def pyramid(
    n_mirrors: int = 4,
    tilt_deg: float = 45.0,
    apex_height: float = DEFAULT_APEX_HEIGHT,
    size: float | None = None,
    yaw_deg: float = 45.0,
    *,
    camera: Camera | None = None,
    robot_T_camera: np.ndarray | None = None,
) -> list[Mirror]:
    """The mirror pyramid, apex down on the optical axis, as Mirrors in the camera frame.

    Args:
        n_mirrors: number of faces (>= 3), spaced evenly in bearing.
        tilt_deg: angle of each face to the optical axis, in (0°, 90°). 45° sends the optical
            axis ray out horizontally; more tilt sends every ray further down.
        apex_height: metres from the optical centre up to the apex (> 0).
        size: horizontal distance in metres from the optical axis to the middle of each face's
            outer edge (the base polygon's inradius; half the base's side for four faces).
            None: just large enough that every pixel's central ray of `camera` meets a
            mirror, but at most MAX_SIZE_PER_APEX_HEIGHT·apex_height.
        yaw_deg: robot bearing (degrees, counter-clockwise from the driving direction) that face 0
            looks at; face k looks at yaw_deg + k·360°/n_mirrors.
        camera: the camera whose field of view sets size=None (default: Camera.sr4000()).
        robot_T_camera: the mount (4×4), which relates bearings to the camera frame; its
            rotation must keep the optical axis vertical. Default: camera_mount(); only its
            rotation matters here, since the pyramid is built in the camera frame.

    Returns:
        n_mirrors Mirrors (triangles: apex and two base corners), face k named after its
        bearing (e.g. "front-left"), with the bearing appended if two names would coincide.
    """
    n, tilt, apex_height = _checked_pyramid_args(n_mirrors, tilt_deg, apex_height)
    rotation = _checked_mount(robot_T_camera)
    bearings = (float(yaw_deg) + 360.0 * np.arange(n) / n) % 360.0
    planes = [_face_plane(rotation, b, tilt, apex_height) for b in bearings]
    if size is None:
        size = _size_to_fill(camera or Camera.sr4000(), planes, tilt, apex_height)
    size = float(size)
    if not (math.isfinite(size) and size > 0.0):
        raise MirrorParameterError(
            f"pyramid size must be a positive number of metres, got {size!r}"
        )
    apex = np.array([0.0, 0.0, apex_height])
    top = apex_height + size / math.tan(tilt)  # height of every base corner
    corners = [_base_corner(planes[k], planes[(k + 1) % n], apex, top) for k in range(n)]
    names = _unique_names(bearings)
    return [
        Mirror(planes[k], np.stack([apex, corners[k - 1], corners[k]]), names[k]) for k in range(n)
    ]


def bearing_of(mirror: Mirror, robot_T_camera: np.ndarray | None = None) -> float:
    """Robot bearing in degrees [0, 360) that a mirror looks at: that of the horizontal part of
    −n (the way its reflective side faces), which for a pyramid face is also the horizontal
    part of the reflected optical axis."""
    facing = mount_rotation(robot_T_camera) @ -mirror.plane.normal
    return math.degrees(math.atan2(facing[1], facing[0])) % 360.0


def first_hits(camera: Camera, mirrors: Sequence[Mirror]) -> tuple[np.ndarray, RayHits]:
    """Trace every pixel's central ray from the optical centre to the first mirror it meets.

    Returns:
        labels (H, W) int32: index into `mirrors`, −1 where the ray meets none (it sees past
        the mirrors); and the RayHits of those first hits, rows in image order (row-major).
        A ray that meets two mirrors at the same distance (exactly on a shared edge) goes to the
        lower index.
    """
    rays = camera.pixel_grid_rays().reshape(-1, 3)
    origins = np.zeros_like(rays)
    best = np.full(len(rays), np.inf)
    labels = np.full(len(rays), -1, dtype=np.int32)
    points = np.full_like(rays, np.nan)
    directions = np.full_like(rays, np.nan)
    for index, mirror in enumerate(mirrors):  # a loop over mirrors; pixels are vectorised
        hits = mirror.intersect(origins, rays)
        nearer = hits.hit & (hits.distances < best)
        best[nearer] = hits.distances[nearer]
        labels[nearer] = index
        points[nearer] = hits.points[nearer]
        directions[nearer] = hits.directions[nearer]
    distances = np.where(labels >= 0, best, np.nan)
    return labels.reshape(camera.shape), RayHits(points, distances, labels >= 0, directions)


def assign_pixels(camera: Camera, mirrors: Sequence[Mirror]) -> np.ndarray:
    """(H, W) int32: the index of the mirror each pixel's central ray meets first, −1 where it
    meets none and sees the ceiling (or the room) directly."""
    return first_hits(camera, mirrors)[0]


def masks(camera: Camera, mirrors: Sequence[Mirror], edge_margin_px: float = 2.0) -> np.ndarray:
    """(H, W) int32: assign_pixels without the pixels near a region's boundary.

    A pixel is left out (−1) if a pixel of another label (another mirror, or −1: past the
    mirrors' outer edges) lies within edge_margin_px of it, centre to centre. Such pixels
    integrate light from two directions (mixed pixels). Along a boundary parallel to an image
    axis this drops ⌊edge_margin_px⌋ pixels on each side; the image border is no boundary.
    """
    margin = float(edge_margin_px)
    if not (math.isfinite(margin) and margin >= 0.0):
        raise MirrorParameterError(f"edge_margin_px must be >= 0, got {edge_margin_px!r}")
    labels = assign_pixels(camera, mirrors)
    return _erode_labels(labels, margin)


class ViewingRays(NamedTuple):
    """Per pixel, the ray that leaves the mirror: origins (H, W, 3) on the mirror and unit
    directions (H, W, 3), camera frame, NaN where labels (H, W) is −1."""

    origins: np.ndarray
    directions: np.ndarray
    labels: np.ndarray


def viewing_rays(
    camera: Camera, mirrors: Sequence[Mirror], labels: np.ndarray | None = None
) -> ViewingRays:
    """The reflected ray of every pixel: where the central ray meets its mirror and where it
    goes from there, camera frame.

    Args:
        labels: (H, W) mirror index per pixel (e.g. from `masks`); −1 pixels get NaN. Default:
            assign_pixels(camera, mirrors). Each ray is reflected in its labelled mirror's plane.

    Each reflected ray, extended backwards, passes through its mirror's virtual camera centre
    D·(0, 0, 0, 1): the mirror acts as a camera there, looking out (see `virtual_centres`).
    """
    if labels is None:
        labels = assign_pixels(camera, mirrors)
    labels = np.asarray(labels)
    if labels.shape != camera.shape:
        raise MirrorParameterError(f"labels must have shape {camera.shape}, got {labels.shape}")
    rays = camera.pixel_grid_rays().reshape(-1, 3)
    flat = labels.reshape(-1)
    origins = np.full_like(rays, np.nan)
    directions = np.full_like(rays, np.nan)
    for index, mirror in enumerate(mirrors):
        selected = flat == index
        hits = mirror.plane.intersect(np.zeros((int(selected.sum()), 3)), rays[selected])
        origins[selected] = hits.points
        directions[selected] = hits.directions
    h, w = camera.shape
    return ViewingRays(origins.reshape(h, w, 3), directions.reshape(h, w, 3), labels)


def virtual_centres(mirrors: Sequence[Mirror]) -> np.ndarray:
    """(M, 3) virtual camera centres D·(0, 0, 0, 1), camera frame, metres."""
    return np.array([m.plane.virtual_centre() for m in mirrors]).reshape(-1, 3)


def virtual_cameras(camera: Camera, mirrors: Sequence[Mirror]) -> list[np.ndarray]:
    """The 3×4 Pv = K[I|0]·D of each mirror (distortion-free part; eq. 6)."""
    P = camera.K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    return [m.virtual_camera(P) for m in mirrors]


def project_via(camera: Camera, mirror: Mirror, points: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) at which `camera` sees points (N, 3, camera frame) through `mirror`.

    The real camera sees X where it would see X's mirror image D·X directly, provided the
    line of sight to D·X crosses the mirror inside its outline and X lies in front of the
    mirror (on the camera's side). NaN otherwise, and where camera.project gives NaN.
    """
    pts = _rows(points, "points")
    images = mirror.plane.reflect_points(pts)
    pixels = camera.project(images)
    hits = mirror.intersect(np.zeros_like(images), images)
    # The mirror must lie between the camera and the image point, else X is behind the mirror.
    with np.errstate(invalid="ignore"):
        ok = hits.hit & (hits.distances <= np.linalg.norm(images, axis=1))
    ok &= mirror.plane.signed_distance(pts) < 0.0
    pixels[~ok] = np.nan
    return pixels


# --- internals -----------------------------------------------------------------------------


def _rows(array: np.ndarray, name: str) -> np.ndarray:
    out = np.asarray(array, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] != 3:
        raise MirrorParameterError(f"{name} must have shape (N, 3), got {out.shape}")
    return out


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z of the 2D cross product, broadcasting over leading axes."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _keep(hits: RayHits, keep: np.ndarray) -> RayHits:
    fields = [hits.points.copy(), hits.distances.copy(), hits.directions.copy()]
    for values in fields:
        values[~keep] = np.nan
    return RayHits(fields[0], fields[1], keep, fields[2])


def _checked_pyramid_args(
    n_mirrors: int, tilt_deg: float, apex_height: float
) -> tuple[int, float, float]:
    if isinstance(n_mirrors, bool) or not isinstance(n_mirrors, (int, np.integer)) or n_mirrors < 3:
        raise MirrorParameterError(f"n_mirrors must be a whole number >= 3, got {n_mirrors!r}")
    tilt_deg = float(tilt_deg)
    if not 0.0 < tilt_deg < 90.0:
        raise MirrorParameterError(f"tilt_deg must lie strictly between 0 and 90, got {tilt_deg!r}")
    apex_height = float(apex_height)
    if not (math.isfinite(apex_height) and apex_height > 0.0):
        raise MirrorParameterError(
            f"apex_height must be a positive number of metres, got {apex_height!r}"
        )
    return int(n_mirrors), math.radians(tilt_deg), apex_height


def _checked_mount(robot_T_camera: np.ndarray | None) -> np.ndarray:
    """mount_rotation, and the optical axis must point straight up (the pyramid needs it)."""
    rotation = mount_rotation(robot_T_camera)
    if not np.allclose(rotation[:, 2], [0.0, 0.0, 1.0], atol=1e-9):
        raise MirrorParameterError("robot_T_camera must keep the optical axis pointing straight up")
    return rotation


def _face_plane(
    robot_R_camera: np.ndarray, bearing_deg: float, tilt: float, apex_height: float
) -> MirrorPlane:
    """The face looking at robot bearing `bearing_deg`, through the apex (0, 0, apex_height).

    With e the face's horizontal looking direction in the camera frame, the normal pointing away
    from the camera is n = −cos(tilt)·e + sin(tilt)·z: the face rises outwards from the apex,
    z = apex_height + (x·e)/tan(tilt), and reflects the optical axis to sin(2·tilt)·e +
    cos(2·tilt)·z, horizontal for tilt = 45°.
    """
    b = math.radians(bearing_deg)
    e = robot_R_camera.T @ np.array([math.cos(b), math.sin(b), 0.0])
    normal = -math.cos(tilt) * e + math.sin(tilt) * np.array([0.0, 0.0, 1.0])
    return MirrorPlane(normal, apex_height * math.sin(tilt))


def _base_corner(a: MirrorPlane, b: MirrorPlane, apex: np.ndarray, top: float) -> np.ndarray:
    """Where the edge shared by faces a and b (a line through the apex) reaches height `top`."""
    edge = np.cross(a.normal, b.normal)
    edge = edge if edge[2] > 0.0 else -edge
    return apex + edge * (top - apex[2]) / edge[2]


def _size_to_fill(
    camera: Camera, planes: list[MirrorPlane], tilt: float, apex_height: float
) -> float:
    """Smallest size whose pyramid catches every pixel's central ray, capped (see pyramid).

    A ray enters the convex pyramid solid where it crosses the last of the faces' planes, and
    only if it approaches every one of them; the entry point's distance out along that face,
    (height − apex_height)·tan(tilt), is the size the face needs for that pixel.
    """
    rays = camera.pixel_grid_rays().reshape(-1, 3)
    rays = rays[np.all(np.isfinite(rays), axis=1)]
    normals = np.array([p.normal for p in planes])
    approach = rays @ normals.T  # (N, M)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(approach > 0.0, planes[0].d / approach, np.inf)  # every face has the same d
    t_entry = t.max(axis=1)
    limit = MAX_SIZE_PER_APEX_HEIGHT * apex_height
    if not np.all(np.isfinite(t_entry)):
        return limit  # some ray runs beside the pyramid: no finite size catches it
    outward = (rays[:, 2] * t_entry - apex_height) * math.tan(tilt)
    return min(float(outward.max()) * (1.0 + _SIZE_SLACK), limit)


def _unique_names(bearings: np.ndarray) -> list[str]:
    names = [direction_name(b) for b in bearings]
    if len(set(names)) == len(names):
        return names
    return [f"{name}-{b:05.1f}deg" for name, b in zip(names, bearings)]


def interior_pixel(region: np.ndarray) -> tuple[int, int] | None:
    """(row, col) of the region's pixel farthest from its boundary (None if it is empty)."""
    if not region.any():
        return None
    padded = np.pad(region, 1)  # the image border counts as boundary for label placement
    distance = distance_transform_edt(padded)[1:-1, 1:-1]
    row, col = np.unravel_index(int(np.argmax(distance)), region.shape)
    return int(row), int(col)


def _erode_labels(labels: np.ndarray, margin: float) -> np.ndarray:
    """Set to −1 every labelled pixel with a differently labelled pixel within `margin` px."""
    out = labels.copy()
    if margin <= 0.0:
        return out
    for value in np.unique(labels[labels >= 0]):
        region = labels == value
        if region.all():
            continue  # no boundary anywhere (the EDT of an all-ones image is meaningless)
        # Distance from each region pixel to the nearest pixel outside it, centre to centre.
        distance = distance_transform_edt(region)
        out[region & (distance <= margin)] = -1
    return out
