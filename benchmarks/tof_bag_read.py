"""Reading a ToF bag's frames: raw images against image_transport's compressed ones.

    python benchmarks/tof_bag_read.py BAG [--runs 3] [--work DIR]

BAG is a ToF bag as `omnitof simulate` writes it (32FC1 distances and amplitudes). Its frames are
written again as a camera driver records them through image_transport: the distance as 16UC1
millimetres in "compressedDepth" (a 12-byte header and a PNG), the amplitude as a mono16 PNG,
with the same camera_info and odometry. Both bags are then read (`ToFBag.frames`, without raw
samples), alternately, `--runs` times each. Prints each bag's size, frames per second of each
run and their medians, and how far the compressed distances lie from the raw ones (the 1 mm
quantisation). Then the first frame's millimetres are RVL-coded once (compressed_depth_image_transport's
other format, `_core.rvl_encode`) and decoded by the core (`_core.rvl_decode`) 200 times:
frames per second of that alone.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore

from omnitof.io.rosbag import read_tof_bag

STORE = get_typestore(Stores.ROS2_HUMBLE)
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
DEPTH_HEADER = np.zeros(1, dtype=[("compression", "<i4"), ("a", "<f4"), ("b", "<f4")]).tobytes()  # PNG, no quantisation


def compressed_copy(source: Path, target: Path) -> int:
    """Write `source`'s frames to `target` as compressed images (module docstring); the frame count."""
    from rosbags.highlevel import AnyReader

    bag = read_tof_bag(source)
    with AnyReader([source]) as reader, Writer(target, version=8) as writer:
        conns = {name: writer.add_connection(topic, kind, typestore=STORE) for name, topic, kind in (
            ("distance", "/cam/depth/compressedDepth", COMPRESSED), ("amplitude", "/cam/amplitude/compressed", COMPRESSED),
            ("info", "/cam/camera_info", CAMERA_INFO), ("odom", "/odom", ODOMETRY))}
        copied = [c for c in reader.connections if c.topic in (bag.topics.camera_info, "/odom")]
        for conn, stamp, raw in reader.messages(connections=copied):
            msg = reader.deserialize(raw, conn.msgtype)
            name = "info" if conn.msgtype == CAMERA_INFO else "odom"
            writer.write(conns[name], stamp, STORE.serialize_cdr(msg, conn.msgtype))
        count = 0
        for frame in bag.frames(samples=False):
            ns = round(frame.timestamp * 1e9)
            stamp = STORE.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
            head = STORE.types["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")
            millimetres = np.where(np.isfinite(frame.distance), np.clip(frame.distance * 1000.0, 0, 65535), 0)
            amplitude = np.clip(np.nan_to_num(frame.amplitude), 0, 65535)
            for name, fmt, data in (
                ("distance", "16UC1; compressedDepth png", DEPTH_HEADER + _png(millimetres)),
                ("amplitude", "mono16; png compressed mono16", _png(amplitude)),
            ):
                msg = STORE.types[COMPRESSED](header=head, format=fmt, data=np.frombuffer(data, dtype=np.uint8))
                writer.write(conns[name], ns, STORE.serialize_cdr(msg, COMPRESSED))
            count += 1
    return count


def _png(pixels: np.ndarray) -> bytes:
    ok, buffer = cv2.imencode(".png", np.round(pixels).astype(np.uint16))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buffer.tobytes()


def frames_per_second(path: Path, **kwargs) -> float:
    bag = read_tof_bag(path, **kwargs)
    start = time.perf_counter()
    n = sum(1 for _ in bag.frames(samples=False))
    return n / (time.perf_counter() - start)


def size_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag", type=Path)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--work", type=Path, default=Path("results/tof_bag_read"))
    args = parser.parse_args(argv)
    from omnitof.io.rosbag import ToFTopics

    args.work.mkdir(parents=True, exist_ok=True)
    target = args.work / f"{args.bag.name}_compressed"
    if not target.exists():
        compressed_copy(args.bag, target)
    topics = ToFTopics(distance="/cam/depth/compressedDepth", amplitude="/cam/amplitude/compressed",
                      camera_info="/cam/camera_info")
    raw = list(read_tof_bag(args.bag).frames(samples=False))
    packed = list(read_tof_bag(target, topics=topics).frames(samples=False))
    both = np.isfinite(np.stack([f.distance for f in raw])) & np.isfinite(np.stack([f.distance for f in packed]))
    diff = np.abs(np.stack([f.distance for f in raw]) - np.stack([f.distance for f in packed]))[both]
    rates: dict[str, list[float]] = {"raw": [], "compressed": []}
    for _ in range(args.runs):
        rates["raw"].append(frames_per_second(args.bag))
        rates["compressed"].append(frames_per_second(target, topics=topics))
    print(f"{len(raw)} frames; raw {size_mb(args.bag):.1f} MB, compressed {size_mb(target):.1f} MB; "
          f"distance difference max {diff.max() * 1000:.2f} mm, median {np.median(diff) * 1000:.2f} mm")
    for name, values in rates.items():
        print(f"{name}: {', '.join(f'{v:.0f}' for v in values)} frames/s, median {statistics.median(values):.0f}")
    from omnitof import _core

    millimetres = np.where(np.isfinite(raw[0].distance), np.round(raw[0].distance * 1000.0), 0).astype(np.uint16)
    stream = _core.rvl_encode(millimetres.ravel())
    assert np.array_equal(_core.rvl_decode(stream, millimetres.size), millimetres.ravel())
    start = time.perf_counter()
    for _ in range(200):
        _core.rvl_decode(stream, millimetres.size)
    print(f"RVL: {millimetres.size} pixels in {stream.size} bytes (PNG {len(_png(millimetres))}); "
          f"{200 / (time.perf_counter() - start):.0f} frames/s decoded")
    return 0


if __name__ == "__main__":
    sys.exit(main())
