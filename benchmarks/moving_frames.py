"""The scan error of frames taken while the robot turns (motion during a frame), with every
camera error on and with one of them off.

Per world, 24 of the drive's frames (seed 0) that the renderer draws once per sample (their four
sample poses move a point within the unambiguous range by more than
`RenderSettings.motion_tolerance`), spread evenly over those frames; default rig, 4 sub-rays,
noise on. Scans from the true rig's extractor, no distance correction, pixel filter off and on;
every 1° bin whose nearest surface at the slice height is matte compared with the exact
horizontal distance (as benchmarks/tof_errors.py does for frames spread over the whole drive).

    python benchmarks/moving_frames.py [--worlds corridor1 office room]
"""

from __future__ import annotations

import argparse

import numpy as np

from tof_errors import stats, true_rig_errors

from omnitof.sensor.tof import SensorNoise
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.render import Renderer
from omnitof.sim.sequence import make_sequence, sample_poses
from omnitof.sim.worlds import load_world

SETTINGS = (
    ("all", ToFErrors.realistic()),
    ("all but multipath", ToFErrors.realistic(multipath=False)),
    ("all but motion", ToFErrors.realistic(motion=False)),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["corridor1", "office", "room"])
    parser.add_argument("--frames", type=int, default=24)
    args = parser.parse_args()
    print("| world | effects | frames that turn | bins, pixel filter off | median / p90 |error| (cm) / within 5 cm "
          "| bins, filter on | the same |")
    print("|---|---|---|---|---|---|---|")
    for name in args.worlds:
        world = load_world(name)
        seq = make_sequence(world, seed=0)
        for label, errors in SETTINGS:
            renderer = Renderer(world, sensor=SensorNoise(errors=errors))
            timing = sample_poses(seq, np.arange(len(seq)), errors.integration_time)
            # The same frames in every row: those that turn with motion on.
            moving = np.flatnonzero(renderer._apparent_motion(timing) > renderer.settings.motion_tolerance)
            pick = moving[np.linspace(0, len(moving) - 1, args.frames).round().astype(int)]
            poses = seq.ground_truth[pick]
            frames = renderer.render_many(poses, seed=1, sample_poses=timing[pick])
            cells = [f"{len(e)} | {stats(e)}" for e in true_rig_errors(world, renderer, poses, frames)]
            print(f"| {name} | {label} | {len(moving)} of {len(seq)} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
