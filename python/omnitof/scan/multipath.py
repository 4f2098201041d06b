"""Multipath compensation: each frame's interreflection predicted from its own point cloud and
taken out of the distances before the slice (model-based, after Fuchs, ICPR 2010, and Jiménez
et al., Image and Vision Computing 2014).

A ToF camera reads a surface too far where other lit surfaces send it light: that light comes
along a longer path. The camera's LEDs sit beside the lens, so they light about what the
mirrors show, and the frame's own points are the secondary sources. Each pixel Q on a grid is
a Lambertian patch whose radiance the camera measured (its amplitude); the light it sends to a
point P, relative to what P gets from the LEDs, is a phasor S_P whose phase follows the extra
path, and the direct light's distance is D_P − arg(1 + S_P)/k (rust/src/multipath.rs gives
the sum). What the model needs of the camera: its amplitude for an albedo-1 target at 1 m, its
modulation frequency, the mirrors' reflectivity, and where its LEDs are: their emission towards
each pixel, relative to a coaxial isotropic source (`emission_map`), and the light they send
onto the seen surfaces just beside the view, which each source stands for (`source_gains`).

What it leaves out: the visibility between P and Q (the frame does not show what lies between
them; furniture hides part of the light, so in cluttered rooms the correction is too large),
where the LEDs' light beside the view lands (each source stands for it at its own place), light
from other surfaces the camera does not see (the light beyond the image only with
`beyond_view`, `beyond_view_sources`, off by default), and more than one interreflection. BENCHMARKS.md,
"Multipath compensation" and "The LEDs' light in the compensation", gives what it gains and
costs in each world. Off unless asked, or
(`auto`, `omnitof.scan.tof_input.multipath_for_bag`) for a simulated camera with multipath: the
simulator's default camera has none (`omnitof.sensor.tof_errors.DEFAULT_SWITCHES`), a
correction for light that is not there makes every wall read short, and for a real camera the
model needs that camera's figures.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import ConfigDict, Field

from omnitof.settings_model import SettingsModel
from omnitof import _core
from omnitof.sensor.camera import Camera
from omnitof.sensor.mirrors import MirrorPlane
from omnitof.sensor.tof_errors import MAX_LEDS, SPEED_OF_LIGHT, ToFErrors, led_ring

# The one-way distance (m) at which each pixel's LED emission is worked out: the working point
# of the sensor model. The LEDs are a few cm from the lens, so which of them light a pixel's
# point changes little with its distance beyond a metre.
EMISSION_DISTANCE = 3.0


class MultipathSettings(SettingsModel):
    """The multipath compensation of the scan extraction (module docstring). The camera's
    figures default to the simulator's (`omnitof.sensor.tof.SensorNoise`, `ToFErrors`,
    `omnitof.sim.render.RenderSettings`); give your camera's for real data."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    enabled: bool = Field(
        False,
        description="take each frame's predicted interreflection out of its distances. Off by default: the "
        "simulator's default camera has no multipath, and on a camera without it the correction makes "
        "walls read short (BENCHMARKS.md, 'Multipath compensation')",
    )
    amplitude_at_1m: float = Field(
        7300.0, gt=0.0, description="the camera's amplitude (sample units) of an albedo-1 Lambertian target facing it at 1 m"
    )
    f_mod: float = Field(20e6, gt=0.0, description="the camera's modulation frequency (Hz)")
    mirror_reflectivity: float = Field(0.9, gt=0.0, le=1.0, description="the mirrors' reflectivity")
    leds: bool = Field(
        True,
        description="the light comes from LEDs beside the lens (the led_* fields); false: a point source at the "
        "lens centre that emits the same in every direction",
    )
    led_count: int = Field(4, ge=1, le=MAX_LEDS, description="LEDs on a ring around the lens")
    led_radius: float = Field(0.035, ge=0.0, lt=0.5, description="the ring's radius (m), in the lens plane")
    led_profile_exponent: float = Field(1.0, ge=0.0, description="each LED emits cos^p of the angle from the optical axis")
    led_half_angle_deg: float = Field(40.0, gt=0.0, le=180.0, description="and nothing beyond this angle (degrees)")
    stride: int = Field(
        3, ge=1, description="every stride-th pixel of every stride-th row is a secondary source (stride² pixels' area)"
    )
    target_stride: int = Field(
        2,
        ge=1,
        description="the sum is taken at every target_stride-th pixel of every target_stride-th row and shared with "
        "the pixels between on the same surface (it changes slowly along a surface); 1: every pixel its own",
    )
    normal_radius: int = Field(3, ge=1, description="normals from the points this many pixels away on either side")
    smooth_radius: int = Field(
        4, ge=0, description="the distances are averaged over this many pixels around (same mirror) before the normals"
    )
    depth_tolerance: float = Field(
        0.15, ge=0.0, description="only neighbours whose distance differs by at most this (m) join the average"
    )
    min_reflectance: float = Field(
        300.0,
        ge=0.0,
        description="sources whose amplitude × distance² is lower are left out (as ScanSettings.min_amplitude_1m: "
        "readings wrapped from beyond the unambiguous range, whose position is wrong)",
    )
    min_cos: float = Field(
        0.1, gt=0.0, le=1.0, description="cosines of the view's incidence below this count as this (grazing patches)"
    )
    min_separation: float = Field(0.05, ge=0.0, description="sources nearer to the point than this (m) are left out")
    visibility: bool = Field(
        False,
        description="leave out the sources that the frame's own points hide from the point: a segment is blocked where it "
        "passes through a 0.1 m cell of the floor plan at a height between the lowest and highest point seen there. "
        "Off: it slows the compensation twelvefold and moves the simulated worlds' bins by -0.9 to +1.0 points "
        "(BENCHMARKS.md, 'The visibility test's cost')",
    )
    beyond_view: bool = Field(
        False,
        description="also take as sources the surfaces the LEDs light beyond the image (their cone is wider than the "
        "view): each seen surface at the image's edge continued beyond it, down to the floor (`beyond_view_sources`; "
        "with `leds` only). Off: it adds light that furniture hides as often as not (BENCHMARKS.md, 'The light "
        "beyond the view')",
    )
    max_ratio: float = Field(
        1.0,
        gt=0.0,
        description="pixels whose predicted interreflection exceeds this share of the direct light are dropped: "
        "their reading is mostly interreflection, and the model's error would exceed what it takes out",
    )

    @classmethod
    def for_camera(cls, errors: ToFErrors, *, amplitude_at_1m: float, f_mod: float, **overrides: object) -> MultipathSettings:
        """Settings for a simulated camera: on if it simulates multipath, with its LEDs."""
        fields: dict[str, object] = dict(
            enabled=errors.multipath, amplitude_at_1m=amplitude_at_1m, f_mod=f_mod, leds=errors.illumination,
            led_count=errors.led_count, led_radius=errors.led_radius,
            led_profile_exponent=errors.led_profile_exponent, led_half_angle_deg=errors.led_half_angle_deg,
        )
        return cls(**{**fields, **overrides})  # type: ignore[arg-type]


