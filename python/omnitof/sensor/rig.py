"""The rig: one omnidirectional ToF sensor as a physical object, with one YAML form.

A rig is the camera with its lens (`Camera`), the mirrors (a plane and a name each, and the
outline where the rig was designed rather than measured), the mount on the robot
(robot_T_camera, 4×4) and the camera's signal and noise (`SensorNoise`). The simulator renders
a rig, a simulated bag carries its rig in the sidecar, the design tool chooses one
(`design.default_rig`), the scan extraction looks through one, and a calibration is an
estimated rig (planes without outlines) plus what only a calibration has: masks, residuals,
provenance (`omnitof.calibration.Calibration`).

The YAML form (`to_dict` / `from_dict`; plain data, floats exact through a YAML round trip):

    camera: {width, height, fx, fy, cx, cy, dist: [k1, k2, p1, p2, k3]}
    mirrors:
      - name: front
        normal: [nx, ny, nz]        # unit, camera frame, pointing away from the camera
        d: 0.0829                   # metres: the plane is {x : normal·x = d}
        polygon: [[x, y, z], ...]   # optional: the outline, camera frame (designed rigs)
    robot_T_camera: [[4 numbers] × 4]
    sensor: {f_mod, electrons_per_unit, read_noise, full_well, modulation_contrast,
             amplitude_at_1m, ambient,      # optional: SensorNoise's defaults
             errors: {...}}                 # optional: the systematic errors (ToFErrors), none

The calibration file and the bag sidecar both hold these keys (beside their own ones), so a
rig read from either is the same object.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import InputError
from omnitof.sensor.camera import Camera, CameraParameterError
from omnitof.sensor.mirrors import (
    Mirror,
    MirrorParameterError,
    MirrorPlane,
    camera_mount,
    masks,
    rigid_mount,
)
from omnitof.sensor.tof import SensorNoise, ToFParameterError

CAMERA_FIELDS = ("width", "height", "fx", "fy", "cx", "cy")


class RigError(InputError):
    """A rig description that cannot be read; the message names the field."""


@dataclass(frozen=True, eq=False)
class Rig:
    """One omnidirectional ToF sensor (see the module docstring).

    Attributes:
        camera: intrinsics and distortion (pixels, OpenCV's order).
        planes: one plane per mirror, camera frame, metres.
        names: the mirrors' names, same order as planes (a mirror's index is its mask label).
        robot_T_camera: 4×4 mount, maps camera-frame points to the robot frame.
        outlines: per mirror its (K, 3) polygon in the camera frame, or None for a rig whose
            outlines nobody measured (an estimated rig): rendering needs them, scans do not.
        sensor: the camera's signal scale, modulation frequency and noise.
    """

    camera: Camera
    planes: tuple[MirrorPlane, ...]
    names: tuple[str, ...]
    robot_T_camera: np.ndarray = field(default_factory=camera_mount)
    outlines: tuple[np.ndarray, ...] | None = None
    sensor: SensorNoise = field(default_factory=SensorNoise)

    def __post_init__(self) -> None:
        planes = tuple(self.planes)
        names = tuple(str(n) for n in self.names)
        if not planes:
            raise MirrorParameterError("a rig needs at least one mirror")
        if len(names) != len(planes):
            raise MirrorParameterError(f"rig: {len(planes)} mirror planes but {len(names)} names")
        if len(set(names)) != len(names):
            raise MirrorParameterError(f"rig: mirror names must differ, got {list(names)}")
        mount = rigid_mount(self.robot_T_camera)  # checked, its rotation made exact
        mount.setflags(write=False)
        outlines = self.outlines
        if outlines is not None:
            outlines = tuple(np.asarray(o, dtype=np.float64) for o in outlines)
            if len(outlines) != len(planes):
                raise MirrorParameterError(f"rig: {len(planes)} mirror planes but {len(outlines)} outlines")
            # Mirror checks that each outline is convex and on its plane.
            for plane, outline, name in zip(planes, outlines, names):
                Mirror(plane, outline, name)
        object.__setattr__(self, "planes", planes)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "robot_T_camera", mount)
        object.__setattr__(self, "outlines", outlines)

    @classmethod
    def from_mirrors(
        cls,
        camera: Camera,
        mirrors: Sequence[Mirror],
        robot_T_camera: np.ndarray | None = None,
        sensor: SensorNoise | None = None,
    ) -> Rig:
        """A designed rig: mirrors with their outlines (e.g. `mirrors.pyramid`)."""
        return cls(
            camera=camera,
            planes=tuple(m.plane for m in mirrors),
            names=tuple(m.name for m in mirrors),
            robot_T_camera=camera_mount() if robot_T_camera is None else robot_T_camera,
            outlines=tuple(m.polygon for m in mirrors),
            sensor=SensorNoise() if sensor is None else sensor,
        )

    @property
    def has_outlines(self) -> bool:
        return self.outlines is not None

    @property
    def mirrors(self) -> list[Mirror]:
        """The mirrors with their outlines (what the renderer and `mirrors.masks` need)."""
        if self.outlines is None:
            raise MirrorParameterError(
                "this rig has mirror planes but no outlines (an estimated rig); "
                "use its planes, or the calibration's masks"
            )
        return [Mirror(p, o, n) for p, o, n in zip(self.planes, self.outlines, self.names)]

    def masks(self, edge_margin_px: float = 2.0) -> np.ndarray:
        """(H, W) int32: the mirror index each pixel looks through, −1 where none or too near an
        edge (`mirrors.masks`; needs the outlines)."""
        return masks(self.camera, self.mirrors, edge_margin_px)

    def index_of(self, name: str) -> int:
        """The index (mask label) of the mirror called `name`."""
        try:
            return self.names.index(name)
        except ValueError:
            raise MirrorParameterError(f"no mirror named {name!r}; mirrors: {list(self.names)}") from None

    # --- the YAML form ---------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """The rig as plain data (see the module docstring)."""
        mirrors = []
        for k, (plane, name) in enumerate(zip(self.planes, self.names)):
            entry: dict[str, Any] = {"name": name, "normal": plane.normal.tolist(), "d": float(plane.d)}
            if self.outlines is not None:
                entry["polygon"] = self.outlines[k].tolist()
            mirrors.append(entry)
        return {
            "camera": camera_to_dict(self.camera),
            "mirrors": mirrors,
            "robot_T_camera": self.robot_T_camera.tolist(),
            "sensor": asdict(self.sensor),
        }

    @classmethod
    def from_dict(cls, data: Any, source: str | Path | None = None) -> Rig:
        """The rig of `to_dict`'s form (extra keys are ignored); RigError naming the field."""
        if not isinstance(data, Mapping):
            raise RigError("expected a mapping with the rig (camera, mirrors)", source)
        camera = camera_from_dict(_required(data, "camera", "", source), source)
        entries = _required(data, "mirrors", "", source)
        if not isinstance(entries, list) or not entries:
            raise RigError("mirrors: expected a non-empty list of mirrors", source)
        planes, names, outlines = [], [], []
        for k, entry in enumerate(entries):
            where = f"mirrors[{k}]"
            name = _required(entry, "name", where + ".", source)
            if not isinstance(name, str) or not name:  # str() would make `null` the name "None"
                raise RigError(f"{where}.name: expected a text, got {name!r}", source)
            normal = _numbers(_required(entry, "normal", where + ".", source), (3,), where + ".normal", source)
            d = _required(entry, "d", where + ".", source)
            if not isinstance(d, numbers.Real) or isinstance(d, bool):  # float() would read "0.08"
                raise RigError(f"{where}.d: expected a number of metres, got {d!r}", source)
            try:
                planes.append(MirrorPlane(normal, float(d)))
            except (MirrorParameterError, TypeError, ValueError) as err:
                raise RigError(f"{where} ({name}): {err}", source) from None
            names.append(name)
            polygon = entry.get("polygon")
            outlines.append(None if polygon is None else _numbers(polygon, (-1, 3), where + ".polygon", source))
        if all(o is None for o in outlines):
            kept_outlines = None
        elif any(o is None for o in outlines):
            raise RigError("mirrors: give a polygon for every mirror or for none", source)
        else:
            kept_outlines = tuple(outlines)
        mount = _numbers(data.get("robot_T_camera", camera_mount()), (4, 4), "robot_T_camera", source)
        sensor_data = data.get("sensor") or {}
        if not isinstance(sensor_data, Mapping):
            raise RigError("sensor: expected a mapping of SensorNoise fields", source)
        try:
            sensor = SensorNoise(**sensor_data)
        except (ToFParameterError, TypeError, ValueError) as err:
            raise RigError(f"sensor: {err}", source) from None
        try:
            return cls(camera, tuple(planes), tuple(names), mount, kept_outlines, sensor)
        except (MirrorParameterError, ValueError) as err:
            raise RigError(str(err), source) from None


