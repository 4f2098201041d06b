"""Simulated calibration images: a checkerboard, or a card with four dots seen directly and
through a mirror (the paper's Fig. 3(a)), as the ToF camera's amplitude and distance images.

Why this renderer is written by hand: the world renderer (`omnitof.sim.render`, Rust) knows only
uniformly coloured quads and boxes, and no rendering library we know of traces textured planes
through a distorted low-resolution ToF lens and a mirror *as phasors* (the sensor integrates
complex returns over the pixel, then adds shot noise to four phase samples). Calibration needs
exactly that: what biases the centroids and corners is the pixel's integration over edges and
the sensor's noise. The renderer is a few vectorised numpy passes over all pixels × sub-rays.

Model (the one of DESIGN.md, as `omnitof.sim.render` uses it): each pixel is S sub-rays
(`sim.render.sub_ray_directions`, stratified over the pixel, through the lens model). A sub-ray
from the optical centre meets the nearest of: the target card (both sides opaque), a mirror
(then it continues reflected, `MirrorPlane.reflect_directions`, and meets the card or the room),
or the room (a box around the camera: floor, walls, ceiling). It returns the phasor
amplitude_at_1m·albedo·|cos incidence|/r²·e^{iΦ}, r the one-way path length (camera → mirror →
surface), Φ from the round trip 2r, times the mirror reflectivity squared (out and back) for
reflected rays. A pixel's phasor is the mean over its sub-rays; the active offset is the mean of
|p|/modulation contrast and the ambient offset sensor.ambient·albedo/0.5 (once the mirror's
reflectivity). `tof.SensorNoise.synthesise` draws the four samples, `tof.decode` decodes them.

Exposure: a white card a few centimetres from the lens saturates an SR4000 at its normal
integration time, so, like the camera's auto-exposure, every image's light is scaled (one factor
for the active and the ambient light, i.e. the integration time) so that its brightest
expected sample is EXPOSURE_TARGET of full well.

Frames: everything in the camera frame of `omnitof.sensor.mirrors` (z up along the optical axis,
metres). A target's pose is camera_T_target (4×4): the card lies in its frame's z = 0 plane; it
is printed alike on both sides (a thin card), so which side faces the camera does not matter.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.ndimage import binary_dilation, distance_transform_edt

from omnitof.calibration.images import AmplitudeImage
from omnitof.sensor.camera import Camera
from omnitof.io.atomic import atomic_write
from omnitof.sensor.mirrors import Mirror, assign_pixels, project_via
from omnitof.sim.render import DEFAULT_MIRROR_REFLECTIVITY, sub_ray_directions
from omnitof.sensor.tof import SensorNoise, ToFFrame, decode, path_to_phase

# The brightest expected sample of an image is scaled to this fraction of full well.
EXPOSURE_TARGET = 0.6
# Candidate centres of a dot target stay this far (metres) in front of the mirror.
CLEAR = 0.004
# Checkerboards are tilted by up to this much (degrees) from facing the camera: more tilt
# pins the focal length better (15 boards: 0.5 % at 40°, 0.2 % at 55°), but beyond ~55° the
# detector misses boards and the principal point gets worse.
BOARD_TILT_DEG = 50.0
# Distance range (metres) of the checkerboard's middle from the lens: boards that fill much of
# the image pin the principal point (15 boards: 0.3 px error against 0.6 px at 0.35–0.75 m).
BOARD_DEPTH = (0.25, 0.5)
# Planned boards are chosen from this many random feasible poses per board
# (`planned_checkerboard_poses`).
PLAN_CANDIDATES = 20
# Sub-rays per pixel (8×8 stratified): a real pixel integrates the light over its whole area,
# and the printed edges' grey values must come from that box filter, not from the sampling
# pattern. Checkerboard corners found by `intrinsics.saddle_points` on noise-free boards lie
# 0.10 / 0.037 / 0.025 px RMS from the truth with 4 / 16 / 64 sub-rays; with 16 the pattern's
# error, not the detector's, set the principal point's (closed form, 30 boards, seeds 0–4:
# 0.03–0.12 px, against 0.03–0.09 px with 64). Only edge pixels get all 64 (`_target_signal`).
DEFAULT_SUB_RAYS = 64
# Flat uniform walls (`calibration.walls`) have no printed edges to resolve: 16 sub-rays.
WALL_SUB_RAYS = 16
# Every pixel is traced with this many sub-rays first; only pixels whose sub-rays meet more than
# one surface or albedo get all of them (`_target_signal`).
COARSE_SUB_RAYS = 16
# Near-infrared reflectances of printer paper and black toner (assumed: white office paper
# 0.8–0.9 at 850 nm; laser toner stays dark in the NIR, about 0.05).
WHITE = 0.85
BLACK = 0.05


@dataclass(frozen=True)
class Room:
    """The background: an axis-aligned box around the camera, camera frame (metres).

    Defaults: a 5 m × 5 m room, the camera 0.4 m above the floor and 2.0 m below the ceiling
    (a 2.4 m ceiling), albedos of grey floor, light walls and ceiling tiles.
    """

    half_width: float = 2.5
    floor: float = -0.4
    ceiling: float = 2.0
    floor_albedo: float = 0.3
    wall_albedo: float = 0.6
    ceiling_albedo: float = 0.75
    ambient: float = 1.0


@dataclass(frozen=True)
class Checkerboard:
    """A printed checkerboard of cols × rows squares of `square` metres with a white border.

    Target frame: the first inner corner at the origin, x along a row of inner corners, y down
    the columns, z = 0 on the board. Inner corners: (cols − 1) × (rows − 1), OpenCV's
    pattern_size.
    """

    cols: int = 8
    rows: int = 6
    square: float = 0.035
    border: float = 0.025

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(corners per row, corners per column), as cv2.findChessboardCorners takes it."""
        return (self.cols - 1, self.rows - 1)

    def object_points(self) -> np.ndarray:
        """(N, 3) float32 inner corners in the target frame, row by row (OpenCV's order)."""
        nx, ny = self.pattern_size
        y, x = np.mgrid[0:ny, 0:nx]
        pts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1) * self.square
        return pts.astype(np.float32)

    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of the card, metres in the target frame."""
        s, b = self.square, self.border
        return (-s - b, (self.cols - 1) * s + b, -s - b, (self.rows - 1) * s + b)

    def albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Albedo at target-frame points (inside the card)."""
        i = np.floor(x / self.square).astype(np.int64) + 1
        j = np.floor(y / self.square).astype(np.int64) + 1
        inside = (i >= 0) & (i < self.cols) & (j >= 0) & (j < self.rows)
        black = inside & ((i + j) % 2 == 0)
        return np.where(black, BLACK, WHITE)


