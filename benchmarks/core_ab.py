"""Two builds of the Rust core's renderer, measured alternately in one process: the speed of a
change to the tracer without the machine's drift in between (on the shared 2-core machine its
speed moves by ±10 % from minute to minute, more than most changes gain).

The other build is loaded from its shared library (e.g. a copy of
python/omnitof/_core*.so built from main before the change) next to the installed one; both
trace the same frames, which are checked equal first (a change meant to keep the output bit for
bit; --allow-different skips the check). Then each renders the world's frames in turn, --runs
times; reported per setting of the camera's errors: the median ms per frame of each and the
median of the per-run ratios old/new (above 1: the installed build is faster).

Usage:
    python benchmarks/core_ab.py OLD_CORE.so [--runs 15] [--world corridor1] [--frames 60]
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import time

import numpy as np

import omnitof.sim.render as render_module
from omnitof.sensor.tof import SensorNoise
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.sequence import make_sequence
from omnitof.sim.worlds import load_world


def load_core(path: str):
    """The core module of another build. Its name ends in `_core`, so that Python finds the
    library's `PyInit__core`; a distinct package name keeps it apart from the installed one."""
    spec = importlib.util.spec_from_file_location("other_build._core", path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"{path}: not a loadable extension module")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def core_renderer(module, world, errors: ToFErrors):
    """The `_core._Renderer` that `Renderer` builds, from the given core module."""
    installed = render_module._core
    render_module._core = module
    try:
        return render_module.Renderer(world, sensor=SensorNoise(errors=errors))._core
    finally:
        render_module._core = installed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", help="the other build's shared library (_core*.so)")
    parser.add_argument("--runs", type=int, default=15)
    parser.add_argument("--world", default="corridor1")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--allow-different", action="store_true", help="skip the check that both trace the same")
    args = parser.parse_args()
    old = load_core(args.old)
    world = load_world(args.world)
    seq = make_sequence(world, seed=0)
    idx = np.linspace(0, len(seq) - 1, args.frames).round().astype(int)
    poses = np.ascontiguousarray(seq.ground_truth[idx])
    print(f"# {args.world}, {args.frames} frames, {args.runs} alternations; old: {args.old}")
    print("| effects | old ms / frame | new ms / frame | old / new, median (min–max) |")
    print("|---|---|---|---|")
    for label, errors in (("off", ToFErrors()), ("default (all but multipath)", ToFErrors.simulation_default()),
                          ("all on", ToFErrors.realistic())):
        cores = {"old": core_renderer(old, world, errors), "new": core_renderer(render_module._core, world, errors)}
        if not args.allow_different and not np.array_equal(cores["old"].render(poses[:3]), cores["new"].render(poses[:3])):
            raise SystemExit(f"{label}: the two builds trace different phasors (--allow-different to time them anyway)")
        times: dict[str, list[float]] = {"old": [], "new": []}
        for _ in range(args.runs):
            for name, core in cores.items():
                start = time.perf_counter()
                core.render(poses)
                times[name].append((time.perf_counter() - start) / len(poses) * 1e3)
        ratios = [o / n for o, n in zip(times["old"], times["new"])]
        print(f"| {label} | {statistics.median(times['old']):.2f} | {statistics.median(times['new']):.2f} | "
              f"{statistics.median(ratios):.3f} ({min(ratios):.3f}–{max(ratios):.3f}) |", flush=True)


if __name__ == "__main__":
    main()
