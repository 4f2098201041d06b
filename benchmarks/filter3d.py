"""The paper's 3D filter (sec. V, Fig. 11(b)) against the 2D one on simulated worlds: trajectories,
error to the truth, map quality, time per integrated frame and peak memory.

For each world and drive seed: the drive is rendered (sub_rays 1) and, with --calibration
estimated (the default), the rig is calibrated from rendered targets of the same seed
(`calibration.simulated.calibrate_from_simulation`, as the demo does); the 2D scans and the rays
of the frames to integrate (every `filter3d.pixel_stride`-th mirror pixel) are extracted once.
Then, per run (PROPOSAL:PARTICLES), both filters run on the same data, the 3D one with preset
tof3d and the 2D one with --preset-2d (tof-scanmatch; tables before 2026-12-06 gave it tof3d's 2D
sections), without the pose-graph back end unless told:

- trajectory error (mean, final) to the truth of each, and the mean/max distance between them
  (with --backend-2d the 2D filter runs with the pose-graph back end, as tof-scanmatch ships;
  with --backend-3d the 3D filter, as tof3d ships);
- map quality: 3D, the share of occupied voxel centres within 0.1 m of a true surface
  (`map3d.surface_distance`); 2D, the share of occupied cells within 0.1 m of a wall at the
  slice height (`eval.floorplan.wall_agreement`);
- time: the 3D filter's median seconds per integrated frame, and the 2D filter's (seconds /
  integrated scans) measured in the same process as the baseline;
- memory: the process's peak RSS during the 3D run above its RSS before it (Linux: VmHWM, reset
  through /proc/self/clear_refs), and the distinct voxel blocks' bytes at the end.

Usage:
    python benchmarks/filter3d.py [--world office] [--seeds 0 1 2] [--runs scanmatch:30 odometry:30]
        [--calibration estimated|true] [--max-frames N] [--preset-2d tof-scanmatch] [--backend-2d] [--backend-3d]

Worlds: a bundled one by name, or `atrium` (benchmarks/atrium.yaml: a 26 m × 22 m hall, every
wall beyond 7 m of the path at slice height, galleries from 1.0 m to 2.2 m high around it).
Prints a Markdown table for BENCHMARKS.md ("The 3D filter").
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np
import yaml

from omnitof.eval.floorplan import wall_agreement
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.map3d import surface_distance
from omnitof.scan.extract import ScanExtractor
from omnitof.scan.tof_input import tof_scans
from omnitof.sim.render import Renderer, RenderSettings
from omnitof.sim.sequence import make_sequence, render_sequence
from omnitof.sim.worlds import load_world, parse_world
from omnitof.slam import run_slam
from omnitof.slam.config import load_config
from omnitof.slam.filter3d import run_slam3d, trajectory_difference

HERE = Path(__file__).resolve().parent


def world_by_name(name: str):
    if name == "atrium":
        return parse_world(yaml.safe_load((HERE / "atrium.yaml").read_text()), HERE / "atrium.yaml")
    return load_world(name)


def status_kib(field: str) -> int:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


def reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
            f.write("5")
        return True
    except OSError:
        return False


def segment_distance(segments: np.ndarray):
    """Distance function (K, 2) -> (K,) to the nearest of segments (S, 2, 2)."""
    a, b = segments[:, 0], segments[:, 1]
    ab = b - a

    def dist(p: np.ndarray) -> np.ndarray:
        out = np.full(len(p), np.inf)
        for k in range(0, len(p), 4096):  # chunks keep the (K, S) arrays small
            q = p[k:k + 4096, None, :]
            t = np.clip(np.sum((q - a) * ab, axis=2) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0.0, 1.0)
            out[k:k + 4096] = np.min(np.linalg.norm(q - (a + t[..., None] * ab), axis=2), axis=1)
        return out

    return dist


def prepare(world_name: str, seed: int, calibration: str, cfg, max_frames: int | None):
    world = world_by_name(world_name)
    seq = make_sequence(world, seed=seed)
    renderer = Renderer(world, settings=RenderSettings(seed=seed, sub_rays=1))
    cal_report = None
    if calibration == "estimated":
        from omnitof.calibration.simulated import calibrate_from_simulation

        cal, cal_report = calibrate_from_simulation(renderer, seed=seed)
        extractor = ScanExtractor.from_calibration(cal)
    else:
        extractor = ScanExtractor.from_rig(renderer.rig)
    keyframes = (cfg.filter.linear_update, math.radians(cfg.filter.angular_update_deg))
    data = tof_scans(render_sequence(seq, renderer, stop=max_frames), extractor, cloud_keyframes=keyframes,
                     cloud_pixel_stride=cfg.filter3d.pixel_stride)
    return world, data, cal_report


def one_run(world, data, cfg, cfg2, backend_2d: bool = False, backend_3d: bool = False) -> dict:
    """Both filters on `data`: the 3D one with `cfg`, the 2D one with `cfg2`."""
    scans = data.scans
    truth = scans.ground_truth
    cfg2 = cfg2.model_copy(deep=True)
    cfg2.backend.enabled = backend_2d
    cfg = cfg.model_copy(deep=True)
    cfg.backend.enabled = backend_3d
    t0 = time.perf_counter()
    flat = run_slam(scans, cfg2)
    seconds_2d = time.perf_counter() - t0
    rss_before = status_kib("VmRSS")
    have_peak = reset_peak()
    run3 = run_slam3d(scans, data.cloud_frames, data.clouds, cfg)
    peak = status_kib("VmHWM") if have_peak else float("nan")
    res3 = run3.result
    occupied = run3.voxels.occupied(0.0)
    near3 = float(np.mean(surface_distance(occupied, world) <= 0.1)) if len(occupied) else float("nan")
    height = data.extractor.settings.height
    walls2d = wall_agreement(flat.map, segment_distance(world.segments_at(height)), tolerance=0.1)
    return {
        "err2_mean": absolute_trajectory_error(flat.trajectory.poses, truth).mean,
        "err2_final": absolute_trajectory_error(flat.trajectory.poses, truth).final,
        "err3_mean": absolute_trajectory_error(res3.trajectory.poses, truth).mean,
        "err3_final": absolute_trajectory_error(res3.trajectory.poses, truth).final,
        "odo_mean": absolute_trajectory_error(scans.odometry, truth).mean,
        "diff": trajectory_difference(res3.trajectory.poses, flat.trajectory.poses),
        "s_frame_3d": res3.stats["seconds_per_integrated_frame"]["median"],
        "s_frame_2d": seconds_2d / max(1, flat.stats["integrated"]),
        "peak_mib": peak / 1024.0,
        "peak_above_mib": (peak - rss_before) / 1024.0,
        "voxel_mib": res3.stats["voxel_bytes"] / 2**20,
        "blocks": (res3.stats["voxel_blocks_distinct"], res3.stats["voxel_blocks_referenced"]),
        "near3": near3,
        "near2": walls2d.near_fraction,
        "integrated": res3.stats["integrated"],
        "rays": res3.stats["rays_per_frame"],
        "fallbacks": res3.stats["scanmatch_fallbacks"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--runs", nargs="+", default=["scanmatch:30", "odometry:30"],
                        help="PROPOSAL:PARTICLES, each run on every seed")
    parser.add_argument("--calibration", choices=("estimated", "true"), default="estimated")
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    parser.add_argument("--backend-2d", action="store_true",
                        help="the 2D filter with the pose-graph back end (tof-scanmatch as shipped)")
    parser.add_argument("--preset-2d", default="tof-scanmatch",
                        help="the 2D filter's preset (the run's proposal, particles, seed and threads, and --set, "
                        "over it); tables before 2026-12-06 ran it with tof3d's")
    parser.add_argument("--backend-3d", action="store_true",
                        help="the 3D filter with the pose-graph back end (tof3d as shipped since 2026-12-06)")
    args = parser.parse_args(argv)
    from omnitof.slam.config import parse_setting, settings_overrides

    overrides = settings_overrides(dict(parse_setting(s) for s in args.set))
    print(f"# {date.today()} · {platform.processor() or platform.machine()} · {os.cpu_count()} cores · "
          f"load {os.getloadavg()[0]:.1f} at start")
    print(f"# command: python benchmarks/filter3d.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print("\n| world | seed | proposal | particles | frames (integrated) | rays/frame | odometry err | 2D err (final) "
          "| 3D err (final) | 3D−2D mean (max) | near 2D / 3D | s/frame 3D (2D) | peak MiB (above) | blocks MiB | load |")
    print("|---" * 15 + "|")
    for seed in args.seeds:
        base = load_config(preset="tof3d", overrides=overrides)
        world, data, cal = prepare(args.world, seed, args.calibration, base, args.max_frames)
        if cal is not None:
            worst = max(m["normal_error_deg"] for m in cal["mirrors"].values())
            print(f"<!-- seed {seed}: estimated calibration, worst mirror normal {worst:.2f} deg -->")
        for spec in args.runs:
            proposal, particles = spec.split(":")
            cfg = base.model_copy(deep=True)
            cfg.filter.proposal = proposal
            cfg.filter.particles = int(particles)
            cfg.filter.seed = seed
            cfg.filter.threads = args.threads
            cfg2 = load_config(preset=args.preset_2d, overrides=overrides)
            cfg2.filter.proposal, cfg2.filter.particles = proposal, int(particles)
            cfg2.filter.seed, cfg2.filter.threads = seed, args.threads
            r = one_run(world, data, cfg, cfg2, args.backend_2d, args.backend_3d)
            d = r["diff"]
            print(f"| {args.world} | {seed} | {proposal} | {particles} | {len(data.scans)} ({r['integrated']}) "
                  f"| {r['rays']:.0f} | {r['odo_mean']:.3f} | {r['err2_mean']:.3f} ({r['err2_final']:.3f}) "
                  f"| {r['err3_mean']:.3f} ({r['err3_final']:.3f}) | {d['mean']:.3f} ({d['max']:.3f}) "
                  f"| {r['near2']:.2f} / {r['near3']:.2f} | {r['s_frame_3d']:.3f} ({r['s_frame_2d']:.3f}) "
                  f"| {r['peak_mib']:.0f} ({r['peak_above_mib']:.0f}) | {r['voxel_mib']:.0f} | {os.getloadavg()[0]:.1f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
