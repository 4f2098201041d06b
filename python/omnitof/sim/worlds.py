"""Simulated indoor worlds: the YAML schema, its loader, and the world's geometry for tests.

A world file (`omnitof/worlds/<name>.yaml`, package data) describes one floor of a building:

- `ceiling_height` (m; the floor is z = 0), `floor_material`, `ceiling_material`, `ambient`
  (scale of the background light, 1 = a lit office);
- `materials`: named materials added to (or replacing) the built-in ones (`MATERIALS`), each
  one of four kinds: matte (albedo), metal (weak diffuse albedo, strong `specular` mirror
  fraction), glass (weak albedo and `specular`, strong `transmission`), grid (bars of `albedo`
  covering `coverage` of the area, `pitch` metres apart);
- `walls`: polylines in plan with a `height` (default: the ceiling) and a material; `doors` cut
  gaps into them (`segment`: which edge of the polyline, `at`: metres from that edge's first
  vertex to the door's centre, `width`, `height` of the opening; a wall piece stays above it).
  A door may have a `leaf` (its material), closed in the gap or swung open by `open_deg`
  about the jamb nearer the edge's first vertex (positive: to the left of the edge's direction);
- `boxes`: furniture as boxes: `centre`, `size` (along the box's own axes), `yaw_deg`,
  `bottom` and `height` (z of the lowest and highest face);
- `landmarks`: places where the distance between two opposite walls is known (the paper's
  Table I): `position`, `direction_deg` of the measurement, true `distance`, `height`;
- `path`: the robot's loop as `waypoints` (closed unless `closed: false`), driven `laps` times (1 to 10 000; an open path once);
  each waypoint within the walls' and boxes' extent and outside the boxes the robot cannot pass;
- `extends`: another world file (name in the same folder, without .yaml; else a bundled world
  of that name) whose keys this one takes over and may replace, key by key; a name starting with
  "_" is a shared part, not a world.

Frames and units: world x, y on the floor, z up, metres; angles in the file in degrees
(`*_deg`), in radians everywhere in code. A bearing is counter-clockwise from +x.

Errors: every problem raises `WorldError` (an `InputError`) whose message names the file and the
field, e.g. `room.yaml: walls[2].doors[0].at: the door runs past the end of edge 1 (4.20 m)`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import ConfigDict, Field, ValidationError, model_validator

from omnitof.settings_model import SettingsModel
from omnitof.errors import InputError, leading_problem, load_yaml, yaml_problem
from omnitof.sim.laser2d import World2D

# Obstacles that reach below this height (m) block the robot: a Pioneer-class base with the
# camera and the mirror pyramid on top stays under about 0.8 m; table tops at 0.72–0.75 m count.
ROBOT_HEIGHT = 1.0
# The loop's waypoints and legs keep at least this distance (m) from every obstacle.
MIN_CLEARANCE = 0.5


class WorldError(InputError):
    """A bad world file or world value; the message names the file and the field."""


# --- materials -------------------------------------------------------------------------------

# Numbers are reflectances in the near infrared (~850 nm, the ToF camera's LEDs). They are
# assumptions for typical indoor surfaces, not measurements: white wall paint reflects about
# 0.7–0.8 in the NIR, less once used (0.6); grey vinyl floors about 0.3; ceiling tiles about
# 0.75. Clear float glass reflects about 4 % per face at normal incidence (Fresnel, n = 1.5),
# so 0.08 for a pane, and transmits about 0.88 at 850 nm; dust scatters a little (0.005), which
# is enough to pull a reading through a pane a few centimetres towards it. Bare brushed steel
# mirrors most of what it does not absorb and scatters only a few per cent.

KINDS = ("matte", "metal", "glass", "grid")


class _Strict(SettingsModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


# Every length and coordinate of a world within 100 km of its origin: a building or a campus
# is far smaller, and a box 1e300 m wide turned the path's clearance into NaN.
WORLD_LIMIT = 1e5
Fraction = Annotated[float, Field(ge=0.0, le=1.0)]
Positive = Annotated[float, Field(gt=0.0, le=WORLD_LIMIT)]
Coordinate = Annotated[float, Field(ge=-WORLD_LIMIT, le=WORLD_LIMIT)]
Point2 = tuple[Coordinate, Coordinate]


class MatteSpec(_Strict):
    """A Lambertian surface."""

    kind: Literal["matte"]
    albedo: Fraction


class MetalSpec(_Strict):
    """Bare metal: a weak diffuse return and a strong mirror reflection."""

    kind: Literal["metal"]
    albedo: Fraction = 0.05
    specular: Fraction = 0.7

    @model_validator(mode="after")
    def _energy(self) -> MetalSpec:
        if self.albedo + self.specular > 1.0:
            raise ValueError("albedo + specular must not exceed 1")
        return self


class GlassSpec(_Strict):
    """A glass pane: transmits most light, mirrors a little, scatters almost nothing."""

    kind: Literal["glass"]
    albedo: Fraction = 0.005
    specular: Fraction = 0.08
    transmission: Fraction = 0.88

    @model_validator(mode="after")
    def _energy(self) -> GlassSpec:
        if self.albedo + self.specular + self.transmission > 1.0:
            raise ValueError("albedo + specular + transmission must not exceed 1")
        return self


class GridSpec(_Strict):
    """A coarse metal grid: bars cover `coverage` of the area; light passes the holes."""

    kind: Literal["grid"]
    albedo: Fraction = 0.3
    coverage: Fraction = 0.3
    pitch: Positive = 0.1


MaterialSpec = Annotated[MatteSpec | MetalSpec | GlassSpec | GridSpec, Field(discriminator="kind")]


@dataclass(frozen=True)
class Material:
    """A material as the renderer uses it; fractions of the incoming light, pitch in metres."""

    name: str
    kind: str
    albedo: float
    specular: float = 0.0
    transmission: float = 0.0
    coverage: float = 0.0
    pitch: float = 1.0

    @classmethod
    def from_spec(cls, name: str, spec: MatteSpec | MetalSpec | GlassSpec | GridSpec) -> Material:
        return cls(name=name, **spec.model_dump())

    def row(self) -> list[float]:
        """[kind index, albedo, specular, transmission, coverage, pitch] for the Rust core."""
        return [
            float(KINDS.index(self.kind)), self.albedo, self.specular, self.transmission,
            self.coverage, self.pitch,
        ]


MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        Material("wall", "matte", 0.6),
        Material("floor", "matte", 0.3),
        Material("ceiling", "matte", 0.75),
        Material("wood", "matte", 0.45),
        Material("furniture", "matte", 0.5),
        Material("dark", "matte", 0.1),
        Material("metal", "metal", 0.05, specular=0.7),
        Material("glass", "glass", 0.005, specular=0.08, transmission=0.88),
        Material("metal_grid", "grid", 0.3, coverage=0.3, pitch=0.1),
    )
}


# --- the schema -------------------------------------------------------------------------------


class DoorSpec(_Strict):
    segment: Annotated[int, Field(ge=0)] = 0
    at: Coordinate
    width: Positive
    height: Positive = 2.05
    leaf: str | None = None
    open_deg: Annotated[float, Field(ge=-180.0, le=180.0)] = 0.0


class WallSpec(_Strict):
    points: Annotated[list[Point2], Field(min_length=2)]
    closed: bool = False
    height: Positive | None = None
    material: str = "wall"
    doors: list[DoorSpec] = []


class BoxSpec(_Strict):
    centre: Point2
    size: tuple[Positive, Positive]
    yaw_deg: float = 0.0
    bottom: Annotated[float, Field(ge=0.0, le=WORLD_LIMIT)] = 0.0
    height: Positive
    material: str = "furniture"


class LandmarkSpec(_Strict):
    name: str
    position: Point2
    direction_deg: float
    distance: Positive
    height: Positive = 1.0


class PathSpec(_Strict):
    waypoints: Annotated[list[Point2], Field(min_length=2)]
    closed: bool = True
    # 10 000 laps of a 10 m loop are 100 km, a million frames at 10 Hz: more is a typo.
    laps: Annotated[int, Field(ge=1, le=10_000)] = 1

    @model_validator(mode="after")
    def _legs(self) -> PathSpec:
        # A leg of no length has no heading (the first one also sets where a closed loop ends).
        for k in range(1, len(self.waypoints)):
            if tuple(self.waypoints[k]) == tuple(self.waypoints[k - 1]):
                raise ValueError(f"waypoints {k - 1} and {k} are both {list(self.waypoints[k])}: consecutive "
                                 "waypoints must differ")
        # An open path ends where it ends: a second lap would start with a jump back (it was
        # driven once without a word).
        if not self.closed and self.laps > 1:
            raise ValueError(f"laps: {self.laps} laps of an open path (closed: false) cannot be driven; close the "
                             "path or drop laps")
        return self


class WorldSpec(_Strict):
    name: str
    description: str = ""
    ceiling_height: Positive
    floor_material: str = "floor"
    ceiling_material: str = "ceiling"
    # Background light relative to the camera's default; 1e4 is beyond direct sunlight.
    ambient: Annotated[float, Field(ge=0.0, le=1e4)] = 1.0
    materials: dict[str, MaterialSpec] = {}
    walls: list[WallSpec] = []
    boxes: list[BoxSpec] = []
    landmarks: list[LandmarkSpec] = []
    path: PathSpec | None = None


# --- the compiled world -----------------------------------------------------------------------


@dataclass(frozen=True)
class Landmark:
    """A place where the true distance between two opposite walls is known.

    position: (2,) metres; direction: radians, the line of the measurement (either way);
    distance: metres between the walls along that line; height: metres above the floor.
    """

    name: str
    position: np.ndarray
    direction: float
    distance: float
    height: float


@dataclass(frozen=True, eq=False)
class World:
    """A loaded world: everything in the world frame, metres and radians.

    Attributes:
        quads: (Q, 6) float64 vertical quads [ax, ay, bx, by, bottom, top]: wall pieces between
            doors, the pieces above doors ("lintels") and door leaves.
        quad_materials: Q material names. quad_roles: Q of "wall", "lintel", "leaf".
        boxes: (B, 7) float64 [cx, cy, size_x, size_y, yaw, bottom, top].
        box_materials: B material names.
        materials: every material the world may use, by name (built-ins and the file's own).
        waypoints: (K, 2) float64 robot loop; path_closed: whether it returns to the first
            waypoint; laps: how often it is driven.
    """

    name: str
    description: str
    source: Path | None
    ceiling_height: float
    floor_material: str
    ceiling_material: str
    ambient: float
    materials: dict[str, Material]
    quads: np.ndarray
    quad_materials: tuple[str, ...]
    quad_roles: tuple[str, ...]
    boxes: np.ndarray
    box_materials: tuple[str, ...]
    landmarks: tuple[Landmark, ...]
    waypoints: np.ndarray
    path_closed: bool
    laps: int

    def landmark(self, name: str) -> Landmark:
        """The landmark called `name` (KeyError if there is none)."""
        for mark in self.landmarks:
            if mark.name == name:
                return mark
        raise KeyError(f"world {self.name!r} has no landmark {name!r}")

    def material_of(self, name: str) -> Material:
        return self.materials[name]

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) of all walls and boxes, metres."""
        pts = [self.quads[:, 0:2], self.quads[:, 2:4]]
        if len(self.boxes):
            pts.append(_box_corners(self.boxes).reshape(-1, 2))
        allpts = np.concatenate(pts)
        return (float(allpts[:, 0].min()), float(allpts[:, 0].max()),
                float(allpts[:, 1].min()), float(allpts[:, 1].max()))

    # --- 2D views ------------------------------------------------------------------------------

    def wall_segments(self) -> np.ndarray:
        """(M, 2, 2) the floor plan: every wall piece that stands on the floor, door gaps open,
        leaves and furniture left out (for comparing a map with the building's plan)."""
        keep = [i for i, role in enumerate(self.quad_roles) if role == "wall"]
        return self.quads[keep, :4].reshape(-1, 2, 2)

    def segments_at(self, height: float, see_through: Iterable[str] = ()) -> np.ndarray:
        """(M, 2, 2) everything the horizontal plane at `height` m cuts: wall pieces, lintels,
        leaves and box sides, except surfaces whose material kind is in `see_through`
        (e.g. ("glass", "grid"))."""
        skip = set(see_through)
        unknown = skip - set(KINDS)
        if unknown:
            raise WorldError(f"see_through: unknown material kinds {sorted(unknown)}", self.source)
        parts = []
        cut = (self.quads[:, 4] <= height) & (height <= self.quads[:, 5])
        for q in np.flatnonzero(cut):
            if self.materials[self.quad_materials[q]].kind not in skip:
                parts.append(self.quads[q, :4].reshape(1, 2, 2))
        for i in range(len(self.boxes)):
            bottom, top = self.boxes[i, 5], self.boxes[i, 6]
            if bottom <= height <= top and self.materials[self.box_materials[i]].kind not in skip:
                corners = _box_corners(self.boxes[i : i + 1])[0]
                parts.append(np.stack([corners, np.roll(corners, -1, axis=0)], axis=1))
        return np.concatenate(parts) if parts else np.zeros((0, 2, 2))

    def to_world2d(self, height: float, see_through: Iterable[str] = ()) -> World2D:
        """The planar world of `segments_at(height, see_through)` (for the 2D laser simulator)."""
        return World2D(self.segments_at(height, see_through))

    def horizontal_distance(
        self,
        origins: np.ndarray,
        bearings: np.ndarray | float,
        height: float,
        see_through: Iterable[str] = (),
    ) -> np.ndarray:
        """Exact distance (m) from each origin to the nearest surface along horizontal rays at
        `height` m; inf where there is none. The floor and ceiling are never met (the rays are
        horizontal). Ground truth for tests: an independent 2D cast, not the renderer.

        Args:
            origins: (N, 2) metres, or (2,) for one origin.
            bearings: radians counter-clockwise from +x: scalar, (B,) for every origin, or (N, B).
            see_through: material kinds the rays pass, e.g. ("glass", "grid").

        Returns:
            (N, B) float64, squeezed like the inputs: (B,) for one origin, scalar for one ray.
        """
        o = np.asarray(origins, dtype=np.float64)
        b = np.asarray(bearings, dtype=np.float64)
        single_origin, single_bearing = o.ndim == 1, b.ndim == 0
        o2 = o.reshape(-1, 2)
        b2 = b.reshape(1, -1) if b.ndim <= 1 else b
        segments = self.segments_at(height, see_through)
        if len(segments) == 0:
            out = np.full((len(o2), b2.shape[1]), np.inf)
        else:
            out = World2D(segments).raycast(o2, np.broadcast_to(b2, (len(o2), b2.shape[1])))
        if single_origin:
            out = out[0]
            return out[0] if single_bearing else out
        return out

    def landmark_distance(self, mark: Landmark) -> float:
        """The distance between the two surfaces either side of a landmark, along its line."""
        ahead, behind = self.horizontal_distance(
            mark.position, np.array([mark.direction, mark.direction + math.pi]), mark.height
        )
        return float(ahead + behind)

    # --- the robot's loop ------------------------------------------------------------------

    def path_legs(self) -> np.ndarray:
        """(L, 2, 2) the straight legs between consecutive waypoints (and back, if closed)."""
        pts = self.waypoints
        if self.path_closed:
            pts = np.vstack([pts, pts[:1]])
        return np.stack([pts[:-1], pts[1:]], axis=1)

    def path_length(self) -> float:
        """Length (m) of the waypoint polyline, times the number of laps."""
        legs = self.path_legs()
        return float(np.linalg.norm(legs[:, 1] - legs[:, 0], axis=1).sum()) * self.laps

    def obstacles(self, robot_height: float = ROBOT_HEIGHT) -> np.ndarray:
        """(M, 2, 2) footprint edges of everything reaching below `robot_height` m (wall pieces,
        leaves, lintels that low, box sides), whatever its material: the robot cannot pass."""
        parts = [self.quads[self.quads[:, 4] < robot_height, :4].reshape(-1, 2, 2)]
        low = self.boxes[self.boxes[:, 5] < robot_height] if len(self.boxes) else self.boxes
        if len(low):
            corners = _box_corners(low)
            parts.append(np.stack([corners, np.roll(corners, -1, axis=1)], axis=2).reshape(-1, 2, 2))
        return np.concatenate(parts)

    def path_clearance(self, robot_height: float = ROBOT_HEIGHT) -> float:
        """Smallest distance (m) from the loop's legs to any obstacle (`obstacles`); 0 if a
        waypoint lies inside a box."""
        if len(self.waypoints) == 0:
            return math.inf
        if len(self.boxes):
            low = self.boxes[self.boxes[:, 5] < robot_height]
            if len(low) and np.any(_inside_boxes(self.waypoints, low)):
                return 0.0
        return float(_segment_distances(self.path_legs(), self.obstacles(robot_height)).min())

    # --- arrays for the renderer -------------------------------------------------------------

    def material_table(self) -> tuple[list[str], np.ndarray]:
        """(names, (M, 6) rows of `Material.row`) of every material, in a fixed order."""
        names = sorted(self.materials)
        return names, np.array([self.materials[n].row() for n in names], dtype=np.float64)


def _box_corners(boxes: np.ndarray) -> np.ndarray:
    """(B, 4, 2) plan corners, counter-clockwise, of boxes rows [cx, cy, sx, sy, yaw, ...]."""
    c, s = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])
    local = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])
    lx = local[None, :, 0] * boxes[:, None, 2]
    ly = local[None, :, 1] * boxes[:, None, 3]
    x = boxes[:, None, 0] + c[:, None] * lx - s[:, None] * ly
    y = boxes[:, None, 1] + s[:, None] * lx + c[:, None] * ly
    return np.stack([x, y], axis=-1)


