"""What a configuration implies for a log, checked before the filter runs: whether the scans can
make a map at all, the memory the run will need and the size of the back end's submaps (and,
`within_cores`, the worker threads the machine can use). A run that cannot fit stops at once, with
the number and the setting that decides it, instead of failing or being killed hours later.
While a run goes on, `MemoryWatch` stops it with the same kind of message where the memory
really left runs short (the estimate below is an order, not a bound).

The memory estimate (`estimate_memory`) is, in bytes,

    particles × (window tiles × 8 + scan tiles × tile bytes) + map cells × 30

- map cells: the cells, at map.resolution, of the rectangle that holds the sensor at every scan
  and every beam end point the map uses (ranges cut at min(map.max_range, the sensor's range);
  no-echo beams at that length when map.clear_no_echo is on). The map a run writes covers it.
- window tiles: the tiles (16 × 16 cells) of that rectangle. Every particle keeps a window of
  pointers (8 bytes each) over its map's tiles (docs/conventions.md, "Memory").
- scan tiles: the tiles the beams of one scan cross (the median over up to 32 scans spread
  over the log). At every step each particle writes its own copy of these tiles
  (copy-on-write), `tile bytes` (1.75 KiB) each.
- 30 bytes per map cell: the measured peak of the dense map, its copies, the PGM and the
  figure while the results are written (30 B per cell for a map of 8.6 million cells).

It is the order of what a run needs, not a bound: on the simulated corridor loop with 1000
particles (sim2d preset) it comes to 69 MB where the filter's peak grew by 125 MB (particles
that were not resampled keep copies of older tiles too; copies made by resampling share
theirs). Rule: a run whose estimate exceeds the memory available is refused, available
meaning MemAvailable of /proc/meminfo, or less where a cgroup limits the process; where
neither can be read (not Linux), only an estimate beyond NO_MACHINE_BYTES (or one that
overflows) is refused.
"""

from __future__ import annotations

import math
import os
import warnings
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnitof import _core
from omnitof.errors import ConfigError, InputError, OmnitofWarning, ResourceError
from omnitof.geometry import compose
from omnitof.slam.config import SlamConfig
from omnitof.types import ScanSequence

TILE_CELLS = 16  # the core's tiles are 16 × 16 cells (rust/src/grid.rs, TILE)
POINTER_BYTES = 8  # one slot of a particle's window of tiles
MAP_CELL_BYTES = 30  # measured, see the module notes
SAMPLED_SCANS = 32
_CHUNK = 2048  # scans per chunk when the extent is computed (bounds the temporary arrays)
# Where the memory available is unknown, estimates above this are refused: 1 PiB, more than any
# single machine has.
NO_MACHINE_BYTES = float(2**50)
# Odometry positions must resolve this fraction of a cell (check_odometry_precision).
PRECISION_CELLS = 1e-3


@dataclass(frozen=True)
class MemoryEstimate:
    """The memory a run will need (module notes), and its parts.

    extent: (width, height) of the mapped rectangle, metres. cells: (columns, rows) at the map
    resolution. particles_bytes: what the particles' windows and tile copies need. map_bytes:
    what the written map needs. total: their sum.
    """

    extent: tuple[float, float]
    cells: tuple[float, float]
    particles_bytes: float
    map_bytes: float

    @property
    def total(self) -> float:
        return self.particles_bytes + self.map_bytes



def _reach(scans: ScanSequence, cfg: SlamConfig) -> float:
    return min(cfg.map.max_range, scans.max_range)


def _beam_lengths(ranges: np.ndarray, mask: np.ndarray, reach: float, clear_no_echo: bool) -> np.ndarray:
    """Length (m) of every beam as the map uses it; NaN for beams that leave no mark."""
    r = ranges.astype(np.float64)
    hit = mask & np.isfinite(r) & (r > 0.0)
    used = hit | (mask & np.isposinf(r) & clear_no_echo)
    return np.where(used, np.minimum(np.where(hit, r, reach), reach), np.nan)