def emission_map(camera: Camera, planes: list[MirrorPlane], labels: np.ndarray, origins: np.ndarray,
                 directions: np.ndarray, settings: MultipathSettings) -> np.ndarray:
    """(H·W,) the LEDs' light that reaches each mirror pixel's point at EMISSION_DISTANCE,
    relative to a coaxial isotropic source (1 with `leds` off; 0 where no LED reaches).
    `origins`, `directions` (H·W, 3): where each pixel's ray leaves its mirror and the
    reflected unit direction, camera frame. Each LED gives cos^p of its emission angle over the
    LED count, through every mirror whose face the light can cross (`_lit_through`)."""
    flat = labels.reshape(-1)
    out = np.zeros(len(flat))
    if not settings.leds:
        out[flat >= 0] = 1.0
        return out
    leds = led_ring(settings.led_count, settings.led_radius)
    min_cos = math.cos(math.radians(settings.led_half_angle_deg))
    on_mirror = _near_mirror_pixels(labels)
    sel = np.flatnonzero(flat >= 0)
    x = origins[sel] + (EMISSION_DISTANCE - np.linalg.norm(origins[sel], axis=1))[:, None] * directions[sel]
    for m, plane in enumerate(planes):  # loop over mirrors and LEDs; pixels vectorised
        n, d = plane.normal, plane.d
        facing = x @ n < d  # the point lies on the mirror's reflective side
        for led in leds:
            if led @ n >= d:  # behind the mirror: no image in it
                continue
            image = led - 2.0 * (led @ n - d) * n
            v = image - x
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (d - x @ n) / (v @ n)
            crossing = x + t[:, None] * v
            emit = crossing - led
            cos_e = emit[:, 2] / np.linalg.norm(emit, axis=1)
            ok = facing & (t > 0.0) & (t < 1.0) & (cos_e >= min_cos)
            ok &= _lit_through(camera, planes, m, crossing, on_mirror)
            out[sel] += np.where(ok, np.maximum(cos_e, 0.0) ** settings.led_profile_exponent, 0.0) / settings.led_count
    return out


