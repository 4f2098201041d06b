"""Time of the demo's calibration stage: the simulated calibration of the default rig as
`omnitof demo` runs it (target images rendered, intrinsics, mirrors, joint refinement, distance
correction from walls), and the share of it spent tracing the target images. Then the time the
fitted distance correction takes on one frame (every pixel of every frame the demo extracts
scans from is corrected), its splines evaluated directly against through their basis.

Prints one line per run and the medians; the calibration's result (the mirrors' largest normal
error against the true rig) so that two builds can be checked to calibrate alike. To compare
two builds, run this script once in each (a clone at the older commit with its own install)
alternately, on an otherwise idle machine.

Usage: python benchmarks/calibration_speed.py [--runs 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import statistics
import time
import timeit

import numpy as np

import omnitof.calibration.targets as targets
from omnitof.calibration import Calibration
from omnitof.calibration.distance import _design
from omnitof.calibration.simulated import calibrate_from_simulation
from omnitof.sensor.tof import SensorNoise
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.render import Renderer, RenderSettings
from omnitof.sim.worlds import load_world


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    traced = [0.0]
    signal = targets._target_signal

    def timed_signal(*a, **k):
        start = time.perf_counter()
        try:
            return signal(*a, **k)
        finally:
            traced[0] += time.perf_counter() - start

    targets._target_signal = timed_signal
    renderer = Renderer(load_world("corridor1"), sensor=SensorNoise(errors=ToFErrors.parse("default")),
                        settings=RenderSettings(seed=args.seed))
    truth = Calibration.from_rig(renderer.rig)
    totals, tracing = [], []
    for run in range(args.runs):
        targets._SCENES.clear()  # each run pays for its sub-rays, as the demo does
        traced[0] = 0.0
        start = time.perf_counter()
        cal, _ = calibrate_from_simulation(renderer, seed=args.seed, truth=truth, refine=True)
        totals.append(time.perf_counter() - start)
        tracing.append(traced[0])
        worst = max(np.degrees(np.arccos(np.clip(abs(a.normal @ b.normal), -1, 1)))
                    for a, b in zip(cal.planes, truth.planes))
        print(f"run {run}: {totals[-1]:.1f} s, tracing target images {tracing[-1]:.1f} s; "
              f"mirror normals within {worst:.4f} deg of the truth", flush=True)
    print(f"median: {statistics.median(totals):.1f} s, tracing {statistics.median(tracing):.1f} s")

    frame = renderer.render_many(np.array([[5.0, 1.1, 0.0]]), seed=args.seed)[0]
    dc = cal.distance_correction
    d, a = frame.tof.distance.astype(np.float64).ravel(), frame.tof.amplitude.astype(np.float64).ravel()
    ok = np.isfinite(d) & np.isfinite(a) & (a > 0)
    d, a = d[ok], a[ok]

    def through_basis():
        return (_design(dc.distance_knots, d) @ dc.distance_coefficients
                + _design(dc.amplitude_knots, np.log(a)) @ dc.amplitude_coefficients)

    def direct():
        return dc.error(d, a, np.flatnonzero(ok))

    offsets = dc.pixel_offsets.ravel()[np.flatnonzero(ok)] if dc.pixel_offsets is not None else 0.0
    assert np.allclose(through_basis() + offsets, direct(), rtol=0, atol=1e-12)
    basis = statistics.median(timeit.repeat(through_basis, number=10, repeat=7)) / 10
    spline = statistics.median(timeit.repeat(direct, number=10, repeat=7)) / 10
    print(f"distance correction of one frame ({len(d)} pixels): through the basis {1e3 * basis:.1f} ms, "
          f"as error() evaluates it {1e3 * spline:.1f} ms ({spline / basis:.2f})")


if __name__ == "__main__":
    main()
