"""One SLAM run of a recording into its results folder: what `omnitof slam` does, as a function,
so that `omnitof bench` runs exactly the same code for each of its runs (the same trajectory
bytes, whichever way a run was started).

    read the input (a ToF bag, a CARMEN log or a LaserScan bag), keep the first `max_scans`
    → re-time the odometry by the scan delay (estimated by default for laser input)
    → run_slam → score it (benchmark relations; the ground truth a simulated bag carries)
    → the results folder (omnitof.results)

`SlamRequest` holds the options of `omnitof slam` that choose and score the input,
`slam_config` builds the configuration from a preset, a file and overrides, and
`slam_to_folder` does the run.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import InputError, OmnitofError
from omnitof.scan.extract import ScanSettings
from omnitof.slam.config import SlamConfig
from omnitof.types import ScanSequence, Trajectory

# Without --preset: the scan-matching filter with the pose-graph back end, for either kind of
# input (the paper's filter is `--preset paper` / `--preset tof`).
DEFAULT_PRESET_LASER = "laser180-scanmatch"
DEFAULT_PRESET_TOF = "tof-scanmatch"


@dataclass(frozen=True)
class SlamRequest:
    """The input of a run and how it is scored; the fields are `omnitof slam`'s options.

    scan_delay: seconds, "auto" (estimated from the log, `omnitof.slam.timing`) or None for the
        default: "auto" for laser logs and LaserScan bags with odometry (they are stamped when
        the reading arrives), none for ToF bags and for odometry estimated from the scans. calibration, height, band, map3d, map3d_every, tof_topics
        (an `io.rosbag.ToFTopics`; default the simulator's topics), tof_depth (the distance
        images hold depth z, not the radial distance): ToF bags only. laser_topics (an
        `io.rosbag.LaserTopics`; default: found by type): LaserScan bags only.
    ignore_odometry: set the input's odometry aside and estimate it from the scans, as for an
        input that has none (omnitof.slam.scan_odometry).
    compare_2d: with the 3D filter (`filter3d.enabled`), also run the 2D filter on the same
        scans and record how far the two trajectories lie apart (trajectory_2d.tum, summary);
        its configuration is `slam_to_folder`'s `cfg_2d`.
    label: the input's path as summary.yaml records it (default `log`): `omnitof bench` runs on
        a worker's copy of the file and records the path the experiment gave.
    """

    log: Path
    relations: Path | None = None
    max_scans: int | None = None
    skip_bad_lines: bool = False
    scan_delay: str | float | None = None
    calibration: Path | None = None
    height: float | None = None
    band: float | None = None
    map3d: bool = False
    map3d_every: int = 5
    label: str | None = None
    compare_2d: bool = False
    multipath_compensation: str = "auto"
    tof_topics: Any = None
    tof_depth: bool = False
    laser_topics: Any = None
    ignore_odometry: bool = False


@dataclass
class SlamRun:
    """What a run made: the SLAM result, the summary's extra sections (input, relations,
    trajectory error), the files written by name, the relations metric when scored, and the
    scans as the filter saw them (re-timed)."""

    result: Any  # omnitof.slam.SlamResult
    extra: dict[str, Any]
    paths: dict[str, Path]
    relations: Any = None  # omnitof.eval.relations.RelationsResult
    scans: ScanSequence | None = None


# A progress bar factory: (total, description, unit) → a context manager whose value has
# .update(n). The command passes tqdm bars; a bench worker passes none.
BarFactory = Callable[[int, str, str], Any]


@contextmanager
def no_bar(total: int, desc: str, unit: str) -> Iterator[Any]:
    class _Null:
        def update(self, n: int = 1) -> None:
            pass

    yield _Null()


def default_preset(log: str | Path, tof_topics: Any = None) -> str:
    """The preset `omnitof slam` uses when none is given: by the kind of input (a bag with named
    ToF topics is a ToF bag, whatever else it holds)."""
    return DEFAULT_PRESET_TOF if _is_tof_input(Path(log), tof_topics) else DEFAULT_PRESET_LASER


def _is_bag(log: Path) -> bool:
    from omnitof.io.scans import is_bag

    return log.exists() and is_bag(log)


def _is_tof_input(log: Path, tof_topics: Any) -> bool:
    """Whether to read `log` as a ToF bag: one of ToF images only, or any bag whose ToF topics
    are named (a robot's bag may hold a laser's scans beside the camera's images)."""
    from omnitof.io.scans import is_tof_bag

    return is_tof_bag(log) or (tof_topics is not None and _is_bag(log))


def slam_config(
    *,
    preset: str | None = None,
    config: str | Path | None = None,
    settings: Mapping[str, Any] | None = None,
    particles: int | None = None,
    seed: int | None = None,
    threads: int | None = None,
    source: str = "--set",
) -> SlamConfig:
    """The configuration of a run: the defaults, then the preset, then the file, then
    `settings` ({"SECTION.FIELD": value}, `--set`), then particles, seed and threads."""
    from omnitof.slam.config import load_layers, settings_overrides

    overrides = settings_overrides(settings or {}, source)
    named = {k: v for k, v in (("particles", particles), ("seed", seed), ("threads", threads)) if v is not None}
    return load_layers(config, preset=preset, settings=overrides, settings_source=source,
                       options={"filter": named} if named else None)


def slam_to_folder(request: SlamRequest, cfg: SlamConfig, out: str | Path, *, cfg_2d: SlamConfig | None = None,
                   bar: BarFactory = no_bar, echo: Callable[[str], None] = print) -> SlamRun:
    """Run SLAM on `request.log` with `cfg` and write the results folder `out`
    (omnitof.results; summary.yaml is written last). `cfg_2d`: with the 3D filter and
    request.compare_2d, the 2D filter's configuration (default `cfg`). `echo` prints what the
    run decided (the scan delay)."""
    from omnitof.interrupts import pause_point
    from omnitof.results import results_folder

    log = Path(request.log)
    label = request.label if request.label is not None else str(log)
    # --height and --band win over the configuration's scan section, and config.yaml records them.
    slice_given = {k: v for k, v in (("height", request.height), ("band", request.band)) if v is not None}
    if slice_given:
        from omnitof.scan import scan_settings

        cfg = cfg.model_copy(update={"scan": scan_settings(cfg.scan, **slice_given)})
    tof = _is_tof_input(log, request.tof_topics)
    tof_only = [name for name, given in (
        ("--calibration", request.calibration is not None), ("--height", request.height is not None),
        ("--band", request.band is not None), ("--map3d", request.map3d), ("--tof-topics", request.tof_topics is not None),
        ("--tof-distance", request.tof_depth), ("--multipath-compensation", request.multipath_compensation != "auto"),
        ("--compare-2d", request.compare_2d)) if given]  # fmt: skip
    if not tof and tof_only:  # a laser log has no slice, rig or images: the option would be ignored
        raise OmnitofError(f"{log}: {', '.join(tof_only)} need{'s' if len(tof_only) == 1 else ''} a bag of ToF images")
    if request.laser_topics is not None and log.exists() and (tof or not _is_bag(log)):
        raise OmnitofError(f"{log}: --laser-topics needs a bag of LaserScan messages")
    if request.ignore_odometry and cfg.filter3d.enabled:  # its frames are chosen by the odometry while reading
        raise OmnitofError(f"{log}: --ignore-odometry does not work with the 3D filter (--filter 3d)")
    if not tof and cfg.filter3d.enabled:
        raise OmnitofError(f"{log}: the 3D filter (--filter 3d, filter3d.enabled) needs a bag of ToF images")
    relations = None
    if request.relations is not None:
        from omnitof.eval.relations import read_relations

        relations = read_relations(request.relations)
    # Opened before any work, so that an output that cannot be written is found at once; the
    # folder replaces `out` only when everything is written (omnitof.results).
    with results_folder(out) as folder:
        pause_point("start")
        run = _run_into(request, cfg, folder, log, label, tof, relations, bar, echo, cfg_2d)
    # The files now lie in `out`, which the new folder became.
    run.paths = {name: Path(out) / Path(path).relative_to(folder) for name, path in run.paths.items()}
    return run


def _run_into(request: SlamRequest, cfg: SlamConfig, out: Path, log: Path, label: str, tof: bool,
              relations: Any, bar: BarFactory, echo: Callable[[str], None], cfg_2d: SlamConfig | None) -> SlamRun:
    """`slam_to_folder`'s work, writing into the new folder `out`."""
    from omnitof.io.scans import read_scans
    from omnitof.results import write_results
    from omnitof.slam import check_limits, run_slam
    from omnitof.slam.thinning import thin_dense_scans

    three_d = tof and cfg.filter3d.enabled
    if tof:
        import math

        keyframes = (cfg.filter.linear_update, math.radians(cfg.filter.angular_update_deg)) if three_d else None
        tof_data = read_tof_input(log, calibration=request.calibration, settings=cfg.scan,
                                  multipath=request.multipath_compensation,
                                  cloud_every=request.map3d_every if request.map3d else 0,
                                  cloud_pixel_stride=cfg.filter3d.pixel_stride if three_d else 1,
                                  cloud_keyframes=keyframes, max_frames=request.max_scans, bar=bar,
                                  topics=request.tof_topics, depth=request.tof_depth)
        scans = tof_data.scans
        extra: dict[str, Any] = {"input": {"path": label, "kind": "tof-rosbag", "rig": tof_data.rig_source,
                                           "multipath_compensation": tof_data.multipath_rule,
                                           "topics": _topics_record(request.tof_topics),
                                           "distance_images": "depth" if request.tof_depth else "radial distance",
                                           "scan": tof_data.extractor.settings.model_dump()}}
    else:
        data = read_scans(log, skip_bad_lines=request.skip_bad_lines, laser_topics=request.laser_topics)
        scans = data.scans if request.max_scans is None else data.scans.slice(0, request.max_scans)
        extra = {"input": {"path": label, "kind": data.kind, "bad_lines_skipped": data.bad_lines}}
    extra["input"]["max_range"] = {"metres": float(scans.max_range), "rule": scans.max_range_rule or "given"}
    extra["input"]["time_order"] = scans.time_order()
    if scans.odometry_rule:
        extra["input"]["odometry"] = scans.odometry_rule
    if relations is not None:
        from omnitof.eval.relations import check_relations_match

        check_relations_match(relations, scans.timestamps)
    scans, thinned = thin_dense_scans(scans, cfg)
    run_cfg = cfg  # what the filter is given; config.yaml records `cfg`
    if thinned is not None:
        extra["input"]["beams_thinned"] = thinned
        run_cfg = cfg.model_copy(update={"map": cfg.map.model_copy(update={"thin_beams": "off"})})  # done once
    if request.ignore_odometry:  # only its first pose stays: where the estimate starts
        scans = dataclasses.replace(scans, odometry=np.broadcast_to(scans.odometry[:1], scans.odometry.shape),
                                    odometry_known=False, odometry_rule="none: set aside by --ignore-odometry")
    else:
        from omnitof.slam.odometry_faults import repair_odometry

        scans, repair = repair_odometry(scans, label)
        if repair:
            extra["input"]["odometry_repair"] = repair
        if three_d and not scans.odometry_known:
            raise OmnitofError(f"{log}: the odometry never moves, and the 3D filter chooses its frames by it; "
                               "run the 2D filter (without --filter 3d), which estimates the odometry from the scans")
    estimated = not scans.odometry_known
    if estimated and request.scan_delay is not None:
        raise OmnitofError(f"{log}: --scan-delay: the odometry is estimated from the scans at their own stamps "
                           f"({scans.odometry_rule}), so no delay applies to it")
    if estimated:
        from omnitof.slam.scan_odometry import with_scan_odometry

        check_limits(scans, cfg)  # before the estimate's work too: a log with nothing to map says so at once
        with bar(len(scans), "odometry from the scans", "scan") as b:
            scans, found = with_scan_odometry(scans, run_cfg, progress=b.update)
        echo(f"odometry estimated from the scans: {found.matched} matched, {found.unmatched} by the step before")
        if found.unmatched > 0.1 * len(scans):
            echo(f"warning: {found.unmatched} of {len(scans)} scans found too little of the map to be matched; "
                 "the estimated odometry, and the map, may be wrong")
        extra["input"]["odometry"] = scans.odometry_rule
        extra["input"]["scan_odometry"] = found.to_dict()
        if scans.ground_truth is not None:  # the estimate has a frame of its own: the truth is moved into it
            scans = dataclasses.replace(scans, ground_truth=_in_frame_of(scans.ground_truth, scans.odometry[0]))
            extra["input"]["ground_truth_frame"] = ("the estimate's: moved so that its first pose is the estimated "
                                                    "odometry's first (the trajectory errors and ground_truth.tum)")
    check_limits(scans, cfg)
    # Laser logs are stamped when the reading arrives, so their delay is estimated by default;
    # odometry estimated from the scans is at the scans' own stamps.
    given = request.scan_delay is not None
    delay = request.scan_delay if given or tof or estimated else "auto"
    if delay is not None:
        scans, extra["input"]["scan_delay"] = _retimed(scans, delay, given=given, echo=echo)
    elif estimated:
        extra["input"]["scan_delay"] = {"seconds": 0.0, "how": "none: the odometry is the scans' own"}
    voxel_paths: dict[str, Path] = {}
    if three_d:
        result, voxel_paths = _run_3d(request, run_cfg, scans, tof_data, out, extra, bar, cfg_2d or run_cfg)
    else:
        with bar(len(scans), "slam", "scan") as b:
            result = run_slam(scans, run_cfg, progress=_pausing(b.update, "slam", len(scans) // 2))
    rel = None
    if relations is not None:
        from omnitof.eval.relations import evaluate_relations

        rel = evaluate_relations(result.trajectory, relations)
        extra["relations"] = rel.to_dict()
    if scans.ground_truth is not None:
        from omnitof.eval.trajectory import absolute_trajectory_error

        from omnitof.eval.ate import evaluate_ate

        truth = Trajectory(result.trajectory.timestamps, scans.ground_truth)
        try:  # the error after a rigid alignment: the map's shape, not its placement
            rigid = evaluate_ate(result.trajectory, truth, align="rigid")[0]
            shape = {**rigid.error.to_dict(), "rotation_deg": float(np.degrees(rigid.alignment.rotation)),
                     "translation_m": list(rigid.alignment.translation)}
        except InputError:  # a robot that never moved: no alignment to fit
            shape = None
        extra["trajectory_error"] = {
            "slam": absolute_trajectory_error(result.trajectory.poses, scans.ground_truth).to_dict(),
            "slam_rigid": shape,
            "odometry": absolute_trajectory_error(scans.odometry, scans.ground_truth).to_dict(),
        }
    if tof and request.map3d and not three_d:
        from omnitof.map3d import voxel_map_from_clouds
        from omnitof.results import write_voxel_outputs

        # Before write_results, so that summary.yaml stays the folder's last file.
        vmap = voxel_map_from_clouds(result.trajectory.poses[tof_data.cloud_frames], tof_data.clouds)
        voxel_paths = write_voxel_outputs(vmap, out, trajectory=result.trajectory.poses)
    paths = write_results(out, result, cfg, title=log.name, extra=extra, ground_truth=scans.ground_truth)
    return SlamRun(result, extra, {**paths, **voxel_paths}, rel, scans)


def _in_frame_of(truth: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The true poses moved rigidly so that the first is `start`: an odometry estimated from the
    scans starts where it likes, and the truth is compared with it there."""
    from omnitof.geometry import compose, relative

    return compose(np.asarray(start, dtype=np.float64), relative(truth[0], truth))


def _run_3d(request: SlamRequest, cfg: SlamConfig, scans: ScanSequence, tof_data: Any, out: Path,
            extra: dict[str, Any], bar: BarFactory, cfg_2d: SlamConfig) -> tuple[Any, dict[str, Path]]:
    """The 3D filter's run (omnitof.slam.filter3d) on the rays kept while reading: its
    SlamResult (map: the voxel map's projection onto the floor), the voxel map's files
    (map3d.ply, map3d.png) and, with request.compare_2d, the 2D filter's trajectory on the same
    scans with `cfg_2d` (trajectory_2d.tum) and the difference in `extra`."""
    from omnitof.io.tum import write_tum
    from omnitof.map3d import VoxelMap
    from omnitof.results import write_voxel_outputs
    from omnitof.slam import run_slam
    from omnitof.slam.filter3d import run_slam3d, trajectory_difference

    # The frames' clouds were kept in the frames' order; a scan delay does not change which.
    with bar(len(scans), "slam 3d", "scan") as b:
        run3 = run_slam3d(scans, tof_data.cloud_frames, tof_data.clouds, cfg,
                          progress=_pausing(b.update, "slam", len(scans) // 2))
    result = run3.result
    paths = write_voxel_outputs(VoxelMap.of_grid(run3.voxels, offset=run3.offset), out, trajectory=result.trajectory.poses,
                                title="3D filter: occupied voxels of the best particle")
    if request.compare_2d:
        with bar(len(scans), "slam 2d", "scan") as b:
            flat = run_slam(scans, cfg_2d, progress=b.update)
        paths["trajectory_2d"] = out / "trajectory_2d.tum"
        write_tum(paths["trajectory_2d"], flat.trajectory, sort=True)
        extra["filter2d"] = {
            "difference_3d_to_2d": trajectory_difference(result.trajectory.poses, flat.trajectory.poses),
            "seconds": flat.stats["seconds"],
        }
        if scans.ground_truth is not None:
            from omnitof.eval.trajectory import absolute_trajectory_error

            extra["filter2d"]["trajectory_error"] = absolute_trajectory_error(
                flat.trajectory.poses, scans.ground_truth).to_dict()
    return result, paths


def read_tof_input(log: str | Path, *, calibration: str | Path | None = None, settings: ScanSettings | None = None,
                   height: float | None = None, band: float | None = None, multipath: str = "auto",
                   cloud_every: int = 0, cloud_pixel_stride: int = 1,
                   cloud_keyframes: tuple[float, float] | None = None, max_frames: int | None = None,
                   bar: BarFactory = no_bar, topics: Any = None, depth: bool = False):
    """The scans of a ToF bag (omnitof.scan.tof_input.read_tof_scans) with the scan settings
    (default: the defaults; a SLAM configuration's `scan` section), the slice's height and band
    over them where given, and the multipath compensation asked for, for `omnitof slam` and
    `omnitof scans`. `topics` (an `io.rosbag.ToFTopics`) and `depth`: as `read_tof_scans`."""
    from omnitof.scan import scan_settings
    from omnitof.scan.tof_input import frame_count, read_tof_scans

    given = {k: v for k, v in (("height", height), ("band", band)) if v is not None}
    settings = scan_settings(settings, **given)
    total = frame_count(log, topics)
    if max_frames is not None:
        total = min(total, max_frames)
    with bar(total, "scans", "frame") as b:
        return read_tof_scans(log, calibration=calibration, settings=settings, multipath=multipath,
                              cloud_every=cloud_every,
                              cloud_pixel_stride=cloud_pixel_stride, cloud_keyframes=cloud_keyframes,
                              max_frames=max_frames, progress=b.update, topics=topics, depth=depth)


def _topics_record(topics: Any) -> dict[str, str]:
    """The ToF bag's topic names as summary.yaml records them ("found by type" for those left to
    the reader)."""
    import dataclasses

    from omnitof.io.rosbag import ToFTopics

    return {role: "found by type" if name is None else name
            for role, name in dataclasses.asdict(topics or ToFTopics()).items()}


def _retimed(scans: ScanSequence, delay: str | float, *, given: bool,
             echo: Callable[[str], None]) -> tuple[ScanSequence, dict]:
    """The scans with their odometry re-timed by `delay` (seconds, or "auto": estimated), and
    what to record of it. Where the log does not allow an estimate (a clock that steps back, too
    few scans taken while turning), the delay is 0 and the record says why; a delay in seconds
    that cannot be applied is an error."""
    from omnitof.slam.timing import LASER_DELAY, estimate_scan_delay, retime_odometry

    option = "--scan-delay" if given else "default --scan-delay auto"
    if delay == "auto":
        try:
            estimate = estimate_scan_delay(scans)
        except ValueError as err:
            echo(f"scan delay 0 s: not estimated ({err})")
            return scans, {"seconds": 0.0, "how": f"{option}: not estimated, so none applied", "reason": str(err)}
        clocks = ""
        if abs(estimate.delay) > LASER_DELAY:
            clocks = (f" (more than a laser's own {LASER_DELAY:g} s: the laser's and the odometry's clocks "
                      "disagree)")
        echo(f"scan delay estimated from {estimate.pairs} scan pairs: {estimate.delay:.3f} s{clocks}")
        record = {"seconds": estimate.delay, "how": f"{option}: estimated from the log",
                  "estimated_from_pairs": estimate.pairs}
    else:
        span = float(np.ptp(scans.timestamps)) if len(scans) else 0.0
        if span > 0.0 and abs(float(delay)) >= span:
            # Every scan would take the odometry from beyond the log's end (or start), which holds
            # still there: a run of one integrated scan, and no word of why.
            raise OmnitofError(f"--scan-delay {float(delay):g} s is as long as the log itself ({span:.3g} s of "
                               "scans): the delay is in seconds, and a laser's is a fraction of one")
        record = {"seconds": float(delay), "how": "--scan-delay: given"}
    try:
        return retime_odometry(scans, record["seconds"]), record
    except ValueError as err:
        raise OmnitofError(f"--scan-delay: {err}") from None


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
