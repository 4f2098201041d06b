"""Which mirror pixels the camera's own light reaches: the LEDs sit beside the lens, not at its
centre, so the mirrors do not send their light exactly where they send the view.

The paper names this as a limit of the design: "performance degradation if the mirrors get
closer to the camera, because reflection of illumination no longer coincides with reflection
of the camera image". This module measures it for a rig, the geometry of rust/src/light.rs
done here independently with numpy: a pixel's central ray meets its mirror at M and goes on to
the surface point X at a one-way path `distance` from the camera; X is lit if some LED L reaches
it, either through a mirror m (the segment from X to L's image in m's plane meets m inside its
outline, and the LED emits towards that point within its largest angle) or directly (within
its largest angle, and no mirror in the way). Frames and units: camera frame, metres.

The closer the mirrors are to the lens, the larger the angle an LED's offset makes seen from
them, and the more of each mirror's view the LEDs reach only through a neighbouring mirror
(sending their light elsewhere) or not at all: `lit_share` falls as the apex comes down
(`omnitof design --apex-sweep`; BENCHMARKS.md, "ToF error budget").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from omnitof.sensor.camera import Camera
from omnitof.sensor.mirrors import Mirror, masks, viewing_rays
from omnitof.sensor.tof_errors import ToFErrors

# The surface distance the lit share is quoted at (one-way path, metres): a wall at 2 m, the
# working point of the sensor model (`omnitof.sensor.tof`).
DEFAULT_LIT_DISTANCE = 2.0


def lit_pixels(camera: Camera, mirrors: Sequence[Mirror], errors: ToFErrors,
               distance: float | np.ndarray = DEFAULT_LIT_DISTANCE, edge_margin_px: float = 0.0) -> np.ndarray:
    """(H, W) bool: pixels that look through a mirror (`masks` with `edge_margin_px`) at a
    point the LEDs of `errors` light (module docstring); `distance` a scalar or (H, W)."""
    labels = masks(camera, mirrors, edge_margin_px)
    rays = viewing_rays(camera, mirrors, labels)
    seen = labels.reshape(-1) >= 0
    origin = rays.origins.reshape(-1, 3)[seen]
    direction = rays.directions.reshape(-1, 3)[seen]
    path = np.broadcast_to(np.asarray(distance, dtype=np.float64), camera.shape).reshape(-1)[seen]
    to_mirror = np.linalg.norm(origin, axis=1)
    x = origin + (path - to_mirror)[:, None] * direction
    min_cos = np.cos(np.radians(errors.led_half_angle_deg))
    lit = np.zeros(len(x), dtype=bool)
    for led in errors.led_positions():
        lit |= _direct(x, led, mirrors, min_cos)
        for mirror in mirrors:
            lit |= _through(x, led, mirror, min_cos)
    out = np.zeros(camera.shape, dtype=bool)
    out.reshape(-1)[np.flatnonzero(seen)] = lit
    return out


def lit_share(camera: Camera, mirrors: Sequence[Mirror], errors: ToFErrors,
              distance: float = DEFAULT_LIT_DISTANCE, edge_margin_px: float = 2.0) -> float:
    """The share of the mirror pixels (edge margin as the scans use) whose point at `distance`
    the LEDs light."""
    seen = masks(camera, mirrors, edge_margin_px) >= 0
    if not seen.any():
        return float("nan")
    return float(lit_pixels(camera, mirrors, errors, distance, edge_margin_px)[seen].mean())


def _emits(direction: np.ndarray, min_cos: float) -> np.ndarray:
    """Within the LED's largest angle from the optical axis (+z)."""
    return direction[:, 2] >= min_cos * np.linalg.norm(direction, axis=1)


def _direct(x: np.ndarray, led: np.ndarray, mirrors: Sequence[Mirror], min_cos: float) -> np.ndarray:
    ok = _emits(x - led, min_cos)
    origins = np.broadcast_to(led, x.shape)
    reach = np.linalg.norm(x - led, axis=1)
    for mirror in mirrors:
        hits = mirror.intersect(origins, x - led)
        ok &= ~(hits.hit & (hits.distances < reach))
    return ok


def _through(x: np.ndarray, led: np.ndarray, mirror: Mirror, min_cos: float) -> np.ndarray:
    n, d = mirror.plane.normal, mirror.plane.d
    if led @ n >= d:  # the LED is behind this mirror
        return np.zeros(len(x), dtype=bool)
    image = led - 2.0 * (led @ n - d) * n
    hits = mirror.intersect(x, image - x)  # from the surface towards the LED's image
    ok = hits.hit.copy()
    ok[ok] = _emits(hits.points[ok] - led, min_cos)
    return ok
