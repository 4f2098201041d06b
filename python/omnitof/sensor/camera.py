"""Pinhole camera with OpenCV's radial-tangential lens distortion (k1, k2, p1, p2, k3).

Conventions, used throughout:

- Pixels: (u, v) = (column, row); pixel centres at integer coordinates (OpenCV's), so pixel
  [row, col] of an image is centred at (u, v) = (col, row) and the sensor spans
  [-0.5, W - 0.5] × [-0.5, H - 0.5]. Images are arrays indexed [row, col], shape (H, W).
- Camera frame: x right (growing u), y down (growing v), z along the optical axis, away from the
  camera (in the omnitof sensor it points up, into the mirrors). Points in metres, float64.
- Normalised coordinates: (x, y) = (X/Z, Y/Z) of a point before distortion.
- Distortion (OpenCV's model, coefficients in OpenCV's order), with r² = x² + y²:
      x_d = x·(1 + k1·r² + k2·r⁴ + k3·r⁶) + 2·p1·x·y + p2·(r² + 2x²)
      y_d = y·(1 + k1·r² + k2·r⁴ + k3·r⁶) + p1·(r² + 2y²) + 2·p2·x·y
      u = fx·x_d + cx,  v = fy·y_d + cy
- Valid region: strong barrel distortion (k1 < 0) makes this polynomial fold back far from the
  axis: beyond the fold, points further out land nearer the centre, so a pixel has two
  preimages. Along each direction the map is kept only up to its fold (the first radius where
  the Jacobian determinant of (x, y) ↦ (x_d, y_d) reaches zero); `project` returns NaN for points
  beyond it and `rays` for pixels it cannot back-project exactly. For the SR4000 default the
  fold is nearest straight up (r = 0.846, 40° off axis), where it maps to image row ≈ -40,
  outside the image: every pixel of both lens models back-projects uniquely (to 1e-10 px).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from scipy.optimize import brentq

from omnitof.errors import ConfigError

# cv2.undistortPoints runs a fixed-point iteration. Its default 5 steps leave 30 % of the SR4000's
# pixels off by more than 1e-3 px and the top-right corner by 2.4 px (the error shrinks only by
# ~0.95 per step there); 500 steps bring every pixel below 1e-10 px. The EPS test (reprojection
# error in pixels) stops the easy pixels early, so the limit costs little.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-10)
# A back-projected ray must reproject to its pixel within this, else it is NaN.
_BACKPROJECTION_TOLERANCE_PX = 1e-6
# The fold search covers directions up to atan(20) = 87° off axis; points further out are NaN.
_FOLD_SEARCH_RADIUS = 20.0
_FOLD_ANGLES = 720  # 0.5° bins of direction in the normalised plane
_INTERPOLATION = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST}


class CameraParameterError(ConfigError, ValueError):
    """A bad camera parameter or input array, named in the message; ConfigError and ValueError."""


# Image sides beyond this are refused: no camera has them, and the images and ray tables of one
# would need terabytes (a typo such as an extra digit, not a camera).
MAX_IMAGE_SIDE = 16384


@dataclass(frozen=True)
class Camera:
    """Intrinsics of a pinhole camera with distortion, in OpenCV's parameterisation.

    Attributes:
        width, height: image size in pixels (columns, rows).
        fx, fy: focal lengths in pixels (> 0).
        cx, cy: principal point in pixels, (column, row), pixel centres at integers.
        dist: (k1, k2, p1, p2, k3), OpenCV's order.

    The instance is immutable, so derived tables (pixel rays, undistortion maps) are cached.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise CameraParameterError(
                    f"Camera.{name} must be a positive whole number of pixels, got {value!r}"
                )
            if value > MAX_IMAGE_SIDE:
                raise CameraParameterError(
                    f"Camera.{name} must be at most {MAX_IMAGE_SIDE} pixels (the largest image sensors), "
                    f"got {value!r}"
                )
            object.__setattr__(self, name, int(value))
        for name in ("fx", "fy"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0.0):
                raise CameraParameterError(
                    f"Camera.{name} must be a positive, finite focal length in pixels, "
                    f"got {value!r}"
                )
            object.__setattr__(self, name, value)
        for name in ("cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise CameraParameterError(f"Camera.{name} must be finite, got {value!r}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "dist", _checked_dist(self.dist))

    # --- models of the paper's camera ------------------------------------------------------

    @classmethod
    def sr4000(cls) -> Camera:
        """MESA SwissRanger SR4000, standard lens: 176×144 pixels, 43.6°×34.6° datasheet FOV.

        Intrinsics and distortion are the SR4000 calibration published with the Care-O-bot ROS
        driver (4am-robotics/cob_driver, cob_camera_sensors/ros/launch/cob3-2/
        swissranger4000.yaml): fx = 249.58, fy = 248.65, cx = 83.60, cy = 76.10 px,
        dist = (-0.8, 0.3, 0.01, 0, 0). fx matches the optics: a 10 mm lens on 40 µm pixels
        (the datasheet's figures, as we recall them) gives 250 px. This model's edge-to-edge field of view is 43.8°×34.9°; a distortion-free
        pinhole with the same focal length would see only 38.8°×32.3°, so the datasheet's
        43.6°×34.6° includes the barrel distortion.
        """
        return cls(176, 144, 249.58, 248.65, 83.60, 76.10, (-0.8, 0.3, 0.01, 0.0, 0.0))

    @classmethod
    def sr4000_wide(cls) -> Camera:
        """The SR4000 with its wide-angle lens option (datasheet: 69° horizontal FOV).

        Assumptions: same sensor and principal point; distortion of the same kind and the same
        size *in pixels* (the same percentage of barrel at the image edge), which for a focal
        length scaled by s = f_wide/f_std means k1·s², k2·s⁴, p1·s, p2·s, k3·s⁶. fx is solved so
        that this model's edge-to-edge horizontal FOV is 69.0°, and fy keeps the standard
        model's fy/fx (square 40 µm pixels). This gives fx = 145.74, fy = 145.20 px and
        k1 = -0.273, k2 = 0.0349, p1 = 0.0058; the vertical FOV then follows as 56.5°
        (the datasheet's wide option is 69°×56°, as far as we recall it).
        """
        return _sr4000_wide()

    # --- intrinsics ------------------------------------------------------------------------

    @property
    def K(self) -> np.ndarray:
        """The 3×3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (a fresh float64 array)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """(k1, k2, p1, p2, k3) as a float64 array, as cv2 functions take them."""
        return np.array(self.dist, dtype=np.float64)

    @property
    def shape(self) -> tuple[int, int]:
        """The image shape (rows, cols) = (height, width)."""
        return (self.height, self.width)

    # --- projection ------------------------------------------------------------------------

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply the distortion to normalised coordinates (N, 2) → distorted normalised (N, 2)."""
        xy = _as_rows(xy, 2, "xy")
        return np.stack(self._distort(xy[:, 0], xy[:, 1]), axis=1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) = (u, v) of points (N, 3) in the camera frame, metres.

        Same model as cv2.projectPoints with zero rotation and translation. Rows are NaN for
        points with z <= 0 (behind the camera) and beyond the distortion's fold (see the
        module docstring); they may land outside the image otherwise.
        """
        pts = _as_rows(points, 3, "points")
        z = pts[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = pts[:, 0] / z, pts[:, 1] / z
        xd, yd = self._distort(x, y)
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        uv[~((z > 0.0) & self._inside_fold(x, y))] = np.nan
        return uv

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """Unit direction vectors (N, 3) in the camera frame of pixel coordinates (N, 2) = (u, v).

        Undistorts with cv2.undistortPoints (iterated to convergence, see _UNDISTORT_CRITERIA),
        then checks that each ray reprojects to its pixel within 1e-6 px and lies inside the
        fold; rows that fail are NaN. Every ray has z > 0.
        """
        px = _as_rows(pixels, 2, "pixels")
        out = np.full((len(px), 3), np.nan)
        if len(px) == 0:
            return out
        xy = cv2.undistortPoints(
            px.reshape(-1, 1, 2), self.K, self.dist_coeffs, criteria=_UNDISTORT_CRITERIA
        ).reshape(-1, 2)
        x, y = xy[:, 0], xy[:, 1]
        xd, yd = self._distort(x, y)
        error = np.hypot(self.fx * xd + self.cx - px[:, 0], self.fy * yd + self.cy - px[:, 1])
        ok = (error <= _BACKPROJECTION_TOLERANCE_PX) & self._inside_fold(x, y)
        direction = np.stack([x, y, np.ones_like(x)], axis=1)
        out[ok] = direction[ok] / np.linalg.norm(direction[ok], axis=1, keepdims=True)
        return out

    def pixel_grid_rays(self) -> np.ndarray:
        """Rays (H, W, 3) through each pixel centre, [row, col] → unit vector; cached, read-only."""
        if "grid_rays" not in self._cache:
            v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
            grid = self.rays(np.stack([u.ravel(), v.ravel()], axis=1))
            grid = grid.reshape(self.height, self.width, 3)
            grid.setflags(write=False)  # shared by every caller: nobody may change it
            self._cache["grid_rays"] = grid
        return self._cache["grid_rays"]

    # --- images ----------------------------------------------------------------------------

    def undistort_image(
        self, image: np.ndarray, interpolation: str = "linear", fill: float | None = None
    ) -> np.ndarray:
        """The image as a distortion-free camera with the same K would have seen it.

        Args:
            image: (H, W) or (H, W, C) array, [row, col] indexing, any dtype cv2.remap takes.
            interpolation: "linear" or "nearest". Use "nearest" for distance images: linear
                interpolation mixes depths across edges into points that lie on no surface.
            fill: value of output pixels whose source lies outside the image; NaN for float
                images and 0 otherwise by default. (Barrel distortion: with the same K the
                output shows the central part of the field of view and needs no fill.)

        Returns:
            An array of the input's shape and dtype.
        """
        img = np.asarray(image)
        if img.shape[:2] != self.shape:
            raise CameraParameterError(
                f"image must have shape (height, width) = {self.shape}, got {img.shape}"
            )
        if interpolation not in _INTERPOLATION:
            raise CameraParameterError(
                f"interpolation must be one of {sorted(_INTERPOLATION)}, got {interpolation!r}"
            )
        if fill is None:
            fill = math.nan if np.issubdtype(img.dtype, np.floating) else 0.0
        map_x, map_y = self._undistort_maps()
        return cv2.remap(
            img,
            map_x,
            map_y,
            _INTERPOLATION[interpolation],
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=fill,
        )

    def field_of_view(self) -> tuple[float, float]:
        """(horizontal, vertical) field of view in degrees, with the distortion.

        The angle between the rays through the outer edges of the outermost pixels (u = -0.5
        and W - 0.5 on the row v = cy; v = -0.5 and H - 0.5 on the column u = cx).
        """
        w, h = self.width - 0.5, self.height - 0.5
        r = self.rays(np.array([[-0.5, self.cy], [w, self.cy], [self.cx, -0.5], [self.cx, h]]))
        horizontal = math.degrees(math.acos(np.clip(r[0] @ r[1], -1.0, 1.0)))
        vertical = math.degrees(math.acos(np.clip(r[2] @ r[3], -1.0, 1.0)))
        return horizontal, vertical

    # --- internals -------------------------------------------------------------------------

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return xd, yd

    def _inside_fold(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """True where (x, y) lies nearer the axis than the distortion's fold in its direction."""
        limits = self._fold_radii()
        angle = np.nan_to_num(np.arctan2(y, x))  # NaN (z = 0) fails the radius test below
        index = np.floor((angle + math.pi) / (2.0 * math.pi) * _FOLD_ANGLES).astype(np.int64)
        index = np.clip(index, 0, _FOLD_ANGLES - 1)
        # Each bin takes the nearer fold of its two edges, so the test never overshoots.
        bound = np.minimum(limits[index], limits[index + 1])
        with np.errstate(invalid="ignore"):
            return np.hypot(x, y) < bound

    def _fold_radii(self) -> np.ndarray:
        """Fold radius at the _FOLD_ANGLES + 1 bin edges of direction in [-π, π] (cached)."""
        if "fold" not in self._cache:
            self._cache["fold"] = _fold_radii(self.dist)
        return self._cache["fold"]

    def _undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        if "maps" not in self._cache:
            self._cache["maps"] = cv2.initUndistortRectifyMap(
                self.K, self.dist_coeffs, None, self.K, (self.width, self.height), cv2.CV_32FC1
            )
        return self._cache["maps"]


