"""Camera intrinsics from amplitude images of a checkerboard, with OpenCV (paper sec. II-C: the
camera is calibrated without the mirrors first, for its lens distortion and P = K[I|0]).

Images come from disk (`calibration.images.load_images`): PNG/PGM/TIFF amplitude images, `.npz` files with
`amplitude` (and `distance`) arrays as `render_calibration_images` writes them, or ROS bags
(every frame's amplitude image, via `omnitof.io.rosbag.read_tof_bag`).

ToF amplitude falls off as 1/r², so images are scaled to 8 bits by a high percentile (not the
maximum, which a few hot pixels set) before OpenCV's detectors see them. Corners are found with
cv2.findChessboardCorners (brought within ~0.1 px by cv2.cornerSubPix) or, failing that,
cv2.findChessboardCornersSB, and refined by `saddle_points` (a quadratic's saddle point on the
locally normalised image; cornerSubPix alone was 4× less accurate on simulated boards, see
there); cv2.calibrateCamera fits K and (k1, k2, p1, p2[, k3]).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates, maximum_filter, minimum_filter

from omnitof.calibration import CalibrationError
from omnitof.calibration.images import AmplitudeImage
from omnitof.calibration.targets import Checkerboard
from omnitof.errors import OmnitofWarning
from omnitof.sensor.camera import Camera

# Percentile of the amplitude that maps to 255 when an image is scaled to 8 bits.
_SCALE_PERCENTILE = 99.5
# At least this many boards are needed for a calibration with distortion.
MIN_VIEWS = 3
# A view whose RMS reprojection error exceeds this many times the median of all views (and
# MIN_OUTLIER_PX) is rejected as an outlier and the calibration repeated without it.
OUTLIER_FACTOR = 3.0
MIN_OUTLIER_PX = 0.2
# An RMS reprojection error above this is a fit gone wrong, not a camera's noise (simulated
# boards: 0.03-0.1 px; a real ToF camera's amplitude images: tenths of a pixel).
SUSPECT_RMS_PX = 1.0


def to_uint8(amplitude: np.ndarray) -> np.ndarray:
    """The amplitude scaled to 8 bits by its 99.5th percentile (NaN → 0)."""
    a = np.nan_to_num(np.asarray(amplitude, dtype=np.float64), nan=0.0)
    top = float(np.percentile(a, _SCALE_PERCENTILE))
    if top <= 0.0:
        return np.zeros(a.shape, dtype=np.uint8)
    return np.clip(a * (255.0 / top), 0.0, 255.0).astype(np.uint8)


# OpenCV's classic detector thresholds the image in blocks that an image narrower than this
# cannot hold (it asserts, OpenCV 4 and 5); no board is seen in so few pixels anyway.
_MIN_IMAGE_SIDE_PX = 15


def detect_checkerboard(amplitude: np.ndarray, pattern_size: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 2) float32 in OpenCV's order, or None if not found whole."""
    if min(np.shape(amplitude)[:2]) < _MIN_IMAGE_SIDE_PX:
        return None
    image = to_uint8(amplitude)
    # The classic detector (its corners can be 1.6 px off, so cornerSubPix brings them within
    # ~0.1 px first); SB is the fallback, as it finds boards the classic one misses. Both are
    # then refined by the same saddle-point fit.
    found, corners = cv2.findChessboardCorners(
        image, pattern_size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    )
    if found:
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
        corners = cv2.cornerSubPix(image, corners, (3, 3), (-1, -1), criteria)
    else:
        flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        found, corners = cv2.findChessboardCornersSB(image, pattern_size, flags=flags)
    if not found:
        return None
    a = np.nan_to_num(np.asarray(amplitude, dtype=np.float64), nan=0.0)
    return saddle_points(a, corners.reshape(-1, 2)).astype(np.float32)


# Saddle-point refinement. The window over which the white and black levels are taken (px:
# wider than a square's side in these images, 5–12 px), the Gaussian blur before the fit, and
# the half-width of the fitted patch. Simulated boards (30 per seed, seeds 0 and 1, rendered
# with 16 sub-rays, noise-free and with the sensor's noise) give 0.033–0.036 px RMS against the
# true corners for any level window of 7–13 px, blur 0.7–1.5 px and half-width 1–3 px: the
# values below sit in the middle (tuned on seed 0, checked on seed 1).
_LEVEL_WINDOW_PX = 9
_SADDLE_BLUR_PX = 1.5
_SADDLE_HALF_WIDTH_PX = 2
_SADDLE_ITERATIONS = 10


