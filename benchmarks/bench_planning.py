"""How long `omnitof bench` takes to plan an experiment before any run starts (issue 18).

    python benchmarks/bench_planning.py [--runs-per-seed 1000] [--seeds 2] [--repeats 3]

Writes an experiment of one input (an empty log file: planning checks that it exists, it
does not read it), the `laser180-scanmatch` preset, a grid of `--runs-per-seed` points
(filter.particles × map.resolution × motion.alpha1) and `--seeds` seeds into a temporary
folder, and times `plan_runs` (every run's configuration built, validated and digested) and
`load_experiment`, `--repeats` times each. Prints Markdown: the median and each repeat.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

from omnitof.bench import load_experiment
from omnitof.bench.experiment import plan_runs


def _grid(points: int) -> dict[str, list[float]]:
    """Three grid fields of about points^(1/3) values each, `points` points in all."""
    side = round(points ** (1 / 3))
    if side**3 != points:
        raise SystemExit(f"--runs-per-seed must be a cube (1000, 8000, ...), got {points}")
    return {"filter.particles": list(range(1, side + 1)),
            "map.resolution": [round(0.01 * (k + 1), 4) for k in range(side)],
            "motion.alpha1": [round(0.01 * (k + 1), 4) for k in range(side)]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs-per-seed", type=int, default=1000)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "empty.clf").write_text("")
        grid = "\n".join(f"  {k}: {v}" for k, v in _grid(args.runs_per_seed).items())
        (folder / "plan.yaml").write_text(
            f"inputs:\n  - {{name: a, log: empty.clf}}\npresets: [laser180-scanmatch]\n"
            f"grid:\n{grid}\nseeds: {list(range(args.seeds))}\n")
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            runs = plan_runs(load_experiment(folder / "plan.yaml"))
            times.append(time.perf_counter() - start)
    shown = " / ".join(f"{t:.2f}" for t in times)
    print(f"{platform.node()}: {len(runs)} runs planned in a median {statistics.median(times):.2f} s "
          f"(repeats {shown}); {1000 * statistics.median(times) / len(runs):.2f} ms per run")


if __name__ == "__main__":
    main()
