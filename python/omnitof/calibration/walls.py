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

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from omnitof.calibration.distance import DistanceCorrection, samples_from_plane

# Wall distances (metres, horizontal, from the centre of the mirror's view): the scans' range
# (ScanSettings.max_range 7 m; oblique rays reach the 7.49 m unambiguous range beyond 5 m).
WALL_DISTANCES = tuple(np.round(np.arange(0.5, 6.51, 0.5), 3))
# Matte reflectances, cycled over distances and mirrors so that each distance is seen dark and
# bright (the amplitude term is told apart from the wiggling only so).
WALL_REFLECTANCES = (0.2, 0.5, 0.85)
# Frames averaged per position: σ/2 per pixel.
FRAMES_PER_POSITION = 4
# Pixels darker than this (sample units) are left out, as the scan extraction leaves them out
# (`ScanSettings.min_amplitude`).
MIN_AMPLITUDE = 40.0


@dataclass
class WallView:
    """One wall position, its frames averaged: the mean distance and amplitude (H, W), the
    wall's plane {x : normal·x = c} in the camera frame, and the mirror facing it."""

    name: str
    distance: np.ndarray
    amplitude: np.ndarray
    normal: np.ndarray
    c: float
    mirror: int


def view_axes(camera: Any, mirrors: Sequence[Any], labels: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per mirror, (where its view's central rays leave the mirror on average, the view's mean
    horizontal direction), camera frame."""
    from omnitof.sensor.mirrors import viewing_rays

    rays = viewing_rays(camera, mirrors, labels)
    out = []
    for k in range(len(mirrors)):
        sel = labels == k
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
    """The frames of one wall position as a camera records them: the wall square to mirror
    `mirror`'s view (`view_axes`), `distance` metres horizontally from the camera's optical
    centre; `distances` and `amplitudes` (N, H, W), `saturated` (N, H, W) or None."""

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
) -> list[tuple[WallRecording, np.ndarray]]:
    """A matte wall 12 m × 6 m facing each mirror at each distance (mirror k's wall k/len(mirrors)
    of the step further, see the module docstring), `frames` noisy frames each (simulator; the
    wall placed by the rig's design). Returns (the recording, camera_T_wall) per position."""
    from omnitof.calibration.targets import PlainBoard, Room, render_target_frames
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
            wall = PlainBoard(width=12.0, height=6.0, reflectance=albedo)
            rngs = [np.random.default_rng([seed, 0x3A11, i, k, f]) for f in range(frames)]
            shots = render_target_frames(camera, wall, pose, mirrors, rngs=rngs, sensor=sensor, room=room)
            origin, direction = axes[k]
            recording = WallRecording(
                f"wall {dist:.2f} m, {mirror.name}, albedo {albedo}", k,
                float(direction[:2] @ origin[:2] + dist),  # from the optical centre, not the mirror
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


def recorded_view(calibration: Any, recording: WallRecording) -> WallView:
    """A recorded wall position as a WallView: its frames averaged, its plane from the
    calibration's geometry. The wall stands square to the mirror's mean horizontal view
    direction (`view_axes` of the calibrated planes) at the recorded distance from the optical
    centre: {x : −u·x = −distance}, u that direction, the plane the simulator puts it in. A wall
    turned by 1° off square lengthens the paths by 0.015 %; a distance measured 1 mm off shifts
    the fitted curve by 1 mm."""
    axes = view_axes(calibration.camera, [_PlaneMirror(p) for p in calibration.planes], calibration.labels)
    _, direction = axes[recording.mirror]
    d, a = average_frames(recording.distances, recording.amplitudes, recording.saturated)
    return WallView(recording.name, d, a, -direction, -float(recording.distance), recording.mirror)


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
        data = yaml.safe_load(path.read_text())
    except OSError as err:
        raise CalibrationError(f"cannot read the walls file: {err.strerror or err}", path) from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        raise CalibrationError(f"not valid YAML: {getattr(err, 'problem', err)}", path,
                               None if mark is None else mark.line + 1) from None
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
            f"{frames_path.name}, {name}, {float(distance):.3f} m", calibration.index_of(name), float(distance),
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
        yaml.safe_dump({"walls": entries}, handle, sort_keys=False)
    return out
