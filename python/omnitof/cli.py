"""The `omnitof` command. Subcommands parse arguments and call the library; no logic here.

Errors that come from the user's input (OmnitofError) print one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys

import numpy as np
import warnings
from pathlib import Path
from typing import Any

from omnitof import __version__
from omnitof.errors import OmnitofError, OmnitofWarning
from omnitof.types import ScanSequence


def _config_from_args(args: argparse.Namespace, default_preset: str | None = None):
    from omnitof.slam.config import load_config

    overrides: dict[str, Any] = {"filter": {}}
    for name in ("particles", "seed", "threads"):
        value = getattr(args, name, None)
        if value is not None:
            overrides["filter"][name] = value
    preset = args.preset if args.preset is not None or args.config is not None else default_preset
    return load_config(args.config, preset=preset, overrides=overrides)


def _progress_bar(total: int, enabled: bool, desc: str, unit: str = "scan"):
    from omnitof.io.terminal import progress_bar

    return progress_bar(total, enabled=enabled, desc=desc, unit=unit)


def _summary_line(stats: dict) -> str:
    return (
        f"scans {stats['scans']} (integrated {stats['integrated']}), "
        f"time {stats['seconds']:.1f} s, particles {stats['particles']}, "
        f"resamplings {stats['resamplings']}"
    )


def _scan_settings(args: argparse.Namespace):
    from omnitof.scan import scan_settings

    given = {k: getattr(args, k) for k in ("height", "band") if getattr(args, k, None) is not None}
    return scan_settings(**given)


def _read_tof_input(args: argparse.Namespace, *, cloud_every: int, max_frames: int | None):
    from omnitof.scan.tof_input import frame_count, read_tof_scans

    total = frame_count(args.log)
    if max_frames is not None:
        total = min(total, max_frames)
    with _progress_bar(total, not args.quiet, "scans", unit="frame") as bar:
        return read_tof_scans(
            args.log, calibration=args.calibration, settings=_scan_settings(args),
            cloud_every=cloud_every, max_frames=max_frames, progress=bar.update,
        )


def cmd_slam(args: argparse.Namespace) -> int:
    from omnitof.interrupts import pause_point
    from omnitof.io.scans import is_tof_bag, read_scans
    from omnitof.results import results_folder, write_results
    from omnitof.slam import check_limits, run_slam

    tof = is_tof_bag(args.log)
    if not tof and (args.calibration is not None or args.map3d):
        raise OmnitofError(f"{args.log}: --calibration and --map3d need a bag of ToF images")
    # Without --preset: the scan-matching filter with the pose-graph back end, for either kind of
    # input (the paper's filter is `--preset paper` / `--preset tof`).
    cfg = _config_from_args(args, default_preset="tof-scanmatch" if tof else "laser180-scanmatch")
    relations = None
    if args.relations is not None:
        from omnitof.eval.relations import read_relations

        relations = read_relations(args.relations)
    # Opened before any work, so that an output that cannot be written is found at once; the
    # folder replaces --out only when everything is written (omnitof.results).
    with results_folder(args.out) as folder:
        pause_point("start")
        if tof:
            tof_data = _read_tof_input(args, cloud_every=args.map3d_every if args.map3d else 0,
                                       max_frames=args.max_scans)
            scans = tof_data.scans
            extra = {"input": {"path": str(args.log), "kind": "tof-rosbag", "rig": tof_data.rig_source,
                               "scan": tof_data.extractor.settings.model_dump()}}
        else:
            data = read_scans(args.log, skip_bad_lines=args.skip_bad_lines)
            scans = data.scans if args.max_scans is None else data.scans.slice(0, args.max_scans)
            extra = {"input": {"path": str(args.log), "kind": data.kind, "bad_lines_skipped": data.bad_lines}}
        extra["input"]["max_range"] = {"metres": float(scans.max_range), "rule": scans.max_range_rule or "given"}
        extra["input"]["time_order"] = scans.time_order()
        if relations is not None:
            from omnitof.eval.relations import check_relations_match

            check_relations_match(relations, scans.timestamps)
        check_limits(scans, cfg)
        # Laser logs are stamped when the reading arrives, so their delay is estimated by default.
        delay = args.scan_delay if args.scan_delay is not None or tof else "auto"
        if delay is not None:
            scans, extra["input"]["scan_delay"] = _retimed(scans, delay, given=args.scan_delay is not None)
        with _progress_bar(len(scans), not args.quiet, "slam") as bar:
            result = run_slam(scans, cfg, progress=_pausing(bar.update, "slam", len(scans) // 2))
        if relations is not None:
            from omnitof.eval.relations import evaluate_relations

            rel = evaluate_relations(result.trajectory, relations)
            extra["relations"] = rel.to_dict()
        if scans.ground_truth is not None:
            from omnitof.eval.trajectory import absolute_trajectory_error

            extra["trajectory_error"] = {
                "slam": absolute_trajectory_error(result.trajectory.poses, scans.ground_truth).to_dict(),
                "odometry": absolute_trajectory_error(scans.odometry, scans.ground_truth).to_dict(),
            }
        if tof and args.map3d:
            from omnitof.map3d import voxel_map_from_clouds
            from omnitof.results import write_voxel_outputs

            vmap = voxel_map_from_clouds(result.trajectory.poses[tof_data.cloud_frames], tof_data.clouds)
            write_voxel_outputs(vmap, folder, trajectory=result.trajectory.poses)
        write_results(folder, result, cfg, title=f"{Path(args.log).name}", extra=extra,
                      ground_truth=scans.ground_truth)
    print(_summary_line(result.stats))
    if relations is not None:
        print(rel.format())
    if "trajectory_error" in extra:
        te = extra["trajectory_error"]
        print(f"trajectory error (mean, final): SLAM {te['slam']['mean']:.3f} m, {te['slam']['final']:.3f} m; "
              f"odometry {te['odometry']['mean']:.3f} m, {te['odometry']['final']:.3f} m")
    print(f"results in {args.out}")
    return 0


def _pausing(update, name: str, at: int):
    """`update` (a progress callback) that passes `pause_point(name)` once `at` scans are done:
    the fault-injection tests stop a run there, in the middle of SLAM."""
    from omnitof.interrupts import pause_point

    done = 0

    def step(n: int) -> None:
        nonlocal done
        update(n)
        if done < at <= done + n:
            pause_point(name)
        done += n

    return step


# A laser's scan delay is a fraction of a second; seconds beyond this are a mistake, not a delay.
MAX_SCAN_DELAY_S = 10.0


def _scan_delay(text: str) -> str | float:
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds or 'auto', got {text!r}") from None
    if not (math.isfinite(value) and abs(value) <= MAX_SCAN_DELAY_S):
        raise argparse.ArgumentTypeError(
            f"expected a delay within ±{MAX_SCAN_DELAY_S:g} s or 'auto', got {text!r}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1, got {value}")
    return value


SEED_LIMIT = 2**63  # seeds are u64 in the core and numpy's generators take any below it


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not 0 <= value < SEED_LIMIT:
        raise argparse.ArgumentTypeError(f"expected a seed in 0 … 2^63 - 1, got {value}")
    return value


def _number(*, above: float | None = None, at_least: float | None = None, at_most: float | None = None):
    """An argparse type for finite numbers (and, if given, > `above`, >= `at_least`, <= `at_most`)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if above is not None and not value > above:
            raise argparse.ArgumentTypeError(f"expected a number above {above:g}, got {text!r}")
        if at_least is not None and not value >= at_least:
            raise argparse.ArgumentTypeError(f"expected a number of at least {at_least:g}, got {text!r}")
        if at_most is not None and not value <= at_most:
            raise argparse.ArgumentTypeError(f"expected a number of at most {at_most:g}, got {text!r}")
        return value

    return parse