def _end_points(scans: ScanSequence, rows: slice | np.ndarray, reach: float, clear: bool):
    """(sensor positions (n, 2), end points x, y (n, B) with NaN where a beam leaves no mark)."""
    sensor = compose(scans.odometry[rows], scans.sensor_pose)
    lengths = _beam_lengths(scans.ranges[rows], scans.beam_mask[rows], reach, clear)
    angles = scans.angles[rows] if scans.per_scan_geometry else scans.angles[None, :]
    bearing = sensor[:, 2:3] + angles
    with np.errstate(invalid="ignore"):
        x = sensor[:, 0:1] + lengths * np.cos(bearing)
        y = sensor[:, 1:2] + lengths * np.sin(bearing)
    return sensor[:, :2], x, y


def map_extent(scans: ScanSequence, cfg: SlamConfig) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax), metres, of the sensor at every scan and every end point the map
    uses, in the odometry's frame.

    Raises:
        InputError: for odometry poses that are not finite.
    """
    if not np.isfinite(scans.odometry).all():
        bad = int(np.flatnonzero(~np.isfinite(scans.odometry).all(axis=1))[0])
        raise InputError(f"the odometry pose of scan {bad} is not finite", scans.source or None)
    reach, clear = _reach(scans, cfg), cfg.map.clear_no_echo
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for start in range(0, len(scans), _CHUNK):
        sensor, x, y = _end_points(scans, slice(start, start + _CHUNK), reach, clear)
        lo = np.fmin(lo, [np.nanmin(x, initial=np.inf), np.nanmin(y, initial=np.inf)])
        lo = np.fmin(lo, sensor.min(axis=0))
        hi = np.fmax(hi, [np.nanmax(x, initial=-np.inf), np.nanmax(y, initial=-np.inf)])
        hi = np.fmax(hi, sensor.max(axis=0))
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def _scan_tiles(scans: ScanSequence, cfg: SlamConfig) -> float:
    """Median count of distinct tiles that the beams of one scan cross, over up to
    SAMPLED_SCANS scans spread over the log (module notes)."""
    tile = TILE_CELLS * cfg.map.resolution
    rows = np.unique(np.linspace(0, len(scans) - 1, min(len(scans), SAMPLED_SCANS)).round().astype(int))
    reach = _reach(scans, cfg)
    sensor = compose(scans.odometry[rows], scans.sensor_pose)
    lengths = _beam_lengths(scans.ranges[rows], scans.beam_mask[rows], reach, cfg.map.clear_no_echo)
    # Points every half tile along each beam land in every tile it crosses but a corner's.
    steps = np.arange(0.0, reach + tile, 0.5 * tile)[:4096]
    counts = []
    for k, i in enumerate(rows):
        used = np.isfinite(lengths[k])
        bearing = sensor[k, 2] + scans.scan_angles(i)[used[: scans.beam_mask[i].sum()]]
        t = np.minimum(steps[None, :], lengths[k, used][:, None])
        # Tile indices relative to the sensor's tile, within ±4097 of it: one integer each.
        # (Odometry near the float limit overflows here; its map is refused as too big anyway.)
        with np.errstate(over="ignore", invalid="ignore"):
            x = np.floor((sensor[k, 0] + t * np.cos(bearing)[:, None]) / tile) - np.floor(sensor[k, 0] / tile)
            y = np.floor((sensor[k, 1] + t * np.sin(bearing)[:, None]) / tile) - np.floor(sensor[k, 1] / tile)
            counts.append(len(np.unique((x * 16384 + y).astype(np.int64))))
    return float(np.median(counts)) if counts else 0.0


def estimate_memory(scans: ScanSequence, cfg: SlamConfig) -> MemoryEstimate:
    """The memory a run of `cfg` on `scans` will need (module notes)."""
    x0, y0, x1, y1 = map_extent(scans, cfg)
    res = cfg.map.resolution
    width, height = max(x1 - x0, 0.0), max(y1 - y0, 0.0)
    # Floats throughout: odometry a few 1e307 m apart spans an infinite map, refused as too big.
    cols, rows = float(np.floor(width / res)) + 1, float(np.floor(height / res)) + 1
    window = float(np.ceil(cols / TILE_CELLS)) * float(np.ceil(rows / TILE_CELLS)) * POINTER_BYTES
    copies = _scan_tiles(scans, cfg) * _core.ParticleFilter.tile_bytes()
    return MemoryEstimate(
        extent=(width, height),
        cells=(float(cols), float(rows)),
        particles_bytes=cfg.filter.particles * (window + copies),
        map_bytes=float(cols) * rows * MAP_CELL_BYTES,
    )


def available_memory() -> int | None:
    """Bytes this process can still have: MemAvailable of /proc/meminfo, lowered to what is left
    below the cgroup's memory limit where there is one; None where neither can be read."""
    found = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    for limit, usage in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                         ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                          "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            found.append(int(Path(limit).read_text()) - int(Path(usage).read_text()))
        except (OSError, ValueError):
            continue
    return min(found) if found else None


