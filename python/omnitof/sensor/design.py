"""How good is a mirror rig? Bearing coverage, elevation bands and resolution, and sweeps of them.

A rig is a camera, its mirrors (camera frame, see `omnitof.sensor.mirrors`) and the mount
robot_T_camera. Every number here comes from tracing each pixel's central ray through the rig
(`omnitof.sensor.mirrors.viewing_rays`), keeping only the pixels of `omnitof.sensor.mirrors.masks` (mixed
pixels along mirror edges left out), and expressing the reflected rays in the robot frame:

- bearing: atan2(y, x) in degrees, counter-clockwise from the driving direction, in [0, 360),
  binned into the 360 one-degree bins [k, k + 1);
- elevation: the angle above the horizontal plane, degrees.

Coverage counts a bearing bin as seen if at least one kept pixel's ray falls into it with an
elevation within ±elev_band_deg of horizontal. Why an elevation band rather than a height
slice: the scan (paper sec. III) keeps points within a distance t of a horizontal plane at the
sensor's height, and a ray of elevation ε stays inside that slice out to the range t/tan ε, so a
band of elevations is a band of usable ranges, the same at every distance from the robot and
independent of the room. The default ±10° keeps a ray within ±0.18 m of the slice height out to
1 m and within ±0.35 m out to 2 m. Coverage at any elevation is reported beside it, because a
quick estimate of a rig usually means that one.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from omnitof.sensor.illumination import lit_share
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sensor.camera import Camera
from omnitof.sensor.rig import Rig
from omnitof.sensor.mirrors import (
    DEFAULT_APEX_HEIGHT,
    Mirror,
    MirrorParameterError,
    bearing_of,
    masks,
    mount_rotation,
    pyramid,
    viewing_rays,
)

DEFAULT_ELEV_BAND_DEG = 10.0
BEARING_BINS = 360  # one-degree bins of bearing

# The rig chosen from `sweep` (see default_rig for the numbers and the reasons).
DEFAULT_RIG_MIRRORS = 4
DEFAULT_RIG_TILT_DEG = 56.0
DEFAULT_RIG_YAW_DEG = 0.0


@dataclass(frozen=True)
class MirrorStats:
    """One mirror's share of a rig.

    name: the mirror's name. bearing_deg: robot bearing it faces. pixels: kept pixels (after the
    edge margin). elevation_min_deg, elevation_max_deg: range of its rays' elevations (NaN if it
    keeps no pixel). band_pixels: kept pixels within the elevation band. band_bearings: number
    of one-degree bearing bins its band pixels see.
    """

    name: str
    bearing_deg: float
    pixels: int
    elevation_min_deg: float
    elevation_max_deg: float
    band_pixels: int
    band_bearings: int


@dataclass(frozen=True, eq=False)
class DesignReport:
    """Coverage of the 360 one-degree bearing bins by a rig (see the module docstring).

    pixels_per_bin: (360,) int, kept pixels within the elevation band per bin [k, k + 1)°.
    seen_any_elevation: (360,) bool, bins seen by a kept pixel at any elevation.
    median_elevation_deg: median elevation of all kept pixels' rays (0 = view centred on the
    horizon).
    """

    elev_band_deg: float
    edge_margin_px: float
    pixels_per_bin: np.ndarray
    seen_any_elevation: np.ndarray
    median_elevation_deg: float
    mirrors: tuple[MirrorStats, ...] = field(default=())

    @property
    def covered(self) -> np.ndarray:
        """(360,) bool: bins seen within the elevation band."""
        return self.pixels_per_bin > 0

    @property
    def coverage(self) -> float:
        """Share of the 360 bearing bins seen within the elevation band, 0–1."""
        return float(self.covered.mean())

    @property
    def coverage_any_elevation(self) -> float:
        """Share of the 360 bearing bins seen at any elevation, 0–1."""
        return float(self.seen_any_elevation.mean())

    @property
    def pixels_per_degree(self) -> float:
        """Mean number of in-band pixels per covered one-degree bin (0 if none is covered)."""
        covered = self.covered
        return float(self.pixels_per_bin[covered].mean()) if covered.any() else 0.0

    @property
    def largest_gap_deg(self) -> int:
        """The longest run of bins not seen within the band, wrapping around 360°, degrees."""
        return _longest_circular_run(~self.covered)

    @property
    def elevation_min_deg(self) -> float:
        """Lowest elevation over all mirrors, degrees."""
        return float(np.nanmin([m.elevation_min_deg for m in self.mirrors] or [np.nan]))

    @property
    def elevation_max_deg(self) -> float:
        """Highest elevation over all mirrors, degrees."""
        return float(np.nanmax([m.elevation_max_deg for m in self.mirrors] or [np.nan]))

    def format(self) -> str:
        """A plain-text summary and a table with one row per mirror."""
        band = self.elev_band_deg
        lines = [
            f"bearings seen within ±{band:g}° of horizontal: {100 * self.coverage:.1f} % "
            f"({int(self.covered.sum())} of {BEARING_BINS} one-degree bins); "
            f"at any elevation: {100 * self.coverage_any_elevation:.1f} %",
            f"pixels per degree of bearing (mean over covered bins): {self.pixels_per_degree:.1f};"
            f" largest gap {self.largest_gap_deg}°; median elevation "
            f"{self.median_elevation_deg:+.1f}°; edge margin {self.edge_margin_px:g} px",
            "",
            f"{'mirror':<14}{'faces':>8}{'pixels':>8}{'elev min':>10}{'elev max':>10}"
            f"{'band px':>9}{'band bins':>11}",
        ]
        for m in self.mirrors:
            lines.append(
                f"{m.name:<14}{m.bearing_deg:>7.1f}°{m.pixels:>8d}{m.elevation_min_deg:>+9.1f}°"
                f"{m.elevation_max_deg:>+9.1f}°{m.band_pixels:>9d}{m.band_bearings:>11d}"
            )
        return "\n".join(lines)


def design_report(
    camera: Camera,
    mirrors: Sequence[Mirror],
    robot_T_camera: np.ndarray | None = None,
    *,
    elev_band_deg: float = DEFAULT_ELEV_BAND_DEG,
    edge_margin_px: float = 2.0,
) -> DesignReport:
    """Measure a rig: bearing coverage within an elevation band, elevation bands per mirror,
    pixels per degree of bearing.

    Args:
        camera: the camera (intrinsics and distortion).
        mirrors: its mirrors, camera frame.
        robot_T_camera: the mount (4×4); default camera_mount(). Only its rotation matters.
        elev_band_deg: half-width of the band of usable elevations around horizontal, degrees.
        edge_margin_px: mixed pixels this close to a mirror boundary are left out (see masks).
    """
    band = float(elev_band_deg)
    if not (math.isfinite(band) and 0.0 <= band <= 90.0):
        raise MirrorParameterError(f"elev_band_deg must lie in [0, 90], got {elev_band_deg!r}")
    rotation = mount_rotation(robot_T_camera)  # robot_R_camera; the height plays no part
    labels = masks(camera, mirrors, edge_margin_px).reshape(-1)
    directions = viewing_rays(camera, mirrors, labels.reshape(camera.shape)).directions
    bearing, elevation = _bearing_elevation(directions.reshape(-1, 3) @ rotation.T)
    kept = labels >= 0
    in_band = kept & (np.abs(elevation) <= band)
    # Rays of pixels left out are NaN; give them bin 0, they are never counted.
    bins = np.floor(np.nan_to_num(bearing)).astype(np.int64) % BEARING_BINS
    per_bin = np.bincount(bins[in_band], minlength=BEARING_BINS)
    any_elevation = np.bincount(bins[kept], minlength=BEARING_BINS) > 0
    stats = tuple(
        _mirror_stats(mirror, robot_T_camera, labels == index, in_band, elevation, bins)
        for index, mirror in enumerate(mirrors)
    )
    median = float(np.median(elevation[kept])) if kept.any() else math.nan
    return DesignReport(band, float(edge_margin_px), per_bin, any_elevation, median, stats)


@dataclass(frozen=True)
class SweepRow:
    """One rig of a sweep: its parameters and the DesignReport's headline numbers.

    size_m is the pyramid's size (see omnitof.sensor.mirrors.pyramid), chosen to fill the lens's view.
    Coverages are shares 0–1; elevations in degrees.
    """

    lens: str
    n_mirrors: int
    tilt_deg: float
    yaw_deg: float
    size_m: float
    coverage: float
    coverage_any_elevation: float
    pixels_per_degree: float
    largest_gap_deg: int
    median_elevation_deg: float
    elevation_min_deg: float
    elevation_max_deg: float


def sweep(
    cameras: Mapping[str, Camera],
    tilts_deg: Iterable[float],
    yaws_deg: Iterable[float] = (45.0,),
    n_mirrors: Iterable[int] = (4,),
    *,
    apex_height: float = DEFAULT_APEX_HEIGHT,
    elev_band_deg: float = DEFAULT_ELEV_BAND_DEG,
    edge_margin_px: float = 2.0,
) -> list[SweepRow]:
    """design_report for every combination of lens, mirror count, tilt and yaw.

    Each pyramid is sized to fill its lens's view (pyramid(size=None)); the mount is
    camera_mount(). Rows come in the order lens, mirror count, yaw, tilt.
    """
    tilts, yaws, counts = list(tilts_deg), list(yaws_deg), list(n_mirrors)
    rows = []
    for lens, camera in cameras.items():
        for count in counts:
            for yaw in yaws:
                for tilt in tilts:
                    mirrors = pyramid(count, tilt, apex_height, None, yaw, camera=camera)
                    report = design_report(
                        camera, mirrors, elev_band_deg=elev_band_deg, edge_margin_px=edge_margin_px
                    )
                    rows.append(_row(lens, count, tilt, yaw, _pyramid_size(mirrors[0]), report))
    return rows


def format_sweep(rows: Sequence[SweepRow]) -> str:
    """A plain-text table of sweep rows."""
    header = (
        f"{'lens':<10}{'mirrors':>8}{'tilt':>7}{'yaw':>7}{'size m':>8}{'cover %':>9}"
        f"{'any el %':>10}{'px/deg':>8}{'gap':>6}{'el med':>8}{'el min':>8}{'el max':>8}"
    )
    lines = [header]
    for r in rows:
        lines.append(
            f"{r.lens:<10}{r.n_mirrors:>8d}{r.tilt_deg:>7.1f}{r.yaw_deg:>7.1f}{r.size_m:>8.3f}"
            f"{100 * r.coverage:>9.1f}{100 * r.coverage_any_elevation:>10.1f}"
            f"{r.pixels_per_degree:>8.1f}{r.largest_gap_deg:>6d}{r.median_elevation_deg:>+8.1f}"
            f"{r.elevation_min_deg:>+8.1f}{r.elevation_max_deg:>+8.1f}"
        )
    return "\n".join(lines)


def default_rig() -> Rig:
    """The rig omnitof assumes: the SR4000 with its wide (69°) lens, four mirrors tilted 56°
    from the optical axis, yaw 0° (faces looking front, left, back, right: the names of the
    paper's Fig. 3), apex 0.10 m above the lens, sized to fill the view; mount camera_mount().

    Why, from `sweep` (band ±10°, 2 px edge margin; tilts 40°–65°, yaws 0°–45°, 3–8
    mirrors):

    - Tilt: 45° looks from the horizon upwards (elevations +1° … +33°), so only rays near the
      apex are usable: 20–22 % of the bearings in the band for either lens. Each degree of
      tilt lowers every ray by about 2°; 56° centres the wide lens's view on the horizon
      (median elevation +0.6°, band −21° … +16°), where it sees 60.6 % of the bearings with
      86 pixels per degree (the best tilt, 58°, reaches 61.7 % with fewer pixels per degree).
    - Lens: the wide lens sees more at every tilt that centres the view (60.6 % against 42.2 %
      for the standard lens centred at 52°), still with dozens of pixels per degree.
    - Yaw: what matters is the pyramid's turn against the rectangular sensor. Edges running
      to the image corners (yaw 0° with this mount) beat edges along the image axes (yaw 45°,
      each mirror a quadrant): 60.6 % against 47.2 %. The paper's "diagonal" placement keeps
      this coverage only if the camera is turned 45° on its axis as well.
    - Mirror count: 3, 5, 6 or 8 faces never beat four with edges in the corners (best
      56.1 %).

    The ordering does not hang on the lens model's strongly distorted corners: ideal pinholes
    with the datasheets' fields of view (43.6°×34.6°, 69°×56°) give 36.7 % and 55.6 % at this
    rig's yaw and tilt, against 30.0 % and 46.7 % at yaw 45°.
    """
    camera = Camera.sr4000_wide()
    mirrors = pyramid(
        DEFAULT_RIG_MIRRORS, DEFAULT_RIG_TILT_DEG, yaw_deg=DEFAULT_RIG_YAW_DEG, camera=camera
    )
    return Rig.from_mirrors(camera, mirrors)


# --- internals -----------------------------------------------------------------------------


def _bearing_elevation(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bearing in [0, 360) and elevation in degrees of robot-frame directions (N, 3)."""
    with np.errstate(invalid="ignore"):
        unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        bearing = np.degrees(np.arctan2(unit[:, 1], unit[:, 0])) % 360.0
        elevation = np.degrees(np.arcsin(np.clip(unit[:, 2], -1.0, 1.0)))
    return bearing, elevation


def _mirror_stats(
    mirror: Mirror,
    robot_T_camera: np.ndarray | None,
    mine: np.ndarray,
    in_band: np.ndarray,
    elevation: np.ndarray,
    bins: np.ndarray,
) -> MirrorStats:
    band = mine & in_band
    low = float(elevation[mine].min()) if mine.any() else math.nan
    high = float(elevation[mine].max()) if mine.any() else math.nan
    return MirrorStats(
        mirror.name, bearing_of(mirror, robot_T_camera), int(mine.sum()), low, high,
        int(band.sum()),
        int(np.unique(bins[band]).size),
    )


def _longest_circular_run(flags: np.ndarray) -> int:
    """Length of the longest run of True in a circular boolean array."""
    if flags.all():
        return len(flags)
    doubled = np.concatenate([flags, flags]).astype(np.int64)
    # Run lengths via the positions of False: the gaps between consecutive Falses.
    falses = np.flatnonzero(doubled == 0)
    return int(np.max(np.diff(falses)) - 1) if len(falses) > 1 else 0


def _pyramid_size(face: Mirror) -> float:
    """A pyramid face's size: horizontal distance from the axis to its outer edge's middle."""
    middle = 0.5 * (face.polygon[1] + face.polygon[2])
    return float(np.hypot(middle[0], middle[1]))


def _row(lens: str, count: int, tilt: float, yaw: float, size: float, r: DesignReport) -> SweepRow:
    return SweepRow(
        lens, int(count), float(tilt), float(yaw), size, r.coverage, r.coverage_any_elevation,
        r.pixels_per_degree, r.largest_gap_deg, r.median_elevation_deg, r.elevation_min_deg,
        r.elevation_max_deg,
    )


def sweep_groups(rows: Sequence[SweepRow]) -> dict[tuple[str, int, float], list[SweepRow]]:
    """Rows by (lens, mirror count, yaw), each group ordered by tilt: one curve of a sweep plot."""
    groups: dict[tuple[str, int, float], list[SweepRow]] = {}
    for r in rows:
        groups.setdefault((r.lens, r.n_mirrors, r.yaw_deg), []).append(r)
    return {k: sorted(v, key=lambda r: r.tilt_deg) for k, v in groups.items()}


# --- the camera's own light (issue 15) ---------------------------------------------------------

DEFAULT_APEX_SWEEP = (0.02, 0.03, 0.04, 0.05, 0.06, 0.08, 0.10, 0.15, 0.20)


def apex_sweep(camera: Camera, n_mirrors: int, tilt_deg: float, yaw_deg: float,
               apex_heights: Sequence[float] = DEFAULT_APEX_SWEEP, errors: ToFErrors | None = None,
               distances: Sequence[float] = (1.0, 2.0, 5.0)) -> list[tuple[float, list[float]]]:
    """(apex height, [lit share at each surface distance]) for pyramids of one shape at several
    heights (`illumination.lit_share`; LEDs of `errors`, default `ToFErrors.realistic()`)."""
    errors = errors if errors is not None else ToFErrors.realistic()
    out = []
    for apex in apex_heights:
        mirrors = pyramid(n_mirrors, tilt_deg, float(apex), None, yaw_deg, camera=camera)
        out.append((float(apex), [lit_share(camera, mirrors, errors, d) for d in distances]))
    return out


def format_apex_sweep(rows: Sequence[tuple[float, list[float]]], distances: Sequence[float] = (1.0, 2.0, 5.0)) -> str:
    head = "apex height (m) | " + " | ".join(f"lit at {d:g} m" for d in distances)
    lines = [head]
    for apex, shares in rows:
        lines.append(f"{apex:15.2f} | " + " | ".join(f"{100 * s:8.1f} %" for s in shares))
    return "\n".join(lines)