@dataclass(frozen=True)
class DotTarget:
    """The paper's small paper target: a white card with four black dots at the corners of a
    square of side `spacing` (metres), centred on the target frame's origin.

    The dots' RMS distance from their centroid is spacing/√2 whatever their order, which is how
    the metric scale is fixed from it (`mirror_planes`).
    """

    # Small, because it must fit between the lens and the mirror: with the default rig (apex
    # 0.10 m above the lens) the dots can be seen both directly and through a mirror only
    # within a few centimetres of
    # 0.10–0.18 m from the lens (the back mirror, nearer the principal point's short side, has
    # the least room: a 1.5 cm square of dots does not fit there, 1.2 cm does).
    spacing: float = 0.012
    radius: float = 0.0025
    margin: float = 0.005

    def dot_centres(self) -> np.ndarray:
        """(4, 3) dot centres in the target frame."""
        h = self.spacing / 2.0
        return np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])

    def extent(self) -> tuple[float, float, float, float]:
        h = self.spacing / 2.0 + self.radius + self.margin
        return (-h, h, -h, h)

    def albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        c = self.dot_centres()
        d2 = np.min((x[..., None] - c[:, 0]) ** 2 + (y[..., None] - c[:, 1]) ** 2, axis=-1)
        return np.where(d2 <= self.radius**2, BLACK, WHITE)


@dataclass(frozen=True)
class PlainBoard:
    """A plain white board of width × height metres centred on the target frame's origin:
    seen through two neighbouring mirrors at once, its path lengths tie the two mirrors together
    (`calibration.refine`). Any flat, matte board does (a wall panel, the back of a checkerboard)."""

    width: float = 1.2
    height: float = 0.8
    reflectance: float = WHITE

    def extent(self) -> tuple[float, float, float, float]:
        return (-self.width / 2, self.width / 2, -self.height / 2, self.height / 2)

    def albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.full(np.shape(x), self.reflectance)


@dataclass
class RenderedImage:
    """One simulated calibration image.

    tof: decoded amplitude (sample units) and distance (metres, one way), (H, W) float32.
    camera_T_target: the target's true pose. mirror: index of the mirror the target was placed
    at (dot targets), None for checkerboards. exposure: the light scale used.
    """

    tof: ToFFrame
    camera_T_target: np.ndarray
    mirror: int | None
    exposure: float


def render_target(
    camera: Camera,
    target: Checkerboard | DotTarget | PlainBoard,
    camera_T_target: np.ndarray,
    mirrors: Sequence[Mirror] = (),
    *,
    rng: np.random.Generator | int,
    sensor: SensorNoise | None = None,
    room: Room = Room(),
    sub_rays: int = DEFAULT_SUB_RAYS,
    mirror_reflectivity: float = DEFAULT_MIRROR_REFLECTIVITY,
    noise: bool = True,
) -> tuple[ToFFrame, float]:
    """Render one image of a target at camera_T_target (see the module docstring).

    Returns:
        (decoded frame, exposure factor). With noise=False the frame is the noise-free
        decoding of the expected samples.
    """
    sensor = sensor or SensorNoise()
    p_pix, active, ambient, exposure = _target_signal(camera, target, camera_T_target, mirrors, sensor, room,
                                                      sub_rays, mirror_reflectivity)
    if noise:
        return _noisy_frame(sensor, p_pix, active, ambient, rng), exposure
    from omnitof.sensor.tof import ideal_samples

    offset = ambient + np.maximum(active, np.abs(p_pix))
    b0, b1, b2, b3 = (q.astype(np.float32) for q in ideal_samples(p_pix, offset))
    return decode(b0, b1, b2, b3, sensor.f_mod), exposure


def render_target_frames(
    camera: Camera,
    target: Checkerboard | DotTarget | PlainBoard,
    camera_T_target: np.ndarray,
    mirrors: Sequence[Mirror] = (),
    *,
    rngs: Sequence[np.random.Generator | int],
    sensor: SensorNoise | None = None,
    room: Room = Room(),
    sub_rays: int = DEFAULT_SUB_RAYS,
    mirror_reflectivity: float = DEFAULT_MIRROR_REFLECTIVITY,
) -> list[ToFFrame]:
    """Several noisy frames of one target pose (one per generator in `rngs`): the scene is
    traced once, only the sensor's noise differs (a camera held still, for averaging)."""
    sensor = sensor or SensorNoise()
    p_pix, active, ambient, _ = _target_signal(camera, target, camera_T_target, mirrors, sensor, room,
                                               sub_rays, mirror_reflectivity)
    return [_noisy_frame(sensor, p_pix, active, ambient, rng) for rng in rngs]


