"""The flying-pixel and multipath filter of the scan extraction: which pixels of a ToF frame are
trusted before they become points.

Three tests, each against one way a ToF pixel lies:

- Neighbourhood consistency (flying pixels). A pixel that straddles a depth edge, or whose four
  samples saw different surfaces while the robot turned, reads a distance between the surfaces,
  on no surface at all; its neighbours read one surface or the other. With the tolerance
  t = `neighbour_tolerance + neighbour_tolerance_rel·d` (a wall seen obliquely changes by up to a
  few cm per pixel at 5 m, and the noise is ~10 cm at 7 m, hence the relative part), a pixel is
  dropped if it lies between two opposite neighbours (left and right, above and below, or a
  diagonal pair) more than t from each (the edge runs through it; a whole column of such
  pixels along an edge vouches for itself, so counting agreeing neighbours alone would not do),
  or if fewer than `min_neighbours` of its 8 neighbours read within t of it (a lone outlier).
  Only neighbours that look through the same mirror count.
- Amplitude against distance. amplitude·d² is an apparent reflectance (`ScanSettings.
  min_amplitude_1m` drops the too-dark ones, wrapped far walls among them). A mixed pixel keeps
  the near surface's light at a longer distance, and an interreflection adds light: readings
  brighter than any real surface can be at their distance (above `max_amplitude_1m`) are dropped.
- Mirror-edge margin. The LEDs beside the lens light the mirror edges' view less (or not at all)
  and the pixels there mix two mirrors' views: `edge_margin_px` more pixels are left out along
  every boundary between mirror regions (on top of the calibration's masks).

Units: metres, sample units; images (rows, cols). Everything is vectorised over a frame's
candidate pixels (no per-pixel Python).
"""

from __future__ import annotations

import numpy as np
from pydantic import ConfigDict, Field
from scipy import ndimage

from omnitof.settings_model import SettingsModel


class PixelFilterSettings(SettingsModel):
    """The filter's switches and thresholds (module docstring); `enabled` false keeps every
    pixel (the extraction as before issue 15)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    enabled: bool = Field(True, description="apply the flying-pixel and multipath filter")
    min_neighbours: int = Field(2, ge=0, le=8, description="same-mirror neighbours that must agree (of 8)")
    neighbour_tolerance: float = Field(0.05, ge=0.0, description="agreement: this many metres ...")
    neighbour_tolerance_rel: float = Field(0.03, ge=0.0, description="... plus this share of the distance")
    max_amplitude_1m: float = Field(
        7000.0, ge=0.0,
        description="readings with amplitude·d² above this (sample units·m²) are dropped; an albedo-1 surface "
        "facing the camera through a mirror gives 7300·0.81 ≈ 5900. 0 turns it off",
    )
    edge_margin_px: float = Field(1.0, ge=0.0, description="extra pixels left out along mirror boundaries")


class PixelFilter:
    """The filter for one extractor: built once from the mirror labels and the candidate
    pixels (flat indices into the image), applied per batch of frames."""

    def __init__(self, settings: PixelFilterSettings, labels: np.ndarray, candidates: np.ndarray) -> None:
        self.settings = settings
        h, w = labels.shape
        rows, cols = np.divmod(candidates, w)
        offsets = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
        nr = rows[:, None] + np.array([o[0] for o in offsets])
        nc = cols[:, None] + np.array([o[1] for o in offsets])
        inside = (nr >= 0) & (nr < h) & (nc >= 0) & (nc < w)
        nr, nc = np.clip(nr, 0, h - 1), np.clip(nc, 0, w - 1)
        # (K, 8) flat indices of each candidate's neighbours and whether they count.
        self.neighbours = nr * w + nc
        own = labels[rows, cols]
        self.valid = inside & (labels[nr, nc] == own[:, None]) & (own[:, None] >= 0)
        self.away_from_edges = self._edge_mask(labels, settings.edge_margin_px)[rows, cols]

    @staticmethod
    def _edge_mask(labels: np.ndarray, margin: float) -> np.ndarray:
        """(H, W) bool: pixels farther than `margin` px from any pixel of another label."""
        if margin <= 0.0:
            return np.ones(labels.shape, dtype=bool)
        boundary = np.zeros(labels.shape, dtype=bool)
        boundary[:, 1:] |= labels[:, 1:] != labels[:, :-1]
        boundary[:, :-1] |= labels[:, 1:] != labels[:, :-1]
        boundary[1:, :] |= labels[1:, :] != labels[:-1, :]
        boundary[:-1, :] |= labels[1:, :] != labels[:-1, :]
        return ndimage.distance_transform_edt(~boundary) > margin

    def keep(self, frames: np.ndarray, dd: np.ndarray, aa: np.ndarray) -> np.ndarray:
        """(N, K) bool: candidates to keep, given the frames' distances (N, H·W) and the
        candidates' distances dd and amplitudes aa (N, K)."""
        s = self.settings
        ok = np.broadcast_to(self.away_from_edges, dd.shape).copy()
        if s.max_amplitude_1m > 0.0:
            ok &= aa * dd * dd <= s.max_amplitude_1m
        if s.min_neighbours > 0:
            nb = np.take(frames, self.neighbours, axis=1)  # (N, K, 8)
            tolerance = (s.neighbour_tolerance + s.neighbour_tolerance_rel * dd)[..., None]
            gap = nb - dd[..., None]
            agree = (np.abs(gap) <= tolerance) & self.valid
            ok &= agree.sum(axis=2) >= s.min_neighbours
            # Opposite neighbours (offsets k and 7 − k): the pixel between them, far from both.
            far = (np.abs(gap) > tolerance) & self.valid
            between = far[..., :4] & far[..., 7:3:-1] & (gap[..., :4] * gap[..., 7:3:-1] < 0.0)
            ok &= ~between.any(axis=2)
        return ok
