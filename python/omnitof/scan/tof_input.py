"""From ToF frames (simulated, or read from a ROS bag) to 360° range scans for the filter, and
the 3D points of some frames for the voxel map: the glue between the sensor and SLAM.

The rig's geometry comes from a calibration file (`omnitof calibrate`, `calibration.
load_calibration`) or, for a simulated bag, from the true rig in its sidecar (`sim.sequence.
rig_sidecar`); the calibration wins when both are there. Frames are streamed in batches, so a
long bag never sits in memory; only the scans (360 floats per frame) and the kept clouds do.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import InputError, OmnitofWarning
from omnitof.scan.extract import ScanExtractor, ScanSettings, scans_from_frames
from omnitof.types import ScanSequence


class ToFInputWarning(OmnitofWarning):
    """Something about ToF input the user should know (e.g. no calibration file was given)."""


@dataclass
class ToFScans:
    """Scans of every frame, and the robot-frame 3D points of every `cloud_every`-th frame.

    scans: the ScanSequence (360 bearings, sensor pose (0, 0, 0), odometry, ground truth if
    known). cloud_frames: (K,) indices of the frames whose points were kept; clouds: K arrays
    (M_k, 6): ray origin on the mirror (x, y, z) and end point (x, y, z), robot frame, metres.
    """

    scans: ScanSequence
    extractor: ScanExtractor
    cloud_frames: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    clouds: list[np.ndarray] = field(default_factory=list)
    rig_source: str = ""
    multipath_rule: str = ""


class _Corrected:
    """A frame whose distances the extractor corrected already (`ScanExtractor.corrected_distances`);
    every other attribute is the frame's own."""

    distance_corrected = True

    def __init__(self, frame: Any, distance: np.ndarray) -> None:
        self._frame, self.distance = frame, distance

    def __getattr__(self, name: str) -> Any:
        return getattr(self._frame, name)


class _CloudTap:
    """Passes frames through and keeps the rays of every `every`-th one, or with `keyframes`
    (linear m, angular rad) of each frame after which the odometry moved more than `linear` or
    turned more than `angular` since the last one kept (the first frame always): the rule by
    which `slam.driver.select_scans` picks the scans to integrate, so that the 3D filter
    (`slam.filter3d`) gets the rays of exactly the frames it integrates, and only those. A kept
    frame goes on with the distances corrected for its rays (`_Corrected`), not to be corrected
    twice."""

    def __init__(self, extractor: ScanExtractor, every: int, pixel_stride: int,
                 progress: Callable[[int], Any] | None,
                 keyframes: tuple[float, float] | None = None) -> None:
        self.extractor, self.every, self.stride, self.progress = extractor, every, pixel_stride, progress
        self.keyframes = keyframes
        self._last: np.ndarray | None = None
        self.frames: list[int] = []
        self.clouds: list[np.ndarray] = []

    def _keep(self, i: int, frame: Any) -> bool:
        if self.keyframes is None:
            return self.every > 0 and i % self.every == 0
        odometry = getattr(frame, "odometry", None)
        if odometry is None or self._last is None:
            self._last = None if odometry is None else np.asarray(odometry, dtype=np.float64)
            return True
        cur = np.asarray(odometry, dtype=np.float64)
        c, s = math.cos(self._last[2]), math.sin(self._last[2])
        dx, dy = cur[0] - self._last[0], cur[1] - self._last[1]
        turn = math.remainder(cur[2] - self._last[2], 2.0 * math.pi)
        if math.hypot(c * dx + s * dy, -s * dx + c * dy) > self.keyframes[0] or abs(turn) > self.keyframes[1]:
            self._last = cur
            return True
        return False

    def __call__(self, frames: Iterable[Any]) -> Iterable[Any]:
        for i, frame in enumerate(frames):
            if self._keep(i, frame):
                # Corrected once (distance correction, multipath) for both its rays and its scan.
                amplitude = np.asarray(frame.amplitude)
                distance = self.extractor.corrected_distances(np.asarray(frame.distance)[None], amplitude[None])[0]
                origins, points = self.extractor.rays(distance, amplitude, corrected=True)
                keep = slice(None, None, self.stride)
                self.frames.append(i)
                self.clouds.append(np.hstack([origins[keep], points[keep]]).astype(np.float32))
                frame = _Corrected(frame, distance)
            yield frame
            if self.progress is not None:
                self.progress(1)