def _checked_dist(dist: Iterable[float]) -> tuple[float, float, float, float, float]:
    try:
        values = tuple(float(c) for c in dist)
    except (TypeError, ValueError):
        raise CameraParameterError(
            f"Camera.dist must be 5 numbers (k1, k2, p1, p2, k3), got {dist!r}"
        ) from None
    if len(values) != 5:
        raise CameraParameterError(
            f"Camera.dist must have 5 coefficients (k1, k2, p1, p2, k3) in OpenCV's order, "
            f"got {len(values)}"
        )
    if not all(math.isfinite(c) for c in values):
        raise CameraParameterError(f"Camera.dist must be finite, got {values}")
    return values  # type: ignore[return-value]


def _as_rows(array: np.ndarray, columns: int, name: str) -> np.ndarray:
    out = np.asarray(array, dtype=np.float64)
    if out.ndim != 2 or out.shape[1] != columns:
        raise CameraParameterError(f"{name} must have shape (N, {columns}), got {out.shape}")
    return out


def _jacobian_det(x: np.ndarray, y: np.ndarray, dist: tuple[float, ...]) -> np.ndarray:
    """det ∂(x_d, y_d)/∂(x, y) of the distortion, analytically."""
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))  # ∂radial/∂x = dradial·x
    dxdx = radial + dradial * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    dxdy = dradial * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    dydx = dradial * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    dydy = radial + dradial * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    return dxdx * dydy - dxdy * dydx


