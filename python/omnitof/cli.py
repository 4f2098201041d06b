"""The `omnitof` command. Subcommands parse arguments and call the library; no logic here.

Errors that come from the user's input (OmnitofError) print one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import tempfile

import numpy as np
import warnings
from pathlib import Path

from omnitof import __version__
from omnitof.errors import OmnitofError, OmnitofWarning, OutputError, os_error_message


def _config_from_args(args: argparse.Namespace, default_preset: str | None = None):
    from omnitof.slam.config import parse_setting
    from omnitof.slam_run import slam_config

    # A --config file lies over the input's default preset as --set does: a file of a few fields
    # (`filter: {particles: 50}`) changes those and nothing else. (It replaced the preset: the
    # fields it left out fell to the bare defaults, the paper's beam model on a laser log, without
    # a word.) A run's own config.yaml names every field, so it reproduces the run either way.
    preset = args.preset if args.preset is not None else default_preset
    settings = dict(parse_setting(item) for item in (getattr(args, "set", None) or []))
    return slam_config(preset=preset, config=args.config, settings=settings,
                       particles=getattr(args, "particles", None), seed=getattr(args, "seed", None),
                       threads=getattr(args, "threads", None))


def _progress_bar(total: int, enabled: bool, desc: str, unit: str = "scan"):
    from omnitof.io.terminal import progress_bar

    return progress_bar(total, enabled=enabled, desc=desc, unit=unit)


def _bar_factory(args: argparse.Namespace):
    """Progress bars for the library's stages (omnitof.slam_run.BarFactory); none with --quiet."""
    return lambda total, desc, unit: _progress_bar(total, not args.quiet, desc, unit)


def _summary_line(stats: dict) -> str:
    line = (
        f"scans {stats['scans']} (integrated {stats['integrated']}), "
        f"time {stats['seconds']:.1f} s, particles {stats['particles']}, "
        f"resamplings {stats['resamplings']}"
    )
    # A wheel glitch that the odometry check repaired is worth a look at the robot's wheels.
    corrected = stats.get("odometry_corrected_scans") or []
    if corrected:
        shown = ", ".join(str(k) for k in corrected[:5]) + (", ..." if len(corrected) > 5 else "")
        line += f"; odometry replaced by the odometry check at {len(corrected)} scan(s): {shown}"
        # A relocalisation onto an older map is the front end closing a loop, not the wheels.
        moved = [c["scan"] for c in stats.get("check_corrections", []) if c["verdict"].startswith("relocalised")]
        if moved:
            line += f" ({len(moved)} of them relocalised onto an older map: {', '.join(str(k) for k in moved[:5])})"
    return line


def cmd_slam(args: argparse.Namespace) -> int:
    from omnitof.slam_run import SlamRequest, default_preset, slam_to_folder

    cfg_2d = None
    if args.filter == "3d" and args.compare_2d:
        # The 2D filter beside the 3D one runs as `omnitof slam` without --filter 3d would.
        cfg_2d = _config_from_args(args, default_preset=default_preset(args.log, args.tof_topics))
    if args.filter == "3d":
        args.set = [*(args.set or []), "filter3d.enabled=true"]
    preset = "tof3d" if args.filter == "3d" else default_preset(args.log, args.tof_topics)
    cfg = _config_from_args(args, default_preset=preset)
    request = SlamRequest(
        log=args.log, relations=args.relations, max_scans=args.max_scans, skip_bad_lines=args.skip_bad_lines,
        scan_delay=args.scan_delay, calibration=args.calibration, height=args.height, band=args.band,
        map3d=args.map3d, map3d_every=args.map3d_every, compare_2d=args.compare_2d,
        multipath_compensation=args.multipath_compensation,
        tof_topics=args.tof_topics, tof_depth=args.tof_distance == "depth", laser_topics=args.laser_topics,
        ignore_odometry=args.ignore_odometry,
    )
    run = slam_to_folder(request, cfg, args.out, cfg_2d=cfg_2d, bar=_bar_factory(args))
    print(_summary_line(run.result.stats))
    if run.relations is not None:
        print(run.relations.format())
    if "trajectory_error" in run.extra:
        te = run.extra["trajectory_error"]
        print(f"trajectory error (mean, final): SLAM {te['slam']['mean']:.3f} m, {te['slam']['final']:.3f} m; "
              f"odometry {te['odometry']['mean']:.3f} m, {te['odometry']['final']:.3f} m")
        if te.get("slam_rigid"):
            print(f"  after a rigid alignment to the truth (the map's shape, not its placement): SLAM mean "
                  f"{te['slam_rigid']['mean']:.3f} m ({te['slam_rigid']['rotation_deg']:+.2f} deg)")
    if "filter2d" in run.extra:
        d = run.extra["filter2d"]["difference_3d_to_2d"]
        print(f"3D filter vs 2D filter: mean {d['mean']:.3f} m, max {d['max']:.3f} m apart")
    print(f"results in {run.paths['summary'].parent}")
    return 0


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


