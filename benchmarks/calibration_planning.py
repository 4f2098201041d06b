"""Checkerboards at planned poses against random ones: the intrinsics of the closed form.

For each seed, 30 boards of the default rig's camera at random poses (`targets.checkerboard_poses`)
and at planned ones (`targets.planned_checkerboard_poses`), rendered with the sensor's noise and
calibrated by `calibrate_intrinsics` (OpenCV); errors against the true camera, and the standard
deviations that `calibration.planning` predicts for the poses (corner error 0.0165 px per
coordinate, the saddle detector's scatter on rendered boards).

Usage: python benchmarks/calibration_planning.py [--seeds 0 1 2 3 4] [--boards 30]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from omnitof.calibration.intrinsics import calibrate_intrinsics
from omnitof.calibration.planning import board_information, predicted_covariance
from omnitof.calibration.targets import Checkerboard, render_checkerboard_images
from omnitof.sensor.design import default_rig

CORNER_SIGMA_PX = 0.0165


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--boards", type=int, default=30)
    args = parser.parse_args()
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


if __name__ == "__main__":
    main()
