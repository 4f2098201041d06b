"""Simulated ToF sequences: the robot's drive through a world, its odometry, and the frames.

A sequence is what the paper recorded (sec. V): a robot driving a loop through a building at
walking pace, a ToF frame every 0.1 s, and the wheel odometry. Here it also has the ground
truth. Three steps, each usable alone:

1. `robot_path`: the world's waypoints (`path:` in the world file) driven `laps` times, closed
   back to the start and `overlap` metres on past it (so that the end sees what the start saw),
   with each corner cut by a circular arc so that the heading turns no faster than
   `max_turn_rate` (`laser2d.plan_path`), sampled at the frame rate at constant speed.
2. `make_sequence`: the ground truth plus wheel odometry with random noise (the odometry motion
   model) and systematic drift (wheel radius, wheel base, heading drift:
   `laser2d.simulate_odometry`), so that raw odometry visibly fails to close the loop.
3. `render_sequence`: the frames, streamed in batches from the renderer (`sim.render`), and
   `simulate_bag`, which writes everything as a ROS 2 bag (`io.rosbag.write_tof_bag`) with the
   true rig in the sidecar (`rig_sidecar`; `Rig.from_dict` reads it back).

Defaults: 0.4 m/s (a Pioneer-class robot driven through an office, and the pace at which the
odometry model's defaults were set, ~4 cm per frame) and at most 0.6 rad/s (34°/s) of turning,
well within such a robot's limits (its firmware allows ~100°/s) and slow enough that a 10 Hz
sensor sees each corner from many poses.

Determinism: everything random comes from one seed: the odometry's noise from the stream
(seed, 0), frame i's sensor noise from (seed + 1, i) (see `Renderer.render_many`), the renderer's
sub-ray jitter from `RenderSettings.seed`. The same seed gives the same bag, byte for byte in its
messages.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import ConfigError
from omnitof.io.rosbag import DEFAULT_STORAGE, ToFFrameStamped, write_tof_bag
from omnitof.io.rosbag.common import SIDECAR_VERSION
from omnitof.sim import laser2d
from omnitof.sim.render import Renderer, RenderSettings
from omnitof.sim.worlds import World, WorldError
from omnitof.sensor.tof import SensorNoise
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.types import Trajectory

# The smoothed path must keep this far (m) from anything the robot would touch: half the width
# of a Pioneer-class base plus a margin.
ROBOT_RADIUS = 0.3
# Frame times start here (seconds, ROS time 2026-01-01T00:00:00Z): zero stamps confuse some
# ROS tools, which take them for "no time".
DEFAULT_START_TIME = 1_767_225_600.0


@dataclass(frozen=True)
class MotionSettings:
    """How the robot drives: speed (m/s), frame rate (Hz), largest turn rate (rad/s), and how
    far (m) it drives on past the start of a closed loop."""

    speed: float = 0.4
    rate_hz: float = 10.0
    max_turn_rate: float = 0.6
    overlap: float = 2.0

    def __post_init__(self) -> None:
        for name in ("speed", "rate_hz", "max_turn_rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"motion.{name} must be a positive number, got {value!r}")
        if not (math.isfinite(self.overlap) and self.overlap >= 0.0):
            raise ConfigError(f"motion.overlap must be >= 0 metres, got {self.overlap!r}")


def _real(value: object) -> bool:
    """A finite number (not a bool)."""
    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
            and math.isfinite(value))


@dataclass(frozen=True)
class OdometryErrors:
    """Wheel odometry errors (see `laser2d.simulate_odometry`): the motion model's variances
    alpha1..4 (dimensionless), wheel radius and wheel base errors (fractions), and heading
    drift (radians per metre)."""

    alphas: tuple[float, float, float, float] = laser2d.DEFAULT_ALPHAS
    wheel_radius_error: float = laser2d.DEFAULT_WHEEL_RADIUS_ERROR
    wheel_base_error: float = laser2d.DEFAULT_WHEEL_BASE_ERROR
    heading_drift: float = laser2d.DEFAULT_HEADING_DRIFT

    def __post_init__(self) -> None:
        # Wheels that err by half their size, or a heading that drifts a radian per metre, are
        # no odometry (an infinite drift made every pose NaN).
        for name in ("wheel_radius_error", "wheel_base_error"):
            value = getattr(self, name)
            if not (_real(value) and abs(value) < 0.5):
                raise ConfigError(f"odometry.{name} must be a fraction within ±0.5, got {value!r}")
        if not (_real(self.heading_drift) and abs(self.heading_drift) <= 1.0):
            raise ConfigError(f"odometry.heading_drift must lie within ±1 radian per metre, got {self.heading_drift!r}")
        if len(self.alphas) != 4 or not all(_real(a) and a >= 0.0 for a in self.alphas):
            raise ConfigError(f"odometry.alphas must be four finite variances >= 0, got {self.alphas!r}")


@dataclass(frozen=True, eq=False)
class Sequence:
    """A drive through a world: frame times (N,) seconds, true and odometry poses (N, 3)
    (x, y, θ in the world frame; the odometry frame coincides with it at the start), and the
    distance driven (m)."""

    world: World
    timestamps: np.ndarray
    ground_truth: np.ndarray
    odometry: np.ndarray
    length: float
    motion: MotionSettings = field(default_factory=MotionSettings)
    odometry_errors: OdometryErrors = field(default_factory=OdometryErrors)
    seed: int = 0

    def __len__(self) -> int:
        return len(self.timestamps)

    def trajectories(self) -> tuple[Trajectory, Trajectory]:
        """(odometry, ground truth) as Trajectory objects."""
        return Trajectory(self.timestamps, self.odometry), Trajectory(self.timestamps, self.ground_truth)

    def odometry_end_error(self, frames: int | None = None) -> tuple[float, float]:
        """How far (m, rad) the odometry is from the truth at the last of the first `frames`
        frames (default: all): what SLAM has to correct."""
        last = len(self) - 1 if frames is None else max(0, min(int(frames), len(self)) - 1)
        dx = self.odometry[last, :2] - self.ground_truth[last, :2]
        dtheta = laser2d.wrap_angle(self.odometry[last, 2] - self.ground_truth[last, 2])
        return float(np.hypot(*dx)), abs(float(dtheta))

    def distance_driven(self, frames: int | None = None) -> float:
        """Metres driven (true path) over the first `frames` frames (default: all)."""
        xy = self.ground_truth[: len(self) if frames is None else int(frames), :2]
        return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())


def loop_waypoints(world: World, overlap: float) -> np.ndarray:
    """The world's waypoints as driven: `laps` times round, back to the start if the path is
    closed, and `overlap` metres on along the first leg."""
    if len(world.waypoints) < 2:
        raise WorldError(f"world {world.name!r} has no path to drive (path.waypoints)", world.source)
    pts = np.asarray(world.waypoints, dtype=np.float64)
    if not world.path_closed:
        return pts
    loop = np.vstack([np.tile(pts, (world.laps, 1)), pts[:1]])
    first_leg = pts[1] - pts[0]
    length = float(np.hypot(*first_leg))
    if overlap > 0.0:
        loop = np.vstack([loop, pts[0] + first_leg * min(overlap, 0.5 * length) / length])
    return loop


def robot_path(world: World, motion: MotionSettings = MotionSettings()) -> laser2d.PlannedPath:
    """The smooth path of the robot through the world's waypoints (see the module docstring).

    Raises WorldError if the smoothed path passes closer than ROBOT_RADIUS to an obstacle.
    """
    # The corners' arcs grow with the speed: a bundled world fails at a speed it was not drawn
    # for, and its file is not the user's to edit, so the message names the speed too.
    arcs = (f"; at {motion.speed:g} m/s the corners are arcs of {motion.speed / motion.max_turn_rate:.2f} m radius "
            f"(speed / the largest turn rate, {motion.max_turn_rate:g} rad/s): a lower speed turns tighter")
    beside_speed = "" if motion.speed == MotionSettings().speed else arcs
    try:  # plan_path bounds the frames (rate_hz 1e9 asked for terabytes)
        path = laser2d.plan_path(
            loop_waypoints(world, motion.overlap), speed=motion.speed, rate_hz=motion.rate_hz,
            max_turn_rate=motion.max_turn_rate,
        )
    except ConfigError as err:
        raise WorldError(f"world {world.name!r}: path.waypoints: {err}{arcs}", world.source) from None
    walls = laser2d.World2D(world.obstacles())
    clearance = walls.distance_to_walls(path.poses[:, :2])
    if not clearance.min() >= ROBOT_RADIUS:  # NaN too: a clearance that cannot be worked out
        i = int(np.argmin(clearance))
        x, y = path.poses[i, :2]
        raise WorldError(
            f"world {world.name!r}: the robot's path passes {clearance[i]:.2f} m from an obstacle "
            f"at ({x:.2f}, {y:.2f}); it needs {ROBOT_RADIUS} m (move path.waypoints){beside_speed}",
            world.source,
        )
    return path


def make_sequence(
    world: World,
    *,
    seed: int = 0,
    motion: MotionSettings = MotionSettings(),
    odometry_errors: OdometryErrors = OdometryErrors(),
    start_time: float = DEFAULT_START_TIME,
) -> Sequence:
    """Ground truth and odometry of the robot's drive through `world` (no frames yet)."""
    if not (_real(start_time) and 0.0 <= start_time < 1e10):
        raise ConfigError(f"start_time must be seconds in [0, 1e10), got {start_time!r}")
    path = robot_path(world, motion)
    odometry = laser2d.simulate_odometry(
        path.poses,
        seed=np.random.default_rng([int(seed), 0]),
        alphas=odometry_errors.alphas,
        wheel_radius_error=odometry_errors.wheel_radius_error,
        wheel_base_error=odometry_errors.wheel_base_error,
        heading_drift=odometry_errors.heading_drift,
    )
    return Sequence(
        world=world, timestamps=start_time + path.timestamps, ground_truth=path.poses,
        odometry=odometry, length=path.length, motion=motion, odometry_errors=odometry_errors,
        seed=int(seed),
    )


