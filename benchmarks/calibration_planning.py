"""Checkerboards at planned poses against random ones: the intrinsics of the closed form.

For each seed, 30 boards of the default rig's camera at random poses (`targets.checkerboard_poses`)
and at planned ones (`targets.planned_checkerboard_poses`), rendered with the sensor's noise and
calibrated by `calibrate_intrinsics` (OpenCV); errors against the true camera, and the standard
deviations that `calibration.planning` predicts for the poses (corner error 0.0165 px per
coordinate, the saddle detector's scatter on rendered boards).

With `--nominal`, the plan made from a nominal camera (a data sheet's: 3 % long in fx and fy,
the principal point 2 px off, k1 and k2 20 % low) against a plan in two rounds as a user follows
it (`omnitof calibrate plan-boards`, then `plan-boards --taken`): the first `--first` boards
planned with the nominal camera, calibrated, and the rest planned from that calibration with
the boards taken counted; and against a plan made with the true camera (which no user has).
Besides the intrinsics' errors: the calibrated camera's projection error over the image (each
pixel of a 12 × 10 grid, its true ray projected by the calibrated camera), mean and largest,
and how many grid pixels the calibrated camera cannot reach (beyond its distortion's fold).

Usage: python benchmarks/calibration_planning.py [--seeds 0 1 2 3 4] [--boards 30]
    [--nominal [--first 10]]
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace

import numpy as np

from omnitof.calibration.intrinsics import calibrate_intrinsics
from omnitof.calibration.planning import GRID, board_information, predicted_covariance, projection_weight
from omnitof.calibration.targets import (
    Checkerboard, planned_checkerboard_poses, render_board_views, render_checkerboard_images,
)
from omnitof.sensor.camera import Camera
from omnitof.sensor.design import default_rig

CORNER_SIGMA_PX = 0.0165


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--boards", type=int, default=30)
    parser.add_argument("--nominal", action="store_true", help="plan from a nominal camera, in one or two rounds")
    parser.add_argument("--first", type=int, default=10, help="with --nominal: boards in the first round")
    args = parser.parse_args()
    if args.nominal:
        nominal_plans(args.seeds, args.boards, args.first)
        return
    rig = default_rig()
    camera, board = rig.camera, Checkerboard()
    print(f"## Closed-form intrinsics from {args.boards} boards, random against planned poses")
    print("| seed | poses | predicted σ cx, cy px / fx % | fx % | fy % | principal point px (cx, cy) | boards used | s |")
    print("|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        for planned in (False, True):
            started = time.perf_counter()
            images, poses = render_checkerboard_images(camera, args.boards, seed, sensor=rig.sensor, planned=planned)
            result = calibrate_intrinsics(images)
            seconds = time.perf_counter() - started
            sigma = np.sqrt(np.diag(predicted_covariance(
                [board_information(camera, board.object_points(), p) for p in poses], CORNER_SIGMA_PX)))
            got = result.camera
            dx, dy = got.cx - camera.cx, got.cy - camera.cy
            print(f"| {seed} | {'planned' if planned else 'random'} | {sigma[2]:.3f}, {sigma[3]:.3f} / "
                  f"{100 * sigma[0] / camera.fx:.3f} | {100 * (got.fx / camera.fx - 1):+.3f} | "
                  f"{100 * (got.fy / camera.fy - 1):+.3f} | {math.hypot(dx, dy):.3f} ({dx:+.3f}, {dy:+.3f}) | "
                  f"{len(result.used)} | {seconds:.0f} |", flush=True)


def nominal_camera(camera: Camera) -> Camera:
    k1, k2, p1, p2, k3 = camera.dist
    return replace(camera, fx=1.03 * camera.fx, fy=1.03 * camera.fy, cx=camera.cx + 2.0, cy=camera.cy - 2.0,
                   dist=(0.8 * k1, 0.8 * k2, p1, p2, k3))


def projection_errors(truth: Camera, got: Camera) -> tuple[float, float, int]:
    """Mean and largest pixel error of `got` projecting the true rays of a grid of pixels, and
    how many of those rays `got` cannot project at all (beyond its distortion's fold)."""
    u, v = np.meshgrid(np.linspace(0, truth.width - 1, GRID[0]), np.linspace(0, truth.height - 1, GRID[1]))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    error = np.hypot(*(got.project(truth.rays(pixels).astype(np.float64)) - pixels).T)
    return float(np.nanmean(error)), float(np.nanmax(error)), int(np.isnan(error).sum())


def nominal_plans(seeds: list[int], boards: int, first: int) -> None:
    rig = default_rig()
    camera, board = rig.camera, Checkerboard()
    nominal = nominal_camera(camera)
    points = board.object_points()
    weight = projection_weight(camera)
    print(f"## Boards planned from a nominal camera: {boards} in one round, or {first} and then "
          f"{boards - first} from a first calibration")
    print("| seed | plan | predicted projection σ px (RMS over the image) | fx % | principal point px | "
          "projection error px, mean (largest) |")
    print("|---|---|---|---|---|---|")
    for seed in seeds:
        one_round = planned_checkerboard_poses(nominal, board, boards, seed)
        opening = planned_checkerboard_poses(nominal, board, first, seed)
        images = render_board_views(camera, opening, seed, sensor=rig.sensor)
        calibrated = calibrate_intrinsics(images)
        second = planned_checkerboard_poses(calibrated.camera, board, boards - first, seed + 1000,
                                            taken=list(calibrated.poses.values()))
        plans = {"nominal, one round": (one_round, None),
                 "nominal, then from the first calibration": (opening + second, images),
                 "true camera (no user has it)": (planned_checkerboard_poses(camera, board, boards, seed), None)}
        for name, (poses, reuse) in plans.items():
            if reuse is None:
                views = render_board_views(camera, poses, seed, sensor=rig.sensor)
            else:  # the first round's images are the ones already taken
                views = reuse + render_board_views(camera, poses[first:], seed, sensor=rig.sensor, first_index=first)
            got = calibrate_intrinsics(views).camera
            cov = predicted_covariance([board_information(camera, points, p) for p in poses], CORNER_SIGMA_PX)
            mean, largest, folded = projection_errors(camera, got)
            print(f"| {seed} | {name} | {math.sqrt(np.trace(cov @ weight)):.3f} | "
                  f"{100 * (got.fx / camera.fx - 1):+.3f} | {math.hypot(got.cx - camera.cx, got.cy - camera.cy):.3f} | "
                  f"{mean:.3f} ({largest:.3f}){f', {folded} beyond the fold' if folded else ''} |", flush=True)


if __name__ == "__main__":
    main()