def _noisy_frame(sensor: SensorNoise, p_pix: np.ndarray, active: np.ndarray, ambient: np.ndarray,
                 rng: np.random.Generator | int) -> ToFFrame:
    a0, a1, a2, a3, saturated = sensor.synthesise(
        p_pix, ambient, rng=rng, active_offset=np.maximum(active, np.abs(p_pix))
    )
    return decode(a0, a1, a2, a3, sensor.f_mod, saturated=saturated)


def _target_signal(camera, target, camera_T_target, mirrors, sensor, room, sub_rays, mirror_reflectivity):
    """(pixel phasors, active light, ambient, exposure factor) of a target pose: the traced
    scene before the sensor's noise.

    Adaptive: every pixel is traced with min(sub_rays, COARSE_SUB_RAYS) sub-rays first; a pixel
    whose sub-rays all meet one surface of one albedo (the same card or room face, directly or
    through the same mirror), and whose neighbours' do too, is kept at that; the others (edges)
    are traced again with all `sub_rays`. Inside a uniform pixel the path and the incidence
    change smoothly, so more sub-rays change its mean by far less than the sensor's noise; at
    an edge they decide the grey value (see DEFAULT_SUB_RAYS). Against every pixel at 64: the
    same corners within 0.0002 px (`tests/test_calibration.py`).
    """
    h, w = camera.shape
    pose = np.asarray(camera_T_target, dtype=np.float64)
    fine = int(sub_rays)
    coarse = min(fine, COARSE_SUB_RAYS)
    scene = _scene(camera, tuple(mirrors), room, coarse)
    traced = _trace(scene, target, pose, mirror_reflectivity, None)
    p_pix, active, ambient = _pixel_means(traced, sensor, room, coarse)
    if fine > coarse:
        surface, albedo = traced[4].reshape(-1, coarse), traced[1].reshape(-1, coarse)
        mixed = np.any(surface != surface[:, :1], axis=1) | np.any(albedo != albedo[:, :1], axis=1)
        # ... and their neighbours: an edge that only clips a pixel's corner can pass between
        # its first sub-rays (those pixels moved corners by up to 0.017 px).
        mixed = np.flatnonzero(binary_dilation(mixed.reshape(h, w), np.ones((3, 3), bool)).ravel())
        if len(mixed):
            rays = (mixed[:, None] * fine + np.arange(fine)[None, :]).ravel()
            traced = _trace(_scene(camera, tuple(mirrors), room, fine), target, pose, mirror_reflectivity, rays)
            p_fine, active_fine, ambient_fine = _pixel_means(traced, sensor, room, fine)
            for whole, part in ((p_pix, p_fine), (active, active_fine), (ambient, ambient_fine)):
                whole[mixed] = part
    p_pix, active, ambient = (x.reshape(h, w) for x in (p_pix, active, ambient))
    brightest = float(np.max(ambient + active + np.abs(p_pix)))
    exposure = min(1.0, EXPOSURE_TARGET * sensor.full_well / brightest) if brightest > 0 else 1.0
    return p_pix * exposure, active * exposure, ambient * exposure, exposure


def _trace(scene: dict, target, pose: np.ndarray, mirror_reflectivity: float, rays: np.ndarray | None):
    """(path, albedo, |cos incidence|, mirror gain, surface) of the scene's sub-rays `rays`
    (all: None) with the card at `pose`. surface: 0 room, 1 card, each + 2·(mirror + 1) when
    seen through a mirror (tells which pixels' sub-rays meet one surface)."""
    pick = (lambda a: a) if rays is None else (lambda a: a[rays])
    dirs, valid, t_mirror = pick(scene["dirs"]), pick(scene["valid"]), pick(scene["t_mirror"])
    # What the rays meet without the card is the same for every pose (cached per rig); the
    # card is then tested on the primary rays and on the mirrors' reflected rays.
    t_card, alb_card, cos_card = _card_hits(target, pose, None, dirs)
    via = np.isfinite(t_mirror) & (t_mirror < t_card)
    direct_card = ~via & np.isfinite(t_card)
    path = np.where(direct_card, t_card, pick(scene["path"]))
    albedo = np.where(direct_card, alb_card, pick(scene["albedo"]))
    cosine = np.where(direct_card, cos_card, pick(scene["cosine"]))
    gain = np.where(via, mirror_reflectivity, 1.0)
    surface = np.where(direct_card, 1, 0) + np.where(via, 2 * (pick(scene["mirror"]) + 1), 0)
    mirrored = pick(scene["mirrored"])  # rays that reach a mirror before any card
    if mirrored.any():
        o2, v2 = pick(scene["reflected_o"])[mirrored], pick(scene["reflected_v"])[mirrored]
        t2c, a2c, c2c = _card_hits(target, pose, o2, v2)
        card2 = (t2c < path[mirrored] - t_mirror[mirrored]) & via[mirrored]
        index = np.flatnonzero(mirrored)[card2]
        path[index] = t_mirror[index] + t2c[card2]
        albedo[index] = a2c[card2]
        cosine[index] = c2c[card2]
        surface[index] += 1
    albedo[~valid] = 0.0
    return path, albedo, cosine, gain, surface


