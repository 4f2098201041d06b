"""Flat walls at known distances: the targets of the distance calibration (issue 16).

The robot stands at measured distances from a flat matte wall and turns so that each mirror
faces it in turn; the camera takes a few frames per position. The wall's plane in the camera
frame follows from the measured distance and the rig's geometry (the calibration's mirrors
give every pixel's true path to it, `distance.samples_from_plane`), so every lit pixel is a
sample of the systematic distance error at its distance and amplitude. One wall spans a range
of path lengths (the mirror's view meets it at up to 45° off its normal), but near the camera
that range is short (0.6–0.8 m for a wall at 0.5 m), and a B-spline left without samples
between two positions swings by centimetres there. So each mirror's wall stands a quarter of
the step further than the previous mirror's (0.5, 0.625, 0.75, 0.875 m, then 1.0, ...): the
four views together cover every path length from 0.6 m on.

The frames of one position are averaged pixel by pixel before the fit: the systematic error
repeats from frame to frame, the sensor's noise does not (one frame of a dark wall at 4 m:
σ ≈ 25 mm per pixel, which left the per-pixel offsets worse than none when single frames were
fitted; BENCHMARKS.md, "Calibration").

In the simulator (`render_wall_views`) the wall is a `targets.PlainBoard` placed by the rig's
design, rendered with the sensor's noise and systematic errors (`sensor.tof_errors`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from omnitof.calibration.distance import DistanceCorrection, samples_from_plane
from omnitof.errors import OmnitofWarning, dump_yaml, load_yaml, yaml_problem

# Wall distances (metres, horizontal, from the centre of the mirror's view): the scans' range
# (ScanSettings.max_range 7 m; oblique rays reach the 7.49 m unambiguous range beyond 5 m).
WALL_DISTANCES = tuple(np.round(np.arange(0.5, 6.51, 0.5), 3))
# Matte reflectances, cycled over distances and mirrors so that each distance is seen dark and
# bright (the amplitude term is told apart from the wiggling only so).
WALL_REFLECTANCES = (0.2, 0.5, 0.85)
# Frames averaged per position: σ/2 per pixel.
FRAMES_PER_POSITION = 4
# How far off square (degrees) a recorded wall's turn is searched (`recorded_view`).
MAX_WALL_TURN_DEG = 5.0
# Fewer lit pixels than this (a dark wall far off) fit no turn: the wall is taken as square.
MIN_TURN_PIXELS = 2000
# Pixels darker than this (sample units) are left out, as the scan extraction leaves them out
# (`ScanSettings.min_amplitude`).
MIN_AMPLITUDE = 40.0
# The measured distances a correction must span not to warn (metres): one period of the
# wiggling (a quarter of the 5 m unambiguous range, `distance.DISTANCE_KNOT_SPACING`). Beyond
# the fitted span the correction holds its end values, which is no correction of a wiggle.
MIN_FITTED_SPAN = 1.25


@dataclass
class WallView:
    """One wall position, its frames averaged: the mean distance and amplitude (H, W), the
    wall's plane {x : normal·x = c} in the camera frame, the mirror facing it, and for a
    recorded wall the turn off square fitted to it (degrees; None where none was fitted)."""

    name: str
    distance: np.ndarray
    amplitude: np.ndarray
    normal: np.ndarray
    c: float
    mirror: int
    turn_deg: float | None = None


def view_axes(camera: Any, mirrors: Sequence[Any], labels: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per mirror, (where its view's central rays leave the mirror on average, the view's mean
    horizontal direction), camera frame."""
    from omnitof.sensor.mirrors import viewing_rays

    return _axes(viewing_rays(camera, mirrors, labels), len(mirrors))