def _inside_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) whether each point lies inside any box's plan rectangle."""
    rel = points[:, None, :] - boxes[None, :, :2]
    c, s = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])
    u = c * rel[..., 0] + s * rel[..., 1]
    v = -s * rel[..., 0] + c * rel[..., 1]
    inside = (np.abs(u) < boxes[:, 2] / 2) & (np.abs(v) < boxes[:, 3] / 2)
    return inside.any(axis=1)


def _segment_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, B) smallest distances between segments a (A, 2, 2) and b (B, 2, 2) in the plane."""
    p0, p1 = a[:, None, 0], a[:, None, 1]
    q0, q1 = b[None, :, 0], b[None, :, 1]

    def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    def point_to_segment(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
        e = s1 - s0
        t = np.clip(np.sum((p - s0) * e, axis=-1) / np.maximum(np.sum(e * e, axis=-1), 1e-300), 0, 1)
        return np.linalg.norm(p - (s0 + t[..., None] * e), axis=-1)

    d = np.minimum.reduce([
        point_to_segment(p0, q0, q1), point_to_segment(p1, q0, q1),
        point_to_segment(q0, p0, p1), point_to_segment(q1, p0, p1),
    ])
    # Proper crossings: the end points of each lie on opposite sides of the other.
    r, s = p1 - p0, q1 - q0
    crosses = (
        (np.sign(cross(r, q0 - p0)) * np.sign(cross(r, q1 - p0)) < 0)
        & (np.sign(cross(s, p0 - q0)) * np.sign(cross(s, p1 - q0)) < 0)
    )
    return np.where(crosses, 0.0, d)


# --- loading ---------------------------------------------------------------------------------


def worlds_folder() -> Path:
    """The folder of the bundled world files (package data omnitof/worlds)."""
    return Path(str(resources.files("omnitof") / "worlds"))


def world_names() -> list[str]:
    """Names of the bundled worlds, sorted (files starting with "_" are shared parts)."""
    return sorted(p.stem for p in worlds_folder().glob("*.yaml") if not p.stem.startswith("_"))


def load_world(name_or_path: str | Path) -> World:
    """Load a bundled world by name ("room", "office", "corridor1", "corridor2") or a world file
    by path. Raises WorldError naming the file and the field on any problem."""
    text = str(name_or_path)
    looks_like_path = isinstance(name_or_path, Path) or text.endswith((".yaml", ".yml")) or (
        "/" in text or "\\" in text
    )
    if looks_like_path:
        path = Path(name_or_path)
    else:
        path = worlds_folder() / f"{text}.yaml"
        if not path.is_file():
            # A name that is no bundled world but names something here: say what it is.
            here = Path(text)
            if here.is_dir():
                raise WorldError(f"{text!r} is a folder: give a world file (.yaml) or a bundled world "
                                 f"({', '.join(world_names())})")
            if here.exists():
                raise WorldError(f"{text!r} is not a world file (a world is a .yaml file) nor a bundled world "
                                 f"({', '.join(world_names())})")
            raise WorldError(f"no bundled world {text!r}; known worlds: {', '.join(world_names())}")
    return parse_world(_read_merged(path, ()), path)


def parse_world(data: Any, source: str | Path | None = None) -> World:
    """Validate a world given as plain data (what the YAML file holds, `extends` resolved) and
    compile it. `source` names the file in error messages."""
    where = Path(source) if source is not None else None
    try:
        spec = WorldSpec.model_validate(data)
    except ValidationError as err:
        first = leading_problem(err.errors())
        more = f" (and {err.error_count() - 1} more problems)" if err.error_count() > 1 else ""
        raise WorldError(f"{_field(first['loc'])}: {first['msg']}{more}", where) from None
    return _compile(spec, where)


def _read_merged(path: Path, chain: tuple[Path, ...]) -> dict:
    """The YAML mapping of `path`, with the world it `extends` merged under it."""
    if path.is_dir():
        raise WorldError("a folder, not a world file (a world is one YAML file)", path)
    if not path.is_file():
        raise WorldError("no such world file", path)
    resolved = path.resolve()
    if resolved in chain:
        raise WorldError("extends: the files extend each other in a cycle", path)
    try:
        data = load_yaml(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise WorldError("not a text file (a world is a UTF-8 YAML file)", path) from None
    except yaml.YAMLError as err:
        problem, line = yaml_problem(err)
        raise WorldError(problem, path, line) from None
    if not isinstance(data, dict):
        raise WorldError("a world file must hold a mapping of fields", path)
    base_name = data.pop("extends", None)
    if base_name is None:
        return data
    if not isinstance(base_name, str):
        raise WorldError("extends: must be the name of another world file", path)
    file_name = base_name if base_name.endswith(".yaml") else f"{base_name}.yaml"
    base_path = path.parent / file_name
    if not base_path.is_file():
        # A user's variant of a bundled world (`extends: office`) takes the bundled file.
        base_path = worlds_folder() / file_name
        if "/" in base_name or "\\" in base_name or not base_path.is_file():
            raise WorldError(f"extends: no world file {file_name!r} beside this one, nor a bundled world of that "
                             f"name ({', '.join(world_names())})", path)
    merged = _read_merged(base_path, chain + (resolved,))
    merged.update(data)
    return merged


def _field(loc: Sequence[Any]) -> str:
    """A pydantic location as a field path: ("walls", 2, "doors", 0, "at") → walls[2].doors[0].at."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _compile(spec: WorldSpec, source: Path | None) -> World:
    materials = dict(MATERIALS)
    for name, mat in spec.materials.items():
        materials[name] = Material.from_spec(name, mat)

    def need(name: str | None, field: str) -> None:
        if name is not None and name not in materials:
            raise WorldError(f"{field}: unknown material {name!r}; known: {', '.join(sorted(materials))}", source)

    need(spec.floor_material, "floor_material")
    need(spec.ceiling_material, "ceiling_material")
    quads: list[list[float]] = []
    quad_materials: list[str] = []
    roles: list[str] = []
    for i, wall in enumerate(spec.walls):
        field = f"walls[{i}]"
        need(wall.material, f"{field}.material")
        top = spec.ceiling_height if wall.height is None else wall.height
        if top > spec.ceiling_height + 1e-9:
            raise WorldError(f"{field}.height: {top} m is above the ceiling ({spec.ceiling_height} m)", source)
        for part, material, role in _wall_pieces(wall, top, field, source, need):
            quads.append(part)
            quad_materials.append(material)
            roles.append(role)
    boxes: list[list[float]] = []
    for i, box in enumerate(spec.boxes):
        field = f"boxes[{i}]"
        need(box.material, f"{field}.material")
        if not box.bottom < box.height <= spec.ceiling_height + 1e-9:
            raise WorldError(
                f"{field}.height: must lie above bottom ({box.bottom} m) and not above the "
                f"ceiling ({spec.ceiling_height} m), got {box.height}", source,
            )
        boxes.append([*box.centre, *box.size, math.radians(box.yaw_deg), box.bottom, box.height])
    if not quads and not boxes:
        raise WorldError("walls: a world needs at least one wall or box", source)
    landmarks = []
    for i, mark in enumerate(spec.landmarks):
        if not mark.height < spec.ceiling_height:
            raise WorldError(f"landmarks[{i}].height: must be below the ceiling", source)
        landmarks.append(Landmark(mark.name, np.array(mark.position), math.radians(mark.direction_deg),
                                  mark.distance, mark.height))
    names = [m.name for m in landmarks]
    if len(set(names)) != len(names):
        raise WorldError("landmarks: names must be unique", source)
    path = spec.path
    waypoints = np.array(path.waypoints, dtype=np.float64) if path else np.zeros((0, 2))
    world = World(
        name=spec.name,
        description=spec.description,
        source=source,
        ceiling_height=spec.ceiling_height,
        floor_material=spec.floor_material,
        ceiling_material=spec.ceiling_material,
        ambient=spec.ambient,
        materials=materials,
        quads=np.array(quads, dtype=np.float64).reshape(-1, 6),
        quad_materials=tuple(quad_materials),
        quad_roles=tuple(roles),
        boxes=np.array(boxes, dtype=np.float64).reshape(-1, 7),
        box_materials=tuple(b.material for b in spec.boxes),
        landmarks=tuple(landmarks),
        waypoints=waypoints,
        path_closed=path.closed if path else True,
        laps=path.laps if path else 1,
    )
    _check_waypoints(world, source)
    _check_landmarks(world, source)
    return world