def _pixel_means(traced, sensor: SensorNoise, room: Room, sub_rays: int):
    """(phasor, active light, ambient) per pixel: the means over its `sub_rays` traced rays."""
    path, albedo, cosine, gain, _ = traced
    amplitude = sensor.amplitude_at_1m * albedo * cosine * gain**2 / np.maximum(path, 1e-6) ** 2
    phasor = amplitude * np.exp(1j * path_to_phase(2.0 * path, sensor.f_mod))
    ambient_rays = sensor.ambient * room.ambient * albedo * gain / 0.5
    return (phasor.reshape(-1, sub_rays).mean(axis=1),
            amplitude.reshape(-1, sub_rays).mean(axis=1) / sensor.modulation_contrast,
            ambient_rays.reshape(-1, sub_rays).mean(axis=1))


_SCENES: dict = {}


def _scene(camera: Camera, mirrors: tuple[Mirror, ...], room: Room, sub_rays: int) -> dict:
    """Sub-rays and what they meet without a target (mirror, then room), cached per rig."""
    key = (camera, tuple((m.plane.normal.tobytes(), m.plane.d, m.polygon.tobytes()) for m in mirrors),
           room, sub_rays)
    if key in _SCENES:
        return _SCENES[key]
    dirs = np.asarray(sub_ray_directions(camera, sub_rays, 0)).reshape(-1, 3)
    valid = np.all(np.isfinite(dirs), axis=1)
    dirs = np.where(valid[:, None], dirs, np.array([0.0, 0.0, 1.0]))
    origins = np.zeros_like(dirs)
    t_mirror = np.full(len(dirs), np.inf)
    which = np.full(len(dirs), -1)
    reflected_o = np.full_like(dirs, np.nan)
    reflected_v = np.full_like(dirs, np.nan)
    for k, mirror in enumerate(mirrors):  # a loop over mirrors; rays are vectorised
        hits = mirror.intersect(origins, dirs)
        nearer = hits.hit & (hits.distances < t_mirror)
        t_mirror[nearer] = hits.distances[nearer]
        which[nearer] = k
        reflected_o[nearer] = hits.points[nearer]
        reflected_v[nearer] = hits.directions[nearer]
    mirrored = np.isfinite(t_mirror)
    path, albedo, cosine = _room_hits(room, origins, dirs)
    if mirrored.any():
        t2, a2, c2 = _room_hits(room, reflected_o[mirrored], reflected_v[mirrored])
        path[mirrored] = t_mirror[mirrored] + t2
        albedo[mirrored] = a2
        cosine[mirrored] = c2
    scene = {
        "dirs": dirs, "valid": valid, "t_mirror": t_mirror, "mirrored": mirrored, "mirror": which,
        "reflected_o": reflected_o, "reflected_v": reflected_v,
        "path": path, "albedo": albedo, "cosine": cosine,
    }
    if len(_SCENES) > 4:
        _SCENES.clear()
    _SCENES[key] = scene
    return scene


def _card_hits(
    target: Checkerboard | DotTarget | PlainBoard, pose: np.ndarray, origins: np.ndarray | None, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, albedo, |cos incidence|) of rays meeting the card; t = inf where they miss. origins:
    None where every ray starts at the optical centre (the primary rays).

    The rays are taken into the card's frame with one product each (x, y across the card, z
    along its normal), so that no array of hit points is built: this runs on every sub-ray of
    every target image (BENCHMARKS.md, "The target images traced in the card's frame")."""
    rotation, centre = pose[:3, :3], pose[:3, 3]
    along = dirs @ rotation
    start = -(centre @ rotation) if origins is None else (origins - centre) @ rotation
    x0, x1, y0, y1 = target.extent()
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = -start[..., 2] / along[:, 2]
        t = np.where(t > 1e-9, t, np.inf)  # behind the ray's start, or parallel (nan) to the card
        x = start[..., 0] + t * along[:, 0]
        y = start[..., 1] + t * along[:, 1]
        inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1) & np.isfinite(t)
    t = np.where(inside, t, np.inf)
    albedo = np.zeros(len(dirs))
    albedo[inside] = target.albedo(x[inside], y[inside])
    return t, albedo, np.abs(along[:, 2])


def _room_hits(
    room: Room, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, albedo, |cos incidence|) where rays from inside the room meet its box."""
    lo = np.array([-room.half_width, -room.half_width, room.floor])
    hi = np.array([room.half_width, room.half_width, room.ceiling])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_axes = np.where(dirs > 0, (hi - origins) / dirs, np.where(dirs < 0, (lo - origins) / dirs, np.inf))
    axis = np.argmin(t_axes, axis=1)
    t = t_axes[np.arange(len(dirs)), axis]
    up = dirs[np.arange(len(dirs)), 2] > 0
    albedo = np.where(axis < 2, room.wall_albedo, np.where(up, room.ceiling_albedo, room.floor_albedo))
    cosine = np.abs(dirs[np.arange(len(dirs)), axis])
    return t, albedo, cosine


# --- poses ---------------------------------------------------------------------------------


