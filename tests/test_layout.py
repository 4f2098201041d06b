"""The package's layout is the data-flow picture (docs/layout.md): every top-level folder of
python/omnitof is a stage, and no stage imports a later one. Module names that scripts of
omnitof 0.1 imported still import, as the same modules at their new places."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "python" / "omnitof"

# Stages in data-flow order; a module may import its own stage and earlier ones only. "runs"
# are the whole runs (a results folder, `omnitof slam`'s run, the demo), which bench/ repeats
# over many inputs and settings, and the commands sit on top of everything.
STAGES = ["foundation", "sensor", "io", "sim", "calibration", "scan", "slam", "map3d", "eval", "viz", "runs",
          "bench", "commands"]
FOUNDATION = {"errors", "types", "geometry", "interrupts", "settings_model", "_core", "_moved", "__init__", "__version__"}
RUNS = {"demo", "results", "slam_run", "calibration_report"}
COMMANDS = {"cli", "cli_calibrate", "__main__"}
TOP_LEVEL = FOUNDATION | RUNS | COMMANDS  # the stages that are modules, not folders
DATA_FOLDERS = {"worlds", "presets", "__pycache__"}


def stage_of(module: str) -> str:
    """Stage of a dotted module name inside omnitof ("omnitof.sim.render" → "sim")."""
    parts = module.split(".")
    assert parts[0] == "omnitof", module
    head = parts[1] if len(parts) > 1 else "__init__"
    if head in FOUNDATION:
        return "foundation"
    if head in RUNS:
        return "runs"
    if head in COMMANDS:
        return "commands"
    assert head in STAGES, f"omnitof.{head} is in no stage of the data flow"
    return head


def imported_modules(path: Path, module: str) -> list[tuple[int, str]]:
    """(line, module) of every omnitof module `path` imports, at any depth of the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "omnitof"]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                name = f"{base}.{node.module}" if node.module else base
            else:
                name = node.module or ""
            if name.split(".")[0] != "omnitof":
                continue
            # `from omnitof import x` imports the submodule x.
            targets = [f"{name}.{a.name}" for a in node.names] if name == "omnitof" else [name]
            found += [(node.lineno, t) for t in targets]
    return found


def modules() -> list[tuple[Path, str]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__" and len(parts) > 1 and parts[:-1] != ["omnitof"]:
            parts = parts[:-1]
        out.append((path, ".".join(parts)))
    return out


def test_every_top_level_folder_is_a_stage():
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir()}
    assert folders - DATA_FOLDERS == set(STAGES) - {"foundation", "runs", "commands"}
    files = {p.stem for p in PACKAGE.glob("*.py")}
    assert files <= TOP_LEVEL, f"top-level modules outside the picture: {files - TOP_LEVEL}"


def test_no_stage_imports_a_later_one():
    wrong = []
    for path, module in modules():
        own = STAGES.index(stage_of(module))
        for line, target in imported_modules(path, module):
            if STAGES.index(stage_of(target)) > own:
                wrong.append(f"{path.relative_to(PACKAGE)}:{line} ({stage_of(module)}) imports {target}")
    assert not wrong, "\n".join(wrong)


def test_the_layout_check_sees_a_backward_import(tmp_path):
    """The check above can fail: a sensor module importing slam is caught."""
    fake = tmp_path / "omnitof" / "sensor" / "bad.py"
    fake.parent.mkdir(parents=True)
    fake.write_text("def f():\n    from omnitof.slam import run_slam\n")
    (line, target), = imported_modules(fake, "omnitof.sensor.bad")
    assert line == 2 and STAGES.index(stage_of(target)) > STAGES.index(stage_of("omnitof.sensor.bad"))


@pytest.mark.parametrize("old", ["omnitof.tof", "omnitof.camera", "omnitof.mirrors", "omnitof.design",
                                 "omnitof.config", "omnitof.timing", "omnitof.tofscans"])
def test_old_module_names_import_the_moved_modules(old):
    from omnitof._moved import MOVED

    assert importlib.import_module(old) is importlib.import_module(MOVED[old])


def test_readme_api_names_still_import():
    from omnitof.calibration import load_calibration  # noqa: F401
    from omnitof.config import load_config
    from omnitof.io.carmen import read_carmen  # noqa: F401
    from omnitof.results import write_results  # noqa: F401
    from omnitof.scan import ScanExtractor
    from omnitof.sim.render import Renderer  # noqa: F401
    from omnitof.sim.sequence import make_sequence, render_sequence  # noqa: F401
    from omnitof.slam import run_slam
    from omnitof.slam.config import load_config as new_load_config
    from omnitof.slam.driver import run_slam as new_run_slam
    from omnitof.tofscans import tof_scans

    assert load_config is new_load_config and run_slam is new_run_slam
    assert ScanExtractor.__module__ == "omnitof.scan.extract"
    assert tof_scans.__module__ == "omnitof.scan.tof_input"
