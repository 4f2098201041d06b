"""Distance calibration: the systematic error of the ToF distances, estimated and removed.

A continuous-wave ToF camera's distance has errors that repeat from frame to frame (Lindner &
Kolb 2006, Fuchs & May 2008):

- the "wiggling" error, a periodic function of the distance (the correlation function's odd
  harmonics; with four phase samples, period a quarter of the unambiguous range);
- an amplitude-dependent error (dark or far surfaces read farther or nearer);
- a per-pixel fixed-pattern offset (the pixel's own delay).

`DistanceCorrection` models the error as the sum of the three,

    error(d, a, p) = w(d) + g(log a) + o[p],

w and g cubic B-splines (Lindner & Kolb's choice for the wiggling curve), o a table with one
offset per pixel, and corrects a reading by subtracting it: d' = d − error(d, a, p). The fit is
one sparse linear least-squares problem (`fit`) over samples (measured distance, true distance,
amplitude, pixel), e.g. the pixels of boards whose poses the refinement found, or of a flat wall
driven past. The three parts share a constant: g is pinned to zero at the median amplitude, and a
ridge on o (a prior of PIXEL_PRIOR against the readings' noise) leaves the rest to w. The normal equations' pixel block is diagonal, so it is
eliminated (Schur complement) before a dense solve of the spline coefficients. Outside the fitted ranges of distance and
amplitude the curves are held at their end values.

The correction is stored in the calibration YAML under `distance_correction`; a file without it
loads with none (the identity).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import BSpline
from scipy.sparse import coo_matrix, csr_matrix, hstack, vstack
from threadpoolctl import threadpool_limits

from omnitof.errors import InputError

DEGREE = 3
# Knot spacing of the wiggling curve (metres): a quarter of the SR4000's 5 m unambiguous range
# is 1.25 m, so 0.125 m gives ten knots per period.
DISTANCE_KNOT_SPACING = 0.125
# Interior knots of the amplitude curve over the range of log amplitude.
AMPLITUDE_KNOTS = 6
# Second-difference penalty on the spline coefficients (P-splines, Eilers & Marx 1996), per
# sample of a coefficient's share: it bridges distances no sample covers (walls or boards at a
# few distances leave gaps between knots) with a straight line, and is too weak to flatten a
# curve the samples cover (a wiggle of ten knots per period loses < 0.1 % of its amplitude).
SMOOTHNESS = 1e-3
# Prior standard deviation of the per-pixel offsets (metres): with the readings' noise σ (from a
# first fit without them) each offset is shrunk toward zero like a mean of its samples with
# (σ / PIXEL_PRIOR)² samples of value zero added, so that offsets fitted to a few noisy readings
# do not add noise (one frame of a dark wall at 4 m: σ ≈ 25 mm; average frames to do better).
PIXEL_PRIOR = 0.005


class DistanceCorrectionError(InputError):
    """A distance correction that cannot be fitted or read; the message names the field."""


def _clamped_knots(lo: float, hi: float, count: int) -> np.ndarray:
    inner = np.linspace(lo, hi, max(2, count))
    return np.concatenate([[lo] * DEGREE, inner, [hi] * DEGREE])


def _held(knots: np.ndarray, x: np.ndarray) -> np.ndarray:
    """x clipped into the knots' span: the spline holds its end values outside it."""
    lo, hi = knots[DEGREE], knots[-DEGREE - 1]
    return np.clip(x, lo, hi - 1e-12 * max(1.0, abs(hi)))


def _design(knots: np.ndarray, x: np.ndarray) -> csr_matrix:
    """B-spline basis (N, n_coefficients) at x, held at the end values outside the knots."""
    return BSpline.design_matrix(_held(knots, x), knots, DEGREE).tocsr()