def tof_scans(
    frames: Iterable[Any],
    extractor: ScanExtractor,
    *,
    cloud_every: int = 0,
    cloud_pixel_stride: int = 1,
    cloud_keyframes: tuple[float, float] | None = None,
    source: str = "",
    progress: Callable[[int], Any] | None = None,
) -> ToFScans:
    """Scans of every frame (`scan.scans_from_frames`) and, with cloud_every > 0, the rays of
    every cloud_every-th frame (every cloud_pixel_stride-th point) for the 3D map; with
    cloud_keyframes (linear m, angular rad), the rays of the frames the odometry rule picks
    instead (see `_CloudTap`), for the 3D filter.

    `frames` are `io.rosbag.ToFFrameStamped` (with timestamp and odometry) as `render_sequence`
    and `ToFBag.frames` give them.
    """
    tap = _CloudTap(extractor, int(cloud_every), max(1, int(cloud_pixel_stride)), progress, cloud_keyframes)
    scans = scans_from_frames(extractor, tap(frames), source=source)
    return ToFScans(scans, extractor, np.asarray(tap.frames, dtype=np.int64), tap.clouds)


MULTIPATH_CHOICES = ("auto", "on", "off")
# The MultipathSettings fields that describe the camera (the rest say how the sum is taken).
CAMERA_FIGURES = frozenset({"enabled", "amplitude_at_1m", "f_mod", "mirror_reflectivity", "leds", "led_count", "led_radius",
                            "led_profile_exponent", "led_half_angle_deg"})


def multipath_for_bag(bag: Any, settings: ScanSettings, choice: str) -> tuple[ScanSettings, str]:
    """The scan settings with the multipath compensation (`omnitof.scan.multipath`) that
    `choice` asks for, and the rule applied, in words for the summary. "auto": on for a
    simulated bag whose camera simulated multipath, with that camera's figures (LEDs, amplitude
    scale, frequency, mirrors: `CAMERA_FIGURES`) from the sidecar and the rest of
    `settings.multipath` (how the sum is taken); off for a simulated bag without it; otherwise
    as `settings` say (a SLAM configuration's `scan.multipath`; off by default:
    for a real camera the model needs the camera's own figures, and for a camera without
    multipath it makes every wall read short). "on": on, with a simulated bag's camera or else
    the settings' camera figures. "off": off."""
    from omnitof.scan.multipath import MultipathSettings

    if choice not in MULTIPATH_CHOICES:
        raise ValueError(f"multipath compensation must be one of {', '.join(MULTIPATH_CHOICES)}, got {choice!r}")
    if choice == "off":
        off = settings.multipath.model_copy(update={"enabled": False})
        return settings.model_copy(update={"multipath": off}), "off (--multipath-compensation off)"
    sensor = bag.rig.sensor if bag.rig is not None else None
    if sensor is None:
        if choice == "on":
            on = settings.multipath.model_copy(update={"enabled": True})
            return settings.model_copy(update={"multipath": on}), \
                "on (--multipath-compensation on), with the settings' camera figures (scan.multipath)"
        state = "on" if settings.multipath.enabled else "off"
        return settings, f"{state} (auto: not a simulated bag, so as the scan settings say)"
    if choice == "auto" and not sensor.errors.multipath:
        off = settings.multipath.model_copy(update={"enabled": False})
        return settings.model_copy(update={"multipath": off}), "off (auto: the simulated camera has no multipath)"
    reflectivity = _sidecar_reflectivity(bag, settings.multipath.mirror_reflectivity)
    # The camera's figures from the sidecar; how the sum is taken (stride, visibility, ...) as the settings say.
    camera = MultipathSettings.for_camera(sensor.errors, amplitude_at_1m=sensor.amplitude_at_1m, f_mod=sensor.f_mod,
                                          mirror_reflectivity=reflectivity, enabled=True)
    figures = camera.model_dump(include=CAMERA_FIGURES)
    why = "--multipath-compensation on" if choice == "on" else "auto: the simulated camera has multipath"
    on = settings.multipath.model_copy(update=figures)
    return settings.model_copy(update={"multipath": on}), f"on ({why}; the camera's figures from the bag's sidecar)"


