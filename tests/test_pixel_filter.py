"""omnitof.scan.pixel_filter: flying pixels at a depth edge, too-bright readings and mirror
edges, on frames whose answer is known by construction."""

from __future__ import annotations

import numpy as np

from omnitof.scan.pixel_filter import PixelFilter, PixelFilterSettings


def run(settings: PixelFilterSettings, labels: np.ndarray, d: np.ndarray, a: np.ndarray) -> np.ndarray:
    candidates = np.arange(labels.size)
    f = PixelFilter(settings, labels, candidates)
    frames = d.reshape(1, -1)
    return f.keep(frames, frames.copy(), a.reshape(1, -1)).reshape(labels.shape)


def test_a_flying_column_between_two_surfaces_is_dropped_and_the_surfaces_kept():
    labels = np.zeros((12, 20), dtype=np.int32)
    d = np.full(labels.shape, 2.0)
    d[:, 10:] = 4.0
    d[:, 10] = 3.0  # mixed pixels: on neither surface
    a = 100.0 / d**2
    keep = run(PixelFilterSettings(edge_margin_px=0.0), labels, d, a)
    assert not keep[:, 10].any()
    assert keep[:, :10].all() and keep[:, 11:].all()
    # A lone pixel with no agreeing neighbour goes too; so does the noise-free wall's, never.
    d2 = d.copy()
    d2[5, 3] = 2.5
    keep2 = run(PixelFilterSettings(edge_margin_px=0.0), labels, d2, a)
    assert not keep2[5, 3] and keep2[4, 3]


def test_brighter_than_any_surface_and_mirror_edges_are_dropped():
    labels = np.zeros((10, 10), dtype=np.int32)
    labels[:, 5:] = 1
    d = np.full(labels.shape, 3.0)
    a = np.full(labels.shape, 100.0)
    a[7, 1] = 7000.0 / 9.0 * 1.01  # apparent reflectance just above the bound
    s = PixelFilterSettings(min_neighbours=0, edge_margin_px=1.0)
    keep = run(s, labels, d, a)
    assert not keep[7, 1] and keep[6, 1]
    # Within 1 px of the boundary between mirror 0 (cols < 5) and 1: cols 4 and 5 sit on it,
    # cols 3 and 6 are 1 px from it (dropped: "farther than" the margin), cols 2 and 7 kept.
    assert not keep[:, 3:7].any() and keep[:, 2].all() and keep[:, 7].all()
    # Neighbours in another mirror's region never vouch for a pixel.
    d3 = np.full(labels.shape, 2.0)
    solo = np.zeros_like(labels)
    solo[:, 5:] = 1
    solo[4, 1] = 1  # a pixel of mirror 1 inside mirror 0's region
    keep3 = run(PixelFilterSettings(edge_margin_px=0.0), solo, d3, np.full(d3.shape, 100.0))
    assert not keep3[4, 1] and keep3[4, 3]
    # Off: everything kept.
    assert run(PixelFilterSettings(enabled=False, min_neighbours=0, max_amplitude_1m=0.0, edge_margin_px=0.0),
               labels, d, a).all()