def _axes(rays: Any, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """`view_axes` from the pixels' viewing rays (`mirrors.viewing_rays`)."""
    out = []
    for k in range(count):
        sel = rays.labels == k
        direction = np.nanmean(rays.directions[sel], axis=0)
        direction[2] = 0.0
        out.append((np.nanmean(rays.origins[sel], axis=0), direction / np.linalg.norm(direction)))
    return out


def wall_pose(axis: tuple[np.ndarray, np.ndarray], distance: float) -> np.ndarray:
    """camera_T_wall of a wall across a mirror's view axis (`view_axes`) at `distance` metres
    horizontally from the mirror, facing back along the axis."""
    from omnitof.calibration.targets import look_at_pose

    origin, direction = axis
    return look_at_pose(origin + distance * direction, -direction, 0.0)


def average_frames(distances: np.ndarray, amplitudes: np.ndarray,
                   saturated: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixelwise mean of (N, H, W) frames; pixels that any frame lost (NaN) or saturated, or
    whose frames disagree by more than 0.5 m (a wrapped phase), are NaN."""
    d = np.asarray(distances, dtype=np.float64)
    a = np.asarray(amplitudes, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        mean = d.mean(axis=0)
        spread = d.max(axis=0) - d.min(axis=0)
    mean[~(spread < 0.5)] = np.nan
    if saturated is not None:
        mean[np.any(saturated, axis=0)] = np.nan
    return mean, a.mean(axis=0)


@dataclass
class WallRecording:
    """The frames of one wall position as a camera records them: the wall facing mirror
    `mirror` (roughly square to its view, `view_axes`), its shortest horizontal distance from the
    camera's optical centre `distance` metres; `distances` and `amplitudes` (N, H, W),
    `saturated` (N, H, W) or None."""

    name: str
    mirror: int
    distance: float
    distances: np.ndarray
    amplitudes: np.ndarray
    saturated: np.ndarray | None = None


def render_wall_recordings(
    camera: Any,
    mirrors: Sequence[Any],
    seed: int,
    *,
    sensor: Any = None,
    distances: Sequence[float] = WALL_DISTANCES,
    reflectances: Sequence[float] = WALL_REFLECTANCES,
    frames: int = FRAMES_PER_POSITION,
    turns_deg: Sequence[float] = (0.0,),
) -> list[tuple[WallRecording, np.ndarray]]:
    """A matte wall 12 m × 6 m facing each mirror at each distance (mirror k's wall k/len(mirrors)
    of the step further, see the module docstring), `frames` noisy frames each (simulator; the
    wall placed by the rig's design, turned about its centre and the camera's axis by the next of
    `turns_deg` in turn, as a wall set up by hand is). Returns (the recording, camera_T_wall) per
    position; the recording's distance is the wall's shortest from the optical centre."""
    from omnitof.calibration.targets import WALL_SUB_RAYS, PlainBoard, Room, render_target_frames
    from omnitof.sensor.mirrors import assign_pixels

    axes = view_axes(camera, mirrors, assign_pixels(camera, mirrors))
    room = Room(half_width=12.0)  # the default room's walls (2.5 m) would hide the far walls
    step = float(np.median(np.diff(distances))) if len(distances) > 1 else 0.0
    out = []
    for i, base in enumerate(distances):
        for k, mirror in enumerate(mirrors):
            albedo = reflectances[(i + k) % len(reflectances)]
            dist = float(base) + step * k / len(mirrors)
            pose = wall_pose(axes[k], dist)
            turn = math.radians(turns_deg[(i * len(mirrors) + k) % len(turns_deg)])
            pose[:3, :3] = _turn(turn) @ pose[:3, :3]
            wall = PlainBoard(width=12.0, height=6.0, reflectance=albedo)
            rngs = [np.random.default_rng([seed, 0x3A11, i, k, f]) for f in range(frames)]
            shots = render_target_frames(camera, wall, pose, mirrors, rngs=rngs, sensor=sensor, room=room,
                                         sub_rays=WALL_SUB_RAYS)
            recording = WallRecording(
                f"wall {dist:.2f} m, {mirror.name}, albedo {albedo}", k,
                -float(pose[:3, 2] @ pose[:3, 3]),  # the shortest distance from the optical centre
                np.stack([s.distance for s in shots]), np.stack([s.amplitude for s in shots]),
                np.stack([s.saturated for s in shots]),
            )
            out.append((recording, pose))
    return out


def render_wall_views(camera: Any, mirrors: Sequence[Any], seed: int, **settings: Any) -> list[WallView]:
    """`render_wall_recordings`, each position's frames averaged, with the wall's exact plane
    (the simulator knows it)."""
    views = []
    for rec, pose in render_wall_recordings(camera, mirrors, seed, **settings):
        d, a = average_frames(rec.distances, rec.amplitudes, rec.saturated)
        normal = pose[:3, 2].copy()
        views.append(WallView(rec.name, d, a, normal, float(normal @ pose[:3, 3]), rec.mirror))
    return views


def recorded_view(calibration: Any, recording: WallRecording, *, fit_turn: bool = True,
                  correction: DistanceCorrection | None = None, rays: Any = None) -> WallView:
    """A recorded wall position as a WallView: its frames averaged, its plane from the
    calibration's geometry and the recorded distance (the wall's shortest from the optical
    centre): {x : n·x = −distance}, n = −R(ψ)·u, u the mirror's mean horizontal view direction
    (`view_axes` of the calibrated planes) and R(ψ) a turn by ψ about the camera's axis.

    Nobody sets a wall square to a mirror's view to a tenth of a degree, and a turn of 1° moves
    the true paths at the edges of a view ±45° wide by about ±5 cm at 3 m, far more than the
    errors to be fitted. So, with `fit_turn`, ψ is fitted (within ±MAX_WALL_TURN_DEG) to the
    frames themselves (`_fitted_turn`): the wall's points, each pixel's measured path along its
    reflected ray, must lie on the plane. The camera's own error hardly pulls it: a turn tilts
    the points' offsets from the plane across the wall (odd in the bearing), the wiggling and
    amplitude terms follow the path length (even). The distance is what it is measured to be:
    1 mm off shifts the fitted curve by 1 mm. With `correction`, the turn is fitted to the
    distances it corrects (`fit_from_recordings`); the view keeps the measured ones. `rays`: the
    calibration's viewing rays (`calibration_rays`), when several walls are viewed."""
    rays = calibration_rays(calibration) if rays is None else rays
    _, direction = _axes(rays, len(calibration.planes))[recording.mirror]
    d, a = average_frames(recording.distances, recording.amplitudes, recording.saturated)
    c = -float(recording.distance)
    if not fit_turn:
        return WallView(recording.name, d, a, -direction, c, recording.mirror)
    seen = d
    if correction is not None:
        seen = correction.correct(d.reshape(-1), a.reshape(-1), np.arange(d.size)).reshape(d.shape)
    turn = _fitted_turn(rays, recording.mirror, direction, recording.distance, seen, a, recording.name)
    if turn is None:
        return WallView(recording.name, d, a, -direction, c, recording.mirror)
    return WallView(recording.name, d, a, -(_turn(turn) @ direction), c, recording.mirror, math.degrees(turn))


def calibration_rays(calibration: Any) -> Any:
    """Every pixel's viewing ray through its own mirror in the calibration (`mirrors.viewing_rays`)."""
    from omnitof.sensor.mirrors import viewing_rays

    return viewing_rays(calibration.camera, [_PlaneMirror(p) for p in calibration.planes], calibration.labels)


def fit_from_recordings(calibration: Any, recordings: Sequence[WallRecording],
                        rounds: int = 2) -> tuple[DistanceCorrection, list[WallView]]:
    """The DistanceCorrection fitted to recorded walls (`recorded_view`), and the views: the
    walls' turns fitted to the measured distances first, then `rounds` times again to the
    distances the correction of the round before corrects (near walls the camera's own error,
    centimetres, tilts the fitted turn by up to 0.7° until it is corrected)."""
    rays = calibration_rays(calibration)
    views = [recorded_view(calibration, r, rays=rays) for r in recordings]
    correction = fit_from_walls(calibration, views)
    for _ in range(rounds):
        views = [recorded_view(calibration, r, correction=correction, rays=rays) for r in recordings]
        correction = fit_from_walls(calibration, views)
    lo, hi = correction.fitted_span
    if hi - lo < MIN_FITTED_SPAN:
        warnings.warn(OmnitofWarning(
            f"the distance correction is fitted to measured distances {lo:.2f}–{hi:.2f} m only and holds its end "
            f"values beyond them: record walls spread over at least {MIN_FITTED_SPAN:g} m (the wiggling repeats "
            f"every {MIN_FITTED_SPAN:g} m), out to the range the scans use"), stacklevel=2)
    return correction, views


def _fitted_turn(rays: Any, mirror: int, direction: np.ndarray, distance: float,
                 measured: np.ndarray, amplitude: np.ndarray, name: str = "") -> float | None:
    """The turn ψ (rad) about the camera's axis that puts the wall's measured points (each lit
    pixel of `mirror`'s view at its measured path along its viewing ray, `rays`) on the plane
    {x : −R(ψ)·u·x = −distance}, u = `direction`: the least trimmed squares of the points'
    offsets from it over a grid of 0.05°, then refined (scipy's bounded scalar search). Points
    more than 0.1 m off the best grid plane (floor, ceiling, mixed pixels) are left out. None
    where fewer than MIN_TURN_PIXELS pixels are lit. Raises CalibrationError (naming `name`)
    where most points lie off every such plane: a mistyped distance, or another mirror's wall."""
    from scipy.optimize import minimize_scalar

    from omnitof.calibration import CalibrationError

    with np.errstate(invalid="ignore"):
        ok = (rays.labels == mirror) & np.isfinite(measured) & (amplitude >= MIN_AMPLITUDE)
    o, v = rays.origins[ok], rays.directions[ok]
    points = o + (measured[ok] - np.linalg.norm(o, axis=1))[:, None] * v
    if len(points) < MIN_TURN_PIXELS:
        return None
    xy = points[:, :2]

    def offsets(turn: float) -> np.ndarray:
        n = _turn(turn) @ direction
        return xy @ n[:2] - distance

    def trimmed(turn: float, keep: np.ndarray | None = None) -> float:
        r = offsets(turn) if keep is None else offsets(turn)[keep]
        return float(np.mean(np.minimum(np.abs(r), 0.1) ** 2))

    bound = math.radians(MAX_WALL_TURN_DEG)
    grid = np.arange(-bound, bound + 1e-12, math.radians(0.05))
    start = float(grid[np.argmin([trimmed(t) for t in grid])])
    keep = np.abs(offsets(start)) < 0.1
    if keep.mean() < 0.5:
        raise CalibrationError(
            f"{name}: most of the wall's points lie more than 0.1 m off a wall {distance:.3f} m away facing "
            f"this mirror (their median distance is {float(np.median(xy @ direction[:2])):.2f} m): check the "
            "distance and the mirror"
        )
    step = math.radians(0.05)
    best = minimize_scalar(lambda t: trimmed(t, keep), bounds=(start - step, start + step), method="bounded",
                           options={"xatol": 1e-5})
    return float(best.x)


def _turn(angle: float) -> np.ndarray:
    """Rotation by `angle` (rad) about the camera's optical axis (z)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class _PlaneMirror:
    """A calibrated mirror plane where the rig's geometry functions expect a mirror."""

    plane: Any


def wall_samples(calibration: Any, views: Sequence[WallView]) -> tuple[np.ndarray, ...]:
    """(measured, true path, amplitude, flat pixel) of every wall pixel of its own mirror,
    the true paths from the calibration's geometry."""
    out = []
    for view in views:
        labels = np.where(calibration.labels == view.mirror, view.mirror, -1)
        amp = np.where(view.amplitude >= MIN_AMPLITUDE, view.amplitude, np.nan)
        out.append(samples_from_plane(calibration.camera, calibration.planes, labels, view.distance, amp,
                                      view.normal, view.c))
    return tuple(np.concatenate(x) for x in zip(*out))


def fit_from_walls(calibration: Any, views: Sequence[WallView]) -> DistanceCorrection:
    """The DistanceCorrection (wiggling + amplitude + per-pixel terms) fitted to wall views."""
    m, t, a, p = wall_samples(calibration, views)
    return DistanceCorrection.fit(m, t, a, p, calibration.camera.shape)


# --- recorded walls: the file `omnitof calibrate distance` reads ------------------------------

def read_wall_recordings(path: str | Path, calibration: Any) -> list[WallRecording]:
    """The wall positions listed in a walls file (its form: `omnitof calibrate distance --help`),
    their frames loaded.
    Raises CalibrationError naming the file and the entry for anything missing or malformed."""
    from omnitof.calibration import CalibrationError
    from omnitof.calibration.images import load_images

    path = Path(path)
    try:
        data = load_yaml(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise CalibrationError(f"cannot read the walls file: {err.strerror or err}", path) from None
    except yaml.YAMLError as err:
        problem, line = yaml_problem(err)
        raise CalibrationError(problem, path, line) from None
    entries = data.get("walls") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not entries:
        raise CalibrationError("expected a list 'walls:' of positions, each with frames, mirror and distance", path)
    recordings = []
    for i, entry in enumerate(entries):
        where = f"walls[{i}]"
        if not isinstance(entry, dict):
            raise CalibrationError(f"{where}: expected a mapping with frames, mirror and distance", path)
        missing = [k for k in ("frames", "mirror", "distance") if k not in entry]
        if missing:
            raise CalibrationError(f"{where}: missing {', '.join(missing)}", path)
        name = str(entry["mirror"])
        if name not in calibration.names:
            raise CalibrationError(f"{where}.mirror: {name!r} is not a mirror of the calibration "
                                   f"({', '.join(calibration.names)})", path)
        distance = entry["distance"]
        if isinstance(distance, bool) or not isinstance(distance, (int, float)) or not 0.05 <= distance <= 50:
            raise CalibrationError(f"{where}.distance: expected metres between 0.05 and 50, got {distance!r}", path)
        frames_path = path.parent / str(entry["frames"])
        if not frames_path.exists():
            raise CalibrationError(f"{where}.frames: no such file or folder {frames_path}", path)
        images = load_images([frames_path])
        flat = [im.name for im in images if im.distance is None]
        if flat:
            raise CalibrationError(f"{where}.frames: {flat[0]} has no distance image (a ToF frame is needed)", path)
        if len({im.amplitude.shape for im in images}) != 1 or images[0].amplitude.shape != calibration.camera.shape:
            raise CalibrationError(f"{where}.frames: the frames must be {calibration.camera.shape} images "
                                   "like the calibration's camera", path)
        recordings.append(WallRecording(
            f"{path}: {where} ({frames_path.name}, {name}, {float(distance):.3f} m)", calibration.index_of(name),
            float(distance),
            np.stack([im.distance for im in images]), np.stack([im.amplitude for im in images]),
        ))
    return recordings


def write_wall_recordings(folder: str | Path, recordings: Sequence[WallRecording], names: Sequence[str]) -> Path:
    """Write recordings as a walls file would list them: folder/walls.yaml and one folder of
    .npz frames per position (for `omnitof calibrate distance`); `names` are the mirrors'."""
    from omnitof.io.atomic import atomic_write

    folder = Path(folder)
    entries = []
    for i, rec in enumerate(recordings):
        sub = f"wall_{i:02d}_{names[rec.mirror]}"
        (folder / sub).mkdir(parents=True, exist_ok=True)
        for f, (d, a) in enumerate(zip(rec.distances, rec.amplitudes)):
            if rec.saturated is not None:
                d = np.where(rec.saturated[f], np.nan, d)
            with atomic_write(folder / sub / f"frame_{f:02d}.npz", "wb") as handle:
                np.savez_compressed(handle, amplitude=a.astype(np.float32), distance=d.astype(np.float32))
        entries.append({"frames": sub, "mirror": names[rec.mirror], "distance": round(rec.distance, 4)})
    out = folder / "walls.yaml"
    with atomic_write(out) as handle:
        handle.write("# Wall positions for `omnitof calibrate distance` (see docs/guide/calibration.md).\n")
        dump_yaml({"walls": entries}, handle, sort_keys=False)
    return out
