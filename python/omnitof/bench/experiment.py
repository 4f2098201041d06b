"""The experiment file: inputs × presets × a grid of configuration settings × seeds, and the
metrics to collect. Validated like the SLAM configuration: any mistake is one line naming the
file and the field (`bench.yaml: inputs[1].relations: no such file`).

    name: intel-particles                 # optional; default: the file's name
    inputs:
      - name: intel
        log: $OMNITOF_DATA/intel.clf.bz2   # relative to this file; $VARIABLES expanded
        relations: $OMNITOF_DATA/intel.relations
        max_scans: 2000
      - name: room
        world: room                        # simulated: a bundled world or a world YAML
        sensor: laser
    presets: [laser180-scanmatch]          # default: what `omnitof slam` picks for each input
    set: {backend.enabled: false}          # settings of every run
    grid: {filter.particles: [10, 30, 100]}
    seeds: [0, 1, 2]
    metrics: [relations, trajectory]       # default: every metric the inputs allow

`plan_runs` turns an experiment into its runs, one per input × preset × grid point × seed, and
builds each run's configuration there and then, so that a bad value is refused before anything
runs. Every field is documented in docs/guide/bench.md.
"""

from __future__ import annotations

import hashlib
import itertools
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import AfterValidator, ConfigDict, Field, ValidationError, field_validator, model_validator

from omnitof.settings_model import SettingsModel
from omnitof.errors import ConfigError, InputError, OmnitofError, dump_yaml, leading_problem, load_yaml, yaml_problem

METRICS = ("relations", "trajectory", "floorplan", "table1")
# Runs of one experiment: planning takes about 1 ms a run, a run seconds to hours.
# A run folder's name (INPUT__PRESET__FIELD=VALUE...__seedS): file systems allow 255 bytes, and
# the folder is built under a hidden name that is about 30 bytes longer (omnitof.io.atomic).
MAX_RUN_NAME = 200
MAX_RUNS = 10_000
# A run's folder name is built from these; anything else in a value becomes "_".
_SAFE = re.compile(r"[^A-Za-z0-9_.+-]")
_NAME = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"


class ExperimentError(ConfigError):
    """A mistake in an experiment file; the message names the file and the field."""


class _Strict(SettingsModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LaserSettings(_Strict):
    """The simulated planar laser of a world input (`sensor: laser`), at the ToF slice's height."""

    beams: int = Field(360, ge=1, le=10_000)
    fov_deg: float = Field(360.0, gt=0, le=360)
    max_range: float = Field(7.5, gt=0, le=100)
    noise: float = Field(0.01, ge=0, le=1)


class InputSpec(_Strict):
    """One input: a recording (`log`) or a world to simulate (`world`), with its reference."""

    name: str = Field(pattern=_NAME)
    log: str | None = None
    world: str | None = None
    relations: str | None = None
    max_scans: int | None = Field(None, ge=1)
    scan_delay: float | Literal["auto"] | None = None
    skip_bad_lines: bool = False
    calibration: str | None = None
    height: float | None = Field(None, gt=0)
    band: float | None = Field(None, gt=0)
    transfer: Literal["auto", "ship", "shared"] = "auto"
    sensor: Literal["laser", "tof"] = "laser"
    sim_seed: int = Field(0, ge=0)
    calibrate: bool = True
    speed: float = Field(0.4, gt=0, le=5)
    laser: LaserSettings = LaserSettings()

    @field_validator("scan_delay", mode="before")
    @classmethod
    def _delay(cls, value: Any) -> Any:
        if value is None or value == "auto":
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not abs(value) <= 10.0:
            raise ValueError(f"expected seconds within ±10 or 'auto', got {value!r}")
        return float(value)

    @model_validator(mode="after")
    def _one_source(self) -> "InputSpec":
        if (self.log is None) == (self.world is None):
            raise ValueError("give either log (a recording) or world (a world to simulate)")
        given = self.model_fields_set
        if self.world is not None:
            wrong = given & {"calibration", "height", "band", "skip_bad_lines", "transfer"}
            if wrong:
                raise ValueError(f"{', '.join(sorted(wrong))}: only for a log, not a world")
            if self.sensor == "tof" and "laser" in given:
                raise ValueError("laser: only for sensor: laser")
        else:
            wrong = given & {"sensor", "sim_seed", "calibrate", "speed", "laser"}
            if wrong:
                raise ValueError(f"{', '.join(sorted(wrong))}: only for a world, not a log")
        return self


def _known_preset(name: str) -> str:
    from omnitof.slam.config import preset_names

    if name not in preset_names():
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(preset_names())}")
    return name


