"""The ToF error budget (issue 15): what each systematic error of the camera costs the scans,
alone and all together, before and after the flying-pixel/multipath filter; and what the
effects cost the renderer.

Per world, --frames frames spread evenly over the robot's drive (sim.sequence.make_sequence,
seed 0: straight legs and turns at up to 0.6 rad/s) are rendered with the default rig (4
sub-rays, sensor noise on) once per setting of the camera's errors: none, each effect alone
(omnitof.sensor.tof_errors.SWITCHES), the simulator's default (all but multipath), all. Each frame becomes a scan with the true rig's
extractor, with the pixel filter off and on; every 1° bin whose nearest surface at the slice
height is matte is compared with the exact horizontal distance there (World.horizontal_distance
at the frame's true pose). Reported per world and setting: the median and 90th percentile of
|error| (cm) and the share within 5 cm, filter off → on.

--corrections adds rows with issue 16's distance correction (`calibration.walls`: fitted to
flat walls at known distances, four frames averaged per position) applied by the extractor:
"true" fits it with the true rig's geometry and extracts with the true rig; "estimated" is the
whole simulated calibration the demo runs (`calibrate_from_simulation`: closed form, joint
refinement, the correction) and extracts with it. "none" is no correction (the default).

--max-incidence adds rows extracted with `ScanSettings.max_incidence_deg` (omnitof.scan.grazing:
bins seen at a grazing angle dropped; 90 is off, the default).

--multipath-compensation off on adds rows extracted with the multipath compensation
(omnitof.scan.multipath) set up for the rendering camera (its LEDs, amplitude scale, frequency
and mirrors), whatever the setting: on a camera without multipath it shows what it costs.
--multipath-set KEY=VALUE ... changes its settings (`MultipathSettings` fields, values as YAML:
`visibility=true beyond_view=true`).

Speed: the renderer's phasors (tracer) and whole frames (noise and decoding too) per second on
corridor1, all effects off and all on, medians of --runs runs measured alternately in one
process.

Usage:
    python benchmarks/tof_errors.py [--frames 24] [--runs 5] [--worlds room office ...]
        [--settings default all] [--corrections none true estimated] [--max-incidence 90 70]
        [--multipath-compensation off on] [--multipath-set visibility=true ...]
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import time

import numpy as np

from omnitof.scan import ScanExtractor
from omnitof.sensor.tof import SensorNoise
from omnitof.sensor.tof_errors import SWITCHES, ToFErrors
from omnitof.sim.render import Renderer
from omnitof.sim.sequence import make_sequence, sample_poses
from omnitof.sim.worlds import load_world, world_names


def settings(only: list[str] | None = None) -> list[tuple[str, ToFErrors]]:
    out = [("none", ToFErrors())]
    out += [(name, ToFErrors().only(name)) for name in SWITCHES]
    out.append(("default (all but multipath)", ToFErrors.simulation_default()))
    out.append(("all", ToFErrors.realistic()))
    return [o for o in out if only is None or o[0].split()[0] in only]


def frames(world, errors: ToFErrors, count: int, seed: int = 0):
    seq = make_sequence(world, seed=seed)
    idx = np.linspace(0, len(seq) - 1, count).round().astype(int)
    renderer = Renderer(world, sensor=SensorNoise(errors=errors))
    timing = sample_poses(seq, idx, errors.integration_time)
    out = renderer.render_many(seq.ground_truth[idx], seed=seed + 1, sample_poses=timing)
    return renderer, seq.ground_truth[idx], out


def matte_errors(world, renderer, extractor, poses, ranges) -> np.ndarray:
    h = extractor.settings.height
    errs = []
    for pose, r in zip(poses, ranges):
        bearings = extractor.angles + pose[2]
        truth = world.horizontal_distance(pose[:2], bearings, h)
        directions = np.column_stack([np.cos(bearings), np.sin(bearings), np.zeros(len(bearings))])
        _, names = renderer.first_surface(np.tile([pose[0], pose[1], h], (len(bearings), 1)), directions)
        matte = np.array([bool(n) and world.materials[n].kind == "matte" for n in names])
        e = (r - truth)[matte]
        errs.append(e[np.isfinite(e)])
    return np.concatenate(errs)


def true_rig_errors(world, renderer, poses, frames) -> list[np.ndarray]:
    """The matte bins' errors of `frames` (rendered at `poses`) with the true rig's extractor and
    no distance correction: [pixel filter off, pixel filter on]."""
    from omnitof.calibration import Calibration

    distance = np.stack([f.tof.distance for f in frames])
    amplitude = np.stack([f.tof.amplitude for f in frames])
    calibration = Calibration.from_rig(renderer.rig)
    out = []
    for enabled in (False, True):
        extractor = ScanExtractor.from_calibration(calibration, pixel_filter={"enabled": enabled})
        out.append(matte_errors(world, renderer, extractor, poses, extractor.extract_many(distance, amplitude)))
    return out


def stats(e: np.ndarray) -> str:
    a = np.abs(e)
    return f"{100 * np.median(a):.1f} / {100 * np.percentile(a, 90):.1f} / {100 * np.mean(a < 0.05):.1f} %"


def calibration_for(kind: str, renderer, cache: dict):
    """The Calibration the scans are extracted with for a --corrections kind (cached per kind
    and sensor: every world has the same rig)."""
    from omnitof.calibration import Calibration
    from omnitof.calibration.simulated import calibrate_from_simulation
    from omnitof.calibration.walls import fit_from_walls, render_wall_views

    key = (kind, renderer.sensor.errors)
    if key not in cache:
        truth = Calibration.from_rig(renderer.rig)
        if kind == "none":
            cal = truth
        elif kind == "true":
            walls = render_wall_views(renderer.camera, renderer.mirrors, 0, sensor=renderer.sensor)
            truth.distance_correction = fit_from_walls(truth, walls)
            cal = truth
        elif kind == "estimated":
            cal, _ = calibrate_from_simulation(renderer, seed=0, truth=truth)
        else:
            raise SystemExit(f"unknown correction {kind!r}: none, true, estimated")
        cache[key] = cal
    return cache[key]


# --multipath-set: changes to the compensation's settings for every row.
MULTIPATH_CHANGES: dict = {}


def compensation(renderer, enabled: bool) -> dict:
    """The ScanSettings.multipath of a --multipath-compensation value: the compensation for the
    rendering camera (its LEDs, amplitude scale, frequency and mirrors), on or off, with
    MULTIPATH_CHANGES."""
    from omnitof.scan.multipath import MultipathSettings

    settings = MultipathSettings.for_camera(renderer.sensor.errors, amplitude_at_1m=renderer.sensor.amplitude_at_1m,
                                            f_mod=renderer.sensor.f_mod,
                                            mirror_reflectivity=renderer.settings.mirror_reflectivity)
    return MultipathSettings(**{**settings.model_dump(), **MULTIPATH_CHANGES, "enabled": enabled}).model_dump()


def budget(names: list[str], count: int, only: list[str] | None = None,
           corrections: tuple[str, ...] = ("none",), incidences: tuple[float, ...] = (90.0,),
           compensations: tuple[str, ...] = ("off",)) -> None:
    print("| world | effects | correction | multipath compensation | max incidence | bins (off / on) | median / p90 "
          "|error| (cm) / within 5 cm, filter off | the same, filter on |")
    print("|---|---|---|---|---|---|---|---|")
    cache: dict = {}
    for name in names:
        world = load_world(name)
        for label, errors in settings(only):
            renderer, poses, fr = frames(world, errors, count)
            d = np.stack([f.distance for f in fr])
            a = np.stack([f.amplitude for f in fr])
            for kind in corrections:
                cal = calibration_for(kind, renderer, cache)
                for incidence, comp in itertools.product(incidences, compensations):
                    multipath = compensation(renderer, comp == "on")
                    off = ScanExtractor.from_calibration(cal, pixel_filter={"enabled": False},
                                                         max_incidence_deg=incidence, multipath=multipath)
                    on = ScanExtractor.from_calibration(cal, max_incidence_deg=incidence, multipath=multipath)
                    e_off = matte_errors(world, renderer, off, poses, off.extract_many(d, a))
                    e_on = matte_errors(world, renderer, on, poses, on.extract_many(d, a))
                    shown = "off" if incidence >= 90 else f"{incidence:g}°"
                    print(f"| {name} | {label} | {kind} | {comp} | {shown} | {len(e_off)} / {len(e_on)} | "
                          f"{stats(e_off)} | {stats(e_on)} |", flush=True)


def speed(runs: int, count: int = 60) -> None:
    world = load_world("corridor1")
    seq = make_sequence(world, seed=0)
    idx = np.linspace(0, len(seq) - 1, count).round().astype(int)
    poses = seq.ground_truth[idx]
    timing = {}
    renderers = {label: Renderer(world, sensor=SensorNoise(errors=e))
                 for label, e in (("off", ToFErrors()), ("default (all but multipath)", ToFErrors.simulation_default()),
                                  ("all on", ToFErrors.realistic()))}
    for r in renderers.values():
        r.phasors(poses[:2])
    tracer = {k: [] for k in renderers}
    full = {k: [] for k in renderers}
    for _ in range(runs):
        for label, r in renderers.items():
            timing = sample_poses(seq, idx, r.sensor.errors.integration_time)
            t = time.perf_counter()
            r.phasors(poses)
            tracer[label].append(count / (time.perf_counter() - t))
            t = time.perf_counter()
            r.render_many(poses, seed=1, sample_poses=timing)
            full[label].append(count / (time.perf_counter() - t))
    print("| effects | tracer fps (median, min–max) | full frames fps (median, min–max) |")
    print("|---|---|---|")
    for label in renderers:
        tr, fu = tracer[label], full[label]
        print(f"| {label} | {statistics.median(tr):.1f} ({min(tr):.1f}–{max(tr):.1f}) | "
              f"{statistics.median(fu):.1f} ({min(fu):.1f}–{max(fu):.1f}) |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--worlds", nargs="*", default=world_names())
    parser.add_argument("--skip-budget", action="store_true")
    parser.add_argument("--skip-speed", action="store_true")
    parser.add_argument("--settings", nargs="*", help="only these rows (none, a switch, default, all)")
    parser.add_argument("--corrections", nargs="+", default=["none"], choices=["none", "true", "estimated"],
                        help="distance corrections to apply (module docstring)")
    parser.add_argument("--max-incidence", nargs="+", type=float, default=[90.0],
                        help="ScanSettings.max_incidence_deg values to extract with (90: off, the default)")
    parser.add_argument("--multipath-compensation", nargs="+", default=["off"], choices=["off", "on"],
                        help="extract without and/or with the multipath compensation (omnitof.scan.multipath), "
                        "set up for the rendering camera")
    parser.add_argument("--multipath-set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="MultipathSettings fields to change (values as YAML), e.g. visibility=true")
    args = parser.parse_args()
    import yaml

    for item in args.multipath_set:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--multipath-set takes KEY=VALUE, got {item!r}")
        MULTIPATH_CHANGES[key] = yaml.safe_load(value)
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}")
    if not args.skip_speed:
        speed(args.runs)
    if not args.skip_budget:
        budget(args.worlds, args.frames, args.settings, tuple(args.corrections), tuple(args.max_incidence),
               tuple(args.multipath_compensation))
    print(f"# done, load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