# Crossings up to this many pixels from the masks count as on a mirror: the masks leave a margin
# (`Calibration.edge_margin_px`, 2 px by default) along the mirrors' edges that the mirrors fill.
MASK_REACH_PX = 4.0


def _near_mirror_pixels(labels: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels within MASK_REACH_PX of a mirror pixel of the masks."""
    from scipy.ndimage import distance_transform_edt

    return distance_transform_edt(labels < 0) <= MASK_REACH_PX


def _lit_through(camera: Camera, planes: list[MirrorPlane], m: int, crossing: np.ndarray,
                 on_mirror: np.ndarray) -> np.ndarray:
    """Whether light crossing mirror m's plane at `crossing` (camera frame) meets mirror m. The
    mirrors are the faces of a convex pyramid, each the half-space n·x ≥ d behind its plane,
    so a point of plane m lies on face m where the ray from the camera centre through it
    enters plane m's half-space last. Where the camera sees the crossing, it must also lie on a
    mirror in the masks (their outer edges end the mirrors); beyond the image the mirrors are
    taken to go on, since a calibration knows their planes but not their outlines there (16 %
    of the LEDs' paths through the default rig cross a mirror outside the view)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        entry = np.stack([np.where(crossing @ p.normal > 0.0, p.d / (crossing @ p.normal), np.inf) for p in planes], axis=1)
    ok = np.all(np.isfinite(entry), axis=1) & (np.argmax(entry, axis=1) == m)
    uv = camera.project(crossing)
    seen = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > -0.5) & (uv[:, 0] < camera.width - 0.5)
    seen &= (uv[:, 1] > -0.5) & (uv[:, 1] < camera.height - 0.5)
    col = np.clip(np.rint(np.nan_to_num(uv[:, 0])).astype(np.int64), 0, camera.width - 1)
    row = np.clip(np.rint(np.nan_to_num(uv[:, 1])).astype(np.int64), 0, camera.height - 1)
    return ok & (~seen | on_mirror[row, col])


def source_gains(camera: Camera, planes: list[MirrorPlane], labels: np.ndarray, origins: np.ndarray,
                 directions: np.ndarray, settings: MultipathSettings, emission: np.ndarray) -> np.ndarray:
    """(H·W,) how much of its surface's light each pixel stands for as a secondary source. LEDs
    beside the lens light the seen points less than a source at the lens centre would
    (`emission` below 1: a point lit by two LEDs of four), and send the rest of their light onto
    the same surfaces just beside the view (the walls above and below what the mirrors show),
    where the frame cannot see it. A source at the centre lights what the camera sees and
    nothing else, and the ring sends out about the same light, so each seen point stands for the
    light the centre would give it: the gain is the centre's emission over the ring's, between 1
    and the LED count (one LED's light standing for all of them). 1 with `leds` off."""
    if not settings.leds:
        return np.ones(len(emission))
    centre = emission_map(camera, planes, labels, origins, directions,
                          settings.model_copy(update={"led_count": 1, "led_radius": 0.0}))
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where(emission > 0.0, centre / emission, 1.0)
    return np.clip(gain, 1.0, float(settings.led_count))


# Anchors lit less than this (relative to a coaxial source) give no source beyond the view: the
# albedo read from them would be mostly noise.
MIN_ANCHOR_EMISSION = 0.2


def beyond_view_sources(camera: Camera, planes: list[MirrorPlane], labels: np.ndarray, emission: np.ndarray,
                        robot_T_camera: np.ndarray, settings: MultipathSettings) -> dict[str, np.ndarray]:
    """The secondary sources beyond the image (rust/src/multipath.rs, `BeyondView`), as the
    `beyond_*` arrays of the core's compensator. The LEDs' cone (`led_half_angle_deg`, 40°) is
    wider than the image (30–33° to its sides), and the mirrors go on beyond it, so the LEDs
    light the scene above and below the band the mirrors show: the walls near the robot higher
    up and lower down, and the floor around it. Those surfaces light the seen points, and the
    frame does not show them (BENCHMARKS.md, "The light beyond the view": a third of the
    interreflection at 1.5–5 m). Each ray on a grid of `stride` pixels continued beyond the
    image (pinhole; the lens's distortion is not known there) and within the cone meets the
    pyramid's face it enters last (as `_lit_through`), and continues the surface of the nearest
    pixel of that mirror at the image's edge, its anchor; its weight is the anchor's albedo lit
    as a source at the lens centre lights the ray's point."""
    s = settings
    st = s.stride
    half = math.radians(s.led_half_angle_deg)
    w, h = camera.width, camera.height
    # Pixel centres beyond the image, as far as the cone reaches.
    reach_u = math.ceil(camera.fx * math.tan(half)) + st
    reach_v = math.ceil(camera.fy * math.tan(half)) + st
    u = np.arange(camera.cx - reach_u, camera.cx + reach_u + 1, st)
    v = np.arange(camera.cy - reach_v, camera.cy + reach_v + 1, st)
    uu, vv = np.meshgrid(u, v)
    uu, vv = uu.ravel(), vv.ravel()
    outside = (uu < -0.5) | (uu > w - 0.5) | (vv < -0.5) | (vv > h - 0.5)
    uu, vv = uu[outside], vv[outside]
    ray = np.stack([(uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy, np.ones(len(uu))], axis=1)
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    cos_axis = ray[:, 2]
    inside_cone = cos_axis >= math.cos(half)
    uu, vv, ray, cos_axis = uu[inside_cone], vv[inside_cone], ray[inside_cone], cos_axis[inside_cone]
    # The face each ray meets: the plane it enters last (the mirrors are a convex pyramid's faces).
    with np.errstate(divide="ignore", invalid="ignore"):
        entry = np.stack([np.where(ray @ p.normal > 0.0, p.d / (ray @ p.normal), np.inf) for p in planes], axis=1)
    hits = np.all(np.isfinite(entry), axis=1)
    face = np.argmax(np.where(hits[:, None], entry, -np.inf), axis=1)
    t = entry[np.arange(len(ray)), face]
    # The anchor: the nearest pixel of that mirror to where the ray leaves the image, no
    # further than the masks' reach beyond the image's edge.
    edge_u, edge_v = np.clip(uu, 0, w - 1), np.clip(vv, 0, h - 1)
    anchor = np.full(len(ray), -1, dtype=np.int64)
    from scipy.ndimage import distance_transform_edt

    for m in range(len(planes)):
        sel = np.flatnonzero(hits & (face == m))
        if len(sel) == 0 or not np.any(labels == m):
            continue
        gap, (rows, cols) = distance_transform_edt(labels != m, return_indices=True)
        er, ec = np.rint(edge_v[sel]).astype(np.int64), np.rint(edge_u[sel]).astype(np.int64)
        near = gap[er, ec] <= MASK_REACH_PX + 1.0
        anchor[sel[near]] = rows[er[near], ec[near]] * w + cols[er[near], ec[near]]
    ok = (anchor >= 0) & (t > 0.0)
    ok[ok] &= emission[anchor[ok]] >= MIN_ANCHOR_EMISSION
    ray, face, t, anchor, cos_axis = ray[ok], face[ok], t[ok], anchor[ok], cos_axis[ok]
    origin = ray * t[:, None]
    normals = np.array([p.normal for p in planes]).reshape(-1, 3)[face]
    reflected = ray - 2.0 * np.sum(ray * normals, axis=1, keepdims=True) * normals
    # A cell of stride² pinhole pixels subtends st²·cos³/(fx·fy); the anchor's cell st²·Ω.
    cell = st * st * cos_axis ** 3 / (camera.fx * camera.fy)
    centre = cos_axis ** s.led_profile_exponent
    factor = centre * cell / (emission[anchor] * st * st * solid_angles(camera)[anchor])
    rotation, translation = robot_T_camera[:3, :3], robot_T_camera[:3, 3]
    return dict(
        beyond_origins=np.ascontiguousarray(origin @ rotation.T + translation, dtype=np.float64),
        beyond_directions=np.ascontiguousarray(reflected @ rotation.T, dtype=np.float64),
        beyond_paths=np.ascontiguousarray(t, dtype=np.float64),
        beyond_anchors=np.ascontiguousarray(anchor, dtype=np.uint32),
        beyond_factors=np.ascontiguousarray(factor, dtype=np.float64),
    )


def solid_angles(camera: Camera) -> np.ndarray:
    """(H·W,) each pixel's solid angle (sr): the parallelogram of the unit rays one pixel apart
    (central differences, one-sided beside a pixel without a ray; a mirror keeps solid angles).
    A pixel without a ray (NaN: an estimated lens distortion can fold an image corner back on
    itself, `Camera.rays`) gets 0: it is no source."""
    rays = camera.pixel_grid_rays()
    area = np.linalg.norm(np.cross(_ray_steps(rays, axis=1), _ray_steps(rays, axis=0)), axis=2)
    return np.where(np.isfinite(area), area, 0.0).reshape(-1)


def _ray_steps(rays: np.ndarray, axis: int) -> np.ndarray:
    """(H, W, 3) the change of the ray per pixel along `axis`: the central difference, or the
    one-sided one where a neighbour has no ray (NaN only where both sides lack one)."""
    step = np.diff(rays, axis=axis)
    pad = [(0, 0)] * rays.ndim
    pad[axis] = (1, 0)
    backward = np.pad(step, pad, constant_values=np.nan)
    pad[axis] = (0, 1)
    forward = np.pad(step, pad, constant_values=np.nan)
    central = np.gradient(rays, axis=axis)
    return np.where(np.isfinite(central), central, np.where(np.isfinite(forward), forward, backward))


class MultipathCompensation:
    """The compensation for one rig: built once by the scan extractor, then `correct` per batch
    of frames. `targets` are the pixels whose distance is corrected (the slice's candidates),
    `windows` (T, 2) the distances (m) at which each is worth correcting; every mirror pixel is
    a source."""

    def __init__(self, settings: MultipathSettings, camera: Camera, planes: list[MirrorPlane], labels: np.ndarray,
                 origins: np.ndarray, directions: np.ndarray, paths: np.ndarray, robot_origins: np.ndarray,
                 robot_directions: np.ndarray, targets: np.ndarray, windows: np.ndarray,
                 robot_T_camera: np.ndarray | None = None) -> None:
        self.settings = settings
        emission = emission_map(camera, planes, labels, origins, directions, settings)
        s = settings
        finite = np.all(np.isfinite(robot_origins), axis=1) & np.all(np.isfinite(robot_directions), axis=1)
        label = np.where(finite, labels.reshape(-1), -1).astype(np.int32)
        self._arguments: dict[str, Any] = dict(
            width=camera.width, height=camera.height,
            origins=np.ascontiguousarray(np.where(finite[:, None], robot_origins, 0.0), dtype=np.float64),
            directions=np.ascontiguousarray(np.where(finite[:, None], robot_directions, 0.0), dtype=np.float64),
            paths=np.ascontiguousarray(np.where(finite, paths, np.inf), dtype=np.float64),
            labels=label, solid_angles=solid_angles(camera), emission=emission,
            source_gain=source_gains(camera, planes, labels, origins, directions, settings, emission),
            targets=np.ascontiguousarray(targets, dtype=np.uint32),
            windows=np.ascontiguousarray(windows, dtype=np.float64),
            k=4.0 * math.pi * s.f_mod / SPEED_OF_LIGHT, amplitude_at_1m=s.amplitude_at_1m,
            mirror_reflectivity=s.mirror_reflectivity, stride=s.stride, target_stride=s.target_stride, normal_radius=s.normal_radius,
            smooth_radius=s.smooth_radius, depth_tolerance=s.depth_tolerance, min_reflectance=s.min_reflectance,
            min_cos=s.min_cos, min_separation=s.min_separation, max_ratio=s.max_ratio, visibility=s.visibility,
        )
        if settings.leds and settings.beyond_view and robot_T_camera is not None:
            self._arguments.update(beyond_view_sources(camera, planes, labels, emission, robot_T_camera, settings))
        self._core = _core._MultipathCompensator(**self._arguments)

    def with_threads(self, threads: int) -> MultipathCompensation:
        """The same compensation on a pool of `threads` workers (same results for any count)."""
        out = object.__new__(MultipathCompensation)
        out.settings, out._arguments = self.settings, self._arguments
        out._core = _core._MultipathCompensator(**self._arguments, threads=threads)
        return out

    def correct(self, distances: np.ndarray, amplitudes: np.ndarray) -> np.ndarray:
        """(F, H, W) float32 distances with the targets' interreflection taken out."""
        d = np.ascontiguousarray(distances, dtype=np.float32)
        a = np.ascontiguousarray(amplitudes, dtype=np.float32)
        return self._core.correct(d, a)
