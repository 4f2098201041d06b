"""Filters on the simulated worlds' ToF scans, many runs from one extraction per drive.

Each (world, drive) is simulated, calibrated from rendered targets and extracted once, as
`omnitof demo` does it (in memory, float64 beam angles), and cached under `--cache` (with the
commit that extracted it: a run on other code says so on stderr, since the cache is keyed by
world and settings only; delete the file to extract anew); every
(preset, particles, seed) then runs `run_slam` on those scans and is scored as the demo scores
it: the trajectory's error to the truth and the map's share of occupied cells within 5 cm of a
wall. This is what the issue-13 tables of BENCHMARKS.md were made with. (`omnitof bench
benchmarks/worlds.yaml` runs the same filters through ROS bags, whose float32 beam angles move
a few seeds' numbers in the last digits.)

    python benchmarks/world_filters.py --worlds corridor1 office --drives 0 1 --seeds 0 1 2 \
        [--preset tof-scanmatch] [--particles 30] [--set backend.min_score=0.65 ...] \
        [--tof-errors default|all|none|LIST] [--ideal-scans [seen]] [--odometry-scale F]
        [--odometry-jump AT DX DY DEG] [--off-plan M] [--ignore-odometry]
        [--max-incidence DEG] [--true-rig] [--multipath-compensation auto|on|off]
        [--multipath-max-ratio R] [--bands HEIGHT:BAND ...] [--amplitudes MIN MIN_1M] [--cache DIR]

The camera's systematic errors (issue 15) are those of the demo, `default` unless told; the
cache is kept per setting. `--ideal-scans` replaces every range by the exact distance to the
floor plan at the slice height from the true pose (same bearings, same 7 m limit, every bearing
seen): what the filter makes of a perfect omnidirectional scanner, to tell the sensor's share of
an error from the filter's; `--ideal-scans seen` keeps the ToF scans' gaps (exact ranges only
where they have a reading), to tell the ranges' errors from the readings' number.
`--odometry-scale F` multiplies every odometry step's translation by F (the simulated wheels
report 1 % too far: F = 1/1.01 takes that out, an oracle no real run has). `--odometry-jump AT
DX DY DEG` makes the wheels glitch once, a fraction AT through the drive (what the filters must
repair). `--off-plan M` drops every reading whose end point, from the true pose, lies more than M
metres off the floor plan at the slice height (an oracle filter, to tell what the wrong readings
cost). `--ignore-odometry` sets the wheels aside and estimates the odometry from the scans
(omnitof.slam.scan_odometry, once per drive, from the first odometry pose), as `omnitof slam
--ignore-odometry` and a bag without odometry do. `--max-incidence DEG`
drops the bins seen at a grazing angle (`ScanSettings.max_incidence_deg`, omnitof.scan.grazing),
as the extraction would have as its last step. `--true-rig` extracts with the true rig, given
the same wall-fitted distance correction as the estimate (issue 16's reference).
`--multipath-compensation` (auto: on where the camera has multipath, as the demo) extracts with
the compensation of omnitof.scan.multipath set up for the simulated camera (cached apart);
`--multipath-max-ratio R` gives it that `max_ratio` (cached apart). `--bands 0.6:0.1 1.35:0.55`
extracts one scan per height band (`ScanSettings.height`, `band`) from the same rendered frames
and keeps, per bin, the nearest band's reading (cached apart): what a scan of more of the image
than the slice gives the 2D filter. `--amplitudes 25 150` extracts with those amplitude thresholds
(`ScanSettings.min_amplitude`, `min_amplitude_1m`; cached apart).

Prints one JSON line per run (with the error after a rigid alignment to the truth and the best
similarity scale, `omnitof.eval.ate`), then a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pickle
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from omnitof.demo import DemoSettings, _calibrate, evaluate_run
from omnitof.eval.ate import evaluate_ate
from omnitof.geometry import compose, relative
from omnitof.scan import ScanExtractor, ScanSettings
from omnitof.scan.grazing import drop_grazing
from omnitof.scan.multipath import MultipathSettings
from omnitof.scan.tof_input import tof_scans
from omnitof.sensor.tof import SensorNoise
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.laser2d import World2D
from omnitof.sim.render import Renderer, RenderSettings
from omnitof.sim.sequence import MotionSettings, make_sequence, render_sequence
from omnitof.sim.worlds import load_world
from omnitof.slam import run_slam
from omnitof.slam.config import load_config
from omnitof.types import Trajectory


def extracted_scans(name: str, drive: int, cache: Path, tof_errors: str = "default", *, true_rig: bool = False,
                    compensation: str = "auto", max_ratio: float | None = None,
                    bands: list[tuple[float, float]] | None = None,
                    amplitudes: tuple[float, float] | None = None):
    """The scans of world `name`, drive seed `drive`, with the estimated calibration, or with
    `true_rig` the true rig given the same wall-fitted distance correction (cached); with the
    multipath compensation set up for the camera where `compensation` is "on", or "auto" and the
    camera has multipath (as `omnitof demo` does), with `max_ratio` if given. `bands`: (height,
    half-thickness) pairs, one scan each, the nearest band's reading per bin. `amplitudes`: the
    extraction's (min_amplitude, min_amplitude_1m) instead of ScanSettings' (cached apart)."""
    errors = ToFErrors.parse(tof_errors)
    tag = ("" if tof_errors == "none" else "_" + tof_errors.replace(",", "+")) + ("_truerig" if true_rig else "")
    compensate = compensation == "on" or (compensation == "auto" and errors.multipath)
    tag += "_mpcomp" if compensate else ""
    tag += f"_ratio{max_ratio:g}" if compensate and max_ratio is not None else ""
    tag += "_bands" + "+".join(f"{h:g}:{b:g}" for h, b in bands) if bands else ""
    tag += f"_amp{amplitudes[0]:g}_{amplitudes[1]:g}" if amplitudes else ""
    thresholds = {"min_amplitude": amplitudes[0], "min_amplitude_1m": amplitudes[1]} if amplitudes else {}
    stem = Path(name).stem if name.endswith((".yaml", ".yml")) else name  # a world YAML by path
    path = cache / f"{stem}_{drive}{tag}.pkl"
    if path.exists():
        cached = pickle.loads(path.read_bytes())
        # The cache is keyed by world and settings, not by the code: say when other code made it.
        made_by, now = cached.get("made_by", "an unrecorded commit"), code_version()
        if made_by != now:
            print(f"note: {path} was extracted by {made_by}, this is {now}; delete it to extract anew",
                  file=sys.stderr)
        return cached["scans"]
    settings = DemoSettings(world=name, seed=drive, calibrate=not true_rig, true_rig_correction=true_rig)
    world = load_world(name)
    sequence = make_sequence(world, seed=drive, motion=MotionSettings(speed=settings.speed))
    sensor = SensorNoise(errors=errors)
    renderer = Renderer(world, sensor=sensor, settings=RenderSettings(seed=drive))
    work = cache / f"{stem}_{drive}{tag}"
    work.mkdir(parents=True, exist_ok=True)
    calibration, _ = _calibrate(renderer, settings, work)
    multipath = MultipathSettings.for_camera(errors, amplitude_at_1m=sensor.amplitude_at_1m, f_mod=sensor.f_mod,
                                             mirror_reflectivity=renderer.settings.mirror_reflectivity,
                                             enabled=compensate,
                                             **({} if max_ratio is None else {"max_ratio": max_ratio}))
    if not bands:
        extractor = ScanExtractor.from_calibration(calibration, multipath=multipath.model_dump(), **thresholds)
        scans = tof_scans(render_sequence(sequence, renderer), extractor, cloud_every=0, source=name).scans
    else:
        frames = list(render_sequence(sequence, renderer))
        scans = None
        for height, band in bands:
            extractor = ScanExtractor.from_calibration(calibration, multipath=multipath.model_dump(),
                                                       height=height, band=band, **thresholds)
            layer = tof_scans(iter(frames), extractor, cloud_every=0, source=name).scans
            scans = layer if scans is None else dataclasses.replace(scans, ranges=np.fmin(scans.ranges, layer.ranges))
    path.write_bytes(pickle.dumps({"world": name, "scans": scans, "made_by": code_version()}))
    return scans


def code_version() -> str:
    """The commit of the checkout that runs this (with "+changes" for a modified tree), or the
    package's version outside a git checkout."""
    import subprocess

    import omnitof

    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True,
                                check=True).stdout.strip()
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                 capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return f"omnitof {omnitof.__version__}"
    return commit + ("+changes" if changed else "")


