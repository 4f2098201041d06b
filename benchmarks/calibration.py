"""Calibration accuracy against the number of images and the image noise (simulated).

For the default rig (`omnitof.sensor.design.default_rig`), renders checkerboard and four-dot target
images with `omnitof.calibration.targets` (the sensor's noise model, `tof.SensorNoise`, with
its standard deviations multiplied by NOISE: the gain divided by NOISE², the read noise times
NOISE), calibrates, and compares with the simulator's true geometry:

1. intrinsics: RMS reprojection error, focal-length error, principal-point error, and the
   largest pixel error over the image (true rays projected with the calibrated model);
2. mirrors, with the true intrinsics (to isolate the mirror step): per cell the worst mirror's
   normal error (degrees) and |plane distance error| (mm), mean over the seeds;
3. mirrors with the calibrated intrinsics (15 boards), the whole chain.

Usage: python benchmarks/calibration.py [--seeds 2] [--quick]
       python benchmarks/calibration.py --refine [--seeds 5]   # issue 16: the joint refinement
                                                               # and the distance correction
                                                               # (benchmarks/calibration_refine.py)
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from omnitof.calibration import CalibrationError
from omnitof.calibration.intrinsics import calibrate_intrinsics
from omnitof.calibration.mirror_planes import calibrate_mirrors
from omnitof.calibration.targets import render_checkerboard_images, render_dot_images
from omnitof.sensor.design import default_rig
from omnitof.sensor.mirrors import assign_pixels
from omnitof.sensor.tof import SensorNoise


def noisy_sensor(factor: float) -> SensorNoise:
    base = SensorNoise()
    return SensorNoise(electrons_per_unit=base.electrons_per_unit / factor**2,
                       read_noise=base.read_noise * factor)


def mirror_errors(camera_used, camera, mirrors, images):
    result = calibrate_mirrors(camera_used, images, [m.name for m in mirrors],
                               [m.plane for m in mirrors], assign_pixels(camera, mirrors))
    angles, dds = [], []
    for estimate, mirror in zip(result.estimates, mirrors):
        cos = float(np.clip(estimate.plane.normal @ mirror.plane.normal, -1.0, 1.0))
        angles.append(math.degrees(math.acos(cos)))
        dds.append(abs(1000.0 * (estimate.plane.d - mirror.plane.d)))
    return max(angles), max(dds), angles, dds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="fewer cells (a smoke run)")
    parser.add_argument("--refine", action="store_true",
                        help="the joint refinement against the closed form (seeds 0..N-1) and the distance correction")
    args = parser.parse_args()
    if args.refine:
        from calibration_refine import distance_table, refinement_table  # beside this script

        refinement_table(range(args.seeds))
        distance_table()
        return
    rig = default_rig()
    camera, mirrors = rig.camera, rig.mirrors
    noises = [1.0, 4.0] if args.quick else [1.0, 4.0, 16.0, 64.0]
    placements = [2, 4] if args.quick else [2, 4, 8, 16]
    boards = [8, 15] if args.quick else [8, 15, 30]
    started = time.perf_counter()

    print("## Intrinsics (checkerboard 8x6 squares of 35 mm, 176x144, wide lens), mean over seeds")
    print("| noise x | boards | RMS px | fx err % | fy err % | pp err px | max px err |")
    print("|---|---|---|---|---|---|---|")
    calibrated = {}
    for noise in noises:
        for n in boards:
            rows = []
            for seed in range(args.seeds):
                images, _ = render_checkerboard_images(camera, n, seed=100 + seed, sensor=noisy_sensor(noise))
                result = calibrate_intrinsics(images)
                c = result.camera
                v, u = np.mgrid[4:140:8, 4:172:8]
                px = np.stack([u.ravel(), v.ravel()], axis=1).astype(float)
                worst = float(np.nanmax(np.linalg.norm(c.project(camera.rays(px)) - px, axis=1)))
                rows.append((result.rms_px, 100 * (c.fx / camera.fx - 1), 100 * (c.fy / camera.fy - 1),
                             math.hypot(c.cx - camera.cx, c.cy - camera.cy), worst))
                if n == 15:
                    calibrated[(noise, seed)] = c
            m = np.mean(np.abs(rows), axis=0)
            print(f"| {noise:g} | {n} | {m[0]:.3f} | {m[1]:.2f} | {m[2]:.2f} | {m[3]:.2f} | {m[4]:.2f} |")

    print()
    print("## Mirrors, true intrinsics: worst mirror's normal error (deg) / |d error| (mm), mean over seeds")
    print("| noise x | " + " | ".join(f"{p} placements" for p in placements) + " |")
    print("|---|" + "---|" * len(placements))
    chain = {}
    failures: list[str] = []
    for noise in noises:
        cells = {p: [] for p in placements}
        for seed in range(args.seeds):
            images, truth = render_dot_images(camera, mirrors, max(placements), seed=10 + seed,
                                              sensor=noisy_sensor(noise))
            per_mirror = {}
            for image, (k, _) in zip(images, truth):
                per_mirror.setdefault(k, []).append(image)
            for p in placements:
                subset = [im for k in sorted(per_mirror) for im in per_mirror[k][:p]]
                try:
                    angle, dd, _, _ = mirror_errors(camera, camera, mirrors, subset)
                    cells[p].append((angle, dd))
                except CalibrationError as err:  # stops with a clear message: count it
                    cells[p].append(None)
                    failures.append(f"noise x{noise:g}, seed {seed}, {p} placements: {err}")
                if p == 8 and (noise, seed) in calibrated:
                    try:
                        chain[(noise, seed)] = mirror_errors(calibrated[(noise, seed)], camera, mirrors, subset)
                    except CalibrationError as err:
                        failures.append(f"whole chain, noise x{noise:g}, seed {seed}: {err}")
        texts = []
        for p in placements:
            ok = [c for c in cells[p] if c is not None]
            text = f"{np.mean([a for a, _ in ok]):.3f} / {np.mean([d for _, d in ok]):.2f}" if ok else "—"
            if len(ok) < len(cells[p]):
                text += f" ({len(cells[p]) - len(ok)} of {len(cells[p])} failed)"
            texts.append(text)
        print(f"| {noise:g} | " + " | ".join(texts) + " |")

    print()
    print("## Whole chain: calibrated intrinsics (15 boards), 8 placements per mirror")
    print("| noise x | seed | normal err deg (front, left, back, right) | d err mm (same order) |")
    print("|---|---|---|---|")
    for (noise, seed), (_, _, angles, dds) in sorted(chain.items()):
        print(f"| {noise:g} | {seed} | " + ", ".join(f"{a:.3f}" for a in angles) + " | "
              + ", ".join(f"{d:.2f}" for d in dds) + " |")
    if failures:
        print()
        print("Runs that stopped (CalibrationError):")
        for text in failures:
            print(f"- {text}")
    print()
    print(f"total {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
