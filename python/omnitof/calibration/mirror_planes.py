"""Mirror planes from a four-dot target seen directly and through the mirror (paper sec. II-C,
after Hu, Brown and Nelson 2005).

A point X in front of a mirror {n·x = d} and its mirror image X' = X + 2(d − n·X)n differ by a
multiple of n, so the image line through the direct view x of X and the mirrored view x' (where
the real camera sees X' directly) passes through the vanishing point of n: the epipole e of the
virtual camera, whose centre 2dn lies along n. With undistorted, normalised image coordinates
(K⁻¹ applied), e is n itself, i.e. n = M⁻¹e (eq. 5, M = K the left 3×3 of P = K[I|0]).

Steps, per mirror (`estimate_mirror`):
1. dots: dark blobs inside bright card regions, sub-pixel centroids weighted by darkness
   (`detect_views`); the two views are the two cards with the most dots, the nearer by ToF
   distance (or, without distances, the larger in the image) being the direct one;
2. pairs: an assignment of direct to mirrored dots whose lines meet in one point; of several
   (a square of dots is symmetric; two lines always meet), the one nearest the prior normal;
3. the epipole: RANSAC over all lines of all placements (two lines give a candidate), then
   least squares over the inliers of a geometric residual: the distance in pixels of each dot
   from the line through e and the pair's midpoint. Lines off the epipole are dropped, and an
   image most of whose lines are off is rejected whole; both are reported;
4. n = e/|e| (eq. 5), its sign chosen so that the triangulated dots lie in front of the camera;
5. scale: with the baseline set to one (d = 1/2), triangulate each pair (the direct ray and the
   mirrored ray reflected in the plane); the metric d follows from the known dot spacing (the
   RMS distance of a placement's four dots from their centroid is spacing/√2, whatever their
   order) or from the ToF distances of the dots (|X| for the direct view, |X'| for the mirrored
   one: their mean point lies on the plane, paper sec. II-C).
The result gives D and Pv = P·D of eq. 6 (`omnitof.sensor.mirrors.MirrorPlane`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.ndimage import grey_dilation
from scipy.optimize import least_squares

from omnitof.calibration import CalibrationError
from omnitof.calibration.images import AmplitudeImage
from omnitof.calibration.targets import DotTarget
from omnitof.sensor.camera import Camera
from omnitof.sensor.mirrors import MirrorPlane

# A pixel belongs to a card if its amplitude exceeds this fraction of the image's 99.5th
# percentile (the cards are the nearest, brightest surfaces; the room is ≥ 10× dimmer).
CARD_THRESHOLD = 0.08
# A card pixel is a dot pixel if darker than this fraction of the local white level.
DOT_THRESHOLD = 0.5
# Dots smaller than this many pixels are noise; cards smaller than this are not cards.
MIN_DOT_PIXELS = 3
MIN_CARD_PIXELS = 40
# RANSAC: a pair is an inlier if its dots lie within this many pixels of the line through e;
# after the first fit the threshold tightens to 5 robust σ of the inliers, but not below
# MIN_INLIER_PX (simulated placements scatter by ~0.02 px RMS).
INLIER_PX = 1.0
MIN_INLIER_PX = 0.1
# An image whose pairs are mostly outliers is rejected whole.
MAX_OUTLIER_SHARE = 0.5
MAX_DOTS_PER_VIEW = 6
# A placement whose scale (dot spacing) differs from the median by more than this is left out.
SCALE_TOLERANCE = 0.02


@dataclass
class View:
    """One card seen in an image: its dots' sub-pixel centroids (K, 2) (u, v), the dots' pixel
    areas, the card's pixel count, the card's median ToF distance (NaN if unknown) and the
    ToF distance at each dot (ring of card pixels around it; NaN if unknown)."""

    dots: np.ndarray
    areas: np.ndarray
    card_pixels: int
    distance: float
    dot_distances: np.ndarray


@dataclass
class Pairs:
    """The dot pairs of one image: direct (K, 2) and mirrored (K, 2) pixels, and notes."""

    image: str
    direct: np.ndarray
    mirrored: np.ndarray
    direct_distance: np.ndarray
    mirrored_distance: np.ndarray
    notes: list[str] = field(default_factory=list)


def detect_views(image: AmplitudeImage) -> list[View]:
    """Cards with dark dots in an amplitude image, the ones with most dots first."""
    a = np.nan_to_num(np.asarray(image.amplitude, dtype=np.float64), nan=0.0)
    top = float(np.percentile(a, 99.5))
    if top <= 0.0:
        return []
    bright = (a > CARD_THRESHOLD * top).astype(np.uint8)
    # Close the dots' holes so that each card is one filled region.
    filled = np.zeros_like(bright)
    contours, _ = cv2.findContours(bright, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    for c in contours:
        if cv2.contourArea(c) >= MIN_CARD_PIXELS:
            cv2.drawContours(filled, [c], -1, 1, thickness=cv2.FILLED)
    n_cards, card_labels = cv2.connectedComponents(filled, connectivity=4)
    # The local white level: the brightest pixel within 3 px (dots are at most ~6 px wide).
    white = grey_dilation(a, size=(7, 7))
    dark = (a < DOT_THRESHOLD * white) & (filled > 0)
    interior = cv2.erode(filled, np.ones((3, 3), np.uint8)) > 0
    core = np.where(interior, card_labels, 0)
    grid_rows, grid_cols = np.mgrid[0 : a.shape[0], 0 : a.shape[1]]
    n_dots, dot_labels, stats, _ = cv2.connectedComponentsWithStats(
        (dark & interior).astype(np.uint8), connectivity=8
    )
    views: dict[int, list[tuple[float, float, int, float]]] = {}
    for k in range(1, n_dots):
        area = int(stats[k, cv2.CC_STAT_AREA])
        if area < MIN_DOT_PIXELS:
            continue
        blob = dot_labels == k
        # The blob must be enclosed by card: no pixel of it on the card's border.
        grown = cv2.dilate(blob.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        if np.any(grown & (filled == 0)):
            continue
        if blob[0].any() or blob[-1].any() or blob[:, 0].any() or blob[:, -1].any():
            continue  # cut by the image border (a card partly outside the image)
        card = int(np.bincount(card_labels[blob]).argmax())
        # Darkness-weighted centroid over a disc 1.5 px wider than the blob (the pixels that the
        # dot covers partly): a pixel integrates coverage linearly, so with the white level w(u, v)
        # known, (w − a) is proportional to the dark area in each pixel. w is a plane fitted
        # to the white ring 2.5 px wide around it (the card's brightness changes across it with
        # 1/r² and the incidence angle, which would pull a flat level's centroid off).
        b_rows, b_cols = np.nonzero(blob)
        radius = math.sqrt(area / math.pi) + 1.5
        gap = np.hypot(grid_cols - b_cols.mean(), grid_rows - b_rows.mean())
        on_card = core == card  # the card without its outermost pixel (mixed with background)
        window = (gap <= radius) & on_card
        ring = (gap > radius) & (gap <= radius + 2.5) & on_card & ~dark
        if ring.sum() < 6 or np.any((gap <= radius) & ~on_card):
            continue  # a dot at the card's edge: its rim is cut, its centroid would be biased
        r_rows, r_cols = np.nonzero(ring)
        design = np.stack([np.ones(len(r_rows)), r_cols, r_rows], axis=1)
        coef, *_ = np.linalg.lstsq(design, a[r_rows, r_cols], rcond=None)
        rows, cols = np.nonzero(window)
        level = coef[0] + coef[1] * cols + coef[2] * rows
        weight = np.clip(level - a[rows, cols], 0.0, None)
        total = float(weight.sum())
        if total <= 0.0:
            continue
        u = float((weight * cols).sum() / total)
        v = float((weight * rows).sum() / total)
        dist = math.nan
        if image.distance is not None:
            values = image.distance[ring]
            values = values[np.isfinite(values)]
            dist = float(np.median(values)) if len(values) else math.nan
        views.setdefault(card, []).append((u, v, area, dist))
    out = []
    for card, dots in views.items():
        mask = card_labels == card
        distance = math.nan
        if image.distance is not None:
            values = image.distance[mask & ~dark]
            values = values[np.isfinite(values)]
            distance = float(np.median(values)) if len(values) else math.nan
        arr = np.array(dots, dtype=np.float64)
        out.append(View(arr[:, :2], arr[:, 2], int(mask.sum()), distance, arr[:, 3]))
    out.sort(key=lambda view: (-len(view.dots), -view.card_pixels))
    return out


def _spread(points: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def split_views(image: AmplitudeImage, views: list[View], mirror_name: str) -> tuple[View, View, list[str]]:
    """(direct, mirrored, notes) from the detected views of one image."""
    notes = []
    usable = [v for v in views if len(v.dots) >= 1]
    if len(usable) < 2:
        found = sum(len(v.dots) for v in usable)
        raise CalibrationError(
            f"mirror {mirror_name!r}: expected the dot target seen twice (directly and in the "
            f"mirror), found {len(usable)} card(s) with {found} dot(s)",
            image.name,
        )
    if len(usable) > 2:
        notes.append(f"{len(usable) - 2} other dotted region(s) ignored")
    first, second = usable[0], usable[1]
    if math.isfinite(first.distance) and math.isfinite(second.distance):
        direct, mirrored = (first, second) if first.distance < second.distance else (second, first)
    else:  # the mirrored view is farther away, hence smaller
        size = [_spread(v.dots) if len(v.dots) > 1 else math.sqrt(v.card_pixels) for v in (first, second)]
        direct, mirrored = (first, second) if size[0] >= size[1] else (second, first)
    for label, view in (("direct", direct), ("mirrored", mirrored)):
        if len(view.dots) != 4:
            notes.append(f"{label} view has {len(view.dots)} dots, expected 4")
        if len(view.dots) > MAX_DOTS_PER_VIEW:
            raise CalibrationError(
                f"mirror {mirror_name!r}: {label} view has {len(view.dots)} dark blobs, at most "
                f"{MAX_DOTS_PER_VIEW} can be paired",
                image.name,
            )
    return direct, mirrored, notes


def normalised(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """Homogeneous normalised coordinates (N, 3) (K⁻¹, distortion removed) of pixels (N, 2)."""
    rays = camera.rays(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
    return rays / rays[:, 2:3]


def _concurrency(x: np.ndarray, xp: np.ndarray) -> tuple[float, np.ndarray]:
    """How well the lines x_i x'_i meet in one point: the smallest singular value of the stacked
    unit line vectors, and that point (unit 3-vector)."""
    lines = np.cross(x, xp)
    lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    _, s, vt = np.linalg.svd(lines)
    return float(s[-1]) if len(lines) >= 3 else 0.0, vt[-1]


def pair_dots(
    camera: Camera, direct: View, mirrored: View, prior_normal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (direct, mirrored) of the dot assignment whose lines meet in one point (eq. 5's
    epipole), with the dots within INLIER_PX of the lines through it; of several such, the one
    whose point is nearest the prior normal.

    Why the prior: a square of dots is symmetric, and the assignment turned by 180° has lines
    that all pass through the point between the two views, exactly. That point is far from the
    epipole (the normal would be off by tens of degrees), so a rough prior, e.g. the rig's
    design, tells them apart; so it does for two pairs, whose two lines always meet.
    """
    x = normalised(camera, direct.dots)
    xp = normalised(camera, mirrored.dots)
    focal = 0.5 * (camera.fx + camera.fy)
    k = min(len(x), len(xp))
    candidates = []
    for di in itertools.combinations(range(len(x)), k):
        for mi in itertools.permutations(range(len(xp)), k):
            _, point = _concurrency(x[list(di)], xp[list(mi)])
            residual = float(np.sqrt(np.mean(_residuals_px(point, x[list(di)], xp[list(mi)], focal) ** 2)))
            angle = math.acos(min(1.0, abs(float(point @ prior_normal))))
            candidates.append((residual, angle, di, mi))
    agreeing = [c for c in candidates if c[0] < INLIER_PX]
    if not agreeing:
        _, _, di, mi = min(candidates, key=lambda c: c[0])
        return np.array(di), np.array(mi)
    nearest = min(c[1] for c in agreeing)
    agreeing = [c for c in agreeing if c[1] <= nearest + math.radians(5.0)]
    if k == 4 and len(agreeing) > 1:
        # Two dots on one epipolar line can be swapped without leaving it: take the
        # assignment whose triangulated dots (baseline one) are most like the printed square.
        _, _, di, mi = min(agreeing, key=lambda c: _shape_error(x[list(c[2])], xp[list(c[3])], prior_normal))
    else:
        _, _, di, mi = min(agreeing, key=lambda c: c[1])
    return np.array(di), np.array(mi)


