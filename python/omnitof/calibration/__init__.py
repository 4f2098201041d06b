"""Calibration of the omnidirectional ToF sensor: the file that the scan extraction reads.

A calibration (`Calibration`) is an estimated rig (`omnitof.sensor.rig.Rig`: camera, mirror
planes with names, mount) plus what only a calibration has: the masks, the residuals
(`quality`) and how it was made (`provenance`). It holds what the paper's sec. II-C
determines, in the camera frame of `omnitof.sensor.mirrors` (z = optical axis, up into the
mirrors; metres):

- the intrinsics (`omnitof.sensor.camera.Camera`: K and the distortion), from a checkerboard seen
  without the mirrors (`omnitof.calibration.intrinsics`);
- one plane {x : n·x = d} per mirror (n away from the camera, d > 0), from the four-dot target
  seen directly and through the mirror (`omnitof.calibration.mirror_planes`; paper eq. 5);
  each plane gives the reflection D and the virtual camera Pv = P·D of eq. 6;
- the masks: per pixel, the index of the mirror it looks through (−1: not used), drawn from
  the calibrated geometry or from hand-drawn image polygons (`omnitof.calibration.masks`);
- the mount robot_T_camera, which the paper does not calibrate: taken from the rig's design.

The file (`save_calibration` / `load_calibration`) is one YAML document; its camera, mirrors
and robot_T_camera are the rig's YAML form (`Rig.to_dict`), read by the same code:

    omnitof_calibration: 1                 # format version
    camera: {width, height, fx, fy, cx, cy, dist: [k1, k2, p1, p2, k3]}
    robot_T_camera: [[4 numbers] × 4]
    mirrors:                               # in label order: labels == k means mirrors[k]
      - name: front
        normal: [nx, ny, nz]               # unit, camera frame, pointing away from the camera
        d: 0.0829                          # metres, > 0
        D: [[...] × 4]                     # informative: recomputed from normal and d on load
        Pv: [[...] × 3]                    # informative: K[I|0]·D (eq. 6)
        quality: {...}                     # optional: residuals of the mirror calibration
    masks:
      edge_margin_px: 2.0
      polygons: {front: [[u, v], ...], ...}   # optional: hand-drawn regions (image pixels)
      rows: ["-1*12 0*40 ...", ...]        # the labels, one run-length string per image row:
                                           # "value*count" tokens, left to right
    quality: {...}                         # optional: intrinsics RMS etc.
    provenance: {...}                      # optional: how and from what it was made
    distance_correction: {...}             # optional: the systematic distance error
                                           # (omnitof.calibration.distance); absent = none

The run-length rows are the truth for `labels` (loading reproduces them exactly); polygons are
kept so that a person can edit them and redraw the rows with `omnitof calibrate masks`.
Floats are written with Python's repr, so numbers survive a round trip bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from omnitof.errors import InputError, YamlDumper, load_yaml, yaml_problem
from omnitof.io.atomic import atomic_write
from omnitof.io.plain import to_plain
from omnitof.calibration.distance import DistanceCorrection, DistanceCorrectionError
from omnitof.sensor.camera import Camera
from omnitof.sensor.mirrors import MirrorParameterError, MirrorPlane
from omnitof.sensor.rig import Rig, RigError, camera_to_dict

__all__ = [
    "FORMAT_VERSION",
    "MIRRORS_NOT_CALIBRATED",
    "Calibration",
    "CalibrationError",
    "decode_rows",
    "encode_rows",
    "load_calibration",
    "save_calibration",
]

FORMAT_VERSION = 1
# What `calibrate intrinsics` writes as the mirrors' provenance of a new calibration file: its
# mirrors are the design's until `calibrate mirrors` measures them (a scan reader warns).
MIRRORS_NOT_CALIBRATED = "rig design (not calibrated yet: run `calibrate mirrors`)"


class CalibrationError(InputError):
    """A calibration that cannot be made or read; the message names the image, mirror or field."""


@dataclass(eq=False)
class Calibration:
    """An estimated rig plus its masks, residuals and provenance (see the module docstring).

    Attributes:
        rig: the estimated sensor: camera (pixels, OpenCV's distortion order), one MirrorPlane
            and name per mirror (camera frame, metres; no outlines), robot_T_camera (4×4).
        labels: (H, W) int32, index into the rig's planes per pixel, −1 = not used.
        polygons: per mirror name, an (K, 2) float64 image polygon (u, v pixels) the mask was
            drawn from, if it was drawn from one; editable.
        edge_margin_px: margin the masks keep from region boundaries (as `mirrors.masks`).
        quality: free-form numbers from the calibration runs (RMS reprojection error, per
            mirror epipole residuals, ...), stored as they are.
        provenance: free-form description of how the calibration was made.
        distance_correction: the systematic distance error to remove from every reading
            (`calibration.distance.DistanceCorrection`), or None.
    """

    rig: Rig
    labels: np.ndarray
    polygons: dict[str, np.ndarray] = field(default_factory=dict)
    edge_margin_px: float = 2.0
    quality: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    distance_correction: DistanceCorrection | None = None

    def __post_init__(self) -> None:
        labels = np.asarray(self.labels)
        if labels.shape != self.camera.shape:
            raise CalibrationError(
                f"Calibration.labels must have the image shape {self.camera.shape}, "
                f"got {labels.shape}"
            )
        if labels.size and (labels.min() < -1 or labels.max() >= len(self.planes)):
            raise CalibrationError(
                f"Calibration.labels must lie in [-1, {len(self.planes) - 1}], "
                f"got [{labels.min()}, {labels.max()}]"
            )
        self.labels = labels.astype(np.int32)
        self.polygons = {
            str(k): np.asarray(v, dtype=np.float64).reshape(-1, 2) for k, v in self.polygons.items()
        }

    @classmethod
    def estimated(
        cls,
        camera: Camera,
        planes: Sequence[MirrorPlane],
        names: Sequence[str],
        robot_T_camera: np.ndarray,
        labels: np.ndarray,
        **rest: Any,
    ) -> Calibration:
        """A calibration from estimated parts (rest: polygons, edge_margin_px, quality,
        provenance); CalibrationError if the parts do not fit together."""
        try:
            rig = Rig(camera, tuple(planes), tuple(names), robot_T_camera)
        except (MirrorParameterError, ValueError) as err:
            raise CalibrationError(f"Calibration: {err}") from None
        return cls(rig, labels, **rest)

    @classmethod
    def from_rig(cls, rig: Rig, edge_margin_px: float = 2.0) -> Calibration:
        """The true geometry of a designed rig: its planes, names, and `mirrors.masks` as
        labels (the outlines are dropped: a calibration does not measure them)."""
        return cls(
            rig=Rig(rig.camera, rig.planes, rig.names, rig.robot_T_camera, sensor=rig.sensor),
            labels=rig.masks(edge_margin_px),
            edge_margin_px=float(edge_margin_px),
            provenance={"source": "rig design (true geometry)"},
        )

    @property
    def camera(self) -> Camera:
        return self.rig.camera

    @property
    def planes(self) -> tuple[MirrorPlane, ...]:
        """The rig's planes (a tuple: change them through `with_rig`)."""
        return self.rig.planes

    @property
    def names(self) -> list[str]:
        return list(self.rig.names)

    @property
    def robot_T_camera(self) -> np.ndarray:
        return self.rig.robot_T_camera

    @property
    def P(self) -> np.ndarray:
        """The real camera's 3×4 projection K[I|0] (camera frame; distortion not included)."""
        return self.camera.K @ np.hstack([np.eye(3), np.zeros((3, 1))])

    def reflection_matrices(self) -> list[np.ndarray]:
        """D (4×4) of each mirror (eq. 6)."""
        return [p.reflection_matrix() for p in self.planes]

    def virtual_cameras(self) -> list[np.ndarray]:
        """Pv = P·D (3×4) of each mirror (eq. 6)."""
        return [p.virtual_camera(self.P) for p in self.planes]

    def index_of(self, name: str) -> int:
        """The label of the mirror called `name`."""
        try:
            return self.names.index(name)
        except ValueError:
            raise CalibrationError(f"no mirror named {name!r}; mirrors: {self.names}") from None

    def with_rig(self, rig: Rig) -> Calibration:
        """The same masks and records with another rig (e.g. a refined one)."""
        return Calibration(rig, self.labels, dict(self.polygons), self.edge_margin_px,
                           dict(self.quality), dict(self.provenance), self.distance_correction)


# --- run-length rows -----------------------------------------------------------------------


def encode_rows(labels: np.ndarray) -> list[str]:
    """One string per image row: "value*count" runs, left to right (e.g. "-1*3 0*5")."""
    rows = []
    for row in np.asarray(labels):
        change = np.flatnonzero(np.diff(row)) + 1
        starts = np.concatenate([[0], change])
        ends = np.concatenate([change, [len(row)]])
        rows.append(" ".join(f"{int(row[s])}*{int(e - s)}" for s, e in zip(starts, ends)))
    return rows


def decode_rows(rows: Sequence[str], shape: tuple[int, int], path: str | Path | None = None) -> np.ndarray:
    """Inverse of `encode_rows`; InputError naming the row if a row is malformed."""
    height, width = shape
    if not isinstance(rows, Sequence) or isinstance(rows, str) or len(rows) != height:
        n = len(rows) if isinstance(rows, Sequence) else type(rows).__name__
        raise CalibrationError(f"masks.rows: expected {height} rows (image height), got {n}", path)
    out = np.empty((height, width), dtype=np.int32)
    for r, text in enumerate(rows):
        values: list[int] = []
        try:
            for token in str(text).split():
                value, count = token.split("*")
                n = int(count)
                if n <= 0:
                    raise ValueError
                # Bounded before expanding: a count of 1e9 would allocate gigabytes first.
                if n > width - len(values):
                    raise CalibrationError(
                        f"masks.rows[{r}]: runs cover more than the image's {width} pixels", path
                    )
                values.extend([int(value)] * n)
        except ValueError:
            raise CalibrationError(
                f"masks.rows[{r}]: expected 'value*count' tokens, got {str(text)[:60]!r}", path
            ) from None
        if len(values) != width:
            raise CalibrationError(
                f"masks.rows[{r}]: runs cover {len(values)} pixels, the image is {width} wide", path
            )
        out[r] = values
    return out


# --- YAML ----------------------------------------------------------------------------------


def _floats(array: np.ndarray) -> list:
    return np.asarray(array, dtype=np.float64).tolist()


def calibration_to_dict(cal: Calibration) -> dict[str, Any]:
    """The YAML document of `cal` as plain Python data (see the module docstring)."""
    cam = cal.camera
    P = cal.P
    mirrors = []
    for name, plane in zip(cal.names, cal.planes):
        entry: dict[str, Any] = {
            "name": name,
            "normal": _floats(plane.normal),
            "d": float(plane.d),
            "D": _floats(plane.reflection_matrix()),
            "Pv": _floats(plane.virtual_camera(P)),
        }
        per_mirror = cal.quality.get("mirrors")
        q = per_mirror.get(name) if isinstance(per_mirror, Mapping) else None
        if q:
            entry["quality"] = to_plain(q)
        mirrors.append(entry)
    mask: dict[str, Any] = {"edge_margin_px": float(cal.edge_margin_px)}
    if cal.polygons:
        mask["polygons"] = {k: _floats(v) for k, v in cal.polygons.items()}
    mask["rows"] = encode_rows(cal.labels)
    # Per-mirror quality (a mapping by name) is written beside each mirror; anything else as is.
    quality = {
        k: v for k, v in cal.quality.items() if not (k == "mirrors" and isinstance(v, Mapping))
    }
    out = {
        "omnitof_calibration": FORMAT_VERSION,
        "camera": camera_to_dict(cam),
        "robot_T_camera": _floats(cal.robot_T_camera),
        "mirrors": mirrors,
        "masks": mask,
        "quality": to_plain(quality),
        "provenance": to_plain(cal.provenance),
    }
    if cal.distance_correction is not None:
        out["distance_correction"] = cal.distance_correction.to_dict()
    return out


def save_calibration(cal: Calibration, path: str | Path) -> Path:
    """Write `cal` as YAML to `path` (atomically); returns the path."""
    path = Path(path)
    text = yaml.dump(
        calibration_to_dict(cal), Dumper=_Dumper, sort_keys=False, width=100, allow_unicode=True
    )
    header = "# omnitof calibration: camera frame, metres; see omnitof.calibration\n"
    with atomic_write(path, "w") as handle:
        handle.write(header + text)
    return path


class _Dumper(YamlDumper):
    """Lists of numbers on one line ([1.0, 2.0]); everything else (mask rows) one item a line."""


def _represent_list(dumper: YamlDumper, data: list) -> yaml.Node:
    flow = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_Dumper.add_representer(list, _represent_list)


def _field(data: Mapping, key: str, where: str, path: Path) -> Any:
    if not isinstance(data, Mapping) or key not in data:
        raise CalibrationError(f"{where}{key}: missing", path)
    return data[key]


def _mapping(value: Any, where: str, path: Path) -> dict[str, Any]:
    """An optional free-form record (quality, provenance): a mapping, or absent."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise CalibrationError(f"{where}: expected a mapping, got {repr(value)[:40]}", path)
    return dict(value)


# A pyramid face's normal must lie this far from the optical axis and from perpendicular to it,
# and two faces' normals this far apart: nearer, the masks and scans come out degenerate.
PYRAMID_TOLERANCE_DEG = 5.0


def _check_pyramid(planes: Sequence[MirrorPlane], names: Sequence[str], path: Path) -> None:
    """CalibrationError unless the planes can be a mirror pyramid around the optical axis (z):
    each in front of the camera, tilted from the axis, and no two facing the same way."""
    tol = PYRAMID_TOLERANCE_DEG
    for k, (plane, name) in enumerate(zip(planes, names)):
        where = f"mirrors[{k}] ({name})"
        angle = math.degrees(math.acos(max(-1.0, min(1.0, float(plane.normal[2])))))
        if angle >= 90.0 + tol:
            raise CalibrationError(
                f"{where}: the plane lies behind the camera (its normal points {angle:.1f}° from the "
                "optical axis); a mirror's normal points away from the camera, up the optical axis", path)
        if angle > 90.0 - tol:
            raise CalibrationError(
                f"{where}: the normal is {angle:.1f}° from the optical axis, within {tol:g}° of "
                "perpendicular: the plane runs along the axis and the camera sees it edge-on", path)
        if angle < tol:
            raise CalibrationError(
                f"{where}: the normal is {angle:.1f}° from the optical axis, within {tol:g}° of it: "
                "the mirror faces the camera and reflects it into itself, not out to the sides", path)
    for k in range(len(planes)):
        for j in range(k):
            cos = max(-1.0, min(1.0, float(planes[j].normal @ planes[k].normal)))
            if math.degrees(math.acos(cos)) < tol:
                raise CalibrationError(
                    f"mirrors[{k}] ({names[k]}) faces the same way as mirrors[{j}] ({names[j]}) "
                    f"(normals within {tol:g}°): a pyramid's mirrors are distinct planes facing "
                    "different ways", path)


def calibration_from_dict(data: Any, path: str | Path = "<calibration>") -> Calibration:
    """Parse the YAML document (plain data) of a calibration; errors name `path` and the field."""
    path = Path(path)
    if not isinstance(data, Mapping):
        raise CalibrationError("expected a YAML mapping (an omnitof calibration file)", path)
    version = data.get("omnitof_calibration")
    if type(version) is not int or version != FORMAT_VERSION:  # `true` and 1.0 equal 1 in Python
        raise CalibrationError(
            f"omnitof_calibration: expected format version {FORMAT_VERSION}, got {version!r}", path
        )
    try:
        rig = Rig.from_dict({k: v for k, v in data.items() if k in ("camera", "mirrors", "robot_T_camera")}, path)
    except RigError as err:
        raise CalibrationError(err.reason, path) from None
    camera, planes, names = rig.camera, list(rig.planes), list(rig.names)
    _check_pyramid(planes, names, path)
    mirror_quality = {
        name: _mapping(entry.get("quality"), f"mirrors[{k}].quality", path)
        for k, (name, entry) in enumerate(zip(names, data["mirrors"])) if entry.get("quality") is not None
    }
    mask = _field(data, "masks", "", path)
    if not isinstance(mask, Mapping):
        raise CalibrationError("masks: expected a mapping with edge_margin_px, rows", path)
    try:
        margin = float(mask.get("edge_margin_px", 2.0))
    except (TypeError, ValueError):
        margin = math.nan
    if not (math.isfinite(margin) and margin >= 0.0):
        raise CalibrationError("masks.edge_margin_px: expected a number >= 0", path)
    polygons = {}
    raw_polygons = mask.get("polygons") or {}
    if not isinstance(raw_polygons, Mapping):
        raise CalibrationError("masks.polygons: expected a mapping from mirror name to [[u, v], ...]", path)
    for key, poly in raw_polygons.items():
        try:
            arr = np.asarray(poly, dtype=np.float64) if isinstance(poly, list) else np.zeros((0,))
        except (TypeError, ValueError):  # a point such as [1] or ["a", 2]
            arr = np.zeros((0,))
        if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 3 or not np.all(np.isfinite(arr)):
            raise CalibrationError(f"masks.polygons.{key}: expected >= 3 points [u, v]", path)
        if str(key) not in names:
            raise CalibrationError(f"masks.polygons.{key}: no mirror of that name ({names})", path)
        polygons[str(key)] = arr
    labels = decode_rows(_field(mask, "rows", "masks.", path), camera.shape, path)
    if labels.min() < -1 or labels.max() >= len(planes):
        raise CalibrationError(
            f"masks.rows: labels must lie in [-1, {len(planes) - 1}], got "
            f"[{labels.min()}, {labels.max()}]",
            path,
        )
    correction = None
    if data.get("distance_correction") is not None:
        try:
            correction = DistanceCorrection.from_dict(data["distance_correction"], camera.shape, path)
        except DistanceCorrectionError as err:
            raise CalibrationError(err.reason, path) from None
    quality = _mapping(data.get("quality"), "quality", path)
    if mirror_quality:
        quality["mirrors"] = mirror_quality
    try:
        return Calibration(
            rig=rig,
            labels=labels,
            polygons=polygons,
            edge_margin_px=margin,
            quality=quality,
            provenance=_mapping(data.get("provenance"), "provenance", path),
            distance_correction=correction,
        )
    except CalibrationError as err:
        raise CalibrationError(err.reason, path) from None


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration YAML written by `save_calibration` (or by hand, same schema)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise CalibrationError(f"cannot read the calibration: {err.strerror or err}", path) from None
    except UnicodeDecodeError:
        raise CalibrationError("not a text file (a calibration is a UTF-8 YAML file)", path) from None
    try:
        data = load_yaml(text)
    except yaml.YAMLError as err:
        problem, line = yaml_problem(err)
        raise CalibrationError(problem, path, line) from None
    return calibration_from_dict(data, path)
