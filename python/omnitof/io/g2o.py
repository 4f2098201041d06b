"""Planar pose graphs in the g2o text format, which g2o, GTSAM (`gtsam.readG2o`), Ceres' pose
graph examples and most SLAM back ends read:

    VERTEX_SE2 id x y theta
    EDGE_SE2 from to dx dy dtheta I11 I12 I13 I22 I23 I33
    FIX id

An edge's measurement is the pose of `to` in the frame of `from`; I its information matrix
(inverse covariance, upper triangle row by row) over (dx, dy, dtheta). Metres and radians.
Written by hand (a line per element): GTSAM's own writer needs its factor graph, which omnitof's
results do not keep.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnitof.io.atomic import atomic_write

_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def write_g2o(path: str | Path, nodes: np.ndarray, edges: np.ndarray, measured: np.ndarray,
              information: np.ndarray, *, fixed: int | None = 0) -> None:
    """Write a pose graph atomically: `nodes` (K, 3) poses (vertex ids 0 … K-1), `edges` (E, 2)
    vertex pairs, `measured` (E, 3) relative poses and `information` (E, 3, 3); `fixed`: a vertex
    held fixed (FIX), or None."""
    nodes = np.asarray(nodes, dtype=np.float64).reshape(-1, 3)
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    measured = np.asarray(measured, dtype=np.float64).reshape(-1, 3)
    information = np.asarray(information, dtype=np.float64).reshape(-1, 3, 3)
    if not len(edges) == len(measured) == len(information):
        raise ValueError(f"edges, measurements and information differ in number: {len(edges)}, {len(measured)}, "
                         f"{len(information)}")
    if len(edges) and (edges.min() < 0 or edges.max() >= len(nodes)):
        raise ValueError(f"an edge names a vertex outside 0 … {len(nodes) - 1}")
    rows = [f"VERTEX_SE2 {i} {x!r} {y!r} {t!r}" for i, (x, y, t) in enumerate(nodes.tolist())]
    upper = information[:, [r for r, _ in _UPPER], [c for _, c in _UPPER]]
    rows += [
        "EDGE_SE2 {} {} {!r} {!r} {!r} ".format(a, b, *m) + " ".join(repr(v) for v in info)
        for (a, b), m, info in zip(edges.tolist(), measured.tolist(), upper.tolist())
    ]
    if fixed is not None and len(nodes):
        rows.append(f"FIX {int(fixed)}")
    with atomic_write(path) as f:
        f.write("\n".join(rows) + "\n")