def _spline(knots: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The B-spline's values at x, held at the end values outside the knots: `_design(knots,
    x) @ coefficients` without building the basis (a quarter of its time; every pixel of every
    frame is corrected with it)."""
    return BSpline(knots, coefficients, DEGREE, extrapolate=False)(_held(knots, x))


@dataclass
class DistanceCorrection:
    """error(d, a, p) = w(d) + g(log a) + o[p] (see the module docstring).

    distance_knots / distance_coefficients: w, a cubic B-spline in metres of measured distance.
    amplitude_knots / amplitude_coefficients: g, a cubic B-spline in log amplitude.
    pixel_offsets: (H, W) metres, or None (no per-pixel term).
    samples, rms_before, rms_after: how it was fitted (metres).
    curve: the fit samples' median error per 0.1 m of distance before and after the
        correction (`distance_m`, `before_mm`, `after_mm`), for the calibration report.
    """

    distance_knots: np.ndarray
    distance_coefficients: np.ndarray
    amplitude_knots: np.ndarray
    amplitude_coefficients: np.ndarray
    pixel_offsets: np.ndarray | None = None
    samples: int = 0
    rms_before: float = math.nan
    rms_after: float = math.nan
    curve: dict[str, list[float]] | None = None

    @property
    def fitted_span(self) -> tuple[float, float]:
        """The measured distances (metres) the wiggling curve was fitted over; outside them it
        holds its end values."""
        return float(self.distance_knots[DEGREE]), float(self.distance_knots[-DEGREE - 1])

    # --- use --------------------------------------------------------------------------------

    def error(self, distance: np.ndarray, amplitude: np.ndarray, pixels: np.ndarray | None = None) -> np.ndarray:
        """The modelled error (metres) of readings; any shape, `pixels` flat indices
        (row·W + col) of the same shape, or None when distance is a whole (H, W) image."""
        d = np.asarray(distance, dtype=np.float64)
        a = np.asarray(amplitude, dtype=np.float64)
        shape = d.shape
        flat_d, flat_a = d.ravel(), a.ravel()
        ok = np.isfinite(flat_d) & np.isfinite(flat_a) & (flat_a > 0)
        out = np.zeros(flat_d.shape)
        if ok.any():
            w = _spline(self.distance_knots, self.distance_coefficients, flat_d[ok])
            g = _spline(self.amplitude_knots, self.amplitude_coefficients, np.log(flat_a[ok]))
            out[ok] = w + g
        if self.pixel_offsets is not None:
            offsets = self.pixel_offsets.ravel()
            if pixels is None:
                if d.shape != self.pixel_offsets.shape:
                    raise DistanceCorrectionError(
                        f"distance_correction: images are {d.shape}, the pixel offsets {self.pixel_offsets.shape}"
                    )
                out += offsets
            else:
                out += offsets[np.asarray(pixels).ravel()]
        return out.reshape(shape)

    def correct(self, distance: np.ndarray, amplitude: np.ndarray, pixels: np.ndarray | None = None) -> np.ndarray:
        """Corrected distances d − error(d, a, p), float32 for float32 input; NaN stays NaN.
        A stack of images (N, H, W) is corrected image by image."""
        d = np.asarray(distance)
        if pixels is None and self.pixel_offsets is not None and d.ndim == 3:
            return np.stack([self.correct(di, ai) for di, ai in zip(d, np.asarray(amplitude))])
        out = d - self.error(d, amplitude, pixels)
        return out.astype(d.dtype if np.issubdtype(d.dtype, np.floating) else np.float64)

    # --- fit --------------------------------------------------------------------------------

    @classmethod
    def fit(
        cls,
        measured: np.ndarray,
        true: np.ndarray,
        amplitude: np.ndarray,
        pixels: np.ndarray | None = None,
        shape: tuple[int, int] | None = None,
        *,
        knot_spacing: float = DISTANCE_KNOT_SPACING,
    ) -> DistanceCorrection:
        """Fit the three terms to samples (1-D arrays of one length; pixels: flat indices into
        an image of `shape`, or None for no per-pixel term). Robust: samples off by more than
        5 robust σ after a first fit (mixed pixels, wrong targets) are dropped and it is refitted."""
        m = np.asarray(measured, dtype=np.float64).ravel()
        t = np.asarray(true, dtype=np.float64).ravel()
        a = np.asarray(amplitude, dtype=np.float64).ravel()
        ok = np.isfinite(m) & np.isfinite(t) & np.isfinite(a) & (a > 0)
        if pixels is not None:
            p = np.asarray(pixels).ravel().astype(np.int64)
            if shape is None:
                raise DistanceCorrectionError("distance_correction: pixel indices need the image shape")
        else:
            p = np.zeros(len(m), dtype=np.int64)
        m, t, a, p = m[ok], t[ok], a[ok], p[ok]
        if len(m) < 50:
            raise DistanceCorrectionError(f"distance_correction: {len(m)} usable samples, need at least 50")
        lo, hi = float(np.min(m)), float(np.max(m))
        n_knots = max(2, int(math.ceil((hi - lo) / knot_spacing)) + 1)
        dk = _clamped_knots(lo, hi, n_knots)
        la = np.log(a)
        ak = _clamped_knots(float(la.min()), float(la.max()), AMPLITUDE_KNOTS)
        keep = np.ones(len(m), dtype=bool)
        ridge = 1.0
        # Weights 1/σ ∝ amplitude (the phase noise falls as the signal grows), relative to the
        # median: unweighted, the dark far readings' noise (tens of mm) drowns the curve.
        wt = np.clip(a / np.median(a), 0.05, 3.0)
        if pixels is not None:  # the readings' noise, from a first fit without the pixel term
            coef = _solve(m, t, la, p, dk, ak, False, shape, 1.0, wt)
            first = cls(dk, coef[0], ak, coef[1], None)
            r = ((m - first.error(m, a)) - t) * wt
            noise = 1.4826 * float(np.median(np.abs(r - np.median(r))))
            ridge = max(noise / PIXEL_PRIOR, 1e-3)
        for _ in range(2):
            coef = _solve(m[keep], t[keep], la[keep], p[keep], dk, ak, pixels is not None, shape, ridge, wt[keep])
            model = cls(dk, coef[0], ak, coef[1], coef[2], int(keep.sum()))
            residual = (m - model.error(m, a, p if pixels is not None else None)) - t
            scaled = residual * wt
            sigma = 1.4826 * float(np.median(np.abs(scaled[keep] - np.median(scaled[keep]))))
            keep = np.abs(scaled - np.median(scaled[keep])) < max(5.0 * sigma, 1e-4)
        model.samples = int(keep.sum())
        model.rms_before = float(np.sqrt(np.mean((m[keep] - t[keep]) ** 2)))
        model.rms_after = float(np.sqrt(np.mean(residual[keep] ** 2)))
        model.curve = _binned_curve(m[keep], (m - t)[keep], residual[keep])
        return model

    # --- YAML -------------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "model": "bspline",
            "degree": DEGREE,
            "distance_knots": [float(v) for v in self.distance_knots],
            "distance_coefficients": [float(v) for v in self.distance_coefficients],
            "log_amplitude_knots": [float(v) for v in self.amplitude_knots],
            "amplitude_coefficients": [float(v) for v in self.amplitude_coefficients],
            "samples": int(self.samples),
            "rms_before_mm": round(1000.0 * self.rms_before, 3) if math.isfinite(self.rms_before) else None,
            "rms_after_mm": round(1000.0 * self.rms_after, 3) if math.isfinite(self.rms_after) else None,
        }
        if self.curve is not None:
            out["curve"] = {k: [round(float(v), 4) for v in vals] for k, vals in self.curve.items()}
        if self.pixel_offsets is not None:
            # Rows of per-pixel offsets in millimetres, to 1 µm.
            out["pixel_offsets_mm"] = [[round(float(v), 3) for v in row] for row in 1000.0 * self.pixel_offsets]
        return out

    @classmethod
    def from_dict(cls, data: Any, shape: tuple[int, int], source: Any = None) -> DistanceCorrection:
        where = "distance_correction"
        if not isinstance(data, Mapping):
            raise DistanceCorrectionError(f"{where}: expected a mapping", source)
        if data.get("model", "bspline") != "bspline" or int(data.get("degree", DEGREE)) != DEGREE:
            raise DistanceCorrectionError(f"{where}: only the cubic B-spline model is known", source)

        def numbers(key: str) -> np.ndarray:
            try:
                arr = np.asarray(data[key], dtype=np.float64)
            except KeyError:
                raise DistanceCorrectionError(f"{where}.{key}: missing", source) from None
            except (TypeError, ValueError):
                raise DistanceCorrectionError(f"{where}.{key}: expected a list of numbers", source) from None
            if arr.ndim != 1 or not np.all(np.isfinite(arr)):
                raise DistanceCorrectionError(f"{where}.{key}: expected a list of finite numbers", source)
            return arr

        dk, dc = numbers("distance_knots"), numbers("distance_coefficients")
        ak, ac = numbers("log_amplitude_knots"), numbers("amplitude_coefficients")
        for knots, coef, name in ((dk, dc, "distance"), (ak, ac, "amplitude")):
            if len(knots) != len(coef) + DEGREE + 1 or np.any(np.diff(knots) < 0):
                raise DistanceCorrectionError(
                    f"{where}: {name} knots ({len(knots)}) must be sorted and number the coefficients "
                    f"({len(coef)}) + {DEGREE + 1}", source)
        offsets = None
        if data.get("pixel_offsets_mm") is not None:
            try:
                offsets = np.asarray(data["pixel_offsets_mm"], dtype=np.float64) / 1000.0
            except (TypeError, ValueError):
                raise DistanceCorrectionError(f"{where}.pixel_offsets_mm: expected rows of numbers", source) from None
            if offsets.shape != tuple(shape) or not np.all(np.isfinite(offsets)):
                raise DistanceCorrectionError(
                    f"{where}.pixel_offsets_mm: expected {shape[0]} rows of {shape[1]} finite numbers", source)
        def number(key: str) -> float:
            value = data.get(key)
            return float(value) / 1000.0 if isinstance(value, (int, float)) else math.nan

        curve = data.get("curve")
        if curve is not None and not (isinstance(curve, Mapping) and all(
                isinstance(curve.get(k), list) for k in ("distance_m", "before_mm", "after_mm"))):
            raise DistanceCorrectionError(f"{where}.curve: expected distance_m, before_mm, after_mm lists", source)
        return cls(dk, dc, ak, ac, offsets, int(data.get("samples") or 0), number("rms_before_mm"),
                   number("rms_after_mm"), dict(curve) if curve is not None else None)


def _solve(m, t, la, p, dk, ak, per_pixel: bool, shape, ridge: float, weights: np.ndarray):
    """Weighted least squares of (m − t) = w(m) + g(la) + o[p] with g(median la) = 0."""
    n = len(m)
    W = coo_matrix((weights, (np.arange(n), np.arange(n))), shape=(n, n)).tocsr()
    Bd = W @ _design(dk, m)
    Ba = W @ _design(ak, la)
    blocks = [Bd, Ba]
    n_pix = int(shape[0] * shape[1]) if per_pixel else 0
    if per_pixel:
        blocks.append(coo_matrix((weights, (np.arange(n), p)), shape=(n, n_pix)).tocsr())
    A = hstack(blocks).tocsr()
    b = (m - t) * weights
    # Constraints as heavily weighted rows, and a light ridge on the pixel offsets.
    heavy = 10.0 * math.sqrt(n)
    g_row = hstack([csr_matrix((1, Bd.shape[1])), _design(ak, np.array([np.median(la)])),
                    csr_matrix((1, n_pix))]) * heavy
    rows = [A, g_row]
    rhs = [b, np.zeros(1)]
    for start, basis in ((0, Bd), (Bd.shape[1], Ba)):
        k = basis.shape[1]
        if k >= 3:
            second = np.zeros((k - 2, A.shape[1]))
            i = np.arange(k - 2)
            second[i, start + i], second[i, start + i + 1], second[i, start + i + 2] = 1.0, -2.0, 1.0
            rows.append(csr_matrix(second * math.sqrt(SMOOTHNESS * n / k)))
            rhs.append(np.zeros(k - 2))
    if per_pixel:
        # A ridge (see PIXEL_PRIOR) keeps the offsets of pixels with few or noisy samples near
        # zero, and sends the constant they share with w into w.
        rows.append(hstack([csr_matrix((n_pix, Bd.shape[1] + Ba.shape[1])), _identity(n_pix) * ridge]))
        rhs.append(np.zeros(n_pix))
    system = vstack(rows).tocsr()
    normal = (system.T @ system).tocsr()
    rhs_n = system.T @ np.concatenate(rhs)
    ns = Bd.shape[1] + Ba.shape[1]
    # The dense products and solves on one BLAS thread: a multithreaded BLAS sums them in an
    # order that depends on its thread count, and the correction differed in its last digits
    # between one core and two (as the refinement did, calibration.refine.refine).
    with threadpool_limits(limits=1, user_api="blas"):
        if not per_pixel:
            x = np.linalg.solve(normal.toarray(), rhs_n)
        else:
            # The pixel block of the normal equations is diagonal (one pixel per sample):
            # eliminate it (Schur complement) and solve the few spline coefficients densely.
            A = normal[:ns, :ns].toarray()
            B = normal[:ns, ns:].toarray()
            D = normal[ns:, ns:].diagonal()
            schur = A - (B / D) @ B.T
            xs = np.linalg.solve(schur, rhs_n[:ns] - (B / D) @ rhs_n[ns:])
            xp = (rhs_n[ns:] - B.T @ xs) / D
            x = np.concatenate([xs, xp])
    wd = x[: Bd.shape[1]]
    wa = x[Bd.shape[1] : Bd.shape[1] + Ba.shape[1]]
    offsets = x[Bd.shape[1] + Ba.shape[1] :].reshape(shape) if per_pixel else None
    return wd, wa, offsets


def _binned_curve(measured: np.ndarray, before: np.ndarray, after: np.ndarray) -> dict[str, list[float]]:
    """Median error per 0.1 m bin of measured distance (bins with at least 20 samples), mm."""
    bins = np.floor(measured / 0.1).astype(np.int64)
    out: dict[str, list[float]] = {"distance_m": [], "before_mm": [], "after_mm": []}
    for b in np.unique(bins):
        sel = bins == b
        if sel.sum() >= 20:
            out["distance_m"].append(0.1 * b + 0.05)
            out["before_mm"].append(1000.0 * float(np.median(before[sel])))
            out["after_mm"].append(1000.0 * float(np.median(after[sel])))
    return out


def _identity(n: int) -> csr_matrix:
    return coo_matrix((np.ones(n), (np.arange(n), np.arange(n))), shape=(n, n)).tocsr()


def samples_from_plane(
    camera: Any, planes: Any, labels: np.ndarray, distance: np.ndarray, amplitude: np.ndarray,
    normal: np.ndarray, c: float, *, max_error: float = 0.15,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Samples for `DistanceCorrection.fit` from one frame of a flat surface of known pose
    {x : normal·x = c} (camera frame; e.g. a wall the robot stands at a measured distance from,
    or a board pose the refinement found): per labelled pixel the measured distance, the true
    path (along the pixel's ray to the plane reflected in the pixel's mirror, eq. 6), the
    amplitude and the flat pixel index. Pixels off the plane by more than max_error (another
    surface, mixed pixels) are left out."""
    rays = camera.pixel_grid_rays().reshape(-1, 3)
    flat = np.asarray(labels).reshape(-1)
    n = np.asarray(normal, dtype=np.float64)
    true = np.full(flat.shape, np.nan)
    for k, plane in enumerate(planes):
        sel = flat == k
        dot = float(n @ plane.normal)
        n2 = n - 2.0 * dot * plane.normal  # the surface's plane reflected in the mirror
        c2 = c - 2.0 * plane.d * dot
        with np.errstate(divide="ignore", invalid="ignore"):
            true[sel] = c2 / (rays[sel] @ n2)
    measured = np.asarray(distance, dtype=np.float64).reshape(-1)
    amp = np.asarray(amplitude, dtype=np.float64).reshape(-1)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(true) & (true > 0) & np.isfinite(measured) & (amp > 0) & (np.abs(measured - true) < max_error)
    index = np.flatnonzero(ok)
    return measured[index], true[index], amp[index], index
