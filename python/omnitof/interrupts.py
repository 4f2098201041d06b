"""Signals, and the moments at which a run may be stopped.

The command treats SIGTERM (`kill`, a batch system's time limit) like Ctrl-C: inside
`signals_as_exceptions` both raise an exception wherever the program is (KeyboardInterrupt, and
its subclass `Terminated` for SIGTERM), so every `with` block unwinds and removes what it had
begun, and the command prints one line. `deferred_signals` holds both off for the few steps
that must happen together (the renames that put a results folder in place).

`pause_point` is for the fault-injection tests (tests/test_faults.py): it lets a test stop a
run at a named stage, without guessing at timings.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

# The signals a user or a batch system sends to stop a run.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

PAUSE_VARIABLE = "OMNITOF_PAUSE_AT"


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled like Ctrl-C (a KeyboardInterrupt), told apart for the exit status."""


def _raise_for(signum: int, frame: object) -> None:
    if signum == signal.SIGTERM:
        raise Terminated()
    raise KeyboardInterrupt()


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def signals_as_exceptions() -> Iterator[None]:
    """Inside the block SIGINT raises KeyboardInterrupt and SIGTERM raises Terminated; the
    handlers before it come back after it. Python runs signal handlers in the main thread only,
    so elsewhere this does nothing."""
    if not _in_main_thread():
        yield
        return
    previous = {s: signal.signal(s, _raise_for) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


@contextmanager
def deferred_signals() -> Iterator[None]:
    """SIGINT and SIGTERM that arrive inside the block are held and delivered, in the order
    they came, to the handlers of before as soon as it ends: the block runs to its end.

    (Blocking them with pthread_sigmask would not do: the kernel hands a signal to any thread
    that does not block it, the Rust core's workers included, and Python then runs its handler
    in the main thread all the same.)"""
    if not _in_main_thread():
        yield
        return
    held: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: held.append(signum)) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in held:
            signal.raise_signal(s)


def pause_point(name: str) -> None:
    """If the environment variable OMNITOF_PAUSE_AT names this point, say so on standard error
    (`omnitof: paused at NAME`) and wait until a signal ends the wait (or the process).

    For the fault-injection tests only: they start a run with the variable set, wait for the
    line and then send SIGINT, SIGTERM or SIGKILL, so that the signal meets the run at a known
    stage. Without the variable this costs one lookup."""
    if os.environ.get(PAUSE_VARIABLE) != name:
        return
    print(f"omnitof: paused at {name} ({PAUSE_VARIABLE})", file=sys.stderr, flush=True)
    while True:
        # Short sleeps: a signal the kernel hands to another thread (the core's workers) does not
        # interrupt this one's sleep, and Python runs the handler (which raises) only when the
        # main thread next looks; a long sleep could then outlast the test's guard.
        time.sleep(0.05)
