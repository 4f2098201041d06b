"""The calibration's input images: amplitude (and, from a ToF source, distance) images read
from image files, `.npz` files as `render_calibration_images` writes them, folders of them, or
ROS bags (every frame, via `omnitof.io.rosbag.read_tof_bag`)."""

from __future__ import annotations

import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from omnitof.calibration import CalibrationError
from omnitof.errors import read_problem
from omnitof.io.rosbag import ToFTopics, read_tof_bag

IMAGE_SUFFIXES = (".png", ".pgm", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp")
BAG_SUFFIXES = (".bag", ".mcap", ".db3")


@dataclass
class AmplitudeImage:
    """One input image: a name for messages (file, or bag:frame), the amplitude (H, W) float32,
    and the distance (H, W) float32 metres when known (ToF sources), else None."""

    name: str
    amplitude: np.ndarray
    distance: np.ndarray | None = None


def load_images(paths: Iterable[str | Path], *, topics: Any = None, depth: bool = False) -> list[AmplitudeImage]:
    """Read amplitude (and distance) images from files, folders of them, and ROS bags.

    A folder that is a ROS 2 bag (has metadata.yaml) is read as a bag; another folder is read
    as the sorted image and .npz files inside it (x.npz rather than x.png when both exist). A
    bag's topics are `topics` (an `io.rosbag.ToFTopics`; default the simulator's), its distance
    images depth images with `depth` (`io.rosbag.read_tof_bag`). Raises CalibrationError naming
    the file for an unreadable or unknown input.
    """
    out: list[AmplitudeImage] = []
    for raw in paths:
        path = Path(raw)
        if not path.exists():  # before OpenCV, which prints its own warning and says only "cannot read"
            raise CalibrationError("no such file or folder", path)
        if path.is_dir() and not (path / "metadata.yaml").exists():
            members = sorted(
                p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES + (".npz",)
            )
            # An image saved both ways (render-targets writes x.png and x.npz): the .npz only,
            # which has the distances too.
            npz = {p.stem for p in members if p.suffix.lower() == ".npz"}
            members = [p for p in members if p.suffix.lower() == ".npz" or p.stem not in npz]
            if not members:
                raise CalibrationError("folder holds no images (.png, .npz, ...)", path)
            out.extend(load_images(members, topics=topics, depth=depth))
        elif path.is_dir() or path.suffix.lower() in BAG_SUFFIXES:
            out.extend(_bag_images(path, topics, depth))
        elif path.suffix.lower() == ".npz":
            out.append(_npz_image(path))
        elif path.suffix.lower() in IMAGE_SUFFIXES:
            image = _read_image(path)
            if image is None:
                raise CalibrationError("cannot read the image", path)
            if image.ndim == 3:
                image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            out.append(AmplitudeImage(str(path), image.astype(np.float32)))
        else:
            raise CalibrationError(
                f"unknown input: expected an image ({', '.join(IMAGE_SUFFIXES)}), .npz, or a "
                "ROS bag",
                path,
            )
    return out


def _npz_image(path: Path) -> AmplitudeImage:
    try:
        with np.load(path) as data:
            if "amplitude" not in data:
                raise CalibrationError("npz file has no 'amplitude' array", path)
            amplitude = np.asarray(data["amplitude"], dtype=np.float32)
            distance = np.asarray(data["distance"], dtype=np.float32) if "distance" in data else None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:  # a truncated file: BadZipFile
        raise CalibrationError(f"cannot read the npz file: {read_problem(err)}", path) from None
    if amplitude.ndim != 2 or (distance is not None and distance.shape != amplitude.shape):
        raise CalibrationError("npz images must be (H, W), amplitude and distance alike", path)
    return AmplitudeImage(str(path), amplitude, distance)


def _read_image(path: Path) -> np.ndarray | None:
    """The image at `path` as OpenCV reads it, or None where it cannot; OpenCV's own log lines
    about a broken file are held back (the caller's one error says it)."""
    from cv2.utils import logging as cv_logging

    level = cv_logging.getLogLevel()
    cv_logging.setLogLevel(cv_logging.LOG_LEVEL_SILENT)
    try:
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    finally:
        cv_logging.setLogLevel(level)


def _bag_images(path: Path, topics: Any = None, depth: bool = False) -> list[AmplitudeImage]:
    bag = read_tof_bag(path, topics=topics or ToFTopics(), depth=depth, odometry=False)
    return [
        AmplitudeImage(f"{path}:frame{k}", frame.amplitude, frame.distance)
        for k, frame in enumerate(bag.frames(samples=False))
    ]
