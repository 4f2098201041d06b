"""The joint refinement (issue 16) against the closed-form chain, and the distance calibration.

1. Refinement: for each seed, the demo's calibration (`calibration.simulated`: 30 boards,
   8 dot placements per mirror, and for the refinement 2 plain boards per pair of neighbouring
   mirrors) with and without the joint refinement; errors against the simulator's true rig and
   the refinement's reported standard deviations.
2. Distance calibration: flat matte walls rendered through the mirrors at 0.5–4.5 m
   (reflectances 0.2, 0.5, 0.85), with a systematic distance error injected into the rendered
   distances (the functional form the simulator's error model has: a wiggling curve of period a
   quarter of the unambiguous range, an amplitude-dependent offset, a per-pixel fixed pattern;
   see `injected_error`). Walls at every other distance fit `DistanceCorrection`, the walls in
   between test it; error = measured (or corrected) − true path length, pixels on the wall.

Usage: python benchmarks/calibration_refine.py [--seeds 0 1 2 3 4] [--skip-refine] [--skip-distance]
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


def refinement_table(seeds) -> None:
    rig = default_rig()
    print("## Joint refinement vs the closed-form chain (30 boards, 8 placements per mirror, "
          "2 two-mirror boards per pair)")
    print("| seed | closed form: fx % / pp px / worst normal ° / worst d mm | refined: fx % / fy % / "
          "pp px (cx, cy) / worst normal ° / worst d mm | reported σ: cx, cy px / normals ° / d mm | refine s |")
    print("|---|---|---|---|---|")
    for seed in seeds:
        closed, _ = calibrate_from_simulation(renderer_of(rig), seed=seed, refine=False)
        started = time.perf_counter()
        refined, report = calibrate_from_simulation(renderer_of(rig), seed=seed, refine=True)
        seconds = time.perf_counter() - started
        a, b = errors(closed, rig), errors(refined, rig)
        std = report["std"]
        print(f"| {seed} | {a['fx']:+.3f} / {a['pp']:.3f} / {a['normal']:.3f} / {a['d']:.2f} | "
              f"{b['fx']:+.3f} / {b['fy']:+.3f} / {b['pp']:.3f} ({b['cx']:+.3f}, {b['cy']:+.3f}) / "
              f"{b['normal']:.3f} / {b['d']:.2f} | {std['camera']['cx']:.3f}, {std['camera']['cy']:.3f} / "
              f"{max(m['normal_deg'] for m in std['mirrors'].values()):.3f} / "
              f"{max(m['d_mm'] for m in std['mirrors'].values()):.3f} | {seconds:.0f} |", flush=True)


# --- distance calibration ------------------------------------------------------------------

UNAMBIGUOUS = 5.0  # metres at the SR4000's 30 MHz


def injected_error(seed: int, shape):
    """A systematic error of the simulator's functional form (metres): wiggling of period
    U/4 (first and second harmonic of it), amplitude term growing by 8 mm per decade of
    darkness below 1000 sample units, per-pixel fixed pattern N(0, 3 mm)."""
    pattern = np.random.default_rng(seed).normal(0.0, 0.003, shape)
    period = UNAMBIGUOUS / 4.0

    def error(d, a):
        wiggle = 0.012 * np.sin(2 * np.pi * d / period) + 0.004 * np.sin(4 * np.pi * d / period + 0.7)
        amp = 0.008 * np.log10(1000.0 / np.maximum(a, 1.0))
        return wiggle + amp + pattern

    return error


def wall_frames(rig, distances, reflectances, seed):
    """Per (distance, reflectance, mirror): a flat wall facing the mirror's view, rendered with
    the sensor's noise; yields (frame, wall normal, wall c) in the camera frame."""
    from omnitof.calibration.targets import PlainBoard, Room, look_at_pose, render_target
    from omnitof.sensor.mirrors import viewing_rays

    camera, mirrors = rig.camera, rig.mirrors
    labels = rig.masks(3.0)
    room = Room(half_width=10.0)  # the default room's walls (2.5 m) would hide walls beyond them
    rays = viewing_rays(camera, mirrors, labels)
    for i, dist in enumerate(distances):
        albedo = reflectances[i % len(reflectances)]
        for k, mirror in enumerate(mirrors):
            sel = labels == k
            origin = np.nanmean(rays.origins[sel], axis=0)
            out = np.nanmean(rays.directions[sel], axis=0)
            out[2] = 0.0
            out /= np.linalg.norm(out)
            pose = look_at_pose(origin + dist * out, -out, 0.0)
            wall = PlainBoard(width=12.0, height=6.0, reflectance=albedo)
            frame, _ = render_target(camera, wall, pose, mirrors, rng=np.random.default_rng([seed, i, k]),
                                     sensor=rig.sensor, room=room)
            yield frame, pose[:3, 2], float(pose[:3, 2] @ pose[:3, 3])


