"""All-or-nothing writes (omnitof.io.atomic): a folder replaced as one unit, leftovers of
killed processes swept, and what is still being written left alone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from omnitof.errors import OutputError
from omnitof.interrupts import deferred_signals, signals_as_exceptions, Terminated
from omnitof.io.atomic import atomic_folder, atomic_write, sweep_leftovers, temporary_folder

DEAD_PID = 2**30 + 7  # beyond any pid_max: no such process


def folder_with(path: Path, files: dict[str, str]) -> Path:
    path.mkdir(parents=True)
    for name, text in files.items():
        (path / name).write_text(text)
    return path


def contents(path: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(path.iterdir())}


def test_a_folder_is_replaced_as_a_whole(tmp_path):
    out = folder_with(tmp_path / "run", {"a.txt": "old a", "stale.txt": "old only"})
    with atomic_folder(out) as folder:
        assert folder.parent == tmp_path and folder.name.startswith(".run.") and folder.name.endswith(".partial")
        assert contents(out) == {"a.txt": "old a", "stale.txt": "old only"}  # untouched meanwhile
        (folder / "a.txt").write_text("new a")
    assert contents(out) == {"a.txt": "new a"}  # the stale file went with the old folder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt, Terminated])
def test_a_failed_block_leaves_the_old_folder_and_nothing_else(tmp_path, error):
    out = folder_with(tmp_path / "run", {"a.txt": "old a"})
    with pytest.raises(error), atomic_folder(out) as folder:
        (folder / "a.txt").write_text("half")
        raise error()
    assert contents(out) == {"a.txt": "old a"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_missing_parents_are_made_and_removed_again_on_failure(tmp_path):
    out = tmp_path / "x" / "y" / "run"
    with pytest.raises(RuntimeError), atomic_folder(out):
        assert (tmp_path / "x" / "y").is_dir()
        raise RuntimeError()
    assert list(tmp_path.iterdir()) == []
    with atomic_folder(out) as folder:
        (folder / "f").write_text("1")
    assert contents(out) == {"f": "1"}


@pytest.mark.parametrize("where", ["out", "parent"])
def test_a_file_where_a_folder_should_be_is_refused_before_the_block(tmp_path, where):
    (tmp_path / "f").write_text("mine")
    out = tmp_path / "f" if where == "out" else tmp_path / "f" / "run"
    with pytest.raises(OutputError, match="is a file, not a folder"):
        with atomic_folder(out):
            pytest.fail("the block must not run")
    assert (tmp_path / "f").read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_an_unwritable_place_is_refused_before_the_block(tmp_path):
    # /proc refuses new folders for every user, root too (chmod does not stop root).
    with pytest.raises(OutputError, match="cannot create the results folder"):
        with atomic_folder("/proc/omnitof-results"):
            pytest.fail("the block must not run")


def test_a_file_in_a_missing_folder_names_the_file_not_its_temporary(tmp_path):
    target = tmp_path / "missing" / "scans.clf"
    for opener in (lambda: atomic_write(target), lambda: temporary_folder(target)):
        with pytest.raises(OutputError, match="its folder does not exist") as caught:
            with opener():
                pass
        assert str(caught.value).startswith(str(target)) and ".tmp" not in str(caught.value)
    assert not (tmp_path / "missing").exists()


def test_may_replace_can_refuse_an_existing_folder(tmp_path):
    out = folder_with(tmp_path / "home", {"thesis.tex": "precious"})

    def only_results(folder: Path) -> None:
        raise OutputError(f"{folder}: not a results folder")

    with pytest.raises(OutputError, match="not a results folder"), atomic_folder(out, may_replace=only_results):
        pytest.fail("the block must not run")
    assert contents(out) == {"thesis.tex": "precious"}


def test_leftovers_of_dead_processes_are_swept_and_live_ones_kept(tmp_path):
    out = folder_with(tmp_path / "run", {"a.txt": "a"})
    dead = [f".run.{DEAD_PID}-0123456789ab.partial", f".run.{DEAD_PID}-0123456789ac.tmp",
            ".run.0123456789ad.tmp"]  # the last: an omnitof 0.1 temporary (no pid)
    live = f".run.{os.getppid()}-0123456789ae.partial"  # a live process's
    other = f".other.{DEAD_PID}-0123456789af.partial"  # another target's
    for name in [*dead, live, other]:
        (tmp_path / name).mkdir()
    assert sorted(sweep_leftovers(out)) == sorted(dead)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live, other, "run"])


def test_a_run_killed_between_its_two_renames_is_repaired_by_the_next(tmp_path):
    # The old result moved aside, the new one not yet in place, the process gone: the next
    # write to the same place puts the old result back first.
    folder_with(tmp_path / f".run.{DEAD_PID}-0123456789ab.old", {"a.txt": "old"})
    folder_with(tmp_path / f".run.{DEAD_PID}-0123456789ac.partial", {"a.txt": "new, unconfirmed"})
    assert len(sweep_leftovers(tmp_path / "run")) == 2
    assert contents(tmp_path / "run") == {"a.txt": "old"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_temporaries_in_use_by_this_process_are_not_swept(tmp_path):
    with atomic_write(tmp_path / "f.txt") as handle, temporary_folder(tmp_path / "bag") as staging:
        handle.write("x")
        sweep_leftovers(tmp_path / "f.txt")
        sweep_leftovers(tmp_path / "bag")
        assert staging.is_dir() and len(list(tmp_path.iterdir())) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.txt"]


def test_signals_are_held_while_deferred_and_delivered_after():
    with signals_as_exceptions():
        with pytest.raises(Terminated):
            with deferred_signals():
                os.kill(os.getpid(), signal.SIGTERM)
                done = True  # the block runs to its end first
        assert done
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            signal.sigtimedwait([], 0)  # a moment for the handler to run


def test_sigterm_ends_a_process_like_ctrl_c_inside_signals_as_exceptions(tmp_path):
    code = (
        "import os, signal, sys\n"
        "from omnitof.interrupts import Terminated, signals_as_exceptions\n"
        "with signals_as_exceptions():\n"
        "    try:\n"
        "        os.kill(os.getpid(), signal.SIGTERM)\n"
        "        signal.sigtimedwait([], 0)\n"
        "    except Terminated:\n"
        "        sys.exit(7)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "python")})
    assert run.returncode == 7


def test_the_current_folder_is_not_replaced(tmp_path, monkeypatch):
    monkeypatch.chdir(folder_with(tmp_path / "run", {}))
    for out in (".", tmp_path / "run", tmp_path):
        with pytest.raises(OutputError, match="holds the current folder"), atomic_folder(out):
            pytest.fail("the block must not run")