def _shape_error(x: np.ndarray, xp: np.ndarray, prior_normal: np.ndarray) -> float:
    """How unlike a square four paired dots triangulate: their six distances, sorted and
    divided by the mean, against a square's (four sides, two diagonals √2 longer)."""
    _, point = _concurrency(x, xp)
    normal = point if point @ prior_normal > 0 else -point
    points, lam, _ = _triangulate(normal, 0.5, x, xp)
    if np.any(lam <= 0):
        return math.inf
    gaps = np.sort([np.linalg.norm(points[i] - points[j]) for i, j in itertools.combinations(range(4), 2)])
    square = np.array([1, 1, 1, 1, math.sqrt(2), math.sqrt(2)])
    return float(np.sum((gaps / gaps.mean() - square / square.mean()) ** 2))


def _residuals_px(normal: np.ndarray, x: np.ndarray, xp: np.ndarray, focal: float) -> np.ndarray:
    """Per pair, the distance (pixels) of x from the line through the pair's midpoint and the
    epipole `normal` (normalised coordinates; the same for x' by symmetry)."""
    mid = 0.5 * (x + xp)
    lines = np.cross(mid, np.broadcast_to(normal, mid.shape))
    length = np.linalg.norm(lines[:, :2], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return focal * np.abs(np.sum(lines * x, axis=1)) / length


def _sphere_update(n0: np.ndarray, params: np.ndarray) -> np.ndarray:
    """n0 turned by the small rotation vector (a, b) in the tangent plane of n0."""
    helper = np.eye(3)[int(np.argmin(np.abs(n0)))]
    t1 = np.cross(n0, helper)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n0, t1)
    n = n0 + params[0] * t1 + params[1] * t2
    return n / np.linalg.norm(n)


