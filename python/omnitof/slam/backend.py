"""The pose-graph back end behind the particle filter: submaps, loop closures, optimisation, and
the correction fed back to the filter.

The filter (either proposal; the 2D one or the 3D one) stays the front end: it integrates scans
and, at each integrated scan, its best particle gives a pose. The submaps and closures use the 2D
scans of the integrated scans in either case (a ToF bag has both). Behind it, as in Cartographer
(Hess, Kohler, Rapp, Andor, "Real-Time Loop Closure in 2D LIDAR SLAM", ICRA 2016):

- **Nodes** are the integrated scans. **Front-end edges** join consecutive nodes with the
  relative motion of the best particle's trajectory (one lineage, so the edges agree with each
  other), with a standard deviation that grows with the distance moved.
- **Submaps**: every `submap_length` metres the scans integrated meanwhile, at the front end's
  poses, make one local grid (`_core.Submap`). A finished submap precomputes its branch-and-
  bound grids once (rust/src/loop_closure.rs).
- **Loop closures**: each new node's scan is searched in the finished submaps near its
  estimated pose, in a window around it, by branch and bound over precomputed max-grids
  (Hess et al. sec. V-C; Olson, ICRA 2009) and refined below the cell size. The search's cell
  values are the submap's probabilities spread by the likelihood field's sigma (each cell
  raised to its Gaussian-discounted neighbours; rust/src/loop_closure.rs, `spread`), so that
  end points a few millimetres in front of a wall on a cell border still count. A match whose
  score reaches `min_score` gives an edge between the submap's first node and the new node,
  with the covariance of the score surface. The matched pose is then refined as the front end
  matches its own scans (the likelihood field of the cells' mean end points), so that a
  closure is as precise as the front end's steps. After `global_search_after` nodes without any
  closure the robot may be lost, and a node is searched in every finished submap, whole.
- **Optimisation**: GTSAM's Levenberg-Marquardt on the Pose2 graph (Dellaert & Kaess,
  "Factor Graphs for Robot Perception", 2017): GTSAM because it is the field's maintained
  library for exactly this (sparse elimination, robust noise models) with wheels on PyPI,
  where writing a sparse solver here would be a toy. The closures carry a robust kernel
  (Cauchy by default) so that one false closure cannot bend the map; the front-end edges do
  not (they are what the filter measured). A batch optimisation of a few thousand nodes takes
  milliseconds, so the graph is optimised whenever a new closure came in (at most every
  `optimize_every` nodes), and a repaired map exists while the run goes on.
- **Feedback**: where the optimum moves the newest node by more than `feedback_xy` /
  `feedback_deg`, every particle restarts at the optimised pose with a map rebuilt from all
  nodes at their optimised poses (`FrontEnd2D`; the 3D filter's voxel map is rebuilt from
  every node's rays, `omnitof.slam.filter3d.FrontEnd3D`). The front end's trajectory then
  begins anew at that node (a new *segment*); the edges of the segment before are kept as they
  were, and the submap in progress is closed, since its scans were placed in the frame before
  the correction.

**Relocalisations**: the front end's odometry check (a wide search where the wheels' motion
explains too little of a scan) replaces the wheels' motion by the pose the map explains. Where
the wheels slipped, the map of the last few metres explains the scan far better at the corrected
pose than at the wheels' one, and the jump belongs in the front-end edge. Where a loop ends, the
filter's drift makes the scan fit the start's map at the corrected pose, which the recent map
does not support. That jump is the loop's whole drift put into one edge: kept there, it stays
there. So the closures are judged with the wheels' motion as such a node's edge, and the
optimisation spreads the drift along the loop, wherever the optimum with that edge still puts the
node nearer the relocalised pose than the wheels' one: the kept closures then say what the
relocalisation said. Where they do not, the jump stands, since nothing else says where the robot is
(`_judge_correction`, `_sides_with_relocalisation`).

Everything is deterministic: the search and the core are bit-identical for any thread count,
and the graph is optimised in node order on one thread.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import cached_property
from typing import Protocol

import gtsam
import numpy as np

from omnitof import _core
from omnitof.geometry import compose, relative, wrap_angle
from omnitof.slam.config import BackendConfig, MapConfig
from omnitof.slam.final_match import grid_along
from omnitof.types import ScanSequence

LM_ITERATIONS = 20
LM_RELATIVE_TOLERANCE = 1e-4
# Levenberg-Marquardt iterations per step of graduated non-convexity: the weights settle long
# before each step's optimum does, and the final robust run polishes the estimate.
GNC_INNER_ITERATIONS = 10
GNC_MIN_DISAGREEING = 2
CHI2_PROBABILITY = 0.99
CHI2_3DOF_99 = 11.345  # the CHI2_PROBABILITY quantile of chi-square with 3 degrees of freedom
# A correction is judged only where the recent map holds at least this many nodes' scans, and
# the scan at least this many end points (the odometry check's own floor in the presets,
# scan_matcher.search_min_points: on fewer, one point is a twentieth of the share). The 3D
# filter's check judges its rays, and the office's 2D slice often holds fewer than 20 end points.
RELOCALISATION_MIN_NODES = 3
RELOCALISATION_MIN_POINTS = 20


class FrontEnd(Protocol):
    """The filter in front of the back end: its best particle's pose and lineage, and a restart
    of every particle at a corrected pose on a map rebuilt along the nodes' optimised poses
    (`FrontEnd2D` here, `omnitof.slam.filter3d.FrontEnd3D` for the 3D filter)."""

    def best_pose(self) -> np.ndarray | None: ...

    def best_trajectory(self) -> tuple[np.ndarray, np.ndarray]: ...

    def reset_along(self, pose: np.ndarray, scan: int, node_scans: list[int], node_poses: list[np.ndarray]) -> None: ...


class FrontEnd2D:
    """The 2D filter as the back end's front end: it restarts on a grid of every node's scan at
    its optimised pose (`ParticleFilter.reset`)."""

    def __init__(self, pf: _core.ParticleFilter, scans: ScanSequence, map_cfg: MapConfig):
        self.pf, self.scans, self.map_cfg = pf, scans, map_cfg

    def best_pose(self) -> np.ndarray | None:
        return self.pf.best_pose()

    def best_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pf.best_trajectory()

    def reset_along(self, pose: np.ndarray, scan: int, node_scans: list[int], node_poses: list[np.ndarray]) -> None:
        self.pf.reset(pose, scan, grid_along(self.scans, node_scans, np.asarray(node_poses), self.map_cfg))


@dataclass
class Closure:
    """One loop-closure search that found a match: node `node` (an integrated scan) seen in the
    submap whose first node is `anchor`; `measured` is the node's pose relative to the anchor's;
    `accepted` says whether the optimisation kept it (its robust weight stayed high)."""

    node: int
    anchor: int
    submap: int
    measured: np.ndarray
    score: float
    covariance: np.ndarray
    search: str  # "local" or "global"
    accepted: bool | None = None  # None until an optimisation has judged it
    information: np.ndarray | None = None  # inverse of the edge's covariance, once computed


@dataclass
class _Submap:
    grid: _core.Submap
    first: int  # first node
    nodes: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)  # insertion poses of its nodes
    length: float = 0.0

    @property
    def anchor_pose(self) -> np.ndarray:
        return self.poses[0]

    @cached_property
    def centre(self) -> np.ndarray:
        """Mean insertion position (x, y) of its nodes (asked only once it is finished)."""
        return np.mean(np.asarray(self.poses)[:, :2], axis=0)


class PoseGraphBackend:
    """Submaps, loop closures and the pose graph of one run (see the module docstring)."""

    def __init__(self, cfg: BackendConfig, map_cfg: MapConfig, field_sigma: float, scans: ScanSequence,
                 threads: int):
        self.cfg = cfg
        self.field_sigma = field_sigma
        self.map_cfg = map_cfg
        self.scans = scans
        self.threads = max(1, threads)
        self.max_range = min(map_cfg.max_range, scans.max_range)
        self.scan_of: list[int] = []  # node -> scan index
        self.frontend: list[np.ndarray] = []  # node -> front-end pose (its segment's frame)
        self.odometry_edges: list[np.ndarray] = []  # edge j-1 -> j, for j >= 1
        self.estimate: list[np.ndarray] = []  # node -> best estimate (optimised or propagated)
        self.segment_start = 0  # first node of the current front-end segment
        self.submaps: list[_Submap] = []
        # Finished submaps that hold their search grids, least recently searched first.
        self._with_grids: OrderedDict[int, None] = OrderedDict()
        self.grids_remade = 0
        self.closures: list[Closure] = []
        self.rejected_searches = 0
        self.searches = 0
        self.optimisations = 0
        self.feedbacks = 0
        self.readmitted = 0  # closures `_readmit` took back after graduated non-convexity
        self.graduated = 0  # optimisations that needed graduated non-convexity
        self._pending = 0  # closures added since the last optimisation
        self._since_closure = 0
        self._searched_globally = False
        self._last_optimised_node = -10**9
        self._edge_factors: dict[int, tuple[bytes, gtsam.BetweenFactorPose2]] = {}
        # The odometry check's corrections: node -> shares of the scan's end points near the recent
        # map at the wheels' and the corrected pose (None: not judged). Those that relocalised
        # the robot onto an older map: node -> the wheels' motion from the node before.
        self.corrections: dict[int, tuple[float, float] | None] = {}
        self.relocalisations: dict[int, np.ndarray] = {}
        self.spread: set[int] = set()  # relocalisations whose wheels' edge the last optimisation used
        self._judging: list[int] | None = None  # those whose wheels' edge the verdicts use (None: all)
        self.seconds = {"submaps": 0.0, "search": 0.0, "optimise": 0.0, "feedback": 0.0, "judge": 0.0}

    # --- the run ----------------------------------------------------------------------------

    def add_node(self, scan: int, pf: FrontEnd, corrected: bool = False) -> None:
        """Take the filter's state after integrating scan `scan`: add the node, insert it into the
        current submap, search loop closures, optimise and feed back where it pays. `corrected`:
        the filter's odometry check replaced the wheels' motion into this scan."""
        pose = np.asarray(pf.best_pose(), dtype=np.float64)
        j = len(self.scan_of)
        self.scan_of.append(scan)
        self.frontend.append(pose)
        if j == 0:
            self.estimate.append(pose.copy())
        else:
            self.odometry_edges.append(relative(self.frontend[j - 1], pose))
            # Propagate from the previous node's best estimate along the front end's motion.
            self.estimate.append(compose(self.estimate[j - 1], self.odometry_edges[-1]))
            if corrected and self.cfg.relocalisation_margin is not None:
                clock = time.perf_counter()
                self._judge_correction(j)
                self._lap("judge", clock)
        clock = time.perf_counter()
        self._insert(j, pose, pf)
        found = 0
        if j % self.cfg.search_every == 0:
            clock = self._lap("submaps", clock)
            found = self._search(j)
            self._lap("search", clock)
        # A global search that found nothing waits as long again before the next one.
        self._since_closure = 0 if found or self._searched_globally else self._since_closure + 1
        self._pending += found
        if self._pending and j - self._last_optimised_node >= self.cfg.optimize_every and self._news_disagree():
            clock = time.perf_counter()
            self._refresh_segment(pf)
            self.optimise()
            clock = self._lap("optimise", clock)
            self._feed_back(j, pf)
            self._lap("feedback", clock)

    def _judge_correction(self, j: int) -> None:
        """Whether the check's correction at node j repaired the wheels or relocalised the robot
        onto an older map: the share of the scan's end points near the map of the last
        `relocalisation_recent_m` metres of the segment (at the front end's poses), at the wheels'
        pose and at the corrected one. A slip leaves the corrected pose explained far better;
        a relocalisation does not (the simulated worlds, tof3d: wheel glitches gain +0.17 to +0.92
        but for one run's two, −0.25 and +0.08, which the optimum's test then kept as jumps;
        loop ends −0.65 to +0.02; BENCHMARKS.md, "A relocalisation where a loop ends, spread
        along the loop")."""
        recent = self._recent_nodes(j)
        scans = self.scans
        k = self.scan_of[j]
        ranges = scans.scan_ranges(k)
        points = int(np.count_nonzero(np.isfinite(ranges) & (ranges < self.max_range)))
        if len(recent) < RELOCALISATION_MIN_NODES or points < RELOCALISATION_MIN_POINTS:
            self.corrections[j] = None  # too little map or scan to tell: the front end's edge stands
            return
        wheels = relative(scans.odometry[self.scan_of[j - 1]], scans.odometry[k])
        grid = grid_along(scans, [self.scan_of[i] for i in recent], np.asarray([self.frontend[i] for i in recent]),
                          self.map_cfg)
        starts = np.stack([compose(self.frontend[j - 1], wheels), self.frontend[j]])
        both = np.ascontiguousarray(np.broadcast_to(ranges, (2, len(ranges))))
        _, share = grid.match_each(starts, both, scans.scan_angles(k), sensor_pose=scans.sensor_pose,
                                   sigma=self.field_sigma, max_range=self.max_range, gauss_newton=0,
                                   threads=self.threads)
        shares = (float(share[0]), float(share[1]))
        self.corrections[j] = shares
        if shares[1] < shares[0] + self.cfg.relocalisation_margin:
            self.relocalisations[j] = wheels

    def _recent_nodes(self, j: int) -> list[int]:
        """The nodes of the current segment before j within `relocalisation_recent_m` metres of
        travel, oldest first."""
        out, moved, i = [], 0.0, j - 1
        while i >= self.segment_start and moved < self.cfg.relocalisation_recent_m:
            out.append(i)
            if i > self.segment_start:
                moved += float(np.hypot(*(self.frontend[i][:2] - self.frontend[i - 1][:2])))
            i -= 1
        return out[::-1]

    def _news_disagree(self) -> bool:
        """Whether a closure not yet judged disagrees with the current estimate. Those that
        agree are accepted as they come: they confirm the estimate within its uncertainty, so
        an optimisation would hardly move it, and it waits until one disagrees or for the end
        of the run (Intel, seed 0: 40 optimisations instead of 54)."""
        news = [c for c in self.closures if c.accepted is None]
        agree = self._agreement(news)
        for c, ok in zip(news, agree):
            if ok:
                c.accepted = True
        self._pending = int((~agree).sum())
        return bool(self._pending)

    def _lap(self, what: str, since: float) -> float:
        now = time.perf_counter()
        self.seconds[what] += now - since
        return now

    def finish(self, pf: FrontEnd) -> np.ndarray:
        """The optimised pose of every node (K, 3), after a last optimisation."""
        if not self.scan_of:
            return np.zeros((0, 3))
        self._refresh_segment(pf)
        if self.closures:
            self.optimise(final=True)
        else:
            self.estimate = self._chain()
        return np.asarray(self.estimate)

    # --- submaps ----------------------------------------------------------------------------

    def _new_submap(self, first: int) -> _Submap:
        m = self.map_cfg
        grid = _core.Submap(m.resolution, m.l_occ, m.l_free, m.l_min, m.l_max, self.max_range,
                            clear_no_echo=m.clear_no_echo, once_per_scan=m.once_per_scan,
                            spread_sigma=self.field_sigma, threads=self.threads)
        sub = _Submap(grid, first)
        self.submaps.append(sub)
        return sub

    def _insert(self, j: int, pose: np.ndarray, pf: FrontEnd) -> None:
        """Count node j into the submap in progress; once it is `submap_length` long, build and
        finish it. It is built only then, from the best particle's lineage as it is then: the
        front end may still have revised the poses of its first nodes after they came in."""
        current = self.submaps[-1] if self.submaps and not self.submaps[-1].grid.finished else None
        if current is None:
            current = self._new_submap(j)
        elif current.nodes:
            current.length += float(np.hypot(*(pose[:2] - self.frontend[current.nodes[-1]][:2])))
        current.nodes.append(j)
        if current.length >= self.cfg.submap_length:
            self._build(current, pf)

    def _build(self, sub: _Submap, pf: FrontEnd) -> None:
        assert sub is self.submaps[-1], "only the submap in progress is built"
        self._refresh_segment(pf)
        for j in sub.nodes:
            k = self.scan_of[j]
            sub.grid.insert(self.frontend[j], self.scans.scan_ranges(k), self.scans.scan_angles(k),
                            self.scans.sensor_pose)
            sub.poses.append(self.frontend[j].copy())
        sub.grid.finish()
        self._keep_grids(len(self.submaps) - 1)  # only the newest submap is ever built

    def _keep_grids(self, s: int) -> None:
        """Submap s was just finished or searched: it keeps its search grids, and the least
        recently searched beyond `search_grids_kept` drop theirs (made again, the same to the
        bit, when next searched), so that the back end's memory stops growing with the log."""
        self._with_grids[s] = None
        self._with_grids.move_to_end(s)
        while len(self._with_grids) > self.cfg.search_grids_kept:
            old, _ = self._with_grids.popitem(last=False)
            self.submaps[old].grid.release_grids()

    def _close_current_submap(self, pf: FrontEnd) -> None:
        """Finish the submap in progress (before a correction moves the front end's frame)."""
        if self.submaps and not self.submaps[-1].grid.finished:
            self._build(self.submaps[-1], pf)

    # --- loop closures ----------------------------------------------------------------------

    def _candidates(self, j: int, radius: float) -> list[int]:
        """Finished submaps far enough back in time whose centre is within `radius` of node j's
        estimate, nearest first."""
        current = len(self.submaps) - (0 if self.submaps[-1].grid.finished else 1)
        eligible = [s for s in range(max(0, current - self.cfg.skip_recent_submaps)) if self.submaps[s].grid.finished]
        if not eligible:
            return []
        subs = [self.submaps[s] for s in eligible]
        # Each centre, kept relative to its submap's first node, follows that node's estimate.
        anchors = np.array([sub.anchor_pose for sub in subs])
        centres = np.array([[*sub.centre, 0.0] for sub in subs])
        firsts = np.array([self.estimate[sub.first] for sub in subs])
        where = compose(firsts, relative(anchors, centres))[:, :2]
        d = np.hypot(*(where - self.estimate[j][:2]).T)
        order = np.argsort(d, kind="stable")
        return [eligible[k] for k in order if d[k] <= radius]

    def _search(self, j: int) -> int:
        """Search node j in the submaps near it (or, when lost, in all); returns the number of
        closures found."""
        self._searched_globally = False
        if not self.submaps:
            return 0
        k = self.scan_of[j]
        ranges, angles = self.scans.scan_ranges(k), self.scans.scan_angles(k)
        cfg = self.cfg
        lost = cfg.global_search_after > 0 and self._since_closure >= cfg.global_search_after
        self._searched_globally = lost
        if lost:
            candidates, kind = self._candidates(j, math.inf), "global"
        else:
            candidates, kind = self._candidates(j, cfg.search_radius)[: cfg.max_closures_per_scan], "local"
        found = 0
        for s in candidates:
            sub = self.submaps[s]
            initial = compose(sub.anchor_pose, relative(self.estimate[sub.first], self.estimate[j]))
            if lost:
                # Anywhere in the submap: around its centre, as far as its scans reach.
                initial = np.array([*sub.centre, initial[2]])
                linear = min(self.max_range, cfg.search_radius) + 0.5 * sub.length
                angular, min_score = math.pi, cfg.global_min_score
            else:
                linear, angular, min_score = cfg.linear_window, math.radians(cfg.angular_window_deg), cfg.min_score
            self.searches += 1
            self.grids_remade += not sub.grid.has_grids
            match = sub.grid.match_scan(ranges, angles, initial, linear, angular, min_score,
                                        sensor_pose=self.scans.sensor_pose, field_sigma=self.field_sigma)
            self._keep_grids(s)
            if match is None:
                self.rejected_searches += 1
                continue
            pose, score, covariance = match
            self.closures.append(Closure(
                node=j, anchor=sub.first, submap=s, measured=relative(sub.anchor_pose, np.asarray(pose)),
                score=float(score), covariance=np.asarray(covariance), search=kind,
            ))
            found += 1
        return found

    # --- the graph --------------------------------------------------------------------------

    def _refresh_segment(self, pf: FrontEnd) -> None:
        """Front-end poses and edges of the current segment from the best particle's lineage,
        which is consistent with itself (the best particle may have changed since a node was
        added)."""
        scans, poses = pf.best_trajectory()
        node_of = {s: j for j, s in enumerate(self.scan_of[self.segment_start:], start=self.segment_start)}
        for s, p in zip(scans.tolist(), poses):
            j = node_of.get(int(s))
            if j is not None:
                self.frontend[j] = np.asarray(p, dtype=np.float64)
        start = self.segment_start
        if len(self.scan_of) > start + 1:
            poses = np.asarray(self.frontend[start:])
            self.odometry_edges[start:] = list(relative(poses[:-1], poses[1:]))

    def _edges(self, spread: set[int] | list[int]) -> list[np.ndarray]:
        """The front-end edges, with the wheels' motion into the relocalised nodes in `spread`."""
        edges = list(self.odometry_edges)
        for j in spread:
            edges[j - 1] = self.relocalisations[j]
        return edges

    def _chain(self) -> list[np.ndarray]:
        """Node poses from the first node along the front-end edges only."""
        # Sequential by nature: each pose is the one before it moved by the edge.
        out = [self.estimate[0]]
        for edge in self.odometry_edges:
            out.append(compose(out[-1], edge))
        return out

    def _odometry_sigmas(self, edge: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        moved = float(np.hypot(edge[0], edge[1]))
        sxy = cfg.odometry_sigma_xy + cfg.odometry_sigma_xy_per_m * moved
        sth = math.radians(cfg.odometry_sigma_deg + cfg.odometry_sigma_deg_per_m * moved)
        return np.array([sxy, sxy, sth])

    def _odometry_noise(self, edge: np.ndarray) -> gtsam.noiseModel.Base:
        return gtsam.noiseModel.Diagonal.Sigmas(self._odometry_sigmas(edge))

    def _compound(self, a: int, b: int, edges: list[np.ndarray] | None = None) -> tuple[gtsam.Pose2, np.ndarray]:
        """The front-end edges (default: `odometry_edges`) from node a to node b composed into
        one (a < b), with the covariance propagated to first order: composing T with an edge E
        moves T's covariance by E⁻¹'s adjoint, Σ ← Ad(E⁻¹) Σ Ad(E⁻¹)ᵀ + Σ_E (GTSAM's right-hand
        tangent convention)."""
        # Sequential by nature, and only over the chain between two closure nodes.
        total, cov = gtsam.Pose2(), np.zeros((3, 3))
        for edge in (self.odometry_edges if edges is None else edges)[a:b]:
            e = gtsam.Pose2(*edge)
            ad = e.inverse().AdjointMap()
            cov = ad @ cov @ ad.T + np.diag(self._odometry_sigmas(edge) ** 2)
            total = total.compose(e)
        return total, cov

    def _closure_noise(self, c: Closure) -> gtsam.noiseModel.Base:
        """The match's covariance (world-aligned in the submap's frame) turned into the anchor's
        frame, with floors, and the robust kernel."""
        cfg = self.cfg
        base = gtsam.noiseModel.Gaussian.Covariance(self._closure_covariance(c))
        if cfg.robust_kernel == "none":
            return base
        if cfg.robust_kernel == "huber":
            kernel = gtsam.noiseModel.mEstimator.Huber.Create(cfg.kernel_width)
        else:
            kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.kernel_width)
        return gtsam.noiseModel.Robust.Create(kernel, base)

    def _closure_covariance(self, c: Closure) -> np.ndarray:
        """The match's covariance, found in the submap's frame, turned into the anchor node's
        frame (where `measured` lives), with the configured floors added."""
        rot = _rotation(-float(self.submaps[c.submap].anchor_pose[2]))
        cov = c.covariance.copy()
        cov[:2, :2] = rot @ cov[:2, :2] @ rot.T
        cov[:2, 2] = rot @ cov[:2, 2]
        cov[2, :2] = cov[:2, 2]
        cfg = self.cfg
        return cov + np.diag([cfg.closure_sigma_xy_min**2] * 2 + [math.radians(cfg.closure_sigma_deg_min) ** 2])

    def optimise(self, final: bool = False) -> None:
        """Optimise the whole graph from the current estimates.

        Where every new closure agrees with the current estimate (within the chi-square bound),
        one Levenberg-Marquardt run with the robust kernel on the kept closures suffices. Where a
        new one does not, the front end may have gone wrong, and a robust kernel started from the wrong
        estimate would discount exactly the closures that could repair it. Then graduated
        non-convexity decides (GTSAM's GncLMOptimizer with the truncated-least-squares loss;
        Yang, Antonante, Tzoumas, Carlone, RA-L 2020): it starts from the convex problem, where
        a consistent group of closures outweighs a few false ones, and turns the loss down to
        truncation step by step; the front-end edges are known inliers. Its verdict on every
        closure (old ones too, so a wrongly kept one can still go), with the dropped ones that
        agree with the kept ones taken back (`_readmit`), stands until the next such run; the
        closures it keeps go into the robust Levenberg-Marquardt run.

        With relocalisations (see the module docstring), the closures are first judged and the
        graph optimised with the wheels' edge into each. Where the optimum then puts a
        relocalised node nearer the wheels' pose than the relocalised one, the kept closures do
        not say what the relocalisation said: everything is judged and optimised again, from the
        same verdicts, with its jump, as without the relocalisation.
        """
        spread = list(self.relocalisations)
        before = ([c.accepted for c in self.closures], self.graduated, self.readmitted)
        estimate = self._judged_optimum(final, spread)
        jumps = [j for j in spread if not self._sides_with_relocalisation(j, estimate[j])]
        if jumps:
            for c, accepted in zip(self.closures, before[0]):
                c.accepted = accepted
            self.graduated, self.readmitted = before[1:]
            spread = [j for j in spread if j not in jumps]
            estimate = self._judged_optimum(final, spread)
        self.spread = set(spread)
        self.estimate = estimate
        kept = [c for c in self.closures if c.accepted]
        for c, ok in zip(kept, self._agreement(kept)):
            if not ok:
                c.accepted = False  # the robust kernel discounted it
        self.optimisations += 1
        self._last_optimised_node = len(self.estimate) - 1
        self._pending = 0

    def _judged_optimum(self, final: bool, spread: list[int]) -> list[np.ndarray]:
        """`optimise`'s verdicts on the closures and its robust optimum, with the wheels' edges
        into the relocalisations in `spread`."""
        self._judging = spread
        pending = [c for c in self.closures if c.accepted is None]
        agree = self._agreement(pending)
        disagreeing = [c for c, ok in zip(pending, agree) if not ok]
        for c, ok in zip(pending, agree):
            if ok:
                c.accepted = True
        # One closure that disagrees proves nothing on its own: it waits, left out, for a
        # second one or for the end of the run.
        if disagreeing and (len(disagreeing) >= GNC_MIN_DISAGREEING or final):
            self.graduated += 1
            for c, keep in zip(self.closures, self._readmit(self._graduated())):
                c.accepted = keep
        return self._optimum([c.accepted is True for c in self.closures], spread)

    def _optimum(self, use: list[bool], spread: list[int]) -> list[np.ndarray]:
        """Levenberg-Marquardt with the robust kernel on the closures in `use`, from the current
        estimate, with the wheels' edges into the relocalisations in `spread`."""
        graph, values = self._graph(robust=True, use=use, spread=spread)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(LM_ITERATIONS)
        # Started from the last optimum, the graph is near its minimum; a millimetre-level
        # change of the cost is all the accuracy the map can show.
        params.setRelativeErrorTol(LM_RELATIVE_TOLERANCE)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        return [_pose(result.atPose2(j)) for j in range(len(self.estimate))]

    def _sides_with_relocalisation(self, j: int, pose: np.ndarray) -> bool:
        """Whether `pose` (node j's optimum) lies nearer the relocalised pose than the wheels'
        pose, both in the front end's frame, in units of the closures' smallest sigmas."""
        cfg = self.cfg
        scale = np.array([cfg.closure_sigma_xy_min, cfg.closure_sigma_xy_min, math.radians(cfg.closure_sigma_deg_min)])
        wheels = compose(self.frontend[j - 1], self.relocalisations[j])
        def distance(to: np.ndarray) -> float:
            d = pose - to
            d[2] = wrap_angle(d[2])
            return float(np.linalg.norm(d / scale))
        return distance(self.frontend[j]) < distance(wheels)

    def _graduated(self) -> list[bool]:
        """Which closures graduated non-convexity keeps as inliers (see `optimise`, which then
        takes back those of the rest that agree with them: `_readmit`).

        It runs on the graph reduced to the nodes that closures join (and the first): the
        front-end edges between two such nodes are compounded into one (`_compound`), which
        marginalises the chain between them, exactly up to linearisation, since nothing else
        touches it. On Intel that is a few hundred of 1400 nodes, and the verdicts are those of
        the whole graph at about a twentieth of the cost (Intel: 0.4 s instead of 7.5 s)."""
        graph, values, n_fixed = self._reduced_graph()
        inner = gtsam.LevenbergMarquardtParams()
        inner.setMaxIterations(GNC_INNER_ITERATIONS)
        params = gtsam.GncLMParams(inner)
        params.setLossType(gtsam.GncLossType.TLS)
        params.setKnownInliers(list(range(n_fixed)))  # the prior and the compounded front-end edges
        gnc = gtsam.GncLMOptimizer(graph, values, params)
        gnc.setInlierCostThresholdsAtProbability(CHI2_PROBABILITY)
        gnc.optimize()
        weights = np.asarray(gnc.getWeights())
        return [bool(w > 0.5) for w in weights[n_fixed:]]

    def _reduced_graph(self, use: list[bool] | None = None) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, int]:
        """The graph of `_graduated`: the prior on node 0, the compounded front-end edges
        between the nodes that closures join, then the closures (those in `use`, default all)
        as plain Gaussian edges. Keys are positions in the sorted node list (`_reduced_keys`).
        Also returns the number of factors before the closures. The edges into the
        relocalisations being judged (`optimise`; default all) are the wheels'."""
        keys = self._reduced_keys()
        edges = self._edges(list(self.relocalisations) if self._judging is None else self._judging)
        index = {k: i for i, k in enumerate(keys)}
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*self.estimate[0]), gtsam.noiseModel.Constrained.All(3)))
        for a, b in zip(keys[:-1], keys[1:]):
            measured, cov = self._compound(a, b, edges)
            graph.add(gtsam.BetweenFactorPose2(index[a], index[b], measured, gtsam.noiseModel.Gaussian.Covariance(cov)))
        for c, keep in zip(self.closures, use or [True] * len(self.closures)):
            if keep:
                noise = gtsam.noiseModel.Gaussian.Covariance(self._closure_covariance(c))
                graph.add(gtsam.BetweenFactorPose2(index[c.anchor], index[c.node], gtsam.Pose2(*c.measured), noise))
        for k in keys:
            values.insert(index[k], gtsam.Pose2(*self.estimate[k]))
        return graph, values, len(keys)

    def _reduced_keys(self) -> list[int]:
        return sorted({0, *(c.anchor for c in self.closures), *(c.node for c in self.closures)})

    def _readmit(self, kept: list[bool]) -> list[bool]:
        """`kept` with the closures graduated non-convexity dropped taken back, one at a time
        (highest score first), where the optimum of the reduced graph with it and the kept ones
        holds every one of them within the chi-square bound; or, where it contradicts only kept
        closures of lower score, in their place (the same test on the exchanged set).

        Why: where closures of one place contradict each other (a scan matched against the same
        corridor at several places along it, one at most right), graduated non-convexity starts
        from their average and may keep the wrong one, or none. On MIT CSAIL, seed 4, it kept a
        closure 0.95 m off the front end (score 0.78) and dropped one that agreed with it to 2 cm
        (0.85); the optimum moved 0.9 m, that correction was fed back to the filter, and the map
        drew a corridor twice (BENCHMARKS.md). A closure taken back agrees with everything kept,
        so it cannot bend the map against them; a false one that happens to agree does no harm.
        Between two that exclude each other the better match stays, as a scan matcher would
        choose."""
        kept = list(kept)
        score = [c.score for c in self.closures]
        def by_score(indices) -> list[int]:  # best first; ties in the order found
            return sorted(indices, key=lambda i: (-score[i], i))

        todo = by_score(i for i, k in enumerate(kept) if not k)
        # At most four tries per closure: exchanges put closures back on the list.
        for _ in range(4 * len(kept)):
            if not todo:
                break
            i = todo.pop(0)
            trial = kept.copy()
            trial[i] = True
            failing = self._disagreeing(trial)
            if failing:
                # Leave out the lower-scored ones the compromise optimum fails (the contradicting
                # closure among them): if the rest then all agree, the exchange stands, and
                # those left out are tried again (most agree once the contradiction is gone).
                lower = [k for k in failing if k != i and score[k] < score[i]]
                if not lower:
                    continue
                for k in lower:
                    trial[k] = False
                if self._disagreeing(trial):
                    continue
                todo = by_score(set(todo) | set(lower))
            kept = trial
            self.readmitted += 1
        return kept

    def _disagreeing(self, use: list[bool]) -> list[int]:
        """The closures in `use` that the optimum of the reduced graph with them (plain least
        squares) does not hold within the chi-square bound."""
        keys = self._reduced_keys()
        index = {k: i for i, k in enumerate(keys)}
        graph, values, _ = self._reduced_graph(use)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(LM_ITERATIONS)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        poses = np.asarray(self.estimate).copy()  # only the reduced graph's nodes are read
        poses[keys] = [_pose(result.atPose2(index[k])) for k in keys]
        used = [i for i, keep in enumerate(use) if keep]
        agree = self._agreement([self.closures[i] for i in used], poses)
        return [i for i, ok in zip(used, agree) if not ok]

    def _graph(self, *, robust: bool, use: list[bool], spread: list[int] | None = None
               ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The prior on the first node, the front-end edges (the wheels' into the relocalisations
        in `spread`, default those of the last optimisation), then the closures in `use`."""
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*self.estimate[0]), gtsam.noiseModel.Constrained.All(3)))
        for j, edge in enumerate(self._edges(self.spread if spread is None else spread), start=1):
            graph.add(self._edge_factor(j, edge))
        for c, keep in zip(self.closures, use):
            if keep:
                noise = self._closure_noise(c) if robust else gtsam.noiseModel.Gaussian.Covariance(self._closure_covariance(c))
                graph.add(gtsam.BetweenFactorPose2(c.anchor, c.node, gtsam.Pose2(*c.measured), noise))
        for j, pose in enumerate(self.estimate):
            values.insert(j, gtsam.Pose2(*pose))
        return graph, values

    def _edge_factor(self, j: int, edge: np.ndarray) -> gtsam.BetweenFactorPose2:
        """The factor of front-end edge j-1 -> j, made once per value of the edge: the graph is
        rebuilt for every optimisation, and most edges have not changed since the last one
        (Intel: 40 optimisations of up to 1400 edges)."""
        key = edge.tobytes()
        cached = self._edge_factors.get(j)
        if cached is None or cached[0] != key:
            cached = (key, gtsam.BetweenFactorPose2(j - 1, j, gtsam.Pose2(*edge), self._odometry_noise(edge)))
            self._edge_factors[j] = cached
        return cached[1]

    def _agreement(self, closures: list[Closure], poses: np.ndarray | None = None) -> np.ndarray:
        """For each closure, whether the node poses (default: the current estimate) agree with
        it: its squared Mahalanobis distance within the CHI2_PROBABILITY quantile of chi-square
        with 3 degrees of freedom."""
        if not closures:
            return np.zeros(0, dtype=bool)
        for c in closures:
            if c.information is None:
                c.information = np.linalg.inv(self._closure_covariance(c))
        estimate = np.asarray(self.estimate) if poses is None else poses
        predicted = relative(estimate[[c.anchor for c in closures]], estimate[[c.node for c in closures]])
        error = predicted - np.array([c.measured for c in closures])
        error[:, 2] = wrap_angle(error[:, 2])
        info = np.array([c.information for c in closures])
        return np.einsum("ki,kij,kj->k", error, info, error) <= CHI2_3DOF_99

    # --- feedback ---------------------------------------------------------------------------

    def _feed_back(self, j: int, pf: FrontEnd) -> None:
        corrected = self.estimate[j]
        d = relative(self.frontend[j], corrected)
        if math.hypot(d[0], d[1]) < self.cfg.feedback_xy and abs(d[2]) < math.radians(self.cfg.feedback_deg):
            return
        self._close_current_submap(pf)
        pf.reset_along(corrected, self.scan_of[j], self.scan_of, self.estimate)
        self.feedbacks += 1
        self.frontend[j] = corrected.copy()
        self.segment_start = j

    def build_grid(self) -> _core.OccupancyGrid:
        """A grid of every node's scan at its current estimate (the corrected map)."""
        return grid_along(self.scans, self.scan_of, self.estimate, self.map_cfg)

    # --- reporting --------------------------------------------------------------------------

    def stats(self) -> dict:
        accepted = [c for c in self.closures if c.accepted]
        return {
            "nodes": len(self.scan_of),
            "submaps": len(self.submaps),
            "searches": self.searches,
            "closures_found": len(self.closures),
            "closures_accepted": len(accepted),
            "closures_rejected": len(self.closures) - len(accepted),
            "searches_without_match": self.rejected_searches,
            "global_closures": sum(c.search == "global" for c in self.closures),
            "optimisations": self.optimisations,
            "graduated_optimisations": self.graduated,
            "closures_readmitted": self.readmitted,
            "feedbacks": self.feedbacks,
            "search_grids_remade": self.grids_remade,
            "submap_bytes": sum(s.grid.memory_bytes() for s in self.submaps),
            "seconds": {k: round(v, 2) for k, v in self.seconds.items()},
        }

    def graph(self, nodes: np.ndarray) -> dict:
        """SlamResult.graph: the nodes' poses `nodes` (K, 3), the closures kept and rejected as
        (anchor, node) pairs, the relocalised nodes, and the edges of the last optimisation
        (`edges` (E, 2) node pairs, `measured` (E, 3) relative poses, `information` (E, 3, 3)):
        the front end's (the wheels' into the relocalisations it spread) and the kept closures,
        each closure's information scaled by its robust kernel's weight at the optimum (the
        weights of iteratively reweighted least squares, at their fixed point), so that the
        plain least squares of these edges has the robust optimum's poses."""
        def pairs(kept: bool) -> np.ndarray:
            edges = [[c.anchor, c.node] for c in self.closures if bool(c.accepted) == kept]
            return np.array(edges, dtype=np.int64).reshape(-1, 2)
        front = self._edges(self.spread)
        kept = [c for c in self.closures if c.accepted]
        edges = [[j, j + 1] for j in range(len(front))] + [[c.anchor, c.node] for c in kept]
        measured = [np.asarray(e, dtype=np.float64) for e in front] + [np.asarray(c.measured, dtype=np.float64) for c in kept]
        information = ([np.diag(1.0 / self._odometry_sigmas(e) ** 2) for e in front]
                       + [self._closure_weight(c) * np.linalg.inv(self._closure_covariance(c)) for c in kept])
        return {"nodes": nodes, "closures": pairs(True), "rejected": pairs(False),
                "relocalised": np.array(sorted(self.relocalisations), dtype=np.int64),
                "edges": np.array(edges, dtype=np.int64).reshape(-1, 2),
                "measured": np.array(measured, dtype=np.float64).reshape(-1, 3),
                "information": np.array(information, dtype=np.float64).reshape(-1, 3, 3)}

    def _closure_weight(self, c: Closure) -> float:
        """The robust kernel's weight of closure `c` at the current estimate (1 without a kernel):
        the kernel's weight function of its whitened error's norm, as GTSAM's Robust noise
        model weighs it."""
        noise = self._closure_noise(c)
        if not isinstance(noise, gtsam.noiseModel.Robust):
            return 1.0
        predicted = gtsam.Pose2(*self.estimate[c.anchor]).between(gtsam.Pose2(*self.estimate[c.node]))
        error = gtsam.Pose2.Logmap(gtsam.Pose2(*c.measured).between(predicted))
        whitened = math.sqrt(float(error @ np.linalg.solve(self._closure_covariance(c), error)))
        return float(noise.robust().weight(whitened))

    def correction_table(self) -> list[dict]:
        """Every correction of the odometry check, for summary.yaml: its scan, the recent map's
        share of end points at the wheels' and the corrected pose, and what became of it:
        "slip" (the front end's edge stands), "relocalised, spread" (the wheels' edge: the
        closures place the node where the relocalisation did), "relocalised, kept" (the jump
        stands: the closures do not) or "not judged" (too little recent map or fewer than
        RELOCALISATION_MIN_POINTS end points: the front end's edge stands)."""
        def row(j: int, shares: tuple[float, float] | None) -> dict:
            if shares is None:
                return {"scan": int(self.scan_of[j]), "recent_share_wheels": None, "recent_share_corrected": None,
                        "verdict": "not judged"}
            if j not in self.relocalisations:
                verdict = "slip"
            else:
                verdict = "relocalised, spread" if j in self.spread else "relocalised, kept"
            return {"scan": int(self.scan_of[j]), "recent_share_wheels": round(shares[0], 3),
                    "recent_share_corrected": round(shares[1], 3), "verdict": verdict}
        return [row(j, shares) for j, shares in self.corrections.items()]

    def closure_table(self) -> list[dict]:
        """Every closure found, for summary.yaml: scans, score, whether it was kept."""
        return [
            {"scan": int(self.scan_of[c.node]), "anchor_scan": int(self.scan_of[c.anchor]),
             "score": round(c.score, 3), "search": c.search, "accepted": c.accepted}
            for c in self.closures
        ]


def _pose(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _rotation(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])
