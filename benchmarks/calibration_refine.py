"""The joint refinement (issue 16) against the closed-form chain, and the distance calibration.

1. Refinement: for each seed, the demo's calibration (`calibration.simulated`: 30 boards,
   8 dot placements per mirror, and for the refinement 2 plain boards per pair of neighbouring
   mirrors) with and without the joint refinement; errors against the simulator's true rig and
   the refinement's reported standard deviations.
2. Distance calibration: the correction `calibrate_from_simulation` fits (flat walls at known
   distances, `calibration.walls`) with the simulator's default systematic errors on (issue 15:
   wiggling, amplitude offset, fixed pattern), tested on walls half-way between the fitted
   positions (0.56–6.06 m, other albedos, other noise), one frame and four averaged; error =
   measured (or corrected) − true path length of the true rig, pixels on the wall.

Usage: python benchmarks/calibration_refine.py [--seeds 0 1 2 3 4] [--skip-refine] [--skip-distance]
       [--random-boards] [--sensor-errors] [--placements 8]
"""

from __future__ import annotations

import argparse
import math
import time
from types import SimpleNamespace

import numpy as np

from omnitof.calibration import Calibration
from omnitof.calibration.simulated import calibrate_from_simulation
from omnitof.sensor.design import default_rig


def renderer_of(rig):
    return SimpleNamespace(camera=rig.camera, mirrors=rig.mirrors, rig=rig, sensor=rig.sensor,
                           robot_T_camera=rig.robot_T_camera)


def errors(cal: Calibration, rig) -> dict:
    est, true = cal.camera, rig.camera
    angles = [math.degrees(math.acos(float(np.clip(p.normal @ m.plane.normal, -1, 1))))
              for p, m in zip(cal.planes, rig.mirrors)]
    dds = [abs(1000 * (p.d - m.plane.d)) for p, m in zip(cal.planes, rig.mirrors)]
    return {"fx": 100 * (est.fx / true.fx - 1), "fy": 100 * (est.fy / true.fy - 1),
            "pp": math.hypot(est.cx - true.cx, est.cy - true.cy), "cx": est.cx - true.cx, "cy": est.cy - true.cy,
            "normal": max(angles), "d": max(dds), "angles": angles, "dds": dds}


def refinement_table(seeds, *, planned_boards: bool = True, sensor_errors: bool = False, placements: int = 8) -> None:
    rig = default_rig()
    renderer = renderer_of(rig)
    if sensor_errors:
        from omnitof.sensor.tof import SensorNoise
        from omnitof.sensor.tof_errors import ToFErrors

        renderer.sensor = SensorNoise(errors=ToFErrors.simulation_default())
    boards = "planned" if planned_boards else "random"
    errors_note = ", the simulator's default systematic distance errors (no path lengths)" if sensor_errors else ""
    print(f"## Joint refinement vs the closed-form chain (30 {boards} boards, {placements} placements per mirror, "
          f"2 two-mirror boards per pair{errors_note})")
    print("| seed | closed form: fx % / pp px / worst normal ° / worst d mm | refined: fx % / fy % / "
          "pp px (cx, cy) / worst normal ° / worst d mm | reported σ: cx, cy px / normals ° / d mm | refine s |")
    print("|---|---|---|---|---|")
    for seed in seeds:
        closed, _ = calibrate_from_simulation(renderer, seed=seed, refine=False, planned_boards=planned_boards,
                                              distance_correction=False, placements=placements)
        started = time.perf_counter()
        refined, report = calibrate_from_simulation(renderer, seed=seed, refine=True, planned_boards=planned_boards,
                                                    distance_correction=False, placements=placements)
        seconds = time.perf_counter() - started
        a, b = errors(closed, rig), errors(refined, rig)
        std = report["std"]
        print(f"| {seed} | {a['fx']:+.3f} / {a['pp']:.3f} / {a['normal']:.3f} / {a['d']:.2f} | "
              f"{b['fx']:+.3f} / {b['fy']:+.3f} / {b['pp']:.3f} ({b['cx']:+.3f}, {b['cy']:+.3f}) / "
              f"{b['normal']:.3f} / {b['d']:.2f} | {std['camera']['cx']:.3f}, {std['camera']['cy']:.3f} / "
              f"{max(m['normal_deg'] for m in std['mirrors'].values()):.3f} / "
              f"{max(m['d_mm'] for m in std['mirrors'].values()):.3f} | {seconds:.0f} |", flush=True)


