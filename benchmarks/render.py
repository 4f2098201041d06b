"""Render speed of the ToF simulator: frames per second for the four bundled worlds.

Each world is rendered with the default rig (SR4000 wide lens, four mirrors at 56°) from poses
spread evenly along its robot loop, heading along the loop, at 4 sub-rays per pixel, in one batch
per run. Printed per world: the median and spread over several runs of

- core: noise-free phasor images (`Renderer.phasors`, the Rust tracer and the conversion);
- frames: full frames (`Renderer.render_many`: phasors, then A0..A3 with noise and their
  decoding, which run in numpy on one core).

Timings are wall-clock, the tracer on all cores unless --threads is given.

Usage:
    python benchmarks/render.py [--runs 7] [--frames 60] [--sub-rays 4] [--threads N]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time


from omnitof.sim.render import Renderer, RenderSettings
from omnitof.sim.worlds import load_world, world_names
from omnitof.sim.sequence import poses_along_loop


def time_runs(fn, runs: int) -> list[float]:
    fn()  # warm up (page faults, thread pool start)
    out = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        out.append(time.perf_counter() - start)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--sub-rays", type=int, default=4)
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"{args.sub_rays} sub-rays per pixel, {args.frames} poses per run, {args.runs} runs, "
          f"threads: {args.threads or 'all'}")
    print(f"{'world':<10} {'core fps (median, min-max)':>30} {'frames fps (median, min-max)':>32}")
    settings = RenderSettings(sub_rays=args.sub_rays, threads=args.threads)
    for name in world_names():
        world = load_world(name)
        renderer = Renderer(world, settings=settings)
        poses = poses_along_loop(world, args.frames)
        core = [args.frames / t for t in time_runs(lambda: renderer.phasors(poses), args.runs)]
        full = [
            args.frames / t
            for t in time_runs(lambda: renderer.render_many(poses, seed=0), max(3, args.runs // 2))
        ]
        print(f"{name:<10} {statistics.median(core):>12.1f} ({min(core):6.1f}-{max(core):6.1f})"
              f"       {statistics.median(full):>12.1f} ({min(full):6.1f}-{max(full):6.1f})")


if __name__ == "__main__":
    main()
