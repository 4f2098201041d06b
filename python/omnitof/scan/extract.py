"""Range readings from omnidirectional ToF frames (paper sec. III): frames → 1° range scans.

Per frame, the paper's steps and what this module does for each:

1. "Removing lens distortion from range and intensity images". The distance image holds, per
   pixel, the one-way path along that pixel's *actual* (distorted) ray: camera centre → mirror →
   surface. Back-projecting each pixel through the lens model (`Camera.rays`, which inverts the
   distortion per pixel) therefore is the undistortion, exactly, with no resampling of the images
   (resampling would interpolate distances across depth edges into points on no surface).
   Where the camera has multipath, each frame's interreflection, predicted from its own points,
   is first taken out of the distances (`omnitof.scan.multipath`, setting `multipath`, off by
   default).
2. Rough amplitude filtering, two thresholds: pixels with amplitude < `min_amplitude` (weak,
   noisy returns of dark, far or steeply seen surfaces) and pixels whose amplitude scaled to
   1 m, amplitude·distance² < `min_amplitude_1m` (an apparent reflectance too low for a real
   surface at that distance: the weak diffuse return of metal and glass, and above all readings
   of surfaces beyond the unambiguous range, whose phase wrapped to a short distance but whose
   amplitude is that of the far surface) are dropped. In the simulated office (outer walls
   7.75–12 m away) the second threshold raises the share of matte-wall bins within 5 cm from
   49 % to 93 % (benchmarks/scan.py).
3. Mirror masks: only pixels with a mirror label (>= 0) count, each back-projected through its
   own mirror (its virtual camera, eq. 6).
4. 3D points in the robot frame: point = o + (distance − |o_cam|)·u, with o the point where the
   pixel's central ray meets its mirror, |o_cam| the path from the camera centre to it, and u the
   unit reflected direction, all precomputed once because the rig is fixed.
5. The slice: points within `band` of the horizontal plane z = `height` are kept. Because z is
   linear in the distance along each pixel's ray, this is precomputed as a per-pixel window of
   distances, so a frame costs one comparison per pixel.
6. Projection onto the floor and 1° bins: bearing atan2(y, x) counter-clockwise from the
   driving direction (robot +x); bin k holds bearings in [k − 0.5°, k + 0.5°) and is reported at
   the angle k°, k = 0..359, so `angles` are 0°, 1°, ..., 359° (evenly spaced, as LaserScan and
   CARMEN need). The range is the horizontal distance from the robot origin (on the floor below
   the camera), so a scan's sensor pose in the robot frame is (0, 0, 0).
7. One range per bin: the `statistic` of its points' ranges (`ScanSettings.statistic`). The
   default, the median, is unbiased on a single surface and ignores the few mixed ("flying")
   pixels of a depth edge, which fall between the two surfaces; a low percentile would favour
   the nearer of two surfaces in a bin (as a laser beam does) but pays with a bias of the
   noise's low tail. Measured on the rendered `room` (matte bins, 24 poses): median 0.2 cm
   median error and 99 % within 5 cm; 25th percentile 0.7 cm and 97 %; minimum 2.5 cm and 81 %.
   Points up to `range_margin` beyond `max_range` take part, so that a wall just inside
   max_range keeps the far half of its noisy points. A bin with fewer than `min_points` points,
   or whose value exceeds `max_range`, is "no reading": +inf (the ScanSequence convention;
   never 0, never NaN).
8. Optionally (`max_incidence_deg` below 90), bins whose surface the neighbouring bins show at
   a grazing angle are no reading either (`omnitof.scan.grazing`: where multipath reads long).

Frames: robot frame x forward, y left, z up (see `omnitof.sensor.mirrors`); robot_T_camera maps camera
points to robot points. Units: metres and radians.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any, NamedTuple

import numpy as np
from pydantic import ConfigDict, Field, ValidationError, field_validator, model_validator

from omnitof.settings_model import SettingsModel
from omnitof.sensor.camera import Camera
from omnitof.errors import ConfigError, InputError, leading_problem
from omnitof.sensor.mirrors import Mirror, MirrorParameterError, MirrorPlane, rigid_mount
from omnitof.scan.grazing import drop_grazing
from omnitof.scan.multipath import MultipathCompensation, MultipathSettings
from omnitof.scan.pixel_filter import PixelFilter, PixelFilterSettings
from omnitof.sensor.rig import Rig
from omnitof.types import ScanSequence

N_BINS = 360  # one-degree bins of bearing
_DEG = math.pi / 180.0
# Ranges are sorted as integers of this many metres (0.1 mm, far below the sensor's noise) in
# the low bits of one int64 sort key; 2^20 quanta = 104 m, more than any ToF range.
_RANGE_QUANTUM = 1e-4
_RANGE_BITS = 20
_RANGE_LIMIT = (1 << _RANGE_BITS) * _RANGE_QUANTUM
# How far (m) beyond a pixel's slice window its measured distance may lie and still be corrected
# for multipath (the interreflection lengthens grazing walls' distances by up to decimetres).
_MULTIPATH_MARGIN = 0.5


class ScanConfigError(ConfigError, ValueError):
    """A bad scan setting or rig (names the field); ConfigError and ValueError."""


class ScanInputError(InputError, ValueError):
    """A bad frame handed to the extractor (names the array and its shape); InputError and
    ValueError."""


class SlicePoints(NamedTuple):
    """Points of one frame in the slice: image rows and cols (K,) of their pixels, horizontal
    ranges (K,) in metres from the robot origin, and bins (K,) 0..359 (bearing in degrees)."""

    rows: np.ndarray
    cols: np.ndarray
    ranges: np.ndarray
    bins: np.ndarray


class ScanSettings(SettingsModel):
    """How a horizontal slice of the ToF point cloud becomes a 1° range scan.

    Defaults for the default rig (`design.default_rig`: SR4000 wide lens, 4 mirrors tilted 56°,
    the camera's optical centre 0.40 m above the floor, the mirror points 0.50–0.63 m): its rays
    leave the mirrors at elevations −21°…+16°. Counting the bearing bins whose rays cross the
    slice at 1, 2, 3, 5 and 7 m: 0.60 ± 0.10 m gives 209, 191, 181, 173, 168 of 360; 0.75 ± 0.10
    m gives 174, 210, 200, 184, 176; 0.50 m fewer beyond 1 m (184…163); 1.0 m none at 1 m. So the
    slice sits as high as it can below desk and table tops (0.72–0.75 m, thin boxes in the worlds)
    and the 0.75–0.80 m tops of low furniture: a slice through a table top gives a range anywhere
    along it. Rendered (benchmarks/scan.py, 24 poses per world, share of bins within 5 cm of the
    true distance): room 89 % at 0.60 ± 0.10 against 79 % at 0.75 ± 0.10; office 85 % against
    67 %, and 43 % at 0.60 ± 0.15, whose band reaches the desk tops; corridor2 91 % against 88 %.
    The price is more empty bins than at 0.75 m (room 46 % against 41 %).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    height: float = Field(0.60, gt=0.0, description="height of the slice plane above the floor (m)")
    band: float = Field(
        0.10, gt=0.0, description="half-thickness of the slice (m): points with |z − height| <= band count"
    )
    min_amplitude: float = Field(
        40.0,
        ge=0.0,
        description="pixels with a lower amplitude (sample units) are dropped: the paper's rough filter "
        "against specular and glass surfaces. 40 units is σ_d ≈ 11 cm per pixel with the default "
        "SensorNoise; a matte wall (albedo 0.6) seen through the mirrors at 7 m gives about 70",
    )
    min_amplitude_1m: float = Field(
        300.0,
        ge=0.0,
        description="pixels whose amplitude scaled to 1 m, amplitude × distance² (sample units·m²), is lower are "
        "dropped. Amplitude falls as 1/r², so this is an apparent reflectance: 300 is a Lambertian albedo of "
        "about 0.05 facing the camera through the mirrors (SensorNoise.amplitude_at_1m 7300 × mirror 0.9²), "
        "or 0.1 at 60° incidence. It drops what the paper's rough filter aims at (metal's and glass's weak "
        "diffuse return) and, above all, wrapped readings: a wall 9 m away reads 1.5 m (phase wrap at 7.49 m) "
        "with the amplitude of 9 m, about 100 units·m² scaled to its apparent 1.5 m. 0 turns it off",
    )
    max_range: float = Field(
        7.0,
        gt=0.0,
        le=100.0,
        description="bins whose range exceeds this (m) are no reading; below the 7.49 m unambiguous range "
        "at 20 MHz, so that wrapped distances of far walls near it are not trusted",
    )
    range_margin: float = Field(
        0.5,
        ge=0.0,
        le=100.0,
        description="points up to this far (m) beyond max_range still feed their bin's statistic, so that a "
        "wall just inside max_range keeps its far points (cut at max_range, its median came out short by "
        "5-30 cm: a sixth of the office's bad bins); the bin is no reading if the statistic exceeds max_range. "
        "About five times a pixel's noise at 7 m (10 cm). Used with statistics at or below the median only "
        "(a higher one would be pushed beyond max_range); max_range + range_margin must stay below 104.86 m",
    )
    min_range: float = Field(
        0.3, ge=0.0, description="points nearer than this horizontally (m) are dropped (the robot's own body)"
    )
    statistic: str = Field(
        "median",
        description="how a bin's points become one range: 'median', 'min', 'max', or 'p<q>' for the q-th "
        "percentile (0..100, linear interpolation), e.g. 'p25'",
    )
    min_points: int = Field(2, ge=1, description="bins with fewer points are no reading (a lone flying pixel)")
    max_incidence_deg: float = Field(
        90.0,
        gt=0.0,
        le=90.0,
        description="bins whose surface is seen more than this far from its normal (degrees, estimated from the "
        "neighbouring bins, omnitof.scan.grazing) are no reading: there multipath makes a ToF camera read long. "
        "With multipath alone on, 70 raises the simulated corridors' matte bins within 5 cm from 87-88 % to "
        "94-95 % (60: 97 %), but costs the filter the walls ahead, hence off (90) by default",
    )
    pixel_filter: PixelFilterSettings = Field(
        default_factory=PixelFilterSettings,
        description="the flying-pixel and multipath filter (omnitof.scan.pixel_filter)",
    )
    multipath: MultipathSettings = Field(
        default_factory=MultipathSettings,
        description="the multipath compensation (omnitof.scan.multipath): each frame's interreflection predicted "
        "from its own points and taken out of the distances, after the distance correction; off by default",
    )

    @field_validator("statistic")
    @classmethod
    def _known_statistic(cls, value: str) -> str:
        _quantile(value)  # raises for an unknown statistic
        return value

    @model_validator(mode="after")
    def _sortable_ranges(self) -> "ScanSettings":
        if self.min_range >= self.max_range:
            raise ValueError(f"min_range {self.min_range:g} m must be less than max_range {self.max_range:g} m: "
                             "every bin would be empty")
        if self.max_range + self.range_margin >= _RANGE_LIMIT:
            raise ValueError(
                f"max_range + range_margin is {self.max_range + self.range_margin:g} m; it must stay below "
                f"{_RANGE_LIMIT:.2f} m, the ranges the extraction sorts (0.1 mm steps in {_RANGE_BITS} bits)"
            )
        return self

    def quantile(self) -> float:
        """The statistic as a quantile in [0, 1] (min 0, median 0.5, max 1)."""
        return _quantile(self.statistic)


def _quantile(statistic: str) -> float:
    named = {"min": 0.0, "median": 0.5, "max": 1.0}
    if statistic in named:
        return named[statistic]
    if statistic.startswith("p"):
        try:
            q = float(statistic[1:])
        except ValueError:
            q = math.nan
        if 0.0 <= q <= 100.0:
            return q / 100.0
    raise ScanConfigError(
        f"ScanSettings.statistic must be 'median', 'min', 'max' or 'p<0..100>', got {statistic!r}"
    )


def scan_settings(settings: ScanSettings | None = None, **overrides: Any) -> ScanSettings:
    """ScanSettings from `settings` (default: the defaults) with fields replaced by keyword
    arguments; a bad value raises ScanConfigError naming the field (not pydantic's
    ValidationError), e.g. for a command line."""
    base = {} if settings is None else settings.model_dump()
    base.update(overrides)
    try:
        out = ScanSettings(**base)
    except ValidationError as err:
        first = leading_problem(err.errors())
        name = ".".join(str(p) for p in first["loc"]) or "(settings)"
        raise ScanConfigError(f"ScanSettings.{name}: {first['msg']}") from None
    return out


class ScanExtractor:
    """Turns distance and amplitude images of one fixed rig into 360 one-degree ranges.

    Args:
        camera: intrinsics and distortion of the ToF camera.
        planes: the mirror planes (camera frame); `Mirror` objects are accepted too (their plane
            is used).
        labels: (H, W) int, the mirror index of each pixel, −1 for pixels to ignore (e.g.
            `mirrors.masks`, which leaves out mixed pixels along mirror edges).
        robot_T_camera: 4×4 mount (e.g. `mirrors.camera_mount()`).
        settings: a ScanSettings; keyword arguments (height, band, min_amplitude,
            min_amplitude_1m, max_range, min_range, statistic, min_points) override its fields.

    Everything geometric is computed here, once: per usable pixel the mirror point and reflected
    direction in the robot frame and the window of distances that lands in the slice. Pixels
    that never reach the slice are left out of the per-frame work altogether.
    """

    def __init__(
        self,
        camera: Camera,
        planes: Sequence[MirrorPlane | Mirror],
        labels: np.ndarray,
        robot_T_camera: np.ndarray,
        *,
        settings: ScanSettings | None = None,
        distance_correction: Any = None,
        **overrides: Any,
    ) -> None:
        self.camera = camera
        # The calibration's systematic distance error (calibration.distance), removed from
        # every frame before anything else; None: distances used as the camera reports them.
        self.distance_correction = distance_correction
        self.settings = scan_settings(settings, **overrides)
        self.planes = [p.plane if isinstance(p, Mirror) else p for p in planes]
        labels = np.asarray(labels)
        if labels.shape != camera.shape:
            raise ScanConfigError(f"labels must have the camera's shape {camera.shape}, got {labels.shape}")
        if not np.issubdtype(labels.dtype, np.integer):
            raise ScanConfigError(f"labels must be integers (mirror index, −1 unused), got {labels.dtype}")
        if labels.size and (labels.min() < -1 or labels.max() >= len(self.planes)):
            raise ScanConfigError(
                f"labels must lie in −1..{len(self.planes) - 1} (one index per mirror plane), "
                f"got {labels.min()}..{labels.max()}"
            )
        self.labels = labels.astype(np.int32)
        try:
            # Its rotation made exact: the multipath compensation needs unit directions.
            self.robot_T_camera = rigid_mount(robot_T_camera)
        except MirrorParameterError as err:
            raise ScanConfigError(str(err)) from None
        self._precompute()

    # --- construction helpers ----------------------------------------------------------------

    @classmethod
    def from_calibration(cls, cal: Any, **settings: Any) -> ScanExtractor:
        """From a calibration with attributes .camera, .planes, .labels, .robot_T_camera."""
        return cls(cal.camera, cal.planes, cal.labels, cal.robot_T_camera,
                   distance_correction=getattr(cal, "distance_correction", None), **settings)

    @classmethod
    def from_rig(cls, rig: Rig | None = None, *, edge_margin_px: float = 2.0, **settings: Any) -> ScanExtractor:
        """From a designed rig (default `design.default_rig()`), labels from its outlines
        (`Rig.masks`) with the given edge margin: what the simulator renders."""
        from omnitof.sensor.design import default_rig

        rig = default_rig() if rig is None else rig
        return cls(rig.camera, list(rig.planes), rig.masks(edge_margin_px), rig.robot_T_camera, **settings)

    # --- results -----------------------------------------------------------------------------

    @property
    def angles(self) -> np.ndarray:
        """(360,) float64 bearings of the bins, radians: 0, 1°, ..., 359° (robot frame, counter-
        clockwise from the driving direction)."""
        return np.arange(N_BINS, dtype=np.float64) * _DEG

    @property
    def shape(self) -> tuple[int, int]:
        """The image shape (H, W) the extractor expects."""
        return self.camera.shape

    @property
    def candidate_pixels(self) -> np.ndarray:
        """(H, W) bool: pixels whose ray crosses the slice (at some distance) at all."""
        out = np.zeros(self.camera.shape, dtype=bool)
        out.reshape(-1)[self._index] = True
        return out

    def extract(self, distance: np.ndarray, amplitude: np.ndarray) -> np.ndarray:
        """(360,) float32 ranges (m) of one frame; +inf where a bin has no reading.

        Args:
            distance: (H, W) one-way distances (m) as the camera reports them (NaN allowed:
                such pixels are dropped).
            amplitude: (H, W) amplitudes, sample units.
        """
        d, a = self._check(distance, amplitude, single=True)
        return self._extract(d, a)[0]

    def extract_many(self, distances: np.ndarray, amplitudes: np.ndarray, *, chunk: int = 32,
                     corrected: np.ndarray | None = None) -> np.ndarray:
        """(N, 360) float32 ranges of N frames (N, H, W); +inf where no reading. Frames are
        processed `chunk` at a time (bounded memory, same result; 32 ran fastest, 2 cores).
        `corrected` (N,) bool marks frames whose distances `corrected_distances` gave already."""
        d, a = self._check(distances, amplitudes, single=False, corrected=corrected)
        if chunk < 1:
            raise ScanConfigError(f"chunk must be >= 1, got {chunk!r}")
        out = np.empty((len(d), N_BINS), dtype=np.float32)
        for start in range(0, len(d), chunk):
            out[start : start + chunk] = self._extract(d[start : start + chunk], a[start : start + chunk])
        return out

    def slice_points(self, distance: np.ndarray, amplitude: np.ndarray) -> SlicePoints:
        """The points of one frame that fed a bin: their pixels, horizontal ranges and bins
        (points of bins that end up empty for want of min_points included)."""
        d, a = self._check(distance, amplitude, single=True)
        _, pixel, r, bins = self._points(d, a)
        rows, cols = np.divmod(self._index[pixel], self.camera.width)
        return SlicePoints(rows, cols, r.astype(np.float64), bins)

    def slice_pixels(self, distance: np.ndarray, amplitude: np.ndarray) -> np.ndarray:
        """(H, W) bool: the pixels whose points fed the slice in this frame (the overlay mask
        for choosing the height; see `viz.scans.plot_slice_overlay`)."""
        pts = self.slice_points(distance, amplitude)
        out = np.zeros(self.camera.shape, dtype=bool)
        out[pts.rows, pts.cols] = True
        return out

    def corrected_distances(self, distances: np.ndarray, amplitudes: np.ndarray) -> np.ndarray:
        """(N, H, W) distances of frames (N, H, W) with the distance correction and the
        multipath compensation applied, as every extraction applies them. A frame that goes
        both into `rays` and into `extract_many` (a 3D filter's keyframe) is corrected once
        this way and handed to both with `corrected=True`: the multipath compensation takes
        about as long as the rest of the extraction."""
        return self._check(distances, amplitudes, single=False)[0]

    def rays(self, distance: np.ndarray, amplitude: np.ndarray, *,
             corrected: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The measured rays of one frame, robot frame, metres: (origins (K, 3), points (K, 3)),
        where each pixel's light leaves its mirror and the surface point it measured. Every
        filter but the slice applies (mirror mask, both amplitude thresholds, finite distance,
        the point beyond the mirror, horizontal range within min_range..max_range); rows in
        image order. For 3D maps: the space between origin and point is free. `corrected`:
        the distance is one `corrected_distances` gave."""
        d, a = self._check(distance, amplitude, single=True, corrected=corrected)
        flat_d = d.reshape(-1).astype(np.float64)
        flat_a = a.reshape(-1).astype(np.float64)
        pixels = np.flatnonzero(self._all_ok)
        amp, dist = flat_a[pixels], flat_d[pixels]
        with np.errstate(invalid="ignore"):
            keep = (amp >= self.settings.min_amplitude) & np.isfinite(dist)
            keep &= amp * dist * dist >= self.settings.min_amplitude_1m
        pixels = pixels[keep]
        s = flat_d[pixels] - self._all_path[pixels]
        origins = self._all_origin[pixels]
        pts = origins + s[:, None] * self._all_dir[pixels]
        r = np.hypot(pts[:, 0], pts[:, 1])
        ok = (s >= 0.0) & (r >= self.settings.min_range) & (r <= self.settings.max_range)
        return origins[ok], pts[ok]

    def points(self, distance: np.ndarray, amplitude: np.ndarray) -> np.ndarray:
        """(K, 3) robot-frame points (m) of one frame that passed every filter except the
        slice (see `rays`). For plots of the cloud and checks of the rig."""
        return self.rays(distance, amplitude)[1]

    # --- internals ---------------------------------------------------------------------------

    def _precompute(self) -> None:
        cam = self.camera
        rays = np.asarray(cam.pixel_grid_rays(), dtype=np.float64).reshape(-1, 3)
        flat = self.labels.reshape(-1)
        origin = np.full_like(rays, np.nan)
        direction = np.full_like(rays, np.nan)
        for mirror_index, plane in enumerate(self.planes):  # loop over mirrors; pixels vectorised
            sel = np.flatnonzero(flat == mirror_index)
            if len(sel) == 0:
                continue
            hits = plane.intersect(np.zeros((len(sel), 3)), rays[sel])
            origin[sel] = hits.points
            direction[sel] = hits.directions
        ok = (flat >= 0) & np.all(np.isfinite(origin), axis=1) & np.all(np.isfinite(direction), axis=1)
        path = np.linalg.norm(origin, axis=1)  # camera centre → mirror, metres
        rotation, translation = self.robot_T_camera[:3, :3], self.robot_T_camera[:3, 3]
        origin_r = origin @ rotation.T + translation
        dir_r = direction @ rotation.T
        # Kept for `points` (every labelled pixel, whatever the slice).
        self._all_ok, self._all_path = ok, path
        self._all_origin, self._all_dir = origin_r, dir_r
        # The slice as a window of distances: z(s) = oz + s·uz within height ± band, s >= 0.
        s_cfg = self.settings
        oz, uz = origin_r[:, 2], dir_r[:, 2]
        lo_z, hi_z = s_cfg.height - s_cfg.band, s_cfg.height + s_cfg.band
        with np.errstate(divide="ignore", invalid="ignore"):
            s1, s2 = (lo_z - oz) / uz, (hi_z - oz) / uz
        s_lo, s_hi = np.minimum(s1, s2), np.maximum(s1, s2)
        flat_ray = np.abs(uz) < 1e-12  # horizontal ray: in the slice everywhere or nowhere
        inside = (oz >= lo_z) & (oz <= hi_z)
        s_lo = np.where(flat_ray, np.where(inside, 0.0, np.inf), s_lo)
        s_hi = np.where(flat_ray, np.where(inside, np.inf, -np.inf), s_hi)
        s_lo = np.maximum(s_lo, 0.0)
        # Beyond the horizontal point horizon no point counts; its s bounds the window too
        # (|horizontal position| grows at least as fast as s·|u_xy| − |o_xy|).
        horiz = np.hypot(dir_r[:, 0], dir_r[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            s_far = (self._point_horizon() + np.hypot(origin_r[:, 0], origin_r[:, 1])) / horiz
        s_hi = np.minimum(s_hi, np.where(horiz > 0.0, s_far, np.inf))
        candidate = np.flatnonzero(ok & (s_lo <= s_hi))
        # Order the candidates by the bin and range they give at the middle of their window, so
        # that a frame's points arrive nearly sorted by bin (the sort below is then cheap).
        s_mid = 0.5 * (s_lo[candidate] + s_hi[candidate])
        x_mid = origin_r[candidate, 0] + s_mid * dir_r[candidate, 0]
        y_mid = origin_r[candidate, 1] + s_mid * dir_r[candidate, 1]
        nominal_bin = np.rint(np.arctan2(y_mid, x_mid) / _DEG).astype(np.int64) % N_BINS
        index = candidate[np.lexsort((np.hypot(x_mid, y_mid), nominal_bin))]
        self._index = index
        self._d_lo = (path[index] + s_lo[index]).astype(np.float32)
        self._d_hi = (path[index] + s_hi[index]).astype(np.float32)
        # Horizontal position is linear in the measured distance d: x = (ox − L·ux) + ux·d.
        self._coef = np.ascontiguousarray(
            np.stack(
                [
                    origin_r[index, 0] - path[index] * dir_r[index, 0],
                    dir_r[index, 0],
                    origin_r[index, 1] - path[index] * dir_r[index, 1],
                    dir_r[index, 1],
                ],
                axis=1,
            ),
            dtype=np.float32,
        )
        self._q = s_cfg.quantile()
        self._filter = PixelFilter(s_cfg.pixel_filter, self.labels, index) if s_cfg.pixel_filter.enabled else None
        self._multipath = None
        if s_cfg.multipath.enabled:
            # The candidates are corrected wherever their distance may land in the slice once
            # corrected: the correction shortens distances by up to decimetres.
            windows = np.stack([path[index] + s_lo[index], path[index] + s_hi[index] + _MULTIPATH_MARGIN], axis=1)
            self._multipath = MultipathCompensation(
                s_cfg.multipath, self.camera, self.planes, self.labels, origin, direction, path, origin_r, dir_r,
                index, windows, self.robot_T_camera,
            )

    def _point_horizon(self) -> float:
        """The horizontal range (m) up to which points feed the bins: max_range + range_margin
        for a statistic at or below the median; max_range for a higher one, which the far
        points would push beyond max_range, leaving a wall just inside it no reading."""
        if self.settings.quantile() > 0.5:
            return self.settings.max_range
        return self.settings.max_range + self.settings.range_margin

    def _check(self, distance: Any, amplitude: Any, *, single: bool,
               corrected: bool | np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        d = np.asarray(distance)
        a = np.asarray(amplitude)
        want = self.camera.shape if single else ("N", *self.camera.shape)
        for name, arr in (("distance" if single else "distances", d), ("amplitude" if single else "amplitudes", a)):
            good = arr.shape == self.camera.shape if single else (arr.ndim == 3 and arr.shape[1:] == self.camera.shape)
            if not good:
                raise ScanInputError(
                    f"{name} must have shape {tuple(want)} (rows, cols of the camera), got {arr.shape}"
                )
            if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
                raise ScanInputError(f"{name} must hold real numbers, got dtype {arr.dtype}")
        if d.shape != a.shape:
            raise ScanInputError(f"distances {d.shape} and amplitudes {a.shape} must have one shape")
        if single:
            d, a = d[None], a[None]
        # Frames marked `corrected` were corrected already (corrected_distances): not twice.
        if corrected is not None and np.shape(corrected) not in ((), (len(d),)):
            raise ScanInputError(f"corrected must hold one flag per frame ({len(d)}), got shape {np.shape(corrected)}")
        done = np.broadcast_to(np.asarray(False if corrected is None else corrected, dtype=bool), (len(d),))
        if done.all() or (self.distance_correction is None and self._multipath is None):
            return d, a
        fixed, amp = (d, a) if not done.any() else (d[~done], a[~done])
        if self.distance_correction is not None:
            fixed = self.distance_correction.correct(fixed, amp)
        if self._multipath is not None:
            fixed = self._multipath.correct(fixed, amp)
        if not done.any():
            return fixed, a
        out = np.empty(d.shape, dtype=fixed.dtype)
        out[done], out[~done] = d[done], fixed
        return out, a

    def _points(
        self, d: np.ndarray, a: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(frame, candidate pixel, range, bin) of every point of frames (N, H, W) that feeds a
        bin; per-frame work is array operations on the candidate pixels only. Ranges are
        float32 (0.5 µm resolution at 7 m: far below the sensor's noise)."""
        n = len(d)
        dd = np.take(d.reshape(n, -1), self._index, axis=1).astype(np.float32, copy=False)
        aa = np.take(a.reshape(n, -1), self._index, axis=1)
        keep = (aa >= self.settings.min_amplitude) & (dd >= self._d_lo) & (dd <= self._d_hi)
        if self.settings.min_amplitude_1m > 0.0:
            keep &= aa * dd * dd >= self.settings.min_amplitude_1m
        if self._filter is not None:
            keep &= self._filter.keep(d.reshape(n, -1), dd, aa)
        flat = np.flatnonzero(keep)
        frame, pixel = np.divmod(flat, len(self._index))
        value = dd.reshape(-1)[flat]
        coef = np.take(self._coef, pixel, axis=0)
        x = coef[:, 0] + coef[:, 1] * value
        y = coef[:, 2] + coef[:, 3] * value
        r = np.hypot(x, y)
        within = (r >= self.settings.min_range) & (r <= self._point_horizon())
        if not within.all():
            frame, pixel, x, y, r = frame[within], pixel[within], x[within], y[within], r[within]
        bins = np.rint(np.arctan2(y, x) * np.float32(1.0 / _DEG)).astype(np.int64) % N_BINS
        return frame, pixel, r, bins

    def _extract(self, d: np.ndarray, a: np.ndarray) -> np.ndarray:
        n = len(d)
        frame, _, r, bins = self._points(d, a)
        out = np.full(n * N_BINS, np.inf, dtype=np.float32)
        if len(r) == 0:
            return out.reshape(n, N_BINS)
        # One integer sort orders the points by (frame, bin) and, within a bin, by range: the
        # range in units of _RANGE_QUANTUM fills the low _RANGE_BITS bits. The points arrive
        # nearly sorted by bin, which the stable (radix/timsort) sort exploits.
        key = frame * N_BINS + bins
        packed = (key << _RANGE_BITS) | np.rint(r * (1.0 / _RANGE_QUANTUM)).astype(np.int64)
        packed.sort(kind="stable")
        r_sorted = (packed & ((1 << _RANGE_BITS) - 1)).astype(np.float64) * _RANGE_QUANTUM
        counts = np.bincount(packed >> _RANGE_BITS, minlength=n * N_BINS)
        filled = np.flatnonzero(counts >= self.settings.min_points)
        starts = np.cumsum(counts) - counts
        position = starts[filled] + self._q * (counts[filled] - 1)
        below = np.floor(position).astype(np.int64)
        above = np.minimum(below + 1, starts[filled] + counts[filled] - 1)
        frac = position - below
        out[filled] = r_sorted[below] * (1.0 - frac) + r_sorted[above] * frac
        out[out > self.settings.max_range] = np.inf
        out = out.reshape(n, N_BINS)
        if self.settings.max_incidence_deg < 90.0:
            out = drop_grazing(out, _DEG, math.radians(self.settings.max_incidence_deg))
        return out


def scans_from_frames(
    extractor: ScanExtractor,
    frames: Iterable[Any],
    *,
    timestamps: np.ndarray | None = None,
    odometry: np.ndarray | None = None,
    ground_truth: np.ndarray | None = None,
    source: str = "",
    chunk: int = 256,
) -> ScanSequence:
    """A ScanSequence (360 beams at 0°..359°, sensor_pose (0, 0, 0): the points are already in
    the robot frame) from ToF frames, ready for `io.rosbag.write_laserscan_bag` (LaserScan) and
    `io.carmen.write_carmen` (CARMEN log) and for the SLAM filter.

    Args:
        extractor: the rig's ScanExtractor.
        frames: objects with `.distance` and `.amplitude` (H, W): `io.rosbag.ToFFrameStamped`
            (its .timestamp, .odometry, .ground_truth are used when present) or
            `sim.render.Frame` (its .pose is the ground truth). A frame whose
            `.distance_corrected` is true carries distances that
            `extractor.corrected_distances` gave already.
        timestamps: (N,) seconds; default the frames' .timestamp.
        odometry: (N, 3) odometry poses; default the frames' .odometry.
        ground_truth: (N, 3) true poses; default the frames' .ground_truth or .pose, else none.
        source: a name for reports.
        chunk: frames extracted at a time.

    Raises:
        ScanInputError: a frame without distance/amplitude, or missing timestamps/odometry.
    """
    stamps: list[float] = []
    odo: list[np.ndarray | None] = []
    truth: list[np.ndarray | None] = []
    ranges: list[np.ndarray] = []
    batch_d: list[np.ndarray] = []
    batch_a: list[np.ndarray] = []
    batch_done: list[bool] = []

    def flush() -> None:
        if batch_d:
            ranges.append(extractor.extract_many(np.stack(batch_d), np.stack(batch_a), corrected=np.array(batch_done)))
            batch_d.clear()
            batch_a.clear()
            batch_done.clear()

    for i, frame in enumerate(frames):
        if not (hasattr(frame, "distance") and hasattr(frame, "amplitude")):
            raise ScanInputError(f"frame {i} has no .distance and .amplitude images")
        batch_d.append(np.asarray(frame.distance))
        batch_a.append(np.asarray(frame.amplitude))
        batch_done.append(bool(getattr(frame, "distance_corrected", False)))
        stamps.append(getattr(frame, "timestamp", math.nan))
        odo.append(getattr(frame, "odometry", None))
        gt = getattr(frame, "ground_truth", None)
        truth.append(gt if gt is not None else getattr(frame, "pose", None))
        if len(batch_d) >= chunk:
            flush()
    flush()
    n = len(stamps)
    all_ranges = np.concatenate(ranges) if ranges else np.zeros((0, N_BINS), dtype=np.float32)
    t = np.asarray(stamps if timestamps is None else timestamps, dtype=np.float64)
    if t.shape != (n,) or not np.all(np.isfinite(t)):
        raise ScanInputError(f"timestamps: need {n} finite values (give timestamps= or frames with .timestamp)")
    if odometry is None:
        if any(o is None for o in odo):
            raise ScanInputError("odometry: a frame has none; give odometry= (N, 3)")
        odometry = np.array(odo, dtype=np.float64).reshape(n, 3)
    odometry = np.asarray(odometry, dtype=np.float64)
    if odometry.shape != (n, 3):
        raise ScanInputError(f"odometry must have shape ({n}, 3), got {odometry.shape}")
    if ground_truth is None and n and all(g is not None for g in truth):
        ground_truth = np.array(truth, dtype=np.float64).reshape(n, 3)
    return ScanSequence(
        timestamps=t,
        ranges=all_ranges,
        angles=extractor.angles,
        odometry=odometry,
        sensor_pose=np.zeros(3),
        max_range=extractor.settings.max_range,
        ground_truth=ground_truth,
        source=source,
        max_range_rule="the scan extraction's max_range",
    )