def normalise_levels(amplitude: np.ndarray, window: int = _LEVEL_WINDOW_PX) -> np.ndarray:
    """The amplitude mapped to 0 (local black) … 1 (local white).

    A ToF amplitude image of a printed board is the print's albedo times the light falling on
    it, which varies across a corner's neighbourhood with 1/r², the incidence angle and the
    LEDs' profile. A corner detector that assumes flat squares is pulled towards the brighter
    side; dividing by the local range removes that gradient.
    """
    white = gaussian_filter(maximum_filter(amplitude, window), 2.0)
    black = gaussian_filter(minimum_filter(amplitude, window), 2.0)
    return (amplitude - black) / np.maximum(white - black, 1e-12)


def saddle_points(amplitude: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Checkerboard corners (N, 2) refined to the saddle point of the image around each.

    Lucchese & Mitra (2002), "Using saddle points for subpixel feature detection in camera
    calibration targets": a checkerboard corner blurred by the optics and the pixels' box is a
    saddle of the intensity; a quadratic z = a x² + b xy + c y² + d x + e y + f fitted to the
    blurred image around it has its saddle where its gradient vanishes. The fit is re-centred on
    the saddle until it stops moving. Here on the locally normalised image
    (`normalise_levels`): on simulated 176×144 ToF boards this gives 0.025 px RMS against the
    true corners (0.034 px when the boards are rendered with 16 sub-rays per pixel instead of 64),
    where cv2.cornerSubPix gave 0.10–0.12 px, noise-free or not (its error is a bias from the
    light's gradient, not noise), and that error was what limited the principal point.
    Written here because OpenCV has no saddle-point refinement; vectorised over the corners.
    """
    blurred = gaussian_filter(normalise_levels(amplitude), _SADDLE_BLUR_PX)
    r = np.arange(-_SADDLE_HALF_WIDTH_PX, _SADDLE_HALF_WIDTH_PX + 1, dtype=np.float64)
    dy, dx = (g.ravel() for g in np.meshgrid(r, r, indexing="ij"))
    weight = np.exp(-(dx * dx + dy * dy) / (2.0 * (0.75 * _SADDLE_HALF_WIDTH_PX) ** 2))
    design = np.stack([dx * dx, dx * dy, dy * dy, dx, dy, np.ones_like(dx)], axis=1) * weight[:, None]
    fit = np.linalg.pinv(design)  # (6, patch): the weighted least-squares fit as one matrix
    points = np.asarray(corners, dtype=np.float64).reshape(-1, 2).copy()
    start = points.copy()
    for _ in range(_SADDLE_ITERATIONS):
        cols = points[:, :1] + dx[None, :]
        rows = points[:, 1:] + dy[None, :]
        patch = map_coordinates(blurred, [rows.ravel(), cols.ravel()], order=1, mode="nearest")
        a, b, c, d, e, _ = fit @ (patch.reshape(cols.shape) * weight[None, :]).T
        det = 4.0 * a * c - b * b
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.stack([(b * e - 2.0 * c * d) / det, (b * d - 2.0 * a * e) / det], axis=1)
        # A saddle has det < 0; elsewhere (or where the fit runs away) keep the point.
        step[~(det < 0.0) | ~np.all(np.isfinite(step), axis=1)] = 0.0
        points += np.clip(step, -1.0, 1.0)
        if np.max(np.abs(step), initial=0.0) < 1e-4:
            break
    # A corner that wandered more than a pixel from the detector's is not trusted: keep that one.
    lost = np.hypot(*(points - start).T) > 1.0
    points[lost] = start[lost]
    return points


@dataclass
class IntrinsicsResult:
    """What `calibrate_intrinsics` found.

    camera: the calibrated Camera. rms_px: OpenCV's RMS reprojection error over all corners.
    per_view_rms_px: RMS per used image, by name. used: names of the images whose board was
    found and kept. skipped: names of the images where it was not. rejected: images whose
    board was found but fitted far worse than the others (outliers), with their RMS.
    poses: each used image's board pose camera_T_board (4×4, metres), as the fit found it.
    """

    camera: Camera
    rms_px: float
    per_view_rms_px: dict[str, float]
    used: list[str]
    skipped: list[str] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)
    poses: dict[str, np.ndarray] = field(default_factory=dict)

    def quality(self) -> dict:
        """The numbers stored in a calibration file's `quality` section."""
        return {
            "intrinsics_rms_px": float(self.rms_px),
            "intrinsics_views": len(self.used),
            "intrinsics_skipped": list(self.skipped),
            "intrinsics_rejected": list(self.rejected),
        }


def calibrate_intrinsics(
    images: Sequence[AmplitudeImage],
    board: Checkerboard = Checkerboard(),
    *,
    fix_k3: bool = True,
) -> IntrinsicsResult:
    """Fit K and the distortion to the checkerboards found in `images` (cv2.calibrateCamera).

    Args:
        images: amplitude images of one camera without mirrors, all of one size.
        board: the printed board (pattern size and square size in metres).
        fix_k3: keep k3 = 0 (the SR4000 lens models have none; at 176×144 it is poorly
            determined and trades off against k1, k2).

    Raises:
        CalibrationError: images of different sizes, or fewer than MIN_VIEWS boards found
            (naming the images where none was).
    """
    if not images:
        raise CalibrationError("no images given for the intrinsic calibration")
    shape = images[0].amplitude.shape
    object_points, image_points, used, skipped = [], [], [], []
    for image in images:
        if image.amplitude.shape != shape:
            raise CalibrationError(
                f"image is {image.amplitude.shape}, the first one {shape}: one camera only",
                image.name,
            )
        corners = detect_checkerboard(image.amplitude, board.pattern_size)
        if corners is None:
            skipped.append(image.name)
            continue
        object_points.append(board.object_points())
        image_points.append(corners.reshape(-1, 1, 2))
        used.append(image.name)
    if len(used) < MIN_VIEWS:
        listed = ", ".join(skipped[:5]) + (" ..." if len(skipped) > 5 else "")
        raise CalibrationError(
            f"checkerboard {board.pattern_size[0]}×{board.pattern_size[1]} found in "
            f"{len(used)} of {len(images)} images, need {MIN_VIEWS}; not found in: {listed}"
        )
    height, width = shape
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-12)
    rejected: list[str] = []
    while True:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            object_points, image_points, (width, height), None, None, flags=flags, criteria=criteria
        )
        per_view = {}
        for name, obj, img, r, t in zip(used, object_points, image_points, rvecs, tvecs):
            projected, _ = cv2.projectPoints(obj, r, t, K, dist)
            per_view[name] = float(np.sqrt(np.mean(np.sum((projected - img) ** 2, axis=-1))))
        # Robust step: a view far worse than the others (a corner detected off the board's
        # true corner, e.g. at a mixed pixel) is dropped and the fit repeated.
        errors = np.array([per_view[n] for n in used])
        worst = int(np.argmax(errors))
        limit = max(OUTLIER_FACTOR * float(np.median(errors)), MIN_OUTLIER_PX)
        if errors[worst] <= limit or len(used) <= MIN_VIEWS:
            break
        rejected.append(f"{used[worst]} (view RMS {errors[worst]:.3f} px)")
        for items in (used, object_points, image_points):
            del items[worst]
    d = np.asarray(dist, dtype=np.float64).ravel()
    d = np.concatenate([d, np.zeros(max(0, 5 - len(d)))])[:5]
    coeffs = (float(d[0]), float(d[1]), float(d[2]), float(d[3]), float(d[4]))
    camera = Camera(width, height, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), coeffs)
    if not math.isfinite(rms):
        raise CalibrationError("cv2.calibrateCamera did not converge")
    inside = 0 <= camera.cx < width and 0 <= camera.cy < height
    if rms > SUSPECT_RMS_PX or not inside:
        # A board size that is not the printed one still finds a part of the board (3x3 inner
        # corners in an 8x6 board: 3.2 px RMS, the principal point outside the image).
        warnings.warn(OmnitofWarning(
            f"the intrinsics fit badly: {rms:.2f} px RMS, principal point ({camera.cx:.1f}, {camera.cy:.1f}) px "
            f"in a {width}x{height} image; is the board {board.cols}x{board.rows} squares as printed (--board)?"),
            stacklevel=2)
    poses = {}
    for name, r, t in zip(used, rvecs, tvecs):
        pose = np.eye(4)
        pose[:3, :3] = cv2.Rodrigues(np.asarray(r, dtype=np.float64))[0]
        pose[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
        poses[name] = pose
    return IntrinsicsResult(camera, float(rms), per_view, used, skipped, rejected, poses)