def look_at_pose(centre: np.ndarray, facing: np.ndarray, spin: float) -> np.ndarray:
    """camera_T_target with the target's origin at `centre`, its +z along `facing` (towards
    the viewer) and turned by `spin` radians about it."""
    z = np.asarray(facing, dtype=np.float64)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = helper - (helper @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(spin), math.sin(spin)
    x, y = c * x + s * y, -s * x + c * y
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = centre
    return pose


def _random_rotation(rng: np.random.Generator, max_angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(-max_angle, max_angle)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def checkerboard_poses(
    camera: Camera, board: Checkerboard, n: int, seed: int, *, margin_px: float = 4.0
) -> list[np.ndarray]:
    """n poses of a checkerboard that the camera (without mirrors) sees whole: BOARD_DEPTH m
    away, tilted up to BOARD_TILT_DEG, spread over the image (corners too, for the distortion)."""
    rng = np.random.default_rng(seed)
    x0, x1, y0, y1 = board.extent()
    outline = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)
    middle = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    poses: list[np.ndarray] = []
    for _ in range(200 * n):
        if len(poses) == n:
            break
        u = rng.uniform(0.15, 0.85) * camera.width
        v = rng.uniform(0.15, 0.85) * camera.height
        ray = camera.rays(np.array([[u, v]]))[0]
        depth = rng.uniform(*BOARD_DEPTH)
        facing = -ray @ _random_rotation(rng, math.radians(BOARD_TILT_DEG))
        pose = look_at_pose(ray * depth, facing, rng.uniform(-math.pi, math.pi))
        pose[:3, 3] -= pose[:3, :3] @ middle  # put the board's middle at ray·depth
        corners = outline @ pose[:3, :3].T + pose[:3, 3]
        px = camera.project(corners)
        if not np.all(np.isfinite(px)):
            continue
        if np.all((px[:, 0] > margin_px) & (px[:, 0] < camera.width - 1 - margin_px)
                  & (px[:, 1] > margin_px) & (px[:, 1] < camera.height - 1 - margin_px)):
            poses.append(pose)
    if len(poses) < n:
        raise ValueError(f"found only {len(poses)} of {n} checkerboard poses in view")
    return poses


def dot_target_poses(
    camera: Camera,
    mirrors: Sequence[Mirror],
    index: int,
    target: DotTarget,
    n: int,
    seed: int,
    *,
    margin_px: float = 3.0,
) -> list[np.ndarray]:
    """n poses of the dot target close to mirror `index`, each seen whole both directly and
    through that mirror (paper Fig. 3(a)), with the two views apart and every dot clear of the
    image border, of the mirror region's edges and of the card's own direct image.

    The card's middle is drawn from the points that are seen directly and through the mirror
    (rejection sampling in a box around the lens); the card faces between the camera and the
    mirror's virtual camera (so both see its face; a random mix of the two directions), tilted
    randomly by up to 15° and turned randomly about its normal.
    """
    rng = np.random.default_rng(seed)
    mirror = mirrors[index]
    labels = assign_pixels(camera, mirrors)
    clearance = distance_transform_edt(labels == index)
    box = rng.uniform([-0.25, -0.25, 0.02], [0.25, 0.25, 0.35], size=(60_000, 3))
    # A centre qualifies if the points 0.6 of a dot's distance from it along ±x, ±y, ±z do too
    # (a cheap screen; _dot_pose_ok checks each pose exactly).
    reach = 0.6 * (np.hypot(target.spacing / 2, target.spacing / 2) + target.radius)
    offsets = np.vstack([np.zeros(3), reach * np.eye(3), -reach * np.eye(3)])

    def qualifies(centres: np.ndarray) -> np.ndarray:
        ok = np.ones(len(centres), dtype=bool)
        for offset in offsets:
            shifted = centres + offset
            ok &= _inside_image(camera, camera.project(shifted), margin_px)
            ok &= _inside_image(camera, project_via(camera, mirror, shifted), margin_px)
            ok &= mirror.plane.signed_distance(shifted) < -CLEAR
        return ok

    candidates = box[qualifies(box)]
    if 0 < len(candidates) < 2000:  # densify: more samples around the few that qualified
        near = candidates[rng.integers(len(candidates), size=50_000)]
        near = near + rng.uniform(-0.01, 0.01, size=near.shape)
        candidates = np.vstack([candidates, near[qualifies(near)]])
    if len(candidates) == 0:
        raise ValueError(f"no point is seen both directly and through mirror {mirror.name!r}")
    virtual = mirror.plane.virtual_centre()
    dots = target.dot_centres()
    x0, x1, y0, y1 = target.extent()
    outline = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)
    focal = 0.5 * (camera.fx + camera.fy)
    poses: list[np.ndarray] = []
    reasons: dict[str, int] = {}
    for _ in range(2000 * n):
        if len(poses) == n:
            break
        centre = candidates[rng.integers(len(candidates))]
        weight = rng.uniform(0.2, 0.8)
        facing = -weight * centre / np.linalg.norm(centre)
        facing += (1.0 - weight) * (virtual - centre) / np.linalg.norm(virtual - centre)
        facing = _random_rotation(rng, math.radians(15.0)) @ facing
        pose = look_at_pose(centre, facing, rng.uniform(-math.pi, math.pi))
        why = _dot_pose_ok(camera, mirrors, index, target, pose, dots, outline, labels,
                           clearance, focal, margin_px)
        reasons[why] = reasons.get(why, 0) + 1
        if not why:
            poses.append(pose)
    if len(poses) < n:
        raise ValueError(
            f"found only {len(poses)} of {n} dot-target poses for mirror {mirror.name!r} "
            f"(rejected: {reasons})"
        )
    return poses


