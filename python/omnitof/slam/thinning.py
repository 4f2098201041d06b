"""Scans far denser than the map, thinned before the filter sees them.

Every particle writes every beam of an integrated scan into its own map, so a scan's cost grows
with its beams times the particles. A planar laser has hundreds to a few thousand beams; a
scan flattened from a 3D lidar or a depth camera can have millions (a log of 2 000 000-beam
scans took 110 s per scan with 30 particles). Most of those beams end in the same map cells
as their neighbours and add nothing the map can hold.

A scan with more than `map.max_beams` beams keeps one beam per cell of a grid of half the map
resolution laid over its end points in the sensor frame (the first beam, in angle order, of
each cell; a no-echo beam's end point taken at the distance it clears, min(map.max_range,
the sensor's range)), as Cartographer's voxel filter does before insertion (Hess et al.,
ICRA 2016, sec. IV). If more than `map.max_beams` remain, every n-th of them is kept, evenly.
Scans at or under the limit are left whole, so a log of ordinary scans runs as before, bit for
bit. Kept beams keep their own angle and range; the thinned log has per-scan geometry
(`ScanSequence.beam_counts`).
"""

from __future__ import annotations

import warnings

import numpy as np

from omnitof.errors import OmnitofWarning
from omnitof.slam.config import SlamConfig
from omnitof.types import ScanSequence, pad_rows


class DenseScanWarning(OmnitofWarning):
    """Scans with more beams than `map.max_beams` were thinned."""


def thin_dense_scans(scans: ScanSequence, cfg: SlamConfig) -> tuple[ScanSequence, dict | None]:
    """(`scans` itself, None) when no scan has more than `cfg.map.max_beams` beams; else a copy
    whose dense scans are thinned (see the module docstring) and a record of how much (for
    summary.yaml), with a DenseScanWarning that says so."""
    limit, mode = cfg.map.max_beams, cfg.map.thin_beams
    counts = scans.beam_counts if scans.beam_counts is not None else np.full(len(scans), scans.n_beams)
    if len(scans) == 0 or mode == "off" or (mode == "dense" and counts.max() <= limit):
        return scans, None
    cell = cfg.map.resolution / 2
    reach = min(cfg.map.max_range, scans.max_range)
    thin = counts > limit if mode == "dense" else np.ones(len(scans), dtype=bool)
    kept = [_thinned(scans.scan_angles(i), scans.scan_ranges(i), cell, reach, limit) if thin[i]
            else np.arange(counts[i]) for i in range(len(scans))]
    angles = pad_rows([scans.scan_angles(i)[k] for i, k in enumerate(kept)], np.nan, np.float64)
    ranges = pad_rows([scans.scan_ranges(i)[k] for i, k in enumerate(kept)], np.inf, np.float32)
    remissions = None
    if scans.remissions is not None:
        rows = [scans.remissions[i, : counts[i]][k] for i, k in enumerate(kept)]
        remissions = pad_rows(rows, 0.0, np.float32)
    new_counts = np.array([len(k) for k in kept], dtype=np.int64)
    record = {"rule": mode, "scans": int(thin.sum()), "max_beams": limit, "cell_m": cell,
              "median_beams_before": int(np.median(counts[thin])),
              "median_beams_after": int(np.median(new_counts[thin]))}
    dense = counts > limit
    if dense.any():  # asked for with `always`, a surprise otherwise
        evenly = f" and then evenly to {limit}" if new_counts[dense].max() >= limit else ""
        warnings.warn(DenseScanWarning(
            f"{scans.source or 'the scans'}: {int(dense.sum())} scans have more than map.max_beams {limit} beams "
            f"(up to {int(counts.max())}); each was thinned to one beam per {cell:g} m cell of its end points"
            f"{evenly}: a median {int(np.median(counts[dense]))} beams became {int(np.median(new_counts[dense]))}"
        ))
    thinned = ScanSequence(
        timestamps=scans.timestamps, ranges=ranges, angles=angles, odometry=scans.odometry,
        sensor_pose=scans.sensor_pose, max_range=scans.max_range, remissions=remissions,
        ground_truth=scans.ground_truth, source=scans.source, beam_counts=new_counts,
        max_range_rule=scans.max_range_rule, repeated_scans_dropped=scans.repeated_scans_dropped,
        odometry_rule=scans.odometry_rule,
    )
    return thinned, record


# Cell indices are clipped to ±2^30 (no end point lies that many cells out: 2^30 half
# millimetres are 537 km) so that a pair packs into one int64, which np.unique sorts 50 times
# faster than rows of two.
_KEY_LIMIT = 2**30


def _thinned(angles: np.ndarray, ranges: np.ndarray, cell: float, reach: float, limit: int) -> np.ndarray:
    """Indices (increasing) of the beams one scan keeps: the first of each end-point cell, then
    at most `limit` of those, evenly spaced."""
    length = np.minimum(ranges.astype(np.float64), reach)  # no echo (+inf): the distance it clears
    kx, ky = (np.clip(np.floor(length * f(angles) / cell), -_KEY_LIMIT, _KEY_LIMIT).astype(np.int64)
              for f in (np.cos, np.sin))
    _, first = np.unique((kx << 32) + ky, return_index=True)
    first.sort()
    if len(first) > limit:
        first = first[np.linspace(0, len(first) - 1, limit).round().astype(np.int64)]
    return first