def _whole(at_least: int, at_most: int | None = None):
    """An argparse type for whole numbers of at least `at_least` (and at most `at_most`)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < at_least:
            raise argparse.ArgumentTypeError(f"expected at least {at_least}, got {value}")
        if at_most is not None and value > at_most:
            raise argparse.ArgumentTypeError(f"expected at most {at_most}, got {value}")
        return value

    return parse


_positive_int = _whole(1)
# Rendered calibration images: a real calibration takes tens of boards and placements; a
# thousand renders take minutes, and more is a typo (100 000 boards ran on and on).
_image_count = _whole(1, 1000)


# A laser's scan delay is a fraction of a second; seconds beyond this are a mistake, not a delay.
MAX_SCAN_DELAY_S = 10.0
SEED_LIMIT = 2**63  # seeds are u64 in the core and numpy's generators take any below it


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not 0 <= value < SEED_LIMIT:
        raise argparse.ArgumentTypeError(f"expected a seed in 0 … 2^63 - 1, got {value}")
    return value


def _number(*, above: float | None = None, at_least: float | None = None, at_most: float | None = None,
            below: float | None = None):
    """An argparse type for finite numbers (and, if given, > `above`, >= `at_least`, <= `at_most`,
    < `below`)."""

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
        if below is not None and not value < below:
            raise argparse.ArgumentTypeError(f"expected a number below {below:g}, got {text!r}")
        return value

    return parse


def _tof_topics(text: str):
    from omnitof.io.rosbag import ToFTopics

    try:
        return ToFTopics.parse(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _laser_topics(text: str):
    from omnitof.io.rosbag import LaserTopics

    try:
        return LaserTopics.parse(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _add_tof_bag_options(p: argparse.ArgumentParser, prefix: str) -> None:
    """--tof-topics and --tof-distance: a camera driver's bag, not the simulator's."""
    p.add_argument("--tof-topics", type=_tof_topics, metavar="ROLE=TOPIC,...",
                   help=f"{prefix}the bag's topics where they are not the simulator's, e.g. "
                   "distance=/cam/distance,amplitude=/cam/amplitude,camera_info=/cam/camera_info,odometry=/odom "
                   "(odometry=/tf: the transform odom → base; roles tf, odom_frame, base_frame too)")
    p.add_argument("--tof-distance", choices=("radial", "depth"), default="radial",
                   help=f"{prefix}what the distance images hold: the radial distance the camera measures "
                   "(the simulator's), or the depth z along the optical axis that many drivers publish")


def _checked_output_file(path: Path, overwrite: bool | None, what: str) -> None:
    """Refuse a file output before any work: a folder in its place, a folder that is missing or
    not writable, or (where `overwrite` is not None) a file there without --overwrite."""
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; {what} is a file: give a file name")
    if overwrite is False and os.path.lexists(path):
        raise OutputError(f"{path} exists already; replace it with --overwrite")
    if not path.parent.is_dir():
        raise OutputError(f"{path}: cannot write: its folder does not exist")
    try:  # a file made and removed beside it: os.access says yes to root even where nothing can be made
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".probe"):
            pass
    except OSError as err:
        raise OutputError(f"{path}: cannot write: {err.strerror or err}") from None


def cmd_scans(args: argparse.Namespace) -> int:
    from omnitof.slam_run import read_tof_input

    # Every output checked before the frames are read: a bad path costs no work, and a run that
    # fails leaves nothing written.
    out = Path(args.out)
    carmen = out.suffix in (".clf", ".log", ".txt")
    if carmen:
        _checked_output_file(out, args.overwrite, "a CARMEN log")
    else:
        from omnitof.io.rosbag import checked_bag_target

        target, source = Path(os.path.abspath(out)).resolve(), Path(args.log).resolve()
        if target == source or target in source.parents:
            raise OutputError(f"{out}: is (or holds) the input {args.log}; give the output a new name")
        checked_bag_target(out, args.overwrite)
    if args.figure is not None:
        _checked_output_file(Path(args.figure), None, "the figure")
    if carmen:
        from omnitof.io.rosbag import ToFTopics, read_tof_bag

        if read_tof_bag(args.log, topics=args.tof_topics or ToFTopics()).odometry is None:
            raise OmnitofError(f"{args.log}: has no odometry, and a CARMEN log holds one pose per scan; write a "
                               "LaserScan bag instead (--out NAME.bag or a folder), which can be without, or map "
                               "it with `omnitof slam`, which estimates the odometry from the scans")
    data = read_tof_input(args.log, calibration=args.calibration, height=args.height, band=args.band,
                          multipath=args.multipath_compensation, max_frames=args.max_frames, bar=_bar_factory(args),
                          topics=args.tof_topics, depth=args.tof_distance == "depth")
    scans = data.scans
    if len(scans) == 0:
        raise OmnitofError(f"{args.log}: no frame gave a scan (see the warnings above); nothing written to {out}")
    if carmen:
        from omnitof.io.carmen import write_carmen

        write_carmen(out, scans)
        kind = "CARMEN log"
    else:
        from omnitof.io.rosbag import write_laserscan_bag

        version = 1 if out.suffix == ".bag" else 2
        write_laserscan_bag(out, scans, version=version, overwrite=args.overwrite)
        odometry = ", nav_msgs/Odometry on /odom" if scans.odometry_known else ", no odometry"
        kind = f"ROS {version} bag (sensor_msgs/LaserScan on /scan{odometry})"
    if args.figure is not None:
        from omnitof.viz.scans import plot_scan

        i = len(scans) // 2
        plot_scan(args.figure, scans.scan_ranges(i), scans.scan_angles(i), max_range=scans.max_range,
                  title=f"frame {i} of {Path(args.log).name}")
    filled = float(np.isfinite(scans.ranges[scans.beam_mask]).mean()) if len(scans) else 0.0
    print(f"{len(scans)} scans of 360 bins ({100 * filled:.1f} % with a reading; rig from {data.rig_source}; "
          f"multipath compensation {data.multipath_rule}) written as a {kind}: {out}")
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


def cmd_eval_ate(args: argparse.Namespace) -> int:
    from omnitof.eval.ate import evaluate_ate
    from omnitof.io.tum import read_tum

    _checked_eval_outputs(args, [args.figure])
    result, estimate, truth = evaluate_ate(
        read_tum(args.estimate), read_tum(args.truth), align=args.align, max_diff=args.max_diff,
        sources=(args.estimate, args.truth),
    )
    print(result.format())
    if args.figure is not None:
        from omnitof.viz.maps import plot_trajectory_errors

        plot_trajectory_errors(args.figure, estimate, truth,
                               title=f"{Path(args.estimate).name} against {Path(args.truth).name} ({args.align})")
        print(f"wrote {args.figure}")
    _write_eval_result(args.out, result.to_dict())
    return 0


def cmd_eval_rpe(args: argparse.Namespace) -> int:
    from omnitof.eval.rpe import evaluate_rpe
    from omnitof.io.tum import read_tum

    if args.unit == "f" and args.delta != int(args.delta):
        raise OmnitofError(f"--delta {args.delta:g} --unit f: a number of poses must be a whole number")
    _checked_eval_outputs(args, [])
    result = evaluate_rpe(read_tum(args.estimate), read_tum(args.truth), delta=args.delta, unit=args.unit,
                          max_diff=args.max_diff, sources=(args.estimate, args.truth))
    print(result.format())
    _write_eval_result(args.out, result.to_dict())
    return 0


def cmd_eval_map(args: argparse.Namespace) -> int:
    from omnitof.eval.map_agreement import MapAgreementError, compare_maps
    from omnitof.io.rosmap import map_image, read_ros_map

    if args.initial is not None and args.align in ("none", "search"):
        raise OmnitofError(f"--initial is the pose ICP starts from: it goes with --align initial (or no --align), "
                           f"not --align {args.align}")
    align = args.align or ("initial" if args.initial is not None else "search")
    # The outputs may name neither a map description nor the image it names.
    inputs = (args.estimate, args.reference, map_image(args.estimate), map_image(args.reference))
    _checked_eval_outputs(args, [args.figure], inputs=inputs)
    estimate, reference = read_ros_map(args.estimate), read_ros_map(args.reference)
    for name, occ in (("estimate", estimate), ("reference", reference)):
        if occ.resolution > args.tolerance:
            warnings.warn(f"the {name}'s cells ({100 * occ.resolution:g} cm) are coarser than --tolerance "
                          f"({100 * args.tolerance:g} cm): where a wall lies in them is blurred by up to half a cell, "
                          "so the shares depend on where the walls fall on the grid; give a --tolerance of at least "
                          "a cell", OmnitofWarning, stacklevel=1)
    initial = (0.0, 0.0, 0.0) if args.initial is None else \
        (args.initial[0], args.initial[1], math.radians(args.initial[2]))
    try:
        result, moved, distance = compare_maps(estimate, reference, align=align, initial=initial,
                                               tolerance=args.tolerance)
    except MapAgreementError as e:
        raise OmnitofError(f"{args.estimate} against {args.reference}: {e}") from None
    print(result.format())
    for text in result.warnings():
        warnings.warn(text, OmnitofWarning, stacklevel=1)
    if args.figure is not None:
        from omnitof.viz.maps import plot_map_agreement

        est, ref = Path(args.estimate), Path(args.reference)
        # Two runs' maps are both map.yaml: then their folders tell them apart.
        names = (est.name, ref.name) if est.name != ref.name else (f"{est.parent.name}/{est.name}",
                                                                   f"{ref.parent.name}/{ref.name}")
        plot_map_agreement(args.figure, reference, moved, distance, args.tolerance,
                           title=f"{names[0]} on {names[1]}")
        print(f"wrote {args.figure}")
    _write_eval_result(args.out, {"estimate": str(args.estimate), "reference": str(args.reference),
                                  **result.to_dict()})
    return 0


def _write_eval_result(path: Path | None, data: dict) -> None:
    """`eval`'s --out: the result as YAML, written whole or not at all."""
    from omnitof.errors import dump_yaml
    from omnitof.io.atomic import atomic_write

    if path is None:
        return
    with atomic_write(path) as f:
        dump_yaml(data, f, sort_keys=False)
    print(f"wrote {path}")