def camera_to_dict(camera: Camera) -> dict[str, Any]:
    """The camera entry of the YAML form."""
    return {
        "width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy,
        "cx": camera.cx, "cy": camera.cy, "dist": list(camera.dist),
    }


def camera_from_dict(data: Any, source: str | Path | None = None, error: type[InputError] = RigError) -> Camera:
    """The camera of a YAML entry; `error` (naming the field) if it is incomplete or invalid."""
    values = {key: _required(data, key, "camera.", source, error) for key in CAMERA_FIELDS}
    for key, value in values.items():  # named here: Camera's own error does not say which field
        if not isinstance(value, numbers.Real) or isinstance(value, bool):
            raise error(f"camera.{key}: expected a number, got {value!r}", source)
    dist = _numbers(_required(data, "dist", "camera.", source, error), (5,), "camera.dist", source, error)
    try:
        return Camera(**values, dist=tuple(float(v) for v in dist))
    except (CameraParameterError, TypeError, ValueError) as err:
        raise error(f"camera: {err}", source) from None


def _required(data: Any, key: str, where: str, source: str | Path | None,
              error: type[InputError] = RigError) -> Any:
    if not isinstance(data, Mapping) or key not in data:
        raise error(f"{where}{key}: missing", source)
    return data[key]


def _numbers(value: Any, shape: tuple[int, ...], where: str, source: str | Path | None,
             error: type[InputError] = RigError) -> np.ndarray:
    """Finite float64 numbers of `shape` (−1: any length)."""
    try:
        # numpy reads `true` as 1 and "0.08" as 0.08: in a YAML file those are typos, not numbers.
        items = [] if isinstance(value, np.ndarray) else np.asarray(value, dtype=object).ravel()
        odd = next((v for v in items if isinstance(v, (bool, str, bytes))), None)
        out = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise error(f"{where}: expected numbers of shape {shape}", source) from None
    if odd is not None:
        raise error(f"{where}: {odd!r} is not a number", source)
    fits = out.ndim == len(shape) and all(w in (-1, s) for w, s in zip(shape, out.shape))
    if not fits:
        raise error(f"{where}: expected finite numbers of shape {shape}, got shape {out.shape}", source)
    if not np.all(np.isfinite(out)):
        at = tuple(int(i) for i in np.argwhere(~np.isfinite(out))[0])
        raise error(f"{where}: entry {list(at)} is {out[at]}, not a finite number", source)
    return out
