"""The multipath compensation of the scan extraction (omnitof.scan.multipath): what it takes
out of the matte walls' distances, and what it costs per frame.

First, against the renderer: noise-free phasors of corridor1 at the 24 poses below, rendered
with multipath (8 rays a pixel, averaged over 9 × 9) and without, coaxial light and LEDs; for
the pixels in the slice, the distance the interreflection really adds (the phase of the ratio
of the two phasors) against the correction the compensation applies to the frame with it, by
measured distance, over the pixels it keeps (it drops those beyond `max_ratio`; their share is
given) (`--skip-check` leaves it out).

Then, per world, the 24 frames of benchmarks/tof_errors.py (seed 0, default rig, 4 sub-rays, noise
on), rendered with multipath alone and with every effect on; scans from the true rig's
extractor, pixel filter on, without and with the compensation set up for the rendering camera;
every 1° bin whose nearest surface at the slice height is matte compared with the exact
horizontal distance: signed median, median / p90 |error| and the share within 5 cm. Then the
time of extract_many on 60 frames of corridor1 with every effect on, without and with the
compensation, alternately, `--runs` times (frames/s, median and range), and the compensation's
results for 1 and 2 threads compared.

    python benchmarks/multipath_compensation.py [--worlds corridor1 room] [--runs 5] [--skip-check]
        [--skip-accuracy] [--skip-speed]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from tof_errors import compensation, frames, matte_errors, stats

from omnitof.calibration import Calibration
from omnitof.scan.extract import ScanExtractor
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.worlds import load_world


def against_renderer(name: str = "corridor1", count: int = 24) -> None:
    from omnitof.sensor.tof import SensorNoise, phase_to_distance
    from omnitof.sim.render import Renderer
    from omnitof.sim.sequence import make_sequence

    world = load_world(name)
    seq = make_sequence(world, seed=0)
    poses = seq.ground_truth[np.linspace(0, len(seq) - 1, count).round().astype(int)]
    print("| light | measured distance m | pixels | dropped | added by the interreflection, median / mean cm | "
          "the compensation's correction, median / mean cm |")
    print("|---|---|---|---|---|---|")
    for leds in (False, True):
        with_mp = Renderer(world, sensor=SensorNoise(errors=ToFErrors(multipath=True, multipath_rays=8,
                                                                      illumination=leds)))
        without = Renderer(world, sensor=SensorNoise(errors=ToFErrors(illumination=leds)))
        ex = ScanExtractor.from_calibration(Calibration.from_rig(without.rig), multipath=compensation(with_mp, True))
        zm = with_mp.phasors(poses).phasor.astype(np.complex128)
        zn = without.phasors(poses).phasor.astype(np.complex128)
        d = phase_to_distance(np.mod(np.angle(zm), 2 * np.pi), without.sensor.f_mod).astype(np.float32)
        a = np.abs(zm).astype(np.float32)
        corrected = ex._multipath.correct(d, a)
        k = phase_to_distance(1.0, without.sensor.f_mod)  # metres per radian
        idx = ex._index
        dd = d.reshape(len(d), -1)[:, idx]
        keep = (np.abs(zn.reshape(len(d), -1)[:, idx]) > 40) & (dd >= ex._d_lo) & (dd <= ex._d_hi)
        with np.errstate(invalid="ignore", divide="ignore"):  # unlit pixels: 0/0, left out by `keep`
            added = (np.angle(zm / zn).reshape(len(d), -1)[:, idx] * k)[keep] * 100
        applied = (dd - corrected.reshape(len(d), -1)[:, idx])[keep] * 100
        for lo, hi in ((0, 1.5), (1.5, 3), (3, 5), (5, 8)):
            band = (dd[keep] >= lo) & (dd[keep] < hi)
            m = band & np.isfinite(applied)  # the pixels it drops (beyond max_ratio) apart
            print(f"| {'LEDs' if leds else 'coaxial'} | {lo}–{hi} | {m.sum()} | {100 * (1 - m.sum() / band.sum()):.1f} % | "
                  f"{np.median(added[m]):.2f} / {np.mean(added[m]):.2f} | {np.median(applied[m]):.2f} / "
                  f"{np.mean(applied[m]):.2f} |", flush=True)


def accuracy(names: list[str], count: int) -> None:
    print("| world | effects | compensation | bins | signed median cm | median / p90 |error| (cm) / within 5 cm |")
    print("|---|---|---|---|---|---|")
    for name in names:
        world = load_world(name)
        for label, errors in (("multipath", ToFErrors(multipath=True)), ("all", ToFErrors.realistic())):
            renderer, poses, fr = frames(world, errors, count)
            d = np.stack([f.distance for f in fr])
            a = np.stack([f.amplitude for f in fr])
            cal = Calibration.from_rig(renderer.rig)
            for on in (False, True):
                ex = ScanExtractor.from_calibration(cal, multipath=compensation(renderer, on))
                e = matte_errors(world, renderer, ex, poses, ex.extract_many(d, a))
                print(f"| {name} | {label} | {'on' if on else 'off'} | {len(e)} | {100 * np.median(e):+.2f} | "
                      f"{stats(e)} |", flush=True)


def speed(runs: int, count: int = 60) -> None:
    world = load_world("corridor1")
    renderer, _, fr = frames(world, ToFErrors.realistic(), count)
    d = np.stack([f.distance for f in fr])
    a = np.stack([f.amplitude for f in fr])
    cal = Calibration.from_rig(renderer.rig)
    off = ScanExtractor.from_calibration(cal, multipath=compensation(renderer, False))
    on = ScanExtractor.from_calibration(cal, multipath=compensation(renderer, True))
    rates: dict[str, list[float]] = {"off": [], "on": []}
    for _ in range(runs):
        for key, ex in (("off", off), ("on", on)):
            t = time.perf_counter()
            ex.extract_many(d, a)
            rates[key].append(count / (time.perf_counter() - t))
    for key, r in rates.items():
        print(f"| extraction, compensation {key} | {statistics.median(r):.1f} ({min(r):.1f}–{max(r):.1f}) frames/s |")
    one, two = (on._multipath.with_threads(n) for n in (1, 2))
    same = np.array_equal(one.correct(d[:8], a[:8]), two.correct(d[:8], a[:8]))
    print(f"| 1 and 2 threads give the same distances | {same} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["corridor1", "corridor2", "office", "room"])
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--skip-accuracy", action="store_true")
    parser.add_argument("--skip-check", action="store_true")
    parser.add_argument("--skip-speed", action="store_true")
    args = parser.parse_args()
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}")
    if not args.skip_check:
        against_renderer()
    if not args.skip_accuracy:
        accuracy(args.worlds, args.frames)
    if not args.skip_speed:
        speed(args.runs)
    print(f"# done, load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