def _sidecar_reflectivity(bag: Any, default: float) -> float:
    """The mirrors' reflectivity the bag's sidecar renders with (`render.mirror_reflectivity`),
    else `default`; an InputError naming the sidecar and the field where it is not a number in
    (0, 1] (a hand-edited sidecar; the compensation would otherwise fail with a traceback)."""
    from omnitof.io.rosbag.common import sidecar_path

    where = sidecar_path(Path(bag.path))
    render = (bag.sidecar or {}).get("render", {})
    if not isinstance(render, dict):
        raise InputError(f"render: expected a mapping, got {render!r}", where)
    value = render.get("mirror_reflectivity", default)
    try:
        reflectivity = float(value)
    except (TypeError, ValueError):
        reflectivity = math.nan
    if isinstance(value, bool) or not 0.0 < reflectivity <= 1.0:
        raise InputError(f"render.mirror_reflectivity: expected a number in (0, 1], got {value!r}", where)
    return reflectivity


def extractor_for_bag(
    bag: Any, calibration: str | Path | None = None, settings: ScanSettings | None = None
) -> tuple[ScanExtractor, str]:
    """The bag's ScanExtractor and where its geometry came from: the calibration file, else the
    true rig of a simulated bag's sidecar (with a ToFInputWarning), else an InputError."""
    if calibration is not None:
        from omnitof.calibration import MIRRORS_NOT_CALIBRATED, load_calibration

        cal = load_calibration(calibration)
        if cal.provenance.get("mirrors") == MIRRORS_NOT_CALIBRATED:
            warnings.warn(f"{calibration}: its mirrors are the rig's design, not measured (the file holds "
                          "`calibrate intrinsics` only): run `omnitof calibrate mirrors` on it, or the scans "
                          "take the design's mirror planes", ToFInputWarning, stacklevel=2)
        if cal.camera.shape != bag.shape:
            raise InputError(
                f"the calibration is for {cal.camera.width}×{cal.camera.height} images, the bag has "
                f"{bag.shape[1]}×{bag.shape[0]}", calibration,
            )
        return ScanExtractor.from_calibration(cal, settings=settings), f"calibration {calibration}"
    rig = bag.rig
    if rig is not None:
        if bag.shape not in ((0, 0), rig.camera.shape):
            # A shape error from deep in the extraction would name neither the file nor the field.
            from omnitof.io.rosbag.common import sidecar_path

            raise InputError(f"camera: {rig.camera.width} x {rig.camera.height} pixels (width x height), but the "
                             f"bag's images are {bag.shape[1]} x {bag.shape[0]} (its camera_info)",
                             sidecar_path(Path(bag.path)))
        warnings.warn(
            f"{bag.path}: no --calibration given; using the true rig from the simulator's sidecar",
            ToFInputWarning, stacklevel=2,
        )
        extractor = ScanExtractor.from_rig(rig, settings=settings)
        return extractor, "the bag's sidecar (true rig)"
    raise InputError(
        "a ToF bag needs the rig's geometry: give --calibration FILE (see `omnitof calibrate`)", bag.path
    )