# Two-mirror boards: the board's middle this far (metres) from the mirrors, along the direction
# the two mirrors' adjacent edges look; at least this many of a 24 × 18 grid of its points must
# be seen through each of the two mirrors.
PAIR_DISTANCE = (0.4, 0.8)
PAIR_MIN_POINTS = 30


def adjacent_pairs(mirrors: Sequence[Mirror]) -> list[tuple[int, int]]:
    """Neighbouring mirrors (a, b) of a pyramid: each mirror and the next one around it."""
    n = len(mirrors)
    return [(k, (k + 1) % n) for k in range(n)] if n > 2 else ([(0, 1)] if n == 2 else [])


def pair_board_poses(
    camera: Camera, mirrors: Sequence[Mirror], a: int, b: int, board: PlainBoard, n: int, seed: int
) -> list[np.ndarray]:
    """n poses of a plain board seen through mirrors a and b at once: out along the direction
    where the two mirrors' image regions meet, PAIR_DISTANCE away, facing back with a random tilt
    of up to 25° and a random turn about its normal."""
    from omnitof.sensor.mirrors import viewing_rays

    rng = np.random.default_rng(seed)
    labels = assign_pixels(camera, mirrors)
    rays = viewing_rays(camera, mirrors, labels)
    # The two mirrors' views do not meet (the default pyramid leaves ~24° blind between them):
    # the board spans the gap, its middle between where the two seams' rays reach.
    side_a = (labels == a) & (distance_transform_edt(labels != b) <= 6)
    side_b = (labels == b) & (distance_transform_edt(labels != a) <= 6)
    if not (side_a.any() and side_b.any()):
        raise ValueError(f"mirrors {mirrors[a].name!r} and {mirrors[b].name!r} are not neighbours in the image")
    x0, x1, y0, y1 = board.extent()
    gx, gy = np.meshgrid(np.linspace(x0, x1, 24), np.linspace(y0, y1, 18))
    grid = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    poses: list[np.ndarray] = []
    for _ in range(400 * n):
        if len(poses) == n:
            break
        i = rng.integers(int(side_a.sum()))
        j = rng.integers(int(side_b.sum()))
        reach = rng.uniform(*PAIR_DISTANCE)
        ends = [rays.origins[side][k] + reach * rays.directions[side][k] for side, k in ((side_a, i), (side_b, j))]
        centre = 0.5 * (ends[0] + ends[1])
        out = rays.directions[side_a][i] + rays.directions[side_b][j]
        facing = _random_rotation(rng, math.radians(15.0)) @ (-out / np.linalg.norm(out))
        pose = look_at_pose(centre, facing, rng.uniform(-math.pi, math.pi))
        points = grid @ pose[:3, :3].T + pose[:3, 3]
        counts = []
        for k in (a, b):
            px = project_via(camera, mirrors[k], points)
            ok = _inside_image(camera, px, 2.0)
            rows = np.round(px[ok, 1]).astype(int)
            cols = np.round(px[ok, 0]).astype(int)
            counts.append(int(np.sum(labels[rows, cols] == k)))
        if min(counts) >= PAIR_MIN_POINTS:
            poses.append(pose)
    if len(poses) < n:
        raise ValueError(f"found only {len(poses)} of {n} board poses seen through mirrors "
                         f"{mirrors[a].name!r} and {mirrors[b].name!r}")
    return poses


def _inside_image(camera: Camera, pixels: np.ndarray, margin_px: float) -> np.ndarray:
    h, w = camera.shape
    with np.errstate(invalid="ignore"):
        return (
            (pixels[:, 0] > margin_px) & (pixels[:, 0] < w - 1 - margin_px)
            & (pixels[:, 1] > margin_px) & (pixels[:, 1] < h - 1 - margin_px)
        )


def _dot_pose_ok(camera, mirrors, index, target, pose, dots, outline, labels, clearance, focal,
                 margin_px) -> str:
    """Why the pose is unusable ("" if it is usable)."""
    mirror = mirrors[index]
    rotation, centre = pose[:3, :3], pose[:3, 3]
    world_dots = dots @ rotation.T + centre
    corners = outline @ rotation.T + centre
    # The card stays in front of its mirror, out of the pyramid's solid (behind every face
    # plane) and at least 3 cm from the lens.
    if np.any(mirror.plane.signed_distance(corners) > -0.001):
        return "behind"
    behind = np.all([m.plane.signed_distance(corners) > -0.001 for m in mirrors], axis=0)
    if np.any(behind):
        return "pyramid"
    if np.min(np.linalg.norm(corners, axis=1)) < 0.03:
        return "near lens"
    direct = camera.project(world_dots)
    mirrored = project_via(camera, mirror, world_dots)
    both = np.vstack([direct, mirrored])
    if not np.all(np.isfinite(both)):
        return "nan"
    h, w = camera.shape
    if not np.all((both[:, 0] > margin_px) & (both[:, 0] < w - 1 - margin_px)
                  & (both[:, 1] > margin_px) & (both[:, 1] < h - 1 - margin_px)):
        return "border"
    # Direct lines of sight must not pass a mirror first (the card occludes the mirror).
    for m in mirrors:
        hits = m.intersect(np.zeros_like(world_dots), world_dots)
        if np.any(hits.hit & (hits.distances < np.linalg.norm(world_dots, axis=1))):
            return "direct blocked"
    # Dot sizes in pixels: the mirrored view is farther; keep its dots >= 1.5 px in radius.
    images = mirror.plane.reflect_points(world_dots)
    r_mirror = focal * target.radius / np.linalg.norm(images, axis=1)
    r_direct = focal * target.radius / np.linalg.norm(world_dots, axis=1)
    if r_mirror.min() < 1.5:
        return "small"
    # Mirrored dots inside the mirror's region, clear of its edges (mixed pixels there).
    rows = np.round(mirrored[:, 1]).astype(int)
    cols = np.round(mirrored[:, 0]).astype(int)
    if np.any(labels[rows, cols] != index) or np.any(clearance[rows, cols] < r_mirror + 3.0):
        return "region"
    # The mirrored view must not fall on the card's own direct image (nor touch it), and the
    # real ray to each mirrored dot must not be blocked by the card on its way to the mirror.
    outline_px = camera.project(corners)
    if not np.all(np.isfinite(outline_px)):
        return "nan outline"
    contour = outline_px.astype(np.float32).reshape(-1, 1, 2)
    for (u, v), r in zip(mirrored, r_mirror):
        if cv2.pointPolygonTest(contour, (float(u), float(v)), True) > -(r + 3.0):
            return "card overlap"
    # Dots well apart from each other in the image.
    radii = np.concatenate([r_direct, r_mirror])
    gaps = np.linalg.norm(both[:, None] - both[None], axis=2)
    need = radii[:, None] + radii[None] + 3.0
    np.fill_diagonal(gaps, np.inf)
    return "" if np.all(gaps > need) else "dots touch"


