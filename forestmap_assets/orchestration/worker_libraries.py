"""What every worker process needs, imported once in the fork server that forks them
(:mod:`.forkserver`): the session (Dagster and the asset modules), Open3D (without its plotly
viewer) and SciPy's k-d trees (the per-scan stages), Dagster's SQLite storage (the worker's
instance), numba's CPU target (initialised once, about 0.4 s, instead of at each worker's first
compiled kernel) and the cached kernels but the parallel ones (about 0.4 s, once rather than in
every worker). Nothing here starts a thread, so the fork server may fork after it."""

from __future__ import annotations

import sys
import types

import scipy.spatial  # noqa: F401
from dagster._core.storage.event_log.sqlite.sqlite_event_log import (  # noqa: F401
    SqliteEventLogStorage,
)
from dagster._core.storage.runs.sqlite.sqlite_run_storage import SqliteRunStorage  # noqa: F401
from dagster._core.storage.sqlite_storage import DagsterSqliteStorage  # noqa: F401

import forestmap_assets.orchestration.session  # noqa: F401


def _open3d() -> None:
    """Open3D, without its plotly viewer: its package imports the viewer, and with it Dash and
    plotly (0.3-0.5 s of the fork server's start-up, on the way to the first scan). A stand-in
    module takes the viewer's place in the fork server, which no notebook shares; a worker
    draws nothing with Open3D."""
    name = "open3d.visualization.draw_plotly"
    if name not in sys.modules:
        stand_in = types.ModuleType(name, "Open3D's plotly viewer, not loaded in forestmap's workers")
        stand_in.get_plotly_fig = stand_in.draw_plotly = stand_in.draw_plotly_server = None
        sys.modules[name] = stand_in
    import open3d  # noqa: F401


_open3d()


def _numba_target() -> None:
    try:
        from numba.core.registry import cpu_target

        cpu_target.target_context.refresh()
    except Exception:  # an internal of numba: without it the first kernel pays instead
        pass


_numba_target()


def _serial_kernels() -> None:
    """The compiled kernels numba has cached, but the parallel ones (their loading starts
    numba's threads, which a fork server must not have): loaded once here rather than in every
    worker at its start (:mod:`.kernel_cache`)."""
    from forestmap_assets.orchestration.kernel_cache import load_cached_kernels

    load_cached_kernels(serial_only=True)


_serial_kernels()


def _freeze() -> None:
    """Move every object imported so far out of the collector's reach (``gc.freeze``, without a
    collection first: 0.14 s on the start-up's path): a forked worker's collections then no
    longer write to the fork server's pages, which copied them into every worker (peak memory of
    a rendered survey's run 2.58-2.82 -> 2.47-2.63 GiB in three alternated pairs of runs, the
    same time)."""
    import gc

    gc.freeze()


_freeze()