def _checked_eval_outputs(args: argparse.Namespace, others: list[Path | None], *,
                          inputs: tuple[Path, ...] | None = None) -> None:
    """`eval`'s --out (and the `others`) checked before any work, and none of them an input
    (`inputs`, default the estimate and the truth)."""
    inputs = {Path(os.path.abspath(p)).resolve() for p in (inputs or (args.estimate, args.truth))}
    outputs: set[Path] = set()
    for path, what in [(args.out, "the result (YAML)"), *((p, "the figure") for p in others)]:
        if path is None:
            continue
        if what == "the figure" and Path(path).suffix.lower() != ".png":
            raise OutputError(f"{path}: the figure is written as PNG; give it a name ending in .png")
        if Path(os.path.abspath(path)).resolve() in outputs:
            raise OutputError(f"{path}: named for two outputs (--out and --figure); give each its own")
        outputs.add(Path(os.path.abspath(path)).resolve())
        if Path(os.path.abspath(path)).resolve() in inputs:
            raise OutputError(f"{path}: is one of the inputs; give the output a new name")
        _checked_output_file(Path(path), None, what)


def cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "report":
        if args.folder is None or args.out is not None:
            raise OmnitofError("usage: omnitof bench report DIR (the folder of an experiment's --out)")
        from omnitof.bench.table import write_tables

        folder = Path(args.folder)
        if not (folder / "runs").is_dir():
            raise OmnitofError(f"{folder}: no runs/ folder here: not the --out folder of an experiment")
        table = write_tables(folder)
        print(f"{len(table.rows)} runs; table in {folder / 'table.md'} and {folder / 'table.csv'}; "
              f"{len(table.figures)} figures")
        return 0
    if args.folder is not None:
        raise OmnitofError(f"unexpected argument {args.folder!r}: omnitof bench EXPERIMENT.yaml --out DIR")
    if args.out is None:
        raise OmnitofError("omnitof bench EXPERIMENT.yaml needs --out DIR")
    if args.workers is not None and args.scheduler is not None:
        raise OmnitofError("--workers starts a local cluster, --scheduler uses a running one: give one of them")
    from omnitof.bench import load_experiment
    from omnitof.bench.runner import run_experiment
    from omnitof.bench.table import write_tables

    experiment = load_experiment(args.what)
    try:
        outcome = run_experiment(experiment, args.out, workers=args.workers, scheduler=args.scheduler,
                                 progress=not args.quiet)
    except KeyboardInterrupt:
        if (Path(args.out) / "runs").is_dir():
            print(f"interrupted: the runs finished so far are in {args.out}; the same command runs the rest",
                  file=sys.stderr)
        else:  # stopped while planning: DIR was never made
            print(f"interrupted before {args.out} was made; the same command starts again", file=sys.stderr)
        raise
    table = write_tables(args.out)
    failed = sum(r["status"] != "ok" for r in table.rows)
    print(f"{outcome.planned} runs: {outcome.skipped} were complete, {len(outcome.done)} ran now, {failed} failed; "
          f"table in {Path(args.out) / 'table.md'} and table.csv, {len(table.figures)} figures")
    return 1 if failed else 0


