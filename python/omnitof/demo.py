"""`omnitof demo`: the whole system in one command, on a simulated world.

    1. simulate the world's sequence (robot path, drifting odometry, ground truth);
    2. render the calibration targets and calibrate the rig (intrinsics, mirror planes, masks);
    3. render every frame and extract its 360° scan with the *estimated* calibration, keeping the
       3D rays of every few frames;
    4. run the particle filter (the scan-matching proposal with 200 particles);
    5. build the 3D voxel map along the SLAM trajectory;
    6. evaluate: trajectory error against the truth (SLAM and raw odometry), the paper's Table I
       where the world has its landmarks, the map against the floor plan;
    7. write everything, with figures and a report (report.md), into one folder.

`run_world` does the work and returns the summary; `benchmarks/worlds.py` calls it for every
world, and `simulated_scans` (steps 1–3) makes the ToF worlds of `omnitof bench`. Times and the
peak memory of every stage are in the summary.
"""

from __future__ import annotations

import math
import resource
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import dump_yaml
from omnitof.io.atomic import atomic_write
from omnitof.io.plain import to_plain

DEFAULT_WORLD = "corridor1"
DEFAULT_PRESET = "tof-scanmatch"
DEFAULT_PARTICLES = 200


@dataclass(frozen=True)
class DemoSettings:
    """What the demo runs.

    world: a bundled world name or a world YAML. seed: fixes every random draw (odometry, sensor
    noise, calibration images, filter). preset: the SLAM preset (`tof-scanmatch`: the
    scan-matching proposal with the pose-graph back end; `tof`: the paper's filter). particles:
    overrides the preset's; the demo uses the paper's 200 with the scan-matching proposal (with
    the back end, corridor1 ends within 3.3 cm in seeds 0 and 1 and 13 cm off in seed 2; with 30
    particles within 1.7–5.2 cm; BENCHMARKS.md, issue 13). None keeps the preset's. calibrate: estimate the rig from rendered target images
    (else use the true rig). map3d_every: frames between those fed to the 3D map (0: no 3D map);
    map3d_pixel_stride: every n-th ray of such a frame. max_frames: stop after this many frames
    (a quick look). speed: m/s. refine: refine the estimated calibration jointly (issue 16:
    two-mirror boards, ToF path lengths; `calibration.refine`) after the closed-form chain, as
    the demo does by default; False keeps the closed-form estimate. tof_errors: the camera's
    systematic errors to simulate (`ToFErrors.parse`: "default", all but multipath; "all",
    "none" or a comma list). true_rig_correction: with calibrate False, give the true rig the
    distance correction fitted to walls (`calibration.walls`) as the estimated calibrations get
    it (the true geometry, but the distance error measured; for benchmarks/calibration_maps.py).
    """

    world: str = DEFAULT_WORLD
    seed: int = 0
    preset: str = DEFAULT_PRESET
    particles: int | None = DEFAULT_PARTICLES
    calibrate: bool = True
    map3d_every: int = 10
    map3d_pixel_stride: int = 2
    max_frames: int | None = None
    speed: float = 0.4
    refine: bool = True
    tof_errors: str = "default"
    true_rig_correction: bool = False