def distance_table(seed: int = 0) -> None:
    from omnitof.calibration.distance import DistanceCorrection, samples_from_plane

    rig = default_rig()
    shape = rig.camera.shape
    error = injected_error(seed, shape)
    fit_d = np.arange(0.5, 4.51, 0.25)
    test_d = fit_d[:-1] + 0.125
    refl = [0.2, 0.5, 0.85]

    # The walls' true poses; the geometry is the refined calibration's (seed 0), so its errors
    # are in the fit as they would be in practice.
    cal, _ = calibrate_from_simulation(renderer_of(rig), seed=seed)
    labels = rig.masks(3.0)

    def samples(distances, reflect):
        out = []
        for frame, normal, c in wall_frames(rig, distances, reflect, seed):
            measured = frame.distance.astype(np.float64)
            measured = measured + error(measured, frame.amplitude)
            amp = np.where(frame.amplitude > 50, frame.amplitude, np.nan)  # the extraction's rough filter
            out.append(samples_from_plane(cal.camera, cal.planes, labels, measured, amp, normal, c))
        return [np.concatenate(x) for x in zip(*out)]

    started = time.perf_counter()
    m, t, a, p = samples(fit_d, refl)
    correction = DistanceCorrection.fit(m, t, a, p, shape)
    # Tested against the truth: the path lengths of the true rig. Per test wall (one distance,
    # one mirror's view) the median signed error is the systematic part; single readings also
    # carry the sensor's noise (tens of mm on dark walls at 4 m), which no calibration removes.
    mt, tt, at, pt, wall, injected = [], [], [], [], [], []
    for w, (frame, normal, c) in enumerate(wall_frames(rig, test_d, refl[::-1], seed + 1)):
        raw = frame.distance.astype(np.float64)
        measured = raw + error(raw, frame.amplitude)
        amp = np.where(frame.amplitude > 50, frame.amplitude, np.nan)
        got = samples_from_plane(rig.camera, rig.planes, labels, measured, amp, normal, c)
        for lst, v in zip((mt, tt, at, pt), got):
            lst.append(v)
        wall.append(np.full(len(got[0]), w))
        injected.append((measured - raw).ravel()[got[3]])
    mt, tt, at, pt, wall, injected = (np.concatenate(v) for v in (mt, tt, at, pt, wall, injected))
    corrected = correction.correct(mt, at, pt)
    before = np.abs(mt - tt)
    after = np.abs(corrected - tt)
    print()
    print("## Distance calibration on matte walls (injected error of the simulator's form)")
    print(f"fit: {len(m)} samples at {len(fit_d)} distances; test: {len(mt)} samples at {len(test_d)} other "
          f"distances × {len(rig.mirrors)} mirrors")
    print("| | systematic: median over walls of |median error| (mm) | worst wall (mm) | single readings: median abs error (mm) | 90th percentile (mm) |")
    print("|---|---|---|---|---|")
    for label, e in (("before correction", mt - tt), ("after correction", corrected - tt)):
        per_wall = np.array([np.median(e[wall == w]) for w in np.unique(wall)])
        print(f"| {label} | {1000 * np.median(np.abs(per_wall)):.2f} | {1000 * np.max(np.abs(per_wall)):.2f} | "
              f"{1000 * np.median(np.abs(e)):.2f} | {1000 * np.percentile(np.abs(e), 90):.2f} |")
    model = correction.error(mt, at, pt)
    print(f"the fitted error against the injected one, per reading: RMS difference "
          f"{1000 * np.sqrt(np.mean((model - injected) ** 2)):.2f} mm (injected RMS "
          f"{1000 * np.sqrt(np.mean(injected ** 2)):.2f} mm)")
    print(f"total {time.perf_counter() - started:.0f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--skip-refine", action="store_true")
    parser.add_argument("--skip-distance", action="store_true")
    args = parser.parse_args()
    if not args.skip_refine:
        refinement_table(args.seeds)
    if not args.skip_distance:
        distance_table()


if __name__ == "__main__":
    main()