def render_sequence(
    sequence: Sequence,
    renderer: Renderer,
    *,
    samples: bool = False,
    batch: int = 32,
    start: int = 0,
    stop: int | None = None,
) -> Iterator[ToFFrameStamped]:
    """The frames of frames [start, stop) of a sequence, rendered `batch` at a time.

    Each frame carries its time, distance, amplitude (and A0..A3 if `samples`), odometry and
    ground truth. Frame i's noise depends only on (sequence.seed, i).
    """
    stop = len(sequence) if stop is None else min(int(stop), len(sequence))
    if batch < 1:
        raise ConfigError(f"batch must be >= 1, got {batch!r}")
    if start < 0:
        raise ConfigError(f"start must be a frame index >= 0, got {start!r}")
    for first in range(int(start), stop, batch):
        last = min(first + batch, stop)
        errors = renderer.sensor.errors
        timing = sample_poses(sequence, range(first, last), errors.integration_time) if errors.motion else None
        frames = renderer.render_many(
            sequence.ground_truth[first:last], seed=sequence.seed + 1, first_index=first, sample_poses=timing
        )
        for i, frame in zip(range(first, last), frames):
            yield ToFFrameStamped(
                timestamp=float(sequence.timestamps[i]),
                distance=frame.distance,
                amplitude=frame.amplitude,
                samples=frame.samples if samples else None,
                odometry=sequence.odometry[i],
                ground_truth=sequence.ground_truth[i],
            )