# --- distance calibration ------------------------------------------------------------------


def distance_table(seed: int = 0) -> None:
    """The correction `calibrate_from_simulation` fits (walls, refined geometry) against the
    simulator's own systematic errors, on walls at distances and albedos the fit never saw."""
    from omnitof.calibration.walls import render_wall_views, wall_samples
    from omnitof.sensor.tof import SensorNoise
    from omnitof.sensor.tof_errors import ToFErrors

    rig = default_rig()
    sensor = SensorNoise(errors=ToFErrors.simulation_default())
    started = time.perf_counter()
    renderer = SimpleNamespace(**{**vars(renderer_of(rig)), "sensor": sensor})
    cal, report = calibrate_from_simulation(renderer, seed=seed)
    seconds = time.perf_counter() - started
    correction = cal.distance_correction
    truth = Calibration.from_rig(rig)
    # Half-way between the fitted positions, albedos in another order, other noise; true paths
    # from the true rig. Per wall (one distance, one mirror) the median signed error is the
    # systematic part; readings of 1 frame and of 4 frames averaged carry the sensor's noise.
    distances = np.arange(0.5625, 6.3, 0.5)
    print()
    print(f"## Distance correction of calibrate_from_simulation (seed {seed}; simulator's errors: "
          f"{', '.join(sensor.errors.switched_on)})")
    print(f"fit: {report['distance_correction']}; calibration {seconds:.0f} s")
    print("| test frames | | walls | systematic: median over walls of \\|median error\\| (mm) | worst wall (mm) | "
          "readings: median abs error (mm) | 90th percentile (mm) |")
    print("|---|---|---|---|---|---|---|")
    for frames in (1, 4):
        views = render_wall_views(rig.camera, rig.mirrors, seed + 101, sensor=sensor, distances=distances,
                                  reflectances=(0.85, 0.2, 0.5), frames=frames)
        rows = {"before": [], "after": []}
        for view in views:
            m, t, a, p = wall_samples(truth, [view])
            if len(m) < 100:
                continue
            rows["before"].append(m - t)
            rows["after"].append(correction.correct(m, a, p) - t)
        for label, errs in rows.items():
            per_wall = np.abs([np.median(e) for e in errs])
            e = np.abs(np.concatenate(errs))
            print(f"| {frames} | {label} | {len(errs)} | {1000 * np.median(per_wall):.2f} | "
                  f"{1000 * np.max(per_wall):.2f} | "
                  f"{1000 * np.median(e):.2f} | {1000 * np.percentile(e, 90):.2f} |", flush=True)
    print(f"total {time.perf_counter() - started:.0f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--skip-refine", action="store_true")
    parser.add_argument("--skip-distance", action="store_true")
    parser.add_argument("--random-boards", action="store_true", help="checkerboards at random poses, not planned")
    parser.add_argument("--sensor-errors", action="store_true",
                        help="the simulator's default systematic distance errors on (the demo's setting)")
    parser.add_argument("--placements", type=int, default=8, help="dot-target placements per mirror")
    args = parser.parse_args()
    if not args.skip_refine:
        refinement_table(args.seeds, planned_boards=not args.random_boards, sensor_errors=args.sensor_errors,
                         placements=args.placements)
    if not args.skip_distance:
        distance_table()


if __name__ == "__main__":
    main()