def _resident_bytes() -> int | None:
    """This process's resident memory (bytes) from /proc/self/statm; None where unreadable."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE")


# The memory a run keeps free while it runs (MemoryWatch): at least this, and what the last
# HEADROOM_STEPS steps took, for as many steps more.
MIN_HEADROOM = 250 * 10**6  # bytes
HEADROOM_STEPS = 8


class MemoryWatch:
    """Stops a run whose memory grows beyond what the machine has, with a ResourceError naming
    the step and the setting to change, before the kernel's out-of-memory killer ends the
    process without a word (on Linux an allocation seldom fails: the process is killed later).

    The estimate before the run (`check_memory`) is the order of what a run needs, not a bound
    (particles keep copies of older tiles, and the 3D filter's voxel blocks depend on what the
    rays see); this watches what is really left. At every `check` it reads the memory
    available (`available_memory`) and this process's resident memory, and stops where less
    is left than `MIN_HEADROOM` or than the process grew in the last `HEADROOM_STEPS` steps
    (room for as many more). Reading the three small files costs about 0.1 ms a step. Where
    nothing can be read (not Linux) it checks nothing.
    """

    def __init__(self, what: str, remedy: str):
        self.what, self.remedy = what, remedy
        self._recent: deque[int] = deque(maxlen=HEADROOM_STEPS + 1)
        resident = _resident_bytes()
        if resident is not None:
            self._recent.append(resident)

    def check(self, step: int, steps: int) -> None:
        """After step `step` (1-based) of `steps`.

        Raises:
            ResourceError: naming the step, the memory left and held, and `remedy`.
        """
        resident = _resident_bytes()
        if resident is not None:
            self._recent.append(resident)
        left = available_memory()
        if left is None:
            return
        grown = self._recent[-1] - self._recent[0] if self._recent else 0
        need = max(MIN_HEADROOM, grown)
        if left < need:
            held = f", holding {_size(resident)}" if resident is not None else ""
            raise ResourceError(
                f"{self.what} stopped at step {step} of {steps}: only {_size(left)} of memory is left{held}, "
                f"and it needs {_size(need)} to go on ({self.remedy})"
            )


def _size(n: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n / 1e3:.3g} kB"


def check_memory(scans: ScanSequence, cfg: SlamConfig, *, available: float | None = None) -> MemoryEstimate:
    """Refuse a run whose estimated memory exceeds what is `available` (default:
    `available_memory()`); returns the estimate.

    Raises:
        ResourceError: naming the estimate, the memory available and the setting that decides
            the estimate: map.resolution when the map's cells weigh more, filter.particles when
            the particles do.
        InputError: for odometry poses that are not finite.
    """
    estimate = estimate_memory(scans, cfg)
    if available is None:
        available = available_memory()
    # An estimate that overflows, or exceeds any machine's memory, is refused even where the
    # memory available is unknown.
    limit = NO_MACHINE_BYTES if available is None else available
    if math.isfinite(estimate.total) and estimate.total <= limit:
        return estimate
    (width, height), (cols, rows) = estimate.extent, estimate.cells
    if available is None:
        have = "no machine has that much"
    else:
        have = f"the machine has {_size(available)} available"
    if not (estimate.particles_bytes > estimate.map_bytes):  # the map's, also where either is NaN
        raise ResourceError(
            f"map.resolution {cfg.map.resolution:g} m: the map of {scans.source or 'these scans'} "
            f"spans {width:.4g} m × {height:.4g} m, {cols:.3g} × {rows:.3g} cells, and the run "
            f"would need about {_size(estimate.total)}; {have} (choose a coarser map.resolution)"
            f"{_outlier(scans, max(width, height))}"
        )
    raise ResourceError(
        f"filter.particles {cfg.filter.particles}: the particles' maps would need about "
        f"{_size(estimate.particles_bytes)} (with map.resolution {cfg.map.resolution:g} m over "
        f"{width:.4g} m × {height:.4g} m); {have} (choose fewer particles)"
    )


def _outlier(scans: ScanSequence, span: float) -> str:
    """Where one odometry pose alone makes most of the map's span (a number read wrong, say):
    a note naming it; otherwise nothing. A trajectory's own extent puts no pose much more than
    half the span from the median position."""
    if len(scans) < 3 or not math.isfinite(span):
        return ""
    xy = scans.odometry[:, :2]
    away = np.hypot(*(xy - np.median(xy, axis=0)).T)
    k = int(np.argmax(away))
    if not away[k] > 0.75 * span:
        return ""
    x, y = xy[k]
    return (f"; most of that span is the odometry pose of scan {k} alone, at ({x:.6g}, {y:.6g}) m, "
            f"{away[k]:.4g} m from the others' median: is it read right?")


def check_submaps(scans: ScanSequence, cfg: SlamConfig) -> None:
    """With the back end on, refuse submaps wider than the core allows: a submap holds
    backend.submap_length metres of trajectory plus the sensor's reach on each side.

    Raises:
        ConfigError: naming backend.submap_length, map.max_range and map.resolution; or
            map.resolution coarser than an eighth of the reach.
    """
    if not cfg.backend.enabled:
        return
    reach = _reach(scans, cfg)
    if 8.0 * cfg.map.resolution > reach:  # the core's SubmapParams::check
        raise ConfigError(
            f"map.resolution {cfg.map.resolution:g} m is too coarse for the back end's submaps at a reach of "
            f"{reach:g} m (map.max_range {cfg.map.max_range:g} m, the scans' {scans.max_range:g} m): a "
            "submap's cells must be at most an eighth of it, or its search turns in steps near π; refine "
            "map.resolution or turn the back end off (backend.enabled false)"
        )
    side = (cfg.backend.submap_length + 2.0 * reach) / cfg.map.resolution
    limit = _core.Submap.max_side_cells()
    if side > limit:
        raise ConfigError(
            f"backend.submap_length {cfg.backend.submap_length:g} m plus twice the reach "
            f"{_reach(scans, cfg):g} m (map.max_range or the sensor's) make submaps {side:.0f} cells "
            f"wide at map.resolution {cfg.map.resolution:g} m; the back end allows {limit:.0f}: "
            "lower map.max_range or backend.submap_length, or coarsen map.resolution"
        )


# More than this share of the echoes beyond map.max_range is warned of (check_mappable). The
# benchmark logs stay well below: Intel 0.2 %, fr079 0.4 %, the Freiburg hospital's long
# corridors 24 % (beyond the laser180 presets' 20 m).
FAR_ECHO_SHARE = 0.5


class MapRangeWarning(OmnitofWarning):
    """Most echoes of the scans lie beyond map.max_range: they clear free space only."""


def check_mappable(scans: ScanSequence, cfg: SlamConfig) -> None:
    """Refuse scans that cannot leave a mark in the map: none at all, no beam with an echo
    while map.clear_no_echo is off (the map would be empty, an image of 0 × 0 cells), or no
    echo within map.max_range (readings beyond it clear free space only: a map without a
    wall). Warn (MapRangeWarning) where more than FAR_ECHO_SHARE of the echoes lie beyond
    map.max_range, naming the share dropped.

    Raises:
        InputError: naming the scans' source.
        ConfigError: naming map.max_range, the nearest echo and a value that keeps half of them.
    """
    source = scans.source or None
    if len(scans) == 0:
        raise InputError("no scans to process", source)
    r = scans.ranges[scans.beam_mask]
    echoes = r[np.isfinite(r) & (r > 0)]
    if echoes.size == 0:
        if cfg.map.clear_no_echo:
            return
        raise InputError(
            f"no beam of the {len(scans)} scans has an echo (every range is beyond the sensor's "
            f"{scans.max_range:g} m or missing): there is nothing to map", source
        )
    reach = cfg.map.max_range
    far = float(np.count_nonzero(echoes > reach)) / echoes.size  # the core marks a wall at r <= max_range
    if far <= FAR_ECHO_SHARE:
        return
    # The whole metre that keeps half of the echoes (at most the sensor's range).
    keeps_half = min(math.ceil(float(np.median(echoes))), scans.max_range)
    if far == 1.0:
        of = f" of {source}" if source else ""
        raise ConfigError(
            f"map.max_range {reach:g} m: every echo of the {len(scans)} scans{of} lies beyond it (the nearest at "
            f"{float(echoes.min()):.4g} m), and readings beyond it clear free space only: the map would have no "
            f"wall; raise it, e.g. --set map.max_range={keeps_half:g} (half of the echoes lie within)"
        )
    named = f"{source}: " if source else ""
    # Rounded down: "100 %" only where every echo is beyond, which is refused above.
    warnings.warn(MapRangeWarning(
        f"{named}{math.floor(100 * far)} % of the echoes lie beyond map.max_range {reach:g} m and leave no wall in "
        f"the map (they clear free space only); --set map.max_range={keeps_half:g} keeps half of them"
    ), stacklevel=2)


def check_odometry_precision(scans: ScanSequence, resolution: float) -> None:
    """Refuse odometry so far from its origin that float64 no longer resolves a thousandth of a
    cell there: positions hold only steps of np.spacing(|x|) (1e-9 m at 5e6 m, 1 m at 1e16 m),
    and the log's motions are lost already when it is read.

    Raises:
        InputError: naming the first such scan, its position and the precision left.
    """
    if len(scans) == 0:
        return
    far = np.max(np.abs(scans.odometry[:, :2]), axis=1)
    coarse = np.spacing(far) > PRECISION_CELLS * resolution
    if coarse.any():
        k = int(np.flatnonzero(coarse)[0])
        x, y = scans.odometry[k, :2]
        raise InputError(
            f"the odometry pose of scan {k} lies at ({x:.6g}, {y:.6g}) m, so far from its origin that "
            f"a float64 position there holds only steps of {np.spacing(far[k]):.3g} m, coarser than a "
            f"thousandth of a cell of map.resolution {resolution:g} m: the log's motions are lost "
            "(subtract a reference position from the odometry)",
            scans.source or None,
        )


def check_limits(scans: ScanSequence, cfg: SlamConfig, *, available: float | None = None) -> MemoryEstimate:
    """Everything a run can be refused for before it runs: scans that cannot make a map
    (`check_mappable`), odometry too far out to resolve its motions (`check_odometry_precision`),
    submaps too wide (`check_submaps`), memory (`check_memory`)."""
    check_mappable(scans, cfg)
    check_odometry_precision(scans, cfg.map.resolution)
    check_submaps(scans, cfg)
    return check_memory(scans, cfg, available=available)


class ThreadsWarning(OmnitofWarning):
    """More worker threads asked for than the process has cores."""


def usable_cores() -> int:
    """The cores this process may run on (a container's or taskset's share, not the machine's)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def within_cores(cfg: SlamConfig) -> SlamConfig:
    """`cfg` with `filter.threads` bounded by the usable cores. Threads beyond them only wait
    for each other (1024 threads on 2 cores ran a 3000-line log in 47 s instead of 3 s), and
    the map does not depend on the count. Bounded where the run runs, not where it was
    configured: a `bench` run's configuration (and its digest) is the same on every worker."""
    cores = usable_cores()
    if cfg.filter.threads <= cores:
        return cfg
    warnings.warn(ThreadsWarning(f"filter.threads {cfg.filter.threads} is more than the {cores} cores this "
                                 f"process may use; {cores} are used (the map does not depend on it)"))
    return cfg.model_copy(update={"filter": cfg.filter.model_copy(update={"threads": cores})})