def sample_poses(sequence: Sequence, frames: range | np.ndarray, integration_time: float) -> np.ndarray:
    """(len(frames), 4, 3) the robot's true pose when each of a frame's four samples was taken.

    The samples follow one another, `integration_time` seconds each, centred on the frame's
    time: sample k at t_i + (k − 1.5)·integration_time, so that the frame's ground-truth pose
    is the middle of its acquisition. Poses between frames are interpolated linearly (x, y, and
    the heading along the shorter way round) between the neighbouring frames of the drive;
    before the first and after the last frame, extrapolated from the nearest step.
    """
    idx = np.asarray(frames, dtype=np.int64)
    n = len(sequence)
    times = sequence.timestamps
    poses = sequence.ground_truth
    offsets = (np.arange(4) - 1.5) * float(integration_time)
    out = np.empty((len(idx), 4, 3))
    for k, tau in enumerate(offsets):
        # The neighbouring frame on the side the sample lies (the other one at the ends).
        other = np.clip(idx + (1 if tau >= 0 else -1), 0, n - 1)
        other = np.where(other == idx, np.clip(idx - (1 if tau >= 0 else -1), 0, n - 1), other)
        dt = times[other] - times[idx]
        frac = np.divide(tau, dt, out=np.zeros(len(idx)), where=dt != 0)[:, None]
        step = poses[other] - poses[idx]
        step[:, 2] = laser2d.wrap_angle(step[:, 2])
        out[:, k] = poses[idx] + frac * step
    out[..., 2] = laser2d.wrap_angle(out[..., 2])
    return out