# --- image sets ----------------------------------------------------------------------------


def planned_checkerboard_poses(
    camera: Camera, board: Checkerboard, n: int, seed: int, *, candidates_per_board: int = PLAN_CANDIDATES,
    taken: Sequence[np.ndarray] = (),
) -> list[np.ndarray]:
    """n checkerboard poses chosen from n·candidates_per_board feasible ones
    (`checkerboard_poses`) for the smallest predicted uncertainty of the calibrated projection
    (`calibration.planning`), counting what the boards already `taken` (their poses
    camera_T_board) tell. The camera's intrinsics enter only the prediction, so nominal ones
    (a data sheet's) do: 3 % off in focal length, 2 px in the principal point and 20 % in the
    distortion, they plan the principal point nearly as well (predicted σ 0.049–0.051 against
    0.047–0.049 px, seeds 0–3) but the image's edges less well; a second plan from a first
    calibration of the boards taken repairs that (BENCHMARKS.md)."""
    from omnitof.calibration.planning import N_INTRINSICS, board_information, plan_boards, projection_weight

    points = board.object_points()
    pool = checkerboard_poses(camera, board, n * candidates_per_board, seed)
    informations = [board_information(camera, points, pose) for pose in pool]
    prior = sum((board_information(camera, points, pose) for pose in taken), np.zeros((N_INTRINSICS,) * 2))
    return [pool[i] for i in plan_boards(informations, n, projection_weight(camera), prior=prior)]


def render_checkerboard_images(
    camera: Camera,
    n: int,
    seed: int,
    *,
    board: Checkerboard = Checkerboard(),
    sensor: SensorNoise | None = None,
    room: Room = Room(),
    planned: bool = True,
) -> tuple[list, list[np.ndarray]]:
    """(images, poses): n noisy amplitude/distance images (AmplitudeImage, named board_00, ...)
    of a checkerboard seen by the camera without mirrors, and the boards' true poses.
    planned: the poses of `planned_checkerboard_poses`; else n random ones."""
    if planned:
        poses = planned_checkerboard_poses(camera, board, n, seed)
    else:
        poses = checkerboard_poses(camera, board, n, seed)
    return render_board_views(camera, poses, seed, board=board, sensor=sensor, room=room), poses


def render_board_views(
    camera: Camera,
    poses: Sequence[np.ndarray],
    seed: int,
    *,
    board: Checkerboard = Checkerboard(),
    sensor: SensorNoise | None = None,
    room: Room = Room(),
    first_index: int = 0,
) -> list:
    """Noisy amplitude/distance images (AmplitudeImage, named board_<first_index + k>) of a
    checkerboard at the given poses (camera_T_board), seen without mirrors."""
    images = []
    for k, pose in enumerate(poses):
        i = first_index + k
        frame, _ = render_target(camera, board, pose, (), rng=np.random.default_rng([seed, i]),
                                 sensor=sensor, room=room)
        images.append(AmplitudeImage(f"board_{i:02d}", frame.amplitude, frame.distance))
    return images


def render_dot_images(
    camera: Camera,
    mirrors: Sequence[Mirror],
    placements: int,
    seed: int,
    *,
    target: DotTarget = DotTarget(),
    sensor: SensorNoise | None = None,
    room: Room = Room(),
    only: Sequence[int] | None = None,
) -> tuple[list, list[tuple[int, np.ndarray]]]:
    """`placements` images of the dot target per mirror (named <mirror>_00, ...), noisy, and
    their (mirror index, true pose)."""
    images, truth = [], []
    for k, mirror in enumerate(mirrors):
        if only is not None and k not in only:
            continue
        poses = dot_target_poses(camera, mirrors, k, target, placements, seed * 1000 + k)
        for i, pose in enumerate(poses):
            frame, _ = render_target(camera, target, pose, mirrors,
                                     rng=np.random.default_rng([seed, k, i]), sensor=sensor, room=room)
            images.append(AmplitudeImage(f"{mirror.name}_{i:02d}", frame.amplitude, frame.distance))
            truth.append((k, pose))
    return images, truth


