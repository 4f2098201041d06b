"""Where to hold the checkerboards: board poses chosen for what they tell about the intrinsics.

Random board poses leave the principal point to chance: with 30 boards of 7×5 corners at
176×144 its predicted standard deviation is 0.06–0.075 px, and the image's outer parts, where
the mirrors are, get few corners, so the distortion there is poorly pinned (BENCHMARKS.md,
"Board poses planned for the intrinsics"). Following the idea of
Peng & Sturm's calibration wizard (ICCV 2019), a set of boards is chosen from many feasible
candidates so that the predicted uncertainty of the calibrated projection, averaged over the
image, is smallest.

Model (written here: OpenCV gives the Jacobians, no library does the selection). Each board's
corners have independent image errors of σ px. `cv2.projectPoints` gives the Jacobian of the
corners' pixels with respect to the board's pose (6) and the intrinsics θ (fx, fy, cx, cy, k1,
k2, p1, p2; k3 is held at 0 as `calibrate_intrinsics` does). The board's pose is unknown, so
its information about θ is the Schur complement

    I_b = A − B C⁻¹ Bᵀ,  A = J_θᵀJ_θ, B = J_θᵀJ_pose, C = J_poseᵀJ_pose,

and n boards give Σ = σ²(Σ_b I_b)⁻¹. A pixel's projection moves with θ by G (2×8, the
Jacobian of projecting a fixed ray), so its variance is trace(G Σ Gᵀ); averaged over a grid of
pixels that is trace(Σ W) with W = mean GᵀG. Boards are added one at a time, each the
candidate that lowers trace(Σ W) most (greedy; a weak ridge makes the first steps defined).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np

from omnitof.sensor.camera import Camera

# Intrinsic parameters planned for, in projectPoints' Jacobian order after rvec, tvec:
# fx, fy, cx, cy, k1, k2, p1, p2.
N_INTRINSICS = 8
_INTRINSIC_COLUMNS = slice(6, 6 + N_INTRINSICS)
# The grid of pixels over which the projection's uncertainty is averaged.
GRID = (12, 10)


def _opencv_model(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])
    return K, np.asarray(camera.dist, dtype=np.float64)


def board_information(camera: Camera, object_points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The 8×8 information (per unit corner variance) that one board at `pose` (camera_T_board,
    4×4) gives about the intrinsics, its own pose marginalised out (module docstring)."""
    K, dist = _opencv_model(camera)
    rvec, _ = cv2.Rodrigues(np.asarray(pose[:3, :3], dtype=np.float64))
    points = np.asarray(object_points, dtype=np.float64).reshape(-1, 3)
    _, jacobian = cv2.projectPoints(points, rvec, np.asarray(pose[:3, 3], dtype=np.float64), K, dist)
    j_pose, j_theta = jacobian[:, :6], jacobian[:, _INTRINSIC_COLUMNS]
    a, b, c = j_theta.T @ j_theta, j_theta.T @ j_pose, j_pose.T @ j_pose
    return a - b @ np.linalg.solve(c, b.T)


def projection_weight(camera: Camera, grid: tuple[int, int] = GRID) -> np.ndarray:
    """W = mean over a grid of pixels of GᵀG, G the Jacobian of a fixed ray's pixel with
    respect to the intrinsics: trace(Σ W) is the mean variance of a projected pixel."""
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, grid[0]), np.linspace(0, camera.height - 1, grid[1]))
    rays = camera.rays(np.column_stack([u.ravel(), v.ravel()])).astype(np.float64)
    # A corner pixel can lie beyond the distortion's fold of a rough camera (a data sheet's, or
    # one calibrated from a few boards): no ray reaches it, so it has no uncertainty to plan for.
    # Left in, its NaN made every candidate's cost NaN and the plan a random pick.
    rays = rays[np.isfinite(rays).all(axis=1)]
    if len(rays) == 0:
        from omnitof.calibration import CalibrationError

        raise CalibrationError("no pixel of the planning grid has a ray: the camera's distortion folds everywhere")
    K, dist = _opencv_model(camera)
    _, jacobian = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)
    g = jacobian[:, _INTRINSIC_COLUMNS]
    return g.T @ g / len(rays)


def plan_boards(informations: Sequence[np.ndarray], n: int, weight: np.ndarray,
                prior: np.ndarray | None = None) -> list[int]:
    """Indices of n of the candidates' informations, chosen greedily to make trace(M⁻¹ W)
    small, M the sum of the chosen informations and of `prior` (the information of boards
    already taken; module docstring)."""
    stack = np.asarray(informations, dtype=np.float64)
    if n > len(stack):
        raise ValueError(f"cannot choose {n} from {len(stack)} candidates")
    size = stack.shape[1]
    ridge = 1e-6 * float(np.mean(np.trace(stack, axis1=1, axis2=2))) / size
    total = ridge * np.eye(size)
    if prior is not None:
        total = total + np.asarray(prior, dtype=np.float64)
    free = np.ones(len(stack), dtype=bool)
    chosen: list[int] = []
    for _ in range(n):
        # trace((M + I_b)⁻¹ W) for every candidate b at once.
        cost = np.trace(np.linalg.solve(total + stack, np.broadcast_to(weight, stack.shape)), axis1=1, axis2=2)
        if not np.isfinite(cost[free]).all():
            from omnitof.calibration import CalibrationError

            raise CalibrationError("a candidate board's predicted cost is not finite (NaN in its information "
                                   "or in the weight): the camera's model cannot plan")
        cost[~free] = np.inf
        best = int(np.argmin(cost))
        chosen.append(best)
        free[best] = False
        total = total + stack[best]
    return chosen