# --- the sidecar: the true rig and how the sequence was made --------------------------------


def rig_sidecar(renderer: Renderer, sequence: Sequence | None = None) -> dict[str, Any]:
    """A YAML-ready dict of the true rig (its YAML form, `Rig.to_dict`: camera, mirrors with
    outlines, mount, sensor), the renderer settings, and, if given, how the sequence was made.
    `Rig.from_dict` reads the rig back."""
    out: dict[str, Any] = {
        "omnitof_sidecar": SIDECAR_VERSION,
        **renderer.rig.to_dict(),
        "render": {k: v for k, v in asdict(renderer.settings).items() if k != "threads"},
        "world": {"name": renderer.world.name,
                  "source": None if renderer.world.source is None else str(renderer.world.source)},
    }
    if sequence is not None:
        out["sequence"] = {
            "seed": sequence.seed,
            "frames": len(sequence),
            "length_m": sequence.length,
            "motion": asdict(sequence.motion),
            "odometry_errors": {**asdict(sequence.odometry_errors),
                                "alphas": list(sequence.odometry_errors.alphas)},
        }
    return out


# --- everything to a bag --------------------------------------------------------------------


def simulate_bag(
    world: World,
    out: str | Path,
    *,
    seed: int = 0,
    motion: MotionSettings = MotionSettings(),
    odometry_errors: OdometryErrors = OdometryErrors(),
    settings: RenderSettings | None = None,
    sensor: SensorNoise | None = None,
    samples: bool = False,
    max_frames: int | None = None,
    storage: str = DEFAULT_STORAGE,
    overwrite: bool = False,
    progress: Callable[[int], Any] | None = None,
) -> tuple[Sequence, int]:
    """Simulate the world's sequence and write it as a ROS 2 bag folder `out`.

    `sensor` defaults to the default camera with the systematic errors of
    `ToFErrors.simulation_default()`; the sidecar records which (`sensor.errors`).
    The bag holds distance and amplitude images (and A0..A3 with `samples`), camera info,
    odometry and ground truth at every frame; `<out>/omnitof.yaml` the true rig
    (`rig_sidecar`). `max_frames` keeps only the first frames (a quick look). Nothing is left
    at `out` if writing fails. Returns (the sequence, frames written).
    """
    sequence = make_sequence(world, seed=seed, motion=motion, odometry_errors=odometry_errors)
    renderer = Renderer(world, sensor=sensor or SensorNoise(errors=ToFErrors.simulation_default()),
                        settings=settings or RenderSettings(seed=int(seed)))
    stop = len(sequence) if max_frames is None else min(int(max_frames), len(sequence))
    odometry, truth = sequence.trajectories()
    if stop < len(sequence):
        odometry = Trajectory(odometry.timestamps[:stop], odometry.poses[:stop])
        truth = Trajectory(truth.timestamps[:stop], truth.poses[:stop])

    def frames() -> Iterator[ToFFrameStamped]:
        for frame in render_sequence(sequence, renderer, samples=samples, stop=stop):
            yield frame
            if progress is not None:
                progress(1)

    written = write_tof_bag(
        out, frames(), camera=renderer.camera, odometry=odometry, ground_truth=truth,  # type: ignore[arg-type]
        sidecar=rig_sidecar(renderer, sequence), storage=storage, overwrite=overwrite,
    )
    return sequence, written


def poses_along_loop(world: World, count: int) -> np.ndarray:
    """(count, 3) poses evenly spaced along the world's waypoint legs (no corner arcs), each
    heading along its leg: quick sample poses for benchmarks and tests."""
    legs = world.path_legs()
    lengths = np.linalg.norm(legs[:, 1] - legs[:, 0], axis=1)
    ends = np.cumsum(lengths)
    s = (np.arange(count) + 0.5) * ends[-1] / count
    leg = np.searchsorted(ends, s)
    frac = (s - (ends[leg] - lengths[leg])) / lengths[leg]
    a, b = legs[leg, 0], legs[leg, 1]
    xy = a + frac[:, None] * (b - a)
    heading = np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])
    return np.column_stack([xy, heading])