def _retimed(scans: ScanSequence, delay: str | float, *, given: bool) -> tuple[ScanSequence, dict]:
    """The scans with their odometry re-timed by `delay` (seconds, or "auto": estimated), and
    what to record of it. Where the log does not allow an estimate (a clock that steps back, too
    few scans taken while turning), the delay is 0 and the record says why; a delay in seconds
    that cannot be applied is an error."""
    from omnitof.slam.timing import estimate_scan_delay, retime_odometry

    option = "--scan-delay" if given else "default --scan-delay auto"
    if delay == "auto":
        try:
            estimate = estimate_scan_delay(scans)
        except ValueError as err:
            print(f"scan delay 0 s: not estimated ({err})")
            return scans, {"seconds": 0.0, "how": f"{option}: not estimated, so none applied", "reason": str(err)}
        print(f"scan delay estimated from {estimate.pairs} scan pairs: {estimate.delay:.3f} s")
        record = {"seconds": estimate.delay, "how": f"{option}: estimated from the log",
                  "estimated_from_pairs": estimate.pairs}
    else:
        record = {"seconds": float(delay), "how": "--scan-delay: given"}
    try:
        return retime_odometry(scans, record["seconds"]), record
    except ValueError as err:
        raise OmnitofError(f"--scan-delay: {err}") from None