# A landmark's declared distance is Table I's truth: it must be the walls' (the bundled worlds'
# agree to 1e-4 m; Table I's errors are centimetres).
LANDMARK_TOLERANCE_M = 0.01


def _check_landmarks(world: World, source: Path | None) -> None:
    """WorldError naming the first landmark outside the world, or whose declared distance is not
    the distance between the walls along its line at its height (Table I would compare the map
    with a number the world does not hold; it showed n/a or a wrong offset)."""
    xmin, xmax, ymin, ymax = world.bounds
    for k, mark in enumerate(world.landmarks):
        x, y = (float(v) for v in mark.position)
        if not (xmin <= x <= xmax and ymin <= y <= ymax):
            raise WorldError(f"landmarks[{k}].position: ({x:g}, {y:g}) lies outside the world, whose walls and boxes "
                             f"span x {xmin:g} .. {xmax:g} m, y {ymin:g} .. {ymax:g} m", source)
        ways = world.horizontal_distance(mark.position, np.array([mark.direction, mark.direction + math.pi]),
                                         mark.height)
        walls = float(np.sum(ways))
        if not math.isfinite(walls):
            raise WorldError(f"landmarks[{k}]: no wall along its line at {mark.height:g} m on one side or both", source)
        if abs(walls - mark.distance) > LANDMARK_TOLERANCE_M:
            raise WorldError(f"landmarks[{k}].distance: {mark.distance:g} m, but the walls along its line are "
                             f"{walls:.3f} m apart at {mark.height:g} m ({ways[0]:.3f} + {ways[1]:.3f} m)", source)


