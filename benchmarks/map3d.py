"""3D voxel map speed and size: frames of a simulated world integrated into a 0.1 m voxel grid.

Frames of the world (default corridor1) are rendered with the default rig from poses spread
evenly along its robot loop, heading along the loop; the weakest tenth of each frame's mirror
pixels is dropped (amplitude), every --stride-th remaining pixel kept, and the rest back-projected
(`map3d.backproject_frame`) to rays in the robot frame. Rendering and back-projection happen once,
before timing. Each run then integrates all frames at their true poses into a fresh VoxelMap
(`integrate_frame`: the world transform, the Rust traversal and the log-odds update). Printed:
the median (and min–max) over the runs of rays/s and frames/s, the map's observed and occupied
voxel counts, the grid's own heap bytes (`VoxelMap.memory_bytes`), how much the resident set
grew over the timed runs, the process's peak RSS (`resource.getrusage`, which includes the
rendered frames and the renderer), and how far the
occupied voxel centres lie from the world's true surfaces (`map3d.surface_distance`).

Usage:
    python benchmarks/map3d.py [--world corridor1] [--frames 120] [--stride 1] [--runs 5]
        [--threads N] [--png map.png] [--ply map.ply]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import time

import numpy as np

from omnitof.sensor import mirrors as mirror_module
from omnitof.sensor.design import default_rig
from omnitof.map3d import (
    VoxelMap,
    backproject_frame,
    surface_distance,
)
from omnitof.io.ply import write_ply
from omnitof.viz.map3d import height_colors, plot_voxels
from omnitof.sim.render import Renderer
from omnitof.sim.worlds import load_world
from omnitof.sim.sequence import poses_along_loop


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def rss_bytes() -> int:
    """The process's resident set size now (Linux /proc; 0 elsewhere)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="corridor1")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--stride", type=int, default=1, help="keep every k-th valid pixel")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--png", default=None, help="draw the map of the last run here")
    parser.add_argument("--ply", default=None, help="write the last run's occupied voxels here")
    args = parser.parse_args()

    world = load_world(args.world)
    rig = default_rig()
    camera, mirrors = rig.camera, rig.mirrors
    mount = mirror_module.camera_mount()
    labels = mirror_module.masks(camera, mirrors)
    renderer = Renderer(world, camera, mirrors, robot_T_camera=mount)
    poses = poses_along_loop(world, args.frames)
    frames = []
    for k, pose in enumerate(poses):
        frame = renderer.render(pose, seed=k)
        valid = frame.amplitude > np.percentile(frame.amplitude[labels >= 0], 10)
        origins, points = backproject_frame(
            frame.distance, camera, mirrors, labels, mount, valid=valid
        )
        frames.append((origins[:: args.stride], points[:: args.stride]))
    rays = sum(len(o) for o, _ in frames)

    seconds = []
    vm = VoxelMap(args.resolution)
    rss_before = rss_bytes()
    for _ in range(args.runs):
        del vm  # one map alive at a time
        vm = VoxelMap(args.resolution, threads=args.threads)
        start = time.perf_counter()
        for pose, (origins, points) in zip(poses, frames):
            vm.integrate_frame(pose, origins, points)
        seconds.append(time.perf_counter() - start)
    rss_after = rss_bytes()
    occupied = vm.occupied()
    accuracy = []
    for threshold in (0.0, 1.0):
        d = surface_distance(vm.occupied(threshold), world)
        accuracy.append(
            f"log-odds > {threshold:g}: {len(d):,} voxels, median {np.median(d):.3f} m, "
            f"{np.mean(d < 0.1):.1%} within 0.10 m, {np.mean(d < 0.15):.1%} within 0.15 m"
        )
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB

    med = statistics.median(seconds)
    print(f"machine: {cpu_model()}, {os.cpu_count()} cores; threads: {args.threads or 'all'}")
    print(f"world {args.world}: {args.frames} frames along its loop, pixel stride {args.stride}, "
          f"{rays} rays ({rays / args.frames:.0f} per frame), resolution {args.resolution} m, "
          f"{args.runs} runs")
    print(f"integrate: {med:.3f} s (min {min(seconds):.3f}, max {max(seconds):.3f})")
    print(f"rays/s:    {rays / med:,.0f} "
          f"(min-max {rays / max(seconds):,.0f}-{rays / min(seconds):,.0f})")
    print(f"frames/s:  {args.frames / med:.1f} (min-max {args.frames / max(seconds):.1f}-"
          f"{args.frames / min(seconds):.1f})")
    print(f"voxels:    {vm.voxel_count():,} observed, {len(occupied):,} occupied")
    print(f"memory:    {vm.memory_bytes() / 2**20:.1f} MiB grid (VoxelMap.memory_bytes), "
          f"RSS +{(rss_after - rss_before) / 2**20:.1f} MiB over the runs, "
          f"peak RSS {peak_rss / 2**20:.0f} MiB (whole process, with the rendered frames)")
    print("accuracy:  occupied voxel centres to the nearest true surface")
    for line in accuracy:
        print(f"           {line}")
    if args.png:
        plot_voxels(args.png, occupied, resolution=args.resolution, trajectory=poses,
                    z_limits=(0.15, world.ceiling_height - 0.15),
                    title=f"{args.world}: {len(occupied)} occupied voxels of {args.resolution:g} m "
                          "(floor and ceiling layers not drawn)")
    if args.ply:
        write_ply(args.ply, occupied, height_colors(occupied))


if __name__ == "__main__":
    main()
