"""How an experiment's inputs reach the workers, and the simulated ones are made.

A recording up to `SHIP_LIMIT_BYTES` (and every relations or calibration file) is read once by
the client and shipped as bytes: `client.scatter(..., broadcast=True)` puts one copy on every
worker, so that a worker that dies takes no input with it (where it held the last copy, the
runner ships it again) and a two-machine cluster needs no shared disk. Each run writes the
bytes, under the file's own name, into its scratch folder on the worker. A larger recording, or a ROS 2 bag (a folder), goes by its path instead, which every
worker must see (the same path on a shared file system); `transfer: ship | shared` forces either.

A world to simulate is made into a recording by a task of its own (`prepare_world`): the drive's
ground truth and odometry, the scans of the simulated sensor (`sensor: laser`, a planar laser at
the ToF slice's height, fast; or `sensor: tof`, the demo's pipeline: render the ToF frames,
calibrate the rig from rendered targets, extract the scans), written as a ROS 1 LaserScan bag
with the ground truth on /ground_truth. Its bytes come back to the client (DIR/inputs/NAME.bag)
and go on to the runs like any shipped file.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omnitof.bench.experiment import InputSpec

# Dask's guidance is to keep what a task carries small; 64 MiB is well above any CARMEN log
# (Intel, the longest public one, is 2.2 MB compressed) and small enough to copy to every worker.
SHIP_LIMIT_BYTES = 64 * 2**20
# The height of the scan slice the simulated laser sees (omnitof.scan's default slice).
SLICE_HEIGHT_M = 0.6


@dataclass(frozen=True)
class InputFile:
    """A file as a run receives it: its bytes (shipped) or a path every worker sees (shared);
    `made`: for a simulated world's bag, how it was made (DIR/inputs/NAME.yaml)."""

    name: str
    data: bytes | None = None
    path: str | None = None
    made: dict[str, Any] | None = None

    def materialise(self, folder: Path) -> Path:
        """The file on this machine: the shared path, or the bytes written into `folder` under
        the file's own name (its suffix tells the readers what it is: .bz2, .gz, .bag)."""
        if self.data is None:
            return Path(self.path)
        target = folder / self.name
        target.write_bytes(self.data)
        return target

    @property
    def shipped(self) -> bool:
        return self.data is not None


def input_file(path: str | Path, transfer: str = "auto") -> InputFile:
    """How the file at `path` (on the client) travels: see the module docstring."""
    path = Path(path)
    ship = transfer == "ship" or (transfer == "auto" and path.is_file() and path.stat().st_size <= SHIP_LIMIT_BYTES)
    if ship and not path.is_file():
        from omnitof.bench.experiment import ExperimentError

        raise ExperimentError(f"{path}: transfer: ship needs a single file (a ROS 2 bag is a folder): use shared")
    if ship:
        return InputFile(path.name, data=path.read_bytes())
    return InputFile(path.name, path=str(path.resolve()))


def prepare_world(item: InputSpec, world: Any) -> InputFile:
    """A world input made into a LaserScan bag (module docstring): the bag's bytes, and how it
    was made (the drive, the sensor, the calibration, the time)."""
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="omnitof-world-") as tmp:
        if item.sensor == "laser":
            scans, record = _laser_scans(item, world)
        else:
            scans, record = _tof_scans(item, world, Path(tmp))
        from omnitof.io.rosbag import write_laserscan_bag

        bag = Path(tmp) / f"{item.name}.bag"
        write_laserscan_bag(bag, scans, version=1)
        data = bag.read_bytes()
    record.update({"scans": len(scans), "seconds": round(time.perf_counter() - started, 2),
                   "input_spec": item.model_dump(mode="json")})
    return InputFile(f"{item.name}.bag", data=data, made=record)


def _laser_scans(item: InputSpec, world: Any):
    import numpy as np

    from omnitof.sim import laser2d
    from omnitof.sim.sequence import MotionSettings, make_sequence
    from omnitof.types import ScanSequence

    seq = make_sequence(world, seed=item.sim_seed, motion=MotionSettings(speed=item.speed))
    n = len(seq) if item.max_scans is None else min(len(seq), item.max_scans)
    laser = item.laser
    angles = laser2d.beam_angles(laser.beams, laser.fov_deg)
    # The scans' noise has its own stream beside the odometry's (seed, 0) of make_sequence.
    ranges = laser2d.simulate_scans(world.to_world2d(SLICE_HEIGHT_M), seq.ground_truth[:n], angles,
                                    max_range=laser.max_range, range_noise=laser.noise,
                                    seed=np.random.default_rng([item.sim_seed, 1]))
    scans = ScanSequence(
        timestamps=seq.timestamps[:n], ranges=ranges, angles=angles, odometry=seq.odometry[:n],
        sensor_pose=np.zeros(3), max_range=laser.max_range, ground_truth=seq.ground_truth[:n],
        source=f"{world.name} (simulated planar laser)", max_range_rule="the simulated laser's max_range",
    )
    record = {"world": world.name, "sensor": "laser", "laser": laser.model_dump(), "sim_seed": item.sim_seed,
              "metres": round(seq.distance_driven(n), 2)}
    return scans, record


def _tof_scans(item: InputSpec, world: Any, tmp: Path):
    from omnitof.demo import DemoSettings, simulated_scans
    from omnitof.io.plain import to_plain

    # The demo's pipeline with the world given by name or file; its 3D rays are not needed.
    settings = DemoSettings(world=str(item.world), seed=item.sim_seed, calibrate=item.calibrate,
                            map3d_every=0, max_frames=item.max_scans, speed=item.speed)
    sim = simulated_scans(settings, tmp, world=world)
    record = {"world": sim.world.name, "sensor": "tof", "sim_seed": item.sim_seed,
              "metres": sim.sequence_summary["metres"], "tof_errors": sim.sequence_summary["tof_errors"], "calibration": to_plain(sim.calibration_report)}
    return sim.data.scans, record