class _Stages:
    """Wall time and peak memory after each stage, for the summary and BENCHMARKS.md."""

    def __init__(self, echo: Callable[[str], None]) -> None:
        self.rows: dict[str, dict[str, float]] = {}
        self.echo = echo

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self.echo(f"[{len(self.rows) + 1}] {name} ...")
        start = time.perf_counter()
        yield
        self.rows[name] = {
            "seconds": round(time.perf_counter() - start, 2),
            "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        }


@dataclass
class DemoRun:
    """What `run_world` made: the summary (also in summary.yaml), the world and the scans (for
    re-running SLAM with other settings)."""

    summary: dict[str, Any]
    world: Any
    scans: Any


def slam_config(preset: str, seed: int, particles: int | None = None,
                extra: dict[str, dict[str, Any]] | None = None) -> Any:
    """The SLAM configuration of a preset with the run's seed (and particle count, and other
    fields `extra`, {section: {field: value}})."""
    from omnitof.slam.config import load_config

    overrides: dict[str, Any] = {section: dict(fields) for section, fields in (extra or {}).items()}
    overrides.setdefault("filter", {})["seed"] = int(seed)
    if particles is not None:
        overrides["filter"]["particles"] = int(particles)
    return load_config(preset=preset, overrides=overrides)


def run_world(settings: DemoSettings, out: str | Path, *, progress: bool = True,
              echo: Callable[[str], None] = print) -> DemoRun:
    """Run the pipeline (module docstring) and write its files into the folder `out`
    (`run_demo` gives it a fresh folder that replaces its results folder when complete)."""
    from omnitof.io.terminal import progress_bar
    from omnitof.map3d import voxel_map_from_clouds
    from omnitof.results import write_results, write_voxel_outputs
    from omnitof.slam import run_slam

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = slam_config(settings.preset, settings.seed, settings.particles)  # a bad value stops us before any work
    stages = _Stages(echo)
    summary: dict[str, Any] = {"settings": asdict(settings)}
    started = time.perf_counter()
    sim = simulated_scans(settings, out, stages=stages, progress=progress)
    world, renderer, extractor, sequence, data, scans = (sim.world, sim.renderer, sim.extractor, sim.sequence,
                                                        sim.data, sim.data.scans)
    summary["sequence"] = sim.sequence_summary
    summary["calibration"] = sim.calibration_report
    summary["scans"] = {"frames": len(scans), "bins_with_reading": round(float(np.isfinite(scans.ranges).mean()), 3),
                        "settings": extractor.settings.model_dump()}

    with stages.stage("SLAM"):
        bar = progress_bar(len(scans), enabled=progress, desc="slam", unit="scan")
        with bar:
            result = run_slam(scans, cfg, progress=bar.update)
        summary["slam"] = {"preset": settings.preset, **result.stats}

    voxel_paths: dict[str, Path] = {}
    if settings.map3d_every > 0:
        with stages.stage("3D map"):
            vmap = voxel_map_from_clouds(result.trajectory.poses[data.cloud_frames], data.clouds)
            voxel_paths = write_voxel_outputs(vmap, out, trajectory=result.trajectory.poses,
                                              title=f"{world.name}: occupied voxels (0.1 m)")
            summary["map3d"] = {"frames": len(data.clouds), "rays": int(sum(len(c) for c in data.clouds)),
                                "voxels_observed": vmap.voxel_count(), "voxels_occupied": len(vmap.occupied()),
                                "memory_mib": round(vmap.memory_bytes() / 2**20, 1)}

    with stages.stage("evaluate and write"):
        evaluation = evaluate_run(world, scans, result, out)
        summary["evaluation"] = evaluation
        summary["stages"] = stages.rows
        summary["total_seconds"] = round(time.perf_counter() - started, 1)
        paths = write_results(out, result, cfg, title=f"{world.name} (simulated)", ground_truth=scans.ground_truth,
                              extra={"demo": to_plain(summary)})
        _figures(world, renderer, extractor, sequence, scans, result, out)
        write_report(out / "report.md", summary, voxel_paths)
    summary["stages"] = stages.rows
    summary["total_seconds"] = round(time.perf_counter() - started, 1)
    with atomic_write(paths["summary"]) as f:
        dump_yaml({"run": result.stats, "demo": to_plain(summary)}, f, sort_keys=False)
    return DemoRun(summary, world, scans)


# --- steps ------------------------------------------------------------------------------------


@dataclass
class SimulatedScans:
    """The first three steps of the pipeline: the world, its drive, the renderer, the extractor
    of the (estimated or true) calibration, and the extracted scans with their ground truth and
    3D rays (`data`: omnitof.scan.tof_input.ToFScans)."""

    world: Any
    sequence: Any
    renderer: Any
    extractor: Any
    data: Any
    sequence_summary: dict[str, Any]
    calibration_report: dict[str, Any]


def simulated_scans(settings: DemoSettings, out: str | Path, *, stages: _Stages | None = None,
                    progress: bool = False, world: Any = None) -> SimulatedScans:
    """Simulate the drive, calibrate the rig (calibration.yaml in `out`), render every frame
    and extract its scan: steps 1–3 of the module docstring, for the demo and for the world
    inputs of `omnitof bench`. `world`: the World already loaded (else `settings.world` is)."""
    from omnitof.io.terminal import progress_bar
    from omnitof.scan import ScanExtractor
    from omnitof.scan.multipath import MultipathSettings
    from omnitof.scan.tof_input import tof_scans
    from omnitof.sensor.tof import SensorNoise
    from omnitof.sensor.tof_errors import ToFErrors
    from omnitof.sim.render import Renderer, RenderSettings
    from omnitof.sim.sequence import MotionSettings, make_sequence, render_sequence
    from omnitof.sim.worlds import load_world

    out = Path(out)
    stages = stages if stages is not None else _Stages(lambda _: None)
    with stages.stage("simulate the drive"):
        world = world if world is not None else load_world(settings.world)
        sequence = make_sequence(world, seed=settings.seed, motion=MotionSettings(speed=settings.speed))
        sensor = SensorNoise(errors=ToFErrors.parse(settings.tof_errors))
        renderer = Renderer(world, sensor=sensor, settings=RenderSettings(seed=settings.seed))
        n_frames = len(sequence) if settings.max_frames is None else min(len(sequence), settings.max_frames)
        drift, turn = sequence.odometry_end_error(n_frames)
        summary = {
            "world": world.name, "frames": n_frames, "metres": round(sequence.distance_driven(n_frames), 2),
            "odometry_end_error_m": round(drift, 3), "odometry_end_error_deg": round(math.degrees(turn), 2),
            "tof_errors": list(sensor.errors.switched_on),
        }

    with stages.stage("calibrate the rig"):
        calibration, calib_report = _calibrate(renderer, settings, out)

    with stages.stage("render frames and extract scans"):
        # The multipath compensation is on where the simulated camera has multipath
        # (`--tof-errors all`), with that camera's figures, as `omnitof slam` does on its bags.
        multipath = MultipathSettings.for_camera(sensor.errors, amplitude_at_1m=sensor.amplitude_at_1m,
                                                 f_mod=sensor.f_mod,
                                                 mirror_reflectivity=renderer.settings.mirror_reflectivity)
        summary["multipath_compensation"] = multipath.enabled
        extractor = ScanExtractor.from_calibration(calibration, multipath=multipath.model_dump())
        bar = progress_bar(n_frames, enabled=progress, desc="render+scan", unit="frame")
        with bar:
            data = tof_scans(
                render_sequence(sequence, renderer, stop=n_frames), extractor,
                cloud_every=settings.map3d_every, cloud_pixel_stride=settings.map3d_pixel_stride,
                source=f"{world.name} (simulated)", progress=bar.update,
            )
    return SimulatedScans(world, sequence, renderer, extractor, data, summary, calib_report)


def _calibrate(renderer: Any, settings: DemoSettings, out: Path) -> tuple[Any, dict[str, Any]]:
    """The calibration the scans are extracted with, and how far it is from the truth."""
    from omnitof.calibration import Calibration, save_calibration

    truth = Calibration.from_rig(renderer.rig)
    if not settings.calibrate:
        source = "true rig (no calibration run)"
        if settings.true_rig_correction:
            from omnitof.calibration.walls import fit_from_walls, render_wall_views

            walls = render_wall_views(renderer.camera, renderer.mirrors, settings.seed, sensor=renderer.sensor)
            truth.distance_correction = fit_from_walls(truth, walls)
            source += f", distance correction from {len(walls)} wall views"
        save_calibration(truth, out / "calibration.yaml")
        return truth, {"source": source}
    from omnitof.calibration.simulated import calibrate_from_simulation

    cal, report = calibrate_from_simulation(renderer, seed=settings.seed, truth=truth, refine=settings.refine)
    save_calibration(cal, out / "calibration.yaml")
    return cal, report


def evaluate_run(world: Any, scans: Any, result: Any, out: Path | None) -> dict[str, Any]:
    """Trajectory errors, Table I (if the world has landmarks) and floor-plan numbers; with
    `out`, writes overlay.png and table1.txt there. The map frame is the world frame (the
    odometry starts at the true start pose)."""
    from omnitof.eval.floorplan import wall_agreement, wall_coverage
    from omnitof.eval.table1 import format_table1, table1
    from omnitof.eval.trajectory import absolute_trajectory_error
    from omnitof.viz.scans import plot_floorplan_overlay

    gt = scans.ground_truth
    slam = absolute_trajectory_error(result.trajectory.poses, gt)
    odom = absolute_trajectory_error(scans.odometry, gt)
    walls = world.segments_at(0.6)
    from omnitof.sim.laser2d import World2D

    plan = World2D(walls)
    agreement = wall_agreement(result.map, plan.distance_to_walls, tolerance=0.05)
    coverage = wall_coverage(result.map, walls, gt[:: 10], scans.max_range, tolerance=0.05)
    if out is not None:
        plot_floorplan_overlay(out / "overlay.png", result.map, walls, trajectory=result.trajectory.poses,
                               title=f"{world.name}: map (grey) and floor plan at 0.6 m (red)")
    evaluation: dict[str, Any] = {
        "trajectory": {"slam": slam.to_dict(), "odometry": odom.to_dict()},
        "floorplan": {
            "occupied_within_5cm": agreement.near_fraction,
            "mean_distance_m": agreement.mean_distance,
            "seen_wall_mapped": coverage.fraction,
            "seen_wall_m": coverage.seen_length,
        },
    }
    if world.landmarks:
        rows = table1(result.map, world.landmarks)
        text = format_table1({world.name: rows})
        if out is not None:
            with atomic_write(out / "table1.txt") as f:
                f.write(text + "\n")
        evaluation["table1"] = {
            r.name: {"true_m": r.true_distance, "measured_m": r.measured, "offset_cm": 100.0 * r.offset,
                     "reason": r.reason}
            for r in rows
        }
        evaluation["table1_text"] = text
    return evaluation


def _figures(world: Any, renderer: Any, extractor: Any, sequence: Any, scans: Any, result: Any, out: Path) -> None:
    """fig3_amplitude.png / fig3_depth.png (the paper's Fig. 3), scan.png (Fig. 5(b)) and
    slice.png (the pixels that fed the slice) of a frame a quarter into the drive."""
    from omnitof.viz.sensor import plot_mirror_regions
    from omnitof.viz.scans import plot_scan, plot_slice_overlay

    i = len(scans) // 4
    frame = renderer.render_many(sequence.ground_truth[i:i + 1], seed=sequence.seed + 1, first_index=i)[0]
    plot_mirror_regions(out / "fig3_amplitude.png", renderer.camera, renderer.mirrors,
                        np.log10(np.maximum(frame.amplitude, 1.0)), title="amplitude (log) and mirror regions")
    plot_mirror_regions(out / "fig3_depth.png", renderer.camera, renderer.mirrors, frame.distance,
                        title="distance and mirror regions")
    truth = world.horizontal_distance(sequence.ground_truth[i, :2], sequence.ground_truth[i, 2] + scans.scan_angles(i),
                                      extractor.settings.height)
    plot_scan(out / "scan.png", scans.scan_ranges(i), scans.scan_angles(i), truth=truth, max_range=scans.max_range,
              title=f"frame {i}: 360° range reading (truth grey)")
    plot_slice_overlay(out / "slice.png", extractor, frame.distance, frame.amplitude,
                       title=f"frame {i}: pixels that fed the slice")


# --- report ------------------------------------------------------------------------------------


def write_report(path: Path, summary: dict[str, Any], voxel_paths: dict[str, Path]) -> None:
    """report.md: the run's numbers and figures, with Table I beside the paper's."""
    seq, ev = summary["sequence"], summary["evaluation"]
    t, fp = ev["trajectory"], ev["floorplan"]
    lines = [
        f"# omnitof demo: {seq['world']}",
        "",
        f"{seq['frames']} frames over {seq['metres']} m; raw odometry ends {seq['odometry_end_error_m']} m and "
        f"{seq['odometry_end_error_deg']}° off the truth. SLAM preset `{summary['slam']['preset']}` with "
        f"{summary['slam']['particles']} particles, seed {summary['settings']['seed']}.",
        "",
        "## Trajectory error against the ground truth",
        "",
        "| | mean (m) | RMSE (m) | max (m) | final (m) | mean heading (°) |",
        "|---|---|---|---|---|---|",
    ]
    for name in ("slam", "odometry"):
        e = t[name]
        lines.append(f"| {name} | {e['mean']:.3f} | {e['rmse']:.3f} | {e['max']:.3f} | {e['final']:.3f} | "
                     f"{e['heading_mean_deg']:.2f} |")
    lines += [
        "",
        "![map](map.png)",
        "",
        "## The map against the floor plan",
        "",
        f"- occupied cells within 5 cm of a true wall: {100 * fp['occupied_within_5cm']:.1f} %",
        f"- mean distance of occupied cells to the nearest wall: {100 * fp['mean_distance_m']:.1f} cm",
        f"- wall the robot could see (within 7 m, line of sight) that the map holds: "
        f"{100 * fp['seen_wall_mapped']:.1f} % of {fp['seen_wall_m']:.0f} m",
        "",
        "![overlay](overlay.png)",
        "",
    ]
    if "table1_text" in ev:
        lines += ["## Table I: distances between opposite walls (cm)", "", "```", ev["table1_text"], "```", ""]
    cal = summary["calibration"]
    lines += ["## Calibration", "", "```", dump_yaml(to_plain(cal), sort_keys=False).rstrip(), "```", ""]
    lines += ["## The sensor", "", "![amplitude](fig3_amplitude.png) ![depth](fig3_depth.png)", "",
              "![scan](scan.png) ![slice](slice.png)", ""]
    if voxel_paths:
        m = summary["map3d"]
        lines += ["## 3D occupancy map", "",
                  f"{m['rays']} rays of {m['frames']} frames; {m['voxels_occupied']} occupied of "
                  f"{m['voxels_observed']} observed voxels; {m['memory_mib']} MiB. Occupied voxels: `map3d.ply`.",
                  "", "![voxels](map3d.png)", ""]
    lines += ["## Time and memory", "", "| stage | seconds | peak RSS (MiB) |", "|---|---|---|"]
    for name, row in summary["stages"].items():
        lines.append(f"| {name} | {row['seconds']} | {row['peak_rss_mib']} |")
    lines.append("")
    with atomic_write(path) as f:
        f.write("\n".join(lines))


def _print_summary(summary: dict[str, Any], out: Path, echo: Callable[[str], None]) -> None:
    ev = summary["evaluation"]
    s, o = ev["trajectory"]["slam"], ev["trajectory"]["odometry"]
    echo(f"trajectory error (mean / final): SLAM {s['mean']:.3f} / {s['final']:.3f} m, "
         f"odometry {o['mean']:.3f} / {o['final']:.3f} m")
    fp = ev["floorplan"]
    echo(f"map: {100 * fp['occupied_within_5cm']:.1f} % of occupied cells within 5 cm of a wall; "
         f"{100 * fp['seen_wall_mapped']:.1f} % of the seen walls mapped")
    if "table1" in ev:
        offsets = [abs(r["offset_cm"]) for r in ev["table1"].values() if math.isfinite(r["offset_cm"])]
        if offsets:
            echo(f"Table I: {len(offsets)} of {len(ev['table1'])} places measured, offsets "
                 f"{min(offsets):.1f}–{max(offsets):.1f} cm")
    echo(f"total {summary['total_seconds']:.0f} s; report in {out / 'report.md'}")


def run_demo(out: str | Path, *, world: str = DEFAULT_WORLD, seed: int = 0, preset: str = DEFAULT_PRESET,
             particles: int | None = DEFAULT_PARTICLES, calibrate: bool = True, max_frames: int | None = None,
             progress: bool = True, refine: bool = True, tof_errors: str = "default") -> dict[str, Any]:
    """`omnitof demo`: run_world with the command's options, into the results folder `out` as
    one unit (omnitof.results.results_folder: `out` is replaced only when the run is complete)."""
    from omnitof.results import results_folder

    settings = DemoSettings(world=world, seed=seed, preset=preset, particles=particles, calibrate=calibrate,
                            max_frames=max_frames, refine=refine, tof_errors=tof_errors)
    cfg = slam_config(preset, seed, particles)  # a bad value is refused before the folder is opened
    if cfg.filter3d.enabled:
        # The demo runs the 2D filter; with tof3d it ran that with the 3D preset's settings.
        from omnitof.errors import OmnitofError

        raise OmnitofError(f"--preset {preset}: the demo runs the 2D filter (tof-scanmatch, tof); the 3D filter runs "
                           "on a ToF bag: `omnitof simulate --out BAG`, then `omnitof slam BAG --preset tof3d`")
    with results_folder(out) as folder:
        summary = run_world(settings, folder, progress=progress).summary
    _print_summary(summary, Path(out), print)
    return summary