def cmd_scans(args: argparse.Namespace) -> int:
    data = _read_tof_input(args, cloud_every=0, max_frames=args.max_frames)
    scans = data.scans
    out = Path(args.out)
    if out.suffix in (".clf", ".log", ".txt"):
        from omnitof.io.carmen import write_carmen

        write_carmen(out, scans)
        kind = "CARMEN log"
    else:
        from omnitof.io.rosbag import write_laserscan_bag

        version = 1 if out.suffix == ".bag" else 2
        write_laserscan_bag(out, scans, version=version, overwrite=args.overwrite)
        kind = f"ROS {version} bag (sensor_msgs/LaserScan on /scan, nav_msgs/Odometry on /odom)"
    if args.figure is not None:
        from omnitof.viz.scans import plot_scan

        i = len(scans) // 2
        plot_scan(args.figure, scans.scan_ranges(i), scans.scan_angles(i), max_range=scans.max_range,
                  title=f"frame {i} of {Path(args.log).name}")
    filled = float(np.isfinite(scans.ranges[scans.beam_mask]).mean()) if len(scans) else 0.0
    print(f"{len(scans)} scans of 360 bins ({100 * filled:.1f} % with a reading; rig from {data.rig_source}) "
          f"written as a {kind}: {out}")
    return 0


def cmd_eval_relations(args: argparse.Namespace) -> int:
    from omnitof.eval.relations import evaluate_relations, read_relations
    from omnitof.io.tum import read_tum

    result = evaluate_relations(
        read_tum(args.trajectory), read_relations(args.relations),
        time_tolerance=args.tolerance, source=args.trajectory,
    )
    print(result.format())
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    from omnitof.slam.config import preset_names

    if args.list:
        print("\n".join(preset_names()))
        return 0
    print(_config_from_args(args).to_yaml(), end="")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from omnitof.demo import run_demo

    run_demo(args.out, world=args.world, seed=args.seed, preset=args.preset, particles=args.particles,
             calibrate=not args.true_rig, max_frames=args.max_frames, progress=not args.quiet)
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    if args.what == "calibration":
        from omnitof.cli_calibrate import cmd_render_targets

        return cmd_render_targets(args)
    from omnitof.sim.sequence import MotionSettings, make_sequence, simulate_bag
    from omnitof.sim.worlds import load_world

    world = load_world(args.world)
    motion = MotionSettings(speed=args.speed)
    total = len(make_sequence(world, seed=args.seed, motion=motion))
    if args.max_frames is not None:
        total = min(total, args.max_frames)
    with _progress_bar(total, not args.quiet, "render", unit="frame") as bar:
        sequence, written = simulate_bag(
            world, args.out, seed=args.seed, motion=motion, samples=args.samples,
            max_frames=args.max_frames, storage=args.storage, overwrite=args.overwrite,
            progress=bar.update,
        )
    drift, turn = sequence.odometry_end_error(written)
    print(
        f"{world.name}: {written} frames at {motion.rate_hz:g} Hz, {sequence.distance_driven(written):.1f} m driven; "
        f"raw odometry ends {drift:.2f} m and {math.degrees(turn):.1f}° off the truth"
    )
    print(f"bag in {args.out}")
    return 0


def cmd_design(args: argparse.Namespace) -> int:
    from omnitof.sensor.camera import Camera
    from omnitof.sensor.design import design_report, format_sweep, sweep
    from omnitof.sensor.mirrors import pyramid
    from omnitof.viz.sensor import plot_mirror_regions, plot_sweep

    lenses = {"standard": Camera.sr4000(), "wide": Camera.sr4000_wide()}
    if args.sweep is not None:
        rows = sweep(lenses, tilts_deg=range(40, 66, 2), yaws_deg=(0.0, 45.0), n_mirrors=(3, 4, 6),
                     elev_band_deg=args.band)
        print(format_sweep(rows))
        plot_sweep(args.sweep, rows)
        print(f"sweep figure: {args.sweep}")
        return 0
    camera = lenses[args.lens]
    mirrors = pyramid(args.mirrors, args.tilt, yaw_deg=args.yaw, camera=camera)
    print(design_report(camera, mirrors, elev_band_deg=args.band).format())
    if args.figure is not None:
        plot_mirror_regions(args.figure, camera, mirrors)
        print(f"mirror regions: {args.figure}")
    return 0