def _fold_radii(dist: tuple[float, ...]) -> np.ndarray:
    """Per direction, the first normalised radius where the Jacobian determinant is <= 0."""
    angles = np.linspace(-math.pi, math.pi, _FOLD_ANGLES + 1)
    radii = np.geomspace(1e-3, _FOLD_SEARCH_RADIUS, 4000)  # steps of 0.25 %
    det = _jacobian_det(
        radii[None, :] * np.cos(angles)[:, None], radii[None, :] * np.sin(angles)[:, None], dist
    )
    folded = det <= 0.0
    first = np.argmax(folded, axis=1)
    return np.where(folded.any(axis=1), radii[first], _FOLD_SEARCH_RADIUS)


# The SR4000 wide-angle option's horizontal field of view (datasheet).
_SR4000_WIDE_HFOV_DEG = 69.0


@lru_cache(maxsize=1)
def _sr4000_wide() -> Camera:
    standard = Camera.sr4000()

    def scaled(s: float) -> Camera:
        k1, k2, p1, p2, k3 = standard.dist
        dist = (k1 * s**2, k2 * s**4, p1 * s, p2 * s, k3 * s**6)
        return Camera(
            standard.width, standard.height, standard.fx * s, standard.fy * s,
            standard.cx, standard.cy, dist,
        )

    # The FOV falls monotonically with the focal length; 0.3–1 brackets 69°.
    s = brentq(lambda s: scaled(s).field_of_view()[0] - _SR4000_WIDE_HFOV_DEG, 0.3, 1.0, xtol=1e-12)
    return scaled(s)