def render_pair_images(
    camera: Camera,
    mirrors: Sequence[Mirror],
    per_pair: int,
    seed: int,
    *,
    board: PlainBoard = PlainBoard(),
    sensor: SensorNoise | None = None,
    room: Room = Room(),
) -> tuple[list, list[tuple[tuple[int, int], np.ndarray]]]:
    """`per_pair` images of a plain board seen through each two neighbouring mirrors (named
    pair_<a>-<b>_00, ...), noisy, and their ((a, b), true pose)."""
    images, truth = [], []
    for a, b in adjacent_pairs(mirrors):
        poses = pair_board_poses(camera, mirrors, a, b, board, per_pair, seed * 1000 + 100 + a)
        for i, pose in enumerate(poses):
            frame, _ = render_target(camera, board, pose, mirrors,
                                     rng=np.random.default_rng([seed, 100 + a, i]), sensor=sensor, room=room)
            name = f"pair_{mirrors[a].name}-{mirrors[b].name}_{i:02d}"
            images.append(AmplitudeImage(name, frame.amplitude, frame.distance))
            truth.append(((a, b), pose))
    return images, truth


def room_of_world(name_or_path: str | Path, camera_height: float = 0.40) -> Room:
    """The Room of a simulated world (its ceiling height, ambient light, floor and ceiling
    albedos; the walls 2.5 m away, as the targets are centimetres from the lens)."""
    from omnitof.sim.worlds import load_world

    world = load_world(name_or_path)
    return Room(
        floor=-camera_height,
        ceiling=world.ceiling_height - camera_height,
        floor_albedo=world.material_of(world.floor_material).albedo,
        ceiling_albedo=world.material_of(world.ceiling_material).albedo,
        ambient=world.ambient,
    )


def render_calibration_images(
    out_dir: str | Path,
    *,
    camera: Camera | None = None,
    mirrors: Sequence[Mirror] | None = None,
    world: str | Path | None = None,
    seed: int = 0,
    placements: int = 8,
    boards: int = 15,
    target: DotTarget = DotTarget(),
    board: Checkerboard = Checkerboard(),
    sensor: SensorNoise | None = None,
    pair_boards: int = 2,
    planned_boards: bool = True,
) -> dict[str, Any]:
    """Render a calibration data set into out_dir and return a summary.

    Writes out_dir/intrinsics/board_XX.{png,npz} (checkerboards, no mirrors),
    out_dir/mirrors/<mirror>_XX.{png,npz} (the dot target at every mirror),
    out_dir/pairs/pair_<a>-<b>_XX.{png,npz} (a plain board seen through each two neighbouring
    mirrors, `pair_boards` per pair, for the joint refinement; none if 0), and
    out_dir/truth.yaml, the true calibration (`Calibration.from_rig`) to compare with. PNGs
    hold the amplitude as 16-bit sample units; the .npz files hold `amplitude` and `distance`
    (float32, metres).
    """
    from omnitof.calibration import Calibration, save_calibration
    from omnitof.sensor.design import default_rig
    from omnitof.sensor.rig import Rig

    if camera is None or mirrors is None:
        default = default_rig()
        camera = camera or default.camera
        mirrors = mirrors if mirrors is not None else default.mirrors
    room = room_of_world(world) if world is not None else Room()
    out = Path(out_dir)
    (out / "intrinsics").mkdir(parents=True, exist_ok=True)
    (out / "mirrors").mkdir(parents=True, exist_ok=True)
    boards_images, _ = render_checkerboard_images(camera, boards, seed, board=board, sensor=sensor, room=room,
                                                  planned=planned_boards)
    dot_images, _ = render_dot_images(camera, mirrors, placements, seed, target=target, sensor=sensor, room=room)
    pair_images: list = []
    if pair_boards > 0:
        (out / "pairs").mkdir(parents=True, exist_ok=True)
        pair_images, _ = render_pair_images(camera, mirrors, pair_boards, seed, sensor=sensor, room=room)
    written = []
    for folder, images in (("intrinsics", boards_images), ("mirrors", dot_images), ("pairs", pair_images)):
        for image in images:
            base = out / folder / image.name
            png = np.clip(np.round(image.amplitude), 0, 65535).astype(np.uint16)
            ok, data = cv2.imencode(".png", png)
            if not ok:
                raise OSError(f"cannot encode {base}.png")
            with atomic_write(base.with_suffix(".png"), "wb") as handle:
                handle.write(data.tobytes())
            with atomic_write(base.with_suffix(".npz"), "wb") as handle:
                np.savez_compressed(handle, amplitude=image.amplitude, distance=image.distance)
            written.append(base)
    truth = Calibration.from_rig(Rig.from_mirrors(camera, mirrors))
    truth.provenance = {
        "source": "simulated rig (true geometry)",
        "seed": seed,
        "world": str(world) if world is not None else "default room",
        "dot_target": {"spacing": target.spacing, "radius": target.radius},
        "checkerboard": {"cols": board.cols, "rows": board.rows, "square": board.square},
    }
    save_calibration(truth, out / "truth.yaml")
    return {
        "out": out,
        "boards": len(boards_images),
        "dot_images": len(dot_images),
        "pair_images": len(pair_images),
        "mirrors": [m.name for m in mirrors],
        "truth": out / "truth.yaml",
    }