def ideal_scans(world, scans, only_seen: bool = False):
    """`scans` with every range replaced by the exact distance to the floor plan at the slice
    height from the true pose (+inf beyond the scans' max_range). `only_seen`: only the bearings
    where the ToF scan has a reading (its gaps kept), so that the ranges' errors are told from
    the readings' number."""
    plan = World2D(world.segments_at(ScanSettings().height))
    gt = scans.ground_truth
    ranges = plan.raycast(gt[:, :2], scans.angles[None, :] + gt[:, 2:3], scans.max_range)
    if only_seen:
        seen = np.isfinite(scans.ranges) & (scans.ranges < scans.max_range)
        ranges = np.where(seen, ranges, np.inf)
    return dataclasses.replace(scans, ranges=ranges.astype(np.float32))


def off_plan_dropped(world, scans, limit: float):
    """`scans` with every reading whose end point, from the true pose, lies more than `limit`
    metres from the floor plan at the slice height turned into no echo: an oracle filter of the
    readings no real run has, to tell what the wrong readings cost."""
    plan = World2D(world.segments_at(ScanSettings().height))
    gt = scans.ground_truth
    bearing = scans.angles[None, :] + gt[:, 2:3]
    r = np.where(np.isfinite(scans.ranges), scans.ranges, 0.0)
    pts = np.stack([gt[:, 0:1] + r * np.cos(bearing), gt[:, 1:2] + r * np.sin(bearing)], axis=-1).reshape(-1, 2)
    off = np.isfinite(scans.ranges) & (plan.distance_to_walls(pts).reshape(scans.ranges.shape) > limit)
    return dataclasses.replace(scans, ranges=np.where(off, np.inf, scans.ranges).astype(np.float32))