def read_tof_scans(
    path: str | Path,
    *,
    calibration: str | Path | None = None,
    settings: ScanSettings | None = None,
    multipath: str = "auto",
    cloud_every: int = 0,
    cloud_pixel_stride: int = 1,
    cloud_keyframes: tuple[float, float] | None = None,
    max_frames: int | None = None,
    progress: Callable[[int], Any] | None = None,
    topics: Any = None,
    depth: bool = False,
) -> ToFScans:
    """Scans (and optionally clouds) of a ToF bag (`io.rosbag.read_tof_bag` layout, its topics
    `topics`, an `io.rosbag.ToFTopics`, default the simulator's; `depth`: the distance images
    are depth images); `multipath` one of MULTIPATH_CHOICES (`multipath_for_bag`)."""
    from itertools import islice

    from omnitof.io.rosbag import ToFTopics, read_tof_bag
    from omnitof.io.rosbag.odometry import odometry_coverage, odometry_rule

    if max_frames is not None and int(max_frames) < 0:
        raise ValueError(f"max_frames must be >= 0, got {max_frames!r}")

    bag = read_tof_bag(path, topics=topics or ToFTopics(), depth=depth)
    if cloud_keyframes is not None and bag.odometry is None:
        raise InputError("the bag has no odometry, and the 3D filter (--filter 3d) picks its frames by it; "
                         "the 2D filter estimates the odometry from the scans", path)
    settings, multipath_rule = multipath_for_bag(bag, settings or ScanSettings(), multipath)
    extractor, rig_source = extractor_for_bag(bag, calibration, settings)
    dropped: list[int] = []
    frames = _with_odometry(bag, dropped, progress)
    if max_frames is not None:
        frames = islice(frames, int(max_frames))
    out = tof_scans(frames, extractor, cloud_every=cloud_every, cloud_pixel_stride=cloud_pixel_stride,
                    cloud_keyframes=cloud_keyframes, source=str(path), progress=progress)
    if dropped:
        assert bag.odometry is not None
        warnings.warn(f"{path}: dropped {len(dropped)} frames outside {odometry_coverage(bag.odometry)} "
                      f"({bag.odometry_source}), the first of them frame {dropped[0]}; "
                      f"{len(out.scans)} kept", ToFInputWarning, stacklevel=2)
    # Without odometry, SLAM estimates it from the scans (omnitof.slam.scan_odometry).
    out.scans = dataclasses.replace(out.scans, odometry_known=bag.odometry is not None, odometry_rule=odometry_rule(
        bag.odometry_source, "frame", bag.topics.odom_frame, bag.topics.tf))
    out.rig_source = rig_source
    out.multipath_rule = multipath_rule
    return out


def _with_odometry(bag: Any, dropped: list[int], progress: Callable[[int], Any] | None) -> Iterator[Any]:
    """The bag's frames, each with an odometry pose: a bag without odometry gives every frame
    the pose (0, 0, 0), to be estimated from the scans; a frame outside the odometry's time
    span (cameras often start before the wheels) or inside a hole in it (`odometry_gaps`: a
    pose interpolated across it would be made up) is skipped, its index appended to `dropped`
    (the caller warns) and counted in `progress`; an InputError where no frame is within it, or
    where the odometry spans no time and a frame lies at another (`spans_no_time`)."""
    from omnitof.io.rosbag.odometry import no_time_span, odometry_coverage, spans_no_time

    kept = 0
    for i, frame in enumerate(bag.frames(samples=False)):
        if bag.odometry is None:
            yield dataclasses.replace(frame, odometry=np.zeros(3))
        elif frame.odometry is None:  # outside the odometry's span or in a hole (ToFBag.odometry_at)
            if spans_no_time(bag.odometry):  # not a late start of the wheels: the stamps are broken
                raise no_time_span(f"the odometry ({bag.odometry_source})", bag.odometry,
                                   f"frame {i} at {frame.timestamp:.9f} s", bag.path)
            dropped.append(i)
            if progress is not None:
                progress(1)
        else:
            kept += 1
            yield frame
    if dropped and not kept:
        raise InputError(f"no frame lies within {odometry_coverage(bag.odometry)} ({bag.odometry_source})",
                         bag.path)


def frame_count(path: str | Path, topics: Any = None) -> int:
    """Frames in a ToF bag (for a progress bar)."""
    from omnitof.io.rosbag import ToFTopics, read_tof_bag

    return read_tof_bag(path, topics=topics or ToFTopics(), odometry=False).n_frames