def predicted_covariance(informations: Sequence[np.ndarray], sigma_px: float) -> np.ndarray:
    """Σ of the intrinsics (fx, fy, cx, cy, k1, k2, p1, p2) from boards with these
    informations and corner errors of sigma_px per coordinate."""
    return sigma_px**2 * np.linalg.inv(np.sum(np.asarray(informations, dtype=np.float64), axis=0))



def board_plan(camera: Camera, board: Any, n: int, seed: int, *, sigma_px: float = 0.05,
               taken: Mapping[str, np.ndarray] | None = None) -> dict[str, Any]:
    """A plan of n checkerboard views for a user to follow (`omnitof calibrate plan-boards`):
    the camera, the board, per board its pose camera_T_board, the board middle's distance and
    tilt, the pixel outline of the printed area and of the first inner corner, and the
    predicted σ of cx, cy and fx at corner errors of sigma_px: for the plan, for as many random
    poses, and, where boards were already `taken` (name -> camera_T_board, e.g.
    `IntrinsicsResult.poses`), for those alone; the plan and the random poses then count the
    taken boards too, and the plan fills in what they leave uncertain.

    Raises:
        CalibrationError: the board does not fit whole in the camera's view at the planned
            distances (BOARD_DEPTH).
    """
    from omnitof.calibration import CalibrationError
    from omnitof.calibration.targets import BOARD_DEPTH, checkerboard_poses, planned_checkerboard_poses

    taken = dict(taken or {})
    cols, rows = board.pattern_size[0] + 1, board.pattern_size[1] + 1
    try:
        poses = planned_checkerboard_poses(camera, board, n, seed, taken=list(taken.values()))
        random_poses = checkerboard_poses(camera, board, n, seed)
    except ValueError as err:
        raise CalibrationError(
            f"a {cols}x{rows} checkerboard of {board.square} m squares is not seen whole by the camera "
            f"at {BOARD_DEPTH[0]}-{BOARD_DEPTH[1]} m often enough ({err}); plan with a smaller board"
        ) from None
    x0, x1, y0, y1 = board.extent()
    outline = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])

    def outline_px(pose: np.ndarray) -> list:
        return np.round(camera.project(outline @ pose[:3, :3].T + pose[:3, 3]), 1).tolist()

    middle_in_board = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    entries = []
    for k, pose in enumerate(poses):
        rotation, origin = pose[:3, :3], pose[:3, 3]
        middle = rotation @ middle_in_board + origin
        cos_tilt = abs(float(rotation[:, 2] @ middle)) / float(np.linalg.norm(middle))
        entries.append({
            "name": f"board_{k:02d}",
            "distance_m": round(float(np.linalg.norm(middle)), 3),
            "tilt_deg": round(math.degrees(math.acos(min(1.0, cos_tilt))), 1),
            "outline_px": outline_px(pose),
            "first_corner_px": np.round(camera.project(origin[None, :])[0], 1).tolist(),
            "camera_T_board": np.round(pose, 6).tolist(),
        })
    points = board.object_points()
    spread: dict[str, Any] = {"corner_error_px": round(float(sigma_px), 4)}
    groups = [("planned", poses), ("random", random_poses)] + ([("taken", [])] if taken else [])
    for name, chosen in groups:
        cov = predicted_covariance([board_information(camera, points, p) for p in [*taken.values(), *chosen]],
                                   sigma_px)
        spread[name] = {"cx_px": round(math.sqrt(cov[2, 2]), 4), "cy_px": round(math.sqrt(cov[3, 3]), 4),
                        "fx_pct": round(100.0 * math.sqrt(cov[0, 0]) / camera.fx, 4)}
    plan = {
        "camera": {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy,
                   "cx": camera.cx, "cy": camera.cy, "dist": list(camera.dist)},
        "board": {"cols": cols, "rows": rows, "square_m": board.square},
        "frames": "camera_T_board: the board's frame (first inner corner at the origin, x along a row of "
                  "corners, z out of the board) in the camera frame (z along the optical axis), metres",
        "predicted_std": spread,
        "boards": entries,
    }
    if taken:
        plan["taken"] = [{"name": name, "outline_px": outline_px(pose)} for name, pose in taken.items()]
    return plan
