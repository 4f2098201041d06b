"""Render raw ToF frames of the omnidirectional sensor in a simulated world.

The Rust core (`omnitof._core._Renderer`, rust/src/render.rs) traces, for every pixel, a few
sub-rays through the lens, the mirror they meet and the world, and returns each pixel's phasor
(the mean over its sub-rays of albedo·cos(incidence)/r²·e^{i·4πf·r/c}, times the mirror's and
any metal's or glass's reflectivity, squared for the round trip). This module prepares what the
core needs once per world and rig (sub-ray directions from the lens model, mirrors, materials)
and has the core turn its phasors into frames: A0..A3 with the sensor's noise and systematic
errors and their decoding (distance, amplitude, offset) in one pass per pixel
(rust/src/tof_frames.rs, the model of `tof.SensorNoise.synthesise` and `tof.decode`, which stay
the numpy reference: without noise both give the same samples).

Frames and units: robot poses (x, y, θ) in the world frame, metres and radians; the camera sits
at robot_T_camera (default `mirrors.camera_mount()`), mirrors and sub-ray directions are in the
camera frame (see `omnitof.sensor.mirrors`). Images are (rows, cols) = (H, W); phasors, amplitudes and
offsets are in the camera's sample units; distances are one-way metres, wrapped at the
unambiguous range c/(2·f_mod).

Ambient light: `SensorNoise.ambient` is the offset that background light gives on an albedo-0.5
surface seen directly (the sensor's working point); each pixel gets that, times the world's
`ambient` scale, times how bright the surfaces it sees are (albedo, through the mirror's
reflectivity once) relative to albedo 0.5.

Determinism: the sub-ray jitter is drawn once from `RenderSettings.seed`; the core is
deterministic and independent of the thread count; the noise of frame i of `render_many` is
seeded by the first number the generator seeded with (seed, i) draws, and the core draws it
along each image row from that seed and the row, so a frame does not depend on the thread
count or on the batch it is rendered in. (Before issue 15's speed work the noise was numpy's:
the same model, other draws.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from omnitof import _core
from omnitof.sensor.camera import Camera
from omnitof.sensor.design import DEFAULT_RIG_MIRRORS, DEFAULT_RIG_TILT_DEG, DEFAULT_RIG_YAW_DEG, default_rig
from omnitof.errors import ConfigError
from omnitof.sensor.mirrors import Mirror, camera_mount, pyramid, rigid_mount
from omnitof.sensor.rig import Rig
from omnitof.sim.worlds import World
from omnitof.sensor.tof import SensorNoise, ToFFrame, unambiguous_range
from omnitof.sensor.tof_errors import fixed_pattern

# Front-surface mirrors of protected aluminium reflect about 0.86–0.9 at 850 nm (an assumption
# for the paper's mirrors, which it does not specify).
DEFAULT_MIRROR_REFLECTIVITY = 0.9
# SensorNoise.ambient is the background offset on a surface of this albedo seen directly.
AMBIENT_REFERENCE_ALBEDO = 0.5
# Most specular bounces the core follows (render_bindings.rs MAX_BOUNCES): between two perfect
# mirrors a ray never fades below min_gain.
MAX_BOUNCES = 64


class RenderConfigError(ConfigError, ValueError):
    """A bad renderer setting or input, named in the message."""


@dataclass(frozen=True)
class RenderSettings:
    """How the renderer samples light.

    Attributes:
        sub_rays: rays per pixel (>= 1). A perfect square is stratified (4 = one ray in each
            quarter of the pixel, jittered); 1 is the pixel centre, exactly.
        seed: seed of the sub-ray jitter.
        max_bounces: specular bounces (metal, glass reflections) followed after the first
            surface; 0 keeps only diffuse returns.
        min_gain: light paths weaker than this fraction of the light are dropped.
        cell: side (m) of the floor-plan grid that holds walls and boxes. 2 m measured best
            over the bundled worlds (benchmarks/render.py): smaller cells cost more steps in
            open space than they save in wall tests.
        mirror_reflectivity: of every mirror, in [0, 1].
        threads: worker threads of the core; None uses all cores. The frames are the same for
            any number.
        motion_tolerance: with motion during a frame on (`ToFErrors.motion`), a frame whose
            four sample poses move no point within the unambiguous range by more than this
            (metres: translation + range·rotation, sample 0 to sample 3) is rendered once, at
            its own pose; others are rendered at each sample's pose (4 times the work).
            1 cm lets straight driving at 0.4 m/s (6 mm in 15 ms) cost one render and renders
            every turn at 0.6 rad/s (6.7 cm at 7.5 m) four times.
    """

    sub_rays: int = 4
    seed: int = 0
    max_bounces: int = 2
    min_gain: float = 1e-4
    cell: float = 2.0
    mirror_reflectivity: float = DEFAULT_MIRROR_REFLECTIVITY
    threads: int | None = None
    motion_tolerance: float = 0.01

    def __post_init__(self) -> None:
        if not (math.isfinite(self.motion_tolerance) and self.motion_tolerance >= 0.0):
            raise RenderConfigError(
                f"RenderSettings.motion_tolerance must be >= 0 metres, got {self.motion_tolerance!r}"
            )
        for name in ("sub_rays", "max_bounces", "seed"):
            value = getattr(self, name)
            minimum = 1 if name == "sub_rays" else 0
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
                raise RenderConfigError(f"RenderSettings.{name} must be a whole number >= {minimum}, got {value!r}")
        if self.seed >= 2**64:
            raise RenderConfigError(f"RenderSettings.seed must be below 2**64, got {self.seed!r}")
        if self.max_bounces > MAX_BOUNCES:
            raise RenderConfigError(f"RenderSettings.max_bounces must be at most {MAX_BOUNCES}, got {self.max_bounces!r}")
        if self.threads is not None and (not isinstance(self.threads, (int, np.integer)) or self.threads < 1):
            raise RenderConfigError(f"RenderSettings.threads must be None or >= 1, got {self.threads!r}")
        if not (math.isfinite(self.cell) and self.cell > 0.0):
            raise RenderConfigError(f"RenderSettings.cell must be > 0 metres, got {self.cell!r}")
        if not 0.0 <= self.min_gain < 1.0:
            raise RenderConfigError(f"RenderSettings.min_gain must lie in [0, 1), got {self.min_gain!r}")
        if not 0.0 <= self.mirror_reflectivity <= 1.0:
            raise RenderConfigError(
                f"RenderSettings.mirror_reflectivity must lie in [0, 1], got {self.mirror_reflectivity!r}"
            )


@dataclass(frozen=True)
class Phasors:
    """What reaches the pixels, before noise; arrays (N, H, W), one image per pose.

    phasor: complex64, the mean phasor A·e^{iΦ} of each pixel, sample units.
    active_offset: float32, the offset the returning modulated light adds (Σ|p_i| over the
        pixel's light paths, divided by the modulation contrast): mixed pixels keep the DC part
        of every path even where their phasors cancel.
    ambient: float32, the offset from background light, sample units.
    """

    phasor: np.ndarray
    active_offset: np.ndarray
    ambient: np.ndarray


@dataclass(frozen=True)
class Frame:
    """One simulated frame at a pose; images (H, W).

    pose: (3,) the robot pose (x, y, θ). phasor: complex64, noise-free (see `Phasors`).
    samples: (4, H, W) float32 A0..A3 with noise. tof: their decoding (distance in metres,
    amplitude, offset, saturated).
    """

    pose: np.ndarray
    phasor: np.ndarray
    samples: np.ndarray
    tof: ToFFrame

    @property
    def distance(self) -> np.ndarray:
        return self.tof.distance

    @property
    def amplitude(self) -> np.ndarray:
        return self.tof.amplitude

    @property
    def offset(self) -> np.ndarray:
        return self.tof.offset


@dataclass(eq=False)
class Renderer:
    """Renders a world as the omnidirectional ToF sensor sees it from robot poses.

    Args:
        world: the world (`omnitof.sim.worlds.load_world`).
        camera, mirrors: the rig; both None gives `design.default_rig()`; a camera alone gets
            the default pyramid sized for it.
        robot_T_camera: 4×4 mount; default `mirrors.camera_mount()`.
        sensor: signal scale, modulation frequency and noise; default `SensorNoise()`.
        settings: sampling; default `RenderSettings()`.
    """

    world: World
    camera: Camera | None = None
    mirrors: Sequence[Mirror] | None = None
    robot_T_camera: np.ndarray | None = None
    sensor: SensorNoise = field(default_factory=SensorNoise)
    settings: RenderSettings = field(default_factory=RenderSettings)

    def __post_init__(self) -> None:
        if self.camera is None and self.mirrors is None:
            rig = default_rig()
            self.camera, self.mirrors = rig.camera, rig.mirrors
        elif self.camera is None:
            raise RenderConfigError("mirrors were given without the camera they belong to")
        elif self.mirrors is None:
            self.mirrors = pyramid(
                DEFAULT_RIG_MIRRORS, DEFAULT_RIG_TILT_DEG, yaw_deg=DEFAULT_RIG_YAW_DEG, camera=self.camera
            )
        if self.robot_T_camera is None:
            self.robot_T_camera = camera_mount()
        self.robot_T_camera = rigid_mount(self.robot_T_camera)  # checked, its rotation made exact
        self._directions = sub_ray_directions(self.camera, self.settings.sub_rays, self.settings.seed)
        self._core = self._build_core()

    @classmethod
    def of_rig(cls, world: World, rig: Rig, settings: RenderSettings | None = None) -> Renderer:
        """A renderer of `rig` (which needs its mirror outlines) in `world`."""
        return cls(world, rig.camera, rig.mirrors, rig.robot_T_camera, rig.sensor,
                   settings if settings is not None else RenderSettings())

    @property
    def rig(self) -> Rig:
        """The rig this renderer renders (camera, mirrors with outlines, mount, sensor)."""
        return Rig.from_mirrors(self.camera, self.mirrors, self.robot_T_camera, self.sensor)  # type: ignore[arg-type]

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the images."""
        return self.camera.shape  # type: ignore[union-attr]

    @property
    def directions(self) -> np.ndarray:
        """(H, W, S, 3) unit sub-ray directions in the camera frame (NaN outside the lens
        model), read-only."""
        return self._directions

    def phasors(self, poses: np.ndarray, *, keys: np.ndarray | None = None) -> Phasors:
        """Noise-free pixel phasors and offsets for robot poses (N, 3) (or one pose (3,),
        which still gives arrays (1, H, W)). `keys` (N, 3): the pose whose hash draws each
        image's multipath rays (default: its own pose; `render_many` gives a moving frame's
        four samples their frame's pose, so that they share them)."""
        poses2 = _poses(poses)
        # (N, H, W, 4) float32: re, im, Σ|p| (kept >= |re + i·im| by the core), ambient brightness.
        raw = self._core.render(poses2, None if keys is None else _poses(keys))
        phasor = np.ascontiguousarray(raw.view(np.complex64)[..., 0])
        active = raw[..., 2] * np.float32(1.0 / self.sensor.modulation_contrast)
        scale = self.sensor.ambient * self.world.ambient / AMBIENT_REFERENCE_ALBEDO
        ambient = raw[..., 3] * np.float32(scale)
        return Phasors(phasor, active, ambient)

    def render(self, pose: np.ndarray, *, seed: int | np.random.Generator) -> Frame:
        """One frame at the robot pose (x, y, θ): phasors, noisy samples and their decoding."""
        pose = np.asarray(pose, dtype=np.float64)
        if not isinstance(seed, np.random.Generator) and int(seed) < 0:
            raise RenderConfigError(f"seed must be >= 0, got {seed!r}")
        gen = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        return self._frames(self.phasors(pose), pose.reshape(1, 3), [gen], np.zeros(1, dtype=np.int64),
                            np.zeros(1, dtype=bool))[0]

    def render_many(self, poses: np.ndarray, *, seed: int, first_index: int = 0,
                    sample_poses: np.ndarray | None = None) -> list[Frame]:
        """Frames at robot poses (N, 3), rendered in one batch; frame i's noise comes from the
        generator seeded with (seed, first_index + i), so a frame does not depend on the others
        and a long sequence rendered in batches is the same as one rendered at once.

        `sample_poses` (N, 4, 3): the robot's pose when each of the four samples was taken
        (`omnitof.sim.sequence.sample_poses`); used when the sensor's `errors.motion` is on, so
        that each sample sees the scene from its own pose (`RenderSettings.motion_tolerance`).
        """
        poses2 = _poses(poses)
        n = len(poses2)
        if first_index < 0:
            raise RenderConfigError(f"first_index must be >= 0, got {first_index!r}")
        if int(seed) < 0:
            raise RenderConfigError(f"seed must be >= 0, got {seed!r}")
        gens = [np.random.default_rng([int(seed), int(first_index) + i]) for i in range(n)]
        if sample_poses is None or not self.sensor.errors.motion:
            return self._frames(self.phasors(poses2), poses2, gens, np.arange(n), np.zeros(n, dtype=bool))
        sp = np.asarray(sample_poses, dtype=np.float64)
        if sp.shape != (n, 4, 3) or not np.all(np.isfinite(sp)):
            raise RenderConfigError(f"sample_poses must be finite with shape ({n}, 4, 3), got {sp.shape}")
        moving = self._apparent_motion(sp) > self.settings.motion_tolerance
        # One call of the core: the still frames at their poses, the moving ones at each sample's.
        # A moving frame's four samples draw the same multipath rays (keyed by the frame's pose):
        # the scene's interreflection changes smoothly over the frame, and four independent
        # Monte-Carlo draws of it would differ by their noise, which the 4-tap decoding turns
        # into distance errors that no camera makes (BENCHMARKS.md, "Multipath in frames taken
        # while turning").
        n_still = int((~moving).sum())
        ph = self.phasors(np.concatenate([poses2[~moving], sp[moving].reshape(-1, 3)]),
                          keys=np.concatenate([poses2[~moving], np.repeat(poses2[moving], 4, axis=0)]))
        first = np.empty(n, dtype=np.int64)
        first[~moving] = np.arange(n_still)
        first[moving] = n_still + 4 * np.arange(n - n_still)
        return self._frames(ph, poses2, gens, first, moving)

    def first_surface(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The first surface along world rays (N, 3) origins, (N, 3) directions (any length; a
        NaN marks a ray that does not exist, as in the rig's directions): (distance (N,) metres
        along the ray, inf if none; material name (N,), "" if none). Zero or infinite
        directions and non-finite origins are refused (ValueError).
        The renderer's own intersection, for tests and ground truth in 3D."""
        o = np.ascontiguousarray(np.reshape(origins, (-1, 3)), dtype=np.float64)
        d = np.ascontiguousarray(np.reshape(directions, (-1, 3)), dtype=np.float64)
        t, index = self._core.cast(o, d)
        names = np.array([""] + self._material_names, dtype=object)[index + 1]
        return t, names

    # --- internals -----------------------------------------------------------------------------

    def _apparent_motion(self, sample_poses: np.ndarray) -> np.ndarray:
        """(N,) how far (m) a point within the unambiguous range moves in the image's terms
        from sample 0 to sample 3: translation + range·|rotation| (a bound)."""
        d = sample_poses[:, 3] - sample_poses[:, 0]
        turn = np.abs(np.mod(d[:, 2] + math.pi, 2 * math.pi) - math.pi)
        reach = unambiguous_range(self.sensor.f_mod) + float(np.hypot(*self.robot_T_camera[:2, 3]))  # type: ignore[index]
        return np.hypot(d[:, 0], d[:, 1]) + reach * turn

    def _frames(self, ph: Phasors, poses: np.ndarray, gens: list[np.random.Generator],
                first: np.ndarray, per_sample: np.ndarray) -> list[Frame]:
        """Noise, clipping and decoding of each frame, in the core (rust/src/tof_frames.rs, the
        model of `SensorNoise.synthesise` and `decode` in one pass per pixel): frame i is made of
        ph's image first[i], or of images first[i] .. first[i] + 3, one per sample, where
        per_sample[i] (motion during the frame). Frame i's noise is seeded by the first number
        its generator draws, so the frames do not depend on the thread count or the batch."""
        seeds = np.array([gen.integers(0, 2**63) for gen in gens], dtype=np.uint64)
        sensor, errors = self.sensor, self.sensor.errors
        pattern = fixed_pattern(self.shape, errors) if errors.fixed_pattern and errors.fixed_pattern_std > 0 else None
        samples, distance, amplitude, offset, saturated = self._core.frames(
            np.ascontiguousarray(ph.phasor).view(np.float32).reshape(-1, 2),
            np.ascontiguousarray(ph.active_offset).reshape(-1),
            np.ascontiguousarray(ph.ambient).reshape(-1),
            np.asarray(first, dtype=np.uint64),
            np.asarray(per_sample, dtype=bool),
            seeds,
            electrons_per_unit=float(sensor.electrons_per_unit),
            read_noise=float(sensor.read_noise),
            full_well=float(sensor.full_well),
            harmonics=(float(errors.harmonic3), float(errors.harmonic5)) if errors.wiggling else None,
            amplitude_offset=((float(errors.amplitude_offset_m), float(errors.amplitude_reference))
                              if errors.amplitude_offset else None),
            fixed_pattern=None if pattern is None else np.ascontiguousarray(pattern, dtype=np.float64).reshape(-1),
        )
        frames = []
        for i in range(len(gens)):
            k = int(first[i])
            phasor = ph.phasor[k:k + 4].mean(axis=0) if per_sample[i] else ph.phasor[k]
            decoded = ToFFrame(distance[i], amplitude[i], offset[i], saturated[i])
            frames.append(Frame(poses[i].copy(), phasor, samples[i], decoded))
        return frames

    def _light_arguments(self) -> dict[str, object]:
        """The LEDs (`errors.illumination`) and secondary rays (`errors.multipath`) for the core."""
        errors = self.sensor.errors
        # The interreflections' sources are lit by the LEDs when they are on (the light that
        # the direct returns get), else by one source at the lens centre with the LEDs' profile:
        # the camera's light leaves in a cone, not in every direction.
        args: dict[str, object] = {
            "seed": int(self.settings.seed),
            "multipath_rays": int(errors.multipath_rays) if errors.multipath else 0,
            "multipath_window": int(errors.multipath_window),
            "led_profile_exponent": float(errors.led_profile_exponent),
            "led_half_angle_deg": float(errors.led_half_angle_deg),
        }
        if errors.illumination:
            args["leds"] = np.ascontiguousarray(errors.led_positions())
        return args

    def _build_core(self) -> _core._Renderer:
        world, settings = self.world, self.settings
        names, table = world.material_table()
        self._material_names = names
        index = {name: i for i, name in enumerate(names)}
        mirrors = list(self.mirrors)  # type: ignore[arg-type]
        planes = np.array([[*m.plane.normal, m.plane.d] for m in mirrors], dtype=np.float64).reshape(-1, 4)
        vertices = (
            np.concatenate([m.polygon for m in mirrors]) if mirrors else np.zeros((0, 3))
        )
        h, w, s, _ = self._directions.shape
        try:
            return _core._Renderer(
                walls=np.ascontiguousarray(world.quads),
                wall_materials=np.array([index[m] for m in world.quad_materials], dtype=np.uint32),
                boxes=np.ascontiguousarray(world.boxes),
                box_materials=np.array([index[m] for m in world.box_materials], dtype=np.uint32),
                materials=table,
                floor_material=index[world.floor_material],
                ceiling_material=index[world.ceiling_material],
                ceiling_height=world.ceiling_height,
                cell=settings.cell,
                directions=np.ascontiguousarray(self._directions.reshape(-1, 3)),
                height=h,
                width=w,
                sub_rays=s,
                mirror_planes=planes,
                mirror_vertices=np.ascontiguousarray(vertices, dtype=np.float64),
                mirror_counts=np.array([len(m.polygon) for m in mirrors], dtype=np.uint64),
                mirror_reflectivity=np.full(len(mirrors), settings.mirror_reflectivity),
                robot_T_camera=np.ascontiguousarray(self.robot_T_camera),
                f_mod=self.sensor.f_mod,
                amplitude_at_1m=self.sensor.amplitude_at_1m,
                max_bounces=settings.max_bounces,
                min_gain=settings.min_gain,
                threads=settings.threads,
                **self._light_arguments(),
            )
        except ValueError as err:
            message = str(err)
            if not message.startswith("world: "):  # the rig's or the settings' (named in it)
                raise RenderConfigError(f"renderer: {message}") from None
            # the world's: a scene the core cannot hold (a plan too wide)
            where = f"{world.source}: " if getattr(world, "source", None) else ""
            raise RenderConfigError(f"{where}world {world.name!r}: {message.removeprefix('world: ')}") from None


def subpixel_offsets(height: int, width: int, sub_rays: int, seed: int) -> np.ndarray:
    """(H, W, S, 2) offsets (du, dv) in pixels, in [−0.5, 0.5), of each pixel's sub-rays.

    One sub-ray: the pixel centre. A perfect square n²: one ray jittered uniformly inside each
    cell of an n×n split of the pixel (stratified). Otherwise uniform jitter over the pixel.
    """
    if sub_rays == 1:
        return np.zeros((height, width, 1, 2))
    rng = np.random.default_rng(seed)
    jitter = rng.random((height, width, sub_rays, 2))
    n = math.isqrt(sub_rays)
    if n * n != sub_rays:
        return jitter - 0.5
    k = np.arange(sub_rays)
    cells = np.stack([k % n, k // n], axis=1)  # (S, 2) stratum (column, row)
    return (cells + jitter) / n - 0.5


@lru_cache(maxsize=8)
def sub_ray_directions(camera: Camera, sub_rays: int, seed: int) -> np.ndarray:
    """(H, W, S, 3) unit camera-frame directions of each pixel's sub-rays (`subpixel_offsets`
    through the lens model `camera.rays`); NaN where the lens model has no ray. Read-only and
    cached: undistorting every sub-ray takes a few seconds."""
    h, w = camera.shape
    if sub_rays == 1:
        directions = np.asarray(camera.pixel_grid_rays()).reshape(h, w, 1, 3).copy()
    else:
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        offsets = subpixel_offsets(h, w, sub_rays, seed)
        pixels = np.stack([u[..., None] + offsets[..., 0], v[..., None] + offsets[..., 1]], axis=-1)
        directions = camera.rays(pixels.reshape(-1, 2)).reshape(h, w, sub_rays, 3)
    directions.setflags(write=False)
    return directions


def _poses(poses: np.ndarray) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    p = p.reshape(1, 3) if p.shape == (3,) else p
    if p.ndim != 2 or p.shape[1] != 3:
        raise RenderConfigError(f"poses must have shape (N, 3) or (3,), got {np.shape(poses)}")
    if not np.all(np.isfinite(p)):
        raise RenderConfigError("poses must be finite")
    return np.ascontiguousarray(p)
