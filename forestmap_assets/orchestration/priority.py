"""Where-to-scan-next runs give way to the map's stages (issue 16): they run in the workers beside
the campaign-level stages of this process, and on a machine with as many cores as workers the
three processes would share two cores evenly, stretching the tree list by about a third. For
such a run the worker raises its nice value, on every thread (Linux keeps one per thread), and
puts it back afterwards where the system allows it (an unprivileged process may not lower it
again: the worker then stays polite, which only matters while something else wants the core)."""

from __future__ import annotations

import contextlib
import os

BACKGROUND_NICE = 10  # added to the worker's nice value while a background run lasts


def _threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def _set_all(values: dict[int, int]) -> None:
    for tid, value in values.items():
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, tid, value)


@contextlib.contextmanager
def background(on: bool = True):
    """Run the body at a lower priority (``on``); a no-op where nice values are not known."""
    if not on or not hasattr(os, "setpriority"):
        yield
        return
    before = {}
    for tid in _threads():
        with contextlib.suppress(OSError):
            before[tid] = os.getpriority(os.PRIO_PROCESS, tid)
    _set_all({tid: min(value + BACKGROUND_NICE, 19) for tid, value in before.items()})
    try:
        yield
    finally:
        _set_all(before)