class ExperimentSpec(_Strict):
    name: str | None = Field(None, pattern=_NAME)
    inputs: list[InputSpec] = Field(min_length=1)
    presets: list[Annotated[str, AfterValidator(_known_preset)]] | None = Field(None, min_length=1)
    set: dict[str, Any] = {}
    grid: dict[str, list[Any]] = {}
    seeds: list[int] = Field([0], min_length=1)
    metrics: list[Literal["relations", "trajectory", "floorplan", "table1"]] | None = None
    threads: int = Field(1, ge=1, le=1024)

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, seeds: list[int]) -> list[int]:
        if any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
            raise ValueError("expected distinct seeds >= 0")
        return seeds

    @field_validator("presets")
    @classmethod
    def _presets(cls, presets: list[str] | None) -> list[str] | None:
        if presets is not None and len(set(presets)) != len(presets):
            raise ValueError("a preset is given twice")
        return presets

    @field_validator("set")
    @classmethod
    def _set(cls, settings: dict[str, Any]) -> dict[str, Any]:
        for key in settings:
            _check_dotted(key)
        return settings

    @field_validator("grid")
    @classmethod
    def _grid(cls, grid: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for key, values in grid.items():
            _check_dotted(key)
            if not values:
                raise ValueError(f"{key}: expected at least one value")
            # Every setting is one value; a list or mapping here is a typo ([[10]]) and cannot
            # name a run's folder.
            nested = next((v for v in values if isinstance(v, (list, dict))), None)
            if nested is not None:
                raise ValueError(f"{key}: expected a list of single values (numbers, text, true/false), "
                                 f"got {nested!r} among them")
        return grid


def _check_dotted(key: str) -> None:
    if not re.fullmatch(r"[a-z_0-9]+(\.[a-z_0-9]+)+", str(key)):
        raise ValueError(f"{key!r}: expected SECTION.FIELD of the configuration, e.g. filter.particles")


@dataclass(frozen=True)
class Experiment:
    """A validated experiment file; input paths are absolute."""

    spec: ExperimentSpec
    source: Path
    name: str
    text: str  # the file as written, kept beside the results

    @property
    def inputs(self) -> list[InputSpec]:
        return self.spec.inputs


@dataclass(frozen=True)
class RunSpec:
    """One run: an input, a preset, a grid point, a seed, and the configuration they make.

    id: the run's folder name under runs/; index: its place in the experiment's order;
    settings: the experiment's `set` and the grid point (dotted SECTION.FIELD → value);
    config_digest: sha256 of the configuration's YAML, which a resumed experiment compares."""

    id: str
    index: int
    input: InputSpec
    preset: str
    point: dict[str, Any]
    seed: int
    settings: dict[str, Any]
    threads: int
    metrics: tuple[str, ...]
    config_digest: str = field(repr=False)

    def cell(self) -> dict[str, Any]:
        """What identifies the run in its folder (bench.yaml) and in the table."""
        return {"input": self.input.name, "preset": self.preset, "point": dict(self.point), "seed": self.seed,
                "index": self.index, "config_sha256": self.config_digest,
                "input_spec": self.input.model_dump(exclude_defaults=True, exclude={"name"})}

    @property
    def scan_delay(self) -> str | float | None:
        """The run's --scan-delay: the input's; for a simulated world 0 unless given (its
        odometry has no delay to estimate)."""
        if self.input.world is not None and self.input.scan_delay is None:
            return 0.0
        return self.input.scan_delay

    def command(self, log: str, out: str) -> list[str]:
        """The `omnitof slam` command that makes the same results folder."""
        argv = ["omnitof", "slam", log, "--out", out, "--preset", self.preset]
        for key, value in self.settings.items():
            argv += ["--set", f"{key}={_yaml_scalar(value)}"]
        argv += ["--seed", str(self.seed), "--threads", str(self.threads)]
        i = self.input
        if i.relations:
            argv += ["--relations", i.relations]
        if i.max_scans is not None:
            argv += ["--max-scans", str(i.max_scans)]
        if self.scan_delay is not None:
            argv += ["--scan-delay", str(self.scan_delay)]
        if i.skip_bad_lines:
            argv.append("--skip-bad-lines")
        for name in ("calibration", "height", "band"):
            if getattr(i, name) is not None:
                argv += [f"--{name}", str(getattr(i, name))]
        return argv + ["--quiet"]


def _yaml_scalar(value: Any) -> str:
    return dump_yaml(value, default_flow_style=True).strip().removesuffix("\n...").strip()


def _field(loc: tuple) -> str:
    """pydantic's error location as the file's field: ("inputs", 0, "log") → inputs[0].log."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in ("float", "int", "str", "bool", "list[any]") or str(part).startswith(("literal[", "function-")):
            continue  # the member of a union that failed, not a field of the file
        else:
            out += f".{part}" if out else str(part)
    return out or "(top level)"


def load_experiment(path: str | Path) -> Experiment:
    """Read and validate an experiment file; ExperimentError names the file and the field."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ExperimentError(f"{path}: cannot read the experiment: {err.strerror}") from None
    except UnicodeDecodeError:
        raise ExperimentError(f"{path}: not a text file (an experiment is YAML text)") from None
    try:
        data = load_yaml(text)
    except yaml.YAMLError as err:
        problem, line = yaml_problem(err)
        raise ExperimentError(f"{path}{'' if line is None else f':{line}'}: {problem}") from None
    if not isinstance(data, dict):
        raise ExperimentError(f"{path}: an experiment is a mapping (inputs, presets, grid, seeds, ...)")
    try:
        spec = ExperimentSpec.model_validate(data)
    except ValidationError as err:
        first = leading_problem(err.errors())
        message = first["msg"].removeprefix("Value error, ")
        if first["type"] == "extra_forbidden":
            message = "unknown field"
        more = f" (and {err.error_count() - 1} more problems)" if err.error_count() > 1 else ""
        raise ExperimentError(f"{path}: {_field(first['loc'])}: {message}{more}") from None
    spec = _resolved(spec, path)
    return Experiment(spec=spec, source=path, name=spec.name or path.name.split(".")[0], text=text)


def _resolved(spec: ExperimentSpec, source: Path) -> ExperimentSpec:
    """Input paths made absolute (relative to the experiment file, $VARIABLES expanded) and
    checked; input names checked unique."""
    names = [i.name for i in spec.inputs]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise ExperimentError(f"{source}: inputs[{i}].name: {name!r} is given twice")
    inputs = []
    for k, item in enumerate(spec.inputs):
        updates: dict[str, Any] = {}
        for key in ("log", "relations", "calibration"):
            value = getattr(item, key)
            if value is not None:
                updates[key] = str(_path(value, source, f"inputs[{k}].{key}"))
                # A log may be a folder (a ROS 2 bag); these two are read as one file each.
                if key != "log" and not Path(updates[key]).is_file():
                    raise ExperimentError(f"{source}: inputs[{k}].{key}: not a file: {updates[key]}")
                if key == "relations":
                    _check_relations(updates[key], source, f"inputs[{k}].relations")
        if item.world is not None:
            if item.world.endswith((".yaml", ".yml")):
                updates["world"] = str(_path(item.world, source, f"inputs[{k}].world"))
            _check_world(updates.get("world", item.world), item.speed, source, f"inputs[{k}].world")
        inputs.append(item.model_copy(update=updates))
    return spec.model_copy(update={"inputs": inputs})


def _check_relations(path: str, source: Path, name: str) -> None:
    """Read the relations once before any run (each run reads them again), as `omnitof slam
    --relations` does: a malformed file is one error here, not a failed folder per run."""
    from omnitof.eval.relations import read_relations

    try:
        read_relations(path)
    except InputError as err:
        raise ExperimentError(f"{source}: {name}: {err}") from None


def _path(value: str, source: Path, name: str) -> Path:
    expanded = os.path.expandvars(os.path.expanduser(value))
    unset = re.search(r"\$\{?(\w+)", expanded)
    if unset:
        raise ExperimentError(f"{source}: {name}: ${unset.group(1)} is not set")
    path = Path(expanded)
    if not path.is_absolute():
        path = source.resolve().parent / path
    if not path.exists():
        raise ExperimentError(f"{source}: {name}: no such file or folder: {path}")
    return path


def _check_world(world: str, speed: float, source: Path, name: str) -> None:
    """Load the world and plan the robot's drive through it, as the worker will: a path that
    turns back or grazes a wall is found here, before anything is written, not on a worker."""
    from omnitof.sim.sequence import MotionSettings, robot_path
    from omnitof.sim.worlds import load_world

    try:
        robot_path(load_world(world), MotionSettings(speed=speed))
    except OmnitofError as err:
        raise ExperimentError(f"{source}: {name}: {err}") from None


def default_preset_of(item: InputSpec) -> str:
    """The preset of an input when the experiment names none: `omnitof slam`'s for a log, and
    `tof-scanmatch` (tuned on the simulated robot's odometry) for a world."""
    if item.world is not None:
        return "tof-scanmatch"
    from omnitof.slam_run import default_preset

    return default_preset(item.log)


def metrics_of(exp: Experiment) -> tuple[str, ...]:
    """The metrics to collect: those asked for, or every metric some input allows."""
    worlds = [i for i in exp.inputs if i.world is not None]
    allowed = {
        "relations": any(i.relations for i in exp.inputs),
        # Worlds carry their ground truth; a bag may, a CARMEN log never does.
        "trajectory": bool(worlds) or any(i.log and not i.log.endswith((".clf", ".log", ".gz", ".bz2"))
                                           for i in exp.inputs),
        "floorplan": bool(worlds),
        "table1": bool(worlds),
    }
    if exp.spec.metrics is None:
        return tuple(m for m in METRICS if allowed[m])
    for m in exp.spec.metrics:
        if not allowed[m]:
            need = {"relations": "an input with relations", "trajectory": "an input with ground truth (a world or a bag)",
                    "floorplan": "a world input", "table1": "a world input"}[m]
            raise ExperimentError(f"{exp.source}: metrics: {m} needs {need}")
    return tuple(dict.fromkeys(exp.spec.metrics))


def plan_runs(exp: Experiment) -> list[RunSpec]:
    """Every run of the experiment, in order: inputs, presets, grid points (the last key
    varying fastest), seeds. Each run's configuration is built here, so that an invalid
    setting is refused, naming it, before anything runs."""
    spec = exp.spec
    _check_run_count(exp)
    metrics = metrics_of(exp)
    keys = list(spec.grid)
    points = [dict(zip(keys, values)) for values in itertools.product(*(spec.grid[k] for k in keys))]
    _check_folder_names(exp, keys)
    runs: list[RunSpec] = []
    digests: dict[tuple, str] = {}
    for item in spec.inputs:
        for preset in spec.presets or [default_preset_of(item)]:
            for point in points:
                settings = {**spec.set, **point}
                for seed in spec.seeds:
                    key = (preset, tuple(settings.items()), seed)
                    if key not in digests:
                        digests[key] = _config_digest(exp, preset, settings, seed, point)
                    run_id = "__".join([item.name, preset, *(f"{k}={_folder_value(v)}" for k, v in point.items()),
                                        f"seed{seed}"])
                    if len(run_id.encode()) > MAX_RUN_NAME:
                        raise ExperimentError(
                            f"{exp.source}: inputs[{spec.inputs.index(item)}].name: the run folder "
                            f"{run_id[:50]}... would be named by {len(run_id.encode())} characters, more than the "
                            f"{MAX_RUN_NAME} a folder name may have here: shorten the input's name or the grid's "
                            "fields and values")
                    runs.append(RunSpec(id=run_id, index=len(runs), input=item, preset=preset, point=point,
                                        seed=seed, settings=settings, threads=spec.threads, metrics=metrics,
                                        config_digest=digests[key]))
    return runs


def _check_run_count(exp: Experiment) -> None:
    """Refuse an experiment of more than MAX_RUNS runs before planning it: a grid of 10^6 points
    planned silently for many minutes, for runs that would take years."""
    spec = exp.spec
    factors = [(len(spec.inputs), "input", "inputs"), (len(spec.presets or [None]), "preset", "presets"),
               *((len(v), f"grid.{k}", f"grid.{k}") for k, v in spec.grid.items()),
               (len(spec.seeds), "seed", "seeds")]
    count = math.prod(n for n, _, _ in factors)
    if count > MAX_RUNS:
        product = " × ".join(f"{n} {one if n == 1 else many}" for n, one, many in factors)
        raise ExperimentError(f"{exp.source}: {count} runs ({product}); an experiment holds at most {MAX_RUNS}: "
                              "split it into several, or grid fewer values")


def _config_digest(exp: Experiment, preset: str, settings: dict[str, Any], seed: int, point: dict) -> str:
    from omnitof.slam_run import slam_config

    where = f"grid point {_point_text(point)}, preset {preset}" if point else f"preset {preset}"
    try:
        cfg = slam_config(preset=preset, settings=settings, seed=seed, threads=exp.spec.threads)
    except OmnitofError as err:
        message = str(err).split("invalid configuration: ", 1)[-1]
        raise ExperimentError(f"{exp.source}: {where}: {message}") from None
    return hashlib.sha256(cfg.to_yaml().encode()).hexdigest()


def _point_text(point: dict[str, Any]) -> str:
    return ", ".join(f"{k}={_yaml_scalar(v)}" for k, v in point.items())


def _folder_value(value: Any) -> str:
    return _SAFE.sub("_", _yaml_scalar(value))


def _check_folder_names(exp: Experiment, keys: list[str]) -> None:
    for key in keys:
        seen: dict[str, Any] = {}
        for value in exp.spec.grid[key]:
            name = _folder_value(value)
            if name in seen:
                raise ExperimentError(f"{exp.source}: grid.{key}: values {seen[name]!r} and {value!r} "
                                      f"are the same or name the same folder")
            seen[name] = value