def _add_config_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", help="a bundled preset (see `omnitof config --list`)")
    p.add_argument("--config", type=Path, help="a YAML configuration file (over the preset)")
    p.add_argument("--particles", type=int, help="number of particles (overrides the configuration)")
    p.add_argument("--seed", type=_seed, help="random seed (overrides the configuration)")
    p.add_argument("--threads", type=int, help="worker threads, 0 = all cores (results do not depend on it)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="omnitof", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"omnitof {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("slam", help="run particle-filter SLAM on a ToF bag, a CARMEN log or a LaserScan ROS bag")
    p.add_argument("log", type=Path, help="ROS 1/2 bag of ToF images + Odometry (omnitof simulate), CARMEN log "
                   "(plain, .gz or .bz2), or ROS 1/2 bag with LaserScan + Odometry")
    p.add_argument("--out", type=Path, required=True, help="results folder")
    _add_config_options(p)
    p.add_argument("--relations", type=Path, help="benchmark relations file to score the trajectory with")
    p.add_argument("--max-scans", type=_positive_int, help="process only the first N scans")
    p.add_argument("--skip-bad-lines", action="store_true", help="skip and count malformed log lines")
    p.add_argument("--scan-delay", type=_scan_delay, metavar="SECONDS|auto",
                   help="the scans were taken this long before their timestamps: take each scan's odometry "
                   "from then; 'auto' (the default for laser logs and LaserScan bags) estimates it from the data "
                   "(omnitof.slam.timing), or uses 0 where the timestamps do not allow it")
    p.add_argument("--calibration", type=Path, help="ToF bags: the rig's calibration YAML (omnitof calibrate); "
                   "default: the true rig of a simulated bag")
    p.add_argument("--height", type=_number(above=0), help="ToF bags: height of the scan slice above the floor (m)")
    p.add_argument("--band", type=_number(above=0), help="ToF bags: half-thickness of the scan slice (m)")
    p.add_argument("--map3d", action="store_true", help="ToF bags: also build the 3D voxel map (map3d.ply, map3d.png)")
    p.add_argument("--map3d-every", type=_positive_int, default=5, help="ToF bags: frames between those fed to the 3D map")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_slam)

    p = sub.add_parser("scans", help="extract the 360° range readings of a ToF bag and write them as a CARMEN log "
                       "or a LaserScan bag, for other SLAM tools")
    p.add_argument("log", type=Path, help="ROS 1/2 bag of ToF images + Odometry (omnitof simulate)")
    p.add_argument("--out", type=Path, required=True,
                   help="FILE.clf / .log: a CARMEN log; FILE.bag: a ROS 1 bag; otherwise a ROS 2 bag folder")
    p.add_argument("--calibration", type=Path, help="the rig's calibration YAML (default: a simulated bag's true rig)")
    p.add_argument("--height", type=_number(above=0), help="height of the scan slice above the floor (m)")
    p.add_argument("--band", type=_number(above=0), help="half-thickness of the scan slice (m)")
    p.add_argument("--max-frames", type=_positive_int, help="only the first N frames")
    p.add_argument("--figure", type=Path, help="draw the middle frame's scan (PNG)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_scans)

    p = sub.add_parser("eval", help="evaluate results")
    esub = p.add_subparsers(dest="eval_command", required=True)
    e = esub.add_parser("relations", help="Kümmerle et al. 2009 relations metric of a TUM trajectory")
    e.add_argument("trajectory", type=Path, help="TUM trajectory (timestamps on the log's clock)")
    e.add_argument("relations", type=Path, help="relations file: t1 t2 x y z roll pitch yaw")
    e.add_argument("--tolerance", type=_number(at_least=0), default=1e-3, help="timestamp match tolerance (s)")
    e.set_defaults(func=cmd_eval_relations)

    p = sub.add_parser("config", help="print the configuration a run would use")
    _add_config_options(p)
    p.add_argument("--list", action="store_true", help="list the bundled presets")
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("design", help="measure a mirror-pyramid rig: bearing coverage, elevation bands")
    p.add_argument("--lens", choices=["standard", "wide"], default="wide", help="SR4000 lens (43.6° or 69°)")
    p.add_argument("--mirrors", type=int, default=4, help="number of mirrors")
    p.add_argument("--tilt", type=_number(), default=56.0, help="mirror tilt from the optical axis (deg)")
    p.add_argument("--yaw", type=_number(at_least=-360, at_most=360), default=0.0, help="pyramid yaw against the driving direction (deg)")
    p.add_argument("--band", type=_number(), default=10.0, help="usable elevations: ± this around horizontal (deg)")
    p.add_argument("--figure", type=Path, help="draw the mirror regions of the image (PNG)")
    p.add_argument("--sweep", type=Path, metavar="PNG", help="sweep tilt, yaw, mirrors and lens; plot to PNG")
    p.set_defaults(func=cmd_design)

    p = sub.add_parser("simulate", help="simulate a robot driving a world with the omnidirectional ToF sensor and "
                       "write a ROS 2 bag; or (`simulate calibration`) render calibration target images")
    p.add_argument("what", nargs="?", choices=["sequence", "calibration"], default="sequence",
                   help="sequence (default): the robot's drive as a bag; calibration: checkerboard and four-dot "
                   "target images with the true calibration (as `omnitof calibrate render-targets`)")
    p.add_argument("--world", default="corridor1", help="a bundled world (room, office, corridor1, corridor2) or a world YAML file")
    p.add_argument("--out", type=Path, required=True, help="the bag folder (or, for calibration, the image folder) to write")
    p.add_argument("--placements", type=_positive_int, default=8, help="calibration: dot-target placements per mirror")
    p.add_argument("--boards", type=_positive_int, default=30, help="calibration: checkerboard images")
    p.add_argument("--seed", type=_seed, default=0, help="fixes the odometry noise, the sensor noise and the sub-ray jitter")
    p.add_argument("--speed", type=_number(above=0), default=0.4, help="driving speed (m/s)")
    p.add_argument("--samples", action="store_true", help="also write the raw samples A0..A3 (3x the size)")
    p.add_argument("--max-frames", type=_positive_int, help="write only the first N frames")
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap", help="ROS 2 bag storage")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("demo", help="the whole system on a simulated world: simulate, calibrate, extract scans, "
                       "SLAM, 3D map, evaluate, report")
    p.add_argument("--world", default="corridor1", help="a bundled world (room, office, corridor1, corridor2) or a world YAML")
    p.add_argument("--out", type=Path, default=Path("results/demo"), help="results folder")
    p.add_argument("--seed", type=_seed, default=0, help="fixes every random draw")
    p.add_argument("--preset", default="tof-scanmatch",
                   help="SLAM preset: tof-scanmatch (the scan-matching proposal) or tof (the paper's filter)")
    p.add_argument("--particles", type=int, default=200, help="number of particles (default 200)")
    p.add_argument("--true-rig", action="store_true", help="skip the calibration and use the true rig")
    p.add_argument("--max-frames", type=_positive_int, help="stop after N frames (a quick look)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_demo)
    from omnitof.cli_calibrate import add_calibrate_parser
    add_calibrate_parser(sub)
    return parser


_library_format = warnings.formatwarning


def _format_warning(message, category, filename, lineno, line=None) -> str:
    # Warnings about the user's data read as one line, without our source location. Another
    # library's warning is not a message of omnitof's: it keeps its own form, so that it reads
    # as what it is (a bug to fix where it arises, not news about the data).
    if issubclass(category, OmnitofWarning):
        return f"omnitof: warning: {message}\n"
    return _library_format(message, category, filename, lineno, line)


def main(argv: list[str] | None = None) -> int:
    from omnitof.interrupts import Terminated, signals_as_exceptions

    args = build_parser().parse_args(argv)
    warnings.formatwarning = _format_warning
    # SIGTERM is handled like Ctrl-C: the run unwinds, removes what it had begun and says so.
    with signals_as_exceptions():
        try:
            return args.func(args)
        except OmnitofError as err:
            print(f"omnitof: error: {err}", file=sys.stderr)
            return 2
        except OSError as err:  # an input that cannot be read, an output folder that cannot be written
            print(f"omnitof: error: {err}", file=sys.stderr)
            return 2
        except Terminated:
            print("omnitof: terminated (SIGTERM); nothing half-written was left", file=sys.stderr)
            return 128 + signal.SIGTERM
        except KeyboardInterrupt:
            print("omnitof: interrupted; nothing half-written was left", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