@dataclass
class MirrorEstimate:
    """A calibrated mirror: its plane and how it was found.

    plane: the MirrorPlane (camera frame). inliers / lines: pairs kept / given to RANSAC.
    rms_px: RMS residual of the inliers (pixels; see `_residuals_px`). scale: method ("dots",
    "tof"); scale_spread: relative standard deviation of the per-placement scales.
    images: names of the images used; rejected: messages about dropped lines and images.
    """

    name: str
    plane: MirrorPlane
    inliers: int
    lines: int
    rms_px: float
    scale: str
    scale_spread: float
    images: list[str]
    rejected: list[str]
    notes: list[str]

    def quality(self) -> dict:
        return {
            "inliers": self.inliers,
            "lines": self.lines,
            "epipole_rms_px": round(self.rms_px, 4),
            "scale": self.scale,
            "scale_spread": round(self.scale_spread, 5),
            "placements": len(self.images),
            "rejected": list(self.rejected),
        }


def estimate_mirror(
    camera: Camera,
    name: str,
    pairs: Sequence[Pairs],
    prior_normal: np.ndarray,
    *,
    target: DotTarget = DotTarget(),
    scale: str = "dots",
    seed: int = 0,
) -> MirrorEstimate:
    """The plane of one mirror from the dot pairs of its placements (see the module docstring).

    Raises:
        CalibrationError naming the mirror (and image): fewer than two pairs in all, no
            consensus on the epipole, a scale that cannot be fixed.
    """
    if scale not in ("dots", "tof"):
        raise CalibrationError(f"scale must be 'dots' or 'tof', got {scale!r}")
    if not pairs:
        raise CalibrationError(f"mirror {name!r}: no image shows the dot target in this mirror")
    focal = 0.5 * (camera.fx + camera.fy)
    x = np.vstack([normalised(camera, p.direct) for p in pairs])
    xp = np.vstack([normalised(camera, p.mirrored) for p in pairs])
    owner = np.concatenate([np.full(len(p.direct), i) for i, p in enumerate(pairs)])
    if len(x) < 2:
        raise CalibrationError(
            f"mirror {name!r}: {len(x)} dot pair(s) in all; need at least two correspondences",
            pairs[0].image,
        )
    lines = np.cross(x, xp)
    lines /= np.linalg.norm(lines, axis=1, keepdims=True)
    # RANSAC: every pair of lines (all of them if few, else a seeded sample) proposes e.
    combos = list(itertools.combinations(range(len(x)), 2))
    if len(combos) > 2000:
        rng = np.random.default_rng(seed)
        combos = [combos[i] for i in rng.choice(len(combos), 2000, replace=False)]
    best_count, best_cost, best_n = -1, math.inf, None
    for i, j in combos:
        e = np.cross(lines[i], lines[j])
        norm = np.linalg.norm(e)
        if norm < 1e-12:
            continue
        e = e / norm
        r = _residuals_px(e, x, xp, focal)
        inside = r < INLIER_PX
        count = int(inside.sum())
        cost = float(np.sum(np.minimum(r, INLIER_PX) ** 2))
        if count > best_count or (count == best_count and cost < best_cost):
            best_count, best_cost, best_n = count, cost, e
    if best_n is None or best_count < 2:
        raise CalibrationError(
            f"mirror {name!r}: the dot pairs' lines do not meet in one epipole (no two agree "
            f"within {INLIER_PX} px); check the dot detection in "
            + ", ".join(p.image for p in pairs)
        )
    # Least squares over the inliers, on the unit sphere around the RANSAC normal (eq. 5);
    # then the inliers again, with a threshold from the inliers' own scatter (5 robust σ, at
    # least MIN_INLIER_PX), and a final fit.
    n0 = best_n
    threshold = INLIER_PX
    inlier = _residuals_px(n0, x, xp, focal) < threshold
    for _ in range(2):
        fit = least_squares(
            lambda q: _residuals_px(_sphere_update(n0, q), x[inlier], xp[inlier], focal), np.zeros(2)
        )
        n0 = _sphere_update(n0, fit.x)
        residuals = _residuals_px(n0, x, xp, focal)
        sigma = 1.4826 * float(np.median(residuals[inlier]))
        threshold = min(INLIER_PX, max(MIN_INLIER_PX, 5.0 * sigma))
        inlier = residuals < threshold
    rejected, used_images = [], []
    for i, p in enumerate(pairs):
        mine = owner == i
        bad = int((mine & ~inlier).sum())
        if bad and bad > MAX_OUTLIER_SHARE * mine.sum():
            inlier[mine] = False
            rejected.append(
                f"{p.image}: rejected, {bad} of {int(mine.sum())} dot pairs miss the epipole by "
                f"more than {threshold:.2f} px"
            )
        elif bad:
            rejected.append(
                f"{p.image}: {bad} of {int(mine.sum())} dot pairs dropped (off the epipole by "
                f"more than {threshold:.2f} px)"
            )
        if inlier[mine].any():
            used_images.append(p.image)
    if inlier.sum() < 2:
        raise CalibrationError(f"mirror {name!r}: fewer than two dot pairs agree on the epipole")
    fit = least_squares(
        lambda q: _residuals_px(_sphere_update(n0, q), x[inlier], xp[inlier], focal), np.zeros(2)
    )
    normal = _sphere_update(n0, fit.x)
    residuals = _residuals_px(normal, x[inlier], xp[inlier], focal)
    rms = float(np.sqrt(np.mean(residuals**2)))
    # Triangulate with the baseline set to one (d = 1/2): λ r + 2(d − λ n·r) n = μ r'.
    unit_points, lam, mu = _triangulate(normal, 0.5, x[inlier], xp[inlier])
    if np.median(lam) < 0.0:  # the other sign of n puts the scene in front of the camera
        normal = -normal
        unit_points, lam, mu = _triangulate(normal, 0.5, x[inlier], xp[inlier])
    if np.any(lam <= 0.0) or np.any(mu <= 0.0):
        raise CalibrationError(f"mirror {name!r}: dots triangulate behind the camera")
    factors = []
    kept_owner = owner[inlier]
    if scale == "dots":
        # Every placement with all four dots kept: the RMS distance from the centroid is
        # spacing/√2 whatever the order of the dots.
        for i in np.unique(kept_owner):
            pts = unit_points[kept_owner == i]
            if len(pts) == 4:
                factors.append((target.spacing / math.sqrt(2.0)) / _spread(pts))
        if not factors:
            raise CalibrationError(
                f"mirror {name!r}: no placement has all four dots paired; the scale from the "
                "dot spacing needs one (or use the ToF scale)"
            )
    else:
        rho = np.concatenate([p.direct_distance for p in pairs])[inlier]
        rho_m = np.concatenate([p.mirrored_distance for p in pairs])[inlier]
        x_unit = np.linalg.norm(x[inlier], axis=1) * lam
        xm_unit = np.linalg.norm(xp[inlier], axis=1) * mu
        ratios = np.concatenate([rho / x_unit, rho_m / xm_unit])
        factors = list(ratios[np.isfinite(ratios)])
        if not factors:
            raise CalibrationError(
                f"mirror {name!r}: no ToF distances at the dots; the images carry no distance "
                "(use the scale from the dot spacing)"
            )
    factors_arr = np.array(factors)
    factor = float(np.median(factors_arr))
    if scale == "dots":
        # A placement whose dots triangulate to a square of another size was paired wrongly
        # (or detected badly): leave it out of the scale.
        off = np.abs(factors_arr / factor - 1.0) > SCALE_TOLERANCE
        placements = [pairs[i].image for i in np.unique(kept_owner) if np.sum(kept_owner == i) == 4]
        for bad_index in np.flatnonzero(off):
            rejected.append(
                f"{placements[bad_index]}: left out of the scale (its dots give a "
                f"{100 * (factors_arr[bad_index] / factor - 1):+.1f} % different size)"
            )
        factors_arr = factors_arr[~off]
        factor = float(np.mean(factors_arr))
    spread = float(np.std(factors_arr) / factor) if len(factors_arr) > 1 else 0.0
    plane = MirrorPlane(normal, 0.5 * factor)
    notes = [n for p in pairs for n in (f"{p.image}: {m}" for m in p.notes)]
    return MirrorEstimate(name, plane, int(inlier.sum()), len(x), rms, scale, spread,
                          used_images, rejected, notes)