def cmd_config(args: argparse.Namespace) -> int:
    from omnitof.slam.config import preset_names

    if args.list:
        print("\n".join(preset_names()))
        return 0
    print(_config_from_args(args).to_yaml(), end="")
    return 0


def _tof_errors(text: str) -> str:
    from omnitof.sensor.tof_errors import ToFErrors, ToFErrorsError

    try:
        ToFErrors.parse(text)
    except ToFErrorsError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def _add_tof_errors(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tof-errors", type=_tof_errors, default="default", metavar="LIST",
                   help="the camera's systematic errors to simulate: default (all but multipath), all, none, or a "
                   "comma list of wiggling, amplitude_offset, fixed_pattern, motion, multipath, illumination "
                   "(docs/guide/simulation.md)")


def cmd_demo(args: argparse.Namespace) -> int:
    from omnitof.demo import run_demo

    run_demo(args.out, world=args.world, seed=args.seed, preset=args.preset, particles=args.particles,
             calibrate=not args.true_rig, max_frames=args.max_frames, progress=not args.quiet,
             refine=not args.closed_form, tof_errors=args.tof_errors)
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    if args.what == "calibration":
        from omnitof.cli_calibrate import cmd_render_targets

        return cmd_render_targets(args)
    from omnitof.sensor.tof import SensorNoise
    from omnitof.sensor.tof_errors import ToFErrors
    from omnitof.sim.sequence import MotionSettings, make_sequence, simulate_bag
    from omnitof.sim.worlds import load_world

    sensor = SensorNoise(errors=ToFErrors.parse(args.tof_errors))
    world = load_world(args.world)
    motion = MotionSettings(speed=args.speed)
    total = len(make_sequence(world, seed=args.seed, motion=motion))
    if args.max_frames is not None:
        total = min(total, args.max_frames)
    with _progress_bar(total, not args.quiet, "render", unit="frame") as bar:
        sequence, written = simulate_bag(
            world, args.out, seed=args.seed, motion=motion, samples=args.samples,
            max_frames=args.max_frames, storage=args.storage, overwrite=args.overwrite,
            progress=bar.update, sensor=sensor,
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
    for path in (args.sweep, args.figure):  # before the work, not after the table is printed
        if path is not None:
            _checked_output_file(path, None, "the figure")
    if args.sweep is not None:
        rows = sweep(lenses, tilts_deg=range(40, 66, 2), yaws_deg=(0.0, 45.0), n_mirrors=(3, 4, 6),
                     elev_band_deg=args.band)
        print(format_sweep(rows))
        plot_sweep(args.sweep, rows)
        print(f"sweep figure: {args.sweep}")
        return 0
    from omnitof.sensor.design import apex_sweep, format_apex_sweep
    from omnitof.sensor.illumination import DEFAULT_LIT_DISTANCE, lit_share
    from omnitof.sensor.tof_errors import ToFErrors

    camera = lenses[args.lens]
    mirrors = pyramid(args.mirrors, args.tilt, yaw_deg=args.yaw, camera=camera)
    report = design_report(camera, mirrors, elev_band_deg=args.band)
    # A mirror without a pixel has no elevations or bearings to report (its rows were nan): too
    # many mirrors split the image into wedges narrower than the edge margins, too small a tilt
    # turns the faces edge-on to the camera.
    empty = next((m for m in report.mirrors if m.pixels == 0), None)
    if empty is not None:
        raise OmnitofError(
            f"--mirrors {args.mirrors} --tilt {args.tilt:g}: mirror {empty.name!r} keeps no pixel of the {args.lens} "
            f"lens's {camera.width}×{camera.height} image beyond the {report.edge_margin_px:g} px edge margin, so "
            "there is nothing to measure: every mirror must keep a pixel; use fewer mirrors or a larger tilt")
    print(report.format())
    leds = ToFErrors.realistic()
    share = lit_share(camera, mirrors, leds, DEFAULT_LIT_DISTANCE)
    print(f"lit by the camera's LEDs ({leds.led_count} on a {100 * leds.led_radius:g} cm ring, surface at "
          f"{DEFAULT_LIT_DISTANCE:g} m): {100 * share:.1f} % of the mirror pixels")
    if args.apex_sweep:
        print(format_apex_sweep(apex_sweep(camera, args.mirrors, args.tilt, args.yaw)))
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
    p.add_argument("--set", action="append", metavar="SECTION.FIELD=VALUE",
                   help="set one configuration field, e.g. --set backend.enabled=false (VALUE read as YAML; "
                   "repeatable; over the preset and --config, under --particles, --seed and --threads)")


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
                   "from then; 'auto' (the default for laser logs and LaserScan bags with odometry) estimates it from the data "
                   "(omnitof.slam.timing), or uses 0 where the timestamps do not allow it")
    p.add_argument("--calibration", type=Path, help="ToF bags: the rig's calibration YAML (omnitof calibrate); "
                   "default: the true rig of a simulated bag")
    p.add_argument("--height", type=_number(above=0), help="ToF bags: height of the scan slice above the floor (m)")
    p.add_argument("--band", type=_number(above=0), help="ToF bags: half-thickness of the scan slice (m)")
    p.add_argument("--multipath-compensation", choices=("auto", "on", "off"), default="auto",
                   help="ToF bags: take each frame's interreflection, predicted from its own points, out of its "
                   "distances (omnitof.scan.multipath); auto: on for a simulated bag whose camera has multipath, "
                   "with that camera's figures from the sidecar")
    _add_tof_bag_options(p, "ToF bags: ")
    p.add_argument("--laser-topics", type=_laser_topics, metavar="ROLE=NAME,...",
                   help="LaserScan bags: where the scans and odometry are when they cannot be found by type; roles "
                   "scan, odometry (a nav_msgs/Odometry topic, or a tf topic such as /tf for the transform "
                   "odom_frame → base_frame), ground_truth, tf, tf_static, odom_frame, base_frame; e.g. "
                   "scan=/base_scan,odometry=/tf,odom_frame=odom_combined")
    p.add_argument("--ignore-odometry", action="store_true",
                   help="set the input's odometry aside and estimate it from the scans, each matched against "
                   "the scans before it (as for an input that has none, which needs no option)")
    p.add_argument("--map3d", action="store_true", help="ToF bags: also build the 3D voxel map (map3d.ply, map3d.png)")
    p.add_argument("--map3d-every", type=_positive_int, default=5, help="ToF bags: frames between those fed to the 3D map")
    p.add_argument("--filter", choices=("2d", "3d"), default="2d",
                   help="ToF bags: 3d runs the paper's 3D variant (voxel maps per particle, every mirror pixel; "
                   "default preset tof3d) and writes map3d.ply/png, map.pgm as its projection")
    p.add_argument("--compare-2d", action="store_true",
                   help="with --filter 3d: also run the 2D filter (as omnitof slam without --filter 3d would: its "
                   "default preset, or --preset/--config/--set as given) and record the trajectories' difference")
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
    p.add_argument("--multipath-compensation", choices=("auto", "on", "off"), default="auto",
                   help="take each frame's interreflection, predicted from its own points, out of its "
                   "distances (omnitof.scan.multipath); auto: on for a simulated bag whose camera has multipath, "
                   "with that camera's figures from the sidecar")
    _add_tof_bag_options(p, "")
    p.add_argument("--max-frames", type=_positive_int, help="only the first N frames")
    p.add_argument("--figure", type=Path, help="draw the middle frame's scan (PNG)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag or log (nothing else)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_scans)

    p = sub.add_parser("eval", help="evaluate results")
    esub = p.add_subparsers(dest="eval_command", required=True)
    e = esub.add_parser("relations", help="Kümmerle et al. 2009 relations metric of a TUM trajectory")
    e.add_argument("trajectory", type=Path, help="TUM trajectory (timestamps on the log's clock)")
    e.add_argument("relations", type=Path, help="relations file: t1 t2 x y z roll pitch yaw")
    e.add_argument("--tolerance", type=_number(at_least=0), default=1e-3, help="timestamp match tolerance (s)")
    e.set_defaults(func=cmd_eval_relations)
    e = esub.add_parser("ate", help="absolute trajectory error of a TUM trajectory against a TUM ground truth, "
                        "after aligning their frames",
                        description="Pairs at most one estimate pose with each truth pose, the nearest in time (within "
                        "--max-diff), aligns the estimate to the truth (rigid by default: a SLAM map's frame is its own) and "
                        "prints the position and heading errors. docs/guide/evaluation.md.")
    e.add_argument("estimate", type=Path, help="the estimated trajectory (TUM), e.g. a run's trajectory.tum")
    e.add_argument("truth", type=Path, help="the ground truth (TUM) on the same clock")
    e.add_argument("--align", choices=("none", "rigid", "similarity"), default="rigid",
                   help="fit a rotation and translation (rigid, default), and a scale (similarity), or none "
                   "(the frames are the same, as in omnitof's simulated runs)")
    e.add_argument("--max-diff", type=_number(at_least=0), default=0.01,
                   help="largest time difference of a pair of poses (s; default 0.01)")
    e.add_argument("--figure", type=Path, help="draw the truth and the aligned estimate, coloured by error (PNG)")
    e.add_argument("--out", type=Path, help="write the result as YAML")
    e.set_defaults(func=cmd_eval_ate)
    e = esub.add_parser("rpe", help="relative pose error of a TUM trajectory against a TUM ground truth, over a "
                        "fixed distance, time or number of poses",
                        description="Pairs each truth pose with the first one --delta further along it and scores the "
                        "estimate's relative motion between the same times against the truth's (no alignment "
                        "needed). docs/guide/evaluation.md.")
    e.add_argument("estimate", type=Path, help="the estimated trajectory (TUM)")
    e.add_argument("truth", type=Path, help="the ground truth (TUM) on the same clock")
    e.add_argument("--delta", type=_number(above=0), default=1.0, help="how far apart the paired poses are (default 1)")
    e.add_argument("--unit", choices=("m", "s", "f"), default="m",
                   help="of --delta: metres of the truth's path (default), seconds, or poses")
    e.add_argument("--max-diff", type=_number(at_least=0), default=0.01,
                   help="largest time difference between a truth pose and the estimate's (s; default 0.01)")
    e.add_argument("--out", type=Path, help="write the result as YAML")
    e.set_defaults(func=cmd_eval_rpe)
    e = esub.add_parser("map", help="an occupancy map against a reference map of the same place (map_server "
                        "YAML + PGM), after aligning their frames",
                        description="Moves the estimate's occupied cells into the reference's frame (a global search "
                        "and ICP by default) and prints the share within --tolerance of the reference's walls and the "
                        "share of the reference's walls next to the estimate's free space that it mapped. "
                        "docs/guide/evaluation.md.")
    e.add_argument("estimate", type=Path, help="the map to score (map_server YAML), e.g. a run's map.yaml")
    e.add_argument("reference", type=Path, help="the reference map (map_server YAML): a floor plan, a surveyed map")
    e.add_argument("--align", choices=("search", "initial", "none"), default=None,
                   help="search: a global search over rotation and translation, then ICP (the default without "
                   "--initial); initial: ICP from --initial; none: the maps share a frame")
    e.add_argument("--initial", nargs=3, type=_number(), metavar=("X", "Y", "DEG"),
                   help="where the estimate's origin lies in the reference (m, m, degrees): ICP starts there "
                   "(implies --align initial)")
    e.add_argument("--tolerance", type=_number(above=0), default=0.05,
                   help="how close to a wall counts (m; default 0.05, the demo's)")
    e.add_argument("--figure", type=Path, help="draw the reference and the aligned estimate's walls, coloured by "
                   "their distance (PNG)")
    e.add_argument("--out", type=Path, help="write the result as YAML")
    e.set_defaults(func=cmd_eval_map)

    p = sub.add_parser("bench", help="run an experiment (inputs × presets × settings × seeds) on Dask; "
                       "`bench report DIR` rebuilds its table and figures",
                       description="omnitof bench EXPERIMENT.yaml --out DIR [--workers N | --scheduler ADDRESS]; "
                       "omnitof bench report DIR. The experiment file's fields: docs/guide/bench.md.")
    p.add_argument("what", metavar="EXPERIMENT.yaml|report", help="the experiment file, or `report`")
    p.add_argument("folder", nargs="?", metavar="DIR", help="with `report`: the experiment's folder")
    p.add_argument("--out", type=Path, metavar="DIR", help="the experiment's folder: one results folder per run, the table, "
                   "the figures; an experiment run again into it runs only what is missing")
    p.add_argument("--workers", type=_positive_int, metavar="N", help="worker processes of the local cluster (default: one per core)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (tcp://host:8786) instead of a "
                   "local cluster")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser(
        "config", help="print the configuration a run would use",
        description="Print the configuration a run would use. Without --preset or --config these are "
                    "the bare defaults; `omnitof slam` picks its preset by its input (laser180-scanmatch "
                    "for CARMEN logs and LaserScan bags, tof-scanmatch for ToF bags): name it to see that run's.",
    )
    _add_config_options(p)
    p.add_argument("--list", action="store_true", help="list the bundled presets")
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("design", help="measure a mirror-pyramid rig: bearing coverage, elevation bands")
    p.add_argument("--lens", choices=["standard", "wide"], default="wide", help="SR4000 lens (43.8° or 69°)")
    # More mirrors than the design's 360 one-degree bearing bins (design.BEARING_BINS) cannot be
    # told apart; the bound also keeps a typo such as 10000000 from building that many mirrors.
    p.add_argument("--mirrors", type=_whole(3, at_most=360), default=4,
                   help="number of mirrors (3 to 360; each must keep a pixel of the image)")
    p.add_argument("--tilt", type=_number(above=0, below=90), default=56.0, help="mirror tilt from the optical axis (deg)")
    p.add_argument("--yaw", type=_number(at_least=-360, at_most=360), default=0.0, help="pyramid yaw against the driving direction (deg)")
    p.add_argument("--band", type=_number(at_least=0, at_most=90), default=10.0,
                   help="usable elevations: ± this around horizontal (deg)")
    p.add_argument("--figure", type=Path, help="draw the mirror regions of the image (PNG)")
    p.add_argument("--sweep", type=Path, metavar="PNG", help="sweep tilt, yaw, mirrors and lens; plot to PNG")
    p.add_argument("--apex-sweep", action="store_true",
                   help="the share of mirror pixels the LEDs light, for apex heights 2-20 cm")
    p.set_defaults(func=cmd_design)

    p = sub.add_parser("simulate", help="simulate a robot driving a world with the omnidirectional ToF sensor and "
                       "write a ROS 2 bag; or (`simulate calibration`) render calibration target images")
    p.add_argument("what", nargs="?", choices=["sequence", "calibration"], default="sequence",
                   help="sequence (default): the robot's drive as a bag; calibration: checkerboard and four-dot "
                   "target images with the true calibration (as `omnitof calibrate render-targets`)")
    p.add_argument("--world", default="corridor1", help="a bundled world (room, office, corridor1, corridor2) or a world YAML file")
    p.add_argument("--out", type=Path, required=True, help="the bag folder (or, for calibration, the image folder) to write")
    p.add_argument("--placements", type=_image_count, default=14, help="calibration: dot-target placements per mirror")
    p.add_argument("--boards", type=_image_count, default=30, help="calibration: checkerboard images")
    p.add_argument("--random-boards", action="store_true",
                   help="calibration: checkerboards at random poses (default: poses planned for the intrinsics)")
    p.add_argument("--pair-boards", type=_image_count, default=2,
                   help="calibration: plain boards seen through each two neighbouring mirrors (for `calibrate refine`)")
    p.add_argument("--walls", action="store_true",
                   help="calibration: also a flat wall facing each mirror at 0.5-6.5 m, with --tof-errors, and "
                        "walls/walls.yaml (for `calibrate distance`)")
    p.add_argument("--seed", type=_seed, default=0, help="fixes the odometry noise, the sensor noise and the sub-ray jitter")
    p.add_argument("--speed", type=_number(above=0), default=0.4, help="driving speed (m/s)")
    p.add_argument("--samples", action="store_true", help="also write the raw samples A0..A3 (3x the size)")
    _add_tof_errors(p)
    p.add_argument("--max-frames", type=_positive_int, help="write only the first N frames")
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap", help="ROS 2 bag storage")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bag (nothing else)")
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
    p.add_argument("--closed-form", action="store_true",
                   help="keep the closed-form calibration (intrinsics, then mirrors) without the joint refinement")
    p.add_argument("--max-frames", type=_positive_int, help="stop after N frames (a quick look)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_tof_errors(p)
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
        except BrokenPipeError:
            # The reader of our output went away (`omnitof eval … | head`): as other Unix tools,
            # stop quietly; stdout goes to /dev/null so that Python's own flush at exit is silent.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 128 + signal.SIGPIPE
        except OSError as err:  # an input that cannot be read, an output folder that cannot be written
            print(f"omnitof: error: {os_error_message(err)}", file=sys.stderr)
            return 2
        except MemoryError as err:  # a setting or input that asks for more than any check foresaw
            detail = f" ({err})" if str(err) else ""
            print(f"omnitof: error: out of memory{detail}: an input or setting asks for more than this "
                  "machine has; nothing half-written was left", file=sys.stderr)
            return 2
        except Terminated:
            print("omnitof: terminated (SIGTERM); nothing half-written was left", file=sys.stderr)
            return 128 + signal.SIGTERM
        except KeyboardInterrupt:
            print("omnitof: interrupted; nothing half-written was left", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
