"""Fault injection: `omnitof slam` run as a process and stopped at chosen moments (SIGINT,
SIGTERM, SIGKILL, a full disk). After each, the --out folder is the complete old result, the
complete new one, or absent, never a mix; standard error holds one line and no traceback.

The moments are chosen without timing: the run is started with OMNITOF_PAUSE_AT=<stage>
(omnitof.interrupts.pause_point), says "paused at <stage>" and waits there for the signal.
Stages: start (the results folder just opened, nothing read), slam (half of the scans
filtered), write (half of the files written), swap (between the two renames that put the new
folder in place)."""

from __future__ import annotations

import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from omnitof.cli import main
from omnitof.io.carmen import write_carmen

PYTHON_PATH = str(Path(__file__).resolve().parents[1] / "python")
HANG_GUARD_S = 300  # only so that a broken run cannot hang the suite; no test depends on it


@pytest.fixture(scope="module")
def logs(tmp_path_factory, corridor_loop):
    """Two different logs (A gives the old result, B the new one), and the old result."""
    folder = tmp_path_factory.mktemp("faults")
    a, b = folder / "a.log", folder / "b.log"
    write_carmen(a, corridor_loop.slice(0, 120))
    write_carmen(b, corridor_loop.slice(120, 240))
    old = folder / "old"
    assert main(slam_args(a, old)) == 0
    return a, b, old


def slam_args(log: Path, out: Path) -> list[str]:
    return ["slam", str(log), "--out", str(out), "--preset", "sim2d", "--particles", "3", "--quiet",
            "--scan-delay", "0"]


def snapshot(folder: Path) -> dict[str, bytes] | None:
    """Every file of a folder and its bytes; None if the folder is absent."""
    if not folder.exists():
        return None
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def start(log: Path, out: Path, pause: str | None = None, preexec=None) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": PYTHON_PATH}
    env.pop("OMNITOF_PAUSE_AT", None)
    if pause is not None:
        env["OMNITOF_PAUSE_AT"] = pause
    return subprocess.Popen([sys.executable, "-m", "omnitof.cli", *slam_args(log, out)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=preexec)


def wait_paused(run: subprocess.Popen, stage: str) -> None:
    line = run.stderr.readline()
    if line != f"omnitof: paused at {stage} (OMNITOF_PAUSE_AT)\n":
        out, err = run.communicate(timeout=HANG_GUARD_S)
        pytest.fail(f"the run did not pause at {stage}: {line}{err}")


def finish(run: subprocess.Popen) -> tuple[int, str]:
    _, err = run.communicate(timeout=HANG_GUARD_S)
    return run.returncode, err


def hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.parent.iterdir() if p.name.startswith("."))


@pytest.mark.parametrize("stage", ["start", "slam", "write"])
@pytest.mark.parametrize("signum, code, said", [
    (signal.SIGINT, 130, "omnitof: interrupted; nothing half-written was left\n"),
    (signal.SIGTERM, 143, "omnitof: terminated (SIGTERM); nothing half-written was left\n"),
])
def test_a_signal_leaves_the_old_result_whole(tmp_path, logs, stage, signum, code, said):
    a, b, old = logs
    out = tmp_path / "run"
    shutil.copytree(old, out)
    before = snapshot(out)
    run = start(b, out, pause=stage)
    wait_paused(run, stage)
    run.send_signal(signum)
    returncode, err = finish(run)
    assert (returncode, err) == (code, said)
    assert snapshot(out) == before
    assert hidden(out) == []


def test_a_signal_to_a_first_run_leaves_no_folder(tmp_path, logs):
    a, b, old = logs
    out = tmp_path / "new" / "run"  # its parent is made for it, and removed again
    run = start(b, out, pause="slam")
    wait_paused(run, "slam")
    run.send_signal(signal.SIGTERM)
    assert finish(run)[0] == 143
    assert list(tmp_path.iterdir()) == []


def test_a_run_killed_between_its_renames_is_repaired_by_the_next(tmp_path, logs):
    # SIGKILL (or a power cut) at the worst moment: the old folder moved aside, the new one not
    # yet in place. Both are complete under hidden names; --out is absent. The next run into
    # the same folder puts the old one back before it starts, here a run that fails.
    a, b, old = logs
    out = tmp_path / "run"
    shutil.copytree(old, out)
    before = snapshot(out)
    run = start(b, out, pause="swap")
    wait_paused(run, "swap")
    run.kill()
    finish(run)
    assert not out.exists()
    aside = [tmp_path / name for name in hidden(out)]
    assert sorted(p.suffix for p in aside) == [".old", ".partial"]
    assert snapshot(next(p for p in aside if p.suffix == ".old")) == before
    new = snapshot(next(p for p in aside if p.suffix == ".partial"))
    assert new is not None and b"b.log" in new["summary.yaml"]  # complete, just not in place
    assert main(slam_args(tmp_path / "missing.log", out)) == 2
    assert snapshot(out) == before and hidden(out) == []


def test_a_complete_run_replaces_the_old_result(tmp_path, logs):
    a, b, old = logs
    out = tmp_path / "run"
    shutil.copytree(old, out)
    returncode, err = finish(start(b, out))
    assert (returncode, err) == (0, "")
    after = snapshot(out)
    assert b"b.log" in after["summary.yaml"] and after != snapshot(old)
    assert hidden(out) == []


def _limit_file_size() -> None:
    # A file may grow to 20 kB: the PGM of the map is larger, so writing the results fails
    # with EFBIG ("File too large"), deterministically, like a disk that is full.
    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))


def test_a_full_disk_leaves_the_old_result_whole(tmp_path, logs):
    # A stand-in for a full disk that needs no privileges: RLIMIT_FSIZE in the child (Python
    # ignores SIGXFSZ, so the write fails with an OSError instead of killing the process).
    a, b, old = logs
    out = tmp_path / "run"
    shutil.copytree(old, out)
    before = snapshot(out)
    returncode, err = finish(start(b, out, preexec=_limit_file_size))
    assert returncode == 2
    assert err.startswith(f"omnitof: error: {out}: cannot write the results: File too large; the folder was left")
    assert err.count("\n") == 1
    assert snapshot(out) == before and hidden(out) == []


def test_a_full_tmpfs_leaves_nothing(tmp_path, logs):
    # A real full disk: a 64 kB tmpfs, where the machine lets the test mount one.
    a, b, old = logs
    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root; test_a_full_disk_leaves_the_old_result_whole covers a full disk")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        out = disk / "run"
        returncode, err = finish(start(b, out))
        assert returncode == 2
        assert err.startswith(f"omnitof: error: {out}: cannot write the results: No space left on device; "
                              "nothing was written")
        assert list(disk.iterdir()) == []
    finally:
        subprocess.run(["umount", str(disk)], check=True)
