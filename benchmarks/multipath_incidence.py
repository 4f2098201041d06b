"""Where multipath errs: the scan bins' errors on matte walls by the angle at which the wall is
seen, and what dropping the grazing bins (`ScanSettings.max_incidence_deg`) leaves.

Per world, the 24 frames of benchmarks/tof_errors.py (seed 0, default rig, 4 sub-rays, noise on)
rendered with the camera's errors as `--tof-errors` says (default: multipath alone), scans from
the true rig's extractor with the pixel filter on and no distance correction. Each 1° bin whose
nearest surface at the slice height is matte is compared with the exact horizontal distance
(World.horizontal_distance at the frame's true pose); its true incidence comes from the floor
plan too: for a straight wall dr/dθ = r·tan(α), differenced over ±0.05°.

    python benchmarks/multipath_incidence.py [--worlds corridor1 corridor2 office room]
        [--tof-errors multipath] [--max-incidence 60 65 70 75]
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from tof_errors import frames

from omnitof.calibration import Calibration
from omnitof.scan import ScanExtractor
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.worlds import load_world

BANDS = [(0, 45), (45, 60), (60, 70), (70, 75), (75, 80), (80, 90)]


def matte_bins(world, renderer, extractor, poses, ranges):
    """(error m, true incidence deg) of every matte bin with a reading, over the frames."""
    h = extractor.settings.height
    out = []
    for pose, r in zip(poses, ranges):
        b = extractor.angles + pose[2]
        truth = world.horizontal_distance(pose[:2], b, h)
        dth = math.radians(0.05)
        slope = (world.horizontal_distance(pose[:2], b + dth, h) - world.horizontal_distance(pose[:2], b - dth, h)) / (2 * dth)
        with np.errstate(invalid="ignore"):
            incidence = np.degrees(np.arctan(np.abs(slope) / truth))
        directions = np.column_stack([np.cos(b), np.sin(b), np.zeros(len(b))])
        _, names = renderer.first_surface(np.tile([pose[0], pose[1], h], (len(b), 1)), directions)
        matte = np.array([bool(n) and world.materials[n].kind == "matte" for n in names])
        ok = matte & np.isfinite(r) & np.isfinite(truth) & np.isfinite(incidence)
        out.append(np.column_stack([(r - truth)[ok], incidence[ok]]))
    return np.concatenate(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["corridor1", "corridor2", "office", "room"])
    parser.add_argument("--tof-errors", default="multipath")
    parser.add_argument("--max-incidence", nargs="+", type=float, default=[60.0, 65.0, 70.0, 75.0])
    args = parser.parse_args()
    errors = ToFErrors.parse(args.tof_errors)
    print("| world | true incidence | bins | share of bins | within 5 cm | median error mm | share of the bins off by ≥ 5 cm |")
    print("|---|---|---|---|---|---|---|")
    summary = []
    for name in args.worlds:
        world = load_world(name)
        renderer, poses, fr = frames(world, errors, 24)
        d = np.stack([f.distance for f in fr])
        a = np.stack([f.amplitude for f in fr])
        cal = Calibration.from_rig(renderer.rig)
        e, incidence = matte_bins(world, renderer, ScanExtractor.from_calibration(cal), poses,
                                  ScanExtractor.from_calibration(cal).extract_many(d, a)).T
        bad = np.abs(e) >= 0.05
        for lo, hi in BANDS:
            m = (incidence >= lo) & (incidence < hi)
            if m.any():
                print(f"| {name} | {lo}–{hi}° | {m.sum()} | {100 * m.mean():.1f} % | {100 * np.mean(~bad[m]):.1f} % | "
                      f"{1000 * np.median(e[m]):+.1f} | {100 * np.sum(m & bad) / max(1, bad.sum()):.1f} % |")
        row = [f"{len(e)}, {100 * np.mean(~bad):.1f} %"]
        for limit in args.max_incidence:
            ex = ScanExtractor.from_calibration(cal, max_incidence_deg=limit)
            k, _ = matte_bins(world, renderer, ex, poses, ex.extract_many(d, a)).T
            row.append(f"{len(k)}, {100 * np.mean(np.abs(k) < 0.05):.1f} %")
        summary.append((name, row))
    print("\nBins (matte, with a reading) and their share within 5 cm, by `max_incidence_deg`:\n")
    print("| world | off | " + " | ".join(f"{v:g}°" for v in args.max_incidence) + " |")
    print("|---|---|" + "---|" * len(args.max_incidence))
    for name, row in summary:
        print(f"| {name} | " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