def _triangulate(
    normal: np.ndarray, d: float, x: np.ndarray, xp: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (K, 3) seen at normalised x directly and at x' through the plane (normal, d):
    least squares of λ(r − 2(n·r)n) − μ r' = −2dn, the point being the mean of the direct
    ray's λr and the mirrored ray's reflection of μr'. Returns (points, λ, μ)."""
    n = normal
    points, lams, mus = [], [], []
    for r, rp in zip(x, xp):
        a = np.stack([r - 2.0 * (n @ r) * n, -rp], axis=1)
        (lam, mu), *_ = np.linalg.lstsq(a, -2.0 * d * n, rcond=None)
        direct = lam * r
        image = mu * rp
        via = image - 2.0 * (n @ image - d) * n
        points.append(0.5 * (direct + via))
        lams.append(lam)
        mus.append(mu)
    return np.array(points), np.array(lams), np.array(mus)


@dataclass
class MirrorCalibration:
    """The result of `calibrate_mirrors`: one estimate per mirror, in the prior's order."""

    estimates: list[MirrorEstimate]

    @property
    def planes(self) -> list[MirrorPlane]:
        return [e.plane for e in self.estimates]

    def report(self) -> list[str]:
        """Human-readable lines: per mirror, the result, then what was dropped and why."""
        lines = []
        for e in self.estimates:
            lines.append(
                f"mirror {e.name}: n = [{e.plane.normal[0]:+.4f} {e.plane.normal[1]:+.4f} "
                f"{e.plane.normal[2]:+.4f}], d = {e.plane.d * 1000:.2f} mm; "
                f"{len(e.images)} placements, {e.inliers}/{e.lines} pairs, "
                f"epipole RMS {e.rms_px:.3f} px, scale ({e.scale}) spread {100 * e.scale_spread:.2f} %"
            )
            lines.extend(f"  {m}" for m in e.rejected + e.notes)
        return lines


def pairs_of_image(
    camera: Camera,
    image: AmplitudeImage,
    names: Sequence[str],
    prior_normals: np.ndarray,
    region_labels: np.ndarray,
    mirror: str | None = None,
) -> tuple[int, Pairs]:
    """Detect, split and pair the dots of one image; (mirror index, pairs).

    The mirror is `mirror` if given, else the one whose image region (region_labels, e.g. the
    design's) holds most of the mirrored dots.
    """
    views = detect_views(image)
    if not views:
        raise CalibrationError(
            f"no dots found (mirror {mirror or 'unknown'}): no bright card with dark dots", image.name
        )
    label_name = mirror
    if label_name is None:  # for messages: the region the dots lie in (the target occludes
        # the mirror it stands at, so even its direct view lies in that mirror's region)
        dots = np.vstack([v.dots for v in views])
        h, w = region_labels.shape
        rows = np.clip(np.round(dots[:, 1]).astype(int), 0, h - 1)
        cols = np.clip(np.round(dots[:, 0]).astype(int), 0, w - 1)
        votes = region_labels[rows, cols]
        votes = votes[votes >= 0]
        label_name = names[int(np.bincount(votes).argmax())] if len(votes) else "unknown"
    direct, mirrored, notes = split_views(image, views, label_name)
    if mirror is not None:
        if mirror not in names:
            raise CalibrationError(f"no mirror named {mirror!r}; mirrors: {list(names)}")
        index = list(names).index(mirror)
    else:
        h, w = region_labels.shape
        rows = np.clip(np.round(mirrored.dots[:, 1]).astype(int), 0, h - 1)
        cols = np.clip(np.round(mirrored.dots[:, 0]).astype(int), 0, w - 1)
        votes = region_labels[rows, cols]
        votes = votes[votes >= 0]
        if len(votes) == 0:
            raise CalibrationError(
                "the mirrored view of the dots lies in no mirror's region; name the mirror "
                "(--mirror)",
                image.name,
            )
        index = int(np.bincount(votes).argmax())
    di, mi = pair_dots(camera, direct, mirrored, prior_normals[index])
    if len(di) < 2:
        raise CalibrationError(
            f"mirror {names[index]!r}: {len(di)} dot correspondence(s) (direct view "
            f"{len(direct.dots)} dots, mirrored view {len(mirrored.dots)}); need at least two",
            image.name,
        )
    pairs = Pairs(
        image.name,
        direct.dots[di],
        mirrored.dots[mi],
        direct.dot_distances[di],
        mirrored.dot_distances[mi],
        notes,
    )
    return index, pairs


def calibrate_mirrors(
    camera: Camera,
    images: Sequence[AmplitudeImage],
    names: Sequence[str],
    prior_planes: Sequence[MirrorPlane],
    region_labels: np.ndarray,
    *,
    target: DotTarget = DotTarget(),
    scale: str = "dots",
    mirror: str | None = None,
) -> MirrorCalibration:
    """Every mirror's plane from images of the dot target (see the module docstring).

    Args:
        camera: the intrinsics (from the checkerboard).
        images: amplitude (and distance) images, one target placement each.
        names, prior_planes: the mirrors, e.g. of the rig's design; the prior normals only
            break ties when pairing two dots, and name the mirrors.
        region_labels: (H, W) mirror index per pixel (the design's), to tell which mirror an
            image shows.
        mirror: the mirror every image shows, instead of finding it from region_labels.

    Raises:
        CalibrationError naming the image and mirror: no dots, fewer than two correspondences,
        a mirror that no image shows.
    """
    prior_normals = np.array([p.normal for p in prior_planes])
    per_mirror: list[list[Pairs]] = [[] for _ in names]
    for image in images:
        index, pairs = pairs_of_image(camera, image, names, prior_normals, region_labels, mirror)
        per_mirror[index].append(pairs)
    wanted = range(len(names)) if mirror is None else [list(names).index(mirror)]
    missing = [names[k] for k in wanted if not per_mirror[k]]
    if missing:
        raise CalibrationError(
            f"mirror(s) {', '.join(repr(m) for m in missing)}: no image shows the dot target in "
            "them; place the target at every mirror"
        )
    estimates = [
        estimate_mirror(camera, names[k], per_mirror[k], prior_normals[k], target=target, scale=scale)
        for k in wanted
    ]
    return MirrorCalibration(estimates)
