"""A small 2D laser world: walls as line segments, a corridor loop, a robot path, wheel odometry
with drift, a planar laser, and people who walk with the robot. It feeds the end-to-end SLAM
tests and the demo.

Frames and units: everything lives in the world frame, x and y on the floor in metres, headings
theta in radians counter-clockwise from +x. A robot pose is world_T_robot = (x, y, theta); the
laser sits at robot_T_sensor (`sensor_pose`), so the ray origin is world_T_robot ⊕ robot_T_sensor,
and beam bearings are in the sensor frame. Times are seconds. A range of +inf means "no echo".

Randomness: each stochastic function takes a seed (an int or a `numpy.random.SeedSequence`) and
draws from `numpy.random.default_rng(seed)`; the same inputs and seed give the same arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from omnitof.errors import ConfigError
from omnitof.geometry import compose, relative, wrap_angle
from omnitof.types import ScanSequence

Seed = int | np.random.SeedSequence

# Ray–segment work is done on (rays × segments) arrays; this bounds one such array to ~8 MB so a
# full dataset never needs more than a few tens of MB at once.
_PAIR_BUDGET = 1 << 18

# A ray that passes exactly through the shared end point of two walls must hit one of them; the
# segment parameter u is compared with this slack so rounding cannot let a ray leak through a
# corner. It lengthens each wall by a relative 1e-12, far below any physical scale.
_U_SLACK = 1e-12


# --------------------------------------------------------------------------------------------
# The world
# --------------------------------------------------------------------------------------------


@dataclass
class World2D:
    """Walls as line segments in the world frame.

    Attributes:
        segments: (M, 2, 2) float64, metres; segments[m] = ((x0, y0), (x1, y1)). Walls have no
            thickness and no side: a ray hits a segment from either side.
    """

    segments: np.ndarray

    def __post_init__(self) -> None:
        seg = np.ascontiguousarray(self.segments, dtype=np.float64)
        if seg.ndim != 3 or seg.shape[1:] != (2, 2):
            raise ValueError(f"segments must have shape (M, 2, 2), got {seg.shape}")
        if not np.all(np.isfinite(seg)):
            raise ValueError("segments must be finite")
        lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
        if np.any(lengths <= 0.0):
            bad = int(np.flatnonzero(lengths <= 0.0)[0])
            raise ValueError(f"segment {bad} has zero length")
        self.segments = seg

    @classmethod
    def from_polylines(cls, polylines: Sequence[np.ndarray]) -> "World2D":
        """A world from polylines, each a (K, 2) array of vertices in metres (K >= 2).

        Consecutive vertices are joined; a closed outline repeats its first vertex at the end.
        """
        parts = []
        for i, poly in enumerate(polylines):
            p = np.asarray(poly, dtype=np.float64)
            if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
                raise ValueError(f"polyline {i} must have shape (K >= 2, 2), got {p.shape}")
            parts.append(np.stack([p[:-1], p[1:]], axis=1))
        if not parts:
            raise ValueError("a world needs at least one polyline")
        return cls(np.concatenate(parts, axis=0))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of all walls, metres."""
        pts = self.segments.reshape(-1, 2)
        return (float(pts[:, 0].min()), float(pts[:, 0].max()),
                float(pts[:, 1].min()), float(pts[:, 1].max()))

    def raycast(
        self, origins: np.ndarray, angles: np.ndarray, max_range: float = math.inf
    ) -> np.ndarray:
        """Distance along each ray to the nearest wall.

        Args:
            origins: (N, 2) ray origins in the world frame, metres.
            angles: (N, B) ray directions in the world frame, radians from +x; a (B,) array is
                used for every origin.
            max_range: hits farther than this are reported as inf. Walls that cannot be reached
                within it are skipped, which is what keeps a scan sequence cheap.

        Returns:
            (N, B) float64 distances in metres; inf where the ray hits nothing (within max_range).
        """
        origins = np.asarray(origins, dtype=np.float64)
        if origins.ndim != 2 or origins.shape[1] != 2:
            raise ValueError(f"origins must have shape (N, 2), got {origins.shape}")
        n = len(origins)
        angles = np.asarray(angles, dtype=np.float64)
        if angles.ndim == 1:
            angles = np.broadcast_to(angles, (n, len(angles)))
        if angles.ndim != 2 or angles.shape[0] != n:
            raise ValueError(f"angles must have shape ({n}, B), got {angles.shape}")
        n_beams = angles.shape[1]
        out = np.full((n, n_beams), np.inf)
        if n == 0 or n_beams == 0:
            return out
        rows = max(1, _PAIR_BUDGET // (n_beams * len(self.segments)))
        for start in range(0, n, rows):
            chunk = slice(start, start + rows)
            segs = self._segments_near(origins[chunk], max_range)
            if len(segs):
                out[chunk] = _cast_rays(origins[chunk], angles[chunk], segs)
        out[out > max_range] = np.inf
        return out

    def distance_to_walls(self, points: np.ndarray) -> np.ndarray:
        """Euclidean distance from each point to the nearest wall.

        Args:
            points: (K, 2) points in the world frame, metres.

        Returns:
            (K,) float64 distances in metres.
        """
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise ValueError(f"points must have shape (K, 2), got {points.shape}")
        a = self.segments[:, 0]
        e = self.segments[:, 1] - a
        e_sq = np.einsum("mi,mi->m", e, e)
        out = np.empty(len(points))
        rows = max(1, _PAIR_BUDGET // len(self.segments))
        for start in range(0, len(points), rows):
            p = points[start:start + rows, None, :]  # (k, 1, 2)
            w = p - a  # (k, M, 2): from each segment start to the point
            # Foot of the perpendicular, clamped onto the segment so end points count.
            u = np.clip(np.einsum("kmi,mi->km", w, e) / e_sq, 0.0, 1.0)
            gap = w - u[..., None] * e
            out[start:start + rows] = np.sqrt(np.einsum("kmi,kmi->km", gap, gap).min(axis=1))
        return out

    def _segments_near(self, origins: np.ndarray, max_range: float) -> np.ndarray:
        """The segments whose bounding box comes within max_range of the origins' bounding box.

        A conservative test (boxes, not exact distances): it may keep a segment that is out of
        reach, never drops one that is in reach.
        """
        if not math.isfinite(max_range):
            return self.segments
        lo = origins.min(axis=0) - max_range
        hi = origins.max(axis=0) + max_range
        seg_lo = self.segments.min(axis=1)
        seg_hi = self.segments.max(axis=1)
        keep = np.all((seg_hi >= lo) & (seg_lo <= hi), axis=1)
        return self.segments[keep]


def _cast_rays(origins: np.ndarray, angles: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Nearest hit of rays (n origins × B bearings) with M segments, all at once.

    A ray p + t·d (t > 0) meets the segment a + u·e (0 <= u <= 1) where t·d − u·e = a − p =: w.
    Taking the 2D cross product of both sides with e and with d gives
    t = (w × e) / (d × e) and u = (w × d) / (d × e). Parallel rays (d × e = 0) give inf or NaN,
    which fail the range tests below and so count as misses.
    """
    a = segments[:, 0]  # (M, 2)
    e = segments[:, 1] - a  # (M, 2)
    w = a[None, :, :] - origins[:, None, :]  # (n, M, 2): depends on origin, not on bearing
    w_cross_e = (w[..., 0] * e[:, 1] - w[..., 1] * e[:, 0])[:, None, :]  # (n, 1, M)
    dx = np.cos(angles)[..., None]  # (n, B, 1)
    dy = np.sin(angles)[..., None]
    wx = w[:, None, :, 0]  # (n, 1, M)
    wy = w[:, None, :, 1]
    d_cross_e = dx * e[:, 1] - dy * e[:, 0]  # (n, B, M)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.reciprocal(d_cross_e, out=d_cross_e)
        u = wx * dy
        u -= wy * dx
        u *= inv
        t = np.multiply(w_cross_e, inv, out=inv)
    # |u - 1/2| <= 1/2 is 0 <= u <= 1 in one comparison; NaN fails it.
    u -= 0.5
    hit = np.abs(u, out=u) <= 0.5 + _U_SLACK
    hit &= t > 0.0
    return np.min(t, axis=-1, initial=np.inf, where=hit)


# --------------------------------------------------------------------------------------------
# The corridor loop
# --------------------------------------------------------------------------------------------

# Features along each wall of the default world (16 m x 10 m block, 2 m corridors), as
# (start, width, depth) in metres: start is measured along the wall from its first corner, depth
# away from the corridor (negative: a box standing out into the corridor). Positions scale with
# the wall's length when the block size changes; widths and depths do not. They are deliberately
# irregular: evenly spaced identical niches would let a scan matcher slip by one period.
_Notch = tuple[float, float, float]
_OUTER_FEATURES: tuple[tuple[_Notch, ...], ...] = (
    # bottom, 20 m, from x = -2 towards +x
    ((3.0, 1.0, 0.25), (6.5, 1.5, 0.6), (11.0, 0.6, -0.35), (14.0, 1.0, 0.25), (16.3, 1.0, 1.0)),
    # right, 14 m, from y = -2 towards +y (the room opening is added separately)
    ((3.0, 1.2, 0.4), (10.5, 1.0, 0.25)),
    # top, 20 m, from x = 18 towards -x
    ((3.0, 0.6, -0.3), (5.5, 1.8, 0.8), (9.5, 1.0, 0.25), (12.5, 1.0, 0.5), (15.5, 0.8, -0.4)),
    # left, 14 m, from y = 12 towards -y
    ((3.0, 1.0, 0.25), (6.0, 1.5, 1.2), (10.0, 0.5, -0.3)),
)
_INNER_FEATURES: tuple[tuple[_Notch, ...], ...] = (
    ((3.0, 1.0, 0.3), (7.0, 2.0, 0.7), (12.5, 1.0, 0.3)),  # bottom, 16 m, from x = 0
    ((2.5, 1.0, 0.5), (6.5, 0.6, -0.3)),  # right, 10 m, from y = 0
    ((2.0, 1.0, 0.3), (7.5, 2.0, 1.0), (12.5, 1.0, 0.3)),  # top, 16 m, from x = 16
    ((2.0, 0.8, -0.35), (5.0, 1.5, 0.6)),  # left, 10 m, from y = 10
)
_DEFAULT_BLOCK = (16.0, 10.0)
_DEFAULT_CORRIDOR = 2.0
# The room off the right-hand corridor: opening (start, width) along that wall at the default
# size, the partition's thickness, and the room's extent along the wall and its depth.
_ROOM_OPENING = (6.0, 1.5)
_ROOM_WALL = 0.2
_ROOM_ALONG = (4.5, 9.5)
_ROOM_DEPTH = 4.0
_PILLAR = 0.4  # side of the square pillars, metres


def corridor_loop_world(
    block_width: float = 16.0,
    block_height: float = 10.0,
    corridor_width: float = 2.0,
    *,
    features: bool = True,
) -> World2D:
    """A ring of corridors around a rectangular block, with a room off one side.

    The block spans [0, block_width] x [0, block_height] in the world frame (metres); the
    corridors are corridor_width wide all round, so the outer wall spans
    [-w, block_width + w] x [-w, block_height + w]. With `features` (the default), the walls
    carry door niches, alcoves of different depths and boxes, two outer corners hold pillars,
    and a room (4 m deep, with a pillar) opens off the right-hand (+x) corridor, so that a laser
    can localise along every corridor. `features=False` gives the bare ring, which is degenerate
    for scan matching along a corridor's axis (useful to show why the features are there).
    Deterministic: the same arguments give the same walls.
    """
    for name, value in (("block_width", block_width), ("block_height", block_height),
                        ("corridor_width", corridor_width)):
        if not (math.isfinite(value) and value > 0.0):
            raise ConfigError(f"{name} must be a positive number of metres, got {value}")
    bw, bh, w = block_width, block_height, corridor_width
    outer_corners = np.array([[-w, -w], [bw + w, -w], [bw + w, bh + w], [-w, bh + w]])
    inner_corners = np.array([[0.0, 0.0], [bw, 0.0], [bw, bh], [0.0, bh]])
    if not features:
        return World2D.from_polylines([_close(outer_corners), _close(inner_corners)])

    outer_default = (_DEFAULT_BLOCK[0] + 2 * _DEFAULT_CORRIDOR,
                     _DEFAULT_BLOCK[1] + 2 * _DEFAULT_CORRIDOR)
    outer_profiles = [
        _scaled_notches(_OUTER_FEATURES[i], outer_default[i % 2], _side_length(outer_corners, i))
        for i in range(4)
    ]
    scale_right = _side_length(outer_corners, 1) / outer_default[1]
    outer_profiles[1] = _merge_profiles(outer_profiles[1], _room_profile(scale_right))
    inner_profiles = [
        _scaled_notches(_INNER_FEATURES[i], _DEFAULT_BLOCK[i % 2], _side_length(inner_corners, i))
        for i in range(4)
    ]
    # The outer ring is traversed counter-clockwise, so "away from the corridor" is to the right
    # of the direction of travel; for the block (also counter-clockwise) it is to the left.
    outer = _ring_with_features(outer_corners, outer_profiles, away_left=False, min_gap=w)
    inner = _ring_with_features(inner_corners, inner_profiles, away_left=True, min_gap=0.0)

    lines = [outer, inner]
    # Pillars in the bottom-right and top-left outer corners, clear of the robot's turning arc.
    inset = 0.25 + _PILLAR / 2
    lines.append(_square(np.array([bw + w - inset, -w + inset]), _PILLAR))
    lines.append(_square(np.array([-w + inset, bh + w - inset]), _PILLAR))
    # One pillar inside the room, off-centre so that it is seen through the opening.
    room_mid = _room_point(outer_corners, scale_right, along=7.2, depth=_ROOM_WALL + 2.3)
    lines.append(_square(room_mid, _PILLAR))
    return World2D.from_polylines(lines)


def _close(points: np.ndarray) -> np.ndarray:
    """The closed polyline through points (first vertex repeated at the end)."""
    return np.vstack([points, points[:1]])


def _square(centre: np.ndarray, side: float) -> np.ndarray:
    """A closed axis-aligned square polyline of the given side around centre, metres."""
    h = side / 2
    return _close(centre + np.array([[-h, -h], [h, -h], [h, h], [-h, h]]))


def _side_length(corners: np.ndarray, i: int) -> float:
    return float(np.linalg.norm(corners[(i + 1) % 4] - corners[i]))


def _scaled_notches(notches: Sequence[_Notch], default_len: float, length: float) -> list:
    """Rectangular notch profiles (along, depth) in wall coordinates, positions scaled."""
    scale = length / default_len
    profiles = []
    for start, width, depth in notches:
        s0 = start * scale
        profiles.append([(s0, 0.0), (s0, depth), (s0 + width, depth), (s0 + width, 0.0)])
    return profiles


def _room_profile(scale: float) -> list:
    """The room's outline in wall coordinates (along, depth): partition, room, partition."""
    o0 = _ROOM_OPENING[0] * scale
    o1 = o0 + _ROOM_OPENING[1]
    r0 = o0 - (_ROOM_OPENING[0] - _ROOM_ALONG[0])
    r1 = o1 + (_ROOM_ALONG[1] - _ROOM_OPENING[0] - _ROOM_OPENING[1])
    t, d = _ROOM_WALL, _ROOM_WALL + _ROOM_DEPTH
    return [(o0, 0.0), (o0, t), (r0, t), (r0, d), (r1, d), (r1, t), (o1, t), (o1, 0.0)]


def _room_point(outer_corners: np.ndarray, scale: float, along: float, depth: float) -> np.ndarray:
    """A point inside the room, given in the right-hand wall's coordinates at default size."""
    start = outer_corners[1]
    s = _ROOM_OPENING[0] * scale + (along - _ROOM_OPENING[0])
    return start + np.array([depth, s])  # the right wall runs +y; away from the corridor is +x


def _merge_profiles(profiles: list, extra: list) -> list:
    return sorted([*profiles, extra], key=lambda p: p[0][0])


def _ring_with_features(
    corners: np.ndarray, profiles: Sequence[list], *, away_left: bool, min_gap: float
) -> np.ndarray:
    """A closed polyline around four corners, each side carrying its feature profiles.

    profiles[i] lists, for side i (corners[i] -> corners[i+1]), features as vertex lists in wall
    coordinates (along the side from its first corner, depth away from the corridor). Features
    must stay min_gap (plus a 0.2 m margin) away from the corners, i.e. out of the crossing
    corridor, and must not overlap each other.
    """
    points = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        length = float(np.linalg.norm(b - a))
        along = (b - a) / length
        left = np.array([-along[1], along[0]])
        away = left if away_left else -left
        points.append(a)
        last_end = min_gap + 0.2
        for feature in sorted(profiles[i], key=lambda p: p[0][0]):
            s = np.array([v[0] for v in feature])
            if s.min() < last_end or s.max() > length - min_gap - 0.2:
                raise ConfigError(
                    f"the features on wall {i} do not fit a {length:.2f} m wall; "
                    "make the block larger"
                )
            last_end = s.max() + 0.2
            points.extend(a + sv * along + dv * away for sv, dv in feature)
    return _close(np.array(points))


# --------------------------------------------------------------------------------------------
# The robot's path
# --------------------------------------------------------------------------------------------


@dataclass
class PlannedPath:
    """A sampled robot path.

    Attributes:
        timestamps: (N,) float64 seconds from the start, at 1 / rate_hz spacing.
        poses: (N, 3) float64 ground-truth world_T_robot poses (x, y, theta), metres and radians.
        length: the distance driven, metres (along the path, not between samples).
    """

    timestamps: np.ndarray
    poses: np.ndarray
    length: float


# Most samples a planned path may have (each a pose; a simulated drive's frames): more only asks
# for memory. 10 000 laps of a 10 m loop at 10 Hz and 0.4 m/s are 2.5 million.
MAX_PATH_SAMPLES = 1e7


def plan_path(
    waypoints: np.ndarray,
    speed: float = 0.4,
    rate_hz: float = 10.0,
    max_turn_rate: float = 0.6,
    turn_radius: float | None = None,
) -> PlannedPath:
    """A smooth path through waypoints, driven at constant speed and sampled at rate_hz.

    The robot starts on the first waypoint facing the second and drives straight legs between
    waypoints; each corner is cut by a circular arc tangent to both legs, so position and heading
    are continuous. On an arc the heading turns at speed / turn_radius; the default radius
    speed / max_turn_rate is the tightest turn the rate limit allows. The path ends at the last
    waypoint (the last sample is the last whole step before it).

    Args:
        waypoints: (K, 2) world-frame points in metres, K >= 2; no leg may reverse direction.
        speed: metres per second along the path.
        rate_hz: samples per second.
        max_turn_rate: the largest allowed |dtheta/dt|, radians per second.
        turn_radius: radius of the corner arcs, metres; at least speed / max_turn_rate.
    """
    pts = np.asarray(waypoints, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
        raise ValueError(f"waypoints must have shape (K >= 2, 2), got {pts.shape}")
    for name, value in (("speed", speed), ("rate_hz", rate_hz), ("max_turn_rate", max_turn_rate)):
        if not (math.isfinite(value) and value > 0.0):
            raise ConfigError(f"{name} must be positive, got {value}")
    radius = speed / max_turn_rate if turn_radius is None else float(turn_radius)
    if radius < speed / max_turn_rate * (1 - 1e-12):
        raise ConfigError(
            f"turn_radius {radius} m needs {speed / radius:.3f} rad/s at {speed} m/s, "
            f"above max_turn_rate {max_turn_rate} rad/s"
        )
    if not np.isfinite(pts).all():
        raise ConfigError(f"waypoints must be finite, got {pts[~np.isfinite(pts).all(axis=1)][0].tolist()}")
    with np.errstate(over="ignore", invalid="ignore"):  # a waypoint at 1e300 m: an infinite length
        pieces = _path_pieces(pts, radius)
        total = float(sum(p.length for p in pieces))
    step = speed / rate_hz
    if not total / step <= MAX_PATH_SAMPLES:  # inf too: a waypoint at 1e300 m
        raise ConfigError(f"the path is {total:.3g} m long: at {speed:g} m/s and {rate_hz:g} Hz that is more than "
                          f"{MAX_PATH_SAMPLES:.0e} samples")
    n = int(math.floor(total / step + 1e-9)) + 1
    s = np.arange(n) * step
    return PlannedPath(timestamps=np.arange(n) / rate_hz, poses=_sample_pieces(pieces, s),
                       length=total)


@dataclass
class _Piece:
    """One straight line or circular arc of a path, starting at (x, y) with heading theta."""

    start: np.ndarray  # (2,) metres
    heading: float  # radians
    length: float  # metres along the path
    turn: float = 0.0  # signed total heading change; 0 for a straight line
    radius: float = math.inf


def _path_pieces(pts: np.ndarray, radius: float) -> list[_Piece]:
    """Straight legs between waypoints, with each interior corner replaced by a tangent arc."""
    legs = np.diff(pts, axis=0)
    leg_len = np.linalg.norm(legs, axis=1)
    if np.any(leg_len <= 0.0):
        raise ConfigError("consecutive waypoints must differ")
    dirs = legs / leg_len[:, None]
    headings = np.arctan2(dirs[:, 1], dirs[:, 0])
    turns = wrap_angle(np.diff(headings)) if len(legs) > 1 else np.zeros(0)
    if np.any(np.abs(turns) > math.radians(170.0)):
        raise ConfigError("a waypoint turns back on the path (> 170 deg); split the turn")
    # Each arc eats radius * tan(|turn| / 2) from the end of the leg before and the start of the
    # leg after it.
    cut = radius * np.tan(np.abs(turns) / 2.0)
    cut_start = np.concatenate([[0.0], cut])
    cut_end = np.concatenate([cut, [0.0]])
    if np.any(cut_start + cut_end > leg_len + 1e-9):
        bad = int(np.flatnonzero(cut_start + cut_end > leg_len + 1e-9)[0])
        raise ConfigError(f"leg {bad} ({leg_len[bad]:.2f} m) is too short for its corner arcs")
    pieces = []
    for i in range(len(legs)):
        straight = leg_len[i] - cut_start[i] - cut_end[i]
        start = pts[i] + cut_start[i] * dirs[i]
        if straight > 0.0:
            pieces.append(_Piece(start, float(headings[i]), float(straight)))
        if i < len(turns) and turns[i] != 0.0:
            arc_start = pts[i + 1] - cut_end[i] * dirs[i]
            pieces.append(_Piece(arc_start, float(headings[i]), float(radius * abs(turns[i])),
                                 turn=float(turns[i]), radius=radius))
    return pieces


def _sample_pieces(pieces: list[_Piece], s: np.ndarray) -> np.ndarray:
    """Poses (len(s), 3) at arc lengths s along the concatenated pieces. Vectorised over the
    samples with each piece's figures looked up per sample (a loop over the pieces that selected
    each one's samples cost pieces × samples: a world of 10 000 laps took minutes)."""
    starts = np.cumsum([0.0] + [p.length for p in pieces[:-1]])
    which = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(pieces) - 1)
    # Per piece, with math's sin and cos as before (numpy's may differ in the last bit).
    sx = np.array([p.start[0] for p in pieces])[which]
    sy = np.array([p.start[1] for p in pieces])[which]
    h0 = np.array([p.heading for p in pieces])[which]
    cos0 = np.array([math.cos(p.heading) for p in pieces])[which]
    sin0 = np.array([math.sin(p.heading) for p in pieces])[which]
    sign = np.array([math.copysign(1.0, p.turn) for p in pieces])[which]
    radius = np.array([p.radius if p.turn != 0.0 else 1.0 for p in pieces])[which]
    straight = np.array([p.turn == 0.0 for p in pieces])[which]
    local = s - starts[which]
    poses = np.empty((len(s), 3))
    poses[:, 0] = sx + local * cos0
    poses[:, 1] = sy + local * sin0
    poses[:, 2] = h0
    arc = ~straight
    # Centre of the turn: one radius to the left (left turn) or right of the start.
    sg, r = sign[arc], radius[arc]
    cx = sx[arc] - sg * r * sin0[arc]
    cy = sy[arc] + sg * r * cos0[arc]
    h = h0[arc] + sg * local[arc] / r
    poses[arc, 0] = cx + sg * r * np.sin(h)
    poses[arc, 1] = cy - sg * r * np.cos(h)
    poses[arc, 2] = h
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses


def loop_waypoints(
    block_width: float = 16.0,
    block_height: float = 10.0,
    corridor_width: float = 2.0,
    overlap: float = 5.0,
) -> np.ndarray:
    """Waypoints (K, 2) once round the corridor centreline of `corridor_loop_world`, metres.

    The loop starts in the middle of the bottom corridor heading +x, goes counter-clockwise round
    the block, and drives `overlap` metres past the start so that the end overlaps the beginning.
    """
    bw, bh, h = block_width, block_height, corridor_width / 2
    start = np.array([bw / 2, -h])
    if not (0.0 <= overlap < bw / 2):
        raise ConfigError(f"overlap must be in [0, {bw / 2}) m, got {overlap}")
    return np.array([
        start,
        [bw + h, -h],
        [bw + h, bh + h],
        [-h, bh + h],
        [-h, -h],
        start + [overlap, 0.0],
    ])


def loop_path(
    block_width: float = 16.0,
    block_height: float = 10.0,
    corridor_width: float = 2.0,
    *,
    overlap: float = 5.0,
    speed: float = 0.4,
    rate_hz: float = 10.0,
    max_turn_rate: float = 0.6,
) -> PlannedPath:
    """The robot's path once round `corridor_loop_world` (same sizes) plus `overlap` metres."""
    return plan_path(loop_waypoints(block_width, block_height, corridor_width, overlap),
                     speed=speed, rate_hz=rate_hz, max_turn_rate=max_turn_rate)


# --------------------------------------------------------------------------------------------
# Odometry
# --------------------------------------------------------------------------------------------

# Default odometry errors. The systematic part is what makes a loop fail to close: a 1 % wheel
# radius error (worn or under-inflated wheels), a 1.5 % effective wheel-base error (the classic
# UMBmark finding that odometry over- or under-turns in every corner) and a 0.05 deg/m heading
# drift (slightly unequal wheels). The random part (the odometry motion model's variances, for
# ~4 cm steps) is kept below the systematic one, so that every seed ends the loop visibly off
# (about 1.2 m and 8.5 deg on average over seeds with the default loop).
DEFAULT_ALPHAS = (0.002, 0.0001, 0.005, 0.0005)
DEFAULT_WHEEL_RADIUS_ERROR = 0.01
DEFAULT_WHEEL_BASE_ERROR = 0.015
DEFAULT_HEADING_DRIFT = math.radians(0.05)  # radians per metre driven
PERSON_RADIUS = 0.25  # a person seen by a laser at hip height, metres


def odometry_increments(poses: np.ndarray) -> np.ndarray:
    """(N-1, 3) increments (rot1, trans, rot2) between consecutive poses.

    The odometry motion model's decomposition (Probabilistic Robotics, sec. 5.4): turn by rot1
    towards the next position, drive trans metres, turn by rot2 to the next heading. A step with
    no translation is a pure turn (rot1 = 0).
    """
    step = relative(poses[:-1], poses[1:])  # (N-1, 3) in the frame of the earlier pose
    trans = np.hypot(step[:, 0], step[:, 1])
    rot1 = np.where(trans > 1e-12, np.arctan2(step[:, 1], step[:, 0]), 0.0)
    rot2 = wrap_angle(step[:, 2] - rot1)
    return np.stack([rot1, trans, rot2], axis=1)


def integrate_increments(start: np.ndarray, increments: np.ndarray) -> np.ndarray:
    """Poses (N, 3) from a start pose and (N-1, 3) increments (rot1, trans, rot2).

    Chaining start ⊕ (trans cos rot1, trans sin rot1, rot1 + rot2) ⊕ ... written as running sums:
    the heading before step k is theta_0 + sum of earlier turns, and each step moves trans along
    that heading plus rot1.
    """
    start = np.asarray(start, dtype=np.float64)
    rot1, trans, rot2 = increments.T
    heading = start[2] + np.concatenate([[0.0], np.cumsum(rot1 + rot2)])
    move = heading[:-1] + rot1
    x = start[0] + np.concatenate([[0.0], np.cumsum(trans * np.cos(move))])
    y = start[1] + np.concatenate([[0.0], np.cumsum(trans * np.sin(move))])
    return np.stack([x, y, wrap_angle(heading)], axis=1)


def simulate_odometry(
    ground_truth: np.ndarray,
    *,
    seed: Seed,
    alphas: tuple[float, float, float, float] = DEFAULT_ALPHAS,
    wheel_radius_error: float = DEFAULT_WHEEL_RADIUS_ERROR,
    wheel_base_error: float = DEFAULT_WHEEL_BASE_ERROR,
    heading_drift: float = DEFAULT_HEADING_DRIFT,
) -> np.ndarray:
    """Wheel odometry poses (N, 3) for a ground-truth path (N, 3), starting at the true start.

    Each true step is split into (rot1, trans, rot2) and corrupted twice:

    * systematically: trans × (1 + wheel_radius_error) (the wheels are larger than the odometry
      believes); rot1, rot2 × (1 + wheel_base_error) (a wheel base off by that fraction turns
      every measured rotation by that fraction, so the bias grows with the angle turned); and
      rot2 + heading_drift × trans (radians per metre, e.g. slightly unequal wheels);
    * randomly, by Probabilistic Robotics' sample_motion_model_odometry (Table 5.6): zero-mean
      Gaussians with variances alpha1 rot1² + alpha2 trans² on rot1, alpha3 trans² +
      alpha4 (rot1² + rot2²) on trans, alpha1 rot2² + alpha2 trans² on rot2. Because the variance
      goes with the square of each step, the accumulated random error depends on the step size
      (the sampling rate) as well as the distance; the defaults are for ~4 cm steps.

    The corrupted steps are integrated from ground_truth[0] in the odometry frame, which here
    coincides with the world frame at the start.

    Args:
        ground_truth: (N, 3) world_T_robot poses, metres and radians.
        seed: the random stream.
        alphas: (alpha1..alpha4), dimensionless variance coefficients.
        wheel_radius_error, wheel_base_error: fractions (0.01 = 1 %).
        heading_drift: radians per metre driven.
    """
    gt = np.asarray(ground_truth, dtype=np.float64)
    if gt.ndim != 2 or gt.shape[1] != 3 or len(gt) < 1:
        raise ValueError(f"ground_truth must have shape (N >= 1, 3), got {gt.shape}")
    if len(alphas) != 4 or any(not (math.isfinite(a) and a >= 0.0) for a in alphas):
        raise ConfigError(f"alphas must be four non-negative variances, got {alphas}")
    a1, a2, a3, a4 = (float(a) for a in alphas)
    rot1, trans, rot2 = odometry_increments(gt).T

    rot1_sys = rot1 * (1.0 + wheel_base_error)
    trans_sys = trans * (1.0 + wheel_radius_error)
    rot2_sys = rot2 * (1.0 + wheel_base_error) + heading_drift * trans

    rng = np.random.default_rng(seed)
    std = np.sqrt(np.stack([
        a1 * rot1**2 + a2 * trans**2,
        a3 * trans**2 + a4 * (rot1**2 + rot2**2),
        a1 * rot2**2 + a2 * trans**2,
    ], axis=1))
    noise = rng.standard_normal(std.shape) * std
    noisy = np.stack([rot1_sys, trans_sys, rot2_sys], axis=1) - noise
    return integrate_increments(gt[0], noisy)


# --------------------------------------------------------------------------------------------
# The laser
# --------------------------------------------------------------------------------------------


def beam_angles(n_beams: int = 181, fov_deg: float = 180.0) -> np.ndarray:
    """Beam bearings (n_beams,) in the sensor frame, radians, centred on the sensor's +x.

    A field of view below 360 deg includes both edges (181 beams over 180 deg is 1 deg apart);
    a full circle does not repeat its edge (360 beams are -180, -179, ..., 179 deg).
    """
    if n_beams < 1:
        raise ConfigError(f"n_beams must be at least 1, got {n_beams}")
    if not (0.0 < fov_deg <= 360.0):
        raise ConfigError(f"fov_deg must be in (0, 360], got {fov_deg}")
    half = math.radians(fov_deg) / 2
    if fov_deg >= 360.0:
        return -math.pi + 2 * math.pi * np.arange(n_beams) / n_beams
    if n_beams == 1:
        return np.zeros(1)
    return np.linspace(-half, half, n_beams)


def simulate_scans(
    world: World2D,
    poses: np.ndarray,
    angles: np.ndarray,
    *,
    sensor_pose: Sequence[float] = (0.0, 0.0, 0.0),
    max_range: float = 8.0,
    range_noise: float = 0.01,
    dropout: float = 0.0,
    people: np.ndarray | None = None,
    person_radius: float = PERSON_RADIUS,
    seed: Seed,
) -> np.ndarray:
    """Laser ranges (N, B) float32 in metres from robot poses (N, 3).

    Each beam leaves world_T_robot ⊕ robot_T_sensor at the sensor-frame bearing angles[b] (or
    angles[i, b]: (N, B) angles give each scan its own beams, as an interlaced laser has). The
    true distance gets zero-mean Gaussian noise of std range_noise (metres); a noisy reading at or
    beyond max_range, a beam that hits nothing, and (with probability dropout, independently per
    beam) a lost echo all read +inf. `people` (N, K, 2), world-frame centres of K people at each
    scan (NaN where one is absent), stand in the way as discs of `person_radius` metres: what
    moves in the scene and is no wall (see `walkers_beside`).
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"poses must have shape (N, 3), got {poses.shape}")
    angles = np.asarray(angles, dtype=np.float64)
    if not (angles.ndim == 1 or (angles.ndim == 2 and len(angles) == len(poses))):
        raise ValueError(f"angles must have shape (B,) or ({len(poses)}, B), got {angles.shape}")
    if not (max_range > 0.0 and range_noise >= 0.0 and 0.0 <= dropout <= 1.0):
        raise ConfigError("need max_range > 0, range_noise >= 0 and 0 <= dropout <= 1")
    world_T_sensor = compose(poses, np.asarray(sensor_pose, dtype=np.float64))
    bearings = world_T_sensor[:, 2:3] + angles
    # Cast a little beyond max_range so that noise can carry a wall just outside it inside.
    reach = max_range + 6.0 * range_noise
    true = world.raycast(world_T_sensor[:, :2], bearings, max_range=reach)
    if people is not None:
        people = np.asarray(people, dtype=np.float64)
        if people.ndim != 3 or people.shape[0] != len(poses) or people.shape[2] != 2:
            raise ValueError(f"people must have shape ({len(poses)}, K, 2), got {people.shape}")
        if not (math.isfinite(person_radius) and person_radius > 0.0):
            raise ConfigError(f"person_radius must be a positive number of metres, got {person_radius}")
        rows = max(1, _PAIR_BUDGET // max(1, bearings.shape[1] * people.shape[1]))
        for start in range(0, len(poses), rows):  # bounded (rays × people) arrays, as raycast's
            chunk = slice(start, start + rows)
            discs = _cast_to_discs(world_T_sensor[chunk, :2], bearings[chunk], people[chunk], person_radius)
            true[chunk] = np.minimum(true[chunk], discs)
        true[true > reach] = np.inf
    rng = np.random.default_rng(seed)
    ranges = true + range_noise * rng.standard_normal(true.shape)
    ranges[ranges >= max_range] = np.inf
    if dropout > 0.0:
        ranges[rng.random(true.shape) < dropout] = np.inf
    return ranges.astype(np.float32)


def _cast_to_discs(origins: np.ndarray, bearings: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """Nearest hit (N, B) of rays from origins (N, 2) at world bearings (N, B) with discs of
    `radius` around centres (N, K, 2) (NaN: no disc). The ray p + t·d meets the circle where
    |w − t·d| = r with w = c − p: t = w·d − √((w·d)² − |w|² + r²), the nearer root. A ray that
    starts inside a disc sees nothing of it (the laser would stand in a person)."""
    w = centres[:, None, :, :] - origins[:, None, None, :]  # (N, 1, K, 2)
    dx, dy = np.cos(bearings)[..., None], np.sin(bearings)[..., None]  # (N, B, 1)
    along = w[..., 0] * dx + w[..., 1] * dy  # (N, B, K)
    outside = (w[..., 0] ** 2 + w[..., 1] ** 2) - radius * radius  # (N, 1, K)
    with np.errstate(invalid="ignore"):
        t = along - np.sqrt(along * along - outside)
    hit = (outside > 0.0) & (t > 0.0)  # NaN (no disc, or a miss) fails both
    return np.min(t, axis=-1, initial=np.inf, where=hit)


def walkers_beside(poses: np.ndarray, timestamps: np.ndarray, walkers: Sequence["Walker"]) -> np.ndarray:
    """Centres (N, K, 2) of K people who walk with the robot along its true path `poses` (N, 3)
    at `timestamps` (N,), each as a `Walker` says; NaN outside each one's time window. People
    beside a robot, keeping its pace, are what the Freiburg hospital log holds and what a scan
    matcher may lay on the mapped walls."""
    poses = np.asarray(poses, dtype=np.float64)
    t = np.asarray(timestamps, dtype=np.float64)
    out = np.full((len(poses), len(walkers), 2), np.nan)
    for k, walker in enumerate(walkers):
        inside = (t >= walker.start) & (t <= walker.stop)
        offset = np.array([walker.ahead, walker.left, 0.0])
        out[inside, k] = compose(poses[inside], offset)[:, :2]
    return out


@dataclass(frozen=True)
class Walker:
    """A person who walks with the robot from time `start` to `stop` (seconds), `ahead` metres
    in front of it and `left` metres to its left (the robot frame; negative: behind, right)."""

    ahead: float
    left: float
    start: float
    stop: float

    def __post_init__(self) -> None:
        for name in ("ahead", "left", "start", "stop"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"Walker.{name} must be a finite number, got {getattr(self, name)!r}")
        if self.stop < self.start:
            raise ConfigError(f"Walker.stop ({self.stop} s) comes before Walker.start ({self.start} s)")


# --------------------------------------------------------------------------------------------
# The dataset
# --------------------------------------------------------------------------------------------


def make_loop_dataset(
    *,
    seed: int = 0,
    n_beams: int = 181,
    fov_deg: float = 180.0,
    max_range: float = 8.0,
    range_noise: float = 0.01,
    dropout: float = 0.0,
    sensor_pose: Sequence[float] = (0.0, 0.0, 0.0),
    speed: float = 0.4,
    rate_hz: float = 10.0,
    overlap: float = 5.0,
    alphas: tuple[float, float, float, float] = DEFAULT_ALPHAS,
    wheel_radius_error: float = DEFAULT_WHEEL_RADIUS_ERROR,
    wheel_base_error: float = DEFAULT_WHEEL_BASE_ERROR,
    heading_drift: float = DEFAULT_HEADING_DRIFT,
    walkers: Sequence[Walker] = (),
    block_width: float = _DEFAULT_BLOCK[0],
    block_height: float = _DEFAULT_BLOCK[1],
    corridor_width: float = _DEFAULT_CORRIDOR,
) -> ScanSequence:
    """The corridor loop driven once plus `overlap` metres, with laser scans and drifting odometry.
    `walkers`: people who walk with the robot for a while (`Walker`), seen by the laser and
    absent from the world's walls (the ground truth of a map).

    World: `corridor_loop_world(block_width, block_height, corridor_width)` (by default a 16 m x
    10 m block with 2 m corridors). Path: `loop_path` of the same sizes.
    Odometry: `simulate_odometry`; scans: `simulate_scans`. One seed drives both through two
    independent child streams (SeedSequence.spawn), so changing the odometry settings leaves the
    scans bit-for-bit unchanged and vice versa. max_range defaults to 8 m, about the unambiguous
    range of the 20 MHz ToF cameras the project models (c / 2f = 7.5 m).
    """
    world = corridor_loop_world(block_width, block_height, corridor_width)
    path = loop_path(block_width, block_height, corridor_width, overlap=overlap, speed=speed, rate_hz=rate_hz)
    odo_seed, scan_seed = np.random.SeedSequence(seed).spawn(2)
    odometry = simulate_odometry(path.poses, seed=odo_seed, alphas=alphas,
                                 wheel_radius_error=wheel_radius_error,
                                 wheel_base_error=wheel_base_error, heading_drift=heading_drift)
    angles = beam_angles(n_beams, fov_deg)
    people = walkers_beside(path.poses, path.timestamps, walkers) if walkers else None
    ranges = simulate_scans(world, path.poses, angles, sensor_pose=sensor_pose,
                            max_range=max_range, range_noise=range_noise, dropout=dropout,
                            people=people, seed=scan_seed)
    return ScanSequence(
        timestamps=path.timestamps,
        ranges=ranges,
        angles=angles,
        odometry=odometry,
        sensor_pose=np.asarray(sensor_pose, dtype=np.float64),
        max_range=max_range,
        ground_truth=path.poses,
        source="corridor-loop (simulated)",
        max_range_rule="the simulated laser's max_range",
    )