def scaled_odometry(scans, factor: float):
    """`scans` with each odometry step's translation (in the robot frame) times `factor`."""
    steps = relative(scans.odometry[:-1], scans.odometry[1:])
    steps[:, :2] *= factor
    poses = [scans.odometry[0]]
    for step in steps:
        poses.append(compose(poses[-1], step))
    return dataclasses.replace(scans, odometry=np.array(poses))


def jumped_odometry(scans, at: float, jump: tuple[float, float, float]):
    """`scans` with odometry that jumps by `jump` (x, y in m, heading in degrees, in the robot's frame)
    at the scan a fraction `at` through the drive and carries the jump on from there: wheels that slipped
    or spun while the robot stood still (as tests/test_scan_match.py's `with_odometry_jump`)."""
    k = min(len(scans) - 1, max(1, int(round(at * len(scans)))))
    before = scans.odometry[k - 1]
    step = np.array([jump[0], jump[1], math.radians(jump[2])])
    odometry = scans.odometry.copy()
    odometry[k:] = compose(compose(before, step), relative(before, scans.odometry[k:]))
    return dataclasses.replace(scans, odometry=odometry)


def overrides(items: list[str]) -> dict:
    out: dict = {}
    for item in items:
        key, value = item.split("=", 1)
        section, field = key.split(".", 1)
        out.setdefault(section, {})[field] = yaml.safe_load(value)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["room", "office", "corridor1", "corridor2"])
    parser.add_argument("--drives", nargs="+", type=int, default=[0])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--preset", default="tof-scanmatch")
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE")
    parser.add_argument("--multipath-compensation", choices=["auto", "on", "off"], default="auto",
                        help="extract with the multipath compensation (omnitof.scan.multipath); auto: where the "
                        "camera has multipath, as the demo")
    parser.add_argument("--multipath-max-ratio", type=float, default=None,
                        help="the compensation's max_ratio (MultipathSettings; default: its default)")
    parser.add_argument("--tof-errors", default="default",
                        help="the camera's systematic errors, as `omnitof demo --tof-errors` (default: the demo's)")
    parser.add_argument("--ideal-scans", nargs="?", const="all", choices=["all", "seen"], default=None,
                        help="exact ranges from the floor plan at the true poses instead of the ToF scans "
                             "(seen: only where the ToF scan has a reading)")
    parser.add_argument("--off-plan", type=float, default=None, metavar="M",
                        help="oracle: drop the readings more than M metres off the floor plan at the true pose")
    parser.add_argument("--odometry-scale", type=float, default=1.0,
                        help="multiply each odometry step's translation by this (an oracle for the wheels' scale error)")
    parser.add_argument("--odometry-jump", nargs=4, type=float, default=None, metavar=("AT", "DX", "DY", "DEG"),
                        help="a wheel glitch: the odometry jumps by DX, DY (m) and DEG (degrees) in the robot's frame "
                             "at the scan a fraction AT through the drive (e.g. 0.5 0.6 0 8)")
    parser.add_argument("--ignore-odometry", action="store_true",
                        help="estimate the odometry from the scans instead of the wheels")
    parser.add_argument("--max-incidence", type=float, default=90.0,
                        help="drop the bins seen more than this far from their surface's normal (degrees; "
                             "ScanSettings.max_incidence_deg, the extraction's last step, applied to the cached "
                             "scans; 90: off)")
    parser.add_argument("--true-rig", action="store_true",
                        help="extract with the true rig (given the same wall-fitted distance correction) instead of "
                             "the calibration estimated from rendered targets")
    parser.add_argument("--bands", nargs="+", default=None, metavar="HEIGHT:BAND",
                        help="one scan per height band (m, the slice's height and half-thickness), the nearest "
                             "band's reading per bin (default: the extraction's one slice)")
    parser.add_argument("--amplitudes", nargs=2, type=float, default=None, metavar=("MIN", "MIN_1M"),
                        help="the extraction's min_amplitude and min_amplitude_1m (default: ScanSettings' 40, 300)")
    parser.add_argument("--cache", type=Path, default=Path("results/world_scans"))
    args = parser.parse_args(argv)
    try:
        bands = [tuple(float(v) for v in item.split(":", 1)) for item in args.bands] if args.bands else None
        if bands and any(len(b) != 2 for b in bands):
            raise ValueError
    except ValueError:
        parser.error(f"--bands takes HEIGHT:BAND pairs in metres, e.g. 0.6:0.1, got {args.bands}")

    rows = []
    for name in args.worlds:
        world = load_world(name)
        for drive in args.drives:
            scans = extracted_scans(name, drive, args.cache, args.tof_errors, true_rig=args.true_rig,
                                    compensation=args.multipath_compensation, max_ratio=args.multipath_max_ratio,
                                    bands=bands, amplitudes=tuple(args.amplitudes) if args.amplitudes else None)
            if args.ideal_scans:
                scans = ideal_scans(world, scans, only_seen=args.ideal_scans == "seen")
            if args.off_plan is not None:
                scans = off_plan_dropped(world, scans, args.off_plan)
            if args.odometry_scale != 1.0:
                scans = scaled_odometry(scans, args.odometry_scale)
            if args.odometry_jump:
                scans = jumped_odometry(scans, args.odometry_jump[0], tuple(args.odometry_jump[1:]))
            if args.max_incidence < 90.0:
                ranges = drop_grazing(scans.ranges, 2 * math.pi / scans.ranges.shape[1], math.radians(args.max_incidence))
                scans = dataclasses.replace(scans, ranges=ranges)
            estimate_s = None
            if args.ignore_odometry:
                from omnitof.slam.scan_odometry import with_scan_odometry

                start = time.perf_counter()
                scans = dataclasses.replace(scans, odometry=np.broadcast_to(scans.odometry[:1], scans.odometry.shape),
                                            odometry_known=False)
                scans, found = with_scan_odometry(scans, load_config(preset=args.preset, overrides=overrides(args.set)))
                estimate_s = round(time.perf_counter() - start, 1)
                print(json.dumps({"world": name, "drive": drive, "scan_odometry": found.to_dict(),
                                  "estimate_s": estimate_s}), flush=True)
            for seed in args.seeds:
                ov = overrides(args.set)
                ov.setdefault("filter", {}).update({"particles": args.particles, "seed": seed})
                cfg = load_config(preset=args.preset, overrides=ov)
                start = time.perf_counter()
                result = run_slam(scans, cfg)
                wall = time.perf_counter() - start
                ev = evaluate_run(world, scans, result, None)
                truth = Trajectory(result.trajectory.timestamps, scans.ground_truth)
                backend = result.stats.get("backend") or {}
                row = {
                    "world": name, "drive": drive, "seed": seed, "preset": args.preset,
                    "particles": args.particles, "set": args.set, "ideal_scans": args.ideal_scans, "odometry_scale": args.odometry_scale,
                    "odometry_jump": args.odometry_jump, "ignore_odometry": args.ignore_odometry,
                    "true_rig": args.true_rig, "bands": args.bands,
                    "readings_median": float(np.median(np.isfinite(scans.ranges).sum(axis=1))),
                    "final_m": round(ev["trajectory"]["slam"]["final"], 3),
                    "mean_m": round(ev["trajectory"]["slam"]["mean"], 3),
                    # After a rigid (and a similarity) alignment to the truth: what of the error is
                    # the map's shape, not its placement, and how far its lengths are off.
                    "rigid_mean_m": round(evaluate_ate(result.trajectory, truth, align="rigid")[0].error.mean, 3),
                    "scale": round(evaluate_ate(result.trajectory, truth, align="similarity")[0].alignment.scale, 4),
                    "within_5cm_pct": round(100 * ev["floorplan"]["occupied_within_5cm"], 1),
                    "closures_kept": backend.get("closures_accepted"),
                    "closures_found": backend.get("closures_found"),
                    "corrected_scans": result.stats.get("odometry_corrected_scans"),
                    "check_verdicts": [[c["scan"], c["verdict"]] for c in result.stats.get("check_corrections", [])],
                    "wall_s": round(wall, 1),
                }
                rows.append(row)
                print(json.dumps(row), flush=True)
    print("\n| world | drive | seed | final error m | mean error m | mean after a rigid alignment m | scale | "
          "occupied ≤ 5 cm of a wall % | closures kept / found |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['world']} | {r['drive']} | {r['seed']} | {r['final_m']:.3f} | {r['mean_m']:.3f} | "
              f"{r['rigid_mean_m']:.3f} | {r['scale']:.4f} | "
              f"{r['within_5cm_pct']:.1f} | {r['closures_kept']} / {r['closures_found']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