def _check_waypoints(world: World, source: Path | None) -> None:
    """WorldError naming the first waypoint outside everything the world holds, or inside a box
    the robot cannot pass. The drive's clearance check (sim.sequence.robot_path) misses both: a
    loop beyond the walls keeps clear of them, and a corner's arc may cut past a small box."""
    xmin, xmax, ymin, ymax = world.bounds
    low = [j for j in range(len(world.boxes)) if world.boxes[j, 5] < ROBOT_HEIGHT]
    for k, (x, y) in enumerate(world.waypoints):
        if not (xmin <= x <= xmax and ymin <= y <= ymax):
            raise WorldError(
                f"path.waypoints[{k}]: ({x:g}, {y:g}) lies outside the world, whose walls and boxes span "
                f"x {xmin:g} .. {xmax:g} m, y {ymin:g} .. {ymax:g} m", source,
            )
        for j in low:
            if _inside_boxes(np.array([[x, y]]), world.boxes[j : j + 1])[0]:
                raise WorldError(
                    f"path.waypoints[{k}]: ({x:g}, {y:g}) lies inside boxes[{j}], which reaches below "
                    f"{ROBOT_HEIGHT:g} m: the robot cannot pass it", source,
                )


def _wall_pieces(
    wall: WallSpec, top: float, field: str, source: Path | None, need: Callable[[str | None, str], None]
) -> list[tuple[list[float], str, str]]:
    """The quads of one polyline wall: solid runs between doors, the piece above each door, and
    each door's leaf. Each item is ([ax, ay, bx, by, bottom, top], material, role)."""
    pts = np.array(wall.points, dtype=np.float64)
    if wall.closed:
        if len(pts) < 3:
            raise WorldError(f"{field}.points: a closed wall needs at least 3 points", source)
        pts = np.vstack([pts, pts[:1]])
    edges = list(zip(pts[:-1], pts[1:]))
    for k, (a, b) in enumerate(edges):
        if np.linalg.norm(b - a) <= 1e-9:
            raise WorldError(f"{field}.points: edge {k} has zero length", source)
    by_edge: dict[int, list[tuple[int, DoorSpec]]] = {}
    for j, door in enumerate(wall.doors):
        dfield = f"{field}.doors[{j}]"
        if door.segment >= len(edges):
            raise WorldError(f"{dfield}.segment: the wall has only {len(edges)} edges", source)
        need(door.leaf, f"{dfield}.leaf")
        if door.height > top + 1e-9:
            raise WorldError(f"{dfield}.height: {door.height} m is above the wall ({top} m)", source)
        by_edge.setdefault(door.segment, []).append((j, door))
    out = []
    for k, (a, b) in enumerate(edges):
        length = float(np.linalg.norm(b - a))
        u = (b - a) / length
        cursor = 0.0
        for j, door in sorted(by_edge.get(k, []), key=lambda item: item[1].at):
            dfield = f"{field}.doors[{j}]"
            start, end = door.at - door.width / 2, door.at + door.width / 2
            if start < cursor - 1e-9:
                what = "starts before its edge" if cursor == 0.0 else "overlaps the previous door"
                raise WorldError(f"{dfield}.at: the door {what}", source)
            if end > length + 1e-9:
                raise WorldError(f"{dfield}.at: the door runs past the end of edge {k} ({length:.2f} m)", source)
            p0, p1 = a + start * u, a + end * u
            if start > cursor + 1e-9:
                out.append(([*(a + cursor * u), *p0, 0.0, top], wall.material, "wall"))
            if door.height < top - 1e-9:
                out.append(([*p0, *p1, door.height, top], wall.material, "lintel"))
            if door.leaf is not None:
                swing = math.radians(door.open_deg)
                c, s = math.cos(swing), math.sin(swing)
                tip = p0 + door.width * np.array([c * u[0] - s * u[1], s * u[0] + c * u[1]])
                out.append(([*p0, *tip, 0.0, door.height], door.leaf, "leaf"))
            cursor = end
        if cursor < length - 1e-9:
            out.append(([*(a + cursor * u), *b, 0.0, top], wall.material, "wall"))
    return out
